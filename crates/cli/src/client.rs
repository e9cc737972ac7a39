//! Client commands: `submit`, `status`, `watch`, `fetch`, `cancel`, `workers`.

use crate::render::BlackImageHint;
use anyhow::{Context, Result, bail};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use tessera_client::{ANSWER_WITHIN, Auth, ConnectError, within};
use tessera_local::animation::{AnimationArgs, frame_path, output_pattern};
use tessera_local::options::RenderOptions;
use tessera_proto::PROTOCOL_VERSION;
use tessera_proto::v1::render_service_client::RenderServiceClient;
use tessera_proto::v1::*;
use tessera_request::placement::Placement;
pub use tessera_request::printable;
use tessera_request::{PreviewFirst, Submission};
use tonic::service::interceptor::InterceptedService;
use tonic::transport::Channel;

pub type Client = RenderServiceClient<InterceptedService<Channel, Auth>>;

#[derive(Args, Debug, Clone)]
pub struct Connection {
    /// The coordinator's URL.
    #[arg(long, default_value = "http://127.0.0.1:7878", env = "TESSERA_COORDINATOR")]
    pub coordinator: String,
    /// Token the coordinator expects from clients.
    #[arg(long, env = "TESSERA_TOKEN", hide_env_values = true, value_parser = crate::secret::Token)]
    pub token: Option<String>,
    /// CA certificate (PEM) to trust for an https:// coordinator.
    #[arg(long, env = "TESSERA_CA")]
    pub ca: Option<PathBuf>,
    /// Seconds to keep trying while the coordinator does not answer (it may be starting).
    #[arg(long, default_value_t = 10.0, value_parser = parse_wait, env = "TESSERA_WAIT_FOR_COORDINATOR")]
    pub wait_for_coordinator: f64,
}

fn parse_wait(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if (0.0..=86_400.0).contains(&v) => Ok(v),
        _ => Err(format!("'{s}' is not a number of seconds between 0 and 86400")),
    }
}

impl Connection {
    pub async fn connect(&self) -> Result<Client> {
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs_f64(self.wait_for_coordinator);
        let mut said = false;
        let channel = loop {
            match tessera_client::connect_channel(&self.coordinator, self.ca.as_deref()).await {
                Ok(channel) => break channel,
                Err(ConnectError::Unreachable(_)) if std::time::Instant::now() < deadline => {
                    if !said {
                        eprintln!("waiting for the coordinator at {} ...", self.coordinator);
                        said = true;
                    }
                    tokio::time::sleep(std::time::Duration::from_millis(250)).await;
                }
                Err(e) => bail!("cannot reach the coordinator at {}: {e}", self.coordinator),
            }
        };
        let _ = COORDINATOR.set(self.coordinator.clone());
        Ok(RenderServiceClient::with_interceptor(channel, Auth::new(self.token.as_deref()))
            .max_decoding_message_size(8 << 20))
    }
}

fn status_error(s: tonic::Status) -> anyhow::Error {
    match s.code() {
        tonic::Code::DeadlineExceeded => anyhow::anyhow!("{} (is it overloaded or stuck?)", s.message()),
        tonic::Code::Unavailable => {
            anyhow::anyhow!(
                "the coordinator stopped answering or closed the connection: it may be restarting, or at its \
                 connection limit (--max-connections) ({})",
                s.message()
            )
        }
        _ => anyhow::anyhow!("the coordinator refused: {}", s.message()),
    }
}

/// The coordinator this process talks to, for [`explain`].
static COORDINATOR: std::sync::OnceLock<String> = std::sync::OnceLock::new();

/// A failed call's status, with what answers at the coordinator's address when the failure looks
/// like the wrong protocol (plain HTTP at a TLS coordinator, a metrics port).
async fn explain(s: tonic::Status) -> anyhow::Error {
    // An HTTP server that is not gRPC answers without a grpc-status (its 404 reads as
    // Unimplemented).
    let transport = matches!(
        s.code(),
        tonic::Code::Internal | tonic::Code::Unknown | tonic::Code::Unavailable | tonic::Code::Cancelled
    ) || s.message().contains("grpc-status header missing");
    if transport
        && let Some(url) = COORDINATOR.get()
        && let Some(hint) = tessera_client::diagnose(url).await
    {
        return anyhow::anyhow!("cannot talk to the coordinator at {url}: {hint} ({})", s.message());
    }
    status_error(s)
}

