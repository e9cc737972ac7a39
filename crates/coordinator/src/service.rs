//! The gRPC shell around [`Core`]: validates requests (protocol version, token, sizes), converts
//! them, and calls the core under a mutex. Nothing slow happens under the lock: the store's
//! changes the core asks for are queued (in order, before the lock is let go) for the writer
//! thread, and reading scenes and stored results, hashing, loading scenes, resolving and writing
//! images run outside it on blocking threads.

use crate::core::{Accepted, Core, CoreError, Outcome, Target, check_scene_hash, read_image};
use crate::store::{Store, Write, Writer};
use crate::users::Identity;
use crate::wire;
use std::pin::Pin;
use std::sync::atomic::AtomicBool;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;
use tessera_proto::v1::render_service_server::RenderService;
use tessera_proto::v1::work_service_server::WorkService;
use tessera_proto::v1::*;
use tessera_proto::{PROTOCOL_VERSION, check_version};
use tessera_render::plan::{FrameList, frame_time};
use tessera_scene::animation::Choice;
use tessera_scene::{LoadOptions, PoseAt};
use tokio::sync::Notify;
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

pub struct Shared {
    core: Mutex<Core>,
    work: Notify,
    /// True while the gRPC server accepts requests (what `/readyz` reports).
    pub serving: AtomicBool,
    /// Connections closed at once because the limit was reached.
    pub connections_refused: Arc<std::sync::atomic::AtomicU64>,
    uploads: Arc<tokio::sync::Semaphore>,
    downloads: Arc<tokio::sync::Semaphore>,
    /// Makes the store's changes outside the state lock, in order, many to a transaction.
    writer: Writer,
    /// Where the store is, for reading it outside the lock.
    data_dir: std::path::PathBuf,
}

impl Shared {
    pub fn new(mut core: Core) -> Result<Arc<Self>, CoreError> {
        let writer = Writer::start(&core.config().data_dir, core.config().fsync)?;
        let data_dir = core.config().data_dir.clone();
        core.defer_writes();
        Ok(Arc::new(Self {
            data_dir,
            core: Mutex::new(core),
            work: Notify::new(),
            serving: AtomicBool::new(false),
            connections_refused: Arc::default(),
            uploads: Arc::new(tokio::sync::Semaphore::new(CONCURRENT_UPLOADS)),
            downloads: Arc::new(tokio::sync::Semaphore::new(CONCURRENT_DOWNLOADS)),
            writer,
        }))
    }

    /// Commits an accepted result outside the state lock, then merges it under the lock, and
    /// writes the image (outside the lock) if it was the render's last.
    async fn commit_and_merge(self: Arc<Self>, accepted: Accepted, bytes: Vec<u8>) -> Result<(), Status> {
        let render = accepted.lease.render as i64;
        let committed = self
            .writer
            .commit(Write::Result { render, result: accepted.stored(), sums: bytes })
            .await
            .unwrap_or_else(|_| Err("the store's writer has stopped".into()));
        let finished = self.with(|c| c.merge(accepted, committed))?;
        if let Some(f) = finished {
            self.write_image(f).await?;
            tracing::info!(render, "render {render} finished");
        }
        Ok(())
    }

    /// Resolves and writes a finished render's image on a blocking thread, then tells the core.
    async fn write_image(&self, f: crate::core::Finished) -> Result<(), Status> {
        let id = f.id;
        let written = tokio::task::spawn_blocking(move || f.write())
            .await
            .unwrap_or_else(|_| Err("writing the image panicked".into()));
        self.with(|c| c.image_written(id, written))
    }

