//! Built-in scenes: `cornell-box` (the Cornell University measured geometry, camera and
//! spectra, with the usual RGB reflectances for RGB renders), `furnace` (a sphere of a chosen
//! material or metal in a uniform environment) and `macbeth-scene` (the 24 ColorChecker patches
//! as a lit chart). Parameters follow the name: `builtin:furnace?roughness=0.3&metal=Au`.

use crate::extras::named_metal;
use crate::shapes::{icosphere, quad};
use crate::{LoadError, LoadedScene, SceneInfo};
use std::sync::Arc;
use tessera_render::SceneBuilder;
use tessera_render::bsdf::Distribution;
use tessera_render::glam::{Mat4, Vec3, Vec4};
use tessera_render::spectral::data;
use tessera_render::{Camera, Projection, look_at};
use tessera_render::{EmissionSpectrum, Material, MaterialSpectra, Model};

pub const NAMES: &[&str] =
    &["cornell-box", "furnace", "macbeth-scene", "tiny-light", "glossy-floor", "closed-sphere", "many-lights"];

/// Longest built-in scene spec (its name and parameters), in bytes.
pub const MAX_SPEC_BYTES: usize = 1024;

/// Loads `name[?key=value&...]`.
pub fn load(spec: &str) -> Result<LoadedScene, LoadError> {
    if spec.len() > MAX_SPEC_BYTES {
        let start = spec.char_indices().nth(32).map_or(spec, |(i, _)| &spec[..i]);
        return Err(LoadError::BuiltinParameter {
            name: format!("{start}..."),
            message: format!("its name and parameters are {} bytes, over the {MAX_SPEC_BYTES}-byte limit", spec.len()),
        });
    }
    let (name, query) = spec.split_once('?').unwrap_or((spec, ""));
    let params = Params::parse(name, query)?;
    let loaded = match name {
        "cornell-box" => {
            params.expect_only(&[])?;
            cornell_box()
        }
        "furnace" => furnace(&params)?,
        "macbeth-scene" => {
            params.expect_only(&[])?;
            macbeth_scene()
        }
        "tiny-light" => tiny_light(&params)?,
        "glossy-floor" => glossy_floor(&params)?,
        "closed-sphere" => closed_sphere(&params)?,
        "many-lights" => many_lights(&params)?,
        _ => {
            return Err(LoadError::UnknownBuiltin(name.to_string(), NAMES.join(", ")));
        }
    };
    let hash =
        blake3::hash(format!("tessera builtin v1: {name}?{}", params.canonical()).as_bytes()).to_hex().to_string();
    Ok(LoadedScene { hash, ..loaded })
}

struct Params {
    name: String,
    pairs: Vec<(String, String)>,
}

impl Params {
    fn parse(name: &str, query: &str) -> Result<Self, LoadError> {
        let mut pairs = Vec::new();
        for part in query.split('&').filter(|p| !p.is_empty()) {
            let (k, v) = part.split_once('=').ok_or_else(|| LoadError::BuiltinParameter {
                name: name.to_string(),
                message: format!("'{part}' is not key=value"),
            })?;
            pairs.push((k.to_string(), v.to_string()));
        }
        pairs.sort();
        Ok(Self { name: name.to_string(), pairs })
    }

    fn canonical(&self) -> String {
        self.pairs.iter().map(|(k, v)| format!("{k}={v}")).collect::<Vec<_>>().join("&")
    }

    fn expect_only(&self, keys: &[&str]) -> Result<(), LoadError> {
        match self.pairs.iter().find(|(k, _)| !keys.contains(&k.as_str())) {
            Some((k, _)) => Err(self.error(format!("unknown parameter '{k}' (known: {})", keys.join(", ")))),
            None => Ok(()),
        }
    }

    fn error(&self, message: String) -> LoadError {
        LoadError::BuiltinParameter { name: self.name.clone(), message }
    }

    fn text(&self, key: &str) -> Option<&str> {
        self.pairs.iter().find(|(k, _)| k == key).map(|(_, v)| v.as_str())
    }

