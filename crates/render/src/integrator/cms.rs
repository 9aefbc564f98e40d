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
//! | parameter | type | default | meaning |
//! |---|---|---|---|
//! | `relative` | bool | `true` | optimise relative variance: weight training samples by `1/(surrogate + 0.01)²` [Hua eq. 25] |
//! | `color` | `"rgb"` \| `"mono"` | `"rgb"` | coefficients per channel or shared [Hua §4.3] |
//! | `training_spp` | u32 | 16 | samples per pixel of the training phase (kept in the image) |
//! | `surrogate_spp` | u32 | 1 | samples per pixel of the surrogate image (only with `relative`; kept in the image) |
//! | `grid_resolution` | `[nx, ny, nz]` \| null | null | cells per axis over the scene bounds; null = adaptive (≈ 16×16 pixels per cell) |
//! | `max_light_components` | u32 | 1024 | more emitters than this are clustered by spatial proximity |
//! | `ridge` | f64 | `1e-6` | relative Tikhonov regularisation of each cell system |
//! | `min_samples` | u64 | 16 | cells with fewer training samples fall back to the plain estimator |
//!
//! ```json
//! { "kind": "cms", "relative": true, "color": "rgb", "training_spp": 16, "grid_resolution": [32, 32, 32] }
//! ```

pub use estimators::spec::CmsOptions;
