//! The store: every piece of coordinator state lives here, in SQLite or PostgreSQL.
//!
//! One implementation serves both backends through `sqlx::Any` (SQL written once with `?`
//! placeholders, rewritten to `$n` for PostgreSQL); the two places where the dialects differ
//! (lease claim with `FOR UPDATE SKIP LOCKED`, SQLite's WAL pragma) branch on [`Backend`].
//! Migrations are embedded per backend (`migrations/sqlite`, `migrations/postgres`).
//!
//! Invariants kept by the queries (each is a single atomic statement or one transaction):
//! - a task is `pending`, `leased` (to one worker, with an attempt number and an expiry),
//!   `done` (with exactly one stored result, keyed by the accepted attempt) or `skipped` (an
//!   adaptive render phase stopped before its round; never leased again, never merged);
//! - each lease increments the attempt, so an upload naming an older attempt is stale;
//! - a result is accepted only from the worker holding the current attempt's lease, and
//!   re-uploading an accepted (task, attempt) is a no-op.

use std::collections::HashMap;
use std::sync::Arc;
use std::time::{SystemTime, UNIX_EPOCH};

use protocol::job::{PhasePlan, ResolvedJob, TileRect};
use protocol::lease::{JobState, PhaseKind};
use sqlx::any::{AnyPoolOptions, AnyRow};
use sqlx::{AnyPool, Row};

/// Which database is behind the pool.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Backend {
    /// SQLite file (single writer, WAL).
    Sqlite,
    /// PostgreSQL server.
    Postgres,
}

/// Database errors.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// The driver failed.
    #[error("database: {0}")]
    Db(#[from] sqlx::Error),
    /// Migrations failed.
    #[error("migration: {0}")]
    Migrate(#[from] sqlx::migrate::MigrateError),
    /// The URL names no supported backend.
    #[error("unsupported database URL `{0}` (expected sqlite:… or postgres://…)")]
    BadUrl(String),
    /// A stored value does not parse (corrupt row).
    #[error("corrupt row: {0}")]
    Corrupt(String),
}

type Result<T> = std::result::Result<T, StoreError>;

/// Milliseconds since the Unix epoch.
pub fn now_ms() -> i64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_millis() as i64)
        .unwrap_or(0)
}

/// Rewrites `?` placeholders to PostgreSQL's `$1, $2, …` (our SQL has no `?` in literals).
pub fn dollar_placeholders(s: &str) -> String {
    let mut out = String::with_capacity(s.len() + 16);
    let mut n = 0;
    for ch in s.chars() {
        if ch == '?' {
            n += 1;
            out.push('$');
            out.push_str(&n.to_string());
        } else {
            out.push(ch);
        }
    }
    out
}

/// A connection pool plus the backend it talks to.
///
/// The only memory it keeps is a cache of rows that never change once written (worker
/// secret hashes, job specs): losing it loses nothing, and every coordinator sharing the
/// database sees the same values.
#[derive(Clone, Debug)]
pub struct Store {
    pool: AnyPool,
    backend: Backend,
    cache: Arc<std::sync::Mutex<Cache>>,
}

/// Entries per cache map before it is cleared.
const CACHE_LIMIT: usize = 10_000;

/// Immutable rows, cached.
#[derive(Debug, Default)]
struct Cache {
    secrets: HashMap<i64, String>,
    jobs: HashMap<i64, Arc<JobRow>>,
}

/// A job row.
#[derive(Clone, Debug)]
pub struct JobRow {
    /// Id.
    pub id: i64,
    /// JobSpec JSON (scene replaced by its bundle hash).
    pub spec: String,
    /// Resolved settings.
    pub resolved: ResolvedJob,
    /// Scene document address.
    pub scene_hash: String,
    /// Estimator name.
    pub estimator: String,
    /// Effects and techniques simulated (from `scene::Features`).
    pub effects: Vec<String>,
    /// Priority.
    pub priority: i64,
    /// State.
    pub state: JobState,
    /// Active phase index.
    pub phase_idx: i64,
    /// Failure reason.
    pub error: Option<String>,
    /// Submission time.
    pub created_ms: i64,
    /// Completion time.
    pub finished_ms: Option<i64>,
}

/// A job to create ([`Store::create_job`]).
#[derive(Clone, Copy, Debug)]
pub struct NewJob<'a> {
    /// JobSpec JSON (scene replaced by its bundle hash).
    pub spec_json: &'a str,
    /// Resolved settings.
    pub resolved: &'a ResolvedJob,
    /// Scene document address.
    pub scene_hash: &'a str,
    /// Estimator name.
    pub estimator: &'a str,
    /// Effects simulated.
    pub effects: &'a [String],
    /// Priority.
    pub priority: i64,
    /// The phase plan: every phase row and task is created with the job (a later phase's
    /// tasks are leased only once the job's `phase_idx` reaches them).
    pub phases: &'a [PhasePlan],
}

/// A phase of a job.
#[derive(Clone, Debug, PartialEq)]
pub struct PhaseRow {
    /// Index (0-based, the order of the phases).
    pub idx: i64,
    /// Which phase.
    pub kind: PhaseKind,
    /// Samples per pixel it renders.
    pub spp: u32,
    /// Surrogate image its tasks train with (content address).
    pub surrogate: Option<String>,
    /// Coefficient table its tasks render with (content address).
    pub coefficients: Option<String>,
    /// Layout signature of its accepted cell blocks (train phases).
    pub layout: Option<String>,
    /// JSON `BarrierStats` of the barrier after it.
    pub barrier: Option<String>,
    /// First lease.
    pub started_ms: Option<i64>,
    /// Barrier passed (or job finished).
    pub finished_ms: Option<i64>,
    /// Last accepted result.
    pub last_done_ms: Option<i64>,
    /// Tasks in the phase (not counting tasks skipped by an early stop).
    pub tasks: i64,
    /// Tasks done.
    pub done: i64,
    /// Last render round checked against the job's budget or target (−1: none).
    pub rounds_checked: i64,
    /// The round after which an adaptive phase stopped, if it did.
    pub stop_round: Option<i64>,
}

