//! Environment lights: the lat-long lookup against hand-computed values and against Mitsuba
//! 3.9.1 itself, χ² of the importance sampling (peaked map, rotated frame, black regions),
//! normalisation of the pdf, unbiasedness of `radiance / pdf`, the constant environment, and
//! degenerate maps.

mod light_support;

use std::f32::consts::PI;

use glam::{Mat3, Vec2, Vec3};
use light_support::{mesh, scene};
use render::chi2::{Chi2Config, Pcg32, test_directions};
use render::light::{LightSelection, Lights};
use scene::{Environment, RgbImage};

/// χ² tests in this file.
const CHI2_TESTS: usize = 4;

fn cfg() -> Chi2Config {
    Chi2Config {
        samples: 1_000_000,
        test_count: CHI2_TESTS,
        ..Chi2Config::default()
    }
}

fn image(width: u32, height: u32, f: impl Fn(u32, u32) -> Vec3) -> RgbImage {
    let data = (0..height)
        .flat_map(|y| (0..width).map(move |x| (x, y)))
        .map(|(x, y)| f(x, y))
        .collect();
    RgbImage {
        width,
        height,
        data,
    }
}

fn env_lights(image: RgbImage, to_world: Mat3) -> Lights {
    Lights::new(
        &scene(
            vec![],
            vec![],
            Some(Environment::Envmap { image, to_world }),
        ),
        LightSelection::Uniform,
    )
}

/// Map-frame direction of lat-long coordinates (u, θ): Mitsuba's `uv_to_direction`.
fn dir(u: f32, theta: f32) -> Vec3 {
    let phi = 2.0 * PI * u;
    Vec3::new(
        phi.sin() * theta.sin(),
        theta.cos(),
        -phi.cos() * theta.sin(),
    )
}

fn close(a: Vec3, b: Vec3, rel: f32) -> bool {
    (a - b).abs().max_element() <= rel * b.abs().max_element().max(1e-6)
}

/// A 4×3 map with distinct texels: texel (x, y) = (x + 1, 10 (y + 1), x + 4y).
fn tiny_map() -> RgbImage {
    image(4, 3, |x, y| {
        Vec3::new((x + 1) as f32, (10 * (y + 1)) as f32, (x + 4 * y) as f32)
    })
}

fn texel(x: u32, y: u32) -> Vec3 {
    Vec3::new((x + 1) as f32, (10 * (y + 1)) as f32, (x + 4 * y) as f32)
}

#[test]
fn envmap_lookup_by_hand() {
    // W = 4, H = 3: texel (x, y) sits at u = (x + ½)/4, θ = y·π/2; bilinear in between.
    let lights = env_lights(tiny_map(), Mat3::IDENTITY);
    let cases = [
        // texel centre (1, 1)
        (dir(0.375, PI / 2.0), texel(1, 1)),
        // column 3 near the south pole: θ = 0.99π → y = 1.98 (rows 1, 2, fy = 0.98)
        (
            dir(0.875, PI * 0.99),
            texel(3, 1) * 0.02 + texel(3, 2) * 0.98,
        ),
        // u = 1 ≡ 0 sits halfway between column 3 and column 0 (periodic wrap)
        (dir(0.0, PI / 2.0), (texel(3, 1) + texel(0, 1)) * 0.5),
        // θ = π/4: halfway between rows 0 and 1
        (dir(0.375, PI / 4.0), (texel(1, 0) + texel(1, 1)) * 0.5),
        // general point: u = 0.3 → x = 1.2 − 0.5 = 0.7 (columns 0, 1, fx = 0.7);
        // θ = 0.8π → y = 1.6 (rows 1, 2, fy = 0.6)
        (
            dir(0.3, 0.8 * PI),
            (texel(0, 1) * 0.3 + texel(1, 1) * 0.7) * 0.4
                + (texel(0, 2) * 0.3 + texel(1, 2) * 0.7) * 0.6,
        ),
    ];
    for (i, (d, expected)) in cases.iter().enumerate() {
        let got = lights.env_radiance(*d);
        assert!(close(got, *expected, 2e-5), "case {i}: {got} vs {expected}");
    }
    // The same lookups through a rotated map: world direction R d reads what d read before.
    let r = Mat3::from_axis_angle(Vec3::new(1.0, 2.0, -0.5).normalize(), 1.1);
    let rotated = env_lights(tiny_map(), r);
    for (i, (d, expected)) in cases.iter().enumerate() {
        let got = rotated.env_radiance(r * *d);
        assert!(
            close(got, *expected, 1e-4),
            "rotated case {i}: {got} vs {expected}"
        );
    }
}

