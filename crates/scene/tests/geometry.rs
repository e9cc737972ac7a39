//! Geometry and materials as glTF files store them: triangle strips and fans, quantised and
//! normalised vertex attributes (KHR_mesh_quantization), sparse accessors, vertex colours,
//! generated tangents, image fallbacks and KHR_materials_ior; and layouts that do not fit their
//! data, refused by name.

use serde_json::{Value, json};
use tessera_render::Rgb;
use tessera_render::Texels;
use tessera_render::glam::{Vec2, Vec3, Vec4};
use tessera_scene::{LoadOptions, LoadedScene, load_bytes};

mod common;
use common::glb;

fn load(json: Value, bin: &[u8]) -> Result<LoadedScene, String> {
    load_bytes(&glb(json, bin), None, "test.glb", &LoadOptions::default()).map_err(|e| e.to_string())
}

fn f32s(v: &[f32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

/// One mesh of one primitive on one node (scaled by `scale`), with the given attributes,
/// buffer views and accessors.
fn mesh_json(primitive: Value, views: Value, accessors: Value, scale: f32) -> Value {
    json!({
        "scene": 0, "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "scale": [scale, scale, scale]}],
        "meshes": [{"primitives": [primitive]}],
        "bufferViews": views, "accessors": accessors,
    })
}

/// The scene's triangles as world-space corners, each turned to start at its smallest corner
/// (which keeps its winding), sorted.
fn triangles(loaded: &LoadedScene) -> Vec<[[f32; 3]; 3]> {
    let s = &loaded.scene;
    let mut out: Vec<[[f32; 3]; 3]> = s
        .mesh
        .triangles
        .iter()
        .map(|t| {
            let mut v = t.vertices.map(|i| s.mesh.positions[i as usize].to_array());
            let first = (0..3).min_by(|&a, &b| v[a].partial_cmp(&v[b]).unwrap()).unwrap();
            v.rotate_left(first);
            v
        })
        .collect();
    out.sort_by(|a, b| a.partial_cmp(b).unwrap());
    out
}

fn sorted(mut t: Vec<[[f32; 3]; 3]>) -> Vec<[[f32; 3]; 3]> {
    for v in &mut t {
        let first = (0..3).min_by(|&a, &b| v[a].partial_cmp(&v[b]).unwrap()).unwrap();
        v.rotate_left(first);
    }
    t.sort_by(|a, b| a.partial_cmp(b).unwrap());
    t
}

/// A strip and a fan become the triangles the glTF specification lists for them (3.7.2.1), all
/// with the winding of the first, so that front faces stay front faces.
#[test]
fn strips_and_fans_become_the_specifications_triangles() {
    // Strip: a zigzag of five vertices, no indices.
    let p = [[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [2.0, 0.0, 0.0]];
    let bin = f32s(&p.concat());
    let strip = mesh_json(
        json!({"attributes": {"POSITION": 0}, "mode": 5}),
        json!([{"buffer": 0, "byteLength": 60}]),
        json!([{"bufferView": 0, "componentType": 5126, "count": 5, "type": "VEC3",
                "min": [0, 0, 0], "max": [2, 1, 0]}]),
        1.0,
    );
    let loaded = load(strip, &bin).unwrap();
    assert!(loaded.info.warnings.iter().all(|w| !w.contains("skipped")), "{:?}", loaded.info.warnings);
    assert_eq!(triangles(&loaded), sorted(vec![[p[0], p[1], p[2]], [p[1], p[3], p[2]], [p[2], p[3], p[4]]]));

    // Fan around vertex 0, through byte indices.
    let p = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0], [-1.0, 1.0, 0.0]];
    let mut bin = f32s(&p.concat());
    bin.extend_from_slice(&[0, 1, 2, 3, 4]);
    let fan = mesh_json(
        json!({"attributes": {"POSITION": 0}, "indices": 1, "mode": 6}),
        json!([{"buffer": 0, "byteLength": 60}, {"buffer": 0, "byteOffset": 60, "byteLength": 5}]),
        json!([{"bufferView": 0, "componentType": 5126, "count": 5, "type": "VEC3",
                "min": [-1, 0, 0], "max": [1, 1, 0]},
               {"bufferView": 1, "componentType": 5121, "count": 5, "type": "SCALAR"}]),
        1.0,
    );
    let loaded = load(fan, &bin).unwrap();
    let t = triangles(&loaded);
    assert_eq!(t, sorted(vec![[p[1], p[2], p[0]], [p[2], p[3], p[0]], [p[3], p[4], p[0]]]));
    for v in t {
        let [a, b, c] = v.map(Vec3::from_array);
        assert!((b - a).cross(c - a).z > 0.0, "a fan triangle turned over: {v:?}");
    }
}

/// KHR_mesh_quantization: positions as normalised shorts (4-byte aligned, so a stride of 8),
/// normals as normalised bytes and texture coordinates as unnormalised unsigned shorts load as
/// the values they stand for, and the extension may be required.
#[test]
fn quantised_attributes_load_as_the_values_they_stand_for() {
    let mut bin = Vec::new();
    for p in [[0i16, 0, 0], [32767, 0, 0], [0, 32767, 0]] {
        bin.extend(p.iter().flat_map(|c| c.to_le_bytes()));
        bin.extend_from_slice(&[0, 0]);
    }
    for _ in 0..3 {
        bin.extend_from_slice(&[0, 0, 127u8, 0]); // normal (0, 0, 1) as bytes, padded to 4
    }
    for uv in [[0u16, 0], [2, 0], [0, 3]] {
        bin.extend(uv.iter().flat_map(|c| c.to_le_bytes()));
    }
    let mut scene = mesh_json(
        json!({"attributes": {"POSITION": 0, "NORMAL": 1, "TEXCOORD_0": 2}}),
        json!([{"buffer": 0, "byteLength": 24, "byteStride": 8},
               {"buffer": 0, "byteOffset": 24, "byteLength": 12, "byteStride": 4},
               {"buffer": 0, "byteOffset": 36, "byteLength": 12}]),
        json!([{"bufferView": 0, "componentType": 5122, "normalized": true, "count": 3, "type": "VEC3",
                "min": [0, 0, 0], "max": [1, 1, 0]},
               {"bufferView": 1, "componentType": 5120, "normalized": true, "count": 3, "type": "VEC3"},
               {"bufferView": 2, "componentType": 5123, "count": 3, "type": "VEC2"}]),
        4.0, // the dequantisation scale lives in the node, as gltfpack writes it
    );
    scene["extensionsUsed"] = json!(["KHR_mesh_quantization"]);
    scene["extensionsRequired"] = json!(["KHR_mesh_quantization"]);
    let loaded = load(scene, &bin).unwrap();
    assert_eq!(triangles(&loaded), vec![[[0.0, 0.0, 0.0], [4.0, 0.0, 0.0], [0.0, 4.0, 0.0]]]);
    let s = &loaded.scene;
    assert!(s.mesh.normals.iter().all(|&n| n == Vec3::Z), "{:?}", s.mesh.normals);
    assert_eq!(s.mesh.uv[0], vec![Vec2::ZERO, Vec2::new(2.0, 0.0), Vec2::new(0.0, 3.0)]);
    assert!(loaded.info.warnings.iter().all(|w| !w.contains("unsupported")), "{:?}", loaded.info.warnings);
}

/// A sparse accessor's substitutions replace its base values.
#[test]
fn sparse_positions_replace_their_base() {
    let mut bin = f32s(&[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0]);
    bin.extend_from_slice(&2u16.to_le_bytes());
    bin.extend_from_slice(&[0, 0]);
    bin.extend(f32s(&[0.0, 5.0, 0.0]));
    let scene = mesh_json(
        json!({"attributes": {"POSITION": 0}}),
        json!([{"buffer": 0, "byteLength": 36}, {"buffer": 0, "byteOffset": 36, "byteLength": 2},
               {"buffer": 0, "byteOffset": 40, "byteLength": 12}]),
        json!([{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3",
                "min": [0, 0, 0], "max": [1, 5, 0],
                "sparse": {"count": 1, "indices": {"bufferView": 1, "componentType": 5123},
                           "values": {"bufferView": 2}}}]),
        1.0,
    );
    let loaded = load(scene, &bin).unwrap();
    assert_eq!(triangles(&loaded), vec![[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 5.0, 0.0]]]);
}

