//! Where a ray meets a surface: the hit, the surface point with its shading frame (interpolated
//! and normal-mapped normals, the clear coat's own normal), and ray origins offset off it.

use crate::material::{Surfaces, TextureContext};
use crate::math::Frame;
use crate::mesh::{HAS_NORMALS, HAS_TANGENTS, Mesh, TriangleRecord, barycentrics};
use crate::texture::TextureRef;
use glam::{Vec2, Vec3, Vec3A, Vec4};

/// A closest hit: the triangle (BVH order) and the distance along the ray.
#[derive(Clone, Copy, Debug)]
pub struct Hit {
    pub triangle: u32,
    pub t: f32,
}

/// Everything the estimators need to know about a surface point.
#[derive(Clone, Copy, Debug)]
pub struct SurfacePoint {
    pub p: Vec3,
    /// Geometric normal, flipped to the side the ray came from.
    pub ng: Vec3,
    /// Shading frame (interpolated and normal-mapped normal), on the same side as `ng`.
    pub frame: Frame,
    /// A clear coat's own normal (KHR_materials_clearcoat): from its clearcoatNormalTexture, or
    /// else, where a normal map bent `frame.n`, the interpolated normal without the map.
    /// `None`: the coat takes `frame.n`.
    pub coat_normal: Option<Vec3>,
    /// True when the ray hit the triangle's front (counter-clockwise) face.
    pub front_face: bool,
    /// KHR_materials_anisotropy's direction at the point (world space), where the material is
    /// anisotropic and the mesh has tangents.
    pub anisotropy: Option<Vec3>,
    pub uv: [Vec2; 2],
    /// The vertex colour (COLOR_0) at the point; white without one.
    pub color: Vec4,
    pub material: u32,
    pub triangle: u32,
}

impl SurfacePoint {
    /// The surface point of `hit` on `mesh`, for a ray from `o` with direction `d`.
    pub(crate) fn at(mesh: &Mesh, surfaces: &Surfaces, hit: Hit, o: Vec3, d: Vec3) -> SurfacePoint {
        let tri = &mesh.triangles[hit.triangle as usize];
        let [i0, i1, i2] = tri.vertices.map(|i| i as usize);
        // The point's geometry in `Vec3A`s: the same bits as in `Vec3`s, in fewer instructions.
        let (a, b, c) = mesh.corners_a(tri);
        let (oa, da) = (Vec3A::from(o), Vec3A::from(d));
        let bary = barycentrics(a, b, c, oa + da * hit.t);
        let p = Vec3::from(a * bary.x + b * bary.y + c * bary.z);
        // `Vec3::normalize`'s arithmetic (times the reciprocal length; `Vec3A`'s divides).
        let cross = (b - a).cross(c - a);
        let n_face_a = cross * cross.length_recip();
        let front_face = n_face_a.dot(da) < 0.0;
        let n_face = Vec3::from(n_face_a);
        let ng = Vec3::from(if front_face { n_face_a } else { -n_face_a });
        let bary = Vec3::from(bary);
        let ctx = mesh.texture_context(surfaces, tri, bary);
        let material = &surfaces.materials()[tri.material as usize];
        // Shading normal in the triangle's front orientation, flipped to the viewer's side at the end.
        let mut n_front = n_face;
        if tri.flags & HAS_NORMALS != 0 {
            let n = mesh.normals[i0] * bary.x + mesh.normals[i1] * bary.y + mesh.normals[i2] * bary.z;
            if let Some(n) = n.try_normalize() {
                n_front = n;
            }
        }
        let n_vertex = n_front;
        let tangents = tri.flags & HAS_TANGENTS != 0;
        let mut tangent = None;
        if tangents
            && material.normal_texture.is_some()
            && let Some((n, t)) =
                normal_mapped(mesh, tri, bary, &ctx, n_vertex, &material.normal_texture, material.normal_scale)
        {
            n_front = n;
            tangent = Some(t);
        }
        let mut ns = if front_face { n_front } else { -n_front };
        let mut frame = tangent.map(|t| Frame::from_normal_tangent(ns, t));
        // A shading normal facing away from the viewer would make the BSDF undefined: use ng.
        if ns.dot(-d) <= 0.0 || !ns.is_finite() {
            ns = ng;
            frame = None;
        }
        let frame = frame.unwrap_or_else(|| Frame::from_normal(ns));
        // The coat takes its own map, or else the unmapped normal where the layers below are mapped.
        let coat_normal = if material.clearcoat > 0.0 {
            let own = (tangents && material.clearcoat_normal_texture.is_some())
                .then(|| {
                    let (texture, scale) = (&material.clearcoat_normal_texture, material.clearcoat_normal_scale);
                    normal_mapped(mesh, tri, bary, &ctx, n_vertex, texture, scale)
                })
                .flatten();
            own.map(|(n, _)| n).or(tangent.map(|_| n_vertex))
        } else {
            None
        };
        let coat_normal = coat_normal.map(|n| if front_face { n } else { -n }).filter(|n| n.dot(-d) > 0.0);
        let anisotropy = (tangents && material.is_anisotropic())
            .then(|| anisotropy_direction(mesh, tri, bary, &ctx, n_vertex, material))
            .flatten();
        SurfacePoint {
            p,
            ng,
            frame,
            coat_normal,
            front_face,
            anisotropy,
            uv: ctx.uv,
            color: ctx.color,
            material: tri.material,
            triangle: hit.triangle,
        }
    }

