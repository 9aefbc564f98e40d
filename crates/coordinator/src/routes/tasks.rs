//! Task operations of the worker holding a lease: heartbeat, result upload, release, fail.
//! Every call names the attempt (`?attempt=N`); an attempt that is not the task's current
//! lease held by the caller is **stale** and answered 409 `stale_attempt` — except a repeated
//! upload of an already accepted (task, attempt), which is an idempotent 200.
//!
//! Uploads are validated completely before anything is stored: the frame stream must decode
//! ([`protocol::frame::decode`]: sizes, order, truncation, finite values), and its header must
//! match the task (job, task, attempt, rectangle, sample range). A `train` result must carry
//! exactly one cell block that decodes, is of the job's kind, has finite values, keys in the
//! job's range and the layout of the job's earlier train results
//! ([`protocol::cv::check_train_block`]); otherwise 422 `invalid_cells` naming the problem,
//! and the task stays leased (the worker may fail it, or the lease expires and it is redone).
//! Other phases carry no cell blocks. A train result's table is stored apart from its pixel
//! frame (`results.cells`): the barrier reads the tables, image assembly only the pixels.
//! The upload that completes a phase triggers the phase
//! barrier or the job's finish ([`crate::finish::advance_job`]) in the background.

use std::sync::Arc;

use axum::body::Bytes;
use axum::extract::rejection::{BytesRejection, PathRejection, QueryRejection};
use axum::extract::{DefaultBodyLimit, Path, Query, State};
use axum::http::HeaderMap;
use axum::routing::{post, put};
use axum::{Json, Router};
use estimators::table::AccumulatorTable;
use protocol::lease::{HeartbeatResponse, JobState, PhaseKind, UploadResponse};
use protocol::{ApiError, JobSpec, cv, frame};
use serde::Deserialize;

use crate::AppState;
use crate::auth::require_worker;
use crate::error::{AppError, AppResult};
use crate::store::{TaskRow, UploadOutcome};

/// Routes of this module; result uploads may be up to `max_result_body` bytes.
pub fn router(max_result_body: usize) -> Router<Arc<AppState>> {
    Router::new()
        .route("/v1/tasks/{id}/heartbeat", post(heartbeat))
        .route(
            "/v1/tasks/{id}/result",
            put(upload).layer(DefaultBodyLimit::max(max_result_body)),
        )
        .route("/v1/tasks/{id}/release", post(release))
        .route("/v1/tasks/{id}/fail", post(fail))
}

/// `?attempt=N`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct AttemptQuery {
    attempt: i64,
}

fn stale(task: i64, attempt: i64) -> AppError {
    AppError::conflict(
        "stale_attempt",
        format!(
            "attempt {attempt} of task {task} is not the current lease of this worker (superseded or expired)"
        ),
    )
}

async fn load(
    st: &AppState,
    headers: &HeaderMap,
    id: Result<Path<i64>, PathRejection>,
    q: Result<Query<AttemptQuery>, QueryRejection>,
) -> AppResult<(i64, TaskRow, i64)> {
    let worker = require_worker(headers, &st.store).await?;
    let Path(id) = id?;
    let Query(q) = q?;
    let task = st
        .store
        .task(id)
        .await?
        .ok_or_else(|| AppError::NotFound(format!("task {id}")))?;
    Ok((worker, task, q.attempt))
}

#[tracing::instrument(skip_all)]
async fn heartbeat(
    State(st): State<Arc<AppState>>,
    headers: HeaderMap,
    id: Result<Path<i64>, PathRejection>,
    q: Result<Query<AttemptQuery>, QueryRejection>,
) -> AppResult<Json<HeartbeatResponse>> {
    let (worker, task, attempt) = load(&st, &headers, id, q).await?;
    if st
        .store
        .heartbeat(task.id, attempt, worker, st.config.lease_ms as i64)
        .await?
    {
        Ok(Json(HeartbeatResponse {
            lease_ms: st.config.lease_ms,
        }))
    } else {
        Err(stale(task.id, attempt))
    }
}

