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

/// A bare name is one of `scenes/`; anything with a `/` is a scene file relative to the
/// repository root (e.g. `../shared/scenes-mitsuba/manylights-4/scene.xml`).
fn scene_file(name: &str) -> String {
    if name.contains('/') {
        name.to_string()
    } else {
        format!("scenes/{name}/scene.json")
    }
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
        let rel = scene_file(name);
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

/// `ocv`'s pilot choice (module docs of `render::integrator::ocv`, "Choosing `path` or the
/// gather") per scene, set against the seed-to-seed error of `path` and of `ocv` with the
/// gather everywhere at the same spp (`CV_SEEDS` seeds, CPU time), i.e. what the pilot
/// predicts against what it should.
///
/// ```text
/// OCV_PILOT="checkers:2,cornell-box:5" CV_SPP=64 CV_SCALE=1 \
///   cargo test --release -p render --test cv_measure -- --ignored --nocapture ocv_pilot
/// ```
#[test]
#[ignore = "measurement harness, prints only"]
fn ocv_pilot_choices() {
    use render::integrator::ocv;
    let scenes = env_or(
        "OCV_PILOT",
        "checkers:2,colour-lamp:5,cornell-box:5,veach-mis:5",
    );
    let scale: u32 = env_or("CV_SCALE", "1").parse().unwrap();
    let spp: u32 = env_or("CV_SPP", "64").parse().unwrap();
    let seeds: u64 = env_or("CV_SEEDS", "4").parse().unwrap();
    let est = parse_estimator(&env_or("CV_EST", "ocv"));
    let render::Estimator::Ocv(o) = est else {
        panic!("CV_EST must be an ocv spec")
    };
    for sd in scenes.split(',') {
        let (name, d) = sd.split_once(':').expect("scene:depth");
        let rel = scene_file(name);
        let s = cv_support::load_scaled(&rel, scale);
        let depth: i32 = d.parse().unwrap();
        let st = render::RenderSettings {
            spp,
            max_depth: depth,
            estimator: est,
            ..render::RenderSettings::from_scene(&s)
        };
        let rs = render::RenderScene::new(&s, &st).expect("scene prepares");
        let c0 = cpu_seconds();
        let choice = ocv::choose(&rs, &st, &o);
        let pilot_cpu = cpu_seconds() - c0;
        // The pilot's spread over job seeds (`CV_PILOT_SEEDS`, default 0 = the one above).
        let pilot_seeds: u64 = env_or("CV_PILOT_SEEDS", "0").parse().unwrap();
        if pilot_seeds > 0 {
            let spread: Vec<String> = (0..pilot_seeds)
                .map(|seed| {
                    let c = ocv::choose(&rs, &render::RenderSettings { seed, ..st }, &o);
                    format!(
                        "{:.2}/{:.2}{}",
                        c.speedup,
                        c.speedup_low,
                        if c.use_ocv { "*" } else { "" }
                    )
                })
                .collect();
            println!(
                "{name} d{d} pilot (prediction/less one s.e.) over seeds (* = gather): {}",
                spread.join(" ")
            );
        }
        let every = render::Estimator::Ocv(ocv::OcvOptions {
            min_speedup: None,
            ..o
        });
        let error = |e: render::Estimator| {
            let (mut films, mut cpu) = (Vec::new(), 0.0);
            for seed in 0..seeds {
                let c0 = cpu_seconds();
                films.push(render(&s, e, spp, seed, Some(depth), RenderOptions::default()).0);
                cpu += cpu_seconds() - c0;
            }
            let images: Vec<Vec<f32>> = films
                .iter()
                .map(|f| f.mean_image().into_iter().flatten().collect())
                .collect();
            let views: Vec<&[f32]> = images.iter().map(Vec::as_slice).collect();
            let err = estimators::metrics::seed_variance_error(&views, None)
                .expect("two or more seeds")
                .rel_mse;
            (err, cpu)
        };
        let (ep, cp) = error(render::Estimator::Path);
        let (eo, co) = error(every);
        println!(
            "{name} d{d} {spp} spp: pilot {:.2}× (less one s.e. {:.2}×, ocv: {}; pilot CPU {:.1} % of path's render); \
             gather everywhere: equal-spp {:.2}×, CPU ×{:.2}, equal-time {:.2}×",
            choice.speedup,
            choice.speedup_low,
            choice.use_ocv,
            100.0 * pilot_cpu / (cp / seeds as f64),
            ep / eo,
            co / cp,
            ep / eo * cp / co
        );
    }
}