/// COLOR_0 multiplies the base colour (glTF 2.0, 3.9.2), its alpha included, so that a mask
/// cuts out where the vertex alpha is low. Stored as normalised unsigned bytes here.
#[test]
fn vertex_colours_multiply_the_base_colour() {
    let quad = |z: f32| [[-1.0, -1.0, z], [1.0, -1.0, z], [1.0, 1.0, z], [-1.0, 1.0, z]].concat();
    let mut bin = f32s(&[quad(0.0), quad(1.0)].concat());
    // The near quad (z = 1) is transparent by its vertex alpha; the far one is tinted.
    let tint = [204u8, 102, 51, 255];
    let clear = [255u8, 255, 255, 25];
    for c in [tint, tint, tint, tint, clear, clear, clear, clear] {
        bin.extend_from_slice(&c);
    }
    bin.extend([0u8, 1, 2, 0, 2, 3, 4, 5, 6, 4, 6, 7]);
    let scene = json!({
        "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
        "materials": [{"pbrMetallicRoughness": {"baseColorFactor": [0.5, 1.0, 1.0, 1.0], "metallicFactor": 0.0},
                       "alphaMode": "MASK", "alphaCutoff": 0.5}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "COLOR_0": 1}, "indices": 2, "material": 0}]}],
        "bufferViews": [{"buffer": 0, "byteLength": 96}, {"buffer": 0, "byteOffset": 96, "byteLength": 32},
                        {"buffer": 0, "byteOffset": 128, "byteLength": 12}],
        "accessors": [{"bufferView": 0, "componentType": 5126, "count": 8, "type": "VEC3",
                       "min": [-1, -1, 0], "max": [1, 1, 1]},
                      {"bufferView": 1, "componentType": 5121, "normalized": true, "count": 8, "type": "VEC4"},
                      {"bufferView": 2, "componentType": 5121, "count": 12, "type": "SCALAR"}],
    });
    let loaded = load(scene, &bin).unwrap();
    let s = &loaded.scene;
    let (o, d) = (Vec3::new(0.2, 0.3, 5.0), Vec3::NEG_Z);
    let hit = s.intersect(o, d, f32::INFINITY).expect("the far quad is hit");
    assert!((hit.t - 5.0).abs() < 1e-5, "the ray stopped at {} (the near quad is cut out)", hit.t);
    let sp = s.surface(hit, o, d);
    let expected = Vec4::from_array(tint.map(|c| c as f32 / 255.0));
    assert!((sp.color - expected).abs().max_element() < 1e-6, "{} against {expected}", sp.color);
    let diffuse = s.bsdf(&sp, &Rgb, true).diffuse;
    let want = Vec3::new(0.5, 1.0, 1.0) * expected.truncate();
    assert!((diffuse - want).abs().max_element() < 1e-6, "{diffuse} against {want}");
}

/// Accessors whose layout cannot hold their elements are refused with the accessor named,
/// not read out of bounds (the glTF crate only checks these in debug builds).
#[test]
fn accessors_that_do_not_fit_are_named() {
    let bin = f32s(&[0.0; 9]);
    let short_stride = mesh_json(
        json!({"attributes": {"POSITION": 0}}),
        json!([{"buffer": 0, "byteLength": 36, "byteStride": 4}]),
        json!([{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3",
                "min": [0, 0, 0], "max": [0, 0, 0]}]),
        1.0,
    );
    let err = load(short_stride, &bin).err().unwrap();
    assert!(err.contains("accessor 0") && err.contains("byteStride 4"), "{err}");
    let wrong_type = mesh_json(
        json!({"attributes": {"POSITION": 0, "NORMAL": 1}}),
        json!([{"buffer": 0, "byteLength": 36}]),
        json!([{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3",
                "min": [0, 0, 0], "max": [0, 0, 0]},
               {"bufferView": 0, "componentType": 5126, "count": 2, "type": "VEC4"}]),
        1.0,
    );
    let err = load(wrong_type, &bin).err().unwrap();
    assert!(err.contains("accessor 1") && err.contains("Vec4"), "{err}");
    // Zeros without a buffer view, but for one sparse substitution: a count that only memory could
    // refuse is refused by name.
    let endless = mesh_json(
        json!({"attributes": {"POSITION": 0}}),
        json!([{"buffer": 0, "byteLength": 36}]),
        json!([{"componentType": 5126, "count": 60_000_000u64, "type": "VEC3", "min": [0, 0, 0], "max": [0, 0, 0],
                "sparse": {"count": 1, "indices": {"bufferView": 0, "componentType": 5125},
                           "values": {"bufferView": 0}}}]),
        1.0,
    );
    let err = load(endless, &bin).err().unwrap();
    assert!(err.contains("accessor 0") && err.contains("without a buffer view"), "{err}");
}

