//! Cell-system benchmarks: dense solve for k = 2..64, Schur solve for P = 10 000 lights,
//! accumulation and merge throughput.
//!
//! `cargo bench -p estimators --bench cells -- --quick`

#![allow(missing_docs)] // criterion_group! generates undocumented items

use criterion::{BenchmarkId, Criterion, Throughput, criterion_group, criterion_main};
use estimators::cell::{CellAccumulator, ColorMode, ComponentLayout, CvSample};
use estimators::solve::{SolvePolicy, solve, solve_dense};
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;
use std::hint::black_box;

fn random_cell(p: u32, k: u32, n: usize, seed: u64) -> CellAccumulator {
    let mut rng = Pcg64::seed_from_u64(seed);
    let mut acc = CellAccumulator::new(ComponentLayout::new(p, k).unwrap(), ColorMode::Rgb);
    let mut lam = vec![0.0; k as usize];
    for i in 0..n {
        for l in lam.iter_mut() {
            *l = rng.random::<f64>() * 3.0;
        }
        // Cycle through the partitions first so that every one is sampled.
        let part = (p > 0).then(|| ((i as u32) % p, rng.random::<f64>() * 5.0 + 0.01));
        let pdf = lam.iter().sum::<f64>() * 0.5 + part.map_or(0.0, |q| q.1) * 0.5 + 0.1;
        let v = [
            rng.random::<f64>(),
            rng.random::<f64>(),
            rng.random::<f64>(),
        ];
        acc.add(
            1.0,
            v,
            &CvSample {
                pdf,
                partition: part,
                overlapping: &lam,
            },
        )
        .unwrap();
    }
    acc
}

fn solves(c: &mut Criterion) {
    let policy = SolvePolicy::default();
    let mut g = c.benchmark_group("solve_dense_k");
    for k in [2u32, 4, 8, 16, 32, 64] {
        let acc = random_cell(0, k, 20 * k as usize, 1);
        g.bench_with_input(BenchmarkId::from_parameter(k), &acc, |b, acc| {
            b.iter(|| solve_dense(black_box(acc), &policy))
        });
    }
    g.finish();
    let mut g = c.benchmark_group("solve_schur_p_k3");
    for p in [100u32, 1000, 10_000] {
        let acc = random_cell(p, 3, 3 * p as usize, 2);
        g.throughput(Throughput::Elements(u64::from(p)));
        g.bench_with_input(BenchmarkId::from_parameter(p), &acc, |b, acc| {
            b.iter(|| solve(black_box(acc), &policy))
        });
    }
    g.finish();
}

/// Weight, value, partition, λ_partition, overlapping λ.
type RawSample = (f64, [f64; 3], u32, f64, [f64; 2]);

fn accumulate_and_merge(c: &mut Criterion) {
    let mut g = c.benchmark_group("accumulate");
    let mut rng = Pcg64::seed_from_u64(3);
    let samples: Vec<RawSample> = (0..4096)
        .map(|_| {
            (
                1.0,
                [rng.random(), rng.random(), rng.random()],
                rng.random_range(0..64),
                rng.random(),
                [rng.random(), rng.random()],
            )
        })
        .collect();
    g.throughput(Throughput::Elements(samples.len() as u64));
    g.bench_function("p64_k2_rgb", |b| {
        b.iter(|| {
            let mut acc =
                CellAccumulator::new(ComponentLayout::new(64, 2).unwrap(), ColorMode::Rgb);
            for (w, v, k, l, lam) in &samples {
                let s = CvSample {
                    pdf: 1.0 + l,
                    partition: Some((*k, *l)),
                    overlapping: lam,
                };
                let _ = acc.add(*w, *v, &s);
            }
            acc
        })
    });
    g.finish();

    let mut g = c.benchmark_group("merge");
    // Typical cells: 16 sampled lights, K = 2; merging 1000 worker accumulators.
    let parts: Vec<CellAccumulator> = (0..1000).map(|s| random_cell(16, 2, 64, s)).collect();
    g.throughput(Throughput::Elements(parts.len() as u64));
    g.bench_function("cells_p16_k2", |b| {
        b.iter(|| {
            let mut acc = CellAccumulator::new(parts[0].layout(), ColorMode::Rgb);
            for p in &parts {
                acc.merge(black_box(p)).unwrap();
            }
            acc
        })
    });
    let bytes: Vec<Vec<u8>> = parts.iter().map(|p| p.encode()).collect();
    g.bench_function("decode_cells_p16_k2", |b| {
        b.iter(|| {
            bytes
                .iter()
                .map(|x| CellAccumulator::decode(black_box(x)).unwrap().samples())
                .sum::<u64>()
        })
    });
    g.finish();
}

fn ocv(c: &mut Criterion) {
    use estimators::ocv::{OcvOptions, ocv_estimate};
    let mut g = c.benchmark_group("ocv_estimate_n64");
    let mut rng = Pcg64::seed_from_u64(4);
    for m in [2usize, 3, 5, 9] {
        let values: Vec<[f64; 3]> = (0..64)
            .map(|_| [rng.random(), rng.random(), rng.random()])
            .collect();
        let pdfs: Vec<f64> = (0..64 * m).map(|_| rng.random::<f64>() + 0.01).collect();
        let mixture = vec![1.0 / m as f64; m];
        g.bench_function(BenchmarkId::from_parameter(m), |b| {
            b.iter(|| {
                ocv_estimate(black_box(&values), &pdfs, &mixture, &OcvOptions::default()).unwrap()
            })
        });
    }
    g.finish();
}

criterion_group!(benches, solves, accumulate_and_merge, ocv);
criterion_main!(benches);
