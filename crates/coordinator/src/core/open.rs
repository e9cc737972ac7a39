//! Starting and resuming: a core read back from the store, each render's stored row checked
//! against today's limits ([`Prepared`]), its results read outside the state lock
//! ([`Prepared::read`]) and put to work ([`Core::install`]).

use super::{CANCELLED, Core, CoreConfig, CoreError, DONE, FAILED, Finished, Metrics, RenderRuntime, Span};
use crate::leases::LeaseTable;
use crate::model::{RenderState, Setup};
use crate::store::{Store, StoredRender, Unchecked, Write};

use std::collections::{BTreeMap, HashMap, HashSet};
use std::time::Instant;
use tessera_film::{Film, stopping_error};
use tessera_render::plan::{RenderPlan, first_round, next_round};
use tessera_request::placement::Placement;

/// A render about to be resumed from the store (at start-up, or by a retry): what its stored
/// row says, checked against the limits. [`Prepared::read`] reads its results, outside the
/// state lock; [`Core::install`] puts it to work.
pub struct Prepared {
    stored: StoredRender,
    setup: Setup,
    plan: RenderPlan,
    state: RenderState,
    placement: Placement,
}

/// A render read back from the store: its merged passes, film (a running render's only) and the
/// budgets its adaptive rounds had reached.
pub struct Resumed {
    prepared: Prepared,
    film: Film,
    merged: Vec<(u32, u32)>,
    budget: Vec<u32>,
    /// Each tile's predicted end, from its last round judged (as the merge predicts it).
    predicted: Vec<[u32; 3]>,
    samples_done: u64,
    /// Its results still to be checked by a second worker.
    unchecked: Vec<Unchecked>,
}

impl Prepared {
    /// Reads the render's results from `store`: for a running render the film they merge into
    /// and the adaptive rounds they show; for a finished or cancelled one only how many samples
    /// it took (its image is on disk, or rebuilt when asked for).
    pub fn read(self, store: &Store) -> Result<Resumed, CoreError> {
        let id = self.stored.id;
        let running = self.state == RenderState::Running;
        let ranges = store.ranges(id)?;
        // A render with nothing stored gets its film with its first result: a queued sequence
        // holds no films.
        let (film, ranges) = if !running || ranges.is_empty() {
            (Film::new(0, 0), ranges)
        } else {
            store.rebuild(id, super::merge::film_for(&self.setup.settings))?
        };
        let merged: Vec<(u32, u32)> =
            ranges.iter().flat_map(|r| (r.first..r.first + r.count).map(move |p| (r.tile, p))).collect();
        let (budget, predicted) =
            replay_budgets(store, &self.stored, &self.plan, &merged, self.setup.settings.confidence)?;
        let samples_done = if running {
            film.total_samples() + film.dropped()
        } else {
            let plan = &self.plan;
            ranges
                .iter()
                .map(|r| plan.samples(r.first, r.count).len() as u64 * plan.tiles[r.tile as usize].pixel_count() as u64)
                .sum()
        };
        let unchecked = if running { store.unchecked(id)? } else { Vec::new() };
        Ok(Resumed { prepared: self, film, merged, budget, predicted, samples_done, unchecked })
    }

    /// A render with nothing stored yet (just submitted): nothing to read.
    pub(super) fn fresh(self) -> Resumed {
        let (budget, predicted) = replay_budgets_fresh(&self.stored, &self.plan);
        Resumed {
            prepared: self,
            film: Film::new(0, 0),
            merged: Vec::new(),
            budget,
            predicted,
            samples_done: 0,
            unchecked: Vec::new(),
        }
    }
}

/// Passes per tile of a render with nothing merged: the whole budget, or an adaptive render's
/// first round; no tile judged.
fn replay_budgets_fresh(r: &StoredRender, plan: &RenderPlan) -> (Vec<u32>, Vec<[u32; 3]>) {
    let max = plan.passes_per_tile();
    let b = if r.target_error > 0.0 { first_round(r.min_spp, plan.pass_spp, max) } else { max };
    (vec![b; plan.tiles.len()], vec![[0; 3]; plan.tiles.len()])
}

