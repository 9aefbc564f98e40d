//! The API error body. Every non-2xx response of the coordinator carries exactly this JSON:
//!
//! ```json
//! { "error": { "code": "invalid_spec", "message": "spp must be in 1..=65536", "field": "spp" } }
//! ```
//!
//! `code` is a stable machine-readable identifier (snake_case); `message` is for people;
//! `field` names the offending JSON field or path when there is one.

use serde::{Deserialize, Serialize};

/// The outer object: `{ "error": ... }`.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ApiErrorBody {
    /// The error itself.
    pub error: ApiError,
}

/// One API error.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ApiError {
    /// Stable snake_case identifier, e.g. `invalid_json`, `unauthorized`, `not_found`, `stale_attempt`.
    pub code: String,
    /// Human-readable explanation naming the problem.
    pub message: String,
    /// The offending field (JSON path), when the error is about one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub field: Option<String>,
}

impl ApiError {
    /// An error without a field.
    pub fn new(code: impl Into<String>, message: impl Into<String>) -> Self {
        Self {
            code: code.into(),
            message: message.into(),
            field: None,
        }
    }

    /// Attaches the offending field.
    pub fn with_field(mut self, field: impl Into<String>) -> Self {
        self.field = Some(field.into());
        self
    }

    /// Wraps in the outer `{ "error": ... }` object.
    pub fn into_body(self) -> ApiErrorBody {
        ApiErrorBody { error: self }
    }
}

impl std::fmt::Display for ApiError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match &self.field {
            Some(field) => write!(f, "{} ({}): {}", self.code, field, self.message),
            None => write!(f, "{}: {}", self.code, self.message),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn error_body_shape() {
        let body = ApiError::new("invalid_spec", "bad spp")
            .with_field("spp")
            .into_body();
        let v = serde_json::to_value(&body).unwrap();
        assert_eq!(
            v,
            serde_json::json!({"error": {"code": "invalid_spec", "message": "bad spp", "field": "spp"}})
        );
        let no_field = serde_json::to_value(ApiError::new("x", "y").into_body()).unwrap();
        assert!(no_field["error"].get("field").is_none());
    }
}
