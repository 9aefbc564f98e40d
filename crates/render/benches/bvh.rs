//! BVH throughput: closest-hit and any-hit rays/s on a procedural ~1M-triangle mesh (a
//! displaced cube-sphere) with incoherent random rays.
//!
//! `cargo bench -p render --bench bvh` (set `BVH_BENCH_RAYS` to change the ray count,
//! `BVH_BENCH_N` the grid size per cube face (default 289: 12·289² ≈ 1M triangles) and
//! `BVH_BENCH_KIND` to `wide` or `cwbvh` to force a BVH; default: the one `Accel::new` picks).
//! Reference point (DESIGN §8): Embree ≈ 1.5 Mrays/s/core incoherent on this CPU; target ≥ 0.6×.

use std::time::Instant;

use glam::{Mat4, Vec3};
use rayon::prelude::*;
use render::accel::{Accel, AccelKind};
use render::math::Ray;
use render::sampler::mix64;

#[path = "../tests/cpu_time/mod.rs"]
mod cpu_time;
use cpu_time::cpu_seconds;

/// Uniform float in [0, 1) from a hash.
fn unit(h: u64) -> f32 {
    (mix64(h) >> 40) as f32 / (1u64 << 24) as f32
}

/// A cube-sphere with `n × n` quads per face (12 n² triangles), displaced radially.
fn displaced_sphere(n: u32) -> scene::Mesh {
    let mut positions = Vec::new();
    let mut indices = Vec::new();
    let faces: [(Vec3, Vec3, Vec3); 6] = [
        (Vec3::X, Vec3::Y, Vec3::Z),
        (-Vec3::X, Vec3::Z, Vec3::Y),
        (Vec3::Y, Vec3::Z, Vec3::X),
        (-Vec3::Y, Vec3::X, Vec3::Z),
        (Vec3::Z, Vec3::X, Vec3::Y),
        (-Vec3::Z, Vec3::Y, Vec3::X),
    ];
    for (normal, u, v) in faces {
        let base = positions.len() as u32;
        for j in 0..=n {
            for i in 0..=n {
                let a = 2.0 * i as f32 / n as f32 - 1.0;
                let b = 2.0 * j as f32 / n as f32 - 1.0;
                let d = (normal + u * a + v * b).normalize();
                let r = 1.0 + 0.05 * (13.0 * d.x).sin() * (17.0 * d.y).sin() * (11.0 * d.z).sin();
                positions.push(d * r);
            }
        }
        let row = n + 1;
        for j in 0..n {
            for i in 0..n {
                let p = base + j * row + i;
                indices.push([p, p + 1, p + row + 1]);
                indices.push([p, p + row + 1, p + row]);
            }
        }
    }
    scene::Mesh {
        positions,
        normals: None,
        uvs: None,
        indices,
        material: 0,
        emitter: None,
    }
}

