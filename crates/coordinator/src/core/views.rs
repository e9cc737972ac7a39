//! What the farm shows: a render's or a sequence's status, listings in pages, the dashboard's
//! preview, tile maps and detail, the workers, and the numbers `/metrics` reports. Read under
//! the lock, in small pieces: a preview reads only the pixels it shows.

use super::counts::Kind;
use super::{Core, CoreError, ERROR_ESTIMATE_EVERY, Metrics, Span, Target, error_estimate};
use crate::model::{RenderInfo, RenderState, Setup, WorkerState, WorkerStatus};
use crate::users::Identity;

use std::collections::{HashMap, HashSet};
use std::path::PathBuf;
use std::time::Instant;
use tessera_film::relative_error;

/// The counters and gauges `/metrics` reports (the HTTP door writes them as Prometheus text).
#[derive(Clone, Debug, Default)]
pub struct FarmMetrics {
    pub counters: Metrics,
    /// Passes leased to workers and not yet merged.
    pub passes_in_flight: u64,
    /// Merged results waiting for a second (or third) worker's (`--verify`).
    pub checks_pending: usize,
    /// Workers blocked for the farm: their results disagreed with two others'.
    pub workers_blocked: usize,
    /// Passes scheduled and not yet leased or merged, over all renders.
    pub pending_passes: u64,
    pub passes_leased: u64,
    pub passes_expired: u64,
    pub passes_released: u64,
    /// Frames of sequences not finished yet (queued or rendering).
    pub pending_frames: usize,
    /// Workers seen within two lease times.
    pub workers_alive: usize,
    pub renders_running: usize,
    pub uptime_seconds: f64,
}

/// What the dashboard shows of a render's image: a preview of its film while it has one, the
/// written EXR's path once it is finished.
pub enum PreviewOf {
    /// `version` changes whenever samples are merged.
    Film {
        preview: tessera_film::Preview,
        version: u64,
    },
    Image(PathBuf),
    /// A running render that is to be denoised: its film's preview with the feature layers at
    /// the same pixels, to be denoised outside the lock.
    Denoise {
        layers: tessera_film::PreviewLayers,
        denoiser: super::SharedDenoiser,
        version: u64,
    },
}

/// One tile as the dashboard maps it: where it is, samples per pixel merged, relative error,
/// its passes merged and planned, and the workers rendering its passes now (with the passes).
#[derive(Clone, Debug, PartialEq)]
pub struct TileView {
    pub tile: tessera_render::Tile,
    pub spp: u32,
    pub error: f32,
    pub passes: u32,
    pub budget: u32,
    pub jobs: Vec<(String, u32, u32)>,
}

/// What the dashboard's page of one render shows beside its status.
#[derive(Clone, Debug)]
pub struct RenderDetail {
    pub info: RenderInfo,
    pub width: u32,
    pub height: u32,
    /// The settings as the EXR header writes them, and the farm's own.
    pub settings: Vec<(String, String)>,
    /// Names of the workers holding its jobs now.
    pub workers: Vec<String>,
}

/// A frame of a sequence as its page lists it: its status, and the workers holding its jobs.
pub type FrameRow = (RenderInfo, Vec<String>);

