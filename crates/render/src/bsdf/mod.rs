//! Reflection models at a surface point, in the local shading frame (+z = shading normal).
//!
//! Every model here has the shape `f = diffuse * wd(wo.h) / pi + Fs(wo.h) D(h) G2 / (4 cos_o cos_i)`:
//! a Lambert lobe weighted by what the specular layer does not reflect, plus a Cook-Torrance
//! microfacet lobe. The models differ only in the Fresnel weights [`Fresnel`]. The glTF model
//! gives back what single scattering loses unless told not to ([`energy`]): a multiple-scattering
//! lobe, and the Lambert lobe weighted by the whole specular layer's albedo at both directions.
//!
//! glTF's KHR_materials_transmission replaces a share of the Lambert lobe by a thin-walled
//! microfacet BTDF: the specular lobe mirrored through the surface (without KHR_materials_volume
//! the surface is infinitely thin, so light passes without bending), weighted by the base colour
//! and by what the specular layer does not reflect. Then `wi` may lie below the surface (`z < 0`).
//!
//! With KHR_materials_volume the object is solid: the transmitting share refracts instead
//! ([`Refraction`]). The BSDF is then a dielectric interface with exact Fresnel (total internal
//! reflection included): `F D G2 / (4 cos_o cos_i)` above, and below Walter et al. 2007's rough
//! BTDF `(1 - F) D G2 |wi.h| |wo.h| / (|cos_o| |cos_i| (wo.h + eta wi.h)^2)` tinted by the base
//! colour, with `eta` the index beyond the surface over the index on `wo`'s side. That form carries
//! radiance (it holds the `1 / eta^2` by which radiance thins out leaving a denser medium): the
//! BTDF is reciprocal up to the squared indices, `f(wo, wi) / n_o^2 = f(wi, wo) / n_i^2`.
//!
//! KHR_materials_sheen lays a cloth lobe over that (see [`sheen`]), and KHR_materials_clearcoat a
//! clear dielectric (ior 1.5, its own roughness) over all of it:
//! `f = (1 - c Fc) f_below + c Fc D_c G_c / (4 cos_o cos_i)`, see [`Coat`].

pub mod energy;
pub mod fresnel;
pub mod lambert;
pub mod microfacet;
pub mod printed;
pub mod sheen;

use crate::channels::Channels;
use crate::math::{Frame, reflect, through_surface};
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
    /// Exact dielectric Fresnel with a real relative index of refraction (Dimov, Gurov and Penzov).
    Dielectric { eta: f32 },
    /// Exact conductor Fresnel with a complex index `eta + i k` per channel (Dimov, Gurov and Penzov).
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

/// A BSDF: a diffuse reflectance, a Fresnel model and a microfacet distribution, under an
/// optional clear coat.
#[derive(Clone, Copy, Debug)]
pub struct Bsdf<C = Vec3> {
    /// Lambert reflectance before the Fresnel diffuse weight.
    pub diffuse: C,
    pub fresnel: Fresnel<C>,
    pub microfacet: Microfacet,
    pub coat: Coat,
    pub sheen: Sheen<C>,
    /// The refracting lobe of a solid dielectric ([`Fresnel::Dielectric`] only); none by default.
    pub refraction: Refraction<C>,
    /// The glTF model gives back what single scattering loses ([`energy`]): on for glTF
    /// materials unless `--energy-compensation off`; never for the other models.
    pub compensated: bool,
}

/// KHR_materials_volume with KHR_materials_transmission: `share` of what the dielectric does not
/// reflect refracts into (or out of) the object, tinted by `tint`; the rest is the diffuse lobe.
#[derive(Clone, Copy, Debug)]
pub struct Refraction<C = Vec3> {
    pub share: f32,
    pub tint: C,
}

impl<C: Channels> Refraction<C> {
    pub const NONE: Refraction<C> = Refraction { share: 0.0, tint: C::ZERO };

    pub fn is_on(&self) -> bool {
        self.share > 0.0
    }
}

/// KHR_materials_sheen's layer: `color` times the Charlie lobe, over the base, which loses
/// `max(color) E` to it (E the lobe's albedo at the more grazing of `wo` and `wi`, so that `f`
/// stays reciprocal). A black colour is no sheen.
#[derive(Clone, Copy, Debug)]
pub struct Sheen<C = Vec3> {
    pub color: C,
    pub lobe: sheen::Charlie,
}

impl<C: Channels> Sheen<C> {
    pub const NONE: Self = Self { color: C::ZERO, lobe: sheen::Charlie { roughness: 1.0 } };

    fn is_on(&self) -> bool {
        self.color.max_element() > 0.0
    }

