//! The 8-wide packet BVH (`AccelKind::Wide`) against obvhs' CWBVH (`AccelKind::Cwbvh`): the
//! same triangle test on both sides, so hits must agree bit for bit; watertightness on shared
//! edges and vertices; any-hit consistent with closest-hit.

mod common;

use common::*;
use glam::{Mat4, Vec3};
use render::accel::{Accel, AccelKind};
use render::math::Ray;

/// A closed, subdivided octahedron (8·4ⁿ triangles sharing exact vertices), radius ~1.
fn octahedron(levels: u32, material: u32) -> scene::Mesh {
    let mut tris: Vec<[Vec3; 3]> = Vec::new();
    let (x, y, z) = (Vec3::X, Vec3::Y, Vec3::Z);
    for sx in [-1.0f32, 1.0] {
        for sy in [-1.0f32, 1.0] {
            for sz in [-1.0f32, 1.0] {
                let (a, b, c) = (x * sx, y * sy, z * sz);
                // Counter-clockwise seen from outside.
                if sx * sy * sz > 0.0 {
                    tris.push([a, b, c]);
                } else {
                    tris.push([a, c, b]);
                }
            }
        }
    }
    for _ in 0..levels {
        let mut next = Vec::new();
        for [a, b, c] in tris {
            let (ab, bc, ca) = ((a + b) * 0.5, (b + c) * 0.5, (c + a) * 0.5);
            next.extend([[a, ab, ca], [ab, b, bc], [ca, bc, c], [ab, bc, ca]]);
        }
        tris = next;
    }
    // Deduplicate vertices (bit-exact) so that neighbours share them.
    let mut positions: Vec<Vec3> = Vec::new();
    let mut indices = Vec::new();
    for t in &tris {
        let idx = t.map(|p| {
            // Push outwards a little (irregular but exact per vertex).
            let p = p * (1.0 + 0.1 * unit(p.x.to_bits() as u64 ^ (p.y.to_bits() as u64) << 20));
            match positions.iter().position(|q| q.to_array() == p.to_array()) {
                Some(i) => i as u32,
                None => {
                    positions.push(p);
                    (positions.len() - 1) as u32
                }
            }
        });
        indices.push(idx);
    }
    scene::Mesh {
        positions,
        normals: None,
        uvs: None,
        indices,
        material,
        emitter: None,
    }
}

/// A scene of random triangles, a closed mesh and two spheres.
fn soup_scene(n: u64) -> scene::Scene {
    let mut s = empty_scene(Mat4::IDENTITY, 45.0, 4, 4);
    let m = add_material(&mut s, diffuse(Vec3::ONE, false));
    let mut positions = Vec::new();
    let mut indices = Vec::new();
    for i in 0..n {
        let c = Vec3::new(unit(i * 7), unit(i * 7 + 1), unit(i * 7 + 2)) * 10.0 - 5.0;
        let base = positions.len() as u32;
        positions.extend([
            c,
            c + unit_vec(i * 7 + 3) * 0.8,
            c + unit_vec(i * 7 + 4) * 0.8,
        ]);
        indices.push([base, base + 1, base + 2]);
    }
    // Two triangles sharing an axis-aligned edge, lying in an axis plane (flat boxes).
    let base = positions.len() as u32;
    positions.extend([
        Vec3::new(-2.0, 4.0, -2.0),
        Vec3::new(2.0, 4.0, -2.0),
        Vec3::new(2.0, 4.0, 2.0),
        Vec3::new(-2.0, 4.0, 2.0),
    ]);
    indices.extend([[base, base + 1, base + 2], [base, base + 2, base + 3]]);
    s.meshes.push(scene::Mesh {
        positions,
        normals: None,
        uvs: None,
        indices,
        material: m,
        emitter: None,
    });
    let mut oct = octahedron(3, m);
    for p in &mut oct.positions {
        *p += Vec3::new(6.0, 0.0, 0.0);
    }
    s.meshes.push(oct);
    s.spheres
        .push(sphere(Vec3::new(1.0, 2.0, 0.5), 0.7, m, None));
    s.spheres
        .push(sphere(Vec3::new(-3.0, -1.0, 2.0), 0.3, m, None));
    s
}

