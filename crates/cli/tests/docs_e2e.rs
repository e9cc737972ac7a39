//! The docs check: the `tessera` commands the README and the guides show, run. Every one is
//! parsed by the binary's own parser in its unit tests; here the quick ones run for real (renders
//! and scene listings, shrunk to a few pixels and samples), so an example that no longer works
//! fails CI. The examples' own file names stand for fixtures of the same kind (`model.glb` a
//! model with two cameras, `walk.glb` an animated one, `scene.gltf` a glTF with its files beside it,
//! `sky.hdr` a small map made here). The farm walkthrough is `deploy_e2e.rs`'s; commands that need
//! a farm, other files or minutes are left to the parse check.

use std::path::Path;
use std::process::Command;

use crate::common;
#[path = "common/docs.rs"]
mod docs;

fn bin() -> &'static str {
    env!("CARGO_BIN_EXE_tessera")
}

/// Flags whose value is replaced to keep a run small, and flags dropped with their value.
const SHRUNK: [(&str, &str); 4] = [("--width", "24"), ("--height", "16"), ("--spp", "2"), ("--frames", "1-2")];
const DROPPED: [&str; 2] = ["--min-spp", "--target-error"];

/// The fixtures the examples' file names stand for.
const STAND_INS: [(&str, &str); 3] = [
    ("model.glb", "crates/scene/tests/fixtures/scenes/Cameras/glTF/Cameras.gltf"),
    ("walk.glb", "crates/scene/tests/fixtures/scenes/BoxAnimated/glTF-Binary/BoxAnimated.glb"),
    ("scene.gltf", "crates/scene/tests/fixtures/scenes/CornellBox/glTF/CornellBox.gltf"),
];

/// `args` shrunk to run in a moment, with paths resolved against the repository (an example's
/// file name as its stand-in, `sky.hdr` in `dir`); `None` where it needs what is not here.
fn quick(args: &[String], repo: &Path, dir: &Path) -> Option<Vec<String>> {
    let (sub, rest) = args.split_first()?;
    if !matches!(sub.as_str(), "render" | "scene-info") {
        return None;
    }
    let exists = |p: &str| {
        let p = STAND_INS.iter().find(|(name, _)| *name == p).map_or(p, |(_, fixture)| fixture);
        [dir.join(p), repo.join(p)].into_iter().find(|f| f.exists()).map(|f| f.display().to_string())
    };
    let mut out = vec![sub.clone()];
    let mut words = rest.iter().peekable();
    if let Some(scene) = words.next_if(|w| !w.starts_with("--")) {
        out.push(if scene.starts_with("builtin:") { scene.clone() } else { exists(scene)? });
    }
    while let Some(flag) = words.next() {
        let value = words.next_if(|w| !w.starts_with("--"));
        if DROPPED.contains(&flag.as_str()) {
            continue;
        }
        out.push(flag.clone());
        match (SHRUNK.iter().find(|(f, _)| f == flag), value) {
            (Some((_, small)), Some(_)) => out.push(small.to_string()),
            (None, Some(v)) if flag == "--env" && (v.ends_with(".hdr") || v.ends_with(".exr")) => out.push(exists(v)?),
            (None, Some(v)) => out.push(v.clone()),
            (_, None) => {}
        }
    }
    if sub == "render" {
        for (flag, small) in &SHRUNK[..3] {
            if !out.iter().any(|w| w == flag) {
                out.extend([flag.to_string(), small.to_string()]);
            }
        }
        if !out.iter().any(|w| w == "--quiet") {
            out.push("--quiet".into());
        }
    }
    Some(out)
}

#[test]
fn the_quick_documented_commands_run() {
    let repo = docs::repository(env!("CARGO_MANIFEST_DIR"));
    let dir = common::scratch("docs", "quick");
    write_sky(&dir.join("sky.hdr"));
    let (mut ran, mut failed) = (Vec::new(), Vec::new());
    for command in docs::documented_commands(&repo) {
        let Some(args) = quick(&command.args, &repo, &dir) else { continue };
        let output = Command::new(bin()).args(&args).current_dir(&dir).output().unwrap();
        if output.status.success() {
            ran.push(command.to_string());
        } else {
            let stderr = String::from_utf8_lossy(&output.stderr);
            failed.push(format!("{command}\n  ran as: tessera {}\n  {}", args.join(" "), stderr.trim()));
        }
    }
    assert!(failed.is_empty(), "documented commands that fail:\n{}", failed.join("\n"));
    assert!(ran.len() >= 12, "only {} documented commands ran: {ran:#?}", ran.len());
}

/// A small equirectangular map, brighter above: what `sky.hdr` stands for.
fn write_sky(path: &Path) {
    let (w, h) = (16usize, 8usize);
    let texels: Vec<image::Rgb<f32>> =
        (0..w * h).map(|i| image::Rgb([1.0, 0.9, 0.8].map(|c| c * (2.0 - (i / w) as f32 / h as f32)))).collect();
    let file = std::io::BufWriter::new(std::fs::File::create(path).unwrap());
    image::codecs::hdr::HdrEncoder::new(file).encode(&texels, w, h).unwrap();
}

#[test]
fn commands_are_shrunk_and_example_files_skipped() {
    let repo = docs::repository(env!("CARGO_MANIFEST_DIR"));
    let dir = common::scratch("docs", "shrunk");
    let words = |s: &str| s.split_whitespace().map(str::to_string).collect::<Vec<_>>();
    let shrunk = quick(&words("render builtin:macbeth-scene --width 384 --height 256 --color spectral"), &repo, &dir);
    assert_eq!(
        shrunk.unwrap().join(" "),
        "render builtin:macbeth-scene --width 24 --height 16 --color spectral --spp 2 --quiet"
    );
    assert!(quick(&words("render model.glb --env sky.hdr"), &repo, &dir).is_none(), "no sky.hdr made there");
    assert!(quick(&words("render other.glb"), &repo, &dir).is_none(), "no stand-in for other.glb");
    assert!(quick(&words("submit builtin:cornell-box"), &repo, &dir).is_none(), "no farm here");
    let frames = quick(&words("render --frames 1-48 --min-spp 64 --out shot.####.exr"), &repo, &dir).unwrap();
    assert_eq!(frames.join(" "), "render --frames 1-2 --out shot.####.exr --width 24 --height 16 --spp 2 --quiet");
}
