//! Helpers shared by the scene-level tests: render a scene whole, and summarise an image.

#![allow(dead_code)]

use rayon::prelude::*;
use std::path::PathBuf;
use tessera_film::Film;
use tessera_render::{Estimator, RenderSettings, Scene, Termination, Tile, render_tile};

pub fn settings(width: u32, height: u32, estimator: Estimator) -> RenderSettings {
    RenderSettings { seed: 7, estimator, termination: Termination::ROULETTE, ..RenderSettings::new(width, height) }
}

/// Renders `spp` samples of every pixel with 16 x 16 tiles in parallel.
pub fn render(scene: &Scene, s: &RenderSettings, spp: u32) -> Film {
    let tiles = Tile::grid(s.width, s.height, 16);
    let sums: Vec<_> = tiles.par_iter().map(|&t| render_tile(scene, s, t, 0..spp).unwrap()).collect();
    let mut film = Film::new(s.width, s.height);
    for t in &sums {
        film.merge_tile(t).unwrap();
    }
    film
}

/// Mean over pixels (and channels) of the pixel means, and its standard error, over the
/// pixels `keep` selects. The error assumes independent samples; under Sobol use
/// [`replicated_mean`].
pub fn image_mean(film: &Film, keep: impl Fn(&tessera_render::PixelSums) -> bool) -> (f64, f64, usize) {
    let (mut sum, mut var, mut n) = (0.0, 0.0, 0usize);
    for p in film.pixels.iter().filter(|p| keep(p)) {
        let (m, v) = (p.mean(), p.variance_of_mean());
        sum += (m[0] + m[1] + m[2]) / 3.0;
        var += (v[0] + v[1] + v[2]) / 3.0;
        n += 1;
    }
    let n_f = n.max(1) as f64;
    (sum / n_f, var.sqrt() / n_f, n)
}

/// Independent renders behind [`replicated_mean`]: with 15 degrees of freedom, 3 standard errors
/// bound a two-sided 99.1% confidence interval (Student's t).
pub const REPLICATES: u32 = 16;

/// What [`replicated_mean`] measures.
pub struct Replicated {
    pub mean: f64,
    pub se: f64,
    /// The fewest pixels `keep` selected in any one render.
    pub pixels: usize,
    /// Samples dropped (non-finite or too large) over all the renders.
    pub dropped: u64,
}

/// The image mean (over pixels `keep` selects, and channels) of [`REPLICATES`] independent
/// renders of `spp / REPLICATES` samples each (seeds `s.seed`, `s.seed + 1`, ...), and its
/// standard error from the spread of the renders' means. This is randomised quasi-Monte Carlo's
/// error estimate. Under Owen-scrambled Sobol, a pixel's sample variance does not give the
/// variance of its mean: scrambled nets beat independent sampling on smooth integrands, but they
/// can also lose to it by a bounded factor. Over 64 seeds the spread of such image means was 1.6
/// times what [`image_mean`]'s per-pixel variances claimed. Independent randomisations need no
/// such assumption.
pub fn replicated_mean(
    scene: &Scene,
    s: &RenderSettings,
    spp: u32,
    keep: impl Fn(&tessera_render::PixelSums) -> bool + Sync,
) -> Replicated {
    assert!(spp.is_multiple_of(REPLICATES), "{spp} samples do not split into {REPLICATES} renders");
    let renders: Vec<(f64, usize, u64)> = (0..REPLICATES as u64)
        .into_par_iter()
        .map(|r| {
            let s = RenderSettings { seed: s.seed.wrapping_add(r), ..s.clone() };
            let film = render(scene, &s, spp / REPLICATES);
            let (mean, _, n) = image_mean(&film, &keep);
            (mean, n, film.dropped())
        })
        .collect();
    let r = renders.len() as f64;
    let mean = renders.iter().map(|m| m.0).sum::<f64>() / r;
    let spread = renders.iter().map(|m| (m.0 - mean).powi(2)).sum::<f64>() / (r - 1.0);
    Replicated {
        mean,
        se: (spread / r).sqrt(),
        pixels: renders.iter().map(|m| m.1).min().unwrap_or(0),
        dropped: renders.iter().map(|m| m.2).sum(),
    }
}

/// The project's copies of small sample scenes.
pub fn fixtures_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../scene/tests/fixtures/scenes")
}

/// The shared scene collection beside the checkout, when present.
pub fn shared_scenes_dir() -> Option<PathBuf> {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared/scenes");
    dir.is_dir().then_some(dir)
}

/// Every .gltf and .glb file under `dir`.
pub fn scene_files(dir: &std::path::Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        let Ok(entries) = std::fs::read_dir(&d) else {
            continue;
        };
        for e in entries.flatten() {
            let p = e.path();
            if p.is_dir() {
                stack.push(p);
            } else if matches!(p.extension().and_then(|e| e.to_str()), Some("gltf") | Some("glb")) {
                out.push(p);
            }
        }
    }
    out.sort();
    out
}

/// A GLB of `json` (whose buffer 0 is `bin`).
pub fn glb(mut json: serde_json::Value, bin: &[u8]) -> Vec<u8> {
    json["asset"] = serde_json::json!({"version": "2.0"});
    json["buffers"] = serde_json::json!([{"byteLength": bin.len().next_multiple_of(4)}]);
    tessera_scene::write_glb(&json, bin)
}
