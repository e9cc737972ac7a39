//! Reflection models at a surface point, in the local shading frame (+z = shading normal).
//!
//! Every model here has the shape `f = diffuse * wd(wo.h) / pi + Fs(wo.h) D(h) G2 / (4 cos_o cos_i)`:
//! a Lambert lobe weighted by what the specular layer does not reflect, plus a Cook-Torrance
//! microfacet lobe. The models differ only in the Fresnel weights [`Fresnel`].

pub mod fresnel;
pub mod lambert;
pub mod microfacet;
pub mod printed;

use crate::channels::Channels;
use crate::math::reflect;
use glam::Vec3;
pub use microfacet::{Distribution, MIRROR_ALPHA, Microfacet};

/// How the specular layer's reflectance and the diffuse weight depend on `cos = wo.h`.
/// Generic over what a path carries (RGB or hero wavelengths, see [`Channels`]).
#[derive(Clone, Copy, Debug)]
pub enum Fresnel<C = Vec3> {
    /// glTF 2.0 metallic-roughness (Appendix B), with KHR_materials_specular's `fresnel_mix`:
    /// dielectric Schlick with `f0 = min(dielectric_f0 * specular_color, 1)` (`dielectric_f0`
    /// 0.04, or from KHR_materials_ior) and `f90 = 1` scaled by `specular`, mixed by `metallic`
    /// with a conductor whose `f0` is the base colour.
    Gltf { base: C, metallic: f32, specular: f32, specular_f0: C },
    /// Exact dielectric Fresnel with a real relative index of refraction (paper 1).
    Dielectric { eta: f32 },
    /// Exact conductor Fresnel with a complex index `eta + i k` per channel (paper 1).
    Conductor { eta: C, k: C },
}

impl<C: Channels> Fresnel<C> {
    /// True for the glTF model with neither a specular layer nor metal: the surface is plain
    /// Lambert (diffuse weight 1, no specular reflectance at any angle). [`Bsdf::eval`],
    /// [`Bsdf::pdf`] and [`Bsdf::sample`] then skip the half vector and these weights; the full
    /// forms reduce to the same values exactly.
    pub fn is_diffuse_only(&self) -> bool {
        matches!(*self, Fresnel::Gltf { metallic, specular, .. } if metallic == 0.0 && specular == 0.0)
    }

    /// `(diffuse weight, specular reflectance)` at `cos = wo.h`. `cos_bound` is the smallest of
    /// `wo.n` and `wi.n`: the diffuse layer receives what the specular layer lets through at
    /// `wo.h`, but never more than at the more grazing of the two directions (see [`Bsdf::eval`]).
    pub fn weights(&self, cos: f32, cos_bound: f32) -> (C, C) {
        match *self {
            Fresnel::Gltf { .. } if self.is_diffuse_only() => (C::ONE, C::ZERO),
            Fresnel::Gltf { base, metallic, specular, specular_f0 } => {
                let fr = fresnel::schlick(specular_f0, C::ONE, cos);
                let bound = fresnel::schlick(specular_f0, C::ONE, cos_bound);
                let dielectric_diffuse = 1.0 - specular * fr.max(bound).max_element();
                let metal = fresnel::schlick(base, C::ONE, cos);
                let spec = fr * ((1.0 - metallic) * specular) + metal * metallic;
                (C::splat((1.0 - metallic) * dielectric_diffuse), spec)
            }
            Fresnel::Dielectric { eta } => {
                let f = fresnel::dielectric(cos, eta);
                let bound = fresnel::dielectric(cos_bound, eta);
                (C::splat(1.0 - f.max(bound)), C::splat(f))
            }
            Fresnel::Conductor { eta, k } => (C::ZERO, fresnel::conductor(cos, eta, k)),
        }
    }
}

/// A BSDF: a diffuse reflectance, a Fresnel model and a microfacet distribution.
#[derive(Clone, Copy, Debug)]
pub struct Bsdf<C = Vec3> {
    /// Lambert reflectance before the Fresnel diffuse weight.
    pub diffuse: C,
    pub fresnel: Fresnel<C>,
    pub microfacet: Microfacet,
}

/// One direction drawn from a BSDF.
#[derive(Clone, Copy, Debug)]
pub struct BsdfSample<C = Vec3> {
    pub wi: Vec3,
    /// `f(wo, wi) cos(theta_i) / pdf`; for a mirror, the discrete lobe's weight.
    pub weight: C,
    /// Solid-angle density of the whole mixture (for MIS), or the lobe probability for a mirror.
    pub pdf: f32,
    /// True when `wi` came from a perfect mirror: no other strategy can produce it.
    pub delta: bool,
}

