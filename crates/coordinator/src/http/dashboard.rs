//! The web dashboard (`tessera coordinator --http ADDR`): the renders, one render's converging
//! preview with its maps of samples and error per tile, and the workers, served by the
//! coordinator's own process from the same engine. The page (`page/`) is compiled into the
//! binary and has no build step; it reads the JSON API below and follows a stream of
//! server-sent events. Who may see and do what is `session.rs`'s.
//!
//! Previews are taken under the core's lock by reading only the film pixels they show, and
//! encoded outside it, at most every [`PREVIEW_EVERY`] per render however many watch: every
//! watcher gets the last encoding until it is that old and the film has changed.

// Handlers' helpers fail with the response to send; boxing it would buy nothing per request.
#![allow(clippy::result_large_err)]

use super::session::{self, Sessions};
use super::{engine_error, refuse};
use crate::core::{PreviewOf, Target, TileView};
use crate::engine::Engine;
use crate::grpc::server::{Standing, Tokens};
use crate::model::RenderInfo;
use crate::users::{Identity, Role};
use axum::extract::{Path, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use serde_json::{Value, json};
use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

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

/// The render list's rows, each as its id and its JSON text.
type Rows = Arc<Vec<(String, String)>>;

struct Encoded {
    version: u64,
    at: Instant,
    jpeg: bytes::Bytes,
}

/// The dashboard's state: the coordinator's, and what it keeps of its own.
pub struct Dashboard {
    pub(super) engine: Arc<Engine>,
    pub(super) sessions: Sessions,
    previews: Mutex<HashMap<i64, Encoded>>,
    /// One preview is encoded at a time; others wait and take it.
    encoding: tokio::sync::Mutex<()>,
    /// The workers' listing, shared by every page and event stream for [`EVENTS_EVERY`]: a
    /// thousand workers are a thousand rows, however many people watch.
    workers: Mutex<HashMap<Option<String>, (Instant, Value)>>,
    /// The render list's rows by who sees them (everyone's, or one user's), shared by the
    /// event streams (see [`Dashboard::shared_rows`]).
    rows: Mutex<HashMap<Option<String>, (Instant, Rows)>>,
}

impl Dashboard {
    pub fn new(engine: Arc<Engine>, tokens: Tokens, tls: bool) -> Arc<Self> {
        Self::answering_to(engine, tokens, tls, Vec::new())
    }

    /// A dashboard that also answers to the host names `hosts` (`--http-host`), besides IP
    /// addresses and `localhost`.
    pub fn answering_to(engine: Arc<Engine>, tokens: Tokens, tls: bool, hosts: Vec<String>) -> Arc<Self> {
        Arc::new(Self {
            engine,
            sessions: Sessions::new(tokens, tls, hosts),
            previews: Mutex::default(),
            encoding: tokio::sync::Mutex::new(()),
            workers: Mutex::default(),
            rows: Mutex::default(),
        })
    }

    /// The HTTP routes, for [`super::serve`] (and tests that call them directly).
    pub fn router(self: &Arc<Self>) -> Router {
        Router::new()
            .route("/", get(session::index))
            .route("/login", post(session::login))
            .route("/logout", post(session::logout))
            .route("/app.js", get(session::script))
            .route("/style.css", get(session::style))
            .route("/api/session", get(session::session))
            .route("/api/renders", get(renders))
            .route("/api/workers", get(workers))
            .route("/api/events", get(events))
            .route("/api/renders/{id}", get(render))
            .route("/api/renders/{id}/tiles", get(tiles))
            .route("/api/renders/{id}/preview.jpg", get(preview))
            .route("/api/renders/{id}/image.exr", get(image_exr))
            .route("/api/renders/{id}/image.png", get(image_png))
            .route("/api/renders/{id}/cancel", post(cancel))
            .route("/api/renders/{id}/retry", post(retry))
            .layer(axum::middleware::from_fn_with_state(self.clone(), door_checks))
            .with_state(self.clone())
    }

    /// A render `who` may see, or 404 as if it did not exist.
    fn visible(&self, who: &Identity, id: &str) -> Result<Target, Response> {
        let target =
            Target::parse(id).ok_or_else(|| refuse(StatusCode::NOT_FOUND, &format!("'{id}' is not a render id")))?;
        let owner = self.engine.with(|c| Ok(c.owner_of(target).map(str::to_string))).map_err(engine_error)?;
        match owner {
            Some(owner) if who.may_touch(&owner) => Ok(target),
            _ => Err(refuse(StatusCode::NOT_FOUND, &format!("no render {target}"))),
        }
    }

    /// The renders `who` sees, newest first, as the page shows them.
    fn render_rows(&self, who: &Identity) -> Result<Vec<Value>, Response> {
        let rows = self
            .engine
            .with(|c| {
                let (renders, _) = c.list_renders(0, LISTED, |o| who.may_touch(o));
                let workers = c.workers_by_row();
                Ok(renders
                    .into_iter()
                    .map(|info| {
                        let target = Target::parse(&info.render_id);
                        let time = target.map(|t| Timing::of(c, t)).unwrap_or_default();
                        let on = target.and_then(|t| workers.get(&t.id()).copied()).unwrap_or(0);
                        (info, time, on)
                    })
                    .collect::<Vec<_>>())
            })
            .map_err(engine_error)?;
        let mut rows: Vec<Value> = rows.into_iter().map(|(info, time, on)| render_json(&info, time, on)).collect();
        rows.reverse();
        Ok(rows)
    }

    /// The rows [`Dashboard::render_rows`] gives `who`, each with its id and as JSON text, made
    /// at most every [`EVENTS_EVERY`] for everyone who sees the same renders: a hundred event
    /// streams cost the state lock what one does.
    fn shared_rows(&self, who: &Identity) -> Result<Rows, Response> {
        let scope = scope(who);
        if let Some((at, rows)) = self.rows.lock().unwrap_or_else(|e| e.into_inner()).get(&scope)
            && at.elapsed() < EVENTS_EVERY
        {
            return Ok(rows.clone());
        }
        let rows: Vec<(String, String)> = self
            .render_rows(who)?
            .into_iter()
            .map(|row| (row["id"].as_str().unwrap_or_default().to_string(), row.to_string()))
            .collect();
        let rows = Arc::new(rows);
        let mut shared = self.rows.lock().unwrap_or_else(|e| e.into_inner());
        shared.retain(|_, (at, _)| at.elapsed() < 10 * EVENTS_EVERY);
        shared.insert(scope, (Instant::now(), rows.clone()));
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
        let of = self.engine.with(|c| c.preview(id, PREVIEW_SIDE)).map_err(engine_error)?;
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

/// A row's time: a running render's start (the page counts its elapsed time from it, so that the
/// row stays the same from one event to the next), or an ended one's elapsed time, frozen.
#[derive(Clone, Copy, Debug, Default)]
struct Timing {
    started_at: Option<f64>,
    elapsed: Option<f64>,
}

impl Timing {
    fn of(c: &crate::core::Core, target: Target) -> Self {
        match c.started_at(target) {
            Some(at) => Timing { started_at: Some(at), elapsed: None },
            None => Timing { started_at: None, elapsed: c.elapsed(target) },
        }
    }
}

fn render_json(info: &RenderInfo, time: Timing, workers: usize) -> Value {
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
        "no_workers": info.no_workers,
        "submitted_at": info.submitted_at,
        "name": info.name,
        "ended_at": info.ended_at,
        "elapsed_seconds": time.elapsed,
        "started_at": time.started_at,
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

async fn renders(State(d): State<Arc<Dashboard>>, headers: HeaderMap) -> Response {
    let (who, _) = match d.sessions.who(&headers) {
        Ok(w) => w,
        Err(r) => return r,
    };
    match d.render_rows(&who) {
        Ok(rows) => Json(json!({ "renders": rows })).into_response(),
        Err(r) => r,
    }
}

/// Who sees the same renders as `who`: everyone (`None`: an admin, or no per-user tokens) or
/// one submitter; what the shared rows and workers are cached by.
fn scope(who: &Identity) -> Option<String> {
    (who.role != Role::Admin).then(|| who.name.clone())
}

/// The workers as `who` sees them (the renders of their jobs only where `who` may see those),
/// made at most every [`EVENTS_EVERY`] for everyone who sees the same renders.
fn workers_json(d: &Dashboard, who: &Identity) -> Result<Value, Response> {
    let scope = scope(who);
    let mut cached = d.workers.lock().unwrap_or_else(|e| e.into_inner());
    if let Some((at, workers)) = cached.get(&scope)
        && at.elapsed() < EVENTS_EVERY
    {
        return Ok(workers.clone());
    }
    let (workers, _) = d.engine.with(|c| Ok(c.list_workers_for(who, "", 10_000))).map_err(engine_error)?;
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
                "state": w.state.name(),
                "blocked_from": w.blocked_from,
            }))
            .collect::<Vec<_>>()
    );
    cached.retain(|_, (at, _)| at.elapsed() < 10 * EVENTS_EVERY);
    cached.insert(scope, (Instant::now(), workers.clone()));
    Ok(workers)
}