#[tracing::instrument(skip_all, fields(task, attempt))]
async fn upload(
    State(st): State<Arc<AppState>>,
    headers: HeaderMap,
    id: Result<Path<i64>, PathRejection>,
    q: Result<Query<AttemptQuery>, QueryRejection>,
    body: Result<Bytes, BytesRejection>,
) -> AppResult<Json<UploadResponse>> {
    let (worker, task, attempt) = load(&st, &headers, id, q).await?;
    tracing::Span::current()
        .record("task", task.id)
        .record("attempt", attempt);
    let body = body?;
    tracing::debug!(bytes = body.len(), "upload received");
    let max_pixels = task.rect.pixel_count();
    let decoded = frame::decode(&body, max_pixels)
        .map_err(|e| AppError::BadRequest(ApiError::new("invalid_frame", e.to_string())))?;
    let h = &decoded.header;
    let mismatch = |what: &str| {
        AppError::BadRequest(ApiError::new(
            "frame_mismatch",
            format!("frame header {what} does not match task {}", task.id),
        ))
    };
    if h.task_id != task.id {
        return Err(mismatch("task id"));
    }
    if h.job_id != task.job_id {
        return Err(mismatch("job id"));
    }
    if i64::from(h.attempt) != attempt {
        return Err(mismatch("attempt"));
    }
    if h.rect != task.rect {
        return Err(mismatch("rectangle"));
    }
    if (h.sample_start, h.sample_end) != (task.sample_start, task.sample_end) {
        return Err(mismatch("sample range"));
    }
    let (layout, table) = match check_cells(&st, &task, &decoded).await? {
        Some((layout, table)) => (layout, Some(table)),
        None => (None, None),
    };
    // A train table is folded into its phase's canonical prefix once accepted; the place
    // is reserved before the result is stored, so the barrier waits for it.
    let place = table
        .is_some()
        .then(|| st.train_merges.reserve(task.job_id, task.phase_idx));
    // A train result's table is stored apart from its pixels (assembly never reads it).
    let pixels_only;
    let (data, cells): (&[u8], Option<&[u8]>) = match decoded.cells.as_slice() {
        [block] => {
            pixels_only = frame::encode(&protocol::TileResult {
                header: decoded.header,
                pixels: decoded.pixels.clone(),
                cells: Vec::new(),
            });
            (&pixels_only, Some(&block.data))
        }
        _ => (&body, None),
    };
    match st
        .store
        .store_result(task.id, attempt, worker, data, cells)
        .await?
    {
        UploadOutcome::Accepted => {
            tracing::debug!("upload stored");
            if let Some(layout) = layout {
                st.store
                    .set_phase_layout(task.job_id, task.phase_idx, &layout)
                    .await?;
            }
            let progress = st.store.progress(task.job_id, task.phase_idx).await?;
            // Check adaptive rounds and finish in the background: the upload is already
            // durable, and should the coordinator die first the reaper (or the next upload)
            // does it after the restart.
            let st2 = st.clone();
            let job = task.job_id;
            let complete = progress.done == progress.total;
            let seq = task.seq;
            tokio::spawn(async move {
                if let (Some(place), Some(table)) = (place, table) {
                    // A fold of one table is milliseconds of CPU: off the async threads.
                    let folded = tokio::task::spawn_blocking(move || place.offer(seq, table)).await;
                    if let Err(e) = folded {
                        tracing::error!(job, error = %e, "folding a train table failed");
                    }
                }
                let stopped = match crate::finish::check_rounds(&st2, job).await {
                    Ok(s) => s,
                    Err(e) => {
                        tracing::error!(job, error = %e, "round check failed");
                        false
                    }
                };
                if stopped {
                    st2.work_available.notify_waiters();
                }
                if (stopped || complete)
                    && let Err(e) = crate::finish::advance_job(&st2, job).await
                {
                    tracing::error!(job, error = %e, "finishing failed");
                }
            });
            Ok(Json(UploadResponse { duplicate: false }))
        }
        UploadOutcome::Duplicate => Ok(Json(UploadResponse { duplicate: true })),
        UploadOutcome::Stale => {
            let job = st.store.job(task.job_id).await?;
            if let Some(job) =
                job.filter(|j| !matches!(j.state, JobState::Running | JobState::Paused))
            {
                return Err(AppError::conflict(
                    "job_not_running",
                    format!("job {} is {}", job.id, job.state.as_str()),
                ));
            }
            Err(stale(task.id, attempt))
        }
    }
}

