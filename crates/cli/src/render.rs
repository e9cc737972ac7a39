//! `tessera render`: load a scene, render it locally, write EXR and PNG.

use anyhow::{Context, Result, bail};
use clap::Args;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;
use tessera_film::{error_estimate, error_statement, write_exr, write_png};
use tessera_local::animation::{AnimationArgs, Shot, frame_path, output_pattern};
use tessera_local::options::RenderOptions;
use tessera_local::{progress_bar, render_film_from};
use tessera_render::Estimator;
use tessera_render::glam::Vec3;
use tessera_scene::environment::Environment;
use tessera_scene::{LoadedScene, Source};

#[derive(Args, Debug)]
pub struct RenderArgs {
    /// Scene: a .gltf or .glb file, or builtin:NAME (cornell-box, furnace[?base=..&metallic=..&roughness=..],
    /// macbeth-scene, many-lights[?count=N], tiny-light, glossy-floor, closed-sphere).
    #[arg(default_value = "builtin:cornell-box")]
    pub scene: String,
    #[command(flatten)]
    pub options: RenderOptions,
    #[command(flatten)]
    pub animation: AnimationArgs,
    /// Worker threads [default: all cores].
    #[arg(long, default_value_t = 0, hide_default_value = true, env = "TESSERA_THREADS")]
    pub threads: usize,
    /// Render through a farm on this machine: an in-process coordinator and K local workers
    /// over loopback gRPC (the threads are shared among them). 0 renders directly.
    #[arg(long, default_value_t = 0, value_parser = clap::value_parser!(u32).range(0..=256), env = "TESSERA_WORKERS")]
    pub workers: u32,
    /// Output EXR path; the PNG preview gets the same stem. A run of #s in the name stands for
    /// the frame number, zero-padded to its width (shot.####.exr) [default: render.exr, or
    /// render.####.exr for a sequence].
    #[arg(long, env = "TESSERA_OUT")]
    pub out: Option<PathBuf>,
    /// No progress bar or summary.
    #[arg(long, short, env = "TESSERA_QUIET")]
    pub quiet: bool,
    /// Keep the render's exact sums beside its image (NAME.sums, about 40 bytes a pixel), so
    /// that --refine can take it further later.
    #[arg(long, env = "TESSERA_KEEP_SUMS")]
    pub keep_sums: bool,
    /// Go on from a render made with --keep-sums (its EXR): give its options, with a lower
    /// --target-error or more --spp, and only the samples those add are rendered; the image
    /// is the bits of a render with them from the start. Its sums are kept for the next step.
    #[arg(long, value_name = "EXR", env = "TESSERA_REFINE")]
    pub refine: Option<PathBuf>,
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
    let only = loaded.scene.lights.emissive_triangles() == 0 && !loaded.scene.lights.has_environment();
    tracing::warn!(
        "the collision estimator never hits punctual lights; {} light(s) ({}) contribute nothing{}: use --estimator nee or mis",
        names.len(),
        names.join(", "),
        if only { " and the image will be black (they are the scene's only lights)" } else { "" }
    );
}

impl RenderArgs {
    /// The output path, a pattern with #s for a sequence.
    pub fn out_pattern(&self) -> Result<PathBuf> {
        output_pattern(self.out.as_deref(), self.animation.sequence())
    }
}

/// Set by the first Ctrl-C (or SIGTERM) during `render`: the frame in hand stops, and what it
/// rendered is written, marked partial. A second one quits at once.
static INTERRUPTED: AtomicBool = AtomicBool::new(false);

/// Watches for Ctrl-C and SIGTERM on a thread of its own, for [`INTERRUPTED`].
fn stop_on_interrupt() {
    std::thread::spawn(|| {
        let Ok(runtime) = tokio::runtime::Builder::new_current_thread().enable_all().build() else { return };
        runtime.block_on(async {
            crate::farm::termination().await;
            INTERRUPTED.store(true, Ordering::Relaxed);
            eprintln!("\ninterrupted: writing what has been rendered (interrupt again to quit at once)");
            crate::farm::termination().await;
            eprintln!("interrupted again: quitting, nothing more written");
            std::process::exit(130);
        });
    });
}

