//! The web dashboard end to end: a real coordinator (`--http`) and worker, the CLI submitting,
//! and headless Chromium (the Debian package `chromium`, driven over the DevTools protocol)
//! logging in, watching the preview converge and cancelling the render.
//!
//! The browser test needs Chromium: it is found as `TESSERA_CHROMIUM`, `chromium`,
//! `chromium-browser` or `google-chrome`. Without one the test says so and passes, except
//! under CI (`CI` set), where it fails: `.ci/run` installs Chromium. With
//! `TESSERA_SCREENSHOTS=DIR` it saves the three pages there (as `docs/dashboard-*.png` are made).

use std::io::{Read, Write};
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use crate::common;
use common::{Proc, port_in_log};

const TOKEN: &str = "dashboard-test-token-0123456789";

fn bin() -> &'static str {
    env!("CARGO_BIN_EXE_tessera")
}

struct Farm {
    grpc: u16,
    http: u16,
    _procs: Vec<Proc>,
    dir: common::Scratch,
}

impl Farm {
    /// A coordinator with the dashboard and a token; `workers` one-thread workers.
    fn start(name: &str, workers: usize) -> Farm {
        let dir = common::scratch("dashboard", name);
        let log_path = dir.join("coordinator.log");
        let log = std::fs::File::create(&log_path).unwrap();
        let mut coordinator = Command::new(bin())
            .args(["coordinator", "--listen", "127.0.0.1:0", "--http", "127.0.0.1:0", "--lease-seconds", "3"])
            .arg("--data-dir")
            .arg(dir.join("data"))
            .env("TESSERA_TOKEN", TOKEN)
            .stdout(Stdio::null())
            .stderr(log)
            .spawn()
            .unwrap();
        let http = port_in_log(&mut coordinator, &log_path, "dashboard on");
        let grpc = port_in_log(&mut coordinator, &log_path, "coordinator listening on");
        let mut procs = vec![Proc(coordinator)];
        for i in 0..workers {
            let log = std::fs::File::create(dir.join(format!("worker{i}.log"))).unwrap();
            let worker = Command::new(bin())
                .args(["worker", "--coordinator", &format!("http://127.0.0.1:{grpc}"), "--threads", "1"])
                .args(["--name", &format!("test-worker-{i}")])
                .env("TESSERA_TOKEN", TOKEN)
                .stdout(Stdio::null())
                .stderr(log)
                .spawn()
                .unwrap();
            procs.push(Proc(worker));
        }
        Farm { grpc, http, _procs: procs, dir }
    }

    /// Submits `scene` with `args`, detached: its id.
    fn submit(&self, scene: &str, args: &[&str]) -> String {
        let out = Command::new(bin())
            .args(["submit", scene, "--detach"])
            .args(args)
            .args(["--coordinator", &format!("http://127.0.0.1:{}", self.grpc)])
            .env("TESSERA_TOKEN", TOKEN)
            .output()
            .unwrap();
        assert!(out.status.success(), "submit failed: {}", String::from_utf8_lossy(&out.stderr));
        String::from_utf8(out.stdout).unwrap().trim().to_string()
    }

    /// Submits a render that runs for minutes (it is cancelled): its id.
    fn submit_long_render(&self) -> String {
        let args = ["--width", "192", "--height", "128", "--spp", "65536", "--target-error", "0"];
        self.submit("builtin:cornell-box", &args)
    }

    /// Submits three 32 x 32 frames of an animated box: the sequence's id.
    fn submit_sequence(&self) -> String {
        let scene = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
            .join("../scene/tests/fixtures/scenes/BoxAnimated/glTF-Binary/BoxAnimated.glb");
        self.submit(scene.to_str().unwrap(), &["--width", "32", "--height", "32", "--spp", "8", "--frames", "1-3"])
    }

