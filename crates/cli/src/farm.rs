//! `tessera coordinator` and `tessera worker`: the two long-running processes of a farm.

use anyhow::{Context, Result, bail};
use clap::Args;
use std::net::SocketAddr;
use std::path::PathBuf;
use tessera_coordinator::{CoreConfig, Engine, MAX_CONNECTIONS, Tokens, serve};
use tessera_request::limits::{MAX_PIXELS, MAX_SPP};
use tessera_worker::{Worker, WorkerConfig};
use tokio::sync::watch;

#[derive(Args, Debug)]
pub struct CoordinatorArgs {
    /// Address to listen on.
    #[arg(long, default_value = "127.0.0.1:7878", env = "TESSERA_LISTEN")]
    pub listen: SocketAddr,
    /// Directory for the SQLite database and finished images.
    #[arg(long, default_value = "tessera-data", env = "TESSERA_DATA_DIR")]
    pub data_dir: PathBuf,
    /// Shared token clients and workers must present (at least 16 bytes; `openssl rand -hex 32`
    /// makes a good one).
    #[arg(long, env = "TESSERA_TOKEN", hide_env_values = true, value_parser = crate::secret::Token)]
    pub token: Option<String>,
    /// A separate token for workers [default: --token].
    #[arg(long, env = "TESSERA_WORKER_TOKEN", hide_env_values = true, value_parser = crate::secret::Token)]
    pub worker_token: Option<String>,
    /// Per-user tokens: a file of `NAME ROLE TOKEN-HASH` lines (roles: submit, admin, worker;
    /// `tessera token-hash` prints a token's hash). A submitter sees and acts on their own renders
    /// only. Read again on SIGHUP. --token keeps working beside it, with every right.
    #[arg(long, env = "TESSERA_TOKENS")]
    pub tokens: Option<PathBuf>,
    /// Allow listening beyond loopback without a token.
    #[arg(long, env = "TESSERA_INSECURE")]
    pub insecure: bool,
    /// Seconds a lease lives without a heartbeat before its passes return to the queue.
    #[arg(long, default_value_t = 30, value_parser = clap::value_parser!(u64).range(1..=3600), env = "TESSERA_LEASE_SECONDS")]
    pub lease_seconds: u64,
    /// Largest scene upload in bytes.
    #[arg(long, default_value_t = 1 << 30, env = "TESSERA_MAX_SCENE_BYTES")]
    pub max_scene_bytes: u64,
    /// Most triangles a scene may draw (every instance of a mesh counted).
    #[arg(long, default_value_t = 20_000_000, env = "TESSERA_MAX_TRIANGLES")]
    pub max_triangles: u64,
    /// Most memory, in bytes, a worker may need to build and render a scene (about 400 bytes a
    /// drawn triangle and 8 a texel): a small file that instances a mesh many times is refused
    /// here, before any worker builds it. The coordinator itself never builds a scene.
    #[arg(long, default_value_t = 8 << 30, env = "TESSERA_MAX_SCENE_MEMORY")]
    pub max_scene_memory: u64,
    /// Most pixels an image may have.
    #[arg(long, default_value_t = MAX_PIXELS, value_parser = clap::value_parser!(u64).range(1..=MAX_PIXELS), env = "TESSERA_MAX_PIXELS")]
    pub max_pixels: u64,
    /// Most samples per pixel a render may ask for.
    #[arg(long, default_value_t = MAX_SPP, value_parser = clap::value_parser!(u32).range(1..=MAX_SPP as i64), env = "TESSERA_MAX_SPP")]
    pub max_spp: u32,
    /// Most renders running at once.
    #[arg(long, default_value_t = 64, env = "TESSERA_MAX_RENDERS")]
    pub max_renders: usize,
    /// Most work items (tiles x passes) one render may be cut into.
    #[arg(long, default_value_t = 1 << 26, env = "TESSERA_MAX_PASSES")]
    pub max_passes: u64,
    /// Most memory, in bytes, the images of all running renders may hold together (each pixel
    /// keeps exact sums of 128 bytes: a 4096 x 4096 render takes 2 GiB).
    #[arg(long, default_value_t = 8 << 30, env = "TESSERA_MAX_FILM_BYTES")]
    pub max_film_bytes: u64,
    /// TLS certificate chain (PEM); with --tls-key, the coordinator speaks https only.
    #[arg(long, env = "TESSERA_TLS_CERT", requires = "tls_key")]
    pub tls_cert: Option<PathBuf>,
    /// TLS private key (PEM).
    #[arg(long, env = "TESSERA_TLS_KEY", requires = "tls_cert")]
    pub tls_key: Option<PathBuf>,
    /// fsync every result before acknowledging it: survives power loss, not only a killed
    /// coordinator (slower; see `tessera bench coordinator`).
    #[arg(long, env = "TESSERA_FSYNC")]
    pub fsync: bool,
    /// The key notifications are signed with (HMAC-SHA256 over the body, in the header
    /// X-Tessera-Signature: sha256=HEX); at least 16 characters. Without it the coordinator sends
    /// no notifications and refuses `submit --notify`.
    #[arg(long, env = "TESSERA_NOTIFY_KEY", hide_env_values = true, value_parser = crate::secret::Token)]
    pub notify_key: Option<String>,
    /// Where to notify about renders submitted without `--notify` (an http or https URL).
    #[arg(long, default_value = "", hide_default_value = true, env = "TESSERA_NOTIFY")]
    pub notify: String,
    /// A host notification URLs may name (repeatable, or comma-separated); without any, every
    /// host may be named, including ones inside the coordinator's own network.
    #[arg(long, env = "TESSERA_NOTIFY_HOST", value_delimiter = ',')]
    pub notify_host: Vec<String>,
    /// Most client and worker connections open at once; more are closed at once. A connection
    /// that makes no request with a valid token within 10 seconds is closed too.
    #[arg(long, default_value_t = MAX_CONNECTIONS, value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..=1_000_000), env = "TESSERA_MAX_CONNECTIONS")]
    pub max_connections: usize,
    /// Serve Prometheus metrics on this address (e.g. 127.0.0.1:9100).
    #[arg(long, env = "TESSERA_METRICS")]
    pub metrics: Option<SocketAddr>,
    /// Serve the web dashboard on this address (e.g. 127.0.0.1:8080): renders, a live preview
    /// of each as it converges, workers, and cancelling. It asks for the same token as
    /// `tessera submit`, and uses https with --tls-cert and --tls-key.
    #[arg(long, env = "TESSERA_HTTP")]
    pub http: Option<SocketAddr>,
    /// A host name the dashboard is reached by (e.g. render.example.org); repeat for more. It
    /// answers to IP addresses and localhost, and refuses other names: a web page may point its
    /// own name at this machine to read the dashboard.
    #[arg(long = "http-host", value_name = "NAME", env = "TESSERA_HTTP_HOST", value_delimiter = ',')]
    pub http_hosts: Vec<String>,
    /// A render fails when one of its passes has failed or timed out on workers this many times
    /// (`tessera retry ID` queues it again).
    #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(u32).range(1..=1000), env = "TESSERA_MAX_ATTEMPTS")]
    pub max_attempts: u32,
    /// A worker that failed this many jobs of a render gets no more of that render's jobs.
    #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(u32).range(1..=1000), env = "TESSERA_BLOCK_AFTER")]
    pub block_after: u32,
    /// Most frames of sequences waiting or rendering at once, over the farm: each holds about
    /// 2.4 KB of the coordinator's memory until it finishes (the default, about 2.4 GB).
    #[arg(long, default_value_t = 1_000_000, value_parser = clap::value_parser!(u64).range(1..), env = "TESSERA_MAX_QUEUED_FRAMES")]
    pub max_queued_frames: u64,
    /// Check workers: this fraction of jobs (0 to 1) is rendered again by a second worker and
    /// the two results compared before the render finishes. Honest workers agree to the bit; a
    /// worker whose results disagree with two others is blocked and what it returned rendered
    /// again. 0.01 costs about 1% more work; 1 renders everything twice. Needs two workers or
    /// more: with one, a render waits at its end for a second.
    #[arg(long, default_value_t = 0.0, value_parser = fraction, env = "TESSERA_VERIFY")]
    pub verify: f64,
}

