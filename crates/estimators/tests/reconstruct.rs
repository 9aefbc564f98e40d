//! Image-space reconstructions [Rou §5] on synthetic images with known answers.

use estimators::metrics::compare;
use estimators::reconstruct::{
    GradientBuffers, PoissonOptions, ReconstructError, WeightedOptions, poisson_l2,
    uniform_iterated, weighted_iterated, weighted_iterated_cross, weighted_poisson_l2,
};
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;

/// Owned buffers for a test image.
struct Owned {
    w: usize,
    h: usize,
    f: Vec<f32>,
    fv: Vec<f32>,
    x: Vec<f32>,
    xv: Vec<f32>,
    y: Vec<f32>,
    yv: Vec<f32>,
}

impl Owned {
    fn view(&self) -> GradientBuffers<'_> {
        GradientBuffers {
            width: self.w,
            height: self.h,
            primal: &self.f,
            primal_var: &self.fv,
            dx: &self.x,
            dx_var: &self.xv,
            dy: &self.y,
            dy_var: &self.yv,
        }
    }
}

/// A smooth image with a bright square.
fn ground_truth(w: usize, h: usize) -> Vec<f32> {
    let mut g = vec![0.0f32; 3 * w * h];
    for y in 0..h {
        for x in 0..w {
            let (u, v) = (x as f32 / w as f32, y as f32 / h as f32);
            let bright = if (w / 3..w / 2).contains(&x) && (h / 3..h / 2).contains(&y) {
                4.0
            } else {
                0.0
            };
            let s = 3 * (y * w + x);
            g[s] = 0.2 + 0.5 * u + bright;
            g[s + 1] = 0.3 + 0.3 * (6.0 * v).sin().abs() + bright;
            g[s + 2] = 0.1 + u * v + 0.5 * bright;
        }
    }
    g
}

/// Noisy primal (σ_f) and noisy differences (σ_g) of `g`; σ = 0 gives exact buffers.
fn noisy(g: &[f32], w: usize, h: usize, sf: f32, sg: f32, seed: u64) -> Owned {
    let mut rng = Pcg64::seed_from_u64(seed);
    let mut gauss = move || {
        // Box–Muller.
        let (a, b): (f32, f32) = (rng.random::<f32>().max(1e-7), rng.random());
        (-2.0 * a.ln()).sqrt() * (std::f32::consts::TAU * b).cos()
    };
    let n = w * h;
    let mut o = Owned {
        w,
        h,
        f: vec![0.0; 3 * n],
        fv: vec![sf * sf; n],
        x: vec![0.0; 3 * n],
        xv: vec![sg * sg; n],
        y: vec![0.0; 3 * n],
        yv: vec![sg * sg; n],
    };
    for yy in 0..h {
        for xx in 0..w {
            let s = yy * w + xx;
            for c in 0..3 {
                o.f[3 * s + c] = g[3 * s + c] + sf * gauss();
                if xx + 1 < w {
                    o.x[3 * s + c] = g[3 * (s + 1) + c] - g[3 * s + c] + sg * gauss();
                }
                if yy + 1 < h {
                    o.y[3 * s + c] = g[3 * (s + w) + c] - g[3 * s + c] + sg * gauss();
                }
            }
        }
    }
    o
}

fn mean(v: &[f32]) -> f64 {
    v.iter().map(|&x| f64::from(x)).sum::<f64>() / v.len() as f64
}

