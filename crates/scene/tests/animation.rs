//! Animation: channels sampled at chosen times against values computed here from the keys
//! (read through the glTF crate's own reader, interpolated with glam), a posed scene against a
//! static copy posed by hand, a skin against joint matrices composed here, and frames of a
//! turning cube against each other.

mod common;

use common::{fixtures_dir, glb, render, settings};
use gltf::animation::util::{ReadOutputs, Rotations};
use tessera_render::Estimator;
use tessera_render::glam::{Mat4, Quat, Vec3, Vec4};
use tessera_scene::animation::Choice;
use tessera_scene::{LoadOptions, PoseAt, open};

fn fixture(path: &str) -> String {
    fixtures_dir().join(path).display().to_string()
}

fn at(animation: Choice, time: f32) -> PoseAt {
    PoseAt { animation, time }
}

/// A channel's keys as the glTF crate reads them: times, and values as Vec4s (xyz for vectors).
struct Keys {
    node: usize,
    path: gltf::animation::Property,
    interpolation: gltf::animation::Interpolation,
    times: Vec<f32>,
    values: Vec<Vec4>,
}

fn keys_of(path: &str) -> Vec<Keys> {
    let (document, buffers, _) = gltf::import(path).unwrap();
    let mut out = Vec::new();
    for a in document.animations() {
        for c in a.channels() {
            let reader = c.reader(|b| Some(&buffers[b.index()].0[..]));
            let times: Vec<f32> = reader.read_inputs().unwrap().collect();
            let values: Vec<Vec4> = match reader.read_outputs().unwrap() {
                ReadOutputs::Translations(v) | ReadOutputs::Scales(v) => {
                    v.map(|t| Vec3::from_array(t).extend(0.0)).collect()
                }
                ReadOutputs::Rotations(Rotations::F32(v)) => v.map(Vec4::from_array).collect(),
                ReadOutputs::MorphTargetWeights(w) => {
                    // Up to four targets a key, padded with zeros.
                    let w: Vec<f32> = w.into_f32().collect();
                    let per_value = w.len()
                        / times.len()
                        / if c.sampler().interpolation() == gltf::animation::Interpolation::CubicSpline {
                            3
                        } else {
                            1
                        };
                    assert!(per_value <= 4);
                    w.chunks(per_value).map(|c| Vec4::from_slice(&[c, &[0.0; 4]].concat()[..4])).collect()
                }
                _ => panic!("unexpected output type"),
            };
            out.push(Keys {
                node: c.target().node().index(),
                path: c.target().property(),
                interpolation: c.sampler().interpolation(),
                times,
                values,
            });
        }
    }
    out
}

/// The value at `t` by the glTF specification, written here with glam: STEP holds, LINEAR lerps
/// (glam's slerp for rotations), CUBICSPLINE is the Hermite form with tangents times the interval.
fn expected(k: &Keys, t: f32) -> Vec4 {
    use gltf::animation::Interpolation as I;
    let cubic = k.interpolation == I::CubicSpline;
    let value = |i: usize| if cubic { k.values[3 * i + 1] } else { k.values[i] };
    let n = k.times.len();
    if t <= k.times[0] {
        return value(0);
    }
    if t >= k.times[n - 1] {
        return value(n - 1);
    }
    let i = (0..n - 1).find(|&i| k.times[i] <= t && t < k.times[i + 1]).unwrap();
    let dt = k.times[i + 1] - k.times[i];
    let s = (t - k.times[i]) / dt;
    let rotation = k.path == gltf::animation::Property::Rotation;
    match k.interpolation {
        I::Step => value(i),
        I::Linear if rotation => {
            let (a, b) = (Quat::from_vec4(value(i)), Quat::from_vec4(value(i + 1)));
            Vec4::from(a.slerp(b, s))
        }
        I::Linear => value(i).lerp(value(i + 1), s),
        I::CubicSpline => {
            let (p0, m0) = (value(i), k.values[3 * i + 2] * dt);
            let (p1, m1) = (value(i + 1), k.values[3 * (i + 1)] * dt);
            let h00 = (1.0 + 2.0 * s) * (1.0 - s) * (1.0 - s);
            let h10 = s * (1.0 - s) * (1.0 - s);
            let h01 = s * s * (3.0 - 2.0 * s);
            let h11 = s * s * (s - 1.0);
            let v = h00 * p0 + h10 * m0 + h01 * p1 + h11 * m1;
            if rotation { v.normalize() } else { v }
        }
    }
}

