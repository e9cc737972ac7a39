//! Small helpers shared by the renderer: orthonormal frames, luminance, and tables computed in
//! parallel with the same bits ([`rows_in_parallel`]).
//!
//! Transcendental functions (sin, exp, pow, ...) come from the `libm` crate, a pure-Rust port of
//! musl's, everywhere in the renderer and the scene loader, never from the platform's C library:
//! glibc versions, macOS and other systems round differently, and glibc picks an FMA variant of
//! `sinf`, `expf`, `powf`, `exp` ... by CPU at run time. One different last bit sends a path
//! elsewhere, so two workers would render the same sample differently and a farm's image would
//! depend on which worker took which tile (invariants 1 and 2). `libm` is plain IEEE arithmetic
//! (Rust never fuses it into FMAs), so a build gives the same bits on every machine.
//! `clippy.toml` disallows the std methods, which CI enforces.

use glam::Vec3;

/// An orthonormal basis whose `n` axis is the local +z direction (shading space).
#[derive(Clone, Copy, Debug)]
pub struct Frame {
    pub s: Vec3,
    pub t: Vec3,
    pub n: Vec3,
}

impl Frame {
    /// Builds a frame around a unit normal (Duff et al. 2017, "Building an Orthonormal Basis, Revisited").
    pub fn from_normal(n: Vec3) -> Self {
        let sign = 1.0f32.copysign(n.z);
        let a = -1.0 / (sign + n.z);
        let b = n.x * n.y * a;
        let s = Vec3::new(1.0 + sign * n.x * n.x * a, sign * b, -sign * n.x);
        let t = Vec3::new(b, sign + n.y * n.y * a, -n.y);
        Self { s, t, n }
    }

    /// Builds a frame around a unit normal with `s` as close as possible to `tangent`.
    pub fn from_normal_tangent(n: Vec3, tangent: Vec3) -> Self {
        let s = (tangent - n * n.dot(tangent)).normalize_or_zero();
        if s == Vec3::ZERO {
            return Self::from_normal(n);
        }
        Self { s, t: n.cross(s), n }
    }

    pub fn to_local(&self, v: Vec3) -> Vec3 {
        Vec3::new(v.dot(self.s), v.dot(self.t), v.dot(self.n))
    }

    pub fn to_world(&self, v: Vec3) -> Vec3 {
        self.s * v.x + self.t * v.y + self.n * v.z
    }
}

/// Rec.709 luminance of a linear RGB triple.
pub fn luminance(c: Vec3) -> f32 {
    0.2126 * c.x + 0.7152 * c.y + 0.0722 * c.z
}

/// Mirror `v` about the unit vector `n`.
pub fn reflect(v: Vec3, n: Vec3) -> Vec3 {
    2.0 * v.dot(n) * n - v
}

/// `v` in the local frame mirrored through the surface (`z` negated): where a thin wall passes a
/// direction reflected above it, or a hemisphere's sample lands below.
pub fn through_surface(v: Vec3) -> Vec3 {
    Vec3::new(v.x, v.y, -v.z)
}

