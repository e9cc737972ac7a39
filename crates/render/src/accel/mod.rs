//! The acceleration structure: an 8-wide compressed BVH (CWBVH, Ylitie et al. 2017) built by
//! `obvhs`, over triangles stored in BVH order so that a hit index needs no indirection. By
//! concern: the tree's build (`build.rs`), its nodes as single rays read them (`wide.rs`), the
//! triangles four to a block (`blocks.rs`), a single ray's walk and a stream of walks
//! (`walk.rs`), packets of camera rays (`packet.rs`), and small scenes tested whole instead
//! (`flat.rs`). Every way gives a ray the bits obvhs's own traversal gives it.

mod blocks;
mod build;
mod flat;
mod packet;
#[cfg(test)]
mod tests;
mod walk;
mod wide;

pub(crate) use blocks::row;
pub(crate) use flat::{FLAT_MAX, Flat, Rays8};

use crate::lanes::Lanes;
use blocks::TriangleBlock;
use build::{bounds_of, build_tree, builder_boxes, normalizing_scale, on_huge_pages};
use glam::{Vec3, Vec3A};
use obvhs::cwbvh::CwBvh;
use obvhs::ray::{Ray, RayHit};
use obvhs::rt_triangle::RtTriangle;
use obvhs::triangle::Triangle;
use wide::{WideNode, node_triangles};

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
/// (such small scenes are now tested whole: [`flat`]),
/// and on 4,000-triangle meshes 1.2-1.4x for incoherent rays. On the 1-million-triangle
/// MetalRoughSpheres it was 0.8x as fast until the tree went onto huge pages ([`on_huge_pages`]);
/// since then it is faster there too. 2 GiB covers the farm's default limit of 20 million
/// triangles, and stays below what loading such a scene takes. Past this, rays take obvhs's
/// traversal. Both give the same bits.
pub(super) const WALK_BUDGET: usize = 2 << 30;

/// Traversal stack entries, as obvhs's (a CWBVH's depth stays far below it).
pub(super) const STACK: usize = 32;

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
    /// What single rays walk the tree with: a node's eight child boxes tested in one AVX2 step
    /// (where the CPU has it) or four at a time; the two give the same bits.
    lanes: Lanes,
    /// Each node's triangles, four to a block.
    blocks: Vec<TriangleBlock>,
    /// A scene of at most [`FLAT_MAX`] triangles: all of them, which single rays test whole
    /// instead of walking the tree (see [`flat`]).
    flat: Option<Flat>,
    /// The triangles' bounds, padded: a packet's rays that miss this box are answered without
    /// a walk ([`Bvh::may_meet`]). `None` for an empty scene or one with non-finite bounds.
    reach: Option<[Vec3; 2]>,
}

/// How far [`Bvh::may_meet`]'s box reaches past the triangles, as a fraction of their largest
/// extent (and of a ray origin's largest coordinate): 800 times the rounding of an `f32`, so a
/// ray that the triangle tests could find a hit for, with their rounding, is never refused.
const REACH_PAD: f32 = 1e-4;

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
                lanes: Lanes::Portable,
                flat: None,
                reach: None,
            };
            return (empty, Vec::new());
        }
        let (lo, hi) = bounds_of(triangles);
        let scale = normalizing_scale(lo, hi);
        let reach = reach_of(lo, hi);
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
            let lanes = Lanes::Portable;
            let bvh = Self { cwbvh: Some(cwbvh), scale, triangles, wide, blocks, lanes, flat: None, reach };
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
        (
            Self {
                cwbvh: Some(cwbvh),
                scale,
                triangles,
                wide,
                blocks,
                lanes: Lanes::widest().at_most(Lanes::Avx2),
                flat: None,
                reach,
            },
            order,
        )
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

    /// False only where the ray `o + t d`, `t` in `(0, tmax)`, cannot meet any triangle: it misses
    /// the triangles' bounds padded by [`REACH_PAD`] of their extent and of the origin's size, by
    /// more than the rounding of this test. A camera ray that misses the scene then costs this
    /// slab test instead of the walk of the tree's root (`bench stages`). Anything uncertain (a
    /// NaN, infinities of both signs) answers true, and the walk decides as before.
    #[inline(always)]
    pub(super) fn may_meet(&self, o: Vec3, d: Vec3, tmax: f32) -> bool {
        let Some([lo, hi]) = self.reach else {
            return true;
        };
        let pad = Vec3::splat(REACH_PAD * o.abs().max_element());
        let (a, b) = ((lo - pad - o) / d, (hi + pad - o) / d);
        // f32::min and max pass over a NaN: an axis the ray runs in a padded face's plane
        // (0 / 0) leaves the interval to the others; that plane holds no triangle.
        let near = a.min(b).max_element().max(0.0);
        let far = a.max(b).min_element().min(tmax);
        let slack = REACH_PAD * near.abs().max(far.abs());
        // Refused only where the comparison holds; a NaN there keeps the ray.
        near.partial_cmp(&(far + slack)) != Some(std::cmp::Ordering::Greater)
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
}

/// The box [`Bvh::may_meet`] tests rays against: the triangles' bounds `lo`, `hi` padded by
/// [`REACH_PAD`] of their largest extent (at least the smallest normal `f32`); `None` where they
/// are not finite.
fn reach_of(lo: Vec3, hi: Vec3) -> Option<[Vec3; 2]> {
    let pad = Vec3::splat(((hi - lo).max_element() * REACH_PAD).max(f32::MIN_POSITIVE));
    (lo.is_finite() && hi.is_finite() && pad.is_finite()).then_some([lo - pad, hi + pad])
}

/// The ray `o + t d`, `t` in `(0, tmax)`. obvhs's traversal and [`Bvh::walk`] choose a box's near
/// planes by `d < 0` but scale by `1 / d`: a component of -0.0 counts as positive there while its
/// inverse is -inf, and the ray missed every box (a directional light shining straight along an
/// axis cast no shadows). Adding +0.0 turns -0.0 into +0.0 and leaves every other value as it is.
pub(super) fn ray_of(o: Vec3, d: Vec3, tmax: f32) -> Ray {
    Ray::new(Vec3A::from(o), Vec3A::from(d + Vec3::ZERO), 0.0, tmax)
}
