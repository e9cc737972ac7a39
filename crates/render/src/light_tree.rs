//! A light tree: lights with a position chosen in proportion to an estimate of what each
//! contributes at the shading point, from bounds on power, place and orientation (Conty Estevez
//! and Kulla 2018, "Importance Sampling of Many Lights with Adaptive Tree Splitting", in the form
//! of pbrt-v4's `BVHLightSampler`).
//!
//! Every node bounds its lights by a box, their total power, a cone holding their normals
//! (`w`, `cos_o`) and how far beyond the normals they emit (`cos_e`). From a point, a node's
//! importance is its power over the squared distance to its box, times the cosine of the smallest
//! angle any of its lights could emit towards the point at, times the cosine of the smallest
//! angle of incidence at the point. A node has up to four children, weighed together in 4-wide
//! IEEE arithmetic ([`F4`]). A sample walks from the root, at each node choosing a child in
//! proportion to the children's importances; a light's probability is the product of those
//! choices, which [`LightTree::pmf`] retraces from the light's path (its trail, two bits a node).
//!
//! An importance of 0 is a proof that no light below reaches the point (the bounds are
//! conservative), so skipping such nodes leaves light sampling unbiased.

use glam::Vec3;
use std::f32::consts::PI;

/// Beyond this many binary splits the build splits at the median, so no path has more than 62
/// (31 nodes of four children: a trail of two bits a node and its end marker fit a `u64`) for up
/// to 2^32 lights, and degenerate input (many lights at one place) costs `O(n log n)`.
const BALANCED_FROM_DEPTH: u32 = 30;

/// Split candidates per axis.
const BUCKETS: usize = 12;

/// Bounds on a set of lights, as seen from anywhere; made by [`LightBounds::point`],
/// [`LightBounds::spot`], [`LightBounds::surface`] and [`LightBounds::union`], which keep `sin_o`
/// the sine of `cos_o`'s angle.
#[derive(Clone, Copy, Debug)]
pub struct LightBounds {
    lo: Vec3,
    hi: Vec3,
    /// Axis of the cone holding the lights' normals (any unit vector when `cos_o` is -1).
    w: Vec3,
    /// Cosine and sine of the half-angle of that cone.
    cos_o: f32,
    sin_o: f32,
    /// Cosine of the angle beyond a normal that a light still emits at (0 for a surface).
    cos_e: f32,
    /// Power, in the units the set was built with; only ratios matter.
    phi: f32,
    /// Whether some light emits from both faces (the cone then holds `-w` as well).
    two_sided: bool,
}

impl LightBounds {
    /// A light at one point emitting in every direction (a point light).
    pub fn point(p: Vec3, phi: f32) -> Self {
        Self { lo: p, hi: p, w: Vec3::Z, cos_o: -1.0, sin_o: 0.0, cos_e: 0.0, phi, two_sided: false }
    }

    /// A light at one point emitting about unit direction `w`: fully within the angle whose
    /// cosine is `cos_o`, and not at all beyond the angle whose cosine is `cos_outer` (a spot light).
    pub fn spot(p: Vec3, w: Vec3, cos_o: f32, cos_outer: f32, phi: f32) -> Self {
        let cos_o = cos_o.clamp(-1.0, 1.0);
        let spread = libm::acosf(cos_outer.clamp(-1.0, 1.0)) - libm::acosf(cos_o);
        let sin_o = (1.0 - cos_o * cos_o).max(0.0).sqrt();
        Self { lo: p, hi: p, w, cos_o, sin_o, cos_e: libm::cosf(spread.max(0.0)), phi, two_sided: false }
    }

    /// A flat emitter with unit normal `n` over the box `lo..hi`.
    pub fn surface(lo: Vec3, hi: Vec3, n: Vec3, phi: f32, two_sided: bool) -> Self {
        Self { lo, hi, w: n, cos_o: 1.0, sin_o: 0.0, cos_e: 0.0, phi, two_sided }
    }

