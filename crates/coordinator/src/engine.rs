//! The engine both doors call: the [`Core`] behind its lock, the store's writer that commits what
//! the core decides (in the order decided, outside the lock), reads of the store on connections
//! of their own, and the slow work a request brings (loading a scene to check it, resolving and
//! writing an image) on blocking threads. It knows no protobuf and no HTTP: the gRPC door
//! (`grpc/`) and the HTTP door (`http/`) turn their requests into these calls and
//! [`EngineError`] into their own answers.

use crate::core::{Accepted, Core, CoreConfig, CoreError, Finished, Outcome, Target};
use crate::model::{Job, Offer, Submission};
use crate::store::{Store, Write, Writer};
use crate::users::{Identity, Role};
use std::path::PathBuf;
use std::sync::atomic::AtomicBool;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;
use tessera_render::TileSums;
use tessera_render::plan::frame_time;
use tessera_scene::PoseAt;
use tokio::sync::Notify;

/// Why the engine could not do what it was asked.
#[derive(Debug, thiserror::Error)]
pub enum EngineError {
    /// The core refused or could not find it (its kinds say which).
    #[error(transparent)]
    Core(#[from] CoreError),
    /// Something went wrong on this side: a poisoned lock, a writer that stopped, a panic.
    #[error("{0}")]
    Internal(String),
}

impl EngineError {
    fn internal(what: impl Into<String>) -> Self {
        EngineError::Internal(what.into())
    }
}

/// Most a lease request may wait for work to arrive.
pub const LONGEST_LEASE_WAIT: Duration = Duration::from_secs(30);

pub struct Engine {
    core: Mutex<Core>,
    /// Woken when there may be new work (a submit, a failed or released job, a retry).
    work: Notify,
    /// True while the gRPC door accepts requests (what `/readyz` reports).
    pub serving: AtomicBool,
    /// Makes the store's changes outside the state lock, in order, many to a transaction.
    writer: Writer,
    /// Where the store is, for reading it outside the lock.
    data_dir: PathBuf,
    /// The data directory's lock, held while the engine lives ([`crate::store::lock_data_dir`]).
    _lock: std::fs::File,
    /// Sends the notifications of renders that ended, when the coordinator has a key to sign
    /// them with.
    pub notifier: Option<crate::http::notify::Notifier>,
}

/// Says when a change to the store is committed, or why it is not.
type Commit = tokio::sync::oneshot::Receiver<Result<(), String>>;

impl Engine {
    /// Opens the data directory: the store read back into a core (every unfinished render
    /// resumed), its writer started, and the images of renders stored whole but not written
    /// when the coordinator stopped written now.
    pub fn open(config: CoreConfig) -> Result<Arc<Self>, EngineError> {
        std::fs::create_dir_all(config.data_dir.join("renders"))
            .map_err(|e| CoreError::Invalid(format!("cannot create {}: {e}", config.data_dir.display())))?;
        let lock = crate::store::lock_data_dir(&config.data_dir).map_err(CoreError::from)?;
        let store = Store::open(&config.data_dir, config.fsync).map_err(CoreError::from)?;
        let data_dir = config.data_dir.clone();
        let writer = Writer::start(&data_dir, config.fsync).map_err(CoreError::from)?;
        let notifier = match &config.notify.key {
            Some(key) => Some(
                crate::http::notify::Notifier::start(key.clone())
                    .map_err(|e| EngineError::Internal(format!("starting the notifier: {e}")))?,
            ),
            None => None,
        };
        let mut core = Core::open(config, &store)?;
        drop(store);
        let stored_whole = core.finish_stored();
        #[cfg(test)]
        core.audit();
        for w in core.take_writes() {
            writer.queue(w);
        }
        let engine = Arc::new(Self {
            core: Mutex::new(core),
            work: Notify::new(),
            serving: AtomicBool::new(false),
            writer,
            data_dir,
            _lock: lock,
            notifier,
        });
        for f in stored_whole {
            let (id, written) = (f.id, write_image(&f));
            engine.with(|c| c.image_written(id, written))?;
        }
        // Preview images written before a restart are told to watches again.
        let written: Vec<i64> = engine
            .with(|c| Ok(c.preview_frames()))?
            .into_iter()
            .filter(|(_, path)| path.is_file())
            .map(|(id, _)| id)
            .collect();
        engine.with(|c| {
            for id in written {
                c.preview_written(id, Ok(()));
            }
            Ok(())
        })?;
        Ok(engine)
    }

