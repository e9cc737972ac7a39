//! The tree's tests: every way a ray meets the triangles against brute force and against
//! obvhs's own traversal, bit for bit.

use super::walk::{STREAM, octant_inv4};
#[cfg(target_arch = "x86_64")]
use super::wide::child_box_hits_avx2;
use super::wide::child_box_hits_of_bytes;
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
    if !avx2 {
        bvh.lanes = Lanes::Portable;
    }
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
    assert!(hits > 1000 && rejected_differs > 100, "the rays exercise hits ({hits}) and cut-outs ({rejected_differs})");
}

/// A packet gives each ray exactly the hit (slot and distance bits) it gets alone: coherent
/// packets (a pinhole's neighbouring rays), packets whose rays spread over octants (traced one by
/// one), partial packets, distance limits, and cut-outs that differ from ray to ray.
#[test]
fn packets_give_each_ray_its_own_hit() {
    let mut state = 11;
    let input = soup(3000, &mut state);
    let (bvh, order) = Bvh::build(&input);
    // The packet's child boxes tested per ray in AVX2 where the CPU has it, or four at a time.
    let (mut portable, _) = Bvh::build(&input);
    portable.lanes = Lanes::Portable;
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
        let bits = |hits: [Option<(u32, f32)>; PACKET]| hits.map(|h| h.map(|(s, t)| (s, t.to_bits())));
        let four = portable.closest_hits(&rays, |r, slot, _| accept(r, slot));
        assert_eq!(bits(got), bits(four), "packet {p}: {} and four at a time", bvh.lanes);
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

/// A packet answers rays that miss the scene's padded bounds without walking the tree, so that
/// test must never refuse a ray that meets a triangle: rays aimed at the faces, edges and corners
/// of a scene whose triangles lie on its bounds, from near and from 10,000 extents away, grazing
/// by a few ulps, in the faces' planes and with zero direction components, get in packets the
/// bits they get alone, and every ray that hits alone passes the bounds test.
#[test]
fn packets_answer_rays_that_miss_the_bounds_with_their_own_hits() {
    let mut state = 5;
    let mut input = soup(2000, &mut state);
    // Two big triangles on each face of the soup's box (-5.15..5.15 would be loose; these are exact).
    let (lo, hi) = input.iter().flatten().fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(l, h), &p| (l.min(p), h.max(p)));
    for axis in 0..3 {
        for side in [lo, hi] {
            let corner = |u: f32, v: f32| {
                let (a, b) = ((axis + 1) % 3, (axis + 2) % 3);
                let mut p = side;
                p[a] = if u < 0.5 { lo[a] } else { hi[a] };
                p[b] = if v < 0.5 { lo[b] } else { hi[b] };
                p
            };
            input.push([corner(0.0, 0.0), corner(1.0, 0.0), corner(1.0, 1.0)]);
            input.push([corner(0.0, 0.0), corner(1.0, 1.0), corner(0.0, 1.0)]);
        }
    }
    let (bvh, _) = Bvh::build(&input);
    let (mut hits, mut refused, mut rays_tried) = (0, 0, 0);
    for p in 0..3000 {
        let distance = [1.0, 30.0, 1e4 * (hi - lo).max_element()][p % 3];
        // A target on the box: a face's point, an edge's, or a corner, nudged by a few ulps.
        let u = uniform3(&mut state);
        let mut target = lo + (hi - lo) * u;
        for k in 0..(p % 4) {
            target[(p + k) % 3] = if u[k] < 0.5 { lo[(p + k) % 3] } else { hi[(p + k) % 3] };
        }
        let nudge = (uniform3(&mut state) - 0.5) * 8.0 * f32::EPSILON * target.abs().max_element();
        let target = target + nudge;
        let from = (uniform3(&mut state) - 0.5).normalize() * distance + (lo + hi) * 0.5;
        let mut d = (target - from).normalize();
        if p % 7 == 0 {
            d[p % 3] = 0.0; // parallel to a face
        }
        let rays: Vec<(Vec3, Vec3, f32)> = (0..PACKET)
            .map(|r| {
                let spread = (uniform3(&mut state) - 0.5) * [0.0, 1e-6, 1e-3][r % 3];
                let mut o = from + spread * distance;
                if p % 11 == 0 {
                    o[p % 3] = if r % 2 == 0 { lo[p % 3] } else { hi[p % 3] }; // in a face's plane
                }
                (o, d, if r == 3 { distance } else { f32::INFINITY })
            })
            .collect();
        let got = bvh.closest_hits(&rays, |_, _, _| true);
        for (r, &(o, d, tmax)) in rays.iter().enumerate() {
            let alone = bvh.closest_hit(o, d, tmax, |_, _| true);
            assert_eq!(
                got[r].map(|(s, t)| (s, t.to_bits())),
                alone.map(|(s, t)| (s, t.to_bits())),
                "packet {p}, ray {r}"
            );
            let passes = bvh.may_meet(o, d, tmax);
            assert!(alone.is_none() || passes, "packet {p}, ray {r} hits {alone:?} but its bounds test refused it");
            hits += alone.is_some() as usize;
            refused += !passes as usize;
            rays_tried += 1;
        }
    }
    assert!(
        hits > rays_tried / 2 && refused > rays_tried / 20,
        "the rays both hit ({hits}) and miss the bounds ({refused}) of {rays_tried}"
    );
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
        if !avx2 {
            bvh.lanes = Lanes::Portable;
        }
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
    assert_eq!(bvh.lanes, Lanes::widest().at_most(Lanes::Avx2), "the walk takes AVX2 where the CPU has it");
    let (mut portable, _) = Bvh::build(&input);
    portable.lanes = Lanes::Portable;
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
    assert!(hits > 600 && limited > 1000 && occluded > 600, "hits {hits}, cut short {limited}, occluded {occluded}");
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
        assert_eq!(Bvh::build(input).0.ray_test(), RayTest::Whole(Lanes::widest()), "{n} triangles are tested whole");
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
    if !Lanes::Avx2.run_here() {
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
        let extent =
            Vec3A::from_array(std::array::from_fn(|axis| f32::from_bits((118 + ((e >> (8 * axis)) & 7) as u32) << 23)));
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
        let pick = |axis: usize, near: bool| if (ray.direction[axis] < 0.0) == near { &hi[axis] } else { &lo[axis] };
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
            if !avx2 {
                bvh.lanes = Lanes::Portable;
            }
            for a in axes {
                let d = Vec3::new(
                    if a.x == 0.0 { -0.0 } else { a.x },
                    if a.y == 0.0 { -0.0 } else { a.y },
                    if a.z == 0.0 { -0.0 } else { a.z },
                );
                let what = format!("{} triangles, budget {budget}, lanes {:?}, along {d:?}", input.len(), bvh.lanes);
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
    assert!(depth <= 16, "a CWBVH {depth} levels deep over coincident triangles (its traversal stack has 32 entries)");
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
