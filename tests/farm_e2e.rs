//! End-to-end tests of the farm: a real coordinator, real workers and the CLI client as separate
//! processes on loopback. Every image must be bit-identical to `tessera render` with the same
//! scene, settings and seed, whatever happens to the processes.

use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

fn bin() -> &'static str {
    env!("CARGO_BIN_EXE_tessera")
}

#[path = "common/mod.rs"]
mod common;
use common::{Proc, assert_same_pixels, free_port};

fn scratch(name: &str) -> common::Scratch {
    common::scratch("farm", name)
}

struct Farm {
    port: u16,
    coordinator: Option<Proc>,
    workers: Vec<Proc>,
    extra: Vec<(String, String)>,
    /// Last, so that it is removed after the processes writing into it are gone.
    dir: common::Scratch,
}

impl Farm {
    fn new(name: &str, lease_seconds: u32, extra: &[(&str, &str)]) -> Self {
        let mut farm = Farm {
            port: free_port(),
            dir: scratch(name),
            coordinator: None,
            workers: Vec::new(),
            extra: extra.iter().map(|(k, v)| (k.to_string(), v.to_string())).collect(),
        };
        farm.start_coordinator(lease_seconds);
        farm
    }

    fn url(&self) -> String {
        if self.extra.iter().any(|(k, _)| k == "TESSERA_TLS_CERT") {
            format!("https://localhost:{}", self.port)
        } else {
            format!("http://127.0.0.1:{}", self.port)
        }
    }

