//! Eight paths side by side for plain scenes: RGB light transport with next-event estimation
//! (and MIS), every material a Lambert surface the same all over. Each lane holds one path; a
//! lane whose path ends takes the tile's next sample at once, so the eight stay full until the
//! tile runs out. The path state lies in structure-of-arrays form (one row of eight per number),
//! and the stages that are arithmetic on it (the surface point, its frame, a point on an
//! emissive triangle, the Lambert lobe, the weights, the next ray) run as branch-free loops over
//! the eight lanes that the compiler puts in SIMD registers (AVX2 where the CPU has it, chosen
//! at run time; SSE otherwise).
//!
//! Each lane makes exactly the IEEE operations the one-path estimator
//! ([`crate::estimator::nee::trace`]) makes, in its order: the same bits for every sample. The
//! eight closest-hit rays of a step (camera rays among them) go to the scene together
//! ([`Scene::intersect8`]), which tests a small scene's triangles against all eight at once and
//! walks a big one's tree ray by ray; shadow rays go one by one. A bounce's numbers come from the
//! sampler eight at a time ([`sampler::bounce_lanes`]), and so do the sines and cosines that turn a
//! direction ([`crate::math::sincos_lanes`], libm's steps in lanes), and with at most eight lights
//! chosen by power, the choice of a light ([`crate::light::LightSet::choose_lanes`]). Elsewhere the
//! choice, and a point on any light but a triangle, are the scalar code's own calls, lane by lane.
//! Samples end in a different order than the pixel loop's, which the sums do not see: they add
//! whole numbers (see [`crate::sums`]).

// A lane's loop reads and writes several rows at its index.
#![allow(clippy::needless_range_loop)]

use crate::bsdf::Bsdf;
use crate::camera::Camera;
use crate::channels::{ColorModel, Rgb};
use crate::estimator::nee::Combination;
use crate::estimator::{same_side, survives_roulette};
use crate::flat::Lanes;
use crate::interaction::Hit;
use crate::light::Choice;
use crate::math::power_heuristic;
use crate::mesh::HAS_NORMALS;
use crate::sampler::{self, PixelSampler, PixelSeeds};
use crate::scene::Scene;
use crate::settings::{ColorMode, Estimator, LightSampler, RenderSettings};
use crate::sums::{Tile, TileSums};
use glam::{Vec2, Vec3};
use std::f32::consts::FRAC_1_PI;
use std::ops::Range;

/// Paths side by side.
const W: usize = sampler::LANES;

type Row = [f32; W];

/// What the wave needs of a material: its BSDF (a Lambert lobe) and, where it glows, what it
/// emits and whether from both faces.
#[derive(Clone, Copy)]
struct Plain {
    bsdf: Bsdf<Vec3>,
    /// [`Bsdf::has_smooth_part`]: whether light sampling can reach it.
    smooth: bool,
    emission: Option<Vec3>,
    double_sided: bool,
}

/// A scene and settings the wave renders: see [`Wave::for_render`].
pub(crate) struct Wave {
    /// Per material, what the wave needs of it where it is plain.
    materials: Vec<Option<Plain>>,
    combination: Combination,
}

