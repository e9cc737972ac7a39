//! Materials as glTF describes them, evaluated at a surface point into a [`Bsdf`].

use crate::bsdf::{Bsdf, Coat, Distribution, Fresnel, Microfacet, Refraction, Sheen};
use crate::channels::{Channels, ColorModel};
use crate::math::luminance;
use crate::spectral::{Spectrum, data};
use crate::texture::{Image, Texture, TextureRef};
use glam::{Vec2, Vec3, Vec4};
use std::any::{Any, TypeId};
use std::cell::Cell;
use std::sync::{Arc, OnceLock};

/// How alpha is used. Blend is rendered as a cut-out at 0.5.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum AlphaMode {
    Opaque,
    Mask { cutoff: f32 },
    Blend,
}

/// Which reflection model a material uses.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Model {
    /// glTF 2.0 metallic-roughness (Appendix B).
    Gltf,
    /// Dimov, Gurov and Penzov's physical Cook-Torrance: exact Fresnel from a complex index `n + i k`
    /// (conductor when any `k > 0`, dielectric otherwise) and a chosen `D`.
    CookTorrance { distribution: Distribution, n: Vec3, k: Vec3 },
}

#[derive(Clone, Debug)]
pub struct Material {
    pub name: String,
    pub base_color: Vec4,
    pub base_color_texture: Option<TextureRef>,
    pub metallic: f32,
    pub roughness: f32,
    pub metallic_roughness_texture: Option<TextureRef>,
    /// Emitted radiance: `emissiveFactor * KHR_materials_emissive_strength`.
    pub emissive: Vec3,
    pub emissive_texture: Option<TextureRef>,
    pub normal_texture: Option<TextureRef>,
    pub normal_scale: f32,
    /// KHR_materials_specular.
    pub specular: f32,
    pub specular_texture: Option<TextureRef>,
    pub specular_color: Vec3,
    pub specular_color_texture: Option<TextureRef>,
    /// KHR_materials_ior: the dielectric's index of refraction, which sets its reflectance at
    /// normal incidence (0.04 at the default 1.5).
    pub ior: f32,
    /// KHR_materials_transmission: the share of the dielectric's diffuse layer that is a
    /// thin-walled BTDF (light through the surface, unbent), times the texture's red channel.
    pub transmission: f32,
    pub transmission_texture: Option<TextureRef>,
    /// KHR_materials_volume: the object is solid, so what it transmits refracts (see
    /// [`Material::refracts`]), and is absorbed on the way through by Beer-Lambert's law.
    pub volume: Option<Volume>,
    /// KHR_materials_anisotropy: how much rougher the specular lobe is along one direction
    /// (times the texture's blue channel; `alpha_t = mix(alpha, 1, strength^2)`), that
    /// direction's angle from the tangent (radians, counter-clockwise towards the bitangent), and
    /// the texture whose red and green channels turn it further, per point.
    pub anisotropy_strength: f32,
    pub anisotropy_rotation: f32,
    pub anisotropy_texture: Option<TextureRef>,
    /// KHR_materials_clearcoat: the clear coat's weight (times the texture's red channel),
    /// roughness (times the roughness texture's green channel) and normal map with its scale.
    /// Without a map of its own the coat keeps the interpolated normal (see
    /// `SurfacePoint::coat_normal`).
    pub clearcoat: f32,
    pub clearcoat_texture: Option<TextureRef>,
    pub clearcoat_roughness: f32,
    pub clearcoat_roughness_texture: Option<TextureRef>,
    pub clearcoat_normal_texture: Option<TextureRef>,
    pub clearcoat_normal_scale: f32,
    /// KHR_materials_sheen: the sheen colour (times its texture, sRGB) and roughness (times the
    /// roughness texture's alpha channel); black is no sheen.
    pub sheen_color: Vec3,
    pub sheen_color_texture: Option<TextureRef>,
    pub sheen_roughness: f32,
    pub sheen_roughness_texture: Option<TextureRef>,
    pub alpha_mode: AlphaMode,
    pub double_sided: bool,
    /// KHR_materials_unlit (see [`Material::make_unlit`]).
    pub unlit: bool,
    pub model: Model,
    /// Measured spectra, used when rendering spectrally.
    pub spectra: MaterialSpectra,
}