/// A number from 0 to 1.
fn fraction(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if (0.0..=1.0).contains(&v) => Ok(v),
        _ => Err(format!("{s:?} is not a fraction from 0 to 1 (0.01 checks one job in a hundred)")),
    }
}

/// Resolves when the process gets SIGTERM or Ctrl-C.
pub async fn termination() {
    let ctrl_c = tokio::signal::ctrl_c();
    #[cfg(unix)]
    {
        let mut term = match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(s) => s,
            Err(_) => return std::future::pending().await,
        };
        tokio::select! {
            _ = ctrl_c => {}
            _ = term.recv() => {}
        }
    }
    #[cfg(not(unix))]
    let _ = ctrl_c.await;
}

/// What SIGHUP does to a coordinator or a worker: read the token file again, or nothing.
enum OnHangup {
    /// Read this token file again; one that no longer parses is refused, and the users as they
    /// were stay in force. The engine (once started) takes the users' weights.
    ReloadTokens(PathBuf, std::sync::Arc<std::sync::RwLock<tessera_coordinator::users::Users>>, EngineCell),
    /// Log it and go on: there is nothing to reload.
    Ignore(&'static str),
}

/// Catches SIGHUP for the rest of the process, whose default action is to end it: a worker,
/// or a coordinator without --tokens, died of a stray `kill -HUP` or a closed terminal. Called
/// before serving, so that no hang-up falls between start and the handler.
/// The engine, once a coordinator has started it.
type EngineCell = std::sync::Arc<std::sync::OnceLock<std::sync::Arc<tessera_coordinator::Engine>>>;

fn handle_hangups(what: OnHangup) -> Result<()> {
    #[cfg(unix)]
    {
        let mut hangups =
            tokio::signal::unix::signal(tokio::signal::unix::SignalKind::hangup()).context("catching SIGHUP")?;
        tokio::spawn(async move {
            while hangups.recv().await.is_some() {
                match &what {
                    OnHangup::ReloadTokens(path, users, engine) => {
                        match tessera_coordinator::users::Users::load(path) {
                            Ok(fresh) => {
                                tracing::info!("token file reloaded: {} users", fresh.len());
                                if let Some(engine) = engine.get() {
                                    engine.set_weights(fresh.weights());
                                }
                                if let Ok(mut u) = users.write() {
                                    *u = fresh;
                                }
                            }
                            Err(e) => tracing::error!("token file not reloaded, the previous users stay: {e}"),
                        }
                    }
                    OnHangup::Ignore(process) => {
                        tracing::info!(
                            "SIGHUP ignored: a {process} has nothing to reload (a coordinator reloads --tokens)"
                        )
                    }
                }
            }
        });
    }
    #[cfg(not(unix))]
    let _ = what;
    Ok(())
}

/// This build's denoiser, for a coordinator to denoise finished images with (`--denoise`).
fn denoiser() -> Result<tessera_coordinator::core::SharedDenoiser, String> {
    tessera_denoise::denoiser().map(tessera_coordinator::core::SharedDenoiser)
}

pub fn start_engine(config: CoreConfig) -> Result<std::sync::Arc<Engine>> {
    let data_dir = config.data_dir.clone();
    Engine::open(config).with_context(|| format!("opening the data directory {}", data_dir.display()))
}

/// The token value the deployment templates ship with (`deploy/k8s/secret.yaml`).
const PLACEHOLDER_TOKEN: &str = "replace-me";

pub fn run_coordinator(args: CoordinatorArgs) -> Result<()> {
    for token in [&args.token, &args.worker_token].into_iter().flatten() {
        if token.starts_with(PLACEHOLDER_TOKEN) {
            bail!(
                "the token is still the template's placeholder '{token}': set a long random one (openssl rand -hex 32)"
            );
        }
    }
    let users = match &args.tokens {
        Some(path) => Some(std::sync::Arc::new(std::sync::RwLock::new(
            tessera_coordinator::users::Users::load(path).map_err(|e| anyhow::anyhow!("the token file {e}"))?,
        ))),
        None => None,
    };
    for addr in std::iter::once(args.listen).chain(args.http) {
        if args.token.is_none() && users.is_none() && !addr.ip().is_loopback() && !args.insecure {
            bail!(
                "refusing to listen on {addr} without a token: pass --token (or TESSERA_TOKEN), or --insecure to accept anyone"
            );
        }
    }
    let runtime = tokio::runtime::Runtime::new()?;
    runtime.block_on(async {
        let engine_cell = EngineCell::default();
        handle_hangups(match (args.tokens.clone(), users.clone()) {
            (Some(path), Some(users)) => OnHangup::ReloadTokens(path, users, engine_cell.clone()),
            _ => OnHangup::Ignore("coordinator without --tokens"),
        })?;
        let mut config = CoreConfig::new(args.data_dir.clone());
        config.lease_ms = args.lease_seconds * 1000;
        config.max_scene_bytes = args.max_scene_bytes;
        config.max_triangles = args.max_triangles;
        config.max_scene_memory = args.max_scene_memory;
        config.max_pixels = args.max_pixels;
        config.max_spp = args.max_spp;
        config.max_active_renders = args.max_renders;
        config.max_passes = args.max_passes;
        config.max_film_bytes = args.max_film_bytes;
        config.max_attempts = args.max_attempts;
        config.block_after = args.block_after;
        config.verify = args.verify;
        config.max_queued_frames = args.max_queued_frames;
        config.fsync = args.fsync;
        config.denoiser = denoiser();
        if let Err(why) = &config.denoiser {
            tracing::info!("renders asking to be denoised are refused: {why}");
        }
        config.notify = tessera_coordinator::core::NotifyConfig {
            key: args.notify_key.clone().map(String::into_bytes),
            hosts: args.notify_host.clone(),
            default_url: args.notify.clone(),
        };
        if !args.notify.is_empty() {
            config.notify.check_url(&args.notify).map_err(|e| anyhow::anyhow!("--notify: {e}"))?;
        }
        let shared = start_engine(config)?;
        if let Some(users) = &users
            && let Ok(users) = users.read()
        {
            shared.set_weights(users.weights());
        }
        let _ = engine_cell.set(shared.clone());
        if let Some(addr) = args.metrics {
            let metrics = tokio::net::TcpListener::bind(addr).await.with_context(|| format!("metrics on {addr}"))?;
            eprintln!("metrics on http://{}/metrics", metrics.local_addr()?);
            tokio::spawn(tessera_coordinator::http::metrics::serve(metrics, shared.clone()));
        }
        let listener =
            tessera_coordinator::listen(args.listen).with_context(|| format!("listening on {}", args.listen))?;
        let tokens = Tokens { clients: args.token.clone(), workers: args.worker_token.or(args.token), users };
        let tls = match (&args.tls_cert, &args.tls_key) {
            (Some(cert), Some(key)) => Some((
                std::fs::read(cert).with_context(|| format!("reading {}", cert.display()))?,
                std::fs::read(key).with_context(|| format!("reading {}", key.display()))?,
            )),
            _ => None,
        };
        if let Some(addr) = args.http {
            let http = tessera_coordinator::listen(addr).with_context(|| format!("dashboard on {addr}"))?;
            let scheme = if tls.is_some() { "https" } else { "http" };
            eprintln!("dashboard on {scheme}://{}/", http.local_addr()?);
            let dashboard = tessera_coordinator::http::Dashboard::answering_to(
                shared.clone(),
                tokens.clone(),
                tls.is_some(),
                args.http_hosts.clone(),
            );
            let tls = tls.clone();
            tokio::spawn(async move {
                if let Err(e) = tessera_coordinator::http::serve(http, dashboard, tls, termination()).await {
                    tracing::error!("the dashboard stopped: {e}");
                }
            });
        }
        eprintln!("coordinator listening on {} (data in {})", listener.local_addr()?, args.data_dir.display());
        serve(listener, shared.clone(), tokens, tls, args.max_connections, termination()).await?;
        match shared.checkpoint().await {
            Ok(()) => {
                eprintln!("coordinator stopped (everything is in {})", args.data_dir.join("tessera.db").display())
            }
            Err(e) => eprintln!("coordinator stopped; {e}"),
        }
        Ok(())
    })
}

#[derive(Args, Debug)]
pub struct BackupArgs {
    /// The coordinator's data directory.
    #[arg(long, default_value = "tessera-data", env = "TESSERA_DATA_DIR")]
    pub data_dir: PathBuf,
    /// Where to write the copy: a new or empty directory. To restore, start a coordinator with
    /// `--data-dir` set to it.
    pub dest: PathBuf,
}

/// `tessera backup`: a consistent copy of a coordinator's database, safe while it serves.
pub fn run_backup(args: BackupArgs) -> Result<()> {
    let copied = tessera_coordinator::store::backup(&args.data_dir, &args.dest)?;
    println!(
        "backed up {} render(s), {} result(s) and {} scene(s) ({} bytes) into {}",
        copied.renders,
        copied.results,
        copied.scenes,
        copied.bytes,
        args.dest.join("tessera.db").display()
    );
    eprintln!("to restore: tessera coordinator --data-dir {}", args.dest.display());
    Ok(())
}

#[derive(Args, Debug)]
pub struct WorkerArgs {
    /// The coordinator's URL.
    #[arg(long, default_value = "http://127.0.0.1:7878", env = "TESSERA_COORDINATOR")]
    pub coordinator: String,
    /// Render threads [default: all cores].
    #[arg(long, default_value_t = 0, hide_default_value = true, env = "TESSERA_THREADS")]
    pub threads: usize,
    /// Name shown in `tessera workers` [default: the host name and a short id, e.g. node12-3f9a].
    #[arg(long, env = "TESSERA_WORKER_NAME")]
    pub name: Option<String>,
    /// Token the coordinator expects from workers.
    #[arg(long, env = "TESSERA_TOKEN", hide_env_values = true, value_parser = crate::secret::Token)]
    pub token: Option<String>,
    /// CA certificate (PEM) to trust for an https:// coordinator.
    #[arg(long, env = "TESSERA_CA")]
    pub ca: Option<PathBuf>,
    /// Serve /healthz, /readyz and Prometheus /metrics on this address (e.g. 0.0.0.0:9101).
    #[arg(long, env = "TESSERA_METRICS")]
    pub metrics: Option<SocketAddr>,
    /// The worker's pool: renders submitted with `--pool` of it come to it first, and only to
    /// workers of their pool (it takes renders of no pool too).
    #[arg(long, default_value = "", hide_default_value = true, env = "TESSERA_POOL",
          value_parser = |s: &str| tessera_request::placement::check_pool(s).map(|()| s.to_string()))]
    pub pool: String,
    /// A tag for `submit --require` to match: KEY or KEY=VALUE (repeatable, or comma-separated).
    /// cpus, mem (in GiB, as 64G) and CPU features (avx2, fma, avx512f) are found at start.
    #[arg(long, env = "TESSERA_TAG", value_delimiter = ',', value_parser = tessera_request::placement::Tag::parse)]
    pub tag: Vec<tessera_request::placement::Tag>,
}