#[test]
fn uniform_iteration_converges_to_integrated_gradient_image() {
    let (w, h) = (12, 10);
    let g = ground_truth(w, h);
    let img = noisy(&g, w, h, 0.3, 0.0, 1);
    let u = uniform_iterated(&img.view(), 6000).unwrap();
    // The limit is G plus a constant: the mean of the noise weighted by each pixel's
    // number of estimators (1 + number of neighbours), which the iteration preserves.
    for c in 0..3 {
        let (mut num, mut den) = (0.0f64, 0.0f64);
        for y in 0..h {
            for x in 0..w {
                let k = 1
                    + usize::from(x > 0)
                    + usize::from(x + 1 < w)
                    + usize::from(y > 0)
                    + usize::from(y + 1 < h);
                let s = 3 * (y * w + x) + c;
                num += k as f64 * f64::from(img.f[s] - g[s]);
                den += k as f64;
            }
        }
        let offset = num / den;
        for s in (c..3 * w * h).step_by(3) {
            let d = f64::from(u[s] - g[s]) - offset;
            assert!(d.abs() < 1e-3, "pixel {s}: off by {d}");
        }
    }
    // Few iterations interpolate between F and the integrated gradients: error drops.
    let early = uniform_iterated(&img.view(), 5).unwrap();
    assert!(compare(&early, &g).mse < compare(&img.f, &g).mse);
}

#[test]
fn poisson_l2_with_exact_gradients_reproduces_image() {
    let (w, h) = (40, 30);
    let g = ground_truth(w, h);
    let exact = noisy(&g, w, h, 0.0, 0.0, 2);
    let u = poisson_l2(&exact.view(), &PoissonOptions::default()).unwrap();
    let e = compare(&u, &g);
    assert!(e.mse < 1e-10, "mse {}", e.mse);
    // Noisy primal, exact gradients: the screened solve removes most of the noise and keeps
    // the mean (the gradient terms integrate to zero).
    let noisy_f = noisy(&g, w, h, 0.3, 0.0, 3);
    let u = poisson_l2(&noisy_f.view(), &PoissonOptions::default()).unwrap();
    assert!(compare(&u, &g).mse < 0.1 * compare(&noisy_f.f, &g).mse);
    assert!((mean(&u) - mean(&noisy_f.f)).abs() < 1e-4);
}

#[test]
fn weighted_l2_with_exact_gradients_reproduces_image_and_denoises() {
    let (w, h) = (40, 30);
    let g = ground_truth(w, h);
    let exact = noisy(&g, w, h, 0.0, 0.0, 4);
    let u = weighted_poisson_l2(&exact.view(), &exact.view(), &PoissonOptions::default()).unwrap();
    assert!(compare(&u, &g).mse < 1e-10);
    let img = noisy(&g, w, h, 0.3, 0.05, 5);
    let u = weighted_poisson_l2(&img.view(), &img.view(), &PoissonOptions::default()).unwrap();
    assert!(compare(&u, &g).mse < 0.5 * compare(&img.f, &g).mse);
    assert!((mean(&u) - mean(&img.f)).abs() < 1e-3 * mean(&img.f));
}

#[test]
fn weighted_iteration_preserves_image_mean_and_reduces_error() {
    let (w, h) = (64, 48);
    let g = ground_truth(w, h);
    let img = noisy(&g, w, h, 0.3, 0.05, 6);
    let u = weighted_iterated(&img.view(), &img.view(), &WeightedOptions::default()).unwrap();
    let (mu, mf) = (mean(&u), mean(&img.f));
    assert!((mu - mf).abs() < 2e-3 * mf, "mean {mu} vs input {mf}");
    let (eu, ef) = (compare(&u, &g).mse, compare(&img.f, &g).mse);
    assert!(eu < 0.2 * ef, "weighted mse {eu} vs input {ef}");
}

