//! The gRPC handlers: each checks what the wire brought (protocol version, ids, hashes, sizes),
//! turns it into the core's types (`wire.rs`), calls the [`Engine`], and turns its answer into a
//! message or a status a person can act on. Streams the coordinator receives or sends are
//! bounded in time and size here.

use super::server::Standing;
use super::wire;
use crate::core::{CoreError, Outcome, Refinement, Steer, Target};
use crate::engine::{Engine, EngineError};
use crate::model::{Offer, Submission};
use crate::users::Identity;
use std::pin::Pin;
use std::sync::Arc;
use std::time::Duration;
use tessera_proto::v1::render_service_server::RenderService;
use tessera_proto::v1::work_service_server::WorkService;
use tessera_proto::v1::*;
use tessera_proto::{PROTOCOL_VERSION, check_version};
use tessera_request::limits::{MAX_MESSAGE_BYTES, clip};
use tokio_stream::{Stream, StreamExt};
use tonic::{Request, Response, Status, Streaming};

/// Chunk size of every stream Tessera sends.
pub const CHUNK_BYTES: usize = 1 << 20;
/// The longest a client or worker streaming to the coordinator may take to send its next
/// message: a stream that stalls is dropped instead of holding its handler for ever.
pub const NEXT_MESSAGE_WITHIN: Duration = Duration::from_secs(60);
/// Scene uploads held in memory at once; more wait their turn (up to a minute).
pub const CONCURRENT_UPLOADS: usize = 2;
/// Scene downloads (workers fetching a scene) held in memory at once: each holds the whole
/// scene, so a thousand workers joining at once must not read it a thousand times over. More
/// wait their turn (up to a minute).
pub const CONCURRENT_DOWNLOADS: usize = 4;
/// Largest page of a listing, and the page a request without `page_size` gets.
const MAX_PAGE: usize = 1000;
/// Most finished frames one message of a sequence's watch tells (the rest follow at once).
const FRAMES_A_MESSAGE: usize = 10_000;
const DEFAULT_PAGE: usize = 500;
/// Most lease ids one heartbeat or release may name.
const MAX_LEASE_IDS: usize = 4096;
// The largest encoded result accepted: submissions hold their tiles to it.
use tessera_request::limits::MAX_RESULT_BYTES;

/// The engine's answer as a gRPC status: its kind decides the code, its message is kept.
pub fn status(e: EngineError) -> Status {
    use tonic::Code;
    let code = match &e {
        EngineError::Core(CoreError::Invalid(_)) => Code::InvalidArgument,
        EngineError::Core(CoreError::NotFound(_)) => Code::NotFound,
        EngineError::Core(CoreError::Limit(_)) => Code::ResourceExhausted,
        EngineError::Core(CoreError::NotReady(_)) => Code::FailedPrecondition,
        EngineError::Core(CoreError::Refused(_)) => Code::PermissionDenied,
        EngineError::Core(CoreError::Store(_)) | EngineError::Internal(_) => Code::Internal,
    };
    let message = clip(&e.to_string(), MAX_MESSAGE_BYTES).into_owned();
    if code != Code::FailedPrecondition {
        tracing::warn!("refused: {message}");
    }
    Status::new(code, message)
}

/// Logs a refusal and passes it on.
fn refuse(status: Status) -> Status {
    tracing::warn!("refused: {}", status.message());
    status
}

/// A turn among the `limit` that `turns` allows at once (uploads, downloads), waited for up to
/// [`NEXT_MESSAGE_WITHIN`]; held until dropped.
async fn take_turn(
    turns: &Arc<tokio::sync::Semaphore>,
    limit: usize,
    what: &str,
) -> Result<tokio::sync::OwnedSemaphorePermit, Status> {
    tokio::time::timeout(NEXT_MESSAGE_WITHIN, turns.clone().acquire_owned())
        .await
        .map_err(|_| {
            refuse(Status::resource_exhausted(format!(
                "{limit} {what} have been in progress for a minute: try again later"
            )))
        })?
        .map_err(|_| Status::unavailable("the coordinator is shutting down"))
}

/// The next message of a stream a peer sends, within [`NEXT_MESSAGE_WITHIN`].
async fn next_message<T>(stream: &mut Streaming<T>, what: &str) -> Result<Option<T>, Status> {
    match tokio::time::timeout(NEXT_MESSAGE_WITHIN, stream.next()).await {
        Ok(message) => message.transpose(),
        Err(_) => Err(refuse(Status::deadline_exceeded(format!(
            "{what} stalled: no message for {} s",
            NEXT_MESSAGE_WITHIN.as_secs()
        )))),
    }
}

