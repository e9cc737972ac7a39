//! `tessera bench envmap`: environment lighting, importance sampled by the map's luminance
//! against directions drawn uniformly over the sphere, at equal time, on a glossy sphere.

use crate::bench::{median, options_from, time};
use anyhow::{Context, Result};
use clap::Args;
use indicatif::ProgressBar;
use std::path::PathBuf;
use std::sync::Arc;
use tessera_film::compare;
use tessera_local::options::Sampling;
use tessera_local::render_film;
use tessera_render::glam::Vec3;

#[derive(Args, Debug)]
pub struct EnvmapBenchArgs {
    /// Environment map [default: ../shared/environments/venice_sunset_1k.hdr].
    #[arg(long, env = "TESSERA_BENCH_MAP")]
    pub map: Option<PathBuf>,
    /// Image side in pixels.
    #[arg(long, default_value_t = 128, env = "TESSERA_BENCH_SIZE")]
    pub size: u32,
    /// Samples per pixel of the timed runs.
    #[arg(long, default_value_t = 64, env = "TESSERA_BENCH_SPP")]
    pub spp: u32,
    /// Samples per pixel of the reference (importance sampled).
    #[arg(long, default_value_t = 4096, env = "TESSERA_BENCH_REFERENCE_SPP")]
    pub reference_spp: u32,
    /// Repetitions of the timed runs (different seeds); medians are reported.
    #[arg(long, default_value_t = 3, env = "TESSERA_BENCH_REPEAT")]
    pub repeat: usize,
}

pub fn envmap(args: EnvmapBenchArgs) -> Result<()> {
    let path = args.map.clone().unwrap_or_else(|| PathBuf::from("../shared/environments/venice_sunset_1k.hdr"));
    let load = || tessera_scene::environment::load(&path, 1.0, 0.0).with_context(|| path.display().to_string());
    let importance = load()?.map;
    let uniform =
        Arc::new(Arc::try_unwrap(load()?.map).map_err(|_| anyhow::anyhow!("the map is shared"))?.sampled_uniformly());
    let spec = "builtin:furnace?base=0.9&metallic=1&roughness=0.25";
    let mut scene = tessera_scene::load(spec, &Default::default())?.scene;
    let side = args.size.to_string();
    let options = options_from(&["--width", &side, "--height", &side, "--quality", "fixed", "--max-bounces", "3"]);
    let (settings, _) = options.settings(&scene)?;
    let light = |scene: &tessera_render::Scene, map: &Arc<tessera_render::EnvMap>| {
        scene.light_set(Vec::new(), Vec3::ZERO, Some(map.clone()))
    };
    scene.lights = light(&scene, &importance);
    eprintln!("rendering the reference ({} spp)...", args.reference_spp);
    let reference =
        render_film(&scene, &settings, Sampling::fixed(args.reference_spp), 0, &ProgressBar::hidden())?.resolve();
    println!(
        "{spec} under {}, {}x{} px, {} spp, 3 bounces, MIS, all threads; RMSE against {} spp:",
        path.display(),
        args.size,
        args.size,
        args.spp,
        args.reference_spp
    );
    let mut rows = Vec::new();
    for (name, map) in [("importance", &importance), ("uniform", &uniform)] {
        scene.lights = light(&scene, map);
        let (mut secs, mut errors) = (Vec::new(), Vec::new());
        for r in 0..args.repeat.max(1) {
            let s = tessera_render::RenderSettings { seed: 1 + r as u64, ..settings.clone() };
            let mut film = None;
            secs.push(time(|| {
                film = Some(render_film(&scene, &s, Sampling::fixed(args.spp), 0, &ProgressBar::hidden()))
            }));
            let image = film.expect("timed")?.resolve();
            errors.push(compare(&image, &reference, false).context("sizes differ")?.rmse);
        }
        rows.push((name, median(secs), median(errors)));
    }
    let (t0, e0) = (rows[0].1, rows[0].2);
    for (name, t, e) in &rows {
        // RMSE falls as 1 / sqrt(time): the error this method would reach in the first's time.
        let equal_time = e * (t / t0).sqrt();
        println!(
            "  {name:<10} {t:.2} s, RMSE {e:.5}; at the importance-sampled run's time {equal_time:.5} ({:.2}x)",
            equal_time / e0
        );
    }
    Ok(())
}
