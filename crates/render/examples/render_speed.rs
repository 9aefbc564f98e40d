//! Render throughput of the `path` estimator on a scene file, for the speed work of issue #2
//! without building the CLI: same settings as `docs/perf/compare_mitsuba.sh` (max_depth 5,
//! rr_depth 6, seed 1, box filter, the scene's resolution).
//!
//! `cargo run --release -p render --example render_speed -- SCENE.json [SPP] [THREADS] [REPEATS] [BVH]`
//! (defaults 16 spp, 1 thread, 3 repeats, `auto`; BVH is `auto`, `wide` or `cwbvh`). Prints the
//! best of the repeats (wall clock, and process CPU time, which is what to compare on a loaded
//! machine with 1 thread) and the image mean.

use std::time::Instant;

use render::{RenderOptions, render_image};

mod common;

#[path = "../tests/cpu_time/mod.rs"]
mod cpu_time;
use cpu_time::cpu_seconds;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let Some(path) = args.get(1) else {
        eprintln!("usage: render_speed SCENE.json [SPP] [THREADS] [REPEATS] [auto|wide|cwbvh]");
        std::process::exit(2);
    };
    let arg = |i: usize, default: u32| {
        args.get(i)
            .and_then(|a| a.parse::<u32>().ok())
            .unwrap_or(default)
    };
    let (spp, threads, repeats) = (arg(2, 16), arg(3, 1), arg(4, 3).max(1));
    let kind = common::accel_kind(args.get(5).map(String::as_str));
    let (rs, st) = common::prepare(path, spp, kind);
    let options = RenderOptions {
        tile_size: 32,
        threads: threads as usize,
    };
    let mut best = f64::INFINITY;
    let mut best_cpu = f64::INFINITY;
    let mut last = None;
    for _ in 0..repeats {
        let t = Instant::now();
        let cpu = cpu_seconds();
        let (film, stats) = match render_image(&rs, &st, &options, &|_, _| {}) {
            Ok(r) => r,
            Err(e) => {
                eprintln!("{path}: {e}");
                std::process::exit(1);
            }
        };
        best = best.min(t.elapsed().as_secs_f64());
        best_cpu = best_cpu.min(cpu_seconds() - cpu);
        last = Some((film.image_mean(), stats));
    }
    let Some((mean, stats)) = last else { return };
    println!(
        "{path}: {}x{} {spp} spp, {threads} thread(s), bvh {:?}: best {best:.3} s (cpu {best_cpu:.2} s), {:.3} M samples/s, {:.2} M rays/s, {:.3} rays/sample, mean [{:.6}, {:.6}, {:.6}]",
        rs.width,
        rs.height,
        rs.accel.kind(),
        stats.samples as f64 / best / 1e6,
        stats.rays as f64 / best / 1e6,
        stats.rays as f64 / stats.samples.max(1) as f64,
        mean[0],
        mean[1],
        mean[2],
    );
}
