//! `tessera bench stages`: what each stage of a path costs alone on Mitsuba's Cornell box (the
//! box `bench cornell` renders), so that a change to one stage can be weighed against the others
//! and a wide (many paths at once) version of a stage against the one-at-a-time one.

use anyhow::{Result, bail};
use std::hint::black_box;
use std::time::Instant;
use tessera_render::glam::Vec3;
use tessera_render::{Bvh, Hit, Lanes, PixelSampler, RayTest, SamplerKind, mix64, sample_cosine_hemisphere};

/// The most hits a run may ask for (about 40 bytes each).
const MAX_RAYS: usize = 10_000_000;

#[derive(clap::Args, Debug)]
pub struct StagesBenchArgs {
    /// Hits each stage is timed on: rays from random points inside the box in random directions.
    #[arg(long, default_value_t = 200_000, env = "TESSERA_BENCH_RAYS")]
    pub rays: usize,
    /// Rounds; each stage reports its fastest (a busy machine only ever adds time).
    #[arg(long, default_value_t = 5, env = "TESSERA_BENCH_REPEAT")]
    pub repeat: usize,
    /// Scene whose camera samples are timed stage by stage [default: WaterBottle from
    /// ../shared/scenes when present, else Mitsuba's Cornell box]
    #[arg(long, env = "TESSERA_BENCH_SCENE")]
    pub scene: Option<String>,
    /// Image side in pixels for the camera samples
    #[arg(long, default_value_t = 256, env = "TESSERA_BENCH_SIZE")]
    pub size: u32,
    /// Samples per pixel for the camera samples
    #[arg(long, default_value_t = 4, env = "TESSERA_BENCH_SPP")]
    pub spp: u32,
    /// Constant environment radiance lighting the scene (as `bench mitsuba`)
    #[arg(long, default_value_t = 1.0, env = "TESSERA_BENCH_ENV")]
    pub env: f32,
}

/// The real asset whose camera samples the bench times when it is there.
const SHARED_CAMERA_SCENE: &str = "../shared/scenes/WaterBottle/glTF/WaterBottle.gltf";

