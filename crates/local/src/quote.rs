//! A quote before rendering (`tessera submit --quote`): a short pilot renders the first adaptive
//! round of a spread of the image's tiles on this machine, and the rest of each tile's rounds is
//! predicted from the error it showed, by the coordinator's own round rule
//! ([`tessera_render::plan::next_round`]): a pixel mean's variance falls as 1/n, so a tile's
//! relative error at n samples is its pilot error times sqrt(n0 / n). The predicted samples,
//! scaled from the pilot's tiles to the whole image, and the pilot's speed give the cost.

use crate::options::Sampling;
use anyhow::Result;
use rayon::prelude::*;
use std::time::Instant;
use tessera_film::stopping_error;
pub use tessera_render::plan::{ERROR_SPREAD, PILOT_TILES};
use tessera_render::plan::{PASS_SPP, RenderPlan, TILE_SIZE, first_round, pilot_tiles, predicted_passes};
use tessera_render::{RenderSettings, Scene, render_tile};

/// What a render will take, predicted from a pilot.
#[derive(Clone, Debug, PartialEq)]
pub struct Quote {
    /// Samples the whole render is predicted to take, and a range (the pilot's error
    /// [`ERROR_SPREAD`] times lower and higher).
    pub samples: u64,
    pub samples_low: u64,
    pub samples_high: u64,
    /// Core-seconds they are predicted to take on this machine, with the same range: each
    /// pilot tile's samples at the cost a sample of that tile took in the pilot (the extra rounds
    /// go to the noisy tiles, which tend to cost more a sample than the rest).
    pub core_seconds: f64,
    pub core_seconds_low: f64,
    pub core_seconds_high: f64,
    /// Pixels in the image.
    pub pixels: u64,
    /// The pilot: tiles rendered (of all), samples, seconds, threads, and the core-seconds its
    /// tiles took together.
    pub pilot_tiles: usize,
    pub tiles: usize,
    pub pilot_samples: u64,
    pub pilot_seconds: f64,
    pub threads: usize,
    pub pilot_core_seconds: f64,
}

impl Quote {
    /// How much more the render's samples are predicted to cost, one with another, than the
    /// pilot's did: what a farm's measured speed (samples a second over the jobs it ran) is to
    /// be divided by for this render.
    pub fn cost_weight(&self) -> f64 {
        let pilot = self.pilot_core_seconds / self.pilot_samples.max(1) as f64;
        let render = self.core_seconds / self.samples.max(1) as f64;
        if pilot > 0.0 && render > 0.0 { render / pilot } else { 1.0 }
    }

    /// Samples per pixel on average.
    pub fn mean_spp(&self) -> f64 {
        self.samples as f64 / self.pixels.max(1) as f64
    }
}

