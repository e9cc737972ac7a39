//! `tessera`: render glTF scenes with a Monte Carlo path tracer, compare images, inspect scenes.

mod bench;
mod bench_farm;
mod client;
mod compare;
mod farm;
mod local;
mod options;
mod render;
mod scene_info;

use clap::{Parser, Subcommand};
use std::process::ExitCode;

#[derive(Parser)]
#[command(name = "tessera", version, about = "Tessera: a Monte Carlo render farm for glTF scenes.", long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
    /// Log level: error, warn, info, debug or trace (also RUST_LOG).
    #[arg(long, global = true, default_value = "info", env = "TESSERA_LOG")]
    log: String,
    /// Log format: human-readable text or one JSON object per line.
    #[arg(long, global = true, value_enum, default_value = "human", env = "TESSERA_LOG_FORMAT")]
    log_format: LogFormat,
}

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
enum LogFormat {
    Human,
    Json,
}

#[derive(Subcommand)]
enum Command {
    /// Render a scene on this machine and write an OpenEXR image and a PNG preview.
    Render(render::RenderArgs),
    /// Compare two EXR images: RMSE and relative MSE.
    Compare(compare::CompareArgs),
    /// Print a scene's triangles, materials, lights, cameras, extensions and warnings.
    SceneInfo(scene_info::SceneInfoArgs),
    /// Measure ray throughput and rendering speed.
    #[command(subcommand)]
    Bench(bench::BenchCommand),
    /// Run a coordinator: plans renders, leases passes to workers, merges results exactly.
    Coordinator(farm::CoordinatorArgs),
    /// Run a worker: renders passes leased from a coordinator.
    Worker(farm::WorkerArgs),
    /// Submit a scene to a coordinator, follow it and write the image.
    Submit(client::SubmitArgs),
    /// Show renders on a coordinator.
    Status(client::StatusArgs),
    /// Follow a render until it ends.
    Watch(client::RenderIdArgs),
    /// Download a finished render.
    Fetch(client::FetchArgs),
    /// Cancel a render.
    Cancel(client::RenderIdArgs),
    /// List the workers a coordinator has seen.
    Workers(client::WorkersArgs),
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(&cli.log));
    use std::io::IsTerminal;
    let logs = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_target(false)
        .with_ansi(std::io::stderr().is_terminal());
    match cli.log_format {
        LogFormat::Human => logs.init(),
        LogFormat::Json => logs.json().init(),
    }
    let result = match cli.command {
        Command::Render(a) => render::run(a),
        Command::Compare(a) => compare::run(a),
        Command::SceneInfo(a) => scene_info::run(a),
        Command::Bench(b) => bench::run(b),
        Command::Coordinator(a) => farm::run_coordinator(a),
        Command::Worker(a) => farm::run_worker(a),
        Command::Submit(a) => client::run_submit(a),
        Command::Status(a) => client::run_status(a),
        Command::Watch(a) => client::run_watch(a),
        Command::Fetch(a) => client::run_fetch(a),
        Command::Cancel(a) => client::run_cancel(a),
        Command::Workers(a) => client::run_workers(a),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}
