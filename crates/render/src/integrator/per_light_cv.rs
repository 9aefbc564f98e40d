//! `per_light_cv` — the per-light control variate of Vévoda et al. 2018, as compared in
//! [Hua §7.2].
//!
//! The CV is formed from the light-sampling pdfs only and applied to the MIS-weighted NEE
//! integral at every vertex: per cell and light (cluster) the coefficient is the mean
//! MIS-weighted NEE contribution of that light over the cell's training vertices (no linear
//! solve; `estimators::perlight`). This is the special case of the CMS system restricted
//! to the NEE technique, so it is never worse than the baseline in expectation [Hua §7.2]
//! — in the cell's pooled variance. A cell mixes bright and dark pixels' vertices, and its
//! means subtracted at a dark one are added variance there, which a relative error weighs
//! most: each training vertex is therefore also weighed as `cms` weighs its samples
//! (squared throughput over the squared 1-spp surrogate [Hua eq. 25, 29]), a cell keeps its
//! means only where they reduce that weighted variance in-sample
//! (`estimators::perlight`, `FallbackReason::NoReduction`), and the table is switched off
//! like `cms`'s when the rest is predicted not to pay (`min_image_gain`, `min_fit_gain`).
//! Phases: surrogate (with `relative`) → train → render. The BSDF sample keeps its plain
//! MIS-weighted value.
//!
//! Options (defaults, ranges, meaning): the table of [`PerLightCvOptions`] (defined once, in
//! `estimators::spec`, for the CLI, the farm's API and the renderer).
//!
//! ```json
//! { "kind": "per_light_cv", "training_spp": 16 }
//! ```

pub use estimators::spec::PerLightCvOptions;