    /// Both sets of lights together.
    pub fn union(&self, other: &Self) -> Self {
        if self.phi <= 0.0 {
            return *other;
        }
        if other.phi <= 0.0 {
            return *self;
        }
        let (w, cos_o) = cone_union((self.w, self.cos_o), (other.w, other.cos_o));
        Self {
            lo: self.lo.min(other.lo),
            hi: self.hi.max(other.hi),
            w,
            cos_o,
            sin_o: (1.0 - cos_o * cos_o).max(0.0).sqrt(),
            cos_e: self.cos_e.min(other.cos_e),
            phi: self.phi + other.phi,
            two_sided: self.two_sided || other.two_sided,
        }
    }

    fn centroid(&self) -> Vec3 {
        0.5 * (self.lo + self.hi)
    }

    /// An upper bound, up to a constant, on what these lights contribute at `p` on a surface with
    /// unit normal `n`: 0 only where none of them can reach `p` at all.
    #[cfg(test)]
    pub fn importance(&self, p: Vec3, n: Vec3) -> f32 {
        let mut one = Reach4::default();
        one.set(0, self);
        one.importance(p, n)[0]
    }

    /// pbrt's orientation-weighted cost of a node: power times the solid angle its emission may
    /// reach (the measure `M_Omega` of Conty Estevez and Kulla) times its box's surface area, the
    /// box stretched by `stretch` along the split axis to favour cubes.
    fn cost(&self, stretch: f32) -> f32 {
        let theta_o = libm::acosf(self.cos_o.clamp(-1.0, 1.0));
        let theta_e = libm::acosf(self.cos_e.clamp(-1.0, 1.0));
        let theta_w = (theta_o + theta_e).min(PI);
        let sin_o = libm::sinf(theta_o);
        let m_omega = 2.0 * PI * (1.0 - self.cos_o)
            + PI / 2.0
                * (2.0 * theta_w * sin_o - libm::cosf(theta_o - 2.0 * theta_w) - 2.0 * theta_o * sin_o + self.cos_o);
        let d = self.hi - self.lo;
        let area = 2.0 * (d.x * d.y + d.y * d.z + d.z * d.x);
        self.phi * m_omega * stretch * area
    }
}

/// Up to four sets of lights as a tree node keeps them, one per lane: each box as its bounding
/// sphere, and every number of a lane in an array of its own, so that one pass of [`F4`]'s
/// 4-wide IEEE arithmetic weighs all four. An empty lane has no power, and weighs 0.
#[derive(Clone, Copy, Debug, Default)]
struct Reach4 {
    cx: [f32; 4],
    cy: [f32; 4],
    cz: [f32; 4],
    radius2: [f32; 4],
    wx: [f32; 4],
    wy: [f32; 4],
    wz: [f32; 4],
    cos_o: [f32; 4],
    sin_o: [f32; 4],
    cos_e: [f32; 4],
    phi: [f32; 4],
    /// 1 where a light of the lane emits from both faces, else 0.
    two_sided: [f32; 4],
}

impl Reach4 {
    fn set(&mut self, k: usize, b: &LightBounds) {
        let c = b.centroid();
        (self.cx[k], self.cy[k], self.cz[k]) = (c.x, c.y, c.z);
        self.radius2[k] = 0.25 * (b.hi - b.lo).length_squared();
        (self.wx[k], self.wy[k], self.wz[k]) = (b.w.x, b.w.y, b.w.z);
        (self.cos_o[k], self.sin_o[k], self.cos_e[k]) = (b.cos_o, b.sin_o, b.cos_e);
        self.phi[k] = b.phi;
        self.two_sided[k] = if b.two_sided { 1.0 } else { 0.0 };
    }

