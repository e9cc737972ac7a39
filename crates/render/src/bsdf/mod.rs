//! Reflection models at a surface point, in the local shading frame (+z = shading normal).
//!
//! Every model here has the shape `f = diffuse * wd(wo.h) / pi + Fs(wo.h) D(h) G2 / (4 cos_o cos_i)`:
//! a Lambert lobe weighted by what the specular layer does not reflect, plus a Cook-Torrance
//! microfacet lobe. The models differ only in the Fresnel weights [`Fresnel`].
//!
//! glTF's KHR_materials_transmission replaces a share of the Lambert lobe by a thin-walled
//! microfacet BTDF: the specular lobe mirrored through the surface (without KHR_materials_volume
//! the surface is infinitely thin, so light passes without bending), weighted by the base colour
//! and by what the specular layer does not reflect. Then `wi` may lie below the surface (`z < 0`).

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
    /// with a conductor whose `f0` is the base colour. `transmission` (KHR_materials_transmission)
    /// is the share of the dielectric's diffuse layer that is a thin-walled BTDF instead.
    Gltf { base: C, metallic: f32, specular: f32, specular_f0: C, transmission: f32 },
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
        matches!(*self, Fresnel::Gltf { metallic, specular, transmission, .. }
            if metallic == 0.0 && specular == 0.0 && transmission == 0.0)
    }

    /// True when some light passes through the surface (the thin-walled BTDF has weight).
    pub fn transmits(&self) -> bool {
        matches!(*self, Fresnel::Gltf { metallic, transmission, .. } if transmission > 0.0 && metallic < 1.0)
    }

    /// The thin-walled BTDF's weight at `cos = wo.h` (with `h` the half vector of `wo` and `wi`
    /// mirrored back above the surface): the base colour times what the dielectric's specular
    /// layer does not reflect there, times the transmitting share.
    pub fn transmitted(&self, cos: f32) -> C {
        match *self {
            Fresnel::Gltf { base, metallic, specular, specular_f0, transmission } if self.transmits() => {
                let fr = fresnel::schlick(specular_f0, C::ONE, cos).max_element();
                base * ((1.0 - metallic) * transmission * (1.0 - specular * fr))
            }
            _ => C::ZERO,
        }
    }

    /// `(diffuse weight, specular reflectance)` at `cos = wo.h`. `cos_bound` is the smallest of
    /// `wo.n` and `wi.n`: the diffuse layer receives what the specular layer lets through at
    /// `wo.h`, but never more than at the more grazing of the two directions (see [`Bsdf::eval`]).
    pub fn weights(&self, cos: f32, cos_bound: f32) -> (C, C) {
        match *self {
            Fresnel::Gltf { .. } if self.is_diffuse_only() => (C::ONE, C::ZERO),
            Fresnel::Gltf { base, metallic, specular, specular_f0, transmission } => {
                let fr = fresnel::schlick(specular_f0, C::ONE, cos);
                let bound = fresnel::schlick(specular_f0, C::ONE, cos_bound);
                let dielectric_diffuse = 1.0 - specular * fr.max(bound).max_element();
                let metal = fresnel::schlick(base, C::ONE, cos);
                let spec = fr * ((1.0 - metallic) * specular) + metal * metallic;
                let mut diffuse = (1.0 - metallic) * dielectric_diffuse;
                if transmission > 0.0 {
                    diffuse *= 1.0 - transmission;
                }
                (C::splat(diffuse), spec)
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
                transmission: 0.0,
            },
            microfacet: Microfacet::new(Distribution::Ggx, roughness * roughness),
        }
    }

    /// The glTF BSDF with KHR_materials_transmission's `transmission` (clamped to [0, 1]) of its
    /// dielectric's diffuse layer turned into the thin-walled BTDF; other models are unchanged.
    pub fn with_transmission(mut self, share: f32) -> Self {
        if let Fresnel::Gltf { transmission, .. } = &mut self.fresnel {
            *transmission = if share > 0.0 { share.min(1.0) } else { 0.0 };
        }
        self
    }

    /// True when `wi` below the surface (`z < 0`) can carry light: see [`Fresnel::transmits`].
    pub fn transmits(&self) -> bool {
        self.fresnel.transmits()
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
            return if wo.z > 0.0 && wi.z < 0.0 { self.eval_transmission(wo, wi) } else { C::ZERO };
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

    /// The thin-walled BTDF for `wi` below the surface: the specular lobe at `wi` mirrored above
    /// it, `T(wo.h) D(h) G2 / (4 cos_o |cos_i|)`, as KHR_materials_transmission defines it.
    fn eval_transmission(&self, wo: Vec3, wi: Vec3) -> C {
        if !self.transmits() || self.is_mirror() {
            return C::ZERO;
        }
        let mirrored = Vec3::new(wi.x, wi.y, -wi.z);
        let h = (wo + mirrored).normalize();
        let m = &self.microfacet;
        self.fresnel.transmitted(wo.dot(h)) * (m.d(h) * m.g2(wo, mirrored) / (4.0 * wo.z * mirrored.z))
    }

    /// Probabilities of choosing the specular lobe and the transmission lobe (the diffuse lobe
    /// takes the rest), from the lobes' weights at `wo`.
    fn lobe_probabilities(&self, wo: Vec3) -> (f32, f32) {
        let (wd, fs) = self.fresnel.weights(wo.z, wo.z);
        let spec = fs.weight();
        let diff = (self.diffuse * wd).weight();
        let trans = self.fresnel.transmitted(wo.z).weight();
        let total = spec + diff + trans;
        if total <= 0.0 { (0.0, 0.0) } else { ((spec / total).clamp(0.0, 1.0), (trans / total).clamp(0.0, 1.0)) }
    }

    /// Solid-angle density with which [`Self::sample`] draws `wi` (delta parts excluded).
    pub fn pdf(&self, wo: Vec3, wi: Vec3) -> f32 {
        if wo.z <= 0.0 || wi.z <= 0.0 {
            if wo.z > 0.0 && wi.z < 0.0 && self.transmits() && !self.is_mirror() {
                // The transmission lobe draws the mirror image of a reflected direction.
                let mirrored = Vec3::new(wi.x, wi.y, -wi.z);
                return self.reflection_pdf(wo, mirrored, self.lobe_probabilities(wo).1);
            }
            return 0.0;
        }
        if self.fresnel.is_diffuse_only() {
            return lambert::pdf(wi);
        }
        let (ps, pt) = self.lobe_probabilities(wo);
        let mut pdf = (1.0 - ps - pt).max(0.0) * lambert::pdf(wi);
        if !self.is_mirror() && ps > 0.0 {
            pdf += self.reflection_pdf(wo, wi, ps);
        }
        pdf
    }

    /// Density of `wi` reflected about a half vector drawn by the microfacet distribution, for a
    /// lobe chosen with probability `lobe`.
    fn reflection_pdf(&self, wo: Vec3, wi: Vec3, lobe: f32) -> f32 {
        let h = (wo + wi).normalize();
        let cos = wo.dot(h);
        // Jacobian of reflection: dwi = 4 (wo.h) dh.
        if cos > 0.0 { lobe * self.microfacet.pdf_h(wo, h) / (4.0 * cos) } else { 0.0 }
    }

    /// Draws a direction by importance sampling `f cos` (lobe choice, then the lobe's own density).
    pub fn sample(&self, wo: Vec3, u_lobe: f32, u: [f32; 2]) -> Option<BsdfSample<C>> {
        if wo.z <= 0.0 {
            return None;
        }
        if self.fresnel.is_diffuse_only() {
            return self.weighted(wo, lambert::sample(u));
        }
        let (ps, pt) = self.lobe_probabilities(wo);
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
        if u_lobe < ps + pt {
            // Through the thin wall: a smooth one passes `wo` straight on.
            if self.is_mirror() {
                return Some(BsdfSample { wi: -wo, weight: self.fresnel.transmitted(wo.z) / pt, pdf: pt, delta: true });
            }
            let reflected = reflect(wo, self.microfacet.sample_h(wo, u));
            if reflected.z <= 0.0 {
                return None;
            }
            return self.weighted(wo, Vec3::new(reflected.x, reflected.y, -reflected.z));
        }
        self.weighted(wo, lambert::sample(u))
    }

    fn weighted(&self, wo: Vec3, wi: Vec3) -> Option<BsdfSample<C>> {
        let pdf = self.pdf(wo, wi);
        if pdf <= 0.0 || !pdf.is_finite() {
            return None;
        }
        let weight = self.eval(wo, wi) * wi.z.abs() / pdf;
        Some(BsdfSample { wi, weight, pdf, delta: false })
    }
}
