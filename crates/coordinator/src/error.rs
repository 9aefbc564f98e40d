//! The coordinator's error type, mapped to an HTTP status and the JSON body of
//! [`protocol::ApiError`]: every non-2xx answer names its problem in `code`/`message`/`field`.

use axum::Json;
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use protocol::ApiError;

use crate::store::StoreError;

/// Everything a handler can fail with.
#[derive(Debug, thiserror::Error)]
pub enum AppError {
    /// 400: the request is malformed (bad JSON, bad query, undecodable frames).
    #[error("{0}")]
    BadRequest(ApiError),
    /// 401: missing or wrong bearer token.
    #[error("unauthorized: {0}")]
    Unauthorized(&'static str),
    /// 404: no such job/task/asset.
    #[error("{0} not found")]
    NotFound(String),
    /// 409: the request conflicts with the current state (stale attempt, job not finished).
    #[error("{0}")]
    Conflict(ApiError),
    /// 413: the body exceeds the route's limit.
    #[error("body too large")]
    TooLarge(String),
    /// 422: well-formed but invalid (spec rules, scene validation, unsupported estimator).
    #[error("{0}")]
    Unprocessable(ApiError),
    /// 500: the store failed.
    #[error("store: {0}")]
    Store(#[from] StoreError),
    /// 500: something else that should not happen.
    #[error("internal: {0}")]
    Internal(String),
}

impl AppError {
    /// A 400 with a code and message.
    pub fn bad_request(code: &str, message: impl Into<String>) -> Self {
        Self::BadRequest(ApiError::new(code, message))
    }
    /// A 409 with a code and message.
    pub fn conflict(code: &str, message: impl Into<String>) -> Self {
        Self::Conflict(ApiError::new(code, message))
    }
    /// A 422 with a code, message and field.
    pub fn unprocessable(code: &str, message: impl Into<String>, field: Option<&str>) -> Self {
        let mut e = ApiError::new(code, message);
        e.field = field.map(str::to_owned);
        Self::Unprocessable(e)
    }
}

impl IntoResponse for AppError {
    fn into_response(self) -> Response {
        let (status, body) = match self {
            Self::BadRequest(e) => (StatusCode::BAD_REQUEST, e),
            Self::Unauthorized(m) => (StatusCode::UNAUTHORIZED, ApiError::new("unauthorized", m)),
            Self::NotFound(what) => (
                StatusCode::NOT_FOUND,
                ApiError::new("not_found", format!("{what} not found")),
            ),
            Self::Conflict(e) => (StatusCode::CONFLICT, e),
            Self::TooLarge(m) => (
                StatusCode::PAYLOAD_TOO_LARGE,
                ApiError::new("body_too_large", m),
            ),
            Self::Unprocessable(e) => (StatusCode::UNPROCESSABLE_ENTITY, e),
            Self::Store(e) => {
                tracing::error!(error = %e, "store failure");
                (
                    StatusCode::INTERNAL_SERVER_ERROR,
                    ApiError::new("internal", "database error"),
                )
            }
            Self::Internal(m) => {
                tracing::error!(error = %m, "internal failure");
                (
                    StatusCode::INTERNAL_SERVER_ERROR,
                    ApiError::new("internal", m),
                )
            }
        };
        let mut resp = (status, Json(body.into_body())).into_response();
        if status == StatusCode::UNAUTHORIZED {
            resp.headers_mut().insert(
                axum::http::header::WWW_AUTHENTICATE,
                axum::http::HeaderValue::from_static("Bearer"),
            );
        }
        resp
    }
}

/// Maps a body-extraction failure (limit exceeded, connection broken) to a JSON error.
impl From<axum::extract::rejection::BytesRejection> for AppError {
    fn from(r: axum::extract::rejection::BytesRejection) -> Self {
        if r.status() == StatusCode::PAYLOAD_TOO_LARGE {
            Self::TooLarge(format!(
                "request body exceeds this route's limit ({})",
                r.body_text()
            ))
        } else {
            Self::bad_request("bad_body", r.body_text())
        }
    }
}

/// Maps a query-string failure to a JSON 400.
impl From<axum::extract::rejection::QueryRejection> for AppError {
    fn from(r: axum::extract::rejection::QueryRejection) -> Self {
        Self::bad_request("invalid_query", r.body_text())
    }
}

/// Maps a path-parameter failure to a JSON 400.
impl From<axum::extract::rejection::PathRejection> for AppError {
    fn from(r: axum::extract::rejection::PathRejection) -> Self {
        Self::bad_request("invalid_path", r.body_text())
    }
}

/// Result alias for handlers.
pub type AppResult<T> = Result<T, AppError>;
