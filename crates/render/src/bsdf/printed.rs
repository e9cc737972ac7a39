//! Dimov, Gurov and Penzov's BRDF as printed, `f = F(0)/pi + F(theta') D G / (pi cos(theta) cos(theta'))`, with
//! `D = exp(-tan^2(theta_h) / m^2)` and Cook-Torrance's `G = min(1, 2 (n.h)(n.v)/(v.h),
//! 2 (n.h)(n.l)/(v.h))`, both at most 1 as the paper takes them. Kept for the stability study
//! only, never rendered: its albedo exceeds 1 at grazing angles, where the Neumann series stops
//! converging. Tessera renders the normalised form ([`super::Bsdf`]: `D` integrating to 1 over
//! projected area, Smith `G`, `4` in the denominator, Fresnel-weighted diffuse).

use super::{Bsdf, Coat, Distribution, Fresnel, Microfacet, Refraction, Sheen, fresnel};
use glam::Vec3;

/// The interface whose Fresnel term both forms use.
#[derive(Clone, Copy, Debug)]
pub enum Interface {
    Dielectric { eta: f32 },
    Conductor { n: f32, k: f32 },
}

impl Interface {
    pub fn reflectance(&self, cos: f32) -> f32 {
        match *self {
            Interface::Dielectric { eta } => fresnel::dielectric(cos, eta),
            Interface::Conductor { n, k } => fresnel::conductor(cos, Vec3::splat(n), Vec3::splat(k)).x,
        }
    }
}

/// The normalised form Tessera renders for `interface` at Beckmann roughness `m` (alpha = m):
/// a conductor, or a dielectric layer over a white Lambertian base.
pub fn normalised(interface: Interface, m: f32) -> Bsdf {
    let (diffuse, fresnel) = match interface {
        Interface::Dielectric { eta } => (Vec3::ONE, Fresnel::Dielectric { eta }),
        Interface::Conductor { n, k } => (Vec3::ZERO, Fresnel::Conductor { eta: Vec3::splat(n), k: Vec3::splat(k) }),
    };
    Bsdf {
        diffuse,
        fresnel,
        microfacet: Microfacet::new(Distribution::Beckmann, m),
        coat: Coat::NONE,
        sheen: Sheen::NONE,
        refraction: Refraction::NONE,
        compensated: false,
    }
}

/// The printed BRDF with Beckmann-exponential roughness `m`, in the local frame (+z normal).
pub fn eval(interface: Interface, m: f32, wo: Vec3, wi: Vec3) -> f32 {
    if wo.z <= 0.0 || wi.z <= 0.0 {
        return 0.0;
    }
    let h = (wo + wi).normalize();
    let (nh, vh) = (h.z, wo.dot(h));
    let tan2 = (1.0 - nh * nh).max(0.0) / (nh * nh);
    let d = libm::expf(-tan2 / (m * m)); // at most 1, as printed: not normalised
    let g = (2.0 * nh * wo.z / vh).min(2.0 * nh * wi.z / vh).min(1.0);
    interface.reflectance(1.0) / std::f32::consts::PI
        + interface.reflectance(vh) * d * g / (std::f32::consts::PI * wo.z * wi.z)
}

/// Directional albedo `integral f(wo, wi) cos(theta_i) dwi` at `theta_o` (radians), by the
/// midpoint rule over `n` cells in `cos(theta_i)` and `4n` in `phi` (deterministic: the same
/// number every time).
pub fn albedo(f: impl Fn(Vec3, Vec3) -> f32, theta_o: f32, n: usize) -> f64 {
    let (sin_o, cos_o) = libm::sincosf(theta_o);
    let wo = Vec3::new(sin_o, 0.0, cos_o);
    let (nu, nphi) = (n, 4 * n);
    let cell = (1.0 / nu as f64) * (2.0 * std::f64::consts::PI / nphi as f64);
    let mut sum = 0.0f64;
    for i in 0..nu {
        let cos = ((i as f64 + 0.5) / nu as f64) as f32;
        let sin = (1.0 - cos * cos).max(0.0).sqrt();
        for j in 0..nphi {
            let phi = (2.0 * std::f64::consts::PI * (j as f64 + 0.5) / nphi as f64) as f32;
            let (sin_phi, cos_phi) = libm::sincosf(phi);
            let wi = Vec3::new(sin * cos_phi, sin * sin_phi, cos);
            sum += (f(wo, wi) * cos) as f64;
        }
    }
    sum * cell
}
