//! Surrogate denoiser: edge-aware à-trous wavelet filter guided by albedo, normal and the
//! per-pixel variance (Dammertz et al. 2010, with SVGF-style variance-scaled colour
//! stopping). Its output is the surrogate ground truth `F̃` of relative-variance training
//! [Hua eq. 25, §4.2.1, §6.1]; it only weights training samples, so its bias never reaches
//! the image.
//!
//! Iteration `i` convolves with the 5×5 B3-spline kernel `[1, 4, 6, 4, 1]/16` dilated by
//! `2^i`; the weight of neighbour `q` of pixel `p` is the kernel weight times
//!
//! ```text
//! exp( −|ℓ_p − ℓ_q| / (σ_c √v_p + ε)  −  ‖a_p − a_q‖² / σ_a²  −  max(0, 1 − n_p·n_q) / σ_n )
//! ```
//!
//! with `ℓ` the channel mean, `v` its (filtered) variance, `a` albedo and `n` normal. The
//! variance is filtered alongside (`Σ w² v / (Σ w)²`) so the colour bandwidth shrinks as
//! the image gets smoother.
//!
//! | option | type | default | meaning |
//! |---|---|---|---|
//! | `iterations` | u32 | 5 | à-trous levels (support `4·2^iterations − 3` pixels) |
//! | `sigma_color` | f32 | 4 | colour bandwidth in standard deviations |
//! | `sigma_albedo` | f32 | 0.1 | albedo bandwidth (≤ 0 disables) |
//! | `sigma_normal` | f32 | 0.1 | normal bandwidth on `1 − cos` (≤ 0 disables) |
//!
//! ```json
//! { "surrogate": { "iterations": 5, "sigma_color": 4.0, "sigma_albedo": 0.1, "sigma_normal": 0.1 } }
//! ```
//!
//! # Contracts
//! - Images are `width × height` row-major: colour, albedo and normal 3 values per pixel,
//!   variance 1 per pixel. Sizes must match and values be finite (variances ≥ 0), else a
//!   typed [`DenoiseError`]; never panics.
//! - Every output pixel is a convex combination of input pixels (the centre weight is
//!   positive), so constant images are preserved and no NaN can appear.

use thiserror::Error;

/// Errors of [`atrous`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Error)]
pub enum DenoiseError {
    /// A buffer does not match the image size.
    #[error("buffer sizes do not match the image size")]
    SizeMismatch,
    /// NaN/Inf value or negative variance.
    #[error("non-finite value or negative variance")]
    InvalidValue,
}

/// À-trous options (see the module table).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AtrousOptions {
    /// Levels.
    pub iterations: u32,
    /// Colour bandwidth in standard deviations.
    pub sigma_color: f32,
    /// Albedo bandwidth (≤ 0 disables).
    pub sigma_albedo: f32,
    /// Normal bandwidth (≤ 0 disables).
    pub sigma_normal: f32,
}

impl Default for AtrousOptions {
    fn default() -> Self {
        Self {
            iterations: 5,
            sigma_color: 4.0,
            sigma_albedo: 0.1,
            sigma_normal: 0.1,
        }
    }
}

const KERNEL: [f32; 5] = [1.0 / 16.0, 4.0 / 16.0, 6.0 / 16.0, 4.0 / 16.0, 1.0 / 16.0];

/// Denoises `color` (RGB per pixel) with per-pixel `variance` of its channel mean, guided by
/// optional `albedo` and `normal` buffers. Returns the filtered RGB image.
pub fn atrous(
    color: &[f32],
    variance: &[f32],
    albedo: Option<&[f32]>,
    normal: Option<&[f32]>,
    width: usize,
    height: usize,
    options: &AtrousOptions,
) -> Result<Vec<f32>, DenoiseError> {
    let n = width
        .checked_mul(height)
        .ok_or(DenoiseError::SizeMismatch)?;
    if color.len() != 3 * n
        || variance.len() != n
        || albedo.is_some_and(|a| a.len() != 3 * n)
        || normal.is_some_and(|a| a.len() != 3 * n)
    {
        return Err(DenoiseError::SizeMismatch);
    }
    let finite = |b: &[f32]| b.iter().all(|v| v.is_finite());
    if !finite(color)
        || !variance.iter().all(|v| v.is_finite() && *v >= 0.0)
        || albedo.is_some_and(|a| !finite(a))
        || normal.is_some_and(|a| !finite(a))
    {
        return Err(DenoiseError::InvalidValue);
    }
    let inv_sa2 = (options.sigma_albedo > 0.0).then(|| 1.0 / (options.sigma_albedo.powi(2)));
    let inv_sn = (options.sigma_normal > 0.0).then(|| 1.0 / options.sigma_normal);
    let ctx = Level {
        albedo,
        normal,
        inv_sa2,
        inv_sn,
        sigma_color: options.sigma_color.max(0.0),
        width,
        height,
    };
    // Rows are independent within a level: bands of rows are filtered on all cores, each
    // pixel with the same arithmetic in the same order, so the bits do not depend on the
    // thread count.
    let threads = if n >= PARALLEL_MIN_PIXELS {
        std::thread::available_parallelism().map_or(1, |t| t.get())
    } else {
        1
    };
    Ok(filter_levels(
        color,
        variance,
        &ctx,
        options.iterations,
        threads,
    ))
}

