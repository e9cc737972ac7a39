//! Scenes of a few dozen triangles: every triangle tested against a ray, sixteen at a time in
//! AVX-512 registers where the CPU has them (eight with AVX2, four elsewhere), instead of a walk
//! down a tree. On such a scene the walk visits most of its few nodes anyway, and what it costs
//! is the branches that steer it; testing every triangle is branch-free work that wide registers
//! do in a few steps. On Mitsuba's 36-triangle Cornell box (`tessera bench stages`) a closest
//! hit takes about half the walk's time and a shadow ray a third.
//!
//! Each lane makes the operations of the walk's triangle test (`RtTriangle::intersect`, in its
//! order, no fused multiply-add), so a distance has the bits the walk gives it. The triangle a
//! ray meets can differ from the walk's in two cases only: two triangles met at exactly the same
//! distance, where the walk takes the first it visits and this takes the lower slot, and a
//! triangle met within the walk's box margin of the ray's origin (1e-4 of the scene's scaled
//! size) whose box the walk skips. All three widths choose the same slot with the same bits, and
//! which scenes are tested whole depends on their size alone, so images do not depend on the CPU.

use super::blocks::TriangleBlock;
use crate::lanes::Lanes;
use glam::Vec4;
use obvhs::ray::Ray;
use obvhs::rt_triangle::RtTriangle;

/// Scenes with at most this many triangles are tested whole rather than walked.
pub(crate) const FLAT_MAX: usize = 64;

/// Triangles side by side in a chunk.
const LANES: usize = 16;

/// Sixteen triangles' planes, per coordinate one row of lanes: a vertex `v0`, the edges `e1 =
/// v0 - v1` and `e2 = v2 - v0`, and their cross product `ng`, as `RtTriangle` stores one. Lanes
/// past the last triangle are zero, which no ray meets (their distance is not a number).
#[repr(C, align(64))]
#[derive(Clone)]
struct Chunk {
    rows: [[f32; LANES]; 12],
}

const V0: usize = 0;
const E1: usize = 3;
const E2: usize = 6;
const NG: usize = 9;

/// Every triangle of a small scene, in chunks of sixteen.
pub(crate) struct Flat {
    chunks: Vec<Chunk>,
    /// How many eight-lane halves of `chunks` hold triangles: eight lanes skip the last chunk's
    /// second half where it holds none (36 triangles take five halves, not six).
    halves: usize,
    /// The same triangles four to a block, for the portable lanes.
    blocks: Vec<TriangleBlock>,
    /// The same triangles one by one (`v0`, `e1`, `e2`, `ng`), for eight rays at a time.
    planes: Vec<[f32; 12]>,
    /// The same triangles two by two, each spread over eight lanes (the first of a pair in the
    /// low half), for eight rays in both halves of an AVX-512 register. Empty below AVX-512.
    pairs: Vec<Chunk>,
    lanes: Lanes,
}

/// Eight rays, one per lane, in the BVH's scaled units: origin and direction as rows, and the
/// far end of each (zero for a lane without a ray: no distance lies in `(0, 0)`).
pub(crate) struct Rays8 {
    pub(crate) o: [[f32; 8]; 3],
    pub(crate) d: [[f32; 8]; 3],
    pub(crate) tmax: [f32; 8],
}

impl Rays8 {
    /// Lane `i`'s ray as `Flat::closest` takes one.
    fn ray(&self, i: usize) -> Ray {
        let row = |r: &[[f32; 8]; 3]| glam::Vec3A::new(r[0][i], r[1][i], r[2][i]);
        Ray::new(row(&self.o), row(&self.d), 0.0, self.tmax[i])
    }
}

impl Flat {
    /// The triangles (in BVH slot order, scaled as the BVH's), tested `lanes` at a time, which
    /// must run on this CPU ([`Lanes::run_here`]).
    pub(crate) fn new(triangles: &[RtTriangle], lanes: Lanes) -> Self {
        assert!(lanes.run_here(), "{lanes} does not run on this CPU");
        assert!(triangles.len() < 1 << 24, "slots are exact in the portable lanes' f32s");
        let chunks = triangles
            .chunks(LANES)
            .map(|group| {
                let mut chunk = Chunk { rows: [[0.0; LANES]; 12] };
                for (lane, tri) in group.iter().enumerate() {
                    for axis in 0..3 {
                        chunk.rows[V0 + axis][lane] = tri.v0[axis];
                        chunk.rows[E1 + axis][lane] = tri.e1[axis];
                        chunk.rows[E2 + axis][lane] = tri.e2[axis];
                        chunk.rows[NG + axis][lane] = tri.ng[axis];
                    }
                }
                chunk
            })
            .collect();
        let blocks = triangles.chunks(4).map(TriangleBlock::new).collect();
        let planes: Vec<[f32; 12]> = triangles
            .iter()
            .map(|tri| {
                let [v0, e1, e2, ng] = [tri.v0, tri.e1, tri.e2, tri.ng];
                [v0.x, v0.y, v0.z, e1.x, e1.y, e1.z, e2.x, e2.y, e2.z, ng.x, ng.y, ng.z]
            })
            .collect();
        let pairs = match lanes {
            Lanes::Avx512 => planes.chunks(2).map(pair).collect(),
            _ => Vec::new(),
        };
        Self { chunks, halves: triangles.len().div_ceil(8), blocks, planes, pairs, lanes }
    }

