//! Verified workers (`--verify`). Every pass is a pure function of its inputs, so any two honest
//! workers return the same bits for the same job. A fraction of merged jobs, picked by a hash of
//! the job, is rendered again by a second worker and the two results' digests compared; the
//! render finishes only once every such check has come back. A disagreement goes to a third
//! worker: the one of the first two that disagrees with it is blocked for the whole farm, and
//! every render holding its results is rendered again from what the store keeps of the others
//! ([`Core::reopen`], then a retry). Three different answers fail the render: the farm's workers
//! do not agree, and no one of them can be told apart as the faulty one.

use super::{Accepted, Core, CoreError, Finished};
use crate::model::RenderState;
use crate::store::Write;

/// A merged result waiting for a second worker's.
pub(super) struct Check {
    count: u32,
    /// The worker whose result was merged, and its result's digest.
    worker: String,
    digest: [u8; 32],
    /// A second worker that disagreed, and its digest: a third decides.
    disputed: Option<(String, [u8; 32])>,
}

/// What a check's result decided.
#[derive(Default)]
pub struct Verdict {
    /// The render's image to write: this was its last check.
    pub finished: Option<Finished>,
    /// A worker found returning wrong results: blocked now, and the renders holding its
    /// results (those it returned since the coordinator started) reopened. The engine reopens
    /// those the store holds from before, has the block stored ([`Core::store_block`]), then
    /// retries them all.
    pub blocked: Option<Blocked>,
}

/// A worker blocked for the farm.
pub struct Blocked {
    pub worker: String,
    pub why: String,
    /// The renders reopened to render its results again.
    pub reopened: Vec<i64>,
}

/// How a render reopened for a blocked worker's results starts its message: the store keeps
/// it failed until its retry, and a coordinator restarted meanwhile retries it at once.
pub const REOPENED: &str = "re-rendering the results of a blocked worker";

impl Core {
    /// Whether a job's result is checked by a second worker: a `--verify` fraction of jobs,
    /// picked by a hash of the job (not by chance, so that a test can know which).
    pub(super) fn sampled(&self, render: i64, tile: u32, first: u32) -> bool {
        let fraction = self.config.verify;
        if fraction <= 0.0 {
            return false;
        }
        if fraction >= 1.0 {
            return true;
        }
        let mut h = blake3::Hasher::new();
        h.update(b"tessera check");
        h.update(&render.to_le_bytes());
        h.update(&tile.to_le_bytes());
        h.update(&first.to_le_bytes());
        let x = u64::from_le_bytes(h.finalize().as_bytes()[..8].try_into().unwrap_or_default());
        (x as f64) < fraction * 2f64.powi(64)
    }

    /// A merged result of `worker` (its sums' digest `digest`) to be checked by another worker.
    pub(super) fn expect_check(
        &mut self,
        render: i64,
        tile: u32,
        first: u32,
        count: u32,
        worker: String,
        digest: [u8; 32],
    ) {
        self.leases.add_check(render as u64, tile, first, count, vec![worker.clone()]);
        self.checks.insert((render, tile, first), Check { count, worker, digest, disputed: None });
    }

    /// The keys of render `id`'s checks not yet decided.
    pub(super) fn checks_of(&self, id: i64) -> impl Iterator<Item = &(i64, u32, u32)> {
        self.checks.range((id, 0, 0)..=(id, u32::MAX, u32::MAX)).map(|(k, _)| k)
    }

    /// Checks of render `id` not yet decided.
    pub(super) fn checks_pending(&self, id: i64) -> usize {
        self.checks_of(id).count()
    }

    /// Refuses a blocked worker, saying why.
    pub(super) fn check_not_blocked(&self, worker_id: &str) -> Result<(), CoreError> {
        match self.blocked.get(worker_id) {
            Some(why) => Err(CoreError::Refused(format!(
                "worker {} is blocked: {why}. Check the machine (memory, overclocking) and its build; a restarted \
                 worker joins under a new id",
                worker_id.escape_debug()
            ))),
            None => Ok(()),
        }
    }

    /// Workers blocked for the farm.
    pub fn blocked_workers(&self) -> usize {
        self.blocked.len()
    }

