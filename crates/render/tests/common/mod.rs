//! Scene builders shared by the integration tests of `render` (programmatic scenes, no files).

#![allow(dead_code)]

use glam::{Mat3, Mat4, Vec3, Vec4};
use scene::{Camera, Color, Environment, Film, IntegratorSettings, Material, Mesh, Scene, Sphere};

/// Mitsuba's `lookat`: camera +Z towards `target`, +X = normalize(up × dir) (left).
pub fn look_at(origin: Vec3, target: Vec3, up: Vec3) -> Mat4 {
    let dir = (target - origin).normalize();
    let left = up.cross(dir).normalize();
    let new_up = dir.cross(left);
    Mat4::from_cols(
        left.extend(0.0),
        new_up.extend(0.0),
        dir.extend(0.0),
        Vec4::new(origin.x, origin.y, origin.z, 1.0),
    )
}

/// An empty scene with a camera and film.
pub fn empty_scene(to_world: Mat4, fov_x_deg: f32, width: u32, height: u32) -> Scene {
    Scene {
        camera: Camera {
            to_world,
            fov_x_deg,
            near_clip: 0.01,
            far_clip: 1e4,
        },
        film: Film { width, height },
        integrator: IntegratorSettings {
            max_depth: -1,
            rr_depth: 5,
            hide_emitters: false,
            sample_count: None,
        },
        textures: Vec::new(),
        materials: Vec::new(),
        meshes: Vec::new(),
        spheres: Vec::new(),
        environment: None,
    }
}

/// Adds a material and returns its id.
pub fn add_material(scene: &mut Scene, m: Material) -> u32 {
    scene.materials.push(m);
    (scene.materials.len() - 1) as u32
}

/// A diffuse material of reflectance `rho`, optionally two-sided.
pub fn diffuse(rho: Vec3, two_sided: bool) -> Material {
    let d = Material::Diffuse {
        reflectance: Color::Rgb(rho),
    };
    if two_sided {
        Material::TwoSided(Box::new(d))
    } else {
        d
    }
}

/// A quad `center ± u ± v` with front side along `u × v`, as two triangles.
pub fn quad(center: Vec3, u: Vec3, v: Vec3, material: u32, emitter: Option<Vec3>) -> Mesh {
    Mesh {
        positions: vec![
            center - u - v,
            center + u - v,
            center + u + v,
            center - u + v,
        ],
        normals: None,
        uvs: None,
        indices: vec![[0, 1, 2], [0, 2, 3]],
        material,
        emitter,
    }
}

/// An analytic sphere.
pub fn sphere(center: Vec3, radius: f32, material: u32, emitter: Option<Vec3>) -> Sphere {
    Sphere {
        center,
        radius,
        flip_normals: false,
        frame: Mat3::IDENTITY,
        material,
        emitter,
    }
}

/// Constant environment.
pub fn constant_env(radiance: Vec3) -> Option<Environment> {
    Some(Environment::Constant { radiance })
}

/// A number in `[0, 1)` hashed from `h` (24 bits, exactly representable).
pub fn unit(h: u64) -> f32 {
    (render::sampler::mix64(h) >> 40) as f32 / (1u64 << 24) as f32
}

/// A unit vector hashed from `h` (a point of the cube `[−1, 1]³` away from the centre,
/// normalised).
pub fn unit_vec(h: u64) -> Vec3 {
    let mut h = h;
    loop {
        let v = Vec3::new(unit(h), unit(h ^ 0x55), unit(h ^ 0xaa)) * 2.0 - 1.0;
        if v.length_squared() > 1e-4 {
            return v.normalize();
        }
        h = h.wrapping_add(0x9e37);
    }
}

/// A ray hashed from `r`: origin in the cube `[−extent, extent]³`, direction [`unit_vec`],
/// unbounded.
pub fn random_ray(r: u64, extent: f32) -> render::math::Ray {
    let o = Vec3::new(
        unit(r * 3 + 1_000_000),
        unit(r * 3 + 1_000_001),
        unit(r * 3 + 1_000_002),
    ) * (2.0 * extent)
        - extent;
    render::math::Ray {
        o,
        d: unit_vec(r ^ 0x1234_5678),
        t_max: f32::INFINITY,
    }
}