    pub(crate) fn lanes(&self) -> Lanes {
        self.lanes
    }

    /// The nearest triangle the ray meets at `t` in `(0, ray.tmax)` that `accept(slot, t)` takes,
    /// with `t`; of two at the same distance, the lower slot.
    #[inline]
    pub(crate) fn closest(&self, ray: &Ray, accept: impl Fn(u32, f32) -> bool) -> Option<(u32, f32)> {
        let nearest = self.nearest(ray)?;
        if accept(nearest.0, nearest.1) {
            return Some(nearest);
        }
        // A cut-out rejected it: the rest in order of distance, then slot.
        let mut hits = Vec::new();
        self.each_hit(ray, |slot, t| {
            hits.push((t, slot));
            false
        });
        hits.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        hits.into_iter().map(|(t, slot)| (slot, t)).find(|&(slot, t)| accept(slot, t))
    }

    /// True when the ray meets a triangle at `t` in `(0, ray.tmax)` that `accept(slot, t)` takes.
    #[inline]
    pub(crate) fn any(&self, ray: &Ray, accept: impl Fn(u32, f32) -> bool) -> bool {
        self.each_hit(ray, accept)
    }

    /// [`Flat::any`] without cut-outs for a ray given by its numbers (`o + t d`, `t` in `(0,
    /// tmax)`), which builds no [`Ray`]: the shadow rays of the wave, whose lanes hold these
    /// numbers already, and whose target features this inlines into.
    #[inline(always)]
    pub(crate) fn blocked(&self, o: [f32; 3], d: [f32; 3], tmax: f32) -> bool {
        #[cfg(target_arch = "x86_64")]
        if self.lanes != Lanes::Portable {
            // SAFETY: `lanes` names only what the CPU runs, and every CPU with AVX-512 has AVX2.
            return unsafe { avx2::blocked(&self.chunks, self.halves, o, d, tmax) };
        }
        let ray = Ray::new(o.into(), d.into(), 0.0, tmax);
        self.any(&ray, |_, _| true)
    }

    /// [`Flat::closest`] for eight rays without cut-outs, each lane's answer the one its own call
    /// gives. Where the CPU has AVX2 the eight rays are tested against one triangle at a time
    /// (the triangle's numbers broadcast, the rays' kept in registers), so a ray costs no call,
    /// set-up or reduction of its own; with AVX-512, against two at a time.
    #[inline]
    pub(crate) fn nearest8(&self, rays: &Rays8) -> [Option<(u32, f32)>; 8] {
        #[cfg(target_arch = "x86_64")]
        if self.lanes != Lanes::Portable {
            let (t, slot) = match self.lanes {
                // SAFETY: `lanes` names only what the CPU runs: AVX-512 F, VL, BW and DQ here.
                Lanes::Avx512 => unsafe { avx512::nearest8(&self.pairs, rays) },
                // SAFETY: as above; every CPU with AVX-512 has AVX2.
                _ => unsafe { avx2::nearest8(&self.planes, rays) },
            };
            return std::array::from_fn(|i| (slot[i] >= 0).then_some((slot[i] as u32, t[i])));
        }
        std::array::from_fn(|i| if rays.tmax[i] > 0.0 { self.nearest(&rays.ray(i)) } else { None })
    }