impl Core {
    /// A render's status as `tessera status`, `watch` and the dashboard show it.
    pub fn status(&self, id: i64) -> Option<RenderInfo> {
        if let Some(stored) = self.failed.get(&id) {
            return Some(RenderInfo {
                render_id: id.to_string(),
                scene_name: stored.scene_name.clone(),
                state: RenderState::Failed,
                message: stored.message.clone(),
                owner: stored.owner.clone(),
                sequence_id: if stored.sequence != 0 {
                    Target::Sequence(stored.sequence).to_string()
                } else {
                    String::new()
                },
                frame: self.frame_of(id),
                ..Default::default()
            });
        }
        let r = self.renders.get(&id)?;
        let (priority, paused) = self.steering_of(r.stored.sequence, id, r.stored.priority);
        let paused = paused && r.state == RenderState::Running;
        let share = self.share_now(id);
        let (done, total) = (share.passes_done, share.passes_total);
        let secs = r.span.seconds().max(1e-3);
        let rate = r.samples_done as f64 / secs;
        // To the end its adaptive rounds are predicted to reach, not the current round's.
        let expected = r.passes_expected().max(total);
        let remaining = (expected - done.min(expected)) as f64
            * r.plan.pass_spp as f64
            * r.plan.tiles.first().map_or(0, |t| t.pixel_count()) as f64;
        let confidence = r.setup.settings.confidence;
        let error = match r.state {
            _ if r.state == RenderState::Done || r.writing => r.final_error,
            _ => match r.error_estimate.get() {
                Some((at, e)) if at.elapsed() < ERROR_ESTIMATE_EVERY => e,
                _ => {
                    let e = error_estimate(&r.film, confidence);
                    r.error_estimate.set(Some((Instant::now(), e)));
                    e
                }
            },
        };
        Some(RenderInfo {
            render_id: id.to_string(),
            scene_name: r.stored.scene_name.clone(),
            state: r.shown_state(),
            passes_done: done,
            passes_total: total,
            samples_done: r.samples_done,
            samples_per_second: rate,
            // An estimate from at most 16384 evenly spread pixels, made at most twice a second.
            error_estimate: error.estimate,
            error_bound: if confidence > 0.0 { error.upper } else { 0.0 },
            // As it was given (0.95), not as its f32 reads in an f64 (0.949999988).
            confidence: if confidence > 0.0 { confidence.to_string().parse().unwrap_or(error.confidence) } else { 0.0 },
            eta_seconds: if rate > 0.0 && !paused { remaining / rate } else { 0.0 },
            message: r.message.clone(),
            mean_spp: r.samples_done as f64 / (r.setup.settings.width as f64 * r.setup.settings.height as f64),
            owner: r.stored.owner.clone(),
            sequence_id: if r.stored.sequence != 0 {
                Target::Sequence(r.stored.sequence).to_string()
            } else {
                String::new()
            },
            frame: self.frame_of(id),
            no_workers: r.state == RenderState::Running && !paused && !self.any_worker_connected(),
            no_worker_fits: r.state == RenderState::Running && !paused && !self.any_worker_fits(&r.placement),
            placement: r.placement.describe(),
            priority,
            paused,
            submitted_at: (r.stored.submitted_at > 0.0).then_some(r.stored.submitted_at),
            name: r.stored.name.clone(),
            started_at: r.span.started_at,
            ended_at: r.span.ended_at,
            ..Default::default()
        })
    }

    /// The priority of render `id` (a frame of sequence `sequence`, or a still for 0) and
    /// whether it is paused: its group's in the lease table while it runs, `stored` otherwise.
    fn steering_of(&self, sequence: i64, id: i64, stored: i32) -> (i32, bool) {
        let group = if sequence != 0 { sequence } else { id };
        self.leases.steering(group as u64).unwrap_or((stored, false))
    }

    /// Whether no worker is connected, or one that is may take a render placed so (of its
    /// pool, with the tags it requires).
    fn any_worker_fits(&self, placement: &tessera_request::placement::Placement) -> bool {
        let alive = |w: &&super::lease::Worker| !w.stopped && self.heard_lately(w);
        let mut connected = self.workers.values().filter(alive).peekable();
        connected.peek().is_none() || connected.any(|w| placement.admits(&w.pool, &w.tags))
    }

    /// Whether any worker has asked for work (or heartbeated) within two lease times and not
    /// said goodbye.
    pub fn any_worker_connected(&self) -> bool {
        self.workers.values().any(|w| !w.stopped && self.heard_lately(w))
    }

    /// Whether `w` has been heard from within two lease times (the farm counts it alive; a
    /// worker silent longer is lost).
    pub(super) fn heard_lately(&self, w: &super::lease::Worker) -> bool {
        w.last_seen.elapsed() < std::time::Duration::from_millis(self.config.lease_ms.saturating_mul(2))
    }

