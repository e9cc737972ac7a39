//! End-to-end tests of the farm: a real coordinator, real workers and the CLI client as separate
//! processes on loopback. Every image must be bit-identical to `tessera render` with the same
//! scene, settings and seed, whatever happens to the processes (workers killed, stopped, a
//! coordinator killed and restarted, chaos).

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use crate::common;
use common::farm::{
    Farm, LONG, SMALL, bin, http_get, local_render, scratch, start_liar, two_workers_mid_render,
    two_workers_mid_render_with,
};
use common::{Proc, assert_same_pixels};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

#[test]
fn one_and_three_workers_match_the_local_render() {
    let mut farm = Farm::new("workers", 30, &[]);
    let local = farm.dir.join("local.exr");
    local_render("builtin:cornell-box", SMALL, &local);
    farm.add_worker(2);
    let one = farm.dir.join("one.exr");
    let o = farm.submit("builtin:cornell-box", SMALL, &one);
    assert!(o.status.success(), "{}\n{}", String::from_utf8_lossy(&o.stderr), farm.logs());
    assert!(one.with_extension("png").is_file());
    assert_same_pixels(&one, &local);
    farm.add_worker(1);
    farm.add_worker(1);
    let three = farm.dir.join("three.exr");
    let o = farm.submit("builtin:cornell-box", SMALL, &three);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_same_pixels(&three, &local);
    // Not only the pixels: the farm's file and the local one are the same bytes, header included.
    for farm_image in [&one, &three] {
        let (a, b) = (std::fs::read(farm_image).unwrap(), std::fs::read(&local).unwrap());
        assert!(a == b, "{} and {} differ beyond their pixels", farm_image.display(), local.display());
    }
    let workers = farm.client(&["workers"]).output().unwrap();
    let text = String::from_utf8_lossy(&workers.stdout);
    assert!(text.contains("w0") && text.contains("w2"), "{text}");
    // w0 rendered the whole first image: its row names where it calls from and counts its results.
    let w0: Vec<&str> = text.lines().find(|l| l.starts_with("w0 ")).expect("a row for w0").split_whitespace().collect();
    let (state, host) = (w0[1], w0[2]);
    let (results, failures) = (w0[7].parse::<u64>().unwrap(), w0[8].parse::<u64>().unwrap());
    assert!(state == "idle" && host == "127.0.0.1" && results > 0 && failures == 0, "{text}");
}

/// `render --workers` gives the bits of a direct render. It also clears the data directories that
/// killed runs left in the temporary folder (their process is gone), and only those.
#[test]
fn render_with_local_workers_matches() {
    let dir = scratch("local-workers");
    let (a, b) = (dir.join("direct.exr"), dir.join("farm.exr"));
    local_render("builtin:cornell-box", SMALL, &a);
    let tmp = dir.join("tmp");
    // No process has an id above Linux's largest pid_max (2^22); this test's process lives.
    let stale = tmp.join("tessera-local-farm-4194305");
    let live = tmp.join(format!("tessera-local-farm-{}", std::process::id()));
    let other = tmp.join("tessera-local-farm-notes");
    for d in [&stale, &live, &other] {
        std::fs::create_dir_all(d).unwrap();
    }
    let mut args = vec!["render", "builtin:cornell-box", "--out", b.to_str().unwrap(), "-q", "--workers", "2"];
    args.extend(SMALL);
    let o = Command::new(bin()).args(&args).env("TMPDIR", &tmp).output().unwrap();
    assert!(o.status.success(), "local farm render failed: {}", String::from_utf8_lossy(&o.stderr));
    assert_same_pixels(&a, &b);
    if Path::new("/proc/self").exists() {
        assert!(!stale.exists(), "a dead run's directory is still there");
    }
    assert!(live.exists() && other.exists(), "a directory that is not a dead run's was removed");
}

