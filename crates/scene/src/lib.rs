//! Turns scene descriptions into a [`tessera_render::Scene`]: glTF 2.0 files (`.gltf`, `.glb`)
//! and built-in scenes (`builtin:NAME`). Also computes the scene hash that identifies a scene's
//! content in image headers and, later, in the farm.

pub mod animation;
pub mod builtin;
pub mod environment;
mod extras;
mod gltf_loader;
mod pack;
pub mod shapes;

pub use gltf_loader::MAX_TRIANGLES;
pub use pack::{load_packed, open_packed, pack, pack_with_environment, write_glb};

use std::path::{Path, PathBuf};
use tessera_render::Scene;
use tessera_render::glam::Vec3;

/// glTF extensions Tessera implements.
pub const SUPPORTED_EXTENSIONS: &[&str] = &[
    "EXT_texture_webp",
    "KHR_lights_punctual",
    "KHR_materials_anisotropy",
    "KHR_materials_clearcoat",
    "KHR_materials_emissive_strength",
    "KHR_materials_ior",
    "KHR_materials_sheen",
    "KHR_materials_specular",
    "KHR_materials_transmission",
    "KHR_materials_unlit",
    "KHR_materials_variants",
    "KHR_materials_volume",
    "KHR_mesh_quantization",
    "KHR_texture_transform",
];

#[derive(Debug, thiserror::Error)]
pub enum LoadError {
    #[error("{path}: {message}")]
    Io { path: String, message: String },
    #[error("{path}: not a valid glTF 2.0 file: {message}")]
    Gltf { path: String, message: String },
    #[error("{path}: requires unsupported extension(s) {names} (listed in extensionsRequired)")]
    RequiredExtension { path: String, names: String },
    #[error("{path}: {message}")]
    Content { path: String, message: String },
    #[error("unknown built-in scene '{0}' (available: {1})")]
    UnknownBuiltin(String, String),
    #[error("built-in scene '{name}': {message}")]
    BuiltinParameter { name: String, message: String },
    #[error("{0}: unsupported scene file (expected .gltf, .glb or builtin:NAME){hint}", hint = export_hint(.0))]
    UnknownFormat(String),
}

/// What to do with a scene in another tool's format: export it as glTF 2.0.
fn export_hint(path: &str) -> &'static str {
    let extension = path.rsplit_once('.').map(|(_, e)| e.to_ascii_lowercase()).unwrap_or_default();
    match extension.as_str() {
        "blend" => {
            ". Export it from Blender as glTF 2.0: File > Export > glTF 2.0 (.glb/.gltf), format glTF Binary \
             (.glb), with Include > Cameras and Punctual Lights checked"
        }
        "obj" | "fbx" | "dae" | "usd" | "usda" | "usdc" | "usdz" | "3ds" | "stl" | "ply" | "abc" => {
            ". Convert it to glTF 2.0 first: import it into Blender and use File > Export > glTF 2.0 (.glb), or a \
             converter such as FBX2glTF or obj2gltf"
        }
        _ => "",
    }
}

/// Options that change what a loaded scene contains.
#[derive(Clone, Debug, Default)]
pub struct LoadOptions {
    /// Constant environment radiance (`--env`); overrides the default.
    pub environment: Option<Vec3>,
    /// Which animations play and when; `None` renders the scene at rest, every node as stored.
    pub pose: Option<PoseAt>,
    /// An environment map (`--env FILE`), which replaces the constant environment.
    pub environment_map: Option<std::sync::Arc<tessera_render::EnvMap>>,
    /// A material variant by name (KHR_materials_variants); `None`: the primitives' own
    /// materials.
    pub variant: Option<String>,
}

/// A moment of a scene's animation: which animations play, and the time in seconds from 0.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PoseAt {
    pub animation: animation::Choice,
    pub time: f32,
}

/// The image header line naming a material variant.
pub fn variant_header(variant: &str) -> String {
    format!("variant={variant}\n")
}