    /// The nearest triangle the ray meets, lowest slot first among equals, without cut-outs.
    #[inline]
    fn nearest(&self, ray: &Ray) -> Option<(u32, f32)> {
        #[cfg(target_arch = "x86_64")]
        match self.lanes {
            // SAFETY: `lanes` names only what the CPU runs.
            Lanes::Avx512 => return unsafe { avx512::nearest(&self.chunks, ray) },
            Lanes::Avx2 => return unsafe { avx2::nearest(&self.chunks, self.halves, ray) },
            Lanes::Portable => {}
        }
        // Per lane the nearest so far (the earlier block's on a tie), then the nearest of the
        // four, lowest slot among equals.
        let mut best_t = Vec4::splat(ray.tmax);
        // Slots as `f32`s (exact below 2^24) so that one lane select serves both.
        let (mut best_slot, mut slots) = (Vec4::ZERO, Vec4::new(0.0, 1.0, 2.0, 3.0));
        for block in &self.blocks {
            let (t, met) = block.distances(ray);
            let closer = met & t.cmpgt(Vec4::ZERO) & t.cmplt(best_t);
            best_t = Vec4::select(closer, t, best_t);
            best_slot = Vec4::select(closer, slots, best_slot);
            slots += 4.0;
        }
        let t = best_t.min_element();
        // Every lane still at `tmax` (NaN where it is): nothing met.
        if t >= ray.tmax || t.is_nan() {
            return None;
        }
        let at = best_t.cmpeq(Vec4::splat(t)).bitmask();
        let slot = (0..4).filter(|lane| at & (1 << lane) != 0).map(|lane| best_slot[lane] as u32).min()?;
        Some((slot, t))
    }

    /// Offers `hit(slot, t)` every triangle the ray meets at `t` in `(0, ray.tmax)` until it
    /// returns true; returns whether it did. (The order is the lanes' own; both callers take
    /// every hit or any one.)
    #[inline]
    fn each_hit(&self, ray: &Ray, mut hit: impl FnMut(u32, f32) -> bool) -> bool {
        #[cfg(target_arch = "x86_64")]
        match self.lanes {
            // SAFETY: `lanes` names only what the CPU runs, and every CPU with AVX-512 has AVX2.
            // Eight lanes here even where sixteen run: on this project's Zen 4, which splits a
            // 512-bit operation in two, a shadow ray took 14 ns against 19 (`bench stages`).
            Lanes::Avx512 | Lanes::Avx2 => return unsafe { avx2::each_hit(&self.chunks, self.halves, ray, &mut hit) },
            Lanes::Portable => {}
        }
        let mut ray = *ray;
        let mut offered = |_: &mut Ray, slot, t| hit(slot, t);
        (0u32..).zip(&self.blocks).any(|(k, block)| block.offer(0xf, 4 * k, &mut ray, &mut offered))
    }
}

/// A pair of triangles' numbers, each over eight lanes (a lone last triangle's partner zero,
/// which no ray meets).
fn pair(two: &[[f32; 12]]) -> Chunk {
    let mut chunk = Chunk { rows: [[0.0; LANES]; 12] };
    for (half, tri) in two.iter().enumerate() {
        for (row, &x) in chunk.rows.iter_mut().zip(tri) {
            row[8 * half..8 * half + 8].fill(x);
        }
    }
    chunk
}

/// The ray's origin, direction and `tmax`, each read on its own. The caller has just written the
/// ray with narrower stores; left to itself the compiler read it back in one 64-byte load, which
/// cannot take its bytes from those stores and waits for them to reach the cache (`bench stages`:
/// a closest hit 41 ns took 58).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn numbers(ray: &Ray) -> [f32; 7] {
    let read = |x: &f32| {
        // SAFETY: a reference to an f32 is valid for reads (volatile only keeps the loads apart).
        unsafe { std::ptr::read_volatile(x) }
    };
    let (o, d) = (&ray.origin, &ray.direction);
    [read(&o.x), read(&o.y), read(&o.z), read(&d.x), read(&d.y), read(&d.z), read(&ray.tmax)]
}

#[cfg(target_arch = "x86_64")]
mod avx512 {
    use super::{Chunk, E1, E2, LANES, NG, V0};
    use obvhs::ray::Ray;
    use std::arch::x86_64::*;

    /// A chunk's sixteen distances (the operations of `TriangleBlock::intersect`, lane for lane)
    /// and the lanes met in `(0, tmax)`.
    #[target_feature(enable = "avx512f")]
    #[inline]
    fn hits(chunk: &Chunk, o: [__m512; 3], d: [__m512; 3], tmax: __m512) -> (__m512, __mmask16) {
        let row = |r: usize| {
            // SAFETY: each row is 16 aligned f32s.
            unsafe { _mm512_load_ps(chunk.rows[r].as_ptr()) }
        };
        test(row, o, d, tmax)
    }

