//! The renderable scene: triangles in BVH order with their vertex attributes, materials,
//! textures, lights and cameras. [`SceneBuilder`] is how loaders (glTF, built-ins) make one.

use crate::bvh::{Bvh, PACKET};
use crate::camera::Camera;
use crate::channels::{Channels, ColorModel};
use crate::light::{LightSet, PunctualLight};
use crate::material::{AlphaMode, Material, TextureContext};
use crate::math::Frame;
use crate::sampler::{mix64, unit_f32};
use crate::texture::{Image, Texture, TextureRef};
use glam::{Mat3, Mat4, Vec2, Vec3, Vec4};

/// Per-triangle flags.
pub const HAS_NORMALS: u8 = 1;
pub const HAS_TANGENTS: u8 = 2;
pub const ALPHA_TESTED: u8 = 4;
pub const HAS_COLORS: u8 = 8;

#[derive(Clone, Copy, Debug)]
pub struct TriangleRecord {
    pub vertices: [u32; 3],
    pub material: u32,
    pub flags: u8,
}

/// The largest world coordinate a vertex may have. Box areas square coordinates, and beyond this
/// the BVH builder's would overflow `f32`; a physical scene in metres is far inside it.
pub const WORLD_LIMIT: f32 = 1e15;

/// One mesh primitive as a loader hands it over, in object space.
#[derive(Clone, Debug, Default)]
pub struct MeshData {
    pub positions: Vec<Vec3>,
    pub normals: Option<Vec<Vec3>>,
    pub uv0: Option<Vec<Vec2>>,
    pub uv1: Option<Vec<Vec2>>,
    pub tangents: Option<Vec<Vec4>>,
    /// COLOR_0: linear RGBA that multiplies the base colour.
    pub colors: Option<Vec<Vec4>>,
    pub indices: Vec<u32>,
    pub material: u32,
}

#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    #[error("mesh '{mesh}': {problem}")]
    BadMesh { mesh: String, problem: String },
    #[error("material index {0} does not exist")]
    BadMaterial(u32),
}

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
    pub uv: [Vec2; 2],
    /// The vertex colour (COLOR_0) at the point; white without one.
    pub color: Vec4,
    pub material: u32,
    pub triangle: u32,
}

pub struct Scene {
    pub positions: Vec<Vec3>,
    pub normals: Vec<Vec3>,
    pub uv: [Vec<Vec2>; 2],
    pub tangents: Vec<Vec4>,
    /// Vertex colours; empty when no mesh has any.
    pub colors: Vec<Vec4>,
    pub triangles: Vec<TriangleRecord>,
    pub bvh: Bvh,
    pub materials: Vec<Material>,
    pub images: Vec<Image>,
    pub textures: Vec<Texture>,
    pub lights: LightSet,
    pub cameras: Vec<Camera>,
    pub bounds: (Vec3, Vec3),
    /// Ray-origin offset: relative to the scene's size and distance from the origin.
    pub ray_epsilon: f32,
    /// True when any triangle's material cuts out by alpha (mask or blend).
    pub alpha_tested: bool,
    /// True when some triangle's material transmits (KHR_materials_transmission): shadow rays
    /// then look for smooth thin walls to pass ([`Scene::transmittance`]).
    pub thin_walls: bool,
}

/// A number in `[0, 1)` that is a pure function of a ray and a triangle, for stochastic alpha
/// blending: rays are continuous random variables, so it is as good as a fresh uniform one
/// (pbrt-v4 hashes the ray the same way), and the triangle makes each layer's number its own.
fn ray_hash(o: Vec3, d: Vec3, triangle: u32) -> f32 {
    let bits = |v: Vec3| ((v.x.to_bits() as u64) << 32 | v.y.to_bits() as u64) ^ (v.z.to_bits() as u64).rotate_left(17);
    let h = mix64(bits(o) ^ mix64(bits(d) ^ mix64(triangle as u64)));
    unit_f32(h)
}

/// Smooth thin walls a shadow ray or a path passes straight through before it gives up: a bound
/// that only degenerate geometry (a stack of coincident panes) reaches.
pub const MAX_WALLS_PASSED: u32 = 16;

