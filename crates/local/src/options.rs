//! Render options shared by every command that renders: parsing, validation and the choice of
//! path termination, turned into [`RenderSettings`].

use anyhow::{Context, Result, bail};
use clap::{Args, ValueEnum};
use tessera_render::glam::Vec3;
use tessera_render::{
    ColorMode, DEFAULT_BOUNCES, Density, Estimator, LightSampler, ROULETTE_FROM, ROULETTE_MAX_BOUNCES, RenderSettings,
    SamplerKind, Scene, Termination, k_eps,
};
pub use tessera_request::Adaptive;
use tessera_request::limits::{MAX_BOUNCES, MAX_PIXELS, MAX_SIDE, MAX_SPP, check_name, check_target_error};
use tessera_request::{EnvironmentMap, Setup, printable};

#[derive(Clone, Copy, Debug, ValueEnum)]
pub enum EstimatorArg {
    Collision,
    Nee,
    Mis,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
pub enum DensityArg {
    Uniform,
    Cosine,
    Brdf,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
pub enum SamplerArg {
    Independent,
    Sobol,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum LightsArg {
    /// The tree where the scene has more than two lights with a position, else power.
    Auto,
    /// In proportion to each light's power, wherever the point being lit is.
    Power,
    /// By a light tree: lights near the point and facing it are chosen more often.
    Tree,
}

/// With `--lights auto`, the light tree is used for more lights with a position than this. One
/// rectangular light (two triangles) gains nothing from it and would pay for its walk.
pub const TREE_FROM_LIGHTS: usize = 2;

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum QualityArg {
    /// Choices from the scene: colour model from its spectral content, path termination from its
    /// maximum albedo, adaptive sampling to --target-error.
    Auto,
    /// The same choices for every scene: RGB, 7 bounces, exactly --spp everywhere.
    Fixed,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum ColorArg {
    Rgb,
    Spectral,
    Auto,
}

#[derive(Args, Clone, Debug)]
pub struct RenderOptions {
    /// Image width in pixels.
    #[arg(long, default_value_t = 512, value_parser = clap::value_parser!(u32).range(1..=MAX_SIDE as i64), env = "TESSERA_WIDTH")]
    pub width: u32,
    /// Image height in pixels.
    #[arg(long, default_value_t = 512, value_parser = clap::value_parser!(u32).range(1..=MAX_SIDE as i64), env = "TESSERA_HEIGHT")]
    pub height: u32,
    /// Samples per pixel: every pixel's count, or with adaptive sampling the most a tile gets.
    #[arg(long, default_value_t = 64, value_parser = clap::value_parser!(u32).range(1..=MAX_SPP as i64), env = "TESSERA_SPP")]
    pub spp: u32,
    /// auto: settings chosen from the scene (colour model, path termination, adaptive
    /// sampling); fixed: RGB, 7 bounces, exactly --spp everywhere. Any flag given overrides both.
    #[arg(long, value_enum, default_value = "auto", env = "TESSERA_QUALITY")]
    pub quality: QualityArg,
    /// Adaptive sampling: the relative standard error of the pixel mean, over a tile, to reach;
    /// tiles still above it after a round get twice the samples, up to --spp. 0 turns it off
    /// [default: 0.01 with --quality auto, off with fixed].
    #[arg(long, value_parser = parse_target_error, allow_negative_numbers = true, env = "TESSERA_TARGET_ERROR")]
    pub target_error: Option<f32>,
    /// Samples per pixel of adaptive sampling's first round [default: --spp / 8, at least 16].
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=MAX_SPP as i64), env = "TESSERA_MIN_SPP")]
    pub min_spp: Option<u32>,
    /// A stated error: adaptive sampling stops a tile only when its relative error is below
    /// --target-error with this probability (0.5 to 0.999, e.g. 0.95), counting the uncertainty
    /// of the error estimate itself; the image states its error with that bound (EXR header,
    /// `tessera status`). With a fixed --spp it only states the error.
    #[arg(long, value_parser = parse_confidence, env = "TESSERA_CONFIDENCE")]
    pub confidence: Option<f32>,
    /// Render seed: the same seed, scene and settings give the same bits.
    #[arg(long, default_value_t = 0, env = "TESSERA_SEED")]
    pub seed: u64,
    /// Estimator: Dimov, Gurov and Penzov's collision estimator, next-event estimation, or MIS of both.
    #[arg(long, value_enum, default_value = "mis", env = "TESSERA_ESTIMATOR")]
    pub estimator: EstimatorArg,
    /// Transition density of the collision estimator's random walk.
    #[arg(long, value_enum, default_value = "brdf", env = "TESSERA_DENSITY")]
    pub density: DensityArg,
    /// Sample generator.
    #[arg(long, value_enum, default_value = "sobol", env = "TESSERA_SAMPLER")]
    pub sampler: SamplerArg,
    /// Stop paths after B bounces (0: only emitters seen directly; 7 matches Mitsuba's max_depth 8).
    /// With --rr, roulette ends paths earlier and B caps them.
    #[arg(long, value_parser = clap::value_parser!(u32).range(0..=MAX_BOUNCES as i64), env = "TESSERA_MAX_BOUNCES")]
    pub max_bounces: Option<u32>,
    /// End paths by Russian roulette from the third bounce on (unbiased; capped at 1024 bounces, or
    /// at --max-bounces, whose image it then converges to).
    #[arg(long, conflicts_with = "eps", env = "TESSERA_RR")]
    pub rr: bool,
    /// Russian roulette from bounce N on instead of the third (implies --rr). Mitsuba's path
    /// tracer defaults are --max-bounces 7 --rr-from 5 (its max_depth 8, rr_depth 5).
    #[arg(long, value_name = "N", conflicts_with = "eps", value_parser = clap::value_parser!(u32).range(1..=MAX_BOUNCES as i64), env = "TESSERA_RR_FROM")]
    pub rr_from: Option<u32>,
    /// Truncate the Neumann series after Dimov, Gurov and Penzov's k_eps terms for this eps [default: 1/512].
    #[arg(long, conflicts_with = "max_bounces", env = "TESSERA_EPS")]
    pub eps: Option<f32>,
    /// Camera: a name or index among the scene's cameras [default: the first].
    #[arg(long, env = "TESSERA_CAMERA")]
    pub camera: Option<String>,
    /// Colour transport: rgb; spectral (4 hero wavelengths per path, measured spectra and metals'
    /// n + ik, RGB colours upsampled); auto: spectral only when the scene has spectral content
    /// [default: auto with --quality auto, rgb with fixed].
    #[arg(long, value_enum, env = "TESSERA_COLOR")]
    pub color: Option<ColorArg>,
    /// The environment around the scene: a constant radiance ("R,G,B" or one number), or an
    /// equirectangular map (a Radiance .hdr or OpenEXR .exr file) that lights the scene and is
    /// seen behind it. The map's centre faces +Z, +Y is up (as Mitsuba 3's envmap).
    #[arg(long, value_name = "R,G,B|FILE", value_parser = parse_env, env = "TESSERA_ENV")]
    pub env: Option<EnvArg>,
    /// Scale of the environment map's radiance.
    #[arg(long, default_value_t = 1.0, value_parser = parse_strength, env = "TESSERA_ENV_STRENGTH")]
    pub env_strength: f32,
    /// Turn the environment map about the vertical (+Y) axis, in degrees.
    #[arg(long, default_value_t = 0.0, allow_negative_numbers = true, value_parser = parse_degrees, env = "TESSERA_ENV_ROTATE")]
    pub env_rotate: f32,
    /// Leave the background out, for compositing over a plate: rays that miss the scene add
    /// nothing (the environment still lights it), the EXR gets an alpha channel `A` (the
    /// fraction of each pixel's rays that hit the scene; colours premultiplied by it) and the PNG
    /// an alpha channel.
    #[arg(long, env = "TESSERA_TRANSPARENT")]
    pub transparent: bool,
    /// A material variant of the file (KHR_materials_variants; `tessera scene-info` lists them)
    /// [default: the materials the file gives its meshes].
    #[arg(long, value_name = "NAME", value_parser = parse_variant, env = "TESSERA_VARIANT")]
    pub variant: Option<String>,
    /// How a light is chosen for each shadow ray: power (in proportion to each light's power),
    /// tree (a light tree weighs each light by its power, distance and orientation as seen from
    /// the point being lit, which scenes with many small lights need), or auto: the tree where the
    /// scene has more than two lights with a position (emissive triangles, point and spot lights).
    #[arg(long, value_enum, default_value = "auto", env = "TESSERA_LIGHTS")]
    pub lights: LightsArg,
    /// glTF materials: on gives back the light that rough surfaces lose to bounces between their
    /// microfacets (Kulla and Conty), so a white rough surface reflects all it receives, as in
    /// Blender; off renders glTF's single-scattering formulas as the specification writes them.
    #[arg(long, value_enum, default_value = "on", env = "TESSERA_ENERGY_COMPENSATION")]
    pub energy_compensation: OnOff,
    /// Extra layers in the EXR, for a denoiser or compositing: albedo (albedo.R/G/B) and normal
    /// (normal.X/Y/Z, world space), averaged over the same samples as the colour at the first
    /// surface that is not a perfect mirror or clear glass. The two are made together: asking
    /// for either writes both.
    #[arg(long, value_name = "LAYERS", value_enum, value_delimiter = ',', env = "TESSERA_AOV")]
    pub aov: Vec<AovArg>,
    /// Also write a denoised image (Open Image Denoise, with the albedo and normal layers, which
    /// this turns on): the EXR gets `denoised.R/G/B` beside the untouched raw colour, and the PNG
    /// shows the denoised one. Needs a tessera built with `--features tessera-cli/denoise`.
    #[arg(long, env = "TESSERA_DENOISE")]
    pub denoise: bool,
}

/// `--aov`: the feature layers a denoiser reads.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum AovArg {
    Albedo,
    Normal,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum OnOff {
    On,
    Off,
}

/// `--env`: a constant radiance or a map file.
#[derive(Clone, Debug, PartialEq)]
pub enum EnvArg {
    Rgb(Vec3),
    File(std::path::PathBuf),
}

pub fn parse_env(s: &str) -> Result<EnvArg, String> {
    let lower = s.to_ascii_lowercase();
    if lower.ends_with(".hdr") || lower.ends_with(".exr") {
        return Ok(EnvArg::File(s.into()));
    }
    parse_rgb(s).map(EnvArg::Rgb).map_err(|e| format!("{e}; or give an environment map, a .hdr or .exr file"))
}

/// A variant's name, checked as every request's names are (the farm refuses the same ones).
fn parse_variant(s: &str) -> Result<String, String> {
    check_name("a material variant's name", s)?;
    Ok(s.to_string())
}

fn parse_strength(s: &str) -> Result<f32, String> {
    match s.parse::<f32>() {
        Ok(v) if v.is_finite() && v >= 0.0 => Ok(v),
        _ => Err(format!("'{s}' is not a finite number >= 0")),
    }
}

fn parse_degrees(s: &str) -> Result<f32, String> {
    match s.parse::<f32>() {
        Ok(v) if v.is_finite() => Ok(v),
        _ => Err(format!("'{s}' is not a number of degrees")),
    }
}

impl RenderOptions {
    /// The environment map `--env FILE` names, read and checked (none for a constant).
    pub fn environment(&self) -> Result<Option<tessera_scene::environment::Environment>> {
        match &self.env {
            Some(EnvArg::File(path)) => Ok(Some(
                tessera_scene::environment::load(path, self.env_strength, self.env_rotate).with_context(|| "--env")?,
            )),
            _ => Ok(None),
        }
    }

