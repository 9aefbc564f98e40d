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
//! Per-lobe parameter tables and formulas are in each lobe's module docs. Scene materials become
//! [`Bsdf`] values through a [`MaterialTable`] (built once per scene; per hit it only evaluates
//! textures, no allocation). [`Bsdf::eval_pdf`] returns both values in one call.
//!
//! # `twosided`
//! | parameter | type | meaning |
//! |---|---|---|
//! | `bsdf` | material | the material used on both sides |
//!
//! ```json
//! "walls": { "type": "twosided", "bsdf": { "type": "diffuse", "reflectance": [0.7, 0.7, 0.7] } }
//! ```
//! As Mitsuba's `twosided`: when `wo.z < 0` both directions are mirrored through the tangent
//! plane (z negated), the inner BSDF is evaluated, and a sampled `wi` is mirrored back. There is
//! still no transmission: `wo` and `wi` on opposite sides give zero.
//!
//! # Deviation from Mitsuba
//! Beckmann's Smith G1 is the exact expression (Mitsuba: a rational approximation, ≤ 0.35 % off,
//! which disagrees with its own visible-normal sampler). Everything else matches Mitsuba 3.9.1 to
//! float precision (`tests/bsdf_mitsuba.rs`).
//!
//! # Layout
//! `diffuse.rs`, `conductor.rs` (smooth), `rough_conductor.rs`, `rough_plastic.rs` (Mitsuba's
//! layered model), `microfacet.rs` (GGX/Beckmann D, G, VNDF sampling), `fresnel.rs`.

pub mod conductor;
pub mod diffuse;
pub mod fresnel;
pub mod microfacet;
pub mod rough_conductor;
pub mod rough_plastic;

