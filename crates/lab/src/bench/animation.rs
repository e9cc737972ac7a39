//! `tessera bench animation`: what a frame of a sequence costs besides rendering it (posing the
//! scene and building its BVH again), and sequence throughput in frames per minute on this
//! machine alone and through a farm of 1 and 2 local workers.

use crate::bench::{median, options_from, time};
use anyhow::{Context, Result, bail};
use clap::Args;
use indicatif::ProgressBar;
use std::path::PathBuf;
use std::process::Command;
use tessera_local::render_film;
use tessera_scene::animation::Choice;
use tessera_scene::{LoadOptions, PoseAt};

#[derive(Args, Debug)]
pub struct AnimationBenchArgs {
    /// Skinned scene to pose [default: the CesiumMan test fixture, from the project's root].
    #[arg(long, env = "TESSERA_BENCH_SCENE")]
    pub scene: Option<PathBuf>,
    /// A large static scene moved by a node animation added here [default:
    /// MetalRoughSpheresNoTextures from ../shared/scenes, skipped when absent].
    #[arg(long, env = "TESSERA_BENCH_LARGE")]
    pub large: Option<PathBuf>,
    /// Image side of the frames rendered.
    #[arg(long, default_value_t = 256, env = "TESSERA_BENCH_SIZE")]
    pub size: u32,
    /// Samples per pixel of each frame.
    #[arg(long, default_value_t = 64, env = "TESSERA_BENCH_SPP")]
    pub spp: u32,
    /// Frames of the sequence throughput runs.
    #[arg(long, default_value_t = 12, env = "TESSERA_BENCH_FRAMES")]
    pub frames: u32,
    /// Repetitions; medians are reported.
    #[arg(long, default_value_t = 3, env = "TESSERA_BENCH_REPEAT")]
    pub repeat: usize,
}

pub fn animation(args: AnimationBenchArgs) -> Result<()> {
    let skinned = args
        .scene
        .clone()
        .unwrap_or_else(|| PathBuf::from("crates/scene/tests/fixtures/scenes/CesiumMan/glTF-Binary/CesiumMan.glb"));
    if !skinned.is_file() {
        bail!("{}: not found (run from the project's root, or give --scene)", skinned.display());
    }
    let skinned_bytes = std::fs::read(&skinned).with_context(|| skinned.display().to_string())?;
    println!(
        "posing and BVH building per frame, against rendering the frame ({0}x{0}, {1} spp, all threads):",
        args.size, args.spp
    );
    pose_cost(&skinned.display().to_string(), &skinned_bytes, &args)?;
    let large = args.large.clone().unwrap_or_else(|| {
        PathBuf::from("../shared/scenes/MetalRoughSpheresNoTextures/glTF-Binary/MetalRoughSpheresNoTextures.glb")
    });
    match std::fs::read(&large) {
        Ok(bytes) => pose_cost(&format!("{} + a root rotation", large.display()), &with_root_rotation(&bytes)?, &args)?,
        Err(e) => println!("{}: skipped ({e})", large.display()),
    }
    println!();
    throughput(&skinned.display().to_string(), &args)
}

/// Median time to pose the scene at a frame's time (meshes skinned or moved, BVH rebuilt),
/// against the median time to render that frame.
fn pose_cost(name: &str, bytes: &[u8], args: &AnimationBenchArgs) -> Result<()> {
    let source = tessera_scene::open_bytes(bytes, None, name)?;
    let duration = source.animations().iter().filter_map(|c| c.as_ref().ok()).map(|c| c.duration()).fold(0.0, f32::max);
    let times: Vec<f32> =
        (0..args.repeat.max(1) * 3).map(|i| duration * (i as f32 + 0.5) / (args.repeat.max(1) * 3) as f32).collect();
    let pose = |t: f32| LoadOptions { pose: Some(PoseAt { animation: Choice::All, time: t }), ..Default::default() };
    let mut posing = Vec::new();
    let mut triangles = 0;
    for &t in &times {
        let mut loaded = None;
        posing.push(time(|| loaded = Some(source.pose(&pose(t)))));
        triangles = loaded.expect("timed")?.info.triangles;
    }
    let options = options_from(&[
        "--width",
        &args.size.to_string(),
        "--height",
        &args.size.to_string(),
        "--spp",
        &args.spp.to_string(),
        "--quality",
        "fixed",
    ]);
    let loaded = source.pose(&pose(times[0]))?;
    let (settings, _) = options.settings(&loaded.scene)?;
    let (sampling, _) = options.sampling()?;
    let mut rendering = Vec::new();
    for _ in 0..args.repeat.max(1) {
        let mut result = Ok(());
        rendering.push(time(|| {
            result = render_film(&loaded.scene, &settings, sampling, 0, &ProgressBar::hidden()).map(|_| ())
        }));
        result?;
    }
    let (p, r) = (median(posing), median(rendering));
    println!(
        "  {name}: {triangles} triangles; pose + BVH {:.1} ms (median of {}), frame {:.0} ms (median of {}): posing is {:.1} % of a frame",
        p * 1e3,
        times.len(),
        r * 1e3,
        args.repeat.max(1),
        100.0 * p / (p + r)
    );
    Ok(())
}

