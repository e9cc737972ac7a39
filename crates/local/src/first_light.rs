//! `--quality auto`'s rule for scenes lit only by their own glow.
//!
//! Many glTF assets carry emissive textures (a helmet's visor, a car's tail lamps) but no light:
//! glTF viewers and Blender show them under a default environment, while a path tracer that
//! takes the file at its word renders them nearly black. The rule: when the scene's only light is
//! emission from its own surfaces, no `--env` is given and the quality is `auto`, a quick probe
//! (at most 64 pixels a side, 4 samples each, the render's own camera and settings) looks at what
//! the camera sees. If more than half of the surface it sees (pixels whose camera rays hit
//! something that does not glow itself) shows darker than 4/255 on screen, the scene is lit by a
//! uniform environment of 1, and the user is told so with the way back (`--env 0`). If the
//! camera sits inside a closed mesh (every direction from it meets a surface), no environment
//! could reach what it sees: the user is told that instead, and the scene is left as it is.
//!
//! The probe is a pure function of the scene and the options, so `render` and `submit` decide
//! alike, and the decision travels in the request as the environment it chose.

use crate::options::{EnvArg, QualityArg, RenderOptions, Sampling};
use anyhow::Result;
use tessera_film::linear_to_srgb;
use tessera_render::glam::Vec3;
use tessera_scene::LoadedScene;

/// The probe's longest side, in pixels, and its samples per pixel.
const PROBE_SIDE: u32 = 64;
const PROBE_SPP: u32 = 4;
/// A pixel "shows black" below this display value (8-bit sRGB steps).
const DARK: f32 = 4.0 / 255.0;
/// Directions tried from the camera to tell whether it is shut in.
const ENCLOSURE_RAYS: u32 = 64;

/// What the probe found.
#[derive(Clone, Debug, PartialEq)]
pub enum FirstLight {
    /// The rule does not apply, or the scene's own light shows what the camera sees.
    AsIs,
    /// Too dark: light it with a uniform environment of 1. `dark` is the share of the seen
    /// surface that showed black.
    Environment { dark: f64 },
    /// Too dark, and the camera is inside a closed mesh: no environment would help.
    Enclosed { dark: f64 },
}

/// Applies the rule to `loaded` (the first image's pose) and returns the options to render
/// with: `options` themselves, or with `--env 1` when the scene needs the environment. Says
/// what it did on the log, naming `scene`.
pub fn light_first_render(options: &RenderOptions, loaded: &LoadedScene, scene: &str) -> Result<RenderOptions> {
    let camera = |loaded: &LoadedScene| -> String {
        options
            .settings(&loaded.scene)
            .ok()
            .and_then(|(s, _)| loaded.scene.cameras.get(s.camera).map(|c| c.name.clone()))
            .unwrap_or_default()
    };
    match probe(options, loaded)? {
        FirstLight::AsIs => Ok(options.clone()),
        FirstLight::Environment { dark } => {
            tracing::warn!(
                "{scene}: the scene's only light is its own glow ({} emissive triangles), and {:.0} % of what camera '{}' \
                 sees shows black with it: lighting the scene with a uniform environment of 1, as glTF viewers do \
                 (--quality auto's rule; --env 0 renders it by its own light alone, --env FILE under a map)",
                loaded.scene.lights.emissive_triangles(),
                100.0 * dark,
                camera(loaded)
            );
            let mut lit = options.clone();
            lit.env = Some(EnvArg::Rgb(Vec3::ONE));
            Ok(lit)
        }
        FirstLight::Enclosed { dark } => {
            tracing::warn!(
                "{scene}: camera '{}' is inside a closed mesh (every direction from it meets a surface), and the scene's \
                 own glow leaves {:.0} % of what it sees black: no environment can reach in. Choose another --camera \
                 (the scene has {}; `tessera scene-info` lists them) or move the camera out of the mesh",
                camera(loaded),
                100.0 * dark,
                loaded.scene.cameras.len()
            );
            Ok(options.clone())
        }
    }
}

