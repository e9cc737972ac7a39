//! Tessera against Mitsuba 3 on the same scene in one run: seconds per pass, error against a
//! reference, and the time each renderer's samplers take to reach an error, measured
//! alternately (`tessera bench cornell`, `tessera bench mitsuba`).

use crate::bench::{median, time};
use crate::peers::Peers;
use anyhow::{Context, Result};
use indicatif::ProgressBar;
use serde_json::{Value, json};
use std::path::{Path, PathBuf};
use tessera_film::{ExrImage, compare};
use tessera_local::options::Sampling;
use tessera_local::render_film;
use tessera_render::{RenderSettings, SamplerKind, Scene};

/// Mitsuba 3's own Cornell box (`mi.cornell_box()`) as glTF: every number taken from Mitsuba's
/// scene (Mitsuba 3 is BSD-3-Clause licensed). Rendered with 7 bounces and roulette from the
/// 5th, it is the work Mitsuba's path tracer does with `max_depth` 8 and `rr_depth` 5.
pub const MITSUBA_BOX: &str = include_str!("mitsuba-cbox.gltf");

/// Mitsuba's samplers that are compared: its default and its two best on this box.
pub const MITSUBA_SAMPLERS: [&str; 3] = ["independent", "multijitter", "orthogonal"];

/// One comparison's set-up.
pub struct Comparison<'a> {
    pub scene: &'a Scene,
    /// The scene as the reference's header names it.
    pub label: String,
    /// Tessera's settings for a seed and sampler, with roulette or without (for a reference).
    pub settings: &'a dyn Fn(u64, SamplerKind, bool) -> Result<RenderSettings>,
    /// Mitsuba's scene, as `peers.py` takes it.
    pub mitsuba: Value,
    pub threads: usize,
    pub target_rmse: f64,
    pub max_spp: u32,
    /// Spp and seconds-per-pass repetitions of the throughput line.
    pub pass_spp: u32,
    pub repeat: usize,
    /// Tessera's reference (and, with `own_references`, Mitsuba's beside it, `STEM-mitsuba.exr`).
    pub reference: PathBuf,
    pub reference_spp: u32,
    /// Each renderer is measured against its own reference: where their materials differ (a
    /// converted glTF scene), the two converge to different images. Both references are then
    /// compared with each other and the difference printed.
    pub own_references: bool,
}

/// A contender: one renderer with one sampler.
#[derive(Clone, Copy, Debug)]
enum Side {
    Tessera(SamplerKind),
    Mitsuba(&'static str),
}

impl Side {
    fn name(self) -> String {
        match self {
            Side::Tessera(s) => format!("tessera {}", s.name()),
            Side::Mitsuba(s) => format!("mitsuba {s}"),
        }
    }
}

struct Run<'a, 'b> {
    c: &'b Comparison<'a>,
    peers: Option<&'b mut Peers>,
    width: u32,
    height: u32,
}

impl Run<'_, '_> {
    /// Renders `spp` (Mitsuba may round it) and times it: (spp rendered, seconds, image).
    fn render(&mut self, side: Side, spp: u32, seed: u64) -> Result<(u32, f64, ExrImage)> {
        match side {
            Side::Tessera(sampler) => {
                let settings = (self.c.settings)(seed, sampler, true)?;
                let mut film = None;
                let secs = time(|| {
                    film = Some(render_film(
                        self.c.scene,
                        &settings,
                        Sampling::fixed(spp),
                        self.c.threads,
                        &ProgressBar::hidden(),
                    ))
                });
                let mut image = film.expect("rendered")?.resolve();
                image.emitter.iter_mut().for_each(|e| *e = 0.0); // the reference's mask only
                Ok((spp, secs, image))
            }
            Side::Mitsuba(sampler) => self.mitsuba(sampler, spp, seed, 1),
        }
    }

