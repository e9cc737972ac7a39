//! Sampling helpers, as pbrt-v4's `util/sampling`: warps of uniform numbers to directions (with
//! their densities in the comments), the power heuristic that weighs two strategies, and the
//! rescaling that lets one number choose among options and then serve again within the choice.

use glam::Vec3;

/// The largest `f32` below 1.
pub(crate) const ONE_BELOW: f32 = 1.0 - f32::EPSILON / 2.0;

/// Uniformly distributed direction on the upper (z > 0) hemisphere; pdf `1 / (2 pi)`.
pub fn sample_uniform_hemisphere(u: [f32; 2]) -> Vec3 {
    let z = u[0];
    let r = (1.0 - z * z).max(0.0).sqrt();
    let (sin, cos) = libm::sincosf(2.0 * std::f32::consts::PI * u[1]);
    Vec3::new(r * cos, r * sin, z)
}

/// Uniformly distributed direction on the unit sphere; pdf `1 / (4 pi)`.
pub fn sample_uniform_sphere(u: [f32; 2]) -> Vec3 {
    let z = 1.0 - 2.0 * u[0];
    let r = (1.0 - z * z).max(0.0).sqrt();
    let (sin, cos) = libm::sincosf(2.0 * std::f32::consts::PI * u[1]);
    Vec3::new(r * cos, r * sin, z)
}

/// Cosine-weighted direction on the upper hemisphere (Malley's method); pdf `cos / pi`.
pub fn sample_cosine_hemisphere(u: [f32; 2]) -> Vec3 {
    let r = u[0].sqrt();
    let (sin, cos) = libm::sincosf(2.0 * std::f32::consts::PI * u[1]);
    let z = (1.0 - u[0]).max(0.0).sqrt();
    Vec3::new(r * cos, r * sin, z)
}

/// Power heuristic with beta = 2 (Veach 1997, eq. 9.13), for the strategy with density `pa`.
#[inline(always)]
pub fn power_heuristic(pa: f32, pb: f32) -> f32 {
    let (a, b) = (pa * pa, pb * pb);
    if a + b == 0.0 { 0.0 } else { a / (a + b) }
}

/// `u`, which lies in the interval from `lo` of width `pmf`, rescaled to `[0, 1)` within it:
/// what light choice (`light.rs`: `choose`, `LightSet::choose_lanes`) and the light tree's descent hand on.
#[inline(always)]
pub(crate) fn rescaled(u: f32, lo: f32, pmf: f32) -> f32 {
    ((u - lo) / pmf).clamp(0.0, ONE_BELOW)
}
