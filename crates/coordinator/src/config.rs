//! Coordinator configuration. Every value is explicit and documented; the CLI maps each to
//! a flag and an environment variable (`cvfarm serve --help`).
//!
//! | field | default | meaning |
//! |---|---|---|
//! | `database_url` | none → `sqlite://<data_dir>/cvfarm.sqlite` | `sqlite:…` or `postgres://…` |
//! | `data_dir` | `./cvfarm-data` | where the SQLite file lives |
//! | `client_tokens` | — (required) | bearer tokens accepted from clients |
//! | `enrollment_token` | — (required) | bearer token workers register with |
//! | `lease_ms` | 30 000 | lease duration; heartbeats extend it |
//! | `heartbeat_ms` | 10 000 | heartbeat period asked of workers |
//! | `max_attempts` | 5 | failed/expired attempts before a job fails |
//! | `max_worker_failures` | 3 | failures of one worker on one job before it is blocked for that job |
//! | `reaper_interval_ms` | 1 000 | how often expired leases are reclaimed |
//! | `long_poll_max_ms` | 20 000 | longest lease long-poll |
//! | `max_json_body` | 64 MiB | job submissions (inline scenes can hold meshes) |
//! | `max_asset_body` | 512 MiB | asset uploads |
//! | `max_result_body` | 64 MiB | tile result uploads |
//! | `limits` | [`protocol::Limits::default`] | resolution, spp and task-count limits |

use std::path::PathBuf;

use protocol::Limits;

/// See the module docs for every field's meaning and default.
#[derive(Clone, Debug)]
pub struct Config {
    /// Database URL; `None` = SQLite file in `data_dir`.
    pub database_url: Option<String>,
    /// Data directory.
    pub data_dir: PathBuf,
    /// Accepted client tokens.
    pub client_tokens: Vec<String>,
    /// Worker enrollment token.
    pub enrollment_token: String,
    /// Lease duration (ms).
    pub lease_ms: u64,
    /// Heartbeat period asked of workers (ms).
    pub heartbeat_ms: u64,
    /// Failed attempts of a task before its job fails.
    pub max_attempts: u32,
    /// Failures of a worker on a job before it is blocked for that job.
    pub max_worker_failures: u32,
    /// Reaper period (ms).
    pub reaper_interval_ms: u64,
    /// Longest long-poll (ms).
    pub long_poll_max_ms: u64,
    /// Body limit of JSON routes (bytes).
    pub max_json_body: usize,
    /// Body limit of asset uploads (bytes).
    pub max_asset_body: usize,
    /// Body limit of result uploads (bytes).
    pub max_result_body: usize,
    /// Job limits.
    pub limits: Limits,
}

impl Config {
    /// Defaults with the given tokens (both required).
    pub fn new(client_token: impl Into<String>, enrollment_token: impl Into<String>) -> Self {
        Self {
            database_url: None,
            data_dir: PathBuf::from("cvfarm-data"),
            client_tokens: vec![client_token.into()],
            enrollment_token: enrollment_token.into(),
            lease_ms: 30_000,
            heartbeat_ms: 10_000,
            max_attempts: 5,
            max_worker_failures: 3,
            reaper_interval_ms: 1_000,
            long_poll_max_ms: 20_000,
            max_json_body: 64 << 20,
            max_asset_body: 512 << 20,
            max_result_body: 64 << 20,
            limits: Limits::default(),
        }
    }
}
