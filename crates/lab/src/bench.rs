//! `tessera bench`: ray throughput of the BVH and rendering speed against error. Figures are
//! medians of repeated runs; the machine is noisy, so compare medians and ratios.

use anyhow::{Context, Result};
use clap::{Args, Subcommand};
use indicatif::ProgressBar;
use std::path::PathBuf;
use std::time::Instant;
use tessera_film::compare;
use tessera_local::load_scene;
use tessera_local::options::{RenderOptions, Sampling};
use tessera_local::render_film;
use tessera_render::Hit;
use tessera_render::glam::{Vec2, Vec3};
use tessera_render::mix64;
use tessera_render::{Bvh, PACKET};
use tessera_render::{Frame, sample_cosine_hemisphere};
use tessera_render::{RenderSettings, SamplerKind, Scene};

#[derive(Subcommand, Debug)]
pub enum BenchCommand {
    /// BVH build time and single-thread closest-hit throughput (primary and incoherent rays).
    Rays(RaysArgs),
    /// Samples per second on the Cornell box at 1 and 2 threads, and the time to reach an RMSE.
    Cornell(CornellArgs),
    /// Coordinator capacity: simulated workers return precomputed 32 x 32 results as fast as
    /// they can over loopback gRPC to a coordinator running on one core.
    Coordinator(CoordinatorBenchArgs),
    /// Farm overhead: `render --workers 2` against the in-process renderer on 2 threads.
    Farm(FarmBenchArgs),
    /// Spectral against RGB transport on the Cornell box's measured spectra: cost per sample and
    /// error against a spectral reference at equal time.
    Spectral(crate::bench_spectral::SpectralBenchArgs),
    /// Animation: the cost of posing a scene and rebuilding its BVH each frame against rendering
    /// the frame, and sequence throughput alone and through 1 and 2 local workers.
    Animation(crate::bench_animation::AnimationBenchArgs),
    /// Environment lighting: importance sampling of the map against uniform sphere sampling, at
    /// equal time, on a glossy sphere.
    Envmap(crate::bench_envmap::EnvmapBenchArgs),
    /// Many lights: the light tree against choosing lights in proportion to power, at equal time.
    Lights(crate::bench_lights::LightsBenchArgs),
}

#[derive(Args, Debug)]
pub struct CoordinatorBenchArgs {
    /// Simulated workers.
    #[arg(long, default_value_t = 8, env = "TESSERA_BENCH_WORKERS")]
    pub workers: usize,
    /// Seconds to run.
    #[arg(long, default_value_t = 10.0, env = "TESSERA_BENCH_SECONDS")]
    pub seconds: f64,
    /// Samples per second each simulated worker claims and renders at: it sleeps as long as a
    /// real worker of that speed would take over each job (the coordinator sizes jobs from it).
    /// 0: return results at once, as fast as the coordinator takes them.
    #[arg(long, default_value_t = 0.0, env = "TESSERA_BENCH_WORKER_SPEED")]
    pub worker_speed: f64,
    /// Also submit, at a higher priority, a render this many pixels on a side (one 16-sample
    /// pass per 32 x 32 tile) and report the lease latency while it finishes and its EXR is
    /// written, beside the latency over the whole run. 0: none.
    #[arg(long, default_value_t = 0, env = "TESSERA_BENCH_FINISH")]
    pub finish: u32,
    /// Also serve the web dashboard, and have this many simulated browsers watch the finishing
    /// render's page (with --finish): each fetches the render list and the preview every 0.5 s,
    /// as fast as the page does.
    #[arg(long, default_value_t = 0, env = "TESSERA_BENCH_WATCHERS")]
    pub watchers: usize,
}

#[derive(Args, Debug)]
pub struct FarmBenchArgs {
    /// Image side.
    #[arg(long, default_value_t = 512, env = "TESSERA_BENCH_SIZE")]
    pub size: u32,
    #[arg(long, default_value_t = 64, env = "TESSERA_BENCH_SPP")]
    pub spp: u32,
    #[arg(long, default_value_t = 3, env = "TESSERA_BENCH_REPEAT")]
    pub repeat: usize,
}