    /// [`hits`] for the triangles' numbers `row(r)` (rows as in [`Chunk`]).
    #[target_feature(enable = "avx512f")]
    #[inline]
    fn test(row: impl Fn(usize) -> __m512, o: [__m512; 3], d: [__m512; 3], tmax: __m512) -> (__m512, __mmask16) {
        let (sub, mul, add) = (_mm512_sub_ps, _mm512_mul_ps, _mm512_add_ps);
        let c = [sub(row(V0), o[0]), sub(row(V0 + 1), o[1]), sub(row(V0 + 2), o[2])];
        let r = [
            sub(mul(d[1], c[2]), mul(c[1], d[2])),
            sub(mul(d[2], c[0]), mul(c[2], d[0])),
            sub(mul(d[0], c[1]), mul(c[0], d[1])),
        ];
        let dot = |a: [__m512; 3], b: [__m512; 3]| add(add(mul(a[0], b[0]), mul(a[1], b[1])), mul(a[2], b[2]));
        let ng = [row(NG), row(NG + 1), row(NG + 2)];
        let one = _mm512_set1_ps(1.0);
        let inv_det = _mm512_div_ps(one, dot(ng, d));
        let u = mul(dot(r, [row(E2), row(E2 + 1), row(E2 + 2)]), inv_det);
        let v = mul(dot(r, [row(E1), row(E1 + 1), row(E1 + 2)]), inv_det);
        let w = sub(sub(one, u), v);
        let t = mul(dot(ng, c), inv_det);
        let signs =
            _mm512_or_si512(_mm512_or_si512(_mm512_castps_si512(u), _mm512_castps_si512(v)), _mm512_castps_si512(w));
        let inside = _mm512_cmp_ps_mask::<_CMP_NEQ_UQ>(inv_det, _mm512_setzero_ps())
            & _mm512_cmpge_epi32_mask(signs, _mm512_setzero_si512());
        let within =
            _mm512_cmp_ps_mask::<_CMP_GT_OQ>(t, _mm512_setzero_ps()) & _mm512_cmp_ps_mask::<_CMP_LT_OQ>(t, tmax);
        (t, inside & within)
    }

    #[target_feature(enable = "avx512f")]
    #[inline]
    fn broadcast(ray: &Ray) -> ([__m512; 3], [__m512; 3], __m512) {
        let [ox, oy, oz, dx, dy, dz, tmax] = super::numbers(ray);
        let o = [_mm512_set1_ps(ox), _mm512_set1_ps(oy), _mm512_set1_ps(oz)];
        let d = [_mm512_set1_ps(dx), _mm512_set1_ps(dy), _mm512_set1_ps(dz)];
        (o, d, _mm512_set1_ps(tmax))
    }

    /// [`super::Flat::nearest8`] two triangles at a time: the eight rays in both halves of each
    /// register, a pair of triangles (`pairs`, one per half) against them. Each half keeps its
    /// own nearest in slot order (only a nearer one replaces the best), and the halves then
    /// take the nearer, the lower slot among equals: the answer of one triangle at a time.
    #[target_feature(enable = "avx512f,avx512vl,avx512dq")]
    pub(super) fn nearest8(pairs: &[Chunk], rays: &super::Rays8) -> ([f32; 8], [i32; 8]) {
        let both = |row: &[f32; 8]| {
            // SAFETY: a row is eight f32s.
            let half = unsafe { _mm256_loadu_ps(row.as_ptr()) };
            _mm512_insertf32x8::<1>(_mm512_castps256_ps512(half), half)
        };
        let (o, d, tmax) = (rays.o.each_ref().map(both), rays.d.each_ref().map(both), both(&rays.tmax));
        let mut best_t = tmax;
        let mut best_slot = _mm512_set1_epi32(-1);
        let mut slots = _mm512_setr_epi32(0, 0, 0, 0, 0, 0, 0, 0, 1, 1, 1, 1, 1, 1, 1, 1);
        let step = _mm512_set1_epi32(2);
        for pair in pairs {
            let row = |r: usize| {
                // SAFETY: each row is 16 aligned f32s.
                unsafe { _mm512_load_ps(pair.rows[r].as_ptr()) }
            };
            let (t, met) = test(row, o, d, tmax);
            let closer = _mm512_mask_cmp_ps_mask::<_CMP_LT_OQ>(met, t, best_t);
            best_t = _mm512_mask_mov_ps(best_t, closer, t);
            best_slot = _mm512_mask_mov_epi32(best_slot, closer, slots);
            slots = _mm512_add_epi32(slots, step);
        }
        // The even slots' nearest against the odd slots'.
        let (t_even, t_odd) = (_mm512_castps512_ps256(best_t), _mm512_extractf32x8_ps::<1>(best_t));
        let (s_even, s_odd) = (_mm512_castsi512_si256(best_slot), _mm512_extracti32x8_epi32::<1>(best_slot));
        let odd = _mm256_cmp_ps_mask::<_CMP_LT_OQ>(t_odd, t_even)
            | (_mm256_cmp_ps_mask::<_CMP_EQ_OQ>(t_odd, t_even) & _mm256_cmplt_epi32_mask(s_odd, s_even));
        let (mut t, mut slots) = ([0.0f32; 8], [0i32; 8]);
        // SAFETY: both hold eight 32-bit numbers.
        unsafe {
            _mm256_storeu_ps(t.as_mut_ptr(), _mm256_mask_mov_ps(t_even, odd, t_odd));
            _mm256_storeu_si256(slots.as_mut_ptr().cast(), _mm256_mask_mov_epi32(s_even, odd, s_odd));
        }
        (t, slots)
    }

