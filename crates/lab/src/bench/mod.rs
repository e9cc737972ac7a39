//! `tessera bench`: ray throughput of the BVH and rendering speed against error. Figures are
//! medians of repeated runs; the machine is noisy, so compare medians and ratios.

mod animation;
mod camera_stages;
mod envmap;
mod farm;
mod lights;
mod memory;
mod peers;
mod quote;
mod scaling;
mod spectral;
mod stages;

use anyhow::{Context, Result};
use clap::{Args, Subcommand};
use indicatif::ProgressBar;
use std::path::PathBuf;
use std::time::Instant;
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
    Spectral(crate::bench::spectral::SpectralBenchArgs),
    /// Animation: the cost of posing a scene and rebuilding its BVH each frame against rendering
    /// the frame, and sequence throughput alone and through 1 and 2 local workers.
    Animation(crate::bench::animation::AnimationBenchArgs),
    /// Environment lighting: importance sampling of the map against uniform sphere sampling, at
    /// equal time, on a glossy sphere.
    Envmap(crate::bench::envmap::EnvmapBenchArgs),
    /// Many lights: the light tree against choosing lights in proportion to power, at equal time.
    Lights(crate::bench::lights::LightsBenchArgs),
    /// Tessera against Mitsuba 3 on a glTF scene both load (textures left out), under a constant
    /// environment: seconds per pass and time to an error, each against its own reference.
    Mitsuba(crate::bench::peers::MitsubaArgs),
    /// What each stage of a path (closest hit, shadow ray, surface point, sampler, BSDF
    /// direction) costs alone on Mitsuba's Cornell box, and whether back-to-back calls overlap.
    Stages(crate::bench::stages::StagesBenchArgs),
    /// Thread scaling: a render's load and render loop from 1 to N threads on a suite of real
    /// scenes, as a fraction of linear.
    Scaling(crate::bench::scaling::ScalingBenchArgs),
    /// Quotes against renders: `submit --quote`'s predicted samples and core-seconds against
    /// what the adaptive render then takes, on three scenes.
    Quote(crate::bench::quote::QuoteBenchArgs),
    /// Memory: each suite scene's peak resident size in a real render, per triangle and texel,
    /// against the estimate the coordinator admits scenes by.
    Memory(crate::bench::memory::MemoryBenchArgs),
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
    /// Also submit, below the endless render's priority (so that it waits), a sequence of this
    /// many 8 x 8 frames: what status, watches and the dashboard's lists cost with a long
    /// sequence on the farm. 0: none.
    #[arg(long, default_value_t = 0, env = "TESSERA_BENCH_SEQUENCE")]
    pub sequence: u32,
    /// Also follow the sequence (or, without one, the endless render) with this many
    /// `tessera watch` streams.
    #[arg(long, default_value_t = 0, env = "TESSERA_BENCH_STATUS_WATCHERS")]
    pub status_watchers: usize,
    /// Also serve the web dashboard and keep this many of its event streams open, each read
    /// as a browser's page reads it.
    #[arg(long, default_value_t = 0, env = "TESSERA_BENCH_EVENT_STREAMS")]
    pub event_streams: usize,
    /// Also submit this many small renders that wait below the endless one: a long render list
    /// for the dashboard's event streams, and `tessera status`, to carry. 0: none.
    #[arg(long, default_value_t = 0, env = "TESSERA_BENCH_LISTED")]
    pub listed: usize,
    /// The coordinator's `--verify`: this fraction of jobs is rendered again by a second
    /// simulated worker and compared (every simulated worker returns the same sums for a job).
    #[arg(long, default_value_t = 0.0, env = "TESSERA_BENCH_VERIFY")]
    pub verify: f64,
    /// Steering in play: three owners of weights 1, 2 and 3 share the workers, each with an
    /// endless render (one of priority 10, one for pool gpu, which every other worker is in).
    #[arg(long, env = "TESSERA_BENCH_STEERING")]
    pub steering: bool,
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
    /// Python with the `embreex` package (Embree 4): its incoherent throughput is measured on the
    /// same rays, alternating with Tessera's. Skipped, with a note, when it cannot be loaded.
    #[arg(long, default_value = "python3", env = "TESSERA_BENCH_PYTHON")]
    pub python: PathBuf,
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
    #[arg(long, default_value = "cornell-mitsuba-box-reference.exr", env = "TESSERA_BENCH_REFERENCE")]
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
    /// Python with Mitsuba 3 (`pip install mitsuba==3.9.1`; its LLVM backend needs libllvm19 and
    /// DRJIT_LIBLLVM_PATH): Mitsuba renders its own box beside Tessera, alternately. Without it
    /// Tessera's side alone is measured, with a note on how to install it.
    #[arg(long, default_value = "python3", env = "TESSERA_BENCH_PYTHON")]
    pub python: PathBuf,
}

