//! Non-local means filtering: prefiltered variances for the composite estimators
//! [Rou §4.1]. (The surrogate denoiser of relative-variance training [Hua §4.2.1] is the
//! à-trous filter in [`crate::denoise`].)
//!
//! Joint NL-means in the style of Rousselle et al. 2012 (Buades et al. 2005): the weight of
//! neighbour `q` for pixel `p` is `exp(−max(0, d²(P, Q))) · exp(−Σ_features ‖f_p − f_q‖²/σ²)`
//! with the variance-cancelled patch distance
//!
//! ```text
//! d²(P, Q) = mean over patch offsets o and channels c of
//!            ((g_c(p+o) − g_c(q+o))² − α (v(p+o) + min(v(p+o), v(q+o))))
//!            / (ε + k² (v(p+o) + v(q+o)))
//! ```
//!
//! on a guide image `g` (RGB) with per-pixel variance `v`.
//!
//! | option | default | meaning |
//! |---|---|---|
//! | `radius` | 1 | search window `(2r+1)²` (3×3 as in [Rou §4.1]) |
//! | `patch_radius` | 1 | patches `(2f+1)²` |
//! | `k` | 0.45 | damping of the patch distance |
//! | `alpha` | 1.0 | variance cancellation strength |
//!
//! ```json
//! { "variance_prefilter": { "radius": 1, "patch_radius": 1, "k": 0.45, "alpha": 1.0 } }
//! ```
//!
//! # Contracts
//! - Images are `width × height` row-major; `values` has `channels` values per pixel, the
//!   guide and features 3 per pixel, variances 1 per pixel. All finite, variances ≥ 0,
//!   else a typed error.
//! - The output is a convex combination of input values (weights ≥ 0, the centre weight is
//!   1), so constant images are preserved exactly and no NaN can appear.
//! - Cost `O(width · height · (2r+1)²)`, independent of the patch size (box-filtered
//!   distances).

use thiserror::Error;

/// Errors of the filters.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Error)]
pub enum FilterError {
    /// A buffer does not match `width × height × channels`.
    #[error("buffer sizes do not match the image size")]
    SizeMismatch,
    /// NaN/Inf values or negative variances.
    #[error("non-finite value or negative variance")]
    InvalidValue,
}

/// NL-means parameters (see the module table).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NlMeansOptions {
    /// Search-window radius.
    pub radius: usize,
    /// Patch radius.
    pub patch_radius: usize,
    /// Damping `k`.
    pub k: f32,
    /// Variance cancellation `α`.
    pub alpha: f32,
}

impl Default for NlMeansOptions {
    fn default() -> Self {
        Self {
            radius: 1,
            patch_radius: 1,
            k: 0.45,
            alpha: 1.0,
        }
    }
}

/// An auxiliary feature buffer (RGB, e.g. albedo or normal) with its bandwidth `σ`.
#[derive(Clone, Copy, Debug)]
pub struct Feature<'a> {
    /// Three values per pixel.
    pub data: &'a [f32],
    /// Bandwidth; a non-positive σ disables the feature.
    pub sigma: f32,
}