    /// The status of a render or of a whole sequence: its frames counted by state, passes and
    /// samples summed, the ETA of what is left. The frames finished are told by
    /// [`Core::finished_frames`]. A sequence's costs what a still's does, however many frames it
    /// has: its sums are kept as its frames change (`counts.rs`).
    pub fn status_of(&self, target: Target) -> Option<RenderInfo> {
        let seq = match target {
            Target::Render(id) => return self.status(id),
            Target::Sequence(seq) => seq,
        };
        let t = self.counts.tallies.get(&seq)?;
        let first = self.sequences.get(&seq).and_then(|f| f.first()).and_then(|id| self.renders.get(id));
        let message = match t.failed.first() {
            Some(&id) => {
                let frame = self.frame_of(id).unwrap_or(0);
                format!("frame {frame}: {}", self.status(id).map(|s| s.message).unwrap_or_default())
            }
            None => String::new(),
        };
        // Samples a second over the whole sequence, from when it started (or resumed).
        let rate = t.samples_done as f64 / t.span.seconds().max(1e-3);
        let left = t.passes_total.saturating_sub(t.passes_done) as f64;
        let per_pass = if t.passes_done > 0 { t.samples_done as f64 / t.passes_done as f64 } else { 0.0 };
        let (done, failed) = (t.count(Kind::Done), t.count(Kind::Failed));
        let (running, queued) = (t.count(Kind::Running), t.count(Kind::Queued));
        let (priority, paused) = self.steering_of(seq, seq, first.map_or(0, |r| r.stored.priority));
        let state = if running + queued > 0 {
            RenderState::Running
        } else if failed > 0 {
            RenderState::Failed
        } else if t.count(Kind::Cancelled) > 0 {
            RenderState::Cancelled
        } else {
            RenderState::Done
        };
        Some(RenderInfo {
            render_id: target.to_string(),
            sequence_id: target.to_string(),
            scene_name: t.scene_name.clone(),
            owner: t.owner.clone(),
            state,
            message,
            passes_done: t.passes_done,
            passes_total: t.passes_total,
            samples_done: t.samples_done,
            samples_per_second: rate,
            eta_seconds: if rate > 0.0 && !paused { left * per_pass / rate } else { 0.0 },
            error_estimate: if done > 0 { t.error_sum / done as f64 } else { 0.0 },
            frames_total: t.frames,
            frames_done: done,
            frames_running: running,
            frames_queued: queued,
            frames_failed: failed,
            no_workers: state == RenderState::Running && !paused && !self.any_worker_connected(),
            no_worker_fits: state == RenderState::Running
                && !paused
                && first.is_some_and(|r| !self.any_worker_fits(&r.placement)),
            placement: first.map(|r| r.placement.describe()).unwrap_or_default(),
            priority,
            paused: paused && state == RenderState::Running,
            submitted_at: first.map(|r| r.stored.submitted_at).filter(|&at| at > 0.0),
            name: first.map(|r| r.stored.name.clone()).unwrap_or_default(),
            started_at: t.span.started_at,
            ended_at: t.span.ended_at,
            ..Default::default()
        })
    }

    /// The render of frame `frame` of sequence `seq`.
    pub fn frame_render(&self, seq: i64, frame: u32) -> Result<i64, CoreError> {
        let frames = self.sequences.get(&seq).ok_or_else(|| CoreError::NotFound(format!("no sequence s{seq}")))?;
        frames
            .iter()
            .copied()
            .find(|&id| self.frame_of(id) == Some(frame))
            .ok_or_else(|| CoreError::NotFound(format!("sequence s{seq} has no frame {frame}")))
    }

    /// The frame number of render `id`, when it is a frame of a sequence: from its pose, or for
    /// a render that failed to resume, from its stored settings.
    pub(super) fn frame_of(&self, id: i64) -> Option<u32> {
        match self.renders.get(&id) {
            Some(r) => r.setup.pose.as_ref().and_then(|p| p.frame),
            None => {
                let stored = self.failed.get(&id)?;
                Setup::decode(&stored.settings).ok()?.pose?.frame
            }
        }
    }

    /// Seconds `target` has run: from its first job to now, or to when it ended (a sequence:
    /// from its earliest frame's start to its last frame's end); 0 while it waits in the queue.
    pub fn elapsed(&self, target: Target) -> Option<f64> {
        self.span(target).map(|s| s.seconds())
    }

    /// When a running `target` started, in seconds since the Unix epoch; `None` before it
    /// starts and once it has ended.
    pub fn started_at(&self, target: Target) -> Option<f64> {
        self.span(target).and_then(|s| s.started_at())
    }

