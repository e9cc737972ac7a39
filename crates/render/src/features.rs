//! The feature layers a denoiser reads beside the colour (Open Image Denoise's `albedo` and
//! `normal`): per sample, the albedo and the shading normal of the first diffuse or glossy
//! surface the camera ray's path meets. Perfect mirrors, smooth glass and smooth thin walls are
//! followed to it, as OIDN's documentation recommends, so that reflections and what lies behind
//! glass keep their edges. Each sample takes the camera ray of the colour's own sample, so the
//! layers are averaged over the same samples and filter as the colour, and they are a pure
//! function of (seed, pixel, sample index) like it: any split merges to the same bits.
//!
//! A ray that leaves the scene gives normal 0 (OIDN's "no surface") and albedo 1, so that the
//! colour over the albedo is the background itself.

use crate::camera::Camera;
use crate::channels::Rgb;
use crate::interaction::Hit;
use crate::scene::Scene;
use crate::settings::RenderSettings;
use crate::sums::{FeatureSums, TileSums};
use glam::Vec3;
use std::ops::Range;

/// Perfectly specular vertices followed before a path's features are taken where it is.
const MAX_SPECULAR: u32 = 8;

/// Sums the features of samples `samples` of every pixel of `sums`' tile into `sums.features`.
pub(crate) fn add_features(
    scene: &Scene,
    settings: &RenderSettings,
    camera: &Camera,
    sums: &mut TileSums,
    samples: Range<u32>,
) {
    let mut features = vec![FeatureSums::default(); sums.tile.pixel_count()];
    crate::tile::camera_rays(scene, settings, camera, sums.tile, samples, |pixel, sampler, _, ray| {
        let (albedo, normal) =
            first_diffuse_hit(scene, settings, ray.o, ray.d, ray.hit, |vertex| sampler.bounce(vertex));
        features[pixel].add(albedo, normal);
    });
    sums.features = features;
}

/// The albedo and normal where the path from `o` along `d` (whose first hit is `first`) first
/// meets a surface that is not perfectly specular; `u(vertex)` gives the vertex's sampler
/// dimensions, which choose between a smooth dielectric's reflection and refraction as the
/// colour's paths do.
fn first_diffuse_hit(
    scene: &Scene,
    settings: &RenderSettings,
    mut o: Vec3,
    mut d: Vec3,
    first: Option<Hit>,
    u: impl Fn(u32) -> [f32; crate::sampler::DIMS_PER_BOUNCE],
) -> (Vec3, Vec3) {
    for vertex in 0..=MAX_SPECULAR {
        let hit = if vertex == 0 { first } else { scene.intersect(o, d, f32::INFINITY) };
        let Some(hit) = hit else {
            return (Vec3::ONE, Vec3::ZERO);
        };
        let sp = scene.surface(hit, o, d);
        let bsdf = scene.bsdf(&sp, &Rgb, settings.energy_compensation);
        if vertex == MAX_SPECULAR || bsdf.has_smooth_part() {
            return (bsdf.albedo_hint(), sp.frame.n);
        }
        let u = u(vertex);
        let Some(s) = bsdf.sample(sp.frame.to_local(-d), u[3], [u[4], u[5]]) else {
            return (bsdf.albedo_hint(), sp.frame.n);
        };
        if !s.passes_through() {
            d = sp.frame.to_world(s.wi);
        }
        o = scene.offset_origin(&sp, d);
    }
    unreachable!("the loop returns at its last vertex")
}