/// A PNG of one texel.
fn png(rgba: [u8; 4]) -> Vec<u8> {
    encode_png(image::RgbaImage::from_pixel(1, 1, image::Rgba(rgba)).into())
}

fn encode_png(image: image::DynamicImage) -> Vec<u8> {
    let mut out = std::io::Cursor::new(Vec::new());
    image.write_to(&mut out, image::ImageFormat::Png).unwrap();
    out.into_inner()
}

/// 16-bit PNGs keep their 16 bits: 0x8000 and 0x80ff, one 8-bit value, stay apart (they were
/// both 128 before). Two-channel PNGs are grey and alpha, as viewers show them (they were red
/// and green).
#[test]
fn sixteen_bit_and_grey_alpha_pngs_decode_as_written() {
    let material = json!({"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}});
    let wide = image::ImageBuffer::from_pixel(1, 1, image::Rgba([0x8000u16, 0x80ff, 0x1234, 0xfffe]));
    let loaded = one_image_quad(encode_png(wide.into()), material.clone()).unwrap();
    assert_eq!(loaded.scene.surfaces.images[0].texels, Texels::Sixteen(vec![[0x8000, 0x80ff, 0x1234, 0xfffe]]));
    let grey = image::ImageBuffer::from_pixel(1, 1, image::Luma([0x4321u16]));
    let loaded = one_image_quad(encode_png(grey.into()), material.clone()).unwrap();
    assert_eq!(loaded.scene.surfaces.images[0].texels, Texels::Sixteen(vec![[0x4321, 0x4321, 0x4321, 0xffff]]));
    let grey_alpha = image::ImageBuffer::from_pixel(1, 1, image::LumaA([200u8, 100]));
    let loaded = one_image_quad(encode_png(grey_alpha.into()), material).unwrap();
    assert_eq!(loaded.scene.surfaces.images[0].texels, Texels::Eight(vec![[200, 200, 200, 100]]));
}

/// A texture that names a WebP image through EXT_texture_webp reads it, not its PNG fallback
/// (`scenes.rs::webp_textures_are_read_before_their_fallback` decodes a real one): a WebP that
/// does not decode is refused by name, though a PNG stands beside it. Without the extension the
/// texture reads its PNG.
#[test]
fn a_broken_webp_is_refused_by_name() {
    let positions = f32s(&[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0]);
    let fallback = png([255, 128, 0, 255]);
    let webp = b"RIFF\x10\x00\x00\x00WEBPVP8 not really".to_vec();
    let scene = |with_webp: bool| {
        let mut bin = positions.clone();
        bin.extend(&fallback);
        bin.extend(&webp);
        let texture = if with_webp {
            json!({"source": 0, "extensions": {"EXT_texture_webp": {"source": 1}}})
        } else {
            json!({"source": 0})
        };
        let json = json!({
            "extensionsUsed": ["EXT_texture_webp"],
            "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
            "materials": [{"name": "painted", "pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}],
            "textures": [texture],
            "images": [{"name": "fallback", "bufferView": 1, "mimeType": "image/png"},
                       {"name": "modern", "bufferView": 2, "mimeType": "image/webp"}],
            "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "material": 0}]}],
            "bufferViews": [{"buffer": 0, "byteLength": 36},
                            {"buffer": 0, "byteOffset": 36, "byteLength": fallback.len()},
                            {"buffer": 0, "byteOffset": 36 + fallback.len(), "byteLength": webp.len()}],
            "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3",
                           "min": [0, 0, 0], "max": [1, 1, 0]}],
        });
        load(json, &bin)
    };
    let loaded = scene(false).unwrap();
    assert_eq!(loaded.scene.surfaces.images[0].texels, Texels::Eight(vec![[255, 128, 0, 255]]));
    let err = scene(true).err().unwrap();
    assert!(err.contains("image 1 'modern'") && err.contains("WebP"), "{err}");
}

/// Images decode in parallel, on as many threads as the pool in use has: the texels are the same
/// on one thread and on four, and of two images that do not decode the error names the first in
/// the file, whichever thread met which first.
#[test]
fn images_decoded_in_parallel_keep_their_texels_and_the_first_error() {
    let positions = f32s(&[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0]);
    let scene = |broken: bool| {
        let images: Vec<Vec<u8>> = (0..6u8)
            .map(|k| {
                if broken && (k == 2 || k == 4) {
                    b"\x89PNG not really".to_vec()
                } else {
                    png([k * 40, 255 - k, 7, 255])
                }
            })
            .collect();
        let mut bin = positions.clone();
        let mut views = vec![json!({"buffer": 0, "byteLength": 36})];
        for image in &images {
            views.push(json!({"buffer": 0, "byteOffset": bin.len(), "byteLength": image.len()}));
            bin.extend(image);
        }
        let textures: Vec<Value> = (0..6).map(|k| json!({"source": k})).collect();
        let materials: Vec<Value> =
            (0..6).map(|k| json!({"pbrMetallicRoughness": {"baseColorTexture": {"index": k}}})).collect();
        let primitives: Vec<Value> = (0..6).map(|k| json!({"attributes": {"POSITION": 0}, "material": k})).collect();
        let json = json!({
            "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
            "materials": materials, "textures": textures,
            "images": (0..6).map(|k| json!({"name": format!("image{k}"), "bufferView": k + 1, "mimeType": "image/png"})).collect::<Vec<_>>(),
            "meshes": [{"primitives": primitives}],
            "bufferViews": views,
            "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3",
                           "min": [0, 0, 0], "max": [1, 1, 0]}],
        });
        load(json, &bin)
    };
    let on = |threads: usize, broken: bool| {
        rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap().install(|| scene(broken))
    };
    let texels = |l: LoadedScene| l.scene.surfaces.images.iter().map(|i| i.texels.clone()).collect::<Vec<_>>();
    let one = texels(on(1, false).unwrap());
    assert_eq!(one.len(), 6);
    assert_eq!(one[3], Texels::Eight(vec![[120, 252, 7, 255]]));
    assert_eq!(one, texels(on(4, false).unwrap()), "threads changed the texels");
    for threads in [1, 4, 4, 4] {
        let err = on(threads, true).err().unwrap();
        assert!(err.contains("image 2 'image2'"), "{threads} threads: {err}");
    }
}

