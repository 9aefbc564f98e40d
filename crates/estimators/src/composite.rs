//! Variance-minimising combinations of estimators [Rou §3.2] and the re-rendering
//! composite [Rou §4].
//!
//! # The `rerender` estimator
//! A re-rendering job renders the edited scene with paths that carry both material
//! settings, producing per pixel `⟨F⟩₁` (new), `⟨H⟩₁` (old, same paths) and
//! `⟨D⟩₁ = ⟨F⟩₁ − ⟨H⟩₁`, and reuses the finished control image `⟨H⟩₀`. The CV estimator
//! `⟨F⟩* = ⟨D⟩₁ + ⟨H⟩₀` [Rou eq. 13] and the plain `⟨F⟩₁` are combined with Keller–Olkin
//! weights from their covariance [Rou eq. 11, 14–16].
//!
//! | name | type | default | meaning |
//! |---|---|---|---|
//! | `control_job` | job id | — | finished job of the same scene (the control image `⟨H⟩₀`) |
//! | `prefilter` | bool | true | NL-means prefilter of the variances ([`crate::filter`]) |
//! | `unbiased` | bool | false | cross-weight two half buffers ([`rerender_image_cross`]) |
//!
//! ```json
//! { "kind": "rerender", "control_job": "j-123", "prefilter": true, "unbiased": false }
//! ```
//!
//! # Contracts
//! - Variances are variances **of the estimates** (sample variance / sample count), one
//!   scalar per pixel (e.g. the channel mean); values are RGB.
//! - Weights always sum to one. Fallback order: Keller–Olkin when the covariance matrix is
//!   positive semi-definite and invertible; inverse-variance weights [Rou eq. 10] when it is
//!   not PSD (eigenvalue check) or singular; estimators with zero variance share the weight
//!   when some (not all) variances vanish; **sample-rate weights** (∝ samples per pixel)
//!   when every variance that matters is zero [Rou §4.1].
//! - With statistics computed from the same samples as the values, the composite is biased
//!   (slightly); [`rerender_image_cross`] uses the other half buffer's statistics and is
//!   unbiased [Rou §4.1].
//!
//! # The phases of a CV job
//! A phased CV job ([`crate::spec::PhasedEstimator`]) keeps its surrogate and training
//! samples in the image [Hua §6.1], but they are `path`'s samples: where the fits pay off, a
//! render-phase sample has a fraction of their variance, and the plain average of all
//! samples [Hua §6.1] gives the noisier ones the weight of their count (16 training samples
//! of 128 made `cms`'s equal-sample speed-up on colour-lamp at depth 5 2.13× instead of the
//! 2.5× of its render samples). [`phase_weight`] and [`combine_phases`] combine each pixel's
//! *uncontrolled* mean (surrogate and training samples) and *controlled* mean (render
//! samples) with **one image-wide weight**, the inverse-variance weights [Rou eq. 10] of the
//! two estimates' summed relative variances — the weight minimising the image's estimated
//! relMSE (DESIGN §6) among weights shared by all pixels. One weight from the whole image's
//! sums is nearly independent of any pixel's samples, so the bias that per-pixel weights from
//! the same samples carry ([`rerender_image_cross`]) is negligible (`render`'s `cv_unbiased`
//! tests); per-block weights (blocks of 8, 16 and 64 pixels) gained 0–4 % more on the test
//! scenes and were not kept. [`phase_weight`] over all pixels in row-major order, then
//! [`combine_phases`] per pixel, is the one combination: the farm's assembly calls it as
//! [`combine_phase_images`], the renderer's in-process driver on its films' sums in place
//! (`render::integrator::cv::combine_phase_films`); the workers' tests hold the two images
//! to the same bits.

use std::borrow::Borrow;

use nalgebra::{DMatrix, DVector};

use crate::surrogate::PixelMoments;
use thiserror::Error;

/// Which rule produced a set of weights.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum WeightScheme {
    /// `w = eΣ⁻¹ / (eΣ⁻¹eᵀ)` [Rou eq. 11].
    KellerOlkin,
    /// `w_i ∝ 1/σ_i²` [Rou eq. 10].
    InverseVariance,
    /// Only the zero-variance estimators, equally weighted.
    ZeroVariance,
    /// `w_i ∝` sample rate (all relevant variances zero) [Rou §4.1].
    SampleRate,
}

