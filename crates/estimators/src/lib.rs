//! Control-variate mathematics for cvfarm, as pure functions on plain data.
//!
//! No I/O, no rendering, no async: the renderer, the worker and the coordinator share this
//! one implementation.
//!
//! # Layout
//! - [`mis`]: balance/power heuristic weights, effective mixture density [Hua eq. 16].
//! - [`metrics`]: relMSE, MSE, efficiency and speedup (DESIGN §6).

#![deny(missing_docs)]

pub mod metrics;
pub mod mis;
