//! Multiple importance sampling (Veach 1997): next-event estimation and BSDF sampling both
//! score emission, each weighted by the power heuristic. The default estimator.

use super::PathResult;
use super::nee::{Combination, trace};
use crate::channels::ColorModel;
use crate::sampler::PixelSampler;
use crate::scene::Scene;
use crate::settings::RenderSettings;
use glam::Vec3;

pub fn radiance<M: ColorModel>(
    scene: &Scene,
    settings: &RenderSettings,
    o: Vec3,
    d: Vec3,
    sampler: &PixelSampler,
    model: &M,
) -> PathResult<M::C> {
    trace(scene, settings, o, d, sampler, Combination::PowerHeuristic, model)
}
