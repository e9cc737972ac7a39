//! Light sources and their sampling: emissive triangles (area lights), KHR_lights_punctual
//! point, spot and directional lights, and the environment (a constant or a map). A light is
//! chosen in proportion to its power ([`LightSampler::Power`]), or among the lights with a
//! position by a light tree ([`LightSampler::Tree`], see `light_tree.rs`).

use crate::channels::ColorModel;
use crate::envmap::EnvMap;
use crate::interaction::SurfacePoint;
use crate::light_tree::{LightBounds, LightTree};
use crate::material::Surfaces;
use crate::math::luminance;
use crate::mesh::Mesh;
use crate::sampling::{rescaled, sample_uniform_sphere};
use crate::settings::LightSampler;
use glam::Vec3;
use std::f32::consts::PI;
use std::sync::Arc;

/// KHR_lights_punctual lights in the specification's units: point and spot intensity in
/// candela, directional illuminance in lux; each already multiplied by its colour.
#[derive(Clone, Copy, Debug)]
pub enum PunctualLight {
    Point {
        position: Vec3,
        intensity: Vec3,
        range: Option<f32>,
    },
    Spot {
        position: Vec3,
        direction: Vec3,
        intensity: Vec3,
        cos_inner: f32,
        cos_outer: f32,
        range: Option<f32>,
    },
    /// `direction` is the way the light travels.
    Directional {
        direction: Vec3,
        illuminance: Vec3,
    },
}

impl PunctualLight {
    pub fn position(&self) -> Option<Vec3> {
        match *self {
            PunctualLight::Point { position, .. } | PunctualLight::Spot { position, .. } => Some(position),
            PunctualLight::Directional { .. } => None,
        }
    }

    pub fn kind(&self) -> &'static str {
        match self {
            PunctualLight::Point { .. } => "point",
            PunctualLight::Spot { .. } => "spot",
            PunctualLight::Directional { .. } => "directional",
        }
    }

    /// Bounds for the light tree; `None` for a directional light, which has no position.
    fn bounds(&self, phi: f32) -> Option<LightBounds> {
        match *self {
            PunctualLight::Point { position, .. } => Some(LightBounds::point(position, phi)),
            PunctualLight::Spot { position, direction, cos_inner, cos_outer, .. } => {
                Some(LightBounds::spot(position, direction, cos_inner, cos_outer, phi))
            }
            PunctualLight::Directional { .. } => None,
        }
    }

    /// Approximate emitted power, for choosing among lights.
    fn power(&self, scene_radius: f32) -> f32 {
        match *self {
            PunctualLight::Point { intensity, .. } => 4.0 * PI * luminance(intensity),
            PunctualLight::Spot { intensity, cos_inner, cos_outer, .. } => {
                2.0 * PI * (1.0 - 0.5 * (cos_inner + cos_outer)) * luminance(intensity)
            }
            PunctualLight::Directional { illuminance, .. } => PI * scene_radius * scene_radius * luminance(illuminance),
        }
    }
}

/// glTF's recommended range window: `clamp(1 - (d / range)^4, 0, 1)^2`.
fn range_window(distance: f32, range: Option<f32>) -> f32 {
    match range {
        Some(r) if r > 0.0 => (1.0 - (distance / r).powi(4)).clamp(0.0, 1.0).powi(2),
        _ => 1.0,
    }
}

/// One light sample seen from a point.
#[derive(Clone, Copy, Debug)]
pub struct LightSample<C = Vec3> {
    /// Unit direction from the shading point to the light.
    pub wi: Vec3,
    /// Distance to the light sample (infinite for directional and environment light).
    pub distance: f32,
    /// Incident radiance (area, environment) or irradiance-like term `I / d^2` (punctual).
    pub li: C,
    /// Solid-angle density including the choice of light; for a delta light, the choice probability.
    pub pdf: f32,
    pub delta: bool,
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) enum Choice {
    Punctual(u32),
    /// An index into [`LightSet::emitters`].
    Triangle(u32),
    Environment,
    /// The light tree (with [`LightSampler::Tree`]), which then chooses.
    Tree,
}

