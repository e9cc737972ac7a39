//! Submitting: a render or a sequence checked against the farm's limits (pixels, samples,
//! tiles, passes, film memory, renders at once) before anything is stored, then recorded and
//! queued, a sequence as one render a frame.

use super::{Core, CoreError, MAX_TILES, RUNNING, Target, film_bytes};
use crate::model::{Pose, Submission};
use crate::store::{StoredRender, Write};
use tessera_render::plan::{RenderPlan, frame_seed, frame_time};
use tessera_scene::Census;

/// Most frames x tiles one sequence may queue: the lease table keeps a few words per tile of
/// every queued frame.
pub const MAX_SEQUENCE_TILES: u64 = 1 << 22;

impl Core {
    /// Refuses a render whose plan or film would cost more than the limits allow, before
    /// anything is stored or allocated.
    fn check_cost(&self, plan: &RenderPlan, film: u64, except: Option<i64>) -> Result<(), CoreError> {
        self.check_plan(plan)?;
        self.check_film(film, except)
    }

    /// Refuses a plan of more tiles, or tiles x passes, than the limits allow.
    pub(super) fn check_plan(&self, plan: &RenderPlan) -> Result<(), CoreError> {
        let c = &self.config;
        let tiles = plan.tiles.len() as u64;
        if tiles > MAX_TILES {
            return Err(CoreError::Limit(format!("{tiles} tiles is over the limit of {MAX_TILES}: use larger tiles")));
        }
        let passes = tiles.saturating_mul(plan.passes_per_tile() as u64);
        if passes > c.max_passes {
            return Err(CoreError::Limit(format!(
                "the render would be {passes} passes ({tiles} tiles x {} passes of {} spp), over the limit of {}: use larger tiles or more samples per pass",
                plan.passes_per_tile(),
                plan.pass_spp,
                c.max_passes
            )));
        }
        Ok(())
    }

    /// Refuses a film of `film` bytes ([`film_bytes`]) that would not fit beside the films the
    /// renders (but `except`) hold, under `--max-film-bytes`.
    pub(super) fn check_film(&self, film: u64, except: Option<i64>) -> Result<(), CoreError> {
        let c = &self.config;
        let live = self.film_bytes_held(except);
        if live.saturating_add(film) > c.max_film_bytes {
            return Err(CoreError::Limit(format!(
                "the render's film needs {} MiB and live renders hold {} MiB, over the {} MiB limit (--max-film-bytes): wait for renders to finish",
                film >> 20,
                live >> 20,
                c.max_film_bytes >> 20
            )));
        }
        Ok(())
    }

    /// Bytes of film the renders (but `except`) hold or will hold: a film allocated, a running
    /// still's (allocated with its first result), or one being written. A sequence's frames
    /// take theirs when they start, which leasing allows only while they fit. Kept up to date
    /// as renders change (`counts.rs`).
    pub(super) fn film_bytes_held(&self, except: Option<i64>) -> u64 {
        let mine = except.map_or(0, |id| self.share_now(id).film_bytes);
        self.counts.film_bytes - mine
    }

