//! Helpers of the end-to-end tests (`tests/tests/farm_*.rs`): a real coordinator and real
//! workers on loopback, each in **its own tokio runtime** so that a test can kill one
//! abruptly (dropping the runtime stops every task and connection of that process-like
//! unit at once, as SIGKILL would, without a graceful shutdown).
//!
//! - [`TestDb`]: a fresh SQLite directory or a fresh PostgreSQL database per test (dropped
//!   afterwards). PostgreSQL comes from `CVFARM_TEST_PG` (admin URL), default
//!   `postgres://postgres@127.0.0.1:5432/postgres`; if it does not answer, the test FAILS.
//! - [`Coordinator`]: `coordinator::App` served on a port; [`Coordinator::kill`] and
//!   [`Coordinator::restart`] (same port, same store).
//! - [`Worker`]: `worker::run` in its own runtime; [`Worker::stop`] (graceful) and
//!   [`Worker::kill`].
//! - [`Client`]: one method per endpoint, JSON errors decoded.
//! - [`Farm`]: the usual start of a test (a fresh store, a coordinator on it, a client) and
//!   [`Farm::finish`] (real workers run a submitted job to `done`).
//! - [`FakeWorker`]: a worker driven by hand through raw HTTP; [`tile_header`] and
//!   [`blank_result`] build the frames it uploads.
//! - [`local_exr`], [`local_scene`], [`film_exr`], [`prepared`]: the in-process references.

use std::path::PathBuf;
use std::time::{Duration, Instant};

use protocol::frame::PixelRecord;
use protocol::lease::{JobState, JobStatus, TaskLease};
use protocol::{ApiErrorBody, TileResult};
use sqlx::Connection;

/// Client token used by every test farm.
pub const CLIENT_TOKEN: &str = "test-client-token";
/// Enrollment token used by every test farm.
pub const ENROLL_TOKEN: &str = "test-enroll-token";

fn unique(prefix: &str) -> String {
    format!(
        "{prefix}{}_{:08x}",
        std::process::id(),
        rand::random::<u32>()
    )
}

/// The backend of a test.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Backend {
    /// SQLite file in a temporary directory.
    Sqlite,
    /// A fresh PostgreSQL database.
    Postgres,
}

/// A fresh store for one test; removed on drop.
#[derive(Debug)]
pub struct TestDb {
    /// Temporary data directory (SQLite file lives here).
    pub data_dir: PathBuf,
    /// `Some(url)` for PostgreSQL.
    pub url: Option<String>,
    pg: Option<(String, String)>,
}

/// The admin URL of the test PostgreSQL server.
pub fn pg_admin_url() -> String {
    std::env::var("CVFARM_TEST_PG")
        .unwrap_or_else(|_| "postgres://postgres@127.0.0.1:5432/postgres".into())
}

fn block_on<F: std::future::Future>(f: F) -> F::Output {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .expect("runtime")
        .block_on(f)
}

impl TestDb {
    /// Creates the store. Panics (fails the test) when PostgreSQL is requested but not answering.
    pub fn new(backend: Backend) -> Self {
        let data_dir = std::env::temp_dir().join(unique("cvfarm_e2e_"));
        std::fs::create_dir_all(&data_dir).expect("temp dir");
        match backend {
            Backend::Sqlite => Self {
                data_dir,
                url: None,
                pg: None,
            },
            Backend::Postgres => {
                let admin = pg_admin_url();
                let name = unique("cvfarm_t_");
                block_on(async {
                    let mut c = sqlx::PgConnection::connect(&admin)
                        .await
                        .unwrap_or_else(|e| panic!("PostgreSQL at {admin} is required by this test and did not answer: {e}"));
                    sqlx::query(&format!("CREATE DATABASE {name}"))
                        .execute(&mut c)
                        .await
                        .expect("create database");
                });
                let base = admin
                    .rsplit_once('/')
                    .map(|(b, _)| b.to_owned())
                    .unwrap_or(admin.clone());
                let url = format!("{base}/{name}");
                Self {
                    data_dir,
                    url: Some(url),
                    pg: Some((admin, name)),
                }
            }
        }
    }

