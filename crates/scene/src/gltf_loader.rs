//! glTF 2.0 / GLB loading: geometry of the default scene with node transforms, the
//! metallic-roughness materials with their textures and supported extensions, cameras and
//! KHR_lights_punctual lights.

use crate::animation::{Channel, Clip, Interpolation, NodePose, Property};
use crate::extras;
use crate::{LoadError, LoadedScene, PoseAt, SUPPORTED_EXTENSIONS, SceneInfo};
use gltf::khr_lights_punctual::Kind;
use std::path::Path;
use tessera_render::glam::{Mat4, Vec2, Vec3, Vec4};
use tessera_render::{AlphaMode, Material};
use tessera_render::{Camera, Projection};
use tessera_render::{Image, Texels, Texture, TextureRef, Wrap, texture_transform};
use tessera_render::{MeshData, PunctualLight, SceneBuilder};

/// Material extensions often met but not modelled, with what their surfaces look like instead.
const FALLBACKS: &[(&str, &str)] = &[
    ("KHR_materials_iridescence", "KHR_materials_iridescence (no thin-film colours)"),
    ("KHR_materials_dispersion", "KHR_materials_dispersion (one index for all wavelengths)"),
    ("KHR_materials_diffuse_transmission", "KHR_materials_diffuse_transmission (opaque diffuse)"),
];

/// A glTF file read, checked and decoded once: its document, buffers, textures, materials and
/// animations. [`Parsed::pose`] builds the scene at any time from it, so that the frames of a
/// sequence decode nothing twice.
pub struct Parsed {
    pub(crate) path: String,
    document: gltf::Document,
    buffers: Vec<gltf::buffer::Data>,
    images: Vec<Image>,
    textures: Vec<Texture>,
    materials: Vec<Material>,
    roots: Vec<usize>,
    hash: String,
    info: SceneInfo,
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

pub fn parse(bytes: &[u8], base: Option<&Path>, path: &str) -> Result<Parsed, LoadError> {
    let gltf_err = |e: gltf::Error| LoadError::Gltf { path: path.to_string(), message: e.to_string() };
    let content = |message: String| LoadError::Content { path: path.to_string(), message };
    let (used, required) = declared_extensions(bytes, path)?;
    let unsupported_required: Vec<&String> =
        required.iter().filter(|e| !SUPPORTED_EXTENSIONS.contains(&e.as_str())).collect();
    if !unsupported_required.is_empty() {
        let names = unsupported_required.iter().map(|s| s.as_str()).collect::<Vec<_>>().join(", ");
        return Err(LoadError::RequiredExtension { path: path.to_string(), names });
    }
    let mut info = SceneInfo { extensions_used: used.clone(), ..Default::default() };
    let unsupported: Vec<&str> =
        used.iter().map(String::as_str).filter(|e| !SUPPORTED_EXTENSIONS.contains(e)).collect();
    if !unsupported.is_empty() {
        let named: Vec<String> = unsupported
            .iter()
            .map(|e| FALLBACKS.iter().find(|f| f.0 == *e).map_or(e.to_string(), |f| f.1.to_string()))
            .collect();
        info.warnings.push(format!(
            "unsupported extension(s) {}: rendering with the core material model instead",
            named.join(", ")
        ));
    }

    let gltf = gltf::Gltf::from_slice_without_validation(bytes).map_err(gltf_err)?;
    validate(&gltf.document).map_err(|message| LoadError::Gltf { path: path.to_string(), message })?;
    let document = gltf.document;
    let buffers = gltf::import_buffers(&document, base, gltf.blob).map_err(gltf_err)?;
    for view in document.views() {
        let (b, start) = (view.buffer().index(), view.offset());
        let len = buffers.get(b).map_or(0, |d| d.0.len());
        if start.checked_add(view.length()).is_none_or(|end| end > len) {
            return Err(content(format!(
                "buffer view {}: bytes {start}..{} lie outside buffer {b} ({len} bytes)",
                view.index(),
                start.saturating_add(view.length())
            )));
        }
    }

    info.variants = variant_names(&document).map_err(content)?;
    let sources = texture_sources(&document).map_err(content)?;
    let images = texture_images(&document, &sources, base, &buffers).map_err(content)?;
    let textures = document
        .textures()
        .zip(&sources)
        .map(|(t, &image)| Texture {
            image: image as u32,
            wrap_s: wrap(t.sampler().wrap_s()),
            wrap_t: wrap(t.sampler().wrap_t()),
        })
        .collect();
    let mut materials = Vec::new();
    for m in document.materials() {
        let material = convert_material(&m, document.textures().len())
            .map_err(|e| content(format!("material {} '{}': {e}", m.index().unwrap_or(0), m.name().unwrap_or(""))))?;
        materials.push(material);
    }

    let scene = document.default_scene().or_else(|| document.scenes().next());
    let roots: Vec<gltf::Node> = match &scene {
        Some(s) => s.nodes().collect(),
        None => return Err(content("the file contains no scene".into())),
    };
    check_node_trees(&document, &roots).map_err(content)?;
    info.name = scene.and_then(|s| s.name().map(str::to_string)).unwrap_or_else(|| path.to_string());
    // Every instance the hierarchy draws, counted before anything expands (the hierarchy is a
    // forest now, so this walk ends).
    let mut instanced: u64 = 0;
    let mut stack: Vec<gltf::Node> = roots.clone();
    while let Some(node) = stack.pop() {
        instanced += node.mesh().map_or(0, |m| mesh_triangles(&m));
        stack.extend(node.children());
    }
    if instanced > MAX_TRIANGLES {
        return Err(content(format!(
            "the scene draws {instanced} triangles (counting every node that instances a mesh), over the limit of {MAX_TRIANGLES}"
        )));
    }
    let clips = document.animations().map(|a| read_clip(&a, &buffers)).collect();
    let hash = content_hash(bytes, &document, base);
    let roots = roots.iter().map(|n| n.index()).collect();
    Ok(Parsed { path: path.to_string(), document, buffers, images, textures, materials, roots, hash, info, clips })
}

impl Parsed {
    /// Every node's local pose at `at` (its stored translation, rotation, scale and morph weights
    /// where no chosen channel moves them), and whether a chosen channel moves it.
    pub fn node_poses(&self, at: &PoseAt) -> Result<(Vec<NodePose>, Vec<bool>), String> {
        let names: Vec<&str> = self.document.animations().map(|a| a.name().unwrap_or("")).collect();
        let chosen: Vec<&Clip> = at
            .animation
            .pick(&names)?
            .into_iter()
            .map(|i| self.clips[i].as_ref().map_err(String::clone))
            .collect::<Result<_, _>>()?;
        let mut nodes: Vec<NodePose> = self
            .document
            .nodes()
            .map(|n| {
                let (translation, rotation, scale) = n.transform().decomposed();
                NodePose { translation, rotation, scale, weights: None }
            })
            .collect();
        let mut animated = vec![false; nodes.len()];
        for c in chosen.iter().flat_map(|c| &c.channels) {
            animated[c.node] = true;
        }
        crate::animation::pose(&chosen, at.time, &mut nodes);
        Ok((nodes, animated))
    }

    /// Every node's world transform at `at` (at rest for `None`), in the order the scene is
    /// built. A node no chosen channel moves keeps its stored matrix, so that a still render has
    /// the bits it had before animation existed; a moved one gets the matrix glTF composes from
    /// translation, rotation and scale, by the glTF crate's own arithmetic, as a static node with
    /// those values would.
    /// The index of material variant `name`, or what the file offers instead.
    pub fn variant_index(&self, name: &str) -> Result<usize, String> {
        let names = &self.info.variants;
        names.iter().position(|v| v == name).ok_or_else(|| match names.len() {
            0 => format!("there is no material variant '{name}': the file has none"),
            _ => format!("there is no material variant '{name}' (the file has: {})", names.join(", ")),
        })
    }

