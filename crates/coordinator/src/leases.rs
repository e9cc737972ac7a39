//! The lease table of one coordinator: which passes of which render are pending, leased to a
//! worker until some time, or merged. Time is passed in (milliseconds), so the table is a plain
//! data structure, tested without clocks or sockets.
//!
//! Rules (design invariants 3 and 5): a pass is merged at most once; a result is accepted only
//! from a lease that is still live; an expired lease's passes return to the queue, ahead of later passes.

use std::collections::{BTreeMap, BTreeSet, HashMap};

/// One job handed out: consecutive passes `first .. first + count` of tile `tile`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct JobLease {
    pub lease_id: u64,
    pub render: u64,
    pub tile: u32,
    pub first: u32,
    pub count: u32,
    pub worker: String,
    pub expires_ms: u64,
}

/// What happened to a completed job.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Completion {
    /// The result is to be merged: its passes are now done.
    Accepted(JobLease),
    /// Unknown, expired or already completed lease: the result must be ignored.
    Ignored,
}

struct RenderQueue {
    priority: i32,
    /// Pending passes as (pass, tile): the smallest is handed out first (pass-major order, so
    /// every tile gets its first pass before any gets its second and a partial image fills evenly).
    pending: BTreeSet<(u32, u32)>,
    merged: BTreeSet<(u32, u32)>,
    merged_per_tile: Vec<u32>,
    total: u64,
    /// Lease ids handed out, for round-robin fairness between equal priorities.
    served: u64,
}

#[derive(Default)]
pub struct LeaseTable {
    renders: BTreeMap<u64, RenderQueue>,
    leases: HashMap<u64, JobLease>,
    next_lease: u64,
    /// Passes handed out, passes whose lease expired and passes handed back, since start.
    pub passes_leased: u64,
    pub passes_expired: u64,
    pub passes_released: u64,
}

impl LeaseTable {
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds a render whose tile `t` gets passes `0 .. budgets[t]`; `merged` lists (tile, pass)
    /// pairs already durable (after a restart), which are not handed out again.
    pub fn add_render(&mut self, render: u64, priority: i32, budgets: &[u32], merged: &[(u32, u32)]) {
        let merged: BTreeSet<(u32, u32)> = merged.iter().copied().collect();
        let mut merged_per_tile = vec![0u32; budgets.len()];
        for &(tile, _) in &merged {
            if let Some(c) = merged_per_tile.get_mut(tile as usize) {
                *c += 1;
            }
        }
        let pending = budgets
            .iter()
            .enumerate()
            .flat_map(|(tile, &b)| (0..b).map(move |pass| (pass, tile as u32)))
            .filter(|&(pass, tile)| !merged.contains(&(tile, pass)))
            .collect();
        let total = budgets.iter().map(|&b| b as u64).sum();
        self.renders.insert(render, RenderQueue { priority, pending, merged, merged_per_tile, total, served: 0 });
    }

    /// Gives tile `tile` of a render the further passes `from .. to` (an adaptive round).
    pub fn extend_tile(&mut self, render: u64, tile: u32, from: u32, to: u32) {
        if let Some(q) = self.renders.get_mut(&render) {
            for pass in from..to {
                if !q.merged.contains(&(tile, pass)) && q.pending.insert((pass, tile)) {
                    q.total += 1;
                }
            }
        }
    }

    /// Passes of `tile` merged so far.
    pub fn tile_merged(&self, render: u64, tile: u32) -> u32 {
        self.renders.get(&render).and_then(|q| q.merged_per_tile.get(tile as usize).copied()).unwrap_or(0)
    }

    /// Drops a render (cancelled or finished) and its leases.
    pub fn remove_render(&mut self, render: u64) {
        self.renders.remove(&render);
        self.leases.retain(|_, l| l.render != render);
    }

    /// (merged, total) passes of a render.
    pub fn progress(&self, render: u64) -> Option<(u64, u64)> {
        self.renders.get(&render).map(|q| (q.merged.len() as u64, q.total))
    }

    pub fn is_complete(&self, render: u64) -> bool {
        self.progress(render).is_some_and(|(m, t)| m == t)
    }

    /// Hands the next job to `worker`: the highest priority render first, round-robin among
    /// equals; up to `max_passes` consecutive pending passes of one tile.
    pub fn lease(&mut self, worker: &str, max_passes: u32, now_ms: u64, lease_ms: u64) -> Option<JobLease> {
        self.expire(now_ms);
        let render = self
            .renders
            .iter()
            .filter(|(_, q)| !q.pending.is_empty())
            .max_by_key(|(id, q)| (q.priority, std::cmp::Reverse(q.served), std::cmp::Reverse(**id)))
            .map(|(id, _)| *id)?;
        let queue = self.renders.get_mut(&render)?;
        let (first, tile) = queue.pending.pop_first()?;
        // Extend the run with the following passes of the same tile while they are pending.
        let mut count = 1;
        while count < max_passes.max(1) && queue.pending.remove(&(first + count, tile)) {
            count += 1;
        }
        queue.served += 1;
        self.passes_leased += count as u64;
        self.next_lease += 1;
        let lease = JobLease {
            lease_id: self.next_lease,
            render,
            tile,
            first,
            count,
            worker: worker.to_string(),
            expires_ms: now_ms + lease_ms,
        };
        self.leases.insert(lease.lease_id, lease.clone());
        Some(lease)
    }