/// A task's state as the round check needs it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TaskState {
    /// Canonical position in its phase.
    pub seq: i64,
    /// `pending`, `leased`, `done` or `skipped`.
    pub state: String,
    /// When its result was accepted.
    pub done_ms: Option<i64>,
}

/// Store-wide counts for `/metrics`.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Metrics {
    /// (state, count) of jobs.
    pub jobs: Vec<(String, i64)>,
    /// (state, count) of tasks.
    pub tasks: Vec<(String, i64)>,
    /// Registered workers.
    pub workers: i64,
    /// Σ attempts over tasks.
    pub attempts: i64,
    /// Σ failed attempts over tasks.
    pub failures: i64,
}

/// A task as leased.
#[derive(Clone, Debug)]
pub struct LeasedTask {
    /// Task id.
    pub id: i64,
    /// Job id.
    pub job_id: i64,
    /// Phase index.
    pub phase_idx: i64,
    /// Pixels.
    pub rect: TileRect,
    /// Sample range start.
    pub sample_start: u32,
    /// Sample range end.
    pub sample_end: u32,
    /// Attempt number of this lease.
    pub attempt: i64,
}

/// What the store knows of a task, for validating uploads.
#[derive(Clone, Debug)]
pub struct TaskRow {
    /// Task id.
    pub id: i64,
    /// Job id.
    pub job_id: i64,
    /// Phase index.
    pub phase_idx: i64,
    /// Canonical position in the phase (dense from 0).
    pub seq: i64,
    /// Pixels.
    pub rect: TileRect,
    /// Sample range start.
    pub sample_start: u32,
    /// Sample range end.
    pub sample_end: u32,
    /// `pending`, `leased` or `done`.
    pub state: String,
    /// Current attempt.
    pub attempt: i64,
    /// Lease holder.
    pub worker_id: Option<i64>,
    /// Accepted attempt, when done.
    pub done_attempt: Option<i64>,
}

/// A `train` result's training table as stored ([`Store::phase_tables`]).
#[derive(Clone, Debug)]
pub enum StoredTable {
    /// The encoded table (`estimators::table` format).
    Table(Vec<u8>),
    /// A whole frame stream whose cell block is the table (rows stored before the split).
    Frame(Vec<u8>),
}

/// Outcome of a result upload.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum UploadOutcome {
    /// Stored now.
    Accepted,
    /// This (task, attempt) had been stored before.
    Duplicate,
    /// The attempt is not the task's current lease of this worker.
    Stale,
}

/// Progress of a phase.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Progress {
    /// Tasks in the phase.
    pub total: i64,
    /// Tasks done.
    pub done: i64,
    /// Sum of attempts over the phase's tasks.
    pub attempts: i64,
}

fn u32_of(row: &AnyRow, col: &str) -> Result<u32> {
    let v: i64 = row.try_get(col)?;
    u32::try_from(v).map_err(|_| StoreError::Corrupt(format!("{col} = {v}")))
}

fn rect_of(row: &AnyRow) -> Result<TileRect> {
    Ok(TileRect {
        x0: u32_of(row, "x0")?,
        y0: u32_of(row, "y0")?,
        width: u32_of(row, "width")?,
        height: u32_of(row, "height")?,
    })
}

fn job_of(row: &AnyRow) -> Result<JobRow> {
    let resolved: String = row.try_get("resolved")?;
    let state: String = row.try_get("state")?;
    let effects: String = row.try_get("effects")?;
    Ok(JobRow {
        id: row.try_get("id")?,
        spec: row.try_get("spec")?,
        resolved: serde_json::from_str(&resolved)
            .map_err(|e| StoreError::Corrupt(e.to_string()))?,
        scene_hash: row.try_get("scene_hash")?,
        estimator: row.try_get("estimator")?,
        effects: serde_json::from_str(&effects).map_err(|e| StoreError::Corrupt(e.to_string()))?,
        priority: row.try_get("priority")?,
        state: JobState::parse(&state)
            .ok_or_else(|| StoreError::Corrupt(format!("job state {state}")))?,
        phase_idx: row.try_get("phase_idx")?,
        error: row.try_get("error")?,
        created_ms: row.try_get("created_ms")?,
        finished_ms: row.try_get("finished_ms")?,
    })
}

const JOB_COLS: &str = "id, spec, resolved, scene_hash, estimator, effects, priority, state, phase_idx, error, created_ms, finished_ms";
const TASK_COLS: &str = "id, job_id, phase_idx, seq, x0, y0, width, height, sample_start, sample_end, state, attempt, worker_id, done_attempt";

impl Store {
    /// Connects (creating the SQLite file if needed) and runs the embedded migrations.
    pub async fn connect(url: &str) -> Result<Self> {
        sqlx::any::install_default_drivers();
        let backend = if url.starts_with("sqlite:") {
            Backend::Sqlite
        } else if url.starts_with("postgres://") || url.starts_with("postgresql://") {
            Backend::Postgres
        } else {
            return Err(StoreError::BadUrl(url.to_owned()));
        };
        let pool = match backend {
            // SQLite has one writer: one connection serialises everything and avoids
            // SQLITE_BUSY upgrades inside transactions. It is a local file: no liveness ping
            // before every acquire (a round trip to the connection's thread per statement).
            Backend::Sqlite => {
                AnyPoolOptions::new()
                    .max_connections(1)
                    .test_before_acquire(false)
                    .connect(url)
                    .await?
            }
            Backend::Postgres => {
                AnyPoolOptions::new()
                    .max_connections(8)
                    .connect(url)
                    .await?
            }
        };
        let store = Self {
            pool,
            backend,
            cache: Arc::default(),
        };
        match backend {
            Backend::Sqlite => {
                // 64 KiB pages for a new file (no-op on an existing one): results are
                // blobs of 0.1–7 MB, and writing one through 4 KiB pages (overflow chains)
                // took 70–95 ms per 6.5 MB training result with `synchronous = FULL` here,
                // 28–31 ms with 64 KiB pages — on the critical path at each phase barrier.
                // Must precede the first write and the switch to WAL.
                sqlx::query("PRAGMA page_size = 65536")
                    .execute(&store.pool)
                    .await?;
                sqlx::query("PRAGMA journal_mode = WAL")
                    .execute(&store.pool)
                    .await?;
                sqlx::query("PRAGMA busy_timeout = 5000")
                    .execute(&store.pool)
                    .await?;
                sqlx::migrate!("../../migrations/sqlite")
                    .run(&store.pool)
                    .await?;
            }
            Backend::Postgres => {
                sqlx::migrate!("../../migrations/postgres")
                    .run(&store.pool)
                    .await?
            }
        }
        Ok(store)
    }