    /// A number in `range`, or `default` when absent.
    fn number(&self, key: &str, default: f32, range: std::ops::RangeInclusive<f32>) -> Result<f32, LoadError> {
        let Some((_, v)) = self.pairs.iter().find(|(k, _)| k == key) else {
            return Ok(default);
        };
        let x: f32 = v.parse().map_err(|_| self.error(format!("{key}='{v}' is not a number")))?;
        if !range.contains(&x) {
            return Err(self.error(format!("{key}={x} is outside {}..={}", range.start(), range.end())));
        }
        Ok(x)
    }
}

/// The Cornell box polygons (millimetres; Cornell University Program of Computer Graphics,
/// "Cornell Box Data"), in the right-handed coordinates of the Cornell page: x to the left,
/// y up, z into the box. The light is lowered 0.1 mm below the ceiling.
const CORNELL_POLYGONS: &[(&str, usize, [[f32; 3]; 4])] = &[
    ("floor", 0, [[552.8, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 559.2], [549.6, 0.0, 559.2]]),
    ("ceiling", 0, [[556.0, 548.8, 0.0], [556.0, 548.8, 559.2], [0.0, 548.8, 559.2], [0.0, 548.8, 0.0]]),
    ("light", 3, [[343.0, 548.7, 227.0], [343.0, 548.7, 332.0], [213.0, 548.7, 332.0], [213.0, 548.7, 227.0]]),
    ("back_wall", 0, [[549.6, 0.0, 559.2], [0.0, 0.0, 559.2], [0.0, 548.8, 559.2], [556.0, 548.8, 559.2]]),
    ("right_wall", 1, [[0.0, 0.0, 559.2], [0.0, 0.0, 0.0], [0.0, 548.8, 0.0], [0.0, 548.8, 559.2]]),
    ("left_wall", 2, [[552.8, 0.0, 0.0], [549.6, 0.0, 559.2], [556.0, 548.8, 559.2], [556.0, 548.8, 0.0]]),
    (
        "short_block_face1",
        0,
        [[130.0, 165.0, 65.0], [82.0, 165.0, 225.0], [240.0, 165.0, 272.0], [290.0, 165.0, 114.0]],
    ),
    ("short_block_face2", 0, [[290.0, 0.0, 114.0], [290.0, 165.0, 114.0], [240.0, 165.0, 272.0], [240.0, 0.0, 272.0]]),
    ("short_block_face3", 0, [[130.0, 0.0, 65.0], [130.0, 165.0, 65.0], [290.0, 165.0, 114.0], [290.0, 0.0, 114.0]]),
    ("short_block_face4", 0, [[82.0, 0.0, 225.0], [82.0, 165.0, 225.0], [130.0, 165.0, 65.0], [130.0, 0.0, 65.0]]),
    ("short_block_face5", 0, [[240.0, 0.0, 272.0], [240.0, 165.0, 272.0], [82.0, 165.0, 225.0], [82.0, 0.0, 225.0]]),
    (
        "tall_block_face1",
        0,
        [[423.0, 330.0, 247.0], [265.0, 330.0, 296.0], [314.0, 330.0, 456.0], [472.0, 330.0, 406.0]],
    ),
    ("tall_block_face2", 0, [[423.0, 0.0, 247.0], [423.0, 330.0, 247.0], [472.0, 330.0, 406.0], [472.0, 0.0, 406.0]]),
    ("tall_block_face3", 0, [[472.0, 0.0, 406.0], [472.0, 330.0, 406.0], [314.0, 330.0, 456.0], [314.0, 0.0, 456.0]]),
    ("tall_block_face4", 0, [[314.0, 0.0, 456.0], [314.0, 330.0, 456.0], [265.0, 330.0, 296.0], [265.0, 0.0, 296.0]]),
    ("tall_block_face5", 0, [[265.0, 0.0, 296.0], [265.0, 330.0, 296.0], [423.0, 330.0, 247.0], [423.0, 0.0, 247.0]]),
];

