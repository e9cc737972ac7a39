//! The farm the farm tests start: a coordinator and workers as processes on loopback, each in a
//! scratch directory, and the CLI that submits to them.

use super::{Proc, port_in_log};
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

pub fn bin() -> &'static str {
    env!("CARGO_BIN_EXE_tessera")
}

pub fn scratch(name: &str) -> super::Scratch {
    super::scratch("farm", name)
}

pub struct Farm {
    /// The coordinator's gRPC port: chosen by the system at the first start, kept at restarts.
    pub port: u16,
    /// The metrics and dashboard ports, when `extra` asks for them (`TESSERA_METRICS`,
    /// `TESSERA_HTTP`, best as `127.0.0.1:0`): read from the coordinator's log at every start.
    pub metrics: Option<u16>,
    pub http: Option<u16>,
    pub coordinator: Option<Proc>,
    pub workers: Vec<Proc>,
    pub extra: Vec<(String, String)>,
    /// Last, so that it is removed after the processes writing into it are gone.
    pub dir: super::Scratch,
}

impl Farm {
    pub fn new(name: &str, lease_seconds: u32, extra: &[(&str, &str)]) -> Self {
        let mut farm = Farm {
            port: 0,
            metrics: None,
            http: None,
            dir: scratch(name),
            coordinator: None,
            workers: Vec::new(),
            extra: extra.iter().map(|(k, v)| (k.to_string(), v.to_string())).collect(),
        };
        farm.start_coordinator(lease_seconds);
        farm
    }

    pub fn url(&self) -> String {
        if self.extra.iter().any(|(k, _)| k == "TESSERA_TLS_CERT") {
            format!("https://localhost:{}", self.port)
        } else {
            format!("http://127.0.0.1:{}", self.port)
        }
    }

    pub fn start_coordinator(&mut self, lease_seconds: u32) {
        let log_path = self.dir.join("coordinator.log");
        let log = std::fs::File::create(&log_path).unwrap();
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
        let mut child = cmd.spawn().unwrap();
        let asked = |var: &str| self.extra.iter().any(|(k, _)| k == var);
        let (metrics, http) = (asked("TESSERA_METRICS"), asked("TESSERA_HTTP"));
        self.metrics = metrics.then(|| port_in_log(&mut child, &log_path, "metrics on"));
        self.http = http.then(|| port_in_log(&mut child, &log_path, "dashboard on"));
        self.port = port_in_log(&mut child, &log_path, "coordinator listening on");
        self.coordinator = Some(Proc(child));
    }

    pub fn add_worker(&mut self, threads: u32) {
        self.add_worker_with(threads, &[]);
    }

