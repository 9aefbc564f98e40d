//! Properties every BSDF must have: sample weight = eval/pdf, Helmholtz reciprocity, energy
//! conservation (Monte-Carlo albedo ≤ 1; exactly ρ for diffuse), one-/two-sided behaviour, no
//! NaN at grazing angles or extreme roughness, and the `MaterialTable` mapping from scene
//! materials. Monte-Carlo checks use fixed seeds and tolerances of 5 standard errors.

use glam::{Affine2, Vec2, Vec3};
use render::bsdf::{Bsdf, BsdfKind, MaterialTable, RoughPlasticParams};
use render::chi2::Pcg32;
use scene::Distribution::{self, Beckmann, Ggx};
use std::f32::consts::PI;

fn rough_conductor(distribution: Distribution, alpha: f32) -> Bsdf {
    Bsdf::new(BsdfKind::RoughConductor {
        distribution,
        alpha,
        eta: Vec3::new(0.2, 0.9, 1.1),
        k: Vec3::new(3.9, 2.45, 2.14),
        specular_reflectance: Vec3::ONE,
    })
}

fn rough_plastic(distribution: Distribution, alpha: f32, diffuse: Vec3, nonlinear: bool) -> Bsdf {
    let d_mean = (diffuse.x + diffuse.y + diffuse.z) / 3.0;
    let params = RoughPlasticParams::new(distribution, alpha, 1.5, d_mean, 1.0, nonlinear);
    Bsdf::new(BsdfKind::RoughPlastic {
        params,
        diffuse_reflectance: diffuse,
        specular_reflectance: Vec3::ONE,
    })
}

fn conductor() -> Bsdf {
    Bsdf::new(BsdfKind::Conductor {
        eta: Vec3::new(0.2, 0.9, 1.1),
        k: Vec3::new(3.9, 2.45, 2.14),
        specular_reflectance: Vec3::ONE,
    })
}

/// Non-delta BSDFs at the given roughness, with names.
fn glossy_bsdfs(alpha: f32) -> Vec<(String, Bsdf)> {
    vec![
        (
            format!("roughconductor ggx α={alpha}"),
            rough_conductor(Ggx, alpha),
        ),
        (
            format!("roughconductor beckmann α={alpha}"),
            rough_conductor(Beckmann, alpha),
        ),
        (
            format!("roughplastic ggx α={alpha}"),
            rough_plastic(Ggx, alpha, Vec3::new(0.2, 0.5, 0.9), false),
        ),
        (
            format!("roughplastic beckmann α={alpha} nonlinear"),
            rough_plastic(Beckmann, alpha, Vec3::splat(0.9), true),
        ),
    ]
}

fn all_bsdfs() -> Vec<(String, Bsdf)> {
    let mut v = vec![(
        "diffuse".to_owned(),
        Bsdf::new(BsdfKind::Diffuse {
            reflectance: Vec3::new(0.3, 0.6, 0.9),
        }),
    )];
    for alpha in [0.05, 0.3, 1.0] {
        v.extend(glossy_bsdfs(alpha));
    }
    v
}

fn dir(theta: f32, phi: f32) -> Vec3 {
    Vec3::new(
        theta.sin() * phi.cos(),
        theta.sin() * phi.sin(),
        theta.cos(),
    )
}

fn uniform_hemisphere(rng: &mut Pcg32) -> Vec3 {
    let z = rng.next_f32();
    let r = (1.0 - z * z).max(0.0).sqrt();
    let phi = 2.0 * PI * rng.next_f32();
    Vec3::new(r * phi.cos(), r * phi.sin(), z)
}

fn rel_close(a: Vec3, b: Vec3, tol: f32) -> bool {
    (a - b).abs().max_element() <= tol * a.abs().max(b.abs()).max_element().max(1e-6)
}

#[test]
fn sample_weight_equals_eval_over_pdf() {
    let mut rng = Pcg32::new(1, 1);
    for (name, bsdf) in all_bsdfs() {
        for theta in [0.0f32, 0.4, 0.9, 1.3, 1.55] {
            let wo = dir(theta, 0.7);
            for _ in 0..500 {
                let u = Vec2::new(rng.next_f32(), rng.next_f32());
                let Some(s) = bsdf.sample(wo, rng.next_f32(), u) else {
                    continue;
                };
                assert!(!s.delta && s.pdf > 0.0 && s.wi.z > 0.0, "{name}: {s:?}");
                let f = bsdf.eval(wo, s.wi);
                let p = bsdf.pdf(wo, s.wi);
                assert!(
                    (p - s.pdf).abs() <= 1e-4 * p,
                    "{name} wo={wo}: pdf {p} vs sample {}",
                    s.pdf
                );
                assert!(
                    rel_close(s.weight, f / p, 1e-3),
                    "{name} wo={wo}: weight {} vs eval/pdf {}",
                    s.weight,
                    f / p
                );
            }
        }
    }
}

