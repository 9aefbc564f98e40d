//! χ² goodness-of-fit of every BSDF's `sample` against its `pdf`, over the whole sphere, for
//! several roughnesses and outgoing directions (normal, oblique, grazing), with the harness in
//! `render::chi2`. Near-delta lobes (α < 0.05) cannot be binned reliably at this resolution;
//! they are covered by `bsdf_properties.rs` (weight = eval/pdf, finiteness, energy).
//!
//! All tests of this file form one suite of [`SUITE_SIZE`] χ² tests; each is judged at the Šidák
//! level for a family-wise false-alarm rate of 1 %.

use glam::{Vec2, Vec3};
use render::bsdf::{Bsdf, BsdfKind, RoughPlasticParams};
use render::chi2::{Chi2Config, test_directions};
use scene::Distribution::{self, Beckmann, Ggx};

/// Upper bound on the number of χ² tests in this file (for the Šidák correction).
const SUITE_SIZE: usize = 120;

/// Outgoing directions: normal, 30°, 60°, 80°, 88° (grazing), with a non-zero azimuth too.
fn wos() -> Vec<Vec3> {
    [
        (0.0f32, 0.0f32),
        (0.52, 0.7),
        (1.05, 2.0),
        (1.4, -1.0),
        (1.535, 0.3),
    ]
    .iter()
    .map(|&(t, p)| Vec3::new(t.sin() * p.cos(), t.sin() * p.sin(), t.cos()))
    .collect()
}

fn cfg(seed: u64) -> Chi2Config {
    Chi2Config {
        samples: 400_000,
        theta_bins: 64,
        phi_bins: 128,
        seed,
        test_count: SUITE_SIZE,
        ..Default::default()
    }
}

fn check(name: &str, bsdf: &Bsdf, wo: Vec3, seed: u64) {
    let r = test_directions(
        |u: Vec2, u_lobe: f32| {
            bsdf.sample(wo, u_lobe, u)
                .filter(|s| !s.delta)
                .map(|s| (s.wi, s.pdf))
        },
        |wi| bsdf.pdf(wo, wi),
        &cfg(seed),
    );
    assert!(r.passed, "{name}, wo = {wo}: {}", r.report());
}

fn rough_conductor(distribution: Distribution, alpha: f32) -> Bsdf {
    Bsdf::new(BsdfKind::RoughConductor {
        distribution,
        alpha,
        eta: Vec3::new(0.143, 0.374, 1.442),
        k: Vec3::new(3.983, 2.385, 1.603),
        specular_reflectance: Vec3::ONE,
    })
}

fn rough_plastic(
    distribution: Distribution,
    alpha: f32,
    eta: f32,
    diffuse: Vec3,
    nonlinear: bool,
) -> Bsdf {
    let d_mean = (diffuse.x + diffuse.y + diffuse.z) / 3.0;
    let params = RoughPlasticParams::new(distribution, alpha, eta, d_mean, 1.0, nonlinear);
    Bsdf::new(BsdfKind::RoughPlastic {
        params,
        diffuse_reflectance: diffuse,
        specular_reflectance: Vec3::ONE,
    })
}

#[test]
fn chi2_diffuse() {
    let bsdf = Bsdf::new(BsdfKind::Diffuse {
        reflectance: Vec3::new(0.2, 0.5, 0.8),
    });
    for (i, wo) in wos().into_iter().enumerate() {
        check("diffuse", &bsdf, wo, i as u64);
    }
}

#[test]
fn chi2_rough_conductor_ggx() {
    for alpha in [0.05, 0.2, 0.6, 1.0] {
        let bsdf = rough_conductor(Ggx, alpha);
        for (i, wo) in wos().into_iter().enumerate() {
            check(
                &format!("roughconductor ggx α={alpha}"),
                &bsdf,
                wo,
                100 + i as u64,
            );
        }
    }
}

#[test]
fn chi2_rough_conductor_beckmann() {
    for alpha in [0.05, 0.3, 1.0] {
        let bsdf = rough_conductor(Beckmann, alpha);
        for (i, wo) in wos().into_iter().enumerate() {
            check(
                &format!("roughconductor beckmann α={alpha}"),
                &bsdf,
                wo,
                200 + i as u64,
            );
        }
    }
}