    /// A worker with the farm's environment, less the coordinator's metrics address, plus `env`.
    pub fn add_worker_with(&mut self, threads: u32, env: &[(&str, &str)]) {
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

    pub fn client(&self, args: &[&str]) -> Command {
        let mut cmd = Command::new(bin());
        cmd.args(args).args(["--coordinator", &self.url()]);
        for (k, v) in &self.extra {
            cmd.env(k, v);
        }
        cmd
    }

    pub fn submit(&self, scene: &str, render_args: &[&str], out: &Path) -> Output {
        let mut args = vec!["submit", scene, "--out", out.to_str().unwrap()];
        args.extend(render_args);
        self.client(&args).output().unwrap()
    }

    pub fn submit_detached(&self, scene: &str, render_args: &[&str]) -> String {
        let mut args = vec!["submit", scene, "--detach"];
        args.extend(render_args);
        let o = self.client(&args).output().unwrap();
        assert!(o.status.success(), "submit failed: {}", String::from_utf8_lossy(&o.stderr));
        String::from_utf8(o.stdout).unwrap().trim().to_string()
    }

    pub fn wait_and_fetch(&self, id: &str, out: &Path) {
        // Bounded: a render that never finishes fails the test instead of hanging the suite.
        let o = run_within(&mut self.client(&["watch", id]), Duration::from_secs(300))
            .unwrap_or_else(|| panic!("render {id} did not finish within 300 s\n{}", self.logs()));
        assert!(o.status.success(), "watch failed: {}\n{}", String::from_utf8_lossy(&o.stderr), self.logs());
        let o = self.client(&["fetch", id, "--out", out.to_str().unwrap()]).output().unwrap();
        assert!(o.status.success(), "fetch failed: {}", String::from_utf8_lossy(&o.stderr));
    }

    /// Waits until at least `fraction` of the render's passes are merged (polling `status`).
    pub fn wait_progress(&self, id: &str, fraction: f64) {
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

    pub fn logs(&self) -> String {
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

pub fn local_render(scene: &str, render_args: &[&str], out: &Path) {
    let mut args = vec!["render", scene, "--out", out.to_str().unwrap(), "-q"];
    args.extend(render_args);
    let o = Command::new(bin()).args(&args).output().unwrap();
    assert!(o.status.success(), "local render failed: {}", String::from_utf8_lossy(&o.stderr));
}

pub const SMALL: &[&str] = &["--width", "64", "--height", "48", "--spp", "32", "--seed", "5"];

pub fn two_workers_mid_render(name: &str, lease_seconds: u32) -> (Farm, PathBuf, String) {
    two_workers_mid_render_with(name, lease_seconds, &[])
}

/// As [`two_workers_mid_render`], with `extra` in the farm's environment.
pub fn two_workers_mid_render_with(name: &str, lease_seconds: u32, extra: &[(&str, &str)]) -> (Farm, PathBuf, String) {
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
pub const LONG: &[&str] = &["--width", "96", "--height", "96", "--spp", "512", "--seed", "9"];

/// Runs `cmd`, killing it if it has not finished within `limit`; its output, or None if killed.
pub fn run_within(cmd: &mut Command, limit: Duration) -> Option<Output> {
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

/// One plain HTTP GET on loopback; the whole response, status line first.
pub fn http_get(port: u16, path: &str) -> String {
    use std::io::{Read, Write};
    let mut s = std::net::TcpStream::connect(("127.0.0.1", port)).unwrap();
    s.write_all(format!("GET {path} HTTP/1.1\r\nHost: x\r\n\r\n").as_bytes()).unwrap();
    let mut text = String::new();
    s.read_to_string(&mut text).unwrap();
    text
}

/// What a lying worker did: results it sent, and the refusal that stopped it (empty if it was
/// stopped first).
pub struct Lies {
    pub sent: u64,
    pub refusal: String,
}

/// A worker that speaks gRPC itself and returns plausible but wrong sums for every job: the
/// right tile, the right sample counts, every value in bounds (each sample 0.3 in every
/// channel). It works until the coordinator refuses it for good (it is blocked) or `stop` is
/// set, reconnecting across coordinator restarts; `sent` counts its results as it goes.
pub fn start_liar(
    url: String,
    sent: std::sync::Arc<std::sync::atomic::AtomicU64>,
    stop: std::sync::Arc<std::sync::atomic::AtomicBool>,
) -> std::thread::JoinHandle<Lies> {
    use std::sync::atomic::Ordering;
    use tessera_proto::v1::work_service_client::WorkServiceClient;
    use tessera_proto::v1::{CompleteRequest, LeaseRequest, TileSumsChunk};
    std::thread::spawn(move || {
        let runtime = tokio::runtime::Runtime::new().unwrap();
        runtime.block_on(async move {
            let version = tessera_proto::PROTOCOL_VERSION;
            while !stop.load(Ordering::Relaxed) {
                let Ok(mut client) = WorkServiceClient::connect(url.clone()).await else {
                    tokio::time::sleep(Duration::from_millis(100)).await;
                    continue;
                };
                let lease = LeaseRequest {
                    protocol_version: version,
                    worker_id: "liar-1".into(),
                    worker_name: "liar".into(),
                    threads: 1,
                    samples_per_second: 1e6,
                    wait_ms: 500,
                    ..LeaseRequest::default()
                };
                let job = match client.lease(lease).await {
                    Ok(r) => r.into_inner().job,
                    Err(s) if s.code() == tonic::Code::PermissionDenied => {
                        return Lies { sent: sent.load(Ordering::Relaxed), refusal: s.message().to_string() };
                    }
                    Err(_) => {
                        tokio::time::sleep(Duration::from_millis(100)).await;
                        continue;
                    }
                };
                let Some(job) = job else { continue };
                let t = job.tile.unwrap();
                let tile = tessera_render::Tile { x0: t.x0, y0: t.y0, width: t.width, height: t.height };
                let end = ((job.first_pass + job.pass_count) * job.pass_spp).min(job.spp);
                let samples = end.saturating_sub(job.first_pass * job.pass_spp) as u64;
                let mut sums = tessera_render::TileSums::new(tile);
                let v = (0.3 * tessera_render::FIXED_POINT_SCALE) as i128 * samples as i128;
                let v2 = (0.09 * tessera_render::FIXED_POINT_SCALE) as u128 * samples as u128;
                for p in &mut sums.pixels {
                    *p = tessera_render::PixelSums {
                        n: samples,
                        hits: samples,
                        sum: [v; 3],
                        sum_sq: [v2; 3],
                        ..Default::default()
                    };
                }
                let request = CompleteRequest {
                    protocol_version: version,
                    worker_id: "liar-1".into(),
                    lease_id: job.lease_id,
                    chunk: Some(TileSumsChunk { data: tessera_proto::sums::encode_tile_sums(&sums) }),
                    render_seconds: 0.01,
                };
                if client.complete(tokio_stream::iter([request])).await.is_ok() {
                    sent.fetch_add(1, Ordering::Relaxed);
                }
            }
            Lies { sent: sent.load(Ordering::Relaxed), refusal: String::new() }
        })
    })
}