    /// Commits every change queued and moves the write-ahead log into `tessera.db`: a graceful
    /// stop's last step, after which the file alone holds everything.
    pub async fn checkpoint(&self) -> Result<(), EngineError> {
        self.writer
            .checkpoint()
            .await
            .unwrap_or_else(|_| Err("the store's writer has stopped".into()))
            .map_err(|e| EngineError::Internal(format!("checkpointing the database: {e}")))
    }

    fn core(&self) -> Result<MutexGuard<'_, Core>, EngineError> {
        self.core.lock().map_err(|_| EngineError::internal("coordinator state poisoned by an earlier panic"))
    }

    /// Whether the state is sound, without waiting for the lock: a busy core is alive (a probe
    /// must not stall behind a long merge), a poisoned one is not.
    pub fn healthy(&self) -> Result<(), String> {
        match self.core.try_lock() {
            Ok(_) | Err(std::sync::TryLockError::WouldBlock) => Ok(()),
            Err(std::sync::TryLockError::Poisoned(_)) => Err("coordinator state poisoned by an earlier panic".into()),
        }
    }

    /// Runs `f` on the core. The changes to the store it asked for are queued for the writer
    /// before the lock is let go (so that they are made in the order the core decided them); no
    /// one waits for them.
    pub fn with<T>(&self, f: impl FnOnce(&mut Core) -> Result<T, CoreError>) -> Result<T, EngineError> {
        let mut core = self.core()?;
        let result = f(&mut core);
        #[cfg(test)]
        core.audit();
        for w in core.take_writes() {
            self.writer.queue(w);
        }
        self.tell(&mut core);
        Ok(result?)
    }

    /// Hands the renders that ended to the notifier (without waiting for it).
    fn tell(&self, core: &mut Core) {
        let ended = core.take_ended();
        if let Some(notifier) = &self.notifier {
            for e in ended {
                notifier.send(crate::http::notify::notice(e));
            }
        }
    }

    /// [`Engine::with`], returning once the changes to the store `f` asked for are committed
    /// (what the caller is told is then durable).
    pub async fn with_durable<T>(&self, f: impl FnOnce(&mut Core) -> Result<T, CoreError>) -> Result<T, EngineError> {
        let (result, commits) = self.with_commits(f)?;
        committed(commits).await?;
        Ok(result?)
    }

    /// Runs `f` on the core and queues the changes to the store it asked for, each with the
    /// receiver that says when it is committed.
    fn with_commits<T>(
        &self,
        f: impl FnOnce(&mut Core) -> Result<T, CoreError>,
    ) -> Result<(Result<T, CoreError>, Vec<Commit>), EngineError> {
        let mut core = self.core()?;
        let result = f(&mut core);
        #[cfg(test)]
        core.audit();
        let commits = core.take_writes().into_iter().map(|w| self.writer.commit(w)).collect();
        self.tell(&mut core);
        Ok((result, commits))
    }

