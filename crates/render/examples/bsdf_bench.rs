//! BSDF throughput: ns per `eval`, `pdf`, `eval_pdf`, `sample` for each kind, and the one-off
//! cost of building a rough plastic's tables. Timing lives here, never in tests.
//!
//! ```text
//! cargo run --release -p render --example bsdf_bench
//! ```

use glam::{Vec2, Vec3};
use render::bsdf::{Bsdf, BsdfKind, RoughPlasticParams};
use render::chi2::Pcg32;
use scene::Distribution::{Beckmann, Ggx};
use std::hint::black_box;
use std::time::Instant;

fn main() {
    let n = 2_000_000;
    let mut rng = Pcg32::new(1, 1);
    let mut hemi = || {
        let z = rng.next_f32().max(1e-3);
        let r = (1.0 - z * z).sqrt();
        let phi = std::f32::consts::TAU * rng.next_f32();
        Vec3::new(r * phi.cos(), r * phi.sin(), z)
    };
    let dirs: Vec<(Vec3, Vec3)> = (0..n).map(|_| (hemi(), hemi())).collect();
    let mut rng = Pcg32::new(2, 2);
    let us: Vec<(f32, Vec2)> = (0..n)
        .map(|_| (rng.next_f32(), Vec2::new(rng.next_f32(), rng.next_f32())))
        .collect();

    let t = Instant::now();
    let params = RoughPlasticParams::new(Ggx, 0.1, 1.5, 0.3, 1.0, false);
    println!(
        "rough plastic tables (GGX): {:.1} ms",
        t.elapsed().as_secs_f64() * 1e3
    );
    let t = Instant::now();
    let _ = black_box(RoughPlasticParams::new(Beckmann, 0.1, 1.5, 0.3, 1.0, false));
    println!(
        "rough plastic tables (Beckmann): {:.1} ms",
        t.elapsed().as_secs_f64() * 1e3
    );

    let eta = Vec3::new(0.2, 0.9, 1.1);
    let k = Vec3::new(3.9, 2.45, 2.14);
    let bsdfs = [
        (
            "diffuse",
            Bsdf::new(BsdfKind::Diffuse {
                reflectance: Vec3::splat(0.5),
            }),
        ),
        (
            "conductor",
            Bsdf::new(BsdfKind::Conductor {
                eta,
                k,
                specular_reflectance: Vec3::ONE,
            }),
        ),
        (
            "roughconductor ggx",
            Bsdf::new(BsdfKind::RoughConductor {
                distribution: Ggx,
                alpha: 0.2,
                eta,
                k,
                specular_reflectance: Vec3::ONE,
            }),
        ),
        (
            "roughconductor beckmann",
            Bsdf::new(BsdfKind::RoughConductor {
                distribution: Beckmann,
                alpha: 0.2,
                eta,
                k,
                specular_reflectance: Vec3::ONE,
            }),
        ),
        (
            "roughplastic ggx",
            Bsdf::new(BsdfKind::RoughPlastic {
                params,
                diffuse_reflectance: Vec3::new(0.2, 0.3, 0.4),
                specular_reflectance: Vec3::ONE,
            }),
        ),
    ];
    println!(
        "{:<26} {:>10} {:>10} {:>10} {:>10}",
        "ns/call", "eval", "pdf", "eval_pdf", "sample"
    );
    for (name, b) in bsdfs {
        let b = black_box(b);
        let time = |f: &dyn Fn(usize) -> f32| {
            let t = Instant::now();
            let mut acc = 0.0f32;
            for i in 0..n {
                acc += f(i);
            }
            black_box(acc);
            t.elapsed().as_secs_f64() * 1e9 / n as f64
        };
        let e = time(&|i| b.eval(dirs[i].0, dirs[i].1).x);
        let p = time(&|i| b.pdf(dirs[i].0, dirs[i].1));
        let ep = time(&|i| {
            let (f, p) = b.eval_pdf(dirs[i].0, dirs[i].1);
            f.x + p
        });
        let s = time(&|i| {
            b.sample(dirs[i].0, us[i].0, us[i].1)
                .map_or(0.0, |s| s.weight.x)
        });
        println!("{name:<26} {e:>10.1} {p:>10.1} {ep:>10.1} {s:>10.1}");
    }
}