pub fn run(cmd: BenchCommand) -> Result<()> {
    match cmd {
        BenchCommand::Rays(a) => rays(a),
        BenchCommand::Cornell(a) => cornell(a),
        BenchCommand::Coordinator(a) => crate::bench::farm::coordinator(a),
        BenchCommand::Farm(a) => crate::bench::farm::farm(a),
        BenchCommand::Spectral(a) => crate::bench::spectral::spectral(a),
        BenchCommand::Animation(a) => crate::bench::animation::animation(a),
        BenchCommand::Envmap(a) => crate::bench::envmap::envmap(a),
        BenchCommand::Lights(a) => crate::bench::lights::lights(a),
        BenchCommand::Mitsuba(a) => crate::bench::peers::mitsuba(a),
        BenchCommand::Stages(a) => crate::bench::stages::stages(a),
        BenchCommand::Scaling(a) => crate::bench::scaling::scaling(a),
        BenchCommand::Memory(a) => crate::bench::memory::memory(a),
        BenchCommand::Quote(a) => crate::bench::quote::quote(a),
    }
}

pub fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

pub(crate) const SHARED_HEAVY_SCENE: &str =
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
    let corners: Vec<[Vec3; 3]> = scene.mesh.triangles.iter().map(|t| scene.mesh.corners(t)).collect();
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
    // The same rays as one stream: several walks side by side, each fetching its next node while
    // the others step (`Scene::intersect_stream`); the same hits, checked here.
    let streamed: Vec<(Vec3, Vec3, f32)> = incoherent.iter().map(|&(o, d)| (o, d, f32::INFINITY)).collect();
    let stream_hits = std::cell::RefCell::new(vec![None; streamed.len()]);
    let stream = || {
        let mut hits = stream_hits.borrow_mut();
        scene.intersect_stream(&streamed, &mut hits);
        hits.iter().filter(|h| h.is_some()).count()
    };
    stream();
    let alone = incoherent.iter().map(|&(o, d)| key(scene.intersect(o, d, f32::INFINITY)));
    anyhow::ensure!(
        alone.eq(stream_hits.borrow().iter().map(|&h| key(h))),
        "the stream and single rays found different hits (a traversal bug)"
    );
    report("incoherent", incoherent.len(), &|| one_by_one(&incoherent));
    report("incoherent, streamed", incoherent.len(), &stream);
    println!(
        "(render traces camera rays in packets: a pixel's samples, or neighbouring pixels; bounces one by one; \
         streams only in this bench so far)"
    );
    let tracers: [(&str, &dyn Fn() -> usize); 2] = [("one by one", &|| one_by_one(&incoherent)), ("streamed", &stream)];
    against_embree(&args.python, scene, &corners, &incoherent, &tracers, repeat)
}

