//! Environment maps: a Lambertian plane under a map against the irradiance computed here by
//! quadrature over the map, and light sampling with MIS against BSDF sampling alone on a glossy
//! sphere. Fixed seeds; 3 standard errors of 16 independent renders (99.1% confidence).

mod common;

use common::{Replicated, replicated_mean, settings};
use std::f32::consts::PI;
use std::sync::Arc;
use tessera_render::EnvMap;
use tessera_render::Material;
use tessera_render::glam::{Mat4, Vec3, Vec4};
use tessera_render::{Camera, Projection, look_at};
use tessera_render::{Estimator, RenderSettings, SceneBuilder, Termination};
use tessera_scene::shapes::{icosphere, quad};

/// A blue-grey sky brightening towards the horizon, with a small warm sun 54 degrees from the
/// zenith, 64 x 32.
fn sunny() -> Arc<EnvMap> {
    let (w, h) = (64, 32);
    let texels: Vec<[f32; 3]> = (0..w * h)
        .map(|k| {
            let (i, j) = (k % w, k / w);
            if (20..22).contains(&i) && (9..11).contains(&j) {
                [300.0, 260.0, 200.0]
            } else {
                [0.3 + j as f32 / 80.0, 0.4, 0.6]
            }
        })
        .collect();
    Arc::new(EnvMap::new(w, h, &texels, 1.0, 25.0).unwrap())
}

fn lit(mut b: SceneBuilder, map: &Arc<EnvMap>) -> tessera_render::Scene {
    b.cameras.push(Camera {
        name: "view".into(),
        to_world: look_at(Vec3::new(0.0, 1.0, 3.0), Vec3::ZERO, Vec3::Y),
        projection: Projection::Perspective { yfov: 40f32.to_radians() },
    });
    let mut scene = b.build();
    scene.lights = scene.light_set(Vec::new(), Vec3::ZERO, Some(map.clone()));
    scene
}

fn assert_agree(what: &str, a: &Replicated, b: &Replicated) {
    let se = (a.se * a.se + b.se * b.se).sqrt();
    assert!((a.mean - b.mean).abs() <= 3.0 * se, "{what}: {} +- {} against {} +- {}", a.mean, a.se, b.mean, b.se);
}

#[test]
fn a_lambertian_plane_reflects_the_irradiance_of_the_map() {
    let map = sunny();
    let albedo = 0.5;
    let mut b = SceneBuilder::new();
    let m = b.add_material(Material {
        name: "white".into(),
        base_color: Vec4::new(albedo, albedo, albedo, 1.0),
        metallic: 0.0,
        specular: 0.0,
        ..Material::default()
    });
    let s = 4.0;
    b.add_mesh(
        "plane",
        quad([Vec3::new(-s, 0.0, s), Vec3::new(s, 0.0, s), Vec3::new(s, 0.0, -s), Vec3::new(-s, 0.0, -s)], m),
        Mat4::IDENTITY,
    )
    .unwrap();
    b.cameras.push(Camera {
        name: "down".into(),
        to_world: look_at(Vec3::new(0.0, 1.0, 0.0), Vec3::ZERO, Vec3::Z),
        projection: Projection::Orthographic { ymag: 0.5 },
    });
    let mut scene = b.build();
    scene.lights = scene.light_set(Vec::new(), Vec3::ZERO, Some(map.clone()));
    // Irradiance on an upward plane, by the midpoint rule over the sphere (8 points a texel
    // each way): E = integral of L(w) max(w.y, 0) dw.
    let (nu, nv) = (512, 256);
    let mut e = [0.0f64; 3];
    for j in 0..nv {
        let theta = PI * (j as f32 + 0.5) / nv as f32;
        let d_omega = (2.0 * PI / nu as f32) * (PI / nv as f32) * libm::sinf(theta);
        for i in 0..nu {
            let phi = 2.0 * PI * (i as f32 + 0.5) / nu as f32;
            let d =
                Vec3::new(libm::sinf(phi) * libm::sinf(theta), libm::cosf(theta), -libm::cosf(phi) * libm::sinf(theta));
            let l = map.radiance(d) * d.y.max(0.0) * d_omega;
            for c in 0..3 {
                e[c] += l[c] as f64;
            }
        }
    }
    let expected = (e[0] + e[1] + e[2]) / 3.0 * albedo as f64 / std::f64::consts::PI;
    for estimator in [Estimator::Nee, Estimator::Mis] {
        // One bounce: the plane lit by the map, nothing else.
        let s = RenderSettings { termination: Termination::MaxBounces(1), ..settings(8, 8, estimator) };
        let r = replicated_mean(&scene, &s, 512, |_| true);
        assert!(
            (r.mean - expected).abs() <= 3.0 * r.se,
            "{estimator:?}: {} +- {}, the quadrature gives {expected}",
            r.mean,
            r.se
        );
    }
}

