//! `optimal_mis` — optimal MIS weights (Kondapaneni et al. 2019) as the CMS system solved
//! per pixel for direct illumination [Hua §7.4].
//!
//! Same components and system as [`super::cms`] (one per light/cluster + BSDF), but the
//! cells are the pixels and only the first vertex (direct illumination seen by the camera)
//! is controlled; deeper vertices use the plain balance heuristic. With one integral per
//! cell the relative weighting cancels, so there is no surrogate phase.
//!
//! Options (defaults, ranges, meaning): the table of [`OptimalMisOptions`] (defined once, in
//! `estimators::spec`, for the CLI, the farm's API and the renderer).
//!
//! ```json
//! { "kind": "optimal_mis", "training_spp": 16 }
//! ```

pub use estimators::spec::OptimalMisOptions;