/// Weights of a composite estimator.
#[derive(Clone, Debug, PartialEq)]
pub struct CompositeWeights {
    /// One weight per estimator; they sum to one.
    pub weights: Vec<f64>,
    /// The rule used.
    pub scheme: WeightScheme,
    /// Predicted variance `wᵀΣw` of the composite (under the model used).
    pub variance: f64,
}

/// Invalid inputs of the composite helpers.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Error)]
pub enum CompositeError {
    /// No estimator, or slices of different lengths / a non-square matrix.
    #[error("sizes do not match")]
    SizeMismatch,
    /// NaN/Inf, a negative variance, or non-positive sample rates.
    #[error("invalid variance, covariance or sample rate")]
    InvalidValue,
}

fn sample_rate_weights(rates: &[f64], variance: f64) -> Result<CompositeWeights, CompositeError> {
    let total: f64 = rates.iter().sum();
    if rates.iter().any(|r| !r.is_finite() || *r < 0.0) || !(total > 0.0) {
        return Err(CompositeError::InvalidValue);
    }
    Ok(CompositeWeights {
        weights: rates.iter().map(|r| r / total).collect(),
        scheme: WeightScheme::SampleRate,
        variance,
    })
}

/// Inverse-variance weights of independent estimators [Rou eq. 10].
///
/// Zero variances: the zero-variance estimators share the weight equally; all zero: the
/// sample-rate weights from `rates`.
pub fn inverse_variance_weights(
    variances: &[f64],
    rates: &[f64],
) -> Result<CompositeWeights, CompositeError> {
    if variances.is_empty() || variances.len() != rates.len() {
        return Err(CompositeError::SizeMismatch);
    }
    if variances.iter().any(|v| !v.is_finite() || *v < 0.0) {
        return Err(CompositeError::InvalidValue);
    }
    let zeros = variances.iter().filter(|&&v| v == 0.0).count();
    if zeros == variances.len() {
        return sample_rate_weights(rates, 0.0);
    }
    if zeros > 0 {
        let w = 1.0 / zeros as f64;
        let weights = variances
            .iter()
            .map(|&v| if v == 0.0 { w } else { 0.0 })
            .collect();
        return Ok(CompositeWeights {
            weights,
            scheme: WeightScheme::ZeroVariance,
            variance: 0.0,
        });
    }
    // Normalise by the smallest variance first so that 1/σ² cannot overflow.
    let min = variances.iter().copied().fold(f64::INFINITY, f64::min);
    let inv: Vec<f64> = variances.iter().map(|v| min / v).collect();
    let total: f64 = inv.iter().sum();
    let weights: Vec<f64> = inv.iter().map(|x| x / total).collect();
    Ok(CompositeWeights {
        weights,
        scheme: WeightScheme::InverseVariance,
        variance: min / total,
    })
}

/// Keller–Olkin weights from a `k × k` covariance matrix (row-major) [Rou eq. 11], with the
/// fallbacks of the module contract. The matrix is symmetrised first.
pub fn keller_olkin_weights(
    covariance: &[f64],
    rates: &[f64],
) -> Result<CompositeWeights, CompositeError> {
    let k = rates.len();
    if k == 0 || covariance.len() != k * k {
        return Err(CompositeError::SizeMismatch);
    }
    if covariance.iter().any(|c| !c.is_finite()) {
        return Err(CompositeError::InvalidValue);
    }
    let diag: Vec<f64> = (0..k).map(|i| covariance[i * k + i]).collect();
    if diag.iter().any(|&d| d < 0.0) {
        return Err(CompositeError::InvalidValue);
    }
    if diag.contains(&0.0) {
        // A zero-variance estimator is exact (and uncorrelated with anything).
        return inverse_variance_weights(&diag, rates);
    }
    // Scale to unit diagonal (correlation matrix) for the PSD check and the solve.
    let s: Vec<f64> = diag.iter().map(|d| 1.0 / d.sqrt()).collect();
    let corr = DMatrix::from_fn(k, k, |i, j| {
        0.5 * (covariance[i * k + j] + covariance[j * k + i]) * s[i] * s[j]
    });
    let eig = corr.clone().symmetric_eigenvalues();
    let tol = 1e-12 * k as f64;
    if eig.iter().any(|&e| e < -tol) || eig.iter().any(|e| !e.is_finite()) {
        return inverse_variance_weights(&diag, rates);
    }
    let Some(chol) = corr.clone().cholesky() else {
        return inverse_variance_weights(&diag, rates);
    };
    let l = chol.l_dirty().diagonal();
    let (lo, hi) = l.iter().fold((f64::INFINITY, 0.0f64), |(a, b), d| {
        (a.min(d * d), b.max(d * d))
    });
    if !(lo > 1e-12 * hi) {
        return inverse_variance_weights(&diag, rates);
    }
    // Σ = S⁻¹ C S⁻¹ ⇒ Σ⁻¹ e = S C⁻¹ S e.
    let se = DVector::from_iterator(k, s.iter().copied());
    let x = chol.solve(&se).component_mul(&se);
    let total = x.sum();
    if !(total > 0.0) || !total.is_finite() {
        return inverse_variance_weights(&diag, rates);
    }
    let weights: Vec<f64> = x.iter().map(|v| v / total).collect();
    let mut variance = 0.0;
    for i in 0..k {
        for j in 0..k {
            variance += weights[i] * weights[j] * covariance[i * k + j];
        }
    }
    Ok(CompositeWeights {
        weights,
        scheme: WeightScheme::KellerOlkin,
        variance: variance.max(0.0),
    })
}

