//! `roughplastic`: Mitsuba 3's layered rough plastic — a rough dielectric coating (microfacet
//! reflection, `sample_visible = true`) over a diffuse base, with the internal scattering of the
//! layer folded into precomputed scalars. It is **not** "GGX + Lambert".
//!
//! | parameter | type | default | meaning |
//! |---|---|---|---|
//! | `distribution` | `ggx` \| `beckmann` | `ggx` | microfacet normal distribution of the coating |
//! | `alpha` | float | 0.1 | roughness α (not squared; clamped to ≥ 1e-4) |
//! | `int_ior`, `ext_ior` | float | 1.49, 1.000277 | η = int_ior / ext_ior |
//! | `diffuse_reflectance` | colour or texture | 0.5 | albedo ρ of the base |
//! | `specular_reflectance` | colour or texture | 1 | multiplier of the coating reflection |
//! | `nonlinear` | bool | false | account for the colour shift of multiple internal bounces |
//!
//! ```json
//! "plastic": { "type": "roughplastic", "alpha": 0.1, "int_ior": 1.5, "ext_ior": 1.0,
//!              "diffuse_reflectance": [0.02, 0.2, 0.1] }
//! ```
//!
//! # Model (Mitsuba 3 `roughplastic.cpp`)
//! With h = normalize(wo + wi), all cosines positive (one-sided):
//! - specular: F(wo·h, η) D(h) G1(wo,h) G1(wi,h) / (4 cos θo) · specular_reflectance;
//! - diffuse: ρ / (1 − R_int) (or ρ / (1 − ρ R_int) if `nonlinear`) · T(cos θo) T(cos θi) /
//!   (π η²) · cos θi — the (1 − F_in)(1 − F_out)/η² of a smooth coating, with the rough
//!   coating's directional transmittance T(μ) in place of 1 − F;
//! - T(μ, η) = ∫ (1 − F(wo·m, η)) G1(wt, m) D_wo(m) dm (wt: wo refracted at m), tabulated at
//!   [`TABLE_RES`] points μ = max(1e-6, i/63) by Gauss–Legendre quadrature over the
//!   visible-normal sample space (32² nodes for η > 1, 128² otherwise), looked up by linear
//!   interpolation ([`transmittance_albedo`]);
//! - R(μ, η) = ∫ F(wo·m, η) G1(wi, m) D_wo(m) dm, the directional albedo of the coating's specular
//!   lobe ([`specular_albedo`], same quadrature);
//! - R_int = 2 · mean_i(R(μ_i, 1/η) μ_i): the internal (cosine-weighted) reflectance of the layer
//!   seen from below.
//!
//! Sampling picks the specular lobe with probability
//! p_s = (1 − T(cos θo)) w / ((1 − T(cos θo)) w + T(cos θo)(1 − w)), where the specular sampling
//! weight w = mean(specular_reflectance) / (mean(diffuse_reflectance) + mean(specular_reflectance))
//! uses the means over the whole texture (computed once); otherwise cosine-weighted. `pdf` is the
//! mixture p_s · D(h) G1(wo,h)/(4 cos θo) + (1 − p_s) cos θi/π, and the weight is eval/pdf.

use super::microfacet::{Microfacet, cosine_hemisphere_pdf, reflect, square_to_cosine_hemisphere};
use super::{BsdfSample, fresnel};
use glam::{Vec2, Vec3};
use scene::Distribution;
use std::f32::consts::FRAC_1_PI;

/// Number of entries of the external transmittance table (Mitsuba's `MI_ROUGH_TRANSMITTANCE_RES`).
pub const TABLE_RES: usize = 64;

/// Everything a rough plastic needs besides its colours; built once per material.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RoughPlasticParams {
    /// Coating distribution (α clamped).
    pub microfacet: Microfacet,
    /// Relative IOR int/ext.
    pub eta: f32,
    /// Mitsuba's `nonlinear`.
    pub nonlinear: bool,
    /// w = s_mean / (d_mean + s_mean).
    pub specular_sampling_weight: f32,
    /// R_int (see the module docs).
    pub internal_reflectance: f32,
    /// T(μ_i), μ_i = i / (TABLE_RES − 1).
    pub external_transmittance: [f32; TABLE_RES],
}

