//! The coordinator's state machine, synchronous and free of I/O: scenes, renders, the lease
//! table, the films being merged and the workers seen. It speaks its own types (`model.rs`;
//! the doors turn protobuf and JSON into them) and holds no store: [`Core::open`] reads one,
//! and every change it decides waits in [`Core::take_writes`] for the engine's writer. Its
//! verbs live one to a file: `open` (start and resume), `submit`, `lease` (jobs, heartbeats,
//! failures), `merge` (results and finished images), `control` (cancel, retry) and `views`
//! (what status, listings, the dashboard and metrics show), with `counts` keeping the sums
//! views read up to date as renders change.

mod control;
mod counts;
mod forecast;
mod lease;
mod merge;
mod notify;
mod open;
mod preview;
mod submit;
#[cfg(test)]
pub(crate) mod tests;
mod verify;
mod views;

pub use control::{Refinement, Steer};
pub use merge::{Accepted, Finished};
pub use notify::NotifyConfig;
pub use open::{Prepared, Resumed};
pub use submit::MAX_SEQUENCE_TILES;
pub use verify::{Blocked, REOPENED, Verdict};
pub use views::{FarmMetrics, PreviewOf, RenderDetail, TileView};

use crate::leases::{Ignored, LeaseTable};
use crate::model::{RenderState, Setup};
use crate::store::{LogOf, StoreError, StoredRender, Write};
use lease::Worker;
use std::collections::{BTreeMap, HashMap, HashSet};
use std::path::PathBuf;
use std::time::Instant;
use tessera_film::{ErrorEstimate, Film};
use tessera_render::plan::RenderPlan;
use tessera_request::limits::{MAX_MESSAGE_BYTES, clip};

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
    /// The caller may not do this, and asking again will not change that (a blocked worker).
    #[error("{0}")]
    Refused(String),
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
    /// Most triangles a scene may draw (every instance counted).
    pub max_triangles: u64,
    /// Most memory a worker may need to build and render a scene (`tessera_scene::Census::memory`),
    /// in bytes: a small file may instance a mesh into millions of triangles.
    pub max_scene_memory: u64,
    pub max_pixels: u64,
    pub max_spp: u32,
    pub max_active_renders: usize,
    /// Most tiles x passes one render may plan.
    pub max_passes: u64,
    /// Most bytes the films of all live renders may take together (a pixel's sums are
    /// [`FILM_BYTES_PER_PIXEL`] bytes, [`FEATURE_BYTES_PER_PIXEL`] more with feature layers).
    pub max_film_bytes: u64,
    /// fsync every committed result (survives power loss, not just the process dying).
    pub fsync: bool,
    /// A pass whose job failed or whose lease expired this many times fails its render.
    pub max_attempts: u32,
    /// A worker that reported this many failed jobs of a render gets no more of its jobs.
    pub block_after: u32,
    /// Most frames of sequences waiting or rendering at once, over the farm: each holds about
    /// [`QUEUED_FRAME_BYTES`] until it finishes.
    pub max_queued_frames: u64,
    /// The fraction of jobs rendered again by a second worker and compared (`--verify`): 0
    /// checks none, 1 every one.
    pub verify: f64,
    /// Where notifications may go, and how they are signed.
    pub notify: NotifyConfig,
    /// What denoises finished images that asked for it (`--denoise`), outside the state lock;
    /// `Err(why)`: this coordinator cannot, and refuses such renders saying why.
    pub denoiser: Result<SharedDenoiser, String>,
}

/// A denoiser shared by the renders that finish ([`tessera_film::Denoiser`]).
#[derive(Clone)]
pub struct SharedDenoiser(pub std::sync::Arc<dyn tessera_film::Denoiser>);

impl std::fmt::Debug for SharedDenoiser {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0.name())
    }
}

/// Memory a frame of a sequence holds on the coordinator while it waits (its row, settings,
/// plan and lease queue): measured with `tessera bench coordinator --sequence 100000`.
pub const QUEUED_FRAME_BYTES: u64 = 2400;
/// Memory one pixel of a film takes: its exact sums.
pub const FILM_BYTES_PER_PIXEL: u64 = size_of::<tessera_render::PixelSums>() as u64;
/// Memory one pixel's feature layers add to a film that sums them (`--aov`).
pub const FEATURE_BYTES_PER_PIXEL: u64 = size_of::<tessera_render::FeatureSums>() as u64;