/// What sampling a point on one emissive triangle needs, gathered once when the set is built
/// (per sample this saves the vertex lookups, a cross product and a square root).
#[derive(Clone, Copy, Debug)]
pub(crate) struct Emitter {
    pub(crate) a: Vec3,
    /// Edges `b - a` and `c - a`.
    pub(crate) e1: Vec3,
    pub(crate) e2: Vec3,
    /// Unit normal of the counter-clockwise (front) face.
    pub(crate) n: Vec3,
    pub(crate) area: f32,
    vertices: [u32; 3],
    pub(crate) material: u32,
    pub(crate) double_sided: bool,
    /// The triangle's BVH slot.
    slot: u32,
}

/// Up to this many lights (at most 8 bits of the reused number spent on the choice), one
/// number both chooses a light and places the point on it.
const REUSE_MAX_LIGHTS: usize = 256;

/// All lights of a scene, with a discrete distribution proportional to power and a light tree.
#[derive(Default)]
pub struct LightSet {
    pub punctual: Vec<PunctualLight>,
    /// Constant environment radiance (none with a map).
    pub environment: Vec3,
    /// An environment map, which replaces the constant.
    pub environment_map: Option<Arc<EnvMap>>,
    choices: Vec<Choice>,
    cdf: Vec<f32>,
    emitters: Vec<Emitter>,
    /// Per triangle (BVH order), the probability of choosing it over its area: the area density
    /// of light sampling on it; 0 when it does not emit.
    triangle_density: Vec<f32>,
    environment_pmf: f32,
    /// With [`LightSampler::Tree`], the first choice is among the lights without a position
    /// (directional, environment) and the tree, by power; the tree then chooses among the rest.
    top_choices: Vec<Choice>,
    top_cdf: Vec<f32>,
    tree: LightTree,
    /// The light behind each of the tree's indices: point and spot lights, then emitters in order.
    tree_lights: Vec<Choice>,
    /// The tree's index of emitter 0.
    tree_first_emitter: u32,
    tree_pmf: f32,
    environment_top_pmf: f32,
    /// Largest emitted radiance over area lights and the environment (`Le*` of Dimov, Gurov and Penzov).
    pub max_radiance: f32,
}