/// A call that gets one answer, within [`ANSWER_WITHIN`].
pub(crate) async fn answer<T>(
    what: &str,
    call: impl std::future::Future<Output = Result<tonic::Response<T>, tonic::Status>>,
) -> Result<T> {
    match within(ANSWER_WITHIN, what, call).await {
        Ok(response) => Ok(response.into_inner()),
        Err(s) => Err(explain(s).await),
    }
}

/// The next message of a stream, within [`ANSWER_WITHIN`].
pub(crate) async fn next_of<T>(what: &str, stream: &mut tonic::Streaming<T>) -> Result<Option<T>> {
    tessera_client::next_within(what, stream).await.map_err(status_error)
}

#[derive(Args, Debug)]
#[command(group(clap::ArgGroup::new("preview_size").args(["preview_spp", "preview_target_error"])))]
pub struct SubmitArgs {
    /// Scene: a .gltf (packed with its files), a .glb, or builtin:NAME.
    pub scene: String,
    #[command(flatten)]
    pub options: RenderOptions,
    #[command(flatten)]
    pub animation: AnimationArgs,
    #[command(flatten)]
    pub connection: Connection,
    /// Output EXR path; the PNG preview gets the same stem. A run of #s in the name stands for
    /// the frame number (shot.####.exr) [default: render.exr, or render.####.exr for a sequence].
    #[arg(long, env = "TESSERA_OUT")]
    pub out: Option<PathBuf>,
    /// Print the render id and return without waiting.
    #[arg(long, env = "TESSERA_DETACH")]
    pub detach: bool,
    /// Higher priorities are served first (-1000 to 1000); among equal ones, the render
    /// submitted first. `tessera priority` changes it later.
    #[arg(long, default_value_t = 0, env = "TESSERA_PRIORITY", allow_negative_numbers = true,
          value_parser = clap::value_parser!(i32).range(-1000..=1000))]
    pub priority: i32,
    /// A name for the render in listings and on the dashboard (e.g. "shot 12, take 3").
    #[arg(long, default_value = "", hide_default_value = true, env = "TESSERA_RENDER_NAME")]
    pub name: String,
    /// Only workers of this pool (`tessera worker --pool`) take it.
    #[arg(long, default_value = "", hide_default_value = true, env = "TESSERA_POOL",
          value_parser = |s: &str| tessera_request::placement::check_pool(s).map(|()| s.to_string()))]
    pub pool: String,
    /// What a worker must have to take it (repeatable, or comma-separated): a tag KEY, KEY=VALUE,
    /// or KEY>=AMOUNT, e.g. mem>=32G (workers find cpus, mem and CPU features at start).
    #[arg(long, env = "TESSERA_REQUIRE", value_delimiter = ',', value_parser = tessera_request::placement::Requirement::parse)]
    pub require: Vec<tessera_request::placement::Requirement>,
    /// Previews first (with --frames): every N-th frame (the first, then every N-th) is rendered
    /// to --preview-spp samples before the rest, and downloaded as NAME.preview.exr; then every
    /// frame goes on to its full samples, to the same image as without previews.
    #[arg(long, value_name = "N", requires = "preview_size", env = "TESSERA_PREVIEW_EVERY")]
    pub preview_every: Option<u32>,
    /// The previews' samples per pixel (rounded up to whole passes of 16).
    #[arg(long, value_name = "SPP", requires = "preview_every", env = "TESSERA_PREVIEW_SPP")]
    pub preview_spp: Option<u32>,
    /// Or the relative error the previews stop at (as `status` estimates a frame's), e.g. 0.05.
    #[arg(
        long,
        value_name = "E",
        requires = "preview_every",
        conflicts_with = "preview_spp",
        env = "TESSERA_PREVIEW_TARGET_ERROR"
    )]
    pub preview_target_error: Option<f32>,
    /// A URL (http or https) the coordinator POSTs a signed JSON event to when the render (or
    /// the whole sequence) is done, fails or is cancelled.
    #[arg(long, default_value = "", hide_default_value = true, env = "TESSERA_NOTIFY")]
    pub notify: String,
    /// No progress bar.
    #[arg(long, short, env = "TESSERA_QUIET")]
    pub quiet: bool,
    /// Say what the render will take, and submit nothing: a short pilot on this machine predicts
    /// its samples (with a range) and their core-seconds, and the farm's live workers, at their
    /// measured speeds, the wall time.
    #[arg(long, env = "TESSERA_QUOTE")]
    pub quote: bool,
    /// Submit it paused: no worker takes it until `tessera resume`. Prints its id and returns;
    /// `tessera quote ID` meanwhile says what it will take, from a pilot on the farm.
    #[arg(long, env = "TESSERA_PAUSED", conflicts_with = "quote")]
    pub paused: bool,
}