    /// The pool, for read-only queries kept beside their routes (`routes::events`,
    /// `convergence`); SQL must go through [`dollar_placeholders`] for PostgreSQL.
    pub fn pool(&self) -> &AnyPool {
        &self.pool
    }

    /// The backend.
    pub fn backend(&self) -> Backend {
        self.backend
    }

    /// Closes the pool (waits for connections to be returned).
    pub async fn close(&self) {
        self.pool.close().await;
    }

    /// The SQL for this backend (see [`dollar_placeholders`]).
    fn sql(&self, s: &str) -> String {
        match self.backend {
            Backend::Sqlite => s.to_owned(),
            Backend::Postgres => dollar_placeholders(s),
        }
    }

    /// `SELECT 1`, for `/healthz`.
    pub async fn ping(&self) -> Result<()> {
        sqlx::query("SELECT 1").execute(&self.pool).await?;
        Ok(())
    }

    // ---- blobs -------------------------------------------------------------------------

    /// Stores a content-addressed blob (no-op when present).
    pub async fn put_blob(&self, hash: &str, data: &[u8]) -> Result<()> {
        let sql = self.sql("INSERT INTO blobs (hash, data, created_ms) VALUES (?, ?, ?) ON CONFLICT (hash) DO NOTHING");
        sqlx::query(&sql)
            .bind(hash)
            .bind(data.to_vec())
            .bind(now_ms())
            .execute(&self.pool)
            .await?;
        Ok(())
    }

    /// A blob by address.
    pub async fn get_blob(&self, hash: &str) -> Result<Option<Vec<u8>>> {
        let sql = self.sql("SELECT data FROM blobs WHERE hash = ?");
        let row = sqlx::query(&sql)
            .bind(hash)
            .fetch_optional(&self.pool)
            .await?;
        Ok(match row {
            Some(r) => Some(r.try_get("data")?),
            None => None,
        })
    }

    /// Whether a blob exists.
    pub async fn has_blob(&self, hash: &str) -> Result<bool> {
        let sql = self.sql("SELECT hash FROM blobs WHERE hash = ?");
        Ok(sqlx::query(&sql)
            .bind(hash)
            .fetch_optional(&self.pool)
            .await?
            .is_some())
    }

    // ---- workers -----------------------------------------------------------------------

    /// Registers a worker with the hash of its secret; returns its id.
    pub async fn add_worker(&self, name: &str, secret_hash: &str) -> Result<i64> {
        let now = now_ms();
        let sql = self.sql(
            "INSERT INTO workers (name, secret_hash, created_ms, last_seen_ms) VALUES (?, ?, ?, ?) RETURNING id",
        );
        let row = sqlx::query(&sql)
            .bind(name)
            .bind(secret_hash)
            .bind(now)
            .bind(now)
            .fetch_one(&self.pool)
            .await?;
        Ok(row.try_get("id")?)
    }

    /// The stored secret hash of a worker (cached: it never changes once written).
    pub async fn worker_secret_hash(&self, id: i64) -> Result<Option<String>> {
        if let Some(h) = self
            .cache
            .lock()
            .ok()
            .and_then(|c| c.secrets.get(&id).cloned())
        {
            return Ok(Some(h));
        }
        let h = self.worker_secret_hash_uncached(id).await?;
        if let (Some(h), Ok(mut c)) = (&h, self.cache.lock()) {
            if c.secrets.len() > CACHE_LIMIT {
                c.secrets.clear();
            }
            c.secrets.insert(id, h.clone());
        }
        Ok(h)
    }

    async fn worker_secret_hash_uncached(&self, id: i64) -> Result<Option<String>> {
        let sql = self.sql("SELECT secret_hash FROM workers WHERE id = ?");
        let row = sqlx::query(&sql)
            .bind(id)
            .fetch_optional(&self.pool)
            .await?;
        Ok(match row {
            Some(r) => Some(r.try_get("secret_hash")?),
            None => None,
        })
    }

    // ---- jobs --------------------------------------------------------------------------

    /// Creates a job with all its phases and their tasks, in one transaction.
    pub async fn create_job(&self, job: &NewJob<'_>) -> Result<i64> {
        let NewJob {
            spec_json,
            resolved,
            scene_hash,
            estimator,
            effects,
            priority,
            phases,
        } = *job;
        let now = now_ms();
        let resolved_json =
            serde_json::to_string(resolved).map_err(|e| StoreError::Corrupt(e.to_string()))?;
        let mut tx = self.pool.begin().await?;
        let sql = self.sql(
            "INSERT INTO jobs (spec, resolved, scene_hash, estimator, effects, priority, state, phase_idx, created_ms) \
             VALUES (?, ?, ?, ?, ?, ?, 'running', 0, ?) RETURNING id",
        );
        let row = sqlx::query(&sql)
            .bind(spec_json)
            .bind(resolved_json)
            .bind(scene_hash)
            .bind(estimator)
            .bind(serde_json::to_string(effects).unwrap_or_else(|_| "[]".into()))
            .bind(priority)
            .bind(now)
            .fetch_one(&mut *tx)
            .await?;
        let job_id: i64 = row.try_get("id")?;
        for (idx, phase) in phases.iter().enumerate() {
            let idx = idx as i64;
            let sql = self.sql("INSERT INTO phases (job_id, idx, name, spp) VALUES (?, ?, ?, ?)");
            sqlx::query(&sql)
                .bind(job_id)
                .bind(idx)
                .bind(phase.kind.as_str())
                .bind(i64::from(phase.samples.end - phase.samples.start))
                .execute(&mut *tx)
                .await?;
            // Multi-row inserts keep large plans fast (100 rows × 10 parameters per statement).
            for chunk in phase.tasks.chunks(100) {
                let mut s = String::from(
                    "INSERT INTO tasks (job_id, phase_idx, seq, x0, y0, width, height, sample_start, sample_end, state) VALUES ",
                );
                for i in 0..chunk.len() {
                    if i > 0 {
                        s.push(',');
                    }
                    s.push_str("(?, ?, ?, ?, ?, ?, ?, ?, ?, 'pending')");
                }
                let sql = self.sql(&s);
                let mut q = sqlx::query(&sql);
                for t in chunk {
                    q = q
                        .bind(job_id)
                        .bind(idx)
                        .bind(i64::from(t.seq))
                        .bind(i64::from(t.rect.x0))
                        .bind(i64::from(t.rect.y0))
                        .bind(i64::from(t.rect.width))
                        .bind(i64::from(t.rect.height))
                        .bind(i64::from(t.sample_start))
                        .bind(i64::from(t.sample_end));
                }
                q.execute(&mut *tx).await?;
            }
        }
        tx.commit().await?;
        Ok(job_id)
    }