/// A normal-mapped mesh without TANGENT gets MikkTSpace tangents in glTF's convention: on a quad
/// whose texture stands upright (v runs down the image, as glTF's does), the tangent is +x and
/// the bitangent `cross(normal, tangent) * w` points up the image, +y. Where the texture is
/// mirrored (the right half of the strip below runs u backwards) the tangent turns to -x and
/// `w` to -1, so the bitangent still points up; the two vertices on the mirror line get one
/// copy per side.
#[test]
fn generated_tangents_follow_gltfs_convention() {
    use tessera_render::glam::Vec3;
    // Two quads side by side in the z = 0 plane; u mirrors at x = 1; v = 0 at the top (y = 1).
    let p = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0], [2.0, 0.0, 0.0], [2.0, 1.0, 0.0]];
    let uv = [[0.0, 1.0], [1.0, 1.0], [1.0, 0.0], [0.0, 0.0], [0.0, 1.0], [0.0, 0.0]];
    let mut bin = f32s(&p.concat());
    bin.extend(f32s(&[0.0, 0.0, 1.0].repeat(6)));
    bin.extend(f32s(&uv.concat()));
    bin.extend([0u8, 1, 2, 0, 2, 3, 1, 4, 5, 1, 5, 2]);
    bin.extend(png([128, 128, 255, 255]));
    let scene = json!({
        "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
        "materials": [{"normalTexture": {"index": 0}}],
        "textures": [{"source": 0}], "images": [{"bufferView": 4, "mimeType": "image/png"}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "NORMAL": 1, "TEXCOORD_0": 2},
                                    "indices": 3, "material": 0}]}],
        "bufferViews": [{"buffer": 0, "byteLength": 72}, {"buffer": 0, "byteOffset": 72, "byteLength": 72},
                        {"buffer": 0, "byteOffset": 144, "byteLength": 48},
                        {"buffer": 0, "byteOffset": 192, "byteLength": 12},
                        {"buffer": 0, "byteOffset": 204, "byteLength": png([128, 128, 255, 255]).len()}],
        "accessors": [{"bufferView": 0, "componentType": 5126, "count": 6, "type": "VEC3",
                       "min": [0, 0, 0], "max": [2, 1, 0]},
                      {"bufferView": 1, "componentType": 5126, "count": 6, "type": "VEC3"},
                      {"bufferView": 2, "componentType": 5126, "count": 6, "type": "VEC2"},
                      {"bufferView": 3, "componentType": 5121, "count": 12, "type": "SCALAR"}],
    });
    let loaded = load(scene.clone(), &bin).unwrap();
    let s = &loaded.scene;
    assert_eq!(s.mesh.positions.len(), 8, "the mirror line's two vertices are split, the rest shared");
    for t in &s.mesh.triangles {
        for &v in &t.vertices {
            let (p, tangent) = (s.mesh.positions[v as usize], s.mesh.tangents[v as usize]);
            let left = t.vertices.iter().all(|&w| s.mesh.positions[w as usize].x <= 1.0);
            let want = if left { Vec3::X } else { Vec3::NEG_X };
            assert!((tangent.truncate() - want).length() < 1e-5, "tangent {tangent} at {p}");
            let bitangent = Vec3::Z.cross(tangent.truncate()) * tangent.w;
            assert!((bitangent - Vec3::Y).length() < 1e-5, "bitangent {bitangent} at {p}: not up the image");
        }
    }
    // A KHR_texture_transform rotation of a quarter turn on the normal map turns its axes with
    // it: on the left quad the map's +x (its u' = -v) runs up the quad, and its +y to the left.
    let mut turned = scene;
    turned["extensionsUsed"] = json!(["KHR_texture_transform"]);
    turned["materials"][0]["normalTexture"]["extensions"] =
        json!({"KHR_texture_transform": {"rotation": std::f32::consts::FRAC_PI_2}});
    let loaded = load(turned, &bin).unwrap();
    let s = &loaded.scene;
    for t in s.mesh.triangles.iter().filter(|t| t.vertices.iter().all(|&v| s.mesh.positions[v as usize].x <= 1.0)) {
        for &v in &t.vertices {
            let tangent = s.mesh.tangents[v as usize];
            assert!((tangent.truncate() - Vec3::Y).length() < 1e-5, "turned tangent {tangent}");
            let bitangent = Vec3::Z.cross(tangent.truncate()) * tangent.w;
            assert!((bitangent - Vec3::NEG_X).length() < 1e-5, "turned bitangent {bitangent}");
        }
    }
}

/// [`one_image_quad`] whose image is one texel of `texel`.
fn one_texel_quad(texel: [u8; 4], material: Value) -> LoadedScene {
    one_image_quad(png(texel), material).unwrap()
}

/// The unit quad in the z = 0 plane without normals (so flat-shaded, facing +z), under
/// `material`, whose texture 0 is `image` (PNG bytes).
fn one_image_quad(image: Vec<u8>, material: Value) -> Result<LoadedScene, String> {
    let p = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]];
    let uv = [[0.0, 1.0], [1.0, 1.0], [1.0, 0.0], [0.0, 0.0]];
    let mut bin = f32s(&p.concat());
    bin.extend(f32s(&uv.concat()));
    bin.extend([0u8, 1, 2, 0, 2, 3]);
    bin.extend(&image);
    let scene = json!({
        "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
        "materials": [material],
        "textures": [{"source": 0}], "images": [{"bufferView": 3, "mimeType": "image/png"}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 1}, "indices": 2, "material": 0}]}],
        "bufferViews": [{"buffer": 0, "byteLength": 48}, {"buffer": 0, "byteOffset": 48, "byteLength": 32},
                        {"buffer": 0, "byteOffset": 80, "byteLength": 6},
                        {"buffer": 0, "byteOffset": 86, "byteLength": image.len()}],
        "accessors": [{"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3",
                       "min": [0, 0, 0], "max": [1, 1, 0]},
                      {"bufferView": 1, "componentType": 5126, "count": 4, "type": "VEC2"},
                      {"bufferView": 2, "componentType": 5121, "count": 6, "type": "SCALAR"}],
    });
    load(scene, &bin)
}