impl<C: Channels> Bsdf<C> {
    /// The glTF 2.0 metallic-roughness BSDF; `dielectric_f0` is 0.04 unless KHR_materials_ior
    /// sets another index.
    pub fn gltf(base: C, metallic: f32, roughness: f32, specular: f32, specular_color: C, dielectric_f0: f32) -> Self {
        let metallic = metallic.clamp(0.0, 1.0);
        let roughness = roughness.clamp(0.0, 1.0);
        Self {
            diffuse: base,
            fresnel: Fresnel::Gltf {
                base,
                metallic,
                specular: specular.clamp(0.0, 1.0),
                specular_f0: (specular_color * dielectric_f0).min(C::ONE),
            },
            microfacet: Microfacet::new(Distribution::Ggx, roughness * roughness),
        }
    }

    pub fn is_mirror(&self) -> bool {
        self.microfacet.is_mirror()
    }

    /// True when the BSDF has a non-delta part that light sampling can reach.
    pub fn has_smooth_part(&self) -> bool {
        !self.is_mirror() || self.fresnel.weights(1.0, 1.0).0.max_element() * self.diffuse.max_element() > 0.0
    }

    /// `f(wo, wi)` without any delta component.
    pub fn eval(&self, wo: Vec3, wi: Vec3) -> C {
        if wo.z <= 0.0 || wi.z <= 0.0 {
            return C::ZERO;
        }
        if self.fresnel.is_diffuse_only() {
            return self.diffuse * lambert::eval(wo, wi);
        }
        let h = (wo + wi).normalize();
        // glTF's fresnel_mix weights the diffuse layer by 1 - F(wo.h); on its own that lets
        // smooth dielectrics reflect slightly more than they receive (albedo 1.0004 at 45 degrees).
        // Bounding F from below by its value at the more grazing direction keeps every albedo <= 1
        // and keeps f symmetric in wo and wi.
        let (wd, fs) = self.fresnel.weights(wo.dot(h), wo.z.min(wi.z));
        let mut f = self.diffuse * wd * lambert::eval(wo, wi);
        if !self.is_mirror() && fs.max_element() > 0.0 {
            let m = &self.microfacet;
            // Cook-Torrance: F D G / (4 cos_o cos_i).
            f += fs * (m.d(h) * m.g2(wo, wi) / (4.0 * wo.z * wi.z));
        }
        f
    }

    /// Probability of choosing the specular lobe, from the lobes' reflectance at `wo`.
    fn specular_probability(&self, wo: Vec3) -> f32 {
        let (wd, fs) = self.fresnel.weights(wo.z, wo.z);
        let spec = fs.weight();
        let diff = (self.diffuse * wd).weight();
        if spec + diff <= 0.0 { 0.0 } else { (spec / (spec + diff)).clamp(0.0, 1.0) }
    }

    /// Solid-angle density with which [`Self::sample`] draws `wi` (delta parts excluded).
    pub fn pdf(&self, wo: Vec3, wi: Vec3) -> f32 {
        if wo.z <= 0.0 || wi.z <= 0.0 {
            return 0.0;
        }
        if self.fresnel.is_diffuse_only() {
            return lambert::pdf(wi);
        }
        let ps = self.specular_probability(wo);
        let mut pdf = (1.0 - ps) * lambert::pdf(wi);
        if !self.is_mirror() && ps > 0.0 {
            let h = (wo + wi).normalize();
            let cos = wo.dot(h);
            if cos > 0.0 {
                // Jacobian of reflection: dwi = 4 (wo.h) dh.
                pdf += ps * self.microfacet.pdf_h(wo, h) / (4.0 * cos);
            }
        }
        pdf
    }

    /// Draws a direction by importance sampling `f cos` (lobe choice, then the lobe's own density).
    pub fn sample(&self, wo: Vec3, u_lobe: f32, u: [f32; 2]) -> Option<BsdfSample<C>> {
        if wo.z <= 0.0 {
            return None;
        }
        if self.fresnel.is_diffuse_only() {
            return self.weighted(wo, lambert::sample(u));
        }
        let ps = self.specular_probability(wo);
        if u_lobe < ps {
            if self.is_mirror() {
                let wi = Vec3::new(-wo.x, -wo.y, wo.z);
                let (_, fs) = self.fresnel.weights(wo.z, wo.z);
                return Some(BsdfSample { wi, weight: fs / ps, pdf: ps, delta: true });
            }
            let h = self.microfacet.sample_h(wo, u);
            let wi = reflect(wo, h);
            if wi.z <= 0.0 {
                return None;
            }
            return self.weighted(wo, wi);
        }
        self.weighted(wo, lambert::sample(u))
    }

    fn weighted(&self, wo: Vec3, wi: Vec3) -> Option<BsdfSample<C>> {
        let pdf = self.pdf(wo, wi);
        if pdf <= 0.0 || !pdf.is_finite() {
            return None;
        }
        let weight = self.eval(wo, wi) * wi.z / pdf;
        Some(BsdfSample { wi, weight, pdf, delta: false })
    }
}