/// The rule's decision for `loaded` under `options` (see the module's documentation).
pub fn probe(options: &RenderOptions, loaded: &LoadedScene) -> Result<FirstLight> {
    let scene = &loaded.scene;
    let lights = &scene.lights;
    if options.quality != QualityArg::Auto
        || options.env.is_some()
        || !lights.punctual.is_empty()
        || lights.has_environment()
        || lights.emissive_triangles() == 0
    {
        return Ok(FirstLight::AsIs);
    }
    let (mut settings, _) = options.settings(scene)?;
    let scale = PROBE_SIDE as f32 / settings.width.max(settings.height) as f32;
    if scale < 1.0 {
        settings.width = ((settings.width as f32 * scale).round() as u32).max(1);
        settings.height = ((settings.height as f32 * scale).round() as u32).max(1);
    }
    let film = crate::render_film(scene, &settings, Sampling::fixed(PROBE_SPP), 0, &indicatif::ProgressBar::hidden())?;
    let image = film.resolve_with_alpha(true);
    let coverage = image.alpha.as_deref().unwrap_or_default();
    // The surface seen: pixels mostly covered, and not glowing themselves.
    let (mut seen, mut dark) = (0u64, 0u64);
    for (i, rgb) in image.rgb.iter().enumerate() {
        if coverage.get(i).copied().unwrap_or(0.0) < 0.5 || image.emitter[i] >= 0.5 {
            continue;
        }
        seen += 1;
        dark += (rgb.iter().map(|&c| linear_to_srgb(c)).fold(0.0, f32::max) < DARK) as u64;
    }
    if seen == 0 || dark * 2 <= seen {
        return Ok(FirstLight::AsIs);
    }
    let dark = dark as f64 / seen as f64;
    let camera = &scene.cameras[settings.camera];
    let eye = camera.to_world.transform_point3(Vec3::ZERO);
    Ok(if enclosed(scene, eye) { FirstLight::Enclosed { dark } } else { FirstLight::Environment { dark } })
}

