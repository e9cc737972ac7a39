//! Exactly associative per-pixel accumulators (ARCHITECTURE.md invariant 2).
//!
//! Each sample's radiance `x` is quantised once, to `round(x * 2^32)` and `round(x^2 * 2^32)`,
//! and summed in 128-bit integers (signed for `x`: a spectral sample's linear sRGB can be
//! negative, though its expectation inside the gamut is not). Integer addition is associative and commutative, so any split
//! of a pixel's samples into tiles, ranges and jobs, merged in any order, gives the same bits.
//! The quantum (2.3e-10) lies far below Monte Carlo noise; the range allows samples up to
//! [`MAX_SAMPLE`] and 2^31 of them per pixel.

use glam::Vec3;

pub const FIXED_POINT_SCALE: f64 = 4_294_967_296.0; // 2^32
/// Largest magnitude a sample may carry; larger or non-finite samples are dropped and counted.
pub const MAX_SAMPLE: f32 = 1_073_741_824.0; // 2^30
const _: () = assert!(MAX_SAMPLE as f64 * FIXED_POINT_SCALE <= 4_611_686_018_427_387_904.0); // 2^62
/// 2^63 and 2^64: squared quanta below them fit in an `i64` and a `u64`.
const I64_LIMIT: f64 = 9_223_372_036_854_775_808.0;
const U64_LIMIT: f64 = 18_446_744_073_709_551_616.0;

/// A pixel's exact sums. All zeros is the empty pixel ([`Default`]), which lets a whole image's
/// worth be allocated as zeroed pages ([`PixelSums::zeroed`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, bytemuck::Zeroable)]
pub struct PixelSums {
    /// Samples merged.
    pub n: u64,
    /// Samples dropped because they were NaN, infinite or above [`MAX_SAMPLE`] in magnitude.
    pub dropped: u64,
    /// Samples whose camera ray saw an emitter directly.
    pub emitter_hits: u64,
    /// Samples whose camera ray hit the scene: over `n`, the pixel's coverage (its alpha in a
    /// `--transparent` render).
    pub hits: u64,
    pub sum: [i128; 3],
    pub sum_sq: [u128; 3],
}

impl PixelSums {
    /// `n` empty pixels, from zeroed memory: the system hands out zero pages without touching
    /// them, so a large film costs nothing until its tiles are merged (where `vec![default; n]`
    /// would write every byte at once: 2 GiB for a 4096 x 4096 film).
    pub fn zeroed(n: usize) -> Vec<PixelSums> {
        bytemuck::zeroed_vec(n)
    }

    /// Adds a sample whose camera ray hit the scene.
    pub fn add_sample(&mut self, rgb: Vec3, saw_emitter: bool) {
        self.add(rgb, saw_emitter, true);
    }

    /// Adds a sample of radiance `rgb`; `hit`: its camera ray hit the scene. A sample that is
    /// not finite or out of range is only counted as dropped.
    pub fn add(&mut self, rgb: Vec3, saw_emitter: bool, hit: bool) {
        let c = rgb.to_array();
        if c.iter().any(|v| !(-MAX_SAMPLE..=MAX_SAMPLE).contains(v)) {
            self.dropped += 1;
            return;
        }
        self.n += 1;
        self.emitter_hits += saw_emitter as u64;
        self.hits += hit as u64;
        for (k, &v) in c.iter().enumerate() {
            let v = v as f64;
            // Both quanta are whole numbers, so converting through 64 bits where they fit gives the
            // same integers as the 128-bit conversion (a slow library call) does; and where they
            // are known to fit, without the checks that a cast saturates.
            let q = (v * FIXED_POINT_SCALE).round();
            // SAFETY: `q` is finite and |q| <= 2^62 (|v| <= MAX_SAMPLE = 2^30, checked above).
            self.sum[k] += unsafe { q.to_int_unchecked::<i64>() } as i128;
            let q_sq = (v * v * FIXED_POINT_SCALE).round();
            self.sum_sq[k] += if q_sq < I64_LIMIT {
                // The common case (|v| < 2^15.5): one signed conversion, where an unsigned one
                // takes a sequence of five.
                // SAFETY: `q_sq` is finite, not negative (a square) and below 2^63.
                (unsafe { q_sq.to_int_unchecked::<i64>() }) as u64 as u128
            } else if q_sq < U64_LIMIT {
                // SAFETY: `q_sq` is finite, not negative (a square) and below 2^64.
                (unsafe { q_sq.to_int_unchecked::<u64>() }) as u128
            } else {
                q_sq as u128
            };
        }
    }

    pub fn merge(&mut self, o: &PixelSums) {
        self.n += o.n;
        self.dropped += o.dropped;
        self.emitter_hits += o.emitter_hits;
        self.hits += o.hits;
        for k in 0..3 {
            self.sum[k] += o.sum[k];
            self.sum_sq[k] += o.sum_sq[k];
        }
    }