    /// [`super::Flat::nearest`] sixteen lanes at a time: per lane the nearest so far (the first
    /// chunk's on a tie), then across lanes the nearest, lowest slot among equals. (Every chunk
    /// whole: a last chunk's empty half left to eight lanes measured no gain on this project's
    /// Zen 4, where one ray's test waits on its own chain of operations more than on their
    /// number.)
    #[target_feature(enable = "avx512f")]
    pub(super) fn nearest(chunks: &[Chunk], ray: &Ray) -> Option<(u32, f32)> {
        let (o, d, tmax) = broadcast(ray);
        let mut best_t = tmax;
        let mut best_slot = _mm512_set1_epi32(-1);
        let mut slots = _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
        let step = _mm512_set1_epi32(LANES as i32);
        for chunk in chunks {
            let (t, met) = hits(chunk, o, d, tmax);
            let closer = _mm512_mask_cmp_ps_mask::<_CMP_LT_OQ>(met, t, best_t);
            best_t = _mm512_mask_mov_ps(best_t, closer, t);
            best_slot = _mm512_mask_mov_epi32(best_slot, closer, slots);
            slots = _mm512_add_epi32(slots, step);
        }
        let t = _mm512_reduce_min_ps(best_t);
        // Every lane still at `tmax` (NaN where it is): nothing met.
        if t >= ray.tmax || t.is_nan() {
            return None;
        }
        let at = _mm512_cmp_ps_mask::<_CMP_EQ_OQ>(best_t, _mm512_set1_ps(t));
        Some((_mm512_mask_reduce_min_epu32(at, best_slot), t))
    }
}

#[cfg(target_arch = "x86_64")]
mod avx2 {
    use super::{Chunk, E1, E2, NG, Rays8, V0};
    use obvhs::ray::Ray;
    use std::arch::x86_64::*;

    /// Half `half` of a chunk: eight distances (the operations of [`super::avx512`]'s lanes) and
    /// the lanes met in `(0, tmax)`, all bits set in each.
    #[target_feature(enable = "avx2")]
    #[inline]
    fn hits(chunk: &Chunk, half: usize, o: [__m256; 3], d: [__m256; 3], tmax: __m256) -> (__m256, __m256) {
        let row = |r: usize| {
            // SAFETY: each row is 16 f32s aligned to 64 bytes: its halves to 32.
            unsafe { _mm256_load_ps(chunk.rows[r].as_ptr().add(8 * half)) }
        };
        let (t, met) = test(row, o, d);
        (t, _mm256_and_ps(met, _mm256_cmp_ps::<_CMP_LT_OQ>(t, tmax)))
    }

    /// `RtTriangle::intersect`'s operations on eight lanes: the triangles' numbers `tri(row)`
    /// (rows as in [`Chunk`]) against the rays `o + t d`. Per lane the distance and whether the
    /// ray meets the triangle at a positive one, all bits set.
    #[target_feature(enable = "avx2")]
    #[inline]
    fn test(tri: impl Fn(usize) -> __m256, o: [__m256; 3], d: [__m256; 3]) -> (__m256, __m256) {
        let (sub, mul, add) = (_mm256_sub_ps, _mm256_mul_ps, _mm256_add_ps);
        let c = [sub(tri(V0), o[0]), sub(tri(V0 + 1), o[1]), sub(tri(V0 + 2), o[2])];
        let r = [
            sub(mul(d[1], c[2]), mul(c[1], d[2])),
            sub(mul(d[2], c[0]), mul(c[2], d[0])),
            sub(mul(d[0], c[1]), mul(c[0], d[1])),
        ];
        let dot = |a: [__m256; 3], b: [__m256; 3]| add(add(mul(a[0], b[0]), mul(a[1], b[1])), mul(a[2], b[2]));
        let ng = [tri(NG), tri(NG + 1), tri(NG + 2)];
        let one = _mm256_set1_ps(1.0);
        let inv_det = _mm256_div_ps(one, dot(ng, d));
        let u = mul(dot(r, [tri(E2), tri(E2 + 1), tri(E2 + 2)]), inv_det);
        let v = mul(dot(r, [tri(E1), tri(E1 + 1), tri(E1 + 2)]), inv_det);
        let w = sub(sub(one, u), v);
        let t = mul(dot(ng, c), inv_det);
        let signs = _mm256_or_ps(_mm256_or_ps(u, v), w);
        let negative = _mm256_castsi256_ps(_mm256_cmpgt_epi32(_mm256_setzero_si256(), _mm256_castps_si256(signs)));
        let zero = _mm256_setzero_ps();
        let inside = _mm256_andnot_ps(negative, _mm256_cmp_ps::<_CMP_NEQ_UQ>(inv_det, zero));
        (t, _mm256_and_ps(inside, _mm256_cmp_ps::<_CMP_GT_OQ>(t, zero)))
    }