    /// Checks a submission against this farm's limits (the request itself was checked at the
    /// door, `Submission::from_wire`), records it, and queues its passes: one render, or one a
    /// frame of a sequence.
    pub fn submit(&mut self, owner: &str, req: &Submission, census: &Census) -> Result<Target, CoreError> {
        let c = &self.config;
        let settings = &req.setup.settings;
        let pixels = settings.width as u64 * settings.height as u64;
        if pixels > c.max_pixels {
            return Err(CoreError::Limit(format!("{pixels} pixels is over the limit of {}", c.max_pixels)));
        }
        if settings.denoise
            && let Err(why) = &c.denoiser
        {
            return Err(CoreError::Invalid(format!("this farm cannot denoise: {why}")));
        }
        let spp = req.spp;
        if spp > c.max_spp {
            return Err(CoreError::Limit(format!("spp {spp} is over this coordinator's limit of {}", c.max_spp)));
        }
        let (triangles, cameras) = (census.drawn_triangles, census.cameras);
        if triangles > c.max_triangles {
            return Err(CoreError::Limit(format!(
                "the scene draws {triangles} triangles (every instance counted), over the limit of {} \
                 (--max-triangles)",
                c.max_triangles
            )));
        }
        if census.memory() > c.max_scene_memory {
            return Err(CoreError::Limit(format!(
                "the scene would take a worker about {} MiB to build and render ({triangles} triangles drawn, {} \
                 texture texels, {} environment map texels), over the {} MiB limit (--max-scene-memory)",
                census.memory() >> 20,
                census.texels,
                census.map_texels,
                c.max_scene_memory >> 20
            )));
        }
        if settings.camera >= cameras {
            return Err(CoreError::Invalid(format!(
                "camera {} does not exist (the scene has {cameras})",
                settings.camera
            )));
        }
        // A sequence counts once, however many frames it has.
        let active = self.targets_running();
        if active >= c.max_active_renders {
            return Err(CoreError::Limit(format!(
                "{active} renders are running, the limit is {}",
                c.max_active_renders
            )));
        }
        let plan = RenderPlan::new(settings.width, settings.height, req.tile_size, spp, req.pass_spp);
        self.check_cost(&plan, film_bytes(settings), None)?;
        let notify = if req.notify.is_empty() { c.notify.default_url.clone() } else { req.notify.clone() };
        c.notify.check_url(&notify).map_err(CoreError::Invalid)?;
        // The scene is there: the service read it to count its triangles and cameras.
        let stored = StoredRender {
            id: 0,
            scene_hash: req.scene_hash.clone(),
            scene_name: req.scene_name.clone(),
            settings: req.setup.encode(),
            spp,
            tile_size: req.tile_size,
            pass_spp: req.pass_spp,
            priority: req.priority,
            state: RUNNING.into(),
            target_error: req.adaptive.map_or(0.0, |a| a.target_error as f64),
            min_spp: req.adaptive.map_or(0, |a| a.min_spp),
            message: String::new(),
            owner: owner.to_string(),
            sequence: 0,
            submitted_at: super::unix_seconds(),
            started_at: 0.0,
            ended_at: 0.0,
            name: req.name.clone(),
            paused: req.paused,
            pool: req.placement.pool.clone(),
            requires: req.placement.requirement_texts().join(" "),
            notify,
            preview_every: req.preview.map_or(0, |p| p.every),
            preview_spp: req.preview.map_or(0, |p| p.spp),
            preview_target: req.preview.map_or(0.0, |p| p.target_error as f64),
            final_error: [0.0; 2],
        };
        let Some(frames) = &req.frames else {
            let stored = StoredRender { id: self.next_id, ..stored };
            let prepared = self.prepare(stored.clone())?;
            self.write(Write::Renders(vec![stored]));
            self.next_id += 1;
            self.install(prepared.fresh());
            let id = self.next_id - 1;
            self.note(
                id,
                format!(
                    "submitted by {}: the scene has {triangles} triangles and {cameras} cameras",
                    if owner.is_empty() { "anyone" } else { owner }
                ),
            );
            return Ok(Target::Render(id));
        };
        // A sequence: one render a frame, each at its own time with its own seed.
        let (frames, fps) = (&frames.list, frames.fps);
        let tiles = frames.0.len() as u64 * plan.tiles.len() as u64;
        if tiles > MAX_SEQUENCE_TILES {
            return Err(CoreError::Limit(format!(
                "{} frames of {} tiles is over the limit of {MAX_SEQUENCE_TILES} tiles a sequence: use larger tiles or submit fewer frames at a time",
                frames.0.len(),
                plan.tiles.len()
            )));
        }
        let queued = self.frames_running() as u64;
        if queued + frames.0.len() as u64 > c.max_queued_frames {
            return Err(CoreError::Limit(format!(
                "{} frames would pass the farm's limit of {} frames waiting or rendering at once ({queued} are now; \
                 each holds about {} KB of the coordinator's memory): submit fewer frames at a time, or raise \
                 --max-queued-frames",
                frames.0.len(),
                c.max_queued_frames,
                super::QUEUED_FRAME_BYTES / 1000
            )));
        }
        let animation = req.setup.pose.as_ref().map(|p| p.animation.clone()).unwrap_or_default();
        let sequence = self.next_id;
        let frame_renders: Vec<StoredRender> = frames
            .0
            .iter()
            .zip(sequence..)
            .map(|(&f, id)| {
                let mut setup = req.setup.clone();
                setup.settings.seed = frame_seed(settings.seed, f);
                setup.pose = Some(Pose {
                    animation: animation.clone(),
                    time: frame_time(f, fps),
                    frame: Some(f),
                    fps,
                    sequence_seed: settings.seed,
                });
                StoredRender { id, sequence, settings: setup.encode(), ..stored.clone() }
            })
            .collect();
        self.write(Write::Renders(frame_renders.clone()));
        self.next_id += frame_renders.len() as i64;
        self.sequences.insert(sequence, frame_renders.iter().map(|r| r.id).collect());
        self.count_sequence(sequence, &req.scene_name, owner, frame_renders.len() as u32);
        for r in frame_renders {
            match self.prepare(r.clone()) {
                Ok(prepared) => self.install(prepared.fresh()),
                Err(e) => self.unresumable(r, format!("could not be queued: {e}")),
            }
        }
        let who = if owner.is_empty() { "anyone" } else { owner };
        self.note_target(Target::Sequence(sequence), format!("submitted by {who}: {} frames", frames.0.len()));
        self.begin_previews(sequence);
        Ok(Target::Sequence(sequence))
    }
}
