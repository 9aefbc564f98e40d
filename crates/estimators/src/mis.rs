//! Multiple importance sampling weights.
//!
//! With one sample per technique, the balance heuristic weight of technique `a` is
//! `p_a / Σ p_t` and the power heuristic (β = 2) is `p_a² / Σ p_t²` (Veach 1997). Both are
//! written so that `0/0` (a direction no technique can sample) gives weight 0, not NaN.

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

#[cfg(test)]
mod tests {
    use super::*;

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