    /// A coordinator config for this store with test-friendly timings.
    pub fn config(&self) -> coordinator::Config {
        let mut c = coordinator::Config::new(CLIENT_TOKEN, ENROLL_TOKEN);
        c.database_url = self.url.clone();
        c.data_dir = self.data_dir.clone();
        c.reaper_interval_ms = 200;
        c.long_poll_max_ms = 2_000;
        c
    }
}

impl Drop for TestDb {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.data_dir);
        if let Some((admin, name)) = self.pg.take() {
            block_on(async {
                if let Ok(mut c) = sqlx::PgConnection::connect(&admin).await {
                    let _ = sqlx::query(&format!("DROP DATABASE IF EXISTS {name} WITH (FORCE)"))
                        .execute(&mut c)
                        .await;
                }
            });
        }
    }
}

/// A coordinator in its own runtime.
pub struct Coordinator {
    runtime: Option<tokio::runtime::Runtime>,
    /// Bound address.
    pub addr: std::net::SocketAddr,
    /// The store the coordinator uses (shared, for assertions).
    pub state: std::sync::Arc<coordinator::AppState>,
    config: coordinator::Config,
}

impl Coordinator {
    /// Starts on an ephemeral port.
    pub fn start(config: coordinator::Config) -> Self {
        Self::start_on(config, "127.0.0.1:0".parse().expect("addr"))
    }

    /// Starts on a given address (retrying the bind for a few seconds).
    pub fn start_on(config: coordinator::Config, addr: std::net::SocketAddr) -> Self {
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_all()
            .build()
            .expect("runtime");
        let (addr, state) = runtime.block_on(async {
            let app = coordinator::App::build(config.clone())
                .await
                .expect("coordinator builds");
            let state = app.state();
            // The port of a killed coordinator can take a moment to be free again.
            let mut tries = 0;
            let listener = loop {
                match tokio::net::TcpListener::bind(addr).await {
                    Ok(l) => break l,
                    Err(e) if tries < 50 => {
                        tries += 1;
                        let _ = e;
                        tokio::time::sleep(Duration::from_millis(100)).await;
                    }
                    Err(e) => panic!("bind {addr}: {e}"),
                }
            };
            let addr = listener.local_addr().expect("local addr");
            tokio::spawn(async move {
                let _ = app.run(listener, std::future::pending()).await;
            });
            (addr, state)
        });
        Self {
            runtime: Some(runtime),
            addr,
            state,
            config,
        }
    }

    /// Base URL.
    pub fn url(&self) -> String {
        format!("http://{}", self.addr)
    }

    /// Kills it abruptly: every task and connection stops, nothing is flushed.
    pub fn kill(&mut self) {
        if let Some(rt) = self.runtime.take() {
            rt.shutdown_background();
        }
    }

    /// Kills it and starts a new one on the same port with the same store.
    pub fn restart(&mut self) {
        self.kill();
        let next = Self::start_on(self.config.clone(), self.addr);
        *self = next;
    }

    /// Runs a future on the coordinator's runtime (store queries in assertions).
    pub fn block_on<F: std::future::Future>(&self, f: F) -> F::Output {
        self.runtime
            .as_ref()
            .expect("coordinator running")
            .block_on(f)
    }
}

impl Drop for Coordinator {
    fn drop(&mut self) {
        self.kill();
    }
}

/// A worker in its own runtime.
pub struct Worker {
    runtime: Option<tokio::runtime::Runtime>,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    done: Option<std::sync::mpsc::Receiver<Result<worker::WorkerSummary, String>>>,
}

impl Worker {
    /// Starts a worker with one slot against `url`.
    pub fn start(url: &str, name: &str) -> Self {
        Self::start_slots(url, name, 1)
    }

    /// Starts a worker with `slots` slots against `url` (test timings: 1 s long polls,
    /// 500 ms back-off cap).
    pub fn start_slots(url: &str, name: &str, slots: usize) -> Self {
        let mut cfg = worker::WorkerConfig::new(url, ENROLL_TOKEN);
        cfg.name = name.into();
        cfg.slots = slots;
        cfg.poll_wait_ms = 1_000;
        cfg.max_backoff_ms = 500;
        Self::start_with(cfg)
    }