    /// Runs `f` with a connection of its own to the store, on a blocking thread (outside the lock).
    async fn read<T: Send + 'static>(
        &self,
        f: impl FnOnce(&Store) -> Result<T, CoreError> + Send + 'static,
    ) -> Result<T, Status> {
        let dir = self.data_dir.clone();
        tokio::task::spawn_blocking(move || f(&Store::reader(&dir)?))
            .await
            .map_err(|_| Status::internal("reading the store panicked"))?
            .map_err(status)
    }

    /// A stored scene's bytes.
    async fn scene_bytes(&self, hash: &str) -> Result<Vec<u8>, Status> {
        let hash = hash.to_string();
        self.read(move |store| {
            store
                .scene(&hash)?
                .ok_or_else(|| CoreError::NotFound(format!("no scene with hash {hash}: upload it first")))
        })
        .await
    }

    /// A finished render's EXR bytes: read outside the lock, and rebuilt from the stored results
    /// (then written again) if the file is gone.
    pub async fn image(&self, id: i64) -> Result<Vec<u8>, Status> {
        let (path, width, height) = self.with(|c| c.image_path(id))?;
        let at = path.clone();
        let read = tokio::task::spawn_blocking(move || at.is_file().then(|| read_image(&at, id)))
            .await
            .map_err(|_| Status::internal("reading the image panicked"))?;
        if let Some(bytes) = read {
            return bytes.map_err(status);
        }
        let (film, _) = self.read(move |store| Ok(store.rebuild(id, width, height)?)).await?;
        let f = self.with(|c| c.rebuilt(id, film))?;
        self.write_image(f).await?;
        tokio::task::spawn_blocking(move || read_image(&path, id))
            .await
            .map_err(|_| Status::internal("reading the image panicked"))?
            .map_err(status)
    }

    /// Retries a failed render, or a sequence's failed frames: each checked under the lock,
    /// its results read outside it, then put to work.
    async fn retry(&self, target: Target) -> Result<(), Status> {
        for id in self.with(|c| c.retry_members(target))? {
            let prepared = self.with(|c| c.begin_retry(id))?;
            let read = self.read(move |store| Ok(prepared.read(store))).await?;
            self.with_durable(|c| c.end_retry(id, read)).await?;
        }
        Ok(())
    }

    #[allow(clippy::result_large_err)]
    fn core(&self) -> Result<MutexGuard<'_, Core>, Status> {
        self.core.lock().map_err(|_| Status::internal("coordinator state poisoned by an earlier panic"))
    }

    /// Whether the state is sound, without waiting for the lock: a busy core is alive (a probe
    /// must not stall behind a long merge), a poisoned one is not.
    pub fn healthy(&self) -> Result<(), String> {
        match self.core.try_lock() {
            Ok(_) | Err(std::sync::TryLockError::WouldBlock) => Ok(()),
            Err(std::sync::TryLockError::Poisoned(_)) => Err("coordinator state poisoned by an earlier panic".into()),
        }
    }

    /// Runs `f` on the core; its errors become statuses a person can act on. The changes to
    /// the store it asked for are queued for the writer before the lock is let go (so that they
    /// are made in the order the core decided them); no one waits for them.
    #[allow(clippy::result_large_err)]
    pub fn with<T>(&self, f: impl FnOnce(&mut Core) -> Result<T, CoreError>) -> Result<T, Status> {
        let mut core = self.core()?;
        let result = f(&mut core);
        for w in core.take_writes() {
            self.writer.queue(w);
        }
        result.map_err(status)
    }

    /// [`Shared::with`], returning once the changes to the store `f` asked for are committed
    /// (what the caller is told is then durable).
    pub async fn with_durable<T>(&self, f: impl FnOnce(&mut Core) -> Result<T, CoreError>) -> Result<T, Status> {
        let (result, commits) = self.with_commits(f)?;
        committed(commits).await?;
        result.map_err(status)
    }

    /// Runs `f` on the core and queues the changes to the store it asked for, each with the
    /// receiver that says when it is committed.
    #[allow(clippy::result_large_err, clippy::type_complexity)]
    fn with_commits<T>(
        &self,
        f: impl FnOnce(&mut Core) -> Result<T, CoreError>,
    ) -> Result<(Result<T, CoreError>, Vec<Commit>), Status> {
        let mut core = self.core()?;
        let result = f(&mut core);
        let commits = core.take_writes().into_iter().map(|w| self.writer.commit(w)).collect();
        Ok((result, commits))
    }
}

/// Says when a change to the store is committed, or why it is not.
type Commit = tokio::sync::oneshot::Receiver<Result<(), String>>;

/// Waits for `commits`; the first failure becomes the answer.
async fn committed(commits: Vec<Commit>) -> Result<(), Status> {
    for commit in commits {
        commit
            .await
            .unwrap_or_else(|_| Err("the store's writer has stopped".into()))
            .map_err(|e| Status::internal(format!("could not be stored: {e}")))?;
    }
    Ok(())
}