#[derive(Args, Debug)]
pub struct RaysArgs {
    /// Scene [default: MetalRoughSpheresNoTextures from ../shared/scenes, when present].
    pub scene: Option<String>,
    /// Rays per measurement (a square grid of about this many primary rays, its side rounded up to whole packets).
    #[arg(long, default_value_t = 1 << 20, env = "TESSERA_BENCH_RAYS")]
    pub rays: usize,
    /// Repetitions; the median is reported.
    #[arg(long, default_value_t = 5, env = "TESSERA_BENCH_REPEAT")]
    pub repeat: usize,
}

#[derive(Args, Debug)]
pub struct CornellArgs {
    /// Image side in pixels.
    #[arg(long, default_value_t = 256, env = "TESSERA_BENCH_SIZE")]
    pub size: u32,
    /// Samples per pixel for the throughput runs.
    #[arg(long, default_value_t = 64, env = "TESSERA_BENCH_SPP")]
    pub spp: u32,
    /// Converged reference EXR; rendered (and written here) when the file does not exist.
    #[arg(long, default_value = "cornell-reference.exr", env = "TESSERA_BENCH_REFERENCE")]
    pub reference: PathBuf,
    /// Samples per pixel of the reference when it has to be rendered.
    #[arg(long, default_value_t = 8192, env = "TESSERA_BENCH_REFERENCE_SPP")]
    pub reference_spp: u32,
    /// RMSE to reach.
    #[arg(long, default_value_t = 0.005, env = "TESSERA_BENCH_TARGET_RMSE")]
    pub target_rmse: f64,
    /// Repetitions of the throughput runs; the median is reported.
    #[arg(long, default_value_t = 3, env = "TESSERA_BENCH_REPEAT")]
    pub repeat: usize,
    /// Path length, as Mitsuba's max_depth 8 (7 bounces); 0 uses the renderer's default.
    #[arg(long, default_value_t = 7, env = "TESSERA_BENCH_MAX_BOUNCES")]
    pub max_bounces: u32,
    /// Russian roulette from this bounce on, under the bounce cap: 5 as Mitsuba's rr_depth 5, the
    /// default of the path tracer it is compared with; 0 turns roulette off. The reference is
    /// rendered without roulette (the same expectation, less noise).
    #[arg(long, default_value_t = 5, env = "TESSERA_BENCH_RR_FROM")]
    pub rr_from: u32,
    /// Largest spp tried while looking for the target RMSE.
    #[arg(long, default_value_t = 2048, env = "TESSERA_BENCH_MAX_SPP")]
    pub max_spp: u32,
    /// Also measure the time to Mitsuba 3's quoted errors with Mitsuba's default Gaussian
    /// reconstruction filter, which its figures use (a second reference, rendered once):
    /// `--mitsuba-filter false` skips it.
    #[arg(long, default_value_t = true, action = clap::ArgAction::Set, env = "TESSERA_BENCH_MITSUBA_FILTER")]
    pub mitsuba_filter: bool,
}

pub fn run(cmd: BenchCommand) -> Result<()> {
    match cmd {
        BenchCommand::Rays(a) => rays(a),
        BenchCommand::Cornell(a) => cornell(a),
        BenchCommand::Coordinator(a) => crate::bench_farm::coordinator(a),
        BenchCommand::Farm(a) => crate::bench_farm::farm(a),
        BenchCommand::Spectral(a) => crate::bench_spectral::spectral(a),
        BenchCommand::Animation(a) => crate::bench_animation::animation(a),
        BenchCommand::Envmap(a) => crate::bench_envmap::envmap(a),
        BenchCommand::Lights(a) => crate::bench_lights::lights(a),
    }
}

pub fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

