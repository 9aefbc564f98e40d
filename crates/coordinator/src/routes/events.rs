//! Observing jobs: `GET /v1/events` (Server-Sent Events) and `GET /v1/jobs/{id}/convergence.csv`.
//!
//! # Events
//! The coordinator keeps no state outside the store and several coordinators may share one
//! PostgreSQL, so events are not pushed by the code that changes a job: each stream is a
//! **read-side poller** that reads the jobs, their phases and task counts every
//! [`POLL_INTERVAL`], compares them with what it has sent, and emits the differences:
//!
//! | event | when | data (JSON) |
//! |---|---|---|
//! | `job` | a job appears or its state changes (`running`, `paused`, `done`, `failed`, `cancelled`) | `{"job", "state", "phase", "error"}` |
//! | `phase` | a phase starts, finishes, or gets its input from the previous barrier: the surrogate image or the coefficient table (the "coefficients announced" event) | `{"job", "idx", "phase", "started_ms", "finished_ms", "surrogate", "coefficients"}` |
//! | `progress` | tasks done changed; at most once per [`PROGRESS_INTERVAL`] per job, but at once when a phase completes, the next one begins or the job ends | `{"job", "tasks_done", "tasks_total", "phase_idx", "phase_done", "phase_total"}` |
//!
//! `?job=ID` restricts the stream to one job (404 when it does not exist). A fresh stream
//! first reports every running or paused job (its state, its phases that started or have an input, its progress); jobs
//! that ended before the stream opened are not replayed. Comments are sent every
//! [`KEEP_ALIVE`] so proxies keep the connection; the stream ends when the coordinator
//! shuts down.
//!
//! # Event ids and `Last-Event-ID`
//! Events are **state reports** (a `job` event says what state the job is in, not that it
//! changed from something), so delivering one twice is harmless and resumption is defined as
//! at-least-once. An id is `poll_ms × 1000 + n`: the wall-clock millisecond of the poll that
//! found the change and a counter, forced to exceed the previous id of the stream, so ids
//! strictly increase within a stream *and across a resumption* (a resumed stream starts
//! counting above the id the client sent). The id is a time rather than a per-job counter
//! because the store has no event log (pausing, for one, leaves no timestamp) and ids must
//! order events of different jobs in one stream.
//!
//! Resuming with `Last-Event-ID: L` reports, as a fresh stream does, every running or paused
//! job, and also every job that ended at or after `L / 1000 − RESUME_MARGIN` ms: the margin
//! covers commits that became visible after the poll that produced `L`, and clock skew between
//! coordinators writing `finished_ms`. A client that missed events thus gets the current state
//! of everything it may have missed.
//!
//! # Convergence
//! `convergence.csv` is computed on read from the stored task rows and results
//! ([`crate::convergence`]); it works for running jobs (rounds completed so far).

use std::collections::{BTreeMap, HashMap, VecDeque};
use std::convert::Infallible;
use std::sync::Arc;
use std::time::Duration;

use axum::Router;
use axum::extract::rejection::{PathRejection, QueryRejection};
use axum::extract::{Path, Query, State};
use axum::http::{HeaderMap, header};
use axum::response::IntoResponse;
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::routing::get;
use protocol::job::TileRect;
use protocol::lease::JobState;
use serde::{Deserialize, Serialize};
use sqlx::Row;
use sqlx::any::AnyRow;

use crate::AppState;
use crate::auth::require_token;
use crate::convergence::{self, TaskSample};
use crate::error::{AppError, AppResult};
use crate::store::{Backend, Store, StoreError, dollar_placeholders, now_ms};

/// How often a stream reads the store.
pub const POLL_INTERVAL: Duration = Duration::from_millis(250);
/// Shortest time between two `progress` events of one job (a phase completing is always sent).
pub const PROGRESS_INTERVAL: Duration = Duration::from_millis(1000);
/// Period of keep-alive comments.
pub const KEEP_ALIVE: Duration = Duration::from_secs(15);
/// How far before a resumed stream's last id ended jobs are reported again.
pub const RESUME_MARGIN: Duration = Duration::from_secs(10);
/// How long an ended job stays in a stream's view after it ended (then it is forgotten).
const ENDED_WINDOW_MS: i64 = 60_000;
/// Most jobs one poll reads.
const MAX_JOBS_PER_POLL: i64 = 1000;

/// Routes of this module.
pub fn router() -> Router<Arc<AppState>> {
    Router::new()
        .route("/v1/events", get(events))
        .route("/v1/jobs/{id}/convergence.csv", get(convergence_csv))
}