impl Wave {
    /// The wave for `scene` under `settings` where it renders them: RGB, next-event estimation
    /// or MIS, no thin walls, no vertex colours, and every material a plain Lambert surface
    /// (the same BSDF and emission at every point: no texture, normal map, clear coat,
    /// anisotropy or refraction). `None` elsewhere: the one-path estimators render those.
    pub(crate) fn for_render(scene: &Scene, settings: &RenderSettings) -> Option<Wave> {
        let combination = match settings.estimator {
            Estimator::Mis => Combination::PowerHeuristic,
            Estimator::Nee => Combination::LightOnly,
            Estimator::Collision => return None,
        };
        if settings.color != ColorMode::Rgb || scene.thin_walls {
            return None;
        }
        if scene.vertex_colors {
            return None;
        }
        let surfaces = &scene.surfaces;
        let plain = |k: usize| {
            let m = &surfaces.materials()[k];
            let bsdf = surfaces.constant_rgb_bsdf(k as u32).filter(|b| b.is_lambert() && !b.transmits())?;
            let plain = m.normal_texture.is_none() && m.clearcoat <= 0.0 && !m.is_anisotropic() && !m.refracts();
            let emission = match m.is_emissive() {
                true => Some(surfaces.constant_rgb_emission(k as u32)?),
                false => None,
            };
            plain.then_some(Plain { bsdf, smooth: bsdf.has_smooth_part(), emission, double_sided: m.double_sided })
        };
        // Every material a triangle uses must be plain; the others do not matter. (Asked for each
        // tile, so from what the scene worked out once, not from its triangles.)
        let used = |k: usize| scene.used.get(k).copied().unwrap_or(false);
        let materials: Vec<Option<Plain>> = (0..surfaces.materials().len()).map(plain).collect();
        if materials.iter().enumerate().any(|(k, m)| used(k) && m.is_none()) {
            return None;
        }
        Some(Wave { materials, combination })
    }

    /// Samples `samples` of every pixel of `tile`: the sums [`crate::tile::render_tile`] gives.
    pub(crate) fn render(
        &self,
        scene: &Scene,
        settings: &RenderSettings,
        camera: &Camera,
        tile: Tile,
        samples: Range<u32>,
    ) -> TileSums {
        self.render_with(Lanes::widest(), scene, settings, camera, tile, samples)
    }

