//! What a user asks Tessera to render, as one type from end to end: the command line builds a
//! [`Submission`] (or, rendering here, a [`Setup`]), the client sends it, the coordinator stores
//! and plans it, and each job carries its [`Setup`] to a worker. `limits` defines its bounds
//! once; `wire` is its one conversion to and from the protocol (and the bytes the coordinator's
//! store keeps a setup in), where every number from the wire is checked; `Setup::header` writes
//! the image header, the same for `tessera render` and the farm.

pub mod limits;
pub mod placement;
pub mod wire;

use tessera_render::RenderSettings;
use tessera_render::glam::Vec3;
use tessera_render::plan::FrameList;
use tessera_scene::PoseAt;
use tessera_scene::animation::{Choice, header_lines};

/// Text as a terminal may show it: control characters (which would be escape sequences) and
/// invisible format characters (bidi overrides, which reorder what follows; zero-width ones)
/// written as escapes ([`limits::unprintable`]). Names a user gave (scenes, maps) are written so
/// into requests and image headers, and whatever a coordinator or a scene file says is printed so.
pub fn printable(text: &str) -> String {
    text.chars().map(|c| if limits::unprintable(c) { c.escape_default().to_string() } else { c.to_string() }).collect()
}

/// Lines of text (a listing, a message of several lines) as a terminal may show them: each line
/// [`printable`], the line breaks kept.
pub fn printable_lines(text: &str) -> String {
    text.lines().map(|line| printable(line) + "\n").collect()
}

/// A moment of a scene's animation.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Pose {
    /// Which animations play.
    pub animation: Choice,
    /// Seconds from the animation's start.
    pub time: f32,
    /// A sequence's frame: its number, the frames per second and the sequence's seed (labels
    /// only: the frame's own seed is in the render settings).
    pub frame: Option<u32>,
    pub fps: f64,
    pub sequence_seed: u64,
}

impl Pose {
    /// What the scene loader poses the scene at.
    pub fn at(&self) -> PoseAt {
        PoseAt { animation: self.animation.clone(), time: self.time }
    }
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

/// What a render's pixels depend on besides its scene and its samples: the settings, the
/// environment, the pose, the map and the material variant.
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

impl Setup {
    /// A still of the scene at rest under a constant environment.
    pub fn new(settings: RenderSettings, environment: Vec3) -> Self {
        Self { settings, environment, pose: None, environment_map: None, variant: None }
    }

    /// The image header of a render of this setup: the scene, the seed (a frame's sequence's),
    /// `spp`, the settings, the samples dropped, then the map, the pose and the variant. One
    /// function for `tessera render` and the farm, so that their images are the same files.
    pub fn header(&self, scene_name: &str, scene_hash: &str, spp: u32, dropped: u64) -> String {
        let seed = match &self.pose {
            Some(p) if p.frame.is_some() => p.sequence_seed,
            _ => self.settings.seed,
        };
        let mut out = tessera_film::image_metadata(
            scene_name,
            scene_hash,
            seed,
            spp,
            self.environment.to_array(),
            &self.settings.describe(),
            dropped,
        );
        if let Some(m) = &self.environment_map {
            out += &tessera_scene::environment::header_lines(&m.name, &m.hash, m.strength, m.rotate_degrees);
        }
        if let Some(p) = &self.pose {
            let frame = p.frame.map(|f| (f, p.fps, self.settings.seed));
            out += &header_lines(&p.animation, p.time, frame);
        }
        if let Some(v) = &self.variant {
            out += &tessera_scene::variant_header(v);
        }
        out
    }
}

/// Adaptive sampling: tiles get rounds of samples until their relative error is below
/// `target_error`, from `min_spp` up to the submission's `spp`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Adaptive {
    pub target_error: f32,
    pub min_spp: u32,
}

/// A sequence: one render a frame, frame `f` at `f / fps` seconds with its own seed.
#[derive(Clone, Debug, PartialEq)]
pub struct Frames {
    pub list: FrameList,
    pub fps: f64,
}

/// A sequence's previews first (`submit --preview-every N --preview-spp S`, or
/// `--preview-target-error E`): every `every`-th frame of its list (the first, then every
/// n-th) is rendered to `spp` samples per pixel (rounded up to whole passes), or until its
/// relative error is down to `target_error`, before anything else of the sequence, then every
/// frame to its full samples, keeping the preview's: the frames are the same bits as without
/// previews.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PreviewFirst {
    pub every: u32,
    /// The previews' samples per pixel; 0 with a target error.
    pub spp: u32,
    /// Or the relative error a preview frame stops at (0 with samples).
    pub target_error: f32,
}

/// A render (or a sequence of frames) as a user submits it to a farm.
#[derive(Clone, Debug, PartialEq)]
pub struct Submission {
    pub scene_hash: String,
    /// For listings and image headers.
    pub scene_name: String,
    /// A sequence's setup names the animation in its pose; the coordinator gives each frame its
    /// time and seed.
    pub setup: Setup,
    /// Samples per pixel: every pixel's, or with `adaptive` the most a tile gets.
    pub spp: u32,
    pub adaptive: Option<Adaptive>,
    pub tile_size: u32,
    pub pass_spp: u32,
    pub priority: i32,
    /// `None`: one image.
    pub frames: Option<Frames>,
    /// A name for listings (`submit --name`); empty: none.
    pub name: String,
    /// Where it may run: a pool and requirements of workers' tags (`submit --pool --require`).
    pub placement: placement::Placement,
    /// Previews first (a sequence only): some frames to a few samples before the rest.
    pub preview: Option<PreviewFirst>,
    /// A URL to POST an event to when it (or its sequence) ends (`submit --notify`; empty: the
    /// coordinator's default). The coordinator checks it against its own rules.
    pub notify: String,
    /// Submitted paused (`submit --paused`): it takes no worker until resumed.
    pub paused: bool,
}
