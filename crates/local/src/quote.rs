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
use tessera_film::relative_error;
use tessera_render::plan::{PASS_SPP, RenderPlan, TILE_SIZE, first_round, predicted_passes};
use tessera_render::{RenderSettings, Scene, render_tile};

/// How far the pilot's error may be off, each way, for the quote's range: a tile's error
/// estimated from its first round (16 samples a pixel by default) moves by about this much
/// between seeds on the scenes tested, more where rare bright paths dominate.
pub const ERROR_SPREAD: f64 = 1.25;

/// What a render will take, predicted from a pilot.
#[derive(Clone, Debug, PartialEq)]
pub struct Quote {
    /// Samples the whole render is predicted to take, and a range (the pilot's error
    /// [`ERROR_SPREAD`] times lower and higher).
    pub samples: u64,
    pub samples_low: u64,
    pub samples_high: u64,
    /// Pixels in the image.
    pub pixels: u64,
    /// The pilot: tiles rendered (of all), samples, seconds, threads.
    pub pilot_tiles: usize,
    pub tiles: usize,
    pub pilot_samples: u64,
    pub pilot_seconds: f64,
    pub threads: usize,
}

impl Quote {
    /// Core-seconds one sample took in the pilot, on this machine.
    pub fn core_seconds_per_sample(&self) -> f64 {
        self.pilot_seconds * self.threads as f64 / self.pilot_samples.max(1) as f64
    }

    /// Samples per pixel on average.
    pub fn mean_spp(&self) -> f64 {
        self.samples as f64 / self.pixels.max(1) as f64
    }
}

/// The tiles a pilot of at most `most` tiles renders: spread evenly over the image.
fn pilot_tiles(count: usize, most: usize) -> Vec<usize> {
    let k = count.min(most.max(1));
    (0..k).map(|i| i * count / k).collect()
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
    let errors: Vec<f64> = pool.install(|| {
        chosen
            .par_iter()
            .with_max_len(1)
            .map(|&i| Ok(relative_error(&render_tile(scene, settings, plan.tiles[i], plan.samples(0, first))?.pixels)))
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
    let predict = |scale: f64| -> u64 {
        let pilot: u64 =
            chosen.iter().zip(&errors).map(|(&i, &e)| pixels(i) * plan.samples(0, passes(e, scale)).len() as u64).sum();
        (pilot as f64 * total_pixels as f64 / pilot_pixels.max(1) as f64).round() as u64
    };
    Ok(Quote {
        samples: predict(1.0),
        samples_low: predict(1.0 / ERROR_SPREAD),
        samples_high: predict(ERROR_SPREAD),
        pixels: total_pixels,
        pilot_tiles: chosen.len(),
        tiles: plan.tiles.len(),
        pilot_samples: pilot_pixels * n0,
        pilot_seconds,
        threads: pool.current_num_threads(),
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
            let fixed = quote(&scene, &settings, Sampling::fixed(64), 0, 4).unwrap();
            assert_eq!((fixed.samples, fixed.pilot_tiles), (128 * 96 * 64, 4));
            assert_eq!(fixed.pilot_samples, 4 * 32 * 32 * 16, "a fixed render's pilot is one pass of its tiles");
        }
    }
}