#[test]
fn wide_bvh_hits_equal_cwbvh_hits_bit_for_bit() {
    let s = soup_scene(600);
    let wide = Accel::with_kind(&s, &[], &[], AccelKind::Wide);
    let cw = Accel::with_kind(&s, &[], &[], AccelKind::Cwbvh);
    assert_eq!(wide.kind(), AccelKind::Wide);
    assert_eq!(cw.kind(), AccelKind::Cwbvh);
    let mut hits = 0;
    for r in 0..4000u64 {
        let mut ray = random_ray(r, 8.0);
        // Some rays axis-aligned (zero direction components) and some with a finite t_max.
        if r % 7 == 0 {
            ray.d = [Vec3::X, -Vec3::Y, Vec3::Z, -Vec3::X][(r / 7 % 4) as usize];
        }
        if r % 5 == 0 {
            ray.t_max = 1.0 + 10.0 * unit(r + 77);
        }
        let (a, b) = (wide.intersect(&ray), cw.intersect(&ray));
        match (a, b) {
            (None, None) => {}
            (Some(a), Some(b)) => {
                hits += 1;
                assert_eq!(
                    a.t.to_bits(),
                    b.t.to_bits(),
                    "ray {r}: t {} vs {}",
                    a.t,
                    b.t
                );
                if a.shape == b.shape {
                    assert_eq!(a, b, "ray {r}");
                }
            }
            _ => panic!("ray {r}: wide {a:?} vs cwbvh {b:?}"),
        }
    }
    assert!(hits > 300, "test rays should hit often ({hits})");
}

#[test]
fn wide_bvh_any_hit_agrees_with_closest_hit() {
    let s = soup_scene(300);
    let a = Accel::with_kind(&s, &[], &[], AccelKind::Wide);
    for r in 0..3000u64 {
        let ray = random_ray(r, 8.0);
        let t_max = 0.5 + 20.0 * unit(r + 5);
        let closest = a.intersect(&Ray { t_max, ..ray }).map(|h| h.t);
        assert_eq!(
            a.occluded(ray.o, ray.d, t_max),
            closest.is_some(),
            "ray {r}: closest {closest:?} within {t_max}"
        );
        // Just past / short of the closest hit.
        if let Some(h) = a.intersect(&ray) {
            assert!(a.occluded(ray.o, ray.d, h.t * 1.0001 + 1e-6), "ray {r}");
            let shorter = a.intersect(&Ray { t_max: h.t, ..ray });
            assert!(shorter.is_none_or(|g| g.t < h.t), "ray {r}");
        }
    }
}

#[test]
fn wide_bvh_is_watertight_on_shared_edges_and_vertices() {
    // Rays from inside a closed mesh aimed exactly at its vertices and edge midpoints must hit.
    let mut s = empty_scene(Mat4::IDENTITY, 45.0, 4, 4);
    let m = add_material(&mut s, diffuse(Vec3::ONE, false));
    let oct = octahedron(4, m);
    let targets: Vec<Vec3> = oct
        .indices
        .iter()
        .flat_map(|t| {
            let [a, b, c] = t.map(|i| oct.positions[i as usize]);
            [a, (a + b) * 0.5, (b + c) * 0.5]
        })
        .collect();
    s.meshes.push(oct);
    for kind in [AccelKind::Wide, AccelKind::Cwbvh] {
        let a = Accel::with_kind(&s, &[], &[], kind);
        for (i, &p) in targets.iter().enumerate() {
            for o in [Vec3::ZERO, Vec3::new(0.01, -0.02, 0.015)] {
                let d = (p - o).normalize();
                let hit = a.intersect(&Ray {
                    o,
                    d,
                    t_max: f32::INFINITY,
                });
                assert!(hit.is_some(), "{kind:?}: ray {i} towards {p} leaked");
                assert!(
                    a.occluded(o, d, f32::INFINITY),
                    "{kind:?}: shadow ray {i} leaked"
                );
            }
        }
    }
}

#[test]
fn wide_bvh_handles_single_primitive_and_sphere_only_scenes() {
    let mut s = empty_scene(Mat4::IDENTITY, 45.0, 4, 4);
    let m = add_material(&mut s, diffuse(Vec3::ONE, false));
    s.spheres.push(sphere(Vec3::ZERO, 1.0, m, None));
    let a = Accel::with_kind(&s, &[], &[], AccelKind::Wide);
    let ray = Ray {
        o: Vec3::new(0.0, 0.0, -5.0),
        d: Vec3::Z,
        t_max: f32::INFINITY,
    };
    assert!((a.intersect(&ray).unwrap().t - 4.0).abs() < 1e-6);
    assert!(a.occluded(ray.o, ray.d, 4.5) && !a.occluded(ray.o, ray.d, 3.5));
    s.spheres.clear();
    s.meshes.push(quad(Vec3::ZERO, Vec3::X, Vec3::Y, m, None));
    let a = Accel::with_kind(&s, &[], &[], AccelKind::Wide);
    assert!((a.intersect(&ray).unwrap().t - 5.0).abs() < 1e-6);
    let empty = Accel::with_kind(
        &empty_scene(Mat4::IDENTITY, 45.0, 4, 4),
        &[],
        &[],
        AccelKind::Wide,
    );
    assert!(empty.intersect(&ray).is_none() && !empty.occluded(ray.o, ray.d, 10.0));
}
