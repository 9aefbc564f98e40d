//! `diffuse`: the Lambertian reflector (Mitsuba 3's `diffuse` plugin).
//!
//! | parameter | type | default | meaning |
//! |---|---|---|---|
//! | `reflectance` | colour or texture | 0.5 | albedo ρ: f = ρ/π |
//!
//! ```json
//! "white": { "type": "diffuse", "reflectance": [0.8, 0.8, 0.8] }
//! ```
//!
//! eval = ρ/π · cos θi; sampling is cosine-weighted (pdf cos θi / π, solid angle), so the sample
//! weight is exactly ρ. One-sided: zero unless `wo.z > 0` and `wi.z > 0`.

use super::BsdfSample;
use super::microfacet::{cosine_hemisphere_pdf, square_to_cosine_hemisphere};
use glam::{Vec2, Vec3};
use std::f32::consts::FRAC_1_PI;

/// f·cos θi.
#[inline]
pub fn eval(reflectance: Vec3, wo: Vec3, wi: Vec3) -> Vec3 {
    if wo.z > 0.0 && wi.z > 0.0 {
        reflectance * (FRAC_1_PI * wi.z)
    } else {
        Vec3::ZERO
    }
}

/// Solid-angle pdf of [`sample`].
#[inline]
pub fn pdf(wo: Vec3, wi: Vec3) -> f32 {
    if wo.z > 0.0 {
        cosine_hemisphere_pdf(wi)
    } else {
        0.0
    }
}

/// Cosine-weighted sample; `None` below the horizon or for a sample on the horizon itself.
#[inline]
pub fn sample(reflectance: Vec3, wo: Vec3, u: Vec2) -> Option<BsdfSample> {
    if wo.z <= 0.0 {
        return None;
    }
    let wi = square_to_cosine_hemisphere(u);
    let pdf = cosine_hemisphere_pdf(wi);
    (pdf > 0.0).then_some(BsdfSample {
        wi,
        weight: reflectance,
        pdf,
        delta: false,
    })
}
