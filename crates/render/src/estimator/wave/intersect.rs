//! The wave's first stage: the eight rays traced together ([`Scene::intersect8`]), what a lane
//! that met nothing sees of the environment, and the surface points of the hits ([`Points`]).

use super::paths::{Paths, Rows};
use super::{W, Wave, dot, select};
use crate::channels::{ColorModel, Rgb};
use crate::interaction::Hit;
use crate::mesh::HAS_NORMALS;
use crate::scene::Scene;
use crate::settings::RenderSettings;
use crate::sums::TileSums;

impl Wave {
    /// The hits of the live lanes' rays. A lane that found none ends with what the environment
    /// sends (a camera ray's with nothing under a transparent background).
    #[inline(always)]
    pub(super) fn intersect(
        &self,
        scene: &Scene,
        settings: &RenderSettings,
        paths: &mut Paths,
        sums: &mut TileSums,
    ) -> [Option<Hit>; W] {
        let lights = &scene.lights;
        let hit = scene.intersect8(&paths.o.0, &paths.d.0, paths.live);
        for i in 0..W {
            if !paths.live[i] {
                continue;
            }
            let d = paths.d.get(i);
            if paths.bounce[i] == 0 {
                paths.covered[i] = hit[i].is_some();
                if settings.transparent && hit[i].is_none() {
                    paths.finish(i, sums);
                    continue;
                }
            }
            if hit[i].is_none() {
                let le = lights.environment_radiance(d);
                if le.max_element() > 0.0 {
                    paths.saw_emitter[i] |= paths.bounce[i] == 0;
                    let w = if paths.prev_delta[i] {
                        1.0
                    } else {
                        self.combination.weight(paths.prev_pdf[i], || lights.environment_pdf(d, settings.lights), false)
                    };
                    paths.l.set(i, paths.l.get(i) + paths.beta.get(i) * Rgb.illuminant(le) * w);
                }
                paths.finish(i, sums);
            }
        }
        hit
    }
}

/// The surface points of eight hits, as rows: `SurfacePoint::at`'s numbers for a triangle of a
/// plain material (no texture, tangent frame or vertex colour), lane by lane in its operations.
pub(super) struct Points {
    pub(super) p: Rows,
    pub(super) ng: Rows,
    pub(super) s: Rows,
    pub(super) t: Rows,
    pub(super) n: Rows,
    pub(super) front_face: [bool; W],
    pub(super) material: [u32; W],
}

impl Points {
    /// The points where the rays `o + t d` of each lane meet their hits (lanes without one get
    /// numbers of no meaning).
    #[inline(always)]
    pub(super) fn at(scene: &Scene, o: &Rows, d: &Rows, hits: &[Option<Hit>; W]) -> Points {
        let mesh = &scene.mesh;
        // The corners, normals and distances, gathered into rows.
        let (mut a, mut b, mut c) = (Rows::default(), Rows::default(), Rows::default());
        let (mut na, mut nb, mut nc) = (Rows::default(), Rows::default(), Rows::default());
        let mut t = [0.0; W];
        let mut material = [0; W];
        for i in 0..W {
            let Some(h) = hits[i] else { continue };
            let tri = &mesh.triangles[h.triangle as usize];
            let [i0, i1, i2] = tri.vertices.map(|k| k as usize);
            a.set(i, mesh.positions[i0]);
            b.set(i, mesh.positions[i1]);
            c.set(i, mesh.positions[i2]);
            if tri.flags & HAS_NORMALS != 0 {
                na.set(i, mesh.normals[i0]);
                nb.set(i, mesh.normals[i1]);
                nc.set(i, mesh.normals[i2]);
            }
            t[i] = h.t;
            material[i] = tri.material;
        }
        let mut out = Points {
            p: Rows::default(),
            ng: Rows::default(),
            s: Rows::default(),
            t: Rows::default(),
            n: Rows::default(),
            front_face: [false; W],
            material,
        };
        let sub = |a: [f32; 3], b: [f32; 3]| [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
        let clamp = |x: f32, lo: f32, hi: f32| {
            // `f32::clamp` without its check that `lo <= hi` (lanes without a hit may break it).
            let x = if x < lo { lo } else { x };
            if x > hi { hi } else { x }
        };
        for i in 0..W {
            let lane = |r: &Rows| [r.0[0][i], r.0[1][i], r.0[2][i]];
            let (a, b, c, o, d) = (lane(&a), lane(&b), lane(&c), lane(o), lane(d));
            // `barycentrics` at `o + d t`.
            let q = [o[0] + d[0] * t[i], o[1] + d[1] * t[i], o[2] + d[2] * t[i]];
            let (e1, e2, ep) = (sub(b, a), sub(c, a), sub(q, a));
            let (d11, d12, d22) = (dot(e1, e1), dot(e1, e2), dot(e2, e2));
            let (dp1, dp2) = (dot(ep, e1), dot(ep, e2));
            let denom = d11 * d22 - d12 * d12;
            let v = clamp((d22 * dp1 - d12 * dp2) / denom, 0.0, 1.0);
            let w = clamp((d11 * dp2 - d12 * dp1) / denom, 0.0, 1.0 - v);
            let (bx, by, bz) = if denom <= 0.0 { (1.0, 0.0, 0.0) } else { (1.0 - v - w, v, w) };
            let p: [f32; 3] = std::array::from_fn(|k| a[k] * bx + b[k] * by + c[k] * bz);
            // The face normal, `Vec3::normalize`'s way, and the side the ray came from.
            let cross = [e1[1] * e2[2] - e2[1] * e1[2], e1[2] * e2[0] - e2[2] * e1[0], e1[0] * e2[1] - e2[0] * e1[1]];
            let recip = 1.0 / dot(cross, cross).sqrt();
            let face = cross.map(|x| x * recip);
            let front = dot(face, d) < 0.0;
            let ng = select(front, face, face.map(|x| -x));
            // The interpolated normal where it has a length (lanes without normals hold zeros,
            // which have none). Branch-free, so that the lanes share registers.
            let (na, nb, nc) = (lane(&na), lane(&nb), lane(&nc));
            let n: [f32; 3] = std::array::from_fn(|k| na[k] * bx + nb[k] * by + nc[k] * bz);
            let rcp = 1.0 / dot(n, n).sqrt();
            let n_front = select(rcp.is_finite() & (rcp > 0.0), n.map(|x| x * rcp), face);
            let ns = select(front, n_front, n_front.map(|x| -x));
            let finite = ns[0].is_finite() & ns[1].is_finite() & ns[2].is_finite();
            let ns = select((dot(ns, d.map(|x| -x)) <= 0.0) | !finite, ng, ns);
            // `Frame::from_normal`.
            let sign = 1.0f32.copysign(ns[2]);
            let k = -1.0 / (sign + ns[2]);
            let m = ns[0] * ns[1] * k;
            let s = [1.0 + sign * ns[0] * ns[0] * k, sign * m, -sign * ns[0]];
            let tt = [m, sign + ns[1] * ns[1] * k, -ns[1]];
            for axis in 0..3 {
                out.p.0[axis][i] = p[axis];
                out.ng.0[axis][i] = ng[axis];
                out.s.0[axis][i] = s[axis];
                out.t.0[axis][i] = tt[axis];
                out.n.0[axis][i] = ns[axis];
            }
            out.front_face[i] = front;
        }
        out
    }
}
