//! Meshes and accessors: a mesh's primitives turned into triangles with their attributes, and
//! every accessor read with the checks the glTF crate leaves to debug assertions.

use super::materials::Materials;
use super::skins::{Pose, apply_morph_targets, apply_skin};
use crate::SceneInfo;
use tessera_render::glam::{Mat4, Vec2, Vec3, Vec4};
use tessera_render::{MeshData, SceneBuilder};

pub(super) fn add_mesh(
    builder: &mut SceneBuilder,
    mesh: &gltf::Mesh,
    pose: &Pose,
    buffers: &[gltf::buffer::Data],
    materials: Materials,
    info: &mut SceneInfo,
) -> Result<(), String> {
    use gltf::Semantic;
    use gltf::mesh::Mode;
    let name = mesh.name().unwrap_or("").to_string();
    for prim in mesh.primitives() {
        let mode = prim.mode();
        if !matches!(mode, Mode::Triangles | Mode::TriangleStrip | Mode::TriangleFan) {
            info.warnings.push(format!("mesh '{name}': {mode:?} primitive skipped (only triangles render)"));
            continue;
        }
        let Some(positions) = prim.get(&Semantic::Positions) else {
            info.warnings.push(format!("mesh '{name}': primitive without POSITION skipped"));
            continue;
        };
        let attribute = |semantic: Semantic| prim.get(&semantic);
        let mut positions: Vec<Vec3> = read_floats(&positions, buffers)?.into_iter().map(Vec3::from_array).collect();
        let vectors = |semantic| attribute(semantic).map(|a| read_floats::<3>(&a, buffers)).transpose();
        let pairs = |semantic| attribute(semantic).map(|a| read_floats::<2>(&a, buffers)).transpose();
        let n = positions.len() as u32;
        let vertices = match prim.indices() {
            Some(a) => read_indices(&a, buffers)?,
            None => (0..n).collect(),
        };
        let mut normals: Option<Vec<Vec3>> =
            vectors(Semantic::Normals)?.map(|v| v.into_iter().map(Vec3::from_array).collect());
        let mut tangents: Option<Vec<Vec4>> = attribute(Semantic::Tangents)
            .map(|a| read_floats::<4>(&a, buffers))
            .transpose()?
            .map(|v| v.into_iter().map(Vec4::from_array).collect());
        apply_morph_targets(&prim, pose.weights, buffers, &mut positions, &mut normals, &mut tangents)
            .map_err(|e| format!("mesh '{name}': {e}"))?;
        let skinned = match pose.joints {
            Some(joints) => apply_skin(&prim, joints, pose.world, buffers, &mut positions, &mut normals, &mut tangents)
                .map_err(|e| format!("mesh '{name}': {e}"))?,
            None => false,
        };
        let data = MeshData {
            normals,
            uv0: pairs(Semantic::TexCoords(0))?.map(|v| v.into_iter().map(Vec2::from_array).collect()),
            uv1: pairs(Semantic::TexCoords(1))?.map(|v| v.into_iter().map(Vec2::from_array).collect()),
            tangents,
            colors: read_colors(&prim, buffers)?,
            indices: triangle_list(mode, &vertices),
            material: materials.of(&prim, &name)?,
            positions,
        };
        // A skinned primitive is already in world space.
        let transform = if skinned { Mat4::IDENTITY } else { pose.world };
        builder.add_mesh(&name, data, transform).map_err(|e| e.to_string())?;
    }
    Ok(())
}

/// Triangle-list indices of a triangles, strip or fan primitive, by the glTF specification's
/// rules (section 3.7.2.1): strip triangle `i` is `v[i], v[i + 1 + i % 2], v[i + 2 - i % 2]`, which
/// keeps one winding; fan triangle `i` is `v[i + 1], v[i + 2], v[0]`.
pub(super) fn triangle_list(mode: gltf::mesh::Mode, v: &[u32]) -> Vec<u32> {
    use gltf::mesh::Mode;
    let triangles = v.len().saturating_sub(2);
    match mode {
        Mode::TriangleStrip => (0..triangles).flat_map(|i| [v[i], v[i + 1 + i % 2], v[i + 2 - i % 2]]).collect(),
        Mode::TriangleFan => (0..triangles).flat_map(|i| [v[i + 1], v[i + 2], v[0]]).collect(),
        _ => v.to_vec(),
    }
}