impl LightSet {
    /// The lights of a scene: the emissive triangles of `mesh` (their materials in `surfaces`),
    /// `punctual`, and the environment: `map` when given (the constant `environment` is then
    /// ignored), else the constant. `diagonal` is the scene's size, which puts a power on lights
    /// at infinity.
    pub fn build(
        mesh: &Mesh,
        surfaces: &Surfaces,
        diagonal: f32,
        punctual: Vec<PunctualLight>,
        environment: Vec3,
        map: Option<Arc<EnvMap>>,
    ) -> Self {
        let environment = if map.is_some() { Vec3::ZERO } else { environment };
        let radius = 0.5 * diagonal.max(1e-6);
        let mut choices = Vec::new();
        let mut power = Vec::new();
        for (i, l) in punctual.iter().enumerate() {
            choices.push(Choice::Punctual(i as u32));
            power.push(l.power(radius));
        }
        let mut max_radiance: f32 = environment.max_element().max(map.as_ref().map_or(0.0, |m| m.max_radiance()));
        let mut emitters = Vec::new();
        // Per material, once: textured emitters weigh by their texture's mean.
        let mean_emission: Vec<f32> = surfaces
            .materials()
            .iter()
            .map(|m| luminance(m.mean_emission(&surfaces.images, &surfaces.textures)))
            .collect();
        for (slot, tri) in mesh.triangles.iter().enumerate() {
            let m = &surfaces.materials()[tri.material as usize];
            if !m.is_emissive() {
                continue;
            }
            let sides = if m.double_sided { 2.0 } else { 1.0 };
            max_radiance = max_radiance.max(m.emissive.max_element());
            let [a, b, c] = mesh.corners(tri);
            let cross = (b - a).cross(c - a);
            let area = 0.5 * cross.length();
            choices.push(Choice::Triangle(emitters.len() as u32));
            emitters.push(Emitter {
                a,
                e1: b - a,
                e2: c - a,
                n: cross / (2.0 * area),
                area,
                vertices: tri.vertices,
                material: tri.material,
                double_sided: m.double_sided,
                slot: slot as u32,
            });
            let le = mean_emission[tri.material as usize].max(1e-6);
            power.push(sides * PI * area * le);
        }
        if let Some(map) = &map {
            choices.push(Choice::Environment);
            power.push(PI * radius * radius * map.luminance_integral().max(1e-6));
        } else if environment.max_element() > 0.0 {
            choices.push(Choice::Environment);
            power.push(PI * 4.0 * PI * radius * radius * luminance(environment).max(1e-6));
        }
        let (mut top_choices, mut top_power) = (Vec::new(), Vec::new());
        let (mut tree_lights, mut bounds) = (Vec::new(), Vec::new());
        for (c, &p) in choices.iter().zip(&power) {
            let bound = match *c {
                Choice::Punctual(i) => punctual[i as usize].bounds(p),
                Choice::Triangle(i) => {
                    let e = &emitters[i as usize];
                    let corners = [e.a, e.a + e.e1, e.a + e.e2];
                    let (lo, hi) =
                        (corners[0].min(corners[1]).min(corners[2]), corners[0].max(corners[1]).max(corners[2]));
                    Some(LightBounds::surface(lo, hi, e.n, if e.area > 0.0 { p } else { 0.0 }, e.double_sided))
                }
                Choice::Environment | Choice::Tree => None,
            };
            match bound {
                Some(b) => {
                    tree_lights.push(*c);
                    bounds.push(b);
                }
                None => {
                    top_choices.push(*c);
                    top_power.push(p);
                }
            }
        }
        let tree_first_emitter = tree_lights.iter().position(|c| matches!(c, Choice::Triangle(_))).unwrap_or(0) as u32;
        let tree = LightTree::build(&bounds);
        if !tree.is_empty() {
            top_choices.push(Choice::Tree);
            top_power.push(tree.power());
        }
        let top_cdf = cdf_of(&top_power);
        let (mut tree_pmf, mut environment_top_pmf) = (0.0, 0.0);
        for (i, c) in top_choices.iter().enumerate() {
            let pmf = top_cdf[i] - if i == 0 { 0.0 } else { top_cdf[i - 1] };
            match c {
                Choice::Tree => tree_pmf = pmf,
                Choice::Environment => environment_top_pmf = pmf,
                _ => {}
            }
        }
        let total: f64 = power.iter().map(|&p| p as f64).sum();
        let cdf = cdf_of(&power);
        let mut triangle_density = vec![0.0; mesh.triangles.len()];
        let mut environment_pmf = 0.0;
        for (c, &p) in choices.iter().zip(&power) {
            let pmf = (p as f64 / total) as f32;
            match *c {
                Choice::Triangle(i) => {
                    let e = &emitters[i as usize];
                    // A degenerate triangle has no area and is never chosen (its power is 0).
                    if e.area > 0.0 {
                        triangle_density[e.slot as usize] = pmf / e.area;
                    }
                }
                Choice::Environment => environment_pmf = pmf,
                Choice::Punctual(_) | Choice::Tree => {}
            }
        }
        Self {
            punctual,
            environment,
            environment_map: map,
            choices,
            cdf,
            emitters,
            triangle_density,
            environment_pmf,
            top_choices,
            top_cdf,
            tree,
            tree_lights,
            tree_first_emitter,
            tree_pmf,
            environment_top_pmf,
            max_radiance,
        }
    }

    /// The emissive triangle behind [`Choice::Triangle`]'s index.
    pub(crate) fn emitter(&self, index: u32) -> &Emitter {
        &self.emitters[index as usize]
    }

    pub fn is_empty(&self) -> bool {
        self.choices.is_empty()
    }

    /// Emissive triangles (area lights).
    pub fn emissive_triangles(&self) -> usize {
        self.emitters.len()
    }

    /// Lights with a position (emissive triangles, point and spot lights): those the light tree
    /// chooses among.
    pub fn located(&self) -> usize {
        self.tree_lights.len()
    }