/// KHR_materials_volume's medium: light keeps `attenuation_color` of itself over
/// `attenuation_distance` (infinite: no absorption), and `exp(-sigma t)` over a path of length `t`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Volume {
    pub attenuation_color: Vec3,
    pub attenuation_distance: f32,
}

/// Indices of refraction a solid dielectric may have: below 1.001 refraction is all but
/// undefined (the half vector of `wo` and `wi` vanishes), above 10 no material goes.
pub const REFRACTIVE_INDEX: std::ops::RangeInclusive<f32> = 1.001..=10.0;

/// Measured spectral data a material may carry (material extras, built-in scenes). Spectral
/// renders use it; RGB renders use the material's RGB values, which loaders set to match.
#[derive(Clone, Debug, Default)]
pub struct MaterialSpectra {
    /// Reflectance replacing `baseColorFactor` (a base colour texture still multiplies it).
    pub reflectance: Option<Arc<Spectrum>>,
    /// Emission shape; see [`EmissionSpectrum`].
    pub emission: Option<EmissionSpectrum>,
    /// A conductor named in [`data::METALS`]: Fresnel from its measured `n(lambda) + i k(lambda)`.
    pub conductor: Option<&'static str>,
}

impl Material {
    /// Sets the RGB values that RGB renders use to the colours of the measured spectra (the
    /// reflectance under D65; the emission at the emissive colour's luminance), so that RGB and
    /// spectral renders of the material differ only by the transport.
    pub fn match_rgb_to_spectra(&mut self) {
        if let Some(r) = &self.spectra.reflectance {
            self.base_color = Vec3::from_array(crate::spectral::color::reflectance_srgb(r)).extend(self.base_color.w);
        }
        if let Some(e) = &self.spectra.emission {
            self.emissive = e.rgb_with_luminance(luminance(self.emissive));
        }
    }
}

impl MaterialSpectra {
    /// True when a spectral render would differ from an RGB one beyond upsampling: the
    /// material carries a measured spectrum or names a metal.
    pub fn is_spectral(&self) -> bool {
        self.reflectance.is_some() || self.emission.is_some() || self.conductor.is_some()
    }

    /// What the spectral content is, for messages ("conductor Au", "measured reflectance").
    pub fn describe(&self) -> Vec<String> {
        let mut out = Vec::new();
        if let Some(m) = self.conductor {
            out.push(format!("conductor {m}"));
        }
        if self.reflectance.is_some() {
            out.push("measured reflectance".into());
        }
        if self.emission.is_some() {
            out.push("measured emission".into());
        }
        out
    }
}

/// The relative spectral power of an emitter. Its absolute level comes from the material's
/// emissive colour: the spectrum is scaled so that its luminance `Y` is the colour's.
#[derive(Clone, Debug)]
pub struct EmissionSpectrum {
    pub shape: Arc<Spectrum>,
    /// `1 / integral(shape * ybar)`.
    per_luminance: f32,
}

impl EmissionSpectrum {
    /// `None` when the shape has no luminance (nothing visible to scale).
    pub fn new(shape: Arc<Spectrum>) -> Option<Self> {
        let y = &data::cmf()[1];
        let lum = crate::spectral::integrate_1nm(|l| shape.eval(l) * y.eval(l));
        (lum > 0.0 && lum.is_finite()).then(|| Self { shape, per_luminance: (1.0 / lum) as f32 })
    }

    /// Linear sRGB of this emitter at luminance `y` (negative channels, outside the sRGB gamut,
    /// clamped): what RGB renders use for it.
    pub fn rgb_with_luminance(&self, y: f32) -> Vec3 {
        let cmf = data::cmf();
        let scale = self.per_luminance as f64 * y as f64;
        let xyz = [0, 1, 2].map(|c| scale * crate::spectral::integrate_1nm(|l| self.shape.eval(l) * cmf[c].eval(l)));
        let rgb = crate::spectral::color::Primaries::Srgb.from_xyz(xyz);
        Vec3::from_array(rgb.map(|c| c.max(0.0) as f32))
    }
}