    /// What the layers below keep, for directions with cosines `cos_o` and `cos_i`.
    fn below(&self, cos_o: f32, cos_i: f32) -> f32 {
        1.0 - self.color.max_element() * self.lobe.albedo(cos_o).max(self.lobe.albedo(cos_i))
    }
}

/// KHR_materials_clearcoat's layer: a clear dielectric of index 1.5 (so `f0 = 0.04`) with a GGX
/// lobe of its own roughness, weighted by `weight`. It reflects `weight Fc` and lets the rest
/// through to the layers below. glTF's `fresnel_coat` takes `Fc` at `n.v` for both; here the lobe
/// takes it at `wo.h` and the layers below lose `weight Fc` at the more grazing of `wo.h`, `wo.n`
/// and `wi.n`, as the diffuse layer does under the specular one (see [`Bsdf::eval`]): so `f` stays
/// reciprocal and no albedo exceeds 1.
#[derive(Clone, Copy, Debug)]
pub struct Coat {
    /// The layer's weight in [0, 1]; 0 is no coat.
    pub weight: f32,
    pub microfacet: Microfacet,
    /// The coat's own normal in the BSDF's frame: `+z` unless a normal map bends the layers
    /// below and not the coat (glTF's coat keeps the geometry's normal).
    pub normal: Vec3,
}

impl Coat {
    pub const NONE: Coat = Coat { weight: 0.0, microfacet: Microfacet::new(Distribution::Ggx, 0.0), normal: Vec3::Z };

    /// The frame of the coat's normal, when it is not the BSDF's.
    fn frame(&self) -> Option<Frame> {
        (self.normal != Vec3::Z).then(|| Frame::from_normal(self.normal))
    }

    /// What the coat reflects at `cos`: its weight times Schlick's Fresnel with `f0 = 0.04`.
    pub fn reflectance(&self, cos: f32) -> f32 {
        self.weight * (0.04 + 0.96 * (1.0 - cos.clamp(0.0, 1.0)).powi(5))
    }

    /// What the coat lets through to the layers below, given the cosines it is bounded by (the
    /// smallest reflects the most).
    fn through(&self, cos: f32, cos_bound: f32) -> f32 {
        1.0 - self.reflectance(cos.min(cos_bound))
    }
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
    /// True when the sample went straight through a smooth thin wall ([`Bsdf::straight_through`]).
    pub straight: bool,
}

