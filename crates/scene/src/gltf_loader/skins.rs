//! Skins and morph targets: where a mesh instance stands (its node's transform, or its skin's
//! joint matrices) and its morph weights, applied to its vertices.

use super::geometry::{items, read_floats};
use tessera_render::glam::{Mat4, Vec3, Vec4};

/// Where a mesh instance stands in the scene's rest pose: its node's world transform, or, for a
/// skinned mesh, its skin's joint matrices (glTF ignores the mesh node's own transform then), and
/// the morph target weights (the node's, else the mesh's defaults).
pub(super) struct Pose<'a> {
    pub(super) world: Mat4,
    pub(super) joints: Option<&'a [Mat4]>,
    pub(super) weights: &'a [f32],
}

/// The skin's joint matrices in the rest pose: each joint's world transform times its inverse
/// bind matrix (identity when the skin has none). A joint outside the scene's tree stands where
/// its own transform puts it.
pub(super) fn joint_matrices(
    skin: &gltf::Skin,
    worlds: &[Option<Mat4>],
    buffers: &[gltf::buffer::Data],
) -> Result<Vec<Mat4>, String> {
    let inverse_bind: Vec<Mat4> = match skin.inverse_bind_matrices() {
        Some(a) => {
            if a.dimensions() != gltf::accessor::Dimensions::Mat4 || a.data_type() != gltf::accessor::DataType::F32 {
                return Err(format!("skin {}: inverse bind matrices must be float MAT4s", skin.index()));
            }
            items::<[[f32; 4]; 4]>(&a, buffers)?.iter().map(Mat4::from_cols_array_2d).collect()
        }
        None => Vec::new(),
    };
    let joints: Vec<gltf::Node> = skin.joints().collect();
    if !inverse_bind.is_empty() && inverse_bind.len() < joints.len() {
        return Err(format!(
            "skin {}: {} inverse bind matrices for {} joints",
            skin.index(),
            inverse_bind.len(),
            joints.len()
        ));
    }
    Ok(joints
        .iter()
        .enumerate()
        .map(|(k, j)| {
            let world = worlds[j.index()].unwrap_or_else(|| Mat4::from_cols_array_2d(&j.transform().matrix()));
            world * inverse_bind.get(k).copied().unwrap_or(Mat4::IDENTITY)
        })
        .collect())
}

/// Adds the morph targets' displacements, each times its weight, to the attributes they move.
pub(super) fn apply_morph_targets(
    prim: &gltf::Primitive,
    weights: &[f32],
    buffers: &[gltf::buffer::Data],
    positions: &mut [Vec3],
    normals: &mut Option<Vec<Vec3>>,
    tangents: &mut Option<Vec<Vec4>>,
) -> Result<(), String> {
    let n = positions.len();
    for (target, &w) in prim.morph_targets().zip(weights) {
        if w == 0.0 || !w.is_finite() {
            continue;
        }
        let deltas = |a: Option<gltf::Accessor>| -> Result<Option<Vec<Vec3>>, String> {
            let Some(a) = a else { return Ok(None) };
            let d: Vec<Vec3> = read_floats::<3>(&a, buffers)?.into_iter().map(Vec3::from_array).collect();
            if d.len() != n {
                return Err(format!("accessor {}: a morph target of {} vertices for {n}", a.index(), d.len()));
            }
            Ok(Some(d))
        };
        if let Some(d) = deltas(target.positions())? {
            positions.iter_mut().zip(d).for_each(|(p, d)| *p += w * d);
        }
        if let (Some(d), Some(normals)) = (deltas(target.normals())?, normals.as_mut()) {
            normals.iter_mut().zip(d).for_each(|(v, d)| *v += w * d);
        }
        if let (Some(d), Some(tangents)) = (deltas(target.tangents())?, tangents.as_mut()) {
            tangents.iter_mut().zip(d).for_each(|(t, d)| *t += (w * d).extend(0.0));
        }
    }
    Ok(())
}

/// Poses a skinned primitive's vertices in world space by linear blend skinning: each vertex
/// moves by the weighted sum of its joints' matrices (weights normalised to sum 1; a vertex whose
/// weights do not sum to a positive number stays with `unskinned`, its node's transform).
/// Returns false, changing nothing, when the primitive has no JOINTS_0 and WEIGHTS_0.
pub(super) fn apply_skin(
    prim: &gltf::Primitive,
    joints: &[Mat4],
    unskinned: Mat4,
    buffers: &[gltf::buffer::Data],
    positions: &mut [Vec3],
    normals: &mut Option<Vec<Vec3>>,
    tangents: &mut Option<Vec<Vec4>>,
) -> Result<bool, String> {
    use gltf::Semantic;
    let (Some(j), Some(w)) = (prim.get(&Semantic::Joints(0)), prim.get(&Semantic::Weights(0))) else {
        return Ok(false);
    };
    let indices: Vec<[u16; 4]> = match (j.data_type(), j.dimensions()) {
        (gltf::accessor::DataType::U8, gltf::accessor::Dimensions::Vec4) if !j.normalized() => {
            items::<[u8; 4]>(&j, buffers)?.into_iter().map(|v| v.map(u16::from)).collect()
        }
        (gltf::accessor::DataType::U16, gltf::accessor::Dimensions::Vec4) if !j.normalized() => {
            items::<[u16; 4]>(&j, buffers)?
        }
        _ => {
            return Err(format!(
                "accessor {} (JOINTS_0): joints must be unnormalised unsigned byte or short VEC4s",
                j.index()
            ));
        }
    };
    let weights = read_floats::<4>(&w, buffers)?;
    let n = positions.len();
    if indices.len() != n || weights.len() != n {
        return Err(format!("a skin of {} joints and {} weights for {n} vertices", indices.len(), weights.len()));
    }
    let mut matrices = Vec::with_capacity(n);
    for (i, (joint, weight)) in indices.iter().zip(&weights).enumerate() {
        let total: f32 = weight.iter().sum();
        let blended = total > 0.0 && total.is_finite();
        let mut m = if blended { Mat4::ZERO } else { unskinned };
        for (&joint, &w) in joint.iter().zip(weight) {
            let Some(&matrix) = joints.get(joint as usize) else {
                return Err(format!("vertex {i} names joint {joint} of a skin with {}", joints.len()));
            };
            if blended {
                m += matrix * (w / total);
            }
        }
        matrices.push(m);
    }
    // Zipped, not indexed: attributes of the wrong length are SceneBuilder::add_mesh's to refuse.
    for (p, m) in positions.iter_mut().zip(&matrices) {
        *p = m.transform_point3(*p);
    }
    let linear = |m: &Mat4| tessera_render::glam::Mat3::from_mat4(*m);
    for (v, m) in normals.iter_mut().flatten().zip(&matrices) {
        *v = linear(m).inverse().transpose() * *v;
    }
    for (t, m) in tangents.iter_mut().flatten().zip(&matrices) {
        *t = (linear(m) * t.truncate()).extend(t.w);
    }
    Ok(true)
}
