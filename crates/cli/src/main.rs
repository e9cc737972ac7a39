//! `tessera`: render glTF scenes with a Monte Carlo path tracer, compare images, inspect scenes.

mod client;
mod compare;
mod cpu;
mod farm;
mod fetch;
mod kept;
mod listing;
mod quote;
mod render;
mod resolve;
mod scene_info;
mod secret;
mod steer;

// The commands the README and the guides show, for the test below and the docs check
// (`tests/docs_e2e.rs`).
#[cfg(test)]
#[path = "../tests/common/docs.rs"]
mod docs;

use clap::{Parser, Subcommand};
use std::process::ExitCode;

#[derive(Parser)]
#[command(
    name = "tessera",
    version,
    about = "Tessera: a Monte Carlo render farm for glTF scenes.",
    long_about = None,
    after_help = "Every option can also be set by an environment variable, TESSERA_<OPTION> (TESSERA_COORDINATOR,\n\
                  TESSERA_TOKEN, TESSERA_SPP, ...; TESSERA_BENCH_<OPTION> and TESSERA_CHART_<OPTION> for\n\
                  benchmarks and charts): `tessera <COMMAND> --help` names each one. A flag on the command line\n\
                  wins over its variable."
)]
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
    /// Kucherov et al.'s Macbeth chart by Monte Carlo over wavelength, and its noise study (--study).
    #[cfg(feature = "study")]
    Macbeth(tessera_lab::macbeth::MacbethArgs),
    /// Measure ray throughput and rendering speed.
    #[cfg(feature = "study")]
    #[command(subcommand)]
    Bench(tessera_lab::bench::BenchCommand),
    /// Speed against accuracy: convergence charts of every estimator and sampler.
    #[cfg(feature = "study")]
    #[command(subcommand)]
    Chart(tessera_lab::chart::ChartCommand),
    /// The study commands (bench, chart, macbeth), left out of this build.
    #[cfg(not(feature = "study"))]
    #[command(name = "bench", alias = "chart", alias = "macbeth", hide = true)]
    Study {
        #[arg(trailing_var_arg = true, allow_hyphen_values = true, hide = true)]
        rest: Vec<String>,
    },
    /// Run a coordinator: plans renders, leases passes to workers, merges results exactly.
    Coordinator(farm::CoordinatorArgs),
    /// Run a worker: renders passes leased from a coordinator.
    Worker(farm::WorkerArgs),
    /// Submit a scene to a coordinator, follow it and write the image.
    Submit(client::SubmitArgs),
    /// Show renders on a coordinator.
    Status(client::StatusArgs),
    /// Follow a render until it ends.
    Watch(client::WatchArgs),
    /// Download a finished render, or a sequence's finished frames.
    Fetch(fetch::FetchArgs),
    /// Cancel a render.
    Cancel(client::RenderIdArgs),
    /// Queue a failed or cancelled render's unfinished passes again (what it rendered is kept).
    Retry(client::RenderIdArgs),
    /// Continue a finished render (or sequence) to more samples or a lower error: only the new
    /// passes render, and the image equals one submitted with that quality from the start.
    Refine(steer::RefineArgs),
    /// Pause a render or a whole sequence: it gets no new jobs until resumed (kept over restarts).
    Pause(steer::PauseArgs),
    /// Resume a paused render or sequence.
    Resume(steer::ResumeArgs),
    /// Say what a submitted render will take (samples, wall time, with a range) before it runs:
    /// the first round of a few of its tiles renders on the farm now, even while it is paused.
    Quote(quote::QuoteArgs),
    /// Change a render's or a sequence's priority (higher is served first; from the next job on).
    Priority(steer::PriorityArgs),
    /// Show what happened to a render or a sequence: submitted, jobs that failed and where,
    /// pauses and priorities and who set them, retries, its end.
    Log(steer::LogArgs),
    /// List the workers a coordinator has seen: what each is doing (busy, idle, lost, stopped),
    /// where it calls from, its speed, the jobs it holds and the renders they belong to, and how
    /// many results it returned and jobs it failed.
    Workers(client::WorkersArgs),
    /// Read a token from standard input and print the hash a token file (--tokens) lists for it.
    TokenHash,
    /// Copy a coordinator's database consistently (safe while it runs); start a coordinator on
    /// the copy to restore it.
    Backup(farm::BackupArgs),
}

