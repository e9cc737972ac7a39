//! The dashboard's API and doors, driven in process.

use super::*;
use crate::core::tests::{SCENE, request};
use crate::http::session::{COOKIE, hex};
use crate::model::{Offer, RenderState};
use crate::users::{Users, token_hash};
use crate::{CoreConfig, Engine};
use axum::body::Body;
use axum::http::Request;
use tower::ServiceExt;

pub(crate) const ALICE: &str = "alice-token-0123456789abcdef";
const BOB: &str = "bob-token-0123456789abcdef00";

/// A dashboard over a core with per-user tokens and one render each of alice's and bob's.
pub(crate) async fn two_users() -> (Arc<Dashboard>, i64, i64, tempfile::TempDir) {
    let dir = tempfile::Builder::new().prefix("tessera-dashboard-").tempdir().unwrap();
    let hash = blake3::hash(SCENE).to_hex().to_string();
    let engine = Engine::open(CoreConfig::new(dir.path().to_path_buf())).unwrap();
    let user = |name: &str| Identity { name: name.into(), role: Role::Submit };
    for name in ["alice", "bob"] {
        engine.put_scene(name, hash.clone(), SCENE.to_vec()).await.unwrap();
    }
    let alices = engine.submit(&user("alice"), request(&hash)).await.unwrap().id();
    let bobs = engine.submit(&user("bob"), request(&hash)).await.unwrap().id();
    let users = Users::parse(&format!("alice submit {}\nbob submit {}\n", token_hash(ALICE), token_hash(BOB))).unwrap();
    let tokens = Tokens { clients: None, workers: None, users: Some(Arc::new(std::sync::RwLock::new(users))) };
    (Dashboard::new(engine, tokens, false), alices, bobs, dir)
}

async fn call(d: &Arc<Dashboard>, method: &str, path: &str, headers: &[(&str, &str)]) -> (StatusCode, String) {
    let mut request = Request::builder().method(method).uri(path);
    for (k, v) in headers {
        request = request.header(*k, *v);
    }
    let response = d.router().oneshot(request.body(Body::empty()).unwrap()).await.unwrap();
    let status = response.status();
    let body = axum::body::to_bytes(response.into_body(), 1 << 24).await.unwrap();
    (status, String::from_utf8_lossy(&body).into_owned())
}

/// A sequence's page lists its frames (a page at a time), each with its state; its owner
/// (and no one else) may retry its cancelled frames from the page, keeping what they merged.
#[tokio::test]
async fn a_sequences_page_lists_its_frames_and_retries_them() {
    let (d, _, _, _dir) = two_users().await;
    let alice = Identity { name: "alice".into(), role: Role::Submit };
    let mut req = request(&blake3::hash(SCENE).to_hex());
    req.frames = Some(crate::model::Frames { list: tessera_render::plan::FrameList::parse("1-3").unwrap(), fps: 24.0 });
    req.setup.pose = Some(crate::model::Pose::default());
    let seq = d.engine.submit(&alice, req).await.unwrap().to_string();
    let (bearer, csrf) = (format!("Bearer {ALICE}"), d.sessions.csrf(ALICE));
    let as_alice = [("authorization", bearer.as_str()), ("x-tessera-csrf", csrf.as_str())];
    let page = |body: String| serde_json::from_str::<Value>(&body).unwrap();
    let (status, body) = call(&d, "GET", &format!("/api/renders/{seq}?from=1"), &as_alice).await;
    assert_eq!(status, StatusCode::OK, "{body}");
    let frames = page(body);
    assert_eq!((frames["frames_total"].as_u64(), frames["from"].as_u64()), (Some(3), Some(1)));
    let numbers: Vec<u64> = frames["frames"].as_array().unwrap().iter().map(|f| f["frame"].as_u64().unwrap()).collect();
    assert_eq!(numbers, [2, 3]);
    let bob = format!("Bearer {BOB}");
    let as_bob = [("authorization", bob.as_str())];
    assert_eq!(call(&d, "GET", &format!("/api/renders/{seq}"), &as_bob).await.0, StatusCode::NOT_FOUND);
    assert_eq!(call(&d, "POST", &format!("/api/renders/{seq}/cancel"), &as_alice).await.0, StatusCode::OK);
    assert_eq!(call(&d, "POST", &format!("/api/renders/{seq}/retry"), &as_bob).await.0, StatusCode::FORBIDDEN);
    let (status, body) = call(&d, "POST", &format!("/api/renders/{seq}/retry"), &as_alice).await;
    assert_eq!((status, body), (StatusCode::OK, format!("{{\"retried\":\"{seq}\"}}")));
    let frames = page(call(&d, "GET", &format!("/api/renders/{seq}"), &as_alice).await.1);
    let states: Vec<&str> = frames["frames"].as_array().unwrap().iter().map(|f| f["state"].as_str().unwrap()).collect();
    assert_eq!(states, ["running"; 3], "retried: {frames}");
}

