//! OpenEXR files: float32 `R G B`, `variance.R/G/B` (variance of the pixel mean), `spp`,
//! `emitter` (fraction of samples whose camera ray saw an emitter), `A` in a transparent render
//! (fraction of samples whose camera ray hit the scene; `R G B` are premultiplied by it, as
//! OpenEXR's alpha convention is), `albedo.R/G/B` and `normal.X/Y/Z` when the render summed the
//! feature layers (`--aov albedo,normal`), `denoised.R/G/B` when it was denoised (`--denoise`),
//! plus one `tessera` text attribute with the scene hash, settings and seed. Scan lines in increasing order, so the same
//! image always gives the same bytes.

use crate::FilmError;
use exr::prelude::*;
use std::path::Path;

/// A resolved image: one entry per pixel, row-major from the top-left.
#[derive(Clone, Debug, PartialEq)]
pub struct ExrImage {
    pub width: u32,
    pub height: u32,
    pub rgb: Vec<[f32; 3]>,
    pub variance: Vec<[f32; 3]>,
    pub spp: Vec<f32>,
    pub emitter: Vec<f32>,
    /// A transparent render's coverage (`A`); `None`: the image is opaque.
    pub alpha: Option<Vec<f32>>,
    /// The feature layers a denoiser reads (`--aov albedo,normal`); `None`: not rendered.
    pub features: Option<FeatureLayers>,
    /// The colour denoised with the help of the feature layers (`--denoise`); `None`: not
    /// denoised. The raw colour stays in `rgb`.
    pub denoised: Option<Vec<[f32; 3]>>,
    /// The `tessera` header attribute: `key=value` lines.
    pub metadata: String,
}

impl ExrImage {
    /// An image of colours alone (a chart, a peer renderer's output): no variance, counts or
    /// layers.
    pub fn from_rgb(width: u32, height: u32, rgb: Vec<[f32; 3]>, metadata: String) -> Self {
        let n = rgb.len();
        Self {
            width,
            height,
            rgb,
            variance: vec![[0.0; 3]; n],
            spp: vec![0.0; n],
            emitter: vec![0.0; n],
            alpha: None,
            features: None,
            denoised: None,
            metadata,
        }
    }
}

/// Per pixel, the mean albedo and mean shading normal (world space, not renormalised; 0 where
/// every camera ray missed) at the samples' first diffuse or glossy hits.
#[derive(Clone, Debug, PartialEq)]
pub struct FeatureLayers {
    pub albedo: Vec<[f32; 3]>,
    pub normal: Vec<[f32; 3]>,
}

/// The feature layers' channel names, as Cycles and OIDN's examples name them.
const ALBEDO_CHANNELS: [&str; 3] = ["albedo.R", "albedo.G", "albedo.B"];
const NORMAL_CHANNELS: [&str; 3] = ["normal.X", "normal.Y", "normal.Z"];
const DENOISED_CHANNELS: [&str; 3] = ["denoised.R", "denoised.G", "denoised.B"];

const METADATA_ATTRIBUTE: &str = "tessera";

