//! Leasing: jobs handed to workers sized from their speed (a sequence's frames kept together,
//! blocked workers and frames whose film would not fit skipped), heartbeats, leases handed
//! back, and the failure policy (failed jobs and expired leases count attempts; a worker that
//! fails a render's jobs is blocked from it, a pass that fails too often fails its render).

use super::{Core, CoreError, MAX_WORKERS, WORKER_FORGET_LEASES, check_name, film_bytes};
use crate::leases::Asker;
use crate::model::{Job, Offer, RenderState};
use crate::store::Write;
use std::time::Instant;
use tessera_render::plan::job_passes;
use tessera_request::placement::{Tag, check_pool, check_tags};

pub(super) struct Worker {
    pub(super) name: String,
    pub(super) threads: u32,
    pub(super) samples_per_second: f64,
    pub(super) last_seen: Instant,
    /// The render of its last job: its scene is posed on the worker, so more of it is cheap.
    pub(super) last_render: Option<u64>,
    /// The address its calls come from, as the service saw it.
    pub(super) host: String,
    /// Results of its merged, and its jobs that failed (reported, or their lease expired).
    pub(super) results: u64,
    pub(super) failures: u64,
    /// It said goodbye: it is stopping, or has stopped.
    pub(super) stopped: bool,
    /// Its pool (empty: none) and tags, as it last said.
    pub(super) pool: String,
    pub(super) tags: Vec<Tag>,
}

impl Core {
    /// Hands a job to a worker, sized from its measured speed.
    pub fn lease(&mut self, offer: &Offer) -> Result<Option<Job>, CoreError> {
        let worker_id = offer.worker_id.as_str();
        check_name("the worker id", worker_id)?;
        check_name("the worker name", &offer.name)?;
        check_pool(&offer.pool).map_err(CoreError::Invalid)?;
        check_tags(&offer.tags).map_err(CoreError::Invalid)?;
        self.check_not_blocked(worker_id)?;
        self.forget_old_workers();
        if !self.workers.contains_key(worker_id) && self.workers.len() >= MAX_WORKERS {
            return Err(CoreError::Limit(format!(
                "{MAX_WORKERS} workers are connected, the most one coordinator serves"
            )));
        }
        Ok(self.lease_job(offer))
    }

    /// Forgets workers not seen for [`WORKER_FORGET_LEASES`] lease times (at most once a second).
    fn forget_old_workers(&mut self) {
        if self.workers_pruned.elapsed().as_secs() < 1 {
            return;
        }
        self.workers_pruned = Instant::now();
        let window = std::time::Duration::from_millis(self.config.lease_ms.saturating_mul(WORKER_FORGET_LEASES));
        self.workers.retain(|_, w| w.last_seen.elapsed() < window);
    }

    fn lease_job(&mut self, offer: &Offer) -> Option<Job> {
        let Offer { worker_id, name, threads, samples_per_second, .. } = offer;
        let (worker_id, threads, samples_per_second) = (worker_id.as_str(), *threads, *samples_per_second);
        let info = self.workers.entry(worker_id.to_string()).or_insert_with(|| Worker {
            name: name.to_string(),
            threads,
            samples_per_second: 0.0,
            last_seen: Instant::now(),
            last_render: None,
            host: String::new(),
            results: 0,
            failures: 0,
            stopped: false,
            pool: String::new(),
            tags: Vec::new(),
        });
        if info.pool != offer.pool || info.tags != offer.tags {
            (info.pool, info.tags) = (offer.pool.clone(), offer.tags.clone());
        }
        info.last_seen = Instant::now();
        info.stopped = false;
        info.threads = threads;
        if samples_per_second.is_finite() && samples_per_second > 0.0 {
            info.samples_per_second = samples_per_second;
        }
        let speed = info.samples_per_second;
        let prefer = info.last_render;
        // Size for the render that will be served; tiles differ little, the first tile will do.
        let next = self.counts.running.first().and_then(|id| self.renders.get(id))?;
        let tile_pixels = next.plan.tiles.first().map_or(1, |t| t.pixel_count() as u64);
        let passes =
            job_passes(speed, tile_pixels, next.plan.pass_spp, self.config.job_seconds, self.config.max_job_passes);
        let now = self.now_ms();
        let (failures, block_after) = (&self.worker_failures, self.config.block_after);
        let blocked = |render: u64| {
            failures.get(&(render as i64)).and_then(|m| m.get(worker_id)).is_some_and(|&n| n >= block_after)
        };
        // Frames start (and take a film) only while the films held fit --max-film-bytes.
        let (renders, held) = (&self.renders, self.counts.film_bytes);
        let fits = |render: u64| {
            renders.get(&(render as i64)).is_some_and(|r| {
                r.film.width > 0
                    || r.stored.sequence == 0
                    || held + film_bytes(&r.setup.settings) <= self.config.max_film_bytes
            })
        };
        let asker = Asker { worker: worker_id, pool: &offer.pool, tags: &offer.tags };
        let lease =
            self.leases.lease_except(asker, passes, now, self.config.lease_ms, prefer, |r| blocked(r) || !fits(r));
        self.note_expiries();
        let lease = lease?;
        if let Some(w) = self.workers.get_mut(worker_id) {
            w.last_render = Some(lease.render);
        }
        let render = lease.render as i64;
        if let Some(r) = self.renders.get_mut(&render)
            && let Some(at) = r.span.start()
        {
            r.stored.started_at = at;
            self.write(Write::Started { render, at });
            self.recount(render);
        }
        let r = self.renders.get(&render)?;
        Some(Job {
            lease_id: lease.lease_id,
            render_id: r.stored.id,
            scene_hash: r.stored.scene_hash.clone(),
            setup: r.setup.clone(),
            tile: r.plan.tiles[lease.tile as usize],
            first_pass: lease.first,
            pass_count: lease.count,
            pass_spp: r.plan.pass_spp,
            spp: r.plan.spp,
            lease_seconds: (self.config.lease_ms / 1000).max(1) as u32,
        })
    }

