//! Textures and their images: each texture's source (WebP or its fallback), every image's size
//! read from its header and bounded before anything is decoded, then decoded to texels.

use super::percent_decode;
use std::path::Path;
use tessera_render::{Image, Texels, Wrap};

pub(super) fn wrap(mode: gltf::texture::WrappingMode) -> Wrap {
    match mode {
        gltf::texture::WrappingMode::ClampToEdge => Wrap::ClampToEdge,
        gltf::texture::WrappingMode::MirroredRepeat => Wrap::MirroredRepeat,
        gltf::texture::WrappingMode::Repeat => Wrap::Repeat,
    }
}

/// The image each texture reads: its EXT_texture_webp source when it has one (the author's
/// first choice), else its core `source` (a KHR_texture_basisu texture reads its PNG or JPEG
/// fallback: Basis cannot be decoded here). A texture with neither is refused.
pub(super) fn texture_sources(document: &gltf::Document) -> Result<Vec<usize>, String> {
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
pub(super) fn texture_images(
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
    // Decoded in parallel (each image alone, so the texels are the same); the first failure in
    // the file's order is the one reported, as when they were decoded one by one.
    use rayon::prelude::*;
    let images: Vec<gltf::Image> = document.images().collect();
    images
        .into_par_iter()
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
        .collect::<Vec<_>>()
        .into_iter()
        .collect()
}

/// Largest texture decoded (16384 x 16384 would be 1 GiB of RGBA8), and the most texture pixels
/// one scene may decode: a 256 KB PNG that claims 12,000 x 12,000 pixels took 540 MB a load.
pub const MAX_IMAGE_PIXELS: u64 = 1 << 26;
pub const MAX_SCENE_IMAGE_PIXELS: u64 = 1 << 28;

/// An image's width, height and format (as its first bytes say) from its header alone, nothing
/// decoded.
pub(super) fn image_header(
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
pub(super) fn image_bytes(
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

pub(super) fn convert_image(data: &gltf::image::Data) -> Result<Image, String> {
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
pub(super) fn rgba<T: Copy>(channels: usize, c: impl Fn(usize) -> T, opaque: T) -> [T; 4] {
    match channels {
        1 => [c(0), c(0), c(0), opaque],
        2 => [c(0), c(0), c(0), c(1)],
        3 => [c(0), c(1), c(2), opaque],
        _ => [c(0), c(1), c(2), c(3)],
    }
}