/// Collects geometry and materials, then builds the BVH and light distribution.
#[derive(Default)]
pub struct SceneBuilder {
    positions: Vec<Vec3>,
    normals: Vec<Vec3>,
    uv: [Vec<Vec2>; 2],
    tangents: Vec<Vec4>,
    colors: Vec<Vec4>,
    triangles: Vec<TriangleRecord>,
    pub materials: Vec<Material>,
    pub images: Vec<Image>,
    pub textures: Vec<Texture>,
    pub punctual: Vec<PunctualLight>,
    pub cameras: Vec<Camera>,
    pub environment: Vec3,
    /// Triangles dropped because they have no area.
    pub degenerate_triangles: usize,
}

impl SceneBuilder {
    pub fn new() -> Self {
        Self::default()
    }

    pub fn add_material(&mut self, m: Material) -> u32 {
        self.materials.push(m);
        (self.materials.len() - 1) as u32
    }

    pub fn triangle_count(&self) -> usize {
        self.triangles.len()
    }

    /// Adds a mesh primitive placed by `transform` (object to world).
    pub fn add_mesh(&mut self, name: &str, mesh: MeshData, transform: Mat4) -> Result<(), SceneError> {
        let bad = |problem: String| SceneError::BadMesh { mesh: name.to_string(), problem };
        let n = mesh.positions.len();
        if !mesh.indices.len().is_multiple_of(3) {
            return Err(bad(format!("{} indices is not a multiple of 3", mesh.indices.len())));
        }
        if let Some(&i) = mesh.indices.iter().find(|&&i| i as usize >= n) {
            return Err(bad(format!("index {i} is out of range for {n} vertices")));
        }
        for (what, len) in [
            ("normals", mesh.normals.as_ref().map(Vec::len)),
            ("uv0", mesh.uv0.as_ref().map(Vec::len)),
            ("uv1", mesh.uv1.as_ref().map(Vec::len)),
            ("tangents", mesh.tangents.as_ref().map(Vec::len)),
            ("colors", mesh.colors.as_ref().map(Vec::len)),
        ] {
            if let Some(len) = len.filter(|&l| l != n) {
                return Err(bad(format!("{len} {what} for {n} positions")));
            }
        }
        if mesh.positions.iter().any(|p| !p.is_finite()) {
            return Err(bad("a vertex position is not finite".into()));
        }
        let material = self.materials.get(mesh.material as usize).ok_or(SceneError::BadMaterial(mesh.material))?;
        let mesh = match material.normal_texture.or(material.clearcoat_normal_texture) {
            Some(normal_map) if mesh.tangents.is_none() => with_mikktspace_tangents(mesh, &normal_map),
            _ => mesh,
        };
        let n = mesh.positions.len();
        let mut flags = 0;
        if !matches!(material.alpha_mode, AlphaMode::Opaque) {
            flags |= ALPHA_TESTED;
        }
        let normal_matrix = Mat3::from_mat4(transform).inverse().transpose();
        let linear = Mat3::from_mat4(transform);
        let flip = linear.determinant() < 0.0;
        let base = self.positions.len() as u32;
        let world: Vec<Vec3> = mesh.positions.iter().map(|&p| transform.transform_point3(p)).collect();
        if let Some(p) = world.iter().find(|p| !p.is_finite() || p.abs().max_element() > WORLD_LIMIT) {
            return Err(bad(format!(
                "a vertex lands at {p} after its node transform (coordinates must stay within {WORLD_LIMIT:e})"
            )));
        }
        self.positions.extend(world);
        match &mesh.normals {
            Some(ns) => {
                flags |= HAS_NORMALS;
                self.normals.extend(ns.iter().map(|&v| (normal_matrix * v).normalize_or_zero()));
            }
            None => self.normals.extend(std::iter::repeat_n(Vec3::ZERO, n)),
        }
        for (set, uv) in [&mesh.uv0, &mesh.uv1].into_iter().enumerate() {
            match uv {
                Some(uv) => self.uv[set].extend(uv),
                None => self.uv[set].extend(std::iter::repeat_n(Vec2::ZERO, n)),
            }
        }
        match &mesh.tangents {
            Some(ts) => {
                flags |= HAS_TANGENTS;
                self.tangents.extend(ts.iter().map(|t| (linear * t.truncate()).normalize_or_zero().extend(t.w)));
            }
            None => self.tangents.extend(std::iter::repeat_n(Vec4::ZERO, n)),
        }
        // Vertex colours are stored only once some mesh has them (white for the vertices before).
        match &mesh.colors {
            Some(colors) => {
                flags |= HAS_COLORS;
                self.colors.resize(base as usize, Vec4::ONE);
                // Colours are reflectance factors: NaN counts as 0, and nothing leaves [0, 1].
                self.colors.extend(
                    colors.iter().map(|c| Vec4::select(c.is_nan_mask(), Vec4::ZERO, c.clamp(Vec4::ZERO, Vec4::ONE))),
                );
            }
            None if !self.colors.is_empty() => self.colors.extend(std::iter::repeat_n(Vec4::ONE, n)),
            None => {}
        }
        for tri in mesh.indices.chunks_exact(3) {
            let mut v = [tri[0] + base, tri[1] + base, tri[2] + base];
            if flip {
                v.swap(1, 2); // a mirroring transform reverses the winding
            }
            let [a, b, c] = v.map(|i| self.positions[i as usize]);
            if (b - a).cross(c - a).length_squared() <= 0.0 {
                self.degenerate_triangles += 1;
                continue;
            }
            self.triangles.push(TriangleRecord { vertices: v, material: mesh.material, flags });
        }
        Ok(())
    }

