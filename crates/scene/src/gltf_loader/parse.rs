//! Reading a glTF file once: its declared extensions, the glTF crate's validation and the checks
//! it leaves out (views inside their buffers, node trees that are trees, every drawn triangle
//! counted before anything expands), its buffers, textures, materials and animations, and the
//! hash of everything it references.

use super::materials::{convert_material, variant_names};
use super::nodes::read_clip;
use super::textures::{texture_images, texture_sources, wrap};
use super::{FALLBACKS, Parsed};
use crate::{LoadError, SUPPORTED_EXTENSIONS, SceneInfo};
use std::path::Path;
use tessera_render::Texture;

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
    check_external_files(&document, base).map_err(content)?;
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
    let drawn_triangles = instanced;
    Ok(Parsed {
        path: path.to_string(),
        document,
        buffers,
        images,
        textures,
        materials,
        roots,
        hash,
        info,
        drawn_triangles,
        clips,
    })
}

/// Most triangles a scene may draw, counted from the accessors before any mesh is expanded.
pub const MAX_TRIANGLES: u64 = 1 << 25;

/// glTF requires node hierarchies to be disjoint trees (section 3.5.3): no node has two
/// parents, no node is its own ancestor, and a scene's root nodes have no parent. Checked before
/// anything is expanded: a kilobyte of nodes that share children would otherwise stand for 2^40
/// instances.
pub(super) fn check_node_trees(document: &gltf::Document, roots: &[gltf::Node]) -> Result<(), String> {
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
pub(super) fn mesh_triangles(mesh: &gltf::Mesh) -> u64 {
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
pub(super) fn validate(document: &gltf::Document) -> Result<(), String> {
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

/// Names the first file a `.gltf` references (a buffer or an image) that is not beside it,
/// and says what to do; the glTF crate's own error names no file.
fn check_external_files(document: &gltf::Document, base: Option<&Path>) -> Result<(), String> {
    let Some(base) = base else { return Ok(()) };
    let buffers = document.buffers().filter_map(|b| match b.source() {
        gltf::buffer::Source::Uri(uri) => Some(uri),
        gltf::buffer::Source::Bin => None,
    });
    let images = document.images().filter_map(|i| match i.source() {
        gltf::image::Source::Uri { uri, .. } => Some(uri),
        gltf::image::Source::View { .. } => None,
    });
    for uri in buffers.chain(images).filter(|uri| !uri.starts_with("data:")) {
        let file = base.join(percent_decode(uri));
        if !file.is_file() {
            return Err(missing_file(uri, &file));
        }
    }
    Ok(())
}

/// What a missing referenced file's message says.
pub(crate) fn missing_file(uri: &str, file: &Path) -> String {
    format!(
        "'{uri}', which it references, is missing (no {}): copy it beside the .gltf, or export the scene as one \
         .glb file, which holds everything",
        file.display()
    )
}

/// `extensionsUsed` and `extensionsRequired`, read before the glTF crate validates anything,
/// so that an unsupported required extension gets a message that names it.
pub(super) fn declared_extensions(bytes: &[u8], path: &str) -> Result<(Vec<String>, Vec<String>), LoadError> {
    let json: &[u8] = if bytes.starts_with(b"glTF") {
        let glb = gltf::Glb::from_slice(bytes)
            .map_err(|e| LoadError::Gltf { path: path.to_string(), message: e.to_string() })?;
        return declared_extensions_json(&glb.json, path);
    } else {
        bytes
    };
    declared_extensions_json(json, path)
}

pub(super) fn declared_extensions_json(json: &[u8], path: &str) -> Result<(Vec<String>, Vec<String>), LoadError> {
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
pub(super) fn content_hash(bytes: &[u8], document: &gltf::Document, base: Option<&Path>) -> String {
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