fn diffuse(name: &str, rgb: [f32; 3]) -> Material {
    Material {
        name: name.into(),
        base_color: Vec4::new(rgb[0], rgb[1], rgb[2], 1.0),
        metallic: 0.0,
        roughness: 1.0,
        // Plain Lambert: the glTF model with no specular layer.
        specular: 0.0,
        ..Material::default()
    }
}

/// A Cornell measured spectrum (white, green, red, light).
fn cornell_spectrum(name: &str) -> Arc<tessera_render::spectral::Spectrum> {
    Arc::new(data::cornell(name).expect("the Cornell spectra are shipped").clone())
}

fn cornell_box() -> LoadedScene {
    let mut b = SceneBuilder::new();
    // RGB reflectances and light radiance as in the widely used RGB Cornell box (pbrt, Mitsuba);
    // spectral renders use the measured spectra instead, the light scaled to the RGB light's luminance.
    for (name, rgb) in [("white", [0.725, 0.71, 0.68]), ("green", [0.14, 0.45, 0.091]), ("red", [0.63, 0.065, 0.05])] {
        let spectra = MaterialSpectra { reflectance: Some(cornell_spectrum(name)), ..Default::default() };
        b.add_material(Material { spectra, ..diffuse(name, rgb) });
    }
    let emission = EmissionSpectrum::new(cornell_spectrum("light"));
    b.add_material(Material {
        emissive: Vec3::new(17.0, 12.0, 4.0),
        spectra: MaterialSpectra { reflectance: Some(cornell_spectrum("white")), emission, ..Default::default() },
        ..diffuse("light", [0.78, 0.78, 0.78])
    });
    for (name, material, corners) in CORNELL_POLYGONS {
        let mut c = corners.map(|p| Vec3::from_array(p) * 0.001); // millimetres to metres
        if *name == "light" && (c[1] - c[0]).cross(c[2] - c[0]).y > 0.0 {
            c.reverse(); // the light's front face (counter-clockwise) must face down
        }
        b.add_mesh(name, quad(c, *material as u32), Mat4::IDENTITY).expect("built-in geometry is valid");
    }
    let eye = Vec3::new(0.278, 0.273, -0.800);
    b.cameras.push(Camera {
        name: "cornell".into(),
        to_world: look_at(eye, eye + Vec3::Z, Vec3::Y),
        projection: Projection::Perspective { yfov: 39.307_648f32.to_radians() },
    });
    finish(b, "cornell-box")
}

fn furnace(p: &Params) -> Result<LoadedScene, LoadError> {
    p.expect_only(&["base", "metal", "metallic", "roughness", "specular", "subdivisions"])?;
    let base = p.number("base", 1.0, 0.0..=1.0)?;
    let metallic = p.number("metallic", 0.0, 0.0..=1.0)?;
    let roughness = p.number("roughness", 1.0, 0.0..=1.0)?;
    let specular = p.number("specular", 0.0, 0.0..=1.0)?;
    let subdivisions = p.number("subdivisions", 4.0, 0.0..=7.0)? as u32;
    let mut b = SceneBuilder::new();
    let mut material = Material {
        name: "sphere".into(),
        base_color: Vec4::new(base, base, base, 1.0),
        metallic,
        roughness,
        specular,
        ..Material::default()
    };
    if let Some(name) = p.text("metal") {
        // A measured conductor: Fresnel from n(lambda) + i k(lambda) (base, metallic, specular unused).
        let (metal, n, k) = named_metal(name).map_err(|e| p.error(format!("metal {e}")))?;
        material.model = Model::CookTorrance { distribution: Distribution::Ggx, n, k };
        material.spectra.conductor = Some(metal);
        material.name = metal.to_string();
    }
    let m = b.add_material(material);
    let mut sphere = icosphere(subdivisions, false);
    sphere.material = m;
    b.add_mesh("sphere", sphere, Mat4::IDENTITY).expect("built-in geometry is valid");
    b.environment = Vec3::ONE;
    b.cameras.push(Camera {
        name: "furnace".into(),
        to_world: look_at(Vec3::new(0.0, 0.0, 4.0), Vec3::ZERO, Vec3::Y),
        projection: Projection::Perspective { yfov: 35f32.to_radians() },
    });
    Ok(finish(b, "furnace"))
}

