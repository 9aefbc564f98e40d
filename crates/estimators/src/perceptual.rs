//! Fan's perceptual error [Fan eq. 12] with the threshold-versus-intensity function of
//! Ferwerda et al. 1996.
//!
//! `E = sqrt( 1/n Σ_pixels ((L − L_true) / tvi(L_true))² )` on luminance.
//!
//! # Contracts
//! - Images are interleaved RGB (`3 × n` values); luminance is Rec. 709
//!   `Y = 0.2126 R + 0.7152 G + 0.0722 B`, multiplied by `nits_per_unit` to get cd/m²
//!   (the tvi function is defined on absolute luminance; 1.0 treats one unit as 1 cd/m²).
//! - [`tvi`] is the photopic (cone) branch of Ferwerda et al.: `log10 ΔL = −0.72` for
//!   `log10 L ≤ −2.6`, `log10 L − 1.255` for `log10 L ≥ 1.9`, else
//!   `(0.249 log10 L + 0.65)^2.7 − 0.72`. Non-positive luminance uses the lower plateau.
//! - Pixels where either luminance is not finite are skipped.

/// Rec. 709 luminance of an RGB triple.
#[inline]
pub fn luminance(rgb: [f64; 3]) -> f64 {
    0.2126 * rgb[0] + 0.7152 * rgb[1] + 0.0722 * rgb[2]
}

/// Photopic threshold-versus-intensity `ΔL(L)` in cd/m² (Ferwerda et al. 1996).
pub fn tvi(luminance: f64) -> f64 {
    let lg = if luminance > 0.0 {
        luminance.log10()
    } else {
        f64::NEG_INFINITY
    };
    let log_threshold = if lg <= -2.6 {
        -0.72
    } else if lg >= 1.9 {
        lg - 1.255
    } else {
        (0.249 * lg + 0.65).powf(2.7) - 0.72
    };
    10f64.powf(log_threshold)
}

/// Perceptual RMS error of `test` against `reference` [Fan eq. 12]; `None` if the slices
/// differ in length, are not RGB triples, or no pixel is finite.
pub fn perceptual_error(test: &[f32], reference: &[f32], nits_per_unit: f64) -> Option<f64> {
    if test.len() != reference.len() || !test.len().is_multiple_of(3) {
        return None;
    }
    let (mut sum, mut n) = (0.0f64, 0usize);
    for (t, r) in test.chunks_exact(3).zip(reference.chunks_exact(3)) {
        let lt = luminance([t[0], t[1], t[2]].map(f64::from)) * nits_per_unit;
        let lr = luminance([r[0], r[1], r[2]].map(f64::from)) * nits_per_unit;
        if !lt.is_finite() || !lr.is_finite() {
            continue;
        }
        let e = (lt - lr) / tvi(lr);
        sum += e * e;
        n += 1;
    }
    (n > 0).then(|| (sum / n as f64).sqrt())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tvi_branches_are_continuous_and_match_ferwerda() {
        assert!((tvi(1e-4) - 10f64.powf(-0.72)).abs() < 1e-12);
        assert!((tvi(1000.0) - 10f64.powf(3.0 - 1.255)).abs() < 1e-9);
        assert!((tvi(1.0) - 10f64.powf(0.65f64.powf(2.7) - 0.72)).abs() < 1e-12);
        for edge in [-2.6f64, 1.9] {
            let (a, b) = (tvi(10f64.powf(edge - 1e-9)), tvi(10f64.powf(edge + 1e-9)));
            // The published fit has a 0.7 % step at log L = 1.9.
            assert!(
                (a - b).abs() < 1e-2 * a,
                "discontinuity at 10^{edge}: {a} {b}"
            );
        }
        assert_eq!(tvi(0.0), tvi(-5.0));
        // Monotone in luminance.
        let mut prev = 0.0;
        for i in -40..40 {
            let t = tvi(10f64.powf(f64::from(i) / 10.0));
            assert!(t >= 0.99 * prev);
            prev = t;
        }
    }

    #[test]
    fn perceptual_error_matches_definition() {
        let reference = [1.0f32, 1.0, 1.0, 0.0, 0.0, 0.0];
        let test = [1.5f32, 1.5, 1.5, 0.0, 0.0, 0.0];
        let e = perceptual_error(&test, &reference, 1.0).unwrap();
        let expected = ((0.5 / tvi(1.0)).powi(2) / 2.0).sqrt();
        assert!((e - expected).abs() < 1e-6 * expected);
        assert_eq!(perceptual_error(&reference, &reference, 1.0), Some(0.0));
        assert_eq!(perceptual_error(&test[..5], &reference[..5], 1.0), None);
        assert_eq!(perceptual_error(&[f32::NAN; 3], &[1.0; 3], 1.0), None);
    }
}