impl Default for Material {
    /// glTF's default material (used by primitives without one): white, metallic 1, roughness 1.
    fn default() -> Self {
        Self {
            name: "default".into(),
            base_color: Vec4::ONE,
            base_color_texture: None,
            metallic: 1.0,
            roughness: 1.0,
            metallic_roughness_texture: None,
            emissive: Vec3::ZERO,
            emissive_texture: None,
            normal_texture: None,
            normal_scale: 1.0,
            specular: 1.0,
            specular_texture: None,
            specular_color: Vec3::ONE,
            specular_color_texture: None,
            ior: 1.5,
            transmission: 0.0,
            transmission_texture: None,
            volume: None,
            anisotropy_strength: 0.0,
            anisotropy_rotation: 0.0,
            anisotropy_texture: None,
            clearcoat: 0.0,
            clearcoat_texture: None,
            clearcoat_roughness: 0.0,
            clearcoat_roughness_texture: None,
            clearcoat_normal_texture: None,
            clearcoat_normal_scale: 1.0,
            sheen_color: Vec3::ZERO,
            sheen_color_texture: None,
            sheen_roughness: 0.0,
            sheen_roughness_texture: None,
            alpha_mode: AlphaMode::Opaque,
            double_sided: false,
            unlit: false,
            model: Model::Gltf,
            spectra: MaterialSpectra::default(),
        }
    }
}

/// A scene's materials and the images and textures they read.
#[derive(Default)]
pub struct Surfaces {
    materials: Vec<Material>,
    pub images: Vec<Image>,
    pub textures: Vec<Texture>,
    /// Per material, in RGB, what does not vary over its surface (made on first use).
    rgb: OnceLock<Vec<Constant>>,
}

/// A material's BSDF and emission in RGB where they are the same at every point of it (no
/// texture looked up, and for the BSDF no refraction, whose indices turn with the side met):
/// made once per scene instead of at every vertex of every path, with the same operations.
/// Both hold for points without a vertex colour (white) only, which the callers check.
#[derive(Clone, Copy, Debug)]
struct Constant {
    bsdf: Option<Bsdf<Vec3>>,
    emission: Option<Vec3>,
}

impl Surfaces {
    pub fn new(materials: Vec<Material>, images: Vec<Image>, textures: Vec<Texture>) -> Self {
        Self { materials, images, textures, rgb: OnceLock::new() }
    }

    pub fn materials(&self) -> &[Material] {
        &self.materials
    }

    /// The materials to change; what was made from them is made again on next use.
    pub fn materials_mut(&mut self) -> &mut [Material] {
        self.rgb = OnceLock::new();
        &mut self.materials
    }

    /// What textures are looked up with at a point with UV sets `uv` and vertex colour `color`.
    pub fn context(&self, uv: [Vec2; 2], color: Vec4) -> TextureContext<'_> {
        TextureContext { images: &self.images, textures: &self.textures, uv, color, looked_up: Cell::new(false) }
    }

    /// Material `material`'s emission at a point with vertex colour `color` and the UV sets
    /// `uv` gives: the one made for the whole material where there is one and the colour is
    /// white, else looked up at the point (`uv` is worked out only then).
    pub(crate) fn emission_at<M: ColorModel>(
        &self,
        material: u32,
        uv: impl FnOnce() -> [Vec2; 2],
        color: Vec4,
        model: &M,
    ) -> M::C {
        if color == Vec4::ONE
            && let Some(le) = self.constant_emission::<M::C>(material)
        {
            return le;
        }
        let ctx = self.context(uv(), color);
        self.materials[material as usize].emission_at(&ctx, model)
    }

    /// Material `material`'s BSDF in channels `C` at a point without a vertex colour, where it
    /// was made once for every such point: in RGB, whose channels are the one model's that are
    /// three floats (`Vec3`), the scene's colours unchanged. `None`: make it at the point (a
    /// texture, a refraction, or another colour model). Which model is known when this compiles,
    /// so the check costs nothing.
    pub(crate) fn constant_bsdf<C: Channels>(&self, material: u32) -> Option<Bsdf<C>> {
        if TypeId::of::<C>() != TypeId::of::<Vec3>() {
            return None;
        }
        let bsdf = self.constant_rgb_bsdf(material)?;
        (&bsdf as &dyn Any).downcast_ref::<Bsdf<C>>().copied()
    }

    /// As [`Surfaces::constant_bsdf`], for the material's emission.
    pub(crate) fn constant_emission<C: Channels>(&self, material: u32) -> Option<C> {
        if TypeId::of::<C>() != TypeId::of::<Vec3>() {
            return None;
        }
        let emission = self.constant_rgb_emission(material)?;
        (&emission as &dyn Any).downcast_ref::<C>().copied()
    }

    /// Material `material`'s RGB BSDF at a point without a vertex colour, where it is the same
    /// at every such point.
    pub(crate) fn constant_rgb_bsdf(&self, material: u32) -> Option<Bsdf<Vec3>> {
        self.rgb_constants().get(material as usize)?.bsdf
    }

    /// Material `material`'s RGB emission at a point without a vertex colour, where it is the
    /// same at every such point.
    pub(crate) fn constant_rgb_emission(&self, material: u32) -> Option<Vec3> {
        self.rgb_constants().get(material as usize)?.emission
    }

    fn rgb_constants(&self) -> &[Constant] {
        self.rgb.get_or_init(|| {
            let rgb = crate::channels::Rgb;
            self.materials
                .iter()
                .map(|m| Constant {
                    bsdf: self.without_textures(|ctx| m.bsdf(ctx, &rgb)).filter(|_| !m.refracts()),
                    emission: self.without_textures(|ctx| m.emission_at(ctx, &rgb)),
                })
                .collect()
        })
    }

    /// `f` of a context at no point in particular, where `f` looked no texture up (so that it
    /// gives the same at every point without a vertex colour).
    fn without_textures<T>(&self, f: impl FnOnce(&TextureContext) -> T) -> Option<T> {
        let ctx = self.context([Vec2::ZERO; 2], Vec4::ONE);
        let value = f(&ctx);
        (!ctx.looked_up.get()).then_some(value)
    }
}