    /// Nodes on the light tree's longest path from its root to a light.
    pub fn tree_depth(&self) -> u32 {
        self.tree.depth()
    }

    /// Samples a light as seen from `sp` with three uniform numbers: `u[0]` chooses the light and
    /// `u[1], u[2]` place the point on it. With few lights the choice reuses `u[1]` instead
    /// (rescaled within the chosen light's interval, as Mitsuba's `sample_reuse`), so that a
    /// stratified pair `u[1], u[2]` stays stratified over all emitters together rather than over
    /// each one's random share of the samples. With many lights the rescaling would spend too
    /// many of `u[1]`'s 24 bits, and `u[0]` chooses. A tree's choices reuse the number likewise.
    pub fn sample<M: ColorModel>(
        &self,
        mesh: &Mesh,
        surfaces: &Surfaces,
        sp: &SurfacePoint,
        u: [f32; 3],
        sampler: LightSampler,
        model: &M,
    ) -> Option<LightSample<M::C>> {
        let (choice, pmf, u) = self.choose_from(sp.p, sp.ng, u, sampler)?;
        self.sample_chosen(mesh, surfaces, choice, pmf, u, sp.p, model)
    }

    /// The first half of [`Self::sample`], for the point `p` with geometric normal `ng`: the
    /// light chosen, its probability, and the three numbers that place the point on it (`u[1]`
    /// rescaled where it also chose). `None` where nothing can be chosen or the choice has no
    /// probability.
    #[inline(always)]
    pub(crate) fn choose_from(
        &self,
        p: Vec3,
        ng: Vec3,
        u: [f32; 3],
        sampler: LightSampler,
    ) -> Option<(Choice, f32, [f32; 3])> {
        let reuse = self.cdf.len() <= REUSE_MAX_LIGHTS;
        let pick = if reuse { u[1] } else { u[0] };
        let (choice, pmf, rest) = match sampler {
            LightSampler::Power => choose(&self.choices, &self.cdf, pick)?,
            LightSampler::Tree => match choose(&self.top_choices, &self.top_cdf, pick)? {
                (Choice::Tree, pmf, rest) => {
                    let (light, tree_pmf, rest) = self.tree.sample(p, ng, rest)?;
                    (self.tree_lights[light as usize], pmf * tree_pmf, rest)
                }
                chosen => chosen,
            },
        };
        let u = if reuse { [u[0], rest, u[2]] } else { u };
        if pmf <= 0.0 {
            return None;
        }
        Some((choice, pmf, u))
    }

