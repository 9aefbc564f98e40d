//! Same job by 1 and 3 workers ⇒ bitwise-identical EXR, equal to an in-process render; on
//! SQLite and on PostgreSQL. Also: a killed worker's lease expires and another worker redoes
//! the tile with an identical image.

use std::time::Duration;

use e2e::{
    Backend, Client, Coordinator, Farm, TestDb, Worker, local_exr, run_on_two_coordinators,
    scene_json,
};

fn spec(scene: &serde_json::Value, res: u32, spp: u32, tile: u32, seed: u64) -> serde_json::Value {
    serde_json::json!({
        "scene": { "inline": scene },
        "estimator": { "kind": "path" },
        "resolution": [res, res],
        "spp": spp,
        "tile_size": tile,
        "seed": seed,
    })
}

fn run_job(
    backend: Backend,
    workers: usize,
    spec: &serde_json::Value,
) -> (Vec<u8>, protocol::lease::JobStatus) {
    let farm = Farm::start(backend);
    let client = &farm.client;
    let id = client.submit(spec);
    let status = farm.finish(id, workers, Duration::from_secs(120));
    let exr = client.download(id, "image.exr");
    let png = client.download(id, "preview.png");
    assert_eq!(&png[1..4], b"PNG");
    let stats = client.stats(id);
    assert_eq!(stats["tasks"].as_u64(), Some(status.tasks_total));
    assert_eq!(stats["spp"].as_f64(), Some(f64::from(status.job.spp)));
    assert!(stats["estimated_rel_mse"].as_f64().expect("rel mse") > 0.0);
    (exr, status)
}

fn one_vs_three(backend: Backend) {
    let scene = scene_json("cornell-box/scene.json");
    let spec = spec(&scene, 32, 8, 8, 7);
    let (one, status) = run_job(backend, 1, &spec);
    let (three, _) = run_job(backend, 3, &spec);
    assert!(one == three, "1-worker and 3-worker EXRs differ");
    let local = local_exr(&scene, &[], &status.job);
    assert!(one == local, "farm EXR differs from the in-process render");
    // And the image is not trivially black.
    let img = imageio::read_exr_bytes(&one).expect("exr decodes");
    let beauty = img.main_layer().expect("beauty");
    assert!(beauty.data.iter().any(|p| p[0] > 0.0));
}

e2e::backend_tests!(one_vs_three: one_and_three_workers_bitwise_identical_sqlite, one_and_three_workers_bitwise_identical_postgres);

#[test]
fn scene_with_uploaded_asset_renders_identically() {
    let farm = Farm::start(Backend::Sqlite);
    let client = &farm.client;
    let scene = scene_json("envmap/scene.json");
    let exr_bytes = std::fs::read(e2e::scene_path("envmap/museum.exr")).expect("museum.exr");
    let hash = client.upload_asset(&exr_bytes);
    // Uploading the same content again is idempotent.
    assert_eq!(client.upload_asset(&exr_bytes), hash);
    let name = scene["environment"]["filename"]
        .as_str()
        .expect("env filename")
        .to_owned();
    // The scene document itself goes up as a bundle, addressed by content.
    let bundle = client.upload_asset(&serde_json::to_vec(&scene).expect("json"));
    let mut s = spec(&scene, 16, 4, 8, 3);
    s["scene"] = serde_json::json!({ "bundle": bundle });
    s["assets"] = serde_json::json!({ name.clone(): hash });
    let id = client.submit(&s);
    let status = farm.finish(id, 1, Duration::from_secs(120));
    let image = client.download(id, "image.exr");
    assert!(image == local_exr(&scene, &[(&name, exr_bytes)], &status.job));
}

#[test]
fn killed_worker_lease_expires_and_another_redoes_it() {
    let farm = Farm::start_with(Backend::Sqlite, |cfg| {
        cfg.lease_ms = 1_500;
        cfg.heartbeat_ms = 300;
    });
    let (coord, client) = (&farm.coord, &farm.client);
    let scene = scene_json("cornell-box/scene.json");
    let spec = spec(&scene, 32, 64, 8, 11);
    let id = client.submit(&spec);

    let mut victim = Worker::start(&coord.url(), "victim");
    // Wait until the victim holds a lease, then kill it mid-tile.
    let leased_task = loop {
        let t: Option<i64> = coord.block_on(leased_task_of(coord, id));
        if let Some(t) = t {
            break t;
        }
        std::thread::sleep(Duration::from_millis(5));
    };
    victim.kill();
    let held_at_kill: Option<(i64, i64)> = coord.block_on(lease_holder(coord, leased_task));
    let rescuer = Worker::start(&coord.url(), "rescuer");
    let status = client.wait_done(id, Duration::from_secs(120));
    rescuer.stop();
    if let Some((attempt, _worker)) = held_at_kill {
        // The killed attempt expired and the task was redone by a later attempt.
        let t = coord
            .block_on(coord.state.store.task(leased_task))
            .expect("store")
            .expect("task");
        assert!(
            t.done_attempt.expect("done") > attempt,
            "task {leased_task} was not redone after the kill"
        );
    }
    let image = client.download(id, "image.exr");
    assert!(
        image == local_exr(&scene, &[], &status.job),
        "image differs after a redone tile"
    );
}

