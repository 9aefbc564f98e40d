//! Jobs: submit, list, status, cancel, outputs.
//!
//! Submission validates everything before anything is stored: JSON shape (unknown fields
//! rejected), the estimator (known but unimplemented kinds → 422 `unsupported`), limits
//! (resolution, spp, tile size, task count), the scene (parsed, every asset it names mapped
//! to an uploaded blob, then loaded by `scene::load` over those blobs). The job, its phases
//! ([`protocol::job::plan_phases`]) and all their tasks are then created in one transaction.
//!
//! `GET /v1/jobs/{id}/coefficients` returns the solved coefficient table of a CV job (the
//! `estimators::table` encoding) as soon as its train barrier has passed; 404 before.

use std::collections::BTreeMap;
use std::sync::Arc;

use axum::body::Bytes;
use axum::extract::rejection::{BytesRejection, PathRejection};
use axum::extract::{Path, State};
use axum::http::{HeaderMap, StatusCode, header};
use axum::response::IntoResponse;
use axum::routing::{get, post};
use axum::{Json, Router};
use protocol::hash::{is_content_address, sha256_hex};
use protocol::job::{SceneSource, plan_phases_ordered};
use protocol::lease::{JobState, JobStatus, PhaseKind, SubmitResponse};
use protocol::{ApiError, JobSpec};
use scene::SceneDesc;

use super::parse_json;
use crate::AppState;
use crate::auth::require_token;
use crate::error::{AppError, AppResult};
use crate::finish::OUTPUTS;
use crate::store::{JobRow, NewJob};

/// Routes of this module.
pub fn router() -> Router<Arc<AppState>> {
    Router::new()
        .route("/v1/jobs", post(submit).get(list))
        .route("/v1/jobs/{id}", get(status))
        .route("/v1/jobs/{id}/cancel", post(cancel))
        .route("/v1/jobs/{id}/pause", post(pause))
        .route("/v1/jobs/{id}/resume", post(resume))
        .route("/v1/jobs/{id}/{output}", get(output))
}

/// Asset names a scene description refers to (meshes, bitmaps, env map).
pub fn referenced_assets(desc: &SceneDesc) -> Vec<String> {
    let mut names = Vec::new();
    for s in &desc.shapes {
        match &s.geometry {
            scene::desc::GeometryDesc::Obj { filename, .. }
            | scene::desc::GeometryDesc::Ply { filename, .. } => {
                names.push(filename.clone());
            }
            _ => {}
        }
    }
    for t in desc.textures.values() {
        if let scene::desc::TextureDesc::Bitmap { filename, .. } = t {
            names.push(filename.clone());
        }
    }
    if let Some(scene::desc::EnvironmentDesc::Envmap { filename, .. }) = &desc.environment {
        names.push(filename.clone());
    }
    names
}

fn invalid_scene(message: impl Into<String>, field: &str) -> AppError {
    AppError::unprocessable("invalid_scene", message, Some(field))
}

