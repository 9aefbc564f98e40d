//! Optimizing control variates (OCV) for one gather integral [Fan eq. 7–11].
//!
//! `ocv` jobs draw, at each shading point, `n_j = N α_j` samples from each mixture component
//! (deterministic mixture sampling [Fan §4], see [`crate::mis::deterministic_counts`]),
//! then fit the CV `Σ β_j p_j` by penalised least squares and return `β0 + Σ β_j`
//! [Fan eq. 10].
//!
//! # Parameters (`estimator.kind = "ocv"`)
//! | name | type | default | meaning |
//! |---|---|---|---|
//! | `lambda` | f64 | 1.0 | ridge penalty λ of [Fan eq. 11] |
//! | `penalize_intercept` | bool | false | literal [Fan eq. 11]: also penalise `β0` |
//! | `max_condition` | f64 | 1e12 | condition estimate above which the plain estimate is used |
//!
//! ```json
//! { "kind": "ocv", "spe": 64, "lambda": 1.0, "penalize_intercept": false }
//! ```
//!
//! # The fit
//! With `y_i = f(X_i)/p(X_i)`, `p = Σ_j α_j p_j`, and regressors `x_ij = p_j(X_i)/p(X_i)` for
//! `j < m` (the last component is dropped because `Σ_j α_j x_ij = 1` makes the columns
//! collinear with the intercept [Fan §5]), minimise `‖y − β0 − Σ_j β_j x_j‖² + λ‖β‖²`.
//! The normal equations `(XᵀX + λ D) β = Xᵀy` use `D = diag(0, 1, …, 1)` by default:
//! penalising `β0` as eq. 11 is printed shrinks every estimate toward zero by about
//! `λ / (N + λ)` (1.5 % at `N = 64`, λ = 1), which is why it is only an option.
//!
//! # Contracts
//! - All pdfs of one call in the same measure; `f` in the units of the estimate.
//! - Samples with a non-finite value, a non-finite or negative component pdf, or a zero
//!   mixture density are skipped and counted in [`OcvResult::rejected`].
//! - On a failed or ill-conditioned fit the result is the plain deterministic-mixture
//!   (balance heuristic) estimate `mean(y)` [Fan eq. 6] with `fallback = true`.
//! - So it is with fewer than [`MIN_SAMPLES_PER_COMPONENT`] valid samples per mixture
//!   component: the fit estimates `q = m − 1` control coefficients from the same `N` samples,
//!   which multiplies the controlled estimate's variance by about `(N − 2)/(N − q − 2)`
//!   (Lavenberg & Welch 1981, for normal samples), unbounded for `N ≤ q + 2`; `N ≥ 2m` keeps
//!   that factor at most 2. Below it the penalty λ alone keeps the system solvable, and the
//!   fitted `β` extrapolate: on `checkers` (2 lights, `m = 3`) `spe` 2 made the image 150×
//!   worse than `path` at equal spp, `spe` 4 2.8× worse than its own plain estimate. The rule
//!   depends on `N` and `m` only, never on the values, so it adds no bias.

use nalgebra::DMatrix;
use thiserror::Error;

use crate::cell::CHANNELS;

/// Fewest valid samples per mixture component for which [`ocv_estimate`] fits the CV (see
/// the module contracts); with fewer it returns the plain estimate.
pub const MIN_SAMPLES_PER_COMPONENT: usize = 2;

/// Options of the OCV fit.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OcvOptions {
    /// Ridge penalty λ [Fan eq. 11].
    pub lambda: f64,
    /// Literal eq. 11: also penalise the intercept.
    pub penalize_intercept: bool,
    /// Largest accepted condition estimate of the (Jacobi-scaled) normal matrix.
    pub max_condition: f64,
}

impl Default for OcvOptions {
    fn default() -> Self {
        Self {
            lambda: 1.0,
            penalize_intercept: false,
            max_condition: 1e12,
        }
    }
}

/// Invalid input to [`ocv_estimate`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Error)]
pub enum OcvError {
    /// No component.
    #[error("no mixture component")]
    NoComponents,
    /// `component_pdfs.len() != values.len() × mixture.len()`.
    #[error("component pdf table has the wrong size")]
    SizeMismatch,
    /// Mixture weights not finite, negative or summing to zero.
    #[error("invalid mixture weights")]
    BadMixture,
    /// Every sample was rejected (or there were none).
    #[error("no valid sample")]
    NoSamples,
}

/// Result of one OCV estimate.
#[derive(Clone, Debug, PartialEq)]
pub struct OcvResult {
    /// `β0 + Σ β_j` per channel [Fan eq. 10] (or the plain estimate on fallback).
    pub estimate: [f64; CHANNELS],
    /// Intercept `β0` per channel.
    pub beta0: [f64; CHANNELS],
    /// `β_j` per component and channel; the dropped last component has `β = 0`.
    pub beta: Vec<[f64; CHANNELS]>,
    /// Condition estimate `(max Lᵢᵢ / min Lᵢᵢ)²` of the scaled normal matrix (NaN when no
    /// fit was attempted: too few samples per component).
    pub condition: f64,
    /// True when the plain estimate was returned.
    pub fallback: bool,
    /// Samples skipped as invalid.
    pub rejected: usize,
    /// The plain deterministic-mixture estimate `mean(y)` [Fan eq. 6].
    pub plain: [f64; CHANNELS],
}