/// A normal-mapped mesh without NORMAL is flat-shaded (glTF 3.7.2.1) and still takes its normal
/// map: each triangle corner gets its face's normal and a MikkTSpace tangent.
#[test]
fn flat_shaded_meshes_take_their_normal_maps() {
    use tessera_render::glam::Vec3;
    let loaded = one_texel_quad([128, 128, 255, 255], json!({"normalTexture": {"index": 0}}));
    let s = &loaded.scene;
    assert_eq!(s.mesh.triangles.len(), 2);
    for t in &s.mesh.triangles {
        assert!(t.flags & tessera_render::HAS_TANGENTS != 0, "no tangents: the normal map would be ignored");
        for &v in &t.vertices {
            let (n, tangent) = (s.mesh.normals[v as usize], s.mesh.tangents[v as usize]);
            assert!((n - Vec3::Z).length() < 1e-6, "normal {n}: not the face's");
            assert!((tangent - Vec4::new(1.0, 0.0, 0.0, 1.0)).length() < 1e-5, "tangent {tangent}");
        }
    }
}

/// On a real asset that ships its tangents (WaterBottle, from ../shared/scenes when present),
/// tangents generated with TANGENT removed agree with the shipped ones: the same handedness and
/// direction at almost every triangle corner (the shipped tangents are one per vertex, so they
/// cannot follow MikkTSpace's split at every seam). The tangents generated before MikkTSpace had
/// the opposite handedness at every corner.
#[test]
fn generated_tangents_match_a_shipped_asset() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/scenes/WaterBottle/glTF");
    let path = dir.join("WaterBottle.gltf");
    if !path.is_file() {
        eprintln!("skipped: {} is not present", path.display());
        return;
    }
    let text = std::fs::read(&path).unwrap();
    let mut json: Value = serde_json::from_slice(&text).unwrap();
    for mesh in json["meshes"].as_array_mut().unwrap() {
        for prim in mesh["primitives"].as_array_mut().unwrap() {
            prim["attributes"].as_object_mut().unwrap().remove("TANGENT");
        }
    }
    let bare = serde_json::to_vec(&json).unwrap();
    let options = LoadOptions::default();
    let shipped = load_bytes(&text, Some(&dir), "shipped", &options).unwrap().scene;
    let generated = load_bytes(&bare, Some(&dir), "generated", &options).unwrap().scene;
    assert_eq!(shipped.mesh.triangles.len(), generated.mesh.triangles.len());
    let (mut corners, mut handedness, mut aligned) = (0, 0, 0);
    for (a, b) in shipped.mesh.triangles.iter().zip(&generated.mesh.triangles) {
        for (&va, &vb) in a.vertices.iter().zip(&b.vertices) {
            assert_eq!(
                shipped.mesh.positions[va as usize], generated.mesh.positions[vb as usize],
                "triangles out of step"
            );
            let (ta, tb) = (shipped.mesh.tangents[va as usize], generated.mesh.tangents[vb as usize]);
            corners += 1;
            handedness += (ta.w == tb.w) as usize;
            aligned += (ta.truncate().dot(tb.truncate()) > 0.95) as usize;
        }
    }
    eprintln!("{corners} corners: {handedness} of the same handedness, {aligned} aligned");
    assert!(handedness as f64 >= 0.99 * corners as f64, "only {handedness} of {corners} of the same handedness");
    assert!(aligned as f64 >= 0.95 * corners as f64, "only {aligned} of {corners} corners aligned");
}

/// Files that a mutation fuzzer (node matrices, accessor and view numbers of the fixtures
/// changed) found crashing the loader, now each refused by name: a node transform that throws
/// vertices past the coordinates the BVH builder's arithmetic can hold, POSITION naming an
/// accessor that does not exist, and a buffer view reaching past its buffer.
#[test]
fn malformed_layouts_found_by_fuzzing_are_named() {
    let bin = f32s(&[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0]);
    let triangle = |views: Value, position: usize| {
        mesh_json(
            json!({"attributes": {"POSITION": position}}),
            views,
            json!([{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3",
                    "min": [0, 0, 0], "max": [1, 1, 0]}]),
            1.0,
        )
    };
    let mut far = triangle(json!([{"buffer": 0, "byteLength": 36}]), 0);
    far["nodes"][0] = json!({"mesh": 0, "matrix": [1e30, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]});
    let err = load(far.clone(), &bin).err().unwrap();
    assert!(err.contains("after its node transform"), "{err}");
    // 1e39 is infinite as f32, and infinity times a zero coordinate is NaN.
    far["nodes"][0]["matrix"][0] = json!(1e39);
    let err = load(far, &bin).err().unwrap();
    assert!(err.contains("after its node transform"), "{err}");
    let err = load(triangle(json!([{"buffer": 0, "byteLength": 36}]), 3), &bin).err().unwrap();
    assert!(err.contains("POSITION names accessor 3"), "{err}");
    let err = load(triangle(json!([{"buffer": 0, "byteOffset": 24, "byteLength": 36}]), 0), &bin).err().unwrap();
    assert!(err.contains("buffer view 0") && err.contains("outside buffer 0"), "{err}");
}

/// A one-triangle file whose only material is `material`, declaring `extension` as used.
fn triangle_with_material(material: Value, extension: &str) -> Result<LoadedScene, String> {
    let mut doc = mesh_json(
        json!({"attributes": {"POSITION": 0}, "material": 0}),
        json!([{"buffer": 0, "byteLength": 36}]),
        json!([{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3",
                "min": [0, 0, 0], "max": [1, 1, 0]}]),
        1.0,
    );
    doc["materials"] = json!([material]);
    doc["extensionsUsed"] = json!([extension]);
    load(doc, &f32s(&[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0]))
}

/// [`triangle_with_material`] with a dielectric (metallic 0) named `name` whose `extension`
/// object is `value`.
fn dielectric_with(name: &str, extension: &str, value: Value) -> Result<LoadedScene, String> {
    let mut material = json!({"name": name, "pbrMetallicRoughness": {"metallicFactor": 0.0}});
    material["extensions"] = json!({ extension: value });
    triangle_with_material(material, extension)
}

/// The BSDF of a loaded file's first material at texture coordinates 0, in RGB.
fn first_bsdf(loaded: &LoadedScene) -> tessera_render::bsdf::Bsdf {
    let s = &loaded.scene;
    let ctx = s.surfaces.context([Vec2::ZERO; 2], Vec4::ONE);
    s.surfaces.materials()[0].bsdf(&ctx, &Rgb)
}

