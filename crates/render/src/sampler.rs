//! Sample generation. Every number is a pure function of (render seed, pixel, sample index,
//! dimension), so a pixel's samples do not depend on tiles, threads, workers or order (invariant 1).

use crate::lanes::Lanes;
use sobol_burley::parts::{Int4, hash, hash_int4, owen_scramble_int4_rev, owen_scramble_rev, sobol_int4_rev};
use std::sync::LazyLock;

/// Which low-level generator produces the sample values.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum SamplerKind {
    /// Counter-based hashing: independent uniform numbers.
    Independent,
    /// Owen-scrambled Sobol (Burley 2020), decorrelated per pixel by the scramble seed.
    Sobol,
}

impl SamplerKind {
    pub fn name(self) -> &'static str {
        match self {
            SamplerKind::Independent => "independent",
            SamplerKind::Sobol => "sobol",
        }
    }
}

/// Bounces whose light and BSDF dimensions come from Sobol under the Sobol sampler.
const SOBOL_BOUNCES: u32 = 4;

/// Sample indices per Sobol block (sobol_burley's limit).
const SOBOL_INDEX_BITS: u32 = 16;
const SOBOL_INDEX_MASK: u32 = (1 << SOBOL_INDEX_BITS) - 1;

/// Dimensions reserved for the camera ray (pixel position and two spares).
const CAMERA_SET: u32 = 0;
/// Dimensions handed out per bounce.
pub const DIMS_PER_BOUNCE: usize = 8;

/// For Sobol set 0 (the camera's, and every padded set's), per
/// nibble of the 16 index bits (most significant of the reversed index first) and per nibble
/// value, the Sobol point of that nibble alone. A Sobol point is linear over GF(2) in its index
/// bits, so the XOR of an index's four entries is `sobol_int4_rev` of the index. 1 KiB.
static SOBOL_TABLE: LazyLock<[[Int4; 16]; 4]> =
    LazyLock::new(|| std::array::from_fn(|k| std::array::from_fn(|v| sobol_int4_rev((v as u32) << (28 - 4 * k), 0))));

/// Scramble constants per dimension of a Sobol set (sobol_burley's).
const SET_SCRAMBLE: [u32; 4] = [0x912f_69ba, 0x174f_18ab, 0x691e_72ca, 0xb40c_c1b8];

/// The sample stream of one (pixel, sample index).
#[derive(Clone, Copy)]
pub struct PixelSampler {
    kind: SamplerKind,
    key: u64,
    scramble: u32,
    index: u32,
}

/// What all samples of one pixel share (its key; per block of 2^16 sample indices its
/// scramble), worked out once per pixel for the samples the pixel loop takes in turn.
/// [`PixelSeeds::sampler`] gives the same sampler as [`PixelSampler::new`].
pub struct PixelSeeds {
    kind: SamplerKind,
    key: u64,
    /// The block whose scramble follows (`u32::MAX`: none yet).
    block: u32,
    scramble: u32,
    /// The camera set's seeds for the scramble they are of, once [`PixelSeeds::camera`] asks.
    camera: Option<(u32, (u32, Int4))>,
}

impl PixelSeeds {
    pub fn new(kind: SamplerKind, render_seed: u64, pixel: (u32, u32)) -> Self {
        let key = mix64(render_seed ^ mix64(((pixel.1 as u64) << 32) | pixel.0 as u64));
        Self { kind, key, block: u32::MAX, scramble: 0, camera: None }
    }

    /// The sampler of sample `index` of this pixel.
    pub fn sampler(&mut self, index: u32) -> PixelSampler {
        let block = index >> SOBOL_INDEX_BITS;
        if block != self.block {
            // sobol_burley covers 2^16 indices; each further block of 2^16 gets its own
            // scramble, an independent randomisation of the same point set (still unbiased).
            self.block = block;
            self.scramble = (mix64(self.key ^ (block as u64).wrapping_mul(0xD6E8_FEB8_6659_FD93)) >> 32) as u32;
        }
        PixelSampler { kind: self.kind, key: self.key, scramble: self.scramble, index }
    }