    fn span(&self, target: Target) -> Option<&Span> {
        match target {
            Target::Sequence(seq) => self.counts.tallies.get(&seq).map(|t| &t.span),
            Target::Render(id) => self.renders.get(&id).map(|r| &r.span),
        }
    }

    /// How many workers hold jobs of each row of the listings now: of each still, and of each
    /// sequence (by its number), its frames together.
    pub fn workers_by_row(&self) -> HashMap<i64, usize> {
        let mut on: HashMap<i64, HashSet<&str>> = HashMap::new();
        for l in self.leases.leases() {
            let id = l.render as i64;
            let row = self.renders.get(&id).map_or(id, |r| if r.stored.sequence != 0 { r.stored.sequence } else { id });
            on.entry(row).or_default().insert(l.worker.as_str());
        }
        on.into_iter().map(|(id, w)| (id, w.len())).collect()
    }

    /// What `/metrics` reports: the counters and gauges of the farm now.
    pub fn farm_metrics(&self) -> FarmMetrics {
        FarmMetrics {
            counters: self.metrics.clone(),
            passes_in_flight: self.leases.passes_in_flight(),
            pending_passes: self.leases.pending_passes(),
            passes_leased: self.leases.passes_leased,
            passes_expired: self.leases.passes_expired,
            passes_released: self.leases.passes_released,
            pending_frames: self.frames_running(),
            workers_alive: self.workers.values().filter(|w| self.heard_lately(w)).count(),
            renders_running: self.counts.running.len(),
            uptime_seconds: self.epoch.elapsed().as_secs_f64(),
            checks_pending: self.checks.len(),
            workers_blocked: self.blocked.len(),
        }
    }

    /// Renders with ids above `after` that `visible` lets through (by owner), in id order, at
    /// most `limit` of them; and whether more follow (then the last id listed is the next page's
    /// `after`).
    pub fn list_renders(&self, after: i64, limit: usize, visible: impl Fn(&str) -> bool) -> (Vec<RenderInfo>, bool) {
        let (mut rows, mut from) = (Vec::new(), after.saturating_add(1));
        // Rows in id order: a still, or a sequence as its first frame's row, its other frames
        // (numbered one after another) stepped over at once.
        loop {
            let running = self.renders.range(from..).next().map(|(&id, r)| (id, r.stored.sequence, &r.stored.owner));
            let failed = self.failed.range(from..).next().map(|(&id, s)| (id, s.sequence, &s.owner));
            let Some((id, seq, owner)) = running.into_iter().chain(failed).min_by_key(|&(id, ..)| id) else {
                return (rows, false);
            };
            let (row, next) = match seq {
                0 => (Some(Target::Render(id)), id),
                seq => {
                    let end = seq + self.sequences.get(&seq).map_or(0, |f| f.len() as i64) - 1;
                    // A page that begins inside a sequence listed it on the page before.
                    ((seq == id).then_some(Target::Sequence(seq)), end)
                }
            };
            from = next.max(id).saturating_add(1);
            let Some(row) = row.filter(|_| visible(owner)) else { continue };
            if rows.len() == limit {
                return (rows, true);
            }
            rows.extend(self.status_of(row));
        }
    }

    /// What the dashboard shows of render `id`'s image (see [`PreviewOf`]); the film's preview
    /// reads only the pixels it shows, so a 4K film costs the lock little.
    /// A running render submitted with `--denoise` shows its film denoised, unless `raw`.
    pub fn preview(&self, id: i64, max_side: u32, raw: bool) -> Result<PreviewOf, CoreError> {
        let r = self.renders.get(&id).ok_or_else(|| CoreError::NotFound(format!("no render {id}")))?;
        if r.state == RenderState::Done && !r.writing {
            return Ok(PreviewOf::Image(self.exr_path(id)));
        }
        if r.setup.settings.denoise
            && !raw
            && let Ok(denoiser) = &self.config.denoiser
            && let Some(layers) = tessera_film::Preview::of_film_layers(&r.film, max_side)
        {
            return Ok(PreviewOf::Denoise { layers, denoiser: denoiser.clone(), version: r.samples_done });
        }
        // A render not yet merged into (or whose film is being written) has an empty film: its
        // preview is black.
        Ok(PreviewOf::Film { preview: tessera_film::Preview::of_film(&r.film, max_side), version: r.samples_done })
    }

