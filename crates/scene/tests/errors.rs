//! Bad input gets a clear error that names the file and the problem, never a panic.

mod common;

use common::fixtures_dir;
use std::path::PathBuf;
use tessera_scene::{LoadError, LoadOptions, load, load_bytes};

/// A file named `name` in a directory of its own, removed when dropped.
struct TempFile {
    path: PathBuf,
    _dir: tempfile::TempDir,
}

impl std::ops::Deref for TempFile {
    type Target = std::path::Path;
    fn deref(&self) -> &std::path::Path {
        &self.path
    }
}

fn temp_file(name: &str, bytes: &[u8]) -> TempFile {
    let dir = tempfile::Builder::new().prefix("tessera-scene-errors-").tempdir().unwrap();
    let path = dir.path().join(name);
    std::fs::write(&path, bytes).unwrap();
    TempFile { path, _dir: dir }
}

fn load_err(path: &std::path::Path) -> String {
    match load(path.to_str().unwrap(), &LoadOptions::default()) {
        Ok(_) => panic!("{} loaded", path.display()),
        Err(e) => e.to_string(),
    }
}

#[test]
fn missing_files_are_named() {
    let err = load_err(std::path::Path::new("/nonexistent/scene.gltf"));
    assert!(err.contains("/nonexistent/scene.gltf"), "{err}");
}

/// A `.gltf` whose `.bin` (or texture) was not copied with it: the missing file is named, and
/// what to do said; so is a scene in another tool's format.
#[test]
fn a_missing_bin_is_named_and_other_formats_get_a_way_in() {
    let gltf = std::fs::read(fixtures_dir().join("AnimatedTriangle/glTF/AnimatedTriangle.gltf")).unwrap();
    let alone = temp_file("AnimatedTriangle.gltf", &gltf);
    let e = load_err(&alone);
    assert!(
        e.contains("'simpleTriangle.bin', which it references, is missing")
            && e.contains("export the scene as one .glb"),
        "{e}"
    );
    let e = tessera_scene::pack(alone.to_str().unwrap()).unwrap_err().to_string();
    assert!(e.contains("'simpleTriangle.bin', which it references, is missing"), "{e}");
    for (name, says) in
        [("a.blend", "File > Export > glTF 2.0"), ("a.obj", "Convert it to glTF 2.0"), ("a.FBX", "FBX2glTF")]
    {
        let e = load_err(&temp_file(name, b"not glTF"));
        assert!(e.contains(says), "{name}: {e}");
    }
}

#[test]
fn random_bytes_and_truncated_glb_are_refused() {
    let noise: Vec<u8> = (0..4096u32).map(|i| (i.wrapping_mul(2654435761) >> 13) as u8).collect();
    let err = load_err(&temp_file("noise.glb", &noise));
    assert!(err.contains("noise.glb"), "{err}");
    let glb = std::fs::read(fixtures_dir().join("Box/glTF-Binary/Box.glb")).unwrap();
    for cut in [12, 20, 100, glb.len() / 2, glb.len() - 1] {
        let err = load_err(&temp_file("truncated.glb", &glb[..cut]));
        assert!(err.contains("truncated.glb"), "cut at {cut}: {err}");
    }
    // Every prefix of a real file either loads or fails cleanly (no panic).
    for cut in (0..glb.len()).step_by(37) {
        let _ = load_bytes(&glb[..cut], None, "prefix", &LoadOptions::default());
    }
}

#[test]
fn unsupported_required_extensions_are_named() {
    let gltf = r#"{"asset":{"version":"2.0"},"extensionsUsed":["KHR_draco_mesh_compression"],
        "extensionsRequired":["KHR_draco_mesh_compression"],"scenes":[{"nodes":[]}],"scene":0}"#;
    let err = load_err(&temp_file("draco.gltf", gltf.as_bytes()));
    assert!(err.contains("KHR_draco_mesh_compression") && err.contains("extensionsRequired"), "{err}");
}

