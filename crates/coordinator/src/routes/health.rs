//! `GET /healthz`: 200 `{"status":"ok"}` when the store answers, 500 otherwise. No auth.

use std::sync::Arc;

use axum::extract::State;
use axum::routing::get;
use axum::{Json, Router};

use crate::AppState;
use crate::error::AppResult;

/// Routes of this module.
pub fn router() -> Router<Arc<AppState>> {
    Router::new().route("/healthz", get(healthz))
}

async fn healthz(State(st): State<Arc<AppState>>) -> AppResult<Json<serde_json::Value>> {
    st.store.ping().await?;
    Ok(Json(serde_json::json!({ "status": "ok" })))
}
