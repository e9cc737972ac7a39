//! `tessera bench lights`: the light tree against choosing lights in proportion to power, at
//! equal time, on scenes with a few to thousands of lights.

use crate::bench::{median, options_from, time};
use anyhow::{Context, Result};
use clap::Args;
use indicatif::ProgressBar;
use tessera_film::compare;
use tessera_local::options::Sampling;
use tessera_local::{load_scene, render_film};
use tessera_render::{LightSampler, RenderSettings};

#[derive(Args, Debug)]
pub struct LightsBenchArgs {
    /// Scenes [default: builtin:many-lights, and from ../shared/scenes LightsPunctualLamp and
    /// EmissiveStrengthTest where present].
    pub scenes: Vec<String>,
    /// Image side in pixels.
    #[arg(long, default_value_t = 160, env = "TESSERA_BENCH_SIZE")]
    pub size: u32,
    /// Samples per pixel of the timed runs.
    #[arg(long, default_value_t = 16, env = "TESSERA_BENCH_SPP")]
    pub spp: u32,
    /// Samples per pixel of the reference (light tree).
    #[arg(long, default_value_t = 1024, env = "TESSERA_BENCH_REFERENCE_SPP")]
    pub reference_spp: u32,
    /// Repetitions of the timed runs (different seeds, the two samplers alternating); medians
    /// are reported.
    #[arg(long, default_value_t = 3, env = "TESSERA_BENCH_REPEAT")]
    pub repeat: usize,
}

const SHARED: &[&str] = &[
    "../shared/scenes/LightsPunctualLamp/glTF/LightsPunctualLamp.gltf",
    "../shared/scenes/EmissiveStrengthTest/glTF-Binary/EmissiveStrengthTest.glb",
];

pub fn lights(args: LightsBenchArgs) -> Result<()> {
    let mut scenes = args.scenes.clone();
    if scenes.is_empty() {
        scenes.push("builtin:many-lights".into());
        for path in SHARED {
            if std::path::Path::new(path).exists() {
                scenes.push(path.to_string());
            } else {
                println!("{path} is absent: skipped");
            }
        }
    }
    let side = args.size.to_string();
    let options = options_from(&["--width", &side, "--height", &side, "--quality", "fixed"]);
    println!(
        "light tree against power-proportional choice: {0}x{0} px, {1} spp, 7 bounces, MIS, all threads; RMSE against \
         {2} spp (tree); medians of {3} runs each, alternating",
        args.size,
        args.spp,
        args.reference_spp,
        args.repeat.max(1)
    );
    for spec in &scenes {
        let loaded = load_scene(spec, &options).with_context(|| spec.clone())?;
        let (settings, _) = options.settings(&loaded.scene)?;
        let scene = &loaded.scene;
        let with = |lights, seed| RenderSettings { lights, seed, ..settings.clone() };
        eprintln!("{spec}: rendering the reference ({} spp)...", args.reference_spp);
        let reference = render_film(
            scene,
            &with(LightSampler::Tree, 1 << 20),
            Sampling::fixed(args.reference_spp),
            0,
            &ProgressBar::hidden(),
        )?
        .resolve();
        let samplers = [LightSampler::Power, LightSampler::Tree];
        let mut runs = [(Vec::new(), Vec::new()), (Vec::new(), Vec::new())];
        for r in 0..args.repeat.max(1) {
            for (k, &lights) in samplers.iter().enumerate() {
                let s = with(lights, 1 + r as u64);
                let mut film = None;
                let secs =
                    time(|| film = Some(render_film(scene, &s, Sampling::fixed(args.spp), 0, &ProgressBar::hidden())));
                let image = film.expect("timed")?.resolve();
                runs[k].0.push(secs);
                runs[k].1.push(compare(&image, &reference, false).context("sizes differ")?.rmse);
            }
        }
        let [(t_power, e_power), (t_tree, e_tree)] = runs.map(|(t, e)| (median(t), median(e)));
        // RMSE falls as 1 / sqrt(time): the error power-proportional choice would reach in the tree's time.
        let equal_time = e_power * (t_power / t_tree).sqrt();
        println!(
            "{spec}: {} emissive triangles, {} punctual lights, tree depth {}",
            scene.lights.emissive_triangles(),
            scene.lights.punctual.len(),
            scene.lights.tree_depth()
        );
        println!("  power {t_power:.2} s, RMSE {e_power:.5}; at the tree's time {equal_time:.5}");
        println!(
            "  tree  {t_tree:.2} s, RMSE {e_tree:.5}: {:.2}x the error at equal time, {:.2}x the time to equal error",
            e_tree / equal_time,
            (e_tree / equal_time).powi(2)
        );
    }
    Ok(())
}
