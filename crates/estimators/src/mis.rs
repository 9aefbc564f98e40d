//! Multiple importance sampling and mixture helpers.
//!
//! With one sample per technique, the balance heuristic weight of technique `a` is
//! `p_a / Σ p_t` and the power heuristic (β = 2) is `p_a² / Σ p_t²` (Veach 1997). Both are
//! written so that `0/0` (a direction no technique can sample) gives weight 0, not NaN.
//!
//! # Contracts
//! - Every pdf passed to one call must be expressed in the **same measure** (solid angle or
//!   area on the light); the helpers never convert.
//! - The *effective mixture density* of `M` MIS techniques, technique `m` taking `n_m`
//!   samples from a mixture with selection probabilities `c_{m,t}` of pdfs `p_{m,t}`, is
//!   `p(x) = Σ_m n_m Σ_t c_{m,t} p_{m,t}(x)` [Hua eq. 16]. It is *not* normalised: it
//!   integrates to `Σ_m n_m`. The per-sample balance-heuristic value is then
//!   `F = f(x) / p(x)` and the vertex estimate is the sum of `F` over all its samples
//!   [Hua eq. 6].
//! - A CV component `λ_i` is a mixture of some of those pdfs with weights proportional to
//!   their effective sample counts `n_k c_k` [Hua eq. 18], so that `∫ λ_i = 1`;
//!   [`component_mixture_weights`] computes those weights.
//! - Deterministic mixture sampling [Fan §4] draws `n_j ≈ N α_j` samples from component
//!   `j`; [`deterministic_counts`] rounds by largest remainder so the counts sum to `N`.

/// Balance-heuristic weight of technique `a` against technique `b` (one sample each).
#[inline]
pub fn balance(pdf_a: f32, pdf_b: f32) -> f32 {
    let sum = pdf_a + pdf_b;
    if sum > 0.0 { pdf_a / sum } else { 0.0 }
}

/// Power-heuristic (β = 2) weight of technique `a` against technique `b` (one sample each).
#[inline]
pub fn power(pdf_a: f32, pdf_b: f32) -> f32 {
    let (a2, b2) = (pdf_a * pdf_a, pdf_b * pdf_b);
    let sum = a2 + b2;
    if sum > 0.0 {
        a2 / sum
    } else if pdf_a.is_infinite() {
        1.0
    } else {
        0.0
    }
}

/// Balance-heuristic weights of many techniques: `w_i = n_i p_i / Σ_j n_j p_j` [Hua eq. 5].
///
/// `effective` holds the products `n_i p_i`; `out` receives the weights (same length, else
/// only the common prefix is written). If every product is zero, all weights are zero.
pub fn balance_weights(effective: &[f64], out: &mut [f64]) {
    let sum: f64 = effective.iter().sum();
    for (w, &e) in out.iter_mut().zip(effective) {
        *w = if sum > 0.0 { e / sum } else { 0.0 };
    }
}

/// Power-heuristic weights of many techniques with exponent `beta` (Veach uses 2):
/// `w_i = (n_i p_i)^β / Σ_j (n_j p_j)^β`. All zero when every product is zero.
pub fn power_weights(effective: &[f64], beta: f64, out: &mut [f64]) {
    // Normalise by the largest entry first so that `powf` cannot overflow for large pdfs.
    let max = effective.iter().fold(0.0f64, |m, &e| m.max(e));
    if !(max > 0.0) || !max.is_finite() {
        for (w, &e) in out.iter_mut().zip(effective) {
            *w = if max.is_infinite() && e.is_infinite() {
                1.0
            } else {
                0.0
            };
        }
        if max.is_infinite() {
            let infinite = effective.iter().filter(|e| e.is_infinite()).count() as f64;
            out.iter_mut().for_each(|w| *w /= infinite);
        }
        return;
    }
    let sum: f64 = effective.iter().map(|&e| (e / max).powf(beta)).sum();
    for (w, &e) in out.iter_mut().zip(effective) {
        *w = (e / max).powf(beta) / sum;
    }
}

/// Density of one mixture: `Σ_t c_t p_t(x)` (pairs of selection probability and pdf).
#[inline]
pub fn mixture_pdf(selection: &[f64], pdfs: &[f64]) -> f64 {
    selection.iter().zip(pdfs).map(|(c, p)| c * p).sum()
}

/// Effective density of an MIS combination of mixtures [Hua eq. 16]:
/// `p(x) = Σ_m n_m q_m(x)` where `q_m` is the (already mixed) density of technique `m`
/// (see [`mixture_pdf`]) and `n_m` its sample count per estimate.
#[inline]
pub fn effective_density(counts: &[f64], technique_pdfs: &[f64]) -> f64 {
    counts.iter().zip(technique_pdfs).map(|(n, q)| n * q).sum()
}

