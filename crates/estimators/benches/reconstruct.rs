//! Weighted iterated reconstruction of a 1280×720 image, 100 iterations [Rou §5.3]
//! (the paper reports 16 core-seconds in C++), plus the screened Poisson solvers.
//!
//! `cargo bench -p estimators --bench reconstruct -- --quick`

#![allow(missing_docs)] // criterion_group! generates undocumented items

use criterion::{Criterion, criterion_group, criterion_main};
use estimators::reconstruct::{
    GradientBuffers, PoissonOptions, WeightedOptions, poisson_l2, weighted_iterated,
};
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;
use std::hint::black_box;

fn buffers(w: usize, h: usize) -> [Vec<f32>; 6] {
    let mut rng = Pcg64::seed_from_u64(1);
    let n = w * h;
    let mut r = |k: usize, s: f32| {
        (0..k)
            .map(|_| rng.random::<f32>() * s)
            .collect::<Vec<f32>>()
    };
    [
        r(3 * n, 1.0),
        r(n, 0.1),
        r(3 * n, 0.2),
        r(n, 0.01),
        r(3 * n, 0.2),
        r(n, 0.01),
    ]
}

fn bench(c: &mut Criterion) {
    let (w, h) = (1280, 720);
    let b = buffers(w, h);
    let view = GradientBuffers {
        width: w,
        height: h,
        primal: &b[0],
        primal_var: &b[1],
        dx: &b[2],
        dx_var: &b[3],
        dy: &b[4],
        dy_var: &b[5],
    };
    let mut g = c.benchmark_group("reconstruct_1280x720");
    g.sample_size(10);
    g.bench_function("weighted_iterated_100", |bch| {
        bch.iter(|| {
            weighted_iterated(black_box(&view), &view, &WeightedOptions::default()).unwrap()
        })
    });
    g.bench_function("poisson_l2", |bch| {
        bch.iter(|| poisson_l2(black_box(&view), &PoissonOptions::default()).unwrap())
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
