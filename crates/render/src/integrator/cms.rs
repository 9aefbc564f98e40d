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

use serde::{Deserialize, Serialize};

use super::cv::CvColor;

/// Options of the `cms` estimator (see the module table).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CmsOptions {
    /// Optimise relative variance [Hua eq. 25].
    pub relative: bool,
    /// Per-channel or shared coefficients [Hua §4.3].
    pub color: CvColor,
    /// Training samples per pixel.
    pub training_spp: u32,
    /// Surrogate samples per pixel (with `relative`).
    pub surrogate_spp: u32,
    /// Grid cells per axis; `None` = adaptive.
    pub grid_resolution: Option<[u32; 3]>,
    /// Clustering threshold for emitters.
    pub max_light_components: u32,
    /// Relative ridge of the cell solves.
    pub ridge: f64,
    /// Minimum training samples per cell.
    pub min_samples: u64,
}

impl Default for CmsOptions {
    fn default() -> Self {
        Self {
            relative: true,
            color: CvColor::Rgb,
            training_spp: 16,
            surrogate_spp: 1,
            grid_resolution: None,
            max_light_components: 1024,
            ridge: 1e-6,
            min_samples: 16,
        }
    }
}