/// What a material's textures are looked up with.
pub struct TextureContext<'a> {
    pub images: &'a [Image],
    pub textures: &'a [Texture],
    /// UV sets 0 and 1 at the point.
    pub uv: [Vec2; 2],
    /// The vertex colour at the point (white without one), which multiplies the base colour.
    pub color: Vec4,
    /// Set when a texture was looked up: what was made from the context varies over the surface.
    pub looked_up: Cell<bool>,
}

impl TextureContext<'_> {
    /// Looks a texture up; `None` (no texture) gives `Vec4::ONE`, the neutral factor.
    pub fn lookup(&self, r: &Option<TextureRef>, srgb: bool) -> Vec4 {
        let Some(r) = r else { return Vec4::ONE };
        self.looked_up.set(true);
        let Some(tex) = self.textures.get(r.texture as usize) else {
            return Vec4::ONE;
        };
        let Some(image) = self.images.get(tex.image as usize) else {
            return Vec4::ONE;
        };
        let uv = r.apply_transform(self.uv[(r.texcoord as usize).min(1)]);
        image.sample(uv, tex.wrap_s, tex.wrap_t, srgb)
    }
}

impl Material {
    /// The dielectric layer's reflectance at normal incidence, `((ior - 1) / (ior + 1))^2`
    /// (KHR_materials_ior; computed in f64, so the default ior 1.5 gives exactly `0.04f32`).
    /// True when the material is a solid dielectric that refracts (KHR_materials_volume over
    /// KHR_materials_transmission, glTF's model): its BSDF is [`Bsdf::solid_dielectric`].
    pub fn is_anisotropic(&self) -> bool {
        self.anisotropy_strength > 0.0 && self.model == Model::Gltf && !self.refracts()
    }

    pub fn refracts(&self) -> bool {
        self.volume.is_some() && self.transmission > 0.0 && self.model == Model::Gltf
    }

    /// What the medium inside lets through over a path of length `t`: `c^(t / d)` per channel
    /// for attenuation colour `c` at distance `d` (Beer-Lambert).
    pub fn absorption<M: ColorModel>(&self, t: f32, model: &M) -> Option<M::C> {
        let v = self.volume.as_ref()?;
        if !v.attenuation_distance.is_finite() || v.attenuation_color == Vec3::ONE {
            return None;
        }
        let exponent = t / v.attenuation_distance;
        Some(model.albedo(v.attenuation_color).zip_map(M::C::ONE, |c, _| libm::powf(c.max(0.0), exponent)))
    }

    pub fn dielectric_f0(&self) -> f32 {
        if self.ior == 1.5 {
            return 0.04; // the default, without the division
        }
        let ior = self.ior as f64;
        (((ior - 1.0) / (ior + 1.0)).powi(2)) as f32
    }