/// Side of one chart patch, metres (the real chart's patches are about 4 cm).
const PATCH: f32 = 0.04;

/// The ColorChecker as Kucherov et al. draws it: 6 x 4 borderless Lambertian patches with the measured
/// reflectances, in chart order from dark skin (top left) to black, under a uniform white (D65
/// when spectral) sky of radiance 1, so a patch's radiance is its reflectance: the chart's
/// colours exactly. The orthographic camera `chart` frames it at 3:2 (render 384 x 256 for
/// Kucherov et al.'s 64-pixel patches); `oblique` looks at it in perspective.
fn macbeth_scene() -> LoadedScene {
    use tessera_render::spectral::chart::{COLUMNS, ROWS};
    let mut b = SceneBuilder::new();
    let (w, h) = (COLUMNS as f32 * PATCH, ROWS as f32 * PATCH);
    for (i, (name, reflectance)) in data::colorchecker().iter().enumerate() {
        let rgb = tessera_render::spectral::color::reflectance_srgb(reflectance);
        let spectra = MaterialSpectra { reflectance: Some(Arc::new(reflectance.clone())), ..Default::default() };
        let m = b.add_material(Material { spectra, ..diffuse(name, rgb) });
        let (col, row) = ((i as u32 % COLUMNS) as f32, (i as u32 / COLUMNS) as f32);
        let (x0, y1) = (col * PATCH - 0.5 * w, 0.5 * h - row * PATCH);
        let corners =
            [[x0, y1 - PATCH], [x0 + PATCH, y1 - PATCH], [x0 + PATCH, y1], [x0, y1]].map(|[x, y]| Vec3::new(x, y, 0.0)); // counter-clockwise seen from +z: faces the camera
        b.add_mesh(name, quad(corners, m), Mat4::IDENTITY).expect("built-in geometry is valid");
    }
    b.environment = Vec3::ONE;
    b.cameras.push(Camera {
        name: "chart".into(),
        to_world: look_at(Vec3::new(0.0, 0.0, 1.0), Vec3::ZERO, Vec3::Y),
        projection: Projection::Orthographic { ymag: 0.5 * h },
    });
    let eye = Vec3::new(0.12, 0.06, 0.35);
    b.cameras.push(Camera {
        name: "oblique".into(),
        to_world: look_at(eye, Vec3::ZERO, Vec3::Y),
        projection: Projection::Perspective { yfov: 40f32.to_radians() },
    });
    finish(b, "macbeth-scene")
}

/// A square of side `side` centred at `centre`, its front face towards the unit `normal`.
fn square(centre: Vec3, normal: Vec3, side: f32, material: u32) -> tessera_render::MeshData {
    let u = if normal.y.abs() > 0.9 { Vec3::X } else { Vec3::Y.cross(normal).normalize() };
    let v = normal.cross(u);
    let h = 0.5 * side;
    // Counter-clockwise seen from the normal's side: u, v, normal is right-handed.
    quad([centre - u * h - v * h, centre + u * h - v * h, centre + u * h + v * h, centre - u * h + v * h], material)
}

fn emitter(radiance: f32) -> Material {
    Material { emissive: Vec3::splat(radiance), ..diffuse("light", [0.0; 3]) }
}