/// Counts and notes about a loaded scene, for `tessera scene-info` and logs.
#[derive(Clone, Debug, Default)]
pub struct SceneInfo {
    pub name: String,
    pub triangles: usize,
    pub materials: usize,
    pub emissive_triangles: usize,
    /// Punctual lights as "kind name" strings.
    pub punctual_lights: Vec<String>,
    pub cameras: Vec<String>,
    /// The scene brought no camera: its only one frames the bounds.
    pub framed: bool,
    pub extensions_used: Vec<String>,
    /// The file's material variants (KHR_materials_variants), by name.
    pub variants: Vec<String>,
    pub warnings: Vec<String>,
}

/// What building a scene would make, counted without building it ([`Source::census`]): what a
/// coordinator checks against its limits before it accepts a render, at a cost bounded by the
/// file, whatever its instancing.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Census {
    /// Triangles the node tree draws, every instance counted.
    pub drawn_triangles: u64,
    /// Cameras (at least one: a scene without any gets one that frames it).
    pub cameras: usize,
    /// Texels of the decoded images.
    pub texels: u64,
    /// Texels of the environment map the package carries (0 without one).
    pub map_texels: u64,
}

/// Peak bytes building and rendering a scene takes per drawn triangle: its mesh, its BVH and
/// their build. Measured: MetalRoughSpheresNoTextures, 1.04 M triangles, peaks at 416 MB
/// (`/usr/bin/time -v tessera render`, 8 x 8, 1 spp, 2026-11-28); 19.9 M triangles drawn by
/// instancing took 7.1 GB (357 bytes each).
pub const BYTES_PER_DRAWN_TRIANGLE: u64 = 400;
/// Peak bytes per decoded texel: the RGBA8 texels kept and the decoder's own buffers. Measured
/// with `tessera bench memory` (2026-11-29, docs/benchmarks.md): 10.2-11.0 bytes on
/// WaterBottle (16.8 M texels), 9.0-9.7 on GlassHurricaneCandleHolder, 11 on CesiumMan, at 1, 2
/// and 8 threads; the 8 it was before let a textured scene past `--max-scene-memory` with more
/// than the budget.
pub const BYTES_PER_TEXEL: u64 = 12;
/// What any scene adds beside its triangles and texels (the BSDF tables, the light tree, the
/// loader's buffers): Duck measures about 1.2 MiB of it; 4 MiB leaves room.
pub const BYTES_PER_SCENE: u64 = 4 << 20;
/// Peak bytes per environment map texel on a worker: the decoded floats (12), kept for the
/// next frame, and the map built from them (radiance 12, sampling tables 8), plus the decoder's
/// own buffers. Measured below ([`Census::memory`]'s note in docs/benchmarks.md).
pub const BYTES_PER_MAP_TEXEL: u64 = 48;

impl Census {
    /// The memory a worker needs to build and render the scene, about.
    pub fn memory(&self) -> u64 {
        BYTES_PER_SCENE
            .saturating_add(self.drawn_triangles.saturating_mul(BYTES_PER_DRAWN_TRIANGLE))
            .saturating_add(self.texels.saturating_mul(BYTES_PER_TEXEL))
            .saturating_add(self.map_texels.saturating_mul(BYTES_PER_MAP_TEXEL))
    }
}

pub struct LoadedScene {
    pub scene: Scene,
    /// BLAKE3 of the scene's content (files, or the built-in's canonical description), hex.
    pub hash: String,
    pub info: SceneInfo,
}

/// Loads `spec`: a path to a `.gltf`/`.glb` file, or `builtin:NAME[?key=value&...]`.
pub fn load(spec: &str, options: &LoadOptions) -> Result<LoadedScene, LoadError> {
    open(spec)?.pose(options)
}

/// A scene read once, to be posed at as many times as a sequence asks ([`Source::pose`]).
pub struct Source {
    kind: SourceKind,
    /// The environment map a scene bundle carries (decoded when first used).
    environment: Option<std::sync::Arc<environment::Decoded>>,
}

enum SourceKind {
    Gltf(Box<gltf_loader::Parsed>),
    /// Built-in scenes have no animations: every pose is the scene itself.
    Builtin(String),
}