    /// Starts a worker with an explicit config.
    pub fn start_with(cfg: worker::WorkerConfig) -> Self {
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .enable_all()
            .build()
            .expect("runtime");
        let (stop_tx, stop_rx) = tokio::sync::oneshot::channel::<()>();
        let (done_tx, done_rx) = std::sync::mpsc::channel();
        runtime.spawn(async move {
            let r = worker::run(cfg, async move {
                let _ = stop_rx.await;
            })
            .await
            .map_err(|e| e.to_string());
            let _ = done_tx.send(r);
        });
        Self {
            runtime: Some(runtime),
            stop: Some(stop_tx),
            done: Some(done_rx),
        }
    }

    /// Graceful stop: waits for the worker to finish its task in hand.
    pub fn stop(mut self) -> worker::WorkerSummary {
        if let Some(s) = self.stop.take() {
            let _ = s.send(());
        }
        let r = self
            .done
            .take()
            .expect("running")
            .recv_timeout(Duration::from_secs(60))
            .expect("worker stops");
        r.expect("worker ran without a fatal error")
    }

    /// Kills it abruptly (no release, no upload, no more heartbeats).
    pub fn kill(&mut self) {
        if let Some(rt) = self.runtime.take() {
            rt.shutdown_background();
        }
    }
}

impl Drop for Worker {
    fn drop(&mut self) {
        self.kill();
    }
}

/// A response: status and body bytes.
#[derive(Debug)]
pub struct Resp {
    /// HTTP status.
    pub status: u16,
    /// Body.
    pub body: Vec<u8>,
}

impl Resp {
    /// The body as JSON.
    pub fn json(&self) -> serde_json::Value {
        serde_json::from_slice(&self.body).unwrap_or_else(|e| {
            panic!(
                "body is not JSON ({e}): {}",
                String::from_utf8_lossy(&self.body)
            )
        })
    }

    /// The body as an API error (panics if it is not one).
    pub fn api_error(&self) -> protocol::ApiError {
        let b: ApiErrorBody = serde_json::from_slice(&self.body).unwrap_or_else(|e| {
            panic!(
                "not an API error body ({e}): {}",
                String::from_utf8_lossy(&self.body)
            )
        });
        b.error
    }
}

/// A blocking HTTP client for the farm API.
pub struct Client {
    base: String,
    token: Option<String>,
    rt: tokio::runtime::Runtime,
    http: reqwest::Client,
}

impl Client {
    /// A client with the test client token.
    pub fn new(base: &str) -> Self {
        Self::with_token(base, Some(CLIENT_TOKEN))
    }

    /// A client with any (or no) token.
    pub fn with_token(base: &str, token: Option<&str>) -> Self {
        Self {
            base: base.trim_end_matches('/').to_owned(),
            token: token.map(str::to_owned),
            rt: tokio::runtime::Builder::new_current_thread()
                .enable_all()
                .build()
                .expect("runtime"),
            http: reqwest::Client::new(),
        }
    }

    /// A raw request.
    pub fn request(&self, method: &str, path: &str, body: Option<Vec<u8>>) -> Resp {
        let url = format!("{}{}", self.base, path);
        self.rt.block_on(async {
            let mut rb = self.http.request(method.parse().expect("method"), url);
            if let Some(t) = &self.token {
                rb = rb.bearer_auth(t);
            }
            if let Some(b) = body {
                rb = rb.body(b);
            }
            let r = rb.send().await.expect("request sent");
            let status = r.status().as_u16();
            Resp {
                status,
                body: r.bytes().await.expect("body").to_vec(),
            }
        })
    }

    /// `POST /v1/jobs` with a raw body.
    pub fn submit_raw(&self, body: &[u8]) -> Resp {
        self.request("POST", "/v1/jobs", Some(body.to_vec()))
    }

    /// `POST /v1/jobs`; panics unless 201; returns the job id.
    pub fn submit(&self, spec: &serde_json::Value) -> i64 {
        let r = self.submit_raw(&serde_json::to_vec(spec).expect("json"));
        assert_eq!(
            r.status,
            201,
            "submit failed: {}",
            String::from_utf8_lossy(&r.body)
        );
        r.json()["job_id"].as_i64().expect("job_id")
    }

