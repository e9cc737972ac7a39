//! Steering a farm's render from the command line: `tessera pause` stops new jobs (the workers
//! go idle), the pause outlives a coordinator restart, `tessera resume` finishes it to the same
//! file as `tessera render`, `tessera priority` changes what `status` reports, and
//! `tessera log` tells all of it after the restart.

use std::path::PathBuf;
use std::time::{Duration, Instant};

use crate::common;
use common::farm::{Farm, local_render};

/// (passes done, state, priority) of render `id`, from `status --json`.
fn progress(farm: &Farm, id: &str) -> (u64, String, i64) {
    let o = farm.client(&["status", id, "--json"]).output().unwrap();
    assert!(o.status.success(), "status failed: {}", String::from_utf8_lossy(&o.stderr));
    let rows: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let row = &rows[0];
    (
        row["passes_done"].as_u64().unwrap(),
        row["state"].as_str().unwrap().to_string(),
        row["priority"].as_i64().unwrap(),
    )
}

fn steer(farm: &Farm, args: &[&str]) {
    let o = farm.client(args).output().unwrap();
    assert!(o.status.success(), "{args:?} failed: {}\n{}", String::from_utf8_lossy(&o.stderr), farm.logs());
}

#[test]
fn a_paused_render_gets_no_jobs_outlives_a_restart_resumes_to_the_same_file_and_refines() {
    let mut farm = Farm::new("pause", 2, &[]);
    let args = ["--width", "64", "--height", "48", "--spp", "512", "--seed", "5"];
    let local: PathBuf = farm.dir.join("local.exr");
    local_render("builtin:cornell-box", &args, &local);
    farm.add_worker(1);
    let id = farm.submit_detached("builtin:cornell-box", &args);
    farm.wait_progress(&id, 0.05);
    steer(&farm, &["priority", &id, "-3"]);
    steer(&farm, &["pause", &id]);
    // Jobs in flight finish and merge within a lease; then nothing more is merged.
    std::thread::sleep(Duration::from_secs(3));
    let (paused_at, state, priority) = progress(&farm, &id);
    assert_eq!((state.as_str(), priority), ("paused", -3));
    std::thread::sleep(Duration::from_secs(10));
    assert_eq!(progress(&farm, &id).0, paused_at, "a pass merged while paused\n{}", farm.logs());
    let o = farm.client(&["workers", "--json"]).output().unwrap();
    let workers: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(workers[0]["state"], "idle", "{workers}");
    assert!(paused_at > 0, "the render had started");

    // The pause is stored: a restarted coordinator keeps it.
    farm.coordinator.take();
    farm.start_coordinator(2);
    let start = Instant::now();
    while start.elapsed() < Duration::from_secs(4) {
        let (done, state, priority) = progress(&farm, &id);
        assert_eq!((done, state.as_str(), priority), (paused_at, "paused", -3), "after a restart\n{}", farm.logs());
        std::thread::sleep(Duration::from_millis(500));
    }
    steer(&farm, &["resume", &id]);
    let out = farm.dir.join("farm.exr");
    farm.wait_and_fetch(&id, &out);
    assert!(std::fs::read(&out).unwrap() == std::fs::read(&local).unwrap(), "the images differ\n{}", farm.logs());
    let o = farm.client(&["pause", &id]).output().unwrap();
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && e.contains("is done"), "{e}");

    // What happened, in order and with times, survived the restart: `tessera log`, and
    // `--follow` of a finished render ends at once.
    let o = farm.client(&["log", &id, "--follow"]).output().unwrap();
    let text = String::from_utf8_lossy(&o.stdout).into_owned();
    let order = ["submitted by", "priority set to -3", "paused", "the coordinator restarted", "resumed", "finished"];
    let mut at = 0;
    for needle in order {
        let found =
            text[at..].find(needle).unwrap_or_else(|| panic!("no '{needle}' after byte {at} of the log:\n{text}"));
        at += found + needle.len();
    }
    assert!(text.lines().all(|l| l.get(..2) == Some("20")), "each line starts with its time:\n{text}");
    let o = farm.client(&["log", &id, "--json"]).output().unwrap();
    let first: serde_json::Value = serde_json::from_slice(o.stdout.split(|&b| b == b'\n').next().unwrap()).unwrap();
    assert!(first["at"].as_f64().unwrap() > 1.7e9 && first["line"].as_str().unwrap().starts_with("submitted"));

    // `tessera refine`: the finished render continued to twice the samples is the file of a
    // render of that many from the start; fewer samples are refused, saying why.
    let o = farm.client(&["refine", &id, "--spp", "256"]).output().unwrap();
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && e.contains("refining adds samples"), "{e}");
    let more = ["--width", "64", "--height", "48", "--spp", "1024", "--seed", "5"];
    let local_more = farm.dir.join("local-1024.exr");
    local_render("builtin:cornell-box", &more, &local_more);
    let o = farm.client(&["refine", &id, "--spp", "1024"]).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let refined = farm.dir.join("refined.exr");
    farm.wait_and_fetch(&id, &refined);
    let same = std::fs::read(&refined).unwrap() == std::fs::read(&local_more).unwrap();
    assert!(same, "the refined image differs from a direct render's\n{}", farm.logs());

    // `submit --quote` prices a render at the live worker's measured speed and submits nothing.
    let listed = |farm: &Farm| {
        let o = farm.client(&["status", "--json"]).output().unwrap();
        String::from_utf8_lossy(&o.stdout).matches("\"id\"").count()
    };
    let before = listed(&farm);
    let o =
        farm.client(&["submit", "builtin:cornell-box", "--quote", "--width", "64", "--height", "48"]).output().unwrap();
    let said = String::from_utf8_lossy(&o.stdout);
    assert!(
        o.status.success() && said.contains("on the farm: 1 live worker(s)") && said.contains("samples/s measured"),
        "{said}"
    );
    assert_eq!(listed(&farm), before, "a quote submitted something");
}