    /// The fraction of samples whose camera ray hit the scene (0 without samples).
    pub fn coverage(&self) -> f64 {
        if self.n == 0 { 0.0 } else { self.hits as f64 / self.n as f64 }
    }

    /// Mean radiance per channel (0 without samples).
    pub fn mean(&self) -> [f64; 3] {
        if self.n == 0 {
            return [0.0; 3];
        }
        std::array::from_fn(|k| self.sum[k] as f64 / FIXED_POINT_SCALE / self.n as f64)
    }

    /// Variance of one sample, `s^2`, per channel (0 with fewer than two samples).
    pub fn sample_variance(&self) -> [f64; 3] {
        self.variance_of_mean().map(|v| v * self.n as f64)
    }

    /// Variance of the pixel mean, `s^2 / n`, per channel (0 with fewer than two samples).
    pub fn variance_of_mean(&self) -> [f64; 3] {
        if self.n < 2 {
            return [0.0; 3];
        }
        let n = self.n as f64;
        std::array::from_fn(|k| {
            let s = self.sum[k] as f64 / FIXED_POINT_SCALE;
            let s2 = self.sum_sq[k] as f64 / FIXED_POINT_SCALE;
            ((s2 - s * s / n) / (n - 1.0)).max(0.0) / n
        })
    }
}

/// Quantum of the feature layers' sums ([`FeatureSums`]): 2^24, a step of 6e-8 on values in
/// [-1, 1]. `2^24 * 2^32` samples stays below 2^63, so a pixel's feature sums fit an `i64`.
pub const FEATURE_SCALE: f64 = 16_777_216.0;

/// A pixel's exact sums of the feature layers a denoiser reads: the albedo and the shading
/// normal at each sample's first diffuse or glossy hit (`crate::features`). Quantised once per
/// sample to `round(x * 2^24)` and summed in integers, so they merge exactly like the colour.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, bytemuck::Zeroable)]
pub struct FeatureSums {
    pub albedo: [i64; 3],
    pub normal: [i64; 3],
}

impl FeatureSums {
    /// `n` empty pixels from zeroed memory, as [`PixelSums::zeroed`].
    pub fn zeroed(n: usize) -> Vec<FeatureSums> {
        bytemuck::zeroed_vec(n)
    }

    /// Adds one sample's features; each component is clamped to its range first (albedo [0, 1],
    /// normal [-1, 1]) and a non-finite one counts as 0, so that no sample can overflow the sums.
    pub fn add(&mut self, albedo: Vec3, normal: Vec3) {
        let q =
            |v: f32, lo: f32| if v.is_finite() { (v.clamp(lo, 1.0) as f64 * FEATURE_SCALE).round() as i64 } else { 0 };
        for k in 0..3 {
            self.albedo[k] += q(albedo[k], 0.0);
            self.normal[k] += q(normal[k], -1.0);
        }
    }

    pub fn merge(&mut self, o: &FeatureSums) {
        for k in 0..3 {
            self.albedo[k] += o.albedo[k];
            self.normal[k] += o.normal[k];
        }
    }

    /// Mean albedo and mean normal over the pixel's `n` samples, its colour's merged and dropped
    /// ones alike (a sample whose colour was dropped still has its features); zeros without
    /// samples. The mean normal is not renormalised: where a pixel's samples see different
    /// surfaces it is shorter, as a denoiser expects of an averaged normal.
    pub fn means(&self, n: u64) -> ([f64; 3], [f64; 3]) {
        if n == 0 {
            return ([0.0; 3], [0.0; 3]);
        }
        let mean = |v: [i64; 3]| v.map(|s| s as f64 / FEATURE_SCALE / n as f64);
        (mean(self.albedo), mean(self.normal))
    }
}

/// A rectangle of pixels, `x0..x0+width` by `y0..y0+height`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct Tile {
    pub x0: u32,
    pub y0: u32,
    pub width: u32,
    pub height: u32,
}

impl Tile {
    pub fn pixel_count(&self) -> usize {
        self.width as usize * self.height as usize
    }

    /// True when the tile lies inside a `width` x `height` image.
    pub fn fits(&self, width: u32, height: u32) -> bool {
        self.x0.checked_add(self.width).is_some_and(|x| x <= width)
            && self.y0.checked_add(self.height).is_some_and(|y| y <= height)
    }

    /// Tiles of at most `size` x `size` covering a `width` x `height` image, row-major.
    pub fn grid(width: u32, height: u32, size: u32) -> Vec<Tile> {
        let size = size.max(1);
        let mut tiles = Vec::new();
        for y0 in (0..height).step_by(size as usize) {
            for x0 in (0..width).step_by(size as usize) {
                tiles.push(Tile { x0, y0, width: size.min(width - x0), height: size.min(height - y0) });
            }
        }
        tiles
    }
}

