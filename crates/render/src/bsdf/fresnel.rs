//! Fresnel reflectance: Schlick's approximation (glTF), exact dielectric and exact conductor
//! (complex index of refraction `n + ik`, Dimov, Gurov and Penzov's `F(lambda, theta)`).

use crate::channels::Channels;

/// Schlick's approximation `F0 + (F90 - F0)(1 - cos)^5`.
pub fn schlick<C: Channels>(f0: C, f90: C, cos: f32) -> C {
    let m = (1.0 - cos.clamp(0.0, 1.0)).powi(5);
    f0 + (f90 - f0) * m
}

/// Unpolarised reflectance of a dielectric interface, `eta = n_transmitted / n_incident`.
/// Returns 1 under total internal reflection.
pub fn dielectric(cos_i: f32, eta: f32) -> f32 {
    let cos_i = cos_i.clamp(0.0, 1.0);
    let sin2_t = (1.0 - cos_i * cos_i) / (eta * eta);
    if sin2_t >= 1.0 {
        return 1.0; // total internal reflection
    }
    let cos_t = (1.0 - sin2_t).sqrt();
    let rs = (cos_i - eta * cos_t) / (cos_i + eta * cos_t);
    let rp = (eta * cos_i - cos_t) / (eta * cos_i + cos_t);
    0.5 * (rs * rs + rp * rp)
}

/// Unpolarised reflectance of a conductor with complex index `eta + i k`, per channel
/// (per wavelength when spectral: Dimov, Gurov and Penzov's `F(lambda, theta)`).
pub fn conductor<C: Channels>(cos_i: f32, eta: C, k: C) -> C {
    eta.zip_map(k, |eta, k| conductor_scalar(cos_i, Complex::new(eta, k)))
}

fn conductor_scalar(cos_i: f32, eta: Complex) -> f32 {
    let cos_i = cos_i.clamp(0.0, 1.0);
    let sin2_i = 1.0 - cos_i * cos_i;
    // Snell's law with a complex index: sin^2 t = sin^2 i / eta^2.
    let sin2_t = Complex::real(sin2_i).div(eta.mul(eta));
    let cos_t = Complex::real(1.0).sub(sin2_t).sqrt();
    let ci = Complex::real(cos_i);
    let r_parl = eta.mul(ci).sub(cos_t).div(eta.mul(ci).add(cos_t));
    let r_perp = ci.sub(eta.mul(cos_t)).div(ci.add(eta.mul(cos_t)));
    0.5 * (r_parl.norm_sqr() + r_perp.norm_sqr())
}

/// Just enough complex arithmetic for the conductor Fresnel equations (in f64 for accuracy).
#[derive(Clone, Copy, Debug)]
struct Complex {
    re: f64,
    im: f64,
}

impl Complex {
    fn new(re: f32, im: f32) -> Self {
        Self { re: re as f64, im: im as f64 }
    }
    fn real(re: f32) -> Self {
        Self::new(re, 0.0)
    }
    fn add(self, o: Self) -> Self {
        Self { re: self.re + o.re, im: self.im + o.im }
    }
    fn sub(self, o: Self) -> Self {
        Self { re: self.re - o.re, im: self.im - o.im }
    }
    fn mul(self, o: Self) -> Self {
        Self { re: self.re * o.re - self.im * o.im, im: self.re * o.im + self.im * o.re }
    }
    fn div(self, o: Self) -> Self {
        let d = o.re * o.re + o.im * o.im;
        Self { re: (self.re * o.re + self.im * o.im) / d, im: (self.im * o.re - self.re * o.im) / d }
    }
    fn norm_sqr(self) -> f32 {
        (self.re * self.re + self.im * self.im) as f32
    }
    /// Principal square root.
    fn sqrt(self) -> Self {
        let r = (self.re * self.re + self.im * self.im).sqrt();
        let re = (0.5 * (r + self.re)).max(0.0).sqrt();
        let im = (0.5 * (r - self.re)).max(0.0).sqrt().copysign(self.im);
        Self { re, im }
    }
}
