//! Rendering on this machine: tiles x sample ranges on a rayon pool, merged exactly into a film.

use anyhow::Result;
use indicatif::{ProgressBar, ProgressStyle};
use rayon::prelude::*;
use std::sync::Mutex;
use tessera_film::Film;
use tessera_render::{RenderSettings, Scene, Tile, render_tile};

/// Default tile side and samples per work item (a "pass" in the farm's words).
pub const TILE_SIZE: u32 = 32;
pub const PASS_SPP: u32 = 16;

/// Renders `spp` samples per pixel on `threads` threads (0: all cores).
pub fn render_film(
    scene: &Scene,
    settings: &RenderSettings,
    spp: u32,
    threads: usize,
    progress: &ProgressBar,
) -> Result<Film> {
    let tiles = Tile::grid(settings.width, settings.height, TILE_SIZE);
    let items: Vec<(Tile, std::ops::Range<u32>)> = tiles
        .iter()
        .flat_map(|&t| (0..spp).step_by(PASS_SPP as usize).map(move |s| (t, s..(s + PASS_SPP).min(spp))))
        .collect();
    progress.set_length(settings.width as u64 * settings.height as u64 * spp as u64);
    let film = Mutex::new(Film::new(settings.width, settings.height));
    let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build()?;
    pool.install(|| {
        items.par_iter().try_for_each(|(tile, samples)| -> Result<()> {
            let sums = render_tile(scene, settings, *tile, samples.clone())?;
            film.lock().map_err(|_| anyhow::anyhow!("a render thread panicked"))?.merge_tile(&sums)?;
            progress.inc(tile.pixel_count() as u64 * samples.len() as u64);
            Ok(())
        })
    })?;
    progress.finish_and_clear();
    film.into_inner().map_err(|_| anyhow::anyhow!("a render thread panicked"))
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
    use anyhow::Context;
    if path.is_file() {
        let image =
            tessera_film::read_exr(path).with_context(|| format!("reading the reference {}", path.display()))?;
        eprintln!("reference {} ({} spp, cached)", path.display(), image.spp.first().copied().unwrap_or(0.0));
        return Ok(image);
    }
    eprintln!("reference: rendering {spp} spp into {} (once; reused afterwards)", path.display());
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    let mut image = render_film(scene, settings, spp, 0, &progress_bar(false))?.resolve();
    image.metadata = format!("scene={scene_label}\nspp={spp}\nsettings={}\n", settings.describe());
    tessera_film::write_exr(&image, path)?;
    Ok(image)
}