/// Per-pixel sums of one tile, row-major within the tile.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TileSums {
    pub tile: Tile,
    pub pixels: Vec<PixelSums>,
    /// The feature layers' sums, one per pixel over the same samples as `pixels`, when the render
    /// asked for them ([`crate::RenderSettings::features`]); empty otherwise.
    pub features: Vec<FeatureSums>,
}

impl TileSums {
    pub fn new(tile: Tile) -> Self {
        Self { tile, pixels: vec![PixelSums::default(); tile.pixel_count()], features: Vec::new() }
    }

    /// Adds another result for the same tile, pixel by pixel (the feature layers too where both
    /// carry them).
    pub fn merge(&mut self, other: &TileSums) {
        assert_eq!(self.tile, other.tile, "merging sums of different tiles");
        for (a, b) in self.pixels.iter_mut().zip(&other.pixels) {
            a.merge(b);
        }
        if self.features.is_empty() {
            self.features = other.features.clone();
        } else {
            for (a, b) in self.features.iter_mut().zip(&other.features) {
                a.merge(b);
            }
        }
    }

    pub fn dropped(&self) -> u64 {
        self.pixels.iter().map(|p| p.dropped).sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sums_of(values: &[f32]) -> PixelSums {
        let mut p = PixelSums::default();
        for &v in values {
            p.add_sample(Vec3::splat(v), false);
        }
        p
    }

    #[test]
    fn merge_is_exact_for_any_grouping() {
        let values: Vec<f32> = (0..1000).map(|i| ((i * 7919) % 1013) as f32 * 0.37 + 1e-3).collect();
        let whole = sums_of(&values);
        let mut a = sums_of(&values[..313]);
        let b = sums_of(&values[313..700]);
        let c = sums_of(&values[700..]);
        let mut cb = c;
        cb.merge(&b);
        a.merge(&cb);
        assert_eq!(a, whole);
    }

    /// The quanta go through 64-bit integers where they fit; they must be the integers a direct
    /// 128-bit conversion gives, on both sides of each limit (`2^15.5` and `2^16` for squares,
    /// `MAX_SAMPLE`).
    #[test]
    fn quanta_equal_the_128_bit_conversion() {
        let (signed, edge) = (46_340.95f32, 65536f32); // 2^15.5 and 2^16
        let values = [
            0.0,
            -0.0,
            1e-12,
            0.4999,
            -3.75,
            signed.next_down(),
            signed,
            signed.next_up(),
            -signed.next_up(),
            edge.next_down(),
            edge,
            edge.next_up(),
            -edge.next_up(),
            1.0e7,
            MAX_SAMPLE.next_down(),
            MAX_SAMPLE,
            -MAX_SAMPLE,
        ];
        for v in values {
            let mut p = PixelSums::default();
            p.add_sample(Vec3::new(v, -v, 0.5 * v), false);
            for (k, c) in [v, -v, 0.5 * v].into_iter().enumerate() {
                let c = c as f64;
                assert_eq!(p.sum[k], (c * FIXED_POINT_SCALE).round() as i128, "sum of {c}");
                assert_eq!(p.sum_sq[k], (c * c * FIXED_POINT_SCALE).round() as u128, "square of {c}");
            }
        }
    }

    #[test]
    fn mean_and_variance_match_the_textbook() {
        let p = sums_of(&[1.0, 2.0, 3.0, 4.0]);
        assert!((p.mean()[0] - 2.5).abs() < 1e-9);
        // s^2 = 5/3, variance of the mean = s^2 / 4.
        assert!((p.variance_of_mean()[1] - 5.0 / 12.0).abs() < 1e-9);
    }

    #[test]
    fn bad_samples_are_dropped_and_counted() {
        let mut p = PixelSums::default();
        p.add_sample(Vec3::new(f32::NAN, 0.0, 0.0), false);
        p.add_sample(Vec3::new(0.0, f32::INFINITY, 0.0), false);
        p.add_sample(Vec3::new(0.0, 0.0, -2.0 * MAX_SAMPLE), false);
        p.add_sample(Vec3::ONE, true);
        assert_eq!((p.n, p.dropped, p.emitter_hits), (1, 3, 1));
        assert_eq!(p.mean(), [1.0; 3]);
        // Negative samples (spectral out-of-gamut estimates) count, and cancel exactly.
        p.add_sample(Vec3::new(-1.0, 0.5, 1.0), false);
        p.add_sample(Vec3::new(1.0, 0.5, 1.0), false);
        assert_eq!(p.n, 3);
        assert_eq!(p.mean(), [1.0 / 3.0, 2.0 / 3.0, 1.0]);
    }

    #[test]
    fn grid_covers_the_image_once() {
        let tiles = Tile::grid(70, 33, 32);
        assert_eq!(tiles.len(), 3 * 2);
        let covered: usize = tiles.iter().map(Tile::pixel_count).sum();
        assert_eq!(covered, 70 * 33);
    }
}
