//! Turns scene descriptions into a [`tessera_render::Scene`]: glTF 2.0 files (`.gltf`, `.glb`)
//! and built-in scenes (`builtin:NAME`). Also computes the scene hash that identifies a scene's
//! content in image headers and, later, in the farm.

pub mod builtin;
mod extras;
mod gltf_loader;
mod pack;
pub mod shapes;

pub use gltf_loader::MAX_TRIANGLES;
pub use pack::{load_packed, pack};

use std::path::{Path, PathBuf};
use tessera_render::Scene;
use tessera_render::glam::Vec3;

/// glTF extensions Tessera implements.
pub const SUPPORTED_EXTENSIONS: &[&str] = &[
    "KHR_lights_punctual",
    "KHR_materials_clearcoat",
    "KHR_materials_emissive_strength",
    "KHR_materials_ior",
    "KHR_materials_sheen",
    "KHR_materials_specular",
    "KHR_materials_transmission",
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
    #[error("{0}: unsupported scene file (expected .gltf, .glb or builtin:NAME)")]
    UnknownFormat(String),
}

/// Options that change what a loaded scene contains.
#[derive(Clone, Debug, Default)]
pub struct LoadOptions {
    /// Constant environment radiance (`--env`); overrides the default.
    pub environment: Option<Vec3>,
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
    pub warnings: Vec<String>,
}

pub struct LoadedScene {
    pub scene: Scene,
    /// BLAKE3 of the scene's content (files, or the built-in's canonical description), hex.
    pub hash: String,
    pub info: SceneInfo,
}

/// Loads `spec`: a path to a `.gltf`/`.glb` file, or `builtin:NAME[?key=value&...]`.
pub fn load(spec: &str, options: &LoadOptions) -> Result<LoadedScene, LoadError> {
    let mut loaded = if let Some(name) = spec.strip_prefix("builtin:") {
        builtin::load(name)?
    } else {
        let path = PathBuf::from(spec);
        match path.extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase).as_deref() {
            Some("gltf") | Some("glb") => load_file(&path)?,
            _ => return Err(LoadError::UnknownFormat(spec.to_string())),
        }
    };
    finish(&mut loaded, options);
    Ok(loaded)
}

fn load_file(path: &Path) -> Result<LoadedScene, LoadError> {
    let bytes =
        std::fs::read(path).map_err(|e| LoadError::Io { path: path.display().to_string(), message: e.to_string() })?;
    let base = path.parent().map(Path::to_path_buf).unwrap_or_default();
    let display = path.display().to_string();
    // The glTF crate is not hardened against every hostile file: a panic becomes an error.
    std::panic::catch_unwind(|| gltf_loader::load(&bytes, Some(&base), &display)).unwrap_or_else(|_| {
        Err(LoadError::Gltf { path: display.clone(), message: "malformed data (the glTF reader gave up)".into() })
    })
}

/// Loads a glTF or GLB held in memory; external URIs resolve against `base` when given.
pub fn load_bytes(
    bytes: &[u8],
    base: Option<&Path>,
    name: &str,
    options: &LoadOptions,
) -> Result<LoadedScene, LoadError> {
    let mut loaded = std::panic::catch_unwind(|| gltf_loader::load(bytes, base, name)).unwrap_or_else(|_| {
        Err(LoadError::Gltf { path: name.to_string(), message: "malformed data (the glTF reader gave up)".into() })
    })?;
    finish(&mut loaded, options);
    Ok(loaded)
}

/// The glTF loader without [`load_bytes`]'s panic guard, for the fuzz harness
/// (`tests/fuzz_loader.rs`): a panic in Tessera's own code must show there, not become an error.
#[doc(hidden)]
pub fn load_bytes_unguarded(bytes: &[u8], base: Option<&Path>, name: &str) -> Result<LoadedScene, LoadError> {
    gltf_loader::load(bytes, base, name)
}

/// Applies options that come after loading: the environment, and the no-light fallback.
fn finish(loaded: &mut LoadedScene, options: &LoadOptions) {
    let built = loaded.scene.lights.environment;
    let mut env = options.environment.unwrap_or(built);
    if loaded.scene.lights.is_empty() && env.max_element() <= 0.0 {
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
    if env != built {
        let punctual = std::mem::take(&mut loaded.scene.lights.punctual);
        loaded.scene.lights = tessera_render::light::LightSet::build(&loaded.scene, punctual, env);
    }
    loaded.info.emissive_triangles = loaded.scene.lights.emissive_triangles();
}