/// Joint NL-means of `values` (`channels` per pixel) guided by `guide` (RGB) with per-pixel
/// `guide_var`, and optional features.
#[allow(clippy::too_many_arguments)]
pub fn nl_means(
    values: &[f32],
    channels: usize,
    guide: &[f32],
    guide_var: &[f32],
    features: &[Feature<'_>],
    width: usize,
    height: usize,
    options: &NlMeansOptions,
) -> Result<Vec<f32>, FilterError> {
    let n = width * height;
    if channels == 0
        || values.len() != n * channels
        || guide.len() != 3 * n
        || guide_var.len() != n
        || features.iter().any(|f| f.data.len() != 3 * n)
    {
        return Err(FilterError::SizeMismatch);
    }
    let finite = |b: &[f32]| b.iter().all(|v| v.is_finite());
    if !finite(values)
        || !finite(guide)
        || !guide_var.iter().all(|v| v.is_finite() && *v >= 0.0)
        || !features.iter().all(|f| finite(f.data))
    {
        return Err(FilterError::InvalidValue);
    }
    if n == 0 {
        return Ok(Vec::new());
    }
    let r = options.radius as isize;
    let f = options.patch_radius;
    let k2 = options.k * options.k;
    let alpha = options.alpha;
    let (w, h) = (width as isize, height as isize);
    let mut acc = vec![0.0f32; n * channels];
    let mut wsum = vec![0.0f32; n];
    let mut dist = vec![0.0f32; n];
    let mut tmp = vec![0.0f32; n];
    for oy in -r..=r {
        for ox in -r..=r {
            // Per-pixel distance to the pixel at the offset (∞ outside the image).
            for y in 0..h {
                for x in 0..w {
                    let p = (y * w + x) as usize;
                    let (qx, qy) = (x + ox, y + oy);
                    if qx < 0 || qy < 0 || qx >= w || qy >= h {
                        dist[p] = f32::INFINITY;
                        continue;
                    }
                    let q = (qy * w + qx) as usize;
                    let (vp, vq) = (guide_var[p], guide_var[q]);
                    let cancel = alpha * (vp + vp.min(vq));
                    let norm = 1e-10 + k2 * (vp + vq);
                    let mut d = 0.0;
                    for c in 0..3 {
                        let diff = guide[3 * p + c] - guide[3 * q + c];
                        d += (diff * diff - cancel) / norm;
                    }
                    dist[p] = d / 3.0;
                }
            }
            box_filter(&mut dist, &mut tmp, width, height, f);
            for y in 0..h {
                for x in 0..w {
                    let p = (y * w + x) as usize;
                    let d = dist[p];
                    if !(d < f32::INFINITY) {
                        continue;
                    }
                    let q = ((y + oy) * w + (x + ox)) as usize;
                    let mut e = d.max(0.0);
                    for feat in features.iter().filter(|ft| ft.sigma > 0.0) {
                        let mut s = 0.0;
                        for c in 0..3 {
                            let diff = feat.data[3 * p + c] - feat.data[3 * q + c];
                            s += diff * diff;
                        }
                        e += s / (feat.sigma * feat.sigma);
                    }
                    let wt = if ox == 0 && oy == 0 { 1.0 } else { (-e).exp() };
                    wsum[p] += wt;
                    for c in 0..channels {
                        acc[p * channels + c] += wt * values[q * channels + c];
                    }
                }
            }
        }
    }
    for p in 0..n {
        for c in 0..channels {
            acc[p * channels + c] /= wsum[p];
        }
    }
    Ok(acc)
}

/// Mean over a `(2f+1)²` box, clamped at the borders; infinities propagate (a patch that
/// leaves the image at the offset is ignored). `tmp` is scratch of the same size.
fn box_filter(data: &mut [f32], tmp: &mut [f32], w: usize, h: usize, f: usize) {
    if f == 0 {
        return;
    }
    let fi = f as isize;
    for y in 0..h {
        for x in 0..w {
            let (lo, hi) = ((x as isize - fi).max(0) as usize, (x + f).min(w - 1));
            let row = &data[y * w..(y + 1) * w];
            tmp[y * w + x] = row[lo..=hi].iter().sum::<f32>() / (hi - lo + 1) as f32;
        }
    }
    for y in 0..h {
        let (lo, hi) = ((y as isize - fi).max(0) as usize, (y + f).min(h - 1));
        for x in 0..w {
            let mut s = 0.0;
            for yy in lo..=hi {
                s += tmp[yy * w + x];
            }
            data[y * w + x] = s / (hi - lo + 1) as f32;
        }
    }
}

/// NL-means prefilter of a per-pixel variance buffer guided by the colour buffer it
/// belongs to [Rou §4.1] (3×3 window, 3×3 patches by default).
pub fn prefilter_variance(
    variance: &[f32],
    color: &[f32],
    color_var: &[f32],
    width: usize,
    height: usize,
    options: &NlMeansOptions,
) -> Result<Vec<f32>, FilterError> {
    nl_means(variance, 1, color, color_var, &[], width, height, options)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn constant_image_is_preserved_and_sizes_checked() {
        let (w, h) = (5, 4);
        let c = vec![0.7f32; 3 * w * h];
        let v = vec![0.1f32; w * h];
        let out = nl_means(&c, 3, &c, &v, &[], w, h, &NlMeansOptions::default()).unwrap();
        assert!(out.iter().all(|x| (x - 0.7).abs() < 1e-6));
        assert_eq!(
            nl_means(&c[1..], 3, &c, &v, &[], w, h, &NlMeansOptions::default()),
            Err(FilterError::SizeMismatch)
        );
        let mut bad = v.clone();
        bad[0] = -1.0;
        assert_eq!(
            prefilter_variance(&bad, &c, &bad, w, h, &NlMeansOptions::default()),
            Err(FilterError::InvalidValue)
        );
    }

    #[test]
    fn noiseless_edges_are_kept() {
        let (w, h) = (8, 6);
        let mut c = vec![0.0f32; 3 * w * h];
        for y in 0..h {
            for x in w / 2..w {
                c[3 * (y * w + x)..3 * (y * w + x) + 3].fill(5.0);
            }
        }
        let v = vec![0.0f32; w * h];
        let out = nl_means(
            &c,
            3,
            &c,
            &v,
            &[],
            w,
            h,
            &NlMeansOptions {
                radius: 2,
                ..Default::default()
            },
        )
        .unwrap();
        for (a, b) in out.iter().zip(&c) {
            assert!((a - b).abs() < 1e-4, "{a} vs {b}");
        }
    }
}