    pub fn place(&self, at: Option<&PoseAt>) -> Result<Placed, String> {
        let all: Vec<gltf::Node> = self.document.nodes().collect();
        let (poses, animated) = match at {
            Some(at) => self.node_poses(at)?,
            None => (Vec::new(), vec![false; all.len()]),
        };
        let local = |node: &gltf::Node| -> Mat4 {
            let i = node.index();
            if !animated[i] {
                return Mat4::from_cols_array_2d(&node.transform().matrix());
            }
            let p = &poses[i];
            let trs =
                gltf::scene::Transform::Decomposed { translation: p.translation, rotation: p.rotation, scale: p.scale };
            Mat4::from_cols_array_2d(&trs.matrix())
        };
        let mut worlds: Vec<Option<Mat4>> = vec![None; all.len()];
        let mut order = Vec::new();
        let mut stack: Vec<(usize, Mat4, u32)> = self.roots.iter().map(|&i| (i, Mat4::IDENTITY, 0)).collect();
        while let Some((i, parent, depth)) = stack.pop() {
            if depth > 256 {
                return Err("node hierarchy deeper than 256 levels (a cycle?)".into());
            }
            let world = parent * local(&all[i]);
            worlds[i].get_or_insert(world);
            stack.extend(all[i].children().map(|c| (c.index(), world, depth + 1)));
            order.push(i);
        }
        Ok(Placed { worlds, order, poses })
    }

