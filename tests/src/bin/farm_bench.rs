//! Farm benchmarks (numbers, not tests; DESIGN §8):
//!
//! 1. **Queue throughput**: one coordinator, `--sim-workers` simulated workers that lease a
//!    task and upload a valid (all-zero) frame as fast as they can; reports leases/s
//!    (lease + upload round trips) and the finishing time (assembly of every block).
//! 2. **Farm overhead**: the same job rendered in-process (`render_image`, 2 threads) and by
//!    a farm of 2 real workers × 1 slot on loopback; reports both wall times and the overhead.
//!
//! ```text
//! cargo run --release -p e2e --bin farm_bench -- [--pg] [--sim-workers 16] [--tasks 1024]
//! ```

use std::time::{Duration, Instant};

use e2e::{Backend, Client, Coordinator, ENROLL_TOKEN, TestDb, Worker, scene_json};
use protocol::TileResult;
use protocol::frame::{PixelRecord, TileHeader};
use protocol::lease::{JobState, TaskLease};

fn arg(name: &str, default: usize) -> usize {
    let args: Vec<String> = std::env::args().collect();
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1))
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

async fn sim_worker(url: String) -> u64 {
    let http = reqwest::Client::new();
    let reg: serde_json::Value = http
        .post(format!("{url}/v1/workers/register"))
        .bearer_auth(ENROLL_TOKEN)
        .json(&serde_json::json!({"name": "sim"}))
        .send()
        .await
        .expect("register")
        .json()
        .await
        .expect("json");
    let token = reg["token"].as_str().expect("token").to_owned();
    let mut n = 0;
    loop {
        let r = http
            .post(format!("{url}/v1/workers/lease"))
            .bearer_auth(&token)
            .json(&serde_json::json!({"wait_ms": 0}))
            .send()
            .await
            .expect("lease");
        if r.status() != 200 {
            return n;
        }
        let l: TaskLease = r.json().await.expect("lease json");
        let body = TileResult {
            header: TileHeader {
                job_id: l.job_id,
                task_id: l.task_id,
                attempt: l.attempt,
                rect: l.rect,
                sample_start: l.sample_start,
                sample_end: l.sample_end,
            },
            pixels: vec![PixelRecord::default(); l.rect.pixel_count()],
            cells: vec![],
        }
        .encode();
        let r = http
            .put(format!(
                "{url}/v1/tasks/{}/result?attempt={}",
                l.task_id, l.attempt
            ))
            .bearer_auth(&token)
            .body(body)
            .send()
            .await
            .expect("upload");
        assert!(r.status().is_success(), "upload: {}", r.status());
        n += 1;
    }
}

fn queue_throughput(backend: Backend, sims: usize, tasks: usize) {
    let db = TestDb::new(backend);
    let coord = Coordinator::start(db.config());
    let client = Client::new(&coord.url());
    let side = (tasks as f64).sqrt().ceil() as u32 * 8;
    let id = client.submit(&serde_json::json!({
        "scene": {"inline": scene_json("cornell-box/scene.json")},
        "resolution": [side, side], "spp": 1, "tile_size": 8,
    }));
    let total = client.status(id).tasks_total;
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .expect("rt");
    let start = Instant::now();
    let done: u64 = rt.block_on(async {
        let hs: Vec<_> = (0..sims)
            .map(|_| tokio::spawn(sim_worker(coord.url())))
            .collect();
        let mut n = 0;
        for h in hs {
            n += h.await.expect("sim");
        }
        n
    });
    let leasing = start.elapsed().as_secs_f64();
    let st = client.wait(id, Duration::from_secs(600));
    let finished = start.elapsed().as_secs_f64();
    assert_eq!(st.state, JobState::Done);
    println!(
        "queue [{backend:?}]: {done}/{total} tasks of 8x8 px by {sims} simulated workers in {leasing:.2} s = {:.0} lease+upload/s; \
         job finished (assembly of {total} blocks, EXR/PNG) {:.2} s after the last upload",
        done as f64 / leasing,
        finished - leasing
    );
}

fn overhead(backend: Backend) {
    let scene = scene_json("cornell-box/scene.json");
    let (res, spp, tile) = (256u32, 32u32, 32u32);
    let spec = serde_json::json!({
        "scene": {"inline": scene}, "resolution": [res, res], "spp": spp, "tile_size": tile, "seed": 1,
    });
    let desc: scene::SceneDesc = serde_json::from_value(scene.clone()).expect("desc");
    let db = TestDb::new(backend);
    let coord = Coordinator::start(db.config());
    let client = Client::new(&coord.url());
    let ws: Vec<Worker> = (0..2)
        .map(|i| Worker::start(&coord.url(), &format!("w{i}")))
        .collect();
    std::thread::sleep(Duration::from_millis(300)); // workers registered and polling
    // The machine may be shared: alternate the two and keep the best of each.
    let (mut local, mut farm, mut tasks) = (f64::INFINITY, f64::INFINITY, 0);
    for _ in 0..3 {
        // In-process: the same render the farm's tasks do (scene load, prepare, 2 threads).
        let t0 = Instant::now();
        let mut loaded = scene::load(&desc, &scene::MemoryAssets::new()).expect("load");
        loaded.scene.film.width = res;
        loaded.scene.film.height = res;
        let settings = render::integrator::RenderSettings {
            spp,
            seed: 1,
            ..render::integrator::RenderSettings::from_scene(&loaded.scene)
        };
        let rs = render::integrator::RenderScene::new(&loaded.scene, &settings).expect("prepare");
        let opts = render::tile::RenderOptions {
            tile_size: tile,
            threads: 2,
        };
        render::tile::render_image(&rs, &settings, &opts, &|_, _| {}).expect("render");
        local = local.min(t0.elapsed().as_secs_f64());

        let t0 = Instant::now();
        let id = client.submit(&spec);
        let st = client.wait(id, Duration::from_secs(600));
        farm = farm.min(t0.elapsed().as_secs_f64());
        assert_eq!(st.state, JobState::Done);
        tasks = st.tasks_total;
    }
    for w in ws {
        w.stop();
    }
    println!(
        "overhead [{backend:?}]: {res}x{res} cornell-box {spp} spp, {tasks} tiles of {tile}, best of 3: in-process 2 threads {local:.3} s, \
         farm 2 workers x 1 slot {farm:.3} s (submit to done, incl. assembly) => overhead {:+.1} %",
        (farm / local - 1.0) * 100.0
    );
}

fn main() {
    let backend = if std::env::args().any(|a| a == "--pg") {
        Backend::Postgres
    } else {
        Backend::Sqlite
    };
    queue_throughput(backend, arg("--sim-workers", 16), arg("--tasks", 1024));
    overhead(backend);
}
