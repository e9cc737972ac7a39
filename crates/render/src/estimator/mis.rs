//! Multiple importance sampling (Veach 1997): next-event estimation and BSDF sampling both
//! score emission, each weighted by the power heuristic. The default estimator.

use super::nee::{Combination, trace};
use super::{CameraRay, PathResult};
use crate::channels::ColorModel;
use crate::sampler::PixelSampler;
use crate::scene::Scene;
use crate::settings::RenderSettings;

pub fn radiance<M: ColorModel>(
    scene: &Scene,
    settings: &RenderSettings,
    ray: &CameraRay,
    sampler: &PixelSampler,
    model: &M,
) -> PathResult<M::C> {
    trace(scene, settings, ray, sampler, Combination::PowerHeuristic, model)
}