    /// The loader's options for these render options, with the map [`Self::environment`] read.
    pub fn load_options(
        &self,
        map: Option<&tessera_scene::environment::Environment>,
        pose: Option<tessera_scene::PoseAt>,
    ) -> tessera_scene::LoadOptions {
        let constant = match &self.env {
            Some(EnvArg::Rgb(c)) => Some(*c),
            _ => None,
        };
        tessera_scene::LoadOptions {
            environment: constant,
            pose,
            environment_map: map.map(|m| m.map.clone()),
            variant: self.variant.clone(),
        }
    }

    /// The package of `scene` that `submit` uploads (and whose hash image headers carry): with
    /// the environment map `--env FILE` names, when it names one.
    pub fn pack(&self, scene: &str) -> Result<Vec<u8>> {
        Ok(match &self.env {
            Some(EnvArg::File(path)) => tessera_scene::pack_with_environment(scene, path)?,
            _ => tessera_scene::pack(scene)?,
        })
    }

    /// The environment map `--env FILE` names, as a request carries it (its name as a terminal
    /// may show it, for the image header).
    pub fn environment_map(&self, map: Option<&tessera_scene::environment::Environment>) -> Option<EnvironmentMap> {
        match (&self.env, map) {
            (Some(EnvArg::File(path)), Some(m)) => Some(EnvironmentMap {
                name: printable(&path.display().to_string()),
                hash: m.hash.clone(),
                strength: self.env_strength,
                rotate_degrees: self.env_rotate,
            }),
            _ => None,
        }
    }

