//! Piecewise-constant 1-D distribution over `n` discrete entries (tabulated CDF + binary
//! search), used to pick a light ∝ power, a triangle ∝ area and an env-map cell ∝ energy.
//!
//! Contract: `sample(u)` for `u ∈ [0, 1)` returns an entry `i` with `pmf(i) > 0`, that pmf
//! (a probability, not a density) and `u` remapped to `[0, 1)` inside the entry, so that
//! the remapped value can drive a further continuous choice. `pmf(i)` is exactly the CDF
//! step that `sample` uses, so a sampled entry's pmf and a later `pmf(i)` query agree
//! bit-for-bit. Sampling is `O(log n)` and allocation-free.

/// A discrete distribution ∝ non-negative weights.
#[derive(Clone, Debug, PartialEq)]
pub struct Distribution1D {
    /// `n + 1` non-decreasing values, `cdf[0] = 0`, `cdf[n] = 1`.
    cdf: Vec<f32>,
    /// Sum of the weights (before normalisation), in f64.
    total: f64,
}

/// The largest f32 below 1, the upper end of every `[0, 1)` sample.
pub(crate) const ONE_MINUS_EPSILON: f32 = 1.0 - f32::EPSILON / 2.0;

impl Distribution1D {
    /// Builds the distribution. Negative and non-finite weights count as 0. Returns `None`
    /// when there is nothing to sample (empty list or zero total weight).
    pub fn new(weights: impl IntoIterator<Item = f64>) -> Option<Self> {
        let mut sums = vec![0.0f64];
        let mut total = 0.0f64;
        for w in weights {
            let w = if w.is_finite() && w > 0.0 { w } else { 0.0 };
            total += w;
            sums.push(total);
        }
        if sums.len() < 2 || total <= 0.0 || !total.is_finite() {
            return None;
        }
        let inv = 1.0 / total;
        let mut cdf: Vec<f32> = sums.iter().map(|s| (s * inv) as f32).collect();
        // Exact end points, whatever the rounding of the running sum.
        cdf[0] = 0.0;
        if let Some(last) = cdf.last_mut() {
            *last = 1.0;
        }
        Some(Self { cdf, total })
    }

    /// Number of entries.
    #[inline]
    pub fn len(&self) -> usize {
        self.cdf.len() - 1
    }

    /// Always false: an empty distribution is never built.
    #[inline]
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Sum of the weights the distribution was built from.
    #[inline]
    pub fn total(&self) -> f64 {
        self.total
    }

    /// Probability of entry `i` (0 out of range).
    #[inline]
    pub fn pmf(&self, i: usize) -> f32 {
        cdf_pmf(&self.cdf, i)
    }

    /// Picks an entry: `(index, pmf, u remapped to [0, 1) within the entry)`.
    #[inline]
    pub fn sample(&self, u: f32) -> (usize, f32, f32) {
        cdf_sample(&self.cdf, u)
    }

    /// The normalised CDF (`len() + 1` entries), e.g. to pack several into one table.
    #[inline]
    pub fn cdf(&self) -> &[f32] {
        &self.cdf
    }
}

/// [`Distribution1D::pmf`] on a bare normalised CDF slice.
#[inline]
pub(crate) fn cdf_pmf(cdf: &[f32], i: usize) -> f32 {
    match (cdf.get(i), cdf.get(i + 1)) {
        (Some(a), Some(b)) => b - a,
        _ => 0.0,
    }
}

/// [`Distribution1D::sample`] on a bare normalised CDF slice (`cdf[0] = 0`, last = 1,
/// at least 2 entries).
#[inline]
pub(crate) fn cdf_sample(cdf: &[f32], u: f32) -> (usize, f32, f32) {
    let n = cdf.len() - 1;
    let u = if u >= 0.0 {
        u.min(ONE_MINUS_EPSILON)
    } else {
        0.0
    };
    // First i with cdf[i + 1] > u; since cdf[n] = 1 > u it exists and has a non-zero step.
    let i = cdf[1..].partition_point(|&c| c <= u).min(n - 1);
    let (lo, hi) = (cdf[i], cdf[i + 1]);
    let pmf = hi - lo;
    let remapped = if pmf > 0.0 {
        ((u - lo) / pmf).clamp(0.0, ONE_MINUS_EPSILON)
    } else {
        0.0
    };
    (i, pmf, remapped)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rejects_empty_and_zero_weights() {
        assert!(Distribution1D::new([]).is_none());
        assert!(Distribution1D::new([0.0, 0.0]).is_none());
        assert!(Distribution1D::new([f64::NAN, -1.0]).is_none());
    }

    #[test]
    fn skips_zero_entries_and_pmf_sums_to_one() {
        let d = Distribution1D::new([0.0, 1.0, 0.0, 3.0, 0.0]).unwrap();
        let sum: f32 = (0..d.len()).map(|i| d.pmf(i)).sum();
        assert!((sum - 1.0).abs() < 1e-6);
        for k in 0..1000 {
            let u = k as f32 / 1000.0;
            let (i, pmf, r) = d.sample(u);
            assert!(
                i == 1 || i == 3,
                "sampled a zero-weight entry {i} at u = {u}"
            );
            assert_eq!(pmf, d.pmf(i));
            assert!((0.0..1.0).contains(&r));
        }
        assert_eq!(d.sample(0.0).0, 1);
        assert_eq!(d.sample(1.0).0, 3);
        assert_eq!(d.sample(0.2499).0, 1);
        assert_eq!(d.sample(0.2501).0, 3);
        assert_eq!(d.pmf(7), 0.0);
    }

    #[test]
    fn remapped_u_is_uniform_within_the_entry() {
        let d = Distribution1D::new([1.0, 1.0]).unwrap();
        let (i, _, r) = d.sample(0.75);
        assert_eq!(i, 1);
        assert!((r - 0.5).abs() < 1e-6);
    }
}
