//! Robustness and determinism of the CV estimators: finite images on every shipped scene
//! and the shared Mitsuba scenes, named hard cases, bitwise determinism across thread
//! counts and tile sizes, and the JSON spec of the estimators.

mod cv_support;

use cv_support::{all_finite, load, region_mean, render};
use estimators::spec::{HELD_OUT_SHARE_STRATIFIED, PER_LIGHT_HELD_OUT_SHARE};
use render::integrator::cms::CmsOptions;
use render::integrator::optimal_mis::OptimalMisOptions;
use render::integrator::per_light_cv::PerLightCvOptions;
use render::{Estimator, RenderOptions};

/// A small `cms` job (8 training spp) starting at `min_depth` whose fits are not switched
/// off by their predicted gains.
fn fits_kept(min_depth: Option<u32>) -> CmsOptions {
    CmsOptions {
        training_spp: 8,
        min_samples: 4,
        min_depth,
        min_image_gain: None,
        min_fit_gain: None,
        ..CmsOptions::default()
    }
}

fn estimators() -> Vec<Estimator> {
    vec![
        // Its gathers' BSDF samples go through the emitters-only BVH (`RenderScene::emitters`).
        Estimator::Ocv(render::integrator::ocv::OcvOptions::default()),
        Estimator::Cms(CmsOptions {
            training_spp: 4,
            min_samples: 4,
            ..CmsOptions::default()
        }),
        Estimator::Cms(CmsOptions {
            relative: false,
            color: render::integrator::cv::CvColor::Mono,
            training_spp: 4,
            grid_resolution: Some([8, 8, 8]),
            // Also the camera hit (the default `min_depth` 1 leaves it to the base).
            min_depth: Some(0),
            min_image_gain: None,
            min_fit_gain: None,
            ..CmsOptions::default()
        }),
        Estimator::PerLightCv(PerLightCvOptions {
            training_spp: 4,
            ..PerLightCvOptions::default()
        }),
        Estimator::OptimalMis(OptimalMisOptions {
            training_spp: 4,
            min_samples: 4,
            ..OptimalMisOptions::default()
        }),
    ]
}

fn finite_everywhere(rel: &str) {
    let s = load(rel, 20, 16);
    for e in estimators() {
        let (f, report) = render(&s, e, 8, 3, None, RenderOptions::default());
        assert!(all_finite(&f), "{rel} {e:?}");
        assert_eq!(f.rejected, 0, "{rel} {e:?}: rejected samples");
        assert!(f.pixels.iter().all(|p| p.count == 8));
        assert!(
            report
                .layers
                .iter()
                .all(|l| l.data.iter().flatten().all(|v| v.is_finite()))
        );
    }
}

#[test]
fn finite_on_cornell_box() {
    finite_everywhere("scenes/cornell-box/scene.json");
}

#[test]
fn finite_on_veach_mis() {
    finite_everywhere("scenes/veach-mis/scene.json");
}

#[test]
fn finite_on_many_lights() {
    finite_everywhere("scenes/many-lights/scene.json");
}

#[test]
fn finite_on_many_lights_256() {
    finite_everywhere("scenes/many-lights-256/scene.json");
}

#[test]
fn finite_on_envmap() {
    finite_everywhere("scenes/envmap/scene.json");
}

#[test]
fn finite_on_colour_lamp() {
    finite_everywhere("scenes/colour-lamp/scene.json");
}

/// High-contrast texture boundaries (checkerboard under a large and a small light).
#[test]
fn finite_on_checkers_high_contrast_texture() {
    finite_everywhere("scenes/checkers/scene.json");
}

#[test]
fn finite_on_mitsuba_scenes() {
    for rel in [
        "../shared/scenes-mitsuba/cbox/scene.xml",
        "../shared/scenes-mitsuba/manylights-4/scene.xml",
        "../shared/scenes-mitsuba/bsdf-spheres/roughconductor-ggx/scene.xml",
        "../shared/scenes-mitsuba/bsdf-spheres/roughplastic-ggx/scene.xml",
    ] {
        // `../shared` is beside the checkout (as in CI); a missing scene fails the test.
        finite_everywhere(rel);
    }
}

/// 64 lights clustered into 4 components: most clusters' lights are unsampled in most cells,
/// and with a fine grid many cells see only a few partitions; the image stays finite and
/// unbiased against `path` on the whole-image mean.
#[test]
fn many_lights_clustered_with_unsampled_partitions() {
    let s = load("scenes/many-lights/scene.json", 24, 24);
    let e = Estimator::Cms(CmsOptions {
        training_spp: 4,
        min_samples: 4,
        grid_resolution: Some([16, 16, 16]),
        max_light_components: 4,
        min_image_gain: None,
        min_fit_gain: None,
        ..CmsOptions::default()
    });
    let opts = RenderOptions::default();
    let mut means = Vec::new();
    for seed in 0..8 {
        let (f, report) = render(&s, e, 12, seed, Some(3), opts);
        assert!(all_finite(&f));
        assert_eq!(report.light_components, 4);
        means.push(region_mean(&f, 0, 0, 24, 24));
    }
    let (reference, _) = render(&s, Estimator::Path, 512, 77, Some(3), opts);
    let r = region_mean(&reference, 0, 0, 24, 24);
    for c in 0..3 {
        let xs: Vec<f64> = means.iter().map(|m| m[c]).collect();
        let (m, se) = cv_support::mean_se(&xs);
        assert!((m - r[c]).abs() < 5.0 * se + 0.03 * r[c], "{m} vs {}", r[c]);
    }
}

