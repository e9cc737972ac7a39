//! Small geometric helpers shared by the renderer: orthonormal frames and luminance.
//!
//! Transcendental functions (sin, exp, pow, ...) come from the `libm` crate, a pure-Rust port of
//! musl's, everywhere in the renderer and the scene loader, never from the platform's C library:
//! glibc versions, macOS and other systems round differently, and glibc picks an FMA variant of
//! `sinf`, `expf`, `powf`, `exp` ... by CPU at run time. One different last bit sends a path
//! elsewhere, so two workers would render the same sample differently and a farm's image would
//! depend on which worker took which tile (invariants 1 and 2). `libm` is plain IEEE arithmetic
//! (Rust never fuses it into FMAs), so a build gives the same bits on every machine.
//! `clippy.toml` disallows the std methods, which CI enforces.

use glam::Vec3;

/// An orthonormal basis whose `n` axis is the local +z direction (shading space).
#[derive(Clone, Copy, Debug)]
pub struct Frame {
    pub s: Vec3,
    pub t: Vec3,
    pub n: Vec3,
}

impl Frame {
    /// Builds a frame around a unit normal (Duff et al. 2017, "Building an Orthonormal Basis, Revisited").
    pub fn from_normal(n: Vec3) -> Self {
        let sign = 1.0f32.copysign(n.z);
        let a = -1.0 / (sign + n.z);
        let b = n.x * n.y * a;
        let s = Vec3::new(1.0 + sign * n.x * n.x * a, sign * b, -sign * n.x);
        let t = Vec3::new(b, sign + n.y * n.y * a, -n.y);
        Self { s, t, n }
    }

    /// Builds a frame around a unit normal with `s` as close as possible to `tangent`.
    pub fn from_normal_tangent(n: Vec3, tangent: Vec3) -> Self {
        let s = (tangent - n * n.dot(tangent)).normalize_or_zero();
        if s == Vec3::ZERO {
            return Self::from_normal(n);
        }
        Self { s, t: n.cross(s), n }
    }

    pub fn to_local(&self, v: Vec3) -> Vec3 {
        Vec3::new(v.dot(self.s), v.dot(self.t), v.dot(self.n))
    }

    pub fn to_world(&self, v: Vec3) -> Vec3 {
        self.s * v.x + self.t * v.y + self.n * v.z
    }
}

/// Rec.709 luminance of a linear RGB triple.
pub fn luminance(c: Vec3) -> f32 {
    0.2126 * c.x + 0.7152 * c.y + 0.0722 * c.z
}

/// Mirror `v` about the unit vector `n`.
pub fn reflect(v: Vec3, n: Vec3) -> Vec3 {
    2.0 * v.dot(n) * n - v
}

/// `v` in the local frame mirrored through the surface (`z` negated): where a thin wall passes a
/// direction reflected above it, or a hemisphere's sample lands below.
pub fn through_surface(v: Vec3) -> Vec3 {
    Vec3::new(v.x, v.y, -v.z)
}

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
