//! Content-addressed assets: `PUT /v1/assets/{sha256}` stores the body after checking that
//! its SHA-256 is the address (idempotent); `GET /v1/assets/{sha256}` returns it. Scenes
//! refer to assets by name, jobs map names to addresses: a client path is never used.

use std::sync::Arc;

use axum::body::Bytes;
use axum::extract::rejection::{BytesRejection, PathRejection};
use axum::extract::{DefaultBodyLimit, Path, State};
use axum::http::{HeaderMap, StatusCode, header};
use axum::response::IntoResponse;
use axum::routing::get;
use axum::{Json, Router};
use protocol::hash::{is_content_address, sha256_hex};

use crate::AppState;
use crate::auth::{require_client_or_worker, require_token};
use crate::error::{AppError, AppResult};

/// Routes of this module; uploads may be up to `max_body` bytes.
pub fn router(max_body: usize) -> Router<Arc<AppState>> {
    Router::new().route(
        "/v1/assets/{hash}",
        get(download)
            .put(upload)
            .layer(DefaultBodyLimit::max(max_body)),
    )
}

fn check_address(hash: &str) -> AppResult<()> {
    if is_content_address(hash) {
        Ok(())
    } else {
        Err(AppError::bad_request(
            "invalid_address",
            "asset address must be 64 lower-case hex digits (sha256)",
        ))
    }
}

#[tracing::instrument(skip_all, fields(hash))]
async fn upload(
    State(st): State<Arc<AppState>>,
    headers: HeaderMap,
    hash: Result<Path<String>, PathRejection>,
    body: Result<Bytes, BytesRejection>,
) -> AppResult<impl IntoResponse> {
    require_token(&headers, &st.config.client_tokens)?;
    let Path(hash) = hash?;
    check_address(&hash)?;
    let body = body?;
    let actual = sha256_hex(&body);
    if actual != hash {
        return Err(AppError::unprocessable(
            "hash_mismatch",
            format!("body hashes to {actual}, not to the address {hash}"),
            None,
        ));
    }
    st.store.put_blob(&hash, &body).await?;
    Ok((
        StatusCode::CREATED,
        Json(serde_json::json!({ "hash": hash, "bytes": body.len() })),
    ))
}

async fn download(
    State(st): State<Arc<AppState>>,
    headers: HeaderMap,
    hash: Result<Path<String>, PathRejection>,
) -> AppResult<impl IntoResponse> {
    require_client_or_worker(&headers, &st.config.client_tokens, &st.store).await?;
    let Path(hash) = hash?;
    check_address(&hash)?;
    let data = st
        .store
        .get_blob(&hash)
        .await?
        .ok_or_else(|| AppError::NotFound(format!("asset {hash}")))?;
    Ok(([(header::CONTENT_TYPE, "application/octet-stream")], data))
}
