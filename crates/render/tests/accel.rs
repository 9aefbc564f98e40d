//! BVH intersection: attributes against Mitsuba 3 values, brute-force agreement, occlusion.

mod common;

use common::*;
use glam::{Mat3, Mat4, Vec2, Vec3};
use render::accel::{Accel, ShapeRef};
use render::math::Ray;

#[test]
fn triangle_attributes_match_mitsuba_with_opposite_vertex_normals() {
    // Mitsuba 3.9.1 (scalar_rgb): mesh (0,0,0),(1,0,0),(0,1,0), vertex normals (0,0,-1), ray
    // from (0.2,0.3,1) along -z ⇒ si.n = (0,0,1), sh_frame.n = (0,0,-1), uv = (0.2,0.3).
    let mut s = empty_scene(Mat4::IDENTITY, 45.0, 4, 4);
    let m = add_material(&mut s, diffuse(Vec3::ONE, false));
    s.meshes.push(scene::Mesh {
        positions: vec![Vec3::ZERO, Vec3::X, Vec3::Y],
        normals: Some(vec![-Vec3::Z; 3]),
        uvs: None,
        indices: vec![[0, 1, 2]],
        material: m,
        emitter: None,
    });
    let a = Accel::new(&s, &[], &[]);
    let h = a
        .intersect(&Ray {
            o: Vec3::new(0.2, 0.3, 1.0),
            d: -Vec3::Z,
            t_max: f32::INFINITY,
        })
        .unwrap();
    assert!((h.t - 1.0).abs() < 1e-6);
    assert!((h.ng - Vec3::Z).length() < 1e-6);
    assert!((h.ns + Vec3::Z).length() < 1e-6);
    assert!((h.uv - Vec2::new(0.2, 0.3)).length() < 1e-6);
    assert_eq!(
        h.shape,
        ShapeRef::Mesh {
            mesh: 0,
            triangle: 0
        }
    );
    assert_eq!(h.light, None);
}

#[test]
fn sphere_uv_and_normal_match_mitsuba_in_rotated_frame() {
    // Mitsuba 3.9.1: sphere with to_world rotate([0,0,1], 90), ray (0.3,0.2,5) along -z ⇒
    // p = (0.3, 0.2, 0.932738), uv = (0.843584, 0.117413), n = p.
    let mut s = empty_scene(Mat4::IDENTITY, 45.0, 4, 4);
    let m = add_material(&mut s, diffuse(Vec3::ONE, false));
    let mut sp = sphere(Vec3::ZERO, 1.0, m, None);
    sp.frame = Mat3::from_rotation_z(90f32.to_radians());
    s.spheres.push(sp);
    let a = Accel::new(&s, &[], &[Some(3)]);
    let h = a
        .intersect(&Ray {
            o: Vec3::new(0.3, 0.2, 5.0),
            d: -Vec3::Z,
            t_max: f32::INFINITY,
        })
        .unwrap();
    assert!((h.p - Vec3::new(0.3, 0.2, 0.932738)).length() < 1e-5);
    assert!(
        (h.uv - Vec2::new(0.843584, 0.117413)).length() < 1e-5,
        "{:?}",
        h.uv
    );
    assert!((h.ng - h.p).length() < 1e-5 && h.ns == h.ng);
    assert_eq!(h.light, Some(3));
    assert_eq!(h.shape, ShapeRef::Sphere(0));
    // From inside: the far side, normal still outward (no flip_normals).
    let h = a
        .intersect(&Ray {
            o: Vec3::ZERO,
            d: Vec3::X,
            t_max: f32::INFINITY,
        })
        .unwrap();
    assert!((h.t - 1.0).abs() < 1e-6 && (h.ng - Vec3::X).length() < 1e-6);
}