    pub fn is_emissive(&self) -> bool {
        self.emissive.max_element() > 0.0
    }

    /// Base colour with alpha at the point: factor, texture (sRGB decoded) and vertex colour.
    pub fn base_color_at(&self, ctx: &TextureContext) -> Vec4 {
        self.base_color * ctx.lookup(&self.base_color_texture, true) * ctx.color
    }

    /// KHR_materials_unlit: the surface shows its base colour (factor, texture and vertex
    /// colour) to every ray that meets it, as emitted radiance, whatever lights it, and reflects
    /// nothing. Being an emitter, it also lights what is near it. Alpha (mask or blend) still
    /// comes from the base colour.
    pub fn make_unlit(&mut self) {
        self.unlit = true;
        self.emissive = self.base_color.truncate();
        self.emissive_texture = self.base_color_texture;
        self.base_color = Vec4::new(0.0, 0.0, 0.0, self.base_color.w);
        (self.metallic, self.specular, self.transmission, self.clearcoat) = (0.0, 0.0, 0.0, 0.0);
        self.sheen_color = Vec3::ZERO;
        self.spectra = MaterialSpectra::default();
    }

    /// Emitted radiance at the point.
    pub fn emission_at<M: ColorModel>(&self, ctx: &TextureContext, model: &M) -> M::C {
        let rgb = self.emissive * ctx.lookup(&self.emissive_texture, true).truncate();
        // An unlit surface's colour is its base colour, which vertex colours multiply.
        let rgb = if self.unlit { rgb * ctx.color.truncate() } else { rgb };
        match &self.spectra.emission {
            Some(e) => model.measured(&e.shape, luminance(rgb) * e.per_luminance, rgb),
            None => model.illuminant(rgb),
        }
    }

    /// True when a ray passes the point: `MASK` cuts away alpha below the cutoff; `BLEND` lets
    /// a ray through with probability `1 - alpha` (stochastic transparency: over many rays the
    /// surface covers `alpha` of what lies behind it), where `u` gives a number in `[0, 1)` that
    /// is a pure function of the ray (drawn only for alpha strictly between 0 and 1).
    pub fn is_cut_out(&self, ctx: &TextureContext, u: impl FnOnce() -> f32) -> bool {
        let alpha = match self.alpha_mode {
            AlphaMode::Opaque => return false,
            AlphaMode::Mask { cutoff } => return self.base_color_at(ctx).w < cutoff,
            AlphaMode::Blend => self.base_color_at(ctx).w,
        };
        alpha <= 0.0 || (alpha < 1.0 && u() >= alpha)
    }

    /// Base colour as the path's channels: the measured reflectance (times the texture and the
    /// vertex colour) when there is one, else the RGB base colour.
    fn base_at<M: ColorModel>(&self, ctx: &TextureContext, model: &M) -> M::C {
        match &self.spectra.reflectance {
            // Without wavelengths `measured` is the factor's RGB stand-in: times the tint, once.
            Some(r) if self.base_color_texture.is_some() || ctx.color != Vec4::ONE => {
                let tint = ctx.lookup(&self.base_color_texture, true).truncate() * ctx.color.truncate();
                model.measured(r, 1.0, self.base_color.truncate()) * model.albedo(tint)
            }
            Some(r) => model.measured(r, 1.0, self.base_color.truncate()),
            None => model.albedo(self.base_color_at(ctx).truncate()),
        }
    }