    /// Builds the BVH (reordering triangles to BVH order) and the light distribution.
    pub fn build(self) -> Scene {
        let corners: Vec<[Vec3; 3]> =
            self.triangles.iter().map(|t| t.vertices.map(|i| self.positions[i as usize])).collect();
        let (bvh, order) = Bvh::build(&corners);
        let triangles: Vec<TriangleRecord> = order.iter().map(|&i| self.triangles[i as usize]).collect();
        let (mut lo, mut hi) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
        for t in &triangles {
            for &v in &t.vertices {
                lo = lo.min(self.positions[v as usize]);
                hi = hi.max(self.positions[v as usize]);
            }
        }
        for l in &self.punctual {
            if let Some(p) = l.position() {
                lo = lo.min(p);
                hi = hi.max(p);
            }
        }
        if lo.x > hi.x {
            (lo, hi) = (Vec3::splat(-1.0), Vec3::splat(1.0));
        }
        let extent = (hi - lo).max_element().max(1e-6);
        let magnitude = lo.abs().max(hi.abs()).max_element();
        let ray_epsilon = 1e-5 * extent.max(magnitude);
        let mut scene = Scene {
            positions: self.positions,
            normals: self.normals,
            uv: self.uv,
            tangents: self.tangents,
            colors: self.colors,
            triangles,
            bvh,
            materials: self.materials,
            images: self.images,
            textures: self.textures,
            lights: LightSet::default(),
            cameras: self.cameras,
            bounds: (lo, hi),
            ray_epsilon,
            alpha_tested: false,
            thin_walls: false,
        };
        scene.alpha_tested = scene.triangles.iter().any(|t| t.flags & ALPHA_TESTED != 0);
        let thin_walls = scene.used_materials().any(|m| m.transmission > 0.0);
        scene.thin_walls = thin_walls;
        scene.lights = LightSet::build(&scene, self.punctual, self.environment, None);
        scene
    }
}

/// `mesh`'s vertex `order[k]` as vertex `k`, every attribute with it, and triangles `indices`.
fn gather_vertices(mesh: &MeshData, order: &[u32], indices: Vec<u32>) -> MeshData {
    fn pick<T: Copy>(attribute: &Option<Vec<T>>, order: &[u32]) -> Option<Vec<T>> {
        attribute.as_ref().map(|a| order.iter().map(|&i| a[i as usize]).collect())
    }
    MeshData {
        positions: order.iter().map(|&i| mesh.positions[i as usize]).collect(),
        normals: pick(&mesh.normals, order),
        uv0: pick(&mesh.uv0, order),
        uv1: pick(&mesh.uv1, order),
        tangents: pick(&mesh.tangents, order),
        colors: pick(&mesh.colors, order),
        indices,
        material: mesh.material,
    }
}