    /// The scene posed by `at`'s animations at its time, or at rest (every node as stored) for
    /// `None`.
    /// The scene at `at` (at rest: `None`) with material variant `variant` (an index into
    /// `info.variants`; `None`: the primitives' own materials).
    pub fn pose(&self, at: Option<&PoseAt>, variant: Option<usize>) -> Result<LoadedScene, LoadError> {
        let content = |message: String| LoadError::Content { path: self.path.clone(), message };
        let document = &self.document;
        let buffers = &self.buffers[..];
        let mut info = self.info.clone();
        let placed = self.place(at).map_err(content)?;
        let mut builder = SceneBuilder::new();
        builder.images = self.images.clone();
        builder.textures = self.textures.clone();
        for m in &self.materials {
            builder.add_material(m.clone());
        }
        let default_material = builder.add_material(Material::default());
        let all: Vec<gltf::Node> = document.nodes().collect();
        let worlds = &placed.worlds;
        for &i in &placed.order {
            let (node, world) = (&all[i], worlds[i].unwrap_or(Mat4::IDENTITY));
            if let Some(mesh) = node.mesh() {
                let joints = node.skin().map(|s| joint_matrices(&s, worlds, buffers)).transpose().map_err(content)?;
                let weights = match placed.poses.get(i).and_then(|p| p.weights.as_deref()) {
                    Some(w) => w,
                    None => node.weights().or(mesh.weights()).unwrap_or(&[]),
                };
                let pose = Pose { world, joints: joints.as_deref(), weights };
                let materials = Materials { default: default_material, count: self.materials.len(), variant };
                add_mesh(&mut builder, &mesh, &pose, buffers, materials, &mut info).map_err(content)?;
            }
            if let Some(camera) = node.camera() {
                let cam = convert_camera(&camera, world, builder.cameras.len()).map_err(content)?;
                info.cameras.push(describe_camera(&cam));
                builder.cameras.push(cam);
            }
            if let Some(light) = node.light() {
                let name = light.name().unwrap_or("").to_string();
                match convert_light(&light, world) {
                    Some(l) => {
                        info.punctual_lights.push(format!("{} '{name}'", l.kind()));
                        builder.punctual.push(l);
                    }
                    None => info
                        .warnings
                        .push(format!("light '{name}' has a non-finite position, direction or intensity: skipped")),
                }
            }
        }
        if builder.degenerate_triangles > 0 {
            info.warnings.push(format!("{} degenerate (zero-area) triangles skipped", builder.degenerate_triangles));
        }
        info.triangles = builder.triangle_count();
        info.materials = document.materials().len();
        let scene = builder.build();
        Ok(LoadedScene { scene, hash: self.hash.clone(), info })
    }
}

/// Reads and checks one animation's channels. Channels that target a property glTF does not
/// define here (KHR_animation_pointer's "pointer") are skipped.
fn read_clip(a: &gltf::Animation, buffers: &[gltf::buffer::Data]) -> Result<Clip, String> {
    use gltf::animation::Property as P;
    let name = a.name().unwrap_or("").to_string();
    let mut channels = Vec::new();
    for (k, c) in a.channels().enumerate() {
        let sampler = c.sampler();
        let (input, output) = (sampler.input(), sampler.output());
        let what = format!(
            "animation {} '{name}' channel {k} (input accessor {}, output accessor {})",
            a.index(),
            input.index(),
            output.index()
        );
        let node = c.target().node();
        let property = match c.target().property() {
            P::Translation => Property::Translation,
            P::Rotation => Property::Rotation,
            P::Scale => Property::Scale,
            P::MorphTargetWeights => Property::Weights,
        };
        let interpolation = match sampler.interpolation() {
            gltf::animation::Interpolation::Step => Interpolation::Step,
            gltf::animation::Interpolation::Linear => Interpolation::Linear,
            gltf::animation::Interpolation::CubicSpline => Interpolation::CubicSpline,
        };
        if input.data_type() != gltf::accessor::DataType::F32
            || input.dimensions() != gltf::accessor::Dimensions::Scalar
        {
            return Err(format!("{what}: key times must be float scalars"));
        }
        let times: Vec<f32> = items::<f32>(&input, buffers).map_err(|e| format!("{what}: {e}"))?;
        let (values, width): (Vec<f32>, usize) = match property {
            Property::Translation | Property::Scale => {
                (read_floats::<3>(&output, buffers).map_err(|e| format!("{what}: {e}"))?.concat(), 3)
            }
            Property::Rotation => (read_floats::<4>(&output, buffers).map_err(|e| format!("{what}: {e}"))?.concat(), 4),
            Property::Weights => {
                let targets =
                    node.mesh().and_then(|m| m.primitives().map(|p| p.morph_targets().len()).max()).unwrap_or(0);
                if targets == 0 {
                    return Err(format!(
                        "{what}: animates the weights of node {}, which has no morph targets",
                        node.index()
                    ));
                }
                (read_scalars(&output, buffers).map_err(|e| format!("{what}: {e}"))?, targets)
            }
        };
        let channel = Channel { node: node.index(), property, interpolation, times, values, width };
        channel.check(&what)?;
        channels.push(channel);
    }
    Ok(Clip { index: a.index(), name, channels })
}

/// Most triangles a scene may draw, counted from the accessors before any mesh is expanded.
pub const MAX_TRIANGLES: u64 = 1 << 25;

/// glTF requires node hierarchies to be disjoint trees (section 3.5.3): no node has two
/// parents, no node is its own ancestor, and a scene's root nodes have no parent. Checked before
/// anything is expanded: a kilobyte of nodes that share children would otherwise stand for 2^40
/// instances.
fn check_node_trees(document: &gltf::Document, roots: &[gltf::Node]) -> Result<(), String> {
    let mut parent: Vec<Option<usize>> = vec![None; document.nodes().len()];
    for node in document.nodes() {
        for child in node.children() {
            if let Some(first) = parent[child.index()].replace(node.index()) {
                return Err(format!(
                    "node {} is a child of both node {first} and node {}: glTF node hierarchies must be trees",
                    child.index(),
                    node.index()
                ));
            }
        }
    }
    let mut listed = vec![false; parent.len()];
    for root in roots {
        if let Some(p) = parent[root.index()] {
            return Err(format!("scene root node {} has a parent (node {p}): roots must be roots", root.index()));
        }
        if std::mem::replace(&mut listed[root.index()], true) {
            return Err(format!("the scene lists node {} twice", root.index()));
        }
    }
    // With one parent each, the nodes on a cycle (and under one) are those no parentless node
    // reaches; each node is visited once.
    let children: Vec<Vec<usize>> = document.nodes().map(|n| n.children().map(|c| c.index()).collect()).collect();
    let mut reached = vec![false; parent.len()];
    let mut stack: Vec<usize> = (0..parent.len()).filter(|&i| parent[i].is_none()).collect();
    while let Some(i) = stack.pop() {
        reached[i] = true;
        stack.extend(&children[i]);
    }
    match reached.iter().position(|&r| !r) {
        Some(i) => Err(format!("node {i} is its own ancestor: glTF node hierarchies must be trees")),
        None => Ok(()),
    }
}

/// Triangles a mesh draws, from its accessors' counts (nothing is read).
fn mesh_triangles(mesh: &gltf::Mesh) -> u64 {
    use gltf::mesh::Mode;
    mesh.primitives()
        .map(|p| {
            let vertices = match p.indices() {
                Some(a) => a.count(),
                None => p.get(&gltf::Semantic::Positions).map_or(0, |a| a.count()),
            } as u64;
            match p.mode() {
                Mode::Triangles => vertices / 3,
                Mode::TriangleStrip | Mode::TriangleFan => vertices.saturating_sub(2),
                _ => 0,
            }
        })
        .sum()
}

/// The glTF crate's validation (indices in range, required fields), except its refusal of
/// required extensions it does not implement itself: [`SUPPORTED_EXTENSIONS`] has decided those
/// already, and the crate knows nothing of KHR_mesh_quantization.
fn validate(document: &gltf::Document) -> Result<(), String> {
    use gltf::json::validation::{Checked, Error, Validate};
    let root = document.as_json();
    // The crate's own check of POSITION's bounds indexes the accessor before checking it exists.
    for (m, mesh) in root.meshes.iter().enumerate() {
        for (p, prim) in mesh.primitives.iter().enumerate() {
            let position = prim.attributes.get(&Checked::Valid(gltf::Semantic::Positions));
            if let Some(i) = position.filter(|i| i.value() >= root.accessors.len()) {
                return Err(format!(
                    "mesh {m} primitive {p}: POSITION names accessor {}, but there are {}",
                    i.value(),
                    root.accessors.len()
                ));
            }
        }
    }
    let mut errors = Vec::new();
    root.validate(root, gltf::json::Path::new, &mut |path, error| {
        let path = path();
        if !(matches!(error, Error::Unsupported) && path.as_str().starts_with("extensionsRequired")) {
            errors.push((path, error));
        }
    });
    if errors.is_empty() { Ok(()) } else { Err(gltf::Error::Validation(errors).to_string()) }
}

/// `extensionsUsed` and `extensionsRequired`, read before the glTF crate validates anything,
/// so that an unsupported required extension gets a message that names it.
fn declared_extensions(bytes: &[u8], path: &str) -> Result<(Vec<String>, Vec<String>), LoadError> {
    let json: &[u8] = if bytes.starts_with(b"glTF") {
        let glb = gltf::Glb::from_slice(bytes)
            .map_err(|e| LoadError::Gltf { path: path.to_string(), message: e.to_string() })?;
        return declared_extensions_json(&glb.json, path);
    } else {
        bytes
    };
    declared_extensions_json(json, path)
}

fn declared_extensions_json(json: &[u8], path: &str) -> Result<(Vec<String>, Vec<String>), LoadError> {
    let v: serde_json::Value = serde_json::from_slice(json)
        .map_err(|e| LoadError::Gltf { path: path.to_string(), message: format!("invalid JSON: {e}") })?;
    let list = |key: &str| -> Vec<String> {
        v.get(key)
            .and_then(|a| a.as_array())
            .map(|a| a.iter().filter_map(|s| s.as_str().map(str::to_string)).collect())
            .unwrap_or_default()
    };
    Ok((list("extensionsUsed"), list("extensionsRequired")))
}

/// BLAKE3 over the file and every external file it references, in document order.
fn content_hash(bytes: &[u8], document: &gltf::Document, base: Option<&Path>) -> String {
    let mut h = blake3::Hasher::new();
    h.update(bytes);
    let uris = document
        .buffers()
        .filter_map(|b| match b.source() {
            gltf::buffer::Source::Uri(u) => Some(u),
            gltf::buffer::Source::Bin => None,
        })
        .chain(document.images().filter_map(|i| match i.source() {
            gltf::image::Source::Uri { uri, .. } => Some(uri),
            gltf::image::Source::View { .. } => None,
        }));
    for uri in uris {
        h.update(uri.as_bytes());
        if !uri.starts_with("data:")
            && let Some(base) = base
            && let Ok(data) = std::fs::read(base.join(percent_decode(uri)))
        {
            h.update(&data);
        }
    }
    h.finalize().to_hex().to_string()
}

/// Percent-decoding of a relative URI, as glTF URIs are.
pub(crate) fn percent_decode(uri: &str) -> String {
    let bytes = uri.as_bytes();
    let mut out = Vec::with_capacity(bytes.len());
    let mut i = 0;
    while i < bytes.len() {
        if bytes[i] == b'%'
            && i + 2 < bytes.len()
            && let Some(v) = std::str::from_utf8(&bytes[i + 1..i + 3]).ok().and_then(|h| u8::from_str_radix(h, 16).ok())
        {
            out.push(v);
            i += 3;
            continue;
        }
        out.push(bytes[i]);
        i += 1;
    }
    String::from_utf8_lossy(&out).into_owned()
}

fn wrap(mode: gltf::texture::WrappingMode) -> Wrap {
    match mode {
        gltf::texture::WrappingMode::ClampToEdge => Wrap::ClampToEdge,
        gltf::texture::WrappingMode::MirroredRepeat => Wrap::MirroredRepeat,
        gltf::texture::WrappingMode::Repeat => Wrap::Repeat,
    }
}

/// The image each texture reads: its EXT_texture_webp source when it has one (the author's
/// first choice), else its core `source` (a KHR_texture_basisu texture reads its PNG or JPEG
/// fallback: Basis cannot be decoded here). A texture with neither is refused.
fn texture_sources(document: &gltf::Document) -> Result<Vec<usize>, String> {
    let json = document.as_json();
    let images = json.images.len();
    json.textures
        .iter()
        .enumerate()
        .map(|(i, t)| {
            let webp = t.extensions.as_ref().and_then(|e| e.others.get("EXT_texture_webp"));
            let core = t.source.value();
            match webp.and_then(|w| w.get("source")) {
                Some(v) => {
                    v.as_u64().map(|v| v as usize).filter(|&v| v < images).ok_or_else(|| {
                        format!("texture {i}: EXT_texture_webp source {v} names no image of the {images}")
                    })
                }
                None if core != u32::MAX as usize => Ok(core),
                None => Err(format!("texture {i} has no image (no source, and no EXT_texture_webp source)")),
            }
        })
        .collect()
}

/// The images that textures read (`sources`, from [`texture_sources`]), decoded; the others
/// (such as a PNG fallback beside a WebP) get an empty placeholder so that image indices keep
/// their meaning.
fn texture_images(
    document: &gltf::Document,
    sources: &[usize],
    base: Option<&Path>,
    buffers: &[gltf::buffer::Data],
) -> Result<Vec<Image>, String> {
    let used: std::collections::BTreeSet<usize> = sources.iter().copied().collect();
    let mut total: u64 = 0;
    let mut webp = std::collections::BTreeSet::new();
    for image in document.images().filter(|i| used.contains(&i.index())) {
        let (w, h, format) = image_header(&image, base, buffers)
            .map_err(|e| format!("image {} '{}': {e}", image.index(), image.name().unwrap_or("")))?;
        if format == Some(image::ImageFormat::WebP) {
            webp.insert(image.index());
        }
        let pixels = w as u64 * h as u64;
        total += pixels;
        if pixels > MAX_IMAGE_PIXELS || total > MAX_SCENE_IMAGE_PIXELS {
            return Err(format!(
                "image {} '{}' is {w}x{h}: over the limit of {MAX_IMAGE_PIXELS} pixels an image and \
                 {MAX_SCENE_IMAGE_PIXELS} a scene ({total} so far), checked before decoding",
                image.index(),
                image.name().unwrap_or("")
            ));
        }
    }
    document
        .images()
        .map(|image| {
            if !used.contains(&image.index()) {
                return Ok(Image { width: 0, height: 0, texels: Texels::Eight(Vec::new()) });
            }
            let name = match (image.name(), image.source()) {
                (Some(name), _) => name.to_string(),
                (None, gltf::image::Source::Uri { uri, .. }) if !uri.starts_with("data:") => uri.to_string(),
                _ => String::new(),
            };
            let problem = |e: String| format!("image {} '{name}': {e}", image.index());
            // WebP (EXT_texture_webp) is decoded here; PNG and JPEG by the glTF crate's decoder,
            // whose bytes the pinned renders were made with.
            if webp.contains(&image.index()) {
                let bytes = image_bytes(&image, base, buffers, None).map_err(problem)?;
                let decoded = image::load_from_memory_with_format(&bytes, image::ImageFormat::WebP)
                    .map_err(|e| problem(format!("the WebP does not decode: {e}")))?
                    .into_rgba8();
                let (width, height) = decoded.dimensions();
                return Ok(Image { width, height, texels: Texels::Eight(decoded.pixels().map(|p| p.0).collect()) });
            }
            let data =
                gltf::image::Data::from_source(image.source(), base, buffers).map_err(|e| problem(e.to_string()))?;
            convert_image(&data).map_err(problem)
        })
        .collect()
}

/// Largest texture decoded (16384 x 16384 would be 1 GiB of RGBA8), and the most texture pixels
/// one scene may decode: a 256 KB PNG that claims 12,000 x 12,000 pixels took 540 MB a load.
pub const MAX_IMAGE_PIXELS: u64 = 1 << 26;
pub const MAX_SCENE_IMAGE_PIXELS: u64 = 1 << 28;

/// An image's width, height and format (as its first bytes say) from its header alone, nothing
/// decoded.
fn image_header(
    image: &gltf::Image,
    base: Option<&Path>,
    buffers: &[gltf::buffer::Data],
) -> Result<(u32, u32, Option<image::ImageFormat>), String> {
    // A header is all the size needs; a megabyte holds any format's.
    let bytes = image_bytes(image, base, buffers, Some(1 << 20))?;
    let reader =
        image::ImageReader::new(std::io::Cursor::new(&bytes[..])).with_guessed_format().map_err(|e| e.to_string())?;
    let format = reader.format();
    let (w, h) = reader.into_dimensions().map_err(|e| e.to_string())?;
    Ok((w, h, format))
}

/// An image's encoded bytes (the first `head` of them, when given): from its buffer view, its
/// data URI, or its file beside the glTF.
fn image_bytes(
    image: &gltf::Image,
    base: Option<&Path>,
    buffers: &[gltf::buffer::Data],
    head: Option<u64>,
) -> Result<Vec<u8>, String> {
    use base64::Engine;
    let cut = |bytes: &[u8]| bytes[..head.map_or(bytes.len(), |h| bytes.len().min(h as usize))].to_vec();
    match image.source() {
        gltf::image::Source::View { view, .. } => {
            let buffer = buffers.get(view.buffer().index()).map_or(&[][..], |b| &b.0[..]);
            Ok(cut(buffer.get(view.offset()..view.offset() + view.length()).unwrap_or(&[])))
        }
        gltf::image::Source::Uri { uri, .. } => {
            match uri.strip_prefix("data:").and_then(|rest| rest.split_once(";base64,")) {
                Some((_, data)) => base64::engine::general_purpose::STANDARD
                    .decode(data)
                    .map(|b| cut(&b))
                    .map_err(|e| format!("its data URI is not base64: {e}")),
                None if uri.contains(':') => Err(format!("'{uri}' is not a relative file URI")),
                None => {
                    let path = base.unwrap_or(Path::new(".")).join(percent_decode(uri));
                    let file = std::fs::File::open(&path).map_err(|e| format!("{}: {e}", path.display()))?;
                    let mut bytes = Vec::new();
                    std::io::Read::read_to_end(&mut std::io::Read::take(file, head.unwrap_or(u64::MAX)), &mut bytes)
                        .map_err(|e| format!("{}: {e}", path.display()))?;
                    Ok(bytes)
                }
            }
        }
    }
}

fn convert_image(data: &gltf::image::Data) -> Result<Image, String> {
    use gltf::image::Format;
    let (w, h) = (data.width, data.height);
    let n = w as usize * h as usize;
    let p = &data.pixels;
    let channels = match data.format {
        Format::R8 => 1,
        Format::R8G8 => 2,
        Format::R8G8B8 => 3,
        Format::R8G8B8A8 => 4,
        Format::R16 => 1,
        Format::R16G16 => 2,
        Format::R16G16B16 => 3,
        Format::R16G16B16A16 => 4,
        Format::R32G32B32FLOAT => 3,
        Format::R32G32B32A32FLOAT => 4,
    };
    let bytes_per = match data.format {
        Format::R16 | Format::R16G16 | Format::R16G16B16 | Format::R16G16B16A16 => 2,
        Format::R32G32B32FLOAT | Format::R32G32B32A32FLOAT => 4,
        _ => 1,
    };
    if p.len() < n * channels * bytes_per {
        return Err(format!("image of {w}x{h} holds only {} bytes", p.len()));
    }
    // The decoder hands over its samples in the machine's byte order. 8-bit images stay 8-bit;
    // 16-bit and float ones keep 16 bits.
    let read16 = |i: usize| -> u16 {
        match bytes_per {
            2 => u16::from_ne_bytes([p[2 * i], p[2 * i + 1]]),
            _ => {
                let v = f32::from_ne_bytes([p[4 * i], p[4 * i + 1], p[4 * i + 2], p[4 * i + 3]]);
                (v.clamp(0.0, 1.0) * 65535.0).round() as u16
            }
        }
    };
    let texels = match bytes_per {
        1 => Texels::Eight((0..n).map(|i| rgba(channels, |k| p[i * channels + k], u8::MAX)).collect()),
        _ => Texels::Sixteen((0..n).map(|i| rgba(channels, |k| read16(i * channels + k), u16::MAX)).collect()),
    };
    Ok(Image { width: w, height: h, texels })
}

/// One texel as RGBA from its `channels` values `c(0..channels)`: grey, grey and alpha (as PNG's
/// two-channel images are, and as viewers show them), RGB, or RGBA; `opaque` fills alpha.
fn rgba<T: Copy>(channels: usize, c: impl Fn(usize) -> T, opaque: T) -> [T; 4] {
    match channels {
        1 => [c(0), c(0), c(0), opaque],
        2 => [c(0), c(0), c(0), c(1)],
        3 => [c(0), c(1), c(2), opaque],
        _ => [c(0), c(1), c(2), c(3)],
    }
}

fn texture_ref(info: Option<gltf::texture::Info>) -> Option<TextureRef> {
    let info = info?;
    let transform = info.texture_transform();
    let texcoord = transform.as_ref().and_then(|t| t.tex_coord()).unwrap_or(info.tex_coord());
    Some(TextureRef {
        texture: info.texture().index() as u32,
        texcoord,
        transform: transform.map(|t| texture_transform(t.offset(), t.rotation(), t.scale())),
    })
}

/// The glTF crate exposes KHR_texture_transform on `textureInfo` but not on
/// `normalTextureInfo`: read the extension's JSON there.
fn normal_texture_ref(n: &gltf::material::NormalTexture) -> TextureRef {
    json_texture_ref(n.texture().index() as u32, n.tex_coord(), n.extension_value("KHR_texture_transform"))
}

/// A texture reference from a texture index, its `texCoord` and the JSON of its
/// KHR_texture_transform (which may name another `texCoord`).
fn json_texture_ref(texture: u32, texcoord: u32, transform: Option<&serde_json::Value>) -> TextureRef {
    let pair = |key: &str, default: [f32; 2]| -> [f32; 2] {
        transform
            .and_then(|e| e.get(key))
            .and_then(|v| v.as_array())
            .filter(|a| a.len() == 2)
            .and_then(|a| Some([a[0].as_f64()? as f32, a[1].as_f64()? as f32]))
            .unwrap_or(default)
    };
    let rotation = transform.and_then(|e| e.get("rotation")).and_then(|v| v.as_f64()).unwrap_or(0.0) as f32;
    let own_texcoord = transform.and_then(|e| e.get("texCoord")).and_then(|v| v.as_u64()).map(|t| t as u32);
    TextureRef {
        texture,
        texcoord: own_texcoord.unwrap_or(texcoord),
        transform: transform
            .map(|_| texture_transform(pair("offset", [0.0, 0.0]), rotation, pair("scale", [1.0, 1.0]))),
    }
}

/// A material extension's JSON, for extensions the glTF crate does not parse (null when the
/// material does not use it, so every value takes its default): factors are checked to lie in
/// [0, 1] and textures to exist (`textures` of them).
struct ExtensionJson<'a> {
    name: &'static str,
    json: &'a serde_json::Value,
    textures: usize,
}

