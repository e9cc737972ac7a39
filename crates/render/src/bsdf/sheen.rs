//! KHR_materials_sheen's lobe (cloth, velvet): the "Charlie" distribution of Estevez and Kulla,
//! "Production Friendly Microfacet Sheen BRDF" (2017), `D = (2 + 1/a) sin(theta_h)^(1/a) / 2 pi`
//! with `a = sheenRoughness^2`, and their fitted visibility `V = 1 / ((1 + L(wo) + L(wi)) 4 cos_o
//! cos_i)`, as the extension's reference implementation writes them. What the lobe reflects the
//! layers below lose, by albedo scaling: `1 - max(sheenColor) E(cos)`, with `E` the lobe's
//! directional albedo (tabulated once) at the more grazing of `wo` and `wi`.

use glam::Vec3;
use std::f32::consts::PI;
use std::sync::OnceLock;

/// Sheen roughness below this is this (the distribution's exponent `1/a` would overflow).
const MIN_ROUGHNESS: f32 = 0.07;

/// The lobe's shape: roughness `sheenRoughness` (before squaring).
#[derive(Clone, Copy, Debug)]
pub struct Charlie {
    pub roughness: f32,
}

impl Charlie {
    pub fn new(roughness: f32) -> Self {
        Self { roughness: roughness.clamp(MIN_ROUGHNESS, 1.0) }
    }

    fn alpha(&self) -> f32 {
        self.roughness * self.roughness
    }

    /// The Charlie distribution at half vector `h`.
    pub fn d(&self, h: Vec3) -> f32 {
        let inv = 1.0 / self.alpha();
        let sin2 = (1.0 - h.z * h.z).max(0.0);
        (2.0 + inv) * libm::powf(sin2, 0.5 * inv) / (2.0 * PI)
    }

    /// Estevez and Kulla's fitted `Lambda`, interpolated in `(1 - alpha)^2`.
    fn lambda(&self, cos: f32) -> f32 {
        let t = (1.0 - self.alpha()) * (1.0 - self.alpha());
        let mix = |a: f32, b: f32| a + (b - a) * t;
        let fit = |x: f32| {
            let (a, b, c) = (mix(21.5473, 25.3245), mix(3.82987, 3.32435), mix(0.19823, 0.16801));
            let (d, e) = (mix(-1.97760, -1.27393), mix(-4.32054, -4.85967));
            a / (1.0 + b * libm::powf(x, c)) + d * x + e
        };
        let cos = cos.abs();
        if cos < 0.5 { libm::expf(fit(cos)) } else { libm::expf(2.0 * fit(0.5) - fit(1.0 - cos)) }
    }

    /// `f` per unit sheen colour for `wo`, `wi` above the surface: `D(h) V(wo, wi)`.
    pub fn eval(&self, wo: Vec3, wi: Vec3) -> f32 {
        let h = (wo + wi).normalize();
        let v = 1.0 / ((1.0 + self.lambda(wo.z) + self.lambda(wi.z)) * (4.0 * wo.z * wi.z));
        self.d(h) * v.clamp(0.0, 1.0)
    }

    /// The lobe's directional albedo `E(cos) = int D V cos_i dwi` per unit colour, from a table
    /// over `cos` and roughness computed once.
    pub fn albedo(&self, cos: f32) -> f32 {
        let table = albedo_table();
        let x = cos.clamp(0.0, 1.0) * (COSINES - 1) as f32;
        let y = (self.roughness - MIN_ROUGHNESS) / (1.0 - MIN_ROUGHNESS) * (ROUGHNESSES - 1) as f32;
        let (i, j) = ((x as usize).min(COSINES - 2), (y as usize).min(ROUGHNESSES - 2));
        let (fx, fy) = (x - i as f32, y - j as f32);
        let at = |i: usize, j: usize| table[j * COSINES + i];
        let low = at(i, j) + (at(i + 1, j) - at(i, j)) * fx;
        let high = at(i, j + 1) + (at(i + 1, j + 1) - at(i, j + 1)) * fx;
        low + (high - low) * fy
    }
}

/// Table entries: cosines and roughnesses, evenly spaced.
const COSINES: usize = 32;
const ROUGHNESSES: usize = 16;

/// `E(cos, roughness)` by the midpoint rule over the hemisphere (32 x 64 cells in `cos_i` and
/// `phi`; about 0.25 s on one core, once), rows of roughness in parallel. Plain arithmetic and
/// `libm`, so every machine and thread count gets its bits.
fn albedo_table() -> &'static [f32] {
    static TABLE_VALUES: OnceLock<Vec<f32>> = OnceLock::new();
    TABLE_VALUES.get_or_init(|| crate::math::rows_in_parallel(ROUGHNESSES, albedo_row).concat())
}

/// Row `j` of [`albedo_table`]: `E` at each cosine for roughness `j` of `ROUGHNESSES`.
fn albedo_row(j: usize) -> Vec<f32> {
    let (nz, nphi) = (32, 64);
    let lobe = Charlie::new(MIN_ROUGHNESS + (1.0 - MIN_ROUGHNESS) * j as f32 / (ROUGHNESSES - 1) as f32);
    (0..COSINES)
        .map(|i| {
            let cos_o = (i as f32 / (COSINES - 1) as f32).max(1e-3);
            let wo = Vec3::new((1.0 - cos_o * cos_o).sqrt(), 0.0, cos_o);
            let mut sum = 0.0f64;
            for a in 0..nz {
                let z = (a as f32 + 0.5) / nz as f32;
                let r = (1.0 - z * z).sqrt();
                for b in 0..nphi {
                    let (s, c) = libm::sincosf(2.0 * PI * (b as f32 + 0.5) / nphi as f32);
                    let wi = Vec3::new(r * c, r * s, z);
                    sum += (lobe.eval(wo, wi) * z) as f64;
                }
            }
            // dw = dz dphi over cells of 1/nz by 2 pi/nphi.
            (sum * 2.0 * std::f64::consts::PI / (nz * nphi) as f64) as f32
        })
        .collect()
}

/// Computes the table now, before the first sample that needs it.
pub fn prepare() {
    albedo_table();
}