/// Query of `/v1/events`.
#[derive(Clone, Copy, Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EventsQuery {
    /// Only this job.
    pub job: Option<i64>,
}

/// Data of a `job` event.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct JobEvent {
    /// Job id.
    pub job: i64,
    /// State.
    pub state: JobState,
    /// Name of the active phase.
    pub phase: Option<String>,
    /// Failure reason.
    pub error: Option<String>,
}

/// Data of a `phase` event.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct PhaseEvent {
    /// Job id.
    pub job: i64,
    /// Phase index.
    pub idx: i64,
    /// Phase name (`surrogate`, `train`, `render`).
    pub phase: String,
    /// First lease (ms since the epoch).
    pub started_ms: Option<i64>,
    /// Completion (ms since the epoch).
    pub finished_ms: Option<i64>,
    /// Content address of the surrogate image the phase trains with.
    pub surrogate: Option<String>,
    /// Content address of the coefficient table the phase renders with (set by the train
    /// barrier: this is the announcement of a solved table).
    pub coefficients: Option<String>,
}

impl PhaseEvent {
    /// Whether there is anything to report yet (a phase that has not started and has no
    /// input is only planned).
    fn reportable(&self) -> bool {
        self.started_ms.is_some()
            || self.finished_ms.is_some()
            || self.surrogate.is_some()
            || self.coefficients.is_some()
    }
}

/// Data of a `progress` event.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct ProgressEvent {
    /// Job id.
    pub job: i64,
    /// Tasks done over all phases.
    pub tasks_done: i64,
    /// Tasks over all phases (not counting tasks skipped by an early stop).
    pub tasks_total: i64,
    /// Active phase.
    pub phase_idx: i64,
    /// Tasks done in the active phase.
    pub phase_done: i64,
    /// Tasks in the active phase.
    pub phase_total: i64,
}

/// A job as one poll sees it.
#[derive(Clone, Debug)]
struct JobView {
    state: JobState,
    phase_idx: i64,
    error: Option<String>,
    phases: BTreeMap<i64, PhaseEvent>,
    /// phase index → (done, total).
    tasks: BTreeMap<i64, (i64, i64)>,
}

impl JobView {
    fn progress(&self, job: i64) -> ProgressEvent {
        let (done, total) = self
            .tasks
            .values()
            .fold((0, 0), |(d, t), (d1, t1)| (d + d1, t + t1));
        let (phase_done, phase_total) = self.tasks.get(&self.phase_idx).copied().unwrap_or((0, 0));
        ProgressEvent {
            job,
            tasks_done: done,
            tasks_total: total,
            phase_idx: self.phase_idx,
            phase_done,
            phase_total,
        }
    }
}

/// What a stream has sent about one job.
#[derive(Clone, Debug)]
struct Sent {
    state: JobState,
    phases: BTreeMap<i64, PhaseEvent>,
    progress: Option<ProgressEvent>,
    progress_at_ms: i64,
}

fn ended(s: JobState) -> bool {
    !matches!(s, JobState::Running | JobState::Paused)
}

/// An event to send, before it gets its id.
#[derive(Clone, Debug, PartialEq)]
enum Outgoing {
    Job(JobEvent),
    Phase(PhaseEvent),
    Progress(ProgressEvent),
}

/// What a stream has sent, per job, and the pure rule turning a new view into events.
#[derive(Debug, Default)]
struct Tracker {
    sent: HashMap<i64, Sent>,
}

