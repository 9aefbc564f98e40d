//! Image-space reconstructions of gradient-domain renderings [Rou §5].
//!
//! Input is a [`GradientBuffers`] view: the primal image `F`, its horizontal and vertical
//! finite differences `X`, `Y` (estimated with correlated paths) and per-pixel variances of
//! all three. Four reconstructions (`gradient` estimator, `reconstruction` parameter):
//!
//! | name | function | what |
//! |---|---|---|
//! | `uniform` | [`uniform_iterated`] | iterated CV estimator, equal weights [Rou eq. 22] |
//! | `weighted` | [`weighted_iterated`] | iterated, inverse-variance weights [Rou eq. 10, 21] with the locally-uniform variance [Rou eq. 23], neighbourhood-median prefilter and deterministic variance model [Rou eq. 24] |
//! | `poisson_l2` | [`poisson_l2`] | screened Poisson, L2 [Rou eq. 25–26], conjugate gradients |
//! | `weighted_l2` | [`weighted_poisson_l2`] | screened Poisson with gradient weights [Rou eq. 32] |
//!
//! ```json
//! { "kind": "gradient", "reconstruction": "weighted", "iterations": 100, "unbiased": false }
//! ```
//!
//! # Conventions and contracts
//! - Images are `width × height`, row-major, RGB interleaved (`3` values per pixel) for
//!   `F`, `X`, `Y`; variances are one value per pixel (e.g. the channel mean).
//! - `X[x, y] ≈ F[x+1, y] − F[x, y]` and `Y[x, y] ≈ F[x, y+1] − F[x, y]` (forward
//!   differences); the last column of `X` and last row of `Y` are ignored. With these,
//!   the five estimators of pixel `p` are `F_p`, `F_l + X_l`, `F_r − X_p`, `F_t + Y_t`,
//!   `F_b − Y_p` ([Rou eq. 22], whose printed subscripts we read this way). Pixels on the
//!   border use only the neighbours they have.
//! - The weighted schemes take their statistics from a separate view: pass the same
//!   buffers for the (biased) standard variant, or the other half buffer for the unbiased
//!   cross-weighted variant [Rou §5.5] ([`weighted_iterated_cross`]).
//! - Inputs must be finite with non-negative variances; otherwise a typed error.
//! - The uniform iteration preserves the mean of `F` weighted by each pixel's number of
//!   estimators and converges to the integrated-gradient image.

use thiserror::Error;

/// Errors of the reconstructions.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Error)]
pub enum ReconstructError {
    /// A buffer does not have `width × height × channels` entries, or the two views of a
    /// cross-weighted reconstruction differ in size.
    #[error("buffer sizes do not match the image size")]
    SizeMismatch,
    /// Zero width or height.
    #[error("empty image")]
    Empty,
    /// A NaN/Inf value or a negative variance.
    #[error("non-finite value or negative variance in the input")]
    InvalidValue,
}

/// Borrowed gradient-domain buffers (see the module conventions).
#[derive(Clone, Copy, Debug)]
pub struct GradientBuffers<'a> {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// Primal image `F`, RGB interleaved.
    pub primal: &'a [f32],
    /// Variance of `F` per pixel.
    pub primal_var: &'a [f32],
    /// Horizontal differences `X`, RGB interleaved.
    pub dx: &'a [f32],
    /// Variance of `X` per pixel.
    pub dx_var: &'a [f32],
    /// Vertical differences `Y`, RGB interleaved.
    pub dy: &'a [f32],
    /// Variance of `Y` per pixel.
    pub dy_var: &'a [f32],
}

impl GradientBuffers<'_> {
    fn validate(&self) -> Result<(), ReconstructError> {
        if self.width == 0 || self.height == 0 {
            return Err(ReconstructError::Empty);
        }
        let n = self.width * self.height;
        if [self.primal.len(), self.dx.len(), self.dy.len()]
            .iter()
            .any(|&l| l != 3 * n)
            || [self.primal_var.len(), self.dx_var.len(), self.dy_var.len()]
                .iter()
                .any(|&l| l != n)
        {
            return Err(ReconstructError::SizeMismatch);
        }
        let values_ok = [self.primal, self.dx, self.dy]
            .iter()
            .all(|b| b.iter().all(|v| v.is_finite()));
        let vars_ok = [self.primal_var, self.dx_var, self.dy_var]
            .iter()
            .all(|b| b.iter().all(|v| v.is_finite() && *v >= 0.0));
        if values_ok && vars_ok {
            Ok(())
        } else {
            Err(ReconstructError::InvalidValue)
        }
    }
}