/// `worker --pool --tag` and `submit --pool --require`: a render of a pool is rendered only by
/// its pool's worker (the other worker returns no result of it), the workers list their pools
/// and tags (with the ones found at start), and a render no connected worker may take says so.
#[test]
fn a_render_of_a_pool_goes_to_its_workers_only_and_one_nobody_fits_says_so() {
    let mut farm = Farm::new("pools", 5, &[]);
    farm.add_worker_with(1, &[("TESSERA_POOL", "gpu"), ("TESSERA_TAG", "site=paris,tier=1")]);
    farm.add_worker(1);
    let args = ["--width", "32", "--height", "32", "--spp", "64", "--pool", "gpu", "--require", "site=paris"];
    let id = farm.submit_detached("builtin:cornell-box", &args);
    farm.wait_and_fetch(&id, &farm.dir.join("gpu.exr"));
    let o = farm.client(&["workers", "--json"]).output().unwrap();
    let workers: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let by_name = |name: &str| workers.as_array().unwrap().iter().find(|w| w["name"] == name).unwrap().clone();
    let (gpu, plain) = (by_name("w0"), by_name("w1"));
    assert_eq!(gpu["pool"], "gpu", "{workers}");
    let tags: Vec<&str> = gpu["tags"].as_array().unwrap().iter().map(|t| t.as_str().unwrap()).collect();
    assert!(tags.contains(&"site=paris") && tags.contains(&"tier=1") && tags.contains(&"cpus=1"), "{tags:?}");
    assert!(
        gpu["results"].as_u64().unwrap() > 0 && plain["results"] == 0,
        "only the pool's worker rendered it: {workers}"
    );

    let lyon = ["--width", "16", "--height", "16", "--spp", "4", "--require", "site=lyon"];
    let stuck = farm.submit_detached("builtin:cornell-box", &lyon);
    std::thread::sleep(Duration::from_secs(1));
    let o = farm.client(&["status", &stuck]).output().unwrap();
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(text.contains("no connected worker can take it: it needs site=lyon"), "{text}");
    let o = farm.client(&["submit", "builtin:cornell-box", "--detach", "--require", "mem>=lots"]).output().unwrap();
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && e.contains("is not an amount"), "{e}");
}

/// A test's webhook receiver: every request's event header, signature header and body, each
/// answered 200.
struct Receiver {
    port: u16,
    got: std::sync::Arc<std::sync::Mutex<Vec<(String, String, String)>>>,
}

impl Receiver {
    fn start() -> Self {
        use std::io::{BufRead, Read, Write};
        let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let port = listener.local_addr().unwrap().port();
        let got = std::sync::Arc::new(std::sync::Mutex::new(Vec::new()));
        let into = got.clone();
        std::thread::spawn(move || {
            for stream in listener.incoming().flatten() {
                let mut reader = std::io::BufReader::new(stream);
                let (mut event, mut signature, mut length) = (String::new(), String::new(), 0usize);
                loop {
                    let mut line = String::new();
                    if reader.read_line(&mut line).unwrap_or(0) == 0 || line == "\r\n" {
                        break;
                    }
                    let (name, value) = line.split_once(':').unwrap_or((&line, ""));
                    let value = value.trim().to_string();
                    match name.to_ascii_lowercase().as_str() {
                        "x-tessera-event" => event = value,
                        "x-tessera-signature" => signature = value,
                        "content-length" => length = value.parse().unwrap_or(0),
                        _ => {}
                    }
                }
                let mut body = vec![0; length];
                let _ = reader.read_exact(&mut body);
                into.lock().unwrap().push((event, signature, String::from_utf8_lossy(&body).into_owned()));
                let _ =
                    reader.get_mut().write_all(b"HTTP/1.1 200 OK\r\ncontent-length: 0\r\nconnection: close\r\n\r\n");
            }
        });
        Receiver { port, got }
    }