    /// What the pixels of an image of `scene` depend on: the settings resolved against it (with
    /// the image's own `seed`), its environment, the map, the variant, and `pose`. Returns the
    /// line [`Self::settings`] says with it.
    pub fn setup(
        &self,
        scene: &Scene,
        seed: u64,
        pose: Option<tessera_request::Pose>,
        map: Option<&tessera_scene::environment::Environment>,
    ) -> Result<(Setup, String)> {
        let (settings, how) = self.settings(scene)?;
        let setup = Setup {
            settings: RenderSettings { seed, ..settings },
            environment: scene.lights.environment,
            pose,
            environment_map: self.environment_map(map),
            variant: self.variant.clone(),
        };
        Ok((setup, how))
    }
}

pub fn parse_rgb(s: &str) -> Result<Vec3, String> {
    let parts: Vec<&str> = s.split(',').map(str::trim).collect();
    let nums: Result<Vec<f32>, _> = parts.iter().map(|p| p.parse::<f32>()).collect();
    let nums = nums.map_err(|_| format!("'{s}' is not R,G,B or a number"))?;
    let v = match nums.as_slice() {
        [x] => Vec3::splat(*x),
        [r, g, b] => Vec3::new(*r, *g, *b),
        _ => return Err(format!("'{s}' needs one or three numbers")),
    };
    if !v.is_finite() || v.min_element() < 0.0 {
        return Err(format!("'{s}': radiance must be finite and not negative"));
    }
    Ok(v)
}

pub fn parse_confidence(s: &str) -> Result<f32, String> {
    match s.parse::<f32>() {
        Ok(c) if c > 0.0 && tessera_request::limits::check_confidence(c).is_ok() => Ok(c),
        _ => Err(format!(
            "'{s}' is not a probability above 0.5 and at most {} (e.g. 0.95)",
            tessera_request::limits::MAX_CONFIDENCE
        )),
    }
}

pub fn parse_target_error(s: &str) -> Result<f32, String> {
    match s.parse::<f32>() {
        Ok(x) if check_target_error(x).is_ok() => Ok(x),
        _ => Err(format!("'{s}' is not a relative error between 0 and 10 (e.g. 0.01; 0 turns adaptive sampling off)")),
    }
}

/// How many samples the pixels get: `spp` each, or with `adaptive` at most `spp`, tile by tile.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Sampling {
    pub spp: u32,
    pub adaptive: Option<Adaptive>,
}