    /// The BSDF at the point.
    pub fn bsdf<M: ColorModel>(&self, ctx: &TextureContext, model: &M) -> Bsdf<M::C> {
        let base = self.base_at(ctx, model);
        // metallicRoughness texture: roughness in G, metallic in B (linear).
        let mr = ctx.lookup(&self.metallic_roughness_texture, false);
        let roughness = (self.roughness * mr.y).clamp(0.0, 1.0);
        let metallic = (self.metallic * mr.z).clamp(0.0, 1.0);
        match self.model {
            Model::Gltf if self.refracts() => {
                let share = self.transmission * ctx.lookup(&self.transmission_texture, false).x;
                let eta = self.ior.clamp(*REFRACTIVE_INDEX.start(), *REFRACTIVE_INDEX.end());
                Bsdf::solid_dielectric(base, roughness, eta, share)
            }
            Model::Gltf => {
                let specular = self.specular * ctx.lookup(&self.specular_texture, false).w;
                let specular_color = self.specular_color * ctx.lookup(&self.specular_color_texture, true).truncate();
                // KHR_materials_specular allows colours above 1; a reflectance spectrum does not.
                let m = specular_color.max_element().max(1.0);
                let f0 = self.dielectric_f0();
                let mut bsdf =
                    Bsdf::gltf(base, metallic, roughness, specular, model.albedo(specular_color / m) * m, f0);
                if self.transmission > 0.0 {
                    bsdf = bsdf.with_transmission(self.transmission * ctx.lookup(&self.transmission_texture, false).x);
                }
                if self.anisotropy_strength > 0.0 {
                    bsdf =
                        bsdf.with_anisotropy(self.anisotropy_strength * ctx.lookup(&self.anisotropy_texture, false).z);
                }
                if self.sheen_color.max_element() > 0.0 {
                    let color = self.sheen_color * ctx.lookup(&self.sheen_color_texture, true).truncate();
                    let roughness = self.sheen_roughness * ctx.lookup(&self.sheen_roughness_texture, false).w;
                    bsdf = bsdf.with_sheen(model.albedo(color), roughness);
                }
                if self.clearcoat > 0.0 {
                    let weight = self.clearcoat * ctx.lookup(&self.clearcoat_texture, false).x;
                    let roughness = self.clearcoat_roughness * ctx.lookup(&self.clearcoat_roughness_texture, false).y;
                    bsdf = bsdf.with_coat(weight, roughness);
                }
                bsdf
            }
            Model::CookTorrance { distribution, n, k } => {
                let fresnel = match self.spectra.conductor.and_then(data::metal) {
                    Some((n_l, k_l)) => {
                        Fresnel::Conductor { eta: model.measured(n_l, 1.0, n), k: model.measured(k_l, 1.0, k) }
                    }
                    None if k.max_element() > 0.0 => {
                        Fresnel::Conductor { eta: model.optical_constant(n), k: model.optical_constant(k) }
                    }
                    None => Fresnel::Dielectric { eta: n.x.max(1.0 + 1e-4) },
                };
                let diffuse = if matches!(fresnel, Fresnel::Conductor { .. }) { M::C::ZERO } else { base };
                let microfacet = Microfacet::new(distribution, roughness * roughness);
                Bsdf {
                    diffuse,
                    fresnel,
                    microfacet,
                    coat: Coat::NONE,
                    sheen: Sheen::NONE,
                    refraction: Refraction::NONE,
                    compensated: false,
                }
            }
        }
    }

    /// Mean emitted radiance over the emissive texture (the factor alone without one): the
    /// weight of this material's triangles when lights are chosen by power.
    pub fn mean_emission(&self, images: &[Image], textures: &[Texture]) -> Vec3 {
        let mean = self
            .emissive_texture
            .and_then(|r| textures.get(r.texture as usize))
            .and_then(|t| images.get(t.image as usize))
            .map_or(Vec4::ONE, |i| i.mean_value(true));
        self.emissive * mean.truncate()
    }