/// With per-user tokens, a submitter sees and cancels only their own renders through the
/// dashboard, as through the CLI: another user's render is answered as missing.
#[tokio::test]
async fn a_submitter_sees_and_cancels_only_their_own_renders() {
    let (d, alices, bobs, _dir) = two_users().await;
    let alice = format!("Bearer {ALICE}");
    let as_alice = [("authorization", alice.as_str())];
    let (status, list) = call(&d, "GET", "/api/renders", &as_alice).await;
    assert_eq!(status, StatusCode::OK);
    assert!(list.contains(&format!("\"id\":\"{alices}\"")) && !list.contains(&format!("\"id\":\"{bobs}\"")), "{list}");
    assert_eq!(call(&d, "GET", &format!("/api/renders/{bobs}"), &as_alice).await.0, StatusCode::NOT_FOUND);
    assert_eq!(call(&d, "GET", &format!("/api/renders/{bobs}/preview.jpg"), &as_alice).await.0, StatusCode::NOT_FOUND);
    let csrf = d.sessions.csrf(ALICE);
    let acting = [("authorization", alice.as_str()), ("x-tessera-csrf", csrf.as_str())];
    assert_eq!(call(&d, "POST", &format!("/api/renders/{bobs}/cancel"), &acting).await.0, StatusCode::NOT_FOUND);
    let state = |id| d.engine.with(|c| Ok(c.status(id).unwrap().state)).unwrap();
    assert_eq!(state(bobs), RenderState::Running);
    assert_eq!(call(&d, "POST", &format!("/api/renders/{alices}/cancel"), &acting).await.0, StatusCode::OK);
    assert_eq!(state(alices), RenderState::Cancelled);
    // Bob's CSRF token is not alice's.
    let bob = format!("Bearer {BOB}");
    let crossed = [("authorization", bob.as_str()), ("x-tessera-csrf", csrf.as_str())];
    assert_eq!(call(&d, "POST", &format!("/api/renders/{bobs}/cancel"), &crossed).await.0, StatusCode::FORBIDDEN);
    assert_eq!(state(bobs), RenderState::Running);
}

/// Without a valid token: 401 from the API and the script, the login page at the root; the
/// shared-token-free coordinator with per-user tokens refuses an unknown one.
#[tokio::test]
async fn without_a_valid_token_there_is_only_the_login_page() {
    let (d, alices, _, _dir) = two_users().await;
    for path in ["/api/renders", "/api/workers", "/api/session", "/app.js", "/api/events"] {
        assert_eq!(call(&d, "GET", path, &[]).await.0, StatusCode::UNAUTHORIZED, "{path}");
    }
    let preview = format!("/api/renders/{alices}/preview.jpg");
    assert_eq!(
        call(&d, "GET", &preview, &[("authorization", "Bearer not-a-user-token-000000")]).await.0,
        StatusCode::UNAUTHORIZED
    );
    let (status, page) = call(&d, "GET", "/", &[]).await;
    assert_eq!(status, StatusCode::OK);
    assert!(page.contains("action=\"/login\"") && !page.contains("app.js"));
    let cookie = format!("{COOKIE}={}", hex(ALICE.as_bytes()));
    let (status, page) = call(&d, "GET", "/", &[("cookie", cookie.as_str())]).await;
    assert_eq!(status, StatusCode::OK);
    assert!(page.contains("app.js"), "logged in, the dashboard itself");
    let (status, preview) = call(&d, "GET", &preview, &[("cookie", cookie.as_str())]).await;
    assert_eq!(status, StatusCode::OK);
    assert!(preview.len() > 100, "a JPEG of the film so far");
}