/// Occluded lights: in the Cornell box most NEE samples from the floor under the boxes and
/// behind them are occluded (zero-contribution samples with every pdf); a fine grid makes
/// many cells mostly occluded. Finite, and the cv_term layer averages to ~0 (unbiased).
#[test]
fn occluded_lights_zero_contribution_samples() {
    let s = load("scenes/cornell-box/scene.json", 32, 32);
    let e = Estimator::Cms(CmsOptions {
        training_spp: 8,
        min_samples: 4,
        grid_resolution: Some([24, 24, 24]),
        min_image_gain: None,
        min_fit_gain: None,
        ..CmsOptions::default()
    });
    let (f, report) = render(&s, e, 32, 5, None, RenderOptions::default());
    assert!(all_finite(&f));
    assert!(report.cells_solved > 0, "{report:?}");
    let cv = &report.layers[0].data;
    for c in 0..3 {
        let xs: Vec<f64> = cv.iter().map(|v| f64::from(v[c])).collect();
        let (m, se) = cv_support::mean_se(&xs);
        assert!(m.abs() <= 5.0 * se + 1e-9, "cv term mean {m} ± {se}");
    }
}

#[test]
fn deterministic_across_threads_and_tile_sizes() {
    let s = load("scenes/colour-lamp/scene.json", 37, 23);
    for e in estimators() {
        let (a, ra) = render(
            &s,
            e,
            8,
            11,
            None,
            RenderOptions {
                tile_size: 8,
                threads: 1,
            },
        );
        let (b, rb) = render(
            &s,
            e,
            8,
            11,
            None,
            RenderOptions {
                tile_size: 13,
                threads: 2,
            },
        );
        assert!(a.pixels == b.pixels, "{e:?}");
        assert_eq!(ra.cells, rb.cells);
        assert_eq!(ra.layers, rb.layers);
    }
}

/// With fewer samples than the training budget there is no render phase: the image is the
/// plain estimator's, and the report says so.
#[test]
fn tiny_budget_has_no_render_phase() {
    let s = load("scenes/cornell-box/scene.json", 8, 8);
    let (f, report) = render(
        &s,
        Estimator::Cms(CmsOptions::default()),
        2,
        0,
        None,
        RenderOptions::default(),
    );
    assert!(all_finite(&f));
    assert_eq!(
        (report.surrogate_spp, report.training_spp, report.render_spp),
        (1, 1, 0)
    );
}