fn page_size(asked: u32) -> usize {
    if asked == 0 { DEFAULT_PAGE } else { (asked as usize).min(MAX_PAGE) }
}

/// A scene hash is 64 lowercase hex digits (BLAKE3); anything else is refused before it is
/// looked up, logged or stored.
#[allow(clippy::result_large_err)]
fn check_hash(hash: &str) -> Result<(), Status> {
    if hash.len() == 64 && hash.bytes().all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b)) {
        Ok(())
    } else {
        let shown: String = hash.chars().take(80).collect::<String>().escape_debug().to_string();
        Err(refuse(Status::invalid_argument(format!("'{shown}' is not a scene hash (64 lowercase hex digits)"))))
    }
}

#[allow(clippy::result_large_err)]
fn check_lease_ids(ids: &[String]) -> Result<(), Status> {
    if ids.len() > MAX_LEASE_IDS || ids.iter().any(|id| id.len() > 20) {
        return Err(refuse(Status::invalid_argument(format!(
            "{} lease ids (at most {MAX_LEASE_IDS}, each a number)",
            ids.len()
        ))));
    }
    Ok(())
}

/// Who made a request: the per-user token's owner, or anyone with every right where the
/// coordinator has no per-user tokens (or the shared token was presented).
fn caller<T>(request: &Request<T>) -> Identity {
    request.extensions().get::<Identity>().cloned().unwrap_or_else(Identity::anyone)
}

#[allow(clippy::result_large_err)]
fn render_id(s: &str) -> Result<Target, Status> {
    Target::parse(s).ok_or_else(|| {
        Status::invalid_argument(format!("'{s}' is not a render id (a number, or s and a number for a sequence)"))
    })
}

/// A request about one render: who asks, and which render (the protocol version and the id
/// checked).
#[allow(clippy::result_large_err)]
fn render_request(request: Request<RenderRequest>) -> Result<(Identity, Target, Option<u32>), Status> {
    let who = caller(&request);
    let r = request.into_inner();
    check_version(r.protocol_version)?;
    Ok((who, render_id(&r.render_id)?, r.frame))
}

/// Checks that `who` may see `target`: another user's render is answered as missing, so that
/// its existence is not told either.
#[allow(clippy::result_large_err)]
pub fn visible(engine: &Engine, who: &Identity, target: Target) -> Result<(), EngineError> {
    engine.with(|c| match c.owner_of(target) {
        Some(owner) if who.may_touch(owner) => Ok(()),
        _ => Err(CoreError::NotFound(match target {
            Target::Render(id) => format!("no render {id}"),
            Target::Sequence(_) => format!("no sequence {target}"),
        })),
    })
}

type BoxStream<T> = Pin<Box<dyn Stream<Item = Result<T, Status>> + Send>>;

/// How long a download's reader may leave its next chunk untaken before the download ends and
/// lets go of what it holds (its bytes, and a scene download's turn). Before, a client that
/// stopped reading held them for as long as it kept its connection: four such streams took every
/// scene-download turn, and real downloads failed after a minute of waiting.
pub const STALLED_READER: Duration = Duration::from_secs(20);

/// `bytes` as a stream of chunks of at most [`CHUNK_BYTES`], each made by `make(total, data)`;
/// `held` (a turn) is let go with the bytes when the stream is read to its end, dropped, or its
/// reader leaves a chunk untaken for [`STALLED_READER`].
fn chunked<T: Send + 'static>(
    bytes: Vec<u8>,
    held: impl Send + 'static,
    make: impl Fn(u64, Vec<u8>) -> T + Send + 'static,
) -> BoxStream<T> {
    let (tx, rx) = tokio::sync::mpsc::channel(1);
    tokio::spawn(async move {
        let _held = held;
        let total = bytes.len() as u64;
        // An empty file is one empty chunk, so that the reader hears its size.
        let chunks: Vec<&[u8]> = if bytes.is_empty() { vec![&[]] } else { bytes.chunks(CHUNK_BYTES).collect() };
        for data in chunks {
            match tx.send_timeout(Ok(make(total, data.to_vec())), STALLED_READER).await {
                Ok(()) => {}
                Err(tokio::sync::mpsc::error::SendTimeoutError::Timeout(_)) => {
                    tracing::warn!(
                        "a download of {total} bytes was ended: its reader took no chunk for {} s",
                        STALLED_READER.as_secs()
                    );
                    return;
                }
                Err(tokio::sync::mpsc::error::SendTimeoutError::Closed(_)) => return,
            }
        }
    });
    Box::pin(tokio_stream::wrappers::ReceiverStream::new(rx))
}

