//! `tessera chart stability`: the pictures of the stability suite (`docs/stability.md`). Each
//! scene is built so that one method fails; each is rendered with the failing method and the ones
//! that survive, at equal samples, into one contact sheet (a row per scene), with a CSV of each
//! render's mean and per-sample variance. The claims themselves are tests
//! (`crates/scene/tests/stability.rs`).

use crate::bench::default_options;
use crate::chart::StabilityArgs;
use anyhow::{Context, Result};
use indicatif::ProgressBar;
use std::time::Instant;
use tessera_film::{ExrImage, Film, write_png};
use tessera_local::load_scene;
use tessera_local::options::Sampling;
use tessera_local::render_film;
use tessera_render::{ColorMode, Density, Estimator, RenderSettings, Termination, k_eps};

/// One render of the sheet: a label, and how it changes the base settings.
struct Method {
    label: &'static str,
    estimator: Estimator,
    density: Density,
    termination: Termination,
}

const fn method(label: &'static str, estimator: Estimator, density: Density, termination: Termination) -> Method {
    Method { label, estimator, density, termination }
}

const FOUR: Termination = Termination::MaxBounces(4);

/// The scenes (rows) and their methods (columns), failing method first.
fn cases() -> Vec<(&'static str, &'static str, Vec<Method>)> {
    // Dimov, Gurov and Penzov's k_eps for eps = 0.1 in the closed sphere (q 0.95, Le 0.05): 45 bounces.
    let k = k_eps(0.95, 0.05, 0.1).unwrap_or(45);
    vec![
        (
            "builtin:tiny-light",
            "tiny bright light",
            vec![
                method("collision, brdf", Estimator::Collision, Density::Brdf, FOUR),
                method("nee", Estimator::Nee, Density::Brdf, FOUR),
                method("mis", Estimator::Mis, Density::Brdf, FOUR),
            ],
        ),
        (
            "builtin:glossy-floor?roughness=0.05",
            "near-mirror, large light",
            vec![
                method("nee", Estimator::Nee, Density::Brdf, FOUR),
                method("collision, brdf", Estimator::Collision, Density::Brdf, FOUR),
                method("mis", Estimator::Mis, Density::Brdf, FOUR),
            ],
        ),
        (
            "builtin:closed-sphere",
            "albedo 0.95, closed",
            vec![
                method("k_eps (eps 0.1)", Estimator::Collision, Density::Cosine, Termination::MaxBounces(k)),
                method("roulette", Estimator::Collision, Density::Cosine, Termination::ROULETTE),
                method("mis, roulette", Estimator::Mis, Density::Brdf, Termination::ROULETTE),
            ],
        ),
    ]
}

/// Mean, and mean per-sample variance, over pixels whose camera rays saw no emitter.
fn statistics(film: &Film) -> (f64, f64) {
    let (mut mean, mut var, mut n) = (0.0, 0.0, 0.0f64);
    for p in film.pixels.iter().filter(|p| p.emitter_hits == 0 || p.emitter_hits == p.n) {
        mean += p.mean().iter().sum::<f64>() / 3.0;
        var += p.sample_variance().iter().sum::<f64>() / 3.0;
        n += 1.0;
    }
    (mean / n.max(1.0), var / n.max(1.0))
}

pub fn stability(args: StabilityArgs) -> Result<()> {
    std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    let cases = cases();
    let columns = cases.iter().map(|c| c.2.len()).max().unwrap_or(1) as u32;
    let side = args.size;
    let (sheet_w, sheet_h) = (side * columns, side * cases.len() as u32);
    let mut sheet = vec![[0.0f32; 3]; (sheet_w * sheet_h) as usize];
    let mut csv = String::from("scene,case,method,spp,seconds,mean,per_sample_variance\n");
    for (row, (spec, case, methods)) in cases.iter().enumerate() {
        let loaded = load_scene(spec, &default_options())?;
        let mut options = default_options();
        (options.width, options.height, options.spp) = (side, side, args.spp);
        let (base, _) = options.settings(&loaded.scene)?;
        for (col, m) in methods.iter().enumerate() {
            let settings = RenderSettings {
                estimator: m.estimator,
                density: m.density,
                termination: m.termination,
                color: ColorMode::Rgb,
                ..base.clone()
            };
            let started = Instant::now();
            let film = render_film(&loaded.scene, &settings, Sampling::fixed(args.spp), 0, &ProgressBar::hidden())?;
            let seconds = started.elapsed().as_secs_f64();
            let (mean, variance) = statistics(&film);
            println!("{case:<26} {:<16} mean {mean:>9.5}  per-sample variance {variance:>10.3e}", m.label);
            csv += &format!("{spec},{case},{},{},{seconds:.4},{mean:.6},{variance:.6e}\n", m.label, args.spp);
            let image = film.resolve();
            for y in 0..side {
                for x in 0..side {
                    let at = ((row as u32 * side + y) * sheet_w + col as u32 * side + x) as usize;
                    sheet[at] = image.rgb[(y * side + x) as usize];
                }
            }
        }
    }
    std::fs::write(args.out.join("stability.csv"), csv)?;
    let image = ExrImage::from_rgb(sheet_w, sheet_h, sheet, String::new());
    write_png(&image, &args.out.join("stability.png"))?;
    eprintln!(
        "wrote stability.csv and stability.png (rows: scenes; columns: the failing method first) in {}",
        args.out.display()
    );
    Ok(())
}