fn main() -> ExitCode {
    if let Some(message) = cpu::missing_features() {
        eprintln!("error: {message}");
        return ExitCode::FAILURE;
    }
    let cli = Cli::try_parse().unwrap_or_else(|e| refused_command_line(e));
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
    if !uses_sockets(&cli.command) {
        quit_quietly_on_closed_pipe();
    }
    let result = match cli.command {
        Command::Render(a) => render::run(a),
        Command::Compare(a) => compare::run(a),
        Command::SceneInfo(a) => scene_info::run(a),
        #[cfg(feature = "study")]
        Command::Macbeth(a) => tessera_lab::macbeth::run(a),
        #[cfg(feature = "study")]
        Command::Bench(b) => tessera_lab::bench::run(b),
        #[cfg(feature = "study")]
        Command::Chart(c) => tessera_lab::chart::run(c),
        #[cfg(not(feature = "study"))]
        Command::Study { .. } => Err(anyhow::anyhow!(
            "this tessera was built without the study commands (bench, chart, macbeth): build it with \
             `cargo build --release -p tessera-cli --features study` (the default) to have them"
        )),
        Command::Coordinator(a) => farm::run_coordinator(a),
        Command::Worker(a) => farm::run_worker(a),
        Command::Submit(a) => client::run_submit(a),
        Command::Status(a) => client::run_status(a),
        Command::Watch(a) => client::run_watch(a),
        Command::Fetch(a) => fetch::run_fetch(a),
        Command::Cancel(a) => client::run_cancel(a),
        Command::Retry(a) => client::run_retry(a),
        Command::Refine(a) => steer::run_refine(a),
        Command::Pause(a) => steer::run_pause(a),
        Command::Resume(a) => steer::run_resume(a),
        Command::Quote(a) => quote::run_quote_submitted(a),
        Command::Priority(a) => steer::run_priority(a),
        Command::Log(a) => steer::run_log(a),
        Command::Workers(a) => client::run_workers(a),
        Command::TokenHash => token_hash(),
        Command::Backup(a) => farm::run_backup(a),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

/// `tessera token-hash`: the token from standard input (so that it stays out of the shell's
/// history), checked as every token is, and its hash for a token file line.
fn token_hash() -> anyhow::Result<()> {
    let mut token = String::new();
    std::io::stdin().read_line(&mut token)?;
    let token = token.trim_end_matches(['\r', '\n']);
    tessera_proto::token::check_token(token).map_err(anyhow::Error::msg)?;
    listing::print(&format!("{}\n", tessera_coordinator::users::token_hash(token)))
}

/// Commands that talk over TCP: writing to a socket the peer has closed raises SIGPIPE too
/// (hyper writes with writev, which cannot ask for no signal), and must be an error the command
/// handles, not the end of the process. Their standard output goes through `listing::print`.
/// Prints clap's answer to a command line it refused, and exits. clap repeats a refused value
/// as it was given; each line is printed with control and format characters escaped, so that a
/// value holding an escape sequence or a bidi override (say, `--variant`) never reaches the
/// terminal raw. Help and version go out as clap writes them.
fn refused_command_line(e: clap::Error) -> ! {
    use clap::error::ErrorKind;
    if matches!(
        e.kind(),
        ErrorKind::DisplayHelp | ErrorKind::DisplayVersion | ErrorKind::DisplayHelpOnMissingArgumentOrSubcommand
    ) {
        e.exit()
    }
    eprint!("{}", tessera_request::printable_lines(&e.render().to_string()));
    std::process::exit(e.exit_code())
}

fn uses_sockets(command: &Command) -> bool {
    match command {
        Command::Render(a) => a.workers > 0,
        #[cfg(feature = "study")]
        Command::Bench(b) => {
            matches!(b, tessera_lab::bench::BenchCommand::Coordinator(_) | tessera_lab::bench::BenchCommand::Farm(_))
        }
        #[cfg(feature = "study")]
        Command::Macbeth(_) | Command::Chart(_) => false,
        #[cfg(not(feature = "study"))]
        Command::Study { .. } => false,
        Command::Compare(_) | Command::SceneInfo(_) | Command::TokenHash | Command::Backup(_) => false,
        Command::Coordinator(_)
        | Command::Worker(_)
        | Command::Submit(_)
        | Command::Status(_)
        | Command::Watch(_)
        | Command::Fetch(_)
        | Command::Cancel(_)
        | Command::Retry(_)
        | Command::Refine(_)
        | Command::Pause(_)
        | Command::Resume(_)
        | Command::Quote(_)
        | Command::Priority(_)
        | Command::Log(_)
        | Command::Workers(_) => true,
    }
}

/// Lets a command whose output goes to a closed pipe (`tessera bench cornell | head`) end as
/// other command-line tools do, by SIGPIPE, instead of panicking in `println!` (Rust ignores
/// SIGPIPE, so writes fail). Not for commands that use sockets ([`uses_sockets`]).
fn quit_quietly_on_closed_pipe() {
    #[cfg(unix)]
    // SAFETY: restoring the default action of one signal, before any thread that could be
    // handling it exists; no Rust state depends on SIGPIPE being ignored in these commands.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::CommandFactory;

    /// Every option of every subcommand, as (command path, long name, environment variable).
    fn options(cmd: &clap::Command, path: &str, out: &mut Vec<(String, String, Option<String>)>) {
        for arg in cmd.get_arguments() {
            let Some(long) = arg.get_long() else { continue };
            if arg.is_positional() || matches!(long, "help" | "version") {
                continue;
            }
            out.push((path.to_string(), long.to_string(), arg.get_env().map(|e| e.to_string_lossy().into_owned())));
        }
        for sub in cmd.get_subcommands() {
            options(sub, &format!("{path} {}", sub.get_name()), out);
        }
    }

    #[test]
    fn every_flag_has_an_environment_variable() {
        let mut all = Vec::new();
        options(&Cli::command(), "tessera", &mut all);
        let missing: Vec<String> =
            all.iter().filter(|(_, _, env)| env.is_none()).map(|(p, l, _)| format!("{p} --{l}")).collect();
        assert!(missing.is_empty(), "flags without an environment variable: {missing:#?}");
        // TESSERA_<FLAG>; benchmarks and charts keep to TESSERA_BENCH_<FLAG> and
        // TESSERA_CHART_<FLAG>, a worker's name is TESSERA_WORKER_NAME and a render's
        // TESSERA_RENDER_NAME (TESSERA_NAME would say nothing).
        for (path, long, env) in &all {
            let flag = long.to_uppercase().replace('-', "_");
            let expected = if path.starts_with("tessera bench") {
                format!("TESSERA_BENCH_{flag}")
            } else if path.starts_with("tessera chart") {
                format!("TESSERA_CHART_{flag}")
            } else if long == "name" && path.starts_with("tessera worker") {
                "TESSERA_WORKER_NAME".to_string()
            } else if long == "name" {
                "TESSERA_RENDER_NAME".to_string()
            } else {
                format!("TESSERA_{flag}")
            };
            assert_eq!(env.as_deref(), Some(expected.as_str()), "{path} --{long}");
        }
    }

    #[test]
    fn the_command_line_is_consistent() {
        Cli::command().debug_assert();
    }

    /// Every `tessera` command the README and the guides show parses: its subcommand, flags and
    /// values are what this binary takes (the docs check runs the quick ones, and
    /// `readme_local_walkthrough` the farm on one machine).
    #[test]
    fn every_documented_command_parses() {
        let repo = docs::repository(env!("CARGO_MANIFEST_DIR"));
        let commands = docs::documented_commands(&repo);
        assert!(commands.len() >= 30, "only {} documented commands found", commands.len());
        let refused: Vec<String> = commands
            .iter()
            .filter_map(|c| {
                let args = std::iter::once("tessera".to_string()).chain(c.args.iter().cloned());
                match Cli::try_parse_from(args) {
                    Ok(_) => None,
                    Err(e) if e.kind() == clap::error::ErrorKind::DisplayHelp => None,
                    Err(e) => Some(format!("{c}\n  {}", e.to_string().lines().next().unwrap_or(""))),
                }
            })
            .collect();
        assert!(refused.is_empty(), "documented commands this binary refuses:\n{}", refused.join("\n"));
    }
}