impl Sampling {
    pub fn fixed(spp: u32) -> Self {
        Self { spp, adaptive: None }
    }
}

/// Default `eps` for `k_eps`: half an 8-bit step (Dimov, Gurov and Penzov).
pub const DEFAULT_EPS: f32 = 1.0 / 512.0;
/// `--quality auto`'s target: a 1 % relative standard error is less than one 8-bit step of the
/// sRGB display value for every linear value up to 0.75 (0.55 steps at 0.18, 0.84 at 0.5).
pub const DEFAULT_TARGET_ERROR: f32 = 0.01;
/// `--quality fixed`'s path length: Mitsuba's default max_depth 8.
pub const FIXED_BOUNCES: u32 = DEFAULT_BOUNCES;
/// Above this many bounces, `k_eps` gives way to Russian roulette: a truncated walk that long
/// costs more than roulette's extra variance (the Cornell box's q = 0.78 gives k_eps = 43).
const K_EPS_LIMIT: u32 = 16;

impl RenderOptions {
    /// Resolves the options against a loaded scene. Returns the settings and a line saying how
    /// paths end and which colour transport was chosen, for the user.
    pub fn settings(&self, scene: &Scene) -> Result<(RenderSettings, String)> {
        let pixels = self.width as u64 * self.height as u64;
        if pixels > MAX_PIXELS {
            bail!(
                "--width {} x --height {} is {pixels} pixels, over the limit of {MAX_PIXELS} (e.g. 4096 x 4096)",
                self.width,
                self.height
            );
        }
        let camera = self.camera_index(scene)?;
        let (termination, how) = self.termination(scene)?;
        let (color, why) = self.color(scene);
        let settings = RenderSettings {
            seed: self.seed,
            estimator: match self.estimator {
                EstimatorArg::Collision => Estimator::Collision,
                EstimatorArg::Nee => Estimator::Nee,
                EstimatorArg::Mis => Estimator::Mis,
            },
            density: match self.density {
                DensityArg::Uniform => Density::Uniform,
                DensityArg::Cosine => Density::Cosine,
                DensityArg::Brdf => Density::Brdf,
            },
            sampler: match self.sampler {
                SamplerArg::Independent => SamplerKind::Independent,
                SamplerArg::Sobol => SamplerKind::Sobol,
            },
            termination,
            camera,
            color,
            transparent: self.transparent,
            lights: self.light_sampler(scene),
            energy_compensation: self.energy_compensation == OnOff::On,
            features: !self.aov.is_empty() || self.denoise,
            denoise: self.denoise,
            confidence: self.confidence.unwrap_or(0.0),
            ..RenderSettings::new(self.width, self.height)
        };
        let lights = match settings.lights {
            LightSampler::Tree => format!("; lights: tree ({} with a position)", scene.lights.located()),
            LightSampler::Power => String::new(),
        };
        Ok((settings, format!("{how}; {why}{lights}")))
    }