    /// A job's immutable parts (spec, resolved settings, scene, estimator, effects; **not**
    /// its state), cached: lease building needs them for every task.
    pub async fn job_spec(&self, id: i64) -> Result<Option<Arc<JobRow>>> {
        if let Some(j) = self
            .cache
            .lock()
            .ok()
            .and_then(|c| c.jobs.get(&id).cloned())
        {
            return Ok(Some(j));
        }
        let Some(job) = self.job(id).await? else {
            return Ok(None);
        };
        let job = Arc::new(job);
        if let Ok(mut c) = self.cache.lock() {
            if c.jobs.len() > CACHE_LIMIT {
                c.jobs.clear();
            }
            c.jobs.insert(id, job.clone());
        }
        Ok(Some(job))
    }

    /// A job by id.
    pub async fn job(&self, id: i64) -> Result<Option<JobRow>> {
        let sql = self.sql(&format!("SELECT {JOB_COLS} FROM jobs WHERE id = ?"));
        match sqlx::query(&sql)
            .bind(id)
            .fetch_optional(&self.pool)
            .await?
        {
            Some(r) => Ok(Some(job_of(&r)?)),
            None => Ok(None),
        }
    }

    /// All jobs, newest first (at most `limit`).
    pub async fn jobs(&self, limit: i64) -> Result<Vec<JobRow>> {
        let sql = self.sql(&format!(
            "SELECT {JOB_COLS} FROM jobs ORDER BY id DESC LIMIT ?"
        ));
        sqlx::query(&sql)
            .bind(limit)
            .fetch_all(&self.pool)
            .await?
            .iter()
            .map(job_of)
            .collect()
    }

    /// Ids of running jobs whose active phase has no unfinished task (ready to finish).
    pub async fn finishable_jobs(&self) -> Result<Vec<i64>> {
        let sql = "SELECT j.id FROM jobs j WHERE j.state = 'running' AND NOT EXISTS \
                   (SELECT 1 FROM tasks t WHERE t.job_id = j.id AND t.phase_idx = j.phase_idx AND t.state NOT IN ('done', 'skipped'))";
        let rows = sqlx::query(sql).fetch_all(&self.pool).await?;
        rows.iter().map(|r| Ok(r.try_get("id")?)).collect()
    }

    /// Ends a running or paused job (done/failed/cancelled); returns whether it changed.
    pub async fn end_job(&self, id: i64, state: JobState, error: Option<&str>) -> Result<bool> {
        let sql = self.sql(
            "UPDATE jobs SET state = ?, error = ?, finished_ms = ? WHERE id = ? AND state IN ('running', 'paused')",
        );
        let r = sqlx::query(&sql)
            .bind(state.as_str())
            .bind(error.map(str::to_owned))
            .bind(now_ms())
            .bind(id)
            .execute(&self.pool)
            .await?;
        Ok(r.rows_affected() == 1)
    }

    /// Pauses a running job (`pause = true`) or resumes a paused one; returns whether it
    /// changed. A paused job's tasks are not leased; leases in hand may still finish.
    pub async fn set_paused(&self, id: i64, pause: bool) -> Result<bool> {
        let (from, to) = if pause {
            ("running", "paused")
        } else {
            ("paused", "running")
        };
        let sql = self.sql("UPDATE jobs SET state = ? WHERE id = ? AND state = ?");
        let r = sqlx::query(&sql)
            .bind(to)
            .bind(id)
            .bind(from)
            .execute(&self.pool)
            .await?;
        Ok(r.rows_affected() == 1)
    }

    /// Progress of a job's phase.
    pub async fn progress(&self, job_id: i64, phase_idx: i64) -> Result<Progress> {
        let sql = self.sql(
            "SELECT CAST(COALESCE(SUM(CASE WHEN state = 'skipped' THEN 0 ELSE 1 END), 0) AS BIGINT) AS total, \
                    CAST(COALESCE(SUM(CASE WHEN state = 'done' THEN 1 ELSE 0 END), 0) AS BIGINT) AS done, \
                    CAST(COALESCE(SUM(attempt), 0) AS BIGINT) AS attempts \
             FROM tasks WHERE job_id = ? AND phase_idx = ?",
        );
        let r = sqlx::query(&sql)
            .bind(job_id)
            .bind(phase_idx)
            .fetch_one(&self.pool)
            .await?;
        Ok(Progress {
            total: r.try_get("total")?,
            done: r.try_get("done")?,
            attempts: r.try_get("attempts")?,
        })
    }

