//! `tessera bench quote`: how close `submit --quote` comes. Each scene is quoted (a pilot of the
//! first round of up to 64 tiles, as `submit --quote` runs it) and then rendered to its target
//! error on the same threads; the quoted samples and core-seconds are set against the render's
//! samples and its core-seconds (wall time x threads, and the process's CPU time).

use crate::bench::scaling::cpu_seconds;
use crate::bench::{median, options_from, time};
use anyhow::Result;
use clap::Args;
use indicatif::ProgressBar;
use tessera_local::quote::{PILOT_TILES, quote as quote_render};
use tessera_local::{load_scene, render_film};

/// Three scenes of different kinds, each with a target error its tiles reach inside 1024 spp
/// at 256 x 256 (run from the project's root, where the fixture lies).
const SCENES: [(&str, f32); 3] = [
    ("builtin:cornell-box", 0.08),
    ("builtin:furnace?base=0.8&metallic=0.5&roughness=0.4", 0.02),
    ("crates/scene/tests/fixtures/scenes/BoxTextured/glTF-Binary/BoxTextured.glb", 0.02),
];

#[derive(Args, Debug)]
pub struct QuoteBenchArgs {
    /// Scenes [default: the Cornell box, a rough half-metal sphere in a white furnace, and
    /// BoxTextured under a grey environment, each at its own target error].
    pub scenes: Vec<String>,
    /// Target error for the scenes named.
    #[arg(long, default_value_t = 0.02, env = "TESSERA_BENCH_TARGET_ERROR")]
    pub target_error: f32,
    /// Image side in pixels.
    #[arg(long, default_value_t = 256, env = "TESSERA_BENCH_SIZE")]
    pub size: u32,
    /// Threads of the pilot and the render (0: every core).
    #[arg(long, default_value_t = 0, env = "TESSERA_BENCH_THREADS")]
    pub threads: usize,
    /// Repetitions, quote and render alternating; medians are reported.
    #[arg(long, default_value_t = 3, env = "TESSERA_BENCH_REPEAT")]
    pub repeat: usize,
}

pub fn quote(args: QuoteBenchArgs) -> Result<()> {
    let scenes: Vec<(String, f32)> = if args.scenes.is_empty() {
        SCENES.iter().map(|(s, e)| (s.to_string(), *e)).collect()
    } else {
        args.scenes.iter().map(|s| (s.clone(), args.target_error)).collect()
    };
    let threads =
        if args.threads == 0 { std::thread::available_parallelism().map_or(1, |n| n.get()) } else { args.threads };
    let side = args.size.to_string();
    println!(
        "{side}x{side}, up to 1024 spp from 16, grey environment 0.5, {threads} thread(s); a pilot of up to {PILOT_TILES} tiles; medians of {}",
        args.repeat.max(1)
    );
    let mut ratios = Vec::new();
    for (spec, target) in &scenes {
        let target = target.to_string();
        let flags = [
            "--width",
            &side,
            "--height",
            &side,
            "--spp",
            "1024",
            "--min-spp",
            "16",
            "--target-error",
            &target,
            "--env",
            "0.5,0.5,0.5",
        ];
        let options = options_from(&flags);
        let loaded = load_scene(spec, &options)?;
        let (settings, sampling) = (options.settings(&loaded.scene)?.0, options.sampling()?.0);
        let (mut quoted, mut actual) = (Vec::new(), Vec::new());
        let (mut quoted_samples, mut samples, mut cpu_share) = (0, 0, Vec::new());
        for _ in 0..args.repeat.max(1) {
            let q = quote_render(&loaded.scene, &settings, sampling, threads, PILOT_TILES)?;
            quoted.push(q.core_seconds);
            quoted_samples = q.samples;
            let (cpu, mut film) = (cpu_seconds(), None);
            let wall =
                time(|| film = Some(render_film(&loaded.scene, &settings, sampling, threads, &ProgressBar::hidden())));
            let film = film.expect("timed")?;
            samples = film.total_samples() + film.dropped();
            actual.push(wall * threads as f64);
            cpu_share.push((cpu_seconds() - cpu) / (wall * threads as f64));
        }
        let (q, a) = (median(quoted), median(actual));
        let name = spec.rsplit('/').next().unwrap_or(spec);
        println!(
            "{name} (target {target}): samples quoted {quoted_samples}, rendered {samples} ({:.2}x); core-seconds quoted {q:.2}, rendered {a:.2} ({:.2}x; CPU busy {:.2} of the render's)",
            quoted_samples as f64 / samples.max(1) as f64,
            q / a,
            median(cpu_share)
        );
        ratios.push(q / a);
    }
    if ratios.len() > 1 {
        let mean = (ratios.iter().map(|r| r.ln()).sum::<f64>() / ratios.len() as f64).exp();
        println!("quoted over rendered core-seconds, geometric mean over {} scenes: {mean:.2}x", ratios.len());
    }
    Ok(())
}
