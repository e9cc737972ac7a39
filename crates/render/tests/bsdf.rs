//! Statistical and analytic tests of the BSDFs through their public sample / eval / pdf.
//! Fixed seeds; the chi-square tests use a 1% significance level, Sidak-corrected for the
//! number of configurations tested.

// Reference values may use the platform's functions: they check the BSDFs, not bits.
#![allow(clippy::disallowed_methods)]

use glam::Vec3;
use std::f64::consts::PI;
use tessera_render::bsdf::fresnel;
use tessera_render::bsdf::{Bsdf, Coat, Distribution, Fresnel, Microfacet, Refraction, Sheen, refract};
use tessera_render::mix64;

/// A deterministic stream of uniforms for the tests.
struct Rng(u64);
impl Rng {
    fn next(&mut self) -> f32 {
        self.0 = self.0.wrapping_add(1);
        (mix64(self.0) >> 40) as f32 / (1u64 << 24) as f32
    }
}

fn dir_from_angle(theta_deg: f32) -> Vec3 {
    let t = theta_deg.to_radians();
    Vec3::new(t.sin(), 0.0, t.cos())
}

/// Adaptive Simpson quadrature of `f` on `[a, b]`.
fn simpson(f: &dyn Fn(f64) -> f64, a: f64, b: f64, tol: f64) -> f64 {
    /// `seg` is `[a, b, f(a), f(midpoint), f(b)]`.
    fn rec(f: &dyn Fn(f64) -> f64, seg: [f64; 5], whole: f64, tol: f64, depth: u32) -> f64 {
        let [a, b, fa, fm, fb] = seg;
        let m = 0.5 * (a + b);
        let (lm, rm) = (0.5 * (a + m), 0.5 * (m + b));
        let (flm, frm) = (f(lm), f(rm));
        let left = (m - a) / 6.0 * (fa + 4.0 * flm + fm);
        let right = (b - m) / 6.0 * (fm + 4.0 * frm + fb);
        if depth == 0 || (left + right - whole).abs() <= 15.0 * tol {
            return left + right + (left + right - whole) / 15.0;
        }
        rec(f, [a, m, fa, flm, fm], left, tol / 2.0, depth - 1)
            + rec(f, [m, b, fm, frm, fb], right, tol / 2.0, depth - 1)
    }
    let (fa, fb, fm) = (f(a), f(b), f(0.5 * (a + b)));
    let whole = (b - a) / 6.0 * (fa + 4.0 * fm + fb);
    rec(f, [a, b, fa, fm, fb], whole, tol, 18)
}

/// Integral of `f(direction)` over the cell `z in [z0, z1], phi in [p0, p1]` (dw = dz dphi).
fn integrate_cell(f: &dyn Fn(Vec3) -> f64, z0: f64, z1: f64, p0: f64, p1: f64, tol: f64) -> f64 {
    let outer = |z: f64| {
        let r = (1.0 - z * z).max(0.0).sqrt();
        let inner = |phi: f64| f(Vec3::new((r * phi.cos()) as f32, (r * phi.sin()) as f32, z as f32));
        simpson(&inner, p0, p1, tol)
    };
    simpson(&outer, z0, z1, tol)
}

/// Regularised lower incomplete gamma P(a, x) (series and continued fraction, Numerical Recipes).
fn gamma_p(a: f64, x: f64) -> f64 {
    fn ln_gamma(x: f64) -> f64 {
        let c = [
            76.18009172947146,
            -86.50532032941677,
            24.01409824083091,
            -1.231739572450155,
            0.1208650973866179e-2,
            -0.5395239384953e-5,
        ];
        let mut y = x;
        let tmp = x + 5.5 - (x + 0.5) * (x + 5.5).ln();
        let mut ser = 1.000000000190015;
        for c in c {
            y += 1.0;
            ser += c / y;
        }
        -tmp + (2.5066282746310005 * ser / x).ln()
    }
    if x <= 0.0 {
        return 0.0;
    }
    if x < a + 1.0 {
        let (mut sum, mut del, mut ap) = (1.0 / a, 1.0 / a, a);
        for _ in 0..1000 {
            ap += 1.0;
            del *= x / ap;
            sum += del;
            if del.abs() < sum.abs() * 1e-14 {
                break;
            }
        }
        sum * (-x + a * x.ln() - ln_gamma(a)).exp()
    } else {
        let mut b = x + 1.0 - a;
        let (mut c, mut d) = (1e300, 1.0 / b);
        let mut h = d;
        for i in 1..1000 {
            let an = -(i as f64) * (i as f64 - a);
            b += 2.0;
            d = an * d + b;
            if d.abs() < 1e-300 {
                d = 1e-300;
            }
            c = b + an / c;
            if c.abs() < 1e-300 {
                c = 1e-300;
            }
            d = 1.0 / d;
            let del = d * c;
            h *= del;
            if (del - 1.0).abs() < 1e-14 {
                break;
            }
        }
        1.0 - (-x + a * x.ln() - ln_gamma(a)).exp() * h
    }
}