    /// Phase timing: (name, started_ms, last done_ms).
    pub async fn phase_times(
        &self,
        job_id: i64,
    ) -> Result<Vec<(String, Option<i64>, Option<i64>)>> {
        let sql = self.sql(
            "SELECT p.name AS name, p.started_ms AS started_ms, \
                    (SELECT MAX(t.done_ms) FROM tasks t WHERE t.job_id = p.job_id AND t.phase_idx = p.idx) AS last_ms \
             FROM phases p WHERE p.job_id = ? ORDER BY p.idx",
        );
        let rows = sqlx::query(&sql).bind(job_id).fetch_all(&self.pool).await?;
        rows.iter()
            .map(|r| {
                Ok((
                    r.try_get("name")?,
                    r.try_get("started_ms")?,
                    r.try_get("last_ms")?,
                ))
            })
            .collect()
    }

    /// The phases of a job in order, with their task counts and last accepted result.
    pub async fn phases(&self, job_id: i64) -> Result<Vec<PhaseRow>> {
        self.phase_rows(job_id, None).await
    }

    /// One phase of a job (leases and uploads read it: one indexed row).
    pub async fn phase(&self, job_id: i64, idx: i64) -> Result<Option<PhaseRow>> {
        Ok(self.phase_rows(job_id, Some(idx)).await?.pop())
    }

    async fn phase_rows(&self, job_id: i64, idx: Option<i64>) -> Result<Vec<PhaseRow>> {
        let filter = if idx.is_some() { " AND p.idx = ?" } else { "" };
        let sql = self.sql(&format!(
            "SELECT p.idx AS idx, p.name AS name, p.spp AS spp, p.surrogate AS surrogate, \
                    p.coefficients AS coefficients, p.layout AS layout, p.barrier AS barrier, \
                    p.started_ms AS started_ms, p.finished_ms AS finished_ms, \
                    (SELECT MAX(t.done_ms) FROM tasks t WHERE t.job_id = p.job_id AND t.phase_idx = p.idx) AS last_ms, \
                    (SELECT COUNT(*) FROM tasks t WHERE t.job_id = p.job_id AND t.phase_idx = p.idx AND t.state <> 'skipped') AS tasks, \
                    (SELECT COUNT(*) FROM tasks t WHERE t.job_id = p.job_id AND t.phase_idx = p.idx AND t.state = 'done') AS done, \
                    p.rounds_checked AS rounds_checked, p.stop_round AS stop_round \
             FROM phases p WHERE p.job_id = ?{filter} ORDER BY p.idx"
        ));
        let mut q = sqlx::query(&sql).bind(job_id);
        if let Some(i) = idx {
            q = q.bind(i);
        }
        let rows = q.fetch_all(&self.pool).await?;
        rows.iter()
            .map(|r| {
                let name: String = r.try_get("name")?;
                Ok(PhaseRow {
                    idx: r.try_get("idx")?,
                    kind: PhaseKind::parse(&name)
                        .ok_or_else(|| StoreError::Corrupt(format!("phase name {name}")))?,
                    spp: u32_of(r, "spp")?,
                    surrogate: r.try_get("surrogate")?,
                    coefficients: r.try_get("coefficients")?,
                    layout: r.try_get("layout")?,
                    barrier: r.try_get("barrier")?,
                    started_ms: r.try_get("started_ms")?,
                    finished_ms: r.try_get("finished_ms")?,
                    last_done_ms: r.try_get("last_ms")?,
                    tasks: r.try_get("tasks")?,
                    done: r.try_get("done")?,
                    rounds_checked: r.try_get("rounds_checked")?,
                    stop_round: r.try_get("stop_round")?,
                })
            })
            .collect()
    }

    /// Records the layout signature of a train phase's cell blocks if none is recorded yet.
    pub async fn set_phase_layout(&self, job_id: i64, idx: i64, layout: &str) -> Result<()> {
        let sql = self
            .sql("UPDATE phases SET layout = ? WHERE job_id = ? AND idx = ? AND layout IS NULL");
        sqlx::query(&sql)
            .bind(layout)
            .bind(job_id)
            .bind(idx)
            .execute(&self.pool)
            .await?;
        Ok(())
    }

    /// The phase barrier: in one transaction, moves the job from phase `from` to `from + 1`
    /// (only if it is still at `from` and running or paused), marks phase `from` finished with
    /// `barrier` (JSON), and gives phase `from + 1` its surrogate / coefficient addresses.
    /// Returns whether this call advanced the job (false: another caller did, or the job
    /// ended); a repeated call is a no-op.
    pub async fn advance_phase(
        &self,
        job_id: i64,
        from: i64,
        barrier: &str,
        surrogate: Option<&str>,
        coefficients: Option<&str>,
    ) -> Result<bool> {
        let now = now_ms();
        let mut tx = self.pool.begin().await?;
        let sql = self.sql(
            "UPDATE jobs SET phase_idx = ? WHERE id = ? AND phase_idx = ? AND state IN ('running', 'paused')",
        );
        let r = sqlx::query(&sql)
            .bind(from + 1)
            .bind(job_id)
            .bind(from)
            .execute(&mut *tx)
            .await?;
        if r.rows_affected() != 1 {
            tx.rollback().await?;
            return Ok(false);
        }
        let sql =
            self.sql("UPDATE phases SET finished_ms = ?, barrier = ? WHERE job_id = ? AND idx = ?");
        sqlx::query(&sql)
            .bind(now)
            .bind(barrier)
            .bind(job_id)
            .bind(from)
            .execute(&mut *tx)
            .await?;
        let sql = self.sql(
            "UPDATE phases SET surrogate = COALESCE(?, surrogate), coefficients = COALESCE(?, coefficients) \
             WHERE job_id = ? AND idx = ?",
        );
        sqlx::query(&sql)
            .bind(surrogate.map(str::to_owned))
            .bind(coefficients.map(str::to_owned))
            .bind(job_id)
            .bind(from + 1)
            .execute(&mut *tx)
            .await?;
        tx.commit().await?;
        Ok(true)
    }

