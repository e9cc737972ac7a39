//! A single ray's walk down the tree ([`Bvh::walk`]) and a stream of such walks taking turns
//! ([`Bvh::closest_hits_stream`], [`Walk`]), each the nodes, child order and tests of obvhs's
//! `ray_traverse`, so with its bits.

use super::{Bvh, STACK, ray_of};
use crate::lanes::{Lanes, dispatch_unchecked};
use glam::{UVec2, Vec3};
use obvhs::ray::Ray;

impl Bvh {
    /// One ray through the tree as obvhs's `ray_traverse` walks it: the same nodes, boxes and child
    /// order, and triangles tested with the arithmetic of `RtTriangle::intersect`, but with the
    /// eight child boxes tested in one AVX2 step where the CPU has it and a node's triangles four
    /// at a time, from blocks laid out at build. `hit(ray, slot, t)` is offered every triangle the
    /// ray meets at `t` in `(0, ray.tmax)`, in obvhs's order (within a node, the highest triangle
    /// first), and stops the walk by returning true; it may shorten `ray.tmax`. So a closest hit
    /// has the slot and distance bits obvhs gives it.
    #[inline(always)]
    pub(super) fn walk(&self, ray: &mut Ray, hit: &mut impl FnMut(&mut Ray, u32, f32) -> bool) -> bool {
        // SAFETY: `lanes` was chosen at build among what the CPU runs (`Lanes::widest`).
        unsafe {
            dispatch_unchecked(
                self.lanes,
                #[inline(always)]
                |lanes| match lanes {
                    Lanes::Portable => self.walk_with::<false>(ray, hit),
                    // `walk_with::<true>`'s AVX2 steps: compiled for `lanes`, which has AVX2.
                    _ => self.walk_with::<true>(ray, hit),
                },
            )
        }
    }

    /// The walk itself; `AVX2` only where [`Bvh::walk`] compiled it for AVX2.
    #[inline(always)]
    fn walk_with<const AVX2: bool>(&self, ray: &mut Ray, hit: &mut impl FnMut(&mut Ray, u32, f32) -> bool) -> bool {
        let (oct_inv4, negative) = ray_octant(ray);
        let mut stack = [UVec2::ZERO; STACK];
        let mut depth = 0usize;
        // Children still to visit (base index, hit bits in the high byte | parent's imask), and the
        // triangles of the last node (its first block and first slot, hit bits).
        let mut group = UVec2::new(0, 0x8000_0000);
        let (mut block, mut first_slot, mut prims) = (0u32, 0u32, 0u32);
        loop {
            while prims != 0 {
                let (quad, lanes) = take_quad(&mut prims);
                if self.blocks[(block + quad) as usize].offer(lanes, first_slot + 4 * quad, ray, hit) {
                    return true;
                }
            }
            if group.y & 0xff00_0000 != 0 {
                let hits_imask = group.y;
                let offset = 31 - hits_imask.leading_zeros();
                group.y &= !(1 << offset);
                if group.y & 0xff00_0000 != 0 {
                    stack[depth] = group;
                    depth = (depth + 1).min(STACK - 1);
                }
                let slot = (offset - 24) ^ (oct_inv4 & 0xff);
                let relative = (hits_imask & !(u32::MAX << slot)).count_ones();
                let wide = &self.wide[(group.x + relative) as usize];
                let mask = wide.hits::<AVX2>(ray, negative, oct_inv4);
                group = UVec2::new(wide.node.child_base_idx, (mask & 0xff00_0000) | wide.node.imask as u32);
                (block, first_slot, prims) = (wide.block, wide.node.primitive_base_idx, mask & 0x00ff_ffff);
            } else {
                group = UVec2::ZERO;
            }
            if prims == 0 && group.y & 0xff00_0000 == 0 {
                if depth == 0 {
                    return false;
                }
                depth -= 1;
                group = stack[depth];
            }
        }
    }

