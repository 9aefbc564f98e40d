//! Light from infinity: a latitude–longitude environment map (Mitsuba 3 `envmap`) or a
//! uniform one (Mitsuba 3 `constant`).
//!
//! # User docs
//! `environment` in a scene:
//!
//! | type | field | type | default | meaning |
//! |---|---|---|---|---|
//! | `envmap` | `filename` | asset | — | lat-long EXR image, linear RGB radiance |
//! | | `scale` | float | 1 | radiance multiplier |
//! | | `transform` | transform | identity | map-to-world rotation (rotations only) |
//! | `constant` | `radiance` | RGB | — | radiance from every direction |
//!
//! ```json
//! "environment": { "type": "envmap", "filename": "museum.exr", "transform": [ { "rotate": { "axis": [0, 1, 0], "angle": 90 } } ] }
//! "environment": { "type": "constant", "radiance": [0.5, 0.5, 0.5] }
//! ```
//!
//! # Mapping and lookup (identical to Mitsuba 3.9 `envmap.cpp` in RGB mode)
//! A world direction `d` (pointing away from the scene) is taken to the map frame,
//! `v = to_world⁻¹ d`, then `u = atan2(v.x, −v.z) / 2π`, `v = acos(v.y) / π`. Texel `(x, y)` of a
//! `W × H` image sits at `u = (x + ½)/W` (periodic in `u`) and at **`θ = y π / (H − 1)`** — the
//! first and last rows lie exactly on the poles. Radiance is the **bilinear** interpolation of
//! the four surrounding texels in `(u, θ)`. Differences from Mitsuba: negative or non-finite
//! texels are read as 0, the exact south pole `v = 1` reads the last row (Mitsuba wraps it to
//! the first), and 1-row images are accepted (the row is used for both poles).
//!
//! # Importance sampling
//! Cell `(i, j)` spans `u ∈ [(i+½)/W, (i+3/2)/W]` and `θ ∈ [θ_j, θ_{j+1}]` — exactly the
//! patch over which the lookup interpolates texels `i, i+1` and rows `j, j+1`. Its weight is
//! the exact integral of the bilinear luminance over its solid angle,
//! `∫∫ L(φ, θ) sin θ dθ dφ` (the "luminance · sin θ" rule, integrated rather than point
//! sampled), so a cell has zero probability iff the radiance is zero all over it. A cell is
//! picked from a marginal (row band) × conditional (column) distribution, then a direction
//! is placed **uniformly in solid angle** inside it (uniform in `φ` and `cos θ`), so that
//!
//! `p_ω(d) = P(cell) / (Δφ · (cos θ_j − cos θ_{j+1}))`, constant per cell and bounded at the
//! poles. In lat-long terms this is `p_ω = p(u, v) / (2π² sin θ)` with the `(u, v)` density
//! `p(u, v) = 2π² sin θ · p_ω`; it differs from Mitsuba's bilinear `(u, v)` warp (whose
//! `p(u, v)` is piecewise bilinear), so per-sample pdfs differ from Mitsuba's while both are
//! unbiased and proportional to the same luminance · sin θ on average over each cell.
//!
//! The constant environment is sampled uniformly over the sphere, `p_ω = 1/(4π)`.

use std::f32::consts::PI;

use glam::{Mat3, Vec2, Vec3};

use super::area::uniform_sphere;
use super::distribution::{Distribution1D, cdf_pmf, cdf_sample};
use super::luminance;

/// A sampled env direction.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct EnvSample {
    /// World direction towards the environment.
    pub wi: Vec3,
    /// Radiance arriving along `−wi`.
    pub radiance: Vec3,
    /// Solid-angle pdf.
    pub pdf: f32,
}

/// The environment light.
#[derive(Clone, Debug, PartialEq)]
pub(crate) enum EnvLight {
    /// Lat-long map.
    Map(Box<EnvMap>),
    /// Uniform radiance.
    Constant {
        /// Radiance.
        radiance: Vec3,
    },
}

