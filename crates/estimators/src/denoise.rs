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
//! [`atrous`] with one channel filters the channel mean with the same weights; the surrogate
//! uses it, since that is all relative training needs (a third of the RGB filter's work).
//! The exponential is a polynomial `2^x` accurate to ~1e-6 relative, and taps whose exponent
//! exceeds 24 are skipped (weight below `e^-24` of the kernel's); measured on a 256×128
//! surrogate: 633 M → 378 M instructions (callgrind). Each level is then filtered tap by
//! tap over whole rows of planar buffers, branch-free (a skipped tap adds exact zeros), which
//! the compiler vectorises with the same bits as the pixel-by-pixel loop: the veach-mis
//! surrogate (384×256) 1.05 G → 0.24 G instructions.
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

/// Denoises `color` (`C` channels per pixel: 3 for RGB) with per-pixel `variance` of its
/// channel mean, guided by optional `albedo` and `normal` buffers (RGB and XYZ per pixel).
/// Returns the filtered image (`C` channels).
///
/// The weights depend only on the channel mean, the variance and the guides, so filtering the
/// channel mean alone (`C = 1`) gives the mean of the RGB result (up to rounding) at a third
/// of the work: the surrogate of relative training [Hua eq. 25] needs no more.
pub fn atrous<const C: usize>(
    color: &[f32],
    variance: &[f32],
    albedo: Option<&[f32]>,
    normal: Option<&[f32]>,
    width: usize,
    height: usize,
    options: &AtrousOptions,
) -> Result<Vec<f32>, DenoiseError> {
    const { assert!(C >= 1, "an image needs at least one channel") };
    let n = width
        .checked_mul(height)
        .ok_or(DenoiseError::SizeMismatch)?;
    if n.checked_mul(C) != Some(color.len())
        || variance.len() != n
        || albedo.is_some_and(|a| n.checked_mul(3) != Some(a.len()))
        || normal.is_some_and(|a| n.checked_mul(3) != Some(a.len()))
    {
        return Err(DenoiseError::SizeMismatch);
    }
    check_finite(color, variance, albedo, normal)?;
    let ctx = Level::new(albedo, normal, options, width, height);
    // Rows are independent within a level: bands of rows are filtered on all cores, each
    // pixel with the same arithmetic in the same order, so the bits do not depend on the
    // thread count.
    Ok(filter_levels::<C>(
        color,
        variance,
        &ctx,
        options.iterations,
        threads_for(n),
    ))
}

/// Finite values, non-negative variances.
fn check_finite(
    color: &[f32],
    variance: &[f32],
    albedo: Option<&[f32]>,
    normal: Option<&[f32]>,
) -> Result<(), DenoiseError> {
    let finite = |b: &[f32]| b.iter().all(|v| v.is_finite());
    if !finite(color)
        || !variance.iter().all(|v| v.is_finite() && *v >= 0.0)
        || albedo.is_some_and(|a| !finite(a))
        || normal.is_some_and(|a| !finite(a))
    {
        return Err(DenoiseError::InvalidValue);
    }
    Ok(())
}

/// Threads for an image of `n` pixels (the bits do not depend on it).
fn threads_for(n: usize) -> usize {
    if n >= PARALLEL_MIN_PIXELS {
        std::thread::available_parallelism().map_or(1, |t| t.get())
    } else {
        1
    }
}

