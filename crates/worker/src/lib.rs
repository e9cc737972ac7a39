//! The worker: a loop that leases a job from the coordinator (long poll), fetches and caches its
//! scene by hash, renders the job's passes on all its threads, heartbeats while it works, and
//! returns the tile's exact sums. It holds nothing that matters: kill it and its leases expire.
//! This file is the async shell (connections, leases, heartbeats, reports); what a job does is
//! the synchronous core in `job.rs`.

pub mod job;
pub mod tags;

pub use job::{JobPlan, SceneCache};

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tessera_client::{ANSWER_WITHIN, Auth, Backoff, connect_channel, diagnose, next_within, within};
use tessera_proto::PROTOCOL_VERSION;
use tessera_proto::probe::Page;
use tessera_proto::sums::encode_tile_sums;
use tessera_proto::v1::work_service_client::WorkServiceClient;
use tessera_proto::v1::*;
use tessera_render::Scene;
use tokio::sync::watch;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::Channel;

pub type Client = WorkServiceClient<InterceptedService<Channel, Auth>>;

#[derive(Clone, Debug)]
pub struct WorkerConfig {
    pub coordinator: String,
    pub threads: usize,
    pub name: String,
    pub token: Option<String>,
    /// Scenes kept loaded (least recently used goes first).
    pub scene_cache: usize,
    /// PEM file of the certificate authority that signed the coordinator's TLS certificate.
    pub ca: Option<std::path::PathBuf>,
    /// Its pool (empty: none) and tags ([`tags`]): renders with a pool or requirements go only
    /// to workers that match.
    pub pool: String,
    pub tags: Vec<tessera_request::placement::Tag>,
}

/// Largest scene a worker downloads (the coordinator's `--max-scene-bytes` cannot exceed it).
pub const MAX_SCENE_BYTES: usize = 4 << 30;

#[derive(Debug, thiserror::Error)]
pub enum WorkerError {
    #[error("cannot reach the coordinator at {0}: {1}")]
    Connect(String, String),
    #[error("the coordinator refused: {0}")]
    Refused(String),
    /// A call to the coordinator failed: the session ends and the worker reconnects.
    #[error("{0}")]
    Rpc(String),
    /// This job could not be rendered: reported to the coordinator, and the worker goes on.
    #[error("{0}")]
    Job(String),
}

pub struct Worker {
    config: WorkerConfig,
    id: String,
    pool: Arc<rayon::ThreadPool>,
    cache: SceneCache,
    samples_per_second: f64,
    health: Arc<Health>,
}

/// What a worker's `/healthz`, `/readyz` and `/metrics` report.
#[derive(Default)]
pub struct Health {
    /// The last call to the coordinator succeeded.
    pub connected: AtomicBool,
    /// Shutdown has begun: the worker takes no new work.
    pub stopping: AtomicBool,
    pub jobs_done: AtomicU64,
    pub samples_done: AtomicU64,
    /// The coordinator answered a call in the current session (so a failure after it is not
    /// a failure to reach it, and the retry delay starts afresh).
    pub answered: AtomicBool,
}

impl Health {
    /// `/healthz`: the process answers (a worker with no coordinator is alive, just idle);
    /// `/readyz`: connected and not stopping.
    pub fn page(&self, path: &str) -> Page {
        let connected = self.connected.load(Ordering::Relaxed);
        let stopping = self.stopping.load(Ordering::Relaxed);
        match path {
            "/healthz" => Page::ok("ok\n"),
            "/readyz" if connected && !stopping => Page::ok("ready\n"),
            "/readyz" if stopping => Page::unavailable("stopping\n"),
            "/readyz" => Page::unavailable("not connected to the coordinator\n"),
            "/metrics" => Page::ok(format!(
                "# HELP tessera_worker_connected 1 when the last call to the coordinator succeeded.\n\
                 # TYPE tessera_worker_connected gauge\ntessera_worker_connected {}\n\
                 # HELP tessera_worker_jobs_total Jobs rendered and returned.\n\
                 # TYPE tessera_worker_jobs_total counter\ntessera_worker_jobs_total {}\n\
                 # HELP tessera_worker_samples_total Pixel samples rendered and returned.\n\
                 # TYPE tessera_worker_samples_total counter\ntessera_worker_samples_total {}\n",
                connected as u8,
                self.jobs_done.load(Ordering::Relaxed),
                self.samples_done.load(Ordering::Relaxed),
            )),
            _ => Page::not_found(),
        }
    }
}

