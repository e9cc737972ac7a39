//! `tessera chart quality`: `--quality auto` against `--quality fixed` at equal time. For each
//! scene, both (and auto without its adaptive sampling, to tell its parts apart) render at
//! doubling `--spp` within a time budget; every render's error against a converged, unbiased
//! reference goes to a CSV, one log-log panel per scene, and a table at equal time.

use crate::bench::default_options;
use crate::chart::{QualityArgs, cached_reference, doubling_spp};
use crate::plot::{Series, log_log_panels};
use anyhow::{Context, Result, bail};
use indicatif::ProgressBar;
use std::io::Write;
use std::time::Instant;
use tessera_film::{ExrImage, compare};
use tessera_local::load_scene;
use tessera_local::options::{QualityArg, RenderOptions, Sampling};
use tessera_local::render_film;
use tessera_render::{RenderSettings, Scene, Termination};

/// How a charted setting changes the default options.
type Setup = fn(&mut RenderOptions);

/// The settings charted, with their labels.
const SETUPS: [(&str, Setup); 3] = [
    ("fixed", |o| o.quality = QualityArg::Fixed),
    ("auto (uniform spp)", |o| o.target_error = Some(0.0)),
    ("auto", |_| {}),
];

/// One render of the chart.
struct Row {
    scene: usize,
    setup: &'static str,
    spp: u32,
    mean_spp: f64,
    seconds: f64,
    rmse: f64,
    rel_mse: f64,
}

pub fn quality(args: QualityArgs) -> Result<()> {
    if !(args.budget > 0.0 && args.budget.is_finite()) {
        bail!("--budget {} must be a positive number of seconds", args.budget);
    }
    std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    let mut rows = Vec::new();
    for (index, spec) in args.scene.iter().enumerate() {
        let loaded = load_scene(spec, &default_options())?;
        let scene = &loaded.scene;
        let options = |setup: Setup| {
            let mut o = default_options();
            (o.width, o.height) = (args.size, args.size);
            setup(&mut o);
            o
        };
        let (auto, _) = options(|_| {}).settings(scene)?;
        let reference = reference(scene, spec, &loaded.hash, &auto, &args)?;
        for (setup, change) in SETUPS {
            let o = options(change);
            let (settings, how) = o.settings(scene)?;
            eprintln!("{spec}, {setup}: {how}");
            doubling_spp(&reference, args.budget, |spp| {
                let (sampling, _) = RenderOptions { spp, ..o.clone() }.sampling()?;
                let (mean_spp, seconds, rmse, rel_mse) = measure(scene, &settings, sampling, &reference, &args)?;
                eprintln!(
                    "  {spp:>6} spp ({mean_spp:>7.1} on average) {seconds:>8.3} s  rmse {rmse:.5}  relmse {rel_mse:.5}"
                );
                rows.push(Row { scene: index, setup, spp, mean_spp, seconds, rmse, rel_mse });
                Ok(seconds)
            })?;
        }
    }
    write_csv(&rows, &args)?;
    let series: Vec<Vec<Series>> = (0..args.scene.len())
        .map(|i| {
            SETUPS
                .iter()
                .map(|(setup, _)| Series { label: setup.to_string(), points: points(&rows, i, setup) })
                .collect()
        })
        .collect();
    let panels: Vec<(String, &[Series])> =
        args.scene.iter().zip(&series).map(|(s, lines)| (short_name(s), lines.as_slice())).collect();
    log_log_panels(&args.out.join("quality.png"), &panels, "seconds", "RMSE (emitters excluded)")?;
    println!("{}", equal_time_table(&rows, &args.scene));
    eprintln!("wrote quality.csv and quality.png in {}", args.out.display());
    Ok(())
}

/// Renders once; returns the mean spp, wall seconds, RMSE and relative MSE against `reference`.
fn measure(
    scene: &Scene,
    settings: &RenderSettings,
    sampling: Sampling,
    reference: &ExrImage,
    args: &QualityArgs,
) -> Result<(f64, f64, f64, f64)> {
    let t = Instant::now();
    let film = render_film(scene, settings, sampling, args.threads, &ProgressBar::hidden())?;
    let seconds = t.elapsed().as_secs_f64();
    let c = compare(&film.resolve(), reference, true).context("the reference's size differs from --size")?;
    Ok((film.mean_spp(), seconds, c.rmse, c.rel_mse))
}