    /// [`LightBounds::importance`] of the four lanes, computed together in [`F4`]'s 4-wide IEEE
    /// arithmetic (every lane takes every step; the answer is chosen at the end).
    #[inline]
    fn importance(&self, p: Vec3, n: Vec3) -> [f32; 4] {
        let (zero, one) = (F4::splat(0.0), F4::splat(1.0));
        let (dx, dy, dz) = (F4::splat(p.x) - F4(self.cx), F4::splat(p.y) - F4(self.cy), F4::splat(p.z) - F4(self.cz));
        let d2 = dx * dx + dy * dy + dz * dz;
        // Kept off 0 so that no step makes a NaN (the lanes it matters to are chosen otherwise).
        let d2_safe = d2.max(F4::splat(1e-30));
        let radius2 = F4(self.radius2);
        // Sine and cosine of the half-angle the bounding sphere subtends at `p`.
        let sin2_b = (radius2 / d2_safe).min(one);
        let (sin_b, cos_b) = (sin2_b.sqrt(), (one - sin2_b).max(zero).sqrt());
        let inv_d = one / d2_safe.sqrt();
        let (ix, iy, iz) = (dx * inv_d, dy * inv_d, dz * inv_d);
        let cos_w = F4(self.wx) * ix + F4(self.wy) * iy + F4(self.wz) * iz;
        let cos_w = F4(self.two_sided).gt(zero).select(cos_w.abs(), cos_w);
        let sin_w = (one - cos_w * cos_w).max(zero).sqrt();
        // The angle from the cone of normals to `p`, less the cone and the sphere's half-angle.
        let (sin_x, cos_x) = angle_less4((sin_w, cos_w), (F4(self.sin_o), F4(self.cos_o)));
        let (_, cos_p) = angle_less4((sin_x, cos_x), (sin_b, cos_b));
        let cos_i = (ix * F4::splat(n.x) + iy * F4::splat(n.y) + iz * F4::splat(n.z)).abs();
        let sin_i = (one - cos_i * cos_i).max(zero).sqrt();
        let (_, cos_pi) = angle_less4((sin_i, cos_i), (sin_b, cos_b));
        let phi = F4(self.phi);
        let outside = cos_p.le(F4(self.cos_e)).select(zero, (phi * cos_p * cos_pi).max(zero) / d2_safe);
        // Within the bounding sphere every direction may hold a light: no orientation bound.
        let inside = phi / radius2.max(F4::splat(1e-20));
        // Kept finite, so that four of them still add up.
        d2.le(radius2).select(inside, outside).min(F4::splat(f32::MAX / 8.0)).0
    }
}

/// Sine and cosine of `max(0, a - b)` for angles `a`, `b` in `[0, pi]` given by their sines and
/// cosines, lane by lane.
#[inline]
fn angle_less4((sin_a, cos_a): (F4, F4), (sin_b, cos_b): (F4, F4)) -> (F4, F4) {
    let none = cos_a.gt(cos_b);
    (
        none.select(F4::splat(0.0), sin_a * cos_b - cos_a * sin_b),
        none.select(F4::splat(1.0), cos_a * cos_b + sin_a * sin_b),
    )
}

/// Four `f32` lanes with IEEE arithmetic: SSE2 on x86-64 (every such CPU has it), the same
/// operations one lane at a time elsewhere. `max` and `min` are SSE's (`a > b ? a : b` and
/// `a < b ? a : b`) on both, so the bits never depend on the machine.
#[derive(Clone, Copy, Debug)]
struct F4([f32; 4]);

/// A lane mask from a comparison.
#[derive(Clone, Copy, Debug)]
struct M4([bool; 4]);

impl F4 {
    fn splat(x: f32) -> Self {
        F4([x; 4])
    }

    #[inline]
    fn map2(self, o: F4, f: impl Fn(f32, f32) -> f32) -> F4 {
        F4(std::array::from_fn(|k| f(self.0[k], o.0[k])))
    }

    #[inline]
    fn sqrt(self) -> F4 {
        F4(crate::math::sqrt4(self.0))
    }

    #[inline]
    fn max(self, o: F4) -> F4 {
        self.map2(o, |a, b| if a > b { a } else { b })
    }

    #[inline]
    fn min(self, o: F4) -> F4 {
        self.map2(o, |a, b| if a < b { a } else { b })
    }