/// COLOR_0 as linear RGBA (RGB gets alpha 1), which multiplies the base colour.
pub(super) fn read_colors(prim: &gltf::Primitive, buffers: &[gltf::buffer::Data]) -> Result<Option<Vec<Vec4>>, String> {
    let Some(a) = prim.get(&gltf::Semantic::Colors(0)) else {
        return Ok(None);
    };
    Ok(Some(match a.dimensions() {
        gltf::accessor::Dimensions::Vec3 => {
            read_floats::<3>(&a, buffers)?.into_iter().map(|c| Vec3::from_array(c).extend(1.0)).collect()
        }
        _ => read_floats::<4>(&a, buffers)?.into_iter().map(Vec4::from_array).collect(),
    }))
}

/// An index accessor as `u32`s: unsigned bytes, shorts or ints, not normalised.
pub(super) fn read_indices(a: &gltf::Accessor, buffers: &[gltf::buffer::Data]) -> Result<Vec<u32>, String> {
    use gltf::accessor::DataType;
    let bad = |problem: &str| format!("accessor {} (indices): {problem}", a.index());
    if a.dimensions() != gltf::accessor::Dimensions::Scalar || a.normalized() {
        return Err(bad("indices must be unnormalised scalars"));
    }
    Ok(match a.data_type() {
        DataType::U8 => items::<u8>(a, buffers)?.into_iter().map(u32::from).collect(),
        DataType::U16 => items::<u16>(a, buffers)?.into_iter().map(u32::from).collect(),
        DataType::U32 => items::<u32>(a, buffers)?,
        other => return Err(bad(&format!("component type {other:?} cannot hold indices"))),
    })
}

/// Reads accessor `a` as vectors of `N` floats, whatever its component type: floats as they are,
/// integers as their values, or, when normalised, scaled to `[0, 1]` (unsigned) or `[-1, 1]`
/// (signed) as glTF defines. Core glTF stores some attributes (texture coordinates, colours) as
/// normalised integers; KHR_mesh_quantization allows integers for positions, normals and
/// tangents too.
pub(super) fn read_floats<const N: usize>(
    a: &gltf::Accessor,
    buffers: &[gltf::buffer::Data],
) -> Result<Vec<[f32; N]>, String>
where
    [i8; N]: gltf::accessor::Item,
    [u8; N]: gltf::accessor::Item,
    [i16; N]: gltf::accessor::Item,
    [u16; N]: gltf::accessor::Item,
    [u32; N]: gltf::accessor::Item,
    [f32; N]: gltf::accessor::Item,
{
    use gltf::accessor::DataType;
    if a.dimensions().multiplicity() != N {
        return Err(format!("accessor {}: type {:?} where a {N}-component vector belongs", a.index(), a.dimensions()));
    }
    let norm = a.normalized();
    fn each<T: Copy, const N: usize>(v: Vec<[T; N]>, f: impl Fn(T) -> f32) -> Vec<[f32; N]> {
        v.into_iter().map(|c| c.map(&f)).collect()
    }
    Ok(match a.data_type() {
        DataType::F32 => items::<[f32; N]>(a, buffers)?,
        DataType::U32 if !norm => each(items::<[u32; N]>(a, buffers)?, |c| c as f32),
        DataType::I8 => {
            each(items::<[i8; N]>(a, buffers)?, |c| if norm { (c as f32 / 127.0).max(-1.0) } else { c as f32 })
        }
        DataType::U8 => each(items::<[u8; N]>(a, buffers)?, |c| if norm { c as f32 / 255.0 } else { c as f32 }),
        DataType::I16 => {
            each(items::<[i16; N]>(a, buffers)?, |c| if norm { (c as f32 / 32767.0).max(-1.0) } else { c as f32 })
        }
        DataType::U16 => each(items::<[u16; N]>(a, buffers)?, |c| if norm { c as f32 / 65535.0 } else { c as f32 }),
        DataType::U32 => return Err(format!("accessor {}: normalised unsigned ints are not allowed", a.index())),
    })
}