#[test]
fn helmholtz_reciprocity() {
    let mut rng = Pcg32::new(2, 1);
    for (name, bsdf) in all_bsdfs() {
        for _ in 0..2000 {
            let a = uniform_hemisphere(&mut rng);
            let b = uniform_hemisphere(&mut rng);
            // f(a, b) = eval(a, b)/cos θb must equal f(b, a) = eval(b, a)/cos θa.
            let fab = bsdf.eval(a, b) / b.z;
            let fba = bsdf.eval(b, a) / a.z;
            assert!(
                rel_close(fab, fba, 2e-3),
                "{name}: f({a}, {b}) = {fab} but f({b}, {a}) = {fba}"
            );
        }
    }
}

/// Monte-Carlo albedo ∫ eval dwi by BSDF sampling: (mean, standard error) per channel.
fn albedo(bsdf: &Bsdf, wo: Vec3, n: usize, seed: u64) -> (Vec3, Vec3) {
    let mut rng = Pcg32::new(seed, 3);
    let (mut sum, mut sum2) = (Vec3::ZERO, Vec3::ZERO);
    for _ in 0..n {
        let u = Vec2::new(rng.next_f32(), rng.next_f32());
        if let Some(s) = bsdf.sample(wo, rng.next_f32(), u) {
            sum += s.weight;
            sum2 += s.weight * s.weight;
        }
    }
    let mean = sum / n as f32;
    let var = (sum2 / n as f32 - mean * mean).max(Vec3::ZERO);
    (mean, (var / n as f32).powf(0.5))
}

#[test]
fn energy_albedo_at_most_one() {
    for (name, bsdf) in all_bsdfs() {
        for theta in [0.0f32, 0.8, 1.3, 1.55] {
            let wo = dir(theta, 0.2);
            let (mean, se) = albedo(&bsdf, wo, 50_000, 7);
            assert!(mean.is_finite(), "{name}");
            assert!(
                (mean - 5.0 * se).max_element() <= 1.0,
                "{name} θo={theta}: albedo {mean} ± {se}"
            );
        }
    }
}

#[test]
fn white_plastic_albedo_at_most_one() {
    // The layered model's diffuse term ρ/(1 − R_int)·T·T/η² with ρ = 1 must not create energy.
    for alpha in [0.05, 0.3, 1.0] {
        for nonlinear in [false, true] {
            let bsdf = rough_plastic(Ggx, alpha, Vec3::ONE, nonlinear);
            for theta in [0.0f32, 0.8, 1.3, 1.55] {
                let (mean, se) = albedo(&bsdf, dir(theta, 0.0), 50_000, 8);
                assert!(
                    mean.x - 5.0 * se.x <= 1.0,
                    "α={alpha} nonlinear={nonlinear} θo={theta}: {mean} ± {se}"
                );
            }
        }
    }
}

#[test]
fn diffuse_white_furnace_is_exactly_the_reflectance() {
    // Uniform hemisphere sampling (independent of the BSDF's own sampler): ∫ eval dwi = ρ.
    let rho = Vec3::new(0.25, 0.5, 1.0);
    let bsdf = Bsdf::new(BsdfKind::Diffuse { reflectance: rho });
    let mut rng = Pcg32::new(3, 3);
    let n = 200_000;
    let (mut sum, mut sum2) = (Vec3::ZERO, Vec3::ZERO);
    for _ in 0..n {
        let wi = uniform_hemisphere(&mut rng);
        let v = bsdf.eval(dir(0.6, 1.0), wi) * (2.0 * PI);
        sum += v;
        sum2 += v * v;
    }
    let mean = sum / n as f32;
    let se = ((sum2 / n as f32 - mean * mean) / n as f32).powf(0.5);
    assert!(
        ((mean - rho).abs() - 5.0 * se).max_element() <= 0.0,
        "{mean} ± {se} vs {rho}"
    );
    // And the sampled weight is exactly ρ.
    let s = bsdf
        .sample(dir(0.6, 1.0), 0.3, Vec2::new(0.3, 0.8))
        .unwrap();
    assert_eq!(s.weight, rho);
}