/// Per-pixel statistics of a re-rendering [Rou §4]: means (RGB) and variances of the means.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RerenderPixel {
    /// `⟨F⟩₁`: new materials, new paths.
    pub f1: [f64; 3],
    /// `⟨D⟩₁ = ⟨F⟩₁ − ⟨H⟩₁` on the same paths.
    pub d1: [f64; 3],
    /// `⟨H⟩₀`: the control image.
    pub h0: [f64; 3],
    /// `Var⟨F⟩₁`.
    pub var_f1: f64,
    /// `Var⟨H⟩₁`.
    pub var_h1: f64,
    /// `Var⟨D⟩₁`.
    pub var_d1: f64,
    /// `Var⟨H⟩₀`.
    pub var_h0: f64,
    /// Samples per pixel of the new render (`n`).
    pub spp_new: f64,
    /// Samples per pixel of the control render (`m`).
    pub spp_control: f64,
}

/// Weights `(w*, w₁)` for `⟨F⟩*` and `⟨F⟩₁` [Rou eq. 11, 14–16].
///
/// `Var⟨F⟩* = Var⟨D⟩₁ + Var⟨H⟩₀` (eq. 14), `Cov(⟨F⟩*, ⟨F⟩₁) = Var⟨F⟩₁ − Cov(⟨H⟩₁, ⟨F⟩₁)`
/// (eq. 15) with `Cov(⟨H⟩₁, ⟨F⟩₁) = (Var⟨F⟩₁ + Var⟨H⟩₁ − Var⟨D⟩₁)/2` (eq. 16). When
/// `Var⟨F⟩₁` and `Var⟨D⟩₁` are both zero the sample-rate weights `(m, n)/(m + n)` are used
/// (the covariance weights would discard the CV estimator).
pub fn rerender_weights(px: &RerenderPixel) -> Result<CompositeWeights, CompositeError> {
    let vars = [px.var_f1, px.var_h1, px.var_d1, px.var_h0];
    if vars.iter().any(|v| !v.is_finite() || *v < 0.0) {
        return Err(CompositeError::InvalidValue);
    }
    let rates = [px.spp_control, px.spp_new];
    if px.var_f1 == 0.0 && px.var_d1 == 0.0 {
        return sample_rate_weights(
            &rates,
            px.var_h0 * (px.spp_control / (px.spp_control + px.spp_new)).powi(2),
        );
    }
    let var_star = px.var_d1 + px.var_h0;
    let cov_hf = 0.5 * (px.var_f1 + px.var_h1 - px.var_d1);
    let cov = px.var_f1 - cov_hf;
    keller_olkin_weights(&[var_star, cov, cov, px.var_f1], &rates)
}

/// The composite value `w* (⟨D⟩₁ + ⟨H⟩₀) + w₁ ⟨F⟩₁` of one pixel and its weights.
pub fn rerender_pixel(px: &RerenderPixel) -> Result<([f64; 3], CompositeWeights), CompositeError> {
    let w = rerender_weights(px)?;
    let v = std::array::from_fn(|c| w.weights[0] * (px.d1[c] + px.h0[c]) + w.weights[1] * px.f1[c]);
    Ok((v, w))
}

