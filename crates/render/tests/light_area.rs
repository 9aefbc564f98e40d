//! Area lights (meshes, spheres) and light selection: χ² goodness-of-fit of every sampling
//! routine against the pdf the light reports (`pdf_area` reached by ray casting the light from
//! the shading point), pdf consistency of individual samples, one-sidedness, selection pmfs,
//! and the degenerate cases (tiny, zero-radiance, zero-area lights, no lights).

mod light_support;

use glam::{Vec2, Vec3};
use light_support::{Zoom, mesh, mesh_direction_pdf, scene, sphere, sphere_direction_pdf};
use render::chi2::{Chi2Config, Pcg32, test_directions};
use render::light::{LightKind, LightSelection, Lights};
use scene::Environment;

/// χ² tests in this file (Šidák correction of the family-wise level).
const CHI2_TESTS: usize = 7;

fn cfg() -> Chi2Config {
    Chi2Config {
        samples: 200_000,
        theta_bins: 32,
        phi_bins: 64,
        test_count: CHI2_TESTS,
        ..Chi2Config::default()
    }
}

const WHITE: Vec3 = Vec3::splat(1.0);

/// A unit square in the plane z = `z`, facing −z (towards the origin when z > 0).
fn quad_facing_down(z: f32, half: f32) -> scene::Mesh {
    mesh(
        vec![
            Vec3::new(-half, -half, z),
            Vec3::new(half, -half, z),
            Vec3::new(half, half, z),
            Vec3::new(-half, half, z),
        ],
        // (p1 − p0) × (p2 − p0) = +x × +y = +z: wind the other way for −z.
        vec![[0, 2, 1], [0, 3, 2]],
        Some(WHITE),
    )
}

#[test]
fn mesh_single_triangle_chi2() {
    let tri = mesh(
        vec![
            Vec3::new(-1.0, -0.5, 0.6),
            Vec3::new(0.8, -0.7, 0.9),
            Vec3::new(0.1, 1.2, 0.5),
        ],
        vec![[0, 2, 1]],
        Some(Vec3::new(2.0, 1.0, 0.5)),
    );
    let sc = scene(vec![tri.clone()], vec![], None);
    let lights = Lights::new(&sc, LightSelection::Uniform);
    let light = lights.mesh_light(0).unwrap();
    let p = Vec3::new(0.1, 0.0, 0.0);
    let r = test_directions(
        |u, _| lights.sample_light(light, p, u).map(|s| (s.wi, s.pdf)),
        |w| mesh_direction_pdf(&lights, light, &tri, p, w),
        &cfg(),
    );
    assert!(r.passed, "{}", r.report());
    assert!(
        r.valid_fraction > 0.99,
        "front-facing triangle: every sample succeeds ({})",
        r.report()
    );
}

#[test]
fn mesh_triangles_of_very_different_areas_chi2() {
    // A big quad overhead (area 4), a tiny triangle to the side (area 1e-3, facing p) and a
    // medium triangle facing away from p (its samples fail: one-sided emission).
    let positions = vec![
        Vec3::new(-1.0, -1.0, 1.0),
        Vec3::new(1.0, -1.0, 1.0),
        Vec3::new(1.0, 1.0, 1.0),
        Vec3::new(-1.0, 1.0, 1.0),
        // tiny, in the plane x = 0.8, facing −x
        Vec3::new(0.8, 0.0, -0.02),
        Vec3::new(0.8, 0.05, -0.02),
        Vec3::new(0.8, 0.0, 0.02),
        // medium, in the plane y = −0.7, facing −y: away from p, which sits at y = 0
        Vec3::new(-0.3, -0.7, -0.3),
        Vec3::new(0.3, -0.7, -0.3),
        Vec3::new(0.0, -0.7, 0.3),
    ];
    let m = mesh(
        positions,
        vec![[0, 2, 1], [0, 3, 2], [4, 6, 5], [7, 8, 9]],
        Some(WHITE),
    );
    // Check the windings the comments claim.
    let n = |t: [u32; 3]| {
        let [a, b, c] = t.map(|i| m.positions[i as usize]);
        (b - a).cross(c - a).normalize()
    };
    assert!(n([0, 2, 1]).z < 0.0 && n([4, 6, 5]).x < 0.0 && n([7, 8, 9]).y < 0.0);
    let sc = scene(vec![m.clone()], vec![], None);
    let lights = Lights::new(&sc, LightSelection::Uniform);
    let light = lights.mesh_light(0).unwrap();
    let p = Vec3::ZERO;
    let r = test_directions(
        |u, _| lights.sample_light(light, p, u).map(|s| (s.wi, s.pdf)),
        |w| mesh_direction_pdf(&lights, light, &m, p, w),
        &cfg(),
    );
    assert!(r.passed, "{}", r.report());
    // The back-facing triangle (area 0.18 of 4.181) makes that fraction of samples fail.
    let area_back = 0.5 * 0.6 * 0.6;
    let expect_valid = 1.0 - area_back / (4.0 + 0.5 * 0.05 * 0.04 + area_back);
    assert!(
        (r.valid_fraction - expect_valid).abs()
            < 5.0 * (expect_valid * (1.0 - expect_valid) / 2e5f64).sqrt()
    );
}