/// Options of the weighted iterated reconstruction.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WeightedOptions {
    /// Number of iterations (the paper uses 100).
    pub iterations: usize,
    /// ε of the deterministic variance model [Rou eq. 24].
    pub epsilon: f32,
    /// Replace each pixel variance by the median over its neighbourhood first [Rou §5.3].
    pub median_prefilter: bool,
}

impl Default for WeightedOptions {
    fn default() -> Self {
        Self {
            iterations: 100,
            epsilon: 0.01,
            median_prefilter: true,
        }
    }
}

/// Smallest variance used in a weight denominator (avoids `1/0`; f32-safe).
const MIN_VARIANCE: f32 = 1e-30;

/// Padded planar working set: one border pixel on every side so the inner loop has no
/// branches; missing neighbours have infinite difference variance, hence zero weight.
struct Planes {
    pw: usize,
    w: usize,
    h: usize,
    /// Current estimate per channel.
    f: [Vec<f32>; 3],
    gx: [Vec<f32>; 3],
    gy: [Vec<f32>; 3],
    /// Variance of the difference to the right / lower neighbour (∞ where there is none).
    vx: Vec<f32>,
    vy: Vec<f32>,
    /// Per-pixel variance of the primal estimate at iteration 0.
    v0: Vec<f32>,
}

impl Planes {
    fn new(
        data: &GradientBuffers<'_>,
        stats: &GradientBuffers<'_>,
        uniform: bool,
        median: bool,
    ) -> Self {
        let (w, h) = (data.width, data.height);
        let (pw, ph) = (w + 2, h + 2);
        let n = pw * ph;
        let plane = || vec![0.0f32; n];
        let mut p = Planes {
            pw,
            w,
            h,
            f: [plane(), plane(), plane()],
            gx: [plane(), plane(), plane()],
            gy: [plane(), plane(), plane()],
            vx: vec![f32::INFINITY; n],
            vy: vec![f32::INFINITY; n],
            v0: vec![1.0; n],
        };
        for y in 0..h {
            for x in 0..w {
                let (s, d) = (y * w + x, (y + 1) * pw + x + 1);
                for c in 0..3 {
                    p.f[c][d] = data.primal[3 * s + c];
                    p.gx[c][d] = data.dx[3 * s + c];
                    p.gy[c][d] = data.dy[3 * s + c];
                }
                if x + 1 < w {
                    p.vx[d] = if uniform { 0.0 } else { stats.dx_var[s] };
                }
                if y + 1 < h {
                    p.vy[d] = if uniform { 0.0 } else { stats.dy_var[s] };
                }
                if !uniform {
                    p.v0[d] = stats.primal_var[s];
                }
            }
        }
        // Left/top padding: the "difference to the right/lower neighbour" of the padding
        // cell is the missing left/top neighbour of the first column/row: keep ∞.
        if median && !uniform {
            let mut filtered = p.v0.clone();
            let mut buf = [0.0f32; 5];
            for y in 0..h {
                for x in 0..w {
                    let i = (y + 1) * pw + x + 1;
                    let mut k = 0;
                    buf[k] = p.v0[i];
                    k += 1;
                    if x > 0 {
                        buf[k] = p.v0[i - 1];
                        k += 1;
                    }
                    if x + 1 < w {
                        buf[k] = p.v0[i + 1];
                        k += 1;
                    }
                    if y > 0 {
                        buf[k] = p.v0[i - pw];
                        k += 1;
                    }
                    if y + 1 < h {
                        buf[k] = p.v0[i + pw];
                        k += 1;
                    }
                    let s = &mut buf[..k];
                    s.sort_by(f32::total_cmp);
                    filtered[i] = if k % 2 == 1 {
                        s[k / 2]
                    } else {
                        0.5 * (s[k / 2 - 1] + s[k / 2])
                    };
                }
            }
            p.v0 = filtered;
        }
        p
    }