/// Quotes a render of `scene` with `settings` and `sampling`, from a pilot of at most
/// `most_tiles` tiles rendered on `threads` threads (0: every core). A fixed render's samples
/// are known; the pilot then only measures the speed.
pub fn quote(
    scene: &Scene,
    settings: &RenderSettings,
    sampling: Sampling,
    threads: usize,
    most_tiles: usize,
) -> Result<Quote> {
    let plan = RenderPlan::new(settings.width, settings.height, TILE_SIZE, sampling.spp, PASS_SPP);
    let max = plan.passes_per_tile();
    // An adaptive render's pilot is its first round; a fixed render's samples are known, and one
    // pass measures the speed.
    let first = sampling.adaptive.map_or(1, |a| first_round(a.min_spp, plan.pass_spp, max));
    let chosen = pilot_tiles(plan.tiles.len(), most_tiles);
    let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build()?;
    let started = Instant::now();
    // Each tile's error and the seconds its thread took on it.
    let measured: Vec<(f64, f64)> = pool.install(|| {
        chosen
            .par_iter()
            .with_max_len(1)
            .map(|&i| {
                let at = Instant::now();
                let sums = render_tile(scene, settings, plan.tiles[i], plan.samples(0, first))?;
                Ok((stopping_error(&sums.pixels, settings.confidence), at.elapsed().as_secs_f64()))
            })
            .collect::<Result<_>>()
    })?;
    let pilot_seconds = started.elapsed().as_secs_f64();
    let pixels = |i: usize| plan.tiles[i].pixel_count() as u64;
    let pilot_pixels: u64 = chosen.iter().map(|&i| pixels(i)).sum();
    let n0 = plan.samples(0, first).len() as u64;
    // Passes a tile ends with when its error at `first` passes is `scale` times what it showed.
    let passes = |error: f64, scale: f64| match sampling.adaptive {
        Some(a) => predicted_passes(&plan, first, error * scale, a.target_error as f64),
        None => max,
    };
    let total_pixels = settings.width as u64 * settings.height as u64;
    let to_image = total_pixels as f64 / pilot_pixels.max(1) as f64;
    // Samples and core-seconds, scaled from the pilot's tiles to the image.
    let predict = |scale: f64| -> (u64, f64) {
        let (mut samples, mut seconds) = (0u64, 0.0);
        for (&i, &(error, took)) in chosen.iter().zip(&measured) {
            let n = pixels(i) * plan.samples(0, passes(error, scale)).len() as u64;
            samples += n;
            seconds += n as f64 * took / (pixels(i) * n0).max(1) as f64;
        }
        ((samples as f64 * to_image).round() as u64, seconds * to_image)
    };
    let [(samples, core_seconds), (samples_low, core_seconds_low), (samples_high, core_seconds_high)] =
        [1.0, 1.0 / ERROR_SPREAD, ERROR_SPREAD].map(predict);
    Ok(Quote {
        samples,
        samples_low,
        samples_high,
        core_seconds,
        core_seconds_low,
        core_seconds_high,
        pixels: total_pixels,
        pilot_tiles: chosen.len(),
        tiles: plan.tiles.len(),
        pilot_samples: pilot_pixels * n0,
        pilot_seconds,
        threads: pool.current_num_threads(),
        pilot_core_seconds: measured.iter().map(|m| m.1).sum(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render_film;
    use tessera_render::Termination;
    use tessera_request::Adaptive;

    /// On three scenes the quoted samples are within 30 % of what the adaptive render then
    /// takes, the actual inside the quoted range; a fixed render's are exact.
    #[test]
    fn quoted_samples_are_within_30_percent_of_the_render() {
        let boxed = concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../scene/tests/fixtures/scenes/BoxTextured/glTF-Binary/BoxTextured.glb"
        );
        let scenes = [
            ("builtin:cornell-box", 0.1),
            ("builtin:furnace?base=0.8&metallic=0.5&roughness=0.4", 0.03),
            (boxed, 0.03),
        ];
        for (spec, target_error) in scenes {
            let options = tessera_scene::LoadOptions {
                environment: Some(tessera_render::glam::Vec3::splat(0.5)),
                ..Default::default()
            };
            let scene = tessera_scene::load(spec, &options).unwrap().scene;
            let settings = RenderSettings { termination: Termination::MaxBounces(4), ..RenderSettings::new(128, 96) };
            let sampling = Sampling { spp: 1024, adaptive: Some(Adaptive { target_error, min_spp: 16 }) };
            let q = quote(&scene, &settings, sampling, 0, usize::MAX).unwrap();
            let film = render_film(&scene, &settings, sampling, 0, &indicatif::ProgressBar::hidden()).unwrap();
            let actual = film.total_samples() + film.dropped();
            let ratio = q.samples as f64 / actual as f64;
            eprintln!(
                "{spec}: quoted {} ({}-{}), rendered {actual}: {ratio:.3}",
                q.samples, q.samples_low, q.samples_high
            );
            assert!((0.7..=1.3).contains(&ratio), "{spec}: quoted {} samples, rendered {actual}", q.samples);
            assert!(q.samples_low <= actual && actual <= q.samples_high, "{spec}: {actual} outside {q:?}");
            assert!(
                0.0 < q.core_seconds_low
                    && q.core_seconds_low <= q.core_seconds
                    && q.core_seconds <= q.core_seconds_high
            );
            let fixed = quote(&scene, &settings, Sampling::fixed(64), 0, 4).unwrap();
            assert_eq!((fixed.samples, fixed.pilot_tiles), (128 * 96 * 64, 4));
            assert_eq!(fixed.pilot_samples, 4 * 32 * 32 * 16, "a fixed render's pilot is one pass of its tiles");
        }
    }
}
