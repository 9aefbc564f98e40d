//! Worker-facing API types (JSON) and client-facing job views.
//!
//! Worker life cycle: `POST /v1/workers/register` with the enrollment token returns a
//! per-worker bearer secret ([`RegisterResponse`]); `POST /v1/workers/lease` long-polls for a
//! [`TaskLease`] (204 when none within the poll window); `POST /v1/tasks/{id}/heartbeat`
//! extends the lease; `PUT /v1/tasks/{id}/result?attempt=N` uploads the binary
//! [`crate::frame`] stream; `POST /v1/tasks/{id}/release?attempt=N` gives a task back on shutdown.
//!
//! ```json
//! { "task_id": 17, "attempt": 2, "job_id": 3, "phase": "render",
//!   "rect": {"x0": 32, "y0": 0, "width": 32, "height": 32}, "sample_start": 0, "sample_end": 16,
//!   "scene_hash": "…64 hex…", "assets": {"meshes/bunny.obj": "…64 hex…"},
//!   "job": { "width": 64, "height": 64, "spp": 16, "seed": 0, "max_depth": 5, "rr_depth": 5,
//!            "hide_emitters": false, "tile_size": 32, "samples_per_task": 16 },
//!   "estimator": {"kind": "path"}, "surrogate": null, "coefficients": null,
//!   "lease_ms": 30000, "heartbeat_ms": 10000 }
//! ```
//!
//! Leases of a CV job's `train` phase carry the content address of the surrogate image
//! (`surrogate`, relative-variance `cms` and `per_light_cv` only), those of its `render` phase the address of
//! the solved coefficient table (`coefficients`); workers fetch both with
//! `GET /v1/assets/{hash}`, check the SHA-256 and cache them.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use crate::frame::TileHeader;
use crate::job::{EstimatorSpec, ResolvedJob, TileRect};

/// Body of `POST /v1/workers/register` (bearer: the enrollment token).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RegisterRequest {
    /// A human-readable name (host name); need not be unique.
    pub name: String,
}

/// Answer to a registration: the worker's identity and its bearer secret (shown once; the
/// coordinator keeps only its hash).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RegisterResponse {
    /// Worker id.
    pub worker_id: i64,
    /// Bearer token to send on every worker request.
    pub token: String,
}

/// Body of `POST /v1/workers/lease`.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LeaseRequest {
    /// How long to wait for a task before answering 204, in milliseconds (capped by the server).
    #[serde(default)]
    pub wait_ms: u64,
}

/// The phase a task belongs to (DESIGN §1).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PhaseKind {
    /// 1–2 spp for the relative-variance surrogate.
    Surrogate,
    /// Training samples (per-cell accumulators + pixels).
    Train,
    /// The final render pass.
    Render,
}

impl PhaseKind {
    /// The name stored in the database and used on the wire.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Surrogate => "surrogate",
            Self::Train => "train",
            Self::Render => "render",
        }
    }

    /// Parses [`Self::as_str`].
    pub fn parse(s: &str) -> Option<Self> {
        match s {
            "surrogate" => Some(Self::Surrogate),
            "train" => Some(Self::Train),
            "render" => Some(Self::Render),
            _ => None,
        }
    }
}

/// A leased task: everything a worker needs to render it and upload the result.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TaskLease {
    /// Task id.
    pub task_id: i64,
    /// Attempt number of this lease (1 for the first); the upload must carry it.
    pub attempt: u32,
    /// Job id.
    pub job_id: i64,
    /// Phase of the task.
    pub phase: PhaseKind,
    /// Pixels to render.
    pub rect: TileRect,
    /// First sample index.
    pub sample_start: u32,
    /// End sample index (exclusive).
    pub sample_end: u32,
    /// Content address of the scene document (`GET /v1/assets/{hash}`).
    pub scene_hash: String,
    /// Asset name → content address.
    #[serde(default)]
    pub assets: BTreeMap<String, String>,
    /// Resolved job settings.
    pub job: ResolvedJob,
    /// Estimator and its options.
    pub estimator: EstimatorSpec,
    /// Content address of the surrogate image the `train` phase weights its samples with
    /// ([`estimators::surrogate::encode_surrogate`]), if the phase has one.
    #[serde(default)]
    pub surrogate: Option<String>,
    /// Content address of the coefficient table the `render` phase applies
    /// (`estimators::table` encoding, kind `KIND_COEFFICIENTS`), if the phase has one.
    #[serde(default)]
    pub coefficients: Option<String>,
    /// Lease duration from now, in milliseconds.
    pub lease_ms: u64,
    /// How often to heartbeat while working, in milliseconds.
    pub heartbeat_ms: u64,
}