impl<C> BsdfSample<C> {
    /// True when the sample went straight through a smooth thin wall ([`Bsdf::straight_through`]):
    /// not a bounce, the path goes on along its direction.
    pub fn passes_through(&self) -> bool {
        self.straight
    }
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
            coat: Coat::NONE,
            sheen: Sheen::NONE,
            refraction: Refraction::NONE,
            compensated: true,
        }
    }

    /// This BSDF under KHR_materials_sheen's layer of colour `color` and roughness `roughness`.
    pub fn with_sheen(mut self, color: C, roughness: f32) -> Self {
        if color.max_element() > 0.0 {
            self.sheen = Sheen { color: color.min(C::ONE).max(C::ZERO), lobe: sheen::Charlie::new(roughness) };
        }
        self
    }

    /// This BSDF under KHR_materials_clearcoat's layer of weight `weight` and roughness
    /// `roughness` (both clamped to [0, 1]).
    pub fn with_coat(mut self, weight: f32, roughness: f32) -> Self {
        if weight > 0.0 {
            let roughness = roughness.clamp(0.0, 1.0);
            let microfacet = Microfacet::new(Distribution::Ggx, roughness * roughness);
            self.coat = Coat { weight: weight.min(1.0), microfacet, normal: Vec3::Z };
        }
        self
    }

    /// The coat's own normal, `normal` in this BSDF's frame (ignored without a coat, or when it
    /// does not point into the upper hemisphere).
    pub fn with_coat_normal(mut self, normal: Vec3) -> Self {
        if self.coat.weight > 0.0 && normal.z > 0.0 && normal.is_finite() {
            self.coat.normal = normal.normalize();
        }
        self
    }

    /// True for a plain Lambert surface: no specular layer, metal, transmission or coat.
    /// [`Bsdf::eval`], [`Bsdf::pdf`] and [`Bsdf::sample`] then skip the half vector and the
    /// layers' weights; the full forms reduce to the same values exactly.
    pub(crate) fn is_lambert(&self) -> bool {
        self.fresnel.is_diffuse_only() && self.coat.weight == 0.0 && !self.sheen.is_on()
    }

    /// The glTF BSDF with KHR_materials_transmission's `transmission` (clamped to [0, 1]) of its
    /// dielectric's diffuse layer turned into the thin-walled BTDF; other models are unchanged.
    pub fn with_transmission(mut self, share: f32) -> Self {
        if let Fresnel::Gltf { transmission, .. } = &mut self.fresnel {
            *transmission = if share > 0.0 { share.min(1.0) } else { 0.0 };
        }
        self
    }

    /// True when `wi` below the surface (`z < 0`) can carry light: see [`Fresnel::transmits`] and
    /// [`Refraction`].
    pub fn transmits(&self) -> bool {
        self.fresnel.transmits() || self.refraction.is_on()
    }

    /// A solid dielectric of relative index `eta` (KHR_materials_volume): exact Fresnel
    /// reflection with `roughness` (GGX), and of what it does not reflect, `share` refracting
    /// tinted by `base` and the rest diffuse with reflectance `base`.
    pub fn solid_dielectric(base: C, roughness: f32, eta: f32, share: f32) -> Self {
        let share = share.clamp(0.0, 1.0);
        let roughness = roughness.clamp(0.0, 1.0);
        Self {
            diffuse: base * (1.0 - share),
            fresnel: Fresnel::Dielectric { eta },
            microfacet: Microfacet::new(Distribution::Ggx, roughness * roughness),
            coat: Coat::NONE,
            sheen: Sheen::NONE,
            refraction: Refraction { share, tint: base },
            compensated: false,
        }
    }

    /// KHR_materials_anisotropy: the specular lobe `strength` (clamped to [0, 1]) rougher along
    /// the local +x (until [`Self::with_anisotropy_direction`] turns it): `alpha_t = mix(alpha,
    /// 1, strength^2)` along it, `alpha` across.
    pub fn with_anisotropy(mut self, strength: f32) -> Self {
        let s = strength.clamp(0.0, 1.0);
        let alpha = self.microfacet.alpha;
        if s > 0.0 && self.microfacet.distribution == Distribution::Ggx {
            self.microfacet = Microfacet::anisotropic(alpha + (1.0 - alpha) * s * s, alpha, (1.0, 0.0));
        }
        self
    }

    /// Turns an anisotropic lobe's rough direction to `direction` (local; its part in the
    /// tangent plane counts).
    pub fn with_anisotropy_direction(mut self, direction: Vec3) -> Self {
        let len = (direction.x * direction.x + direction.y * direction.y).sqrt();
        if len > 0.0 && len.is_finite() {
            self.microfacet.direction = (direction.x / len, direction.y / len);
        }
        self
    }

    /// The same dielectric met from its other side: the relative index inverted.
    pub fn from_inside(mut self) -> Self {
        if let Fresnel::Dielectric { eta } = &mut self.fresnel {
            *eta = 1.0 / *eta;
        }
        self
    }

    /// The relative index of a refracting BSDF.
    fn eta(&self) -> f32 {
        match self.fresnel {
            Fresnel::Dielectric { eta } => eta,
            _ => 1.0,
        }
    }

    /// The albedo a denoiser's feature layer takes for this surface (`crate::features`): the
    /// lobes' reflectances at normal incidence, the diffuse under what the specular layer lets
    /// through, plus what transmits, clamped to [0, 1]. A Lambert surface's is its reflectance; a
    /// metal's, its base colour. Not the directional albedo: a colour the network reads, noise free.
    pub fn albedo_hint(&self) -> C {
        let (diffuse, specular) = self.fresnel.weights(1.0, 1.0);
        let mut albedo = self.diffuse * diffuse + specular + self.fresnel.transmitted(1.0);
        if self.refraction.is_on() {
            albedo += self.refraction.tint * (self.refraction.share * (1.0 - specular.max_element()));
        }
        albedo.max(C::ZERO).min(C::ONE)
    }

    pub fn is_mirror(&self) -> bool {
        self.microfacet.is_mirror()
    }

    /// True when the BSDF has a non-delta part that light sampling can reach.
    pub fn has_smooth_part(&self) -> bool {
        !self.is_mirror()
            || self.fresnel.weights(1.0, 1.0).0.max_element() * self.diffuse.max_element() > 0.0
            || self.coat.weight > 0.0 && !self.coat.microfacet.is_mirror()
            || self.sheen.is_on()
    }

    /// `f(wo, wi)` without any delta component.
    pub fn eval(&self, wo: Vec3, wi: Vec3) -> C {
        self.eval_known(wo, wi, Known::NONE)
    }

    /// The BSDF at one `wo`, with what its terms there share worked out once: a path vertex
    /// asks for `f`, the density and a sample at the same `wo` ([`At`]).
    pub fn at(&self, wo: Vec3) -> At<C> {
        let mut known = Known::NONE;
        if wo.z > 0.0 && !self.is_lambert() {
            if self.compensates_isotropic() {
                known.albedo_o = Some(energy::Albedo::of(&self.microfacet, wo.z));
            }
            known.lobes = Some(self.lobe_probabilities(wo, known));
        }
        At { bsdf: *self, wo, known }
    }

    /// [`Self::eval`], with what is `known` at `wo`.
    fn eval_known(&self, wo: Vec3, wi: Vec3, known: Known) -> C {
        if wo.z <= 0.0 || wi.z <= 0.0 {
            if wo.z > 0.0 && wi.z < 0.0 {
                if self.refraction.is_on() {
                    return self.eval_refraction(wo, wi);
                }
                let mut f = self.eval_transmission(wo, wi, known);
                if self.sheen.is_on() {
                    f = f * self.sheen.below(wo.z, -wi.z);
                }
                if self.coat.weight > 0.0 {
                    let (co, ci) = self.coat.frame().map_or((wo, wi), |c| (c.to_local(wo), c.to_local(wi)));
                    f = f * self.coat.through(co.z, -ci.z);
                }
                return f;
            }
            return C::ZERO;
        }
        if self.is_lambert() {
            return self.diffuse * lambert::eval(wo, wi);
        }
        let h = (wo + wi).normalize();
        // glTF's fresnel_mix weights the diffuse layer by 1 - F(wo.h); on its own that lets
        // smooth dielectrics reflect slightly more than they receive (albedo 1.0004 at 45 degrees).
        // Bounding F from below by its value at the more grazing direction keeps every albedo <= 1
        // and keeps f symmetric in wo and wi.
        let (mut wd, fs) = self.fresnel.weights(wo.dot(h), wo.z.min(wi.z));
        let mut ms = C::ZERO;
        if let Some((base_weight, lobe)) = self.compensation(wo.z, wi.z, known) {
            (wd, ms) = (base_weight, lobe);
        }
        let mut f = self.diffuse * wd * lambert::eval(wo, wi) + ms;
        if !self.is_mirror() && fs.max_element() > 0.0 {
            let m = &self.microfacet;
            // Cook-Torrance: F D G / (4 cos_o cos_i).
            f += fs * (m.d(h) * m.g2(wo, wi) / (4.0 * wo.z * wi.z));
        }
        if self.sheen.is_on() {
            f = f * self.sheen.below(wo.z, wi.z) + self.sheen.color * self.sheen.lobe.eval(wo, wi);
        }
        let coat = &self.coat;
        if coat.weight > 0.0 {
            // In the coat's frame (h turns with wo and wi, so wo.h is the same). A tilted coat's
            // lobe is foreshortened by its own cosine, `ci.z`, where the caller multiplies by the
            // BSDF's, `wi.z`: so it divides by `wi.z` (as any shading normal, it is then not
            // reciprocal; with the coat upright `ci = wi`).
            let (co, ci, hc) = coat.frame().map_or((wo, wi, h), |c| (c.to_local(wo), c.to_local(wi), c.to_local(h)));
            f = f * coat.through(wo.dot(h), co.z.min(ci.z));
            if !coat.microfacet.is_mirror() && co.z > 0.0 && ci.z > 0.0 {
                let m = &coat.microfacet;
                f += C::splat(coat.reflectance(wo.dot(h)) * m.d(hc) * m.g2(co, ci) / (4.0 * co.z * wi.z));
            }
        }
        f
    }

    /// The glTF model's energy compensation at `cos_o`, `cos_i` ([`energy`]): the diffuse base's
    /// weight (in place of `fresnel_mix`'s) and the reflected multiple-scattering lobe's value.
    /// `None` for other models, with compensation off, for plain Lambert and for anisotropic
    /// lobes ([`Self::multiple_scattering`]).
    fn compensation(&self, cos_o: f32, cos_i: f32, known: Known) -> Option<(C, C)> {
        let Fresnel::Gltf { base, metallic, specular, specular_f0, transmission } = self.fresnel else { return None };
        let (ao, ai, ms_dielectric, lobe) = self.multiple_scattering(cos_o, cos_i, known)?;
        // What the dielectric layer reflects in all, first bounce and the bounces after it.
        let layer = |e: f32, s: f32| (specular_f0 * (e - s) + C::splat(s)) * specular + ms_dielectric * (1.0 - e);
        let (to, ti, avg) = (layer(ao.e, ao.s), layer(ai.e, ai.s), layer(ao.e_avg, ao.s_avg));
        let through = ((C::ONE - to) * (C::ONE - ti))
            .zip_map(C::ONE - avg, |x, d| if d > 1e-6 { (x / d).clamp(0.0, 1.0) } else { 0.0 });
        let base_weight = through * ((1.0 - metallic) * (1.0 - transmission));
        let ms_metal = base.zip_map(base, |b, _| energy::multiple_scattering_share(b + (1.0 - b) / 21.0, ao.e_avg));
        Some((base_weight, (ms_dielectric * (1.0 - metallic) + ms_metal * metallic) * lobe))
    }

    /// The thin wall's transmitted multiple scattering at `cos_o` and `cos_m` (`wi` mirrored
    /// above the surface): of the light the single-scattering lobe loses, what the dielectric's
    /// own multiple scattering does not reflect ([`Self::compensation`]) passes, tinted as the
    /// single-scattering BTDF is. A white wall then keeps all the light, reflected or passed.
    fn transmitted_compensation(&self, cos_o: f32, cos_m: f32, known: Known) -> Option<C> {
        let Fresnel::Gltf { base, metallic, transmission, .. } = self.fresnel else { return None };
        let (_, _, ms_dielectric, lobe) = self.multiple_scattering(cos_o, cos_m, known)?;
        Some(base * (C::ONE - ms_dielectric) * ((1.0 - metallic) * transmission * lobe))
    }

    /// Whether [`Self::multiple_scattering`] gives back energy: a compensated glTF lobe that is
    /// not diffuse only and not anisotropic.
    fn compensates_isotropic(&self) -> bool {
        matches!(self.fresnel, Fresnel::Gltf { .. })
            && self.compensated
            && !self.fresnel.is_diffuse_only()
            && self.microfacet.alpha == self.microfacet.alpha_across
    }

    /// Kulla and Conty's terms at `cos_o`, `cos_i`: the lobe's albedos at both, the share of the
    /// lost light the dielectric layer reflects (`F_ms` of its average Fresnel) and the
    /// multiple-scattering lobe `(1 - E(cos_o)) (1 - E(cos_i)) / (pi (1 - E_avg))`.
    /// `known.albedo_o`, when given, is the lobe's albedo at `cos_o` ([`Self::at`]).
    fn multiple_scattering(
        &self,
        cos_o: f32,
        cos_i: f32,
        known: Known,
    ) -> Option<(energy::Albedo, energy::Albedo, C, f32)> {
        let Fresnel::Gltf { specular, specular_f0, .. } = self.fresnel else { return None };
        // An anisotropic lobe's albedo turns with the azimuth, which the tables do not hold: it
        // keeps the single-scattering form (the tables at its mean roughness kept 0.89-1.01 of
        // the light of a white brushed metal, against 1 within 0.1 % for isotropic lobes).
        if !self.compensates_isotropic() {
            return None;
        }
        // The lobe probabilities ask at `cos_o` twice: one lookup (the same bits).
        let ao = known.albedo_o.unwrap_or_else(|| energy::Albedo::of(&self.microfacet, cos_o));
        let ai = if cos_i == cos_o { ao } else { energy::Albedo::of(&self.microfacet, cos_i) };
        let f_avg = (specular_f0 + (C::ONE - specular_f0) / 21.0) * specular;
        let ms_dielectric = f_avg.zip_map(f_avg, |f, _| energy::multiple_scattering_share(f, ao.e_avg));
        let lost = 1.0 - ao.e_avg;
        let lobe = if lost > 1e-4 { (1.0 - ao.e) * (1.0 - ai.e) / (std::f32::consts::PI * lost) } else { 0.0 };
        Some((ao, ai, ms_dielectric, lobe))
    }

    /// Turns [`energy`] compensation off (`--energy-compensation off`): glTF's single-scattering
    /// definition, `fresnel_mix` and all.
    pub fn without_compensation(mut self) -> Self {
        self.compensated = false;
        self
    }

    /// The thin-walled BTDF for `wi` below the surface: the specular lobe at `wi` mirrored above
    /// it, `T(wo.h) D(h) G2 / (4 cos_o |cos_i|)`, as KHR_materials_transmission defines it, and
    /// with compensation the light its microfacets pass after more than one bounce.
    fn eval_transmission(&self, wo: Vec3, wi: Vec3, known: Known) -> C {
        if !self.transmits() || self.is_mirror() {
            return C::ZERO;
        }
        let mirrored = through_surface(wi);
        let h = (wo + mirrored).normalize();
        let m = &self.microfacet;
        let single = self.fresnel.transmitted(wo.dot(h)) * (m.d(h) * m.g2(wo, mirrored) / (4.0 * wo.z * mirrored.z));
        match self.transmitted_compensation(wo.z, mirrored.z, known) {
            Some(multiple) => single + multiple,
            None => single,
        }
    }

    /// Walter et al.'s rough BTDF for `wi` below the surface (see the module's notes); zero for a
    /// smooth surface, whose refraction is a delta lobe.
    fn eval_refraction(&self, wo: Vec3, wi: Vec3) -> C {
        let Some((h, cos_o, cos_i, denominator)) = refraction_half(wo, wi, self.eta()) else {
            return C::ZERO;
        };
        if self.is_mirror() {
            return C::ZERO;
        }
        let m = &self.microfacet;
        let t = 1.0 - fresnel::dielectric(cos_o, self.eta());
        let value = t * m.d(h) * m.g2(wo, wi) * (cos_i.abs() * cos_o) / (wo.z * -wi.z * denominator * denominator);
        self.refraction.tint * (self.refraction.share * value)
    }

    /// Probabilities of choosing the specular, the transmission and the coat lobes (the diffuse
    /// and sheen lobes take the rest), from the lobes' weights at `wo`.
    fn lobe_probabilities(&self, wo: Vec3, known: Known) -> Lobes {
        if let Some(lobes) = known.lobes {
            return lobes;
        }
        let (wd, fs) = self.fresnel.weights(wo.z, wo.z);
        let mut spec = fs.weight();
        // The multiple-scattering lobe is drawn cosine-weighted with the diffuse one.
        let mut diff = match self.compensation(wo.z, wo.z, known) {
            Some((base_weight, lobe)) => (self.diffuse * base_weight + lobe * std::f32::consts::PI).weight(),
            None => (self.diffuse * wd).weight(),
        };
        let mut trans = self.fresnel.transmitted(wo.z).weight();
        if self.refraction.is_on() {
            // What the interface does not reflect at `wo`; a rough one refracts through tilted
            // microfacets even beyond the critical angle, so it keeps a floor there.
            let through = wd.max_element();
            let through = if self.is_mirror() { through } else { through.max(0.1) };
            trans = (self.refraction.tint * (self.refraction.share * through)).weight();
        }
        let (mut coat, mut sheen) = (0.0, 0.0);
        if self.sheen.is_on() {
            sheen = (self.sheen.color * self.sheen.lobe.albedo(wo.z)).weight();
            let below = self.sheen.below(wo.z, wo.z);
            (spec, diff, trans) = (spec * below, diff * below, trans * below);
        }
        if self.coat.weight > 0.0 {
            coat = self.coat.reflectance(self.coat.frame().map_or(wo.z, |c| c.to_local(wo).z));
            let below = 1.0 - coat;
            (spec, diff, trans, sheen) = (spec * below, diff * below, trans * below, sheen * below);
        }
        // The sheen lobe is drawn cosine-weighted with the diffuse lobe: it takes its share of
        // what the other lobes leave.
        let total = spec + diff + trans + coat + sheen;
        if total <= 0.0 {
            return Lobes { specular: 0.0, transmission: 0.0, coat: 0.0 };
        }
        let share = |w: f32| (w / total).clamp(0.0, 1.0);
        Lobes { specular: share(spec), transmission: share(trans), coat: share(coat) }
    }

    /// Solid-angle density with which [`Self::sample`] draws `wi` (delta parts excluded).
    pub fn pdf(&self, wo: Vec3, wi: Vec3) -> f32 {
        self.pdf_given(wo, wi, Known::NONE)
    }

    /// [`Self::pdf`], with what is `known` at `wo` (the lobe probabilities [`Self::sample`]
    /// drew with): the same value, without working it out again.
    fn pdf_given(&self, wo: Vec3, wi: Vec3, known: Known) -> f32 {
        let lobes = || self.lobe_probabilities(wo, known);
        if wo.z <= 0.0 || wi.z <= 0.0 {
            if wo.z > 0.0 && wi.z < 0.0 && self.refraction.is_on() && !self.is_mirror() {
                let Some((h, _, cos_i, denominator)) = refraction_half(wo, wi, self.eta()) else {
                    return 0.0;
                };
                // Jacobian of refraction: dh = eta^2 |wi.h| / (wo.h + eta wi.h)^2 dwi.
                let jacobian = self.eta() * self.eta() * cos_i.abs() / (denominator * denominator);
                return lobes().transmission * self.microfacet.pdf_h(wo, h) * jacobian;
            }
            if wo.z > 0.0 && wi.z < 0.0 && self.transmits() && !self.is_mirror() {
                // The transmission lobe draws the mirror image of a reflected direction.
                let mirrored = through_surface(wi);
                return reflection_pdf(&self.microfacet, wo, mirrored, lobes().transmission);
            }
            return 0.0;
        }
        if self.is_lambert() {
            return lambert::pdf(wi);
        }
        let Lobes { specular: ps, transmission: pt, coat: pc } = lobes();
        let mut pdf = (1.0 - ps - pt - pc).max(0.0) * lambert::pdf(wi);
        if !self.is_mirror() && ps > 0.0 {
            pdf += reflection_pdf(&self.microfacet, wo, wi, ps);
        }
        if pc > 0.0 && !self.coat.microfacet.is_mirror() {
            let (co, ci) = self.coat.frame().map_or((wo, wi), |c| (c.to_local(wo), c.to_local(wi)));
            if co.z > 0.0 && ci.z > 0.0 {
                pdf += reflection_pdf(&self.coat.microfacet, co, ci, pc);
            }
        }
        pdf
    }

    /// Draws a direction by importance sampling `f cos` (lobe choice, then the lobe's own density).
    pub fn sample(&self, wo: Vec3, u_lobe: f32, u: [f32; 2]) -> Option<BsdfSample<C>> {
        self.sample_known(wo, u_lobe, u, Known::NONE)
    }

    /// [`Self::sample`], with what is `known` at `wo`.
    fn sample_known(&self, wo: Vec3, u_lobe: f32, u: [f32; 2], known: Known) -> Option<BsdfSample<C>> {
        if wo.z <= 0.0 {
            return None;
        }
        if self.is_lambert() {
            // `weighted` with `pdf` and `eval` cut down to the Lambert lobe (`wo.z > 0` here):
            // the same values, without the general forms' tests and calls.
            let wi = lambert::sample(u);
            return Self::sampled(wi, lambert::pdf(wi), || self.diffuse * lambert::eval(wo, wi));
        }
        let lobes = self.lobe_probabilities(wo, known);
        let Lobes { specular: ps, transmission: pt, coat: pc } = lobes;
        let known = Known { lobes: Some(lobes), ..known };
        let weighted = |wi: Vec3| Self::sampled(wi, self.pdf_given(wo, wi, known), || self.eval_known(wo, wi, known));
        if u_lobe < ps {
            if self.is_mirror() {
                let wi = Vec3::new(-wo.x, -wo.y, wo.z);
                let (_, fs) = self.fresnel.weights(wo.z, wo.z);
                return Some(BsdfSample {
                    wi,
                    weight: fs * self.above_delta(wo) / ps,
                    pdf: ps,
                    delta: true,
                    straight: false,
                });
            }
            let h = self.microfacet.sample_h(wo, u);
            let wi = reflect(wo, h);
            if wi.z <= 0.0 {
                return None;
            }
            return weighted(wi);
        }
        if u_lobe < ps + pt && self.refraction.is_on() {
            let eta = self.eta();
            if self.is_mirror() {
                // Smooth: refraction about the normal, thinned by eta^2 (radiance).
                let wi = refract(wo, Vec3::Z, eta)?;
                let t = 1.0 - fresnel::dielectric(wo.z, eta);
                let weight = self.refraction.tint * (self.refraction.share * t / (eta * eta * pt));
                return Some(BsdfSample { wi, weight, pdf: pt, delta: true, straight: false });
            }
            let wi = refract(wo, self.microfacet.sample_h(wo, u), eta)?;
            if wi.z >= 0.0 {
                return None;
            }
            return weighted(wi);
        }
        if u_lobe < ps + pt {
            // Through the thin wall: a smooth one passes `wo` straight on.
            if self.is_mirror() {
                let weight = self.straight_through(wo) / pt;
                return Some(BsdfSample { wi: -wo, weight, pdf: pt, delta: true, straight: true });
            }
            let reflected = reflect(wo, self.microfacet.sample_h(wo, u));
            if reflected.z <= 0.0 {
                return None;
            }
            return weighted(through_surface(reflected));
        }
        if u_lobe < ps + pt + pc {
            // In the coat's frame, then back.
            let coat = &self.coat;
            let coat_frame = coat.frame();
            let co = coat_frame.map_or(wo, |c| c.to_local(wo));
            if co.z <= 0.0 {
                return None;
            }
            let back = |ci: Vec3| coat_frame.map_or(ci, |c| c.to_world(ci));
            if coat.microfacet.is_mirror() {
                let wi = back(Vec3::new(-co.x, -co.y, co.z));
                let weight = C::splat(coat.reflectance(co.z) / pc);
                return (wi.z > 0.0).then_some(BsdfSample { wi, weight, pdf: pc, delta: true, straight: false });
            }
            let ci = reflect(co, coat.microfacet.sample_h(co, u));
            let wi = back(ci);
            if ci.z <= 0.0 || wi.z <= 0.0 {
                return None;
            }
            return weighted(wi);
        }
        // The rest: the diffuse lobe, and the sheen lobe, both drawn cosine-weighted.
        weighted(lambert::sample(u))
    }

    /// What the coat and the sheen let through to the delta lobes below them, at `wo`.
    fn above_delta(&self, wo: Vec3) -> f32 {
        let mut below = if self.coat.weight > 0.0 {
            let co = self.coat.frame().map_or(wo, |c| c.to_local(wo));
            self.coat.through(co.z, co.z)
        } else {
            1.0
        };
        if self.sheen.is_on() {
            below *= self.sheen.below(wo.z, wo.z);
        }
        below
    }

    /// What passes straight through a smooth thin wall (KHR_materials_transmission at roughness
    /// 0) arriving along `-wo`, on the side `wo.z > 0`: the delta transmission lobe's `f cos`,
    /// which does not bend light. Zero where the BSDF has no such lobe. Shadow rays pass such
    /// walls with this weight, and paths go through them without counting a bounce.
    pub fn straight_through(&self, wo: Vec3) -> C {
        if wo.z <= 0.0 || !self.is_mirror() || !self.transmits() {
            return C::ZERO;
        }
        self.fresnel.transmitted(wo.z) * self.above_delta(wo)
    }

    /// The sample `wi` of density `pdf` (none where that is not positive and finite) and value
    /// `f()`.
    #[inline(always)]
    fn sampled(wi: Vec3, pdf: f32, f: impl FnOnce() -> C) -> Option<BsdfSample<C>> {
        if pdf <= 0.0 || !pdf.is_finite() {
            return None;
        }
        let weight = f() * wi.z.abs() / pdf;
        Some(BsdfSample { wi, weight, pdf, delta: false, straight: false })
    }
}