    /// The state `tessera status ID` reports (the second column of its row).
    fn state(&self, id: &str) -> String {
        let out = Command::new(bin())
            .args(["status", id, "--coordinator", &format!("http://127.0.0.1:{}", self.grpc)])
            .env("TESSERA_TOKEN", TOKEN)
            .output()
            .unwrap();
        assert!(out.status.success(), "status failed: {}", String::from_utf8_lossy(&out.stderr));
        let text = String::from_utf8_lossy(&out.stdout).into_owned();
        text.lines().nth(1).and_then(|l| l.split_whitespace().nth(1)).unwrap_or_default().to_string()
    }

    /// The priority `tessera status ID --json` reports.
    fn priority(&self, id: &str) -> i64 {
        let out = Command::new(bin())
            .args(["status", id, "--json", "--coordinator", &format!("http://127.0.0.1:{}", self.grpc)])
            .env("TESSERA_TOKEN", TOKEN)
            .output()
            .unwrap();
        let rows: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap_or_default();
        rows[0]["priority"].as_i64().unwrap_or(i64::MIN)
    }

    /// One HTTP/1.1 request to the dashboard: (status code, headers and body as text).
    fn http(&self, method: &str, path: &str, headers: &[(&str, &str)], body: &str) -> (u16, String) {
        let mut s = std::net::TcpStream::connect(("127.0.0.1", self.http)).unwrap();
        let mut request = format!("{method} {path} HTTP/1.1\r\nHost: 127.0.0.1:{}\r\nConnection: close\r\n", self.http);
        for (k, v) in headers {
            request += &format!("{k}: {v}\r\n");
        }
        request += &format!("Content-Length: {}\r\n\r\n{body}", body.len());
        s.write_all(request.as_bytes()).unwrap();
        let mut bytes = Vec::new();
        s.read_to_end(&mut bytes).unwrap();
        let text = String::from_utf8_lossy(&bytes).into_owned();
        let code = text.split(' ').nth(1).and_then(|c| c.parse().ok()).unwrap_or(0);
        (code, text)
    }
}

impl Farm {
    /// A GET's whole response, as bytes.
    fn http_bytes(&self, path: &str, headers: &[(&str, &str)]) -> Vec<u8> {
        let mut s = std::net::TcpStream::connect(("127.0.0.1", self.http)).unwrap();
        let mut request = format!("GET {path} HTTP/1.1\r\nHost: 127.0.0.1:{}\r\nConnection: close\r\n", self.http);
        for (k, v) in headers {
            request += &format!("{k}: {v}\r\n");
        }
        s.write_all((request + "\r\n").as_bytes()).unwrap();
        let mut bytes = Vec::new();
        s.read_to_end(&mut bytes).unwrap();
        bytes
    }
}

fn cookie() -> String {
    format!("tessera_token={}", TOKEN.bytes().map(|b| format!("{b:02x}")).collect::<String>())
}

