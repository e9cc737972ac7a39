//! The acceleration structure: an 8-wide compressed BVH (CWBVH, Ylitie et al. 2017) built by
//! `obvhs`, over triangles stored in BVH order so that a hit index needs no indirection.

use glam::{Vec3, Vec3A};
use obvhs::BvhBuildParams;
use obvhs::cwbvh::CwBvh;
use obvhs::cwbvh::builder::build_cwbvh_from_tris;
use obvhs::ray::{Ray, RayHit};
use obvhs::rt_triangle::RtTriangle;
use obvhs::triangle::Triangle;
use std::time::Duration;

/// Triangles and their BVH. `order[i]` is the caller's index of BVH slot `i`.
pub struct Bvh {
    cwbvh: Option<CwBvh>,
    triangles: Vec<RtTriangle>,
}

impl Bvh {
    /// Builds the BVH and returns it with the permutation from BVH slots to input triangles.
    pub fn build(triangles: &[[Vec3; 3]]) -> (Self, Vec<u32>) {
        if triangles.is_empty() {
            return (Self { cwbvh: None, triangles: Vec::new() }, Vec::new());
        }
        let tris: Vec<Triangle> =
            triangles.iter().map(|t| Triangle { v0: t[0].into(), v1: t[1].into(), v2: t[2].into() }).collect();
        // No spatial pre-splits: they would make primitive indices repeat.
        let params = BvhBuildParams { pre_split: false, ..BvhBuildParams::medium_build() };
        let cwbvh = build_cwbvh_from_tris(&tris, params, &mut Duration::default());
        let order = cwbvh.primitive_indices.clone();
        let triangles = order.iter().map(|&i| RtTriangle::from(&tris[i as usize])).collect();
        (Self { cwbvh: Some(cwbvh), triangles }, order)
    }

    pub fn len(&self) -> usize {
        self.triangles.len()
    }

    pub fn is_empty(&self) -> bool {
        self.triangles.is_empty()
    }

    /// Closest hit along `o + t d`, `t` in `(0, tmax)`; `accept(slot, t)` may reject a hit (alpha cut-outs).
    pub fn closest_hit(&self, o: Vec3, d: Vec3, tmax: f32, accept: impl Fn(u32, f32) -> bool) -> Option<(u32, f32)> {
        let bvh = self.cwbvh.as_ref()?;
        let ray = Ray::new(Vec3A::from(o), Vec3A::from(d), 0.0, tmax);
        let mut hit = RayHit::none();
        let found = bvh.ray_traverse(ray, &mut hit, |r, id| {
            let t = self.triangles[id].intersect(r);
            if t.is_finite() && t > 0.0 && accept(id as u32, t) { t } else { f32::INFINITY }
        });
        found.then_some((hit.primitive_id, hit.t))
    }

    /// True when anything accepted lies along `o + t d`, `t` in `(0, tmax)`.
    pub fn occluded(&self, o: Vec3, d: Vec3, tmax: f32, accept: impl Fn(u32, f32) -> bool) -> bool {
        let Some(bvh) = self.cwbvh.as_ref() else {
            return false;
        };
        let ray = Ray::new(Vec3A::from(o), Vec3A::from(d), 0.0, tmax);
        !bvh.ray_traverse_miss(ray, |r, id| {
            let t = self.triangles[id].intersect(r);
            if t.is_finite() && t > 0.0 && accept(id as u32, t) { t } else { f32::INFINITY }
        })
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
