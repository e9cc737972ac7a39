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
use crate::core::{PreviewOf, Steer, Target, TileView};
use crate::engine::Engine;
use crate::grpc::server::{Standing, Tokens};
use crate::model::RenderInfo;
use crate::users::{Identity, Role};
use axum::extract::{Path, Query, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use serde_json::{Value, json};
use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tessera_request::limits::check_priority;
use tessera_request::printable;

/// Longest side of a live preview, in pixels.
pub const PREVIEW_SIDE: u32 = 800;
/// The previews' JPEG quality.
const PREVIEW_QUALITY: u8 = 85;
/// A render's preview is encoded at most this often, however many watch it.
pub const PREVIEW_EVERY: Duration = Duration::from_millis(500);
/// A running render's denoised preview is made at most this often: denoising takes seconds,
/// and previews are made one at a time.
pub const DENOISED_PREVIEW_EVERY: Duration = Duration::from_secs(10);
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
    /// How long it stays fresh (while the render's samples change).
    every: Duration,
    jpeg: bytes::Bytes,
}

/// The dashboard's state: the coordinator's, and what it keeps of its own.
pub struct Dashboard {
    pub(super) engine: Arc<Engine>,
    pub(super) sessions: Sessions,
    /// By render and whether raw (a denoised render's raw colour rather than its denoised one).
    previews: Mutex<HashMap<(i64, bool), Encoded>>,
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
            .route("/api/renders/{id}/log", get(log))
            .route("/api/renders/{id}/preview.jpg", get(preview))
            .route("/api/renders/{id}/image.exr", get(image_exr))
            .route("/api/renders/{id}/image.png", get(image_png))
            .route("/api/renders/{id}/cancel", post(cancel))
            .route("/api/renders/{id}/retry", post(retry))
            .route("/api/renders/{id}/pause", post(pause))
            .route("/api/renders/{id}/resume", post(resume))
            .route("/api/renders/{id}/priority", post(priority))
            .route("/api/renders/{id}/quote", post(quote))
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

