//! Materials and their extensions: glTF's metallic-roughness model with its textures, the KHR
//! material extensions read from their JSON (factors checked, textures present), the `tessera`
//! extras, and which material a primitive takes under a KHR_materials_variants variant.

use crate::extras;
use tessera_render::glam::{Vec3, Vec4};
use tessera_render::{AlphaMode, Material, TextureRef, texture_transform};

pub(super) fn texture_ref(info: Option<gltf::texture::Info>) -> Option<TextureRef> {
    let info = info?;
    let transform = info.texture_transform();
    let texcoord = transform.as_ref().and_then(|t| t.tex_coord()).unwrap_or(info.tex_coord());
    Some(TextureRef {
        texture: info.texture().index() as u32,
        texcoord,
        transform: transform.map(|t| texture_transform(t.offset(), t.rotation(), t.scale())),
    })
}

/// The glTF crate exposes KHR_texture_transform on `textureInfo` but not on
/// `normalTextureInfo`: read the extension's JSON there.
pub(super) fn normal_texture_ref(n: &gltf::material::NormalTexture) -> TextureRef {
    json_texture_ref(n.texture().index() as u32, n.tex_coord(), n.extension_value("KHR_texture_transform"))
}

/// A texture reference from a texture index, its `texCoord` and the JSON of its
/// KHR_texture_transform (which may name another `texCoord`).
pub(super) fn json_texture_ref(texture: u32, texcoord: u32, transform: Option<&serde_json::Value>) -> TextureRef {
    let pair = |key: &str, default: [f32; 2]| -> [f32; 2] {
        transform
            .and_then(|e| e.get(key))
            .and_then(|v| v.as_array())
            .filter(|a| a.len() == 2)
            .and_then(|a| Some([a[0].as_f64()? as f32, a[1].as_f64()? as f32]))
            .unwrap_or(default)
    };
    let rotation = transform.and_then(|e| e.get("rotation")).and_then(|v| v.as_f64()).unwrap_or(0.0) as f32;
    let own_texcoord = transform.and_then(|e| e.get("texCoord")).and_then(|v| v.as_u64()).map(|t| t as u32);
    TextureRef {
        texture,
        texcoord: own_texcoord.unwrap_or(texcoord),
        transform: transform
            .map(|_| texture_transform(pair("offset", [0.0, 0.0]), rotation, pair("scale", [1.0, 1.0]))),
    }
}

/// A material extension's JSON, for extensions the glTF crate does not parse (null when the
/// material does not use it, so every value takes its default): factors are checked to lie in
/// [0, 1] and textures to exist (`textures` of them).
pub(super) struct ExtensionJson<'a> {
    name: &'static str,
    json: &'a serde_json::Value,
    textures: usize,
}

impl<'a> ExtensionJson<'a> {
    fn of(m: &'a gltf::Material, name: &'static str, textures: usize) -> Self {
        const ABSENT: serde_json::Value = serde_json::Value::Null;
        Self { name, json: m.extension_value(name).unwrap_or(&ABSENT), textures }
    }

    fn factor(&self, key: &str, default: f32) -> Result<f32, String> {
        self.number(key, default, |f| (0.0..=1.0).contains(&f), "a number between 0 and 1")
    }

    /// A number that `valid` accepts, or `default` when absent; the error says it should be
    /// `expected`.
    fn number(&self, key: &str, default: f32, valid: impl Fn(f64) -> bool, expected: &str) -> Result<f32, String> {
        match self.json.get(key) {
            None => Ok(default),
            Some(v) => match v.as_f64() {
                Some(f) if valid(f) => Ok(f as f32),
                _ => Err(format!("{} {key} {v} is not {expected}", self.name)),
            },
        }
    }

    /// An RGB factor, black by default.
    fn color(&self, key: &str) -> Result<Vec3, String> {
        let Some(v) = self.json.get(key) else { return Ok(Vec3::ZERO) };
        let rgb = v.as_array().filter(|a| a.len() == 3).and_then(|a| {
            let c: Vec<f64> = a.iter().filter_map(|c| c.as_f64()).filter(|c| (0.0..=1.0).contains(c)).collect();
            (c.len() == 3).then(|| Vec3::new(c[0] as f32, c[1] as f32, c[2] as f32))
        });
        rgb.ok_or_else(|| format!("{} {key} {v} is not three numbers between 0 and 1", self.name))
    }

