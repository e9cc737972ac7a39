//! The Monte Carlo core of Tessera: cameras, samplers, BSDFs, lights, estimators and
//! `render_tile`. Pure and synchronous: no files, no network, no async.

pub mod bsdf;
pub mod bvh;
pub mod camera;
pub mod channels;
pub mod envmap;
pub mod estimator;
pub mod light;
pub mod material;
pub mod math;
pub mod plan;
pub mod sampler;
pub mod scene;
pub mod settings;
pub mod spectral;
pub mod sums;
pub mod texture;
pub mod tile;

pub use camera::{Camera, FilmRays, Projection};
pub use glam;
pub use light::PunctualLight;
pub use material::{AlphaMode, Material, Model};
pub use sampler::SamplerKind;
pub use scene::{MeshData, Scene, SceneBuilder, SceneError};
pub use settings::{
    ColorMode, Density, Estimator, ROULETTE_FROM, ROULETTE_MAX_BOUNCES, RenderSettings, Termination, k_eps,
};
pub use sums::{FIXED_POINT_SCALE, MAX_SAMPLE, PixelSums, Tile, TileSums};
pub use tile::{RenderError, render_tile};
