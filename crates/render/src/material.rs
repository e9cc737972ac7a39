//! Materials as glTF describes them, evaluated at a surface point into a [`Bsdf`].

use crate::bsdf::{Bsdf, Distribution, Fresnel, Microfacet};
use crate::texture::{Image, Texture, TextureRef};
use glam::{Vec2, Vec3, Vec4};

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
    /// Paper 1's physical Cook-Torrance: exact Fresnel from a complex index `n + i k`
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
    pub alpha_mode: AlphaMode,
    pub double_sided: bool,
    pub model: Model,
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
            alpha_mode: AlphaMode::Opaque,
            double_sided: false,
            model: Model::Gltf,
        }
    }
}

/// What a material's textures are looked up with.
pub struct TextureContext<'a> {
    pub images: &'a [Image],
    pub textures: &'a [Texture],
    /// UV sets 0 and 1 at the point.
    pub uv: [Vec2; 2],
}

impl TextureContext<'_> {
    /// Looks a texture up; `None` (no texture) gives `Vec4::ONE`, the neutral factor.
    pub fn lookup(&self, r: &Option<TextureRef>, srgb: bool) -> Vec4 {
        let Some(r) = r else { return Vec4::ONE };
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
    pub fn is_emissive(&self) -> bool {
        self.emissive.max_element() > 0.0
    }

    /// Base colour with alpha at the point (sRGB texture decoded).
    pub fn base_color_at(&self, ctx: &TextureContext) -> Vec4 {
        self.base_color * ctx.lookup(&self.base_color_texture, true)
    }

    /// Emitted radiance at the point.
    pub fn emission_at(&self, ctx: &TextureContext) -> Vec3 {
        self.emissive * ctx.lookup(&self.emissive_texture, true).truncate()
    }

    /// True when the point is cut away by the alpha mode.
    pub fn is_cut_out(&self, ctx: &TextureContext) -> bool {
        let cutoff = match self.alpha_mode {
            AlphaMode::Opaque => return false,
            AlphaMode::Mask { cutoff } => cutoff,
            AlphaMode::Blend => 0.5,
        };
        self.base_color_at(ctx).w < cutoff
    }

    /// The BSDF at the point.
    pub fn bsdf(&self, ctx: &TextureContext) -> Bsdf {
        let base = self.base_color_at(ctx).truncate();
        // metallicRoughness texture: roughness in G, metallic in B (linear).
        let mr = ctx.lookup(&self.metallic_roughness_texture, false);
        let roughness = (self.roughness * mr.y).clamp(0.0, 1.0);
        let metallic = (self.metallic * mr.z).clamp(0.0, 1.0);
        match self.model {
            Model::Gltf => {
                let specular = self.specular * ctx.lookup(&self.specular_texture, false).w;
                let specular_color = self.specular_color * ctx.lookup(&self.specular_color_texture, true).truncate();
                Bsdf::gltf(base, metallic, roughness, specular, specular_color)
            }
            Model::CookTorrance { distribution, n, k } => {
                let fresnel = if k.max_element() > 0.0 {
                    Fresnel::Conductor { eta: n, k }
                } else {
                    Fresnel::Dielectric { eta: n.x.max(1.0 + 1e-4) }
                };
                let diffuse = if matches!(fresnel, Fresnel::Conductor { .. }) { Vec3::ZERO } else { base };
                Bsdf { diffuse, fresnel, microfacet: Microfacet::new(distribution, roughness * roughness) }
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

    /// An upper bound on the material's directional albedo, for `q` in `k_eps` (paper 1).
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
                let spec = (0.04 * self.specular_color.max_element()).min(1.0) * self.specular.clamp(0.0, 1.0);
                let dielectric = base.max(spec).max(0.04);
                ((1.0 - metallic) * dielectric + metallic * base).min(1.0)
            }
            Model::CookTorrance { k, .. } if k.max_element() > 0.0 => 1.0,
            Model::CookTorrance { .. } => base.clamp(0.1, 1.0),
        }
    }
}
