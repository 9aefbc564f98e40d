//! OCV [Fan eq. 7–11] on 1-D integrals with closed-form answers.

mod common;

use common::{Pdf, mean_var};
use estimators::mis::deterministic_counts;
use estimators::ocv::{OcvError, OcvOptions, OcvSolver, ocv_estimate};
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;

fn f(x: f64) -> [f64; 3] {
    [3.0 * x * x + 0.5, 2.0 * x, 1.0]
}
const TRUTH: [f64; 3] = [1.5, 1.0, 1.0];

/// Deterministic mixture sampling of `n` samples from uniform + linear + quadratic.
fn draw(n: usize, seed: u64) -> (Vec<[f64; 3]>, Vec<f64>, Vec<f64>) {
    let comps = [Pdf::Uniform, Pdf::Linear, Pdf::Quadratic];
    let mixture = vec![0.5, 0.25, 0.25];
    let counts = deterministic_counts(&mixture, n).unwrap();
    let mut rng = Pcg64::seed_from_u64(seed);
    let (mut values, mut pdfs) = (Vec::new(), Vec::new());
    for (c, &k) in comps.iter().zip(&counts) {
        for _ in 0..k {
            let x = c.sample(rng.random());
            values.push(f(x));
            pdfs.extend(comps.iter().map(|p| p.pdf(x)));
        }
    }
    (values, pdfs, mixture)
}

fn run(options: &OcvOptions, seeds: u64) -> (Vec<[f64; 3]>, Vec<[f64; 3]>) {
    let (mut ocv, mut plain) = (Vec::new(), Vec::new());
    for s in 0..seeds {
        let (v, p, m) = draw(64, s);
        let r = ocv_estimate(&v, &p, &m, options).unwrap();
        assert!(!r.fallback);
        ocv.push(r.estimate);
        plain.push(r.plain);
    }
    (ocv, plain)
}

#[test]
fn ocv_is_accurate_and_beats_deterministic_mixture() {
    let seeds = 400;
    let (ocv, plain) = run(&OcvOptions::default(), seeds);
    let (m, v) = mean_var(&ocv);
    let (mp, vp) = mean_var(&plain);
    for c in 0..3 {
        let se = (vp[c] / seeds as f64).sqrt().max(1e-12);
        assert!((mp[c] - TRUTH[c]).abs() < 4.5 * se, "plain channel {c}");
        // The regression estimator's bias is O(1/N); it must stay well inside the plain SE.
        assert!(
            (m[c] - TRUTH[c]).abs() < 4.5 * se,
            "ocv channel {c}: {} vs {}",
            m[c],
            TRUTH[c]
        );
        assert!(
            v[c] <= vp[c] * 1.05 + 1e-20,
            "channel {c}: ocv var {} plain {}",
            v[c],
            vp[c]
        );
    }
    // Channels 1 and 2 equal the linear and uniform pdfs: in the span of the CV, so the
    // unpenalised fit (λ = 0) is exact; the ridge trades a little of that for robustness.
    let (exact, _) = run(
        &OcvOptions {
            lambda: 0.0,
            ..OcvOptions::default()
        },
        50,
    );
    let (m0, v0) = mean_var(&exact);
    for c in 1..3 {
        assert!(
            v0[c] < 1e-20 && (m0[c] - 1.0).abs() < 1e-9,
            "λ = 0: mean {} var {}",
            m0[c],
            v0[c]
        );
        assert!(
            v[c] < 0.5 * vp[c],
            "channel {c}: ocv var {} plain {}",
            v[c],
            vp[c]
        );
    }
}

#[test]
fn penalized_intercept_shrinks_estimates_toward_zero() {
    let seeds = 100;
    let (free, _) = run(&OcvOptions::default(), seeds);
    let literal = OcvOptions {
        penalize_intercept: true,
        ..OcvOptions::default()
    };
    let (shrunk, _) = run(&literal, seeds);
    let (mf, _) = mean_var(&free);
    let (ms, _) = mean_var(&shrunk);
    // Expected relative shrink ≈ λ / (N + λ) = 1/65 ≈ 1.5 % for the constant channel.
    let expected = 1.0 / 65.0;
    let shrink: Vec<f64> = (0..3).map(|c| 1.0 - ms[c] / mf[c]).collect();
    eprintln!("relative shrink per channel {shrink:?}, λ/(N+λ) = {expected}");
    for (c, s) in shrink.iter().enumerate() {
        assert!(*s > 0.0 && *s < 2.0 * expected, "channel {c}: shrink {s}");
    }
    // With a single component the fit is the intercept alone: the literal eq. 11 returns
    // exactly N/(N+λ) times the sample mean, the unpenalised default the mean itself.
    let (v, p, _) = draw(64, 5);
    let p1: Vec<f64> = p.chunks_exact(3).map(|r| r[0]).collect();
    let a = ocv_estimate(&v, &p1, &[1.0], &OcvOptions::default()).unwrap();
    let b = ocv_estimate(&v, &p1, &[1.0], &literal).unwrap();
    for c in 0..3 {
        assert!((a.estimate[c] - a.plain[c]).abs() < 1e-12 * a.plain[c].abs());
        assert!((b.estimate[c] - a.plain[c] * 64.0 / 65.0).abs() < 1e-12 * a.plain[c].abs());
    }
}