    /// One iteration [Rou eq. 21] with pixel variance `v0 · scale` (locally uniform,
    /// [Rou eq. 23]) and inverse-variance weights [Rou eq. 10].
    fn iterate(&mut self, next: &mut [Vec<f32>; 3], scale: f32, wbuf: &mut [Vec<f32>; 5]) {
        let (pw, w) = (self.pw, self.w);
        for y in 1..=self.h {
            let row = y * pw + 1;
            // Normalised weights of the row's five estimators (vectorisable).
            let [ws, wl, wr, wt, wb] = wbuf;
            for x in 0..w {
                let i = row + x;
                let v = (self.v0[i] * scale).max(MIN_VARIANCE);
                let (s, l, r) = (1.0 / v, 1.0 / (v + self.vx[i - 1]), 1.0 / (v + self.vx[i]));
                let (t, b) = (1.0 / (v + self.vy[i - pw]), 1.0 / (v + self.vy[i]));
                let norm = 1.0 / (s + l + r + t + b);
                (ws[x], wl[x], wr[x], wt[x], wb[x]) =
                    (s * norm, l * norm, r * norm, t * norm, b * norm);
            }
            for (c, out) in next.iter_mut().enumerate() {
                let (f, gx, gy) = (&self.f[c], &self.gx[c], &self.gy[c]);
                for x in 0..w {
                    let i = row + x;
                    out[i] = ws[x] * f[i]
                        + wl[x] * (f[i - 1] + gx[i - 1])
                        + wr[x] * (f[i + 1] - gx[i])
                        + wt[x] * (f[i - pw] + gy[i - pw])
                        + wb[x] * (f[i + pw] - gy[i]);
                }
            }
        }
        std::mem::swap(&mut self.f, next);
    }

    fn run(mut self, iterations: usize, epsilon: Option<f32>) -> Vec<f32> {
        let mut next = self.f.clone();
        let mut wbuf: [Vec<f32>; 5] = std::array::from_fn(|_| vec![0.0; self.w]);
        let mut scale = 1.0f32;
        for i in 1..=iterations {
            self.iterate(&mut next, scale, &mut wbuf);
            if let Some(eps) = epsilon {
                // [Rou eq. 24]: Var Fⁱ = Var Fⁱ⁻¹ / (ε + 1 + 4 · 0.5^(i−1)).
                scale /= eps + 1.0 + 4.0 * 0.5f32.powi(i as i32 - 1);
            }
        }
        let mut out = vec![0.0f32; 3 * self.w * self.h];
        for y in 0..self.h {
            for x in 0..self.w {
                let i = (y + 1) * self.pw + x + 1;
                for c in 0..3 {
                    out[3 * (y * self.w + x) + c] = self.f[c][i];
                }
            }
        }
        out
    }
}

/// Uniform iterated reconstruction [Rou eq. 22]: every available estimator weighted
/// equally, `iterations` times. Returns the RGB image.
pub fn uniform_iterated(
    data: &GradientBuffers<'_>,
    iterations: usize,
) -> Result<Vec<f32>, ReconstructError> {
    data.validate()?;
    Ok(Planes::new(data, data, true, false).run(iterations, None))
}

/// Weighted iterated reconstruction [Rou eq. 21, 23, 24] of `data`, with weights from the
/// variances of `stats` (pass `data` itself for the standard, biased variant).
pub fn weighted_iterated(
    data: &GradientBuffers<'_>,
    stats: &GradientBuffers<'_>,
    options: &WeightedOptions,
) -> Result<Vec<f32>, ReconstructError> {
    data.validate()?;
    stats.validate()?;
    if (data.width, data.height) != (stats.width, stats.height) {
        return Err(ReconstructError::SizeMismatch);
    }
    let eps = if options.epsilon.is_finite() && options.epsilon > 0.0 {
        options.epsilon
    } else {
        0.01
    };
    Ok(
        Planes::new(data, stats, false, options.median_prefilter)
            .run(options.iterations, Some(eps)),
    )
}

