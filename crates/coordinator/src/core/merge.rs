//! Merging: a worker's result checked against its live lease ([`Core::accept`]), merged once the
//! engine has committed it ([`Core::merge`]; a tile's next adaptive round decided when the film
//! holds all of its current one), and a render whose last pass merged handed out as the image to
//! write ([`Finished`]).

use super::{Core, CoreError, DONE, error_estimate};
use crate::leases::{Completion, Ignored};
use crate::model::RenderState;
use crate::store::{StoredResult, Write};
use std::path::PathBuf;
use std::time::Instant;
use tessera_film::{ErrorEstimate, ExrImage, Film, error_statement, stopping_error};
use tessera_render::plan::{ERROR_SPREAD, next_round, predicted_passes};

/// What a render whose passes are all merged says while checks keep it from finishing.
const WAITING_FOR_CHECKS: &str = "every pass merged; waiting for";

/// A result accepted against its lease, to be committed (outside the state lock) and then
/// merged with [`Core::merge`].
pub struct Accepted {
    pub lease: crate::leases::JobLease,
    generation: u64,
    sums: tessera_render::TileSums,
    samples: u64,
    started: Instant,
    /// A second worker is to check it before its render may finish (`--verify`).
    sampled: bool,
    /// The digest of its sums, which checks compare ([`Accepted::wants_digest`]): taken by the
    /// engine outside the state lock (the hash of the sums encoded as the wire encodes them).
    pub digest: Option<[u8; 32]>,
}

impl Accepted {
    /// The result as the store keeps it: its sums as `encode_tile_sums` wrote them (`bytes`).
    pub fn stored(&self, bytes: Vec<u8>) -> Write {
        Write::Result {
            render: self.lease.render as i64,
            result: StoredResult { tile: self.lease.tile, first: self.lease.first, count: self.lease.count },
            sums: bytes,
            worker: self.lease.worker.clone(),
            unchecked: self.sampled,
        }
    }

    /// It answers a check: compared ([`Core::checked`]), never stored or merged.
    pub fn is_check(&self) -> bool {
        self.lease.check.is_some()
    }

    /// Whether its digest is needed: it answers a check, or is to be checked.
    pub fn wants_digest(&self) -> bool {
        self.sampled || self.is_check()
    }

    pub fn sums(&self) -> &tessera_render::TileSums {
        &self.sums
    }
}

/// A render whose last pass was merged: its film and the image's header, to be resolved and
/// written outside the state lock (by the engine), then reported with
/// [`Core::image_written`].
pub struct Finished {
    pub id: i64,
    film: Film,
    /// The render is transparent: its image has an alpha channel.
    transparent: bool,
    metadata: String,
    pub path: PathBuf,
    /// The render asked to be denoised: with what (or why it cannot be).
    denoiser: Option<Result<super::SharedDenoiser, String>>,
    /// The render states its error (`--confidence`): its estimate and bound, with its target
    /// error (0: a fixed render).
    stated: Option<(ErrorEstimate, f32)>,
}

impl Finished {
    pub(super) fn new(id: i64, film: Film, transparent: bool, metadata: String, path: PathBuf) -> Self {
        Finished { id, film, transparent, metadata, path, denoiser: None, stated: None }
    }

    /// The image: the film resolved, with its header (and the error it states, as
    /// `tessera render` states it).
    pub fn image(&self) -> ExrImage {
        let stated = self.stated.map(|(e, target)| error_statement(&e, target));
        ExrImage {
            metadata: self.metadata.clone() + &stated.unwrap_or_default(),
            ..self.film.resolve_with_alpha(self.transparent)
        }
    }

    /// The image, denoised when the render asked for it: the raw channels as [`Self::image`]'s,
    /// a `denoised` layer beside them. A denoiser that fails leaves the raw image, its header
    /// saying why (a finished render is never lost to its denoising).
    pub fn final_image(&self) -> ExrImage {
        let mut image = self.image();
        let Some(denoiser) = &self.denoiser else { return image };
        let denoised = match denoiser {
            Ok(d) => image.denoise_with(&*d.0).map_err(|e| e.to_string()),
            Err(why) => Err(why.clone()),
        };
        if let Err(why) = denoised {
            tracing::warn!(render = self.id, "render {} was not denoised: {why}", self.id);
            image.metadata += &format!("denoiser=none: {why}\n");
        }
        image
    }
}