/// A user removed from the token file (as SIGHUP reloads it) loses the event stream they had
/// open; another user's stream goes on.
#[tokio::test]
async fn a_removed_users_event_stream_ends() {
    let (d, _, _, _dir) = two_users().await;
    let open = |token: &str| {
        let request = Request::builder()
            .uri("/api/events")
            .header("authorization", format!("Bearer {token}"))
            .body(Body::empty())
            .unwrap();
        let router = d.router();
        async move { router.oneshot(request).await.unwrap() }
    };
    use tokio_stream::StreamExt;
    let (alices, bobs) = (open(ALICE).await, open(BOB).await);
    assert_eq!((alices.status(), bobs.status()), (StatusCode::OK, StatusCode::OK));
    let (mut alices, mut bobs) = (alices.into_body().into_data_stream(), bobs.into_body().into_data_stream());
    for stream in [&mut alices, &mut bobs] {
        let first = stream.next().await.unwrap().unwrap();
        assert!(String::from_utf8_lossy(&first).contains("event: state"), "the stream begins with the state");
    }
    let only_bob = Users::parse(&format!("bob submit {}\n", token_hash(BOB))).unwrap();
    *d.sessions.tokens.users.as_ref().unwrap().write().unwrap() = only_bob;
    let rest = tokio::time::timeout(Duration::from_secs(10), async {
        while let Some(chunk) = alices.next().await {
            chunk.unwrap();
        }
    });
    rest.await.expect("alice's stream ended");
    let bob_goes_on = tokio::time::timeout(Duration::from_secs(2), bobs.next());
    let next = bob_goes_on.await;
    assert!(!matches!(next, Ok(None)), "bob's stream ended: {next:?}");
    assert_eq!(
        call(&d, "GET", "/api/events", &[("authorization", &format!("Bearer {ALICE}"))]).await.0,
        StatusCode::UNAUTHORIZED
    );
}

/// DNS rebinding: a page on another site that points its name at a tokenless loopback
/// dashboard names that site in `Host`, and is refused before any route runs; IP addresses,
/// localhost and the configured names are answered. An `Origin` must match the dashboard's
/// own, scheme included.
#[tokio::test]
async fn only_the_dashboards_own_names_and_origin_are_answered() {
    let (d, alices, _, _dir) = two_users().await;
    let d = Dashboard::answering_to(d.engine.clone(), Tokens::default(), false, vec!["render.example.org".into()]);
    for host in ["evil.example:8080", "evil.example", "127.0.0.1.evil.example:8080", "localhost.evil.example"] {
        for path in ["/", "/api/renders", "/api/session", "/style.css"] {
            let (status, body) = call(&d, "GET", path, &[("host", host)]).await;
            assert_eq!(status, StatusCode::MISDIRECTED_REQUEST, "{host}{path}: {body}");
        }
    }
    for host in ["127.0.0.1:8080", "localhost:8080", "LOCALHOST", "[::1]:8080", "10.1.2.3", "render.example.org:443"] {
        assert_eq!(call(&d, "GET", "/api/renders", &[("host", host)]).await.0, StatusCode::OK, "{host}");
    }
    let csrf = d.sessions.csrf("");
    let cancel = format!("/api/renders/{alices}/cancel");
    for origin in ["https://localhost:8080", "http://evil.example", "null", "http://localhost:8081"] {
        let headers = [("host", "localhost:8080"), ("origin", origin), ("x-tessera-csrf", csrf.as_str())];
        assert_eq!(call(&d, "POST", &cancel, &headers).await.0, StatusCode::FORBIDDEN, "{origin}");
    }
    let headers = [("host", "localhost:8080"), ("origin", "http://localhost:8080"), ("x-tessera-csrf", csrf.as_str())];
    assert_eq!(call(&d, "POST", &cancel, &headers).await.0, StatusCode::OK);
}