/// The render service: what clients (the CLI) call.
#[derive(Clone)]
pub struct RenderApi {
    engine: Arc<Engine>,
    uploads: Arc<tokio::sync::Semaphore>,
}

impl RenderApi {
    pub fn new(engine: Arc<Engine>) -> Self {
        Self { engine, uploads: Arc::new(tokio::sync::Semaphore::new(CONCURRENT_UPLOADS)) }
    }
}

#[tonic::async_trait]
impl RenderService for RenderApi {
    async fn upload_scene(&self, request: Request<Streaming<SceneChunk>>) -> Result<Response<SceneRef>, Status> {
        let who = caller(&request);
        let mut stream = request.into_inner();
        let _turn = take_turn(&self.uploads, CONCURRENT_UPLOADS, "scene uploads").await?;
        let limit = self.engine.with(|c| Ok(c.config().max_scene_bytes)).map_err(status)?;
        let (mut hash, mut bytes) = (String::new(), Vec::new());
        while let Some(chunk) = next_message(&mut stream, "the scene upload").await? {
            check_version(chunk.protocol_version)?;
            if chunk.total_bytes > limit || (bytes.len() + chunk.data.len()) as u64 > limit {
                return Err(refuse(Status::resource_exhausted(format!(
                    "scene exceeds the {limit}-byte limit ({} bytes)",
                    chunk.total_bytes.max((bytes.len() + chunk.data.len()) as u64)
                ))));
            }
            if hash.is_empty() {
                check_hash(&chunk.hash)?;
                hash = chunk.hash;
            } else if chunk.hash != hash {
                return Err(refuse(Status::invalid_argument("the chunks of one upload name different hashes")));
            }
            bytes.extend_from_slice(&chunk.data);
        }
        if bytes.is_empty() {
            return Err(Status::invalid_argument("empty scene upload"));
        }
        let size = self.engine.put_scene(&who.name, hash.clone(), bytes).await.map_err(status)?;
        Ok(Response::new(SceneRef { hash, bytes: size }))
    }

    async fn has_scene(&self, request: Request<HasSceneRequest>) -> Result<Response<HasSceneResponse>, Status> {
        let who = caller(&request);
        let r = request.into_inner();
        check_version(r.protocol_version)?;
        check_hash(&r.hash)?;
        let present = self.engine.has_scene(&who, &r.hash).await.map_err(status)?;
        Ok(Response::new(HasSceneResponse { present }))
    }

    async fn submit_render(
        &self,
        request: Request<SubmitRenderRequest>,
    ) -> Result<Response<SubmitRenderResponse>, Status> {
        let who = caller(&request);
        let r = request.into_inner();
        check_version(r.protocol_version)?;
        check_hash(&r.scene_hash)?;
        let submission = Submission::from_wire(&r).map_err(|e| refuse(Status::invalid_argument(e)))?;
        let target = self.engine.submit(&who, submission).await.map_err(status)?;
        Ok(Response::new(SubmitRenderResponse { render_id: target.to_string() }))
    }

    type WatchRenderStream = BoxStream<RenderStatus>;