impl Tracker {
    /// The events that bring a client from what it was sent about job `id` to `view`, seen
    /// at `now` (ms): a running job is announced before its phases and progress, an end
    /// after them; progress at most every [`PROGRESS_INTERVAL`] unless a phase completed, the
    /// active phase changed or the job ended.
    fn diff(&mut self, id: i64, view: &JobView, now: i64) -> Vec<Outgoing> {
        let mut out = Vec::new();
        let prev = self.sent.get(&id).cloned();
        let state_changed = prev.as_ref().is_none_or(|p| p.state != view.state);
        let job_event = JobEvent {
            job: id,
            state: view.state,
            phase: view.phases.get(&view.phase_idx).map(|p| p.phase.clone()),
            error: view.error.clone(),
        };
        if state_changed && !ended(view.state) {
            out.push(Outgoing::Job(job_event.clone()));
        }
        for (idx, ph) in &view.phases {
            let before = prev.as_ref().and_then(|p| p.phases.get(idx));
            if ph.reportable() && before != Some(ph) {
                out.push(Outgoing::Phase(ph.clone()));
            }
        }
        let progress = view.progress(id);
        let last = prev.as_ref().and_then(|p| p.progress);
        let due = prev
            .as_ref()
            .is_none_or(|p| now - p.progress_at_ms >= PROGRESS_INTERVAL.as_millis() as i64);
        let phase_complete =
            progress.phase_total > 0 && progress.phase_done == progress.phase_total;
        let mut progress_at_ms = prev.as_ref().map_or(0, |p| p.progress_at_ms);
        let mut progress_sent = last;
        let phase_moved = last.is_some_and(|l| l.phase_idx != progress.phase_idx);
        if last != Some(progress) && (due || phase_complete || phase_moved || ended(view.state)) {
            out.push(Outgoing::Progress(progress));
            progress_at_ms = now;
            progress_sent = Some(progress);
        }
        if state_changed && ended(view.state) {
            out.push(Outgoing::Job(job_event));
        }
        self.sent.insert(
            id,
            Sent {
                state: view.state,
                phases: view
                    .phases
                    .iter()
                    .filter(|(_, p)| p.reportable())
                    .map(|(k, v)| (*k, v.clone()))
                    .collect(),
                progress: progress_sent,
                progress_at_ms,
            },
        );
        out
    }

    /// Jobs reported as running or paused (their end must still be reported).
    fn unfinished(&self) -> impl Iterator<Item = i64> + '_ {
        self.sent
            .iter()
            .filter(|(_, s)| !ended(s.state))
            .map(|(id, _)| *id)
    }

    /// Forgets ended jobs that are not in `views` any more.
    fn forget_ended_except(&mut self, views: &BTreeMap<i64, JobView>) {
        self.sent
            .retain(|id, s| views.contains_key(id) || !ended(s.state));
    }
}

/// One stream's poller: its filter, cursor and what it has sent.
struct Poller {
    state: Arc<AppState>,
    filter: Option<i64>,
    last_id: u64,
    /// Ended jobs are read when they ended at or after this time (ms).
    horizon_ms: i64,
    tracker: Tracker,
    queue: VecDeque<Event>,
    stopping: tokio::sync::watch::Receiver<bool>,
    polled: bool,
}

impl Poller {
    fn next_id(&mut self) -> u64 {
        let t = u64::try_from(now_ms()).unwrap_or(0).saturating_mul(1000);
        self.last_id = t.max(self.last_id.saturating_add(1));
        self.last_id
    }

    fn push<T: Serialize>(&mut self, kind: &str, data: &T) {
        let id = self.next_id();
        match Event::default()
            .event(kind)
            .id(id.to_string())
            .json_data(data)
        {
            Ok(e) => self.queue.push_back(e),
            Err(e) => tracing::error!(error = %e, "event not serialisable"),
        }
    }

    /// Reads the store and queues the events of every difference.
    async fn poll(&mut self) -> Result<(), StoreError> {
        let now = now_ms();
        let store = &self.state.store;
        let mut views = read_jobs(store, self.filter, self.horizon_ms).await?;
        // Jobs this stream saw running but that fell out of the window (an end time far in
        // the past, e.g. a skewed clock): read them by id so their end is reported.
        let missing: Vec<i64> = self
            .tracker
            .unfinished()
            .filter(|id| !views.contains_key(id))
            .collect();
        for id in missing {
            views.extend(read_jobs(store, Some(id), i64::MIN).await?);
        }
        for (id, view) in &views {
            for e in self.tracker.diff(*id, view, now) {
                match &e {
                    Outgoing::Job(d) => self.push("job", d),
                    Outgoing::Phase(d) => self.push("phase", d),
                    Outgoing::Progress(d) => self.push("progress", d),
                }
            }
        }
        // Forget ended jobs that left the window.
        self.tracker.forget_ended_except(&views);
        if self.polled {
            self.horizon_ms = self.horizon_ms.max(now - ENDED_WINDOW_MS);
        }
        self.polled = true;
        Ok(())
    }

    /// The next event, polling the store as needed; `None` once the coordinator stops.
    async fn next(&mut self) -> Option<Event> {
        loop {
            if let Some(e) = self.queue.pop_front() {
                return Some(e);
            }
            if *self.stopping.borrow() {
                return None;
            }
            if let Err(e) = self.poll().await {
                tracing::warn!(error = %e, "event poll failed; retrying");
            }
            if !self.queue.is_empty() {
                continue;
            }
            tokio::select! {
                _ = tokio::time::sleep(POLL_INTERVAL) => {}
                _ = self.stopping.changed() => {}
            }
        }
    }
}

