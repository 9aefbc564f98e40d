//! BSDFs with Mitsuba 3's conventions, evaluated and sampled in the local shading frame
//! (`n = +z`, see [`crate::math::Frame`]).
//!
//! Contract shared by every lobe:
//! - `eval(wo, wi)` returns **f(wo, wi)·|cos θi|** (Mitsuba's convention), RGB.
//! - `pdf(wo, wi)` is the **solid-angle** density with which `sample` produces `wi` given `wo`
//!   (0 for delta lobes, whose pdf is a Dirac).
//! - `sample(wo, u_lobe, u)` returns `None` for a failed sample; otherwise `weight` is
//!   `eval/pdf` (for delta lobes the ratio of the Dirac parts), `pdf` as above.
//! - One-sided: zero unless `wo.z > 0` and `wi.z > 0`. `two_sided` mirrors `wo` (and so `wi`)
//!   into the upper hemisphere first.
//!
//! # Layout
//! `diffuse.rs`, `conductor.rs` (smooth), `rough_conductor.rs`, `rough_plastic.rs` (Mitsuba's
//! layered model), `microfacet.rs` (GGX/Beckmann D, G, VNDF sampling), `fresnel.rs`.

use glam::{Vec2, Vec3};

/// One sampled direction.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BsdfSample {
    /// Sampled incident direction, local frame, unit length.
    pub wi: Vec3,
    /// f·|cos θi| / pdf.
    pub weight: Vec3,
    /// Solid-angle pdf of `wi` (for a delta lobe: the probability of choosing that lobe).
    pub pdf: f32,
    /// Whether `wi` came from a delta lobe (no MIS with light sampling possible).
    pub delta: bool,
}

/// The closed set of BSDF kinds, with textures already evaluated at the hit point.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum BsdfKind {
    /// Lambertian with this albedo.
    Diffuse {
        /// Albedo.
        reflectance: Vec3,
    },
    /// Perfect mirror with conductor Fresnel.
    Conductor {
        /// Complex IOR real part.
        eta: Vec3,
        /// Complex IOR imaginary part.
        k: Vec3,
        /// Multiplier.
        specular_reflectance: Vec3,
    },
    /// Microfacet conductor.
    RoughConductor {
        /// Distribution.
        distribution: scene::Distribution,
        /// α (not squared).
        alpha: f32,
        /// Complex IOR real part.
        eta: Vec3,
        /// Complex IOR imaginary part.
        k: Vec3,
        /// Multiplier.
        specular_reflectance: Vec3,
    },
    /// Mitsuba's `roughplastic` layered model.
    RoughPlastic {
        /// Distribution.
        distribution: scene::Distribution,
        /// α (not squared).
        alpha: f32,
        /// Relative IOR.
        eta: f32,
        /// Diffuse base albedo.
        diffuse_reflectance: Vec3,
        /// Specular multiplier.
        specular_reflectance: Vec3,
        /// Mitsuba's `nonlinear`.
        nonlinear: bool,
    },
}

/// A BSDF at one shading point.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Bsdf {
    /// The lobe(s).
    pub kind: BsdfKind,
    /// Whether the back side reflects like the front.
    pub two_sided: bool,
}