/// Without a valid token the API answers 401 and the page is the login form; a wrong token
/// is refused at login; a state-changing request without the page's CSRF token (or from
/// another origin) is refused, and with it the render is cancelled.
#[test]
fn the_api_asks_for_the_token_and_the_csrf_guard() {
    let farm = Farm::start("api", 1);
    let id = farm.submit_long_render();
    assert_eq!(farm.http("GET", "/api/renders", &[], "").0, 401);
    let (code, page) = farm.http("GET", "/", &[], "");
    assert_eq!(code, 200);
    assert!(page.contains("name=\"token\"") && !page.contains("app.js"), "without a token, only the login page");
    assert_eq!(farm.http("GET", "/app.js", &[], "").0, 401);
    let wrong = [("Cookie", "tessera_token=77726f6e672d746f6b656e2d77726f6e672d746f6b656e")];
    assert_eq!(farm.http("GET", "/api/renders", &wrong, "").0, 401, "a wrong token in the cookie");
    let form = [("Content-Type", "application/x-www-form-urlencoded")];
    let (code, page) = farm.http("POST", "/login", &form, "token=not-the-token-at-all-000");
    assert_eq!(code, 401);
    assert!(page.contains("not accepted"));
    let (code, answer) = farm.http("POST", "/login", &form, &format!("token={TOKEN}"));
    assert_eq!(code, 303);
    assert!(answer.contains(&format!("{}; Path=/; HttpOnly; SameSite=Strict", cookie())), "{answer}");
    let cookie = cookie();
    let auth = [("Cookie", cookie.as_str())];
    let (code, renders) = farm.http("GET", "/api/renders", &auth, "");
    assert_eq!(code, 200);
    assert!(renders.contains(&format!("\"id\":\"{id}\"")), "{renders}");
    // The CSRF guard: a cancel with the cookie alone, or with a wrong token, is refused.
    let cancel = format!("/api/renders/{id}/cancel");
    assert_eq!(farm.http("POST", &cancel, &auth, "").0, 403);
    let bad = [("Cookie", cookie.as_str()), ("x-tessera-csrf", "0123")];
    assert_eq!(farm.http("POST", &cancel, &bad, "").0, 403);
    assert_eq!(farm.state(&id), "running");
    let (_, session) = farm.http("GET", "/api/session", &auth, "");
    let csrf = session.split("\"csrf\":\"").nth(1).and_then(|s| s.split('"').next()).unwrap().to_string();
    let foreign = [("Cookie", cookie.as_str()), ("x-tessera-csrf", csrf.as_str()), ("Origin", "http://evil.example")];
    assert_eq!(farm.http("POST", &cancel, &foreign, "").0, 403, "another origin");
    let good = [("Cookie", cookie.as_str()), ("x-tessera-csrf", csrf.as_str())];
    assert_eq!(farm.http("POST", &cancel, &good, "").0, 200);
    assert_eq!(farm.state(&id), "cancelled");
    // A Bearer token works as the CLI's does; a render that is not there is 404.
    let bearer = format!("Bearer {TOKEN}");
    assert_eq!(farm.http("GET", "/api/renders/999", &[("Authorization", bearer.as_str())], "").0, 404);

    // A finished render's EXR and PNG download from the page's links, with the token only.
    let out = Command::new(bin())
        .args(["submit", "builtin:cornell-box", "--width", "32", "--height", "24", "--spp", "4", "--quiet"])
        .args(["--coordinator", &format!("http://127.0.0.1:{}", farm.grpc)])
        .arg("--out")
        .arg(farm.dir.join("small.exr"))
        .env("TESSERA_TOKEN", TOKEN)
        .output()
        .unwrap();
    assert!(out.status.success(), "submit failed: {}", String::from_utf8_lossy(&out.stderr));
    let small = (id.parse::<u32>().unwrap() + 1).to_string();
    assert_eq!(farm.state(&small), "done");
    assert_eq!(farm.http("GET", &format!("/api/renders/{small}/image.exr"), &[], "").0, 401);
    let (code, exr) = farm.http("GET", &format!("/api/renders/{small}/image.exr"), &auth, "");
    assert_eq!(code, 200);
    assert!(exr.contains("Content-Type: image/x-exr") || exr.contains("content-type: image/x-exr"), "{}", &exr[..200]);
    let (code, png) = farm.http("GET", &format!("/api/renders/{small}/image.png"), &auth, "");
    assert_eq!(code, 200);
    assert!(png.contains("\u{FFFD}PNG") || png.contains("PNG\r\n"), "a PNG follows the headers");
    // The downloaded EXR is the one `tessera submit` wrote, byte for byte.
    let body = http_body(farm.http_bytes(&format!("/api/renders/{small}/image.exr"), &auth));
    assert_eq!(body, std::fs::read(farm.dir.join("small.exr")).unwrap());
}

/// The body of a raw HTTP/1.1 response.
fn http_body(response: Vec<u8>) -> Vec<u8> {
    let at = response.windows(4).position(|w| w == b"\r\n\r\n").expect("a header ends") + 4;
    response[at..].to_vec()
}

fn chromium() -> Option<PathBuf> {
    if let Some(p) = std::env::var_os("TESSERA_CHROMIUM") {
        return Some(PathBuf::from(p));
    }
    let path = std::env::var_os("PATH")?;
    ["chromium", "chromium-browser", "google-chrome"]
        .iter()
        .flat_map(|name| std::env::split_paths(&path).map(move |dir| dir.join(name)))
        .find(|p| p.is_file())
}