#[test]
#[allow(clippy::excessive_precision)] // digits as Mitsuba printed them
fn envmap_lookup_matches_mitsuba() {
    // Values from Mitsuba 3.9.1 (scalar_rgb): `envmap` with a 5×4 bitmap, texel (x, y) =
    // (1 + x + 10y, (x + 1)(y + 1)/2, x/4 except (3, 1) = 100), to_world = rotate(axis
    // normalize(0.3, 1, 0.2), 40°), evaluated with si.wi = −d (script in the commit message).
    let img = image(5, 4, |x, y| {
        let b = if (x, y) == (3, 1) {
            100.0
        } else {
            0.25 * x as f32
        };
        Vec3::new((1 + x + 10 * y) as f32, 0.5 * ((x + 1) * (y + 1)) as f32, b)
    });
    let rows = [
        [0.784_678_04, -0.058_824_643, 0.617_106_14],
        [0.183_048_83, 0.973_084_75, -0.139_997_04],
        [-0.592_261_25, 0.222_813_16, 0.774_326_03],
    ];
    let to_world = Mat3::from_cols_array_2d(&rows).transpose();
    let lights = env_lights(img, to_world);
    let cases = [
        (
            [0.303_045_76, 0.505_076_27, -0.808_122_04],
            [13.457_169, 1.443_055_2, 0.075_680_73],
        ),
        (
            [-0.952_579_34, 0.136_082_76, 0.272_165_53],
            [17.181_328, 5.180_517, 31.367_353],
        ),
        (
            [0.0, -0.913_811_55, 0.406_138_47],
            [27.427_353, 6.077_784_5, 0.648_157_9],
        ),
        (
            [0.204_926_21, 0.973_399_5, 0.102_463_1],
            [4.723_066_3, 1.242_571_8, 0.236_206_05],
        ),
        (
            [0.602_141_4, -0.200_713_8, 0.772_748_1],
            [18.576_944, 3.856_253_9, 1.274_579_8],
        ),
        (
            [-0.104_828_48, -0.314_485_45, -0.943_456_35],
            [21.492_04, 2.078_644_8, 0.095_159_05],
        ),
    ];
    for (d, expected) in cases {
        let got = lights.env_radiance(Vec3::from_array(d));
        let expected = Vec3::from_array(expected);
        assert!(
            close(got, expected, 2e-5),
            "d = {d:?}: {got} vs Mitsuba {expected}"
        );
    }
}

/// 32×16 map: a dim gradient, one texel 10⁴ times brighter, and a black band over the
/// bottom quarter (zero-probability cells).
fn peaked_map() -> RgbImage {
    image(32, 16, |x, y| {
        if y >= 12 {
            Vec3::ZERO
        } else if (x, y) == (20, 5) {
            Vec3::new(3e3, 1e3, 5e2)
        } else {
            Vec3::new(0.1 + 0.01 * x as f32, 0.2, 0.05 + 0.02 * y as f32)
        }
    })
}

fn rotation() -> Mat3 {
    Mat3::from_axis_angle(Vec3::new(0.4, -0.3, 0.8).normalize(), 2.0)
}

#[test]
fn envmap_peaked_rotated_chi2() {
    let lights = env_lights(peaked_map(), rotation());
    let env = lights.env_light().unwrap();
    let p = Vec3::new(1.0, 2.0, 3.0);
    let r = test_directions(
        |u, _| lights.sample_light(env, p, u).map(|s| (s.wi, s.pdf)),
        |w| lights.pdf_env(w),
        &cfg(),
    );
    assert!(r.passed, "{}", r.report());
    assert!(
        (r.pdf_integral - 1.0).abs() < 1e-3,
        "∫ pdf dω = {}",
        r.pdf_integral
    );
    assert!(r.valid_fraction > 0.9999, "{}", r.report());
}