    async fn watch_render(&self, request: Request<RenderRequest>) -> Result<Response<Self::WatchRenderStream>, Status> {
        let standing = request.extensions().get::<Standing>().cloned();
        let (who, target, _) = render_request(request)?;
        // Refused at once (not as the stream's first message) when the render is not there or
        // not the caller's.
        visible(&self.engine, &who, target).map_err(status)?;
        let engine = self.engine.clone();
        let (tx, rx) = tokio::sync::mpsc::channel(4);
        tokio::spawn(async move {
            // A sequence's finished frames are each told once on this stream, in the order they
            // finished, at most FRAMES_A_MESSAGE a message: `told` is how many were.
            let (mut told, mut previews_told) = (0, 0);
            loop {
                if standing.as_ref().is_some_and(|s| !s.holds()) {
                    let revoked =
                        Status::unauthenticated("this token no longer admits its user (the token file changed)");
                    let _ = tx.send(Err(revoked)).await;
                    break;
                }
                let answer = engine.with(|c| {
                    let mut info =
                        c.status_of(target).ok_or_else(|| CoreError::NotFound(format!("no render {target}")))?;
                    let mut all_told = true;
                    if let Target::Render(id) = target {
                        info.quote = c.forecast(id);
                    }
                    if let Target::Sequence(seq) = target {
                        let (frames, finished) = c.finished_frames(seq, told, FRAMES_A_MESSAGE);
                        told += frames.len();
                        info.finished = frames;
                        let (previews, previewed) = c.previewed_frames(seq, previews_told, FRAMES_A_MESSAGE);
                        previews_told += previews.len();
                        info.previewed = previews;
                        all_told = told == finished && previews_told == previewed;
                    }
                    Ok((info, all_told))
                });
                let (status, all_told) = match answer {
                    Ok((info, all_told)) => (Ok(wire::info_to_wire(info)), all_told),
                    Err(e) => (Err(status(e)), true),
                };
                // (A render reopened for a blocked worker's results shows as running.)
                let ended = status.as_ref().map_or(true, |s| s.state != RenderState::Running as i32);
                if tx.send(status).await.is_err() || (ended && all_told) {
                    break;
                }
                if all_told {
                    tokio::time::sleep(Duration::from_millis(250)).await;
                }
            }
        });
        Ok(Response::new(Box::pin(tokio_stream::wrappers::ReceiverStream::new(rx))))
    }

    type FetchImageStream = BoxStream<ImageChunk>;

    async fn fetch_image(&self, request: Request<RenderRequest>) -> Result<Response<Self::FetchImageStream>, Status> {
        let preview = request.get_ref().preview;
        let (who, target, frame) = render_request(request)?;
        visible(&self.engine, &who, target).map_err(status)?;
        let id = self
            .engine
            .with(|c| {
                Ok(match (target, frame) {
                    (Target::Render(id), None) => id,
                    (Target::Sequence(seq), Some(f)) => c.frame_render(seq, f)?,
                    (Target::Sequence(_), None) => {
                        return Err(CoreError::Invalid(format!("{target} is a sequence: name one of its frames")));
                    }
                    (Target::Render(id), Some(_)) => {
                        return Err(CoreError::Invalid(format!("render {id} is not a sequence: it has no frames")));
                    }
                })
            })
            .map_err(status)?;
        let bytes = match preview {
            true => self.engine.preview_image(id).await,
            false => self.engine.image(id).await,
        }
        .map_err(status)?;
        Ok(Response::new(chunked(bytes, (), |total_bytes, data| ImageChunk { total_bytes, data })))
    }

    async fn cancel_render(&self, request: Request<RenderRequest>) -> Result<Response<CancelResponse>, Status> {
        let (who, target, _) = render_request(request)?;
        visible(&self.engine, &who, target).map_err(status)?;
        self.engine.cancel(target).await.map_err(status)?;
        Ok(Response::new(CancelResponse {}))
    }

    async fn retry_render(&self, request: Request<RenderRequest>) -> Result<Response<RetryResponse>, Status> {
        let (who, target, _) = render_request(request)?;
        visible(&self.engine, &who, target).map_err(status)?;
        self.engine.retry(target).await.map_err(status)?;
        Ok(Response::new(RetryResponse {}))
    }

    async fn refine_render(&self, request: Request<RefineRequest>) -> Result<Response<RefineResponse>, Status> {
        let who = caller(&request);
        let r = request.into_inner();
        check_version(r.protocol_version)?;
        let target = render_id(&r.render_id)?;
        visible(&self.engine, &who, target).map_err(status)?;
        tessera_request::limits::check_target_error(r.target_error).map_err(Status::invalid_argument)?;
        if r.spp == 0 && r.target_error == 0.0 {
            return Err(Status::invalid_argument("nothing to refine: give spp or target_error"));
        }
        let to = Refinement {
            spp: (r.spp > 0).then_some(r.spp),
            // As a submission's is stored, so that the bits equal a render submitted with it.
            target_error: (r.target_error > 0.0).then_some(r.target_error as f64),
        };
        self.engine.refine(target, to).await.map_err(status)?;
        Ok(Response::new(RefineResponse {}))
    }