pub fn run_submit(args: SubmitArgs) -> Result<()> {
    if args.quote {
        return crate::quote::run_quote(&args);
    }
    let pattern = output_pattern(args.out.as_deref(), args.animation.sequence())?;
    let runtime = tokio::runtime::Runtime::new()?;
    runtime.block_on(async {
        let mut client = args.connection.connect().await?;
        let queue = Queue {
            priority: args.priority,
            name: args.name.clone(),
            placement: Placement { pool: args.pool.clone(), requires: args.require.clone() },
            notify: args.notify.clone(),
            preview: args.preview_every.map(|every| PreviewFirst {
                every,
                spp: args.preview_spp.unwrap_or(0),
                target_error: args.preview_target_error.unwrap_or(0.0),
            }),
            paused: args.paused,
        };
        let (id, hint) = submit(&mut client, &args.scene, &args.options, &args.animation, &queue).await?;
        if args.paused {
            eprintln!("{id} is paused: `tessera quote {id}` says what it will take, `tessera resume {id}` starts it");
        }
        if args.detach || args.paused {
            return crate::listing::print(&format!("{id}\n"));
        }
        follow(&mut client, &id, &pattern, args.quiet, hint.as_ref()).await
    })
}

/// Follows a render or sequence to its end and downloads its images: a sequence's frames as
/// they finish, to `pattern` with their frame numbers. An image that comes out black gets
/// `hint` (see [`BlackImageHint`]), once.
pub async fn follow(
    client: &mut Client,
    id: &str,
    pattern: &Path,
    quiet: bool,
    hint: Option<&BlackImageHint>,
) -> Result<()> {
    let sequence = id.starts_with('s');
    let mut fetched = 0;
    let mut told = false;
    let mut tell = |image: &tessera_film::ExrImage, what: &str| {
        if let Some(why) = hint.and_then(|h| h.explain(image)).filter(|_| !std::mem::replace(&mut told, true)) {
            tracing::warn!("{what}: {why}");
        }
    };
    let mut fetch_frames = async |client: &mut Client, done: &[FrameDone], preview: bool| -> Result<()> {
        for f in done {
            let out = frame_path(pattern, Some(f.frame))?;
            let out = if preview { out.with_extension("preview.exr") } else { out };
            let image = fetch(client, &f.render_id, None, preview, &out).await?;
            if !preview {
                tell(&image, &format!("frame {}", f.frame));
                fetched += 1;
            }
            if !quiet {
                let what = if preview { "preview" } else { "frame" };
                eprintln!("{what} {}: wrote {} and {}", f.frame, out.display(), out.with_extension("png").display());
            }
        }
        Ok(())
    };
    if sequence {
        watch_with(client, id, Progress::quiet(quiet), &mut fetch_frames).await?;
        return Ok(());
    }
    watch(client, id, quiet).await?;
    let out = frame_path(pattern, None)?;
    let image = fetch(client, id, None, false, &out).await?;
    tell(&image, &format!("render {id}"));
    if !quiet {
        eprintln!("wrote {} and {}", out.display(), out.with_extension("png").display());
    }
    Ok(())
}

/// How a submission waits its turn: its priority, its name in listings, and where it may run.
#[derive(Clone, Debug, Default)]
pub struct Queue {
    pub priority: i32,
    pub name: String,
    pub placement: Placement,
    /// Where the coordinator POSTs an event when it ends (empty: its default).
    pub notify: String,
    pub preview: Option<PreviewFirst>,
    /// Submitted paused.
    pub paused: bool,
}