/// Unbiased cross-weighted variant [Rou §5.5]: reconstruct each half buffer with the other
/// half's statistics and average the two results.
pub fn weighted_iterated_cross(
    a: &GradientBuffers<'_>,
    b: &GradientBuffers<'_>,
    options: &WeightedOptions,
) -> Result<Vec<f32>, ReconstructError> {
    let ra = weighted_iterated(a, b, options)?;
    let rb = weighted_iterated(b, a, options)?;
    Ok(ra.iter().zip(&rb).map(|(x, y)| 0.5 * (x + y)).collect())
}

/// Options of the screened Poisson solvers.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PoissonOptions {
    /// Screening weight λ of the primal term [Rou eq. 25] (GDPT uses 0.2).
    pub lambda: f64,
    /// Relative residual at which conjugate gradients stop.
    pub tolerance: f64,
    /// Iteration cap of conjugate gradients.
    pub max_iterations: usize,
}

impl Default for PoissonOptions {
    fn default() -> Self {
        Self {
            lambda: 0.2,
            tolerance: 1e-6,
            max_iterations: 5000,
        }
    }
}

/// Screened Poisson L2 reconstruction [Rou eq. 25–26]: minimises
/// `Σ λ²(U − F)² + Σ (∇U − (X, Y))²` by Jacobi-preconditioned conjugate gradients.
pub fn poisson_l2(
    data: &GradientBuffers<'_>,
    options: &PoissonOptions,
) -> Result<Vec<f32>, ReconstructError> {
    data.validate()?;
    let n = data.width * data.height;
    let ones = vec![1.0f64; n];
    Ok(solve_screened(data, &ones, &ones, options))
}

/// Gradient weights of the weighted L2 solver [Rou eq. 32] from `stats`.
///
/// With the locally uniform variance [Rou eq. 23], the estimator of `p` from its right
/// neighbour has variance `V_p + Var X_p`; its weight relative to `p`'s own estimator is
/// `V_p / (V_p + Var X_p)`. The weight of `X_p` is the smaller of that ratio for `p` and
/// for `r` (we read eq. 32's ratio as one of inverse variances, i.e. weights, as the text
/// describes, so that it lies in `[0, 1]`). Variances are median-prefiltered first.
/// Returns `(wx, wy)`, one weight per pixel.
pub fn gradient_weights(
    stats: &GradientBuffers<'_>,
) -> Result<(Vec<f64>, Vec<f64>), ReconstructError> {
    stats.validate()?;
    let planes = Planes::new(stats, stats, false, true);
    let (w, h, pw) = (stats.width, stats.height, planes.pw);
    let ratio = |v: f32, g: f32| {
        let v = f64::from(v).max(f64::from(MIN_VARIANCE));
        v / (v + f64::from(g))
    };
    let mut wx = vec![0.0; w * h];
    let mut wy = vec![0.0; w * h];
    for y in 0..h {
        for x in 0..w {
            let (s, i) = (y * w + x, (y + 1) * pw + x + 1);
            if x + 1 < w {
                let g = stats.dx_var[s];
                wx[s] = ratio(planes.v0[i], g).min(ratio(planes.v0[i + 1], g));
            }
            if y + 1 < h {
                let g = stats.dy_var[s];
                wy[s] = ratio(planes.v0[i], g).min(ratio(planes.v0[i + pw], g));
            }
        }
    }
    Ok((wx, wy))
}

/// Weighted screened Poisson L2 reconstruction [Rou eq. 32]: gradient constraints of `data`
/// weighted by [`gradient_weights`] of `stats`, primal constraints unweighted.
pub fn weighted_poisson_l2(
    data: &GradientBuffers<'_>,
    stats: &GradientBuffers<'_>,
    options: &PoissonOptions,
) -> Result<Vec<f32>, ReconstructError> {
    data.validate()?;
    if (data.width, data.height) != (stats.width, stats.height) {
        return Err(ReconstructError::SizeMismatch);
    }
    let (wx, wy) = gradient_weights(stats)?;
    Ok(solve_screened(data, &wx, &wy, options))
}

