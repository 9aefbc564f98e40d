//! A 2-D "direct lighting" integral with the structure the renderer uses: per vertex one
//! next-event sample (uniform light selection, uniform point in the light's box) and one
//! BSDF sample, combined by the balance heuristic [Hua eq. 16]; CV components = one
//! partition per light + the BSDF (overlapping). Also the relative-variance weighting of
//! high-contrast cells [Hua eq. 25, Fig. 2].

use estimators::cell::{CellAccumulator, ColorMode, ComponentLayout, CvSample, training_weight};
use estimators::solve::{CellCoefficients, SolvePolicy, SolveStatus, solve};
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;

/// Light boxes `[x0, x1] × [y0, y1]` and their RGB emission.
const LIGHTS: [([f64; 4], [f64; 3]); 4] = [
    ([0.1, 0.2, 0.1, 0.3], [4.0, 1.0, 0.5]),
    ([0.5, 0.6, 0.5, 0.7], [0.5, 3.0, 0.5]),
    ([0.7, 0.9, 0.2, 0.25], [1.0, 1.0, 6.0]),
    ([0.3, 0.35, 0.8, 0.95], [2.0, 2.0, 2.0]),
];
const SKY: f64 = 0.05;

fn area(b: &[f64; 4]) -> f64 {
    (b[1] - b[0]) * (b[3] - b[2])
}

fn light_at(x: [f64; 2]) -> Option<usize> {
    LIGHTS
        .iter()
        .position(|(b, _)| x[0] >= b[0] && x[0] < b[1] && x[1] >= b[2] && x[1] < b[3])
}

fn rho(x: [f64; 2]) -> f64 {
    1.0 + x[0]
}

fn f(x: [f64; 2]) -> [f64; 3] {
    let e = light_at(x).map_or([SKY; 3], |i| LIGHTS[i].1);
    e.map(|c| c * rho(x))
}

fn truth() -> [f64; 3] {
    // ∫ρ = 1.5 over the square; ∫_box ρ = area · (1 + centre x).
    let mut t = [SKY * 1.5; 3];
    for (b, e) in LIGHTS {
        let i = area(&b) * (1.0 + 0.5 * (b[0] + b[1]));
        for c in 0..3 {
            t[c] += (e[c] - SKY) * i;
        }
    }
    t
}

fn bsdf_pdf(x: [f64; 2]) -> f64 {
    rho(x) / 1.5
}

/// Mixture density of the vertex: one NEE sample + one BSDF sample (n = 1 each).
fn pdf(x: [f64; 2]) -> (f64, Option<(u32, f64)>, f64) {
    let part = light_at(x).map(|i| (i as u32, 1.0 / area(&LIGHTS[i].0)));
    let q_nee = part.map_or(0.0, |(_, l)| 0.25 * l);
    let pb = bsdf_pdf(x);
    (q_nee + pb, part, pb)
}

fn vertex_samples(rng: &mut Pcg64) -> [[f64; 2]; 2] {
    let i = rng.random_range(0..4);
    let b = LIGHTS[i].0;
    let nee = [
        b[0] + (b[1] - b[0]) * rng.random::<f64>(),
        b[2] + (b[3] - b[2]) * rng.random::<f64>(),
    ];
    let u: f64 = rng.random();
    let bsdf = [-1.0 + (1.0 + 3.0 * u).sqrt(), rng.random()];
    [nee, bsdf]
}

fn train(vertices: usize, seed: u64) -> CellCoefficients {
    let mut rng = Pcg64::seed_from_u64(seed);
    let mut acc = CellAccumulator::new(ComponentLayout::new(4, 1).unwrap(), ColorMode::Rgb);
    for _ in 0..vertices {
        for x in vertex_samples(&mut rng) {
            let (p, part, pb) = pdf(x);
            let lam = [pb];
            acc.add(
                1.0,
                f(x).map(|v| v / p),
                &CvSample {
                    pdf: p,
                    partition: part,
                    overlapping: &lam,
                },
            )
            .unwrap();
        }
    }
    solve(&acc, &SolvePolicy::default())
}

fn estimate(c: &CellCoefficients, vertices: usize, seed: u64) -> Vec<[f64; 3]> {
    let mut rng = Pcg64::seed_from_u64(seed);
    (0..vertices)
        .map(|_| {
            let mut e = c.alpha_sum();
            for x in vertex_samples(&mut rng) {
                let (p, part, pb) = pdf(x);
                let lam = [pb];
                let v = c.apply(
                    f(x).map(|v| v / p),
                    &CvSample {
                        pdf: p,
                        partition: part,
                        overlapping: &lam,
                    },
                );
                for ch in 0..3 {
                    e[ch] += v[ch];
                }
            }
            e
        })
        .collect()
}

fn mean_var(v: &[[f64; 3]]) -> ([f64; 3], [f64; 3]) {
    let n = v.len() as f64;
    let m: [f64; 3] = std::array::from_fn(|c| v.iter().map(|x| x[c]).sum::<f64>() / n);
    let var =
        std::array::from_fn(|c| v.iter().map(|x| (x[c] - m[c]).powi(2)).sum::<f64>() / (n - 1.0));
    (m, var)
}