    /// A ray origin just off the surface by `epsilon`, on the side `w` points to.
    pub(crate) fn offset_origin(&self, w: Vec3, epsilon: f32) -> Vec3 {
        let side = if w.dot(self.ng) >= 0.0 { 1.0 } else { -1.0 };
        self.p + self.ng * (side * epsilon)
    }
}

/// The interpolated tangent of `tri` (which has tangents) at `bary`, and glTF's bitangent
/// `cross(n, tangent) * tangent.w` for the normal `n`.
fn tangent_basis(mesh: &Mesh, tri: &TriangleRecord, bary: Vec3, n: Vec3) -> (Vec3, Vec3) {
    let [i0, i1, i2] = tri.vertices.map(|i| i as usize);
    let t = (mesh.tangents[i0] * bary.x + mesh.tangents[i1] * bary.y + mesh.tangents[i2] * bary.z).truncate();
    (t, n.cross(t) * mesh.tangents[i0].w.signum())
}

/// KHR_materials_anisotropy's direction in world space: the texture's (red, green) direction
/// (`2 c - 1`; the tangent without a texture), turned by the material's rotation, in the
/// (tangent, bitangent) frame of `tri` at `bary` around the normal `n`.
fn anisotropy_direction(
    mesh: &Mesh,
    tri: &TriangleRecord,
    bary: Vec3,
    ctx: &TextureContext,
    n: Vec3,
    material: &crate::material::Material,
) -> Option<Vec3> {
    let (t, bitangent) = tangent_basis(mesh, tri, bary, n);
    // The tangent made orthogonal to `n` and unit; the bitangent, `n x t`, shrinks with it.
    let across = t - n * n.dot(t);
    let len = across.length();
    if !(len > 0.0 && len.is_finite()) {
        return None;
    }
    let (t, bitangent) = (across / len, bitangent / len);
    let (x, y) = match material.anisotropy_texture {
        Some(_) => {
            let m = ctx.lookup(&material.anisotropy_texture, false);
            (2.0 * m.x - 1.0, 2.0 * m.y - 1.0)
        }
        None => (1.0, 0.0),
    };
    let (sin, cos) = libm::sincosf(material.anisotropy_rotation);
    let (x, y) = (cos * x - sin * y, sin * x + cos * y);
    (t * x + bitangent * y).try_normalize()
}

/// A normal map's normal at barycentrics `bary` of `tri` (which has tangents), in the
/// tangent frame around the interpolated normal `n`, and the tangent; `None` where it
/// degenerates.
fn normal_mapped(
    mesh: &Mesh,
    tri: &TriangleRecord,
    bary: Vec3,
    ctx: &TextureContext,
    n: Vec3,
    texture: &Option<TextureRef>,
    scale: f32,
) -> Option<(Vec3, Vec3)> {
    let (t, bitangent) = tangent_basis(mesh, tri, bary, n);
    let m = ctx.lookup(texture, false);
    let local = Vec3::new((2.0 * m.x - 1.0) * scale, (2.0 * m.y - 1.0) * scale, 2.0 * m.z - 1.0);
    Some(((t * local.x + bitangent * local.y + n * local.z).try_normalize()?, t))
}