#[test]
fn gltf_with_external_files_round_trips() {
    let mut farm = Farm::new("gltf", 30, &[]);
    farm.add_worker(2);
    let fixtures = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scene/tests/fixtures/scenes");
    // An external .bin with two cameras; an external .bin and an external PNG texture.
    for (scene, camera) in [("Cameras/glTF/Cameras.gltf", "1"), ("TexturedQuad/glTF/TexturedQuad.gltf", "0")] {
        let scene = fixtures.join(scene);
        let scene = scene.to_str().unwrap();
        let (local, remote) = (farm.dir.join("local.exr"), farm.dir.join("remote.exr"));
        let args = [SMALL, &["--camera", camera]].concat();
        local_render(scene, &args, &local);
        let o = farm.submit(scene, &args, &remote);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        assert_same_pixels(&local, &remote);
    }
}

/// A farm with two one-thread workers, a render of `LONG` a fifth done, and the local image of it.
#[test]
fn a_killed_worker_loses_nothing() {
    let (farm, local, id) = two_workers_mid_render("sigkill", 2);
    farm.workers[0].signal("-KILL");
    let out = farm.dir.join("farm.exr");
    farm.wait_and_fetch(&id, &out);
    assert_same_pixels(&out, &local);
}

#[test]
fn sigterm_lets_a_worker_finish_its_job_and_leave() {
    let (mut farm, local, id) = two_workers_mid_render("sigterm", 30);
    farm.workers[0].signal("-TERM");
    let start = Instant::now();
    let status = loop {
        if let Some(status) = farm.workers[0].0.try_wait().unwrap() {
            break status;
        }
        assert!(start.elapsed() < Duration::from_secs(30), "the worker did not stop");
        std::thread::sleep(Duration::from_millis(50));
    };
    assert!(status.success(), "worker exit status {status}");
    // With a 30 s lease, the render finishes this soon only if nothing was left dangling.
    let out = farm.dir.join("farm.exr");
    let waited = Instant::now();
    farm.wait_and_fetch(&id, &out);
    assert!(waited.elapsed() < Duration::from_secs(25), "a lease was abandoned and had to expire");
    assert_same_pixels(&out, &local);
    let log = std::fs::read_to_string(farm.dir.join("worker0.log")).unwrap();
    assert!(log.contains("handed back the job leased ahead"), "{log}");
    // It said goodbye: `tessera workers` shows it stopped, not idle or lost.
    let o = farm.client(&["workers", "--json"]).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let workers: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let state = |name: &str| workers.as_array().unwrap().iter().find(|w| w["name"] == name).unwrap()["state"].clone();
    assert_eq!(state("w0"), "stopped", "{workers}");
    assert_ne!(state("w1"), "stopped", "{workers}");
    let o = farm.client(&["workers", "--json", "--hide-gone", "0"]).output().unwrap();
    let shown: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert!(shown.as_array().unwrap().iter().all(|w| w["name"] != "w0"), "{shown}");
}

#[test]
fn an_interrupted_submit_leaves_the_render_running() {
    let mut farm = Farm::new("interrupted-submit", 30, &[]);
    let local = farm.dir.join("local.exr");
    local_render("builtin:cornell-box", LONG, &local);
    farm.add_worker(2);
    let mut args = vec!["submit", "builtin:cornell-box", "--out", "never.exr"];
    args.extend(LONG);
    let mut submit = Proc(farm.client(&args).stderr(Stdio::piped()).spawn().unwrap());
    farm.wait_progress("1", 0.1);
    submit.signal("-TERM");
    let status = submit.0.wait().unwrap();
    let mut stderr = String::new();
    std::io::Read::read_to_string(&mut submit.0.stderr.take().unwrap(), &mut stderr).unwrap();
    assert!(!status.success());
    assert!(stderr.contains("interrupted: stopped following render 1"), "{stderr}");
    let out = farm.dir.join("farm.exr");
    farm.wait_and_fetch("1", &out);
    assert_same_pixels(&out, &local);
}

