//! The coordinator's state machine, synchronous: scenes, renders, the lease table, the films
//! being merged and the workers seen. It speaks its own types (`model.rs`; the service turns
//! protobuf into them, `wire.rs`) and, once the service has it defer its writes, does no I/O:
//! the store's changes it decides wait in [`Core::take_writes`], and what must be read (scenes,
//! stored results) is read by the caller. The gRPC shell (`service.rs`) holds it behind a mutex
//! and calls one method per request.

use crate::leases::{Completion, Ignored, LeaseTable};
use crate::model::{FrameDone, Job, Pose, RenderInfo, RenderState, Setup, Submission, WorkerStatus};
use crate::store::{Store, StoreError, StoredRender, StoredResult, Write};
use crate::wire::{decode_setup, encode_setup};
use std::collections::{BTreeMap, HashMap, HashSet};
use std::path::{Path, PathBuf};
use std::time::Instant;
use tessera_film::{ExrImage, Film, image_metadata, relative_error, write_exr};
use tessera_proto::sums::decode_tile_sums;
use tessera_render::plan::{FrameList, RenderPlan, first_round, frame_seed, frame_time, job_passes, next_round};
use tessera_scene::animation::{Choice, header_lines};

#[derive(Debug, thiserror::Error)]
pub enum CoreError {
    #[error("{0}")]
    Store(#[from] StoreError),
    #[error("{0}")]
    Invalid(String),
    #[error("{0}")]
    NotFound(String),
    #[error("{0}")]
    Limit(String),
    #[error("{0}")]
    NotReady(String),
}

/// Limits and timings of one coordinator.
#[derive(Clone, Debug)]
pub struct CoreConfig {
    pub data_dir: PathBuf,
    pub lease_ms: u64,
    /// Jobs are sized to take about this long on the worker that leases them.
    pub job_seconds: f64,
    pub max_job_passes: u32,
    pub max_scene_bytes: u64,
    pub max_triangles: usize,
    pub max_pixels: u64,
    pub max_spp: u32,
    pub max_active_renders: usize,
    /// Most tiles x passes one render may plan.
    pub max_passes: u64,
    /// Most bytes the films of all live renders may take together (a pixel's sums are
    /// [`FILM_BYTES_PER_PIXEL`] bytes).
    pub max_film_bytes: u64,
    /// fsync every committed result (survives power loss, not just the process dying).
    pub fsync: bool,
    /// A pass whose job failed or whose lease expired this many times fails its render.
    pub max_attempts: u32,
    /// A worker that reported this many failed jobs of a render gets no more of its jobs.
    pub block_after: u32,
}

/// Memory one pixel of a film takes: its exact sums.
pub const FILM_BYTES_PER_PIXEL: u64 = size_of::<tessera_render::PixelSums>() as u64;
/// Most tiles one render may have (a 1024 x 1024 image in 1 x 1 tiles).
pub const MAX_TILES: u64 = 1 << 20;
/// Longest scene name, worker name or worker id accepted, in bytes.
pub const MAX_NAME_BYTES: usize = 1024;
/// Workers remembered at once; one not seen for [`WORKER_FORGET_LEASES`] lease times is forgotten.
pub const MAX_WORKERS: usize = 1 << 16;
const WORKER_FORGET_LEASES: u64 = 10;

/// Refuses a name that is too long or carries control characters (which would print as
/// terminal escape sequences in `tessera status` and the logs).
pub fn check_name(what: &str, name: &str) -> Result<(), CoreError> {
    if name.len() > MAX_NAME_BYTES {
        return Err(CoreError::Limit(format!("{what} is {} bytes, over the {MAX_NAME_BYTES}-byte limit", name.len())));
    }
    if name.chars().any(char::is_control) {
        return Err(CoreError::Invalid(format!("{what} '{}' holds control characters", name.escape_debug())));
    }
    Ok(())
}

impl CoreConfig {
    pub fn new(data_dir: PathBuf) -> Self {
        Self {
            data_dir,
            lease_ms: 30_000,
            job_seconds: 2.0,
            max_job_passes: 64,
            max_scene_bytes: 1 << 30,
            max_triangles: 20_000_000,
            max_pixels: 1 << 24,
            max_spp: 1 << 20,
            max_active_renders: 64,
            max_passes: 1 << 26,
            max_film_bytes: 8 << 30,
            fsync: false,
            max_attempts: 3,
            block_after: 3,
        }
    }
}

struct RenderRuntime {
    /// Passes scheduled per tile (adaptive renders grow these round by round).
    budget: Vec<u32>,
    stored: StoredRender,
    /// What its pixels depend on: settings, environment, pose, map, variant.
    setup: Setup,
    plan: RenderPlan,
    film: Film,
    /// Passes merged into the film, per tile (the lease table counts them once accepted, which
    /// is before they are committed and merged).
    film_passes: Vec<u32>,
    /// Results accepted and not yet merged (their commit is under way).
    committing: u32,
    /// Which resumption of the render this is: a result accepted before a retry rebuilt the
    /// film from the store must not be merged into the new film as well.
    generation: u64,
    samples_done: u64,
    started: Instant,
    state: RenderState,
    message: String,
    /// The error estimate when the render finished (its film is dropped once the image is
    /// written).
    final_error: f64,
    /// True while its image is being written: the film is the writer's until then.
    writing: bool,
    /// What happened to it, newest last (at most [`LOG_LINES`]), for the dashboard.
    log: std::collections::VecDeque<String>,
    /// Each tile's relative error as last computed for the dashboard, with the passes merged
    /// then: recomputed only for tiles that have changed since.
    tile_errors: Vec<(u32, f32)>,
    /// The status's error estimate and when it was made: made again at most every
    /// [`ERROR_ESTIMATE_EVERY`], however many watch (each costs 16,384 pixels read under the lock).
    error_estimate: std::cell::Cell<Option<(Instant, f64)>>,
}

/// How long a running render's error estimate is reused.
const ERROR_ESTIMATE_EVERY: std::time::Duration = std::time::Duration::from_millis(500);

/// A film's relative error, estimated from at most 16,384 evenly spread pixels (cheap enough
/// for the state lock, even for a 4K film).
fn error_estimate(film: &Film) -> f64 {
    relative_error(film.pixels.iter().step_by((film.pixels.len() / 16384).max(1)))
}

/// Lines a render's log keeps.
pub const LOG_LINES: usize = 100;

impl RenderRuntime {
    fn note(&mut self, line: impl Into<String>) {
        if self.log.len() == LOG_LINES {
            self.log.pop_front();
        }
        self.log.push_back(format!("{:>8.1} s  {}", self.started.elapsed().as_secs_f64(), line.into()));
    }
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
}

/// One tile as the dashboard maps it: where it is, samples per pixel merged, relative error.
#[derive(Clone, Debug, PartialEq)]
pub struct TileView {
    pub tile: tessera_render::Tile,
    pub spp: u32,
    pub error: f32,
}

/// What the dashboard's page of one render shows beside its status.
#[derive(Clone, Debug)]
pub struct RenderDetail {
    pub info: RenderInfo,
    pub width: u32,
    pub height: u32,
    /// The settings as the EXR header writes them, and the farm's own.
    pub settings: Vec<(String, String)>,
    pub log: Vec<String>,
    /// Names of the workers holding its jobs now.
    pub workers: Vec<String>,
}

/// What a client names: a render, or a sequence (by its first frame's id, written `s<id>`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Target {
    Render(i64),
    Sequence(i64),
}

impl Target {
    /// The number in it: a render's id, or a sequence's first frame's.
    pub fn id(self) -> i64 {
        match self {
            Target::Render(id) | Target::Sequence(id) => id,
        }
    }

    pub fn parse(s: &str) -> Option<Target> {
        match s.strip_prefix('s') {
            Some(rest) => rest.parse().ok().filter(|&id: &i64| id > 0).map(Target::Sequence),
            None => s.parse().ok().map(Target::Render),
        }
    }
}

impl std::fmt::Display for Target {
    fn fmt(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        match self {
            Target::Render(id) => write!(f, "{id}"),
            Target::Sequence(id) => write!(f, "s{id}"),
        }
    }
}

/// Most frames x tiles one sequence may queue: the lease table keeps a few words per tile of
/// every queued frame.
pub const MAX_SEQUENCE_TILES: u64 = 1 << 22;

/// A result accepted against its lease, to be committed (outside the state lock) and then
/// merged with [`Core::merge`].
pub struct Accepted {
    pub lease: crate::leases::JobLease,
    generation: u64,
    sums: tessera_render::TileSums,
    samples: u64,
    started: Instant,
}

impl Accepted {
    /// Where the result goes in the store.
    pub fn stored(&self) -> StoredResult {
        StoredResult { tile: self.lease.tile, first: self.lease.first, count: self.lease.count }
    }
}

/// A render whose last pass was merged: its film and the image's header, to be resolved and
/// written outside the state lock ([`Finished::write`]), then reported with
/// [`Core::image_written`].
pub struct Finished {
    pub id: i64,
    film: Film,
    /// The render is transparent: its image has an alpha channel.
    transparent: bool,
    metadata: String,
    pub path: PathBuf,
}

impl Finished {
    /// The image: the film resolved, with its header.
    pub fn image(&self) -> ExrImage {
        ExrImage { metadata: self.metadata.clone(), ..self.film.resolve_with_alpha(self.transparent) }
    }

    /// Resolves the film and writes the EXR.
    pub fn write(&self) -> Result<(), String> {
        write_exr(&self.image(), &self.path).map_err(|e| e.to_string())
    }
}

/// A render about to be resumed from the store (at start-up, or by a retry): what its stored
/// row says, checked against the limits. [`Prepared::read`] reads its results, outside the
/// state lock; [`Core::install`] puts it to work.
pub struct Prepared {
    stored: StoredRender,
    setup: Setup,
    plan: RenderPlan,
    state: RenderState,
}

/// A render read back from the store: its merged passes, film (a running render's only) and the
/// budgets its adaptive rounds had reached.
pub struct Resumed {
    prepared: Prepared,
    film: Film,
    merged: Vec<(u32, u32)>,
    budget: Vec<u32>,
    samples_done: u64,
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
            store.rebuild(id, self.setup.settings.width, self.setup.settings.height)?
        };
        let merged: Vec<(u32, u32)> =
            ranges.iter().flat_map(|r| (r.first..r.first + r.count).map(move |p| (r.tile, p))).collect();
        let budget = replay_budgets(store, &self.stored, &self.plan, &merged)?;
        let samples_done = if running {
            film.total_samples() + film.dropped()
        } else {
            let plan = &self.plan;
            ranges
                .iter()
                .map(|r| plan.samples(r.first, r.count).len() as u64 * plan.tiles[r.tile as usize].pixel_count() as u64)
                .sum()
        };
        Ok(Resumed { prepared: self, film, merged, budget, samples_done })
    }

    /// A render with nothing stored yet (just submitted): nothing to read.
    fn fresh(self) -> Resumed {
        let budget = replay_budgets_fresh(&self.stored, &self.plan);
        Resumed { prepared: self, film: Film::new(0, 0), merged: Vec::new(), budget, samples_done: 0 }
    }
}

/// Passes per tile of a render with nothing merged: the whole budget, or an adaptive render's
/// first round.
fn replay_budgets_fresh(r: &StoredRender, plan: &RenderPlan) -> Vec<u32> {
    let max = plan.passes_per_tile();
    let b = if r.target_error > 0.0 { first_round(r.min_spp, plan.pass_spp, max) } else { max };
    vec![b; plan.tiles.len()]
}

