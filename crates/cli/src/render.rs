//! `tessera render`: load a scene, render it locally, write EXR and PNG.

use crate::local::{progress_bar, render_film};
use crate::options::RenderOptions;
use anyhow::{Context, Result};
use clap::Args;
use std::path::PathBuf;
use std::time::Instant;
use tessera_film::{write_exr, write_png};
use tessera_render::Estimator;
use tessera_scene::{LoadOptions, LoadedScene};

#[derive(Args, Debug)]
pub struct RenderArgs {
    /// Scene: a .gltf or .glb file, or builtin:NAME (cornell-box, furnace[?base=..&metallic=..&roughness=..]).
    #[arg(default_value = "builtin:cornell-box")]
    pub scene: String,
    #[command(flatten)]
    pub options: RenderOptions,
    /// Worker threads [default: all cores].
    #[arg(long, default_value_t = 0, hide_default_value = true, env = "TESSERA_THREADS")]
    pub threads: usize,
    /// Render through a farm on this machine: an in-process coordinator and K local workers
    /// over loopback gRPC (the threads are shared among them). 0 renders directly.
    #[arg(long, default_value_t = 0, value_parser = clap::value_parser!(u32).range(0..=256), env = "TESSERA_WORKERS")]
    pub workers: u32,
    /// Output EXR path; the PNG preview gets the same stem.
    #[arg(long, default_value = "render.exr", env = "TESSERA_OUT")]
    pub out: PathBuf,
    /// No progress bar or summary.
    #[arg(long, short, env = "TESSERA_QUIET")]
    pub quiet: bool,
}

pub fn load_scene(spec: &str, options: &RenderOptions) -> Result<LoadedScene> {
    let loaded = tessera_scene::load(spec, &LoadOptions { environment: options.env, ..Default::default() })?;
    for w in &loaded.info.warnings {
        tracing::warn!("{spec}: {w}");
    }
    Ok(loaded)
}

/// Warns when the chosen estimator cannot see some of the scene's lights.
fn warn_unreachable_lights(loaded: &LoadedScene, estimator: Estimator) {
    if estimator != Estimator::Collision || loaded.scene.lights.punctual.is_empty() {
        return;
    }
    // The loader's "kind 'name'" descriptions; the kinds alone where a scene was built in code.
    let mut names = loaded.info.punctual_lights.clone();
    if names.len() != loaded.scene.lights.punctual.len() {
        names = loaded.scene.lights.punctual.iter().map(|l| l.kind().to_string()).collect();
    }
    let only = loaded.scene.lights.emissive_triangles() == 0 && loaded.scene.lights.environment.max_element() <= 0.0;
    tracing::warn!(
        "the collision estimator never hits punctual lights; {} light(s) ({}) contribute nothing{}: use --estimator nee or mis",
        names.len(),
        names.join(", "),
        if only { " and the image will be black (they are the scene's only lights)" } else { "" }
    );
}

pub fn run(args: RenderArgs) -> Result<()> {
    if args.workers > 0 {
        return crate::farm::render_with_local_farm(&args);
    }
    let loaded = load_scene(&args.scene, &args.options)?;
    let (settings, termination) = args.options.settings(&loaded.scene)?;
    let (sampling, how_many) = args.options.sampling()?;
    warn_unreachable_lights(&loaded, settings.estimator);
    if !args.quiet {
        eprintln!(
            "{}: {} triangles, {}x{}, {how_many}, {} estimator, {} sampler; {termination}",
            args.scene,
            loaded.info.triangles,
            settings.width,
            settings.height,
            settings.estimator.name(),
            settings.sampler.name()
        );
    }
    let start = Instant::now();
    let film = render_film(&loaded.scene, &settings, sampling, args.threads, &progress_bar(args.quiet))?;
    let elapsed = start.elapsed().as_secs_f64();
    let dropped = film.dropped();
    if dropped > 0 {
        tracing::warn!("{dropped} samples were NaN, infinite or out of range and were dropped");
    }
    let mut image = film.resolve();
    let env = loaded.scene.lights.environment;
    // The hash of the scene as `submit` packs and the farm stores it, so that a farm's image of
    // the same scene and settings is the same file, byte for byte.
    let packed_hash = blake3::hash(&tessera_scene::pack(&args.scene)?).to_hex().to_string();
    image.metadata = tessera_film::image_metadata(
        &args.scene,
        &packed_hash,
        settings.seed,
        args.options.spp,
        env.to_array(),
        &settings.describe(),
        dropped,
    );
    write_exr(&image, &args.out).with_context(|| "writing the EXR")?;
    let png = args.out.with_extension("png");
    write_png(&image, &png)?;
    if !args.quiet {
        let samples = film.total_samples() as f64;
        let mean_spp = match sampling.adaptive {
            Some(_) => format!(", {:.1} spp on average", film.mean_spp()),
            None => String::new(),
        };
        eprintln!(
            "wrote {} and {} in {elapsed:.2} s ({:.2} M samples/s{mean_spp})",
            args.out.display(),
            png.display(),
            samples / elapsed / 1e6
        );
    }
    Ok(())
}
