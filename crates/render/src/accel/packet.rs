//! Camera rays in packets of [`PACKET`]: the union of the rays' walks in the order one ray would
//! take, each ray tested only at the nodes and triangles its own boxes reach, against its own
//! nearest hit, so each gets the bits it gets alone.

use super::walk::{octant_inv4, take_quad};
#[cfg(target_arch = "x86_64")]
use super::wide::child_planes_hits_avx2;
use super::wide::{byte_planes, child_box_hits};
use super::{Bvh, PACKET, STACK};
use crate::lanes::{Lanes, dispatch_unchecked};
use glam::{UVec2, Vec3, Vec3A, Vec4};
use obvhs::cwbvh::node::CwBvhNode;
use obvhs::ray::Ray;

impl Bvh {
    /// Closest hits of up to [`PACKET`] rays `(o, d, tmax)` traced together; `accept(ray, slot, t)`
    /// as in [`Bvh::closest_hit`]. Each ray's answer has the bits `closest_hit` gives it alone: the
    /// packet walks the union of the rays' paths in the order one ray would, and tests each ray only
    /// at the nodes and triangles its own boxes reach, against its own nearest hit so far. Rays that
    /// do not share one direction octant (so one child order) are traced one by one.
    pub fn closest_hits(
        &self,
        rays: &[(Vec3, Vec3, f32)],
        accept: impl Fn(usize, u32, f32) -> bool,
    ) -> [Option<(u32, f32)>; PACKET] {
        // SAFETY: `lanes` was chosen at build among what the CPU runs (`Lanes::widest`).
        unsafe {
            dispatch_unchecked(
                self.lanes,
                #[inline(always)]
                |lanes| match lanes {
                    Lanes::Portable => self.closest_hits_with::<false>(rays, &accept),
                    // A node's child boxes in one AVX2 step per ray: compiled for `lanes`, which
                    // has AVX2.
                    _ => self.closest_hits_with::<true>(rays, &accept),
                },
            )
        }
    }

    /// The packet's walk; `AVX2` only where [`Bvh::closest_hits`] compiled it for AVX2.
    // Indexed lane loops: the zipped-iterator forms measured 10-25% slower in `bench rays`.
    #[allow(clippy::needless_range_loop)]
    #[inline(always)]
    fn closest_hits_with<const AVX2: bool>(
        &self,
        rays: &[(Vec3, Vec3, f32)],
        accept: &impl Fn(usize, u32, f32) -> bool,
    ) -> [Option<(u32, f32)>; PACKET] {
        let mut out = [None; PACKET];
        assert!(rays.len() <= PACKET, "at most {PACKET} rays in a packet");
        let Some(bvh) = self.cwbvh.as_ref() else {
            return out;
        };
        // A ray that misses the scene's bounds misses every triangle: most camera rays of an
        // asset seen small in its frame are answered here, and the rest walk without them.
        let live: [bool; PACKET] =
            std::array::from_fn(|r| rays.get(r).is_some_and(|&(o, d, t)| self.may_meet(o, d, t)));
        let mut walking = rays.iter().zip(live).filter(|(_, live)| *live);
        let Some((first, _)) = walking.next() else {
            return out;
        };
        let oct_inv4 = octant_inv4(first.1);
        if rays.len() < 2 || walking.any(|(r, _)| octant_inv4(r.1) != oct_inv4) || self.flat.is_some() {
            for (r, &(o, d, tmax)) in rays.iter().enumerate().filter(|&(r, _)| live[r]) {
                out[r] = self.closest_hit(o, d, tmax, |slot, t| accept(r, slot, t));
            }
            return out;
        }
        let mut ray: [Ray; PACKET] = [Ray::new_inf(Vec3A::ZERO, Vec3A::Z); PACKET];
        for (r, &(o, d, tmax)) in rays.iter().enumerate() {
            ray[r] = self.ray_of(o, d, tmax);
        }
        let lanes = rays.len();
        // A group of children (base index, hit bits in the high byte | parent's imask) with each
        // ray's own hit bits, and the primitives of the last node likewise.
        let mut stack = [(UVec2::ZERO, [0u32; PACKET]); STACK];
        let mut depth = 0usize;
        let mut group = (UVec2::new(0, 0x8000_0000), live.map(|live| if live { 0x8000_0000u32 } else { 0 }));
        let mut prims = (UVec2::ZERO, [0u32; PACKET]);
        let mut block = 0u32;
        loop {
            // Where the walk's blocks exist, each ray tests a node's triangles four at a time, in
            // the order and with the bits of the one-by-one loop below.
            while prims.0.y != 0 && !self.blocks.is_empty() {
                let (quad, _) = take_quad(&mut prims.0.y);
                let tris = &self.blocks[(block + quad) as usize];
                for r in 0..lanes {
                    let hit = (prims.1[r] >> (4 * quad)) & 0xf;
                    if hit != 0 {
                        let accept = |id, t: f32| accept(r, id, t / self.scale);
                        tris.offer(hit, prims.0.x + 4 * quad, &mut ray[r], &mut self.nearest(&accept, &mut out[r]));
                    }
                }
            }
            while prims.0.y != 0 {
                let bit = 31 - prims.0.y.leading_zeros();
                prims.0.y &= !(1 << bit);
                let id = prims.0.x + bit;
                let tri = &self.triangles[id as usize];
                for r in 0..lanes {
                    if prims.1[r] & (1 << bit) != 0 {
                        let t = tri.intersect(&ray[r]);
                        if t.is_finite() && t > 0.0 && t < ray[r].tmax && accept(r, id, t / self.scale) {
                            out[r] = Some((id, t / self.scale));
                            ray[r].tmax = t;
                        }
                    }
                }
            }
            if group.0.y & 0xff00_0000 != 0 {
                let hits_imask = group.0.y;
                let offset = 31 - hits_imask.leading_zeros();
                group.0.y &= !(1 << offset);
                let mut reach = [0u32; PACKET];
                for r in 0..lanes {
                    reach[r] = group.1[r] & (1 << offset);
                    group.1[r] &= !(1 << offset);
                }
                if group.0.y & 0xff00_0000 != 0 {
                    stack[depth] = group;
                    depth = (depth + 1).min(STACK - 1);
                }
                let slot = (offset - 24) ^ (oct_inv4 & 0xff);
                let relative = (hits_imask & !(u32::MAX << slot)).count_ones();
                let index = (group.0.x + relative) as usize;
                let node = &bvh.nodes[index];
                block = self.wide.get(index).map_or(0, |w| w.block);
                let planes = ChildPlanes::decode(node, oct_inv4);
                let (mut union, mut mask) = (0, [0u32; PACKET]);
                for r in 0..lanes {
                    if reach[r] != 0 {
                        mask[r] = planes.hits::<AVX2>(&ray[r]);
                        union |= mask[r];
                    }
                }
                group.0 = UVec2::new(node.child_base_idx, (union & 0xff00_0000) | node.imask as u32);
                prims.0 = UVec2::new(node.primitive_base_idx, union & 0x00ff_ffff);
                for r in 0..PACKET {
                    group.1[r] = mask[r] & 0xff00_0000;
                    prims.1[r] = mask[r] & 0x00ff_ffff;
                }
            } else {
                group.0 = UVec2::ZERO;
            }
            if prims.0.y == 0 && group.0.y & 0xff00_0000 == 0 {
                if depth == 0 {
                    break;
                }
                depth -= 1;
                group = stack[depth];
            }
        }
        out
    }
}