    fn mitsuba(&mut self, sampler: &str, spp: u32, seed: u64, passes: u32) -> Result<(u32, f64, ExrImage)> {
        let peers = self.peers.as_mut().context("Mitsuba is not loaded")?;
        let out = peers.scratch("mitsuba.rgb");
        let answer = peers.request(json!({
            "op": "mitsuba_render", "scene": self.c.mitsuba, "sampler": sampler, "spp": spp,
            "seed": seed, "threads": self.c.threads, "out": out, "passes": passes,
        }))?;
        let (w, h) = (answer["width"].as_u64().unwrap_or(0) as u32, answer["height"].as_u64().unwrap_or(0) as u32);
        anyhow::ensure!(
            (w, h) == (self.width, self.height),
            "Mitsuba rendered {w} x {h}, not {} x {}",
            self.width,
            self.height
        );
        let words = crate::peers::read_words(&out)?;
        anyhow::ensure!(words.len() == 3 * (w * h) as usize, "Mitsuba's image has {} values", words.len());
        let rgb = words.chunks_exact(3).map(|c| [0, 1, 2].map(|k| f32::from_le_bytes(c[k]))).collect();
        let image = ExrImage::from_rgb(w, h, rgb, String::new());
        let spp = answer["spp"].as_u64().context("mitsuba_render: no spp")? as u32;
        Ok((spp, answer["seconds"].as_f64().context("mitsuba_render: no seconds")?, image))
    }
}

/// Runs the comparison; without Mitsuba (when `python` cannot load it) Tessera's side alone, with
/// a note on how to install it.
pub fn compare_with_mitsuba(c: &Comparison, python: &Path) -> Result<()> {
    let mut peers = match Peers::with(python, "mitsuba") {
        Ok(p) => Some(p),
        Err(why) => {
            println!("mitsuba: skipped: {why}\n  to install: {}", crate::peers::INSTALL);
            None
        }
    };
    let probe = (c.settings)(0, SamplerKind::Sobol, true)?;
    let with_mitsuba = peers.is_some();
    if let Some((_, version)) = &peers {
        println!(
            "side by side with Mitsuba {version} llvm_ad_rgb, {} threads each, box filter both, {} x {}, {:?}",
            c.threads, probe.width, probe.height, probe.termination
        );
    }
    let mut run = Run { c, peers: peers.as_mut().map(|p| &mut p.0), width: probe.width, height: probe.height };

    // Seconds per pass, alternating.
    let best_tessera = Side::Tessera(SamplerKind::Sobol);
    let sides: Vec<Side> =
        [best_tessera, Side::Mitsuba("independent")].into_iter().take(1 + with_mitsuba as usize).collect();
    let mut secs = vec![Vec::new(); sides.len()];
    for _ in 0..c.repeat.max(1) {
        for (k, &side) in sides.iter().enumerate() {
            let (spp, s, _) = run.render(side, c.pass_spp, 5)?;
            secs[k].push(s / spp as f64);
        }
    }
    let per_pass: Vec<f64> = secs.into_iter().map(median).collect();
    for (side, s) in sides.iter().zip(&per_pass) {
        println!("{:<22} {:>7.2} ms per pass ({} spp, median of {})", side.name(), s * 1e3, c.pass_spp, c.repeat);
    }
    if with_mitsuba {
        println!("tessera's time per pass: {:.2}x mitsuba's", per_pass[0] / per_pass[1]);
    }

    // References.
    let tessera_reference = {
        let s = (c.settings)(999, SamplerKind::Sobol, false)?;
        tessera_local::load_or_render_reference(c.scene, &c.label, &s, c.reference_spp, &c.reference)?
    };
    let mitsuba_reference = if c.own_references && with_mitsuba {
        let stem = c.reference.file_stem().and_then(|s| s.to_str()).unwrap_or("reference");
        let path = c.reference.with_file_name(format!("{stem}-mitsuba.exr"));
        let passes = c.reference_spp.div_ceil(256);
        let mut image = tessera_local::load_or_make_reference(&path, 256 * passes, || {
            let (_, _, mut image) = run.mitsuba("multijitter", 256, 999, passes)?;
            image.spp = vec![(256 * passes) as f32; image.rgb.len()];
            Ok(image)
        })?;
        // Tessera's mask of pixels that see an emitter, on both.
        image.emitter.clone_from(&tessera_reference.emitter);
        let between = compare(&image, &tessera_reference, true).context("reference sizes differ")?;
        println!(
            "each renderer against its own reference (Tessera's {} spp, Mitsuba's {}; the scenes' materials are \
             converted, not the same): the references differ by rmse {:.5}",
            tessera_local::reference_spp(&tessera_reference),
            tessera_local::reference_spp(&image),
            between.rmse
        );
        Some(image)
    } else {
        println!("reference: Tessera's, {} spp without roulette", tessera_local::reference_spp(&tessera_reference));
        None
    };
    let reference_of = |side: Side| match (side, &mitsuba_reference) {
        (Side::Mitsuba(_), Some(m)) => m,
        _ => &tessera_reference,
    };

    // Time to the target error, every contender at each doubling in turn.
    let contenders: Vec<Side> = [Side::Tessera(SamplerKind::Independent), best_tessera]
        .into_iter()
        .chain(MITSUBA_SAMPLERS.map(Side::Mitsuba).into_iter().filter(|_| with_mitsuba))
        .collect();
    let mut levels: Vec<Vec<(u32, f64, f64)>> = vec![Vec::new(); contenders.len()];
    let mut done = vec![false; contenders.len()];
    let mut spp = 1;
    println!("error over the pixels that do not see an emitter (spp, seconds on {} threads, rmse):", c.threads);
    while spp <= c.max_spp && done.contains(&false) {
        for (k, &side) in contenders.iter().enumerate() {
            if done[k] {
                continue;
            }
            let (used, secs, image) = run.render(side, spp, 2)?;
            let rmse = compare(&image, reference_of(side), true).context("reference size differs")?.rmse;
            println!("  {:<22} {used:>5} spp {secs:>8.3} s  rmse {rmse:.5}", side.name());
            levels[k].push((used, secs, rmse));
            done[k] = rmse <= c.target_rmse;
        }
        spp *= 2;
    }
    println!("time to rmse {} (the fewest spp found by halving the last doubling twice):", c.target_rmse);
    let mut reached = Vec::new();
    for (k, &side) in contenders.iter().enumerate() {
        let found = reach(c.target_rmse, &levels[k], |spp| {
            let (used, secs, image) = run.render(side, spp, 2)?;
            let rmse = compare(&image, reference_of(side), true).context("reference size differs")?.rmse;
            println!("  {:<22} {used:>5} spp {secs:>8.3} s  rmse {rmse:.5}  (narrowing)", side.name());
            Ok((used, secs, rmse))
        })?;
        match found {
            Some((spp, secs)) => println!("  {:<22} {spp:>5} spp in {secs:.3} s", side.name()),
            None => println!("  {:<22} not reached by {} spp", side.name(), c.max_spp),
        }
        reached.push(found.map(|f| f.1));
    }
    let best = |mitsuba: bool| {
        contenders
            .iter()
            .zip(&reached)
            .filter(|(s, _)| matches!(s, Side::Mitsuba(_)) == mitsuba)
            .filter_map(|(s, r)| r.map(|r| (r, s.name())))
            .min_by(|a, b| a.0.total_cmp(&b.0))
    };
    match (best(false), best(true)) {
        (Some((t, tn)), Some((m, mn))) => println!(
            "time to rmse {}: {tn} {t:.3} s against {mn} {m:.3} s: Tessera takes {:.2}x Mitsuba's time",
            c.target_rmse,
            t / m
        ),
        (Some((t, tn)), None) if !with_mitsuba => {
            println!("time to rmse {}: {tn} {t:.3} s (Mitsuba not measured)", c.target_rmse)
        }
        _ => println!("time to rmse {}: not reached by both", c.target_rmse),
    }
    Ok(())
}

/// The fewest spp that reach `target`, and their time: the first doubling level that does, its
/// bracket then halved twice (to an eighth of its top), since doubling overshoots by up to 2x.
/// `levels` and `measure(spp)` give (spp rendered, seconds, rmse): Mitsuba's orthogonal sampler
/// rounds a count up to a prime's square.
fn reach(
    target: f64,
    levels: &[(u32, f64, f64)],
    mut measure: impl FnMut(u32) -> Result<(u32, f64, f64)>,
) -> Result<Option<(u32, f64)>> {
    let Some(&(top, secs, _)) = levels.iter().find(|l| l.2 <= target) else {
        return Ok(None);
    };
    let mut reached = (top, secs);
    let (mut lo, mut hi) = (top / 2, top);
    while top > 1 && hi - lo > (top / 8).max(1) {
        let mid = (lo + hi) / 2;
        let (used, secs, rmse) = measure(mid)?;
        if rmse <= target && used < reached.0 {
            reached = (used, secs);
        }
        if rmse <= target {
            hi = mid;
        } else {
            lo = mid;
        }
    }
    Ok(Some(reached))
}

#[derive(clap::Args, Debug)]
pub struct MitsubaArgs {
    /// glTF scene [default: MetalRoughSpheresNoTextures from ../shared/scenes, when present].
    /// The bench also names WaterBottle. Textures are left out on both sides (Mitsuba's converter
    /// ignores them), and so is emission that came through a texture.
    pub scene: Option<String>,
    /// Image side in pixels.
    #[arg(long, default_value_t = 256, env = "TESSERA_BENCH_SIZE")]
    pub size: u32,
    /// Constant environment radiance lighting the scene, on both sides.
    #[arg(long, default_value_t = 1.0, env = "TESSERA_BENCH_ENV")]
    pub env: f32,
    /// Samples per pixel for the seconds-per-pass runs.
    #[arg(long, default_value_t = 16, env = "TESSERA_BENCH_SPP")]
    pub spp: u32,
    /// Repetitions of the seconds-per-pass runs; the median is reported.
    #[arg(long, default_value_t = 3, env = "TESSERA_BENCH_REPEAT")]
    pub repeat: usize,
    /// Tessera's converged reference; Mitsuba's is written beside it (`STEM-mitsuba.exr`).
    /// Rendered when absent [default: SCENE-reference.exr in the current folder].
    #[arg(long, env = "TESSERA_BENCH_REFERENCE")]
    pub reference: Option<PathBuf>,
    /// Samples per pixel of each reference.
    #[arg(long, default_value_t = 2048, env = "TESSERA_BENCH_REFERENCE_SPP")]
    pub reference_spp: u32,
    /// RMSE to reach.
    #[arg(long, default_value_t = 0.01, env = "TESSERA_BENCH_TARGET_RMSE")]
    pub target_rmse: f64,
    /// Largest spp tried while looking for the target RMSE.
    #[arg(long, default_value_t = 512, env = "TESSERA_BENCH_MAX_SPP")]
    pub max_spp: u32,
    /// Bounces, as Mitsuba's max_depth minus one.
    #[arg(long, default_value_t = 7, env = "TESSERA_BENCH_MAX_BOUNCES")]
    pub max_bounces: u32,
    /// Russian roulette from this bounce, as Mitsuba's rr_depth.
    #[arg(long, default_value_t = 5, env = "TESSERA_BENCH_RR_FROM")]
    pub rr_from: u32,
    /// Python with Mitsuba 3 and pygltflib (see `bench cornell --help`).
    #[arg(long, default_value = "python3", env = "TESSERA_BENCH_PYTHON")]
    pub python: PathBuf,
    /// Mitsuba's glTF converter, `gltf_to_mitsuba.py` from ../shared/peers.
    #[arg(long, default_value = "../shared/peers/gltf_to_mitsuba.py", env = "TESSERA_BENCH_CONVERTER")]
    pub converter: PathBuf,
}

/// Every texture of every material left out, as Mitsuba's converter leaves them out; and the
/// emission of materials whose emission came through a texture (which masked it: WaterBottle's
/// emissive factor is 1 on the whole bottle), as `peers.py` leaves it out on Mitsuba's side.
/// Returns whether any emission was left out (the lights must then be built again).
fn strip_textures(scene: &mut Scene) -> bool {
    let mut darkened = false;
    for m in scene.surfaces.materials_mut() {
        if m.emissive_texture.is_some() && m.emissive.max_element() > 0.0 {
            m.emissive = tessera_render::glam::Vec3::ZERO;
            darkened = true;
        }
        for texture in [
            &mut m.base_color_texture,
            &mut m.metallic_roughness_texture,
            &mut m.emissive_texture,
            &mut m.normal_texture,
            &mut m.specular_texture,
            &mut m.specular_color_texture,
            &mut m.transmission_texture,
            &mut m.anisotropy_texture,
            &mut m.clearcoat_texture,
            &mut m.clearcoat_roughness_texture,
            &mut m.clearcoat_normal_texture,
            &mut m.sheen_color_texture,
            &mut m.sheen_roughness_texture,
        ] {
            *texture = None;
        }
    }
    darkened
}

pub fn mitsuba(args: MitsubaArgs) -> Result<()> {
    let spec = match args.scene {
        Some(s) => s,
        None if Path::new(crate::bench::SHARED_HEAVY_SCENE).is_file() => crate::bench::SHARED_HEAVY_SCENE.to_string(),
        None => {
            println!("skipped: {} is not present (name a scene)", crate::bench::SHARED_HEAVY_SCENE);
            return Ok(());
        }
    };
    anyhow::ensure!(
        args.converter.is_file(),
        "Mitsuba's converter {} is not there (--converter)",
        args.converter.display()
    );
    let env = format!("{0},{0},{0}", args.env);
    let options = crate::bench::options_from(&["--env", &env]);
    let mut loaded = tessera_local::load_scene(&spec, &options)?;
    if strip_textures(&mut loaded.scene) {
        anyhow::ensure!(
            loaded.info.punctual_lights.is_empty(),
            "the scene has textured emission and punctual lights: the bench rebuilds its lights without them"
        );
        let environment = tessera_render::glam::Vec3::splat(args.env);
        loaded.scene.lights = loaded.scene.light_set(Vec::new(), environment, None);
    }
    let scene = &loaded.scene;
    let camera = scene.cameras.first().context("the scene has no camera")?;
    let tessera_render::Projection::Perspective { yfov } = camera.projection else {
        anyhow::bail!("the scene's camera is orthographic: Mitsuba's converter is given a perspective one");
    };
    println!("{spec}: {} triangles, textures left out, constant environment {}", scene.mesh.triangles.len(), args.env);
    let settings = |seed, sampler, roulette: bool| -> Result<RenderSettings> {
        let mut options = crate::bench::options_from(&["--env", &env]);
        options.max_bounces = Some(args.max_bounces);
        options.rr_from = (roulette && args.rr_from > 0).then_some(args.rr_from);
        (options.width, options.height, options.seed) = (args.size, args.size, seed);
        options.color = Some(tessera_local::options::ColorArg::Rgb);
        let (mut s, _) = options.settings(scene)?;
        s.sampler = sampler;
        Ok(s)
    };
    let rows: Vec<[f32; 4]> = (0..4).map(|r| camera.to_world.row(r).to_array()).collect();
    let stem = Path::new(&spec).file_stem().and_then(|s| s.to_str()).unwrap_or("scene").to_string();
    let comparison = Comparison {
        scene,
        label: spec.clone(),
        settings: &settings,
        mitsuba: json!({
            "kind": "gltf", "path": std::fs::canonicalize(&spec)?, "converter": std::fs::canonicalize(&args.converter)?,
            "width": args.size, "height": args.size, "environment": [args.env, args.env, args.env],
            "camera": {"to_world": rows, "yfov_deg": yfov.to_degrees()},
            "max_depth": args.max_bounces + 1, "rr_depth": args.rr_from,
        }),
        threads: 2,
        target_rmse: args.target_rmse,
        max_spp: args.max_spp,
        pass_spp: args.spp,
        repeat: args.repeat,
        reference: args.reference.unwrap_or_else(|| PathBuf::from(format!("{stem}-reference.exr"))),
        reference_spp: args.reference_spp,
        own_references: true,
    };
    compare_with_mitsuba(&comparison, &args.python)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Mitsuba's box as shipped: its 34 Lambertian triangles and 2 of light, its camera, and a
    /// render that sees the light (the emitter channel) and lights the walls.
    #[test]
    fn the_mitsuba_box_loads_and_renders() {
        let loaded = crate::bench::mitsuba_box().unwrap();
        let scene = &loaded.scene;
        assert_eq!(scene.mesh.triangles.len(), 36);
        assert!(!loaded.info.framed, "the box brings Mitsuba's camera");
        let mut options = crate::bench::options_from(&["--width", "32", "--height", "32", "--quality", "fixed"]);
        options.spp = 4;
        let (settings, _) = options.settings(scene).unwrap();
        let image = render_film(scene, &settings, Sampling::fixed(4), 1, &ProgressBar::hidden()).unwrap().resolve();
        assert!(image.emitter.iter().any(|&e| e > 0.0), "the camera sees the light");
        let lit = image.rgb.iter().zip(&image.emitter).filter(|(c, e)| **e == 0.0 && c[1] > 0.01).count();
        assert!(lit > 500, "walls lit: {lit} of 1024 pixels");
    }

    /// `reach` narrows the first doubling that reaches the target to the fewest spp that do, and
    /// reports the spp actually rendered (Mitsuba's orthogonal sampler rounds up).
    #[test]
    fn reach_finds_the_fewest_samples() {
        // Error 1/sqrt(spp); target 0.1 needs 100 spp.
        let levels: Vec<(u32, f64, f64)> =
            (0..9).map(|k| 1u32 << k).map(|n| (n, n as f64, 1.0 / (n as f64).sqrt())).collect();
        let mut asked = Vec::new();
        let found = reach(0.1, &levels, |spp| {
            asked.push(spp);
            Ok((spp, spp as f64, 1.0 / (spp as f64).sqrt()))
        })
        .unwrap();
        assert_eq!(found, Some((112, 112.0)), "asked {asked:?}");
        // Rounded up to the next square (as an orthogonal sampler would): the rendered count.
        let rounded = |spp: u32| (spp as f64).sqrt().ceil().powi(2) as u32;
        let found = reach(0.1, &levels, |spp| {
            let n = rounded(spp);
            Ok((n, n as f64, 1.0 / (n as f64).sqrt()))
        })
        .unwrap();
        assert_eq!(found, Some((100, 100.0)), "96 spp rendered as 100 reach it");
        assert_eq!(reach(0.01, &levels, |_| unreachable!()).unwrap(), None, "not reached by 256 spp");
    }
}
