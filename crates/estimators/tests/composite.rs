//! Composite estimators [Rou §3.2, §4] against Monte Carlo simulations.

use estimators::composite::{
    RerenderBuffers, RerenderPixel, WeightScheme, keller_olkin_weights, rerender_image,
    rerender_image_cross, rerender_pixel,
};
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;

fn gauss(rng: &mut Pcg64) -> f64 {
    let (a, b): (f64, f64) = (rng.random::<f64>().max(1e-300), rng.random());
    (-2.0 * a.ln()).sqrt() * (std::f64::consts::TAU * b).cos()
}

fn var(v: &[f64]) -> (f64, f64) {
    let n = v.len() as f64;
    let m = v.iter().sum::<f64>() / n;
    (
        m,
        v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (n - 1.0),
    )
}

#[test]
fn keller_olkin_composite_attains_predicted_variance() {
    // Two unbiased estimators of 3.0 with σ₁² = 1, σ₂² = 2, correlation 0.5.
    let (s1, s2, rho) = (1.0f64, 2.0f64.sqrt(), 0.5);
    let cov = [s1 * s1, rho * s1 * s2, rho * s1 * s2, s2 * s2];
    let w = keller_olkin_weights(&cov, &[1.0, 1.0]).unwrap();
    assert_eq!(w.scheme, WeightScheme::KellerOlkin);
    let mut rng = Pcg64::seed_from_u64(1);
    let n = 200_000;
    let combined: Vec<f64> = (0..n)
        .map(|_| {
            let (z1, z2) = (gauss(&mut rng), gauss(&mut rng));
            let a = 3.0 + s1 * z1;
            let b = 3.0 + s2 * (rho * z1 + (1.0 - rho * rho).sqrt() * z2);
            w.weights[0] * a + w.weights[1] * b
        })
        .collect();
    let (m, v) = var(&combined);
    assert!((m - 3.0).abs() < 5.0 * (v / n as f64).sqrt());
    // Predicted (eΣ⁻¹eᵀ)⁻¹; sampling error of a variance ≈ v·sqrt(2/n).
    assert!(
        (v - w.variance).abs() < 5.0 * w.variance * (2.0 / n as f64).sqrt(),
        "{v} vs {}",
        w.variance
    );
    assert!(w.variance <= 1.0);
}

/// One simulated pixel: `n` new paths with old contribution h and new f = 1.3 h + noise,
/// and `m` control paths of h. True value of F = 1.3 · 2 + 0 = 2.6.
fn simulate(rng: &mut Pcg64, n: usize, m: usize) -> RerenderPixel {
    let (mut f, mut h, mut d) = (Vec::new(), Vec::new(), Vec::new());
    for _ in 0..n {
        let hv = 2.0 + gauss(rng);
        let fv = 1.3 * hv + 0.2 * gauss(rng);
        f.push(fv);
        h.push(hv);
        d.push(fv - hv);
    }
    let h0: Vec<f64> = (0..m).map(|_| 2.0 + gauss(rng)).collect();
    let (mf, vf) = var(&f);
    let (_, vh) = var(&h);
    let (md, vd) = var(&d);
    let (mh0, vh0) = var(&h0);
    RerenderPixel {
        f1: [mf; 3],
        d1: [md; 3],
        h0: [mh0; 3],
        var_f1: vf / n as f64,
        var_h1: vh / n as f64,
        var_d1: vd / n as f64,
        var_h0: vh0 / m as f64,
        spp_new: n as f64,
        spp_control: m as f64,
    }
}

#[test]
fn rerender_composite_beats_both_inputs() {
    let mut rng = Pcg64::seed_from_u64(2);
    let (mut comp, mut plain, mut cv) = (Vec::new(), Vec::new(), Vec::new());
    for _ in 0..4000 {
        let px = simulate(&mut rng, 16, 256);
        let (v, w) = rerender_pixel(&px).unwrap();
        assert!((w.weights.iter().sum::<f64>() - 1.0).abs() < 1e-12);
        comp.push(v[0]);
        plain.push(px.f1[0]);
        cv.push(px.d1[0] + px.h0[0]);
    }
    let ((mc, vc), (_, vp), (_, vs)) = (var(&comp), var(&plain), var(&cv));
    assert!(vc < vp && vc < vs, "composite {vc}, plain {vp}, cv {vs}");
    // Statistics from the same samples bias the composite slightly; it must stay small.
    assert!((mc - 2.6).abs() < 0.01, "mean {mc}");
}

#[test]
fn rerender_cross_weighting_is_unbiased() {
    // Half buffers A and B per pixel (one pixel per trial); A weighted by B and vice versa.
    let mut rng = Pcg64::seed_from_u64(3);
    let trials = 4000;
    let mut vals = Vec::with_capacity(trials);
    let mut biased = Vec::with_capacity(trials);
    for _ in 0..trials {
        let (a, b) = (simulate(&mut rng, 4, 8), simulate(&mut rng, 4, 8));
        let buf = |p: &RerenderPixel| {
            (
                p.f1.map(|x| x as f32),
                p.d1.map(|x| x as f32),
                p.h0.map(|x| x as f32),
                [
                    p.var_f1 as f32,
                    p.var_h1 as f32,
                    p.var_d1 as f32,
                    p.var_h0 as f32,
                ],
            )
        };
        let (fa, da, ha, va) = buf(&a);
        let (fb, db, hb, vb) = buf(&b);
        let ba = RerenderBuffers {
            f1: &fa,
            d1: &da,
            h0: &ha,
            var_f1: &va[0..1],
            var_h1: &va[1..2],
            var_d1: &va[2..3],
            var_h0: &va[3..4],
            spp_new: 4.0,
            spp_control: 8.0,
        };
        let bb = RerenderBuffers {
            f1: &fb,
            d1: &db,
            h0: &hb,
            var_f1: &vb[0..1],
            var_h1: &vb[1..2],
            var_d1: &vb[2..3],
            var_h0: &vb[3..4],
            ..ba
        };
        vals.push(f64::from(rerender_image_cross(&ba, &bb).unwrap()[0]));
        biased.push(f64::from(rerender_image(&ba).unwrap()[0]));
    }
    let (m, v) = var(&vals);
    assert!(
        (m - 2.6).abs() < 4.5 * (v / trials as f64).sqrt(),
        "cross-weighted mean {m}"
    );
    assert!(biased.iter().all(|x| x.is_finite()));
}

#[test]
fn rerender_zero_variances_use_sample_rates() {
    let px = RerenderPixel {
        f1: [1.0; 3],
        d1: [0.0; 3],
        h0: [1.0; 3],
        var_f1: 0.0,
        var_h1: 0.0,
        var_d1: 0.0,
        var_h0: 0.0,
        spp_new: 64.0,
        spp_control: 1024.0,
    };
    let (v, w) = rerender_pixel(&px).unwrap();
    assert_eq!(w.scheme, WeightScheme::SampleRate);
    assert!((w.weights[0] - 1024.0 / 1088.0).abs() < 1e-12);
    assert!((v[0] - 1.0).abs() < 1e-12);
    assert!(
        rerender_pixel(&RerenderPixel {
            var_h0: f64::NAN,
            ..px
        })
        .is_err()
    );
}