#[test]
fn ocv_occluded_component_stays_finite() {
    // Component 1's pdf reported as zero everywhere (occluded light): λ keeps it finite.
    let (v, mut p, m) = draw(64, 7);
    for row in p.chunks_exact_mut(3) {
        row[1] = 0.0;
    }
    let r = ocv_estimate(&v, &p, &m, &OcvOptions::default()).unwrap();
    assert!(!r.fallback);
    assert!(r.estimate.iter().all(|e| e.is_finite()));
    assert_eq!(r.beta[1], [0.0; 3]);
    // Without the penalty that column cannot be fitted: plain estimate.
    let r = ocv_estimate(
        &v,
        &p,
        &m,
        &OcvOptions {
            lambda: 0.0,
            ..OcvOptions::default()
        },
    )
    .unwrap();
    assert!(r.fallback);
    assert_eq!(r.estimate, r.plain);
}

#[test]
fn ocv_single_component_is_the_sample_mean() {
    let mut rng = Pcg64::seed_from_u64(3);
    let xs: Vec<f64> = (0..32).map(|_| Pdf::Linear.sample(rng.random())).collect();
    let v: Vec<[f64; 3]> = xs.iter().map(|&x| f(x)).collect();
    let p: Vec<f64> = xs.iter().map(|&x| Pdf::Linear.pdf(x)).collect();
    let r = ocv_estimate(&v, &p, &[1.0], &OcvOptions::default()).unwrap();
    for c in 0..3 {
        assert!((r.estimate[c] - r.plain[c]).abs() < 1e-12 * r.plain[c].abs().max(1.0));
    }
}

#[test]
fn ocv_rejects_bad_samples_and_inputs() {
    let (mut v, mut p, m) = draw(64, 9);
    v[3] = [f64::NAN, 0.0, 0.0];
    p[10 * 3 + 2] = f64::INFINITY;
    p[20 * 3] = -1.0;
    let r = ocv_estimate(&v, &p, &m, &OcvOptions::default()).unwrap();
    assert_eq!(r.rejected, 3);
    assert!(r.estimate.iter().all(|e| e.is_finite()));
    assert_eq!(
        ocv_estimate(&v, &p[1..], &m, &OcvOptions::default()),
        Err(OcvError::SizeMismatch)
    );
    assert_eq!(
        ocv_estimate(&v, &p, &[0.0, 0.0, 0.0], &OcvOptions::default()),
        Err(OcvError::BadMixture)
    );
    assert_eq!(
        ocv_estimate(&[], &[], &m, &OcvOptions::default()),
        Err(OcvError::NoSamples)
    );
    assert_eq!(
        ocv_estimate(&[], &[], &[], &OcvOptions::default()),
        Err(OcvError::NoComponents)
    );
    // Huge and tiny magnitudes scale through.
    let (v, p, m) = draw(64, 10);
    let base = ocv_estimate(
        &v,
        &p,
        &m,
        &OcvOptions {
            lambda: 0.0,
            ..OcvOptions::default()
        },
    )
    .unwrap();
    for s in [1e-30, 1e30] {
        let vs: Vec<[f64; 3]> = v.iter().map(|x| x.map(|y| y * s)).collect();
        let r = ocv_estimate(
            &vs,
            &p,
            &m,
            &OcvOptions {
                lambda: 0.0,
                ..OcvOptions::default()
            },
        )
        .unwrap();
        for c in 0..3 {
            assert!((r.estimate[c] / s - base.estimate[c]).abs() < 1e-9 * base.estimate[c].abs());
        }
    }
}