fn main() {
    let n_rays: usize = std::env::var("BVH_BENCH_RAYS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(2_000_000);
    let grid: u32 = std::env::var("BVH_BENCH_N")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(289);
    let kind = match std::env::var("BVH_BENCH_KIND").as_deref() {
        Ok("wide") => AccelKind::Wide,
        Ok("cwbvh") => AccelKind::Cwbvh,
        _ => AccelKind::Auto,
    };
    let mesh = displaced_sphere(grid);
    let tris = mesh.indices.len();
    let scene = scene::Scene {
        camera: scene::Camera {
            to_world: Mat4::IDENTITY,
            fov_x_deg: 45.0,
            near_clip: 0.01,
            far_clip: 1e4,
        },
        film: scene::Film {
            width: 1,
            height: 1,
        },
        integrator: scene::IntegratorSettings {
            max_depth: -1,
            rr_depth: 5,
            hide_emitters: false,
            sample_count: None,
        },
        textures: Vec::new(),
        materials: vec![scene::Material::Diffuse {
            reflectance: scene::Color::Rgb(Vec3::ONE),
        }],
        meshes: vec![mesh],
        spheres: Vec::new(),
        environment: None,
    };
    let t = Instant::now();
    let accel = Accel::with_kind(&scene, &[], &[], kind);
    let build = t.elapsed().as_secs_f64();
    println!(
        "mesh: {tris} triangles; {:?} BVH build {build:.2} s (single thread)",
        accel.kind()
    );

    // Incoherent rays: origins uniform in the ball of radius 1.5 (inside and outside the
    // surface), directions uniform on the sphere.
    let rays: Vec<Ray> = (0..n_rays as u64)
        .map(|i| {
            let o = loop_point(i);
            let z = 1.0 - 2.0 * unit(i * 4 + 3);
            let phi = 2.0 * std::f32::consts::PI * unit(i * 4 + 4);
            let s = (1.0 - z * z).max(0.0).sqrt();
            Ray {
                o,
                d: Vec3::new(s * phi.cos(), s * phi.sin(), z),
                t_max: f32::INFINITY,
            }
        })
        .collect();

    let (t, c) = (Instant::now(), cpu_seconds());
    let hits = rays.iter().filter(|r| accel.intersect(r).is_some()).count();
    let (secs, cpu) = (t.elapsed().as_secs_f64(), cpu_seconds() - c);
    println!(
        "closest hit, 1 thread: {:.3} Mrays/s wall, {:.3} Mrays/CPU-s ({} rays, {:.1} % hit)",
        n_rays as f64 / secs / 1e6,
        n_rays as f64 / cpu / 1e6,
        n_rays,
        100.0 * hits as f64 / n_rays as f64
    );
    let (t, c) = (Instant::now(), cpu_seconds());
    let occ = rays
        .iter()
        .filter(|r| accel.occluded(r.o, r.d, 10.0))
        .count();
    let (secs, cpu) = (t.elapsed().as_secs_f64(), cpu_seconds() - c);
    println!(
        "any hit, 1 thread: {:.3} Mrays/s wall, {:.3} Mrays/CPU-s ({occ} occluded)",
        n_rays as f64 / secs / 1e6,
        n_rays as f64 / cpu / 1e6
    );

    // All-hit variant: the same directions from inside the surface (every ray hits).
    let inside: Vec<Ray> = rays
        .iter()
        .map(|r| Ray {
            o: r.o * (0.9 / 1.5),
            ..*r
        })
        .collect();
    let (t, c) = (Instant::now(), cpu_seconds());
    let hits_in = inside
        .iter()
        .filter(|r| accel.intersect(r).is_some())
        .count();
    let (secs, cpu) = (t.elapsed().as_secs_f64(), cpu_seconds() - c);
    assert_eq!(hits_in, n_rays, "rays from inside must all hit");
    println!(
        "closest hit from inside (100 % hit), 1 thread: {:.3} Mrays/s wall, {:.3} Mrays/CPU-s",
        n_rays as f64 / secs / 1e6,
        n_rays as f64 / cpu / 1e6
    );

    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .expect("thread pool");
    let t = Instant::now();
    let hits2 = pool.install(|| {
        rays.par_iter()
            .filter(|r| accel.intersect(r).is_some())
            .count()
    });
    let secs = t.elapsed().as_secs_f64();
    assert_eq!(hits, hits2);
    println!(
        "closest hit, {threads} threads: {:.3} Mrays/s ({:.3} Mrays/s/thread)",
        n_rays as f64 / secs / 1e6,
        n_rays as f64 / secs / 1e6 / threads as f64
    );
}

/// A point uniform in the ball of radius 1.5 (rejection sampling on hashed numbers).
fn loop_point(i: u64) -> Vec3 {
    let mut k = 0u64;
    loop {
        let p = Vec3::new(
            unit(i * 4 + k * 7_919_001),
            unit(i * 4 + 1 + k * 7_919_001),
            unit(i * 4 + 2 + k * 7_919_001),
        ) * 2.0
            - 1.0;
        if p.length_squared() <= 1.0 {
            return p * 1.5;
        }
        k += 1;
    }
}
