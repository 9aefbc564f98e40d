//! Wire and API types of the cvfarm farm, shared by the coordinator, the workers and the CLI.
//!
//! Everything here is plain data plus pure functions: no I/O, no async, no rendering. Two
//! encodings are used on the wire:
//! - **JSON** (serde) for the REST API: [`job::JobSpec`] submitted by clients, [`lease::TaskLease`]
//!   handed to workers, [`error::ApiError`] for every 4xx/5xx body.
//! - **Binary frames** ([`frame`]) for tile results streamed by workers: length-delimited,
//!   versioned, validated on decode (sizes, finite values), never panicking on arbitrary bytes.
//!
//! # Layout
//! - [`job`]: `JobSpec`, `EstimatorSpec` (typed options of every estimator, from
//!   `estimators::spec`), limits and validation, the canonical phase plan.
//! - [`lease`]: worker registration, `TaskLease`, heartbeats, job status views.
//! - [`frame`]: the `TileResult` binary frame format (encode / decode / validate).
//! - [`assemble`]: merging pixel blocks into an image in canonical task order.
//! - [`cv`]: the barriers of CV phases (surrogate image; train-block checks, merge in
//!   canonical order, solve summary), shared by the coordinator and the worker.
//! - [`error`]: the API error body `{ "error": { "code", "message", "field"? } }`.
//! - [`hash`]: SHA-256 content addresses (lower-case hex).
//!
//! # Determinism
//! A job's decomposition into phases and tasks ([`job::plan_phases`]) depends only on its spec,
//! never on the number of workers; [`assemble::ImageAccumulator`] adds blocks in (phase, task)
//! order and [`cv::merge_train`] merges training tables in task order, so the final image is
//! bitwise-identical however the tasks were distributed or retried.

#![deny(missing_docs)]

pub mod assemble;
pub mod cv;
pub mod error;
pub mod frame;
pub mod hash;
pub mod job;
pub mod lease;

pub use error::{ApiError, ApiErrorBody};
pub use frame::{FrameError, PixelRecord, TileResult};
pub use job::{EstimatorSpec, JobSpec, Limits, PhasePlan, SpecError, TaskPlan, TileRect};
pub use lease::TaskLease;