    /// Sample `index`'s sampler and its camera numbers (those of [`PixelSampler::camera`]), the
    /// block's camera seeds worked out once for the pixel's samples one by one. (The tile loop
    /// works out eight samples' numbers side by side instead: [`camera_lanes`].)
    pub fn camera(&mut self, index: u32) -> (PixelSampler, [f32; 4]) {
        let sampler = self.sampler(index);
        let numbers = match self.kind {
            SamplerKind::Sobol => sobol_camera(index, cached_camera_seeds(&mut self.camera, self.scramble)),
            SamplerKind::Independent => sampler.camera(),
        };
        (sampler, numbers)
    }
}

/// The camera seeds of `scramble`, from `cache` where they are of that scramble, else worked out
/// and kept there.
fn cached_camera_seeds(cache: &mut Option<(u32, (u32, Int4))>, scramble: u32) -> (u32, Int4) {
    match *cache {
        Some((of, seeds)) if of == scramble => seeds,
        _ => cache.insert((scramble, camera_seeds(scramble))).1,
    }
}

/// The camera set's seeds for a block's scramble: the index shuffle's, and the Owen scramble's
/// of each of the four dimensions (sobol_burley's `sample_4d` for [`CAMERA_SET`]).
fn camera_seeds(scramble: u32) -> (u32, Int4) {
    let index_seed = hash(scramble ^ 0x79c6_8e4a);
    let dims =
        Int4::from([scramble.wrapping_mul(0x9c8f_2d3b); 4]) ^ Int4::from([CAMERA_SET; 4]) ^ Int4::from(SET_SCRAMBLE);
    (index_seed, hash_int4(dims))
}

/// `sobol_burley::sample_4d(index, CAMERA_SET, scramble)`, bit for bit, from the block's
/// [`camera_seeds`] and with the Sobol point from [`SOBOL_TABLE`] (four lookups instead of a
/// loop over the index's bits).
fn sobol_camera(index: u32, (index_seed, dims): (u32, Int4)) -> [f32; 4] {
    let shuffled_rev = owen_scramble_rev((index & SOBOL_INDEX_MASK).reverse_bits(), index_seed);
    owen_scramble_int4_rev(table_point(shuffled_rev), dims).reverse_bits().to_f32_norm()
}

impl PixelSampler {
    pub fn new(kind: SamplerKind, render_seed: u64, pixel: (u32, u32), index: u32) -> Self {
        PixelSeeds::new(kind, render_seed, pixel).sampler(index)
    }

    /// Four dimensions for the camera ray: `[px, py, spare, spare]`.
    pub fn camera(&self) -> [f32; 4] {
        match self.kind {
            SamplerKind::Sobol => sobol_camera(self.index, camera_seeds(self.scramble)),
            SamplerKind::Independent => self.hashed(0x8000_0000 | CAMERA_SET),
        }
    }

    /// Eight dimensions for bounce `bounce` (0 = first surface hit): `[0]` chooses the light
    /// where a scene has too many to choose with `[1]`, `[1], [2]` place the light point, `[3]`
    /// chooses the BSDF lobe, `[4], [5]` the direction in it, `[6]` plays roulette, `[7]` is
    /// spare. Under the Sobol sampler the first bounces take them from two padded Sobol sets,
    /// one for the light and one for the BSDF, so that every number a path uses on them is
    /// stratified over every power-of-two run of samples; deeper bounces hash (they weigh
    /// little in the image, and stratification there measured no gain).
    pub fn bounce(&self, bounce: u32) -> [f32; DIMS_PER_BOUNCE] {
        match self.kind {
            SamplerKind::Sobol if bounce < SOBOL_BOUNCES => {
                let [l0, l1, l2, l3] = self.padded_set(2 * bounce + 1);
                let [b0, b1, b2, b3] = self.padded_set(2 * bounce + 2);
                [l2, l0, l1, b2, b0, b1, b3, l3]
            }
            _ => {
                let stream = if bounce < SOBOL_BOUNCES { 0x8000_0000 | (1 + bounce) } else { 0x4000_0000 | bounce };
                let s = self.hashed(stream);
                let h = self.hashed(bounce);
                [h[0], s[0], s[1], h[1], s[2], s[3], h[2], h[3]]
            }
        }
    }