#[test]
fn bvh_closest_hit_agrees_with_brute_force_on_a_triangle_soup() {
    let mut s = empty_scene(Mat4::IDENTITY, 45.0, 4, 4);
    let m = add_material(&mut s, diffuse(Vec3::ONE, false));
    let mut tris = Vec::new();
    let mut positions = Vec::new();
    for i in 0..2000u64 {
        let c = Vec3::new(unit(i * 7), unit(i * 7 + 1), unit(i * 7 + 2)) * 10.0 - 5.0;
        let e = |k: u64| {
            Vec3::new(
                unit(i * 7 + k),
                unit(i * 7 + k + 10_000),
                unit(i * 7 + k + 20_000),
            ) - 0.5
        };
        let base = positions.len() as u32;
        positions.extend([c, c + e(3), c + e(4)]);
        tris.push([base, base + 1, base + 2]);
    }
    s.meshes.push(scene::Mesh {
        positions: positions.clone(),
        normals: None,
        uvs: None,
        indices: tris.clone(),
        material: m,
        emitter: None,
    });
    s.spheres
        .push(sphere(Vec3::new(1.0, 2.0, 0.5), 0.7, m, None));
    let a = Accel::new(&s, &[], &[]);
    let mut hits = 0;
    for r in 0..500u64 {
        let ray = random_ray(r, 6.0);
        let (o, d) = (ray.o, ray.d);
        // Brute force (ray–plane + inside test in f64).
        let mut best = f64::INFINITY;
        for t in &tris {
            let [p0, p1, p2] = t.map(|i| positions[i as usize].as_dvec3());
            let (o, d) = (o.as_dvec3(), d.as_dvec3());
            let n = (p1 - p0).cross(p2 - p0);
            let den = n.dot(d);
            if den == 0.0 {
                continue;
            }
            let tt = n.dot(p0 - o) / den;
            if tt <= 0.0 {
                continue;
            }
            let p = o + d * tt;
            let inside = n.dot((p1 - p0).cross(p - p0)) >= 0.0
                && n.dot((p2 - p1).cross(p - p1)) >= 0.0
                && n.dot((p0 - p2).cross(p - p2)) >= 0.0;
            if inside {
                best = best.min(tt);
            }
        }
        let (c, rad) = (glam::DVec3::new(1.0, 2.0, 0.5), 0.7);
        let oc = o.as_dvec3() - c;
        let b = oc.dot(d.as_dvec3());
        let disc = b * b - (oc.length_squared() - rad * rad);
        if disc >= 0.0 {
            for tt in [-b - disc.sqrt(), -b + disc.sqrt()] {
                if tt > 0.0 {
                    best = best.min(tt);
                    break;
                }
            }
        }
        let got = a
            .intersect(&ray)
            .map(|h| f64::from(h.t))
            .unwrap_or(f64::INFINITY);
        if best.is_finite() {
            hits += 1;
            assert!(
                (got - best).abs() < 1e-3 * best.max(1.0),
                "ray {r}: bvh {got} vs brute {best}"
            );
            assert!(a.occluded(o, d, (best * 1.01) as f32));
            assert!(!a.occluded(o, d, (best * 0.99) as f32));
        } else {
            assert!(
                got.is_infinite(),
                "ray {r}: bvh hit {got}, brute force missed"
            );
            assert!(!a.occluded(o, d, f32::INFINITY));
        }
    }
    assert!(hits > 100, "test rays should hit often ({hits})");
}

#[test]
fn spawned_rays_do_not_self_intersect_at_millimetre_scale() {
    // The Cornell box is in mm, up to 555 units: offset rays must leave the surface cleanly.
    let mut s = empty_scene(Mat4::IDENTITY, 45.0, 4, 4);
    let m = add_material(&mut s, diffuse(Vec3::ONE, false));
    s.meshes.push(quad(
        Vec3::new(278.0, 0.0, 279.6),
        Vec3::new(0.0, 0.0, 280.0),
        Vec3::new(280.0, 0.0, 0.0),
        m,
        None,
    ));
    let a = Accel::new(&s, &[], &[]);
    for i in 0..200u64 {
        let o = Vec3::new(50.0 + 450.0 * unit(i), 300.0, 50.0 + 450.0 * unit(i + 99));
        let h = a
            .intersect(&Ray {
                o,
                d: -Vec3::Y,
                t_max: f32::INFINITY,
            })
            .unwrap();
        let d = Vec3::new(unit(i + 7) - 0.5, 0.3 + unit(i + 8), unit(i + 9) - 0.5).normalize();
        let up = if h.ng.y > 0.0 {
            d
        } else {
            Vec3::new(d.x, -d.y, d.z)
        };
        assert!(
            a.intersect(&h.spawn_ray(up)).is_none(),
            "self-intersection leaving the floor"
        );
        // And a shadow ray to a point above is unoccluded.
        let r = h.spawn_ray_to(h.p + up * 100.0);
        assert!(!a.occluded(r.o, r.d, r.t_max));
    }
}