#[test]
fn unsupported_optional_extensions_warn_once_by_name() {
    let gltf = r#"{"asset":{"version":"2.0"},"extensionsUsed":["KHR_materials_dispersion","KHR_materials_iridescence"],
        "scenes":[{"nodes":[]}],"scene":0}"#;
    let loaded = load(temp_file("volume.gltf", gltf.as_bytes()).to_str().unwrap(), &LoadOptions::default()).unwrap();
    let warnings: Vec<&String> = loaded.info.warnings.iter().filter(|w| w.contains("unsupported extension")).collect();
    assert_eq!(warnings.len(), 1, "{:?}", loaded.info.warnings);
    assert!(warnings[0].contains("KHR_materials_dispersion") && warnings[0].contains("KHR_materials_iridescence"));
    assert!(warnings[0].contains("one index for all"), "says what they look like instead: {}", warnings[0]);
}

#[test]
fn bad_material_extras_name_the_material() {
    let gltf = r#"{"asset":{"version":"2.0"},"materials":[{"name":"brass","extras":{"tessera":{"distribution":"phong"}}}],
        "scenes":[{"nodes":[]}],"scene":0}"#;
    let err = load_err(&temp_file("extras.gltf", gltf.as_bytes()));
    assert!(err.contains("brass") && err.contains("phong"), "{err}");
}

#[test]
fn out_of_range_indices_are_refused() {
    // One triangle whose third index (7) points past the 3 vertices.
    let positions: Vec<u8> =
        [0f32, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0].iter().flat_map(|f| f.to_le_bytes()).collect();
    let indices: Vec<u8> = [0u16, 1, 7, 0].iter().flat_map(|i| i.to_le_bytes()).collect();
    let mut bin = positions.clone();
    bin.extend(&indices);
    let uri = format!("data:application/octet-stream;base64,{}", base64(&bin));
    let gltf = format!(
        r#"{{"asset":{{"version":"2.0"}},"buffers":[{{"byteLength":{len},"uri":"{uri}"}}],
        "bufferViews":[{{"buffer":0,"byteOffset":0,"byteLength":36}},{{"buffer":0,"byteOffset":36,"byteLength":6}}],
        "accessors":[{{"bufferView":0,"componentType":5126,"count":3,"type":"VEC3","min":[0,0,0],"max":[1,1,0]}},
                     {{"bufferView":1,"componentType":5123,"count":3,"type":"SCALAR"}}],
        "meshes":[{{"name":"bad","primitives":[{{"attributes":{{"POSITION":0}},"indices":1}}]}}],
        "nodes":[{{"mesh":0}}],"scenes":[{{"nodes":[0]}}],"scene":0}}"#,
        len = bin.len()
    );
    let err = load_err(&temp_file("indices.gltf", gltf.as_bytes()));
    assert!(err.contains("index 7") && err.contains("bad"), "{err}");
}

#[test]
fn unknown_builtins_list_the_available_ones() {
    let err = load("builtin:teapot", &LoadOptions::default()).err().unwrap();
    assert!(matches!(err, LoadError::UnknownBuiltin(..)));
    assert!(err.to_string().contains("cornell-box"), "{err}");
    let err = load("builtin:furnace?roughness=7", &LoadOptions::default()).err().unwrap().to_string();
    assert!(err.contains("roughness"), "{err}");
    let err = load("scene.obj", &LoadOptions::default()).err().unwrap().to_string();
    assert!(err.contains("scene.obj") && err.contains(".gltf"), "{err}");
}

fn base64(data: &[u8]) -> String {
    const T: &[u8] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut s = String::new();
    for c in data.chunks(3) {
        let b = [c[0], *c.get(1).unwrap_or(&0), *c.get(2).unwrap_or(&0)];
        let n = (b[0] as u32) << 16 | (b[1] as u32) << 8 | b[2] as u32;
        for i in 0..4 {
            if i <= c.len() {
                s.push(T[(n >> (18 - 6 * i) & 63) as usize] as char);
            } else {
                s.push('=');
            }
        }
    }
    s
}