    #[target_feature(enable = "avx2")]
    #[inline]
    fn broadcast(ray: &Ray) -> ([__m256; 3], [__m256; 3], __m256) {
        let [ox, oy, oz, dx, dy, dz, tmax] = super::numbers(ray);
        let o = [_mm256_set1_ps(ox), _mm256_set1_ps(oy), _mm256_set1_ps(oz)];
        let d = [_mm256_set1_ps(dx), _mm256_set1_ps(dy), _mm256_set1_ps(dz)];
        (o, d, _mm256_set1_ps(tmax))
    }

    /// [`super::Flat::nearest`] eight lanes at a time over the first `halves` halves, as
    /// [`super::avx512::nearest`] chooses.
    #[target_feature(enable = "avx2")]
    pub(super) fn nearest(chunks: &[Chunk], halves: usize, ray: &Ray) -> Option<(u32, f32)> {
        let (o, d, tmax) = broadcast(ray);
        let mut best_t = tmax;
        let mut best_slot = _mm256_set1_epi32(-1);
        let mut slots = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
        let step = _mm256_set1_epi32(8);
        for h in 0..halves {
            let (t, met) = hits(&chunks[h / 2], h % 2, o, d, tmax);
            let closer = _mm256_and_ps(met, _mm256_cmp_ps::<_CMP_LT_OQ>(t, best_t));
            best_t = _mm256_blendv_ps(best_t, t, closer);
            best_slot = _mm256_blendv_epi8(best_slot, slots, _mm256_castps_si256(closer));
            slots = _mm256_add_epi32(slots, step);
        }
        // The nearest in every lane, then the lowest slot among the lanes that have it.
        let mut t = _mm256_min_ps(best_t, _mm256_permute2f128_ps::<1>(best_t, best_t));
        t = _mm256_min_ps(t, _mm256_permute_ps::<0b01_00_11_10>(t));
        t = _mm256_min_ps(t, _mm256_permute_ps::<0b10_11_00_01>(t));
        let nearest = _mm256_cvtss_f32(t);
        // Every lane still at `tmax` (NaN where it is): nothing met.
        if nearest >= ray.tmax || nearest.is_nan() {
            return None;
        }
        let at = _mm256_castps_si256(_mm256_cmp_ps::<_CMP_EQ_OQ>(best_t, t));
        let mut slot = _mm256_blendv_epi8(_mm256_set1_epi32(-1), best_slot, at);
        slot = _mm256_min_epu32(slot, _mm256_permute2x128_si256::<1>(slot, slot));
        slot = _mm256_min_epu32(slot, _mm256_shuffle_epi32::<0b01_00_11_10>(slot));
        slot = _mm256_min_epu32(slot, _mm256_shuffle_epi32::<0b10_11_00_01>(slot));
        Some((_mm256_cvtsi256_si32(slot) as u32, nearest))
    }

    /// Eight rays against triangle `tri` (`v0`, `e1`, `e2`, `ng`): [`test`] with the triangle's
    /// numbers broadcast and the rays' in the lanes.
    #[target_feature(enable = "avx2")]
    #[inline]
    fn meet8(tri: &[f32; 12], o: [__m256; 3], d: [__m256; 3]) -> (__m256, __m256) {
        test(|k| _mm256_broadcast_ss(&tri[k]), o, d)
    }

    /// The rows of `rays`.
    #[target_feature(enable = "avx2")]
    #[inline]
    fn rows(rays: &Rays8) -> ([__m256; 3], [__m256; 3], __m256) {
        let load = |row: &[f32; 8]| {
            // SAFETY: a row is eight f32s.
            unsafe { _mm256_loadu_ps(row.as_ptr()) }
        };
        (rays.o.each_ref().map(load), rays.d.each_ref().map(load), load(&rays.tmax))
    }