    /// An upper bound on the material's directional albedo, for `q` in `k_eps` (Dimov, Gurov and Penzov).
    pub fn max_albedo(&self, images: &[Image], textures: &[Texture]) -> f32 {
        let tex_max = |r: &Option<TextureRef>, srgb: bool| -> Vec4 {
            r.and_then(|r| textures.get(r.texture as usize))
                .and_then(|t| images.get(t.image as usize))
                .map_or(Vec4::ONE, |i| i.max_value(srgb))
        };
        let base = (self.base_color * tex_max(&self.base_color_texture, true)).truncate().max_element();
        let metallic = (self.metallic * tex_max(&self.metallic_roughness_texture, false).z).clamp(0.0, 1.0);
        match self.model {
            Model::Gltf => {
                let f0 = self.dielectric_f0();
                let spec = (f0 * self.specular_color.max_element()).min(1.0) * self.specular.clamp(0.0, 1.0);
                let dielectric = base.max(spec).max(f0.min(1.0));
                ((1.0 - metallic) * dielectric + metallic * base).min(1.0)
            }
            Model::CookTorrance { k, .. } if k.max_element() > 0.0 => 1.0,
            Model::CookTorrance { .. } => base.clamp(0.1, 1.0),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::channels::Rgb;
    use crate::texture::{Texels, Wrap};

    #[test]
    fn a_measured_reflectance_with_a_texture_applies_the_texture_once_in_rgb() {
        // A one-texel texture of linear value 0.5 (sRGB 188) under a measured reflectance whose
        // RGB stand-in is 0.6 grey: the RGB base is 0.6 x 0.5, the same as without spectra.
        let images = [Image { width: 1, height: 1, texels: Texels::Eight(vec![[188, 188, 188, 255]]) }];
        let textures = [Texture { image: 0, wrap_s: Wrap::Repeat, wrap_t: Wrap::Repeat }];
        let ctx = TextureContext {
            images: &images,
            textures: &textures,
            uv: [Vec2::ZERO; 2],
            color: Vec4::ONE,
            looked_up: Cell::new(false),
        };
        let mut m = Material {
            base_color: Vec4::new(0.6, 0.6, 0.6, 1.0),
            base_color_texture: Some(TextureRef { texture: 0, texcoord: 0, transform: None }),
            metallic: 0.0,
            ..Material::default()
        };
        let plain = m.base_at(&ctx, &Rgb);
        m.spectra.reflectance = Some(Arc::new(Spectrum::constant(0.6)));
        assert_eq!(m.base_at(&ctx, &Rgb), plain);
        assert!((plain.x - 0.6 * 0.5).abs() < 0.01, "{plain}");
    }

    /// A material's BSDF and emission made once are what a point of it gets, and are made only
    /// where they look no texture up (a one-texel texture of 0.5 here, which the constants would
    /// miss) and, for the BSDF, where nothing refracts; a changed material is made again.
    #[test]
    fn what_is_made_once_per_material_is_what_every_point_gets() {
        let images = vec![Image { width: 1, height: 1, texels: Texels::Eight(vec![[188, 188, 188, 255]]) }];
        let textures = vec![Texture { image: 0, wrap_s: Wrap::Repeat, wrap_t: Wrap::Repeat }];
        let texture = Some(TextureRef { texture: 0, texcoord: 0, transform: None });
        let plain = Material {
            base_color: Vec4::new(0.6, 0.3, 0.2, 1.0),
            emissive: Vec3::new(2.0, 1.0, 0.5),
            roughness: 0.4,
            ..Material::default()
        };
        let textured = Material { base_color_texture: texture, emissive_texture: texture, ..plain.clone() };
        let rough_textured = Material { metallic_roughness_texture: texture, ..plain.clone() };
        let volume = Some(Volume { attenuation_color: Vec3::ONE, attenuation_distance: f32::INFINITY });
        let solid_glass = Material { transmission: 1.0, volume, ..plain.clone() };
        let mut surfaces = Surfaces::new(vec![plain, textured, rough_textured, solid_glass], images, textures);
        let at_a_point = |s: &Surfaces, m: usize| {
            let ctx = s.context([Vec2::new(0.3, 0.7); 2], Vec4::ONE);
            (format!("{:?}", s.materials()[m].bsdf(&ctx, &Rgb)), s.materials()[m].emission_at(&ctx, &Rgb))
        };
        let made = |s: &Surfaces, m: u32| s.constant_rgb_bsdf(m).map(|b| format!("{b:?}"));
        assert_eq!(made(&surfaces, 0), Some(at_a_point(&surfaces, 0).0));
        assert_eq!(surfaces.constant_rgb_emission(0), Some(at_a_point(&surfaces, 0).1));
        assert_eq!((made(&surfaces, 1), surfaces.constant_rgb_emission(1)), (None, None), "textured");
        assert_ne!(at_a_point(&surfaces, 1).0, at_a_point(&surfaces, 0).0, "the texture matters");
        assert_eq!(made(&surfaces, 2), None, "a textured roughness");
        assert_eq!(surfaces.constant_rgb_emission(2), Some(at_a_point(&surfaces, 2).1), "untextured emission");
        assert!(surfaces.materials()[3].refracts());
        assert_eq!(made(&surfaces, 3), None, "refraction turns with the side met");
        assert_eq!(made(&surfaces, 4), None, "no such material");
        surfaces.materials_mut()[0].base_color = Vec4::new(0.1, 0.9, 0.1, 1.0);
        assert_eq!(made(&surfaces, 0), Some(at_a_point(&surfaces, 0).0), "made again after a change");
    }
}