#[test]
fn light_sampling_with_mis_agrees_with_bsdf_sampling_alone() {
    let map = sunny();
    for (roughness, metallic) in [(0.3, 1.0), (0.8, 0.0)] {
        let mut b = SceneBuilder::new();
        let m = b.add_material(Material {
            name: "ball".into(),
            base_color: Vec4::new(0.9, 0.7, 0.5, 1.0),
            metallic,
            roughness,
            ..Material::default()
        });
        let mut ball = icosphere(3, false);
        ball.material = m;
        b.add_mesh("ball", ball, Mat4::IDENTITY).unwrap();
        let scene = lit(b, &map);
        let s = |estimator| RenderSettings { termination: Termination::MaxBounces(3), ..settings(12, 12, estimator) };
        let mis = replicated_mean(&scene, &s(Estimator::Mis), 1024, |_| true);
        let bsdf = replicated_mean(&scene, &s(Estimator::Collision), 4096, |_| true);
        assert_agree(&format!("roughness {roughness}, metallic {metallic}"), &mis, &bsdf);
        // Light sampling is what makes the sun cheap: MIS's error is far below BSDF sampling's
        // at a quarter of the samples.
        assert!(mis.se < bsdf.se, "MIS {} against BSDF sampling {}", mis.se, bsdf.se);
    }
}

/// A 16 x 8 map whose texel (i, j) has radiance (i, j, 1), written as `ext` under `dir`.
fn write_map(dir: &std::path::Path, ext: &str, poison: Option<f32>) -> std::path::PathBuf {
    let (w, h) = (16usize, 8usize);
    let mut texels: Vec<[f32; 3]> = (0..w * h).map(|k| [(k % w) as f32, (k / w) as f32, 1.0]).collect();
    if let Some(v) = poison {
        texels[w + 3][1] = v;
    }
    let path = dir.join(format!("map.{ext}"));
    match ext {
        "exr" => {
            use exr::prelude::*;
            let channels = SpecificChannels::rgb(|p: Vec2<usize>| {
                let t = texels[p.y() * w + p.x()];
                (t[0], t[1], t[2])
            });
            Image::from_channels((w, h), channels).write().to_file(&path).unwrap();
        }
        _ => {
            let pixels: Vec<image::Rgb<f32>> = texels.iter().map(|&t| image::Rgb(t)).collect();
            let file = std::io::BufWriter::new(std::fs::File::create(&path).unwrap());
            image::codecs::hdr::HdrEncoder::new(file).encode(&pixels, w, h).unwrap();
        }
    }
    path
}

#[test]
fn maps_load_from_hdr_and_exr_files_and_bad_ones_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    for ext in ["hdr", "exr"] {
        let path = write_map(dir.path(), ext, None);
        let env = tessera_scene::environment::load(&path, 2.0, 0.0).unwrap();
        assert_eq!((env.width, env.height), (16, 8));
        // Straight up is the top row (j = 0); the horizon towards +Z is the centre column, i = 8
        // (just right of it), scaled by the strength. Radiance HDR keeps about 8 bits of mantissa.
        let up = env.map.radiance(Vec3::new(0.001, 1.0, 0.0).normalize());
        assert!((up.y - 0.0).abs() < 1e-6 && (up.z - 2.0).abs() < 0.02, "{ext}: {up}");
        let ahead = env.map.radiance(Vec3::new(-0.01, -0.01, 1.0).normalize());
        assert!((ahead.x - 16.0).abs() < 0.2 && (ahead.y - 8.0).abs() < 0.1, "{ext}: {ahead}");
        assert_eq!(env.hash, blake3::hash(&std::fs::read(&path).unwrap()).to_hex().to_string());
    }
    let nan = write_map(dir.path(), "exr", Some(f32::NAN));
    let err = tessera_scene::environment::load(&nan, 1.0, 0.0).unwrap_err().to_string();
    assert!(err.contains("texel (3, 1)") && err.contains("finite"), "{err}");
    let negative = write_map(dir.path(), "exr", Some(-1.0));
    assert!(tessera_scene::environment::load(&negative, 1.0, 0.0).unwrap_err().to_string().contains("not negative"));
    let junk = dir.path().join("junk.hdr");
    std::fs::write(&junk, b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 99999 +X 99999\n").unwrap();
    let err = tessera_scene::environment::load(&junk, 1.0, 0.0).unwrap_err().to_string();
    assert!(err.contains("99999 x 99999") || err.contains("readable"), "{err}");
    let png = dir.path().join("map.png");
    std::fs::write(&png, b"x").unwrap();
    assert!(tessera_scene::environment::load(&png, 1.0, 0.0).unwrap_err().to_string().contains(".hdr or an OpenEXR"));
}