/// Chi-square goodness of fit of `bsdf.sample` against `bsdf.pdf` for outgoing direction `wo`,
/// over the hemisphere above the surface, or the whole sphere for a BSDF that transmits.
/// Returns the p-value.
fn chi_square_p_value(bsdf: &Bsdf, wo: Vec3, seed: u64) -> f64 {
    const PHI_BINS: usize = 20;
    const SAMPLES: usize = 200_000;
    // Bins in (z = cos theta, phi), ten per unit of z, plus one for failed samples.
    let (z_low, z_bins) = if bsdf.transmits() { (-1.0f32, 20) } else { (0.0, 10) };
    let bin_of = |w: Vec3| -> usize {
        let zi = (((w.z.clamp(z_low, 1.0) - z_low) * 10.0) as usize).min(z_bins - 1);
        let phi = (w.y.atan2(w.x) as f64).rem_euclid(2.0 * PI);
        let pi = ((phi / (2.0 * PI) * PHI_BINS as f64) as usize).min(PHI_BINS - 1);
        zi * PHI_BINS + pi
    };
    let mut observed = vec![0.0f64; z_bins * PHI_BINS + 1];
    let mut rng = Rng(seed);
    for _ in 0..SAMPLES {
        match bsdf.sample(wo, rng.next(), [rng.next(), rng.next()]) {
            Some(s) if !s.delta && (s.wi.z > 0.0 || bsdf.transmits() && s.wi.z < 0.0) => observed[bin_of(s.wi)] += 1.0,
            _ => observed[z_bins * PHI_BINS] += 1.0,
        }
    }
    let mut expected = vec![0.0f64; z_bins * PHI_BINS + 1];
    let pdf = |w: Vec3| bsdf.pdf(wo, w) as f64;
    for zi in 0..z_bins {
        for pi in 0..PHI_BINS {
            let (z0, z1) = (z_low as f64 + zi as f64 / 10.0, z_low as f64 + (zi + 1) as f64 / 10.0);
            let (p0, p1) = (2.0 * PI * pi as f64 / PHI_BINS as f64, 2.0 * PI * (pi + 1) as f64 / PHI_BINS as f64);
            expected[zi * PHI_BINS + pi] = SAMPLES as f64 * integrate_cell(&pdf, z0, z1, p0, p1, 1e-6);
        }
    }
    let total: f64 = expected.iter().sum();
    expected[z_bins * PHI_BINS] = (SAMPLES as f64 - total).max(0.0);
    // Pool cells with small expectations (ascending), the usual rule of at least 5.
    let mut cells: Vec<(f64, f64)> = expected.into_iter().zip(observed).collect();
    cells.sort_by(|a, b| a.0.total_cmp(&b.0));
    let (mut chi2, mut dof, mut pool) = (0.0, 0usize, (0.0, 0.0));
    for (e, o) in cells {
        if e < 5.0 {
            pool = (pool.0 + e, pool.1 + o);
            if pool.0 < 5.0 {
                continue;
            }
            let (pe, po) = std::mem::take(&mut pool);
            chi2 += (po - pe) * (po - pe) / pe;
        } else {
            chi2 += (o - e) * (o - e) / e;
        }
        dof += 1;
    }
    if pool.1 > 0.0 && pool.0 == 0.0 {
        return 0.0; // samples where the pdf says there can be none
    }
    1.0 - gamma_p((dof as f64 - 1.0) / 2.0, chi2 / 2.0)
}

fn gltf(base: f32, metallic: f32, roughness: f32) -> Bsdf {
    Bsdf::gltf(Vec3::splat(base), metallic, roughness, 1.0, Vec3::ONE, 0.04)
}

/// The glTF BSDF with KHR_materials_transmission's thin-walled BTDF taking `transmission` of its
/// diffuse layer.
fn thin(base: f32, metallic: f32, roughness: f32, transmission: f32) -> Bsdf {
    gltf(base, metallic, roughness).with_transmission(transmission)
}

/// The glTF BSDF under KHR_materials_clearcoat's layer.
fn coated(base: f32, metallic: f32, roughness: f32, coat: f32, coat_roughness: f32) -> Bsdf {
    gltf(base, metallic, roughness).with_coat(coat, coat_roughness)
}

/// A coat whose normal is tilted by `degrees` from the base's (a normal map under a smooth coat).
fn tilted(b: Bsdf, degrees: f32) -> Bsdf {
    b.with_coat_normal(dir_from_angle(degrees))
}

/// The glTF BSDF under KHR_materials_sheen's layer of grey `sheen`.
fn sheened(base: f32, roughness: f32, sheen: f32, sheen_roughness: f32) -> Bsdf {
    gltf(base, 0.0, roughness).with_sheen(Vec3::splat(sheen), sheen_roughness)
}

/// A solid dielectric of index `ior` met from outside (KHR_materials_volume), white, all of what
/// it does not reflect refracting.
fn glass(roughness: f32, ior: f32) -> Bsdf {
    Bsdf::solid_dielectric(Vec3::ONE, roughness, ior, 1.0)
}

/// The glTF BSDF with KHR_materials_anisotropy of `strength`, rough along the local direction at
/// `degrees` from +x.
fn brushed(base: f32, metallic: f32, roughness: f32, strength: f32, degrees: f32) -> Bsdf {
    let (sin, cos) = libm::sincosf(degrees.to_radians());
    gltf(base, metallic, roughness).with_anisotropy(strength).with_anisotropy_direction(Vec3::new(cos, sin, 0.0))
}

/// `w` mirrored through the surface.
fn through(w: Vec3) -> Vec3 {
    Vec3::new(w.x, w.y, -w.z)
}

