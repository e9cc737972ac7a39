//! The Lambertian lobe: `f = rho / pi`, sampled with a cosine-weighted density.

use crate::sampling::sample_cosine_hemisphere;
use glam::Vec3;
use std::f32::consts::FRAC_1_PI;

/// Value of the Lambert BRDF per unit reflectance: `1 / pi` above the surface, else 0.
pub fn eval(wo: Vec3, wi: Vec3) -> f32 {
    if wo.z <= 0.0 || wi.z <= 0.0 { 0.0 } else { FRAC_1_PI }
}

/// Cosine-weighted sample in the local frame.
pub fn sample(u: [f32; 2]) -> Vec3 {
    sample_cosine_hemisphere(u)
}

/// Solid-angle density of [`sample`].
pub fn pdf(wi: Vec3) -> f32 {
    if wi.z <= 0.0 { 0.0 } else { wi.z * FRAC_1_PI }
}