/// The à-trous levels of a `C`-channel image on `threads` threads (bands of rows); the
/// result does not depend on `threads`.
///
/// Inside, images are row-planar (row `y` holds the `C` channel planes of its `width`
/// pixels), so that a band of rows is one slice and every tap reads contiguous runs of a
/// row: [`Level::filter_rows`] then runs each tap over a whole row at once, which the
/// compiler vectorises.
fn filter_levels<const C: usize>(
    color: &[f32],
    variance: &[f32],
    ctx: &Level,
    iterations: u32,
    threads: usize,
) -> Vec<f32> {
    let (width, height) = (ctx.width, ctx.height);
    let n = width * height;
    if n == 0 {
        return color.to_vec();
    }
    let mut cur = vec![0.0f32; C * n];
    for (row, src) in cur
        .chunks_exact_mut(C * width)
        .zip(color.chunks_exact(C * width))
    {
        for (x, px) in src.chunks_exact(C).enumerate() {
            for (c, &v) in px.iter().enumerate() {
                row[c * width + x] = v;
            }
        }
    }
    let mut var = variance.to_vec();
    let mut next = vec![0.0f32; C * n];
    let mut next_var = vec![0.0f32; n];
    let mut lum = vec![0.0f32; n];
    let rows_per_band = height.div_ceil(threads.max(1)).max(1);
    for it in 0..iterations.min(16) {
        let step = 1usize << it;
        // Channel means of this level, once per pixel rather than once per tap.
        for (l_row, row) in lum.chunks_exact_mut(width).zip(cur.chunks_exact(C * width)) {
            for (x, l) in l_row.iter_mut().enumerate() {
                *l = if C == 1 {
                    row[x]
                } else {
                    (0..C).map(|c| row[c * width + x]).sum::<f32>() / C as f32
                };
            }
        }
        let (cur_ref, var_ref) = (&cur, &var);
        let lum_ref = &lum;
        let bands = next
            .chunks_mut(C * width * rows_per_band)
            .zip(next_var.chunks_mut(width * rows_per_band))
            .enumerate();
        if threads > 1 {
            std::thread::scope(|s| {
                for (b, (out, out_var)) in bands {
                    s.spawn(move || {
                        let y0 = b * rows_per_band;
                        ctx.filter_rows::<C>(y0, step, cur_ref, lum_ref, var_ref, out, out_var)
                    });
                }
            });
        } else {
            for (b, (out, out_var)) in bands {
                let y0 = b * rows_per_band;
                ctx.filter_rows::<C>(y0, step, cur_ref, lum_ref, var_ref, out, out_var);
            }
        }
        std::mem::swap(&mut cur, &mut next);
        std::mem::swap(&mut var, &mut next_var);
    }
    let mut out = vec![0.0f32; C * n];
    for (dst, row) in out
        .chunks_exact_mut(C * width)
        .zip(cur.chunks_exact(C * width))
    {
        for (x, px) in dst.chunks_exact_mut(C).enumerate() {
            for (c, v) in px.iter_mut().enumerate() {
                *v = row[c * width + x];
            }
        }
    }
    out
}

/// Images of at least this many pixels are filtered on several threads.
const PARALLEL_MIN_PIXELS: usize = 1 << 14;

/// Edge-stopping exponents above this give weights below `e^-24 ≈ 4e-11` of the kernel's:
/// the tap is skipped (it could not move an `f32` sum of the centre's weight `36/256`).
const MAX_EXPONENT: f32 = 24.0;

/// `e^{-x}` for `0 <= x <= MAX_EXPONENT`, to ~1e-6 relative: `2^{-x log2 e}` split into an
/// integer power (the exponent bits) and a degree-5 polynomial of the fraction (relative
/// least-squares fit of `2^f` on `[0, 1)`, 2e-7; the rest is the rounding of `x log2 e`).
/// Plain `f32` arithmetic without fused operations, so the bits are the same on every
/// machine; a few times cheaper than the libm call it replaces, which was a sixth of the
/// filter's instructions.
#[inline]
fn exp_neg(x: f32) -> f32 {
    let t = -x * std::f32::consts::LOG2_E;
    let k = t.floor();
    let f = t - k;
    let p = 0.999_999_8
        + f * (0.693_154_75
            + f * (0.240_146_49 + f * (0.055_835_966 + f * (0.008_987_259 + f * 0.001_875_376_6))));
    // k >= -35 here, so the biased exponent stays normal.
    p * f32::from_bits(((k as i32 + 127) as u32) << 23)
}

/// The guides of all levels: albedo and normal planes (zeros when absent, with a zero
/// bandwidth factor so they add nothing) and the bandwidths.
struct Level {
    /// `[a_r, a_g, a_b, n_x, n_y, n_z]`, each a plane of `width × height` values.
    guide: [Vec<f32>; 6],
    /// `1/σ_a²`, 0 when disabled or absent.
    inv_sa2: f32,
    /// `1/σ_n`, 0 when disabled or absent.
    inv_sn: f32,
    sigma_color: f32,
    width: usize,
    height: usize,
}

