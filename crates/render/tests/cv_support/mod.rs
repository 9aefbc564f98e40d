//! Shared helpers of the `cv_*` tests: scene loading at test resolution, renders, statistics.
#![allow(dead_code)]

use std::path::{Path, PathBuf};

use render::integrator::cv::{EstimatorReport, render_estimator_image};
use render::{Estimator, Film, RenderOptions, RenderScene, RenderSettings};

/// Repository root.
pub fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// Loads `scenes/<name>/scene.json` (or any path relative to the repo root) at `w × h`.
pub fn load(rel: &str, w: u32, h: u32) -> scene::Scene {
    let mut s = scene::load_file(&root().join(rel))
        .expect("scene loads")
        .scene;
    s.film.width = w;
    s.film.height = h;
    s
}

/// Loads the scene at `rel` with its film divided by `scale` in both axes.
pub fn load_scaled(rel: &str, scale: u32) -> scene::Scene {
    let mut s = scene::load_file(&root().join(rel))
        .expect("scene loads")
        .scene;
    s.film.width /= scale;
    s.film.height /= scale;
    s
}

/// Renders `scene` with `estimator`, `spp`, `seed` (and `max_depth` if given).
pub fn render(
    s: &scene::Scene,
    estimator: Estimator,
    spp: u32,
    seed: u64,
    max_depth: Option<i32>,
    opts: RenderOptions,
) -> (Film, EstimatorReport) {
    let st = RenderSettings {
        spp,
        seed,
        estimator,
        max_depth: max_depth.unwrap_or(s.integrator.max_depth),
        ..RenderSettings::from_scene(s)
    };
    render_with(s, &st, opts)
}

/// [`render`] with the settings `st` (e.g. another sampler).
pub fn render_with(
    s: &scene::Scene,
    st: &RenderSettings,
    opts: RenderOptions,
) -> (Film, EstimatorReport) {
    let rs = RenderScene::new(s, st).expect("scene prepares");
    let (film, _, report) = render_estimator_image(&rs, st, &opts, &|_, _| {}).expect("renders");
    (film, report)
}

/// Mean of the pixels in `[x0, x1) × [y0, y1)` per channel.
pub fn region_mean(f: &Film, x0: u32, y0: u32, x1: u32, y1: u32) -> [f64; 3] {
    let mut s = [0.0; 3];
    for y in y0..y1 {
        for x in x0..x1 {
            let m = f.pixel(x, y).mean();
            for c in 0..3 {
                s[c] += m[c];
            }
        }
    }
    let n = f64::from((x1 - x0) * (y1 - y0));
    s.map(|v| v / n)
}

/// relMSE of `f` against `reference` (DESIGN §6).
pub fn rel_mse(f: &Film, reference: &Film) -> f64 {
    let a: Vec<f32> = f.mean_image().into_iter().flatten().collect();
    let b: Vec<f32> = reference.mean_image().into_iter().flatten().collect();
    estimators::metrics::compare(&a, &b).rel_mse
}

/// Every pixel sum finite.
pub fn all_finite(f: &Film) -> bool {
    f.pixels.iter().all(|p| p.sum.iter().all(|v| v.is_finite()))
}

/// Sample mean and standard error of the mean.
pub fn mean_se(xs: &[f64]) -> (f64, f64) {
    let n = xs.len() as f64;
    let m = xs.iter().sum::<f64>() / n;
    let v = xs.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (n - 1.0);
    (m, (v / n).sqrt())
}