/// Weights of the pdfs inside one CV component [Hua eq. 18]: `n_k c_k / Σ_k' n_k' c_k'`,
/// so that the component `λ_i = Σ_k weight_k p_k` integrates to one.
///
/// Returns `None` if the effective counts are not all finite and non-negative or sum to 0.
pub fn component_mixture_weights(effective_counts: &[f64]) -> Option<Vec<f64>> {
    if effective_counts.iter().any(|c| !c.is_finite() || *c < 0.0) {
        return None;
    }
    let sum: f64 = effective_counts.iter().sum();
    (sum > 0.0).then(|| effective_counts.iter().map(|c| c / sum).collect())
}

/// Deterministic mixture sample counts [Fan §4]: `n_j ≈ N α_j`, rounded by largest
/// remainder so that `Σ n_j = N` exactly (ties go to the lower index).
///
/// Returns `None` when the weights are not finite and non-negative or sum to zero.
/// Weights need not be normalised.
pub fn deterministic_counts(weights: &[f64], total: usize) -> Option<Vec<usize>> {
    if weights.iter().any(|w| !w.is_finite() || *w < 0.0) {
        return None;
    }
    let sum: f64 = weights.iter().sum();
    if !(sum > 0.0) {
        return None;
    }
    let ideal: Vec<f64> = weights.iter().map(|w| w / sum * total as f64).collect();
    let mut counts: Vec<usize> = ideal.iter().map(|x| x.floor() as usize).collect();
    let assigned: usize = counts.iter().sum();
    let mut order: Vec<usize> = (0..weights.len()).collect();
    // Largest fractional part first; stable sort keeps the lower index first on ties.
    order.sort_by(|&a, &b| {
        let fa = ideal[a] - ideal[a].floor();
        let fb = ideal[b] - ideal[b].floor();
        fb.total_cmp(&fa)
    });
    for &j in order.iter().cycle().take(total.saturating_sub(assigned)) {
        counts[j] += 1;
    }
    Some(counts)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn many_technique_weights_sum_to_one() {
        let e = [0.3, 2.0, 1e-12, 5.0];
        let mut w = [0.0; 4];
        balance_weights(&e, &mut w);
        assert!((w.iter().sum::<f64>() - 1.0).abs() < 1e-12);
        assert!((w[1] - 2.0 / 7.300000000001).abs() < 1e-9);
        power_weights(&e, 2.0, &mut w);
        assert!((w.iter().sum::<f64>() - 1.0).abs() < 1e-12);
        power_weights(&[1e200, 1e200], 2.0, &mut w[..2]);
        assert_eq!(&w[..2], &[0.5, 0.5]);
        power_weights(&[0.0, 0.0], 2.0, &mut w[..2]);
        assert_eq!(&w[..2], &[0.0, 0.0]);
    }

    #[test]
    fn effective_density_is_counts_times_mixtures() {
        let q_bsdf = mixture_pdf(&[0.25, 0.75], &[2.0, 4.0]);
        assert_eq!(q_bsdf, 3.5);
        assert_eq!(effective_density(&[1.0, 2.0], &[q_bsdf, 0.5]), 4.5);
    }

    #[test]
    fn deterministic_counts_sum_to_total() {
        assert_eq!(
            deterministic_counts(&[0.5, 0.25, 0.25], 64),
            Some(vec![32, 16, 16])
        );
        assert_eq!(
            deterministic_counts(&[1.0, 1.0, 1.0], 10),
            Some(vec![4, 3, 3])
        );
        assert_eq!(deterministic_counts(&[0.0, 0.0], 10), None);
        assert_eq!(deterministic_counts(&[f64::NAN], 10), None);
        let c = deterministic_counts(&[0.1, 0.7, 0.2, 1e-9], 7).unwrap();
        assert_eq!(c.iter().sum::<usize>(), 7);
        assert_eq!(
            component_mixture_weights(&[1.0, 3.0]),
            Some(vec![0.25, 0.75])
        );
        assert_eq!(component_mixture_weights(&[0.0]), None);
    }

    #[test]
    fn weights_of_two_techniques_sum_to_one() {
        for &(a, b) in &[(1.0f32, 2.0f32), (1e-20, 3.0), (5.0, 0.0), (0.3, 0.3)] {
            assert!((balance(a, b) + balance(b, a) - 1.0).abs() < 1e-6);
            assert!((power(a, b) + power(b, a) - 1.0).abs() < 1e-6);
        }
    }

    #[test]
    fn zero_pdfs_give_zero_weight_not_nan() {
        assert_eq!(balance(0.0, 0.0), 0.0);
        assert_eq!(power(0.0, 0.0), 0.0);
    }
}