#[test]
fn weighted_iteration_beats_uniform_when_gradient_noise_varies() {
    // Left half: very noisy differences (σ = 1); right half: clean ones (σ = 0.01). Uniform
    // weights spread the bad gradients; inverse-variance weights discount them.
    let (w, h) = (64, 48);
    let g = ground_truth(w, h);
    let bad = noisy(&g, w, h, 0.3, 1.0, 11);
    let mut img = noisy(&g, w, h, 0.3, 0.01, 12);
    for y in 0..h {
        for x in 0..w / 2 {
            let s = y * w + x;
            img.xv[s] = bad.xv[s];
            img.yv[s] = bad.yv[s];
            img.x[3 * s..3 * s + 3].copy_from_slice(&bad.x[3 * s..3 * s + 3]);
            img.y[3 * s..3 * s + 3].copy_from_slice(&bad.y[3 * s..3 * s + 3]);
        }
    }
    let weighted =
        weighted_iterated(&img.view(), &img.view(), &WeightedOptions::default()).unwrap();
    let uniform = uniform_iterated(&img.view(), 100).unwrap();
    let (ew, eu) = (compare(&weighted, &g).mse, compare(&uniform, &g).mse);
    assert!(ew < 0.5 * eu, "weighted {ew} uniform {eu}");
}

#[test]
fn cross_weighted_reconstruction_is_finite_and_mean_preserving() {
    let (w, h) = (48, 32);
    let g = ground_truth(w, h);
    let a = noisy(&g, w, h, 0.4, 0.07, 7);
    let b = noisy(&g, w, h, 0.4, 0.07, 8);
    let u = weighted_iterated_cross(&a.view(), &b.view(), &WeightedOptions::default()).unwrap();
    assert!(u.iter().all(|v| v.is_finite()));
    let both: Vec<f32> = a.f.iter().zip(&b.f).map(|(x, y)| 0.5 * (x + y)).collect();
    assert!((mean(&u) - mean(&both)).abs() < 2e-3 * mean(&both));
    assert!(compare(&u, &g).mse < 0.3 * compare(&both, &g).mse);
}

#[test]
fn zero_variances_keep_the_input() {
    // All-zero variances (e.g. a constant image): the self estimator is exact, no NaN.
    let (w, h) = (8, 6);
    let g = ground_truth(w, h);
    let mut img = noisy(&g, w, h, 0.0, 0.0, 9);
    img.fv.iter_mut().for_each(|v| *v = 0.0);
    img.xv.iter_mut().for_each(|v| *v = 1.0);
    img.yv.iter_mut().for_each(|v| *v = 1.0);
    let u = weighted_iterated(&img.view(), &img.view(), &WeightedOptions::default()).unwrap();
    for (a, b) in u.iter().zip(&g) {
        assert!((a - b).abs() < 1e-5);
    }
}

#[test]
fn invalid_buffers_are_typed_errors() {
    let g = ground_truth(4, 4);
    let mut img = noisy(&g, 4, 4, 0.1, 0.1, 10);
    let mut v = img.view();
    v.width = 5;
    assert_eq!(uniform_iterated(&v, 1), Err(ReconstructError::SizeMismatch));
    v.width = 0;
    assert_eq!(uniform_iterated(&v, 1), Err(ReconstructError::Empty));
    img.fv[3] = -1.0;
    assert_eq!(
        weighted_iterated(&img.view(), &img.view(), &WeightedOptions::default()),
        Err(ReconstructError::InvalidValue)
    );
    img.fv[3] = 0.0;
    img.x[0] = f32::NAN;
    assert_eq!(
        poisson_l2(&img.view(), &PoissonOptions::default()),
        Err(ReconstructError::InvalidValue)
    );
}

#[test]
fn prefiltered_variances_stay_non_negative_and_less_noisy() {
    use estimators::filter::{NlMeansOptions, prefilter_variance};
    let (w, h) = (64, 48);
    let g = ground_truth(w, h);
    let img = noisy(&g, w, h, 0.3, 0.0, 13);
    // Prefiltered variances stay non-negative and close to the true value on average.
    let mut rng = Pcg64::seed_from_u64(14);
    let sample_var: Vec<f32> = (0..w * h)
        .map(|_| 0.09 * (0.5 + rng.random::<f32>()))
        .collect();
    let pre = prefilter_variance(
        &sample_var,
        &img.f,
        &img.fv,
        w,
        h,
        &NlMeansOptions::default(),
    )
    .unwrap();
    assert!(pre.iter().all(|v| *v >= 0.0 && v.is_finite()));
    let spread = |v: &[f32]| {
        v.iter()
            .map(|x| (f64::from(*x) - 0.09).powi(2))
            .sum::<f64>()
    };
    assert!(spread(&pre) < spread(&sample_var));
}

