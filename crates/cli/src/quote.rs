//! `tessera submit --quote`: what a render will take, said before the farm spends anything on it.
//! A short pilot on this machine predicts the samples (`tessera_local::quote`); the farm's live
//! workers and their measured speeds turn them into wall time.

use crate::client::SubmitArgs;
use crate::resolve::{Resolved, resolve};
use anyhow::Result;
use tessera_local::quote::PILOT_TILES;

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