/// The failure policy from the command line: with --max-attempts 1 a killed worker's expired
/// lease fails the render, `status` and `watch` say why, and `tessera retry` finishes it with the
/// same pixels as `tessera render` (what was rendered before the failure is kept).
#[test]
fn a_failed_render_says_why_and_retry_finishes_it() {
    let (farm, local, id) = two_workers_mid_render_with("retry", 2, &[("TESSERA_MAX_ATTEMPTS", "1")]);
    farm.workers[0].signal("-KILL");
    let start = Instant::now();
    let status = loop {
        let text = String::from_utf8_lossy(&farm.client(&["status", &id]).output().unwrap().stdout).into_owned();
        if text.contains("failed") {
            break text;
        }
        assert!(start.elapsed() < Duration::from_secs(60), "the render did not fail:\n{text}\n{}", farm.logs());
        std::thread::sleep(Duration::from_millis(200));
    };
    assert!(status.contains("lease expired on worker w0"), "{status}");
    let o = farm.client(&["watch", &id]).output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("failed") && err.contains("tessera retry"), "{err}");
    let o = farm.client(&["retry", &id]).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let out = farm.dir.join("farm.exr");
    farm.wait_and_fetch(&id, &out);
    assert_same_pixels(&out, &local);
}

#[test]
fn a_stopped_worker_comes_back_too_late() {
    let (farm, local, id) = two_workers_mid_render("sigstop", 1);
    farm.workers[0].signal("-STOP");
    std::thread::sleep(Duration::from_millis(3000)); // its leases expire (1 s)
    farm.workers[0].signal("-CONT");
    let out = farm.dir.join("farm.exr");
    farm.wait_and_fetch(&id, &out);
    assert_same_pixels(&out, &local);
    // Give the resumed worker time to report, then check its late result was refused.
    let start = Instant::now();
    while !farm.logs().lines().any(|l| l.contains("ignored a result") && l.contains("late")) {
        assert!(start.elapsed() < Duration::from_secs(20), "no late result was ignored:\n{}", farm.logs());
        std::thread::sleep(Duration::from_millis(200));
    }
}

/// With the feature layers on (`--aov`): they are stored with each result, rebuilt with the film
/// on restart and written beside the colour, the same bits as `tessera render`'s.
#[test]
fn a_killed_coordinator_resumes_without_rerendering() {
    let mut farm = Farm::new("restart", 2, &[]);
    let local = farm.dir.join("local.exr");
    let args = [LONG, &["--aov", "albedo,normal"]].concat();
    local_render("builtin:cornell-box", &args, &local);
    assert!(tessera_film::read_exr(&local).unwrap().features.is_some(), "--aov wrote no layers");
    farm.add_worker(2);
    let id = farm.submit_detached("builtin:cornell-box", &args);
    farm.wait_progress(&id, 0.3);
    farm.coordinator.as_ref().unwrap().signal("-KILL");
    drop(farm.coordinator.take());
    let merged_before = merged_passes(&farm.dir.join("data/tessera.db"));
    assert!(merged_before > 0, "no pass was merged before the kill");
    farm.start_coordinator(2);
    let out = farm.dir.join("farm.exr");
    farm.wait_and_fetch(&id, &out);
    assert_same_pixels(&out, &local);
    // 96 x 96 in 32 x 32 tiles is 9 tiles; 512 spp in 16-spp passes is 32 passes each. Each pass
    // was stored exactly once: none merged before the kill was merged (or rendered) again.
    assert_eq!(merged_passes(&farm.dir.join("data/tessera.db")), 9 * 32);
}

