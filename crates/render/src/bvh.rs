//! The acceleration structure. `obvhs` builds an 8-wide BVH (CWBVH, Ylitie et al. 2017, with its
//! SAH-optimal collapse of a PLOC binary tree); we keep its topology and leaf order but store each
//! node's child boxes uncompressed, as exact `f32` bounds of the triangles below them, in
//! structure-of-arrays form so that one node is two 4-wide slab tests. The compressed node is made
//! for GPU memory bandwidth; on a CPU its decoding costs more than the 3x larger node, and exact
//! boxes cull more than quantised ones. Each leaf (at most three triangles) is one 4-wide packet
//! tested at once. Traversal is ours: children are visited nearest first and a stacked child is
//! dropped when it lies beyond the closest hit found so far.

use glam::{Vec3, Vec4};
use obvhs::BvhBuildParams;
use obvhs::cwbvh::builder::build_cwbvh_from_tris;
use obvhs::cwbvh::node::CwBvhNode;
use obvhs::triangle::Triangle;
use std::mem::MaybeUninit;
use std::time::Duration;

/// Child reference: a node index, or `LEAF | packet << 2 | count` (count 1..=3 triangles, as CWBVH
/// leaves have), or `EMPTY`.
const LEAF: u32 = 1 << 31;
const EMPTY: u32 = u32::MAX;
const MAX_LEAF_FIRST: u32 = (LEAF >> 2) - 1;

/// Slab distances are scaled by this before the overlap test so that rounding in the box test can
/// never cull a box the ray touches (Ize 2013, "Robust BVH ray traversal": 1 + 2 gamma(3)).
const TFAR_SCALE: f32 = 1.0 + 2.0 * (3.0 * f32::EPSILON * 0.5) / (1.0 - 3.0 * f32::EPSILON * 0.5);

/// Eight children's boxes (`bounds[axis][0]` the low planes, `[1]` the high ones, each two halves of
/// four children) and references.
#[derive(Clone, Copy)]
#[repr(C, align(64))]
struct Node {
    bounds: [[[Vec4; 2]; 2]; 3],
    child: [u32; 8],
}

/// Up to four triangles as the intersection test wants them, structure of arrays: a vertex, two
/// edges and the unnormalised normal, each `[x, y, z]` over the four lanes.
#[derive(Clone, Copy)]
#[repr(C, align(64))]
struct Tri4 {
    v0: [Vec4; 3],
    e1: [Vec4; 3],
    e2: [Vec4; 3],
    ng: [Vec4; 3],
}

fn dot(a: &[Vec4; 3], b: &[Vec4; 3]) -> Vec4 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

impl Tri4 {
    /// Packs up to four triangles; lanes past `tris.len()` are never reported.
    fn new(tris: &[[Vec3; 3]]) -> Self {
        let mut p = Self { v0: [Vec4::ZERO; 3], e1: [Vec4::ZERO; 3], e2: [Vec4::ZERO; 3], ng: [Vec4::ZERO; 3] };
        for (lane, v) in tris.iter().enumerate() {
            let (e1, e2) = (v[1] - v[0], v[2] - v[0]);
            let ng = (-e1).cross(e2);
            for a in 0..3 {
                (p.v0[a][lane], p.e1[a][lane], p.e2[a][lane], p.ng[a][lane]) = (v[0][a], e1[a], e2[a], ng[a]);
            }
        }
        p
    }

    /// Per lane, the distance to the hit, or infinity (Möller-Trumbore with the normal
    /// precomputed; edges inclusive, and a NaN from a degenerate triangle never hits).
    #[inline(always)]
    fn intersect(&self, o: &[Vec4; 3], d: &[Vec4; 3], tmax: f32) -> Vec4 {
        let c = [self.v0[0] - o[0], self.v0[1] - o[1], self.v0[2] - o[2]];
        let r = [d[1] * c[2] - d[2] * c[1], d[2] * c[0] - d[0] * c[2], d[0] * c[1] - d[1] * c[0]];
        let inv_det = Vec4::ONE / dot(&self.ng, d);
        let u = dot(&r, &self.e2) * inv_det;
        let v = -dot(&r, &self.e1) * inv_det;
        let w = Vec4::ONE - u - v;
        let t = dot(&self.ng, &c) * inv_det;
        let hit = u.cmpge(Vec4::ZERO)
            & v.cmpge(Vec4::ZERO)
            & w.cmpge(Vec4::ZERO)
            & t.cmpgt(Vec4::ZERO)
            & t.cmplt(Vec4::splat(tmax));
        Vec4::select(hit, t, Vec4::INFINITY)
    }
}

