//! Choosing N wavelengths for one pixel: uniformly (Kucherov et al.), stratified, or hero-wavelength
//! sampling (one random wavelength, the others at even offsets of the CDF, so that all N are
//! stratified together) with a pdf shaped like the eye's sensitivity.

use super::{LAMBDA_MAX, LAMBDA_MIN};

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum WavelengthSampler {
    /// Independent, uniform over the visible range, as in Kucherov et al.
    Uniform,
    /// One uniform wavelength in each of N equal strata.
    Stratified,
    /// Hero wavelength: one uniform number rotated by i/N, mapped through the visible pdf.
    Hero,
}

impl WavelengthSampler {
    pub const ALL: [WavelengthSampler; 3] = [Self::Uniform, Self::Stratified, Self::Hero];

    pub fn name(self) -> &'static str {
        match self {
            Self::Uniform => "uniform",
            Self::Stratified => "stratified",
            Self::Hero => "hero",
        }
    }

    /// Fills `out` with N (wavelength in nm, pdf per nm) pairs, drawing uniform numbers from `u`.
    pub fn sample(self, n: usize, mut u: impl FnMut() -> f64, out: &mut Vec<(f64, f64)>) {
        out.clear();
        let width = LAMBDA_MAX - LAMBDA_MIN;
        match self {
            Self::Uniform => out.extend((0..n).map(|_| (LAMBDA_MIN + width * u(), 1.0 / width))),
            Self::Stratified => {
                out.extend((0..n).map(|i| (LAMBDA_MIN + width * (i as f64 + u()) / n as f64, 1.0 / width)))
            }
            Self::Hero => {
                let u0 = u();
                out.extend((0..n).map(|i| {
                    let ui = (u0 + i as f64 / n as f64).fract();
                    let l = sample_visible(ui);
                    (l, visible_pdf(l))
                }))
            }
        }
    }
}

/// The visible pdf: `sech²(a (λ - 538 nm))` with a = 0.0072/nm (the shape pbrt uses, after
/// Radziszewski et al.), normalised over [380, 780] nm. Its CDF is a tanh, inverted exactly.
const A: f64 = 0.0072;
const CENTRE: f64 = 538.0;

fn tanh_at(l: f64) -> f64 {
    libm::tanh(A * (l - CENTRE))
}

/// `tanh` at the ends of the range: the CDF's bounds, computed once (every path needs them).
static ENDS: std::sync::LazyLock<(f64, f64)> = std::sync::LazyLock::new(|| (tanh_at(LAMBDA_MIN), tanh_at(LAMBDA_MAX)));

pub fn visible_pdf(lambda: f64) -> f64 {
    if !(LAMBDA_MIN..=LAMBDA_MAX).contains(&lambda) {
        return 0.0;
    }
    let c = libm::cosh(A * (lambda - CENTRE));
    let (t0, t1) = *ENDS;
    A / (c * c) / (t1 - t0)
}

/// [`sample_visible`] with the pdf at the wavelength it returns. The pdf comes from the tanh the
/// sampling inverts (`sech² = 1 - tanh²`) rather than from a cosh of the wavelength: one
/// transcendental function per wavelength instead of three. Equal to [`visible_pdf`] up to
/// rounding.
pub fn sample_visible_with_pdf(u: f64) -> (f64, f64) {
    let (x, l) = invert_cdf(u);
    if !(LAMBDA_MIN..=LAMBDA_MAX).contains(&l) {
        let l = l.clamp(LAMBDA_MIN, LAMBDA_MAX); // rounding past an end: the pdf of the end
        return (l, visible_pdf(l));
    }
    let (t0, t1) = *ENDS;
    (l, A * (1.0 - x * x) / (t1 - t0))
}

/// Inverse CDF of [`visible_pdf`]: u in [0, 1) to a wavelength in [380, 780] nm.
pub fn sample_visible(u: f64) -> f64 {
    invert_cdf(u).1.clamp(LAMBDA_MIN, LAMBDA_MAX)
}

/// The tanh that `u` stands for on the CDF's scale, and the wavelength it inverts to (before
/// clamping to the range, which rounding may leave).
fn invert_cdf(u: f64) -> (f64, f64) {
    let (t0, t1) = *ENDS;
    let x = t0 + u * (t1 - t0);
    (x, CENTRE + libm::atanh(x) / A)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::spectral::integrate_1nm;

    #[test]
    fn the_sampled_pdf_is_the_pdf_at_the_sample() {
        for k in 0..=10_000 {
            let u = k as f64 / 10_001.0;
            let (l, pdf) = sample_visible_with_pdf(u);
            assert_eq!(l, sample_visible(u));
            let exact = visible_pdf(l);
            assert!((pdf - exact).abs() <= 1e-13 * exact, "u {u}: {pdf} against {exact}");
        }
    }

    #[test]
    fn visible_pdf_integrates_to_one_and_inverts() {
        let total = integrate_1nm(visible_pdf);
        assert!((total - 1.0).abs() < 1e-4, "{total}");
        for u in [0.0, 0.1, 0.5, 0.9, 0.999] {
            let l = sample_visible(u);
            let cdf = integrate_1nm(|x| if x <= l { visible_pdf(x) } else { 0.0 });
            assert!((cdf - u).abs() < 3e-3, "u {u}: cdf({l}) = {cdf}");
        }
    }
}
