//! End-to-end tests of the farm's doors and what stands at them: metrics and JSON logs, TLS with
//! a private CA, connection limits and timers, workers and clients at the wrong door, and hostile
//! input. A real coordinator, workers and the CLI as separate processes on loopback.

use std::path::Path;
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

use crate::common;
use common::farm::{Farm, bin, http_get, run_within, scratch};
use common::{Proc, port_in_log};

#[test]
fn metrics_and_json_logs() {
    let mut farm = Farm::new("metrics", 30, &[("TESSERA_METRICS", "127.0.0.1:0"), ("TESSERA_LOG_FORMAT", "json")]);
    let metrics_port = farm.metrics.unwrap();
    assert!(http_get(metrics_port, "/healthz").starts_with("HTTP/1.1 200"));
    assert!(http_get(metrics_port, "/readyz").starts_with("HTTP/1.1 200"));
    farm.add_worker_with(2, &[("TESSERA_METRICS", "127.0.0.1:0")]);
    let worker_port = port_in_log(&mut farm.workers[0].0, &farm.dir.join("worker0.log"), "health and metrics on");
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
    // A coordinator built without denoising refuses `--denoise` at submit, saying how to build one.
    if !cfg!(feature = "denoise") {
        let o = farm.submit("builtin:cornell-box", &["--width", "16", "--height", "16", "--denoise"], &out);
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(
            !o.status.success() && err.contains("this farm cannot denoise") && err.contains("tessera-cli/denoise"),
            "{err}"
        );
    }
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
    let (c, k) = (cert_path.to_str().unwrap(), key_path.to_str().unwrap());
    let extra = [("TESSERA_TLS_CERT", c), ("TESSERA_TLS_KEY", k), ("TESSERA_METRICS", "127.0.0.1:0")];
    let farm = Farm::new("wrong-door", 30, &extra);
    let metrics = format!("127.0.0.1:{}", farm.metrics.unwrap());
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

/// The client at the wrong door says what to do: a URL without its scheme is refused at once,
/// the dashboard's port is named. A render with no worker connected says so instead of an ETA,
/// and `watch` without a terminal prints a line as it goes and one at the end.
#[test]
fn the_client_says_what_to_do_at_the_wrong_door_and_without_workers() {
    let mut farm = Farm::new("client-doors", 30, &[("TESSERA_HTTP", "127.0.0.1:0")]);
    let http = format!("127.0.0.1:{}", farm.http.unwrap());
    let err = |o: &Output| String::from_utf8_lossy(&o.stderr).into_owned();
    let started = Instant::now();
    let bare = format!("127.0.0.1:{}", farm.port);
    let o = Command::new(bin()).args(["status", "--coordinator", &bare]).output().unwrap();
    assert!(!o.status.success() && err(&o).contains(&format!("write http://{bare}")), "{}", err(&o));
    assert!(started.elapsed() < Duration::from_secs(5), "refused at once, not after waiting");
    let o = Command::new(bin()).args(["status", "--coordinator", &format!("http://{http}")]).output().unwrap();
    assert!(!o.status.success() && err(&o).contains("dashboard"), "{}", err(&o));
    let args = ["--width", "16", "--height", "16", "--spp", "4", "--name", "probe, take 1"];
    let id = farm.submit_detached("builtin:cornell-box", &args);
    let o = farm.client(&["status", &id, "--json"]).output().unwrap();
    let rows: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(rows[0]["no_workers"], true, "{rows}");
    assert_eq!(rows[0]["name"], "probe, take 1", "{rows}");
    let o = farm.client(&["status"]).output().unwrap();
    assert!(String::from_utf8_lossy(&o.stdout).contains("probe, take 1 (builtin:cornell-box)"));
    let watch = farm.client(&["watch", &id]).stderr(Stdio::piped()).spawn().unwrap();
    std::thread::sleep(Duration::from_secs(1));
    farm.add_worker(1);
    let o = watch.wait_with_output().unwrap();
    let said = err(&o);
    assert!(o.status.success(), "{said}");
    assert!(said.contains("no workers connected"), "{said}");
    assert!(said.lines().last().is_some_and(|l| l.contains("done, 100%")), "{said}");
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
        // What `printf '%s' "$TOKEN" | b3sum` writes when $TOKEN is unset.
        let empty_hash = dir.join("tokens");
        std::fs::write(&empty_hash, format!("eve admin {}\n", blake3::hash(b"").to_hex())).unwrap();
        let empty_hash = empty_hash.to_str().unwrap();
        type Case<'a> = (&'a [&'a str], &'a [(&'a str, &'a str)], &'a str);
        let cases: [Case; 8] = [
            (&["coordinator", "--data-dir", data, "--tokens", empty_hash], &[], "hash of the empty token"),
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
        let others = [
            vec!["cancel", id.as_str()],
            vec!["watch", id.as_str()],
            vec!["status", id.as_str()],
            vec!["pause", id.as_str()],
            vec!["resume", id.as_str()],
            vec!["priority", id.as_str(), "5"],
            vec!["log", id.as_str()],
        ];
        for args in others {
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
        // Bob follows a long render of his.
        let long = ["submit", "builtin:cornell-box", "--detach", "--width", "64", "--height", "64", "--spp", "65536"];
        let o = as_user(BOB, &long);
        assert!(o.status.success(), "{}", stderr(&o));
        let bobs = String::from_utf8_lossy(&o.stdout).trim().to_string();
        let mut watching = farm.client(&["watch", &bobs]);
        watching
            .env("TESSERA_TOKEN", BOB)
            .env("TESSERA_WAIT_FOR_COORDINATOR", "0")
            .stdout(Stdio::null())
            .stderr(Stdio::piped());
        let mut watching = Proc(watching.spawn().unwrap());
        std::thread::sleep(Duration::from_millis(1500));
        assert!(watching.0.try_wait().unwrap().is_none(), "bob's watch is under way");
        // SIGHUP: carol is added and bob removed without a restart.
        let without_bob: String = lines.lines().filter(|l| !l.starts_with("bob ")).map(|l| format!("{l}\n")).collect();
        std::fs::write(&file, format!("{without_bob}carol submit {}\n", hash("carol-token-0123456789"))).unwrap();
        farm.coordinator.as_ref().unwrap().signal("-HUP");
        let start = Instant::now();
        while !as_user("carol-token-0123456789", &["status"]).status.success() {
            assert!(start.elapsed() < Duration::from_secs(10), "the token file was not reloaded\n{}", farm.logs());
            std::thread::sleep(Duration::from_millis(100));
        }
        assert!(farm.logs().contains("token file reloaded: 4 users"), "{}", farm.logs());
        // Bob's open watch ends with him, not only his next call.
        let start = Instant::now();
        let ended = loop {
            if let Some(status) = watching.0.try_wait().unwrap() {
                break status;
            }
            assert!(start.elapsed() < Duration::from_secs(10), "bob's watch went on after he was removed");
            std::thread::sleep(Duration::from_millis(50));
        };
        let mut err = String::new();
        std::io::Read::read_to_string(watching.0.stderr.as_mut().unwrap(), &mut err).unwrap();
        assert!(!ended.success() && err.contains("no longer admits"), "{err}");
        assert!(!as_user(BOB, &["status"]).status.success(), "bob's token still works");
        assert!(as_user(ROOT, &["cancel", &bobs]).status.success());
    }

    /// SIGHUP's default action ends a process: a worker, or a coordinator without a token file
    /// (nothing to reload), logs it and goes on working.
    #[test]
    fn sighup_is_logged_and_ignored_where_there_is_nothing_to_reload() {
        let mut farm = Farm::new("hangup", 30, &[]);
        farm.add_worker(2);
        let start = Instant::now();
        while !farm.logs().contains("working for") {
            assert!(start.elapsed() < Duration::from_secs(20), "the worker did not start\n{}", farm.logs());
            std::thread::sleep(Duration::from_millis(50));
        }
        farm.coordinator.as_ref().unwrap().signal("-HUP");
        farm.workers[0].signal("-HUP");
        std::thread::sleep(Duration::from_millis(500));
        assert!(farm.coordinator.as_mut().unwrap().0.try_wait().unwrap().is_none(), "the coordinator died of SIGHUP");
        assert!(farm.workers[0].0.try_wait().unwrap().is_none(), "the worker died of SIGHUP");
        let out = farm.dir.join("after-hangup.exr");
        let o = farm.submit("builtin:cornell-box", &["--width", "16", "--height", "16", "--spp", "4"], &out);
        assert!(o.status.success(), "{}\n{}", stderr(&o), farm.logs());
        let logs = farm.logs();
        assert_eq!(logs.matches("SIGHUP ignored").count(), 2, "{logs}");
    }

    /// CPU seconds process `pid` has used (Linux).
    fn cpu_seconds(pid: u32) -> f64 {
        let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).unwrap();
        let fields: Vec<&str> = stat.rsplit_once(") ").unwrap().1.split_whitespace().collect();
        let ticks: f64 = fields[11].parse::<f64>().unwrap() + fields[12].parse::<f64>().unwrap();
        ticks / 100.0
    }

    /// Out of file handles (a coordinator under `ulimit -n 64`, and more connections waiting on
    /// its gRPC and probe doors than it can hold), the accept loops back off and say so instead
    /// of spinning a core (the probe measured 95-120 % CPU); once handles are free it answers.
    #[test]
    fn out_of_file_handles_the_doors_wait_and_say_so() {
        if !Path::new("/proc/self/stat").exists() {
            eprintln!("skipped: needs /proc");
            return;
        }
        let dir = scratch("nofile");
        let log_path = dir.join("coordinator.log");
        let log = std::fs::File::create(&log_path).unwrap();
        let script =
            "ulimit -n 64 && exec \"$0\" coordinator --listen 127.0.0.1:0 --metrics 127.0.0.1:0 --data-dir \"$1\"";
        let mut child =
            Command::new("sh").arg("-c").arg(script).arg(bin()).arg(dir.join("data")).stderr(log).spawn().unwrap();
        let metrics = port_in_log(&mut child, &log_path, "metrics on");
        let port = port_in_log(&mut child, &log_path, "coordinator listening on");
        let coordinator = Proc(child);
        let held: Vec<std::net::TcpStream> = (0..80)
            .map(|i| std::net::TcpStream::connect(("127.0.0.1", if i % 4 == 0 { metrics } else { port })).unwrap())
            .collect();
        std::thread::sleep(Duration::from_millis(1000));
        let pid = coordinator.0.id();
        let before = cpu_seconds(pid);
        std::thread::sleep(Duration::from_secs(3));
        let used = cpu_seconds(pid) - before;
        let logs = std::fs::read_to_string(dir.join("coordinator.log")).unwrap();
        assert!(used < 0.75, "the coordinator used {used:.2} CPU s in 3 s out of file handles\n{logs}");
        assert!(logs.contains("could not accept") && logs.contains("out of file handles"), "{logs}");
        drop(held);
        let start = Instant::now();
        loop {
            let o = Command::new(bin())
                .args(["status", "--coordinator", &format!("http://127.0.0.1:{port}")])
                .env("TESSERA_WAIT_FOR_COORDINATOR", "0")
                .output()
                .unwrap();
            if o.status.success() {
                break;
            }
            assert!(
                start.elapsed() < Duration::from_secs(30),
                "no answer after the handles were freed: {}",
                stderr(&o)
            );
            std::thread::sleep(Duration::from_millis(200));
        }
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
                Path::new(env!("CARGO_MANIFEST_DIR")).join("../scene/tests/fixtures/scenes/Box/glTF-Binary/Box.glb"),
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
