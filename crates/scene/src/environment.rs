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
    Decoded::new(bytes, kind, &name)?.map(strength, rotate_degrees)
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

/// A map file read as far as its header, decoded when first turned into a map (what a scene
/// package carries): a coordinator that only checks a package, and counts what the map will
/// cost a worker ([`Decoded::texels`]), never decodes it.
pub struct Decoded {
    name: String,
    pub hash: String,
    width: usize,
    height: usize,
    kind: Kind,
    bytes: Vec<u8>,
    /// Linear RGB, three floats a texel, row by row from the top; decoded once.
    rgb: std::sync::OnceLock<Result<Vec<f32>, String>>,
}

impl Decoded {
    /// Reads `bytes`'s header: its size is checked ([`MAX_TEXELS`]); the texels wait.
    pub fn new(bytes: Vec<u8>, kind: Kind, name: &str) -> Result<Decoded, LoadError> {
        let fail = |message: String| LoadError::Content { path: name.to_string(), message };
        let (width, height) = match kind {
            Kind::Hdr => hdr_size(&bytes).map_err(fail)?,
            Kind::Exr => exr_size(&bytes).map_err(fail)?,
        };
        check_size(width, height).map_err(fail)?;
        let hash = blake3::hash(&bytes).to_hex().to_string();
        Ok(Decoded { name: name.to_string(), hash, width, height, kind, bytes, rgb: Default::default() })
    }

    /// The texels, decoded now: three floats each, row by row from the top.
    fn decode(&self) -> Result<Vec<f32>, String> {
        match self.kind {
            Kind::Hdr => decode_hdr(&self.bytes, self.width, self.height),
            Kind::Exr => decode_exr(&self.bytes, self.width, self.height),
        }
    }

    /// How many texels the map has.
    pub fn texels(&self) -> u64 {
        self.width as u64 * self.height as u64
    }

    /// Decodes the map and checks its values, keeping nothing: what a coordinator does once when
    /// a package is uploaded (two uploads at most at once), so that a cut or damaged map is
    /// refused then rather than on every worker.
    pub fn check(&self) -> Result<(), LoadError> {
        let fail = |message: String| LoadError::Content { path: self.name.clone(), message };
        let rgb = self.decode().map_err(fail)?;
        match rgb.iter().position(|c| !c.is_finite() || *c < 0.0) {
            Some(i) => Err(fail(format!(
                "texel ({}, {}) holds {}: radiance must be finite and not negative",
                (i / 3) % self.width,
                (i / 3) / self.width,
                rgb[i]
            ))),
            None => Ok(()),
        }
    }

    /// The map scaled by `strength` and turned `rotate_degrees` about +Y; decoded the first
    /// time, its values checked.
    pub fn map(&self, strength: f32, rotate_degrees: f32) -> Result<Environment, LoadError> {
        let fail = |message: String| LoadError::Content { path: self.name.clone(), message };
        let rgb = self.rgb.get_or_init(|| self.decode());
        let rgb = rgb.as_ref().map_err(|e| fail(e.clone()))?;
        let (texels, _) = rgb.as_chunks::<3>();
        let map = EnvMap::new(self.width, self.height, texels, strength, rotate_degrees).map_err(fail)?;
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

fn hdr_reader(bytes: &[u8]) -> image::ImageReader<std::io::Cursor<&[u8]>> {
    image::ImageReader::with_format(std::io::Cursor::new(bytes), image::ImageFormat::Hdr)
}

fn hdr_size(bytes: &[u8]) -> Result<(usize, usize), String> {
    let (w, h) = hdr_reader(bytes).into_dimensions().map_err(|e| format!("not a readable Radiance HDR file: {e}"))?;
    Ok((w as usize, h as usize))
}

/// Decodes a Radiance HDR file of `width` x `height` texels (its size checked already, so the
/// decoder's own allocation limit, 512 MiB, which refused maps well under [`MAX_TEXELS`], is
/// lifted) into three floats a texel, without a copy.
fn decode_hdr(bytes: &[u8], width: usize, height: usize) -> Result<Vec<f32>, String> {
    let mut reader = hdr_reader(bytes);
    reader.no_limits();
    let image = reader.decode().map_err(|e| format!("not a readable Radiance HDR file: {e}"))?.into_rgb32f();
    if (image.width() as usize, image.height() as usize) != (width, height) {
        return Err("the HDR file's size changed between its header and its pixels".into());
    }
    Ok(image.into_raw())
}

fn exr_size(bytes: &[u8]) -> Result<(usize, usize), String> {
    let meta = exr::meta::MetaData::read_from_buffered(std::io::Cursor::new(bytes), false)
        .map_err(|e| format!("not a readable OpenEXR file: {e}"))?;
    let size = meta.headers.first().map(|h| h.layer_size).ok_or("an OpenEXR file without layers")?;
    Ok((size.0, size.1))
}

fn decode_exr(bytes: &[u8], width: usize, height: usize) -> Result<Vec<f32>, String> {
    use exr::prelude::*;
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
    let (read_width, texels) = image.layer_data.channel_data.pixels;
    if read_width != width || texels.len() != width * height {
        return Err("the OpenEXR file's first valid layer is not the size its header gives".into());
    }
    Ok(texels.into_flattened())
}