    pub fn heartbeat(&mut self, worker_id: &str, lease_ids: &[String]) -> Vec<String> {
        if let Some(w) = self.workers.get_mut(worker_id) {
            w.last_seen = Instant::now();
        }
        let ids: Vec<u64> = lease_ids.iter().filter_map(|s| s.parse().ok()).collect();
        let now = self.now_ms();
        let mut dropped: Vec<String> =
            self.leases.heartbeat(worker_id, &ids, now, self.config.lease_ms).iter().map(u64::to_string).collect();
        self.note_expiries();
        dropped.extend(lease_ids.iter().filter(|s| s.parse::<u64>().is_err()).cloned());
        dropped
    }

    /// A worker hands back leases it will not render: it is shutting down (its goodbye, with
    /// or without leases).
    pub fn release(&mut self, worker_id: &str, lease_ids: &[String]) -> u64 {
        if let Some(w) = self.workers.get_mut(worker_id) {
            w.stopped = true;
            w.last_seen = Instant::now();
        }
        let ids: Vec<u64> = lease_ids.iter().filter_map(|s| s.parse().ok()).collect();
        let passes = self.leases.release(worker_id, &ids);
        if passes > 0 {
            tracing::info!(worker = %worker_id, passes, "worker handed back leases");
        }
        passes
    }

    /// A worker could not render a job (its scene did not load, the render failed): the passes
    /// go back in line at once, count an attempt each, and the worker a failure of the render.
    pub fn fail(&mut self, worker_id: &str, lease_id: &str, error: &str) -> Result<(), CoreError> {
        check_name("the worker id", worker_id)?;
        let Some(lease) = lease_id.parse::<u64>().ok().and_then(|id| self.leases.fail(worker_id, id)) else {
            return Ok(()); // not a live lease of this worker: nothing to count
        };
        let error: String = error.chars().take(2000).collect::<String>().escape_debug().to_string();
        let name = match self.workers.get_mut(worker_id) {
            Some(w) => {
                w.failures += 1;
                w.name.clone()
            }
            None => worker_id.to_string(),
        };
        tracing::warn!(render = lease.render, worker = %name, "a job failed: {error}");
        let render = lease.render as i64;
        let failures = self.worker_failures.entry(render).or_default().entry(worker_id.to_string()).or_default();
        *failures += 1;
        if *failures == self.config.block_after {
            let line = format!("worker {name} failed {} of its jobs: it gets no more of them", self.config.block_after);
            tracing::warn!(render, worker = %name, "render {render}: {line}");
            self.note(render, line);
        }
        self.record_attempt(&lease, &format!("worker {name}: {error}"));
        Ok(())
    }

    /// Counts the expired leases' passes as failed attempts.
    pub(super) fn note_expiries(&mut self) {
        for lease in self.leases.take_expired() {
            let name = match self.workers.get_mut(&lease.worker) {
                Some(w) => {
                    w.failures += 1;
                    w.name.clone()
                }
                None => lease.worker.clone(),
            };
            let why = format!("the lease expired on worker {name} (it died, stalled or lost the coordinator)");
            self.record_attempt(&lease, &why);
        }
    }

    /// One more attempt of each pass of `lease`; the render fails when a pass reaches
    /// `max_attempts`, with `error` as its message.
    fn record_attempt(&mut self, lease: &crate::leases::JobLease, error: &str) {
        let render = lease.render as i64;
        let Some(r) = self.renders.get_mut(&render).filter(|r| r.state == RenderState::Running) else { return };
        let mut most = 0;
        for pass in lease.first..lease.first.saturating_add(lease.count) {
            let n = self.attempts.entry((render, lease.tile, pass)).or_default();
            *n += 1;
            most = most.max(*n);
        }
        r.message = format!("last error: {error}");
        let (tile, first, end) = (lease.tile, lease.first, lease.first + lease.count);
        self.note(render, format!("a job failed (tile {tile}, passes {first}..{end}): {error}"));
        if most >= self.config.max_attempts {
            let message = format!(
                "tile {} passes {}..{} failed {most} times; the last time, {error}",
                lease.tile,
                lease.first,
                lease.first + lease.count
            );
            self.fail_render(render, message);
        }
    }

    /// Notes where worker `worker_id`'s calls come from (shown by the dashboard).
    pub fn seen_from(&mut self, worker_id: &str, host: &str) {
        if let Some(w) = self.workers.get_mut(worker_id)
            && w.host != host
        {
            w.host = host.chars().take(100).collect();
        }
    }
}
