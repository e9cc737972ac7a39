//! Microfacet distributions `D` (GGX / Trowbridge-Reitz and Beckmann), the height-correlated
//! Smith masking-shadowing `G`, and their sampling (visible normals for GGX, Heitz 2018).
//! All vectors are in the local shading frame, +z the macro-surface normal.

use glam::Vec3;
use std::f32::consts::PI;

/// Which normal distribution function a specular lobe uses.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Distribution {
    Ggx,
    Beckmann,
}

/// A microfacet distribution with roughness `alpha` (glTF: `alpha = roughness^2`), isotropic
/// unless [`Microfacet::anisotropic`] stretched it (GGX only): then `alpha` along the local
/// direction `(cos, sin, 0)` and `alpha_across` across it (KHR_materials_anisotropy).
#[derive(Clone, Copy, Debug)]
pub struct Microfacet {
    pub distribution: Distribution,
    pub alpha: f32,
    pub alpha_across: f32,
    /// The direction of `alpha` in the local frame, as cosine and sine of its angle from +x.
    pub direction: (f32, f32),
}

/// Below this roughness a lobe is treated as a perfect mirror: `D` would overflow f32.
pub const MIRROR_ALPHA: f32 = 1e-3;

impl Microfacet {
    pub const fn new(distribution: Distribution, alpha: f32) -> Self {
        Self { distribution, alpha, alpha_across: alpha, direction: (1.0, 0.0) }
    }

    /// GGX with roughness `along` in the local direction at `angle` cosine and sine
    /// `direction` from +x, and `across` across it. A distribution rough one way and smooth the
    /// other keeps `across` at [`MIRROR_ALPHA`], so that `D` stays finite.
    pub fn anisotropic(along: f32, across: f32, direction: (f32, f32)) -> Self {
        if along < MIRROR_ALPHA || along == across {
            return Self::new(Distribution::Ggx, along);
        }
        Self { distribution: Distribution::Ggx, alpha: along, alpha_across: across.max(MIRROR_ALPHA), direction }
    }

    pub fn is_mirror(&self) -> bool {
        self.alpha < MIRROR_ALPHA
    }

    fn is_anisotropic(&self) -> bool {
        self.alpha_across != self.alpha
    }

    /// `w` in the frame whose +x is the direction of `alpha`.
    fn stretched(&self, w: Vec3) -> Vec3 {
        let (c, s) = self.direction;
        Vec3::new(c * w.x + s * w.y, -s * w.x + c * w.y, w.z)
    }

    fn unstretched(&self, w: Vec3) -> Vec3 {
        let (c, s) = self.direction;
        Vec3::new(c * w.x - s * w.y, s * w.x + c * w.y, w.z)
    }

    /// The normal distribution `D(h)`, normalised so that `int D(h) cos(theta_h) dh = 1`.
    pub fn d(&self, h: Vec3) -> f32 {
        let cos2 = h.z * h.z;
        if h.z <= 0.0 {
            return 0.0;
        }
        if self.is_anisotropic() {
            // Anisotropic GGX: 1 / (pi ax ay (x^2 / ax^2 + y^2 / ay^2 + z^2)^2).
            let (ax, ay) = (self.alpha, self.alpha_across);
            let h = self.stretched(h);
            let t = h.x * h.x / (ax * ax) + h.y * h.y / (ay * ay) + cos2;
            return 1.0 / (PI * ax * ay * t * t);
        }
        let a2 = self.alpha * self.alpha;
        match self.distribution {
            Distribution::Ggx => {
                let t = cos2 * (a2 - 1.0) + 1.0;
                a2 / (PI * t * t)
            }
            Distribution::Beckmann => {
                let tan2 = (1.0 - cos2).max(0.0) / cos2;
                libm::expf(-tan2 / a2) / (PI * a2 * cos2 * cos2)
            }
        }
    }

