//! `tessera chart convergence`: speed against accuracy. Every estimator (Dimov, Gurov and Penzov's collision
//! estimator with uniform, cosine and BRDF densities; NEE; MIS) with every sampler (independent,
//! Sobol) renders at doubling spp within a time budget; each render's error against a converged
//! reference (cached by scene hash and settings) goes to a CSV and two log-log plots.

mod brdf;
mod quality;
mod stability;

use crate::bench::default_options;
use crate::plot::{Series, log_log};
use anyhow::{Context, Result, bail};
use clap::{Args, Subcommand};
use indicatif::ProgressBar;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;
use tessera_film::{ExrImage, compare, read_exr};
use tessera_local::load_scene;
use tessera_local::options::Sampling;
use tessera_local::render_film;
use tessera_render::{Density, Estimator, RenderSettings, SamplerKind, Scene};

#[derive(Subcommand, Debug)]
pub enum ChartCommand {
    /// Error against time and against spp for every estimator and sampler: CSV and PNG plots.
    Convergence(ConvergenceArgs),
    /// Albedo maps over view angle and roughness of Dimov, Gurov and Penzov's BRDF as printed and of the
    /// normalised form Tessera renders: where the printed form reflects more than it receives.
    Brdf(BrdfArgs),
    /// The stability suite's pictures: each failure scene with the failing and surviving methods.
    Stability(StabilityArgs),
    /// --quality auto against --quality fixed at equal time on several scenes: CSV, PNG, table.
    Quality(QualityArgs),
}

#[derive(Args, Debug)]
pub struct QualityArgs {
    /// Scenes, comma-separated or repeated [default: the Cornell box (measured spectra), gold in
    /// a white sky, a rough metal floor under a large panel light].
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "builtin:cornell-box,builtin:furnace?metal=Au&roughness=0.3,builtin:glossy-floor?roughness=0.3",
        env = "TESSERA_CHART_SCENE"
    )]
    pub scene: Vec<String>,
    /// Seconds of rendering for each setting on each scene.
    #[arg(long, default_value_t = 4.0, env = "TESSERA_CHART_BUDGET")]
    pub budget: f64,
    /// Directory for quality.csv and quality.png.
    #[arg(long, default_value = "quality", env = "TESSERA_CHART_OUT")]
    pub out: PathBuf,
    /// Image side in pixels.
    #[arg(long, default_value_t = 128, value_parser = clap::value_parser!(u32).range(8..=2048), env = "TESSERA_CHART_SIZE")]
    pub size: u32,
    /// Samples per pixel of each reference (rendered once, then cached under --cache).
    #[arg(long, default_value_t = 16384, value_parser = clap::value_parser!(u32).range(4..=(1 << 20)), env = "TESSERA_CHART_REFERENCE_SPP")]
    pub reference_spp: u32,
    /// Where rendered references are kept.
    #[arg(long, default_value = "tessera-references", env = "TESSERA_CHART_CACHE")]
    pub cache: PathBuf,
    /// Render threads [default: all cores].
    #[arg(long, default_value_t = 0, env = "TESSERA_CHART_THREADS")]
    pub threads: usize,
}

#[derive(Args, Debug)]
pub struct StabilityArgs {
    /// Directory for stability.csv and stability.png.
    #[arg(long, default_value = "stability", env = "TESSERA_CHART_OUT")]
    pub out: PathBuf,
    /// Side of each picture in pixels.
    #[arg(long, default_value_t = 128, value_parser = clap::value_parser!(u32).range(8..=1024), env = "TESSERA_CHART_SIZE")]
    pub size: u32,
    /// Samples per pixel of every picture (equal for all methods).
    #[arg(long, default_value_t = 64, value_parser = clap::value_parser!(u32).range(1..=65536), env = "TESSERA_CHART_SPP")]
    pub spp: u32,
}

#[derive(Args, Debug)]
pub struct BrdfArgs {
    /// Directory for brdf-albedo.csv and brdf-albedo.png.
    #[arg(long, default_value = "brdf", env = "TESSERA_CHART_OUT")]
    pub out: PathBuf,
    /// Quadrature cells in cos(theta) per albedo (4x as many in phi).
    #[arg(long, default_value_t = 256, value_parser = clap::value_parser!(u32).range(8..=2048), env = "TESSERA_CHART_RESOLUTION")]
    pub resolution: u32,
}