#[test]
fn sampling_matches_pdf_chi_square() {
    let mut cases: Vec<(String, Bsdf, Vec3)> = Vec::new();
    let lambert = Bsdf {
        diffuse: Vec3::splat(0.8),
        fresnel: Fresnel::Dielectric { eta: 1.0 },
        microfacet: Microfacet::new(Distribution::Ggx, 1.0),
        coat: Coat::NONE,
        sheen: Sheen::NONE,
        refraction: Refraction::NONE,
        compensated: false,
    };
    cases.push(("lambert 30deg".into(), lambert, dir_from_angle(30.0)));
    for alpha in [0.05f32, 0.2, 0.5, 1.0] {
        for theta in [0.0f32, 45.0, 85.0] {
            for metallic in [0.0f32, 0.5, 1.0] {
                let roughness = alpha.sqrt();
                cases.push((
                    format!("ggx alpha {alpha} metallic {metallic} at {theta} deg"),
                    gltf(0.7, metallic, roughness),
                    dir_from_angle(theta),
                ));
            }
        }
    }
    for alpha in [0.05f32, 0.2, 0.5, 1.0] {
        for theta in [0.0f32, 45.0, 85.0] {
            for (metallic, transmission) in [(0.0f32, 1.0f32), (0.5, 0.8)] {
                cases.push((
                    format!("thin transmission {transmission} alpha {alpha} metallic {metallic} at {theta} deg"),
                    thin(0.7, metallic, alpha.sqrt(), transmission),
                    dir_from_angle(theta),
                ));
            }
        }
    }
    for (coat_roughness, roughness, metallic) in
        [(0.3f32, 0.6f32, 0.0f32), (0.5, 0.3, 1.0), (0.0, 0.8, 0.0), (0.4, 0.0, 0.0)]
    {
        for theta in [0.0f32, 45.0, 85.0] {
            cases.push((
                format!(
                    "coat roughness {coat_roughness} over roughness {roughness} metallic {metallic} at {theta} deg"
                ),
                coated(0.7, metallic, roughness, 0.8, coat_roughness),
                dir_from_angle(theta),
            ));
        }
    }
    for (coat_roughness, tilt) in [(0.4f32, 30.0f32), (0.7, 60.0)] {
        for theta in [0.0f32, 45.0, 85.0] {
            cases.push((
                format!("coat roughness {coat_roughness} tilted {tilt} deg at {theta} deg"),
                tilted(coated(0.6, 0.0, 0.5, 1.0, coat_roughness), tilt),
                dir_from_angle(theta),
            ));
        }
    }
    for (sheen_roughness, base) in [(0.3f32, 0.5f32), (0.8, 0.0), (1.0, 0.9)] {
        for theta in [0.0f32, 60.0, 85.0] {
            cases.push((
                format!("sheen roughness {sheen_roughness} over base {base} at {theta} deg"),
                sheened(base, 0.5, 1.0, sheen_roughness),
                dir_from_angle(theta),
            ));
        }
    }
    for (roughness, strength, degrees) in [(0.3f32, 0.5f32, 30.0f32), (0.1, 0.9, -60.0), (0.6, 1.0, 90.0)] {
        for theta in [0.0f32, 45.0, 85.0] {
            for metallic in [0.0f32, 1.0] {
                cases.push((
                    format!("anisotropy {strength} at {degrees} deg, roughness {roughness}, metallic {metallic}, at {theta} deg"),
                    brushed(0.7, metallic, roughness, strength, degrees),
                    dir_from_angle(theta),
                ));
            }
        }
    }
    for alpha in [0.05f32, 0.2, 0.6] {
        for theta in [0.0f32, 45.0, 85.0] {
            for (side, b) in [("outside", glass(alpha.sqrt(), 1.5)), ("inside", glass(alpha.sqrt(), 1.5).from_inside())]
            {
                cases.push((format!("glass alpha {alpha} from {side} at {theta} deg"), b, dir_from_angle(theta)));
            }
        }
    }
    cases.push((
        "half-diffuse glass alpha 0.3 at 30 deg".into(),
        Bsdf::solid_dielectric(Vec3::splat(0.8), 0.55, 1.33, 0.5),
        dir_from_angle(30.0),
    ));
    for alpha in [0.1f32, 0.5] {
        let b = Bsdf {
            diffuse: Vec3::ZERO,
            fresnel: Fresnel::Conductor { eta: Vec3::splat(0.2), k: Vec3::splat(3.0) },
            microfacet: Microfacet::new(Distribution::Beckmann, alpha),
            coat: Coat::NONE,
            sheen: Sheen::NONE,
            refraction: Refraction::NONE,
            compensated: false,
        };
        cases.push((format!("beckmann conductor alpha {alpha} at 60 deg"), b, dir_from_angle(60.0)));
    }
    // 1% overall, Sidak-corrected.
    let threshold = 1.0 - (1.0 - 0.01f64).powf(1.0 / cases.len() as f64);
    use rayon::prelude::*;
    let failures: Vec<String> = cases
        .par_iter()
        .enumerate()
        .filter_map(|(i, (name, bsdf, wo))| {
            let p = chi_square_p_value(bsdf, *wo, 1000 + i as u64 * 7919);
            (p < threshold).then(|| format!("{name}: p = {p:.2e}"))
        })
        .collect();
    assert!(failures.is_empty(), "rejected at p < {threshold:.2e}: {failures:#?}");
}

#[test]
fn sample_eval_and_pdf_agree() {
    let mut rng = Rng(5);
    let models = [(0.0, 0.3, 0.0), (0.5, 0.6, 0.0), (1.0, 0.1, 0.0), (0.0, 1.0, 0.0), (0.0, 0.3, 1.0), (0.3, 0.6, 0.5)];
    for (i, (metallic, roughness, transmission)) in models.into_iter().enumerate() {
        // Every other model under a clear coat (a smooth one, then rough ones), every third
        // under sheen.
        let b = thin(0.6, metallic, roughness, transmission)
            .with_coat((i % 2) as f32, 0.2 * (i / 2) as f32)
            .with_sheen(Vec3::splat((i % 3 == 0) as u32 as f32 * 0.7), 0.5)
            .with_coat_normal(dir_from_angle(10.0 * i as f32));
        for theta in [5.0f32, 40.0, 80.0] {
            let wo = dir_from_angle(theta);
            for _ in 0..2000 {
                let Some(s) = b.sample(wo, rng.next(), [rng.next(), rng.next()]).filter(|s| !s.delta) else {
                    continue; // a mirror lobe's direction has no density
                };
                let pdf = b.pdf(wo, s.wi);
                assert!((pdf - s.pdf).abs() <= 1e-3 * pdf.max(1e-3), "pdf {pdf} vs sampled {}", s.pdf);
                let expect = b.eval(wo, s.wi) * s.wi.z.abs() / pdf;
                assert!((expect - s.weight).abs().max_element() <= 1e-3 * expect.max_element().max(1e-3));
            }
        }
    }
}