/// Triangles (in BVH order) and the nodes over them.
pub struct Bvh {
    nodes: Vec<Node>,
    /// One packet per leaf, and the BVH slot of its first triangle.
    packets: Vec<Tri4>,
    first: Vec<u32>,
    triangles: usize,
    /// Stack entries one traversal can need: 7 per level below the root, plus one.
    stack_size: usize,
}

/// Stacks up to this size live on the machine stack; deeper trees (degenerate input) use the heap.
const INLINE_STACK: usize = 96;

/// A ray prepared for slab tests.
struct SlabRay {
    o: [Vec4; 3],
    inv: [Vec4; 3],
    /// Per axis, the index of the near planes in `Node::bounds` (1 when the direction is negative).
    near: [usize; 3],
}

impl SlabRay {
    fn new(o: Vec3, d: Vec3) -> Self {
        // A zero component becomes a huge finite reciprocal of the right sign, never inf * 0 = NaN.
        let inv = |x: f32| {
            let tiny = f32::MIN_POSITIVE;
            1.0 / if x.abs() < tiny { tiny.copysign(x) } else { x }
        };
        Self {
            o: [Vec4::splat(o.x), Vec4::splat(o.y), Vec4::splat(o.z)],
            inv: [Vec4::splat(inv(d.x)), Vec4::splat(inv(d.y)), Vec4::splat(inv(d.z))],
            near: [(d.x < 0.0) as usize, (d.y < 0.0) as usize, (d.z < 0.0) as usize],
        }
    }

    /// Entry distances of the eight children and the bitmask of those the ray meets within `tmax`.
    #[inline(always)]
    fn test(&self, node: &Node, tmax: f32) -> ([Vec4; 2], u32) {
        let mut near = [Vec4::ZERO; 2];
        let mut mask = 0;
        for (h, out) in near.iter_mut().enumerate() {
            let mut t0 = Vec4::ZERO;
            let mut t1 = Vec4::INFINITY;
            for a in 0..3 {
                let (lo, hi) = (node.bounds[a][0][h], node.bounds[a][1][h]);
                let (n, f) = if self.near[a] == 1 { (hi, lo) } else { (lo, hi) };
                t0 = t0.max((n - self.o[a]) * self.inv[a]);
                t1 = t1.min((f - self.o[a]) * self.inv[a]);
            }
            let t1 = (t1 * TFAR_SCALE).min(Vec4::splat(tmax));
            *out = t0;
            mask |= t0.cmple(t1).bitmask() << (4 * h);
        }
        (near, mask)
    }
}

/// A traversal stack of `u64` entries (entry distance in the high half, child reference in the low).
struct Stack<'a> {
    items: &'a mut [MaybeUninit<u64>],
    len: usize,
}

impl Stack<'_> {
    #[inline(always)]
    fn push(&mut self, v: u64) {
        self.items[self.len] = MaybeUninit::new(v);
        self.len += 1;
    }

    #[inline(always)]
    fn pop(&mut self) -> Option<u64> {
        self.len = self.len.checked_sub(1)?;
        // SAFETY: every slot below `len` was written by `push`.
        Some(unsafe { self.items[self.len].assume_init() })
    }
}

impl Bvh {
    /// Builds the BVH and returns it with the permutation from BVH slots to input triangles.
    pub fn build(triangles: &[[Vec3; 3]]) -> (Self, Vec<u32>) {
        let empty = Self { nodes: Vec::new(), packets: Vec::new(), first: Vec::new(), triangles: 0, stack_size: 1 };
        if triangles.is_empty() {
            return (empty, Vec::new());
        }
        assert!(triangles.len() < MAX_LEAF_FIRST as usize, "more than {MAX_LEAF_FIRST} triangles in one scene");
        let tris: Vec<Triangle> =
            triangles.iter().map(|t| Triangle { v0: t[0].into(), v1: t[1].into(), v2: t[2].into() }).collect();
        // No spatial pre-splits: they would make primitive indices repeat.
        let params = BvhBuildParams { pre_split: false, ..BvhBuildParams::medium_build() };
        let cwbvh = build_cwbvh_from_tris(&tris, params, &mut Duration::default());
        let order = cwbvh.primitive_indices.clone();
        let in_order: Vec<[Vec3; 3]> = order.iter().map(|&i| triangles[i as usize]).collect();
        let mut bvh = Self {
            nodes: vec![Node { bounds: [[[Vec4::ZERO; 2]; 2]; 3], child: [EMPTY; 8] }; cwbvh.nodes.len()],
            packets: Vec::new(),
            first: Vec::new(),
            triangles: triangles.len(),
            stack_size: 1,
        };
        let (_, depth) = bvh.convert(&cwbvh.nodes, &in_order, 0);
        bvh.stack_size = 7 * depth + 1;
        (bvh, order)
    }

