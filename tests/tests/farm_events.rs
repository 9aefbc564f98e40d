//! Observing jobs: the `/v1/events` Server-Sent Events stream (job states, phases, progress,
//! the `?job=` filter, `Last-Event-ID` resumption, tokens, shutdown) and
//! `/v1/jobs/{id}/convergence.csv`; on SQLite and on PostgreSQL.

use std::sync::mpsc;
use std::time::{Duration, Instant};

use e2e::{Backend, CLIENT_TOKEN, Client, Coordinator, Farm, TestDb, Worker, scene_json};

/// One received event.
#[derive(Clone, Debug)]
struct SseEvent {
    kind: String,
    id: u64,
    data: serde_json::Value,
}

impl SseEvent {
    fn job(&self) -> i64 {
        self.data["job"].as_i64().expect("event names its job")
    }
}

/// A Server-Sent Events client on its own thread (reqwest streaming the body chunk by chunk),
/// parsing `event:`/`id:`/`data:` lines into [`SseEvent`]s.
struct SseStream {
    rx: mpsc::Receiver<Option<SseEvent>>,
}

impl SseStream {
    /// Opens `path`; panics unless the answer is 200 `text/event-stream`.
    fn open(base: &str, path: &str, last_event_id: Option<u64>) -> Self {
        let url = format!("{base}{path}");
        let (tx, rx) = mpsc::channel();
        let (ready_tx, ready_rx) = mpsc::channel();
        std::thread::spawn(move || {
            let rt = tokio::runtime::Builder::new_current_thread()
                .enable_all()
                .build()
                .expect("runtime");
            rt.block_on(async move {
                let mut rb = reqwest::Client::new().get(url).bearer_auth(CLIENT_TOKEN);
                if let Some(id) = last_event_id {
                    rb = rb.header("Last-Event-ID", id.to_string());
                }
                let mut resp = rb.send().await.expect("events request");
                let ctype = resp
                    .headers()
                    .get("content-type")
                    .and_then(|v| v.to_str().ok())
                    .unwrap_or("")
                    .to_owned();
                let _ = ready_tx.send((resp.status().as_u16(), ctype));
                let (mut buf, mut kind, mut id, mut data) =
                    (String::new(), String::new(), 0u64, String::new());
                while let Ok(Some(chunk)) = resp.chunk().await {
                    buf.push_str(&String::from_utf8_lossy(&chunk));
                    while let Some(nl) = buf.find('\n') {
                        let line = buf[..nl].trim_end_matches('\r').to_owned();
                        buf.drain(..=nl);
                        if line.is_empty() {
                            if !data.is_empty() {
                                let ev = SseEvent {
                                    kind: std::mem::take(&mut kind),
                                    id,
                                    data: serde_json::from_str(&data).expect("event data is JSON"),
                                };
                                data.clear();
                                if tx.send(Some(ev)).is_err() {
                                    return;
                                }
                            }
                        } else if let Some(v) = line.strip_prefix("event:") {
                            kind = v.trim().to_owned();
                        } else if let Some(v) = line.strip_prefix("id:") {
                            id = v.trim().parse().expect("numeric event id");
                        } else if let Some(v) = line.strip_prefix("data:") {
                            data.push_str(v.trim_start());
                        }
                    }
                }
                // The stream ended.
                let _ = tx.send(None);
            });
        });
        let (status, ctype) = ready_rx
            .recv_timeout(Duration::from_secs(30))
            .expect("events answered");
        assert_eq!(status, 200, "events: status {status}");
        assert!(ctype.starts_with("text/event-stream"), "{ctype}");
        Self { rx }
    }

    /// Events until `stop` returns true for one (inclusive); panics after `timeout`.
    fn until(&self, timeout: Duration, stop: impl Fn(&SseEvent) -> bool) -> Vec<SseEvent> {
        let start = Instant::now();
        let mut out = Vec::new();
        loop {
            let left = timeout.saturating_sub(start.elapsed());
            match self.rx.recv_timeout(left) {
                Ok(Some(e)) => {
                    let done = stop(&e);
                    out.push(e);
                    if done {
                        return out;
                    }
                }
                Ok(None) => panic!("stream ended early after {out:?}"),
                Err(_) => panic!("no stopping event within {timeout:?}; got {out:?}"),
            }
        }
    }
}

fn spec(res: u32, spp: u32, per_task: u32) -> serde_json::Value {
    serde_json::json!({
        "scene": { "inline": scene_json("cornell-box/scene.json") },
        "estimator": { "kind": "path" },
        "resolution": [res, res],
        "spp": spp,
        "tile_size": 8,
        "samples_per_task": per_task,
        "seed": 5,
    })
}