#[test]
fn degenerate_cameras_are_refused_by_name() {
    let gltf = r#"{"asset":{"version":"2.0"},"cameras":[{"name":"flat","type":"perspective","perspective":{"yfov":0.0,"znear":0.1}}],
        "nodes":[{"camera":0}],"scenes":[{"nodes":[0]}],"scene":0}"#;
    let err = load_err(&temp_file("camera.gltf", gltf.as_bytes()));
    assert!(err.contains("flat") && err.contains("yfov"), "{err}");
}

/// A glTF of `nodes` (JSON) over one triangle, in a data URI.
fn one_triangle_gltf(nodes: &str, scene_nodes: &str) -> String {
    // Three float VEC3 positions: (0,0,0), (1,0,0), (0,1,0).
    let floats: [f32; 9] = [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0];
    let bytes: Vec<u8> = floats.iter().flat_map(|f| f.to_le_bytes()).collect();
    let b64 = base64_encode(&bytes);
    format!(
        r#"{{"asset":{{"version":"2.0"}},"scene":0,"scenes":[{{"nodes":{scene_nodes}}}],"nodes":{nodes},
        "meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}}}}]}}],
        "accessors":[{{"bufferView":0,"componentType":5126,"count":3,"type":"VEC3","min":[0,0,0],"max":[1,1,0]}}],
        "bufferViews":[{{"buffer":0,"byteLength":36}}],
        "buffers":[{{"byteLength":36,"uri":"data:application/octet-stream;base64,{b64}"}}]}}"#
    )
}

/// Base64 as data URIs carry it (the crate the loader reads them with).
fn base64_encode(bytes: &[u8]) -> String {
    use base64::Engine;
    base64::engine::general_purpose::STANDARD.encode(bytes)
}

fn bytes_err(json: &str) -> String {
    match load_bytes(json.as_bytes(), None, "graph.gltf", &LoadOptions::default()) {
        Ok(l) => panic!("loaded with {} triangles", l.info.triangles),
        Err(e) => e.to_string(),
    }
}