const SHARED_HEAVY_SCENE: &str =
    "../shared/scenes/MetalRoughSpheresNoTextures/glTF-Binary/MetalRoughSpheresNoTextures.glb";

fn rays(args: RaysArgs) -> Result<()> {
    let spec = match args.scene {
        Some(s) => s,
        None if std::path::Path::new(SHARED_HEAVY_SCENE).is_file() => SHARED_HEAVY_SCENE.to_string(),
        None => {
            println!(
                "skipped: {SHARED_HEAVY_SCENE} is not present (run from the checkout beside ../shared, or name a scene)"
            );
            return Ok(());
        }
    };
    let options = default_options();
    let loaded = load_scene(&spec, &options)?;
    let scene = &loaded.scene;
    let corners: Vec<[Vec3; 3]> =
        scene.mesh.triangles.iter().map(|t| t.vertices.map(|i| scene.mesh.positions[i as usize])).collect();
    let repeat = args.repeat.max(1);
    let build = median((0..repeat.min(3)).map(|_| time(|| drop(Bvh::build(&corners)))).collect());
    println!("scene       {spec} ({} triangles)", corners.len());
    println!("bvh build   {:.3} s (median of {}, CWBVH via obvhs, rayon off)", build, repeat.min(3));

    let side = (args.rays as f64).sqrt() as u32;
    // Primary rays from the scene's own first camera: the view its renders take (from outside, a
    // closed room such as the Cornell box would only show walls from behind, and no bounce would
    // come back in). A scene without one gets a camera on the +z side whose view the bounds just
    // fill, so that as many rays as possible hit (the framing camera leaves margins).
    let (lo, hi) = scene.bounds;
    let (center, half) = ((lo + hi) * 0.5, (hi - lo) * 0.5);
    let yfov = 30f32.to_radians();
    let distance = half.x.max(half.y) / (0.5 * yfov).tan() + half.z;
    let bounds_camera = tessera_render::Camera {
        name: "bench".into(),
        to_world: tessera_render::look_at(center + Vec3::Z * distance, center, Vec3::Y),
        projection: tessera_render::Projection::Perspective { yfov },
    };
    let camera = if loaded.info.framed { &bounds_camera } else { &scene.cameras[0] };
    println!("rays from   camera '{}'", camera.name);
    // Pixel centres in blocks of PACKET/2 x 2 pixels, the packets the first measurement traces.
    let bw = (PACKET as u32 / 2).max(2);
    let side = side.div_ceil(bw).max(1) * bw;
    let primary: Vec<(Vec3, Vec3)> = (0..side * side)
        .map(|i| {
            let (block, corner) = (i / (2 * bw), i % (2 * bw));
            let (x, y) = ((block % (side / bw)) * bw + corner % bw, (block / (side / bw)) * 2 + corner / bw);
            camera.generate_ray(side, side, Vec2::new(x as f32 + 0.5, y as f32 + 0.5))
        })
        .collect();
    // Incoherent rays: diffuse bounces from the primary hits.
    let mut incoherent = Vec::with_capacity(primary.len());
    for (i, &(o, d)) in primary.iter().enumerate() {
        if let Some(hit) = scene.intersect(o, d, f32::INFINITY) {
            let sp = scene.surface(hit, o, d);
            let h = mix64(i as u64);
            let u = [(h >> 40) as f32 / (1u64 << 24) as f32, ((h >> 16) & 0xFF_FFFF) as f32 / (1u64 << 24) as f32];
            let wi = Frame::from_normal(sp.ng).to_world(sample_cosine_hemisphere(u));
            incoherent.push((scene.offset_origin(&sp, wi), wi));
        }
    }
    let packets: Vec<Vec<(Vec3, Vec3, f32)>> =
        primary.chunks(PACKET).map(|c| c.iter().map(|&(o, d)| (o, d, f32::INFINITY)).collect()).collect();
    let key = |h: Option<Hit>| h.map(|h| (h.triangle, h.t.to_bits()));
    let alone = primary.iter().map(|&(o, d)| key(scene.intersect(o, d, f32::INFINITY)));
    let together = packets.iter().flat_map(|p| scene.intersect_packet(p).into_iter().take(p.len()).map(key));
    anyhow::ensure!(alone.eq(together), "packets and single rays found different hits (a traversal bug)");
    // The timed runs only count hits: storing them would pass through memory and evict the BVH.
    let one_by_one =
        |rays: &[(Vec3, Vec3)]| rays.iter().filter(|&&(o, d)| scene.intersect(o, d, f32::INFINITY).is_some()).count();
    let packed = || packets.iter().map(|p| scene.intersect_packet(p).iter().filter(|h| h.is_some()).count()).sum();
    let report = |name: &str, rays: usize, trace: &dyn Fn() -> usize| {
        let mut hits = 0usize;
        let secs = median((0..repeat).map(|_| time(|| hits = trace())).collect());
        println!(
            "{name:<21} {:.2} Mrays/s single thread ({rays} rays, {:.0}% hit, median of {repeat})",
            rays as f64 / secs / 1e6,
            100.0 * hits as f64 / rays.max(1) as f64
        );
    };
    report(&format!("primary, packets of {PACKET}"), primary.len(), &packed);
    report("primary, one by one", primary.len(), &|| one_by_one(&primary));
    report("incoherent", incoherent.len(), &|| one_by_one(&incoherent));
    println!("(render traces camera rays in packets: a pixel's samples, or neighbouring pixels; bounces one by one)");
    Ok(())
}