    /// Closest hits of `rays` `(o, d, tmax)`, each given to `found(r, hit)` as it is known (in no
    /// particular order), with the bits [`Bvh::closest_hit`] gives the ray alone. The rays walk the
    /// tree [`STREAM`] at a time, taking a step of each in turn and fetching the node each will
    /// visit next before stepping the others: rays whose paths share nothing (bounces off a curved
    /// surface) wait for memory together rather than one after another. That pays where the tree
    /// outgrows the caches (1.3x one by one on a million triangles); on a tree that fits, the
    /// switching between walks costs more than it hides (0.9x on 4,500 triangles).
    pub fn closest_hits_stream(
        &self,
        rays: &[(Vec3, Vec3, f32)],
        accept: impl Fn(usize, u32, f32) -> bool,
        mut found: impl FnMut(usize, Option<(u32, f32)>),
    ) {
        if self.wide.is_empty() || self.flat.is_some() {
            for (r, &(o, d, tmax)) in rays.iter().enumerate() {
                found(r, self.closest_hit(o, d, tmax, |slot, t| accept(r, slot, t)));
            }
            return;
        }
        // SAFETY: as in [`Bvh::walk`].
        unsafe {
            dispatch_unchecked(
                self.lanes,
                #[inline(always)]
                |lanes| match lanes {
                    Lanes::Portable => self.stream_with::<false>(rays, &accept, &mut found),
                    _ => self.stream_with::<true>(rays, &accept, &mut found),
                },
            )
        }
    }

    /// The stream itself; `AVX2` only where [`Bvh::closest_hits_stream`] compiled it for AVX2.
    #[inline(always)]
    fn stream_with<const AVX2: bool>(
        &self,
        rays: &[(Vec3, Vec3, f32)],
        accept: &impl Fn(usize, u32, f32) -> bool,
        found: &mut impl FnMut(usize, Option<(u32, f32)>),
    ) {
        // A lane: the ray's index (`IDLE` when the lane has none), its ray, walk and nearest hit.
        type Lane = (usize, Ray, Walk, Option<(u32, f32)>);
        const IDLE: usize = usize::MAX;
        let mut lanes: [Lane; STREAM] =
            std::array::from_fn(|_| (IDLE, ray_of(Vec3::ZERO, Vec3::Z, 0.0), Walk::idle(), None));
        let (mut next, mut busy) = (0usize, 0usize);
        loop {
            for (r, ray, walk, best) in &mut lanes {
                if *r == IDLE {
                    let Some(&(o, d, tmax)) = rays.get(next) else { continue };
                    (*r, *ray, *best, busy, next) = (next, self.ray_of(o, d, tmax), None, busy + 1, next + 1);
                    *walk = Walk::new(ray);
                }
                let index = *r;
                let accept = |slot, t: f32| accept(index, slot, t / self.scale);
                if walk.step::<AVX2, true>(self, ray, &mut self.nearest(&accept, best)).is_some() {
                    found(index, *best);
                    (*r, busy) = (IDLE, busy - 1);
                }
            }
            if busy == 0 && next == rays.len() {
                return;
            }
        }
    }
}

/// Rays that [`Bvh::closest_hits_stream`] walks side by side.
pub(super) const STREAM: usize = 8;

/// No node: the walk ends once its last node's triangles are tested.
pub(super) const NO_NODE: u32 = u32::MAX;

/// One ray's walk through the tree for [`Bvh::closest_hits_stream`], a node at a time: the nodes,
/// order and tests of [`Bvh::walk_with`], but each [`Walk::step`] tests the last node's triangles,
/// visits the next node and then chooses the one after it, so that the stream can fetch it while
/// other walks take their steps. Choosing the next node before testing the triangles changes no
/// bits: the choice depends on the node's hit mask and the stack, never on the nearest hit. (The
/// single-ray walk keeps its own loop: built on `step`, it took 10 % more instructions on the
/// Cornell box, whose tree stays in cache and gains nothing from fetching ahead; even the child
/// choice alone as a shared function took 0.6 % more of its walk's instructions.)
pub(super) struct Walk {
    oct_inv4: u32,
    negative: [bool; 3],
    stack: [UVec2; STACK],
    depth: usize,
    /// Children still to visit: base index, hit bits in the high byte | parent's imask.
    group: UVec2,
    /// The node the next step visits, or [`NO_NODE`].
    node: u32,
    /// The last node's triangles: its first block and first slot, and hit bits.
    block: u32,
    first_slot: u32,
    prims: u32,
}

impl Walk {
    /// A walk from the root.
    #[inline(always)]
    fn new(ray: &Ray) -> Self {
        let (oct_inv4, negative) = ray_octant(ray);
        Self { oct_inv4, negative, node: 0, ..Self::idle() }
    }

    /// A walk with nothing left to do.
    #[inline(always)]
    fn idle() -> Self {
        Self {
            oct_inv4: 0,
            negative: [false; 3],
            stack: [UVec2::ZERO; STACK],
            depth: 0,
            group: UVec2::ZERO,
            node: NO_NODE,
            block: 0,
            first_slot: 0,
            prims: 0,
        }
    }