    /// States of a phase's tasks in canonical order.
    pub async fn task_states(&self, job_id: i64, idx: i64) -> Result<Vec<TaskState>> {
        let sql = self.sql(
            "SELECT seq, state, done_ms FROM tasks WHERE job_id = ? AND phase_idx = ? ORDER BY seq",
        );
        let rows = sqlx::query(&sql)
            .bind(job_id)
            .bind(idx)
            .fetch_all(&self.pool)
            .await?;
        rows.iter()
            .map(|r| {
                Ok(TaskState {
                    seq: r.try_get("seq")?,
                    state: r.try_get("state")?,
                    done_ms: r.try_get("done_ms")?,
                })
            })
            .collect()
    }

    /// Records that rounds up to `round` were checked and did not stop the phase.
    pub async fn set_rounds_checked(&self, job_id: i64, idx: i64, round: i64) -> Result<()> {
        let sql = self.sql(
            "UPDATE phases SET rounds_checked = ? WHERE job_id = ? AND idx = ? AND rounds_checked < ? AND stop_round IS NULL",
        );
        sqlx::query(&sql)
            .bind(round)
            .bind(job_id)
            .bind(idx)
            .bind(round)
            .execute(&self.pool)
            .await?;
        Ok(())
    }

    /// Stops an adaptive phase after `round`: in one transaction, records the stop (only if
    /// none is recorded) and marks every task from `first_skipped_seq` on `skipped` (leases in
    /// hand become stale; results already accepted are kept but not merged). Returns whether
    /// this call stopped it.
    pub async fn stop_after_round(
        &self,
        job_id: i64,
        idx: i64,
        round: i64,
        first_skipped_seq: i64,
    ) -> Result<bool> {
        let mut tx = self.pool.begin().await?;
        let sql = self.sql(
            "UPDATE phases SET stop_round = ?, rounds_checked = ? WHERE job_id = ? AND idx = ? AND stop_round IS NULL",
        );
        let r = sqlx::query(&sql)
            .bind(round)
            .bind(round)
            .bind(job_id)
            .bind(idx)
            .execute(&mut *tx)
            .await?;
        if r.rows_affected() != 1 {
            tx.rollback().await?;
            return Ok(false);
        }
        let sql = self.sql(
            "UPDATE tasks SET state = 'skipped', worker_id = NULL, lease_expires_ms = NULL \
             WHERE job_id = ? AND phase_idx = ? AND seq >= ? AND state <> 'skipped'",
        );
        sqlx::query(&sql)
            .bind(job_id)
            .bind(idx)
            .bind(first_skipped_seq)
            .execute(&mut *tx)
            .await?;
        tx.commit().await?;
        Ok(true)
    }

    /// Marks the last phase of a finished job finished (no-op when already marked).
    pub async fn finish_phase(&self, job_id: i64, idx: i64) -> Result<()> {
        let sql = self.sql(
            "UPDATE phases SET finished_ms = ? WHERE job_id = ? AND idx = ? AND finished_ms IS NULL",
        );
        sqlx::query(&sql)
            .bind(now_ms())
            .bind(job_id)
            .bind(idx)
            .execute(&self.pool)
            .await?;
        Ok(())
    }

    /// The newest coefficient table address of a job (the render phase's), if solved.
    pub async fn coefficients_of(&self, job_id: i64) -> Result<Option<String>> {
        Ok(self
            .phases(job_id)
            .await?
            .into_iter()
            .rev()
            .find_map(|p| p.coefficients))
    }

    /// Accepted results of a phase in canonical task order: frames of header and pixels (a
    /// `train` result's table is kept apart, see [`Store::phase_tables`]).
    pub async fn phase_results(&self, job_id: i64, phase_idx: i64) -> Result<Vec<Vec<u8>>> {
        let rows = self
            .accepted_results(job_id, phase_idx, "r.data AS data")
            .await?;
        rows.iter().map(|r| Ok(r.try_get("data")?)).collect()
    }

    /// `columns` of the accepted results (`r`) of a phase's done tasks (`t`), in canonical
    /// task order.
    async fn accepted_results(
        &self,
        job_id: i64,
        phase_idx: i64,
        columns: &str,
    ) -> Result<Vec<AnyRow>> {
        let sql = self.sql(&format!(
            "SELECT {columns} FROM tasks t JOIN results r ON r.task_id = t.id AND r.attempt = t.done_attempt \
             WHERE t.job_id = ? AND t.phase_idx = ? AND t.state = 'done' ORDER BY t.seq"
        ));
        Ok(sqlx::query(&sql)
            .bind(job_id)
            .bind(phase_idx)
            .fetch_all(&self.pool)
            .await?)
    }

    /// The training tables of a phase's accepted results in canonical task order (the train
    /// barrier's input), each as stored: the table alone, or, for a result stored before
    /// tables were kept apart, the whole frame that carries it.
    pub async fn phase_tables(&self, job_id: i64, phase_idx: i64) -> Result<Vec<StoredTable>> {
        let columns = "r.cells AS cells, CASE WHEN r.cells IS NULL THEN r.data END AS data";
        let rows = self.accepted_results(job_id, phase_idx, columns).await?;
        rows.iter()
            .map(|r| {
                Ok(match r.try_get::<Option<Vec<u8>>, _>("cells")? {
                    Some(t) => StoredTable::Table(t),
                    None => StoredTable::Frame(r.try_get("data")?),
                })
            })
            .collect()
    }

    /// Stores an output of a job (no-op when present: outputs are deterministic).
    pub async fn put_artifact(
        &self,
        job_id: i64,
        name: &str,
        content_type: &str,
        data: &[u8],
    ) -> Result<()> {
        let sql = self.sql(
            "INSERT INTO artifacts (job_id, name, content_type, data) VALUES (?, ?, ?, ?) \
             ON CONFLICT (job_id, name) DO NOTHING",
        );
        sqlx::query(&sql)
            .bind(job_id)
            .bind(name)
            .bind(content_type)
            .bind(data.to_vec())
            .execute(&self.pool)
            .await?;
        Ok(())
    }