impl TaskLease {
    /// The frame header of this lease's result (job, task, attempt, rectangle, samples).
    pub fn tile_header(&self) -> TileHeader {
        TileHeader {
            job_id: self.job_id,
            task_id: self.task_id,
            attempt: self.attempt,
            rect: self.rect,
            sample_start: self.sample_start,
            sample_end: self.sample_end,
        }
    }
}

/// Answer to a heartbeat.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HeartbeatResponse {
    /// New lease duration from now, in milliseconds.
    pub lease_ms: u64,
}

/// Answer to a result upload.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct UploadResponse {
    /// `true` when this (task, attempt) had already been accepted (an idempotent retry).
    pub duplicate: bool,
}

/// State of a job.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum JobState {
    /// Waiting for or being worked on by workers.
    Running,
    /// Paused by a client: no new leases until resumed.
    Paused,
    /// Finished: results can be downloaded.
    Done,
    /// Gave up (a task exceeded its retry cap).
    Failed,
    /// Cancelled by a client.
    Cancelled,
}

impl JobState {
    /// The name stored in the database.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Running => "running",
            Self::Paused => "paused",
            Self::Done => "done",
            Self::Failed => "failed",
            Self::Cancelled => "cancelled",
        }
    }

    /// Parses [`Self::as_str`].
    pub fn parse(s: &str) -> Option<Self> {
        match s {
            "running" => Some(Self::Running),
            "paused" => Some(Self::Paused),
            "done" => Some(Self::Done),
            "failed" => Some(Self::Failed),
            "cancelled" => Some(Self::Cancelled),
            _ => None,
        }
    }
}

/// Answer to `POST /v1/jobs`.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SubmitResponse {
    /// New job id.
    pub job_id: i64,
    /// Number of tasks of the first phase.
    pub tasks: u64,
}

/// `GET /v1/jobs/{id}`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct JobStatus {
    /// Job id.
    pub job_id: i64,
    /// State.
    pub state: JobState,
    /// Current phase.
    pub phase: PhaseKind,
    /// Estimator name.
    pub estimator: String,
    /// Priority.
    pub priority: i32,
    /// Tasks of the current phase.
    pub tasks_total: u64,
    /// Finished tasks of the current phase.
    pub tasks_done: u64,
    /// Resolved settings.
    pub job: ResolvedJob,
    /// Why the job failed, if it did.
    #[serde(default)]
    pub error: Option<String>,
    /// Estimated seconds to completion of a running job (from the tasks done so far; capped
    /// by what is left of a time budget); absent when unknown or finished.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub eta_s: Option<f64>,
}

/// `stats.json` of a finished job.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct JobStats {
    /// Job id.
    pub job_id: i64,
    /// Estimator name.
    pub estimator: String,
    /// Resolved settings.
    pub job: ResolvedJob,
    /// Per phase: name, wall-clock seconds from first lease to last accepted result.
    pub phases: Vec<PhaseStats>,
    /// Seconds from submission to completion.
    pub total_seconds: f64,
    /// Samples per pixel actually merged (mean over pixels).
    pub spp: f64,
    /// Estimated relMSE of the image from per-pixel variance (DESIGN §6).
    pub estimated_rel_mse: f64,
    /// Tasks whose result was accepted, and attempts made in all.
    pub tasks: u64,
    /// Lease attempts over all tasks (≥ tasks; more when leases expired or failed).
    pub attempts: u64,
    /// Effects and techniques simulated (empty until the renderer reports them).
    pub effects: Vec<String>,
    /// Weight of the samples rendered without the CV (surrogate and training phases) in the
    /// image, the render phase's samples the rest (`protocol::assemble`); absent when all
    /// phases were merged plainly.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub uncontrolled_weight: Option<f64>,
}

