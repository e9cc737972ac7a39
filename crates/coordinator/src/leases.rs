//! The lease table of one coordinator: which passes of which render are pending, leased to a
//! worker until some time, or merged. Time is passed in (milliseconds), so the table is a plain
//! data structure, tested without clocks or sockets.
//!
//! Rules (ARCHITECTURE.md invariants 4 and 7): a pass is merged at most once; a result is accepted only
//! from a lease that is still live; an expired lease's passes return to the queue, ahead of later passes.
//!
//! Besides a render's passes the table hands out checks: jobs already rendered and merged, to be
//! rendered again by a worker other than those named (`--verify`), whose result is compared,
//! never merged. A check waits for such a worker, goes out before any pass (it keeps its render
//! from finishing), and comes back in line when its lease ends unanswered.

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
    /// A check of passes merged already: the workers that may not render it (those whose
    /// results it is checking). `None` for passes to merge.
    pub check: Option<Vec<String>>,
}

/// A check waiting for a worker: passes `first .. first + count` of `tile` again, by a worker
/// not in `exclude`.
#[derive(Clone, Debug, PartialEq, Eq)]
struct CheckJob {
    render: u64,
    tile: u32,
    first: u32,
    count: u32,
    exclude: Vec<String>,
}

/// What happened to a completed job.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Completion {
    /// The result is to be merged: its passes are now done.
    Accepted(JobLease),
    /// The result must be ignored, for this reason.
    Ignored(Ignored),
}

/// Why a result was ignored: each is counted under its own name in `/metrics`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Ignored {
    /// Its lease was completed already: a retried or repeated result.
    Duplicate,
    /// Its lease expired before the result came; the passes went to another worker.
    Late,
    /// Its worker had handed the lease back (shutting down), or reported that it failed.
    Released,
    /// Its render was cancelled or has finished.
    RenderEnded,
    /// The lease is held by another worker.
    WrongWorker,
    /// No such lease was ever handed out, or it ended too long ago to remember.
    Unknown,
    /// Its worker is blocked: its results disagreed with two other workers'.
    Blocked,
}

impl Ignored {
    pub const ALL: [Ignored; 7] = [
        Ignored::Duplicate,
        Ignored::Late,
        Ignored::Released,
        Ignored::RenderEnded,
        Ignored::WrongWorker,
        Ignored::Unknown,
        Ignored::Blocked,
    ];

    /// The `reason` label of `tessera_results_ignored_total`.
    pub fn label(self) -> &'static str {
        match self {
            Ignored::Duplicate => "duplicate",
            Ignored::Late => "late",
            Ignored::Released => "released",
            Ignored::RenderEnded => "render_ended",
            Ignored::WrongWorker => "wrong_worker",
            Ignored::Unknown => "unknown_lease",
            Ignored::Blocked => "blocked_worker",
        }
    }
}

/// How many ended leases are remembered, to say why a result for one is ignored.
const ENDED_REMEMBERED: usize = 1 << 16;

/// One tile's passes: `0 .. budget` are scheduled; `next ..` were never handed out.
#[derive(Clone, Copy, Debug, Default)]
struct TileQueue {
    budget: u32,
    next: u32,
}

/// A render's queue, lazy: nothing is stored per pass. A tile with never-leased passes has one
/// entry `(next, tile)` in `frontier`; passes that came back (expired or released leases, gaps
/// left by a restart) sit in `returned`. Pending passes are their union, handed out smallest
/// `(pass, tile)` first (pass-major, so every tile gets its first pass before any gets its
/// second and a partial image fills evenly). Memory is O(tiles + passes in flight), whatever
/// the budget.
struct RenderQueue {
    tiles: Vec<TileQueue>,
    frontier: BTreeSet<(u32, u32)>,
    returned: BTreeSet<(u32, u32)>,
    merged: u64,
    total: u64,
    group: u64,
}