/// The data rows of a `convergence.csv` (header skipped), as numbers.
fn csv_rows(csv: &str) -> Vec<Vec<f64>> {
    csv.lines()
        .skip(1)
        .map(|l| l.split(',').map(|x| x.parse().expect("number")).collect())
        .collect()
}

fn is_end(e: &SseEvent, job: i64) -> bool {
    e.kind == "job" && e.job() == job && e.data["state"] != "running" && e.data["state"] != "paused"
}

fn events_follow_jobs(backend: Backend) {
    let farm = Farm::start(backend);
    let (coord, client) = (&farm.coord, &farm.client);
    // Two jobs queued before any worker; one stream for all jobs, one for job b only.
    let a = client.submit(&spec(16, 4, 2));
    let b = client.submit(&spec(16, 4, 2));
    let all = SseStream::open(&coord.url(), "/v1/events", None);
    let only_b = SseStream::open(&coord.url(), &format!("/v1/events?job={b}"), None);
    let w = Worker::start(&coord.url(), "w");

    let seen_b = only_b.until(Duration::from_secs(120), |e| is_end(e, b));
    let done = std::cell::Cell::new(0);
    let seen_all = all.until(Duration::from_secs(120), |e| {
        if is_end(e, a) || is_end(e, b) {
            done.set(done.get() + 1);
        }
        done.get() == 2
    });
    w.stop();

    // The filter: job b only.
    assert!(seen_b.iter().all(|e| e.job() == b), "{seen_b:?}");
    for (seen, jobs) in [(&seen_b, vec![b]), (&seen_all, vec![a, b])] {
        // Ids strictly increase within a stream.
        assert!(seen.windows(2).all(|w| w[1].id > w[0].id), "{seen:?}");
        for job in jobs {
            let of: Vec<&SseEvent> = seen.iter().filter(|e| e.job() == job).collect();
            let states: Vec<&str> = of
                .iter()
                .filter(|e| e.kind == "job")
                .map(|e| e.data["state"].as_str().expect("state"))
                .collect();
            assert_eq!(states, ["running", "done"], "job {job}: {of:?}");
            let progress: Vec<&&SseEvent> = of.iter().filter(|e| e.kind == "progress").collect();
            let last = progress.last().expect("progress events");
            assert_eq!(
                last.data["tasks_done"], last.data["tasks_total"],
                "{last:?}"
            );
            assert_eq!(last.data["tasks_total"].as_u64(), Some(8), "{last:?}");
            assert!(
                of.iter().any(|e| e.kind == "phase"
                    && e.data["phase"] == "render"
                    && e.data["started_ms"].is_i64()),
                "job {job}: no phase-started event: {of:?}"
            );
            // The running report comes first, the end last.
            assert_eq!(of.first().map(|e| e.kind.as_str()), Some("job"));
            assert!(is_end(of.last().expect("events"), job));
        }
    }

    // Resuming after the first event of b's stream reports b's end again, with a larger id.
    let first = seen_b[0].id;
    let resumed = SseStream::open(&coord.url(), &format!("/v1/events?job={b}"), Some(first));
    let again = resumed.until(Duration::from_secs(30), |e| is_end(e, b));
    assert!(again.iter().all(|e| e.id > first), "{again:?}");
    // A fresh stream does not replay jobs that ended before it opened.
    let fresh = SseStream::open(&coord.url(), "/v1/events", None);
    assert!(
        fresh.rx.recv_timeout(Duration::from_millis(1500)).is_err(),
        "a fresh stream replayed an ended job"
    );
}

e2e::backend_tests!(events_follow_jobs: events_follow_jobs_from_running_to_done_sqlite, events_follow_jobs_from_running_to_done_postgres);

