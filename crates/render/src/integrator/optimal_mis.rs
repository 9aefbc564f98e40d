//! `optimal_mis` — optimal MIS weights (Kondapaneni et al. 2019) as the CMS system solved
//! per pixel for direct illumination [Hua §7.4].
//!
//! Same components and system as [`super::cms`] (one per light/cluster + BSDF), but the
//! cells are the pixels and only the first vertex (direct illumination seen by the camera)
//! is controlled; deeper vertices use the plain balance heuristic. With one integral per
//! cell the relative weighting cancels, so there is no surrogate phase.
//!
//! | parameter | type | default | meaning |
//! |---|---|---|---|
//! | `training_spp` | u32 | 16 | samples per pixel of the training phase (kept in the image) |
//! | `color` | `"rgb"` \| `"mono"` | `"rgb"` | coefficients per channel or shared |
//! | `max_light_components` | u32 | 1024 | more emitters than this are clustered by spatial proximity |
//! | `ridge` | f64 | `1e-6` | relative Tikhonov regularisation |
//! | `min_samples` | u64 | 16 | pixels with fewer training samples fall back to the plain estimator |
//!
//! ```json
//! { "kind": "optimal_mis", "training_spp": 16 }
//! ```

pub use estimators::spec::OptimalMisOptions;