/// Renders scheduled together: a still render alone, or the frames of a sequence. The highest
/// priority goes first, and among equal priorities the oldest (first submitted): a render
/// submitted later waits its turn instead of taking every worker from the one before. Within a
/// group the earliest frame with pending passes goes first (so that frames finish in order
/// while idle workers start the next), unless the asking worker's last frame still has some (it
/// holds that frame's scene posed). A paused group gets no new jobs, passes or checks.
struct Group {
    priority: i32,
    paused: bool,
    members: BTreeSet<u64>,
}

impl RenderQueue {
    fn has_pending(&self) -> bool {
        !self.frontier.is_empty() || !self.returned.is_empty()
    }

    /// The smallest pending (pass, tile).
    fn first_pending(&self) -> Option<(u32, u32)> {
        match (self.frontier.first(), self.returned.first()) {
            (Some(&f), Some(&r)) => Some(f.min(r)),
            (f, r) => f.or(r).copied(),
        }
    }

    /// Takes pass `pass` of `tile` out of the pending set, if it is pending.
    fn take(&mut self, pass: u32, tile: u32) -> bool {
        if self.returned.remove(&(pass, tile)) {
            return true;
        }
        let Some(t) = self.tiles.get_mut(tile as usize) else { return false };
        if pass != t.next || t.next >= t.budget {
            return false;
        }
        self.frontier.remove(&(t.next, tile));
        t.next += 1;
        if t.next < t.budget {
            self.frontier.insert((t.next, tile));
        }
        true
    }

    /// Puts passes `first .. first + count` of `tile` back in line.
    fn give_back(&mut self, tile: u32, first: u32, count: u32) {
        for pass in first..first.saturating_add(count) {
            self.returned.insert((pass, tile));
        }
    }
}

