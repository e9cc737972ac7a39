//! `tessera bench scaling`: how a render's time falls from one thread to many on real scenes,
//! with loading (parsing, the BVH) and the render loop timed apart, so that a stage left on one
//! thread, or a thread left idle at the end of a frame, shows as a ratio below linear.

use crate::bench::{median, options_from, time};
use anyhow::Result;
use clap::Args;
use indicatif::ProgressBar;
use std::path::Path;
use tessera_local::{load_scene, render_film};

/// The suite: the built-in Cornell box and the glTF assets of `../shared/scenes` that are present
/// (textured PBR, a million-triangle mesh, glass, a skinned character).
const SUITE: &[&str] = &[
    "builtin:cornell-box",
    "../shared/scenes/WaterBottle/glTF/WaterBottle.gltf",
    "../shared/scenes/MetalRoughSpheresNoTextures/glTF-Binary/MetalRoughSpheresNoTextures.glb",
    "../shared/scenes/Duck/glTF-Binary/Duck.glb",
    "../shared/scenes/GlassHurricaneCandleHolder/glTF-Binary/GlassHurricaneCandleHolder.glb",
    "../shared/scenes/CesiumMan/glTF-Binary/CesiumMan.glb",
];

/// The scenes `named`, or else those of the suite that are present (saying so when some are not).
pub(crate) fn suite(named: &[String]) -> Vec<String> {
    if !named.is_empty() {
        return named.to_vec();
    }
    let found: Vec<String> =
        SUITE.iter().filter(|s| s.starts_with("builtin:") || Path::new(s).is_file()).map(|s| s.to_string()).collect();
    if found.len() < SUITE.len() {
        println!("(run from the project's root with ../shared beside it for the whole suite; {} found)", found.len());
    }
    found
}

#[derive(Args, Debug)]
pub struct ScalingBenchArgs {
    /// Scenes [default: the suite: the Cornell box and those of WaterBottle,
    /// MetalRoughSpheresNoTextures, Duck, GlassHurricaneCandleHolder and CesiumMan found in
    /// ../shared/scenes].
    pub scenes: Vec<String>,
    /// Thread counts, comma-separated [default: 1, 2, 4, ... and this machine's core count].
    #[arg(long, value_delimiter = ',', env = "TESSERA_BENCH_THREADS")]
    pub threads: Vec<usize>,
    /// Image side in pixels.
    #[arg(long, default_value_t = 256, env = "TESSERA_BENCH_SIZE")]
    pub size: u32,
    /// Samples per pixel (every pixel, --quality fixed).
    #[arg(long, default_value_t = 64, env = "TESSERA_BENCH_SPP")]
    pub spp: u32,
    /// Repetitions, thread counts alternating within each; medians are reported.
    #[arg(long, default_value_t = 3, env = "TESSERA_BENCH_REPEAT")]
    pub repeat: usize,
}

/// One scene's medians at one thread count.
struct Timing {
    threads: usize,
    load: f64,
    render: f64,
    /// The render loop's CPU time over `threads` x its wall time: below 1 by the time its
    /// threads sat without work.
    busy: f64,
    /// `threads` renders of one thread each, at once: their throughput as a fraction of
    /// `threads` x one alone (of the first count's), what this machine's cores give work that
    /// shares nothing: the ceiling of the render loop's fraction of linear here.
    independent: f64,
}

