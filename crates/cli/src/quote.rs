//! What a render will take, said before the farm spends it. `tessera submit --quote`: a short
//! pilot on this machine predicts the samples (`tessera_local::quote`), and the farm's live
//! workers and their measured speeds turn them into wall time. `tessera quote ID`: a submitted
//! render's (one submitted `--paused`, or waiting behind others) pilot runs on the farm itself,
//! as the render's own first passes, and the coordinator predicts the rest.

use crate::client::{Connection, SubmitArgs, answer, block_on};
use crate::resolve::{Resolved, resolve};
use anyhow::{Context, Result};
use clap::Args;
use tessera_local::quote::PILOT_TILES;
use tessera_proto::PROTOCOL_VERSION;
use tessera_proto::v1::{RenderQuote, RenderRequest, RenderState, SteerRequest};

/// The farm's workers that can take work now: their count, threads and samples a second.
struct Farm {
    workers: usize,
    threads: u64,
    samples_per_second: f64,
}

pub fn run_quote(args: &SubmitArgs) -> Result<()> {
    let Resolved { loaded, setup, sampling, how_many, frames, .. } =
        resolve(&args.scene, &args.options, &args.animation)?;
    let frames = frames.map_or(1, |f| f.list.0.len() as u64);
    if !args.quiet {
        eprintln!("pilot: rendering up to {PILOT_TILES} tiles' first round on this machine");
    }
    let q = tessera_local::quote::quote(&loaded.scene, &setup.settings, sampling, 0, PILOT_TILES)?;
    let farm = crate::client::block_on(async {
        let mut client = args.connection.connect().await?;
        let workers = crate::client::all_workers(&mut client).await?;
        let live: Vec<_> = workers.iter().filter(|w| matches!(w.state.as_str(), "busy" | "idle")).collect();
        Ok(Farm {
            workers: live.len(),
            threads: live.iter().map(|w| w.threads as u64).sum(),
            samples_per_second: live.iter().map(|w| w.samples_per_second).sum(),
        })
    });
    let s = &setup.settings;
    let m = |n: u64| n as f64 * frames as f64 / 1e6;
    println!("quote for {}: {}x{}, {how_many}{}", args.scene, s.width, s.height, plural_frames(frames));
    println!(
        "  samples: {:.1} M ({:.1}-{:.1} M), {:.1} spp on average",
        m(q.samples),
        m(q.samples_low),
        m(q.samples_high),
        q.mean_spp()
    );
    let cost = |seconds: f64| seconds * frames as f64;
    println!(
        "  on this machine: {:.0} core-seconds ({:.0}-{:.0}); the pilot rendered {} of {} tiles, {:.2} M samples in {:.2} s on {} threads",
        cost(q.core_seconds),
        cost(q.core_seconds_low),
        cost(q.core_seconds_high),
        q.pilot_tiles,
        q.tiles,
        q.pilot_samples as f64 / 1e6,
        q.pilot_seconds,
        q.threads
    );
    match farm {
        Ok(f) if f.samples_per_second > 0.0 => {
            // The farm's speed is over the jobs it ran; this render's samples cost the pilot's
            // weight more (or less) a sample.
            let wall = |n: u64| n as f64 * frames as f64 * q.cost_weight() / f.samples_per_second;
            let core = |n: u64| wall(n) * f.threads as f64;
            println!(
                "  on the farm: {} live worker(s), {} threads, {:.1} M samples/s measured: about {} ({}-{}), {:.0} core-seconds ({:.0}-{:.0})",
                f.workers,
                f.threads,
                f.samples_per_second / 1e6,
                duration(wall(q.samples)),
                duration(wall(q.samples_low)),
                duration(wall(q.samples_high)),
                core(q.samples),
                core(q.samples_low),
                core(q.samples_high)
            );
        }
        Ok(f) => println!(
            "  on the farm: {} live worker(s), none with a measured speed yet: no wall time to quote",
            f.workers
        ),
        Err(e) => println!("  on the farm: not reached ({e:#}): no wall time to quote"),
    }
    println!("  (nothing was submitted: run the same command without --quote to render it)");
    Ok(())
}

fn plural_frames(frames: u64) -> String {
    if frames > 1 { format!(", {frames} frames (each quoted as the first)") } else { String::new() }
}

/// Seconds as a person reads them.
fn duration(seconds: f64) -> String {
    match seconds {
        s if s < 90.0 => format!("{s:.0} s"),
        s if s < 5400.0 => format!("{:.0} min", s / 60.0),
        s => format!("{:.1} h", s / 3600.0),
    }
}

