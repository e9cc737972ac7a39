//! Rendering on this machine: tiles x sample ranges on a rayon pool, merged exactly into a film.

use crate::options::Sampling;
use anyhow::Result;
use indicatif::{ProgressBar, ProgressStyle};
use rayon::prelude::*;
use std::sync::Mutex;
use tessera_film::{Film, stopping_error};
use tessera_render::plan::{PASS_SPP, RenderPlan, TILE_SIZE, first_round, next_round};
use tessera_render::{RenderSettings, Scene, Tile, render_tile};

/// Renders on `threads` threads (0: all cores): every pixel `sampling.spp` samples, or with
/// adaptive sampling round by round, tiles above the target error doubling their passes by the
/// coordinator's rule, so that `render` and a farm give the same bits.
pub fn render_film(
    scene: &Scene,
    settings: &RenderSettings,
    sampling: Sampling,
    threads: usize,
    progress: &ProgressBar,
) -> Result<Film> {
    let never = std::sync::atomic::AtomicBool::new(false);
    Ok(render_film_until(scene, settings, sampling, threads, progress, &never)?.0)
}

/// [`render_film`], stopping early once `stop` is set (Ctrl-C): the passes already rendered
/// are merged, the rest left out. Returns the film and whether it is whole.
pub fn render_film_until(
    scene: &Scene,
    settings: &RenderSettings,
    sampling: Sampling,
    threads: usize,
    progress: &ProgressBar,
    stop: &std::sync::atomic::AtomicBool,
) -> Result<(Film, bool)> {
    use std::sync::atomic::Ordering;
    let plan = &RenderPlan::new(settings.width, settings.height, TILE_SIZE, sampling.spp, PASS_SPP);
    let max = plan.passes_per_tile();
    let first = sampling.adaptive.map_or(max, |a| first_round(a.min_spp, plan.pass_spp, max));
    let mut budget = vec![first; plan.tiles.len()];
    let mut done = vec![0; plan.tiles.len()];
    let samples = |tile: &Tile, passes: std::ops::Range<u32>| {
        tile.pixel_count() as u64 * plan.samples(passes.start, passes.len() as u32).len() as u64
    };
    progress.set_length(plan.tiles.iter().map(|t| samples(t, 0..first)).sum());
    let film = Mutex::new(Film::with_features(settings.width, settings.height, settings.features));
    let lock = || film.lock().map_err(|_| anyhow::anyhow!("a render thread panicked"));
    let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build()?;
    loop {
        // Tiles with passes left in their round; once rendered, each is judged once, as
        // `Core::complete` judges a tile when the last pass of its round is merged.
        let pending: Vec<usize> = (0..plan.tiles.len()).filter(|&i| done[i] < budget[i]).collect();
        if pending.is_empty() {
            break;
        }
        let items: Vec<(Tile, std::ops::Range<u32>)> = pending
            .iter()
            .flat_map(|&i| (done[i]..budget[i]).map(move |p| (plan.tiles[i], plan.samples(p, 1))))
            .collect();
        // One item a task: a thread that runs out of work steals a single (tile, pass) from
        // another, so none sits idle while the other finishes a block of items it took.
        pool.install(|| {
            items.par_iter().with_max_len(1).try_for_each(|(tile, samples)| -> Result<()> {
                if stop.load(Ordering::Relaxed) {
                    return Ok(());
                }
                let sums = render_tile(scene, settings, *tile, samples.clone())?;
                lock()?.merge_tile(&sums)?;
                progress.inc(tile.pixel_count() as u64 * samples.len() as u64);
                Ok(())
            })
        })?;
        if stop.load(Ordering::Relaxed) {
            progress.finish_and_clear();
            let film = film.into_inner().map_err(|_| anyhow::anyhow!("a render thread panicked"))?;
            return Ok((film, false));
        }
        done.clone_from(&budget);
        let Some(adaptive) = sampling.adaptive else { break };
        let film = lock()?;
        for i in pending {
            let tile = &plan.tiles[i];
            let error = stopping_error(film.tile_pixels(*tile), settings.confidence);
            if let Some(next) = next_round(budget[i], max, error, adaptive.target_error as f64) {
                progress.inc_length(samples(tile, budget[i]..next));
                budget[i] = next;
            }
        }
    }
    progress.finish_and_clear();
    Ok((film.into_inner().map_err(|_| anyhow::anyhow!("a render thread panicked"))?, true))
}

