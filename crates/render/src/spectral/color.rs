//! From spectra to display colours: the CIE XYZ integrals, XYZ to linear RGB (IEC 61966-2-1
//! sRGB, or the CIE 1931 RGB primaries Kucherov et al. printed by mistake), and the sRGB transfer curve.

use super::{Spectrum, data, integrate_1nm};

/// The light a chart is seen under.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Illuminant {
    D65,
    A,
    /// Equal energy: 1 at every wavelength.
    E,
}

impl Illuminant {
    pub fn spd(self) -> &'static Spectrum {
        static E: std::sync::OnceLock<Spectrum> = std::sync::OnceLock::new();
        match self {
            Illuminant::D65 => data::d65(),
            Illuminant::A => data::illuminant_a(),
            Illuminant::E => E.get_or_init(|| Spectrum::constant(1.0)),
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Illuminant::D65 => "d65",
            Illuminant::A => "a",
            Illuminant::E => "e",
        }
    }

    /// `1 / ∫ S ȳ`: scales XYZ so that a perfect white under this light has Y = 1. Integrated
    /// once per illuminant: every chart pixel asks for it.
    pub fn normalisation(self) -> f64 {
        static CACHE: [std::sync::OnceLock<f64>; 3] = [const { std::sync::OnceLock::new() }; 3];
        *CACHE[self as usize].get_or_init(|| {
            let (s, y) = (self.spd(), &data::cmf()[1]);
            1.0 / integrate_1nm(|l| s.eval(l) * y.eval(l))
        })
    }
}

/// Which RGB primaries XYZ is mapped to.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Primaries {
    /// IEC 61966-2-1 (sRGB, Rec. 709 primaries, D65 white).
    Srgb,
    /// CIE 1931 RGB (700, 546.1, 435.8 nm primaries, E white): the matrix Kucherov et al. printed.
    CieRgb,
}

/// XYZ to linear sRGB, IEC 61966-2-1 (the standard's own four-digit matrix).
pub const XYZ_TO_SRGB: [[f64; 3]; 3] =
    [[3.2406, -1.5372, -0.4986], [-0.9689, 1.8758, 0.0415], [0.0557, -0.2040, 1.0570]];

/// CIE 1931 RGB to XYZ (CIE 1931): each row sums to 1, so R = G = B = 1 is the equal-energy
/// white with Y = 1.
pub const CIE_RGB_TO_XYZ: [[f64; 3]; 3] = [[0.49, 0.31, 0.20], [0.17697, 0.81240, 0.01063], [0.0, 0.01, 0.99]];

impl Primaries {
    pub fn matrix(self) -> [[f64; 3]; 3] {
        match self {
            Primaries::Srgb => XYZ_TO_SRGB,
            Primaries::CieRgb => invert3(CIE_RGB_TO_XYZ),
        }
    }

    pub fn from_xyz(self, xyz: [f64; 3]) -> [f64; 3] {
        mul3(&self.matrix(), xyz)
    }
}

pub fn mul3(m: &[[f64; 3]; 3], v: [f64; 3]) -> [f64; 3] {
    [0, 1, 2].map(|r| m[r][0] * v[0] + m[r][1] * v[1] + m[r][2] * v[2])
}

/// The inverse of a 3x3 matrix (by cofactors; the matrices here are well conditioned).
pub fn invert3(m: [[f64; 3]; 3]) -> [[f64; 3]; 3] {
    let c = |r: usize, k: usize| {
        let (r1, r2, k1, k2) = ((r + 1) % 3, (r + 2) % 3, (k + 1) % 3, (k + 2) % 3);
        m[r1][k1] * m[r2][k2] - m[r1][k2] * m[r2][k1]
    };
    let det = m[0][0] * c(0, 0) + m[0][1] * c(0, 1) + m[0][2] * c(0, 2);
    [0, 1, 2].map(|r| [0, 1, 2].map(|k| c(k, r) / det))
}

/// The sRGB transfer curve (IEC 61966-2-1: a = 0.055, not Kucherov et al.'s 0.55).
pub fn srgb_encode(linear: f64) -> f64 {
    if linear <= 0.0031308 { 12.92 * linear } else { 1.055 * libm::pow(linear, 1.0 / 2.4) - 0.055 }
}

/// Exact (1 nm trapezoid) XYZ of reflectance `r` under `light`, normalised so white has Y = 1.
pub fn xyz_exact(r: &Spectrum, light: Illuminant) -> [f64; 3] {
    let (s, cmf, k) = (light.spd(), data::cmf(), light.normalisation());
    [0, 1, 2].map(|c| k * integrate_1nm(|l| s.eval(l) * r.eval(l) * cmf[c].eval(l)))
}

/// Linear sRGB of a reflectance under D65, clamped to [0, 1]: the RGB stand-in for a measured
/// reflectance when rendering without wavelengths.
pub fn reflectance_srgb(r: &Spectrum) -> [f32; 3] {
    Primaries::Srgb.from_xyz(xyz_exact(r, Illuminant::D65)).map(|x| x.clamp(0.0, 1.0) as f32)
}