impl<'a> ExtensionJson<'a> {
    fn of(m: &'a gltf::Material, name: &'static str, textures: usize) -> Self {
        const ABSENT: serde_json::Value = serde_json::Value::Null;
        Self { name, json: m.extension_value(name).unwrap_or(&ABSENT), textures }
    }

    fn factor(&self, key: &str, default: f32) -> Result<f32, String> {
        self.number(key, default, |f| (0.0..=1.0).contains(&f), "a number between 0 and 1")
    }

    /// A number that `valid` accepts, or `default` when absent; the error says it should be
    /// `expected`.
    fn number(&self, key: &str, default: f32, valid: impl Fn(f64) -> bool, expected: &str) -> Result<f32, String> {
        match self.json.get(key) {
            None => Ok(default),
            Some(v) => match v.as_f64() {
                Some(f) if valid(f) => Ok(f as f32),
                _ => Err(format!("{} {key} {v} is not {expected}", self.name)),
            },
        }
    }

    /// An RGB factor, black by default.
    fn color(&self, key: &str) -> Result<Vec3, String> {
        let Some(v) = self.json.get(key) else { return Ok(Vec3::ZERO) };
        let rgb = v.as_array().filter(|a| a.len() == 3).and_then(|a| {
            let c: Vec<f64> = a.iter().filter_map(|c| c.as_f64()).filter(|c| (0.0..=1.0).contains(c)).collect();
            (c.len() == 3).then(|| Vec3::new(c[0] as f32, c[1] as f32, c[2] as f32))
        });
        rgb.ok_or_else(|| format!("{} {key} {v} is not three numbers between 0 and 1", self.name))
    }