/// Half buffer of `n` exponential samples per pixel (mean G, variance G², skewed so that
/// the sample variance correlates with the sample mean), with its sample variance of the
/// mean, plus noisy differences of known variance.
fn exp_half(g: &[f32], w: usize, h: usize, n: usize, rng: &mut Pcg64) -> Owned {
    let np = w * h;
    let mut o = Owned {
        w,
        h,
        f: vec![0.0; 3 * np],
        fv: vec![0.0; np],
        x: vec![0.0; 3 * np],
        xv: vec![0.01; np],
        y: vec![0.0; 3 * np],
        yv: vec![0.01; np],
    };
    for s in 0..np {
        let mut var = 0.0;
        for c in 0..3 {
            let xs: Vec<f32> = (0..n)
                .map(|_| -g[3 * s + c] * rng.random::<f32>().max(1e-7).ln())
                .collect();
            let m = xs.iter().sum::<f32>() / n as f32;
            let sv = xs.iter().map(|x| (x - m).powi(2)).sum::<f32>() / (n as f32 - 1.0);
            o.f[3 * s + c] = m;
            var += sv / n as f32 / 3.0;
        }
        o.fv[s] = var;
        for c in 0..3 {
            let noise = |rng: &mut Pcg64| 0.1 * (rng.random::<f32>() - 0.5) * 12f32.sqrt();
            if s % w + 1 < w {
                o.x[3 * s + c] = g[3 * (s + 1) + c] - g[3 * s + c] + noise(rng);
            }
            if s / w + 1 < h {
                o.y[3 * s + c] = g[3 * (s + w) + c] - g[3 * s + c] + noise(rng);
            }
        }
    }
    o
}

#[test]
fn cross_weighting_removes_the_bias_of_self_weighted_reconstruction() {
    // [Rou §5.5, Fig. 7]: weights computed from the data's own sample variances bias the
    // result (high samples come with high variances and get low weights); weighting each
    // half with the other half's statistics is unbiased.
    let (w, h) = (12, 10);
    let g = ground_truth(w, h);
    let mut rng = Pcg64::seed_from_u64(21);
    let opts = WeightedOptions {
        iterations: 20,
        ..WeightedOptions::default()
    };
    let rel_err = |u: &[f32]| {
        u.iter()
            .zip(&g)
            .map(|(a, b)| f64::from((a - b) / b))
            .sum::<f64>()
            / u.len() as f64
    };
    let (mut cross, mut own) = (Vec::new(), Vec::new());
    for _ in 0..1000 {
        let a = exp_half(&g, w, h, 4, &mut rng);
        let b = exp_half(&g, w, h, 4, &mut rng);
        cross.push(rel_err(
            &weighted_iterated_cross(&a.view(), &b.view(), &opts).unwrap(),
        ));
        own.push(rel_err(
            &weighted_iterated(&a.view(), &a.view(), &opts).unwrap(),
        ));
    }
    let stats = |v: &[f64]| {
        let n = v.len() as f64;
        let m = v.iter().sum::<f64>() / n;
        (
            m,
            (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (n - 1.0) / n).sqrt(),
        )
    };
    let ((mc, sc), (mo, so)) = (stats(&cross), stats(&own));
    eprintln!("relative bias: cross {mc:.4} ± {sc:.4}, self-weighted {mo:.4} ± {so:.4}");
    assert!(mc.abs() < 4.5 * sc, "cross-weighted bias {mc} (se {sc})");
    assert!(
        mo < -4.5 * so,
        "self-weighted reconstruction should be biased low: {mo} (se {so})"
    );
}