    /// Fills node `i` from the CWBVH node of the same index; returns its exact bounds and depth.
    fn convert(&mut self, cw: &[CwBvhNode], tris: &[[Vec3; 3]], i: usize) -> ((Vec3, Vec3), usize) {
        let src = &cw[i];
        let empty = [[Vec4::splat(f32::INFINITY); 2], [Vec4::splat(f32::NEG_INFINITY); 2]];
        let mut node = Node { bounds: [empty; 3], child: [EMPTY; 8] };
        let (mut lo, mut hi) = (Vec3::INFINITY, Vec3::NEG_INFINITY);
        let mut depth = 1;
        for c in 0..8 {
            if src.is_child_empty(c) {
                continue;
            }
            let (reference, (clo, chi)) = if src.is_leaf(c) {
                let (first, count) = src.child_primitives(c);
                let bounds = tris[first as usize..(first + count) as usize]
                    .iter()
                    .flatten()
                    .fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(l, h), &p| (l.min(p), h.max(p)));
                let packet = self.packets.len() as u32;
                self.packets.push(Tri4::new(&tris[first as usize..(first + count) as usize]));
                self.first.push(first);
                (LEAF | packet << 2 | count, bounds)
            } else {
                let child = src.child_node_index(c);
                let (bounds, d) = self.convert(cw, tris, child as usize);
                depth = depth.max(d + 1);
                (child, bounds)
            };
            node.child[c] = reference;
            for a in 0..3 {
                node.bounds[a][0][c / 4][c % 4] = clo[a];
                node.bounds[a][1][c / 4][c % 4] = chi[a];
            }
            (lo, hi) = (lo.min(clo), hi.max(chi));
        }
        self.nodes[i] = node;
        ((lo, hi), depth)
    }

    #[inline(always)]
    fn prefetch(&self, reference: u32) {
        #[cfg(target_arch = "x86_64")]
        unsafe {
            use std::arch::x86_64::{_MM_HINT_T0, _mm_prefetch};
            if reference & LEAF == 0 {
                let p = self.nodes.as_ptr().add(reference as usize) as *const i8;
                _mm_prefetch(p, _MM_HINT_T0);
                _mm_prefetch(p.add(64), _MM_HINT_T0);
                _mm_prefetch(p.add(128), _MM_HINT_T0);
            } else {
                let p = self.packets.as_ptr().add(((reference & !LEAF) >> 2) as usize) as *const i8;
                _mm_prefetch(p, _MM_HINT_T0);
                _mm_prefetch(p.add(64), _MM_HINT_T0);
                _mm_prefetch(p.add(128), _MM_HINT_T0);
            }
        }
    }

    pub fn len(&self) -> usize {
        self.triangles
    }

    pub fn is_empty(&self) -> bool {
        self.triangles == 0
    }

    /// Runs `f` with an empty stack large enough for this tree.
    #[inline(always)]
    fn with_stack<R>(&self, f: impl FnOnce(Stack) -> R) -> R {
        if self.stack_size <= INLINE_STACK {
            let mut items = [MaybeUninit::uninit(); INLINE_STACK];
            f(Stack { items: &mut items, len: 0 })
        } else {
            let mut items = vec![MaybeUninit::uninit(); self.stack_size];
            f(Stack { items: &mut items, len: 0 })
        }
    }

    /// Closest hit along `o + t d`, `t` in `(0, tmax)`; `accept(slot, t)` may reject a hit (alpha cut-outs).
    pub fn closest_hit(&self, o: Vec3, d: Vec3, tmax: f32, accept: impl Fn(u32, f32) -> bool) -> Option<(u32, f32)> {
        if self.nodes.is_empty() {
            return None;
        }
        let ray = SlabRay::new(o, d);
        let (o4, d4) = (o.to_array().map(Vec4::splat), d.to_array().map(Vec4::splat));
        self.with_stack(|mut stack| {
            let mut best: Option<(u32, f32)> = None;
            let mut tmax = tmax;
            let mut current = 0u32; // the root
            loop {
                if current & LEAF == 0 {
                    let node = &self.nodes[current as usize];
                    let (near, mut mask) = ray.test(node, tmax);
                    // Children hit, nearest first: push all but the nearest, farthest first.
                    let mut keys = [0u64; 8];
                    let mut n = 0;
                    while mask != 0 {
                        let c = mask.trailing_zeros() as usize;
                        mask &= mask - 1;
                        let key = u64::from(near[c / 4][c % 4].to_bits()) << 32 | u64::from(node.child[c]);
                        self.prefetch(node.child[c]);
                        // Insertion into the sorted prefix (at most eight entries).
                        let mut j = n;
                        while j > 0 && keys[j - 1] > key {
                            keys[j] = keys[j - 1];
                            j -= 1;
                        }
                        keys[j] = key;
                        n += 1;
                    }
                    if n > 0 {
                        for &k in keys[1..n].iter().rev() {
                            stack.push(k);
                        }
                        current = keys[0] as u32;
                        continue;
                    }
                } else {
                    let packet = ((current & !LEAF) >> 2) as usize;
                    let t = self.packets[packet].intersect(&o4, &d4, tmax);
                    let mut lanes = t.cmplt(Vec4::INFINITY).bitmask() & ((1 << (current & 3)) - 1);
                    while lanes != 0 {
                        let lane = lanes.trailing_zeros() as usize;
                        lanes &= lanes - 1;
                        let slot = self.first[packet] + lane as u32;
                        if t[lane] < tmax && accept(slot, t[lane]) {
                            tmax = t[lane];
                            best = Some((slot, t[lane]));
                        }
                    }
                }
                // Next: the nearest stacked child that may still hold a closer hit.
                loop {
                    let Some(k) = stack.pop() else {
                        return best;
                    };
                    if f32::from_bits((k >> 32) as u32) <= tmax {
                        current = k as u32;
                        break;
                    }
                }
            }
        })
    }

    /// True when anything accepted lies along `o + t d`, `t` in `(0, tmax)`.
    pub fn occluded(&self, o: Vec3, d: Vec3, tmax: f32, accept: impl Fn(u32, f32) -> bool) -> bool {
        if self.nodes.is_empty() {
            return false;
        }
        let ray = SlabRay::new(o, d);
        let (o4, d4) = (o.to_array().map(Vec4::splat), d.to_array().map(Vec4::splat));
        self.with_stack(|mut stack| {
            stack.push(0);
            while let Some(k) = stack.pop() {
                let current = k as u32;
                if current & LEAF == 0 {
                    let node = &self.nodes[current as usize];
                    let (_, mut mask) = ray.test(node, tmax);
                    while mask != 0 {
                        let c = mask.trailing_zeros() as usize;
                        mask &= mask - 1;
                        stack.push(u64::from(node.child[c]));
                    }
                } else {
                    let packet = ((current & !LEAF) >> 2) as usize;
                    let t = self.packets[packet].intersect(&o4, &d4, tmax);
                    let mut lanes = t.cmplt(Vec4::INFINITY).bitmask() & ((1 << (current & 3)) - 1);
                    while lanes != 0 {
                        let lane = lanes.trailing_zeros() as usize;
                        lanes &= lanes - 1;
                        if accept(self.first[packet] + lane as u32, t[lane]) {
                            return true;
                        }
                    }
                }
            }
            false
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sampler::mix64;

    fn uniform(state: &mut u64) -> f32 {
        *state += 1;
        (mix64(*state) >> 40) as f32 / (1u64 << 24) as f32
    }

    /// A soup of small and large triangles, some sharing edges, some axis-aligned.
    fn soup(n: usize, state: &mut u64) -> Vec<[Vec3; 3]> {
        let mut tris = Vec::new();
        while tris.len() < n {
            let p = Vec3::new(uniform(state), uniform(state), uniform(state)) * 10.0 - 5.0;
            let size = if tris.len() % 7 == 0 { 4.0 } else { 0.3 };
            let a = p + (Vec3::new(uniform(state), uniform(state), uniform(state)) - 0.5) * size;
            let b = p + (Vec3::new(uniform(state), uniform(state), uniform(state)) - 0.5) * size;
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

    /// Scalar Möller-Trumbore, written independently of the packet test.
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
    #[test]
    fn traversal_agrees_with_brute_force() {
        let mut state = 7;
        let input = soup(3000, &mut state);
        let (bvh, order) = Bvh::build(&input);
        let in_order: Vec<[Vec3; 3]> = order.iter().map(|&i| input[i as usize]).collect();
        assert_eq!(bvh.len(), input.len());
        let mut sorted = order.clone();
        sorted.sort_unstable();
        assert!(sorted.iter().enumerate().all(|(i, &s)| i as u32 == s), "order is a permutation");
        assert!(bvh.stack_size > 1);
        let reject_odd = |slot: u32| order[slot as usize] % 2 == 0;
        let (mut hits, mut rejected_differs) = (0, 0);
        for i in 0..4000 {
            let o = Vec3::new(uniform(&mut state), uniform(&mut state), uniform(&mut state)) * 14.0 - 7.0;
            let mut d = Vec3::new(uniform(&mut state), uniform(&mut state), uniform(&mut state)) - 0.5;
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
