//! Unbiasedness of the CV estimators: the mean over seeds of each estimator's image (whole
//! image and quadrants, per channel) matches a high-spp `path` reference within five
//! standard errors (errors of both sides combined).

mod cv_support;

use cv_support::{load, mean_se, region_mean, render, render_with};
use render::integrator::cms::CmsOptions;
use render::integrator::optimal_mis::OptimalMisOptions;
use render::integrator::per_light_cv::PerLightCvOptions;
use render::sampler::SamplerKind;
use render::{Estimator, RenderOptions};

const W: u32 = 24;
const H: u32 = 24;

/// Regions: whole image and the four quadrants.
fn regions() -> Vec<(u32, u32, u32, u32)> {
    vec![
        (0, 0, W, H),
        (0, 0, W / 2, H / 2),
        (W / 2, 0, W, H / 2),
        (0, H / 2, W / 2, H),
        (W / 2, H / 2, W, H),
    ]
}

/// Checks the region means of `seeds` renders against a `path` reference; returns the
/// smallest number of cells solved (with coefficients) over the renders.
fn check(scene_rel: &str, estimator: Estimator, seeds: u64, spp: u32, ref_spp: u32) -> u64 {
    check_sampled(
        scene_rel,
        estimator,
        seeds,
        spp,
        ref_spp,
        SamplerKind::Sobol,
    )
}

/// [`check`] with the estimator's renders drawn by `sampler` (the reference: Sobol `path`).
fn check_sampled(
    scene_rel: &str,
    estimator: Estimator,
    seeds: u64,
    spp: u32,
    ref_spp: u32,
    sampler: SamplerKind,
) -> u64 {
    let s = load(scene_rel, W, H);
    let depth = 3;
    let opts = RenderOptions::default();
    let (reference, _) = render(&s, Estimator::Path, ref_spp, 999, Some(depth), opts);
    let mut per_seed: Vec<Vec<[f64; 3]>> = Vec::new();
    let mut solved = u64::MAX;
    for seed in 0..seeds {
        let st = render::RenderSettings {
            spp,
            seed,
            estimator,
            sampler,
            max_depth: depth,
            ..render::RenderSettings::from_scene(&s)
        };
        let (f, report) = render_with(&s, &st, opts);
        assert!(cv_support::all_finite(&f));
        assert!(report.render_spp > 0, "{report:?}");
        solved = solved.min(report.cells_solved);
        per_seed.push(
            regions()
                .iter()
                .map(|&(a, b, c, d)| region_mean(&f, a, b, c, d))
                .collect(),
        );
    }
    for (ri, &(x0, y0, x1, y1)) in regions().iter().enumerate() {
        let r = region_mean(&reference, x0, y0, x1, y1);
        // Standard error of the reference region mean from its per-pixel variances.
        let mut rv = [0.0f64; 3];
        for y in y0..y1 {
            for x in x0..x1 {
                let v = reference.pixel(x, y).variance_of_mean();
                for c in 0..3 {
                    rv[c] += v[c];
                }
            }
        }
        let n = f64::from((x1 - x0) * (y1 - y0));
        for c in 0..3 {
            let xs: Vec<f64> = per_seed.iter().map(|m| m[ri][c]).collect();
            let (m, se) = mean_se(&xs);
            let se_ref = rv[c].sqrt() / n;
            let tol = 5.0 * (se * se + se_ref * se_ref).sqrt() + 1e-6 * r[c].abs();
            println!(
                "{scene_rel} {:?} region {ri} ch {c}: cv {m:.5} ± {se:.5}, path {:.5} ± {se_ref:.5}",
                std::mem::discriminant(&estimator),
                r[c]
            );
            assert!(
                (m - r[c]).abs() <= tol,
                "{scene_rel} region {ri} channel {c}: {m} vs {} (tol {tol})",
                r[c]
            );
        }
    }
    solved
}

fn cms_coarse() -> Estimator {
    Estimator::Cms(CmsOptions {
        training_spp: 8,
        grid_resolution: Some([4, 4, 4]),
        min_samples: 8,
        // The fits applied whatever their predicted gain: this tests their mechanics.
        min_image_gain: None,
        min_fit_gain: None,
        ..CmsOptions::default()
    })
}

#[test]
fn cms_is_unbiased_on_colour_lamp() {
    assert!(check("scenes/colour-lamp/scene.json", cms_coarse(), 16, 16, 1024) > 0);
}

/// The independent sampler (the papers' baseline) with the CV at every vertex, the camera
/// hit included: `path` and `cms` stay unbiased against the Sobol reference.
#[test]
fn path_and_cms_at_every_vertex_are_unbiased_with_the_independent_sampler() {
    let every_vertex = match cms_coarse() {
        Estimator::Cms(o) => Estimator::Cms(CmsOptions {
            min_depth: Some(0),
            ..o
        }),
        _ => unreachable!(),
    };
    let scene = "scenes/colour-lamp/scene.json";
    check_sampled(
        scene,
        Estimator::Path,
        16,
        16,
        1024,
        SamplerKind::Independent,
    );
    assert!(check_sampled(scene, every_vertex, 16, 16, 1024, SamplerKind::Independent) > 0);
}

