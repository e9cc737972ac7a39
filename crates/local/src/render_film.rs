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
    let rendered = render_film_from(scene, settings, sampling, threads, progress, stop, None)?;
    Ok((rendered.film, rendered.whole))
}

/// A finished render to go on from (a local refine): its film and each tile's passes, all of
/// `0 .. passes` merged.
pub struct Finished {
    pub film: Film,
    pub passes: Vec<u32>,
}

/// What [`render_film_from`] rendered: the film, whether it is whole, and each tile's passes.
pub struct Rendered {
    pub film: Film,
    pub whole: bool,
    pub passes: Vec<u32>,
}

/// [`render_film_until`], going on from `from` when given: only the passes `sampling` adds are
/// rendered, and the film is the bits of a render with `sampling` from the start. The caller
/// checks that `from` is a render of the same scene and settings, with at most `sampling`'s
/// samples and, when adaptive, a target error at least its own (so that every round before
/// a tile's passes went on in the render with `sampling` too: [`resume_budgets`]).
pub fn render_film_from(
    scene: &Scene,
    settings: &RenderSettings,
    sampling: Sampling,
    threads: usize,
    progress: &ProgressBar,
    stop: &std::sync::atomic::AtomicBool,
    from: Option<Finished>,
) -> Result<Rendered> {
    use std::sync::atomic::Ordering;
    let plan = &RenderPlan::new(settings.width, settings.height, TILE_SIZE, sampling.spp, PASS_SPP);
    let max = plan.passes_per_tile();
    let first = sampling.adaptive.map_or(max, |a| first_round(a.min_spp, plan.pass_spp, max));
    let (film, mut done) = match from {
        Some(f) => (f.film, f.passes),
        None => (Film::with_features(settings.width, settings.height, settings.features), vec![0; plan.tiles.len()]),
    };
    let mut budget = resume_budgets(plan, first, &done);
    let samples = |tile: &Tile, passes: std::ops::Range<u32>| {
        tile.pixel_count() as u64 * plan.samples(passes.start, passes.len() as u32).len() as u64
    };
    // A tile whose passes end on a round of this render is judged now, as it would have been.
    let judged: Vec<usize> = (0..plan.tiles.len()).filter(|&i| done[i] > 0 && done[i] == budget[i]).collect();
    judge(plan, settings, sampling, &film, &judged, &mut budget);
    let to_render = |budget: &[u32], done: &[u32]| {
        plan.tiles.iter().zip(budget.iter().zip(done)).map(|(t, (&b, &d))| samples(t, d..b.max(d))).sum::<u64>()
    };
    progress.set_length(to_render(&budget, &done));
    let film = Mutex::new(film);
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
            return Ok(Rendered { film, whole: false, passes: done });
        }
        done.clone_from(&budget);
        judge(plan, settings, sampling, &*lock()?, &pending, &mut budget);
        progress.inc_length(to_render(&budget, &done));
    }
    progress.finish_and_clear();
    let film = film.into_inner().map_err(|_| anyhow::anyhow!("a render thread panicked"))?;
    Ok(Rendered { film, whole: true, passes: done })
}

/// Each tile's first round at or past the passes it has (`done`; none: the first round). A
/// tile of a finished render went on past every round below its passes; a render with a
/// target error at most that render's, and at least its samples, goes on past them too, and
/// the doubling rounds land here.
fn resume_budgets(plan: &RenderPlan, first: u32, done: &[u32]) -> Vec<u32> {
    let max = plan.passes_per_tile();
    done.iter()
        .map(|&d| {
            let mut b = first;
            while b < d && b < max {
                b = b.saturating_mul(2).min(max);
            }
            b
        })
        .collect()
}

/// Judges `tiles` (each with its round merged) by the plan's round rule: a tile above the
/// target error gets its next round. A fixed render's tiles are done.
fn judge(
    plan: &RenderPlan,
    settings: &RenderSettings,
    sampling: Sampling,
    film: &Film,
    tiles: &[usize],
    budget: &mut [u32],
) {
    let Some(adaptive) = sampling.adaptive else { return };
    for &i in tiles {
        let error = stopping_error(film.tile_pixels(plan.tiles[i]), settings.confidence);
        if let Some(next) = next_round(budget[i], plan.passes_per_tile(), error, adaptive.target_error as f64) {
            budget[i] = next;
        }
    }
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

    fn from(scene: &Scene, s: &RenderSettings, sampling: Sampling, start: Option<Finished>) -> Rendered {
        let never = std::sync::atomic::AtomicBool::new(false);
        render_film_from(scene, s, sampling, 2, &ProgressBar::hidden(), &never, start).unwrap()
    }

    /// A finished render goes on to a lower target error or more samples to the bits of a render
    /// with them from the start, rendering only what they add; so does a chain of such steps.
    #[test]
    fn a_finished_render_refines_to_the_bits_of_a_direct_one() {
        let (scene, s) = (scene(), settings());
        let adaptive = |target_error, spp| Sampling { spp, adaptive: Some(Adaptive { target_error, min_spp: 16 }) };
        for (before, after) in [
            (adaptive(0.2, 256), adaptive(0.05, 256)),
            (adaptive(0.1, 96), adaptive(0.1, 256)),
            (adaptive(0.2, 64), adaptive(0.04, 512)),
            (Sampling::fixed(32), Sampling::fixed(80)),
        ] {
            let old = from(&scene, &s, before, None);
            let (old_samples, old_passes) = (old.film.total_samples(), old.passes.clone());
            let refined = from(&scene, &s, after, Some(Finished { film: old.film, passes: old.passes }));
            let direct = from(&scene, &s, after, None);
            assert!(refined.film == direct.film, "{before:?} refined to {after:?} differs from a direct render");
            assert_eq!(refined.passes, direct.passes);
            assert!(refined.passes.iter().zip(&old_passes).all(|(n, o)| n >= o));
            assert!(direct.film.total_samples() > old_samples, "{before:?} to {after:?} added nothing to test");
        }
    }
}