pub fn time(f: impl FnOnce()) -> f64 {
    let t = Instant::now();
    f();
    t.elapsed().as_secs_f64()
}

pub(crate) fn default_options() -> RenderOptions {
    options_from(&[])
}

/// Render options as `tessera render` would take them from these flags.
pub(crate) fn options_from(flags: &[&str]) -> RenderOptions {
    use clap::Parser;
    #[derive(Parser)]
    struct Wrapper {
        #[command(flatten)]
        options: RenderOptions,
    }
    Wrapper::parse_from(std::iter::once("bench").chain(flags.iter().copied())).options
}

/// The benchmark's settings; `roulette`: whether to play Russian roulette (`--rr-from`).
fn cornell_settings(
    scene: &Scene,
    args: &CornellArgs,
    seed: u64,
    sampler: SamplerKind,
    roulette: bool,
) -> Result<RenderSettings> {
    let size = args.size;
    let mut options = default_options();
    options.max_bounces = (args.max_bounces > 0).then_some(args.max_bounces);
    options.rr_from = (roulette && args.rr_from > 0).then_some(args.rr_from);
    options.width = size;
    options.height = size;
    options.seed = seed;
    // RGB, as the Mitsuba and pbrt figures it is compared with (`bench spectral` compares transports).
    options.color = Some(tessera_local::options::ColorArg::Rgb);
    let (mut settings, _) = options.settings(scene)?;
    settings.sampler = sampler;
    Ok(settings)
}

