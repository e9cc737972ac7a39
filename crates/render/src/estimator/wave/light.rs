//! The wave's third stage: a light sample for each lane whose lobe light sampling reaches. Each
//! lane chooses its light (in the lanes with few lights chosen by power); a point on an emissive
//! triangle is placed in the lanes, on any other light by its own code.

use super::intersect::Points;
use super::paths::Rows;
use super::{Plain, Vertex, W, Wave, dot};
use crate::channels::Rgb;
use crate::light::Choice;
use crate::sampler::DIMS_PER_BOUNCE;
use crate::scene::Scene;
use crate::settings::{LightSampler, RenderSettings};

/// Each lane's light sample: whether it has one, its direction, radiance, distance and density,
/// and whether that density is a point's (a delta).
pub(super) struct LightSamples {
    pub(super) lit: [bool; W],
    pub(super) wi: Rows,
    pub(super) li: Rows,
    pub(super) distance: [f32; W],
    pub(super) pdf: [f32; W],
    pub(super) delta: [bool; W],
}

impl Wave {
    /// The light samples of the lanes `vertex` says go on with a smooth lobe; `u` their bounce's
    /// numbers.
    #[inline(always)]
    pub(super) fn light_sample(
        &self,
        scene: &Scene,
        settings: &RenderSettings,
        sp: &Points,
        vertex: &Vertex,
        u: &[[f32; W]; DIMS_PER_BOUNCE],
    ) -> LightSamples {
        let lights = &scene.lights;
        let (on, smooth) = (&vertex.on, &vertex.smooth);
        let mut lit = [false; W];
        let (mut light_wi, mut light_li) = (Rows::default(), Rows::default());
        let (mut light_distance, mut light_pdf) = ([0.0f32; W], [1.0f32; W]);
        let mut light_delta = [false; W];
        // Each lane chooses its light; a point on an emissive triangle is placed in the lanes
        // below, on any other light by its own code.
        let mut on_triangle = [false; W];
        let (mut corner, mut edge1, mut edge2, mut normal) =
            (Rows::default(), Rows::default(), Rows::default(), Rows::default());
        let (mut area, mut pmf, mut place) = ([1.0f32; W], [0.0f32; W], [[0.0f32; W]; 2]);
        let mut double_sided = [false; W];
        // With few lights chosen by power, the choices are made in the lanes.
        let chosen = match settings.lights {
            LightSampler::Power => lights.choose_lanes(&u[1]),
            LightSampler::Tree => None,
        };
        for i in 0..W {
            if !(on[i] && smooth[i]) {
                continue;
            }
            let (p, ng) = (sp.p.get(i), sp.ng.get(i));
            let (choice, probability, numbers) = match &chosen {
                Some((_, pmf, _)) if pmf[i] <= 0.0 => continue,
                Some((choice, pmf, rest)) => (choice[i], pmf[i], [u[0][i], rest[i], u[2][i]]),
                None => match lights.choose_from(p, ng, [u[0][i], u[1][i], u[2][i]], settings.lights) {
                    Some(chosen) => chosen,
                    None => continue,
                },
            };
            if let Choice::Triangle(e) = choice {
                let e = lights.emitter(e);
                on_triangle[i] = true;
                corner.set(i, e.a);
                edge1.set(i, e.e1);
                edge2.set(i, e.e2);
                normal.set(i, e.n);
                (area[i], pmf[i], double_sided[i]) = (e.area, probability, e.double_sided);
                (place[0][i], place[1][i]) = (numbers[1], numbers[2]);
                let Some(Plain { emission: Some(le), .. }) = self.materials[e.material as usize] else {
                    unreachable!("an emitter's material is used, so plain, and emissive")
                };
                light_li.set(i, le);
                continue;
            }
            let (mesh, surfaces) = (&scene.mesh, &scene.surfaces);
            if let Some(ls) = lights.sample_chosen(mesh, surfaces, choice, probability, numbers, p, &Rgb)
                && ls.wi.dot(ng) > 0.0
            {
                lit[i] = true;
                light_wi.set(i, ls.wi);
                light_li.set(i, ls.li);
                (light_distance[i], light_pdf[i], light_delta[i]) = (ls.distance, ls.pdf, ls.delta);
            }
        }
        // A uniform point on each lane's emissive triangle, as a direction with its solid-angle
        // density (`light::sample_triangle`'s operations).
        for i in 0..W {
            let lane = |r: &Rows| [r.0[0][i], r.0[1][i], r.0[2][i]];
            let (a, e1, e2, n, p, ng) =
                (lane(&corner), lane(&edge1), lane(&edge2), lane(&normal), lane(&sp.p), lane(&sp.ng));
            let su = place[0][i].sqrt();
            let (by, bz) = (place[1][i] * su, (1.0 - place[1][i]) * su);
            let d: [f32; 3] = std::array::from_fn(|k| a[k] + e1[k] * by + e2[k] * bz - p[k]);
            let dist2 = dot(d, d);
            let dist = dist2.sqrt();
            let wi = d.map(|x| x / dist);
            let cos_light = dot(n, wi.map(|x| -x));
            let finite = wi[0].is_finite() & wi[1].is_finite() & wi[2].is_finite();
            let dark = (cos_light == 0.0) | ((cos_light < 0.0) & !double_sided[i]) | !finite;
            let taken = on_triangle[i] & !dark & (dot(wi, ng) > 0.0);
            lit[i] |= taken;
            for k in 0..3 {
                light_wi.0[k][i] = if taken { wi[k] } else { light_wi.0[k][i] };
            }
            light_distance[i] = if taken { dist } else { light_distance[i] };
            let pdf = pmf[i] * dist2 / (cos_light.abs() * area[i]);
            light_pdf[i] = if taken { pdf } else { light_pdf[i] };
            light_delta[i] &= !taken;
        }
        LightSamples { lit, wi: light_wi, li: light_li, distance: light_distance, pdf: light_pdf, delta: light_delta }
    }
}