/// A tile's predicted end judged at `passes` with relative `error`: at that error and at it
/// [`ERROR_SPREAD`] times lower and higher (the quote's range).
pub(super) fn predicted_ends(
    plan: &tessera_render::plan::RenderPlan,
    passes: u32,
    error: f64,
    target: f64,
) -> [u32; 3] {
    [1.0, 1.0 / ERROR_SPREAD, ERROR_SPREAD].map(|s| predicted_passes(plan, passes, error * s, target))
}

impl Core {
    /// Checks a result against its live lease and takes its passes (no one else gets them
    /// again); `Err(why)` when it is to be ignored, counted by reason. Nothing is stored yet.
    /// `sums` is the result decoded by the caller (the service decodes outside the lock);
    /// one that did not decode is refused if its lease is live, and ignored like any other
    /// result if it is not.
    pub fn accept(
        &mut self,
        worker_id: &str,
        lease_id: &str,
        sums: Result<tessera_render::TileSums, String>,
    ) -> Result<Result<Accepted, Ignored>, CoreError> {
        let started = Instant::now();
        let lease = match lease_id.parse::<u64>() {
            Ok(id) => self.leases.get(id).cloned().ok_or(self.leases.why_gone(id)),
            Err(_) => Err(Ignored::Unknown),
        };
        let lease = match lease {
            Ok(_) if self.blocked.contains_key(worker_id) => Err(Ignored::Blocked),
            lease => lease,
        };
        let lease = match lease {
            Ok(lease) => lease,
            Err(why) => return Ok(Err(self.ignore(why))),
        };
        let sums = sums.map_err(CoreError::Invalid)?;
        let render =
            self.renders.get(&(lease.render as i64)).ok_or_else(|| CoreError::NotFound("render gone".into()))?;
        let expected_tile = render.plan.tiles[lease.tile as usize];
        let samples = render.plan.samples(lease.first, lease.count).len() as u64;
        // Every number from the wire is checked before it is added: a forged count must not wrap.
        if sums.tile != expected_tile || sums.pixels.iter().any(|p| p.n.checked_add(p.dropped) != Some(samples)) {
            return Err(CoreError::Invalid(format!(
                "result does not match lease {lease_id}: expected {samples} samples per pixel of tile {expected_tile:?}"
            )));
        }
        // The feature layers are there exactly when the render asked for them, checked before the
        // result is stored: a film that would refuse it at merge must never see it on disk.
        let features = render.setup.settings.features;
        if sums.features.is_empty() == features {
            return Err(CoreError::Invalid(format!(
                "result does not match lease {lease_id}: {}",
                tessera_film::FilmError::FeatureLayers { expected: features }
            )));
        }
        let now = self.now_ms();
        let completion = self.leases.complete(lease.lease_id, worker_id, now);
        self.note_expiries();
        let lease = match completion {
            Completion::Accepted(lease) => lease,
            Completion::Ignored(why) => return Ok(Err(self.ignore(why))),
        };
        let sampled = lease.check.is_none() && self.sampled(lease.render as i64, lease.tile, lease.first);
        let Some(r) = self.renders.get_mut(&(lease.render as i64)) else {
            return Err(CoreError::NotFound("render gone".into()));
        };
        let generation = r.generation;
        if lease.check.is_none() {
            r.committing += 1;
            r.workers.insert(lease.worker.clone());
            self.recount(lease.render as i64);
        }
        Ok(Ok(Accepted { lease, generation, sums, samples, started, sampled, digest: None }))
    }