/// OCV estimate from `N` samples: `values[i] = f(X_i)` (RGB), `component_pdfs` row-major
/// `N × m` with `p_j(X_i)`, `mixture` the weights `α_j` (normalised internally).
pub fn ocv_estimate(
    values: &[[f64; CHANNELS]],
    component_pdfs: &[f64],
    mixture: &[f64],
    options: &OcvOptions,
) -> Result<OcvResult, OcvError> {
    let m = mixture.len();
    if m == 0 {
        return Err(OcvError::NoComponents);
    }
    if component_pdfs.len() != values.len() * m {
        return Err(OcvError::SizeMismatch);
    }
    let total: f64 = mixture.iter().sum();
    if mixture.iter().any(|a| !a.is_finite() || *a < 0.0) || !(total > 0.0) {
        return Err(OcvError::BadMixture);
    }
    // Unknowns: β0 and β_1..β_{m-1}.
    let q = m;
    let mut xtx = DMatrix::<f64>::zeros(q, q);
    let mut xty = DMatrix::<f64>::zeros(q, CHANNELS);
    let mut row = vec![0.0; q];
    let (mut n, mut rejected) = (0usize, 0usize);
    let mut sum_y = [0.0; CHANNELS];
    for (v, pdfs) in values.iter().zip(component_pdfs.chunks_exact(m)) {
        let p: f64 = pdfs.iter().zip(mixture).map(|(pj, a)| pj * a / total).sum();
        let valid = v.iter().all(|x| x.is_finite())
            && pdfs.iter().all(|x| x.is_finite() && *x >= 0.0)
            && p > 0.0
            && p.is_finite();
        if !valid {
            rejected += 1;
            continue;
        }
        let y = v.map(|f| f / p);
        if y.iter().any(|x| !x.is_finite()) {
            rejected += 1;
            continue;
        }
        row[0] = 1.0;
        for j in 1..q {
            row[j] = pdfs[j - 1] / p;
        }
        for a in 0..q {
            for b in a..q {
                xtx[(a, b)] += row[a] * row[b];
            }
            for ch in 0..CHANNELS {
                xty[(a, ch)] += row[a] * y[ch];
            }
        }
        for ch in 0..CHANNELS {
            sum_y[ch] += y[ch];
        }
        n += 1;
    }
    if n == 0 {
        return Err(OcvError::NoSamples);
    }
    let plain = sum_y.map(|s| s / n as f64);
    let fallback = |condition: f64| OcvResult {
        estimate: plain,
        beta0: plain,
        beta: vec![[0.0; CHANNELS]; m],
        condition,
        fallback: true,
        rejected,
        plain,
    };
    if n < MIN_SAMPLES_PER_COMPONENT * m {
        return Ok(fallback(f64::NAN));
    }
    let lambda = if options.lambda.is_finite() {
        options.lambda.max(0.0)
    } else {
        0.0
    };
    for a in 0..q {
        for b in 0..a {
            xtx[(a, b)] = xtx[(b, a)];
        }
        if a > 0 || options.penalize_intercept {
            xtx[(a, a)] += lambda;
        }
    }
    // Jacobi scaling for the factorisation and the condition estimate; a zero diagonal
    // (a component never nonzero and λ = 0) cannot be fitted.
    let mut scale = vec![0.0; q];
    for a in 0..q {
        let d = xtx[(a, a)];
        if !(d > 0.0) || !d.is_finite() {
            return Ok(fallback(f64::INFINITY));
        }
        scale[a] = 1.0 / d.sqrt();
    }
    for a in 0..q {
        for b in 0..q {
            xtx[(a, b)] *= scale[a] * scale[b];
        }
        for ch in 0..CHANNELS {
            xty[(a, ch)] *= scale[a];
        }
    }
    let Some(chol) = xtx.cholesky() else {
        return Ok(fallback(f64::INFINITY));
    };
    let l = chol.l_dirty().diagonal();
    let (lo, hi) = l.iter().fold((f64::INFINITY, 0.0f64), |(lo, hi), d| {
        (lo.min(d * d), hi.max(d * d))
    });
    let condition = if lo > 0.0 { hi / lo } else { f64::INFINITY };
    if !(condition <= options.max_condition) {
        return Ok(fallback(condition));
    }
    let x = chol.solve(&xty);
    let mut beta0 = [0.0; CHANNELS];
    let mut beta = vec![[0.0; CHANNELS]; m];
    let mut estimate = [0.0; CHANNELS];
    for ch in 0..CHANNELS {
        beta0[ch] = x[(0, ch)] * scale[0];
        estimate[ch] = beta0[ch];
        for j in 1..q {
            let b = x[(j, ch)] * scale[j];
            beta[j - 1][ch] = b;
            estimate[ch] += b;
        }
    }
    if estimate.iter().any(|e| !e.is_finite()) {
        return Ok(fallback(condition));
    }
    Ok(OcvResult {
        estimate,
        beta0,
        beta,
        condition,
        fallback: false,
        rejected,
        plain,
    })
}