/// A progress bar on a terminal, nothing otherwise.
pub fn progress_bar(quiet: bool) -> ProgressBar {
    use std::io::IsTerminal;
    if quiet || !std::io::stderr().is_terminal() {
        return ProgressBar::hidden();
    }
    let bar = ProgressBar::new(0);
    bar.set_style(
        ProgressStyle::with_template(
            "{spinner} [{elapsed_precise}] {wide_bar} {percent}% {human_per_sec} samples, ETA {eta}",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    bar
}

/// A converged reference image: read from `path` when the file exists, else rendered with
/// `settings` at `spp` on all cores (with a progress bar), written to `path` and returned.
pub fn load_or_render_reference(
    scene: &Scene,
    scene_label: &str,
    settings: &RenderSettings,
    spp: u32,
    path: &std::path::Path,
) -> Result<tessera_film::ExrImage> {
    load_or_make_reference(path, spp, || {
        let mut image = render_film(scene, settings, Sampling::fixed(spp), 0, &progress_bar(false))?.resolve();
        image.metadata = format!("scene={scene_label}\nspp={spp}\nsettings={}\n", settings.describe());
        Ok(image)
    })
}

/// The samples per pixel of a reference image (every pixel has the same count); 0 for none. A
/// cached reference keeps the count it was made with, whatever a later run asks for.
pub fn reference_spp(image: &tessera_film::ExrImage) -> u32 {
    image.spp.first().copied().unwrap_or(0.0) as u32
}

/// A reference image of `spp` samples: read from `path` when the file exists, else made by
/// `render`, written to `path` (its folder created) and returned.
pub fn load_or_make_reference(
    path: &std::path::Path,
    spp: u32,
    render: impl FnOnce() -> Result<tessera_film::ExrImage>,
) -> Result<tessera_film::ExrImage> {
    use anyhow::Context;
    if path.is_file() {
        let image =
            tessera_film::read_exr(path).with_context(|| format!("reading the reference {}", path.display()))?;
        eprintln!("reference {} ({} spp, cached)", path.display(), reference_spp(&image));
        return Ok(image);
    }
    eprintln!("reference: rendering {spp} spp into {} (once; reused afterwards)", path.display());
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    let image = render()?;
    tessera_film::write_exr(&image, path)?;
    Ok(image)
}

#[cfg(test)]
mod tests {
    use super::*;
    use tessera_render::Termination;
    use tessera_request::Adaptive;

    fn scene() -> Scene {
        tessera_scene::load("builtin:cornell-box", &Default::default()).unwrap().scene
    }

    fn settings() -> RenderSettings {
        RenderSettings { termination: Termination::MaxBounces(3), ..RenderSettings::new(40, 24) }
    }

    /// A fixed render is every tile's passes merged, in any order: the film of one thread, of
    /// three, and of each pass rendered alone and merged here are the same bits.
    #[test]
    fn a_film_has_the_same_bits_on_any_number_of_threads_and_as_passes_merged_alone() {
        let (scene, s) = (scene(), settings());
        let sampling = Sampling::fixed(40);
        let one = render_film(&scene, &s, sampling, 1, &ProgressBar::hidden()).unwrap();
        let three = render_film(&scene, &s, sampling, 3, &ProgressBar::hidden()).unwrap();
        assert!(one == three, "threads changed the film");
        let plan = RenderPlan::new(s.width, s.height, TILE_SIZE, 40, PASS_SPP);
        let mut merged = Film::new(s.width, s.height);
        for tile in plan.tiles.iter().rev() {
            for pass in (0..plan.passes_per_tile()).rev() {
                merged.merge_tile(&render_tile(&scene, &s, *tile, plan.samples(pass, 1)).unwrap()).unwrap();
            }
        }
        assert!(one == merged, "the film differs from its passes merged one by one");
        assert_eq!(one.total_samples(), 40 * 40 * 24);
    }

    /// Adaptive rounds decide alike whatever the threads: the same budgets (samples per pixel)
    /// and bits; a converged tile stops early and a noisy one gets more.
    #[test]
    fn adaptive_rounds_are_the_same_on_any_number_of_threads() {
        let (scene, s) = (scene(), settings());
        let sampling = Sampling { spp: 256, adaptive: Some(Adaptive { target_error: 0.05, min_spp: 16 }) };
        let one = render_film(&scene, &s, sampling, 1, &ProgressBar::hidden()).unwrap();
        let four = render_film(&scene, &s, sampling, 4, &ProgressBar::hidden()).unwrap();
        assert!(one == four, "threads changed the adaptive film");
        let spp: Vec<u64> = one.pixels.iter().map(|p| p.n + p.dropped).collect();
        let (least, most) = (spp.iter().min().unwrap(), spp.iter().max().unwrap());
        assert!(*least >= 16 && *most <= 256 && least < most, "rounds did not adapt: {least}..{most}");
    }
}