#[test]
fn events_reject_bad_tokens_unknown_jobs_and_bad_ids() {
    let db = TestDb::new(Backend::Sqlite);
    let coord = Coordinator::start(db.config());
    for token in [None, Some("wrong-token")] {
        let r = Client::with_token(&coord.url(), token).request("GET", "/v1/events", None);
        assert_eq!(r.status, 401);
        assert_eq!(r.api_error().code, "unauthorized");
    }
    let client = Client::new(&coord.url());
    let r = client.request("GET", "/v1/events?job=999", None);
    assert_eq!(r.status, 404);
    assert_eq!(r.api_error().code, "not_found");
    let r = client.request("GET", "/v1/events?job=x", None);
    assert_eq!(r.status, 400);
    assert_eq!(r.api_error().code, "invalid_query");
    // The largest id a client can send: the stream still serves (ids saturate).
    let id = client.submit(&spec(16, 4, 4));
    let s = SseStream::open(&coord.url(), "/v1/events", Some(u64::MAX));
    let got = s.until(Duration::from_secs(30), |e| e.kind == "job");
    assert_eq!(got[0].job(), id);
    let r = client.request("GET", "/v1/jobs/999/convergence.csv", None);
    assert_eq!(r.status, 404);
    assert_eq!(r.api_error().code, "not_found");
    let r = Client::with_token(&coord.url(), Some("wrong-token")).request(
        "GET",
        "/v1/jobs/1/convergence.csv",
        None,
    );
    assert_eq!(r.status, 401);
}

fn convergence(backend: Backend) {
    let farm = Farm::start(backend);
    let client = &farm.client;
    // 4 tiles × 4 sample ranges of 2: 4 rounds.
    let id = client.submit(&spec(16, 8, 2));
    // Before any worker: a running job has a series with no completed round yet.
    let early = client.download_text(id, "convergence.csv");
    assert_eq!(early, "seconds,spp,rel_mse_est,tasks_done\n");
    farm.finish(id, 1, Duration::from_secs(120));
    let csv = client.download_text(id, "convergence.csv");
    assert_eq!(
        csv.lines().next(),
        Some("seconds,spp,rel_mse_est,tasks_done")
    );
    let rows = csv_rows(&csv);
    assert_eq!(rows.len(), 4, "{csv}");
    assert!(rows.iter().all(|r| r.len() == 4), "{csv}");
    for w in rows.windows(2) {
        assert!(w[1][1] > w[0][1], "spp must increase: {csv}");
        assert!(w[1][0] >= w[0][0], "time must not decrease: {csv}");
        assert!(w[1][3] > w[0][3], "tasks must increase: {csv}");
    }
    let last = rows.last().expect("rows");
    let stats = client.stats(id);
    assert_eq!(last[1], 8.0);
    assert_eq!(last[3], 16.0);
    // Merged in the canonical order finish uses: the very same estimate.
    assert_eq!(
        Some(last[2]),
        stats["estimated_rel_mse"].as_f64(),
        "{csv}\n{stats}"
    );
    assert!(last[0] <= stats["total_seconds"].as_f64().expect("total") + 1e-9);
}

e2e::backend_tests!(convergence: convergence_csv_has_one_row_per_round_sqlite, convergence_csv_has_one_row_per_round_postgres);

/// A `cms` job: the stream reports each phase (surrogate, train, render) and the coefficient
/// table the train barrier announced, whose address is the one `/coefficients` serves; the
/// convergence series has rounds of every phase and ends at the stats.json estimate.
fn cms_events_and_convergence(backend: Backend) {
    let farm = Farm::start(backend);
    let (coord, client) = (&farm.coord, &farm.client);
    let mut s = spec(16, 24, 4);
    s["estimator"] = serde_json::json!({ "kind": "cms" });
    let id = client.submit(&s);
    let stream = SseStream::open(&coord.url(), &format!("/v1/events?job={id}"), None);
    let w = Worker::start(&coord.url(), "w");
    let seen = stream.until(Duration::from_secs(180), |e| is_end(e, id));
    w.stop();
    assert_eq!(
        seen.last().expect("events").data["state"],
        "done",
        "{seen:?}"
    );
    let coefficients = protocol::hash::sha256_hex(&client.download(id, "coefficients"));
    let announced: Vec<&SseEvent> = seen
        .iter()
        .filter(|e| e.kind == "phase" && e.data["coefficients"].is_string())
        .collect();
    assert!(!announced.is_empty(), "no coefficients announced: {seen:?}");
    assert!(
        announced
            .iter()
            .all(|e| e.data["coefficients"] == coefficients.as_str() && e.data["phase"] == "render"),
        "{announced:?}"
    );
    for phase in ["surrogate", "train", "render"] {
        assert!(
            seen.iter().any(|e| e.kind == "phase"
                && e.data["phase"] == phase
                && e.data["finished_ms"].is_i64()),
            "no finished `{phase}` phase event: {seen:?}"
        );
    }
    // One row per round: per distinct (phase, sample range) of the job's tasks.
    let rounds = coord.block_on(rounds_of(coord, id));
    assert!(rounds >= 3, "a cms job has at least one round per phase");
    let csv = client.download_text(id, "convergence.csv");
    let rows = csv_rows(&csv);
    assert_eq!(rows.len() as i64, rounds, "{csv}");
    assert!(rows.windows(2).all(|w| w[1][1] > w[0][1]), "{csv}");
    let stats = client.stats(id);
    let last = rows.last().expect("rows");
    assert_eq!(Some(last[1]), stats["spp"].as_f64(), "{csv}\n{stats}");
    assert_eq!(
        Some(last[2]),
        stats["estimated_rel_mse"].as_f64(),
        "{csv}\n{stats}"
    );
}

