//! Estimator selection on the command line: `--estimator NAME`, `--opt key=value` (repeated)
//! and `--estimator-json '{"kind": …}'` / `--estimator-json @file.json`.
//!
//! The options are the fields of the estimator's option struct in `render::integrator`
//! (`OcvOptions`, `CmsOptions`, …), which reject unknown fields; the JSON form is exactly
//! the job's `estimator` object, e.g. `{ "kind": "ocv", "spe": 64, "lambda": 1.0 }`.
//! Precedence: `--opt` overrides `--estimator-json`, whose `kind` must agree with
//! `--estimator` when both are given.
//!
//! A `--opt` value is read as JSON when it parses (`3`, `0.5`, `true`, `[1,2]`), else as a
//! string (`mode=rgb` ≡ `mode="rgb"`).

use std::fmt;

use render::integrator::Estimator;
use serde_json::{Map, Value};

/// A bad command line detected after parsing (exit status 2, like clap's errors).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct UsageError(pub String);

impl fmt::Display for UsageError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for UsageError {}

/// The estimator kinds `--estimator` accepts, in the order of the docs.
pub const KINDS: &[&str] = &["path", "ocv", "cms", "per_light_cv", "optimal_mis"];

/// The `kind` of an estimator (its JSON tag).
pub fn kind_of(e: &Estimator) -> String {
    serde_json::to_value(e)
        .ok()
        .and_then(|v| v.get("kind").and_then(Value::as_str).map(str::to_string))
        .unwrap_or_else(|| "unknown".into())
}

/// The option names of estimator `kind` (from its defaults' JSON form).
pub fn option_names(kind: &str) -> Vec<String> {
    let mut obj = Map::new();
    obj.insert("kind".into(), Value::String(kind.into()));
    serde_json::from_value::<Estimator>(Value::Object(obj))
        .ok()
        .and_then(|e| serde_json::to_value(e).ok())
        .and_then(|v| v.as_object().cloned())
        .map(|o| o.keys().filter(|k| *k != "kind").cloned().collect())
        .unwrap_or_default()
}

/// Parses one `--opt key=value` (the value as JSON when it parses, else as a string).
pub fn parse_opt(text: &str) -> Result<(String, Value), UsageError> {
    let (k, v) = text
        .split_once('=')
        .ok_or_else(|| UsageError(format!("--opt `{text}`: expected KEY=VALUE")))?;
    let (k, v) = (k.trim(), v.trim());
    if k.is_empty() {
        return Err(UsageError(format!("--opt `{text}`: empty option name")));
    }
    let value = serde_json::from_str(v).unwrap_or_else(|_| Value::String(v.to_string()));
    Ok((k.to_string(), value))
}

/// Reads `--estimator-json`: inline JSON, or `@path` to a JSON file.
fn read_json(arg: &str) -> Result<Map<String, Value>, UsageError> {
    let text = match arg.strip_prefix('@') {
        Some(path) => std::fs::read_to_string(path)
            .map_err(|e| UsageError(format!("--estimator-json: reading {path}: {e}")))?,
        None => arg.to_string(),
    };
    match serde_json::from_str::<Value>(&text) {
        Ok(Value::Object(o)) => Ok(o),
        Ok(_) => Err(UsageError(
            "--estimator-json: expected a JSON object like {\"kind\": \"ocv\", \"spe\": 32}".into(),
        )),
        Err(e) => Err(UsageError(format!("--estimator-json: invalid JSON: {e}"))),
    }
}

/// The estimator flags `cvfarm render` and `cvfarm submit` share (flattened into both), so a
/// job means the same thing locally and on the farm.
#[derive(Debug, Clone, clap::Args)]
pub struct EstimatorArgs {
    /// Estimator [default: path, or the kind of --estimator-json]: path, ocv, cms,
    /// per_light_cv, optimal_mis.
    #[arg(long, env = "CVFARM_ESTIMATOR", value_enum)]
    pub estimator: Option<crate::render_cmd::EstimatorArg>,
    /// Estimator option `key=value` (repeatable, or several separated by `;`; the value is
    /// JSON when it parses as JSON, else a string), e.g. --opt spe=32 or
    /// --opt grid_resolution=[8,8,8]. Unknown options are errors listing the valid ones.
    #[arg(
        long = "opt",
        env = "CVFARM_OPTS",
        value_name = "KEY=VALUE",
        value_delimiter = ';'
    )]
    pub opts: Vec<String>,
    /// Estimator as JSON ({"kind":"cms","training_spp":32}) or @file.json.
    #[arg(long, env = "CVFARM_ESTIMATOR_JSON", value_name = "JSON|@FILE")]
    pub estimator_json: Option<String>,
}