#[tracing::instrument(skip_all)]
async fn submit(
    State(st): State<Arc<AppState>>,
    headers: HeaderMap,
    body: Result<Bytes, BytesRejection>,
) -> AppResult<(StatusCode, Json<SubmitResponse>)> {
    require_token(&headers, &st.config.client_tokens)?;
    let body = body?;
    let spec: JobSpec = parse_json(&body)?;

    // The scene document and its address.
    let (desc, scene_bytes) = match &spec.scene {
        SceneSource::Inline(desc) => {
            let bytes = serde_json::to_vec(desc).map_err(|e| AppError::Internal(e.to_string()))?;
            ((**desc).clone(), bytes)
        }
        SceneSource::Bundle(hash) => {
            if !is_content_address(hash) {
                return Err(invalid_scene(
                    "scene bundle address must be 64 lower-case hex digits",
                    "scene.bundle",
                ));
            }
            let bytes = st.store.get_blob(hash).await?.ok_or_else(|| {
                invalid_scene(
                    format!("scene bundle {hash} has not been uploaded"),
                    "scene.bundle",
                )
            })?;
            let desc: SceneDesc = serde_json::from_slice(&bytes).map_err(|e| {
                invalid_scene(
                    format!("scene bundle is not a native scene: {e}"),
                    "scene.bundle",
                )
            })?;
            (desc, bytes)
        }
    };
    let scene_hash = sha256_hex(&scene_bytes);

    let resolved = spec
        .resolve(&desc, &st.config.limits)
        .map_err(|e| AppError::Unprocessable(ApiError::from(e)))?;

    // Every asset the scene names must be mapped and uploaded.
    let mut assets = BTreeMap::new();
    for name in referenced_assets(&desc) {
        let Some(hash) = spec.assets.get(&name) else {
            return Err(AppError::unprocessable(
                "missing_asset",
                format!(
                    "the scene names asset `{name}` but `assets` does not map it to an uploaded sha256"
                ),
                Some(&format!("assets.{name}")),
            ));
        };
        let Some(bytes) = st.store.get_blob(hash).await? else {
            return Err(AppError::unprocessable(
                "missing_asset",
                format!("asset `{name}` ({hash}) has not been uploaded (PUT /v1/assets/{hash})"),
                Some(&format!("assets.{name}")),
            ));
        };
        assets.insert(name, bytes);
    }
    let effects = validate_scene(desc, assets, resolved.max_depth).await?;

    st.store.put_blob(&scene_hash, &scene_bytes).await?;
    let mut stored = spec.clone();
    stored.scene = SceneSource::Bundle(scene_hash.clone());
    let stored_json =
        serde_json::to_string(&stored).map_err(|e| AppError::Internal(e.to_string()))?;
    let plan = plan_phases_ordered(&resolved, &spec.estimator, spec.is_adaptive());
    let first_tasks = plan.first().map_or(0, |p| p.tasks.len());
    let job_id = st
        .store
        .create_job(&NewJob {
            spec_json: &stored_json,
            resolved: &resolved,
            scene_hash: &scene_hash,
            estimator: spec.estimator.name(),
            effects: &effects,
            priority: i64::from(spec.priority),
            phases: &plan,
        })
        .await?;
    tracing::info!(
        job = job_id,
        phases = plan.len(),
        tasks = first_tasks,
        "job submitted"
    );
    st.work_available.notify_waiters();
    Ok((
        StatusCode::CREATED,
        Json(SubmitResponse {
            job_id,
            tasks: first_tasks as u64,
        }),
    ))
}

/// Loads the scene with `scene`'s validator over the uploaded assets (CPU work, off the
/// async threads) and lists the effects it calls for. The coordinator never builds render
/// structures, it only validates.
async fn validate_scene(
    desc: SceneDesc,
    assets: BTreeMap<String, Vec<u8>>,
    max_depth: i32,
) -> AppResult<Vec<String>> {
    tokio::task::spawn_blocking(move || load_scene(&desc, assets).map(|f| effects(&f, max_depth)))
        .await
        .map_err(|e| AppError::Internal(e.to_string()))?
}

/// Scene validation proper: loads `desc` with `scene::load` over in-memory assets.
pub fn load_scene(
    desc: &SceneDesc,
    assets: BTreeMap<String, Vec<u8>>,
) -> AppResult<scene::Features> {
    let mut mem = scene::MemoryAssets::new();
    for (name, bytes) in assets {
        mem.insert(&name, bytes)
            .map_err(|e| invalid_scene(e.to_string(), &format!("assets.{name}")))?;
    }
    let loaded = scene::load(desc, &mem).map_err(|e| invalid_scene(e.to_string(), "scene"))?;
    Ok(scene::Features::of(&loaded.scene))
}