    /// [`Wave::render`] with the lane loops compiled for `lanes`, which must run on this CPU. All
    /// give the same bits: the instructions differ (AVX-512 has masked stores and 32 registers,
    /// where AVX2 spills and uses `VMASKMOVPS`; Cornell 256 x 256, 32 spp, one thread, on this
    /// project's Zen 4: medians 1.80 s against 1.68 s and 1.74 s against 1.50 s in two sets of six
    /// alternating runs), the operations do not.
    pub(crate) fn render_with(
        &self,
        lanes: Lanes,
        scene: &Scene,
        settings: &RenderSettings,
        camera: &Camera,
        tile: Tile,
        samples: Range<u32>,
    ) -> TileSums {
        assert!(lanes.run_here(), "{lanes} does not run on this CPU");
        #[cfg(target_arch = "x86_64")]
        match lanes {
            // SAFETY: the CPU has them (asserted above).
            Lanes::Avx512 => return unsafe { self.render_avx512(scene, settings, camera, tile, samples) },
            // SAFETY: as above.
            Lanes::Avx2 => return unsafe { self.render_avx2(scene, settings, camera, tile, samples) },
            Lanes::Portable => {}
        }
        self.render_lanes(Lanes::Portable, scene, settings, camera, tile, samples)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,avx512f,avx512vl,avx512bw,avx512dq")]
    fn render_avx512(
        &self,
        scene: &Scene,
        settings: &RenderSettings,
        camera: &Camera,
        tile: Tile,
        samples: Range<u32>,
    ) -> TileSums {
        self.render_lanes(Lanes::Avx512, scene, settings, camera, tile, samples)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    fn render_avx2(
        &self,
        scene: &Scene,
        settings: &RenderSettings,
        camera: &Camera,
        tile: Tile,
        samples: Range<u32>,
    ) -> TileSums {
        self.render_lanes(Lanes::Avx2, scene, settings, camera, tile, samples)
    }

    #[inline(always)]
    fn render_lanes(
        &self,
        lanes: Lanes,
        scene: &Scene,
        settings: &RenderSettings,
        camera: &Camera,
        tile: Tile,
        samples: Range<u32>,
    ) -> TileSums {
        let mut sums = TileSums::new(tile);
        let film = camera.film(settings.width, settings.height);
        let mut queue = Queue::new(settings, tile, samples);
        let mut paths = Paths::new();
        loop {
            // Every empty lane takes the next sample: its camera ray, which the step traces with
            // the other lanes' rays.
            for i in 0..W {
                if !paths.live[i]
                    && let Some((pixel, (x, y), sampler)) = queue.next()
                {
                    let c = sampler.camera();
                    // Box filter: every sample stays inside its own pixel.
                    let (o, d) = film.ray(Vec2::new(x as f32 + c[0], y as f32 + c[1]));
                    paths.start(i, pixel, sampler, o, d);
                }
            }
            if !paths.live.contains(&true) {
                return sums;
            }
            self.step(lanes, scene, settings, &mut paths, &mut sums);
        }
    }

    /// One vertex of every live path: its hit (or escape), emission, light sample and the
    /// BSDF-sampled direction on, as [`crate::estimator::nee::trace`] makes them.
    #[inline(always)]
    fn step(&self, lanes: Lanes, scene: &Scene, settings: &RenderSettings, paths: &mut Paths, sums: &mut TileSums) {
        let lights = &scene.lights;
        let max = settings.max_bounces();
        // The hits, the eight rays traced together. A lane that found none ends with what the
        // environment sends (a camera ray's with nothing under a transparent background).
        let hit = scene.intersect8(&paths.o.0, &paths.d.0, paths.live);
        for i in 0..W {
            if !paths.live[i] {
                continue;
            }
            let d = paths.d.get(i);
            if paths.bounce[i] == 0 {
                paths.covered[i] = hit[i].is_some();
                if settings.transparent && hit[i].is_none() {
                    paths.finish(i, sums);
                    continue;
                }
            }
            if hit[i].is_none() {
                let le = lights.environment_radiance(d);
                if le.max_element() > 0.0 {
                    paths.saw_emitter[i] |= paths.bounce[i] == 0;
                    let w = if paths.prev_delta[i] {
                        1.0
                    } else {
                        self.combination.weight(paths.prev_pdf[i], || lights.environment_pdf(d, settings.lights), false)
                    };
                    paths.l.set(i, paths.l.get(i) + paths.beta.get(i) * Rgb.illuminant(le) * w);
                }
                paths.finish(i, sums);
            }
        }
        let sp = Points::at(scene, &paths.o, &paths.d, &hit);
        // Emission; then the lanes whose paths go on take their bounce's numbers, eight at once.
        let mut on = [false; W];
        let mut diffuse = Rows::default();
        let mut smooth = [false; W];
        for i in 0..W {
            let Some(h) = hit[i] else { continue };
            let Some(material) = &self.materials[sp.material[i] as usize] else {
                unreachable!("every material a triangle uses is plain (`Wave::for_render`)")
            };
            let bounce = paths.bounce[i];
            if let Some(le) = material.emission.filter(|_| sp.front_face[i] || material.double_sided)
                && le.max_element() > 0.0
            {
                paths.saw_emitter[i] |= bounce == 0;
                let w = if paths.prev_delta[i] {
                    1.0
                } else {
                    let (p, ng) = (sp.p.get(i), sp.ng.get(i));
                    let (prev_p, prev_n) = (paths.prev_p.get(i), paths.prev_n.get(i));
                    self.combination.weight(
                        paths.prev_pdf[i],
                        || lights.triangle_pdf_at(prev_p, prev_n, h.triangle, p, ng, settings.lights),
                        false,
                    )
                };
                paths.l.set(i, paths.l.get(i) + paths.beta.get(i) * le * w);
            }
            if bounce == max {
                paths.finish(i, sums);
                continue;
            }
            diffuse.set(i, material.bsdf.diffuse);
            smooth[i] = material.smooth;
            on[i] = true;
        }
        let u = sampler::bounce_lanes(lanes, &paths.sampler, &paths.bounce, on);
        // A light sample for each, where its material has a lobe that light sampling reaches.
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
            let lw = lane(&light_wi);
            let wi = to_local(lw);
            let cos_geometric = dot(lw, ng);
            // Both above the surface, as `Bsdf::eval` and `pdf` ask it (a NaN counts as above).
            let below = (o_local[2] <= 0.0) | (wi[2] <= 0.0);
            let above = !below;
            let f = select(same_side(cos_geometric, wi[2]) & above, lane(&diffuse).map(|x| x * FRAC_1_PI), [0.0; 3]);
            shadow[i] = lit[i] & (max3(f) > 0.0);
            let bsdf_pdf = if above { wi[2] * FRAC_1_PI } else { 0.0 };
            // The heuristic worked out in every lane, kept where it applies (a select, not a branch).
            let heuristic = power_heuristic(light_pdf[i], bsdf_pdf);
            let w = if light_delta[i] | !power { 1.0 } else { heuristic };
            let scale = w / light_pdf[i];
            let (beta, li) = (lane(&paths.beta), lane(&light_li));
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
            let f = lane(&diffuse).map(|c| c * e);
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

/// `Vec3::dot`'s sum: `(x + y) + z`.
#[inline(always)]
fn dot(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// `a` where `c`, else `b`, lane by lane.
#[inline(always)]
fn select(c: bool, a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    std::array::from_fn(|k| if c { a[k] } else { b[k] })
}

/// `Vec3::max_element`.
#[inline(always)]
fn max3(v: [f32; 3]) -> f32 {
    let max = |a: f32, b: f32| if a > b { a } else { b };
    max(v[0], max(v[1], v[2]))
}

/// Three rows: a vector per lane.
#[derive(Clone, Copy, Default)]
struct Rows([Row; 3]);

impl Rows {
    #[inline(always)]
    fn get(&self, i: usize) -> Vec3 {
        Vec3::new(self.0[0][i], self.0[1][i], self.0[2][i])
    }

    #[inline(always)]
    fn set(&mut self, i: usize, v: Vec3) {
        (self.0[0][i], self.0[1][i], self.0[2][i]) = (v.x, v.y, v.z);
    }
}

/// The paths in the lanes.
struct Paths {
    live: [bool; W],
    pixel: [usize; W],
    sampler: [PixelSampler; W],
    /// Whether the camera ray met the scene (the pixel's coverage), set by the first step.
    covered: [bool; W],
    bounce: [u32; W],
    o: Rows,
    d: Rows,
    beta: Rows,
    l: Rows,
    saw_emitter: [bool; W],
    prev_pdf: Row,
    prev_delta: [bool; W],
    prev_p: Rows,
    prev_n: Rows,
}

impl Paths {
    fn new() -> Self {
        let idle = PixelSampler::new(crate::sampler::SamplerKind::Independent, 0, (0, 0), 0);
        Self {
            live: [false; W],
            pixel: [0; W],
            sampler: [idle; W],
            covered: [false; W],
            bounce: [0; W],
            o: Rows::default(),
            d: Rows::default(),
            beta: Rows::default(),
            l: Rows::default(),
            saw_emitter: [false; W],
            prev_pdf: [0.0; W],
            prev_delta: [true; W],
            prev_p: Rows::default(),
            prev_n: Rows::default(),
        }
    }

    /// Lane `i` takes the sample `sampler` of pixel `pixel` (its index in the tile), whose camera
    /// ray is `o + t d`.
    #[inline(always)]
    fn start(&mut self, i: usize, pixel: usize, sampler: PixelSampler, o: Vec3, d: Vec3) {
        self.live[i] = true;
        self.pixel[i] = pixel;
        self.sampler[i] = sampler;
        self.covered[i] = false;
        self.bounce[i] = 0;
        self.o.set(i, o);
        self.d.set(i, d);
        self.beta.set(i, Vec3::ONE);
        self.l.set(i, Vec3::ZERO);
        self.saw_emitter[i] = false;
        self.prev_pdf[i] = 0.0;
        self.prev_delta[i] = true;
        self.prev_p.set(i, o);
        self.prev_n.set(i, Vec3::Z);
    }

    /// Lane `i`'s path ends: its sample goes to its pixel.
    #[inline(always)]
    fn finish(&mut self, i: usize, sums: &mut TileSums) {
        sums.pixels[self.pixel[i]].add(self.l.get(i), self.saw_emitter[i], self.covered[i]);
        self.live[i] = false;
    }
}

/// The tile's samples in the pixel loop's order: pixel by pixel, each pixel's indices in turn.
struct Queue {
    tile: Tile,
    samples: Range<u32>,
    kind: crate::sampler::SamplerKind,
    seed: u64,
    /// The pixel (index in the tile) being handed out, its seeds and its next sample index.
    pixel: usize,
    seeds: Option<PixelSeeds>,
    index: u32,
}

impl Queue {
    fn new(settings: &RenderSettings, tile: Tile, samples: Range<u32>) -> Self {
        let index = samples.start;
        Self { tile, samples, kind: settings.sampler, seed: settings.seed, pixel: 0, seeds: None, index }
    }

    /// The next sample: its pixel's index in the tile, the pixel and its sampler.
    #[inline(always)]
    fn next(&mut self) -> Option<(usize, (u32, u32), PixelSampler)> {
        let pixels = (self.tile.width * self.tile.height) as usize;
        loop {
            if self.pixel >= pixels || self.samples.is_empty() {
                return None;
            }
            let (px, py) = ((self.pixel as u32) % self.tile.width, (self.pixel as u32) / self.tile.width);
            let (x, y) = (self.tile.x0 + px, self.tile.y0 + py);
            if self.index < self.samples.end {
                let seeds = self.seeds.get_or_insert_with(|| PixelSeeds::new(self.kind, self.seed, (x, y)));
                let sampler = seeds.sampler(self.index);
                self.index += 1;
                return Some((self.pixel, (x, y), sampler));
            }
            (self.pixel, self.seeds, self.index) = (self.pixel + 1, None, self.samples.start);
        }
    }
}

/// The surface points of eight hits, as rows: `SurfacePoint::at`'s numbers for a triangle of a
/// plain material (no texture, tangent frame or vertex colour), lane by lane in its operations.
struct Points {
    p: Rows,
    ng: Rows,
    s: Rows,
    t: Rows,
    n: Rows,
    front_face: [bool; W],
    material: [u32; W],
}

impl Points {
    /// The points where the rays `o + t d` of each lane meet their hits (lanes without one get
    /// numbers of no meaning).
    #[inline(always)]
    fn at(scene: &Scene, o: &Rows, d: &Rows, hits: &[Option<Hit>; W]) -> Points {
        let mesh = &scene.mesh;
        // The corners, normals and distances, gathered into rows.
        let (mut a, mut b, mut c) = (Rows::default(), Rows::default(), Rows::default());
        let (mut na, mut nb, mut nc) = (Rows::default(), Rows::default(), Rows::default());
        let mut t = [0.0; W];
        let mut material = [0; W];
        for i in 0..W {
            let Some(h) = hits[i] else { continue };
            let tri = &mesh.triangles[h.triangle as usize];
            let [i0, i1, i2] = tri.vertices.map(|k| k as usize);
            a.set(i, mesh.positions[i0]);
            b.set(i, mesh.positions[i1]);
            c.set(i, mesh.positions[i2]);
            if tri.flags & HAS_NORMALS != 0 {
                na.set(i, mesh.normals[i0]);
                nb.set(i, mesh.normals[i1]);
                nc.set(i, mesh.normals[i2]);
            }
            t[i] = h.t;
            material[i] = tri.material;
        }
        let mut out = Points {
            p: Rows::default(),
            ng: Rows::default(),
            s: Rows::default(),
            t: Rows::default(),
            n: Rows::default(),
            front_face: [false; W],
            material,
        };
        let sub = |a: [f32; 3], b: [f32; 3]| [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
        let clamp = |x: f32, lo: f32, hi: f32| {
            // `f32::clamp` without its check that `lo <= hi` (lanes without a hit may break it).
            let x = if x < lo { lo } else { x };
            if x > hi { hi } else { x }
        };
        for i in 0..W {
            let lane = |r: &Rows| [r.0[0][i], r.0[1][i], r.0[2][i]];
            let (a, b, c, o, d) = (lane(&a), lane(&b), lane(&c), lane(o), lane(d));
            // `barycentrics` at `o + d t`.
            let q = [o[0] + d[0] * t[i], o[1] + d[1] * t[i], o[2] + d[2] * t[i]];
            let (e1, e2, ep) = (sub(b, a), sub(c, a), sub(q, a));
            let (d11, d12, d22) = (dot(e1, e1), dot(e1, e2), dot(e2, e2));
            let (dp1, dp2) = (dot(ep, e1), dot(ep, e2));
            let denom = d11 * d22 - d12 * d12;
            let v = clamp((d22 * dp1 - d12 * dp2) / denom, 0.0, 1.0);
            let w = clamp((d11 * dp2 - d12 * dp1) / denom, 0.0, 1.0 - v);
            let (bx, by, bz) = if denom <= 0.0 { (1.0, 0.0, 0.0) } else { (1.0 - v - w, v, w) };
            let p: [f32; 3] = std::array::from_fn(|k| a[k] * bx + b[k] * by + c[k] * bz);
            // The face normal, `Vec3::normalize`'s way, and the side the ray came from.
            let cross = [e1[1] * e2[2] - e2[1] * e1[2], e1[2] * e2[0] - e2[2] * e1[0], e1[0] * e2[1] - e2[0] * e1[1]];
            let recip = 1.0 / dot(cross, cross).sqrt();
            let face = cross.map(|x| x * recip);
            let front = dot(face, d) < 0.0;
            let ng = select(front, face, face.map(|x| -x));
            // The interpolated normal where it has a length (lanes without normals hold zeros,
            // which have none). Branch-free, so that the lanes share registers.
            let (na, nb, nc) = (lane(&na), lane(&nb), lane(&nc));
            let n: [f32; 3] = std::array::from_fn(|k| na[k] * bx + nb[k] * by + nc[k] * bz);
            let rcp = 1.0 / dot(n, n).sqrt();
            let n_front = select(rcp.is_finite() & (rcp > 0.0), n.map(|x| x * rcp), face);
            let ns = select(front, n_front, n_front.map(|x| -x));
            let finite = ns[0].is_finite() & ns[1].is_finite() & ns[2].is_finite();
            let ns = select((dot(ns, d.map(|x| -x)) <= 0.0) | !finite, ng, ns);
            // `Frame::from_normal`.
            let sign = 1.0f32.copysign(ns[2]);
            let k = -1.0 / (sign + ns[2]);
            let m = ns[0] * ns[1] * k;
            let s = [1.0 + sign * ns[0] * ns[0] * k, sign * m, -sign * ns[0]];
            let tt = [m, sign + ns[1] * ns[1] * k, -ns[1]];
            for axis in 0..3 {
                out.p.0[axis][i] = p[axis];
                out.ng.0[axis][i] = ng[axis];
                out.s.0[axis][i] = s[axis];
                out.t.0[axis][i] = tt[axis];
                out.n.0[axis][i] = ns[axis];
            }
            out.front_face[i] = front;
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::channels::Rgb;
    use crate::material::Material;
    use crate::mesh::MeshData;
    use crate::sampler::SamplerKind;
    use crate::scene::SceneBuilder;
    use crate::settings::Termination;
    use crate::tile::render_pixels;
    use glam::{Mat4, Vec4};

    /// A quad `corners` (counter-clockwise seen from its front) cut into `n` x `n` squares, with
    /// its normal at each vertex where `normals`.
    fn quad(corners: [Vec3; 4], n: u32, normals: bool, material: u32) -> MeshData {
        let [a, b, c, d] = corners;
        let at = |i: u32, j: u32| {
            let (u, v) = (i as f32 / n as f32, j as f32 / n as f32);
            (a * (1.0 - u) + b * u) * (1.0 - v) + (d * (1.0 - u) + c * u) * v
        };
        let mut mesh = MeshData { material, ..MeshData::default() };
        for j in 0..=n {
            for i in 0..=n {
                mesh.positions.push(at(i, j));
            }
        }
        for j in 0..n {
            for i in 0..n {
                let k = j * (n + 1) + i;
                mesh.indices.extend([k, k + 1, k + n + 2, k, k + n + 2, k + n + 1]);
            }
        }
        let normal = (b - a).cross(d - a).normalize();
        mesh.normals = normals.then(|| vec![normal; mesh.positions.len()]);
        mesh
    }

    /// A box from `lo` to `hi`, its faces outwards.
    fn cube(builder: &mut SceneBuilder, lo: Vec3, hi: Vec3, material: u32) {
        let p = |x: usize, y: usize, z: usize| Vec3::new([lo.x, hi.x][x], [lo.y, hi.y][y], [lo.z, hi.z][z]);
        let faces = [
            [p(0, 0, 1), p(1, 0, 1), p(1, 1, 1), p(0, 1, 1)],
            [p(1, 0, 0), p(0, 0, 0), p(0, 1, 0), p(1, 1, 0)],
            [p(0, 1, 1), p(1, 1, 1), p(1, 1, 0), p(0, 1, 0)],
            [p(1, 0, 1), p(0, 0, 1), p(0, 0, 0), p(1, 0, 0)],
            [p(1, 0, 1), p(1, 0, 0), p(1, 1, 0), p(1, 1, 1)],
            [p(0, 0, 0), p(0, 0, 1), p(0, 1, 1), p(0, 1, 0)],
        ];
        for face in faces {
            builder.add_mesh("box", quad(face, 1, false, material), Mat4::IDENTITY).unwrap();
        }
    }

    fn lambert(name: &str, rgb: Vec3) -> Material {
        let base_color = rgb.extend(1.0);
        Material { name: name.into(), base_color, metallic: 0.0, specular: 0.0, ..Material::default() }
    }

    /// A room open at the front (paths escape to a dim sky), a light under its ceiling and a
    /// small one glowing from both faces, two boxes; the floor cut into `floor` x `floor`
    /// squares (8 leaves 50 triangles, tested whole; 16 makes the rays walk a tree).
    fn room(floor: u32) -> Scene {
        let mut b = SceneBuilder::new();
        let white = b.add_material(lambert("white", Vec3::new(0.73, 0.71, 0.68)));
        let red = b.add_material(lambert("red", Vec3::new(0.63, 0.06, 0.05)));
        let light = b.add_material(Material { emissive: Vec3::new(17.0, 12.0, 4.0), ..lambert("light", Vec3::ONE) });
        let both = b.add_material(Material {
            emissive: Vec3::new(1.0, 2.0, 4.0),
            double_sided: true,
            ..lambert("both", Vec3::splat(0.5))
        });
        let v = Vec3::new;
        let walls = [
            ([v(-1., 0., 1.), v(1., 0., 1.), v(1., 0., -1.), v(-1., 0., -1.)], floor, true, white),
            ([v(-1., 2., -1.), v(1., 2., -1.), v(1., 2., 1.), v(-1., 2., 1.)], 1, false, white),
            ([v(-1., 0., -1.), v(1., 0., -1.), v(1., 2., -1.), v(-1., 2., -1.)], 1, true, white),
            ([v(-1., 0., 1.), v(-1., 0., -1.), v(-1., 2., -1.), v(-1., 2., 1.)], 1, false, red),
            ([v(1., 0., -1.), v(1., 0., 1.), v(1., 2., 1.), v(1., 2., -1.)], 1, true, white),
            ([v(-0.3, 1.98, -0.3), v(-0.3, 1.98, 0.3), v(0.3, 1.98, 0.3), v(0.3, 1.98, -0.3)], 1, false, light),
            ([v(0.5, 0.8, -0.9), v(0.9, 0.8, -0.9), v(0.9, 1.2, -0.9), v(0.5, 1.2, -0.9)], 1, false, both),
        ];
        for (corners, n, normals, material) in walls {
            b.add_mesh("wall", quad(corners, n, normals, material), Mat4::IDENTITY).unwrap();
        }
        cube(&mut b, v(-0.6, 0.0, -0.6), v(-0.1, 1.2, -0.1), white);
        cube(&mut b, v(0.1, 0.0, 0.1), v(0.6, 0.6, 0.6), red);
        b.environment = Vec3::splat(0.2);
        let mut scene = b.build();
        scene.cameras.push(Camera::framing(v(-1.0, 0.0, -1.0), v(1.0, 2.0, 1.0)));
        scene
    }

    fn settings(estimator: Estimator, sampler: SamplerKind, termination: Termination) -> RenderSettings {
        RenderSettings { seed: 5, estimator, sampler, termination, ..RenderSettings::new(24, 20) }
    }

    /// Every sample the wave renders has the bits the one-path estimator gives it, for both
    /// estimators, samplers and terminations, a transparent background, a tile off the image's
    /// corner and a run of samples not from zero, whether the rays test every triangle or walk,
    /// with its loops compiled for every instruction set this CPU has.
    #[test]
    fn the_wave_renders_every_sample_with_the_bits_of_one_path() {
        let mut checked = 0;
        for floor in [8, 16] {
            let scene = room(floor);
            for estimator in [Estimator::Mis, Estimator::Nee] {
                for sampler in [SamplerKind::Sobol, SamplerKind::Independent] {
                    for (termination, transparent) in [
                        (Termination::MaxBounces(4), false),
                        (Termination::RussianRoulette { from: 2, max_bounces: 7 }, true),
                    ] {
                        let mut s = settings(estimator, sampler, termination);
                        s.transparent = transparent;
                        let wave = Wave::for_render(&scene, &s).expect("a plain scene");
                        let camera = &scene.cameras[0];
                        let tile = Tile { x0: 5, y0: 3, width: 13, height: 11 };
                        let one_path = render_pixels(&scene, &s, camera, tile, 3..14, |_| Rgb);
                        for lanes in Lanes::ALL.into_iter().filter(|lanes| lanes.run_here()) {
                            let waved = wave.render_with(lanes, &scene, &s, camera, tile, 3..14);
                            let what = format!("{floor} {estimator:?} {sampler:?} {termination:?}, {lanes}");
                            assert_eq!(waved, one_path, "{what}");
                        }
                        checked += 1;
                    }
                }
            }
        }
        assert_eq!(checked, 16);
    }

    /// The wave takes plain scenes in RGB only: not the collision estimator, spectral light
    /// transport, a glossy material or vertex colours.
    #[test]
    fn the_wave_leaves_other_scenes_to_one_path() {
        let scene = room(1);
        let s = settings(Estimator::Mis, SamplerKind::Sobol, Termination::MaxBounces(3));
        assert!(Wave::for_render(&scene, &s).is_some());
        let collision = RenderSettings { estimator: Estimator::Collision, ..s.clone() };
        assert!(Wave::for_render(&scene, &collision).is_none());
        let spectral = RenderSettings { color: ColorMode::Spectral, ..s.clone() };
        assert!(Wave::for_render(&scene, &spectral).is_none());
        let mut glossy = room(1);
        glossy.surfaces.materials_mut()[0].specular = 1.0;
        assert!(Wave::for_render(&glossy, &s).is_none(), "a specular layer");
        let mut b = SceneBuilder::new();
        let white = b.add_material(lambert("white", Vec3::ONE));
        let mut mesh = quad([Vec3::X, Vec3::Y, Vec3::Z, Vec3::ONE], 1, false, white);
        mesh.colors = Some(vec![Vec4::ONE; mesh.positions.len()]);
        b.add_mesh("coloured", mesh, Mat4::IDENTITY).unwrap();
        assert!(Wave::for_render(&b.build(), &s).is_none(), "vertex colours");
    }
}