#[derive(Args, Debug)]
pub struct QuoteArgs {
    /// The render id, or a sequence's (s and a number: its first running frame is quoted).
    pub render: String,
    /// Print the quote as one JSON object, for scripts.
    #[arg(long, env = "TESSERA_JSON")]
    pub json: bool,
    #[command(flatten)]
    pub connection: Connection,
}

/// `tessera quote ID`: asks for a submitted render's pilot, waits until its tiles are judged
/// (or the render ends), and says what the render will take.
pub fn run_quote_submitted(args: QuoteArgs) -> Result<()> {
    block_on(async {
        let mut client = args.connection.connect().await?;
        let request = SteerRequest {
            protocol_version: PROTOCOL_VERSION,
            render_id: args.render.clone(),
            pilot: true,
            ..SteerRequest::default()
        };
        let asked = answer("the quote", client.steer_render(request)).await?;
        let status = asked.status.context("the coordinator said nothing of the render")?;
        let id = status.render_id.clone();
        let request =
            RenderRequest { protocol_version: PROTOCOL_VERSION, render_id: id.clone(), frame: None, preview: false };
        let mut watch = answer("the watch", client.watch_render(request)).await?;
        let (mut last, mut told_waiting) = (status, false);
        while let Some(q) = &last.quote {
            let pilot = PILOT_TILES.min(q.tiles as usize);
            if q.tiles_judged as usize >= pilot {
                break;
            }
            if last.no_workers && !told_waiting {
                eprintln!("render {id}: no worker is connected; the pilot waits for one (Ctrl-C stops waiting)");
                told_waiting = true;
            }
            if !args.json {
                eprint!("\rpilot on the farm: {} of {pilot} tiles judged ", q.tiles_judged);
            }
            match watch.message().await? {
                Some(s) => last = s,
                None => break,
            }
        }
        if !args.json {
            eprintln!();
        }
        print_farm_quote(&id, &last, args.json)
    })
}

/// Prints render `id`'s quote as `status` last gave it.
fn print_farm_quote(id: &str, status: &tessera_proto::v1::RenderStatus, json: bool) -> Result<()> {
    let Some(q) = &status.quote else {
        let state = RenderState::try_from(status.state).map_or("unknown", |s| s.as_str_name());
        anyhow::bail!("render {id} has no quote: it is {} (only a running render has one)", state.to_lowercase());
    };
    let RenderQuote { samples, samples_low, samples_high, samples_done, tiles_judged, tiles, .. } = *q;
    // Wall time left: the samples still to render at the live workers' measured speed.
    let left =
        |n: u64| (q.samples_per_second > 0.0).then(|| n.saturating_sub(samples_done) as f64 / q.samples_per_second);
    if json {
        let value = serde_json::json!({
            "render_id": id,
            "paused": status.paused,
            "tiles_judged": tiles_judged,
            "tiles": tiles,
            "samples": samples,
            "samples_low": samples_low,
            "samples_high": samples_high,
            "samples_done": samples_done,
            "workers": q.workers,
            "threads": q.threads,
            "samples_per_second": q.samples_per_second,
            "seconds_left": left(samples),
            "seconds_left_low": left(samples_low),
            "seconds_left_high": left(samples_high),
        });
        return crate::listing::print(&format!("{value}\n"));
    }
    let m = |n: u64| n as f64 / 1e6;
    let paused = if status.paused { " (paused)" } else { "" };
    let mut out = format!("quote for render {id}{paused}, from {tiles_judged} of {tiles} tiles judged on the farm\n");
    out += &format!(
        "  samples: {:.1} M ({:.1}-{:.1} M), {:.1} M rendered so far\n",
        m(samples),
        m(samples_low),
        m(samples_high),
        m(samples_done)
    );
    out += &match (left(samples), left(samples_low), left(samples_high)) {
        (Some(wall), Some(low), Some(high)) => format!(
            "  on the farm: {} live worker(s), {} threads, {:.1} M samples/s measured: about {} ({}-{}) left once it runs\n",
            q.workers,
            q.threads,
            q.samples_per_second / 1e6,
            duration(wall),
            duration(low),
            duration(high)
        ),
        _ => format!(
            "  on the farm: {} live worker(s) that may take it, none with a measured speed yet: no wall time to quote\n",
            q.workers
        ),
    };
    if status.paused {
        out += &format!("  (`tessera resume {id}` starts it: the pilot's passes are its own first ones)\n");
    }
    crate::listing::print(&out)
}