#[test]
fn brdfs_are_reciprocal() {
    let mut rng = Rng(11);
    let models = [
        gltf(0.8, 0.0, 0.4),
        gltf(0.8, 1.0, 0.2),
        gltf(0.3, 0.5, 0.9),
        coated(0.8, 0.0, 0.5, 1.0, 0.2),
        coated(0.5, 1.0, 0.3, 0.6, 0.7),
        sheened(0.6, 0.4, 0.8, 0.5),
        sheened(0.2, 0.9, 1.0, 0.1).with_coat(0.5, 0.3),
        brushed(0.8, 0.0, 0.3, 0.8, 25.0),
        brushed(0.5, 1.0, 0.2, 1.0, 100.0),
        Bsdf {
            diffuse: Vec3::splat(0.5),
            fresnel: Fresnel::Dielectric { eta: 1.5 },
            microfacet: Microfacet::new(Distribution::Beckmann, 0.3),
            coat: Coat::NONE,
            sheen: Sheen::NONE,
            refraction: Refraction::NONE,
            compensated: false,
        },
        Bsdf {
            diffuse: Vec3::ZERO,
            fresnel: Fresnel::Conductor { eta: Vec3::new(0.2, 0.4, 1.4), k: Vec3::new(3.4, 2.4, 1.8) },
            microfacet: Microfacet::new(Distribution::Ggx, 0.3),
            coat: Coat::NONE,
            sheen: Sheen::NONE,
            refraction: Refraction::NONE,
            compensated: false,
        },
    ];
    for b in models {
        for _ in 0..1000 {
            let a = tessera_render::sample_uniform_hemisphere([rng.next(), rng.next()]);
            let c = tessera_render::sample_uniform_hemisphere([rng.next(), rng.next()]);
            let (f1, f2) = (b.eval(a, c), b.eval(c, a));
            assert!((f1 - f2).abs().max_element() <= 1e-4 * f1.max_element().max(1e-2), "{f1} vs {f2}");
        }
    }
}

/// Through a thin wall, light going the other way meets the surface from its other side, where
/// the shading frame turns over: `f(wo, wi) = f(through(wi), through(wo))` for `wi` below.
/// Reflection on either side stays reciprocal, and a mirror's smooth BTDF is zero (its
/// transmission is a delta lobe).
#[test]
fn thin_transmission_is_reciprocal() {
    let mut rng = Rng(13);
    let mut nonzero = 0;
    for (metallic, roughness, transmission) in [(0.0, 0.4, 1.0), (0.0, 0.8, 0.5), (0.4, 0.2, 0.7)] {
        let b = thin(0.8, metallic, roughness, transmission);
        for _ in 0..1000 {
            let a = tessera_render::sample_uniform_hemisphere([rng.next(), rng.next()]);
            let c = through(tessera_render::sample_uniform_hemisphere([rng.next(), rng.next()]));
            let (f1, f2) = (b.eval(a, c), b.eval(through(c), through(a)));
            assert!((f1 - f2).abs().max_element() <= 1e-4 * f1.max_element().max(1e-2), "{f1} vs {f2}");
            nonzero += (f1.max_element() > 0.0) as u32;
            let (r1, r2) = (b.eval(a, through(c)), b.eval(through(c), a));
            assert!((r1 - r2).abs().max_element() <= 1e-4 * r1.max_element().max(1e-2), "{r1} vs {r2}");
        }
    }
    assert!(nonzero > 2500, "the BTDF is non-zero below the surface ({nonzero} of 3000)");
    let a = dir_from_angle(30.0);
    assert_eq!(thin(0.8, 0.0, 0.0, 1.0).eval(a, through(a)), Vec3::ZERO);
    assert_eq!(gltf(0.8, 0.0, 0.4).eval(a, -a), Vec3::ZERO, "without transmission nothing passes");
}

/// Refraction is reciprocal up to the squared indices (Veach 1997, 5.2): light refracting from
/// outside (index 1) to inside (1.5) and back meet `f(wo, wi) / n_o^2 = f(wi, wo) / n_i^2`, the
/// inside seen in its own frame (turned over). Reflection stays symmetric on either side.
#[test]
fn refraction_is_reciprocal_up_to_the_squared_indices() {
    let mut rng = Rng(17);
    let mut nonzero = 0;
    for roughness in [0.3f32, 0.6, 0.9] {
        let (outside, inside) = (glass(roughness, 1.5), glass(roughness, 1.5).from_inside());
        for _ in 0..1000 {
            let a = tessera_render::sample_uniform_hemisphere([rng.next(), rng.next()]);
            let c = through(tessera_render::sample_uniform_hemisphere([rng.next(), rng.next()]));
            // Where the half vector a + 1.5 c lies almost in the surface its height cancels, and
            // where `a` grazes the microfacet the inside meets it near the critical angle, whose
            // cosine cancels: f32 rounding alone parts the two sides there.
            let h = (a + 1.5 * c).normalize();
            if h.z.abs() < 0.05 || a.dot(h).abs() < 0.05 {
                continue;
            }
            let (f1, f2) = (outside.eval(a, c), inside.eval(through(c), through(a)));
            assert!(
                (f1 * 2.25 - f2).abs().max_element() <= 1e-3 * f2.max_element().max(1e-3),
                "{f1} vs {f2} at {a}, {c}, roughness {roughness}"
            );
            nonzero += (f1.max_element() > 0.0) as u32;
            for b in [outside, inside] {
                let (r1, r2) = (b.eval(a, through(c)), b.eval(through(c), a));
                assert!((r1 - r2).abs().max_element() <= 1e-4 * r1.max_element().max(1e-2), "{r1} vs {r2}");
            }
        }
    }
    assert!(nonzero > 300, "the BTDF is non-zero below the surface ({nonzero} of 3000)");
}