    /// An output of a job: (content type, bytes).
    pub async fn artifact(&self, job_id: i64, name: &str) -> Result<Option<(String, Vec<u8>)>> {
        let sql =
            self.sql("SELECT content_type, data FROM artifacts WHERE job_id = ? AND name = ?");
        match sqlx::query(&sql)
            .bind(job_id)
            .bind(name)
            .fetch_optional(&self.pool)
            .await?
        {
            Some(r) => Ok(Some((r.try_get("content_type")?, r.try_get("data")?))),
            None => Ok(None),
        }
    }

    // ---- queue -------------------------------------------------------------------------

    /// Claims the next pending task for `worker_id`: highest priority first, FIFO within a
    /// priority, canonical order within a job; skips jobs that blocked this worker.
    pub async fn claim(
        &self,
        worker_id: i64,
        lease_ms: i64,
        max_worker_failures: i64,
    ) -> Result<Option<LeasedTask>> {
        let lock = match self.backend {
            Backend::Postgres => " FOR UPDATE OF t SKIP LOCKED",
            Backend::Sqlite => "",
        };
        let now = now_ms();
        let sql = self.sql(&format!(
            "UPDATE tasks SET state = 'leased', attempt = attempt + 1, worker_id = ?, lease_expires_ms = ? \
             WHERE state = 'pending' AND id = ( \
               SELECT t.id FROM tasks t JOIN jobs j ON j.id = t.job_id \
               WHERE t.state = 'pending' AND j.state = 'running' AND t.phase_idx = j.phase_idx \
                 AND NOT EXISTS (SELECT 1 FROM worker_job_failures f \
                                 WHERE f.job_id = t.job_id AND f.worker_id = ? AND f.failures >= ?) \
               ORDER BY j.priority DESC, j.id ASC, t.seq ASC LIMIT 1{lock}) \
             RETURNING id, job_id, phase_idx, x0, y0, width, height, sample_start, sample_end, attempt"
        ));
        let row = sqlx::query(&sql)
            .bind(worker_id)
            .bind(now + lease_ms)
            .bind(worker_id)
            .bind(max_worker_failures)
            .fetch_optional(&self.pool)
            .await?;
        let Some(r) = row else { return Ok(None) };
        let task = LeasedTask {
            id: r.try_get("id")?,
            job_id: r.try_get("job_id")?,
            phase_idx: r.try_get("phase_idx")?,
            rect: rect_of(&r)?,
            sample_start: u32_of(&r, "sample_start")?,
            sample_end: u32_of(&r, "sample_end")?,
            attempt: r.try_get("attempt")?,
        };
        let sql = self.sql(
            "UPDATE phases SET started_ms = ? WHERE job_id = ? AND idx = ? AND started_ms IS NULL",
        );
        sqlx::query(&sql)
            .bind(now)
            .bind(task.job_id)
            .bind(task.phase_idx)
            .execute(&self.pool)
            .await?;
        let sql = self.sql("UPDATE workers SET last_seen_ms = ? WHERE id = ?");
        sqlx::query(&sql)
            .bind(now)
            .bind(worker_id)
            .execute(&self.pool)
            .await?;
        Ok(Some(task))
    }

    /// A task by id.
    pub async fn task(&self, id: i64) -> Result<Option<TaskRow>> {
        let sql = self.sql(&format!("SELECT {TASK_COLS} FROM tasks WHERE id = ?"));
        let Some(r) = sqlx::query(&sql)
            .bind(id)
            .fetch_optional(&self.pool)
            .await?
        else {
            return Ok(None);
        };
        Ok(Some(TaskRow {
            id: r.try_get("id")?,
            job_id: r.try_get("job_id")?,
            phase_idx: r.try_get("phase_idx")?,
            seq: r.try_get("seq")?,
            rect: rect_of(&r)?,
            sample_start: u32_of(&r, "sample_start")?,
            sample_end: u32_of(&r, "sample_end")?,
            state: r.try_get("state")?,
            attempt: r.try_get("attempt")?,
            worker_id: r.try_get("worker_id")?,
            done_attempt: r.try_get("done_attempt")?,
        }))
    }

    /// Extends the lease of (task, attempt) held by `worker_id`; false when it is not held.
    pub async fn heartbeat(
        &self,
        task_id: i64,
        attempt: i64,
        worker_id: i64,
        lease_ms: i64,
    ) -> Result<bool> {
        let sql = self.sql(
            "UPDATE tasks SET lease_expires_ms = ? WHERE id = ? AND attempt = ? AND worker_id = ? AND state = 'leased' \
             AND EXISTS (SELECT 1 FROM jobs j WHERE j.id = tasks.job_id AND j.state IN ('running', 'paused'))",
        );
        let r = sqlx::query(&sql)
            .bind(now_ms() + lease_ms)
            .bind(task_id)
            .bind(attempt)
            .bind(worker_id)
            .execute(&self.pool)
            .await?;
        Ok(r.rows_affected() == 1)
    }

    /// Gives a lease back without counting a failure (graceful worker shutdown).
    pub async fn release(&self, task_id: i64, attempt: i64, worker_id: i64) -> Result<bool> {
        let sql = self.sql(
            "UPDATE tasks SET state = 'pending', worker_id = NULL, lease_expires_ms = NULL \
             WHERE id = ? AND attempt = ? AND worker_id = ? AND state = 'leased'",
        );
        let r = sqlx::query(&sql)
            .bind(task_id)
            .bind(attempt)
            .bind(worker_id)
            .execute(&self.pool)
            .await?;
        Ok(r.rows_affected() == 1)
    }

