//! The core's own words for what it is asked and what it answers: a render submitted, a job
//! handed out, a render's or a worker's status. The gRPC service turns protobuf messages into
//! these and back (`wire.rs`); the core never sees a protobuf type.

use tessera_render::glam::Vec3;
use tessera_render::{RenderSettings, Tile};

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
}

/// A moment of a scene's animation (see `tessera_scene::animation`).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Pose {
    /// Which animations play, as `animation::Choice::to_wire` writes it.
    pub animation: String,
    /// Seconds from the animation's start.
    pub time: f32,
    /// A sequence's frame: its number, the frames per second and the sequence's seed (labels
    /// only: the frame's own seed is in the render settings).
    pub frame: Option<u32>,
    pub fps: f64,
    pub sequence_seed: u64,
}

/// The environment map a scene's package carries, as a render uses it.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct EnvironmentMap {
    /// The file's name as the client gave it, and its BLAKE3 hash (for image headers).
    pub name: String,
    pub hash: String,
    pub strength: f32,
    pub rotate_degrees: f32,
}

/// What a render's pixels depend on besides its scene and its plan.
#[derive(Clone, Debug, PartialEq)]
pub struct Setup {
    pub settings: RenderSettings,
    /// The constant environment (ignored where `environment_map` is given).
    pub environment: Vec3,
    /// The scene at a moment of its animation; `None`: at rest.
    pub pose: Option<Pose>,
    pub environment_map: Option<EnvironmentMap>,
    /// A material variant of the scene, by name; `None`: the file's own materials.
    pub variant: Option<String>,
}

/// A render (or a sequence of frames) as submitted.
#[derive(Clone, Debug, PartialEq)]
pub struct Submission {
    pub scene_hash: String,
    /// For listings.
    pub scene_name: String,
    pub setup: Setup,
    pub spp: u32,
    pub tile_size: u32,
    pub pass_spp: u32,
    pub priority: i32,
    /// Adaptive budgets: the relative error to reach per tile (0: off), from `min_spp` up to
    /// `max_spp` (or `spp` when 0).
    pub target_error: f32,
    pub min_spp: u32,
    pub max_spp: u32,
    /// A sequence's frames (`plan::FrameList` syntax), each at frame / `fps` seconds; empty: one
    /// image.
    pub frames: String,
    pub fps: f64,
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
}
