//! `tessera bench stages --scene FILE`: what a camera sample costs before its path's first
//! bounce, stage by stage, on a real scene. On an asset seen small in its frame (WaterBottle:
//! three quarters of the camera rays miss it) these fixed costs are most of a pass, and each
//! stage is timed alone on the samples of one pass, in the tile loop's order.

use anyhow::Result;
use std::cell::RefCell;
use std::hint::black_box;
use std::time::Instant;
use tessera_render::estimator::{self, CameraRay};
use tessera_render::glam::{Vec2, Vec3};
use tessera_render::{
    Hit, Lanes, PACKET, PixelSampler, PixelSeeds, PixelSums, RenderSettings, Rgb, Scene, Tile, camera_lanes,
    render_tile,
};

/// The pixels of one of the farm's 32 x 32 tiles.
const TILE_PIXELS: usize = 32 * 32;

/// Times each stage of the camera samples `0..spp` of every pixel of a `settings.width` x
/// `settings.height` image, one thread, and prints ns per sample (per miss for the environment);
/// the fastest of `repeat` rounds.
pub(crate) fn camera_stages(scene: &Scene, settings: &RenderSettings, spp: u32, repeat: usize) -> Result<()> {
    let camera = scene.cameras.get(settings.camera).ok_or_else(|| anyhow::anyhow!("the scene has no camera"))?;
    let (width, height) = (settings.width, settings.height);
    let film_rays = camera.film(width, height);
    // The samples in the tile loop's order: a pixel's consecutive samples, pixel by pixel.
    let mut film = Vec::new();
    let mut pixel_of = Vec::new();
    for y in 0..height {
        for x in 0..width {
            let mut seeds = PixelSeeds::new(settings.sampler, settings.seed, (x, y));
            for index in 0..spp {
                let c = seeds.sampler(index).camera();
                film.push(Vec2::new(x as f32 + c[0], y as f32 + c[1]));
                pixel_of.push((y * width + x) as usize);
            }
        }
    }
    let n = film.len();
    let mut rays = vec![(Vec3::ZERO, Vec3::Z, f32::INFINITY); n.next_multiple_of(PACKET)];
    let packets = |film: &[Vec2], rays: &mut [(Vec3, Vec3, f32)]| {
        let mut chunk = [Vec2::ZERO; PACKET];
        for (f, r) in film.chunks(PACKET).zip(rays.chunks_exact_mut(PACKET)) {
            chunk[..f.len()].copy_from_slice(f);
            film_rays.rays(&chunk, r.try_into().expect("a packet"));
        }
    };
    packets(&film, &mut rays);
    rays.truncate(n);
    let hits: Vec<Option<Hit>> =
        rays.chunks(PACKET).flat_map(|p| scene.intersect_packet(p)[..p.len()].to_vec()).collect();
    let missed: Vec<(Vec3, Vec3, f32)> = rays.iter().zip(&hits).filter(|(_, h)| h.is_none()).map(|(r, _)| *r).collect();
    let struck: Vec<(Vec3, Vec3, f32)> = rays.iter().zip(&hits).filter(|(_, h)| h.is_some()).map(|(r, _)| *r).collect();
    let radiance: Vec<Vec3> = rays
        .iter()
        .zip(&hits)
        .map(|(r, h)| if h.is_none() { scene.lights.environment_radiance(r.1) } else { Vec3::splat(0.25) })
        .collect();

    // ns per item of the fastest round.
    let time = |items: usize, f: &dyn Fn()| {
        (0..repeat.max(1))
            .map(|_| {
                let t = Instant::now();
                f();
                t.elapsed().as_secs_f64() / items.max(1) as f64 * 1e9
            })
            .fold(f64::INFINITY, f64::min)
    };
    println!(
        "camera samples of a {width}x{height} image at {spp} spp ({n} samples, {:.0} % miss the scene), one thread, \
         ns per sample (fastest of {} rounds):",
        missed.len() as f64 / n as f64 * 100.0,
        repeat.max(1)
    );
    // The sums are allocated and touched once, outside the timed rounds.
    let sums = RefCell::new(vec![PixelSums::default(); TILE_PIXELS]);
    let row = |what: &str, ns: f64| println!("  {what:<58} {ns:>7.1}");
    let mut fixed = 0.0;
    let mut stage = |what: &str, ns: f64, share: f64| {
        row(what, ns);
        fixed += ns * share;
    };
    stage(
        "sampler: a pixel's seeds, each sample's camera numbers",
        // Eight samples' camera numbers side by side, as the tile loop works them out.
        time(n, &|| {
            let lanes = Lanes::widest();
            let mut samplers = [PixelSampler::new(settings.sampler, settings.seed, (0, 0), 0); PACKET];
            let (mut acc, mut k) = (0.0f32, 0);
            for y in 0..height {
                for x in 0..width {
                    let mut seeds = PixelSeeds::new(settings.sampler, settings.seed, (x, y));
                    for index in 0..spp {
                        samplers[k] = seeds.sampler(index);
                        k += 1;
                        if k == PACKET {
                            acc += camera_lanes(lanes, &samplers)[PACKET - 1][0];
                            k = 0;
                        }
                    }
                }
            }
            black_box(acc + camera_lanes(lanes, &samplers)[0][0]);
        }),
        1.0,
    );
    stage(
        "camera ray (packets of 8)",
        // Into one packet's buffer, as the tile loop makes them (it stays in the cache).
        time(n, &|| {
            let mut out = [(Vec3::ZERO, Vec3::Z, f32::INFINITY); PACKET];
            let mut x = 0.0;
            for f in film.chunks_exact(PACKET) {
                film_rays.rays(f.try_into().expect("a packet"), &mut out);
                x += out[PACKET - 1].1.x;
            }
            black_box(x);
        }),
        1.0,
    );
    let first_hits = |rays: &[(Vec3, Vec3, f32)]| {
        let found = rays.chunks(PACKET).map(|p| scene.intersect_packet(p).iter().flatten().count()).sum::<usize>();
        black_box(found);
    };
    stage("first hit (packets of 8)", time(n, &|| first_hits(&rays)), 1.0);
    let miss_ns = time(missed.len(), &|| first_hits(&missed));
    row("  of rays that all miss, per ray", miss_ns);
    let hit_ns = time(struck.len(), &|| first_hits(&struck));
    row("  of rays that all hit, per ray", hit_ns);
    let share = missed.len() as f64 / n as f64;
    stage(
        "environment radiance, per miss",
        time(missed.len(), &|| {
            let v: Vec3 = missed.iter().map(|r| scene.lights.environment_radiance(r.1)).sum();
            black_box(v);
        }),
        share,
    );
    stage(
        "a miss's path: the estimator's environment term",
        time(missed.len(), &|| {
            let sampler = PixelSampler::new(settings.sampler, settings.seed, (0, 0), 0);
            let v: Vec3 = missed
                .iter()
                .map(|&(o, d, _)| {
                    let ray = CameraRay { o, d, hit: None };
                    estimator::radiance(scene, settings, &ray, &sampler, &Rgb).radiance
                })
                .sum();
            black_box(v);
        }),
        share,
    );
    // Into one tile's worth of pixels, as the tile loop sums (its sums stay in the cache).
    stage(
        "exact sum of a sample",
        time(n, &|| {
            let mut sums = sums.borrow_mut();
            for ((&p, &v), h) in pixel_of.iter().zip(&radiance).zip(&hits) {
                sums[p % TILE_PIXELS].add(v, false, h.is_some());
            }
            black_box(&sums[0]);
        }),
        1.0,
    );
    row("the stages' sum, per sample (misses weighted by their share)", fixed);
    let tile = Tile { x0: 0, y0: 0, width, height };
    let whole = time(n, &|| drop(black_box(render_tile(scene, settings, tile, 0..spp))));
    row(&format!("whole samples ({:?}), per sample", settings.termination), whole);
    println!("  the camera sample's fixed stages are {:.0} % of a whole sample", fixed / whole * 100.0);
    Ok(())
}
