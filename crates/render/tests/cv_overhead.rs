//! Overhead harness (ignored; prints only, no assertions): CPU time of each `cms` phase on
//! one thread against `path` over the same sample ranges, best of `CV_REPEAT` runs, all
//! measured in the same process so that the ratios share the machine's load.
//!
//! ```text
//! CV_MEASURE="many-lights:5,veach-mis:5" CV_SPP=64 CV_SCALE=2 \
//!   cargo test --release -p render --test cv_overhead -- --ignored --nocapture
//! ```
//! `CV_EST` (default `cms`), `CV_REPEAT` (default 3), `CV_SAMPLER` (`sobol` or `independent`;
//! default: the scene's).

mod cv_support;

use std::ops::Range;

use estimators::surrogate::surrogate_image;
use render::integrator::cv::{CvJob, TRAIN_TILE, film_moments};
use render::tile::render_tile_counted;
use render::{Estimator, Film, RenderScene, RenderSettings, TileRect};

mod cpu_time;
use cpu_time::cpu_seconds;

fn env_or(key: &str, default: &str) -> String {
    std::env::var(key).unwrap_or_else(|_| default.to_string())
}

/// Best (smallest) CPU seconds of `n` runs of `f`.
fn best<T>(n: u32, mut f: impl FnMut() -> T) -> (f64, T) {
    let mut best = f64::INFINITY;
    let mut out = None;
    for _ in 0..n.max(1) {
        let c0 = cpu_seconds();
        let r = f();
        best = best.min(cpu_seconds() - c0);
        out = Some(r);
    }
    (best, out.expect("ran"))
}

fn path_range(rs: &RenderScene, st: &RenderSettings, tiles: &[TileRect], r: Range<u32>) -> u64 {
    let mut rays = 0;
    for &t in tiles {
        rays += render_tile_counted(rs, st, t, r.clone()).unwrap().1;
    }
    rays
}

#[test]
#[ignore = "measurement harness, prints only"]
fn measure_phase_overhead() {
    // One worker thread for the phases' bands. On the global pool (every core) two busy
    // threads ran the CV phases while `path`'s loop here runs on one, and on this 2-vCPU VM
    // two busy threads each run slower than one: the CPU seconds overstated the CV's
    // overhead (colour-lamp d5, 128², 128 spp, independent: +20.1 % there, +11.6 % here).
    rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .expect("a one-thread pool")
        .install(measure);
}

