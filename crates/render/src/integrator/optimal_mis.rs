//! `optimal_mis` — optimal MIS weights (Kondapaneni et al. 2019) as the CMS system solved
//! per pixel for direct illumination [Hua §7.4].
//!
//! Same components and system as [`super::cms`] (one per light/cluster + BSDF), but the
//! cells are the pixels and only the first vertex (direct illumination seen by the camera)
//! is controlled; deeper vertices use the plain balance heuristic. With one integral per
//! cell the relative weighting cancels, so there is no surrogate phase.
//!
//! A per-pixel fit removes iid per-sample variance at the camera hit, but the plain pixel
//! estimate is a mean of the Sobol sampler's stratified samples, whose error falls faster.
//! So each training tile checks its fits out of sample on its two halves of training samples
//! (`min_split_gain`, see `cv::split_half_gain`) and renders its pixels as `path` where they
//! do not pay.
//!
//! Options (defaults, ranges, meaning): the table of [`OptimalMisOptions`] (defined once, in
//! `estimators::spec`, for the CLI, the farm's API and the renderer).
//!
//! ```json
//! { "kind": "optimal_mis", "training_spp": 16 }
//! ```

pub use estimators::spec::OptimalMisOptions;
