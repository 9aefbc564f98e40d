//! Service metadata: `GET /metrics` (Prometheus text format), `GET /openapi.json` (OpenAPI
//! 3.1 description of the API) and `GET /docs` (a self-contained HTML page generated from
//! it: no scripts, no external assets). No authentication: these reveal no job content.
//!
//! Metrics are read from the store at scrape time, so they are right after a restart and
//! agree between several coordinators sharing one PostgreSQL.

use std::fmt::Write as _;
use std::sync::Arc;

use axum::extract::State;
use axum::http::header;
use axum::response::{Html, IntoResponse};
use axum::routing::get;
use axum::{Json, Router};

use crate::AppState;
use crate::error::AppResult;

/// Routes of this module.
pub fn router() -> Router<Arc<AppState>> {
    Router::new()
        .route("/metrics", get(metrics))
        .route("/openapi.json", get(|| async { Json(openapi()) }))
        .route("/docs", get(docs))
}

async fn metrics(State(st): State<Arc<AppState>>) -> AppResult<impl IntoResponse> {
    let m = st.store.metrics().await?;
    let mut out = String::new();
    let _ = writeln!(
        out,
        "# HELP cvfarm_jobs Jobs by state.\n# TYPE cvfarm_jobs gauge"
    );
    for (state, n) in &m.jobs {
        let _ = writeln!(out, "cvfarm_jobs{{state=\"{state}\"}} {n}");
    }
    let _ = writeln!(
        out,
        "# HELP cvfarm_tasks Tasks by state.\n# TYPE cvfarm_tasks gauge"
    );
    for (state, n) in &m.tasks {
        let _ = writeln!(out, "cvfarm_tasks{{state=\"{state}\"}} {n}");
    }
    let _ = writeln!(
        out,
        "# HELP cvfarm_workers_registered Workers ever registered.\n# TYPE cvfarm_workers_registered gauge\ncvfarm_workers_registered {}",
        m.workers
    );
    let _ = writeln!(
        out,
        "# HELP cvfarm_task_attempts_total Lease attempts over all tasks.\n# TYPE cvfarm_task_attempts_total counter\ncvfarm_task_attempts_total {}",
        m.attempts
    );
    let _ = writeln!(
        out,
        "# HELP cvfarm_task_failures_total Failed or expired attempts.\n# TYPE cvfarm_task_failures_total counter\ncvfarm_task_failures_total {}",
        m.failures
    );
    Ok(([(header::CONTENT_TYPE, "text/plain; version=0.0.4")], out))
}

fn op(summary: &str, who: &str, ok: &str) -> serde_json::Value {
    let mut v = serde_json::json!({
        "summary": summary,
        "responses": {
            ok: { "description": "success" },
            "4XX": { "description": "client error", "content": { "application/json": { "schema": { "$ref": "#/components/schemas/ApiError" } } } }
        }
    });
    if who != "none" {
        v["security"] = serde_json::json!([{ who: [] }]);
    }
    v
}

