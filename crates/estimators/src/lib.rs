//! Control-variate mathematics for cvfarm, as pure functions on plain data.
//!
//! No I/O, no rendering, no async: the renderer, the worker and the coordinator share this
//! one implementation.
//!
//! # Layout
//! - [`mis`]: balance/power heuristic weights, effective mixture density [Hua eq. 16],
//!   deterministic mixture sample counts [Fan §4].
//! - [`cell`]: per-cell accumulators of the CV normal equations [Hua eq. 21, 23, 25, 29],
//!   merge and versioned binary encoding.
//! - [`solve`]: dense and Schur-complement solvers [Hua eq. 32–33], the policy for hard
//!   cells, coefficients and their application to samples.
//! - [`ocv`]: optimizing control variates, penalised least squares per estimate
//!   [Fan eq. 7–11].
//! - [`table`]: keyed tables of per-cell records (accumulators, coefficients), their wire
//!   encoding (the opaque payload of the protocol's cell frames), merge and solve-all.
//! - [`perlight`]: per-light mean-contribution coefficients of the `per_light_cv` baseline
//!   [Hua §7.2].
//! - [`composite`]: inverse-variance and Keller–Olkin weights with PSD check and fallbacks,
//!   the re-rendering composite [Rou §3.2, §4].
//! - [`reconstruct`]: image-space reconstructions of gradient-domain renderings: uniform and
//!   weighted iterated CV, screened Poisson L2 and weighted L2 [Rou §5].
//! - [`filter`]: NL-means prefiltering of variances [Rou §4.1] and the surrogate denoiser
//!   for relative-variance training [Hua §4.2.1].
//! - [`denoise`]: edge-aware à-trous wavelet denoiser (albedo/normal/variance guided) for
//!   the surrogate image of relative-variance training [Hua §4.2.1].
//! - [`spec`]: options of the CV estimators and their phase split (shared by renderer,
//!   wire format and coordinator).
//! - [`surrogate`]: the denoised surrogate image of relative training [Hua eq. 25] from
//!   per-pixel moments.
//! - [`metrics`]: relMSE, MSE, efficiency and speedup (DESIGN §6).
//! - [`perceptual`]: Fan's perceptual error with the tvi function [Fan eq. 12].

//! # The CV pipeline in one example
//! ```
//! use estimators::cell::{CellAccumulator, ColorMode, ComponentLayout, CvSample, training_weight};
//! use estimators::solve::{SolvePolicy, solve};
//!
//! // Two lights (partitions) and a BSDF component (overlapping).
//! let layout = ComponentLayout::new(2, 1).unwrap();
//! let mut cell = CellAccumulator::new(layout, ColorMode::Rgb);
//! // Training pass, per sample: weight, F = f/p, mixture density p and the λ's.
//! for i in 0..64 {
//!     let light = (i % 2) as u32;
//!     let s = CvSample { pdf: 2.0, partition: Some((light, 1.5)), overlapping: &[0.5] };
//!     let w = training_weight(1.0, Some(0.3));
//!     cell.add(w, [0.8, 0.4, 0.2 + 0.01 * i as f64], &s).unwrap();
//! }
//! // Coordinator: merge cells in task order, then solve each.
//! let coeffs = solve(&cell, &SolvePolicy::default());
//! // Render pass, per vertex: Σα once, and F − Σ α_k λ_k / p per sample.
//! let s = CvSample { pdf: 2.0, partition: Some((1, 1.5)), overlapping: &[0.5] };
//! let controlled = coeffs.apply([0.8, 0.4, 0.5], &s);
//! let vertex_estimate: Vec<f64> = (0..3).map(|c| coeffs.alpha_sum()[c] + controlled[c]).collect();
//! assert!(vertex_estimate.iter().all(|v| v.is_finite()));
//! ```

#![deny(missing_docs)]
// `!(x > 0.0)` is deliberate throughout: a NaN must fail every validity check.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

pub mod cell;
pub mod composite;
pub mod denoise;
pub mod filter;
pub mod metrics;
pub mod mis;
pub mod ocv;
pub mod perceptual;
pub mod perlight;
pub mod reconstruct;
pub mod solve;
pub mod spec;
pub mod surrogate;
pub mod table;