    /// `PUT /v1/assets/{sha256}`; returns the address.
    pub fn upload_asset(&self, bytes: &[u8]) -> String {
        let hash = protocol::hash::sha256_hex(bytes);
        let r = self.request("PUT", &format!("/v1/assets/{hash}"), Some(bytes.to_vec()));
        assert_eq!(
            r.status,
            201,
            "asset upload failed: {}",
            String::from_utf8_lossy(&r.body)
        );
        hash
    }

    /// `GET /v1/jobs/{id}`.
    pub fn status(&self, id: i64) -> JobStatus {
        let r = self.request("GET", &format!("/v1/jobs/{id}"), None);
        assert_eq!(
            r.status,
            200,
            "status failed: {}",
            String::from_utf8_lossy(&r.body)
        );
        serde_json::from_slice(&r.body).expect("JobStatus")
    }

    /// Polls until the job leaves `running` (panics after `timeout`).
    pub fn wait(&self, id: i64, timeout: Duration) -> JobStatus {
        let start = Instant::now();
        loop {
            let s = self.status(id);
            if !matches!(s.state, JobState::Running | JobState::Paused) {
                return s;
            }
            assert!(
                start.elapsed() < timeout,
                "job {id} did not finish in {timeout:?}: {s:?}"
            );
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    /// [`Client::wait`], then asserts the job ended `done`.
    pub fn wait_done(&self, id: i64, timeout: Duration) -> JobStatus {
        let status = self.wait(id, timeout);
        assert_eq!(status.state, JobState::Done, "{status:?}");
        status
    }

    /// `GET /v1/jobs/{id}/stats.json`, parsed.
    pub fn stats(&self, id: i64) -> serde_json::Value {
        serde_json::from_slice(&self.download(id, "stats.json")).expect("stats")
    }

    /// `GET /v1/jobs/{id}/{name}` of a UTF-8 output (`convergence.csv`).
    pub fn download_text(&self, id: i64, name: &str) -> String {
        String::from_utf8(self.download(id, name)).expect("utf-8")
    }

    /// `GET /v1/jobs/{id}/{name}`; panics unless 200.
    pub fn download(&self, id: i64, name: &str) -> Vec<u8> {
        let r = self.request("GET", &format!("/v1/jobs/{id}/{name}"), None);
        assert_eq!(
            r.status,
            200,
            "download {name} failed: {}",
            String::from_utf8_lossy(&r.body)
        );
        r.body
    }
}

/// Two `#[test]`s running `body(Backend)`: `$sqlite` on SQLite, `$postgres` on PostgreSQL.
///
/// ```ignore
/// e2e::backend_tests!(convergence: convergence_sqlite, convergence_postgres);
/// ```
#[macro_export]
macro_rules! backend_tests {
    ($body:ident: $sqlite:ident, $postgres:ident) => {
        #[test]
        fn $sqlite() {
            $body($crate::Backend::Sqlite);
        }

        #[test]
        fn $postgres() {
            $body($crate::Backend::Postgres);
        }
    };
}

/// Starts `n` workers named `w0`, `w1`, … against `url`.
pub fn start_workers(url: &str, n: usize) -> Vec<Worker> {
    (0..n)
        .map(|i| Worker::start(url, &format!("w{i}")))
        .collect()
}

/// Stops every worker gracefully.
pub fn stop_workers(workers: Vec<Worker>) {
    for w in workers {
        w.stop();
    }
}

/// A test farm: a fresh store, a coordinator on it and a client of it. Fields drop in
/// order: the coordinator stops before its store is removed.
pub struct Farm {
    /// The coordinator.
    pub coord: Coordinator,
    /// A client with the client token.
    pub client: Client,
    /// The store.
    pub db: TestDb,
}

impl Farm {
    /// A farm with the test config of [`TestDb::config`].
    pub fn start(backend: Backend) -> Self {
        Self::start_with(backend, |_| {})
    }

    /// A farm whose config `tune` adjusts first.
    pub fn start_with(backend: Backend, tune: impl FnOnce(&mut coordinator::Config)) -> Self {
        let db = TestDb::new(backend);
        let mut cfg = db.config();
        tune(&mut cfg);
        let coord = Coordinator::start(cfg);
        let client = Client::new(&coord.url());
        Self { coord, client, db }
    }

    /// The coordinator's base URL.
    pub fn url(&self) -> String {
        self.coord.url()
    }

    /// [`Coordinator::restart`], with a fresh client (the old one's pooled connection died
    /// with the coordinator).
    pub fn restart(&mut self) {
        self.coord.restart();
        self.client = Client::new(&self.coord.url());
    }

    /// Runs job `id` on `workers` fresh workers until it ends (asserting `done`), then
    /// stops them.
    pub fn finish(&self, id: i64, workers: usize, timeout: Duration) -> JobStatus {
        let ws = start_workers(&self.url(), workers);
        let status = self.client.wait_done(id, timeout);
        stop_workers(ws);
        status
    }
}

/// A job run by two coordinators sharing one PostgreSQL database: see [`run_on_two_coordinators`].
pub struct SharedRun {
    /// The final status, read from coordinator B.
    pub status: JobStatus,
    /// The summaries of the worker of A and the worker of B.
    pub workers: [worker::WorkerSummary; 2],
    /// `image.exr`, downloaded from coordinator A.
    pub exr: Vec<u8>,
}

/// Two coordinators A and B on one fresh PostgreSQL database and one worker on each:
/// `spec` is submitted to A, its end awaited on B (asserted `done`), the workers stopped
/// and the image downloaded from A.
pub fn run_on_two_coordinators(spec: &serde_json::Value, timeout: Duration) -> SharedRun {
    let db = TestDb::new(Backend::Postgres);
    let a = Coordinator::start(db.config());
    let b = Coordinator::start(db.config());
    let id = Client::new(&a.url()).submit(spec);
    let wa = Worker::start(&a.url(), "wa");
    let wb = Worker::start(&b.url(), "wb");
    let status = Client::new(&b.url()).wait_done(id, timeout);
    let workers = [wa.stop(), wb.stop()];
    let exr = Client::new(&a.url()).download(id, "image.exr");
    SharedRun {
        status,
        workers,
        exr,
    }
}

/// A worker driven by hand through raw HTTP (registered with the enrollment token).
pub struct FakeWorker {
    /// A client with the worker's token.
    pub c: Client,
    wait_ms: u64,
}

impl FakeWorker {
    /// Registers as `fake`; its leases long-poll for `wait_ms`.
    pub fn register(url: &str, wait_ms: u64) -> Self {
        let enrol = Client::with_token(url, Some(ENROLL_TOKEN));
        let r = enrol.request(
            "POST",
            "/v1/workers/register",
            Some(br#"{"name":"fake"}"#.to_vec()),
        );
        assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
        let token = r.json()["token"].as_str().expect("token").to_owned();
        Self {
            c: Client::with_token(url, Some(&token)),
            wait_ms,
        }
    }

    /// `POST /v1/workers/lease`: `Some` on 200, `None` on 204; panics otherwise.
    pub fn lease(&self) -> Option<TaskLease> {
        let body = serde_json::json!({ "wait_ms": self.wait_ms });
        let r = self.c.request(
            "POST",
            "/v1/workers/lease",
            Some(serde_json::to_vec(&body).expect("json")),
        );
        match r.status {
            200 => Some(serde_json::from_slice(&r.body).expect("lease")),
            204 => None,
            s => panic!("lease: {s} {}", String::from_utf8_lossy(&r.body)),
        }
    }

    /// `PUT /v1/tasks/{task}/result?attempt={attempt}`.
    pub fn upload(&self, task: i64, attempt: u32, body: Vec<u8>) -> Resp {
        self.c.request(
            "PUT",
            &format!("/v1/tasks/{task}/result?attempt={attempt}"),
            Some(body),
        )
    }

    /// `POST /v1/tasks/{task}/heartbeat?attempt={attempt}`.
    pub fn heartbeat(&self, task: i64, attempt: u32) -> Resp {
        self.c.request(
            "POST",
            &format!("/v1/tasks/{task}/heartbeat?attempt={attempt}"),
            None,
        )
    }

    /// `POST /v1/tasks/{id}/fail?attempt={attempt}` of a lease; panics unless 200.
    pub fn fail(&self, l: &TaskLease, reason: &str) {
        let r = self.c.request(
            "POST",
            &format!("/v1/tasks/{}/fail?attempt={}", l.task_id, l.attempt),
            Some(reason.as_bytes().to_vec()),
        );
        assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    }
}

/// A result of a lease's tile with every pixel equal to `pixel` and no cells.
pub fn blank_result(l: &TaskLease, pixel: PixelRecord) -> TileResult {
    TileResult {
        header: l.tile_header(),
        pixels: vec![pixel; l.rect.pixel_count()],
        cells: vec![],
    }
}

/// A worker's `Prepared` scene of an inline scene without assets.
pub fn prepared(
    scene: &serde_json::Value,
    job: &protocol::job::ResolvedJob,
    estimator: &protocol::job::EstimatorSpec,
) -> worker::tile::Prepared {
    worker::tile::Prepared::new(
        &serde_json::to_vec(scene).expect("json"),
        std::collections::BTreeMap::new(),
        job,
        estimator,
    )
    .expect("prepare")
}

/// Path of a file in the repository's `scenes/` directory.
pub fn scene_path(rel: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("..")
        .join("scenes")
        .join(rel)
}

/// A shipped scene's JSON.
pub fn scene_json(rel: &str) -> serde_json::Value {
    let text = std::fs::read_to_string(scene_path(rel)).expect("scene file");
    serde_json::from_str(&text).expect("scene JSON")
}

/// The scene of a job as the in-process references render it (scene + assets, the job's
/// resolution) and the job's render settings (the scene's default estimator).
pub fn local_scene(
    scene: &serde_json::Value,
    assets: &[(&str, Vec<u8>)],
    job: &protocol::job::ResolvedJob,
) -> (scene::LoadedScene, render::integrator::RenderSettings) {
    let desc: scene::SceneDesc = serde_json::from_value(scene.clone()).expect("scene desc");
    let mut mem = scene::MemoryAssets::new();
    for (n, b) in assets {
        mem.insert(n, b.clone()).expect("asset");
    }
    let mut loaded = scene::load(&desc, &mem).expect("scene loads");
    loaded.scene.film.width = job.width;
    loaded.scene.film.height = job.height;
    let settings = render::integrator::RenderSettings {
        spp: job.spp,
        seed: job.seed,
        max_depth: job.max_depth,
        rr_depth: job.rr_depth,
        hide_emitters: job.hide_emitters,
        ..render::integrator::RenderSettings::from_scene(&loaded.scene)
    };
    (loaded, settings)
}

/// Render options of the in-process references (the image does not depend on them).
pub fn local_options() -> render::tile::RenderOptions {
    render::tile::RenderOptions {
        tile_size: 8,
        threads: 2,
    }
}

/// The EXR of a film's layers at the job's resolution.
pub fn film_exr(film: &render::film::Film, job: &protocol::job::ResolvedJob) -> Vec<u8> {
    let layers: Vec<imageio::RgbLayer> = film
        .layers()
        .into_iter()
        .map(|l| imageio::RgbLayer {
            name: l.name.to_owned(),
            data: l.data,
        })
        .collect();
    imageio::encode_exr(job.width, job.height, &layers).expect("exr")
}

/// The EXR an in-process `render::tile::render_image` produces for the same job (the
/// reference the farm must equal bit for bit): scene + overrides, film layers, `imageio`.
pub fn local_exr(
    scene: &serde_json::Value,
    assets: &[(&str, Vec<u8>)],
    job: &protocol::job::ResolvedJob,
) -> Vec<u8> {
    let (loaded, settings) = local_scene(scene, assets, job);
    let rs = render::integrator::RenderScene::new(&loaded.scene, &settings).expect("prepare");
    let (film, _) =
        render::tile::render_image(&rs, &settings, &local_options(), &|_, _| {}).expect("render");
    film_exr(&film, job)
}