    /// The second half of [`Self::sample`]: a point on the chosen light, for the point `p`.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn sample_chosen<M: ColorModel>(
        &self,
        mesh: &Mesh,
        surfaces: &Surfaces,
        choice: Choice,
        pmf: f32,
        u: [f32; 3],
        p: Vec3,
        model: &M,
    ) -> Option<LightSample<M::C>> {
        match choice {
            Choice::Punctual(i) => self.sample_punctual(&self.punctual[i as usize], p, pmf, model),
            Choice::Environment if self.environment_map.is_some() => {
                let map = self.environment_map.as_ref()?;
                let (wi, radiance, pdf) = map.sample([u[1], u[2]])?;
                let li = model.illuminant(radiance);
                Some(LightSample { wi, distance: f32::INFINITY, li, pdf: pmf * pdf, delta: false })
            }
            Choice::Environment => {
                let wi = sample_uniform_sphere([u[1], u[2]]);
                let pdf = pmf / (4.0 * PI);
                let li = model.illuminant(self.environment);
                Some(LightSample { wi, distance: f32::INFINITY, li, pdf, delta: false })
            }
            Choice::Triangle(i) => {
                sample_triangle(mesh, surfaces, &self.emitters[i as usize], p, pmf, [u[1], u[2]], model)
            }
            Choice::Tree => None,
        }
    }

    fn sample_punctual<M: ColorModel>(
        &self,
        light: &PunctualLight,
        p: Vec3,
        pmf: f32,
        model: &M,
    ) -> Option<LightSample<M::C>> {
        let (wi, distance, li) = match *light {
            PunctualLight::Point { position, intensity, range } => {
                let d = position - p;
                let dist = d.length();
                (d / dist, dist, intensity * range_window(dist, range) / (dist * dist))
            }
            PunctualLight::Spot { position, direction, intensity, cos_inner, cos_outer, range } => {
                let d = position - p;
                let dist = d.length();
                let wi = d / dist;
                // glTF's smooth cone falloff, squared.
                let scale = 1.0 / (cos_inner - cos_outer).max(1e-3);
                let cone = ((direction.dot(-wi) - cos_outer) * scale).clamp(0.0, 1.0);
                (wi, dist, intensity * (cone * cone) * range_window(dist, range) / (dist * dist))
            }
            PunctualLight::Directional { direction, illuminance } => (-direction, f32::INFINITY, illuminance),
        };
        if !wi.is_finite() || li.max_element() <= 0.0 {
            return None;
        }
        Some(LightSample { wi, distance, li: model.illuminant(li), pdf: pmf, delta: true })
    }

    /// Solid-angle density with which [`Self::sample`] would pick the point `light_point` on an
    /// emissive triangle, sampling for the point `from` with unit geometric normal `n`.
    pub fn triangle_pdf(&self, from: Vec3, n: Vec3, light_point: &SurfacePoint, sampler: LightSampler) -> f32 {
        self.triangle_pdf_at(from, n, light_point.triangle, light_point.p, light_point.ng, sampler)
    }

    /// [`Self::triangle_pdf`] for the point `p` with geometric normal `ng` on triangle `triangle`.
    pub(crate) fn triangle_pdf_at(
        &self,
        from: Vec3,
        n: Vec3,
        triangle: u32,
        p: Vec3,
        ng: Vec3,
        sampler: LightSampler,
    ) -> f32 {
        let mut density = self.triangle_density.get(triangle as usize).copied().unwrap_or(0.0);
        if density == 0.0 {
            return 0.0;
        }
        if sampler == LightSampler::Tree {
            // Emitters are listed in BVH order.
            let Ok(i) = self.emitters.binary_search_by_key(&triangle, |e| e.slot) else {
                return 0.0;
            };
            let pmf = self.tree_pmf * self.tree.pmf(from, n, self.tree_first_emitter + i as u32);
            density = pmf / self.emitters[i].area;
        }
        let d = p - from;
        let dist2 = d.length_squared();
        let cos = ng.dot(d / dist2.sqrt()).abs();
        if cos <= 0.0 {
            return 0.0;
        }
        density * dist2 / cos
    }

    /// Solid-angle density with which [`Self::sample`] picks environment direction `d`.
    pub fn environment_pdf(&self, d: Vec3, sampler: LightSampler) -> f32 {
        let pmf = match sampler {
            LightSampler::Power => self.environment_pmf,
            LightSampler::Tree => self.environment_top_pmf,
        };
        match &self.environment_map {
            Some(map) => pmf * map.pdf(d),
            None => pmf / (4.0 * PI),
        }
    }

    /// Whether anything arrives from the environment.
    pub fn has_environment(&self) -> bool {
        self.environment_map.is_some() || self.environment.max_element() > 0.0
    }

    /// Radiance arriving from the environment along unit direction `d` (where a ray that
    /// escapes the scene along `d` comes from).
    pub fn environment_radiance(&self, d: Vec3) -> Vec3 {
        match &self.environment_map {
            Some(map) => map.radiance(d),
            None => self.environment,
        }
    }
}

/// The running sums of `power`, normalised, the last exactly 1 (empty for no power).
fn cdf_of(power: &[f32]) -> Vec<f32> {
    let total: f64 = power.iter().map(|&p| p as f64).sum();
    let mut acc = 0.0f64;
    let mut cdf: Vec<f32> = power
        .iter()
        .map(|&p| {
            acc += p as f64;
            (acc / total) as f32
        })
        .collect();
    if let Some(last) = cdf.last_mut() {
        *last = 1.0;
    }
    cdf
}

