//! `roughconductor`: a microfacet metal (Mitsuba 3's `roughconductor` plugin with
//! `sample_visible = true`, isotropic α).
//!
//! | parameter | type | default | meaning |
//! |---|---|---|---|
//! | `distribution` | `ggx` \| `beckmann` | `ggx` | microfacet normal distribution |
//! | `alpha` | float | 0.1 | roughness α (not squared; clamped to ≥ 1e-4) |
//! | `eta` | RGB | aluminium | real part of the complex IOR |
//! | `k` | RGB | aluminium | imaginary part |
//! | `specular_reflectance` | colour or texture | 1 | multiplier |
//!
//! ```json
//! "gold": { "type": "roughconductor", "alpha": 0.15, "eta": [0.143, 0.374, 1.442], "k": [3.983, 2.385, 1.603] }
//! ```
//!
//! With h = normalize(wo + wi):
//! eval = F(wo·h) D(h) G1(wo,h) G1(wi,h) / (4 cos θo) · specular_reflectance (this is f·cos θi);
//! pdf = D(h) G1(wo,h) / (4 cos θo) (visible-normal sampling, solid angle of wi);
//! sample weight = F(wo·h) G1(wi,h) · specular_reflectance.

use super::microfacet::{Microfacet, reflect};
use super::{BsdfSample, fresnel};
use glam::{Vec2, Vec3};

/// f·cos θi.
#[inline]
pub fn eval(
    mf: &Microfacet,
    eta: Vec3,
    k: Vec3,
    specular_reflectance: Vec3,
    wo: Vec3,
    wi: Vec3,
) -> Vec3 {
    if wo.z <= 0.0 || wi.z <= 0.0 {
        return Vec3::ZERO;
    }
    let h = (wo + wi).normalize();
    let d = mf.d(h);
    if d == 0.0 {
        return Vec3::ZERO;
    }
    let g = mf.g(wo, wi, h);
    let f = fresnel::conductor(wo.dot(h), eta, k);
    let v = d * g / (4.0 * wo.z);
    if v.is_finite() {
        specular_reflectance * f * v
    } else {
        Vec3::ZERO
    }
}

/// Solid-angle pdf of [`sample`].
#[inline]
pub fn pdf(mf: &Microfacet, wo: Vec3, wi: Vec3) -> f32 {
    if wo.z <= 0.0 || wi.z <= 0.0 {
        return 0.0;
    }
    let h = (wo + wi).normalize();
    if wo.dot(h) <= 0.0 || wi.dot(h) <= 0.0 {
        return 0.0;
    }
    let p = mf.d(h) * mf.g1(wo, h) / (4.0 * wo.z);
    if p.is_finite() { p } else { 0.0 }
}

/// `(eval, pdf)` in one pass (shares h, D and G1(wo, h)).
#[inline]
pub fn eval_pdf(
    mf: &Microfacet,
    eta: Vec3,
    k: Vec3,
    specular_reflectance: Vec3,
    wo: Vec3,
    wi: Vec3,
) -> (Vec3, f32) {
    if wo.z <= 0.0 || wi.z <= 0.0 {
        return (Vec3::ZERO, 0.0);
    }
    let h = (wo + wi).normalize();
    if wo.dot(h) <= 0.0 || wi.dot(h) <= 0.0 {
        return (Vec3::ZERO, 0.0);
    }
    let pdf = mf.d(h) * mf.g1(wo, h) / (4.0 * wo.z);
    if !pdf.is_finite() || pdf == 0.0 {
        return (Vec3::ZERO, 0.0);
    }
    let v = specular_reflectance * fresnel::conductor(wo.dot(h), eta, k) * (pdf * mf.g1(wi, h));
    (if v.is_finite() { v } else { Vec3::ZERO }, pdf)
}

/// Visible-normal sample; `None` if `wo` is below the surface or the reflection goes below it.
#[inline]
pub fn sample(
    mf: &Microfacet,
    eta: Vec3,
    k: Vec3,
    specular_reflectance: Vec3,
    wo: Vec3,
    u: Vec2,
) -> Option<BsdfSample> {
    if wo.z <= 0.0 {
        return None;
    }
    let m = mf.sample_visible(wo, u);
    let wi = reflect(wo, m).normalize();
    if wi.z <= 0.0 || !wi.is_finite() {
        return None;
    }
    let (value, pdf) = eval_pdf(mf, eta, k, specular_reflectance, wo, wi);
    if pdf.is_nan() || pdf <= 0.0 {
        return None;
    }
    Some(BsdfSample {
        wi,
        weight: value / pdf,
        pdf,
        delta: false,
    })
}