pub fn status(e: CoreError) -> Status {
    if !matches!(e, CoreError::NotReady(_)) {
        tracing::warn!("refused: {e}");
    }
    match e {
        CoreError::Invalid(m) => Status::invalid_argument(m),
        CoreError::NotFound(m) => Status::not_found(m),
        CoreError::Limit(m) => Status::resource_exhausted(m),
        CoreError::NotReady(m) => Status::failed_precondition(m),
        CoreError::Store(e) => Status::internal(e.to_string()),
    }
}

/// Logs a refusal and passes it on.
fn refuse(status: Status) -> Status {
    tracing::warn!("refused: {}", status.message());
    status
}

/// Largest page of a listing, and the page a request without `page_size` gets.
const MAX_PAGE: usize = 1000;
const DEFAULT_PAGE: usize = 500;
/// Most lease ids one heartbeat or release may name.
const MAX_LEASE_IDS: usize = 4096;

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

/// A request about one render: who asks, and which render (the protocol version and the id
/// checked).
#[allow(clippy::result_large_err)]
fn render_request(request: Request<RenderRequest>) -> Result<(Identity, Target, Option<u32>), Status> {
    let who = caller(&request);
    let r = request.into_inner();
    check_version(r.protocol_version)?;
    Ok((who, render_id(&r.render_id)?, r.frame))
}

impl Shared {
    /// Runs `f` on the core if `who` may see render `id`: another user's render is answered as
    /// missing, so that its existence is not told either.
    #[allow(clippy::result_large_err)]
    fn with_render<T>(
        &self,
        who: &Identity,
        target: Target,
        f: impl FnOnce(&mut Core) -> Result<T, CoreError>,
    ) -> Result<T, Status> {
        self.with(|c| match c.owner_of(target) {
            Some(owner) if who.may_touch(owner) => f(c),
            _ => Err(CoreError::NotFound(match target {
                Target::Render(id) => format!("no render {id}"),
                Target::Sequence(_) => format!("no sequence {target}"),
            })),
        })
    }
}

#[allow(clippy::result_large_err)]
fn render_id(s: &str) -> Result<Target, Status> {
    Target::parse(s).ok_or_else(|| {
        Status::invalid_argument(format!("'{s}' is not a render id (a number, or s and a number for a sequence)"))
    })
}

type BoxStream<T> = Pin<Box<dyn Stream<Item = Result<T, Status>> + Send>>;

fn chunked<T: Send + 'static>(bytes: Vec<u8>, make: impl Fn(u64, Vec<u8>) -> T + Send + 'static) -> BoxStream<T> {
    let total = bytes.len() as u64;
    let chunks: Vec<Vec<u8>> =
        if bytes.is_empty() { vec![Vec::new()] } else { bytes.chunks(CHUNK_BYTES).map(<[u8]>::to_vec).collect() };
    Box::pin(tokio_stream::iter(chunks.into_iter().map(move |c| Ok(make(total, c)))))
}

#[derive(Clone)]
pub struct RenderApi(pub Arc<Shared>);

#[tonic::async_trait]
impl RenderService for RenderApi {
    async fn upload_scene(&self, request: Request<Streaming<SceneChunk>>) -> Result<Response<SceneRef>, Status> {
        let mut stream = request.into_inner();
        let _turn = take_turn(&self.0.uploads, CONCURRENT_UPLOADS, "scene uploads").await?;
        let limit = self.0.with(|c| Ok(c.config().max_scene_bytes))?;
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
        // Load it once here, so that a scene that cannot render is refused now, not on workers.
        let name = format!("uploaded scene {hash}");
        let claimed = hash.clone();
        let bytes = tokio::task::spawn_blocking(move || {
            check_scene_hash(&claimed, &bytes).map_err(status)?;
            tessera_scene::load_packed(&bytes, &name, &Default::default())
                .map_err(|e| refuse(Status::invalid_argument(format!("the scene does not load: {e}"))))?;
            Ok::<_, Status>(bytes)
        })
        .await
        .map_err(|_| Status::internal("scene check failed"))??;
        let size = bytes.len() as u64;
        self.0.with(|c| {
            c.metrics.bytes_in += size;
            Ok(())
        })?;
        self.0
            .writer
            .commit(Write::Scene { hash: hash.clone(), bytes })
            .await
            .unwrap_or_else(|_| Err("the store's writer has stopped".into()))
            .map_err(|e| Status::internal(format!("the scene could not be stored: {e}")))?;
        Ok(Response::new(SceneRef { hash, bytes: size }))
    }

