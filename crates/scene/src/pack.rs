//! Scene packages: what `tessera submit` uploads and workers load. A `.glb` travels as it is;
//! a `.gltf` is packed with its buffers and images into one GLB (only files inside the scene's
//! folder; a URI that escapes it is an error); a built-in travels as its name.

use crate::{LoadError, LoadOptions, LoadedScene, Source};
use serde_json::{Value, json};
use std::path::{Component, Path};

const BUILTIN_MARKER: &[u8] = b"tessera-builtin:";

/// Packs `spec` (a path or `builtin:NAME`) into the bytes that identify and carry the scene.
pub fn pack(spec: &str) -> Result<Vec<u8>, LoadError> {
    if let Some(name) = spec.strip_prefix("builtin:") {
        crate::builtin::load(name)?; // refuse unknown names here, not on a worker
        return Ok([BUILTIN_MARKER, name.as_bytes()].concat());
    }
    let path = Path::new(spec);
    let io = |e: std::io::Error| LoadError::Io { path: spec.to_string(), message: e.to_string() };
    match path.extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase).as_deref() {
        Some("glb") => std::fs::read(path).map_err(io),
        Some("gltf") => pack_gltf(path, &std::fs::read(path).map_err(io)?),
        _ => Err(LoadError::UnknownFormat(spec.to_string())),
    }
}

const BUNDLE_MARKER: &[u8] = b"tessera-bundle-v1\0";

/// Packs `spec` with the environment map file `map`: the scene's package and the map's bytes
/// travel (and are addressed by their hash) together.
pub fn pack_with_environment(spec: &str, map: &Path) -> Result<Vec<u8>, LoadError> {
    let scene = pack(spec)?;
    let name = map.display().to_string();
    let kind = crate::environment::Kind::of(map).ok_or_else(|| LoadError::Content {
        path: name.clone(),
        message: "an environment map must be a Radiance .hdr or an OpenEXR .exr file".into(),
    })?;
    let bytes = std::fs::read(map).map_err(|e| LoadError::Io { path: name, message: e.to_string() })?;
    let tag = match kind {
        crate::environment::Kind::Hdr => b'h',
        crate::environment::Kind::Exr => b'e',
    };
    Ok([BUNDLE_MARKER, &(scene.len() as u64).to_le_bytes(), &scene, &[tag], &bytes].concat())
}

/// An environment map file's bytes in a package, and its format.
type PackedMap<'a> = (&'a [u8], crate::environment::Kind);

/// A package's scene part and, for a bundle, its environment map.
fn unbundle<'a>(bytes: &'a [u8], name: &str) -> Result<(&'a [u8], Option<PackedMap<'a>>), LoadError> {
    let Some(rest) = bytes.strip_prefix(BUNDLE_MARKER) else { return Ok((bytes, None)) };
    let bad = || LoadError::Content { path: name.to_string(), message: "a truncated scene bundle".into() };
    let len = rest.get(..8).ok_or_else(bad)?;
    let len = u64::from_le_bytes(len.try_into().map_err(|_| bad())?);
    let rest = &rest[8..];
    let len = usize::try_from(len).ok().filter(|&n| n < rest.len()).ok_or_else(bad)?;
    let (scene, env) = rest.split_at(len);
    let kind = match env[0] {
        b'h' => crate::environment::Kind::Hdr,
        b'e' => crate::environment::Kind::Exr,
        _ => return Err(bad()),
    };
    Ok((scene, Some((&env[1..], kind))))
}

/// Loads packed bytes (see [`pack`]); `name` is used in messages.
pub fn load_packed(bytes: &[u8], name: &str, options: &LoadOptions) -> Result<LoadedScene, LoadError> {
    open_packed(bytes, name)?.pose(options)
}

/// Reads packed bytes (see [`pack`], [`pack_with_environment`]) without building the scene, to
/// pose it later; a bundle's environment map is read as far as its header, and decoded when a
/// render first uses it (a coordinator checking the package never decodes it).
pub fn open_packed(bytes: &[u8], name: &str) -> Result<Source, LoadError> {
    let (scene, environment) = unbundle(bytes, name)?;
    let mut source = if let Some(builtin) = scene.strip_prefix(BUILTIN_MARKER) {
        crate::open(&format!("builtin:{}", String::from_utf8_lossy(builtin)))?
    } else {
        crate::open_bytes(scene, None, name)?
    };
    if let Some((bytes, kind)) = environment {
        let decoded = crate::environment::Decoded::new(bytes.to_vec(), kind, &format!("{name} (its environment map)"))?;
        source.environment = Some(std::sync::Arc::new(decoded));
    }
    Ok(source)
}