#[test]
fn sphere_outside_near_chi2() {
    let s = sphere(Vec3::new(0.3, 0.2, 1.0), 0.8, false, Some(WHITE));
    let sc = scene(vec![], vec![s], None);
    let lights = Lights::new(&sc, LightSelection::Uniform);
    let light = lights.sphere_light(0).unwrap();
    let p = Vec3::ZERO; // distance 1.063: sin θ_max = 0.75
    let r = test_directions(
        |u, _| lights.sample_light(light, p, u).map(|s| (s.wi, s.pdf)),
        |w| sphere_direction_pdf(&lights, light, &s, p, w),
        &cfg(),
    );
    assert!(r.passed, "{}", r.report());
    assert!(r.valid_fraction > 0.999);
}

#[test]
fn sphere_outside_far_chi2() {
    // θ_max ≈ 2.9°: magnify the cone onto a hemisphere so the histogram resolves it.
    let center = Vec3::new(-4.0, 12.0, 3.0);
    let radius = center.length() / 20.0;
    let s = sphere(center, radius, false, Some(WHITE));
    let sc = scene(vec![], vec![s], None);
    let lights = Lights::new(&sc, LightSelection::Uniform);
    let light = lights.sphere_light(0).unwrap();
    let p = Vec3::ZERO;
    let sin2 = (radius / center.length()).powi(2);
    let zoom = Zoom::new(center, sin2 / (1.0 + (1.0 - sin2).sqrt()));
    let r = test_directions(
        |u, _| {
            lights
                .sample_light(light, p, u)
                .map(|s| (zoom.forward(s.wi), s.pdf / zoom.s))
        },
        |w| sphere_direction_pdf(&lights, light, &s, p, zoom.inverse(w)) / zoom.s,
        &cfg(),
    );
    assert!(r.passed, "{}", r.report());
}

#[test]
fn sphere_inside_flipped_chi2() {
    // An emitting dome seen from inside, off-centre: area sampling, pdf = d² / (cos · 4πr²).
    let s = sphere(Vec3::new(0.2, -0.1, 0.3), 1.5, true, Some(WHITE));
    let sc = scene(vec![], vec![s], None);
    let lights = Lights::new(&sc, LightSelection::Uniform);
    let light = lights.sphere_light(0).unwrap();
    let p = Vec3::new(0.6, 0.3, -0.4);
    let r = test_directions(
        |u, _| lights.sample_light(light, p, u).map(|s| (s.wi, s.pdf)),
        |w| sphere_direction_pdf(&lights, light, &s, p, w),
        &cfg(),
    );
    assert!(r.passed, "{}", r.report());
    assert!((r.pdf_integral - 1.0).abs() < 1e-3, "{}", r.report());
}

#[test]
fn sphere_seen_from_its_back_side_emits_nothing() {
    // Outside a flipped sphere and inside a normal one, the visible surface is the back side.
    for (flip, p) in [
        (true, Vec3::new(0.0, 0.0, -3.0)),
        (false, Vec3::new(0.1, 0.2, 0.0)),
    ] {
        let s = sphere(Vec3::ZERO, 1.0, flip, Some(WHITE));
        let lights = Lights::new(&scene(vec![], vec![s], None), LightSelection::Uniform);
        let mut rng = Pcg32::new(3, 0);
        for _ in 0..1000 {
            let u = Vec2::new(rng.next_f32(), rng.next_f32());
            assert!(lights.sample_light(0, p, u).is_none(), "flip = {flip}");
        }
        for w in [Vec3::Z, Vec3::X, Vec3::new(0.3, 0.2, 0.9).normalize()] {
            assert_eq!(
                sphere_direction_pdf(&lights, 0, &s, p, w),
                0.0,
                "flip = {flip}"
            );
        }
    }
}