    async fn steer_render(&self, request: Request<SteerRequest>) -> Result<Response<SteerResponse>, Status> {
        let who = caller(&request);
        let r = request.into_inner();
        check_version(r.protocol_version)?;
        let target = render_id(&r.render_id)?;
        visible(&self.engine, &who, target).map_err(status)?;
        if r.paused.is_none() && r.priority.is_none() && !r.pilot {
            return Err(Status::invalid_argument("nothing to change: give paused, priority or pilot"));
        }
        if r.now && r.paused != Some(true) {
            return Err(Status::invalid_argument("now goes with a pause (paused = true)"));
        }
        if r.paused.is_some() || r.priority.is_some() {
            let steer = Steer { paused: r.paused, priority: r.priority, now: r.now };
            self.engine.steer(target, steer, &who.name).await.map_err(status)?;
        }
        // The answer is about the render quoted, when a sequence's frame was.
        let shown = match r.pilot {
            true => Target::Render(self.engine.pilot(target, &who.name).await.map_err(status)?.0),
            false => target,
        };
        let info = self
            .engine
            .with(|c| {
                Ok(c.status_of(shown).map(|mut info| {
                    if let Target::Render(id) = shown {
                        info.quote = c.forecast(id);
                    }
                    info
                }))
            })
            .map_err(status)?;
        Ok(Response::new(SteerResponse { status: info.map(wire::info_to_wire) }))
    }

    async fn render_log(&self, request: Request<LogRequest>) -> Result<Response<LogResponse>, Status> {
        let who = caller(&request);
        let r = request.into_inner();
        check_version(r.protocol_version)?;
        let target = render_id(&r.render_id)?;
        visible(&self.engine, &who, target).map_err(status)?;
        let after = i64::try_from(r.after).map_err(|_| Status::invalid_argument("after is out of range"))?;
        let page = self.engine.log(target, after, crate::store::LOG_LINES).await.map_err(status)?;
        let lines = page.lines.into_iter().map(|l| LogLine { id: l.id as u64, at: l.at, line: l.line }).collect();
        Ok(Response::new(LogResponse { lines, dropped: page.dropped }))
    }

    async fn list_renders(
        &self,
        request: Request<ListRendersRequest>,
    ) -> Result<Response<ListRendersResponse>, Status> {
        let who = caller(&request);
        let r = request.into_inner();
        check_version(r.protocol_version)?;
        let after = match render_id(&r.page_token) {
            _ if r.page_token.is_empty() => 0,
            Ok(Target::Render(id) | Target::Sequence(id)) => id,
            Err(e) => return Err(e),
        };
        let (renders, more) = self
            .engine
            .with(|c| Ok(c.list_renders(after, page_size(r.page_size), |o| who.may_touch(o))))
            .map_err(status)?;
        let renders: Vec<RenderStatus> = renders.into_iter().map(wire::info_to_wire).collect();
        let next_page_token = match renders.last() {
            Some(last) if more => last.render_id.clone(),
            _ => String::new(),
        };
        Ok(Response::new(ListRendersResponse { renders, next_page_token }))
    }

    async fn list_workers(
        &self,
        request: Request<ListWorkersRequest>,
    ) -> Result<Response<ListWorkersResponse>, Status> {
        let who = caller(&request);
        let r = request.into_inner();
        check_version(r.protocol_version)?;
        let (workers, more) = self
            .engine
            .with(|c| Ok(c.list_workers_for(&who, &r.page_token, page_size(r.page_size))))
            .map_err(status)?;
        let workers: Vec<WorkerStatus> = workers.into_iter().map(wire::worker_to_wire).collect();
        let next_page_token = match workers.last() {
            Some(last) if more => last.worker_id.clone(),
            _ => String::new(),
        };
        Ok(Response::new(ListWorkersResponse { workers, next_page_token }))
    }
}

/// The work service: what workers call.
#[derive(Clone)]
pub struct WorkApi {
    engine: Arc<Engine>,
    downloads: Arc<tokio::sync::Semaphore>,
}

impl WorkApi {
    pub fn new(engine: Arc<Engine>) -> Self {
        Self { engine, downloads: Arc::new(tokio::sync::Semaphore::new(CONCURRENT_DOWNLOADS)) }
    }
}

