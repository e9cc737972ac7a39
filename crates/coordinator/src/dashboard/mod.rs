//! The web dashboard (`tessera coordinator --http ADDR`): the renders, one render's converging
//! preview with its maps of samples and error per tile, and the workers, served by the
//! coordinator's own process from the same core. The page (`page/`) is compiled into the
//! binary and has no build step; it reads the JSON API below and follows a stream of
//! server-sent events.
//!
//! Access is the CLI's: the same tokens, checked on every request (a login form puts the token
//! in a cookie that scripts cannot read, `Secure` over TLS); without one, only the login page.
//! Requests that change something must carry the session's CSRF token in a header (a form or
//! image on another site cannot set one), derived from the login token with a key this process
//! made at start, and an `Origin`, when sent, must be this host.
//!
//! Previews are taken under the core's lock by reading only the film pixels they show, and
//! encoded outside it, at most every [`PREVIEW_EVERY`] per render however many watch: every
//! watcher gets the last encoding until it is that old and the film has changed.

// Handlers' helpers fail with the response to send; boxing it would buy nothing per request.
#![allow(clippy::result_large_err)]

use crate::core::{PreviewOf, Target, TileView};
use crate::model::RenderInfo;
use crate::server::{Tokens, constant_time_eq};
use crate::service::Shared;
use crate::users::Identity;
use axum::extract::{Form, Path, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{Html, IntoResponse, Redirect, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use serde::Deserialize;
use serde_json::{Value, json};
use std::collections::HashMap;
use std::future::Future;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

const LOGIN: &str = include_str!("page/login.html");
const APP: &str = include_str!("page/index.html");
const SCRIPT: &str = include_str!("page/app.js");
const STYLE: &str = include_str!("page/style.css");

/// The cookie that carries the login token (hex-encoded).
const COOKIE: &str = "tessera_token";
/// The header state-changing requests carry the session's CSRF token in.
const CSRF_HEADER: &str = "x-tessera-csrf";
/// Longest side of a live preview, in pixels.
pub const PREVIEW_SIDE: u32 = 800;
/// The previews' JPEG quality.
const PREVIEW_QUALITY: u8 = 85;
/// A render's preview is encoded at most this often, however many watch it.
pub const PREVIEW_EVERY: Duration = Duration::from_millis(500);
/// How often the event stream looks for changes.
const EVENTS_EVERY: Duration = Duration::from_millis(500);
/// Renders the dashboard lists (newest first).
const LISTED: usize = 500;
/// Previews kept encoded.
const PREVIEWS_KEPT: usize = 64;

struct Encoded {
    version: u64,
    at: Instant,
    jpeg: bytes::Bytes,
}

/// The dashboard's state: the coordinator's, and what it keeps of its own.
pub struct Dashboard {
    shared: Arc<Shared>,
    tokens: Tokens,
    tls: bool,
    /// Keys the CSRF tokens; made at start, so a restart ends every page's session.
    secret: [u8; 32],
    previews: Mutex<HashMap<i64, Encoded>>,
    /// One preview is encoded at a time; others wait and take it.
    encoding: tokio::sync::Mutex<()>,
    /// The workers' listing, shared by every page and event stream for [`EVENTS_EVERY`]: a
    /// thousand workers are a thousand rows, however many people watch.
    workers: Mutex<Option<(Instant, Value)>>,
}

impl Dashboard {
    pub fn new(shared: Arc<Shared>, tokens: Tokens, tls: bool) -> Arc<Self> {
        Arc::new(Self {
            shared,
            tokens,
            tls,
            secret: process_secret(),
            previews: Mutex::default(),
            encoding: tokio::sync::Mutex::new(()),
            workers: Mutex::default(),
        })
    }

    /// The HTTP routes, for [`serve`] (and tests that call them directly).
    pub fn router(self: &Arc<Self>) -> Router {
        Router::new()
            .route("/", get(index))
            .route("/login", post(login))
            .route("/logout", post(logout))
            .route("/app.js", get(script))
            .route("/style.css", get(style))
            .route("/api/session", get(session))
            .route("/api/renders", get(renders))
            .route("/api/workers", get(workers))
            .route("/api/events", get(events))
            .route("/api/renders/{id}", get(render))
            .route("/api/renders/{id}/tiles", get(tiles))
            .route("/api/renders/{id}/preview.jpg", get(preview))
            .route("/api/renders/{id}/image.exr", get(image_exr))
            .route("/api/renders/{id}/image.png", get(image_png))
            .route("/api/renders/{id}/cancel", post(cancel))
            .with_state(self.clone())
    }

    /// The token a request presents: the login cookie, or an `Authorization: Bearer` header.
    fn presented(headers: &HeaderMap) -> Option<String> {
        if let Some(bearer) =
            headers.get(header::AUTHORIZATION).and_then(|v| v.to_str().ok()).and_then(|v| v.strip_prefix("Bearer "))
        {
            return Some(bearer.to_string());
        }
        let cookies = headers.get_all(header::COOKIE).iter().filter_map(|v| v.to_str().ok());
        cookies
            .flat_map(|line| line.split(';'))
            .filter_map(|c| c.trim().strip_prefix(COOKIE)?.strip_prefix('='))
            .find_map(unhex)
    }

    /// Who is asking, or the answer for someone who may not.
    fn who(&self, headers: &HeaderMap) -> Result<(Identity, String), Response> {
        let presented = Self::presented(headers);
        match self.tokens.client(presented.as_deref()) {
            Ok(identity) => Ok((identity, presented.unwrap_or_default())),
            Err(status) => Err((StatusCode::UNAUTHORIZED, Json(json!({"error": status.message()}))).into_response()),
        }
    }

    /// The CSRF token of a session logged in with `token`.
    fn csrf(&self, token: &str) -> String {
        blake3::keyed_hash(&self.secret, token.as_bytes()).to_hex().to_string()
    }

    /// Who is asking to change something: a valid token, this session's CSRF header, and no
    /// foreign `Origin`.
    fn who_may_act(&self, headers: &HeaderMap) -> Result<Identity, Response> {
        let (who, token) = self.who(headers)?;
        let sent = headers.get(CSRF_HEADER).and_then(|v| v.to_str().ok()).unwrap_or("");
        if !constant_time_eq(sent.as_bytes(), self.csrf(&token).as_bytes()) {
            return Err(refuse(StatusCode::FORBIDDEN, "this request lacks the page's CSRF token: reload the page"));
        }
        same_origin(headers)?;
        Ok(who)
    }

    /// A render `who` may see, or 404 as if it did not exist.
    fn visible(&self, who: &Identity, id: &str) -> Result<Target, Response> {
        let target =
            Target::parse(id).ok_or_else(|| refuse(StatusCode::NOT_FOUND, &format!("'{id}' is not a render id")))?;
        let owner = self.shared.with(|c| Ok(c.owner_of(target).map(str::to_string))).map_err(internal)?;
        match owner {
            Some(owner) if who.may_touch(&owner) => Ok(target),
            _ => Err(refuse(StatusCode::NOT_FOUND, &format!("no render {target}"))),
        }
    }

    /// The renders `who` sees, newest first, as the page shows them.
    fn render_rows(&self, who: &Identity) -> Result<Vec<Value>, Response> {
        let rows = self
            .shared
            .with(|c| {
                let (renders, _) = c.list_renders(0, LISTED, |o| who.may_touch(o));
                let workers = c.workers_by_render();
                Ok(renders
                    .into_iter()
                    .map(|info| {
                        let target = Target::parse(&info.render_id);
                        let elapsed = target.and_then(|t| c.elapsed(t));
                        let on = target.map_or(0, |t| {
                            c.members(t).iter().map(|id| workers.get(id).copied().unwrap_or(0)).sum::<usize>()
                        });
                        (info, elapsed, on)
                    })
                    .collect::<Vec<_>>())
            })
            .map_err(internal)?;
        let mut rows: Vec<Value> =
            rows.into_iter().map(|(info, elapsed, on)| render_json(&info, elapsed, on)).collect();
        rows.reverse();
        Ok(rows)
    }

    /// Render `id`'s preview JPEG: the cached one while it is fresh, else a new one.
    async fn preview_jpeg(&self, id: i64) -> Result<bytes::Bytes, Response> {
        let fresh = |previews: &HashMap<i64, Encoded>, version: Option<u64>| {
            previews
                .get(&id)
                .filter(|e| e.at.elapsed() < PREVIEW_EVERY || Some(e.version) == version)
                .map(|e| e.jpeg.clone())
        };
        if let Some(jpeg) = fresh(&self.previews.lock().unwrap_or_else(|e| e.into_inner()), None) {
            return Ok(jpeg);
        }
        let _turn = self.encoding.lock().await;
        if let Some(jpeg) = fresh(&self.previews.lock().unwrap_or_else(|e| e.into_inner()), None) {
            return Ok(jpeg);
        }
        let of = self.shared.with(|c| c.preview(id, PREVIEW_SIDE)).map_err(internal)?;
        let version = match &of {
            PreviewOf::Film { version, .. } => *version,
            PreviewOf::Image(_) => u64::MAX,
        };
        if let Some(jpeg) = fresh(&self.previews.lock().unwrap_or_else(|e| e.into_inner()), Some(version)) {
            return Ok(jpeg);
        }
        let jpeg = tokio::task::spawn_blocking(move || match of {
            PreviewOf::Film { preview, .. } => preview.jpeg(PREVIEW_QUALITY),
            PreviewOf::Image(path) => tessera_film::read_exr(&path)
                .map_err(|e| e.to_string())
                .and_then(|img| tessera_film::Preview::of_image(&img, PREVIEW_SIDE).jpeg(PREVIEW_QUALITY)),
        })
        .await
        .map_err(|_| refuse(StatusCode::INTERNAL_SERVER_ERROR, "encoding the preview panicked"))?
        .map_err(|e| refuse(StatusCode::INTERNAL_SERVER_ERROR, &format!("the preview could not be made: {e}")))?;
        let jpeg = bytes::Bytes::from(jpeg);
        let mut previews = self.previews.lock().unwrap_or_else(|e| e.into_inner());
        if previews.len() >= PREVIEWS_KEPT
            && !previews.contains_key(&id)
            && let Some(oldest) = previews.iter().min_by_key(|(_, e)| e.at).map(|(k, _)| *k)
        {
            previews.remove(&oldest);
        }
        previews.insert(id, Encoded { version, at: Instant::now(), jpeg: jpeg.clone() });
        Ok(jpeg)
    }
}

/// Most dashboard connections open at once; more are closed at once.
pub const MAX_CONNECTIONS: usize = 512;
/// How long a connection may take to send a request's headers (and a TLS handshake to finish):
/// one that sends nothing, or a byte at a time, is closed.
pub const HEADER_TIMEOUT: Duration = Duration::from_secs(10);

/// How long an open connection may pass without a byte either way (an event stream sends a
/// keep-alive every 15 s).
const IDLE: Duration = Duration::from_secs(60);

/// A connection closed when it is silent too long: no first byte within `first`, then no byte
/// read or written for `idle`. (hyper's header timeout starts only at a request's first byte.)
struct Idle<S> {
    inner: S,
    deadline: std::pin::Pin<Box<tokio::time::Sleep>>,
    idle: Duration,
}

impl<S> Idle<S> {
    fn new(inner: S, first: Duration, idle: Duration) -> Self {
        Self { inner, deadline: Box::pin(tokio::time::sleep(first)), idle }
    }

    fn heard(&mut self) {
        let next = tokio::time::Instant::now() + self.idle;
        self.deadline.as_mut().reset(next);
    }
}

impl<S: tokio::io::AsyncRead + Unpin> tokio::io::AsyncRead for Idle<S> {
    fn poll_read(
        mut self: std::pin::Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
        buf: &mut tokio::io::ReadBuf<'_>,
    ) -> std::task::Poll<std::io::Result<()>> {
        use std::task::Poll;
        let before = buf.filled().len();
        match std::pin::Pin::new(&mut self.inner).poll_read(cx, buf) {
            Poll::Ready(Ok(())) if buf.filled().len() > before => {
                self.heard();
                Poll::Ready(Ok(()))
            }
            Poll::Pending if self.deadline.as_mut().poll(cx).is_ready() => Poll::Ready(Err(std::io::Error::new(
                std::io::ErrorKind::TimedOut,
                "the connection was silent too long",
            ))),
            other => other,
        }
    }
}

impl<S: tokio::io::AsyncWrite + Unpin> tokio::io::AsyncWrite for Idle<S> {
    fn poll_write(
        mut self: std::pin::Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
        buf: &[u8],
    ) -> std::task::Poll<std::io::Result<usize>> {
        let written = std::pin::Pin::new(&mut self.inner).poll_write(cx, buf);
        if matches!(written, std::task::Poll::Ready(Ok(n)) if n > 0) {
            self.heard();
        }
        written
    }
    fn poll_flush(
        mut self: std::pin::Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
    ) -> std::task::Poll<std::io::Result<()>> {
        std::pin::Pin::new(&mut self.inner).poll_flush(cx)
    }
    fn poll_shutdown(
        mut self: std::pin::Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
    ) -> std::task::Poll<std::io::Result<()>> {
        std::pin::Pin::new(&mut self.inner).poll_shutdown(cx)
    }
}

/// Serves the dashboard on `listener` until `shutdown` resolves; over TLS with
/// `tls` = (certificate chain, key) in PEM. At most [`MAX_CONNECTIONS`] at once, each sending
/// its headers within [`HEADER_TIMEOUT`] and closed after a minute without a byte either way.
pub async fn serve(
    listener: tokio::net::TcpListener,
    dashboard: Arc<Dashboard>,
    tls: Option<(Vec<u8>, Vec<u8>)>,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> std::io::Result<()> {
    serve_limited(listener, dashboard, tls, MAX_CONNECTIONS, HEADER_TIMEOUT, shutdown).await
}

/// [`serve`] with its limits given.
pub async fn serve_limited(
    listener: tokio::net::TcpListener,
    dashboard: Arc<Dashboard>,
    tls: Option<(Vec<u8>, Vec<u8>)>,
    max_connections: usize,
    header_timeout: Duration,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> std::io::Result<()> {
    let app = dashboard.router();
    let acceptor = tls.map(|(cert, key)| tls_acceptor(&cert, &key)).transpose()?;
    let places = Arc::new(tokio::sync::Semaphore::new(max_connections.max(1)));
    let mut refused = 0u64;
    let mut shutdown = std::pin::pin!(shutdown);
    loop {
        let (stream, _) = tokio::select! {
            accepted = listener.accept() => match accepted {
                Ok(a) => a,
                Err(e) => {
                    tracing::warn!("the dashboard could not accept a connection: {e}");
                    tokio::time::sleep(Duration::from_millis(100)).await;
                    continue;
                }
            },
            _ = &mut shutdown => return Ok(()),
        };
        let Ok(place) = places.clone().try_acquire_owned() else {
            if refused.is_multiple_of(100) {
                tracing::warn!("the dashboard refused a connection: {max_connections} are open, the limit");
            }
            refused += 1;
            continue;
        };
        let (acceptor, app) = (acceptor.clone(), app.clone());
        tokio::spawn(async move {
            let _place = place;
            let service = hyper_util::service::TowerToHyperService::new(app);
            // HTTP/1.1 only: the TLS setup offers no h2, and browsers speak 1.1 over plain HTTP.
            let mut http =
                hyper_util::server::conn::auto::Builder::new(hyper_util::rt::TokioExecutor::new()).http1_only();
            http.http1().timer(hyper_util::rt::TokioTimer::new()).header_read_timeout(header_timeout);
            let stream = Idle::new(stream, header_timeout, IDLE);
            let _ = match acceptor {
                None => http.serve_connection_with_upgrades(hyper_util::rt::TokioIo::new(stream), service).await,
                Some(acceptor) => {
                    let Ok(Ok(stream)) = tokio::time::timeout(header_timeout, acceptor.accept(stream)).await else {
                        return;
                    };
                    http.serve_connection_with_upgrades(hyper_util::rt::TokioIo::new(stream), service).await
                }
            };
        });
    }
}

fn tls_acceptor(cert: &[u8], key: &[u8]) -> std::io::Result<tokio_rustls::TlsAcceptor> {
    use rustls_pki_types::pem::PemObject;
    use rustls_pki_types::{CertificateDer, PrivateKeyDer};
    let bad = |what: &str, e: &dyn std::fmt::Display| std::io::Error::other(format!("the dashboard's TLS {what}: {e}"));
    let chain =
        CertificateDer::pem_slice_iter(cert).collect::<Result<Vec<_>, _>>().map_err(|e| bad("certificate", &e))?;
    let key = PrivateKeyDer::from_pem_slice(key).map_err(|e| bad("key", &e))?;
    let config = tokio_rustls::rustls::ServerConfig::builder_with_provider(Arc::new(
        tokio_rustls::rustls::crypto::ring::default_provider(),
    ))
    .with_safe_default_protocol_versions()
    .map_err(|e| bad("setup", &e))?
    .with_no_client_auth()
    .with_single_cert(chain, key)
    .map_err(|e| bad("certificate and key", &e))?;
    Ok(tokio_rustls::TlsAcceptor::from(Arc::new(config)))
}

/// 32 bytes no one else knows: the kernel's randomness, or failing that the clock and process.
fn process_secret() -> [u8; 32] {
    use std::io::Read;
    let mut key = [0u8; 32];
    let read = std::fs::File::open("/dev/urandom").and_then(|mut f| f.read_exact(&mut key));
    if read.is_ok() {
        return key;
    }
    let seed = format!("{:?} {}", std::time::SystemTime::now(), std::process::id());
    *blake3::hash(seed.as_bytes()).as_bytes()
}

fn refuse(code: StatusCode, message: &str) -> Response {
    (code, Json(json!({ "error": message }))).into_response()
}

fn internal(status: tonic::Status) -> Response {
    let code = match status.code() {
        tonic::Code::NotFound => StatusCode::NOT_FOUND,
        tonic::Code::InvalidArgument | tonic::Code::FailedPrecondition => StatusCode::BAD_REQUEST,
        tonic::Code::PermissionDenied => StatusCode::FORBIDDEN,
        _ => StatusCode::INTERNAL_SERVER_ERROR,
    };
    refuse(code, status.message())
}

/// Refuses a request whose `Origin` names another site.
fn same_origin(headers: &HeaderMap) -> Result<(), Response> {
    let (Some(origin), Some(host)) = (
        headers.get(header::ORIGIN).and_then(|v| v.to_str().ok()),
        headers.get(header::HOST).and_then(|v| v.to_str().ok()),
    ) else {
        return Ok(());
    };
    let origin_host = origin.split_once("://").map_or("", |(_, h)| h);
    if origin_host != host {
        return Err(refuse(StatusCode::FORBIDDEN, &format!("a request from {origin} may not act on this dashboard")));
    }
    Ok(())
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

fn unhex(s: &str) -> Option<String> {
    if !s.len().is_multiple_of(2) || s.len() > 1024 {
        return None;
    }
    let bytes: Option<Vec<u8>> =
        (0..s.len()).step_by(2).map(|i| u8::from_str_radix(s.get(i..i + 2)?, 16).ok()).collect();
    String::from_utf8(bytes?).ok()
}

fn render_json(info: &RenderInfo, elapsed: Option<f64>, workers: usize) -> Value {
    json!({
        "id": info.render_id,
        "scene": info.scene_name,
        "state": info.state.name(),
        "owner": info.owner,
        "passes_done": info.passes_done,
        "passes_total": info.passes_total,
        "samples_done": info.samples_done,
        "mean_spp": info.mean_spp,
        "samples_per_second": info.samples_per_second,
        "error": info.error_estimate,
        "eta_seconds": info.eta_seconds,
        "elapsed_seconds": elapsed,
        "workers": workers,
        "message": info.message,
        "sequence": (info.frames_total > 0).then(|| json!({
            "frames_total": info.frames_total,
            "frames_done": info.frames_done,
            "frames_running": info.frames_running,
            "frames_queued": info.frames_queued,
            "frames_failed": info.frames_failed,
            "finished": info.finished.iter().map(|f| json!({"frame": f.frame, "id": f.render_id})).collect::<Vec<_>>(),
        })),
    })
}

fn page(body: &'static str) -> Response {
    let mut r = Html(body).into_response();
    let h = r.headers_mut();
    h.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-store"));
    h.insert(header::X_FRAME_OPTIONS, HeaderValue::from_static("DENY"));
    h.insert(
        header::CONTENT_SECURITY_POLICY,
        HeaderValue::from_static(
            "default-src 'self'; img-src 'self' blob: data:; style-src 'self'; frame-ancestors 'none'",
        ),
    );
    r
}

async fn index(State(d): State<Arc<Dashboard>>, headers: HeaderMap) -> Response {
    match d.who(&headers) {
        Ok(_) => page(APP),
        Err(_) => page(LOGIN),
    }
}

async fn script(State(d): State<Arc<Dashboard>>, headers: HeaderMap) -> Response {
    if let Err(r) = d.who(&headers) {
        return r;
    }
    ([(header::CONTENT_TYPE, "text/javascript; charset=utf-8")], SCRIPT).into_response()
}

async fn style() -> Response {
    ([(header::CONTENT_TYPE, "text/css; charset=utf-8")], STYLE).into_response()
}

#[derive(Deserialize)]
struct LoginForm {
    token: String,
}

async fn login(State(d): State<Arc<Dashboard>>, headers: HeaderMap, Form(form): Form<LoginForm>) -> Response {
    if let Err(r) = same_origin(&headers) {
        return r;
    }
    if form.token.is_empty() || d.tokens.client(Some(&form.token)).is_err() || !d.tokens.required() {
        tracing::warn!("the dashboard refused a login");
        let page = LOGIN.replace("<p id=\"refused\" hidden>", "<p id=\"refused\">");
        return (StatusCode::UNAUTHORIZED, Html(page)).into_response();
    }
    let secure = if d.tls { "; Secure" } else { "" };
    let cookie = format!("{COOKIE}={}; Path=/; HttpOnly; SameSite=Strict{secure}", hex(form.token.as_bytes()));
    let mut r = Redirect::to("/").into_response();
    *r.status_mut() = StatusCode::SEE_OTHER;
    r.headers_mut().insert(header::SET_COOKIE, HeaderValue::from_str(&cookie).expect("hex is a valid header"));
    r
}

async fn logout(State(d): State<Arc<Dashboard>>, headers: HeaderMap) -> Response {
    if let Err(r) = d.who_may_act(&headers) {
        return r;
    }
    let mut r = StatusCode::NO_CONTENT.into_response();
    r.headers_mut().insert(
        header::SET_COOKIE,
        HeaderValue::from_static("tessera_token=; Path=/; HttpOnly; SameSite=Strict; Max-Age=0"),
    );
    r
}

async fn session(State(d): State<Arc<Dashboard>>, headers: HeaderMap) -> Response {
    match d.who(&headers) {
        Ok((who, token)) => Json(json!({
            "user": who.name,
            "role": format!("{:?}", who.role).to_lowercase(),
            "csrf": d.csrf(&token),
            "login": d.tokens.required(),
        }))
        .into_response(),
        Err(r) => r,
    }
}

async fn renders(State(d): State<Arc<Dashboard>>, headers: HeaderMap) -> Response {
    let (who, _) = match d.who(&headers) {
        Ok(w) => w,
        Err(r) => return r,
    };
    match d.render_rows(&who) {
        Ok(rows) => Json(json!({ "renders": rows })).into_response(),
        Err(r) => r,
    }
}

fn workers_json(d: &Dashboard) -> Result<Value, Response> {
    let mut cached = d.workers.lock().unwrap_or_else(|e| e.into_inner());
    if let Some((at, workers)) = cached.as_ref()
        && at.elapsed() < EVENTS_EVERY
    {
        return Ok(workers.clone());
    }
    let (workers, _) = d.shared.with(|c| Ok(c.list_workers("", 10_000))).map_err(internal)?;
    let workers = json!(
        workers
            .iter()
            .map(|w| json!({
                "id": w.worker_id,
                "name": w.name,
                "host": w.host,
                "threads": w.threads,
                "samples_per_second": w.samples_per_second,
                "leases": w.leases,
                "renders": w.renders,
                "seconds_since_seen": w.seconds_since_seen,
                "results": w.results,
                "failures": w.failures,
            }))
            .collect::<Vec<_>>()
    );
    *cached = Some((Instant::now(), workers.clone()));
    Ok(workers)
}

async fn workers(State(d): State<Arc<Dashboard>>, headers: HeaderMap) -> Response {
    if let Err(r) = d.who(&headers) {
        return r;
    }
    match workers_json(&d) {
        Ok(w) => Json(json!({ "workers": w })).into_response(),
        Err(r) => r,
    }
}

async fn render(State(d): State<Arc<Dashboard>>, headers: HeaderMap, Path(id): Path<String>) -> Response {
    let result = (|| {
        let (who, _) = d.who(&headers)?;
        let target = d.visible(&who, &id)?;
        let Target::Render(id) = target else {
            // A sequence's page is its row: its frames are renders of their own.
            let rows = d.render_rows(&who)?;
            let row = rows.into_iter().find(|r| r["id"] == target.to_string()).unwrap_or(Value::Null);
            return Ok(Json(json!({ "info": row })).into_response());
        };
        let (detail, elapsed) = d.shared.with(|c| Ok((c.render_detail(id)?, c.elapsed(target)))).map_err(internal)?;
        let workers = detail.workers.len();
        Ok::<_, Response>(
            Json(json!({
                "info": render_json(&detail.info, elapsed, workers),
                "width": detail.width,
                "height": detail.height,
                "settings": detail.settings,
                "log": detail.log,
                "workers": detail.workers,
            }))
            .into_response(),
        )
    })();
    result.unwrap_or_else(|r| r)
}

async fn tiles(State(d): State<Arc<Dashboard>>, headers: HeaderMap, Path(id): Path<String>) -> Response {
    let result = (|| {
        let (who, _) = d.who(&headers)?;
        let Target::Render(id) = d.visible(&who, &id)? else {
            return Err(refuse(StatusCode::BAD_REQUEST, "a sequence has no tiles of its own: open one of its frames"));
        };
        let views: Vec<TileView> = d.shared.with(|c| c.tile_views(id)).map_err(internal)?;
        let tiles: Vec<[f64; 6]> = views
            .iter()
            .map(|v| {
                [
                    v.tile.x0 as f64,
                    v.tile.y0 as f64,
                    v.tile.width as f64,
                    v.tile.height as f64,
                    v.spp as f64,
                    v.error as f64,
                ]
            })
            .collect();
        Ok(Json(json!({ "tiles": tiles })).into_response())
    })();
    result.unwrap_or_else(|r| r)
}

async fn preview(State(d): State<Arc<Dashboard>>, headers: HeaderMap, Path(id): Path<String>) -> Response {
    let id = match d.who(&headers).and_then(|(who, _)| d.visible(&who, &id)) {
        Ok(Target::Render(id)) => id,
        Ok(_) => {
            return refuse(StatusCode::BAD_REQUEST, "a sequence has no preview of its own: open one of its frames");
        }
        Err(r) => return r,
    };
    match d.preview_jpeg(id).await {
        // The page asks for it by version, so a browser may keep what it has.
        Ok(jpeg) => ([(header::CONTENT_TYPE, "image/jpeg"), (header::CACHE_CONTROL, "private, max-age=60")], jpeg)
            .into_response(),
        Err(r) => r,
    }
}

/// A finished render's EXR bytes (read, or rebuilt from the stored results, as `tessera fetch`
/// does).
async fn finished_exr(d: &Dashboard, headers: &HeaderMap, id: &str) -> Result<(i64, Vec<u8>), Response> {
    let (who, _) = d.who(headers)?;
    let Target::Render(id) = d.visible(&who, id)? else {
        return Err(refuse(StatusCode::BAD_REQUEST, "a sequence's images are its frames': open one of them"));
    };
    let bytes = d.shared.image(id).await.map_err(internal)?;
    Ok((id, bytes))
}

fn download(bytes: Vec<u8>, kind: &'static str, name: String) -> Response {
    let disposition = format!("attachment; filename=\"{name}\"");
    (
        [
            (header::CONTENT_TYPE, HeaderValue::from_static(kind)),
            (header::CONTENT_DISPOSITION, HeaderValue::from_str(&disposition).expect("an ascii name")),
        ],
        bytes,
    )
        .into_response()
}

async fn image_exr(State(d): State<Arc<Dashboard>>, headers: HeaderMap, Path(id): Path<String>) -> Response {
    match finished_exr(&d, &headers, &id).await {
        Ok((id, bytes)) => download(bytes, "image/x-exr", format!("render-{id}.exr")),
        Err(r) => r,
    }
}

async fn image_png(State(d): State<Arc<Dashboard>>, headers: HeaderMap, Path(id): Path<String>) -> Response {
    let (id, bytes) = match finished_exr(&d, &headers, &id).await {
        Ok(found) => found,
        Err(r) => return r,
    };
    let png = tokio::task::spawn_blocking(move || {
        let image = tessera_film::read_exr_bytes(&bytes, &format!("render {id}'s image")).map_err(|e| e.to_string())?;
        tessera_film::encode_png(image.width, image.height, &image.rgb, image.alpha.as_deref())
    })
    .await;
    match png {
        Ok(Ok(png)) => download(png, "image/png", format!("render-{id}.png")),
        Ok(Err(e)) => refuse(StatusCode::INTERNAL_SERVER_ERROR, &format!("the PNG could not be made: {e}")),
        Err(_) => refuse(StatusCode::INTERNAL_SERVER_ERROR, "making the PNG panicked"),
    }
}

async fn cancel(State(d): State<Arc<Dashboard>>, headers: HeaderMap, Path(id): Path<String>) -> Response {
    let target = match d.who_may_act(&headers).and_then(|who| d.visible(&who, &id)) {
        Ok(t) => t,
        Err(r) => return r,
    };
    match d.shared.with_durable(|c| c.cancel_target(target)).await {
        Ok(()) => {
            tracing::info!(render = %target, "render {target} cancelled from the dashboard");
            Json(json!({ "cancelled": target.to_string() })).into_response()
        }
        Err(status) => internal(status),
    }
}

/// The event stream: the render list (and the workers) whenever it changes, looked at every
/// [`EVENTS_EVERY`].
async fn events(State(d): State<Arc<Dashboard>>, headers: HeaderMap) -> Response {
    let (who, _) = match d.who(&headers) {
        Ok(w) => w,
        Err(r) => return r,
    };
    let stream = async_stream(d, who);
    Sse::new(stream).keep_alive(KeepAlive::default()).into_response()
}

fn async_stream(
    d: Arc<Dashboard>,
    who: Identity,
) -> impl tokio_stream::Stream<Item = Result<Event, std::convert::Infallible>> {
    let (tx, rx) = tokio::sync::mpsc::channel(2);
    tokio::spawn(async move {
        let mut last = String::new();
        loop {
            let rows = d.render_rows(&who).ok();
            let workers = workers_json(&d).ok();
            let Some((rows, workers)) = rows.zip(workers) else { break };
            // Seconds since seen change all the time; the page counts them itself.
            let state = json!({ "renders": rows, "workers": workers }).to_string();
            let key = json!({ "renders": rows, "workers": workers.as_array().map(|w| w.iter().map(|w| (w["id"].clone(), w["leases"].clone(), w["results"].clone())).collect::<Vec<_>>()) }).to_string();
            if key != last {
                if tx.send(Ok(Event::default().event("state").data(state))).await.is_err() {
                    break;
                }
                last = key;
            }
            if tx.is_closed() {
                break;
            }
            tokio::time::sleep(EVENTS_EVERY).await;
        }
    });
    tokio_stream::wrappers::ReceiverStream::new(rx)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::tests::{SCENE, request};
    use crate::model::RenderState;
    use crate::users::{Users, token_hash};
    use crate::{Core, CoreConfig};
    use axum::body::Body;
    use axum::http::Request;
    use tower::ServiceExt;

    const ALICE: &str = "alice-token-0123456789abcdef";
    const BOB: &str = "bob-token-0123456789abcdef00";

    /// A dashboard over a core with per-user tokens and one render each of alice's and bob's.
    fn two_users() -> (Arc<Dashboard>, i64, i64, tempfile::TempDir) {
        let dir = tempfile::Builder::new().prefix("tessera-dashboard-").tempdir().unwrap();
        let hash = blake3::hash(SCENE).to_hex().to_string();
        let mut core = Core::open(CoreConfig::new(dir.path().to_path_buf())).unwrap();
        core.put_scene(&hash, SCENE).unwrap();
        let alices = core.submit("alice", &request(&hash), 100, 1).unwrap().id();
        let bobs = core.submit("bob", &request(&hash), 100, 1).unwrap().id();
        let users =
            Users::parse(&format!("alice submit {}\nbob submit {}\n", token_hash(ALICE), token_hash(BOB))).unwrap();
        let tokens = Tokens { clients: None, workers: None, users: Some(Arc::new(std::sync::RwLock::new(users))) };
        (Dashboard::new(Shared::new(core).unwrap(), tokens, false), alices, bobs, dir)
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

    /// With per-user tokens, a submitter sees and cancels only their own renders through the
    /// dashboard, as through the CLI: another user's render is answered as missing.
    #[tokio::test]
    async fn a_submitter_sees_and_cancels_only_their_own_renders() {
        let (d, alices, bobs, _dir) = two_users();
        let alice = format!("Bearer {ALICE}");
        let as_alice = [("authorization", alice.as_str())];
        let (status, list) = call(&d, "GET", "/api/renders", &as_alice).await;
        assert_eq!(status, StatusCode::OK);
        assert!(
            list.contains(&format!("\"id\":\"{alices}\"")) && !list.contains(&format!("\"id\":\"{bobs}\"")),
            "{list}"
        );
        assert_eq!(call(&d, "GET", &format!("/api/renders/{bobs}"), &as_alice).await.0, StatusCode::NOT_FOUND);
        assert_eq!(
            call(&d, "GET", &format!("/api/renders/{bobs}/preview.jpg"), &as_alice).await.0,
            StatusCode::NOT_FOUND
        );
        let csrf = d.csrf(ALICE);
        let acting = [("authorization", alice.as_str()), ("x-tessera-csrf", csrf.as_str())];
        assert_eq!(call(&d, "POST", &format!("/api/renders/{bobs}/cancel"), &acting).await.0, StatusCode::NOT_FOUND);
        let state = |id| d.shared.with(|c| Ok(c.status(id).unwrap().state)).unwrap();
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
        let (d, alices, _, _dir) = two_users();
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

    /// Over TLS (the coordinator's certificate and key), the dashboard speaks https, and the
    /// login cookie is marked Secure as well as HttpOnly.
    #[tokio::test]
    async fn over_tls_the_login_cookie_is_secure() {
        use tokio::io::{AsyncReadExt, AsyncWriteExt};
        use tokio_rustls::rustls;
        let key = rcgen::KeyPair::generate().unwrap();
        let cert = rcgen::CertificateParams::new(vec!["localhost".to_string()]).unwrap().self_signed(&key).unwrap();
        let (d, _, _, _dir) = two_users();
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let port = listener.local_addr().unwrap().port();
        let tls = Some((cert.pem().into_bytes(), key.serialize_pem().into_bytes()));
        let d = Dashboard::new(d.shared.clone(), d.tokens.clone(), true);
        tokio::spawn(serve(listener, d, tls, std::future::pending()));

        let mut roots = rustls::RootCertStore::empty();
        roots.add(cert.der().clone()).unwrap();
        let config = rustls::ClientConfig::builder_with_provider(Arc::new(rustls::crypto::ring::default_provider()))
            .with_safe_default_protocol_versions()
            .unwrap()
            .with_root_certificates(roots)
            .with_no_client_auth();
        let connector = tokio_rustls::TlsConnector::from(Arc::new(config));
        let tcp = tokio::net::TcpStream::connect(("127.0.0.1", port)).await.unwrap();
        let name = rustls_pki_types::ServerName::try_from("localhost").unwrap();
        let mut stream = connector.connect(name, tcp).await.expect("the dashboard speaks TLS");
        let body = format!("token={ALICE}");
        let request = format!(
            "POST /login HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\nContent-Type: application/x-www-form-urlencoded\r\nContent-Length: {}\r\n\r\n{body}",
            body.len()
        );
        stream.write_all(request.as_bytes()).await.unwrap();
        let mut answer = Vec::new();
        let _ = stream.read_to_end(&mut answer).await;
        let answer = String::from_utf8_lossy(&answer).to_lowercase();
        assert!(answer.starts_with("http/1.1 303"), "{answer}");
        assert!(answer.contains("; httponly; samesite=strict; secure"), "{answer}");
    }

    /// The dashboard's doors are bounded: a connection past the limit is closed at once, and one
    /// that sends no request within the header timeout is closed then.
    #[tokio::test]
    async fn connections_are_limited_and_silent_ones_closed() {
        use tokio::io::AsyncReadExt;
        let (d, _, _, _dir) = two_users();
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let port = listener.local_addr().unwrap().port();
        let timeout = Duration::from_millis(300);
        tokio::spawn(serve_limited(listener, d, None, 2, timeout, std::future::pending()));
        let closed_within = |mut s: tokio::net::TcpStream, limit: Duration| async move {
            let mut buf = [0u8; 16];
            matches!(tokio::time::timeout(limit, s.read(&mut buf)).await, Ok(Ok(0) | Err(_)))
        };
        let first = tokio::net::TcpStream::connect(("127.0.0.1", port)).await.unwrap();
        let second = tokio::net::TcpStream::connect(("127.0.0.1", port)).await.unwrap();
        tokio::time::sleep(Duration::from_millis(50)).await;
        let third = tokio::net::TcpStream::connect(("127.0.0.1", port)).await.unwrap();
        assert!(
            closed_within(third, Duration::from_millis(200)).await,
            "a connection past the limit is closed at once"
        );
        let started = Instant::now();
        assert!(closed_within(first, Duration::from_secs(5)).await, "a silent connection is closed");
        assert!(started.elapsed() >= Duration::from_millis(200), "not before its time");
        assert!(closed_within(second, Duration::from_secs(5)).await);
        // With the places free again, a request is answered.
        let mut s = tokio::net::TcpStream::connect(("127.0.0.1", port)).await.unwrap();
        tokio::io::AsyncWriteExt::write_all(
            &mut s,
            b"GET /api/renders HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n",
        )
        .await
        .unwrap();
        let mut answer = String::new();
        s.read_to_string(&mut answer).await.unwrap();
        assert!(answer.starts_with("HTTP/1.1 401"), "{answer}");
    }
}