/// The choice whose interval of `cdf` holds `u`, its probability, and `u` rescaled to `[0, 1)`
/// within that interval.
#[inline(always)]
fn choose(choices: &[Choice], cdf: &[f32], u: f32) -> Option<(Choice, f32, f32)> {
    // Among a few, the count of entries at or below `u` (what the search finds: the cdf never
    // decreases), without the search's branch, which a random `u` mispredicts half the time.
    let at_or_below = match cdf.len() {
        0..=8 => cdf.iter().map(|&c| (c <= u) as usize).sum(),
        _ => cdf.partition_point(|&c| c <= u),
    };
    let i = at_or_below.min(cdf.len().checked_sub(1)?);
    let lo = if i == 0 { 0.0 } else { cdf[i - 1] };
    let pmf = cdf[i] - lo;
    Some((choices[i], pmf, rescaled(u, lo, pmf)))
}

/// Lanes side by side in [`LightSet::choose_lanes`].
const LANES: usize = 8;
// `choose_lanes` takes the reused number: so few lights must be few enough to reuse it.
const _: () = assert!(LANES <= REUSE_MAX_LIGHTS);

impl LightSet {
    /// [`Self::choose_from`] under [`LightSampler::Power`] for eight shading points at once, where
    /// the scene has at most eight lights to choose from (`None` elsewhere): lane `i` chooses with
    /// `pick[i]` (the reused number `u[1]`; with so few lights the choice is where it does not
    /// depend on the point). Per lane the light, its probability and `pick[i]` rescaled within
    /// its interval, with the bits `choose` gives; a probability of zero or less is no choice.
    /// The count and the lookups are selects over the lanes, with no branch on a random number.
    #[inline(always)]
    pub(crate) fn choose_lanes(&self, pick: &[f32; LANES]) -> Option<([Choice; LANES], [f32; LANES], [f32; LANES])> {
        let cdf = &self.cdf;
        if cdf.is_empty() || cdf.len() > LANES {
            return None;
        }
        let last = cdf.len() - 1;
        // Per lane the count of entries at or below its number, at most the last index, then the
        // interval's ends.
        let mut at_or_below = [0usize; LANES];
        for &c in cdf {
            for i in 0..LANES {
                at_or_below[i] += (c <= pick[i]) as usize;
            }
        }
        let index = at_or_below.map(|n| n.min(last));
        let (mut lo, mut hi) = ([0.0f32; LANES], [0.0f32; LANES]);
        for (k, &c) in cdf.iter().enumerate() {
            for i in 0..LANES {
                lo[i] = if index[i] == k + 1 { c } else { lo[i] };
                hi[i] = if index[i] == k { c } else { hi[i] };
            }
        }
        let pmf: [f32; LANES] = std::array::from_fn(|i| hi[i] - lo[i]);
        let rest = std::array::from_fn(|i| rescaled(pick[i], lo[i], pmf[i]));
        Some((index.map(|k| self.choices[k]), pmf, rest))
    }
}