    async fn has_scene(&self, request: Request<HasSceneRequest>) -> Result<Response<HasSceneResponse>, Status> {
        let r = request.into_inner();
        check_version(r.protocol_version)?;
        check_hash(&r.hash)?;
        let hash = r.hash.clone();
        let present = self.0.read(move |store| Ok(store.has_scene(&hash)?)).await?;
        if present {
            // Kept for the hour after: the client submits next, without uploading it again.
            self.0.writer.queue(Write::TouchScene(r.hash));
        }
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
        // Before the scene is loaded to count its triangles (Core::submit checks it again).
        crate::core::check_name("the scene name", &r.scene_name).map_err(status)?;
        let submission = wire::submission_from_wire(&r).map_err(|e| refuse(Status::invalid_argument(e)))?;
        let bytes = self.0.scene_bytes(&r.scene_hash).await?;
        let name = r.scene_name.clone();
        // A posed render or a sequence: the scene is posed (at the first frame) to check that the
        // animation is there and its keys are sound.
        let pose = match r.settings.as_ref().and_then(|s| s.pose.as_ref()) {
            Some(p) => {
                tessera_proto::convert::check_pose(p).map_err(Status::invalid_argument)?;
                let animation = Choice::from_wire(&p.animation).map_err(Status::invalid_argument)?;
                Some(PoseAt { animation, time: p.time })
            }
            None => None,
        };
        let pose = match (pose, r.frames.is_empty()) {
            (pose, true) => pose,
            (pose, false) => {
                let frames =
                    FrameList::parse(&r.frames).map_err(|e| Status::invalid_argument(format!("frames: {e}")))?;
                let first = frame_time(frames.0[0], r.fps);
                Some(PoseAt { animation: pose.map(|p| p.animation).unwrap_or_default(), time: first })
            }
        };
        let map = r.settings.as_ref().and_then(|s| s.environment_map.clone());
        let variant = submission.setup.variant.clone();
        let loaded = tokio::task::spawn_blocking(move || -> Result<_, String> {
            let source = tessera_scene::open_packed(&bytes, &name).map_err(|e| e.to_string())?;
            let mut options = LoadOptions { pose, variant, ..Default::default() };
            if let Some(m) = map {
                let env = source.environment(m.strength, m.rotate_degrees).map_err(|e| e.to_string())?;
                let env = env.ok_or("the settings name an environment map, but the scene's package carries none")?;
                if env.hash != m.hash {
                    return Err(format!("the environment map's hash is {}, not {}", env.hash, m.hash));
                }
                options.environment_map = Some(env.map);
            }
            source.pose(&options).map_err(|e| e.to_string())
        })
        .await
        .map_err(|_| Status::internal("scene check failed"))?
        .map_err(|e| refuse(Status::invalid_argument(format!("the scene does not load: {e}"))))?;
        let (triangles, cameras) = (loaded.info.triangles, loaded.scene.cameras.len());
        let (target, commits) = self.0.with_commits(|c| c.submit(&who.name, &submission, triangles, cameras))?;
        let target = target.map_err(status)?;
        if let Err(e) = committed(commits).await {
            // Not stored: it would be gone after a restart, so it is not started either.
            self.0.with(|c| {
                c.forget(target);
                Ok(())
            })?;
            return Err(e);
        }
        tracing::info!(render = %target, scene = %r.scene_name, "render submitted");
        self.0.work.notify_waiters();
        Ok(Response::new(SubmitRenderResponse { render_id: target.to_string() }))
    }

    type WatchRenderStream = BoxStream<RenderStatus>;

