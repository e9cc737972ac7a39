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
use tessera_request::placement::{Placement, Tag};

/// A worker asking for a job: its id, its pool (empty: none) and its tags.
#[derive(Clone, Copy, Debug)]
pub struct Asker<'a> {
    pub worker: &'a str,
    pub pool: &'a str,
    pub tags: &'a [Tag],
}

impl<'a> Asker<'a> {
    /// A worker of no pool, with no tags.
    pub fn plain(worker: &'a str) -> Self {
        Asker { worker, pool: "", tags: &[] }
    }
}

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
    /// Only passes below this are handed out (a sequence's previews first: its preview frames
    /// up to their preview passes, the others none); `None`: every pass.
    cap: Option<u32>,
    /// A quote's pilot ([`LeaseTable::pilot`]), if one was asked for.
    pilot: Option<Pilot>,
}

/// A quote's pilot: passes below `below` (the first adaptive round) of `tiles`, handed out
/// ahead of other work (checks apart) and even while the render is paused, so that its quote
/// rests on judged tiles before the farm is committed. They are the render's own first passes:
/// none renders twice once it goes on.
struct Pilot {
    tiles: BTreeSet<u32>,
    below: u32,
}

/// Renders scheduled together: a still render alone, or the frames of a sequence. A worker
/// gets a job of a group whose placement admits it (its pool, its tags), choosing, in order:
/// a group of the worker's own pool over one of no pool; the owner furthest below their share
/// of the farm (jobs in flight over their weight; one owner alone gets every worker); the
/// highest priority; and among equal priorities the oldest (first submitted): a render
/// submitted later waits its turn instead of taking every worker from the one before. Within a
/// group the earliest frame with pending passes goes first (so that frames finish in order
/// while idle workers start the next), unless the asking worker's last frame still has some (it
/// holds that frame's scene posed). A paused group gets no new jobs, passes or checks.
struct Group {
    priority: i32,
    paused: bool,
    members: BTreeSet<u64>,
    owner: String,
    placement: Placement,
}

impl RenderQueue {
    fn has_pending(&self) -> bool {
        self.first_pending().is_some()
    }

    /// The smallest pending (pass, tile) below the cap.
    fn first_pending(&self) -> Option<(u32, u32)> {
        let first = match (self.frontier.first(), self.returned.first()) {
            (Some(&f), Some(&r)) => Some(f.min(r)),
            (f, r) => f.or(r).copied(),
        };
        first.filter(|&(pass, _)| self.below_cap(pass))
    }

    fn below_cap(&self, pass: u32) -> bool {
        self.cap.is_none_or(|cap| pass < cap)
    }

    /// The smallest pending (pass, tile) of the pilot, if one was asked for. Looked up by the
    /// pilot's own tiles (at most [`tessera_render::plan::PILOT_TILES`]), not over the image's:
    /// it is asked at every lease for as long as the render is in the table.
    fn pilot_pending(&self) -> Option<(u32, u32)> {
        let pilot = self.pilot.as_ref()?;
        let wanted =
            |&(pass, tile): &(u32, u32)| pass < pilot.below && self.below_cap(pass) && pilot.tiles.contains(&tile);
        // Never-leased passes: a tile's are its `next` one onwards (its frontier entry).
        let fresh = pilot.tiles.iter().filter_map(|&tile| {
            let t = self.tiles.get(tile as usize)?;
            (t.next < t.budget).then_some((t.next, tile))
        });
        // Passes that came back: few, and pass-major, so the pilot's are at the front.
        let back = self.returned.iter().take_while(|&&(pass, _)| pass < pilot.below).copied();
        fresh.chain(back).filter(wanted).min()
    }

    /// Takes the passes after `first` of `tile` (taken already) while they are pending and
    /// `may(pass)`, up to `max_passes` in all: how many the job holds. A tile's first pass goes
    /// alone, so that every tile has one before any has more and the image fills in as a whole
    /// (the order of leases changes no bit of the merge).
    fn take_run(&mut self, first: u32, tile: u32, max_passes: u32, may: impl Fn(u32) -> bool) -> u32 {
        let longest = if first == 0 { 1 } else { max_passes.max(1) };
        let mut count = 1;
        while count < longest
            && first.checked_add(count).is_some_and(|p| may(p) && self.below_cap(p) && self.take(p, tile))
        {
            count += 1;
        }
        count
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
    /// The owner of each live lease's render, and each owner's live leases: the fair share.
    lease_owners: HashMap<u64, String>,
    in_flight: HashMap<String, u64>,
    /// Owners' weights in the fair share; 1 when not set.
    weights: HashMap<String, f64>,
    /// Renders with a pilot asked for (scanned first at every lease).
    piloting: BTreeSet<u64>,
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
            cap: None,
            pilot: None,
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
        let entry = self.groups.entry(group).or_insert(Group {
            priority,
            paused: false,
            members: BTreeSet::new(),
            owner: String::new(),
            placement: Placement::default(),
        });
        entry.members.insert(render);
    }

    /// Says whose group `group` is and where it may run (a new group is anyone's, anywhere).
    pub fn place(&mut self, group: u64, owner: &str, placement: &Placement) {
        if let Some(g) = self.groups.get_mut(&group) {
            g.owner = owner.to_string();
            g.placement = placement.clone();
        }
    }

    /// Sets the owners' weights in the fair share (an owner not named weighs 1).
    pub fn set_weights(&mut self, weights: HashMap<String, f64>) {
        self.weights = weights.into_iter().map(|(owner, w)| (owner, w.max(0.001))).collect();
    }

