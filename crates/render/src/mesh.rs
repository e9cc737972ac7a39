//! Triangle meshes: what loaders hand over ([`MeshData`], in object space), and the scene's
//! world-space vertex and triangle arrays they are gathered into ([`Mesh`]), with the vertex
//! processing glTF asks for (flat normals, MikkTSpace tangents).

use crate::material::{AlphaMode, Material, Surfaces, TextureContext};
use crate::texture::TextureRef;
use glam::{Mat3, Mat4, Vec2, Vec3, Vec3A, Vec4};

/// Per-triangle flags.
pub const HAS_NORMALS: u8 = 1;
pub const HAS_TANGENTS: u8 = 2;
pub const ALPHA_TESTED: u8 = 4;
pub const HAS_COLORS: u8 = 8;
/// The mesh has a UV set (either); without one both sets are zero at every vertex.
pub const HAS_UV: u8 = 16;

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

/// The scene's triangles and their vertex attributes in world space. Triangles are in BVH order
/// once the scene is built; every attribute array has one entry per vertex.
#[derive(Default)]
pub struct Mesh {
    pub positions: Vec<Vec3>,
    /// Zero for vertices of meshes without normals.
    pub normals: Vec<Vec3>,
    pub uv: [Vec<Vec2>; 2],
    /// Zero for vertices of meshes without tangents.
    pub tangents: Vec<Vec4>,
    /// Vertex colours; empty when no mesh has any.
    pub colors: Vec<Vec4>,
    pub triangles: Vec<TriangleRecord>,
}

impl Mesh {
    /// Adds a mesh primitive placed by `transform` (object to world), its material one of
    /// `materials`. Returns how many of its triangles were dropped for having no area.
    pub(crate) fn add(
        &mut self,
        name: &str,
        mesh: MeshData,
        transform: Mat4,
        materials: &[Material],
    ) -> Result<usize, SceneError> {
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
        let material = materials.get(mesh.material as usize).ok_or(SceneError::BadMaterial(mesh.material))?;
        // Anisotropy turns with the tangent frame too (its texture's coordinates, or set 0).
        let anisotropy = material
            .is_anisotropic()
            .then(|| material.anisotropy_texture.unwrap_or(TextureRef { texture: 0, texcoord: 0, transform: None }));
        let mesh = match material.normal_texture.or(material.clearcoat_normal_texture).or(anisotropy) {
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
        let mut degenerate = 0;
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
                Some(uv) => {
                    flags |= HAS_UV;
                    self.uv[set].extend(uv)
                }
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
                degenerate += 1;
                continue;
            }
            self.triangles.push(TriangleRecord { vertices: v, material: mesh.material, flags });
        }
        Ok(degenerate)
    }

    /// The triangle's three corners.
    pub fn corners(&self, tri: &TriangleRecord) -> [Vec3; 3] {
        tri.vertices.map(|i| self.positions[i as usize])
    }

    /// [`Mesh::corners`] in `Vec3A`s, each loaded straight into its register (built as an array
    /// first, the three were stored and read back across their stores, which stalls the read).
    #[inline(always)]
    pub(crate) fn corners_a(&self, tri: &TriangleRecord) -> (Vec3A, Vec3A, Vec3A) {
        let corner = |k: usize| Vec3A::from(self.positions[tri.vertices[k] as usize]);
        (corner(0), corner(1), corner(2))
    }

    /// Barycentric coordinates of point `p` (on the triangle's plane) in `tri`.
    pub(crate) fn barycentrics(&self, tri: &TriangleRecord, p: Vec3) -> Vec3 {
        let (a, b, c) = self.corners_a(tri);
        barycentrics(a, b, c, p.into()).into()
    }

    /// What `surfaces`' textures are looked up with at barycentrics `b` of `tri`.
    pub(crate) fn texture_context<'a>(
        &self,
        surfaces: &'a Surfaces,
        tri: &TriangleRecord,
        b: Vec3,
    ) -> TextureContext<'a> {
        let [i0, i1, i2] = tri.vertices.map(|i| i as usize);
        // Without UV sets every corner's are zero, and so is their blend (`b` is never negative).
        let uv = if tri.flags & HAS_UV != 0 {
            std::array::from_fn(|s| self.uv[s][i0] * b.x + self.uv[s][i1] * b.y + self.uv[s][i2] * b.z)
        } else {
            [Vec2::ZERO; 2]
        };
        let color = if tri.flags & HAS_COLORS != 0 {
            self.colors[i0] * b.x + self.colors[i1] * b.y + self.colors[i2] * b.z
        } else {
            Vec4::ONE
        };
        surfaces.context(uv, color)
    }

    /// The triangles in `order` (the BVH's): the arrays the scene keeps.
    pub(crate) fn reordered(mut self, order: &[u32]) -> Self {
        self.triangles = order.iter().map(|&i| self.triangles[i as usize]).collect();
        self
    }
}

/// Barycentric coordinates of point `p` (on the triangle's plane) in the triangle `a b c`, each
/// never negative. In `Vec3A`s, whose lanes do the arithmetic of `Vec3`'s components (the same
/// products, sums and order, so the same bits) in fewer instructions.
pub(crate) fn barycentrics(a: Vec3A, b: Vec3A, c: Vec3A, p: Vec3A) -> Vec3A {
    let (e1, e2, ep) = (b - a, c - a, p - a);
    let (d11, d12, d22) = (e1.dot(e1), e1.dot(e2), e2.dot(e2));
    let (dp1, dp2) = (ep.dot(e1), ep.dot(e2));
    let denom = d11 * d22 - d12 * d12;
    if denom <= 0.0 {
        return Vec3A::new(1.0, 0.0, 0.0);
    }
    let v = ((d22 * dp1 - d12 * dp2) / denom).clamp(0.0, 1.0);
    let w = ((d11 * dp2 - d12 * dp1) / denom).clamp(0.0, 1.0 - v);
    Vec3A::new(1.0 - v - w, v, w)
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
fn with_mikktspace_tangents(mesh: MeshData, normal_map: &TextureRef) -> MeshData {
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
        normal_map: &'a TextureRef,
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