/// Passes per tile: the whole budget, or for an adaptive render the rounds that the stored
/// results show were decided, replayed from the same merged data (so the same decisions; a
/// render with a `confidence` stops its tiles on their error bounds, as when it ran), with
/// each tile's predicted end from its last round judged.
fn replay_budgets(
    store: &Store,
    r: &StoredRender,
    plan: &RenderPlan,
    merged: &[(u32, u32)],
    confidence: f32,
) -> Result<(Vec<u32>, Vec<[u32; 3]>), CoreError> {
    let max = plan.passes_per_tile();
    if r.target_error <= 0.0 || merged.is_empty() {
        return Ok(replay_budgets_fresh(r, plan));
    }
    let first = first_round(r.min_spp, plan.pass_spp, max);
    let mut per_tile: Vec<std::collections::BTreeSet<u32>> = vec![Default::default(); plan.tiles.len()];
    for &(tile, pass) in merged {
        if let Some(set) = per_tile.get_mut(tile as usize) {
            set.insert(pass);
        }
    }
    let mut budget = Vec::with_capacity(plan.tiles.len());
    let mut predicted = vec![[0; 3]; plan.tiles.len()];
    for (index, tile) in plan.tiles.iter().enumerate() {
        let mut b = first;
        while per_tile[index].range(..b).count() as u32 == b {
            let sums = store.tile_sums(r.id, *tile, index as u32, b)?;
            let error = stopping_error(&sums.pixels, confidence);
            predicted[index] = super::merge::predicted_ends(plan, b, error, r.target_error);
            match next_round(b, max, error, r.target_error) {
                Some(next) => b = next,
                None => break,
            }
        }
        budget.push(b);
    }
    Ok((budget, predicted))
}

impl Core {
    /// A core resumed from `store`: every unfinished render's film, merged passes and adaptive
    /// rounds rebuilt from its stored results. A render that cannot be resumed is marked failed
    /// (a change left in [`Core::take_writes`]); one stored whole whose image was not written is
    /// left for [`Core::finish_stored`].
    pub fn open(config: CoreConfig, store: &Store) -> Result<Self, CoreError> {
        let mut core = Self {
            config,
            leases: LeaseTable::new(),
            renders: BTreeMap::new(),
            sequences: BTreeMap::new(),
            failed: BTreeMap::new(),
            workers: HashMap::new(),
            workers_pruned: Instant::now(),
            attempts: HashMap::new(),
            worker_failures: HashMap::new(),
            generations: 0,
            next_id: store.max_render_id()? + 1,
            retrying: HashSet::new(),
            writes: Vec::new(),
            ended: Vec::new(),
            previewing: HashMap::new(),
            previews: Vec::new(),
            epoch: Instant::now(),
            metrics: Metrics::default(),
            counts: Default::default(),
            checks: BTreeMap::new(),
            blocked: HashMap::new(),
            #[cfg(test)]
            reads: Default::default(),
        };
        core.blocked.extend(store.blocked_workers()?);
        let renders = store.renders()?;
        // Each sequence is counted before its frames are (`counts.rs`).
        let mut heads = BTreeMap::new();
        for stored in &renders {
            if stored.sequence != 0 {
                core.sequences.entry(stored.sequence).or_default().push(stored.id);
                heads.entry(stored.sequence).or_insert((stored.scene_name.clone(), stored.owner.clone()));
            }
        }
        for (seq, (scene, owner)) in heads {
            let frames = core.sequences[&seq].len() as u32;
            core.count_sequence(seq, &scene, &owner, frames);
        }
        for mut stored in renders {
            if stored.state == FAILED && stored.message.starts_with(super::REOPENED) {
                // Reopened for a blocked worker's results and not yet retried when the
                // coordinator stopped: its retry is this resumption.
                core.write(Write::State { render: stored.id, state: super::RUNNING, message: String::new() });
                stored.state = super::RUNNING.into();
                stored.message.clear();
            }
            if stored.state == FAILED {
                let id = stored.id;
                core.failed.insert(id, stored);
                core.recount(id);
                continue;
            }
            // One render that cannot be resumed (its stored settings no longer valid, its plan
            // over today's limits, its results unreadable) must not keep the coordinator down:
            // it is marked failed, saying why, and everything else resumes.
            match core.prepare(stored.clone()).and_then(|p| p.read(store)) {
                Ok(r) => {
                    let (id, running, samples) =
                        (r.prepared.stored.id, r.prepared.state == RenderState::Running, r.samples_done);
                    core.install(r);
                    if running && samples > 0 {
                        core.note(id, format!("the coordinator restarted: resumed with its {samples} samples merged"));
                    }
                }
                Err(e) => core.unresumable(stored, format!("could not be resumed after a restart: {e}")),
            }
        }
        let sequences: Vec<i64> = core.sequences.keys().copied().collect();
        for seq in sequences {
            core.begin_previews(seq);
        }
        core.collect_scenes();
        Ok(core)
    }

    /// The images of renders whose every result was stored but whose image was not written when
    /// the coordinator stopped: no result is left to merge and finish them, so they are finished
    /// here, to be written like any other ([`Finished::write`], [`Core::image_written`]).
    pub fn finish_stored(&mut self) -> Vec<Finished> {
        let complete: Vec<i64> = self
            .renders
            .iter()
            .filter(|&(&id, r)| r.state == RenderState::Running && self.leases.is_complete(id as u64))
            .filter(|&(&id, _)| self.checks_pending(id) == 0)
            .map(|(&id, _)| id)
            .collect();
        complete
            .into_iter()
            .filter_map(|id| {
                tracing::info!(render = id, "render {id} had every pass stored before the restart: writing its image");
                self.finish(id).ok()
            })
            .collect()
    }