    /// Render `id`'s preview JPEG: the cached one while it is fresh, else a new one. A finished
    /// render shows what its PNG shows (denoised, if it was), or its raw colour when `raw`; a
    /// running one that is denoised, its film denoised. `finished`: the page knows the render is
    /// done, so a preview of its film is stale however fresh.
    async fn preview_jpeg(&self, id: i64, raw: bool, finished: bool) -> Result<bytes::Bytes, Response> {
        let fresh = |previews: &HashMap<(i64, bool), Encoded>, version: Option<u64>| {
            previews
                .get(&(id, raw))
                .filter(|e| !(finished && e.version != u64::MAX))
                .filter(|e| e.at.elapsed() < e.every || Some(e.version) == version)
                .map(|e| e.jpeg.clone())
        };
        if let Some(jpeg) = fresh(&self.previews.lock().unwrap_or_else(|e| e.into_inner()), None) {
            return Ok(jpeg);
        }
        let _turn = self.encoding.lock().await;
        if let Some(jpeg) = fresh(&self.previews.lock().unwrap_or_else(|e| e.into_inner()), None) {
            return Ok(jpeg);
        }
        let of = self.engine.with(|c| c.preview(id, PREVIEW_SIDE, raw)).map_err(engine_error)?;
        let (version, every) = match &of {
            PreviewOf::Film { version, .. } => (*version, PREVIEW_EVERY),
            PreviewOf::Denoise { version, .. } => (*version, DENOISED_PREVIEW_EVERY),
            PreviewOf::Image(_) => (u64::MAX, PREVIEW_EVERY),
        };
        if let Some(jpeg) = fresh(&self.previews.lock().unwrap_or_else(|e| e.into_inner()), Some(version)) {
            return Ok(jpeg);
        }
        let jpeg = tokio::task::spawn_blocking(move || match of {
            PreviewOf::Film { preview, .. } => preview.jpeg(PREVIEW_QUALITY),
            // A denoiser that fails leaves the raw preview, as it leaves a finished image raw.
            PreviewOf::Denoise { layers, denoiser, .. } => match layers.denoised(&*denoiser.0) {
                Ok(denoised) => denoised.jpeg(PREVIEW_QUALITY),
                Err(why) => {
                    tracing::warn!(render = id, "the preview was not denoised: {why}");
                    layers.preview.jpeg(PREVIEW_QUALITY)
                }
            },
            PreviewOf::Image(path) => tessera_film::read_exr(&path)
                .map_err(|e| e.to_string())
                .and_then(|img| tessera_film::Preview::of_image_shown(&img, PREVIEW_SIDE, raw).jpeg(PREVIEW_QUALITY)),
        })
        .await
        .map_err(|_| refuse(StatusCode::INTERNAL_SERVER_ERROR, "encoding the preview panicked"))?
        .map_err(|e| refuse(StatusCode::INTERNAL_SERVER_ERROR, &format!("the preview could not be made: {e}")))?;
        let jpeg = bytes::Bytes::from(jpeg);
        let mut previews = self.previews.lock().unwrap_or_else(|e| e.into_inner());
        if previews.len() >= PREVIEWS_KEPT
            && !previews.contains_key(&(id, raw))
            && let Some(oldest) = previews.iter().min_by_key(|(_, e)| e.at).map(|(k, _)| *k)
        {
            previews.remove(&oldest);
        }
        previews.insert((id, raw), Encoded { version, at: Instant::now(), every, jpeg: jpeg.clone() });
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
        "error_bound": info.error_bound,
        "confidence": info.confidence,
        "eta_seconds": info.eta_seconds,
        "no_workers": info.no_workers,
        "priority": info.priority,
        "paused": info.paused,
        "placement": info.placement,
        "no_worker_fits": info.no_worker_fits,
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
                "pool": w.pool,
                "tags": w.tags.iter().map(ToString::to_string).collect::<Vec<_>>(),
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
    Query(page): Query<HashMap<String, String>>,
) -> Response {
    let (who, target) = match d.sessions.who(&headers).and_then(|(who, _)| Ok((d.visible(&who, &id)?, who))) {
        Ok((target, who)) => (who, target),
        Err(refused) => return refused,
    };
    let shown = match target {
        Target::Render(id) => still_page(&d, id, target),
        Target::Sequence(_) => {
            let from: usize = page.get("from").and_then(|f| f.parse().ok()).unwrap_or(0);
            sequence_page(&d, &who, target, from).await
        }
    };
    shown.unwrap_or_else(|r| r)
}

/// A still's (or a frame's) page: its status, size, settings and workers.
fn still_page(d: &Dashboard, id: i64, target: Target) -> Result<Response, Response> {
    let (detail, time, forecast) =
        d.engine.with(|c| Ok((c.render_detail(id)?, Timing::of(c, target), c.forecast(id)))).map_err(engine_error)?;
    let workers = detail.workers.len();
    let quote = forecast.map(|f| {
        json!({
            "samples": f.samples,
            "samples_low": f.samples_low,
            "samples_high": f.samples_high,
            "samples_done": f.samples_done,
            "tiles_judged": f.tiles_judged,
            "tiles": f.tiles,
            // The tiles a quote's pilot renders (the Quote button shows until they are judged).
            "pilot_tiles": tessera_render::plan::PILOT_TILES.min(f.tiles),
            "workers": f.workers,
            "threads": f.threads,
            "samples_per_second": f.samples_per_second,
        })
    });
    Ok(Json(json!({
        "info": render_json(&detail.info, time, workers),
        "width": detail.width,
        "height": detail.height,
        "settings": detail.settings,
        "workers": detail.workers,
        "quote": quote,
    }))
    .into_response())
}

/// A sequence's page: its row and a page of its frames (from the `from`-th), each a render of
/// its own with the workers on it now, or, once none is, the workers whose results it holds.
async fn sequence_page(d: &Dashboard, who: &Identity, target: Target, from: usize) -> Result<Response, Response> {
    let row = d.render_rows(who)?.into_iter().find(|r| r["id"] == target.to_string()).unwrap_or(Value::Null);
    let (mut frames, ended, total) = d
        .engine
        .with(|c| {
            let (frames, total) = c.sequence_frames(target.id(), from, FRAMES_A_PAGE).unwrap_or_default();
            let mut ended = Vec::new();
            let rows: Vec<Value> = frames
                .iter()
                .enumerate()
                .map(|(k, (info, workers))| {
                    let id = info.render_id.parse().unwrap_or(0);
                    if workers.is_empty() && info.samples_done > 0 {
                        ended.push((k, id));
                    }
                    let mut row = render_json(info, Timing::of(c, Target::Render(id)), workers.len());
                    row["frame"] = json!(info.frame);
                    row["worker_names"] = json!(workers);
                    row
                })
                .collect();
            Ok((rows, ended, total))
        })
        .map_err(engine_error)?;
    let ids: Vec<i64> = ended.iter().map(|&(_, id)| id).collect();
    if let Ok(who) = d.engine.read(move |store| Ok(store.workers_of(&ids)?)).await {
        let names = d.engine.with(|c| Ok(who.iter().map(|ids| c.worker_names(ids)).collect::<Vec<_>>()));
        for (&(k, _), names) in ended.iter().zip(names.unwrap_or_default()) {
            frames[k]["worker_names"] = json!(names);
        }
    }
    Ok(Json(json!({ "info": row, "frames": frames, "from": from, "frames_total": total })).into_response())
}

/// A render's or a sequence's log (`?after=ID`: the lines after that one), as
/// `{"lines": [{"id", "at", "line"}], "dropped": N}`.
async fn log(
    State(d): State<Arc<Dashboard>>,
    headers: HeaderMap,
    Path(id): Path<String>,
    Query(query): Query<HashMap<String, String>>,
) -> Response {
    let target = match d.sessions.who(&headers).and_then(|(who, _)| d.visible(&who, &id)) {
        Ok(t) => t,
        Err(r) => return r,
    };
    let Ok(after) = query.get("after").map_or("0", String::as_str).parse::<i64>() else {
        return refuse(StatusCode::BAD_REQUEST, "after is a line's id: a whole number");
    };
    match d.engine.log(target, after, crate::store::LOG_LINES).await {
        Ok(page) => Json(json!({
            "lines": page.lines.iter().map(|l| json!({"id": l.id, "at": l.at, "line": l.line})).collect::<Vec<_>>(),
            "dropped": page.dropped,
        }))
        .into_response(),
        Err(e) => engine_error(e),
    }
}

async fn tiles(State(d): State<Arc<Dashboard>>, headers: HeaderMap, Path(id): Path<String>) -> Response {
    let result = (|| {
        let (who, _) = d.sessions.who(&headers)?;
        let Target::Render(id) = d.visible(&who, &id)? else {
            return Err(refuse(StatusCode::BAD_REQUEST, "a sequence has no tiles of its own: open one of its frames"));
        };
        let views: Vec<TileView> = d.engine.with(|c| c.tile_views(id)).map_err(engine_error)?;
        let tiles: Vec<[f64; 8]> = views
            .iter()
            .map(|v| {
                [
                    v.tile.x0 as f64,
                    v.tile.y0 as f64,
                    v.tile.width as f64,
                    v.tile.height as f64,
                    v.spp as f64,
                    v.error as f64,
                    v.passes as f64,
                    v.budget as f64,
                ]
            })
            .collect();
        // The jobs in flight: each tile's, with its worker and passes.
        let jobs: Vec<Value> = views
            .iter()
            .enumerate()
            .flat_map(|(t, v)| {
                v.jobs.iter().map(move |(worker, first, count)| {
                    json!({ "tile": t, "x": v.tile.x0, "y": v.tile.y0, "worker": worker, "first": first, "count": count })
                })
            })
            .collect();
        Ok(Json(json!({ "tiles": tiles, "jobs": jobs })).into_response())
    })();
    result.unwrap_or_else(|r| r)
}

/// `GET /api/renders/{id}/preview.jpg[?raw=1]`: `raw` shows a denoised render's raw colour.
async fn preview(
    State(d): State<Arc<Dashboard>>,
    headers: HeaderMap,
    Path(id): Path<String>,
    Query(query): Query<HashMap<String, String>>,
) -> Response {
    let raw = query.get("raw").is_some_and(|v| v == "1");
    // The page's version says the render is done: a preview kept from while it ran will not do.
    let finished = query.get("v").is_some_and(|v| v.split(':').nth(1) == Some("done"));
    let id = match d.sessions.who(&headers).and_then(|(who, _)| d.visible(&who, &id)) {
        Ok(Target::Render(id)) => id,
        Ok(_) => {
            return refuse(StatusCode::BAD_REQUEST, "a sequence has no preview of its own: open one of its frames");
        }
        Err(r) => return r,
    };
    match d.preview_jpeg(id, raw, finished).await {
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
    act_on(&d, &headers, &id, "cancelled", async |target, _| d.engine.cancel(target).await).await
}

/// Retries a failed or cancelled render (a frame, or a sequence's failed and cancelled frames),
/// keeping what it merged: `tessera retry` from the page.
async fn retry(State(d): State<Arc<Dashboard>>, headers: HeaderMap, Path(id): Path<String>) -> Response {
    act_on(&d, &headers, &id, "retried", async |target, _| d.engine.retry(target).await).await
}

/// Pauses a render or a sequence (`?now=1`: handing its jobs in flight back at once).
async fn pause(
    State(d): State<Arc<Dashboard>>,
    headers: HeaderMap,
    Path(id): Path<String>,
    Query(query): Query<HashMap<String, String>>,
) -> Response {
    let now = match query.get("now").map(String::as_str) {
        None | Some("0") => false,
        Some("1") => true,
        Some(other) => return refuse(StatusCode::BAD_REQUEST, &format!("now is 0 or 1, not '{other}'")),
    };
    let steer = Steer { paused: Some(true), now, ..Steer::default() };
    act_on(&d, &headers, &id, "paused", async |target, who| d.engine.steer(target, steer, &who.name).await).await
}

async fn resume(State(d): State<Arc<Dashboard>>, headers: HeaderMap, Path(id): Path<String>) -> Response {
    let steer = Steer { paused: Some(false), ..Steer::default() };
    act_on(&d, &headers, &id, "resumed", async |target, who| d.engine.steer(target, steer, &who.name).await).await
}

/// Asks for a submitted render's quote ([`crate::core::Core::pilot`]): its pilot renders now,
/// ahead of other work and even while it is paused; the render's page then shows the quote.
async fn quote(State(d): State<Arc<Dashboard>>, headers: HeaderMap, Path(id): Path<String>) -> Response {
    act_on(&d, &headers, &id, "quoted", async |target, who| d.engine.pilot(target, &who.name).await.map(|_| ())).await
}

/// Sets a render's or a sequence's priority (`?to=N`, -1000..=1000).
async fn priority(
    State(d): State<Arc<Dashboard>>,
    headers: HeaderMap,
    Path(id): Path<String>,
    Query(query): Query<HashMap<String, String>>,
) -> Response {
    let to = query.get("to").map_or("", String::as_str);
    let parsed = to.parse::<i32>().map_err(|_| format!("'{}' is not a whole number", printable(to)));
    let priority = match parsed.and_then(|p| check_priority(p).map(|()| p)) {
        Ok(p) => p,
        Err(why) => return refuse(StatusCode::BAD_REQUEST, &format!("priority: {why}")),
    };
    let steer = Steer { priority: Some(priority), ..Steer::default() };
    act_on(&d, &headers, &id, "reprioritised", async |target, who| d.engine.steer(target, steer, &who.name).await).await
}

/// Does `act` to render `id` for a caller who may act (a CSRF-checked request) on it, and says
/// so in the log and the answer (`{"<done>": "<id>"}`).
async fn act_on(
    d: &Dashboard,
    headers: &HeaderMap,
    id: &str,
    done: &str,
    act: impl AsyncFnOnce(Target, Identity) -> Result<(), crate::engine::EngineError>,
) -> Response {
    let (target, who) = match d.sessions.who_may_act(headers).and_then(|who| Ok((d.visible(&who, id)?, who))) {
        Ok(found) => found,
        Err(r) => return r,
    };
    match act(target, who).await {
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
pub(crate) mod tests;