    fn light_sampler(&self, scene: &Scene) -> LightSampler {
        match self.lights {
            LightsArg::Power => LightSampler::Power,
            LightsArg::Tree => LightSampler::Tree,
            LightsArg::Auto if scene.lights.located() > TREE_FROM_LIGHTS => LightSampler::Tree,
            LightsArg::Auto => LightSampler::Power,
        }
    }

    /// The colour transport, and why: `auto` is spectral exactly when the scene carries spectra.
    fn color(&self, scene: &Scene) -> (ColorMode, String) {
        let mut content = scene.spectral_content();
        if content.len() > 3 {
            let more = content.len() - 2;
            content.truncate(2);
            content.push(format!("{more} more"));
        }
        let color = self.color.unwrap_or(match self.quality {
            QualityArg::Auto => ColorArg::Auto,
            QualityArg::Fixed => ColorArg::Rgb,
        });
        match (color, content.is_empty()) {
            (ColorArg::Rgb, true) => (ColorMode::Rgb, "colour: rgb".into()),
            (ColorArg::Rgb, false) => (
                ColorMode::Rgb,
                format!(
                    "colour: rgb {}, although {} carry spectra (RGB stand-ins used)",
                    if self.color.is_some() { "as asked" } else { "(--quality fixed)" },
                    content.join(", ")
                ),
            ),
            (ColorArg::Spectral, _) => (ColorMode::Spectral, "colour: spectral as asked".into()),
            (ColorArg::Auto, true) => (ColorMode::Rgb, "colour: rgb (auto: no spectral content)".into()),
            (ColorArg::Auto, false) => {
                (ColorMode::Spectral, format!("colour: spectral (auto: material {})", content.join(", ")))
            }
        }
    }

    /// Samples per pixel, adaptive or not, and a line saying which for the user.
    pub fn sampling(&self) -> Result<(Sampling, String)> {
        let spp = self.spp;
        let target = self.target_error.unwrap_or(match self.quality {
            QualityArg::Auto => DEFAULT_TARGET_ERROR,
            QualityArg::Fixed => 0.0,
        });
        if target <= 0.0 {
            if self.min_spp.is_some() {
                bail!("--min-spp needs adaptive sampling: give --target-error, or leave --quality at auto");
            }
            return Ok((Sampling::fixed(spp), format!("{spp} spp")));
        }
        let min_spp = self.min_spp.unwrap_or((spp / 8).max(tessera_render::plan::PASS_SPP).min(spp));
        if min_spp > spp {
            bail!("--min-spp {min_spp} is above --spp {spp}, the most adaptive sampling gives a pixel");
        }
        // The first round is whole passes, by the planner's rule.
        let pass = tessera_render::plan::PASS_SPP;
        let passes = spp.div_ceil(pass);
        let first_passes = tessera_render::plan::first_round(min_spp, pass, passes);
        if first_passes >= passes {
            return Ok((Sampling::fixed(spp), format!("{spp} spp (too few to adapt)")));
        }
        let first = first_passes * pass;
        let why = if self.target_error.is_some() { "--target-error" } else { "auto" };
        Ok((
            Sampling { spp, adaptive: Some(Adaptive { target_error: target, min_spp }) },
            format!("{first}..{spp} spp, adaptive to relative error {target} per tile ({why})"),
        ))
    }

