//! The Monte Carlo core of Tessera: cameras, samplers, BSDFs, lights, estimators and
//! `render_tile`. Pure and synchronous: no files, no network, no async.
//!
//! The API is what this root re-exports, plus four modules whose insides are meant to be used:
//! [`plan`] (the tile grid, passes and adaptive rounds every renderer shares), [`bsdf`] (the
//! lobes, which the charts and tests evaluate on their own), [`spectral`] (spectra, colour
//! science and the Macbeth chart) and [`estimator`] (one camera ray's estimate, for studies).
//! Everything else is the crate's own.

mod accel;
pub mod bsdf;
mod camera;
mod channels;
mod envmap;
pub mod estimator;
mod features;
mod interaction;
mod lanes;
mod light;
mod light_tree;
mod material;
mod math;
mod mesh;
pub mod plan;
mod sampler;
mod sampling;
mod scene;
mod settings;
pub mod spectral;
mod sums;
mod texture;
mod tile;

pub use accel::{Bvh, PACKET, RayTest};
pub use camera::{Camera, FilmRays, Projection, look_at};
pub use channels::{ColorModel, Rgb};
pub use envmap::{EnvMap, MAX_TEXELS as MAX_ENVIRONMENT_TEXELS};
pub use glam;
pub use interaction::{Hit, SurfacePoint};
pub use lanes::Lanes;
pub use light::{LightSet, PunctualLight};
pub use material::{
    AlphaMode, EmissionSpectrum, Material, MaterialSpectra, Model, REFRACTIVE_INDEX, Surfaces, TextureContext, Volume,
};
pub use math::Frame;
pub use mesh::{
    ALPHA_TESTED, HAS_COLORS, HAS_NORMALS, HAS_TANGENTS, HAS_UV, Mesh, MeshData, SceneError, TriangleRecord,
};
pub use sampler::{PixelSampler, PixelSeeds, SamplerKind, camera_lanes, mix64};
pub use sampling::{sample_cosine_hemisphere, sample_uniform_hemisphere};
pub use scene::{Scene, SceneBuilder};
pub use settings::{
    ColorMode, DEFAULT_BOUNCES, Density, Estimator, LightSampler, ROULETTE_FROM, ROULETTE_MAX_BOUNCES, RenderSettings,
    Termination, k_eps, truncation_bound,
};
pub use sums::{FEATURE_SCALE, FIXED_POINT_SCALE, FeatureSums, MAX_SAMPLE, PixelSums, Tile, TileSums};
pub use texture::{Image, Texels, Texture, TextureRef, Wrap, texture_transform};
pub use tile::{RenderError, render_tile};