    /// [`super::Flat::nearest8`]: per lane the nearest distance met in `(0, tmax)` and its slot,
    /// the lowest among equals (the triangles come in slot order and only a nearer one replaces
    /// the best), or slot -1.
    #[target_feature(enable = "avx2")]
    #[inline]
    pub(super) fn nearest8(planes: &[[f32; 12]], rays: &Rays8) -> ([f32; 8], [i32; 8]) {
        let (o, d, tmax) = rows(rays);
        let mut best_t = tmax;
        let mut best_slot = _mm256_set1_epi32(-1);
        let mut slot = _mm256_setzero_si256();
        let one = _mm256_set1_epi32(1);
        for tri in planes {
            let (t, met) = meet8(tri, o, d);
            // Nearer than the best so far, which is never past `tmax`.
            let closer = _mm256_and_ps(met, _mm256_cmp_ps::<_CMP_LT_OQ>(t, best_t));
            best_t = _mm256_blendv_ps(best_t, t, closer);
            best_slot = _mm256_blendv_epi8(best_slot, slot, _mm256_castps_si256(closer));
            slot = _mm256_add_epi32(slot, one);
        }
        let (mut t, mut slots) = ([0.0f32; 8], [0i32; 8]);
        // SAFETY: both hold eight 32-bit numbers.
        unsafe {
            _mm256_storeu_ps(t.as_mut_ptr(), best_t);
            _mm256_storeu_si256(slots.as_mut_ptr().cast(), best_slot);
        }
        (t, slots)
    }

    /// [`super::Flat::blocked`]: [`each_hit`] with every hit taken, for the ray's numbers.
    #[target_feature(enable = "avx2")]
    #[inline]
    pub(super) fn blocked(chunks: &[Chunk], halves: usize, o: [f32; 3], d: [f32; 3], tmax: f32) -> bool {
        let splat = |v: [f32; 3]| v.map(|x| _mm256_set1_ps(x));
        let (o, d, tmax) = (splat(o), splat(d), _mm256_set1_ps(tmax));
        (0..halves).any(|h| _mm256_movemask_ps(hits(&chunks[h / 2], h % 2, o, d, tmax).1) != 0)
    }

