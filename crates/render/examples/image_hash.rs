//! Bit-level fingerprint of a `path` render, to check that a speed change leaves the image
//! bit-identical: renders a scene file with the settings of `render_speed` (max_depth 5,
//! rr_depth 6, seed 1, box filter, the scene's resolution) and prints an FNV-1a hash of every
//! accumulator bit of the film (sums, squared sums, AOV sums, counts) and the image mean.
//!
//! `cargo run --release -p render --example image_hash -- SCENE.json [SPP] [THREADS] [auto|wide|cwbvh]`
//! (defaults 4 spp, 1 thread, `auto`). The film does not depend on the thread count (DESIGN §3).

use render::{RenderOptions, render_image};

mod common;

/// FNV-1a, 64-bit (offset basis and prime of the reference description by Fowler, Noll, Vo).
fn fnv1a(hash: u64, word: u64) -> u64 {
    word.to_le_bytes().iter().fold(hash, |h, &b| {
        (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3)
    })
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let Some(path) = args.get(1) else {
        eprintln!("usage: image_hash SCENE.json [SPP] [THREADS] [auto|wide|cwbvh]");
        std::process::exit(2);
    };
    let arg = |i: usize, default: u32| {
        args.get(i)
            .and_then(|a| a.parse::<u32>().ok())
            .unwrap_or(default)
    };
    let (spp, threads) = (arg(2, 4), arg(3, 1));
    let kind = common::accel_kind(args.get(4).map(String::as_str));
    let (rs, st) = common::prepare(path, spp, kind);
    let options = RenderOptions {
        tile_size: 32,
        threads: threads as usize,
    };
    let (film, stats) = render_image(&rs, &st, &options, &|_, _| {}).unwrap_or_else(|e| {
        eprintln!("{path}: {e}");
        std::process::exit(1);
    });
    let mut h = 0xcbf2_9ce4_8422_2325u64;
    for p in &film.pixels {
        for v in p
            .sum
            .iter()
            .chain(&p.sum_sq)
            .chain(&p.albedo_sum)
            .chain(&p.normal_sum)
        {
            h = fnv1a(h, v.to_bits());
        }
        h = fnv1a(h, p.count);
    }
    let mean = film.image_mean();
    println!(
        "{path}: {spp} spp, bvh {:?}, rays {}: hash {h:016x}, mean [{:.9}, {:.9}, {:.9}]",
        rs.accel.kind(),
        stats.rays,
        mean[0],
        mean[1],
        mean[2],
    );
}
