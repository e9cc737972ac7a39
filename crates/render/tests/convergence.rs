//! How fast the default estimator converges (issue 5): its MSE against a converged reference
//! must fall at least as fast as 1/N, the rate of plain Monte Carlo. Fixed seeds.

// Fitting slopes may use the platform's functions: they never reach an image.
#![allow(clippy::disallowed_methods)]

// The helpers the scene crate's tests share: render a scene whole, summarise an image.
#[path = "../../scene/tests/common/mod.rs"]
mod common;

use common::{render, settings};
use tessera_film::Film;
use tessera_render::{ColorMode, Estimator, SamplerKind};
use tessera_scene::{LoadOptions, load};

/// Mean squared error over pixels and channels.
fn mse(image: &Film, reference: &Film) -> f64 {
    let mut se = 0.0;
    for (a, b) in image.pixels.iter().zip(&reference.pixels) {
        let (a, b) = (a.mean(), b.mean());
        se += (0..3).map(|c| (a[c] - b[c]).powi(2)).sum::<f64>();
    }
    se / (3 * image.pixels.len()) as f64
}

/// Least-squares slope of `ln y` against `ln x`.
fn log_log_slope(points: &[(f64, f64)]) -> f64 {
    let n = points.len() as f64;
    let (xs, ys): (Vec<f64>, Vec<f64>) = points.iter().map(|&(x, y)| (x.ln(), y.ln())).unzip();
    let (mx, my) = (xs.iter().sum::<f64>() / n, ys.iter().sum::<f64>() / n);
    let sxy: f64 = xs.iter().zip(&ys).map(|(x, y)| (x - mx) * (y - my)).sum();
    let sxx: f64 = xs.iter().map(|x| (x - mx).powi(2)).sum();
    sxy / sxx
}

#[test]
fn the_default_estimators_mse_falls_at_least_as_fast_as_one_over_n() {
    // The Cornell box at 32 x 32 with the defaults (MIS, Sobol, Russian roulette), RGB. The
    // reference has 32x the largest spp, so its own noise adds at most 3 % to the last MSE.
    let loaded = load("builtin:cornell-box", &LoadOptions::default()).unwrap();
    let mut s = settings(32, 32, Estimator::Mis);
    (s.sampler, s.color, s.seed) = (SamplerKind::Sobol, ColorMode::Rgb, 11);
    let reference = render(&loaded.scene, &tessera_render::RenderSettings { seed: 9_999, ..s.clone() }, 32_768);
    let points: Vec<(f64, f64)> =
        (4..=10).map(|k| 1u32 << k).map(|spp| (spp as f64, mse(&render(&loaded.scene, &s, spp), &reference))).collect();
    for (spp, m) in &points {
        eprintln!("{spp:>5} spp  mse {m:.3e}");
    }
    let slope = log_log_slope(&points);
    eprintln!("log-log slope of MSE against spp over 16..1024: {slope:.3}");
    assert!(slope <= -0.95, "MSE falls with slope {slope:.3}, slower than 1/N");
}