#[test]
fn rough_conductor_albedo_tends_to_fresnel_when_smooth() {
    // At α = 0.01 the lobe is nearly a mirror: albedo ≈ F(cos θo) (masking ≈ 1 away from grazing).
    let rough = rough_conductor(Ggx, 0.01);
    let smooth = conductor();
    for theta in [0.0f32, 0.5, 1.0] {
        let wo = dir(theta, 0.3);
        let (mean, _) = albedo(&rough, wo, 20_000, 9);
        let f = smooth.sample(wo, 0.5, Vec2::splat(0.5)).unwrap().weight;
        assert!(rel_close(mean, f, 0.01), "θo={theta}: {mean} vs F = {f}");
    }
}

#[test]
fn near_delta_lobes_sample_near_the_mirror_direction() {
    for alpha in [1e-4f32, 0.01] {
        for (name, bsdf) in [
            ("conductor", rough_conductor(Ggx, alpha)),
            ("beckmann", rough_conductor(Beckmann, alpha)),
        ] {
            let wo = dir(0.7, 1.1);
            let mirror = Vec3::new(-wo.x, -wo.y, wo.z);
            let mut rng = Pcg32::new(4, 4);
            let n = 1000;
            let mut near = 0;
            for _ in 0..n {
                let u = Vec2::new(rng.next_f32(), rng.next_f32());
                let s = bsdf
                    .sample(wo, 0.5, u)
                    .expect("a near-mirror sample above the horizon");
                assert!(s.weight.is_finite() && s.pdf.is_finite());
                // θh < 10α ⇒ wi within 20α of the mirror direction. GGX puts 1/(1+10²) ≈ 1 % of
                // its normals beyond 10α (long tails), Beckmann e^{-100}.
                if s.wi.dot(mirror) > (20.0 * alpha).cos() - 1e-4 {
                    near += 1;
                }
            }
            assert!(
                near as f32 >= 0.97 * n as f32,
                "{name} α={alpha}: only {near}/{n} near the mirror direction"
            );
        }
    }
}

#[test]
fn smooth_conductor_is_delta() {
    let c = conductor();
    assert!(c.is_delta());
    let wo = dir(0.5, 0.5);
    let s = c.sample(wo, 0.1, Vec2::new(0.2, 0.9)).unwrap();
    assert!(s.delta && s.pdf == 1.0);
    assert!((s.wi - Vec3::new(-wo.x, -wo.y, wo.z)).length() < 1e-6);
    assert_eq!(c.eval(wo, s.wi), Vec3::ZERO);
    assert_eq!(c.pdf(wo, s.wi), 0.0);
    for (_, b) in all_bsdfs() {
        assert!(!b.is_delta());
    }
}

#[test]
fn one_sided_bsdfs_are_black_from_below() {
    let mut all = all_bsdfs();
    all.push(("conductor".into(), conductor()));
    let up = dir(0.5, 0.3);
    let down = Vec3::new(up.x, up.y, -up.z);
    let other_up = dir(0.8, 2.0);
    let other_down = Vec3::new(other_up.x, other_up.y, -other_up.z);
    for (name, b) in all {
        for (wo, wi) in [(down, other_up), (up, other_down), (down, other_down)] {
            assert_eq!(b.eval(wo, wi), Vec3::ZERO, "{name}");
            assert_eq!(b.pdf(wo, wi), 0.0, "{name}");
        }
        assert!(b.sample(down, 0.5, Vec2::new(0.3, 0.6)).is_none(), "{name}");
        // A horizon wo is excluded too.
        assert!(
            b.sample(Vec3::X, 0.5, Vec2::new(0.3, 0.6)).is_none(),
            "{name}"
        );
    }
}