    /// A normal texture's `scale` (1 by default): any finite number.
    fn texture_scale(&self, key: &str) -> Result<f32, String> {
        match self.json.get(key).and_then(|info| info.get("scale")) {
            None => Ok(1.0),
            Some(v) => v
                .as_f64()
                .map(|s| s as f32)
                .filter(|s| s.is_finite())
                .ok_or_else(|| format!("{} {key} scale {v} is not a finite number", self.name)),
        }
    }

    fn texture(&self, key: &str) -> Result<Option<TextureRef>, String> {
        let Some(info) = self.json.get(key) else { return Ok(None) };
        let index = info.get("index").and_then(|i| i.as_u64()).filter(|&i| (i as usize) < self.textures);
        let Some(index) = index else {
            return Err(format!("{} {key} names no texture of the {} in the file", self.name, self.textures));
        };
        let texcoord = match info.get("texCoord") {
            None => 0,
            Some(t) => t.as_u64().filter(|&t| t < 2).ok_or(format!("{} {key}: texCoord {t}", self.name))?,
        };
        let transform = info.get("extensions").and_then(|e| e.get("KHR_texture_transform"));
        Ok(Some(json_texture_ref(index as u32, texcoord as u32, transform)))
    }
}

/// KHR_materials_volume: a solid when `thicknessFactor` is above 0 (0, the default, is a thin
/// wall), with its attenuation colour and distance (absent: none). The thickness itself (and its
/// texture) only approximates the geometry for rasterisers: a path tracer has the geometry.
pub(super) fn volume(e: &ExtensionJson) -> Result<Option<tessera_render::Volume>, String> {
    let thickness = e.number("thicknessFactor", 0.0, |t| t.is_finite() && t >= 0.0, "a number >= 0")?;
    e.texture("thicknessTexture")?;
    let attenuation_distance =
        e.number("attenuationDistance", f32::INFINITY, |d| d > 0.0 && (d as f32).is_finite(), "a positive number")?;
    let attenuation_color =
        if e.json.get("attenuationColor").is_some() { e.color("attenuationColor")? } else { Vec3::ONE };
    Ok((thickness > 0.0).then_some(tessera_render::Volume { attenuation_color, attenuation_distance }))
}

