//! Kucherov et al.'s test image: the Macbeth ColorChecker, 6 x 4 patches of 64 x 64 pixels without
//! borders (384 x 256), each pixel's X, Y, Z estimated by Monte Carlo over N wavelengths, then
//! mapped to linear RGB. Every random number is a pure function of (seed, pixel, index).

use super::color::{Illuminant, Primaries, srgb_encode, xyz_exact};
use super::wavelengths::WavelengthSampler;
use super::{Spectrum, data};
use crate::sampler::mix64;

pub const PATCH: u32 = 64;
pub const COLUMNS: u32 = 6;
pub const ROWS: u32 = 4;
pub const WIDTH: u32 = PATCH * COLUMNS;
pub const HEIGHT: u32 = PATCH * ROWS;

#[derive(Clone, Copy, Debug)]
pub struct ChartSettings {
    /// Wavelengths per pixel (N).
    pub samples: usize,
    pub sampler: WavelengthSampler,
    pub illuminant: Illuminant,
    pub primaries: Primaries,
    pub seed: u64,
}

/// The patch under pixel (x, y), in chart order.
pub fn patch_of(x: u32, y: u32) -> usize {
    ((y / PATCH) * COLUMNS + x / PATCH) as usize
}

/// Per-pixel state reused across pixels (the wavelength buffer).
#[derive(Default)]
pub struct Scratch {
    wavelengths: Vec<(f64, f64)>,
}

/// Linear RGB of pixel (x, y): `k/N Σ S(λ) R(λ) cmf(λ) / p(λ)`, with `k` the exact white
/// normalisation, then the RGB matrix.
pub fn pixel(settings: &ChartSettings, x: u32, y: u32, scratch: &mut Scratch) -> [f64; 3] {
    let reflectance = &data::colorchecker()[patch_of(x, y)].1;
    pixel_of(settings, reflectance, (y * WIDTH + x) as u64, scratch)
}

/// Row `y` of the chart, left to right (rows are independent: render them on any threads).
pub fn row(settings: &ChartSettings, y: u32) -> Vec<[f64; 3]> {
    let mut scratch = Scratch::default();
    (0..WIDTH).map(|x| pixel(settings, x, y, &mut scratch)).collect()
}

/// One pixel's estimate for `reflectance`, with random stream `stream`.
pub fn pixel_of(settings: &ChartSettings, reflectance: &Spectrum, stream: u64, scratch: &mut Scratch) -> [f64; 3] {
    let key = mix64(settings.seed ^ mix64(stream.wrapping_add(0x5bd1_e995)));
    let mut counter = 0u64;
    let u = || {
        counter += 1;
        (mix64(key.wrapping_add(counter)) >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    };
    settings.sampler.sample(settings.samples.max(1), u, &mut scratch.wavelengths);
    let (s, cmf) = (settings.illuminant.spd(), data::cmf());
    let mut xyz = [0.0; 3];
    for &(l, pdf) in &scratch.wavelengths {
        let w = s.eval(l) * reflectance.eval(l) / pdf;
        for (c, acc) in xyz.iter_mut().enumerate() {
            *acc += w * cmf[c].eval(l);
        }
    }
    let k = settings.illuminant.normalisation() / scratch.wavelengths.len() as f64;
    settings.primaries.from_xyz(xyz.map(|v| v * k))
}

/// The exact (1 nm) linear RGB of every patch, in chart order.
pub fn exact_patches(illuminant: Illuminant, primaries: Primaries) -> Vec<[f64; 3]> {
    data::colorchecker().iter().map(|(_, r)| primaries.from_xyz(xyz_exact(r, illuminant))).collect()
}

/// On the 8-bit display scale: `255 * srgb(clamp(linear))`, unrounded.
pub fn to_8bit(linear: f64) -> f64 {
    255.0 * srgb_encode(linear.clamp(0.0, 1.0))
}

/// What the study measures of one patch.
#[derive(Clone, Copy, Debug)]
pub struct PatchStats {
    /// Mean linear RGB over the patch's pixels.
    pub mean: [f64; 3],
    /// Standard deviation of linear RGB over the patch's pixels (the noise).
    pub std: [f64; 3],
    /// |8-bit value of the mean - 8-bit exact value|, largest channel.
    pub mean_error_8bit: f64,
    /// Largest |8-bit pixel value - 8-bit exact value| over the patch's pixels and channels.
    pub max_pixel_error_8bit: f64,
}

/// Statistics of every patch of a chart given as linear RGB, row-major `WIDTH x HEIGHT`.
pub fn patch_stats(rgb: &[[f64; 3]], exact: &[[f64; 3]]) -> Vec<PatchStats> {
    let patches = (COLUMNS * ROWS) as usize;
    let (mut sum, mut sum2, mut max_err) = (vec![[0.0; 3]; patches], vec![[0.0; 3]; patches], vec![0.0f64; patches]);
    for y in 0..HEIGHT {
        for x in 0..WIDTH {
            let (p, v) = (patch_of(x, y), rgb[(y * WIDTH + x) as usize]);
            for c in 0..3 {
                sum[p][c] += v[c];
                sum2[p][c] += v[c] * v[c];
                max_err[p] = max_err[p].max((to_8bit(v[c]) - to_8bit(exact[p][c])).abs());
            }
        }
    }
    let n = (PATCH * PATCH) as f64;
    (0..patches)
        .map(|p| {
            let mean = sum[p].map(|s| s / n);
            let std = [0, 1, 2].map(|c| ((sum2[p][c] / n - mean[c] * mean[c]).max(0.0) * n / (n - 1.0)).sqrt());
            let mean_error_8bit = (0..3).map(|c| (to_8bit(mean[c]) - to_8bit(exact[p][c])).abs()).fold(0.0, f64::max);
            PatchStats { mean, std, mean_error_8bit, max_pixel_error_8bit: max_err[p] }
        })
        .collect()
}

/// The chart's noise: the per-patch standard deviation, averaged over patches and channels.
pub fn noise(stats: &[PatchStats]) -> f64 {
    stats.iter().map(|s| s.std.iter().sum::<f64>() / 3.0).sum::<f64>() / stats.len() as f64
}

/// Least-squares slope of log(y) against log(x).
pub fn log_log_slope(points: &[(f64, f64)]) -> f64 {
    let n = points.len() as f64;
    let (lx, ly): (Vec<f64>, Vec<f64>) = points.iter().map(|&(x, y)| (libm::log(x), libm::log(y))).unzip();
    let (mx, my) = (lx.iter().sum::<f64>() / n, ly.iter().sum::<f64>() / n);
    let cov: f64 = lx.iter().zip(&ly).map(|(x, y)| (x - mx) * (y - my)).sum();
    let var: f64 = lx.iter().map(|x| (x - mx) * (x - mx)).sum();
    cov / var
}