/// Packs, uploads (unless the coordinator has it) and submits a scene; returns the render id
/// (`s` and a number for a sequence).
pub async fn submit(
    client: &mut Client,
    scene: &str,
    options: &RenderOptions,
    animation: &AnimationArgs,
    queue: &Queue,
) -> Result<(String, Option<BlackImageHint>)> {
    let crate::resolve::Resolved { bytes, loaded, setup, termination, sampling, how_many, frames } =
        crate::resolve::resolve(scene, options, animation)?;
    let hash = blake3::hash(&bytes).to_hex().to_string();
    let request = HasSceneRequest { protocol_version: PROTOCOL_VERSION, hash: hash.clone() };
    let present = answer("whether it has the scene", client.has_scene(request)).await?.present;
    if !present {
        let total = bytes.len() as u64;
        let chunks: Vec<SceneChunk> = bytes
            .chunks(1 << 20)
            .map(|c| SceneChunk {
                protocol_version: PROTOCOL_VERSION,
                hash: hash.clone(),
                total_bytes: total,
                data: c.to_vec(),
            })
            .collect();
        // A minute, and a second per MiB on top.
        let limit = ANSWER_WITHIN + std::time::Duration::from_secs(total >> 20);
        within(limit, "the scene upload", client.upload_scene(tokio_stream::iter(chunks)))
            .await
            .map_err(status_error)?;
    }
    let hint = BlackImageHint::of(&loaded, &setup.settings);
    let submission = Submission {
        scene_hash: hash,
        scene_name: printable(scene),
        setup,
        spp: sampling.spp,
        adaptive: sampling.adaptive,
        tile_size: tessera_render::plan::TILE_SIZE,
        pass_spp: tessera_render::plan::PASS_SPP,
        priority: queue.priority,
        frames,
        name: printable(&queue.name),
        placement: queue.placement.clone(),
        notify: queue.notify.clone(),
        preview: queue.preview,
        paused: queue.paused,
    };
    let request = submission.to_wire(PROTOCOL_VERSION);
    let id = answer("the submission", client.submit_render(request)).await?.render_id;
    tracing::info!("render {id} submitted ({how_many}; {termination})");
    Ok((id, hint))
}

/// A watch stopped by Ctrl-C or SIGTERM (a local farm writes what it merged instead).
#[derive(Debug)]
pub struct Interrupted(pub String);

impl std::fmt::Display for Interrupted {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let (id, sequence) = (&self.0, self.0.starts_with('s'));
        write!(
            f,
            "interrupted: stopped following render {id}; a farm's coordinator keeps rendering it \
             (`tessera watch {id}` follows it again, `tessera fetch {id}{} --out PATH` downloads {})",
            if sequence { " --frame F" } else { "" },
            if sequence { "a frame" } else { "it" }
        )
    }
}

impl std::error::Error for Interrupted {}

/// How a watch shows its progress.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Progress {
    /// A progress bar on a terminal; elsewhere (a log, a pipe) a line for every tenth of the
    /// work and one at the end.
    Shown,
    /// Nothing.
    Quiet,
    /// Every status as one JSON object a line on standard output.
    Json,
}

impl Progress {
    pub fn quiet(quiet: bool) -> Self {
        if quiet { Progress::Quiet } else { Progress::Shown }
    }
}

/// Follows a render until it ends, with a progress bar on a terminal.
pub async fn watch(client: &mut Client, id: &str, quiet: bool) -> Result<()> {
    watch_with(client, id, Progress::quiet(quiet), &mut async |_: &mut Client, _: &[FrameDone], _| Ok(())).await
}

