//! Area lights: emitting triangle meshes and emitting analytic spheres (Mitsuba 3 `area`
//! emitter on a `mesh`/`obj`/`ply`/`rectangle`/`cube` or `sphere` shape).
//!
//! # User docs
//! Any shape becomes an area light by carrying an `emitter`:
//!
//! | field | type | default | meaning |
//! |---|---|---|---|
//! | `radiance` | RGB | — | radiance emitted from the **front side** only (uniform over the surface) |
//!
//! ```json
//! { "type": "rectangle", "emitter": { "radiance": [18.4, 11.0, 2.75] } }
//! { "type": "sphere", "center": [0, 1.9, 0], "radius": 0.1, "emitter": { "radiance": [10, 10, 10] } }
//! ```
//! The front side of a triangle is the side its counter-clockwise winding's normal
//! `(p1 − p0) × (p2 − p0)` points to; of a sphere the outside, or the inside with
//! `flip_normals`. Each emitting shape is **one** light for light selection, as in Mitsuba.
//!
//! # Sampling (all pdfs returned are solid-angle densities at the shading point `p`)
//! - **Mesh**: a triangle ∝ area, then a uniform point `y` on it; the area density is
//!   `1 / A_total` for every point of the mesh, converted to solid angle as
//!   `p_ω = ‖y − p‖² / (|cos θ_y| · A_total)` (Mitsuba `mesh.cpp` `sample_position` +
//!   `Shape::pdf_direction`). Back-side points are failed samples (`None`), as in Mitsuba's
//!   `area.cpp`, and have pdf 0.
//! - **Sphere, `p` outside**: a direction uniform in the cone subtended by the sphere,
//!   `p_ω = 1 / (2π (1 − cos θ_max))` with `sin θ_max = r / ‖c − p‖`; the light point is the
//!   first intersection (on the visible cap). `1 − cos θ_max` is evaluated as
//!   `sin² θ_max / (1 + cos θ_max)` so that tiny or distant spheres keep an accurate, finite pdf.
//! - **Sphere, `p` inside**: a uniform point on the whole sphere, `p_ω = ‖y − p‖² / (|cos θ_y| 4πr²)`.
//!
//! "Inside" uses Mitsuba's slightly shrunk (grown with `flip_normals`) radius
//! `r (1 ∓ 1500·2⁻²⁴)` so that a point on the sphere's own surface is "outside" a normal
//! sphere (it cannot see itself) and "inside" a flipped one (it sees the inner surface).
//!
//! Normals passed in by the integrator (`n_y`) are the **oriented geometric** normals of the
//! hit (flipped for `flip_normals`), not interpolated shading normals: the solid-angle
//! Jacobian is a property of the surface, and this keeps `pdf_area` exactly the density of
//! the samples (Mitsuba uses the shading normal for meshes with vertex normals; the two
//! agree for flat emitters such as every quad light in our scene suite).

use glam::{Vec2, Vec3};

use super::distribution::Distribution1D;
use crate::math::Frame;

/// `math::RayEpsilon<float>` of Mitsuba 3 (1500 × 2⁻²⁴), used for the inside/outside test.
const RAY_EPSILON: f32 = 1500.0 * f32::EPSILON / 2.0;

/// A point sampled on an area light, before the light's radiance is attached.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct AreaSample {
    /// Unit direction from the shading point to the light point.
    pub wi: Vec3,
    /// Distance to the light point.
    pub dist: f32,
    /// Oriented geometric normal at the light point (front side).
    pub n: Vec3,
    /// Solid-angle pdf at the shading point.
    pub pdf: f32,
}

/// One triangle of an emitting mesh, stored as origin + edges + oriented unit normal.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Tri {
    p0: Vec3,
    e1: Vec3,
    e2: Vec3,
    n: Vec3,
}

/// An emitting triangle mesh.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct MeshLight {
    /// Triangles with non-zero area (degenerate ones are dropped: they can never be hit).
    tris: Vec<Tri>,
    /// Triangle choice ∝ area; `None` when the total area is 0.
    distribution: Option<Distribution1D>,
    /// Total area.
    pub area: f32,
    /// Front-side radiance.
    pub radiance: Vec3,
}

impl MeshLight {
    /// Calls `f` with each (non-degenerate) triangle's corners.
    pub(crate) fn for_each_triangle(&self, mut f: impl FnMut([Vec3; 3])) {
        for t in &self.tris {
            f([t.p0, t.p0 + t.e1, t.p0 + t.e2]);
        }
    }