/// The effects a job simulates (DESIGN §1, "simulate only the effects a scene calls for"),
/// as short tags recorded in `stats.json`.
pub fn effects(f: &scene::Features, max_depth: i32) -> Vec<String> {
    let mut out = Vec::new();
    if f.area_emitters > 0 {
        out.push(format!("area_lights:{}", f.area_emitters));
    }
    match f.environment {
        scene::EnvironmentKind::None => {}
        scene::EnvironmentKind::Envmap => out.push("environment:envmap".into()),
        scene::EnvironmentKind::Constant => out.push("environment:constant".into()),
    }
    for k in &f.bsdf_kinds {
        let name = serde_json::to_value(k)
            .ok()
            .and_then(|v| v.as_str().map(str::to_owned));
        out.push(format!("bsdf:{}", name.unwrap_or_else(|| format!("{k:?}"))));
    }
    if f.textures > 0 {
        out.push(format!("textures:{}", f.textures));
    }
    if f.delta_lobes {
        out.push("delta_lobes".into());
    }
    out.push(match max_depth {
        1 => "emitters_only".into(),
        2 => "direct_only".into(),
        -1 => "indirect:unbounded".into(),
        d => format!("indirect:max_depth={d}"),
    });
    out
}

fn job_status(
    job: &JobRow,
    phase: PhaseKind,
    progress: crate::store::Progress,
    eta_s: Option<f64>,
) -> AppResult<JobStatus> {
    Ok(JobStatus {
        job_id: job.id,
        state: job.state,
        phase,
        estimator: job.estimator.clone(),
        priority: job.priority as i32,
        tasks_total: progress.total.max(0) as u64,
        tasks_done: progress.done.max(0) as u64,
        job: job.resolved,
        error: job.error.clone(),
        eta_s,
    })
}

async fn load_job(st: &AppState, id: Result<Path<i64>, PathRejection>) -> AppResult<JobRow> {
    let Path(id) = id?;
    st.store
        .job(id)
        .await?
        .ok_or_else(|| AppError::NotFound(format!("job {id}")))
}

/// The job's row read again (after a state change).
async fn reload(st: &AppState, id: i64) -> AppResult<JobRow> {
    st.store
        .job(id)
        .await?
        .ok_or_else(|| AppError::NotFound(format!("job {id}")))
}

/// The API status of a job row, with its current phase's progress.
async fn status_of(st: &AppState, job: JobRow) -> AppResult<JobStatus> {
    let progress = st.store.progress(job.id, job.phase_idx).await?;
    let phases = st.store.phases(job.id).await?;
    let phase = phases
        .iter()
        .find(|p| p.idx == job.phase_idx)
        .map_or(PhaseKind::Render, |p| p.kind);
    let eta = eta_s(&st.store, &job, &phases).await?;
    job_status(&job, phase, progress, eta)
}

/// Seconds to completion of a running job: the time so far scaled by the tasks left over
/// the tasks done (all phases), capped by what is left of a time budget.
async fn eta_s(
    store: &crate::store::Store,
    job: &JobRow,
    phases: &[crate::store::PhaseRow],
) -> AppResult<Option<f64>> {
    if !matches!(job.state, JobState::Running | JobState::Paused) {
        return Ok(None);
    }
    let elapsed = (crate::store::now_ms() - job.created_ms).max(0) as f64 / 1000.0;
    let (done, total) = phases
        .iter()
        .fold((0i64, 0i64), |(d, t), p| (d + p.done, t + p.tasks));
    let mut eta = (done > 0).then(|| elapsed * (total - done).max(0) as f64 / done as f64);
    let spec = store.job_spec(job.id).await?;
    let budget = spec
        .and_then(|j| serde_json::from_str::<JobSpec>(&j.spec).ok())
        .and_then(|s| s.time_budget_s);
    if let Some(b) = budget {
        let left = (b - elapsed).max(0.0);
        eta = Some(eta.map_or(left, |e| e.min(left)));
    }
    Ok(eta)
}

async fn status(
    State(st): State<Arc<AppState>>,
    headers: HeaderMap,
    id: Result<Path<i64>, PathRejection>,
) -> AppResult<Json<JobStatus>> {
    require_token(&headers, &st.config.client_tokens)?;
    let job = load_job(&st, id).await?;
    Ok(Json(status_of(&st, job).await?))
}

async fn list(
    State(st): State<Arc<AppState>>,
    headers: HeaderMap,
) -> AppResult<Json<Vec<JobStatus>>> {
    require_token(&headers, &st.config.client_tokens)?;
    let mut out = Vec::new();
    for job in st.store.jobs(1000).await? {
        out.push(status_of(&st, job).await?);
    }
    Ok(Json(out))
}

