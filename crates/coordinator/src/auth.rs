//! Bearer-token authentication.
//!
//! - **Clients** send one of the configured client tokens (`CVFARM_CLIENT_TOKEN`).
//! - **Workers** enrol with the enrollment token (`CVFARM_WORKER_TOKEN`) and receive a
//!   per-worker token `cvw_<id>_<secret>`; the store keeps only SHA-256(secret), so a leaked
//!   database does not leak working credentials. The secret is 256 random bits, so a fast
//!   hash is enough (no password stretching needed).
//!
//! Comparisons are constant-time in the length of the compared strings.

use axum::http::HeaderMap;
use axum::http::header::AUTHORIZATION;
use protocol::hash::{sha256_hex, to_hex};

use crate::error::AppError;
use crate::store::Store;

/// The bearer token of a request, if any.
pub fn bearer(headers: &HeaderMap) -> Option<&str> {
    let v = headers.get(AUTHORIZATION)?.to_str().ok()?;
    let t = v
        .strip_prefix("Bearer ")
        .or_else(|| v.strip_prefix("bearer "))?;
    Some(t.trim())
}

/// Constant-time string equality (length may leak, content does not).
pub fn ct_eq(a: &str, b: &str) -> bool {
    if a.len() != b.len() {
        return false;
    }
    a.bytes()
        .zip(b.bytes())
        .fold(0u8, |acc, (x, y)| acc | (x ^ y))
        == 0
}

/// Checks that the request carries one of `tokens`.
pub fn require_token(headers: &HeaderMap, tokens: &[String]) -> Result<(), AppError> {
    let t = bearer(headers).ok_or(AppError::Unauthorized("missing bearer token"))?;
    // Evaluate every comparison so the time does not say which token matched.
    let ok = tokens.iter().fold(false, |acc, k| acc | ct_eq(t, k));
    if ok {
        Ok(())
    } else {
        Err(AppError::Unauthorized("invalid token"))
    }
}

/// A fresh worker secret (64 hex digits) and the token carrying it.
pub fn new_worker_secret() -> String {
    let bytes: [u8; 32] = rand::random();
    to_hex(&bytes)
}

/// The bearer token of worker `id` with `secret`.
pub fn worker_token(id: i64, secret: &str) -> String {
    format!("cvw_{id}_{secret}")
}

/// Authenticates a worker request; returns the worker id.
pub async fn require_worker(headers: &HeaderMap, store: &Store) -> Result<i64, AppError> {
    let t = bearer(headers).ok_or(AppError::Unauthorized("missing bearer token"))?;
    let bad = AppError::Unauthorized("invalid worker token");
    let rest = t
        .strip_prefix("cvw_")
        .ok_or(AppError::Unauthorized("invalid worker token"))?;
    let (id, secret) = rest
        .split_once('_')
        .ok_or(AppError::Unauthorized("invalid worker token"))?;
    let id: i64 = id
        .parse()
        .map_err(|_| AppError::Unauthorized("invalid worker token"))?;
    let Some(stored) = store.worker_secret_hash(id).await? else {
        return Err(bad);
    };
    if ct_eq(&sha256_hex(secret.as_bytes()), &stored) {
        Ok(id)
    } else {
        Err(bad)
    }
}

/// Accepts either a client token or a valid worker token (shared read routes such as assets).
pub async fn require_client_or_worker(
    headers: &HeaderMap,
    tokens: &[String],
    store: &Store,
) -> Result<(), AppError> {
    if require_token(headers, tokens).is_ok() {
        return Ok(());
    }
    require_worker(headers, store).await.map(|_| ())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bearer_parsing_and_comparison() {
        let mut h = HeaderMap::new();
        assert!(bearer(&h).is_none());
        h.insert(AUTHORIZATION, "Bearer abc".parse().unwrap());
        assert_eq!(bearer(&h), Some("abc"));
        assert!(require_token(&h, &["abc".into()]).is_ok());
        assert!(require_token(&h, &["abd".into(), "ab".into()]).is_err());
        assert!(ct_eq("", ""));
        assert_eq!(new_worker_secret().len(), 64);
    }
}