    #[inline]
    fn abs(self) -> F4 {
        F4(self.0.map(f32::abs))
    }

    #[inline]
    fn le(self, o: F4) -> M4 {
        M4(std::array::from_fn(|k| self.0[k] <= o.0[k]))
    }

    #[inline]
    fn gt(self, o: F4) -> M4 {
        M4(std::array::from_fn(|k| self.0[k] > o.0[k]))
    }
}

impl M4 {
    #[inline]
    fn select(self, yes: F4, no: F4) -> F4 {
        F4(std::array::from_fn(|k| if self.0[k] { yes.0[k] } else { no.0[k] }))
    }
}

macro_rules! lanewise {
    ($trait:ident, $method:ident, $op:tt) => {
        impl std::ops::$trait for F4 {
            type Output = F4;
            #[inline]
            fn $method(self, o: F4) -> F4 {
                self.map2(o, |a, b| a $op b)
            }
        }
    };
}
lanewise!(Add, add, +);
lanewise!(Sub, sub, -);
lanewise!(Mul, mul, *);
lanewise!(Div, div, /);

/// The angle between two unit vectors, accurate near 0 and pi.
fn angle_between(a: Vec3, b: Vec3) -> f32 {
    if a.dot(b) < 0.0 {
        PI - 2.0 * libm::asinf(((a + b).length() / 2.0).min(1.0))
    } else {
        2.0 * libm::asinf(((a - b).length() / 2.0).min(1.0))
    }
}

/// The smallest cone (axis, cosine of half-angle) holding two cones.
fn cone_union(a: (Vec3, f32), b: (Vec3, f32)) -> (Vec3, f32) {
    if a.1 <= -1.0 || b.1 <= -1.0 {
        return (a.0, -1.0);
    }
    // Lights facing one way (a panel, a row of lamps) need no trigonometry.
    if a.0 == b.0 {
        return if a.1 <= b.1 { a } else { b };
    }
    let theta_a = libm::acosf(a.1.clamp(-1.0, 1.0));
    let theta_b = libm::acosf(b.1.clamp(-1.0, 1.0));
    let theta_d = angle_between(a.0, b.0);
    if (theta_d + theta_b).min(PI) <= theta_a {
        return a;
    }
    if (theta_d + theta_a).min(PI) <= theta_b {
        return b;
    }
    let theta_o = 0.5 * (theta_a + theta_d + theta_b);
    if theta_o >= PI {
        return (a.0, -1.0);
    }
    // Turn a's axis towards b's by theta_o - theta_a.
    let axis = a.0.cross(b.0);
    if axis.length_squared() == 0.0 {
        return (a.0, -1.0);
    }
    let k = axis.normalize();
    let (sin_r, cos_r) = libm::sincosf(theta_o - theta_a);
    let w = (a.0 * cos_r + k.cross(a.0) * sin_r).normalize();
    (w, libm::cosf(theta_o))
}

/// A node: up to four children, each a light (a leaf) or another node.
#[derive(Clone, Copy, Debug, Default)]
struct Node {
    reach: Reach4,
    /// Per lane, the light of a leaf or the index of a child node.
    child: [u32; 4],
    leaf: [bool; 4],
}

/// A tree over lights with four children to a node, each leaf one light.
#[derive(Default)]
pub struct LightTree {
    nodes: Vec<Node>,
    /// Per light given to [`LightTree::build`], its path from the root: two bits per level, the
    /// lane taken, and a marker bit after the last. `None` for lights without power.
    trails: Vec<Option<u64>>,
    power: f32,
}

impl LightTree {
    /// The tree over `lights`; those without power are left out (never chosen).
    pub fn build(lights: &[LightBounds]) -> Self {
        let mut items: Vec<u32> = (0..lights.len() as u32).filter(|&i| lights[i as usize].phi > 0.0).collect();
        let mut tree =
            Self { nodes: Vec::with_capacity(items.len() / 2 + 1), trails: vec![None; lights.len()], power: 0.0 };
        if !items.is_empty() {
            tree.power = tree.build_node(lights, &mut items, 0, 0).phi;
        }
        tree
    }