    /// A padded Sobol set (Burley 2020, section 4; pbrt-v4's `PaddedSobolSampler`): Sobol's
    /// dimensions 0 to 3 with the index shuffled and the values Owen-scrambled by seeds of this
    /// pixel's set `set` alone. Each power-of-two run of samples is then a (0,m,2)-net in its
    /// first two numbers (which form a (0,2)-sequence) and stratified in each of the other two.
    /// Numbers taken from one higher-dimensional Sobol set, or hashed, are not:
    /// - Light sampling chooses the emitter with `[1]` and reuses the rest of it to place the
    ///   point, which assumes the pair evenly stratified. With Sobol's dimensions 4 and 5 there,
    ///   next-event estimation in a closed sphere of 80 emitters came out noisier with Sobol than
    ///   with independent numbers (per-pixel RMSE 0.056 against 0.041; 0.038 with a padded pair).
    /// - The BSDF direction came from dimensions 6 and 7, whose first 16 points put 4 in one
    ///   elementary cell. On WaterBottle under a constant environment the error then stalled
    ///   between 16 and 32 spp (RMSE 0.0350, 0.0307, then 0.0070 at 64); padded, it falls
    ///   steadily (0.0202, 0.0113, 0.0067), and the Cornell box's error at 16 and 32 spp drops
    ///   12-15 %.
    /// - The discrete choices were hashed. Stratified, the RMSE with 320 emitters (more than
    ///   `[1]` chooses among, so `[0]` does) halves at 16-128 spp, and on MetalRoughSpheres,
    ///   where `[3]` chooses between a dielectric's specular and diffuse lobes, it drops 21-23 %
    ///   (README, "Benchmarks").
    fn padded_set(&self, set: u32) -> [f32; 4] {
        let seed = hash(self.scramble ^ set.wrapping_mul(0x9e37_79b9) ^ 0x5bd1_e995);
        let index_rev = owen_scramble_rev((self.index & SOBOL_INDEX_MASK).reverse_bits(), seed);
        let sobol = table_point(index_rev);
        let scramble = Int4::from([hash(seed ^ 0x2c1b_3c6d); 4]) ^ Int4::from(SET_SCRAMBLE);
        owen_scramble_int4_rev(sobol, hash_int4(scramble)).reverse_bits().to_f32_norm()
    }

    /// Four independent uniforms for stream `stream` of this (pixel, index).
    fn hashed(&self, stream: u32) -> [f32; 4] {
        let base = mix64(self.key ^ mix64(((stream as u64) << 32) | self.index as u64));
        let next = mix64(base);
        [unit_f32(base), unit_f32(base << 24), unit_f32(next), unit_f32(next << 24)]
    }
}

/// Samplers side by side: [`bounce_lanes`] works on this many at once.
pub(crate) const LANES: usize = 8;

/// [`PixelSampler::bounce`] for eight samples at once: lane `i` gets `samplers[i].bounce(
/// bounce[i])`, bit for bit, where `on[i]` (other lanes' numbers are of no use), with `[k][i]`
/// its number `k`. Where `lanes` has AVX2 (it must run on this CPU), a Sobol sampler's first
/// bounces work out their two padded sets in AVX2 registers, eight lanes at once; any other
/// lane takes its sampler's own call.
#[inline(always)]
pub(crate) fn bounce_lanes(
    lanes: Lanes,
    samplers: &[PixelSampler; LANES],
    bounce: &[u32; LANES],
    on: [bool; LANES],
) -> [[f32; LANES]; DIMS_PER_BOUNCE] {
    let mut u = [[0.0f32; LANES]; DIMS_PER_BOUNCE];
    // The lanes whose numbers AVX2 works out: a Sobol sampler's padded bounces.
    let padded: [bool; LANES] = match cfg!(target_arch = "x86_64") && lanes != Lanes::Portable {
        true => std::array::from_fn(|i| on[i] & (samplers[i].kind == SamplerKind::Sobol) & (bounce[i] < SOBOL_BOUNCES)),
        false => [false; LANES],
    };
    #[cfg(target_arch = "x86_64")]
    if padded.contains(&true) {
        let scramble = samplers.map(|s| s.scramble);
        let index = samplers.map(|s| s.index & SOBOL_INDEX_MASK);
        // The light's set, then the BSDF's, with the slots `bounce` gives their numbers.
        for (first, slots) in [(1, [1, 2, 0, 7]), (2, [4, 5, 3, 6])] {
            let set = bounce.map(|b| 2 * b + first);
            // SAFETY: `lanes` has AVX2 (no lane is padded otherwise) and runs on this CPU (the
            // caller's promise).
            let numbers = unsafe { avx2::padded_sets(&scramble, &index, &set) };
            for (d, &k) in slots.iter().enumerate() {
                u[k] = numbers[d];
            }
        }
    }
    for i in 0..LANES {
        if on[i] && !padded[i] {
            let numbers = samplers[i].bounce(bounce[i]);
            for k in 0..DIMS_PER_BOUNCE {
                u[k][i] = numbers[k];
            }
        }
    }
    u
}