impl EnvLight {
    /// Builds the light from the scene's description.
    pub(crate) fn new(env: &scene::Environment) -> Self {
        match env {
            scene::Environment::Envmap { image, to_world } => {
                Self::Map(Box::new(EnvMap::new(image, *to_world)))
            }
            scene::Environment::Constant { radiance } => Self::Constant {
                radiance: *radiance,
            },
        }
    }

    /// Radiance arriving from world direction `d` (need not be unit).
    #[inline]
    pub(crate) fn eval(&self, d: Vec3) -> Vec3 {
        match self {
            Self::Map(map) => map.eval_world(d),
            Self::Constant { radiance } => *radiance,
        }
    }

    /// Samples a direction.
    #[inline]
    pub(crate) fn sample(&self, u: Vec2) -> Option<EnvSample> {
        match self {
            Self::Map(map) => map.sample(u),
            Self::Constant { radiance } => {
                let wi = uniform_sphere(u);
                wi.is_finite().then_some(EnvSample {
                    wi,
                    radiance: *radiance,
                    pdf: 1.0 / (4.0 * PI),
                })
            }
        }
    }

    /// Solid-angle pdf of [`Self::sample`] producing world direction `d`.
    #[inline]
    pub(crate) fn pdf(&self, d: Vec3) -> f32 {
        match self {
            Self::Map(map) => map.pdf_world(d),
            Self::Constant { .. } => 1.0 / (4.0 * PI),
        }
    }

    /// `∫ luminance(L(ω)) dω` over the sphere (for selection ∝ power).
    pub(crate) fn luminance_integral(&self) -> f64 {
        match self {
            Self::Map(map) => map.distribution.as_ref().map_or(0.0, |(m, _)| m.total()),
            Self::Constant { radiance } => {
                4.0 * std::f64::consts::PI * f64::from(luminance(*radiance))
            }
        }
    }
}

/// Where a direction falls in the lookup grid: column cell `i` (texels `i`, `i+1`), row
/// band `j` (rows `j`, `j+1`) and the fractions inside them.
#[derive(Clone, Copy, Debug)]
struct Coords {
    i: usize,
    fx: f32,
    j: usize,
    fy: f32,
}

/// A lat-long environment map with its sampling tables.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct EnvMap {
    /// Image width `W` (texels per row).
    width: usize,
    /// Image height as stored.
    height: usize,
    /// Number of texel rows of the lookup grid (`max(height, 2)`), at `θ = y π / (rows − 1)`.
    rows: usize,
    /// `W × height` texels, top row first, clamped to ≥ 0.
    texels: Vec<Vec3>,
    /// Map-to-world rotation.
    to_world: Mat3,
    /// World-to-map rotation.
    to_local: Mat3,
    /// `cos θ_y` of every grid row (`rows` entries, decreasing).
    cos_theta: Vec<f32>,
    /// `1 / (Δφ (cos θ_j − cos θ_{j+1}))` of every row band (`rows − 1` entries).
    inv_cell_solid_angle: Vec<f32>,
    /// Marginal over row bands, and the conditional CDFs over columns of every band packed
    /// in one table (`W + 1` entries per band, all 0 for a black band, which the marginal
    /// never picks); `None` for an all-black map.
    distribution: Option<(Distribution1D, Vec<f32>)>,
}

impl EnvMap {
    fn new(image: &scene::RgbImage, to_world: Mat3) -> Self {
        let (width, height) = (image.width as usize, image.height as usize);
        let valid = width > 0 && height > 0 && image.data.len() >= width * height;
        let texels: Vec<Vec3> = if valid {
            image.data[..width * height]
                .iter()
                .map(|c| {
                    Vec3::from_array(
                        c.to_array()
                            .map(|x| if x.is_finite() && x > 0.0 { x } else { 0.0 }),
                    )
                })
                .collect()
        } else {
            Vec::new()
        };
        let (width, height) = if valid { (width, height) } else { (0, 0) };
        let rows = height.max(2);
        let to_local = {
            let inv = to_world.inverse();
            if inv.is_finite() {
                inv
            } else {
                to_world.transpose()
            }
        };
        let dtheta = std::f64::consts::PI / (rows - 1) as f64;
        let cos_theta: Vec<f32> = (0..rows)
            .map(|y| (y as f64 * dtheta).cos() as f32)
            .collect();
        let dphi = if width > 0 {
            std::f64::consts::TAU / width as f64
        } else {
            0.0
        };
        let inv_cell_solid_angle = (0..rows - 1)
            .map(|j| {
                let (a, b) = (j as f64 * dtheta, (j + 1) as f64 * dtheta);
                (1.0 / (dphi * (a.cos() - b.cos()))) as f32
            })
            .collect();

        let mut map = Self {
            width,
            height,
            rows,
            texels,
            to_world,
            to_local,
            cos_theta,
            inv_cell_solid_angle,
            distribution: None,
        };
        if valid {
            map.distribution = map.build_distribution(dtheta, dphi);
        }
        map
    }