fn invalid_cells(message: impl Into<String>) -> AppError {
    AppError::unprocessable("invalid_cells", message, None)
}

/// Checks a result's cell block against its phase: none outside `train`; in `train` one
/// valid table of the job's layout. Returns the table's layout signature (to record on the
/// phase when it is the first) and the decoded table for a `train` result, `None` for the
/// other phases.
async fn check_cells(
    st: &AppState,
    task: &TaskRow,
    decoded: &protocol::TileResult,
) -> AppResult<Option<(Option<String>, AccumulatorTable)>> {
    let phase = st
        .store
        .phase(task.job_id, task.phase_idx)
        .await?
        .ok_or_else(|| AppError::Internal(format!("task {} has no phase row", task.id)))?;
    if phase.kind != PhaseKind::Train {
        if !decoded.cells.is_empty() {
            return Err(AppError::BadRequest(ApiError::new(
                "invalid_frame",
                format!(
                    "cell accumulator records are not expected in a {} result",
                    phase.kind.as_str()
                ),
            )));
        }
        return Ok(None);
    }
    let job = st
        .store
        .job_spec(task.job_id)
        .await?
        .ok_or_else(|| AppError::NotFound(format!("job {}", task.job_id)))?;
    let spec: JobSpec = serde_json::from_str(&job.spec)
        .map_err(|e| AppError::Internal(format!("stored spec: {e}")))?;
    let Some(est) = spec.estimator.phased_for(&job.resolved) else {
        return Err(AppError::Internal(format!(
            "job {} has a train phase but estimator `{}` has none",
            job.id, job.estimator
        )));
    };
    let table = cv::check_train_block(&est, &job.resolved, decoded)
        .map_err(|e| invalid_cells(e.to_string()))?;
    let sig = cv::layout_signature(&table).map_err(|e| invalid_cells(e.to_string()))?;
    if let (Some(sig), Some(known)) = (&sig, &phase.layout)
        && sig != known
    {
        return Err(invalid_cells(
            cv::CvError::Layout {
                found: sig.clone(),
                expected: format!("{known} (of the job's earlier train results)"),
            }
            .to_string(),
        ));
    }
    Ok(Some((sig, table)))
}

#[tracing::instrument(skip_all)]
async fn release(
    State(st): State<Arc<AppState>>,
    headers: HeaderMap,
    id: Result<Path<i64>, PathRejection>,
    q: Result<Query<AttemptQuery>, QueryRejection>,
) -> AppResult<Json<serde_json::Value>> {
    let (worker, task, attempt) = load(&st, &headers, id, q).await?;
    if st.store.release(task.id, attempt, worker).await? {
        st.work_available.notify_waiters();
        Ok(Json(serde_json::json!({ "released": true })))
    } else {
        Err(stale(task.id, attempt))
    }
}

#[tracing::instrument(skip_all)]
async fn fail(
    State(st): State<Arc<AppState>>,
    headers: HeaderMap,
    id: Result<Path<i64>, PathRejection>,
    q: Result<Query<AttemptQuery>, QueryRejection>,
    body: Result<Bytes, BytesRejection>,
) -> AppResult<Json<serde_json::Value>> {
    let (worker, task, attempt) = load(&st, &headers, id, q).await?;
    let reason = String::from_utf8_lossy(&body?)
        .chars()
        .take(1000)
        .collect::<String>();
    if task.worker_id != Some(worker) || task.attempt != attempt || task.state != "leased" {
        return Err(stale(task.id, attempt));
    }
    let Some((failures, job_id)) = st
        .store
        .fail_attempt(task.id, attempt, Some(worker))
        .await?
    else {
        return Err(stale(task.id, attempt));
    };
    tracing::warn!(task = task.id, attempt, failures, reason = %reason, "worker reported failure");
    if failures >= i64::from(st.config.max_attempts) {
        let msg = format!(
            "task {} failed {failures} attempts (retry cap); last error: {reason}",
            task.id
        );
        st.store
            .end_job(job_id, JobState::Failed, Some(&msg))
            .await?;
    }
    st.work_available.notify_waiters();
    Ok(Json(serde_json::json!({ "failures": failures })))
}