#[tonic::async_trait]
impl WorkService for WorkApi {
    async fn lease(&self, request: Request<LeaseRequest>) -> Result<Response<LeaseResponse>, Status> {
        let host = crate::doors::peer(&request).map(|a| a.ip().to_string());
        let r = request.into_inner();
        check_version(r.protocol_version)?;
        if r.worker_id.is_empty() {
            return Err(Status::invalid_argument("worker_id is empty"));
        }
        let wait = Duration::from_millis(r.wait_ms as u64);
        let tags = tessera_request::placement::parse_tags(&r.tags).map_err(Status::invalid_argument)?;
        let offer = Offer {
            worker_id: r.worker_id,
            name: r.worker_name,
            threads: r.threads,
            samples_per_second: r.samples_per_second,
            pool: r.pool,
            tags,
        };
        let job = self.engine.lease(&offer, host.as_deref(), wait).await.map_err(status)?;
        Ok(Response::new(LeaseResponse { job: job.as_ref().map(wire::job_to_wire) }))
    }

    async fn heartbeat(&self, request: Request<HeartbeatRequest>) -> Result<Response<HeartbeatResponse>, Status> {
        let r = request.into_inner();
        check_version(r.protocol_version)?;
        check_lease_ids(&r.lease_ids)?;
        let cancelled_lease_ids = self.engine.with(|c| Ok(c.heartbeat(&r.worker_id, &r.lease_ids))).map_err(status)?;
        Ok(Response::new(HeartbeatResponse { cancelled_lease_ids }))
    }

    async fn release(&self, request: Request<ReleaseRequest>) -> Result<Response<ReleaseResponse>, Status> {
        let r = request.into_inner();
        check_version(r.protocol_version)?;
        check_lease_ids(&r.lease_ids)?;
        let passes = self.engine.release(&r.worker_id, &r.lease_ids).map_err(status)?;
        Ok(Response::new(ReleaseResponse { passes }))
    }

    async fn fail(&self, request: Request<FailRequest>) -> Result<Response<FailResponse>, Status> {
        let r = request.into_inner();
        check_version(r.protocol_version)?;
        self.engine.fail(&r.worker_id, &r.lease_id, &r.error).map_err(status)?;
        Ok(Response::new(FailResponse {}))
    }

    type FetchSceneStream = BoxStream<SceneChunk>;

    async fn fetch_scene(
        &self,
        request: Request<FetchSceneRequest>,
    ) -> Result<Response<Self::FetchSceneStream>, Status> {
        let r = request.into_inner();
        check_version(r.protocol_version)?;
        check_hash(&r.hash)?;
        // Held until the stream is sent or dropped, with the scene's bytes.
        let turn = take_turn(&self.downloads, CONCURRENT_DOWNLOADS, "scene downloads").await?;
        let bytes = self.engine.scene_bytes(&r.hash).await.map_err(status)?;
        self.engine
            .with(|c| {
                c.metrics.bytes_out += bytes.len() as u64;
                Ok(())
            })
            .map_err(status)?;
        let hash = r.hash.clone();
        Ok(Response::new(chunked(bytes, turn, move |total_bytes, data| SceneChunk {
            protocol_version: PROTOCOL_VERSION,
            hash: hash.clone(),
            total_bytes,
            data,
        })))
    }