pub fn stages(args: StagesBenchArgs) -> Result<()> {
    if args.rays == 0 || args.rays > MAX_RAYS {
        bail!("--rays {} is out of range: 1 to {MAX_RAYS}", args.rays);
    }
    let samples = args.size as u64 * args.size as u64 * args.spp as u64;
    if !(1..=4096).contains(&args.size) || !(1..=1024).contains(&args.spp) || samples > 1 << 24 {
        bail!("--size {} --spp {}: at most 4096 a side, 1024 spp and 2^24 samples in all", args.size, args.spp);
    }
    let loaded = crate::bench::mitsuba_box()?;
    let scene = &loaded.scene;
    let (lo, hi) = scene.bounds;
    let center = (lo + hi) * 0.5;
    // Uniform numbers in [0, 1) from the renderer's own mixer (as `bench rays` draws its bounces).
    let mut count = 0u64;
    let mut uniform = || {
        count += 1;
        (mix64(count) >> 40) as f32 / (1u64 << 24) as f32
    };
    let mut hits: Vec<(Vec3, Vec3, Hit)> = Vec::with_capacity(args.rays);
    for _ in 0..args.rays.saturating_mul(4) {
        if hits.len() == args.rays {
            break;
        }
        let o = center + (Vec3::new(uniform(), uniform(), uniform()) - 0.5) * (hi - lo) * 0.8;
        let Some(d) = (Vec3::new(uniform(), uniform(), uniform()) - 0.5).try_normalize() else {
            continue;
        };
        if let Some(hit) = scene.intersect(o, d, f32::INFINITY) {
            hits.push((o, d, hit));
        }
    }
    if hits.len() < args.rays {
        bail!("only {} of {} rays from inside the box hit it", hits.len(), args.rays);
    }
    // A point just under the middle of the ceiling, where the light is: every shadow ray's target.
    let light = Vec3::new(center.x, hi.y - 1e-3 * (hi.y - lo.y), center.z);
    let n = hits.len() as f64;
    let time = |f: &dyn Fn()| {
        (0..args.repeat.max(1))
            .map(|_| {
                let t = Instant::now();
                f();
                t.elapsed().as_secs_f64() / n * 1e9
            })
            .fold(f64::INFINITY, f64::min)
    };
    println!(
        "Mitsuba's Cornell box, {} hits of rays from inside it, one thread, ns per call (fastest of {} rounds);",
        hits.len(),
        args.repeat.max(1)
    );
    println!("rays meet its {} triangles {}:", scene.mesh.triangles.len(), scene.bvh.ray_test());
    let row = |what: &str, ns: f64| println!("  {what:<58} {ns:>7.1}");
    row("closest hit", time(&closest_hits(&hits, |o, d| scene.intersect(o, d, f32::INFINITY).map_or(0.0, |h| h.t))));
    // Each call's input waits for the previous call's output (`x * 0` is zero but must be
    // computed): as long as the independent calls, the calls do not overlap one another.
    row(
        "closest hit, each waiting for the one before",
        time(&|| {
            let mut prev = 0.0f32;
            for &(o, d, _) in &hits {
                prev = scene.intersect(o + Vec3::splat(prev * 0.0), d, f32::INFINITY).map_or(0.0, |h| h.t);
            }
            black_box(prev);
        }),
    );
    row("shadow ray (towards the light)", time(&shadow_rays(&hits, light, |o, d, tmax| scene.occluded(o, d, tmax))));
    // The other ways rays could meet the box's triangles, on the same rays.
    let corners: Vec<[Vec3; 3]> = scene.mesh.triangles.iter().map(|t| scene.mesh.corners(t)).collect();
    let tests = std::iter::once(RayTest::Walk).chain(Lanes::ALL.map(RayTest::Whole));
    for test in tests.filter(|&test| test != scene.bvh.ray_test()) {
        let Some((bvh, _)) = Bvh::build_testing(&corners, test) else { continue };
        let distance = |o, d| bvh.closest_hit(o, d, f32::INFINITY, |_, _| true).map_or(0.0, |h| h.1);
        row(&format!("closest hit, {test}"), time(&closest_hits(&hits, distance)));
        let blocked = |o, d, tmax| bvh.occluded(o, d, tmax, |_, _| true);
        row(&format!("shadow ray, {test}"), time(&shadow_rays(&hits, light, blocked)));
    }
    row(
        "surface point",
        time(&|| {
            let x: f32 = hits.iter().map(|&(o, d, h)| scene.surface(h, o, d).p.x).sum();
            black_box(x);
        }),
    );
    row(
        "surface point, each waiting for the one before",
        time(&|| {
            let mut prev = 0.0f32;
            for &(o, d, mut h) in &hits {
                h.t += prev * 0.0;
                prev = scene.surface(h, o, d).p.x;
            }
            black_box(prev);
        }),
    );
    row(
        "sampler: a pixel's seeds and one bounce's numbers",
        time(&|| {
            let x: f32 = (0..hits.len() as u32)
                .map(|i| PixelSampler::new(SamplerKind::Sobol, 1, (i & 255, i >> 8), 7).bounce(1)[4])
                .sum();
            black_box(x);
        }),
    );
    row(
        "cosine-weighted direction",
        time(&|| {
            let v: Vec3 =
                hits.iter().map(|&(o, _, _)| sample_cosine_hemisphere([o.x.fract().abs(), o.y.fract().abs()])).sum();
            black_box(v);
        }),
    );
    camera_samples(&args)
}

/// The camera-sample stages of `--scene` (see `camera_stages`).
fn camera_samples(args: &StagesBenchArgs) -> Result<()> {
    let env = format!("{0},{0},{0}", args.env);
    let mut options = crate::bench::options_from(&["--env", &env, "--quality", "fixed"]);
    (options.width, options.height) = (args.size, args.size);
    let spec = match &args.scene {
        Some(spec) => Some(spec.as_str()),
        None => std::path::Path::new(SHARED_CAMERA_SCENE).is_file().then_some(SHARED_CAMERA_SCENE),
    };
    let loaded = match spec {
        Some(spec) => tessera_local::load_scene(spec, &options)?,
        None => crate::bench::mitsuba_box()?,
    };
    let (settings, _) = options.settings(&loaded.scene)?;
    println!();
    println!("{}, constant environment {}:", spec.unwrap_or("Mitsuba's Cornell box"), args.env);
    crate::bench::camera_stages::camera_stages(&loaded.scene, &settings, args.spp, args.repeat)
}

/// A round of closest hits: `distance(o, d)` for every hit's ray (generic, so that the call
/// inlines into the loop as a direct call would).
fn closest_hits(hits: &[(Vec3, Vec3, Hit)], distance: impl Fn(Vec3, Vec3) -> f32) -> impl Fn() {
    move || {
        black_box(hits.iter().map(|&(o, d, _)| distance(o, d)).sum::<f32>());
    }
}

/// A round of shadow rays: `blocked(o, direction, tmax)` from every hit's origin towards `light`,
/// stopping just short of it.
fn shadow_rays(hits: &[(Vec3, Vec3, Hit)], light: Vec3, blocked: impl Fn(Vec3, Vec3, f32) -> bool) -> impl Fn() {
    move || {
        let count = hits
            .iter()
            .filter(|&&(o, _, _)| {
                let to = light - o;
                blocked(o, to.normalize(), to.length() * 0.999)
            })
            .count();
        black_box(count);
    }
}