    /// Merges an accepted result once `committed` says it is durable (or puts its passes back
    /// in line if it is not), and decides the tile's next adaptive round when the film holds all
    /// of the current one. Returns the image to write when this was the render's last result.
    pub fn merge(&mut self, a: Accepted, committed: Result<(), String>) -> Result<Option<Finished>, CoreError> {
        let id = a.lease.render as i64;
        let Some(render) = self.renders.get_mut(&id).filter(|r| r.generation == a.generation) else {
            return Ok(None); // the render was retried meanwhile: its film was rebuilt from the store
        };
        render.committing = render.committing.saturating_sub(1);
        if let Err(e) = committed {
            self.leases.requeue(&a.lease);
            self.recount(id);
            return Err(CoreError::Invalid(format!("the result could not be stored: {e}")));
        }
        if render.state != RenderState::Running {
            return Ok(None); // cancelled or failed meanwhile: stored, and that is all
        }
        let pixels = a.sums.pixels.len() as u64;
        self.metrics.passes_merged += a.lease.count as u64;
        self.metrics.samples_merged += a.samples * pixels;
        if render.film.width == 0 {
            render.film = film_for(&render.setup.settings);
        }
        if let Err(e) = render.film.merge_tile(&a.sums) {
            self.recount(id);
            return Err(CoreError::Invalid(e.to_string()));
        }
        render.samples_done += a.samples * pixels;
        let tile = a.lease.tile as usize;
        render.film_passes[tile] += a.lease.count;
        if render.stored.target_error > 0.0 && render.film_passes[tile] == render.budget[tile] {
            let b = render.budget[tile];
            let error =
                stopping_error(render.film.tile_pixels(render.plan.tiles[tile]), render.setup.settings.confidence);
            let target = render.stored.target_error;
            render.predicted[tile] = predicted_ends(&render.plan, b, error, target);
            if let Some(next) = next_round(b, render.plan.passes_per_tile(), error, target) {
                self.leases.extend_tile(a.lease.render, a.lease.tile, b, next);
                render.budget[tile] = next;
                render.passes_total += (next - b) as u64;
            }
        }
        self.metrics.merges += 1;
        self.metrics.merge_seconds_total += a.started.elapsed().as_secs_f64();
        if let Some(w) = self.workers.get_mut(&a.lease.worker) {
            w.results += 1;
        }
        if let (true, Some(digest)) = (a.sampled, a.digest) {
            let l = a.lease;
            self.expect_check(id, l.tile, l.first, l.count, l.worker, digest);
        }
        self.preview_progress(id);
        self.finish_if_complete(id)
    }

    /// The image to write if render `id` has every pass merged and checked.
    pub(super) fn finish_if_complete(&mut self, id: i64) -> Result<Option<Finished>, CoreError> {
        let checks = self.checks_pending(id);
        let Some(r) = self.renders.get_mut(&id).filter(|r| r.state == RenderState::Running && !r.writing) else {
            return Ok(None);
        };
        if r.committing == 0 && self.leases.is_complete(id as u64) {
            if checks == 0 {
                return self.finish(id).map(Some);
            }
            let message = format!("{WAITING_FOR_CHECKS} {checks} result(s) to be checked by another worker");
            if r.message != message {
                r.message = message.clone();
                self.note(id, message);
            }
        }
        self.recount(id);
        Ok(None)
    }

    /// The image of a render whose passes are all merged; its leases are gone. The render is
    /// done once [`Core::image_written`] hears the file was written. The film goes with it: the
    /// image is resolved where it is written, outside the state lock.
    pub(super) fn finish(&mut self, id: i64) -> Result<Finished, CoreError> {
        let r = self.renders.get_mut(&id).ok_or_else(|| CoreError::NotFound(format!("render {id}")))?;
        let film = std::mem::replace(&mut r.film, Film::new(0, 0));
        self.finished(id, film)
    }

    /// Render `id`'s image to be: `film` (all its results merged) and the image's header.
    fn finished(&mut self, id: i64, film: Film) -> Result<Finished, CoreError> {
        let path = self.exr_path(id);
        let r = self.renders.get_mut(&id).ok_or_else(|| CoreError::NotFound(format!("render {id}")))?;
        let film = if film.width == 0 { film_for(&r.setup.settings) } else { film };
        let metadata = r.setup.header(&r.stored.scene_name, &r.stored.scene_hash, r.stored.spp, film.dropped());
        let confidence = r.setup.settings.confidence;
        // A stated error is the whole film's, as `tessera render` states it.
        r.final_error = if confidence > 0.0 {
            tessera_film::error_estimate(&film.pixels, confidence as f64)
        } else {
            error_estimate(&film, 0.0)
        };
        r.writing = true;
        // Kept, so that its status states it after a restart (which reads no finished film).
        let error = [r.final_error.estimate, if confidence > 0.0 { r.final_error.upper } else { 0.0 }];
        let transparent = r.setup.settings.transparent;
        let denoiser = r.setup.settings.denoise.then(|| self.config.denoiser.clone());
        let stated = (confidence > 0.0).then_some((r.final_error, r.stored.target_error as f32));
        self.write(crate::store::Write::FinalError { render: id, error });
        self.leases.remove_render(id as u64);
        self.recount(id);
        Ok(Finished { id, film, transparent, metadata, path, denoiser, stated })
    }