    /// Extends live leases of `worker`; returns the ids it should drop (unknown or expired).
    pub fn heartbeat(&mut self, worker: &str, lease_ids: &[u64], now_ms: u64, lease_ms: u64) -> Vec<u64> {
        self.expire(now_ms);
        let mut dropped = Vec::new();
        for id in lease_ids {
            match self.leases.get_mut(id) {
                Some(l) if l.worker == worker => l.expires_ms = now_ms + lease_ms,
                _ => dropped.push(*id),
            }
        }
        dropped
    }

    /// A worker reports a job done. Accepted at most once, and only while the lease is live.
    pub fn complete(&mut self, lease_id: u64, worker: &str, now_ms: u64) -> Completion {
        self.expire(now_ms);
        match self.leases.get(&lease_id) {
            Some(l) if l.worker == worker => {}
            _ => return Completion::Ignored,
        }
        let Some(lease) = self.leases.remove(&lease_id) else {
            return Completion::Ignored;
        };
        let Some(queue) = self.renders.get_mut(&lease.render) else {
            return Completion::Ignored;
        };
        for pass in lease.first..lease.first + lease.count {
            if queue.merged.insert((lease.tile, pass))
                && let Some(c) = queue.merged_per_tile.get_mut(lease.tile as usize)
            {
                *c += 1;
            }
        }
        Completion::Accepted(lease)
    }

    /// Returns the passes of every lease that expired by `now_ms` to their queue.
    pub fn expire(&mut self, now_ms: u64) -> Vec<JobLease> {
        let expired: Vec<u64> = self.leases.values().filter(|l| l.expires_ms <= now_ms).map(|l| l.lease_id).collect();
        let mut out: Vec<JobLease> = expired.into_iter().filter_map(|id| self.hand_back(id)).collect();
        self.passes_expired += out.iter().map(|l| l.count as u64).sum::<u64>();
        out.sort_by_key(|l| l.lease_id);
        out
    }

    /// A worker gives leases back unrendered (it is shutting down): their passes return to the
    /// queue at once instead of when the leases would expire. Leases of other workers, unknown
    /// or already gone, are left alone. Returns how many passes went back.
    pub fn release(&mut self, worker: &str, lease_ids: &[u64]) -> u64 {
        let mut passes = 0;
        for id in lease_ids {
            if self.leases.get(id).is_some_and(|l| l.worker == worker) {
                passes += self.hand_back(*id).map_or(0, |l| l.count as u64);
            }
        }
        self.passes_released += passes;
        passes
    }

    /// Removes a live lease and puts its unmerged passes back in the queue.
    fn hand_back(&mut self, lease_id: u64) -> Option<JobLease> {
        let l = self.leases.remove(&lease_id)?;
        if let Some(q) = self.renders.get_mut(&l.render) {
            for pass in l.first..l.first + l.count {
                if !q.merged.contains(&(l.tile, pass)) {
                    q.pending.insert((pass, l.tile));
                }
            }
        }
        Some(l)
    }

    pub fn live_leases(&self) -> usize {
        self.leases.len()
    }

    pub fn get(&self, lease_id: u64) -> Option<&JobLease> {
        self.leases.get(&lease_id)
    }

    pub fn leases(&self) -> impl Iterator<Item = &JobLease> {
        self.leases.values()
    }

