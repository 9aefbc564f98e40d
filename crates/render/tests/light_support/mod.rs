//! Shared helpers of the `light_*` tests: tiny scenes, ray casts that turn a direction into
//! the area-light point it hits, and a "zoom" warp that magnifies a small cone of directions
//! to a hemisphere so that the whole-sphere χ² harness can resolve it.

#![allow(dead_code)] // each test binary uses a subset

use glam::{Mat3, Mat4, Vec3};
use render::light::Lights;
use render::math::Frame;
use scene::{Camera, Environment, Film, IntegratorSettings, Mesh, Scene, Sphere};

/// A scene holding only the given geometry and environment.
pub fn scene(meshes: Vec<Mesh>, spheres: Vec<Sphere>, environment: Option<Environment>) -> Scene {
    Scene {
        camera: Camera {
            to_world: Mat4::IDENTITY,
            fov_x_deg: 45.0,
            near_clip: 0.01,
            far_clip: 1e4,
        },
        film: Film {
            width: 4,
            height: 4,
        },
        integrator: IntegratorSettings {
            max_depth: 2,
            rr_depth: 5,
            hide_emitters: false,
            sample_count: None,
        },
        textures: Vec::new(),
        materials: Vec::new(),
        meshes,
        spheres,
        environment,
    }
}

/// A mesh from positions and CCW triangles.
pub fn mesh(positions: Vec<Vec3>, indices: Vec<[u32; 3]>, emitter: Option<Vec3>) -> Mesh {
    Mesh {
        positions,
        normals: None,
        uvs: None,
        indices,
        material: 0,
        emitter,
    }
}

/// A sphere.
pub fn sphere(center: Vec3, radius: f32, flip_normals: bool, emitter: Option<Vec3>) -> Sphere {
    Sphere {
        center,
        radius,
        flip_normals,
        frame: Mat3::IDENTITY,
        material: 0,
        emitter,
    }
}

/// Direction density of an emitting mesh seen from `p`: the sum of `pdf_area` over every
/// triangle the ray `p + t w` crosses (the sampler ignores occlusion inside the light, so a
/// direction may be produced through several triangles).
pub fn mesh_direction_pdf(lights: &Lights, light: u32, mesh: &Mesh, p: Vec3, w: Vec3) -> f32 {
    let mut pdf = 0.0;
    for idx in &mesh.indices {
        let [a, b, c] = idx.map(|i| mesh.positions[i as usize]);
        if let Some(t) = ray_triangle(p, w, a, b, c) {
            let n = (b - a).cross(c - a).normalize();
            pdf += lights.pdf_area(light, p, p + w * t, n);
        }
    }
    pdf
}

/// Möller–Trumbore, t > 0.
pub fn ray_triangle(o: Vec3, d: Vec3, a: Vec3, b: Vec3, c: Vec3) -> Option<f32> {
    let (e1, e2) = (b - a, c - a);
    let pv = d.cross(e2);
    let det = e1.dot(pv);
    if det.abs() < 1e-12 {
        return None;
    }
    let inv = 1.0 / det;
    let tv = o - a;
    let u = tv.dot(pv) * inv;
    if !(0.0..=1.0).contains(&u) {
        return None;
    }
    let qv = tv.cross(e1);
    let v = d.dot(qv) * inv;
    if v < 0.0 || u + v > 1.0 {
        return None;
    }
    let t = e2.dot(qv) * inv;
    (t > 0.0).then_some(t)
}

/// First hit of `p + t w` (t > 0) with a sphere: (point, oriented normal).
pub fn ray_sphere(p: Vec3, w: Vec3, s: &Sphere) -> Option<(Vec3, Vec3)> {
    let oc = s.center - p;
    let b = oc.dot(w) as f64;
    let c = oc.length_squared() as f64 - (s.radius as f64).powi(2);
    // Rays grazing the silhouette (e.g. a cone sample at θ_max) may round to a slightly
    // negative discriminant: accept them as tangent.
    let disc = b * b - c;
    if disc < -1e-6 * (s.radius as f64).powi(2) {
        return None;
    }
    let disc = disc.max(0.0);
    let sq = disc.sqrt();
    let t = if b - sq > 0.0 { b - sq } else { b + sq };
    if t <= 0.0 {
        return None;
    }
    let y = p + w * t as f32;
    let n = (y - s.center).normalize();
    Some((y, if s.flip_normals { -n } else { n }))
}

/// Direction density of an emitting sphere seen from `p` via its first hit.
pub fn sphere_direction_pdf(lights: &Lights, light: u32, s: &Sphere, p: Vec3, w: Vec3) -> f32 {
    ray_sphere(p, w, s).map_or(0.0, |(y, n)| lights.pdf_area(light, p, y, n))
}

/// Warp magnifying the cone `θ ≤ θ_max` around `axis` onto the hemisphere around `axis`:
/// `1 − cos θ' = s (1 − cos θ)`, `φ' = φ`, with `s = 1 / (1 − cos θ_max)`. Its Jacobian is
/// `dω' = s dω`, so a density transforms as `p'(w') = p(w) / s`.
pub struct Zoom {
    frame: Frame,
    /// Magnification `s`.
    pub s: f32,
}

impl Zoom {
    /// Zoom on the cone of half-angle with the given `1 − cos θ_max` around `axis`.
    pub fn new(axis: Vec3, one_minus_cos_max: f32) -> Self {
        Self {
            frame: Frame::from_normal(axis.normalize()),
            s: 1.0 / one_minus_cos_max,
        }
    }

    /// `w → w'`.
    pub fn forward(&self, w: Vec3) -> Vec3 {
        let l = self.frame.to_local(w);
        let omc = (one_minus_cos(l) * self.s as f64).min(2.0);
        self.rebuild(l, 1.0 - omc)
    }

    /// `w' → w`.
    pub fn inverse(&self, w: Vec3) -> Vec3 {
        let l = self.frame.to_local(w);
        let omc = one_minus_cos(l) / self.s as f64;
        self.rebuild(l, 1.0 - omc)
    }

    fn rebuild(&self, l: Vec3, cos: f64) -> Vec3 {
        let sin_new = (1.0 - cos * cos).max(0.0).sqrt();
        let sin_old = ((l.x as f64).powi(2) + (l.y as f64).powi(2)).sqrt();
        let (x, y) = if sin_old > 0.0 {
            (
                l.x as f64 * sin_new / sin_old,
                l.y as f64 * sin_new / sin_old,
            )
        } else {
            (sin_new, 0.0)
        };
        let v = Vec3::new(x as f32, y as f32, cos as f32).normalize();
        self.frame.to_world(v)
    }
}

/// `1 − cos θ` of a local direction without cancellation near the pole.
fn one_minus_cos(l: Vec3) -> f64 {
    let (x, y, z) = (l.x as f64, l.y as f64, l.z as f64);
    if z > 0.0 {
        (x * x + y * y) / (1.0 + z)
    } else {
        1.0 - z
    }
}