#[derive(Args, Debug)]
pub struct ConvergenceArgs {
    /// Scene: a .gltf or .glb file, or builtin:NAME.
    #[arg(long, default_value = "builtin:cornell-box", env = "TESSERA_CHART_SCENE")]
    pub scene: String,
    /// Converged reference EXR [default: rendered once with MIS and Sobol at --reference-spp and
    /// cached under --cache, keyed by the scene's hash and the settings].
    #[arg(long, env = "TESSERA_CHART_REFERENCE")]
    pub reference: Option<PathBuf>,
    /// Seconds of rendering for each estimator and sampler.
    #[arg(long, default_value_t = 4.0, env = "TESSERA_CHART_BUDGET")]
    pub budget: f64,
    /// Directory for convergence.csv, error-vs-time.png and error-vs-spp.png.
    #[arg(long, default_value = "convergence", env = "TESSERA_CHART_OUT")]
    pub out: PathBuf,
    /// Image side in pixels.
    #[arg(long, default_value_t = 128, value_parser = clap::value_parser!(u32).range(8..=2048), env = "TESSERA_CHART_SIZE")]
    pub size: u32,
    /// Samples per pixel of a reference that has to be rendered.
    #[arg(long, default_value_t = 16384, env = "TESSERA_CHART_REFERENCE_SPP")]
    pub reference_spp: u32,
    /// Where rendered references are kept.
    #[arg(long, default_value = "tessera-references", env = "TESSERA_CHART_CACHE")]
    pub cache: PathBuf,
    /// Stop paths after B bounces [default: the renderer's own choice, k_eps or Russian roulette].
    #[arg(long, env = "TESSERA_CHART_MAX_BOUNCES")]
    pub max_bounces: Option<u32>,
    /// Render threads [default: all cores].
    #[arg(long, default_value_t = 0, env = "TESSERA_CHART_THREADS")]
    pub threads: usize,
}

pub fn run(cmd: ChartCommand) -> Result<()> {
    match cmd {
        ChartCommand::Convergence(a) => convergence(a),
        ChartCommand::Brdf(a) => crate::chart::brdf::brdf(a),
        ChartCommand::Stability(a) => crate::chart::stability::stability(a),
        ChartCommand::Quality(a) => crate::chart::quality::quality(a),
    }
}

/// The methods charted: an estimator with, for the collision estimator, its density.
pub const METHODS: [(&str, Estimator, Density); 5] = [
    ("collision-uniform", Estimator::Collision, Density::Uniform),
    ("collision-cosine", Estimator::Collision, Density::Cosine),
    ("collision-brdf", Estimator::Collision, Density::Brdf),
    ("nee", Estimator::Nee, Density::Brdf),
    ("mis", Estimator::Mis, Density::Brdf),
];

/// One render of the chart.
struct Row {
    method: &'static str,
    sampler: SamplerKind,
    spp: u32,
    seconds: f64,
    rmse: f64,
    rel_mse: f64,
}

fn convergence(args: ConvergenceArgs) -> Result<()> {
    if !(args.budget > 0.0 && args.budget.is_finite()) {
        bail!("--budget {} must be a positive number of seconds", args.budget);
    }
    let loaded = load_scene(&args.scene, &default_options())?;
    let scene = &loaded.scene;
    let mut options = default_options();
    (options.width, options.height, options.max_bounces) = (args.size, args.size, args.max_bounces);
    let (base, how) = options.settings(scene)?;
    eprintln!("{}: {}x{}, {how}", args.scene, args.size, args.size);
    let reference = reference(scene, &loaded.hash, &base, &args)?;
    std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    let mut rows = Vec::new();
    for (method, estimator, density) in METHODS {
        for sampler in [SamplerKind::Independent, SamplerKind::Sobol] {
            let settings = RenderSettings { estimator, density, sampler, seed: 1, ..base.clone() };
            rows.extend(series(scene, &settings, method, &reference, &args)?);
        }
    }
    write_csv(&rows, &args.scene, &args.out.join("convergence.csv"))?;
    plots(&rows, &args)?;
    eprintln!("wrote convergence.csv, error-vs-time.png and error-vs-spp.png in {}", args.out.display());
    Ok(())
}

/// Calls `render(spp)`, which returns the seconds it took, at 1, 2, 4, ... spp until `budget`
/// seconds are spent (or the next render, about twice as long, would overrun them), or until
/// the reference's own noise would matter: at most a quarter of its spp.
pub(crate) fn doubling_spp(
    reference: &ExrImage,
    budget: f64,
    mut render: impl FnMut(u32) -> Result<f64>,
) -> Result<()> {
    let max_spp = (tessera_local::reference_spp(reference) / 4).max(1);
    let (mut spent, mut spp) = (0.0, 1u32);
    loop {
        let seconds = render(spp)?;
        spent += seconds;
        if spent + 2.0 * seconds > budget || spp >= max_spp {
            return Ok(());
        }
        spp *= 2;
    }
}

