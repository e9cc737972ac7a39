//! End-to-end tests of the `tessera` binary: real processes, real files.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn tessera() -> Command {
    Command::new(env!("CARGO_BIN_EXE_tessera"))
}

fn run(args: &[&str]) -> Output {
    tessera().args(args).output().expect("the tessera binary runs")
}

use crate::common;

fn scratch(name: &str) -> common::Scratch {
    common::scratch("render", name)
}

fn fixture(rel: &str) -> String {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../scene/tests/fixtures/scenes").join(rel).display().to_string()
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

fn render_to(dir: &Path, name: &str, extra: &[&str]) -> PathBuf {
    let out = dir.join(format!("{name}.exr"));
    let mut args = vec!["render", "--width", "48", "--height", "40", "--spp", "8", "--out", out.to_str().unwrap()];
    args.extend(extra);
    let o = run(&args);
    assert!(o.status.success(), "render {extra:?} failed: {}", stderr(&o));
    out
}

#[test]
fn default_render_writes_exr_and_png_with_metadata() {
    let dir = scratch("default");
    let exr = render_to(&dir, "render", &[]);
    assert!(exr.with_extension("png").is_file());
    let img = tessera_film::read_exr(&exr).unwrap();
    assert_eq!((img.width, img.height), (48, 40));
    assert!(img.spp.iter().all(|&n| n == 8.0));
    assert!(img.variance.iter().flatten().all(|v| v.is_finite() && *v >= 0.0));
    assert!(img.metadata.contains("scene=builtin:cornell-box"), "{}", img.metadata);
    assert!(img.metadata.contains("scene_hash=") && img.metadata.contains("seed=0"), "{}", img.metadata);
    let mean: f32 = img.rgb.iter().flatten().sum::<f32>() / (img.rgb.len() * 3) as f32;
    assert!(mean > 0.05, "the Cornell box is lit: mean {mean}");
}

/// Samples per pixel of each 32 x 32 tile of a 128 x 32 image, in order.
fn tile_spp(img: &tessera_film::ExrImage) -> Vec<Vec<f32>> {
    (0..4).map(|t| (0..32 * 32).map(|i| img.spp[(i / 32) * 128 + t * 32 + i % 32]).collect()).collect()
}

#[test]
fn quality_auto_adapts_per_tile_and_fixed_gives_every_pixel_spp() {
    // Four tiles side by side: the outer two see only the uniform environment (no variance).
    let dir = scratch("quality");
    let scene = "builtin:furnace?base=0.8&metallic=0.5&roughness=0.4";
    let render = |name: &str, extra: &[&str]| {
        let out = dir.join(format!("{name}.exr"));
        let mut args = vec!["render", scene, "--width", "128", "--height", "32", "--spp", "256"];
        args.extend(["--out", out.to_str().unwrap()]);
        args.extend(extra);
        let o = run(&args);
        assert!(o.status.success(), "{extra:?}: {}", stderr(&o));
        (tessera_film::read_exr(&out).unwrap(), stderr(&o))
    };
    let (auto, text) = render("auto", &[]);
    assert!(text.contains("32..256 spp, adaptive to relative error 0.01 per tile (auto)"), "{text}");
    assert!(text.contains("spp on average"), "{text}");
    let tiles = tile_spp(&auto);
    assert!(tiles[0].iter().chain(&tiles[3]).all(|&n| n == 32.0), "background tiles stop after the first round");
    assert!(tiles[1].iter().chain(&tiles[2]).all(|&n| n > 32.0 && n <= 256.0), "sphere tiles get more");

    let (fixed, text) = render("fixed", &["--quality", "fixed"]);
    assert!(fixed.spp.iter().all(|&n| n == 256.0));
    assert!(text.contains("paths end after 7 bounces (--quality fixed)") && text.contains("colour: rgb"), "{text}");
    let (off, text) = render("off", &["--target-error", "0"]);
    assert!(off.spp.iter().all(|&n| n == 256.0), "--target-error 0 turns adaptive sampling off");
    assert!(text.contains(", 256 spp,") && !text.contains("--quality fixed"), "auto's other choices stay: {text}");

    // Every choice can still be forced: fixed quality with auto colour on gold renders spectrally.
    let out = dir.join("gold.exr");
    let gold = ["render", "builtin:furnace?metal=Au", "--width", "8", "--height", "8", "--spp", "1"];
    let o = run(&[&gold[..], &["--quality", "fixed", "--color", "auto", "--out", out.to_str().unwrap()]].concat());
    assert!(o.status.success() && stderr(&o).contains("colour: spectral (auto"), "{}", stderr(&o));
}

#[test]
fn thread_count_does_not_change_a_bit() {
    let dir = scratch("threads");
    let one = render_to(&dir, "one", &["--threads", "1", "--seed", "3"]);
    let two = render_to(&dir, "two", &["--threads", "2", "--seed", "3"]);
    assert_eq!(std::fs::read(one).unwrap(), std::fs::read(two).unwrap(), "EXR files differ");
}

#[test]
fn compare_reports_zero_for_identical_and_excludes_emitters() {
    let dir = scratch("compare");
    let a = render_to(&dir, "a", &["--seed", "1"]);
    let b = render_to(&dir, "b", &["--seed", "2"]);
    let same = run(&["compare", a.to_str().unwrap(), a.to_str().unwrap()]);
    assert!(same.status.success());
    assert!(String::from_utf8_lossy(&same.stdout).contains("rmse 0.000000"));
    let diff = run(&["compare", a.to_str().unwrap(), b.to_str().unwrap(), "--exclude-emitters"]);
    let text = String::from_utf8_lossy(&diff.stdout).into_owned();
    assert!(!text.contains("rmse 0.000000"), "{text}");
    // The Cornell light is in view: some pixels are excluded.
    assert!(!text.contains(" 0 excluded"), "{text}");
}

/// A reader that stops early (`tessera compare ... | head -1`) must not make tessera panic: the
/// pipe is closed before tessera writes (it reads two EXRs first), so every write meets it. The
/// command ends as other Unix tools do, by SIGPIPE, or successfully where it notices first;
/// `bench`, which prints with `println!`, used to panic.
#[test]
fn listings_end_quietly_when_the_reader_has_gone() {
    #[cfg(unix)]
    use std::os::unix::process::ExitStatusExt;
    let dir = scratch("closed-pipe");
    let a = render_to(&dir, "a", &[]);
    let a = a.to_str().unwrap();
    let bench = vec!["bench", "rays", "builtin:cornell-box", "--rays", "256", "--repeat", "1"];
    for args in [vec!["compare", a, a], vec!["scene-info", "builtin:cornell-box"], bench] {
        let mut child = tessera()
            .args(&args)
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        drop(child.stdout.take());
        let o = child.wait_with_output().unwrap();
        #[cfg(unix)]
        let quiet = o.status.success() || o.status.signal() == Some(13);
        #[cfg(not(unix))]
        let quiet = o.status.success();
        assert!(quiet, "{args:?}: {:?}, {}", o.status, stderr(&o));
        assert!(!stderr(&o).contains("panicked"), "{args:?}: {}", stderr(&o));
    }
}

/// `bench rays` traces from a scene's own camera when it has one: inside the Cornell box, bounce
/// rays mostly hit (from outside the closed box they all missed). A scene without a camera is
/// seen from a camera its bounds fill.
#[test]
fn bench_rays_start_from_the_scenes_camera() {
    let hit_share = |o: &Output, name: &str| -> f64 {
        let out = String::from_utf8_lossy(&o.stdout).to_string();
        let line = out.lines().find(|l| l.starts_with(name)).unwrap_or_else(|| panic!("no {name} line in {out}"));
        let counts = line.split('(').nth(1).unwrap_or_default();
        counts.split(", ").nth(1).and_then(|p| p.split('%').next()).and_then(|p| p.parse().ok()).unwrap()
    };
    let o = run(&["bench", "rays", "builtin:cornell-box", "--rays", "4096", "--repeat", "1"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(String::from_utf8_lossy(&o.stdout).contains("camera 'cornell'"));
    assert!(hit_share(&o, "incoherent") > 50.0, "{}", String::from_utf8_lossy(&o.stdout));
    let o =
        run(&["bench", "rays", &fixture("BoxTextured/glTF-Binary/BoxTextured.glb"), "--rays", "4096", "--repeat", "1"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(String::from_utf8_lossy(&o.stdout).contains("camera 'bench'"));
    assert!(hit_share(&o, "primary, one by one") > 90.0, "{}", String::from_utf8_lossy(&o.stdout));
}

/// `bench stages` times every stage it names, each a positive number of nanoseconds per call,
/// and refuses a ray count that would do nothing or claim gigabytes.
#[test]
fn bench_stages_times_each_stage_and_bounds_its_work() {
    let o = run(&["bench", "stages", "--rays", "2000", "--repeat", "1"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let out = String::from_utf8_lossy(&o.stdout).to_string();
    assert!(out.contains("rays meet its 36 triangles every triangle"), "{out}");
    let stages = ["closest hit", "shadow ray", "surface point", "sampler", "cosine-weighted direction"];
    // The box is small enough to test whole; the walk is timed beside it.
    let walk = ["closest hit, walking the tree", "shadow ray, walking the tree"];
    for stage in stages.into_iter().chain(walk) {
        let line =
            out.lines().find(|l| l.trim_start().starts_with(stage)).unwrap_or_else(|| panic!("no {stage}: {out}"));
        let ns: f64 = line.split_whitespace().last().and_then(|n| n.parse().ok()).unwrap();
        assert!(ns > 0.0 && ns.is_finite(), "{line}");
    }
    for rays in ["0", "10000001"] {
        let o = run(&["bench", "stages", "--rays", rays]);
        assert!(!o.status.success());
        assert!(stderr(&o).contains("out of range"), "{}", stderr(&o));
    }
}

#[test]
fn gltf_with_external_buffers_and_named_camera() {
    let dir = scratch("cameras");
    let scene = fixture("Cameras/glTF/Cameras.gltf");
    render_to(&dir, "ortho", &[&scene, "--camera", "0"]);
    render_to(&dir, "persp", &[&scene, "--camera", "1"]);
    let o = run(&["render", &scene, "--camera", "nope", "--out", dir.join("x.exr").to_str().unwrap()]);
    assert!(!o.status.success());
    assert!(stderr(&o).contains("no camera named 'nope'") && stderr(&o).contains("camera0"), "{}", stderr(&o));
}

#[test]
fn absurd_parameters_are_refused_with_the_parameter_named() {
    for (args, needle) in [
        (vec!["--spp", "0"], "--spp"),
        (vec!["--width", "0"], "--width"),
        (vec!["--height", "100000"], "--height"),
        (vec!["--width", "16384", "--height", "16384"], "over the limit"),
        (vec!["--eps", "2"], "--eps"),
        (vec!["--env", "1,-1,0"], "--env"),
        (vec!["--max-bounces", "3", "--eps", "0.1"], "--eps"),
        (vec!["--rr", "--eps", "0.1"], "--rr"),
        (vec!["--rr-from", "0"], "--rr-from"),
        (vec!["--max-bounces", "2", "--rr-from", "5"], "--rr-from 5 lies beyond --max-bounces 2"),
        (vec!["--estimator", "magic"], "--estimator"),
        (vec!["--quality", "best"], "--quality"),
        (vec!["--target-error", "-1"], "--target-error"),
        (vec!["--target-error", "NaN"], "--target-error"),
        (vec!["--confidence", "0.4"], "a probability above 0.5"),
        (vec!["--confidence", "1"], "--confidence"),
        (vec!["--spp", "64", "--min-spp", "100"], "--min-spp 100 is above --spp 64"),
        (vec!["--quality", "fixed", "--min-spp", "16"], "--min-spp needs adaptive sampling"),
    ] {
        let mut full = vec!["render"];
        full.extend(args.iter());
        let o = run(&full);
        assert!(!o.status.success(), "{args:?} accepted");
        assert!(stderr(&o).contains(needle), "{args:?}: {}", stderr(&o));
        assert!(!stderr(&o).contains("panicked"), "{args:?}: {}", stderr(&o));
    }
}

#[test]
fn bad_scenes_fail_cleanly_naming_the_file() {
    let dir = scratch("bad");
    let junk = dir.join("junk.glb");
    std::fs::write(&junk, b"glTF\x02\x00\x00\x00garbage").unwrap();
    for scene in [junk.display().to_string(), "/no/such/scene.gltf".to_string()] {
        let o = run(&["render", &scene, "--out", dir.join("x.exr").to_str().unwrap()]);
        assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
        assert!(stderr(&o).contains(&scene), "{}", stderr(&o));
        assert!(!stderr(&o).contains("panicked"));
    }
}

#[test]
fn collision_estimator_warns_about_point_lights() {
    let dir = scratch("points");
    let o = run(&[
        "render",
        &fixture("Lights/Point/LightsPoint.gltf"),
        "--estimator",
        "collision",
        "--width",
        "8",
        "--height",
        "8",
        "--spp",
        "1",
        "--out",
        dir.join("p.exr").to_str().unwrap(),
    ]);
    assert!(o.status.success());
    assert!(stderr(&o).contains("never hits punctual lights") && stderr(&o).contains("point"), "{}", stderr(&o));
    // Named, and the consequence said: they are the only lights, so the image is black.
    assert!(stderr(&o).contains("point 'PointLightRed'") && stderr(&o).contains("will be black"), "{}", stderr(&o));
}

#[test]
fn scene_info_describes_the_scene() {
    let o = run(&["scene-info", &fixture("CornellBox/glTF/CornellBox.gltf")]);
    assert!(o.status.success(), "{}", stderr(&o));
    let text = String::from_utf8_lossy(&o.stdout).into_owned();
    for needle in [
        "triangles    32",
        "KHR_materials_emissive_strength",
        "cornell_camera",
        "2 emissive triangles",
        "spectra      none (--color auto renders RGB)",
    ] {
        assert!(text.contains(needle), "missing '{needle}' in:\n{text}");
    }
}

#[test]
fn a_scene_without_lights_warns_and_is_not_black() {
    let dir = scratch("nolight");
    let out = dir.join("box.exr");
    let o = run(&[
        "render",
        &fixture("Box/glTF-Binary/Box.glb"),
        "--width",
        "16",
        "--height",
        "16",
        "--spp",
        "2",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success());
    assert!(stderr(&o).contains("no lights"), "{}", stderr(&o));
    let img = tessera_film::read_exr(&out).unwrap();
    assert!(img.rgb.iter().flatten().any(|&v| v > 0.1));
}

#[test]
fn macbeth_chart_and_study() {
    let scratch = scratch("macbeth");
    // A folder that does not exist yet: `macbeth` makes it.
    let dir = scratch.join("out");
    let png = dir.join("chart.png");
    let o = Command::new(env!("CARGO_BIN_EXE_tessera"))
        .args(["macbeth", "--samples", "16", "--sampler", "stratified", "--illuminant", "a", "--out"])
        .arg(&png)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let exr = tessera_film::read_exr(&png.with_extension("exr")).unwrap();
    assert_eq!((exr.width, exr.height), (384, 256), "6 x 4 patches of 64 x 64");
    assert!(png.exists());
    let study = dir.join("study");
    let o =
        Command::new(env!("CARGO_BIN_EXE_tessera")).args(["macbeth", "--study", "--out"]).arg(&study).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let stdout = String::from_utf8_lossy(&o.stdout);
    let uniform_slope: f64 = stdout
        .lines()
        .find_map(|l| l.trim().strip_prefix("uniform").and_then(|r| r.split_whitespace().next()?.parse().ok()))
        .unwrap_or_else(|| panic!("no uniform slope in:\n{stdout}"));
    assert!((uniform_slope + 0.5).abs() < 0.05, "{stdout}");
    let csv = std::fs::read_to_string(study.join("macbeth-study.csv")).unwrap();
    assert_eq!(csv.lines().count(), 1 + 3 * 4, "a row per sampler and N:\n{csv}");
    for f in ["macbeth-noise.png", "macbeth-contact-sheet.png"] {
        assert!(std::fs::metadata(study.join(f)).unwrap().len() > 1000, "{f}");
    }
}

/// Cameras.gltf (a square under the fallback sky) with material `extras` set to `tessera`.
fn square_with_extras(dir: &Path, tessera: serde_json::Value) -> String {
    let src = Path::new(&fixture("Cameras/glTF/Cameras.gltf")).to_path_buf();
    std::fs::copy(src.with_file_name("simpleSquare.bin"), dir.join("simpleSquare.bin")).unwrap();
    let mut doc: serde_json::Value = serde_json::from_slice(&std::fs::read(&src).unwrap()).unwrap();
    doc["materials"] = serde_json::json!([{ "name": "sample", "extras": { "tessera": tessera } }]);
    doc["meshes"][0]["primitives"][0]["material"] = 0.into();
    let path = dir.join("square.gltf");
    std::fs::write(&path, serde_json::to_vec(&doc).unwrap()).unwrap();
    path.display().to_string()
}

#[test]
fn spectral_content_makes_auto_spectral_and_the_render_says_why() {
    let dir = scratch("color");
    let gold = square_with_extras(&dir, serde_json::json!({ "conductor": "Au" }));
    let out = dir.join("gold.exr");
    let o = run(&["render", &gold, "--width", "16", "--height", "16", "--spp", "4", "--out", out.to_str().unwrap()]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stderr(&o).contains("colour: spectral (auto: material 'sample' (conductor Au))"), "{}", stderr(&o));
    assert!(tessera_film::read_exr(&out).unwrap().metadata.contains("color=spectral"));
    let o = run(&[
        "render",
        &gold,
        "--width",
        "16",
        "--height",
        "16",
        "--spp",
        "4",
        "--color",
        "rgb",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(
        stderr(&o).contains("colour: rgb as asked, although 'sample' (conductor Au) carry spectra"),
        "{}",
        stderr(&o)
    );
    // Plain glTF colours stay RGB under auto.
    let o = run(&[
        "render",
        "builtin:furnace",
        "--width",
        "8",
        "--height",
        "8",
        "--spp",
        "1",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(stderr(&o).contains("colour: rgb (auto: no spectral content)"), "{}", stderr(&o));
    // A measured reflectance outside 0..1 is refused, naming the key.
    let bad = square_with_extras(
        &dir,
        serde_json::json!({ "reflectance": { "wavelengths": [400, 700], "values": [0.2, 3] } }),
    );
    let o = run(&["render", &bad, "--out", out.to_str().unwrap()]);
    assert!(!o.status.success());
    assert!(stderr(&o).contains("extras.tessera.reflectance: value 3 is outside 0..=1"), "{}", stderr(&o));
}

#[test]
fn quality_chart_compares_auto_and_fixed_on_each_scene() {
    let dir = scratch("quality-chart");
    let (out, cache) = (dir.join("chart"), dir.join("cache"));
    let scenes = "builtin:furnace?metal=Au,builtin:tiny-light";
    let o = run(&[
        "chart",
        "quality",
        "--scene",
        scenes,
        "--size",
        "8",
        "--budget",
        "0.05",
        "--reference-spp",
        "64",
        "--out",
        out.to_str().unwrap(),
        "--cache",
        cache.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let text = stderr(&o);
    assert!(text.contains("builtin:furnace?metal=Au, fixed: paths end after 7 bounces (--quality fixed); colour: rgb"));
    assert!(text.contains("builtin:furnace?metal=Au, auto: ") && text.contains("colour: spectral (auto"), "{text}");
    let csv = std::fs::read_to_string(out.join("quality.csv")).unwrap();
    let mut lines = csv.lines();
    assert_eq!(lines.next(), Some("scene,setting,spp,mean_spp,seconds,rmse,relmse"));
    let rows: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
    for scene in scenes.split(',') {
        for setting in ["fixed", "auto (uniform spp)", "auto"] {
            let series: Vec<_> = rows.iter().filter(|r| r[0] == scene && r[1] == setting).collect();
            assert!(!series.is_empty(), "no rows for {scene} {setting}");
            assert!(series.iter().all(|r| r[5].parse::<f64>().is_ok_and(|e| e.is_finite() && e >= 0.0)));
        }
    }
    assert!(out.join("quality.png").is_file());
    let table = String::from_utf8_lossy(&o.stdout);
    assert!(table.contains("| fixed / auto |") && table.lines().count() == 2 + 2, "{table}");
}

#[test]
fn convergence_chart_writes_csv_and_plots_for_every_method_and_sampler() {
    let dir = scratch("chart");
    let out = dir.join("chart");
    let cache = dir.join("cache");
    let args =
        ["chart", "convergence", "--size", "8", "--budget", "0.05", "--reference-spp", "64", "--max-bounces", "3"];
    let mut with_dirs: Vec<&str> = args.to_vec();
    with_dirs.extend(["--out", out.to_str().unwrap(), "--cache", cache.to_str().unwrap()]);
    let o = run(&with_dirs);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stderr(&o).contains("rendering 64 spp"), "{}", stderr(&o));
    let csv = std::fs::read_to_string(out.join("convergence.csv")).unwrap();
    let mut lines = csv.lines();
    assert_eq!(lines.next(), Some("scene,method,sampler,spp,seconds,rmse,relmse"));
    let rows: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
    for method in ["collision-uniform", "collision-cosine", "collision-brdf", "nee", "mis"] {
        for sampler in ["independent", "sobol"] {
            let series: Vec<&Vec<&str>> = rows.iter().filter(|r| r[1] == method && r[2] == sampler).collect();
            assert!(!series.is_empty(), "no rows for {method} {sampler}");
            assert_eq!(series[0][3], "1", "{method} {sampler} starts at 1 spp");
            assert!(series.iter().all(|r| r[5].parse::<f64>().is_ok_and(|e| e.is_finite() && e >= 0.0)));
        }
    }
    for png in ["error-vs-time.png", "error-vs-spp.png"] {
        assert!(std::fs::metadata(out.join(png)).unwrap().len() > 1000, "{png}");
    }
    // A second run finds the reference in the cache instead of rendering it again.
    let o = run(&with_dirs);
    assert!(o.status.success() && stderr(&o).contains("cached)"), "{}", stderr(&o));
}

#[test]
fn brdf_chart_shows_the_printed_form_above_one_and_the_normalised_form_not() {
    let dir = scratch("brdf");
    let out = dir.join("brdf");
    let o = run(&["chart", "brdf", "--resolution", "16", "--out", out.to_str().unwrap()]);
    assert!(o.status.success(), "{}", stderr(&o));
    let text = String::from_utf8_lossy(&o.stdout).into_owned();
    assert!(text.contains("normalised gold at 550 nm    max albedo 0."), "{text}");
    assert!(!text.lines().any(|l| l.starts_with("normalised") && !l.contains("above 1 in 0 of")), "{text}");
    assert!(text.lines().any(|l| l.starts_with("printed    gold") && !l.contains("above 1 in 0 of")), "{text}");
    let csv = std::fs::read_to_string(out.join("brdf-albedo.csv")).unwrap();
    assert_eq!(csv.lines().count(), 1 + 2 * 2 * 10 * 19);
    assert!(std::fs::metadata(out.join("brdf-albedo.png")).unwrap().len() > 1000);
}

#[test]
fn stability_chart_renders_every_failure_scene_with_every_method() {
    let dir = scratch("stability");
    let out = dir.join("stability");
    let o = run(&["chart", "stability", "--size", "8", "--spp", "2", "--out", out.to_str().unwrap()]);
    assert!(o.status.success(), "{}", stderr(&o));
    let csv = std::fs::read_to_string(out.join("stability.csv")).unwrap();
    assert_eq!(csv.lines().count(), 1 + 3 * 3, "{csv}");
    for scene in ["builtin:tiny-light", "builtin:glossy-floor?roughness=0.05", "builtin:closed-sphere"] {
        assert_eq!(csv.lines().filter(|l| l.starts_with(&format!("{scene},"))).count(), 3, "{csv}");
    }
    assert!(std::fs::metadata(out.join("stability.png")).unwrap().len() > 100);
}

#[test]
fn a_sequence_writes_one_image_a_frame_each_as_its_single_frame_render() {
    let dir = scratch("sequence");
    let scene = fixture("BoxAnimated/glTF-Binary/BoxAnimated.glb");
    let pattern = dir.join("box.###.exr");
    let base = ["render", &scene, "--width", "40", "--height", "30", "--spp", "4", "--quiet"];
    let o = run(&[&base[..], &["--frames", "10-40x15", "--out", pattern.to_str().unwrap()]].concat());
    assert!(o.status.success(), "{}", stderr(&o));
    let frames: Vec<PathBuf> = [10, 25, 40].iter().map(|f| dir.join(format!("box.{f:03}.exr"))).collect();
    for f in &frames {
        assert!(f.is_file() && f.with_extension("png").is_file(), "{} is missing", f.display());
    }
    let image = |p: &Path| tessera_film::read_exr(p).unwrap();
    let middle = image(&frames[1]);
    for line in ["frame=25", "fps=24", "time=1.0416666", "animation=first", "seed=0"] {
        assert!(middle.metadata.contains(line), "no {line} in {}", middle.metadata);
    }
    // A frame of the sequence is the frame rendered alone, byte for byte.
    let alone = dir.join("alone.exr");
    let o = run(&[&base[..], &["--frame", "25", "--out", alone.to_str().unwrap()]].concat());
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(std::fs::read(&alone).unwrap(), std::fs::read(&frames[1]).unwrap());
    // Through a farm on this machine (a coordinator and two workers; the client downloads each
    // frame as it finishes): the same files.
    let farm = dir.join("farm.###.exr");
    let o = run(&[&base[..], &["--frames", "10-40x15", "--workers", "2", "--out", farm.to_str().unwrap()]].concat());
    assert!(o.status.success(), "{}", stderr(&o));
    for f in [10, 25, 40] {
        let (a, b) = (dir.join(format!("farm.{f:03}.exr")), dir.join(format!("box.{f:03}.exr")));
        assert!(std::fs::read(a).unwrap() == std::fs::read(b).unwrap(), "frame {f}: the farm's file differs");
    }
    // The box moves: every frame differs from the others.
    let (a, b, c) = (image(&frames[0]).rgb, middle.rgb, image(&frames[2]).rgb);
    assert!(a != b && b != c && a != c);

    // Bad requests are refused before anything renders, naming the flag.
    for (flags, says) in [
        (vec!["--frames", "9-1"], "runs backwards"),
        (vec!["--frames", "1-200000"], "more than 100000"),
        (vec!["--fps", "-2", "--frame", "1"], "--fps"),
        (vec!["--frame", "1", "--animation", "Dance"], "no animation named 'Dance'"),
        (vec!["--frames", "1-2", "--out", "plain.exr"], "needs #s"),
    ] {
        let o = run(&[&base[..], &flags[..]].concat());
        assert!(!o.status.success() && stderr(&o).contains(says), "{flags:?}: {}", stderr(&o));
    }
}

#[test]
fn an_environment_map_lights_the_scene_and_is_named_in_the_header() {
    let dir = scratch("envmap");
    // A 32 x 16 sky, brighter towards the zenith, as a Radiance HDR file.
    let (w, h) = (32usize, 16usize);
    let pixels: Vec<image::Rgb<f32>> = (0..w * h).map(|k| image::Rgb([2.0 - (k / w) as f32 / 8.0, 1.0, 0.5])).collect();
    let map = dir.join("sky.hdr");
    let file = std::io::BufWriter::new(std::fs::File::create(&map).unwrap());
    image::codecs::hdr::HdrEncoder::new(file).encode(&pixels, w, h).unwrap();
    let out = dir.join("lit.exr");
    let base = ["render", "builtin:furnace?base=0.8&roughness=0.5", "--width", "32", "--height", "32", "--spp", "16"];
    let o = run(&[
        &base[..],
        &["-q", "--env", map.to_str().unwrap(), "--env-strength", "2", "--out", out.to_str().unwrap()],
    ]
    .concat());
    assert!(o.status.success(), "{}", stderr(&o));
    let img = tessera_film::read_exr(&out).unwrap();
    assert!(
        img.metadata.contains("environment_map_hash=") && img.metadata.contains("environment_strength=2"),
        "{}",
        img.metadata
    );
    // The background is the map: red about 2 x (2 - row/8), green 2, blue 1.
    let corner = img.rgb[0];
    assert!((corner[1] - 2.0).abs() < 0.05 && (corner[2] - 1.0).abs() < 0.05, "{corner:?}");
    // Through a farm (the map travels with the scene): the same file.
    let farm = dir.join("farm.exr");
    let flags = [
        "-q",
        "--env",
        map.to_str().unwrap(),
        "--env-strength",
        "2",
        "--workers",
        "2",
        "--out",
        farm.to_str().unwrap(),
    ];
    let o = run(&[&base[..], &flags[..]].concat());
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(std::fs::read(&farm).unwrap() == std::fs::read(&out).unwrap(), "the farm's file differs");
    let o = run(&[&base[..], &["--env", "sky.png"]].concat());
    assert!(!o.status.success() && stderr(&o).contains(".hdr or .exr"), "{}", stderr(&o));
}

#[test]
fn a_black_image_of_a_lit_scene_says_why() {
    let dir = scratch("black");
    // The square of Cameras.gltf, lit only by a spot light behind the camera that points away.
    let src = Path::new(&fixture("Cameras/glTF/Cameras.gltf")).to_path_buf();
    std::fs::copy(src.with_file_name("simpleSquare.bin"), dir.join("simpleSquare.bin")).unwrap();
    let mut doc: serde_json::Value = serde_json::from_slice(&std::fs::read(&src).unwrap()).unwrap();
    doc["extensionsUsed"] = serde_json::json!(["KHR_lights_punctual"]);
    doc["extensions"] = serde_json::json!({"KHR_lights_punctual": {"lights": [
        {"type": "spot", "intensity": 50.0, "spot": {"outerConeAngle": 0.3}}
    ]}});
    doc["nodes"].as_array_mut().unwrap().push(serde_json::json!({
        "translation": [0.5, 0.5, 5.0], "rotation": [0.0, 1.0, 0.0, 0.0],
        "extensions": {"KHR_lights_punctual": {"light": 0}}
    }));
    doc["scenes"][0]["nodes"].as_array_mut().unwrap().push(3.into());
    let (scene, out) = (dir.join("away.gltf"), dir.join("away.exr"));
    // Rendered here, and through a farm (where `submit` says it when the image arrives).
    let render = |doc: &serde_json::Value, farm: &[&str]| {
        std::fs::write(&scene, serde_json::to_vec(doc).unwrap()).unwrap();
        let args = ["render", scene.to_str().unwrap(), "--width", "16", "--height", "16", "--spp", "4", "-q"];
        let o = run(&[&args[..], farm, &["--out", out.to_str().unwrap()]].concat());
        assert!(o.status.success(), "{}", stderr(&o));
        stderr(&o)
    };
    for farm in [&[][..], &["--workers", "1"][..]] {
        let err = render(&doc, farm);
        assert!(
            err.contains("the image is black")
                && err.contains("it lies behind the camera")
                && err.contains("--env FILE"),
            "{farm:?}: {err}"
        );
        assert!(tessera_film::read_exr(&out).unwrap().rgb.iter().flatten().all(|&v| v == 0.0));
    }
    // Turned towards the square, the same light lights it, and nothing is said.
    doc["nodes"][3]["rotation"] = serde_json::json!([0.0, 0.0, 0.0, 1.0]);
    for farm in [&[][..], &["--workers", "1"][..]] {
        let err = render(&doc, farm);
        assert!(!err.contains("the image is black"), "{farm:?}: {err}");
        assert!(tessera_film::read_exr(&out).unwrap().rgb.iter().flatten().any(|&v| v > 0.0));
    }
}

#[test]
fn transparent_renders_carry_alpha_here_and_through_a_farm() {
    let dir = scratch("transparent");
    let out = dir.join("t.exr");
    let base = ["render", "builtin:furnace?base=0.8", "--width", "32", "--height", "32", "--spp", "8", "-q"];
    let o = run(&[&base[..], &["--transparent", "--out", out.to_str().unwrap()]].concat());
    assert!(o.status.success(), "{}", stderr(&o));
    let img = tessera_film::read_exr(&out).unwrap();
    let alpha = img.alpha.as_ref().expect("an A channel");
    assert_eq!((alpha[0], img.rgb[0]), (0.0, [0.0; 3]), "the corner is background: left out");
    assert_eq!(alpha[16 * 32 + 16], 1.0, "the centre is the sphere");
    assert!(img.metadata.contains("transparent"), "{}", img.metadata);
    let png = image::open(out.with_extension("png")).unwrap();
    assert_eq!(png.color(), image::ColorType::Rgba8);
    assert_eq!(png.to_rgba8().get_pixel(0, 0)[3], 0, "the PNG's corner is see-through");
    // Through a farm: the same file.
    let farm = dir.join("farm.exr");
    let o = run(&[&base[..], &["--transparent", "--workers", "2", "--out", farm.to_str().unwrap()]].concat());
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(std::fs::read(&farm).unwrap() == std::fs::read(&out).unwrap(), "the farm's file differs");
    // Without the flag: no A channel, and the background is there.
    let opaque = dir.join("o.exr");
    let o = run(&[&base[..], &["--out", opaque.to_str().unwrap()]].concat());
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(tessera_film::read_exr(&opaque).unwrap().alpha.is_none());
}

/// Names from a scene file reach the terminal escaped: an escape sequence and a bidi override in
/// a variant's name print as `\u{1b}` and `\u{202e}`, and `render --variant` refuses such a
/// name as `submit` does.
#[test]
fn scene_info_escapes_control_and_format_characters_from_the_file() {
    let dir = scratch("escapes");
    let path = square_with_extras(&dir, serde_json::json!({}));
    let mut doc: serde_json::Value = serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap();
    let name = "\u{1b}[2Jred\u{202e}gnp.exe";
    doc["extensions"] = serde_json::json!({ "KHR_materials_variants": { "variants": [{ "name": name }] } });
    doc["extensionsUsed"] = serde_json::json!(["KHR_materials_variants"]);
    std::fs::write(&path, serde_json::to_vec(&doc).unwrap()).unwrap();
    let o = run(&["scene-info", &path]);
    assert!(o.status.success(), "{}", stderr(&o));
    let text = String::from_utf8_lossy(&o.stdout).into_owned();
    assert!(!text.contains('\u{1b}') && !text.contains('\u{202e}'), "printed raw: {text:?}");
    assert!(text.contains("\\u{1b}[2Jred\\u{202e}gnp.exe"), "{text}");
    let o = run(&["render", &path, "--width", "8", "--height", "8", "--spp", "1", "-q", "--variant", name]);
    assert!(!o.status.success() && stderr(&o).contains("format characters"), "{}", stderr(&o));
    assert!(!stderr(&o).contains('\u{202e}'), "the refusal echoes the name raw");
}

#[test]
fn a_material_variant_renders_here_and_through_a_farm_and_is_named() {
    let dir = scratch("variant");
    // The square, red, with a blue material for variant "blue".
    let path = square_with_extras(&dir, serde_json::json!({}));
    let mut doc: serde_json::Value = serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap();
    let color = |rgb: [f32; 3]| serde_json::json!({ "pbrMetallicRoughness": { "baseColorFactor": [rgb[0], rgb[1], rgb[2], 1.0] } });
    doc["materials"] = serde_json::json!([color([0.8, 0.1, 0.1]), color([0.1, 0.1, 0.8])]);
    doc["meshes"][0]["primitives"][0]["extensions"] =
        serde_json::json!({ "KHR_materials_variants": { "mappings": [{ "material": 1, "variants": [0] }] } });
    doc["extensions"] = serde_json::json!({ "KHR_materials_variants": { "variants": [{ "name": "blue" }] } });
    doc["extensionsUsed"] = serde_json::json!(["KHR_materials_variants"]);
    std::fs::write(&path, serde_json::to_vec(&doc).unwrap()).unwrap();
    let o = run(&["scene-info", &path]);
    assert!(String::from_utf8_lossy(&o.stdout).contains("variants     blue"), "{}", String::from_utf8_lossy(&o.stdout));
    let base = ["render", &path, "--width", "16", "--height", "16", "--spp", "4", "-q"];
    let image = |extra: &[&str], name: &str| {
        let out = dir.join(name);
        let o = run(&[&base[..], extra, &["--out", out.to_str().unwrap()]].concat());
        assert!(o.status.success(), "{}", stderr(&o));
        (std::fs::read(&out).unwrap(), tessera_film::read_exr(&out).unwrap())
    };
    let (_, red) = image(&[], "red.exr");
    let (local, blue) = image(&["--variant", "blue"], "blue.exr");
    let centre = 8 * 16 + 8;
    assert!(
        red.rgb[centre][0] > red.rgb[centre][2] && blue.rgb[centre][2] > blue.rgb[centre][0],
        "{:?} {:?}",
        red.rgb[centre],
        blue.rgb[centre]
    );
    assert!(blue.metadata.contains("variant=blue"), "{}", blue.metadata);
    let (farm, _) = image(&["--variant", "blue", "--workers", "1"], "farm.exr");
    assert!(farm == local, "the farm's file differs");
    let o = run(&[&base[..], &["--variant", "green"]].concat());
    assert!(!o.status.success() && stderr(&o).contains("no material variant 'green'"), "{}", stderr(&o));
}

#[test]
fn the_light_tree_renders_here_and_through_a_farm_to_the_same_file() {
    let dir = scratch("lights");
    let base = ["render", "builtin:many-lights?count=64", "--width", "16", "--height", "12", "--spp", "4"];
    let image = |extra: &[&str], name: &str| {
        let out = dir.join(name);
        let o = run(&[&base[..], extra, &["--out", out.to_str().unwrap()]].concat());
        assert!(o.status.success(), "{}", stderr(&o));
        (std::fs::read(&out).unwrap(), tessera_film::read_exr(&out).unwrap(), stderr(&o))
    };
    // 128 emissive triangles: `auto` chooses the tree and says so.
    let (local, exr, said) = image(&[], "auto.exr");
    assert!(said.contains("lights: tree (128 with a position)"), "{said}");
    assert!(exr.metadata.contains("lights=tree"), "{}", exr.metadata);
    let (tree, ..) = image(&["--lights", "tree", "-q"], "tree.exr");
    assert!(tree == local, "--lights tree differs from auto's choice of it");
    let (power, exr, _) = image(&["--lights", "power", "-q"], "power.exr");
    assert!(power != local && !exr.metadata.contains("lights="), "{}", exr.metadata);
    let (farm, ..) = image(&["--workers", "1", "-q"], "farm.exr");
    assert!(farm == local, "the farm's file differs");
}

/// A white floor under a 2 cm glowing speck 5 m up (its only light), seen from 3 m above:
/// `dir/glow.gltf`, its buffer in `glow.bin`.
fn glow_scene(dir: &Path) -> PathBuf {
    let quad = |s: f32, y: f32, down: bool| {
        let q = [[-s, y, -s], [s, y, -s], [s, y, s], [-s, y, s]];
        let q = if down { q } else { [q[0], q[3], q[2], q[1]] };
        [0, 1, 2, 0, 2, 3].map(|i| q[i])
    };
    let bin: Vec<u8> = [quad(3.0, 0.0, false), quad(0.01, 5.0, true)]
        .iter()
        .flatten()
        .flatten()
        .flat_map(|f| f.to_le_bytes())
        .collect();
    std::fs::write(dir.join("glow.bin"), &bin).unwrap();
    let gltf = serde_json::json!({
        "asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0, 1]}],
        "nodes": [{"mesh": 0}, {"camera": 0, "translation": [0, 3, 0], "rotation": [-0.70710677, 0, 0, 0.70710677]}],
        "cameras": [{"name": "above", "type": "perspective", "perspective": {"yfov": 1.0, "znear": 0.01}}],
        "materials": [
            {"pbrMetallicRoughness": {"baseColorFactor": [0.8, 0.8, 0.8, 1], "metallicFactor": 0, "roughnessFactor": 1}},
            {"pbrMetallicRoughness": {"baseColorFactor": [0, 0, 0, 1], "metallicFactor": 0}, "emissiveFactor": [1, 1, 1]}
        ],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "material": 0}, {"attributes": {"POSITION": 1}, "material": 1}]}],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": 6, "type": "VEC3", "min": [-3, 0, -3], "max": [3, 0, 3]},
            {"bufferView": 1, "componentType": 5126, "count": 6, "type": "VEC3", "min": [-0.01, 5, -0.01], "max": [0.01, 5, 0.01]}
        ],
        "bufferViews": [{"buffer": 0, "byteLength": 72}, {"buffer": 0, "byteOffset": 72, "byteLength": 72}],
        "buffers": [{"byteLength": 144, "uri": "glow.bin"}]
    });
    let path = dir.join("glow.gltf");
    std::fs::write(&path, serde_json::to_vec(&gltf).unwrap()).unwrap();
    path
}

/// A scene lit only by its own glow, which leaves what the camera sees black, is lit by the
/// default environment under `--quality auto`, and the user is told so and how to undo it;
/// `render` and a farm decide alike (the request carries the environment chosen).
#[test]
fn a_scene_lit_only_by_its_own_glow_is_given_the_environment() {
    let dir = scratch("glow");
    let scene = glow_scene(&dir);
    let render = |flags: &[&str], name: &str| {
        let out = dir.join(name);
        let args = ["render", scene.to_str().unwrap(), "--width", "24", "--height", "16", "--spp", "4", "-q"];
        let o = run(&[&args[..], flags, &["--out", out.to_str().unwrap()]].concat());
        assert!(o.status.success(), "{}", stderr(&o));
        (stderr(&o), out)
    };
    let (here, local) = render(&[], "here.exr");
    let (there, farm) = render(&["--workers", "1"], "farm.exr");
    for err in [&here, &there] {
        assert!(err.contains("uniform environment of 1") && err.contains("--env 0"), "{err}");
    }
    common::assert_same_pixels(&local, &farm);
    let image = tessera_film::read_exr(&local).unwrap();
    assert!(image.metadata.contains("environment=[1, 1, 1]"), "{}", image.metadata);
    // `--env 0` keeps the speck's light alone: nearly black, and the hint names --env.
    let (err, dark) = render(&["--env", "0"], "dark.exr");
    assert!(
        !err.contains("uniform environment") && err.contains("nearly black") && err.contains("--env FILE"),
        "{err}"
    );
    assert!(tessera_film::read_exr(&dark).unwrap().metadata.contains("environment=[0, 0, 0]"));
}

/// Ctrl-C during `render` writes what was rendered, marked partial in the header and said on
/// the terminal, and exits with an error; a second Ctrl-C would quit at once. The same through
/// a local farm (`--workers`), from what its coordinator merged.
#[test]
fn ctrl_c_writes_a_partial_image_and_says_so() {
    let dir = scratch("interrupted");
    for (farm, wait_ms, said) in
        [(&[][..], 1500, "partial: interrupted at"), (&["--workers", "1"], 4000, "marked partial")]
    {
        let out = dir.join("partial.exr");
        let _ = std::fs::remove_file(&out);
        let mut child = tessera()
            .args([
                "render",
                "--width",
                "256",
                "--height",
                "256",
                "--spp",
                "65536",
                "--quality",
                "fixed",
                "--threads",
                "1",
            ])
            .args(farm)
            .arg("--out")
            .arg(&out)
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        std::thread::sleep(std::time::Duration::from_millis(wait_ms));
        assert!(Command::new("kill").args(["-INT", &child.id().to_string()]).status().unwrap().success());
        let status = child.wait().unwrap();
        let mut err = String::new();
        std::io::Read::read_to_string(child.stderr.as_mut().unwrap(), &mut err).unwrap();
        assert!(!status.success(), "{farm:?}: an interrupted render is not a success: {err}");
        assert!(err.contains(said), "{farm:?}: {err}");
        let image = tessera_film::read_exr(&out).unwrap();
        assert!(image.metadata.contains("partial=interrupted after"), "{farm:?}: {}", image.metadata);
        assert!(image.spp.iter().any(|&s| s > 0.0) && image.spp.iter().all(|&s| s < 65536.0), "{farm:?}");
        assert!(out.with_extension("png").is_file(), "{farm:?}");
    }
}

/// Scenes in other tools' formats are told how to become glTF; a `.gltf` whose `.bin` was not
/// copied names the file.
#[test]
fn other_formats_and_missing_buffers_say_what_to_do() {
    let dir = scratch("formats");
    let blend = dir.join("shot.blend");
    std::fs::write(&blend, b"BLENDER").unwrap();
    let o = run(&["render", blend.to_str().unwrap(), "--out", dir.join("x.exr").to_str().unwrap()]);
    assert!(!o.status.success() && stderr(&o).contains("File > Export > glTF 2.0"), "{}", stderr(&o));
    let gltf = std::fs::read(fixture("AnimatedTriangle/glTF/AnimatedTriangle.gltf")).unwrap();
    let alone = dir.join("alone.gltf");
    std::fs::write(&alone, gltf).unwrap();
    let o = run(&["render", alone.to_str().unwrap(), "--out", dir.join("y.exr").to_str().unwrap()]);
    assert!(stderr(&o).contains("'simpleTriangle.bin', which it references, is missing"), "{}", stderr(&o));
}
