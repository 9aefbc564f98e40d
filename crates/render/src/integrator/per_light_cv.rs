//! `per_light_cv` — the per-light control variate of Vévoda et al. 2018, as compared in
//! [Hua §7.2].
//!
//! The CV is formed from the light-sampling pdfs only and applied to the MIS-weighted NEE
//! integral at every vertex: per cell and light (cluster) the coefficient is the mean
//! MIS-weighted NEE contribution of that light over the cell's training vertices (no linear
//! solve; `estimators::perlight`). This is the special case of the CMS system restricted
//! to the NEE technique, so it is never worse than the baseline in expectation [Hua §7.2].
//! The BSDF sample keeps its plain balance-heuristic value.
//!
//! Options (defaults, ranges, meaning): the table of [`PerLightCvOptions`] (defined once, in
//! `estimators::spec`, for the CLI, the farm's API and the renderer).
//!
//! ```json
//! { "kind": "per_light_cv", "training_spp": 16 }
//! ```

pub use estimators::spec::PerLightCvOptions;