/// Memory the film of a render with `settings` takes: its pixels' sums, and their feature
/// layers' when it has them.
pub fn film_bytes(settings: &tessera_render::RenderSettings) -> u64 {
    let per_pixel = FILM_BYTES_PER_PIXEL + if settings.features { FEATURE_BYTES_PER_PIXEL } else { 0 };
    settings.width as u64 * settings.height as u64 * per_pixel
}
/// Most tiles one render may have (a 1024 x 1024 image in 1 x 1 tiles).
pub const MAX_TILES: u64 = 1 << 20;
/// Workers remembered at once; one not seen for [`WORKER_FORGET_LEASES`] lease times is forgotten.
pub const MAX_WORKERS: usize = 1 << 16;
const WORKER_FORGET_LEASES: u64 = 10;

/// Refuses a name that is too long or carries control characters (the request's own rule,
/// `tessera_request::limits::check_name`): worker ids and names, which arrive outside a request.
pub fn check_name(what: &str, name: &str) -> Result<(), CoreError> {
    tessera_request::limits::check_name(what, name).map_err(CoreError::Invalid)
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
            max_scene_memory: 8 << 30,
            max_pixels: tessera_request::limits::MAX_PIXELS,
            max_spp: tessera_request::limits::MAX_SPP,
            max_active_renders: 64,
            max_passes: 1 << 26,
            max_film_bytes: 8 << 30,
            fsync: false,
            max_attempts: 3,
            block_after: 3,
            verify: 0.0,
            max_queued_frames: 1_000_000,
            notify: Default::default(),
            denoiser: Err("this coordinator has no denoiser".into()),
        }
    }
}

struct RenderRuntime {
    /// Passes scheduled per tile (adaptive renders grow these round by round).
    budget: Vec<u32>,
    /// The budget summed.
    passes_total: u64,
    stored: StoredRender,
    /// What its pixels depend on: settings, environment, pose, map, variant.
    setup: Setup,
    /// Where it may run: its pool and requirements.
    placement: tessera_request::placement::Placement,
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
    /// From its first job to when it left the running state.
    span: Span,
    state: RenderState,
    message: String,
    /// The error estimate when the render finished (its film is dropped once the image is
    /// written).
    final_error: ErrorEstimate,
    /// True while its image is being written: the film is the writer's until then.
    writing: bool,
    /// The workers whose results it accepted since it was installed: to be rendered again
    /// should one of them be found lying.
    workers: HashSet<String>,
    /// Each tile's relative error as last computed for the dashboard, with the passes merged
    /// then: recomputed only for tiles that have changed since.
    tile_errors: Vec<(u32, f32)>,
    /// An adaptive render's passes each tile is predicted to end with, from its error when its
    /// last round was judged (`plan::predicted_passes`), and with that error
    /// `plan::ERROR_SPREAD` times lower and higher; 0 before its first judgement. For the ETA
    /// and the quote only.
    predicted: Vec<[u32; 3]>,
    /// The status's error estimate and when it was made: made again at most every
    /// [`ERROR_ESTIMATE_EVERY`], however many watch (each costs 16,384 pixels read under the lock).
    error_estimate: std::cell::Cell<Option<(Instant, ErrorEstimate)>>,
}

impl RenderRuntime {
    /// The passes it is expected to end with, for its ETA: a fixed render's budget; an adaptive
    /// render's predicted rounds, tile by tile, where a tile not judged yet is expected to end
    /// as the judged ones do on average (at the render's full samples before any is judged).
    fn passes_expected(&self) -> u64 {
        if self.stored.target_error <= 0.0 || self.state != RenderState::Running || self.writing {
            return self.passes_total;
        }
        self.tile_passes_expected(0).map(u64::from).sum()
    }

