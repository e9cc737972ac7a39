//! The feature layers a denoiser reads (`--aov albedo,normal`): exact values on analytic
//! scenes (a Lambertian plane's albedo is its base colour, its normal the plane's; a sphere's
//! normals point out of it; a mirror shows the features of what it reflects; misses give albedo
//! 1 and normal 0), merged exactly from any split, and the colour untouched by asking for them.

mod common;

use tessera_film::Film;
use tessera_render::glam::{Mat4, Vec2, Vec3, Vec4};
use tessera_render::{
    Camera, FEATURE_SCALE, Material, Projection, RenderSettings, Scene, SceneBuilder, Tile, look_at, render_tile,
};
use tessera_scene::shapes::{icosphere, quad};

const BASE: [f32; 3] = [0.2, 0.5, 0.7];

/// What the layers hold for a value summed `n` times: its quantum, exactly.
fn quantised(v: f32) -> f32 {
    ((v as f64 * FEATURE_SCALE).round() / FEATURE_SCALE) as f32
}

fn lambert(b: &mut SceneBuilder) -> u32 {
    b.add_material(Material {
        name: "plane".into(),
        base_color: Vec4::new(BASE[0], BASE[1], BASE[2], 1.0),
        metallic: 0.0,
        roughness: 0.8,
        specular: 0.0,
        ..Material::default()
    })
}

fn looking_down_z(mut b: SceneBuilder, yfov: f32) -> Scene {
    b.cameras.push(Camera {
        name: "view".into(),
        to_world: look_at(Vec3::ZERO, Vec3::NEG_Z, Vec3::Y),
        projection: Projection::Perspective { yfov: yfov.to_radians() },
    });
    b.environment = Vec3::splat(0.5);
    let mut scene = b.build();
    scene.lights = scene.light_set(Vec::new(), Vec3::splat(0.5), None);
    scene
}

fn layered(width: u32, height: u32) -> RenderSettings {
    RenderSettings { features: true, ..common::settings(width, height, tessera_render::Estimator::Mis) }
}

/// Renders `spp` samples with the layers, in 8 x 8 tiles, into a film that sums them.
fn render(scene: &Scene, s: &RenderSettings, spp: u32) -> Film {
    let mut film = Film::with_features(s.width, s.height, true);
    for tile in Tile::grid(s.width, s.height, 8) {
        film.merge_tile(&render_tile(scene, s, tile, 0..spp).unwrap()).unwrap();
    }
    film
}

#[test]
fn a_lambertian_plane_gives_its_base_colour_and_normal_and_misses_give_none() {
    let mut b = SceneBuilder::new();
    let m = lambert(&mut b);
    let corners = [
        Vec3::new(-1.0, -1.0, -3.0),
        Vec3::new(1.0, -1.0, -3.0),
        Vec3::new(1.0, 1.0, -3.0),
        Vec3::new(-1.0, 1.0, -3.0),
    ];
    b.add_mesh("plane", quad(corners, m), Mat4::IDENTITY).unwrap();
    let scene = looking_down_z(b, 90.0);
    let s = layered(24, 24);
    let film = render(&scene, &s, 16);
    let image = film.resolve();
    let layers = image.features.as_ref().expect("a film with features resolves to layers");
    let (mut on, mut off) = (0, 0);
    for (i, p) in film.pixels.iter().enumerate() {
        if p.hits == p.n {
            assert_eq!(layers.albedo[i], BASE.map(quantised), "pixel {i}: the plane's base colour");
            assert_eq!(layers.normal[i], [0.0, 0.0, 1.0], "pixel {i}: the plane's normal, towards the camera");
            on += 1;
        } else if p.hits == 0 {
            assert_eq!((layers.albedo[i], layers.normal[i]), ([1.0; 3], [0.0; 3]), "pixel {i}: a miss");
            off += 1;
        }
    }
    assert!(on >= 36 && off >= 200, "{on} pixels on the plane, {off} off it");

    // The colour's bits do not change with the layers, and the layers merge exactly from any split.
    let plain = RenderSettings { features: false, ..s.clone() };
    let tile = Tile { x0: 4, y0: 6, width: 12, height: 10 };
    let whole = render_tile(&scene, &s, tile, 0..16).unwrap();
    assert_eq!(render_tile(&scene, &plain, tile, 0..16).unwrap().pixels, whole.pixels);
    assert!(render_tile(&scene, &plain, tile, 0..16).unwrap().features.is_empty());
    let mut split = render_tile(&scene, &s, tile, 11..16).unwrap();
    split.merge(&render_tile(&scene, &s, tile, 0..4).unwrap());
    split.merge(&render_tile(&scene, &s, tile, 4..11).unwrap());
    assert_eq!(split, whole);
}