/// A relative URI inside the scene's folder, percent-decoded; `None` when it escapes.
fn contained(uri: &str) -> Option<std::path::PathBuf> {
    let decoded = crate::gltf_loader::percent_decode(uri);
    let p = Path::new(&decoded);
    let inside = p.components().all(|c| matches!(c, Component::Normal(_) | Component::CurDir));
    (inside && !decoded.contains(':')).then(|| p.to_path_buf())
}

fn pack_gltf(path: &Path, json_bytes: &[u8]) -> Result<Vec<u8>, LoadError> {
    let name = path.display().to_string();
    let content = |message: String| LoadError::Content { path: name.clone(), message };
    let mut doc: Value = serde_json::from_slice(json_bytes)
        .map_err(|e| LoadError::Gltf { path: name.clone(), message: format!("invalid JSON: {e}") })?;
    let base = path.parent().unwrap_or(Path::new("."));
    let read = |uri: &str| -> Result<Vec<u8>, LoadError> {
        if uri.starts_with("data:") {
            return Err(content("data: URIs are packed by re-exporting as .glb".into()));
        }
        let rel = contained(uri).ok_or_else(|| content(format!("URI '{uri}' points outside the scene's folder")))?;
        let file = base.join(&rel);
        std::fs::read(&file).map_err(|e| match e.kind() {
            std::io::ErrorKind::NotFound => content(crate::gltf_loader::missing_file(uri, &file)),
            _ => content(format!("'{uri}': {e}")),
        })
    };
    let mut bin: Vec<u8> = Vec::new();
    let mut append = |bytes: &[u8]| -> usize {
        pad4(&mut bin, 0);
        let offset = bin.len();
        bin.extend_from_slice(bytes);
        offset
    };
    // Buffers: each becomes a slice of the one BIN buffer; views shift by its offset.
    let mut offsets = Vec::new();
    if let Some(buffers) = doc.get("buffers").and_then(Value::as_array) {
        for b in buffers {
            let bytes = match b.get("uri").and_then(Value::as_str) {
                Some(uri) if uri.starts_with("data:") => {
                    decode_data_uri(uri).ok_or_else(|| content("a buffer's data: URI is not base64".into()))?
                }
                Some(uri) => read(uri)?,
                None => return Err(content("a buffer without a URI (already a GLB?)".into())),
            };
            offsets.push(append(&bytes) as u64);
        }
    }
    if let Some(views) = doc.get_mut("bufferViews").and_then(Value::as_array_mut) {
        for v in views {
            let buffer = v.get("buffer").and_then(Value::as_u64).unwrap_or(0) as usize;
            let offset = v.get("byteOffset").and_then(Value::as_u64).unwrap_or(0);
            let shift = *offsets.get(buffer).ok_or_else(|| content(format!("bufferView refers to buffer {buffer}")))?;
            v["buffer"] = json!(0);
            v["byteOffset"] = json!(offset + shift);
        }
    }
    // Images with URIs become buffer views of the BIN buffer.
    let mut new_views = Vec::new();
    if let Some(images) = doc.get("images").and_then(Value::as_array) {
        for (i, img) in images.iter().enumerate() {
            if let Some(uri) = img.get("uri").and_then(Value::as_str) {
                let bytes = if uri.starts_with("data:") {
                    decode_data_uri(uri).ok_or_else(|| content("an image's data: URI is not base64".into()))?
                } else {
                    read(uri)?
                };
                let mime = if bytes.starts_with(b"\x89PNG") { "image/png" } else { "image/jpeg" };
                let offset = append(&bytes);
                new_views.push((i, offset, bytes.len(), mime));
            }
        }
    }
    let view_base = doc.get("bufferViews").and_then(Value::as_array).map_or(0, Vec::len);
    if !new_views.is_empty() {
        if doc.get("bufferViews").is_none() {
            doc["bufferViews"] = json!([]);
        }
        for (k, &(i, offset, len, mime)) in new_views.iter().enumerate() {
            if let Some(views) = doc["bufferViews"].as_array_mut() {
                views.push(json!({"buffer": 0, "byteOffset": offset, "byteLength": len}));
            }
            let img = &mut doc["images"][i];
            if let Some(obj) = img.as_object_mut() {
                obj.remove("uri");
            }
            img["bufferView"] = json!(view_base + k);
            img["mimeType"] = json!(mime);
        }
    }
    pad4(&mut bin, 0);
    if !bin.is_empty() {
        doc["buffers"] = json!([{"byteLength": bin.len()}]);
    }
    Ok(write_glb(&doc, &bin))
}

