//! Statistical tests of the CV estimator on 1-D integrals with closed-form answers
//! [Hua §3.3, §5], and the hard cases of DESIGN §7.

mod common;

use common::{Pdf, Setup, mean_var, sum3};
use estimators::cell::{
    CellAccumulator, ColorMode, ComponentLayout, CvSample, Technique, training_weight,
};
use estimators::solve::{
    CellCoefficients, CellHalves, FallbackReason, SolvePolicy, SolveStatus, solve, solve_dense,
    value_variance, variance_reduction,
};
use estimators::table::{
    AccumulatorTable, encode_table, predicted_fit_gain, predicted_image_gain, solve_table,
};
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;
use std::collections::BTreeMap;

fn poly(x: f64) -> [f64; 3] {
    [x * x * x + 0.5, 2.0 * x, (std::f64::consts::PI * x).sin()]
}
const POLY_INTEGRAL: [f64; 3] = [0.75, 1.0, 2.0 / std::f64::consts::PI];

fn three_overlapping(f: common::Integrand) -> Setup {
    Setup {
        comps: vec![Pdf::Uniform, Pdf::Linear, Pdf::Quadratic],
        select: vec![0.3, 0.3, 0.4],
        partitioned: false,
        f,
    }
}

fn plain(setup: &Setup) -> CellCoefficients {
    CellCoefficients::plain(setup.layout(), ColorMode::Rgb)
}

#[test]
fn cv_estimate_is_unbiased_over_many_seeds() {
    let setup = three_overlapping(poly);
    let policy = SolvePolicy::default();
    let seeds = 200;
    let mut means = Vec::new();
    for s in 0..seeds {
        // Training and estimation use independent samples, as in the render pass.
        let coeffs = setup.train(64, 1000 + s, ColorMode::Rgb, &policy);
        assert!(!coeffs.is_fallback());
        let (m, _) = mean_var(&setup.estimates(&coeffs, 256, 50_000 + s));
        means.push(m);
    }
    let (grand, var) = mean_var(&means);
    for c in 0..3 {
        let se = (var[c] / seeds as f64).sqrt();
        assert!(
            (grand[c] - POLY_INTEGRAL[c]).abs() < 4.5 * se,
            "channel {c}: {} vs {} (se {se})",
            grand[c],
            POLY_INTEGRAL[c]
        );
    }
}

#[test]
fn cv_variance_is_not_above_plain_mixture() {
    let setup = three_overlapping(poly);
    let coeffs = setup.train(4096, 7, ColorMode::Rgb, &SolvePolicy::default());
    let (m_cv, v_cv) = mean_var(&setup.estimates(&coeffs, 20_000, 8));
    let (m_pl, v_pl) = mean_var(&setup.estimates(&plain(&setup), 20_000, 8));
    for c in 0..3 {
        assert!(
            v_cv[c] <= 1.05 * v_pl[c],
            "channel {c}: cv {} plain {}",
            v_cv[c],
            v_pl[c]
        );
        let se = (v_pl[c] / 20_000.0).sqrt();
        assert!((m_cv[c] - POLY_INTEGRAL[c]).abs() < 5.0 * se);
        assert!((m_pl[c] - POLY_INTEGRAL[c]).abs() < 5.0 * se);
    }
    // With small training sets the estimated α is noisy but still no worse on average.
    let mut worse = 0;
    for s in 0..20 {
        let c = setup.train(32, 100 + s, ColorMode::Rgb, &SolvePolicy::default());
        let (_, v) = mean_var(&setup.estimates(&c, 4000, 900 + s));
        if sum3(v) > 1.1 * sum3(v_pl) {
            worse += 1;
        }
    }
    assert!(
        worse <= 2,
        "{worse} of 20 small-training cells were >10% worse than plain"
    );
}

fn cubic_mono(x: f64) -> [f64; 3] {
    [3.0 * x * x; 3]
}

#[test]
fn owen_zhou_bound_holds_for_best_technique() {
    // f = 3x² with a 50/50 mixture of uniform and 2x. Technique variances σ²_t = ∫f²/p_t − 1:
    // uniform 9/5 − 1 = 0.8, linear 9/8 − 1 = 0.125 → bound min σ²_t / c_t = 0.25.
    let setup = Setup {
        comps: vec![Pdf::Uniform, Pdf::Linear],
        select: vec![0.5, 0.5],
        partitioned: false,
        f: cubic_mono,
    };
    let coeffs = setup.train(8192, 11, ColorMode::Mono, &SolvePolicy::default());
    let n = 40_000;
    let (m, v) = mean_var(&setup.estimates(&coeffs, n, 12));
    let (_, v_pl) = mean_var(&setup.estimates(&plain(&setup), n, 12));
    // Plain mixture: ∫ 9x⁴ / (0.5 + x) dx − 1 (closed form below).
    let ln = (1.5f64 / 0.5).ln();
    let integral = 9.0 * (0.25 - 0.5 / 3.0 + 0.25 / 2.0 - 0.125 + 0.0625 * ln);
    let plain_var = integral - 1.0;
    assert!(
        (v_pl[0] - plain_var).abs() < 0.05 * plain_var,
        "plain {} vs {plain_var}",
        v_pl[0]
    );
    // Sampling error of a variance estimate: about var·sqrt(2/n) for light tails.
    assert!(
        v[0] <= 0.25 * (1.0 + 5.0 * (2.0 / n as f64).sqrt()),
        "cv variance {} above Owen–Zhou bound 0.25",
        v[0]
    );
    assert!(v[0] <= v_pl[0]);
    assert!((m[0] - 1.0).abs() < 5.0 * (v[0] / n as f64).sqrt());
}

fn sine(x: f64) -> [f64; 3] {
    [(2.0 * std::f64::consts::PI * x).sin(); 3]
}

#[test]
fn zero_variance_for_signed_sine_with_positive_negative_partitions() {
    // [Hua Fig. 4]: f = sin 2πx = p₊/π − p₋/π is in the span of the components.
    let setup = Setup {
        comps: vec![Pdf::SinPos, Pdf::SinNeg],
        select: vec![0.5, 0.5],
        partitioned: true,
        f: sine,
    };
    let coeffs = setup.train(256, 3, ColorMode::Rgb, &SolvePolicy::default());
    let (m, v) = mean_var(&setup.estimates(&coeffs, 4000, 4));
    let (_, v_pl) = mean_var(&setup.estimates(&plain(&setup), 4000, 4));
    let expected_plain = (2.0 / std::f64::consts::PI).powi(2);
    assert!(
        (v_pl[0] - expected_plain).abs() < 0.01 * expected_plain,
        "plain mixture variance {}",
        v_pl[0]
    );
    assert!(v[0] < 1e-9 * v_pl[0], "cv variance {}", v[0]);
    assert!(m[0].abs() < 1e-6);
    let a = coeffs.alpha_partition(0)[0];
    assert!((a - 1.0 / std::f64::consts::PI).abs() < 1e-5, "α₊ = {a}");
}

fn colored_bsdf(x: f64) -> [f64; 3] {
    // A coloured, perfectly importance-sampled "sky": f = colour · p_bsdf.
    [0.9 * 2.0 * x, 0.4 * 2.0 * x, 0.1 * 2.0 * x]
}

#[test]
fn zero_variance_restored_for_low_variance_component_rgb_only() {
    // [Hua Fig. 5]: BSDF sampling is perfect, mixing in "guiding" adds variance; an RGB CV
    // restores zero variance, a monochrome one cannot but still helps.
    let setup = Setup {
        comps: vec![Pdf::Linear, Pdf::Box(0.0, 0.5)],
        select: vec![0.5, 0.5],
        partitioned: false,
        f: colored_bsdf,
    };
    let policy = SolvePolicy::default();
    let rgb = setup.train(512, 5, ColorMode::Rgb, &policy);
    let mono = setup.train(512, 5, ColorMode::Mono, &policy);
    let (_, v_rgb) = mean_var(&setup.estimates(&rgb, 4000, 6));
    let (_, v_mono) = mean_var(&setup.estimates(&mono, 4000, 6));
    let (_, v_pl) = mean_var(&setup.estimates(&plain(&setup), 4000, 6));
    assert!(
        sum3(v_rgb) < 1e-9 * sum3(v_pl),
        "rgb {v_rgb:?} plain {v_pl:?}"
    );
    assert!(
        sum3(v_mono) > 1e-3 * sum3(v_pl),
        "mono cannot be exact for a coloured integrand"
    );
    assert!(sum3(v_mono) < sum3(v_pl));
}

fn blue_green(x: f64) -> [f64; 3] {
    // Constant brightness, colour varying from blue to green [Hua Fig. 3].
    let t = x * x;
    [0.0, t, 1.0 - t]
}

#[test]
fn rgb_cv_beats_mono_on_colour_noise() {
    let setup = Setup {
        comps: vec![Pdf::Uniform, Pdf::Linear, Pdf::LinearDown],
        select: vec![0.5, 0.25, 0.25],
        partitioned: false,
        f: blue_green,
    };
    let policy = SolvePolicy::default();
    let rgb = setup.train(2048, 21, ColorMode::Rgb, &policy);
    let mono = setup.train(2048, 21, ColorMode::Mono, &policy);
    let (_, v_rgb) = mean_var(&setup.estimates(&rgb, 20_000, 22));
    let (_, v_mono) = mean_var(&setup.estimates(&mono, 20_000, 22));
    let (_, v_pl) = mean_var(&setup.estimates(&plain(&setup), 20_000, 22));
    assert!(
        sum3(v_rgb) < 0.5 * sum3(v_mono),
        "rgb {} mono {}",
        sum3(v_rgb),
        sum3(v_mono)
    );
    assert!(sum3(v_mono) <= 1.05 * sum3(v_pl));
}

