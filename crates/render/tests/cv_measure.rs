//! Measurement harness (ignored; no assertions): equal-spp relMSE ratios of the CV
//! estimators over `path` and their CPU-time ratios on the bench scenes at reduced
//! resolution, to try estimator variants quickly without the `cvfarm` binary. Equal-time
//! speedup ≈ equal-spp ratio / time ratio (both from this one run).
//!
//! ```text
//! CV_MEASURE="colour-lamp:2,veach-mis:5" CV_EST="cms,cms:relative=false" \
//!   cargo test --release -p render --test cv_measure -- --ignored --nocapture
//! ```
//! `CV_SPP` (default 128), `CV_SEEDS` (default 2), `CV_REF_SPP` (default 1024),
//! `CV_SCALE` (film divisor, default 2). A scene is a name under `scenes/` or a path (with a
//! `/`) relative to the repository root.

mod cv_support;

use std::time::Instant;

use cv_support::{rel_mse, render};
use render::integrator::cms::CmsOptions;
use render::integrator::optimal_mis::OptimalMisOptions;
use render::integrator::per_light_cv::PerLightCvOptions;
use render::{Estimator, RenderOptions};

mod cpu_time;
use cpu_time::cpu_seconds;

fn env_or(key: &str, default: &str) -> String {
    std::env::var(key).unwrap_or_else(|_| default.to_string())
}

/// `kind[:key=value…]` → estimator (options through serde, as the CLI does).
fn parse_estimator(spec: &str) -> Estimator {
    let mut parts = spec.split(':');
    let kind = parts.next().unwrap_or("path");
    let mut obj = serde_json::Map::new();
    obj.insert("kind".into(), kind.into());
    for kv in parts {
        let (k, v) = kv.split_once('=').expect("key=value");
        let v: serde_json::Value = serde_json::from_str(v).unwrap_or_else(|_| v.into());
        obj.insert(k.into(), v);
    }
    let _ = (
        CmsOptions::default(),
        PerLightCvOptions::default(),
        OptimalMisOptions::default(),
    );
    serde_json::from_value(serde_json::Value::Object(obj)).expect("estimator spec")
}

#[test]
#[ignore = "measurement harness, prints only"]
fn measure_equal_spp_ratios() {
    let scenes = env_or(
        "CV_MEASURE",
        "colour-lamp:2,colour-lamp:5,many-lights:2,many-lights:5,veach-mis:2,veach-mis:5,envmap:2,envmap:5",
    );
    let ests: Vec<String> = env_or("CV_EST", "cms")
        .split(',')
        .map(String::from)
        .collect();
    let spp: u32 = env_or("CV_SPP", "128").parse().unwrap();
    let seeds: u64 = env_or("CV_SEEDS", "2").parse().unwrap();
    let ref_spp: u32 = env_or("CV_REF_SPP", "1024").parse().unwrap();
    let scale: u32 = env_or("CV_SCALE", "2").parse().unwrap();
    let opts = RenderOptions::default();
    for sd in scenes.split(',') {
        let (name, d) = sd.split_once(':').expect("scene:depth");
        let depth: i32 = d.parse().unwrap();
        // A bare name is one of `scenes/`; anything with a `/` is a scene file relative to
        // the repository root (e.g. `../shared/scenes-mitsuba/manylights-4/scene.xml`).
        let rel = if name.contains('/') {
            name.to_string()
        } else {
            format!("scenes/{name}/scene.json")
        };
        let s = cv_support::load_scaled(&rel, scale);
        let (reference, _) = render(&s, Estimator::Path, ref_spp, 4242, Some(depth), opts);
        let run = |e: Estimator| {
            let (mut err, mut cpu, mut wall) = (0.0, 0.0, 0.0);
            let mut rep = None;
            for seed in 0..seeds {
                let (c0, w0) = (cpu_seconds(), Instant::now());
                let (f, r) = render(&s, e, spp, seed, Some(depth), opts);
                cpu += cpu_seconds() - c0;
                wall += w0.elapsed().as_secs_f64();
                err += rel_mse(&f, &reference);
                rep.get_or_insert(r);
            }
            (err, cpu, wall, rep.unwrap())
        };
        let (e_path, c_path, w_path, _) = run(Estimator::Path);
        for spec in &ests {
            let (e, c, w, r) = run(parse_estimator(spec));
            let q = e_path / e;
            let t = c / c_path;
            println!(
                "{name} d{depth} {spec}: equal-spp {q:.3}  cpu-time ratio {t:.3} (wall {:.3})  equal-time≈{:.3}  [relMSE path {:.3e} cv {:.3e}; solved {} fb {:?}; phases {:?}]",
                w / w_path,
                q / t,
                e_path / seeds as f64,
                e / seeds as f64,
                r.cells_solved,
                r.cells_fallback,
                r.phases
            );
        }
    }
}
