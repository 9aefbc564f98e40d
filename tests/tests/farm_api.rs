//! The farm API under misuse: stale attempts, bad input of every kind (4xx + a JSON error
//! naming the problem, nothing accepted lost), and a coordinator killed mid-job.

use std::time::Duration;

use e2e::{Backend, Client, FakeWorker, Farm, blank_result, local_exr, scene_json};
use protocol::TileResult;
use protocol::frame::{PixelRecord, TileHeader};
use protocol::lease::{JobState, TaskLease};

fn small_spec(spp: u32) -> serde_json::Value {
    serde_json::json!({
        "scene": { "inline": scene_json("cornell-box/scene.json") },
        "resolution": [16, 16],
        "spp": spp,
        "tile_size": 8,
    })
}

/// A frame of a lease's tile under `attempt`: zero sums, the lease's sample count.
fn frame(l: &TaskLease, attempt: u32) -> Vec<u8> {
    let pixel = PixelRecord {
        count: u64::from(l.sample_end - l.sample_start),
        ..Default::default()
    };
    let r = blank_result(l, pixel);
    TileResult {
        header: TileHeader {
            attempt,
            ..r.header
        },
        ..r
    }
    .encode()
}

/// Long-poll of a fake worker's leases.
const WAIT_MS: u64 = 1_000;

