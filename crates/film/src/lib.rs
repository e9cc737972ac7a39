//! The film: whole-image per-pixel sums merged exactly from tiles, OpenEXR output with
//! per-pixel variance and sample counts, an sRGB PNG preview, and error metrics between images.

mod denoise;
mod error;
mod exr_io;
mod metadata;
mod metrics;

pub use denoise::Denoiser;
pub use error::{ErrorEstimate, error_estimate, error_statement, relative_error, stopping_error, z_score};
pub use exr_io::{ExrImage, FeatureLayers, read_exr, read_exr_bytes, write_exr};
pub use metadata::image_metadata;
pub use metrics::{Comparison, compare, compare_where, saw_emitter};

use tessera_render::{FIXED_POINT_SCALE, FeatureSums, PixelSums, TileSums};

#[derive(Debug, thiserror::Error)]
pub enum FilmError {
    #[error("tile {x0},{y0} {width}x{height} does not fit the {image_width}x{image_height} film")]
    TileOutside { x0: u32, y0: u32, width: u32, height: u32, image_width: u32, image_height: u32 },
    #[error("tile sums hold {got} pixels, the tile has {expected}")]
    WrongPixelCount { got: usize, expected: usize },
    #[error("{}", if *.expected {
        "the render sums the feature layers (albedo, normal) and this result has none"
    } else {
        "this result carries feature layers (albedo, normal) the render did not ask for"
    })]
    FeatureLayers { expected: bool },
    #[error("denoising failed: {0}")]
    Denoise(String),
    #[error("cannot write {path}: {message}")]
    Write { path: String, message: String },
    #[error("cannot read {path}: {message}")]
    Read { path: String, message: String },
}

/// Per-pixel sums for a whole image.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Film {
    pub width: u32,
    pub height: u32,
    pub pixels: Vec<PixelSums>,
    /// The feature layers' sums, one per pixel, in a film that sums them; else empty.
    pub features: Vec<FeatureSums>,
}

impl Film {
    pub fn new(width: u32, height: u32) -> Self {
        Self::with_features(width, height, false)
    }

    /// A film that also sums the feature layers (albedo and normal) when `features`: every tile
    /// merged into it must then carry them, and no tile may carry them otherwise.
    pub fn with_features(width: u32, height: u32, features: bool) -> Self {
        let n = width as usize * height as usize;
        let features = if features { FeatureSums::zeroed(n) } else { Vec::new() };
        Self { width, height, pixels: PixelSums::zeroed(n), features }
    }

    /// True when the film sums the feature layers.
    pub fn has_features(&self) -> bool {
        !self.features.is_empty()
    }

    /// Adds a tile's sums. Exact: the result does not depend on the order of merges.
    pub fn merge_tile(&mut self, sums: &TileSums) -> Result<(), FilmError> {
        let t = sums.tile;
        if !t.fits(self.width, self.height) {
            return Err(FilmError::TileOutside {
                x0: t.x0,
                y0: t.y0,
                width: t.width,
                height: t.height,
                image_width: self.width,
                image_height: self.height,
            });
        }
        if sums.pixels.len() != t.pixel_count() {
            return Err(FilmError::WrongPixelCount { got: sums.pixels.len(), expected: t.pixel_count() });
        }
        if self.has_features() == sums.features.is_empty() {
            return Err(FilmError::FeatureLayers { expected: self.has_features() });
        }
        if self.has_features() && sums.features.len() != t.pixel_count() {
            return Err(FilmError::WrongPixelCount { got: sums.features.len(), expected: t.pixel_count() });
        }
        for row in 0..t.height {
            let src = &sums.pixels[(row * t.width) as usize..((row + 1) * t.width) as usize];
            let start = ((t.y0 + row) * self.width + t.x0) as usize;
            for (dst, s) in self.pixels[start..start + t.width as usize].iter_mut().zip(src) {
                dst.merge(s);
            }
            if self.has_features() {
                let src = &sums.features[(row * t.width) as usize..((row + 1) * t.width) as usize];
                for (dst, s) in self.features[start..start + t.width as usize].iter_mut().zip(src) {
                    dst.merge(s);
                }
            }
        }
        Ok(())
    }

