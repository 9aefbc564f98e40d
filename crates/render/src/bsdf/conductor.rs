//! `conductor`: a perfectly smooth metal — a delta reflection lobe with conductor Fresnel
//! (Mitsuba 3's `conductor` plugin).
//!
//! | parameter | type | default | meaning |
//! |---|---|---|---|
//! | `eta` | RGB | aluminium (1.657, 0.880, 0.521) | real part of the complex IOR |
//! | `k` | RGB | aluminium (9.224, 6.270, 4.837) | imaginary part |
//! | `specular_reflectance` | colour or texture | 1 | multiplier (not physical) |
//!
//! ```json
//! "mirror": { "type": "conductor", "eta": [0.2, 0.92, 1.1], "k": [3.9, 2.45, 2.14] }
//! ```
//!
//! `eval` and `pdf` are 0 (the lobe is a Dirac); `sample` returns the mirror direction with
//! `pdf = 1` (the probability of the only lobe) and weight `specular_reflectance · F(cos θo)`.

use super::{BsdfSample, fresnel};
use glam::Vec3;

/// Mirror sample; `None` when `wo` is below the surface.
#[inline]
pub fn sample(eta: Vec3, k: Vec3, specular_reflectance: Vec3, wo: Vec3) -> Option<BsdfSample> {
    if wo.z <= 0.0 {
        return None;
    }
    let wi = Vec3::new(-wo.x, -wo.y, wo.z);
    let weight = specular_reflectance * fresnel::conductor(wo.z, eta, k);
    Some(BsdfSample {
        wi,
        weight,
        pdf: 1.0,
        delta: true,
    })
}