    pub fn is_empty(&self) -> bool {
        self.nodes.is_empty()
    }

    /// Total power of the lights in the tree.
    pub fn power(&self) -> f32 {
        self.power
    }

    /// Nodes on the longest path from the root to a light.
    pub fn depth(&self) -> u32 {
        self.trails.iter().flatten().map(|&t| (63 - t.leading_zeros()) / 2).max().unwrap_or(0)
    }

    /// Adds the node over `items` (at least one light) at binary depth `depth` (two per level)
    /// with the path `trail` to it, and returns the bounds of its lights.
    fn build_node(&mut self, lights: &[LightBounds], items: &mut [u32], depth: u32, trail: u64) -> LightBounds {
        let at = self.nodes.len();
        self.nodes.push(Node::default());
        // Two binary splits make up to four parts.
        let mut parts: Vec<&mut [u32]> = Vec::with_capacity(4);
        if items.len() == 1 {
            parts.push(items);
        } else {
            let mid = split(lights, items, depth);
            let (a, b) = items.split_at_mut(mid);
            for half in [a, b] {
                if half.len() == 1 {
                    parts.push(half);
                } else {
                    let mid = split(lights, half, depth + 1);
                    let (c, d) = half.split_at_mut(mid);
                    parts.extend([c, d]);
                }
            }
        }
        let mut node = Node::default();
        let mut bounds: Option<LightBounds> = None;
        for (k, part) in parts.into_iter().enumerate() {
            let lane_trail = trail | (k as u64) << (2 * (depth / 2));
            let b = if let [only] = part {
                node.child[k] = *only;
                node.leaf[k] = true;
                self.trails[*only as usize] = Some(lane_trail | 1 << (2 * (depth / 2 + 1)));
                lights[*only as usize]
            } else {
                node.child[k] = self.nodes.len() as u32;
                self.build_node(lights, part, depth + 2, lane_trail)
            };
            node.reach.set(k, &b);
            bounds = Some(bounds.map_or(b, |a| a.union(&b)));
        }
        self.nodes[at] = node;
        bounds.expect("a node holds a light")
    }

    /// Chooses a light for the point `p` with unit surface normal `n` from one uniform number;
    /// returns the light (its index in the list built from), its probability and `u` rescaled to
    /// `[0, 1)` within the choice, to be used again. `None` when no light can reach `p`.
    pub fn sample(&self, p: Vec3, n: Vec3, mut u: f32) -> Option<(u32, f32, f32)> {
        let mut node = self.nodes.first()?;
        let mut pmf = 1.0f32;
        loop {
            let shares = shares(node.reach.importance(p, n))?;
            // The lane whose interval of [0, 1) holds `u`, intervals in lane order; rounding
            // leaves the rest to the last lane that has a share.
            let last = shares.iter().rposition(|&x| x > 0.0)?;
            let (mut lane, mut below) = (0, 0.0);
            while lane < last && !(shares[lane] > 0.0 && u < below + shares[lane]) {
                below += shares[lane];
                lane += 1;
            }
            pmf *= shares[lane];
            u = crate::sampling::rescaled(u, below, shares[lane]);
            if node.leaf[lane] {
                return Some((node.child[lane], pmf, u));
            }
            node = &self.nodes[node.child[lane] as usize];
        }
    }

    /// The probability with which [`Self::sample`] chooses light `light` at `p` with normal `n`.
    pub fn pmf(&self, p: Vec3, n: Vec3, light: u32) -> f32 {
        let Some(Some(mut trail)) = self.trails.get(light as usize).copied() else {
            return 0.0;
        };
        let Some(mut node) = self.nodes.first() else {
            return 0.0;
        };
        let mut pmf = 1.0f32;
        loop {
            let Some(shares) = shares(node.reach.importance(p, n)) else {
                return 0.0;
            };
            let lane = (trail & 3) as usize;
            trail >>= 2;
            pmf *= shares[lane];
            if node.leaf[lane] {
                return pmf;
            }
            node = &self.nodes[node.child[lane] as usize];
        }
    }
}