/// Reads `spec` (see [`load`]) without building its scene.
pub fn open(spec: &str) -> Result<Source, LoadError> {
    if let Some(name) = spec.strip_prefix("builtin:") {
        builtin::load(name)?;
        return Ok(Source { kind: SourceKind::Builtin(name.to_string()), environment: None });
    }
    let path = PathBuf::from(spec);
    match path.extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase).as_deref() {
        Some("gltf") | Some("glb") => {}
        _ => return Err(LoadError::UnknownFormat(spec.to_string())),
    }
    let bytes =
        std::fs::read(&path).map_err(|e| LoadError::Io { path: path.display().to_string(), message: e.to_string() })?;
    let base = path.parent().map(Path::to_path_buf).unwrap_or_default();
    open_bytes(&bytes, Some(&base), &path.display().to_string())
}

/// Reads a glTF or GLB held in memory (see [`load_bytes`]) without building its scene.
pub fn open_bytes(bytes: &[u8], base: Option<&Path>, name: &str) -> Result<Source, LoadError> {
    let parsed = guarded(name, || gltf_loader::parse(bytes, base, name))?;
    Ok(Source { kind: SourceKind::Gltf(Box::new(parsed)), environment: None })
}

/// The glTF crate is not hardened against every hostile file: a panic becomes an error.
fn guarded<T>(name: &str, f: impl FnOnce() -> Result<T, LoadError>) -> Result<T, LoadError> {
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)).unwrap_or_else(|_| {
        Err(LoadError::Gltf { path: name.to_string(), message: "malformed data (the glTF reader gave up)".into() })
    })
}

impl Source {
    /// The scene as `options` ask: at rest or posed, under the chosen environment.
    pub fn pose(&self, options: &LoadOptions) -> Result<LoadedScene, LoadError> {
        let mut loaded = match &self.kind {
            SourceKind::Builtin(name) => {
                if let Some(at) = &options.pose {
                    at.animation
                        .pick(&[])
                        .map_err(|message| LoadError::BuiltinParameter { name: name.clone(), message })?;
                }
                if let Some(v) = &options.variant {
                    let message = format!("built-in scenes have no material variants ('{v}' asked for)");
                    return Err(LoadError::BuiltinParameter { name: name.clone(), message });
                }
                builtin::load(name)?
            }
            SourceKind::Gltf(parsed) => {
                let variant = match &options.variant {
                    None => None,
                    Some(v) => Some(
                        parsed
                            .variant_index(v)
                            .map_err(|message| LoadError::Content { path: parsed.path.clone(), message })?,
                    ),
                };
                guarded(&parsed.path, || parsed.pose(options.pose.as_ref(), variant))?
            }
        };
        finish(&mut loaded, options);
        Ok(loaded)
    }

    /// What building the scene at `pose` with material variant `variant` would make, checked and
    /// counted without building it (see [`Census`]). A built-in scene is built: they are small.
    pub fn census(&self, pose: Option<&PoseAt>, variant: Option<&str>) -> Result<Census, LoadError> {
        let map_texels = self.environment.as_ref().map_or(0, |d| d.texels());
        let census = match &self.kind {
            SourceKind::Gltf(parsed) => guarded(&parsed.path, || {
                parsed
                    .census(pose, variant)
                    .map_err(|message| LoadError::Content { path: parsed.path.clone(), message })
            }),
            SourceKind::Builtin(_) => {
                let options =
                    LoadOptions { pose: pose.cloned(), variant: variant.map(str::to_string), ..Default::default() };
                let loaded = self.pose(&options)?;
                Ok(Census {
                    drawn_triangles: loaded.info.triangles as u64,
                    cameras: loaded.scene.cameras.len(),
                    texels: loaded.scene.surfaces.images.iter().map(|i| i.width as u64 * i.height as u64).sum(),
                    map_texels: 0,
                })
            }
        };
        census.map(|c| Census { map_texels, ..c })
    }

    /// The BLAKE3 hash of the environment map the package carries, if it carries one (what a
    /// render's settings name it by).
    pub fn environment_hash(&self) -> Option<&str> {
        self.environment.as_ref().map(|d| d.hash.as_str())
    }

