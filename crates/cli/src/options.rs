//! Render options shared by every command that renders: parsing, validation and the choice of
//! path termination, turned into [`RenderSettings`].

use anyhow::{Context, Result, bail};
use clap::{Args, ValueEnum};
use tessera_render::glam::Vec3;
use tessera_render::{ColorMode, Density, Estimator, RenderSettings, SamplerKind, Scene, Termination, k_eps};

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
pub enum ColorArg {
    Rgb,
    Spectral,
    Auto,
}

/// Largest accepted image side, samples per pixel and path length.
pub const MAX_SIDE: u32 = 16384;
pub const MAX_SPP: u32 = 1 << 20;
pub const MAX_BOUNCES: u32 = 1024;
/// Largest accepted image area: the film holds 112 bytes of exact sums per pixel (1.9 GB here).
pub const MAX_PIXELS: u64 = 1 << 24;

#[derive(Args, Clone, Debug)]
pub struct RenderOptions {
    /// Image width in pixels.
    #[arg(long, default_value_t = 512, value_parser = clap::value_parser!(u32).range(1..=MAX_SIDE as i64), env = "TESSERA_WIDTH")]
    pub width: u32,
    /// Image height in pixels.
    #[arg(long, default_value_t = 512, value_parser = clap::value_parser!(u32).range(1..=MAX_SIDE as i64), env = "TESSERA_HEIGHT")]
    pub height: u32,
    /// Samples per pixel.
    #[arg(long, default_value_t = 64, value_parser = clap::value_parser!(u32).range(1..=MAX_SPP as i64), env = "TESSERA_SPP")]
    pub spp: u32,
    /// Render seed: the same seed, scene and settings give the same bits.
    #[arg(long, default_value_t = 0, env = "TESSERA_SEED")]
    pub seed: u64,
    /// Estimator: paper 1's collision estimator, next-event estimation, or MIS of both.
    #[arg(long, value_enum, default_value = "mis", env = "TESSERA_ESTIMATOR")]
    pub estimator: EstimatorArg,
    /// Transition density of the collision estimator's random walk.
    #[arg(long, value_enum, default_value = "brdf", env = "TESSERA_DENSITY")]
    pub density: DensityArg,
    /// Sample generator.
    #[arg(long, value_enum, default_value = "sobol", env = "TESSERA_SAMPLER")]
    pub sampler: SamplerArg,
    /// Stop paths after B bounces (0: only emitters seen directly; 7 matches Mitsuba's max_depth 8).
    #[arg(long, group = "termination", value_parser = clap::value_parser!(u32).range(0..=MAX_BOUNCES as i64), env = "TESSERA_MAX_BOUNCES")]
    pub max_bounces: Option<u32>,
    /// End paths by Russian roulette (unbiased).
    #[arg(long, group = "termination", env = "TESSERA_RR")]
    pub rr: bool,
    /// Truncate the Neumann series after paper 1's k_eps terms for this eps [default: 1/512].
    #[arg(long, group = "termination", env = "TESSERA_EPS")]
    pub eps: Option<f32>,
    /// Camera: a name or index among the scene's cameras [default: the first].
    #[arg(long, env = "TESSERA_CAMERA")]
    pub camera: Option<String>,
    /// Colour transport: rgb; spectral (4 hero wavelengths per path, measured spectra and metals'
    /// n + ik, RGB colours upsampled); auto: spectral only when the scene has spectral content.
    #[arg(long, value_enum, default_value = "auto", env = "TESSERA_COLOR")]
    pub color: ColorArg,
    /// Constant environment radiance, "R,G,B" or one number.
    #[arg(long, value_parser = parse_rgb, env = "TESSERA_ENV")]
    pub env: Option<Vec3>,
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

/// Default `eps` for `k_eps`: half an 8-bit step (paper 1).
pub const DEFAULT_EPS: f32 = 1.0 / 512.0;
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
            width: self.width,
            height: self.height,
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
        };
        Ok((settings, format!("{how}; {why}")))
    }

    /// The colour transport, and why: `auto` is spectral exactly when the scene carries spectra.
    fn color(&self, scene: &Scene) -> (ColorMode, String) {
        let mut content = scene.spectral_content();
        if content.len() > 3 {
            let more = content.len() - 2;
            content.truncate(2);
            content.push(format!("{more} more"));
        }
        match (self.color, content.is_empty()) {
            (ColorArg::Rgb, true) => (ColorMode::Rgb, "colour: rgb".into()),
            (ColorArg::Rgb, false) => (
                ColorMode::Rgb,
                format!("colour: rgb as asked, although {} carry spectra (RGB stand-ins used)", content.join(", ")),
            ),
            (ColorArg::Spectral, _) => (ColorMode::Spectral, "colour: spectral as asked".into()),
            (ColorArg::Auto, true) => (ColorMode::Rgb, "colour: rgb (auto: no spectral content)".into()),
            (ColorArg::Auto, false) => {
                (ColorMode::Spectral, format!("colour: spectral (auto: material {})", content.join(", ")))
            }
        }
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
        if let Some(b) = self.max_bounces {
            return Ok((Termination::MaxBounces(b), format!("paths end after {b} bounces (--max-bounces)")));
        }
        if self.rr {
            return Ok((Termination::RussianRoulette, "paths end by Russian roulette (--rr)".into()));
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
                Termination::RussianRoulette,
                format!("k_eps = {k} would be long (q = {q:.3}): paths end by Russian roulette instead"),
            )),
            None => Ok((
                Termination::RussianRoulette,
                format!("max albedo q = {q:.3} >= 1, k_eps is unbounded: paths end by Russian roulette"),
            )),
        }
    }
}