    /// Runs `f` with a connection of its own to the store, on a blocking thread (outside the lock).
    pub async fn read<T: Send + 'static>(
        &self,
        f: impl FnOnce(&Store) -> Result<T, CoreError> + Send + 'static,
    ) -> Result<T, EngineError> {
        let dir = self.data_dir.clone();
        let read = tokio::task::spawn_blocking(move || f(&Store::reader(&dir)?))
            .await
            .map_err(|_| EngineError::internal("reading the store panicked"))?;
        Ok(read?)
    }

    /// The lines of `target`'s log after line `after` (0: from the first kept), at most
    /// `limit`; read from the store outside the lock.
    pub async fn log(&self, target: Target, after: i64, limit: i64) -> Result<crate::store::LogPage, EngineError> {
        let of = match target {
            Target::Render(id) => crate::store::LogOf { id, sequence: false },
            Target::Sequence(id) => crate::store::LogOf { id, sequence: true },
        };
        self.read(move |store| Ok(store.log(of, after, limit)?)).await
    }

    /// Sets the owners' weights in the fair share (from the token file; an owner not named
    /// weighs 1).
    pub fn set_weights(&self, weights: std::collections::HashMap<String, f64>) {
        let _ = self.with(|c| {
            c.set_weights(weights);
            Ok(())
        });
    }

    /// Wakes the lease requests waiting for work.
    pub fn notify_work(&self) {
        self.work.notify_waiters();
    }

    /// A stored scene's bytes, checked against their hash as they are read: a copy that no
    /// longer matches (a flipped bit on disk) is deleted, the renders that use it fail saying
    /// why, and the caller hears it is missing (a submit uploads it again).
    pub async fn scene_bytes(&self, hash: &str) -> Result<Vec<u8>, EngineError> {
        self.stored_scene(hash, None).await
    }

    /// A stored scene's bytes for `who` to render ([`Engine::scene_bytes`]): a submitter may use
    /// only a scene they uploaded themselves, and any other is answered as missing (the client
    /// then uploads it), so that no one learns whether another user's scene is stored, nor
    /// renders it by its hash alone. An admin (and anyone, without per-user tokens) uses any.
    pub async fn scene_for(&self, who: &Identity, hash: &str) -> Result<Vec<u8>, EngineError> {
        self.stored_scene(hash, (who.role != Role::Admin).then(|| who.name.clone())).await
    }

    /// [`Engine::scene_bytes`], and with `uploader` only if they uploaded it: one read.
    async fn stored_scene(&self, hash: &str, uploader: Option<String>) -> Result<Vec<u8>, EngineError> {
        let owned = hash.to_string();
        let bytes = self
            .read(move |store| match uploader {
                Some(name) if !store.uploaded(&owned, &name)? => Ok(None),
                _ => Ok(store.scene(&owned)?),
            })
            .await?;
        match bytes {
            None => Err(CoreError::NotFound(format!("no scene with hash {hash}: upload it first")).into()),
            Some(bytes) if blake3::hash(&bytes).to_hex().as_str() == hash => Ok(bytes),
            Some(_) => {
                self.scene_lost(hash)?;
                Err(CoreError::NotFound(format!(
                    "the stored copy of scene {hash} is corrupt (its bytes no longer match their hash) and was \
                     deleted: submit the scene again to upload it"
                ))
                .into())
            }
        }
    }

    /// A stored scene found corrupt: deleted, and the renders that use it failed.
    fn scene_lost(&self, hash: &str) -> Result<(), EngineError> {
        let why = "its stored copy no longer matches its hash (the database was damaged): submit the scene \
                   again, then `tessera retry` the render";
        let failed = self.with(|c| Ok(c.scene_lost(hash, why)))?;
        tracing::error!("scene {hash}: its stored copy is corrupt; deleted it and failed {} render(s)", failed.len());
        self.writer.queue(Write::DeleteScene(hash.to_string()));
        Ok(())
    }

    /// Whether the scene is stored whole (its bytes checked against its hash, as
    /// [`Engine::scene_bytes`] checks them); if it is, it is kept for the hour after (the client
    /// submits next, without uploading it again).
    pub async fn has_scene(&self, who: &Identity, hash: &str) -> Result<bool, EngineError> {
        match self.scene_for(who, hash).await {
            Ok(_) => {
                self.writer.queue(Write::TouchScene(hash.to_string()));
                Ok(true)
            }
            Err(EngineError::Core(CoreError::NotFound(_))) => Ok(false),
            Err(e) => Err(e),
        }
    }

    /// Stores an uploaded scene once it is known to be what its hash says and to load (a scene
    /// that cannot render is refused now, not on the workers); returns once it is committed.
    pub async fn put_scene(&self, uploader: &str, hash: String, bytes: Vec<u8>) -> Result<u64, EngineError> {
        let name = format!("uploaded scene {hash}");
        let claimed = hash.clone();
        let bytes = tokio::task::spawn_blocking(move || {
            crate::core::check_scene_hash(&claimed, &bytes)?;
            // Read and checked, not built: what building costs is counted at submit. An
            // environment map is decoded to check it, and dropped.
            tessera_scene::open_packed(&bytes, &name)
                .and_then(|source| source.check_environment())
                .map_err(|e| CoreError::Invalid(format!("the scene does not load: {e}")))?;
            Ok::<_, CoreError>(bytes)
        })
        .await
        .map_err(|_| EngineError::internal("checking the scene panicked"))??;
        let size = bytes.len() as u64;
        self.with(|c| {
            c.metrics.bytes_in += size;
            Ok(())
        })?;
        committed(vec![self.writer.commit(Write::Scene { hash, bytes, owner: uploader.to_string() })])
            .await
            .map_err(|e| EngineError::Internal(format!("the scene could not be stored: {e}")))?;
        Ok(size)
    }

    /// Submits a render or a sequence for `who`: its scene, stored already (and theirs to use:
    /// [`Engine::scene_for`]), is read outside the
    /// lock to check that it poses as these settings ask (at the first frame) and to count what
    /// building it would make (`tessera_scene::Census`); then the core checks that against the
    /// farm's limits and records it, and once that is
    /// committed the render is queued.
    pub async fn submit(&self, who: &Identity, submission: Submission) -> Result<Target, EngineError> {
        let owner = who.name.as_str();
        let bytes = self.scene_for(who, &submission.scene_hash).await?;
        // A posed render or a sequence: the scene is posed (at the first frame) to check that the
        // animation is there and its keys are sound.
        let setup = &submission.setup;
        let mut pose = setup.pose.as_ref().map(|p| p.at());
        if let Some(frames) = &submission.frames {
            let first = frame_time(frames.list.0[0], frames.fps);
            pose = Some(PoseAt { animation: pose.map(|p| p.animation).unwrap_or_default(), time: first });
        }
        let (name, variant, map) =
            (submission.scene_name.clone(), setup.variant.clone(), setup.environment_map.clone());
        // Read, checked and counted, never built: accepting a render costs what the file does,
        // whatever its instancing (a worker pays for the build, within --max-scene-memory).
        let census = tokio::task::spawn_blocking(move || -> Result<_, String> {
            let source = tessera_scene::open_packed(&bytes, &name).map_err(|e| e.to_string())?;
            if let Some(m) = map {
                match source.environment_hash() {
                    None => {
                        return Err("the settings name an environment map, but the scene's package carries none".into());
                    }
                    Some(hash) if hash != m.hash => {
                        return Err(format!("the environment map's hash is {hash}, not {}", m.hash));
                    }
                    Some(_) => {}
                }
            }
            source.census(pose.as_ref(), variant.as_deref()).map_err(|e| e.to_string())
        })
        .await
        .map_err(|_| EngineError::internal("checking the scene panicked"))?
        .map_err(|e| CoreError::Invalid(format!("the scene does not load: {e}")))?;
        let (target, commits) = self.with_commits(|c| c.submit(owner, &submission, &census))?;
        let target = target?;
        if let Err(e) = committed(commits).await {
            // Not stored: it would be gone after a restart, so it is not started either.
            self.with(|c| {
                c.forget(target);
                Ok(())
            })?;
            return Err(e);
        }
        tracing::info!(render = %target, scene = %submission.scene_name, "render submitted");
        self.notify_work();
        Ok(target)
    }

    /// Hands worker `worker_id` a job, waiting up to `wait` (at most [`LONGEST_LEASE_WAIT`]) for
    /// one to arrive; `host` is where its call came from.
    pub async fn lease(&self, offer: &Offer, host: Option<&str>, wait: Duration) -> Result<Option<Job>, EngineError> {
        let deadline = tokio::time::Instant::now() + wait.min(LONGEST_LEASE_WAIT);
        loop {
            let job = self.with(|c| {
                let job = c.lease(offer)?;
                if let Some(host) = host {
                    c.seen_from(&offer.worker_id, host);
                }
                Ok(job)
            })?;
            if job.is_some() || tokio::time::Instant::now() >= deadline {
                return Ok(job);
            }
            // Wake on new work, or poll for expired leases.
            let _ = tokio::time::timeout(Duration::from_millis(200), self.work.notified()).await;
        }
    }

    /// A worker hands back leases it will not render: their passes go to others at once.
    pub fn release(&self, worker_id: &str, lease_ids: &[String]) -> Result<u64, EngineError> {
        let passes = self.with(|c| Ok(c.release(worker_id, lease_ids)))?;
        if passes > 0 {
            self.notify_work();
        }
        Ok(passes)
    }

    /// A worker could not render a job: its passes go back in line.
    pub fn fail(&self, worker_id: &str, lease_id: &str, error: &str) -> Result<(), EngineError> {
        self.with(|c| c.fail(worker_id, lease_id, error))?;
        self.notify_work();
        Ok(())
    }

    /// A worker's result: decoded outside the lock, checked against its lease under it,
    /// committed by the writer, merged, and the image written if it was the render's last.
    /// Committed and merged to the end even if the worker hangs up meanwhile: an accepted result
    /// left half done would keep its render from finishing.
    pub async fn complete(
        self: &Arc<Self>,
        worker_id: &str,
        lease_id: &str,
        bytes: Vec<u8>,
    ) -> Result<Outcome, EngineError> {
        // Decoded before the lock is taken: it is most of what a result costs the coordinator.
        let sums: Result<TileSums, String> = tessera_proto::sums::decode_tile_sums(&bytes).map_err(|e| e.to_string());
        let accepted = self.with(|c| {
            crate::core::check_name("the worker id", worker_id)?;
            c.metrics.bytes_in += bytes.len() as u64;
            c.accept(worker_id, lease_id, sums)
        })?;
        // What checks compare, taken outside the lock and only where a check needs it.
        let accepted = accepted.map(|mut a| {
            if a.wants_digest() {
                a.digest = Some(tessera_proto::sums::digest(a.sums()));
            }
            a
        });
        let outcome = match accepted {
            Err(why) => {
                let (worker, lease) = (worker_id.escape_debug().to_string(), lease_id.escape_debug().to_string());
                tracing::info!(worker = %worker, lease = %lease, reason = why.label(), "ignored a result");
                Outcome::Ignored(why)
            }
            Ok(accepted) if accepted.is_check() => {
                // On a task of its own, as a merge: a worker that hangs up (or dies) while its
                // check finishes the render must not leave the image written and the render
                // never marked done.
                let engine = self.clone();
                tokio::spawn(async move { engine.check_and_finish(accepted).await })
                    .await
                    .map_err(|_| EngineError::internal("checking the result failed"))??;
                Outcome::Merged
            }
            Ok(accepted) => {
                let engine = self.clone();
                tokio::spawn(async move { engine.commit_and_merge(accepted, bytes).await })
                    .await
                    .map_err(|_| EngineError::internal("merging the result failed"))??;
                Outcome::Merged
            }
        };
        self.notify_work();
        Ok(outcome)
    }

    /// Judges a check's result; writes the image if it was the render's last check, and renders
    /// a blocked worker's results again.
    async fn check_and_finish(self: &Arc<Self>, accepted: Accepted) -> Result<(), EngineError> {
        let verdict = self.with_durable(|c| c.checked(accepted)).await?;
        if let Some(f) = verdict.finished {
            let render = f.id;
            self.write_image(f).await?;
            tracing::info!(render, "render {render} finished");
        }
        if let Some(blocked) = verdict.blocked {
            let engine = self.clone();
            tokio::spawn(async move {
                if let Err(e) = engine.rerender(blocked).await {
                    tracing::error!("rendering a blocked worker's results again: {e}");
                }
            });
        }
        Ok(())
    }

    /// Commits an accepted result outside the state lock, then merges it under the lock, and
    /// writes the image (outside the lock) if it was the render's last.
    pub(crate) async fn commit_and_merge(&self, accepted: Accepted, bytes: Vec<u8>) -> Result<(), EngineError> {
        let render = accepted.lease.render as i64;
        let committed = self
            .writer
            .commit(accepted.stored(bytes))
            .await
            .unwrap_or_else(|_| Err("the store's writer has stopped".into()));
        let (finished, previews) = self.with(|c| Ok((c.merge(accepted, committed), c.take_previews())))?;
        for preview in previews {
            let id = preview.id;
            let written = tokio::task::spawn_blocking(move || write_image(&preview))
                .await
                .unwrap_or_else(|_| Err("writing the preview panicked".into()));
            self.with(|c| {
                c.preview_written(id, written);
                Ok(())
            })?;
        }
        if let Some(f) = finished? {
            self.write_image(f).await?;
            tracing::info!(render, "render {render} finished");
        }
        Ok(())
    }

    /// Resolves and writes a finished render's image on a blocking thread, then tells the core.
    async fn write_image(&self, f: Finished) -> Result<(), EngineError> {
        let id = f.id;
        let written = tokio::task::spawn_blocking(move || write_image(&f))
            .await
            .unwrap_or_else(|_| Err("writing the image panicked".into()));
        self.with(|c| c.image_written(id, written))
    }

    /// A finished render's EXR bytes: read outside the lock, and rebuilt from the stored results
    /// (then written again) if the file is gone.
    pub async fn image(&self, id: i64) -> Result<Vec<u8>, EngineError> {
        let (path, empty) = self.with(|c| c.image_path(id))?;
        let at = path.clone();
        let present = tokio::task::spawn_blocking(move || at.is_file())
            .await
            .map_err(|_| EngineError::internal("reading the image panicked"))?;
        if !present {
            let (film, _) = self.read(move |store| Ok(store.rebuild(id, empty)?)).await?;
            let f = self.with(|c| c.rebuilt(id, film))?;
            self.write_image(f).await?;
        }
        self.send_image(path, id).await
    }

    /// A frame's preview image (a sequence with previews first), once written.
    pub async fn preview_image(&self, id: i64) -> Result<Vec<u8>, EngineError> {
        let path = self.with(|c| c.written_preview(id))?;
        self.send_image(path, id).await
    }

    /// The bytes of render `id`'s image file at `path`, read on a blocking thread and counted as
    /// sent.
    async fn send_image(&self, path: PathBuf, id: i64) -> Result<Vec<u8>, EngineError> {
        let bytes = tokio::task::spawn_blocking(move || read_image(&path, id))
            .await
            .map_err(|_| EngineError::internal("reading the image panicked"))??;
        self.with(|c| {
            c.metrics.bytes_out += bytes.len() as u64;
            Ok(())
        })?;
        Ok(bytes)
    }

    /// Cancels a render or every frame of a sequence; returns once that is committed.
    pub async fn cancel(&self, target: Target) -> Result<(), EngineError> {
        self.with_durable(|c| c.cancel_target(target)).await
    }

    /// Pauses, resumes or reprioritises a render or a sequence for `who` ([`Core::steer`]);
    /// returns once that is committed, and wakes the workers waiting for work.
    pub async fn steer(&self, target: Target, steer: crate::core::Steer, who: &str) -> Result<(), EngineError> {
        self.with_durable(|c| c.steer(target, steer, who)).await?;
        self.notify_work();
        Ok(())
    }

    /// Asks for a submitted render's quote ([`crate::core::Core::pilot`]): the render quoted and
    /// the tiles its pilot still has to judge.
    pub async fn pilot(&self, target: Target, who: &str) -> Result<(i64, usize), EngineError> {
        let quoted = self.with_durable(|c| c.pilot(target, who)).await?;
        self.notify_work();
        Ok(quoted)
    }

    /// Retries a failed or cancelled render, or a sequence's failed and cancelled frames: each
    /// checked under the lock, its results read outside it, then put to work.
    pub async fn retry(self: &Arc<Self>, target: Target) -> Result<(), EngineError> {
        // On a task of its own: a client that hangs up between a render's two steps must not
        // leave it begun and never resumed.
        let engine = self.clone();
        tokio::spawn(async move {
            for id in engine.with(|c| c.retry_members(target))? {
                let prepared = engine.with(|c| c.begin_retry(id))?;
                engine.resume(id, prepared).await?;
            }
            engine.notify_work();
            Ok(())
        })
        .await
        .map_err(|_| EngineError::internal("the retry failed"))?
    }

    /// Refines a finished render, or every frame of a finished sequence, to more samples or a
    /// lower target error ([`crate::core::Core::begin_refine`]): each change is stored, then
    /// the render's results are read outside the lock and only the passes it adds are queued.
    pub async fn refine(self: &Arc<Self>, target: Target, to: crate::core::Refinement) -> Result<(), EngineError> {
        // On a task of its own, as a retry: a client that hangs up must not leave a render begun.
        let engine = self.clone();
        tokio::spawn(async move {
            for id in engine.with(|c| c.refine_members(target))? {
                let (prepared, commits) = engine.with_commits(|c| c.begin_refine(id, to))?;
                let prepared = prepared?;
                if let Err(e) = committed(commits).await {
                    engine.with(|c| {
                        c.abandon_refine(id);
                        Ok(())
                    })?;
                    return Err(e);
                }
                engine.resume(id, prepared).await?;
            }
            engine.notify_work();
            Ok(())
        })
        .await
        .map_err(|_| EngineError::internal("the refinement failed"))?
    }

    /// Reads a render being retried from the store and puts it to work.
    async fn resume(&self, id: i64, prepared: crate::core::Prepared) -> Result<(), EngineError> {
        let read = self.read(move |store| Ok(prepared.read(store))).await?;
        self.with_durable(|c| c.end_retry(id, read)).await
    }

    /// Renders again what a blocked worker returned ([`crate::core::Verdict`]): the renders
    /// holding its results from before this coordinator started are reopened too, the block is
    /// stored (deleting its results, and refusing any of its results still on their way to the
    /// store), and then each reopened render is retried, its film rebuilt from the results of
    /// the others.
    async fn rerender(&self, blocked: crate::core::Blocked) -> Result<(), EngineError> {
        let worker = blocked.worker.clone();
        let before = self.read(move |store| Ok(store.renders_of_worker(&worker)?)).await?;
        let mut renders = blocked.reopened;
        self.with_durable(|c| {
            renders.extend(before.into_iter().filter(|&id| c.reopen(id, &blocked.worker)));
            c.store_block(&blocked.worker, &blocked.why);
            Ok(())
        })
        .await?;
        for id in renders {
            // A result still being stored keeps a render from its retry a moment; a render put
            // back to work by another retry meanwhile is reopened again (that retry may have
            // read it before this block was stored).
            let mut tries = 0;
            let prepared = loop {
                tries += 1;
                match self.with(|c| c.begin_retry(id)) {
                    Ok(prepared) => break Some(prepared),
                    Err(EngineError::Core(CoreError::NotReady(_))) if tries < 6000 => {}
                    Err(EngineError::Core(CoreError::Invalid(_))) if tries < 6000 => {
                        if !self.with(|c| Ok(c.reopen(id, &blocked.worker)))? {
                            break None; // cancelled meanwhile: nothing to render again
                        }
                    }
                    Err(e) => {
                        tracing::error!(render = id, "render {id} could not be retried: {e}");
                        break None;
                    }
                }
                tokio::time::sleep(Duration::from_millis(10)).await;
            };
            if let Some(prepared) = prepared {
                self.resume(id, prepared).await?;
                tracing::info!(render = id, "render {id} is rendering again what the blocked worker returned");
            }
        }
        self.notify_work();
        Ok(())
    }
}

/// Waits for `commits`; the first failure becomes the answer.
async fn committed(commits: Vec<Commit>) -> Result<(), EngineError> {
    for commit in commits {
        commit
            .await
            .unwrap_or_else(|_| Err("the store's writer has stopped".into()))
            .map_err(|e| EngineError::Internal(format!("could not be stored: {e}")))?;
    }
    Ok(())
}

/// Resolves a finished render's film (denoising it when asked) and writes its EXR.
fn write_image(f: &Finished) -> Result<(), String> {
    tessera_film::write_exr(&f.final_image(), &f.path).map_err(|e| e.to_string())
}

/// The bytes of render `id`'s image file.
fn read_image(path: &std::path::Path, id: i64) -> Result<Vec<u8>, CoreError> {
    std::fs::read(path).map_err(|e| CoreError::NotFound(format!("image of render {id}: {e}")))
}