/// What a BSDF's terms at one `wo` share, worked out once ([`Bsdf::at`]); `None`: not known,
/// worked out where needed. The same values either way, so the same bits.
#[derive(Clone, Copy, Debug)]
struct Known {
    /// The microfacet lobe's albedo at `wo.z` ([`energy::Albedo::of`]).
    albedo_o: Option<energy::Albedo>,
    lobes: Option<Lobes>,
}

impl Known {
    const NONE: Known = Known { albedo_o: None, lobes: None };
}

/// A BSDF at one `wo` ([`Bsdf::at`]): `f`, the density and a sample there, as the BSDF's own
/// methods give them, with the terms they share worked out once.
#[derive(Clone, Copy, Debug)]
pub struct At<C = Vec3> {
    bsdf: Bsdf<C>,
    wo: Vec3,
    known: Known,
}

impl<C: Channels> At<C> {
    /// [`Bsdf::eval`] at this `wo`.
    pub fn eval(&self, wi: Vec3) -> C {
        self.bsdf.eval_known(self.wo, wi, self.known)
    }

    /// [`Bsdf::pdf`] at this `wo`.
    pub fn pdf(&self, wi: Vec3) -> f32 {
        self.bsdf.pdf_given(self.wo, wi, self.known)
    }

    /// [`Bsdf::sample`] at this `wo`.
    pub fn sample(&self, u_lobe: f32, u: [f32; 2]) -> Option<BsdfSample<C>> {
        self.bsdf.sample_known(self.wo, u_lobe, u, self.known)
    }
}

