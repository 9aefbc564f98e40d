//! Farm benchmarks (numbers, not tests; DESIGN §8):
//!
//! 1. **Queue throughput**: one coordinator, `--sim-workers` simulated workers that lease a
//!    task and upload a valid (all-zero) frame as fast as they can; reports leases/s
//!    (lease + upload round trips) and the finishing time (assembly of every block).
//! 2. **Farm overhead** (`--only overhead [--estimator cms] [--scene many-lights] [--res 256]
//!    [--spp 64] [--tile 32] [--repeats 3] [--workers 2] [--slots 1] [--poll-ms MS]
//!    [--side local|farm]`): the same job rendered in-process (what `cvfarm render` does:
//!    `render_estimator_image` with 2 threads, EXR encoded) and by a farm of `--workers` real
//!    workers × `--slots` slots on loopback, `--repeats` times as pairs run back to back in
//!    alternating order; reports every pair's wall and CPU seconds (stderr), the median of the
//!    pairs' ratios (the figure that survives a machine whose speed drifts) and best vs best.
//!    The job's status is polled at a quarter of its ETA (5–100 ms) unless `--poll-ms` fixes
//!    the interval. `--side` runs one side only (to profile it).
//! 3. **Merge + solve throughput** (DESIGN §8, "coordinator merge/solve throughput"): the
//!    coordinator's barrier work on realistic training accumulators. `--sim-workers` threads
//!    each produce the tables of their share of `--tiles` tiles (`--cells` cells per tile,
//!    half of them shared with the next tile as neighbouring tiles share world-space cells;
//!    layout 8 light partitions + 1 BSDF component, RGB, `--samples` training samples per
//!    cell) and encode them as a worker uploads them. Then timed, as the coordinator does it:
//!    decode + merge of every tile table in canonical order
//!    (`AccumulatorTable::decode` / `merge`), and `AccumulatorTable::solve` on 1 and 2
//!    threads. Reports merged cell records/s and solved cells/s as a markdown table.
//! 4. **A real `cms` job** through a real coordinator and `--workers` real workers on
//!    loopback (`--scene`, default `many-lights`, `--res`, `--spp`): the coordinator's own
//!    train barrier (decode, validate, merge in canonical order, solve on all cores, encode),
//!    read from `stats.json`, as cells/s; plus every phase's wall time.
//!
//! ```text
//! cargo run --release -p e2e --bin farm_bench -- [--pg] [--sim-workers 16] [--tasks 1024]
//!     [--tiles 256] [--cells 300] [--samples 64] [--workers 2] [--res 256] [--spp 32]
//!     [--scene many-lights] [--only queue|merge|cms|overhead]
//! ```

use std::time::{Duration, Instant};

#[path = "../../../crates/render/tests/cpu_time/mod.rs"]
mod cpu_time;

use e2e::{
    Backend, Coordinator, ENROLL_TOKEN, Farm, blank_result, scene_json, start_workers, stop_workers,
};
use estimators::cell::{CellAccumulator, ColorMode, ComponentLayout, CvSample};
use estimators::solve::{SolvePolicy, SolveStatus};
use estimators::table::AccumulatorTable;
use protocol::frame::PixelRecord;
use protocol::lease::{JobState, TaskLease};

/// The value after the command-line flag `name`, if any.
fn arg_str(name: &str) -> Option<String> {
    std::env::args().skip_while(|a| a != name).nth(1)
}