/// Borrowed re-rendering buffers of an image (`n` pixels; RGB interleaved values, one
/// variance per pixel).
#[derive(Clone, Copy, Debug)]
pub struct RerenderBuffers<'a> {
    /// `⟨F⟩₁`.
    pub f1: &'a [f32],
    /// `⟨D⟩₁`.
    pub d1: &'a [f32],
    /// `⟨H⟩₀`.
    pub h0: &'a [f32],
    /// `Var⟨F⟩₁`.
    pub var_f1: &'a [f32],
    /// `Var⟨H⟩₁`.
    pub var_h1: &'a [f32],
    /// `Var⟨D⟩₁`.
    pub var_d1: &'a [f32],
    /// `Var⟨H⟩₀`.
    pub var_h0: &'a [f32],
    /// Samples per pixel of the new render.
    pub spp_new: f64,
    /// Samples per pixel of the control render.
    pub spp_control: f64,
}

impl RerenderBuffers<'_> {
    fn pixels(&self) -> Result<usize, CompositeError> {
        let n = self.var_f1.len();
        let ok = [self.f1, self.d1, self.h0].iter().all(|b| b.len() == 3 * n)
            && [self.var_h1, self.var_d1, self.var_h0]
                .iter()
                .all(|b| b.len() == n);
        if ok {
            Ok(n)
        } else {
            Err(CompositeError::SizeMismatch)
        }
    }

    fn pixel(&self, values: &Self, i: usize) -> RerenderPixel {
        let rgb = |b: &[f32]| [0, 1, 2].map(|c| f64::from(b[3 * i + c]));
        RerenderPixel {
            f1: rgb(values.f1),
            d1: rgb(values.d1),
            h0: rgb(values.h0),
            var_f1: f64::from(self.var_f1[i]),
            var_h1: f64::from(self.var_h1[i]),
            var_d1: f64::from(self.var_d1[i]),
            var_h0: f64::from(self.var_h0[i]),
            spp_new: self.spp_new,
            spp_control: self.spp_control,
        }
    }
}

/// Composite re-rendered image (values and statistics from the same buffers).
pub fn rerender_image(b: &RerenderBuffers<'_>) -> Result<Vec<f32>, CompositeError> {
    let n = b.pixels()?;
    let mut out = Vec::with_capacity(3 * n);
    for i in 0..n {
        let (v, _) = rerender_pixel(&b.pixel(b, i))?;
        out.extend(v.map(|x| x as f32));
    }
    Ok(out)
}

/// Unbiased cross-weighted composite [Rou §4.1]: half buffer `a` weighted with `b`'s
/// statistics and vice versa, averaged.
pub fn rerender_image_cross(
    a: &RerenderBuffers<'_>,
    b: &RerenderBuffers<'_>,
) -> Result<Vec<f32>, CompositeError> {
    let n = a.pixels()?;
    if b.pixels()? != n {
        return Err(CompositeError::SizeMismatch);
    }
    let mut out = Vec::with_capacity(3 * n);
    for i in 0..n {
        let (va, _) = rerender_pixel(&b.pixel(a, i))?;
        let (vb, _) = rerender_pixel(&a.pixel(b, i))?;
        out.extend((0..3).map(|c| (0.5 * (va[c] + vb[c])) as f32));
    }
    Ok(out)
}

/// The image-wide weight of the uncontrolled means ([module docs](self#the-phases-of-a-cv-job)):
/// with `A = Σ_{p,c} Var[ū_pc] / (m_pc² + ε)` and `B` the same for the controlled means
/// (`m` the pixel's plain mean of all its samples, `ε` =
/// [`crate::metrics::REL_MSE_EPSILON`]), the inverse-variance weight `B / (A + B)`
/// [Rou eq. 10] ([`inverse_variance_weights`], whose zero-variance and sample-rate rules
/// apply). Pixels with fewer than 2 samples in either set are left out. `None` when no pixel
/// counts or a sum is not finite: then the sets are merged plainly.
///
/// Pixels are summed in the iterator's order: the same order gives the same bits. (The
/// pairs may be references or values, e.g. sums read out of a film on the fly.)
pub fn phase_weight<U: Borrow<PixelMoments>, C: Borrow<PixelMoments>>(
    pixels: impl IntoIterator<Item = (U, C)>,
) -> Option<f64> {
    let eps = crate::metrics::REL_MSE_EPSILON;
    let (mut a, mut b) = (0.0f64, 0.0f64);
    let (mut nu, mut nc) = (0u64, 0u64);
    for (u, c) in pixels {
        let (u, c) = (u.borrow(), c.borrow());
        if u.count < 2 || c.count < 2 {
            continue;
        }
        let (vu, vc) = (u.variance_of_mean(), c.variance_of_mean());
        let n = (u.count + c.count) as f64;
        for ch in 0..3 {
            let m = (u.sum[ch] + c.sum[ch]) / n;
            let d = m * m + eps;
            a += vu[ch] / d;
            b += vc[ch] / d;
        }
        nu += u.count;
        nc += c.count;
    }
    if nu == 0 {
        return None;
    }
    inverse_variance_weights(&[a, b], &[nu as f64, nc as f64])
        .ok()
        .map(|w| w.weights[0])
}