/// Serves `/healthz`, `/readyz` and `/metrics` of a worker until the task is dropped.
pub async fn serve_probes(listener: tokio::net::TcpListener, health: Arc<Health>) {
    tessera_proto::probe::serve(listener, Arc::new(move |path: &str| health.page(path))).await
}

impl Worker {
    pub fn new(config: WorkerConfig) -> Result<Self, WorkerError> {
        if let Some(token) = &config.token {
            tessera_proto::token::check_token(token).map_err(WorkerError::Refused)?;
        }
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(config.threads)
            .build()
            .map_err(|e| WorkerError::Job(e.to_string()))?;
        let scene_cache = config.scene_cache;
        let nonce = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_nanos());
        let id = format!("{}-{}-{:x}", config.name, std::process::id(), nonce & 0xFFFF_FFFF);
        Ok(Self {
            config,
            id,
            pool: Arc::new(pool),
            cache: SceneCache::new(scene_cache),
            samples_per_second: 0.0,
            health: Arc::default(),
        })
    }

    pub fn id(&self) -> &str {
        &self.id
    }

    pub fn health(&self) -> Arc<Health> {
        self.health.clone()
    }

    async fn connect(&self) -> Result<Client, WorkerError> {
        let url = self.config.coordinator.clone();
        let channel = connect_channel(&url, self.config.ca.as_deref())
            .await
            .map_err(|e| WorkerError::Connect(url.clone(), e.to_string()))?;
        Ok(WorkServiceClient::with_interceptor(channel, Auth::new(self.config.token.as_deref()))
            .max_decoding_message_size(64 << 20))
    }

    /// Works until `shutdown` turns true; a job in hand is finished first. Every failed session
    /// (no connection, or a connection that failed before the coordinator answered) waits a
    /// capped, jittered, growing delay before the next try, and says what looks wrong.
    pub async fn run(mut self, mut shutdown: watch::Receiver<bool>) -> Result<(), WorkerError> {
        let mut backoff = Backoff::new(&self.id);
        while !*shutdown.borrow() {
            let failure = match self.connect().await {
                Ok(mut client) => {
                    tracing::debug!(worker = %self.id, "opened a connection to {}", self.config.coordinator);
                    self.health.answered.store(false, Ordering::Relaxed);
                    match self.work(&mut client, &mut shutdown).await {
                        Ok(()) => continue,
                        Err(WorkerError::Refused(m)) => return Err(WorkerError::Refused(m)),
                        Err(e) => e.to_string(),
                    }
                }
                Err(e) => e.to_string(),
            };
            self.health.connected.store(false, Ordering::Relaxed);
            if self.health.answered.swap(false, Ordering::Relaxed) {
                backoff.reset();
            }
            let wait = backoff.next_delay();
            let hint = match backoff.failures {
                // Say what is wrong once per run of failures, not on every retry.
                1 => diagnose(&self.config.coordinator).await.map(|h| format!(" ({h})")).unwrap_or_default(),
                _ => String::new(),
            };
            tracing::warn!("{failure}{hint}; retrying in {:.1} s", wait.as_secs_f64());
            tokio::select! {
                _ = tokio::time::sleep(wait) => {}
                _ = shutdown.changed() => {}
            }
        }
        self.health.stopping.store(true, Ordering::Relaxed);
        tracing::info!(worker = %self.id, "stopped");
        Ok(())
    }

    fn lease_request(&self) -> LeaseRequest {
        LeaseRequest {
            protocol_version: PROTOCOL_VERSION,
            worker_id: self.id.clone(),
            worker_name: self.config.name.clone(),
            threads: self.config.threads as u32,
            samples_per_second: self.samples_per_second,
            wait_ms: 2000,
            pool: self.config.pool.clone(),
            tags: self.config.tags.iter().map(ToString::to_string).collect(),
        }
    }

    /// Jobs on one connection. The next lease is requested while the current job renders, so the
    /// render threads never wait for a round trip; one heartbeat task keeps every held lease alive.
    async fn work(&mut self, client: &mut Client, shutdown: &mut watch::Receiver<bool>) -> Result<(), WorkerError> {
        let held: Arc<Mutex<Vec<String>>> = Arc::default();
        let period_ms = Arc::new(AtomicU64::new(1000));
        let heartbeat = {
            let (mut c, held, period_ms, worker_id) =
                (client.clone(), held.clone(), period_ms.clone(), self.id.clone());
            tokio::spawn(async move {
                loop {
                    tokio::time::sleep(Duration::from_millis(period_ms.load(Ordering::Relaxed))).await;
                    let lease_ids = held.lock().map(|h| h.clone()).unwrap_or_default();
                    if lease_ids.is_empty() {
                        continue;
                    }
                    let req = HeartbeatRequest {
                        protocol_version: PROTOCOL_VERSION,
                        worker_id: worker_id.clone(),
                        lease_ids,
                    };
                    if within(Duration::from_secs(10), "a heartbeat", c.heartbeat(req)).await.is_err() {
                        break;
                    }
                }
            })
        };
        let result = self.job_loop(client, shutdown, &held, &period_ms).await;
        heartbeat.abort();
        result
    }

    async fn job_loop(
        &mut self,
        client: &mut Client,
        shutdown: &mut watch::Receiver<bool>,
        held: &Arc<Mutex<Vec<String>>>,
        period_ms: &Arc<AtomicU64>,
    ) -> Result<(), WorkerError> {
        type LeaseTask = tokio::task::JoinHandle<Result<Option<Job>, tonic::Status>>;
        let spawn_lease = |client: &Client, request: LeaseRequest| -> LeaseTask {
            let (mut c, held) = (client.clone(), held.clone());
            tokio::spawn(async move {
                let limit = ANSWER_WITHIN + Duration::from_millis(request.wait_ms as u64);
                let job = within(limit, "a lease request", c.lease(request)).await?.into_inner().job;
                if let (Some(j), Ok(mut h)) = (&job, held.lock()) {
                    h.push(j.lease_id.clone());
                }
                Ok(job)
            })
        };
        let mut ahead: Option<LeaseTask> = None;
        while !*shutdown.borrow() {
            let mut task = match ahead.take() {
                Some(t) => t,
                None => spawn_lease(client, self.lease_request()),
            };
            let job = tokio::select! {
                r = &mut task => r.map_err(|_| WorkerError::Rpc("lease task failed".into()))?.map_err(refusal)?,
                _ = shutdown.changed() => {
                    ahead = Some(task);
                    break;
                }
            };
            self.health.connected.store(true, Ordering::Relaxed);
            if !self.health.answered.swap(true, Ordering::Relaxed) {
                tracing::info!(worker = %self.id, "connected to {}", self.config.coordinator);
            }
            let Some(job) = job else { continue };
            period_ms.store((job.lease_seconds.max(1) as u64 * 1000 / 3).max(200), Ordering::Relaxed);
            ahead = Some(spawn_lease(client, self.lease_request()));
            // The job in hand is finished even if shutdown comes meanwhile.
            let lease_id = job.lease_id.clone();
            let done = self.one_job(client, job).await;
            if let Ok(mut h) = held.lock() {
                h.retain(|id| id != &lease_id);
            }
            match done {
                Ok(()) => {}
                // The job failed here; the coordinator hears why at once (instead of when the
                // lease expires), counts it against the job and this worker, and work goes on.
                Err(WorkerError::Job(error)) => {
                    tracing::warn!(lease = %lease_id, "could not render a job: {error}");
                    let request =
                        FailRequest { protocol_version: PROTOCOL_VERSION, worker_id: self.id.clone(), lease_id, error };
                    within(Duration::from_secs(10), "a failure report", client.fail(request)).await.map_err(refusal)?;
                }
                Err(e) => {
                    if let Some(t) = ahead.take() {
                        t.abort();
                    }
                    return Err(e);
                }
            }
        }
        // Shutting down: a job leased ahead is handed back unrendered, so its passes go to other
        // workers now instead of when its lease expires; with or without one, the release is the
        // worker's goodbye (the coordinator shows it stopped, not lost).
        let mut lease_ids = Vec::new();
        if let Some(task) = ahead
            && let Ok(Ok(Some(job))) = task.await
        {
            lease_ids.push(job.lease_id);
        }
        let said = if lease_ids.is_empty() { "" } else { "handed back the job leased ahead and " };
        let request = ReleaseRequest { protocol_version: PROTOCOL_VERSION, worker_id: self.id.clone(), lease_ids };
        match within(Duration::from_secs(10), "a release", client.release(request)).await {
            Ok(r) => {
                tracing::info!(worker = %self.id, passes = r.into_inner().passes, "{said}said goodbye to the coordinator")
            }
            Err(e) => tracing::warn!("could not say goodbye to the coordinator: {}", e.message()),
        }
        Ok(())
    }

    async fn one_job(&mut self, client: &mut Client, job: Job) -> Result<(), WorkerError> {
        let plan = JobPlan::from_job(&job).map_err(WorkerError::Job)?;
        let scene = self.scene(client, &plan).await?;
        let began = Instant::now();
        let (pool, threads) = (self.pool.clone(), self.config.threads.max(1) as u32);
        let (settings, tile, samples) = (plan.setup.settings.clone(), plan.tile, plan.samples.clone());
        let sums =
            blocking(move || job::render_split(&pool, threads, &scene, &settings, tile, samples), "render").await?;
        let secs = began.elapsed().as_secs_f64().max(1e-6);
        let count = plan.samples.len() as u64 * tile.pixel_count() as u64;
        self.samples_per_second = count as f64 / secs;
        let bytes = encode_tile_sums(&sums);
        let chunks: Vec<CompleteRequest> = bytes
            .chunks(1 << 20)
            .map(|c| CompleteRequest {
                protocol_version: PROTOCOL_VERSION,
                worker_id: self.id.clone(),
                lease_id: job.lease_id.clone(),
                chunk: Some(TileSumsChunk { data: c.to_vec() }),
                render_seconds: secs,
            })
            .collect();
        let merged = within(ANSWER_WITHIN, "a result", client.complete(tokio_stream::iter(chunks)))
            .await
            .map_err(refusal)?
            .into_inner()
            .merged;
        self.health.jobs_done.fetch_add(1, Ordering::Relaxed);
        self.health.samples_done.fetch_add(count, Ordering::Relaxed);
        tracing::debug!(lease = %job.lease_id, merged, "job done in {secs:.3} s");
        Ok(())
    }

    /// The scene a job renders: posed from the cache, else posed (and its BVH built) from the
    /// kept file, else from the file fetched from the coordinator.
    async fn scene(&mut self, client: &mut Client, plan: &JobPlan) -> Result<Arc<Scene>, WorkerError> {
        let key = plan.scene_key();
        if let Some(scene) = self.cache.posed(&key) {
            return Ok(scene);
        }
        let source = match self.cache.source(&plan.scene_hash) {
            Some(source) => source,
            None => {
                let bytes = self.fetch_scene(client, &plan.scene_hash).await?;
                let (name, pool) = (format!("scene {}", plan.scene_hash), self.pool.clone());
                let source = blocking(
                    move || pool.install(|| tessera_scene::open_packed(&bytes, &name).map_err(|e| e.to_string())),
                    "scene loading",
                )
                .await?;
                let source = Arc::new(source);
                self.cache.keep_source(&plan.scene_hash, source.clone());
                source
            }
        };
        // Decoding and building run on the worker's own threads, as many as it renders with.
        let (to_pose, pool) = (plan.clone(), self.pool.clone());
        let scene = Arc::new(blocking(move || pool.install(|| job::pose(&source, &to_pose)), "scene posing").await?);
        self.cache.keep_posed(key, scene.clone());
        Ok(scene)
    }

    /// The packed scene `hash`, from the coordinator.
    async fn fetch_scene(&self, client: &mut Client, hash: &str) -> Result<Vec<u8>, WorkerError> {
        let request = FetchSceneRequest { protocol_version: PROTOCOL_VERSION, hash: hash.to_string() };
        let mut stream =
            within(ANSWER_WITHIN, "a scene request", client.fetch_scene(request)).await.map_err(refusal)?.into_inner();
        let mut bytes = Vec::new();
        while let Some(chunk) = next_within("a scene chunk", &mut stream).await.map_err(refusal)? {
            if bytes.len() + chunk.data.len() > MAX_SCENE_BYTES {
                return Err(WorkerError::Job(format!("scene {hash} is over {MAX_SCENE_BYTES} bytes")));
            }
            bytes.extend_from_slice(&chunk.data);
        }
        job::check_scene_bytes(hash, &bytes).map_err(WorkerError::Job)?;
        Ok(bytes)
    }
}

/// Runs `f` (rendering, loading: seconds of CPU) off the async threads; its error fails the job.
async fn blocking<T: Send + 'static>(
    f: impl FnOnce() -> Result<T, String> + Send + 'static,
    what: &str,
) -> Result<T, WorkerError> {
    tokio::task::spawn_blocking(f)
        .await
        .map_err(|_| WorkerError::Job(format!("{what} failed")))?
        .map_err(WorkerError::Job)
}

/// Statuses the worker cannot fix by retrying stop it with a message; others reconnect.
fn refusal(s: tonic::Status) -> WorkerError {
    match s.code() {
        tonic::Code::Unauthenticated | tonic::Code::PermissionDenied | tonic::Code::FailedPrecondition => {
            WorkerError::Refused(s.message().to_string())
        }
        _ => WorkerError::Rpc(format!("{}: {}", s.code(), s.message())),
    }
}