    /// Builds the light from a world-space mesh.
    pub(crate) fn new(mesh: &scene::Mesh, radiance: Vec3) -> Self {
        let mut tris = Vec::with_capacity(mesh.indices.len());
        let mut areas = Vec::with_capacity(mesh.indices.len());
        for idx in &mesh.indices {
            let [Some(&p0), Some(&p1), Some(&p2)] = idx.map(|i| mesh.positions.get(i as usize))
            else {
                continue; // invalid index: the scene contract excludes it, stay safe anyway
            };
            let (e1, e2) = (p1 - p0, p2 - p0);
            let cross = e1.cross(e2);
            let len = cross.length();
            if !(len.is_finite() && len > 0.0) {
                continue;
            }
            tris.push(Tri {
                p0,
                e1,
                e2,
                n: cross / len,
            });
            areas.push(0.5 * f64::from(len));
        }
        let distribution = Distribution1D::new(areas.iter().copied());
        let area = distribution.as_ref().map_or(0.0, |d| d.total() as f32);
        Self {
            tris,
            distribution,
            area,
            radiance,
        }
    }

    /// Samples a point as seen from `p` (`u.x` picks the triangle and is reused, `u` then
    /// places the point uniformly).
    #[inline]
    pub(crate) fn sample(&self, p: Vec3, u: Vec2) -> Option<AreaSample> {
        let dist = self.distribution.as_ref()?;
        let (i, _, ux) = dist.sample(u.x);
        let tri = self.tris.get(i)?;
        // Uniform point on the triangle: b = (1 − √u₀, u₁ √u₀) (Shirley–Chiu mapping).
        let su = ux.sqrt();
        let (b1, b2) = (1.0 - su, u.y * su);
        let y = tri.p0 + tri.e1 * b1 + tri.e2 * b2;
        let d = y - p;
        let dist2 = d.length_squared();
        let dist = dist2.sqrt();
        if !(dist > 0.0 && dist.is_finite()) {
            return None;
        }
        let wi = d / dist;
        let cos_y = -wi.dot(tri.n);
        if cos_y <= 0.0 {
            return None; // back side: emits nothing, Mitsuba reports pdf 0
        }
        let pdf = dist2 / (cos_y * self.area);
        // `pdf.is_finite() && pdf > 0.0` as two comparisons (NaN fails both; that form
        // compiled to a floating-point class test).
        ((pdf > 0.0) & (pdf < f32::INFINITY)).then_some(AreaSample {
            wi,
            dist,
            n: tri.n,
            pdf,
        })
    }

    /// Solid-angle pdf of [`Self::sample`] producing `y` (normal `n_y`) from `p`.
    #[inline]
    pub(crate) fn pdf(&self, p: Vec3, y: Vec3, n_y: Vec3) -> f32 {
        if self.distribution.is_none() {
            return 0.0;
        }
        solid_angle_pdf(p, y, n_y, self.area)
    }
}

/// `‖y − p‖² / (cos θ_y · area)` for a front-facing `y`, else 0.
#[inline]
fn solid_angle_pdf(p: Vec3, y: Vec3, n_y: Vec3, area: f32) -> f32 {
    let d = p - y;
    let dist2 = d.length_squared();
    let dist = dist2.sqrt();
    if dist.is_nan() || dist <= 0.0 {
        return 0.0;
    }
    let cos_y = n_y.dot(d) / dist;
    if cos_y <= 0.0 {
        return 0.0;
    }
    let pdf = dist2 / (cos_y * area);
    if pdf.is_finite() { pdf } else { 0.0 }
}

/// An emitting analytic sphere.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct SphereLight {
    /// Centre.
    pub center: Vec3,
    /// Radius.
    pub radius: f32,
    /// Front side = inside.
    pub flip_normals: bool,
    /// Front-side radiance.
    pub radiance: Vec3,
}

/// The cone subtended by a sphere seen from outside.
struct Cone {
    /// Unit axis from `p` towards the centre.
    axis: Vec3,
    /// `sin² θ_max`.
    sin2_max: f32,
    /// `1 − cos θ_max`, computed without cancellation.
    one_minus_cos_max: f32,
}

impl SphereLight {
    /// Surface area `4πr²`.
    #[inline]
    pub(crate) fn area(&self) -> f32 {
        4.0 * std::f32::consts::PI * self.radius * self.radius
    }

    /// The cone seen from `p`, or `None` when `p` is inside (Mitsuba's adjusted radius).
    #[inline]
    fn cone(&self, p: Vec3) -> Option<Cone> {
        let dc = self.center - p;
        let dc2 = dc.length_squared();
        let adj = if self.flip_normals {
            1.0 + RAY_EPSILON
        } else {
            1.0 - RAY_EPSILON
        };
        let r_adj = self.radius * adj;
        if dc2.is_nan() || dc2 <= r_adj * r_adj {
            return None;
        }
        let sin2_max = ((self.radius * self.radius) / dc2).min(1.0);
        let cos_max = (1.0 - sin2_max).max(0.0).sqrt();
        Some(Cone {
            axis: dc / dc2.sqrt(),
            sin2_max,
            one_minus_cos_max: sin2_max / (1.0 + cos_max),
        })
    }

