//! Workers: registration with the enrollment token, and the lease long-poll.
//!
//! A lease is claimed atomically in the store (highest priority first, FIFO within a
//! priority, canonical task order within a job); when none is available the request waits
//! up to `wait_ms` (capped by `long_poll_max_ms`), waking when a job is submitted or a lease
//! is freed, and re-polling the store periodically (another coordinator may have done it).

use std::sync::Arc;
use std::time::Duration;

use axum::body::Bytes;
use axum::extract::State;
use axum::extract::rejection::BytesRejection;
use axum::http::{HeaderMap, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::post;
use axum::{Json, Router};
use protocol::JobSpec;
use protocol::hash::sha256_hex;
use protocol::lease::{LeaseRequest, RegisterRequest, RegisterResponse, TaskLease};

use super::parse_json;
use crate::AppState;
use crate::auth::{new_worker_secret, require_token, require_worker, worker_token};
use crate::error::{AppError, AppResult};
use crate::store::LeasedTask;

/// Longest accepted worker name.
pub const MAX_WORKER_NAME: usize = 200;
/// Period at which a waiting long-poll re-checks the store.
const POLL_PERIOD: Duration = Duration::from_millis(200);

/// Routes of this module.
pub fn router() -> Router<Arc<AppState>> {
    Router::new()
        .route("/v1/workers/register", post(register))
        .route("/v1/workers/lease", post(lease))
}

#[tracing::instrument(skip_all)]
async fn register(
    State(st): State<Arc<AppState>>,
    headers: HeaderMap,
    body: Result<Bytes, BytesRejection>,
) -> AppResult<(StatusCode, Json<RegisterResponse>)> {
    require_token(&headers, std::slice::from_ref(&st.config.enrollment_token))?;
    let req: RegisterRequest = parse_json(&body?)?;
    if req.name.is_empty() || req.name.len() > MAX_WORKER_NAME {
        return Err(AppError::unprocessable(
            "invalid_name",
            format!("worker name must have 1..={MAX_WORKER_NAME} bytes"),
            Some("name"),
        ));
    }
    let secret = new_worker_secret();
    let worker_id = st
        .store
        .add_worker(&req.name, &sha256_hex(secret.as_bytes()))
        .await?;
    tracing::info!(worker = worker_id, name = %req.name, "worker registered");
    Ok((
        StatusCode::CREATED,
        Json(RegisterResponse {
            worker_id,
            token: worker_token(worker_id, &secret),
        }),
    ))
}

#[tracing::instrument(skip_all, fields(worker))]
async fn lease(
    State(st): State<Arc<AppState>>,
    headers: HeaderMap,
    body: Result<Bytes, BytesRejection>,
) -> AppResult<Response> {
    let worker = require_worker(&headers, &st.store).await?;
    tracing::Span::current().record("worker", worker);
    let body = body?;
    let req: LeaseRequest = if body.is_empty() {
        LeaseRequest::default()
    } else {
        parse_json(&body)?
    };
    let wait = Duration::from_millis(req.wait_ms.min(st.config.long_poll_max_ms));
    let deadline = tokio::time::Instant::now() + wait;
    let cfg = &st.config;
    loop {
        // Register interest before checking, so a notification between the check and the
        // wait is not lost.
        let notified = st.work_available.notified();
        if let Some(task) = st
            .store
            .claim(
                worker,
                cfg.lease_ms as i64,
                i64::from(cfg.max_worker_failures),
            )
            .await?
        {
            tracing::debug!(task = task.id, attempt = task.attempt, "leased");
            return Ok(Json(build_lease(&st, task).await?).into_response());
        }
        let now = tokio::time::Instant::now();
        if now >= deadline {
            return Ok(StatusCode::NO_CONTENT.into_response());
        }
        let nap = POLL_PERIOD.min(deadline - now);
        tokio::select! {
            _ = notified => {}
            _ = tokio::time::sleep(nap) => {}
        }
    }
}

async fn build_lease(st: &AppState, t: LeasedTask) -> AppResult<TaskLease> {
    let job = st
        .store
        .job_spec(t.job_id)
        .await?
        .ok_or_else(|| AppError::Internal(format!("job {} vanished", t.job_id)))?;
    let spec: JobSpec = serde_json::from_str(&job.spec)
        .map_err(|e| AppError::Internal(format!("stored spec: {e}")))?;
    // The phase row carries the addresses of the phase's inputs, written by the barrier
    // before the job entered the phase.
    let phase = st
        .store
        .phase(t.job_id, t.phase_idx)
        .await?
        .ok_or_else(|| {
            AppError::Internal(format!("job {} has no phase {}", t.job_id, t.phase_idx))
        })?;
    Ok(TaskLease {
        task_id: t.id,
        attempt: u32::try_from(t.attempt).unwrap_or(u32::MAX),
        job_id: t.job_id,
        phase: phase.kind,
        rect: t.rect,
        sample_start: t.sample_start,
        sample_end: t.sample_end,
        scene_hash: job.scene_hash.clone(),
        assets: spec.assets,
        job: job.resolved,
        estimator: spec.estimator,
        surrogate: phase.surrogate,
        coefficients: phase.coefficients,
        lease_ms: st.config.lease_ms,
        heartbeat_ms: st.config.heartbeat_ms,
    })
}