pub fn write_exr(image: &ExrImage, path: &Path) -> std::result::Result<(), FilmError> {
    let size = (image.width as usize, image.height as usize);
    let channel = |name: &str, values: Vec<f32>| AnyChannel::new(name, FlatSamples::F32(values));
    let rgb = |k: usize| image.rgb.iter().map(|p| p[k]).collect::<Vec<_>>();
    let var = |k: usize| image.variance.iter().map(|p| p[k]).collect::<Vec<_>>();
    let mut list = vec![
        channel("R", rgb(0)),
        channel("G", rgb(1)),
        channel("B", rgb(2)),
        channel("variance.R", var(0)),
        channel("variance.G", var(1)),
        channel("variance.B", var(2)),
        channel("spp", image.spp.clone()),
        channel("emitter", image.emitter.clone()),
    ];
    if let Some(alpha) = &image.alpha {
        list.push(channel("A", alpha.clone()));
    }
    let layers = image.features.iter().flat_map(|f| [(ALBEDO_CHANNELS, &f.albedo), (NORMAL_CHANNELS, &f.normal)]);
    for (names, values) in layers.chain(image.denoised.iter().map(|d| (DENOISED_CHANNELS, d))) {
        for (k, name) in names.iter().enumerate() {
            list.push(channel(name, values.iter().map(|p| p[k]).collect()));
        }
    }
    let channels = AnyChannels::sort(SmallVec::from_vec(list));
    let mut attributes = LayerAttributes::default();
    attributes.other.insert(Text::from(METADATA_ATTRIBUTE), AttributeValue::Text(Text::from(image.metadata.as_str())));
    let encoding =
        Encoding { compression: Compression::ZIP16, blocks: Blocks::ScanLines, line_order: LineOrder::Increasing };
    let layer = Layer::new(size, attributes, encoding, channels);
    Image::from_layer(layer)
        .write()
        .to_file(path)
        .map_err(|e| FilmError::Write { path: path.display().to_string(), message: e.to_string() })
}

pub fn read_exr(path: &Path) -> std::result::Result<ExrImage, FilmError> {
    let bytes = std::fs::read(path)
        .map_err(|e| FilmError::Read { path: path.display().to_string(), message: e.to_string() })?;
    read_exr_bytes(&bytes, &path.display().to_string())
}

/// [`read_exr`] of a file's bytes (`what` names them in errors).
pub fn read_exr_bytes(bytes: &[u8], what: &str) -> std::result::Result<ExrImage, FilmError> {
    let fail = |message: String| FilmError::Read { path: what.to_string(), message };
    let image = read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .first_valid_layer()
        .all_attributes()
        .from_buffered(std::io::Cursor::new(bytes))
        .map_err(|e| fail(e.to_string()))?;
    decode(&image.layer_data, fail)
}

fn decode(
    layer: &Layer<AnyChannels<FlatSamples>>,
    fail: impl Fn(String) -> FilmError,
) -> std::result::Result<ExrImage, FilmError> {
    let (w, h) = (layer.size.0, layer.size.1);
    let get = |name: &str| -> Option<Vec<f32>> {
        layer.channel_data.list.iter().find(|c| c.name == *name).map(|c| c.sample_data.values_as_f32().collect())
    };
    let need = |name: &str| get(name).ok_or_else(|| fail(format!("no '{name}' channel")));
    let (r, g, b) = (need("R")?, need("G")?, need("B")?);
    let zeros = || vec![0.0; w * h];
    let (vr, vg, vb) = (
        get("variance.R").unwrap_or_else(zeros),
        get("variance.G").unwrap_or_else(zeros),
        get("variance.B").unwrap_or_else(zeros),
    );
    let layer3 = |names: [&str; 3]| -> Option<Vec<[f32; 3]>> {
        let [x, y, z] = names.map(get);
        let (x, y, z) = (x?, y?, z?);
        Some((0..w * h).map(|i| [x[i], y[i], z[i]]).collect())
    };
    let features = match (layer3(ALBEDO_CHANNELS), layer3(NORMAL_CHANNELS)) {
        (Some(albedo), Some(normal)) => Some(FeatureLayers { albedo, normal }),
        _ => None,
    };
    let metadata = match layer.attributes.other.get(&Text::from(METADATA_ATTRIBUTE)) {
        Some(AttributeValue::Text(t)) => t.to_string(),
        _ => String::new(),
    };
    Ok(ExrImage {
        width: w as u32,
        height: h as u32,
        rgb: (0..w * h).map(|i| [r[i], g[i], b[i]]).collect(),
        variance: (0..w * h).map(|i| [vr[i], vg[i], vb[i]]).collect(),
        spp: get("spp").unwrap_or_else(zeros),
        emitter: get("emitter").unwrap_or_else(zeros),
        alpha: get("A"),
        features,
        denoised: layer3(DENOISED_CHANNELS),
        metadata,
    })
}