fn sql(store: &Store, s: &str) -> String {
    match store.backend() {
        Backend::Sqlite => s.to_owned(),
        Backend::Postgres => dollar_placeholders(s),
    }
}

/// `?, ?, …` for `n` values.
/// Runs `template` with `{ids}` replaced by one placeholder per id, bound in order.
async fn rows_for_jobs(
    store: &Store,
    template: &str,
    ids: &[i64],
) -> Result<Vec<sqlx::any::AnyRow>, StoreError> {
    let q = sql(
        store,
        &template.replace("{ids}", &vec!["?"; ids.len()].join(", ")),
    );
    let mut query = sqlx::query(&q);
    for id in ids {
        query = query.bind(*id);
    }
    Ok(query.fetch_all(store.pool()).await?)
}

/// Running or paused jobs, plus those that ended at or after `horizon_ms` (one job only when
/// `only` is set), with their phases and task counts.
async fn read_jobs(
    store: &Store,
    only: Option<i64>,
    horizon_ms: i64,
) -> Result<BTreeMap<i64, JobView>, StoreError> {
    let pool = store.pool();
    let filter = if only.is_some() { " AND id = ?" } else { "" };
    let q = sql(
        store,
        &format!(
            "SELECT id, state, phase_idx, error FROM jobs \
             WHERE (state IN ('running', 'paused') OR finished_ms >= ?){filter} ORDER BY id LIMIT ?"
        ),
    );
    let mut query = sqlx::query(&q).bind(horizon_ms);
    if let Some(id) = only {
        query = query.bind(id);
    }
    let rows = query.bind(MAX_JOBS_PER_POLL).fetch_all(pool).await?;
    let mut views = BTreeMap::new();
    for r in &rows {
        let state: String = r.try_get("state")?;
        let state = JobState::parse(&state)
            .ok_or_else(|| StoreError::Corrupt(format!("job state {state}")))?;
        views.insert(
            r.try_get::<i64, _>("id")?,
            JobView {
                state,
                phase_idx: r.try_get("phase_idx")?,
                error: r.try_get("error")?,
                phases: BTreeMap::new(),
                tasks: BTreeMap::new(),
            },
        );
    }
    if views.is_empty() {
        return Ok(views);
    }
    let ids: Vec<i64> = views.keys().copied().collect();
    let phases = rows_for_jobs(
        store,
        "SELECT job_id, idx, name, surrogate, coefficients, started_ms, finished_ms FROM phases \
         WHERE job_id IN ({ids}) ORDER BY job_id, idx",
        &ids,
    )
    .await?;
    for r in phases {
        let job: i64 = r.try_get("job_id")?;
        let idx: i64 = r.try_get("idx")?;
        if let Some(v) = views.get_mut(&job) {
            v.phases.insert(
                idx,
                PhaseEvent {
                    job,
                    idx,
                    phase: r.try_get("name")?,
                    started_ms: r.try_get("started_ms")?,
                    finished_ms: r.try_get("finished_ms")?,
                    surrogate: r.try_get("surrogate")?,
                    coefficients: r.try_get("coefficients")?,
                },
            );
        }
    }
    let counts = rows_for_jobs(
        store,
        "SELECT job_id, phase_idx, COUNT(*) AS total, \
                CAST(COALESCE(SUM(CASE WHEN state = 'done' THEN 1 ELSE 0 END), 0) AS BIGINT) AS done \
         FROM tasks WHERE job_id IN ({ids}) AND state <> 'skipped' GROUP BY job_id, phase_idx",
        &ids,
    )
    .await?;
    for r in counts {
        let job: i64 = r.try_get("job_id")?;
        if let Some(v) = views.get_mut(&job) {
            v.tasks.insert(
                r.try_get("phase_idx")?,
                (r.try_get("done")?, r.try_get("total")?),
            );
        }
    }
    Ok(views)
}

/// Parses `Last-Event-ID` (absent → `None`; not a number → 400).
fn last_event_id(headers: &HeaderMap) -> AppResult<Option<u64>> {
    let Some(v) = headers.get("last-event-id") else {
        return Ok(None);
    };
    let s = v.to_str().unwrap_or("").trim();
    if s.is_empty() {
        return Ok(None);
    }
    s.parse().map(Some).map_err(|_| {
        AppError::bad_request(
            "invalid_header",
            format!("Last-Event-ID `{s}` is not an event id of this API (a decimal number)"),
        )
    })
}