pub fn worker_config(args: &WorkerArgs) -> WorkerConfig {
    let threads =
        if args.threads == 0 { std::thread::available_parallelism().map_or(1, |n| n.get()) } else { args.threads };
    let name = args.name.clone().unwrap_or_else(|| {
        let host = std::fs::read_to_string("/etc/hostname").map_or("worker".into(), |h| h.trim().to_string());
        // Two workers on one host (or started without names on hosts named alike) must be told
        // apart in `tessera workers`: the host and a short id of this process.
        let nanos = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_nanos());
        let short = blake3::hash(format!("{nanos} {}", std::process::id()).as_bytes()).to_hex();
        format!("{host}-{}", &short[..4])
    });
    WorkerConfig {
        coordinator: args.coordinator.clone(),
        threads,
        name,
        token: args.token.clone(),
        scene_cache: 4,
        ca: args.ca.clone(),
        pool: args.pool.clone(),
        tags: tessera_worker::tags::merged(tessera_worker::tags::found(threads), &args.tag),
    }
}

pub fn run_worker(args: WorkerArgs) -> Result<()> {
    let config = worker_config(&args);
    tessera_request::placement::check_tags(&config.tags).map_err(|e| anyhow::anyhow!("--tag: {e}"))?;
    let runtime = tokio::runtime::Runtime::new()?;
    runtime.block_on(async {
        handle_hangups(OnHangup::Ignore("worker"))?;
        let worker = Worker::new(config)?;
        let health = worker.health();
        if let Some(addr) = args.metrics {
            let listener = tokio::net::TcpListener::bind(addr).await.with_context(|| format!("metrics on {addr}"))?;
            eprintln!("health and metrics on http://{}/", listener.local_addr()?);
            tokio::spawn(tessera_worker::serve_probes(listener, health.clone()));
        }
        eprintln!("worker {} working for {}", worker.id(), args.coordinator);
        let (tx, rx) = watch::channel(false);
        tokio::spawn(async move {
            termination().await;
            health.stopping.store(true, std::sync::atomic::Ordering::Relaxed);
            eprintln!("worker: finishing the job in hand, handing back the one leased ahead, then stopping");
            let _ = tx.send(true);
        });
        worker.run(rx).await?;
        Ok(())
    })
}

