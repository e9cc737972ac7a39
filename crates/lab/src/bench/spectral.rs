//! `tessera bench spectral`: spectral against RGB transport on the Cornell box at equal time.
//! The truth is a converged spectral render of the measured spectra. RGB renders the same scene
//! with each spectrum replaced by its colour (reflectances under D65, the light at its
//! luminance): what a user converting the measured data to RGB would render. RGB is cheaper per
//! sample but biased (the colour of a product of spectra is not the product of their colours);
//! spectral is unbiased but pays for four wavelengths and colour noise.

use crate::bench::{default_options, median, time};
use anyhow::{Context, Result};
use clap::Args;
use indicatif::ProgressBar;
use std::path::PathBuf;
use std::time::Instant;
use tessera_film::{ExrImage, compare};
use tessera_local::load_scene;
use tessera_local::options::{ColorArg, Sampling};
use tessera_local::render_film;
use tessera_render::{RenderSettings, Scene};

#[derive(Args, Debug)]
pub struct SpectralBenchArgs {
    /// Image side in pixels.
    #[arg(long, default_value_t = 128, env = "TESSERA_BENCH_SIZE")]
    pub size: u32,
    /// Converged spectral reference EXR; rendered (and written here) when the file does not exist.
    #[arg(long, default_value = "cornell-spectral-reference.exr", env = "TESSERA_BENCH_REFERENCE")]
    pub reference: PathBuf,
    /// Samples per pixel of the reference when it has to be rendered.
    #[arg(long, default_value_t = 8192, env = "TESSERA_BENCH_REFERENCE_SPP")]
    pub reference_spp: u32,
    /// Time budgets in seconds (two threads), comma-separated.
    #[arg(long, default_value = "0.25,0.5,1,2,4", value_delimiter = ',', env = "TESSERA_BENCH_BUDGETS")]
    pub budgets: Vec<f64>,
    /// Repetitions of the throughput runs; the median is reported.
    #[arg(long, default_value_t = 3, env = "TESSERA_BENCH_REPEAT")]
    pub repeat: usize,
}

const THREADS: usize = 2;

pub fn spectral(args: SpectralBenchArgs) -> Result<()> {
    let spectral_scene = load_scene("builtin:cornell-box", &default_options())?.scene;
    let mut rgb_scene = load_scene("builtin:cornell-box", &default_options())?.scene;
    for m in rgb_scene.surfaces.materials_mut() {
        m.match_rgb_to_spectra();
    }
    let spectral = settings(&spectral_scene, args.size, ColorArg::Spectral, 1)?;
    let rgb = settings(&rgb_scene, args.size, ColorArg::Rgb, 1)?;
    println!("cornell box {0}x{0}, measured spectra, mis, sobol, {1:?}, {THREADS} threads", args.size, rgb.termination);
    let pixels = (args.size * args.size) as f64;
    let rate = |scene: &Scene, s: &RenderSettings| {
        let secs = median(
            (0..args.repeat.max(1))
                .map(|_| time(|| drop(render_film(scene, s, Sampling::fixed(32), THREADS, &ProgressBar::hidden()))))
                .collect(),
        );
        pixels * 32.0 / secs
    };
    let (rate_rgb, rate_spectral) = (rate(&rgb_scene, &rgb), rate(&spectral_scene, &spectral));
    println!(
        "throughput: rgb {:.2} M samples/s, spectral {:.2} M samples/s: a spectral sample costs {:.2}x",
        rate_rgb / 1e6,
        rate_spectral / 1e6,
        rate_rgb / rate_spectral
    );
    let reference = load_or_render_reference(&spectral_scene, &args)?;
    println!(
        "{:<9} {:>8} {:>6} {:>8} {:>9} {:>18}",
        "colour", "budget", "spp", "seconds", "rmse", "rmse (no emitters)"
    );
    for &budget in &args.budgets {
        for (name, scene, s, rate) in
            [("rgb", &rgb_scene, &rgb, rate_rgb), ("spectral", &spectral_scene, &spectral, rate_spectral)]
        {
            let spp = ((budget * rate / pixels).round() as u32).max(1);
            let t = Instant::now();
            let image = render_film(scene, s, Sampling::fixed(spp), THREADS, &ProgressBar::hidden())?.resolve();
            let secs = t.elapsed().as_secs_f64();
            let (all, lit) = errors(&image, &reference)?;
            println!("{name:<9} {budget:>7.2}s {spp:>6} {secs:>8.3} {all:>9.5} {lit:>18.5}");
        }
    }
    // RGB's error cannot fall below its bias: measure it with noise far below it.
    let floor_spp = (args.reference_spp / 4).max(1);
    let image = render_film(&rgb_scene, &rgb, Sampling::fixed(floor_spp), 0, &ProgressBar::hidden())?.resolve();
    let (all, lit) = errors(&image, &reference)?;
    println!("rgb bias floor: rmse {all:.5} (no emitters {lit:.5}) at {floor_spp} spp");
    Ok(())
}

fn settings(scene: &Scene, size: u32, color: ColorArg, seed: u64) -> Result<RenderSettings> {
    let mut options = default_options();
    (options.width, options.height, options.seed) = (size, size, seed);
    options.max_bounces = Some(7); // as `bench cornell` and Mitsuba's max_depth 8
    options.color = Some(color);
    Ok(options.settings(scene)?.0)
}

/// RMSE against the reference, with and without directly seen emitters.
fn errors(image: &ExrImage, reference: &ExrImage) -> Result<(f64, f64)> {
    let all = compare(image, reference, false).context("reference size differs")?;
    let lit = compare(image, reference, true).context("reference size differs")?;
    Ok((all.rmse, lit.rmse))
}

fn load_or_render_reference(scene: &Scene, args: &SpectralBenchArgs) -> Result<ExrImage> {
    let s = settings(scene, args.size, ColorArg::Spectral, 999)?;
    tessera_local::load_or_render_reference(scene, "builtin:cornell-box", &s, args.reference_spp, &args.reference)
}
