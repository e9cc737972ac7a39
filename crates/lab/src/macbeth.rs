//! `tessera macbeth`: Kucherov et al.'s Macbeth chart by Monte Carlo over wavelength, and the study of
//! its noise against the number of wavelengths for each sampler.

use anyhow::{Context, Result};
use clap::{Args, ValueEnum};
use rayon::prelude::*;
use std::path::{Path, PathBuf};
use std::time::Instant;
use tessera_film::{ExrImage, write_exr, write_png};
use tessera_render::spectral::chart::{self, ChartSettings, PatchStats};
use tessera_render::spectral::color::{Illuminant, Primaries};
use tessera_render::spectral::wavelengths::WavelengthSampler;

#[derive(Clone, Copy, Debug, ValueEnum)]
pub enum SamplerArg {
    Uniform,
    Stratified,
    Hero,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
pub enum IlluminantArg {
    D65,
    A,
    E,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
pub enum MatrixArg {
    /// IEC 61966-2-1 sRGB.
    Srgb,
    /// CIE 1931 RGB: the matrix Kucherov et al. printed (its slip), for comparison.
    CieRgb,
}

#[derive(Args, Debug)]
pub struct MacbethArgs {
    /// Wavelengths per pixel (N).
    #[arg(long, default_value_t = 32, value_parser = clap::value_parser!(u32).range(1..=65536), env = "TESSERA_SAMPLES")]
    pub samples: u32,
    /// Wavelength sampler: independent uniform (Kucherov et al.), stratified, or hero wavelengths with a
    /// visible-importance pdf.
    #[arg(long, value_enum, default_value = "hero", env = "TESSERA_SAMPLER")]
    pub sampler: SamplerArg,
    /// The light the chart is seen under (E: equal energy).
    #[arg(long, value_enum, default_value = "d65", env = "TESSERA_ILLUMINANT")]
    pub illuminant: IlluminantArg,
    /// XYZ to RGB matrix.
    #[arg(long, value_enum, default_value = "srgb", env = "TESSERA_MATRIX")]
    pub matrix: MatrixArg,
    #[arg(long, default_value_t = 0, env = "TESSERA_SEED")]
    pub seed: u64,
    /// Output: the PNG (the linear EXR gets the same stem); with --study, a directory
    /// [default: macbeth.png, or macbeth-study/].
    #[arg(long, env = "TESSERA_OUT")]
    pub out: Option<PathBuf>,
    /// Render N = 32, 128, 512, 1024 with every sampler; write a CSV, a noise plot and a contact sheet.
    #[arg(long, env = "TESSERA_STUDY")]
    pub study: bool,
}

fn sampler(a: SamplerArg) -> WavelengthSampler {
    match a {
        SamplerArg::Uniform => WavelengthSampler::Uniform,
        SamplerArg::Stratified => WavelengthSampler::Stratified,
        SamplerArg::Hero => WavelengthSampler::Hero,
    }
}

pub fn run(args: MacbethArgs) -> Result<()> {
    let illuminant = match args.illuminant {
        IlluminantArg::D65 => Illuminant::D65,
        IlluminantArg::A => Illuminant::A,
        IlluminantArg::E => Illuminant::E,
    };
    let primaries = match args.matrix {
        MatrixArg::Srgb => Primaries::Srgb,
        MatrixArg::CieRgb => Primaries::CieRgb,
    };
    let base = ChartSettings {
        samples: args.samples as usize,
        sampler: sampler(args.sampler),
        illuminant,
        primaries,
        seed: args.seed,
    };
    if args.study {
        return study(base, &args.out.unwrap_or_else(|| PathBuf::from("macbeth-study")));
    }
    let out = args.out.unwrap_or_else(|| PathBuf::from("macbeth.png"));
    let started = Instant::now();
    let rgb = render(&base);
    let seconds = started.elapsed().as_secs_f64();
    let stats = chart::patch_stats(&rgb, &chart::exact_patches(illuminant, primaries));
    write_chart(&rgb, &base, &out)?;
    let worst = stats.iter().map(|s| s.max_pixel_error_8bit).fold(0.0, f64::max);
    println!(
        "{} wavelengths per pixel ({}), {:.2} s: noise {:.5} (linear), worst pixel {:.2} and worst patch mean {:.3} from exact on the 8-bit scale",
        base.samples,
        base.sampler.name(),
        seconds,
        chart::noise(&stats),
        worst,
        stats.iter().map(|s| s.mean_error_8bit).fold(0.0, f64::max)
    );
    eprintln!("wrote {} and {}", out.display(), out.with_extension("exr").display());
    Ok(())
}

/// The chart's linear RGB, row-major, on all threads.
fn render(settings: &ChartSettings) -> Vec<[f64; 3]> {
    (0..chart::HEIGHT).into_par_iter().flat_map_iter(|y| chart::row(settings, y)).collect()
}

fn image_of(rgb: &[[f64; 3]], width: u32, height: u32, metadata: String) -> ExrImage {
    ExrImage::from_rgb(width, height, rgb.iter().map(|p| p.map(|c| c as f32)).collect(), metadata)
}

/// PNG at `out` (sRGB, 8 bit) and the linear EXR beside it.
fn write_chart(rgb: &[[f64; 3]], s: &ChartSettings, out: &Path) -> Result<()> {
    let metadata = format!(
        "image=macbeth\nsamples={}\nsampler={}\nilluminant={}\nprimaries={:?}\nseed={}\nvariance=not estimated\n",
        s.samples,
        s.sampler.name(),
        s.illuminant.name(),
        s.primaries,
        s.seed
    );
    let mut image = image_of(rgb, chart::WIDTH, chart::HEIGHT, metadata);
    image.spp = vec![s.samples as f32; rgb.len()];
    if let Some(dir) = out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    write_png(&image, out)?;
    write_exr(&image, &out.with_extension("exr"))?;
    Ok(())
}

/// The N of Kucherov et al.'s figures.
const STUDY_N: [usize; 4] = [32, 128, 512, 1024];

struct Row {
    sampler: WavelengthSampler,
    n: usize,
    seconds: f64,
    noise: f64,
    worst_pixel: f64,
    worst_mean: f64,
}

fn study(base: ChartSettings, dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let exact = chart::exact_patches(base.illuminant, base.primaries);
    let mut rows = Vec::new();
    let mut sheet = vec![[0.0; 3]; (chart::WIDTH * chart::HEIGHT) as usize * STUDY_N.len() * 3];
    let sheet_width = chart::WIDTH as usize * STUDY_N.len();
    for (si, sampler) in WavelengthSampler::ALL.into_iter().enumerate() {
        for (ni, n) in STUDY_N.into_iter().enumerate() {
            let settings = ChartSettings { samples: n, sampler, ..base };
            let started = Instant::now();
            let rgb = render(&settings);
            let seconds = started.elapsed().as_secs_f64();
            let stats: Vec<PatchStats> = chart::patch_stats(&rgb, &exact);
            rows.push(Row {
                sampler,
                n,
                seconds,
                noise: chart::noise(&stats),
                worst_pixel: stats.iter().map(|s| s.max_pixel_error_8bit).fold(0.0, f64::max),
                worst_mean: stats.iter().map(|s| s.mean_error_8bit).fold(0.0, f64::max),
            });
            for y in 0..chart::HEIGHT as usize {
                for x in 0..chart::WIDTH as usize {
                    let (sx, sy) = (ni * chart::WIDTH as usize + x, si * chart::HEIGHT as usize + y);
                    sheet[sy * sheet_width + sx] = rgb[y * chart::WIDTH as usize + x];
                }
            }
            eprintln!("{:>10} N = {:>4}: {:.2} s", sampler.name(), n, seconds);
        }
    }
    let mut csv = String::from("sampler,n,seconds,noise,worst_pixel_error_8bit,worst_patch_mean_error_8bit\n");
    for r in &rows {
        csv += &format!(
            "{},{},{:.4},{:.6e},{:.4},{:.4}\n",
            r.sampler.name(),
            r.n,
            r.seconds,
            r.noise,
            r.worst_pixel,
            r.worst_mean
        );
    }
    std::fs::write(dir.join("macbeth-study.csv"), &csv)?;
    let sheet_image = image_of(&sheet, sheet_width as u32, chart::HEIGHT * 3, String::new());
    write_png(&sheet_image, &dir.join("macbeth-contact-sheet.png"))?;
    let slopes: Vec<(WavelengthSampler, f64)> = WavelengthSampler::ALL
        .into_iter()
        .map(|s| {
            let pts: Vec<(f64, f64)> = rows.iter().filter(|r| r.sampler == s).map(|r| (r.n as f64, r.noise)).collect();
            (s, chart::log_log_slope(&pts))
        })
        .collect();
    plot(&rows, &slopes, &dir.join("macbeth-noise.png"))?;
    println!("{:>10}  {:>12}  per chart at N = {STUDY_N:?}", "sampler", "noise slope");
    for (s, slope) in &slopes {
        let times: Vec<String> =
            rows.iter().filter(|r| r.sampler == *s).map(|r| format!("{:.2} s", r.seconds)).collect();
        println!("{:>10}  {:>12.3}  {}", s.name(), slope, times.join(", "));
    }
    for s in WavelengthSampler::ALL {
        let exact_at = rows.iter().find(|r| r.sampler == s && r.worst_pixel < 0.5).map(|r| r.n);
        match exact_at {
            Some(n) => println!("{:>10}: every pixel within 0.5 of exact (8-bit) from N = {n}", s.name()),
            None => {
                let last = rows.iter().rfind(|r| r.sampler == s).expect("rows for every sampler");
                let slope = slopes.iter().find(|x| x.0 == s).map_or(-0.5, |x| x.1);
                let needed = last.n as f64 * (0.5 / last.worst_pixel).powf(1.0 / slope);
                println!(
                    "{:>10}: worst pixel {:.2} from exact at N = {}; about N = {:.0} needed (extrapolated along the slope)",
                    s.name(),
                    last.worst_pixel,
                    last.n,
                    needed
                );
            }
        }
    }
    eprintln!("wrote macbeth-study.csv, macbeth-noise.png and macbeth-contact-sheet.png in {}", dir.display());
    Ok(())
}

fn plot(rows: &[Row], slopes: &[(WavelengthSampler, f64)], path: &Path) -> Result<()> {
    let series: Vec<crate::plot::Series> = slopes
        .iter()
        .map(|(s, slope)| crate::plot::Series {
            label: format!("{} (slope {:.2})", s.name(), slope),
            points: rows.iter().filter(|r| r.sampler == *s).map(|r| (r.n as f64, r.noise)).collect(),
        })
        .collect();
    crate::plot::log_log(
        path,
        "Macbeth chart: noise against wavelengths per pixel",
        "N (wavelengths per pixel)",
        "per-patch standard deviation (linear)",
        &series,
    )
}