    /// A normal texture's `scale` (1 by default): any finite number.
    fn texture_scale(&self, key: &str) -> Result<f32, String> {
        match self.json.get(key).and_then(|info| info.get("scale")) {
            None => Ok(1.0),
            Some(v) => v
                .as_f64()
                .map(|s| s as f32)
                .filter(|s| s.is_finite())
                .ok_or_else(|| format!("{} {key} scale {v} is not a finite number", self.name)),
        }
    }

    fn texture(&self, key: &str) -> Result<Option<TextureRef>, String> {
        let Some(info) = self.json.get(key) else { return Ok(None) };
        let index = info.get("index").and_then(|i| i.as_u64()).filter(|&i| (i as usize) < self.textures);
        let Some(index) = index else {
            return Err(format!("{} {key} names no texture of the {} in the file", self.name, self.textures));
        };
        let texcoord = match info.get("texCoord") {
            None => 0,
            Some(t) => t.as_u64().filter(|&t| t < 2).ok_or(format!("{} {key}: texCoord {t}", self.name))?,
        };
        let transform = info.get("extensions").and_then(|e| e.get("KHR_texture_transform"));
        Ok(Some(json_texture_ref(index as u32, texcoord as u32, transform)))
    }
}

/// KHR_materials_volume: a solid when `thicknessFactor` is above 0 (0, the default, is a thin
/// wall), with its attenuation colour and distance (absent: none). The thickness itself (and its
/// texture) only approximates the geometry for rasterisers: a path tracer has the geometry.
fn volume(e: &ExtensionJson) -> Result<Option<tessera_render::Volume>, String> {
    let thickness = e.number("thicknessFactor", 0.0, |t| t.is_finite() && t >= 0.0, "a number >= 0")?;
    e.texture("thicknessTexture")?;
    let attenuation_distance =
        e.number("attenuationDistance", f32::INFINITY, |d| d > 0.0 && (d as f32).is_finite(), "a positive number")?;
    let attenuation_color =
        if e.json.get("attenuationColor").is_some() { e.color("attenuationColor")? } else { Vec3::ONE };
    Ok((thickness > 0.0).then_some(tessera_render::Volume { attenuation_color, attenuation_distance }))
}

fn convert_material(m: &gltf::Material, textures: usize) -> Result<Material, String> {
    let pbr = m.pbr_metallic_roughness();
    let coat = ExtensionJson::of(m, "KHR_materials_clearcoat", textures);
    let sheen = ExtensionJson::of(m, "KHR_materials_sheen", textures);
    let anisotropy = ExtensionJson::of(m, "KHR_materials_anisotropy", textures);
    let strength = m.emissive_strength().unwrap_or(1.0);
    let specular = m.specular();
    let finite = |v: f32, what: &str| {
        if v.is_finite() { Ok(v) } else { Err(format!("{what} is not finite")) }
    };
    let extras = extras::parse(m.extras().as_ref().map(|r| r.get()))?;
    let mut material = Material {
        name: m.name().unwrap_or("").to_string(),
        base_color: Vec4::from_array(pbr.base_color_factor()),
        base_color_texture: texture_ref(pbr.base_color_texture()),
        metallic: finite(pbr.metallic_factor(), "metallicFactor")?,
        roughness: finite(pbr.roughness_factor(), "roughnessFactor")?,
        metallic_roughness_texture: texture_ref(pbr.metallic_roughness_texture()),
        emissive: Vec3::from_array(m.emissive_factor()) * finite(strength, "emissiveStrength")?.max(0.0),
        emissive_texture: texture_ref(m.emissive_texture()),
        normal_texture: m.normal_texture().map(|n| normal_texture_ref(&n)),
        normal_scale: m.normal_texture().map_or(1.0, |n| n.scale()),
        specular: specular.as_ref().map_or(1.0, |s| s.specular_factor()),
        specular_texture: specular.as_ref().and_then(|s| texture_ref(s.specular_texture())),
        specular_color: specular.as_ref().map_or(Vec3::ONE, |s| Vec3::from_array(s.specular_color_factor())),
        specular_color_texture: specular.as_ref().and_then(|s| texture_ref(s.specular_color_texture())),
        ior: match m.ior() {
            Some(ior) if !(ior.is_finite() && ior >= 0.0) => {
                return Err(format!("ior {ior} is not a finite number >= 0"));
            }
            ior => ior.unwrap_or(1.5),
        },
        // The glTF crate parses KHR_materials_transmission (and checks its texture's index).
        transmission: match m.transmission().map(|t| t.transmission_factor()) {
            Some(t) if !(0.0..=1.0).contains(&t) => {
                return Err(format!("transmissionFactor {t} is not a number between 0 and 1"));
            }
            t => t.unwrap_or(0.0),
        },
        transmission_texture: m.transmission().and_then(|t| texture_ref(t.transmission_texture())),
        clearcoat: coat.factor("clearcoatFactor", 0.0)?,
        clearcoat_texture: coat.texture("clearcoatTexture")?,
        clearcoat_roughness: coat.factor("clearcoatRoughnessFactor", 0.0)?,
        clearcoat_roughness_texture: coat.texture("clearcoatRoughnessTexture")?,
        clearcoat_normal_texture: coat.texture("clearcoatNormalTexture")?,
        clearcoat_normal_scale: coat.texture_scale("clearcoatNormalTexture")?,
        sheen_color: sheen.color("sheenColorFactor")?,
        sheen_color_texture: sheen.texture("sheenColorTexture")?,
        sheen_roughness: sheen.factor("sheenRoughnessFactor", 0.0)?,
        sheen_roughness_texture: sheen.texture("sheenRoughnessTexture")?,
        volume: volume(&ExtensionJson::of(m, "KHR_materials_volume", textures))?,
        anisotropy_strength: anisotropy.factor("anisotropyStrength", 0.0)?,
        anisotropy_rotation: anisotropy.number(
            "anisotropyRotation",
            0.0,
            |r| (r as f32).is_finite(),
            "a finite number of radians",
        )?,
        anisotropy_texture: anisotropy.texture("anisotropyTexture")?,
        alpha_mode: match m.alpha_mode() {
            gltf::material::AlphaMode::Opaque => AlphaMode::Opaque,
            gltf::material::AlphaMode::Mask => AlphaMode::Mask { cutoff: m.alpha_cutoff().unwrap_or(0.5) },
            gltf::material::AlphaMode::Blend => AlphaMode::Blend,
        },
        double_sided: m.double_sided(),
        unlit: false,
        model: extras.model.unwrap_or(tessera_render::Model::Gltf),
        spectra: extras.spectra,
    };
    // A measured reflectance replaces baseColorFactor; an emission spectrum sets the colour and
    // the factor the luminance. RGB renders use their colours.
    material.match_rgb_to_spectra();
    if m.extension_value("KHR_materials_unlit").is_some() {
        material.make_unlit();
    }
    Ok(material)
}