    /// Samples dropped as NaN, infinite, negative or out of range, over the whole film.
    pub fn dropped(&self) -> u64 {
        self.pixels.iter().map(|p| p.dropped).sum()
    }

    /// The pixels of `tile`, row by row (the tile must fit the film).
    pub fn tile_pixels(&self, tile: tessera_render::Tile) -> impl Iterator<Item = &PixelSums> {
        (tile.y0..tile.y0 + tile.height).flat_map(move |y| {
            let start = (y * self.width + tile.x0) as usize;
            self.pixels[start..start + tile.width as usize].iter()
        })
    }

    /// The sums of `tile`'s pixels (and feature layers), as one tile's result: merged into an
    /// empty film of this size, they give these pixels back (the tile must fit the film).
    pub fn tile_sums(&self, tile: tessera_render::Tile) -> TileSums {
        let features = (tile.y0..tile.y0 + tile.height)
            .filter(|_| self.has_features())
            .flat_map(|y| {
                let start = (y * self.width + tile.x0) as usize;
                self.features[start..start + tile.width as usize].iter().cloned()
            })
            .collect();
        TileSums { tile, pixels: self.tile_pixels(tile).cloned().collect(), features }
    }

    /// Samples per pixel on average (adaptive renders give tiles different counts).
    pub fn mean_spp(&self) -> f64 {
        self.total_samples() as f64 / self.pixels.len().max(1) as f64
    }

    pub fn total_samples(&self) -> u64 {
        self.pixels.iter().map(|p| p.n).sum()
    }

    /// The image the film resolves to: means, variances of the mean and counts.
    pub fn resolve(&self) -> ExrImage {
        let n = self.pixels.len();
        let mut img = ExrImage {
            width: self.width,
            height: self.height,
            rgb: Vec::with_capacity(n),
            variance: Vec::with_capacity(n),
            spp: Vec::with_capacity(n),
            emitter: Vec::with_capacity(n),
            alpha: None,
            features: None,
            denoised: None,
            metadata: String::new(),
        };
        for p in &self.pixels {
            img.rgb.push(p.mean().map(|v| v as f32));
            img.variance.push(p.variance_of_mean().map(|v| v as f32));
            img.spp.push(p.n as f32);
            img.emitter.push(if p.n == 0 { 0.0 } else { (p.emitter_hits as f64 / p.n as f64) as f32 });
        }
        if self.has_features() {
            let (mut albedo, mut normal) = (Vec::with_capacity(n), Vec::with_capacity(n));
            for (f, p) in self.features.iter().zip(&self.pixels) {
                let (a, m) = f.means(p.n + p.dropped);
                albedo.push(a.map(|v| v as f32));
                normal.push(m.map(|v| v as f32));
            }
            img.features = Some(FeatureLayers { albedo, normal });
        }
        img
    }

    /// The image the film resolves to, with its coverage as the alpha channel when
    /// `transparent` (see [`PixelSums::coverage`]).
    pub fn resolve_with_alpha(&self, transparent: bool) -> ExrImage {
        let mut img = self.resolve();
        if transparent {
            img.alpha = Some(self.pixels.iter().map(|p| p.coverage() as f32).collect());
        }
        img
    }
}

/// The sRGB transfer curve (IEC 61966-2-1), for display.
pub fn linear_to_srgb(c: f32) -> f32 {
    tessera_render::spectral::color::srgb_encode(c.clamp(0.0, 1.0) as f64) as f32
}

/// Writes an 8-bit sRGB PNG preview (values clipped to [0, 1]); with an alpha channel when the
/// image has one (PNG's alpha is straight: colours are divided by it before encoding).
pub fn write_png(image: &ExrImage, path: &std::path::Path) -> Result<(), FilmError> {
    let shown = image.denoised.as_ref().unwrap_or(&image.rgb);
    let bytes = encode_png(image.width, image.height, shown, image.alpha.as_deref())
        .map_err(|message| FilmError::Write { path: path.display().to_string(), message })?;
    std::fs::write(path, bytes)
        .map_err(|e| FilmError::Write { path: path.display().to_string(), message: e.to_string() })
}

