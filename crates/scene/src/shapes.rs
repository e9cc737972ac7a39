//! Procedural meshes for built-in scenes and tests.

use tessera_render::MeshData;
use tessera_render::glam::Vec3;

/// A unit icosphere: an icosahedron subdivided `subdivisions` times, vertices on the unit
/// sphere, with smooth normals. `inward` flips winding and normals to face the centre.
pub fn icosphere(subdivisions: u32, inward: bool) -> MeshData {
    let t = (1.0 + 5f32.sqrt()) / 2.0;
    let mut positions: Vec<Vec3> = [
        (-1.0, t, 0.0),
        (1.0, t, 0.0),
        (-1.0, -t, 0.0),
        (1.0, -t, 0.0),
        (0.0, -1.0, t),
        (0.0, 1.0, t),
        (0.0, -1.0, -t),
        (0.0, 1.0, -t),
        (t, 0.0, -1.0),
        (t, 0.0, 1.0),
        (-t, 0.0, -1.0),
        (-t, 0.0, 1.0),
    ]
    .iter()
    .map(|&(x, y, z)| Vec3::new(x, y, z).normalize())
    .collect();
    let mut faces: Vec<[u32; 3]> = vec![
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ];
    for _ in 0..subdivisions {
        let mut midpoints = std::collections::HashMap::new();
        let mut midpoint = |a: u32, b: u32, positions: &mut Vec<Vec3>| -> u32 {
            *midpoints.entry((a.min(b), a.max(b))).or_insert_with(|| {
                positions.push((positions[a as usize] + positions[b as usize]).normalize());
                (positions.len() - 1) as u32
            })
        };
        let mut next = Vec::with_capacity(faces.len() * 4);
        for [a, b, c] in faces {
            let ab = midpoint(a, b, &mut positions);
            let bc = midpoint(b, c, &mut positions);
            let ca = midpoint(c, a, &mut positions);
            next.extend([[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]);
        }
        faces = next;
    }
    let sign = if inward { -1.0 } else { 1.0 };
    let normals = positions.iter().map(|&p| p * sign).collect();
    let indices = faces.iter().flat_map(|&[a, b, c]| if inward { [a, c, b] } else { [a, b, c] }).collect();
    MeshData { positions, normals: Some(normals), indices, ..Default::default() }
}

/// A quad from four corners in order, as two triangles with face normals.
pub fn quad(corners: [Vec3; 4], material: u32) -> MeshData {
    MeshData { positions: corners.to_vec(), indices: vec![0, 1, 2, 0, 2, 3], material, ..Default::default() }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn icosphere_is_closed_and_outward() {
        let m = icosphere(2, false);
        assert_eq!(m.indices.len() / 3, 20 * 16);
        for tri in m.indices.chunks_exact(3) {
            let [a, b, c] = [tri[0], tri[1], tri[2]].map(|i| m.positions[i as usize]);
            let n = (b - a).cross(c - a);
            assert!(n.dot(a + b + c) > 0.0, "face winding must point outward");
        }
    }
}