    /// A check's result, compared with the result it checks (never stored or merged).
    pub fn checked(&mut self, a: Accepted) -> Result<Verdict, CoreError> {
        let (id, tile, first) = (a.lease.render as i64, a.lease.tile, a.lease.first);
        let digest = a.digest.ok_or_else(|| CoreError::Invalid("a check's result came without its digest".into()))?;
        let checker = a.lease.worker;
        self.metrics.results_checked += 1;
        let Some(check) = self.checks.get_mut(&(id, tile, first)) else {
            return Ok(Verdict::default()); // its render was reopened or has ended meanwhile
        };
        let (count, original) = (check.count, check.worker.clone());
        let passes = format!("render {id} tile {tile} passes {first}..{}", first + count);
        let liar = match check.disputed.clone() {
            None if digest == check.digest => None,
            None => {
                check.disputed = Some((checker.clone(), digest));
                self.metrics.results_disputed += 1;
                let line = format!(
                    "workers {} and {} returned different sums for {passes}: a third worker decides",
                    self.worker_name(&original),
                    self.worker_name(&checker)
                );
                tracing::warn!(render = id, "{line}");
                self.note(id, line);
                self.leases.add_check(id as u64, tile, first, count, vec![original, checker]);
                return Ok(Verdict::default());
            }
            Some((second, _)) if digest == check.digest => Some(second),
            Some((_, second)) if digest == second => Some(original.clone()),
            Some((second, _)) => {
                self.checks.remove(&(id, tile, first));
                let message = format!(
                    "workers {}, {} and {} returned three different sums for {passes}: the farm's workers do not \
                     agree on this scene (different builds of tessera?)",
                    self.worker_name(&original),
                    self.worker_name(&second),
                    self.worker_name(&checker)
                );
                self.fail_render(id, message);
                return Ok(Verdict::default());
            }
        };
        self.checks.remove(&(id, tile, first));
        let mut verdict = Verdict::default();
        if let Some(liar) = &liar {
            let why = format!(
                "its sums for {passes} disagreed with those of two other workers ({})",
                self.worker_name(if *liar == original { &checker } else { &original })
            );
            let reopened = self.block(liar, &why);
            verdict.blocked = Some(Blocked { worker: liar.clone(), why, reopened });
        }
        if liar.as_ref() != Some(&original) {
            // The merged result stands.
            self.write(Write::Checked { render: id, tile, first });
            verdict.finished = self.finish_if_complete(id)?;
        }
        Ok(verdict)
    }

    /// Blocks `worker` for the farm: it gets no more jobs, its live leases go to others, none
    /// of its results is accepted, and every render it returned results to since the
    /// coordinator started is reopened. Returns those renders.
    fn block(&mut self, worker: &str, why: &str) -> Vec<i64> {
        let name = self.worker_name(worker);
        tracing::error!(worker = %name, "blocked worker {name} for the farm: {why}; its results will be rendered again");
        self.blocked.insert(worker.to_string(), why.to_string());
        self.leases.drop_worker(worker);
        let held: Vec<i64> =
            self.renders.iter().filter(|(_, r)| r.workers.contains(worker)).map(|(&id, _)| id).collect();
        held.into_iter().filter(|&id| self.reopen(id, worker)).collect()
    }

    /// Stores the block of a worker (its results deleted with it), once the renders holding its
    /// results are reopened.
    pub fn store_block(&mut self, worker: &str, why: &str) {
        self.write(Write::Block { worker: worker.to_string(), why: why.to_string() });
    }

    /// Takes render `id` (running or done) out of work to render again what blocked worker
    /// `worker` returned: it is failed inside the core (and the store, so that a restart retries
    /// it), saying so, until the engine's retry rebuilds its film from the store, which then no
    /// longer holds that worker's results. Its users see it running throughout, and are not told
    /// it ended. Returns whether it was reopened.
    pub fn reopen(&mut self, id: i64, worker: &str) -> bool {
        let reopened =
            self.renders.get(&id).is_some_and(|r| matches!(r.state, RenderState::Running | RenderState::Done));
        if reopened {
            // Not failed for its users: no failure noted, notified or shown (`shown_state`).
            let name = self.worker_name(worker);
            let message = format!("{REOPENED} ({name}); it is retried at once");
            tracing::warn!(render = id, "render {id}: {message}");
            self.note(id, message.clone());
            self.take_out_of_work(id, message);
        }
        reopened
    }

    /// A worker's name as the log shows it (its id if it is not known).
    fn worker_name(&self, worker: &str) -> String {
        match self.workers.get(worker) {
            Some(w) => format!("{} ({})", w.name, worker).escape_debug().to_string(),
            None => worker.escape_debug().to_string(),
        }
    }
}