/// The data directories of `render --workers` are this prefix and the process id.
const LOCAL_FARM_PREFIX: &str = "tessera-local-farm-";

/// Removes the data directories that `render --workers` runs left behind when they were killed
/// (SIGKILL, or Ctrl-C, which ends the process without unwinding): those whose process is gone.
/// Only where `/proc` says which processes live; elsewhere nothing is removed.
fn remove_stale_local_farms(dir: &std::path::Path) {
    if !std::path::Path::new("/proc/self").exists() {
        return;
    }
    let Ok(entries) = std::fs::read_dir(dir) else { return };
    for entry in entries.flatten() {
        let name = entry.file_name();
        let Some(pid) =
            name.to_str().and_then(|n| n.strip_prefix(LOCAL_FARM_PREFIX)).and_then(|p| p.parse::<u32>().ok())
        else {
            continue;
        };
        if !std::path::Path::new(&format!("/proc/{pid}")).exists() {
            let _ = std::fs::remove_dir_all(entry.path());
        }
    }
}

/// After an interrupt: writes what the in-process farm merged of still `id` to `out` (EXR and
/// PNG), its header marked partial, and fails saying so; a sequence keeps the frames already
/// written.
fn write_so_far(engine: &Engine, id: &str, out: &std::path::Path) -> Result<()> {
    eprintln!("\ninterrupted: writing what has been rendered");
    let Ok(still) = id.parse::<i64>() else {
        bail!("interrupted: the frames written so far are kept; the frames in progress were not written");
    };
    let so_far = engine.with(|c| c.so_far(still)).map_err(|e| anyhow::anyhow!("interrupted, nothing written: {e}"))?;
    let Some((image, samples)) = so_far else {
        bail!("interrupted before any sample was rendered: nothing written");
    };
    tessera_film::write_exr(&image, out).with_context(|| format!("writing {}", out.display()))?;
    let png = out.with_extension("png");
    tessera_film::write_png(&image, &png).with_context(|| format!("writing {}", png.display()))?;
    bail!(
        "interrupted: wrote {} and {} after {samples} samples, marked partial in the header",
        out.display(),
        png.display()
    )
}

