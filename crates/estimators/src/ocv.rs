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
///
/// A convenience over [`OcvSolver::fit`] that allocates its buffers and the `β` list; the
/// renderer calls the solver, which reuses its buffers.
pub fn ocv_estimate(
    values: &[[f64; CHANNELS]],
    component_pdfs: &[f64],
    mixture: &[f64],
    options: &OcvOptions,
) -> Result<OcvResult, OcvError> {
    let mut solver = OcvSolver::default();
    let fit = solver.fit(values, component_pdfs, mixture, options)?;
    let m = mixture.len();
    Ok(OcvResult {
        estimate: fit.estimate,
        beta0: fit.beta0,
        beta: (0..m).map(|j| solver.beta(j)).collect(),
        condition: fit.condition,
        fallback: fit.fallback,
        rejected: fit.rejected,
        plain: fit.plain,
    })
}

/// The scalars of one OCV fit ([`OcvSolver::fit`]); the `β_j` are read with
/// [`OcvSolver::beta`]. Fields as in [`OcvResult`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OcvFit {
    /// `β0 + Σ β_j` per channel [Fan eq. 10] (or the plain estimate on fallback).
    pub estimate: [f64; CHANNELS],
    /// Intercept `β0` per channel.
    pub beta0: [f64; CHANNELS],
    /// Condition estimate (see [`OcvResult::condition`]).
    pub condition: f64,
    /// True when the plain estimate was returned.
    pub fallback: bool,
    /// Samples skipped as invalid.
    pub rejected: usize,
    /// The plain deterministic-mixture estimate `mean(y)` [Fan eq. 6].
    pub plain: [f64; CHANNELS],
}

/// The OCV fit with reusable buffers: after the first fit of a given component count it
/// allocates nothing, which matters at one fit per shading point (`ocv` jobs fit at every
/// vertex of every camera sample).
#[derive(Clone, Debug, Default)]
pub struct OcvSolver {
    /// The mixture weights of the last call, as passed (validated).
    mixture: Vec<f64>,
    /// Normalised mixture weights `α_j / Σα`.
    alpha: Vec<f64>,
    /// Normal matrix, `q × q` row-major; after the fit its lower triangle holds the Cholesky
    /// factor of the Jacobi-scaled matrix.
    xtx: Vec<f64>,
    /// Right-hand sides `q × CHANNELS`; after the fit the scaled solution.
    xty: Vec<f64>,
    /// One regressor row `(1, x_i1, …, x_i,m−1)`.
    row: Vec<f64>,
    /// Jacobi scale `1/√A_aa`.
    scale: Vec<f64>,
    /// Unknowns of the last fit (`q = m`), 0 after a fallback (every `β_j` is then 0).
    solved: usize,
}

/// Whether `x` is finite (false for NaN), as one comparison.
#[inline(always)]
fn finite(x: f64) -> bool {
    x.abs() < f64::INFINITY
}

impl OcvSolver {
    /// `β_j` of the last [`fit`](Self::fit) per channel; 0 for the dropped last component,
    /// for `j` out of range and after a fallback.
    pub fn beta(&self, j: usize) -> [f64; CHANNELS] {
        let q = self.solved;
        if j + 1 >= q {
            return [0.0; CHANNELS];
        }
        let a = j + 1;
        std::array::from_fn(|ch| self.xty[a * CHANNELS + ch] * self.scale[a])
    }

    /// Fits the OCV to one gather's samples (arguments and contracts as [`ocv_estimate`]).
    pub fn fit(
        &mut self,
        values: &[[f64; CHANNELS]],
        component_pdfs: &[f64],
        mixture: &[f64],
        options: &OcvOptions,
    ) -> Result<OcvFit, OcvError> {
        self.solved = 0;
        let m = mixture.len();
        if m == 0 {
            return Err(OcvError::NoComponents);
        }
        if component_pdfs.len() != values.len() * m {
            return Err(OcvError::SizeMismatch);
        }
        // A renderer passes the same mixture at every shading point: validate and normalise
        // it once.
        if self.mixture != mixture {
            let total: f64 = mixture.iter().sum();
            if mixture.iter().any(|a| !a.is_finite() || *a < 0.0) || !(total > 0.0) {
                return Err(OcvError::BadMixture);
            }
            self.mixture.clear();
            self.mixture.extend_from_slice(mixture);
            self.alpha.clear();
            self.alpha.extend(mixture.iter().map(|a| a / total));
            // Unknowns: β0 and β_1..β_{m-1}.
            let q = m;
            self.xtx.resize(q * q, 0.0);
            self.xty.resize(q * CHANNELS, 0.0);
            self.row.resize(q, 0.0);
            self.scale.resize(q, 0.0);
        }
        // Compiled for each small component count so that the loops unroll; generic above.
        match m {
            1 => self.fit_q::<1>(values, component_pdfs, options),
            2 => self.fit_q::<2>(values, component_pdfs, options),
            3 => self.fit_q::<3>(values, component_pdfs, options),
            4 => self.fit_q::<4>(values, component_pdfs, options),
            5 => self.fit_q::<5>(values, component_pdfs, options),
            6 => self.fit_q::<6>(values, component_pdfs, options),
            _ => self.fit_q::<0>(values, component_pdfs, options),
        }
    }