/// As [`watch`], handing each status's newly finished frames (of a sequence) to `on_frames`.
pub async fn watch_with(
    client: &mut Client,
    id: &str,
    progress: Progress,
    on_frames: &mut impl AsyncFnMut(&mut Client, &[FrameDone], bool) -> Result<()>,
) -> Result<()> {
    use std::io::IsTerminal;
    let bar = tessera_local::progress_bar(progress != Progress::Shown);
    // Without a terminal, a line at first, each tenth of the passes (the last tenth said) and at
    // the end.
    let mut lines = (progress == Progress::Shown && !std::io::stderr().is_terminal()).then_some(None::<u64>);
    bar.set_style(
        ProgressStyle::with_template("{spinner} [{elapsed_precise}] {wide_bar} {pos}/{len} passes {msg}")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let request =
        RenderRequest { protocol_version: PROTOCOL_VERSION, render_id: id.to_string(), frame: None, preview: false };
    let mut stream = answer("the watch request", client.watch_render(request)).await?;
    let mut last = None;
    let interrupted = crate::farm::termination();
    tokio::pin!(interrupted);
    loop {
        let status = tokio::select! {
            status = next_of("with the render's progress", &mut stream) => status?,
            _ = &mut interrupted => {
                bar.finish_and_clear();
                return Err(Interrupted(id.to_string()).into());
            }
        };
        let Some(s) = status else { break };
        update(&bar, &s);
        if progress == Progress::Json {
            println!("{}", status_json(&s));
        }
        if let Some(said) = lines.as_mut() {
            let tenth = (s.passes_done * 10).checked_div(s.passes_total).unwrap_or(0);
            if said.is_none_or(|t| tenth > t) || RenderState::try_from(s.state) != Ok(RenderState::Running) {
                *said = Some(tenth);
                eprintln!("render {id}: {}", progress_line(&s));
            }
        }
        // Frames finished, and previews written (previews first): a second connection would do
        // as well; the watch stream waits meanwhile.
        for (frames, preview) in [(&s.previewed, true), (&s.finished, false)] {
            if !frames.is_empty() {
                let mut downloads = client.clone();
                bar.suspend(|| ());
                on_frames(&mut downloads, frames, preview).await?;
            }
        }
        last = Some(s);
    }
    bar.finish_and_clear();
    match last.map(|s| (RenderState::try_from(s.state), s)) {
        Some((Ok(RenderState::Done), _)) => Ok(()),
        Some((Ok(RenderState::Cancelled), _)) => bail!("render {id} was cancelled"),
        Some((Ok(RenderState::Failed), s)) => {
            bail!(
                "render {id} failed: {} (`tessera retry {id}` queues its unfinished passes again)",
                printable(&s.message)
            )
        }
        Some((_, s)) => bail!("render {id} ended in state {}: {}", s.state, printable(&s.message)),
        None => bail!("the coordinator closed the watch of render {id} without a status"),
    }
}

fn update(bar: &ProgressBar, s: &RenderStatus) {
    bar.set_length(s.passes_total);
    bar.set_position(s.passes_done);
    bar.set_message(status_words(s));
}

/// A status in words: the frames of a sequence, or a render's samples, speed, error and ETA.
fn status_words(s: &RenderStatus) -> String {
    if s.no_workers {
        return NO_WORKERS.into();
    }
    if s.no_worker_fits {
        return no_worker_fits(s);
    }
    if s.paused {
        return "paused: `tessera resume` puts it back to work".into();
    }
    if s.frames_total > 0 {
        return format!(
            "frames: {} done, {} running, {} queued{} of {}; {:.2} M samples/s, {}",
            s.frames_done,
            s.frames_running,
            s.frames_queued,
            if s.frames_failed > 0 { format!(", {} failed", s.frames_failed) } else { String::new() },
            s.frames_total,
            s.samples_per_second / 1e6,
            eta_words(s)
        );
    }
    format!(
        "{:.1} spp, {:.2} M samples/s, {}, {}",
        s.mean_spp,
        s.samples_per_second / 1e6,
        error_words(s),
        eta_words(s)
    )
}

/// The relative error, with its bound where the render states one (`--confidence`).
fn error_words(s: &RenderStatus) -> String {
    match s.confidence {
        c if c > 0.0 => {
            format!("error {:.4} (below {:.4} with {} % confidence)", s.error_estimate, s.error_bound, c * 100.0)
        }
        _ => format!("error {:.4}", s.error_estimate),
    }
}

/// The time left, once the render has a speed to judge it by.
fn eta_words(s: &RenderStatus) -> String {
    if s.samples_per_second > 0.0 || s.passes_done >= s.passes_total {
        format!("ETA {:.0} s", s.eta_seconds)
    } else {
        "ETA not known yet (no samples merged)".into()
    }
}

/// A status's state as the listings write it (`running`, `paused`, `done`...; `unknown` for a
/// state this client does not know).
pub(crate) fn state_of(s: &RenderStatus) -> String {
    match RenderState::try_from(s.state) {
        Ok(RenderState::Running) if s.paused => "paused".into(),
        Ok(state) => format!("{state:?}").to_lowercase(),
        Err(_) => "unknown".into(),
    }
}

/// A scene as listings show it: its file's name, not the submitter's path to it (`status
/// --json` keeps the whole).
fn scene_file(scene: &str) -> &str {
    scene.rsplit(['/', '\\']).next().unwrap_or(scene)
}

/// What a running render says while no connected worker may take it.
fn no_worker_fits(s: &RenderStatus) -> String {
    format!(
        "no connected worker can take it: it needs {} (start one with `tessera worker --pool NAME --tag KEY=VALUE`, \
         or see `tessera workers`)",
        printable(&s.placement)
    )
}

/// What a running render says while no worker is connected.
const NO_WORKERS: &str = "no workers connected: start one with `tessera worker --coordinator URL`";

/// A status as one line of a log: its state, the passes merged and the rest in words.
fn progress_line(s: &RenderStatus) -> String {
    let state = state_of(s);
    let percent = (s.passes_done * 100).checked_div(s.passes_total).unwrap_or(0);
    format!("{state}, {percent}% ({}/{} passes), {}", s.passes_done, s.passes_total, status_words(s))
}

/// Downloads a finished render's EXR (or frame `frame` of a sequence; or with `preview`, a
/// frame's preview image) to `out` and writes a PNG beside it; returns the image.
pub async fn fetch(
    client: &mut Client,
    id: &str,
    frame: Option<u32>,
    preview: bool,
    out: &Path,
) -> Result<tessera_film::ExrImage> {
    let request = RenderRequest { protocol_version: PROTOCOL_VERSION, render_id: id.to_string(), frame, preview };
    let mut stream = answer("the image request", client.fetch_image(request)).await?;
    let (mut bytes, mut total) = (Vec::new(), 0);
    while let Some(chunk) = next_of("with the image", &mut stream).await? {
        total = chunk.total_bytes;
        bytes.extend_from_slice(&chunk.data);
    }
    if bytes.len() as u64 != total {
        bail!("the image of {id} arrived incomplete ({} of {total} bytes): fetch it again", bytes.len());
    }
    if let Some(dir) = out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    std::fs::write(out, &bytes).with_context(|| format!("writing {}", out.display()))?;
    let image = tessera_film::read_exr(out)?;
    tessera_film::write_png(&image, &out.with_extension("png"))?;
    Ok(image)
}

#[derive(Args, Debug)]
pub struct RenderIdArgs {
    /// The render id (from `submit --detach` or `status`).
    pub render: String,
    #[command(flatten)]
    pub connection: Connection,
}

#[derive(Args, Debug)]
pub struct WatchArgs {
    /// The render id, or a sequence's (s and a number).
    pub render: String,
    #[command(flatten)]
    pub connection: Connection,
    /// Print each status as one JSON object a line, for scripts (no progress bar).
    #[arg(long, env = "TESSERA_JSON")]
    pub json: bool,
}

#[derive(Args, Debug)]
pub struct StatusArgs {
    /// One render [default: all].
    pub render: Option<String>,
    #[command(flatten)]
    pub connection: Connection,
    /// Print the renders as one JSON document (an array of objects), for scripts.
    #[arg(long, env = "TESSERA_JSON")]
    pub json: bool,
}

/// A render's status as JSON, for `status --json` and `watch --json`.
fn status_json(r: &RenderStatus) -> serde_json::Value {
    let state = state_of(r);
    let mut v = serde_json::json!({
        "id": r.render_id,
        "name": r.name,
        "scene": r.scene_name,
        "state": state,
        "owner": r.owner,
        "passes_done": r.passes_done,
        "passes_total": r.passes_total,
        "samples_done": r.samples_done,
        "samples_per_second": r.samples_per_second,
        "mean_spp": r.mean_spp,
        "error_estimate": r.error_estimate,
        "error_bound": (r.confidence > 0.0).then_some(r.error_bound),
        // As given (0.95), not as its f32 reads in an f64 (0.949999988...).
        "confidence": (r.confidence > 0.0).then(|| r.confidence.to_string().parse::<f64>().unwrap_or(r.confidence as f64)),
        "eta_seconds": r.eta_seconds,
        "no_workers": r.no_workers,
        "priority": r.priority,
        "paused": r.paused,
        "placement": r.placement,
        "no_worker_fits": r.no_worker_fits,
        "submitted_at": (r.submitted_at > 0.0).then_some(r.submitted_at),
        "started_at": (r.started_at > 0.0).then_some(r.started_at),
        "ended_at": (r.ended_at > 0.0).then_some(r.ended_at),
        "message": r.message,
    });
    if r.frames_total > 0 {
        v["frames"] = serde_json::json!({
            "total": r.frames_total,
            "done": r.frames_done,
            "running": r.frames_running,
            "queued": r.frames_queued,
            "failed": r.frames_failed,
        });
    }
    if !r.sequence_id.is_empty() {
        v["sequence"] = r.sequence_id.clone().into();
        v["frame"] = r.frame.into();
    }
    if !r.finished.is_empty() {
        v["finished"] = r.finished.iter().map(|f| serde_json::json!({ "frame": f.frame, "id": f.render_id })).collect();
    }
    v
}

#[derive(Args, Debug)]
pub struct WorkersArgs {
    #[command(flatten)]
    pub connection: Connection,
    /// Leave out workers lost or stopped for longer than this many seconds.
    #[arg(long, value_name = "SECONDS", env = "TESSERA_HIDE_GONE")]
    pub hide_gone: Option<f64>,
    /// Print the workers as one JSON document (an array of objects), for scripts.
    #[arg(long, env = "TESSERA_JSON")]
    pub json: bool,
}

/// Every item of a listing that comes in pages: `page(token)` gives a page and the next token,
/// empty after the last page.
async fn every_page<T>(mut page: impl AsyncFnMut(String) -> Result<(Vec<T>, String)>) -> Result<Vec<T>> {
    let (mut all, mut token) = (Vec::new(), String::new());
    loop {
        let (items, next) = page(token).await?;
        all.extend(items);
        if next.is_empty() {
            return Ok(all);
        }
        token = next;
    }
}

pub(crate) fn block_on<T>(f: impl std::future::Future<Output = Result<T>>) -> Result<T> {
    tokio::runtime::Runtime::new()?.block_on(f)
}

pub fn run_status(args: StatusArgs) -> Result<()> {
    block_on(async {
        let mut client = args.connection.connect().await?;
        let renders = every_page(async |page_token| {
            let request = ListRendersRequest { protocol_version: PROTOCOL_VERSION, page_size: 0, page_token };
            let page = answer("the list of renders", client.list_renders(request)).await?;
            Ok((page.renders, page.next_page_token))
        })
        .await?;
        let shown: Vec<&RenderStatus> =
            renders.iter().filter(|r| args.render.as_ref().is_none_or(|id| &r.render_id == id)).collect();
        if let Some(id) = &args.render
            && shown.is_empty()
        {
            bail!("no render {id}");
        }
        if args.json {
            let rows: Vec<serde_json::Value> = shown.iter().map(|r| status_json(r)).collect();
            return crate::listing::print(&format!("{}\n", serde_json::to_string_pretty(&rows)?));
        }
        let owners = shown.iter().any(|r| !r.owner.is_empty());
        let priorities = shown.iter().any(|r| r.priority != 0);
        let mut out = format!(
            "{:<6} {:<10} {:>16} {:>12}  {}{}scene\n",
            "id",
            "state",
            "passes",
            "Msamples/s",
            if priorities { format!("{:>8}  ", "priority") } else { String::new() },
            if owners { format!("{:<12} ", "owner") } else { String::new() }
        );
        for r in shown {
            writeln!(
                out,
                "{:<6} {:<10} {:>16} {:>12.2}  {}{}{}",
                r.render_id,
                state_of(r),
                format!("{}/{}", r.passes_done, r.passes_total),
                r.samples_per_second / 1e6,
                if priorities { format!("{:>8}  ", r.priority) } else { String::new() },
                if owners { format!("{:<12} ", printable(&r.owner)) } else { String::new() },
                match r.name.as_str() {
                    "" => printable(scene_file(&r.scene_name)),
                    name => format!("{} ({})", printable(name), printable(scene_file(&r.scene_name))),
                }
            )?;
            if r.frames_total > 0 {
                writeln!(
                    out,
                    "       {}/{} frames done, {} running, {} queued{}; ETA {:.0} s",
                    r.frames_done,
                    r.frames_total,
                    r.frames_running,
                    r.frames_queued,
                    if r.frames_failed > 0 { format!(", {} failed", r.frames_failed) } else { String::new() },
                    r.eta_seconds
                )?;
            }
            if !r.message.is_empty() {
                writeln!(out, "       {}", printable(&r.message))?;
            }
            if r.no_workers {
                writeln!(out, "       {NO_WORKERS}")?;
            }
            if r.no_worker_fits {
                writeln!(out, "       {}", no_worker_fits(r))?;
            }
        }
        crate::listing::print(&out)
    })
}

pub fn run_watch(args: WatchArgs) -> Result<()> {
    block_on(async {
        let mut client = args.connection.connect().await?;
        let progress = if args.json { Progress::Json } else { Progress::Shown };
        watch_with(&mut client, &args.render, progress, &mut async |_: &mut Client, _: &[FrameDone], _| Ok(())).await
    })
}

pub fn run_cancel(args: RenderIdArgs) -> Result<()> {
    block_on(async {
        let mut client = args.connection.connect().await?;
        let request = RenderRequest {
            protocol_version: PROTOCOL_VERSION,
            render_id: args.render.clone(),
            frame: None,
            preview: false,
        };
        answer("the cancellation", client.cancel_render(request)).await?;
        eprintln!("render {} cancelled", args.render);
        Ok(())
    })
}

pub fn run_retry(args: RenderIdArgs) -> Result<()> {
    block_on(async {
        let mut client = args.connection.connect().await?;
        let request = RenderRequest {
            protocol_version: PROTOCOL_VERSION,
            render_id: args.render.clone(),
            frame: None,
            preview: false,
        };
        answer("the retry", client.retry_render(request)).await?;
        eprintln!(
            "render {} queued again: its unfinished passes will be rendered (`tessera watch {}` follows it)",
            args.render, args.render
        );
        Ok(())
    })
}

/// Every worker the coordinator knows, page by page.
pub async fn all_workers(client: &mut Client) -> Result<Vec<WorkerStatus>> {
    every_page(async |page_token| {
        let request = ListWorkersRequest { protocol_version: PROTOCOL_VERSION, page_size: 0, page_token };
        let page = answer("the list of workers", client.list_workers(request)).await?;
        Ok((page.workers, page.next_page_token))
    })
    .await
}

pub fn run_workers(args: WorkersArgs) -> Result<()> {
    block_on(async {
        let mut client = args.connection.connect().await?;
        let mut workers = all_workers(&mut client).await?;
        workers.sort_by(|a, b| a.name.cmp(&b.name).then(a.worker_id.cmp(&b.worker_id)));
        if let Some(limit) = args.hide_gone {
            workers.retain(|w| !matches!(w.state.as_str(), "lost" | "stopped") || w.seconds_since_seen <= limit);
        }
        if args.json {
            let rows: Vec<serde_json::Value> = workers
                .iter()
                .map(|w| {
                    serde_json::json!({
                        "id": w.worker_id,
                        "name": w.name,
                        "state": w.state,
                        "host": w.host,
                        "threads": w.threads,
                        "samples_per_second": w.samples_per_second,
                        "leases": w.leases,
                        "seconds_since_seen": w.seconds_since_seen,
                        "results": w.results,
                        "failures": w.failures,
                        "renders": w.render_ids,
                        "render_count": w.render_count,
                        "blocked_from": w.blocked_from,
                        "pool": w.pool,
                        "tags": w.tags,
                    })
                })
                .collect();
            println!("{}", serde_json::to_string_pretty(&rows)?);
            return Ok(());
        }
        let pools = workers.iter().any(|w| !w.pool.is_empty());
        let mut out = format!(
            "{:<24} {:<8} {}{:<16} {:>7} {:>12} {:>7} {:>10} {:>8} {:>8}  {}\n",
            "name",
            "state",
            if pools { format!("{:<12} ", "pool") } else { String::new() },
            "host",
            "threads",
            "Msamples/s",
            "leases",
            "last seen",
            "results",
            "failures",
            "renders"
        );
        for w in workers {
            let mut renders = if w.render_ids.is_empty() { "-".to_string() } else { w.render_ids.join(",") };
            let unlisted = (w.render_count as usize).saturating_sub(w.render_ids.len());
            if unlisted > 0 {
                write!(renders, " and {unlisted} more")?;
            }
            if !w.blocked_from.is_empty() {
                write!(renders, " (no more jobs of render {})", w.blocked_from.join(","))?;
            }
            writeln!(
                out,
                "{:<24} {:<8} {}{:<16} {:>7} {:>12.2} {:>7} {:>9.1}s {:>8} {:>8}  {}",
                printable(&w.name),
                printable(&w.state),
                if pools {
                    format!("{:<12} ", printable(if w.pool.is_empty() { "-" } else { &w.pool }))
                } else {
                    String::new()
                },
                printable(&w.host),
                w.threads,
                w.samples_per_second / 1e6,
                w.leases,
                w.seconds_since_seen,
                w.results,
                w.failures,
                printable(&renders)
            )?;
        }
        crate::listing::print(&out)
    })
}
