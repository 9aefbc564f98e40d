//! HTTP routes, one module per resource. Every handler authenticates first, reads its body
//! through a size-limited extractor, and answers errors as JSON ([`crate::error::AppError`]).
//!
//! | method | path | who | what |
//! |---|---|---|---|
//! | GET | `/healthz` | anyone | store reachable |
//! | GET | `/metrics`, `/openapi.json`, `/docs` | anyone | Prometheus metrics, OpenAPI document, HTML docs |
//! | POST | `/v1/jobs` | client | submit a [`protocol::JobSpec`] |
//! | GET | `/v1/jobs`, `/v1/jobs/{id}` | client | list / status |
//! | POST | `/v1/jobs/{id}/cancel`, `/pause`, `/resume` | client | cancel, pause, resume |
//! | GET | `/v1/jobs/{id}/image.exr`, `preview.png`, `stats.json` | client | outputs of a finished job |
//! | GET | `/v1/jobs/{id}/coefficients` | client | solved coefficient table of a CV job (404 before its train barrier) |
//! | GET | `/v1/jobs/{id}/convergence.csv` | client | convergence series (running jobs too) |
//! | GET | `/v1/events[?job=ID]` | client | Server-Sent Events: job, phase, progress |
//! | PUT / GET | `/v1/assets/{sha256}` | client / client or worker | content-addressed upload / download |
//! | POST | `/v1/workers/register` | enrollment token | per-worker token |
//! | POST | `/v1/workers/lease` | worker | long-poll a [`protocol::TaskLease`] (204: none) |
//! | POST | `/v1/tasks/{id}/heartbeat?attempt=N` | worker | extend the lease |
//! | PUT | `/v1/tasks/{id}/result?attempt=N` | worker | upload the frame stream |
//! | POST | `/v1/tasks/{id}/release?attempt=N` | worker | give the task back (shutdown) |
//! | POST | `/v1/tasks/{id}/fail?attempt=N` | worker | report a failed attempt |

pub mod assets;
pub mod events;
pub mod health;
pub mod jobs;
pub mod meta;
pub mod tasks;
pub mod workers;

use std::sync::Arc;

use axum::Router;
use axum::extract::DefaultBodyLimit;

use crate::AppState;
use crate::error::AppError;

/// The whole API.
pub fn router(state: Arc<AppState>) -> Router {
    let json_limit = state.config.max_json_body;
    Router::new()
        .merge(health::router())
        .merge(meta::router())
        .merge(jobs::router())
        .merge(assets::router(state.config.max_asset_body))
        .merge(workers::router())
        .merge(tasks::router(state.config.max_result_body))
        .merge(events::router())
        .fallback(|| async { AppError::NotFound("route".into()) })
        .layer(DefaultBodyLimit::max(json_limit))
        .layer(tower_http::trace::TraceLayer::new_for_http())
        .with_state(state)
}

/// Parses a JSON body, mapping syntax errors to 400 `invalid_json` and shape errors (unknown
/// field, unknown variant, wrong type) to 422 `invalid_spec`, naming the field when serde does.
pub fn parse_json<T: serde::de::DeserializeOwned>(body: &[u8]) -> Result<T, AppError> {
    serde_json::from_slice(body).map_err(|e| {
        use serde_json::error::Category;
        let msg = e.to_string();
        match e.classify() {
            Category::Syntax | Category::Eof | Category::Io => {
                AppError::bad_request("invalid_json", msg)
            }
            Category::Data => {
                let field = msg
                    .split_once("field `")
                    .and_then(|(_, rest)| rest.split_once('`'))
                    .map(|(f, _)| f.to_owned());
                AppError::unprocessable("invalid_spec", msg, field.as_deref())
            }
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn json_errors_are_classified_and_name_the_field() {
        #[derive(Debug, serde::Deserialize)]
        #[serde(deny_unknown_fields)]
        #[allow(dead_code)]
        struct S {
            a: u32,
        }
        let e = parse_json::<S>(b"{").unwrap_err();
        assert!(
            matches!(e, AppError::BadRequest(ref x) if x.code == "invalid_json"),
            "{e:?}"
        );
        let e = parse_json::<S>(br#"{"a": 1, "zz": 2}"#).unwrap_err();
        match e {
            AppError::Unprocessable(x) => {
                assert_eq!(x.code, "invalid_spec");
                assert_eq!(x.field.as_deref(), Some("zz"));
            }
            other => panic!("{other:?}"),
        }
        let e = parse_json::<S>(br#"{"a": "x"}"#).unwrap_err();
        assert!(matches!(e, AppError::Unprocessable(_)), "{e:?}");
        assert_eq!(parse_json::<S>(br#"{"a": 3}"#).unwrap().a, 3);
    }
}