/// A node's child boxes decoded once for all the rays of a packet (which share one octant), and
/// tested against each ray with the arithmetic of obvhs's `CwBvhNode::intersect_ray`, so that a
/// ray's hit mask has the same bits as when it traverses alone.
pub(super) struct ChildPlanes {
    /// Near and far planes per axis for the octant, children 0-3 and 4-7, in quantised units.
    near: [[Vec4; 2]; 3],
    far: [[Vec4; 2]; 3],
    extent: Vec3A,
    p: Vec3A,
    /// The hit mask of each subset of children 0-3 and of children 4-7 (from obvhs's
    /// `get_child_and_index_bits`), so that a ray's mask needs no loop over the children it hits.
    masks: [[u32; 16]; 2],
}

impl ChildPlanes {
    #[inline(always)]
    fn decode(node: &CwBvhNode, oct_inv4: u32) -> Self {
        #[inline(always)]
        fn axis(neg: bool, lo: &[u8; 8], hi: &[u8; 8]) -> ([Vec4; 2], [Vec4; 2]) {
            let (near, far) = if neg { (hi, lo) } else { (lo, hi) };
            (byte_planes(near), byte_planes(far))
        }
        let (nx, fx) = axis(oct_inv4 & 4 == 0, &node.child_min_x, &node.child_max_x);
        let (ny, fy) = axis(oct_inv4 & 2 == 0, &node.child_min_y, &node.child_max_y);
        let (nz, fz) = axis(oct_inv4 & 1 == 0, &node.child_min_z, &node.child_max_z);
        let (bits8, shift8) = node.get_child_and_index_bits(oct_inv4);
        let mut masks = [[0u32; 16]; 2];
        for (half, table) in masks.iter_mut().enumerate() {
            for subset in 1..16usize {
                let c = 4 * half + subset.trailing_zeros() as usize;
                let child = (((bits8 >> (8 * c)) & 0xff) as u32) << ((shift8 >> (8 * c)) & 0xff);
                table[subset] = table[subset & (subset - 1)] | child;
            }
        }
        Self { near: [nx, ny, nz], far: [fx, fy, fz], extent: node.compute_extent(), p: Vec3A::from(node.p), masks }
    }

    /// The ray's hit mask; `AVX2`: the eight children in one register, where the caller was
    /// compiled for AVX2 (the same operations on each child, so the same bits).
    #[inline(always)]
    fn hits<const AVX2: bool>(&self, ray: &Ray) -> u32 {
        #[cfg(target_arch = "x86_64")]
        if AVX2 {
            use std::arch::x86_64::_mm256_loadu_ps;
            // Each axis's planes of children 0-3 and 4-7 lie side by side: eight floats.
            // SAFETY: eight f32s read unaligned; the caller was compiled for AVX2 (`AVX2`).
            let load = |planes: &[Vec4; 2]| unsafe { _mm256_loadu_ps(planes.as_ptr().cast()) };
            // SAFETY: as above.
            let m = unsafe {
                child_planes_hits_avx2(
                    self.near.each_ref().map(load),
                    self.far.each_ref().map(load),
                    self.extent,
                    self.p,
                    ray,
                )
            };
            return self.masks[0][(m & 0xf) as usize] | self.masks[1][(m >> 4) as usize];
        }
        let [low, high] = child_box_hits(&self.near, &self.far, self.extent, self.p, ray);
        self.masks[0][low as usize] | self.masks[1][high as usize]
    }
}
