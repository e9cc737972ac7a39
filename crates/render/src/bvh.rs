//! The acceleration structure: an 8-wide compressed BVH (CWBVH, Ylitie et al. 2017) built by
//! `obvhs`, over triangles stored in BVH order so that a hit index needs no indirection.

use crate::flat::{FLAT_MAX, Flat, Lanes, Rays8};
use glam::{BVec4A, UVec2, Vec3, Vec3A, Vec4};
use obvhs::aabb::Aabb;
use obvhs::cwbvh::CwBvh;
use obvhs::cwbvh::builder::build_cwbvh;
use obvhs::cwbvh::node::CwBvhNode;
use obvhs::ray::{Ray, RayHit};
use obvhs::rt_triangle::RtTriangle;
use obvhs::triangle::Triangle;
use obvhs::{Boundable, BvhBuildParams};
use std::collections::HashMap;
use std::time::Duration;

/// Rays that [`Bvh::closest_hits`] traces together.
pub const PACKET: usize = 8;

/// How a ray meets a scene's triangles.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RayTest {
    /// Down the tree, testing the boxes it reaches and the triangles in them.
    Walk,
    /// Every triangle, so many at a time (scenes of a few dozen triangles).
    Whole(Lanes),
}

impl std::fmt::Display for RayTest {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            RayTest::Walk => write!(f, "walking the tree"),
            RayTest::Whole(lanes) => write!(f, "every triangle, {lanes}"),
        }
    }
}

/// Largest size of the nodes and triangle blocks of [`Bvh::walk`], which single rays walk: on
/// the 32-triangle Cornell box the walk was 1.1x faster per render pass than obvhs's traversal
/// (such small scenes are now tested whole: [`crate::flat`]),
/// and on 4,000-triangle meshes 1.2-1.4x for incoherent rays. On the 1-million-triangle
/// MetalRoughSpheres it was 0.8x as fast until the tree went onto huge pages ([`on_huge_pages`]);
/// since then it is faster there too. 2 GiB covers the farm's default limit of 20 million
/// triangles, and stays below what loading such a scene takes. Past this, rays take obvhs's
/// traversal. Both give the same bits.
const WALK_BUDGET: usize = 2 << 30;

/// Traversal stack entries, as obvhs's (a CWBVH's depth stays far below it).
const STACK: usize = 32;

/// Triangles and their BVH. `order[i]` is the caller's index of BVH slot `i`.
///
/// The BVH holds the triangles multiplied by a power of two, `scale`, that brings their extent to
/// between 8 and 16, and rays are scaled alike on the way in and out. Scaling by a power of two
/// is exact, so hits and distances have the bits they would have unscaled, but obvhs's fixed
/// lower bound on box entry distances (1e-4) becomes relative to the scene: about 1e-5 of its
/// extent, the size of the ray-origin offset. Unscaled, a 5 mm scene lost hits nearer than 0.1 mm
/// (2 % of its size) and came out darker in its corners; now a scene and its copy scaled by a
/// power of two give the same image bits.
pub struct Bvh {
    cwbvh: Option<CwBvh>,
    /// The power of two that the stored triangles and the traced rays are multiplied by.
    scale: f32,
    triangles: Vec<RtTriangle>,
    /// obvhs's nodes with where their triangle blocks start, for single rays.
    wide: Vec<WideNode>,
    /// Whether single rays test a node's eight child boxes in one AVX2 step (chosen at build from
    /// what the CPU has) or four at a time; the two give the same bits.
    avx2: bool,
    /// Each node's triangles, four to a block.
    blocks: Vec<TriangleBlock>,
    /// A scene of at most [`FLAT_MAX`] triangles: all of them, which single rays test whole
    /// instead of walking the tree (see [`crate::flat`]).
    flat: Option<Flat>,
}

impl Bvh {
    /// Builds the BVH and returns it with the permutation from BVH slots to input triangles.
    pub fn build(triangles: &[[Vec3; 3]]) -> (Self, Vec<u32>) {
        let test = if triangles.len() <= FLAT_MAX { RayTest::Whole(Lanes::widest()) } else { RayTest::Walk };
        Self::build_testing(triangles, test).expect("the widest lanes this CPU has run on it")
    }

    /// As [`Bvh::build`], with single rays meeting the triangles as `test` says whatever the
    /// scene's size (for `tessera bench stages`, which times each way); `None` where `test` names
    /// lanes this CPU does not have.
    pub fn build_testing(triangles: &[[Vec3; 3]], test: RayTest) -> Option<(Self, Vec<u32>)> {
        if let RayTest::Whole(lanes) = test
            && !lanes.run_here()
        {
            return None;
        }
        let (mut bvh, order) = Self::build_with(triangles, WALK_BUDGET);
        if let RayTest::Whole(lanes) = test {
            bvh.flat = Some(Flat::new(&bvh.triangles, lanes));
        }
        Some((bvh, order))
    }

    /// How single rays meet the triangles.
    pub fn ray_test(&self) -> RayTest {
        self.flat.as_ref().map_or(RayTest::Walk, |flat| RayTest::Whole(flat.lanes()))
    }

    /// As [`Bvh::build`], decoding the nodes for single rays only when they and the triangle
    /// blocks take at most `walk_budget` bytes, and walking even the smallest scenes.
    fn build_with(triangles: &[[Vec3; 3]], walk_budget: usize) -> (Self, Vec<u32>) {
        if triangles.is_empty() {
            let empty = Self {
                cwbvh: None,
                scale: 1.0,
                triangles: Vec::new(),
                wide: Vec::new(),
                blocks: Vec::new(),
                avx2: false,
                flat: None,
            };
            return (empty, Vec::new());
        }
        let scale = normalizing_scale(triangles);
        let tris: Vec<Triangle> = triangles
            .iter()
            .map(|t| Triangle { v0: (t[0] * scale).into(), v1: (t[1] * scale).into(), v2: (t[2] * scale).into() })
            .collect();
        let mut cwbvh = build_tree(&builder_boxes(&tris));
        let order = cwbvh.primitive_indices.clone();
        let triangles = on_huge_pages(order.len(), order.iter().map(|&i| RtTriangle::from(&tris[i as usize])));
        cwbvh.nodes = on_huge_pages(cwbvh.nodes.len(), cwbvh.nodes.iter().copied());
        let blocks_needed: usize = cwbvh.nodes.iter().map(|n| node_triangles(n).div_ceil(4)).sum();
        let walk_bytes = cwbvh.nodes.len() * size_of::<WideNode>() + blocks_needed * size_of::<TriangleBlock>();
        if walk_bytes > walk_budget {
            let (wide, blocks) = (Vec::new(), Vec::new());
            let bvh = Self { cwbvh: Some(cwbvh), scale, triangles, wide, blocks, avx2: false, flat: None };
            return (bvh, order);
        }
        let mut blocks = on_huge_pages(blocks_needed, std::iter::empty());
        let walked = cwbvh.nodes.iter().map(|node| {
            let block = blocks.len() as u32;
            let (base, count) = (node.primitive_base_idx as usize, node_triangles(node));
            for first in (0..count).step_by(4) {
                blocks.push(TriangleBlock::new(&triangles[base + first..base + (first + 4).min(count)]));
            }
            WideNode::new(node, block)
        });
        let wide = on_huge_pages(cwbvh.nodes.len(), walked);
        (Self { cwbvh: Some(cwbvh), scale, triangles, wide, blocks, avx2: has_avx2(), flat: None }, order)
    }