    fn url(&self) -> String {
        format!("http://127.0.0.1:{}/hook", self.port)
    }

    /// Waits until `n` events came (failing after 60 s), and a little longer for any extra one.
    fn events(&self, n: usize) -> Vec<(String, String, String)> {
        let start = Instant::now();
        while self.got.lock().unwrap().len() < n {
            assert!(
                start.elapsed() < Duration::from_secs(60),
                "{} of {n} notifications came",
                self.got.lock().unwrap().len()
            );
            std::thread::sleep(Duration::from_millis(100));
        }
        std::thread::sleep(Duration::from_secs(1));
        self.got.lock().unwrap().clone()
    }
}

/// `submit --notify URL`: one POST per render or whole sequence that ends, signed with the
/// coordinator's key (HMAC-SHA256 over the body); a receiver that is down does not hold up
/// the farm; URLs are checked at the door.
#[test]
fn notifications_are_posted_once_per_end_signed_and_never_hold_up_the_farm() {
    use hmac::Mac;
    const KEY: &str = "notify-key-0123456789";
    let receiver = Receiver::start();
    let mut farm = Farm::new("notify", 5, &[("TESSERA_NOTIFY_KEY", KEY)]);
    farm.add_worker(1);
    let small = ["--width", "16", "--height", "16", "--spp", "8"];
    // A receiver that is down: its render finishes as fast as any (the notifier retries it on
    // its own thread).
    let dead = format!("http://127.0.0.1:{}/hook", common::free_port());
    let started = Instant::now();
    let mut args = small.to_vec();
    args.extend(["--notify", dead.as_str()]);
    let first = farm.submit_detached("builtin:cornell-box", &args);
    farm.wait_and_fetch(&first, &farm.dir.join("dead.exr"));
    assert!(started.elapsed() < Duration::from_secs(60), "a dead receiver held the render up");

    let url = receiver.url();
    let mut args = small.to_vec();
    args.extend(["--notify", url.as_str()]);
    let still = farm.submit_detached("builtin:cornell-box", &args);
    farm.wait_and_fetch(&still, &farm.dir.join("still.exr"));
    let scene = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../scene/tests/fixtures/scenes/BoxAnimated/glTF-Binary/BoxAnimated.glb");
    args.extend(["--frames", "1-2"]);
    let seq = farm.submit_detached(scene.to_str().unwrap(), &args);
    let o = farm.client(&["watch", &seq]).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let long = ["--width", "64", "--height", "64", "--spp", "65536", "--notify", url.as_str()];
    let cancelled = farm.submit_detached("builtin:cornell-box", &long);
    let o = farm.client(&["cancel", &cancelled]).output().unwrap();
    assert!(o.status.success());

    let events = receiver.events(3);
    assert_eq!(events.len(), 3, "one per render or sequence that ended: {events:#?}");
    for (event, signature, body) in &events {
        let mut mac = hmac::Hmac::<sha2::Sha256>::new_from_slice(KEY.as_bytes()).unwrap();
        mac.update(body.as_bytes());
        let hex: String = mac.finalize().into_bytes().iter().map(|b| format!("{b:02x}")).collect();
        assert_eq!(signature, &format!("sha256={hex}"), "the signature of {body}");
        let json: serde_json::Value = serde_json::from_str(body).unwrap();
        assert_eq!(&json["event"], event.as_str());
    }
    let of = |id: &str| events.iter().find(|(_, _, b)| b.contains(&format!("\"id\":\"{id}\""))).cloned();
    assert_eq!(of(&still).map(|e| e.0), Some("done".to_string()));
    let sequence = of(&seq).expect("the sequence's event");
    assert!(sequence.0 == "done" && sequence.2.contains("\"total\":2"), "{sequence:?}");
    assert_eq!(of(&cancelled).map(|e| e.0), Some("cancelled".to_string()));

    let o = farm
        .client(&["submit", "builtin:cornell-box", "--detach", "--notify", "ftp://example.com/x"])
        .output()
        .unwrap();
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && e.contains("not an http:// or https:// URL"), "{e}");
}