/// The à-trous levels on `threads` threads (bands of rows); the result does not depend on
/// `threads`.
fn filter_levels(
    color: &[f32],
    variance: &[f32],
    ctx: &Level<'_>,
    iterations: u32,
    threads: usize,
) -> Vec<f32> {
    let (width, height) = (ctx.width, ctx.height);
    let n = width * height;
    let mut cur = color.to_vec();
    let mut var = variance.to_vec();
    let mut next = vec![0.0f32; 3 * n];
    let mut next_var = vec![0.0f32; n];
    let mut lum = vec![0.0f32; n];
    if n == 0 {
        return cur;
    }
    let rows_per_band = height.div_ceil(threads.max(1)).max(1);
    for it in 0..iterations.min(16) {
        let step = 1usize << it;
        // Channel means of this level, once per pixel rather than once per tap.
        for (l, c) in lum.iter_mut().zip(cur.chunks_exact(3)) {
            *l = (c[0] + c[1] + c[2]) / 3.0;
        }
        let (cur_ref, var_ref) = (&cur, &var);
        let lum_ref = &lum;
        let bands = next
            .chunks_mut(3 * width * rows_per_band)
            .zip(next_var.chunks_mut(width * rows_per_band))
            .enumerate();
        if threads > 1 {
            std::thread::scope(|s| {
                for (b, (out, out_var)) in bands {
                    s.spawn(move || {
                        let y0 = b * rows_per_band;
                        ctx.filter_rows(y0, step, cur_ref, lum_ref, var_ref, out, out_var)
                    });
                }
            });
        } else {
            for (b, (out, out_var)) in bands {
                let y0 = b * rows_per_band;
                ctx.filter_rows(y0, step, cur_ref, lum_ref, var_ref, out, out_var);
            }
        }
        std::mem::swap(&mut cur, &mut next);
        std::mem::swap(&mut var, &mut next_var);
    }
    cur
}

/// Images of at least this many pixels are filtered on several threads.
const PARALLEL_MIN_PIXELS: usize = 1 << 14;

/// What one à-trous level needs besides the current colour and variance.
struct Level<'a> {
    albedo: Option<&'a [f32]>,
    normal: Option<&'a [f32]>,
    inv_sa2: Option<f32>,
    inv_sn: Option<f32>,
    sigma_color: f32,
    width: usize,
    height: usize,
}