/// Conjugate gradients on `(λ² I + Gᵀ W G) U = λ² F + Gᵀ W g` per channel.
fn solve_screened(
    data: &GradientBuffers<'_>,
    wx: &[f64],
    wy: &[f64],
    options: &PoissonOptions,
) -> Vec<f32> {
    let (w, h) = (data.width, data.height);
    let n = w * h;
    let l2 = options.lambda * options.lambda;
    // Edge weights, zero where the neighbour does not exist.
    let ex: Vec<f64> = (0..n)
        .map(|s| if s % w + 1 < w { wx[s] } else { 0.0 })
        .collect();
    let ey: Vec<f64> = (0..n)
        .map(|s| if s / w + 1 < h { wy[s] } else { 0.0 })
        .collect();
    let apply = |u: &[f64], out: &mut [f64]| {
        for s in 0..n {
            out[s] = l2 * u[s];
        }
        for s in 0..n {
            if ex[s] != 0.0 {
                let d = ex[s] * (u[s] - u[s + 1]);
                out[s] += d;
                out[s + 1] -= d;
            }
            if ey[s] != 0.0 {
                let d = ey[s] * (u[s] - u[s + w]);
                out[s] += d;
                out[s + w] -= d;
            }
        }
    };
    let mut diag = vec![l2; n];
    for s in 0..n {
        diag[s] += ex[s] + ey[s];
        if ex[s] != 0.0 {
            diag[s + 1] += ex[s];
        }
        if ey[s] != 0.0 {
            diag[s + w] += ey[s];
        }
    }
    let mut out = vec![0.0f32; 3 * n];
    let (mut r, mut z, mut p, mut ap) = (vec![0.0; n], vec![0.0; n], vec![0.0; n], vec![0.0; n]);
    for c in 0..3 {
        let mut b: Vec<f64> = (0..n)
            .map(|s| l2 * f64::from(data.primal[3 * s + c]))
            .collect();
        for s in 0..n {
            if ex[s] != 0.0 {
                let g = ex[s] * f64::from(data.dx[3 * s + c]);
                b[s] -= g;
                b[s + 1] += g;
            }
            if ey[s] != 0.0 {
                let g = ey[s] * f64::from(data.dy[3 * s + c]);
                b[s] -= g;
                b[s + w] += g;
            }
        }
        // Start from the primal image.
        let mut u: Vec<f64> = (0..n).map(|s| f64::from(data.primal[3 * s + c])).collect();
        apply(&u, &mut ap);
        for s in 0..n {
            r[s] = b[s] - ap[s];
            z[s] = if diag[s] > 0.0 { r[s] / diag[s] } else { 0.0 };
            p[s] = z[s];
        }
        let b_norm = b
            .iter()
            .map(|x| x * x)
            .sum::<f64>()
            .sqrt()
            .max(f64::MIN_POSITIVE);
        let mut rz: f64 = r.iter().zip(&z).map(|(a, b)| a * b).sum();
        for _ in 0..options.max_iterations {
            let r_norm = r.iter().map(|x| x * x).sum::<f64>().sqrt();
            if r_norm <= options.tolerance * b_norm {
                break;
            }
            apply(&p, &mut ap);
            let pap: f64 = p.iter().zip(&ap).map(|(a, b)| a * b).sum();
            if !(pap > 0.0) {
                break;
            }
            let alpha = rz / pap;
            for s in 0..n {
                u[s] += alpha * p[s];
                r[s] -= alpha * ap[s];
                z[s] = if diag[s] > 0.0 { r[s] / diag[s] } else { 0.0 };
            }
            let rz_new: f64 = r.iter().zip(&z).map(|(a, b)| a * b).sum();
            let beta = rz_new / rz;
            rz = rz_new;
            for s in 0..n {
                p[s] = z[s] + beta * p[s];
            }
        }
        for s in 0..n {
            out[3 * s + c] = u[s] as f32;
        }
    }
    out
}