/// [`PixelSampler::camera`] for eight samples at once: lane `i` gets `samplers[i].camera()`,
/// bit for bit. Where `lanes` has AVX2 (it must run on this CPU) and every lane is a Sobol
/// sampler's, their camera sets are worked out in AVX2 registers, eight at once; otherwise lane
/// by lane, each block's seeds worked out once for the lanes in a row that share it (a pixel's
/// samples).
#[inline(always)]
pub fn camera_lanes(lanes: Lanes, samplers: &[PixelSampler; LANES]) -> [[f32; 4]; LANES] {
    #[cfg(target_arch = "x86_64")]
    if lanes != Lanes::Portable && samplers.iter().all(|s| s.kind == SamplerKind::Sobol) {
        assert!(lanes.run_here(), "{lanes} does not run on this CPU");
        let scramble = samplers.map(|s| s.scramble);
        let index = samplers.map(|s| s.index & SOBOL_INDEX_MASK);
        // SAFETY: `lanes` has AVX2 and runs on this CPU (checked above).
        let numbers = unsafe { avx2::camera_sets(&scramble, &index) };
        return std::array::from_fn(|i| numbers.map(|d| d[i]));
    }
    let mut seeds = None;
    samplers.map(|s| match s.kind {
        SamplerKind::Sobol => sobol_camera(s.index, cached_camera_seeds(&mut seeds, s.scramble)),
        SamplerKind::Independent => s.camera(),
    })
}

/// [`SOBOL_TABLE`] by dimension first (`[d][k][v]`), for the lanes' lookups.
static SOBOL_LANES: LazyLock<[[[u32; 16]; 4]; 4]> = LazyLock::new(|| {
    let table = &*SOBOL_TABLE;
    std::array::from_fn(|d| std::array::from_fn(|k| std::array::from_fn(|v| <[u32; 4]>::from(table[k][v])[d])))
});

#[cfg(target_arch = "x86_64")]
mod avx2 {
    use super::{CAMERA_SET, LANES, SET_SCRAMBLE, SOBOL_LANES};
    use std::arch::x86_64::*;

    /// [`super::PixelSampler::padded_set`] in eight lanes: lane `i` of `[d]` is number `d` of
    /// set `set[i]` of the sampler with scramble `scramble[i]` and masked index `index[i]`.
    #[target_feature(enable = "avx2")]
    #[inline]
    pub(super) fn padded_sets(scramble: &[u32; LANES], index: &[u32; LANES], set: &[u32; LANES]) -> [[f32; LANES]; 4] {
        let (xor, splat) = (_mm256_xor_si256, |c: u32| _mm256_set1_epi32(c as i32));
        let seed =
            hash(xor(xor(load(scramble), _mm256_mullo_epi32(load(set), splat(0x9e37_79b9))), splat(0x5bd1_e995)));
        let base = hash(xor(seed, splat(0x2c1b_3c6d)));
        sets(load(index), seed, SET_SCRAMBLE.map(|d| hash(xor(base, splat(d)))))
    }

    /// [`super::camera_seeds`] and [`super::sobol_camera`] in eight lanes: lane `i` of `[d]` is
    /// number `d` of the camera set of the sampler with scramble `scramble[i]` and masked index
    /// `index[i]`.
    #[target_feature(enable = "avx2")]
    #[inline]
    pub(super) fn camera_sets(scramble: &[u32; LANES], index: &[u32; LANES]) -> [[f32; LANES]; 4] {
        let (xor, splat) = (_mm256_xor_si256, |c: u32| _mm256_set1_epi32(c as i32));
        let scramble = load(scramble);
        let index_seed = hash(xor(scramble, splat(0x79c6_8e4a)));
        let base = xor(_mm256_mullo_epi32(scramble, splat(0x9c8f_2d3b)), splat(CAMERA_SET));
        sets(load(index), index_seed, SET_SCRAMBLE.map(|d| hash(xor(base, splat(d)))))
    }