/// `submit --frames 1-3 --preview-every 2 --preview-spp 4`: the previews of frames 1 and 3 are
/// downloaded as they come (NAME.preview.exr), then every frame, each the same pixels as the
/// frame of a sequence submitted without previews.
#[test]
fn preview_first_sequences_download_previews_and_the_same_frames() {
    let mut farm = Farm::new("previews", 5, &[]);
    farm.add_worker(1);
    let scene = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../scene/tests/fixtures/scenes/BoxAnimated/glTF-Binary/BoxAnimated.glb");
    let scene = scene.to_str().unwrap();
    let args = ["--width", "32", "--height", "32", "--spp", "32", "--frames", "1-3"];
    let previewed = farm.dir.join("p.####.exr");
    let mut with_previews = args.to_vec();
    with_previews.extend(["--preview-every", "2", "--preview-spp", "4"]);
    let o = farm.submit(scene, &with_previews, &previewed);
    let said = String::from_utf8_lossy(&o.stderr).into_owned();
    assert!(o.status.success(), "{said}\n{}", farm.logs());
    assert!(
        said.contains("preview 1: wrote") && said.contains("preview 3: wrote") && !said.contains("preview 2"),
        "{said}"
    );
    for f in [1, 3] {
        assert!(farm.dir.join(format!("p.{f:04}.preview.exr")).is_file(), "{said}");
    }
    let plain = farm.dir.join("q.####.exr");
    let o = farm.submit(scene, &args, &plain);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    for f in 1..=3 {
        common::assert_same_pixels(&farm.dir.join(format!("p.{f:04}.exr")), &farm.dir.join(format!("q.{f:04}.exr")));
    }
    let preview = tessera_film::read_exr(&farm.dir.join("p.0001.preview.exr")).unwrap();
    let full = tessera_film::read_exr(&farm.dir.join("p.0001.exr")).unwrap();
    assert!(
        preview.spp.iter().all(|&n| n == 16.0) && full.spp.iter().all(|&n| n == 32.0),
        "16 spp (one pass), then 32"
    );
}

/// A render submitted `--paused` takes no worker; `tessera quote` runs its pilot on the farm
/// (the first round of its tiles, though it stays paused) and says what the rest will take;
/// resumed, it finishes to the same file as `tessera render`, the pilot's passes its own.
#[test]
fn a_render_submitted_paused_is_quoted_on_the_farm_and_resumes_to_the_same_file() {
    let mut farm = Farm::new("quote", 2, &[]);
    let args = ["--width", "128", "--height", "96", "--spp", "256", "--target-error", "0.08", "--seed", "3"];
    let local: PathBuf = farm.dir.join("local.exr");
    local_render("builtin:cornell-box", &args, &local);
    farm.add_worker(1);
    let mut paused = vec!["--paused"];
    paused.extend(args);
    let id = farm.submit_detached("builtin:cornell-box", &paused);
    std::thread::sleep(Duration::from_secs(3));
    assert_eq!(progress(&farm, &id), (0, "paused".to_string(), 0), "it waits\n{}", farm.logs());

    let mut quote = farm.client(&["quote", &id, "--json"]);
    let o =
        common::farm::run_within(&mut quote, Duration::from_secs(120)).expect("the quote did not come within 120 s");
    assert!(o.status.success(), "quote failed: {}\n{}", String::from_utf8_lossy(&o.stderr), farm.logs());
    let q: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    // 128 x 96 in 32-pixel tiles: 12 tiles, all in the pilot; their first round is --min-spp's
    // default 32 spp, two passes of 16.
    assert_eq!((&q["tiles_judged"], &q["tiles"], &q["paused"]), (&12.into(), &12.into(), &true.into()), "{q}");
    let (samples, done) = (q["samples"].as_u64().unwrap(), q["samples_done"].as_u64().unwrap());
    assert_eq!(done, 128 * 96 * 32, "the pilot's first round: {q}");
    assert!(
        samples > done && q["samples_low"].as_u64() <= Some(samples) && q["samples_high"].as_u64() >= Some(samples)
    );
    assert_eq!(q["workers"], 1, "{q}");
    assert!(q["seconds_left"].as_f64().is_some_and(|s| s > 0.0), "the worker measured its speed: {q}");
    std::thread::sleep(Duration::from_secs(2));
    let (passes, state, _) = progress(&farm, &id);
    assert_eq!((passes, state.as_str()), (24, "paused"), "only the pilot rendered\n{}", farm.logs());

    // Asked again, the quote is there at once, in words.
    let o = farm.client(&["quote", &id]).output().unwrap();
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(text.starts_with(&format!("quote for render {id} (paused), from 12 of 12 tiles judged")), "{text}");
    assert!(text.contains("1 live worker(s)") && text.contains(&format!("`tessera resume {id}` starts it")), "{text}");

    steer(&farm, &["resume", &id]);
    let out = farm.dir.join("farm.exr");
    farm.wait_and_fetch(&id, &out);
    assert!(std::fs::read(&out).unwrap() == std::fs::read(&local).unwrap(), "the images differ\n{}", farm.logs());
    let o = farm.client(&["quote", &id]).output().unwrap();
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && e.contains("is done") && e.contains("only a queued or running render"), "{e}");
}