#[derive(Default)]
pub struct LeaseTable {
    renders: BTreeMap<u64, RenderQueue>,
    groups: BTreeMap<u64, Group>,
    leases: HashMap<u64, JobLease>,
    /// Checks waiting for a worker, oldest first.
    checks: std::collections::VecDeque<CheckJob>,
    /// Recently ended leases and how they ended, oldest evicted first.
    ended: BTreeMap<u64, Ignored>,
    /// Leases that expired since the owner last asked ([`LeaseTable::take_expired`]).
    expired: Vec<JobLease>,
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
        self.add_to_group(render, render, priority, budgets, merged);
    }

    /// As [`LeaseTable::add_render`], scheduling the render with the others of `group` (the
    /// frames of a sequence).
    pub fn add_to_group(&mut self, render: u64, group: u64, priority: i32, budgets: &[u32], merged: &[(u32, u32)]) {
        let mut done: Vec<BTreeSet<u32>> = vec![BTreeSet::new(); budgets.len()];
        for &(tile, pass) in merged {
            if let Some(set) = done.get_mut(tile as usize).filter(|_| pass < budgets[tile as usize]) {
                set.insert(pass);
            }
        }
        let mut queue = RenderQueue {
            tiles: Vec::with_capacity(budgets.len()),
            frontier: BTreeSet::new(),
            returned: BTreeSet::new(),
            merged: 0,
            total: budgets.iter().map(|&b| b as u64).sum(),
            group,
        };
        for (index, (&budget, done)) in budgets.iter().zip(&done).enumerate() {
            let tile = index as u32;
            // Passes past the last merged one were never handed out (as far as anything durable
            // says); merged ones below it left gaps, which go back in line.
            let next = done.last().map_or(0, |&p| p + 1);
            for pass in (0..next).filter(|p| !done.contains(p)) {
                queue.returned.insert((pass, tile));
            }
            if next < budget {
                queue.frontier.insert((next, tile));
            }
            queue.tiles.push(TileQueue { budget, next });
            queue.merged += done.len() as u64;
        }
        self.renders.insert(render, queue);
        let entry = self.groups.entry(group).or_insert(Group { priority, paused: false, members: BTreeSet::new() });
        entry.members.insert(render);
    }

    /// Sets group `group`'s priority and whether it is paused (`None`: as it was); both take
    /// effect at the next lease. `false` if no render of the group is in the table.
    pub fn steer(&mut self, group: u64, priority: Option<i32>, paused: Option<bool>) -> bool {
        let Some(g) = self.groups.get_mut(&group) else { return false };
        g.priority = priority.unwrap_or(g.priority);
        g.paused = paused.unwrap_or(g.paused);
        true
    }

    /// Group `group`'s priority and whether it is paused, while it has renders in the table.
    pub fn steering(&self, group: u64) -> Option<(i32, bool)> {
        self.groups.get(&group).map(|g| (g.priority, g.paused))
    }

    /// Whether render `render`'s group is paused.
    fn paused(&self, render: u64) -> bool {
        self.renders.get(&render).and_then(|q| self.groups.get(&q.group)).is_some_and(|g| g.paused)
    }

    /// Hands back every live lease of group `group`'s renders at once (a pause `--now`): their
    /// passes and checks go back in line and a result for one is ignored as released.
    /// Returns the leases ended.
    pub fn release_group(&mut self, group: u64) -> Vec<JobLease> {
        let Some(g) = self.groups.get(&group) else { return Vec::new() };
        let ids: Vec<u64> =
            self.leases.values().filter(|l| g.members.contains(&l.render)).map(|l| l.lease_id).collect();
        let ended: Vec<JobLease> = ids.into_iter().filter_map(|id| self.hand_back(id, Ignored::Released)).collect();
        self.passes_released += ended.iter().filter(|l| l.check.is_none()).map(|l| l.count as u64).sum::<u64>();
        ended
    }

    /// Gives tile `tile` of a render the further passes `from .. to` (an adaptive round).
    pub fn extend_tile(&mut self, render: u64, tile: u32, from: u32, to: u32) {
        let Some(q) = self.renders.get_mut(&render) else { return };
        let Some(t) = q.tiles.get_mut(tile as usize) else { return };
        debug_assert_eq!(from, t.budget, "rounds extend a tile from the end of its budget");
        if to <= t.budget {
            return;
        }
        q.total += (to - t.budget) as u64;
        let had_frontier = t.next < t.budget;
        t.budget = to;
        if !had_frontier {
            q.frontier.insert((t.next, tile));
        }
    }

    /// Drops a render (cancelled or finished) and its leases.
    pub fn remove_render(&mut self, render: u64) {
        if let Some(q) = self.renders.remove(&render)
            && let Some(g) = self.groups.get_mut(&q.group)
        {
            g.members.remove(&render);
            if g.members.is_empty() {
                self.groups.remove(&q.group);
            }
        }
        self.checks.retain(|c| c.render != render);
        let gone: Vec<u64> = self.leases.values().filter(|l| l.render == render).map(|l| l.lease_id).collect();
        for id in gone {
            self.leases.remove(&id);
            self.remember(id, Ignored::RenderEnded);
        }
    }

    /// Queues a check: passes `first .. first + count` of `tile` of `render` (merged already) to
    /// be rendered again by a worker not in `exclude`.
    pub fn add_check(&mut self, render: u64, tile: u32, first: u32, count: u32, exclude: Vec<String>) {
        if self.renders.contains_key(&render) {
            self.checks.push_back(CheckJob { render, tile, first, count, exclude });
        }
    }

    /// Checks waiting for a worker.
    pub fn pending_checks(&self) -> usize {
        self.checks.len()
    }

    /// Ends every live lease of `worker` (it is blocked): their passes and checks go back in
    /// line, and a result for one is ignored as [`Ignored::Blocked`].
    pub fn drop_worker(&mut self, worker: &str) -> u64 {
        let ids: Vec<u64> = self.leases.values().filter(|l| l.worker == worker).map(|l| l.lease_id).collect();
        ids.into_iter().filter_map(|id| self.hand_back(id, Ignored::Blocked)).map(|l| l.count as u64).sum()
    }

    /// (merged, total) passes of a render.
    pub fn progress(&self, render: u64) -> Option<(u64, u64)> {
        self.renders.get(&render).map(|q| (q.merged, q.total))
    }

    pub fn is_complete(&self, render: u64) -> bool {
        self.progress(render).is_some_and(|(m, t)| m == t)
    }

    /// Passes leased to workers and not yet accepted back (checks not counted).
    pub fn passes_in_flight(&self) -> u64 {
        self.leases.values().filter(|l| l.check.is_none()).map(|l| l.count as u64).sum()
    }

    /// Pending passes of every render: scheduled, neither leased nor merged.
    pub fn pending_passes(&self) -> u64 {
        let open: u64 = self.renders.values().map(|q| q.total - q.merged).sum();
        open.saturating_sub(self.passes_in_flight())
    }

    /// Hands the next job to `worker`: the highest priority render first, the oldest among
    /// equals ([`Group`]); up to `max_passes` consecutive pending passes of one tile.
    pub fn lease(&mut self, worker: &str, max_passes: u32, now_ms: u64, lease_ms: u64) -> Option<JobLease> {
        self.lease_except(worker, max_passes, now_ms, lease_ms, None, |_| false)
    }

    /// As [`LeaseTable::lease`], skipping the renders `skip` names (those a worker is blocked
    /// from, frames that may not start yet), and preferring `prefer` (the worker's last render)
    /// within its group.
    pub fn lease_except(
        &mut self,
        worker: &str,
        max_passes: u32,
        now_ms: u64,
        lease_ms: u64,
        prefer: Option<u64>,
        skip: impl Fn(u64) -> bool,
    ) -> Option<JobLease> {
        self.expire(now_ms);
        let usable = |c: &CheckJob| !c.exclude.iter().any(|w| w == worker) && !skip(c.render) && !self.paused(c.render);
        if let Some(at) = self.checks.iter().position(usable) {
            let c = self.checks.remove(at)?;
            return Some(self.hand_out(worker, c.render, c.tile, c.first, c.count, now_ms, lease_ms, Some(c.exclude)));
        }
        let renders = &self.renders;
        let ready = |id: &u64| renders.get(id).is_some_and(|q| q.has_pending()) && !skip(*id);
        let render = self
            .groups
            .iter()
            .filter(|(_, g)| !g.paused)
            .filter_map(|(&gid, g)| {
                let preferred = prefer.filter(|p| g.members.contains(p) && ready(p));
                let render = preferred.or_else(|| g.members.iter().copied().find(|id| ready(id)))?;
                Some(((g.priority, std::cmp::Reverse(gid)), render))
            })
            .max_by_key(|(key, _)| *key)
            .map(|(_, render)| render)?;
        let queue = self.renders.get_mut(&render)?;
        let (first, tile) = queue.first_pending()?;
        queue.take(first, tile);
        // Extend the run with the following passes of the same tile while they are pending; a
        // tile's first pass goes alone, so that every tile has one before any has more and the
        // image fills in as a whole (the order of leases changes no bit of the merge).
        let longest = if first == 0 { 1 } else { max_passes.max(1) };
        let mut count = 1;
        while count < longest && first.checked_add(count).is_some_and(|p| queue.take(p, tile)) {
            count += 1;
        }
        Some(self.hand_out(worker, render, tile, first, count, now_ms, lease_ms, None))
    }

    /// Makes a live lease of passes `first .. first + count` of `tile` for `worker`.
    #[allow(clippy::too_many_arguments)]
    fn hand_out(
        &mut self,
        worker: &str,
        render: u64,
        tile: u32,
        first: u32,
        count: u32,
        now_ms: u64,
        lease_ms: u64,
        check: Option<Vec<String>>,
    ) -> JobLease {
        self.passes_leased += count as u64;
        self.next_lease += 1;
        let lease = JobLease {
            lease_id: self.next_lease,
            render,
            tile,
            first,
            count,
            worker: worker.to_string(),
            expires_ms: now_ms.saturating_add(lease_ms),
            check,
        };
        self.leases.insert(lease.lease_id, lease.clone());
        lease
    }

    /// Extends live leases of `worker`; returns the ids it should drop (unknown or expired).
    pub fn heartbeat(&mut self, worker: &str, lease_ids: &[u64], now_ms: u64, lease_ms: u64) -> Vec<u64> {
        self.expire(now_ms);
        let mut dropped = Vec::new();
        for id in lease_ids {
            match self.leases.get_mut(id) {
                Some(l) if l.worker == worker => l.expires_ms = now_ms.saturating_add(lease_ms),
                _ => dropped.push(*id),
            }
        }
        dropped
    }

    /// Why a result for a lease that is not live must be ignored.
    pub fn why_gone(&self, lease_id: u64) -> Ignored {
        self.ended.get(&lease_id).copied().unwrap_or(Ignored::Unknown)
    }

    /// A worker reports a job done. Accepted at most once, and only while the lease is live.
    pub fn complete(&mut self, lease_id: u64, worker: &str, now_ms: u64) -> Completion {
        self.expire(now_ms);
        match self.leases.get(&lease_id) {
            Some(l) if l.worker == worker => {}
            Some(_) => return Completion::Ignored(Ignored::WrongWorker),
            None => return Completion::Ignored(self.why_gone(lease_id)),
        }
        let Some(lease) = self.leases.remove(&lease_id) else {
            return Completion::Ignored(Ignored::Unknown);
        };
        self.remember(lease_id, Ignored::Duplicate);
        let Some(queue) = self.renders.get_mut(&lease.render) else {
            return Completion::Ignored(Ignored::RenderEnded);
        };
        if lease.check.is_none() {
            queue.merged += lease.count as u64;
        }
        Completion::Accepted(lease)
    }

    /// Returns the passes of every lease that expired by `now_ms` to their queue.
    pub fn expire(&mut self, now_ms: u64) -> Vec<JobLease> {
        let expired: Vec<u64> = self.leases.values().filter(|l| l.expires_ms <= now_ms).map(|l| l.lease_id).collect();
        let mut out: Vec<JobLease> = expired.into_iter().filter_map(|id| self.hand_back(id, Ignored::Late)).collect();
        self.passes_expired += out.iter().map(|l| l.count as u64).sum::<u64>();
        out.sort_by_key(|l| l.lease_id);
        self.expired.extend(out.iter().cloned());
        out
    }

    /// The leases that expired since the last call, oldest first.
    pub fn take_expired(&mut self) -> Vec<JobLease> {
        std::mem::take(&mut self.expired)
    }

    /// A worker reports that it could not render a lease: its passes go back in line at once.
    /// `None` when the lease is not the worker's live lease.
    pub fn fail(&mut self, worker: &str, lease_id: u64) -> Option<JobLease> {
        self.hand_back_own(worker, lease_id)
    }

    /// A worker gives leases back unrendered (it is shutting down): their passes return to the
    /// queue at once instead of when the leases would expire. Leases of other workers, unknown
    /// or already gone, are left alone. Returns how many passes went back.
    pub fn release(&mut self, worker: &str, lease_ids: &[u64]) -> u64 {
        let passes: u64 =
            lease_ids.iter().filter_map(|&id| self.hand_back_own(worker, id)).map(|l| l.count as u64).sum();
        self.passes_released += passes;
        passes
    }

    /// [`LeaseTable::hand_back`] of a live lease `worker` holds (its own release or failure);
    /// `None` for another worker's, an unknown or an ended lease.
    fn hand_back_own(&mut self, worker: &str, lease_id: u64) -> Option<JobLease> {
        if self.leases.get(&lease_id).is_some_and(|l| l.worker == worker) {
            self.hand_back(lease_id, Ignored::Released)
        } else {
            None
        }
    }

    /// Removes a live lease and puts its passes back in the queue.
    fn hand_back(&mut self, lease_id: u64, why: Ignored) -> Option<JobLease> {
        let l = self.leases.remove(&lease_id)?;
        self.remember(lease_id, why);
        match (&l.check, self.renders.get_mut(&l.render)) {
            (_, None) => {}
            (Some(exclude), Some(_)) => self.checks.push_front(CheckJob {
                render: l.render,
                tile: l.tile,
                first: l.first,
                count: l.count,
                exclude: exclude.clone(),
            }),
            (None, Some(q)) => q.give_back(l.tile, l.first, l.count),
        }
        Some(l)
    }

    fn remember(&mut self, lease_id: u64, why: Ignored) {
        self.ended.insert(lease_id, why);
        while self.ended.len() > ENDED_REMEMBERED {
            self.ended.pop_first();
        }
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
            q.merged = q.merged.saturating_sub(lease.count as u64);
            q.give_back(lease.tile, lease.first, lease.count);
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
        assert_eq!(t.complete(a.lease_id, "a", 6), Completion::Ignored(Ignored::Duplicate), "duplicate");
        let b = t.lease("b", 1, 10, LEASE).unwrap();
        // b's lease expires; its pass goes to c; b's late result is ignored.
        let expired = t.expire(10 + LEASE);
        assert_eq!(expired.len(), 1);
        assert_eq!((t.passes_leased, t.passes_expired), (2, 1));
        let c = t.lease("c", 1, 10 + LEASE + 1, LEASE).unwrap();
        assert_eq!((c.tile, c.first), (b.tile, b.first));
        assert_eq!(t.complete(b.lease_id, "b", 10 + LEASE + 2), Completion::Ignored(Ignored::Late), "late");
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
        assert_eq!(t.complete(a.lease_id, "intruder", LEASE + 4), Completion::Ignored(Ignored::WrongWorker));
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
        assert_eq!(
            t.complete(a.lease_id, "a", 2),
            Completion::Ignored(Ignored::Released),
            "a released lease cannot complete"
        );
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
    fn higher_priority_first_then_oldest_first() {
        let mut t = LeaseTable::new();
        t.add_render(1, 0, &[1; 3], &[]);
        t.add_render(2, 0, &[1; 3], &[]);
        t.add_render(3, 5, &[1; 2], &[]);
        let order: Vec<u64> = (0..8).map(|i| t.lease("w", 1, i, LEASE).unwrap().render).collect();
        assert_eq!(order, [3, 3, 1, 1, 1, 2, 2, 2], "a later render waits for the one before it");
    }

    #[test]
    fn adaptive_rounds_extend_one_tile() {
        let mut t = LeaseTable::new();
        t.add_render(1, 0, &[1, 1], &[]);
        drain(&mut t, 1);
        assert!(t.is_complete(1));
        assert_eq!(t.progress(1), Some((2, 2)));
        t.extend_tile(1, 1, 1, 4);
        assert!(!t.is_complete(1));
        assert_eq!(drain(&mut t, 1), vec![(1, 1), (1, 2), (1, 3)]);
        assert_eq!(t.progress(1), Some((5, 5)));
    }

    #[test]
    fn jobs_are_runs_of_consecutive_passes_of_one_tile() {
        let mut t = LeaseTable::new();
        t.add_render(1, 0, &[10; 1], &[(0, 4)]);
        let l = t.lease("w", 8, 0, LEASE).unwrap();
        assert_eq!((l.first, l.count), (0, 1), "a tile's first pass goes alone");
        let l = t.lease("w", 8, 0, LEASE).unwrap();
        assert_eq!((l.first, l.count), (1, 3), "stops at the merged pass 4");
        let l = t.lease("w", 8, 0, LEASE).unwrap();
        assert_eq!((l.first, l.count), (5, 5));
    }

    #[test]
    fn a_huge_budget_costs_nothing_until_leased() {
        // 65,536 tiles x 2^20 passes (2^36 passes) once built one entry per pass and froze the
        // coordinator; the lazy queue holds one entry per tile.
        let mut t = LeaseTable::new();
        t.add_render(1, 0, &vec![1 << 20; 1 << 16], &[]);
        assert_eq!(t.progress(1), Some((0, 1 << 36)));
        let a = t.lease("w", 4, 0, LEASE).unwrap();
        let b = t.lease("w", 4, 0, LEASE).unwrap();
        assert_eq!((a.tile, a.first, a.count), (0, 0, 1));
        assert_eq!((b.tile, b.first, b.count), (1, 0, 1), "pass-major: every tile's first pass comes first");
        assert_eq!(t.pending_passes(), (1 << 36) - 2);
    }

    #[test]
    fn every_tile_gets_its_first_pass_before_any_gets_a_second() {
        // Long jobs (64 passes) once gave tile 0 its whole budget before tile 1 had anything:
        // the preview filled as a strip from the top.
        let mut t = LeaseTable::new();
        t.add_render(1, 0, &[100; 6], &[]);
        let first: Vec<(u32, u32, u32)> =
            (0..6).map(|_| t.lease("w", 64, 0, LEASE).unwrap()).map(|l| (l.tile, l.first, l.count)).collect();
        assert_eq!(first, (0..6).map(|tile| (tile, 0, 1)).collect::<Vec<_>>());
        let next = t.lease("w", 64, 0, LEASE).unwrap();
        assert_eq!((next.tile, next.first, next.count), (0, 1, 64), "then long jobs");
    }

    #[test]
    fn every_ignored_result_says_why() {
        let mut t = LeaseTable::new();
        t.add_render(1, 0, &[4; 2], &[]);
        let done = t.lease("a", 1, 0, LEASE).unwrap();
        assert!(matches!(t.complete(done.lease_id, "a", 1), Completion::Accepted(_)));
        let expired = t.lease("a", 1, 0, LEASE).unwrap();
        let released = t.lease("a", 1, 0, LEASE).unwrap();
        t.release("a", &[released.lease_id]);
        t.add_render(2, 1, &[4; 1], &[]);
        let other = t.lease("a", 1, 0, LEASE).unwrap();
        assert_eq!(other.render, 2, "the higher priority");
        t.remove_render(2);
        let held = t.lease("a", 1, LEASE + 1, LEASE).unwrap();
        let why = |t: &mut LeaseTable, id: u64, worker: &str| match t.complete(id, worker, LEASE + 2) {
            Completion::Ignored(why) => why,
            Completion::Accepted(l) => panic!("accepted {l:?}"),
        };
        assert_eq!(why(&mut t, done.lease_id, "a"), Ignored::Duplicate);
        assert_eq!(why(&mut t, expired.lease_id, "a"), Ignored::Late);
        assert_eq!(why(&mut t, released.lease_id, "a"), Ignored::Released);
        assert_eq!(why(&mut t, other.lease_id, "a"), Ignored::RenderEnded);
        assert_eq!(why(&mut t, held.lease_id, "b"), Ignored::WrongWorker);
        assert_eq!(why(&mut t, 10_000, "a"), Ignored::Unknown);
    }

    #[test]
    fn checks_go_first_to_other_workers_and_come_back_when_their_lease_ends() {
        let mut t = LeaseTable::new();
        t.add_render(1, 0, &[2; 1], &[]);
        let a = t.lease("a", 1, 0, LEASE).unwrap();
        assert!(matches!(t.complete(a.lease_id, "a", 1), Completion::Accepted(_)));
        t.add_check(1, a.tile, a.first, a.count, vec!["a".into()]);
        let own = t.lease("a", 1, 2, LEASE).unwrap();
        assert_eq!((own.check.clone(), own.first), (None, 1), "a checks none of its own results");
        let b = t.lease("b", 1, 3, LEASE).unwrap();
        assert_eq!((b.check.clone(), b.first), (Some(vec!["a".to_string()]), 0), "a check goes before any pass");
        assert_eq!(t.passes_in_flight(), 1, "a check is not a pass to merge");
        t.expire(3 + LEASE);
        let c = t.lease("c", 1, 4 + LEASE, LEASE).unwrap();
        assert_eq!((c.check.is_some(), c.first), (true, 0), "an expired check comes back first");
        assert!(matches!(t.complete(c.lease_id, "c", 5 + LEASE), Completion::Accepted(_)));
        assert_eq!(t.progress(1), Some((1, 2)), "a check's result merges no pass");
        assert_eq!(t.pending_checks(), 0);
        t.add_check(1, 0, 0, 1, vec!["a".into()]);
        t.remove_render(1);
        assert_eq!(t.pending_checks(), 0, "a render's checks go with it");
    }

    #[test]
    fn a_blocked_workers_leases_go_back_in_line() {
        let mut t = LeaseTable::new();
        t.add_render(1, 0, &[2; 1], &[]);
        let l = t.lease("liar", 1, 0, LEASE).unwrap();
        assert_eq!(t.drop_worker("liar"), 1);
        assert_eq!(t.complete(l.lease_id, "liar", 1), Completion::Ignored(Ignored::Blocked));
        let again = t.lease("b", 1, 2, LEASE).unwrap();
        assert_eq!((again.tile, again.first), (l.tile, l.first));
    }

    #[test]
    fn gaps_left_by_a_restart_are_handed_out_first() {
        let mut t = LeaseTable::new();
        // Passes 0-3 and 8-9 were merged; 4-7 were in flight when the coordinator died.
        let merged: Vec<(u32, u32)> = [0, 1, 2, 3, 8, 9].iter().map(|&p| (0, p)).collect();
        t.add_render(1, 0, &[12], &merged);
        assert_eq!(t.progress(1), Some((6, 12)));
        let l = t.lease("w", 8, 0, LEASE).unwrap();
        assert_eq!((l.first, l.count), (4, 4));
        let l = t.lease("w", 8, 0, LEASE).unwrap();
        assert_eq!((l.first, l.count), (10, 2));
    }

    #[test]
    fn a_paused_group_gets_no_jobs_until_resumed_and_priority_changes_the_order() {
        let mut t = LeaseTable::new();
        t.add_render(1, 0, &[4], &[]);
        t.add_to_group(2, 2, 0, &[4], &[]);
        t.add_to_group(3, 2, 0, &[4], &[]);
        assert!(t.steer(2, None, Some(true)));
        assert!(!t.steer(9, None, Some(true)), "no such group");
        assert_eq!(t.steering(2), Some((0, true)));
        for _ in 0..4 {
            assert_eq!(t.lease("w", 1, 0, LEASE).unwrap().render, 1, "only the render not paused");
        }
        assert_eq!(t.lease("w", 1, 0, LEASE), None, "the paused sequence waits");
        // A check of a paused render waits too.
        t.add_check(2, 0, 0, 1, vec!["x".into()]);
        assert_eq!(t.lease("w", 1, 0, LEASE), None);
        t.steer(2, Some(5), Some(false));
        let l = t.lease("w", 1, 0, LEASE).unwrap();
        assert!(l.check.is_some() && l.render == 2, "the check goes first once resumed");
        t.add_render(4, 0, &[4], &[]);
        assert_eq!(t.lease("w", 1, 0, LEASE).unwrap().render, 2, "priority 5 before 0");
        t.steer(2, Some(-1), None);
        assert_eq!(t.lease("w", 1, 0, LEASE).unwrap().render, 4, "lowered below the newer render");
    }

    #[test]
    fn a_pause_now_hands_back_the_groups_leases() {
        let mut t = LeaseTable::new();
        t.add_render(1, 0, &[4], &[]);
        t.add_render(2, 0, &[4], &[]);
        let a = t.lease("w", 2, 0, LEASE).unwrap();
        let b = t.lease("w", 2, 0, LEASE).unwrap();
        let c = t.lease("v", 2, 0, LEASE).unwrap();
        assert_eq!((a.render, b.render, c.render), (1, 1, 1));
        let other = t.lease("v", 2, 0, LEASE).unwrap();
        assert_eq!(other.render, 2);
        t.steer(1, None, Some(true));
        let ended = t.release_group(1);
        assert_eq!(ended.len(), 3, "render 1's leases, not render 2's");
        assert_eq!(t.passes_released, 4);
        assert!(t.get(other.lease_id).is_some());
        assert_eq!(t.complete(a.lease_id, "w", 1), Completion::Ignored(Ignored::Released));
        assert_eq!(t.lease("w", 2, 0, LEASE).unwrap().render, 2);
        t.steer(1, None, Some(false));
        let again = t.lease("w", 1, 0, LEASE).unwrap();
        assert_eq!((again.render, again.first), (1, 0), "its passes came back in line");
    }
}