    /// Exact per-cell integrals of the bilinear luminance over solid angle.
    fn build_distribution(&self, dtheta: f64, dphi: f64) -> Option<(Distribution1D, Vec<f32>)> {
        let w = self.width;
        let lum: Vec<f64> = self
            .texels
            .iter()
            .map(|&c| f64::from(luminance(c)))
            .collect();
        let lum_at = |x: usize, y: usize| lum[y.min(self.height - 1) * w + x % w];
        let mut band_totals = Vec::with_capacity(self.rows - 1);
        let mut conditionals = Vec::with_capacity((self.rows - 1) * (w + 1));
        let mut cell = vec![0.0f64; w];
        for j in 0..self.rows - 1 {
            let (a, b) = (j as f64 * dtheta, (j + 1) as f64 * dtheta);
            // With t = (θ − θ_a)/Δθ: A1 = ∫ t sin θ dθ, A0 = ∫ (1 − t) sin θ dθ over the band.
            let a1 = -b.cos() + (b.sin() - a.sin()) / dtheta;
            let a0 = (a.cos() - b.cos()) - a1;
            for (i, c) in cell.iter_mut().enumerate() {
                let top = 0.5 * (lum_at(i, j) + lum_at(i + 1, j));
                let bottom = 0.5 * (lum_at(i, j + 1) + lum_at(i + 1, j + 1));
                *c = dphi * (top * a0.max(0.0) + bottom * a1.max(0.0));
            }
            band_totals.push(cell.iter().sum::<f64>());
            match Distribution1D::new(cell.iter().copied()) {
                Some(d) => conditionals.extend_from_slice(d.cdf()),
                None => conditionals.extend(std::iter::repeat_n(0.0, w + 1)),
            }
        }
        let marginal = Distribution1D::new(band_totals)?;
        Some((marginal, conditionals))
    }

    /// Texel `(x mod W, min(y, H−1))`.
    #[inline]
    fn texel(&self, x: usize, y: usize) -> Vec3 {
        let x = if x >= self.width { x - self.width } else { x };
        self.texels[y.min(self.height - 1) * self.width + x]
    }

    /// World direction → unit map-frame direction.
    #[inline]
    fn to_local_dir(&self, d: Vec3) -> Vec3 {
        (self.to_local * d).normalize_or_zero()
    }

    /// Radiance towards world direction `d`.
    #[inline]
    fn eval_world(&self, d: Vec3) -> Vec3 {
        if self.texels.is_empty() {
            return Vec3::ZERO;
        }
        self.eval_local(self.to_local_dir(d))
    }

    /// Radiance towards unit map-frame direction `v` (zero vector: black).
    #[inline]
    fn eval_local(&self, v: Vec3) -> Vec3 {
        match self.coords(v) {
            Some(c) => self.bilinear(&c),
            None => Vec3::ZERO,
        }
    }

