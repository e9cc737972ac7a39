//! How far a film is from its converged image. Adaptive sampling stops a tile on a relative
//! error estimate; with a confidence (`--confidence`), on an upper bound that also counts the
//! estimate's own noise, and the finished image states its estimate with that bound.

use tessera_render::PixelSums;

/// One pixel's squared relative standard error of its mean: the channels' variance of the
/// mean over `max(mean, 1e-3)` squared; `None` for a pixel with fewer than two samples.
fn pixel_term(p: &PixelSums) -> Option<f64> {
    (p.n > 1).then(|| {
        let (m, v) = (p.mean(), p.variance_of_mean());
        let mean = ((m[0] + m[1] + m[2]) / 3.0).max(1e-3);
        (v[0] + v[1] + v[2]) / 3.0 / (mean * mean)
    })
}

/// Relative standard error of the pixel mean over a set of pixels: the root mean square over
/// pixels with two or more samples of `SE / max(mean, 1e-3)` (channels averaged). The adaptive
/// sampler's per-tile measure and the progress bar's error estimate.
pub fn relative_error<'a>(pixels: impl IntoIterator<Item = &'a PixelSums>) -> f64 {
    error_estimate(pixels, 0.5).estimate
}

/// A relative RMSE estimate of a set of pixels and an upper bound on the true relative RMSE
/// at `confidence`.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ErrorEstimate {
    /// [`relative_error`]'s estimate.
    pub estimate: f64,
    /// The true relative RMSE is below this with probability `confidence` (infinite where a
    /// single pixel leaves the estimate's noise unknown).
    pub upper: f64,
    pub confidence: f64,
    /// Pixels with two or more samples, which the estimate averages.
    pub pixels: u64,
}

/// The relative RMSE of `pixels` (the root of the mean of each pixel's squared relative
/// standard error) with an upper bound at `confidence` on the image's true relative RMSE, the
/// error this image has against the converged one. Two things put the truth away from the
/// estimate, and the bound counts both, by the central limit theorem over pixels:
/// - the error an image happens to have: a pixel mean's error is close to normal, so its
///   squared error has its expected value `v` (the pixel's term) and a variance of `2 v^2`;
/// - the estimate's own noise: each term is itself estimated from the pixel's samples; the
///   spread of the terms over the pixels bounds that noise from above (it counts the real
///   differences between pixels as noise too).
///
/// What no sample shows (a light path too rare to have been drawn yet) no estimate counts.
/// A pure function of the pixels in their order, like [`relative_error`]: the same sums give
/// the same bits.
pub fn error_estimate<'a>(pixels: impl IntoIterator<Item = &'a PixelSums>, confidence: f64) -> ErrorEstimate {
    let (mut sum, mut sum_sq, mut n) = (0.0f64, 0.0f64, 0u64);
    // sum: the terms; sum_sq: their squares, for the spread and for the squared errors' variance.
    for term in pixels.into_iter().filter_map(pixel_term) {
        sum += term;
        sum_sq += term * term;
        n += 1;
    }
    if n == 0 {
        return ErrorEstimate { estimate: 0.0, upper: 0.0, confidence, pixels: 0 };
    }
    let mean = sum / n as f64;
    let upper = if n < 2 {
        f64::INFINITY
    } else {
        let n = n as f64;
        let spread = ((sum_sq - sum * mean) / (n - 1.0)).max(0.0);
        // Variance of the mean squared error the image has, plus that of its estimate.
        let variance = (2.0 * sum_sq + n * spread) / (n * n);
        (mean + z_score(confidence) * variance.sqrt()).sqrt()
    };
    ErrorEstimate { estimate: mean.sqrt(), upper, confidence, pixels: n }
}

/// The error a tile's adaptive rounds stop on: the estimate, or with a `confidence` (not 0)
/// its upper bound at that confidence.
pub fn stopping_error<'a>(pixels: impl IntoIterator<Item = &'a PixelSums>, confidence: f32) -> f64 {
    if confidence > 0.0 { error_estimate(pixels, confidence as f64).upper } else { relative_error(pixels) }
}