async fn leased_task_of(coord: &Coordinator, job: i64) -> Option<i64> {
    let status = coord.state.store.progress(job, 0).await.expect("progress");
    if status.attempts == 0 {
        return None;
    }
    for id in 1..=status.total {
        if let Ok(Some(t)) = coord.state.store.task(id).await
            && t.job_id == job
            && t.state == "leased"
        {
            return Some(id);
        }
    }
    None
}

async fn lease_holder(coord: &Coordinator, task: i64) -> Option<(i64, i64)> {
    let t = coord.state.store.task(task).await.expect("store")?;
    if t.state == "leased" {
        Some((t.attempt, t.worker_id.unwrap_or(0)))
    } else {
        None
    }
}

#[test]
fn graceful_worker_stop_finishes_the_tile_in_hand() {
    let farm = Farm::start(Backend::Sqlite);
    let (coord, client) = (&farm.coord, &farm.client);
    let scene = scene_json("cornell-box/scene.json");
    let id = client.submit(&spec(&scene, 32, 1024, 16, 1));
    let w = Worker::start(&coord.url(), "w");
    while coord.block_on(leased_task_of(coord, id)).is_none() {
        std::thread::sleep(Duration::from_millis(5));
    }
    // Let the lease reach the worker (a lease arriving after the stop is released instead).
    std::thread::sleep(Duration::from_millis(100));
    let summary = w.stop();
    assert!(summary.uploaded + summary.released >= 1, "{summary:?}");
    assert_eq!(summary.stale, 0);
    // Nothing is left leased by the stopped worker: every lease was finished or released.
    assert_eq!(coord.block_on(leased_task_of(coord, id)), None);
    let status = farm.finish(id, 1, Duration::from_secs(120));
    let stats = client.stats(id);
    // No tile was rendered twice: one attempt per task, plus one per lease released unrendered.
    assert_eq!(
        stats["attempts"].as_u64(),
        Some(status.tasks_total + summary.released),
        "{stats}"
    );
    let effects: Vec<String> = serde_json::from_value(stats["effects"].clone()).expect("effects");
    assert!(
        effects.iter().any(|e| e.starts_with("area_lights")),
        "{effects:?}"
    );
    assert!(effects.iter().any(|e| e == "bsdf:diffuse"), "{effects:?}");
}

#[test]
fn two_coordinators_share_one_postgres() {
    let scene = scene_json("cornell-box/scene.json");
    // Either coordinator answers for the job.
    let run = run_on_two_coordinators(&spec(&scene, 32, 16, 8, 4), Duration::from_secs(120));
    let [sa, sb] = &run.workers;
    assert_eq!(
        sa.uploaded + sb.uploaded,
        run.status.tasks_total,
        "{sa:?} {sb:?}"
    );
    assert!(run.exr == local_exr(&scene, &[], &run.status.job));
}

#[test]
fn worker_started_before_the_coordinator_connects_with_back_off() {
    let db = TestDb::new(Backend::Sqlite);
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .expect("bind")
        .local_addr()
        .expect("addr")
        .port();
    let addr: std::net::SocketAddr = format!("127.0.0.1:{port}").parse().expect("addr");
    let w = Worker::start(&format!("http://{addr}"), "early");
    std::thread::sleep(Duration::from_millis(800)); // several refused connections
    let coord = Coordinator::start_on(db.config(), addr);
    let client = Client::new(&coord.url());
    let scene = scene_json("cornell-box/scene.json");
    let id = client.submit(&spec(&scene, 16, 4, 8, 2));
    let status = client.wait_done(id, Duration::from_secs(60));
    assert_eq!(w.stop().uploaded, status.tasks_total);
}