/// True when every one of [`ENCLOSURE_RAYS`] directions from `eye`, spread evenly over the
/// sphere (a Fibonacci lattice), meets a surface.
fn enclosed(scene: &tessera_render::Scene, eye: Vec3) -> bool {
    let golden = std::f32::consts::PI * (3.0 - 5f32.sqrt());
    (0..ENCLOSURE_RAYS).all(|i| {
        let z = 1.0 - (2 * i + 1) as f32 / ENCLOSURE_RAYS as f32;
        let r = (1.0 - z * z).max(0.0).sqrt();
        let phi = golden * i as f32;
        let d = Vec3::new(r * libm::cosf(phi), r * libm::sinf(phi), z);
        scene.intersect(eye, d, f32::INFINITY).is_some()
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::options::tests::options;

    /// A quad's two triangles, corners counter-clockwise as seen from the side it faces.
    type Quad = [[f32; 3]; 4];

    /// A horizontal square of half side `s` at height `y`, facing down or up.
    fn level(s: f32, y: f32, down: bool) -> Quad {
        let q = [[-s, y, -s], [s, y, -s], [s, y, s], [-s, y, s]];
        if down { q } else { [q[0], q[3], q[2], q[1]] }
    }

    /// A glTF of white diffuse quads and glowing ones (emissive factor 1, black base), seen by
    /// a camera 3 m up looking straight down.
    fn scene(white: &[Quad], glowing: &[Quad]) -> LoadedScene {
        use base64::Engine;
        let quads: Vec<(&Quad, usize)> = white.iter().map(|q| (q, 0)).chain(glowing.iter().map(|q| (q, 1))).collect();
        let mut bin = Vec::new();
        let (mut views, mut accessors, mut primitives) = (vec![], vec![], vec![]);
        for (k, (q, material)) in quads.iter().enumerate() {
            for i in [0, 1, 2, 0, 2, 3] {
                bin.extend(q[i].iter().flat_map(|f| f.to_le_bytes()));
            }
            let (lo, hi) = (0..3).fold(([f32::MAX; 3], [f32::MIN; 3]), |(mut lo, mut hi), a| {
                for p in q.iter() {
                    lo[a] = lo[a].min(p[a]);
                    hi[a] = hi[a].max(p[a]);
                }
                (lo, hi)
            });
            views.push(format!(r#"{{"buffer":0,"byteOffset":{},"byteLength":72}}"#, k * 72));
            accessors.push(format!(
                r#"{{"bufferView":{k},"componentType":5126,"count":6,"type":"VEC3","min":{lo:?},"max":{hi:?}}}"#
            ));
            primitives.push(format!(r#"{{"attributes":{{"POSITION":{k}}},"material":{material}}}"#));
        }
        let uri = base64::engine::general_purpose::STANDARD.encode(&bin);
        let json = format!(
            r#"{{"asset":{{"version":"2.0"}},"scene":0,"scenes":[{{"nodes":[0,1]}}],
            "nodes":[{{"mesh":0}},{{"camera":0,"translation":[0,3,0],"rotation":[-0.70710677,0,0,0.70710677]}}],
            "cameras":[{{"name":"above","type":"perspective","perspective":{{"yfov":1.0,"znear":0.01}}}}],
            "materials":[{{"pbrMetallicRoughness":{{"baseColorFactor":[0.8,0.8,0.8,1],"metallicFactor":0,"roughnessFactor":1}}}},
                         {{"pbrMetallicRoughness":{{"baseColorFactor":[0,0,0,1],"metallicFactor":0}},"emissiveFactor":[1,1,1]}}],
            "meshes":[{{"primitives":[{}]}}],"accessors":[{}],"bufferViews":[{}],
            "buffers":[{{"byteLength":{},"uri":"data:application/octet-stream;base64,{uri}"}}]}}"#,
            primitives.join(","),
            accessors.join(","),
            views.join(","),
            bin.len()
        );
        tessera_scene::load_bytes(json.as_bytes(), None, "probe.gltf", &Default::default()).unwrap()
    }

    const FLOOR: f32 = 3.0;

    #[test]
    fn a_floor_lit_by_a_speck_is_given_the_environment() {
        // A 2 cm glowing speck 5 m above a white floor: the floor gets about 1e-4 of its light.
        let loaded = scene(&[level(FLOOR, 0.0, false)], &[level(0.01, 5.0, true)]);
        let defaults = options(&["--width", "48", "--height", "32"]);
        let FirstLight::Environment { dark } = probe(&defaults, &loaded).unwrap() else { panic!("not lit") };
        assert!(dark > 0.99, "{dark}");
        let lit = light_first_render(&defaults, &loaded, "probe.gltf").unwrap();
        assert_eq!(lit.env, Some(EnvArg::Rgb(Vec3::ONE)));
        // Only `--quality auto` without an `--env` of its own.
        for flags in [&["--quality", "fixed"][..], &["--env", "0"], &["--env", "0.5,0.5,0.5"]] {
            assert_eq!(probe(&options(flags), &loaded).unwrap(), FirstLight::AsIs, "{flags:?}");
        }
    }

    #[test]
    fn a_floor_lit_by_a_panel_is_left_as_it_is() {
        // A 10 m glowing ceiling 5 m up lights the floor as a Cornell box's light does.
        let loaded = scene(&[level(FLOOR, 0.0, false)], &[level(5.0, 5.0, true)]);
        assert_eq!(probe(&options(&["--width", "48", "--height", "32"]), &loaded).unwrap(), FirstLight::AsIs);
    }

    #[test]
    fn a_camera_shut_in_a_box_is_told_so_and_left_dark() {
        // The speck and the floor inside a closed box around the camera.
        let (s, lo, hi) = (4.0, -1.0, 6.0);
        let wall = |a: [f32; 3], b: [f32; 3], c: [f32; 3], d: [f32; 3]| [a, b, c, d];
        let walls = [
            level(s, lo, false),
            level(s, hi, true),
            wall([-s, lo, -s], [s, lo, -s], [s, hi, -s], [-s, hi, -s]),
            wall([-s, lo, s], [-s, hi, s], [s, hi, s], [s, lo, s]),
            wall([-s, lo, -s], [-s, hi, -s], [-s, hi, s], [-s, lo, s]),
            wall([s, lo, -s], [s, lo, s], [s, hi, s], [s, hi, -s]),
            level(FLOOR, 0.0, false),
        ];
        let loaded = scene(&walls, &[level(0.01, 5.0, true)]);
        let defaults = options(&["--width", "48", "--height", "32"]);
        assert!(matches!(probe(&defaults, &loaded).unwrap(), FirstLight::Enclosed { .. }));
        assert_eq!(light_first_render(&defaults, &loaded, "probe.gltf").unwrap().env, None);
        // Open the lid: the camera sees out, and the environment could reach the floor.
        let open = scene(&[&walls[..1], &walls[2..]].concat(), &[level(0.01, 5.0, true)]);
        assert!(matches!(probe(&defaults, &open).unwrap(), FirstLight::Environment { .. }));
    }
}
