//! `cms` — controlled mixture sampling [Hua 2023], the flagship CV estimator.
//!
//! At every path vertex the direct-lighting integral (NEE sample + BSDF sample, balance
//! heuristic) is estimated with a control variate made of the sampling pdfs themselves
//! [Hua eq. 17]:
//!
//! ```text
//! ⟨L⟩_v = β_v · ( Σ_k α_k + Σ_{s ∈ {nee, bsdf}} (F_s − Σ_k α_k λ_k(x_s) / p(x_s)) )
//! ```
//!
//! with `p = p_light + p_bsdf` the effective mixture density [Hua eq. 16], `F_s = f/p`, one
//! component `λ_k` per light (or light cluster, env map included) and one for the BSDF
//! [Hua eq. 18]. The coefficients `α` are fitted per cell of a sparse regular grid over the
//! scene from the training samples [Hua eq. 23, 29] (relative variance: [Hua eq. 25]) and
//! solved with the Schur complement [Hua eq. 32–33]. Phases: surrogate (only with
//! `relative`) → train → solve → render; training samples are kept in the image.
//! See `cv.rs` for the measures and the handling of zero-contribution samples.
//!
//! Options (defaults, ranges, meaning): the table of [`CmsOptions`] (defined once, in
//! `estimators::spec`, for the CLI, the farm's API and the renderer). With the default
//! `base: "balance"` each sample's `F_s` is the paper's `f/p`; with `base: "mis"` it is the
//! job's MIS-weighted value (power heuristic, as `path`). The CV term has zero mean for
//! either base, and for either a cell without coefficients (`α ≡ 0`) renders exactly like
//! `path`, as do the training samples.
//!
//! ```json
//! { "kind": "cms", "relative": true, "color": "rgb", "training_spp": 16, "grid_resolution": [16, 16, 16], "grid_levels": 2, "ridge": 1.0, "base": "balance" }
//! ```

pub use estimators::spec::CmsOptions;