/// A row changes only when its render does: a waiting render has not run (its elapsed time
/// is 0, queue time not counted), a running one's row carries when it started (the page
/// counts its elapsed time), an ended one's its elapsed time, frozen. Before, every row's
/// elapsed time changed each second, and each event stream was sent the whole list every
/// half second; a finished render's time and speed went on changing.
#[tokio::test]
async fn rows_change_only_when_their_render_does() {
    let (d, _, _, _dir) = two_users().await;
    let root = Identity::anyone();
    let rows = || d.render_rows(&root).unwrap().into_iter().map(|r| r.to_string()).collect::<Vec<_>>();
    let before = rows();
    assert!(
        before.iter().all(|r| r.contains("\"started_at\":null") && r.contains("\"elapsed_seconds\":0.0")),
        "{before:?}"
    );
    tokio::time::sleep(Duration::from_millis(600)).await;
    assert_eq!(rows(), before, "a waiting render's row changed by itself");
    let job = d.engine.lease(&Offer::plain("w"), None, Duration::ZERO).await.unwrap().expect("a job");
    let id = job.render_id;
    let row_of = |rows: &[String]| rows.iter().find(|r| r.contains(&format!("\"id\":\"{id}\""))).unwrap().clone();
    let running = rows();
    let row = row_of(&running);
    assert!(row.contains("\"started_at\":1") && row.contains("\"elapsed_seconds\":null"), "{row}");
    tokio::time::sleep(Duration::from_millis(1100)).await;
    assert_eq!(rows(), running, "a running render's row changed by itself");
    d.engine.cancel(Target::Render(id)).await.unwrap();
    let ended = rows();
    let row = row_of(&ended);
    assert!(row.contains("\"started_at\":null") && row.contains("\"elapsed_seconds\":1."), "{row}");
    tokio::time::sleep(Duration::from_millis(1100)).await;
    assert_eq!(rows(), ended, "an ended render's row changed by itself");
}