    /// Sobol's dimensions 0 to 3 in eight lanes: lane `i` of `[d]` is dimension `d` of the
    /// point whose masked index `index[i]` is shuffled by `index_seed[i]`, Owen-scrambled by
    /// `dims[d][i]`. Integer operations throughout, then `u32_to_f32_norm`'s exact subtraction:
    /// the same bits as the scalar code.
    #[target_feature(enable = "avx2")]
    #[inline]
    fn sets(index: __m256i, index_seed: __m256i, dims: [__m256i; 4]) -> [[f32; LANES]; 4] {
        let (xor, splat) = (_mm256_xor_si256, |c: u32| _mm256_set1_epi32(c as i32));
        let shuffled = owen_scramble(reverse_bits(index), index_seed);
        // The Sobol point from the table, a nibble of `shuffled` at a time: each 16-entry row
        // is two registers, `VPERMD` looks up both halves, and the nibble's top bit chooses.
        let table = &*SOBOL_LANES;
        let mut sobol = [_mm256_setzero_si256(); 4];
        for k in 0..4 {
            let nibble = _mm256_and_si256(_mm256_srl_epi32(shuffled, _mm_cvtsi32_si128(28 - 4 * k as i32)), splat(0xf));
            let upper = _mm256_castsi256_ps(_mm256_slli_epi32::<28>(nibble));
            for (sobol, rows) in sobol.iter_mut().zip(table) {
                let row = &rows[k];
                // SAFETY: sixteen u32s, read unaligned as two halves.
                let (low, high) = unsafe { (load8(row.as_ptr()), load8(row.as_ptr().add(8))) };
                let (low, high) = (_mm256_permutevar8x32_epi32(low, nibble), _mm256_permutevar8x32_epi32(high, nibble));
                let entry = _mm256_blendv_ps(_mm256_castsi256_ps(low), _mm256_castsi256_ps(high), upper);
                *sobol = xor(*sobol, _mm256_castps_si256(entry));
            }
        }
        std::array::from_fn(|d| {
            let n = reverse_bits(owen_scramble(sobol[d], dims[d]));
            // `u32_to_f32_norm`: the top 23 bits as a mantissa of [1, 2), less one (exact).
            let one_to_two = _mm256_castsi256_ps(_mm256_or_si256(_mm256_srli_epi32::<9>(n), splat(0x3f80_0000)));
            let mut out = [0.0f32; LANES];
            // SAFETY: eight f32s, written unaligned.
            unsafe { _mm256_storeu_ps(out.as_mut_ptr(), _mm256_sub_ps(one_to_two, _mm256_set1_ps(1.0))) };
            out
        })
    }

    /// Eight u32s.
    #[target_feature(enable = "avx2")]
    #[inline]
    fn load(v: &[u32; LANES]) -> __m256i {
        // SAFETY: eight u32s, read unaligned.
        unsafe { load8(v.as_ptr()) }
    }

    /// Eight u32s from `p`, unaligned.
    ///
    /// # Safety
    /// `p` must point to eight readable u32s.
    #[target_feature(enable = "avx2")]
    #[inline]
    unsafe fn load8(p: *const u32) -> __m256i {
        // SAFETY: as the caller promises.
        unsafe { _mm256_loadu_si256(p.cast()) }
    }

    /// `sobol_burley::parts::hash` in each lane.
    #[target_feature(enable = "avx2")]
    #[inline]
    fn hash(n: __m256i) -> __m256i {
        let (xor, splat) = (_mm256_xor_si256, |c: u32| _mm256_set1_epi32(c as i32));
        let n = xor(n, splat(0xe6fe_3beb));
        let n = xor(n, _mm256_srli_epi32::<16>(n));
        let n = _mm256_mullo_epi32(n, splat(0x7feb_352d));
        let n = xor(n, _mm256_srli_epi32::<15>(n));
        let n = _mm256_mullo_epi32(n, splat(0x846c_a68b));
        xor(n, _mm256_srli_epi32::<16>(n))
    }