pub fn run(args: RenderArgs) -> Result<()> {
    let pattern = args.out_pattern()?;
    // Started once, before anything renders: a build without it refuses, saying how to build one.
    let denoiser = match args.options.denoise {
        true => Some(tessera_denoise::denoiser().map_err(anyhow::Error::msg)?),
        false => None,
    };
    if args.workers > 0 && (args.keep_sums || args.refine.is_some()) {
        bail!(
            "--keep-sums and --refine are for renders on this machine: a farm keeps its results, refine them with `tessera refine ID`"
        );
    }
    if args.workers > 0 {
        return crate::farm::render_with_local_farm(&args, &pattern);
    }
    if args.refine.is_some() && args.animation.sequence() {
        bail!("--refine takes one image: refine a sequence's frames one at a time (--frame N)");
    }
    stop_on_interrupt();
    tessera_local::load_on_threads(args.threads);
    let source = tessera_scene::open(&args.scene)?;
    let environment = args.options.environment()?;
    let shots = args.animation.shots(args.options.seed);
    check_animation(&source, &args.scene, &shots)?;
    // The hash of the scene as `submit` packs and the farm stores it, so that a farm's image of
    // the same scene and settings is the same file, byte for byte.
    let packed = args.options.pack(&args.scene)?;
    let packed_hash = blake3::hash(&packed).to_hex().to_string();
    let start = Instant::now();
    // The first image may change the options (see `tessera_local::first_light`): every frame
    // renders with what it chose.
    let mut options = args.options.clone();
    for (k, shot) in shots.iter().enumerate() {
        let out = frame_path(&pattern, shot.frame)?;
        let frame_start = Instant::now();
        let (env, denoise) = (environment.as_ref(), denoiser.as_deref());
        render_shot(&args, &mut options, &source, env, shot, &out, &packed_hash, k == 0, denoise)?;
        if INTERRUPTED.load(Ordering::Relaxed) {
            bail!("interrupted: {} of {} frames written, the last of them partial", k + 1, shots.len());
        }
        if shots.len() > 1 && !args.quiet {
            let done = k + 1;
            let per_frame = start.elapsed().as_secs_f64() / done as f64;
            eprintln!(
                "frame {} ({done} of {}) in {:.2} s; sequence {:.0}% done, about {:.0} s to go",
                shot.frame.unwrap_or(0),
                shots.len(),
                frame_start.elapsed().as_secs_f64(),
                100.0 * done as f64 / shots.len() as f64,
                per_frame * (shots.len() - done) as f64
            );
        }
    }
    Ok(())
}

/// Refuses an animation that is not there (before any frame renders), and warns when a
/// sequence will show the same pose in every frame.
pub fn check_animation(source: &Source, scene: &str, shots: &[Shot]) -> Result<()> {
    let Some(pose) = shots.iter().find_map(|s| s.pose.as_ref()) else { return Ok(()) };
    source.node_poses(pose).with_context(|| format!("--animation {}", pose.animation))?;
    if shots.len() > 1 && source.animations().is_empty() {
        tracing::warn!("{scene}: the scene has no animations: every frame shows the same pose");
    }
    Ok(())
}

/// What to tell a user whose render of a lit scene comes out exactly black: worked out from the
/// scene before it renders (so that `submit` can say it too, when the image arrives), for
/// scenes whose only light comes from lights (an environment lights everything).
pub struct BlackImageHint(String);