#[test]
fn point_on_a_sphere_light_does_not_light_itself() {
    // A shading point on the emitter's own surface is "outside" (Mitsuba's shrunk radius):
    // the cone is a hemisphere whose samples degenerate to the point itself or fail.
    let s = sphere(Vec3::ZERO, 1.0, false, Some(WHITE));
    let lights = Lights::new(&scene(vec![], vec![s], None), LightSelection::Uniform);
    let p = Vec3::new(0.0, 0.0, 1.0);
    let mut rng = Pcg32::new(5, 0);
    for _ in 0..1000 {
        let u = Vec2::new(rng.next_f32(), rng.next_f32());
        if let Some(ls) = lights.sample_light(0, p, u) {
            assert!(ls.pdf.is_finite() && ls.dist.is_finite() && ls.wi.is_finite());
        }
    }
}

#[test]
fn sample_pdf_equals_pdf_area_at_the_sampled_point() {
    let quad = quad_facing_down(2.0, 0.5);
    let s_out = sphere(Vec3::new(3.0, 0.0, 1.0), 0.5, false, Some(WHITE));
    let s_in = sphere(Vec3::new(0.0, 0.0, 0.0), 10.0, true, Some(WHITE));
    let sc = scene(vec![quad], vec![s_out, s_in], None);
    let lights = Lights::new(&sc, LightSelection::Uniform);
    let p = Vec3::new(0.1, -0.2, 0.3);
    let mut rng = Pcg32::new(11, 0);
    for light in 0..3u32 {
        let mut valid = 0;
        for _ in 0..2000 {
            let u = Vec2::new(rng.next_f32(), rng.next_f32());
            let Some(ls) = lights.sample_light(light, p, u) else {
                continue;
            };
            valid += 1;
            let y = p + ls.wi * ls.dist;
            let q = lights.pdf_area(light, p, y, ls.n);
            assert!(
                (q - ls.pdf).abs() <= 1e-3 * ls.pdf,
                "light {light}: sample pdf {} vs pdf_area {q}",
                ls.pdf
            );
            assert!(ls.n.dot(ls.wi) < 0.0, "the sampled point faces p");
            assert_eq!(lights.area_radiance(light, ls.n, -ls.wi), ls.radiance);
            assert!(!ls.delta && ls.light == light);
        }
        assert!(valid > 1900, "light {light}: only {valid} valid samples");
    }
}

#[test]
fn area_radiance_is_one_sided() {
    let sc = scene(vec![quad_facing_down(1.0, 1.0)], vec![], None);
    let lights = Lights::new(&sc, LightSelection::Uniform);
    let n = -Vec3::Z;
    assert_eq!(
        lights.area_radiance(0, n, Vec3::new(0.1, 0.0, -1.0).normalize()),
        WHITE
    );
    assert_eq!(
        lights.area_radiance(0, n, Vec3::new(0.1, 0.0, 1.0).normalize()),
        Vec3::ZERO
    );
    // From above the quad (its back side) nothing is sampled and the pdf is 0.
    let p = Vec3::new(0.0, 0.0, 2.0);
    assert!(lights.sample_light(0, p, Vec2::new(0.3, 0.6)).is_none());
    assert_eq!(lights.pdf_area(0, p, Vec3::new(0.0, 0.0, 1.0), n), 0.0);
    assert!(lights.pdf_area(0, Vec3::ZERO, Vec3::new(0.0, 0.0, 1.0), n) > 0.0);
}

