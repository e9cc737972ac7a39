//! The wave's last stage: what each light sample brings through the Lambert lobe and the shadow
//! ray that decides whether it arrives; the lobe's cosine-weighted direction (its sines and
//! cosines eight at a time), the path's weight and next ray; and Russian roulette.

use super::intersect::Points;
use super::light::LightSamples;
use super::paths::{Paths, Rows};
use super::{Vertex, W, Wave, dot, max3, select};
use crate::estimator::nee::Combination;
use crate::estimator::{same_side, survives_roulette};
use crate::lanes::Lanes;
use crate::sampler::DIMS_PER_BOUNCE;
use crate::sampling::power_heuristic;
use crate::scene::Scene;
use crate::settings::RenderSettings;
use crate::sums::TileSums;
use std::f32::consts::FRAC_1_PI;

impl Wave {
    /// Adds the light samples that arrive, and sends each path that goes on along its lobe's
    /// sampled direction (or ends it).
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    pub(super) fn scatter(
        &self,
        lanes: Lanes,
        scene: &Scene,
        settings: &RenderSettings,
        sp: &Points,
        vertex: &Vertex,
        light: &LightSamples,
        u: &[[f32; W]; DIMS_PER_BOUNCE],
        paths: &mut Paths,
        sums: &mut TileSums,
    ) {
        let (on, diffuse) = (vertex.on, &vertex.diffuse);
        let LightSamples {
            lit,
            wi: light_wi,
            li: light_li,
            distance: light_distance,
            pdf: light_pdf,
            delta: light_delta,
        } = light;
        // What each light sample brings through the Lambert lobe (`Bsdf::eval` and `pdf` cut
        // down to it), and the shadow ray that decides whether it arrives.
        let power = self.combination == Combination::PowerHeuristic;
        let epsilon = scene.ray_epsilon;
        let mut wo = Rows::default();
        let mut shadow = [false; W];
        let (mut brings, mut shadow_o) = (Rows::default(), Rows::default());
        let mut shadow_tmax = [0.0f32; W];
        for i in 0..W {
            let lane = |r: &Rows| [r.0[0][i], r.0[1][i], r.0[2][i]];
            let (s, t, n, ng, p) = (lane(&sp.s), lane(&sp.t), lane(&sp.n), lane(&sp.ng), lane(&sp.p));
            let to_local = |v: [f32; 3]| [dot(v, s), dot(v, t), dot(v, n)];
            let o_local = to_local(lane(&paths.d).map(|x| -x));
            let lw = lane(light_wi);
            let wi = to_local(lw);
            let cos_geometric = dot(lw, ng);
            // Both above the surface, as `Bsdf::eval` and `pdf` ask it (a NaN counts as above).
            let below = (o_local[2] <= 0.0) | (wi[2] <= 0.0);
            let above = !below;
            let f = select(same_side(cos_geometric, wi[2]) & above, lane(diffuse).map(|x| x * FRAC_1_PI), [0.0; 3]);
            shadow[i] = lit[i] & (max3(f) > 0.0);
            let bsdf_pdf = if above { wi[2] * FRAC_1_PI } else { 0.0 };
            // The heuristic worked out in every lane, kept where it applies (a select, not a branch).
            let heuristic = power_heuristic(light_pdf[i], bsdf_pdf);
            let w = if light_delta[i] | !power { 1.0 } else { heuristic };
            let scale = w / light_pdf[i];
            let (beta, li) = (lane(&paths.beta), lane(light_li));
            // `beta * f * |wi.z| * li * through * (w / pdf)`, `through` one.
            let brought: [f32; 3] = std::array::from_fn(|k| beta[k] * f[k] * wi[2].abs() * li[k] * 1.0 * scale);
            // `Scene::visible`: from just off the surface, stopping short of the light.
            let side = if cos_geometric >= 0.0 { 1.0 } else { -1.0 };
            let origin: [f32; 3] = std::array::from_fn(|k| p[k] + ng[k] * (side * epsilon));
            shadow_tmax[i] = light_distance[i] - 2.0 * epsilon;
            for k in 0..3 {
                wo.0[k][i] = o_local[k];
                brings.0[k][i] = brought[k];
                shadow_o.0[k][i] = origin[k];
            }
        }
        let mut angle = [0.0f32; W];
        for i in 0..W {
            // Shadow rays one by one: most lanes have one, but eight at once cost more than the
            // one-ray test, which stops at the first triangle in the way (callgrind, Mitsuba's
            // box: 401 M instructions against 423 M).
            if shadow[i] {
                let tmax = shadow_tmax[i];
                if tmax <= 0.0 || !scene.occluded_inline(shadow_o.get(i), light_wi.get(i), tmax) {
                    paths.l.set(i, paths.l.get(i) + brings.get(i));
                }
            }
            // The cosine-weighted direction's turn about the normal (`sample_cosine_hemisphere`).
            angle[i] = 2.0 * std::f32::consts::PI * u[5][i];
        }
        let (sin, cos) = crate::math::sincos_lanes(lanes, angle, on);
        // The Lambert lobe's sample (`Bsdf::sample`), the path's weight and its next ray.
        let mut goes_on = [false; W];
        for i in 0..W {
            let lane = |r: &Rows| [r.0[0][i], r.0[1][i], r.0[2][i]];
            let (s, t, n, ng, p) = (lane(&sp.s), lane(&sp.t), lane(&sp.n), lane(&sp.ng), lane(&sp.p));
            let o_local = lane(&wo);
            let r = u[4][i].sqrt();
            let z = (1.0 - u[4][i]).max(0.0).sqrt();
            let (x, y) = (r * cos[i], r * sin[i]);
            let pdf = if z <= 0.0 { 0.0 } else { z * FRAC_1_PI };
            let grazing = o_local[2] <= 0.0;
            let sampled = !grazing & (pdf > 0.0) & pdf.is_finite();
            let e = if grazing | (z <= 0.0) { 0.0 } else { FRAC_1_PI };
            let f = lane(diffuse).map(|c| c * e);
            let weight = f.map(|c| c * z.abs() / pdf);
            // `Frame::to_world`.
            let world: [f32; 3] = std::array::from_fn(|k| s[k] * x + t[k] * y + n[k] * z);
            let cos_geometric = dot(world, ng);
            let on = on[i] & sampled & same_side(cos_geometric, z);
            goes_on[i] = on;
            let beta = lane(&paths.beta);
            let side = if cos_geometric >= 0.0 { 1.0 } else { -1.0 };
            for k in 0..3 {
                let keep = |new: f32, old: f32| if on { new } else { old };
                paths.beta.0[k][i] = keep(beta[k] * weight[k], beta[k]);
                paths.prev_p.0[k][i] = keep(p[k], paths.prev_p.0[k][i]);
                paths.prev_n.0[k][i] = keep(ng[k], paths.prev_n.0[k][i]);
                paths.o.0[k][i] = keep(p[k] + ng[k] * (side * epsilon), paths.o.0[k][i]);
                paths.d.0[k][i] = keep(world[k], paths.d.0[k][i]);
            }
            paths.prev_pdf[i] = if on { pdf } else { paths.prev_pdf[i] };
            paths.prev_delta[i] &= !on;
        }
        for i in 0..W {
            if !on[i] {
                continue;
            }
            let mut beta = paths.beta.get(i);
            if goes_on[i] && survives_roulette(settings, paths.bounce[i], &mut beta, u[6][i]) {
                paths.beta.set(i, beta);
                paths.bounce[i] += 1;
            } else {
                paths.finish(i, sums);
            }
        }
    }
}