/// `tessera backup` of a serving coordinator mid-render; the data directory is then lost with
/// the coordinator (SIGKILL), and a coordinator started on the backup finishes the render to the
/// same pixels as `tessera render`, every pass stored once.
#[test]
fn a_backup_taken_while_serving_restores_the_farm() {
    let (mut farm, local, id) = two_workers_mid_render("backup", 2);
    let copy = farm.dir.join("backup");
    let o = Command::new(bin()).arg("backup").arg(&copy).arg("--data-dir").arg(farm.dir.join("data")).output().unwrap();
    assert!(o.status.success(), "backup failed: {}", String::from_utf8_lossy(&o.stderr));
    let said = String::from_utf8_lossy(&o.stdout).into_owned();
    assert!(said.starts_with("backed up 1 render(s)") && said.contains("1 scene(s)"), "{said}");
    let o = Command::new(bin()).arg("backup").arg(&copy).arg("--data-dir").arg(farm.dir.join("data")).output().unwrap();
    assert!(!o.status.success() && String::from_utf8_lossy(&o.stderr).contains("already exists"));
    farm.coordinator.as_ref().unwrap().signal("-KILL");
    drop(farm.coordinator.take());
    std::fs::rename(farm.dir.join("data"), farm.dir.join("data.lost")).unwrap();
    std::fs::rename(&copy, farm.dir.join("data")).unwrap();
    farm.start_coordinator(2);
    let out = farm.dir.join("farm.exr");
    farm.wait_and_fetch(&id, &out);
    assert_same_pixels(&out, &local);
    assert_eq!(merged_passes(&farm.dir.join("data/tessera.db")), 9 * 32, "each pass stored once");
}

/// A sequence of 8 frames on two workers, one SIGKILLed mid-sequence and the coordinator
/// SIGKILLed and restarted once: every frame is the same file as `tessera render --frame F`'s.
#[test]
fn a_sequence_survives_a_killed_worker_and_a_restarted_coordinator() {
    let mut farm = Farm::new("sequence", 2, &[]);
    let scene = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../scene/tests/fixtures/scenes/BoxAnimated/glTF-Binary/BoxAnimated.glb");
    let scene = scene.to_str().unwrap();
    let args: &[&str] = &["--width", "64", "--height", "48", "--spp", "512", "--seed", "4", "--frames", "1-78x11"];
    let local = farm.dir.join("local.##.exr");
    local_render(scene, args, &local);
    farm.add_worker(1);
    farm.add_worker(1);
    let id = farm.submit_detached(scene, args);
    assert!(id.starts_with('s'), "a sequence's id: {id}");
    farm.wait_progress(&id, 0.25);
    farm.workers[0].signal("-KILL");
    farm.add_worker(1);
    farm.wait_progress(&id, 0.5);
    farm.coordinator.as_ref().unwrap().signal("-KILL");
    drop(farm.coordinator.take());
    // 8 frames of 4 tiles of 32 passes: the kills came mid-sequence.
    let merged = merged_passes(&farm.dir.join("data/tessera.db"));
    assert!(merged > 0 && merged < 8 * 4 * 32, "{merged} passes merged when the coordinator was killed");
    farm.start_coordinator(2);
    let o = farm.client(&["watch", &id]).output().unwrap();
    assert!(o.status.success(), "watch failed: {}\n{}", String::from_utf8_lossy(&o.stderr), farm.logs());
    let o = farm.client(&["status", &id]).output().unwrap();
    let text = String::from_utf8_lossy(&o.stdout).into_owned();
    assert!(text.contains("done") && text.contains("8/8 frames"), "{text}");
    // One frame by --frame, then every finished frame with one command, and a range of them.
    let one = farm.dir.join("one.##.exr");
    let o = farm.client(&["fetch", &id, "--frame", "12", "--out", one.to_str().unwrap()]).output().unwrap();
    assert!(o.status.success(), "fetch failed: {}", String::from_utf8_lossy(&o.stderr));
    assert!(farm.dir.join("one.12.exr").is_file());
    let every = farm.dir.join("farm.##.exr");
    let o = farm.client(&["fetch", &id, "--out", every.to_str().unwrap()]).output().unwrap();
    assert!(o.status.success(), "fetch failed: {}", String::from_utf8_lossy(&o.stderr));
    for frame in (1..=78).step_by(11) {
        let out = farm.dir.join(format!("farm.{frame:02}.exr"));
        let local = farm.dir.join(format!("local.{frame:02}.exr"));
        assert!(
            std::fs::read(&out).unwrap() == std::fs::read(&local).unwrap(),
            "frame {frame} differs\n{}",
            farm.logs()
        );
    }
    let some = farm.dir.join("some.####.exr");
    let o = farm.client(&["fetch", &id, "--frames", "20-50", "--out", some.to_str().unwrap()]).output().unwrap();
    assert!(o.status.success(), "fetch failed: {}", String::from_utf8_lossy(&o.stderr));
    let fetched: Vec<bool> =
        [23, 34, 45, 12, 56].iter().map(|f| farm.dir.join(format!("some.{f:04}.exr")).is_file()).collect();
    assert_eq!(fetched, [true, true, true, false, false], "frames 23, 34 and 45 lie in 20-50");
    // For scripts: the sequence's status as JSON.
    let o = farm.client(&["status", &id, "--json"]).output().unwrap();
    let rows: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(rows[0]["state"], "done", "{rows}");
    assert_eq!(rows[0]["frames"]["done"], 8, "{rows}");
}