#[test]
fn stale_attempt_is_rejected_and_accepted_upload_is_idempotent() {
    let farm = Farm::start_with(Backend::Sqlite, |cfg| {
        cfg.lease_ms = 400;
        cfg.max_attempts = 10;
    });
    let (coord, client) = (&farm.coord, &farm.client);
    let job = client.submit(&small_spec(2));
    let a = FakeWorker::register(&farm.url(), WAIT_MS);
    let b = FakeWorker::register(&farm.url(), WAIT_MS);

    let la = a.lease().expect("a leases");
    assert_eq!(la.attempt, 1);
    assert!(a.heartbeat(la.task_id, 1).status == 200);
    // A goes silent; its lease expires and the reaper gives the task back.
    let t0 = std::time::Instant::now();
    while coord
        .block_on(coord.state.store.task(la.task_id))
        .expect("store")
        .expect("task")
        .state
        != "pending"
    {
        assert!(
            t0.elapsed() < Duration::from_secs(20),
            "the reaper never reclaimed the lease"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    let lb = b.lease().expect("b leases");
    assert_eq!(
        (lb.task_id, lb.attempt),
        (la.task_id, 2),
        "the expired task is leased again, attempt 2"
    );

    // A's late upload and heartbeat name a superseded attempt.
    let r = a.upload(la.task_id, 1, frame(&la, 1));
    assert_eq!(r.status, 409);
    assert_eq!(r.api_error().code, "stale_attempt");
    assert_eq!(a.heartbeat(la.task_id, 1).status, 409);
    // A cannot upload B's attempt either (not its lease).
    let r = a.upload(lb.task_id, 2, frame(&lb, 2));
    assert_eq!(r.status, 409, "{}", String::from_utf8_lossy(&r.body));

    // B's upload is accepted; repeating it is a no-op.
    let r = b.upload(lb.task_id, 2, frame(&lb, 2));
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    assert_eq!(r.json()["duplicate"], false);
    let r = b.upload(lb.task_id, 2, frame(&lb, 2));
    assert_eq!(r.status, 200);
    assert_eq!(r.json()["duplicate"], true);
    // A frame whose header names another attempt than the query is refused.
    let r = b.upload(lb.task_id, 2, frame(&lb, 3));
    assert_eq!(r.status, 400);
    let n = coord
        .block_on(coord.state.store.result_count(job))
        .expect("count");
    assert_eq!(n, 1, "exactly one result stored");
}

#[test]
fn bad_input_is_4xx_json_naming_the_problem() {
    let farm = Farm::start_with(Backend::Sqlite, |cfg| {
        cfg.max_json_body = 64 << 10;
        cfg.max_result_body = 32 << 10;
    });
    let url = farm.url();
    let client = &farm.client;

    // A valid job first: it must survive everything below.
    let good = client.submit(&small_spec(2));

    let check = |r: e2e::Resp, status: u16, code: &str, needle: &str| {
        assert_eq!(
            r.status,
            status,
            "expected {status} {code}: {}",
            String::from_utf8_lossy(&r.body)
        );
        let e = r.api_error();
        assert_eq!(e.code, code, "{e:?}");
        assert!(
            e.message.contains(needle) || e.field.as_deref().is_some_and(|f| f.contains(needle)),
            "error does not name `{needle}`: {e:?}"
        );
        e
    };

    check(
        client.submit_raw(b"{\"scene\": "),
        400,
        "invalid_json",
        "EOF",
    );
    check(
        client.submit_raw(b"not json"),
        400,
        "invalid_json",
        "expected",
    );
    let mut s = small_spec(2);
    s["estimator"] = serde_json::json!({"kind": "magic"});
    check(
        client.submit_raw(&serde_json::to_vec(&s).unwrap()),
        422,
        "invalid_spec",
        "magic",
    );
    s["estimator"] = serde_json::json!({"kind": "gradient"});
    let e = check(
        client.submit_raw(&serde_json::to_vec(&s).unwrap()),
        422,
        "unsupported",
        "gradient",
    );
    assert_eq!(e.field.as_deref(), Some("estimator.kind"));
    // CV options are typed: a misspelt one is named, a bad value names the option.
    s["estimator"] = serde_json::json!({"kind": "cms", "trainig_spp": 3});
    check(
        client.submit_raw(&serde_json::to_vec(&s).unwrap()),
        422,
        "invalid_spec",
        "trainig_spp",
    );
    s["estimator"] = serde_json::json!({"kind": "cms", "grid_resolution": [0, 1, 1]});
    let e = check(
        client.submit_raw(&serde_json::to_vec(&s).unwrap()),
        422,
        "invalid_spec",
        "grid_resolution",
    );
    assert_eq!(e.field.as_deref(), Some("estimator.grid_resolution"));
    s["estimator"] = serde_json::json!({"kind": "path", "mis": "power", "bogus": 1});
    let e = check(
        client.submit_raw(&serde_json::to_vec(&s).unwrap()),
        422,
        "invalid_spec",
        "bogus",
    );
    assert_eq!(e.field.as_deref(), Some("bogus"));
    let mut s = small_spec(2);
    s["spp"] = serde_json::json!(1 << 20);
    check(
        client.submit_raw(&serde_json::to_vec(&s).unwrap()),
        422,
        "invalid_spec",
        "spp",
    );
    let mut s = small_spec(2);
    s["resolution"] = serde_json::json!([100_000, 100_000]);
    check(
        client.submit_raw(&serde_json::to_vec(&s).unwrap()),
        422,
        "invalid_spec",
        "resolution",
    );
    // Invalid scene: a shape naming a material that does not exist.
    let mut s = small_spec(2);
    s["scene"]["inline"]["shapes"][0]["material"] = serde_json::json!("no-such-material");
    check(
        client.submit_raw(&serde_json::to_vec(&s).unwrap()),
        422,
        "invalid_scene",
        "no-such-material",
    );
    // A scene naming an asset that was never uploaded.
    let mut s = small_spec(2);
    s["scene"] = serde_json::json!({"inline": scene_json("envmap/scene.json")});
    check(
        client.submit_raw(&serde_json::to_vec(&s).unwrap()),
        422,
        "missing_asset",
        "museum",
    );
    // A scene bundle that was never uploaded, and one that is not a scene.
    let mut s = small_spec(2);
    s["scene"] = serde_json::json!({"bundle": "ab".repeat(32)});
    check(
        client.submit_raw(&serde_json::to_vec(&s).unwrap()),
        422,
        "invalid_scene",
        "uploaded",
    );
    s["scene"] = serde_json::json!({"bundle": client.upload_asset(b"[1, 2]")});
    check(
        client.submit_raw(&serde_json::to_vec(&s).unwrap()),
        422,
        "invalid_scene",
        "native scene",
    );
    // Oversized body.
    let big = vec![b' '; 100 << 10];
    check(client.submit_raw(&big), 413, "body_too_large", "limit");
    // Asset whose body does not hash to its address.
    let r = client.request(
        "PUT",
        &format!("/v1/assets/{}", "0".repeat(64)),
        Some(b"hello".to_vec()),
    );
    check(r, 422, "hash_mismatch", "address");
    // Wrong and missing tokens.
    check(
        Client::with_token(&url, Some("wrong")).request("GET", "/v1/jobs", None),
        401,
        "unauthorized",
        "token",
    );
    check(
        Client::with_token(&url, None).request("GET", "/v1/jobs", None),
        401,
        "unauthorized",
        "token",
    );
    let r = Client::with_token(&url, Some("wrong")).request(
        "POST",
        "/v1/workers/register",
        Some(b"{}".to_vec()),
    );
    check(r, 401, "unauthorized", "token");
    // A client token is not a worker token.
    check(
        client.request("POST", "/v1/workers/lease", None),
        401,
        "unauthorized",
        "token",
    );
    // Unknown job, unknown route, output of an unfinished job.
    check(
        client.request("GET", "/v1/jobs/999999", None),
        404,
        "not_found",
        "999999",
    );
    check(
        client.request("GET", "/v1/nope", None),
        404,
        "not_found",
        "route",
    );
    check(
        client.request("GET", &format!("/v1/jobs/{good}/image.exr"), None),
        409,
        "not_finished",
        "running",
    );

    // Worker-side: truncated and non-finite frames.
    let fw = FakeWorker::register(&url, WAIT_MS);
    let l = fw.lease().expect("lease");
    let full = frame(&l, l.attempt);
    check(
        fw.upload(l.task_id, l.attempt, full[..full.len() - 3].to_vec()),
        400,
        "invalid_frame",
        "truncated",
    );
    let mut bad = blank_result(&l, PixelRecord::default());
    bad.pixels[5].sum[1] = f64::NAN;
    check(
        fw.upload(l.task_id, l.attempt, bad.encode()),
        400,
        "invalid_frame",
        "non-finite",
    );
    check(
        fw.upload(l.task_id, l.attempt, b"garbage".to_vec()),
        400,
        "invalid_frame",
        "frame",
    );
    let r = fw.c.request(
        "PUT",
        &format!("/v1/tasks/{}/result", l.task_id),
        Some(full.clone()),
    );
    check(r, 400, "invalid_query", "attempt");
    let r = fw.upload(l.task_id, l.attempt, vec![0u8; 64 << 10]);
    check(r, 413, "body_too_large", "limit");
    // Nothing bad was stored; the real upload still goes through.
    assert_eq!(fw.upload(l.task_id, l.attempt, full).status, 200);

    // Nothing accepted was lost: the good job completes with real workers.
    farm.finish(good, 1, Duration::from_secs(60));
    let jobs = client.request("GET", "/v1/jobs", None).json();
    assert_eq!(
        jobs.as_array().map(Vec::len),
        Some(1),
        "only the valid job was created"
    );
}

fn restart_mid_job(backend: Backend) {
    let mut farm = Farm::start_with(backend, |cfg| {
        cfg.lease_ms = 3_000;
        cfg.heartbeat_ms = 500;
    });
    let client = &farm.client;
    let scene = scene_json("cornell-box/scene.json");
    let spec = serde_json::json!({
        "scene": { "inline": scene }, "resolution": [48, 48], "spp": 128, "tile_size": 8, "seed": 5,
    });
    let id = client.submit(&spec);
    let ws = e2e::start_workers(&farm.url(), 1);
    // Kill the coordinator once some, but not all, tiles are done.
    loop {
        let s = client.status(id);
        assert_eq!(
            s.state,
            JobState::Running,
            "job finished before the kill; make it heavier"
        );
        if s.tasks_done >= 2 {
            break;
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    farm.restart();
    let (coord, client) = (&farm.coord, &farm.client);
    let status = client.wait_done(id, Duration::from_secs(180));
    e2e::stop_workers(ws);
    // Nothing lost, nothing finished stored twice.
    let stored = coord
        .block_on(coord.state.store.result_count(id))
        .expect("count");
    assert_eq!(stored as u64, status.tasks_total);
    let stats = client.stats(id);
    // At most the lease answered while the coordinator died is taken again.
    assert!(
        stats["attempts"].as_u64().unwrap() <= status.tasks_total + 1,
        "{stats}"
    );
    let farm = client.download(id, "image.exr");
    assert!(
        farm == local_exr(&scene, &[], &status.job),
        "image differs after the restart"
    );
}

e2e::backend_tests!(restart_mid_job: coordinator_killed_and_restarted_mid_job_completes_sqlite, coordinator_killed_and_restarted_mid_job_completes_postgres);

#[test]
fn priorities_first_then_fifo_and_cancel_stops_leasing() {
    let farm = Farm::start(Backend::Sqlite);
    let client = &farm.client;
    let a = client.submit(&small_spec(1));
    let b = client.submit(&small_spec(1));
    let mut urgent = small_spec(1);
    urgent["priority"] = serde_json::json!(5);
    let c = client.submit(&urgent);
    let w = FakeWorker::register(&farm.url(), WAIT_MS);
    // 16×16 in 8×8 tiles: 4 tasks per job. Highest priority first, then FIFO.
    let order: Vec<i64> = (0..7).map(|_| w.lease().expect("lease").job_id).collect();
    assert_eq!(order, [c, c, c, c, a, a, a]);

    // Pause c (its tasks are all leased): a paused job's lease can still finish.
    let r = client.request("POST", &format!("/v1/jobs/{c}/pause"), None);
    assert_eq!(r.json()["state"], "paused");
    let r = client.request("POST", &format!("/v1/jobs/{c}/pause"), None);
    assert_eq!(
        (r.status, r.api_error().code.as_str()),
        (409, "wrong_state")
    );
    // Pause b: its tasks are skipped while paused, leased again once resumed.
    assert_eq!(
        client
            .request("POST", &format!("/v1/jobs/{b}/pause"), None)
            .status,
        200
    );
    let r = client.request("POST", &format!("/v1/jobs/{a}/pause"), None);
    assert_eq!(r.status, 200);
    assert!(w.lease().is_none(), "paused jobs are not leased");
    assert_eq!(
        client
            .request("POST", &format!("/v1/jobs/{a}/resume"), None)
            .json()["state"],
        "running"
    );
    assert_eq!(w.lease().expect("lease after resume").job_id, a);
    assert_eq!(
        client
            .request("POST", &format!("/v1/jobs/{b}/resume"), None)
            .status,
        200
    );
    // Cancel a and b: nothing of them is leased any more.
    let r = client.request("POST", &format!("/v1/jobs/{a}/cancel"), None);
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    assert_eq!(r.json()["state"], "cancelled");
    let r = client.request("POST", &format!("/v1/jobs/{a}/cancel"), None);
    assert_eq!(r.status, 409);
    assert_eq!(r.api_error().code, "not_running");
    let r = client.request("POST", &format!("/v1/jobs/{b}/cancel"), None);
    assert_eq!(r.status, 200);
    assert!(
        w.lease().is_none(),
        "a cancelled job's tasks are not leased"
    );
    let r = client.request("GET", &format!("/v1/jobs/{b}/image.exr"), None);
    assert_eq!(r.status, 409);
    assert_eq!(r.api_error().code, "no_output");
}

#[test]
fn retry_cap_fails_the_job_and_a_failing_worker_is_blocked_for_it() {
    let farm = Farm::start_with(Backend::Sqlite, |cfg| {
        cfg.max_attempts = 3;
        cfg.max_worker_failures = 2;
    });
    let client = &farm.client;
    let job = client.submit(&small_spec(1));
    let x = FakeWorker::register(&farm.url(), WAIT_MS);
    let y = FakeWorker::register(&farm.url(), WAIT_MS);
    let fail = |w: &FakeWorker, l: &TaskLease| w.fail(l, "boom");
    let l1 = x.lease().expect("lease");
    fail(&x, &l1);
    let l2 = x.lease().expect("lease");
    assert_eq!((l2.task_id, l2.attempt), (l1.task_id, 2));
    fail(&x, &l2);
    // x failed twice on this job: it is blocked for it, y is not.
    assert!(x.lease().is_none(), "blocked worker got a lease");
    let l3 = y.lease().expect("lease");
    assert_eq!((l3.task_id, l3.attempt), (l1.task_id, 3));
    fail(&y, &l3);
    let st = client.status(job);
    assert_eq!(st.state, JobState::Failed);
    assert!(
        st.error.as_deref().unwrap_or("").contains("retry cap"),
        "{st:?}"
    );
    // A failed job is not leased; its outputs are refused with a reason.
    assert!(y.lease().is_none());
    let r = client.request("GET", &format!("/v1/jobs/{job}/stats.json"), None);
    assert_eq!(r.status, 409);
}

#[test]
fn health_metrics_openapi_and_docs_are_served() {
    let farm = Farm::start(Backend::Postgres);
    farm.client.submit(&small_spec(1));
    let anon = Client::with_token(&farm.url(), None);
    let r = anon.request("GET", "/healthz", None);
    assert_eq!((r.status, r.json()["status"].as_str()), (200, Some("ok")));
    let r = anon.request("GET", "/metrics", None);
    assert_eq!(r.status, 200);
    let text = String::from_utf8(r.body).expect("utf8");
    assert!(text.contains("cvfarm_tasks{state=\"pending\"} 4"), "{text}");
    assert!(text.contains("cvfarm_jobs{state=\"running\"} 1"), "{text}");
    let api = anon.request("GET", "/openapi.json", None).json();
    assert_eq!(api["openapi"], "3.1.0");
    assert!(api["paths"]["/v1/jobs"]["post"].is_object());
    let r = anon.request("GET", "/docs", None);
    assert_eq!(r.status, 200);
    assert!(String::from_utf8_lossy(&r.body).contains("/v1/workers/lease"));
}
