//! Estimators of the radiance arriving along a camera ray, one file each.

pub mod collision;
pub mod mis;
pub mod nee;

use crate::sampler::PixelSampler;
use crate::scene::Scene;
use crate::settings::{Estimator, RenderSettings, Termination};
use glam::Vec3;

/// What one path contributes to its pixel.
#[derive(Clone, Copy, Debug)]
pub struct PathResult {
    pub radiance: Vec3,
    /// The camera ray itself hit an emitter (or escaped to a lit environment).
    pub saw_emitter: bool,
}

/// Radiance along the camera ray `o + t d` with the settings' estimator.
pub fn radiance(scene: &Scene, settings: &RenderSettings, o: Vec3, d: Vec3, sampler: &PixelSampler) -> PathResult {
    match settings.estimator {
        Estimator::Collision => collision::radiance(scene, settings, o, d, sampler),
        Estimator::Nee => nee::radiance(scene, settings, o, d, sampler),
        Estimator::Mis => mis::radiance(scene, settings, o, d, sampler),
    }
}

/// Russian roulette after the second bounce: survive with probability `min(1, max(weight))`
/// and divide the weight by it, which keeps the estimator unbiased. Returns false to stop.
pub(crate) fn survives_roulette(settings: &RenderSettings, bounce: u32, weight: &mut Vec3, u: f32) -> bool {
    if settings.termination != Termination::RussianRoulette || bounce < 2 {
        return true;
    }
    let p = weight.max_element().min(1.0);
    if p >= 1.0 {
        return true;
    }
    if u >= p {
        return false;
    }
    *weight /= p;
    true
}