#[test]
fn tiny_and_zero_radiance_lights_stay_finite() {
    let tiny_sphere = sphere(
        Vec3::new(0.0, 0.0, 10.0),
        1e-5,
        false,
        Some(Vec3::splat(1e30)),
    );
    let dark_sphere = sphere(Vec3::new(0.0, 2.0, 0.0), 0.5, false, Some(Vec3::ZERO));
    let tiny_tri = mesh(
        vec![
            Vec3::new(0.0, 0.0, 1.0),
            Vec3::new(0.0, 1e-4, 1.0),
            Vec3::new(1e-4, 0.0, 1.0),
        ],
        vec![[0, 1, 2]],
        Some(WHITE),
    );
    let sc = scene(vec![tiny_tri], vec![tiny_sphere, dark_sphere], None);
    for selection in [LightSelection::Uniform, LightSelection::Power] {
        let lights = Lights::new(&sc, selection);
        let p = Vec3::ZERO;
        let mut rng = Pcg32::new(13, 0);
        for light in 0..3u32 {
            let mut valid = 0;
            for _ in 0..500 {
                let u = Vec2::new(rng.next_f32(), rng.next_f32());
                let Some(ls) = lights.sample_light(light, p, u) else {
                    continue;
                };
                valid += 1;
                assert!(
                    ls.pdf.is_finite() && ls.pdf > 0.0,
                    "light {light}: pdf {}",
                    ls.pdf
                );
                assert!(ls.radiance.is_finite() && ls.wi.is_finite() && ls.dist.is_finite());
                let q = lights.pdf_area(light, p, p + ls.wi * ls.dist, ls.n);
                assert!(q.is_finite() && q > 0.0, "light {light}: pdf_area {q}");
            }
            assert!(valid > 0, "light {light} never sampled");
        }
        // The zero-radiance sphere still samples (zero contribution, valid pdf) under Uniform
        // and has selection probability 0 under Power.
        let pmf = lights.selection_pmf(2);
        match selection {
            LightSelection::Uniform => assert!((pmf - 1.0 / 3.0).abs() < 1e-6),
            LightSelection::Power => assert_eq!(pmf, 0.0),
        }
    }
    // The tiny sphere's cone pdf: 1 / (2π (1 − cos θmax)) with sin θmax = 1e-6.
    let lights = Lights::new(&sc, LightSelection::Uniform);
    let ls = lights
        .sample_light(1, Vec3::ZERO, Vec2::new(0.5, 0.5))
        .unwrap();
    let expected = 1.0 / (2.0 * std::f64::consts::PI * 0.5e-12);
    assert!(
        ((ls.pdf as f64) - expected).abs() < 1e-3 * expected,
        "{} vs {expected}",
        ls.pdf
    );
}

#[test]
fn zero_area_mesh_light_is_never_sampled() {
    let flat = mesh(
        vec![Vec3::ZERO, Vec3::X, Vec3::X * 2.0],
        vec![[0, 1, 2]],
        Some(WHITE),
    );
    let sc = scene(vec![flat], vec![], None);
    for selection in [LightSelection::Uniform, LightSelection::Power] {
        let lights = Lights::new(&sc, selection);
        assert_eq!(lights.len(), 1);
        let p = Vec3::new(0.0, 1.0, 0.0);
        assert!(lights.sample_light(0, p, Vec2::new(0.5, 0.5)).is_none());
        assert!(lights.sample(p, 0.5, Vec2::new(0.5, 0.5)).is_none());
        assert_eq!(lights.pdf_area(0, p, Vec3::X, Vec3::Y), 0.0);
        assert!(
            (lights.selection_pmf(0) - 1.0).abs() < 1e-6,
            "all-zero power falls back to uniform"
        );
    }
}

#[test]
fn no_lights() {
    let sc = scene(
        vec![mesh(
            vec![Vec3::ZERO, Vec3::X, Vec3::Y],
            vec![[0, 1, 2]],
            None,
        )],
        vec![],
        None,
    );
    let lights = Lights::new(&sc, LightSelection::Power);
    assert!(lights.is_empty());
    assert_eq!(lights.len(), 0);
    assert_eq!(lights.mesh_light(0), None);
    assert_eq!(lights.env_light(), None);
    assert!(lights.select(0.3).is_none());
    assert!(
        lights
            .sample(Vec3::ZERO, 0.3, Vec2::new(0.2, 0.2))
            .is_none()
    );
    assert!(
        lights
            .sample_light(0, Vec3::ZERO, Vec2::new(0.2, 0.2))
            .is_none()
    );
    assert_eq!(lights.selection_pmf(0), 0.0);
    assert_eq!(lights.env_radiance(Vec3::Z), Vec3::ZERO);
    assert_eq!(lights.pdf_env(Vec3::Z), 0.0);
    assert_eq!(lights.pdf_area(0, Vec3::ZERO, Vec3::X, Vec3::Y), 0.0);
}

/// Mesh 0 (no emitter), mesh 1 (emitter), sphere 0 (emitter), sphere 1 (no), constant env.
fn mixed_scene() -> scene::Scene {
    scene(
        vec![
            mesh(
                vec![
                    Vec3::new(5.0, 0.0, 0.0),
                    Vec3::new(5.0, 1.0, 0.0),
                    Vec3::new(5.0, 0.0, 1.0),
                ],
                vec![[0, 1, 2]],
                None,
            ),
            quad_facing_down(1.5, 0.75),
        ],
        vec![
            sphere(
                Vec3::new(1.5, 0.0, 0.5),
                0.4,
                false,
                Some(Vec3::new(8.0, 4.0, 2.0)),
            ),
            sphere(Vec3::new(-3.0, 0.0, 0.0), 1.0, false, None),
        ],
        Some(Environment::Constant {
            radiance: Vec3::new(0.2, 0.3, 0.4),
        }),
    )
}