    /// Each tile's passes as [`Self::passes_expected`] expects them, by prediction `k`: 0 the
    /// pilot's error, 1 and 2 that error [`tessera_render::plan::ERROR_SPREAD`] times lower and
    /// higher. At least the passes already scheduled.
    fn tile_passes_expected(&self, k: usize) -> impl Iterator<Item = u32> + '_ {
        let judged: Vec<u64> = self.predicted.iter().filter(|p| p[k] > 0).map(|p| p[k] as u64).collect();
        let unjudged = match judged.len() {
            0 => self.plan.passes_per_tile(),
            n => judged.iter().sum::<u64>().div_ceil(n as u64) as u32,
        };
        self.budget.iter().enumerate().map(move |(t, &b)| {
            b.max(match self.predicted.get(t) {
                Some(p) if p[k] > 0 => p[k],
                _ => unjudged,
            })
        })
    }

    /// The state users see: a render reopened to render a blocked worker's results again is
    /// failed inside the core only until the engine's retry, which follows at once; its status
    /// (the CLI, the watch, the dashboard, notifications) shows it running all along, its message
    /// saying what it does. The farm's counts keep the core's state.
    fn shown_state(&self) -> RenderState {
        match self.state {
            RenderState::Failed if self.message.starts_with(REOPENED) => RenderState::Running,
            state => state,
        }
    }
}

/// How long a running render's error estimate is reused.
const ERROR_ESTIMATE_EVERY: std::time::Duration = std::time::Duration::from_millis(500);

/// A film's relative error, estimated from at most 16,384 evenly spread pixels (cheap enough
/// for the state lock, even for a 4K film), with its bound at `confidence` (0: none, the
/// bound is the estimate). The bound counts the pixels left out: its spread term is that of a
/// sample of pixels.
fn error_estimate(film: &Film, confidence: f32) -> ErrorEstimate {
    let confidence = if confidence > 0.0 { confidence as f64 } else { 0.5 };
    tessera_film::error_estimate(film.pixels.iter().step_by((film.pixels.len() / 16384).max(1)), confidence)
}

/// When a render or a sequence ran: from its first job to when it stopped running, in seconds
/// since the Unix epoch. A render's is stored (`renders.started_at`, `ended_at`), so that it
/// survives restarts; its time in the queue before is not counted. A retry runs it again: its
/// elapsed time goes on from its first start.
#[derive(Clone, Copy, Debug, Default)]
struct Span {
    started_at: Option<f64>,
    ended_at: Option<f64>,
}

impl Span {
    /// A span as stored: 0 is "not yet".
    fn stored(started_at: f64, ended_at: f64) -> Self {
        Span { started_at: (started_at > 0.0).then_some(started_at), ended_at: (ended_at > 0.0).then_some(ended_at) }
    }

    /// It runs from now, unless it started before; returns the start if it is new.
    fn start(&mut self) -> Option<f64> {
        if self.started_at.is_some() {
            return None;
        }
        let now = unix_seconds();
        self.started_at = Some(now);
        self.ended_at = None;
        Some(now)
    }

    /// It ran from `at` at the latest (a sequence: its earliest frame's start).
    fn started_by(&mut self, at: f64) {
        self.started_at = Some(self.started_at.map_or(at, |s| s.min(at)));
    }

    /// Notes whether it is live now (queued or running): the first time it is not, its
    /// elapsed time stops; if it is again (a retry), it goes on.
    fn running(&mut self, running: bool) {
        match (running, self.ended_at) {
            (true, Some(_)) => self.ended_at = None,
            (false, None) if self.started_at.is_some() => self.ended_at = Some(unix_seconds()),
            _ => {}
        }
    }

    /// Seconds it ran: from its start to now, or to when it stopped; 0 before it started.
    fn seconds(&self) -> f64 {
        match self.started_at {
            Some(start) => (self.ended_at.unwrap_or_else(unix_seconds) - start).max(0.0),
            None => 0.0,
        }
    }

    /// When it started, while it runs.
    fn started_at(&self) -> Option<f64> {
        self.started_at.filter(|_| self.ended_at.is_none())
    }
}

/// Now, in seconds since the Unix epoch, to the millisecond.
pub fn unix_seconds() -> f64 {
    let ms = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_millis());
    ms as f64 / 1000.0
}

impl Core {
    /// Adds a line to render `id`'s stored log (and, for a frame, to its sequence's, naming the
    /// frame), made printable and cut to [`MAX_MESSAGE_BYTES`]: a worker's error text is
    /// quoted there.
    pub(super) fn note(&mut self, id: i64, line: impl Into<String>) {
        let line = clip(&tessera_request::printable(&line.into()), MAX_MESSAGE_BYTES).into_owned();
        let at = unix_seconds();
        let sequence =
            self.renders.get(&id).map(|r| r.stored.sequence).or_else(|| self.failed.get(&id).map(|s| s.sequence));
        if let Some(seq) = sequence.filter(|&s| s != 0) {
            let frame = self.frame_of(id).map_or(String::new(), |f| format!("frame {f}: "));
            self.write(Write::Log { of: LogOf { id: seq, sequence: true }, at, line: format!("{frame}{line}") });
        }
        self.write(Write::Log { of: LogOf { id, sequence: false }, at, line });
    }