    async fn complete(
        &self,
        request: Request<Streaming<CompleteRequest>>,
    ) -> Result<Response<CompleteResponse>, Status> {
        let mut stream = request.into_inner();
        let (mut worker, mut lease, mut bytes) = (String::new(), String::new(), Vec::new());
        while let Some(msg) = next_message(&mut stream, "the result").await? {
            check_version(msg.protocol_version)?;
            if worker.is_empty() {
                worker = msg.worker_id;
                lease = msg.lease_id;
            }
            let data = msg.chunk.map(|c| c.data).unwrap_or_default();
            if bytes.len() + data.len() > MAX_RESULT_BYTES {
                return Err(Status::resource_exhausted(format!("result exceeds {MAX_RESULT_BYTES} bytes")));
            }
            bytes.extend_from_slice(&data);
        }
        let outcome = self.engine.complete(&worker, &lease, bytes).await.map_err(status)?;
        Ok(Response::new(CompleteResponse { merged: outcome == Outcome::Merged }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{CoreConfig, Engine};

    /// The Box sample as a GLB whose JSON chunk is padded with spaces to about `bytes`: a scene
    /// that takes several chunks to send.
    fn padded_glb(bytes: usize) -> Vec<u8> {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../scene/tests/fixtures/scenes/Box/glTF-Binary/Box.glb");
        let glb = std::fs::read(path).unwrap();
        let word = |at: usize| u32::from_le_bytes(glb[at..at + 4].try_into().unwrap()) as usize;
        let (json_len, pad) = (word(12), bytes.div_ceil(4) * 4);
        let mut out = glb[..20 + json_len].to_vec();
        out.resize(out.len() + pad, b' ');
        out.extend_from_slice(&glb[20 + json_len..]);
        out[12..16].copy_from_slice(&((json_len + pad) as u32).to_le_bytes());
        let total = out.len() as u32;
        out[8..12].copy_from_slice(&total.to_le_bytes());
        out
    }

    /// A work service with a scene of several chunks stored (so that a download has more to
    /// give than its buffer holds): the service, the scene's hash and bytes, and its directory.
    async fn serving_a_large_scene() -> (WorkApi, String, Vec<u8>, tempfile::TempDir) {
        let dir = tempfile::Builder::new().prefix("tessera-downloads-").tempdir().unwrap();
        let engine = Engine::open(CoreConfig::new(dir.path().to_path_buf())).unwrap();
        let bytes = padded_glb(3 * CHUNK_BYTES);
        let hash = blake3::hash(&bytes).to_hex().to_string();
        engine.put_scene("", hash.clone(), bytes.clone()).await.unwrap();
        (WorkApi::new(engine), hash, bytes, dir)
    }

    /// Every byte a download stream gives, to its end.
    async fn read_all(stream: &mut BoxStream<SceneChunk>) -> Vec<u8> {
        let mut got = Vec::new();
        while let Some(Ok(chunk)) = stream.next().await {
            got.extend(chunk.data);
        }
        got
    }

    /// Scene downloads take turns: with every turn taken a fetch waits, and it goes on as soon
    /// as a turn is free; a turn is held while its stream has bytes left to send.
    #[tokio::test]
    async fn scene_downloads_take_turns() {
        let (api, hash, bytes, _dir) = serving_a_large_scene().await;
        let fetch = || {
            let (api, hash) = (api.clone(), hash.clone());
            async move {
                let request = FetchSceneRequest { protocol_version: PROTOCOL_VERSION, hash };
                api.fetch_scene(Request::new(request)).await.map(Response::into_inner)
            }
        };
        let mut streams = Vec::new();
        for _ in 0..CONCURRENT_DOWNLOADS {
            streams.push(fetch().await.unwrap());
        }
        assert_eq!(api.downloads.available_permits(), 0, "each open stream holds a turn");
        let waiting = tokio::spawn(fetch());
        tokio::time::sleep(Duration::from_millis(300)).await;
        assert!(!waiting.is_finished(), "a fetch went ahead with every turn taken");
        drop(streams.pop());
        let mut stream = tokio::time::timeout(Duration::from_secs(10), waiting).await.unwrap().unwrap().unwrap();
        assert!(read_all(&mut stream).await == bytes);
    }

    /// A download whose reader stops taking chunks lets go of its turn after [`STALLED_READER`]:
    /// four streams opened and never read no longer lock every worker out of scene downloads.
    #[tokio::test(start_paused = true)]
    async fn a_stalled_download_frees_its_turn() {
        let (api, hash, bytes, _dir) = serving_a_large_scene().await;
        let fetch = || {
            let request = FetchSceneRequest { protocol_version: PROTOCOL_VERSION, hash: hash.clone() };
            api.fetch_scene(Request::new(request))
        };
        let mut stalled = Vec::new();
        for _ in 0..CONCURRENT_DOWNLOADS {
            let mut stream = fetch().await.unwrap().into_inner();
            stream.next().await.unwrap().unwrap();
            stalled.push(stream);
        }
        assert_eq!(api.downloads.available_permits(), 0, "each open stream holds a turn");
        tokio::time::sleep(STALLED_READER + Duration::from_secs(1)).await;
        assert_eq!(api.downloads.available_permits(), CONCURRENT_DOWNLOADS, "stalled streams keep their turns");
        // A real download goes ahead and gets every byte.
        let mut stream = fetch().await.unwrap().into_inner();
        assert!(read_all(&mut stream).await == bytes);
        // A stalled stream ends short.
        assert!(read_all(&mut stalled[0]).await.len() < bytes.len());
    }
}
