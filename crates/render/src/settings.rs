//! Render settings: everything besides the scene that decides an image's bits.

use crate::sampler::SamplerKind;

/// Which Monte Carlo estimator computes a path's radiance.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Estimator {
    /// Dimov, Gurov and Penzov's collision estimator (eq. 5): scores `Le` at every collision of a random walk.
    Collision,
    /// Next-event estimation: a light sample at every vertex, BSDF-sampled continuation.
    Nee,
    /// Light and BSDF sampling combined by multiple importance sampling (power heuristic).
    Mis,
}

/// The transition density of the collision estimator's walk.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Density {
    Uniform,
    Cosine,
    /// Proportional to the kernel `K = f_r cos` as far as the BSDF's sampling allows (Dimov, Gurov and Penzov, eq. 8).
    Brdf,
}

impl Estimator {
    pub fn name(self) -> &'static str {
        match self {
            Estimator::Collision => "collision",
            Estimator::Nee => "nee",
            Estimator::Mis => "mis",
        }
    }
}

impl Density {
    pub fn name(self) -> &'static str {
        match self {
            Density::Uniform => "uniform",
            Density::Cosine => "cosine",
            Density::Brdf => "brdf",
        }
    }
}

/// What light transport carries along a path.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum ColorMode {
    /// Three linear sRGB channels.
    Rgb,
    /// Four hero wavelengths per path; measured spectra and metals' `n + i k` where the scene
    /// has them, upsampled RGB elsewhere; XYZ to linear sRGB at the end.
    Spectral,
}

impl ColorMode {
    pub fn name(self) -> &'static str {
        match self {
            ColorMode::Rgb => "rgb",
            ColorMode::Spectral => "spectral",
        }
    }
}

/// How a light is chosen for next-event estimation.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum LightSampler {
    /// In proportion to each light's power, wherever the shading point is.
    Power,
    /// By a light tree: in proportion to bounds on what each light contributes at the shading
    /// point (power, distance, orientation); scenes with many small lights need far fewer samples.
    Tree,
}

impl LightSampler {
    pub fn name(self) -> &'static str {
        match self {
            LightSampler::Power => "power",
            LightSampler::Tree => "tree",
        }
    }
}

/// How a path ends.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Termination {
    /// Exactly this many bounces at most (0: only emitters seen directly). Used for `--max-bounces`
    /// and for Dimov, Gurov and Penzov's `k_eps`.
    MaxBounces(u32),
    /// Russian roulette on the path weight from bounce `from` on (1: from the first), with paths
    /// capped at `max_bounces`. Unbiased for that cap: with [`ROULETTE_MAX_BOUNCES`], for the
    /// whole series; with `MaxBounces(b)`'s cap `b`, it has `MaxBounces(b)`'s expectation (Mitsuba's
    /// path tracer does this: `max_depth` 8 and `rr_depth` 5 are `{ from: 5, max_bounces: 7 }`).
    RussianRoulette { from: u32, max_bounces: u32 },
}

/// Hard cap on path length under Russian roulette, so no path runs forever.
pub const ROULETTE_MAX_BOUNCES: u32 = 1024;

/// The bounce from which `--rr` plays roulette unless told otherwise.
pub const ROULETTE_FROM: u32 = 3;

impl Termination {
    /// Russian roulette from the third bounce on, uncapped (`--rr`).
    pub const ROULETTE: Termination =
        Termination::RussianRoulette { from: ROULETTE_FROM, max_bounces: ROULETTE_MAX_BOUNCES };
}

#[derive(Clone, Debug, PartialEq)]
pub struct RenderSettings {
    pub width: u32,
    pub height: u32,
    pub seed: u64,
    pub estimator: Estimator,
    pub density: Density,
    pub sampler: SamplerKind,
    pub termination: Termination,
    /// Index into the scene's cameras.
    pub camera: usize,
    pub color: ColorMode,
    /// Leave the background out: camera rays that miss the scene add nothing (the environment
    /// still lights it), so the image can be composited by its coverage.
    pub transparent: bool,
    pub lights: LightSampler,
    /// glTF materials give back the energy single scattering loses ([`crate::bsdf::energy`]);
    /// off: glTF's single-scattering definition (`--energy-compensation off`).
    pub energy_compensation: bool,
    /// Also sum the feature layers a denoiser reads, albedo and normal at each sample's first
    /// diffuse or glossy hit ([`crate::TileSums::features`]; `--aov albedo,normal`). Off by
    /// default: the colour's bits and a result's size do not change with it off.
    pub features: bool,
    /// Denoise the finished image with the help of the feature layers (`--denoise`, which
    /// turns `features` on): a `denoised` layer beside the raw colour. The renderer ignores it;
    /// whoever writes the image (`tessera render`, the coordinator) denoises.
    pub denoise: bool,
    /// Adaptive sampling stops a tile only when the upper bound of its relative error at this
    /// confidence is below the target, and the image states its error with that bound
    /// (`--confidence`, for example 0.95); 0: on the error estimate alone. The renderer ignores it.
    pub confidence: f32,
}