impl BlackImageHint {
    pub fn of(loaded: &LoadedScene, settings: &tessera_render::RenderSettings) -> Option<Self> {
        let scene = &loaded.scene;
        if scene.lights.is_empty() || scene.lights.has_environment() {
            return None;
        }
        let camera = scene.cameras.get(settings.camera)?;
        let eye = camera.to_world.transform_point3(Vec3::ZERO);
        let forward = camera.to_world.transform_vector3(Vec3::NEG_Z).normalize_or_zero();
        // Where each light is: punctual lights' positions, emissive triangles' centres.
        let mut places: Vec<Vec3> = scene.lights.punctual.iter().filter_map(|l| l.position()).collect();
        let emitters = scene.lights.emissive_triangles();
        places.extend(
            scene
                .mesh
                .triangles
                .iter()
                .filter(|t| scene.surfaces.materials()[t.material as usize].is_emissive())
                .map(|t| t.vertices.iter().map(|&v| scene.mesh.positions[v as usize]).sum::<Vec3>() / 3.0),
        );
        let behind = places.iter().filter(|p| (**p - eye).dot(forward) <= 0.0).count();
        let lights = scene.lights.punctual.len() + emitters;
        let where_they_are = match behind {
            0 => String::new(),
            1 if places.len() == 1 => "; it lies behind the camera".to_string(),
            n if n == places.len() => format!("; all {n} lie behind the camera"),
            n => format!("; {n} of the {} with a position lie behind the camera", places.len()),
        };
        Some(Self(format!(
            "no light reaches what camera '{}' sees, although the scene has {lights} light(s) \
             ({} punctual, {emitters} emissive triangles){where_they_are}. Try --env FILE (an environment map \
             lights everything), --env R,G,B, or another --camera (the scene has {})",
            camera.name,
            scene.lights.punctual.len(),
            scene.cameras.len()
        )))
    }

    /// The hint, if `image` is black or nearly so (see [`black_share`]).
    pub fn explain(&self, image: &tessera_film::ExrImage) -> Option<String> {
        black_share(image).map(|share| self.said(image, share))
    }

    /// The hint for `image`, a `share` of whose pixels show black.
    fn said(&self, image: &tessera_film::ExrImage, share: f64) -> String {
        if share >= 1.0 && image.rgb.iter().flatten().all(|&v| v == 0.0) {
            format!("the image is black: {}", self.0)
        } else {
            format!("the image is nearly black ({:.1} % of its pixels show black): {}", 100.0 * share, self.0)
        }
    }
}

/// The share of `image`'s pixels that show black (below 1/255 on screen, in sRGB), when it is
/// at least 99 %: an image a user would call black.
fn black_share(image: &tessera_film::ExrImage) -> Option<f64> {
    let dark = image
        .rgb
        .iter()
        .filter(|p| p.iter().map(|&c| tessera_film::linear_to_srgb(c)).fold(0.0, f32::max) < 1.0 / 255.0)
        .count();
    let share = dark as f64 / image.rgb.len().max(1) as f64;
    (share >= 0.99).then_some(share)
}

