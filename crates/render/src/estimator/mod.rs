//! Estimators of the radiance arriving along a camera ray, one file each; `wave/` renders plain
//! scenes' paths eight at a time with the bits of `nee`'s.

pub mod collision;
pub mod mis;
pub mod nee;
pub(crate) mod wave;

use crate::channels::{Channels, ColorModel};
use crate::interaction::{Hit, SurfacePoint};
use crate::sampler::PixelSampler;
use crate::scene::{MAX_WALLS_PASSED, Scene};
use crate::settings::{Estimator, RenderSettings, Termination};
use glam::Vec3;

/// What one path contributes to its pixel.
#[derive(Clone, Copy, Debug)]
pub struct PathResult<C = Vec3> {
    pub radiance: C,
    /// The camera ray itself hit an emitter (or escaped to a lit environment).
    pub saw_emitter: bool,
}

/// A camera ray `o + t d` and its first hit, which the caller finds (the tile loop traces camera
/// rays in packets).
#[derive(Clone, Copy, Debug)]
pub struct CameraRay {
    pub o: Vec3,
    pub d: Vec3,
    pub hit: Option<Hit>,
}

/// Radiance along the camera ray with the settings' estimator, in `model`'s channels.
pub fn radiance<M: ColorModel>(
    scene: &Scene,
    settings: &RenderSettings,
    ray: &CameraRay,
    sampler: &PixelSampler,
    model: &M,
) -> PathResult<M::C> {
    if ray.hit.is_none() {
        return escaped(scene, settings.estimator, ray.d, model);
    }
    match settings.estimator {
        Estimator::Collision => collision::radiance(scene, settings, ray, sampler, model),
        Estimator::Nee => nee::radiance(scene, settings, ray, sampler, model),
        Estimator::Mis => mis::radiance(scene, settings, ray, sampler, model),
    }
}

/// What a camera ray that meets nothing brings back: the environment along `d`, with the
/// operations each estimator's path loop does on a first ray that escapes (so the same bits),
/// without entering the loop: most camera rays of an asset seen small in its frame end here.
#[inline(always)]
fn escaped<M: ColorModel>(scene: &Scene, estimator: Estimator, d: Vec3, model: &M) -> PathResult<M::C> {
    let le = scene.lights.environment_radiance(d);
    let seen = le.max_element() > 0.0;
    let radiance = match estimator {
        // `l += w * illuminant`, the path weight `w` still one.
        Estimator::Collision => M::C::ZERO + M::C::ONE * model.illuminant(le),
        // `l += beta * illuminant * mis_weight`, the weight one after the camera (a delta).
        Estimator::Nee | Estimator::Mis if seen => M::C::ZERO + M::C::ONE * model.illuminant(le) * 1.0,
        Estimator::Nee | Estimator::Mis => M::C::ZERO,
    };
    PathResult { radiance, saw_emitter: seen }
}

/// Where a path that goes straight through the smooth thin wall at `sp` (along `d`) goes on
/// from; `None` once more than [`MAX_WALLS_PASSED`] walls were passed since the last bounce
/// (`walls` counts them).
pub(crate) fn past_wall(scene: &Scene, sp: &SurfacePoint, d: Vec3, walls: &mut u32) -> Option<Vec3> {
    *walls += 1;
    (*walls <= MAX_WALLS_PASSED).then(|| scene.offset_origin(sp, d))
}

/// True when a direction leaves on the side of the geometric surface that its shading-frame `z`
/// says (`cos_geometric = w.ng`, `ng` facing the viewer): above both for reflection, below both
/// for transmission. Where the shading normal disagrees with the geometry the path stops.
/// Written without branches, so that the wave's lanes ([`wave`]) share it.
#[inline(always)]
pub(crate) fn same_side(cos_geometric: f32, z: f32) -> bool {
    let below = z < 0.0;
    (below & (cos_geometric < 0.0)) | (!below & (cos_geometric > 0.0))
}

/// Roulette plays on paths whose weight (its largest channel) fell below this, and raises the
/// survivors' weight back to it. pbrt and Mitsuba use 1, which stakes everything a path still
/// carries on one coin: on the Cornell box with Mitsuba's termination (7 bounces, roulette from
/// the 5th) roulette then made 17 % of the error at 128 spp. With 1/3, 4 % more rays cut the
/// squared error by 8 % (12 % with visible emitters left out). Reference-free error x cost of
/// the weights 1, 1/2, 1/3, 1/5 and 1/8 put 1/3 at or within 3 % of the best on the open scenes
/// roulette touches (two Cornell boxes, EmissiveStrengthTest, Duck). In a closed sphere lit by
/// its own walls 1/3 was 4x better than 1, and smaller weights better still (1/8: 4.7x 1/3's).
const ROULETTE_WEIGHT: f32 = 1.0 / 3.0;

/// Russian roulette on the `from`-th bounce and later (`bounce` counts from 0): survive with
/// probability `min(1, max(weight) / ROULETTE_WEIGHT)` and divide the weight by it, which keeps
/// the estimator unbiased. Returns false to stop.
pub(crate) fn survives_roulette<C: Channels>(settings: &RenderSettings, bounce: u32, weight: &mut C, u: f32) -> bool {
    let Termination::RussianRoulette { from, .. } = settings.termination else {
        return true;
    };
    if bounce + 1 < from {
        return true;
    }
    let p = (weight.max_element() / ROULETTE_WEIGHT).min(1.0);
    if p >= 1.0 {
        return true;
    }
    if u >= p {
        return false;
    }
    *weight /= p;
    true
}
