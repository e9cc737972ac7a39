//! Environment maps from files: equirectangular Radiance `.hdr` (decoded by the `image` crate) or
//! OpenEXR `.exr` (the `exr` crate), checked before decoding (size from the header) and after
//! (finite, not negative), turned into a [`tessera_render::EnvMap`].

use crate::LoadError;
use std::path::Path;
use std::sync::Arc;
use tessera_render::{EnvMap, MAX_ENVIRONMENT_TEXELS as MAX_TEXELS};

/// An environment map read from a file, with what identifies it in image headers.
#[derive(Clone, Debug)]
pub struct Environment {
    pub map: Arc<EnvMap>,
    /// BLAKE3 of the file, hex.
    pub hash: String,
    pub width: usize,
    pub height: usize,
}

/// Reads `path` (`.hdr` or `.exr`) as an environment map scaled by `strength` and turned
/// `rotate_degrees` about +Y.
pub fn load(path: &Path, strength: f32, rotate_degrees: f32) -> Result<Environment, LoadError> {
    let name = path.display().to_string();
    let bytes = std::fs::read(path).map_err(|e| LoadError::Io { path: name.clone(), message: e.to_string() })?;
    let kind = Kind::of(path).ok_or_else(|| LoadError::Content {
        path: name.clone(),
        message: "an environment map must be a Radiance .hdr or an OpenEXR .exr file".into(),
    })?;
    Decoded::new(&bytes, kind, &name)?.map(strength, rotate_degrees)
}

/// The file formats a map may come in.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kind {
    Hdr,
    Exr,
}

impl Kind {
    /// By the file name's extension.
    pub fn of(path: &Path) -> Option<Kind> {
        match path.extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase).as_deref() {
            Some("hdr") => Some(Kind::Hdr),
            Some("exr") => Some(Kind::Exr),
            _ => None,
        }
    }
}

/// A map file decoded, before strength and rotation (what a scene package carries, decoded once).
pub struct Decoded {
    name: String,
    pub hash: String,
    width: usize,
    height: usize,
    texels: Vec<[f32; 3]>,
}

impl Decoded {
    pub fn new(bytes: &[u8], kind: Kind, name: &str) -> Result<Decoded, LoadError> {
        let fail = |message: String| LoadError::Content { path: name.to_string(), message };
        let (width, height, texels) = match kind {
            Kind::Hdr => decode_hdr(bytes).map_err(fail)?,
            Kind::Exr => decode_exr(bytes).map_err(fail)?,
        };
        let hash = blake3::hash(bytes).to_hex().to_string();
        Ok(Decoded { name: name.to_string(), hash, width, height, texels })
    }

    /// The map scaled by `strength` and turned `rotate_degrees` about +Y; its values checked.
    pub fn map(&self, strength: f32, rotate_degrees: f32) -> Result<Environment, LoadError> {
        let map = EnvMap::new(self.width, self.height, &self.texels, strength, rotate_degrees)
            .map_err(|message| LoadError::Content { path: self.name.clone(), message })?;
        Ok(Environment { map: Arc::new(map), hash: self.hash.clone(), width: self.width, height: self.height })
    }
}

/// The image header lines naming a render's environment map (one function for `tessera render`
/// and the farm, so that their images are the same files).
pub fn header_lines(name: &str, hash: &str, strength: f32, rotate_degrees: f32) -> String {
    format!(
        "environment_map={name}\nenvironment_map_hash={hash}\nenvironment_strength={strength}\nenvironment_rotate={rotate_degrees}\n"
    )
}

fn check_size(width: usize, height: usize) -> Result<(), String> {
    if width == 0 || height == 0 || width.saturating_mul(height) > MAX_TEXELS {
        return Err(format!(
            "{width} x {height} texels: at least 1 and at most {MAX_TEXELS} (checked before decoding)"
        ));
    }
    Ok(())
}

type Texels = (usize, usize, Vec<[f32; 3]>);

fn decode_hdr(bytes: &[u8]) -> Result<Texels, String> {
    let reader = || image::ImageReader::with_format(std::io::Cursor::new(bytes), image::ImageFormat::Hdr);
    let (w, h) = reader().into_dimensions().map_err(|e| format!("not a readable Radiance HDR file: {e}"))?;
    check_size(w as usize, h as usize)?;
    let image = reader().decode().map_err(|e| format!("not a readable Radiance HDR file: {e}"))?.into_rgb32f();
    Ok((w as usize, h as usize, image.pixels().map(|p| p.0).collect()))
}

fn decode_exr(bytes: &[u8]) -> Result<Texels, String> {
    use exr::prelude::*;
    let meta = exr::meta::MetaData::read_from_buffered(std::io::Cursor::new(bytes), false)
        .map_err(|e| format!("not a readable OpenEXR file: {e}"))?;
    let size = meta.headers.first().map(|h| h.layer_size).ok_or("an OpenEXR file without layers")?;
    check_size(size.0, size.1)?;
    let image = read()
        .no_deep_data()
        .largest_resolution_level()
        .rgba_channels(
            |resolution, _| (resolution.0, vec![[0.0f32; 3]; resolution.0 * resolution.1]),
            |(width, texels), position, (r, g, b, _a): (f32, f32, f32, f32)| {
                texels[position.1 * *width + position.0] = [r, g, b];
            },
        )
        .first_valid_layer()
        .all_attributes()
        .from_buffered(std::io::Cursor::new(bytes))
        .map_err(|e| format!("not a readable RGB OpenEXR file: {e}"))?;
    let (width, texels) = image.layer_data.channel_data.pixels;
    Ok((width, texels.len() / width.max(1), texels))
}