    /// Records that `stored` could not be resumed: failed, with `message`, in the store and in the
    /// listings, holding no leases.
    pub(super) fn unresumable(&mut self, stored: StoredRender, message: String) {
        let id = stored.id;
        tracing::error!(render = id, "render {id} {message}; marked failed");
        self.leases.remove_render(id as u64);
        self.renders.remove(&id);
        self.write(Write::State { render: id, state: FAILED, message: message.clone() });
        self.failed.insert(id, StoredRender { state: FAILED.into(), message, ..stored });
        self.recount(id);
    }

    /// Decodes a stored render's settings and checks an unfinished one's plan against today's
    /// limits (a queued frame's film is checked when it starts, when leasing); no I/O.
    pub(super) fn prepare(&self, stored: StoredRender) -> Result<Prepared, CoreError> {
        let setup = Setup::decode(&stored.settings)
            .map_err(|e| CoreError::Invalid(format!("stored settings of render {}: {e}", stored.id)))?;
        let settings = &setup.settings;
        let plan = RenderPlan::new(settings.width, settings.height, stored.tile_size, stored.spp, stored.pass_spp);
        let state = match stored.state.as_str() {
            DONE => RenderState::Done,
            CANCELLED => RenderState::Cancelled,
            _ => RenderState::Running,
        };
        if state == RenderState::Running {
            self.check_plan(&plan)?;
            // As a submission's tiles are held to it (`tessera_request::wire`): one stored before
            // would ask workers for results no coordinator accepts.
            tessera_request::limits::check_result_bytes(stored.tile_size, settings.features)
                .map_err(CoreError::Limit)?;
            if stored.sequence == 0 {
                self.check_film(super::film_bytes(settings), Some(stored.id))?;
            }
        }
        let requires: Vec<String> = stored.requires.split_whitespace().map(str::to_string).collect();
        let placement = Placement::parse(&stored.pool, &requires)
            .map_err(|e| CoreError::Invalid(format!("stored placement of render {}: {e}", stored.id)))?;
        Ok(Prepared { stored, setup, plan, state, placement })
    }

    /// Puts a render read back from the store (or just submitted) to work: its unmerged passes
    /// queued, if it is running.
    pub fn install(&mut self, resumed: Resumed) {
        let Resumed { prepared: p, film, merged, budget, predicted, samples_done, unchecked } = resumed;
        let stored = p.stored;
        if p.state == RenderState::Running {
            let group = if stored.sequence != 0 { stored.sequence } else { stored.id } as u64;
            self.leases.add_to_group(stored.id as u64, group, stored.priority, &budget, &merged);
            if stored.paused {
                self.leases.steer(group, None, Some(true));
            }
            self.leases.place(group, &stored.owner, &p.placement);
        }
        let mut film_passes = vec![0u32; p.plan.tiles.len()];
        for &(tile, _) in &merged {
            if let Some(n) = film_passes.get_mut(tile as usize) {
                *n += 1;
            }
        }
        self.generations += 1;
        let span = Span::stored(stored.started_at, stored.ended_at);
        let final_error = stored_error(&stored, p.state, p.setup.settings.confidence);
        let runtime = RenderRuntime {
            passes_total: budget.iter().map(|&b| b as u64).sum(),
            film_passes,
            committing: 0,
            generation: self.generations,
            budget,
            stored,
            placement: p.placement,
            setup: p.setup,
            plan: p.plan,
            film,
            samples_done,
            span,
            state: p.state,
            message: String::new(),
            final_error,
            writing: false,
            workers: HashSet::new(),
            tile_errors: Vec::new(),
            predicted,
            error_estimate: Default::default(),
        };
        let id = runtime.stored.id;
        let running = runtime.state == RenderState::Running;
        self.renders.insert(id, runtime);
        if running {
            // A result accepted before a restart whose check had not come back: checked again.
            for u in unchecked {
                if self.blocked.contains_key(&u.worker) {
                    continue;
                }
                self.expect_check(id, u.result.tile, u.result.first, u.result.count, u.worker, u.digest);
            }
        }
        self.recount(id);
    }
}

/// A finished render's error as it was kept when it finished (a running one's is worked out
/// when it finishes).
fn stored_error(stored: &StoredRender, state: RenderState, confidence: f32) -> tessera_film::ErrorEstimate {
    let [estimate, bound] = stored.final_error;
    match state {
        RenderState::Done => {
            tessera_film::ErrorEstimate { estimate, upper: bound, confidence: confidence as f64, pixels: 0 }
        }
        _ => Default::default(),
    }
}