/// The probabilities of descending to each lane, in proportion to their weights; `None` when
/// no lane has weight.
#[inline]
fn shares(weights: [f32; 4]) -> Option<[f32; 4]> {
    let total = weights[0] + weights[1] + weights[2] + weights[3];
    if total <= 0.0 {
        return None;
    }
    let inverse = 1.0 / total;
    Some(weights.map(|w| w * inverse))
}

/// Orders `items` so that the first `mid` go to one child and the rest to the other, and returns
/// `mid` (never 0 nor `items.len()`): the cheapest of the bucket splits along the three axes by
/// [`LightBounds::cost`], or the median along the longest axis where none separates the lights or
/// the tree is already deep.
fn split(lights: &[LightBounds], items: &mut [u32], depth: u32) -> usize {
    let (mut lo, mut hi) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
    let (mut box_lo, mut box_hi) = (lo, hi);
    for &i in items.iter() {
        let l = &lights[i as usize];
        (lo, hi) = (lo.min(l.centroid()), hi.max(l.centroid()));
        (box_lo, box_hi) = (box_lo.min(l.lo), box_hi.max(l.hi));
    }
    let extent = hi - lo;
    let longest = if extent.x >= extent.y && extent.x >= extent.z {
        0
    } else if extent.y >= extent.z {
        1
    } else {
        2
    };
    if depth < BALANCED_FROM_DEPTH
        && let Some((axis, cut)) = cheapest_split(lights, items, box_hi - box_lo, lo, extent)
    {
        let bucket = |i: &u32| bucket_of(lights[*i as usize].centroid()[axis], lo[axis], extent[axis]);
        // Stable, so the order (and the tree) depends on the lights alone.
        let (mut below, above): (Vec<u32>, Vec<u32>) = items.iter().partition(|i| bucket(i) <= cut);
        let mid = below.len();
        below.extend(above);
        items.copy_from_slice(&below);
        return mid;
    }
    let mid = items.len() / 2;
    items.select_nth_unstable_by(mid, |a, b| {
        let (ca, cb) = (lights[*a as usize].centroid()[longest], lights[*b as usize].centroid()[longest]);
        ca.total_cmp(&cb).then(a.cmp(b))
    });
    mid
}

fn bucket_of(c: f32, lo: f32, extent: f32) -> usize {
    ((BUCKETS as f32 * (c - lo) / extent) as usize).min(BUCKETS - 1)
}

