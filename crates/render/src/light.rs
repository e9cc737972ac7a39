//! Light sources and their sampling: emissive triangles (area lights, chosen in proportion to
//! power), KHR_lights_punctual point, spot and directional lights, and a constant environment.

use crate::channels::ColorModel;
use crate::material::TextureContext;
use crate::math::{luminance, sample_uniform_sphere};
use crate::scene::{Scene, SurfacePoint};
use glam::Vec3;
use std::f32::consts::PI;

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

#[derive(Clone, Copy, Debug)]
enum Choice {
    Punctual(u32),
    Triangle(u32),
    Environment,
}

/// All lights of a scene with a discrete distribution proportional to power.
#[derive(Default)]
pub struct LightSet {
    pub punctual: Vec<PunctualLight>,
    pub environment: Vec3,
    choices: Vec<Choice>,
    cdf: Vec<f32>,
    /// Probability of choosing each triangle (BVH order), 0 when it does not emit.
    triangle_pmf: Vec<f32>,
    environment_pmf: f32,
    /// Largest emitted radiance over area lights and the environment (`Le*` of paper 1).
    pub max_radiance: f32,
    pub emissive_triangles: usize,
}

impl LightSet {
    pub fn build(scene: &Scene, punctual: Vec<PunctualLight>, environment: Vec3) -> Self {
        let radius = 0.5 * scene.diagonal().max(1e-6);
        let mut choices = Vec::new();
        let mut power = Vec::new();
        for (i, l) in punctual.iter().enumerate() {
            choices.push(Choice::Punctual(i as u32));
            power.push(l.power(radius));
        }
        let mut max_radiance: f32 = environment.max_element();
        let mut emissive_triangles = 0;
        // Per material, once: textured emitters weigh by their texture's mean.
        let mean_emission: Vec<f32> =
            scene.materials.iter().map(|m| luminance(m.mean_emission(&scene.images, &scene.textures))).collect();
        for (slot, tri) in scene.triangles.iter().enumerate() {
            let m = &scene.materials[tri.material as usize];
            if !m.is_emissive() {
                continue;
            }
            emissive_triangles += 1;
            let sides = if m.double_sided { 2.0 } else { 1.0 };
            max_radiance = max_radiance.max(m.emissive.max_element());
            choices.push(Choice::Triangle(slot as u32));
            let le = mean_emission[tri.material as usize].max(1e-6);
            power.push(sides * PI * scene.triangle_area(slot as u32) * le);
        }
        if environment.max_element() > 0.0 {
            choices.push(Choice::Environment);
            power.push(PI * 4.0 * PI * radius * radius * luminance(environment).max(1e-6));
        }
        let total: f64 = power.iter().map(|&p| p as f64).sum();
        let mut cdf = Vec::with_capacity(power.len());
        let mut acc = 0.0f64;
        let mut triangle_pmf = vec![0.0; scene.triangles.len()];
        let mut environment_pmf = 0.0;
        for (c, &p) in choices.iter().zip(&power) {
            let pmf = (p as f64 / total) as f32;
            acc += p as f64;
            cdf.push((acc / total) as f32);
            match *c {
                Choice::Triangle(slot) => triangle_pmf[slot as usize] = pmf,
                Choice::Environment => environment_pmf = pmf,
                Choice::Punctual(_) => {}
            }
        }
        if let Some(last) = cdf.last_mut() {
            *last = 1.0;
        }
        Self { punctual, environment, choices, cdf, triangle_pmf, environment_pmf, max_radiance, emissive_triangles }
    }

    pub fn is_empty(&self) -> bool {
        self.choices.is_empty()
    }

    fn choose(&self, u: f32) -> Option<(Choice, f32)> {
        let i = self.cdf.partition_point(|&c| c <= u).min(self.cdf.len().checked_sub(1)?);
        let lo = if i == 0 { 0.0 } else { self.cdf[i - 1] };
        Some((self.choices[i], self.cdf[i] - lo))
    }

    /// Samples a light as seen from `sp` with three uniform numbers.
    pub fn sample<M: ColorModel>(
        &self,
        scene: &Scene,
        sp: &SurfacePoint,
        u: [f32; 3],
        model: &M,
    ) -> Option<LightSample<M::C>> {
        let (choice, pmf) = self.choose(u[0])?;
        if pmf <= 0.0 {
            return None;
        }
        match choice {
            Choice::Punctual(i) => self.sample_punctual(&self.punctual[i as usize], sp.p, pmf, model),
            Choice::Environment => {
                let wi = sample_uniform_sphere([u[1], u[2]]);
                let pdf = pmf / (4.0 * PI);
                let li = model.illuminant(self.environment);
                Some(LightSample { wi, distance: f32::INFINITY, li, pdf, delta: false })
            }
            Choice::Triangle(slot) => sample_triangle(scene, slot, sp.p, pmf, [u[1], u[2]], model),
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

    /// Solid-angle density with which [`Self::sample`] would pick the point `sp_light` on an
    /// emissive triangle, seen from `from` along unit direction `wi`.
    pub fn triangle_pdf(&self, scene: &Scene, from: glam::Vec3, light_point: &SurfacePoint) -> f32 {
        let pmf = self.triangle_pmf.get(light_point.triangle as usize).copied().unwrap_or(0.0);
        if pmf == 0.0 {
            return 0.0;
        }
        let d = light_point.p - from;
        let dist2 = d.length_squared();
        let cos = light_point.ng.dot(d / dist2.sqrt()).abs();
        if cos <= 0.0 {
            return 0.0;
        }
        pmf * dist2 / (cos * scene.triangle_area(light_point.triangle))
    }

    /// Solid-angle density with which [`Self::sample`] picks environment direction.
    pub fn environment_pdf(&self) -> f32 {
        self.environment_pmf / (4.0 * PI)
    }
}

/// Uniform point on an emissive triangle, converted to a solid-angle density at `p`.
fn sample_triangle<M: ColorModel>(
    scene: &Scene,
    slot: u32,
    p: Vec3,
    pmf: f32,
    u: [f32; 2],
    model: &M,
) -> Option<LightSample<M::C>> {
    let tri = &scene.triangles[slot as usize];
    let [i0, i1, i2] = tri.vertices.map(|i| i as usize);
    let [a, b, c] = [scene.positions[i0], scene.positions[i1], scene.positions[i2]];
    let su = u[0].sqrt();
    let bary = Vec3::new(1.0 - su, u[1] * su, (1.0 - u[1]) * su);
    let q = a * bary.x + b * bary.y + c * bary.z;
    let cross = (b - a).cross(c - a);
    let area = 0.5 * cross.length();
    let n = cross / (2.0 * area);
    let d = q - p;
    let dist2 = d.length_squared();
    let dist = dist2.sqrt();
    let wi = d / dist;
    let cos_light = n.dot(-wi);
    let material = &scene.materials[tri.material as usize];
    // One-sided emitters shine from their front (counter-clockwise) face only.
    if cos_light == 0.0 || (cos_light < 0.0 && !material.double_sided) || !wi.is_finite() {
        return None;
    }
    let uv = std::array::from_fn(|s| scene.uv[s][i0] * bary.x + scene.uv[s][i1] * bary.y + scene.uv[s][i2] * bary.z);
    let ctx = TextureContext { images: &scene.images, textures: &scene.textures, uv };
    let li = material.emission_at(&ctx, model);
    let pdf = pmf * dist2 / (cos_light.abs() * area);
    Some(LightSample { wi, distance: dist, li, pdf, delta: false })
}