#[test]
fn light_indices_and_selection_pmfs() {
    let sc = mixed_scene();
    for selection in [LightSelection::Uniform, LightSelection::Power] {
        let lights = Lights::new(&sc, selection);
        assert_eq!(lights.len(), 3);
        assert_eq!(
            (
                lights.mesh_light(0),
                lights.mesh_light(1),
                lights.mesh_light(2)
            ),
            (None, Some(0), None)
        );
        assert_eq!(
            (lights.sphere_light(0), lights.sphere_light(1)),
            (Some(1), None)
        );
        assert_eq!(lights.env_light(), Some(2));
        assert_eq!(lights.kind(0), Some(LightKind::Mesh { mesh: 1 }));
        assert_eq!(lights.kind(1), Some(LightKind::Sphere { sphere: 0 }));
        assert_eq!(lights.kind(2), Some(LightKind::Environment));
        assert_eq!(lights.kind(3), None);
        let sum: f32 = (0..3).map(|l| lights.selection_pmf(l)).sum();
        assert!((sum - 1.0).abs() < 1e-6, "{selection:?}: pmfs sum to {sum}");
        assert_eq!(lights.selection_pmf(3), 0.0);
        // select() frequencies match the pmfs (5 s.e.) and it reports the same pmf.
        let n = 100_000;
        let mut counts = [0usize; 3];
        let mut rng = Pcg32::new(17, 0);
        for _ in 0..n {
            let (l, pmf) = lights.select(rng.next_f32()).unwrap();
            assert_eq!(pmf, lights.selection_pmf(l));
            counts[l as usize] += 1;
        }
        for (l, &count) in counts.iter().enumerate() {
            let p = lights.selection_pmf(l as u32) as f64;
            let se = (p * (1.0 - p) / n as f64).sqrt();
            let f = count as f64 / n as f64;
            assert!(
                (f - p).abs() <= 5.0 * se + 1e-12,
                "{selection:?}: light {l} freq {f} vs pmf {p}"
            );
        }
    }
    // Power: Φ = π A lum(L) for the area lights; the quad has A = 2.25, lum(1) = 1.
    let lights = Lights::new(&sc, LightSelection::Power);
    let lum = |c: Vec3| render::light::luminance(c) as f64;
    let phi_quad = std::f64::consts::PI * 2.25;
    let phi_sphere =
        std::f64::consts::PI * 4.0 * std::f64::consts::PI * 0.16 * lum(Vec3::new(8.0, 4.0, 2.0));
    let ratio = lights.selection_pmf(1) as f64 / lights.selection_pmf(0) as f64;
    assert!((ratio - phi_sphere / phi_quad).abs() < 1e-4 * ratio);
}

#[test]
fn combined_sample_with_power_selection_chi2() {
    // The full `sample` (selection + light): its direction density is the pmf-weighted sum.
    let sc = mixed_scene();
    let lights = Lights::new(&sc, LightSelection::Power);
    let p = Vec3::new(0.2, 0.1, 0.0);
    let quad = &sc.meshes[1];
    let sph = &sc.spheres[0];
    let pdf = |w: Vec3| {
        lights.selection_pmf(0) * mesh_direction_pdf(&lights, 0, quad, p, w)
            + lights.selection_pmf(1) * sphere_direction_pdf(&lights, 1, sph, p, w)
            + lights.selection_pmf(2) * lights.pdf_env(w)
    };
    let sample = |u: Vec2, u_sel: f32| {
        let s = lights.sample(p, u_sel, u)?;
        // The reported pdf is the picked light's pdf times its selection pmf.
        let y = p + s.wi * s.dist;
        let own = match s.light {
            2 => lights.pdf_env(s.wi),
            l => lights.pdf_area(l, p, y, s.n),
        };
        let expect = lights.selection_pmf(s.light) * own;
        assert!(
            (s.pdf - expect).abs() <= 1e-3 * expect,
            "light {}: {} vs {expect}",
            s.light,
            s.pdf
        );
        Some((s.wi, pdf(s.wi)))
    };
    let r = test_directions(sample, pdf, &cfg());
    assert!(r.passed, "{}", r.report());
    assert!((r.pdf_integral - 1.0).abs() < 2e-3, "{}", r.report());
}