/// Chaos, bounded: three renders and a sequence at once while workers are SIGKILLed (and replaced) and
/// SIGSTOPped past their lease at random (a fixed seed), the coordinator is SIGKILLed and
/// restarted twice, the second time from a `tessera backup` taken while it served, its data
/// directory lost, and a fifth worker returns wrong sums under `--verify 0.5`. Every image is the same file as `tessera render`'s, every pass is stored
/// exactly once, and the last coordinator's ignored-results counter equals the ignored results
/// its log reports.
#[test]
fn chaos_loses_nothing_and_changes_no_bit() {
    let extra = [("TESSERA_MAX_ATTEMPTS", "1000"), ("TESSERA_METRICS", "127.0.0.1:0"), ("TESSERA_VERIFY", "0.5")];
    let mut farm = Farm::new("chaos", 2, &extra);
    let renders: [&[&str]; 3] = [
        &["--width", "96", "--height", "64", "--spp", "256", "--seed", "1"],
        &["--width", "64", "--height", "96", "--spp", "192", "--seed", "2"],
        &["--width", "80", "--height", "80", "--spp", "128", "--seed", "3", "--estimator", "nee"],
    ];
    let locals: Vec<PathBuf> = (0..renders.len()).map(|i| farm.dir.join(format!("local{i}.exr"))).collect();
    for (args, local) in renders.iter().zip(&locals) {
        local_render("builtin:cornell-box", args, local);
    }
    // And a sequence of four frames of an animated scene.
    let animated = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../scene/tests/fixtures/scenes/BoxAnimated/glTF-Binary/BoxAnimated.glb");
    let animated = animated.to_str().unwrap();
    let sequence: &[&str] = &["--width", "48", "--height", "48", "--spp", "256", "--seed", "7", "--frames", "6-66x20"];
    local_render(animated, sequence, &farm.dir.join("local-frame.##.exr"));
    for _ in 0..4 {
        farm.add_worker(1);
    }
    // And a worker that returns wrong sums, under --verify 0.5.
    let (sent, stop) = (Arc::new(AtomicU64::new(0)), Arc::new(AtomicBool::new(false)));
    let liar = start_liar(farm.url(), sent, stop.clone());
    let ids: Vec<String> = renders.iter().map(|args| farm.submit_detached("builtin:cornell-box", args)).collect();
    let sequence_id = farm.submit_detached(animated, sequence);
    let mut rng = 0x9e37_79b9_7f4a_7c15u64;
    let mut next = move || {
        rng ^= rng << 13;
        rng ^= rng >> 7;
        rng ^= rng << 17;
        rng
    };
    let (mut live, mut stopped): (Vec<usize>, Vec<(usize, Instant)>) = ((0..4).collect(), Vec::new());
    let (mut kills, mut stops) = (0, 0);
    let start = Instant::now();
    let mut coordinator_kills = [Duration::from_secs(4), Duration::from_secs(10)].into_iter().peekable();
    while start.elapsed() < Duration::from_secs(16) {
        std::thread::sleep(Duration::from_millis(700));
        for &(w, _) in stopped.iter().filter(|(_, until)| Instant::now() >= *until) {
            farm.workers[w].signal("-CONT");
        }
        stopped.retain(|(_, until)| Instant::now() < *until);
        if coordinator_kills.peek().is_some_and(|&at| start.elapsed() >= at) {
            coordinator_kills.next();
            // The second time, a backup is taken while it serves, the coordinator is killed
            // with its data directory lost, and the farm goes on from the backup.
            let restore = coordinator_kills.peek().is_none();
            let backup = farm.dir.join("backup");
            if restore {
                let o = Command::new(bin())
                    .arg("backup")
                    .arg(&backup)
                    .arg("--data-dir")
                    .arg(farm.dir.join("data"))
                    .output();
                assert!(o.unwrap().status.success(), "the backup failed\n{}", farm.logs());
            }
            farm.coordinator.as_ref().unwrap().signal("-KILL");
            drop(farm.coordinator.take());
            if restore {
                std::fs::rename(farm.dir.join("data"), farm.dir.join("data.lost")).unwrap();
                std::fs::rename(&backup, farm.dir.join("data")).unwrap();
            }
            farm.start_coordinator(2);
            continue;
        }
        let pick = live[next() as usize % live.len()];
        if stopped.iter().any(|&(w, _)| w == pick) {
            continue;
        }
        if next() % 2 == 0 {
            kills += 1;
            farm.workers[pick].signal("-KILL");
            live.retain(|&w| w != pick);
            farm.add_worker(1);
            live.push(farm.workers.len() - 1);
        } else {
            stops += 1;
            farm.workers[pick].signal("-STOP");
            stopped.push((pick, Instant::now() + Duration::from_secs(3)));
        }
    }
    for (w, _) in stopped.drain(..) {
        farm.workers[w].signal("-CONT");
    }
    for (i, id) in ids.iter().enumerate() {
        let out = farm.dir.join(format!("farm{i}.exr"));
        farm.wait_and_fetch(id, &out);
        let (a, b) = (std::fs::read(&out).unwrap(), std::fs::read(&locals[i]).unwrap());
        assert!(a == b, "render {id}: the farm's file differs from tessera render's\n{}", farm.logs());
    }
    let o = farm.client(&["watch", &sequence_id]).output().unwrap();
    assert!(o.status.success(), "watch failed: {}\n{}", String::from_utf8_lossy(&o.stderr), farm.logs());
    for frame in [6, 26, 46, 66] {
        let out = farm.dir.join(format!("farm-frame.{frame}.exr"));
        let f = frame.to_string();
        let o = farm.client(&["fetch", &sequence_id, "--frame", &f, "--out", out.to_str().unwrap()]).output().unwrap();
        assert!(o.status.success(), "fetch failed: {}", String::from_utf8_lossy(&o.stderr));
        let local = std::fs::read(farm.dir.join(format!("local-frame.{frame:02}.exr"))).unwrap();
        assert!(std::fs::read(&out).unwrap() == local, "frame {frame} of the sequence differs\n{}", farm.logs());
    }
    // Every pass stored exactly once: per tile, the stored ranges tile the passes without overlap.
    let conn = rusqlite::Connection::open(farm.dir.join("data/tessera.db")).unwrap();
    let mut stmt = conn
        .prepare("SELECT render, tile, first_pass, pass_count FROM results ORDER BY render, tile, first_pass")
        .unwrap();
    let rows: Vec<(i64, i64, i64, i64)> =
        stmt.query_map([], |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?, r.get(3)?))).unwrap().map(Result::unwrap).collect();
    let mut expected_next = std::collections::HashMap::new();
    for (render, tile, first, count) in &rows {
        let next_pass = expected_next.entry((*render, *tile)).or_insert(0);
        assert_eq!(first, next_pass, "render {render} tile {tile}: a gap or an overlap at pass {first}");
        *next_pass += count;
    }
    for (i, args) in renders.iter().enumerate() {
        let arg = |name: &str| args[args.iter().position(|a| *a == name).unwrap() + 1].parse::<i64>().unwrap();
        let tiles = ((arg("--width") + 31) / 32) * ((arg("--height") + 31) / 32);
        let passes: i64 = expected_next.iter().filter(|((r, _), _)| *r == i as i64 + 1).map(|(_, n)| n).sum();
        assert_eq!(passes, tiles * ((arg("--spp") + 15) / 16), "render {}: passes stored", i + 1);
    }
    // The last coordinator's counter of ignored results equals the ignored results it logged.
    let text = http_get(farm.metrics.unwrap(), "/metrics");
    let counted: u64 = text
        .lines()
        .filter(|l| l.starts_with("tessera_results_ignored_total{"))
        .filter_map(|l| l.rsplit(' ').next()?.parse::<u64>().ok())
        .sum();
    let log = std::fs::read_to_string(farm.dir.join("coordinator.log")).unwrap();
    let logged = log.lines().filter(|l| l.contains("ignored a result")).count() as u64;
    assert_eq!(counted, logged, "{text}");
    stop.store(true, Ordering::Relaxed);
    let lies = liar.join().unwrap();
    assert!(
        lies.refusal.contains("is blocked"),
        "the lying worker was not blocked: {:?}\n{}",
        lies.refusal,
        farm.logs()
    );
    eprintln!(
        "chaos: {kills} workers killed, {stops} stopped, the coordinator killed twice (restored from a backup once); \
         {counted} results ignored; the lying worker sent {} results before it was blocked",
        lies.sent
    );
    assert!(text.contains("tessera_pending_frames 0"), "{text}");
}

