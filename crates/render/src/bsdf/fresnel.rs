//! Unpolarized Fresnel reflectance, with Mitsuba 3's formulas (`fresnel.h`).
//!
//! - [`dielectric`]: reflectance of a smooth interface between two dielectrics, relative IOR
//!   `eta = η_inside / η_outside`; `cos_theta_i` is signed (negative = arriving from inside, then
//!   the relative IOR is inverted). Total internal reflection gives 1; `eta == 1` gives 0.
//! - [`conductor`]: reflectance of a conductor with complex IOR `eta + i·k` (relative to the
//!   outside medium) for `cos_theta_i ∈ [0, 1]`, evaluated per RGB channel.

use glam::Vec3;

/// Fresnel reflectance of a dielectric interface (Mitsuba's `fresnel(cos_theta_i, eta)`,
/// reflectance only).
#[inline]
pub fn dielectric(cos_theta_i: f32, eta: f32) -> f32 {
    if eta == 1.0 {
        return 0.0;
    }
    let outside = cos_theta_i >= 0.0;
    // η_i/η_t as seen from the incident side.
    let (eta_it, eta_ti) = if outside {
        (eta, 1.0 / eta)
    } else {
        (1.0 / eta, eta)
    };
    let cos_i = cos_theta_i.abs();
    if cos_i == 0.0 {
        return 1.0;
    }
    // Snell: sin²θt = (1 − cos²θi) (η_i/η_t)².
    let cos_t_sqr = 1.0 - (1.0 - cos_i * cos_i) * eta_ti * eta_ti;
    if cos_t_sqr <= 0.0 {
        return 1.0; // total internal reflection
    }
    let cos_t = cos_t_sqr.sqrt();
    let a_s = (cos_i - eta_it * cos_t) / (cos_i + eta_it * cos_t);
    let a_p = (cos_t - eta_it * cos_i) / (cos_t + eta_it * cos_i);
    0.5 * (a_s * a_s + a_p * a_p)
}

/// Fresnel reflectance of a conductor with complex relative IOR `eta + i·k`, per channel
/// (Mitsuba's `fresnel_conductor`; exact for unpolarized light).
#[inline]
pub fn conductor(cos_theta_i: f32, eta: Vec3, k: Vec3) -> Vec3 {
    let c = cos_theta_i.clamp(0.0, 1.0);
    Vec3::new(
        conductor1(c, eta.x, k.x),
        conductor1(c, eta.y, k.y),
        conductor1(c, eta.z, k.z),
    )
}

#[inline]
fn conductor1(cos_i: f32, eta: f32, k: f32) -> f32 {
    let cos2 = cos_i * cos_i;
    let sin2 = 1.0 - cos2;
    let sin4 = sin2 * sin2;
    let t1 = eta * eta - k * k - sin2;
    let a2pb2 = (t1 * t1 + 4.0 * k * k * eta * eta).max(0.0).sqrt();
    let a = (0.5 * (a2pb2 + t1)).max(0.0).sqrt();
    let term1 = a2pb2 + cos2;
    let term2 = 2.0 * cos_i * a;
    let r_s = (term1 - term2) / (term1 + term2);
    let term3 = a2pb2 * cos2 + sin4;
    let term4 = term2 * sin2;
    let r_p = r_s * (term3 - term4) / (term3 + term4);
    let r = 0.5 * (r_s + r_p);
    if r.is_finite() { r } else { 1.0 }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dielectric_normal_incidence_and_tir() {
        let eta = 1.5f32;
        let r0 = ((eta - 1.0) / (eta + 1.0)).powi(2);
        assert!((dielectric(1.0, eta) - r0).abs() < 1e-6);
        assert!((dielectric(-1.0, eta) - r0).abs() < 1e-6);
        // Inside, beyond the critical angle (sin θc = 1/1.5): total internal reflection.
        assert_eq!(dielectric(-0.3, eta), 1.0);
        assert_eq!(dielectric(0.5, 1.0), 0.0);
        assert_eq!(dielectric(0.0, eta), 1.0);
        // Grazing from outside tends to 1.
        assert!(dielectric(1e-4, eta) > 0.99);
    }

    #[test]
    fn conductor_reduces_to_dielectric_for_zero_k() {
        for c in [0.05f32, 0.3, 0.7, 1.0] {
            let a = conductor(c, Vec3::splat(1.5), Vec3::ZERO).x;
            let b = dielectric(c, 1.5);
            assert!((a - b).abs() < 1e-5, "{c}: {a} vs {b}");
        }
        // Normal incidence: ((η−1)² + k²)/((η+1)² + k²).
        let (eta, k) = (0.2f32, 3.0f32);
        let r0 = ((eta - 1.0).powi(2) + k * k) / ((eta + 1.0).powi(2) + k * k);
        assert!((conductor(1.0, Vec3::splat(eta), Vec3::splat(k)).x - r0).abs() < 1e-5);
        assert!((conductor(0.0, Vec3::splat(eta), Vec3::splat(k)).x - 1.0).abs() < 1e-5);
    }
}