/// A linear value as an 8-bit sRGB one, as the PNG and the preview's JPEG store it.
fn srgb8(c: f32) -> u8 {
    (linear_to_srgb(c) * 255.0).round() as u8
}

/// The 8-bit sRGB PNG of linear `rgb` (row-major, values clipped to [0, 1]), with straight
/// alpha when `alpha` is given.
pub fn encode_png(width: u32, height: u32, rgb: &[[f32; 3]], alpha: Option<&[f32]>) -> Result<Vec<u8>, String> {
    let mut out = std::io::Cursor::new(Vec::new());
    let written = match alpha {
        None => {
            let mut buf = image::RgbImage::new(width, height);
            for (px, rgb) in buf.pixels_mut().zip(rgb) {
                *px = image::Rgb(rgb.map(srgb8));
            }
            buf.write_to(&mut out, image::ImageFormat::Png)
        }
        Some(alpha) => {
            let mut buf = image::RgbaImage::new(width, height);
            for ((px, rgb), &a) in buf.pixels_mut().zip(rgb).zip(alpha) {
                let straight = rgb.map(|c| if a > 0.0 { srgb8(c / a) } else { 0 });
                *px = image::Rgba([straight[0], straight[1], straight[2], (a.clamp(0.0, 1.0) * 255.0).round() as u8]);
            }
            buf.write_to(&mut out, image::ImageFormat::Png)
        }
    };
    written.map_err(|e| e.to_string())?;
    Ok(out.into_inner())
}

/// A film's preview with its albedo and normal at the same pixels ([`Preview::of_film_layers`]).
pub struct PreviewLayers {
    pub preview: Preview,
    pub albedo: Vec<[f32; 3]>,
    pub normal: Vec<[f32; 3]>,
}

impl PreviewLayers {
    /// The preview denoised with its layers. Seconds on a large preview: call it outside any lock.
    pub fn denoised(&self, denoiser: &dyn Denoiser) -> Result<Preview, String> {
        let p = &self.preview;
        let rgb = denoiser.denoise(p.width, p.height, &p.rgb, &self.albedo, &self.normal)?;
        if rgb.len() != p.rgb.len() || rgb.iter().flatten().any(|c| !c.is_finite()) {
            return Err("the denoiser returned an image of the wrong size or with values that are not finite".into());
        }
        Ok(Preview { rgb, ..p.clone() })
    }
}

/// A small view of an image for display (the dashboard's live preview): at most `max_side`
/// pixels on its longer side, each the film pixel at its centre. Point-sampled, so that
/// taking one from a 4K film under the coordinator's lock reads only the pixels it shows.
#[derive(Clone, Debug, PartialEq)]
pub struct Preview {
    pub width: u32,
    pub height: u32,
    pub rgb: Vec<[f32; 3]>,
}

impl Preview {
    /// `width` x `height` pixels, `pixel(i)` the `i`-th in row order; an empty image gives an
    /// empty preview.
    fn sampled(width: u32, height: u32, max_side: u32, pixel: impl Fn(usize) -> [f32; 3]) -> Self {
        if width == 0 || height == 0 {
            return Self { width: 0, height: 0, rgb: Vec::new() };
        }
        let scale = (width.max(height) as f64 / max_side.max(1) as f64).max(1.0);
        let (w, h) = (((width as f64 / scale).round() as u32).max(1), ((height as f64 / scale).round() as u32).max(1));
        let mut rgb = Vec::with_capacity(w as usize * h as usize);
        for y in 0..h {
            let sy = (((y as f64 + 0.5) * height as f64 / h as f64) as u32).min(height - 1);
            for x in 0..w {
                let sx = (((x as f64 + 0.5) * width as f64 / w as f64) as u32).min(width - 1);
                rgb.push(pixel(sy as usize * width as usize + sx as usize));
            }
        }
        Self { width: w, height: h, rgb }
    }

    /// The preview of a film being rendered: its pixels' means so far.
    pub fn of_film(film: &Film, max_side: u32) -> Self {
        // The mean without `PixelSums::mean`'s i128 conversions, which are done in software:
        // sums that fit an i64 (nearly all) convert in one instruction, to the same value.
        let to_f64 = |v: i128| i64::try_from(v).map_or(v as f64, |v| v as f64);
        Self::sampled(film.width, film.height, max_side, |i| {
            let p = &film.pixels[i];
            if p.n == 0 {
                return [0.0; 3];
            }
            p.sum.map(|v| (to_f64(v) / FIXED_POINT_SCALE / p.n as f64) as f32)
        })
    }