    /// Jobs in flight of each owner's renders (checks included).
    pub fn in_flight_by_owner(&self) -> &HashMap<String, u64> {
        &self.in_flight
    }

    /// Hands out only passes below `cap` of render `render` from now on (`None`: every pass).
    pub fn set_cap(&mut self, render: u64, cap: Option<u32>) {
        if let Some(q) = self.renders.get_mut(&render) {
            q.cap = cap;
        }
    }

    /// Asks for render `render`'s pilot: passes below `below` of `tiles` go out ahead of other
    /// work, paused or not, until they are merged ([`Pilot`]). `false` if the render is not in
    /// the table.
    pub fn pilot(&mut self, render: u64, tiles: impl IntoIterator<Item = u32>, below: u32) -> bool {
        let Some(q) = self.renders.get_mut(&render) else { return false };
        q.pilot = Some(Pilot { tiles: tiles.into_iter().collect(), below });
        self.piloting.insert(render);
        true
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
        self.piloting.remove(&render);
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
            self.take_lease(id);
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
        self.lease_except(Asker::plain(worker), max_passes, now_ms, lease_ms, None, |_| false)
    }

    /// As [`LeaseTable::lease`], for a worker with a pool and tags (`asker`), skipping the
    /// renders `skip` names (those a worker is blocked from, frames that may not start yet), and
    /// preferring `prefer` (the worker's last render) within its group. The order is
    /// [`Group`]'s.
    pub fn lease_except(
        &mut self,
        asker: Asker,
        max_passes: u32,
        now_ms: u64,
        lease_ms: u64,
        prefer: Option<u64>,
        skip: impl Fn(u64) -> bool,
    ) -> Option<JobLease> {
        let worker = asker.worker;
        self.expire(now_ms);
        let admits = |g: &Group| !g.paused && g.placement.admits(asker.pool, asker.tags);
        let group_of = |render: u64| self.renders.get(&render).and_then(|q| self.groups.get(&q.group));
        let usable = |c: &CheckJob| {
            !c.exclude.iter().any(|w| w == worker) && !skip(c.render) && group_of(c.render).is_some_and(admits)
        };
        if let Some(at) = self.checks.iter().position(usable) {
            let c = self.checks.remove(at)?;
            return Some(self.hand_out(worker, c.render, c.tile, c.first, c.count, now_ms, lease_ms, Some(c.exclude)));
        }
        // A pilot goes first, paused or not: its placement still has to admit the worker.
        let placed = |g: &Group| g.placement.admits(asker.pool, asker.tags);
        let pilot = self.piloting.iter().find_map(|&id| {
            let q = self.renders.get(&id).filter(|q| !skip(id) && self.groups.get(&q.group).is_some_and(placed))?;
            Some((id, q.pilot_pending()?))
        });
        if let Some((render, (first, tile))) = pilot {
            let queue = self.renders.get_mut(&render)?;
            queue.take(first, tile);
            let below = queue.pilot.as_ref().map_or(0, |p| p.below);
            let count = queue.take_run(first, tile, max_passes, |pass| pass < below);
            return Some(self.hand_out(worker, render, tile, first, count, now_ms, lease_ms, None));
        }
        let renders = &self.renders;
        let ready = |id: &u64| renders.get(id).is_some_and(|q| q.has_pending()) && !skip(*id);
        let share = |owner: &str| {
            self.in_flight.get(owner).copied().unwrap_or(0) as f64 / self.weights.get(owner).copied().unwrap_or(1.0)
        };
        // Admitted, a group of a pool is the worker's own pool's.
        let own_pool = |g: &Group| !g.placement.pool.is_empty();
        let render = self
            .groups
            .iter()
            .filter(|(_, g)| admits(g))
            .filter_map(|(&gid, g)| {
                let preferred = prefer.filter(|p| g.members.contains(p) && ready(p));
                let render = preferred.or_else(|| g.members.iter().copied().find(|id| ready(id)))?;
                Some((gid, g, render))
            })
            .max_by(|(a_id, a, _), (b_id, b, _)| {
                own_pool(a)
                    .cmp(&own_pool(b))
                    .then(share(&b.owner).total_cmp(&share(&a.owner)))
                    .then(a.priority.cmp(&b.priority))
                    .then(b_id.cmp(a_id))
            })
            .map(|(_, _, render)| render)?;
        let queue = self.renders.get_mut(&render)?;
        let (first, tile) = queue.first_pending()?;
        queue.take(first, tile);
        let count = queue.take_run(first, tile, max_passes, |_| true);
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
        let owner = self.renders.get(&render).and_then(|q| self.groups.get(&q.group)).map(|g| g.owner.clone());
        let owner = owner.unwrap_or_default();
        *self.in_flight.entry(owner.clone()).or_default() += 1;
        self.lease_owners.insert(lease.lease_id, owner);
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
        let Some(lease) = self.take_lease(lease_id) else {
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
        let l = self.take_lease(lease_id)?;
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

    /// Removes a live lease, and its count from its owner's jobs in flight.
    fn take_lease(&mut self, lease_id: u64) -> Option<JobLease> {
        let lease = self.leases.remove(&lease_id)?;
        if let Some(owner) = self.lease_owners.remove(&lease_id)
            && let Some(n) = self.in_flight.get_mut(&owner)
        {
            *n -= 1;
            if *n == 0 {
                self.in_flight.remove(&owner);
            }
        }
        Some(lease)
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
mod tests;