/// Energy through a dielectric: radiance refracting into an index `eta` times higher is
/// `eta^2` denser, so `R + eta^2 T` is what the interface keeps. A smooth one keeps all of it,
/// sample by sample (Fresnel splits, total internal reflection returns the rest), from either
/// side; a rough one keeps at most all and, at moderate roughness, most. Samples' weights are
/// `f cos / pdf` of `eval` and `pdf`.
#[test]
fn dielectrics_split_energy_by_fresnel_and_never_gain() {
    let energy = |b: &Bsdf, eta: f32, wo: Vec3, n: usize, seed: u64| {
        let mut rng = Rng(seed);
        let (mut s, mut s2) = (0.0f64, 0.0f64);
        for _ in 0..n {
            let w = match b.sample(wo, rng.next(), [rng.next(), rng.next()]) {
                Some(x) => {
                    if !x.delta {
                        let expected = b.eval(wo, x.wi) * x.wi.z.abs() / b.pdf(wo, x.wi);
                        assert!((x.weight - expected).abs().max_element() <= 1e-4 * expected.max_element().max(1.0));
                    }
                    (x.weight.x * if x.wi.z < 0.0 { eta * eta } else { 1.0 }) as f64
                }
                None => 0.0,
            };
            s += w;
            s2 += w * w;
        }
        let mean = s / n as f64;
        (mean, ((s2 / n as f64 - mean * mean).max(0.0) / n as f64).sqrt())
    };
    for theta in [0.0f32, 30.0, 60.0, 85.0] {
        let wo = dir_from_angle(theta);
        for (side, eta) in [("outside", 1.5f32), ("inside", 1.0 / 1.5)] {
            let smooth = if eta > 1.0 { glass(0.0, 1.5) } else { glass(0.0, 1.5).from_inside() };
            let (e, se) = energy(&smooth, eta, wo, 2000, 3);
            assert!((e - 1.0).abs() < 1e-4 && se < 1e-4, "smooth from {side} at {theta}: {e} +- {se}");
            for roughness in [0.3f32, 0.7] {
                let b = if eta > 1.0 { glass(roughness, 1.5) } else { glass(roughness, 1.5).from_inside() };
                let (e, se) = energy(&b, eta, wo, 40_000, 5);
                assert!(e <= 1.0 + 3.0 * se, "roughness {roughness} from {side} at {theta}: {e} +- {se}");
                if roughness < 0.5 && theta < 80.0 {
                    assert!(e > 0.9, "roughness {roughness} from {side} at {theta} keeps only {e}");
                }
            }
        }
    }
}

#[test]
fn refraction_follows_snell_and_reflects_totally_past_the_critical_angle() {
    for theta in [0.0f32, 20.0, 40.0, 60.0, 80.0] {
        let wo = dir_from_angle(theta);
        let wi = refract(wo, Vec3::Z, 1.5).unwrap();
        let (sin_o, sin_i) = ((1.0 - wo.z * wo.z).sqrt(), (1.0 - wi.z * wi.z).sqrt());
        assert!((sin_o - 1.5 * sin_i).abs() < 1e-5 && wi.z < 0.0 && wi.x * wo.x <= 0.0, "{theta}: {wi}");
        // Back out, seen from inside (the frame turned over): the same angle.
        let back = refract(through(wi), Vec3::Z, 1.0 / 1.5);
        assert!(back.is_some_and(|b| (b - through(wo)).length() < 1e-4), "{theta}: {back:?}");
    }
    // Inside glass the critical angle is asin(1 / 1.5) = 41.8 degrees.
    assert!(refract(dir_from_angle(41.0), Vec3::Z, 1.0 / 1.5).is_some());
    assert!(refract(dir_from_angle(42.5), Vec3::Z, 1.0 / 1.5).is_none());
    assert_eq!(fresnel::dielectric(dir_from_angle(42.5).z, 1.0 / 1.5), 1.0);
}

#[test]
fn d_is_normalised() {
    for distribution in [Distribution::Ggx, Distribution::Beckmann] {
        for alpha in [0.05f32, 0.2, 0.5, 1.0] {
            let m = Microfacet::new(distribution, alpha);
            // int D(h) cos(theta_h) dw = 2 pi int_0^1 D(z) z dz for isotropic D.
            let f = |z: f64| m.d(Vec3::new((1.0 - z * z).max(0.0).sqrt() as f32, 0.0, z as f32)) as f64 * z;
            let integral = 2.0 * PI * simpson(&f, 0.0, 1.0, 1e-9);
            assert!((integral - 1.0).abs() < 2e-3, "{distribution:?} alpha {alpha}: {integral}");
        }
    }
}