async fn cancel(
    State(st): State<Arc<AppState>>,
    headers: HeaderMap,
    id: Result<Path<i64>, PathRejection>,
) -> AppResult<Json<JobStatus>> {
    require_token(&headers, &st.config.client_tokens)?;
    let job = load_job(&st, id).await?;
    if !st
        .store
        .end_job(job.id, JobState::Cancelled, Some("cancelled by client"))
        .await?
    {
        return Err(AppError::conflict(
            "not_running",
            format!("job {} is {}", job.id, job.state.as_str()),
        ));
    }
    Ok(Json(status_of(&st, reload(&st, job.id).await?).await?))
}

async fn pause(
    State(st): State<Arc<AppState>>,
    headers: HeaderMap,
    id: Result<Path<i64>, PathRejection>,
) -> AppResult<Json<JobStatus>> {
    set_paused(&st, &headers, id, true).await
}

async fn resume(
    State(st): State<Arc<AppState>>,
    headers: HeaderMap,
    id: Result<Path<i64>, PathRejection>,
) -> AppResult<Json<JobStatus>> {
    set_paused(&st, &headers, id, false).await
}

async fn set_paused(
    st: &AppState,
    headers: &HeaderMap,
    id: Result<Path<i64>, PathRejection>,
    pause: bool,
) -> AppResult<Json<JobStatus>> {
    require_token(headers, &st.config.client_tokens)?;
    let job = load_job(st, id).await?;
    if !st.store.set_paused(job.id, pause).await? {
        let want = if pause { "running" } else { "paused" };
        return Err(AppError::conflict(
            "wrong_state",
            format!("job {} is {}, not {want}", job.id, job.state.as_str()),
        ));
    }
    if !pause {
        st.work_available.notify_waiters();
    }
    Ok(Json(status_of(st, reload(st, job.id).await?).await?))
}

async fn output(
    State(st): State<Arc<AppState>>,
    headers: HeaderMap,
    path: Result<Path<(i64, String)>, PathRejection>,
) -> AppResult<axum::response::Response> {
    require_token(&headers, &st.config.client_tokens)?;
    let Path((id, name)) = path?;
    if name == "coefficients" {
        return coefficients(&st, id).await;
    }
    if !OUTPUTS.iter().any(|(n, _)| *n == name) {
        return Err(AppError::NotFound(format!(
            "output `{name}` (available: image.exr, preview.png, stats.json, coefficients)"
        )));
    }
    let job = st
        .store
        .job(id)
        .await?
        .ok_or_else(|| AppError::NotFound(format!("job {id}")))?;
    match job.state {
        JobState::Done => {}
        JobState::Running | JobState::Paused => {
            return Err(AppError::conflict(
                "not_finished",
                format!("job {id} is still running"),
            ));
        }
        other => {
            return Err(AppError::conflict(
                "no_output",
                format!(
                    "job {id} is {}: {}",
                    other.as_str(),
                    job.error.unwrap_or_default()
                ),
            ));
        }
    }
    let (ctype, data) = st
        .store
        .artifact(id, &name)
        .await?
        .ok_or_else(|| AppError::NotFound(format!("output {name} of job {id}")))?;
    Ok(([(header::CONTENT_TYPE, ctype)], data).into_response())
}

/// The solved coefficient table of a job (404 until its train barrier has passed).
async fn coefficients(st: &AppState, id: i64) -> AppResult<axum::response::Response> {
    if st.store.job(id).await?.is_none() {
        return Err(AppError::NotFound(format!("job {id}")));
    }
    let hash = st.store.coefficients_of(id).await?.ok_or_else(|| {
        AppError::NotFound(format!(
            "coefficients of job {id} (not solved yet, or its estimator has none)"
        ))
    })?;
    let data = st
        .store
        .get_blob(&hash)
        .await?
        .ok_or_else(|| AppError::Internal(format!("coefficient table {hash} is missing")))?;
    Ok((
        [
            (header::CONTENT_TYPE, "application/octet-stream".to_owned()),
            (header::ETAG, format!("\"{hash}\"")),
        ],
        data,
    )
        .into_response())
}
