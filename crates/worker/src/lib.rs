//! The cvfarm worker: registers with a coordinator, long-polls for task leases, renders
//! each tile with `render`, uploads the [`protocol::frame`] stream, heartbeats meanwhile.
//!
//! Behaviour, in the order a task sees it:
//! 1. **Register** once with the enrollment token; the per-worker token it returns is kept in
//!    memory (a restarted worker registers again; its old leases simply expire).
//! 2. **Lease** (long poll). Network failures and 5xx answers are retried with exponential
//!    back-off (100 ms doubling up to `max_backoff_ms`); a 401 re-registers.
//! 3. **Prepare** the job once: scene document and assets are fetched by content address,
//!    verified against their SHA-256 and cached in memory; the `RenderScene` is cached per job.
//!    A CV phase's input — the surrogate image (`train`) or the coefficient table (`render`),
//!    named by content address in the lease — is fetched the same way, verified, decoded
//!    and checked against the job once, and cached with the prepared job.
//! 4. **Render** on a blocking thread while a heartbeat task extends the lease every
//!    `heartbeat_ms` (from the moment the lease arrives). Each slot renders one task at a
//!    time and keeps one more lease in hand, fetched and prepared while the current one
//!    renders, so lease and upload round trips overlap rendering. A CV task (`cms`,
//!    `per_light_cv`, `optimal_mis`) renders its tile in bands on the process's rayon pool,
//!    i.e. on every core, whatever the slot count. The result is encoded on a blocking thread
//!    after the render permit is freed. A heartbeat answered 409 means the lease was lost
//!    (expired and re-leased, or the job was cancelled): the result is dropped, not uploaded.
//! 5. **Upload** `PUT /v1/tasks/{id}/result?attempt=N`, retried on network errors (the
//!    coordinator makes a repeated upload of an accepted attempt a no-op); a result the
//!    coordinator refuses (4xx other than 409) is reported as a failed attempt.
//! 6. **Shutdown** (the future passed to [`run`] resolves, e.g. on SIGTERM/ctrl-c): no new
//!    lease is taken; a task being rendered is finished and uploaded; a lease in hand that
//!    has not started rendering (or arrives after the signal) is released.
//!
//! # Layout
//! - [`tile`]: [`tile::Prepared`] (scene + settings of a job), tile rendering, in-process job rendering.
//! - this file: [`WorkerConfig`], [`run`], the HTTP calls.

#![deny(missing_docs)]

pub mod tile;

use std::collections::{BTreeMap, HashMap};
use std::future::Future;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::Duration;

use protocol::hash::sha256_hex;
use protocol::lease::{LeaseRequest, RegisterRequest, RegisterResponse, TaskLease};
use reqwest::StatusCode;
use tokio::sync::{Mutex, Semaphore, watch};

use crate::tile::{PhaseInputs, Prepared, TaskError};

/// Worker settings (every one has a CLI flag and environment variable in `cvfarm worker`).
///
/// | field | default | meaning |
/// |---|---|---|
/// | `coordinator` | — | base URL, e.g. `http://127.0.0.1:8080` |
/// | `enrollment_token` | — | `CVFARM_WORKER_TOKEN` |
/// | `name` | host name | shown in the coordinator's logs |
/// | `slots` | cores | tasks rendered concurrently |
/// | `poll_wait_ms` | 5 000 | long-poll length |
/// | `max_backoff_ms` | 10 000 | reconnect back-off cap |
#[derive(Clone, Debug)]
pub struct WorkerConfig {
    /// Coordinator base URL.
    pub coordinator: String,
    /// Enrollment token.
    pub enrollment_token: String,
    /// Worker name.
    pub name: String,
    /// Concurrent tasks.
    pub slots: usize,
    /// Long-poll length (ms).
    pub poll_wait_ms: u64,
    /// Back-off cap (ms).
    pub max_backoff_ms: u64,
}

impl WorkerConfig {
    /// Defaults for a coordinator URL and enrollment token.
    pub fn new(coordinator: impl Into<String>, enrollment_token: impl Into<String>) -> Self {
        Self {
            coordinator: coordinator.into(),
            enrollment_token: enrollment_token.into(),
            name: "worker".into(),
            slots: std::thread::available_parallelism()
                .map(|n| n.get())
                .unwrap_or(1),
            poll_wait_ms: 5_000,
            max_backoff_ms: 10_000,
        }
    }
}