#[test]
fn shifted_coefficients_give_the_same_estimate() {
    // Two MIS techniques with one sample each per vertex: p = q₁ + q₂ (n = 1), λ_i = q_i,
    // n_i c_i = 1. α and α + s (1, 1) give the same vertex estimate [Hua eq. 14].
    let layout = ComponentLayout::new(0, 2).unwrap();
    let a = CellCoefficients::from_values(
        layout,
        ColorMode::Rgb,
        &[],
        &[[0.3, -1.0, 2.0], [0.7, 0.1, 0.0]],
    )
    .unwrap();
    let s = 12.5;
    let b = CellCoefficients::from_values(
        layout,
        ColorMode::Rgb,
        &[],
        &[[0.3 + s, -1.0 + s, 2.0 + s], [0.7 + s, 0.1 + s, s]],
    )
    .unwrap();
    let mut rng = Pcg64::seed_from_u64(1);
    let techniques = [Pdf::Uniform, Pdf::Quadratic];
    for _ in 0..1000 {
        let mut est = [a.alpha_sum(), b.alpha_sum()];
        for t in techniques {
            let x = t.sample(rng.random());
            let l = [techniques[0].pdf(x), techniques[1].pdf(x)];
            let p = l[0] + l[1];
            let f = poly(x).map(|v| v / p);
            let smp = CvSample {
                pdf: p,
                partition: None,
                overlapping: &l,
            };
            for (e, c) in est.iter_mut().zip([&a, &b]) {
                let v = c.apply(f, &smp);
                for ch in 0..3 {
                    e[ch] += v[ch];
                }
            }
        }
        for ch in 0..3 {
            assert!(
                (est[0][ch] - est[1][ch]).abs() < 1e-12 * (1.0 + s.abs() * 4.0),
                "{est:?}"
            );
        }
    }
}

// ----------------------------------------------------------------------------------------
// Schur solver against the dense oracle.