/// The OpenAPI document of the API.
pub fn openapi() -> serde_json::Value {
    serde_json::json!({
        "openapi": "3.1.0",
        "info": {
            "title": "cvfarm coordinator",
            "version": env!("CARGO_PKG_VERSION"),
            "description": "Render farm for control-variate Monte Carlo rendering. Errors are `{ \"error\": { \"code\", \"message\", \"field\"? } }`."
        },
        "components": {
            "securitySchemes": {
                "client": { "type": "http", "scheme": "bearer", "description": "a client token (CVFARM_CLIENT_TOKEN)" },
                "enrollment": { "type": "http", "scheme": "bearer", "description": "the worker enrollment token (CVFARM_WORKER_TOKEN)" },
                "worker": { "type": "http", "scheme": "bearer", "description": "a per-worker token `cvw_<id>_<secret>` from registration" }
            },
            "schemas": {
                "ApiError": {
                    "type": "object", "required": ["error"],
                    "properties": { "error": { "type": "object", "required": ["code", "message"],
                        "properties": { "code": {"type": "string"}, "message": {"type": "string"}, "field": {"type": "string"} } } }
                },
                "JobSpec": {
                    "type": "object", "required": ["scene"], "additionalProperties": false,
                    "description": "See protocol::job::JobSpec for every field and default.",
                    "properties": {
                        "scene": { "description": "{\"inline\": <native scene JSON>} or {\"bundle\": <sha256>}" },
                        "assets": { "type": "object", "additionalProperties": { "type": "string", "pattern": "^[0-9a-f]{64}$" } },
                        "estimator": { "type": "object", "required": ["kind"],
                            "description": "kind plus that estimator's options (protocol::job::EstimatorSpec; options of estimators::spec: OcvOptions, CmsOptions, PerLightCvOptions, OptimalMisOptions; unknown options rejected). Supported: path, ocv, cms, per_light_cv, optimal_mis; rerender and gradient answer 422 unsupported. CV kinds run the phases surrogate (relative cms and per_light_cv) → train → render.",
                            "properties": { "kind": { "enum": ["path", "ocv", "cms", "per_light_cv", "optimal_mis", "rerender", "gradient"] } } },
                        "spp": { "type": "integer", "minimum": 1 },
                        "time_budget_s": { "type": "number", "exclusiveMinimum": 0, "description": "stop adding render rounds (of samples_per_task) once this many seconds have passed since submission; spp is the cap" },
                        "target_rel_mse": { "type": "number", "exclusiveMinimum": 0, "description": "stop after the first render round whose estimated relMSE is at most this; spp is the cap" },
                        "resolution": { "type": "array", "items": { "type": "integer", "minimum": 1 }, "minItems": 2, "maxItems": 2 },
                        "max_depth": { "type": "integer" },
                        "seed": { "type": "integer", "minimum": 0 },
                        "tile_size": { "type": "integer", "minimum": 8, "maximum": 512 },
                        "samples_per_task": { "type": "integer", "minimum": 1 },
                        "priority": { "type": "integer" }
                    }
                }
            }
        },
        "paths": {
            "/healthz": { "get": op("Store reachable", "none", "200") },
            "/metrics": { "get": op("Prometheus metrics", "none", "200") },
            "/openapi.json": { "get": op("This document", "none", "200") },
            "/docs": { "get": op("API documentation page", "none", "200") },
            "/v1/jobs": {
                "post": { "requestBody": { "required": true, "content": { "application/json": { "schema": { "$ref": "#/components/schemas/JobSpec" } } } },
                          "summary": "Submit a job", "security": [{"client": []}],
                          "responses": { "201": {"description": "created: {job_id, tasks}"}, "4XX": {"description": "invalid JSON, spec, scene, limits, token, body size"} } },
                "get": op("List jobs", "client", "200")
            },
            "/v1/jobs/{id}": { "get": op("Job status (state, current phase, its progress, eta_s)", "client", "200") },
            "/v1/jobs/{id}/cancel": { "post": op("Cancel a running or paused job", "client", "200") },
            "/v1/jobs/{id}/pause": { "post": op("Pause a running job (no new leases)", "client", "200") },
            "/v1/jobs/{id}/resume": { "post": op("Resume a paused job", "client", "200") },
            "/v1/jobs/{id}/image.exr": { "get": op("Multi-layer EXR (beauty, variance, albedo, normal) of a finished job", "client", "200") },
            "/v1/jobs/{id}/preview.png": { "get": op("sRGB preview of a finished job", "client", "200") },
            "/v1/jobs/{id}/stats.json": { "get": op("Time, tasks and spp per phase, barrier results (cells solved/fallback, blob address), estimated error, effects simulated", "client", "200") },
            "/v1/jobs/{id}/coefficients": { "get": op("Solved coefficient table of a CV job (estimators::table encoding, kind 3); 404 before the train barrier", "client", "200") },
            "/v1/jobs/{id}/convergence.csv": { "get": op("Convergence series seconds,spp,rel_mse_est,tasks_done, one row per completed sample round (running jobs too)", "client", "200") },
            "/v1/events": { "get": op("Server-Sent Events (text/event-stream): job, phase (coefficients announced), progress; ?job=ID filters; resumes after Last-Event-ID", "client", "200") },
            "/v1/assets/{sha256}": {
                "put": op("Upload an asset or scene document by content address (body must hash to it)", "client", "201"),
                "get": op("Download an asset (clients and workers)", "client", "200")
            },
            "/v1/workers/register": { "post": op("Register a worker; returns its token", "enrollment", "201") },
            "/v1/workers/lease": { "post": op("Long-poll for a task lease (204: none)", "worker", "200") },
            "/v1/tasks/{id}/heartbeat": { "post": op("Extend the lease of ?attempt=N", "worker", "200") },
            "/v1/tasks/{id}/result": { "put": op("Upload the TileResult frame stream of ?attempt=N (409: stale attempt; 422 invalid_cells: a train result's cell block is missing, truncated, non-finite, of the wrong kind, out of key range or of another layout)", "worker", "200") },
            "/v1/tasks/{id}/release": { "post": op("Give the lease of ?attempt=N back", "worker", "200") },
            "/v1/tasks/{id}/fail": { "post": op("Report a failed attempt ?attempt=N", "worker", "200") }
        }
    })
}

fn escape(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
}

async fn docs() -> Html<String> {
    let api = openapi();
    let mut rows = String::new();
    if let Some(paths) = api["paths"].as_object() {
        for (path, ops) in paths {
            for (method, op) in ops.as_object().into_iter().flatten() {
                let who = op["security"][0]
                    .as_object()
                    .and_then(|o| o.keys().next().cloned())
                    .unwrap_or_else(|| "—".into());
                let _ = write!(
                    rows,
                    "<tr><td><code>{}</code></td><td><code>{}</code></td><td>{}</td><td>{}</td></tr>",
                    method.to_uppercase(),
                    escape(path),
                    escape(&who),
                    escape(op["summary"].as_str().unwrap_or(""))
                );
            }
        }
    }
    Html(format!(
        "<!doctype html><html><head><meta charset=\"utf-8\"><title>cvfarm API</title></head><body>\
         <h1>cvfarm coordinator API</h1><p>Machine-readable: <a href=\"/openapi.json\">/openapi.json</a>. \
         Authentication: <code>Authorization: Bearer &lt;token&gt;</code>. Errors: <code>{{\"error\": {{\"code\", \"message\", \"field\"?}}}}</code>.</p>\
         <table border=\"1\" cellpadding=\"4\"><tr><th>method</th><th>path</th><th>token</th><th>what</th></tr>{rows}</table></body></html>"
    ))
}