/// Fatal worker errors (everything else is retried).
#[derive(Debug, thiserror::Error)]
pub enum WorkerError {
    /// The enrollment token was refused.
    #[error("the coordinator refused the enrollment token")]
    EnrollmentRefused,
    /// The HTTP client could not be built.
    #[error("http client: {0}")]
    Client(String),
}

/// What a worker did before it stopped.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct WorkerSummary {
    /// Results accepted by the coordinator.
    pub uploaded: u64,
    /// Leases lost or uploads rejected as stale.
    pub stale: u64,
    /// Leases released on shutdown.
    pub released: u64,
    /// Tasks that failed to render (reported to the coordinator).
    pub failed: u64,
}

#[derive(Default)]
struct Counters {
    uploaded: AtomicU64,
    stale: AtomicU64,
    released: AtomicU64,
    failed: AtomicU64,
}

/// Errors of one HTTP exchange.
#[derive(Debug, thiserror::Error)]
enum CallError {
    #[error("network: {0}")]
    Net(#[from] reqwest::Error),
    #[error("status {0}: {1}")]
    Status(StatusCode, String),
}

struct Inner {
    cfg: WorkerConfig,
    http: reqwest::Client,
    token: Mutex<String>,
    blobs: Mutex<HashMap<String, Arc<Vec<u8>>>>,
    prepared: Mutex<HashMap<i64, Arc<Prepared>>>,
    counters: Counters,
    stopping: watch::Receiver<bool>,
}

/// Most prepared jobs kept in memory.
const PREPARED_CACHE: usize = 4;
/// Most blobs (scenes, assets, surrogate images, coefficient tables) kept in memory; the
/// cache is cleared when full (a job's blobs are simply fetched again).
const BLOB_CACHE: usize = 64;

/// Runs the worker until `shutdown` resolves (then finishes the tasks in hand) or a fatal
/// error occurs.
pub async fn run(
    cfg: WorkerConfig,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<WorkerSummary, WorkerError> {
    let http = reqwest::Client::builder()
        .connect_timeout(Duration::from_secs(5))
        .build()
        .map_err(|e| WorkerError::Client(e.to_string()))?;
    let (stop_tx, stop_rx) = watch::channel(false);
    tokio::spawn(async move {
        shutdown.await;
        let _ = stop_tx.send(true);
    });
    let inner = Arc::new(Inner {
        cfg: cfg.clone(),
        http,
        token: Mutex::new(String::new()),
        blobs: Mutex::new(HashMap::new()),
        prepared: Mutex::new(HashMap::new()),
        counters: Counters::default(),
        stopping: stop_rx,
    });
    if !inner.register().await? {
        return Ok(WorkerSummary::default());
    }
    let mut slots = Vec::new();
    for _ in 0..cfg.slots.max(1) {
        let inner = inner.clone();
        slots.push(tokio::spawn(async move { inner.slot_loop().await }));
    }
    for s in slots {
        match s.await {
            Ok(Err(e)) => return Err(e),
            Ok(Ok(())) => {}
            Err(e) => tracing::error!(error = %e, "worker slot panicked"),
        }
    }
    let c = &inner.counters;
    Ok(WorkerSummary {
        uploaded: c.uploaded.load(Ordering::Relaxed),
        stale: c.stale.load(Ordering::Relaxed),
        released: c.released.load(Ordering::Relaxed),
        failed: c.failed.load(Ordering::Relaxed),
    })
}

/// Aborts a background task when dropped (heartbeats end with the task, however it ends).
struct AbortOnDrop(tokio::task::JoinHandle<()>);

impl Drop for AbortOnDrop {
    fn drop(&mut self) {
        self.0.abort();
    }
}

async fn error_text(resp: reqwest::Response) -> CallError {
    let status = resp.status();
    CallError::Status(status, resp.text().await.unwrap_or_default())
}

impl Inner {
    fn url(&self, path: &str) -> String {
        format!("{}{}", self.cfg.coordinator.trim_end_matches('/'), path)
    }

    fn stopping(&self) -> bool {
        *self.stopping.borrow()
    }

    async fn sleep_or_stop(&self, d: Duration) {
        let mut rx = self.stopping.clone();
        tokio::select! {
            _ = tokio::time::sleep(d) => {}
            _ = rx.wait_for(|s| *s) => {}
        }
    }

    fn next_backoff(&self, b: Duration) -> Duration {
        (b * 2).min(Duration::from_millis(self.cfg.max_backoff_ms.max(100)))
    }

    /// Registers (retrying until the coordinator answers). `Ok(false)`: stopped first.
    async fn register(&self) -> Result<bool, WorkerError> {
        let mut backoff = Duration::from_millis(100);
        loop {
            if self.stopping() {
                return Ok(false);
            }
            let resp = self
                .http
                .post(self.url("/v1/workers/register"))
                .bearer_auth(&self.cfg.enrollment_token)
                .json(&RegisterRequest {
                    name: self.cfg.name.clone(),
                })
                .send()
                .await;
            match resp {
                Ok(r) if r.status() == StatusCode::CREATED => {
                    match r.json::<RegisterResponse>().await {
                        Ok(reg) => {
                            tracing::info!(worker = reg.worker_id, "registered");
                            *self.token.lock().await = reg.token;
                            return Ok(true);
                        }
                        Err(e) => tracing::warn!(error = %e, "bad registration answer"),
                    }
                }
                Ok(r) if r.status() == StatusCode::UNAUTHORIZED => {
                    return Err(WorkerError::EnrollmentRefused);
                }
                Ok(r) => tracing::warn!(status = %r.status(), "registration failed; retrying"),
                Err(e) => tracing::warn!(error = %e, "coordinator unreachable; retrying"),
            }
            self.sleep_or_stop(backoff).await;
            backoff = self.next_backoff(backoff);
        }
    }

    async fn token(&self) -> String {
        self.token.lock().await.clone()
    }

    /// One slot: renders one task at a time and keeps **one more lease in hand** (fetched,
    /// prepared and heartbeating while the current one renders), so lease and upload
    /// latency overlap rendering instead of adding to it.
    async fn slot_loop(self: Arc<Self>) -> Result<(), WorkerError> {
        let render_permit = Arc::new(Semaphore::new(1));
        let mut tasks = tokio::task::JoinSet::new();
        let mut backoff = Duration::from_millis(100);
        while !self.stopping() {
            match self.lease().await {
                Ok(Some(lease)) => {
                    backoff = Duration::from_millis(100);
                    if self.stopping() {
                        self.release(&lease).await;
                        break;
                    }
                    let (started_tx, started_rx) = tokio::sync::oneshot::channel();
                    let (me, permit) = (self.clone(), render_permit.clone());
                    tasks.spawn(async move { me.process(lease, permit, started_tx).await });
                    // Lease the next task once this one is rendering (or over).
                    let _ = started_rx.await;
                }
                Ok(None) => backoff = Duration::from_millis(100),
                Err(CallError::Status(StatusCode::UNAUTHORIZED, _)) => {
                    // The coordinator no longer knows us (e.g. a new database): enrol again.
                    if !self.register().await? {
                        break;
                    }
                }
                Err(e) => {
                    tracing::warn!(error = %e, backoff_ms = backoff.as_millis() as u64, "lease failed; backing off");
                    self.sleep_or_stop(backoff).await;
                    backoff = self.next_backoff(backoff);
                }
            }
            // Reap finished tasks so the set does not grow.
            while tasks.try_join_next().is_some() {}
        }
        while tasks.join_next().await.is_some() {}
        Ok(())
    }

    async fn lease(&self) -> Result<Option<TaskLease>, CallError> {
        let r = self
            .http
            .post(self.url("/v1/workers/lease"))
            .bearer_auth(self.token().await)
            .timeout(Duration::from_millis(self.cfg.poll_wait_ms + 30_000))
            .json(&LeaseRequest {
                wait_ms: self.cfg.poll_wait_ms,
            })
            .send()
            .await?;
        match r.status() {
            StatusCode::OK => Ok(Some(r.json().await?)),
            StatusCode::NO_CONTENT => Ok(None),
            _ => Err(error_text(r).await),
        }
    }

    async fn release(&self, l: &TaskLease) {
        let url = self.url(&format!(
            "/v1/tasks/{}/release?attempt={}",
            l.task_id, l.attempt
        ));
        match self
            .http
            .post(url)
            .bearer_auth(self.token().await)
            .send()
            .await
        {
            Ok(r) if r.status().is_success() => {
                self.counters.released.fetch_add(1, Ordering::Relaxed);
                tracing::info!(task = l.task_id, "lease released on shutdown");
            }
            Ok(r) => tracing::warn!(task = l.task_id, status = %r.status(), "release refused"),
            Err(e) => {
                tracing::warn!(task = l.task_id, error = %e, "release failed; the lease will expire")
            }
        }
    }

    /// A blob by content address, from the cache or the coordinator (verified).
    async fn blob(&self, hash: &str) -> Result<Arc<Vec<u8>>, String> {
        if let Some(b) = self.blobs.lock().await.get(hash) {
            return Ok(b.clone());
        }
        let r = self
            .http
            .get(self.url(&format!("/v1/assets/{hash}")))
            .bearer_auth(self.token().await)
            .send()
            .await
            .map_err(|e| e.to_string())?;
        if !r.status().is_success() {
            return Err(format!("fetching {hash}: {}", error_text(r).await));
        }
        let bytes = r.bytes().await.map_err(|e| e.to_string())?.to_vec();
        if sha256_hex(&bytes) != hash {
            return Err(format!("blob {hash} does not match its address"));
        }
        let b = Arc::new(bytes);
        let mut cache = self.blobs.lock().await;
        if cache.len() >= BLOB_CACHE {
            cache.clear();
        }
        cache.insert(hash.to_owned(), b.clone());
        Ok(b)
    }

    async fn prepare(&self, l: &TaskLease) -> Result<Arc<Prepared>, String> {
        if let Some(p) = self.prepared.lock().await.get(&l.job_id) {
            return Ok(p.clone());
        }
        let scene = self.blob(&l.scene_hash).await?;
        let mut assets = BTreeMap::new();
        for (name, hash) in &l.assets {
            assets.insert(name.clone(), self.blob(hash).await?.as_ref().clone());
        }
        let (job, est) = (l.job, l.estimator.clone());
        let p = tokio::task::spawn_blocking(move || Prepared::new(&scene, assets, &job, &est))
            .await
            .map_err(|e| e.to_string())?
            .map_err(|e: TaskError| e.to_string())?;
        let p = Arc::new(p);
        let mut cache = self.prepared.lock().await;
        if cache.len() >= PREPARED_CACHE {
            cache.clear();
        }
        cache.insert(l.job_id, p.clone());
        Ok(p)
    }

    /// The phase inputs named by the lease, fetched by content address (verified) and
    /// decoded once per job.
    async fn phase_inputs(&self, l: &TaskLease, p: &Arc<Prepared>) -> Result<PhaseInputs, String> {
        let mut inputs = PhaseInputs::default();
        if let Some(hash) = &l.surrogate {
            let bytes = self.blob(hash).await?;
            let (p, hash) = (p.clone(), hash.clone());
            let s = tokio::task::spawn_blocking(move || p.surrogate(&hash, &bytes))
                .await
                .map_err(|e| e.to_string())?
                .map_err(|e| e.to_string())?;
            inputs.surrogate = Some(s);
        }
        if let Some(hash) = &l.coefficients {
            let bytes = self.blob(hash).await?;
            let (p, hash) = (p.clone(), hash.clone());
            let t = tokio::task::spawn_blocking(move || p.coefficients(&hash, &bytes))
                .await
                .map_err(|e| e.to_string())?
                .map_err(|e| e.to_string())?;
            inputs.coefficients = Some(t);
        }
        Ok(inputs)
    }

    /// Heartbeats (from receipt), prepares, waits for the slot's render permit, renders,
    /// frees the permit, uploads. Signals `started` once it holds the permit (or gives up).
    #[tracing::instrument(skip_all, fields(task = l.task_id, attempt = l.attempt))]
    async fn process(
        self: Arc<Self>,
        l: TaskLease,
        permit: Arc<Semaphore>,
        started: tokio::sync::oneshot::Sender<()>,
    ) {
        let lost = Arc::new(AtomicBool::new(false));
        let _heartbeat = self.heartbeat(&l, lost.clone()).await;
        tracing::debug!("leased");
        let prepared = match self.prepare(&l).await {
            Ok(p) => p,
            Err(e) => return self.fail(&l, &e).await,
        };
        let inputs = match self.phase_inputs(&l, &prepared).await {
            Ok(i) => i,
            Err(e) => return self.fail(&l, &e).await,
        };
        tracing::debug!(phase = l.phase.as_str(), "inputs ready");
        let Ok(render_permit) = permit.acquire_owned().await else {
            return;
        };
        tracing::debug!("rendering");
        let _ = started.send(());
        if self.stopping() {
            // Shutdown before this prefetched task started: give it back.
            return self.release(&l).await;
        }
        if lost.load(Ordering::Relaxed) {
            self.counters.stale.fetch_add(1, Ordering::Relaxed);
            return;
        }
        let header = l.tile_header();
        let phase = l.phase;
        let rendered =
            tokio::task::spawn_blocking(move || prepared.render_task(header, phase, &inputs)).await;
        drop(render_permit);
        tracing::debug!("rendered");
        let result = match rendered {
            Ok(Ok(r)) => r,
            Ok(Err(e)) => return self.fail(&l, &e.to_string()).await,
            Err(e) => return self.fail(&l, &format!("render thread: {e}")).await,
        };
        if lost.load(Ordering::Relaxed) {
            tracing::info!("lease lost while rendering; result dropped");
            self.counters.stale.fetch_add(1, Ordering::Relaxed);
            return;
        }
        // Encoding a training result (its cell table is megabytes) takes tens of
        // milliseconds: on a blocking thread, so this slot's next task — woken by the freed
        // permit, and run by the same async threads — starts rendering meanwhile.
        let body = match tokio::task::spawn_blocking(move || result.encode()).await {
            Ok(b) => b,
            Err(e) => return self.fail(&l, &format!("encode thread: {e}")).await,
        };
        self.upload(&l, body).await;
    }

    /// Starts heartbeating `l` every `heartbeat_ms`; a 409 sets `lost`. Stops when the
    /// returned guard is dropped.
    async fn heartbeat(&self, l: &TaskLease, lost: Arc<AtomicBool>) -> AbortOnDrop {
        let http = self.http.clone();
        let url = self.url(&format!(
            "/v1/tasks/{}/heartbeat?attempt={}",
            l.task_id, l.attempt
        ));
        let token = self.token().await;
        let period = Duration::from_millis(l.heartbeat_ms.max(50));
        AbortOnDrop(tokio::spawn(async move {
            loop {
                tokio::time::sleep(period).await;
                match http.post(&url).bearer_auth(&token).send().await {
                    Ok(r) if r.status() == StatusCode::CONFLICT => {
                        lost.store(true, Ordering::Relaxed);
                        return;
                    }
                    Ok(_) => {}
                    Err(e) => tracing::warn!(error = %e, "heartbeat failed"),
                }
            }
        }))
    }

    async fn upload(&self, l: &TaskLease, body: Vec<u8>) {
        let url = self.url(&format!(
            "/v1/tasks/{}/result?attempt={}",
            l.task_id, l.attempt
        ));
        let mut backoff = Duration::from_millis(100);
        // Retry while the lease can still be valid; the coordinator dedups accepted attempts.
        for _ in 0..10 {
            match self
                .http
                .put(&url)
                .bearer_auth(self.token().await)
                .body(body.clone())
                .send()
                .await
            {
                Ok(r) if r.status().is_success() => {
                    self.counters.uploaded.fetch_add(1, Ordering::Relaxed);
                    tracing::debug!(bytes = body.len(), "uploaded");
                    return;
                }
                Ok(r) if r.status() == StatusCode::CONFLICT => {
                    let body = error_text(r).await;
                    tracing::info!(body = %body, "upload rejected as stale");
                    self.counters.stale.fetch_add(1, Ordering::Relaxed);
                    return;
                }
                Ok(r) if r.status().is_client_error() => {
                    // The coordinator refused the result itself (e.g. 422 invalid_cells):
                    // report the attempt failed so the task is redone now, not after the
                    // lease expires (the retry cap ends a job that keeps failing).
                    let body = error_text(r).await;
                    tracing::error!(body = %body, "upload rejected");
                    return self.fail(l, &format!("upload rejected: {body}")).await;
                }
                Ok(r) => tracing::warn!(status = %r.status(), "upload failed; retrying"),
                Err(e) => tracing::warn!(error = %e, "upload failed; retrying"),
            }
            tokio::time::sleep(backoff).await;
            backoff = self.next_backoff(backoff);
        }
        tracing::error!("upload failed repeatedly; the lease will expire and the task be redone");
    }

    async fn fail(&self, l: &TaskLease, reason: &str) {
        tracing::error!(reason, "task failed");
        self.counters.failed.fetch_add(1, Ordering::Relaxed);
        let url = self.url(&format!(
            "/v1/tasks/{}/fail?attempt={}",
            l.task_id, l.attempt
        ));
        if let Err(e) = self
            .http
            .post(url)
            .bearer_auth(self.token().await)
            .body(reason.to_owned())
            .send()
            .await
        {
            tracing::warn!(error = %e, "could not report the failure; the lease will expire");
        }
    }
}