/// One pixel's combined estimate `w·ū + (1 − w)·c̄` ([`phase_weight`]) as sums the film's
/// formulas read back: `count = n_u + n_c`, `sum = count·mean`, and `sum_sq` chosen so that
/// [`PixelMoments::variance_of_mean`] gives the combination's variance
/// `w²·Var[ū] + (1 − w)²·Var[c̄]` (the sets are independent given the coefficients). A pixel
/// with fewer than 2 samples in either set, or `w = None`, gets the plain merge; the AOV
/// sums are added.
pub fn combine_phases(
    plain: &PixelMoments,
    controlled: &PixelMoments,
    w: Option<f64>,
) -> PixelMoments {
    let Some(w) = pixel_weight(plain, controlled, w) else {
        return plain.merged(controlled);
    };
    let (nu, nc) = (plain.count as f64, controlled.count as f64);
    let count = plain.count + controlled.count;
    let n = count as f64;
    let (vu, vc) = (plain.variance_of_mean(), controlled.variance_of_mean());
    let mut out = PixelMoments {
        count,
        ..plain.merged(controlled)
    };
    for c in 0..3 {
        let mean = w * (plain.sum[c] / nu) + (1.0 - w) * (controlled.sum[c] / nc);
        let var = w * w * vu[c] + (1.0 - w) * (1.0 - w) * vc[c];
        out.sum[c] = n * mean;
        out.sum_sq[c] = n * mean * mean + var * n * (n - 1.0);
    }
    out
}

/// The weight [`combine_phases`] gives this pixel's uncontrolled mean: `w` when both sets
/// have at least 2 samples, else `None` (the plain merge).
fn pixel_weight(plain: &PixelMoments, controlled: &PixelMoments, w: Option<f64>) -> Option<f64> {
    w.filter(|_| plain.count >= 2 && controlled.count >= 2)
}

/// The factor with which the controlled samples' values enter [`combine_phases`]'s mean,
/// relative to the plain average of all the pixel's samples: `(1 − w)·n/n_c` where it weighs,
/// else 1. (A per-pixel sum over the controlled samples divided by `n`, times this, is that
/// sum's part of the combined mean.)
pub fn controlled_scale(plain: &PixelMoments, controlled: &PixelMoments, w: Option<f64>) -> f64 {
    match pixel_weight(plain, controlled, w) {
        Some(w) => (1.0 - w) * (plain.count + controlled.count) as f64 / controlled.count as f64,
        None => 1.0,
    }
}

/// Two whole images' sums combined: [`phase_weight`] over all pixels (in order), then
/// [`combine_phases`] pixel by pixel; and the weight. The images have the same size.
pub fn combine_phase_images(
    plain: &[PixelMoments],
    controlled: &[PixelMoments],
) -> (Vec<PixelMoments>, Option<f64>) {
    let w = phase_weight(plain.iter().zip(controlled));
    let combined = plain
        .iter()
        .zip(controlled)
        .map(|(u, c)| combine_phases(u, c, w))
        .collect();
    (combined, w)
}

#[cfg(test)]
mod tests {
    use rand::{Rng, SeedableRng};
    use rand_pcg::Pcg64;

    use super::*;

    /// A standard normal sample (Box–Muller).
    fn normal(rng: &mut Pcg64) -> f64 {
        let (u, v): (f64, f64) = (rng.random(), rng.random());
        (-2.0 * (1.0 - u).ln()).sqrt() * (std::f64::consts::TAU * v).cos()
    }