/// `tessera render --workers K`: a coordinator on a loopback port with a throw-away data
/// directory, K workers, and the client path of `submit`; the same code as a real farm.
pub fn render_with_local_farm(args: &crate::render::RenderArgs, out: &std::path::Path) -> Result<()> {
    let runtime = tokio::runtime::Runtime::new()?;
    runtime.block_on(async {
        remove_stale_local_farms(&std::env::temp_dir());
        let data_dir = std::env::temp_dir().join(format!("{LOCAL_FARM_PREFIX}{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&data_dir);
        let shared = start_engine(CoreConfig { denoiser: denoiser(), ..CoreConfig::new(data_dir.clone()) })?;
        let engine = shared.clone();
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
        let url = format!("http://{}", listener.local_addr()?);
        let (stop_tx, mut stop_rx) = watch::channel(false);
        let mut server_stop = stop_rx.clone();
        let server = tokio::spawn(serve(listener, shared, Tokens::default(), None, MAX_CONNECTIONS, async move {
            let _ = server_stop.changed().await;
        }));
        let cores =
            if args.threads == 0 { std::thread::available_parallelism().map_or(1, |n| n.get()) } else { args.threads };
        let per_worker = (cores / args.workers as usize).max(1);
        let mut workers = Vec::new();
        for i in 0..args.workers {
            let config = WorkerConfig {
                coordinator: url.clone(),
                threads: per_worker,
                name: format!("local{i}"),
                token: None,
                scene_cache: 2,
                ca: None,
                pool: String::new(),
                tags: Vec::new(),
            };
            let worker = Worker::new(config)?;
            workers.push(tokio::spawn(worker.run(stop_rx.clone())));
        }
        let connection =
            crate::client::Connection { coordinator: url, token: None, ca: None, wait_for_coordinator: 0.0 };
        let result = async {
            let mut client = connection.connect().await?;
            let (id, hint) =
                crate::client::submit(&mut client, &args.scene, &args.options, &args.animation, &Default::default())
                    .await?;
            // Ctrl-C (or SIGTERM) writes what the farm has merged, as `tessera render` does.
            match crate::client::follow(&mut client, &id, out, args.quiet, hint.as_ref()).await {
                Err(e) if e.is::<crate::client::Interrupted>() => write_so_far(&engine, &id, out),
                followed => followed,
            }
        }
        .await;
        // The render is over (or failed): nothing a worker holds matters any more, and a
        // graceful stop would wait out each worker's last long poll (2 s).
        let _ = stop_tx.send(true);
        let _ = stop_rx.changed().await;
        for w in workers {
            w.abort();
            let _ = w.await;
        }
        // Workers are gone; nothing in flight matters any more (a graceful stop would wait out
        // their last long-poll).
        server.abort();
        let _ = std::fs::remove_dir_all(&data_dir);
        result
    })
}