/// Distinct (phase, sample range) pairs of a job's tasks, read from the store.
async fn rounds_of(coord: &Coordinator, job: i64) -> i64 {
    let store = &coord.state.store;
    let mut sql = "SELECT COUNT(*) AS n FROM (SELECT DISTINCT phase_idx, sample_start, sample_end \
                   FROM tasks WHERE job_id = ?) r"
        .to_owned();
    if store.backend() == coordinator::store::Backend::Postgres {
        sql = coordinator::store::dollar_placeholders(&sql);
    }
    let row = sqlx::query(&sql)
        .bind(job)
        .fetch_one(store.pool())
        .await
        .expect("rounds query");
    sqlx::Row::try_get(&row, "n").expect("count")
}

e2e::backend_tests!(cms_events_and_convergence: cms_job_announces_coefficients_sqlite, cms_job_announces_coefficients_postgres);

/// A job whose error target is met by its first round: the later rounds are skipped, so the
/// final progress counts only the tasks that ran and the series has the one round that did.
#[test]
fn early_stopped_job_reports_only_the_rounds_it_ran() {
    let farm = Farm::start(Backend::Sqlite);
    let (coord, client) = (&farm.coord, &farm.client);
    let mut s = spec(16, 64, 4);
    s["target_rel_mse"] = serde_json::json!(1e9);
    let id = client.submit(&s);
    let stream = SseStream::open(&coord.url(), &format!("/v1/events?job={id}"), None);
    let ws = e2e::start_workers(&coord.url(), 2);
    let seen = stream.until(Duration::from_secs(120), |e| is_end(e, id));
    e2e::stop_workers(ws);
    assert_eq!(seen.last().expect("events").data["state"], "done");
    let last = seen
        .iter()
        .rfind(|e| e.kind == "progress")
        .expect("progress");
    assert_eq!(
        last.data["tasks_done"], last.data["tasks_total"],
        "{last:?}"
    );
    assert_eq!(last.data["tasks_total"].as_u64(), Some(4), "{last:?}");
    let csv = client.download_text(id, "convergence.csv");
    let rows = csv_rows(&csv);
    let stats = client.stats(id);
    assert_eq!(rows.len(), 1, "{csv}");
    assert_eq!(Some(rows[0][1]), stats["spp"].as_f64(), "{csv}\n{stats}");
    assert_eq!(rows[0][1], 4.0);
    assert_eq!(Some(rows[0][2]), stats["estimated_rel_mse"].as_f64());
}

#[test]
fn event_streams_end_when_the_coordinator_shuts_down() {
    let db = TestDb::new(Backend::Sqlite);
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .expect("runtime");
    let (stop_tx, stop_rx) = tokio::sync::oneshot::channel::<()>();
    let (url, server) = rt.block_on(async {
        let app = coordinator::App::build(db.config()).await.expect("builds");
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
            .await
            .expect("bind");
        let url = format!("http://{}", listener.local_addr().expect("addr"));
        let server = tokio::spawn(app.run(listener, async move {
            let _ = stop_rx.await;
        }));
        (url, server)
    });
    let client = Client::new(&url);
    let id = client.submit(&spec(16, 4, 4));
    let stream = SseStream::open(&url, "/v1/events", None);
    let first = stream.until(Duration::from_secs(30), |e| e.kind == "job");
    assert_eq!(first[0].job(), id);
    let _ = stop_tx.send(());
    // Graceful shutdown completes (it would hang on an endless response) and the stream ends.
    let served = rt.block_on(async { tokio::time::timeout(Duration::from_secs(30), server).await });
    assert!(
        served.is_ok(),
        "coordinator did not shut down with a stream open"
    );
    let start = Instant::now();
    loop {
        match stream.rx.recv_timeout(Duration::from_secs(30)) {
            Ok(Some(_)) => assert!(start.elapsed() < Duration::from_secs(30)),
            Ok(None) => break,
            Err(e) => panic!("stream did not end: {e}"),
        }
    }
}