    /// Adds a line to the log of `target`: a render's, or a sequence's own.
    pub(super) fn note_target(&mut self, target: Target, line: impl Into<String>) {
        match target {
            Target::Render(id) => self.note(id, line),
            Target::Sequence(seq) => {
                let line = clip(&tessera_request::printable(&line.into()), MAX_MESSAGE_BYTES).into_owned();
                self.write(Write::Log { of: LogOf { id: seq, sequence: true }, at: unix_seconds(), line });
            }
        }
    }
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

pub struct Core {
    config: CoreConfig,
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
    /// Changes to the store decided and not yet taken by the engine ([`Core::take_writes`]).
    writes: Vec<Write>,
    /// Renders and sequences that ended, to be told to their notification URLs
    /// ([`Core::take_ended`]).
    ended: Vec<crate::model::Ended>,
    /// Sequences rendering their previews first, and preview images to write.
    previewing: HashMap<i64, preview::Previewing>,
    previews: Vec<Finished>,
    epoch: Instant,
    pub metrics: Metrics,
    /// Sums kept up to date as renders change (`counts.rs`).
    counts: counts::Counts,
    /// Merged results waiting for a second worker's (`verify.rs`), by (render, tile, first pass).
    checks: BTreeMap<(i64, u32, u32), verify::Check>,
    /// Workers blocked for the farm, and why: their results disagreed with two others'.
    blocked: HashMap<String, String>,
    /// Renders read to count them ([`Core::share_now`]), for tests of what views cost.
    #[cfg(test)]
    reads: std::cell::Cell<u64>,
}

/// What became of a worker's result.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Outcome {
    Merged,
    Ignored(Ignored),
}

/// Counters since the coordinator started, for `/metrics` (with [`FarmMetrics`]).
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
    /// Results rendered again by a second (or third) worker and compared.
    pub results_checked: u64,
    /// Checks whose result disagreed with the result checked.
    pub results_disputed: u64,
}

const RUNNING: &str = "running";
const DONE: &str = "done";
const CANCELLED: &str = "cancelled";
const FAILED: &str = "failed";
/// A scene no render needs is kept this long after its upload (for the submit that follows).
const SCENE_GRACE_SECONDS: i64 = 3600;

/// Refuses scene bytes whose BLAKE3 hash is not the one claimed.
pub fn check_scene_hash(claimed_hash: &str, bytes: &[u8]) -> Result<(), CoreError> {
    let actual = blake3::hash(bytes).to_hex().to_string();
    if actual != claimed_hash {
        return Err(CoreError::Invalid(format!("scene hash mismatch: claimed {claimed_hash}, content is {actual}")));
    }
    Ok(())
}

impl Core {
    /// The changes to the store decided since the last call, in order: to be committed in this
    /// order (the engine queues them for its writer before it lets go of the lock).
    pub fn take_writes(&mut self) -> Vec<Write> {
        std::mem::take(&mut self.writes)
    }

    /// Records a change to the store, for the engine to commit.
    fn write(&mut self, w: Write) {
        self.writes.push(w);
    }

    /// Deletes the stored scenes that no running or failed render needs (after an hour's grace),
    /// so that uploads do not pile up for ever.
    fn collect_scenes(&mut self) {
        self.write(Write::CollectScenes { grace_seconds: SCENE_GRACE_SECONDS });
    }

    fn now_ms(&self) -> u64 {
        self.epoch.elapsed().as_millis() as u64
    }

    pub fn config(&self) -> &CoreConfig {
        &self.config
    }

    /// Counts an ignored result by its reason.
    fn ignore(&mut self, why: Ignored) -> Ignored {
        *self.metrics.results_ignored.entry(why).or_default() += 1;
        why
    }

    /// Where render `id`'s image is written.
    pub fn exr_path(&self, id: i64) -> PathBuf {
        self.config.data_dir.join("renders").join(format!("{id}.exr"))
    }
}