    fn start_coordinator(&mut self, lease_seconds: u32) {
        let log = std::fs::File::create(self.dir.join("coordinator.log")).unwrap();
        let mut cmd = Command::new(bin());
        cmd.args([
            "coordinator",
            "--listen",
            &format!("127.0.0.1:{}", self.port),
            "--lease-seconds",
            &lease_seconds.to_string(),
        ])
        .arg("--data-dir")
        .arg(self.dir.join("data"))
        .stderr(log)
        .stdout(Stdio::null());
        for (k, v) in &self.extra {
            cmd.env(k, v);
        }
        self.coordinator = Some(Proc(cmd.spawn().unwrap()));
        let start = Instant::now();
        while std::net::TcpStream::connect(("127.0.0.1", self.port)).is_err() {
            assert!(start.elapsed() < Duration::from_secs(20), "coordinator did not start");
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    fn add_worker(&mut self, threads: u32) {
        self.add_worker_with(threads, &[]);
    }

    /// A worker with the farm's environment, less the coordinator's metrics address, plus `env`.
    fn add_worker_with(&mut self, threads: u32, env: &[(&str, &str)]) {
        let i = self.workers.len();
        let log = std::fs::File::create(self.dir.join(format!("worker{i}.log"))).unwrap();
        let mut cmd = Command::new(bin());
        cmd.args([
            "worker",
            "--coordinator",
            &self.url(),
            "--threads",
            &threads.to_string(),
            "--name",
            &format!("w{i}"),
        ])
        .stderr(log)
        .stdout(Stdio::null());
        for (k, v) in self.extra.iter().filter(|(k, _)| k != "TESSERA_METRICS") {
            cmd.env(k, v);
        }
        cmd.env_remove("TESSERA_METRICS").envs(env.iter().copied());
        self.workers.push(Proc(cmd.spawn().unwrap()));
    }

    fn client(&self, args: &[&str]) -> Command {
        let mut cmd = Command::new(bin());
        cmd.args(args).args(["--coordinator", &self.url()]);
        for (k, v) in &self.extra {
            cmd.env(k, v);
        }
        cmd
    }

    fn submit(&self, scene: &str, render_args: &[&str], out: &Path) -> Output {
        let mut args = vec!["submit", scene, "--out", out.to_str().unwrap()];
        args.extend(render_args);
        self.client(&args).output().unwrap()
    }

    fn submit_detached(&self, scene: &str, render_args: &[&str]) -> String {
        let mut args = vec!["submit", scene, "--detach"];
        args.extend(render_args);
        let o = self.client(&args).output().unwrap();
        assert!(o.status.success(), "submit failed: {}", String::from_utf8_lossy(&o.stderr));
        String::from_utf8(o.stdout).unwrap().trim().to_string()
    }

    fn wait_and_fetch(&self, id: &str, out: &Path) {
        // Bounded: a render that never finishes fails the test instead of hanging the suite.
        let o = run_within(&mut self.client(&["watch", id]), Duration::from_secs(300))
            .unwrap_or_else(|| panic!("render {id} did not finish within 300 s\n{}", self.logs()));
        assert!(o.status.success(), "watch failed: {}\n{}", String::from_utf8_lossy(&o.stderr), self.logs());
        let o = self.client(&["fetch", id, "--out", out.to_str().unwrap()]).output().unwrap();
        assert!(o.status.success(), "fetch failed: {}", String::from_utf8_lossy(&o.stderr));
    }

    /// Waits until at least `fraction` of the render's passes are merged (polling `status`).
    fn wait_progress(&self, id: &str, fraction: f64) {
        let start = Instant::now();
        loop {
            let o = self.client(&["status", id]).output().unwrap();
            let text = String::from_utf8_lossy(&o.stdout).into_owned();
            let done = text.lines().nth(1).and_then(|l| l.split_whitespace().nth(2)).and_then(|p| {
                let (d, t) = p.split_once('/')?;
                Some((d.parse::<f64>().ok()?, t.parse::<f64>().ok()?))
            });
            if let Some((d, t)) = done
                && d >= fraction * t
            {
                return;
            }
            assert!(
                start.elapsed() < Duration::from_secs(120),
                "render {id} made no progress:\n{text}\n{}",
                self.logs()
            );
            std::thread::sleep(Duration::from_millis(100));
        }
    }

    fn logs(&self) -> String {
        let mut s = String::new();
        for e in std::fs::read_dir(&self.dir).unwrap().flatten() {
            if e.path().extension().is_some_and(|x| x == "log") {
                s +=
                    &format!("--- {}\n{}\n", e.path().display(), std::fs::read_to_string(e.path()).unwrap_or_default());
            }
        }
        s
    }
}

fn local_render(scene: &str, render_args: &[&str], out: &Path) {
    let mut args = vec!["render", scene, "--out", out.to_str().unwrap(), "-q"];
    args.extend(render_args);
    let o = Command::new(bin()).args(&args).output().unwrap();
    assert!(o.status.success(), "local render failed: {}", String::from_utf8_lossy(&o.stderr));
}

const SMALL: &[&str] = &["--width", "64", "--height", "48", "--spp", "32", "--seed", "5"];

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
    let (host, results, failures) = (w0[1], w0[6].parse::<u64>().unwrap(), w0[7].parse::<u64>().unwrap());
    assert!(host == "127.0.0.1" && results > 0 && failures == 0, "{text}");
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
    let fixtures = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/fixtures/scenes");
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
fn two_workers_mid_render(name: &str, lease_seconds: u32) -> (Farm, PathBuf, String) {
    two_workers_mid_render_with(name, lease_seconds, &[])
}

/// As [`two_workers_mid_render`], with `extra` in the farm's environment.
fn two_workers_mid_render_with(name: &str, lease_seconds: u32, extra: &[(&str, &str)]) -> (Farm, PathBuf, String) {
    let mut farm = Farm::new(name, lease_seconds, extra);
    let local = farm.dir.join("local.exr");
    local_render("builtin:cornell-box", LONG, &local);
    farm.add_worker(1);
    farm.add_worker(1);
    let id = farm.submit_detached("builtin:cornell-box", LONG);
    farm.wait_progress(&id, 0.2);
    (farm, local, id)
}

/// A render long enough to interrupt: a few seconds on two threads.
const LONG: &[&str] = &["--width", "96", "--height", "96", "--spp", "512", "--seed", "9"];

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

#[test]
fn a_killed_coordinator_resumes_without_rerendering() {
    let mut farm = Farm::new("restart", 2, &[]);
    let local = farm.dir.join("local.exr");
    local_render("builtin:cornell-box", LONG, &local);
    farm.add_worker(2);
    let id = farm.submit_detached("builtin:cornell-box", LONG);
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

/// A sequence of 8 frames on two workers, one SIGKILLed mid-sequence and the coordinator
/// SIGKILLed and restarted once: every frame is the same file as `tessera render --frame F`'s.
#[test]
fn a_sequence_survives_a_killed_worker_and_a_restarted_coordinator() {
    let mut farm = Farm::new("sequence", 2, &[]);
    let scene = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../tests/fixtures/scenes/BoxAnimated/glTF-Binary/BoxAnimated.glb");
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
    for frame in (1..=78).step_by(11) {
        let out = farm.dir.join(format!("farm.{frame:02}.exr"));
        let f = frame.to_string();
        let o = farm.client(&["fetch", &id, "--frame", &f, "--out", out.to_str().unwrap()]).output().unwrap();
        assert!(o.status.success(), "fetch failed: {}", String::from_utf8_lossy(&o.stderr));
        let local = farm.dir.join(format!("local.{frame:02}.exr"));
        assert!(
            std::fs::read(&out).unwrap() == std::fs::read(&local).unwrap(),
            "frame {frame} differs\n{}",
            farm.logs()
        );
    }
}

/// Chaos, bounded: three renders and a sequence at once while workers are SIGKILLed (and replaced) and
/// SIGSTOPped past their lease at random (a fixed seed), and the coordinator is SIGKILLed and
/// restarted twice. Every image is the same file as `tessera render`'s, every pass is stored
/// exactly once, and the last coordinator's ignored-results counter equals the ignored results
/// its log reports.
#[test]
fn chaos_loses_nothing_and_changes_no_bit() {
    let metrics_port = free_port();
    let metrics = format!("127.0.0.1:{metrics_port}");
    let extra = [("TESSERA_MAX_ATTEMPTS", "1000"), ("TESSERA_METRICS", metrics.as_str())];
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
        .join("../../tests/fixtures/scenes/BoxAnimated/glTF-Binary/BoxAnimated.glb");
    let animated = animated.to_str().unwrap();
    let sequence: &[&str] = &["--width", "48", "--height", "48", "--spp", "256", "--seed", "7", "--frames", "6-66x20"];
    local_render(animated, sequence, &farm.dir.join("local-frame.##.exr"));
    for _ in 0..4 {
        farm.add_worker(1);
    }
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
            farm.coordinator.as_ref().unwrap().signal("-KILL");
            drop(farm.coordinator.take());
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
    let text = http_get(metrics_port, "/metrics");
    let counted: u64 = text
        .lines()
        .filter(|l| l.starts_with("tessera_results_ignored_total{"))
        .filter_map(|l| l.rsplit(' ').next()?.parse::<u64>().ok())
        .sum();
    let log = std::fs::read_to_string(farm.dir.join("coordinator.log")).unwrap();
    let logged = log.lines().filter(|l| l.contains("ignored a result")).count() as u64;
    assert_eq!(counted, logged, "{text}");
    eprintln!(
        "chaos: {kills} workers killed, {stops} stopped, the coordinator killed twice; {counted} results ignored"
    );
    assert!(text.contains("tessera_pending_frames 0"), "{text}");
}

/// Sum of pass counts over the stored results, read with the sqlite3-compatible file format.
fn merged_passes(db: &Path) -> u64 {
    let conn = rusqlite::Connection::open(db).unwrap();
    conn.query_row("SELECT COALESCE(SUM(pass_count), 0) FROM results", [], |r| r.get::<_, i64>(0)).unwrap() as u64
}

#[test]
fn adaptive_budgets_stop_converged_tiles_and_stay_deterministic() {
    // 128 x 32 is four tiles side by side: the outer two see only the uniform environment (no
    // variance), the inner two the sphere.
    let scene = "builtin:furnace?base=0.8&metallic=0.5&roughness=0.4";
    let args = ["--width", "128", "--height", "32", "--spp", "256", "--target-error", "0.01", "--min-spp", "16"];
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

/// One plain HTTP GET on loopback; the whole response, status line first.
fn http_get(port: u16, path: &str) -> String {
    use std::io::{Read, Write};
    let mut s = std::net::TcpStream::connect(("127.0.0.1", port)).unwrap();
    s.write_all(format!("GET {path} HTTP/1.1\r\nHost: x\r\n\r\n").as_bytes()).unwrap();
    let mut text = String::new();
    s.read_to_string(&mut text).unwrap();
    text
}

#[test]
fn metrics_and_json_logs() {
    let metrics_port = free_port();
    let addr = format!("127.0.0.1:{metrics_port}");
    let mut farm = Farm::new("metrics", 30, &[("TESSERA_METRICS", addr.as_str()), ("TESSERA_LOG_FORMAT", "json")]);
    assert!(http_get(metrics_port, "/healthz").starts_with("HTTP/1.1 200"));
    assert!(http_get(metrics_port, "/readyz").starts_with("HTTP/1.1 200"));
    let worker_port = free_port();
    farm.add_worker_with(2, &[("TESSERA_METRICS", &format!("127.0.0.1:{worker_port}"))]);
    let out = farm.dir.join("m.exr");
    let o = farm.submit("builtin:cornell-box", &["--width", "32", "--height", "32", "--spp", "32"], &out);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(http_get(worker_port, "/healthz").starts_with("HTTP/1.1 200"));
    assert!(http_get(worker_port, "/readyz").starts_with("HTTP/1.1 200"), "the worker has worked: it is connected");
    let worker_metrics = http_get(worker_port, "/metrics");
    assert!(worker_metrics.contains("tessera_worker_samples_total 32768"), "{worker_metrics}");
    assert!(http_get(worker_port, "/nothing").starts_with("HTTP/1.1 404"));
    let text = http_get(metrics_port, "/metrics");
    // 32 x 32 is one tile; 32 spp is two passes.
    for needle in [
        "tessera_passes_completed_total 2",
        "tessera_workers_alive 1",
        "tessera_samples_merged_total 32768",
        "tessera_merge_seconds_total",
    ] {
        assert!(text.contains(needle), "missing {needle} in:\n{text}");
    }
    let log = std::fs::read_to_string(farm.dir.join("coordinator.log")).unwrap();
    assert!(log.lines().any(|l| l.starts_with('{') && l.contains("\"render submitted\"")), "{log}");
}

#[test]
fn tls_with_a_private_ca() {
    let dir = scratch("tls-certs");
    let key = rcgen::KeyPair::generate().unwrap();
    let params = rcgen::CertificateParams::new(vec!["localhost".to_string()]).unwrap();
    let cert = params.self_signed(&key).unwrap();
    let (cert_path, key_path) = (dir.join("cert.pem"), dir.join("key.pem"));
    std::fs::write(&cert_path, cert.pem()).unwrap();
    std::fs::write(&key_path, key.serialize_pem()).unwrap();
    let (c, k) = (cert_path.to_str().unwrap(), key_path.to_str().unwrap());
    let mut farm = Farm::new("tls", 30, &[("TESSERA_TLS_CERT", c), ("TESSERA_TLS_KEY", k), ("TESSERA_CA", c)]);
    farm.add_worker(2);
    let out = farm.dir.join("tls.exr");
    let o = farm.submit("builtin:cornell-box", &["--width", "16", "--height", "16", "--spp", "4"], &out);
    assert!(o.status.success(), "{}\n{}", String::from_utf8_lossy(&o.stderr), farm.logs());
    // Without the CA the client does not trust the coordinator, and says so.
    let mut untrusting = farm.client(&["status"]);
    untrusting.env_remove("TESSERA_CA").env("TESSERA_WAIT_FOR_COORDINATOR", "1");
    let o = untrusting.output().unwrap();
    assert!(!o.status.success(), "an unknown CA was trusted");
    assert!(
        String::from_utf8_lossy(&o.stderr).contains("not signed by a CA this machine trusts"),
        "{}",
        String::from_utf8_lossy(&o.stderr)
    );
    // Plain HTTP at the TLS coordinator is told what to use instead of a bare "h2 protocol error".
    let o = Command::new(bin())
        .args(["status", "--coordinator", &format!("http://127.0.0.1:{}", farm.port)])
        .env("TESSERA_WAIT_FOR_COORDINATOR", "0")
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && err.contains("speaks TLS: use https://"),
        "{err} {:?} {}",
        o.status,
        String::from_utf8_lossy(&o.stdout)
    );
}

/// Runs `cmd`, killing it if it has not finished within `limit`; its output, or None if killed.
fn run_within(cmd: &mut Command, limit: Duration) -> Option<Output> {
    let child = cmd.stdout(Stdio::piped()).stderr(Stdio::piped()).spawn().unwrap();
    let start = Instant::now();
    let mut child = Proc(child);
    while child.0.try_wait().unwrap().is_none() {
        if start.elapsed() > limit {
            return None;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    let Proc(c) = &mut child;
    let (mut out, mut err) = (Vec::new(), Vec::new());
    std::io::Read::read_to_end(c.stdout.as_mut().unwrap(), &mut out).unwrap();
    std::io::Read::read_to_end(c.stderr.as_mut().unwrap(), &mut err).unwrap();
    Some(Output { status: c.wait().unwrap(), stdout: out, stderr: err })
}

/// True when the server has closed `s` (a read ends or fails) within `limit`.
fn closed_within(s: &mut std::net::TcpStream, limit: Duration) -> bool {
    s.set_read_timeout(Some(limit)).unwrap();
    let mut buf = [0u8; 64];
    loop {
        match std::io::Read::read(s, &mut buf) {
            Ok(0) => return true,
            Ok(_) => continue, // a TLS alert or HTTP/2 GOAWAY before the close
            Err(e) => return !matches!(e.kind(), std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut),
        }
    }
}

/// Idle connections need no token: 300 of them once hung real clients, and they were never
/// closed. Now a connection that makes no authenticated request within 10 s is closed, at most
/// --max-connections are open, and a client whose coordinator does not answer gives up saying so.
#[test]
fn idle_connections_are_closed_and_bounded() {
    let farm = Farm::new("idle", 30, &[("TESSERA_TOKEN", "idle-test-token-0123456789")]);
    let mut idle: Vec<std::net::TcpStream> =
        (0..300).map(|_| std::net::TcpStream::connect(("127.0.0.1", farm.port)).unwrap()).collect();
    let o = run_within(farm.client(&["status"]).env("TESSERA_WAIT_FOR_COORDINATOR", "0"), Duration::from_secs(20))
        .expect("status hung behind 300 idle connections");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    for (i, s) in idle.iter_mut().enumerate().step_by(50) {
        assert!(closed_within(s, Duration::from_secs(20)), "idle connection {i} was kept open");
    }
    drop(idle);
    // The limit: the ninth connection of eight allowed is closed at once.
    let small = Farm::new("idle-limit", 30, &[("TESSERA_MAX_CONNECTIONS", "8")]);
    std::thread::sleep(Duration::from_millis(500)); // the start-up probe's connection is let go
    let held: Vec<std::net::TcpStream> =
        (0..8).map(|_| std::net::TcpStream::connect(("127.0.0.1", small.port)).unwrap()).collect();
    std::thread::sleep(Duration::from_millis(300));
    let mut ninth = std::net::TcpStream::connect(("127.0.0.1", small.port)).unwrap();
    assert!(closed_within(&mut ninth, Duration::from_secs(3)), "a connection past the limit was kept");
    drop(held);
    assert!(small.logs().contains("refused a connection"), "{}", small.logs());
    // A "coordinator" that accepts and never answers: the client gives up with a message.
    let silent = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let url = format!("http://{}", silent.local_addr().unwrap());
    let o = run_within(
        Command::new(bin()).args(["status", "--coordinator", &url]).env("TESSERA_WAIT_FOR_COORDINATOR", "0"),
        Duration::from_secs(60),
    )
    .expect("status hung on a coordinator that does not answer");
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("coordinator"), "{err}");
    drop(silent);
}

/// A worker pointed at the wrong door (plain HTTP at a TLS coordinator, or at its metrics port)
/// once reconnected in a hot loop, about 5,000 log lines a second. It backs off now, and says
/// what is wrong.
#[test]
fn a_worker_at_the_wrong_door_backs_off_and_says_why() {
    let dir = scratch("wrong-door-certs");
    let key = rcgen::KeyPair::generate().unwrap();
    let cert = rcgen::CertificateParams::new(vec!["localhost".to_string()]).unwrap().self_signed(&key).unwrap();
    let (cert_path, key_path) = (dir.join("cert.pem"), dir.join("key.pem"));
    std::fs::write(&cert_path, cert.pem()).unwrap();
    std::fs::write(&key_path, key.serialize_pem()).unwrap();
    let metrics_port = free_port();
    let metrics = format!("127.0.0.1:{metrics_port}");
    let (c, k) = (cert_path.to_str().unwrap(), key_path.to_str().unwrap());
    let farm =
        Farm::new("wrong-door", 30, &[("TESSERA_TLS_CERT", c), ("TESSERA_TLS_KEY", k), ("TESSERA_METRICS", &metrics)]);
    let doors = [
        (format!("http://127.0.0.1:{}", farm.port), "speaks TLS: use https://"),
        (format!("http://{metrics}"), "metrics port"),
    ];
    for (i, (url, says)) in doors.iter().enumerate() {
        let log = farm.dir.join(format!("wrong{i}.log"));
        let child = Command::new(bin())
            .args(["worker", "--coordinator", url, "--threads", "1"])
            .stderr(std::fs::File::create(&log).unwrap())
            .stdout(Stdio::null())
            .spawn()
            .unwrap();
        let worker = Proc(child);
        std::thread::sleep(Duration::from_secs(4));
        drop(worker);
        let text = std::fs::read_to_string(&log).unwrap();
        let retries = text.lines().filter(|l| l.contains("retrying in")).count();
        assert!((1..=12).contains(&retries), "{retries} retries in 4 s at {url}:\n{text}");
        assert!(text.contains(says), "{url}: the log does not say '{says}':\n{text}");
    }
}

mod hostile {
    //! Bad input at the farm's doors: each refused with a clear message, and the coordinator
    //! keeps serving (a render submitted afterwards completes).

    use super::*;
    use std::io::Write;
    use tessera_proto::PROTOCOL_VERSION;
    use tessera_proto::v1::render_service_client::RenderServiceClient;
    use tessera_proto::v1::*;

    fn stderr(o: &Output) -> String {
        String::from_utf8_lossy(&o.stderr).into_owned()
    }

    fn runtime() -> tokio::runtime::Runtime {
        tokio::runtime::Runtime::new().unwrap()
    }

    #[test]
    fn tokens_are_checked() {
        let mut farm = Farm::new("tokens", 30, &[("TESSERA_TOKEN", "s3cret-s3cret-s3cret")]);
        farm.add_worker(2);
        // The right token (from the environment) works.
        let ok = farm.dir.join("ok.exr");
        let o = farm.submit("builtin:cornell-box", &["--width", "16", "--height", "16", "--spp", "4"], &ok);
        assert!(o.status.success(), "{}", stderr(&o));
        // A wrong one and a missing one are refused, saying so.
        let mut wrong = farm.client(&["status"]);
        wrong.env("TESSERA_TOKEN", "guess-guess-guess-guess");
        let o = wrong.output().unwrap();
        assert!(!o.status.success() && stderr(&o).contains("wrong client token"), "{}", stderr(&o));
        let mut missing = farm.client(&["status"]);
        missing.env_remove("TESSERA_TOKEN");
        let o = missing.output().unwrap();
        assert!(!o.status.success() && stderr(&o).contains("requires a client token"), "{}", stderr(&o));
        assert!(farm.logs().contains("refused a client call"), "refusals are logged");
    }

    /// An empty token must not turn authentication off, nor may a short one stand in for a
    /// secret: every command that reads a token refuses them, from the flag and the environment.
    #[test]
    fn empty_and_short_tokens_are_refused_everywhere() {
        let dir = scratch("short-tokens");
        let data = dir.join("data");
        let data = data.to_str().unwrap();
        type Case<'a> = (&'a [&'a str], &'a [(&'a str, &'a str)], &'a str);
        let cases: [Case; 7] = [
            (&["coordinator", "--data-dir", data, "--token", ""], &[], "empty"),
            (&["coordinator", "--data-dir", data, "--token", "x"], &[], "16-byte minimum"),
            (&["coordinator", "--data-dir", data, "--listen", "0.0.0.0:0"], &[("TESSERA_TOKEN", "")], "empty"),
            (&["coordinator", "--data-dir", data], &[("TESSERA_WORKER_TOKEN", "short")], "16-byte minimum"),
            (&["worker", "--token", ""], &[], "empty"),
            (&["status"], &[("TESSERA_TOKEN", "")], "empty"),
            (&["submit", "builtin:cornell-box", "--token", "abc"], &[], "16-byte minimum"),
        ];
        for (args, env, says) in cases {
            let mut cmd = Command::new(bin());
            cmd.args(args).env_remove("TESSERA_TOKEN").env("TESSERA_WAIT_FOR_COORDINATOR", "0");
            cmd.envs(env.iter().copied());
            let child = cmd.stdout(Stdio::null()).stderr(Stdio::piped()).spawn().unwrap();
            // A command that accepted the token would run (a coordinator serves for good): give
            // it a few seconds, then kill it, and fail.
            let start = Instant::now();
            let mut child = Proc(child);
            while child.0.try_wait().unwrap().is_none() {
                assert!(start.elapsed() < Duration::from_secs(10), "{args:?} {env:?} was accepted");
                std::thread::sleep(Duration::from_millis(20));
            }
            let mut err = String::new();
            std::io::Read::read_to_string(child.0.stderr.as_mut().unwrap(), &mut err).unwrap();
            assert!(!child.0.wait().unwrap().success(), "{args:?} {env:?} succeeded");
            assert!(err.contains(says) && err.contains("token"), "{args:?} {env:?}: {err}");
        }
    }

    /// Per-user tokens: a submitter sees and acts on their own renders only, an admin on all,
    /// a worker's token makes no client calls, and SIGHUP reads the file again.
    #[test]
    fn users_see_their_own_renders_and_roles_are_enforced() {
        const ALICE: &str = "alice-token-0123456789";
        const BOB: &str = "bob-token-0123456789ab";
        const ROOT: &str = "root-token-0123456789a";
        const WORKER: &str = "worker-token-012345678";
        let hash = |token: &str| {
            let mut child =
                Command::new(bin()).arg("token-hash").stdin(Stdio::piped()).stdout(Stdio::piped()).spawn().unwrap();
            child.stdin.take().unwrap().write_all(format!("{token}\n").as_bytes()).unwrap();
            let out = child.wait_with_output().unwrap();
            assert!(out.status.success());
            String::from_utf8(out.stdout).unwrap().trim().to_string()
        };
        assert_eq!(hash(ALICE), blake3::hash(ALICE.as_bytes()).to_hex().to_string());
        let dir = scratch("users-file");
        let file = dir.join("tokens");
        let lines = format!(
            "alice submit {}\nbob submit {}\nroot admin {}\nfarm worker {}\n",
            hash(ALICE),
            hash(BOB),
            hash(ROOT),
            hash(WORKER)
        );
        std::fs::write(&file, &lines).unwrap();
        let mut farm = Farm::new("users", 30, &[("TESSERA_TOKENS", file.to_str().unwrap())]);
        farm.add_worker_with(2, &[("TESSERA_TOKEN", WORKER)]);
        let as_user = |token: &str, args: &[&str]| {
            let mut cmd = farm.client(args);
            cmd.env("TESSERA_TOKEN", token).env("TESSERA_WAIT_FOR_COORDINATOR", "0");
            cmd.output().unwrap()
        };
        let small = ["--width", "16", "--height", "16", "--spp", "4"];
        let mut args = vec!["submit", "builtin:cornell-box", "--detach"];
        args.extend(small);
        let o = as_user(ALICE, &args);
        assert!(o.status.success(), "{}\n{}", stderr(&o), farm.logs());
        let id = String::from_utf8_lossy(&o.stdout).trim().to_string();
        let listed = |token: &str| String::from_utf8_lossy(&as_user(token, &["status"]).stdout).into_owned();
        assert!(listed(ALICE).contains("alice"), "{}", listed(ALICE));
        assert!(!listed(BOB).lines().any(|l| l.starts_with(&format!("{id} "))), "bob sees alice's render");
        assert!(listed(ROOT).contains("alice"), "the admin sees every render");
        for args in [vec!["cancel", id.as_str()], vec!["watch", id.as_str()], vec!["status", id.as_str()]] {
            let o = as_user(BOB, &args);
            assert!(
                !o.status.success() && stderr(&o).contains(&format!("no render {id}")),
                "bob {args:?}: {}",
                stderr(&o)
            );
        }
        let o = as_user(WORKER, &["status"]);
        assert!(!o.status.success() && stderr(&o).contains("Worker role"), "{}", stderr(&o));
        let o = as_user("carol-token-0123456789", &["status"]);
        assert!(!o.status.success(), "an unknown token was let in");
        let o = as_user(ALICE, &["watch", &id]);
        assert!(o.status.success(), "{}", stderr(&o));
        // SIGHUP: carol is added without a restart.
        std::fs::write(&file, format!("{lines}carol submit {}\n", hash("carol-token-0123456789"))).unwrap();
        farm.coordinator.as_ref().unwrap().signal("-HUP");
        let start = Instant::now();
        while !as_user("carol-token-0123456789", &["status"]).status.success() {
            assert!(start.elapsed() < Duration::from_secs(10), "the token file was not reloaded\n{}", farm.logs());
            std::thread::sleep(Duration::from_millis(100));
        }
        assert!(farm.logs().contains("token file reloaded: 5 users"), "{}", farm.logs());
    }

    #[test]
    fn non_loopback_without_token_is_refused() {
        let o = Command::new(bin())
            .args(["coordinator", "--listen", "0.0.0.0:0", "--data-dir"])
            .arg(scratch("open"))
            .output()
            .unwrap();
        assert!(!o.status.success());
        assert!(stderr(&o).contains("without a token") && stderr(&o).contains("--insecure"), "{}", stderr(&o));
    }

    #[test]
    fn bad_requests_are_refused_and_the_farm_keeps_working() {
        let mut farm = Farm::new("hostile", 30, &[]);
        farm.add_worker(2);
        let url = farm.url();
        runtime().block_on(async {
            let mut c = RenderServiceClient::connect(url.clone()).await.unwrap();
            // Another protocol version.
            let e =
                c.list_renders(ListRendersRequest { protocol_version: 99, ..Default::default() }).await.unwrap_err();
            let ours = format!("version {PROTOCOL_VERSION}");
            assert!(e.message().contains(&ours) && e.message().contains("version 99"), "{}", e.message());
            // Bytes that are not a scene, and a truncated GLB.
            let glb = std::fs::read(
                Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/fixtures/scenes/Box/glTF-Binary/Box.glb"),
            )
            .unwrap();
            for bytes in [b"this is not a scene".to_vec(), glb[..glb.len() / 2].to_vec()] {
                let hash = blake3::hash(&bytes).to_hex().to_string();
                let chunk = SceneChunk {
                    protocol_version: PROTOCOL_VERSION,
                    hash,
                    total_bytes: bytes.len() as u64,
                    data: bytes,
                };
                let e = c.upload_scene(tokio_stream::iter(vec![chunk])).await.unwrap_err();
                assert!(e.message().contains("does not load"), "{}", e.message());
            }
            // A malformed hash, and a lying one.
            for (hash, says) in [("00".to_string(), "not a scene hash"), ("ab".repeat(32), "hash mismatch")] {
                let chunk = SceneChunk {
                    protocol_version: PROTOCOL_VERSION,
                    hash,
                    total_bytes: glb.len() as u64,
                    data: glb.clone(),
                };
                let e = c.upload_scene(tokio_stream::iter(vec![chunk])).await.unwrap_err();
                assert!(e.message().contains(says), "{}", e.message());
            }
            // Absurd settings for a real scene.
            let hash = blake3::hash(&glb).to_hex().to_string();
            let chunk = SceneChunk {
                protocol_version: PROTOCOL_VERSION,
                hash: hash.clone(),
                total_bytes: glb.len() as u64,
                data: glb.clone(),
            };
            c.upload_scene(tokio_stream::iter(vec![chunk])).await.unwrap();
            let settings = RenderSettings {
                width: 100_000,
                height: 100_000,
                estimator: Estimator::Mis as i32,
                density: Density::Brdf as i32,
                sampler: Sampler::Sobol as i32,
                termination: Some(render_settings::Termination::MaxBounces(4)),
                ..Default::default()
            };
            let mut req = SubmitRenderRequest {
                protocol_version: PROTOCOL_VERSION,
                scene_hash: hash,
                scene_name: "box".into(),
                settings: Some(settings.clone()),
                spp: 16,
                tile_size: 32,
                pass_spp: 16,
                ..Default::default()
            };
            let e = c.submit_render(req.clone()).await.unwrap_err();
            assert!(e.message().contains("100000x100000"), "{}", e.message());
            req.settings = Some(RenderSettings { width: 64, height: 64, ..settings });
            req.spp = 0;
            let e = c.submit_render(req.clone()).await.unwrap_err();
            assert!(e.message().contains("spp 0"), "{}", e.message());
            req.spp = 16;
            req.scene_hash = "cd".repeat(32);
            let e = c.submit_render(req.clone()).await.unwrap_err();
            assert!(e.message().contains("upload it first"), "{}", e.message());
            req.scene_hash = "unknown".into();
            let e = c.submit_render(req).await.unwrap_err();
            assert!(e.message().contains("not a scene hash"), "{}", e.message());
        });
        // Random bytes at the gRPC port.
        let mut s = std::net::TcpStream::connect(("127.0.0.1", farm.port)).unwrap();
        let noise: Vec<u8> = (0..4096u32).map(|i| (i.wrapping_mul(2_654_435_761) >> 9) as u8).collect();
        let _ = s.write_all(&noise);
        drop(s);
        // A .gltf whose buffer escapes its folder is refused by the client, naming the URI.
        let dir = farm.dir.join("evil");
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(dir.join("evil.gltf"), r#"{"asset":{"version":"2.0"},"buffers":[{"uri":"../../etc/passwd","byteLength":4}],"scenes":[{"nodes":[]}]}"#).unwrap();
        let o = farm.submit(dir.join("evil.gltf").to_str().unwrap(), &[], &farm.dir.join("x.exr"));
        assert!(!o.status.success() && stderr(&o).contains("../../etc/passwd"), "{}", stderr(&o));
        // Absurd parameters stop at the CLI.
        let o = farm.submit("builtin:cornell-box", &["--spp", "0"], &farm.dir.join("x.exr"));
        assert!(!o.status.success() && stderr(&o).contains("--spp"), "{}", stderr(&o));
        assert!(farm.logs().contains("refused: the scene does not load"), "refusals are logged");
        // And the farm still renders.
        let out = farm.dir.join("after.exr");
        let o = farm.submit("builtin:cornell-box", &["--width", "16", "--height", "16", "--spp", "4"], &out);
        assert!(o.status.success(), "{}\n{}", stderr(&o), farm.logs());
        assert!(out.is_file());
    }
}
