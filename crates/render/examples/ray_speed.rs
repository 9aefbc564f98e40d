//! Closest-hit and any-hit cost per ray in isolation on a scene file, with incoherent rays from
//! points inside the scene bounds (for comparing with the renderer's per-ray cost); process CPU
//! time per ray.
//!
//! `cargo run --release -p render --example ray_speed -- SCENE.json [RAYS]`

use std::path::Path;

use glam::Vec3;
use render::math::Ray;
use render::sampler::mix64;
use render::{RenderScene, RenderSettings};

#[path = "../tests/cpu_time/mod.rs"]
mod cpu_time;
use cpu_time::cpu_seconds;

fn unit(h: u64) -> f32 {
    (mix64(h) >> 40) as f32 / (1u64 << 24) as f32
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let path = args.get(1).expect("usage: ray_speed SCENE.json [RAYS]");
    let n: usize = args
        .get(2)
        .and_then(|a| a.parse().ok())
        .unwrap_or(2_000_000);
    let loaded = scene::load_file(Path::new(path)).expect("scene");
    let st = RenderSettings::from_scene(&loaded.scene);
    let rs = RenderScene::new(&loaded.scene, &st).expect("render scene");
    let (lo, hi) = rs.accel.bounds();
    let rays: Vec<Ray> = (0..n as u64)
        .map(|i| {
            let o = lo + (hi - lo) * Vec3::new(unit(i * 6), unit(i * 6 + 1), unit(i * 6 + 2));
            let mut h = i * 6 + 3;
            let d = loop {
                let v = Vec3::new(unit(h), unit(h ^ 0x55), unit(h ^ 0xaa)) * 2.0 - 1.0;
                if v.length_squared() > 1e-3 {
                    break v.normalize();
                }
                h = mix64(h);
            };
            Ray {
                o,
                d,
                t_max: f32::INFINITY,
            }
        })
        .collect();
    for _ in 0..3 {
        let t = cpu_seconds();
        let hits: Vec<f32> = rays
            .iter()
            .map(|r| rs.accel.intersect(r).map_or(f32::INFINITY, |h| h.t))
            .collect();
        let closest = cpu_seconds() - t;
        let t = cpu_seconds();
        let occ = rays
            .iter()
            .zip(&hits)
            .filter(|(r, h)| rs.accel.occluded(r.o, r.d, (**h).min(1e30) * 0.999))
            .count();
        let any = cpu_seconds() - t;
        println!(
            "{n} rays: closest {:.1} ns/ray (CPU), any-hit (to just short of the closest hit) {:.1} ns/ray ({occ} occluded)",
            closest / n as f64 * 1e9,
            any / n as f64 * 1e9
        );
    }
}