#[tracing::instrument(skip_all, fields(job = query.as_ref().ok().and_then(|q| q.job)))]
async fn events(
    State(st): State<Arc<AppState>>,
    headers: HeaderMap,
    query: Result<Query<EventsQuery>, QueryRejection>,
) -> AppResult<impl IntoResponse> {
    require_token(&headers, &st.config.client_tokens)?;
    let Query(q) = query?;
    let resume = last_event_id(&headers)?;
    if let Some(id) = q.job
        && st.store.job(id).await?.is_none()
    {
        return Err(AppError::NotFound(format!("job {id}")));
    }
    let horizon_ms = match resume {
        Some(l) => i64::try_from(l / 1000)
            .unwrap_or(i64::MAX)
            .saturating_sub(RESUME_MARGIN.as_millis() as i64),
        None => now_ms(),
    };
    let poller = Poller {
        stopping: st.stopping.subscribe(),
        state: st,
        filter: q.job,
        last_id: resume.unwrap_or(0),
        horizon_ms,
        tracker: Tracker::default(),
        queue: VecDeque::new(),
        polled: false,
    };
    let stream = futures_util::stream::unfold(poller, |mut p| async move {
        p.next().await.map(|e| (Ok::<_, Infallible>(e), p))
    });
    Ok(Sse::new(stream).keep_alive(KeepAlive::new().interval(KEEP_ALIVE).text("keep-alive")))
}

fn task_sample(r: &AnyRow) -> Result<TaskSample, StoreError> {
    let u = |col: &str| -> Result<u32, StoreError> {
        let v: i64 = r.try_get(col)?;
        u32::try_from(v).map_err(|_| StoreError::Corrupt(format!("{col} = {v}")))
    };
    let state: String = r.try_get("state")?;
    let done = state == "done";
    Ok(TaskSample {
        phase_idx: r.try_get("phase_idx")?,
        seq: r.try_get("seq")?,
        rect: TileRect {
            x0: u("x0")?,
            y0: u("y0")?,
            width: u("width")?,
            height: u("height")?,
        },
        sample_start: u("sample_start")?,
        sample_end: u("sample_end")?,
        done_ms: if done { r.try_get("done_ms")? } else { None },
        data: if done { r.try_get("data")? } else { None },
    })
}

/// Every task of a job with its accepted result when done; tasks skipped by an early stop
/// (a time budget or error target met) never run, so they form no round.
async fn job_tasks(store: &Store, job_id: i64) -> Result<Vec<TaskSample>, StoreError> {
    let q = sql(
        store,
        "SELECT t.phase_idx AS phase_idx, t.seq AS seq, t.x0 AS x0, t.y0 AS y0, t.width AS width, \
                t.height AS height, t.sample_start AS sample_start, t.sample_end AS sample_end, \
                t.state AS state, t.done_ms AS done_ms, r.data AS data \
         FROM tasks t LEFT JOIN results r ON r.task_id = t.id AND r.attempt = t.done_attempt \
         WHERE t.job_id = ? AND t.state <> 'skipped' ORDER BY t.phase_idx, t.seq",
    );
    sqlx::query(&q)
        .bind(job_id)
        .fetch_all(store.pool())
        .await?
        .iter()
        .map(task_sample)
        .collect()
}

