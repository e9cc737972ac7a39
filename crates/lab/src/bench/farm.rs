//! Farm benchmarks: coordinator capacity with simulated workers, and the overhead of rendering
//! through a local farm.

use crate::bench::{CoordinatorBenchArgs, FarmBenchArgs, median, time};
use anyhow::Result;
use std::process::Command;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};
use tessera_coordinator::{CoreConfig, MAX_CONNECTIONS, Tokens, serve};
use tessera_proto::PROTOCOL_VERSION;
use tessera_proto::sums::encode_tile_sums;
use tessera_proto::v1::render_service_client::RenderServiceClient;
use tessera_proto::v1::work_service_client::WorkServiceClient;
use tessera_proto::v1::*;
use tessera_render::glam::Vec3;
use tessera_render::plan::FrameList;
use tessera_render::{Termination, Tile, TileSums};
use tessera_request::{Frames, Pose, Setup, Submission};

pub fn coordinator(args: CoordinatorBenchArgs) -> Result<()> {
    let data_dir = std::env::temp_dir().join(format!("tessera-bench-coordinator-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&data_dir);
    // The coordinator gets a runtime with one worker thread: "one core". Its threads are named,
    // so that their CPU time can be told from the simulated workers'.
    let server_rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .thread_name(COORDINATOR_THREADS)
        .enable_all()
        .build()?;
    let cpu_before = coordinator_cpu_seconds();
    let mut config = CoreConfig::new(data_dir.clone());
    config.max_active_renders = config.max_active_renders.max(args.listed + 3);
    config.verify = args.verify.clamp(0.0, 1.0);
    let shared = tessera_coordinator::Engine::open(config)?;
    let steering = shared.clone();
    let listener = server_rt.block_on(async { tessera_coordinator::listen(([127, 0, 0, 1], 0).into()) })?;
    let url = format!("http://{}", listener.local_addr()?);
    let metrics = shared.clone();
    let dashboard = match args.watchers + args.event_streams {
        0 => None,
        _ => {
            let http = server_rt.block_on(async { tessera_coordinator::listen(([127, 0, 0, 1], 0).into()) })?;
            let port = http.local_addr()?.port();
            let dashboard = tessera_coordinator::http::Dashboard::new(shared.clone(), Tokens::default(), false);
            server_rt.spawn(tessera_coordinator::http::serve(http, dashboard, None, std::future::pending()));
            Some(port)
        }
    };
    server_rt.spawn(serve(listener, shared, Tokens::default(), None, MAX_CONNECTIONS, std::future::pending()));

    let client_rt = tokio::runtime::Runtime::new()?;
    let (merged, secs, bytes, leases, window, errors, status) = client_rt.block_on(async {
        // A render that does not run out: 1024 x 1024 in 32 x 32 tiles, 4096 passes each (jobs of
        // one pass for workers that claim no speed, up to 64 for fast ones).
        let scene = b"tessera-builtin:cornell-box".to_vec();
        let hash = blake3::hash(&scene).to_hex().to_string();
        let mut c = RenderServiceClient::connect(url.clone()).await?;
        let chunk = SceneChunk {
            protocol_version: PROTOCOL_VERSION,
            hash: hash.clone(),
            total_bytes: scene.len() as u64,
            data: scene,
        };
        c.upload_scene(tokio_stream::iter(vec![chunk])).await?;
        let settings = tessera_render::RenderSettings {
            termination: Termination::MaxBounces(4),
            ..tessera_render::RenderSettings::new(1024, 1024)
        };
        let endless = Submission {
            scene_hash: hash.clone(),
            scene_name: "bench".into(),
            setup: Setup::new(settings.clone(), Vec3::ZERO),
            spp: 1 << 16,
            adaptive: None,
            tile_size: 32,
            pass_spp: 16,
            priority: 0,
            frames: None,
            name: String::new(),
            placement: Default::default(),
            notify: String::new(),
            preview: None,
            paused: false,
        };
        let endless_id = c.submit_render(endless.to_wire(PROTOCOL_VERSION)).await?.into_inner().render_id;
        if args.steering {
            // Owners' renders go in through the engine (the bench's gRPC calls carry no token).
            steering.set_weights([("ann", 1.0), ("ben", 2.0), ("cat", 3.0)].map(|(o, w)| (o.to_string(), w)).into());
            for (owner, priority, pool) in [("ann", 10, ""), ("ben", 0, "gpu"), ("cat", 0, "")] {
                let who = tessera_coordinator::users::Identity {
                    name: owner.into(),
                    role: tessera_coordinator::users::Role::Submit,
                };
                let placement = tessera_request::placement::Placement { pool: pool.into(), requires: Vec::new() };
                let theirs = Submission { priority, placement, ..endless.clone() };
                steering.put_scene(owner, hash.clone(), b"tessera-builtin:cornell-box".to_vec()).await?;
                steering.submit(&who, theirs).await?;
            }
        }
        // The long sequence waits below the endless render; it is watched, and listed.
        let watched = match args.sequence {
            0 => endless_id,
            frames => {
                let mut setup =
                    Setup::new(tessera_render::RenderSettings { width: 8, height: 8, ..settings.clone() }, Vec3::ZERO);
                setup.pose = Some(Pose::default());
                let sequence = Submission {
                    scene_name: "bench-sequence".into(),
                    setup,
                    spp: 16,
                    tile_size: 8,
                    priority: -1,
                    frames: Some(Frames {
                        list: FrameList::parse(&format!("1-{frames}")).map_err(anyhow::Error::msg)?,
                        fps: 24.0,
                    }),
                    ..endless.clone()
                };
                let submitted = Instant::now();
                let id = c.submit_render(sequence.to_wire(PROTOCOL_VERSION)).await?.into_inner().render_id;
                println!("a sequence of {frames} frames submitted in {:.2} s", submitted.elapsed().as_secs_f64());
                id
            }
        };
        // The long list waits below the endless render too.
        for _ in 0..args.listed {
            let small = tessera_render::RenderSettings { width: 8, height: 8, ..settings.clone() };
            let listed = Submission {
                scene_name: "bench-listed".into(),
                setup: Setup::new(small, Vec3::ZERO),
                spp: 16,
                tile_size: 8,
                priority: -1,
                ..endless.clone()
            };
            c.submit_render(listed.to_wire(PROTOCOL_VERSION)).await?;
        }
        for _ in 0..args.status_watchers {
            tokio::spawn(watch_status(c.clone(), watched.clone()));
        }
        if let Some(port) = dashboard {
            for _ in 0..args.event_streams {
                tokio::spawn(follow_events(port));
            }
        }
        let started = Instant::now();
        // The render that finishes while the workers lease: ahead of the endless one.
        let finishing = match args.finish {
            0 => None,
            side => {
                let settings = tessera_render::RenderSettings { width: side, height: side, ..settings };
                let finishing = Submission {
                    scene_name: "bench-finish".into(),
                    setup: Setup::new(settings, Vec3::ZERO),
                    spp: 16,
                    priority: 1,
                    ..endless.clone()
                };
                let id = c.submit_render(finishing.to_wire(PROTOCOL_VERSION)).await?.into_inner().render_id;
                if let Some(port) = dashboard {
                    for _ in 0..args.watchers {
                        tokio::spawn(watch_page(port, id.clone()));
                    }
                }
                Some(tokio::spawn(watch_finish(c.clone(), id, started)))
            }
        };
        // What a user's `tessera status` (the whole list) takes meanwhile, asked once a second.
        let status_latency = tokio::spawn(time_status(c.clone(), Duration::from_secs_f64(args.seconds)));
        let deadline = Instant::now() + Duration::from_secs_f64(args.seconds);
        let mut tasks = Vec::new();
        let results = Results::default();
        for w in 0..args.workers {
            let url = url.clone();
            let speed = args.worker_speed;
            let steered = args.steering;
            let results = results.clone();
            tasks.push(tokio::spawn(async move {
                let mut client = WorkServiceClient::connect(url).await.expect("connect");
                let (mut done, mut bytes, mut latencies, mut first, mut errors) = (0u64, 0u64, Vec::new(), true, 0u64);
                let id = format!("sim{w}");
                while Instant::now() < deadline {
                    let req = LeaseRequest {
                        protocol_version: PROTOCOL_VERSION,
                        worker_id: id.clone(),
                        worker_name: id.clone(),
                        threads: 1,
                        samples_per_second: speed,
                        wait_ms: 100,
                        pool: if steered && w % 2 == 0 { "gpu".into() } else { String::new() },
                        tags: if steered { vec!["mem=64G".into()] } else { Vec::new() },
                    };
                    let asked = Instant::now();
                    // A failed call is counted; the channel reconnects on the next, as a
                    // worker's does, and that lease (which opens the connection) is not timed.
                    let job = match client.lease(req).await {
                        Ok(answer) => answer.into_inner().job,
                        Err(e) => {
                            errors += 1;
                            eprintln!("simulated worker {id}: lease failed: {e}");
                            first = true;
                            tokio::time::sleep(Duration::from_millis(200)).await;
                            continue;
                        }
                    };
                    let Some(job) = job else { continue };
                    // The first lease of each worker also opens its connection: not counted.
                    if !std::mem::take(&mut first) {
                        let at = asked.duration_since(started).as_secs_f64();
                        latencies.push((at, asked.elapsed().as_secs_f64() * 1e3));
                    }
                    let t = job.tile.expect("tile");
                    let tile = Tile { x0: t.x0, y0: t.y0, width: t.width, height: t.height };
                    let samples =
                        tessera_render::plan::pass_samples(job.first_pass, job.pass_count, job.pass_spp, job.spp).len()
                            as u32;
                    if speed > 0.0 {
                        let render = samples as f64 * (tile.width * tile.height) as f64 / speed;
                        tokio::time::sleep(Duration::from_secs_f64(render)).await;
                    }
                    let data = results.bytes(tile, samples);
                    bytes += data.len() as u64;
                    let msg = CompleteRequest {
                        protocol_version: PROTOCOL_VERSION,
                        worker_id: id.clone(),
                        lease_id: job.lease_id,
                        chunk: Some(TileSumsChunk { data }),
                        render_seconds: 0.0,
                    };
                    match client.complete(tokio_stream::iter(vec![msg])).await {
                        Ok(answer) => done += if answer.into_inner().merged { job.pass_count as u64 } else { 0 },
                        Err(e) => {
                            errors += 1;
                            eprintln!("simulated worker {id}: complete failed: {e}");
                            first = true;
                        }
                    }
                }
                (done, bytes, latencies, errors)
            }));
        }
        let (mut merged, mut bytes, mut latencies, mut errors) = (0u64, 0u64, Vec::new(), 0u64);
        for t in tasks {
            let (d, b, l, e) = t.await?;
            merged += d;
            bytes += b;
            latencies.extend(l);
            errors += e;
        }
        let window = match finishing {
            Some(task) => Some(task.await??),
            None => None,
        };
        let status = status_latency.await?;
        anyhow::Ok((merged, started.elapsed().as_secs_f64(), bytes, latencies, window, errors, status))
    })?;
    let cpu = coordinator_cpu_seconds() - cpu_before;
    let (merge_secs, results, checked) = metrics
        .with(|c| Ok((c.metrics.merge_seconds_total, c.metrics.merges, c.metrics.results_checked)))
        .unwrap_or((0.0, 0, 0));
    let pace = if args.worker_speed > 0.0 {
        format!("each rendering at {:.2} M samples/s", args.worker_speed / 1e6)
    } else {
        "returning results at once".into()
    };
    println!("coordinator on 1 core, {} simulated workers {pace}, {secs:.1} s", args.workers);
    let all: Vec<f64> = leases.iter().map(|&(_, ms)| ms).collect();
    println!(
        "lease latency over {} jobs (each worker's first, which opens its connection, left out): {}",
        all.len(),
        percentiles(all)
    );
    // The first two seconds hold the start: every worker connecting and asking at once.
    let settled: Vec<f64> = leases.iter().filter(|&&(at, _)| at >= 2.0).map(|&(_, ms)| ms).collect();
    println!("  of them, {} asked after the first 2 s: {}", settled.len(), percentiles(settled));
    if let Some(w) = window {
        let during: Vec<f64> =
            leases.iter().filter(|&&(at, _)| at >= w.last_tenth && at <= w.done).map(|&(_, ms)| ms).collect();
        println!(
            "the {0} x {0} render: all passes merged at {1:.2} s, done (EXR written) at {2:.2} s; lease latency over the {3} jobs asked from its last tenth of passes ({4:.2} s) to done: {5}",
            args.finish,
            w.merged,
            w.done,
            during.len(),
            w.last_tenth,
            percentiles(during)
        );
    }
    println!(
        "coordinator CPU: {:.0}% of one core; process memory (coordinator and simulated workers): {} MiB",
        100.0 * cpu / secs,
        resident_mib()
    );
    println!(
        "durable results merged: {results} ({:.0} per second) covering {merged} passes, {:.1} MB/s in",
        results as f64 / secs,
        bytes as f64 / secs / 1e6
    );
    if args.verify > 0.0 {
        println!(
            "--verify {}: {checked} results checked by a second worker ({:.0} per second)",
            args.verify,
            checked as f64 / secs
        );
    }
    if errors > 0 {
        println!("failed calls (the simulated worker reconnected): {errors}");
    }
    println!("tessera status (the whole list, once a second): {}", percentiles(status));
    if args.status_watchers + args.event_streams > 0 {
        println!(
            "{} watches were sent {} statuses, {} event streams ({} answered) {:.1} MB",
            args.status_watchers,
            FOLLOWED.0.load(Ordering::Relaxed),
            args.event_streams,
            STREAMS_ANSWERED.load(Ordering::Relaxed),
            FOLLOWED.1.load(Ordering::Relaxed) as f64 / 1e6
        );
    }
    println!(
        "a result from accepted to merged (checked against its lease, committed to SQLite in a group, merged): {:.2} ms on average",
        merge_secs / results.max(1) as f64 * 1e3,
    );
    let _ = std::fs::remove_dir_all(&data_dir);
    Ok(())
}

/// Lists every render once a second for `run` (what `tessera status` asks); the times in ms.
async fn time_status(mut client: RenderServiceClient<tonic::transport::Channel>, run: Duration) -> Vec<f64> {
    let (end, mut times) = (Instant::now() + run, Vec::new());
    while Instant::now() < end {
        let asked = Instant::now();
        let request = ListRendersRequest { protocol_version: PROTOCOL_VERSION, ..Default::default() };
        if client.list_renders(request).await.is_ok() {
            times.push(asked.elapsed().as_secs_f64() * 1e3);
        }
        tokio::time::sleep(Duration::from_secs(1)).await;
    }
    times
}

/// "p50 .. ms, p99 .. ms, max .. ms" of `ms`.
fn percentiles(mut ms: Vec<f64>) -> String {
    ms.sort_by(f64::total_cmp);
    let at = |q: f64| ms.get(((ms.len() as f64 - 1.0) * q).round() as usize).copied().unwrap_or(0.0);
    format!("p50 {:.2} ms, p99 {:.2} ms, max {:.2} ms", at(0.5), at(0.99), at(1.0))
}

/// A browser watching render `id`'s dashboard page, for ever: the render list and the preview
/// every 0.5 s, each on a connection of its own. The page can ask no faster: it fetches a
/// preview when its event stream, which looks every 0.5 s, says the render has changed.
async fn watch_page(port: u16, id: String) {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let get = |path: String| async move {
        let mut s = tokio::net::TcpStream::connect(("127.0.0.1", port)).await.ok()?;
        let request = format!("GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n");
        s.write_all(request.as_bytes()).await.ok()?;
        let mut answer = Vec::new();
        s.read_to_end(&mut answer).await.ok()?;
        Some(answer.len())
    };
    for tick in 0u64.. {
        get(format!("/api/renders/{id}/preview.jpg?v={tick}")).await;
        get("/api/renders".to_string()).await;
        tokio::time::sleep(Duration::from_millis(500)).await;
    }
}

/// A `tessera watch` of render or sequence `id`, for ever: every status it is sent, read.
async fn watch_status(mut client: RenderServiceClient<tonic::transport::Channel>, id: String) {
    let request = RenderRequest { protocol_version: PROTOCOL_VERSION, render_id: id, frame: None, preview: false };
    let Ok(answer) = client.watch_render(request).await else { return };
    let mut stream = answer.into_inner();
    while let Ok(Some(_)) = stream.message().await {
        FOLLOWED.0.fetch_add(1, Ordering::Relaxed);
    }
}

/// Status messages the watches and bytes the event streams were sent (both prove they ran).
static FOLLOWED: (AtomicU64, AtomicU64) = (AtomicU64::new(0), AtomicU64::new(0));
/// Event streams that were answered (a stream refused at the door reads nothing).
static STREAMS_ANSWERED: AtomicU64 = AtomicU64::new(0);

/// A dashboard page's event stream, for ever: every event it is sent, read. A stream closed
/// before it was answered (the door was full) is opened again a second later, as a browser's
/// EventSource reconnects.
async fn follow_events(port: u16) {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    loop {
        let Ok(mut s) = tokio::net::TcpStream::connect(("127.0.0.1", port)).await else { return };
        let request = "GET /api/events HTTP/1.1\r\nHost: 127.0.0.1\r\nAccept: text/event-stream\r\n\r\n";
        if s.write_all(request.as_bytes()).await.is_ok() {
            let mut buf = vec![0u8; 1 << 16];
            let mut answered = false;
            while let Ok(n) = s.read(&mut buf).await {
                if n == 0 {
                    break;
                }
                if !answered {
                    answered = true;
                    STREAMS_ANSWERED.fetch_add(1, Ordering::Relaxed);
                }
                FOLLOWED.1.fetch_add(n as u64, Ordering::Relaxed);
            }
            if answered {
                return;
            }
        }
        tokio::time::sleep(Duration::from_secs(1)).await;
    }
}

/// When the finishing render reached its last tenth of passes, had all of them merged, and was
/// done, in seconds from `started`.
struct FinishWindow {
    last_tenth: f64,
    merged: f64,
    done: f64,
}

/// Polls render `id` every 10 ms until it is done.
async fn watch_finish(
    mut client: RenderServiceClient<tonic::transport::Channel>,
    id: String,
    started: Instant,
) -> Result<FinishWindow> {
    let (mut last_tenth, mut merged) = (None, None);
    loop {
        let page = client
            .list_renders(ListRendersRequest { protocol_version: PROTOCOL_VERSION, ..Default::default() })
            .await?
            .into_inner();
        let s =
            page.renders.into_iter().find(|r| r.render_id == id).ok_or_else(|| anyhow::anyhow!("render {id} gone"))?;
        let now = started.elapsed().as_secs_f64();
        if s.passes_done * 10 >= s.passes_total * 9 {
            last_tenth.get_or_insert(now);
        }
        if s.passes_done == s.passes_total {
            merged.get_or_insert(now);
        }
        match RenderState::try_from(s.state) {
            Ok(RenderState::Running) => {}
            Ok(RenderState::Done) => {
                let (last_tenth, merged) = (last_tenth.unwrap_or(now), merged.unwrap_or(now));
                return Ok(FinishWindow { last_tenth, merged, done: now });
            }
            other => anyhow::bail!("render {id} ended {other:?}: {}", s.message),
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}

pub fn farm(args: FarmBenchArgs) -> Result<()> {
    let exe = std::env::current_exe()?;
    let out = std::env::temp_dir().join(format!("tessera-bench-farm-{}.exr", std::process::id()));
    let common =
        ["--width", &args.size.to_string(), "--height", &args.size.to_string(), "--spp", &args.spp.to_string(), "-q"]
            .map(str::to_string);
    let run = |extra: &[&str]| -> Result<f64> {
        let mut cmd = Command::new(&exe);
        cmd.arg("render").args(&common).args(extra).arg("--out").arg(&out);
        let mut ok = true;
        let secs = time(|| ok = cmd.output().map(|o| o.status.success()).unwrap_or(false));
        anyhow::ensure!(ok, "render {extra:?} failed");
        Ok(secs)
    };
    let mut direct = Vec::new();
    let mut farm = Vec::new();
    for _ in 0..args.repeat.max(1) {
        direct.push(run(&["--threads", "2"])?);
        farm.push(run(&["--workers", "2", "--threads", "2"])?);
    }
    let (d, f) = (median(direct), median(farm));
    println!("cornell box {0}x{0}, {1} spp (wall time, median of {2})", args.size, args.spp, args.repeat);
    println!("in-process, 2 threads:      {d:.2} s");
    println!("render --workers 2 (gRPC):  {f:.2} s");
    println!("farm overhead ratio:        {:.3}", f / d);
    let _ = std::fs::remove_file(&out);
    let _ = std::fs::remove_file(out.with_extension("png"));
    Ok(())
}

/// The name of the benchmarked coordinator's threads.
const COORDINATOR_THREADS: &str = "tessera-coord";

/// CPU seconds (user and system) the coordinator's threads have used: its runtime's, named
/// [`COORDINATOR_THREADS`], and the store's result writer. From `/proc` (0
/// where there is none).
fn coordinator_cpu_seconds() -> f64 {
    let Ok(tasks) = std::fs::read_dir("/proc/self/task") else { return 0.0 };
    let ticks_per_second = 100.0; // USER_HZ on Linux
    let mut ticks = 0u64;
    for task in tasks.flatten() {
        let comm = std::fs::read_to_string(task.path().join("comm")).unwrap_or_default();
        if !(comm.trim().starts_with(COORDINATOR_THREADS) || comm.trim() == tessera_coordinator::store::WRITER_THREAD) {
            continue;
        }
        let stat = std::fs::read_to_string(task.path().join("stat")).unwrap_or_default();
        // Fields after the command's closing parenthesis; utime and stime are the 12th and 13th.
        let fields: Vec<&str> = stat.rsplit_once(')').map_or("", |(_, rest)| rest).split_whitespace().collect();
        ticks += fields.get(11).and_then(|v| v.parse::<u64>().ok()).unwrap_or(0);
        ticks += fields.get(12).and_then(|v| v.parse::<u64>().ok()).unwrap_or(0);
    }
    ticks as f64 / ticks_per_second
}

/// The process's resident memory in MiB (0 where `/proc` does not say).
fn resident_mib() -> u64 {
    let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<u64>().ok())
        .map_or(0, |kb| kb / 1024)
}

/// A tile result with radiance 0.5 in every sample (sums of realistic size), encoded once per
/// sample count and re-addressed to each tile, so the simulated workers cost next to nothing.
/// The encoded 32 x 32 results the simulated workers send, one per sample count, made once for
/// all of them: making one costs a million `add_sample`s at 1,024 samples, and a thousand
/// workers each making their own would hold the client runtime's threads for seconds at the
/// start, which the lease latencies would then count as the coordinator's.
#[derive(Clone, Default)]
struct Results(std::sync::Arc<std::sync::Mutex<std::collections::HashMap<u32, Vec<u8>>>>);

impl Results {
    fn bytes(&self, tile: Tile, samples: u32) -> Vec<u8> {
        let mut made = self.0.lock().unwrap_or_else(|e| e.into_inner());
        let mut bytes = made
            .entry(samples)
            .or_insert_with(|| {
                let mut sums = TileSums::new(Tile { x0: 0, y0: 0, width: 32, height: 32 });
                for p in &mut sums.pixels {
                    for _ in 0..samples {
                        p.add_sample(Vec3::splat(0.5), false);
                    }
                }
                encode_tile_sums(&sums)
            })
            .clone();
        // Header: "TSUM", format, x0, y0, width, height.
        bytes[8..12].copy_from_slice(&tile.x0.to_le_bytes());
        bytes[12..16].copy_from_slice(&tile.y0.to_le_bytes());
        bytes
    }
}