/// A random cell: `p` partitions (light-like, non-overlapping) and `k` overlapping
/// components, every sample picking one partition (or none) and random overlapping λ.
fn random_cell(p: u32, k: u32, n: usize, seed: u64, color: ColorMode) -> CellAccumulator {
    let mut rng = Pcg64::seed_from_u64(seed);
    let mut acc = CellAccumulator::new(ComponentLayout::new(p, k).unwrap(), color);
    let mut lam = vec![0.0; k as usize];
    for _ in 0..n {
        for l in lam.iter_mut() {
            *l = if rng.random::<f64>() < 0.2 {
                0.0
            } else {
                rng.random::<f64>() * 3.0
            };
        }
        let part = (p > 0 && rng.random::<f64>() < 0.9)
            .then(|| (rng.random_range(0..p), rng.random::<f64>() * 5.0 + 0.01));
        let pdf = lam.iter().sum::<f64>() * 0.5 + part.map_or(0.0, |q| q.1) * 0.5 + 0.1;
        let w = rng.random::<f64>() + 0.1;
        let v = [
            rng.random::<f64>(),
            rng.random::<f64>() * 2.0,
            rng.random::<f64>() - 0.5,
        ];
        acc.add(
            w,
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

fn max_rel_diff(a: &CellCoefficients, b: &CellCoefficients, layout: ComponentLayout) -> f64 {
    let mut scale = 0.0f64;
    let mut diff = 0.0f64;
    for id in 0..layout.partitions {
        let (x, y) = (a.alpha_partition(id), b.alpha_partition(id));
        for c in 0..3 {
            scale = scale.max(x[c].abs());
            diff = diff.max((x[c] - y[c]).abs());
        }
    }
    for j in 0..layout.overlapping as usize {
        let (x, y) = (a.alpha_overlapping(j), b.alpha_overlapping(j));
        for c in 0..3 {
            scale = scale.max(x[c].abs());
            diff = diff.max((x[c] - y[c]).abs());
        }
    }
    diff / scale.max(f64::MIN_POSITIVE)
}

#[test]
fn schur_equals_dense_on_random_systems() {
    let policy = SolvePolicy::default();
    for (p, k, n, seed) in [
        (0, 3, 200, 1),
        (5, 0, 200, 2),
        (1, 1, 100, 3),
        (10, 3, 500, 4),
        (200, 3, 5000, 5),
        (1000, 3, 20_000, 6),
        (2000, 3, 40_000, 8),
        (50, 8, 3000, 7),
    ] {
        for color in [ColorMode::Rgb, ColorMode::Mono] {
            let acc = random_cell(p, k, n, seed, color);
            let s = solve(&acc, &policy);
            let d = solve_dense(&acc, &policy);
            assert_eq!(s.diagnostics().status, SolveStatus::Solved);
            assert_eq!(d.diagnostics().status, SolveStatus::Solved);
            let r = max_rel_diff(&s, &d, acc.layout());
            assert!(r < 1e-9, "P={p} K={k}: relative difference {r}");
            let (cs, cd) = (s.diagnostics().condition, d.diagnostics().condition);
            assert!((cs - cd).abs() <= 1e-6 * cd, "condition {cs} vs {cd}");
        }
    }
}

/// The full-size dense oracle: a 10 003² matrix (800 MB, minutes of Cholesky). Run with
/// `cargo nextest run -p estimators --run-ignored only schur_equals_dense_at_ten_thousand`.
#[test]
#[ignore = "800 MB dense oracle, minutes of runtime"]
fn schur_equals_dense_at_ten_thousand_partitions() {
    let policy = SolvePolicy::default();
    let acc = random_cell(10_000, 3, 100_000, 99, ColorMode::Rgb);
    let (s, d) = (solve(&acc, &policy), solve_dense(&acc, &policy));
    assert_eq!(d.diagnostics().status, SolveStatus::Solved);
    let r = max_rel_diff(&s, &d, acc.layout());
    eprintln!("P = 10 000, K = 3: max relative difference {r:e}");
    assert!(r < 1e-9, "relative difference {r}");
}

#[test]
fn schur_solves_ten_thousand_partitions_exactly() {
    // The dense oracle would need a 10 003² matrix; check the residual of the regularised
    // system (A + ridge·diag A) α = b instead, using the accumulator's sparse sums.
    let policy = SolvePolicy::default();
    let (p, k) = (10_000u32, 3u32);
    let acc = random_cell(p, k, 100_000, 99, ColorMode::Rgb);
    let sol = solve(&acc, &policy);
    assert_eq!(sol.diagnostics().status, SolveStatus::Solved);
    assert_eq!(
        sol.diagnostics().active_partitions,
        acc.sampled_partitions()
    );
    let e = 1.0 + policy.ridge;
    let mut worst = 0.0f64;
    for ch in 0..3 {
        let ao: Vec<f64> = (0..k as usize)
            .map(|j| sol.alpha_overlapping(j)[ch])
            .collect();
        let mut ov_res: Vec<f64> = (0..k as usize)
            .map(|i| {
                (0..k as usize)
                    .map(|j| acc.dense(i, j) * ao[j] * if i == j { e } else { 1.0 })
                    .sum::<f64>()
                    - acc.b_overlapping(i)[ch]
            })
            .collect();
        let mut scale = 0.0f64;
        for pm in acc.partitions() {
            let ak = sol.alpha_partition(pm.id)[ch];
            let row = pm.diag * e * ak + pm.cross.iter().zip(&ao).map(|(c, a)| c * a).sum::<f64>()
                - pm.b[ch];
            worst = worst.max(row.abs() / pm.b[ch].abs().max(pm.diag * ak.abs()).max(1e-300));
            for (j, r) in ov_res.iter_mut().enumerate() {
                *r += pm.cross[j] * ak;
            }
            scale = scale.max(pm.b[ch].abs());
        }
        for (i, r) in ov_res.iter().enumerate() {
            worst = worst.max(
                r.abs()
                    / acc.b_overlapping(i)[ch]
                        .abs()
                        .max(acc.dense(i, i) * ao[i].abs()),
            );
        }
    }
    assert!(worst < 1e-9, "relative residual {worst}");
}

// ----------------------------------------------------------------------------------------
// Hard cases (DESIGN §7), one named test each.

#[test]
fn all_zero_component_samples_get_zero_alpha() {
    // Overlapping component 1 is fully occluded: λ₁ = 0 on every sample.
    let mut acc = CellAccumulator::new(ComponentLayout::new(2, 2).unwrap(), ColorMode::Rgb);
    let mut rng = Pcg64::seed_from_u64(4);
    for _ in 0..500 {
        let x: f64 = rng.random();
        let lam = [2.0 * x, 0.0];
        let part = if x < 0.5 { (0, 2.0) } else { (1, 2.0) };
        let pdf = 0.5 * lam[0] + 0.5 * 2.0;
        acc.add(
            1.0,
            [x / pdf; 3],
            &CvSample {
                pdf,
                partition: Some(part),
                overlapping: &lam,
            },
        )
        .unwrap();
    }
    let c = solve(&acc, &SolvePolicy::default());
    assert_eq!(c.diagnostics().status, SolveStatus::Solved);
    assert_eq!(c.diagnostics().active_overlapping, 1);
    assert_eq!(c.alpha_overlapping(1), [0.0; 3]);
    assert!(c.alpha_sum().iter().all(|a| a.is_finite()));
    // And a cell where every λ is zero falls back.
    let mut zero = CellAccumulator::new(ComponentLayout::new(1, 1).unwrap(), ColorMode::Rgb);
    for _ in 0..100 {
        zero.add(
            1.0,
            [0.3; 3],
            &CvSample {
                pdf: 1.0,
                partition: Some((0, 0.0)),
                overlapping: &[0.0],
            },
        )
        .unwrap();
    }
    let c = solve(&zero, &SolvePolicy::default());
    assert_eq!(
        c.diagnostics().status,
        SolveStatus::Fallback(FallbackReason::NoActiveComponents)
    );
    assert_eq!(zero.sampled_partitions(), 0);
}

#[test]
fn duplicate_collinear_components_stay_finite_and_no_worse() {
    // The same pdf listed twice: the system is singular without the ridge.
    let setup = Setup {
        comps: vec![Pdf::Uniform, Pdf::Linear, Pdf::Linear],
        select: vec![0.4, 0.3, 0.3],
        partitioned: false,
        f: poly,
    };
    let coeffs = setup.train(2048, 31, ColorMode::Rgb, &SolvePolicy::default());
    assert_eq!(coeffs.diagnostics().status, SolveStatus::Solved);
    let a1 = coeffs.alpha_overlapping(1);
    let a2 = coeffs.alpha_overlapping(2);
    for c in 0..3 {
        assert!(
            (a1[c] - a2[c]).abs() <= 1e-6 * a1[c].abs().max(1e-3),
            "duplicates share the weight: {a1:?} {a2:?}"
        );
    }
    let (_, v) = mean_var(&setup.estimates(&coeffs, 20_000, 32));
    let (_, v_pl) = mean_var(&setup.estimates(&plain(&setup), 20_000, 32));
    assert!(sum3(v) <= 1.05 * sum3(v_pl));
    // Without regularisation the exact singularity is detected, never NaN.
    let strict = SolvePolicy {
        ridge: 0.0,
        ..SolvePolicy::default()
    };
    let c = setup.train(2048, 31, ColorMode::Rgb, &strict);
    assert!(c.alpha_sum().iter().all(|a| a.is_finite()));
    if let SolveStatus::Fallback(r) = c.diagnostics().status {
        assert!(
            matches!(
                r,
                FallbackReason::IllConditioned | FallbackReason::NotPositiveDefinite
            ),
            "{r:?}"
        );
    }
}

#[test]
fn single_component_reproduces_plain_estimate() {
    // One component equal to the sampling pdf: λ/p = 1, so F − α + α = F exactly.
    let setup = Setup {
        comps: vec![Pdf::Linear],
        select: vec![1.0],
        partitioned: false,
        f: poly,
    };
    let coeffs = setup.train(256, 41, ColorMode::Rgb, &SolvePolicy::default());
    assert_eq!(coeffs.diagnostics().status, SolveStatus::Solved);
    let cv = setup.estimates(&coeffs, 100, 42);
    let pl = setup.estimates(&plain(&setup), 100, 42);
    for (a, b) in cv.iter().zip(&pl) {
        for c in 0..3 {
            assert!((a[c] - b[c]).abs() < 1e-12 * (1.0 + b[c].abs()));
        }
    }
}

#[test]
fn partition_never_sampled_gets_zero_alpha() {
    let setup = Setup {
        comps: vec![Pdf::Box(0.0, 0.5), Pdf::Box(0.5, 1.0)],
        select: vec![1.0, 0.0],
        partitioned: true,
        f: poly,
    };
    // Only partition 0 is ever sampled; partitions 2..5 of the layout do not exist in the data.
    let mut rng = Pcg64::seed_from_u64(51);
    let mut acc = CellAccumulator::new(ComponentLayout::new(6, 1).unwrap(), ColorMode::Rgb);
    for _ in 0..300 {
        let d = setup.draw(&mut rng);
        let lam = [1.0];
        acc.add(
            1.0,
            d.value,
            &CvSample {
                pdf: d.pdf,
                partition: Some((0, d.lambdas[0])),
                overlapping: &lam,
            },
        )
        .unwrap();
    }
    assert_eq!(acc.sampled_partitions(), 1);
    let c = solve(&acc, &SolvePolicy::default());
    assert_eq!(c.diagnostics().status, SolveStatus::Solved);
    for id in 1..6 {
        assert_eq!(c.alpha_partition(id), [0.0; 3]);
    }
    assert!(c.alpha_sum().iter().all(|a| a.is_finite()));
    let d = solve_dense(&acc, &SolvePolicy::default());
    assert!(max_rel_diff(&c, &d, acc.layout()) < 1e-9);
}

#[test]
fn extreme_magnitudes_scale_coefficients_exactly() {
    // Scaling f by s scales α by s; scaling every density by t leaves α unchanged.
    let base = random_cell(20, 3, 3000, 61, ColorMode::Rgb);
    let reference = solve(&base, &SolvePolicy::default());
    for (fs, ps) in [
        (1e-30, 1.0),
        (1e30, 1.0),
        (1.0, 1e-30),
        (1.0, 1e30),
        (1e30, 1e-30),
        (1e-30, 1e30),
    ] {
        let mut rng = Pcg64::seed_from_u64(61);
        let mut acc = CellAccumulator::new(base.layout(), ColorMode::Rgb);
        let mut lam = [0.0; 3];
        for _ in 0..3000 {
            // Same random stream as random_cell, with scaled values and densities.
            for l in lam.iter_mut() {
                *l = if rng.random::<f64>() < 0.2 {
                    0.0
                } else {
                    rng.random::<f64>() * 3.0
                };
            }
            let part = (rng.random::<f64>() < 0.9)
                .then(|| (rng.random_range(0..20u32), rng.random::<f64>() * 5.0 + 0.01));
            let pdf = lam.iter().sum::<f64>() * 0.5 + part.map_or(0.0, |q| q.1) * 0.5 + 0.1;
            let w = rng.random::<f64>() + 0.1;
            let v = [
                rng.random::<f64>(),
                rng.random::<f64>() * 2.0,
                rng.random::<f64>() - 0.5,
            ];
            let lam_s = lam.map(|l| l * ps);
            let smp = CvSample {
                pdf: pdf * ps,
                partition: part.map(|(k, l)| (k, l * ps)),
                overlapping: &lam_s,
            };
            acc.add(w, v.map(|x| x * fs), &smp).unwrap();
        }
        let c = solve(&acc, &SolvePolicy::default());
        assert_eq!(c.diagnostics().status, SolveStatus::Solved, "f×{fs} p×{ps}");
        for id in 0..20 {
            let (a, r) = (c.alpha_partition(id), reference.alpha_partition(id));
            for ch in 0..3 {
                assert!(
                    (a[ch] / fs - r[ch]).abs() <= 1e-9 * r[ch].abs().max(1e-6),
                    "f×{fs} p×{ps}: {} vs {}",
                    a[ch] / fs,
                    r[ch]
                );
            }
        }
    }
}

#[test]
fn nan_and_inf_samples_are_rejected_counted_and_never_merged() {
    let layout = ComponentLayout::new(3, 2).unwrap();
    let mut clean = CellAccumulator::new(layout, ColorMode::Rgb);
    let mut dirty = CellAccumulator::new(layout, ColorMode::Rgb);
    let good = CvSample {
        pdf: 2.0,
        partition: Some((1, 1.5)),
        overlapping: &[0.5, 1.0],
    };
    clean.add(1.0, [1.0, 2.0, 3.0], &good).unwrap();
    dirty.add(1.0, [1.0, 2.0, 3.0], &good).unwrap();
    let nan = f64::NAN;
    let inf = f64::INFINITY;
    let nan_lam = [nan, 1.0];
    let bad: Vec<(f64, [f64; 3], CvSample<'_>)> = vec![
        (1.0, [nan, 0.0, 0.0], good),
        (1.0, [0.0, inf, 0.0], good),
        (nan, [1.0; 3], good),
        (inf, [1.0; 3], good),
        (-1.0, [1.0; 3], good),
        (1.0, [1.0; 3], CvSample { pdf: nan, ..good }),
        (1.0, [1.0; 3], CvSample { pdf: 0.0, ..good }),
        (1.0, [1.0; 3], CvSample { pdf: -1.0, ..good }),
        (
            1.0,
            [1.0; 3],
            CvSample {
                partition: Some((1, nan)),
                ..good
            },
        ),
        (
            1.0,
            [1.0; 3],
            CvSample {
                partition: Some((1, inf)),
                ..good
            },
        ),
        (
            1.0,
            [1.0; 3],
            CvSample {
                partition: Some((3, 1.0)),
                ..good
            },
        ),
        (
            1.0,
            [1.0; 3],
            CvSample {
                overlapping: &nan_lam,
                ..good
            },
        ),
        (
            1.0,
            [1.0; 3],
            CvSample {
                overlapping: &[1.0],
                ..good
            },
        ),
        // Finite inputs whose products overflow.
        (
            1e300,
            [1e300; 3],
            CvSample {
                pdf: 1e-300,
                ..good
            },
        ),
    ];
    for (i, (w, v, s)) in bad.iter().enumerate() {
        assert!(dirty.add(*w, *v, s).is_err(), "bad sample {i} accepted");
    }
    assert_eq!(dirty.rejected(), bad.len() as u64);
    assert_eq!(dirty.samples(), 1);
    // Identical sums: the encodings differ only in the rejected counter.
    let mut dirty_enc = dirty.encode();
    let clean_enc = clean.encode();
    let rejected_at = 4 + 2 + 1 + 1 + 4 + 4 + 8;
    dirty_enc[rejected_at..rejected_at + 8].copy_from_slice(&0u64.to_le_bytes());
    assert_eq!(dirty_enc, clean_enc);
    // f32 entry point rejects too.
    assert!(
        dirty
            .add_f32(1.0, [f32::NAN, 0.0, 0.0], 1.0, None, &[1.0, 1.0])
            .is_err()
    );
    assert!(dirty.add_f32(1.0, [0.0; 3], 1.0, None, &[1.0; 65]).is_err());
}

#[test]
fn zero_surrogate_gives_finite_weights() {
    assert_eq!(training_weight(2.0, None), 4.0);
    assert!((training_weight(1.0, Some(0.0)) - 1e4).abs() < 1e-8);
    assert!((training_weight(1.0, Some(1.0)) - 1.0 / 1.0201).abs() < 1e-12);
    for s in [f64::NAN, -3.0, f64::INFINITY, f64::NEG_INFINITY] {
        let w = training_weight(0.5, Some(s));
        assert!(w.is_finite() && w >= 0.0, "surrogate {s} → {w}");
    }
    // A relative-variance cell whose surrogate is black still solves to finite α.
    let setup = three_overlapping(poly);
    let mut rng = Pcg64::seed_from_u64(71);
    let mut acc = CellAccumulator::new(setup.layout(), ColorMode::Rgb);
    for i in 0..500 {
        let d = setup.draw(&mut rng);
        let surrogate = if i % 2 == 0 { 0.0 } else { 0.7 };
        acc.add(
            training_weight(1.0, Some(surrogate)),
            d.value,
            &setup.sample_view(&d),
        )
        .unwrap();
    }
    let c = solve(&acc, &SolvePolicy::default());
    assert_eq!(c.diagnostics().status, SolveStatus::Solved);
    assert!(c.alpha_sum().iter().all(|a| a.is_finite()));
}

#[test]
fn empty_cell_falls_back_to_plain_estimator() {
    let acc = CellAccumulator::new(ComponentLayout::new(4, 2).unwrap(), ColorMode::Rgb);
    for c in [
        solve(&acc, &SolvePolicy::default()),
        solve_dense(&acc, &SolvePolicy::default()),
    ] {
        assert_eq!(
            c.diagnostics().status,
            SolveStatus::Fallback(FallbackReason::Empty)
        );
        assert_eq!(c.alpha_sum(), [0.0; 3]);
        let s = CvSample {
            pdf: 1.0,
            partition: Some((2, 3.0)),
            overlapping: &[1.0, 2.0],
        };
        assert_eq!(c.apply([0.5, 0.25, 1.0], &s), [0.5, 0.25, 1.0]);
    }
}

#[test]
fn too_few_samples_fall_back() {
    let setup = three_overlapping(poly);
    let c = setup.train(10, 1, ColorMode::Rgb, &SolvePolicy::default());
    assert_eq!(
        c.diagnostics().status,
        SolveStatus::Fallback(FallbackReason::TooFewSamples)
    );
    // One huge weight dominates: effective sample count ≈ 1.
    let mut rng = Pcg64::seed_from_u64(2);
    let mut acc = CellAccumulator::new(setup.layout(), ColorMode::Rgb);
    for i in 0..100 {
        let d = setup.draw(&mut rng);
        acc.add(
            if i == 0 { 1e12 } else { 1.0 },
            d.value,
            &setup.sample_view(&d),
        )
        .unwrap();
    }
    assert!(acc.effective_samples() < 1.01);
    let c = solve(&acc, &SolvePolicy::default());
    assert_eq!(
        c.diagnostics().status,
        SolveStatus::Fallback(FallbackReason::TooFewEffectiveSamples)
    );
}

#[test]
fn f32_inputs_are_accumulated_in_f64() {
    let layout = ComponentLayout::new(1, 1).unwrap();
    let mut acc = CellAccumulator::new(layout, ColorMode::Mono);
    let n = 1_000_000;
    let mut f32_sum = 0.0f32;
    for _ in 0..n {
        acc.add_f32(1.0, [0.1, 0.1, 0.1], 1.0, Some((0, 1.0)), &[1.0])
            .unwrap();
        f32_sum += 0.1f32;
    }
    let exact = f64::from(0.1f32) * f64::from(n);
    let b = acc.b_overlapping(0)[0];
    assert!(
        (b - exact).abs() < 1e-9 * exact,
        "f64 accumulation {b} vs {exact}"
    );
    // The same sum in f32 drifts by far more: the reason to accumulate in f64.
    assert!((f64::from(f32_sum) - exact).abs() > 1e-3 * exact);
    assert_eq!(acc.partition(0).unwrap().count, n as u64);
}

fn spiky(x: f64) -> [f64; 3] {
    // A narrow bright feature the mixture samples poorly: noisy training, noisy α.
    let bump = if (0.80..0.82).contains(&x) { 40.0 } else { 0.0 };
    [0.2 + bump, 0.1 + x, 0.3]
}

#[test]
fn negative_cv_outliers_stay_finite_and_unbiased() {
    // Minimal training (16 samples) gives noisy coefficients; individual controlled samples
    // can then go negative for a non-negative integrand [Hua §7.3.2]. They must stay finite
    // and the estimator unbiased (no clamping, which would bias it).
    let setup = Setup {
        comps: vec![Pdf::Uniform, Pdf::Linear, Pdf::Box(0.0, 0.5)],
        select: vec![0.4, 0.3, 0.3],
        partitioned: false,
        f: spiky,
    };
    let truth = [0.2 + 40.0 * 0.02, 0.6, 0.3];
    let seeds = 300;
    let (mut means, mut negatives) = (Vec::new(), 0usize);
    for s in 0..seeds {
        let c = setup.train(16, 7000 + s, ColorMode::Rgb, &SolvePolicy::default());
        let est = setup.estimates(&c, 200, 90_000 + s);
        negatives += est.iter().filter(|e| e[0] < 0.0).count();
        assert!(est.iter().flatten().all(|v| v.is_finite()));
        means.push(mean_var(&est).0);
    }
    assert!(negatives > 0, "the test should exercise negative outliers");
    let (m, v) = mean_var(&means);
    for c in 0..3 {
        let se = (v[c] / seeds as f64).sqrt();
        assert!(
            (m[c] - truth[c]).abs() < 4.5 * se,
            "channel {c}: {} vs {} (se {se})",
            m[c],
            truth[c]
        );
    }
}

// ----------------------------------------------------------------------------------------
// Variance reduction, the predicted image gain and the `LowImageGain` fallback.

/// One recorded sample of a random cell: weight, value, pdf, partition, overlapping λ.
type Recorded = (f64, [f64; 3], f64, Option<(u32, f64)>, Vec<f64>);

/// A random cell with every sample kept, as the renderer's are: the density is the mixture
/// `p = ½ Σ_j λ_j + ½ λ_partition` of the components (so a constant is a combination of
/// the ratios `λ/p`), the first overlapping λ never zero; the values correlated with the
/// ratios by `slope` (0: pure noise).
fn recorded_cell(p: u32, k: u32, n: usize, seed: u64, slope: f64) -> Vec<Recorded> {
    let mut rng = Pcg64::seed_from_u64(seed);
    (0..n)
        .map(|_| {
            let lam: Vec<f64> = (0..k)
                .map(|j| {
                    if j > 0 && rng.random::<f64>() < 0.2 {
                        0.0
                    } else {
                        rng.random::<f64>() * 3.0 + 0.05
                    }
                })
                .collect();
            let part = (p > 0 && (k == 0 || rng.random::<f64>() < 0.9))
                .then(|| (rng.random_range(0..p), rng.random::<f64>() * 5.0 + 0.01));
            let pdf = lam.iter().sum::<f64>() * 0.5 + part.map_or(0.0, |q| q.1) * 0.5;
            let g = (lam.first().copied().unwrap_or(0.0) + part.map_or(0.0, |q| q.1)) / pdf;
            let w = rng.random::<f64>() + 0.1;
            let v = [
                rng.random::<f64>() + slope * g,
                rng.random::<f64>() * 2.0 - slope * g,
                rng.random::<f64>() - 0.5,
            ];
            (w, v, pdf, part, lam)
        })
        .collect()
}

/// The technique of recorded sample `i`: NEE and BSDF samples alternate, as a vertex
/// records them.
fn technique_of(i: usize) -> Technique {
    if i.is_multiple_of(2) {
        Technique::Light
    } else {
        Technique::Bsdf
    }
}

fn accumulate(samples: &[Recorded], p: u32, k: u32, color: ColorMode) -> CellAccumulator {
    let mut acc = CellAccumulator::new(ComponentLayout::new(p, k).unwrap(), color);
    for (i, (w, v, pdf, part, lam)) in samples.iter().enumerate() {
        let s = CvSample {
            pdf: *pdf,
            partition: *part,
            overlapping: lam,
        };
        acc.add_from(technique_of(i), *w, *v, &s).unwrap();
    }
    acc
}

/// Weighted sum of squares of `x` about each technique's own weighted mean ([`technique_of`]
/// the index), the variance of a one-sample-per-technique estimator.
fn within_technique_ss(w: &[f64], x: &[f64]) -> f64 {
    let mut ss = 0.0;
    for t in [Technique::Light, Technique::Bsdf] {
        let idx: Vec<usize> = (0..w.len()).filter(|&i| technique_of(i) == t).collect();
        let sw: f64 = idx.iter().map(|&i| w[i]).sum();
        let mean = idx.iter().map(|&i| w[i] * x[i]).sum::<f64>() / sw;
        ss += idx
            .iter()
            .map(|&i| w[i] * (x[i] - mean).powi(2))
            .sum::<f64>();
    }
    ss
}

#[test]
fn variance_reduction_equals_its_definition_on_the_samples() {
    for (p, k, color, ridge, slope, offset, seed) in [
        (6, 2, ColorMode::Rgb, 0.0, 1.0, 0.0, 1),
        (6, 2, ColorMode::Rgb, 1.0, 0.3, 2.0, 2),
        (0, 3, ColorMode::Mono, 1e-6, 2.0, -1.0, 3),
        (9, 0, ColorMode::Rgb, 0.5, 0.0, 5.0, 4),
        (4, 1, ColorMode::Mono, 1.0, 1.0, 0.5, 5),
    ] {
        let mut samples = recorded_cell(p, k, 300, seed, slope);
        // The light technique's values sit `offset` above the BSDF's: a spread between the
        // techniques that is no variance of the estimator.
        for (i, s) in samples.iter_mut().enumerate() {
            if technique_of(i) == Technique::Light {
                s.1 = s.1.map(|v| v + offset);
            }
        }
        let acc = accumulate(&samples, p, k, color);
        let policy = SolvePolicy {
            ridge,
            ..SolvePolicy::default()
        };
        for co in [solve(&acc, &policy), solve_dense(&acc, &policy)] {
            assert!(!co.is_fallback());
            // Brute force: the plain values' weighted sum of squares about their technique's
            // weighted mean minus the controlled values' about theirs, channel by channel.
            let c = color.channels();
            let w: Vec<f64> = samples.iter().map(|s| s.0).collect();
            let (mut want, mut scale) = (0.0, 0.0);
            for ch in 0..c {
                let y = |v: &[f64; 3]| match color {
                    ColorMode::Rgb => v[ch],
                    ColorMode::Mono => (v[0] + v[1] + v[2]) / 3.0,
                };
                let plain: Vec<f64> = samples.iter().map(|s| y(&s.1)).collect();
                let controlled: Vec<f64> = samples
                    .iter()
                    .map(|(_, v, pdf, part, lam)| {
                        y(v) - co.cv_term(&CvSample {
                            pdf: *pdf,
                            partition: *part,
                            overlapping: lam,
                        })[if c == 1 { 0 } else { ch }]
                    })
                    .collect();
                let r0 = within_technique_ss(&w, &plain);
                want += r0 - within_technique_ss(&w, &controlled);
                scale += r0;
            }
            let got = variance_reduction(&acc, &co);
            assert!(
                (got - want).abs() < 1e-9 * scale,
                "p {p} k {k} slope {slope}: {got} vs {want}"
            );
            // The plain values' sum of squares is the cell's value variance.
            let v = value_variance(&acc);
            assert!((v - scale).abs() < 1e-9 * scale, "{v} vs {scale}");
            // A correlated cell loses variance (in RGB: the slope cancels in the channel
            // mean).
            if slope >= 1.0 && color == ColorMode::Rgb {
                assert!(got > 0.2 * scale, "{got} of {scale}");
            }
        }
        // The plain estimator removes nothing.
        assert_eq!(
            variance_reduction(&acc, &CellCoefficients::plain(acc.layout(), color)),
            0.0
        );
    }
}

/// The Cornell box's cells: one small light, which NEE finds (`λ_light/p ≈ 1`, value the
/// irradiance and its noise) and the BSDF sample misses (`λ_bsdf/p = 1`, value 0). The
/// pooled regression explains the techniques' means with the two components and claims
/// most of the variance; the estimator, one sample of each technique, has none of that
/// spread, and the fit removes (nearly) nothing within a technique.
#[test]
fn a_fit_that_only_separates_the_techniques_removes_no_variance() {
    let mut rng = Pcg64::seed_from_u64(11);
    let layout = ComponentLayout::new(1, 1).unwrap();
    let mut within = CellAccumulator::new(layout, ColorMode::Rgb);
    let mut pooled = CellAccumulator::new(layout, ColorMode::Rgb);
    for i in 0..2000u32 {
        let (t, value, sample) = if i.is_multiple_of(2) {
            // NEE: a point on the light, whose BSDF density is small.
            let pb = 0.02 * rng.random::<f64>();
            let irradiance = 1.0 + 0.3 * (rng.random::<f64>() - 0.5);
            (Technique::Light, [irradiance; 3], (1.0 + pb, 1.0, pb))
        } else {
            // The BSDF sample: misses the light.
            (Technique::Bsdf, [0.0; 3], (1.0, 0.0, 1.0))
        };
        let (pdf, lp, lb) = sample;
        let lam = [lb];
        let s = CvSample {
            pdf,
            partition: (lp > 0.0).then_some((0, lp)),
            overlapping: &lam,
        };
        within.add_from(t, 1.0, value, &s).unwrap();
        pooled.add(1.0, value, &s).unwrap();
    }
    let gain = |acc: &CellAccumulator| {
        let co = solve(acc, &SolvePolicy::default());
        assert!(!co.is_fallback());
        let one = BTreeMap::from([(0u64, acc.clone())]);
        predicted_fit_gain(&one, &BTreeMap::from([(0u64, co)])).unwrap()
    };
    // The same sums but for the technique split: the same coefficients.
    assert_eq!(
        solve(&within, &SolvePolicy::default()).encode(),
        solve(&pooled, &SolvePolicy::default()).encode()
    );
    let (g_pooled, g_within) = (gain(&pooled), gain(&within));
    assert!(g_pooled > 0.9, "pooled fit gain {g_pooled}");
    assert!(
        g_within.abs() < 0.05,
        "within-technique fit gain {g_within}"
    );
}

/// A table of `cells` recorded cells (the even ones correlated, the odd ones noise) and
/// one cell too small to solve.
fn gate_table(cells: u64) -> BTreeMap<u64, CellAccumulator> {
    let mut t: BTreeMap<u64, CellAccumulator> = (0..cells)
        .map(|k| {
            let slope = if k % 2 == 0 { 2.0 } else { 0.0 };
            (
                k,
                accumulate(
                    &recorded_cell(5, 2, 300, 500 + k, slope),
                    5,
                    2,
                    ColorMode::Rgb,
                ),
            )
        })
        .collect();
    t.insert(
        cells,
        accumulate(&recorded_cell(5, 2, 5, 999, 2.0), 5, 2, ColorMode::Rgb),
    );
    t
}

/// [`gate_table`] of 6 cells, the gate tests' policy (ridge 1) and its plain cell solves.
fn gate_fixture() -> (
    BTreeMap<u64, CellAccumulator>,
    SolvePolicy,
    BTreeMap<u64, CellCoefficients>,
) {
    let cells = gate_table(6);
    let policy = SolvePolicy {
        ridge: 1.0,
        ..SolvePolicy::default()
    };
    let fitted = solve_table(&cells, &policy);
    (cells, policy, fitted)
}

#[test]
fn a_table_below_its_minimum_image_gain_falls_back_everywhere() {
    let (cells, policy, fitted) = gate_fixture();
    let reduction: f64 = cells
        .iter()
        .map(|(k, a)| variance_reduction(a, &fitted[k]))
        .sum();
    assert!(reduction > 0.0);
    let image = 40.0 * reduction;
    let gain = predicted_image_gain(&cells, &fitted, Some(image)).unwrap();
    assert!((gain - 0.025).abs() < 1e-12, "{gain}");
    let solved_with = |min: f64, image: Option<f64>| {
        AccumulatorTable::Moments(cells.clone(), image).solve(
            &SolvePolicy {
                min_image_gain: min,
                ..policy
            },
            3,
        )
    };
    // Above the minimum (and with no minimum) the fits are the plain solves'.
    for min in [0.02, f64::NEG_INFINITY] {
        let kept = solved_with(min, Some(image));
        assert_eq!(kept.image_gain, Some(gain));
        // (Compared encoded: a fallback's NaN condition is not equal to itself.)
        assert!(encode_table(&kept.coefficients) == encode_table(&fitted));
    }
    // Below it every fitted cell falls back, with zero coefficients; a cell that fell back
    // for its own reason keeps that reason.
    let off = solved_with(0.03, Some(image));
    assert_eq!(off.image_gain, Some(gain));
    for (k, co) in &off.coefficients {
        assert_eq!(co.alpha_sum(), [0.0; 3]);
        let want = match fitted[k].diagnostics().status {
            SolveStatus::Solved => SolveStatus::Fallback(FallbackReason::LowImageGain),
            other => other,
        };
        assert_eq!(co.diagnostics().status, want, "cell {k}");
    }
    assert_eq!(
        fitted[&6].diagnostics().status,
        SolveStatus::Fallback(FallbackReason::TooFewSamples)
    );
    // The fallback round-trips through the coefficient encoding.
    let back = CellCoefficients::decode(&off.coefficients[&0].encode()).unwrap();
    assert_eq!(
        back.diagnostics().status,
        SolveStatus::Fallback(FallbackReason::LowImageGain)
    );
    // An unknown or empty image variance makes no decision.
    for image in [None, Some(0.0)] {
        let kept = solved_with(0.03, image);
        assert_eq!(kept.image_gain, None);
        assert!(encode_table(&kept.coefficients) == encode_table(&fitted));
    }
}

/// The fit gain is `Σ reduction / Σ value variance` over all cells (a cell that fell back
/// counts in the denominator); below `min_fit_gain` every fitted cell falls back
/// (`LowFitGain`), whether or not the image variance is known; a table whose cells are
/// noise only has a small fit gain; the image gain's minimum is checked first.
#[test]
fn a_table_whose_fits_remove_little_of_their_cells_variance_falls_back_everywhere() {
    let (cells, policy, fitted) = gate_fixture();
    let (mut reduction, mut variance) = (0.0, 0.0);
    for (k, a) in &cells {
        reduction += variance_reduction(a, &fitted[k]);
        variance += value_variance(a);
    }
    let gain = predicted_fit_gain(&cells, &fitted).unwrap();
    assert!((gain - reduction / variance).abs() < 1e-15, "{gain}");
    assert!(gain > 0.1 && gain < 0.9, "{gain}");
    let solved_with = |min_fit: f64, min_image: f64, image: Option<f64>| {
        AccumulatorTable::Moments(cells.clone(), image).solve(
            &SolvePolicy {
                min_fit_gain: min_fit,
                min_image_gain: min_image,
                ..policy
            },
            2,
        )
    };
    let image = 10.0 * reduction;
    for min in [gain - 0.01, f64::NEG_INFINITY] {
        let kept = solved_with(min, f64::NEG_INFINITY, Some(image));
        assert_eq!(kept.fit_gain, Some(gain));
        assert!(encode_table(&kept.coefficients) == encode_table(&fitted));
    }
    let status = |t: &estimators::table::SolvedTable, reason| {
        for (k, co) in &t.coefficients {
            assert_eq!(co.alpha_sum(), [0.0; 3]);
            let want = match fitted[k].diagnostics().status {
                SolveStatus::Solved => SolveStatus::Fallback(reason),
                other => other,
            };
            assert_eq!(co.diagnostics().status, want, "cell {k}");
        }
    };
    for image in [Some(image), None] {
        let off = solved_with(gain + 0.01, f64::NEG_INFINITY, image);
        assert_eq!(off.fit_gain, Some(gain));
        status(&off, FallbackReason::LowFitGain);
    }
    // Both below: the image gain's reason.
    status(
        &solved_with(gain + 0.01, 0.2, Some(image)),
        FallbackReason::LowImageGain,
    );
    let back = CellCoefficients::decode(
        &solved_with(gain + 0.01, f64::NEG_INFINITY, None).coefficients[&0].encode(),
    )
    .unwrap();
    assert_eq!(
        back.diagnostics().status,
        SolveStatus::Fallback(FallbackReason::LowFitGain)
    );
    // Cells of pure noise: the fits remove only what they overfit.
    let noise: BTreeMap<u64, CellAccumulator> = (0..6)
        .map(|k| {
            let r = recorded_cell(5, 2, 300, 700 + k, 0.0);
            (k, accumulate(&r, 5, 2, ColorMode::Rgb))
        })
        .collect();
    let noise_gain = predicted_fit_gain(&noise, &solve_table(&noise, &policy)).unwrap();
    assert!((0.0..0.05).contains(&noise_gain), "{noise_gain}");
}

/// The version-`to` encoding (1 or 2) of a version-3 accumulator with `k` overlapping
/// components and `c` channels: version 2 lacks the light technique's sums (after the
/// overlapping `Σ w λ/p`) and each partition entry's last `f64` (their light part); version 1
/// also the 2·C value moments after Σw², the K overlapping `Σ w λ/p` after the overlapping
/// `b` and each entry's `Σ w λ/p`.
fn downgrade(v3: &[u8], to: u16, k: usize, c: usize) -> Vec<u8> {
    let header = 4 + 2 + 1 + 1 + 4 + 4 + 8 + 8 + 8 + 8;
    let dense = 8 * (k * (k + 1) / 2 + k * c);
    let mut out = v3[..header].to_vec();
    let mut at = header;
    if to >= 2 {
        out.extend_from_slice(&v3[at..at + 8 * 2 * c]);
    }
    at += 8 * 2 * c;
    out.extend_from_slice(&v3[at..at + dense]);
    at += dense;
    if to >= 2 {
        out.extend_from_slice(&v3[at..at + 8 * k]);
    }
    at += 8 * k + 8 * (1 + c + k);
    out.extend_from_slice(&v3[at..at + 4]);
    at += 4;
    let entry = 12 + 8 * (3 + k + c);
    let dropped = if to >= 2 { 8 } else { 16 };
    while at < v3.len() {
        out.extend_from_slice(&v3[at..at + entry - dropped]);
        at += entry;
    }
    assert_eq!(at, v3.len());
    out[4..6].copy_from_slice(&to.to_le_bytes());
    out
}

#[test]
fn version_1_accumulators_decode_with_no_value_moments_and_remove_nothing() {
    let samples = recorded_cell(4, 2, 200, 7, 2.0);
    let acc = accumulate(&samples, 4, 2, ColorMode::Rgb);
    let v1 = downgrade(&acc.encode(), 1, 2, 3);
    let old = CellAccumulator::decode(&v1).unwrap();
    assert_eq!(old.value_moments(0), (0.0, 0.0));
    assert_eq!(old.g_overlapping(1), 0.0);
    assert!(old.partitions().all(|p| p.g == 0.0 && p.g_light == 0.0));
    for (a, b) in old.partitions().zip(acc.partitions()) {
        assert_eq!(
            (a.id, a.count, a.diag, a.cross, a.b),
            (b.id, b.count, b.diag, b.cross, b.b)
        );
    }
    assert_eq!(old.samples(), acc.samples());
    let co = solve(&old, &SolvePolicy::default());
    assert_eq!(co.encode(), solve(&acc, &SolvePolicy::default()).encode());
    assert_eq!(variance_reduction(&old, &co), 0.0);
    assert!(variance_reduction(&acc, &co) > 0.0);
    // No value moments, no fit gain: a table of old cells makes no `min_fit_gain` decision.
    assert_eq!(value_variance(&old), 0.0);
    let one = |a: &CellAccumulator| BTreeMap::from([(0u64, a.clone())]);
    let fitted = BTreeMap::from([(0u64, co)]);
    assert_eq!(predicted_fit_gain(&one(&old), &fitted), None);
    assert!(predicted_fit_gain(&one(&acc), &fitted).is_some_and(|g| g > 0.0));
    // Re-encoded, it is a current accumulator with zero moments.
    assert_eq!(CellAccumulator::decode(&old.encode()).unwrap(), old);
}

#[test]
fn version_2_accumulators_decode_with_no_technique_sums_and_pooled_figures() {
    let mut samples = recorded_cell(4, 2, 200, 8, 2.0);
    for (i, s) in samples.iter_mut().enumerate() {
        if technique_of(i) == Technique::Light {
            s.1 = s.1.map(|v| v + 3.0);
        }
    }
    let acc = accumulate(&samples, 4, 2, ColorMode::Rgb);
    let old = CellAccumulator::decode(&downgrade(&acc.encode(), 2, 2, 3)).unwrap();
    // Every sum but the technique split is kept.
    assert_eq!(old.value_moments(1), acc.value_moments(1));
    assert_eq!(old.g_overlapping(1), acc.g_overlapping(1));
    let (wl, yl, gl) = old.technique_sums();
    assert_eq!((wl, yl), (0.0, [0.0; 3]));
    assert!(gl.iter().all(|&g| g == 0.0));
    assert!(old.partitions().all(|p| p.g_light == 0.0));
    // Its figures are those of the same samples added without their techniques (pooled).
    let mut pooled = CellAccumulator::new(acc.layout(), ColorMode::Rgb);
    for (w, v, pdf, part, lam) in &samples {
        let s = CvSample {
            pdf: *pdf,
            partition: *part,
            overlapping: lam,
        };
        pooled.add(*w, *v, &s).unwrap();
    }
    assert_eq!(old, pooled);
    let co = solve(&old, &SolvePolicy::default());
    assert_eq!(co.encode(), solve(&acc, &SolvePolicy::default()).encode());
    assert_eq!(
        variance_reduction(&old, &co),
        variance_reduction(&pooled, &co)
    );
    // The light samples' offset is pooled variance, not within-technique variance.
    assert!(value_variance(&old) > 1.5 * value_variance(&acc));
    assert_eq!(CellAccumulator::decode(&old.encode()).unwrap(), old);
}

// ----------------------------------------------------------------------------------------
// Partition groups (`SolvePolicy::min_group_samples`).

/// A cell of `counts.len()` partitions whose partition `k` has `counts[k]` samples, with one
/// overlapping component (BSDF-like); values correlated with the ratios. `relabel` maps a
/// partition to the one it is recorded as, with a factor on its `λ` (for the merged oracle).
fn counted_cell(counts: &[usize], seed: u64, relabel: impl Fn(u32) -> (u32, f64)) -> Vec<Recorded> {
    let mut rng = Pcg64::seed_from_u64(seed);
    let mut out = Vec::new();
    for (k, &n) in counts.iter().enumerate() {
        for _ in 0..n {
            let lam = vec![rng.random::<f64>() * 2.0 + 0.05];
            let lp = rng.random::<f64>() * 4.0 + 0.05;
            let pdf = 0.5 * lam[0] + 0.5 * lp;
            let g = lp / pdf;
            let w = rng.random::<f64>() + 0.5;
            let v = [
                0.3 * k as f64 + g + rng.random::<f64>(),
                2.0 - 0.5 * g + rng.random::<f64>(),
                rng.random::<f64>(),
            ];
            let (id, scale) = relabel(k as u32);
            out.push((w, v, pdf, Some((id, lp * scale)), lam));
        }
    }
    out
}

/// `cms`'s Sobol ridge with partitions fitted in groups of at least `min_group_samples`.
fn grouped_policy(min_group_samples: u64) -> SolvePolicy {
    SolvePolicy {
        ridge: 0.5,
        min_group_samples,
        ..SolvePolicy::default()
    }
}

#[test]
fn a_partition_group_solves_as_the_mixture_of_its_members() {
    // Counts 40, 40, 12, 6 with groups of at least 16: the halves [0, 2) and [2, 4) have 80
    // and 18 samples (split), [0, 2)'s members 40 each (split), [2, 4)'s 12 and 6 (one
    // group). The group is the component `λ_G = (12 λ_2 + 6 λ_3)/18`: the same cell recorded
    // with partitions 2 and 3 as one partition of that `λ` must give `α_G`, and the members
    // `α_2 = (12/18) α_G`, `α_3 = (6/18) α_G`.
    let counts = [40, 40, 12, 6];
    let grouped = grouped_policy(16);
    for color in [ColorMode::Rgb, ColorMode::Mono] {
        let cell = counted_cell(&counts, 71, |k| (k, 1.0));
        let acc = accumulate(&cell, 4, 1, color);
        let (t2, t3) = (12.0 / 18.0, 6.0 / 18.0);
        let merged = counted_cell(&counts, 71, |k| match k {
            2 => (2, t2),
            3 => (2, t3),
            k => (k, 1.0),
        });
        let oracle = solve(
            &accumulate(&merged, 3, 1, color),
            &SolvePolicy {
                min_group_samples: 1,
                ..grouped
            },
        );
        let co = solve(&acc, &grouped);
        assert_eq!(co.diagnostics().status, SolveStatus::Solved);
        assert_eq!(co.diagnostics().active_partitions, 3);
        let expect = [
            oracle.alpha_partition(0),
            oracle.alpha_partition(1),
            oracle.alpha_partition(2).map(|a| t2 * a),
            oracle.alpha_partition(2).map(|a| t3 * a),
        ];
        for (id, e) in expect.iter().enumerate() {
            let a = co.alpha_partition(id as u32);
            for c in 0..3 {
                assert!(
                    (a[c] - e[c]).abs() <= 1e-9 * e[c].abs().max(1e-3),
                    "{color:?} partition {id} channel {c}: {} vs {}",
                    a[c],
                    e[c]
                );
            }
        }
        let (a, e) = (co.alpha_overlapping(0), oracle.alpha_overlapping(0));
        let (s, se) = (co.alpha_sum(), oracle.alpha_sum());
        for c in 0..3 {
            assert!((a[c] - e[c]).abs() <= 1e-9 * e[c].abs().max(1e-3));
            assert!((s[c] - se[c]).abs() <= 1e-9 * se[c].abs().max(1e-3));
        }
        // The same variance removed, and the dense oracle agrees.
        let (r, re) = (
            variance_reduction(&acc, &co),
            variance_reduction(&accumulate(&merged, 3, 1, color), &oracle),
        );
        assert!((r - re).abs() <= 1e-9 * re.abs(), "reduction {r} vs {re}");
        assert!(max_rel_diff(&co, &solve_dense(&acc, &grouped), acc.layout()) < 1e-9);
        // Groups of one are the partitions' own fits: without grouping all four are fitted.
        let alone = solve(
            &acc,
            &SolvePolicy {
                min_group_samples: 1,
                ..grouped
            },
        );
        assert_eq!(alone.diagnostics().active_partitions, 4);
        assert_eq!(
            solve(
                &acc,
                &SolvePolicy {
                    min_group_samples: 6,
                    ..grouped
                }
            ),
            alone
        );
    }
}

#[test]
fn an_undersampled_half_keeps_its_sibling_in_the_group() {
    // [0, 2) has 80 samples, [2, 4) only 10 < 16: the whole range is one group, every
    // member's `α` the group's times its share of the samples.
    let counts = [40, 40, 6, 4];
    let policy = grouped_policy(16);
    let acc = accumulate(
        &counted_cell(&counts, 72, |k| (k, 1.0)),
        4,
        1,
        ColorMode::Rgb,
    );
    let co = solve(&acc, &policy);
    assert_eq!(co.diagnostics().active_partitions, 1);
    let total: f64 = counts.iter().sum::<usize>() as f64;
    let group = co.alpha_partition(0).map(|a| a * total / 40.0);
    for (id, &n) in counts.iter().enumerate() {
        let a = co.alpha_partition(id as u32);
        for c in 0..3 {
            let e = group[c] * n as f64 / total;
            assert!(
                (a[c] - e).abs() <= 1e-12 * e.abs().max(1e-12),
                "partition {id}"
            );
        }
    }
    assert!(max_rel_diff(&co, &solve_dense(&acc, &policy), acc.layout()) < 1e-9);
}

/// Out-of-sample weighted variance (within each technique) of a cell's controlled values
/// `y − Σ α λ/p` on `samples`, per channel summed.
fn held_out_variance(samples: &[Recorded], co: &CellCoefficients) -> f64 {
    let w: Vec<f64> = samples.iter().map(|s| s.0).collect();
    (0..3)
        .map(|c| {
            let x: Vec<f64> = samples
                .iter()
                .map(|(_, v, pdf, part, lam)| {
                    let s = CvSample {
                        pdf: *pdf,
                        partition: *part,
                        overlapping: lam,
                    };
                    v[c] - co.cv_term(&s)[c]
                })
                .collect();
            within_technique_ss(&w, &x)
        })
        .sum()
}

/// `n` samples of each of `p` partitions: heavy-tailed ratios (as light samples far from
/// their pdf's bulk are), values `slope · g` (a part every partition shares) plus a
/// per-sample noise the ratios cannot explain.
fn many_light_samples(p: u32, n: usize, seed: u64, slope: f64) -> Vec<Recorded> {
    let mut rng = Pcg64::seed_from_u64(seed);
    let mut out: Vec<Recorded> = Vec::new();
    for _ in 0..n {
        for k in 0..p {
            let lam = vec![rng.random::<f64>() * 2.0 + 0.05];
            let lp = rng.random::<f64>().powi(3) * 8.0 + 0.01;
            let pdf = 0.5 * lam[0] + 0.5 * lp;
            let g = lp / pdf;
            let noise = 3.0 * (rng.random::<f64>() - 0.5);
            let v = [slope * g + noise, 0.4 * slope * g + noise, noise];
            out.push((1.0, v, pdf, Some((k, lp)), lam));
        }
    }
    out
}

/// A table of cell `0`'s two halves (keys 0 and 1, [`CellHalves`]) and the cell's merged
/// accumulator.
fn halved_table(
    even: &[Recorded],
    odd: &[Recorded],
    p: u32,
) -> (AccumulatorTable, CellAccumulator) {
    let mut t = BTreeMap::new();
    t.insert(0, accumulate(even, p, 1, ColorMode::Rgb));
    t.insert(1, accumulate(odd, p, 1, ColorMode::Rgb));
    let mut whole = t[&0].clone();
    whole.merge(&t[&1]).unwrap();
    (AccumulatorTable::Moments(t, None), whole)
}

#[test]
fn halves_solve_merged_and_a_fit_that_follows_noise_fails_its_held_out_check() {
    let base = grouped_policy(1);
    // Two samples per partition: alone, the fits follow the noise (see
    // `grouping_keeps_many_thinly_sampled_partitions_from_fitting_noise`).
    let (noisy, whole) = halved_table(
        &many_light_samples(512, 1, 91, 1.0),
        &many_light_samples(512, 1, 92, 1.0),
        512,
    );
    let merged = noisy.solve(
        &SolvePolicy {
            halves: CellHalves::Merged,
            ..base
        },
        2,
    );
    assert_eq!(
        merged.coefficients.keys().copied().collect::<Vec<_>>(),
        vec![0]
    );
    assert_eq!(merged.coefficients[&0], solve(&whole, &base));
    let crossed = noisy.solve(
        &SolvePolicy {
            halves: CellHalves::CrossFitted,
            ..base
        },
        2,
    );
    assert_eq!(
        crossed.coefficients[&0].diagnostics().status,
        SolveStatus::Fallback(FallbackReason::HeldOutLoss)
    );
    // Grouped, the same cell's fits remove variance out of sample, and are kept.
    let grouped = SolvePolicy {
        halves: CellHalves::CrossFitted,
        min_group_samples: 64,
        ..base
    };
    let kept = noisy.solve(&grouped, 2);
    assert_eq!(kept.coefficients[&0], solve(&whole, &grouped));
    assert_eq!(
        kept.coefficients[&0].diagnostics().status,
        SolveStatus::Solved
    );
    // A cell without its odd half is solved on what it has, unchecked (key 5 = cell 2's odd
    // half).
    let AccumulatorTable::Moments(mut t, _) = noisy else {
        unreachable!()
    };
    let odd = t.remove(&1).unwrap();
    t.insert(5, odd.clone());
    let lone = AccumulatorTable::Moments(t, None).solve(
        &SolvePolicy {
            halves: CellHalves::CrossFitted,
            ..base
        },
        1,
    );
    assert_eq!(
        lone.coefficients.keys().copied().collect::<Vec<_>>(),
        vec![0, 2]
    );
    assert_eq!(lone.coefficients[&2], solve(&odd, &base));
}

#[test]
fn grouping_keeps_many_thinly_sampled_partitions_from_fitting_noise() {
    // 512 partitions and 2 training samples each (a many-light cell): values carry a
    // per-sample noise the ratios cannot explain, plus a part every partition shares (`g`).
    // Alone, each partition's coefficient follows its two samples' noise and the fits add
    // variance on fresh samples (≈ 12× here, as on a scene of 10 080 emissive triangles:
    // 0.18× at equal spp); in groups of at least 64 samples they remove some of the shared
    // part (≈ 0.86×). Fresh samples: 40 960, a relative standard error of the variances of
    // ≈ 1 %, far inside the margins.
    let p = 512u32;
    let draw = |n: usize, seed: u64| many_light_samples(p, n, seed, 1.0);
    let train = draw(2, 81);
    let fresh = draw(80, 82);
    let acc = accumulate(&train, p, 1, ColorMode::Rgb);
    let base = grouped_policy(1);
    let plain_var = held_out_variance(
        &fresh,
        &CellCoefficients::plain(acc.layout(), ColorMode::Rgb),
    );
    let alone = held_out_variance(&fresh, &solve(&acc, &base));
    let grouped = held_out_variance(
        &fresh,
        &solve(
            &acc,
            &SolvePolicy {
                min_group_samples: 64,
                ..base
            },
        ),
    );
    eprintln!(
        "plain {plain_var:.4e}, alone {alone:.4e} ({:.3}x), grouped {grouped:.4e} ({:.3}x)",
        alone / plain_var,
        grouped / plain_var
    );
    assert!(alone > 2.0 * plain_var, "alone {alone} plain {plain_var}");
    assert!(
        grouped < 0.95 * plain_var,
        "grouped {grouped} plain {plain_var}"
    );
}

/// A table of one undivided cell's nine children (ids `0..9`, [`CellHalves`] keys `2c`,
/// `2c + 1`) from `halves(child) = (even, odd)` samples, and each child's merged sums.
fn family_table(
    p: u32,
    halves: impl Fn(u64) -> (Vec<Recorded>, Vec<Recorded>),
) -> (AccumulatorTable, Vec<CellAccumulator>) {
    let mut t = BTreeMap::new();
    let mut wholes = Vec::new();
    for c in 0..9u64 {
        let (even, odd) = halves(c);
        let (e, o) = (
            accumulate(&even, p, 1, ColorMode::Rgb),
            accumulate(&odd, p, 1, ColorMode::Rgb),
        );
        let mut whole = e.clone();
        whole.merge(&o).unwrap();
        t.insert(2 * c, e);
        t.insert(2 * c + 1, o);
        wholes.push(whole);
    }
    (AccumulatorTable::Moments(t, None), wholes)
}

/// A check without halves (a training tile's probe) keeps the fits of a subdivided table
/// when either the pooled fits (the undivided cell's, which merged halves give its
/// children) or the children's own fits pay, and switches them off only when neither does.
#[test]
fn a_check_without_halves_keeps_fits_that_pay_pooled_or_alone() {
    let policy = SolvePolicy {
        halves: CellHalves::Merged,
        levels: 1,
        bins: 1,
        min_fit_gain: 0.3,
        ..grouped_policy(1)
    };
    let alone = SolvePolicy {
        levels: 0,
        ..policy
    };
    let off = |t: &AccumulatorTable, p: &SolvePolicy| t.solve(p, 2).switched_off;
    // Children of opposite slopes (+5 and −5): pooled, the undivided cell's coefficient is
    // near the mean slope and removes little; alone, each child removes most of its variance.
    let (opposite, _) = family_table(2, |c| {
        let slope = if c % 2 == 0 { 5.0 } else { -5.0 };
        (
            many_light_samples(2, 200, 3000 + 2 * c, slope),
            many_light_samples(2, 200, 3001 + 2 * c, slope),
        )
    });
    assert_eq!(off(&opposite, &policy), Some(FallbackReason::LowFitGain));
    assert_eq!(off(&opposite, &alone), None);
    assert!(opposite.fits_pay_pooled_or_alone(&policy, 2));
    // One integrand, too few samples per child to fit alone (12 < `min_samples`): only the
    // pooled fit pays.
    let (thin, _) = family_table(2, |c| {
        (
            many_light_samples(2, 3, 4000 + 2 * c, 5.0),
            many_light_samples(2, 3, 4001 + 2 * c, 5.0),
        )
    });
    assert_eq!(off(&thin, &policy), None);
    assert_eq!(off(&thin, &alone), Some(FallbackReason::LowFitGain));
    assert!(thin.fits_pay_pooled_or_alone(&policy, 2));
    // Values that are noise only: neither pays, the fits are switched off.
    let (noise, _) = family_table(2, |c| {
        (
            many_light_samples(2, 200, 5000 + 2 * c, 0.0),
            many_light_samples(2, 200, 5001 + 2 * c, 0.0),
        )
    });
    assert!(off(&noise, &policy).is_some() && off(&noise, &alone).is_some());
    assert!(!noise.fits_pay_pooled_or_alone(&policy, 2));
    // Without levels there is one solve.
    assert!(!opposite.fits_pay_pooled_or_alone(
        &SolvePolicy {
            levels: 0,
            min_fit_gain: 0.99,
            ..policy
        },
        2
    ));
}

#[test]
fn a_subdivided_cell_keeps_its_own_fit_or_its_parents_whichever_removes_more_held_out() {
    let policy = SolvePolicy {
        halves: CellHalves::CrossFitted,
        levels: 1,
        bins: 1,
        ..grouped_policy(1)
    };
    let parent_of = |wholes: &[CellAccumulator]| {
        let mut all = wholes[0].clone();
        for w in &wholes[1..] {
            all.merge(w).unwrap();
        }
        all
    };
    // One integrand over the whole cell and a handful of samples per child (12: below
    // `min_samples`): no child can fit itself, and each takes the parent's fit.
    let (thin, wholes) = family_table(2, |c| {
        (
            many_light_samples(2, 3, 1000 + 2 * c, 5.0),
            many_light_samples(2, 3, 1001 + 2 * c, 5.0),
        )
    });
    let solved = thin.solve(&policy, 2);
    let parent = solve(&parent_of(&wholes), &policy);
    assert_eq!(parent.diagnostics().status, SolveStatus::Solved);
    for c in 0..9 {
        assert_eq!(
            solve(&wholes[c as usize], &policy).diagnostics().status,
            SolveStatus::Fallback(FallbackReason::TooFewSamples)
        );
        assert_eq!(solved.coefficients[&c], parent, "child {c}");
    }
    // Without subdivision (levels 0) the same children fall back.
    let flat = thin.solve(
        &SolvePolicy {
            levels: 0,
            ..policy
        },
        2,
    );
    assert!(flat.coefficients.values().all(|co| co.is_fallback()));
    // Without a held-out check (merged halves) every child takes its undivided cell's fit.
    let merged = thin.solve(
        &SolvePolicy {
            halves: CellHalves::Merged,
            ..policy
        },
        2,
    );
    assert!(merged.coefficients.values().all(|co| *co == parent));
    // Children whose integrands differ (slopes 1…25) and are well sampled keep their own
    // fits (unshrunk: with a ridge the parent's larger slope, shrunk, can fit a child's
    // better than the child's own shrunk fit, and the held-out check then rightly takes it).
    let policy = SolvePolicy {
        ridge: 1e-6,
        ..policy
    };
    let (rich, wholes) = family_table(2, |c| {
        let slope = 1.0 + 3.0 * c as f64;
        (
            many_light_samples(2, 200, 2000 + 2 * c, slope),
            many_light_samples(2, 200, 2001 + 2 * c, slope),
        )
    });
    let solved = rich.solve(&policy, 2);
    for c in 0..9u64 {
        let own = solve(&wholes[c as usize], &policy);
        assert_eq!(own.diagnostics().status, SolveStatus::Solved);
        assert_eq!(solved.coefficients[&c], own, "child {c}");
    }
    // The choice does not depend on the thread count.
    assert_eq!(rich.solve(&policy, 1), solved);
    // Cells alone under their ancestors (the other vertices' child of three undivided
    // cells, digits 8 then 0: ids 72, 153, 234 with two levels) are solved as without
    // subdivision, bit for bit, and so are their halves' checks (the third cell's fit
    // follows its samples' noise: `HeldOutLoss`).
    let mut t = BTreeMap::new();
    for (c, (slope, n)) in [(72u64, (5.0, 40)), (153, (2.0, 40)), (234, (0.0, 40))] {
        t.insert(
            2 * c,
            accumulate(&many_light_samples(2, n, c, slope), 2, 1, ColorMode::Rgb),
        );
        t.insert(
            2 * c + 1,
            accumulate(
                &many_light_samples(2, n, c + 1, slope),
                2,
                1,
                ColorMode::Rgb,
            ),
        );
    }
    let lone = AccumulatorTable::Moments(t, None);
    let two = SolvePolicy {
        levels: 2,
        ..policy
    };
    let solved = lone.solve(&two, 2);
    assert_eq!(solved, lone.solve(&SolvePolicy { levels: 0, ..two }, 2));
    assert_eq!(
        solved.coefficients[&234].diagnostics().status,
        SolveStatus::Fallback(FallbackReason::HeldOutLoss)
    );
    assert_eq!(
        solved.coefficients[&72].diagnostics().status,
        SolveStatus::Solved
    );
}

/// A cross-fitted table (keys `2c`, `2c + 1`: cell `c`'s halves) of `cells` cells of
/// [`recorded_cell`] samples with the given `slope` (0: values the ratios cannot explain),
/// each half `n` samples of its own seed.
fn crossed_table(cells: u64, n: usize, slope: f64, seed: u64) -> AccumulatorTable {
    let t = (0..2 * cells)
        .map(|key| {
            let r = recorded_cell(5, 2, n, seed + key, slope);
            (key, accumulate(&r, 5, 2, ColorMode::Rgb))
        })
        .collect();
    AccumulatorTable::Moments(t, None)
}

/// The held-out figures are, over the cells whose own fit is kept (no hierarchy: `levels`
/// 0), the variance each half's fit removes from the other half, against the fit gain's
/// denominator (gain) and against the kept fits' in-sample reduction (share), computed here
/// from the halves by brute force.
#[test]
fn the_held_out_gain_and_share_are_the_kept_fits_judged_on_the_other_half() {
    let policy = SolvePolicy {
        ridge: 0.5,
        halves: CellHalves::CrossFitted,
        ..SolvePolicy::default()
    };
    // Signal in some cells, noise in others, so that some fail their own check.
    let AccumulatorTable::Moments(mut t, _) = crossed_table(4, 200, 1.5, 3100) else {
        unreachable!()
    };
    let AccumulatorTable::Moments(noise, _) = crossed_table(4, 200, 0.0, 3200) else {
        unreachable!()
    };
    t.extend(noise.into_iter().map(|(k, a)| (k + 8, a)));
    let table = AccumulatorTable::Moments(t.clone(), None);
    let solved = table.solve(&policy, 2);
    let half = policy.for_half();
    let (mut held_out, mut in_sample, mut variance) = (0.0, 0.0, 0.0);
    let mut kept = 0;
    for c in 0..8u64 {
        let (even, odd) = (&t[&(2 * c)], &t[&(2 * c + 1)]);
        let mut whole = even.clone();
        whole.merge(odd).unwrap();
        variance += value_variance(&whole);
        let co = &solved.coefficients[&c];
        if co.diagnostics().status == SolveStatus::Solved {
            kept += 1;
            held_out += variance_reduction(odd, &solve(even, &half))
                + variance_reduction(even, &solve(odd, &half));
            in_sample += variance_reduction(&whole, co);
        }
    }
    assert!((1..8).contains(&kept), "{kept} of 8 cells kept");
    let (gain, share) = (
        solved.held_out_gain.unwrap(),
        solved.held_out_share.unwrap(),
    );
    assert!(
        (gain - held_out / variance).abs() <= 1e-12 * gain.abs(),
        "{gain}"
    );
    assert!(
        (share - held_out / in_sample).abs() <= 1e-12 * share.abs(),
        "{share}"
    );
    // Held out, a fit removes less than in sample; the signal cells' fits keep most of it.
    assert!(share > 0.5 && share < 1.0, "{share}");
    assert!(gain < solved.fit_gain.unwrap());
    // The same on one thread (sums in key order).
    let one = table.solve(&policy, 1);
    assert_eq!(one.held_out_gain, solved.held_out_gain);
    assert_eq!(one.held_out_share, solved.held_out_share);
    // Only cross-fitted tables have the figures.
    let merged = table.solve(
        &SolvePolicy {
            halves: CellHalves::Merged,
            ..policy
        },
        2,
    );
    assert_eq!((merged.held_out_gain, merged.held_out_share), (None, None));
}

/// Below `min_held_out_share` *and* with a held-out gain below `min_fit_gain`, every fitted
/// cell falls back (`Overfitted`, round-tripping through the coefficient encoding); a
/// held-out gain that clears `min_fit_gain` keeps the fits whatever the share; the in-sample
/// fit gain's reason comes first.
#[test]
fn fits_that_keep_little_of_their_gain_held_out_fall_back_everywhere() {
    let table = crossed_table(6, 150, 1.0, 3300);
    let base = SolvePolicy {
        ridge: 0.5,
        halves: CellHalves::CrossFitted,
        ..SolvePolicy::default()
    };
    let free = table.solve(&base, 2);
    let (fit, gain, share) = (
        free.fit_gain.unwrap(),
        free.held_out_gain.unwrap(),
        free.held_out_share.unwrap(),
    );
    assert!(
        free.controls_any() && gain > 0.0 && gain < fit,
        "{fit} {gain} {share}"
    );
    let with = |min_fit_gain: f64, min_held_out_share: f64| {
        table.solve(
            &SolvePolicy {
                min_fit_gain,
                min_held_out_share,
                ..base
            },
            2,
        )
    };
    let same = |t: &estimators::table::SolvedTable| {
        assert!(encode_table(&t.coefficients) == encode_table(&free.coefficients));
        assert_eq!(t.switched_off, None);
    };
    let off_by = |t: &estimators::table::SolvedTable, reason| {
        assert_eq!(t.switched_off, Some(reason));
        assert!(!t.controls_any());
        for (k, co) in &t.coefficients {
            let want = match free.coefficients[k].diagnostics().status {
                SolveStatus::Solved => SolveStatus::Fallback(reason),
                other => other,
            };
            assert_eq!(co.diagnostics().status, want, "cell {k}");
        }
    };
    // Held-out gain below min_fit_gain (which the in-sample gain clears):
    let between = (gain + fit) / 2.0;
    off_by(&with(between, share + 0.01), FallbackReason::Overfitted);
    same(&with(between, share - 0.01));
    same(&with(between, f64::NEG_INFINITY));
    // A held-out gain that clears min_fit_gain keeps the fits.
    same(&with(gain - 1e-9, share + 0.5));
    // The in-sample fit gain below its minimum: its own reason.
    off_by(&with(fit + 0.01, share + 0.01), FallbackReason::LowFitGain);
    let off = with(between, share + 0.01);
    let (&k, co) = off
        .coefficients
        .iter()
        .find(|(k, _)| free.coefficients[k].diagnostics().status == SolveStatus::Solved)
        .unwrap();
    let back = CellCoefficients::decode(&co.encode()).unwrap();
    assert_eq!(
        back.diagnostics().status,
        SolveStatus::Fallback(FallbackReason::Overfitted),
        "cell {k}"
    );
}
