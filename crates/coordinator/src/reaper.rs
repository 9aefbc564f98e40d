//! The reaper: a background loop that reclaims expired leases (counting a failed attempt
//! against the task, and against the worker for that job) and advances jobs whose active
//! phase is complete — runs the phase barrier or finishes the job — when nobody did yet (e.g.
//! the coordinator died between a phase's last upload and its barrier). Each pass reads everything it needs from the store, so several
//! coordinators may run reapers against one PostgreSQL safely: every transition is a
//! conditional update that only one of them wins.

use std::sync::Arc;
use std::time::Duration;

use protocol::lease::JobState;

use crate::AppState;
use crate::store::StoreError;

/// Runs passes every `reaper_interval_ms` until `stop` turns true.
pub async fn run(state: Arc<AppState>, mut stop: tokio::sync::watch::Receiver<bool>) {
    let period = Duration::from_millis(state.config.reaper_interval_ms.max(10));
    loop {
        if let Err(e) = pass(&state).await {
            tracing::warn!(error = %e, "reaper pass failed");
        }
        tokio::select! {
            _ = tokio::time::sleep(period) => {}
            _ = stop.changed() => return,
        }
    }
}

/// One pass: expire leases, fail jobs over the retry cap, advance jobs with a complete phase.
#[tracing::instrument(skip_all)]
pub async fn pass(state: &AppState) -> Result<(), StoreError> {
    let store = &state.store;
    let mut freed = false;
    for (task_id, attempt, worker) in store.expired_leases().await? {
        if let Some((failures, job_id)) = store.fail_attempt(task_id, attempt, worker).await? {
            tracing::info!(task = task_id, attempt, failures, "lease expired");
            freed = true;
            if failures >= i64::from(state.config.max_attempts) {
                let msg = format!(
                    "task {task_id} failed {failures} attempts (retry cap {})",
                    state.config.max_attempts
                );
                store.end_job(job_id, JobState::Failed, Some(&msg)).await?;
            }
        }
    }
    if freed {
        state.work_available.notify_waiters();
    }
    for job_id in store.finishable_jobs().await? {
        match crate::finish::finish_job(state, job_id).await {
            Ok(_) => {}
            // Stored results that cannot be assembled will not get better: fail the job
            // instead of retrying forever. Store errors are transient: retry next pass.
            Err(
                e @ (crate::finish::FinishError::Corrupt(_) | crate::finish::FinishError::Image(_)),
            ) => {
                tracing::error!(job = job_id, error = %e, "finishing failed; failing the job");
                store
                    .end_job(job_id, JobState::Failed, Some(&e.to_string()))
                    .await?;
            }
            Err(e) => tracing::warn!(job = job_id, error = %e, "finishing failed; will retry"),
        }
    }
    Ok(())
}