/// `--verify 1`: a worker returning plausible wrong sums (right tile and counts, values in
/// bounds) is outvoted by two honest `tessera worker`s, blocked for the farm (it is refused jobs
/// with a message saying why), counted in `tessera_results_disputed_total`, and its results
/// are rendered again: the image is the same file as `tessera render`'s.
#[test]
fn a_lying_worker_is_caught_and_the_image_matches_tessera_render() {
    let mut farm = Farm::new("liar", 5, &[("TESSERA_VERIFY", "1"), ("TESSERA_METRICS", "127.0.0.1:0")]);
    let args = ["--width", "64", "--height", "48", "--spp", "64", "--seed", "11"];
    let local = farm.dir.join("local.exr");
    local_render("builtin:cornell-box", &args, &local);
    // The liar works alone first, so that results of its are merged before anyone checks them.
    let (sent, stop) = (Arc::new(AtomicU64::new(0)), Arc::new(AtomicBool::new(false)));
    let liar = start_liar(farm.url(), sent.clone(), stop.clone());
    let id = farm.submit_detached("builtin:cornell-box", &args);
    let start = Instant::now();
    while sent.load(Ordering::Relaxed) < 3 {
        assert!(start.elapsed() < Duration::from_secs(30), "the liar got no work\n{}", farm.logs());
        std::thread::sleep(Duration::from_millis(20));
    }
    farm.add_worker(1);
    farm.add_worker(1);
    let out = farm.dir.join("farm.exr");
    farm.wait_and_fetch(&id, &out);
    stop.store(true, Ordering::Relaxed);
    let lies = liar.join().unwrap();
    assert!(lies.refusal.contains("is blocked"), "the liar was not refused: {:?}\n{}", lies.refusal, farm.logs());
    assert!(std::fs::read(&out).unwrap() == std::fs::read(&local).unwrap(), "the images differ\n{}", farm.logs());
    let text = http_get(farm.metrics.unwrap(), "/metrics");
    assert!(text.contains("tessera_workers_blocked 1\n"), "{text}");
    let disputed = text.lines().find_map(|l| l.strip_prefix("tessera_results_disputed_total ")).unwrap();
    assert!(disputed.parse::<u64>().unwrap() >= 1, "{text}");
    let log = std::fs::read_to_string(farm.dir.join("coordinator.log")).unwrap();
    assert!(log.contains("blocked worker liar"), "{log}");
    eprintln!("the liar sent {} results before it was blocked", lies.sent);
}