/// The mesh with one vertex per triangle corner, each carrying its face's normal (zero for a
/// triangle without area): flat shading made explicit.
fn with_flat_normals(mesh: MeshData) -> MeshData {
    let normals = mesh
        .indices
        .chunks_exact(3)
        .flat_map(|t| {
            let [a, b, c] = [t[0], t[1], t[2]].map(|i| mesh.positions[i as usize]);
            [(b - a).cross(c - a).normalize_or_zero(); 3]
        })
        .collect();
    let corners = (0..mesh.indices.len() as u32).collect();
    MeshData { normals: Some(normals), ..gather_vertices(&mesh, &mesh.indices, corners) }
}

/// The mesh with MikkTSpace tangents (Mikkelsen 2008), which glTF asks for when a normal-mapped
/// mesh comes without TANGENT: normal maps are baked in that tangent space. Texture coordinates
/// are the normal map's, after its KHR_texture_transform (which turns the map's axes with it); a
/// mesh without those coordinates is returned as it is (its normal map cannot be oriented). A mesh
/// without normals is flat-shaded, as glTF says, so it first gets its faces' normals, one copy of
/// a vertex per triangle. MikkTSpace gives each triangle corner its own tangent: corners of one
/// vertex that agree share it, and the others get a copy of the vertex (at UV seams and mirrored
/// UVs).
fn with_mikktspace_tangents(mesh: MeshData, normal_map: &crate::texture::TextureRef) -> MeshData {
    use bevy_mikktspace::{Geometry, Ops, TangentSpace};
    struct Libm;
    impl Ops for Libm {
        fn sqrt(x: f32) -> f32 {
            libm::sqrtf(x)
        }
        fn acos(x: f32) -> f32 {
            libm::acos(x as f64) as f32 // in f64, as the C implementation computes it
        }
    }
    struct Corners<'a> {
        indices: &'a [u32],
        positions: &'a [Vec3],
        normals: &'a [Vec3],
        uv: &'a [Vec2],
        normal_map: &'a crate::texture::TextureRef,
        tangents: Vec<Vec4>,
    }
    impl Corners<'_> {
        fn vertex(&self, face: usize, corner: usize) -> usize {
            self.indices[3 * face + corner] as usize
        }
    }
    impl Geometry<Libm> for Corners<'_> {
        fn num_faces(&self) -> usize {
            self.indices.len() / 3
        }
        fn num_vertices_of_face(&self, _: usize) -> usize {
            3
        }
        fn position(&self, face: usize, corner: usize) -> [f32; 3] {
            self.positions[self.vertex(face, corner)].to_array()
        }
        fn normal(&self, face: usize, corner: usize) -> [f32; 3] {
            self.normals[self.vertex(face, corner)].to_array()
        }
        fn tex_coord(&self, face: usize, corner: usize) -> [f32; 2] {
            self.normal_map.apply_transform(self.uv[self.vertex(face, corner)]).to_array()
        }
        fn set_tangent(&mut self, space: Option<TangentSpace>, face: usize, corner: usize) {
            let [x, y, z, w] = space.unwrap_or_default().tangent_encoded();
            // glTF's v runs down the image and MikkTSpace's up, so glTF's bitangent
            // (cross(normal, tangent) * w, the normal map's +Y) is MikkTSpace's negated.
            self.tangents[3 * face + corner] = Vec4::new(x, y, z, -w);
        }
    }
    fn uv_set(mesh: &MeshData, set: u32) -> &Option<Vec<Vec2>> {
        if set == 0 { &mesh.uv0 } else { &mesh.uv1 }
    }
    if uv_set(&mesh, normal_map.texcoord).is_none() {
        return mesh;
    }
    let mesh = if mesh.normals.is_none() { with_flat_normals(mesh) } else { mesh };
    let (Some(normals), Some(uv)) = (&mesh.normals, uv_set(&mesh, normal_map.texcoord)) else {
        return mesh;
    };
    let mut corners = Corners {
        indices: &mesh.indices,
        positions: &mesh.positions,
        normals,
        uv,
        normal_map,
        tangents: vec![Vec4::ZERO; mesh.indices.len()],
    };
    let generated = bevy_mikktspace::generate_tangents(&mut corners).is_ok(); // no error exists yet
    let tangents = corners.tangents;
    if !generated {
        return mesh;
    }
    // Corners of one vertex with the same tangent share a vertex again.
    let (mut order, mut vertex_tangents, mut indices) = (Vec::new(), Vec::new(), Vec::with_capacity(tangents.len()));
    let mut shared = std::collections::HashMap::new();
    for (&i, &t) in mesh.indices.iter().zip(&tangents) {
        let index = *shared.entry((i, t.to_array().map(f32::to_bits))).or_insert_with(|| {
            order.push(i);
            vertex_tangents.push(t);
            order.len() as u32 - 1
        });
        indices.push(index);
    }
    MeshData { tangents: Some(vertex_tangents), ..gather_vertices(&mesh, &order, indices) }
}