    pub fn len(&self) -> usize {
        self.triangles.len()
    }

    pub fn is_empty(&self) -> bool {
        self.triangles.is_empty()
    }

    /// Closest hit along `o + t d`, `t` in `(0, tmax)`; `accept(slot, t)` may reject a hit (alpha cut-outs).
    pub fn closest_hit(&self, o: Vec3, d: Vec3, tmax: f32, accept: impl Fn(u32, f32) -> bool) -> Option<(u32, f32)> {
        let mut ray = self.ray_of(o, d, tmax);
        let accept = |slot, t| accept(slot, t / self.scale);
        if let Some(flat) = &self.flat {
            return flat.closest(&ray, accept).map(|(slot, t)| (slot, t / self.scale));
        }
        if self.wide.is_empty() {
            let bvh = self.cwbvh.as_ref()?;
            let mut hit = RayHit::none();
            let found = bvh.ray_traverse(ray, &mut hit, |r, id| self.accepted_distance(r, id, &accept));
            return found.then_some((hit.primitive_id, hit.t / self.scale));
        }
        let mut best = None;
        self.walk(&mut ray, &mut self.nearest(&accept, &mut best));
        best
    }

    /// A walk's `hit` for a closest hit: keeps in `best` each hit `accept(slot, t)` takes (slot and
    /// unscaled distance), and shortens the ray to it.
    #[inline(always)]
    fn nearest<'a>(
        &'a self,
        accept: &'a impl Fn(u32, f32) -> bool,
        best: &'a mut Option<(u32, f32)>,
    ) -> impl FnMut(&mut Ray, u32, f32) -> bool + 'a {
        move |ray: &mut Ray, slot, t| {
            if accept(slot, t) {
                *best = Some((slot, t / self.scale));
                ray.tmax = t;
            }
            false
        }
    }

    /// True when anything accepted lies along `o + t d`, `t` in `(0, tmax)`.
    pub fn occluded(&self, o: Vec3, d: Vec3, tmax: f32, accept: impl Fn(u32, f32) -> bool) -> bool {
        let mut ray = self.ray_of(o, d, tmax);
        let accept = |slot, t| accept(slot, t / self.scale);
        if let Some(flat) = &self.flat {
            return flat.any(&ray, accept);
        }
        if self.wide.is_empty() {
            let Some(bvh) = self.cwbvh.as_ref() else {
                return false;
            };
            return !bvh.ray_traverse_miss(ray, |r, id| self.accepted_distance(r, id, &accept));
        }
        self.walk(&mut ray, &mut |_: &mut Ray, slot, t| accept(slot, t))
    }

    /// [`Bvh::occluded`] without cut-outs, the same answer. A scene tested whole takes the ray's
    /// numbers as they are, without building a ray ([`Flat::blocked`]).
    #[inline(always)]
    pub(crate) fn occluded_plain(&self, o: Vec3, d: Vec3, tmax: f32) -> bool {
        match &self.flat {
            Some(flat) => {
                let (o, d, tmax) = self.scaled(o, d, tmax);
                flat.blocked(o.into(), d.into(), tmax)
            }
            None => self.occluded(o, d, tmax, |_, _| true),
        }
    }

    /// [`Bvh::closest_hit`] without cut-outs for the rays of the lanes where `live`, rows of
    /// eight: `o[axis][lane]`, `d[axis][lane]`. Each lane's answer has the bits its own call
    /// gives; a scene tested whole takes the eight rays together ([`Flat::nearest8`]).
    pub(crate) fn closest_hits8(
        &self,
        o: &[[f32; 8]; 3],
        d: &[[f32; 8]; 3],
        tmax: &[f32; 8],
        live: [bool; 8],
    ) -> [Option<(u32, f32)>; 8] {
        let Some(flat) = &self.flat else {
            return std::array::from_fn(|i| {
                live[i].then(|| self.closest_hit(row(o, i), row(d, i), tmax[i], |_, _| true))?
            });
        };
        let hits = flat.nearest8(&self.rays8(o, d, tmax, live));
        hits.map(|hit| hit.map(|(slot, t)| (slot, t / self.scale)))
    }

    /// Eight rays in the BVH's scaled units, each lane's numbers [`Bvh::scaled`]'s; a lane not
    /// `live` gets none.
    #[inline(always)]
    fn rays8(&self, o: &[[f32; 8]; 3], d: &[[f32; 8]; 3], tmax: &[f32; 8], live: [bool; 8]) -> Rays8 {
        let mut rays = Rays8 { o: [[0.0; 8]; 3], d: [[0.0; 8]; 3], tmax: [0.0; 8] };
        for i in 0..8 {
            let (o, d, t) = self.scaled(row(o, i), row(d, i), tmax[i]);
            for k in 0..3 {
                (rays.o[k][i], rays.d[k][i]) = (o[k], d[k]);
            }
            rays.tmax[i] = if live[i] { t } else { 0.0 };
        }
        rays
    }

    /// The ray `o + t d`, `t` in `(0, tmax)`, in the BVH's scaled units.
    fn ray_of(&self, o: Vec3, d: Vec3, tmax: f32) -> Ray {
        let (o, d, tmax) = self.scaled(o, d, tmax);
        Ray::new(Vec3A::from(o), Vec3A::from(d), 0.0, tmax)
    }

    /// A ray's numbers in the BVH's scaled units: origin and `tmax` scaled, and the direction with
    /// a negative zero made positive (`d + 0`, as [`ray_of`] says why). Every ray a walk or the
    /// whole-scene test takes comes through here.
    #[inline(always)]
    fn scaled(&self, o: Vec3, d: Vec3, tmax: f32) -> (Vec3, Vec3, f32) {
        (o * self.scale, d + Vec3::ZERO, tmax * self.scale)
    }

    /// For obvhs's traversals: the distance at which the ray meets triangle `slot`, when it lies in
    /// `(0, tmax]` and `accept` takes it; otherwise infinity (a miss).
    #[inline(always)]
    fn accepted_distance(&self, ray: &Ray, slot: usize, accept: &impl Fn(u32, f32) -> bool) -> f32 {
        let t = self.triangles[slot].intersect(ray);
        if t.is_finite() && t > 0.0 && accept(slot as u32, t) { t } else { f32::INFINITY }
    }

    /// One ray through the tree as obvhs's `ray_traverse` walks it: the same nodes, boxes and child
    /// order, and triangles tested with the arithmetic of `RtTriangle::intersect`, but with the
    /// eight child boxes tested in one AVX2 step where the CPU has it and a node's triangles four
    /// at a time, from blocks laid out at build. `hit(ray, slot, t)` is offered every triangle the
    /// ray meets at `t` in `(0, ray.tmax)`, in obvhs's order (within a node, the highest triangle
    /// first), and stops the walk by returning true; it may shorten `ray.tmax`. So a closest hit
    /// has the slot and distance bits obvhs gives it.
    #[inline(always)]
    fn walk(&self, ray: &mut Ray, hit: &mut impl FnMut(&mut Ray, u32, f32) -> bool) -> bool {
        #[cfg(target_arch = "x86_64")]
        if self.avx2 {
            // SAFETY: `avx2` is set only where the CPU has AVX2, BMI1, BMI2 and LZCNT.
            return unsafe { self.walk_avx2(ray, hit) };
        }
        self.walk_with::<false>(ray, hit)
    }

    /// [`Bvh::walk`] compiled for AVX2, with child boxes tested eight at a time.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,bmi1,bmi2,lzcnt")]
    fn walk_avx2(&self, ray: &mut Ray, hit: &mut impl FnMut(&mut Ray, u32, f32) -> bool) -> bool {
        self.walk_with::<true>(ray, hit)
    }

    /// The walk itself; `AVX2` only where [`Bvh::walk_avx2`] calls it.
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
        #[cfg(target_arch = "x86_64")]
        if self.avx2 {
            // SAFETY: `avx2` is set only where the CPU has AVX2, BMI1, BMI2 and LZCNT.
            return unsafe { self.stream_avx2(rays, &accept, &mut found) };
        }
        self.stream_with::<false>(rays, &accept, &mut found)
    }

    /// [`Bvh::closest_hits_stream`] compiled for AVX2.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,bmi1,bmi2,lzcnt")]
    fn stream_avx2(
        &self,
        rays: &[(Vec3, Vec3, f32)],
        accept: &impl Fn(usize, u32, f32) -> bool,
        found: &mut impl FnMut(usize, Option<(u32, f32)>),
    ) {
        self.stream_with::<true>(rays, accept, found)
    }

    /// The stream itself; `AVX2` only where [`Bvh::stream_avx2`] calls it.
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

    /// Closest hits of up to [`PACKET`] rays `(o, d, tmax)` traced together; `accept(ray, slot, t)`
    /// as in [`Bvh::closest_hit`]. Each ray's answer has the bits `closest_hit` gives it alone: the
    /// packet walks the union of the rays' paths in the order one ray would, and tests each ray only
    /// at the nodes and triangles its own boxes reach, against its own nearest hit so far. Rays that
    /// do not share one direction octant (so one child order) are traced one by one.
    // Indexed lane loops: the zipped-iterator forms measured 10-25% slower in `bench rays`.
    #[allow(clippy::needless_range_loop)]
    pub fn closest_hits(
        &self,
        rays: &[(Vec3, Vec3, f32)],
        accept: impl Fn(usize, u32, f32) -> bool,
    ) -> [Option<(u32, f32)>; PACKET] {
        let mut out = [None; PACKET];
        assert!(rays.len() <= PACKET, "at most {PACKET} rays in a packet");
        let Some(bvh) = self.cwbvh.as_ref() else {
            return out;
        };
        let oct_inv4 = rays.first().map_or(0, |r| octant_inv4(r.1));
        if rays.len() < 2 || rays.iter().any(|r| octant_inv4(r.1) != oct_inv4) || self.flat.is_some() {
            for (r, &(o, d, tmax)) in rays.iter().enumerate() {
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
        let mut group = (UVec2::new(0, 0x8000_0000), [0x8000_0000u32; PACKET]);
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
                        mask[r] = planes.hits(&ray[r]);
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

/// More triangles than this with bit-identical boxes are a crowd that [`builder_boxes`] spreads.
/// Two triangles of a quad share a box, and so may a few more in real meshes; these keep their own.
const CROWD: u32 = 16;

/// The boxes the builder sorts the triangles by: each triangle's own box (obvhs's, as its
/// `build_cwbvh_from_tris` would take them), except in a crowd of more than [`CROWD`] triangles
/// whose boxes are bit-identical, as a triangle repeated thousands of times in a broken or hostile
/// file has it. PLOC finds no nearest pair among equal boxes and merges them one at a time:
/// n coincident triangles cost O(n^2) (32,768 took 24 s to load) and came out as a chain n deep,
/// whose conversion to a CWBVH overflowed the stack, and whose traversal would overflow its
/// 32-entry stack. Member `k` of a crowd of `m` gets its box stretched to also cover a copy of it
/// moved one box width along the `k`-th of `m` directions spread evenly over the sphere: still a
/// bound of the triangle, so hits are unchanged (boxes only prune), but no box holds another,
/// and PLOC builds them into a balanced tree in O(m log m).
fn builder_boxes(tris: &[Triangle]) -> Vec<Aabb> {
    let mut boxes: Vec<Aabb> = tris.iter().map(Boundable::aabb).collect();
    let key = |b: &Aabb| -> [u32; 6] {
        let (lo, hi) = (b.min.to_array(), b.max.to_array());
        [lo[0], lo[1], lo[2], hi[0], hi[1], hi[2]].map(f32::to_bits)
    };
    // (members, members spread so far) per distinct box.
    let mut crowds: HashMap<[u32; 6], (u32, u32), BoxHash> = HashMap::with_capacity_and_hasher(boxes.len(), BoxHash);
    for b in &boxes {
        crowds.entry(key(b)).or_default().0 += 1;
    }
    if crowds.values().all(|&(m, _)| m <= CROWD) {
        return boxes;
    }
    for b in &mut boxes {
        let Some((m, k)) = crowds.get_mut(&key(b)).filter(|(m, _)| *m > CROWD) else { continue };
        let d = spread_direction(*k, *m) * (b.max - b.min).max_element();
        *k += 1;
        *b = b.union(&Aabb { min: b.min + d, max: b.max + d });
    }
    boxes
}

/// The `k`-th of `m` unit vectors spread evenly over the sphere (a Fibonacci lattice).
fn spread_direction(k: u32, m: u32) -> Vec3A {
    const GOLDEN_ANGLE: f64 = 2.399_963_229_728_653;
    let z = 1.0 - (2.0 * k as f64 + 1.0) / m as f64;
    let r = libm::sqrt((1.0 - z * z).max(0.0));
    let phi = GOLDEN_ANGLE * k as f64;
    Vec3A::new((r * libm::cos(phi)) as f32, (r * libm::sin(phi)) as f32, z as f32)
}

/// A cheap hash of box bits for [`builder_boxes`] (SipHash costs more than the grouping saves).
#[derive(Clone, Copy, Default)]
struct BoxHash;

impl std::hash::BuildHasher for BoxHash {
    type Hasher = BoxHasher;
    fn build_hasher(&self) -> BoxHasher {
        BoxHasher(0)
    }
}

struct BoxHasher(u64);

impl std::hash::Hasher for BoxHasher {
    fn finish(&self) -> u64 {
        self.0
    }
    /// A box's six `u32`s arrive here as 24 bytes (and its length as a `usize`): eight at a time.
    fn write(&mut self, bytes: &[u8]) {
        let mut words = bytes.chunks_exact(8);
        for word in &mut words {
            self.write_u64(u64::from_le_bytes([
                word[0], word[1], word[2], word[3], word[4], word[5], word[6], word[7],
            ]));
        }
        for &b in words.remainder() {
            self.write_u64(b as u64);
        }
    }
    fn write_u64(&mut self, v: u64) {
        self.0 = (self.0.rotate_left(5) ^ v).wrapping_mul(0x51_7c_c1_b7_27_22_0a_95);
    }
}

/// obvhs's build (PLOC, reinsertion, conversion to a CWBVH), without spatial pre-splits (they
/// would make primitive indices repeat). It runs on a thread with a large stack: the conversion
/// recurses once per level, and a tree left deep by input no one foresaw must not overflow a
/// small stack (a tokio blocking thread has 2 MiB) and abort the process.
fn build_tree(boxes: &[Aabb]) -> CwBvh {
    const BUILD_STACK: usize = 256 << 20;
    let params = BvhBuildParams { pre_split: false, ..BvhBuildParams::medium_build() };
    let build = || build_cwbvh(boxes, params, &mut Duration::default());
    std::thread::scope(|scope| {
        match std::thread::Builder::new().name("bvh-build".into()).stack_size(BUILD_STACK).spawn_scoped(scope, build) {
            Ok(handle) => handle.join().unwrap_or_else(|panic| std::panic::resume_unwind(panic)),
            // No thread to be had: build here, as before.
            Err(_) => build(),
        }
    })
}

/// The power of two that brings the triangles' extent (their bounding box's longest side) to
/// between 8 and 16; 1 for triangles of no extent. The exponent comes from the bits, so no
/// rounding can move it.
fn normalizing_scale(triangles: &[[Vec3; 3]]) -> f32 {
    let (mut lo, mut hi) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
    for v in triangles.iter().flatten() {
        (lo, hi) = (lo.min(*v), hi.max(*v));
    }
    let extent = (hi - lo).max_element();
    if !extent.is_normal() {
        return 1.0;
    }
    // The extent lies in [2^e, 2^(e+1)); the scale is 2^(3 - e), kept a normal f32.
    let e = ((extent.to_bits() >> 23) & 0xff) as i32 - 127;
    f32::from_bits(((127 + 3 - e).clamp(1, 254) as u32) << 23)
}

/// A vector with room for `len` items, holding `items` (none, for a caller that pushes them
/// later: it must not push more than `len`, or they move off). The kernel is asked, before the
/// memory is first written, to back it with huge pages (2 MiB on x86-64) where it can. Rays
/// through a big tree go to nodes and triangles all over tens of megabytes; with 4 KiB pages most
/// of those loads also miss the address translation cache and wait for a page walk. Where
/// transparent huge pages are on ("madvise" or "always" in
/// /sys/kernel/mm/transparent_hugepage/enabled) this takes the page walks away; elsewhere it
/// changes nothing. Nothing depends on it: the bits are the same.
fn on_huge_pages<T>(len: usize, items: impl Iterator<Item = T>) -> Vec<T> {
    let mut v = Vec::with_capacity(len);
    #[cfg(target_os = "linux")]
    {
        const HUGE: usize = 2 << 20;
        let (start, bytes) = (v.as_ptr() as usize, len * size_of::<T>());
        // The whole huge pages inside the allocation; below one there is nothing to gain.
        let (first, end) = (start.next_multiple_of(HUGE), (start + bytes) / HUGE * HUGE);
        if end > first {
            // SAFETY: the range lies inside `v`'s allocation, which nothing has written yet;
            // the advice only changes how its pages are backed, never their contents.
            unsafe { libc::madvise(first as *mut libc::c_void, end - first, libc::MADV_HUGEPAGE) };
        }
    }
    v.extend(items);
    v
}

/// How many triangles a node's leaf children hold (they lie together from `primitive_base_idx`).
fn node_triangles(node: &CwBvhNode) -> usize {
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
struct WideNode {
    node: CwBvhNode,
    /// The node's first [`TriangleBlock`].
    block: u32,
}

impl WideNode {
    fn new(node: &CwBvhNode, block: u32) -> Self {
        Self { node: *node, block }
    }

    /// The ray's hit mask for this node, as obvhs's `intersect_ray_simd` makes it (and so with its
    /// bits): children in the high byte by traversal priority, triangles below. `AVX2` tests the
    /// eight child boxes in one step, where the caller is compiled for it.
    #[inline(always)]
    fn hits<const AVX2: bool>(&self, ray: &Ray, negative: [bool; 3], oct_inv4: u32) -> u32 {
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
            // SAFETY: `AVX2` is true only in `Bvh::walk_avx2`, which runs where the CPU has AVX2.
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

/// Rays that [`Bvh::closest_hits_stream`] walks side by side.
const STREAM: usize = 8;

/// No node: the walk ends once its last node's triangles are tested.
const NO_NODE: u32 = u32::MAX;

/// One ray's walk through the tree for [`Bvh::closest_hits_stream`], a node at a time: the nodes,
/// order and tests of [`Bvh::walk_with`], but each [`Walk::step`] tests the last node's triangles,
/// visits the next node and then chooses the one after it, so that the stream can fetch it while
/// other walks take their steps. Choosing the next node before testing the triangles changes no
/// bits: the choice depends on the node's hit mask and the stack, never on the nearest hit. (The
/// single-ray walk keeps its own loop: built on `step`, it took 10 % more instructions on the
/// Cornell box, whose tree stays in cache and gains nothing from fetching ahead; even the child
/// choice alone as a shared function took 0.6 % more of its walk's instructions.)
struct Walk {
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
fn take_quad(prims: &mut u32) -> (u32, u32) {
    let quad = (31 - prims.leading_zeros()) / 4;
    let lanes = (*prims >> (4 * quad)) & 0xf;
    *prims &= !(0xf << (4 * quad));
    (quad, lanes)
}

/// Asks for the cache lines of `*item` without waiting for them; any address will do (a
/// prefetch reads nothing into the program and never faults).
#[inline(always)]
fn prefetch<T>(item: *const T) {
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

/// Children 0-7 of a node as bytes to `f32`, four at a time (exact).
#[inline(always)]
fn byte_planes(q: &[u8; 8]) -> [Vec4; 2] {
    std::array::from_fn(|half| Vec4::from_array(std::array::from_fn(|i| q[4 * half + i] as f32)))
}

/// Which of a node's eight children the ray's boxes reach, one bit each, from the quantised near
/// and far planes per axis, four children at a time with [`child_box_hits`].
#[inline(always)]
fn child_box_hits_of_bytes(near: [&[u8; 8]; 3], far: [&[u8; 8]; 3], extent: Vec3A, p: Vec3A, ray: &Ray) -> u32 {
    let [low, high] = child_box_hits(&near.map(byte_planes), &far.map(byte_planes), extent, p, ray);
    low | high << 4
}

/// [`child_box_hits_of_bytes`] with the eight children in one AVX register: the same operations on
/// each child in the same order (multiply, then add; no fused multiply-add), so the same bits.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
fn child_box_hits_avx2(near: [&[u8; 8]; 3], far: [&[u8; 8]; 3], extent: Vec3A, p: Vec3A, ray: &Ray) -> u32 {
    use std::arch::x86_64::*;
    let scale = extent * ray.inv_direction;
    let origin = (p - ray.origin) * ray.inv_direction;
    #[target_feature(enable = "avx2")]
    #[inline]
    fn distances(q: &[u8; 8], scale: f32, origin: f32) -> __m256 {
        let planes = _mm256_cvtepi32_ps(_mm256_cvtepu8_epi32(_mm_cvtsi64_si128(i64::from_le_bytes(*q))));
        _mm256_add_ps(_mm256_mul_ps(planes, _mm256_set1_ps(scale)), _mm256_set1_ps(origin))
    }
    let (s, o) = (scale.to_array(), origin.to_array());
    let tmin = _mm256_max_ps(
        distances(near[0], s[0], o[0]),
        _mm256_max_ps(distances(near[1], s[1], o[1]), distances(near[2], s[2], o[2])),
    );
    let tmax = _mm256_min_ps(
        distances(far[0], s[0], o[0]),
        _mm256_min_ps(distances(far[1], s[1], o[1]), distances(far[2], s[2], o[2])),
    );
    let tmin = _mm256_max_ps(tmin, _mm256_set1_ps(BOX_EPSILON));
    let tmax = _mm256_min_ps(tmax, _mm256_set1_ps(ray.tmax));
    _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_LE_OQ>(tmin, tmax)) as u32
}

/// Whether this CPU runs [`Bvh::walk_avx2`].
fn has_avx2() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        is_x86_feature_detected!("avx2")
            && is_x86_feature_detected!("bmi1")
            && is_x86_feature_detected!("bmi2")
            && is_x86_feature_detected!("lzcnt")
    }
    #[cfg(not(target_arch = "x86_64"))]
    false
}

/// Which of a node's children 0-3 and 4-7 the ray's boxes reach, one bit each, given their near
/// and far planes per axis (in the node's quantised units, for the ray's octant) and the node's
/// `compute_extent()` and `p`. The arithmetic
/// of obvhs's `CwBvhNode::intersect_ray_simd`, operand for operand, so that the bits agree.
#[inline(always)]
fn child_box_hits(near: &[[Vec4; 2]; 3], far: &[[Vec4; 2]; 3], extent: Vec3A, p: Vec3A, ray: &Ray) -> [u32; 2] {
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

/// The ray `o + t d`, `t` in `(0, tmax)`. obvhs's traversal and [`Bvh::walk`] choose a box's near
/// planes by `d < 0` but scale by `1 / d`: a component of -0.0 counts as positive there while its
/// inverse is -inf, and the ray missed every box (a directional light shining straight along an
/// axis cast no shadows). Adding +0.0 turns -0.0 into +0.0 and leaves every other value as it is.
fn ray_of(o: Vec3, d: Vec3, tmax: f32) -> Ray {
    Ray::new(Vec3A::from(o), Vec3A::from(d + Vec3::ZERO), 0.0, tmax)
}

/// A single ray's walk set-up, for [`Bvh::walk_with`] and [`Walk::new`] alike: its child order
/// ([`octant_inv4`]) and, per axis, whether it points to negative values (which picks a box's
/// near planes).
#[inline(always)]
fn ray_octant(ray: &Ray) -> (u32, [bool; 3]) {
    let d = ray.direction;
    (octant_inv4(Vec3::from(d)), [d.x < 0.0, d.y < 0.0, d.z < 0.0])
}

/// obvhs's `ray_get_octant_inv4`: the child order for rays in `d`'s octant; a bit is clear
/// where `d` points to negative values on that axis.
#[inline(always)]
fn octant_inv4(d: Vec3) -> u32 {
    (if d.x < 0.0 { 0 } else { 0x0404_0404 })
        | if d.y < 0.0 { 0 } else { 0x0202_0202 }
        | if d.z < 0.0 { 0 } else { 0x0101_0101 }
}

/// A node's child boxes decoded once for all the rays of a packet (which share one octant), and
/// tested against each ray with the arithmetic of obvhs's `CwBvhNode::intersect_ray`, so that a
/// ray's hit mask has the same bits as when it traverses alone.
struct ChildPlanes {
    /// Near and far planes per axis for the octant, children 0-3 and 4-7, in quantised units.
    near: [[Vec4; 2]; 3],
    far: [[Vec4; 2]; 3],
    extent: Vec3A,
    p: Vec3A,
    /// The hit mask of each subset of children 0-3 and of children 4-7 (from obvhs's
    /// `get_child_and_index_bits`), so that a ray's mask needs no loop over the children it hits.
    masks: [[u32; 16]; 2],
}

/// obvhs's lower bound on box entry distances, in the BVH's units (see [`Bvh`]).
const BOX_EPSILON: f32 = 0.0001;

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

    #[inline(always)]
    fn hits(&self, ray: &Ray) -> u32 {
        let [low, high] = child_box_hits(&self.near, &self.far, self.extent, self.p, ray);
        self.masks[0][low as usize] | self.masks[1][high as usize]
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sampler::{mix64, unit_f32};

    /// A point uniform in the unit cube, from a counter.
    fn uniform3(state: &mut u64) -> Vec3 {
        Vec3::from_array(std::array::from_fn(|_| {
            *state += 1;
            unit_f32(mix64(*state))
        }))
    }

    /// A soup of small and large triangles, some sharing edges, some axis-aligned.
    fn soup(n: usize, state: &mut u64) -> Vec<[Vec3; 3]> {
        let mut tris = Vec::new();
        while tris.len() < n {
            let p = uniform3(state) * 10.0 - 5.0;
            let size = if tris.len() % 7 == 0 { 4.0 } else { 0.3 };
            let a = p + (uniform3(state) - 0.5) * size;
            let b = p + (uniform3(state) - 0.5) * size;
            tris.push([p, a, b]);
            if tris.len() % 5 == 0 {
                tris.push([p, b, Vec3::new(p.x, a.y, b.z)]); // shares an edge with the previous one
            }
            if tris.len() % 11 == 0 {
                tris.push([p, Vec3::new(p.x + size, p.y, p.z), Vec3::new(p.x, p.y + size, p.z)]); // flat in z
            }
        }
        tris
    }

    /// Scalar Möller-Trumbore, written independently of the intersection test the BVH uses.
    fn reference_intersect(v: &[Vec3; 3], o: Vec3, d: Vec3) -> Option<f32> {
        let (e1, e2) = (v[1] - v[0], v[2] - v[0]);
        let p = d.cross(e2);
        let det = e1.dot(p);
        if det == 0.0 {
            return None;
        }
        let s = o - v[0];
        let u = s.dot(p) / det;
        let q = s.cross(e1);
        let w = d.dot(q) / det;
        let t = e2.dot(q) / det;
        (u >= 0.0 && w >= 0.0 && u + w <= 1.0 && t > 0.0).then_some(t)
    }

    /// Closest accepted hit by testing every triangle (slots in BVH order).
    fn brute_force(tris: &[[Vec3; 3]], o: Vec3, d: Vec3, tmax: f32, accept: impl Fn(u32) -> bool) -> Option<f32> {
        let ts = tris.iter().enumerate().filter_map(|(i, v)| reference_intersect(v, o, d).filter(|_| accept(i as u32)));
        ts.filter(|&t| t < tmax).min_by(f32::total_cmp)
    }

    /// Equal up to the two formulations' rounding.
    fn close(a: Option<f32>, b: Option<f32>) -> bool {
        match (a, b) {
            (Some(a), Some(b)) => (a - b).abs() <= 1e-4 * a.abs().max(1.0),
            (a, b) => a == b,
        }
    }

    /// Every ray finds the hit distance brute force finds (same triangle, or another at the same
    /// distance), with and without a distance limit and with a rejecting `accept`; occlusion agrees.
    /// Both for the walk and for obvhs's traversal (a tree over the walk's budget).
    #[test]
    fn traversal_agrees_with_brute_force() {
        for (budget, avx2) in [(WALK_BUDGET, true), (WALK_BUDGET, false), (0, false)] {
            traversal_agrees_with_brute_force_within(budget, avx2);
        }
    }

    fn traversal_agrees_with_brute_force_within(budget: usize, avx2: bool) {
        let mut state = 7;
        let input = soup(3000, &mut state);
        let (mut bvh, order) = Bvh::build_with(&input, budget);
        bvh.avx2 &= avx2;
        assert_eq!(bvh.wide.is_empty(), budget == 0, "the walk is laid out within the budget only");
        let in_order: Vec<[Vec3; 3]> = order.iter().map(|&i| input[i as usize]).collect();
        assert_eq!(bvh.len(), input.len());
        let mut sorted = order.clone();
        sorted.sort_unstable();
        assert!(sorted.iter().enumerate().all(|(i, &s)| i as u32 == s), "order is a permutation");
        let reject_odd = |slot: u32| order[slot as usize] % 2 == 0;
        let (mut hits, mut rejected_differs) = (0, 0);
        for i in 0..4000 {
            let o = uniform3(&mut state) * 14.0 - 7.0;
            let mut d = uniform3(&mut state) - 0.5;
            if i % 4 == 0 {
                d = [Vec3::X, Vec3::NEG_Y, Vec3::Z][i % 3]; // axis-aligned: zero direction components
            }
            let d = d.normalize();
            let tmax = if i % 3 == 0 { 4.0 } else { f32::INFINITY };
            let expect = brute_force(&in_order, o, d, tmax, |_| true);
            let got = bvh.closest_hit(o, d, tmax, |_, _| true);
            assert!(close(got.map(|h| h.1), expect), "ray {i}: {o} {d} tmax {tmax}: {got:?} against {expect:?}");
            if let Some((slot, t)) = got {
                assert!(close(reference_intersect(&in_order[slot as usize], o, d), Some(t)), "ray {i}: slot");
            }
            assert_eq!(bvh.occluded(o, d, tmax, |_, _| true), expect.is_some(), "ray {i} occlusion");
            hits += expect.is_some() as usize;
            let expect_cut = brute_force(&in_order, o, d, tmax, reject_odd);
            let got_cut = bvh.closest_hit(o, d, tmax, |slot, _| reject_odd(slot));
            assert!(close(got_cut.map(|h| h.1), expect_cut), "ray {i} with cut-outs");
            assert!(got_cut.is_none_or(|(slot, _)| reject_odd(slot)));
            assert_eq!(bvh.occluded(o, d, tmax, |slot, _| reject_odd(slot)), expect_cut.is_some());
            rejected_differs += (expect_cut != expect) as usize;
        }
        assert!(
            hits > 1000 && rejected_differs > 100,
            "the rays exercise hits ({hits}) and cut-outs ({rejected_differs})"
        );
    }

    /// A packet gives each ray exactly the hit (slot and distance bits) it gets alone: coherent
    /// packets (a pinhole's neighbouring rays), packets whose rays spread over octants (traced one by
    /// one), partial packets, distance limits, and cut-outs that differ from ray to ray.
    #[test]
    fn packets_give_each_ray_its_own_hit() {
        let mut state = 11;
        let input = soup(3000, &mut state);
        let (bvh, order) = Bvh::build(&input);
        let (mut hits, mut coherent) = (0, 0);
        for p in 0..1500 {
            let eye = uniform3(&mut state) * 16.0 - 8.0;
            let towards = (uniform3(&mut state) * 6.0 - 3.0 - eye).normalize();
            let spread = [0.002, 0.02, 0.3, 2.0][p % 4];
            let lanes = if p % 5 == 0 { 1 + p % PACKET } else { PACKET };
            let rays: Vec<(Vec3, Vec3, f32)> = (0..lanes)
                .map(|r| {
                    let d = (towards + (uniform3(&mut state) - 0.5) * spread).normalize();
                    let tmax = if (p + r) % 3 == 0 { 1.0 + 6.0 * uniform3(&mut state).x } else { f32::INFINITY };
                    (eye, d, tmax)
                })
                .collect();
            let cut = p % 2 == 1;
            let accept = |r: usize, slot: u32| !cut || !(order[slot as usize] as usize + r).is_multiple_of(3);
            let got = bvh.closest_hits(&rays, |r, slot, _| accept(r, slot));
            coherent += rays.iter().all(|r| octant_inv4(r.1) == octant_inv4(rays[0].1)) as usize;
            for (r, &(o, d, tmax)) in rays.iter().enumerate() {
                let alone = bvh.closest_hit(o, d, tmax, |slot, _| accept(r, slot));
                assert_eq!(
                    got[r].map(|(s, t)| (s, t.to_bits())),
                    alone.map(|(s, t)| (s, t.to_bits())),
                    "packet {p}, ray {r}"
                );
                hits += alone.is_some() as usize;
            }
            assert!(got[lanes..].iter().all(Option::is_none), "packet {p}: lanes past the rays stay empty");
        }
        assert!(hits > 2000 && coherent > 1000, "the packets exercise hits ({hits}) and shared octants ({coherent})");
    }

    /// A stream of rays, walked side by side with lanes refilled as rays finish, gives every ray
    /// the slot and distance bits it gets alone, exactly once: incoherent rays with and without a
    /// distance limit, cut-outs that depend on the ray, streams shorter and longer than the lanes,
    /// with both box tests, and through obvhs's traversal where the walk's nodes are not built.
    #[test]
    fn streams_give_each_ray_its_own_hit() {
        let mut state = 17;
        let input = soup(3000, &mut state);
        for (budget, avx2) in [(WALK_BUDGET, true), (WALK_BUDGET, false), (0, false)] {
            let (mut bvh, order) = Bvh::build_with(&input, budget);
            bvh.avx2 &= avx2;
            let mut hits = 0;
            for (s, len) in [0, 1, 5, STREAM, 3 * STREAM + 1, 700].into_iter().enumerate() {
                let rays: Vec<(Vec3, Vec3, f32)> = (0..len)
                    .map(|r| {
                        let o = uniform3(&mut state) * 16.0 - 8.0;
                        let d = (uniform3(&mut state) - 0.5).normalize();
                        (o, d, if r % 3 == 0 { 1.0 + 6.0 * uniform3(&mut state).x } else { f32::INFINITY })
                    })
                    .collect();
                let accept = |r: usize, slot: u32| s % 2 == 0 || !(order[slot as usize] as usize + r).is_multiple_of(3);
                let mut got = vec![Vec::new(); len];
                bvh.closest_hits_stream(&rays, |r, slot, _| accept(r, slot), |r, hit| got[r].push(hit));
                for (r, &(o, d, tmax)) in rays.iter().enumerate() {
                    let alone = bvh.closest_hit(o, d, tmax, |slot, _| accept(r, slot));
                    let key = |h: Option<(u32, f32)>| h.map(|(s, t)| (s, t.to_bits()));
                    assert_eq!(got[r].len(), 1, "budget {budget}, stream {s}, ray {r}: one answer");
                    assert_eq!(key(got[r][0]), key(alone), "budget {budget}, stream {s}, ray {r}");
                    hits += alone.is_some() as usize;
                }
            }
            assert!(hits > 100, "the streams exercise hits ({hits})");
        }
    }

    /// A single ray's walk (child boxes eight at a time with AVX2 or four at a time without,
    /// triangles four at a time) gives every ray the slot and distance bits obvhs's `ray_traverse`
    /// gives it, and `ray_traverse_miss`'s answer: random and axis-aligned rays from inside and
    /// outside the soup, distance limits that end on or before hits, and cut-outs. On a CPU
    /// without AVX2 both walks below are the portable one.
    #[test]
    fn single_rays_get_obvhs_bits() {
        let mut state = 5;
        let input = soup(3000, &mut state);
        let (bvh, order) = Bvh::build(&input);
        assert!(!bvh.wide.is_empty(), "3000 triangles are walked");
        assert_eq!(bvh.avx2, has_avx2(), "the walk takes AVX2 where the CPU has it");
        let (mut portable, _) = Bvh::build(&input);
        portable.avx2 = false;
        // Over its budget the tree is left to obvhs's traversal: the reference.
        let (obvhs, _) = Bvh::build_with(&input, 0);
        let obvhs_walk = |o, d, tmax, accept: &dyn Fn(u32) -> bool| {
            (obvhs.closest_hit(o, d, tmax, |slot, _| accept(slot)), obvhs.occluded(o, d, tmax, |slot, _| accept(slot)))
        };
        let (mut hits, mut limited, mut occluded) = (0, 0, 0);
        for i in 0..6000 {
            let o = uniform3(&mut state) * 14.0 - 7.0;
            let mut d = uniform3(&mut state) - 0.5;
            if i % 5 == 0 {
                d = [Vec3::X, Vec3::NEG_Y, Vec3::Z, Vec3::new(1.0, 1.0, 0.0)][i % 4];
            }
            let d = d.normalize();
            let cut = i % 2 == 1;
            let accept = |slot: u32| !cut || !order[slot as usize].is_multiple_of(3);
            let (full, _) = obvhs_walk(o, d, f32::INFINITY, &accept);
            // Limits: none, exactly at the first hit (exclusive there), or short of it.
            let tmax = match (i % 3, full) {
                (1, Some((_, t))) => t,
                (2, Some((_, t))) => 0.5 * t + 1e-3,
                _ => f32::INFINITY,
            };
            let (expect, expect_occluded) = obvhs_walk(o, d, tmax, &accept);
            for (walk, bvh) in [("avx2", &bvh), ("portable", &portable)] {
                let got = bvh.closest_hit(o, d, tmax, |slot, _| accept(slot));
                assert_eq!(
                    got.map(|(s, t)| (s, t.to_bits())),
                    expect.map(|(s, t)| (s, t.to_bits())),
                    "{walk} walk, ray {i}: {o} {d} tmax {tmax}"
                );
                let occluded = bvh.occluded(o, d, tmax, |slot, _| accept(slot));
                assert_eq!(occluded, expect_occluded, "{walk} walk, ray {i} occlusion");
            }
            hits += expect.is_some() as usize;
            limited += (tmax.is_finite() && expect.is_none()) as usize;
            occluded += expect_occluded as usize;
        }
        assert!(
            hits > 600 && limited > 1000 && occluded > 600,
            "hits {hits}, cut short {limited}, occluded {occluded}"
        );
    }

    /// Small scenes tested whole: every width this CPU runs gives each ray the slot and distance
    /// bits the portable lanes give it (closest hits with and without cut-outs, distance limits
    /// that end on or before the hit, shadow rays), and the walk over the same triangles meets the
    /// same triangle at the same distance, except where two triangles are met at exactly one
    /// distance: the walk takes the first it visits, the whole test the lower slot. Rays aimed at
    /// corners, which triangles share, and at triangles the scene holds twice make such ties.
    #[test]
    fn whole_scenes_meet_what_the_walk_meets() {
        let mut state = 11;
        let (mut hits, mut ties, mut limited) = (0, 0, 0);
        for n in [1, 3, 16, 17, 36, 63, FLAT_MAX] {
            let mut input = soup(n, &mut state);
            input.truncate(n);
            for j in 0..n / 4 {
                input[n - 1 - j] = input[j];
            }
            let input = &input[..];
            let (walk, order) = Bvh::build_testing(input, RayTest::Walk).unwrap();
            assert_eq!(
                Bvh::build(input).0.ray_test(),
                RayTest::Whole(Lanes::widest()),
                "{n} triangles are tested whole"
            );
            let whole: Vec<(Lanes, Bvh)> = Lanes::ALL
                .into_iter()
                .filter_map(|lanes| {
                    let (bvh, same) = Bvh::build_testing(input, RayTest::Whole(lanes))?;
                    assert_eq!(same, order, "one build, one slot order");
                    Some((lanes, bvh))
                })
                .collect();
            let portable = &whole.last().expect("the portable lanes run anywhere").1;
            for i in 0..3000 {
                let o = uniform3(&mut state) * 12.0 - 6.0;
                let [a, b, c] = input[i % n];
                let d = match i % 4 {
                    0 => [a, b, c][i % 3] - o,
                    1 => [Vec3::X, Vec3::new(-0.0, -1.0, -0.0), Vec3::new(0.3, 0.0, -1.0)][i % 3],
                    2 => uniform3(&mut state) - 0.5,
                    _ => (a + b + c) / 3.0 - o,
                };
                let d = d.normalize();
                let cut = i % 2 == 1;
                let accept = |slot: u32| !cut || !order[slot as usize].is_multiple_of(3);
                let full = portable.closest_hit(o, d, f32::INFINITY, |slot, _| accept(slot));
                let tmax = match (i / 4 % 3, full) {
                    (1, Some((_, t))) => t,
                    (2, Some((_, t))) => 0.5 * t + 1e-3,
                    _ => f32::INFINITY,
                };
                let key = |h: Option<(u32, f32)>| h.map(|(s, t)| (s, t.to_bits()));
                let expect = portable.closest_hit(o, d, tmax, |slot, _| accept(slot));
                let expect_occluded = portable.occluded(o, d, tmax, |slot, _| accept(slot));
                for (lanes, bvh) in &whole {
                    let got = bvh.closest_hit(o, d, tmax, |slot, _| accept(slot));
                    assert_eq!(key(got), key(expect), "{lanes}, {n} triangles, ray {i}: {o} {d} tmax {tmax}");
                    let blocked = bvh.occluded(o, d, tmax, |slot, _| accept(slot));
                    assert_eq!(blocked, expect_occluded, "{lanes}, {n} triangles, ray {i} occlusion");
                }
                let walked = walk.closest_hit(o, d, tmax, |slot, _| accept(slot));
                match (walked, expect) {
                    (Some((a, ta)), Some((b, tb))) if a != b => {
                        assert_eq!(ta.to_bits(), tb.to_bits(), "{n} triangles, ray {i}: slots {a} and {b} differ");
                        assert!(b < a, "the lower slot of a tie");
                        ties += 1;
                    }
                    _ => assert_eq!(key(walked), key(expect), "{n} triangles, ray {i}: walk and whole"),
                }
                assert_eq!(walk.occluded(o, d, tmax, |slot, _| accept(slot)), expect_occluded, "ray {i}");
                hits += expect.is_some() as usize;
                limited += (tmax.is_finite() && expect.is_none()) as usize;
            }
        }
        assert!(hits > 1000 && limited > 2000 && ties > 5, "hits {hits}, cut short {limited}, ties {ties}");
    }

    /// The AVX2 box test gives the portable test's bits for any node and ray: rays inside, near and
    /// far from the node, along its axes, with distance limits, and with the NaNs that an infinite
    /// inverse direction gives on a slab's plane (0 x inf; `Ray::new` keeps inverses finite, so
    /// these are set by hand), where the operand order of min and max decides the answer.
    /// (On a CPU without AVX2 there is nothing to compare, and the test says so.)
    #[test]
    fn avx2_box_test_matches_the_portable_one() {
        if !has_avx2() {
            eprintln!("this CPU has no AVX2: only the portable box test runs here");
            return;
        }
        let mut state = 3u64;
        let next = |state: &mut u64| {
            *state += 1;
            mix64(*state)
        };
        let (mut nans, mut hits) = (0, 0);
        for i in 0..50_000 {
            let (a, b) = (next(&mut state).to_le_bytes(), next(&mut state).to_le_bytes());
            let lo: [[u8; 8]; 3] = std::array::from_fn(|axis| std::array::from_fn(|c| a[c].min(b[c]) >> axis));
            let hi: [[u8; 8]; 3] = std::array::from_fn(|axis| std::array::from_fn(|c| a[c].max(b[c]) >> axis));
            let p = Vec3A::from(uniform3(&mut state) * 8.0 - 4.0);
            let e = next(&mut state);
            let extent = Vec3A::from_array(std::array::from_fn(|axis| {
                f32::from_bits((118 + ((e >> (8 * axis)) & 7) as u32) << 23)
            }));
            let o = Vec3::from(p + extent * Vec3A::from(uniform3(&mut state) * 400.0 - 72.0));
            let mut d = uniform3(&mut state) - 0.5;
            if i % 5 == 0 {
                d[i % 3] = 0.0;
            }
            let tmax = [f32::INFINITY, 50.0, 0.5][i % 3];
            let mut ray = ray_of(o, d, tmax);
            if i % 7 == 0 {
                let axis = i % 3;
                ray.inv_direction[axis] = if i % 2 == 0 { f32::INFINITY } else { f32::NEG_INFINITY };
                ray.origin[axis] = p[axis];
            }
            let pick =
                |axis: usize, near: bool| if (ray.direction[axis] < 0.0) == near { &hi[axis] } else { &lo[axis] };
            let near = std::array::from_fn(|axis| pick(axis, true));
            let far = std::array::from_fn(|axis| pick(axis, false));
            let portable = child_box_hits_of_bytes(near, far, extent, p, &ray);
            // SAFETY: the CPU has AVX2 (checked above).
            let avx2 = unsafe { child_box_hits_avx2(near, far, extent, p, &ray) };
            assert_eq!(avx2, portable, "case {i}: {ray:?}, extent {extent}, p {p}");
            nans += ((p - ray.origin) * ray.inv_direction).is_nan() as usize;
            hits += (portable != 0) as usize;
        }
        assert!(nans > 1000 && hits > 5000, "the cases exercise NaNs ({nans}) and hits ({hits})");
    }

    /// Rays along an axis whose other components are -0.0 (as `-direction` of a light shining
    /// along an axis gives) meet what lies ahead, in both traversals and in packets.
    #[test]
    fn negative_zero_directions_hit() {
        // A big triangle across each axis at distance 2, around the origin.
        let axes = [Vec3::X, Vec3::NEG_X, Vec3::Y, Vec3::NEG_Y, Vec3::Z, Vec3::NEG_Z];
        let walls: Vec<[Vec3; 3]> = axes
            .iter()
            .map(|&a| {
                let (u, v) = a.any_orthonormal_pair();
                let c = a * 2.0;
                [c - u * 9.0 - v * 9.0, c + u * 9.0 - v * 9.0, c + v * 9.0]
            })
            .collect();
        // And with 3000 more far off the axes, so that the tree is deep enough to be walked.
        let mut many = walls.clone();
        many.extend(soup(3000, &mut 3).iter().map(|t| t.map(|p| p + Vec3::splat(30.0))));
        for input in [&walls, &many] {
            for (budget, avx2) in [(WALK_BUDGET, true), (WALK_BUDGET, false), (0, false)] {
                let (mut bvh, _) = Bvh::build_with(input, budget);
                bvh.avx2 &= avx2;
                for a in axes {
                    let d = Vec3::new(
                        if a.x == 0.0 { -0.0 } else { a.x },
                        if a.y == 0.0 { -0.0 } else { a.y },
                        if a.z == 0.0 { -0.0 } else { a.z },
                    );
                    let what = format!("{} triangles, budget {budget}, AVX2 {}, along {d:?}", input.len(), bvh.avx2);
                    let hit = bvh.closest_hit(Vec3::ZERO, d, f32::INFINITY, |_, _| true);
                    assert!(hit.is_some_and(|(_, t)| (t - 2.0).abs() < 1e-5), "{what}: {hit:?}");
                    assert!(bvh.occluded(Vec3::ZERO, d, f32::INFINITY, |_, _| true), "{what}: not occluded");
                    let rays = [(Vec3::ZERO, d, f32::INFINITY), (Vec3::ZERO, d, 3.0)];
                    let hits = bvh.closest_hits(&rays, |_, _, _| true);
                    assert!(hits[..2].iter().all(|h| h.is_some_and(|(_, t)| (t - 2.0).abs() < 1e-5)), "{what}: packet");
                }
            }
        }
    }

    /// 32,768 copies of one triangle once took obvhs's builder 24 s and a chain 32,768 deep whose
    /// conversion overflowed the stack (the process aborted). The crowd is spread into a
    /// balanced tree, and every ray through the triangle still hits it.
    #[test]
    fn coincident_triangles_build_a_shallow_tree() {
        let tri = [Vec3::new(0.0, 0.0, 1.0), Vec3::new(1.0, 0.0, 1.0), Vec3::new(0.0, 1.0, 1.0)];
        let input = vec![tri; 1 << 15];
        let (bvh, order) = Bvh::build(&input);
        assert_eq!(order.len(), input.len());
        let cwbvh = bvh.cwbvh.as_ref().unwrap();
        let depth = cwbvh_depth(cwbvh);
        assert!(
            depth <= 16,
            "a CWBVH {depth} levels deep over coincident triangles (its traversal stack has 32 entries)"
        );
        for (x, y) in [(0.1, 0.1), (0.4, 0.5), (0.05, 0.9)] {
            let hit = bvh.closest_hit(Vec3::new(x, y, 0.0), Vec3::Z, f32::INFINITY, |_, _| true);
            assert_eq!(hit.map(|(_, t)| t), Some(1.0), "({x}, {y})");
            assert!(bvh.occluded(Vec3::new(x, y, 0.0), Vec3::Z, 2.0, |_, _| true));
        }
        assert!(bvh.closest_hit(Vec3::new(0.9, 0.9, 0.0), Vec3::Z, f32::INFINITY, |_, _| true).is_none());
    }

    /// Levels of a CWBVH, counted from its root.
    fn cwbvh_depth(cwbvh: &CwBvh) -> usize {
        let mut deepest = 0;
        let mut stack = vec![(0usize, 1usize)];
        while let Some((i, depth)) = stack.pop() {
            deepest = deepest.max(depth);
            let node = &cwbvh.nodes[i];
            for child in (0..8).filter(|&c| !node.is_child_empty(c) && !node.is_leaf(c)) {
                stack.push((node.child_node_index(child) as usize, depth + 1));
            }
        }
        deepest
    }

    #[test]
    fn empty_and_single_triangle() {
        let (bvh, order) = Bvh::build(&[]);
        assert!(bvh.is_empty() && order.is_empty());
        assert_eq!(bvh.closest_hit(Vec3::ZERO, Vec3::Z, f32::INFINITY, |_, _| true), None);
        assert!(!bvh.occluded(Vec3::ZERO, Vec3::Z, f32::INFINITY, |_, _| true));
        let (bvh, _) = Bvh::build(&[[Vec3::new(-1.0, -1.0, 2.0), Vec3::new(1.0, -1.0, 2.0), Vec3::new(0.0, 1.0, 2.0)]]);
        assert_eq!(bvh.closest_hit(Vec3::ZERO, Vec3::Z, f32::INFINITY, |_, _| true), Some((0, 2.0)));
        assert_eq!(bvh.closest_hit(Vec3::ZERO, Vec3::Z, 2.0, |_, _| true), None, "tmax is exclusive");
        assert_eq!(bvh.closest_hit(Vec3::ZERO, Vec3::NEG_Z, f32::INFINITY, |_, _| true), None, "behind the origin");
    }
}
