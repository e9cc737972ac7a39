//! Multiple importance sampling (Veach 1997): next-event estimation and BSDF sampling both
//! score emission, each weighted by the power heuristic. The default estimator.

use super::PathResult;
use super::nee::{Combination, trace};
use crate::sampler::PixelSampler;
use crate::scene::Scene;
use crate::settings::RenderSettings;
use glam::Vec3;

pub fn radiance(scene: &Scene, settings: &RenderSettings, o: Vec3, d: Vec3, sampler: &PixelSampler) -> PathResult {
    trace(scene, settings, o, d, sampler, Combination::PowerHeuristic)
}