pub fn scaling(args: ScalingBenchArgs) -> Result<()> {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let mut counts = if args.threads.is_empty() {
        let mut c: Vec<usize> =
            std::iter::successors(Some(1usize), |t| Some(t * 2)).take_while(|&t| t < cores).collect();
        c.push(cores);
        c
    } else {
        args.threads.iter().map(|&t| t.max(1)).collect()
    };
    counts.sort_unstable();
    counts.dedup();
    let scenes = suite(&args.scenes);
    let (side, spp) = (args.size.to_string(), args.spp.to_string());
    let options =
        options_from(&["--width", &side, "--height", &side, "--spp", &spp, "--quality", "fixed", "--env", "1,1,1"]);
    println!(
        "{side}x{side}, {spp} spp, 7 bounces, white environment; {cores} cores here; medians of {} (thread counts alternating)",
        args.repeat.max(1)
    );
    println!("load: parsing and building the scene (BVH); render: the render loop; whole: both");
    let mut fractions: Vec<Vec<[f64; 4]>> = vec![Vec::new(); counts.len()];
    for spec in &scenes {
        let timings = measure(spec, &options, &counts, args.repeat.max(1))?;
        let name = spec.rsplit('/').next().unwrap_or(spec);
        println!("{name}:");
        let base = &timings[0];
        for (k, t) in timings.iter().enumerate() {
            let render_speedup = base.render / t.render * base.threads as f64;
            let whole_speedup = (base.load + base.render) / (t.load + t.render) * base.threads as f64;
            let linear = render_speedup / t.threads as f64;
            fractions[k].push([linear, t.busy, t.independent, whole_speedup / t.threads as f64]);
            println!(
                "  {:>3} thread(s): load {:.3} s, render {:.3} s ({render_speedup:.2}x: {linear:.3} of linear, threads busy {:.3}, ceiling {:.3}), whole {:.3} s ({whole_speedup:.2}x)",
                t.threads,
                t.load,
                t.render,
                t.busy,
                t.independent,
                t.load + t.render,
            );
        }
    }
    if scenes.len() > 1 {
        println!("geometric means over {} scenes:", scenes.len());
        for (t, f) in counts.iter().zip(&fractions) {
            let mean = |i: usize| (f.iter().map(|x| x[i].ln()).sum::<f64>() / f.len() as f64).exp();
            println!(
                "  {t:>3} thread(s): render loop {:.3} of linear (busy {:.3}, ceiling {:.3}); whole {:.3} of linear",
                mean(0),
                mean(1),
                mean(2),
                mean(3)
            );
        }
    }
    println!("busy: the render loop's CPU time over its threads x wall time; ceiling: as many one-thread");
    println!("renders at once, against one alone (what these cores give work that shares nothing)");
    Ok(())
}

/// Load and render `spec` at each of `counts` threads, `repeat` times, counts alternating; the
/// load runs on a pool of as many threads as the render, as `tessera render --threads` has it.
fn measure(
    spec: &str,
    options: &tessera_local::options::RenderOptions,
    counts: &[usize],
    repeat: usize,
) -> Result<Vec<Timing>> {
    let loaded = load_scene(spec, options)?;
    let (settings, sampling) = (options.settings(&loaded.scene)?.0, options.sampling()?.0);
    let render = |scene: &tessera_render::Scene, threads: usize| -> Result<(f64, f64)> {
        let (cpu, mut film) = (cpu_seconds(), Ok(()));
        let wall = time(|| film = render_film(scene, &settings, sampling, threads, &ProgressBar::hidden()).map(drop));
        film?;
        Ok((wall, (cpu_seconds() - cpu) / (threads as f64 * wall)))
    };
    let n = counts.len();
    let (mut loads, mut walls, mut busy, mut apart) =
        (vec![vec![]; n], vec![vec![]; n], vec![vec![]; n], vec![vec![]; n]);
    for _ in 0..repeat {
        for (k, &threads) in counts.iter().enumerate() {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build()?;
            let mut again = None;
            loads[k].push(time(|| again = Some(pool.install(|| load_scene(spec, options)))));
            let (wall, b) = render(&again.expect("timed")?.scene, threads)?;
            walls[k].push(wall);
            busy[k].push(b);
            // The same render on one thread, `threads` of them at once.
            let mut each = Vec::new();
            let all = time(|| {
                each = std::thread::scope(|s| {
                    let runs: Vec<_> = (0..threads).map(|_| s.spawn(|| render(&loaded.scene, 1))).collect();
                    runs.into_iter().map(|r| r.join().unwrap_or_else(|p| std::panic::resume_unwind(p))).collect()
                })
            });
            each.into_iter().collect::<Result<Vec<_>>>()?;
            apart[k].push(all);
        }
    }
    let alone = median(apart[0].clone());
    Ok((0..n)
        .map(|k| Timing {
            threads: counts[k],
            load: median(loads[k].clone()),
            render: median(walls[k].clone()),
            busy: median(busy[k].clone()),
            independent: alone / median(apart[k].clone()),
        })
        .collect())
}

/// CPU time of this process so far, all threads (0 where it cannot be read).
pub(crate) fn cpu_seconds() -> f64 {
    #[cfg(unix)]
    {
        let mut usage = std::mem::MaybeUninit::<libc::rusage>::zeroed();
        // SAFETY: getrusage writes a whole rusage into the buffer it is given.
        if unsafe { libc::getrusage(libc::RUSAGE_SELF, usage.as_mut_ptr()) } == 0 {
            // SAFETY: written by the successful call above.
            let u = unsafe { usage.assume_init() };
            let secs = |t: libc::timeval| t.tv_sec as f64 + t.tv_usec as f64 * 1e-6;
            return secs(u.ru_utime) + secs(u.ru_stime);
        }
    }
    0.0
}
