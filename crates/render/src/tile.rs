//! `render_tile`: the unit of work of the farm and of the local renderer.

use crate::accel::PACKET;
use crate::camera::Camera;
use crate::channels::{ColorModel, Rgb};
use crate::estimator::{self, CameraRay};
use crate::lanes::Lanes;
use crate::sampler::{self, PixelSampler, PixelSeeds};
use crate::scene::Scene;
use crate::settings::{ColorMode, RenderSettings};
use crate::spectral::hero::Hero;
use crate::sums::{Tile, TileSums};
use glam::{Vec2, Vec3};
use std::ops::Range;

#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    #[error("camera {index} does not exist (the scene has {count})")]
    NoSuchCamera { index: usize, count: usize },
    #[error("tile {x0},{y0} {width}x{height} lies outside the {image_width}x{image_height} image")]
    TileOutside { x0: u32, y0: u32, width: u32, height: u32, image_width: u32, image_height: u32 },
}

/// Renders samples `samples` of every pixel of `tile`. Each sample is a pure function of
/// (seed, pixel, sample index), so results for disjoint ranges merge to the bits of the whole.
pub fn render_tile(
    scene: &Scene,
    settings: &RenderSettings,
    tile: Tile,
    samples: Range<u32>,
) -> Result<TileSums, RenderError> {
    let camera = scene
        .cameras
        .get(settings.camera)
        .ok_or(RenderError::NoSuchCamera { index: settings.camera, count: scene.cameras.len() })?;
    if !tile.fits(settings.width, settings.height) {
        return Err(RenderError::TileOutside {
            x0: tile.x0,
            y0: tile.y0,
            width: tile.width,
            height: tile.height,
            image_width: settings.width,
            image_height: settings.height,
        });
    }
    let mut sums = if let Some(wave) = crate::estimator::wave::Wave::for_render(scene, settings) {
        wave.render(scene, settings, camera, tile, samples.clone())
    } else {
        match settings.color {
            ColorMode::Rgb => render_pixels(scene, settings, camera, tile, samples.clone(), |_| Rgb),
            // The wavelengths take the camera set's third dimension: stratified with the pixel position.
            ColorMode::Spectral => render_pixels(scene, settings, camera, tile, samples.clone(), |c| Hero::new(c[2])),
        }
    };
    if settings.features {
        crate::features::add_features(scene, settings, camera, &mut sums, samples);
    }
    Ok(sums)
}

/// The pixel loop, for the colour model that `model_for(camera sample)` makes for each path.
pub(crate) fn render_pixels<M: ColorModel>(
    scene: &Scene,
    settings: &RenderSettings,
    camera: &Camera,
    tile: Tile,
    samples: Range<u32>,
    model_for: impl Fn([f32; 4]) -> M,
) -> TileSums {
    let mut sums = TileSums::new(tile);
    camera_rays(scene, settings, camera, tile, samples, |pixel, sampler, c, ray| {
        // A transparent render leaves the background out: a camera ray that misses adds
        // nothing, and the pixel's coverage (its alpha) says how much of it is scene.
        if settings.transparent && ray.hit.is_none() {
            sums.pixels[pixel].add(Vec3::ZERO, false, false);
            return;
        }
        let model = model_for(c);
        let r = estimator::radiance(scene, settings, &ray, sampler, &model);
        sums.pixels[pixel].add(model.to_rgb(r.radiance), r.saw_emitter, ray.hit.is_some());
    });
    sums
}

/// Every camera sample of `samples` of each pixel of `tile`, traced to its first hit:
/// `each(pixel in the tile, sampler, camera dimensions, ray)`, in pixel and sample order. The
/// samples go in batches of [`PACKET`]: their camera numbers are worked out side by side
/// ([`sampler::camera_lanes`]) and their rays go to the BVH as a packet: a pixel's consecutive
/// samples, or neighbouring pixels when a pixel has fewer. Each lane gets the numbers and the hit
/// it gets alone, so the grouping does not change any bit of what `each` makes of them.
pub(crate) fn camera_rays(
    scene: &Scene,
    settings: &RenderSettings,
    camera: &Camera,
    tile: Tile,
    samples: Range<u32>,
    mut each: impl FnMut(usize, &PixelSampler, [f32; 4], CameraRay),
) {
    const _: () = assert!(PACKET == sampler::LANES, "a packet's samplers fill the sampler's lanes");
    let lanes = Lanes::widest();
    let film_rays = camera.film(settings.width, settings.height);
    // The batch: `n` samples, each with its pixel (in the tile, and in the image) and sampler.
    let mut n = 0;
    let mut pixel = [0usize; PACKET];
    let mut xy = [(0u32, 0u32); PACKET];
    let mut samplers = [PixelSampler::new(settings.sampler, settings.seed, (0, 0), 0); PACKET];
    let mut film = [Vec2::ZERO; PACKET];
    let mut rays = [(Vec3::ZERO, Vec3::Z, f32::INFINITY); PACKET];
    let mut flush =
        |n: usize, pixel: &[usize; PACKET], xy: &[(u32, u32); PACKET], samplers: &[PixelSampler; PACKET]| {
            // Lanes past `n` hold earlier samples again: worked out and traced, then left.
            let c = sampler::camera_lanes(lanes, samplers);
            for i in 0..PACKET {
                // Box filter: every sample stays inside its own pixel (Dimov, Gurov and Penzov, eq. 1).
                film[i] = Vec2::new(xy[i].0 as f32 + c[i][0], xy[i].1 as f32 + c[i][1]);
            }
            film_rays.rays(&film, &mut rays);
            let hits = scene.intersect_packet(&rays[..n]);
            for (i, (&(o, d, _), hit)) in rays[..n].iter().zip(hits).enumerate() {
                each(pixel[i], &samplers[i], c[i], CameraRay { o, d, hit });
            }
        };
    for py in 0..tile.height {
        for px in 0..tile.width {
            let (x, y) = (tile.x0 + px, tile.y0 + py);
            let mut seeds = PixelSeeds::new(settings.sampler, settings.seed, (x, y));
            for index in samples.clone() {
                (pixel[n], xy[n], samplers[n]) = ((py * tile.width + px) as usize, (x, y), seeds.sampler(index));
                n += 1;
                if n == PACKET {
                    flush(n, &pixel, &xy, &samplers);
                    n = 0;
                }
            }
        }
    }
    if n > 0 {
        flush(n, &pixel, &xy, &samplers);
    }
}