/// KHR_materials_anisotropy's GGX: `D` integrates to 1 over projected area however stretched
/// and turned, is wider along its rough direction than across it, and passes the weak white
/// furnace `int G1(wo) max(0, wo.h) D(h) dh = cos(theta_o)` from every azimuth.
#[test]
fn anisotropic_ggx_is_normalised_stretched_and_passes_the_weak_white_furnace() {
    for (along, across, degrees) in [(0.5f32, 0.15f32, 0.0f32), (0.9, 0.25, 35.0), (0.4, 0.12, 120.0)] {
        let (sin, cos) = libm::sincosf(degrees.to_radians());
        let m = Microfacet::anisotropic(along, across, (cos, sin));
        let integral = integrate_cell(&|h: Vec3| (m.d(h) * h.z) as f64, 0.0, 1.0, 0.0, 2.0 * PI, 1e-5);
        assert!((integral - 1.0).abs() < 5e-3, "{along}/{across} at {degrees}: {integral}");
        // Tilted 30 degrees along the rough direction, and across it.
        let tilt = |azimuth: f32| {
            let (s, c) = libm::sincosf(azimuth);
            Vec3::new(0.5 * c, 0.5 * s, 0.75f32.sqrt())
        };
        let angle = degrees.to_radians();
        assert!(m.d(tilt(angle)) > 2.0 * m.d(tilt(angle + std::f32::consts::FRAC_PI_2)), "{along}/{across}");
        for (theta, phi) in [(30.0f32, 0.0f32), (60.0, 50.0), (75.0, 130.0)] {
            let (st, ct) = libm::sincosf(theta.to_radians());
            let (sp, cp) = libm::sincosf(phi.to_radians());
            let wo = Vec3::new(st * cp, st * sp, ct);
            let f = |h: Vec3| (m.g1(wo) * wo.dot(h).max(0.0) * m.d(h)) as f64;
            let furnace = integrate_cell(&f, 0.0, 1.0, 0.0, 2.0 * PI, 1e-5) / wo.z as f64;
            assert!((furnace - 1.0).abs() < 5e-3, "{along}/{across} at {degrees}, wo {theta}/{phi}: {furnace}");
        }
    }
}

#[test]
fn g1_passes_the_weak_white_furnace() {
    // int G1(wo) max(0, wo.h) D(h) dh = cos(theta_o) (Heitz 2014) for GGX, whose Lambda is exact.
    for alpha in [0.2f32, 0.5, 1.0] {
        let m = Microfacet::new(Distribution::Ggx, alpha);
        for theta in [0.0f32, 30.0, 60.0, 80.0] {
            let wo = dir_from_angle(theta);
            let f = |h: Vec3| (m.g1(wo) * wo.dot(h).max(0.0) * m.d(h)) as f64;
            let integral = integrate_cell(&f, 0.0, 1.0, 0.0, 2.0 * PI, 1e-6);
            assert!(
                (integral / wo.z as f64 - 1.0).abs() < 5e-3,
                "alpha {alpha} theta {theta}: {}",
                integral / wo.z as f64
            );
        }
    }
}

/// Directional albedo `int f cos dwi` by importance sampling, with its standard error.
fn albedo(b: &Bsdf, wo: Vec3, n: usize, seed: u64) -> (f64, f64) {
    let mut rng = Rng(seed);
    let (mut s, mut s2) = (0.0f64, 0.0f64);
    for _ in 0..n {
        let w = b.sample(wo, rng.next(), [rng.next(), rng.next()]).map_or(0.0, |s| s.weight.max_element() as f64);
        s += w;
        s2 += w * w;
    }
    let mean = s / n as f64;
    (mean, ((s2 / n as f64 - mean * mean).max(0.0) / n as f64).sqrt())
}

#[test]
fn gltf_albedo_never_exceeds_one() {
    for metallic in [0.0f32, 0.5, 1.0] {
        for roughness in [0.0f32, 0.1, 0.3, 0.6, 1.0] {
            for theta in [0.0f32, 45.0, 75.0, 89.0] {
                let (a, se) = albedo(&brushed(1.0, metallic, roughness, 0.7, 20.0), dir_from_angle(theta), 20_000, 4);
                assert!(
                    a <= 1.0 + 3.0 * se + 1e-6,
                    "anisotropic, metallic {metallic} roughness {roughness} theta {theta}: {a}"
                );
                let (a, se) = albedo(&gltf(1.0, metallic, roughness), dir_from_angle(theta), 20_000, 3);
                assert!(
                    a <= 1.0 + 3.0 * se + 1e-6,
                    "metallic {metallic} roughness {roughness} theta {theta}: albedo {a} +- {se}"
                );
            }
        }
    }
}

/// A thin wall of white base colour absorbs nothing the specular lobe does not lose: what its
/// specular layer does not reflect it transmits, so its albedo is a white metal's (the same GGX
/// lobe, with all of it reflected; with energy compensation, 1 for both), and exactly 1 for a
/// smooth wall. With transmission below 1 the
/// diffuse layer takes the rest, and the albedo never exceeds 1.
#[test]
fn thin_transmission_conserves_energy() {
    for theta in [0.0f32, 45.0, 80.0] {
        let wo = dir_from_angle(theta);
        let (smooth, se) = albedo(&thin(1.0, 0.0, 0.0, 1.0), wo, 10_000, 5);
        assert!((smooth - 1.0).abs() < 1e-5 && se < 1e-5, "smooth wall at {theta}: {smooth} +- {se}");
        for roughness in [0.3f32, 0.7, 1.0] {
            // Single scattering, the wall's lobe is the white metal's; with energy compensation
            // both keep all the light (the wall reflects or passes what bounces between facets).
            for compensated in [false, true] {
                let keep = |b: Bsdf| if compensated { b } else { b.without_compensation() };
                let (wall, se_wall) = albedo(&keep(thin(1.0, 0.0, roughness, 1.0)), wo, 100_000, 7);
                let (metal, se_metal) = albedo(&keep(gltf(1.0, 1.0, roughness)), wo, 100_000, 8);
                let tolerance = 3.0 * (se_wall * se_wall + se_metal * se_metal).sqrt() + 2e-3;
                assert!(
                    (wall - metal).abs() <= tolerance,
                    "roughness {roughness} at {theta}, compensated {compensated}: wall {wall} +- {se_wall}, metal {metal} +- {se_metal}"
                );
            }
            for (metallic, transmission) in [(0.0f32, 0.5f32), (0.5, 1.0)] {
                let (a, se) = albedo(&thin(1.0, metallic, roughness, transmission), wo, 20_000, 9);
                assert!(a <= 1.0 + 3.0 * se + 1e-6, "{metallic} {transmission} {roughness} {theta}: {a} +- {se}");
            }
        }
    }
}

