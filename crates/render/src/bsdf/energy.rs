//! Energy that single-scattering GGX loses, given back (Kulla and Conty 2017, "Revisiting
//! Physically Based Shading at Imageworks").
//!
//! A microfacet lobe `F D G2 / (4 cos_o cos_i)` counts light that leaves after one bounce on the
//! microsurface; light that bounces between microfacets is lost (two thirds of it for a white
//! metal of roughness 1 seen head-on). glTF's `fresnel_mix` then weights the diffuse base by
//! what the Fresnel term lets through at `wo.h`, which is not what the rough specular layer
//! above it reflects. Together a white rough plastic keeps about 90 % of the light it receives
//! head-on and less at grazing angles, where Blender's Principled BSDF keeps all of it.
//!
//! With `E(mu)` the directional albedo of the lobe with `F = 1` and `E_avg = 2 int E(mu) mu dmu`:
//! - the bounces after the first come back as a second, diffuse-like lobe
//!   `F_ms (1 - E(mu_o)) (1 - E(mu_i)) / (pi (1 - E_avg))`, whose albedo is `1 - E(mu_o)` times
//!   `F_ms = F_avg^2 E_avg / (1 - F_avg (1 - E_avg))` (the share a coloured Fresnel of average
//!   `F_avg` lets out over all the bounces);
//! - the base layer under a dielectric of total albedo `E_s` (first bounce and the rest) is weighted
//!   `(1 - E_s(mu_o)) (1 - E_s(mu_i)) / (1 - E_s,avg)`: reciprocal, and a white base then returns
//!   exactly what the layer does not reflect, so the whole keeps all the light.
//!
//! `E` and its Schlick part `S = int (1 - wo.h)^5 D G2 / (4 cos_o cos_i) cos_i dwi` are tabled
//! over `cos_o` and roughness once (plain arithmetic and `libm`: the same bits on every machine),
//! so that the albedo of a Schlick lobe of any `f0` is `f0 (E - S) + S`.

use super::microfacet::{Distribution, Microfacet};
use crate::math::reflect;
use glam::Vec3;
use std::sync::OnceLock;

/// Table entries: `cos_o` and roughness (`sqrt(alpha)`), each evenly spaced over [0, 1].
const COSINES: usize = 32;
const ROUGHNESSES: usize = 32;
/// Visible normals drawn per entry, on a stratified grid of `STRATA` x `STRATA`.
const STRATA: usize = 48;

/// The tables: per roughness row, `E` and `S` at each cosine, and their cosine-weighted means.
struct Tables {
    e: Vec<f32>,
    s: Vec<f32>,
    e_avg: Vec<f32>,
    s_avg: Vec<f32>,
}

/// `E` and `S` by importance sampling visible normals on a stratified grid (the estimator of
/// `E` is `G2 / G1(wo)`, at most 1 and smooth, so 2,304 normals give it to about 1e-4). Rows of
/// roughness are computed in parallel, each entry as one thread alone would: the same bits.
fn tables() -> &'static Tables {
    static TABLES: OnceLock<Tables> = OnceLock::new();
    TABLES.get_or_init(|| {
        let rows = crate::math::rows_in_parallel(ROUGHNESSES, table_row);
        let mut t = Tables {
            e: Vec::with_capacity(COSINES * ROUGHNESSES),
            s: Vec::with_capacity(COSINES * ROUGHNESSES),
            e_avg: Vec::with_capacity(ROUGHNESSES),
            s_avg: Vec::with_capacity(ROUGHNESSES),
        };
        // 2 int_0^1 f(mu) mu dmu by the trapezoidal rule over the table's cosines.
        let mean = |row: &[f32]| -> f32 {
            let h = 1.0 / (COSINES - 1) as f64;
            let sum: f64 = (0..COSINES - 1)
                .map(|i| {
                    let (m0, m1) = (i as f64 * h, (i + 1) as f64 * h);
                    0.5 * h * (row[i] as f64 * m0 + row[i + 1] as f64 * m1)
                })
                .sum();
            (2.0 * sum) as f32
        };
        for (e, s) in rows {
            t.e_avg.push(mean(&e));
            t.s_avg.push(mean(&s));
            t.e.extend(e);
            t.s.extend(s);
        }
        t
    })
}

/// Row `j` (roughness `j / (ROUGHNESSES - 1)`) of `E` and `S`, one entry per cosine.
fn table_row(j: usize) -> (Vec<f32>, Vec<f32>) {
    let roughness = j as f32 / (ROUGHNESSES - 1) as f32;
    let m = Microfacet::new(Distribution::Ggx, (roughness * roughness).max(1e-4));
    (0..COSINES)
        .map(|i| {
            let cos_o = (i as f32 / (COSINES - 1) as f32).max(1e-3);
            let wo = Vec3::new((1.0 - cos_o * cos_o).max(0.0).sqrt(), 0.0, cos_o);
            let (mut e, mut s) = (0.0f64, 0.0f64);
            for a in 0..STRATA {
                for b in 0..STRATA {
                    let u = [(a as f32 + 0.5) / STRATA as f32, (b as f32 + 0.5) / STRATA as f32];
                    let h = m.sample_h(wo, u);
                    let wi = reflect(wo, h);
                    if wi.z <= 0.0 {
                        continue;
                    }
                    let w = (m.g2(wo, wi) / m.g1(wo)) as f64;
                    e += w;
                    s += w * ((1.0 - wo.dot(h).clamp(0.0, 1.0)) as f64).powi(5);
                }
            }
            let n = (STRATA * STRATA) as f64;
            ((e / n) as f32, (s / n) as f32)
        })
        .unzip()
}

