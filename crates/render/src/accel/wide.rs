//! The tree's nodes as single rays and packets read them: obvhs's node with where its triangle
//! blocks start ([`WideNode`]), and the child-box tests, eight at a time with AVX2 or four at a
//! time elsewhere, with the arithmetic of obvhs's `intersect_ray_simd` operand for operand.

use glam::{Vec3A, Vec4};
use obvhs::cwbvh::node::CwBvhNode;
use obvhs::ray::Ray;

/// obvhs's lower bound on box entry distances, in the BVH's units (see [`super::Bvh`]).
pub(super) const BOX_EPSILON: f32 = 0.0001;

/// How many triangles a node's leaf children hold (they lie together from `primitive_base_idx`).
pub(super) fn node_triangles(node: &CwBvhNode) -> usize {
    (0..8)
        .filter(|&c| node.imask & (1 << c) == 0)
        .map(|c| {
            let meta = node.child_meta[c];
            (meta & 0x1f) as usize + (meta >> 5).count_ones() as usize
        })
        .max()
        .unwrap_or(0)
}

/// A CWBVH node for single rays: obvhs's node as it is (80 bytes, its child planes quantised to
/// bytes) and where its triangles' blocks start, aligned so that a node spans two cache lines.
/// Planes decoded to `f32` at build made a node 288 bytes; decoding them on each visit costs a
/// few instructions and takes a third of the memory, which incoherent rays through large scenes
/// wait on.
#[repr(C, align(32))]
pub(super) struct WideNode {
    pub(super) node: CwBvhNode,
    /// The node's first [`TriangleBlock`].
    pub(super) block: u32,
}

impl WideNode {
    pub(super) fn new(node: &CwBvhNode, block: u32) -> Self {
        Self { node: *node, block }
    }

    /// The ray's hit mask for this node, as obvhs's `intersect_ray_simd` makes it (and so with its
    /// bits): children in the high byte by traversal priority, triangles below. `AVX2` tests the
    /// eight child boxes in one step, where the caller is compiled for it.
    #[inline(always)]
    pub(super) fn hits<const AVX2: bool>(&self, ray: &Ray, negative: [bool; 3], oct_inv4: u32) -> u32 {
        let node = &self.node;
        let planes = [
            (&node.child_min_x, &node.child_max_x),
            (&node.child_min_y, &node.child_max_y),
            (&node.child_min_z, &node.child_max_z),
        ];
        let near = std::array::from_fn(|axis| if negative[axis] { planes[axis].1 } else { planes[axis].0 });
        let far = std::array::from_fn(|axis| if negative[axis] { planes[axis].0 } else { planes[axis].1 });
        let (extent, p) = (node.compute_extent(), Vec3A::from(node.p));
        #[cfg(target_arch = "x86_64")]
        let mut children = if AVX2 {
            // SAFETY: `AVX2` is true only where `Bvh::walk` compiled the walk for AVX2, which the
            // CPU has.
            unsafe { child_box_hits_avx2(near, far, extent, p, ray) }
        } else {
            child_box_hits_of_bytes(near, far, extent, p, ray)
        };
        #[cfg(not(target_arch = "x86_64"))]
        let mut children = child_box_hits_of_bytes(near, far, extent, p, ray);
        let (child_bits, bit_index) = node.get_child_and_index_bits(oct_inv4);
        let mut mask = 0u32;
        while children != 0 {
            let c = children.trailing_zeros() as u64;
            children &= children - 1;
            mask |= (((child_bits >> (8 * c)) & 0xff) as u32) << ((bit_index >> (8 * c)) & 0xff);
        }
        mask
    }
}

/// Children 0-7 of a node as bytes to `f32`, four at a time (exact).
#[inline(always)]
pub(super) fn byte_planes(q: &[u8; 8]) -> [Vec4; 2] {
    std::array::from_fn(|half| Vec4::from_array(std::array::from_fn(|i| q[4 * half + i] as f32)))
}