/// A clear coat reflects what it takes from the layers below and no more: a white surface under
/// any coat has albedo at most 1; over a black base a smooth coat reflects exactly its weight times
/// Schlick's Fresnel with `f0 = 0.04` (a delta lobe); a coat of weight 0 changes no bit.
#[test]
fn clear_coats_conserve_energy() {
    for theta in [0.0f32, 45.0, 75.0, 89.0] {
        let wo = dir_from_angle(theta);
        for (metallic, roughness) in [(0.0f32, 0.0f32), (0.0, 0.5), (0.0, 1.0), (1.0, 0.2), (1.0, 0.0)] {
            for (coat_roughness, tilt) in
                [(0.0f32, 0.0f32), (0.1, 0.0), (0.4, 0.0), (1.0, 0.0), (0.0, 40.0), (0.3, 70.0)]
            {
                let (a, se) =
                    albedo(&tilted(coated(1.0, metallic, roughness, 1.0, coat_roughness), tilt), wo, 20_000, 4);
                assert!(
                    a <= 1.0 + 3.0 * se + 1e-6,
                    "metallic {metallic} roughness {roughness} coat {coat_roughness} tilted {tilt} at {theta}: {a} +- {se}"
                );
            }
        }
        let black = Bsdf::gltf(Vec3::ZERO, 0.0, 0.5, 0.0, Vec3::ONE, 0.04).with_coat(0.7, 0.0);
        let (a, se) = albedo(&black, wo, 5_000, 6);
        let expect = 0.7 * (0.04 + 0.96 * (1.0 - wo.z as f64).powi(5));
        assert!((a - expect).abs() < 1e-5 && se < 1e-5, "a smooth coat over black at {theta}: {a}, expected {expect}");
        // A tilted coat is the same coat turned: over black, seen along its own normal, it
        // reflects what an untilted one does at normal incidence (its lobe stays above the base).
        let black_coat = |tilt: f32| {
            Bsdf::gltf(Vec3::ZERO, 0.0, 0.5, 0.0, Vec3::ONE, 0.04)
                .with_coat(1.0, 0.1)
                .with_coat_normal(dir_from_angle(tilt))
        };
        let (turned, se_turned) = albedo(&black_coat(60.0), dir_from_angle(60.0), 20_000, 21);
        let (upright, se_upright) = albedo(&black_coat(0.0), Vec3::Z, 20_000, 22);
        let tolerance = 3.0 * (se_turned * se_turned + se_upright * se_upright).sqrt() + 1e-4;
        assert!((turned - upright).abs() <= tolerance, "tilted coat {turned} +- {se_turned}, upright {upright}");
        let plain = gltf(0.6, 0.3, 0.4);
        let mut rng = Rng(17);
        for _ in 0..200 {
            let wi = tessera_render::sample_uniform_hemisphere([rng.next(), rng.next()]);
            assert_eq!(plain.with_coat(0.0, 0.5).eval(wo, wi), plain.eval(wo, wi));
        }
    }
}

/// The sheen lobe's tabulated albedo is its albedo (a sheen over black, measured by sampling,
/// agrees within the table's interpolation and 3 standard errors), and a white surface under
/// white sheen reflects at most what it receives. The Charlie distribution is normalised.
#[test]
fn sheen_conserves_energy() {
    use tessera_render::bsdf::sheen::Charlie;
    for roughness in [0.1f32, 0.3, 0.6, 1.0] {
        let lobe = Charlie::new(roughness);
        let f = |z: f64| lobe.d(Vec3::new((1.0 - z * z).max(0.0).sqrt() as f32, 0.0, z as f32)) as f64 * z;
        let integral = 2.0 * PI * simpson(&f, 0.0, 1.0, 1e-9);
        assert!((integral - 1.0).abs() < 2e-3, "Charlie roughness {roughness}: {integral}");
        for theta in [0.0f32, 45.0, 75.0, 88.0] {
            let wo = dir_from_angle(theta);
            let black = Bsdf::gltf(Vec3::ZERO, 0.0, 0.5, 0.0, Vec3::ONE, 0.04).with_sheen(Vec3::ONE, roughness);
            let (a, se) = albedo(&black, wo, 40_000, 12);
            let table = lobe.albedo(wo.z) as f64;
            assert!(
                (a - table).abs() <= 3.0 * se + 0.01 * table + 1e-3,
                "{roughness} at {theta}: {a} +- {se} vs {table}"
            );
            for base_roughness in [0.0f32, 0.5, 1.0] {
                let (a, se) = albedo(&sheened(1.0, base_roughness, 1.0, roughness), wo, 20_000, 13);
                assert!(a <= 1.0 + 3.0 * se + 1e-6, "white under sheen {roughness}, {base_roughness} at {theta}: {a}");
            }
        }
    }
}