/// Stability suite: a `side` (default 0.02 m) square light of `radiance` (2500) one metre over a
/// grey floor. The collision estimator's walks rarely hit it; light sampling always does.
fn tiny_light(p: &Params) -> Result<LoadedScene, LoadError> {
    p.expect_only(&["side", "radiance"])?;
    let side = p.number("side", 0.02, 1e-4..=2.0)?;
    let radiance = p.number("radiance", 2500.0, 0.0..=1e9)?;
    let mut b = SceneBuilder::new();
    let floor = b.add_material(diffuse("floor", [0.5; 3]));
    let light = b.add_material(emitter(radiance));
    b.add_mesh("floor", square(Vec3::ZERO, Vec3::Y, 2.0, floor), Mat4::IDENTITY).expect("built-in geometry is valid");
    b.add_mesh("light", square(Vec3::Y, Vec3::NEG_Y, side, light), Mat4::IDENTITY).expect("built-in geometry is valid");
    b.cameras.push(Camera {
        name: "above".into(),
        to_world: look_at(Vec3::new(0.0, 2.0, 2.0), Vec3::ZERO, Vec3::Y),
        projection: Projection::Perspective { yfov: 30f32.to_radians() },
    });
    Ok(finish(b, "tiny-light"))
}

/// Stability suite: a metal floor of GGX `roughness` (default 0.05) reflecting a 4 x 2 m panel
/// light of radiance 1 (Veach's classic: light sampling fails on the near-mirror).
fn glossy_floor(p: &Params) -> Result<LoadedScene, LoadError> {
    p.expect_only(&["roughness"])?;
    let roughness = p.number("roughness", 0.05, 0.0..=1.0)?;
    let mut b = SceneBuilder::new();
    let floor = b.add_material(Material {
        name: "metal".into(),
        base_color: Vec4::new(0.9, 0.9, 0.9, 1.0),
        metallic: 1.0,
        roughness,
        ..Material::default()
    });
    let panel = b.add_material(emitter(1.0));
    b.add_mesh("floor", square(Vec3::ZERO, Vec3::Y, 4.0, floor), Mat4::IDENTITY).expect("built-in geometry is valid");
    // Counter-clockwise seen from +z: the panel faces the floor and the camera.
    let c =
        [Vec3::new(-2.0, 0.0, -2.0), Vec3::new(2.0, 0.0, -2.0), Vec3::new(2.0, 2.0, -2.0), Vec3::new(-2.0, 2.0, -2.0)];
    b.add_mesh("panel", quad(c, panel), Mat4::IDENTITY).expect("built-in geometry is valid");
    b.cameras.push(Camera {
        name: "low".into(),
        to_world: look_at(Vec3::new(0.0, 0.5, 2.5), Vec3::ZERO, Vec3::Y),
        projection: Projection::Perspective { yfov: 20f32.to_radians() },
    });
    Ok(finish(b, "glossy-floor"))
}

/// Stability suite: the inside of a unit sphere (flat facets) of `albedo` (default 0.95)
/// emitting `emission` (0.05), seen from its centre: radiance `emission / (1 - albedo)`
/// everywhere, reached only through many bounces as the albedo nears 1.
fn closed_sphere(p: &Params) -> Result<LoadedScene, LoadError> {
    p.expect_only(&["albedo", "emission"])?;
    let albedo = p.number("albedo", 0.95, 0.0..=1.0)?;
    let emission = p.number("emission", 0.05, 0.0..=1e6)?;
    let mut b = SceneBuilder::new();
    let m = b.add_material(Material { emissive: Vec3::splat(emission), ..diffuse("inside", [albedo; 3]) });
    let mut mesh = icosphere(2, true);
    // Flat facets: with interpolated normals a few walks end where a direction the shading
    // normal allows leaves through the facet, a loss that would blur the truncation study.
    (mesh.material, mesh.normals) = (m, None);
    b.add_mesh("sphere", mesh, Mat4::IDENTITY).expect("built-in geometry is valid");
    b.cameras.push(Camera {
        name: "centre".into(),
        to_world: look_at(Vec3::ZERO, Vec3::new(0.3, 0.2, -1.0), Vec3::Y),
        projection: Projection::Perspective { yfov: 90f32.to_radians() },
    });
    Ok(finish(b, "closed-sphere"))
}

