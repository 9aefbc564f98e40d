//! Error metrics (DESIGN §6): relMSE with ε = 0.01, MSE, efficiency and speedup.
//!
//! relMSE = mean over pixels and channels of (x − ref)² / (ref² + ε). Images are flat slices of
//! interleaved channels; both must have the same length.

/// The ε of relMSE, so that black reference pixels do not divide by zero.
pub const REL_MSE_EPSILON: f64 = 0.01;

/// Error statistics of a test image against a reference.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ErrorStats {
    /// Mean of (x − ref)² / (ref² + ε) over finite entries.
    pub rel_mse: f64,
    /// Mean of (x − ref)² over finite entries.
    pub mse: f64,
    /// Entries of the test image that are NaN or ±Inf (excluded from the means).
    pub non_finite: usize,
}

/// Compares `test` with `reference` (same length, interleaved channels).
///
/// Non-finite test values are counted and left out of the means; a non-finite reference value
/// leaves its entry out too.
///
/// # Panics
/// If the slices differ in length (a caller bug, not bad input: callers check image sizes).
pub fn compare(test: &[f32], reference: &[f32]) -> ErrorStats {
    assert_eq!(
        test.len(),
        reference.len(),
        "images must have the same size"
    );
    let (mut rel, mut sq, mut n, mut non_finite) = (0.0f64, 0.0f64, 0usize, 0usize);
    for (&x, &r) in test.iter().zip(reference) {
        if !x.is_finite() {
            non_finite += 1;
            continue;
        }
        if !r.is_finite() {
            continue;
        }
        let (x, r) = (f64::from(x), f64::from(r));
        let d2 = (x - r) * (x - r);
        rel += d2 / (r * r + REL_MSE_EPSILON);
        sq += d2;
        n += 1;
    }
    let n = n.max(1) as f64;
    ErrorStats {
        rel_mse: rel / n,
        mse: sq / n,
        non_finite,
    }
}

/// Efficiency = 1 / (error × time) [Hua §7]; 0 when either is not positive and finite.
pub fn efficiency(error: f64, seconds: f64) -> f64 {
    let cost = error * seconds;
    if cost > 0.0 && cost.is_finite() {
        1.0 / cost
    } else {
        0.0
    }
}

/// Speedup of an estimator over a baseline: the ratio of their efficiencies.
pub fn speedup(error: f64, seconds: f64, base_error: f64, base_seconds: f64) -> f64 {
    let base = efficiency(base_error, base_seconds);
    if base > 0.0 {
        efficiency(error, seconds) / base
    } else {
        f64::NAN
    }
}

/// relMSE estimated without a reference (DESIGN §6): the mean over entries of
/// `Var[x] / (x² + ε)`, where `variance` is the variance **of the estimate** `x` (sample
/// variance divided by the sample count), per entry. For an unbiased estimator the expected
/// squared error equals that variance. Non-finite entries are skipped; `None` if the
/// lengths differ or nothing is finite.
pub fn estimated_rel_mse(estimate: &[f32], variance: &[f32]) -> Option<f64> {
    if estimate.len() != variance.len() {
        return None;
    }
    let (mut sum, mut n) = (0.0f64, 0usize);
    for (&x, &v) in estimate.iter().zip(variance) {
        if !x.is_finite() || !v.is_finite() || v < 0.0 {
            continue;
        }
        let x = f64::from(x);
        sum += f64::from(v) / (x * x + REL_MSE_EPSILON);
        n += 1;
    }
    (n > 0).then(|| sum / n as f64)
}

/// relMSE of **one** render estimated from `N ≥ 2` independent renders of the same job with
/// different seeds (DESIGN §6), with no reference noise in the numerator.
///
/// Per entry, the unbiased sample variance across the renders, `s² = Σ_i (x_i − x̄)²/(N − 1)`,
/// is an unbiased estimate of the variance of one render, which for an unbiased estimator is
/// its expected squared error. The result is the mean over entries of `s² / (r² + ε)` with
/// `r` the `reference` entry when given (only the normaliser: its noise does not add to the
/// error, unlike [`compare`] against a reference whose own error is a floor under every
/// figure), else `x̄`; and the mean of `s²` as the MSE. Unlike [`estimated_rel_mse`] it needs
/// no independence between the samples *within* a render, so it is right for stratified or
/// quasi-Monte Carlo samplers (independent seeds are independent randomisations). Entries
/// where any render or the reference is non-finite are skipped. `None` when fewer than two
/// renders are given, the lengths differ or no entry is finite.
pub fn seed_variance_error(renders: &[&[f32]], reference: Option<&[f32]>) -> Option<ErrorStats> {
    let first = renders.first()?;
    let len = first.len();
    if renders.len() < 2
        || renders.iter().any(|r| r.len() != len)
        || reference.is_some_and(|r| r.len() != len)
    {
        return None;
    }
    let n = renders.len() as f64;
    let (mut rel, mut sq, mut count, mut non_finite) = (0.0f64, 0.0f64, 0usize, 0usize);
    for e in 0..len {
        if renders.iter().any(|r| !r[e].is_finite()) {
            non_finite += 1;
            continue;
        }
        let mean = renders.iter().map(|r| f64::from(r[e])).sum::<f64>() / n;
        let r = match reference {
            Some(rf) if rf[e].is_finite() => f64::from(rf[e]),
            Some(_) => continue,
            None => mean,
        };
        let var = renders
            .iter()
            .map(|x| (f64::from(x[e]) - mean).powi(2))
            .sum::<f64>()
            / (n - 1.0);
        rel += var / (r * r + REL_MSE_EPSILON);
        sq += var;
        count += 1;
    }
    (count > 0).then(|| ErrorStats {
        rel_mse: rel / count as f64,
        mse: sq / count as f64,
        non_finite,
    })
}