    /// Render `id`'s tiles with their samples per pixel and relative error; the error is
    /// recomputed only for the tiles merged into since the last call.
    pub fn tile_views(&mut self, id: i64) -> Result<Vec<TileView>, CoreError> {
        let mut jobs: HashMap<u32, Vec<(String, u32, u32)>> = HashMap::new();
        for l in self.leases.leases().filter(|l| l.render == id as u64 && l.check.is_none()) {
            let name = self.workers.get(&l.worker).map_or(l.worker.as_str(), |w| w.name.as_str());
            jobs.entry(l.tile).or_default().push((name.to_string(), l.first, l.count));
        }
        let r = self.renders.get_mut(&id).ok_or_else(|| CoreError::NotFound(format!("no render {id}")))?;
        let tiles = r.plan.tiles.len();
        if r.tile_errors.len() != tiles {
            r.tile_errors = vec![(0, 0.0); tiles];
        }
        let has_film = r.film.width > 0;
        Ok((0..tiles)
            .map(|t| {
                let (tile, passes) = (r.plan.tiles[t], r.film_passes[t]);
                if has_film && r.tile_errors[t].0 != passes {
                    r.tile_errors[t] = (passes, relative_error(r.film.tile_pixels(tile)) as f32);
                }
                TileView {
                    tile,
                    spp: r.plan.samples(0, passes).len() as u32,
                    error: r.tile_errors[t].1,
                    passes,
                    budget: r.budget[t],
                    jobs: jobs.remove(&(t as u32)).unwrap_or_default(),
                }
            })
            .collect())
    }

    /// The frames of sequence `seq` from the `from`-th, at most `limit`, each with its status
    /// and the names of the workers holding its jobs now; and how many frames it has.
    pub fn sequence_frames(&self, seq: i64, from: usize, limit: usize) -> Option<(Vec<FrameRow>, usize)> {
        let frames = self.sequences.get(&seq)?;
        let shown = &frames[from.min(frames.len())..(from.saturating_add(limit)).min(frames.len())];
        let wanted: HashSet<u64> = shown.iter().map(|&id| id as u64).collect();
        let mut on: HashMap<u64, std::collections::BTreeSet<&str>> = HashMap::new();
        for l in self.leases.leases().filter(|l| wanted.contains(&l.render)) {
            let name = self.workers.get(&l.worker).map_or(l.worker.as_str(), |w| w.name.as_str());
            on.entry(l.render).or_default().insert(name);
        }
        let rows = shown
            .iter()
            .filter_map(|&id| {
                let workers =
                    on.get(&(id as u64)).map(|w| w.iter().map(|n| n.to_string()).collect()).unwrap_or_default();
                self.status(id).map(|info| (info, workers))
            })
            .collect();
        Some((rows, frames.len()))
    }

    /// Workers' names for their ids (the id itself for a worker this coordinator no longer
    /// knows), sorted, each once.
    pub fn worker_names(&self, ids: &[String]) -> Vec<String> {
        let names: std::collections::BTreeSet<&str> =
            ids.iter().map(|id| self.workers.get(id).map_or(id.as_str(), |w| w.name.as_str())).collect();
        names.into_iter().map(str::to_string).collect()
    }