/// Where a mesh instance stands in the scene's rest pose: its node's world transform, or, for a
/// skinned mesh, its skin's joint matrices (glTF ignores the mesh node's own transform then), and
/// the morph target weights (the node's, else the mesh's defaults).
struct Pose<'a> {
    world: Mat4,
    joints: Option<&'a [Mat4]>,
    weights: &'a [f32],
}

/// The skin's joint matrices in the rest pose: each joint's world transform times its inverse
/// bind matrix (identity when the skin has none). A joint outside the scene's tree stands where
/// its own transform puts it.
fn joint_matrices(
    skin: &gltf::Skin,
    worlds: &[Option<Mat4>],
    buffers: &[gltf::buffer::Data],
) -> Result<Vec<Mat4>, String> {
    let inverse_bind: Vec<Mat4> = match skin.inverse_bind_matrices() {
        Some(a) => {
            if a.dimensions() != gltf::accessor::Dimensions::Mat4 || a.data_type() != gltf::accessor::DataType::F32 {
                return Err(format!("skin {}: inverse bind matrices must be float MAT4s", skin.index()));
            }
            items::<[[f32; 4]; 4]>(&a, buffers)?.iter().map(Mat4::from_cols_array_2d).collect()
        }
        None => Vec::new(),
    };
    let joints: Vec<gltf::Node> = skin.joints().collect();
    if !inverse_bind.is_empty() && inverse_bind.len() < joints.len() {
        return Err(format!(
            "skin {}: {} inverse bind matrices for {} joints",
            skin.index(),
            inverse_bind.len(),
            joints.len()
        ));
    }
    Ok(joints
        .iter()
        .enumerate()
        .map(|(k, j)| {
            let world = worlds[j.index()].unwrap_or_else(|| Mat4::from_cols_array_2d(&j.transform().matrix()));
            world * inverse_bind.get(k).copied().unwrap_or(Mat4::IDENTITY)
        })
        .collect())
}

/// Adds the morph targets' displacements, each times its weight, to the attributes they move.
fn apply_morph_targets(
    prim: &gltf::Primitive,
    weights: &[f32],
    buffers: &[gltf::buffer::Data],
    positions: &mut [Vec3],
    normals: &mut Option<Vec<Vec3>>,
    tangents: &mut Option<Vec<Vec4>>,
) -> Result<(), String> {
    let n = positions.len();
    for (target, &w) in prim.morph_targets().zip(weights) {
        if w == 0.0 || !w.is_finite() {
            continue;
        }
        let deltas = |a: Option<gltf::Accessor>| -> Result<Option<Vec<Vec3>>, String> {
            let Some(a) = a else { return Ok(None) };
            let d: Vec<Vec3> = read_floats::<3>(&a, buffers)?.into_iter().map(Vec3::from_array).collect();
            if d.len() != n {
                return Err(format!("accessor {}: a morph target of {} vertices for {n}", a.index(), d.len()));
            }
            Ok(Some(d))
        };
        if let Some(d) = deltas(target.positions())? {
            positions.iter_mut().zip(d).for_each(|(p, d)| *p += w * d);
        }
        if let (Some(d), Some(normals)) = (deltas(target.normals())?, normals.as_mut()) {
            normals.iter_mut().zip(d).for_each(|(v, d)| *v += w * d);
        }
        if let (Some(d), Some(tangents)) = (deltas(target.tangents())?, tangents.as_mut()) {
            tangents.iter_mut().zip(d).for_each(|(t, d)| *t += (w * d).extend(0.0));
        }
    }
    Ok(())
}

/// Poses a skinned primitive's vertices in world space by linear blend skinning: each vertex
/// moves by the weighted sum of its joints' matrices (weights normalised to sum 1; a vertex whose
/// weights do not sum to a positive number stays with `unskinned`, its node's transform).
/// Returns false, changing nothing, when the primitive has no JOINTS_0 and WEIGHTS_0.
fn apply_skin(
    prim: &gltf::Primitive,
    joints: &[Mat4],
    unskinned: Mat4,
    buffers: &[gltf::buffer::Data],
    positions: &mut [Vec3],
    normals: &mut Option<Vec<Vec3>>,
    tangents: &mut Option<Vec<Vec4>>,
) -> Result<bool, String> {
    use gltf::Semantic;
    let (Some(j), Some(w)) = (prim.get(&Semantic::Joints(0)), prim.get(&Semantic::Weights(0))) else {
        return Ok(false);
    };
    let indices: Vec<[u16; 4]> = match (j.data_type(), j.dimensions()) {
        (gltf::accessor::DataType::U8, gltf::accessor::Dimensions::Vec4) if !j.normalized() => {
            items::<[u8; 4]>(&j, buffers)?.into_iter().map(|v| v.map(u16::from)).collect()
        }
        (gltf::accessor::DataType::U16, gltf::accessor::Dimensions::Vec4) if !j.normalized() => {
            items::<[u16; 4]>(&j, buffers)?
        }
        _ => {
            return Err(format!(
                "accessor {} (JOINTS_0): joints must be unnormalised unsigned byte or short VEC4s",
                j.index()
            ));
        }
    };
    let weights = read_floats::<4>(&w, buffers)?;
    let n = positions.len();
    if indices.len() != n || weights.len() != n {
        return Err(format!("a skin of {} joints and {} weights for {n} vertices", indices.len(), weights.len()));
    }
    let mut matrices = Vec::with_capacity(n);
    for (i, (joint, weight)) in indices.iter().zip(&weights).enumerate() {
        let total: f32 = weight.iter().sum();
        let blended = total > 0.0 && total.is_finite();
        let mut m = if blended { Mat4::ZERO } else { unskinned };
        for (&joint, &w) in joint.iter().zip(weight) {
            let Some(&matrix) = joints.get(joint as usize) else {
                return Err(format!("vertex {i} names joint {joint} of a skin with {}", joints.len()));
            };
            if blended {
                m += matrix * (w / total);
            }
        }
        matrices.push(m);
    }
    // Zipped, not indexed: attributes of the wrong length are SceneBuilder::add_mesh's to refuse.
    for (p, m) in positions.iter_mut().zip(&matrices) {
        *p = m.transform_point3(*p);
    }
    let linear = |m: &Mat4| tessera_render::glam::Mat3::from_mat4(*m);
    for (v, m) in normals.iter_mut().flatten().zip(&matrices) {
        *v = linear(m).inverse().transpose() * *v;
    }
    for (t, m) in tangents.iter_mut().flatten().zip(&matrices) {
        *t = (linear(m) * t.truncate()).extend(t.w);
    }
    Ok(true)
}