/// `bytes` (a GLB) with an animation that turns its scene's root nodes a full turn about y in
/// 2 s, so that every mesh moves and every frame rebuilds the whole BVH.
fn with_root_rotation(bytes: &[u8]) -> Result<Vec<u8>> {
    // GLB: a 12-byte header, then chunks of (length, type, data): JSON, then BIN.
    let word = |at: usize| bytes.get(at..at + 4).map(|w| u32::from_le_bytes([w[0], w[1], w[2], w[3]]) as usize);
    let json_len = word(12).filter(|_| bytes.starts_with(b"glTF")).context("not a GLB file")?;
    let json_bytes = bytes.get(20..20 + json_len).context("a truncated GLB file")?;
    let mut json: serde_json::Value = serde_json::from_slice(json_bytes)?;
    let bin_at = 20 + json_len;
    let mut bin = match word(bin_at) {
        Some(n) => bytes.get(bin_at + 8..bin_at + 8 + n).context("a truncated GLB file")?.to_vec(),
        None => Vec::new(),
    };
    bin.resize(bin.len().next_multiple_of(4), 0);
    let offset = bin.len();
    let (times, turns): (Vec<f32>, Vec<[f32; 4]>) = (0..5)
        .map(|k| {
            let half = std::f32::consts::PI * k as f32 / 4.0;
            (k as f32 * 0.5, [0.0, libm::sinf(half), 0.0, libm::cosf(half)])
        })
        .unzip();
    bin.extend(times.iter().flat_map(|t| t.to_le_bytes()));
    bin.extend(turns.iter().flatten().flat_map(|t| t.to_le_bytes()));
    let views = json["bufferViews"].as_array().map_or(0, Vec::len);
    let accessors = json["accessors"].as_array().map_or(0, Vec::len);
    let push = |json: &mut serde_json::Value, key: &str, v: serde_json::Value| {
        json[key].as_array_mut().map(|a| a.push(v.clone())).unwrap_or_else(|| json[key] = serde_json::json!([v]));
    };
    push(&mut json, "bufferViews", serde_json::json!({"buffer": 0, "byteOffset": offset, "byteLength": 20}));
    push(&mut json, "bufferViews", serde_json::json!({"buffer": 0, "byteOffset": offset + 20, "byteLength": 80}));
    push(
        &mut json,
        "accessors",
        serde_json::json!({"bufferView": views, "componentType": 5126, "count": 5, "type": "SCALAR", "min": [0.0], "max": [2.0]}),
    );
    push(
        &mut json,
        "accessors",
        serde_json::json!({"bufferView": views + 1, "componentType": 5126, "count": 5, "type": "VEC4"}),
    );
    let scene = json["scene"].as_u64().unwrap_or(0) as usize;
    let roots: Vec<u64> = json["scenes"][scene]["nodes"]
        .as_array()
        .map(|a| a.iter().filter_map(|n| n.as_u64()).collect())
        .unwrap_or_default();
    let channels: Vec<serde_json::Value> =
        roots.iter().map(|&n| serde_json::json!({"sampler": 0, "target": {"node": n, "path": "rotation"}})).collect();
    for &n in &roots {
        // An animated node is moved by its translation, rotation and scale: a matrix goes.
        if let Some(node) = json["nodes"][n as usize].as_object_mut() {
            node.remove("matrix");
        }
    }
    json["animations"] = serde_json::json!([{"channels": channels, "samplers": [{"input": accessors, "output": accessors + 1, "interpolation": "LINEAR"}]}]);
    json["buffers"] = serde_json::json!([{"byteLength": bin.len()}]);
    Ok(tessera_scene::write_glb(&json, &bin))
}

/// Frames per minute of `tessera render --frames` on 2 threads, and through `--workers 1` and
/// `--workers 2` (the same 2 threads), runs alternating.
fn throughput(scene: &str, args: &AnimationBenchArgs) -> Result<()> {
    let exe = std::env::current_exe()?;
    let dir = std::env::temp_dir().join(format!("tessera-bench-animation-{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    let frames = format!("1-{}", args.frames.max(1));
    let side = args.size.to_string();
    let spp = args.spp.to_string();
    let run = |extra: &[&str]| -> Result<f64> {
        let mut cmd = Command::new(&exe);
        cmd.args(["render", scene, "--width", &side, "--height", &side, "--spp", &spp, "--quality", "fixed", "-q"])
            .args(["--frames", &frames, "--threads", "2"])
            .args(extra)
            .arg("--out")
            .arg(dir.join("frame.####.exr"));
        let mut ok = true;
        let secs = time(|| ok = cmd.output().map(|o| o.status.success()).unwrap_or(false));
        anyhow::ensure!(ok, "render {extra:?} failed");
        Ok(secs)
    };
    let (mut direct, mut one, mut two) = (Vec::new(), Vec::new(), Vec::new());
    for _ in 0..args.repeat.max(1) {
        direct.push(run(&[])?);
        one.push(run(&["--workers", "1"])?);
        two.push(run(&["--workers", "2"])?);
    }
    let _ = std::fs::remove_dir_all(&dir);
    let per_minute = |secs: f64| 60.0 * args.frames.max(1) as f64 / secs;
    let (d, o, t) = (median(direct), median(one), median(two));
    println!(
        "sequence of {} frames of {scene}, {1}x{1}, {2} spp (wall time, median of {3}):",
        args.frames, args.size, args.spp, args.repeat
    );
    println!("  tessera render, 2 threads:        {d:.2} s, {:.1} frames/minute", per_minute(d));
    println!(
        "  render --workers 1 (2 threads):   {o:.2} s, {:.1} frames/minute ({:.3} of direct)",
        per_minute(o),
        d / o
    );
    println!(
        "  render --workers 2 (1 thread each): {t:.2} s, {:.1} frames/minute ({:.3} of direct)",
        per_minute(t),
        d / t
    );
    Ok(())
}
