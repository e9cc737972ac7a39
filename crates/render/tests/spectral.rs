//! Kucherov et al.'s colour by Monte Carlo over wavelength: the colour science checked against known
//! values, the chart against exact 1 nm integration, and the paper's noise law. Fixed seeds.

use tessera_render::spectral::chart::{self, ChartSettings};
use tessera_render::spectral::color::{Illuminant, Primaries, invert3, mul3, xyz_exact};
use tessera_render::spectral::upsample::RgbToSpectrum;
use tessera_render::spectral::wavelengths::WavelengthSampler;
use tessera_render::spectral::{Spectrum, data};

fn render(settings: &ChartSettings) -> Vec<[f64; 3]> {
    (0..chart::HEIGHT).flat_map(|y| chart::row(settings, y)).collect()
}

fn settings(samples: usize, sampler: WavelengthSampler) -> ChartSettings {
    ChartSettings { samples, sampler, illuminant: Illuminant::D65, primaries: Primaries::Srgb, seed: 1 }
}

#[test]
fn a_constant_spectrum_is_equal_energy_white() {
    let xyz = xyz_exact(&Spectrum::constant(0.5), Illuminant::E);
    let sum: f64 = xyz.iter().sum();
    let (x, y) = (xyz[0] / sum, xyz[1] / sum);
    assert!((x - 1.0 / 3.0).abs() < 1e-3 && (y - 1.0 / 3.0).abs() < 1e-3, "chromaticity ({x}, {y})");
    assert!((xyz[1] - 0.5).abs() < 1e-12, "Y of reflectance 0.5 under any light is 0.5");
}

#[test]
fn white_under_d65_is_srgb_white() {
    let xyz = xyz_exact(&Spectrum::constant(1.0), Illuminant::D65);
    // The D65 white point of the 1931 observer, as tabulated (CIE 15): X 0.95047, Z 1.08883.
    assert!(
        (xyz[0] - 0.95047).abs() < 1e-3 && (xyz[1] - 1.0).abs() < 1e-12 && (xyz[2] - 1.08883).abs() < 2e-3,
        "{xyz:?}"
    );
    let rgb = Primaries::Srgb.from_xyz(xyz);
    for c in rgb {
        assert!((c - 1.0).abs() < 1e-3, "sRGB of D65 white {rgb:?}");
    }
}

#[test]
fn the_normalisation_is_the_tables_own_sum() {
    // 1 / sum of S(λ) ȳ(λ) over the shipped 1 nm rows inside 380..780 (trapezoid ends).
    let (s, y) = (data::d65(), &data::cmf()[1]);
    let rows: Vec<f64> =
        y.points().iter().filter(|p| (380.0..=780.0).contains(&p.0)).map(|p| s.eval(p.0) * p.1).collect();
    let sum: f64 = rows.iter().sum::<f64>() - 0.5 * (rows[0] + rows[rows.len() - 1]);
    assert_eq!(rows.len(), 401);
    assert!((Illuminant::D65.normalisation() * sum - 1.0).abs() < 1e-12);
}

#[test]
fn cie_rgb_is_the_matrix_the_paper_printed_and_maps_e_white_to_one() {
    let m = Primaries::CieRgb.matrix();
    // Kucherov et al.'s matrix (XYZ to CIE RGB), as commonly tabulated.
    let printed = [[2.3647, -0.8966, -0.4681], [-0.5152, 1.4264, 0.0887], [0.0052, -0.0144, 1.0092]];
    for r in 0..3 {
        for c in 0..3 {
            assert!((m[r][c] - printed[r][c]).abs() < 2e-3, "{m:?}");
        }
    }
    let white = mul3(&m, [1.0, 1.0, 1.0]);
    assert!(white.iter().all(|v| (v - 1.0).abs() < 1e-3), "{white:?}");
    let back = invert3(m);
    assert!((back[1][0] - 0.17697).abs() < 1e-12, "inverting gives back the CIE table");
}

#[test]
fn at_large_n_every_patch_agrees_with_exact_integration_for_every_sampler() {
    let exact = chart::exact_patches(Illuminant::D65, Primaries::Srgb);
    for sampler in WavelengthSampler::ALL {
        let stats = chart::patch_stats(&render(&settings(256, sampler)), &exact);
        for (i, s) in stats.iter().enumerate() {
            assert!(
                s.mean_error_8bit < 0.5,
                "{} patch {i}: off by {:.3} on the 8-bit scale",
                sampler.name(),
                s.mean_error_8bit
            );
        }
    }
}

#[test]
fn uniform_noise_halves_when_n_quadruples() {
    let exact = chart::exact_patches(Illuminant::D65, Primaries::Srgb);
    let points: Vec<(f64, f64)> = [32, 128, 512, 1024]
        .iter()
        .map(|&n| {
            (n as f64, chart::noise(&chart::patch_stats(&render(&settings(n, WavelengthSampler::Uniform)), &exact)))
        })
        .collect();
    let slope = chart::log_log_slope(&points);
    assert!((slope + 0.5).abs() < 0.05, "uniform noise slope {slope:.3} (Kucherov et al.: -1/2); {points:?}");
}

#[test]
fn stratified_and_hero_beat_uniform() {
    let exact = chart::exact_patches(Illuminant::D65, Primaries::Srgb);
    let noise = |s| chart::noise(&chart::patch_stats(&render(&settings(32, s)), &exact));
    let uniform = noise(WavelengthSampler::Uniform);
    for s in [WavelengthSampler::Stratified, WavelengthSampler::Hero] {
        assert!(noise(s) < 0.5 * uniform, "{} noise {} against uniform {uniform}", s.name(), noise(s));
    }
}

/// Linear sRGB of a sigmoid spectrum under D65, by exact 1 nm integration.
fn round_trip(rgb: [f32; 3]) -> [f64; 3] {
    let s = RgbToSpectrum::get().lookup(rgb);
    let table: Vec<(f64, f64)> = (380..=780).map(|l| (l as f64, s.eval(l as f32) as f64)).collect();
    Primaries::Srgb.from_xyz(xyz_exact(&Spectrum::new(table), Illuminant::D65))
}

#[test]
fn rgb_to_spectrum_to_rgb_round_trips_within_0_01_across_the_srgb_gamut() {
    // Every point of an 11^3 grid over the unit cube, plus its saturated edges at a finer step.
    let steps: Vec<f32> = (0..=10).map(|i| i as f32 / 10.0).collect();
    let mut worst = (0.0f64, [0.0f32; 3]);
    let mut check = |rgb: [f32; 3]| {
        let back = round_trip(rgb);
        let err = (0..3).map(|c| (back[c] - rgb[c] as f64).abs()).fold(0.0, f64::max);
        if err > worst.0 {
            worst = (err, rgb);
        }
    };
    for &r in &steps {
        for &g in &steps {
            for &b in &steps {
                check([r, g, b]);
            }
        }
    }
    for i in 0..=40 {
        let t = i as f32 / 40.0;
        for rgb in [[1.0, t, 0.0], [t, 1.0, 0.0], [0.0, 1.0, t], [0.0, t, 1.0], [t, 0.0, 1.0], [1.0, 0.0, t]] {
            check(rgb);
        }
    }
    eprintln!("worst round trip error {:.5} at {:?}", worst.0, worst.1);
    assert!(worst.0 < 0.01, "round trip error {:.4} at {:?}", worst.0, worst.1);
}