#[test]
fn two_sided_mirrors_the_lower_hemisphere() {
    let mut all = all_bsdfs();
    all.push(("conductor".into(), conductor()));
    let mut rng = Pcg32::new(5, 5);
    for (name, one) in all {
        let two = Bsdf {
            two_sided: true,
            ..one
        };
        for _ in 0..200 {
            let wo = uniform_hemisphere(&mut rng);
            let wi = uniform_hemisphere(&mut rng);
            let flip = |v: Vec3| Vec3::new(v.x, v.y, -v.z);
            // Front side unchanged.
            assert_eq!(two.eval(wo, wi), one.eval(wo, wi), "{name}");
            // Back side = front side mirrored.
            assert_eq!(two.eval(flip(wo), flip(wi)), one.eval(wo, wi), "{name}");
            assert_eq!(two.pdf(flip(wo), flip(wi)), one.pdf(wo, wi), "{name}");
            // Still no transmission.
            assert_eq!(two.eval(flip(wo), wi), Vec3::ZERO, "{name}");
            assert_eq!(two.pdf(flip(wo), wi), 0.0, "{name}");
            let u = Vec2::new(rng.next_f32(), rng.next_f32());
            let l = rng.next_f32();
            match (two.sample(flip(wo), l, u), one.sample(wo, l, u)) {
                (Some(a), Some(b)) => {
                    assert_eq!(a.wi, flip(b.wi), "{name}");
                    assert_eq!(
                        (a.weight, a.pdf, a.delta),
                        (b.weight, b.pdf, b.delta),
                        "{name}"
                    );
                }
                (None, None) => {}
                (a, b) => panic!("{name}: two-sided {a:?} vs one-sided {b:?}"),
            }
        }
    }
}

#[test]
fn no_nan_at_grazing_angles_and_extreme_roughness() {
    let mut bsdfs = vec![("conductor".to_owned(), conductor())];
    for alpha in [1e-4f32, 1e-3, 1.0] {
        bsdfs.extend(glossy_bsdfs(alpha));
    }
    bsdfs.push((
        "diffuse".into(),
        Bsdf::new(BsdfKind::Diffuse {
            reflectance: Vec3::ONE,
        }),
    ));
    let grazing = [
        Vec3::new(1.0, 0.0, 1e-7).normalize(),
        Vec3::new(0.6, 0.8, 1e-7).normalize(),
        Vec3::new(1.0, 0.0, 1e-3).normalize(),
        Vec3::Z,
    ];
    let mut rng = Pcg32::new(6, 6);
    for (name, b) in &bsdfs {
        for &wo in &grazing {
            for &wi in &grazing {
                for wi in [wi, Vec3::new(-wi.x, -wi.y, wi.z)] {
                    let f = b.eval(wo, wi);
                    let p = b.pdf(wo, wi);
                    assert!(
                        f.is_finite() && f.min_element() >= 0.0,
                        "{name} eval({wo}, {wi}) = {f}"
                    );
                    assert!(p.is_finite() && p >= 0.0, "{name} pdf({wo}, {wi}) = {p}");
                }
            }
            for _ in 0..2000 {
                let u = Vec2::new(rng.next_f32(), rng.next_f32());
                if let Some(s) = b.sample(wo, rng.next_f32(), u) {
                    assert!(
                        s.weight.is_finite() && s.weight.min_element() >= 0.0,
                        "{name} wo={wo}: {s:?}"
                    );
                    assert!(
                        s.pdf.is_finite() && s.pdf > 0.0 && s.wi.is_finite(),
                        "{name} wo={wo}: {s:?}"
                    );
                    assert!((s.wi.length() - 1.0).abs() < 1e-3, "{name} wo={wo}: {s:?}");
                }
            }
            // Edge samples of the unit square.
            for u in [
                Vec2::ZERO,
                Vec2::new(0.0, 0.999_999_9),
                Vec2::new(0.999_999_9, 0.0),
                Vec2::splat(0.999_999_9),
            ] {
                if let Some(s) = b
                    .sample(wo, 0.0, u)
                    .into_iter()
                    .chain(b.sample(wo, 0.999_999_9, u))
                    .next()
                {
                    assert!(
                        s.weight.is_finite() && s.pdf.is_finite(),
                        "{name} wo={wo} u={u}: {s:?}"
                    );
                }
            }
        }
    }
}

#[test]
fn albedo_aov_reports_the_surface_colour() {
    let rho = Vec3::new(0.1, 0.2, 0.3);
    assert_eq!(
        Bsdf::new(BsdfKind::Diffuse { reflectance: rho }).albedo(),
        rho
    );
    assert_eq!(rough_plastic(Ggx, 0.2, rho, false).albedo(), rho);
    assert_eq!(conductor().albedo(), Vec3::ONE);
}