    /// The preview of a film being rendered with its feature layers, for a denoised preview: its
    /// colour, and its albedo and normal at the same pixels; `None` for a film without them.
    pub fn of_film_layers(film: &Film, max_side: u32) -> Option<PreviewLayers> {
        if !film.has_features() || film.width == 0 {
            return None;
        }
        let layer = |normal: bool| {
            Self::sampled(film.width, film.height, max_side, |i| {
                let p = &film.pixels[i];
                let (a, n) = film.features[i].means(p.n + p.dropped);
                (if normal { n } else { a }).map(|v| v as f32)
            })
            .rgb
        };
        Some(PreviewLayers { preview: Self::of_film(film, max_side), albedo: layer(false), normal: layer(true) })
    }

    /// The preview of a finished image.
    pub fn of_image(image: &ExrImage, max_side: u32) -> Self {
        Self::of_image_shown(image, max_side, false)
    }

    /// [`Self::of_image`] of what its PNG shows (the denoised colour, if it has one), or of its
    /// raw colour when `raw`.
    pub fn of_image_shown(image: &ExrImage, max_side: u32, raw: bool) -> Self {
        let shown = if raw { &image.rgb } else { image.denoised.as_ref().unwrap_or(&image.rgb) };
        Self::sampled(image.width, image.height, max_side, |i| shown[i])
    }

    /// As an 8-bit sRGB JPEG at `quality` (1-100; an empty film gives a 1 x 1 black one): a
    /// preview of a noisy render is a tenth of its PNG's size and is sent a few times a second.
    pub fn jpeg(&self, quality: u8) -> Result<Vec<u8>, String> {
        let (width, height) = if self.rgb.is_empty() { (1, 1) } else { (self.width, self.height) };
        let mut bytes: Vec<u8> = self.rgb.iter().flat_map(|c| c.map(srgb8)).collect();
        if bytes.is_empty() {
            bytes = vec![0; 3];
        }
        let mut out = Vec::new();
        image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, quality.clamp(1, 100))
            .encode(&bytes, width, height, image::ExtendedColorType::Rgb8)
            .map_err(|e| e.to_string())?;
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tessera_render::Tile;
    use tessera_render::glam::Vec3;

    /// A preview shows the film pixels at the centres of its pixels, at most `max_side` on a
    /// side with the film's shape, and encodes to a JPEG of that size.
    #[test]
    fn a_preview_samples_the_film_at_pixel_centres() {
        let mut film = Film::new(400, 200);
        let tile = Tile { x0: 0, y0: 0, width: 400, height: 200 };
        let mut sums = TileSums::new(tile);
        for (i, p) in sums.pixels.iter_mut().enumerate() {
            p.add_sample(Vec3::new((i % 400) as f32, (i / 400) as f32, 1.0), false);
        }
        film.merge_tile(&sums).unwrap();
        let preview = Preview::of_film(&film, 100);
        assert_eq!((preview.width, preview.height), (100, 50));
        // Preview pixel (x, y) covers film pixels 4x .. 4x + 4: its centre is 4x + 2.
        assert_eq!(preview.rgb[3 * 100 + 7], [30.0, 14.0, 1.0]);
        // The same values as the pixels' own means.
        assert_eq!(preview.rgb[3 * 100 + 7], film.pixels[14 * 400 + 30].mean().map(|v| v as f32));
        let whole = Preview::of_film(&film, 1000);
        assert_eq!((whole.width, whole.height), (400, 200), "never larger than the film");
        assert_eq!(whole.rgb[5 * 400 + 9], [9.0, 5.0, 1.0]);
        let jpeg = image::load_from_memory(&preview.jpeg(85).unwrap()).unwrap();
        assert_eq!((jpeg.width(), jpeg.height()), (100, 50));
        assert_eq!(Preview::of_film(&Film::new(0, 0), 64).jpeg(85).map(|b| b.len() > 8), Ok(true));
    }