    fn camera_index(&self, scene: &Scene) -> Result<usize> {
        let names = || {
            scene.cameras.iter().enumerate().map(|(i, c)| format!("{i}: '{}'", c.name)).collect::<Vec<_>>().join(", ")
        };
        let Some(c) = &self.camera else { return Ok(0) };
        if let Ok(i) = c.parse::<usize>() {
            if i < scene.cameras.len() {
                return Ok(i);
            }
            bail!("camera {i} does not exist; the scene has {}", names());
        }
        scene
            .cameras
            .iter()
            .position(|cam| &cam.name == c)
            .with_context(|| format!("no camera named '{c}'; the scene has {}", names()))
    }

    fn termination(&self, scene: &Scene) -> Result<(Termination, String)> {
        if self.rr || self.rr_from.is_some() {
            let from = self.rr_from.unwrap_or(ROULETTE_FROM);
            let flag = if self.rr_from.is_some() { "--rr-from" } else { "--rr" };
            // Without --max-bounces the cap is ROULETTE_MAX_BOUNCES, which --rr-from's range stays under.
            let max_bounces = self.max_bounces.unwrap_or(ROULETTE_MAX_BOUNCES);
            if from > max_bounces {
                bail!("--rr-from {from} lies beyond --max-bounces {max_bounces}: no path would reach the roulette");
            }
            let cap = self.max_bounces.map_or(String::new(), |b| format!(", after {b} bounces at most"));
            return Ok((
                Termination::RussianRoulette { from, max_bounces },
                format!("paths end by Russian roulette from bounce {from} on{cap} ({flag})"),
            ));
        }
        if let Some(b) = self.max_bounces {
            return Ok((Termination::MaxBounces(b), format!("paths end after {b} bounces (--max-bounces)")));
        }
        if self.quality == QualityArg::Fixed && self.eps.is_none() {
            let b = FIXED_BOUNCES;
            return Ok((Termination::MaxBounces(b), format!("paths end after {b} bounces (--quality fixed)")));
        }
        let eps = self.eps.unwrap_or(DEFAULT_EPS);
        if !(eps > 0.0 && eps < 1.0) {
            bail!("--eps must lie strictly between 0 and 1 (got {eps})");
        }
        let q = scene.max_albedo();
        let le = scene.lights.max_radiance.max(1e-3);
        match k_eps(q, le, eps) {
            Some(k) if k <= K_EPS_LIMIT || self.eps.is_some() => Ok((
                Termination::MaxBounces(k),
                format!("paths end after k_eps = {k} bounces (q = {q:.3}, Le* = {le}, eps = {eps})"),
            )),
            Some(k) => Ok((
                Termination::ROULETTE,
                format!("k_eps = {k} would be long (q = {q:.3}): paths end by Russian roulette instead"),
            )),
            None => Ok((
                Termination::ROULETTE,
                format!("max albedo q = {q:.3} >= 1, k_eps is unbounded: paths end by Russian roulette"),
            )),
        }
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        options: RenderOptions,
    }

    /// Render options as `tessera render` takes them from `args` (for this crate's tests).
    pub(crate) fn options(args: &[&str]) -> RenderOptions {
        Cli::try_parse_from(std::iter::once("render").chain(args.iter().copied())).unwrap().options
    }

    fn scene(spec: &str) -> Scene {
        tessera_scene::load(spec, &Default::default()).unwrap().scene
    }