/// Embree 4's closest-hit throughput on the same incoherent rays and triangles, one thread, timed
/// alternately with Tessera's ways of tracing `rays` (`tracers`: a name and a function that
/// traces them); and how often the two name the same triangle.
fn against_embree(
    python: &std::path::Path,
    scene: &Scene,
    corners: &[[Vec3; 3]],
    rays: &[(Vec3, Vec3)],
    tracers: &[(&str, &dyn Fn() -> usize)],
    repeat: usize,
) -> Result<()> {
    let (mut peers, version) = match crate::peers::Peers::with(python, "embreex") {
        Ok(p) => p,
        Err(why) => {
            println!("embree      skipped: {why}\n            to install: {}", crate::peers::INSTALL);
            return Ok(());
        }
    };
    let (triangles, ray_file, hits_file) = (peers.scratch("triangles"), peers.scratch("rays"), peers.scratch("hits"));
    crate::peers::write_f32(&triangles, corners.iter().flatten().flat_map(|v| v.to_array()))?;
    crate::peers::write_f32(&ray_file, rays.iter().flat_map(|(o, d)| o.to_array().into_iter().chain(d.to_array())))?;
    let loaded = peers.request(serde_json::json!({"op": "embree_load", "triangles": triangles, "rays": ray_file}))?;
    println!(
        "embree      embreex {version} (Embree 4, its single-ray rtcIntersect1 through Cython), build {:.3} s",
        loaded["build_s"].as_f64().unwrap_or(f64::NAN)
    );
    let ours: Vec<Option<u32>> =
        rays.iter().map(|&(o, d)| scene.intersect(o, d, f32::INFINITY).map(|h| h.triangle)).collect();
    let mut trace = |hits: Option<&std::path::Path>| -> Result<f64> {
        let answer = peers.request(serde_json::json!({"op": "embree_trace", "hits": hits}))?;
        answer["seconds"].as_f64().context("embree_trace: no seconds")
    };
    trace(Some(&hits_file))?;
    let theirs = crate::peers::read_words(&hits_file)?;
    anyhow::ensure!(theirs.len() == rays.len(), "embree answered {} rays of {}", theirs.len(), rays.len());
    let same = ours.iter().zip(&theirs).filter(|(a, b)| a.map_or(-1, |t| t as i32) == i32::from_le_bytes(**b)).count();
    let (mut tessera, mut embree) = (vec![Vec::new(); tracers.len()], Vec::new());
    for _ in 0..repeat {
        for ((_, trace_tessera), times) in tracers.iter().zip(&mut tessera) {
            times.push(time(|| {
                std::hint::black_box(trace_tessera());
            }));
        }
        embree.push(trace(None)?);
    }
    let embree = median(embree);
    let rate = |secs: f64| rays.len() as f64 / secs / 1e6;
    println!(
        "incoherent, alternating, one thread each (median of {repeat}): Embree {:.2} Mrays/s (single rays)",
        rate(embree)
    );
    for ((name, _), times) in tracers.iter().zip(tessera) {
        let secs = median(times);
        println!("            Tessera {name}: {:.2} Mrays/s, {:.2}x Embree's rate", rate(secs), embree / secs);
    }
    println!(
        "            the same triangle (or both a miss) for {:.3} % of the rays",
        100.0 * same as f64 / rays.len().max(1) as f64
    );
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
    // RGB, as Mitsuba's rgb variant (`bench spectral` compares transports).
    options.color = Some(tessera_local::options::ColorArg::Rgb);
    let (mut settings, _) = options.settings(scene)?;
    settings.sampler = sampler;
    Ok(settings)
}

/// Mitsuba's Cornell box (see [`crate::bench::peers::MITSUBA_BOX`]), loaded as `tessera render`
/// loads a file.
pub(crate) fn mitsuba_box() -> Result<tessera_scene::LoadedScene> {
    let dir = tempfile::tempdir()?;
    let path = dir.path().join("mitsuba-cbox.gltf");
    std::fs::write(&path, crate::bench::peers::MITSUBA_BOX)?;
    load_scene(path.to_str().context("temporary path")?, &default_options())
}

fn cornell(args: CornellArgs) -> Result<()> {
    let loaded = mitsuba_box()?;
    let scene = &loaded.scene;
    let settings = cornell_settings(scene, &args, 1, SamplerKind::Sobol, true)?;
    println!(
        "Mitsuba 3's Cornell box (its numbers, as glTF) {0}x{0}, mis, sobol, {1:?}",
        args.size, settings.termination
    );
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
    let settings = |seed, sampler, roulette| cornell_settings(scene, &args, seed, sampler, roulette);
    let comparison = crate::bench::peers::Comparison {
        scene,
        label: "mitsuba-cbox.gltf (compiled into the bench)".into(),
        settings: &settings,
        mitsuba: serde_json::json!({"kind": "cornell", "max_depth": args.max_bounces + 1, "rr_depth": args.rr_from}),
        threads: 2,
        target_rmse: args.target_rmse,
        max_spp: args.max_spp,
        pass_spp: args.spp,
        repeat: args.repeat,
        reference: args.reference.clone(),
        reference_spp: args.reference_spp,
        own_references: false,
    };
    anyhow::ensure!(args.size == 256, "Mitsuba's box is 256 x 256: use --size 256");
    crate::bench::peers::compare_with_mitsuba(&comparison, &args.python)
}