    /// [`fit`](Self::fit) after the mixture checks, with `Q` the component count, or 0 for
    /// "take it from the buffers" (any count).
    fn fit_q<const Q: usize>(
        &mut self,
        values: &[[f64; CHANNELS]],
        component_pdfs: &[f64],
        options: &OcvOptions,
    ) -> Result<OcvFit, OcvError> {
        let q = if Q == 0 { self.alpha.len() } else { Q };
        debug_assert_eq!(q, self.alpha.len());
        let alpha = &self.alpha[..q];
        let xtx = &mut self.xtx[..q * q];
        let xty = &mut self.xty[..q * CHANNELS];
        let row = &mut self.row[..q];
        let scale = &mut self.scale[..q];
        xtx.fill(0.0);
        xty.fill(0.0);

        // The per-sample sums: the upper triangle of `XᵀX`, and `Xᵀy`.
        let (mut n, mut rejected) = (0usize, 0usize);
        let mut sum_y = [0.0; CHANNELS];
        for (v, pdfs) in values.iter().zip(component_pdfs.chunks_exact(q)) {
            let mut p = 0.0;
            let mut negative = false;
            for (&pj, &a) in pdfs.iter().zip(alpha) {
                p += pj * a;
                negative |= pj < 0.0;
            }
            let mut valid = !negative;
            // `p` finite and positive means every density finite (an infinite or NaN one
            // makes `p` infinite or NaN, as the weights are finite and ≥ 0, and `∞ · 0` is
            // NaN); then `y` finite means `v` finite.
            let y = v.map(|f| f / p);
            valid &= p > 0.0 && p < f64::INFINITY && finite(y[0]) & finite(y[1]) & finite(y[2]);
            if !valid {
                rejected += 1;
                continue;
            }
            row[0] = 1.0;
            for (r, pj) in row[1..].iter_mut().zip(pdfs) {
                *r = pj / p;
            }
            for a in 0..q {
                let ra = row[a];
                for (x, rb) in xtx[a * q + a..(a + 1) * q].iter_mut().zip(&row[a..]) {
                    *x += ra * rb;
                }
                for (x, yc) in xty[a * CHANNELS..(a + 1) * CHANNELS].iter_mut().zip(&y) {
                    *x += ra * yc;
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
        let fallback = |condition: f64| OcvFit {
            estimate: plain,
            beta0: plain,
            condition,
            fallback: true,
            rejected,
            plain,
        };
        if n < MIN_SAMPLES_PER_COMPONENT * q {
            return Ok(fallback(f64::NAN));
        }
        let lambda = if options.lambda.is_finite() {
            options.lambda.max(0.0)
        } else {
            0.0
        };
        for a in 0..q {
            for b in 0..a {
                xtx[a * q + b] = xtx[b * q + a];
            }
            if a > 0 || options.penalize_intercept {
                xtx[a * q + a] += lambda;
            }
        }
        // Jacobi scaling for the factorisation and the condition estimate; a zero diagonal
        // (a component never nonzero and λ = 0) cannot be fitted.
        for a in 0..q {
            let d = xtx[a * q + a];
            if !(d > 0.0 && d < f64::INFINITY) {
                return Ok(fallback(f64::INFINITY));
            }
            scale[a] = 1.0 / d.sqrt();
        }
        for a in 0..q {
            for b in 0..q {
                xtx[a * q + b] *= scale[a] * scale[b];
            }
            for ch in 0..CHANNELS {
                xty[a * CHANNELS + ch] *= scale[a];
            }
        }
        // Cholesky `A = L Lᵀ` in place (lower triangle); a non-positive pivot means the
        // matrix is not numerically positive definite.
        for j in 0..q {
            let mut d = xtx[j * q + j];
            for k in 0..j {
                d -= xtx[j * q + k] * xtx[j * q + k];
            }
            if !(d > 0.0 && d < f64::INFINITY) {
                return Ok(fallback(f64::INFINITY));
            }
            let ljj = d.sqrt();
            xtx[j * q + j] = ljj;
            for i in j + 1..q {
                let mut s = xtx[i * q + j];
                for k in 0..j {
                    s -= xtx[i * q + k] * xtx[j * q + k];
                }
                xtx[i * q + j] = s / ljj;
            }
        }
        let (mut lo, mut hi) = (f64::INFINITY, 0.0f64);
        for a in 0..q {
            let d = xtx[a * q + a];
            (lo, hi) = (lo.min(d * d), hi.max(d * d));
        }
        let condition = if lo > 0.0 { hi / lo } else { f64::INFINITY };
        if !(condition <= options.max_condition) {
            return Ok(fallback(condition));
        }
        // Forward `L z = b`, then back `Lᵀ x = z`, all channels at once, in place.
        for i in 0..q {
            for ch in 0..CHANNELS {
                let mut s = xty[i * CHANNELS + ch];
                for k in 0..i {
                    s -= xtx[i * q + k] * xty[k * CHANNELS + ch];
                }
                xty[i * CHANNELS + ch] = s / xtx[i * q + i];
            }
        }
        for i in (0..q).rev() {
            for ch in 0..CHANNELS {
                let mut s = xty[i * CHANNELS + ch];
                for k in i + 1..q {
                    s -= xtx[k * q + i] * xty[k * CHANNELS + ch];
                }
                xty[i * CHANNELS + ch] = s / xtx[i * q + i];
            }
        }
        let mut beta0 = [0.0; CHANNELS];
        let mut estimate = [0.0; CHANNELS];
        for ch in 0..CHANNELS {
            beta0[ch] = xty[ch] * scale[0];
            estimate[ch] = beta0[ch];
            for j in 1..q {
                estimate[ch] += xty[j * CHANNELS + ch] * scale[j];
            }
        }
        if !estimate.iter().all(|e| e.is_finite()) {
            return Ok(fallback(condition));
        }
        self.solved = q;
        Ok(OcvFit {
            estimate,
            beta0,
            condition,
            fallback: false,
            rejected,
            plain,
        })
    }
}