    /// Lookup coordinates of a unit map-frame direction (one `atan2`, one `acos`).
    ///
    /// The row band `j` is corrected against the `cos θ` table that [`Self::sample`] uses,
    /// so that a sample's pdf and [`Self::pdf_world`] agree even when `acos` rounds across
    /// a band edge; the lookup is continuous there, so `fy` is simply clamped.
    #[inline]
    fn coords(&self, v: Vec3) -> Option<Coords> {
        if v == Vec3::ZERO || self.texels.is_empty() {
            return None;
        }
        // Column: texel x sits at u = (x + ½)/W (Mitsuba's half-texel shift), periodic.
        let w = self.width as f32;
        let u = v.x.atan2(-v.z) * (0.5 / PI);
        let mut x = u - 0.5 / w;
        x -= x.floor();
        x *= w;
        let i = (x as usize).min(self.width - 1);
        let fx = (x - i as f32).clamp(0.0, 1.0);
        // Row: row y sits at θ = y π / (rows − 1).
        let cos = v.y.clamp(-1.0, 1.0);
        let y = cos.acos() * (1.0 / PI) * (self.rows - 1) as f32;
        let mut j = (y as usize).min(self.rows - 2);
        if j > 0 && cos > self.cos_theta[j] {
            j -= 1;
        } else if j + 2 < self.rows && cos <= self.cos_theta[j + 1] {
            j += 1;
        }
        let fy = (y - j as f32).clamp(0.0, 1.0);
        Some(Coords { i, fx, j, fy })
    }

    /// Bilinear interpolation of texels `i, i+1` (periodic) × rows `j, j+1`.
    #[inline]
    fn bilinear(&self, c: &Coords) -> Vec3 {
        let top = self.texel(c.i, c.j) * (1.0 - c.fx) + self.texel(c.i + 1, c.j) * c.fx;
        let bottom = self.texel(c.i, c.j + 1) * (1.0 - c.fx) + self.texel(c.i + 1, c.j + 1) * c.fx;
        top * (1.0 - c.fy) + bottom * c.fy
    }

    /// Solid-angle pdf of the cell `(c.i, c.j)`.
    #[inline]
    fn cell_pdf(&self, c: &Coords) -> f32 {
        let Some((marginal, conditionals)) = self.distribution.as_ref() else {
            return 0.0;
        };
        let stride = self.width + 1;
        let Some(cond) = conditionals.get(c.j * stride..(c.j + 1) * stride) else {
            return 0.0;
        };
        marginal.pmf(c.j) * cdf_pmf(cond, c.i) * self.inv_cell_solid_angle[c.j]
    }

    fn sample(&self, u: Vec2) -> Option<EnvSample> {
        let (marginal, conditionals) = self.distribution.as_ref()?;
        let (j, _, uy) = marginal.sample(u.y);
        let stride = self.width + 1;
        let (i, _, ux) = cdf_sample(conditionals.get(j * stride..(j + 1) * stride)?, u.x);
        // Uniform in φ and cos θ inside the cell.
        let phi = 2.0 * PI * ((i as f32 + 0.5 + ux) / self.width as f32);
        let (c0, c1) = (self.cos_theta[j], self.cos_theta[j + 1]);
        let cos = (c0 + (c1 - c0) * uy).clamp(-1.0, 1.0);
        let sin = (1.0 - cos * cos).max(0.0).sqrt();
        let (sin_phi, cos_phi) = phi.sin_cos();
        let local = Vec3::new(sin_phi * sin, cos, -cos_phi * sin);
        let wi = (self.to_world * local).normalize_or_zero();
        if wi == Vec3::ZERO {
            return None;
        }
        // Radiance and pdf are evaluated exactly as `env_radiance` / `pdf_env` would for
        // `wi` (same rotation round trip), so MIS sees bit-identical values from both sides;
        // up to rounding at cell borders this is pmf_j · pmf_i / Ω_cell.
        let v = self.to_local_dir(wi);
        let pdf = self.pdf_local(v);
        if !(pdf.is_finite() && pdf > 0.0) {
            return None;
        }
        Some(EnvSample {
            wi,
            radiance: self.eval_local(v),
            pdf,
        })
    }

    fn pdf_world(&self, d: Vec3) -> f32 {
        self.pdf_local(self.to_local_dir(d))
    }

    /// Solid-angle pdf of unit map-frame direction `v`.
    #[inline]
    fn pdf_local(&self, v: Vec3) -> f32 {
        self.coords(v).map_or(0.0, |c| self.cell_pdf(&c))
    }
}