/// Sum of pass counts over the stored results, read with the sqlite3-compatible file format.
fn merged_passes(db: &Path) -> u64 {
    let conn = rusqlite::Connection::open(db).unwrap();
    conn.query_row("SELECT COALESCE(SUM(pass_count), 0) FROM results", [], |r| r.get::<_, i64>(0)).unwrap() as u64
}

#[test]
fn adaptive_budgets_stop_converged_tiles_and_stay_deterministic() {
    // 128 x 32 is four tiles side by side: the outer two see only the uniform environment (no
    // variance), the inner two the sphere. With a stated error (`--confidence`): tiles stop on
    // their error bounds, and the image states its error.
    let scene = "builtin:furnace?base=0.8&metallic=0.5&roughness=0.4";
    let args = [
        "--width",
        "128",
        "--height",
        "32",
        "--spp",
        "256",
        "--target-error",
        "0.01",
        "--min-spp",
        "16",
        "--confidence",
        "0.95",
    ];
    // The farms stay up to the end: their folders, which hold the images, go with them.
    let (mut images, mut farms) = (Vec::new(), Vec::new());
    for workers in [1, 2] {
        let mut farm = Farm::new(&format!("adaptive{workers}"), 30, &[]);
        for _ in 0..workers {
            farm.add_worker(1);
        }
        let out = farm.dir.join("adaptive.exr");
        let o = farm.submit(scene, &args, &out);
        assert!(o.status.success(), "{}\n{}", String::from_utf8_lossy(&o.stderr), farm.logs());
        images.push(out);
        farms.push(farm);
    }
    assert_same_pixels(&images[0], &images[1]);
    // `tessera render` runs the same rounds on its threads: the same budgets, the same bits.
    let local = images[0].with_file_name("local.exr");
    local_render(scene, &args, &local);
    assert_same_pixels(&images[0], &local);
    let img = tessera_film::read_exr(&images[0]).unwrap();
    let stated = |img: &tessera_film::ExrImage| -> String {
        img.metadata.lines().filter(|l| l.starts_with("relative_error=")).collect::<Vec<_>>().join("\n")
    };
    let statement = stated(&img);
    assert!(
        statement.contains(" error_bound=") && statement.ends_with(" confidence=0.95 target_error=0.01"),
        "the image states its error: {statement:?}"
    );
    assert_eq!(statement, stated(&tessera_film::read_exr(&local).unwrap()), "the farm states what render states");
    let spp_of_tile = |t: u32| -> Vec<f32> {
        (0..32).flat_map(|y| (0..32).map(move |x| (y * 128 + t * 32 + x) as usize)).map(|i| img.spp[i]).collect()
    };
    assert!(
        spp_of_tile(0).iter().chain(&spp_of_tile(3)).all(|&n| n == 16.0),
        "background tiles stop after the first round"
    );
    assert!(
        spp_of_tile(1).iter().all(|&n| n > 16.0 && n <= 256.0),
        "sphere tiles get more: {:?}",
        &spp_of_tile(1)[..4]
    );
}