#[test]
fn estimator_json_specs_parse_and_reject_unknown_fields() {
    let e: Estimator = serde_json::from_str(
        r#"{ "kind": "cms", "relative": false, "color": "mono", "grid_resolution": [4, 5, 6] }"#,
    )
    .unwrap();
    let Estimator::Cms(o) = e else {
        panic!("{e:?}")
    };
    assert_eq!(o.grid_resolution, Some([4, 5, 6]));
    assert_eq!(o.color, render::integrator::cv::CvColor::Mono);
    assert_eq!(o.training_spp, 16);
    assert!(serde_json::from_str::<Estimator>(r#"{ "kind": "cms", "bogus": 1 }"#).is_err());
    assert!(matches!(
        serde_json::from_str::<Estimator>(r#"{ "kind": "per_light_cv" }"#),
        Ok(Estimator::PerLightCv(_))
    ));
    assert!(matches!(
        serde_json::from_str::<Estimator>(r#"{ "kind": "optimal_mis", "training_spp": 8 }"#),
        Ok(Estimator::OptimalMis(o)) if o.training_spp == 8
    ));
    let s = serde_json::to_string(&Estimator::Cms(CmsOptions::default())).unwrap();
    assert!(s.contains(r#""kind":"cms""#), "{s}");
}

#[test]
fn bad_grid_resolution_is_an_error() {
    let s = load("scenes/cornell-box/scene.json", 8, 8);
    let st = render::RenderSettings {
        spp: 4,
        estimator: Estimator::Cms(CmsOptions {
            grid_resolution: Some([0, 4, 4]),
            ..CmsOptions::default()
        }),
        ..render::RenderSettings::from_scene(&s)
    };
    let rs = render::RenderScene::new(&s, &st).unwrap();
    let r = render::integrator::cv::render_estimator_image(
        &rs,
        &st,
        &RenderOptions::default(),
        &|_, _| {},
    );
    assert!(r.is_err());
}

/// Largest per-pixel, per-channel difference of the sample sums of `f` and `p`, relative to
/// `p`'s (plus 10⁻³); both films must hold the same sample count in every pixel.
fn worst_relative_difference(f: &render::film::Film, p: &render::film::Film) -> f64 {
    let mut worst = 0.0f64;
    for (a, b) in f.pixels.iter().zip(&p.pixels) {
        assert_eq!(a.count, b.count);
        for c in 0..3 {
            let d = (a.sum[c] - b.sum[c]).abs() / (1e-3 + b.sum[c].abs());
            worst = worst.max(d);
        }
    }
    worst
}

/// When the fits are predicted not to pay (the table's predicted image gain under
/// `min_image_gain`) every fitted cell falls back (`LowImageGain`), the training tiles stop
/// recording after their probe, and the render phase is traced as `path`: the image is
/// `path`'s up to rounding (the training vertices' values are the same estimator summed in
/// another order), while with the fits applied it is not; a minimum under the prediction
/// changes no bit.
#[test]
fn fits_predicted_not_to_pay_leave_the_image_to_path() {
    let opts = RenderOptions::default();
    let s = load("scenes/cornell-box/scene.json", 24, 16);
    let (p, _) = render(&s, Estimator::Path, 24, 5, None, opts);
    let run = |min_image_gain| {
        let e = Estimator::Cms(CmsOptions {
            training_spp: 8,
            min_samples: 4,
            min_image_gain,
            min_fit_gain: None,
            ..CmsOptions::default()
        });
        render(&s, e, 24, 5, None, opts)
    };
    let worst = |f: &render::film::Film| worst_relative_difference(f, &p);
    let (on, r_on) = run(None);
    let gain = r_on.predicted_image_gain.expect("a predicted gain");
    assert!(r_on.cells_solved > 0, "{r_on:?}");
    assert_eq!(r_on.training_tiles_stopped, 0, "{r_on:?}");
    let (off, r_off) = run(Some(gain + 0.5));
    assert_eq!(r_off.cells_solved, 0, "{r_off:?}");
    assert!(
        r_off.cells_fallback.get("LowImageGain").copied() > Some(0),
        "{r_off:?}"
    );
    assert!(
        r_off.training_tiles > 0 && r_off.training_tiles_stopped == r_off.training_tiles,
        "{r_off:?}"
    );
    let (d_on, d_off) = (worst(&on), worst(&off));
    assert!(d_off <= 1e-5, "fits off: {d_off} from path");
    assert!(d_on > 1e-3, "fits on: {d_on} from path");
    let (kept, _) = run(Some(gain - 0.5));
    let bits = |f: &render::film::Film| {
        f.pixels
            .iter()
            .flat_map(|q| q.sum.map(f64::to_bits))
            .collect::<Vec<_>>()
    };
    assert!(bits(&kept) == bits(&on));
}

/// The `cell` layer holds the camera-hit cell of each pixel's first render-phase sample that
/// found one. Below `min_depth` (the default 1 with the Sobol sampler) that cell is looked up
/// for the layer alone, and only until a sample of the pixel finds it. With `min_depth` 0 the
/// control looks it up at every sample, and the layer is the same bit for bit, since the
/// render phase's samples and camera rays are the same. In the closed Cornell box every camera
/// ray hits, so every pixel has a cell.
#[test]
fn the_cell_layer_is_the_first_samples_cell_whatever_the_min_depth() {
    let opts = RenderOptions::default();
    let s = load("scenes/cornell-box/scene.json", 24, 16);
    let run = |min_depth| {
        let e = Estimator::Cms(CmsOptions {
            min_held_out_share: Some(0.0),
            ..fits_kept(min_depth)
        });
        let (_, r) = render(&s, e, 24, 5, None, opts);
        assert!(r.cells_solved > 0, "{r:?}");
        let layer = r.layers.iter().find(|l| l.name == "cell").unwrap();
        layer.data.iter().map(|c| c[0]).collect::<Vec<f32>>()
    };
    let (skipped, controlled) = (run(None), run(Some(0)));
    assert_eq!(skipped.len(), 24 * 16);
    assert!(
        skipped.iter().all(|&c| c >= 0.0 && c.fract() == 0.0),
        "{skipped:?}"
    );
    let bits = |v: &[f32]| v.iter().map(|c| c.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(&skipped), bits(&controlled));
}

/// The default `min_image_gain` and `min_fit_gain` against the scenes they were measured on
/// (`docs/bench/README.md`, "Regressing to the baseline" and "Within a technique"):
/// veach-mis, whose controlled vertices hold almost none of the image's variance (image gain
/// ~10⁻⁵ here) but whose fits are good (fit gain ~0.5), is switched off by the first;
/// envmap, the shared rough-plastic spheres and both Cornell boxes, whose fits remove at most
/// 3 % of the variance within a technique where they act (1.00× / 0.99× at equal spp), have
/// a fit gain under the second (and their image gain is as small); colour-lamp (fit gain
/// ~0.45) and the shared `manylights-4` at its native size (image gain ~7·10⁻⁴, fit gain
/// ~0.37, a measured 1.23× at equal spp) keep their fits.
#[test]
fn the_default_switch_drops_useless_fits_and_keeps_useful_ones() {
    let opts = RenderOptions::default();
    let mitsuba = "../shared/scenes-mitsuba";
    for (rel, w, h, off_by) in [
        ("scenes/veach-mis/scene.json", 96, 64, Some("LowImageGain")),
        ("scenes/envmap/scene.json", 64, 48, Some("LowFitGain")),
        (
            &format!("{mitsuba}/bsdf-spheres/roughplastic-ggx/scene.xml"),
            64,
            64,
            Some("LowFitGain"),
        ),
        // One small light, which NEE finds and the BSDF sample misses: the pooled fit
        // explained that spread between the techniques (pooled fit gain 0.56, 0.99x at
        // equal spp); within a technique it removes nothing.
        (
            &format!("{mitsuba}/cbox/scene.xml"),
            64,
            64,
            Some("LowFitGain"),
        ),
        ("scenes/cornell-box/scene.json", 64, 64, Some("LowFitGain")),
        ("scenes/colour-lamp/scene.json", 64, 64, None),
        (&format!("{mitsuba}/manylights-4/scene.xml"), 128, 128, None),
    ] {
        let s = load(rel, w, h);
        let (f, r) = render(
            &s,
            Estimator::Cms(CmsOptions::default()),
            20,
            0,
            Some(5),
            opts,
        );
        assert!(all_finite(&f));
        let (Some(image_gain), Some(fit_gain)) = (r.predicted_image_gain, r.predicted_fit_gain)
        else {
            panic!("{rel}: no predictions");
        };
        let count = |reason| r.cells_fallback.get(reason).copied().unwrap_or(0);
        let switched = count("LowImageGain") + count("LowFitGain");
        let defaults = CmsOptions::default();
        let (min_image, min_fit) = (
            defaults.min_image_gain.unwrap(),
            defaults.min_fit_gain.unwrap(),
        );
        let summary = format!(
            "{rel}: image gain {image_gain}, fit gain {fit_gain}, solved {}, fallback {:?}",
            r.cells_solved, r.cells_fallback
        );
        eprintln!("{summary}");
        match off_by {
            None => assert!(
                r.cells_solved > 0
                    && switched == 0
                    && fit_gain >= min_fit
                    && r.predicted_held_out_share.unwrap() >= HELD_OUT_SHARE_STRATIFIED,
                "{summary}, held-out share {:?}",
                r.predicted_held_out_share
            ),
            // The image gain is checked first (its cells are counted under it), so a scene
            // whose fits are useless may be caught by either; the claim is the fit gain's.
            Some("LowFitGain") => assert!(
                r.cells_solved == 0 && switched > 0 && fit_gain < min_fit,
                "{summary}"
            ),
            Some(reason) => assert!(
                r.cells_solved == 0
                    && count(reason) == switched
                    && switched > 0
                    && image_gain < min_image
                    && fit_gain >= min_fit,
                "{summary}"
            ),
        }
    }
}

/// Many lights with a few training samples of each per cell (`many-lights-256`: 256 lamps,
/// here at 96×96): the fits' in-sample gain clears `min_fit_gain`, but held out (each half's
/// fits on the other half) they keep a tenth of it, so under the Sobol sampler the job
/// switches them off (`Overfitted`) and renders `path`'s image; such fits gave 1.03× at
/// equal spp for +13…+17 % of time (`docs/bench/README.md`). With the check off (`0`), the same
/// training applies them. The many-light scenes whose fits pay keep a share of 0.4 or more
/// (the calibration test above; `many-lights`' is measured in the docs).
#[test]
fn fits_that_follow_their_samples_noise_are_switched_off() {
    let s = load("scenes/many-lights-256/scene.json", 96, 96);
    let opts = RenderOptions::default();
    let cms = |share| {
        Estimator::Cms(CmsOptions {
            min_held_out_share: share,
            ..CmsOptions::default()
        })
    };
    let (f, r) = render(&s, cms(None), 20, 3, Some(5), opts);
    assert!(all_finite(&f));
    let count = |r: &render::integrator::cv::EstimatorReport, reason: &str| {
        r.cells_fallback.get(reason).copied().unwrap_or(0)
    };
    let min_fit = CmsOptions::default().min_fit_gain.unwrap();
    let (fit, held_out, share) = (
        r.predicted_fit_gain.unwrap(),
        r.predicted_held_out_gain.unwrap(),
        r.predicted_held_out_share.unwrap(),
    );
    let summary = format!(
        "fit gain {fit}, held out {held_out}, share {share}, solved {}, fallback {:?}",
        r.cells_solved, r.cells_fallback
    );
    assert!(fit >= min_fit && held_out < min_fit, "{summary}");
    assert!(share < HELD_OUT_SHARE_STRATIFIED / 2.0, "{summary}");
    assert!(
        r.cells_solved == 0 && count(&r, "Overfitted") > 0,
        "{summary}"
    );
    // The render phase is `path`'s: no CV term anywhere.
    let cv_term = |r: &render::integrator::cv::EstimatorReport| {
        let layer = r.layers.iter().find(|l| l.name == "cv_term").unwrap();
        layer.data.iter().any(|v| *v != [0.0; 3])
    };
    assert!(!cv_term(&r), "{summary}");
    let (g, kept) = render(&s, cms(Some(0.0)), 20, 3, Some(5), opts);
    assert!(all_finite(&g));
    assert!(kept.cells_solved > 0 && count(&kept, "Overfitted") == 0);
    assert!(cv_term(&kept));
    assert_eq!(kept.predicted_held_out_share, Some(share));
    assert!(f.pixels != g.pixels);
}

/// A training tile of `many-lights` (64 lamps) is not stopped by its probe's fit gain: at 2
/// spp every light partition of its cells is thin (below `min_group_samples`), its grouped
/// fits remove a few percent of what the job's fits remove once trained (probe fit gain
/// 0.025–0.06 here, the job's 0.21–0.25), and judging them stopped the tile at seeds 2, 4 and
/// 5 of 1–5 at this size, leaving the job no fits (`path`, where they give 1.25× at equal
/// spp at 256²). The probe still judges its image gain.
#[test]
fn a_many_light_tiles_thin_probe_does_not_stop_it() {
    let opts = RenderOptions::default();
    let s = load("scenes/many-lights/scene.json", 96, 96);
    for seed in [2, 4] {
        let (f, r) = render(
            &s,
            Estimator::Cms(CmsOptions::default()),
            20,
            seed,
            Some(5),
            opts,
        );
        assert!(all_finite(&f));
        let summary = format!(
            "seed {seed}: stopped {} of {}, solved {}, fit gain {:?}",
            r.training_tiles_stopped, r.training_tiles, r.cells_solved, r.predicted_fit_gain
        );
        assert_eq!(r.training_tiles_stopped, 0, "{summary}");
        assert!(r.cells_solved > 0, "{summary}");
    }
}

/// `per_light_cv`'s cell means on the same room: held out (each half's light means judged
/// on the other half's vertices) they keep 0.64–0.73 of their in-sample reduction where the
/// scenes whose means pay keep 0.87 or more (`PER_LIGHT_HELD_OUT_SHARE`'s measurements), so
/// the job switches them off (`Overfitted`, whatever the held-out gain) and renders `path`'s
/// image; applied they gave 1.07× at equal spp for +19 % of time. On `many-lights` (64 lamps,
/// 1.28× at equal spp) the means stay. With the check off the same training applies them.
#[test]
fn per_light_means_that_follow_their_samples_noise_are_switched_off() {
    let opts = RenderOptions::default();
    let run = |scene: &scene::Scene, share| {
        render(
            scene,
            Estimator::PerLightCv(PerLightCvOptions {
                min_held_out_share: share,
                ..PerLightCvOptions::default()
            }),
            20,
            3,
            Some(5),
            opts,
        )
    };
    let count = |r: &render::integrator::cv::EstimatorReport, reason: &str| {
        r.cells_fallback.get(reason).copied().unwrap_or(0)
    };
    let summary = |r: &render::integrator::cv::EstimatorReport| {
        format!(
            "fit gain {:?}, held out {:?}, share {:?}, solved {}, fallback {:?}",
            r.predicted_fit_gain,
            r.predicted_held_out_gain,
            r.predicted_held_out_share,
            r.cells_solved,
            r.cells_fallback
        )
    };
    let min_share = PER_LIGHT_HELD_OUT_SHARE;
    let room = load("scenes/many-lights-256/scene.json", 96, 96);
    let (f, r) = run(&room, Some(min_share));
    assert!(all_finite(&f));
    let share = r.predicted_held_out_share.expect("a share");
    assert!(share < min_share, "{}", summary(&r));
    assert!(
        r.cells_solved == 0 && count(&r, "Overfitted") > 0,
        "{}",
        summary(&r)
    );
    let (g, kept) = run(&room, None);
    assert!(kept.cells_solved > 0 && count(&kept, "Overfitted") == 0);
    assert_eq!(kept.predicted_held_out_share, Some(share));
    assert!(f.pixels != g.pixels);
    // At its own 256×256 (0.86–0.88 at seeds 3, 20, 21; at 96×96 its cells hold fewer
    // vertices and it keeps 0.79–0.81, where a false switch costs the surrogate and the
    // training's recording, ≈ 2 %).
    let lamps = load("scenes/many-lights/scene.json", 256, 256);
    let (_, r) = run(&lamps, Some(min_share));
    assert!(
        r.predicted_held_out_share.is_some_and(|s| s >= min_share) && r.cells_solved > 0,
        "{}",
        summary(&r)
    );
}

/// `optimal_mis`'s per-pixel fits lose to the Sobol sampler's stratified pixel means on
/// veach-mis (0.94–0.96× at equal spp, docs/bench/README.md): the split-half check drops the
/// tile and the image is `path`'s; without the check the fits are applied and the image
/// differs.
#[test]
fn optimal_mis_drops_fits_that_lose_to_the_stratified_pixel_mean() {
    let opts = RenderOptions::default();
    let veach = load("scenes/veach-mis/scene.json", 96, 64);
    let (p, _) = render(&veach, Estimator::Path, 20, 0, Some(5), opts);
    let run = |o: OptimalMisOptions| render(&veach, Estimator::OptimalMis(o), 20, 0, Some(5), opts);
    let (f, r) = run(OptimalMisOptions::default());
    assert!(
        r.training_tiles > 0 && r.training_tiles_dropped == r.training_tiles && r.cells_solved == 0,
        "{r:?}"
    );
    assert!(worst_relative_difference(&f, &p) <= 1e-5);
    let (f, r) = run(OptimalMisOptions {
        min_split_gain: None,
        ..OptimalMisOptions::default()
    });
    assert!(r.training_tiles_dropped == 0 && r.cells_solved > 0, "{r:?}");
    assert!(all_finite(&f) && worst_relative_difference(&f, &p) > 1e-3);
}

/// `per_light_cv`'s coefficients (cell means, not fitted) are kept only where they reduce the
/// cell's surrogate-weighted variance [Hua eq. 25, 29], and the table switch of `cms` decides
/// whether the rest pays. On veach-mis the cell means subtracted at the dark pixels' vertices
/// made the image 8× noisier at equal spp (`docs/bench/README.md`); now the cells that would
/// add variance fall back (`NoReduction`), the rest are predicted to remove little of the
/// NEE estimates' weighted variance (fit gain ~0.04 < 0.2), the table is switched off and
/// the job is `path`'s image up to rounding. Without the switches (`min_*_gain` null) the
/// per-cell rule alone still drops cells there. On colour-lamp (1.9× at equal spp) the fit
/// gain passes and most cells keep their means.
#[test]
fn per_light_cv_keeps_its_means_only_where_they_reduce_the_weighted_variance() {
    let opts = RenderOptions::default();
    let run = |s: &scene::Scene, o: PerLightCvOptions| {
        render(s, Estimator::PerLightCv(o), 20, 0, Some(5), opts)
    };
    let count = |r: &render::integrator::cv::EstimatorReport, reason: &str| {
        r.cells_fallback.get(reason).copied().unwrap_or(0)
    };
    let summary = |r: &render::integrator::cv::EstimatorReport| {
        format!(
            "solved {}, fallback {:?}, image gain {:?}, fit gain {:?}",
            r.cells_solved, r.cells_fallback, r.predicted_image_gain, r.predicted_fit_gain
        )
    };
    let defaults = PerLightCvOptions::default();
    let veach = load("scenes/veach-mis/scene.json", 96, 64);
    let (p, _) = render(&veach, Estimator::Path, 20, 0, Some(5), opts);
    let (f, r) = run(&veach, defaults);
    let switched = count(&r, "LowImageGain") + count(&r, "LowFitGain");
    assert!(
        r.cells_solved == 0 && count(&r, "NoReduction") > 0 && switched > 0,
        "{}",
        summary(&r)
    );
    let fit_gain = r.predicted_fit_gain.expect("a prediction");
    assert!(fit_gain < defaults.min_fit_gain.unwrap(), "{}", summary(&r));
    assert!(worst_relative_difference(&f, &p) <= 1e-5);
    // The per-cell rule on its own (no table switch).
    let (_, r) = run(
        &veach,
        PerLightCvOptions {
            min_image_gain: None,
            min_fit_gain: None,
            min_held_out_share: None,
            ..defaults
        },
    );
    assert!(
        r.cells_solved > 0 && count(&r, "NoReduction") > 0,
        "{}",
        summary(&r)
    );
    assert_eq!(count(&r, "LowImageGain") + count(&r, "LowFitGain"), 0);
    let lamp = load("scenes/colour-lamp/scene.json", 64, 64);
    let (f, r) = run(&lamp, defaults);
    assert!(all_finite(&f));
    let fit_gain = r.predicted_fit_gain.expect("a prediction");
    assert!(
        fit_gain >= defaults.min_fit_gain.unwrap() && r.cells_solved > count(&r, "NoReduction"),
        "{}",
        summary(&r)
    );
}

/// With the default `min_depth` 1 a depth-2 job has no vertex to control: every phase is
/// traced by `path` itself, so the image is `path`'s up to the order in which the phases'
/// sums are added; with `min_depth` 0 the same job applies a CV at the camera hit and differs.
#[test]
fn cms_at_depth_two_is_path() {
    let opts = RenderOptions::default();
    for rel in [
        "scenes/many-lights/scene.json",
        "scenes/veach-mis/scene.json",
    ] {
        let s = load(rel, 24, 16);
        let (p, _) = render(&s, Estimator::Path, 24, 5, Some(2), opts);
        let diff = |min_depth| {
            let e = Estimator::Cms(fits_kept(min_depth));
            let (cv, report) = render(&s, e, 24, 5, Some(2), opts);
            (worst_relative_difference(&cv, &p), report.cells_solved)
        };
        let (d1, solved1) = diff(Some(1));
        assert_eq!(solved1, 0, "{rel}");
        // The default with the (default) Sobol sampler is 1.
        assert_eq!(diff(None), (d1, solved1), "{rel}");
        assert!(d1 <= 1e-9, "{rel}: min_depth 1 differs from path by {d1}");
        let (d0, solved0) = diff(Some(0));
        assert!(
            solved0 > 0 && d0 > 1e-6,
            "{rel}: min_depth 0 {d0} ({solved0} cells)"
        );
    }
}

/// A training tile's table has the same bits for any thread count: its bands render in
/// parallel and finish in any order, but their samples are added to the tile's cells in band
/// order (a regression guard for the in-order fold; pixels alone would not show a changed
/// sum, since the coefficients are rounded to `bfloat16`).
#[test]
fn training_table_bits_do_not_depend_on_threads() {
    use render::integrator::cv::CvJob;
    use render::{RenderScene, RenderSettings, TileRect};

    // One 64 × 128 training tile: 64 bands of `BAND_ROWS` (2) rows.
    let s = load("scenes/many-lights/scene.json", 64, 128);
    let estimators = [
        Estimator::Cms(CmsOptions::default()),
        // The split-half check off: it would drop the tile's table.
        Estimator::OptimalMis(OptimalMisOptions {
            min_split_gain: None,
            ..OptimalMisOptions::default()
        }),
        Estimator::PerLightCv(PerLightCvOptions::default()),
    ];
    for e in estimators {
        let st = RenderSettings {
            spp: 20,
            seed: 3,
            max_depth: 5,
            estimator: e,
            ..RenderSettings::from_scene(&s)
        };
        let rs = RenderScene::new(&s, &st).unwrap();
        let job = CvJob::new(&rs, &st).unwrap().expect("a phased estimator");
        let train = job.phases().train.clone();
        let surrogate = job.needs_surrogate().then(|| vec![0.5; 64 * 128]);
        let tile = TileRect {
            x0: 0,
            y0: 0,
            width: 64,
            height: 128,
        };
        let bits = |threads: usize| {
            let cells = train_on_threads(&job, tile, &train, surrogate.as_deref(), threads).cells;
            // The whole table, image variance included.
            cells.encode()
        };
        let one = bits(1);
        assert!(one.len() > 1000, "{e:?}: a table with cells");
        for threads in [2, 3, 5, 8] {
            assert!(
                bits(threads) == one,
                "{e:?}: {threads} threads changed the table"
            );
        }
    }
}

/// `job`'s training tile `tile` rendered on a pool of `threads` threads.
fn train_on_threads(
    job: &render::integrator::cv::CvJob<'_>,
    tile: render::TileRect,
    samples: &std::ops::Range<u32>,
    surrogate: Option<&[f64]>,
    threads: usize,
) -> render::integrator::cv::TrainTile {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap();
    pool.install(|| job.train_tile(tile, samples.clone(), surrogate))
        .unwrap()
}

/// Training tile `tile` of `scene` under `estimator` (40 spp, seed 2, depth 5; a flat 0.5
/// surrogate where the estimator needs one) on `threads` threads, and its training spp.
fn train_tile_of(
    scene: &scene::Scene,
    estimator: Estimator,
    tile: render::TileRect,
    threads: usize,
) -> (render::integrator::cv::TrainTile, u32) {
    use render::integrator::cv::CvJob;
    use render::{RenderScene, RenderSettings};
    let st = RenderSettings {
        spp: 40,
        seed: 2,
        max_depth: 5,
        estimator,
        ..RenderSettings::from_scene(scene)
    };
    let rs = RenderScene::new(scene, &st).unwrap();
    let job = CvJob::new(&rs, &st).unwrap().expect("a phased estimator");
    let range = job.phases().train.clone();
    let n = (scene.film.width * scene.film.height) as usize;
    let surrogate = job.needs_surrogate().then(|| vec![0.5; n]);
    let t = train_on_threads(&job, tile, &range, surrogate.as_deref(), threads);
    (t, range.len() as u32)
}

/// A training tile's table encoding and its film's sums as bit patterns.
fn tile_bits(t: &render::integrator::cv::TrainTile) -> (Vec<u8>, Vec<u64>) {
    let film = t
        .out
        .film
        .pixels
        .iter()
        .flat_map(|q| q.sum.map(f64::to_bits))
        .collect();
    (t.cells.encode(), film)
}

/// A training tile probes its own fits after `TRAIN_PROBE_SPP` samples per pixel: on the
/// Cornell box (fits that only separate the techniques) it stops recording and traces the
/// rest as `path`, reporting only the probe's samples, while its film still holds every
/// training sample; on colour-lamp (useful fits) it records everything, with the same bits
/// as a job that sets no minimum. Both are independent of the thread count.
#[test]
fn a_training_tile_whose_own_fits_cannot_pay_records_only_its_probe() {
    use estimators::table::AccumulatorTable;
    use render::TileRect;
    use render::integrator::cv::{TRAIN_PROBE_SPP, TrainTile};

    let tile = TileRect {
        x0: 0,
        y0: 0,
        width: 64,
        height: 64,
    };
    let train = |rel: &str, o: CmsOptions, threads: usize| {
        train_tile_of(&load(rel, 64, 64), Estimator::Cms(o), tile, threads)
    };
    let samples = |t: &TrainTile| match &t.cells {
        AccumulatorTable::Moments(m, _) => m.values().map(|a| a.samples()).sum::<u64>(),
        AccumulatorTable::Mean(..) => panic!("moments"),
    };
    let bits = tile_bits;
    // The power base: on the Cornell box its fits only separate the techniques (with the
    // balance base they remove variance and the tile keeps recording).
    let power = CmsOptions {
        base: render::integrator::cv::CvBase::Mis,
        ..CmsOptions::default()
    };
    let always = |o: &CmsOptions| CmsOptions {
        min_image_gain: None,
        min_fit_gain: None,
        ..*o
    };
    // The Cornell box: stopped after the probe.
    let cbox = "scenes/cornell-box/scene.json";
    let (stopped, spp) = train(cbox, power, 1);
    let (full, _) = train(cbox, always(&power), 1);
    assert!(stopped.stopped && !full.stopped);
    assert!(
        stopped
            .out
            .film
            .pixels
            .iter()
            .all(|p| p.count == u64::from(spp))
    );
    let (a, b) = (samples(&stopped), samples(&full));
    let share = a as f64 / b as f64;
    let want = f64::from(TRAIN_PROBE_SPP) / f64::from(spp);
    assert!(
        a > 0 && (share - want).abs() < 0.25 * want,
        "{a} of {b} samples recorded, want a share of {want}"
    );
    assert!(bits(&train(cbox, power, 3).0) == bits(&stopped));
    // Colour-lamp: everything recorded, as without a minimum.
    let lamp = "scenes/colour-lamp/scene.json";
    let (kept, _) = train(lamp, CmsOptions::default(), 1);
    assert!(!kept.stopped);
    assert!(bits(&kept) == bits(&train(lamp, always(&CmsOptions::default()), 1).0));
    assert!(bits(&kept) == bits(&train(lamp, CmsOptions::default(), 3).0));
}

/// An `optimal_mis` training tile records all the training samples of its split-half check's
/// pixels (one in 8) first and decides on them: a tile the check drops (veach-mis) traces its
/// other pixels' training samples as `path`, without records, so those pixels hold every
/// training sample and agree with the recorded run up to rounding while the checked pixels
/// keep its bits and no cell is reported; a tile the check keeps records the other pixels in
/// the same passes, with the bits of a job without the check. Both independent of the thread
/// count.
#[test]
fn an_optimal_mis_tile_records_its_checked_pixels_first() {
    use estimators::table::AccumulatorTable;
    use render::TileRect;
    use render::integrator::cv::TrainTile;

    let (w, h) = (64u32, 48u32);
    let tile = TileRect {
        x0: 0,
        y0: 0,
        width: w,
        height: h,
    };
    let veach = load("scenes/veach-mis/scene.json", w, h);
    let train = |o: OptimalMisOptions, threads: usize| {
        train_tile_of(&veach, Estimator::OptimalMis(o), tile, threads)
    };
    let bits = tile_bits;
    let cells = |t: &TrainTile| match &t.cells {
        AccumulatorTable::Moments(m, _) => m.len(),
        AccumulatorTable::Mean(..) => panic!("moments"),
    };
    let off = OptimalMisOptions {
        min_split_gain: None,
        ..OptimalMisOptions::default()
    };
    let (recorded, spp) = train(off, 1);
    assert!(!recorded.dropped && cells(&recorded) > 0);

    // Kept: the check runs and its minimum keeps every tile.
    let keep = OptimalMisOptions {
        min_split_gain: Some(f64::MIN),
        ..OptimalMisOptions::default()
    };
    for threads in [1, 3] {
        let (kept, _) = train(keep, threads);
        assert!(!kept.dropped);
        assert!(bits(&kept) == bits(&recorded), "{threads} threads");
    }

    // Dropped: the default minimum on veach-mis.
    let (dropped, _) = train(OptimalMisOptions::default(), 1);
    assert!(dropped.dropped && cells(&dropped) == 0);
    assert!(bits(&train(OptimalMisOptions::default(), 3).0) == bits(&dropped));
    let (mut checked, mut other) = (0, 0);
    for (i, (p, q)) in dropped
        .out
        .film
        .pixels
        .iter()
        .zip(&recorded.out.film.pixels)
        .enumerate()
    {
        let (x, y) = (i as u32 % w, i as u32 / w);
        assert_eq!(p.count, u64::from(spp));
        if (x + 3 * y).is_multiple_of(8) {
            checked += 1;
            assert!(
                p.sum.map(f64::to_bits) == q.sum.map(f64::to_bits),
                "pixel {x},{y}"
            );
        } else {
            other += 1;
            for c in 0..3 {
                let d = (p.sum[c] - q.sum[c]).abs();
                assert!(
                    d <= 1e-5 * q.sum[c].abs().max(1e-3),
                    "pixel {x},{y}: {p:?} vs {q:?}"
                );
            }
        }
    }
    assert!(checked > 0 && other > 6 * checked);
}