/// Bounces of [`RenderSettings::new`]'s paths: Mitsuba's default `max_depth` 8.
pub const DEFAULT_BOUNCES: u32 = 7;

impl RenderSettings {
    /// Settings for a `width` x `height` image with the command line's defaults: seed 0, MIS,
    /// BSDF sampling, Sobol samples, [`DEFAULT_BOUNCES`] bounces, the first camera, RGB, an
    /// opaque background, lights chosen by power, energy compensation on. Other settings are written as struct updates
    /// of these (`RenderSettings { seed, ..RenderSettings::new(w, h) }`).
    pub fn new(width: u32, height: u32) -> Self {
        Self {
            width,
            height,
            seed: 0,
            estimator: Estimator::Mis,
            density: Density::Brdf,
            sampler: SamplerKind::Sobol,
            termination: Termination::MaxBounces(DEFAULT_BOUNCES),
            camera: 0,
            color: ColorMode::Rgb,
            transparent: false,
            lights: LightSampler::Power,
            energy_compensation: true,
            features: false,
            denoise: false,
            confidence: 0.0,
        }
    }

    pub fn max_bounces(&self) -> u32 {
        match self.termination {
            Termination::MaxBounces(b) => b,
            Termination::RussianRoulette { max_bounces, .. } => max_bounces,
        }
    }

    /// A one-line description, recorded in image headers.
    pub fn describe(&self) -> String {
        let termination = match self.termination {
            Termination::MaxBounces(b) => format!("max-bounces={b}"),
            Termination::ROULETTE => "rr".to_string(),
            Termination::RussianRoulette { from, max_bounces } => format!("rr-from={from} max-bounces={max_bounces}"),
        };
        format!(
            "width={} height={} seed={} estimator={} density={} sampler={} {} camera={} color={}",
            self.width,
            self.height,
            self.seed,
            self.estimator.name(),
            self.density.name(),
            self.sampler.name(),
            termination,
            self.camera,
            self.color.name()
        ) + if self.transparent { " transparent" } else { "" }
            + if self.lights == LightSampler::Tree { " lights=tree" } else { "" }
            + if self.energy_compensation { "" } else { " single-scattering" }
            + if self.features { " layers=albedo,normal" } else { "" }
            + if self.denoise { " denoise" } else { "" }
            + &if self.confidence > 0.0 { format!(" confidence={}", self.confidence) } else { String::new() }
    }
}

/// Dimov, Gurov and Penzov's truncation depth `k_eps = ceil(c1 |ln eps| + c2)`, with `c1 = 1 / |ln q|` and
/// `c2 = |ln((1 - q) / Le*)| / |ln q|`. `None` when `q >= 1` (the series need not converge).
pub fn k_eps(q: f32, le_max: f32, eps: f32) -> Option<u32> {
    if !(0.0..1.0).contains(&q) || eps <= 0.0 || le_max <= 0.0 {
        return None;
    }
    if q == 0.0 {
        return Some(0); // nothing reflects: only emitted light
    }
    let (q, le, eps) = (q as f64, le_max as f64, eps as f64);
    let c1 = 1.0 / libm::log(q).abs();
    let c2 = libm::log((1.0 - q) / le).abs() / libm::log(q).abs();
    let k = (c1 * libm::log(eps).abs() + c2).ceil();
    (k.is_finite() && k < u32::MAX as f64).then_some(k as u32)
}

/// Dimov, Gurov and Penzov's bound on the truncation error after `k` terms: `Le* q^k / (1 - q)`.
pub fn truncation_bound(q: f32, le_max: f32, k: u32) -> f32 {
    le_max * q.powi(k as i32) / (1.0 - q)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn k_eps_matches_worked_examples() {
        // q = 0.5, Le* = 1, eps = 1/512: c1 = 1/ln2, c2 = ln2/ln2 = 1, k = ceil(9 + 1) = 10.
        assert_eq!(k_eps(0.5, 1.0, 1.0 / 512.0), Some(10));
        // q = 0.8, Le* = 17, eps = 1/512: (ln 512 + |ln(0.2/17)|) / |ln 0.8| = (6.238 + 4.443) / 0.2231 = 47.87.
        assert_eq!(k_eps(0.8, 17.0, 1.0 / 512.0), Some(48));
        assert_eq!(k_eps(1.0, 1.0, 0.01), None);
    }

    #[test]
    fn k_eps_meets_its_own_bound() {
        for &(q, le) in &[(0.3f32, 1.0f32), (0.7, 17.0), (0.9, 5.0), (0.95, 0.5)] {
            let eps = 1.0 / 512.0;
            let k = k_eps(q, le, eps).unwrap();
            assert!(truncation_bound(q, le, k) <= eps * 1.0001, "q={q} le={le} k={k}");
            // and it is the smallest such k when (1 - q) / Le* < 1
            if (1.0 - q) / le < 1.0 {
                assert!(truncation_bound(q, le, k - 1) > eps, "q={q} le={le} k={k}");
            }
        }
    }
}
