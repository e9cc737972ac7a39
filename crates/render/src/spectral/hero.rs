//! Hero-wavelength transport (Wilkie et al. 2014): every path carries four wavelengths, the
//! first drawn from the visible-importance pdf and the others rotated a quarter of the way
//! along it, so one path's geometry serves four spectral samples. Colours become spectra
//! here: RGB reflectances by the Jakob-Hanika sigmoid, RGB emitters shaped like D65, measured
//! spectra as they are; the four values become linear sRGB through the CIE 1931 functions.

use super::color::{Illuminant, XYZ_TO_SRGB};
use super::upsample::RgbToSpectrum;
use super::wavelengths::sample_visible_with_pdf;
use super::{RGB_WAVELENGTHS, Spectrum, Step, data, even_step};
use crate::channels::ColorModel;
use glam::{Vec3, Vec4};
use std::sync::LazyLock;

/// The first wavelength of [`OBSERVER`] (that of the colour matching functions' table).
const OBSERVER_FIRST: f64 = 360.0;

/// x̄, ȳ, z̄ and D65 at every nm of the colour matching functions' table (360-830 nm), side by
/// side: one index computation serves the four lookups a wavelength needs. Both tables are
/// tabulated at whole nm, so interpolating here gives [`Spectrum::eval`]'s bits for each.
static OBSERVER: LazyLock<Vec<[f64; 4]>> = LazyLock::new(|| {
    let (cmf, d65) = (data::cmf(), data::d65());
    cmf[0]
        .points()
        .iter()
        .enumerate()
        .map(|(i, &(l, x))| [x, cmf[1].points()[i].1, cmf[2].points()[i].1, d65.eval(l)])
        .collect()
});

/// x̄, ȳ, z̄ and D65 at `lambda`, interpolated as [`Spectrum::eval`] does.
fn observer_at(lambda: f64) -> [f64; 4] {
    let rows = &*OBSERVER;
    match even_step(lambda - OBSERVER_FIRST, rows.len()) {
        Step::First => rows[0],
        Step::Last => rows[rows.len() - 1],
        Step::Between(i, f) => std::array::from_fn(|c| rows[i][c] + (rows[i + 1][c] - rows[i][c]) * f),
    }
}

/// Wavelengths per path.
pub const LANES: usize = 4;

/// [`XYZ_TO_SRGB`]'s rows in f32, once, not per path.
const XYZ_TO_SRGB_ROWS: [Vec3; 3] = {
    let m = XYZ_TO_SRGB;
    [
        Vec3::new(m[0][0] as f32, m[0][1] as f32, m[0][2] as f32),
        Vec3::new(m[1][0] as f32, m[1][1] as f32, m[1][2] as f32),
        Vec3::new(m[2][0] as f32, m[2][1] as f32, m[2][2] as f32),
    ]
};

/// The wavelengths of one path and what converting its four values needs.
#[derive(Clone, Copy, Debug)]
pub struct Hero {
    pub lambda: [f32; LANES],
    /// D65 at each wavelength, normalised so that D65 white has Y = 1.
    d65: Vec4,
    /// `xbar, ybar, zbar (lambda) / (LANES p(lambda))`: one path's share of each XYZ integral.
    to_xyz: [Vec4; 3],
}

impl Hero {
    /// The path's wavelengths from one uniform number.
    pub fn new(u: f32) -> Self {
        let k = Illuminant::D65.normalisation();
        let mut lambda = [0.0f32; LANES];
        let mut white = [0.0f32; LANES];
        let mut to_xyz = [[0.0f32; LANES]; 3];
        for j in 0..LANES {
            let (l, pdf) = sample_visible_with_pdf((u as f64 + j as f64 / LANES as f64).fract());
            let weight = 1.0 / (LANES as f64 * pdf);
            let [x, y, z, d65] = observer_at(l);
            lambda[j] = l as f32;
            white[j] = (d65 * k) as f32;
            for (xyz, v) in to_xyz.iter_mut().zip([x, y, z]) {
                xyz[j] = (v * weight) as f32;
            }
        }
        Self { lambda, d65: Vec4::from_array(white), to_xyz: to_xyz.map(Vec4::from_array) }
    }

    fn each(&self, f: impl Fn(f32) -> f32) -> Vec4 {
        Vec4::from_array(self.lambda.map(f))
    }
}

impl ColorModel for Hero {
    type C = Vec4;

    fn albedo(&self, rgb: Vec3) -> Vec4 {
        let s = RgbToSpectrum::spectrum_of(rgb.to_array());
        self.each(|l| s.eval(l))
    }

    /// An RGB emitter's spectrum: `2m S(lambda) D65(lambda)` with `S` the reflectance of
    /// `rgb / 2m`, `m` the largest channel (as pbrt-v4's RGBIlluminantSpectrum), so its colour
    /// is `rgb` and white is D65.
    fn illuminant(&self, rgb: Vec3) -> Vec4 {
        let m = rgb.max_element();
        if m.is_nan() || m <= 0.0 {
            return Vec4::ZERO;
        }
        let s = RgbToSpectrum::spectrum_of((rgb / (2.0 * m)).to_array());
        self.each(|l| s.eval(l)) * self.d65 * (2.0 * m)
    }

    fn measured(&self, spectrum: &Spectrum, scale: f32, _rgb: Vec3) -> Vec4 {
        self.each(|l| spectrum.eval(l as f64) as f32 * scale)
    }

    fn optical_constant(&self, rgb: Vec3) -> Vec4 {
        let [r, g, b] = RGB_WAVELENGTHS.map(|l| l as f32);
        self.each(|l| {
            if l <= b {
                rgb.z
            } else if l <= g {
                rgb.z + (rgb.y - rgb.z) * (l - b) / (g - b)
            } else if l <= r {
                rgb.y + (rgb.x - rgb.y) * (l - g) / (r - g)
            } else {
                rgb.x
            }
        })
    }

    fn to_rgb(&self, c: Vec4) -> Vec3 {
        let xyz = Vec3::new(self.to_xyz[0].dot(c), self.to_xyz[1].dot(c), self.to_xyz[2].dot(c));
        let m = &XYZ_TO_SRGB_ROWS;
        Vec3::new(m[0].dot(xyz), m[1].dot(xyz), m[2].dot(xyz))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The side-by-side table gives each of its spectra's own interpolated bits, at whole,
    /// fractional and end wavelengths.
    #[test]
    fn the_observer_table_interpolates_as_each_spectrum() {
        let (cmf, d65) = (data::cmf(), data::d65());
        let mut state = 1u64;
        let mut lambdas = vec![300.0, 360.0, 380.0, 380.5, 555.0, 779.999, 780.0, 830.0, 900.0];
        lambdas.extend((0..20_000).map(|_| {
            state = crate::sampler::mix64(state);
            380.0 + 400.0 * crate::sampler::unit_f32(state) as f64 + (state >> 40) as f64 * 1e-9
        }));
        for l in lambdas {
            let [x, y, z, white] = observer_at(l);
            assert_eq!([x, y, z], [cmf[0].eval(l), cmf[1].eval(l), cmf[2].eval(l)], "at {l} nm");
            if l >= OBSERVER_FIRST {
                assert_eq!(white, d65.eval(l), "D65 at {l} nm");
            }
        }
    }
}
