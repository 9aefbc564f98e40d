//! Renderer throughput on the shared Mitsuba scenes: samples/s and rays/s at 256×256,
//! `max_depth` 5, with all cores.
//!
//! `cargo bench -p render --bench render` (env: `RENDER_BENCH_SPP`, default 16;
//! `RENDER_BENCH_SCENES`, default `cbox,manylights-4`; `SCENES_MITSUBA`, default
//! `/work/shared/scenes-mitsuba`).

use std::path::PathBuf;

use render::{RenderOptions, RenderScene, RenderSettings, render_image};

#[path = "../tests/cpu_time/mod.rs"]
mod cpu_time;
use cpu_time::cpu_seconds;

fn main() {
    let root = PathBuf::from(std::env::var("SCENES_MITSUBA").unwrap_or_else(|_| {
        concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../../../shared/scenes-mitsuba"
        )
        .into()
    }));
    let spp: u32 = std::env::var("RENDER_BENCH_SPP")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(16);
    let names = std::env::var("RENDER_BENCH_SCENES").unwrap_or_else(|_| "cbox,manylights-4".into());
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    for name in names.split(',') {
        let path = root.join(name).join("scene.xml");
        let loaded = match scene::load_file(&path) {
            Ok(l) => l,
            Err(e) => {
                eprintln!("skipping {name}: {e}");
                continue;
            }
        };
        let mut s = loaded.scene;
        s.film = scene::Film {
            width: 256,
            height: 256,
        };
        let st = RenderSettings {
            spp,
            seed: 1,
            max_depth: 5,
            rr_depth: 6,
            ..RenderSettings::from_scene(&s)
        };
        let rs = RenderScene::new(&s, &st).expect("prepare scene");
        let cpu0 = cpu_seconds();
        let (_, stats) = render_image(
            &rs,
            &st,
            &RenderOptions {
                tile_size: 32,
                threads,
            },
            &|_, _| {},
        )
        .expect("render");
        let cpu = cpu_seconds() - cpu0;
        println!(
            "{name}: 256x256 @ {spp} spp, depth 5, {threads} threads: wall {:.3} s, {:.3} Msamples/s, \
             {:.3} Mrays/s; CPU {cpu:.3} s, {:.3} Msamples/CPU-s, {:.3} Mrays/CPU-s",
            stats.seconds,
            stats.samples as f64 / stats.seconds / 1e6,
            stats.rays as f64 / stats.seconds / 1e6,
            stats.samples as f64 / cpu / 1e6,
            stats.rays as f64 / cpu / 1e6,
        );
    }
}
