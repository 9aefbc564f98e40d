//! Mesh files and built-in meshes, in object space (before the shape's transform).
//!
//! - [`obj`]: Wavefront OBJ (`v`, `vt`, `vn`, `f` with `v`, `v/t`, `v//n`, `v/t/n` and
//!   negative indices; polygons as fans; `vt` v flipped as Mitsuba does; a vertex is a unique
//!   (position, uv, normal) triple).
//! - [`ply`]: Stanford PLY, ASCII and binary little/big endian; vertex `x y z`, optional
//!   `nx ny nz`, `u v` / `s t` / `texture_u texture_v`; faces as a list property
//!   `vertex_indices` (or `vertex_index`), polygons as fans; other elements/properties skipped.
//! - [`rectangle`], [`cube`]: Mitsuba's `rectangle` and `cube` (same vertices, uvs, winding).

pub mod obj;
pub mod ply;

use glam::{Vec2, Vec3};

/// A triangle mesh as read from a file (object space, nothing validated but index ranges).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RawMesh {
    /// Vertex positions.
    pub positions: Vec<Vec3>,
    /// Per-vertex normals, if the file has them for every vertex.
    pub normals: Option<Vec<Vec3>>,
    /// Per-vertex uvs, if the file has them for every vertex.
    pub uvs: Option<Vec<Vec2>>,
    /// Triangles (indices are `< positions.len()`).
    pub indices: Vec<[u32; 3]>,
}

/// Mitsuba's `rectangle`: [−1,1]² at z = 0, normal +Z, uv = (x, y)·½ + ½.
pub fn rectangle() -> RawMesh {
    let corners = [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)];
    RawMesh {
        positions: corners.iter().map(|&(x, y)| Vec3::new(x, y, 0.0)).collect(),
        normals: Some(vec![Vec3::Z; 4]),
        uvs: Some(
            corners
                .iter()
                .map(|&(x, y)| Vec2::new(0.5 * x + 0.5, 0.5 * y + 0.5))
                .collect(),
        ),
        indices: vec![[0, 1, 2], [2, 3, 0]],
    }
}

/// Mitsuba's `cube`: [−1,1]³ as 24 vertices (4 per face, flat normals, each face's uv the unit
/// square) and 12 outward-facing triangles.
pub fn cube() -> RawMesh {
    // Per face: outward normal and its four corners in Mitsuba's order; every face uses the uv
    // corners (0,1) (1,1) (1,0) (0,0) and the triangles (0,1,2) (3,0,2).
    let faces: [([f32; 3], [[f32; 3]; 4]); 6] = [
        (
            [0.0, -1.0, 0.0],
            [
                [1.0, -1.0, -1.0],
                [1.0, -1.0, 1.0],
                [-1.0, -1.0, 1.0],
                [-1.0, -1.0, -1.0],
            ],
        ),
        (
            [0.0, 1.0, 0.0],
            [
                [1.0, 1.0, -1.0],
                [-1.0, 1.0, -1.0],
                [-1.0, 1.0, 1.0],
                [1.0, 1.0, 1.0],
            ],
        ),
        (
            [1.0, 0.0, 0.0],
            [
                [1.0, -1.0, -1.0],
                [1.0, 1.0, -1.0],
                [1.0, 1.0, 1.0],
                [1.0, -1.0, 1.0],
            ],
        ),
        (
            [0.0, 0.0, 1.0],
            [
                [1.0, -1.0, 1.0],
                [1.0, 1.0, 1.0],
                [-1.0, 1.0, 1.0],
                [-1.0, -1.0, 1.0],
            ],
        ),
        (
            [-1.0, 0.0, 0.0],
            [
                [-1.0, -1.0, 1.0],
                [-1.0, 1.0, 1.0],
                [-1.0, 1.0, -1.0],
                [-1.0, -1.0, -1.0],
            ],
        ),
        (
            [0.0, 0.0, -1.0],
            [
                [1.0, 1.0, -1.0],
                [1.0, -1.0, -1.0],
                [-1.0, -1.0, -1.0],
                [-1.0, 1.0, -1.0],
            ],
        ),
    ];
    let uv = [
        Vec2::new(0.0, 1.0),
        Vec2::new(1.0, 1.0),
        Vec2::new(1.0, 0.0),
        Vec2::new(0.0, 0.0),
    ];
    let mut m = RawMesh {
        normals: Some(Vec::new()),
        uvs: Some(Vec::new()),
        ..Default::default()
    };
    for (f, (n, corners)) in faces.iter().enumerate() {
        let base = 4 * f as u32;
        for (c, p) in corners.iter().enumerate() {
            m.positions.push(Vec3::from(*p));
            if let Some(v) = m.normals.as_mut() {
                v.push(Vec3::from(*n));
            }
            if let Some(v) = m.uvs.as_mut() {
                v.push(uv[c]);
            }
        }
        m.indices.push([base, base + 1, base + 2]);
        m.indices.push([base + 3, base, base + 2]);
    }
    m
}

#[cfg(test)]
mod tests {
    use super::*;

    fn check_outward(m: &RawMesh) {
        let n = m.normals.as_ref().unwrap();
        for t in &m.indices {
            let [a, b, c] = t.map(|i| m.positions[i as usize]);
            let geo = (b - a).cross(c - a).normalize();
            assert!(
                (geo - n[t[0] as usize]).length() < 1e-6,
                "winding vs normal {geo}"
            );
        }
    }

    #[test]
    fn rectangle_faces_plus_z() {
        let m = rectangle();
        check_outward(&m);
        assert_eq!(m.uvs.as_ref().unwrap()[0], Vec2::ZERO);
        assert_eq!(m.uvs.as_ref().unwrap()[2], Vec2::ONE);
    }

    #[test]
    fn cube_has_12_outward_triangles() {
        let m = cube();
        assert_eq!(m.indices.len(), 12);
        assert_eq!(m.positions.len(), 24);
        check_outward(&m);
        for (p, n) in m.positions.iter().zip(m.normals.as_ref().unwrap()) {
            assert_eq!(p.dot(*n), 1.0, "vertex {p} lies on its face plane");
        }
    }
}