#[test]
fn material_table_maps_scene_materials() {
    use scene::{Color, Material, RgbImage, Texture, TextureFilter, TextureWrap};
    let textures = vec![
        Texture::Checkerboard {
            color0: Vec3::ONE,
            color1: Vec3::ZERO,
            uv_transform: Affine2::IDENTITY,
        },
        Texture::Bitmap {
            image: RgbImage {
                width: 1,
                height: 1,
                data: vec![Vec3::new(0.2, 0.4, 0.6)],
            },
            filter: TextureFilter::Nearest,
            wrap: TextureWrap::Repeat,
            uv_transform: Affine2::IDENTITY,
        },
    ];
    let materials = vec![
        Material::Diffuse {
            reflectance: Color::Texture(0),
        },
        Material::TwoSided(Box::new(Material::RoughPlastic {
            distribution: Ggx,
            alpha: 0.1,
            eta: 1.5,
            diffuse_reflectance: Color::Texture(1),
            specular_reflectance: Color::Rgb(Vec3::ONE),
            nonlinear: false,
        })),
        Material::Conductor {
            eta: Vec3::ONE,
            k: Vec3::ONE,
            specular_reflectance: Color::Rgb(Vec3::splat(0.5)),
        },
        Material::RoughConductor {
            distribution: Beckmann,
            alpha: 0.3,
            eta: Vec3::ONE,
            k: Vec3::ONE,
            specular_reflectance: Color::Rgb(Vec3::ONE),
        },
    ];
    let table = MaterialTable::new(&materials, &textures);
    assert_eq!(table.len(), 4);
    let d0 = table.bsdf(0, Vec2::new(0.25, 0.25));
    let d1 = table.bsdf(0, Vec2::new(0.75, 0.25));
    assert_eq!(
        d0.kind,
        BsdfKind::Diffuse {
            reflectance: Vec3::ONE
        }
    );
    assert_eq!(
        d1.kind,
        BsdfKind::Diffuse {
            reflectance: Vec3::ZERO
        }
    );
    assert!(!d0.two_sided);
    let p = table.bsdf(1, Vec2::ZERO);
    assert!(p.two_sided);
    match p.kind {
        BsdfKind::RoughPlastic {
            params,
            diffuse_reflectance,
            ..
        } => {
            assert_eq!(diffuse_reflectance, Vec3::new(0.2, 0.4, 0.6));
            // w = s_mean / (d_mean + s_mean), d_mean = texture mean 0.4.
            assert!((params.specular_sampling_weight - 1.0 / 1.4).abs() < 1e-6);
        }
        other => panic!("expected rough plastic, got {other:?}"),
    }
    assert!(table.bsdf(2, Vec2::ZERO).is_delta());
    assert!(matches!(
        table.bsdf(3, Vec2::ZERO).kind,
        BsdfKind::RoughConductor {
            distribution: Beckmann,
            ..
        }
    ));
}

#[test]
fn material_table_out_of_range_id_is_default_grey_not_a_panic() {
    let table = MaterialTable::new(&[], &[]);
    assert!(table.is_empty());
    assert_eq!(
        table.bsdf(3, Vec2::ZERO).kind,
        BsdfKind::Diffuse {
            reflectance: Vec3::splat(0.5)
        }
    );
}

#[test]
fn eval_pdf_agrees_with_eval_and_pdf() {
    let mut rng = Pcg32::new(10, 10);
    let mut all = all_bsdfs();
    all.push(("conductor".into(), conductor()));
    for (name, b) in all {
        for two_sided in [false, true] {
            let b = Bsdf { two_sided, ..b };
            for _ in 0..500 {
                let mut wo = uniform_hemisphere(&mut rng);
                let mut wi = uniform_hemisphere(&mut rng);
                if rng.next_f32() < 0.3 {
                    wo.z = -wo.z;
                }
                if rng.next_f32() < 0.3 {
                    wi.z = -wi.z;
                }
                let (f, p) = b.eval_pdf(wo, wi);
                assert!(
                    rel_close(f, b.eval(wo, wi), 1e-4),
                    "{name}: {f} vs {}",
                    b.eval(wo, wi)
                );
                assert!(
                    (p - b.pdf(wo, wi)).abs() <= 1e-4 * p.max(1e-6),
                    "{name}: {p} vs {}",
                    b.pdf(wo, wi)
                );
            }
        }
    }
}