/// Computes the tables now rather than in the first sample that needs them, where the other
/// render threads would wait on it.
pub fn prepare() {
    tables();
}

/// `E`, `S` of the GGX lobe of `alpha` at `cos`, and its `E_avg`, `S_avg`: bilinear in the
/// tables (anisotropic lobes use the geometric mean of their two roughnesses).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Albedo {
    pub e: f32,
    pub s: f32,
    pub e_avg: f32,
    pub s_avg: f32,
}

impl Albedo {
    pub fn of(m: &Microfacet, cos: f32) -> Self {
        let t = tables();
        let roughness = (m.alpha * m.alpha_across).sqrt().sqrt().clamp(0.0, 1.0);
        let x = cos.clamp(0.0, 1.0) * (COSINES - 1) as f32;
        let y = roughness * (ROUGHNESSES - 1) as f32;
        let (i, j) = ((x as usize).min(COSINES - 2), (y as usize).min(ROUGHNESSES - 2));
        let (fx, fy) = (x - i as f32, y - j as f32);
        let lerp = |a: f32, b: f32, f: f32| a + (b - a) * f;
        let at = |table: &[f32]| {
            let row = |j: usize| lerp(table[j * COSINES + i], table[j * COSINES + i + 1], fx);
            lerp(row(j), row(j + 1), fy)
        };
        Albedo {
            e: at(&t.e),
            s: at(&t.s),
            e_avg: lerp(t.e_avg[j], t.e_avg[j + 1], fy),
            s_avg: lerp(t.s_avg[j], t.s_avg[j + 1], fy),
        }
    }
}

/// Kulla and Conty's `F_ms` for a Fresnel of average `f_avg` over a lobe of mean albedo `e_avg`.
pub fn multiple_scattering_share(f_avg: f32, e_avg: f32) -> f32 {
    let d = 1.0 - f_avg * (1.0 - e_avg);
    if d <= 0.0 { 0.0 } else { f_avg * f_avg * e_avg / d }
}

/// The average over the hemisphere (cosine-weighted) of Schlick's Fresnel with `f90 = 1`.
pub fn schlick_average(f0: f32) -> f32 {
    f0 + (1.0 - f0) / 21.0
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The directional albedo of `F D G2 / (4 cos_o cos_i)` by the midpoint rule over the
    /// hemisphere, with `fresnel(wo.h)`: independent of the tables' visible-normal estimator.
    fn quadrature(m: &Microfacet, cos_o: f32, fresnel: impl Fn(f32) -> f32) -> f64 {
        let wo = Vec3::new((1.0 - cos_o * cos_o).sqrt(), 0.0, cos_o);
        let (nz, nphi) = (400, 400);
        let mut sum = 0.0f64;
        for a in 0..nz {
            let z = (a as f32 + 0.5) / nz as f32;
            let r = (1.0 - z * z).sqrt();
            for b in 0..nphi {
                let (s, c) = libm::sincosf(2.0 * std::f32::consts::PI * (b as f32 + 0.5) / nphi as f32);
                let wi = Vec3::new(r * c, r * s, z);
                let h = (wo + wi).normalize();
                let f = fresnel(wo.dot(h)) * m.d(h) * m.g2(wo, wi) / (4.0 * wo.z * wi.z);
                sum += (f * z) as f64;
            }
        }
        sum * 2.0 * std::f64::consts::PI / (nz * nphi) as f64
    }

    #[test]
    fn the_tables_match_quadrature() {
        for roughness in [0.3f32, 0.6, 1.0] {
            let m = Microfacet::new(Distribution::Ggx, roughness * roughness);
            for cos in [0.2f32, 0.5, 0.9] {
                let a = Albedo::of(&m, cos);
                let e = quadrature(&m, cos, |_| 1.0);
                let s = quadrature(&m, cos, |c| (1.0 - c).powi(5));
                assert!((a.e as f64 - e).abs() < 4e-3, "E at roughness {roughness}, cos {cos}: {} against {e}", a.e);
                assert!((a.s as f64 - s).abs() < 2e-3, "S at roughness {roughness}, cos {cos}: {} against {s}", a.s);
            }
        }
    }

    #[test]
    fn a_rough_lobe_loses_energy_a_smooth_one_does_not() {
        let smooth = Albedo::of(&Microfacet::new(Distribution::Ggx, 1e-4), 0.7);
        assert!(smooth.e > 0.999 && smooth.e_avg > 0.99, "{smooth:?}");
        let rough = Albedo::of(&Microfacet::new(Distribution::Ggx, 1.0), 0.7);
        assert!(rough.e < 0.8 && rough.e_avg < 0.8, "{rough:?}");
        assert_eq!(multiple_scattering_share(1.0, rough.e_avg), 1.0);
    }
}