#[test]
fn negative_zero_direction_components_still_hit() {
    // Regression: obvhs chose the octant from `d < 0` and the reciprocal sign from
    // `signum(d)`; for −0.0 they disagree and every node test missed.
    let mut s = empty_scene(Mat4::IDENTITY, 45.0, 4, 4);
    let m = add_material(&mut s, diffuse(Vec3::ONE, false));
    s.spheres.push(sphere(Vec3::ZERO, 1.0, m, None));
    let a = Accel::new(&s, &[], &[]);
    let d = Vec3::new(-0.0, -0.0, -1.0);
    assert!(
        a.intersect(&Ray {
            o: Vec3::new(0.3, 0.2, 5.0),
            d,
            t_max: f32::INFINITY
        })
        .is_some()
    );
    assert!(a.occluded(Vec3::new(0.3, 0.2, 5.0), d, 10.0));
}

#[test]
fn the_emitters_structure_finds_the_first_emitter_and_the_full_one_what_blocks_it() {
    // A soup of 600 triangles in three meshes (the middle one emits as light 7) and two
    // spheres (the second emits as light 2). For every ray: the full structure's closest hit
    // is an emitter exactly when the emitters-only structure's hit is unoccluded, and then it
    // is the same shape, point and light.
    let mut s = empty_scene(Mat4::IDENTITY, 45.0, 4, 4);
    let m = add_material(&mut s, diffuse(Vec3::ONE, false));
    for mesh in 0..3u64 {
        let mut positions = Vec::new();
        let mut tris = Vec::new();
        for i in 0..200u64 {
            let k = (mesh * 1000 + i) * 7;
            let c = Vec3::new(unit(k), unit(k + 1), unit(k + 2)) * 10.0 - 5.0;
            let e =
                |j: u64| Vec3::new(unit(k + j), unit(k + j + 50_000), unit(k + j + 90_000)) - 0.5;
            let base = positions.len() as u32;
            positions.extend([c, c + e(3) * 2.0, c + e(4) * 2.0]);
            tris.push([base, base + 1, base + 2]);
        }
        s.meshes.push(scene::Mesh {
            positions,
            normals: None,
            uvs: None,
            indices: tris,
            material: m,
            emitter: None,
        });
    }
    s.spheres
        .push(sphere(Vec3::new(1.0, 2.0, 0.5), 0.7, m, None));
    s.spheres
        .push(sphere(Vec3::new(-2.0, -1.0, 1.0), 0.9, m, None));
    let (mesh_lights, sphere_lights) = ([None, Some(7), None], [None, Some(2)]);
    let full = Accel::new(&s, &mesh_lights, &sphere_lights);
    let emitters = Accel::emitters(&s, &mesh_lights, &sphere_lights);
    assert_eq!(emitters.primitive_count(), 201);
    let (mut reached, mut blocked) = (0, 0);
    for r in 0..2000u64 {
        let ray = random_ray(r ^ 0x00e0_17e2, 6.0);
        let (o, d) = (ray.o, ray.d);
        let first = full.intersect(&ray);
        match emitters.intersect(&ray) {
            None => assert!(
                first.is_none_or(|h| h.light.is_none()),
                "ray {r}: the full structure hits an emitter the emitters' one misses"
            ),
            Some(e) => {
                assert!(
                    e.light.is_some(),
                    "ray {r}: a non-emitter in the emitters' structure"
                );
                let t_block = e.t * (1.0 - 1e-4);
                if full.occluded(o, d, t_block) {
                    blocked += 1;
                    let h = first.unwrap();
                    assert!(h.t < e.t, "ray {r}: blocked behind the emitter");
                } else {
                    reached += 1;
                    let h = first.unwrap();
                    assert_eq!((h.shape, h.light), (e.shape, e.light), "ray {r}");
                    assert!((h.p - e.p).length() < 1e-4, "ray {r}");
                }
            }
        }
    }
    assert!(
        reached > 50 && blocked > 20,
        "reached {reached}, blocked {blocked}"
    );
}