impl RoughPlasticParams {
    /// Precompute the tables (≈ 1 M microfacet evaluations: call once per material, not per hit).
    /// `diffuse_mean` and `specular_mean` are the mean reflectances (over channels and texels).
    pub fn new(
        distribution: Distribution,
        alpha: f32,
        eta: f32,
        diffuse_mean: f32,
        specular_mean: f32,
        nonlinear: bool,
    ) -> Self {
        let microfacet = Microfacet::new(distribution, alpha);
        let eta = if eta.is_finite() && eta > 0.0 {
            eta
        } else {
            1.49
        };
        // The 64 directions are independent: evaluate them in parallel, then sum in a fixed
        // order so the result does not depend on scheduling.
        use rayon::prelude::*;
        let per_mu: Vec<(f32, f32)> = (0..TABLE_RES)
            .into_par_iter()
            .map(|i| {
                let mu = (i as f32 / (TABLE_RES - 1) as f32).max(1e-6);
                (
                    transmittance_albedo(&microfacet, mu, eta),
                    specular_albedo(&microfacet, mu, 1.0 / eta) * mu,
                )
            })
            .collect();
        let mut external_transmittance = [0.0f32; TABLE_RES];
        let mut internal = 0.0f64;
        for (t, (ext, int)) in external_transmittance.iter_mut().zip(&per_mu) {
            *t = *ext;
            internal += *int as f64;
        }
        let internal_reflectance = (2.0 * internal / TABLE_RES as f64) as f32;
        let sum = diffuse_mean + specular_mean;
        let specular_sampling_weight = if sum > 0.0 && sum.is_finite() {
            specular_mean / sum
        } else {
            0.5
        };
        Self {
            microfacet,
            eta,
            nonlinear,
            specular_sampling_weight,
            internal_reflectance,
            external_transmittance,
        }
    }

    /// T(μ) by linear interpolation in the table (μ clamped to [0, 1]).
    #[inline]
    pub fn transmittance(&self, mu: f32) -> f32 {
        let x = mu.clamp(0.0, 1.0) * (TABLE_RES - 1) as f32;
        let i = (x as usize).min(TABLE_RES - 2);
        let w1 = x - i as f32;
        (1.0 - w1) * self.external_transmittance[i] + w1 * self.external_transmittance[i + 1]
    }

    /// Probability of sampling the specular lobe given cos θo.
    #[inline]
    fn prob_specular(&self, cos_theta_o: f32) -> f32 {
        self.prob_specular_from_t(self.transmittance(cos_theta_o))
    }

    /// Probability of sampling the specular lobe given T(cos θo).
    #[inline]
    fn prob_specular_from_t(&self, t: f32) -> f32 {
        let ps = (1.0 - t) * self.specular_sampling_weight;
        let pd = t * (1.0 - self.specular_sampling_weight);
        if ps + pd > 0.0 { ps / (ps + pd) } else { 0.5 }
    }
}

/// R(μ, η): directional albedo of the dielectric coating's specular lobe (with Fresnel) at
/// cos θ = μ, by Gauss–Legendre quadrature of E_{m ~ D_wo}[F(wo·m) G1(wi, m)] (Mitsuba's
/// `eval_reflectance`).
pub fn specular_albedo(mf: &Microfacet, mu: f32, eta: f32) -> f32 {
    let n = if eta > 1.0 { 32 } else { 128 };
    let (nodes, weights) = gauss_legendre(n);
    let wo = Vec3::new((1.0 - mu * mu).max(0.0).sqrt(), 0.0, mu);
    let mut acc = 0.0f64;
    for (x, wx) in nodes.iter().zip(&weights) {
        for (y, wy) in nodes.iter().zip(&weights) {
            let u = Vec2::new((0.5 * x + 0.5) as f32, (0.5 * y + 0.5) as f32);
            let m = mf.sample_visible(wo, u);
            let wi = reflect(wo, m);
            if wi.z <= 0.0 || wo.z <= 0.0 {
                continue;
            }
            let v = mf.g1(wi, m) * fresnel::dielectric(wo.dot(m), eta);
            if v.is_finite() {
                acc += v as f64 * wx * wy;
            }
        }
    }
    (acc * 0.25) as f32
}