/// Reads scalar accessor `a` as floats by [`read_floats`]'s rules (morph target weights may be
/// stored as normalised integers).
pub(super) fn read_scalars(a: &gltf::Accessor, buffers: &[gltf::buffer::Data]) -> Result<Vec<f32>, String> {
    use gltf::accessor::DataType;
    if a.dimensions() != gltf::accessor::Dimensions::Scalar {
        return Err(format!("accessor {}: type {:?} where scalars belong", a.index(), a.dimensions()));
    }
    let norm = a.normalized();
    let scale = |c: f32, max: f32| if norm { (c / max).max(-1.0) } else { c };
    Ok(match a.data_type() {
        DataType::F32 => items::<f32>(a, buffers)?,
        DataType::U32 if !norm => items::<u32>(a, buffers)?.into_iter().map(|c| c as f32).collect(),
        DataType::I8 => items::<i8>(a, buffers)?.into_iter().map(|c| scale(c as f32, 127.0)).collect(),
        DataType::U8 => items::<u8>(a, buffers)?.into_iter().map(|c| scale(c as f32, 255.0)).collect(),
        DataType::I16 => items::<i16>(a, buffers)?.into_iter().map(|c| scale(c as f32, 32767.0)).collect(),
        DataType::U16 => items::<u16>(a, buffers)?.into_iter().map(|c| scale(c as f32, 65535.0)).collect(),
        DataType::U32 => return Err(format!("accessor {}: normalised unsigned ints are not allowed", a.index())),
    })
}

/// The most elements an accessor without a buffer view may declare (glTF fills it with zeros).
pub(super) const VIEWLESS_MAX: usize = 1 << 24;

/// All `a.count()` elements of accessor `a`, as the glTF crate reads them (sparse ones
/// included), after the checks that crate leaves to debug assertions: each buffer view's
/// stride must hold an element, and the data must lie inside its buffer.
pub(super) fn items<T: gltf::accessor::Item>(
    a: &gltf::Accessor,
    buffers: &[gltf::buffer::Data],
) -> Result<Vec<T>, String> {
    let size = size_of::<T>();
    let views = a.view().into_iter().chain(a.sparse().map(|s| s.values().view()));
    for view in views {
        if let Some(stride) = view.stride().filter(|&s| s < size) {
            return Err(format!(
                "accessor {}: buffer view {} has byteStride {stride}, less than its {size}-byte elements",
                a.index(),
                view.index()
            ));
        }
    }
    if a.view().is_none() {
        // Zeros (with sparse substitutions): nothing in the file bounds the count, so a limit does.
        if a.count() > VIEWLESS_MAX {
            return Err(format!(
                "accessor {}: {} elements without a buffer view (at most {VIEWLESS_MAX})",
                a.index(),
                a.count()
            ));
        }
        if a.sparse().is_none() {
            return Ok((0..a.count()).map(|_| T::zero()).collect());
        }
    }
    let data = |b: gltf::Buffer| buffers.get(b.index()).map(|d| d.0.as_slice());
    let out: Vec<T> = gltf::accessor::Iter::new(a.clone(), data)
        .ok_or_else(|| format!("accessor {}: its data lies outside its buffer", a.index()))?
        .collect();
    if out.len() != a.count() {
        return Err(format!("accessor {}: {} elements where it declares {}", a.index(), out.len(), a.count()));
    }
    Ok(out)
}