/// Lobe choice probabilities at one `wo` (the diffuse and sheen lobes take what they leave).
#[derive(Clone, Copy, Debug)]
struct Lobes {
    specular: f32,
    transmission: f32,
    coat: f32,
}

/// `wo` (with `wo.h > 0`) refracted through the microfacet with unit normal `h` into a medium of
/// relative index `eta`; `None` under total internal reflection.
pub fn refract(wo: Vec3, h: Vec3, eta: f32) -> Option<Vec3> {
    let cos_o = wo.dot(h);
    let sin2_t = (1.0 - cos_o * cos_o).max(0.0) / (eta * eta);
    if sin2_t >= 1.0 || cos_o <= 0.0 {
        return None;
    }
    let cos_t = (1.0 - sin2_t).sqrt();
    Some((-wo / eta + h * (cos_o / eta - cos_t)).normalize())
}

/// For `wo` above and `wi` below the surface, the microfacet normal that refracts one into the
/// other (Walter et al.'s `h = -(wo + eta wi)`, turned up), `wo.h`, `wi.h` and `wo.h + eta wi.h`;
/// `None` where no microfacet facing `wo` can do it.
fn refraction_half(wo: Vec3, wi: Vec3, eta: f32) -> Option<(Vec3, f32, f32, f32)> {
    let sum = wo + wi * eta;
    if wo.z <= 0.0 || wi.z >= 0.0 || sum.length_squared() == 0.0 {
        return None;
    }
    let h = sum.normalize();
    let h = if h.z < 0.0 { -h } else { h };
    let (cos_o, cos_i) = (wo.dot(h), wi.dot(h));
    let denominator = cos_o + eta * cos_i;
    (cos_o > 0.0 && cos_i < 0.0 && denominator != 0.0).then_some((h, cos_o, cos_i, denominator))
}

/// Density of `wi` reflected about a half vector drawn from `microfacet`, for a lobe chosen with
/// probability `lobe`.
fn reflection_pdf(microfacet: &Microfacet, wo: Vec3, wi: Vec3, lobe: f32) -> f32 {
    let h = (wo + wi).normalize();
    let cos = wo.dot(h);
    // Jacobian of reflection: dwi = 4 (wo.h) dh.
    if cos > 0.0 { lobe * microfacet.pdf_h(wo, h) / (4.0 * cos) } else { 0.0 }
}