/// KHR_materials_ior sets the dielectric layer's reflectance at normal incidence to
/// `((ior - 1) / (ior + 1))^2`: 1/9 at 2, and exactly glTF's 0.04 at the default 1.5. An ior that
/// is not a number >= 0 is refused with the material named.
#[test]
fn ior_sets_the_dielectric_reflectance() {
    let scene = |ior: Value| {
        let mut m = json!({"name": "glass-like", "pbrMetallicRoughness": {"metallicFactor": 0.0}});
        if !ior.is_null() {
            m["extensions"] = json!({"KHR_materials_ior": {"ior": ior}});
        }
        triangle_with_material(m, "KHR_materials_ior")
    };
    let normal_reflectance = |loaded: &LoadedScene| first_bsdf(loaded).fresnel.weights(1.0, 1.0).1;
    let two = scene(json!(2.0)).unwrap();
    assert!(two.info.warnings.iter().all(|w| !w.contains("KHR_materials_ior")), "{:?}", two.info.warnings);
    let f = normal_reflectance(&two);
    assert!((f - Vec3::splat(1.0 / 9.0)).abs().max_element() < 1e-6, "{f}");
    assert_eq!(normal_reflectance(&scene(Value::Null).unwrap()), Vec3::splat(0.04));
    assert_eq!(normal_reflectance(&scene(json!(1.5)).unwrap()), Vec3::splat(0.04));
    let err = scene(json!(-1.0)).err().unwrap();
    assert!(err.contains("glass-like") && err.contains("ior"), "{err}");
}

/// KHR_materials_transmission turns the named share of the diffuse layer into a thin-walled
/// BTDF, without the unsupported-extension warning. A factor outside [0, 1] is refused with the
/// material named, and a transmission texture that does not exist is refused, not a panic.
#[test]
fn transmission_is_read_and_checked() {
    use tessera_render::bsdf::Fresnel;
    let scene = |transmission| dielectric_with("paper", "KHR_materials_transmission", transmission);
    let loaded = scene(json!({"transmissionFactor": 0.6})).unwrap();
    assert!(loaded.info.warnings.iter().all(|w| !w.contains("transmission")), "{:?}", loaded.info.warnings);
    let bsdf = first_bsdf(&loaded);
    assert!(bsdf.transmits());
    assert!(matches!(bsdf.fresnel, Fresnel::Gltf { transmission, .. } if transmission == 0.6), "{bsdf:?}");
    let err = scene(json!({"transmissionFactor": 1.5})).err().unwrap();
    assert!(err.contains("paper") && err.contains("transmissionFactor"), "{err}");
    let err = scene(json!({"transmissionTexture": {"index": 4}})).err().unwrap();
    assert!(err.contains("transmissionTexture") && err.contains("out of bounds"), "{err}");
}

/// KHR_materials_volume (which the glTF crate does not parse) with transmission makes a solid
/// that refracts: thickness above 0, the attenuation colour and distance read; thickness 0 (the
/// default) stays a thin wall; without transmission it is opaque as before. Bad numbers are
/// refused with the material named.
#[test]
fn volume_is_read_and_checked() {
    use tessera_render::bsdf::Fresnel;
    let scene = |volume: Value, transmission: f32| {
        let mut m = json!({"name": "bottle", "pbrMetallicRoughness": {"metallicFactor": 0.0}});
        m["extensions"] = json!({"KHR_materials_volume": volume, "KHR_materials_transmission": {"transmissionFactor": transmission},
            "KHR_materials_ior": {"ior": 1.4}});
        triangle_with_material(m, "KHR_materials_volume")
    };
    let loaded =
        scene(json!({"thicknessFactor": 0.2, "attenuationColor": [0.5, 0.8, 1.0], "attenuationDistance": 2.0}), 1.0)
            .unwrap();
    assert!(loaded.info.warnings.iter().all(|w| !w.contains("volume")), "{:?}", loaded.info.warnings);
    let material = &loaded.scene.surfaces.materials()[0];
    let volume = material.volume.expect("a solid");
    assert_eq!((volume.attenuation_color, volume.attenuation_distance), (Vec3::new(0.5, 0.8, 1.0), 2.0));
    assert!(material.refracts());
    let bsdf = first_bsdf(&loaded);
    assert!(
        bsdf.transmits()
            && bsdf.refraction.is_on()
            && matches!(bsdf.fresnel, Fresnel::Dielectric { eta } if eta == 1.4)
    );
    // Over 2 units of length the attenuation colour is kept, over 4 its square.
    let kept = material.absorption(4.0, &Rgb).unwrap();
    assert!((kept - Vec3::new(0.25, 0.64, 1.0)).abs().max_element() < 1e-6, "{kept}");
    let thin = scene(json!({}), 1.0).unwrap();
    assert!(thin.scene.surfaces.materials()[0].volume.is_none() && !thin.scene.surfaces.materials()[0].refracts());
    let opaque = scene(json!({"thicknessFactor": 1.0}), 0.0).unwrap();
    assert!(!opaque.scene.surfaces.materials()[0].refracts() && !first_bsdf(&opaque).transmits());
    for bad in
        [json!({"thicknessFactor": -1}), json!({"attenuationDistance": 0}), json!({"attenuationColor": [2, 0, 0]})]
    {
        let err = scene(bad.clone(), 1.0).err().unwrap();
        assert!(err.contains("bottle") && err.contains("KHR_materials_volume"), "{bad}: {err}");
    }
}