impl EstimatorArgs {
    /// The estimator these flags select ([`build`]).
    pub fn build(&self) -> Result<Estimator, UsageError> {
        build(
            self.estimator.map(crate::render_cmd::EstimatorArg::name),
            self.estimator_json.as_deref(),
            &self.opts,
        )
    }
}

/// Builds the estimator from `--estimator` (`kind`, if given), `--estimator-json` and the
/// `--opt`s. Errors name the offending option and list the valid ones.
pub fn build(
    kind: Option<&str>,
    json: Option<&str>,
    opts: &[String],
) -> Result<Estimator, UsageError> {
    let mut obj = match json {
        Some(j) => read_json(j)?,
        None => Map::new(),
    };
    let json_kind = obj.get("kind").map(|k| k.as_str().map(str::to_string));
    let kind = match (kind, json_kind) {
        (_, Some(None)) => {
            return Err(UsageError(
                "--estimator-json: `kind` must be a string".into(),
            ));
        }
        (Some(a), Some(Some(b))) if a != b => {
            return Err(UsageError(format!(
                "--estimator {a} disagrees with --estimator-json kind `{b}`"
            )));
        }
        (Some(a), _) => a.to_string(),
        (None, Some(Some(b))) => b,
        (None, None) => "path".to_string(),
    };
    if !KINDS.contains(&kind.as_str()) {
        return Err(UsageError(format!(
            "unknown estimator `{kind}` (valid: {})",
            KINDS.join(", ")
        )));
    }
    for o in opts {
        let (k, v) = parse_opt(o)?;
        if k == "kind" {
            return Err(UsageError(
                "--opt kind=…: choose the estimator with --estimator".into(),
            ));
        }
        obj.insert(k, v);
    }
    obj.insert("kind".into(), Value::String(kind.clone()));
    let valid = option_names(&kind);
    // Name an unknown option ourselves (also for estimators without options, whose unit
    // variant would silently ignore it).
    if let Some(bad) = obj.keys().find(|k| *k != "kind" && !valid.contains(k)) {
        let list = if valid.is_empty() {
            "it takes no options".to_string()
        } else {
            format!("valid options: {}", valid.join(", "))
        };
        return Err(UsageError(format!(
            "estimator `{kind}` has no option `{bad}` ({list})"
        )));
    }
    let est: Estimator = serde_json::from_value(Value::Object(obj)).map_err(|e| {
        UsageError(format!(
            "estimator `{kind}` options: {e} (valid options: {})",
            valid.join(", ")
        ))
    })?;
    if let Estimator::Ocv(o) = &est
        && let Err((field, why)) = o.validate()
    {
        return Err(UsageError(format!(
            "estimator `ocv` option `{field}` {why}"
        )));
    }
    Ok(est)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ocv_options_parse_and_unknown_ones_are_named() {
        let e = build(Some("ocv"), None, &["spe=32".into(), "lambda=0.5".into()]).unwrap();
        let Estimator::Ocv(o) = e else {
            panic!("not ocv: {e:?}")
        };
        assert_eq!((o.spe, o.lambda), (32, 0.5));
        let err = build(Some("ocv"), None, &["speed=3".into()]).unwrap_err();
        assert!(err.0.contains("`speed`") && err.0.contains("spe"), "{err}");
        let err = build(Some("path"), None, &["spe=3".into()]).unwrap_err();
        assert!(err.0.contains("no options"), "{err}");
    }

    #[test]
    fn json_and_opt_combine_and_kinds_must_agree() {
        let e = build(
            None,
            Some(r#"{"kind":"ocv","spe":8}"#),
            &["lambda=2".into()],
        )
        .unwrap();
        let Estimator::Ocv(o) = e else {
            panic!("not ocv")
        };
        assert_eq!((o.spe, o.lambda), (8, 2.0));
        assert!(build(Some("path"), Some(r#"{"kind":"ocv"}"#), &[]).is_err());
        assert!(build(None, Some("[1]"), &[]).is_err());
        assert!(build(Some("ocv"), None, &["spe=0".into()]).is_err());
        assert!(build(Some("ocv"), None, &["spe=many".into()]).is_err());
        assert_eq!(build(None, None, &[]).unwrap(), Estimator::Path);
    }
}