    /// Puts an accepted job's passes back (its result could not be stored).
    pub fn requeue(&mut self, lease: &JobLease) {
        if let Some(q) = self.renders.get_mut(&lease.render) {
            for pass in lease.first..lease.first + lease.count {
                if q.merged.remove(&(lease.tile, pass))
                    && let Some(c) = q.merged_per_tile.get_mut(lease.tile as usize)
                {
                    *c -= 1;
                }
                q.pending.insert((pass, lease.tile));
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const LEASE: u64 = 10_000;

    fn drain(table: &mut LeaseTable, render: u64) -> Vec<(u32, u32)> {
        let mut done = Vec::new();
        while let Some(l) = table.lease("w", 3, 0, LEASE) {
            assert_eq!(l.render, render);
            let Completion::Accepted(l) = table.complete(l.lease_id, "w", 1) else { panic!("ignored") };
            done.extend((l.first..l.first + l.count).map(|p| (l.tile, p)));
        }
        done.sort();
        done
    }

    #[test]
    fn every_pass_is_handed_out_and_merged_once() {
        let mut t = LeaseTable::new();
        t.add_render(1, 0, &[5; 4], &[]);
        let done = drain(&mut t, 1);
        let expected: Vec<(u32, u32)> = (0..4).flat_map(|tile| (0..5).map(move |p| (tile, p))).collect();
        assert_eq!(done, expected);
        assert!(t.is_complete(1));
    }

    #[test]
    fn duplicates_and_late_results_are_ignored() {
        let mut t = LeaseTable::new();
        t.add_render(1, 0, &[2; 1], &[]);
        let a = t.lease("a", 1, 0, LEASE).unwrap();
        assert!(matches!(t.complete(a.lease_id, "a", 5), Completion::Accepted(_)));
        assert_eq!(t.complete(a.lease_id, "a", 6), Completion::Ignored, "duplicate");
        let b = t.lease("b", 1, 10, LEASE).unwrap();
        // b's lease expires; its pass goes to c; b's late result is ignored.
        let expired = t.expire(10 + LEASE);
        assert_eq!(expired.len(), 1);
        assert_eq!((t.passes_leased, t.passes_expired), (2, 1));
        let c = t.lease("c", 1, 10 + LEASE + 1, LEASE).unwrap();
        assert_eq!((c.tile, c.first), (b.tile, b.first));
        assert_eq!(t.complete(b.lease_id, "b", 10 + LEASE + 2), Completion::Ignored, "late");
        assert!(matches!(t.complete(c.lease_id, "c", 10 + LEASE + 3), Completion::Accepted(_)));
        assert!(t.is_complete(1));
        assert_eq!(t.progress(1), Some((2, 2)));
    }

    #[test]
    fn heartbeats_keep_leases_alive_and_name_dead_ones() {
        let mut t = LeaseTable::new();
        t.add_render(1, 0, &[1; 2], &[]);
        let a = t.lease("a", 1, 0, LEASE).unwrap();
        assert!(t.heartbeat("a", &[a.lease_id], LEASE - 1, LEASE).is_empty());
        assert!(t.expire(LEASE + 1).is_empty(), "the heartbeat extended the lease");
        assert_eq!(t.heartbeat("a", &[999], LEASE + 2, LEASE), vec![999]);
        assert_eq!(t.heartbeat("intruder", &[a.lease_id], LEASE + 3, LEASE), vec![a.lease_id]);
        assert_eq!(t.complete(a.lease_id, "intruder", LEASE + 4), Completion::Ignored);
    }

    #[test]
    fn released_leases_go_back_to_the_queue_at_once() {
        let mut t = LeaseTable::new();
        t.add_render(1, 0, &[2; 1], &[]);
        let a = t.lease("a", 1, 0, LEASE).unwrap();
        assert_eq!(t.release("intruder", &[a.lease_id]), 0, "only the holder may release");
        assert_eq!(t.release("a", &[a.lease_id, 999]), 1);
        assert_eq!(t.release("a", &[a.lease_id]), 0, "released once");
        let b = t.lease("b", 1, 1, LEASE).unwrap();
        assert_eq!((b.tile, b.first), (a.tile, a.first), "the released pass is first in line, long before expiry");
        assert_eq!(t.complete(a.lease_id, "a", 2), Completion::Ignored, "a released lease cannot complete");
        assert!(matches!(t.complete(b.lease_id, "b", 3), Completion::Accepted(_)));
        assert_eq!((t.passes_released, t.passes_expired), (1, 0));
    }

    #[test]
    fn restart_skips_passes_already_merged() {
        let mut t = LeaseTable::new();
        t.add_render(1, 0, &[2; 2], &[(0, 0), (1, 1)]);
        let done = drain(&mut t, 1);
        assert_eq!(done, vec![(0, 1), (1, 0)]);
    }

    #[test]
    fn higher_priority_first_then_round_robin() {
        let mut t = LeaseTable::new();
        t.add_render(1, 0, &[1; 10], &[]);
        t.add_render(2, 0, &[1; 10], &[]);
        t.add_render(3, 5, &[1; 2], &[]);
        let order: Vec<u64> = (0..6).map(|i| t.lease("w", 1, i, LEASE).unwrap().render).collect();
        assert_eq!(&order[..2], &[3, 3]);
        assert_eq!(&order[2..], &[1, 2, 1, 2]);
    }

    #[test]
    fn adaptive_rounds_extend_one_tile() {
        let mut t = LeaseTable::new();
        t.add_render(1, 0, &[1, 1], &[]);
        drain(&mut t, 1);
        assert!(t.is_complete(1));
        assert_eq!(t.tile_merged(1, 1), 1);
        t.extend_tile(1, 1, 1, 4);
        assert!(!t.is_complete(1));
        assert_eq!(drain(&mut t, 1), vec![(1, 1), (1, 2), (1, 3)]);
        assert_eq!((t.progress(1), t.tile_merged(1, 1)), (Some((5, 5)), 4));
    }

    #[test]
    fn jobs_are_runs_of_consecutive_passes_of_one_tile() {
        let mut t = LeaseTable::new();
        t.add_render(1, 0, &[10; 1], &[(0, 4)]);
        let l = t.lease("w", 8, 0, LEASE).unwrap();
        assert_eq!((l.first, l.count), (0, 4), "stops at the merged pass 4");
        let l = t.lease("w", 8, 0, LEASE).unwrap();
        assert_eq!((l.first, l.count), (5, 5));
    }
}