/// T(μ, η): fraction of light arriving at cos θ = μ that the rough interface refracts into the
/// layer, E_{m ~ D_wo}[(1 − F(wo·m, η)) G1(wt, m)] with wt the refracted direction (Mitsuba's
/// `eval_transmittance`, same quadrature as [`specular_albedo`]).
pub fn transmittance_albedo(mf: &Microfacet, mu: f32, eta: f32) -> f32 {
    let n = if eta > 1.0 { 32 } else { 128 };
    let (nodes, weights) = gauss_legendre(n);
    let wo = Vec3::new((1.0 - mu * mu).max(0.0).sqrt(), 0.0, mu);
    let mut acc = 0.0f64;
    for (x, wx) in nodes.iter().zip(&weights) {
        for (y, wy) in nodes.iter().zip(&weights) {
            let u = Vec2::new((0.5 * x + 0.5) as f32, (0.5 * y + 0.5) as f32);
            let m = mf.sample_visible(wo, u);
            let cos_i = wo.dot(m);
            let f = fresnel::dielectric(cos_i, eta);
            // Snell with the side-dependent relative IOR; TIR gives f = 1 (no contribution).
            let eta_ti = if cos_i >= 0.0 { 1.0 / eta } else { eta };
            let cos_t_sqr = 1.0 - (1.0 - cos_i * cos_i) * eta_ti * eta_ti;
            if cos_t_sqr <= 0.0 {
                continue;
            }
            let cos_t = -cos_t_sqr.sqrt().copysign(cos_i);
            let wt = m * (cos_i * eta_ti + cos_t) - wo * eta_ti;
            if wt.z * wo.z >= 0.0 {
                continue;
            }
            let v = mf.g1(wt, m) * (1.0 - f);
            if v.is_finite() {
                acc += v as f64 * wx * wy;
            }
        }
    }
    (acc * 0.25) as f32
}

/// Gauss–Legendre nodes and weights on [−1, 1] (Newton iteration on Pₙ).
pub fn gauss_legendre(n: usize) -> (Vec<f64>, Vec<f64>) {
    let mut nodes = vec![0.0; n];
    let mut weights = vec![0.0; n];
    for i in 0..n {
        let mut x = (std::f64::consts::PI * (i as f64 + 0.75) / (n as f64 + 0.5)).cos();
        let mut dp = 1.0;
        for _ in 0..100 {
            // Three-term recurrence for P_n(x) and its derivative.
            let (mut p0, mut p1) = (1.0f64, x);
            for k in 2..=n {
                let p2 = ((2 * k - 1) as f64 * x * p1 - (k - 1) as f64 * p0) / k as f64;
                p0 = p1;
                p1 = p2;
            }
            let pn = if n == 1 { x } else { p1 };
            let pn1 = if n == 1 { 1.0 } else { p0 };
            dp = n as f64 * (x * pn - pn1) / (x * x - 1.0);
            let dx = pn / dp;
            x -= dx;
            if dx.abs() < 1e-15 {
                break;
            }
        }
        nodes[i] = x;
        weights[i] = 2.0 / ((1.0 - x * x) * dp * dp);
    }
    (nodes, weights)
}

/// f·cos θi.
#[inline]
pub fn eval(p: &RoughPlasticParams, diffuse: Vec3, specular: Vec3, wo: Vec3, wi: Vec3) -> Vec3 {
    if wo.z <= 0.0 || wi.z <= 0.0 {
        return Vec3::ZERO;
    }
    let mf = &p.microfacet;
    let h = (wo + wi).normalize();
    let spec = fresnel::dielectric(wo.dot(h), p.eta) * mf.d(h) * mf.g(wo, wi, h) / (4.0 * wo.z);
    let denom = if p.nonlinear {
        Vec3::ONE - diffuse * p.internal_reflectance
    } else {
        Vec3::splat(1.0 - p.internal_reflectance)
    };
    let t = p.transmittance(wo.z) * p.transmittance(wi.z);
    let diff = diffuse / denom * (FRAC_1_PI / (p.eta * p.eta) * wi.z * t);
    let v = specular * spec + diff;
    if v.is_finite() { v } else { Vec3::ZERO }
}