    #[test]
    fn inverse_variance_weights_match_eq_10() {
        let w = inverse_variance_weights(&[1.0, 4.0], &[1.0, 1.0]).unwrap();
        assert!((w.weights[0] - 0.8).abs() < 1e-12 && (w.variance - 0.8).abs() < 1e-12);
        let z = inverse_variance_weights(&[0.0, 4.0, 0.0], &[1.0; 3]).unwrap();
        assert_eq!(
            (z.weights, z.scheme),
            (vec![0.5, 0.0, 0.5], WeightScheme::ZeroVariance)
        );
        let r = inverse_variance_weights(&[0.0, 0.0], &[64.0, 1024.0]).unwrap();
        assert_eq!(r.scheme, WeightScheme::SampleRate);
        assert!((r.weights[1] - 1024.0 / 1088.0).abs() < 1e-12);
        assert!(inverse_variance_weights(&[-1.0], &[1.0]).is_err());
        assert!(inverse_variance_weights(&[1.0], &[]).is_err());
        let huge = inverse_variance_weights(&[1e-300, 1e300], &[1.0, 1.0]).unwrap();
        assert!(huge.weights.iter().all(|w| w.is_finite()));
    }

    #[test]
    fn keller_olkin_falls_back_when_not_psd() {
        let w = keller_olkin_weights(&[1.0, 2.0, 2.0, 1.0], &[1.0, 1.0]).unwrap();
        assert_eq!(w.scheme, WeightScheme::InverseVariance);
        // Perfectly correlated, equal variances: singular → inverse variance (0.5, 0.5).
        let s = keller_olkin_weights(&[1.0, 1.0, 1.0, 1.0], &[1.0, 1.0]).unwrap();
        assert_eq!(s.scheme, WeightScheme::InverseVariance);
        let k = keller_olkin_weights(&[1.0, 0.5, 0.5, 2.0], &[1.0, 1.0]).unwrap();
        assert_eq!(k.scheme, WeightScheme::KellerOlkin);
        // Closed form for two estimators: w₁ = (σ₂² − c)/(σ₁² + σ₂² − 2c).
        assert!((k.weights[0] - 1.5 / 2.0).abs() < 1e-12);
        assert!(k.variance <= 1.0);
        assert!(keller_olkin_weights(&[f64::NAN, 0.0, 0.0, 1.0], &[1.0, 1.0]).is_err());
    }

    fn sums(values: &[[f64; 3]]) -> PixelMoments {
        let mut s = PixelMoments::default();
        for v in values {
            for (c, &x) in v.iter().enumerate() {
                s.sum[c] += x;
                s.sum_sq[c] += x * x;
            }
            s.count += 1;
        }
        s
    }

    #[test]
    fn combined_sums_read_back_as_the_weighted_mean_and_its_variance() {
        let u = sums(&[[1.0, 0.0, 2.0], [3.0, 0.0, 2.0], [2.0, 0.0, 5.0]]);
        let c = sums(&[
            [0.5, 1.0, 1.0],
            [1.5, 3.0, 1.0],
            [1.0, 2.0, 4.0],
            [1.0, 2.0, 2.0],
        ]);
        let w = 0.25;
        let out = combine_phases(&u, &c, Some(w));
        assert_eq!(out.count, 7);
        let (vu, vc) = (u.variance_of_mean(), c.variance_of_mean());
        let v = out.variance_of_mean();
        for ch in 0..3 {
            let mean = w * u.sum[ch] / 3.0 + (1.0 - w) * c.sum[ch] / 4.0;
            assert!((out.sum[ch] / 7.0 - mean).abs() < 1e-12, "channel {ch}");
            let var = w * w * vu[ch] + (1.0 - w) * (1.0 - w) * vc[ch];
            assert!(
                (v[ch] - var).abs() < 1e-12 * (1.0 + var),
                "{} vs {var}",
                v[ch]
            );
        }
        // Green: the uncontrolled set is constant (no variance), so is its share.
        assert!((v[1] - 0.75 * 0.75 * vc[1]).abs() < 1e-12);
        // The controlled sum, divided by the count and scaled, is its part of the mean.
        let k = controlled_scale(&u, &c, Some(w));
        for ch in 0..3 {
            let part = (1.0 - w) * c.sum[ch] / 4.0;
            assert!((c.sum[ch] / 7.0 * k - part).abs() < 1e-12, "channel {ch}");
        }
        assert_eq!(controlled_scale(&u, &c, None), 1.0);
    }