/// Which of a node's eight children the ray's boxes reach, one bit each, from the quantised near
/// and far planes per axis, four children at a time with [`child_box_hits`].
#[inline(always)]
pub(super) fn child_box_hits_of_bytes(
    near: [&[u8; 8]; 3],
    far: [&[u8; 8]; 3],
    extent: Vec3A,
    p: Vec3A,
    ray: &Ray,
) -> u32 {
    let [low, high] = child_box_hits(&near.map(byte_planes), &far.map(byte_planes), extent, p, ray);
    low | high << 4
}

/// [`child_box_hits_of_bytes`] with the eight children in one AVX register: the same operations on
/// each child in the same order (multiply, then add; no fused multiply-add), so the same bits.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
pub(super) fn child_box_hits_avx2(near: [&[u8; 8]; 3], far: [&[u8; 8]; 3], extent: Vec3A, p: Vec3A, ray: &Ray) -> u32 {
    use std::arch::x86_64::*;
    let planes = |q: &[u8; 8]| _mm256_cvtepi32_ps(_mm256_cvtepu8_epi32(_mm_cvtsi64_si128(i64::from_le_bytes(*q))));
    child_planes_hits_avx2(near.map(planes), far.map(planes), extent, p, ray)
}

/// [`child_box_hits_avx2`] from the eight children's near and far planes per axis, as floats
/// already (a packet's rays share them: `packet::ChildPlanes`).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
pub(super) fn child_planes_hits_avx2(
    near: [std::arch::x86_64::__m256; 3],
    far: [std::arch::x86_64::__m256; 3],
    extent: Vec3A,
    p: Vec3A,
    ray: &Ray,
) -> u32 {
    use std::arch::x86_64::*;
    let scale = extent * ray.inv_direction;
    let origin = (p - ray.origin) * ray.inv_direction;
    let (s, o) = (scale.to_array(), origin.to_array());
    let distances = |planes: [__m256; 3], axis: usize| {
        _mm256_add_ps(_mm256_mul_ps(planes[axis], _mm256_set1_ps(s[axis])), _mm256_set1_ps(o[axis]))
    };
    let tmin = _mm256_max_ps(distances(near, 0), _mm256_max_ps(distances(near, 1), distances(near, 2)));
    let tmax = _mm256_min_ps(distances(far, 0), _mm256_min_ps(distances(far, 1), distances(far, 2)));
    let tmin = _mm256_max_ps(tmin, _mm256_set1_ps(BOX_EPSILON));
    let tmax = _mm256_min_ps(tmax, _mm256_set1_ps(ray.tmax));
    _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_LE_OQ>(tmin, tmax)) as u32
}

/// Which of a node's children 0-3 and 4-7 the ray's boxes reach, one bit each, given their near
/// and far planes per axis (in the node's quantised units, for the ray's octant) and the node's
/// `compute_extent()` and `p`. The arithmetic
/// of obvhs's `CwBvhNode::intersect_ray_simd`, operand for operand, so that the bits agree.
#[inline(always)]
pub(super) fn child_box_hits(
    near: &[[Vec4; 2]; 3],
    far: &[[Vec4; 2]; 3],
    extent: Vec3A,
    p: Vec3A,
    ray: &Ray,
) -> [u32; 2] {
    let scale = extent * ray.inv_direction;
    let origin = (p - ray.origin) * ray.inv_direction;
    let (sx, sy, sz) = (Vec4::splat(scale.x), Vec4::splat(scale.y), Vec4::splat(scale.z));
    let (ox, oy, oz) = (Vec4::splat(origin.x), Vec4::splat(origin.y), Vec4::splat(origin.z));
    std::array::from_fn(|half| {
        let (n, f) = (near, far);
        let tmin = (n[0][half] * sx + ox).max((n[1][half] * sy + oy).max(n[2][half] * sz + oz));
        let tmax = (f[0][half] * sx + ox).min((f[1][half] * sy + oy).min(f[2][half] * sz + oz));
        let tmin = tmin.max(Vec4::splat(BOX_EPSILON));
        let tmax = tmax.min(Vec4::splat(ray.tmax));
        tmin.cmple(tmax).bitmask()
    })
}