/// Solid-angle pdf of [`sample`].
#[inline]
pub fn pdf(p: &RoughPlasticParams, wo: Vec3, wi: Vec3) -> f32 {
    if wo.z <= 0.0 || wi.z <= 0.0 {
        return 0.0;
    }
    let ps = p.prob_specular(wo.z);
    let mf = &p.microfacet;
    let h = (wo + wi).normalize();
    let spec = mf.d(h) * mf.g1(wo, h) / (4.0 * wo.z);
    let v = ps * spec + (1.0 - ps) * cosine_hemisphere_pdf(wi);
    if v.is_finite() { v } else { 0.0 }
}

/// `(eval, pdf)` in one pass (shares h, D and G1(wo, h)).
#[inline]
pub fn eval_pdf(
    p: &RoughPlasticParams,
    diffuse: Vec3,
    specular: Vec3,
    wo: Vec3,
    wi: Vec3,
) -> (Vec3, f32) {
    if wo.z <= 0.0 || wi.z <= 0.0 {
        return (Vec3::ZERO, 0.0);
    }
    let mf = &p.microfacet;
    let h = (wo + wi).normalize();
    let d = mf.d(h);
    let g1o = mf.g1(wo, h);
    let spec_pdf = d * g1o / (4.0 * wo.z);
    let spec = fresnel::dielectric(wo.dot(h), p.eta) * spec_pdf * mf.g1(wi, h);
    let denom = if p.nonlinear {
        Vec3::ONE - diffuse * p.internal_reflectance
    } else {
        Vec3::splat(1.0 - p.internal_reflectance)
    };
    let t_o = p.transmittance(wo.z);
    let diff = diffuse / denom * (FRAC_1_PI / (p.eta * p.eta) * wi.z * t_o * p.transmittance(wi.z));
    let v = specular * spec + diff;
    let ps = p.prob_specular_from_t(t_o);
    let pdf = ps * spec_pdf + (1.0 - ps) * cosine_hemisphere_pdf(wi);
    (
        if v.is_finite() { v } else { Vec3::ZERO },
        if pdf.is_finite() { pdf } else { 0.0 },
    )
}

/// Mixture sample (lobe chosen with `u_lobe`); `None` if the direction falls below the surface.
#[inline]
pub fn sample(
    p: &RoughPlasticParams,
    diffuse: Vec3,
    specular: Vec3,
    wo: Vec3,
    u_lobe: f32,
    u: Vec2,
) -> Option<BsdfSample> {
    if wo.z <= 0.0 {
        return None;
    }
    let wi = if u_lobe < p.prob_specular(wo.z) {
        reflect(wo, p.microfacet.sample_visible(wo, u)).normalize()
    } else {
        square_to_cosine_hemisphere(u)
    };
    let (value, pdf) = eval_pdf(p, diffuse, specular, wo, wi);
    if pdf.is_nan() || pdf <= 0.0 {
        return None;
    }
    let weight = value / pdf;
    Some(BsdfSample {
        wi,
        weight,
        pdf,
        delta: false,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gauss_legendre_is_exact_for_polynomials() {
        for n in [1usize, 2, 5, 32, 128] {
            let (x, w) = gauss_legendre(n);
            // Exact for degree ≤ 2n − 1: ∫_{-1}^{1} t^k dt = 2/(k+1) for even k, 0 for odd.
            for k in 0..(2 * n).min(12) {
                let v: f64 = x.iter().zip(&w).map(|(x, w)| w * x.powi(k as i32)).sum();
                let exact = if k % 2 == 0 {
                    2.0 / (k as f64 + 1.0)
                } else {
                    0.0
                };
                assert!((v - exact).abs() < 1e-12, "n={n} k={k}: {v} vs {exact}");
            }
        }
    }

    #[test]
    fn smooth_limit_transmittance_is_one_minus_fresnel() {
        // For a nearly smooth coating T(μ) → 1 − F(μ) and R(μ) → F(μ) (away from grazing).
        let mf = Microfacet::new(Distribution::Ggx, 1e-3);
        for mu in [0.3f32, 0.7, 1.0] {
            let f = fresnel::dielectric(mu, 1.5);
            assert!(
                (transmittance_albedo(&mf, mu, 1.5) - (1.0 - f)).abs() < 1e-3,
                "μ={mu}"
            );
            assert!((specular_albedo(&mf, mu, 1.5) - f).abs() < 1e-3, "μ={mu}");
        }
    }
}