async fn workers(State(d): State<Arc<Dashboard>>, headers: HeaderMap) -> Response {
    let who = match d.sessions.who(&headers) {
        Ok((who, _)) => who,
        Err(r) => return r,
    };
    match workers_json(&d, &who) {
        Ok(w) => Json(json!({ "workers": w })).into_response(),
        Err(r) => r,
    }
}

/// Frames a sequence's page lists at once (`?from=` pages on).
const FRAMES_A_PAGE: usize = 200;

async fn render(
    State(d): State<Arc<Dashboard>>,
    headers: HeaderMap,
    Path(id): Path<String>,
    axum::extract::Query(page): axum::extract::Query<HashMap<String, String>>,
) -> Response {
    let result = (|| {
        let (who, _) = d.sessions.who(&headers)?;
        let target = d.visible(&who, &id)?;
        let Target::Render(id) = target else {
            // A sequence's page is its row and a page of its frames, each a render of its own.
            let rows = d.render_rows(&who)?;
            let row = rows.into_iter().find(|r| r["id"] == target.to_string()).unwrap_or(Value::Null);
            let from: usize = page.get("from").and_then(|f| f.parse().ok()).unwrap_or(0);
            let (frames, total) = d
                .engine
                .with(|c| {
                    let (frames, total) = c.sequence_frames(target.id(), from, FRAMES_A_PAGE).unwrap_or_default();
                    let rows: Vec<Value> = frames
                        .iter()
                        .map(|(info, workers)| {
                            let t = Target::Render(info.render_id.parse().unwrap_or(0));
                            let mut row = render_json(info, Timing::of(c, t), workers.len());
                            row["frame"] = json!(info.frame);
                            row["worker_names"] = json!(workers);
                            row
                        })
                        .collect();
                    Ok((rows, total))
                })
                .map_err(engine_error)?;
            return Ok(
                Json(json!({ "info": row, "frames": frames, "from": from, "frames_total": total })).into_response()
            );
        };
        let (detail, time) =
            d.engine.with(|c| Ok((c.render_detail(id)?, Timing::of(c, target)))).map_err(engine_error)?;
        let workers = detail.workers.len();
        Ok::<_, Response>(
            Json(json!({
                "info": render_json(&detail.info, time, workers),
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
        let (who, _) = d.sessions.who(&headers)?;
        let Target::Render(id) = d.visible(&who, &id)? else {
            return Err(refuse(StatusCode::BAD_REQUEST, "a sequence has no tiles of its own: open one of its frames"));
        };
        let views: Vec<TileView> = d.engine.with(|c| c.tile_views(id)).map_err(engine_error)?;
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
    let id = match d.sessions.who(&headers).and_then(|(who, _)| d.visible(&who, &id)) {
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
    let (who, _) = d.sessions.who(headers)?;
    let Target::Render(id) = d.visible(&who, id)? else {
        return Err(refuse(StatusCode::BAD_REQUEST, "a sequence's images are its frames': open one of them"));
    };
    let bytes = d.engine.image(id).await.map_err(engine_error)?;
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
    act_on(&d, &headers, &id, "cancelled", async |target| d.engine.cancel(target).await).await
}

/// Retries a failed or cancelled render (a frame, or a sequence's failed and cancelled frames),
/// keeping what it merged: `tessera retry` from the page.
async fn retry(State(d): State<Arc<Dashboard>>, headers: HeaderMap, Path(id): Path<String>) -> Response {
    act_on(&d, &headers, &id, "retried", async |target| d.engine.retry(target).await).await
}

/// Does `act` to render `id` for a caller who may act (a CSRF-checked request) on it, and says
/// so in the log and the answer (`{"<done>": "<id>"}`).
async fn act_on(
    d: &Dashboard,
    headers: &HeaderMap,
    id: &str,
    done: &str,
    act: impl AsyncFnOnce(Target) -> Result<(), crate::engine::EngineError>,
) -> Response {
    let target = match d.sessions.who_may_act(headers).and_then(|who| d.visible(&who, id)) {
        Ok(t) => t,
        Err(r) => return r,
    };
    match act(target).await {
        Ok(()) => {
            tracing::info!(render = %target, "render {target} {done} from the dashboard");
            let mut answer = serde_json::Map::new();
            answer.insert(done.to_string(), json!(target.to_string()));
            Json(Value::Object(answer)).into_response()
        }
        Err(e) => engine_error(e),
    }
}

/// What the door asks of every request before its route runs: its `Host` is one the dashboard
/// answers to ([`Sessions::check_host`]). A request with a valid token vouches for its
/// connection (which then no longer counts against its peer's unvouched connections); the
/// answer to any other closes the connection, so that unauthenticated keep-alive connections
/// (the probe held 512 fetching `/style.css`) cannot hold the door's places.
async fn door_checks(
    State(d): State<Arc<Dashboard>>,
    request: axum::extract::Request,
    next: axum::middleware::Next,
) -> Response {
    if let Err(refused) = d.sessions.check_host(request.headers()) {
        return close(refused);
    }
    let vouched = d.sessions.tokens.admits_client(Sessions::presented(request.headers()).as_deref());
    let connection = request.extensions().get::<Arc<crate::doors::Admission>>().cloned();
    let response = next.run(request).await;
    match (vouched, connection) {
        (true, Some(connection)) => {
            connection.vouch();
            response
        }
        (true, None) => response,
        (false, _) => close(response),
    }
}

/// `response`, closing its connection after it.
fn close(mut response: Response) -> Response {
    response.headers_mut().insert(header::CONNECTION, HeaderValue::from_static("close"));
    response
}

/// The event stream: first a `state` event with the render list and the workers, then, looked
/// at every [`EVENTS_EVERY`], a `changes` event with only the rows that changed (`renders`), the
/// ids of rows gone (`gone`), and the workers when they changed.
async fn events(State(d): State<Arc<Dashboard>>, headers: HeaderMap) -> Response {
    let (who, standing) = match d.sessions.standing(&headers) {
        Ok(w) => w,
        Err(r) => return r,
    };
    let stream = async_stream(d, who, standing);
    Sse::new(stream).keep_alive(KeepAlive::default()).into_response()
}

/// The events of [`events`]; they end when `standing` no longer holds (the user was removed
/// from the token file), and the page, reconnecting, is then asked to log in.
fn async_stream(
    d: Arc<Dashboard>,
    who: Identity,
    standing: Standing,
) -> impl tokio_stream::Stream<Item = Result<Event, std::convert::Infallible>> {
    let (tx, rx) = tokio::sync::mpsc::channel(2);
    tokio::spawn(async move {
        // What this stream's page has: each row's JSON by id, and the workers' key.
        let mut shown: Option<(HashMap<String, String>, String)> = None;
        while standing.holds() {
            let rows = d.shared_rows(&who).ok();
            let workers = workers_json(&d, &who).ok();
            let Some((rows, workers)) = rows.zip(workers) else { break };
            // Seconds since seen change all the time; the page counts them itself.
            let key = json!(workers.as_array().map(|w| {
                w.iter().map(|w| (w["id"].clone(), w["leases"].clone(), w["results"].clone())).collect::<Vec<_>>()
            }))
            .to_string();
            let event = match &mut shown {
                None => {
                    let list = rows.iter().map(|(_, row)| row.as_str()).collect::<Vec<_>>().join(",");
                    let state =
                        format!(r#"{{"renders":[{list}],"workers":{workers},"now":{}}}"#, crate::core::unix_seconds());
                    shown = Some((rows.iter().cloned().collect(), key));
                    Some(Event::default().event("state").data(state))
                }
                Some((had, had_key)) => changes(had, had_key, &rows, key, &workers),
            };
            if let Some(event) = event
                && tx.send(Ok(event)).await.is_err()
            {
                break;
            }
            if tx.is_closed() {
                break;
            }
            tokio::time::sleep(EVENTS_EVERY).await;
        }
    });
    tokio_stream::wrappers::ReceiverStream::new(rx)
}

/// The `changes` event that takes a page from `had` (rows by id) and `had_key` (the workers'
/// key) to `rows` and `key`, noting them as shown; `None` when nothing changed.
fn changes(
    had: &mut HashMap<String, String>,
    had_key: &mut String,
    rows: &[(String, String)],
    key: String,
    workers: &Value,
) -> Option<Event> {
    let changed: Vec<&str> =
        rows.iter().filter(|(id, row)| had.get(id) != Some(row)).map(|(_, row)| row.as_str()).collect();
    let now: std::collections::HashSet<&str> = rows.iter().map(|(id, _)| id.as_str()).collect();
    let gone: Vec<String> = had.keys().filter(|id| !now.contains(id.as_str())).cloned().collect();
    let workers_changed = *had_key != key;
    if changed.is_empty() && gone.is_empty() && !workers_changed {
        return None;
    }
    let mut data =
        format!(r#"{{"renders":[{}],"gone":{},"now":{}"#, changed.join(","), json!(gone), crate::core::unix_seconds());
    if workers_changed {
        data.push_str(&format!(r#","workers":{workers}"#));
    }
    data.push('}');
    for id in &gone {
        had.remove(id);
    }
    for (id, row) in rows {
        if had.get(id) != Some(row) {
            had.insert(id.clone(), row.clone());
        }
    }
    *had_key = key;
    Some(Event::default().event("changes").data(data))
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::core::tests::{SCENE, request};
    use crate::http::session::{COOKIE, hex};
    use crate::model::RenderState;
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
        let users =
            Users::parse(&format!("alice submit {}\nbob submit {}\n", token_hash(ALICE), token_hash(BOB))).unwrap();
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
        req.frames =
            Some(crate::model::Frames { list: tessera_render::plan::FrameList::parse("1-3").unwrap(), fps: 24.0 });
        req.setup.pose = Some(crate::model::Pose::default());
        let seq = d.engine.submit(&alice, req).await.unwrap().to_string();
        let (bearer, csrf) = (format!("Bearer {ALICE}"), d.sessions.csrf(ALICE));
        let as_alice = [("authorization", bearer.as_str()), ("x-tessera-csrf", csrf.as_str())];
        let page = |body: String| serde_json::from_str::<Value>(&body).unwrap();
        let (status, body) = call(&d, "GET", &format!("/api/renders/{seq}?from=1"), &as_alice).await;
        assert_eq!(status, StatusCode::OK, "{body}");
        let frames = page(body);
        assert_eq!((frames["frames_total"].as_u64(), frames["from"].as_u64()), (Some(3), Some(1)));
        let numbers: Vec<u64> =
            frames["frames"].as_array().unwrap().iter().map(|f| f["frame"].as_u64().unwrap()).collect();
        assert_eq!(numbers, [2, 3]);
        let bob = format!("Bearer {BOB}");
        let as_bob = [("authorization", bob.as_str())];
        assert_eq!(call(&d, "GET", &format!("/api/renders/{seq}"), &as_bob).await.0, StatusCode::NOT_FOUND);
        assert_eq!(call(&d, "POST", &format!("/api/renders/{seq}/cancel"), &as_alice).await.0, StatusCode::OK);
        assert_eq!(call(&d, "POST", &format!("/api/renders/{seq}/retry"), &as_bob).await.0, StatusCode::FORBIDDEN);
        let (status, body) = call(&d, "POST", &format!("/api/renders/{seq}/retry"), &as_alice).await;
        assert_eq!((status, body), (StatusCode::OK, format!("{{\"retried\":\"{seq}\"}}")));
        let frames = page(call(&d, "GET", &format!("/api/renders/{seq}"), &as_alice).await.1);
        let states: Vec<&str> =
            frames["frames"].as_array().unwrap().iter().map(|f| f["state"].as_str().unwrap()).collect();
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
        assert!(
            list.contains(&format!("\"id\":\"{alices}\"")) && !list.contains(&format!("\"id\":\"{bobs}\"")),
            "{list}"
        );
        assert_eq!(call(&d, "GET", &format!("/api/renders/{bobs}"), &as_alice).await.0, StatusCode::NOT_FOUND);
        assert_eq!(
            call(&d, "GET", &format!("/api/renders/{bobs}/preview.jpg"), &as_alice).await.0,
            StatusCode::NOT_FOUND
        );
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
        for host in
            ["127.0.0.1:8080", "localhost:8080", "LOCALHOST", "[::1]:8080", "10.1.2.3", "render.example.org:443"]
        {
            assert_eq!(call(&d, "GET", "/api/renders", &[("host", host)]).await.0, StatusCode::OK, "{host}");
        }
        let csrf = d.sessions.csrf("");
        let cancel = format!("/api/renders/{alices}/cancel");
        for origin in ["https://localhost:8080", "http://evil.example", "null", "http://localhost:8081"] {
            let headers = [("host", "localhost:8080"), ("origin", origin), ("x-tessera-csrf", csrf.as_str())];
            assert_eq!(call(&d, "POST", &cancel, &headers).await.0, StatusCode::FORBIDDEN, "{origin}");
        }
        let headers =
            [("host", "localhost:8080"), ("origin", "http://localhost:8080"), ("x-tessera-csrf", csrf.as_str())];
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
        let job = d.engine.lease("w", "w", 1, 0.0, None, Duration::ZERO).await.unwrap().expect("a job");
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
}