    #[test]
    fn thin_pixels_and_no_weight_merge_plainly() {
        let u = sums(&[[1.0; 3]]);
        let c = sums(&[[2.0; 3], [4.0; 3]]);
        assert_eq!(combine_phases(&u, &c, Some(0.5)), u.merged(&c));
        assert_eq!(combine_phases(&c, &c, None), c.merged(&c));
        // No pixel with two samples in both sets: no weight.
        assert_eq!(phase_weight([(&u, &c)]), None);
        assert_eq!(
            phase_weight(std::iter::empty::<(PixelMoments, PixelMoments)>()),
            None
        );
    }

    #[test]
    fn zero_variance_sets_take_the_weight_and_equal_ones_share_by_count() {
        let flat = sums(&[[1.0; 3], [1.0; 3]]);
        let noisy = sums(&[[0.0; 3], [2.0; 3]]);
        assert_eq!(phase_weight([(&flat, &noisy)]), Some(1.0));
        assert_eq!(phase_weight([(&noisy, &flat)]), Some(0.0));
        // Both without variance: the sample-rate rule.
        let three = sums(&[[1.0; 3], [1.0; 3], [1.0; 3]]);
        assert_eq!(phase_weight([(&flat, &three)]), Some(0.4));
    }

    /// Synthetic phases: pixel `p` has truth `t_p`; its `nu` uncontrolled samples have standard
    /// deviation `σ_p`, its `nc` controlled ones `σ_p / √g` (a CV of gain `g`). The image-wide
    /// weight is then `1/(1 + g·nc/nu)` up to the noise of the variance estimates, and the
    /// combination is unbiased and beats the plain average by the predicted factor.
    #[test]
    fn the_phase_weight_is_the_optimal_share_and_the_combination_unbiased() {
        let (pixels, nu, nc, g) = (20_000usize, 16usize, 112usize, 4.0f64);
        let truth = |p: usize| 0.1 + (p % 11) as f64 * 0.2;
        let sigma = |p: usize| 0.3 * truth(p);
        let mut rng = Pcg64::seed_from_u64(0x5eed_0001);
        let mut sets = Vec::with_capacity(pixels);
        for p in 0..pixels {
            let draw = |rng: &mut Pcg64, n: usize, s: f64| {
                let v: Vec<[f64; 3]> = (0..n)
                    .map(|_| std::array::from_fn(|_| truth(p) + s * normal(rng)))
                    .collect();
                sums(&v)
            };
            let u = draw(&mut rng, nu, sigma(p));
            let c = draw(&mut rng, nc, sigma(p) / g.sqrt());
            sets.push((u, c));
        }
        let w = phase_weight(sets.iter().map(|(u, c)| (u, c))).unwrap();
        let want = 1.0 / (1.0 + g * nc as f64 / nu as f64);
        // Each relative variance estimate has relative sd √(2/(n−1)) per pixel-channel; over
        // 60 000 of them the ratio's relative error is below 1 %.
        assert!((w / want - 1.0).abs() < 0.03, "weight {w} vs {want}");
        let (mut err_plain, mut err_comb, mut bias) = (0.0, 0.0, 0.0);
        for (p, (u, c)) in sets.iter().enumerate() {
            let n = (nu + nc) as f64;
            let plain = u.merged(c);
            let comb = combine_phases(u, c, Some(w));
            for ch in 0..3 {
                let t = truth(p);
                err_plain += (plain.sum[ch] / n - t).powi(2);
                err_comb += (comb.sum[ch] / n - t).powi(2);
                bias += comb.sum[ch] / n - t;
            }
        }
        // Predicted MSE ratio of the plain average over the combination:
        // (nu + nc/g)/n² against 1/(nu + g·nc).
        let n = (nu + nc) as f64;
        let ratio = (nu as f64 + nc as f64 / g) / (n * n) * (nu as f64 + g * nc as f64);
        let got = err_plain / err_comb;
        assert!(
            (got / ratio - 1.0).abs() < 0.05,
            "MSE ratio {got} vs {ratio}"
        );
        // Mean error over 60 000 pixel-channels: within 4 standard errors of 0.
        let m = 3.0 * pixels as f64;
        let se = (err_comb / m).sqrt() / m.sqrt();
        assert!((bias / m).abs() < 4.0 * se, "bias {} vs se {se}", bias / m);
    }
}