/// Fewer than two samples per mixture component (3 components here): the plain estimate, with
/// no fit attempted; from `2m` samples on, the fit.
#[test]
fn ocv_needs_two_samples_per_component() {
    use estimators::ocv::MIN_SAMPLES_PER_COMPONENT;
    let need = MIN_SAMPLES_PER_COMPONENT * 3;
    for n in [2, 4, need - 1] {
        let (v, p, m) = draw(n, 11);
        let r = ocv_estimate(&v, &p, &m, &OcvOptions::default()).unwrap();
        assert!(r.fallback && r.condition.is_nan(), "{n} samples: {r:?}");
        assert_eq!(r.estimate, r.plain);
        assert!(r.beta.iter().all(|b| *b == [0.0; 3]));
    }
    let (v, p, m) = draw(need, 11);
    let r = ocv_estimate(&v, &p, &m, &OcvOptions::default()).unwrap();
    assert!(!r.fallback && r.condition.is_finite(), "{r:?}");
    assert!(r.estimate != r.plain);
}

proptest::proptest! {
    #![proptest_config(proptest::prelude::ProptestConfig::with_cases(64))]

    /// The solver's `β` solve the penalised normal equations `(XᵀX + λD) β = Xᵀy` [Fan eq. 11]
    /// (checked with an independent LU solve), and a solver reused across fits of other sizes
    /// gives the bits of a fresh one.
    #[test]
    fn ocv_solver_solves_the_normal_equations_and_reuses_its_buffers(
        m in 1usize..7,
        extra in 0usize..20,
        seed in 0u64..1000,
        lambda in 0.0f64..4.0,
    ) {
        let n = 2 * m + extra;
        let mut rng = Pcg64::seed_from_u64(seed);
        let values: Vec<[f64; 3]> = (0..n)
            .map(|_| [rng.random::<f64>(), rng.random::<f64>() * 3.0, rng.random::<f64>() - 0.2])
            .collect();
        let pdfs: Vec<f64> = (0..n * m).map(|_| rng.random::<f64>() * 2.0 + 0.05).collect();
        let mixture: Vec<f64> = (0..m).map(|_| rng.random::<f64>() + 0.1).collect();
        let options = OcvOptions { lambda, ..OcvOptions::default() };
        let r = ocv_estimate(&values, &pdfs, &mixture, &options).unwrap();
        proptest::prop_assume!(!r.fallback);

        // Reuse: a solver that fitted a larger and a smaller problem first.
        let mut solver = OcvSolver::default();
        let big: Vec<f64> = (0..n * (m + 2)).map(|i| 0.3 + (i % 7) as f64).collect();
        let _ = solver.fit(&values, &big, &vec![1.0; m + 2], &options);
        let _ = solver.fit(&values[..1], &pdfs[..m], &mixture, &options);
        let fit = solver.fit(&values, &pdfs, &mixture, &options).unwrap();
        proptest::prop_assert_eq!(fit.estimate, r.estimate);
        for j in 0..m {
            proptest::prop_assert_eq!(solver.beta(j), r.beta[j]);
        }

        // Independent check of the normal equations.
        let total: f64 = mixture.iter().sum();
        let mut a = nalgebra::DMatrix::<f64>::zeros(m, m);
        let mut b = nalgebra::DMatrix::<f64>::zeros(m, 3);
        for (v, row) in values.iter().zip(pdfs.chunks_exact(m)) {
            let p: f64 = row.iter().zip(&mixture).map(|(x, w)| x * w / total).sum();
            let x: Vec<f64> = std::iter::once(1.0).chain(row[..m - 1].iter().map(|x| x / p)).collect();
            for i in 0..m {
                for k in 0..m {
                    a[(i, k)] += x[i] * x[k];
                }
                for c in 0..3 {
                    b[(i, c)] += x[i] * v[c] / p;
                }
            }
        }
        for i in 1..m {
            a[(i, i)] += lambda;
        }
        let sol = a.clone().lu().solve(&b).unwrap();
        for c in 0..3 {
            let scale = sol.column(c).amax().max(1.0);
            proptest::prop_assert!((sol[(0, c)] - r.beta0[c]).abs() < 1e-7 * scale);
            for j in 1..m {
                proptest::prop_assert!(
                    (sol[(j, c)] - r.beta[j - 1][c]).abs() < 1e-7 * scale,
                    "β_{} channel {}: {} vs {}", j, c, sol[(j, c)], r.beta[j - 1][c]
                );
            }
            proptest::prop_assert_eq!(r.beta[m - 1][c], 0.0);
        }
    }
}
