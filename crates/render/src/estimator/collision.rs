//! Dimov, Gurov and Penzov's collision estimator (eq. 5): a random walk `x0 -> x1 -> ...` that scores `Le` at
//! every collision with weights `W_j = W_{j-1} K(x_j) / p(x_j)`, `K = f_r cos`. The transition
//! density is uniform, cosine, or proportional to `K` (BRDF sampling, Dimov, Gurov and Penzov's eq. 8).

use super::{CameraRay, PathResult, past_wall, same_side, survives_roulette};
use crate::channels::{Channels, ColorModel};
use crate::math::through_surface;
use crate::sampler::PixelSampler;
use crate::sampling::{sample_cosine_hemisphere, sample_uniform_hemisphere};
use crate::scene::Scene;
use crate::settings::{Density, RenderSettings};
use glam::Vec3;
use std::f32::consts::PI;

pub fn radiance<M: ColorModel>(
    scene: &Scene,
    settings: &RenderSettings,
    ray: &CameraRay,
    sampler: &PixelSampler,
    model: &M,
) -> PathResult<M::C> {
    let (mut o, mut d) = (ray.o, ray.d);
    let mut l = M::C::ZERO;
    let mut w = M::C::ONE;
    let mut saw_emitter = false;
    let max = settings.max_bounces();
    // Smooth thin walls are passed without counting a bounce, as the other estimators do (see
    // `nee::trace`); `vertex` counts them too, for the sampler's dimensions.
    let (mut bounce, mut vertex, mut walls) = (0, 0, 0);
    loop {
        let hit = if vertex == 0 { ray.hit } else { scene.intersect(o, d, f32::INFINITY) };
        let Some(hit) = hit else {
            let env = scene.lights.environment_radiance(d);
            saw_emitter |= bounce == 0 && env.max_element() > 0.0;
            l += w * model.illuminant(env);
            break;
        };
        let sp = scene.surface(hit, o, d);
        if let Some(absorbed) = scene.absorption(&sp, hit.t, model) {
            w *= absorbed;
        }
        let le = scene.emission(&sp, model);
        saw_emitter |= bounce == 0 && le.max_element() > 0.0;
        l += w * le;
        let last = bounce == max;
        if last && !scene.may_pass(&sp) {
            break;
        }
        let u = sampler.bounce(vertex);
        vertex += 1;
        let bsdf = scene.bsdf(&sp, model, settings.energy_compensation);
        let wo = sp.frame.to_local(-d);
        // The non-optimal densities cover the hemisphere above; for a surface that transmits, the
        // one below too, each chosen with probability 1/2 (`u[3]`, the lobe choice of BRDF sampling).
        let (sides, below) = if bsdf.transmits() { (2.0, u[3] < 0.5) } else { (1.0, false) };
        let flip = |w: Vec3| if below { through_surface(w) } else { w };
        let (local, weight) = match settings.density {
            Density::Uniform => {
                let wi = flip(sample_uniform_hemisphere([u[4], u[5]]));
                (wi, bsdf.eval(wo, wi) * wi.z.abs() * (2.0 * PI * sides))
            }
            Density::Cosine => {
                let wi = flip(sample_cosine_hemisphere([u[4], u[5]]));
                // f cos / (cos / pi); guard the horizon where both vanish.
                let weight = if wi.z != 0.0 { bsdf.eval(wo, wi) * (PI * sides) } else { M::C::ZERO };
                (wi, weight)
            }
            Density::Brdf => match bsdf.sample(wo, u[3], [u[4], u[5]]) {
                Some(s) if s.passes_through() => {
                    let Some(next) = past_wall(scene, &sp, d, &mut walls) else {
                        break;
                    };
                    w *= s.weight;
                    o = next;
                    continue;
                }
                Some(s) => (s.wi, s.weight),
                None => break,
            },
        };
        if last {
            break;
        }
        let wi = sp.frame.to_world(local);
        if weight.max_element() <= 0.0 || !same_side(wi.dot(sp.ng), local.z) {
            break;
        }
        w *= weight;
        if !survives_roulette(settings, bounce, &mut w, u[6]) {
            break;
        }
        o = scene.offset_origin(&sp, wi);
        d = wi;
        bounce += 1;
        walls = 0;
    }
    PathResult { radiance: l, saw_emitter }
}