/// Uniform point on an emissive triangle, converted to a solid-angle density at `p`.
fn sample_triangle<M: ColorModel>(
    mesh: &Mesh,
    surfaces: &Surfaces,
    e: &Emitter,
    p: Vec3,
    pmf: f32,
    u: [f32; 2],
    model: &M,
) -> Option<LightSample<M::C>> {
    let [i0, i1, i2] = e.vertices.map(|i| i as usize);
    let su = u[0].sqrt();
    let bary = Vec3::new(1.0 - su, u[1] * su, (1.0 - u[1]) * su);
    let q = e.a + e.e1 * bary.y + e.e2 * bary.z;
    let d = q - p;
    let dist2 = d.length_squared();
    let dist = dist2.sqrt();
    let wi = d / dist;
    let cos_light = e.n.dot(-wi);
    // One-sided emitters shine from their front (counter-clockwise) face only.
    if cos_light == 0.0 || (cos_light < 0.0 && !e.double_sided) || !wi.is_finite() {
        return None;
    }
    let uv = || std::array::from_fn(|s| mesh.uv[s][i0] * bary.x + mesh.uv[s][i1] * bary.y + mesh.uv[s][i2] * bary.z);
    let li = surfaces.emission_at(e.material, uv, glam::Vec4::ONE, model);
    let pdf = pmf * dist2 / (cos_light.abs() * e.area);
    Some(LightSample { wi, distance: dist, li, pdf, delta: false })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sampling::ONE_BELOW;

    /// Choosing among lights with one number and rescaling it: each light is chosen with its
    /// probability, and the rescaled numbers of each light's choices are again uniform in `[0, 1)`
    /// (mean, count below one half and largest value, over a stratified sweep of `u`).
    #[test]
    fn choice_and_rescaled_number() {
        let pmf = [0.125f32, 0.5, 0.0, 0.375];
        let mut acc = 0.0;
        let cdf: Vec<f32> = pmf
            .iter()
            .map(|p| {
                acc += p;
                acc
            })
            .collect();
        let choices: Vec<Choice> = (0..pmf.len() as u32).map(Choice::Punctual).collect();
        let n = 1 << 16;
        let mut count = [0usize; 4];
        let mut sum = [0f64; 4];
        let mut below_half = [0usize; 4];
        let mut largest = [0f64; 4];
        for k in 0..n {
            let u = (k as f32 + 0.5) / n as f32;
            let (Choice::Punctual(i), p, r) = choose(&choices, &cdf, u).unwrap() else { unreachable!() };
            assert_eq!(p, pmf[i as usize]);
            assert!((0.0..1.0).contains(&r), "rescaled {r}");
            count[i as usize] += 1;
            sum[i as usize] += r as f64;
            below_half[i as usize] += (r < 0.5) as usize;
            largest[i as usize] = largest[i as usize].max(r as f64);
        }
        for i in 0..4 {
            let expected = pmf[i] as f64 * n as f64;
            assert!((count[i] as f64 - expected).abs() <= 1.0, "light {i}: {} of {expected}", count[i]);
            if count[i] > 0 {
                // A stratified sweep: within a few grid steps of exact.
                let step = 1.0 / count[i] as f64;
                let mean = sum[i] / count[i] as f64;
                assert!((mean - 0.5).abs() < 2.0 * step, "light {i}: mean {mean}");
                assert!((below_half[i] as f64 / count[i] as f64 - 0.5).abs() < 2.0 * step);
                assert!(1.0 - largest[i] < 2.0 * step, "light {i}: largest {}", largest[i]);
            }
        }
    }

    /// Eight lanes choose as `choose_from` does, bit for bit, with one to eight lights (powers
    /// with zero shares among them), for random numbers, each cdf entry and its neighbours, and
    /// the ends of `[0, 1)`; with nine lights the lanes decline.
    #[test]
    fn eight_lanes_choose_as_one_does() {
        use crate::sampler::{mix64, unit_f32};
        let mut state = 5u64;
        let mut next = || {
            state = mix64(state);
            unit_f32(state)
        };
        for n in 1..=9usize {
            let power: Vec<f32> = (0..n).map(|k| if k % 3 == 1 { 0.0 } else { 0.1 + next() }).collect();
            let lights = LightSet {
                choices: (0..n as u32).map(Choice::Punctual).collect(),
                cdf: cdf_of(&power),
                ..LightSet::default()
            };
            if n > LANES {
                assert!(lights.choose_lanes(&[0.5; LANES]).is_none());
                continue;
            }
            let mut picks: Vec<f32> = (0..256).map(|_| next()).collect();
            for &c in &lights.cdf {
                picks.extend([c.next_down(), c, c.next_up()].into_iter().filter(|u| (0.0..1.0).contains(u)));
            }
            picks.extend([0.0, ONE_BELOW]);
            for chunk in picks.chunks(LANES) {
                let mut pick = [0.25f32; LANES];
                pick[..chunk.len()].copy_from_slice(chunk);
                let (choice, pmf, rest) = lights.choose_lanes(&pick).unwrap();
                for i in 0..LANES {
                    let one = lights.choose_from(Vec3::ZERO, Vec3::Z, [0.3, pick[i], 0.7], LightSampler::Power);
                    let lane =
                        (pmf[i] > 0.0).then(|| (choice[i], pmf[i].to_bits(), [0.3, rest[i], 0.7].map(f32::to_bits)));
                    let one = one.map(|(c, p, u)| (c, p.to_bits(), u.map(f32::to_bits)));
                    assert_eq!(lane, one, "{n} lights, pick {} (bits {:#x})", pick[i], pick[i].to_bits());
                }
            }
        }
    }

    /// For emissive triangles, the density `sample` reports for a point equals the density
    /// `triangle_pdf` gives the same point when a BSDF-sampled ray finds it, which is what MIS
    /// weights need, with either light sampler. Three emitters of different sizes and orientations,
    /// one of them two-sided, and a non-emitting triangle; 2000 samples from points around the origin.
    #[test]
    fn triangle_sample_density_matches_triangle_pdf() {
        use crate::channels::Rgb;
        use crate::material::Material;
        use crate::sampler::{mix64, unit_f32};
        use crate::{MeshData, SceneBuilder};
        use glam::{Mat4, Vec4};
        let mut b = SceneBuilder::new();
        let emitter = |e: f32, double_sided| Material {
            emissive: Vec3::splat(e),
            double_sided,
            base_color: Vec4::new(0.5, 0.5, 0.5, 1.0),
            ..Material::default()
        };
        let materials = [
            b.add_material(emitter(1.0, false)),
            b.add_material(emitter(4.0, true)),
            b.add_material(emitter(0.0, false)),
        ];
        let triangles = [
            ([Vec3::new(-1.0, 2.0, -1.0), Vec3::new(1.0, 2.0, 0.0), Vec3::new(-1.0, 2.0, 1.0)], 0),
            ([Vec3::new(3.0, 0.0, 0.0), Vec3::new(3.0, 0.5, 0.0), Vec3::new(3.0, 0.0, 0.2)], 1),
            ([Vec3::new(0.0, -2.0, 0.0), Vec3::new(0.0, -2.0, 0.1), Vec3::new(0.3, -2.0, 0.0)], 0),
            ([Vec3::new(-3.0, 0.0, 0.0), Vec3::new(-3.0, 1.0, 0.0), Vec3::new(-3.0, 0.0, 1.0)], 2),
        ];
        for (i, (v, m)) in triangles.iter().enumerate() {
            let mesh = MeshData {
                positions: v.to_vec(),
                indices: vec![0, 1, 2],
                material: materials[*m],
                ..Default::default()
            };
            b.add_mesh(&format!("t{i}"), mesh, Mat4::IDENTITY).unwrap();
        }
        let scene = b.build();
        assert_eq!(scene.lights.emissive_triangles(), 3);
        let mut state = 0u64;
        let mut next = || {
            state += 1;
            unit_f32(mix64(state))
        };
        for k in 0..2000 {
            let sampler = if k % 2 == 0 { LightSampler::Power } else { LightSampler::Tree };
            // Inside the cube [-1, 1]^3 every point sees the front of both one-sided emitters.
            let from = Vec3::new(next() - 0.5, next() - 0.5, next() - 0.5) * 2.0;
            let u = [next(), next(), next()];
            let ls = scene
                .lights
                .sample(&scene.mesh, &scene.surfaces, &point_at(from), u, sampler, &Rgb)
                .expect("every emitter faces the point");
            let hit = scene.intersect(from, ls.wi, f32::INFINITY).expect("the sampled point is on a triangle");
            assert!((hit.t - ls.distance).abs() < 1e-4 * ls.distance, "distance {} against {}", hit.t, ls.distance);
            let light_point = scene.surface(hit, from, ls.wi);
            let pdf = scene.lights.triangle_pdf(from, Vec3::Z, &light_point, sampler);
            assert!((pdf - ls.pdf).abs() <= 1e-3 * ls.pdf, "pdf {pdf} against the sample's {}", ls.pdf);
        }
    }

    /// A surface point at `p` (only its position matters to light sampling).
    fn point_at(p: Vec3) -> SurfacePoint {
        SurfacePoint {
            p,
            ng: Vec3::Z,
            frame: crate::math::Frame::from_normal(Vec3::Z),
            coat_normal: None,
            front_face: true,
            anisotropy: None,
            uv: [glam::Vec2::ZERO; 2],
            color: glam::Vec4::ONE,
            material: 0,
            triangle: 0,
        }
    }
}