#[test]
fn a_sphere_s_normals_point_out_of_it() {
    let mut b = SceneBuilder::new();
    let m = lambert(&mut b);
    let mut ball = icosphere(4, false);
    ball.material = m;
    let centre = Vec3::new(0.0, 0.0, -3.0);
    b.add_mesh("ball", ball, Mat4::from_translation(centre)).unwrap();
    let scene = looking_down_z(b, 45.0);
    let s = layered(32, 32);
    let film = render(&scene, &s, 16);
    let layers = film.resolve().features.unwrap();
    let rays = scene.cameras[0].film(s.width, s.height);
    let mut checked = 0;
    for (i, p) in film.pixels.iter().enumerate() {
        if p.hits != p.n {
            continue; // the silhouette and the background
        }
        // The unit sphere's normal where the ray through the pixel's centre meets it.
        let (o, d) = rays.ray(Vec2::new((i % 32) as f32 + 0.5, (i / 32) as f32 + 0.5));
        let oc = o - centre;
        let (half_b, c) = (oc.dot(d), oc.length_squared() - 1.0);
        let t = -half_b - (half_b * half_b - c).sqrt();
        let expected = (o + d * t - centre).normalize();
        let got = Vec3::from_array(layers.normal[i]);
        assert!(got.distance(expected) < 0.03, "pixel {i}: normal {got}, the sphere's is {expected}");
        checked += 1;
    }
    assert!(checked > 150, "only {checked} pixels lie inside the sphere's outline");
}

#[test]
fn a_mirror_shows_the_features_of_what_it_reflects() {
    let mut b = SceneBuilder::new();
    let wall = lambert(&mut b);
    let mirror = b.add_material(Material {
        name: "mirror".into(),
        base_color: Vec4::ONE,
        metallic: 1.0,
        roughness: 0.0,
        ..Material::default()
    });
    // A mirror at 45 degrees turns the view's -Z into +X, towards a wall facing back along -X.
    let (u, v, c) = (Vec3::new(1.0, 0.0, -1.0).normalize(), Vec3::Y, Vec3::new(0.0, 0.0, -3.0));
    let corners = [c - u - v, c + u - v, c + u + v, c - u + v];
    b.add_mesh("mirror", quad(corners, mirror), Mat4::IDENTITY).unwrap();
    let (x, y0, y1, z0, z1) = (3.0, -20.0, 20.0, -30.0, 20.0);
    let corners = [Vec3::new(x, y0, z0), Vec3::new(x, y1, z0), Vec3::new(x, y1, z1), Vec3::new(x, y0, z1)];
    b.add_mesh("wall", quad(corners, wall), Mat4::IDENTITY).unwrap();
    let scene = looking_down_z(b, 30.0);
    let s = layered(16, 16);
    let film = render(&scene, &s, 16);
    let layers = film.resolve().features.unwrap();
    let on_mirror = |i: usize| {
        let rays = scene.cameras[0].film(s.width, s.height);
        [(0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (1.0, 1.0)].iter().all(|&(dx, dy)| {
            let (o, d) = rays.ray(Vec2::new((i % 16) as f32 + dx, (i / 16) as f32 + dy));
            scene.intersect(o, d, f32::INFINITY).is_some_and(|h| scene.surface(h, o, d).material == mirror)
        })
    };
    let mut checked = 0;
    for i in (0..film.pixels.len()).filter(|&i| on_mirror(i)) {
        assert_eq!(layers.albedo[i], BASE.map(quantised), "pixel {i}: the wall's colour, seen in the mirror");
        assert_eq!(layers.normal[i], [-1.0, 0.0, 0.0], "pixel {i}: the wall's normal, seen in the mirror");
        checked += 1;
    }
    assert!(checked >= 16, "only {checked} pixels lie wholly on the mirror");
}