#[test]
fn envmap_pdf_integrates_to_one_and_is_zero_on_black_cells() {
    // Midpoint rule on a (φ, cos θ) grid in the map frame, finer than the cells.
    let lights = env_lights(peaked_map(), Mat3::IDENTITY);
    let (nphi, nz) = (1024, 1024);
    let mut integral = 0.0f64;
    for i in 0..nz {
        let z = -1.0 + (i as f64 + 0.5) * 2.0 / nz as f64;
        let r = (1.0 - z * z).sqrt();
        for j in 0..nphi {
            let phi = (j as f64 + 0.5) * std::f64::consts::TAU / nphi as f64;
            let d = Vec3::new((r * phi.cos()) as f32, z as f32, (r * phi.sin()) as f32);
            integral += lights.pdf_env(d) as f64;
        }
    }
    integral *= 4.0 * std::f64::consts::PI / (nphi * nz) as f64;
    // The midpoint rule misplaces at most the grid cells crossing the pdf's discontinuities.
    assert!((integral - 1.0).abs() < 5e-3, "∫ pdf dω = {integral}");
    // Rows 12.. are black: θ > 12π/15 has zero radiance and zero pdf (cell rows 12–14 only
    // touch black texels); the band just above (row band 11, touching row 11) does not.
    let black = dir(0.3, 0.9 * PI);
    assert_eq!(lights.env_radiance(black), Vec3::ZERO);
    assert_eq!(lights.pdf_env(black), 0.0);
    let lit = dir(0.3, 11.5 * PI / 15.0);
    assert!(lights.env_radiance(lit).max_element() > 0.0 && lights.pdf_env(lit) > 0.0);
}

#[test]
fn envmap_sample_matches_lookup_and_estimates_the_integral() {
    // radiance/pdf of the samples is an unbiased estimate of ∫ L dω; the reference is a
    // brute-force quadrature of the lookup itself.
    let to_world = rotation();
    let lights = env_lights(peaked_map(), to_world);
    let env = lights.env_light().unwrap();
    let (nphi, nz) = (2048, 2048);
    let mut reference = glam::DVec3::ZERO;
    for i in 0..nz {
        let z = -1.0 + (i as f64 + 0.5) * 2.0 / nz as f64;
        let r = (1.0 - z * z).sqrt();
        for j in 0..nphi {
            let phi = (j as f64 + 0.5) * std::f64::consts::TAU / nphi as f64;
            let d = Vec3::new((r * phi.cos()) as f32, z as f32, (r * phi.sin()) as f32);
            reference += lights.env_radiance(d).as_dvec3();
        }
    }
    reference *= 4.0 * std::f64::consts::PI / (nphi * nz) as f64;

    let n = 400_000;
    let mut rng = Pcg32::new(23, 0);
    let (mut sum, mut sum2) = (glam::DVec3::ZERO, glam::DVec3::ZERO);
    for _ in 0..n {
        let u = Vec2::new(rng.next_f32(), rng.next_f32());
        let s = lights
            .sample_light(env, Vec3::ZERO, u)
            .expect("a map with light never fails");
        assert_eq!(s.dist, f32::INFINITY);
        assert_eq!(
            s.radiance,
            lights.env_radiance(s.wi),
            "sample radiance = lookup"
        );
        assert_eq!(s.pdf, lights.pdf_env(s.wi), "sample pdf = pdf_env");
        assert!((s.n + s.wi).length() < 1e-6);
        let f = (s.radiance / s.pdf).as_dvec3();
        sum += f;
        sum2 += f * f;
    }
    let mean = sum / n as f64;
    let se = ((sum2 / n as f64 - mean * mean) / n as f64)
        .max(glam::DVec3::ZERO)
        .powf(0.5);
    for c in 0..3 {
        // 5 standard errors + the quadrature's error (0.1 %).
        let tol = 5.0 * se[c] + 1e-3 * reference[c];
        assert!(
            (mean[c] - reference[c]).abs() < tol,
            "channel {c}: MC {} vs quadrature {} (tol {tol})",
            mean[c],
            reference[c]
        );
    }
    // Importance sampling pays off: the relative s.e. is far below uniform sampling's.
    assert!(se.x / mean.x < 0.01, "relative s.e. {}", se.x / mean.x);
}