/// Checks every channel of `path` at `times` against [`expected`]; returns how many it checked.
fn check_channels(path: &str, animation: Choice, times: &[f32]) -> usize {
    let keys = keys_of(path);
    let source = open(path).unwrap();
    let mut checked = 0;
    for &t in times {
        let poses = source.node_poses(&at(animation.clone(), t)).unwrap();
        for k in &keys {
            let want = expected(k, t);
            let p = &poses[k.node];
            let got = match k.path {
                gltf::animation::Property::Translation => Vec3::from_array(p.translation).extend(0.0),
                gltf::animation::Property::Scale => Vec3::from_array(p.scale).extend(0.0),
                gltf::animation::Property::Rotation => Vec4::from_array(p.rotation),
                gltf::animation::Property::MorphTargetWeights => {
                    let w = p.weights.as_ref().unwrap();
                    Vec4::from_slice(&[&w[..], &[0.0; 4]].concat()[..4])
                }
            };
            assert!(
                (got - want).abs().max_element() < 1e-5,
                "{path}: node {} {:?} {:?} at {t} s: {got} where the keys give {want}",
                k.node,
                k.path,
                k.interpolation
            );
            checked += 1;
        }
    }
    checked
}

#[test]
fn interpolation_test_channels_match_values_computed_from_their_keys() {
    let path = fixture("InterpolationTest/glTF-Binary/InterpolationTest.glb");
    // Before the first key (the scale channels start at 0.042 s), at keys, between keys in every
    // segment, at the last key and after it.
    let times = [-1.0, 0.0, 0.02, 0.1, 0.3, 0.5, 0.62, 0.9, 1.0, 1.1, 1.25, 1.4, 1.6, 1.667, 1.7, 1.708, 2.5];
    assert_eq!(check_channels(&path, Choice::All, &times), 9 * times.len(), "three interpolations by three properties");
    // AnimatedTriangle turns in quarter turns; its last key is the quaternion -identity, so the
    // last segment must turn the shorter way (glam's slerp does).
    let triangle = fixture("AnimatedTriangle/glTF/AnimatedTriangle.gltf");
    assert_eq!(check_channels(&triangle, Choice::First, &[0.1, 0.3, 0.6, 0.8, 0.875, 0.95]), 6);
    // Morph target weights, two a key.
    let morph = fixture("AnimatedMorphCube/glTF-Binary/AnimatedMorphCube.glb");
    assert_eq!(check_channels(&morph, Choice::First, &[0.0, 0.5, 1.234, 2.0, 3.3, 9.0]), 6);
    let source = open(&path).unwrap();
    // Only the chosen animation moves: the first one alone (the default) leaves node 3 at rest.
    let first = source.node_poses(&at(Choice::First, 0.5)).unwrap();
    let all = source.node_poses(&at(Choice::All, 0.5)).unwrap();
    assert_ne!(first[0].scale, [1.0; 3]);
    assert_eq!(first[3].scale, [1.0; 3]);
    assert_ne!(all[3].scale, [1.0; 3]);
    assert_eq!(first[3], source.node_poses(&at(Choice::Name("Step Scale".into()), 0.5)).unwrap()[3]);
}

/// BoxAnimated's GLB as JSON and its binary chunk.
fn split_glb(bytes: &[u8]) -> (serde_json::Value, Vec<u8>) {
    let g = gltf::Glb::from_slice(bytes).unwrap();
    (serde_json::from_slice(&g.json).unwrap(), g.bin.unwrap().into_owned())
}

