//! Building the tree: obvhs's CWBVH builder over each triangle's box (crowds of identical boxes
//! spread first), the power-of-two scale that brings a scene to a standard size, and the big
//! arrays on huge pages.

use glam::{Vec3, Vec3A};
use obvhs::aabb::Aabb;
use obvhs::cwbvh::CwBvh;
use obvhs::cwbvh::builder::build_cwbvh;
use obvhs::triangle::Triangle;
use obvhs::{Boundable, BvhBuildParams};
use std::collections::HashMap;
use std::time::Duration;

/// More triangles than this with bit-identical boxes are a crowd that [`builder_boxes`] spreads.
/// Two triangles of a quad share a box, and so may a few more in real meshes; these keep their own.
pub(super) const CROWD: u32 = 16;

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
pub(super) fn builder_boxes(tris: &[Triangle]) -> Vec<Aabb> {
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
pub(super) fn spread_direction(k: u32, m: u32) -> Vec3A {
    const GOLDEN_ANGLE: f64 = 2.399_963_229_728_653;
    let z = 1.0 - (2.0 * k as f64 + 1.0) / m as f64;
    let r = libm::sqrt((1.0 - z * z).max(0.0));
    let phi = GOLDEN_ANGLE * k as f64;
    Vec3A::new((r * libm::cos(phi)) as f32, (r * libm::sin(phi)) as f32, z as f32)
}

/// A cheap hash of box bits for [`builder_boxes`] (SipHash costs more than the grouping saves).
#[derive(Clone, Copy, Default)]
pub(super) struct BoxHash;

impl std::hash::BuildHasher for BoxHash {
    type Hasher = BoxHasher;
    fn build_hasher(&self) -> BoxHasher {
        BoxHasher(0)
    }
}

pub(super) struct BoxHasher(u64);

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
pub(super) fn build_tree(boxes: &[Aabb]) -> CwBvh {
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

/// The triangles' bounding box, `(lo, hi)`.
pub(super) fn bounds_of(triangles: &[[Vec3; 3]]) -> (Vec3, Vec3) {
    let (mut lo, mut hi) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
    for v in triangles.iter().flatten() {
        (lo, hi) = (lo.min(*v), hi.max(*v));
    }
    (lo, hi)
}

/// The power of two that brings the extent of triangles bounded by `lo`, `hi` (their bounding
/// box's longest side) to between 8 and 16; 1 for triangles of no extent. The exponent comes
/// from the bits, so no rounding can move it.
pub(super) fn normalizing_scale(lo: Vec3, hi: Vec3) -> f32 {
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
pub(super) fn on_huge_pages<T>(len: usize, items: impl Iterator<Item = T>) -> Vec<T> {
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