    /// `--quality` decides the colour model and the path length a scene gets; any flag given
    /// wins over it. These choices are image bits: `render` and `submit` both make them here.
    #[test]
    fn quality_chooses_colour_and_termination_and_flags_win() {
        let cornell = scene("builtin:cornell-box");
        let (auto, how) = options(&[]).settings(&cornell).unwrap();
        assert_eq!(auto.color, ColorMode::Spectral, "the Cornell box carries measured spectra: {how}");
        assert_eq!(auto.termination, Termination::ROULETTE, "q = 0.78 gives a k_eps over the limit: {how}");
        let (fixed, _) = options(&["--quality", "fixed"]).settings(&cornell).unwrap();
        assert_eq!((fixed.color, fixed.termination), (ColorMode::Rgb, Termination::MaxBounces(FIXED_BOUNCES)));
        let (eps, how) = options(&["--eps", "0.01"]).settings(&cornell).unwrap();
        let k = k_eps(cornell.max_albedo(), cornell.lights.max_radiance.max(1e-3), 0.01).unwrap();
        assert_eq!(eps.termination, Termination::MaxBounces(k), "{how}");
        let (rr, _) = options(&["--rr-from", "5", "--max-bounces", "7"]).settings(&cornell).unwrap();
        assert_eq!(rr.termination, Termination::RussianRoulette { from: 5, max_bounces: 7 });
        let e = options(&["--rr-from", "9", "--max-bounces", "7"]).settings(&cornell).unwrap_err();
        assert!(e.to_string().contains("beyond --max-bounces 7"), "{e}");
        let (rgb, _) = options(&["--color", "rgb"]).settings(&cornell).unwrap();
        assert_eq!(rgb.color, ColorMode::Rgb);
        let (big, _) = options(&["--width", "640", "--height", "360", "--seed", "9"]).settings(&cornell).unwrap();
        assert_eq!((big.width, big.height, big.seed), (640, 360, 9));
        let e = options(&["--width", "16384", "--height", "16384"]).settings(&cornell).unwrap_err();
        assert!(e.to_string().contains("over the limit"), "{e}");
    }

    /// `--lights auto` takes the light tree for more than two lights with a position.
    #[test]
    fn the_light_tree_is_chosen_for_many_lights() {
        let (few, _) = options(&[]).settings(&scene("builtin:cornell-box")).unwrap();
        assert_eq!(few.lights, LightSampler::Power);
        let (many, how) = options(&[]).settings(&scene("builtin:many-lights?count=8")).unwrap();
        assert_eq!(many.lights, LightSampler::Tree, "{how}");
        let (forced, _) = options(&["--lights", "power"]).settings(&scene("builtin:many-lights?count=8")).unwrap();
        assert_eq!(forced.lights, LightSampler::Power);
    }

    /// How many samples a pixel gets: adaptive rounds from an eighth of `--spp` (at least a
    /// pass) under `--quality auto`, all of them under `fixed`, and no rounds where the first
    /// round would already be all.
    #[test]
    fn sampling_is_adaptive_under_auto_and_fixed_otherwise() {
        let (auto, _) = options(&["--spp", "256"]).sampling().unwrap();
        assert_eq!(auto.adaptive, Some(Adaptive { target_error: DEFAULT_TARGET_ERROR, min_spp: 32 }));
        let (fixed, _) = options(&["--spp", "256", "--quality", "fixed"]).sampling().unwrap();
        assert_eq!(fixed, Sampling::fixed(256));
        let (few, why) = options(&["--spp", "16"]).sampling().unwrap();
        assert_eq!(few, Sampling::fixed(16), "{why}");
        let (own, _) = options(&["--spp", "256", "--min-spp", "64", "--target-error", "0.05"]).sampling().unwrap();
        assert_eq!(own.adaptive, Some(Adaptive { target_error: 0.05, min_spp: 64 }));
        assert!(options(&["--spp", "32", "--min-spp", "64"]).sampling().is_err());
        assert!(options(&["--min-spp", "64", "--quality", "fixed"]).sampling().is_err());
    }

    /// A render's setup: the resolved settings with the image's own seed, the scene's
    /// environment, the variant and the map's name as a terminal may show it.
    #[test]
    fn a_setup_carries_the_seed_the_environment_and_the_variant() {
        let furnace = scene("builtin:furnace");
        let o = options(&["--quality", "fixed", "--variant", "midnight", "--seed", "3"]);
        let (setup, _) = o.setup(&furnace, 42, None, None).unwrap();
        assert_eq!(setup.settings.seed, 42, "the shot's seed, not --seed");
        assert_eq!(setup.environment, furnace.lights.environment);
        assert_eq!(setup.variant.as_deref(), Some("midnight"));
        assert!(setup.environment_map.is_none() && setup.pose.is_none());
        let (settings, _) = o.settings(&furnace).unwrap();
        assert_eq!(setup.settings, RenderSettings { seed: 42, ..settings });
        // The names the farm's wire check refuses, refused here too.
        for bad in ["evil\x1b[2J", &"v".repeat(1025)] {
            assert!(Cli::try_parse_from(["render", "--variant", bad]).is_err(), "{bad:?}");
        }
    }
}