    async fn watch_render(&self, request: Request<RenderRequest>) -> Result<Response<Self::WatchRenderStream>, Status> {
        let (who, target, _) = render_request(request)?;
        // Refused at once (not as the stream's first message) when the render is not there or
        // not the caller's.
        self.0.with_render(&who, target, |_| Ok(()))?;
        let shared = self.0.clone();
        let (tx, rx) = tokio::sync::mpsc::channel(4);
        tokio::spawn(async move {
            // A sequence's finished frames are each told once on this stream.
            let mut told = std::collections::HashSet::new();
            loop {
                let status = shared
                    .with(|c| c.status_of(target).ok_or_else(|| CoreError::NotFound(format!("no render {target}"))))
                    .map(wire::info_to_wire);
                let status = status.map(|mut s| {
                    s.finished.retain(|f| told.insert(f.frame));
                    s
                });
                let finished = status.as_ref().map_or(true, |s| s.state != RenderState::Running as i32);
                if tx.send(status).await.is_err() || finished {
                    break;
                }
                tokio::time::sleep(Duration::from_millis(250)).await;
            }
        });
        Ok(Response::new(Box::pin(tokio_stream::wrappers::ReceiverStream::new(rx))))
    }

    type FetchImageStream = BoxStream<ImageChunk>;

    async fn fetch_image(&self, request: Request<RenderRequest>) -> Result<Response<Self::FetchImageStream>, Status> {
        let (who, target, frame) = render_request(request)?;
        let id = self.0.with_render(&who, target, |c| {
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
        })?;
        let bytes = self.0.image(id).await?;
        self.0.with(|c| {
            c.metrics.bytes_out += bytes.len() as u64;
            Ok(())
        })?;
        Ok(Response::new(chunked(bytes, |total_bytes, data| ImageChunk { total_bytes, data })))
    }

    async fn cancel_render(&self, request: Request<RenderRequest>) -> Result<Response<CancelResponse>, Status> {
        let (who, target, _) = render_request(request)?;
        self.0.with_render(&who, target, |_| Ok(()))?;
        self.0.with_durable(|c| c.cancel_target(target)).await?;
        Ok(Response::new(CancelResponse {}))
    }

    async fn retry_render(&self, request: Request<RenderRequest>) -> Result<Response<RetryResponse>, Status> {
        let (who, target, _) = render_request(request)?;
        self.0.with_render(&who, target, |_| Ok(()))?;
        self.0.retry(target).await?;
        self.0.work.notify_waiters();
        Ok(Response::new(RetryResponse {}))
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
        let (renders, more) =
            self.0.with(|c| Ok(c.list_renders(after, page_size(r.page_size), |o| who.may_touch(o))))?;
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
        let r = request.into_inner();
        check_version(r.protocol_version)?;
        let (workers, more) = self.0.with(|c| Ok(c.list_workers(&r.page_token, page_size(r.page_size))))?;
        let workers: Vec<WorkerStatus> = workers.into_iter().map(wire::worker_to_wire).collect();
        let next_page_token = match workers.last() {
            Some(last) if more => last.worker_id.clone(),
            _ => String::new(),
        };
        Ok(Response::new(ListWorkersResponse { workers, next_page_token }))
    }
}

#[derive(Clone)]
pub struct WorkApi(pub Arc<Shared>);

/// Largest encoded result accepted (a 1024 x 1024 tile).
const MAX_RESULT_BYTES: usize = 130 << 20;

#[tonic::async_trait]
impl WorkService for WorkApi {
    async fn lease(&self, request: Request<LeaseRequest>) -> Result<Response<LeaseResponse>, Status> {
        let host = crate::connections::peer(&request).map(|a| a.ip().to_string());
        let r = request.into_inner();
        check_version(r.protocol_version)?;
        if r.worker_id.is_empty() {
            return Err(Status::invalid_argument("worker_id is empty"));
        }
        let deadline = tokio::time::Instant::now() + Duration::from_millis(r.wait_ms.min(30_000) as u64);
        loop {
            let job = self.0.with(|c| {
                let job = c.lease(&r.worker_id, &r.worker_name, r.threads, r.samples_per_second)?;
                if let Some(host) = &host {
                    c.seen_from(&r.worker_id, host);
                }
                Ok(job)
            })?;
            let job = job.as_ref().map(wire::job_to_wire);
            if job.is_some() || tokio::time::Instant::now() >= deadline {
                return Ok(Response::new(LeaseResponse { job }));
            }
            // Wake on new work, or poll for expired leases.
            let _ = tokio::time::timeout(Duration::from_millis(200), self.0.work.notified()).await;
        }
    }