#[cfg(test)]
mod tests {
    use rand::{Rng, SeedableRng};
    use rand_pcg::Pcg64;

    use super::*;

    /// Standard normal samples (Box–Muller) from a seeded PCG stream.
    fn normal(rng: &mut Pcg64) -> f64 {
        let (u, v): (f64, f64) = (rng.random(), rng.random());
        (-2.0 * (1.0 - u).ln()).sqrt() * (std::f64::consts::TAU * v).cos()
    }

    #[test]
    fn seed_variance_error_estimates_the_error_of_one_render() {
        // Renders = truth + independent N(0, σ²) noise: the expected relMSE of one render is
        // mean σ²/(r² + ε); the estimate is a weighted mean of χ²_{N−1}/(N−1) variables.
        let (m, n) = (20_000usize, 4usize);
        let truth: Vec<f32> = (0..m).map(|i| 0.2 + (i % 7) as f32 * 0.3).collect();
        let sigma = |i: usize| 0.05 + (i % 5) as f64 * 0.02;
        let mut g = Pcg64::seed_from_u64(0x1234_5678_9abc_def1);
        let renders: Vec<Vec<f32>> = (0..n)
            .map(|_| {
                (0..m)
                    .map(|i| (f64::from(truth[i]) + sigma(i) * normal(&mut g)) as f32)
                    .collect()
            })
            .collect();
        let views: Vec<&[f32]> = renders.iter().map(Vec::as_slice).collect();
        let w: Vec<f64> = (0..m)
            .map(|i| sigma(i).powi(2) / (f64::from(truth[i]).powi(2) + REL_MSE_EPSILON))
            .collect();
        let expected = w.iter().sum::<f64>() / m as f64;
        let est = seed_variance_error(&views, Some(&truth)).unwrap();
        // Standard deviation of a weighted mean of χ²_{N−1}/(N−1) variables, relative to its
        // expectation: sqrt(2/(N−1)) · sqrt(Σw²)/Σw. Five of them.
        let rel_sd = (2.0 / (n - 1) as f64).sqrt() * w.iter().map(|x| x * x).sum::<f64>().sqrt()
            / w.iter().sum::<f64>();
        let tol = 5.0 * rel_sd;
        assert!(
            (est.rel_mse / expected - 1.0).abs() < tol,
            "{} vs {expected} (tol {tol})",
            est.rel_mse
        );
        // Against a noisy reference the classic comparison pays the reference's error too;
        // the seed variance does not depend on the reference's noise beyond the normaliser.
        let noisy_ref = &renders[0];
        let classic = compare(&renders[1], noisy_ref).rel_mse;
        assert!(classic > 1.6 * expected, "{classic} vs {expected}");
        // Without a reference the normaliser is the renders' mean (the numerator is the same).
        let mean: Vec<f32> = (0..m)
            .map(|i| (renders.iter().map(|r| f64::from(r[i])).sum::<f64>() / n as f64) as f32)
            .collect();
        let free = seed_variance_error(&views, None).unwrap();
        let with_mean = seed_variance_error(&views, Some(&mean)).unwrap();
        assert_eq!(free.mse, est.mse);
        assert!((free.rel_mse / with_mean.rel_mse - 1.0).abs() < 1e-5);
    }

    #[test]
    fn seed_variance_error_needs_two_finite_renders_of_one_size() {
        let a = [1.0f32, 2.0];
        let b = [1.0f32, 2.5];
        assert!(seed_variance_error(&[&a], None).is_none());
        assert!(seed_variance_error(&[&a, &[1.0]], None).is_none());
        assert!(seed_variance_error(&[&a, &b], Some(&[1.0])).is_none());
        let e = seed_variance_error(&[&a, &b], None).unwrap();
        // Entry 0: no spread; entry 1: s² = 0.125 around 2.25.
        assert!((e.mse - 0.0625).abs() < 1e-12);
        assert!((e.rel_mse - 0.125 / (2.25 * 2.25 + 0.01) / 2.0).abs() < 1e-12);
        let nan = [f32::NAN, 2.0];
        let e = seed_variance_error(&[&a, &nan], None).unwrap();
        assert_eq!(e.non_finite, 1);
        assert!(seed_variance_error(&[&nan, &[f32::INFINITY, f32::NAN]], None).is_none());
    }

    #[test]
    fn estimated_rel_mse_is_variance_over_value_squared() {
        let e = estimated_rel_mse(&[1.0, 0.0, f32::NAN], &[0.5, 0.01, 1.0]).unwrap();
        assert!((e - (0.5 / 1.01 + 0.01 / 0.01) / 2.0).abs() < 1e-6);
        assert_eq!(estimated_rel_mse(&[1.0], &[]), None);
        assert_eq!(estimated_rel_mse(&[f32::NAN], &[1.0]), None);
    }

    #[test]
    fn identical_images_have_zero_error() {
        let img = [0.1f32, 0.5, 2.0, 0.0];
        let s = compare(&img, &img);
        assert_eq!((s.rel_mse, s.mse, s.non_finite), (0.0, 0.0, 0));
    }

    #[test]
    fn rel_mse_matches_definition_and_skips_non_finite() {
        let s = compare(&[1.0, f32::NAN, 0.0], &[0.0, 1.0, 1.0]);
        let expected = (1.0 / 0.01 + 1.0 / 1.01) / 2.0;
        assert!((s.rel_mse - expected).abs() < 1e-12);
        assert_eq!(s.non_finite, 1);
    }

    #[test]
    fn halving_error_at_equal_time_is_a_2x_speedup() {
        assert!((speedup(0.5, 1.0, 1.0, 1.0) - 2.0).abs() < 1e-12);
    }
}