    /// One step: `Some(stopped)` once the walk is over (`stopped` when `hit` stopped it). With
    /// `PREFETCH` it asks for the memory the next step reads.
    #[inline(always)]
    fn step<const AVX2: bool, const PREFETCH: bool>(
        &mut self,
        bvh: &Bvh,
        ray: &mut Ray,
        hit: &mut impl FnMut(&mut Ray, u32, f32) -> bool,
    ) -> Option<bool> {
        while self.prims != 0 {
            let (quad, lanes) = take_quad(&mut self.prims);
            if bvh.blocks[(self.block + quad) as usize].offer(lanes, self.first_slot + 4 * quad, ray, hit) {
                return Some(true);
            }
        }
        if self.node == NO_NODE {
            return Some(false);
        }
        let wide = &bvh.wide[self.node as usize];
        let mask = wide.hits::<AVX2>(ray, self.negative, self.oct_inv4);
        self.group = UVec2::new(wide.node.child_base_idx, (mask & 0xff00_0000) | wide.node.imask as u32);
        (self.block, self.first_slot, self.prims) = (wide.block, wide.node.primitive_base_idx, mask & 0x00ff_ffff);
        self.node = self.following();
        if PREFETCH {
            prefetch(bvh.wide.as_ptr().wrapping_add(self.node as usize));
            let mut quads = self.prims;
            while quads != 0 {
                let (quad, _) = take_quad(&mut quads);
                prefetch(bvh.blocks.as_ptr().wrapping_add((self.block + quad) as usize));
            }
        }
        None
    }

    /// The node to visit after the current one's triangles: its highest-priority child the ray's
    /// boxes reach (the rest of the group goes on the stack), else the next child of the group on
    /// top of the stack, else [`NO_NODE`].
    #[inline(always)]
    fn following(&mut self) -> u32 {
        loop {
            let hits_imask = self.group.y;
            if hits_imask & 0xff00_0000 != 0 {
                let offset = 31 - hits_imask.leading_zeros();
                self.group.y &= !(1 << offset);
                if self.group.y & 0xff00_0000 != 0 {
                    self.stack[self.depth] = self.group;
                    self.depth = (self.depth + 1).min(STACK - 1);
                }
                let slot = (offset - 24) ^ (self.oct_inv4 & 0xff);
                return self.group.x + (hits_imask & !(u32::MAX << slot)).count_ones();
            }
            if self.depth == 0 {
                return NO_NODE;
            }
            self.depth -= 1;
            self.group = self.stack[self.depth];
        }
    }
}

/// Takes the highest block of a node's triangle hit bits (four bits per block): clears them in
/// `prims` and returns the block's index within the node and its four bits.
#[inline(always)]
pub(super) fn take_quad(prims: &mut u32) -> (u32, u32) {
    let quad = (31 - prims.leading_zeros()) / 4;
    let lanes = (*prims >> (4 * quad)) & 0xf;
    *prims &= !(0xf << (4 * quad));
    (quad, lanes)
}

/// Asks for the cache lines of `*item` without waiting for them; any address will do (a
/// prefetch reads nothing into the program and never faults).
#[inline(always)]
pub(super) fn prefetch<T>(item: *const T) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_MM_HINT_T0, _mm_prefetch};
        let bytes = item as *const i8;
        for line in (0..size_of::<T>()).step_by(64) {
            // SAFETY: a prefetch is a hint: it dereferences nothing.
            unsafe { _mm_prefetch::<_MM_HINT_T0>(bytes.wrapping_add(line)) };
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = item;
}

/// A single ray's walk set-up, for [`Bvh::walk_with`] and [`Walk::new`] alike: its child order
/// ([`octant_inv4`]) and, per axis, whether it points to negative values (which picks a box's
/// near planes).
#[inline(always)]
pub(super) fn ray_octant(ray: &Ray) -> (u32, [bool; 3]) {
    let d = ray.direction;
    (octant_inv4(Vec3::from(d)), [d.x < 0.0, d.y < 0.0, d.z < 0.0])
}

/// obvhs's `ray_get_octant_inv4`: the child order for rays in `d`'s octant; a bit is clear
/// where `d` points to negative values on that axis.
#[inline(always)]
pub(super) fn octant_inv4(d: Vec3) -> u32 {
    (if d.x < 0.0 { 0 } else { 0x0404_0404 })
        | if d.y < 0.0 { 0 } else { 0x0202_0202 }
        | if d.z < 0.0 { 0 } else { 0x0101_0101 }
}