    /// [`super::Flat::each_hit`] eight lanes at a time over the first `halves` halves.
    #[target_feature(enable = "avx2")]
    pub(super) fn each_hit(chunks: &[Chunk], halves: usize, ray: &Ray, hit: &mut impl FnMut(u32, f32) -> bool) -> bool {
        let (o, d, tmax) = broadcast(ray);
        for h in 0..halves {
            let (t, met) = hits(&chunks[h / 2], h % 2, o, d, tmax);
            let mut met = _mm256_movemask_ps(met) as u32;
            if met != 0 {
                let mut ts = [0.0f32; 8];
                // SAFETY: `ts` holds eight f32s.
                unsafe { _mm256_storeu_ps(ts.as_mut_ptr(), t) };
                while met != 0 {
                    let lane = met.trailing_zeros();
                    met &= met - 1;
                    if hit((8 * h) as u32 + lane, ts[lane as usize]) {
                        return true;
                    }
                }
            }
        }
        false
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3A;
    use obvhs::triangle::Triangle;

    /// Of triangles met at one distance, every width this CPU runs takes the lowest slot, and
    /// the next lowest where a cut-out rejects it: one triangle held in slots `k`, `k + 4`,
    /// `k + 8`, `k + 16` and `k + 32` (the same lane of another block, half or chunk), the others
    /// off the ray's way.
    #[test]
    fn ties_go_to_the_lowest_slot_at_every_width() {
        let tri = |z: f32, x: f32| {
            let v = |x: f32, y: f32| Vec3A::new(x, y, z);
            RtTriangle::from(&Triangle { v0: v(x - 1.0, -1.0), v1: v(x + 1.0, -1.0), v2: v(x, 1.0) })
        };
        let ray = Ray::new(Vec3A::ZERO, Vec3A::Z, 0.0, f32::INFINITY);
        let mut checked = 0;
        for k in 0..4 {
            let copies = [k, k + 4, k + 8, k + 16, k + 32];
            let triangles: Vec<RtTriangle> =
                (0..40).map(|s| if copies.contains(&s) { tri(5.0, 0.0) } else { tri(2.0 + s as f32, 9.0) }).collect();
            for lanes in Lanes::ALL.into_iter().filter(|lanes| lanes.run_here()) {
                let flat = Flat::new(&triangles, lanes);
                assert_eq!(flat.closest(&ray, |_, _| true), Some((k as u32, 5.0)), "{lanes}, slot {k}");
                let rejected = |slot: u32, _| slot != k as u32 && slot != k as u32 + 4;
                assert_eq!(flat.closest(&ray, rejected), Some((k as u32 + 8, 5.0)), "{lanes}, slot {k} cut out");
                assert!(flat.any(&ray, rejected), "{lanes}: the uncut copies block the ray");
                assert!(!flat.any(&ray, |slot, _| !copies.contains(&(slot as usize))), "{lanes}: nothing else does");
                checked += 1;
            }
        }
        assert!(checked >= 4, "the portable lanes run everywhere");
    }

    /// Eight rays at once get, lane by lane, the slot and distance bits of their own calls, at every width this CPU runs: rays from inside a box of 40 triangles
    /// in all directions, some stopping short, a lane without a ray, and a tie that the lowest
    /// slot must win.
    #[test]
    fn eight_rays_at_once_get_each_ray_its_own_answer() {
        let v = |x: f32, y: f32, z: f32| Vec3A::new(x, y, z);
        let (sin, cos) = (libm::sinf, libm::cosf);
        let mut triangles: Vec<RtTriangle> = Vec::new();
        // Triangles of several sizes and slopes on both sides of the origin.
        for k in 0..38 {
            let (a, b) = (k as f32 * 0.37, k as f32 * 0.61 + 0.2);
            let z = if k % 2 == 0 { 3.0 + sin(a) } else { -3.0 - cos(b) };
            triangles.push(RtTriangle::from(&Triangle {
                v0: v(-4.0 + sin(a), -4.0, z),
                v1: v(4.0, -4.0 + cos(b), z + 0.5),
                v2: v(sin(b), 4.0, z - 0.25),
            }));
        }
        // A small triangle nearer than all of them straight ahead, in slots 6 and 39 (a tie).
        let tie = RtTriangle::from(&Triangle { v0: v(-0.1, -0.1, 1.5), v1: v(0.1, -0.1, 1.5), v2: v(0.0, 0.1, 1.5) });
        triangles.insert(6, tie);
        triangles.push(tie);
        let (mut checked, mut shadows) = (0, [0; 2]);
        for lanes in Lanes::ALL.into_iter().filter(|lanes| lanes.run_here()) {
            let flat = Flat::new(&triangles, lanes);
            for round in 0..64 {
                let mut rays = Rays8 { o: [[0.0; 8]; 3], d: [[0.0; 8]; 3], tmax: [0.0; 8] };
                for i in 0..8 {
                    let s = (round * 8 + i) as f32;
                    let d = Vec3A::new(sin(s * 0.73), cos(s * 1.37) * 0.6, cos(s * 0.29)).normalize();
                    let o = Vec3A::new(sin(s * 0.11), cos(s * 0.23) * 0.5, 0.1 * sin(s * 0.7));
                    let tmax = match i {
                        3 => 0.0,                // no ray
                        5 => 1.5 + sin(s * 0.5), // stops short of some
                        _ => f32::INFINITY,
                    };
                    for axis in 0..3 {
                        (rays.o[axis][i], rays.d[axis][i]) = (o[axis], d[axis]);
                    }
                    rays.tmax[i] = tmax;
                }
                // A shadow ray from the numbers alone answers as `any` does, stopping at several
                // distances (the nearest triangles lie 1.5 to 4 away).
                for i in 0..8 {
                    for tmax in [0.0, 1.0, 2.0, 3.2, f32::INFINITY] {
                        let lane = rays.ray(i);
                        let ray = Ray::new(lane.origin, lane.direction, 0.0, tmax);
                        let (o, d) = (ray.origin.into(), ray.direction.into());
                        let blocked = flat.any(&ray, |_, _| true);
                        assert_eq!(flat.blocked(o, d, tmax), blocked, "{lanes}, round {round}, lane {i}, tmax {tmax}");
                        shadows[blocked as usize] += 1;
                    }
                }
                for (i, got) in flat.nearest8(&rays).into_iter().enumerate() {
                    let expected = (rays.tmax[i] > 0.0).then(|| flat.closest(&rays.ray(i), |_, _| true)).flatten();
                    let bits = |h: Option<(u32, f32)>| h.map(|(slot, t)| (slot, t.to_bits()));
                    assert_eq!(bits(got), bits(expected), "{lanes}, round {round}, lane {i}");
                    checked += expected.is_some() as usize;
                }
            }
            // Straight at the tied pair: the lower slot.
            let mut rays = Rays8 { o: [[0.0; 8]; 3], d: [[0.0; 8]; 3], tmax: [f32::INFINITY; 8] };
            for i in 0..8 {
                (rays.d[0][i], rays.d[1][i], rays.d[2][i]) = (0.004 * i as f32, -0.002 * i as f32, 1.0);
            }
            let expected = flat.closest(&rays.ray(0), |_, _| true).map(|(slot, _)| slot);
            assert_eq!(expected, Some(6), "the tie goes to slot 6");
            assert!(flat.nearest8(&rays).iter().all(|h| h.map(|(slot, _)| slot) == Some(6)), "{lanes}");
        }
        assert!(checked > 500, "most rays must meet something ({checked})");
        assert!(shadows[0] > 300 && shadows[1] > 300, "shadow rays blocked and not: {shadows:?}");
    }
}