#[test]
fn non_finite_inputs_give_none_or_zero() {
    let sc = mixed_scene();
    let lights = Lights::new(&sc, LightSelection::Power);
    let bad = [f32::NAN, f32::INFINITY, f32::NEG_INFINITY];
    for &x in &bad {
        let p = Vec3::new(x, 0.0, 0.0);
        let u = Vec2::new(x, 0.5);
        for light in 0..lights.len() as u32 {
            for (p, u) in [(p, Vec2::new(0.3, 0.4)), (Vec3::ZERO, u)] {
                if let Some(s) = lights.sample_light(light, p, u) {
                    assert!(
                        s.wi.is_finite()
                            && s.pdf.is_finite()
                            && s.pdf > 0.0
                            && s.radiance.is_finite(),
                        "light {light}, p = {p}, u = {u}: {s:?}"
                    );
                }
            }
            let q = lights.pdf_area(light, p, Vec3::new(0.0, 0.0, 1.5), -Vec3::Z);
            assert!(q.is_finite(), "light {light}: pdf_area {q}");
        }
        let d = Vec3::new(x, 1.0, 0.0);
        assert!(lights.pdf_env(d).is_finite() && lights.env_radiance(d).is_finite());
        if let Some((l, pmf)) = lights.select(x) {
            assert!((l as usize) < lights.len() && pmf > 0.0);
        }
    }
}

#[test]
fn ten_thousand_lights_with_extreme_magnitudes() {
    // 10 000 small quads with radiance from 1e-30 to 1e30 (and a few black ones).
    let meshes: Vec<scene::Mesh> = (0..10_000)
        .map(|k| {
            let mut m = quad_facing_down(1.0 + k as f32 * 1e-3, 0.01);
            let e = if k % 1000 == 0 {
                0.0
            } else {
                10f32.powf(-30.0 + 60.0 * (k as f32 / 9_999.0))
            };
            m.emitter = Some(Vec3::splat(e));
            m
        })
        .collect();
    let sc = scene(meshes, vec![], None);
    for selection in [LightSelection::Uniform, LightSelection::Power] {
        let lights = Lights::new(&sc, selection);
        assert_eq!(lights.len(), 10_000);
        let sum: f64 = (0..10_000).map(|l| lights.selection_pmf(l) as f64).sum();
        assert!((sum - 1.0).abs() < 1e-4, "{selection:?}: Σ pmf = {sum}");
        let mut rng = Pcg32::new(31, 0);
        for _ in 0..10_000 {
            let (l, pmf) = lights.select(rng.next_f32()).unwrap();
            assert!(
                pmf > 0.0 && pmf == lights.selection_pmf(l),
                "{selection:?}: light {l} pmf {pmf}"
            );
            let u = Vec2::new(rng.next_f32(), rng.next_f32());
            let s = lights.sample(Vec3::ZERO, rng.next_f32(), u).unwrap();
            assert!(s.pdf.is_finite() && s.pdf > 0.0 && s.radiance.is_finite());
        }
        if selection == LightSelection::Power {
            // The brightest lights dominate; black lights are never picked.
            assert!(lights.selection_pmf(9_999) > 1e-3);
            assert_eq!(lights.selection_pmf(1_000), 0.0, "black light");
        }
    }
}

#[test]
fn grazing_shading_points_stay_finite() {
    // Shading points in (and just above) the plane of a quad light: samples are either
    // None or have a finite pdf, and pdf_area agrees with the sample.
    let sc = scene(vec![quad_facing_down(1.0, 0.5)], vec![], None);
    let lights = Lights::new(&sc, LightSelection::Uniform);
    let mut rng = Pcg32::new(37, 0);
    for p in [
        Vec3::new(2.0, 0.0, 1.0),
        Vec3::new(2.0, 0.0, 1.0 - 1e-6),
        Vec3::new(0.5, 0.5, 1.0 - 1e-7),
    ] {
        for _ in 0..1000 {
            let u = Vec2::new(rng.next_f32(), rng.next_f32());
            if let Some(s) = lights.sample_light(0, p, u) {
                assert!(s.pdf.is_finite() && s.pdf > 0.0, "p = {p}: pdf {}", s.pdf);
                let q = lights.pdf_area(0, p, p + s.wi * s.dist, s.n);
                assert!(q.is_finite(), "p = {p}: pdf_area {q}");
            }
        }
    }
}