fn measure() {
    let scenes = env_or("CV_MEASURE", "many-lights:5,veach-mis:5");
    let spec = env_or("CV_EST", "cms");
    let spp: u32 = env_or("CV_SPP", "64").parse().unwrap();
    let scale: u32 = env_or("CV_SCALE", "2").parse().unwrap();
    let repeat: u32 = env_or("CV_REPEAT", "3").parse().unwrap();
    for sd in scenes.split(',') {
        let (name, d) = sd.split_once(':').expect("scene:depth");
        let depth: i32 = d.parse().unwrap();
        let s = cv_support::load_scaled(&format!("scenes/{name}/scene.json"), scale);
        let mut obj = serde_json::Map::new();
        let mut parts = spec.split(':');
        obj.insert("kind".into(), parts.next().unwrap().into());
        for kv in parts {
            let (k, v) = kv.split_once('=').expect("key=value");
            let v: serde_json::Value = serde_json::from_str(v).unwrap_or_else(|_| v.into());
            obj.insert(k.into(), v);
        }
        let est: Estimator = serde_json::from_value(serde_json::Value::Object(obj)).unwrap();
        let st = RenderSettings {
            spp,
            seed: 7,
            estimator: est,
            max_depth: depth,
            ..RenderSettings::from_scene(&s)
        };
        let st = match std::env::var("CV_SAMPLER") {
            Ok(k) => RenderSettings {
                sampler: serde_json::from_value(k.into()).expect("CV_SAMPLER: sobol | independent"),
                ..st
            },
            Err(_) => st,
        };
        let rs = RenderScene::new(&s, &st).unwrap();
        let pst = RenderSettings {
            estimator: Estimator::Path,
            ..st
        };
        let job = CvJob::new(&rs, &st).unwrap().expect("a phased estimator");
        let ph = job.phases().clone();
        let tiles = TileRect::grid(rs.width, rs.height, 32);
        let train_tiles = TileRect::grid(rs.width, rs.height, TRAIN_TILE);

        // `CV_ONLY=path|cms` runs one side only, `render` / `path-render` the render phase and
        // `path` over its samples (for `perf record`).
        let only = env_or("CV_ONLY", "");
        let run_path = only.is_empty() || only == "path";
        let run_cv = only != "path";
        if only == "path-render" {
            let t = best(repeat, || path_range(&rs, &pst, &tiles, ph.render.clone())).0;
            println!("{name} d{depth} path over the render range {t:.3} s");
            continue;
        }
        let (mut t_path_all, mut t_path_train, mut t_path_render) = (f64::NAN, f64::NAN, f64::NAN);
        let (mut r_path_train, mut r_path_render) = (0, 0);
        if run_path {
            t_path_all = best(repeat, || path_range(&rs, &pst, &tiles, 0..spp)).0;
            (t_path_train, r_path_train) = best(repeat, || {
                path_range(&rs, &pst, &train_tiles, ph.train.clone())
            });
            (t_path_render, r_path_render) =
                best(repeat, || path_range(&rs, &pst, &tiles, ph.render.clone()));
        }
        if !run_cv {
            println!("{name} d{depth} path {t_path_all:.3} s");
            continue;
        }

        // The render-phase profile repeats that phase only.
        let pre = if only == "render" { 1 } else { repeat };
        let (t_sur, sfilm) = best(pre, || {
            let mut f = Film::new(rs.width, rs.height);
            for &t in &tiles {
                f.merge(&job.surrogate_tile(t, ph.surrogate.clone()).film);
            }
            f
        });
        let (t_den, sur) = best(pre, || {
            job.needs_surrogate().then(|| {
                surrogate_image(&film_moments(&sfilm), rs.width as usize, rs.height as usize)
            })
        });
        let (t_train, outs) = best(pre, || {
            train_tiles
                .iter()
                .map(|&t| job.train_tile(t, ph.train.clone(), sur.as_deref()).unwrap())
                .collect::<Vec<_>>()
        });
        let (t_solve, table) = best(pre, || {
            let mut merged = None;
            for o in &outs {
                match &mut merged {
                    None => merged = Some(o.cells.clone()),
                    Some(m) => m.merge(&o.cells).unwrap(),
                }
            }
            let solved = merged.unwrap().solve(&job.solve_policy(), 1);
            job.coefficient_table(&solved.coefficients).unwrap()
        });
        if only == "render" {
            // The render phase alone (for `perf record`), after the same training.
            let (t, _) = best(repeat, || {
                tiles
                    .iter()
                    .map(|&t| job.render_tile(t, ph.render.clone(), &table).out.rays)
                    .sum::<u64>()
            });
            println!("{name} d{depth} render phase {t:.3} s");
            continue;
        }
        let (t_render, r_render) = best(repeat, || {
            tiles
                .iter()
                .map(|&t| job.render_tile(t, ph.render.clone(), &table).out.rays)
                .sum::<u64>()
        });
        let r_train: u64 = outs.iter().map(|o| o.out.rays).sum();
        let n_tr = ph.train.len().max(1) as f64;
        let n_re = ph.render.len().max(1) as f64;
        let total = t_sur + t_den + t_train + t_solve + t_render;
        println!(
            "{name} d{depth} {spec} {}x{} {spp} spp (1 thread, best of {repeat}): path {t_path_all:.3} s, \
             cms {total:.3} s ({:+.1} %) = surrogate {t_sur:.3} + denoise {t_den:.3} + train {t_train:.3} \
             + solve {t_solve:.3} + render {t_render:.3}; per sample vs path: train {:+.1} %, render {:+.1} %; rays vs path: train {:+.2} %, render {:+.2} %",
            rs.width,
            rs.height,
            100.0 * (total / t_path_all - 1.0),
            100.0 * (t_train / t_path_train - 1.0),
            100.0 * (t_render / t_path_render - 1.0),
            100.0 * (r_train as f64 / r_path_train as f64 - 1.0),
            100.0 * (r_render as f64 / r_path_render as f64 - 1.0),
        );
        let _ = (n_tr, n_re);
    }
}