#[test]
fn many_lights_mis_cv_is_unbiased_and_reduces_variance() {
    let t = truth();
    let seeds = 150;
    let mut means = Vec::new();
    for s in 0..seeds {
        let c = train(128, s);
        assert_eq!(c.diagnostics().status, SolveStatus::Solved);
        means.push(mean_var(&estimate(&c, 256, 10_000 + s)).0);
    }
    let (m, v) = mean_var(&means);
    for ch in 0..3 {
        let se = (v[ch] / seeds as f64).sqrt();
        assert!(
            (m[ch] - t[ch]).abs() < 4.5 * se,
            "channel {ch}: {} vs {} (se {se})",
            m[ch],
            t[ch]
        );
    }
    let c = train(4096, 1);
    let plain = CellCoefficients::plain(c.layout(), ColorMode::Rgb);
    let (_, v_cv) = mean_var(&estimate(&c, 20_000, 2));
    let (_, v_pl) = mean_var(&estimate(&plain, 20_000, 2));
    for ch in 0..3 {
        assert!(
            v_cv[ch] < 0.8 * v_pl[ch],
            "channel {ch}: cv {} plain {}",
            v_cv[ch],
            v_pl[ch]
        );
    }
}

#[test]
fn many_lights_shift_by_effective_counts_keeps_estimates() {
    // Effective counts: NEE picks each light with c = 1/4 (n = 1), the BSDF has n c = 1.
    let c = train(1024, 3);
    let s = -7.25;
    let parts: Vec<(u32, [f64; 3])> = (0..4)
        .map(|i| (i, c.alpha_partition(i).map(|a| a + 0.25 * s)))
        .collect();
    let shifted = CellCoefficients::from_values(
        c.layout(),
        ColorMode::Rgb,
        &parts,
        &[c.alpha_overlapping(0).map(|a| a + s)],
    )
    .unwrap();
    for (a, b) in estimate(&c, 500, 4).iter().zip(&estimate(&shifted, 500, 4)) {
        for ch in 0..3 {
            assert!(
                (a[ch] - b[ch]).abs() < 1e-9 * (1.0 + a[ch].abs()),
                "{a:?} vs {b:?}"
            );
        }
    }
}

/// Two integrals sharing one cell: a bright one (scale 100, mostly linear shape) and a
/// dark one (scale 0.01, mostly constant), sampled by a 50/50 uniform + linear mixture.
fn bright(x: f64) -> f64 {
    100.0 * (0.2 + 2.0 * x)
}
fn dark(x: f64) -> f64 {
    0.01 * (1.0 + 0.1 * x)
}

#[test]
fn high_contrast_cell_relative_weighting_protects_dark_integrals() {
    let truth_b = 100.0 * 1.2;
    let truth_d = 0.01 * 1.05;
    let lam = |x: f64| [1.0, 2.0 * x];
    let draw = |rng: &mut Pcg64| {
        let u: f64 = rng.random();
        if rng.random::<f64>() < 0.5 {
            u
        } else {
            u.sqrt()
        }
    };
    let fit = |relative: bool| {
        let mut rng = Pcg64::seed_from_u64(5);
        let mut acc = CellAccumulator::new(ComponentLayout::new(0, 2).unwrap(), ColorMode::Mono);
        for _ in 0..4000 {
            for (g, t) in [(bright as fn(f64) -> f64, truth_b), (dark, truth_d)] {
                let x = draw(&mut rng);
                let l = lam(x);
                let p = 0.5 * l[0] + 0.5 * l[1];
                // Surrogate = the integral's value (a perfect denoised first pass).
                let w = training_weight(1.0, relative.then_some(t));
                acc.add(
                    w,
                    [g(x) / p; 3],
                    &CvSample {
                        pdf: p,
                        partition: None,
                        overlapping: &l,
                    },
                )
                .unwrap();
            }
        }
        solve(&acc, &SolvePolicy::default())
    };
    let rel_var = |c: &CellCoefficients, g: fn(f64) -> f64, t: f64| {
        let mut rng = Pcg64::seed_from_u64(6);
        let n = 20_000;
        let vals: Vec<f64> = (0..n)
            .map(|_| {
                let x = draw(&mut rng);
                let l = lam(x);
                let p = 0.5 * l[0] + 0.5 * l[1];
                c.alpha_sum()[0]
                    + c.apply(
                        [g(x) / p; 3],
                        &CvSample {
                            pdf: p,
                            partition: None,
                            overlapping: &l,
                        },
                    )[0]
            })
            .collect();
        let m = vals.iter().sum::<f64>() / n as f64;
        vals.iter().map(|v| (v - m).powi(2)).sum::<f64>() / (n as f64 - 1.0) / (t * t)
    };
    let (abs, rel) = (fit(false), fit(true));
    let (ab, ad) = (rel_var(&abs, bright, truth_b), rel_var(&abs, dark, truth_d));
    let (rb, rd) = (rel_var(&rel, bright, truth_b), rel_var(&rel, dark, truth_d));
    assert!(
        rd < 0.5 * ad,
        "dark relative variance: relative fit {rd} vs absolute fit {ad}"
    );
    assert!(
        rb + rd < ab + ad,
        "summed relative variance: {} vs {}",
        rb + rd,
        ab + ad
    );
}
