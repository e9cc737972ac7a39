//! Triangles four to a block, per coordinate one lane each, as obvhs's `RtTriangle` stores one:
//! what a node's triangles, and the portable lanes of a small scene, are tested from.

use glam::{BVec4A, Vec3, Vec3A, Vec4};
use obvhs::ray::Ray;
use obvhs::rt_triangle::RtTriangle;

/// Four triangles side by side (unused lanes zero), as obvhs's `RtTriangle` stores one: a vertex,
/// the edges `v0 - v1` and `v2 - v0`, and their cross product; per coordinate, one lane each.
/// Aligned to cache lines, a block spans three of them rather than four.
#[repr(C, align(64))]
pub(crate) struct TriangleBlock {
    v0: [Vec4; 3],
    e1: [Vec4; 3],
    e2: [Vec4; 3],
    ng: [Vec4; 3],
}

impl TriangleBlock {
    pub(crate) fn new(triangles: &[RtTriangle]) -> Self {
        let lanes = |f: &dyn Fn(&RtTriangle) -> Vec3A| -> [Vec4; 3] {
            std::array::from_fn(|axis| {
                Vec4::from_array(std::array::from_fn(|lane| triangles.get(lane).map_or(0.0, |t| f(t)[axis])))
            })
        };
        Self { v0: lanes(&|t| t.v0), e1: lanes(&|t| t.e1), e2: lanes(&|t| t.e2), ng: lanes(&|t| t.ng) }
    }

    /// The four distances of `RtTriangle::intersect`, lane by lane with its operations in its
    /// order (so with its bits), and a mask of the lanes it would not report as a miss.
    #[inline(always)]
    pub(crate) fn intersect(&self, ray: &Ray) -> ([f32; 4], u32) {
        let (t, met) = self.distances(ray);
        (t.to_array(), met.bitmask())
    }

    /// [`TriangleBlock::intersect`] with the distances in a register.
    #[inline(always)]
    pub(crate) fn distances(&self, ray: &Ray) -> (Vec4, BVec4A) {
        let d = [Vec4::splat(ray.direction.x), Vec4::splat(ray.direction.y), Vec4::splat(ray.direction.z)];
        let c = [self.v0[0] - ray.origin.x, self.v0[1] - ray.origin.y, self.v0[2] - ray.origin.z];
        // r = d x c, then dot products summed as (x + y) + z, as glam's.
        let r = [d[1] * c[2] - c[1] * d[2], d[2] * c[0] - c[2] * d[0], d[0] * c[1] - c[0] * d[1]];
        let dot = |a: &[Vec4; 3], b: &[Vec4; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
        let inv_det = Vec4::ONE / dot(&self.ng, &d);
        let u = dot(&r, &self.e2) * inv_det;
        let v = dot(&r, &self.e1) * inv_det;
        let w = Vec4::ONE - u - v;
        let t = dot(&self.ng, &c) * inv_det;
        // A sign bit set in u, v or w (negative zero included, as obvhs has it) is a miss.
        let signs = u.is_negative_mask() | v.is_negative_mask() | w.is_negative_mask();
        let inside = inv_det.cmpne(Vec4::ZERO) & !signs;
        let within = t.cmpge(Vec4::splat(ray.tmin)) & t.cmple(Vec4::splat(ray.tmax));
        (t, inside & within)
    }

    /// Offers the ray the block's triangles in `lanes` (four bits; lane `k` is slot `first + k`)
    /// that it meets at `t` in `(0, ray.tmax)`, highest lane first: `hit(ray, slot, t)` as in
    /// [`Bvh::walk`], which may shorten `ray.tmax` and stops the offers by returning true. One
    /// place for the single-ray walk and the packets, so that both report the same bits.
    #[inline(always)]
    pub(crate) fn offer(
        &self,
        lanes: u32,
        first: u32,
        ray: &mut Ray,
        hit: &mut impl FnMut(&mut Ray, u32, f32) -> bool,
    ) -> bool {
        let (ts, valid) = self.intersect(ray);
        let mut lanes = lanes & valid;
        while lanes != 0 {
            let lane = 31 - lanes.leading_zeros();
            lanes &= !(1 << lane);
            let t = ts[lane as usize];
            if t.is_finite() && t > 0.0 && t < ray.tmax && hit(ray, first + lane, t) {
                return true;
            }
        }
        false
    }
}

/// Lane `i` of three rows.
#[inline(always)]
pub(crate) fn row(rows: &[[f32; 8]; 3], i: usize) -> Vec3 {
    Vec3::new(rows[0][i], rows[1][i], rows[2][i])
}