#[test]
fn chi2_rough_plastic_ggx() {
    for alpha in [0.05, 0.3, 1.0] {
        let bsdf = rough_plastic(Ggx, alpha, 1.5, Vec3::new(0.02, 0.2, 0.1), false);
        for (i, wo) in wos().into_iter().enumerate() {
            check(
                &format!("roughplastic ggx α={alpha}"),
                &bsdf,
                wo,
                300 + i as u64,
            );
        }
    }
}

#[test]
fn chi2_rough_plastic_beckmann_nonlinear() {
    for alpha in [0.1, 0.5] {
        let bsdf = rough_plastic(Beckmann, alpha, 1.49, Vec3::new(0.8, 0.5, 0.1), true);
        for (i, wo) in wos().into_iter().enumerate() {
            check(
                &format!("roughplastic beckmann α={alpha}"),
                &bsdf,
                wo,
                400 + i as u64,
            );
        }
    }
}

#[test]
fn chi2_rough_plastic_eta_below_one() {
    // int_ior < ext_ior: the coating is "optically thinner" (TIR inside the tables' quadrature).
    let bsdf = rough_plastic(Ggx, 0.2, 1.0 / 1.33, Vec3::splat(0.5), false);
    for (i, wo) in wos().into_iter().enumerate() {
        check("roughplastic η<1", &bsdf, wo, 500 + i as u64);
    }
}

#[test]
fn chi2_two_sided_back_face() {
    // Seen from below, a two-sided BSDF samples the lower hemisphere with the mirrored lobe.
    let mut bsdfs = vec![
        (
            "diffuse",
            Bsdf::new(BsdfKind::Diffuse {
                reflectance: Vec3::splat(0.7),
            }),
        ),
        ("roughconductor", rough_conductor(Ggx, 0.3)),
        (
            "roughplastic",
            rough_plastic(Ggx, 0.3, 1.5, Vec3::splat(0.5), false),
        ),
    ];
    for (name, bsdf) in &mut bsdfs {
        bsdf.two_sided = true;
        for (i, wo) in wos().into_iter().enumerate() {
            let wo = Vec3::new(wo.x, wo.y, -wo.z);
            check(&format!("twosided {name} (back)"), bsdf, wo, 600 + i as u64);
        }
    }
}

#[test]
fn chi2_detects_a_slightly_wrong_roughness() {
    // Power check: samples of α = 0.22 judged against the pdf of α = 0.2 must be rejected,
    // otherwise the tests above would prove little.
    let sampled = rough_conductor(Ggx, 0.22);
    let claimed = rough_conductor(Ggx, 0.2);
    let wo = wos()[1];
    let r = test_directions(
        |u: Vec2, u_lobe: f32| {
            sampled
                .sample(wo, u_lobe, u)
                .map(|s| (s.wi, claimed.pdf(wo, s.wi)))
        },
        |wi| claimed.pdf(wo, wi),
        &cfg(900),
    );
    assert!(!r.passed && r.p_value < 1e-6, "{}", r.report());
}

#[test]
fn chi2_detects_a_wrong_lobe_selection_probability() {
    // Rough plastic whose sampler picks the specular lobe more often than its pdf says.
    let bsdf = rough_plastic(Ggx, 0.3, 1.5, Vec3::splat(0.5), false);
    let wo = wos()[2];
    let r = test_directions(
        |u: Vec2, u_lobe: f32| {
            bsdf.sample(wo, (u_lobe - 0.05).max(0.0), u)
                .map(|s| (s.wi, s.pdf))
        },
        |wi| bsdf.pdf(wo, wi),
        &cfg(901),
    );
    assert!(!r.passed, "{}", r.report());
}

#[test]
fn chi2_accepts_delta_samples_reported_as_none() {
    // A mixture: 30 % of draws are a delta lobe (returned as None); the continuous part's pdf
    // integrates to 0.7 and the harness must accept it.
    let bsdf = Bsdf::new(BsdfKind::Diffuse {
        reflectance: Vec3::ONE,
    });
    let wo = wos()[1];
    let r = test_directions(
        |u: Vec2, u_lobe: f32| {
            if u_lobe < 0.3 {
                None
            } else {
                bsdf.sample(wo, 0.5, u).map(|s| (s.wi, 0.7 * s.pdf))
            }
        },
        |wi| 0.7 * bsdf.pdf(wo, wi),
        &cfg(902),
    );
    assert!(r.passed, "{}", r.report());
    assert!((r.pdf_integral - 0.7).abs() < 1e-4 && (r.valid_fraction - 0.7).abs() < 0.005);
}