/// How a primitive's material is chosen: its KHR_materials_variants mapping for `variant` when it
/// has one, else its own, else `default`; `count` materials are in the file.
#[derive(Clone, Copy)]
struct Materials {
    default: u32,
    count: usize,
    variant: Option<usize>,
}

impl Materials {
    fn of(&self, prim: &gltf::Primitive, mesh: &str) -> Result<u32, String> {
        let own = prim.material().index().map_or(self.default, |i| i as u32);
        let Some(variant) = self.variant else { return Ok(own) };
        let mappings = prim.extension_value("KHR_materials_variants").and_then(|v| v.get("mappings"));
        let Some(mappings) = mappings.and_then(|m| m.as_array()) else { return Ok(own) };
        for m in mappings {
            let names_it = m
                .get("variants")
                .and_then(|v| v.as_array())
                .is_some_and(|v| v.iter().any(|i| i.as_u64() == Some(variant as u64)));
            if names_it {
                return m
                    .get("material")
                    .and_then(|i| i.as_u64())
                    .filter(|&i| (i as usize) < self.count)
                    .map(|i| i as u32)
                    .ok_or_else(|| {
                        format!(
                            "mesh '{mesh}': a KHR_materials_variants mapping names no material of the {}",
                            self.count
                        )
                    });
            }
        }
        Ok(own)
    }
}

/// The names of the file's material variants (KHR_materials_variants), in index order.
fn variant_names(document: &gltf::Document) -> Result<Vec<String>, String> {
    let Some(v) = document.extension_value("KHR_materials_variants") else { return Ok(Vec::new()) };
    let list = v.get("variants").and_then(|l| l.as_array()).ok_or("KHR_materials_variants has no variants list")?;
    list.iter()
        .enumerate()
        .map(|(i, v)| {
            v.get("name").and_then(|n| n.as_str()).map(str::to_string).ok_or(format!("variant {i} has no name"))
        })
        .collect()
}

fn add_mesh(
    builder: &mut SceneBuilder,
    mesh: &gltf::Mesh,
    pose: &Pose,
    buffers: &[gltf::buffer::Data],
    materials: Materials,
    info: &mut SceneInfo,
) -> Result<(), String> {
    use gltf::Semantic;
    use gltf::mesh::Mode;
    let name = mesh.name().unwrap_or("").to_string();
    for prim in mesh.primitives() {
        let mode = prim.mode();
        if !matches!(mode, Mode::Triangles | Mode::TriangleStrip | Mode::TriangleFan) {
            info.warnings.push(format!("mesh '{name}': {mode:?} primitive skipped (only triangles render)"));
            continue;
        }
        let Some(positions) = prim.get(&Semantic::Positions) else {
            info.warnings.push(format!("mesh '{name}': primitive without POSITION skipped"));
            continue;
        };
        let attribute = |semantic: Semantic| prim.get(&semantic);
        let mut positions: Vec<Vec3> = read_floats(&positions, buffers)?.into_iter().map(Vec3::from_array).collect();
        let vectors = |semantic| attribute(semantic).map(|a| read_floats::<3>(&a, buffers)).transpose();
        let pairs = |semantic| attribute(semantic).map(|a| read_floats::<2>(&a, buffers)).transpose();
        let n = positions.len() as u32;
        let vertices = match prim.indices() {
            Some(a) => read_indices(&a, buffers)?,
            None => (0..n).collect(),
        };
        let mut normals: Option<Vec<Vec3>> =
            vectors(Semantic::Normals)?.map(|v| v.into_iter().map(Vec3::from_array).collect());
        let mut tangents: Option<Vec<Vec4>> = attribute(Semantic::Tangents)
            .map(|a| read_floats::<4>(&a, buffers))
            .transpose()?
            .map(|v| v.into_iter().map(Vec4::from_array).collect());
        apply_morph_targets(&prim, pose.weights, buffers, &mut positions, &mut normals, &mut tangents)
            .map_err(|e| format!("mesh '{name}': {e}"))?;
        let skinned = match pose.joints {
            Some(joints) => apply_skin(&prim, joints, pose.world, buffers, &mut positions, &mut normals, &mut tangents)
                .map_err(|e| format!("mesh '{name}': {e}"))?,
            None => false,
        };
        let data = MeshData {
            normals,
            uv0: pairs(Semantic::TexCoords(0))?.map(|v| v.into_iter().map(Vec2::from_array).collect()),
            uv1: pairs(Semantic::TexCoords(1))?.map(|v| v.into_iter().map(Vec2::from_array).collect()),
            tangents,
            colors: read_colors(&prim, buffers)?,
            indices: triangle_list(mode, &vertices),
            material: materials.of(&prim, &name)?,
            positions,
        };
        // A skinned primitive is already in world space.
        let transform = if skinned { Mat4::IDENTITY } else { pose.world };
        builder.add_mesh(&name, data, transform).map_err(|e| e.to_string())?;
    }
    Ok(())
}

/// Triangle-list indices of a triangles, strip or fan primitive, by the glTF specification's
/// rules (section 3.7.2.1): strip triangle `i` is `v[i], v[i + 1 + i % 2], v[i + 2 - i % 2]`, which
/// keeps one winding; fan triangle `i` is `v[i + 1], v[i + 2], v[0]`.
fn triangle_list(mode: gltf::mesh::Mode, v: &[u32]) -> Vec<u32> {
    use gltf::mesh::Mode;
    let triangles = v.len().saturating_sub(2);
    match mode {
        Mode::TriangleStrip => (0..triangles).flat_map(|i| [v[i], v[i + 1 + i % 2], v[i + 2 - i % 2]]).collect(),
        Mode::TriangleFan => (0..triangles).flat_map(|i| [v[i + 1], v[i + 2], v[0]]).collect(),
        _ => v.to_vec(),
    }
}

/// COLOR_0 as linear RGBA (RGB gets alpha 1), which multiplies the base colour.
fn read_colors(prim: &gltf::Primitive, buffers: &[gltf::buffer::Data]) -> Result<Option<Vec<Vec4>>, String> {
    let Some(a) = prim.get(&gltf::Semantic::Colors(0)) else {
        return Ok(None);
    };
    Ok(Some(match a.dimensions() {
        gltf::accessor::Dimensions::Vec3 => {
            read_floats::<3>(&a, buffers)?.into_iter().map(|c| Vec3::from_array(c).extend(1.0)).collect()
        }
        _ => read_floats::<4>(&a, buffers)?.into_iter().map(Vec4::from_array).collect(),
    }))
}

/// An index accessor as `u32`s: unsigned bytes, shorts or ints, not normalised.
fn read_indices(a: &gltf::Accessor, buffers: &[gltf::buffer::Data]) -> Result<Vec<u32>, String> {
    use gltf::accessor::DataType;
    let bad = |problem: &str| format!("accessor {} (indices): {problem}", a.index());
    if a.dimensions() != gltf::accessor::Dimensions::Scalar || a.normalized() {
        return Err(bad("indices must be unnormalised scalars"));
    }
    Ok(match a.data_type() {
        DataType::U8 => items::<u8>(a, buffers)?.into_iter().map(u32::from).collect(),
        DataType::U16 => items::<u16>(a, buffers)?.into_iter().map(u32::from).collect(),
        DataType::U32 => items::<u32>(a, buffers)?,
        other => return Err(bad(&format!("component type {other:?} cannot hold indices"))),
    })
}