/// Time spent in one phase, and what its barrier computed.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PhaseStats {
    /// Phase name.
    pub name: String,
    /// Seconds from the phase's first lease to its last accepted result.
    pub seconds: f64,
    /// Tasks in the phase.
    pub tasks: u64,
    /// Samples per pixel rendered in the phase.
    #[serde(default)]
    pub spp: u32,
    /// What the barrier after this phase computed (surrogate, or merge + solve), if any.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub barrier: Option<BarrierStats>,
}

/// What the coordinator computed at a phase barrier: the surrogate image after `surrogate`,
/// the merged and solved cell table after `train`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BarrierStats {
    /// Seconds spent (decode, merge, solve or denoise, encode).
    pub seconds: f64,
    /// Content address of the stored blob (surrogate image or coefficient table).
    pub blob: String,
    /// Cells that received training data (train barrier).
    #[serde(default)]
    pub cells: u64,
    /// Cells whose system was solved.
    #[serde(default)]
    pub cells_solved: u64,
    /// Cells that fell back to the plain estimator, by reason.
    #[serde(default)]
    pub cells_fallback: BTreeMap<String, u64>,
    /// Training samples rejected as non-finite.
    #[serde(default)]
    pub rejected_samples: u64,
    /// Predicted image gain of the fits (`estimators::table::predicted_image_gain`; below
    /// the job's `min_image_gain` every cell falls back), when known.
    #[serde(default)]
    pub predicted_image_gain: Option<f64>,
    /// Predicted fit gain (`estimators::table::predicted_fit_gain`; below the job's
    /// `min_fit_gain` every cell falls back), when known.
    #[serde(default)]
    pub predicted_fit_gain: Option<f64>,
    /// Held-out fit gain (`estimators::table::SolvedTable::held_out_gain`), when known.
    #[serde(default)]
    pub predicted_held_out_gain: Option<f64>,
    /// Held-out share of the fits' gain (`estimators::table::SolvedTable::held_out_share`;
    /// below the job's `min_held_out_share`, with a held-out gain below `min_fit_gain` — for
    /// `per_light_cv` whatever the gain — every cell falls back), when known.
    #[serde(default)]
    pub predicted_held_out_share: Option<f64>,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lease_roundtrip() {
        let l = TaskLease {
            task_id: 1,
            attempt: 2,
            job_id: 3,
            phase: PhaseKind::Render,
            rect: TileRect {
                x0: 0,
                y0: 0,
                width: 8,
                height: 8,
            },
            sample_start: 0,
            sample_end: 4,
            scene_hash: "0".repeat(64),
            assets: BTreeMap::new(),
            job: ResolvedJob {
                width: 8,
                height: 8,
                spp: 4,
                seed: 1,
                sampler: Default::default(),
                max_depth: 5,
                rr_depth: 5,
                hide_emitters: false,
                tile_size: 8,
                samples_per_task: 4,
            },
            estimator: EstimatorSpec::default(),
            surrogate: None,
            coefficients: None,
            lease_ms: 1000,
            heartbeat_ms: 300,
        };
        let s = serde_json::to_string(&l).unwrap();
        assert_eq!(serde_json::from_str::<TaskLease>(&s).unwrap(), l);
        for p in [PhaseKind::Surrogate, PhaseKind::Train, PhaseKind::Render] {
            assert_eq!(PhaseKind::parse(p.as_str()), Some(p));
        }
        for st in [
            JobState::Running,
            JobState::Done,
            JobState::Failed,
            JobState::Cancelled,
        ] {
            assert_eq!(JobState::parse(st.as_str()), Some(st));
        }
    }
}