#[test]
fn a_posed_scene_renders_as_a_static_copy_posed_by_hand() {
    let path = fixture("BoxAnimated/glTF-Binary/BoxAnimated.glb");
    let bytes = std::fs::read(&path).unwrap();
    let keys = keys_of(&path);
    // Halfway through the rotation (1.25-2.5 s), where the translation rests between two equal
    // keys (0, 2.52, 0): the rotation is the library's slerp of the two keys (its agreement with
    // glam's is the test above); this test is about posing, not interpolating.
    let t = 1.875;
    let rotation = keys.iter().find(|k| k.path == gltf::animation::Property::Rotation).unwrap();
    let translation = keys.iter().find(|k| k.path == gltf::animation::Property::Translation).unwrap();
    let q = tessera_scene::animation::slerp(&rotation.values[0].to_array(), &rotation.values[1].to_array(), 0.5);
    let v = translation.values[1];
    assert_eq!(translation.values[1], translation.values[2]);

    let (mut json, bin) = split_glb(&bytes);
    json.as_object_mut().unwrap().remove("animations");
    json["nodes"][rotation.node]["rotation"] = serde_json::json!(q);
    json["nodes"][translation.node]["translation"] = serde_json::json!([v.x, v.y, v.z]);
    let static_copy = glb(json, &bin);

    let posed =
        open(&path).unwrap().pose(&LoadOptions { pose: Some(at(Choice::First, t)), ..Default::default() }).unwrap();
    let by_hand = tessera_scene::load_bytes(&static_copy, None, "by hand", &LoadOptions::default()).unwrap();
    let rest = open(&path).unwrap().pose(&LoadOptions::default()).unwrap();
    let s = settings(48, 36, Estimator::Nee);
    let image = |scene| render(scene, &s, 4).resolve().rgb;
    let posed_image = image(&posed.scene);
    assert_eq!(posed_image, image(&by_hand.scene), "the posed scene and its static copy differ");
    assert_ne!(posed_image, image(&rest.scene), "the pose moved nothing");
}

#[test]
fn a_skin_follows_joint_matrices_composed_from_the_keys() {
    let path = fixture("CesiumMan/glTF-Binary/CesiumMan.glb");
    let bytes = std::fs::read(&path).unwrap();
    let keys = keys_of(&path);
    let g = gltf::Gltf::from_slice(&bytes).unwrap();
    let blob = g.blob.clone();
    let doc = &g.document;
    let t = 0.77;
    // Each node's local matrix from its stored transform, its animated channels sampled here.
    let local = |i: usize| -> Mat4 {
        let node = doc.nodes().nth(i).unwrap();
        let (mut tr, mut r, mut sc) = node.transform().decomposed();
        let moved = keys.iter().filter(|k| k.node == i).collect::<Vec<_>>();
        if moved.is_empty() {
            return Mat4::from_cols_array_2d(&node.transform().matrix());
        }
        for k in moved {
            let v = expected(k, t);
            match k.path {
                gltf::animation::Property::Translation => tr = v.truncate().to_array(),
                gltf::animation::Property::Rotation => r = v.to_array(),
                gltf::animation::Property::Scale => sc = v.truncate().to_array(),
                _ => unreachable!(),
            }
        }
        Mat4::from_scale_rotation_translation(sc.into(), Quat::from_array(r), tr.into())
    };
    // World matrices by walking the hierarchy from the scene's roots.
    let mut world = vec![None; doc.nodes().len()];
    let mut stack: Vec<(usize, Mat4)> =
        doc.default_scene().unwrap().nodes().map(|n| (n.index(), Mat4::IDENTITY)).collect();
    while let Some((i, parent)) = stack.pop() {
        let w = parent * local(i);
        world[i] = Some(w);
        stack.extend(doc.nodes().nth(i).unwrap().children().map(|c| (c.index(), w)));
    }
    let skin = doc.skins().next().unwrap();
    let inverse: Vec<Mat4> = skin
        .reader(|_| blob.as_deref())
        .read_inverse_bind_matrices()
        .unwrap()
        .map(|m| Mat4::from_cols_array_2d(&m))
        .collect();
    let joints: Vec<Mat4> = skin.joints().zip(&inverse).map(|(j, ib)| world[j.index()].unwrap() * *ib).collect();

    let source = open(&path).unwrap();
    let pose = at(Choice::First, t);
    let worlds = source.world_transforms(Some(&pose)).unwrap();
    for (k, j) in skin.joints().enumerate() {
        let got = worlds[j.index()].unwrap() * inverse[k];
        let close = got.to_cols_array().iter().zip(joints[k].to_cols_array()).all(|(a, b)| (a - b).abs() < 1e-4);
        assert!(close, "joint {k} (node {}) at {t} s:\n{got}\nwhere the keys give\n{}", j.index(), joints[k]);
    }

    // The skinned mesh's bounds are those of its vertices blended here by the same matrices.
    let mesh = doc.meshes().next().unwrap();
    let (mut lo, mut hi) = (Vec3::splat(f32::MAX), Vec3::splat(f32::MIN));
    for prim in mesh.primitives() {
        let r = prim.reader(|_| blob.as_deref());
        let positions: Vec<Vec3> = r.read_positions().unwrap().map(Vec3::from_array).collect();
        let js: Vec<[u16; 4]> = r.read_joints(0).unwrap().into_u16().collect();
        let ws: Vec<[f32; 4]> = r.read_weights(0).unwrap().into_f32().collect();
        for ((p, j), w) in positions.iter().zip(&js).zip(&ws) {
            let m = (0..4).fold(Mat4::ZERO, |m, c| m + joints[j[c] as usize] * (w[c] / w.iter().sum::<f32>()));
            let q = m.transform_point3(*p);
            lo = lo.min(q);
            hi = hi.max(q);
        }
    }
    let posed = source.pose(&LoadOptions { pose: Some(pose), ..Default::default() }).unwrap();
    let (plo, phi) = posed.scene.bounds;
    assert!((plo - lo).abs().max_element() < 1e-4 && (phi - hi).abs().max_element() < 1e-4, "{plo} {phi} vs {lo} {hi}");
    let (rlo, rhi) = source.pose(&LoadOptions::default()).unwrap().scene.bounds;
    assert!((rlo - lo).abs().max_element() > 1e-3 || (rhi - hi).abs().max_element() > 1e-3, "the walk moved nothing");
}