/// Polls `f` until it gives `Some`, for at most `secs` seconds.
fn eventually<T>(secs: u64, what: &str, mut f: impl FnMut() -> Option<T>) -> T {
    let start = Instant::now();
    loop {
        if let Some(v) = f() {
            return v;
        }
        assert!(start.elapsed() < Duration::from_secs(secs), "timed out waiting for {what}");
        std::thread::sleep(Duration::from_millis(200));
    }
}

#[test]
fn a_browser_logs_in_watches_the_preview_converge_and_cancels() {
    let Some(chromium) = chromium() else {
        assert!(
            std::env::var_os("CI").is_none(),
            "no Chromium found (TESSERA_CHROMIUM, chromium, chromium-browser, google-chrome): CI must install it (apt-get install -y chromium)"
        );
        eprintln!(
            "SKIPPED: no Chromium found; install it (apt-get install -y chromium) or set TESSERA_CHROMIUM to run this test"
        );
        return;
    };
    use headless_chrome::protocol::cdp::Page::CaptureScreenshotFormatOption;
    use headless_chrome::{Browser, LaunchOptions};
    let farm = Farm::start("browser", 1);
    let profile = farm.dir.join("chromium-profile");
    let options = LaunchOptions::default_builder()
        .path(Some(chromium))
        .headless(true)
        .sandbox(false)
        .window_size(Some((1400, 900)))
        .user_data_dir(Some(profile))
        .idle_browser_timeout(Duration::from_secs(120))
        .build()
        .unwrap();
    let browser = Browser::new(options).expect("Chromium starts");
    let tab = browser.new_tab().unwrap();
    tab.set_default_timeout(Duration::from_secs(30));
    let js = |expr: &str| tab.evaluate(expr, false).unwrap().value.unwrap_or(serde_json::Value::Null);
    let shots = std::env::var_os("TESSERA_SCREENSHOTS").map(PathBuf::from);
    let shoot = |name: &str| {
        if let Some(dir) = &shots {
            let png = tab.capture_screenshot(CaptureScreenshotFormatOption::Png, None, None, true).unwrap();
            std::fs::write(dir.join(format!("dashboard-{name}.png")), png).unwrap();
        }
    };
    let base = format!("http://127.0.0.1:{}/", farm.http);

    // Without a token: the login page. A wrong token is refused, the right one lets us in.
    tab.navigate_to(&base).unwrap().wait_until_navigated().unwrap();
    tab.wait_for_element("#token").unwrap().click().unwrap();
    tab.type_str("this-is-not-the-token-0000").unwrap();
    tab.wait_for_element("#login").unwrap().click().unwrap();
    tab.wait_until_navigated().unwrap();
    eventually(20, "the refusal", || {
        (js("!!document.getElementById('refused') && !document.getElementById('refused').hidden") == true).then_some(())
    });
    tab.wait_for_element("#token").unwrap().click().unwrap();
    tab.type_str(TOKEN).unwrap();
    tab.wait_for_element("#login").unwrap().click().unwrap();
    tab.wait_until_navigated().unwrap();
    tab.wait_for_element("#live.on").expect("the dashboard's event stream is live after logging in");
    assert_eq!(js("document.cookie"), "", "the token's cookie is HttpOnly: scripts do not see it");

    // A render submitted by the CLI appears without reloading.
    let id = farm.submit_long_render();
    tab.wait_for_element_with_custom_timeout(&format!("#render-{id}"), Duration::from_secs(30))
        .expect("the submitted render appears in the list");
    eventually(60, "the render to be worked on", || {
        (js(&format!("document.querySelector('#render-{id}').dataset.state")) == "running").then_some(())
    });
    shoot("renders");

    // Its page: the preview image changes as passes merge.
    tab.navigate_to(&format!("{base}#/render/{id}")).unwrap();
    tab.wait_for_element("#preview").unwrap();
    // A checksum of the pixels the page shows, drawn through a canvas.
    let pixels = "(() => { const i = document.getElementById('preview'); if (!i.complete || !i.naturalWidth) return null; \
        const c = document.createElement('canvas'); c.width = i.naturalWidth; c.height = i.naturalHeight; \
        const x = c.getContext('2d'); x.drawImage(i, 0, 0); const d = x.getImageData(0, 0, c.width, c.height).data; \
        let h = 0; for (let k = 0; k < d.length; k++) h = (h * 31 + d[k]) >>> 0; \
        return i.dataset.version + ' ' + i.naturalWidth + 'x' + i.naturalHeight + ' ' + h; })()";
    let first = eventually(60, "a first preview", || js(pixels).as_str().map(str::to_string));
    assert!(first.contains(" 192x128 "), "the preview has the render's size: {first}");
    let second = eventually(90, "the preview to change as passes merge", || {
        js(pixels)
            .as_str()
            .filter(|now| {
                let (a, b) = (first.split(' ').collect::<Vec<_>>(), now.split(' ').collect::<Vec<_>>());
                a[0] != b[0] && a[2] != b[2]
            })
            .map(str::to_string)
    });
    eprintln!("preview went from {first} to {second}");
    // The preview sharpens as a whole: no tile gets a second pass before every tile has its
    // first (checked from the tiles the page's maps read, as passes merge).
    let order = format!(
        "(async () => {{ const t = (await (await fetch('/api/renders/{id}/tiles')).json()).tiles; \
         const passes = t.map((x) => x[6]); return [Math.min(...passes), Math.max(...passes)].join(' '); }})()"
    );
    for _ in 0..20 {
        let answer = tab.evaluate(&order, true).unwrap().value.unwrap_or_default();
        let (min, max) = answer.as_str().and_then(|a| a.split_once(' ')).expect("the tiles' passes");
        let (min, max): (u64, u64) = (min.parse().unwrap(), max.parse().unwrap());
        assert!(max <= 1 || min >= 1, "a tile got a second pass while another had none: {min} to {max}");
        std::thread::sleep(Duration::from_millis(100));
    }
    tab.wait_for_element("#map-error").unwrap().click().unwrap();
    tab.wait_for_element("#preview").unwrap();
    eventually(30, "the error map drawn over the preview", || {
        (js(
            "(() => { const c = document.getElementById('tiles'); return !!c && !!c.dataset.tiles && c.width > 0; })()",
        ) == true)
            .then_some(())
    });
    // The jobs map: tiles done, being rendered and waiting, and each job in flight with its
    // worker.
    tab.wait_for_element("#map-jobs").unwrap().click().unwrap();
    eventually(30, "the jobs in flight listed with their worker", || {
        let legend = js("document.getElementById('legend') ? document.getElementById('legend').textContent : ''");
        let legend = legend.as_str().unwrap_or_default();
        (legend.contains("being rendered") && legend.contains("test-worker-0")).then_some(())
    });
    tab.wait_for_element("#map-error").unwrap().click().unwrap();
    if shots.is_some() {
        // For the screenshot, an image with samples in every tile.
        eventually(180, "every tile to have samples", || {
            (js("(() => { const c = document.getElementById('tiles'); return !!c && !!c.dataset.tiles && JSON.parse(c.dataset.tiles).every((t) => t[4] > 0); })()") == true).then_some(())
        });
        std::thread::sleep(Duration::from_secs(2));
    }
    shoot("render");

    tab.navigate_to(&format!("{base}#/workers")).unwrap();
    tab.wait_for_element("#worker-0, #workers tr + tr").expect("the worker is listed");
    let workers = js("document.getElementById('workers').textContent").as_str().unwrap().to_string();
    assert!(workers.contains("test-worker-0") && workers.contains("busy"), "{workers}");
    shoot("workers");

    // A worker killed outright shows as lost once it misses its heartbeats (twice the lease, 6 s
    // here); one stopped with SIGTERM says goodbye and shows as stopped. Gone ones can be hidden.
    let extra = |name: &str| {
        let worker = Command::new(bin())
            .args(["worker", "--coordinator", &format!("http://127.0.0.1:{}", farm.grpc), "--threads", "1"])
            .args(["--name", name])
            .env("TESSERA_TOKEN", TOKEN)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        Proc(worker)
    };
    let (killed, stopped) = (extra("test-worker-killed"), extra("test-worker-stopped"));
    let state_of = |name: &str| {
        js(&format!(
            "(() => {{ const row = Array.from(document.querySelectorAll('#workers tr')).find((r) => r.cells[0] && r.cells[0].textContent === '{name}'); return row ? row.cells[1].textContent : ''; }})()"
        ))
        .as_str()
        .unwrap_or_default()
        .to_string()
    };
    eventually(30, "both new workers listed", || {
        (!state_of("test-worker-killed").is_empty() && !state_of("test-worker-stopped").is_empty()).then_some(())
    });
    assert!(Command::new("kill").args(["-KILL", &killed.0.id().to_string()]).status().unwrap().success());
    assert!(Command::new("kill").args(["-TERM", &stopped.0.id().to_string()]).status().unwrap().success());
    eventually(60, "the killed worker shown lost and the other stopped", || {
        (state_of("test-worker-killed") == "lost" && state_of("test-worker-stopped") == "stopped").then_some(())
    });
    shoot("workers-gone");
    js(
        "(() => { const s = document.getElementById('list-gone'); s.value = '10'; s.dispatchEvent(new Event('change')); return true; })()",
    );
    eventually(60, "gone workers hidden after 10 s, the others still listed", || {
        (state_of("test-worker-killed").is_empty()
            && state_of("test-worker-stopped").is_empty()
            && !state_of("test-worker-0").is_empty())
        .then_some(())
    });
    assert_eq!(js("document.getElementById('workers-hidden').textContent").as_str(), Some("2 hidden"));

    // Pause, resume and a new priority from the page: the coordinator (and `tessera status`)
    // says so.
    tab.navigate_to(&format!("{base}#/render/{id}")).unwrap();
    tab.wait_for_element("#pause").unwrap().click().unwrap();
    eventually(30, "the coordinator to pause the render", || (farm.state(&id) == "paused").then_some(()));
    tab.wait_for_element_with_custom_timeout("#resume", Duration::from_secs(30)).unwrap().click().unwrap();
    eventually(30, "the coordinator to resume the render", || (farm.state(&id) == "running").then_some(()));
    tab.wait_for_element_with_custom_timeout("#pause", Duration::from_secs(30)).expect("the page shows Pause again");
    js("document.getElementById('priority').value = '12'");
    tab.wait_for_element("#set-priority").unwrap().click().unwrap();
    eventually(30, "the priority to be set", || (farm.priority(&id) == 12).then_some(()));
    eventually(30, "the page's log to say who paused, resumed and set the priority", || {
        let log = js("document.getElementById('log') ? document.getElementById('log').textContent : ''");
        let log = log.as_str().unwrap_or_default();
        ["paused by admin", "resumed by admin", "priority set to 12 by admin"]
            .iter()
            .all(|s| log.contains(s))
            .then_some(())
    });

    // Its quote: a fixed render's samples are known (192 x 128 x 65536), the live workers'
    // measured speed gives the core-seconds and the time left.
    eventually(30, "the page to quote the render", || {
        let q =
            js("document.getElementById('status-quote') ? document.getElementById('status-quote').textContent : ''");
        let q = q.as_str().unwrap_or_default().to_string();
        (q.starts_with("about 1.61 G samples;") && q.contains("core-seconds") && q.contains("left on")).then_some(())
    });

    // Cancel from the page (a second click confirms); the coordinator has cancelled it.
    tab.wait_for_element("#cancel").unwrap().click().unwrap();
    tab.wait_for_element("#cancel").unwrap().click().unwrap();
    eventually(30, "the page to say the render is cancelled", || {
        (js("document.getElementById('cancel') ? document.getElementById('cancel').textContent : 'gone'")
            != "Really cancel?")
            .then_some(())
    });
    eventually(30, "the coordinator to cancel the render", || (farm.state(&id) == "cancelled").then_some(()));

    // A render submitted paused is quoted from the page: its pilot (all 12 tiles of 128 x 96)
    // renders on the farm while it stays paused, and the quote rests on every tile.
    let args = ["--paused", "--width", "128", "--height", "96", "--spp", "4096", "--target-error", "0.01"];
    let quoted = farm.submit("builtin:cornell-box", &args);
    tab.navigate_to(&format!("{base}#/render/{quoted}")).unwrap();
    tab.wait_for_element_with_custom_timeout("#quote", Duration::from_secs(30)).unwrap().click().unwrap();
    eventually(60, "the page to quote the paused render from its pilot", || {
        let q =
            js("document.getElementById('status-quote') ? document.getElementById('status-quote').textContent : ''");
        let q = q.as_str().unwrap_or_default().to_string();
        (q.starts_with("about ") && !q.contains("judged") && q.contains("left on")).then_some(q)
    });
    assert_eq!(farm.state(&quoted), "paused", "the pilot leaves it paused");

    // A sequence's page lists its frames as they finish, each with its downloads.
    let seq = farm.submit_sequence();
    tab.navigate_to(&format!("{base}#/render/{seq}")).unwrap();
    eventually(120, "every frame listed as done", || {
        let done = js("document.querySelectorAll('#frames tr[data-state=done]').length").as_u64();
        (done == Some(3)).then_some(())
    });
    let fetched = "(async () => { const a = document.querySelector('#frame-2 a.frame-exr');         const r = await fetch(a.href); const b = new Uint8Array(await r.arrayBuffer());         return r.status + ' ' + Array.from(b.slice(0, 4)).join(','); })()";
    let answer = tab.evaluate(fetched, true).unwrap().value.unwrap_or_default();
    assert_eq!(answer, "200 118,47,49,1", "frame 2's EXR downloads from its row (OpenEXR's magic number)");
    // A done frame names the workers that rendered it (from the results stored).
    let workers = js("document.querySelector('#frame-2').cells[4].textContent");
    assert!(workers.as_str().is_some_and(|w| w.contains("test-worker-0")), "{workers}");

    // Under the table, the chosen frame: the last one done until the user picks another, with
    // its preview (the frame's own 32 x 32 pixels), its settings and its log.
    let chosen = |frame: u64| {
        eventually(30, &format!("frame {frame}'s preview, settings and log under the table"), || {
            let shown = js(
                "(() => { const c = document.getElementById('frame-chosen'); const i = document.getElementById('frame-preview'); \
                 return c && i && i.complete ? [c.dataset.frame, i.naturalWidth, document.querySelectorAll('#frame-settings dt').length, \
                 document.getElementById('frame-log').textContent.length].join(' ') : ''; })()",
            );
            let parts: Vec<u64> =
                shown.as_str().unwrap_or_default().split(' ').filter_map(|p| p.parse().ok()).collect();
            (parts.len() == 4 && parts[0] == frame && parts[1] == 32 && parts[2] > 3 && parts[3] > 0).then_some(())
        })
    };
    chosen(3);
    js("document.querySelector('#frame-1 td.num').click()");
    chosen(1);
    assert_eq!(js("document.querySelector('#frames tr.chosen').id").as_str(), Some("frame-1"));
    shoot("sequence-frame");

    // The list filters by state: the cancelled render alone, then the done sequence alone.
    tab.navigate_to(&base).unwrap();
    tab.wait_for_element("#list-state").unwrap();
    let filter = |state: &str| {
        js(&format!(
            "(() => {{ const s = document.getElementById('list-state'); s.value = '{state}'; s.dispatchEvent(new Event('change')); return true; }})()"
        ))
    };
    filter("cancelled");
    eventually(30, "only the cancelled render listed", || {
        let ids = js("Array.from(document.querySelectorAll('#renders tr[id]')).map((r) => r.id).join(' ')");
        (ids.as_str() == Some(&format!("render-{id}"))).then_some(())
    });
    filter("done");
    eventually(30, "only the done sequence listed", || {
        let ids = js("Array.from(document.querySelectorAll('#renders tr[id]')).map((r) => r.id).join(' ')");
        (ids.as_str() == Some(&format!("render-{seq}"))).then_some(())
    });
    shoot("sequence");
}
