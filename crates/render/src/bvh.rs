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