/// A kilobyte of nodes whose children are shared stands for 2^40 instances: it once grew a
/// client to 24 GB. Node hierarchies must be trees, and are checked before anything expands.
#[test]
fn nodes_that_share_children_or_loop_are_refused() {
    let chain: Vec<String> = (0..40).map(|i| format!(r#"{{"children":[{},{}]}}"#, i + 1, i + 1)).collect();
    let nodes = format!(r#"[{},{{"mesh":0}}]"#, chain.join(","));
    assert!(nodes.len() < 1100);
    let err = bytes_err(&one_triangle_gltf(&nodes, "[0]"));
    assert!(err.contains("node 1 is a child of both node 0 and node 0") && err.contains("trees"), "{err}");
    let err = bytes_err(&one_triangle_gltf(r#"[{"children":[2]},{"children":[2]},{"mesh":0}]"#, "[0,1]"));
    assert!(err.contains("node 2 is a child of both node 0 and node 1"), "{err}");
    let err = bytes_err(&one_triangle_gltf(r#"[{"mesh":0,"children":[1]},{"children":[0]}]"#, "[0]"));
    assert!(err.contains("has a parent"), "{err}");
    let err = bytes_err(&one_triangle_gltf(r#"[{"mesh":0},{"children":[2]},{"children":[1]}]"#, "[0]"));
    assert!(err.contains("its own ancestor"), "{err}");
    let err = bytes_err(&one_triangle_gltf(r#"[{"mesh":0}]"#, "[0,0]"));
    assert!(err.contains("lists node 0 twice"), "{err}");
    // A proper tree loads.
    let ok = one_triangle_gltf(r#"[{"children":[1,2]},{"mesh":0},{"mesh":0,"translation":[2,0,0]}]"#, "[0]");
    let loaded = load_bytes(ok.as_bytes(), None, "tree.gltf", &LoadOptions::default()).unwrap();
    assert_eq!(loaded.info.triangles, 2);
}

/// A mesh that reuses one large index accessor in many primitives draws far more triangles
/// than its file suggests; the count is bounded from the accessors before anything expands.
#[test]
fn triangle_counts_are_bounded_before_expanding() {
    let triangles: u64 = 1 << 20;
    let primitives = tessera_scene::MAX_TRIANGLES / triangles + 1;
    let prim = serde_json::json!({"attributes": {"POSITION": 0}, "indices": 1});
    let json = serde_json::json!({
        "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": vec![prim; primitives as usize]}],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3", "min": [0, 0, 0], "max": [1, 1, 0]},
            {"bufferView": 1, "componentType": 5121, "count": 3 * triangles, "type": "SCALAR"}
        ],
        "bufferViews": [
            {"buffer": 0, "byteLength": 36},
            {"buffer": 0, "byteOffset": 36, "byteLength": 3 * triangles}
        ]
    });
    let glb = common::glb(json, &vec![0u8; 36 + 3 * triangles as usize]);
    let started = std::time::Instant::now();
    let err = match load_bytes(&glb, None, "many.glb", &LoadOptions::default()) {
        Ok(l) => panic!("loaded with {} triangles", l.info.triangles),
        Err(e) => e.to_string(),
    };
    assert!(err.contains(&format!("draws {} triangles", primitives * triangles)) && err.contains("limit"), "{err}");
    eprintln!("refused in {:.2} s", started.elapsed().as_secs_f64());
}

/// CRC-32 (ISO-HDLC), as PNG chunks carry it.
fn crc32(bytes: &[u8]) -> u32 {
    let mut crc = !0u32;
    for &b in bytes {
        crc ^= b as u32;
        for _ in 0..8 {
            crc = if crc & 1 == 1 { (crc >> 1) ^ 0xEDB8_8320 } else { crc >> 1 };
        }
    }
    !crc
}

/// A PNG whose header claims `width` x `height` pixels, with one byte of image data: what a
/// decompression bomb looks like to a header reader.
fn png_claiming(width: u32, height: u32) -> Vec<u8> {
    let mut png = b"\x89PNG\r\n\x1a\n".to_vec();
    let mut chunk = |kind: &[u8], data: &[u8]| {
        png.extend_from_slice(&(data.len() as u32).to_be_bytes());
        let body: Vec<u8> = kind.iter().chain(data).copied().collect();
        png.extend_from_slice(&body);
        png.extend_from_slice(&crc32(&body).to_be_bytes());
    };
    let mut ihdr = Vec::new();
    ihdr.extend_from_slice(&width.to_be_bytes());
    ihdr.extend_from_slice(&height.to_be_bytes());
    ihdr.extend_from_slice(&[8, 6, 0, 0, 0]); // 8-bit RGBA
    chunk(b"IHDR", &ihdr);
    chunk(b"IDAT", &[0x78, 0x9c]);
    chunk(b"IEND", &[]);
    png
}

/// A small PNG that inflates to gigabytes is refused from its header, before any decoding.
#[test]
fn huge_textures_are_refused_before_decoding() {
    let with_texture = |png: &[u8]| {
        let gltf = one_triangle_gltf(r#"[{"mesh":0}]"#, "[0]");
        let uri = format!("data:image/png;base64,{}", base64_encode(png));
        gltf.replacen(
            r#""meshes":[{"primitives":[{"attributes":{"POSITION":0}}]}],"#,
            &format!(
                r#""meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}},"material":0}}]}}],
                "materials":[{{"pbrMetallicRoughness":{{"baseColorTexture":{{"index":0}}}}}}],
                "textures":[{{"source":0}}],"images":[{{"uri":"{uri}"}}],"#
            ),
            1,
        )
    };
    let err = bytes_err(&with_texture(&png_claiming(20_000, 20_000)));
    assert!(err.contains("20000x20000") && err.contains("checked before decoding"), "{err}");
    // The same file with a sane size gets as far as decoding its (broken) data.
    let err = bytes_err(&with_texture(&png_claiming(4, 4)));
    assert!(!err.contains("checked before decoding"), "{err}");
}