    /// Every node's local pose at `at` (see [`animation::NodePose`]); empty for built-in scenes.
    pub fn node_poses(&self, at: &PoseAt) -> Result<Vec<animation::NodePose>, LoadError> {
        match &self.kind {
            SourceKind::Gltf(parsed) => parsed
                .node_poses(at)
                .map(|(nodes, _)| nodes)
                .map_err(|message| LoadError::Content { path: parsed.path.clone(), message }),
            SourceKind::Builtin(_) => Ok(Vec::new()),
        }
    }

    /// Every node's world transform at `at` (at rest for `None`); `None` for nodes outside the
    /// scene's tree; empty for built-in scenes.
    pub fn world_transforms(&self, at: Option<&PoseAt>) -> Result<Vec<Option<tessera_render::glam::Mat4>>, LoadError> {
        match &self.kind {
            SourceKind::Gltf(parsed) => parsed
                .place(at)
                .map(|p| p.worlds)
                .map_err(|message| LoadError::Content { path: parsed.path.clone(), message }),
            SourceKind::Builtin(_) => Ok(Vec::new()),
        }
    }

    /// Decodes and checks the environment map the package carries, if any, keeping nothing
    /// ([`environment::Decoded::check`]).
    pub fn check_environment(&self) -> Result<(), LoadError> {
        self.environment.as_ref().map_or(Ok(()), |d| d.check())
    }

    /// The environment map the package carried, scaled by `strength` and turned
    /// `rotate_degrees` about +Y; `None` when it carried none.
    pub fn environment(
        &self,
        strength: f32,
        rotate_degrees: f32,
    ) -> Result<Option<environment::Environment>, LoadError> {
        self.environment.as_ref().map(|d| d.map(strength, rotate_degrees)).transpose()
    }

    /// The file's animations, each read and checked, or what is wrong with it.
    pub fn animations(&self) -> &[Result<animation::Clip, String>] {
        match &self.kind {
            SourceKind::Gltf(parsed) => &parsed.clips,
            SourceKind::Builtin(_) => &[],
        }
    }
}

/// Loads a glTF or GLB held in memory; external URIs resolve against `base` when given.
pub fn load_bytes(
    bytes: &[u8],
    base: Option<&Path>,
    name: &str,
    options: &LoadOptions,
) -> Result<LoadedScene, LoadError> {
    open_bytes(bytes, base, name)?.pose(options)
}

/// The glTF loader without [`load_bytes`]'s panic guard, for the fuzz harness
/// (`tests/fuzz_loader.rs`): a panic in Tessera's own code must show there, not become an error.
/// `pose` poses the scene (see [`LoadOptions::pose`]).
#[doc(hidden)]
pub fn load_bytes_unguarded(
    bytes: &[u8],
    base: Option<&Path>,
    name: &str,
    pose: Option<&PoseAt>,
) -> Result<LoadedScene, LoadError> {
    gltf_loader::parse(bytes, base, name)?.pose(pose, None)
}

/// Applies options that come after loading: the environment, and the no-light fallback.
fn finish(loaded: &mut LoadedScene, options: &LoadOptions) {
    let built = loaded.scene.lights.environment;
    let mut env = options.environment.unwrap_or(built);
    let map = options.environment_map.clone();
    if map.is_none() && loaded.scene.lights.is_empty() && env.max_element() <= 0.0 {
        loaded.info.warnings.push(
            "the scene has no lights (no emissive material, punctual light or environment): \
             rendering under a uniform environment of 1"
                .into(),
        );
        env = Vec3::ONE;
    }
    if loaded.scene.cameras.is_empty() {
        let (lo, hi) = loaded.scene.bounds;
        loaded.scene.cameras.push(tessera_render::Camera::framing(lo, hi));
        loaded.info.cameras.push("'framing' perspective (the scene has no camera: framing its bounds)".into());
        loaded.info.framed = true;
    }
    // The light distribution weighs the environment too: rebuild it when that changed.
    if env != built || map.is_some() {
        let punctual = std::mem::take(&mut loaded.scene.lights.punctual);
        loaded.scene.lights = loaded.scene.light_set(punctual, env, map);
    }
    loaded.info.emissive_triangles = loaded.scene.lights.emissive_triangles();
}
