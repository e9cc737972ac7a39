//! The core's own words for what it answers: a job handed out, a render's or a worker's status.
//! What it is asked (a [`Submission`], each render's [`Setup`]) is `tessera-request`'s, the same
//! type the client and the worker use. The doors turn protobuf and JSON into these and back; the
//! core never sees a protobuf type.

use tessera_render::Tile;
pub use tessera_request::{Adaptive, EnvironmentMap, Frames, Pose, Setup, Submission};

/// Where a render stands.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum RenderState {
    #[default]
    Running,
    Done,
    Cancelled,
    Failed,
}

impl RenderState {
    /// Its name as `status` and the dashboard show it.
    pub fn name(self) -> &'static str {
        match self {
            RenderState::Running => "running",
            RenderState::Done => "done",
            RenderState::Cancelled => "cancelled",
            RenderState::Failed => "failed",
        }
    }

    /// It stopped before its end (failed or cancelled): a retry resumes it.
    pub fn stopped(self) -> bool {
        matches!(self, RenderState::Failed | RenderState::Cancelled)
    }
}

/// A worker asking for work: who it is, how fast it renders, and where it belongs (its pool,
/// empty for none, and its tags: `tessera worker --pool --tag`, with what it found at start).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Offer {
    pub worker_id: String,
    pub name: String,
    pub threads: u32,
    /// Measured, 0 when not yet known.
    pub samples_per_second: f64,
    pub pool: String,
    pub tags: Vec<tessera_request::placement::Tag>,
}

impl Offer {
    /// A one-thread worker of no pool and no tags, named as its id.
    pub fn plain(worker_id: &str) -> Self {
        Offer { worker_id: worker_id.into(), name: worker_id.into(), threads: 1, ..Offer::default() }
    }
}

/// Passes of one tile leased to a worker.
#[derive(Clone, Debug, PartialEq)]
pub struct Job {
    pub lease_id: u64,
    pub render_id: i64,
    pub scene_hash: String,
    pub setup: Setup,
    pub tile: Tile,
    pub first_pass: u32,
    pub pass_count: u32,
    pub pass_spp: u32,
    /// Samples per pixel of the whole render (a tile's last pass may be shorter).
    pub spp: u32,
    pub lease_seconds: u32,
}

/// A finished frame of a sequence.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct FrameDone {
    pub frame: u32,
    pub render_id: String,
}

/// A render's (or a whole sequence's) status, as `tessera status` and `watch` show it.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RenderInfo {
    /// The render's id, or a sequence's (`s<id>`).
    pub render_id: String,
    pub scene_name: String,
    pub state: RenderState,
    pub passes_done: u64,
    pub passes_total: u64,
    pub samples_done: u64,
    pub samples_per_second: f64,
    /// The relative standard error of the pixel mean, estimated.
    pub error_estimate: f64,
    /// A render with a stated error (`--confidence`): the bound its true relative error is
    /// below with `confidence` (both 0 without one).
    pub error_bound: f64,
    pub confidence: f64,
    pub eta_seconds: f64,
    pub message: String,
    /// Samples merged per pixel so far, averaged over the image.
    pub mean_spp: f64,
    pub owner: String,
    /// A frame's sequence (`s<id>`; empty for a still), and its frame number.
    pub sequence_id: String,
    pub frame: Option<u32>,
    /// A sequence's frames by state.
    pub frames_total: u32,
    pub frames_done: u32,
    pub frames_running: u32,
    pub frames_queued: u32,
    pub frames_failed: u32,
    pub finished: Vec<FrameDone>,
    /// When it was submitted, first given to a worker, and ended (seconds since the Unix epoch;
    /// `None`: not yet). A sequence: its first frame's submission, its earliest start, and when
    /// its last frame ended.
    pub submitted_at: Option<f64>,
    pub started_at: Option<f64>,
    pub ended_at: Option<f64>,
    /// The name it was submitted with (empty: none).
    pub name: String,
    /// It is running and no worker is connected (none has asked for work within two lease
    /// times): its ETA means nothing.
    pub no_workers: bool,
    /// Its priority (a frame's is its sequence's): higher is served first.
    pub priority: i32,
    /// It is running and paused (`tessera pause`): it gets no new jobs until resumed.
    pub paused: bool,
    /// Where it may run, in words (empty: anywhere).
    pub placement: String,
    /// It is running, workers are connected, and none may take it (its pool or requirements).
    pub no_worker_fits: bool,
    /// A sequence with previews first: frames whose preview image is written (a watch's
    /// message: those since its previous one).
    pub previewed: Vec<FrameDone>,
    /// A running render's quote ([`crate::core::Core::forecast`]): filled in for one render's
    /// watch and steering, not for listings.
    pub quote: Option<Forecast>,
}

/// A render or a sequence that stopped running (done, failed or cancelled), to be told to the
/// URL it was submitted with.
#[derive(Clone, Debug, PartialEq)]
pub struct Ended {
    pub url: String,
    pub info: RenderInfo,
}

/// A worker as the coordinator last saw it.
#[derive(Clone, Debug, PartialEq)]
pub struct WorkerStatus {
    pub worker_id: String,
    pub name: String,
    pub threads: u32,
    pub samples_per_second: f64,
    /// Leases it holds now.
    pub leases: u32,
    pub seconds_since_seen: f64,
    /// The address its calls come from.
    pub host: String,
    /// Its results merged, and its jobs that failed.
    pub results: u64,
    pub failures: u64,
    /// The renders of the jobs it holds now.
    pub renders: Vec<i64>,
    pub state: WorkerState,
    /// The renders it gets no more jobs of: it failed `--block-after` of their jobs.
    pub blocked_from: Vec<i64>,
    /// Its pool (empty: none) and tags.
    pub pool: String,
    pub tags: Vec<tessera_request::placement::Tag>,
}

/// What a worker is doing, as far as the coordinator knows.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum WorkerState {
    /// It holds jobs.
    Busy,
    /// It asks for work and holds none.
    Idle,
    /// Not heard from for two lease times: it died, hangs or lost the network.
    Lost,
    /// It said goodbye (stopped cleanly).
    Stopped,
    /// Blocked for the farm: its results disagreed with two other workers' (`--verify`).
    Blocked,
}

impl WorkerState {
    pub fn name(self) -> &'static str {
        match self {
            WorkerState::Busy => "busy",
            WorkerState::Idle => "idle",
            WorkerState::Lost => "lost",
            WorkerState::Stopped => "stopped",
            WorkerState::Blocked => "blocked",
        }
    }
}

/// A running render's quote ([`crate::core::Core::forecast`]): the samples it is predicted to
/// take in all, with a range, from the tiles whose rounds were judged, and the speed of the live
/// workers that may take it.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Forecast {
    pub samples: u64,
    pub samples_low: u64,
    pub samples_high: u64,
    /// Samples merged so far.
    pub samples_done: u64,
    /// Tiles the prediction rests on, of all (all of a fixed render's: its samples are known).
    pub tiles_judged: usize,
    pub tiles: usize,
    /// Live workers that may take it and have a measured speed: their count, threads and
    /// samples per second together.
    pub workers: usize,
    pub threads: u64,
    pub samples_per_second: f64,
}
