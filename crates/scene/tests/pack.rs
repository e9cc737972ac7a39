//! Packing a .gltf with its external files into one GLB keeps the scene: the packed scene
//! renders to the same bits as the original.

mod common;

use common::{fixtures_dir, render, settings, shared_scenes_dir};
use tessera_render::Estimator;
use tessera_scene::{LoadOptions, load, load_packed, pack};

fn same_render(spec: &str) {
    let original = load(spec, &LoadOptions::default()).unwrap();
    let bytes = pack(spec).unwrap();
    assert!(bytes.starts_with(b"glTF") || spec.starts_with("builtin:"));
    let packed = load_packed(&bytes, spec, &LoadOptions::default()).unwrap();
    assert_eq!(original.info.triangles, packed.info.triangles, "{spec}");
    let s = settings(24, 16, Estimator::Mis);
    assert!(render(&original.scene, &s, 2) == render(&packed.scene, &s, 2), "{spec}: packed scene renders differently");
}

#[test]
fn packed_scenes_render_the_same() {
    same_render(&fixtures_dir().join("Cameras/glTF/Cameras.gltf").display().to_string());
    same_render(&fixtures_dir().join("CornellBox/glTF/CornellBox.gltf").display().to_string());
    same_render(&fixtures_dir().join("Duck/glTF-Binary/Duck.glb").display().to_string());
    same_render("builtin:cornell-box");
}

#[test]
fn external_textures_are_packed() {
    // A textured quad whose image and buffer are separate files.
    let scratch = tempfile::Builder::new().prefix("tessera-pack-").tempdir().unwrap();
    let dir = scratch.path();
    let img = image::RgbaImage::from_fn(4, 4, |x, y| image::Rgba([(x * 60) as u8, (y * 60) as u8, 200, 255]));
    img.save(dir.join("checker.png")).unwrap();
    let mut bin = Vec::new();
    for v in [[0f32, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]] {
        for c in v {
            bin.extend_from_slice(&c.to_le_bytes());
        }
    }
    for uv in [[0f32, 1.0], [1.0, 1.0], [1.0, 0.0], [0.0, 0.0]] {
        for c in uv {
            bin.extend_from_slice(&c.to_le_bytes());
        }
    }
    for i in [0u16, 1, 2, 0, 2, 3] {
        bin.extend_from_slice(&i.to_le_bytes());
    }
    std::fs::write(dir.join("quad.bin"), &bin).unwrap();
    let gltf = format!(
        r#"{{"asset":{{"version":"2.0"}},"buffers":[{{"uri":"quad.bin","byteLength":{}}}],
        "bufferViews":[{{"buffer":0,"byteOffset":0,"byteLength":48}},{{"buffer":0,"byteOffset":48,"byteLength":32}},{{"buffer":0,"byteOffset":80,"byteLength":12}}],
        "accessors":[{{"bufferView":0,"componentType":5126,"count":4,"type":"VEC3","min":[0,0,0],"max":[1,1,0]}},
                     {{"bufferView":1,"componentType":5126,"count":4,"type":"VEC2"}},
                     {{"bufferView":2,"componentType":5123,"count":6,"type":"SCALAR"}}],
        "images":[{{"uri":"checker.png"}}],"textures":[{{"source":0}}],
        "materials":[{{"pbrMetallicRoughness":{{"baseColorTexture":{{"index":0}},"metallicFactor":0}}}}],
        "meshes":[{{"primitives":[{{"attributes":{{"POSITION":0,"TEXCOORD_0":1}},"indices":2,"material":0}}]}}],
        "nodes":[{{"mesh":0}}],"scenes":[{{"nodes":[0]}}],"scene":0}}"#,
        bin.len()
    );
    let path = dir.join("quad.gltf");
    std::fs::write(&path, gltf).unwrap();
    same_render(path.to_str().unwrap());

    // A URI escaping the folder is refused by name.
    let evil = std::fs::read_to_string(&path).unwrap().replace("\"quad.bin\"", "\"../quad.bin\"");
    let evil_path = dir.join("evil.gltf");
    std::fs::write(&evil_path, evil).unwrap();
    let err = pack(evil_path.to_str().unwrap()).unwrap_err().to_string();
    assert!(err.contains("../quad.bin") && err.contains("outside"), "{err}");
}

#[test]
fn shared_scenes_with_external_files_pack() {
    let Some(dir) = shared_scenes_dir() else {
        eprintln!("skipped: ../shared/scenes is not present beside this checkout");
        return;
    };
    same_render(&dir.join("Suzanne/glTF/Suzanne.gltf").display().to_string());
}
