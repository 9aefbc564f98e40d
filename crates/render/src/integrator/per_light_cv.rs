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
//! | parameter | type | default | meaning |
//! |---|---|---|---|
//! | `training_spp` | u32 | 16 | samples per pixel of the training phase (kept in the image) |
//! | `grid_resolution` | `[nx, ny, nz]` \| null | null | cells per axis; null = adaptive (≈ 16×16 pixels per cell) |
//! | `max_light_components` | u32 | 1024 | more emitters than this are clustered by spatial proximity |
//!
//! ```json
//! { "kind": "per_light_cv", "training_spp": 16 }
//! ```

use serde::{Deserialize, Serialize};

/// Options of the `per_light_cv` estimator (see the module table).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PerLightCvOptions {
    /// Training samples per pixel.
    pub training_spp: u32,
    /// Grid cells per axis; `None` = adaptive.
    pub grid_resolution: Option<[u32; 3]>,
    /// Clustering threshold for emitters.
    pub max_light_components: u32,
}

impl Default for PerLightCvOptions {
    fn default() -> Self {
        Self {
            training_spp: 16,
            grid_resolution: None,
            max_light_components: 1024,
        }
    }
}