/// The numeric value after the flag `name`, or `default`.
fn arg(name: &str, default: usize) -> usize {
    arg_str(name)
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
        let body = blank_result(&l, PixelRecord::default()).encode();
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
    let farm = Farm::start(backend);
    let (coord, client) = (&farm.coord, &farm.client);
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

/// Farm vs in-process for one job: `--estimator` (default `path`), `--scene` (default
/// `cornell-box`), `--res`, `--spp`, `--tile` (default 32), `--repeats` (default 3). The
/// in-process side is what `cvfarm render -o x.exr` does: load and prepare the scene, run the
/// estimator's phases with 2 threads (`render_estimator_image`), encode the EXR. The farm side
/// is submit → done (all phases, barriers, assembly, EXR/PNG/stats stored) with 2 workers × 1
/// slot. The two alternate and the best of each counts (the machine may be shared).
fn overhead(backend: Backend, estimator: &str, scene_name: &str, res: u32, spp: u32, tile: u32) {
    let scene = scene_json(&format!("{scene_name}/scene.json"));
    let repeats = arg("--repeats", 3);
    let spec = serde_json::json!({
        "scene": {"inline": scene}, "estimator": {"kind": estimator},
        "resolution": [res, res], "spp": spp, "tile_size": tile, "seed": 1,
    });
    let job: protocol::JobSpec = serde_json::from_value(spec.clone()).expect("job spec");
    let desc: scene::SceneDesc = serde_json::from_value(scene.clone()).expect("desc");
    let resolved = job
        .resolve(&desc, &protocol::job::Limits::default())
        .expect("resolve");
    let scene_bytes = serde_json::to_vec(&scene).expect("scene bytes");
    let testfarm = Farm::start(backend);
    let client = &testfarm.client;
    let (n_workers, slots) = (arg("--workers", 2), arg("--slots", 1));
    let ws = (0..n_workers)
        .map(|i| e2e::Worker::start_slots(&testfarm.url(), &format!("w{i}"), slots))
        .collect::<Vec<_>>();
    std::thread::sleep(Duration::from_millis(300)); // workers registered and polling
    // `--side local|farm` runs one side only (to profile it alone); both by default.
    let side = arg_str("--side").unwrap_or_else(|| "both".into());
    // One in-process render: (wall s, process CPU s, phase times).
    let run_local = || {
        let (t0, c0) = (Instant::now(), cpu_time::cpu_seconds());
        let p = worker::tile::Prepared::new(
            &scene_bytes,
            Default::default(),
            &resolved,
            &job.estimator,
        )
        .expect("prepare");
        let opts = render::tile::RenderOptions {
            tile_size: tile,
            threads: 2,
        };
        let t_prep = t0.elapsed().as_secs_f64();
        let (film, _, report) = render::integrator::cv::render_estimator_image(
            &p.scene,
            &p.settings,
            &opts,
            &|_, _| {},
        )
        .expect("render");
        let layers = film
            .layers()
            .into_iter()
            .map(|l| imageio::RgbLayer {
                name: l.name.to_owned(),
                data: l.data,
            })
            .collect::<Vec<_>>();
        let exr = imageio::encode_exr(res, res, &layers).expect("exr");
        assert!(!exr.is_empty());
        let ph = &report.phases;
        let phases = format!(
            "prepare {t_prep:.2}, surrogate+denoise {:.2}, train {:.2}, merge+solve {:.2}, render {:.2}",
            ph.surrogate, ph.train, ph.solve, ph.render
        );
        (
            t0.elapsed().as_secs_f64(),
            cpu_time::cpu_seconds() - c0,
            phases,
        )
    };
    // One farm job, submit to done: (wall s, process CPU s, phase times, tasks).
    let run_farm = || {
        let (t0, c0) = (Instant::now(), cpu_time::cpu_seconds());
        let id = client.submit(&spec);
        // Polling is not free: a fixed 5 ms is 200 status requests/s, each a few queries on
        // the coordinator sharing the 2 cores with the workers. So poll at a quarter of the
        // job's ETA, between 5 ms (the end of the job is seen within 5 ms) and 100 ms
        // (`--poll-ms` fixes the interval instead).
        let fixed = arg("--poll-ms", 0) as u64;
        let st = loop {
            let s = client.status(id);
            if !matches!(s.state, JobState::Running | JobState::Paused) {
                break s;
            }
            let ms = match (fixed, s.eta_s) {
                (0, Some(eta)) => (eta * 250.0).clamp(5.0, 100.0) as u64,
                (0, None) => 20,
                (f, _) => f,
            };
            std::thread::sleep(Duration::from_millis(ms));
        };
        let t = t0.elapsed().as_secs_f64();
        // The coordinator and both workers run in this process: its CPU time is the farm's.
        let cpu = cpu_time::cpu_seconds() - c0;
        assert_eq!(st.state, JobState::Done, "{st:?}");
        let stats = client.stats(id);
        let phases = stats["phases"]
            .as_array()
            .into_iter()
            .flatten()
            .map(|p| {
                let barrier = p["barrier"]["seconds"]
                    .as_f64()
                    .map_or(String::new(), |b| format!(" + barrier {b:.2}"));
                format!(
                    "{} {:.2}{barrier}",
                    p["name"].as_str().unwrap_or("?"),
                    p["seconds"].as_f64().unwrap_or(0.0)
                )
            })
            .collect::<Vec<_>>()
            .join(", ");
        let tasks = stats
            .get("tasks")
            .and_then(serde_json::Value::as_u64)
            .unwrap_or(0);
        (t, cpu, phases, tasks)
    };
    // Repeats alternate the order (local first, then farm first, ...), so a machine whose
    // speed drifts or that favours the first of two runs biases neither side; each repeat is
    // a pair run back to back, and the median of the pairs' ratios is the robust figure.
    let mut pairs: Vec<[(f64, f64); 2]> = Vec::new();
    let (mut best_local, mut best_farm) = (
        (f64::INFINITY, String::new()),
        (f64::INFINITY, String::new()),
    );
    let mut tasks = 0;
    for r in 0..repeats.max(1) {
        let mut pair = [(f64::NAN, f64::NAN); 2];
        for first_farm in [r % 2 == 1, r % 2 == 0] {
            if first_farm && side != "local" {
                let (t, cpu, phases, n) = run_farm();
                tasks = n;
                pair[1] = (t, cpu);
                if t < best_farm.0 {
                    best_farm = (t, phases);
                }
            } else if !first_farm && side != "farm" {
                let (t, cpu, phases) = run_local();
                pair[0] = (t, cpu);
                if t < best_local.0 {
                    best_local = (t, phases);
                }
            }
        }
        pairs.push(pair);
    }
    stop_workers(ws);
    let median = |mut v: Vec<f64>| {
        v.sort_by(f64::total_cmp);
        match v.len() {
            0 => f64::NAN,
            n if n % 2 == 1 => v[n / 2],
            n => 0.5 * (v[n / 2 - 1] + v[n / 2]),
        }
    };
    let wall: Vec<f64> = pairs.iter().map(|p| p[1].0 / p[0].0).collect();
    let cpu: Vec<f64> = pairs.iter().map(|p| p[1].1 / p[0].1).collect();
    let each = |v: &[f64]| {
        v.iter()
            .map(|r| format!("{:+.1}", (r - 1.0) * 100.0))
            .collect::<Vec<_>>()
            .join(" ")
    };
    let (local, farm) = (best_local.0, best_farm.0);
    for (i, p) in pairs.iter().enumerate() {
        eprintln!(
            "pair {i}: in-process {:.3} s / {:.2} CPU s, farm {:.3} s / {:.2} CPU s",
            p[0].0, p[0].1, p[1].0, p[1].1
        );
    }
    println!(
        "overhead [{backend:?}]: {estimator}, {scene_name} {res}x{res} {spp} spp, tiles of {tile}, {tasks} tasks, {repeats} pairs: \
         in-process 2 threads best {local:.3} s ({}), farm {n_workers} workers x {slots} slots best {farm:.3} s (submit to done; {}); \
         wall overhead: median of pairs {:+.1} % (each pair: {}; best vs best {:+.1} %); \
         CPU overhead (whole process): median of pairs {:+.1} % (each pair: {})",
        best_local.1,
        best_farm.1,
        (median(wall.clone()) - 1.0) * 100.0,
        each(&wall),
        (farm / local - 1.0) * 100.0,
        (median(cpu.clone()) - 1.0) * 100.0,
        each(&cpu),
    );
}

/// A small deterministic generator (xorshift64*), so the tables are the same every run.
struct Rng(u64);

impl Rng {
    fn next_f64(&mut self) -> f64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        (self.0.wrapping_mul(0x2545_f491_4f6c_dd1d) >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// Light partitions and overlapping (BSDF) components of the simulated cells.
const PARTITIONS: u32 = 8;
const OVERLAPPING: u32 = 1;

/// The training table a worker uploads for tile `tile`: `cells` cells with keys
/// `tile·cells/2 ..`, each with `samples` samples spread over the lights (one partition
/// per sample, as for light sampling) and a BSDF component.
fn tile_table(tile: usize, cells: usize, samples: usize) -> Vec<u8> {
    let layout = ComponentLayout::new(PARTITIONS, OVERLAPPING).expect("layout");
    let mut rng =
        Rng(0x9e37_79b9_7f4a_7c15 ^ (tile as u64 + 1).wrapping_mul(0xbf58_476d_1ce4_e5b9));
    let first = (tile * cells / 2) as u64;
    let mut table = std::collections::BTreeMap::new();
    for c in 0..cells as u64 {
        let mut acc = CellAccumulator::new(layout, ColorMode::Rgb);
        for _ in 0..samples {
            let light = (rng.next_f64() * f64::from(PARTITIONS)) as u32 % PARTITIONS;
            let lambda_light = 0.2 + rng.next_f64();
            let lambda_bsdf = [0.1 + rng.next_f64()];
            let pdf = 0.3 + lambda_light + lambda_bsdf[0];
            let f = rng.next_f64() * 2.0;
            let s = CvSample {
                pdf,
                partition: Some((light, lambda_light)),
                overlapping: &lambda_bsdf,
            };
            let w = 0.5 + rng.next_f64();
            let _ = acc.add(w, [f, 0.8 * f, 0.6 * f + 0.1], &s);
        }
        table.insert(first + c, acc);
    }
    AccumulatorTable::Moments(table, Some(1.0)).encode()
}

/// The merge + solve benchmark (see the module docs); prints a markdown table.
fn merge_solve(sims: usize, tiles: usize, cells: usize, samples: usize) {
    // Simulated workers produce and encode their tiles' tables in parallel (not timed).
    let t0 = Instant::now();
    let per = tiles.div_ceil(sims.max(1));
    let mut uploads: Vec<(usize, Vec<u8>)> = std::thread::scope(|s| {
        let hs: Vec<_> = (0..sims.max(1))
            .map(|w| {
                s.spawn(move || {
                    (w * per..((w + 1) * per).min(tiles))
                        .map(|t| (t, tile_table(t, cells, samples)))
                        .collect::<Vec<_>>()
                })
            })
            .collect();
        hs.into_iter()
            .flat_map(|h| h.join().expect("sim worker"))
            .collect()
    });
    uploads.sort_by_key(|(t, _)| *t);
    let produced = t0.elapsed().as_secs_f64();
    let bytes: usize = uploads.iter().map(|(_, b)| b.len()).sum();
    let records = tiles * cells;

    // Decode + merge in canonical (tile) order, as the coordinator's barrier does; best of 3.
    let mut merge_s = f64::INFINITY;
    let mut merged = None;
    for _ in 0..3 {
        let t = Instant::now();
        let mut acc = AccumulatorTable::Moments(Default::default(), Some(0.0));
        for (_, b) in &uploads {
            let table = AccumulatorTable::decode(b).expect("decode");
            acc.merge(&table).expect("merge");
        }
        merge_s = merge_s.min(t.elapsed().as_secs_f64());
        merged = Some(acc);
    }
    let merged = merged.expect("merged");
    let distinct = merged.len();

    let policy = SolvePolicy::default();
    let mut solve_s = Vec::new();
    let mut solved_cells = 0;
    let mut fitted = 0;
    for threads in [1usize, 2] {
        let mut best = f64::INFINITY;
        for _ in 0..3 {
            let t = Instant::now();
            let solved = merged.solve(&policy, threads);
            best = best.min(t.elapsed().as_secs_f64());
            solved_cells = solved.coefficients.len();
            fitted = solved
                .coefficients
                .values()
                .filter(|c| c.diagnostics().status == SolveStatus::Solved)
                .count();
        }
        solve_s.push((threads, best));
    }
    let encoded = merged.encode().len();

    println!(
        "merge/solve: {tiles} tile tables from {sims} simulated workers, {cells} cells/tile \
         ({PARTITIONS} light partitions + {OVERLAPPING} BSDF, RGB, {samples} samples/cell), \
         {:.1} MiB uploaded ({:.1} KiB/tile), {distinct} distinct cells after merge \
         ({fitted} fitted, merged table {:.1} MiB); tables produced in {produced:.2} s\n",
        bytes as f64 / (1 << 20) as f64,
        bytes as f64 / 1024.0 / tiles as f64,
        encoded as f64 / (1 << 20) as f64,
    );
    println!("| step | time (best of 3) | throughput |");
    println!("|---|---:|---:|");
    println!(
        "| decode + merge ({records} records, canonical order) | {:.1} ms | {:.2} M merged cells/s ({:.0} MiB/s) |",
        merge_s * 1e3,
        records as f64 / merge_s / 1e6,
        bytes as f64 / (1 << 20) as f64 / merge_s
    );
    for (threads, s) in solve_s {
        println!(
            "| solve ({solved_cells} cells, {threads} thread{}) | {:.1} ms | {:.2} M solved cells/s |",
            if threads == 1 { "" } else { "s" },
            s * 1e3,
            solved_cells as f64 / s / 1e6
        );
    }
}

/// A real `cms` job on a loopback farm; prints the train barrier's throughput and the phases.
fn cms_job(backend: Backend, workers: usize, scene: &str, res: u32, spp: u32) {
    let farm = Farm::start(backend);
    let (coord, client) = (&farm.coord, &farm.client);
    let ws = start_workers(&coord.url(), workers);
    let t0 = Instant::now();
    let id = client.submit(&serde_json::json!({
        "scene": {"inline": scene_json(&format!("{scene}/scene.json"))},
        "estimator": {"kind": "cms"},
        "resolution": [res, res], "spp": spp, "tile_size": 32, "seed": 1,
    }));
    let st = client.wait(id, Duration::from_secs(3600));
    let wall = t0.elapsed().as_secs_f64();
    stop_workers(ws);
    assert_eq!(st.state, JobState::Done, "{st:?}");
    let stats = client.stats(id);
    let table = client.download(id, "coefficients");
    println!(
        "cms job [{backend:?}]: {scene} {res}x{res} {spp} spp, {workers} workers x 1 slot, submit to done {wall:.2} s; \
         coefficient table {:.1} KiB\n",
        table.len() as f64 / 1024.0
    );
    println!(
        "| phase | spp | tasks | wall (first lease → last result) | barrier after it | cells | barrier throughput |"
    );
    println!("|---|---:|---:|---:|---:|---:|---:|");
    for p in stats["phases"].as_array().into_iter().flatten() {
        let b = &p["barrier"];
        let (bs, cells) = (b["seconds"].as_f64(), b["cells"].as_u64().unwrap_or(0));
        println!(
            "| {} | {} | {} | {:.2} s | {} | {} | {} |",
            p["name"].as_str().unwrap_or("?"),
            p["spp"],
            p["tasks"],
            p["seconds"].as_f64().unwrap_or(0.0),
            bs.map_or("—".into(), |s| format!("{:.1} ms", s * 1e3)),
            if cells > 0 {
                cells.to_string()
            } else {
                "—".into()
            },
            match bs {
                Some(s) if cells > 0 && s > 0.0 => {
                    format!("{:.0} distinct cells/s (all steps)", cells as f64 / s)
                }
                _ => "—".into(),
            },
        );
    }
    // convergence.csv is computed on read from every stored result: its cost for this job.
    let t = Instant::now();
    let csv = client.download(id, "convergence.csv");
    let csv_s = t.elapsed().as_secs_f64();
    let rows = csv
        .iter()
        .filter(|&&b| b == b'\n')
        .count()
        .saturating_sub(1);
    println!(
        "\nconvergence.csv: {rows} rows in {:.0} ms (decode + merge of every stored result per read)",
        csv_s * 1e3
    );
    let train = stats["phases"]
        .as_array()
        .and_then(|ph| ph.iter().position(|p| p["name"] == "train"));
    if let Some(train) = train {
        barrier_breakdown(coord, id, train as i64);
    }
}

/// The train barrier of job `id` redone step by step from its stored tables, with the
/// coordinator's own functions (`protocol::cv`, `AccumulatorTable`), each step timed on 1 and
/// 2 threads (best of 3).
fn barrier_breakdown(coord: &Coordinator, id: i64, train: i64) {
    let store = &coord.state.store;
    let blobs: Vec<Vec<u8>> = coord
        .block_on(store.phase_tables(id, train))
        .expect("train tables")
        .into_iter()
        .map(|t| match t {
            coordinator::store::StoredTable::Table(b) => b,
            coordinator::store::StoredTable::Frame(_) => panic!("a table stored inside its frame"),
        })
        .collect();
    let job = coord.block_on(store.job(id)).expect("store").expect("job");
    let spec: protocol::JobSpec = serde_json::from_str(&job.spec).expect("spec");
    let est = spec
        .estimator
        .phased_for(&job.resolved)
        .expect("a phased estimator");
    let best = |f: &mut dyn FnMut()| {
        (0..3)
            .map(|_| {
                let t = Instant::now();
                f();
                t.elapsed().as_secs_f64()
            })
            .fold(f64::INFINITY, f64::min)
    };
    let kind = protocol::cv::table_kind(&est);
    let policy = est.solve_policy();
    let mut rows = Vec::new();
    let (mut records, mut cells) = (0, 0);
    for threads in [1usize, 2] {
        let mut tables = Vec::new();
        let check_s = best(&mut || {
            tables = protocol::cv::check_train_tables(&est, &job.resolved, &blobs, threads)
                .expect("tables");
        });
        records = tables.iter().map(AccumulatorTable::len).sum();
        // The barrier moves the tables into the merge: clone them before the clock starts.
        let mut copies: Vec<Vec<AccumulatorTable>> = (0..3).map(|_| tables.clone()).collect();
        let mut merged = None;
        let merge_s = best(&mut || {
            let t = copies.pop().expect("a copy per run");
            merged = Some(protocol::cv::merge_train(kind, t, threads).expect("merge"));
        });
        let merged = merged.expect("merged");
        cells = merged.len();
        let solve_s = best(&mut || {
            let _ = merged.solve(&policy, threads);
        });
        rows.push((threads, check_s, merge_s, solve_s));
    }
    let bytes: usize = blobs.iter().map(Vec::len).sum();
    println!(
        "\ntrain barrier step by step: {} stored tables ({:.1} MiB, {records} cell records, \
         {:.0} per tile), {cells} distinct cells\n",
        blobs.len(),
        bytes as f64 / (1 << 20) as f64,
        records as f64 / blobs.len().max(1) as f64,
    );
    println!("| step | threads | time (best of 3) | throughput |");
    println!("|---|---:|---:|---:|");
    for (threads, check_s, merge_s, solve_s) in rows {
        println!(
            "| validate + decode tables (`check_train_tables`) | {threads} | {:.1} ms | {:.2} M records/s |",
            check_s * 1e3,
            records as f64 / check_s / 1e6
        );
        println!(
            "| merge in canonical order (`merge_train`) | {threads} | {:.1} ms | {:.2} M merged cells/s |",
            merge_s * 1e3,
            records as f64 / merge_s / 1e6
        );
        println!(
            "| solve | {threads} | {:.1} ms | {:.3} M solved cells/s |",
            solve_s * 1e3,
            cells as f64 / solve_s / 1e6
        );
    }
}

fn main() {
    // `RUST_LOG=coordinator=debug,worker=debug` prints the farm's timeline (lease, inputs,
    // render, upload, barrier) with the time since start, to see where a job waits.
    if std::env::var_os("RUST_LOG").is_some() {
        tracing_subscriber::fmt()
            .with_env_filter(tracing_subscriber::EnvFilter::from_default_env())
            .with_timer(tracing_subscriber::fmt::time::uptime())
            .with_writer(std::io::stderr)
            .init();
    }
    let args: Vec<String> = std::env::args().collect();
    let backend = if args.iter().any(|a| a == "--pg") {
        Backend::Postgres
    } else {
        Backend::Sqlite
    };
    let only = arg_str("--only");
    let run = |name: &str| only.as_deref().is_none_or(|o| o == name);
    if run("queue") {
        queue_throughput(backend, arg("--sim-workers", 16), arg("--tasks", 1024));
    }
    if run("merge") {
        merge_solve(
            arg("--sim-workers", 16),
            arg("--tiles", 256),
            arg("--cells", 300),
            arg("--samples", 64),
        );
    }
    if run("cms") {
        let scene = arg_str("--scene").unwrap_or_else(|| "many-lights".into());
        cms_job(
            backend,
            arg("--workers", 2),
            &scene,
            arg("--res", 256) as u32,
            arg("--spp", 32) as u32,
        );
    }
    if run("overhead") {
        let estimator = arg_str("--estimator").unwrap_or_else(|| "path".into());
        let scene = arg_str("--scene").unwrap_or_else(|| "cornell-box".into());
        overhead(
            backend,
            &estimator,
            &scene,
            arg("--res", 256) as u32,
            arg("--spp", 32) as u32,
            arg("--tile", 32) as u32,
        );
    }
}
