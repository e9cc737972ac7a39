//! glTF 2.0 / GLB loading: geometry of the default scene with node transforms, the
//! metallic-roughness materials with their textures and supported extensions, cameras and
//! KHR_lights_punctual lights. By concern: parsing and validation (`parse.rs`), the node tree,
//! its animations and the scene posed from them (`nodes.rs`), materials and their extensions
//! (`materials.rs`), textures and images (`textures.rs`), skins and morph targets (`skins.rs`),
//! meshes and accessors (`geometry.rs`), cameras and lights (`cameras.rs`).

mod cameras;
mod geometry;
mod materials;
mod nodes;
mod parse;
mod skins;
mod textures;

pub use parse::{MAX_TRIANGLES, parse};
pub(crate) use parse::{missing_file, percent_decode};

use crate::SceneInfo;
use crate::animation::{Clip, NodePose};
use tessera_render::glam::Mat4;
use tessera_render::{Image, Material, Texture};

/// Material extensions often met but not modelled, with what their surfaces look like instead.
pub(super) const FALLBACKS: &[(&str, &str)] = &[
    ("KHR_materials_iridescence", "KHR_materials_iridescence (no thin-film colours)"),
    ("KHR_materials_dispersion", "KHR_materials_dispersion (one index for all wavelengths)"),
    ("KHR_materials_diffuse_transmission", "KHR_materials_diffuse_transmission (opaque diffuse)"),
];

/// A glTF file read, checked and decoded once: its document, buffers, textures, materials and
/// animations. [`Parsed::pose`] builds the scene at any time from it, so that the frames of a
/// sequence decode nothing twice.
pub struct Parsed {
    pub(crate) path: String,
    pub(super) document: gltf::Document,
    pub(super) buffers: Vec<gltf::buffer::Data>,
    pub(super) images: Vec<Image>,
    pub(super) textures: Vec<Texture>,
    pub(super) materials: Vec<Material>,
    pub(super) roots: Vec<usize>,
    pub(super) hash: String,
    pub(super) info: SceneInfo,
    /// Triangles the scene's node tree draws, every instance counted (at rest; animation moves
    /// nodes, it does not add them).
    pub(super) drawn_triangles: u64,
    /// Every animation of the file, or what is wrong with it: a broken animation is an error
    /// only when it is asked to play.
    pub clips: Vec<Result<Clip, String>>,
}

/// Where every node stands at one moment (see [`Parsed::place`]).
pub struct Placed {
    /// Each node's world transform; `None` for nodes outside the scene's tree.
    pub worlds: Vec<Option<Mat4>>,
    /// The scene's nodes, in the order their meshes are built.
    pub order: Vec<usize>,
    /// Each node's local pose when animated (empty at rest).
    pub poses: Vec<NodePose>,
}