use glam::{Vec2, Vec3, Vec4};
use microfacet::Microfacet;
pub use rough_plastic::RoughPlasticParams;

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
///
/// `RoughPlastic` carries its 64-entry transmittance table inline (≈ 300 bytes) so that a
/// `Bsdf` stays `Copy` and needs no allocation or lifetime; copying it per hit is cheap.
#[allow(clippy::large_enum_variant)]
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
    /// Mitsuba's `roughplastic` layered model. Distribution, α, η, `nonlinear` and the
    /// precomputed tables are in `params` (build them with [`RoughPlasticParams::new`], once
    /// per material: [`MaterialTable`] does).
    RoughPlastic {
        /// Distribution, α, η, `nonlinear`, sampling weight and transmittance tables.
        params: RoughPlasticParams,
        /// Diffuse base albedo.
        diffuse_reflectance: Vec3,
        /// Specular multiplier.
        specular_reflectance: Vec3,
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

impl Bsdf {
    /// A one-sided BSDF of this kind.
    #[inline]
    pub fn new(kind: BsdfKind) -> Self {
        Self {
            kind,
            two_sided: false,
        }
    }

    /// Apply the sidedness rule: a two-sided BSDF mirrors both directions through the tangent
    /// plane when `wo` is below it (as Mitsuba's `twosided` does). Returns the directions to
    /// hand to the lobe and whether they were flipped.
    #[inline]
    fn orient(&self, wo: Vec3, wi: Vec3) -> (Vec3, Vec3, bool) {
        if self.two_sided && wo.z < 0.0 {
            (
                Vec3::new(wo.x, wo.y, -wo.z),
                Vec3::new(wi.x, wi.y, -wi.z),
                true,
            )
        } else {
            (wo, wi, false)
        }
    }

    /// f(wo, wi)·|cos θi|, RGB. Zero if the sidedness rule excludes the pair.
    #[inline]
    pub fn eval(&self, wo: Vec3, wi: Vec3) -> Vec3 {
        let (wo, wi, _) = self.orient(wo, wi);
        match &self.kind {
            BsdfKind::Diffuse { reflectance } => diffuse::eval(*reflectance, wo, wi),
            BsdfKind::Conductor { .. } => Vec3::ZERO,
            BsdfKind::RoughConductor {
                distribution,
                alpha,
                eta,
                k,
                specular_reflectance,
            } => {
                let mf = Microfacet::new(*distribution, *alpha);
                rough_conductor::eval(&mf, *eta, *k, *specular_reflectance, wo, wi)
            }
            BsdfKind::RoughPlastic {
                params,
                diffuse_reflectance,
                specular_reflectance,
            } => rough_plastic::eval(params, *diffuse_reflectance, *specular_reflectance, wo, wi),
        }
    }

    /// Solid-angle density of `sample` producing `wi` (0 for delta lobes).
    #[inline]
    pub fn pdf(&self, wo: Vec3, wi: Vec3) -> f32 {
        let (wo, wi, _) = self.orient(wo, wi);
        match &self.kind {
            BsdfKind::Diffuse { .. } => diffuse::pdf(wo, wi),
            BsdfKind::Conductor { .. } => 0.0,
            BsdfKind::RoughConductor {
                distribution,
                alpha,
                ..
            } => rough_conductor::pdf(&Microfacet::new(*distribution, *alpha), wo, wi),
            BsdfKind::RoughPlastic { params, .. } => rough_plastic::pdf(params, wo, wi),
        }
    }

    /// `(eval(wo, wi), pdf(wo, wi))` in one call, sharing the microfacet terms (what an
    /// integrator wants for MIS after light sampling).
    ///
    /// As in [`Self::sample`], the diffuse lobe is evaluated inline and the others out of line.
    #[inline(always)]
    pub fn eval_pdf(&self, wo: Vec3, wi: Vec3) -> (Vec3, f32) {
        let (wo, wi, _) = self.orient(wo, wi);
        match &self.kind {
            BsdfKind::Diffuse { reflectance } => {
                (diffuse::eval(*reflectance, wo, wi), diffuse::pdf(wo, wi))
            }
            _ => self.eval_pdf_non_diffuse(wo, wi),
        }
    }

    /// [`Self::eval_pdf`] of the lobes other than diffuse (directions already oriented).
    #[inline(never)]
    fn eval_pdf_non_diffuse(&self, wo: Vec3, wi: Vec3) -> (Vec3, f32) {
        match &self.kind {
            BsdfKind::Diffuse { reflectance } => {
                (diffuse::eval(*reflectance, wo, wi), diffuse::pdf(wo, wi))
            }
            BsdfKind::Conductor { .. } => (Vec3::ZERO, 0.0),
            BsdfKind::RoughConductor {
                distribution,
                alpha,
                eta,
                k,
                specular_reflectance,
            } => {
                let mf = Microfacet::new(*distribution, *alpha);
                rough_conductor::eval_pdf(&mf, *eta, *k, *specular_reflectance, wo, wi)
            }
            BsdfKind::RoughPlastic {
                params,
                diffuse_reflectance,
                specular_reflectance,
            } => {
                rough_plastic::eval_pdf(params, *diffuse_reflectance, *specular_reflectance, wo, wi)
            }
        }
    }

    /// Sample `wi` given `wo`; `u_lobe` picks the lobe, `u` the direction within it (both uniform
    /// in [0, 1)). `None` for a failed sample (wrong side, direction below the surface, pdf 0).
    ///
    /// The diffuse lobe (the most common, and the cheapest) is sampled inline; the others in
    /// an out-of-line call, which keeps this function small enough to inline into the path
    /// loop (no call, no `Option<BsdfSample>` through memory for the diffuse case).
    #[inline(always)]
    pub fn sample(&self, wo: Vec3, u_lobe: f32, u: Vec2) -> Option<BsdfSample> {
        let (wo, _, flipped) = self.orient(wo, Vec3::Z);
        let mut s = match &self.kind {
            BsdfKind::Diffuse { reflectance } => diffuse::sample(*reflectance, wo, u),
            _ => self.sample_non_diffuse(wo, u_lobe, u),
        }?;
        if !valid_sample(s.weight, s.pdf) {
            return None;
        }
        if flipped {
            s.wi.z = -s.wi.z;
        }
        Some(s)
    }

    /// The lobe samples of [`Self::sample`] other than diffuse (`wo` already oriented).
    #[inline(never)]
    fn sample_non_diffuse(&self, wo: Vec3, u_lobe: f32, u: Vec2) -> Option<BsdfSample> {
        match &self.kind {
            BsdfKind::Diffuse { reflectance } => diffuse::sample(*reflectance, wo, u),
            BsdfKind::Conductor {
                eta,
                k,
                specular_reflectance,
            } => conductor::sample(*eta, *k, *specular_reflectance, wo),
            BsdfKind::RoughConductor {
                distribution,
                alpha,
                eta,
                k,
                specular_reflectance,
            } => {
                let mf = Microfacet::new(*distribution, *alpha);
                rough_conductor::sample(&mf, *eta, *k, *specular_reflectance, wo, u)
            }
            BsdfKind::RoughPlastic {
                params,
                diffuse_reflectance,
                specular_reflectance,
            } => rough_plastic::sample(
                params,
                *diffuse_reflectance,
                *specular_reflectance,
                wo,
                u_lobe,
                u,
            ),
        }
    }

    /// Whether a lobe is glossy (a microfacet lobe: rough conductor, rough plastic's
    /// coating): the light it reflects varies with direction at the scale of the lobe, and
    /// so across a surface at the scale of a highlight.
    #[inline]
    pub fn is_glossy(&self) -> bool {
        matches!(
            self.kind,
            BsdfKind::RoughConductor { .. } | BsdfKind::RoughPlastic { .. }
        )
    }

    /// Whether every lobe is a Dirac delta (no MIS with light sampling possible).
    #[inline]
    pub fn is_delta(&self) -> bool {
        matches!(self.kind, BsdfKind::Conductor { .. })
    }

    /// Albedo AOV for the denoiser: the diffuse reflectance (diffuse, rough plastic base) or the
    /// specular reflectance multiplier (conductors).
    #[inline]
    pub fn albedo(&self) -> Vec3 {
        match &self.kind {
            BsdfKind::Diffuse { reflectance } => *reflectance,
            BsdfKind::Conductor {
                specular_reflectance,
                ..
            }
            | BsdfKind::RoughConductor {
                specular_reflectance,
                ..
            } => *specular_reflectance,
            BsdfKind::RoughPlastic {
                diffuse_reflectance,
                ..
            } => *diffuse_reflectance,
        }
    }
}

/// Whether a sample's weight and pdf are finite and the pdf positive (what
/// [`Bsdf::sample`] requires), with one vector comparison: `|x| < ∞` is exactly
/// `x.is_finite()` (false for ±∞ and NaN).
#[inline(always)]
fn valid_sample(weight: Vec3, pdf: f32) -> bool {
    Vec4::new(weight.x, weight.y, weight.z, pdf)
        .abs()
        .cmplt(Vec4::splat(f32::INFINITY))
        .all()
        && pdf > 0.0
}

/// One material, with colours still unevaluated and per-material precomputations done.
#[derive(Clone, Debug)]
enum Entry {
    Diffuse {
        reflectance: scene::Color,
    },
    Conductor {
        eta: Vec3,
        k: Vec3,
        specular_reflectance: scene::Color,
    },
    RoughConductor {
        distribution: scene::Distribution,
        alpha: f32,
        eta: Vec3,
        k: Vec3,
        specular_reflectance: scene::Color,
    },
    RoughPlastic {
        params: Box<RoughPlasticParams>,
        diffuse_reflectance: scene::Color,
        specular_reflectance: scene::Color,
    },
}

/// The scene's materials, ready to produce a [`Bsdf`] per hit.
///
/// Built once per scene ([`MaterialTable::new`] precomputes, e.g., rough plastic tables, about
/// 1 M microfacet evaluations per rough plastic material); [`MaterialTable::bsdf`] then only
/// evaluates textures.
#[derive(Clone, Debug)]
pub struct MaterialTable {
    entries: Vec<(Entry, bool)>,
    textures: Vec<scene::Texture>,
}

impl MaterialTable {
    /// Prepare `materials` (indexed by [`scene::MaterialId`]) whose colours refer to `textures`.
    pub fn new(materials: &[scene::Material], textures: &[scene::Texture]) -> Self {
        // Rough plastic tables depend only on (distribution, α, η): share them between materials.
        let mut cache = Vec::new();
        let entries = materials
            .iter()
            .map(|m| Self::entry(m, textures, false, &mut cache))
            .collect();
        Self {
            entries,
            textures: textures.to_vec(),
        }
    }

    fn entry(
        m: &scene::Material,
        textures: &[scene::Texture],
        two_sided: bool,
        cache: &mut Vec<((scene::Distribution, u32, u32), RoughPlasticParams)>,
    ) -> (Entry, bool) {
        use scene::Material as M;
        let e = match m {
            M::Diffuse { reflectance } => Entry::Diffuse {
                reflectance: *reflectance,
            },
            M::Conductor {
                eta,
                k,
                specular_reflectance,
            } => Entry::Conductor {
                eta: *eta,
                k: *k,
                specular_reflectance: *specular_reflectance,
            },
            M::RoughConductor {
                distribution,
                alpha,
                eta,
                k,
                specular_reflectance,
            } => Entry::RoughConductor {
                distribution: *distribution,
                alpha: *alpha,
                eta: *eta,
                k: *k,
                specular_reflectance: *specular_reflectance,
            },
            M::RoughPlastic {
                distribution,
                alpha,
                eta,
                diffuse_reflectance,
                specular_reflectance,
                nonlinear,
            } => {
                let d_mean = crate::texture::mean_color(diffuse_reflectance, textures);
                let s_mean = crate::texture::mean_color(specular_reflectance, textures);
                let key = (*distribution, alpha.to_bits(), eta.to_bits());
                let mut params = match cache.iter().find(|(k, _)| *k == key) {
                    Some((_, p)) => *p,
                    None => {
                        let p = RoughPlasticParams::new(
                            *distribution,
                            *alpha,
                            *eta,
                            d_mean,
                            s_mean,
                            *nonlinear,
                        );
                        cache.push((key, p));
                        p
                    }
                };
                // Colour-dependent parts are per material.
                let sum = d_mean + s_mean;
                params.specular_sampling_weight = if sum > 0.0 && sum.is_finite() {
                    s_mean / sum
                } else {
                    0.5
                };
                params.nonlinear = *nonlinear;
                Entry::RoughPlastic {
                    params: Box::new(params),
                    diffuse_reflectance: *diffuse_reflectance,
                    specular_reflectance: *specular_reflectance,
                }
            }
            M::TwoSided(inner) => return Self::entry(inner, textures, true, cache),
        };
        (e, two_sided)
    }

    /// Number of materials.
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    /// Whether there are no materials.
    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// The BSDF of material `id` at texture coordinates `uv`. An out-of-range id (which a
    /// validated scene never contains) gives Mitsuba's default material, grey diffuse 0.5.
    ///
    /// A diffuse material with a constant colour (the common case) is built inline; every
    /// other one in an out-of-line call, which keeps this function small enough to inline
    /// into the path loop.
    #[inline(always)]
    pub fn bsdf(&self, id: scene::MaterialId, uv: Vec2) -> Bsdf {
        if let Some((
            Entry::Diffuse {
                reflectance: scene::Color::Rgb(reflectance),
            },
            two_sided,
        )) = self.entries.get(id as usize)
        {
            return Bsdf {
                kind: BsdfKind::Diffuse {
                    reflectance: *reflectance,
                },
                two_sided: *two_sided,
            };
        }
        self.bsdf_general(id, uv)
    }

    /// [`Self::bsdf`] for every material.
    #[inline(never)]
    fn bsdf_general(&self, id: scene::MaterialId, uv: Vec2) -> Bsdf {
        let Some((entry, two_sided)) = self.entries.get(id as usize) else {
            return Bsdf::new(BsdfKind::Diffuse {
                reflectance: Vec3::splat(0.5),
            });
        };
        let two_sided = *two_sided;
        let tex = |c: &scene::Color| crate::texture::eval_color(c, &self.textures, uv);
        // Each arm builds its `Bsdf` in place: with one shared tail, the compiler copied the
        // ~260-byte rough-plastic payload (uninitialised for the other kinds) on every call.
        let kind = match entry {
            Entry::Diffuse { reflectance } => BsdfKind::Diffuse {
                reflectance: tex(reflectance),
            },
            Entry::Conductor {
                eta,
                k,
                specular_reflectance,
            } => BsdfKind::Conductor {
                eta: *eta,
                k: *k,
                specular_reflectance: tex(specular_reflectance),
            },
            Entry::RoughConductor {
                distribution,
                alpha,
                eta,
                k,
                specular_reflectance,
            } => BsdfKind::RoughConductor {
                distribution: *distribution,
                alpha: *alpha,
                eta: *eta,
                k: *k,
                specular_reflectance: tex(specular_reflectance),
            },
            Entry::RoughPlastic {
                params,
                diffuse_reflectance,
                specular_reflectance,
            } => {
                return rough_plastic_bsdf(
                    params,
                    tex(diffuse_reflectance),
                    tex(specular_reflectance),
                    two_sided,
                );
            }
        };
        Bsdf { kind, two_sided }
    }
}

/// The rough-plastic arm of [`MaterialTable::bsdf`], out of line (see there).
#[inline(never)]
fn rough_plastic_bsdf(
    params: &RoughPlasticParams,
    diffuse_reflectance: Vec3,
    specular_reflectance: Vec3,
    two_sided: bool,
) -> Bsdf {
    Bsdf {
        kind: BsdfKind::RoughPlastic {
            params: *params,
            diffuse_reflectance,
            specular_reflectance,
        },
        two_sided,
    }
}
