//! Next-event estimation: at every vertex one light sample (shadow ray), and a BSDF-sampled
//! continuation whose emitter hits count only after a perfect mirror. [`trace`] is shared with
//! the MIS estimator, which weights both strategies instead of choosing one.

use super::{CameraRay, PathResult, past_wall, same_side, survives_roulette};
use crate::channels::{Channels, ColorModel};
use crate::sampler::PixelSampler;
use crate::sampling::power_heuristic;
use crate::scene::Scene;
use crate::settings::RenderSettings;

pub fn radiance<M: ColorModel>(
    scene: &Scene,
    settings: &RenderSettings,
    ray: &CameraRay,
    sampler: &PixelSampler,
    model: &M,
) -> PathResult<M::C> {
    trace(scene, settings, ray, sampler, Combination::LightOnly, model)
}

/// How light-sampled and BSDF-sampled emission are combined.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Combination {
    /// Emission reached by BSDF sampling counts only after a delta (mirror) bounce.
    LightOnly,
    /// Both strategies count, weighted by the power heuristic.
    PowerHeuristic,
}

impl Combination {
    /// Weight of the strategy with density `p_this` against the other with density `p_other()`
    /// (worked out only where it matters).
    pub(crate) fn weight(self, p_this: f32, p_other: impl FnOnce() -> f32, this_is_light: bool) -> f32 {
        match self {
            Combination::LightOnly => this_is_light as u32 as f32,
            Combination::PowerHeuristic => power_heuristic(p_this, p_other()),
        }
    }
}

pub fn trace<M: ColorModel>(
    scene: &Scene,
    settings: &RenderSettings,
    ray: &CameraRay,
    sampler: &PixelSampler,
    combination: Combination,
    model: &M,
) -> PathResult<M::C> {
    let lights = &scene.lights;
    let (mut o, mut d) = (ray.o, ray.d);
    let mut l = M::C::ZERO;
    let mut beta = M::C::ONE;
    let mut saw_emitter = false;
    // The previous vertex: its BSDF pdf for the current direction, and whether it was a mirror.
    let mut prev_pdf = 0.0;
    let mut prev_delta = true;
    let mut prev_p = ray.o;
    let mut prev_n = glam::Vec3::Z;
    let max = settings.max_bounces();
    // Walls passed straight through are not bounces: they keep the previous vertex's state for
    // MIS, as light sampling from that vertex passes them too. `vertex` counts them as well, for
    // the sampler's dimensions; `walls` counts those passed since the last bounce.
    let (mut bounce, mut vertex, mut walls) = (0, 0, 0);
    loop {
        let hit = if vertex == 0 { ray.hit } else { scene.intersect(o, d, f32::INFINITY) };
        let Some(hit) = hit else {
            let le = lights.environment_radiance(d);
            if le.max_element() > 0.0 {
                saw_emitter |= bounce == 0;
                let w = if prev_delta {
                    1.0
                } else {
                    combination.weight(prev_pdf, || lights.environment_pdf(d, settings.lights), false)
                };
                l += beta * model.illuminant(le) * w;
            }
            break;
        };
        let sp = scene.surface(hit, o, d);
        if let Some(absorbed) = scene.absorption(&sp, hit.t, model) {
            beta *= absorbed;
        }
        let le = scene.emission(&sp, model);
        if le.max_element() > 0.0 {
            saw_emitter |= bounce == 0;
            let w = if prev_delta {
                1.0
            } else {
                combination.weight(prev_pdf, || lights.triangle_pdf(prev_p, prev_n, &sp, settings.lights), false)
            };
            l += beta * le * w;
        }
        // The last bounce still passes walls: light sampling from the vertex before saw through them.
        let last = bounce == max;
        if last && !scene.may_pass(&sp) {
            break;
        }
        let u = sampler.bounce(vertex);
        vertex += 1;
        let bsdf = scene.bsdf(&sp, model, settings.energy_compensation);
        let wo = sp.frame.to_local(-d);
        // f, its density and a sample at the same `wo`: what they share is worked out once.
        let at = bsdf.at(wo);
        if !last
            && bsdf.has_smooth_part()
            && let Some(ls) =
                lights.sample(&scene.mesh, &scene.surfaces, &sp, [u[0], u[1], u[2]], settings.lights, model)
            && (ls.wi.dot(sp.ng) > 0.0 || bsdf.transmits())
        {
            let wi = sp.frame.to_local(ls.wi);
            let f = if same_side(ls.wi.dot(sp.ng), wi.z) { at.eval(wi) } else { M::C::ZERO };
            if f.max_element() > 0.0
                && let Some(through) = scene.transmittance(&sp, ls.wi, ls.distance, model)
            {
                let w = if ls.delta { 1.0 } else { combination.weight(ls.pdf, || at.pdf(wi), true) };
                l += beta * f * wi.z.abs() * ls.li * through * (w / ls.pdf);
            }
        }
        let Some(s) = at.sample(u[3], [u[4], u[5]]) else {
            break;
        };
        if s.passes_through() {
            let Some(next) = past_wall(scene, &sp, d, &mut walls) else {
                break;
            };
            beta *= s.weight;
            o = next;
            continue;
        }
        if last {
            break;
        }
        let wi = sp.frame.to_world(s.wi);
        if !same_side(wi.dot(sp.ng), s.wi.z) {
            break;
        }
        beta *= s.weight;
        prev_pdf = s.pdf;
        prev_delta = s.delta;
        prev_p = sp.p;
        prev_n = sp.ng;
        if !survives_roulette(settings, bounce, &mut beta, u[6]) {
            break;
        }
        o = scene.offset_origin(&sp, wi);
        d = wi;
        bounce += 1;
        walls = 0;
    }
    PathResult { radiance: l, saw_emitter }
}
