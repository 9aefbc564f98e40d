//! Camera rays against Mitsuba 3.9.1's `sensor.sample_ray` on the shared scenes.
//!
//! Values from (scalar_rgb, in `/work/shared/scenes-mitsuba`):
//! ```python
//! s = mi.load_file(name + '/scene.xml'); sen = s.sensors()[0]
//! r, _ = sen.sample_ray(0.0, 0.0, mi.Point2f(x, y), mi.Point2f(0.5, 0.5))  # x, y in [0,1]²
//! ```

#![allow(clippy::excessive_precision)] // Mitsuba printouts kept verbatim.

use std::path::PathBuf;

use glam::{Vec2, Vec3};
use render::camera::Camera;

type Case = (f32, f32, [f32; 3], [f32; 3]);

const CBOX: [Case; 4] = [
    (
        0.0,
        0.0,
        [281.571442, 276.571442, -790.0],
        [0.318789, 0.318789, 0.892607],
    ),
    (
        0.25,
        0.75,
        [279.785706, 271.214294, -790.0],
        [0.173136, -0.173136, 0.969561],
    ),
    (0.5, 0.5, [278.0, 273.0, -790.0], [0.0, 0.0, 1.0]),
    (
        1.0,
        0.3,
        [274.428558, 274.428589, -790.0],
        [-0.333334, 0.133334, 0.933333],
    ),
];

const ROUGHCONDUCTOR: [Case; 4] = [
    (
        0.0,
        0.0,
        [-3.0, 0.305942, 0.305942],
        [0.917779, 0.280787, 0.280787],
    ),
    (
        0.25,
        0.75,
        [-3.0, 0.152971, -0.152971],
        [0.977390, 0.149512, -0.149512],
    ),
    (0.5, 0.5, [-3.0, 0.0, 0.0], [1.0, 0.0, 0.0]),
    (
        1.0,
        0.3,
        [-3.0, -0.305941, 0.122377],
        [0.949767, -0.290573, 0.116229],
    ),
];

fn check(dir: &str, cases: &[Case]) {
    let root = PathBuf::from(std::env::var("SCENES_MITSUBA").unwrap_or_else(|_| {
        concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../../../shared/scenes-mitsuba"
        )
        .into()
    }));
    let s = scene::load_file(&root.join(dir).join("scene.xml"))
        .unwrap_or_else(|e| panic!("{dir}: {e}"))
        .scene;
    let cam = Camera::new(&s.camera, &s.film);
    let scale = s.camera.to_world.w_axis.truncate().length().max(1.0);
    for &(x, y, o, d) in cases {
        let r = cam.ray(Vec2::new(x * s.film.width as f32, y * s.film.height as f32));
        assert!(
            (r.d - Vec3::from(d)).length() < 2e-5,
            "{dir} ({x},{y}): d {} vs Mitsuba {d:?}",
            r.d
        );
        assert!(
            (r.o - Vec3::from(o)).length() < 2e-6 * scale,
            "{dir} ({x},{y}): o {} vs Mitsuba {o:?}",
            r.o
        );
    }
}

#[test]
fn cbox_camera_rays_match_mitsuba_incl_near_clip() {
    check("cbox", &CBOX);
}

#[test]
fn roughconductor_camera_rays_match_mitsuba() {
    check("bsdf-spheres/roughconductor-ggx", &ROUGHCONDUCTOR);
}