/// A GLB file of glTF JSON `doc` and binary chunk `bin` (left out when empty); each chunk is
/// padded to 4 bytes, as the format asks. `doc` names the buffer (its `byteLength`) itself.
pub fn write_glb(doc: &Value, bin: &[u8]) -> Vec<u8> {
    // A serde_json Value always serialises.
    let mut json_chunk = serde_json::to_vec(doc).unwrap_or_default();
    pad4(&mut json_chunk, b' ');
    let mut bin = bin.to_vec();
    pad4(&mut bin, 0);
    let total = 12 + 8 + json_chunk.len() + if bin.is_empty() { 0 } else { 8 + bin.len() };
    let mut glb = Vec::with_capacity(total);
    glb.extend_from_slice(b"glTF");
    glb.extend_from_slice(&2u32.to_le_bytes());
    glb.extend_from_slice(&(total as u32).to_le_bytes());
    glb.extend_from_slice(&(json_chunk.len() as u32).to_le_bytes());
    glb.extend_from_slice(b"JSON");
    glb.extend_from_slice(&json_chunk);
    if !bin.is_empty() {
        glb.extend_from_slice(&(bin.len() as u32).to_le_bytes());
        glb.extend_from_slice(b"BIN\0");
        glb.extend_from_slice(&bin);
    }
    glb
}

/// GLB chunks are 4-byte aligned.
fn pad4(bytes: &mut Vec<u8>, fill: u8) {
    while !bytes.len().is_multiple_of(4) {
        bytes.push(fill);
    }
}

/// The payload of a base64 `data:` URI.
fn decode_data_uri(uri: &str) -> Option<Vec<u8>> {
    let (_, b64) = uri.split_once(";base64,")?;
    const T: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut out = Vec::with_capacity(b64.len() * 3 / 4);
    let (mut acc, mut bits) = (0u32, 0u32);
    for c in b64.bytes().filter(|&c| c != b'=') {
        let v = T.iter().position(|&t| t == c)? as u32;
        acc = (acc << 6) | v;
        bits += 6;
        if bits >= 8 {
            bits -= 8;
            out.push((acc >> bits) as u8);
        }
    }
    Some(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn escaping_uris_are_refused() {
        assert!(contained("textures/a.png").is_some());
        assert!(contained("../secret.bin").is_none());
        assert!(contained("/etc/passwd").is_none());
        assert!(contained("a/%2E%2E/%2E%2E/b.bin").is_none());
        assert!(contained("file:///etc/passwd").is_none());
    }

    /// A package's environment map is read as far as its header when the package is opened
    /// (what the coordinator does to accept it): the census counts its texels for the memory
    /// budget, and the pixels are decoded, and their faults found, only when a render uses it.
    #[test]
    fn a_packages_map_is_counted_from_its_header_and_decoded_when_used() {
        let dir = tempfile::tempdir().unwrap();
        let header = b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 32 +X 64\n".to_vec();
        let whole = [header.clone(), [128u8, 128, 128, 129].repeat(64 * 32)].concat();
        for (file, bytes, decodes) in [("whole.hdr", whole, true), ("cut.hdr", header, false)] {
            let path = dir.path().join(file);
            std::fs::write(&path, &bytes).unwrap();
            let package = pack_with_environment("builtin:cornell-box", &path).unwrap();
            let source = open_packed(&package, "p").expect("opened without decoding the map");
            assert_eq!(source.census(None, None).unwrap().map_texels, 64 * 32);
            let map = source.environment(1.0, 0.0);
            assert_eq!(map.is_ok(), decodes, "{file}: {:?}", map.as_ref().err().map(|e| e.to_string()));
            if let Err(e) = map {
                assert!(e.to_string().contains("not a readable Radiance HDR"), "{e}");
            }
        }
    }

    #[test]
    fn data_uris_decode() {
        assert_eq!(decode_data_uri("data:application/octet-stream;base64,aGVsbG8=").unwrap(), b"hello");
    }
}