/// Many small lights: `count` (default 2048) lanterns, squares of 8 cm glowing downwards in
/// six colours, hung 0.3 to 2.5 m over a 40 x 40 m grey floor among 64 pillars, seen from one
/// end. Their total power stays that of 2048 lanterns of radiance 100 whatever the count. From
/// any point a few nearby lanterns give most of the light: the test bed of the light tree.
fn many_lights(p: &Params) -> Result<LoadedScene, LoadError> {
    p.expect_only(&["count"])?;
    let count = p.number("count", 2048.0, 1.0..=100_000.0)? as u32;
    let mut b = SceneBuilder::new();
    let floor = b.add_material(diffuse("floor", [0.5; 3]));
    let pillar = b.add_material(diffuse("pillar", [0.7, 0.65, 0.6]));
    let radiance = 100.0 * 2048.0 / count as f32;
    let colours =
        [[1.0, 0.55, 0.2], [1.0, 0.85, 0.6], [0.5, 0.7, 1.0], [1.0, 0.3, 0.3], [0.4, 1.0, 0.5], [0.9, 0.9, 0.9]];
    let lanterns: Vec<u32> = colours
        .iter()
        .map(|&c| b.add_material(Material { emissive: Vec3::from(c) * radiance, ..diffuse("lantern", [0.0; 3]) }))
        .collect();
    let add = |b: &mut SceneBuilder, name: &str, mesh| {
        b.add_mesh(name, mesh, Mat4::IDENTITY).expect("built-in geometry is valid")
    };
    add(&mut b, "floor", square(Vec3::ZERO, Vec3::Y, 40.0, floor));
    for i in 0..64 {
        let (x, z) = ((i % 8) as f32 * 5.0 - 17.5, (i / 8) as f32 * 5.0 - 17.5);
        for (normal, offset) in [(Vec3::X, 0.25), (Vec3::NEG_X, 0.25), (Vec3::Z, 0.25), (Vec3::NEG_Z, 0.25)] {
            add(&mut b, "pillar", square(Vec3::new(x, 1.5, z) + normal * offset, normal, 0.5, pillar));
        }
    }
    // A fixed scatter (a 64-bit LCG), so the scene is the same on every machine.
    let mut state = 0x9e37_79b9_7f4a_7c15u64;
    let mut next = || {
        state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        (state >> 40) as f32 / (1u64 << 24) as f32
    };
    for i in 0..count {
        let centre = Vec3::new(next() * 39.0 - 19.5, 0.3 + next() * 2.2, next() * 39.0 - 19.5);
        let colour = lanterns[i as usize % lanterns.len()];
        add(&mut b, "lantern", square(centre, Vec3::NEG_Y, 0.08, colour));
    }
    b.cameras.push(Camera {
        name: "hall".into(),
        to_world: look_at(Vec3::new(0.0, 1.7, 21.0), Vec3::new(0.0, 0.8, 0.0), Vec3::Y),
        projection: Projection::Perspective { yfov: 50f32.to_radians() },
    });
    Ok(finish(b, "many-lights"))
}

fn finish(b: SceneBuilder, name: &str) -> LoadedScene {
    let info = SceneInfo {
        name: name.into(),
        triangles: b.triangle_count(),
        materials: b.materials.len(),
        cameras: b.cameras.iter().map(|c| c.name.clone()).collect(),
        ..Default::default()
    };
    LoadedScene { scene: b.build(), hash: String::new(), info }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A packed scene may be a built-in spec of any length; its refusal quotes a few characters,
    /// not the megabytes (the message went into the log and over gRPC whole).
    #[test]
    fn an_overlong_spec_is_refused_without_quoting_it() {
        let spec = format!("cornell-box#{}", " ".repeat(2 << 20));
        let message = load(&spec).err().expect("refused").to_string();
        assert!(message.len() < 200 && message.contains("1024-byte limit"), "{}", &message[..200.min(message.len())]);
    }
}