    /// Samples a point as seen from `p`.
    #[inline]
    pub(crate) fn sample(&self, p: Vec3, u: Vec2) -> Option<AreaSample> {
        let s = match self.cone(p) {
            Some(cone) => self.sample_cone(&cone, p, u)?,
            None => self.sample_inside(p, u)?,
        };
        (s.pdf.is_finite() && s.pdf > 0.0 && s.dist > 0.0 && s.dist.is_finite() && s.wi.is_finite())
            .then_some(s)
    }

    /// Uniform direction in the cone, then the first intersection with the sphere.
    fn sample_cone(&self, cone: &Cone, p: Vec3, u: Vec2) -> Option<AreaSample> {
        // 1 − cos θ uniform in [0, 1 − cos θ_max]: uniform over the cone's solid angle.
        let omc = u.x * cone.one_minus_cos_max;
        let cos_theta = 1.0 - omc;
        let sin2_theta = (omc * (2.0 - omc)).max(0.0);
        let sin_theta = sin2_theta.sqrt();
        let phi = 2.0 * std::f32::consts::PI * u.y;
        let (sin_phi, cos_phi) = phi.sin_cos();
        let frame = Frame::from_normal(cone.axis);
        let e_phi = frame.s * cos_phi + frame.t * sin_phi;
        let wi = cone.axis * cos_theta + e_phi * sin_theta;
        // Angle α at the centre between −axis and the hit point (visible-cap formula:
        // cos α = sin²θ / sin θ_max + cos θ · √(1 − sin²θ / sin²θ_max)).
        let sin_max = cone.sin2_max.sqrt();
        let ratio = if cone.sin2_max > 0.0 {
            (sin2_theta / cone.sin2_max).min(1.0)
        } else {
            0.0
        };
        let cos_alpha = (sin2_theta / sin_max.max(f32::MIN_POSITIVE)
            + cos_theta * (1.0 - ratio).sqrt())
        .min(1.0);
        let sin_alpha = (1.0 - cos_alpha * cos_alpha).max(0.0).sqrt();
        let n_out = -cone.axis * cos_alpha + e_phi * sin_alpha;
        let y = self.center + n_out * self.radius;
        let dist = (y - p).length();
        let n = if self.flip_normals { -n_out } else { n_out };
        if n.dot(wi) >= 0.0 {
            return None; // seen from its back side (flipped sphere seen from outside)
        }
        let pdf = 1.0 / (2.0 * std::f32::consts::PI * cone.one_minus_cos_max);
        Some(AreaSample { wi, dist, n, pdf })
    }

    /// Uniform point on the whole sphere.
    fn sample_inside(&self, p: Vec3, u: Vec2) -> Option<AreaSample> {
        let n_out = uniform_sphere(u);
        let y = self.center + n_out * self.radius;
        let n = if self.flip_normals { -n_out } else { n_out };
        let d = y - p;
        let dist2 = d.length_squared();
        let dist = dist2.sqrt();
        if dist.is_nan() || dist <= 0.0 {
            return None;
        }
        let wi = d / dist;
        let cos_y = -n.dot(wi);
        if cos_y <= 0.0 {
            return None;
        }
        Some(AreaSample {
            wi,
            dist,
            n,
            pdf: dist2 / (cos_y * self.area()),
        })
    }

    /// Solid-angle pdf of [`Self::sample`] producing `y` (oriented normal `n_y`) from `p`.
    #[inline]
    pub(crate) fn pdf(&self, p: Vec3, y: Vec3, n_y: Vec3) -> f32 {
        match self.cone(p) {
            Some(cone) => {
                // Only the visible cap is ever produced. Any point a ray from an outside `p`
                // reaches first lies on it, so `y` and `n_y` are not re-checked: for a small,
                // distant sphere their f32 rounding is a sizeable fraction of the radius and a
                // facing test would reject valid rim points. A flipped sphere shows its back.
                if self.flip_normals {
                    return 0.0;
                }
                let pdf = 1.0 / (2.0 * std::f32::consts::PI * cone.one_minus_cos_max);
                if pdf.is_finite() { pdf } else { 0.0 }
            }
            None => solid_angle_pdf(p, y, n_y, self.area()),
        }
    }
}

/// Uniform direction on the unit sphere; pdf `1/(4π)`.
#[inline]
pub(crate) fn uniform_sphere(u: Vec2) -> Vec3 {
    let z = 1.0 - 2.0 * u.x;
    let r = (1.0 - z * z).max(0.0).sqrt();
    let (s, c) = (2.0 * std::f32::consts::PI * u.y).sin_cos();
    Vec3::new(r * c, r * s, z)
}