#[test]
fn envmap_power_selection_uses_its_energy() {
    // A uniform grey map has the same power as a constant environment of the same value.
    let grey = image(8, 4, |_, _| Vec3::splat(0.5));
    let quad = mesh(
        vec![
            Vec3::new(-1.0, -1.0, 2.0),
            Vec3::new(1.0, 1.0, 2.0),
            Vec3::new(1.0, -1.0, 2.0),
        ],
        vec![[0, 1, 2]],
        Some(Vec3::ONE),
    );
    let with = |env| {
        Lights::new(
            &scene(vec![quad.clone()], vec![], Some(env)),
            LightSelection::Power,
        )
    };
    let a = with(Environment::Envmap {
        image: grey,
        to_world: Mat3::IDENTITY,
    });
    let b = with(Environment::Constant {
        radiance: Vec3::splat(0.5),
    });
    assert!(
        (a.selection_pmf(1) - b.selection_pmf(1)).abs() < 1e-4,
        "{} vs {}",
        a.selection_pmf(1),
        b.selection_pmf(1)
    );
    assert!((a.selection_pmf(0) + a.selection_pmf(1) - 1.0).abs() < 1e-6);
}

#[test]
fn constant_env_chi2() {
    let radiance = Vec3::new(0.3, 0.6, 0.9);
    let lights = Lights::new(
        &scene(vec![], vec![], Some(Environment::Constant { radiance })),
        LightSelection::Power,
    );
    assert_eq!(lights.len(), 1);
    assert_eq!(lights.select(0.7), Some((0, 1.0)));
    let r = test_directions(
        |u, _| {
            let s = lights.sample_light(0, Vec3::ZERO, u)?;
            assert_eq!(s.radiance, radiance);
            Some((s.wi, s.pdf))
        },
        |w| lights.pdf_env(w),
        &cfg(),
    );
    assert!(r.passed, "{}", r.report());
    assert_eq!(lights.env_radiance(Vec3::new(0.3, -0.2, 0.1)), radiance);
    assert_eq!(lights.pdf_area(0, Vec3::ZERO, Vec3::X, -Vec3::X), 0.0);
    assert_eq!(lights.area_radiance(0, Vec3::X, Vec3::X), Vec3::ZERO);
}

#[test]
fn small_maps_chi2_and_finite() {
    // One row (used for both poles) and a single texel: lookups are finite and sampling is
    // still consistent.
    let one_row = image(3, 1, |x, _| Vec3::splat(1.0 + x as f32));
    let lights = env_lights(one_row, Mat3::IDENTITY);
    let r = test_directions(
        |u, _| lights.sample_light(0, Vec3::ZERO, u).map(|s| (s.wi, s.pdf)),
        |w| lights.pdf_env(w),
        &Chi2Config {
            samples: 200_000,
            test_count: CHI2_TESTS,
            ..Chi2Config::default()
        },
    );
    assert!(r.passed, "{}", r.report());
    let single = env_lights(image(1, 1, |_, _| Vec3::splat(2.0)), Mat3::IDENTITY);
    for d in [Vec3::Y, -Vec3::Y, Vec3::X, Vec3::new(0.3, -0.4, 0.5)] {
        assert!(close(single.env_radiance(d), Vec3::splat(2.0), 1e-6));
        let p = single.pdf_env(d);
        assert!(
            (p - 0.25 / PI).abs() < 1e-4,
            "uniform single-texel map: pdf {p}"
        );
    }
}

#[test]
fn black_and_malformed_maps_emit_nothing() {
    let black = env_lights(image(8, 4, |_, _| Vec3::ZERO), Mat3::IDENTITY);
    let bad = env_lights(
        RgbImage {
            width: 4,
            height: 4,
            data: vec![Vec3::ONE; 3],
        },
        Mat3::IDENTITY,
    );
    let nan = env_lights(
        image(
            4,
            4,
            |x, _| if x == 0 { Vec3::NAN } else { Vec3::splat(-1.0) },
        ),
        Mat3::IDENTITY,
    );
    for lights in [black, bad, nan] {
        assert_eq!(lights.len(), 1);
        assert!(
            lights
                .sample_light(0, Vec3::ZERO, Vec2::new(0.3, 0.3))
                .is_none()
        );
        assert_eq!(lights.pdf_env(Vec3::Z), 0.0);
        assert_eq!(lights.env_radiance(Vec3::Z), Vec3::ZERO);
    }
}