#[test]
fn frames_of_a_turning_cube_differ_on_the_cube_and_nowhere_else() {
    let path = fixture("AnimatedCube/glTF/AnimatedCube.gltf");
    let source = open(&path).unwrap();
    // A quarter turn apart: the cube's silhouette (and so the framing camera) is the same, its
    // faces are not. The scene has no lights: it renders under the uniform environment of 1.
    let frame = |t| {
        let loaded = source.pose(&LoadOptions { pose: Some(at(Choice::First, t)), ..Default::default() }).unwrap();
        render(&loaded.scene, &settings(40, 40, Estimator::Nee), 4)
    };
    let (a, b) = (frame(0.0), frame(0.5));
    let (pa, pb) = (a.resolve().rgb, b.resolve().rgb);
    // A pixel that sees only the environment has every sample exactly 1.
    let whole = tessera_render::Tile { x0: 0, y0: 0, width: 40, height: 40 };
    let background = |f: &tessera_film::Film| -> Vec<bool> {
        f.tile_pixels(whole).map(|p| p.mean() == [1.0; 3] && p.sample_variance() == [0.0; 3]).collect()
    };
    let (ba, bb) = (background(&a), background(&b));
    let mut differing = 0;
    let mut cube = 0;
    for i in 0..pa.len() {
        let on_cube = !(ba[i] && bb[i]);
        cube += on_cube as usize;
        if pa[i] != pb[i] {
            differing += 1;
            assert!(on_cube, "pixel {i} sees only the environment in both frames, yet differs");
        }
    }
    assert!(cube > 200 && cube < 1400, "{cube} of 1600 pixels see the cube");
    assert!(differing * 10 > cube * 9, "only {differing} of the cube's {cube} pixels changed");
}

#[test]
fn broken_or_absent_animations_are_named() {
    let path = fixture("BoxAnimated/glTF-Binary/BoxAnimated.glb");
    let (json, bin) = split_glb(&std::fs::read(&path).unwrap());
    let source = open(&path).unwrap();
    let err = source.pose(&LoadOptions { pose: Some(at(Choice::Name("Jump".into()), 0.0)), ..Default::default() });
    let err = err.err().unwrap().to_string();
    assert!(err.contains("no animation named 'Jump'") && err.contains("0 (unnamed)"), "{err}");
    let still = open(&fixture("Box/glTF-Binary/Box.glb")).unwrap();
    let err = still.pose(&LoadOptions { pose: Some(at(Choice::Index(0), 0.0)), ..Default::default() });
    assert!(err.err().unwrap().to_string().contains("has no animations"));
    // The first animation's default on a still scene is the scene at rest.
    assert!(still.pose(&LoadOptions { pose: Some(at(Choice::First, 3.0)), ..Default::default() }).is_ok());

    // Key times that go backwards: refused when asked to play, naming the accessor; the scene
    // still loads at rest.
    let input = json["animations"][0]["samplers"][0]["input"].as_u64().unwrap() as usize;
    let view = &json["bufferViews"][json["accessors"][input]["bufferView"].as_u64().unwrap() as usize];
    let offset = view["byteOffset"].as_u64().unwrap_or(0) as usize
        + json["accessors"][input]["byteOffset"].as_u64().unwrap_or(0) as usize;
    let mut bad = bin.clone();
    bad[offset + 4..offset + 8].copy_from_slice(&(-1.0f32).to_le_bytes());
    let broken = tessera_scene::open_bytes(&glb(json.clone(), &bad), None, "broken").unwrap();
    let err = broken.pose(&LoadOptions { pose: Some(at(Choice::First, 1.0)), ..Default::default() });
    let err = err.err().unwrap().to_string();
    assert!(err.contains(&format!("input accessor {input}")) && err.contains("must increase"), "{err}");
    assert!(broken.pose(&LoadOptions::default()).is_ok());
    let mut nan = bin.clone();
    nan[offset + 4..offset + 8].copy_from_slice(&f32::NAN.to_le_bytes());
    let broken = tessera_scene::open_bytes(&glb(json, &nan), None, "nan").unwrap();
    let err = broken.pose(&LoadOptions { pose: Some(at(Choice::First, 1.0)), ..Default::default() });
    assert!(err.err().unwrap().to_string().contains("not a finite number"));
}