#[test]
fn an_event_after_the_first_carries_only_what_changed() {
    let row = |id: &str, state: &str| (id.to_string(), json!({"id": id, "state": state}).to_string());
    let mut had: HashMap<String, String> = [row("1", "done"), row("s2", "running")].into_iter().collect();
    let mut key = "w".to_string();
    let workers = json!([]);
    // Nothing changed: nothing is sent.
    let same = [row("s2", "running"), row("1", "done")];
    assert!(changes(&mut had, &mut key, &same, "w".into(), &workers).is_none());
    // One row changed, one is new, one is gone, the workers are the same: only those.
    let now = [row("7", "running"), row("s2", "done")];
    let event = changes(&mut had, &mut key, &now, "w".into(), &workers).expect("a change");
    let data = format!("{event:?}");
    assert!(data.contains("changes") && data.contains(r#"\"gone\":[\"1\"]"#), "{data}");
    assert!(data.contains(r#"\"id\":\"7\""#) && data.contains(r#"\"state\":\"done\""#), "{data}");
    assert!(!data.contains("workers"), "the workers did not change: {data}");
    assert_eq!(had.len(), 2);
    // Then the workers change alone.
    let event = changes(&mut had, &mut key, &now, "w2".into(), &workers).expect("a change");
    let data = format!("{event:?}");
    assert!(data.contains(r#"\"renders\":[]"#) && data.contains("workers"), "{data}");
}

/// The page pauses, resumes, reprioritises and quotes only what its caller owns, with the CSRF
/// token; the list shows the priority and the paused state; a bad priority is refused, saying
/// why.
#[tokio::test]
async fn a_submitter_pauses_resumes_and_reprioritises_only_their_own_renders() {
    let (d, alices, bobs, _dir) = two_users().await;
    let (bearer, csrf) = (format!("Bearer {ALICE}"), d.sessions.csrf(ALICE));
    let acting = [("authorization", bearer.as_str()), ("x-tessera-csrf", csrf.as_str())];
    let info = |id| d.engine.with(|c| Ok(c.status(id).unwrap())).unwrap();
    for action in ["pause", "resume", "priority?to=5", "quote"] {
        let (status, _) = call(&d, "POST", &format!("/api/renders/{bobs}/{action}"), &acting).await;
        assert_eq!(status, StatusCode::NOT_FOUND, "{action} on another user's render");
    }
    assert!(!info(bobs).paused && info(bobs).priority == 0, "bob's render untouched");
    let without_csrf = [("authorization", bearer.as_str())];
    for action in ["pause", "quote"] {
        let (status, _) = call(&d, "POST", &format!("/api/renders/{alices}/{action}"), &without_csrf).await;
        assert_eq!(status, StatusCode::FORBIDDEN, "{action} without the CSRF token");
    }
    assert_eq!(call(&d, "POST", &format!("/api/renders/{alices}/pause?now=1"), &acting).await.0, StatusCode::OK);
    assert!(info(alices).paused);
    let (status, body) = call(&d, "POST", &format!("/api/renders/{alices}/quote"), &acting).await;
    assert!(status == StatusCode::OK && body.contains("\"quoted\""), "{body}");
    let (status, body) = call(&d, "GET", "/api/renders", &acting).await;
    assert!(status == StatusCode::OK && body.contains("\"paused\":true"), "{body}");
    assert_eq!(call(&d, "POST", &format!("/api/renders/{alices}/resume"), &acting).await.0, StatusCode::OK);
    assert!(!info(alices).paused);
    assert_eq!(call(&d, "POST", &format!("/api/renders/{alices}/priority?to=-7"), &acting).await.0, StatusCode::OK);
    assert_eq!(info(alices).priority, -7);
    for bad in ["priority?to=1001", "priority?to=x", "priority", "pause?now=yes"] {
        let (status, body) = call(&d, "POST", &format!("/api/renders/{alices}/{bad}"), &acting).await;
        assert_eq!(status, StatusCode::BAD_REQUEST, "{bad}: {body}");
    }
    let (status, body) = call(&d, "GET", &format!("/api/renders/{alices}/log"), &acting).await;
    assert_eq!(status, StatusCode::OK, "{body}");
    let log: Vec<String> = serde_json::from_str::<Value>(&body).unwrap()["lines"]
        .as_array()
        .unwrap()
        .iter()
        .map(|l| l["line"].as_str().unwrap().to_string())
        .collect();
    assert_eq!(call(&d, "GET", &format!("/api/renders/{bobs}/log"), &acting).await.0, StatusCode::NOT_FOUND);
    assert!(log.iter().any(|l| l.contains("paused by alice")), "{log:?}");
    assert!(log.iter().any(|l| l.contains("quote asked by alice")), "{log:?}");
    assert!(log.iter().any(|l| l.contains("priority set to -7 by alice")), "{log:?}");
}

/// A stand-in denoiser whose images are black: a preview that shows it is told apart at once.
struct Blackout;

impl tessera_film::Denoiser for Blackout {
    fn name(&self) -> String {
        "blackout".into()
    }
    fn denoise(&self, _: u32, _: u32, c: &[[f32; 3]], _: &[[f32; 3]], _: &[[f32; 3]]) -> Result<Vec<[f32; 3]>, String> {
        Ok(vec![[0.0; 3]; c.len()])
    }
}

/// A denoised render's preview shows the denoised colour, as its PNG does, and `?raw=1` (the
/// page's Raw button) its raw colour, while it runs and once it is finished; a render that was
/// not denoised shows the same either way. Its settings list `denoise`, which is what the page
/// shows the button for.
#[tokio::test]
async fn a_denoised_renders_preview_shows_the_denoised_or_the_raw_colour() {
    use crate::core::tests::{furnace, hash, work};
    let dir = tempfile::Builder::new().prefix("tessera-dashboard-denoise-").tempdir().unwrap();
    let denoiser = Ok(crate::core::SharedDenoiser(Arc::new(Blackout)));
    let engine = Engine::open(CoreConfig { denoiser, ..CoreConfig::new(dir.path().to_path_buf()) }).unwrap();
    engine.put_scene("", hash(), SCENE.to_vec()).await.unwrap();
    let mut ids = Vec::new();
    for denoise in [true, true, false] {
        let mut req = request(&hash());
        (req.setup.settings.features, req.setup.settings.denoise) = (denoise, denoise);
        ids.push(engine.submit(&Identity::anyone(), req).await.unwrap().id());
    }
    let d = Dashboard::new(engine.clone(), Tokens::default(), false);
    let preview = async |id: i64, query: &str| {
        let (status, jpeg) = call(&d, "GET", &format!("/api/renders/{id}/preview.jpg{query}"), &[]).await;
        assert_eq!(status, StatusCode::OK);
        jpeg
    };
    let (running, denoised, plain) = (ids[0], ids[1], ids[2]);
    work(&engine, &furnace(), 3).await;
    assert_eq!(crate::core::tests::state(&engine, running), RenderState::Running);
    assert_ne!(preview(running, "").await, preview(running, "?raw=1").await, "a running render's film is not denoised");
    work(&engine, &furnace(), usize::MAX).await;
    assert_ne!(preview(denoised, "").await, preview(denoised, "?raw=1").await, "the toggle changed nothing");
    assert_eq!(
        preview(denoised, "?raw=1").await,
        preview(plain, "").await,
        "the raw colour is the undenoised render's"
    );
    assert_eq!(preview(plain, "").await, preview(plain, "?raw=1").await);
    let detail: Value =
        serde_json::from_str(&call(&d, "GET", &format!("/api/renders/{denoised}"), &[]).await.1).unwrap();
    assert!(detail["settings"].as_array().unwrap().iter().any(|kv| kv[0] == "denoise"), "{detail}");
}