/// Passes per tile: the whole budget, or for an adaptive render the rounds that the stored
/// results show were decided, replayed from the same merged data (so the same decisions).
fn replay_budgets(
    store: &Store,
    r: &StoredRender,
    plan: &RenderPlan,
    merged: &[(u32, u32)],
) -> Result<Vec<u32>, CoreError> {
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
    for (index, tile) in plan.tiles.iter().enumerate() {
        let mut b = first;
        while b < max && per_tile[index].range(..b).count() as u32 == b {
            let sums = store.tile_sums(r.id, *tile, index as u32, b)?;
            match next_round(b, max, relative_error(&sums.pixels), r.target_error) {
                Some(next) => b = next,
                None => break,
            }
        }
        budget.push(b);
    }
    Ok(budget)
}

struct Worker {
    name: String,
    threads: u32,
    samples_per_second: f64,
    last_seen: Instant,
    /// The render of its last job: its scene is posed on the worker, so more of it is cheap.
    last_render: Option<u64>,
    /// The address its calls come from, as the service saw it.
    host: String,
    /// Results of its merged, and jobs it reported failed.
    results: u64,
    failures: u64,
}

pub struct Core {
    config: CoreConfig,
    store: Store,
    leases: LeaseTable,
    renders: BTreeMap<i64, RenderRuntime>,
    /// The frames of each sequence, by the sequence's id (its first frame's).
    sequences: BTreeMap<i64, Vec<i64>>,
    /// Renders that could not be resumed (their `message` says why); they stay listed as failed.
    failed: BTreeMap<i64, StoredRender>,
    workers: HashMap<String, Worker>,
    /// When workers not seen for a while were last forgotten.
    workers_pruned: Instant,
    /// The failure policy's counts: attempts of each (render, tile, pass) that failed or
    /// expired, and failed jobs of each render by worker id.
    attempts: HashMap<(i64, u32, u32), u32>,
    worker_failures: HashMap<i64, HashMap<String, u32>>,
    /// Runtimes made so far (each render's resumption gets the next number).
    generations: u64,
    /// The id the next render gets.
    next_id: i64,
    /// Failed renders whose retry is reading their results.
    retrying: HashSet<i64>,
    /// Changes to the store not yet made: with [`Core::defer_writes`], the service takes them
    /// ([`Core::take_writes`]) for its writer thread; otherwise each is made at once.
    writes: Vec<Write>,
    deferred: bool,
    epoch: Instant,
    pub metrics: Metrics,
}

/// What became of a worker's result.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Outcome {
    Merged,
    Ignored(Ignored),
}

/// Counters since the coordinator started, for `/metrics`.
#[derive(Clone, Debug, Default)]
pub struct Metrics {
    pub passes_merged: u64,
    /// Results ignored, by reason.
    pub results_ignored: BTreeMap<Ignored, u64>,
    pub samples_merged: u64,
    pub bytes_in: u64,
    pub bytes_out: u64,
    pub merge_seconds_total: f64,
    pub merges: u64,
}

const RUNNING: &str = "running";
const DONE: &str = "done";
const CANCELLED: &str = "cancelled";
const FAILED: &str = "failed";
/// A scene no render needs is kept this long after its upload (for the submit that follows).
const SCENE_GRACE_SECONDS: i64 = 3600;

/// Bytes of film `renders` hold or will hold: a film allocated, or a running still's (allocated
/// with its first result). A sequence's frames take theirs when they start, which leasing allows
/// only while they fit.
fn film_bytes_held(renders: &BTreeMap<i64, RenderRuntime>, except: Option<i64>) -> u64 {
    renders
        .iter()
        .filter(|(id, _)| Some(**id) != except)
        .map(|(_, r)| {
            let pixels = match r.film.pixels.len() {
                0 if r.writing || (r.state == RenderState::Running && r.stored.sequence == 0) => {
                    r.setup.settings.width as u64 * r.setup.settings.height as u64
                }
                n => n as u64,
            };
            pixels * FILM_BYTES_PER_PIXEL
        })
        .sum()
}

/// Refuses scene bytes whose BLAKE3 hash is not the one claimed.
pub fn check_scene_hash(claimed_hash: &str, bytes: &[u8]) -> Result<(), CoreError> {
    let actual = blake3::hash(bytes).to_hex().to_string();
    if actual != claimed_hash {
        return Err(CoreError::Invalid(format!("scene hash mismatch: claimed {claimed_hash}, content is {actual}")));
    }
    Ok(())
}

/// The bytes of render `id`'s image file.
pub fn read_image(path: &Path, id: i64) -> Result<Vec<u8>, CoreError> {
    std::fs::read(path).map_err(|e| CoreError::NotFound(format!("image of render {id}: {e}")))
}

impl Core {
    /// Opens the data directory and resumes every unfinished render from its stored results.
    pub fn open(config: CoreConfig) -> Result<Self, CoreError> {
        std::fs::create_dir_all(config.data_dir.join("renders"))
            .map_err(|e| CoreError::Invalid(format!("cannot create {}: {e}", config.data_dir.display())))?;
        let store = Store::open(&config.data_dir, config.fsync)?;
        let mut core = Self {
            config,
            store,
            leases: LeaseTable::new(),
            renders: BTreeMap::new(),
            sequences: BTreeMap::new(),
            failed: BTreeMap::new(),
            workers: HashMap::new(),
            workers_pruned: Instant::now(),
            attempts: HashMap::new(),
            worker_failures: HashMap::new(),
            generations: 0,
            next_id: 1,
            retrying: HashSet::new(),
            writes: Vec::new(),
            deferred: false,
            epoch: Instant::now(),
            metrics: Metrics::default(),
        };
        core.next_id = core.store.max_render_id()? + 1;
        for stored in core.store.renders()? {
            if stored.sequence != 0 {
                core.sequences.entry(stored.sequence).or_default().push(stored.id);
            }
            if stored.state == FAILED {
                core.failed.insert(stored.id, stored);
                continue;
            }
            // One render that cannot be resumed (its stored settings no longer valid, its plan
            // over today's limits, its results unreadable) must not keep the coordinator down:
            // it is marked failed, saying why, and everything else resumes.
            let resumed = core.prepare(stored.clone()).and_then(|p| p.read(&core.store));
            match resumed {
                Ok(r) => core.install(r),
                Err(e) => core.unresumable(stored, format!("could not be resumed after a restart: {e}"))?,
            }
        }
        // A render whose every result was stored, but whose image was not written when the
        // coordinator stopped: no result is left to merge and finish it, so it is finished here.
        let complete: Vec<i64> = core
            .renders
            .iter()
            .filter(|&(&id, r)| r.state == RenderState::Running && core.leases.is_complete(id as u64))
            .map(|(&id, _)| id)
            .collect();
        for id in complete {
            tracing::info!(render = id, "render {id} had every pass stored before the restart: writing its image");
            let f = core.finish(id)?;
            let written = f.write();
            core.image_written(id, written)?;
        }
        core.collect_scenes();
        Ok(core)
    }

    /// From now on changes to the store wait in [`Core::take_writes`] for the caller to make
    /// them (the service's writer thread, outside the state lock) instead of being made at once.
    pub fn defer_writes(&mut self) {
        self.deferred = true;
    }

    /// The changes to the store made since the last call, in order: to be committed in this
    /// order (the service queues them for its writer before it lets go of the lock).
    pub fn take_writes(&mut self) -> Vec<Write> {
        std::mem::take(&mut self.writes)
    }

    /// Records a change to the store: made at once, or queued when writes are deferred.
    fn write(&mut self, w: Write) -> Result<(), CoreError> {
        if self.deferred {
            self.writes.push(w);
            Ok(())
        } else {
            Ok(self.store.apply(&w)?)
        }
    }

    /// Records that `stored` could not be resumed: failed, with `message`, in the store and in the
    /// listings, holding no leases.
    fn unresumable(&mut self, stored: StoredRender, message: String) -> Result<(), CoreError> {
        let id = stored.id;
        tracing::error!(render = id, "render {id} {message}; marked failed");
        self.leases.remove_render(id as u64);
        self.renders.remove(&id);
        self.write(Write::State { render: id, state: FAILED, message: message.clone() })?;
        self.failed.insert(id, StoredRender { state: FAILED.into(), message, ..stored });
        Ok(())
    }

    /// Deletes the stored scenes that no running or failed render needs (after an hour's grace),
    /// so that uploads do not pile up for ever. A failure to do so is logged, not fatal.
    fn collect_scenes(&mut self) {
        if let Err(e) = self.write(Write::CollectScenes { grace_seconds: SCENE_GRACE_SECONDS }) {
            tracing::warn!("could not collect unused scenes: {e}");
        }
    }

    /// Refuses a render whose plan or film would cost more than the limits allow, before
    /// anything is stored or allocated.
    fn check_cost(&self, plan: &RenderPlan, pixels: u64, except: Option<i64>) -> Result<(), CoreError> {
        self.check_plan(plan)?;
        self.check_film(pixels, except)
    }