    fn tile_with(tile: Tile, value: f32) -> TileSums {
        let mut s = TileSums::new(tile);
        for (i, p) in s.pixels.iter_mut().enumerate() {
            p.add_sample(Vec3::splat(value + i as f32), false);
        }
        s
    }

    /// A tile's sums taken out of a film merge into an empty one to the same pixels.
    #[test]
    fn a_tiles_sums_come_back_out_of_a_film() {
        let mut film = Film::new(40, 20);
        for (i, t) in Tile::grid(40, 20, 16).iter().enumerate() {
            film.merge_tile(&tile_with(*t, i as f32)).unwrap();
            film.merge_tile(&tile_with(*t, 0.5)).unwrap();
        }
        let mut again = Film::new(40, 20);
        for t in Tile::grid(40, 20, 16) {
            let sums = film.tile_sums(t);
            assert_eq!((sums.pixels.len(), sums.features.len()), (t.pixel_count(), 0));
            again.merge_tile(&sums).unwrap();
        }
        assert!(again == film);
    }

    #[test]
    fn merge_order_does_not_matter() {
        let tiles = Tile::grid(40, 20, 16);
        let mut a = Film::new(40, 20);
        let mut b = Film::new(40, 20);
        for (i, t) in tiles.iter().enumerate() {
            a.merge_tile(&tile_with(*t, i as f32 * 0.1)).unwrap();
        }
        for (i, t) in tiles.iter().enumerate().rev() {
            b.merge_tile(&tile_with(*t, i as f32 * 0.1)).unwrap();
        }
        assert_eq!(a, b);
    }

    /// A film with feature layers merges them exactly, refuses tiles with the wrong layers either
    /// way, and its EXR carries `albedo.R/G/B` and `normal.X/Y/Z` back unchanged.
    #[test]
    fn feature_layers_merge_resolve_and_round_trip_through_the_exr() {
        let tile = Tile { x0: 1, y0: 0, width: 3, height: 2 };
        let mut sums = tile_with(tile, 0.5);
        sums.features = vec![tessera_render::FeatureSums::default(); 6];
        for (i, f) in sums.features.iter_mut().enumerate() {
            f.add(Vec3::new(0.25, 0.5, i as f32 / 8.0), Vec3::new(0.0, -1.0, 0.5));
        }
        let mut film = Film::with_features(4, 2, true);
        film.merge_tile(&sums).unwrap();
        film.merge_tile(&sums).unwrap();
        let err = film.merge_tile(&tile_with(tile, 0.5)).unwrap_err().to_string();
        assert!(err.contains("has none"), "{err}");
        let err = Film::new(4, 2).merge_tile(&sums).unwrap_err().to_string();
        assert!(err.contains("did not ask for"), "{err}");
        let image = film.resolve();
        let layers = image.features.clone().unwrap();
        assert_eq!(layers.albedo[1], [0.25, 0.5, 0.0]);
        assert_eq!(layers.albedo[6], [0.25, 0.5, 0.5]);
        assert_eq!(layers.normal[2], [0.0, -1.0, 0.5]);
        assert_eq!((layers.albedo[0], layers.normal[0]), ([0.0; 3], [0.0; 3]), "a pixel without samples");
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("layers.exr");
        write_exr(&image, &path).unwrap();
        assert_eq!(read_exr(&path).unwrap(), image);
        assert_eq!(read_exr(&path).unwrap().features, Some(layers));
        // Without layers the file has none.
        let plain = dir.path().join("plain.exr");
        write_exr(&Film::new(4, 2).resolve(), &plain).unwrap();
        assert_eq!(read_exr(&plain).unwrap().features, None);
    }

    #[test]
    fn tiles_outside_the_film_are_refused() {
        let mut f = Film::new(10, 10);
        let err = f.merge_tile(&TileSums::new(Tile { x0: 8, y0: 0, width: 4, height: 4 })).unwrap_err();
        assert!(err.to_string().contains("does not fit"), "{err}");
    }

    #[test]
    fn srgb_curve_uses_a_0_055() {
        assert!((linear_to_srgb(1.0) - 1.0).abs() < 1e-6);
        assert!((linear_to_srgb(0.5) - 0.735_357).abs() < 1e-5);
    }
}