impl Level<'_> {
    /// Filters rows `y0..` (as many as `out_var` holds) of one level with kernel spacing
    /// `step` into `out` (RGB) and `out_var`; `lum` holds the channel means of `cur`.
    #[allow(clippy::too_many_arguments)]
    fn filter_rows(
        &self,
        y0: usize,
        step: usize,
        cur: &[f32],
        lum: &[f32],
        var: &[f32],
        out: &mut [f32],
        out_var: &mut [f32],
    ) {
        let (width, height) = (self.width, self.height);
        for (r, (row, row_var)) in out
            .chunks_mut(3 * width)
            .zip(out_var.chunks_mut(width))
            .enumerate()
        {
            let y = y0 + r;
            for x in 0..width {
                let p = y * width + x;
                let lp = lum[p];
                let denom = self.sigma_color * var[p].sqrt() + 1e-4;
                let ap = self.albedo.map(|a| [a[3 * p], a[3 * p + 1], a[3 * p + 2]]);
                let np = self
                    .normal
                    .map(|nb| [nb[3 * p], nb[3 * p + 1], nb[3 * p + 2]]);
                let (mut ws, mut wv) = (0.0f32, 0.0f32);
                let mut acc = [0.0f32; 3];
                for (j, kj) in KERNEL.iter().enumerate() {
                    let yy = y as isize + (j as isize - 2) * step as isize;
                    if yy < 0 || yy >= height as isize {
                        continue;
                    }
                    for (i, ki) in KERNEL.iter().enumerate() {
                        let xx = x as isize + (i as isize - 2) * step as isize;
                        if xx < 0 || xx >= width as isize {
                            continue;
                        }
                        let q = yy as usize * width + xx as usize;
                        let mut e = (lp - lum[q]).abs() / denom;
                        if let (Some(a), Some(ap), Some(s)) = (self.albedo, ap, self.inv_sa2) {
                            let d2: f32 = (0..3).map(|c| (ap[c] - a[3 * q + c]).powi(2)).sum();
                            e += d2 * s;
                        }
                        if let (Some(nb), Some(np), Some(s)) = (self.normal, np, self.inv_sn) {
                            let dot: f32 = (0..3).map(|c| np[c] * nb[3 * q + c]).sum();
                            e += (1.0 - dot).max(0.0) * s;
                        }
                        let w = kj * ki * (-e).exp();
                        if !(w > 0.0) {
                            continue;
                        }
                        ws += w;
                        wv += w * w * var[q];
                        for c in 0..3 {
                            acc[c] += w * cur[3 * q + c];
                        }
                    }
                }
                // The centre weight is 36/256 > 0, so `ws > 0`.
                for c in 0..3 {
                    row[3 * x + c] = acc[c] / ws;
                }
                row_var[x] = wv / (ws * ws);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lcg(state: &mut u64) -> f32 {
        *state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((*state >> 40) as f32) / (1u64 << 24) as f32
    }

    #[test]
    fn constant_image_is_preserved_and_errors_are_typed() {
        let (w, h) = (7, 5);
        let c = vec![0.25f32; 3 * w * h];
        let v = vec![0.01f32; w * h];
        let out = atrous(&c, &v, None, None, w, h, &AtrousOptions::default()).unwrap();
        assert!(out.iter().all(|x| (x - 0.25).abs() < 1e-6));
        assert_eq!(
            atrous(&c[1..], &v, None, None, w, h, &AtrousOptions::default()),
            Err(DenoiseError::SizeMismatch)
        );
        let mut bad = c.clone();
        bad[4] = f32::NAN;
        assert_eq!(
            atrous(&bad, &v, None, None, w, h, &AtrousOptions::default()),
            Err(DenoiseError::InvalidValue)
        );
        assert_eq!(
            atrous(&c, &v, None, None, usize::MAX, 2, &AtrousOptions::default()),
            Err(DenoiseError::SizeMismatch)
        );
    }

    /// Noise on a flat region drops; an albedo edge between two flat regions is kept.
    #[test]
    fn reduces_noise_and_keeps_albedo_edges() {
        let (w, h) = (32, 32);
        let mut rng = 7u64;
        let mut c = vec![0.0f32; 3 * w * h];
        let mut a = vec![0.0f32; 3 * w * h];
        let truth = |x: usize| if x < w / 2 { 0.2f32 } else { 0.8 };
        for y in 0..h {
            for x in 0..w {
                let p = y * w + x;
                let t = truth(x);
                let noisy = t * (0.5 + lcg(&mut rng));
                c[3 * p..3 * p + 3].fill(noisy);
                a[3 * p..3 * p + 3].fill(t);
            }
        }
        // Variance of t·U(0.5, 1.5) is t²/12.
        let v: Vec<f32> = (0..w * h).map(|p| truth(p % w).powi(2) / 12.0).collect();
        let out = atrous(&c, &v, Some(&a), None, w, h, &AtrousOptions::default()).unwrap();
        let mse = |img: &[f32]| {
            (0..w * h)
                .map(|p| (img[3 * p] - truth(p % w)).powi(2))
                .sum::<f32>()
                / (w * h) as f32
        };
        assert!(mse(&out) < 0.1 * mse(&c), "{} vs {}", mse(&out), mse(&c));
        // Columns next to the edge keep their side's level within 10 %.
        for y in 0..h {
            let l = out[3 * (y * w + w / 2 - 1)];
            let r = out[3 * (y * w + w / 2)];
            assert!((l - 0.2).abs() < 0.05 && (r - 0.8).abs() < 0.1, "{l} {r}");
        }
    }

    /// Bands of rows on several threads give the single thread's bits, for any band split
    /// (including more threads than rows and a last band shorter than the others).
    #[test]
    fn thread_count_does_not_change_the_bits() {
        let (w, h) = (23, 17);
        let mut rng = 11u64;
        let c: Vec<f32> = (0..3 * w * h).map(|_| lcg(&mut rng)).collect();
        let v: Vec<f32> = (0..w * h).map(|_| 0.05 * lcg(&mut rng)).collect();
        let a: Vec<f32> = (0..3 * w * h).map(|_| lcg(&mut rng)).collect();
        let nrm: Vec<f32> = (0..3 * w * h)
            .map(|i| if i % 3 == 2 { 1.0 } else { 0.0 })
            .collect();
        let ctx = Level {
            albedo: Some(&a),
            normal: Some(&nrm),
            inv_sa2: Some(1.0 / 0.1f32.powi(2)),
            inv_sn: Some(1.0 / 0.1f32),
            sigma_color: 4.0,
            width: w,
            height: h,
        };
        let bits = |t: usize| -> Vec<u32> {
            filter_levels(&c, &v, &ctx, 5, t)
                .iter()
                .map(|x| x.to_bits())
                .collect()
        };
        let one = bits(1);
        for t in [2, 3, 5, 40] {
            assert!(bits(t) == one, "{t} threads changed the bits");
        }
        // And `atrous` itself (whatever thread count it picks) agrees.
        let opts = AtrousOptions::default();
        let out = atrous(&c, &v, Some(&a), Some(&nrm), w, h, &opts).unwrap();
        assert!(out.iter().map(|x| x.to_bits()).eq(one));
        assert!(
            atrous(&[], &[], None, None, 0, 4, &opts)
                .unwrap()
                .is_empty()
        );
    }
}