/// The repository's copy of Mitsuba's `museum.exr` (512×256 half-float lat-long map).
fn museum() -> RgbImage {
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../scenes/envmap/museum.exr"
    );
    let exr = imageio::read_exr(path).expect("scenes/envmap/museum.exr");
    let layer = exr.main_layer().expect("an RGB layer");
    RgbImage {
        width: exr.width,
        height: exr.height,
        data: layer.data.iter().map(|&c| Vec3::from_array(c)).collect(),
    }
}

#[test]
fn museum_env_map_matches_mitsuba_integrals() {
    // Mitsuba 3.9.1 (llvm_ad_rgb) `envmap` on museum.exr, midpoint quadrature of `eval` on a
    // 4096 × 2048 grid uniform in (φ, cos θ) with d = (r cos φ, z, r sin φ):
    // ∫ L dω and the irradiance ∫ L max(0, n·ω) dω for five normals.
    let lights = env_lights(museum(), Mat3::IDENTITY);
    let (nphi, nz) = (4096, 2048);
    let mut integral = glam::DVec3::ZERO;
    for i in 0..nz {
        let z = -1.0 + (i as f64 + 0.5) * 2.0 / nz as f64;
        let r = (1.0 - z * z).sqrt();
        for j in 0..nphi {
            let phi = (j as f64 + 0.5) * std::f64::consts::TAU / nphi as f64;
            let d = Vec3::new((r * phi.cos()) as f32, z as f32, (r * phi.sin()) as f32);
            integral += lights.env_radiance(d).as_dvec3();
        }
    }
    integral *= 4.0 * std::f64::consts::PI / (nphi * nz) as f64;
    let mitsuba = glam::DVec3::new(6.442_307_5, 5.246_613_5, 4.645_759_6);
    assert!(
        ((integral - mitsuba) / mitsuba).abs().max_element() < 2e-5,
        "∫ L dω: ours {integral} vs Mitsuba {mitsuba}"
    );

    // Irradiance by importance sampling the map: unbiased, within 5 s.e. of Mitsuba's.
    let cases = [
        ([0.0, 1.0, 0.0], [1.564_038_9, 1.537_543_4, 1.642_008_1]),
        ([0.0, -1.0, 0.0], [0.574_770_0, 0.303_241_0, 0.173_340_7]),
        ([1.0, 0.0, 0.0], [0.859_874_9, 0.508_644_9, 0.357_523_3]),
        ([0.0, 0.0, 1.0], [0.872_321_6, 0.527_243_5, 0.375_766_4]),
        (
            [0.577_350_3, 0.577_350_3, -0.577_350_3],
            [1.607_616_7, 1.386_777_9, 1.313_162_4],
        ),
    ];
    let env = lights.env_light().unwrap();
    for (k, (n, expected)) in cases.into_iter().enumerate() {
        let n = Vec3::from_array(n);
        let expected = glam::DVec3::from_array(expected);
        let samples = 200_000;
        let mut rng = Pcg32::new(29, k as u64);
        let (mut sum, mut sum2) = (glam::DVec3::ZERO, glam::DVec3::ZERO);
        for _ in 0..samples {
            let u = Vec2::new(rng.next_f32(), rng.next_f32());
            if let Some(s) = lights.sample_light(env, Vec3::ZERO, u) {
                let f = (s.radiance * n.dot(s.wi).max(0.0) / s.pdf).as_dvec3();
                sum += f;
                sum2 += f * f;
            }
        }
        let mean = sum / samples as f64;
        let se = ((sum2 / samples as f64 - mean * mean) / samples as f64)
            .max(glam::DVec3::ZERO)
            .powf(0.5);
        for c in 0..3 {
            let tol = 5.0 * se[c] + 1e-4 * expected[c];
            assert!(
                (mean[c] - expected[c]).abs() < tol,
                "n = {n}, channel {c}: ours {} ± {} vs Mitsuba {}",
                mean[c],
                se[c],
                expected[c]
            );
        }
    }
}
