//! Colour by Monte Carlo over wavelength (Kucherov et al.): tabulated spectra, the CIE observer, XYZ to
//! RGB, wavelength samplers, and the Macbeth chart of the paper.

pub mod chart;
pub mod color;
pub mod data;
pub mod hero;
pub mod upsample;
pub mod wavelengths;

/// The visible range Tessera integrates over, in nm (the ColorChecker's measured range).
pub const LAMBDA_MIN: f64 = 380.0;
pub const LAMBDA_MAX: f64 = 780.0;

/// Where an RGB renderer samples quantities that depend on wavelength (a named metal's `n`, `k`),
/// and where a spectral one places per-channel optical constants: red, green, blue (nm).
pub const RGB_WAVELENGTHS: [f64; 3] = [630.0, 532.0, 465.0];

/// A tabulated spectrum: (wavelength in nm, value) pairs, ascending, interpolated linearly and
/// held constant beyond its ends (a measured table says nothing better there).
#[derive(Clone, Debug, PartialEq)]
pub struct Spectrum {
    points: Vec<(f64, f64)>,
    /// 1 / spacing when the wavelengths are evenly spaced (most tables): lookups index directly.
    inv_step: Option<f64>,
}

impl Spectrum {
    /// Points must be ascending in wavelength; at least one.
    pub fn new(points: Vec<(f64, f64)>) -> Self {
        assert!(!points.is_empty(), "a spectrum needs at least one point");
        debug_assert!(points.windows(2).all(|w| w[0].0 < w[1].0), "wavelengths must ascend");
        let inv_step = (points.len() >= 2)
            .then(|| (points[points.len() - 1].0 - points[0].0) / (points.len() - 1) as f64)
            .filter(|&step| points.windows(2).all(|w| ((w[1].0 - w[0].0) - step).abs() < 1e-9 * step))
            .map(|step| 1.0 / step);
        Self { points, inv_step }
    }

    /// The same value at every wavelength.
    pub fn constant(value: f64) -> Self {
        Self::new(vec![(LAMBDA_MIN, value)])
    }

    pub fn points(&self) -> &[(f64, f64)] {
        &self.points
    }

    pub fn eval(&self, lambda: f64) -> f64 {
        let p = &self.points;
        if let Some(inv) = self.inv_step {
            return match even_step((lambda - p[0].0) * inv, p.len()) {
                Step::First => p[0].1,
                Step::Last => p[p.len() - 1].1,
                Step::Between(i, f) => p[i].1 + (p[i + 1].1 - p[i].1) * f,
            };
        }
        let i = p.partition_point(|&(l, _)| l <= lambda);
        if i == 0 {
            return p[0].1;
        }
        if i == p.len() {
            return p[p.len() - 1].1;
        }
        let ((l0, v0), (l1, v1)) = (p[i - 1], p[i]);
        v0 + (v1 - v0) * (lambda - l0) / (l1 - l0)
    }

    /// The largest value of the table.
    pub fn max(&self) -> f64 {
        self.points.iter().map(|p| p.1).fold(f64::MIN, f64::max)
    }
}

/// Where position `t` (in steps from the first entry) falls in an evenly spaced table of `len`
/// entries; beyond its ends a table is held constant.
pub(crate) enum Step {
    First,
    Last,
    /// Between entries `i` and `i + 1`, the fraction `f` of the way.
    Between(usize, f64),
}

pub(crate) fn even_step(t: f64, len: usize) -> Step {
    if t <= 0.0 {
        return Step::First;
    }
    let i = t as usize;
    if i + 1 >= len { Step::Last } else { Step::Between(i, t - i as f64) }
}

/// `∫ f(λ) dλ` over the visible range by the trapezoid rule at 1 nm: the "exact" integral every
/// Monte Carlo estimate is compared with.
pub fn integrate_1nm(f: impl Fn(f64) -> f64) -> f64 {
    let n = (LAMBDA_MAX - LAMBDA_MIN) as usize;
    let mut sum = 0.5 * (f(LAMBDA_MIN) + f(LAMBDA_MAX));
    for i in 1..n {
        sum += f(LAMBDA_MIN + i as f64);
    }
    sum
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn even_and_uneven_tables_interpolate_alike() {
        let even = Spectrum::new(vec![(400.0, 1.0), (500.0, 3.0), (600.0, 2.0)]);
        let uneven = Spectrum::new(vec![(400.0, 1.0), (500.0, 3.0), (600.0, 2.0), (601.0, 2.0)]);
        assert!(even.inv_step.is_some() && uneven.inv_step.is_none());
        for l in [300.0, 400.0, 450.0, 500.0, 575.0, 600.0, 700.0] {
            assert_eq!(even.eval(l), uneven.eval(l), "at {l}");
        }
        assert_eq!(even.eval(450.0), 2.0);
        assert_eq!(even.eval(300.0), 1.0);
        assert_eq!(even.eval(700.0), 2.0);
    }
}