/// One tap of a level over a run of pixels: the run's own values (`p`), its neighbours'
/// at the tap's offset (`q`), and the sums the tap adds to.
struct TapRun<'a, const C: usize> {
    lum_p: &'a [f32],
    inv_den: &'a [f32],
    guide_p: [&'a [f32]; 6],
    lum_q: &'a [f32],
    var_q: &'a [f32],
    guide_q: [&'a [f32]; 6],
    color_q: [&'a [f32]; C],
}

impl Level {
    fn new(
        albedo: Option<&[f32]>,
        normal: Option<&[f32]>,
        options: &AtrousOptions,
        width: usize,
        height: usize,
    ) -> Self {
        let n = width * height;
        let plane = |b: Option<&[f32]>, c: usize| -> Vec<f32> {
            b.map_or_else(
                || vec![0.0; n],
                |b| b.chunks_exact(3).map(|v| v[c]).collect(),
            )
        };
        let on = |sigma: f32, present: bool| present && sigma > 0.0;
        Self {
            guide: [
                plane(albedo, 0),
                plane(albedo, 1),
                plane(albedo, 2),
                plane(normal, 0),
                plane(normal, 1),
                plane(normal, 2),
            ],
            inv_sa2: if on(options.sigma_albedo, albedo.is_some()) {
                1.0 / (options.sigma_albedo * options.sigma_albedo)
            } else {
                0.0
            },
            inv_sn: if on(options.sigma_normal, normal.is_some()) {
                1.0 / options.sigma_normal
            } else {
                0.0
            },
            sigma_color: options.sigma_color.max(0.0),
            width,
            height,
        }
    }

    /// Filters rows `y0..` (as many as `out_var` holds) of one level with kernel spacing
    /// `step` into `out` (`C` row-planar channels) and `out_var`; `lum` holds the channel
    /// means of `cur`.
    ///
    /// Each pixel adds its taps in kernel order (row `j`, then column `i`), a tap outside
    /// the image or with an exponent of at least [`MAX_EXPONENT`] adding nothing, so a row
    /// is filtered tap by tap, each tap over the run of pixels whose neighbour is inside.
    #[allow(clippy::too_many_arguments)]
    fn filter_rows<const C: usize>(
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
        let mut inv_den = vec![0.0f32; width];
        let mut ws = vec![0.0f32; width];
        let mut wv = vec![0.0f32; width];
        let mut acc = vec![0.0f32; C * width];
        for (r, (row, row_var)) in out
            .chunks_mut(C * width)
            .zip(out_var.chunks_mut(width))
            .enumerate()
        {
            let p0 = (y0 + r) * width;
            for (d, v) in inv_den.iter_mut().zip(&var[p0..p0 + width]) {
                *d = 1.0 / (self.sigma_color * v.sqrt() + 1e-4);
            }
            ws.fill(0.0);
            wv.fill(0.0);
            acc.fill(0.0);
            for (j, &kj) in KERNEL.iter().enumerate() {
                let Some(yy) = (y0 + r + j * step)
                    .checked_sub(2 * step)
                    .filter(|&yy| yy < height)
                else {
                    continue;
                };
                for (i, &ki) in KERNEL.iter().enumerate() {
                    // Pixels `x` whose neighbour `x + i·step − 2·step` is inside the row.
                    let lo = (2 * step).saturating_sub(i * step);
                    let hi = (width + 2 * step).saturating_sub(i * step).min(width);
                    if lo >= hi {
                        continue;
                    }
                    let (q0, q1) = (lo + i * step - 2 * step, hi + i * step - 2 * step);
                    let (pa, pb) = (p0 + lo, p0 + hi);
                    let (qa, qb) = (yy * width + q0, yy * width + q1);
                    let crow = yy * C * width;
                    let run = TapRun::<C> {
                        lum_p: &lum[pa..pb],
                        inv_den: &inv_den[lo..hi],
                        guide_p: std::array::from_fn(|g| &self.guide[g][pa..pb]),
                        lum_q: &lum[qa..qb],
                        var_q: &var[qa..qb],
                        guide_q: std::array::from_fn(|g| &self.guide[g][qa..qb]),
                        color_q: std::array::from_fn(|c| {
                            &cur[crow + c * width + q0..crow + c * width + q1]
                        }),
                    };
                    let mut acc_runs = acc.chunks_exact_mut(width).map(|a| &mut a[lo..hi]);
                    let acc_run: [&mut [f32]; C] =
                        std::array::from_fn(|_| acc_runs.next().unwrap_or_default());
                    self.tap::<C>(
                        kj * ki,
                        i == 2 && j == 2,
                        &run,
                        &mut ws[lo..hi],
                        &mut wv[lo..hi],
                        acc_run,
                    );
                }
            }
            // The centre weight is at least 36/256·e^-24 > 0, so `ws > 0`.
            for (c, o) in row.chunks_exact_mut(width).enumerate() {
                for ((o, a), w) in o.iter_mut().zip(&acc[c * width..]).zip(&ws) {
                    *o = a / w;
                }
            }
            for ((o, v), w) in row_var.iter_mut().zip(&wv).zip(&ws) {
                *o = v / (w * w);
            }
        }
    }

    /// Adds one tap of kernel weight `k` to a run of pixels (`centre`: the tap is the pixel
    /// itself, which always counts, its exponent capped at [`MAX_EXPONENT`]). Branch-free,
    /// so it vectorises; a skipped tap adds exact zeros, which leaves the sums' bits as if
    /// it had not been visited.
    #[inline]
    fn tap<const C: usize>(
        &self,
        k: f32,
        centre: bool,
        run: &TapRun<'_, C>,
        ws: &mut [f32],
        wv: &mut [f32],
        acc: [&mut [f32]; C],
    ) {
        let (sa, sn) = (self.inv_sa2, self.inv_sn);
        let n = ws.len();
        let (lp, den, lq, vq) = (
            &run.lum_p[..n],
            &run.inv_den[..n],
            &run.lum_q[..n],
            &run.var_q[..n],
        );
        let gp: [&[f32]; 6] = std::array::from_fn(|g| &run.guide_p[g][..n]);
        let gq: [&[f32]; 6] = std::array::from_fn(|g| &run.guide_q[g][..n]);
        let cq: [&[f32]; C] = std::array::from_fn(|c| &run.color_q[c][..n]);
        let mut acc = acc;
        for a in &mut acc {
            *a = &mut std::mem::take(a)[..n];
        }
        for x in 0..n {
            let d0 = gp[0][x] - gq[0][x];
            let d1 = gp[1][x] - gq[1][x];
            let d2 = gp[2][x] - gq[2][x];
            let dist = d0 * d0 + d1 * d1 + d2 * d2;
            let dot = gp[3][x] * gq[3][x] + gp[4][x] * gq[4][x] + gp[5][x] * gq[5][x];
            let e = (lp[x] - lq[x]).abs() * den[x] + dist * sa + (1.0 - dot).max(0.0) * sn;
            let inside = e < MAX_EXPONENT;
            let w = k * exp_neg(if inside { e } else { MAX_EXPONENT });
            let w = if inside || centre { w } else { 0.0 };
            ws[x] += w;
            wv[x] += w * w * vq[x];
            for c in 0..C {
                acc[c][x] += w * cq[c][x];
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
        let out = atrous::<3>(&c, &v, None, None, w, h, &AtrousOptions::default()).unwrap();
        assert!(out.iter().all(|x| (x - 0.25).abs() < 1e-6));
        assert_eq!(
            atrous::<3>(&c[1..], &v, None, None, w, h, &AtrousOptions::default()),
            Err(DenoiseError::SizeMismatch)
        );
        let mut bad = c.clone();
        bad[4] = f32::NAN;
        assert_eq!(
            atrous::<3>(&bad, &v, None, None, w, h, &AtrousOptions::default()),
            Err(DenoiseError::InvalidValue)
        );
        assert_eq!(
            atrous::<3>(&c, &v, None, None, usize::MAX, 2, &AtrousOptions::default()),
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
        let out = atrous::<3>(&c, &v, Some(&a), None, w, h, &AtrousOptions::default()).unwrap();
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
        let opts = AtrousOptions::default();
        let ctx = Level::new(Some(&a), Some(&nrm), &opts, w, h);
        let bits = |t: usize| -> Vec<u32> {
            filter_levels::<3>(&c, &v, &ctx, 5, t)
                .iter()
                .map(|x| x.to_bits())
                .collect()
        };
        let one = bits(1);
        for t in [2, 3, 5, 40] {
            assert!(bits(t) == one, "{t} threads changed the bits");
        }
        // And `atrous` itself (whatever thread count it picks) agrees.
        let out = atrous::<3>(&c, &v, Some(&a), Some(&nrm), w, h, &opts).unwrap();
        assert!(out.iter().map(|x| x.to_bits()).eq(one));
        assert!(
            atrous::<3>(&[], &[], None, None, 0, 4, &opts)
                .unwrap()
                .is_empty()
        );
    }

    /// The polynomial `e^-x` against `f64` `exp` over the whole range it is used on.
    #[test]
    fn exp_neg_is_accurate_on_its_range() {
        let mut worst = 0.0f64;
        for i in 0..=240_000 {
            let x = i as f32 * (MAX_EXPONENT / 240_000.0);
            let want = (-f64::from(x)).exp();
            let got = f64::from(exp_neg(x));
            worst = worst.max((got - want).abs() / want);
        }
        assert!(worst < 5e-6, "worst relative error {worst}");
    }

    /// Filtering the channel mean gives the channel mean of the RGB filter (the weights see
    /// only the mean), to `f32` rounding.
    #[test]
    fn mono_filter_is_the_mean_of_the_rgb_filter() {
        let (w, h) = (37, 29);
        let mut rng = 5u64;
        let c: Vec<f32> = (0..3 * w * h).map(|_| lcg(&mut rng)).collect();
        let v: Vec<f32> = (0..w * h).map(|_| 0.02 * lcg(&mut rng)).collect();
        let a: Vec<f32> = (0..3 * w * h)
            .map(|i| if i % 97 < 40 { 0.2 } else { 0.7 })
            .collect();
        let nrm: Vec<f32> = (0..3 * w * h)
            .map(|i| ((i % 3 == 1) as u8) as f32)
            .collect();
        let mean: Vec<f32> = c
            .chunks_exact(3)
            .map(|x| (x[0] + x[1] + x[2]) / 3.0)
            .collect();
        let opts = AtrousOptions::default();
        let rgb = atrous::<3>(&c, &v, Some(&a), Some(&nrm), w, h, &opts).unwrap();
        let mono = atrous::<1>(&mean, &v, Some(&a), Some(&nrm), w, h, &opts).unwrap();
        for (m, x) in mono.iter().zip(rgb.chunks_exact(3)) {
            let want = (x[0] + x[1] + x[2]) / 3.0;
            assert!(
                (m - want).abs() <= 1e-5 * want.abs().max(1.0),
                "{m} vs {want}"
            );
        }
        assert_eq!(
            atrous::<1>(&mean[1..], &v, None, None, w, h, &opts),
            Err(DenoiseError::SizeMismatch)
        );
    }

    /// Bandwidths so narrow that every exponent is huge still leave the centre's weight:
    /// the output is the input, never NaN.
    #[test]
    fn tiny_bandwidths_keep_the_centre() {
        let (w, h) = (9, 7);
        let mut rng = 3u64;
        let c: Vec<f32> = (0..3 * w * h).map(|_| lcg(&mut rng)).collect();
        let v = vec![0.0f32; w * h];
        // Non-unit normals (a pixel mean of differing normals) make even the centre's normal
        // term large with σ_n = 1e-3.
        let nrm = vec![0.5f32; 3 * w * h];
        let opts = AtrousOptions {
            sigma_color: 0.0,
            sigma_normal: 1e-3,
            ..AtrousOptions::default()
        };
        let out = atrous::<3>(&c, &v, None, Some(&nrm), w, h, &opts).unwrap();
        assert!(out.iter().zip(&c).all(|(o, i)| (o - i).abs() < 1e-6));
    }

    /// The filter as it was written before it was vectorised, single-threaded: pixel by
    /// pixel on interleaved channels, a tap outside the image or above the exponent cap
    /// `continue`d. The definition the vectorised filter must match bit for bit.
    fn reference<const C: usize>(
        color: &[f32],
        variance: &[f32],
        ctx: &Level,
        iterations: u32,
    ) -> Vec<f32> {
        let (w, h) = (ctx.width, ctx.height);
        let (mut cur, mut var) = (color.to_vec(), variance.to_vec());
        let g = |q: usize| -> [f32; 6] { std::array::from_fn(|k| ctx.guide[k][q]) };
        for it in 0..iterations.min(16) {
            let step = 1usize << it;
            let lum: Vec<f32> = cur
                .chunks_exact(C)
                .map(|c| {
                    if C == 1 {
                        c[0]
                    } else {
                        c.iter().sum::<f32>() / C as f32
                    }
                })
                .collect();
            let mut next = vec![0.0f32; C * w * h];
            let mut next_var = vec![0.0f32; w * h];
            for y in 0..h {
                for x in 0..w {
                    let p = y * w + x;
                    let inv_den = 1.0 / (ctx.sigma_color * var[p].sqrt() + 1e-4);
                    let gp = g(p);
                    let (mut ws, mut wv, mut acc) = (0.0f32, 0.0f32, [0.0f32; C]);
                    for (j, kj) in KERNEL.iter().enumerate() {
                        for (i, ki) in KERNEL.iter().enumerate() {
                            let (Some(yy), Some(xx)) = (
                                (y + j * step).checked_sub(2 * step),
                                (x + i * step).checked_sub(2 * step),
                            ) else {
                                continue;
                            };
                            if yy >= h || xx >= w {
                                continue;
                            }
                            let q = yy * w + xx;
                            let gq = g(q);
                            let (mut d2, mut dot) = (0.0f32, 0.0f32);
                            for c in 0..3 {
                                let d = gp[c] - gq[c];
                                d2 += d * d;
                                dot += gp[3 + c] * gq[3 + c];
                            }
                            let mut e = (lum[p] - lum[q]).abs() * inv_den
                                + d2 * ctx.inv_sa2
                                + (1.0 - dot).max(0.0) * ctx.inv_sn;
                            if !(e < MAX_EXPONENT) {
                                if q != p {
                                    continue;
                                }
                                e = MAX_EXPONENT;
                            }
                            let wt = kj * ki * exp_neg(e);
                            ws += wt;
                            wv += wt * wt * var[q];
                            for (a, v) in acc.iter_mut().zip(&cur[C * q..C * q + C]) {
                                *a += wt * v;
                            }
                        }
                    }
                    for (o, a) in next[C * p..C * p + C].iter_mut().zip(acc) {
                        *o = a / ws;
                    }
                    next_var[p] = wv / (ws * ws);
                }
            }
            cur = next;
            var = next_var;
        }
        cur
    }

    /// The vectorised filter gives the per-pixel definition's bits: RGB and mono, with and
    /// without guides, narrow bandwidths (skipped taps, capped centres), images narrower
    /// and shorter than the kernel's spacing, on one and several threads.
    #[test]
    fn vectorised_filter_has_the_per_pixel_bits() {
        let mut rng = 19u64;
        for &(w, h) in &[(1, 1), (2, 9), (9, 2), (13, 7), (37, 23), (70, 41)] {
            let n = w * h;
            let c: Vec<f32> = (0..3 * n).map(|_| 3.0 * lcg(&mut rng)).collect();
            let mono: Vec<f32> = (0..n).map(|_| lcg(&mut rng)).collect();
            let v: Vec<f32> = (0..n).map(|_| 0.1 * lcg(&mut rng)).collect();
            let a: Vec<f32> = (0..3 * n)
                .map(|i| {
                    if (i / 3) % 11 < 5 {
                        0.2
                    } else {
                        0.9 * lcg(&mut rng)
                    }
                })
                .collect();
            let nrm: Vec<f32> = (0..3 * n).map(|_| 2.0 * lcg(&mut rng) - 1.0).collect();
            for opts in [
                AtrousOptions::default(),
                AtrousOptions {
                    sigma_color: 0.3,
                    sigma_albedo: 0.02,
                    sigma_normal: 1e-3,
                    iterations: 3,
                },
                AtrousOptions {
                    iterations: 7,
                    ..AtrousOptions::default()
                },
            ] {
                for guides in [false, true] {
                    let (ga, gn) = if guides {
                        (Some(&a[..]), Some(&nrm[..]))
                    } else {
                        (None, None)
                    };
                    let ctx = Level::new(ga, gn, &opts, w, h);
                    let bits = |x: Vec<f32>| x.into_iter().map(f32::to_bits).collect::<Vec<_>>();
                    let want_rgb = bits(reference::<3>(&c, &v, &ctx, opts.iterations));
                    let want_mono = bits(reference::<1>(&mono, &v, &ctx, opts.iterations));
                    for t in [1, 3] {
                        let got = bits(filter_levels::<3>(&c, &v, &ctx, opts.iterations, t));
                        assert!(
                            got == want_rgb,
                            "rgb {w}x{h} {opts:?} guides {guides} threads {t}"
                        );
                        let got = bits(filter_levels::<1>(&mono, &v, &ctx, opts.iterations, t));
                        assert!(
                            got == want_mono,
                            "mono {w}x{h} {opts:?} guides {guides} threads {t}"
                        );
                    }
                }
            }
        }
    }
}