/// The square root of each of four lanes, each correctly rounded as `f32::sqrt` is: one packed
/// instruction on x86-64 (SSE2 is part of it).
#[inline]
pub(crate) fn sqrt4(v: [f32; 4]) -> [f32; 4] {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::*;
        // SAFETY: SSE2 is part of x86-64; loads and stores are unaligned.
        unsafe {
            let mut out = [0.0; 4];
            _mm_storeu_ps(out.as_mut_ptr(), _mm_sqrt_ps(_mm_loadu_ps(v.as_ptr())));
            out
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    v.map(f32::sqrt)
}

/// `libm::sincosf` of eight angles at once, bit for bit: lane `i` of the result is
/// `sincosf(x[i])` where `on[i]` (other lanes' values are of no use). Where `lanes` has AVX2 (it
/// must run on this CPU) and every angle that is on lies in `[+0, 9π/4]` (the wave's angles,
/// `2π u`, always do), the eight go through libm's own steps in AVX2 registers: the same case by
/// magnitude, the same `f64` reduction and polynomials, the same rounding to `f32`. Any other
/// angle takes libm's call.
#[inline(always)]
pub(crate) fn sincos_lanes(lanes: crate::lanes::Lanes, x: [f32; 8], on: [bool; 8]) -> ([f32; 8], [f32; 8]) {
    #[cfg(target_arch = "x86_64")]
    if lanes != crate::lanes::Lanes::Portable && (0..8).all(|i| !on[i] || x[i].to_bits() <= sincos_avx2::LAST_CASE) {
        // SAFETY: `lanes` has AVX2 and runs on this CPU (the caller's promise).
        return unsafe { sincos_avx2::sincos(x) };
    }
    let _ = lanes;
    let (mut sin, mut cos) = ([0.0f32; 8], [0.0f32; 8]);
    for i in 0..8 {
        if on[i] {
            (sin[i], cos[i]) = libm::sincosf(x[i]);
        }
    }
    (sin, cos)
}

/// libm's `sincosf` (FreeBSD's `s_sinf.c` with `k_sinf`, `k_cosf`) for non-negative angles up
/// to 9π/4, four `f64` lanes at a time.
#[cfg(target_arch = "x86_64")]
mod sincos_avx2 {
    use std::arch::x86_64::*;

    /// The largest angle's bits that the cases below cover (about 9π/4); beyond it libm reduces
    /// the argument by other means.
    pub(super) const LAST_CASE: u32 = 0x40e2_31d5;
    /// Where each of libm's cases ends, as the angle's bits: below 2^-12 the angle is its own
    /// sine; then about π/4, 3π/4, 5π/4 and 7π/4.
    const TINY: u32 = 0x3980_0000;
    const ENDS: [u32; 4] = [0x3f49_0fda, 0x4016_cbe3, 0x407b_53d1, 0x40af_eddf];
    /// Multiples of π/2 in `f64`, as libm rounds them.
    const PI_2: f64 = 0.5 * std::f64::consts::PI;
    /// `m 2^-e`, the form libm's comments give its coefficients in (exact: `m` has 53 bits).
    const fn p(m: u64, e: u32) -> f64 {
        m as f64 / (1u128 << e) as f64
    }

    /// `sincosf` of eight angles, each in `[+0, 9π/4]` (bits at most [`LAST_CASE`]).
    #[target_feature(enable = "avx2")]
    #[inline]
    pub(super) fn sincos(x: [f32; 8]) -> ([f32; 8], [f32; 8]) {
        // SAFETY: eight f32s, read unaligned.
        let all = unsafe { _mm256_loadu_ps(x.as_ptr()) };
        let (s_low, c_low) = half(_mm256_castps256_ps128(all));
        let (s_high, c_high) = half(_mm256_extractf128_ps::<1>(all));
        let (mut sin, mut cos) = ([0.0f32; 8], [0.0f32; 8]);
        // SAFETY: four f32s written at each of 0 and 4 of eight.
        unsafe {
            _mm_storeu_ps(sin.as_mut_ptr(), s_low);
            _mm_storeu_ps(sin.as_mut_ptr().add(4), s_high);
            _mm_storeu_ps(cos.as_mut_ptr(), c_low);
            _mm_storeu_ps(cos.as_mut_ptr().add(4), c_high);
        }
        (sin, cos)
    }

    /// Four angles of [`sincos`].
    #[target_feature(enable = "avx2")]
    #[inline]
    fn half(x: __m128) -> (__m128, __m128) {
        let (sub, d) = (_mm256_sub_pd, _mm256_set1_pd);
        let xd = _mm256_cvtps_pd(x);
        // Each lane's case: the first end at or above its angle (angles are non-negative, so
        // their bits order as they do).
        let at_most = |end: u32| _mm256_cmp_pd::<_CMP_LE_OQ>(xd, d(f32::from_bits(end) as f64));
        let [c0, c1, c2, c3] = ENDS.map(at_most);
        // The reduced argument, as libm forms it in each case.
        let y = [xd, sub(d(PI_2), xd), sub(xd, d(2.0 * PI_2)), sub(xd, d(3.0 * PI_2)), sub(xd, d(4.0 * PI_2))];
        let pick = |v: [__m256d; 5]| {
            let v34 = _mm256_blendv_pd(v[4], v[3], c3);
            let v234 = _mm256_blendv_pd(v34, v[2], c2);
            let v1234 = _mm256_blendv_pd(v234, v[1], c1);
            _mm256_blendv_pd(v1234, v[0], c0)
        };
        let y = pick(y);
        let (ks, kc) = (k_sin(y), k_cos(y));
        // Cases 1 and 3 swap the two; cases 2 and 3 negate the sine, case 2 the cosine.
        let [c0, c1, c2, c3] = ENDS.map(|end| _mm_cmp_ps::<_CMP_LE_OQ>(x, _mm_set1_ps(f32::from_bits(end))));
        let (one, two, three) = (_mm_andnot_ps(c0, c1), _mm_andnot_ps(c1, c2), _mm_andnot_ps(c2, c3));
        let swapped = _mm_or_ps(one, three);
        let (s, c) = (_mm_blendv_ps(ks, kc, swapped), _mm_blendv_ps(kc, ks, swapped));
        let sign = _mm_set1_ps(-0.0);
        let s = _mm_xor_ps(s, _mm_and_ps(_mm_or_ps(two, three), sign));
        let c = _mm_xor_ps(c, _mm_and_ps(two, sign));
        // Below 2^-12 the sine is the angle and the cosine one.
        let tiny = _mm_castsi128_ps(_mm_cmplt_epi32(_mm_castps_si128(x), _mm_set1_epi32(TINY as i32)));
        (_mm_blendv_ps(s, x, tiny), _mm_blendv_ps(c, _mm_set1_ps(1.0), tiny))
    }

    /// libm's `k_sinf`: sine on `[-π/4, π/4]`, rounded to `f32`.
    #[target_feature(enable = "avx2")]
    #[inline]
    fn k_sin(x: __m256d) -> __m128 {
        const S: [f64; 4] = [
            -p(0x15_5555_54cb_ac77, 55),
            p(0x11_1110_896e_fbb2, 59),
            -p(0x1a_00f9_e2ca_e774, 65),
            p(0x16_cd87_8c3b_46a7, 71),
        ];
        let (add, mul, d) = (_mm256_add_pd, _mm256_mul_pd, _mm256_set1_pd);
        let z = mul(x, x);
        let w = mul(z, z);
        let r = add(d(S[2]), mul(z, d(S[3])));
        let s = mul(z, x);
        _mm256_cvtpd_ps(add(add(x, mul(s, add(d(S[0]), mul(z, d(S[1]))))), mul(mul(s, w), r)))
    }

    /// libm's `k_cosf`: cosine on `[-π/4, π/4]`, rounded to `f32`.
    #[target_feature(enable = "avx2")]
    #[inline]
    fn k_cos(x: __m256d) -> __m128 {
        const C: [f64; 4] = [
            -p(0x1f_ffff_fd0c_5e81, 54),
            p(0x15_5553_e105_3a42, 57),
            -p(0x16_c087_e80f_1e27, 62),
            p(0x19_9342_e0ee_5069, 68),
        ];
        let (add, mul, d) = (_mm256_add_pd, _mm256_mul_pd, _mm256_set1_pd);
        let z = mul(x, x);
        let w = mul(z, z);
        let r = add(d(C[2]), mul(z, d(C[3])));
        _mm256_cvtpd_ps(add(add(add(d(1.0), mul(z, d(C[0]))), mul(w, d(C[1]))), mul(mul(w, z), r)))
    }
}

/// `row(0)`, ..., `row(rows - 1)`, in order, computed on as many plain threads as the calling
/// rayon pool has: a table's rows (the BSDFs' albedo tables, the RGB-to-spectrum table), each
/// made as one thread alone would make it, so the same bits on any number of threads. Not on
/// the pool itself: a table is made inside a `OnceLock`, and a pool thread waiting there for its
/// rows could steal a render task that needs the same table, and wait on itself.
pub(crate) fn rows_in_parallel<T: Send>(rows: usize, row: impl Fn(usize) -> T + Sync) -> Vec<T> {
    let threads = rayon::current_num_threads().clamp(1, rows.max(1));
    let per = rows.div_ceil(threads);
    std::thread::scope(|s| {
        let row = &row;
        let parts: Vec<_> = (0..threads)
            .map(|k| s.spawn(move || (k * per..((k + 1) * per).min(rows)).map(row).collect::<Vec<T>>()))
            .collect();
        parts.into_iter().flat_map(|p| p.join().unwrap_or_else(|panic| std::panic::resume_unwind(panic))).collect()
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lanes::Lanes;

    /// Checks `sincos_lanes` against `libm::sincosf` on `angles`, eight at a time, at every
    /// width this CPU runs.
    fn agrees_with_libm(angles: impl Iterator<Item = f32>) -> usize {
        let angles: Vec<f32> = angles.collect();
        for lanes in Lanes::ALL.into_iter().filter(|l| l.run_here()) {
            for chunk in angles.chunks(8) {
                let mut x = [0.0f32; 8];
                x[..chunk.len()].copy_from_slice(chunk);
                let on = std::array::from_fn(|i| i < chunk.len());
                let (sin, cos) = sincos_lanes(lanes, x, on);
                for i in 0..chunk.len() {
                    let (s, c) = libm::sincosf(x[i]);
                    assert_eq!(
                        (sin[i].to_bits(), cos[i].to_bits()),
                        (s.to_bits(), c.to_bits()),
                        "{lanes}: sincos of {} (bits {:#x})",
                        x[i],
                        x[i].to_bits()
                    );
                }
            }
        }
        angles.len()
    }

    /// Every angle the wave turns a cosine-weighted direction by (`2π u`, for each of the 2^24
    /// values a sampler's `u` takes), every 37th float up to 9π/4, and the floats about each
    /// end of libm's cases, all bit for bit.
    #[test]
    fn sines_and_cosines_of_eight_angles_are_libms() {
        let wave = (0..1u32 << 24).map(|k| 2.0 * std::f32::consts::PI * (k as f32 / (1u32 << 24) as f32));
        assert_eq!(agrees_with_libm(wave), 1 << 24);
        agrees_with_libm((0..=0x40e2_31d5u32).step_by(37).map(f32::from_bits));
        let ends = [0, 0x3980_0000, 0x3f49_0fda, 0x4016_cbe3, 0x407b_53d1, 0x40af_eddf, 0x40e2_31d5u32];
        agrees_with_libm(ends.iter().flat_map(|&e| e.saturating_sub(3)..e + 4).map(f32::from_bits));
    }

    /// Angles outside the lanes' range (negative, beyond 9π/4, not finite) take libm's own call,
    /// whichever lane they are in, and lanes left out do not matter.
    #[test]
    fn other_angles_take_libms_call() {
        let odd = [-0.0, -1.0, 7.1, 1e6, f32::INFINITY, f32::NAN, -f32::MIN_POSITIVE, 3.0e38];
        for &a in &odd {
            for at in 0..8 {
                let mut x: [f32; 8] = std::array::from_fn(|i| 0.1 + i as f32);
                x[at] = a;
                agrees_with_libm(x.into_iter());
            }
        }
        for lanes in Lanes::ALL.into_iter().filter(|l| l.run_here()) {
            let x = [1.0, f32::NAN, 2.0, -5.0, 3.0, 1e9, 4.0, 5.0];
            let on = [true, false, true, false, true, false, true, true];
            let (sin, cos) = sincos_lanes(lanes, x, on);
            for i in (0..8).filter(|&i| on[i]) {
                assert_eq!((sin[i], cos[i]), libm::sincosf(x[i]), "{lanes}: lane {i}");
            }
        }
    }
}