pub(super) fn convert_material(m: &gltf::Material, textures: usize) -> Result<Material, String> {
    let pbr = m.pbr_metallic_roughness();
    let coat = ExtensionJson::of(m, "KHR_materials_clearcoat", textures);
    let sheen = ExtensionJson::of(m, "KHR_materials_sheen", textures);
    let anisotropy = ExtensionJson::of(m, "KHR_materials_anisotropy", textures);
    let strength = m.emissive_strength().unwrap_or(1.0);
    let specular = m.specular();
    let finite = |v: f32, what: &str| {
        if v.is_finite() { Ok(v) } else { Err(format!("{what} is not finite")) }
    };
    let extras = extras::parse(m.extras().as_ref().map(|r| r.get()))?;
    let mut material = Material {
        name: m.name().unwrap_or("").to_string(),
        base_color: Vec4::from_array(pbr.base_color_factor()),
        base_color_texture: texture_ref(pbr.base_color_texture()),
        metallic: finite(pbr.metallic_factor(), "metallicFactor")?,
        roughness: finite(pbr.roughness_factor(), "roughnessFactor")?,
        metallic_roughness_texture: texture_ref(pbr.metallic_roughness_texture()),
        emissive: Vec3::from_array(m.emissive_factor()) * finite(strength, "emissiveStrength")?.max(0.0),
        emissive_texture: texture_ref(m.emissive_texture()),
        normal_texture: m.normal_texture().map(|n| normal_texture_ref(&n)),
        normal_scale: m.normal_texture().map_or(1.0, |n| n.scale()),
        specular: specular.as_ref().map_or(1.0, |s| s.specular_factor()),
        specular_texture: specular.as_ref().and_then(|s| texture_ref(s.specular_texture())),
        specular_color: specular.as_ref().map_or(Vec3::ONE, |s| Vec3::from_array(s.specular_color_factor())),
        specular_color_texture: specular.as_ref().and_then(|s| texture_ref(s.specular_color_texture())),
        ior: match m.ior() {
            Some(ior) if !(ior.is_finite() && ior >= 0.0) => {
                return Err(format!("ior {ior} is not a finite number >= 0"));
            }
            ior => ior.unwrap_or(1.5),
        },
        // The glTF crate parses KHR_materials_transmission (and checks its texture's index).
        transmission: match m.transmission().map(|t| t.transmission_factor()) {
            Some(t) if !(0.0..=1.0).contains(&t) => {
                return Err(format!("transmissionFactor {t} is not a number between 0 and 1"));
            }
            t => t.unwrap_or(0.0),
        },
        transmission_texture: m.transmission().and_then(|t| texture_ref(t.transmission_texture())),
        clearcoat: coat.factor("clearcoatFactor", 0.0)?,
        clearcoat_texture: coat.texture("clearcoatTexture")?,
        clearcoat_roughness: coat.factor("clearcoatRoughnessFactor", 0.0)?,
        clearcoat_roughness_texture: coat.texture("clearcoatRoughnessTexture")?,
        clearcoat_normal_texture: coat.texture("clearcoatNormalTexture")?,
        clearcoat_normal_scale: coat.texture_scale("clearcoatNormalTexture")?,
        sheen_color: sheen.color("sheenColorFactor")?,
        sheen_color_texture: sheen.texture("sheenColorTexture")?,
        sheen_roughness: sheen.factor("sheenRoughnessFactor", 0.0)?,
        sheen_roughness_texture: sheen.texture("sheenRoughnessTexture")?,
        volume: volume(&ExtensionJson::of(m, "KHR_materials_volume", textures))?,
        anisotropy_strength: anisotropy.factor("anisotropyStrength", 0.0)?,
        anisotropy_rotation: anisotropy.number(
            "anisotropyRotation",
            0.0,
            |r| (r as f32).is_finite(),
            "a finite number of radians",
        )?,
        anisotropy_texture: anisotropy.texture("anisotropyTexture")?,
        alpha_mode: match m.alpha_mode() {
            gltf::material::AlphaMode::Opaque => AlphaMode::Opaque,
            gltf::material::AlphaMode::Mask => AlphaMode::Mask { cutoff: m.alpha_cutoff().unwrap_or(0.5) },
            gltf::material::AlphaMode::Blend => AlphaMode::Blend,
        },
        double_sided: m.double_sided(),
        unlit: false,
        model: extras.model.unwrap_or(tessera_render::Model::Gltf),
        spectra: extras.spectra,
    };
    // A measured reflectance replaces baseColorFactor; an emission spectrum sets the colour and
    // the factor the luminance. RGB renders use their colours.
    material.match_rgb_to_spectra();
    if m.extension_value("KHR_materials_unlit").is_some() {
        material.make_unlit();
    }
    Ok(material)
}

/// How a primitive's material is chosen: its KHR_materials_variants mapping for `variant` when it
/// has one, else its own, else `default`; `count` materials are in the file.
#[derive(Clone, Copy)]
pub(super) struct Materials {
    pub(super) default: u32,
    pub(super) count: usize,
    pub(super) variant: Option<usize>,
}

impl Materials {
    pub(super) fn of(&self, prim: &gltf::Primitive, mesh: &str) -> Result<u32, String> {
        let own = prim.material().index().map_or(self.default, |i| i as u32);
        let Some(variant) = self.variant else { return Ok(own) };
        let mappings = prim.extension_value("KHR_materials_variants").and_then(|v| v.get("mappings"));
        let Some(mappings) = mappings.and_then(|m| m.as_array()) else { return Ok(own) };
        for m in mappings {
            let names_it = m
                .get("variants")
                .and_then(|v| v.as_array())
                .is_some_and(|v| v.iter().any(|i| i.as_u64() == Some(variant as u64)));
            if names_it {
                return m
                    .get("material")
                    .and_then(|i| i.as_u64())
                    .filter(|&i| (i as usize) < self.count)
                    .map(|i| i as u32)
                    .ok_or_else(|| {
                        format!(
                            "mesh '{mesh}': a KHR_materials_variants mapping names no material of the {}",
                            self.count
                        )
                    });
            }
        }
        Ok(own)
    }
}

/// The names of the file's material variants (KHR_materials_variants), in index order.
pub(super) fn variant_names(document: &gltf::Document) -> Result<Vec<String>, String> {
    let Some(v) = document.extension_value("KHR_materials_variants") else { return Ok(Vec::new()) };
    let list = v.get("variants").and_then(|l| l.as_array()).ok_or("KHR_materials_variants has no variants list")?;
    list.iter()
        .enumerate()
        .map(|(i, v)| {
            v.get("name").and_then(|n| n.as_str()).map(str::to_string).ok_or(format!("variant {i} has no name"))
        })
        .collect()
}