#[test]
fn cms_is_unbiased_on_veach_mis() {
    assert!(check("scenes/veach-mis/scene.json", cms_coarse(), 16, 16, 1024) > 0);
}

/// The unshrunk fit on the balance base (the paper's estimator [Hua eq. 17]).
#[test]
fn cms_balance_base_without_shrinkage_is_unbiased_on_colour_lamp() {
    let e = Estimator::Cms(CmsOptions {
        training_spp: 8,
        grid_resolution: Some([4, 4, 4]),
        min_samples: 8,
        ridge: Some(1e-6),
        base: render::integrator::cv::CvBase::Balance,
        // The fits applied whatever their predicted gain: this tests their mechanics.
        min_image_gain: None,
        min_fit_gain: None,
        ..CmsOptions::default()
    });
    assert!(check("scenes/colour-lamp/scene.json", e, 16, 16, 1024) > 0);
}

#[test]
fn cms_absolute_mono_is_unbiased_on_cornell_box() {
    let e = Estimator::Cms(CmsOptions {
        relative: false,
        color: render::integrator::cv::CvColor::Mono,
        training_spp: 8,
        // The fits applied whatever their predicted gain: this tests their mechanics.
        min_image_gain: None,
        min_fit_gain: None,
        ..CmsOptions::default()
    });
    assert!(check("scenes/cornell-box/scene.json", e, 16, 16, 1024) > 0);
}

#[test]
fn cms_is_unbiased_on_envmap() {
    assert!(check("scenes/envmap/scene.json", cms_coarse(), 16, 16, 1024) > 0);
}

/// With the surrogate weights and the per-cell rule, the table switches off so that the
/// cells that keep their means are applied whatever the predicted gain (checked: some do).
#[test]
fn per_light_cv_is_unbiased_on_many_lights() {
    let e = Estimator::PerLightCv(PerLightCvOptions {
        training_spp: 8,
        grid_resolution: Some([4, 4, 4]),
        min_image_gain: None,
        min_fit_gain: None,
        min_held_out_share: None,
        ..PerLightCvOptions::default()
    });
    let solved = check("scenes/many-lights/scene.json", e, 16, 16, 1024);
    assert!(solved > 0, "no cell kept its means");
}

#[test]
fn optimal_mis_is_unbiased_on_veach_mis() {
    let e = Estimator::OptimalMis(OptimalMisOptions {
        training_spp: 8,
        min_samples: 8,
        // The fits themselves (the split-half check would drop them on veach-mis).
        min_split_gain: None,
        ..OptimalMisOptions::default()
    });
    assert!(check("scenes/veach-mis/scene.json", e, 16, 16, 1024) > 0);
}

/// With `α ≡ 0` the CV bookkeeping must reproduce the path tracer with the job's MIS
/// heuristic sample for sample (same sampler dimensions; only summation order differs),
/// whatever the base: a vertex in a cell without coefficients is `path`'s, and training
/// samples are `path`'s (the balance base only enters where a cell has coefficients).
/// `α ≡ 0` both without a training phase and with every
/// trained cell falling back (`min_samples` unreachable), which exercises the surrogate,
/// training and render phases.
#[test]
fn cms_with_zero_alpha_equals_path_whatever_the_base() {
    use render::MisHeuristic;
    use render::integrator::cv::CvBase;
    for rel in [
        "scenes/veach-mis/scene.json",
        "scenes/many-lights/scene.json",
        "scenes/envmap/scene.json",
    ] {
        let s = load(rel, 16, 12);
        let opts = RenderOptions::default();
        // Uncontrolled vertices are `path`'s (the job's heuristic) whatever the base.
        for (base, mis) in [
            (CvBase::Mis, MisHeuristic::Power),
            (CvBase::Balance, MisHeuristic::Power),
        ] {
            for (training_spp, min_samples, spp) in [(0, 16, 4), (8, u64::MAX, 12)] {
                let e = Estimator::Cms(CmsOptions {
                    training_spp,
                    min_samples,
                    base,
                    // The fits applied whatever their predicted gain: this tests their mechanics.
                    min_image_gain: None,
                    min_fit_gain: None,
                    ..CmsOptions::default()
                });
                let (cv, report) = render(&s, e, spp, 9, None, opts);
                assert_eq!(report.cells_solved, 0, "{report:?}");
                let st = render::RenderSettings {
                    spp,
                    seed: 9,
                    mis,
                    ..render::RenderSettings::from_scene(&s)
                };
                let rs = render::RenderScene::new(&s, &st).unwrap();
                let (p, _) = render::render_image(&rs, &st, &opts, &|_, _| {}).unwrap();
                for (a, b) in cv.pixels.iter().zip(&p.pixels) {
                    assert_eq!(a.count, b.count);
                    for c in 0..3 {
                        let (x, y) = (a.sum[c], b.sum[c]);
                        assert!(
                            (x - y).abs() <= 1e-4 * (1.0 + x.abs().max(y.abs())),
                            "{rel} {base:?}: {x} vs {y}"
                        );
                    }
                }
            }
        }
    }
}
