//! Same job + seed ⇒ bitwise-identical film whatever the tile size and thread count, and
//! whatever the split of a pixel's samples into ranges (merged in canonical order).

mod common;

use common::*;
use glam::Vec3;
use render::{RenderOptions, RenderScene, RenderSettings, TileRect, render_image, render_tile};

fn test_scene() -> scene::Scene {
    let mut s = empty_scene(
        look_at(Vec3::new(0.0, 1.5, -5.0), Vec3::new(0.0, 0.5, 0.0), Vec3::Y),
        45.0,
        40,
        24,
    );
    s.environment = constant_env(Vec3::new(0.2, 0.3, 0.4));
    let grey = add_material(&mut s, diffuse(Vec3::splat(0.6), true));
    let red = add_material(&mut s, diffuse(Vec3::new(0.8, 0.1, 0.1), false));
    s.meshes.push(quad(
        Vec3::ZERO,
        Vec3::new(0.0, 0.0, 3.0),
        Vec3::new(3.0, 0.0, 0.0),
        grey,
        None,
    ));
    s.meshes.push(quad(
        Vec3::new(0.0, 2.5, 0.0),
        Vec3::new(0.5, 0.0, 0.0),
        Vec3::new(0.0, 0.0, 0.5),
        grey,
        Some(Vec3::splat(8.0)),
    ));
    s.spheres
        .push(sphere(Vec3::new(0.0, 0.6, 0.0), 0.6, red, None));
    s.spheres.push(sphere(
        Vec3::new(1.3, 0.3, 0.5),
        0.3,
        grey,
        Some(Vec3::new(2.0, 1.0, 0.5)),
    ));
    s
}

#[test]
fn film_is_bitwise_identical_across_tile_sizes_and_thread_counts() {
    let s = test_scene();
    let st = RenderSettings {
        spp: 8,
        seed: 1234,
        max_depth: 6,
        rr_depth: 2,
        ..RenderSettings::from_scene(&s)
    };
    let rs = RenderScene::new(&s, &st).unwrap();
    let reference = render_image(
        &rs,
        &st,
        &RenderOptions {
            tile_size: 8,
            threads: 1,
        },
        &|_, _| {},
    )
    .unwrap()
    .0
    .to_bits();
    for (tile_size, threads) in [(8, 2), (16, 1), (16, 2), (64, 1), (64, 2)] {
        let film = render_image(&rs, &st, &RenderOptions { tile_size, threads }, &|_, _| {})
            .unwrap()
            .0;
        assert!(
            film.to_bits() == reference,
            "tile {tile_size}, threads {threads} differ"
        );
    }
    // A different seed gives a different image (the test can fail).
    let other = RenderSettings { seed: 1235, ..st };
    let film = render_image(&rs, &other, &RenderOptions::default(), &|_, _| {})
        .unwrap()
        .0;
    assert!(film.to_bits() != reference);
}

#[test]
fn sample_ranges_merged_in_order_equal_one_range() {
    let s = test_scene();
    let st = RenderSettings {
        spp: 6,
        seed: 9,
        max_depth: 4,
        ..RenderSettings::from_scene(&s)
    };
    let rs = RenderScene::new(&s, &st).unwrap();
    let tile = TileRect {
        x0: 8,
        y0: 4,
        width: 12,
        height: 10,
    };
    let whole = render_tile(&rs, &st, tile, 0..6).unwrap();
    let mut parts = render_tile(&rs, &st, tile, 0..2).unwrap();
    parts.merge(&render_tile(&rs, &st, tile, 2..6).unwrap());
    assert_eq!(whole.pixels.iter().map(|p| p.count).sum::<u64>(), 6 * 120);
    // Counts and the first sample range agree exactly; sums agree to rounding.
    for (a, b) in whole.pixels.iter().zip(&parts.pixels) {
        assert_eq!(a.count, b.count);
        for c in 0..3 {
            assert!((a.sum[c] - b.sum[c]).abs() <= 1e-9 * a.sum[c].abs().max(1.0));
        }
    }
}

#[test]
fn tile_outside_the_image_is_an_error_not_a_panic() {
    let s = test_scene();
    let st = RenderSettings::from_scene(&s);
    let rs = RenderScene::new(&s, &st).unwrap();
    assert!(
        render_tile(
            &rs,
            &st,
            TileRect {
                x0: 30,
                y0: 0,
                width: 16,
                height: 4
            },
            0..1
        )
        .is_err()
    );
    let bad = RenderSettings { max_depth: 0, ..st };
    assert!(RenderScene::new(&s, &bad).is_err());
}

#[test]
fn same_pixel_and_sample_give_the_same_numbers_and_pixels_are_decorrelated() {
    use render::sampler::Sampler;
    let a: Vec<f32> = {
        let mut s = Sampler::new(5, 100, 3);
        (0..40).map(|_| s.next_1d()).collect()
    };
    let b: Vec<f32> = {
        let mut s = Sampler::new(5, 100, 3);
        (0..40).map(|_| s.next_1d()).collect()
    };
    assert_eq!(a, b);
    // Correlation of dimension 0..8 between neighbouring pixels over 256 samples ≈ 0.
    for dim in 0..8 {
        let xs: Vec<f64> = (0..256)
            .map(|i| f64::from(Sampler::new(5, 100, i).get(dim)))
            .collect();
        let ys: Vec<f64> = (0..256)
            .map(|i| f64::from(Sampler::new(5, 101, i).get(dim)))
            .collect();
        let (mx, my) = (
            xs.iter().sum::<f64>() / 256.0,
            ys.iter().sum::<f64>() / 256.0,
        );
        let cov: f64 = xs
            .iter()
            .zip(&ys)
            .map(|(x, y)| (x - mx) * (y - my))
            .sum::<f64>()
            / 256.0;
        let corr = cov / (1.0 / 12.0);
        // Independent uniforms: corr has σ ≈ 1/√256 = 0.0625; 5σ bound.
        assert!(corr.abs() < 0.31, "dim {dim}: correlation {corr}");
        assert!((mx - 0.5).abs() < 0.05, "dim {dim}: mean {mx}");
    }
}