    /// What the dashboard's page of render `id` shows (see [`RenderDetail`]).
    pub fn render_detail(&self, id: i64) -> Result<RenderDetail, CoreError> {
        let info = self.status(id).ok_or_else(|| CoreError::NotFound(format!("no render {id}")))?;
        let r = self.renders.get(&id).ok_or_else(|| CoreError::NotFound(format!("no render {id}")))?;
        let s = &r.stored;
        let mut settings = vec![
            ("scene".to_string(), s.scene_name.clone()),
            ("scene hash".to_string(), s.scene_hash.clone()),
            ("size".to_string(), format!("{} x {}", r.setup.settings.width, r.setup.settings.height)),
            ("samples per pixel".to_string(), s.spp.to_string()),
            ("tile size".to_string(), s.tile_size.to_string()),
            ("samples per pass".to_string(), s.pass_spp.to_string()),
            ("priority".to_string(), s.priority.to_string()),
        ];
        if s.target_error > 0.0 {
            settings
                .push(("target error".to_string(), format!("{} (at least {} spp)", s.target_error as f32, s.min_spp)));
        }
        for word in r.setup.settings.describe().split_whitespace() {
            let (k, v) = word.split_once('=').unwrap_or((word, "on"));
            settings.push((k.to_string(), v.to_string()));
        }
        let names: std::collections::BTreeSet<String> = self
            .leases
            .leases()
            .filter(|l| l.render == id as u64)
            .map(|l| self.workers.get(&l.worker).map_or_else(|| l.worker.clone(), |w| w.name.clone()))
            .collect();
        Ok(RenderDetail {
            info,
            width: r.setup.settings.width,
            height: r.setup.settings.height,
            settings,
            workers: names.into_iter().collect(),
        })
    }

    /// Workers whose ids sort after `after`, at most `limit`, and whether more follow.
    pub fn list_workers(&self, after: &str, limit: usize) -> (Vec<WorkerStatus>, bool) {
        let mut ids: Vec<&String> = self.workers.keys().filter(|id| id.as_str() > after).collect();
        ids.sort_unstable();
        let more = ids.len() > limit;
        ids.truncate(limit);
        let wanted: std::collections::HashSet<&String> = ids.into_iter().collect();
        let mut out = self.worker_statuses(|id| wanted.contains(id));
        out.sort_by(|a, b| a.worker_id.cmp(&b.worker_id));
        (out, more)
    }

    /// [`Core::list_workers`] as `who` may see it: the renders of jobs that are not theirs to
    /// see are left out (a submitter learned other users' render ids from `tessera workers`).
    pub fn list_workers_for(&self, who: &Identity, after: &str, limit: usize) -> (Vec<WorkerStatus>, bool) {
        let (mut workers, more) = self.list_workers(after, limit);
        for w in &mut workers {
            w.renders.retain(|&id| self.owner(id).is_some_and(|owner| who.may_touch(owner)));
        }
        (workers, more)
    }

    fn worker_statuses(&self, keep: impl Fn(&String) -> bool) -> Vec<WorkerStatus> {
        let mut leases: HashMap<&str, u32> = HashMap::new();
        let mut renders: HashMap<&str, std::collections::BTreeSet<i64>> = HashMap::new();
        for l in self.leases.leases() {
            *leases.entry(l.worker.as_str()).or_default() += 1;
            renders.entry(l.worker.as_str()).or_default().insert(l.render as i64);
        }
        let block_after = self.config.block_after;
        let blocked_from = |id: &str| -> Vec<i64> {
            let mut from: Vec<i64> = self
                .worker_failures
                .iter()
                .filter(|(_, by)| by.get(id).is_some_and(|&n| n >= block_after))
                .map(|(&render, _)| render)
                .collect();
            from.sort_unstable();
            from
        };
        self.workers
            .iter()
            .filter(|(id, _)| keep(id))
            .map(|(id, w)| WorkerStatus {
                state: match leases.get(id.as_str()) {
                    _ if self.blocked.contains_key(id) => WorkerState::Blocked,
                    _ if w.stopped => WorkerState::Stopped,
                    _ if !self.heard_lately(w) => WorkerState::Lost,
                    Some(&n) if n > 0 => WorkerState::Busy,
                    _ => WorkerState::Idle,
                },
                blocked_from: blocked_from(id),
                pool: w.pool.clone(),
                tags: w.tags.clone(),
                worker_id: id.clone(),
                name: w.name.clone(),
                threads: w.threads,
                samples_per_second: w.samples_per_second,
                leases: leases.get(id.as_str()).copied().unwrap_or(0),
                seconds_since_seen: w.last_seen.elapsed().as_secs_f64(),
                host: w.host.clone(),
                results: w.results,
                failures: w.failures,
                renders: renders.get(id.as_str()).map(|r| r.iter().copied().collect()).unwrap_or_default(),
            })
            .collect()
    }
}