#[test]
fn cameras_and_lights_move_with_their_animated_nodes() {
    // A rig node that slides along x from 0 to 4 over 2 s (LINEAR), carrying a camera and a
    // point light 1 m above it; a triangle stands still so that there is something to frame.
    let floats = |v: &[f32]| v.iter().flat_map(|f| f.to_le_bytes()).collect::<Vec<u8>>();
    let mut bin = floats(&[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0]); // triangle, 36 bytes
    bin.extend(floats(&[0.0, 2.0])); // key times, 8 bytes at 36
    bin.extend(floats(&[0.0, 0.0, 5.0, 4.0, 0.0, 5.0])); // translations, 24 bytes at 44
    let json = serde_json::json!({
        "extensionsUsed": ["KHR_lights_punctual"],
        "extensions": {"KHR_lights_punctual": {"lights": [{"type": "point", "intensity": 10.0}]}},
        "scene": 0,
        "scenes": [{"nodes": [0, 1]}],
        "nodes": [
            {"mesh": 0},
            {"name": "rig", "children": [2, 3]},
            {"camera": 0},
            {"translation": [0.0, 1.0, 0.0], "extensions": {"KHR_lights_punctual": {"light": 0}}}
        ],
        "cameras": [{"type": "perspective", "perspective": {"yfov": 0.8, "znear": 0.1}}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
        "animations": [{"channels": [{"sampler": 0, "target": {"node": 1, "path": "translation"}}],
                        "samplers": [{"input": 1, "output": 2, "interpolation": "LINEAR"}]}],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3", "min": [0, 0, 0], "max": [1, 1, 0]},
            {"bufferView": 1, "componentType": 5126, "count": 2, "type": "SCALAR", "min": [0], "max": [2]},
            {"bufferView": 2, "componentType": 5126, "count": 2, "type": "VEC3"}
        ],
        "bufferViews": [
            {"buffer": 0, "byteLength": 36},
            {"buffer": 0, "byteOffset": 36, "byteLength": 8},
            {"buffer": 0, "byteOffset": 44, "byteLength": 24}
        ]
    });
    let source = tessera_scene::open_bytes(&glb(json, &bin), None, "rig").unwrap();
    let at_time = |t| source.pose(&LoadOptions { pose: Some(at(Choice::First, t)), ..Default::default() }).unwrap();
    for (t, x) in [(-1.0, 0.0), (0.5, 1.0), (1.5, 3.0), (9.0, 4.0)] {
        let scene = at_time(t).scene;
        let camera = scene.cameras[0].to_world.transform_point3(Vec3::ZERO);
        assert!((camera - Vec3::new(x, 0.0, 5.0)).length() < 1e-6, "camera at {t} s: {camera}");
        match scene.lights.punctual[0] {
            tessera_render::PunctualLight::Point { position, .. } => {
                assert!((position - Vec3::new(x, 1.0, 5.0)).length() < 1e-6, "light at {t} s: {position}")
            }
            ref other => panic!("{other:?}"),
        }
        // The triangle does not move.
        let top = scene.mesh.positions.iter().fold(Vec3::splat(f32::MIN), |m, &p| m.max(p));
        assert_eq!(top, Vec3::new(1.0, 1.0, 0.0));
    }
}
