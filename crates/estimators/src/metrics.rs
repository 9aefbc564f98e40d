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

#[cfg(test)]
mod tests {
    use super::*;

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