#[tracing::instrument(skip_all)]
async fn convergence_csv(
    State(st): State<Arc<AppState>>,
    headers: HeaderMap,
    id: Result<Path<i64>, PathRejection>,
) -> AppResult<impl IntoResponse> {
    require_token(&headers, &st.config.client_tokens)?;
    let Path(id) = id?;
    let job = st
        .store
        .job(id)
        .await?
        .ok_or_else(|| AppError::NotFound(format!("job {id}")))?;
    let tasks = job_tasks(&st.store, id).await?;
    let max_pixels = st.config.limits.max_pixels as usize;
    let (w, h, created) = (job.resolved.width, job.resolved.height, job.created_ms);
    // Decoding and merging are CPU work: keep them off the async workers.
    let csv = tokio::task::spawn_blocking(move || {
        convergence::series(w, h, created, &tasks, max_pixels).map(|r| convergence::to_csv(&r))
    })
    .await
    .map_err(|e| AppError::Internal(e.to_string()))?
    .map_err(|e| AppError::Internal(e.to_string()))?;
    Ok(([(header::CONTENT_TYPE, "text/csv; charset=utf-8")], csv))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn last_event_id_parses_or_is_a_400() {
        let mut h = HeaderMap::new();
        assert_eq!(last_event_id(&h).unwrap(), None);
        h.insert("last-event-id", "1763900000000123".parse().unwrap());
        assert_eq!(last_event_id(&h).unwrap(), Some(1_763_900_000_000_123));
        h.insert("last-event-id", "abc".parse().unwrap());
        assert!(matches!(last_event_id(&h), Err(AppError::BadRequest(_))));
    }

    fn view(state: JobState, phase_idx: i64, tasks: &[(i64, i64)]) -> JobView {
        let phases = (0..tasks.len() as i64)
            .map(|idx| {
                (
                    idx,
                    PhaseEvent {
                        job: 1,
                        idx,
                        phase: ["train", "render"][idx as usize % 2].into(),
                        started_ms: (idx <= phase_idx && tasks[idx as usize].0 > 0).then_some(10),
                        finished_ms: (idx < phase_idx).then_some(20),
                        surrogate: None,
                        coefficients: (idx == 1 && phase_idx == 1).then(|| "ab".repeat(32)),
                    },
                )
            })
            .collect();
        JobView {
            state,
            phase_idx,
            error: None,
            phases,
            tasks: tasks
                .iter()
                .copied()
                .enumerate()
                .map(|(i, t)| (i as i64, t))
                .collect(),
        }
    }

    fn kinds(events: &[Outgoing]) -> Vec<&'static str> {
        events
            .iter()
            .map(|e| match e {
                Outgoing::Job(_) => "job",
                Outgoing::Phase(_) => "phase",
                Outgoing::Progress(_) => "progress",
            })
            .collect()
    }

    #[test]
    fn tracker_reports_changes_once_in_order_and_rate_limits_progress() {
        let mut t = Tracker::default();
        // New running job: state first, then its progress (no phase started yet).
        let e = t.diff(1, &view(JobState::Running, 0, &[(0, 4), (0, 2)]), 0);
        assert_eq!(kinds(&e), ["job", "progress"]);
        // Unchanged: nothing.
        assert!(
            t.diff(1, &view(JobState::Running, 0, &[(0, 4), (0, 2)]), 100)
                .is_empty()
        );
        // A task done 200 ms later: the phase started; progress waits for the interval.
        let e = t.diff(1, &view(JobState::Running, 0, &[(1, 4), (0, 2)]), 200);
        assert_eq!(kinds(&e), ["phase"]);
        let e = t.diff(1, &view(JobState::Running, 0, &[(1, 4), (0, 2)]), 1000);
        assert_eq!(kinds(&e), ["progress"]);
        // The phase completes: progress at once, however recent the last one.
        let e = t.diff(1, &view(JobState::Running, 0, &[(4, 4), (0, 2)]), 1100);
        assert_eq!(kinds(&e), ["progress"]);
        // The barrier: phase 0 finished, phase 1 gets its coefficients before any lease.
        let e = t.diff(1, &view(JobState::Running, 1, &[(4, 4), (0, 2)]), 1200);
        assert_eq!(kinds(&e), ["phase", "phase", "progress"]);
        let Outgoing::Phase(p) = &e[1] else {
            unreachable!()
        };
        assert_eq!(
            (p.idx, p.coefficients.is_some(), p.started_ms),
            (1, true, None)
        );
        // Done: the final progress before the end.
        let e = t.diff(1, &view(JobState::Done, 1, &[(4, 4), (2, 2)]), 1300);
        assert_eq!(kinds(&e), ["phase", "progress", "job"]);
        assert!(matches!(&e[2], Outgoing::Job(j) if j.state == JobState::Done));
        assert_eq!(t.unfinished().count(), 0);
        t.forget_ended_except(&BTreeMap::new());
        assert!(t.sent.is_empty());
    }

    #[test]
    fn progress_sums_phases_and_reports_the_active_one() {
        let v = JobView {
            state: JobState::Running,
            phase_idx: 1,
            error: None,
            phases: BTreeMap::new(),
            tasks: BTreeMap::from([(0, (4, 4)), (1, (1, 6))]),
        };
        let p = v.progress(9);
        assert_eq!((p.tasks_done, p.tasks_total), (5, 10));
        assert_eq!((p.phase_idx, p.phase_done, p.phase_total), (1, 1, 6));
    }
}