#[test]
fn a_map_travels_with_its_scene_in_one_package() {
    let dir = tempfile::tempdir().unwrap();
    let map = write_map(dir.path(), "exr", None);
    let packed = tessera_scene::pack_with_environment("builtin:furnace", &map).unwrap();
    let source = tessera_scene::open_packed(&packed, "bundle").unwrap();
    let carried = source.environment(2.0, 30.0).unwrap().expect("the bundle carries its map");
    let direct = tessera_scene::environment::load(&map, 2.0, 30.0).unwrap();
    assert_eq!(carried.hash, direct.hash);
    for d in [Vec3::Y, Vec3::new(0.3, 0.2, -0.9).normalize(), Vec3::new(-0.7, -0.1, 0.2).normalize()] {
        assert_eq!(carried.map.radiance(d), direct.map.radiance(d));
    }
    // A package without a map carries none; a cut or mangled bundle is refused.
    assert!(
        tessera_scene::open_packed(&tessera_scene::pack("builtin:furnace").unwrap(), "plain")
            .unwrap()
            .environment(1.0, 0.0)
            .unwrap()
            .is_none()
    );
    // A cut bundle is refused when opened; a map cut in its pixels, when it is checked (as the
    // coordinator does on upload) or first used.
    for cut in [20, 30] {
        assert!(tessera_scene::open_packed(&packed[..cut], "cut").is_err(), "cut at {cut}");
    }
    let cut = tessera_scene::open_packed(&packed[..packed.len() - 10], "cut").unwrap();
    assert!(cut.check_environment().is_err() && cut.environment(1.0, 0.0).is_err());
    assert!(tessera_scene::open_packed(&packed, "whole").unwrap().check_environment().is_ok());
    let mut mangled = packed.clone();
    let tag = 18 + 8 + tessera_scene::pack("builtin:furnace").unwrap().len();
    mangled[tag] = b'x';
    assert!(tessera_scene::open_packed(&mangled, "mangled").err().unwrap().to_string().contains("bundle"));
}

/// A white furnace under a non-uniform map, seen from inside an albedo-1 sphere: a smooth thin
/// wall of white that transmits everything and reflects nothing (specular 0) loses and bends
/// nothing, so from its centre every pixel shows the map as if the sphere were not there, with
/// every estimator (the sun included, reached through the wall by light sampling as well).
#[test]
fn a_white_wall_around_the_camera_shows_the_map_unchanged() {
    let map = sunny();
    let view = |wall: bool| {
        let mut b = SceneBuilder::new();
        if wall {
            let m = b.add_material(Material {
                name: "white wall".into(),
                base_color: Vec4::ONE,
                metallic: 0.0,
                roughness: 0.0,
                specular: 0.0,
                transmission: 1.0,
                ..Material::default()
            });
            let mut sphere = icosphere(2, false);
            sphere.material = m;
            b.add_mesh("wall", sphere, Mat4::IDENTITY).unwrap();
        }
        b.cameras.push(Camera {
            name: "centre".into(),
            to_world: look_at(Vec3::ZERO, Vec3::new(0.3, 0.4, -1.0), Vec3::Y),
            projection: Projection::Perspective { yfov: 100f32.to_radians() },
        });
        let mut scene = b.build();
        scene.lights = scene.light_set(Vec::new(), Vec3::ZERO, Some(map.clone()));
        scene
    };
    let (inside, open) = (view(true), view(false));
    for estimator in [Estimator::Collision, Estimator::Nee, Estimator::Mis] {
        let s = settings(24, 16, estimator);
        let (a, b) = (common::render(&inside, &s, 16), common::render(&open, &s, 16));
        for (p, q) in a.pixels.iter().zip(&b.pixels) {
            let (m, n) = (p.mean(), q.mean());
            for c in 0..3 {
                assert!(
                    (m[c] - n[c]).abs() <= 1e-5 * n[c].abs().max(1.0),
                    "{estimator:?}: {m:?} against the open map's {n:?}"
                );
            }
        }
    }
}