/// The truth the settings are judged against: auto's colour model (measured spectra are the
/// truth where a scene has them), MIS, Sobol, Russian roulette (no truncation bias), another seed.
fn reference(scene: &Scene, spec: &str, hash: &str, auto: &RenderSettings, args: &QualityArgs) -> Result<ExrImage> {
    let settings = RenderSettings { termination: Termination::ROULETTE, seed: 0x5EED, ..auto.clone() };
    cached_reference(scene, spec, hash, &settings, args.reference_spp, &args.cache)
}

/// (seconds, RMSE) of one setting's renders of scene `scene`, in the order they were made.
fn points(rows: &[Row], scene: usize, setup: &str) -> Vec<(f64, f64)> {
    rows.iter().filter(|r| r.scene == scene && r.setup == setup).map(|r| (r.seconds, r.rmse)).collect()
}

fn short_name(spec: &str) -> String {
    std::path::Path::new(spec).file_name().map_or(spec.to_string(), |n| n.to_string_lossy().into_owned())
}

fn write_csv(rows: &[Row], args: &QualityArgs) -> Result<()> {
    let path = args.out.join("quality.csv");
    let mut f =
        std::io::BufWriter::new(std::fs::File::create(&path).with_context(|| format!("creating {}", path.display()))?);
    writeln!(f, "scene,setting,spp,mean_spp,seconds,rmse,relmse")?;
    for r in rows {
        let scene = &args.scene[r.scene];
        writeln!(f, "{scene},{},{},{:.2},{:.6},{:.8},{:.8}", r.setup, r.spp, r.mean_spp, r.seconds, r.rmse, r.rel_mse)?;
    }
    f.flush()?;
    Ok(())
}

/// Error of a series at time `t`, interpolated linearly in log-log between its renders (`None`
/// outside the times it covers).
fn error_at(points: &[(f64, f64)], t: f64) -> Option<f64> {
    points.windows(2).find(|w| w[0].0 <= t && t <= w[1].0).map(|w| {
        let ((t0, e0), (t1, e1)) = (w[0], w[1]);
        if t1 <= t0 {
            return e0;
        }
        let f = (t / t0).ln() / (t1 / t0).ln();
        (e0.ln() + f * (e1 / e0).ln()).exp()
    })
}

/// A Markdown table: for each scene, every setting's RMSE at the longest time all settings
/// reached, and fixed's RMSE over auto's.
fn equal_time_table(rows: &[Row], scenes: &[String]) -> String {
    let mut out = String::from("| scene | seconds |");
    for (setup, _) in SETUPS {
        out += &format!(" {setup} RMSE |");
    }
    out += " fixed / auto |\n|---|---|";
    out += &"---|".repeat(SETUPS.len() + 1);
    for (i, scene) in scenes.iter().enumerate() {
        let curves: Vec<Vec<(f64, f64)>> = SETUPS
            .iter()
            .map(|(setup, _)| {
                let mut p = points(rows, i, setup);
                p.sort_by(|a, b| a.0.total_cmp(&b.0));
                p
            })
            .collect();
        let t = curves.iter().map(|c| c.last().map_or(0.0, |p| p.0)).fold(f64::INFINITY, f64::min);
        let errors: Vec<Option<f64>> = curves.iter().map(|c| error_at(c, t)).collect();
        out += &format!("\n| {} | {t:.2} |", short_name(scene));
        for e in &errors {
            out += &e.map_or(" - |".into(), |e| format!(" {e:.5} |"));
        }
        out += &match (errors[0], errors[SETUPS.len() - 1]) {
            (Some(f), Some(a)) => format!(" {:.2} |", f / a),
            _ => " - |".into(),
        };
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn interpolation_is_linear_in_log_log() {
        let points = [(1.0, 1.0), (4.0, 0.25)];
        assert!((error_at(&points, 2.0).unwrap() - 0.5).abs() < 1e-12);
        assert_eq!(error_at(&points, 4.0), Some(0.25));
        assert_eq!(error_at(&points, 8.0), None);
        assert_eq!(error_at(&points[..1], 1.0), None);
    }
}