    /// Records a failed attempt (lease expired or worker reported failure): the task goes
    /// back to pending, its failure count and the worker's count for the job grow. Returns
    /// the task's failure count, or `None` when (task, attempt) was no longer leased.
    pub async fn fail_attempt(
        &self,
        task_id: i64,
        attempt: i64,
        worker_id: Option<i64>,
    ) -> Result<Option<(i64, i64)>> {
        let mut tx = self.pool.begin().await?;
        let sql = self.sql(
            "UPDATE tasks SET state = 'pending', worker_id = NULL, lease_expires_ms = NULL, failures = failures + 1 \
             WHERE id = ? AND attempt = ? AND state = 'leased' RETURNING failures, job_id",
        );
        let Some(r) = sqlx::query(&sql)
            .bind(task_id)
            .bind(attempt)
            .fetch_optional(&mut *tx)
            .await?
        else {
            return Ok(None);
        };
        let failures: i64 = r.try_get("failures")?;
        let job_id: i64 = r.try_get("job_id")?;
        if let Some(w) = worker_id {
            let sql = self.sql(
                "INSERT INTO worker_job_failures (job_id, worker_id, failures) VALUES (?, ?, 1) \
                 ON CONFLICT (job_id, worker_id) DO UPDATE SET failures = worker_job_failures.failures + 1",
            );
            sqlx::query(&sql)
                .bind(job_id)
                .bind(w)
                .execute(&mut *tx)
                .await?;
        }
        tx.commit().await?;
        Ok(Some((failures, job_id)))
    }

    /// Leases that expired before now: (task id, attempt, worker).
    pub async fn expired_leases(&self) -> Result<Vec<(i64, i64, Option<i64>)>> {
        let sql = self.sql(
            "SELECT id, attempt, worker_id FROM tasks WHERE state = 'leased' AND lease_expires_ms < ? ORDER BY id LIMIT 1000",
        );
        let rows = sqlx::query(&sql)
            .bind(now_ms())
            .fetch_all(&self.pool)
            .await?;
        rows.iter()
            .map(|r| {
                Ok((
                    r.try_get("id")?,
                    r.try_get("attempt")?,
                    r.try_get("worker_id")?,
                ))
            })
            .collect()
    }

    /// Stores the result of (task, attempt) uploaded by `worker_id`, atomically with the
    /// task's transition to `done`: `data` is the validated frame without cell blocks, `cells`
    /// the encoded training table of a `train` result (stored apart, so that assembling the
    /// image never reads it). Idempotent for an accepted (task, attempt).
    pub async fn store_result(
        &self,
        task_id: i64,
        attempt: i64,
        worker_id: i64,
        data: &[u8],
        cells: Option<&[u8]>,
    ) -> Result<UploadOutcome> {
        let mut tx = self.pool.begin().await?;
        let sql = self.sql("SELECT attempt FROM results WHERE task_id = ? AND attempt = ?");
        if sqlx::query(&sql)
            .bind(task_id)
            .bind(attempt)
            .fetch_optional(&mut *tx)
            .await?
            .is_some()
        {
            return Ok(UploadOutcome::Duplicate);
        }
        let now = now_ms();
        let sql = self.sql(
            "UPDATE tasks SET state = 'done', done_attempt = ?, done_ms = ?, lease_expires_ms = NULL \
             WHERE id = ? AND attempt = ? AND worker_id = ? AND state = 'leased' \
             AND EXISTS (SELECT 1 FROM jobs j WHERE j.id = tasks.job_id AND j.state IN ('running', 'paused'))",
        );
        let r = sqlx::query(&sql)
            .bind(attempt)
            .bind(now)
            .bind(task_id)
            .bind(attempt)
            .bind(worker_id)
            .execute(&mut *tx)
            .await?;
        if r.rows_affected() != 1 {
            return Ok(UploadOutcome::Stale);
        }
        let sql = self.sql(
            "INSERT INTO results (task_id, attempt, data, cells, created_ms) VALUES (?, ?, ?, ?, ?)",
        );
        sqlx::query(&sql)
            .bind(task_id)
            .bind(attempt)
            .bind(data.to_vec())
            .bind(cells.map(<[u8]>::to_vec))
            .bind(now)
            .execute(&mut *tx)
            .await?;
        tx.commit().await?;
        Ok(UploadOutcome::Accepted)
    }

    /// Counts for `/metrics`.
    pub async fn metrics(&self) -> Result<Metrics> {
        let mut m = Metrics::default();
        for r in sqlx::query("SELECT state, COUNT(*) AS n FROM jobs GROUP BY state ORDER BY state")
            .fetch_all(&self.pool)
            .await?
        {
            m.jobs.push((r.try_get("state")?, r.try_get("n")?));
        }
        for r in sqlx::query("SELECT state, COUNT(*) AS n FROM tasks GROUP BY state ORDER BY state")
            .fetch_all(&self.pool)
            .await?
        {
            m.tasks.push((r.try_get("state")?, r.try_get("n")?));
        }
        let r = sqlx::query(
            "SELECT CAST(COALESCE(SUM(attempt), 0) AS BIGINT) AS a, CAST(COALESCE(SUM(failures), 0) AS BIGINT) AS f FROM tasks",
        )
        .fetch_one(&self.pool)
        .await?;
        m.attempts = r.try_get("a")?;
        m.failures = r.try_get("f")?;
        m.workers = sqlx::query("SELECT COUNT(*) AS n FROM workers")
            .fetch_one(&self.pool)
            .await?
            .try_get("n")?;
        Ok(m)
    }

    /// Number of result rows stored for a job (tests: nothing rendered twice is stored twice).
    pub async fn result_count(&self, job_id: i64) -> Result<i64> {
        let sql = self.sql(
            "SELECT COUNT(*) AS n FROM results r JOIN tasks t ON t.id = r.task_id WHERE t.job_id = ?",
        );
        Ok(sqlx::query(&sql)
            .bind(job_id)
            .fetch_one(&self.pool)
            .await?
            .try_get("n")?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn placeholders_are_numbered_in_order() {
        assert_eq!(dollar_placeholders("SELECT 1"), "SELECT 1");
        assert_eq!(
            dollar_placeholders(
                "UPDATE t SET a = ?, b = ? WHERE id = ? AND x IN (?, ?, ?, ?, ?, ?, ?, ?)"
            ),
            "UPDATE t SET a = $1, b = $2 WHERE id = $3 AND x IN ($4, $5, $6, $7, $8, $9, $10, $11)"
        );
    }

    #[tokio::test]
    async fn unknown_url_scheme_is_an_error() {
        let e = Store::connect("mysql://x").await.unwrap_err();
        assert!(matches!(e, StoreError::BadUrl(_)), "{e}");
    }
}