impl Scene {
    pub fn diagonal(&self) -> f32 {
        (self.bounds.1 - self.bounds.0).length()
    }

    fn texture_context(&self, tri: &TriangleRecord, b: Vec3) -> TextureContext<'_> {
        let [i0, i1, i2] = tri.vertices.map(|i| i as usize);
        let uv = std::array::from_fn(|s| self.uv[s][i0] * b.x + self.uv[s][i1] * b.y + self.uv[s][i2] * b.z);
        let color = if tri.flags & HAS_COLORS != 0 {
            self.colors[i0] * b.x + self.colors[i1] * b.y + self.colors[i2] * b.z
        } else {
            Vec4::ONE
        };
        TextureContext { images: &self.images, textures: &self.textures, uv, color }
    }

    /// Barycentric coordinates of point `p` (on the triangle's plane) in triangle `slot`.
    fn barycentrics(&self, tri: &TriangleRecord, p: Vec3) -> Vec3 {
        let [a, b, c] = tri.vertices.map(|i| self.positions[i as usize]);
        let (e1, e2, ep) = (b - a, c - a, p - a);
        let (d11, d12, d22) = (e1.dot(e1), e1.dot(e2), e2.dot(e2));
        let (dp1, dp2) = (ep.dot(e1), ep.dot(e2));
        let denom = d11 * d22 - d12 * d12;
        if denom <= 0.0 {
            return Vec3::new(1.0, 0.0, 0.0);
        }
        let v = ((d22 * dp1 - d12 * dp2) / denom).clamp(0.0, 1.0);
        let w = ((d11 * dp2 - d12 * dp1) / denom).clamp(0.0, 1.0 - v);
        Vec3::new(1.0 - v - w, v, w)
    }

    /// False when the hit point lies in a cut-out (alpha mask) part of the triangle, or when the
    /// ray passes a blended one (see [`Material::is_cut_out`]).
    fn accepts(&self, slot: u32, o: Vec3, d: Vec3, t: f32) -> bool {
        let tri = &self.triangles[slot as usize];
        if tri.flags & ALPHA_TESTED == 0 {
            return true;
        }
        let b = self.barycentrics(tri, o + d * t);
        !self.materials[tri.material as usize].is_cut_out(&self.texture_context(tri, b), || ray_hash(o, d, slot))
    }

    pub fn intersect(&self, o: Vec3, d: Vec3, tmax: f32) -> Option<Hit> {
        let hit = if self.alpha_tested {
            self.bvh.closest_hit(o, d, tmax, |slot, t| self.accepts(slot, o, d, t))
        } else {
            self.bvh.closest_hit(o, d, tmax, |_, _| true) // no cut-outs: skip the per-hit lookup
        };
        hit.map(|(triangle, t)| Hit { triangle, t })
    }

    /// [`Scene::intersect`] for up to [`PACKET`] rays `(o, d, tmax)` at once, with the same answers;
    /// faster when the rays are coherent (camera rays of one pixel or of neighbours).
    pub fn intersect_packet(&self, rays: &[(Vec3, Vec3, f32)]) -> [Option<Hit>; PACKET] {
        let hits = if self.alpha_tested {
            self.bvh.closest_hits(rays, |r, slot, t| self.accepts(slot, rays[r].0, rays[r].1, t))
        } else {
            self.bvh.closest_hits(rays, |_, _, _| true)
        };
        hits.map(|h| h.map(|(triangle, t)| Hit { triangle, t }))
    }

    pub fn occluded(&self, o: Vec3, d: Vec3, tmax: f32) -> bool {
        if self.alpha_tested {
            self.bvh.occluded(o, d, tmax, |slot, t| self.accepts(slot, o, d, t))
        } else {
            self.bvh.occluded(o, d, tmax, |_, _| true)
        }
    }

    /// A ray origin just off the surface, on the side `w` points to.
    pub fn offset_origin(&self, sp: &SurfacePoint, w: Vec3) -> Vec3 {
        let side = if w.dot(sp.ng) >= 0.0 { 1.0 } else { -1.0 };
        sp.p + sp.ng * (side * self.ray_epsilon)
    }

    /// Is `to` visible from surface point `sp`? (The shadow ray stops short of `to` by epsilon.)
    pub fn visible(&self, sp: &SurfacePoint, wi: Vec3, distance: f32) -> bool {
        let o = self.offset_origin(sp, wi);
        let tmax = distance - 2.0 * self.ray_epsilon;
        tmax <= 0.0 || !self.occluded(o, wi, tmax)
    }

    /// What reaches surface point `sp` from `distance` along `wi`: `None` when something opaque
    /// is in the way, else the product of [`Bsdf::straight_through`] over the smooth thin walls
    /// the shadow ray passes (one when there are none). Light sampling through a glass pane is
    /// what lets a point light or the sun shine through it: no BSDF-sampled path can hit them.
    ///
    /// [`Bsdf::straight_through`]: crate::bsdf::Bsdf::straight_through
    pub fn transmittance<M: ColorModel>(&self, sp: &SurfacePoint, wi: Vec3, distance: f32, model: &M) -> Option<M::C> {
        if !self.thin_walls {
            return self.visible(sp, wi, distance).then_some(M::C::ONE);
        }
        let target = sp.p + wi * distance;
        let mut o = self.offset_origin(sp, wi);
        let mut through = M::C::ONE;
        for _ in 0..=MAX_WALLS_PASSED {
            let tmax = if distance.is_finite() { o.distance(target) - 2.0 * self.ray_epsilon } else { f32::INFINITY };
            let Some(hit) = (tmax > 0.0).then(|| self.intersect(o, wi, tmax)).flatten() else {
                return Some(through);
            };
            let wall = self.surface(hit, o, wi);
            if !self.may_pass(&wall) {
                return None;
            }
            let t = self.bsdf(&wall, model).straight_through(wall.frame.to_local(-wi));
            if t.max_element() <= 0.0 {
                return None;
            }
            through *= t;
            o = self.offset_origin(&wall, wi);
        }
        None
    }

    /// True when `sp`'s material transmits, so that it may be a smooth thin wall that light passes
    /// straight through (its BSDF decides: [`crate::bsdf::Bsdf::straight_through`]).
    pub fn may_pass(&self, sp: &SurfacePoint) -> bool {
        self.thin_walls && self.materials[sp.material as usize].transmission > 0.0
    }

    /// The surface point of a hit, for a ray with direction `d`.
    pub fn surface(&self, hit: Hit, o: Vec3, d: Vec3) -> SurfacePoint {
        let tri = &self.triangles[hit.triangle as usize];
        let [i0, i1, i2] = tri.vertices.map(|i| i as usize);
        let [a, b, c] = [self.positions[i0], self.positions[i1], self.positions[i2]];
        let bary = self.barycentrics(tri, o + d * hit.t);
        let p = a * bary.x + b * bary.y + c * bary.z;
        let n_face = (b - a).cross(c - a).normalize();
        let front_face = n_face.dot(d) < 0.0;
        let ng = if front_face { n_face } else { -n_face };
        let ctx = self.texture_context(tri, bary);
        let material = &self.materials[tri.material as usize];
        // Shading normal in the triangle's front orientation, flipped to the viewer's side at the end.
        let mut n_front = n_face;
        if tri.flags & HAS_NORMALS != 0 {
            let n = self.normals[i0] * bary.x + self.normals[i1] * bary.y + self.normals[i2] * bary.z;
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
                self.normal_mapped(tri, bary, &ctx, n_vertex, &material.normal_texture, material.normal_scale)
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
                    self.normal_mapped(tri, bary, &ctx, n_vertex, texture, scale)
                })
                .flatten();
            own.map(|(n, _)| n).or(tangent.map(|_| n_vertex))
        } else {
            None
        };
        let coat_normal = coat_normal.map(|n| if front_face { n } else { -n }).filter(|n| n.dot(-d) > 0.0);
        SurfacePoint {
            p,
            ng,
            frame,
            coat_normal,
            front_face,
            uv: ctx.uv,
            color: ctx.color,
            material: tri.material,
            triangle: hit.triangle,
        }
    }

    /// A normal map's normal at barycentrics `bary` of `tri` (which has tangents), in the
    /// tangent frame around the interpolated normal `n`, and the tangent; `None` where it
    /// degenerates.
    fn normal_mapped(
        &self,
        tri: &TriangleRecord,
        bary: Vec3,
        ctx: &TextureContext,
        n: Vec3,
        texture: &Option<TextureRef>,
        scale: f32,
    ) -> Option<(Vec3, Vec3)> {
        let [i0, i1, i2] = tri.vertices.map(|i| i as usize);
        let t = (self.tangents[i0] * bary.x + self.tangents[i1] * bary.y + self.tangents[i2] * bary.z).truncate();
        // glTF: bitangent = cross(normal, tangent.xyz) * tangent.w
        let bitangent = n.cross(t) * self.tangents[i0].w.signum();
        let m = ctx.lookup(texture, false);
        let local = Vec3::new((2.0 * m.x - 1.0) * scale, (2.0 * m.y - 1.0) * scale, 2.0 * m.z - 1.0);
        Some(((t * local.x + bitangent * local.y + n * local.z).try_normalize()?, t))
    }

    /// Emitted radiance leaving `sp` towards the viewer.
    pub fn emission<M: ColorModel>(&self, sp: &SurfacePoint, model: &M) -> M::C {
        let material = &self.materials[sp.material as usize];
        if !material.is_emissive() || !(sp.front_face || material.double_sided) {
            return M::C::ZERO;
        }
        let ctx = TextureContext { images: &self.images, textures: &self.textures, uv: sp.uv, color: sp.color };
        material.emission_at(&ctx, model)
    }

    pub fn bsdf<M: ColorModel>(&self, sp: &SurfacePoint, model: &M) -> crate::bsdf::Bsdf<M::C> {
        let ctx = TextureContext { images: &self.images, textures: &self.textures, uv: sp.uv, color: sp.color };
        let bsdf = self.materials[sp.material as usize].bsdf(&ctx, model);
        match sp.coat_normal {
            Some(n) => bsdf.with_coat_normal(sp.frame.to_local(n)),
            None => bsdf,
        }
    }

    /// The materials (by name) that carry spectral content, with what it is: what makes
    /// `--color auto` render spectrally. Only materials some triangle uses count.
    pub fn spectral_content(&self) -> Vec<String> {
        self.used_materials()
            .filter(|m| m.spectra.is_spectral())
            .map(|m| format!("'{}' ({})", m.name, m.spectra.describe().join(", ")))
            .collect()
    }

    /// The largest directional albedo of any material: `q` of Dimov, Gurov and Penzov.
    pub fn max_albedo(&self) -> f32 {
        self.used_materials().map(|m| m.max_albedo(&self.images, &self.textures)).fold(0.0, f32::max)
    }

    /// The materials some triangle uses, each once, in index order.
    fn used_materials(&self) -> impl Iterator<Item = &Material> {
        let used: std::collections::BTreeSet<u32> = self.triangles.iter().map(|t| t.material).collect();
        used.into_iter().map(|m| &self.materials[m as usize])
    }
}