/// One method's renders at doubling spp within the budget.
fn series(
    scene: &Scene,
    settings: &RenderSettings,
    method: &'static str,
    reference: &ExrImage,
    args: &ConvergenceArgs,
) -> Result<Vec<Row>> {
    let mut rows = Vec::new();
    doubling_spp(reference, args.budget, |spp| {
        let t = Instant::now();
        let image = render_film(scene, settings, Sampling::fixed(spp), args.threads, &ProgressBar::hidden())?.resolve();
        let seconds = t.elapsed().as_secs_f64();
        let c = compare(&image, reference, true).context("the reference's size differs from --size")?;
        eprintln!(
            "{method:<17} {:<11} {spp:>6} spp {seconds:>8.3} s  rmse {:.5}  relmse {:.5}",
            settings.sampler.name(),
            c.rmse,
            c.rel_mse
        );
        rows.push(Row { method, sampler: settings.sampler, spp, seconds, rmse: c.rmse, rel_mse: c.rel_mse });
        Ok(seconds)
    })?;
    Ok(rows)
}

/// Loads `--reference`, or the cached one for this scene and settings, or renders and caches it.
fn reference(scene: &Scene, hash: &str, base: &RenderSettings, args: &ConvergenceArgs) -> Result<ExrImage> {
    if let Some(path) = &args.reference {
        return read_exr(path).with_context(|| format!("reading the reference {}", path.display()));
    }
    let settings =
        RenderSettings { estimator: Estimator::Mis, sampler: SamplerKind::Sobol, seed: 0x5EED, ..base.clone() };
    cached_reference(scene, &args.scene, hash, &settings, args.reference_spp, &args.cache)
}

/// A reference rendered once and kept in `cache`, named by the BLAKE3 hash of the scene's hash,
/// the settings and the spp, so that any change of them renders a new one.
pub(crate) fn cached_reference(
    scene: &Scene,
    label: &str,
    hash: &str,
    settings: &RenderSettings,
    spp: u32,
    cache: &Path,
) -> Result<ExrImage> {
    let key = blake3::hash(format!("{hash}\n{}\nspp={spp}", settings.describe()).as_bytes());
    let path = cache.join(format!("reference-{}.exr", &key.to_hex()[..16]));
    tessera_local::load_or_render_reference(scene, label, settings, spp, &path)
}

fn write_csv(rows: &[Row], scene: &str, path: &Path) -> Result<()> {
    let mut f =
        std::io::BufWriter::new(std::fs::File::create(path).with_context(|| format!("creating {}", path.display()))?);
    writeln!(f, "scene,method,sampler,spp,seconds,rmse,relmse")?;
    for r in rows {
        writeln!(
            f,
            "{scene},{},{},{},{:.6},{:.8},{:.8}",
            r.method,
            r.sampler.name(),
            r.spp,
            r.seconds,
            r.rmse,
            r.rel_mse
        )?;
    }
    f.flush()?;
    Ok(())
}

fn plots(rows: &[Row], args: &ConvergenceArgs) -> Result<()> {
    let lines = |x: fn(&Row) -> f64| -> Vec<Series> {
        let mut out = Vec::new();
        for (method, ..) in METHODS {
            for sampler in [SamplerKind::Independent, SamplerKind::Sobol] {
                let points: Vec<(f64, f64)> = rows
                    .iter()
                    .filter(|r| r.method == method && r.sampler == sampler)
                    .map(|r| (x(r), r.rmse))
                    .collect();
                out.push(Series { label: format!("{method}, {}", sampler.name()), points });
            }
        }
        out
    };
    // A path's file name is enough for a title (and fits).
    let name = Path::new(&args.scene).file_name().map_or(args.scene.clone(), |n| n.to_string_lossy().into_owned());
    let title = format!("{name}: RMSE (emitters excluded)");
    log_log(&args.out.join("error-vs-time.png"), &title, "seconds", "RMSE", &lines(|r| r.seconds))?;
    log_log(&args.out.join("error-vs-spp.png"), &title, "samples per pixel", "RMSE", &lines(|r| r.spp as f64))
}