fn cornell(args: CornellArgs) -> Result<()> {
    // Checked before the minutes of rendering that come first.
    anyhow::ensure!(
        !args.mitsuba_filter || args.size == 256,
        "Mitsuba's figures are for 256 x 256: use --size 256, or --mitsuba-filter false"
    );
    let loaded = load_scene("builtin:cornell-box", &default_options())?;
    let scene = &loaded.scene;
    let settings = cornell_settings(scene, &args, 1, SamplerKind::Sobol, true)?;
    println!("cornell box {0}x{0}, mis, sobol, {1:?}", args.size, settings.termination);
    let pixels = (args.size * args.size) as f64;
    let mut per_thread = Vec::new();
    for threads in [1usize, 2] {
        let secs = median(
            (0..args.repeat.max(1))
                .map(|_| {
                    time(|| {
                        drop(render_film(scene, &settings, Sampling::fixed(args.spp), threads, &ProgressBar::hidden()))
                    })
                })
                .collect(),
        );
        let rate = pixels * args.spp as f64 / secs;
        per_thread.push(rate);
        println!(
            "{threads} thread(s): {:.2} M samples/s, {:.1} ms per {size}x{size} sample pass (median of {})",
            rate / 1e6,
            secs / args.spp as f64 * 1e3,
            args.repeat,
            size = args.size
        );
    }
    println!("scaling 1 -> 2 threads: {:.2}x", per_thread[1] / per_thread[0]);

    let reference = load_or_render_reference(scene, &args)?;
    for sampler in [SamplerKind::Independent, SamplerKind::Sobol] {
        let s = cornell_settings(scene, &args, 2, sampler, true)?;
        // Renders `spp` on 2 threads and prints its error; returns (seconds, rmse).
        let measure = |spp: u32, note: &str| -> Result<(f64, f64)> {
            let t = Instant::now();
            let film = render_film(scene, &s, Sampling::fixed(spp), 2, &ProgressBar::hidden())?;
            let secs = t.elapsed().as_secs_f64();
            let c = compare(&film.resolve(), &reference, false).context("reference size differs")?;
            let ce = compare(&film.resolve(), &reference, true).context("reference size differs")?;
            println!(
                "{:<11} {spp:>5} spp  {secs:>7.3} s  rmse {:.5}  (emitters excluded {:.5}){note}",
                sampler.name(),
                c.rmse,
                ce.rmse
            );
            Ok((secs, c.rmse))
        };
        let levels = doubling(args.max_spp, args.target_rmse, measure)?;
        match reach(args.target_rmse, &levels, measure)? {
            Some((spp, secs)) => println!(
                "{}: rmse {} reached at {spp} spp in {secs:.3} s (2 threads)",
                sampler.name(),
                args.target_rmse
            ),
            None => println!("{}: rmse {} not reached by {} spp", sampler.name(), args.target_rmse, args.max_spp),
        }
    }
    if args.mitsuba_filter {
        against_mitsuba(scene, &args, pixels / per_thread[1])?;
    }
    Ok(())
}

/// The figures the issue gives for Mitsuba 3's LLVM backend on this machine's kind: 15 ms per
/// 256 x 256 sample pass on 2 threads, RMSE 0.0079 at 256 spp with its default independent
/// sampler and 0.0032 with its best, developed with its default Gaussian filter.
const MITSUBA_PASS_SECS: f64 = 0.015;
const MITSUBA_SPP: u32 = 256;
const MITSUBA_RMSE: [(&str, f64); 2] = [("independent", 0.0079), ("best sampler", 0.0032)];

/// Time to Mitsuba's errors with Mitsuba's filter (see [`crate::bench_filter`]): each sampler's
/// error curve, and for each of Mitsuba's figures the fewest spp that reach it, timed as Mitsuba's
/// are, as passes of the renderer (`pass_secs` each, measured on 2 threads above): the bench's
/// splatting is instrumentation, written for clarity, not speed.
fn against_mitsuba(scene: &Scene, args: &CornellArgs, pass_secs: f64) -> Result<()> {
    let reference = load_or_render_gaussian_reference(scene, args)?;
    println!(
        "with Mitsuba's default Gaussian filter (stddev 0.5 px, radius 2 px), as Mitsuba's figures; \
         times are spp x {:.1} ms per pass (2 threads, above), as Mitsuba's are spp x {:.0} ms:",
        pass_secs * 1e3,
        MITSUBA_PASS_SECS * 1e3
    );
    // Curves go on until the smallest of Mitsuba's errors is reached.
    let hardest = MITSUBA_RMSE.iter().map(|m| m.1).fold(f64::INFINITY, f64::min);
    let mitsuba = MITSUBA_SPP as f64 * MITSUBA_PASS_SECS;
    for sampler in [SamplerKind::Independent, SamplerKind::Sobol] {
        let s = cornell_settings(scene, args, 2, sampler, true)?;
        let measure = |spp: u32, note: &str| -> Result<(f64, f64)> {
            let image = crate::bench_filter::render_gaussian(scene, &s, spp, 2)?;
            let secs = spp as f64 * pass_secs;
            let c = compare(&image, &reference, false).context("reference size differs")?;
            println!("{:<11} {spp:>5} spp  {secs:>7.3} s  rmse {:.5} (gaussian){note}", sampler.name(), c.rmse);
            Ok((secs, c.rmse))
        };
        let levels = doubling(args.max_spp, hardest, measure)?;
        for (name, rmse) in MITSUBA_RMSE {
            match reach(rmse, &levels, measure)? {
                Some((spp, secs)) => println!(
                    "{}: Mitsuba's {name} rmse {rmse} at {spp} spp in {secs:.3} s; Mitsuba {MITSUBA_SPP} spp \
                     in {mitsuba:.2} s: {:.2}x its time",
                    sampler.name(),
                    secs / mitsuba
                ),
                None => {
                    println!("{}: Mitsuba's {name} rmse {rmse} not reached by {} spp", sampler.name(), args.max_spp)
                }
            }
        }
    }
    Ok(())
}