/// KHR_materials_anisotropy (which the glTF crate does not parse) stretches the specular lobe:
/// `alpha_t = mix(alpha, 1, strength^2)` along its direction, `alpha` across; the rotation is
/// read; the mesh gets tangents to turn with (MikkTSpace, as for a normal map). A strength
/// outside [0, 1], a rotation that is not a number or a texture that does not exist is refused
/// with the material named.
#[test]
fn anisotropy_is_read_and_checked() {
    let scene = |anisotropy| dielectric_with("brushed", "KHR_materials_anisotropy", anisotropy);
    let mut material =
        json!({"name": "brushed", "pbrMetallicRoughness": {"metallicFactor": 1.0, "roughnessFactor": 0.5}});
    material["extensions"] =
        json!({"KHR_materials_anisotropy": {"anisotropyStrength": 0.6, "anisotropyRotation": 1.0}});
    let mut doc = mesh_json(
        json!({"attributes": {"POSITION": 0, "NORMAL": 1, "TEXCOORD_0": 2}, "material": 0}),
        json!([{"buffer": 0, "byteLength": 36}, {"buffer": 0, "byteOffset": 36, "byteLength": 36},
               {"buffer": 0, "byteOffset": 72, "byteLength": 24}]),
        json!([{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3", "min": [0, 0, 0], "max": [1, 1, 0]},
               {"bufferView": 1, "componentType": 5126, "count": 3, "type": "VEC3"},
               {"bufferView": 2, "componentType": 5126, "count": 3, "type": "VEC2"}]),
        1.0,
    );
    doc["materials"] = json!([material]);
    doc["extensionsUsed"] = json!(["KHR_materials_anisotropy"]);
    let bin = f32s(&[
        0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 1.0, 0.0,
        0.0, 1.0,
    ]);
    let loaded = load(doc, &bin).unwrap();
    assert!(loaded.info.warnings.iter().all(|w| !w.contains("anisotropy")), "{:?}", loaded.info.warnings);
    let m = &loaded.scene.surfaces.materials()[0];
    assert_eq!((m.anisotropy_strength, m.anisotropy_rotation), (0.6, 1.0));
    let micro = first_bsdf(&loaded).microfacet;
    assert!((micro.alpha - (0.25 + 0.75 * 0.36)).abs() < 1e-6 && micro.alpha_across == 0.25, "{micro:?}");
    assert!(loaded.scene.mesh.tangents.iter().any(|t| t.truncate().length() > 0.5), "tangents were made");
    // A ray straight down at the triangle finds the direction: the tangent (+u, here +x) turned
    // by 1 radian towards the bitangent, in the tangent plane.
    let s = &loaded.scene;
    let (o, d) = (tessera_render::glam::Vec3::new(0.2, 0.2, 1.0), tessera_render::glam::Vec3::NEG_Z);
    let sp = s.surface(s.intersect(o, d, f32::INFINITY).unwrap(), o, d);
    let dir = sp.anisotropy.expect("an anisotropic point with tangents");
    assert!(
        dir.z.abs() < 1e-5 && (dir.x - libm::cosf(1.0)).abs() < 1e-4 && (dir.y.abs() - libm::sinf(1.0)).abs() < 1e-4,
        "{dir}"
    );
    for bad in [
        json!({"anisotropyStrength": 1.5}),
        json!({"anisotropyRotation": "left"}),
        json!({"anisotropyTexture": {"index": 2}}),
    ] {
        let err = scene(bad.clone()).err().unwrap();
        assert!(err.contains("brushed") && err.contains("anisotropy"), "{bad}: {err}");
    }
}

/// KHR_materials_clearcoat (which the glTF crate does not parse) puts its coat over the BSDF:
/// weight and roughness are read (roughness squared, as glTF's); a factor outside [0, 1] or a
/// texture that does not exist is refused with the material named.
#[test]
fn clearcoat_is_read_and_checked() {
    let scene = |coat| dielectric_with("lacquer", "KHR_materials_clearcoat", coat);
    let loaded = scene(json!({"clearcoatFactor": 0.8, "clearcoatRoughnessFactor": 0.25})).unwrap();
    assert!(loaded.info.warnings.iter().all(|w| !w.contains("clearcoat")), "{:?}", loaded.info.warnings);
    let coat = first_bsdf(&loaded).coat;
    assert_eq!((coat.weight, coat.microfacet.alpha), (0.8, 0.0625), "{coat:?}");
    assert_eq!(scene(json!({})).unwrap().scene.surfaces.materials()[0].clearcoat, 0.0, "the factor defaults to 0");
    let err = scene(json!({"clearcoatFactor": 2})).err().unwrap();
    assert!(err.contains("lacquer") && err.contains("clearcoatFactor"), "{err}");
    let err = scene(json!({"clearcoatFactor": 1, "clearcoatRoughnessTexture": {"index": 3}})).err().unwrap();
    assert!(err.contains("lacquer") && err.contains("clearcoatRoughnessTexture"), "{err}");
}

/// KHR_materials_sheen (which the glTF crate does not parse) lays its cloth lobe over the BSDF:
/// colour and roughness are read; a colour that is not three numbers in [0, 1] is refused with the
/// material named.
#[test]
fn sheen_is_read_and_checked() {
    let scene = |sheen| dielectric_with("velvet", "KHR_materials_sheen", sheen);
    let loaded = scene(json!({"sheenColorFactor": [0.9, 0.2, 0.1], "sheenRoughnessFactor": 0.4})).unwrap();
    assert!(loaded.info.warnings.iter().all(|w| !w.contains("sheen")), "{:?}", loaded.info.warnings);
    let sheen = first_bsdf(&loaded).sheen;
    assert_eq!((sheen.color, sheen.lobe.roughness), (Vec3::new(0.9, 0.2, 0.1), 0.4), "{sheen:?}");
    for bad in
        [json!({"sheenColorFactor": [1, 2, 0]}), json!({"sheenColorFactor": 1}), json!({"sheenRoughnessFactor": -1})]
    {
        let err = scene(bad.clone()).err().unwrap();
        assert!(err.contains("velvet") && err.contains("KHR_materials_sheen"), "{bad}: {err}");
    }
}

/// A clear coat keeps the geometry's normal where a normal map bends the layers below it (glTF:
/// without clearcoatNormalTexture the coat is not normal-mapped): on a quad whose map tilts the
/// shading normal 45 degrees, the coat's normal is still the quad's.
#[test]
fn a_clear_coat_is_not_normal_mapped() {
    use tessera_render::glam::Vec3;
    let material =
        json!({"normalTexture": {"index": 0}, "extensions": {"KHR_materials_clearcoat": {"clearcoatFactor": 1.0}}});
    let loaded = one_texel_quad([218, 128, 218, 255], material);
    let s = &loaded.scene;
    let (o, d) = (Vec3::new(0.4, 0.6, 1.0), Vec3::NEG_Z);
    let sp = s.surface(s.intersect(o, d, f32::INFINITY).expect("the ray meets the quad"), o, d);
    assert!((sp.frame.n.dot(Vec3::Z) - 0.5f32.sqrt()).abs() < 0.02, "the map tilts the shading normal: {}", sp.frame.n);
    let coat_normal = sp.coat_normal.expect("the coat has its own normal");
    assert!((coat_normal - Vec3::Z).length() < 1e-5, "coat normal {coat_normal}");
    let coat = s.bsdf(&sp, &Rgb, true).coat;
    assert!((coat.normal - sp.frame.to_local(Vec3::Z)).length() < 1e-5, "{coat:?}");
    assert!(coat.normal.z < 0.75, "the coat's normal leans in the BSDF's frame: {}", coat.normal);
}

/// KHR_materials_clearcoat's clearcoatNormalTexture bends the coat alone, by its own scale,
/// and the quad gets tangents for it without a base normal map; a scale that is not a number is
/// refused by name.
#[test]
fn a_clear_coat_takes_its_own_normal_map() {
    use tessera_render::glam::Vec3;
    let coat = |scale: Value| {
        json!({"extensions": {"KHR_materials_clearcoat":
            {"clearcoatFactor": 1.0, "clearcoatNormalTexture": {"index": 0, "scale": scale}}}})
    };
    // The texel (218, 128, 218) is the tangent-frame normal (0.71, 0, 0.71): 45 degrees towards
    // +x at scale 1, so x / z is the scale (26.6 degrees at 0.5).
    for scale in [1.0f32, 0.5] {
        let loaded = one_texel_quad([218, 128, 218, 255], coat(json!(scale)));
        let s = &loaded.scene;
        let (o, d) = (Vec3::new(0.4, 0.6, 1.0), Vec3::NEG_Z);
        let sp = s.surface(s.intersect(o, d, f32::INFINITY).expect("the ray meets the quad"), o, d);
        assert!((sp.frame.n - Vec3::Z).length() < 1e-5, "the base is not mapped: {}", sp.frame.n);
        let n = sp.coat_normal.expect("the coat has its own normal");
        assert!((n.x / n.z - scale).abs() < 0.02 && n.y.abs() < 0.02, "scale {scale}: coat normal {n}");
        assert!((s.bsdf(&sp, &Rgb, true).coat.normal - n).length() < 1e-5, "the BSDF's coat leans the same way");
    }
    let bad = one_image_quad(png([218, 128, 218, 255]), coat(json!("steep"))).err().expect("refused");
    assert!(bad.contains("clearcoatNormalTexture scale"), "{bad}");
}

/// A skinned mesh stands where its joints put it in the rest pose (glTF ignores the mesh node's
/// own transform then): each vertex moves by its joints' world transforms times their inverse
/// bind matrices, blended by its weights. Morph targets move vertices by their weights, the
/// node's overriding the mesh's defaults.
#[test]
fn skins_and_morph_targets_pose_the_rest_pose() {
    // A triangle skinned to two joints: vertex 0 wholly to joint 0, vertex 1 wholly to joint 1,
    // vertex 2 half and half. Joint 0 stands at y = 4 with an inverse bind matrix that moves
    // down by 1; joint 1 at the origin, rotated a quarter turn about z.
    let mut bin = f32s(&[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0]); // 0..36
    bin.extend([0u8, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0]); // joints 36..48
    bin.extend(f32s(&[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.5, 0.5, 0.0, 0.0])); // weights 48..96
    let down = [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, -1.0, 0.0, 1.0];
    let identity = [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0];
    bin.extend(f32s(&[down, identity].concat())); // inverse bind matrices 96..224
    bin.extend(f32s(&[0.0, 0.0, 1.0].repeat(3))); // a morph target: +z, 224..260
    let quarter = std::f32::consts::FRAC_1_SQRT_2;
    let doc = |node_weights: Option<f32>| {
        let mut mesh_node = json!({"mesh": 0, "skin": 0, "scale": [100, 100, 100]});
        if let Some(w) = node_weights {
            mesh_node["weights"] = json!([w]);
        }
        json!({
            "scene": 0, "scenes": [{"nodes": [0, 1, 2]}],
            "nodes": [mesh_node, {"translation": [0, 4, 0]}, {"rotation": [0, 0, quarter, quarter]}],
            "skins": [{"joints": [1, 2], "inverseBindMatrices": 3}],
            "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "JOINTS_0": 1, "WEIGHTS_0": 2},
                                        "targets": [{"POSITION": 4}]}], "weights": [0.5]}],
            "bufferViews": [{"buffer": 0, "byteLength": 36}, {"buffer": 0, "byteOffset": 36, "byteLength": 12},
                            {"buffer": 0, "byteOffset": 48, "byteLength": 48},
                            {"buffer": 0, "byteOffset": 96, "byteLength": 128},
                            {"buffer": 0, "byteOffset": 224, "byteLength": 36}],
            "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3",
                           "min": [0, 0, 0], "max": [1, 1, 0]},
                          {"bufferView": 1, "componentType": 5121, "count": 3, "type": "VEC4"},
                          {"bufferView": 2, "componentType": 5126, "count": 3, "type": "VEC4"},
                          {"bufferView": 3, "componentType": 5126, "count": 2, "type": "MAT4"},
                          {"bufferView": 4, "componentType": 5126, "count": 3, "type": "VEC3",
                           "min": [0, 0, 1], "max": [0, 0, 1]}],
        })
    };
    let corners = |node_weights| {
        let loaded = load(doc(node_weights), &bin).unwrap();
        let s = &loaded.scene;
        let mut v: Vec<[f32; 3]> =
            s.mesh.triangles[0].vertices.iter().map(|&i| s.mesh.positions[i as usize].to_array()).collect();
        v.sort_by(|a, b| a.partial_cmp(b).unwrap());
        v
    };
    let close = |got: Vec<[f32; 3]>, want: [[f32; 3]; 3]| {
        for w in want {
            let near = |g: &[f32; 3]| g.iter().zip(w).all(|(a, b)| (a - b).abs() < 1e-5);
            assert!(got.iter().any(near), "{w:?} is not among {got:?}");
        }
    };
    // The mesh's default weight 0.5 lifts every vertex by z = 0.5 before skinning. Vertex 0:
    // (0, 0, 0.5) -> down 1, up 4 -> (0, 3, 0.5). Vertex 1: (1, 0, 0.5) turned a quarter about z
    // -> (0, 1, 0.5). Vertex 2: (0, 1, 0.5) -> half (0, 4, 0.5) and half (-1, 0, 0.5).
    close(corners(None), [[0.0, 3.0, 0.5], [0.0, 1.0, 0.5], [-0.5, 2.0, 0.5]]);
    // The node's weight 1 overrides the mesh's 0.5.
    close(corners(Some(1.0)), [[0.0, 3.0, 1.0], [0.0, 1.0, 1.0], [-0.5, 2.0, 1.0]]);
}