    /// Refuses a plan of more tiles, or tiles x passes, than the limits allow.
    fn check_plan(&self, plan: &RenderPlan) -> Result<(), CoreError> {
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

    /// Refuses a film of `pixels` that would not fit beside the films the renders (but `except`)
    /// hold, under `--max-film-bytes`.
    fn check_film(&self, pixels: u64, except: Option<i64>) -> Result<(), CoreError> {
        let c = &self.config;
        let film = pixels.saturating_mul(FILM_BYTES_PER_PIXEL);
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

    /// Bytes of film the renders hold or will hold (see [`film_bytes_held`]).
    fn film_bytes_held(&self, except: Option<i64>) -> u64 {
        film_bytes_held(&self.renders, except)
    }

    /// Decodes a stored render's settings and checks an unfinished one's plan against today's
    /// limits (a queued frame's film is checked when it starts, when leasing); no I/O.
    fn prepare(&self, stored: StoredRender) -> Result<Prepared, CoreError> {
        let setup = decode_setup(&stored.settings)
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
            if stored.sequence == 0 {
                self.check_film(settings.width as u64 * settings.height as u64, Some(stored.id))?;
            }
        }
        Ok(Prepared { stored, setup, plan, state })
    }

    /// Puts a render read back from the store (or just submitted) to work: its unmerged passes
    /// queued, if it is running.
    pub fn install(&mut self, resumed: Resumed) {
        let Resumed { prepared: p, film, merged, budget, samples_done } = resumed;
        let stored = p.stored;
        if p.state == RenderState::Running {
            let group = if stored.sequence != 0 { stored.sequence } else { stored.id } as u64;
            self.leases.add_to_group(stored.id as u64, group, stored.priority, &budget, &merged);
        }
        let mut film_passes = vec![0u32; p.plan.tiles.len()];
        for &(tile, _) in &merged {
            if let Some(n) = film_passes.get_mut(tile as usize) {
                *n += 1;
            }
        }
        self.generations += 1;
        let mut runtime = RenderRuntime {
            film_passes,
            committing: 0,
            generation: self.generations,
            budget,
            stored,
            setup: p.setup,
            plan: p.plan,
            film,
            samples_done,
            started: Instant::now(),
            state: p.state,
            message: String::new(),
            final_error: 0.0,
            writing: false,
            log: Default::default(),
            tile_errors: Vec::new(),
            error_estimate: Default::default(),
        };
        runtime.note(match (runtime.state, runtime.samples_done) {
            (RenderState::Running, 0) => "queued".to_string(),
            (RenderState::Running, _) => "resumed from the store".to_string(),
            (state, _) => format!("read back from the store: {}", state.name()),
        });
        self.renders.insert(runtime.stored.id, runtime);
    }

    fn now_ms(&self) -> u64 {
        self.epoch.elapsed().as_millis() as u64
    }

    pub fn config(&self) -> &CoreConfig {
        &self.config
    }

    /// Stores a scene after checking its hash (the service checks it and has its writer store
    /// it, outside the lock).
    pub fn put_scene(&mut self, claimed_hash: &str, bytes: &[u8]) -> Result<(), CoreError> {
        check_scene_hash(claimed_hash, bytes)?;
        self.write(Write::Scene { hash: claimed_hash.to_string(), bytes: bytes.to_vec() })
    }

    /// Validates and records a render, and queues its passes.
    pub fn submit(
        &mut self,
        owner: &str,
        req: &Submission,
        triangles: usize,
        cameras: usize,
    ) -> Result<Target, CoreError> {
        let c = &self.config;
        check_name("the scene name", &req.scene_name)?;
        let settings = &req.setup.settings;
        let pixels = settings.width as u64 * settings.height as u64;
        if pixels > c.max_pixels {
            return Err(CoreError::Limit(format!("{pixels} pixels is over the limit of {}", c.max_pixels)));
        }
        // Adaptive renders: `max_spp` (or `spp`) is the most a tile gets, `min_spp` the first round.
        let adaptive = req.target_error > 0.0;
        if !req.target_error.is_finite() || req.target_error < 0.0 {
            return Err(CoreError::Invalid(format!("target error {} must be a positive number", req.target_error)));
        }
        let spp = if adaptive && req.max_spp > 0 { req.max_spp } else { req.spp };
        if spp == 0 || spp > c.max_spp {
            return Err(CoreError::Limit(format!("spp {spp} is outside 1..={}", c.max_spp)));
        }
        let min_spp = if adaptive { req.min_spp.max(1) } else { 0 };
        if min_spp > spp {
            return Err(CoreError::Invalid(format!("min spp {min_spp} is above max spp {spp}")));
        }
        if !(1..=1024).contains(&req.tile_size) || !(1..=1 << 16).contains(&req.pass_spp) {
            return Err(CoreError::Invalid(format!(
                "tile size {} (1..=1024) or pass spp {} (1..=65536) out of range",
                req.tile_size, req.pass_spp
            )));
        }
        if triangles > c.max_triangles {
            return Err(CoreError::Limit(format!("{triangles} triangles is over the limit of {}", c.max_triangles)));
        }
        if settings.camera >= cameras {
            return Err(CoreError::Invalid(format!(
                "camera {} does not exist (the scene has {cameras})",
                settings.camera
            )));
        }
        // A sequence counts once, however many frames it has.
        let active: std::collections::HashSet<i64> = self
            .renders
            .values()
            .filter(|r| r.state == RenderState::Running)
            .map(|r| if r.stored.sequence != 0 { r.stored.sequence } else { r.stored.id })
            .collect();
        let active = active.len();
        if active >= c.max_active_renders {
            return Err(CoreError::Limit(format!(
                "{active} renders are running, the limit is {}",
                c.max_active_renders
            )));
        }
        let plan = RenderPlan::new(settings.width, settings.height, req.tile_size, spp, req.pass_spp);
        self.check_cost(&plan, pixels, None)?;
        // The scene is there: the service read it to count its triangles and cameras.
        let stored = StoredRender {
            id: 0,
            scene_hash: req.scene_hash.clone(),
            scene_name: req.scene_name.clone(),
            settings: encode_setup(&req.setup),
            spp,
            tile_size: req.tile_size,
            pass_spp: req.pass_spp,
            priority: req.priority,
            state: RUNNING.into(),
            target_error: req.target_error as f64,
            min_spp,
            message: String::new(),
            owner: owner.to_string(),
            sequence: 0,
        };
        if req.frames.is_empty() {
            let stored = StoredRender { id: self.next_id, ..stored };
            let prepared = self.prepare(stored.clone())?;
            self.write(Write::Renders(vec![stored]))?;
            self.next_id += 1;
            self.install(prepared.fresh());
            let id = self.next_id - 1;
            if let Some(r) = self.renders.get_mut(&id) {
                r.note(format!(
                    "submitted by {}: the scene has {triangles} triangles and {cameras} cameras",
                    if owner.is_empty() { "anyone" } else { owner }
                ));
            }
            return Ok(Target::Render(id));
        }
        // A sequence: one render a frame, each at its own time with its own seed.
        let frames = FrameList::parse(&req.frames).map_err(|e| CoreError::Invalid(format!("frames: {e}")))?;
        let fps = req.fps;
        if !(fps.is_finite() && fps > 0.0 && fps <= 1e6) {
            return Err(CoreError::Invalid(format!("fps {fps} is not a positive number of frames per second")));
        }
        let tiles = frames.0.len() as u64 * plan.tiles.len() as u64;
        if tiles > MAX_SEQUENCE_TILES {
            return Err(CoreError::Limit(format!(
                "{} frames of {} tiles is over the limit of {MAX_SEQUENCE_TILES} tiles a sequence: use larger tiles or submit fewer frames at a time",
                frames.0.len(),
                plan.tiles.len()
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
                StoredRender { id, sequence, settings: encode_setup(&setup), ..stored.clone() }
            })
            .collect();
        self.write(Write::Renders(frame_renders.clone()))?;
        self.next_id += frame_renders.len() as i64;
        self.sequences.insert(sequence, frame_renders.iter().map(|r| r.id).collect());
        for r in frame_renders {
            match self.prepare(r.clone()) {
                Ok(prepared) => self.install(prepared.fresh()),
                Err(e) => self.unresumable(r, format!("could not be queued: {e}"))?,
            }
        }
        Ok(Target::Sequence(sequence))
    }

    /// Hands a job to a worker, sized from its measured speed.
    pub fn lease(
        &mut self,
        worker_id: &str,
        name: &str,
        threads: u32,
        samples_per_second: f64,
    ) -> Result<Option<Job>, CoreError> {
        check_name("the worker id", worker_id)?;
        check_name("the worker name", name)?;
        self.forget_old_workers();
        if !self.workers.contains_key(worker_id) && self.workers.len() >= MAX_WORKERS {
            return Err(CoreError::Limit(format!(
                "{MAX_WORKERS} workers are connected, the most one coordinator serves"
            )));
        }
        Ok(self.lease_job(worker_id, name, threads, samples_per_second))
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

    fn lease_job(&mut self, worker_id: &str, name: &str, threads: u32, samples_per_second: f64) -> Option<Job> {
        let info = self.workers.entry(worker_id.to_string()).or_insert_with(|| Worker {
            name: name.to_string(),
            threads,
            samples_per_second: 0.0,
            last_seen: Instant::now(),
            last_render: None,
            host: String::new(),
            results: 0,
            failures: 0,
        });
        info.last_seen = Instant::now();
        info.threads = threads;
        if samples_per_second.is_finite() && samples_per_second > 0.0 {
            info.samples_per_second = samples_per_second;
        }
        let speed = info.samples_per_second;
        let prefer = info.last_render;
        // Size for the render that will be served; tiles differ little, the first tile will do.
        let next = self.renders.values().find(|r| r.state == RenderState::Running)?;
        let tile_pixels = next.plan.tiles.first().map_or(1, |t| t.pixel_count() as u64);
        let passes =
            job_passes(speed, tile_pixels, next.plan.pass_spp, self.config.job_seconds, self.config.max_job_passes);
        let now = self.now_ms();
        let (failures, block_after) = (&self.worker_failures, self.config.block_after);
        let blocked = |render: u64| {
            failures.get(&(render as i64)).and_then(|m| m.get(worker_id)).is_some_and(|&n| n >= block_after)
        };
        // Frames start (and take a film) only while the films held fit --max-film-bytes. What
        // the films hold is summed over every render (each frame of a sequence is one), so only
        // when a frame is about to start, not on every lease.
        let held = std::cell::OnceCell::new();
        let renders = &self.renders;
        let fits = |render: u64| {
            renders.get(&(render as i64)).is_some_and(|r| {
                r.film.width > 0
                    || r.stored.sequence == 0
                    || *held.get_or_init(|| film_bytes_held(renders, None))
                        + r.setup.settings.width as u64 * r.setup.settings.height as u64 * FILM_BYTES_PER_PIXEL
                        <= self.config.max_film_bytes
            })
        };
        let lease =
            self.leases.lease_except(worker_id, passes, now, self.config.lease_ms, prefer, |r| blocked(r) || !fits(r));
        self.note_expiries();
        let lease = lease?;
        if let Some(w) = self.workers.get_mut(worker_id) {
            w.last_render = Some(lease.render);
        }
        let r = self.renders.get(&(lease.render as i64))?;
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

    /// A worker hands back leases it will not render (it is shutting down).
    pub fn release(&mut self, worker_id: &str, lease_ids: &[String]) -> u64 {
        let ids: Vec<u64> = lease_ids.iter().filter_map(|s| s.parse().ok()).collect();
        let passes = self.leases.release(worker_id, &ids);
        if passes > 0 {
            tracing::info!(worker = %worker_id, passes, "worker handed back leases");
        }
        passes
    }

    /// A worker's result: validated, committed to the store, then merged, all in this call (the
    /// service commits outside the lock instead: [`Core::accept`], the store's writer,
    /// [`Core::merge`]). Ignored (and counted by reason) when its lease is not live.
    pub fn complete(&mut self, worker_id: &str, lease_id: &str, bytes: &[u8]) -> Result<Outcome, CoreError> {
        let accepted = match self.accept(worker_id, lease_id, decode_tile_sums(bytes))? {
            Ok(a) => a,
            Err(why) => return Ok(Outcome::Ignored(why)),
        };
        let committed = self.store.put_result(accepted.lease.render as i64, &accepted.stored(), bytes);
        let finished = self.merge(accepted, committed.map_err(|e| e.to_string()))?;
        if let Some(f) = finished {
            let written = f.write();
            self.image_written(f.id, written)?;
        }
        Ok(Outcome::Merged)
    }

    /// Checks a result against its live lease and takes its passes (no one else gets them
    /// again); `Err(why)` when it is to be ignored, counted by reason. Nothing is stored yet.
    /// `sums` is the result decoded by the caller (the service decodes outside the lock);
    /// one that did not decode is refused if its lease is live, and ignored like any other
    /// result if it is not.
    pub fn accept(
        &mut self,
        worker_id: &str,
        lease_id: &str,
        sums: Result<tessera_render::TileSums, tessera_proto::WireError>,
    ) -> Result<Result<Accepted, Ignored>, CoreError> {
        let started = Instant::now();
        let lease = match lease_id.parse::<u64>() {
            Ok(id) => self.leases.get(id).cloned().ok_or(self.leases.why_gone(id)),
            Err(_) => Err(Ignored::Unknown),
        };
        let lease = match lease {
            Ok(lease) => lease,
            Err(why) => return Ok(Err(self.ignore(why))),
        };
        let sums = sums.map_err(|e| CoreError::Invalid(e.to_string()))?;
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
        let now = self.now_ms();
        let completion = self.leases.complete(lease.lease_id, worker_id, now);
        self.note_expiries();
        let lease = match completion {
            Completion::Accepted(lease) => lease,
            Completion::Ignored(why) => return Ok(Err(self.ignore(why))),
        };
        let Some(r) = self.renders.get_mut(&(lease.render as i64)) else {
            return Err(CoreError::NotFound("render gone".into()));
        };
        r.committing += 1;
        Ok(Ok(Accepted { lease, generation: r.generation, sums, samples, started }))
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
            return Err(CoreError::Invalid(format!("the result could not be stored: {e}")));
        }
        if render.state != RenderState::Running {
            return Ok(None); // cancelled or failed meanwhile: stored, and that is all
        }
        let pixels = a.sums.pixels.len() as u64;
        self.metrics.passes_merged += a.lease.count as u64;
        self.metrics.samples_merged += a.samples * pixels;
        if render.film.width == 0 {
            render.film = Film::new(render.setup.settings.width, render.setup.settings.height);
        }
        render.film.merge_tile(&a.sums).map_err(|e| CoreError::Invalid(e.to_string()))?;
        render.samples_done += a.samples * pixels;
        let tile = a.lease.tile as usize;
        render.film_passes[tile] += a.lease.count;
        if render.stored.target_error > 0.0 && render.film_passes[tile] == render.budget[tile] {
            let b = render.budget[tile];
            let error = relative_error(render.film.tile_pixels(render.plan.tiles[tile]));
            if let Some(next) = next_round(b, render.plan.passes_per_tile(), error, render.stored.target_error) {
                self.leases.extend_tile(a.lease.render, a.lease.tile, b, next);
                render.budget[tile] = next;
            }
        }
        self.metrics.merges += 1;
        self.metrics.merge_seconds_total += a.started.elapsed().as_secs_f64();
        if let Some(w) = self.workers.get_mut(&a.lease.worker) {
            w.results += 1;
        }
        if render.committing == 0 && self.leases.is_complete(a.lease.render) {
            return self.finish(id).map(Some);
        }
        Ok(None)
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
            tracing::warn!(render, worker = %name, "worker {name} failed {} jobs of render {render}: it gets no more of them", self.config.block_after);
        }
        self.record_attempt(&lease, &format!("worker {name}: {error}"));
        Ok(())
    }

    /// Counts the expired leases' passes as failed attempts.
    fn note_expiries(&mut self) {
        for lease in self.leases.take_expired() {
            let name = self.workers.get(&lease.worker).map_or(lease.worker.as_str(), |w| w.name.as_str()).to_string();
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
        r.note(format!(
            "a job failed (tile {}, passes {}..{}): {error}",
            lease.tile,
            lease.first,
            lease.first + lease.count
        ));
        if most >= self.config.max_attempts {
            let message = format!(
                "tile {} passes {}..{} failed {most} times; the last time, {error}",
                lease.tile,
                lease.first,
                lease.first + lease.count
            );
            tracing::error!(render, "render {render} failed: {message}");
            r.state = RenderState::Failed;
            r.message = message.clone();
            r.note(format!("failed: {message}"));
            self.leases.remove_render(lease.render);
            if let Err(e) = self.write(Write::State { render, state: FAILED, message }) {
                tracing::error!(render, "could not record the failure: {e}");
            }
        }
    }

    /// Puts a failed render back to work: its stored results are kept, its unfinished passes
    /// queued again, its failure counts and blocked workers forgotten. Reads the store at once;
    /// the service reads it outside the lock ([`Core::begin_retry`], [`Prepared::read`],
    /// [`Core::end_retry`]).
    pub fn retry(&mut self, id: i64) -> Result<(), CoreError> {
        let prepared = self.begin_retry(id)?;
        let read = prepared.read(&self.store);
        self.end_retry(id, read)
    }

    /// Checks that render `id` may be retried (it failed, and stores nothing any more) and
    /// prepares it; its results are then read ([`Prepared::read`]) and [`Core::end_retry`] puts
    /// it to work. Until then it stays failed, and another retry is refused.
    pub fn begin_retry(&mut self, id: i64) -> Result<Prepared, CoreError> {
        let stored = match (self.failed.get(&id), self.renders.get(&id)) {
            _ if self.retrying.contains(&id) => {
                return Err(CoreError::NotReady(format!("render {id} is being retried")));
            }
            (Some(stored), _) => stored.clone(),
            (None, Some(r)) if r.state == RenderState::Failed && r.committing > 0 => {
                // Its film is rebuilt from the store: results still on their way there would be
                // missed by it, and stored again later.
                return Err(CoreError::NotReady(format!(
                    "render {id} is still storing {} result(s): retry in a moment",
                    r.committing
                )));
            }
            (None, Some(r)) if r.state == RenderState::Failed => r.stored.clone(),
            (None, Some(r)) => {
                let state = r.state.name();
                return Err(CoreError::Invalid(format!("render {id} is {state}: only a failed render can be retried")));
            }
            (None, None) => return Err(CoreError::NotFound(format!("no render {id}"))),
        };
        let stored = StoredRender { state: RUNNING.into(), message: String::new(), ..stored };
        // Its own film (if it still holds one) is about to be replaced: not counted against it.
        let prepared = self.prepare(stored)?;
        self.retrying.insert(id);
        Ok(prepared)
    }

    /// Puts a retried render to work with what was read of it, or marks it failed again saying
    /// why it could not be read.
    pub fn end_retry(&mut self, id: i64, read: Result<Resumed, CoreError>) -> Result<(), CoreError> {
        self.retrying.remove(&id);
        let stored = self.failed.remove(&id).or_else(|| self.renders.remove(&id).map(|r| r.stored));
        self.attempts.retain(|&(render, _, _), _| render != id);
        self.worker_failures.remove(&id);
        match read {
            Ok(resumed) => {
                self.write(Write::State { render: id, state: RUNNING, message: String::new() })?;
                self.install(resumed);
                tracing::info!(render = id, "render {id} retried");
                Ok(())
            }
            Err(e) => {
                let message = format!("could not be resumed: {e}");
                if let Some(stored) = stored {
                    self.unresumable(stored, message.clone())?;
                }
                Err(CoreError::Invalid(format!("render {id} {message}")))
            }
        }
    }

    /// Counts an ignored result by its reason.
    fn ignore(&mut self, why: Ignored) -> Ignored {
        *self.metrics.results_ignored.entry(why).or_default() += 1;
        why
    }

    pub fn exr_path(&self, id: i64) -> PathBuf {
        self.config.data_dir.join("renders").join(format!("{id}.exr"))
    }

    /// The image of a render whose passes are all merged; its leases are gone. The render is
    /// done once [`Core::image_written`] hears the file was written. The film goes with it: the
    /// image is resolved where it is written, outside the state lock.
    fn finish(&mut self, id: i64) -> Result<Finished, CoreError> {
        let r = self.renders.get_mut(&id).ok_or_else(|| CoreError::NotFound(format!("render {id}")))?;
        let film = std::mem::replace(&mut r.film, Film::new(0, 0));
        self.finished(id, film)
    }

    /// Render `id`'s image to be: `film` (all its results merged) and the image's header.
    fn finished(&mut self, id: i64, film: Film) -> Result<Finished, CoreError> {
        let path = self.exr_path(id);
        let r = self.renders.get_mut(&id).ok_or_else(|| CoreError::NotFound(format!("render {id}")))?;
        let film = if film.width == 0 { Film::new(r.setup.settings.width, r.setup.settings.height) } else { film };
        let pose = r.setup.pose.as_ref().map(|p| {
            let frame = p.frame.map(|f| (f, p.fps, r.setup.settings.seed));
            let choice = Choice::from_wire(&p.animation).unwrap_or_default();
            (header_lines(&choice, p.time, frame), p.frame.map_or(r.setup.settings.seed, |_| p.sequence_seed))
        });
        let metadata = image_metadata(
            &r.stored.scene_name,
            &r.stored.scene_hash,
            pose.as_ref().map_or(r.setup.settings.seed, |p| p.1),
            r.stored.spp,
            r.setup.environment.to_array(),
            &r.setup.settings.describe(),
            film.dropped(),
        ) + &r.setup.environment_map.as_ref().map_or(String::new(), |m| {
            tessera_scene::environment::header_lines(&m.name, &m.hash, m.strength, m.rotate_degrees)
        }) + pose.as_ref().map_or("", |p| p.0.as_str())
            + &r.setup.variant.as_deref().map_or(String::new(), tessera_scene::variant_header);
        r.final_error = error_estimate(&film);
        r.writing = true;
        r.note("every pass merged: writing the image");
        self.leases.remove_render(id as u64);
        Ok(Finished { id, film, transparent: r.setup.settings.transparent, metadata, path })
    }

    /// A finished render's image was written (or not: then it is rebuilt from the stored results
    /// when asked for); the render is done.
    pub fn image_written(&mut self, id: i64, written: Result<(), String>) -> Result<(), CoreError> {
        if let Err(e) = written {
            tracing::error!(render = id, "could not write the image of render {id} (it is rebuilt when fetched): {e}");
        }
        if let Some(r) = self.renders.get_mut(&id) {
            r.state = RenderState::Done;
            r.writing = false;
        }
        self.write(Write::State { render: id, state: DONE, message: String::new() })?;
        self.collect_scenes();
        Ok(())
    }

    /// Where a finished render's EXR is, and its size (to rebuild it from the stored results
    /// should the file be gone: [`Store::rebuild`], then [`Core::rebuilt`]).
    pub fn image_path(&self, id: i64) -> Result<(PathBuf, u32, u32), CoreError> {
        if let Some(stored) = self.failed.get(&id) {
            return Err(CoreError::NotReady(format!("render {id} failed: {}", stored.message)));
        }
        let r = self.renders.get(&id).ok_or_else(|| CoreError::NotFound(format!("no render {id}")))?;
        if r.state != RenderState::Done {
            return Err(CoreError::NotReady(format!("render {id} is not finished")));
        }
        Ok((self.exr_path(id), r.setup.settings.width, r.setup.settings.height))
    }

    /// The image of a finished render whose file was lost, from `film` (its stored results
    /// merged again): to be written like a render's last result's ([`Finished::write`],
    /// [`Core::image_written`]).
    pub fn rebuilt(&mut self, id: i64, film: Film) -> Result<Finished, CoreError> {
        self.image_path(id)?;
        self.finished(id, film)
    }

    /// The finished image's EXR bytes, rebuilt from the stored results if the file is gone.
    /// Reads (and may write) files at once: the service does each step outside the lock.
    pub fn image(&mut self, id: i64) -> Result<Vec<u8>, CoreError> {
        let (path, width, height) = self.image_path(id)?;
        if !path.is_file() {
            let (film, _) = self.store.rebuild(id, width, height)?;
            let f = self.rebuilt(id, film)?;
            f.write().map_err(CoreError::Invalid)?;
            self.image_written(id, Ok(()))?;
        }
        read_image(&path, id)
    }

    pub fn cancel(&mut self, id: i64) -> Result<(), CoreError> {
        if self.failed.contains_key(&id) {
            return Ok(());
        }
        let r = self.renders.get_mut(&id).ok_or_else(|| CoreError::NotFound(format!("no render {id}")))?;
        if r.state == RenderState::Running {
            r.state = RenderState::Cancelled;
            r.note("cancelled");
            self.leases.remove_render(id as u64);
            self.write(Write::State { render: id, state: CANCELLED, message: String::new() })?;
            self.collect_scenes();
        }
        Ok(())
    }

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
        let total: u64 = r.budget.iter().map(|&b| b as u64).sum();
        let done = match r.state {
            RenderState::Done => total,
            _ => self.leases.progress(id as u64).map_or(0, |(m, _)| m),
        };
        let secs = r.started.elapsed().as_secs_f64().max(1e-3);
        let rate = r.samples_done as f64 / secs;
        let remaining = (total - done.min(total)) as f64
            * r.plan.pass_spp as f64
            * r.plan.tiles.first().map_or(0, |t| t.pixel_count()) as f64;
        Some(RenderInfo {
            render_id: id.to_string(),
            scene_name: r.stored.scene_name.clone(),
            state: r.state,
            passes_done: done,
            passes_total: total,
            samples_done: r.samples_done,
            samples_per_second: rate,
            // An estimate from at most 16384 evenly spread pixels, made at most twice a second.
            error_estimate: match r.state {
                _ if r.state == RenderState::Done || r.writing => r.final_error,
                _ => match r.error_estimate.get() {
                    Some((at, e)) if at.elapsed() < ERROR_ESTIMATE_EVERY => e,
                    _ => {
                        let e = error_estimate(&r.film);
                        r.error_estimate.set(Some((Instant::now(), e)));
                        e
                    }
                },
            },
            eta_seconds: if rate > 0.0 { remaining / rate } else { 0.0 },
            message: r.message.clone(),
            mean_spp: r.samples_done as f64 / (r.setup.settings.width as f64 * r.setup.settings.height as f64),
            owner: r.stored.owner.clone(),
            sequence_id: if r.stored.sequence != 0 {
                Target::Sequence(r.stored.sequence).to_string()
            } else {
                String::new()
            },
            frame: self.frame_of(id),
            ..Default::default()
        })
    }

    /// The status of a render or of a whole sequence: its frames counted by state, passes and
    /// samples summed, the ETA of what is left, and the frames finished (frame, render id).
    pub fn status_of(&self, target: Target) -> Option<RenderInfo> {
        let seq = match target {
            Target::Render(id) => return self.status(id),
            Target::Sequence(seq) => seq,
        };
        let frames = self.sequences.get(&seq)?;
        let mut out = RenderInfo {
            render_id: target.to_string(),
            sequence_id: target.to_string(),
            frames_total: frames.len() as u32,
            ..Default::default()
        };
        let (mut rate, mut weight, mut errors) = (0.0, 0.0, 0.0);
        for &id in frames {
            let Some(st) = self.status(id) else { continue };
            out.scene_name.clone_from(&st.scene_name);
            out.owner.clone_from(&st.owner);
            out.passes_done += st.passes_done;
            out.passes_total += st.passes_total;
            out.samples_done += st.samples_done;
            rate = f64::max(rate, st.samples_per_second);
            match st.state {
                RenderState::Done => {
                    out.frames_done += 1;
                    out.finished.push(FrameDone { frame: st.frame.unwrap_or(0), render_id: st.render_id });
                    errors += st.error_estimate;
                    weight += 1.0;
                }
                RenderState::Running if st.passes_done > 0 => out.frames_running += 1,
                RenderState::Running => out.frames_queued += 1,
                RenderState::Failed => {
                    out.frames_failed += 1;
                    if out.message.is_empty() {
                        out.message = format!("frame {}: {}", st.frame.unwrap_or(0), st.message);
                    }
                }
                _ => {}
            }
        }
        // Samples a second over the whole sequence: from its first frame's start.
        let started = frames.iter().filter_map(|id| self.renders.get(id)).map(|r| r.started).min();
        if let Some(started) = started {
            rate = rate.max(out.samples_done as f64 / started.elapsed().as_secs_f64().max(1e-3));
        }
        out.samples_per_second = rate;
        let left = out.passes_total.saturating_sub(out.passes_done) as f64;
        let per_pass = if out.passes_done > 0 { out.samples_done as f64 / out.passes_done as f64 } else { 0.0 };
        out.eta_seconds = if rate > 0.0 { left * per_pass / rate } else { 0.0 };
        out.error_estimate = if weight > 0.0 { errors / weight } else { 0.0 };
        let running = out.frames_running + out.frames_queued;
        let cancelled = out.frames_total - out.frames_done - running - out.frames_failed;
        out.state = if running > 0 {
            RenderState::Running
        } else if out.frames_failed > 0 {
            RenderState::Failed
        } else if cancelled > 0 {
            RenderState::Cancelled
        } else {
            RenderState::Done
        };
        Some(out)
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
    fn frame_of(&self, id: i64) -> Option<u32> {
        match self.renders.get(&id) {
            Some(r) => r.setup.pose.as_ref().and_then(|p| p.frame),
            None => {
                let stored = self.failed.get(&id)?;
                decode_setup(&stored.settings).ok()?.pose?.frame
            }
        }
    }

    /// Seconds since `target` started (or resumed, after a restart): its first frame's, for a
    /// sequence.
    pub fn elapsed(&self, target: Target) -> Option<f64> {
        self.renders.get(&target.id()).map(|r| r.started.elapsed().as_secs_f64())
    }

    /// How many workers hold jobs of each render now.
    pub fn workers_by_render(&self) -> HashMap<i64, usize> {
        let mut on: HashMap<i64, HashSet<&str>> = HashMap::new();
        for l in self.leases.leases() {
            on.entry(l.render as i64).or_default().insert(l.worker.as_str());
        }
        on.into_iter().map(|(id, w)| (id, w.len())).collect()
    }

    /// The renders a target stands for: itself, or a sequence's frames.
    pub fn members(&self, target: Target) -> Vec<i64> {
        match target {
            Target::Render(id) => vec![id],
            Target::Sequence(seq) => self.sequences.get(&seq).cloned().unwrap_or_default(),
        }
    }

    /// Forgets a render or sequence just submitted whose rows could not be stored.
    pub fn forget(&mut self, target: Target) {
        for id in self.members(target) {
            self.leases.remove_render(id as u64);
            self.renders.remove(&id);
            self.failed.remove(&id);
        }
        if let Target::Sequence(seq) = target {
            self.sequences.remove(&seq);
        }
    }

    /// Cancels a render, or every frame of a sequence.
    pub fn cancel_target(&mut self, target: Target) -> Result<(), CoreError> {
        for id in self.members(target) {
            self.cancel(id)?;
        }
        Ok(())
    }

    /// Retries a failed render, or the failed frames of a sequence.
    pub fn retry_target(&mut self, target: Target) -> Result<(), CoreError> {
        for id in self.retry_members(target)? {
            self.retry(id)?;
        }
        Ok(())
    }

    /// The renders a retry of `target` retries: the render, or a sequence's failed frames.
    pub fn retry_members(&self, target: Target) -> Result<Vec<i64>, CoreError> {
        let Target::Sequence(_) = target else { return Ok(self.members(target)) };
        let failed: Vec<i64> = self
            .members(target)
            .into_iter()
            .filter(|id| self.status(*id).is_some_and(|s| s.state == RenderState::Failed))
            .collect();
        if failed.is_empty() {
            return Err(CoreError::Invalid(format!("sequence {target} has no failed frames to retry")));
        }
        Ok(failed)
    }

    /// Who submitted a render or sequence; `None` if there is none.
    pub fn owner_of(&self, target: Target) -> Option<&str> {
        match target {
            Target::Render(id) => self.owner(id),
            Target::Sequence(seq) => self.sequences.get(&seq).and_then(|f| f.first()).and_then(|&id| self.owner(id)),
        }
    }

    /// Prometheus text exposition of the counters.
    pub fn prometheus(&self) -> String {
        let m = &self.metrics;
        let alive_window = 2.0 * self.config.lease_ms as f64 / 1000.0;
        let alive = self.workers.values().filter(|w| w.last_seen.elapsed().as_secs_f64() < alive_window).count();
        let uptime = self.epoch.elapsed().as_secs_f64().max(1e-3);
        let running = self.renders.values().filter(|r| r.state == RenderState::Running).count();
        let frames =
            self.renders.values().filter(|r| r.state == RenderState::Running && r.stored.sequence != 0).count();
        let rows: [(&str, &str, &str, f64); 14] = [
            (
                "tessera_passes_in_flight",
                "gauge",
                "Passes leased to workers and not yet merged.",
                self.leases.passes_in_flight() as f64,
            ),
            (
                "tessera_pending_passes",
                "gauge",
                "Passes scheduled and not yet leased or merged, over all renders.",
                self.leases.pending_passes() as f64,
            ),
            ("tessera_passes_leased_total", "counter", "Passes handed to workers.", self.leases.passes_leased as f64),
            ("tessera_passes_completed_total", "counter", "Passes merged.", m.passes_merged as f64),
            (
                "tessera_passes_expired_total",
                "counter",
                "Passes whose lease expired.",
                self.leases.passes_expired as f64,
            ),
            (
                "tessera_passes_released_total",
                "counter",
                "Passes handed back unrendered by workers shutting down.",
                self.leases.passes_released as f64,
            ),
            (
                "tessera_pending_frames",
                "gauge",
                "Frames of sequences not finished yet (queued or rendering).",
                frames as f64,
            ),
            ("tessera_workers_alive", "gauge", "Workers seen within two lease times.", alive as f64),
            ("tessera_renders_running", "gauge", "Renders in progress.", running as f64),
            ("tessera_samples_merged_total", "counter", "Samples merged.", m.samples_merged as f64),
            (
                "tessera_samples_per_second",
                "gauge",
                "Samples merged per second since start.",
                m.samples_merged as f64 / uptime,
            ),
            ("tessera_bytes_in_total", "counter", "Scene and result bytes received.", m.bytes_in as f64),
            ("tessera_bytes_out_total", "counter", "Scene and image bytes sent.", m.bytes_out as f64),
            (
                "tessera_merge_seconds_total",
                "counter",
                "Time spent validating, storing and merging results.",
                m.merge_seconds_total,
            ),
        ];
        let mut out = String::new();
        for (name, kind, help, value) in rows {
            out += &format!("# HELP {name} {help}\n# TYPE {name} {kind}\n{name} {value}\n");
        }
        out += "# HELP tessera_results_ignored_total Results ignored, by reason (duplicate, late, released, render_ended, wrong_worker, unknown_lease).\n# TYPE tessera_results_ignored_total counter\n";
        for why in Ignored::ALL {
            let n = m.results_ignored.get(&why).copied().unwrap_or(0);
            out += &format!("tessera_results_ignored_total{{reason=\"{}\"}} {n}\n", why.label());
        }
        out += &format!(
            "# HELP tessera_merges_total Results merged.\n# TYPE tessera_merges_total counter\ntessera_merges_total {}\n",
            m.merges
        );
        out
    }

    /// Who submitted render `id` (empty without per-user tokens); `None` if there is no such render.
    pub fn owner(&self, id: i64) -> Option<&str> {
        self.renders
            .get(&id)
            .map(|r| r.stored.owner.as_str())
            .or_else(|| self.failed.get(&id).map(|s| s.owner.as_str()))
    }

    /// Renders with ids above `after` that `visible` lets through (by owner), in id order, at
    /// most `limit` of them; and whether more follow (then the last id listed is the next page's
    /// `after`).
    pub fn list_renders(&self, after: i64, limit: usize, visible: impl Fn(&str) -> bool) -> (Vec<RenderInfo>, bool) {
        let from = after.saturating_add(1)..;
        // A sequence is listed once, as its first frame's row; its other frames are not.
        let listed = |id: i64, sequence: i64| sequence == 0 || sequence == id;
        let mut ids: Vec<i64> = self
            .renders
            .range(from.clone())
            .filter(|(id, r)| visible(&r.stored.owner) && listed(**id, r.stored.sequence))
            .map(|(&id, _)| id)
            .take(limit + 1)
            .chain(
                self.failed
                    .range(from)
                    .filter(|(id, s)| visible(&s.owner) && listed(**id, s.sequence))
                    .map(|(&id, _)| id)
                    .take(limit + 1),
            )
            .collect();
        ids.sort_unstable();
        let more = ids.len() > limit;
        ids.truncate(limit);
        // A sequence is listed once, as its first frame's row; its other frames are not.
        let sequence = |id: i64| {
            self.renders.get(&id).map(|r| r.stored.sequence).or_else(|| self.failed.get(&id).map(|s| s.sequence))
        };
        let rows = ids
            .into_iter()
            .filter_map(|id| match sequence(id) {
                Some(0) | None => self.status(id),
                Some(seq) if seq == id => self.status_of(Target::Sequence(seq)).map(|mut s| {
                    s.finished.clear();
                    s
                }),
                Some(_) => None,
            })
            .collect();
        (rows, more)
    }

    /// What the dashboard shows of render `id`'s image (see [`PreviewOf`]); the film's preview
    /// reads only the pixels it shows, so a 4K film costs the lock little.
    pub fn preview(&self, id: i64, max_side: u32) -> Result<PreviewOf, CoreError> {
        let r = self.renders.get(&id).ok_or_else(|| CoreError::NotFound(format!("no render {id}")))?;
        if r.state == RenderState::Done && !r.writing {
            return Ok(PreviewOf::Image(self.exr_path(id)));
        }
        // A render not yet merged into (or whose film is being written) has an empty film: its
        // preview is black.
        Ok(PreviewOf::Film { preview: tessera_film::Preview::of_film(&r.film, max_side), version: r.samples_done })
    }

    /// Render `id`'s tiles with their samples per pixel and relative error; the error is
    /// recomputed only for the tiles merged into since the last call.
    pub fn tile_views(&mut self, id: i64) -> Result<Vec<TileView>, CoreError> {
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
                TileView { tile, spp: r.plan.samples(0, passes).len() as u32, error: r.tile_errors[t].1 }
            })
            .collect())
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
            log: r.log.iter().cloned().collect(),
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

    /// Notes where worker `worker_id`'s calls come from (shown by the dashboard).
    pub fn seen_from(&mut self, worker_id: &str, host: &str) {
        if let Some(w) = self.workers.get_mut(worker_id)
            && w.host != host
        {
            w.host = host.chars().take(100).collect();
        }
    }

    fn worker_statuses(&self, keep: impl Fn(&String) -> bool) -> Vec<WorkerStatus> {
        let mut leases: HashMap<&str, u32> = HashMap::new();
        let mut renders: HashMap<&str, std::collections::BTreeSet<i64>> = HashMap::new();
        for l in self.leases.leases() {
            *leases.entry(l.worker.as_str()).or_default() += 1;
            renders.entry(l.worker.as_str()).or_default().insert(l.render as i64);
        }
        self.workers
            .iter()
            .filter(|(id, _)| keep(id))
            .map(|(id, w)| WorkerStatus {
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

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use tessera_proto::sums::encode_tile_sums;
    use tessera_render::glam::Vec3;
    use tessera_render::{Density, Estimator, RenderSettings, SamplerKind, Termination, render_tile};

    pub(crate) const SCENE: &[u8] = b"tessera-builtin:furnace?base=0.8&metallic=0.5&roughness=0.4";

    fn settings() -> RenderSettings {
        RenderSettings {
            width: 64,
            height: 16,
            seed: 3,
            estimator: Estimator::Mis,
            density: Density::Brdf,
            sampler: SamplerKind::Sobol,
            termination: Termination::MaxBounces(4),
            camera: 0,
            color: tessera_render::ColorMode::Rgb,
            transparent: false,
            lights: tessera_render::LightSampler::Power,
        }
    }

    pub(crate) fn request(hash: &str) -> Submission {
        Submission {
            scene_hash: hash.into(),
            scene_name: "furnace".into(),
            setup: Setup {
                settings: settings(),
                environment: Vec3::ONE,
                pose: None,
                environment_map: None,
                variant: None,
            },
            spp: 64,
            tile_size: 16,
            pass_spp: 4,
            priority: 0,
            target_error: 0.02,
            min_spp: 4,
            max_spp: 64,
            frames: String::new(),
            fps: 0.0,
        }
    }

    /// Leases a job to worker "w" and renders it for real, as a worker would; `None` when there
    /// is no work. The result is not sent.
    fn render_job(core: &mut Core, scene: &tessera_render::Scene) -> Option<(Job, tessera_render::TileSums)> {
        let job = core.lease("w", "w", 1, 0.0).unwrap()?;
        let samples = RenderPlan::new(64, 16, 16, job.spp, job.pass_spp).samples(job.first_pass, job.pass_count);
        let sums = render_tile(scene, &job.setup.settings, job.tile, samples).unwrap();
        Some((job, sums))
    }

    /// Works `jobs` jobs as a worker would, with real renders.
    fn work(core: &mut Core, scene: &tessera_render::Scene, jobs: usize) {
        for _ in 0..jobs {
            let Some((job, sums)) = render_job(core, scene) else { return };
            assert_eq!(
                core.complete("w", &job.lease_id.to_string(), &encode_tile_sums(&sums)).unwrap(),
                Outcome::Merged
            );
        }
    }

    fn furnace() -> tessera_render::Scene {
        let options = tessera_scene::LoadOptions { environment: Some(Vec3::ONE), ..Default::default() };
        tessera_scene::load_packed(SCENE, "furnace", &options).unwrap().scene
    }

    /// An empty data directory under the temp dir, removed when dropped.
    fn fresh_dir(name: &str) -> tempfile::TempDir {
        tempfile::Builder::new().prefix(&format!("tessera-core-{name}-")).tempdir().unwrap()
    }

    /// A coordinator on `dir` with the furnace stored and the test render submitted.
    fn submitted(dir: &std::path::Path) -> (Core, i64) {
        let hash = blake3::hash(SCENE).to_hex().to_string();
        let mut core = Core::open(CoreConfig::new(dir.to_path_buf())).unwrap();
        core.put_scene(&hash, SCENE).unwrap();
        let id = core.submit("", &request(&hash), 100, 1).unwrap().id();
        (core, id)
    }

    /// A sequence of frames "1-3" of the test render, fixed 16 spp in passes of 4.
    fn sequence(core: &mut Core) -> i64 {
        let mut req = request(&blake3::hash(SCENE).to_hex());
        (req.target_error, req.spp, req.frames, req.fps) = (0.0, 16, "1-3".into(), 24.0);
        req.setup.pose = Some(Pose::default());
        match core.submit("", &req, 100, 1).unwrap() {
            Target::Sequence(id) => id,
            t => panic!("a sequence was submitted, {t} came back"),
        }
    }

    /// A coordinator stopped after storing a render's last result but before writing its image
    /// finishes it when it starts again (nothing is left to merge that would): the chaos test
    /// once waited for ever on such a frame.
    #[test]
    fn a_render_stored_whole_but_not_written_is_finished_at_start() {
        let dir = fresh_dir("stored-whole");
        let scene = furnace();
        let id = {
            let hash = blake3::hash(SCENE).to_hex().to_string();
            let mut core = Core::open(CoreConfig::new(dir.path().to_path_buf())).unwrap();
            core.put_scene(&hash, SCENE).unwrap();
            let mut req = request(&hash);
            (req.target_error, req.spp) = (0.0, 16);
            let id = core.submit("", &req, 100, 1).unwrap().id();
            let mut jobs = Vec::new();
            while let Some(job) = render_job(&mut core, &scene) {
                jobs.push(job);
            }
            let (last, rest) = jobs.split_last().unwrap();
            for (job, sums) in rest {
                core.complete("w", &job.lease_id.to_string(), &encode_tile_sums(sums)).unwrap();
            }
            // The last result is accepted and stored, and then the coordinator stops.
            let bytes = encode_tile_sums(&last.1);
            let accepted = core.accept("w", &last.0.lease_id.to_string(), decode_tile_sums(&bytes)).unwrap().unwrap();
            core.store.put_result(id, &accepted.stored(), &bytes).unwrap();
            assert_eq!(core.status(id).unwrap().state, RenderState::Running);
            id
        };
        let core = Core::open(CoreConfig::new(dir.path().to_path_buf())).unwrap();
        assert_eq!(core.status(id).unwrap().state, RenderState::Done);
        assert!(core.exr_path(id).is_file(), "its image is written");
    }

    #[test]
    fn sequences_run_frames_in_order_keep_workers_on_their_frame_and_survive_a_restart() {
        let dir = fresh_dir("sequence");
        let scene = furnace();
        let seq = {
            let (mut core, still) = submitted(dir.path());
            core.cancel(still).unwrap();
            let seq = sequence(&mut core);
            let s = core.status_of(Target::Sequence(seq)).unwrap();
            assert_eq!((s.frames_total, s.frames_queued, s.frames_running), (3, 3, 0));
            assert_eq!(core.film_bytes_held(None), 0, "queued frames hold no film");
            // Each frame has its own seed and time; the first frame's id names the sequence.
            let frames = core.members(Target::Sequence(seq));
            assert_eq!(frames.len(), 3);
            let pose = |id: i64| core.renders[&id].setup.pose.clone().unwrap();
            assert_eq!((pose(frames[1]).frame, pose(frames[1]).time), (Some(2), 2.0 / 24.0));
            assert_ne!(core.renders[&frames[0]].setup.settings.seed, core.renders[&frames[1]].setup.settings.seed);
            // Worker a takes all of frame 1's passes (4 tiles x 4) before any of frame 2's.
            let mut a_jobs = Vec::new();
            let mut passes = 0;
            while passes < 16 {
                let job = core.lease("a", "a", 1, 0.0).unwrap().unwrap();
                assert_eq!(job.render_id, seq, "frame 1 first");
                passes += job.pass_count;
                a_jobs.push(job);
            }
            assert_eq!(core.lease("a", "a", 1, 0.0).unwrap().unwrap().render_id, frames[1]);
            // A job of frame 1 comes back: worker a stays on its frame 2, worker b takes frame 1's.
            core.fail("a", &a_jobs[0].lease_id.to_string(), "out of memory").unwrap();
            assert_eq!(core.lease("a", "a", 1, 0.0).unwrap().unwrap().render_id, frames[1]);
            assert_eq!(core.lease("b", "b", 1, 0.0).unwrap().unwrap().render_id, seq);
            let s = core.status_of(Target::Sequence(seq)).unwrap();
            assert_eq!((s.frames_running, s.frames_queued, s.frames_done), (0, 3, 0), "nothing merged yet");
            // The listing shows the sequence once.
            let (rows, _) = core.list_renders(0, 100, |_| true);
            assert_eq!(rows.iter().map(|r| r.render_id.as_str()).collect::<Vec<_>>(), ["1", &format!("s{seq}")]);
            seq
        };
        // After a restart the leases are gone and the frames queued again; they finish, each
        // with its own image.
        let mut core = Core::open(CoreConfig::new(dir.path().to_path_buf())).unwrap();
        assert_eq!(core.film_bytes_held(None), 0);
        while let Some((job, sums)) = render_job(&mut core, &scene) {
            assert_eq!(
                core.complete("w", &job.lease_id.to_string(), &encode_tile_sums(&sums)).unwrap(),
                Outcome::Merged
            );
        }
        let s = core.status_of(Target::Sequence(seq)).unwrap();
        assert_eq!((s.state, s.frames_done), (RenderState::Done, 3));
        assert_eq!(s.finished.iter().map(|f| f.frame).collect::<Vec<_>>(), [1, 2, 3]);
        let second = core.frame_render(seq, 2).unwrap();
        let header = String::from_utf8_lossy(&core.image(second).unwrap()).into_owned();
        assert!(header.contains("frame=2") && header.contains("seed=3"), "the header names the frame");
        assert_eq!(core.film_bytes_held(None), 0, "finished frames drop their films");
        assert!(core.frame_render(seq, 9).unwrap_err().to_string().contains("no frame 9"));
    }

    #[test]
    fn frames_that_cannot_resume_keep_their_frame_numbers() {
        let dir = fresh_dir("sequence-unresumable");
        let seq = {
            let (mut core, still) = submitted(dir.path());
            core.cancel(still).unwrap();
            sequence(&mut core)
        };
        // Today's limit is below the frames' plans: each frame fails to resume, saying why.
        let mut config = CoreConfig::new(dir.path().to_path_buf());
        config.max_passes = 1;
        let mut core = Core::open(config).unwrap();
        let s = core.status_of(Target::Sequence(seq)).unwrap();
        assert_eq!((s.frames_failed, s.state), (3, RenderState::Failed));
        assert!(s.message.starts_with("frame 1: could not be resumed"), "{}", s.message);
        let second = core.frame_render(seq, 2).unwrap();
        assert_eq!(core.status(second).unwrap().frame, Some(2));
        assert!(core.image(second).unwrap_err().to_string().contains("failed"));
    }

    #[test]
    fn sequences_are_bounded_before_anything_is_stored() {
        let dir = fresh_dir("sequence-bounds");
        let (mut core, still) = submitted(dir.path());
        let mut req = request(&blake3::hash(SCENE).to_hex());
        for (frames, fps, says) in [
            ("1-100001", 24.0, "more than 100000"),
            ("3-1", 24.0, "runs backwards"),
            ("1-2", 0.0, "fps 0"),
            ("1-2", f64::NAN, "fps NaN"),
            // 4 tiles a frame: 2^20 frames would be 2^22 tiles, the limit; more is refused.
            ("0-99999", 1e6, ""),
        ] {
            (req.frames, req.fps) = (frames.into(), fps);
            match core.submit("", &req, 100, 1) {
                Err(e) => assert!(!says.is_empty() && e.to_string().contains(says), "{frames} {fps}: {e}"),
                Ok(t) => {
                    assert!(says.is_empty(), "{frames} {fps} was accepted");
                    assert!(core.prometheus().contains("tessera_pending_frames 100000"));
                    core.cancel_target(t).unwrap();
                    let s = core.status_of(t).unwrap();
                    assert_eq!((s.state, s.frames_queued), (RenderState::Cancelled, 0));
                    assert!(core.prometheus().contains("tessera_pending_frames 0"));
                    assert_eq!(core.lease("w", "w", 1, 0.0).unwrap().map(|j| j.render_id), Some(still));
                }
            }
        }
        core.cancel(still).unwrap();
        // 512 x 512 in 16-pixel tiles is 1024 tiles a frame: 4097 frames pass the limit.
        req.setup.settings = RenderSettings { width: 512, height: 512, ..settings() };
        (req.frames, req.fps) = ("0-4096".into(), 24.0);
        let e = core.submit("", &req, 100, 1).unwrap_err().to_string();
        assert!(e.contains("4097 frames of 1024 tiles"), "{e}");
    }

    #[test]
    fn adaptive_rounds_replay_identically_after_a_restart() {
        let dir = fresh_dir("adaptive");
        let scene = furnace();
        let (id, budgets_before) = {
            let (mut core, id) = submitted(dir.path());
            work(&mut core, &scene, 6);
            assert_eq!(core.status(id).unwrap().state, RenderState::Running, "restart mid-render");
            (id, core.renders[&id].budget.clone())
        };
        assert!(budgets_before.iter().any(|&b| b > 1), "some tile went past its first round: {budgets_before:?}");
        let mut core = Core::open(CoreConfig::new(dir.path().to_path_buf())).unwrap();
        assert_eq!(core.renders[&id].budget, budgets_before, "replayed rounds differ");
        work(&mut core, &scene, 100_000);
        let status = core.status(id).unwrap();
        assert_eq!(status.state, RenderState::Done);
        // The same render straight through, without a restart, decides the same budgets.
        let straight_dir = fresh_dir("straight");
        let (mut straight, id2) = submitted(straight_dir.path());
        work(&mut straight, &scene, 100_000);
        assert_eq!(straight.renders[&id2].budget, core.renders[&id].budget);
        assert!(straight.renders[&id2].film == core.renders[&id].film, "films differ");
    }

    #[test]
    fn deferred_writes_touch_no_store_until_made_and_then_survive_a_restart() {
        let dir = fresh_dir("deferred");
        let hash = blake3::hash(SCENE).to_hex().to_string();
        let store = || Store::reader(dir.path()).unwrap();
        let writes = {
            let mut core = Core::open(CoreConfig::new(dir.path().to_path_buf())).unwrap();
            core.defer_writes();
            core.put_scene(&hash, SCENE).unwrap();
            let first = core.submit("", &request(&hash), 100, 1).unwrap().id();
            let second = core.submit("", &request(&hash), 100, 1).unwrap().id();
            core.cancel(first).unwrap();
            assert_eq!((first, second), (1, 2), "ids are the core's, given in order");
            assert!(store().renders().unwrap().is_empty() && !store().has_scene(&hash).unwrap(), "nothing written yet");
            core.take_writes()
        };
        let kinds: Vec<String> =
            writes.iter().map(|w| format!("{w:?}").split([' ', '(']).next().unwrap().into()).collect();
        assert_eq!(kinds, ["Scene", "Renders", "Renders", "State", "CollectScenes"], "in the order decided");
        for w in &writes {
            store().apply(w).unwrap();
        }
        let core = Core::open(CoreConfig::new(dir.path().to_path_buf())).unwrap();
        let states: Vec<RenderState> = [1, 2].map(|id| core.status(id).unwrap().state).to_vec();
        assert_eq!(states, [RenderState::Cancelled, RenderState::Running]);
        assert_eq!(core.next_id, 3, "ids go on after the stored ones");
    }

    #[test]
    fn finished_renders_reopen_without_their_film_and_images_survive() {
        let dir = fresh_dir("finished");
        let scene = furnace();
        let (id, image, status) = {
            let (mut core, id) = submitted(dir.path());
            work(&mut core, &scene, 100_000);
            (id, core.image(id).unwrap(), core.status(id).unwrap())
        };
        let mut core = Core::open(CoreConfig::new(dir.path().to_path_buf())).unwrap();
        assert_eq!(core.renders[&id].film.width, 0, "no film is rebuilt for a finished render");
        let reopened = core.status(id).unwrap();
        assert_eq!(
            (reopened.samples_done, reopened.passes_done, reopened.passes_total),
            (status.samples_done, status.passes_done, status.passes_total)
        );
        assert_eq!(core.image(id).unwrap(), image);
        std::fs::remove_file(dir.path().join("renders").join(format!("{id}.exr"))).unwrap();
        assert_eq!(core.image(id).unwrap(), image, "a lost image is rebuilt from the stored results");
    }

    #[test]
    fn a_forged_sample_count_is_refused_and_the_lease_stays_live() {
        let dir = fresh_dir("forged");
        let scene = furnace();
        let (mut core, id) = submitted(dir.path());
        let (job, sums) = render_job(&mut core, &scene).expect("a job");
        let mut forged = sums.clone();
        // n + dropped wraps a u64 to the expected count.
        let expected = forged.pixels[0].n;
        forged.pixels[0].n = u64::MAX;
        forged.pixels[0].dropped = expected + 1;
        let e = core.complete("w", &job.lease_id.to_string(), &encode_tile_sums(&forged)).unwrap_err();
        assert!(matches!(e, CoreError::Invalid(_)), "{e}");
        assert_eq!(core.status(id).unwrap().samples_done, 0, "nothing merged");
        assert_eq!(core.complete("w", &job.lease_id.to_string(), &encode_tile_sums(&sums)).unwrap(), Outcome::Merged);
    }

    #[test]
    fn costly_renders_are_refused_before_anything_is_stored() {
        let dir = fresh_dir("costly");
        let hash = blake3::hash(SCENE).to_hex().to_string();
        let mut core = Core::open(CoreConfig::new(dir.path().to_path_buf())).unwrap();
        core.put_scene(&hash, SCENE).unwrap();
        // 256 x 256 in 1 x 1 tiles of 1-sample passes at 4096 spp: 268 M passes.
        let mut req = request(&hash);
        req.setup.settings = RenderSettings { width: 256, height: 256, ..settings() };
        (req.tile_size, req.pass_spp, req.spp, req.max_spp, req.target_error) = (1, 1, 4096, 0, 0.0);
        let e = core.submit("", &req, 100, 1).unwrap_err().to_string();
        assert!(e.contains("268435456 passes") && e.contains("over the limit"), "{e}");
        // Films: two 2048 x 2048 renders (512 MiB of sums each) fit under an 800 MiB limit one at a time, not together.
        let mut config = CoreConfig::new(dir.path().to_path_buf());
        config.max_film_bytes = 800 << 20;
        drop(core);
        let mut core = Core::open(config).unwrap();
        req = request(&hash);
        req.setup.settings = RenderSettings { width: 2048, height: 2048, ..settings() };
        let first = core.submit("", &req, 100, 1).unwrap().id();
        let e = core.submit("", &req, 100, 1).unwrap_err().to_string();
        assert!(e.contains("--max-film-bytes"), "{e}");
        core.cancel(first).unwrap();
        assert_eq!(core.store.renders().unwrap().len(), 1, "refused renders are not stored");
    }

    #[test]
    fn a_flipped_bit_in_a_stored_result_is_dropped_and_rendered_again() {
        let dir = fresh_dir("bitflip");
        let scene = furnace();
        let id = {
            let (mut core, id) = submitted(dir.path());
            work(&mut core, &scene, 6);
            id
        };
        let db = rusqlite::Connection::open(dir.path().join("tessera.db")).unwrap();
        let (rowid, mut sums): (i64, Vec<u8>) = db
            .query_row("SELECT rowid, sums FROM results ORDER BY rowid LIMIT 1", [], |r| Ok((r.get(0)?, r.get(1)?)))
            .unwrap();
        let last = sums.len() - 1;
        sums[last] ^= 0x01; // still decodes, to a different sum
        db.execute("UPDATE results SET sums = ?1 WHERE rowid = ?2", rusqlite::params![sums, rowid]).unwrap();
        drop(db);
        let mut core = Core::open(CoreConfig::new(dir.path().to_path_buf())).unwrap();
        work(&mut core, &scene, 100_000);
        assert_eq!(core.status(id).unwrap().state, RenderState::Done);
        let straight_dir = fresh_dir("bitflip-straight");
        let (mut straight, id2) = submitted(straight_dir.path());
        work(&mut straight, &scene, 100_000);
        assert!(straight.renders[&id2].film == core.renders[&id].film, "the corrupt result was merged");
    }

    #[test]
    fn a_render_that_cannot_resume_fails_and_the_rest_resume() {
        let dir = fresh_dir("unresumable");
        let (broken, fine) = {
            let (mut core, broken) = submitted(dir.path());
            let fine = core.submit("", &request(blake3::hash(SCENE).to_hex().as_ref()), 100, 1).unwrap().id();
            (broken, fine)
        };
        let db = rusqlite::Connection::open(dir.path().join("tessera.db")).unwrap();
        db.execute("UPDATE renders SET settings = x'ff' WHERE id = ?1", [broken]).unwrap();
        drop(db);
        for _ in 0..2 {
            let core = Core::open(CoreConfig::new(dir.path().to_path_buf())).unwrap();
            let status = core.status(broken).unwrap();
            assert_eq!(status.state, RenderState::Failed);
            assert!(status.message.contains("could not be resumed"), "{}", status.message);
            assert_eq!(core.status(fine).unwrap().state, RenderState::Running);
        }
    }

    #[test]
    fn an_empty_database_beside_render_images_is_refused() {
        let dir = fresh_dir("emptydb");
        let scene = furnace();
        {
            let (mut core, _) = submitted(dir.path());
            work(&mut core, &scene, 100_000);
        }
        for f in ["tessera.db-wal", "tessera.db-shm"] {
            let _ = std::fs::remove_file(dir.path().join(f));
        }
        std::fs::write(dir.path().join("tessera.db"), b"").unwrap();
        let e = Core::open(CoreConfig::new(dir.path().to_path_buf())).err().expect("refused").to_string();
        assert!(e.contains("is empty (0 bytes)") && e.contains("Restore it from a backup"), "{e}");
        std::fs::write(dir.path().join("tessera.db"), b"not a database, just junk bytes of some length").unwrap();
        let e = Core::open(CoreConfig::new(dir.path().to_path_buf())).err().expect("refused").to_string();
        assert!(e.contains("not a readable SQLite database"), "{e}");
    }

    #[test]
    fn names_are_bounded_and_listings_come_in_pages() {
        let dir = fresh_dir("names");
        let hash = blake3::hash(SCENE).to_hex().to_string();
        let (mut core, _) = submitted(dir.path());
        let mut req = request(&hash);
        req.scene_name = "x".repeat(4 << 20);
        assert!(core.submit("", &req, 100, 1).unwrap_err().to_string().contains("over the 1024-byte limit"));
        req.scene_name = "evil\x1b[2J".into();
        assert!(core.submit("", &req, 100, 1).unwrap_err().to_string().contains("control characters"));
        assert!(core.lease(&"w".repeat(2000), "w", 1, 0.0).is_err());
        req.scene_name = "fine".into();
        for _ in 0..4 {
            core.submit("", &req, 100, 1).unwrap();
        }
        let (page, more) = core.list_renders(0, 2, |_| true);
        assert_eq!((page.iter().map(|r| r.render_id.as_str()).collect::<Vec<_>>(), more), (vec!["1", "2"], true));
        let (page, more) = core.list_renders(4, 2, |_| true);
        assert_eq!((page.len(), more), (1, false));
    }

    #[test]
    fn ignored_results_are_counted_by_reason() {
        let dir = fresh_dir("ignored");
        let scene = furnace();
        let (mut core, _) = submitted(dir.path());
        let (job, sums) = render_job(&mut core, &scene).expect("a job");
        let bytes = encode_tile_sums(&sums);
        assert_eq!(core.complete("w", &job.lease_id.to_string(), &bytes).unwrap(), Outcome::Merged);
        assert_eq!(
            core.complete("w", &job.lease_id.to_string(), &bytes).unwrap(),
            Outcome::Ignored(Ignored::Duplicate)
        );
        assert_eq!(core.complete("w", "12345", &bytes).unwrap(), Outcome::Ignored(Ignored::Unknown));
        assert_eq!(core.complete("w", "not-a-lease", &bytes).unwrap(), Outcome::Ignored(Ignored::Unknown));
        let text = core.prometheus();
        assert!(text.contains("tessera_results_ignored_total{reason=\"duplicate\"} 1\n"), "{text}");
        assert!(text.contains("tessera_results_ignored_total{reason=\"unknown_lease\"} 2\n"), "{text}");
        assert!(text.contains("tessera_results_ignored_total{reason=\"late\"} 0\n"), "{text}");
    }

    /// A core with the furnace stored, the test render submitted (all passes fixed, no
    /// adaptive rounds) and the failure policy's limits given.
    fn submitted_with(config: CoreConfig) -> (Core, i64) {
        let hash = blake3::hash(SCENE).to_hex().to_string();
        let mut core = Core::open(config).unwrap();
        core.put_scene(&hash, SCENE).unwrap();
        let mut req = request(&hash);
        (req.target_error, req.max_spp) = (0.0, 0);
        let id = core.submit("", &req, 100, 1).unwrap().id();
        (core, id)
    }

    #[test]
    fn failed_jobs_block_their_worker_then_fail_the_render_and_retry_finishes_it() {
        let dir = fresh_dir("failures");
        let mut config = CoreConfig::new(dir.path().to_path_buf());
        (config.max_attempts, config.block_after) = (3, 2);
        let (mut core, id) = submitted_with(config);
        for _ in 0..2 {
            let job = core.lease("bad", "bad", 1, 0.0).unwrap().expect("a job");
            core.fail("bad", &job.lease_id.to_string(), "out of memory").unwrap();
        }
        assert!(core.lease("bad", "bad", 1, 0.0).unwrap().is_none(), "a worker that failed twice is blocked");
        let status = core.status(id).unwrap();
        assert_eq!(status.state, RenderState::Running);
        assert!(status.message.contains("out of memory"), "{}", status.message);
        // The same passes come back first; their third failure fails the render.
        let job = core.lease("bad2", "bad2", 1, 0.0).unwrap().expect("another worker gets the job");
        assert_eq!(job.first_pass, 0);
        core.fail("bad2", &job.lease_id.to_string(), "scene did not load").unwrap();
        let status = core.status(id).unwrap();
        assert_eq!(status.state, RenderState::Failed);
        assert!(
            status.message.contains("failed 3 times") && status.message.contains("scene did not load"),
            "{}",
            status.message
        );
        assert!(core.lease("good", "good", 1, 0.0).unwrap().is_none(), "a failed render hands out nothing");
        assert!(matches!(core.image(id), Err(CoreError::NotReady(_))));
        // Retried, it finishes with the same bits as a render that never failed.
        core.retry(id).unwrap();
        assert!(core.retry(id).is_err(), "a running render is not retried");
        let scene = furnace();
        work(&mut core, &scene, 100_000);
        assert_eq!(core.status(id).unwrap().state, RenderState::Done);
        let straight_dir = fresh_dir("failures-straight");
        let (mut straight, id2) = submitted_with(CoreConfig::new(straight_dir.path().to_path_buf()));
        work(&mut straight, &scene, 100_000);
        assert!(straight.renders[&id2].film == core.renders[&id].film, "films differ");
    }

    #[test]
    fn expired_leases_count_as_attempts_and_failures_survive_a_restart() {
        let dir = fresh_dir("expiries");
        let mut config = CoreConfig::new(dir.path().to_path_buf());
        (config.max_attempts, config.lease_ms) = (2, 1);
        let (mut core, id) = submitted_with(config);
        for _ in 0..3 {
            let _ = core.lease("w", "w", 1, 0.0).unwrap();
            std::thread::sleep(std::time::Duration::from_millis(5));
        }
        let status = core.status(id).unwrap();
        assert_eq!(status.state, RenderState::Failed);
        assert!(status.message.contains("lease expired"), "{}", status.message);
        drop(core);
        let mut core = Core::open(CoreConfig::new(dir.path().to_path_buf())).unwrap();
        let status = core.status(id).unwrap();
        assert_eq!(status.state, RenderState::Failed, "still failed after a restart");
        assert!(status.message.contains("lease expired"), "{}", status.message);
        core.retry(id).unwrap();
        assert_eq!(core.status(id).unwrap().state, RenderState::Running);
    }

    /// Results committed outside the lock merge in whatever order their commits finish. Leased
    /// in batches of five, accepted together and merged in reverse, an adaptive render decides the
    /// same rounds and ends with the same film as one merged as it goes: a tile's next round is
    /// decided only once the film holds all of its current one.
    #[test]
    fn results_merged_out_of_order_give_the_same_rounds_and_film() {
        let scene = furnace();
        let dir = fresh_dir("reordered");
        let (mut core, id) = submitted(dir.path());
        loop {
            let mut batch = Vec::new();
            while batch.len() < 5 {
                let Some((job, sums)) = render_job(&mut core, &scene) else { break };
                let bytes = encode_tile_sums(&sums);
                let accepted = core.accept("w", &job.lease_id.to_string(), decode_tile_sums(&bytes)).unwrap().unwrap();
                batch.push((accepted, bytes));
            }
            if batch.is_empty() {
                break;
            }
            for (accepted, bytes) in batch.into_iter().rev() {
                core.store.put_result(id, &accepted.stored(), &bytes).unwrap();
                if let Some(f) = core.merge(accepted, Ok(())).unwrap() {
                    f.write().unwrap();
                    core.image_written(f.id, Ok(())).unwrap();
                }
            }
        }
        assert_eq!(core.status(id).unwrap().state, RenderState::Done);
        let straight_dir = fresh_dir("reordered-straight");
        let (mut straight, id2) = submitted(straight_dir.path());
        work(&mut straight, &scene, 100_000);
        assert_eq!(straight.renders[&id2].budget, core.renders[&id].budget, "rounds differ");
        assert!(straight.renders[&id2].film == core.renders[&id].film, "films differ");
        assert!(core.renders[&id].budget.iter().any(|&b| b > 1), "no tile went past its first round");
    }

    #[test]
    fn scenes_no_render_needs_are_collected_after_a_grace_period() {
        let dir = fresh_dir("scene-gc");
        let scene = furnace();
        let (mut core, done) = submitted(dir.path());
        let other = b"tessera-builtin:cornell-box".to_vec();
        let other_hash = blake3::hash(&other).to_hex().to_string();
        core.put_scene(&other_hash, &other).unwrap();
        work(&mut core, &scene, 100_000);
        assert_eq!(core.status(done).unwrap().state, RenderState::Done);
        // Both scenes are within their grace period: kept.
        core.collect_scenes();
        assert!(core.store.has_scene(&other_hash).unwrap());
        // An hour later the unused upload and the finished render's scene go; a running render's
        // scene stays however old.
        let running = core.submit("", &request(blake3::hash(SCENE).to_hex().as_ref()), 100, 1).unwrap().id();
        let db = rusqlite::Connection::open(dir.path().join("tessera.db")).unwrap();
        db.execute("UPDATE scenes SET stored_at = stored_at - 7200", []).unwrap();
        core.collect_scenes();
        assert!(!core.store.has_scene(&other_hash).unwrap(), "an unused scene was kept");
        assert!(core.store.has_scene(&blake3::hash(SCENE).to_hex()).unwrap(), "a running render's scene was deleted");
        core.cancel(running).unwrap();
        assert!(!core.store.has_scene(&blake3::hash(SCENE).to_hex()).unwrap(), "a cancelled render keeps its scene");
    }
}