    /// Smith's auxiliary function `Lambda(w)`.
    pub fn lambda(&self, w: Vec3) -> f32 {
        if self.is_anisotropic() {
            // The roughness seen along w's azimuth: tan^2 alpha_0^2 = (x^2 ax^2 + y^2 ay^2) / z^2.
            let w = self.stretched(w);
            let (ax, ay) = (self.alpha, self.alpha_across);
            let stretched = (w.x * w.x * ax * ax + w.y * w.y * ay * ay) / (w.z * w.z);
            return if stretched == 0.0 { 0.0 } else { 0.5 * ((1.0 + stretched).sqrt() - 1.0) };
        }
        let cos2 = w.z * w.z;
        let sin2 = (1.0 - cos2).max(0.0);
        if sin2 == 0.0 {
            return 0.0;
        }
        let tan2 = sin2 / cos2;
        match self.distribution {
            Distribution::Ggx => 0.5 * ((1.0 + self.alpha * self.alpha * tan2).sqrt() - 1.0),
            Distribution::Beckmann => {
                // Walter et al. 2007's rational approximation.
                let a = 1.0 / (self.alpha * tan2.sqrt());
                if a >= 1.6 { 0.0 } else { (1.0 - 1.259 * a + 0.396 * a * a) / (3.535 * a + 2.181 * a * a) }
            }
        }
    }

    /// Masking `G1(w) = 1 / (1 + Lambda(w))`.
    pub fn g1(&self, w: Vec3) -> f32 {
        1.0 / (1.0 + self.lambda(w))
    }

    /// Height-correlated masking-shadowing `G2 = 1 / (1 + Lambda(wo) + Lambda(wi))`.
    pub fn g2(&self, wo: Vec3, wi: Vec3) -> f32 {
        1.0 / (1.0 + self.lambda(wo) + self.lambda(wi))
    }

    /// Samples a microfacet normal `h`: visible normals for GGX (density `G1(wo) max(0, wo.h) D(h) / wo.z`),
    /// `D(h) cos(theta_h)` for Beckmann.
    pub fn sample_h(&self, wo: Vec3, u: [f32; 2]) -> Vec3 {
        match self.distribution {
            Distribution::Ggx => self.sample_ggx_visible(wo, u),
            Distribution::Beckmann => {
                let tan2 = -self.alpha * self.alpha * libm::logf((1.0 - u[0]).max(1e-12));
                let cos = 1.0 / (1.0 + tan2).sqrt();
                let sin = (1.0 - cos * cos).max(0.0).sqrt();
                let (sin_phi, cos_phi) = libm::sincosf(2.0 * PI * u[1]);
                Vec3::new(sin * cos_phi, sin * sin_phi, cos)
            }
        }
    }

    /// Density of [`Self::sample_h`] over microfacet normals.
    pub fn pdf_h(&self, wo: Vec3, h: Vec3) -> f32 {
        match self.distribution {
            Distribution::Ggx => self.g1(wo) * wo.dot(h).max(0.0) * self.d(h) / wo.z,
            Distribution::Beckmann => self.d(h) * h.z,
        }
    }

    /// Heitz 2018, "Sampling the GGX Distribution of Visible Normals".
    fn sample_ggx_visible(&self, wo: Vec3, u: [f32; 2]) -> Vec3 {
        if self.is_anisotropic() {
            return self.unstretched(self.sample_ggx_stretched(self.stretched(wo), u));
        }
        self.sample_ggx_stretched(wo, u)
    }

    /// Heitz 2018, `wo` in the frame of the roughness's direction (any frame when isotropic).
    fn sample_ggx_stretched(&self, wo: Vec3, u: [f32; 2]) -> Vec3 {
        let (ax, ay) = (self.alpha, self.alpha_across);
        let vh = Vec3::new(ax * wo.x, ay * wo.y, wo.z).normalize();
        let len2 = vh.x * vh.x + vh.y * vh.y;
        let t1 = if len2 > 0.0 { Vec3::new(-vh.y, vh.x, 0.0) / len2.sqrt() } else { Vec3::X };
        let t2 = vh.cross(t1);
        let r = u[0].sqrt();
        let (sin_phi, cos_phi) = libm::sincosf(2.0 * PI * u[1]);
        let p1 = r * cos_phi;
        let s = 0.5 * (1.0 + vh.z);
        let p2 = (1.0 - s) * (1.0 - p1 * p1).max(0.0).sqrt() + s * r * sin_phi;
        let nh = p1 * t1 + p2 * t2 + (1.0 - p1 * p1 - p2 * p2).max(0.0).sqrt() * vh;
        Vec3::new(ax * nh.x, ay * nh.y, nh.z.max(1e-6)).normalize()
    }
}