    /// A finished render's image was written (or not: then it is rebuilt from the stored results
    /// when asked for); the render is done.
    pub fn image_written(&mut self, id: i64, written: Result<(), String>) -> Result<(), CoreError> {
        let finished = match &written {
            Ok(()) => "finished".to_string(),
            Err(e) => format!("finished; its image could not be written (it is rebuilt when fetched): {e}"),
        };
        if let Err(e) = written {
            tracing::error!(render = id, "could not write the image of render {id} (it is rebuilt when fetched): {e}");
        }
        let Some(r) = self.renders.get_mut(&id) else { return Ok(()) };
        r.writing = false;
        if r.state != RenderState::Running {
            // Rebuilt after it was done, or reopened meanwhile (a worker's results were found
            // wrong: it is rendered again).
            self.recount(id);
            return Ok(());
        }
        r.state = RenderState::Done;
        if r.message.starts_with(WAITING_FOR_CHECKS) {
            r.message.clear();
        }
        self.note(id, finished);
        self.recount(id);
        self.tell_end(id);
        self.write(Write::State { render: id, state: DONE, message: String::new() });
        self.collect_scenes();
        Ok(())
    }

    /// Where a finished render's EXR is, and an empty film of its size and layers (to rebuild it
    /// from the stored results should the file be gone: [`Store::rebuild`], then [`Core::rebuilt`]).
    pub fn image_path(&self, id: i64) -> Result<(PathBuf, Film), CoreError> {
        if let Some(stored) = self.failed.get(&id) {
            return Err(CoreError::NotReady(format!("render {id} failed: {}", stored.message)));
        }
        let r = self.renders.get(&id).ok_or_else(|| CoreError::NotFound(format!("no render {id}")))?;
        match r.state {
            RenderState::Done => {}
            RenderState::Cancelled => {
                return Err(CoreError::NotReady(format!(
                    "render {id} was cancelled: `tessera retry {id}` resumes it, keeping what it merged"
                )));
            }
            _ => {
                return Err(CoreError::NotReady(format!(
                    "render {id} is not finished yet: `tessera watch {id}` follows it"
                )));
            }
        }
        Ok((self.exr_path(id), film_for(&r.setup.settings)))
    }

    /// What running render `id` has merged so far, as an image with its header marked partial,
    /// and the samples in it (`None` before any was merged): for a local farm interrupted
    /// before the render finished, whose only user is that process (it is resolved under the
    /// lock).
    pub fn so_far(&self, id: i64) -> Result<Option<(ExrImage, u64)>, CoreError> {
        let r = self.renders.get(&id).ok_or_else(|| CoreError::NotFound(format!("no render {id}")))?;
        if r.writing || r.film.total_samples() == 0 {
            return Ok(None);
        }
        let film = &r.film;
        let metadata = r.setup.header(&r.stored.scene_name, &r.stored.scene_hash, r.stored.spp, film.dropped())
            + &format!(
                "partial=interrupted after {} samples ({:.1} spp on average)\n",
                film.total_samples(),
                film.mean_spp()
            );
        let image = ExrImage { metadata, ..film.resolve_with_alpha(r.setup.settings.transparent) };
        Ok(Some((image, film.total_samples())))
    }

    /// The image of a finished render whose file was lost, from `film` (its stored results
    /// merged again): to be written like a render's last result's (then
    /// [`Core::image_written`]).
    pub fn rebuilt(&mut self, id: i64, film: Film) -> Result<Finished, CoreError> {
        self.image_path(id)?;
        self.finished(id, film)
    }
}

/// An empty film for a render with `settings`: its size, with the feature layers it asked for.
pub(crate) fn film_for(settings: &tessera_render::RenderSettings) -> Film {
    Film::with_features(settings.width, settings.height, settings.features)
}