    /// `sobol_burley::parts::owen_scramble_rev` in each lane.
    #[target_feature(enable = "avx2")]
    #[inline]
    fn owen_scramble(n: __m256i, scramble: __m256i) -> __m256i {
        let (xor, mul, splat) = (_mm256_xor_si256, _mm256_mullo_epi32, |c: u32| _mm256_set1_epi32(c as i32));
        let n = xor(n, mul(n, splat(0x3d20_adea)));
        let n = _mm256_add_epi32(n, scramble);
        let n = mul(n, _mm256_or_si256(_mm256_srli_epi32::<16>(scramble), splat(1)));
        let n = xor(n, mul(n, splat(0x0552_6c56)));
        xor(n, mul(n, splat(0x53a2_2864)))
    }

    /// `u32::reverse_bits` in each lane: the bytes reversed, then each byte's nibbles swapped
    /// and reversed by table.
    #[target_feature(enable = "avx2")]
    #[inline]
    fn reverse_bits(n: __m256i) -> __m256i {
        let bytes = _mm256_setr_epi8(
            3, 2, 1, 0, 7, 6, 5, 4, 11, 10, 9, 8, 15, 14, 13, 12, 3, 2, 1, 0, 7, 6, 5, 4, 11, 10, 9, 8, 15, 14, 13, 12,
        );
        let n = _mm256_shuffle_epi8(n, bytes);
        // Each nibble value reversed, as the low nibble and as the high one.
        let low: [i8; 16] = std::array::from_fn(|v| ((v as u8).reverse_bits() >> 4) as i8);
        let high = low.map(|r| ((r as u8) << 4) as i8);
        let table = |t: [i8; 16]| {
            // SAFETY: sixteen bytes, read unaligned.
            let half = unsafe { _mm_loadu_si128(t.as_ptr().cast()) };
            _mm256_broadcastsi128_si256(half)
        };
        let nibble = _mm256_set1_epi8(0x0f);
        let lo = _mm256_and_si256(n, nibble);
        let hi = _mm256_and_si256(_mm256_srli_epi16::<4>(n), nibble);
        _mm256_or_si256(_mm256_shuffle_epi8(table(high), lo), _mm256_shuffle_epi8(table(low), hi))
    }
}

/// `sobol_int4_rev(index_rev, 0)` from [`SOBOL_TABLE`]: the XOR of the points of the reversed
/// index's four nibbles.
fn table_point(index_rev: u32) -> Int4 {
    let nibble = |k: usize| (index_rev >> (28 - 4 * k)) as usize & 0xf;
    let table = &*SOBOL_TABLE;
    table[0][nibble(0)] ^ table[1][nibble(1)] ^ table[2][nibble(2)] ^ table[3][nibble(3)]
}