/// The header line a finished image states its error in (`--confidence`): `e`, the whole
/// film's estimate with its bound, and the adaptive `target` (0: a fixed render). One function
/// for `tessera render` and the farm, so that their images are the same files.
pub fn error_statement(e: &ErrorEstimate, target: f32) -> String {
    let target = if target > 0.0 { format!(" target_error={target}") } else { String::new() };
    format!("relative_error={:.6} error_bound={:.6} confidence={}{target}\n", e.estimate, e.upper, e.confidence as f32)
}

/// The standard normal quantile of `p` in [0.5, 1): the `z` with P(Z <= z) = p. Bisection on
/// the normal distribution function through `libm`'s `erfc` (software, so every machine gets
/// the same bits), to the last bit of an f64.
pub fn z_score(p: f64) -> f64 {
    if p <= 0.5 {
        return 0.0;
    }
    let below = |z: f64| 0.5 * libm::erfc(-z / std::f64::consts::SQRT_2);
    let (mut lo, mut hi) = (0.0f64, 40.0f64);
    for _ in 0..200 {
        let mid = 0.5 * (lo + hi);
        if mid == lo || mid == hi {
            break;
        }
        if below(mid) < p { lo = mid } else { hi = mid }
    }
    hi
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    #[test]
    fn z_scores_are_the_normal_quantiles() {
        for (p, z) in [(0.5, 0.0), (0.8413447460685429, 1.0), (0.95, 1.6448536269514722), (0.99, 2.3263478740408408)] {
            assert!((z_score(p) - z).abs() < 1e-12, "{p}: {} against {z}", z_score(p));
        }
    }

    /// Pixels of known sample sets: the estimate is the root mean square of the relative
    /// standard errors; the bound adds the squared errors' variance (2 v^2 a pixel) and the
    /// terms' spread, grows with the confidence, and equals the estimate at 0.5.
    #[test]
    fn the_bound_is_the_estimate_plus_the_spread_of_the_pixel_terms() {
        let pixel = |values: &[f32]| {
            let mut p = PixelSums::default();
            for &v in values {
                p.add_sample(Vec3::splat(v), false);
            }
            p
        };
        // Mean 1, sample variance 1/3 over 4 samples: a variance of the mean of 1/12.
        let a = pixel(&[0.5, 1.5, 0.5, 1.5]);
        // Mean 2, sample variance 4/3: 1/3, over a mean of 2 squared: 1/12 again.
        let b = pixel(&[1.0, 3.0, 1.0, 3.0]);
        let same = error_estimate([&a, &b], 0.95);
        assert!((same.estimate - (1.0f64 / 12.0).sqrt()).abs() < 1e-9, "{same:?}");
        let t = 1.0f64 / 12.0;
        let upper = (t + 1.6448536269514722 * (2.0 * 2.0 * t * t).sqrt() / 2.0).sqrt();
        assert!((same.upper - upper).abs() < 1e-9, "terms that agree: only the squared errors' own spread: {same:?}");
        let c = pixel(&[0.0, 2.0, 0.0, 2.0]);
        let both = error_estimate([&a, &c], 0.95);
        let (ta, tc) = (1.0f64 / 12.0, 4.0 / 3.0 / 4.0);
        let (mean, spread) = ((ta + tc) / 2.0, (tc - ta).powi(2) / 2.0);
        let variance = (2.0 * (ta * ta + tc * tc) + 2.0 * spread) / 4.0;
        let upper = (mean + 1.6448536269514722 * variance.sqrt()).sqrt();
        assert!((both.estimate - mean.sqrt()).abs() < 1e-9 && (both.upper - upper).abs() < 1e-9, "{both:?}");
        assert!(error_estimate([&a, &c], 0.99).upper > both.upper);
        assert_eq!(error_estimate([&a, &c], 0.5).upper, both.estimate);
        assert_eq!(stopping_error([&a, &c], 0.0), relative_error([&a, &c]));
        assert_eq!(stopping_error([&a, &c], 0.95), error_estimate([&a, &c], 0.95f32 as f64).upper);
        assert_eq!(error_estimate([&a], 0.95).upper, f64::INFINITY, "one pixel: its noise is unknown");
        assert_eq!(error_estimate([&PixelSums::default()], 0.95).pixels, 0);
    }
}