/// Renders one image of the sequence (or the one still) and writes its EXR and PNG.
#[allow(clippy::too_many_arguments)]
fn render_shot(
    args: &RenderArgs,
    options: &mut RenderOptions,
    source: &Source,
    environment: Option<&Environment>,
    shot: &Shot,
    out: &std::path::Path,
    packed_hash: &str,
    first: bool,
    denoiser: Option<&dyn tessera_film::Denoiser>,
) -> Result<()> {
    let mut loaded = source.pose(&options.load_options(environment, shot.pose.clone()))?;
    if first {
        for w in &loaded.info.warnings {
            tracing::warn!("{}: {w}", args.scene);
        }
        let lit = tessera_local::first_light::light_first_render(options, &loaded, &args.scene)?;
        if lit.env != options.env {
            *options = lit;
            loaded = source.pose(&options.load_options(environment, shot.pose.clone()))?;
        }
    }
    let options = &*options;
    let pose = args.animation.pose(shot, options.seed);
    let (setup, termination) = options.setup(&loaded.scene, shot.seed, pose, environment)?;
    let settings = &setup.settings;
    let (sampling, how_many) = options.sampling()?;
    if first {
        warn_unreachable_lights(&loaded, settings.estimator);
    }
    if !args.quiet {
        let when = match (shot.frame, &shot.pose) {
            (Some(f), Some(p)) => format!(" frame {f} ({:.3} s)", p.time),
            (None, Some(p)) => format!(" at {:.3} s", p.time),
            _ => String::new(),
        };
        eprintln!(
            "{}{when}: {} triangles, {}x{}, {how_many}, {} estimator, {} sampler; {termination}",
            args.scene,
            loaded.info.triangles,
            settings.width,
            settings.height,
            settings.estimator.name(),
            settings.sampler.name()
        );
    }
    // A refine goes on from the render kept beside its image.
    let from = match &args.refine {
        Some(old) => {
            let kept = crate::kept::read(old, settings.width, settings.height)?;
            crate::kept::check(&kept, packed_hash, &setup, sampling)
                .with_context(|| format!("refining {}", old.display()))?;
            if !args.quiet {
                let film = &kept.finished.film;
                eprintln!("going on from {} ({:.1} spp on average)", old.display(), film.mean_spp());
            }
            Some(kept.finished)
        }
        None => None,
    };
    let had = from.as_ref().map_or(0, |f| f.film.total_samples());
    let start = Instant::now();
    let progress = progress_bar(args.quiet);
    let rendered = render_film_from(&loaded.scene, settings, sampling, args.threads, &progress, &INTERRUPTED, from)?;
    if rendered.whole && (args.keep_sums || args.refine.is_some()) {
        crate::kept::write(&crate::kept::path_for(out), packed_hash, &setup, sampling, &rendered)?;
    }
    let (film, whole) = (rendered.film, rendered.whole);
    let elapsed = start.elapsed().as_secs_f64();
    if !whole && film.total_samples() + film.dropped() == 0 {
        bail!("interrupted before any sample was rendered: nothing written");
    }
    let dropped = film.dropped();
    if dropped > 0 {
        tracing::warn!("{dropped} samples were NaN, infinite or out of range and were dropped");
    }
    let mut image = film.resolve_with_alpha(settings.transparent);
    // The hint walks the scene's emitters: only for an image that needs it.
    if let Some(share) = black_share(&image)
        && let Some(hint) = BlackImageHint::of(&loaded, settings)
    {
        tracing::warn!("{}: {}", args.scene, hint.said(&image, share));
    }
    image.metadata = setup.header(&tessera_request::printable(&args.scene), packed_hash, args.options.spp, dropped);
    let target = sampling.adaptive.map_or(0.0, |a| a.target_error);
    let stated = (settings.confidence > 0.0).then(|| error_estimate(&film.pixels, settings.confidence as f64));
    if let Some(e) = &stated {
        image.metadata += &error_statement(e, target);
    }
    if !whole {
        // Which pixels got how many samples is in the image's own spp channel.
        image.metadata += &format!(
            "partial=interrupted after {} samples ({:.1} spp on average)\n",
            film.total_samples(),
            film.mean_spp()
        );
    }
    if let Some(denoiser) = denoiser.filter(|_| settings.denoise) {
        let started = Instant::now();
        image.denoise_with(denoiser)?;
        if !args.quiet {
            eprintln!("denoised in {:.2} s", started.elapsed().as_secs_f64());
        }
    }
    if let Some(dir) = out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    write_exr(&image, out).with_context(|| "writing the EXR")?;
    let png = out.with_extension("png");
    write_png(&image, &png)?;
    if !whole {
        eprintln!(
            "wrote {} and {}, partial: interrupted at {:.1} spp on average of the {} asked for",
            out.display(),
            png.display(),
            film.mean_spp(),
            args.options.spp
        );
        if shot.frame.is_none() {
            bail!("interrupted: the image written is partial");
        }
        return Ok(());
    }
    if !args.quiet {
        // The samples rendered now (a refine's went on from `had`).
        let samples = (film.total_samples() - had) as f64;
        let mean_spp = match sampling.adaptive {
            Some(_) => format!(", {:.1} spp on average", film.mean_spp()),
            None => String::new(),
        };
        if let Some(e) = stated {
            eprintln!("{}", said_error(&e, target));
        }
        eprintln!(
            "wrote {} and {} in {elapsed:.2} s ({:.2} M samples/s{mean_spp})",
            out.display(),
            png.display(),
            samples / elapsed / 1e6
        );
    }
    Ok(())
}

/// A stated error for people: "relative error 0.91 %, below 0.98 % with 95 % confidence
/// (target 1 %)".
pub fn said_error(e: &tessera_film::ErrorEstimate, target: f32) -> String {
    let target = match target {
        t if t > 0.0 && e.upper <= t as f64 => format!(" (target {} %: met)", t * 100.0),
        t if t > 0.0 => format!(" (target {} %: not met, the samples ran out first)", t * 100.0),
        _ => String::new(),
    };
    format!(
        "relative error {:.3} %, below {:.3} % with {} % confidence{target}",
        e.estimate * 100.0,
        e.upper * 100.0,
        e.confidence as f32 * 100.0
    )
}