/// The axis and last bucket of the first part of the cheapest split that leaves lights on both
/// sides; `size` is the node's box, `lo` and `extent` its lights' centroids'.
fn cheapest_split(lights: &[LightBounds], items: &[u32], size: Vec3, lo: Vec3, extent: Vec3) -> Option<(usize, usize)> {
    let longest_side = size.max_element();
    let mut best: Option<(f32, usize, usize)> = None;
    for axis in 0..3 {
        if extent[axis] <= 0.0 {
            continue;
        }
        let mut buckets: [Option<LightBounds>; BUCKETS] = [None; BUCKETS];
        for &i in items {
            let l = &lights[i as usize];
            let b = &mut buckets[bucket_of(l.centroid()[axis], lo[axis], extent[axis])];
            *b = Some(b.map_or(*l, |b| b.union(l)));
        }
        let stretch = if size[axis] > 0.0 { longest_side / size[axis] } else { 1.0 };
        for cut in 0..BUCKETS - 1 {
            let join = |range: &[Option<LightBounds>]| {
                range.iter().flatten().fold(None, |acc: Option<LightBounds>, b| Some(acc.map_or(*b, |a| a.union(b))))
            };
            let (Some(below), Some(above)) = (join(&buckets[..=cut]), join(&buckets[cut + 1..])) else {
                continue;
            };
            let cost = below.cost(stretch) + above.cost(stretch);
            if best.is_none_or(|(c, _, _)| cost < c) {
                best = Some((cost, axis, cut));
            }
        }
    }
    best.map(|(_, axis, cut)| (axis, cut))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rng(seed: &mut u64) -> f32 {
        *seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        (*seed >> 40) as f32 / (1u64 << 24) as f32
    }

    /// A cloud of small emitters facing every way, some two-sided, plus points.
    fn lights(n: usize, seed: u64) -> Vec<LightBounds> {
        let mut s = seed;
        (0..n)
            .map(|i| {
                let c = Vec3::new(rng(&mut s), rng(&mut s), rng(&mut s)) * 10.0;
                let phi = 0.1 + rng(&mut s) * 5.0;
                if i % 7 == 0 {
                    LightBounds::point(c, phi)
                } else {
                    let nrm = Vec3::new(rng(&mut s) - 0.5, rng(&mut s) - 0.5, rng(&mut s) - 0.5).normalize();
                    LightBounds::surface(c - 0.05, c + 0.05, nrm, phi, i % 3 == 0)
                }
            })
            .collect()
    }

    /// A sample's probability is what `pmf` gives its light; the probabilities add up to at most
    /// 1 (a walk may end at a node both of whose children are out of reach, as pbrt's does) and
    /// to the share of numbers that give a light; a light with probability 0 cannot reach the point.
    #[test]
    fn probabilities_match_sampling() {
        let lights = lights(300, 1);
        let tree = LightTree::build(&lights);
        let mut s = 7;
        let sweep = 4000;
        for _ in 0..20 {
            let p = Vec3::new(rng(&mut s), rng(&mut s), rng(&mut s)) * 14.0 - 2.0;
            let n = Vec3::new(rng(&mut s) - 0.5, rng(&mut s) - 0.5, rng(&mut s) - 0.5).normalize();
            let pmfs: Vec<f32> = (0..lights.len() as u32).map(|i| tree.pmf(p, n, i)).collect();
            let total: f64 = pmfs.iter().map(|&x| x as f64).sum();
            assert!(total <= 1.0 + 1e-5 && total > 0.5, "pmfs sum to {total} at {p}");
            for (i, &pmf) in pmfs.iter().enumerate() {
                assert!(pmf > 0.0 || lights[i].importance(p, n) == 0.0, "light {i} reaches {p} but is never chosen");
            }
            let mut chosen = 0;
            for k in 0..sweep {
                if let Some((light, pmf, rescaled)) = tree.sample(p, n, (k as f32 + 0.5) / sweep as f32) {
                    assert_eq!(pmf, pmfs[light as usize], "sampling and evaluation disagree for light {light}");
                    assert!((0.0..1.0).contains(&rescaled));
                    chosen += 1;
                }
            }
            let share = chosen as f64 / sweep as f64;
            assert!((share - total).abs() < 2e-3, "{share} of the numbers choose a light, the pmfs sum to {total}");
        }
    }

    /// Chi-square of the lights chosen from 200,000 uniform numbers (and of no choice) against
    /// their pmfs, at 99.9 %.
    #[test]
    fn choices_follow_the_pmf() {
        let lights = lights(40, 3);
        let tree = LightTree::build(&lights);
        let (p, n) = (Vec3::new(4.0, 1.0, 6.0), Vec3::new(0.0, 1.0, 0.0));
        let draws = 200_000;
        // The last count is of numbers that chose nothing.
        let mut counts = vec![0u32; lights.len() + 1];
        let mut s = 11;
        for _ in 0..draws {
            match tree.sample(p, n, rng(&mut s)) {
                Some((light, _, _)) => counts[light as usize] += 1,
                None => counts[lights.len()] += 1,
            }
        }
        let mut pmfs: Vec<f64> = (0..lights.len() as u32).map(|i| tree.pmf(p, n, i) as f64).collect();
        pmfs.push(1.0 - pmfs.iter().sum::<f64>());
        let (mut chi2, mut dof) = (0.0, 0);
        for (i, (&c, &pmf)) in counts.iter().zip(&pmfs).enumerate() {
            let expected = pmf * draws as f64;
            if expected > 5.0 {
                chi2 += (c as f64 - expected).powi(2) / expected;
                dof += 1;
            } else {
                assert!(expected > 0.0 || c == 0, "light {i} chosen with probability 0");
            }
        }
        assert!(dof > 20, "{dof} lights with enough expected choices");
        // Wilson-Hilferty approximation of the 99.9 % point of chi-square with dof - 1 degrees.
        let k = (dof - 1) as f64;
        let limit = k * (1.0 - 2.0 / (9.0 * k) + 3.09 * (2.0 / (9.0 * k)).sqrt()).powi(3);
        assert!(chi2 < limit, "chi-square {chi2:.1} over {limit:.1} with {k} degrees of freedom");
    }

    #[test]
    fn importance_is_zero_only_where_no_light_reaches() {
        // A one-sided square facing +y at the origin: nothing below its plane sees its front.
        let light = LightBounds::surface(Vec3::new(-1.0, 0.0, -1.0), Vec3::new(1.0, 0.0, 1.0), Vec3::Y, 1.0, false);
        assert_eq!(light.importance(Vec3::new(0.0, -3.0, 0.0), Vec3::Y), 0.0);
        assert!(light.importance(Vec3::new(5.0, 0.5, 0.0), Vec3::Y) > 0.0);
        assert!(light.importance(Vec3::new(0.0, 3.0, 0.0), Vec3::X) > 0.0, "the box subtends an angle");
        let two_sided = LightBounds { two_sided: true, ..light };
        assert!(two_sided.importance(Vec3::new(0.0, -3.0, 0.0), Vec3::Y) > 0.0);
        // Nearer is more important, power scales it.
        let far = light.importance(Vec3::new(0.0, 10.0, 0.0), Vec3::Y);
        assert!(light.importance(Vec3::new(0.0, 5.0, 0.0), Vec3::Y) > far);
        let bright = LightBounds { phi: 2.0, ..light };
        assert_eq!(bright.importance(Vec3::new(0.0, 10.0, 0.0), Vec3::Y), 2.0 * far);
    }

    #[test]
    fn cones_unite_to_hold_both() {
        let (w, cos) = cone_union((Vec3::X, 1.0), (Vec3::Y, 1.0));
        assert!((w - Vec3::new(1.0, 1.0, 0.0).normalize()).length() < 1e-5);
        assert!((cos - libm::cosf(PI / 4.0)).abs() < 1e-5);
        assert_eq!(cone_union((Vec3::X, 1.0), (-Vec3::X, 1.0)).1, -1.0);
        let wide = (Vec3::Z, 0.0);
        assert_eq!(cone_union(wide, (Vec3::new(0.0, 0.1, 1.0).normalize(), 0.99)).1, 0.0);
    }

    /// Thousands of lights at one place (degenerate input) build a balanced tree quickly.
    #[test]
    fn coincident_lights_build_a_shallow_tree() {
        let light = LightBounds::surface(Vec3::ZERO, Vec3::ONE, Vec3::Y, 1.0, false);
        let tree = LightTree::build(&vec![light; 40_000]);
        assert!(tree.depth() <= 9, "depth {}", tree.depth());
        let pmf = tree.pmf(Vec3::new(0.5, 3.0, 0.5), Vec3::Y, 123);
        assert!((pmf - 1.0 / 40_000.0).abs() < 1e-7, "{pmf}");
    }

    #[test]
    fn lights_without_power_are_never_chosen() {
        let mut lights = lights(10, 5);
        lights[3].phi = 0.0;
        let tree = LightTree::build(&lights);
        assert_eq!(tree.pmf(Vec3::ZERO, Vec3::Y, 3), 0.0);
        assert!(LightTree::build(&[]).sample(Vec3::ZERO, Vec3::Y, 0.5).is_none());
    }
}