/// Reads accessor `a` as vectors of `N` floats, whatever its component type: floats as they are,
/// integers as their values, or, when normalised, scaled to `[0, 1]` (unsigned) or `[-1, 1]`
/// (signed) as glTF defines. Core glTF stores some attributes (texture coordinates, colours) as
/// normalised integers; KHR_mesh_quantization allows integers for positions, normals and
/// tangents too.
fn read_floats<const N: usize>(a: &gltf::Accessor, buffers: &[gltf::buffer::Data]) -> Result<Vec<[f32; N]>, String>
where
    [i8; N]: gltf::accessor::Item,
    [u8; N]: gltf::accessor::Item,
    [i16; N]: gltf::accessor::Item,
    [u16; N]: gltf::accessor::Item,
    [u32; N]: gltf::accessor::Item,
    [f32; N]: gltf::accessor::Item,
{
    use gltf::accessor::DataType;
    if a.dimensions().multiplicity() != N {
        return Err(format!("accessor {}: type {:?} where a {N}-component vector belongs", a.index(), a.dimensions()));
    }
    let norm = a.normalized();
    fn each<T: Copy, const N: usize>(v: Vec<[T; N]>, f: impl Fn(T) -> f32) -> Vec<[f32; N]> {
        v.into_iter().map(|c| c.map(&f)).collect()
    }
    Ok(match a.data_type() {
        DataType::F32 => items::<[f32; N]>(a, buffers)?,
        DataType::U32 if !norm => each(items::<[u32; N]>(a, buffers)?, |c| c as f32),
        DataType::I8 => {
            each(items::<[i8; N]>(a, buffers)?, |c| if norm { (c as f32 / 127.0).max(-1.0) } else { c as f32 })
        }
        DataType::U8 => each(items::<[u8; N]>(a, buffers)?, |c| if norm { c as f32 / 255.0 } else { c as f32 }),
        DataType::I16 => {
            each(items::<[i16; N]>(a, buffers)?, |c| if norm { (c as f32 / 32767.0).max(-1.0) } else { c as f32 })
        }
        DataType::U16 => each(items::<[u16; N]>(a, buffers)?, |c| if norm { c as f32 / 65535.0 } else { c as f32 }),
        DataType::U32 => return Err(format!("accessor {}: normalised unsigned ints are not allowed", a.index())),
    })
}

/// Reads scalar accessor `a` as floats by [`read_floats`]'s rules (morph target weights may be
/// stored as normalised integers).
fn read_scalars(a: &gltf::Accessor, buffers: &[gltf::buffer::Data]) -> Result<Vec<f32>, String> {
    use gltf::accessor::DataType;
    if a.dimensions() != gltf::accessor::Dimensions::Scalar {
        return Err(format!("accessor {}: type {:?} where scalars belong", a.index(), a.dimensions()));
    }
    let norm = a.normalized();
    let scale = |c: f32, max: f32| if norm { (c / max).max(-1.0) } else { c };
    Ok(match a.data_type() {
        DataType::F32 => items::<f32>(a, buffers)?,
        DataType::U32 if !norm => items::<u32>(a, buffers)?.into_iter().map(|c| c as f32).collect(),
        DataType::I8 => items::<i8>(a, buffers)?.into_iter().map(|c| scale(c as f32, 127.0)).collect(),
        DataType::U8 => items::<u8>(a, buffers)?.into_iter().map(|c| scale(c as f32, 255.0)).collect(),
        DataType::I16 => items::<i16>(a, buffers)?.into_iter().map(|c| scale(c as f32, 32767.0)).collect(),
        DataType::U16 => items::<u16>(a, buffers)?.into_iter().map(|c| scale(c as f32, 65535.0)).collect(),
        DataType::U32 => return Err(format!("accessor {}: normalised unsigned ints are not allowed", a.index())),
    })
}

/// The most elements an accessor without a buffer view may declare (glTF fills it with zeros).
const VIEWLESS_MAX: usize = 1 << 24;

/// All `a.count()` elements of accessor `a`, as the glTF crate reads them (sparse ones
/// included), after the checks that crate leaves to debug assertions: each buffer view's
/// stride must hold an element, and the data must lie inside its buffer.
fn items<T: gltf::accessor::Item>(a: &gltf::Accessor, buffers: &[gltf::buffer::Data]) -> Result<Vec<T>, String> {
    let size = size_of::<T>();
    let views = a.view().into_iter().chain(a.sparse().map(|s| s.values().view()));
    for view in views {
        if let Some(stride) = view.stride().filter(|&s| s < size) {
            return Err(format!(
                "accessor {}: buffer view {} has byteStride {stride}, less than its {size}-byte elements",
                a.index(),
                view.index()
            ));
        }
    }
    if a.view().is_none() {
        // Zeros (with sparse substitutions): nothing in the file bounds the count, so a limit does.
        if a.count() > VIEWLESS_MAX {
            return Err(format!(
                "accessor {}: {} elements without a buffer view (at most {VIEWLESS_MAX})",
                a.index(),
                a.count()
            ));
        }
        if a.sparse().is_none() {
            return Ok((0..a.count()).map(|_| T::zero()).collect());
        }
    }
    let data = |b: gltf::Buffer| buffers.get(b.index()).map(|d| d.0.as_slice());
    let out: Vec<T> = gltf::accessor::Iter::new(a.clone(), data)
        .ok_or_else(|| format!("accessor {}: its data lies outside its buffer", a.index()))?
        .collect();
    if out.len() != a.count() {
        return Err(format!("accessor {}: {} elements where it declares {}", a.index(), out.len(), a.count()));
    }
    Ok(out)
}

fn convert_camera(camera: &gltf::Camera, world: Mat4, index: usize) -> Result<Camera, String> {
    let name = camera.name().map_or_else(|| format!("camera{index}"), str::to_string);
    let projection = match camera.projection() {
        gltf::camera::Projection::Perspective(p) => {
            let yfov = p.yfov();
            if !(yfov > 0.0 && yfov < std::f32::consts::PI) {
                return Err(format!("camera '{name}': yfov {yfov} is not between 0 and pi"));
            }
            Projection::Perspective { yfov }
        }
        gltf::camera::Projection::Orthographic(o) => {
            let ymag = o.ymag().abs();
            if !(ymag > 0.0 && ymag.is_finite()) {
                return Err(format!("camera '{name}': ymag {} must be positive and finite", o.ymag()));
            }
            Projection::Orthographic { ymag }
        }
    };
    if !world.is_finite() || world.determinant() == 0.0 {
        return Err(format!("camera '{name}': its node transform is singular or not finite"));
    }
    Ok(Camera { name, to_world: world, projection })
}

fn describe_camera(c: &Camera) -> String {
    match c.projection {
        Projection::Perspective { yfov } => format!("'{}' perspective, yfov {:.1} deg", c.name, yfov.to_degrees()),
        Projection::Orthographic { ymag } => format!("'{}' orthographic, ymag {ymag}", c.name),
    }
}

/// The light in world space; `None` when anything about it is not finite.
fn convert_light(light: &gltf::khr_lights_punctual::Light, world: Mat4) -> Option<PunctualLight> {
    let color = Vec3::from_array(light.color()) * light.intensity().max(0.0);
    let position = world.transform_point3(Vec3::ZERO);
    let direction = world.transform_vector3(Vec3::NEG_Z).normalize_or(Vec3::NEG_Z);
    if !(color.is_finite() && position.is_finite() && direction.is_finite()) {
        return None;
    }
    Some(match light.kind() {
        Kind::Directional => PunctualLight::Directional { direction, illuminance: color },
        Kind::Point => PunctualLight::Point { position, intensity: color, range: light.range() },
        Kind::Spot { inner_cone_angle, outer_cone_angle } => PunctualLight::Spot {
            position,
            direction,
            intensity: color,
            cos_inner: libm::cosf(inner_cone_angle),
            cos_outer: libm::cosf(outer_cone_angle),
            range: light.range(),
        },
    })
}