#[test]
fn rough_conductors_lose_energy_and_never_gain() {
    // glTF's single-scattering definition (`--energy-compensation off`).
    let mut previous = f64::INFINITY;
    for roughness in [0.0f32, 0.25, 0.5, 0.75, 1.0] {
        let (a, se) = albedo(&gltf(1.0, 1.0, roughness).without_compensation(), dir_from_angle(60.0), 50_000, 9);
        assert!(a <= 1.0 + 3.0 * se + 1e-6, "roughness {roughness}: {a}");
        assert!(a <= previous + 3.0 * se, "albedo rose with roughness at {roughness}: {a} after {previous}");
        previous = a;
    }
    assert!(previous < 0.97, "GGX at roughness 1 must lose energy (single scattering): {previous}");
}

/// With energy compensation (the default for glTF materials) a white rough dielectric (base 1,
/// f0 0.04) and a white rough metal keep all the light from every angle: the white furnace,
/// within 1 % (the bound; the tables' interpolation is the error), with a standard error
/// under 0.1 %. Without it the same surfaces lose up to a tenth.
#[test]
fn compensated_white_surfaces_pass_the_white_furnace() {
    let mut worst_off = 1.0f64;
    for metallic in [0.0f32, 1.0] {
        for roughness in [0.1f32, 0.3, 0.5, 0.75, 1.0] {
            for theta in [0.0f32, 30.0, 60.0, 75.0, 85.0] {
                let wo = dir_from_angle(theta);
                let (a, se) = albedo(&gltf(1.0, metallic, roughness), wo, 100_000, 21);
                eprintln!("metallic {metallic} roughness {roughness} theta {theta}: {a:.4} +- {se:.4}");
                assert!(se < 3e-3, "standard error {se}");
                assert!(
                    (a - 1.0).abs() < 0.01,
                    "metallic {metallic} roughness {roughness} theta {theta}: albedo {a} +- {se}"
                );
                let (off, _) = albedo(&gltf(1.0, metallic, roughness).without_compensation(), wo, 20_000, 22);
                worst_off = worst_off.min(off);
            }
        }
    }
    assert!(worst_off < 0.93, "single scattering should lose energy somewhere: {worst_off}");
}

#[test]
fn fresnel_special_cases() {
    assert!((fresnel::dielectric(1.0, 1.5) - 0.04).abs() < 1e-6);
    // Total internal reflection: from glass into air beyond the critical angle.
    assert_eq!(fresnel::dielectric(0.3, 1.0 / 1.5), 1.0);
    // A conductor with k = 0 is a dielectric.
    for cos in [1.0f32, 0.8, 0.5, 0.2, 0.05] {
        let c = fresnel::conductor(cos, Vec3::splat(1.5), Vec3::ZERO);
        assert!(
            (c.x - fresnel::dielectric(cos, 1.5)).abs() < 1e-5,
            "cos {cos}: {} vs {}",
            c.x,
            fresnel::dielectric(cos, 1.5)
        );
    }
    // Everything reflects at grazing incidence.
    assert!(fresnel::conductor(0.0, Vec3::splat(0.2), Vec3::splat(3.0)).min_element() > 0.999);
    assert!((fresnel::schlick(Vec3::splat(0.04), Vec3::ONE, 1.0).x - 0.04).abs() < 1e-7);
}

#[test]
fn mirrors_reflect_specularly_without_nan() {
    let b = gltf(0.9, 1.0, 0.0);
    let mut rng = Rng(17);
    for theta in [0.0f32, 30.0, 89.9] {
        let wo = dir_from_angle(theta);
        let s = b.sample(wo, 0.0, [rng.next(), rng.next()]).expect("a mirror always reflects");
        assert!(s.delta);
        assert!((s.wi - Vec3::new(-wo.x, -wo.y, wo.z)).length() < 1e-6);
        assert!(s.weight.is_finite() && s.weight.max_element() <= 1.0 + 1e-5);
    }
    let _: Fresnel = Fresnel::Dielectric { eta: 1.5 };
}

#[test]
fn paper_1s_printed_brdf_reflects_more_than_it_receives_where_the_normalised_form_does_not() {
    // Directional albedo by deterministic quadrature (64 x 256 cells), for gold at 550 nm
    // (n 0.43, k 2.46) and a dielectric of n = 1.5, Beckmann roughness m from 0.3 to 1. The
    // printed form (F(0)/pi diffuse, D and G at most 1, pi in the denominator) must exceed 1 for
    // gold at every roughness from 0.3, even at normal incidence: a scene of it has q > 1 and its
    // Neumann series diverges. The normalised form must stay at most 1 (quadrature slack 0.01).
    use tessera_render::bsdf::printed::{self, Interface};
    let gold = Interface::Conductor { n: 0.43, k: 2.46 };
    let glass = Interface::Dielectric { eta: 1.5 };
    for m in [0.3f32, 0.6, 1.0] {
        for theta in [0.0f32, 45.0, 80.0] {
            let t = theta.to_radians();
            let printed_gold = printed::albedo(|wo, wi| printed::eval(gold, m, wo, wi), t, 64);
            assert!(printed_gold > 1.0, "printed gold m={m} theta={theta}: {printed_gold}");
            let printed_glass = printed::albedo(|wo, wi| printed::eval(glass, m, wo, wi), t, 64);
            assert!(printed_glass < 1.0, "printed dielectric m={m} theta={theta}: {printed_glass}");
            for (what, interface) in [("gold", gold), ("dielectric", glass)] {
                let bsdf = printed::normalised(interface, m);
                let a = printed::albedo(|wo, wi| bsdf.eval(wo, wi).x, t, 64);
                assert!(a <= 1.01, "normalised {what} m={m} theta={theta}: {a}");
            }
        }
    }
}