    async fn heartbeat(&self, request: Request<HeartbeatRequest>) -> Result<Response<HeartbeatResponse>, Status> {
        let r = request.into_inner();
        check_version(r.protocol_version)?;
        check_lease_ids(&r.lease_ids)?;
        let cancelled_lease_ids = self.0.with(|c| Ok(c.heartbeat(&r.worker_id, &r.lease_ids)))?;
        Ok(Response::new(HeartbeatResponse { cancelled_lease_ids }))
    }

    async fn release(&self, request: Request<ReleaseRequest>) -> Result<Response<ReleaseResponse>, Status> {
        let r = request.into_inner();
        check_version(r.protocol_version)?;
        check_lease_ids(&r.lease_ids)?;
        let passes = self.0.with(|c| Ok(c.release(&r.worker_id, &r.lease_ids)))?;
        if passes > 0 {
            self.0.work.notify_waiters();
        }
        Ok(Response::new(ReleaseResponse { passes }))
    }

    async fn fail(&self, request: Request<FailRequest>) -> Result<Response<FailResponse>, Status> {
        let r = request.into_inner();
        check_version(r.protocol_version)?;
        self.0.with(|c| c.fail(&r.worker_id, &r.lease_id, &r.error))?;
        self.0.work.notify_waiters();
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
        let turn = take_turn(&self.0.downloads, CONCURRENT_DOWNLOADS, "scene downloads").await?;
        let bytes = self.0.scene_bytes(&r.hash).await?;
        self.0.with(|c| {
            c.metrics.bytes_out += bytes.len() as u64;
            Ok(())
        })?;
        let hash = r.hash.clone();
        Ok(Response::new(chunked(bytes, move |total_bytes, data| {
            let _turn = &turn;
            SceneChunk { protocol_version: PROTOCOL_VERSION, hash: hash.clone(), total_bytes, data }
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
        // Decoded before the lock is taken: it is most of what a result costs the coordinator.
        let sums = tessera_proto::sums::decode_tile_sums(&bytes);
        let accepted = self.0.with(|c| {
            crate::core::check_name("the worker id", &worker)?;
            c.metrics.bytes_in += bytes.len() as u64;
            c.accept(&worker, &lease, sums)
        })?;
        let outcome = match accepted {
            Err(why) => Outcome::Ignored(why),
            Ok(accepted) => {
                // Committed and merged to the end even if the worker hangs up meanwhile: an
                // accepted result left half done would keep its render from finishing.
                let shared = self.0.clone();
                tokio::spawn(shared.commit_and_merge(accepted, bytes))
                    .await
                    .map_err(|_| Status::internal("merging the result failed"))??;
                Outcome::Merged
            }
        };
        if let Outcome::Ignored(why) = outcome {
            let (worker, lease) = (worker.escape_debug().to_string(), lease.escape_debug().to_string());
            tracing::info!(worker = %worker, lease = %lease, reason = why.label(), "ignored a result");
        }
        self.0.work.notify_waiters();
        Ok(Response::new(CompleteResponse { merged: outcome == Outcome::Merged }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{Core, CoreConfig};

    /// Scene downloads take turns: with every turn taken a fetch waits, and it goes on as soon
    /// as a turn is free; the turn is held until its stream is dropped.
    #[tokio::test]
    async fn scene_downloads_take_turns() {
        let dir = tempfile::Builder::new().prefix("tessera-downloads-").tempdir().unwrap();
        let mut core = Core::open(CoreConfig::new(dir.path().to_path_buf())).unwrap();
        let bytes = b"tessera-builtin:cornell-box".to_vec();
        let hash = blake3::hash(&bytes).to_hex().to_string();
        core.put_scene(&hash, &bytes).unwrap();
        let shared = Shared::new(core).unwrap();
        let api = WorkApi(shared.clone());
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
        assert_eq!(shared.downloads.available_permits(), 0, "each open stream holds a turn");
        let waiting = tokio::spawn(fetch());
        tokio::time::sleep(Duration::from_millis(300)).await;
        assert!(!waiting.is_finished(), "a fetch went ahead with every turn taken");
        drop(streams.pop());
        let mut stream = tokio::time::timeout(Duration::from_secs(10), waiting).await.unwrap().unwrap().unwrap();
        let chunk = stream.next().await.unwrap().unwrap();
        assert_eq!(chunk.data, bytes);
    }
}