/// Error curve by doubling from 1 spp: each level is measured (and printed) until the error
/// reaches `target` and at least 256 spp were seen, or past `max_spp`. Returns (spp, secs, rmse).
fn doubling(
    max_spp: u32,
    target: f64,
    mut measure: impl FnMut(u32, &str) -> Result<(f64, f64)>,
) -> Result<Vec<(u32, f64, f64)>> {
    let mut levels = Vec::new();
    let mut spp = 1;
    while spp <= max_spp {
        let (secs, rmse) = measure(spp, "")?;
        levels.push((spp, secs, rmse));
        if rmse <= target && spp >= 256 {
            break;
        }
        spp *= 2;
    }
    Ok(levels)
}

/// The fewest spp that reach `target`, and their time: the first doubling level that does, its
/// bracket then halved twice (to an eighth of its top), since doubling overshoots by up to 2x.
fn reach(
    target: f64,
    levels: &[(u32, f64, f64)],
    mut measure: impl FnMut(u32, &str) -> Result<(f64, f64)>,
) -> Result<Option<(u32, f64)>> {
    let Some(&(top, secs, _)) = levels.iter().find(|l| l.2 <= target) else {
        return Ok(None);
    };
    let mut reached = (top, secs);
    let (mut lo, mut hi) = (top / 2, top);
    while top > 1 && hi - lo > (top / 8).max(1) {
        let mid = (lo + hi) / 2;
        let (secs, rmse) = measure(mid, "  (narrowing)")?;
        if rmse <= target {
            (hi, reached) = (mid, (mid, secs));
        } else {
            lo = mid;
        }
    }
    Ok(Some(reached))
}

/// The Gaussian-filtered reference, rendered like the box one (no roulette, Sobol, its own seed)
/// and cached next to it as `STEM-gaussian.exr`.
fn load_or_render_gaussian_reference(scene: &Scene, args: &CornellArgs) -> Result<tessera_film::ExrImage> {
    let stem = args.reference.file_stem().and_then(|s| s.to_str()).unwrap_or("cornell-reference");
    let path = args.reference.with_file_name(format!("{stem}-gaussian.exr"));
    let s = cornell_settings(scene, args, 999, SamplerKind::Sobol, false)?;
    tessera_local::load_or_make_reference(&path, args.reference_spp, || {
        crate::bench_filter::render_gaussian(scene, &s, args.reference_spp, 0)
    })
}

fn load_or_render_reference(scene: &Scene, args: &CornellArgs) -> Result<tessera_film::ExrImage> {
    let s = cornell_settings(scene, args, 999, SamplerKind::Sobol, false)?;
    tessera_local::load_or_render_reference(scene, "builtin:cornell-box", &s, args.reference_spp, &args.reference)
}