/// SplitMix64's finaliser: a bijective 64-bit mixer with full avalanche.
pub fn mix64(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// The top 24 bits of `h` as a float in `[0, 1)`.
pub(crate) fn unit_f32(h: u64) -> f32 {
    (h >> 40) as f32 * (1.0 / (1u64 << 24) as f32)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn samples_are_pure_functions_of_pixel_and_index() {
        for kind in [SamplerKind::Independent, SamplerKind::Sobol] {
            let a = PixelSampler::new(kind, 7, (3, 4), 11).bounce(2);
            let b = PixelSampler::new(kind, 7, (3, 4), 11).bounce(2);
            assert_eq!(a, b);
            let c = PixelSampler::new(kind, 7, (4, 3), 11).bounce(2);
            assert_ne!(a, c, "{kind:?}: transposed pixels must not share samples");
        }
    }

    #[test]
    fn the_camera_set_equals_sobol_burley_bit_for_bit() {
        // The table and the hoisted index shuffle must not change a single sample.
        for (pixel, index) in [((0, 0), 0), ((3, 9), 1), ((17, 2), 255), ((5, 5), 40_000), ((9, 1), (1 << 16) - 1)] {
            for i in index..index + 64 {
                let sampler = PixelSampler::new(SamplerKind::Sobol, 7, pixel, i);
                let expected = sobol_burley::sample_4d(i & SOBOL_INDEX_MASK, CAMERA_SET, sampler.scramble);
                assert_eq!(sampler.camera().map(f32::to_bits), expected.map(f32::to_bits), "index {i}");
            }
        }
    }

    /// Over every aligned run of 2^m samples, the light pair and the BSDF pair are each a
    /// (0,m,2)-net (for each split of m into a + b, the 2^a x 2^b grid has exactly one point per
    /// cell), and each single number `[0], [3], [6], [7]` has one value in each of 2^m equal
    /// intervals. (Sobol's dimensions 4 and 5, and 6 and 7, the pairs before padding, are not
    /// nets; hashed numbers are not stratified.)
    #[test]
    fn bounce_numbers_are_stratified_over_power_of_two_runs() {
        let m = 6;
        for (pixel, start) in [((0, 0), 0), ((12, 7), 64), ((3, 30), 4096)] {
            for bounce in 0..SOBOL_BOUNCES {
                let samples: Vec<_> = (start..start + (1 << m))
                    .map(|i| PixelSampler::new(SamplerKind::Sobol, 3, pixel, i).bounce(bounce))
                    .collect();
                // (what, dimension across, its cells, dimension down, its cells): the 2-D nets'
                // splits, then the single numbers as 2^m x 1 grids.
                let pairs = [("light pair", 1, 2), ("bsdf pair", 4, 5)]
                    .into_iter()
                    .flat_map(|(what, x, y)| (0..=m).map(move |a| (what, x, a, y, m - a)));
                let singles = [0, 3, 6, 7].into_iter().map(|k| ("single number", k, m, k, 0));
                for (what, x, a, y, b) in pairs.chain(singles) {
                    let mut seen = vec![false; 1 << m];
                    for u in &samples {
                        let cell = ((u[y] * (1u32 << b) as f32) as usize) << a | (u[x] * (1u32 << a) as f32) as usize;
                        assert!(
                            !seen[cell],
                            "{what} [{x}] [{y}], bounce {bounce}, pixel {pixel:?}: two points in a 2^{a} x 2^{b} cell"
                        );
                        seen[cell] = true;
                    }
                }
            }
        }
    }

    /// Every number of a bounce is shuffled apart from the others, so they are uncorrelated:
    /// over 4096 samples of one pixel each correlation has sigma 1/64; 0.07 is over four sigma
    /// (two numbers made alike would give 1, or two sharing a shuffle 0.75).
    #[test]
    fn the_numbers_of_a_bounce_are_uncorrelated() {
        let n = 4096;
        let samples: Vec<_> = (0..n).map(|i| PixelSampler::new(SamplerKind::Sobol, 3, (5, 6), i).bounce(1)).collect();
        let mean = |k: usize| samples.iter().map(|u| u[k] as f64).sum::<f64>() / n as f64;
        let cov = |x: usize, y: usize| {
            let (mx, my) = (mean(x), mean(y));
            samples.iter().map(|u| (u[x] as f64 - mx) * (u[y] as f64 - my)).sum::<f64>() / n as f64
        };
        for a in 0..DIMS_PER_BOUNCE {
            for b in a + 1..DIMS_PER_BOUNCE {
                let corr = cov(a, b) / (cov(a, a) * cov(b, b)).sqrt();
                assert!(corr.abs() < 0.07, "dimensions {a} and {b}: correlation {corr}");
            }
        }
    }

    /// A pixel's seeds, worked out once and reused sample after sample, give each sample the
    /// numbers its own `PixelSampler::new` gives, across Sobol's 2^16-sample blocks and back.
    #[test]
    fn pixel_seeds_give_each_sample_its_own_numbers() {
        for kind in [SamplerKind::Independent, SamplerKind::Sobol] {
            let mut seeds = PixelSeeds::new(kind, 9, (7, 2));
            let indices = (0..40).chain((1 << 16) - 20..(1 << 16) + 20).chain([3, 1 << 17, 5, u32::MAX]);
            for index in indices {
                let (a, b) = (seeds.sampler(index), PixelSampler::new(kind, 9, (7, 2), index));
                assert_eq!(a.camera().map(f32::to_bits), b.camera().map(f32::to_bits), "{kind:?} {index}");
                let (c, numbers) = seeds.camera(index);
                assert_eq!(numbers.map(f32::to_bits), b.camera().map(f32::to_bits), "{kind:?} {index}: seeds' camera");
                assert_eq!(
                    c.bounce(0).map(f32::to_bits),
                    b.bounce(0).map(f32::to_bits),
                    "{kind:?} {index}: seeds' camera"
                );
                for bounce in [0, 1, 3, 4, 9] {
                    let bits = |s: &PixelSampler| s.bounce(bounce).map(f32::to_bits);
                    assert_eq!(bits(&a), bits(&b), "{kind:?} {index} bounce {bounce}");
                }
            }
        }
    }

    /// Eight samplers at once give each lane its own sampler's numbers, the camera's and a
    /// bounce's, at every width the CPU runs: Sobol and independent lanes mixed, runs of a
    /// pixel's samples and lanes of different pixels, the padded bounces and the hashed ones
    /// beyond, indices in several 2^16 blocks (and at their ends), and lanes left out.
    #[test]
    fn eight_samplers_at_once_give_each_lane_its_own_numbers() {
        let mut rng = 0x1234_5678_9abc_def0u64;
        let mut next = || {
            rng = mix64(rng);
            rng
        };
        for round in 0..4096 {
            // Half the lanes take the next sample of the lane before's pixel, as a pixel's
            // samples come in the tile loop (across the end of a 2^16 block too).
            let mut before: Option<(SamplerKind, (u32, u32), u32)> = None;
            let samplers: [PixelSampler; LANES] = std::array::from_fn(|_| {
                let r = next();
                let kind = if r % 5 == 0 { SamplerKind::Independent } else { SamplerKind::Sobol };
                let index = match (r >> 8) % 4 {
                    0 => (r >> 16) as u32 % 64,
                    1 => (1 << 16) - 1 - (r >> 16) as u32 % 3,
                    _ => (r >> 32) as u32,
                };
                let pixel = ((r >> 40) as u32 % 97, (r >> 50) as u32 % 89);
                let (kind, pixel, index) = match before {
                    Some((kind, pixel, index)) if r % 2 == 0 => (kind, pixel, index.wrapping_add(1)),
                    _ => (kind, pixel, index),
                };
                before = Some((kind, pixel, index));
                PixelSampler::new(kind, round, pixel, index)
            });
            for lanes in Lanes::ALL.into_iter().filter(|l| l.run_here()) {
                let c = camera_lanes(lanes, &samplers);
                for (i, sampler) in samplers.iter().enumerate() {
                    let own = sampler.camera().map(f32::to_bits);
                    assert_eq!(c[i].map(f32::to_bits), own, "{lanes}: round {round}, lane {i}: camera numbers");
                }
            }
            let bounce: [u32; LANES] = std::array::from_fn(|_| (next() % 7) as u32);
            let on: [bool; LANES] = std::array::from_fn(|_| next() % 8 != 0);
            for lanes in Lanes::ALL.into_iter().filter(|l| l.run_here()) {
                let u = bounce_lanes(lanes, &samplers, &bounce, on);
                for i in (0..LANES).filter(|&i| on[i]) {
                    let lane: [u32; DIMS_PER_BOUNCE] = std::array::from_fn(|k| u[k][i].to_bits());
                    let own = samplers[i].bounce(bounce[i]).map(f32::to_bits);
                    assert_eq!(lane, own, "{lanes}: round {round}, lane {i}, bounce {}", bounce[i]);
                }
            }
        }
    }

    #[test]
    fn sobol_goes_past_its_65536_index_limit() {
        // Indices beyond 2^16 start a new, differently scrambled block instead of failing.
        let a = PixelSampler::new(SamplerKind::Sobol, 1, (2, 3), 5).bounce(0);
        let b = PixelSampler::new(SamplerKind::Sobol, 1, (2, 3), 5 + (1 << 16)).bounce(0);
        assert_ne!(a, b);
        let mut sum = 0.0f64;
        for i in (1u32 << 20) - 4096..(1 << 20) {
            let v = PixelSampler::new(SamplerKind::Sobol, 1, (2, 3), i).camera();
            assert!((0.0..1.0).contains(&v[0]));
            sum += v[0] as f64;
        }
        assert!((sum / 4096.0 - 0.5).abs() < 0.02);
    }

    #[test]
    fn values_lie_in_unit_interval_with_mean_one_half() {
        for kind in [SamplerKind::Independent, SamplerKind::Sobol] {
            let mut sum = 0.0f64;
            let n = 4096;
            for i in 0..n {
                for v in PixelSampler::new(kind, 1, (0, 0), i).bounce(40) {
                    assert!((0.0..1.0).contains(&v));
                    sum += v as f64;
                }
            }
            let mean = sum / (n as f64 * 8.0);
            // The mean of 32768 uniforms has sigma 0.0016; 0.01 is over six sigma.
            assert!((mean - 0.5).abs() < 0.01, "{kind:?} mean {mean}");
        }
    }
}
