//! Ray–scene intersection: one BVH over every triangle of every mesh plus the analytic
//! spheres. Scenes of up to [`WIDE_MAX_PRIMS`] primitives use our own 8-wide BVH with SoA
//! triangle packets (`accel/wide.rs`); larger ones obvhs' CWBVH (8-wide compressed BVH), with the
//! triangles and spheres intersected in its traversal closure. Both use the same triangle test
//! and return the same hits ([`AccelKind`] forces one for tests and benchmarks).
//!
//! Contract:
//! - [`Accel::intersect`] returns the closest [`Hit`] with `t ∈ (0, ray.t_max)`; the ray
//!   direction must be unit length (then `t` is a distance).
//! - [`Accel::occluded`] answers any-hit queries for shadow rays.
//! - obvhs's own `Triangle::compute_barycentric` is not used (it is wrong in 0.4): the closure
//!   computes `(t, b1, b2)` itself with the **watertight** test of Woop, Benthin & Wald 2013
//!   (shear into ray space, edge functions with an f64 fallback on exact zeros), so rays cannot
//!   slip between triangles sharing an edge or vertex (Möller–Trumbore leaked ~5 rays per
//!   million through a closed mesh in `benches/bvh.rs`).
//! - Surface attributes follow Mitsuba 3: `ng` is the face normal from the winding
//!   (`normalize((p1 − p0) × (p2 − p0))`) — or the sphere's outward normal, inward with
//!   `flip_normals` — and `ns` the interpolated vertex normal (`ng` without vertex normals, or
//!   when every vertex normal of the mesh equals its face normal up to rounding).
//!   Like Mitsuba, `ns` is **not** flipped towards `ng` when they disagree; the shading
//!   frame is built on `ns` and one-sided BSDFs see the back side as black.
//! - UVs: interpolated mesh UVs, or the barycentrics `(b1, b2)` when a mesh has none
//!   (Mitsuba's default); spheres use `u = φ/2π`, `v = θ/π` in the sphere's own frame.
//! - Ray offsetting as Mitsuba's `Interaction::offset_p`: the origin moves along `ng` by
//!   `(1 + max|p|)·ε_ray`, `ε_ray = 1500·2⁻²⁴`, on the side the new ray leaves to; shadow rays
//!   end `ε_shadow = 10·ε_ray` (relative) short of their target. Scale-aware, so the Cornell box
//!   in millimetres works as well as a unit scene.
//! - Limitation inherited from obvhs 0.4: its node test clamps the entry distance to an
//!   absolute `1e-4`, so geometry lying entirely within `1e-4` scene units of a ray origin is
//!   not found (irrelevant at the offsets above for scenes in metres or millimetres).

use std::f32::consts::PI;
use std::time::Duration;

use glam::{Mat3, Vec2, Vec3, Vec3A};
use obvhs::{BvhBuildParams, aabb::Aabb, cwbvh::CwBvh, cwbvh::builder::build_cwbvh, ray::RayHit};
use scene::MaterialId;

use crate::math::Ray;

mod wide;

pub use wide::WIDE_MAX_PRIMS;
use wide::WideBvh;

/// Which BVH an [`Accel`] uses.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum AccelKind {
    /// [`AccelKind::Wide`] up to [`WIDE_MAX_PRIMS`] primitives, else [`AccelKind::Cwbvh`].
    #[default]
    Auto,
    /// Our 8-wide BVH with SoA triangle packets (fast for small scenes); the CWBVH is built
    /// instead if the tree would need a deeper traversal stack than it has.
    Wide,
    /// obvhs' compressed wide BVH (fast to build and traverse for large meshes).
    Cwbvh,
}

/// The BVH of an [`Accel`].
///
/// `repr(u8)`: an explicit tag byte, tested once per ray by one compare (the niche in
/// `WideBvh`'s vectors took ~10 instructions to decode).
#[derive(Clone, Debug)]
#[repr(u8)]
enum Bvh {
    /// No geometry.
    Empty,
    /// [`WideBvh`] over `Accel::prims` in scene order.
    Wide(WideBvh),
    /// obvhs CWBVH; `Accel::prims` is in BVH order.
    Cwbvh(CwBvh),
}

/// Mitsuba's `RayEpsilon` for f32: 1500 · 2⁻²⁴.
pub const RAY_EPSILON: f32 = 1500.0 * f32::EPSILON * 0.5;
/// Mitsuba's `ShadowEpsilon`: shadow rays stop this fraction short of their target.
pub const SHADOW_EPSILON: f32 = RAY_EPSILON * 10.0;

/// Which primitive a hit is on.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ShapeRef {
    /// Triangle `triangle` of `scene.meshes[mesh]`.
    Mesh {
        /// Mesh index.
        mesh: u32,
        /// Triangle index within the mesh.
        triangle: u32,
    },
    /// `scene.spheres[i]`.
    Sphere(u32),
}

/// A ray–surface intersection.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    /// Ray parameter (distance for a unit direction).
    pub t: f32,
    /// World-space position.
    pub p: Vec3,
    /// Unit geometric normal (winding / sphere orientation; see the module docs).
    pub ng: Vec3,
    /// Unit shading normal (interpolated vertex normal, or `ng`).
    pub ns: Vec3,
    /// Texture coordinates.
    pub uv: Vec2,
    /// The primitive.
    pub shape: ShapeRef,
    /// Material of the shape.
    pub material: MaterialId,
    /// Light index ([`crate::light::Lights`]) if the shape emits.
    pub light: Option<u32>,
}

impl Hit {
    /// The ray origin for leaving the surface in direction `d` (Mitsuba's `offset_p`).
    #[inline]
    pub fn offset_origin(&self, d: Vec3) -> Vec3 {
        let mag = (1.0 + self.p.abs().max_element()) * RAY_EPSILON;
        let mag = if self.ng.dot(d) >= 0.0 { mag } else { -mag };
        self.p + self.ng * mag
    }

    /// An unbounded ray leaving the surface along unit direction `d`.
    #[inline]
    pub fn spawn_ray(&self, d: Vec3) -> Ray {
        Ray {
            o: self.offset_origin(d),
            d,
            t_max: f32::INFINITY,
        }
    }

    /// A shadow ray towards the point `target`: unit direction and `t_max` stopping
    /// [`SHADOW_EPSILON`] short of the target (Mitsuba's `spawn_ray_to`).
    #[inline]
    pub fn spawn_ray_to(&self, target: Vec3) -> Ray {
        let o = self.offset_origin(target - self.p);
        let d = target - o;
        let dist = d.length();
        Ray {
            o,
            d: d / dist,
            t_max: dist * (1.0 - SHADOW_EPSILON),
        }
    }
}

/// Tag bit of [`Prim::shape`] marking a sphere.
const SPHERE_BIT: u32 = 1 << 31;

/// One BVH primitive, stored in BVH order so that the closure indexes it directly.
/// Triangles keep their exact vertices (watertightness needs shared vertices bit-identical);
/// spheres keep centre and radius.
#[derive(Clone, Copy, Debug)]
struct Prim {
    /// Triangle `p0` or sphere centre.
    a: Vec3,
    /// Triangle `p1`, or `(radius, 0, 0)` for a sphere.
    b: Vec3,
    /// Triangle `p2`.
    c: Vec3,
    /// Mesh index, or `SPHERE_BIT | sphere index`.
    shape: u32,
    /// Triangle index within the mesh (0 for spheres).
    index: u32,
    /// Unit face normal `normalize((b − a) × (c − a))` of a triangle (zero for spheres).
    ng: Vec3,
}

/// Per-mesh data needed to finish a hit.
#[derive(Clone, Debug)]
struct MeshGeom {
    /// Whether the mesh has vertex normals (then in [`Accel::prim_normals`]).
    has_normals: bool,
    /// Whether the mesh has UVs (then in [`Accel::prim_uvs`]).
    has_uvs: bool,
    material: MaterialId,
    light: Option<u32>,
}

/// Per-sphere data needed to finish a hit.
#[derive(Clone, Copy, Debug)]
struct SphereGeom {
    center: Vec3,
    radius: f32,
    flip_normals: bool,
    /// Inverse rotation (world → sphere frame) for the UV parametrisation.
    to_local: Mat3,
    material: MaterialId,
    light: Option<u32>,
}

/// The acceleration structure of a scene.
#[derive(Clone, Debug)]
pub struct Accel {
    bvh: Bvh,
    prims: Vec<Prim>,
    /// Vertex normals per primitive of `prims` (empty when no mesh has normals).
    prim_normals: Vec<[Vec3; 3]>,
    /// Vertex UVs per primitive of `prims` (empty when no mesh has UVs).
    prim_uvs: Vec<[Vec2; 3]>,
    meshes: Vec<MeshGeom>,
    spheres: Vec<SphereGeom>,
    bounds_min: Vec3,
    bounds_max: Vec3,
}

/// Intermediate result of the traversal closure.
#[derive(Clone, Copy)]
struct RawHit {
    prim: u32,
    u: f32,
    v: f32,
}

impl Accel {
    /// Builds the BVH over all meshes and spheres of `scene`. `mesh_lights[i]` /
    /// `sphere_lights[i]` give the light index of emitting shapes (may be shorter than the
    /// shape lists: missing entries mean "not an emitter").
    pub fn new(
        scene: &scene::Scene,
        mesh_lights: &[Option<u32>],
        sphere_lights: &[Option<u32>],
    ) -> Self {
        Self::with_kind(scene, mesh_lights, sphere_lights, AccelKind::Auto)
    }

    /// [`Accel::new`] with an explicit choice of BVH.
    pub fn with_kind(
        scene: &scene::Scene,
        mesh_lights: &[Option<u32>],
        sphere_lights: &[Option<u32>],
        kind: AccelKind,
    ) -> Self {
        Self::build(scene, mesh_lights, sphere_lights, kind, false)
    }

    /// The BVH over the emitting shapes of `scene` alone (arguments as [`Accel::new`]): the
    /// emitter a ray reaches first, whatever lies in front of it. Its hits carry the shape,
    /// material and light of the full structure's; a caller that needs the first surface
    /// tests the segment to the hit against that structure ([`Accel::occluded`]).
    pub fn emitters(
        scene: &scene::Scene,
        mesh_lights: &[Option<u32>],
        sphere_lights: &[Option<u32>],
    ) -> Self {
        Self::build(scene, mesh_lights, sphere_lights, AccelKind::Auto, true)
    }

    fn build(
        scene: &scene::Scene,
        mesh_lights: &[Option<u32>],
        sphere_lights: &[Option<u32>],
        kind: AccelKind,
        emitters_only: bool,
    ) -> Self {
        let emits = |lights: &[Option<u32>], i: usize| lights.get(i).copied().flatten().is_some();
        let mut prims = Vec::new();
        let mut aabbs = Vec::new();
        for (mi, mesh) in scene.meshes.iter().enumerate() {
            if emitters_only && !emits(mesh_lights, mi) {
                continue;
            }
            for (ti, tri) in mesh.indices.iter().enumerate() {
                let [p0, p1, p2] = tri.map(|i| mesh.positions[i as usize]);
                prims.push(Prim {
                    a: p0,
                    b: p1,
                    c: p2,
                    shape: mi as u32,
                    index: ti as u32,
                    ng: (p1 - p0).cross(p2 - p0).normalize(),
                });
                aabbs.push(Aabb::new(
                    Vec3A::from(p0.min(p1).min(p2)),
                    Vec3A::from(p0.max(p1).max(p2)),
                ));
            }
        }
        for (si, s) in scene.spheres.iter().enumerate() {
            if emitters_only && !emits(sphere_lights, si) {
                continue;
            }
            prims.push(Prim {
                a: s.center,
                b: Vec3::new(s.radius, 0.0, 0.0),
                c: Vec3::ZERO,
                shape: SPHERE_BIT | si as u32,
                index: 0,
                ng: Vec3::ZERO,
            });
            let r = Vec3::splat(s.radius);
            aabbs.push(Aabb::new(
                Vec3A::from(s.center - r),
                Vec3A::from(s.center + r),
            ));
        }
        let (mut bounds_min, mut bounds_max) =
            (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
        for b in &aabbs {
            bounds_min = bounds_min.min(b.min.into());
            bounds_max = bounds_max.max(b.max.into());
        }
        let wide = match kind {
            AccelKind::Auto => prims.len() <= WIDE_MAX_PRIMS,
            AccelKind::Wide => true,
            AccelKind::Cwbvh => false,
        };
        let (bvh, prims) = if aabbs.is_empty() {
            (Bvh::Empty, prims)
        } else if wide {
            match WideBvh::new(&prims) {
                Some(w) => (Bvh::Wide(w), prims),
                None => (Bvh::Empty, prims),
            }
        } else {
            let bvh = build_cwbvh(
                &aabbs,
                BvhBuildParams::medium_build(),
                &mut Duration::default(),
            );
            // Reorder into BVH order so the closure needs no indirection.
            let ordered = bvh
                .primitive_indices
                .iter()
                .map(|&i| prims[i as usize])
                .collect();
            (Bvh::Cwbvh(bvh), ordered)
        };
        let meshes = scene
            .meshes
            .iter()
            .enumerate()
            .map(|(i, m)| MeshGeom {
                has_normals: m.normals.is_some() && !normals_are_flat(m),
                has_uvs: m.uvs.is_some(),
                material: m.material,
                light: mesh_lights.get(i).copied().flatten(),
            })
            .collect();
        // Per-primitive vertex attributes in primitive order: one load in `finish_hit`
        // instead of mesh → index triple → attribute (empty when no mesh has any).
        let corners = |p: &Prim| -> Option<(&scene::Mesh, [usize; 3])> {
            let m = (p.shape & SPHERE_BIT == 0).then(|| &scene.meshes[p.shape as usize])?;
            let idx = m.indices.get(p.index as usize)?;
            Some((m, idx.map(|i| i as usize)))
        };
        let prim_normals = if scene.meshes.iter().any(|m| m.normals.is_some()) {
            prims
                .iter()
                .map(|p| match corners(p) {
                    Some((m, idx)) => m
                        .normals
                        .as_ref()
                        .map_or([Vec3::ZERO; 3], |n| idx.map(|i| n[i])),
                    None => [Vec3::ZERO; 3],
                })
                .collect()
        } else {
            Vec::new()
        };
        let prim_uvs = if scene.meshes.iter().any(|m| m.uvs.is_some()) {
            prims
                .iter()
                .map(|p| match corners(p) {
                    Some((m, idx)) => m
                        .uvs
                        .as_ref()
                        .map_or([Vec2::ZERO; 3], |uv| idx.map(|i| uv[i])),
                    None => [Vec2::ZERO; 3],
                })
                .collect()
        } else {
            Vec::new()
        };
        let spheres = scene
            .spheres
            .iter()
            .enumerate()
            .map(|(i, s)| SphereGeom {
                center: s.center,
                radius: s.radius,
                flip_normals: s.flip_normals,
                to_local: s.frame.transpose(),
                material: s.material,
                light: sphere_lights.get(i).copied().flatten(),
            })
            .collect();
        Self {
            bvh,
            prims,
            prim_normals,
            prim_uvs,
            meshes,
            spheres,
            bounds_min,
            bounds_max,
        }
    }

    /// Which BVH was built ([`AccelKind::Wide`] or [`AccelKind::Cwbvh`]; `Auto` when empty).
    pub fn kind(&self) -> AccelKind {
        match self.bvh {
            Bvh::Empty => AccelKind::Auto,
            Bvh::Wide(_) => AccelKind::Wide,
            Bvh::Cwbvh(_) => AccelKind::Cwbvh,
        }
    }

    /// Number of BVH primitives (triangles + spheres).
    pub fn primitive_count(&self) -> usize {
        self.prims.len()
    }

    /// World-space bounds `(min, max)` of all geometry (`+∞, −∞` when empty).
    pub fn bounds(&self) -> (Vec3, Vec3) {
        (self.bounds_min, self.bounds_max)
    }

    /// Closest hit along `ray` (unit direction) with `t ∈ (0, ray.t_max)`.
    #[inline]
    pub fn intersect(&self, ray: &Ray) -> Option<Hit> {
        let bvh = match &self.bvh {
            Bvh::Empty => return None,
            Bvh::Wide(w) => {
                let shear = RayShear::new(ray.o, ray.d + Vec3::ZERO);
                let (prim, t, u, v) = w.intersect(&self.prims, &shear, ray.t_max)?;
                return Some(self.finish_hit(ray, t, RawHit { prim, u, v }));
            }
            Bvh::Cwbvh(b) => b,
        };
        let r = obvhs_ray(ray.o, ray.d, ray.t_max);
        let mut hit = RayHit::none();
        let mut raw = RawHit {
            prim: 0,
            u: 0.0,
            v: 0.0,
        };
        let shear = RayShear::new(ray.o, ray.d + Vec3::ZERO);
        let found = bvh.ray_traverse(r, &mut hit, |r, id| {
            let prim = &self.prims[id];
            match intersect_prim(prim, &shear, r.tmax) {
                Some((t, u, v)) if t < r.tmax => {
                    raw = RawHit {
                        prim: id as u32,
                        u,
                        v,
                    };
                    t
                }
                _ => f32::INFINITY,
            }
        });
        if !found {
            return None;
        }
        Some(self.finish_hit(ray, hit.t, raw))
    }

    /// Whether anything blocks the segment `o + t·d`, `t ∈ (0, t_max)` (any hit; `d` unit).
    #[inline]
    pub fn occluded(&self, o: Vec3, d: Vec3, t_max: f32) -> bool {
        let bvh = match &self.bvh {
            Bvh::Empty => return false,
            Bvh::Wide(w) => {
                return w.occluded(&self.prims, &RayShear::new(o, d + Vec3::ZERO), t_max);
            }
            Bvh::Cwbvh(b) => b,
        };
        let r = obvhs_ray(o, d, t_max);
        let shear = RayShear::new(o, d + Vec3::ZERO);
        !bvh.ray_traverse_miss(r, |r, id| {
            match intersect_prim(&self.prims[id], &shear, r.tmax) {
                Some((t, _, _)) => t,
                None => f32::INFINITY,
            }
        })
    }

    /// Surface attributes of a raw hit.
    #[inline(always)]
    fn finish_hit(&self, ray: &Ray, t: f32, raw: RawHit) -> Hit {
        let prim = &self.prims[raw.prim as usize];
        if prim.shape & SPHERE_BIT != 0 {
            let si = prim.shape & !SPHERE_BIT;
            let s = &self.spheres[si as usize];
            let mut n = (ray.o + ray.d * t - s.center).normalize();
            // Reproject onto the surface (as Mitsuba does) to limit drift.
            let p = s.center + n * s.radius;
            let l = s.to_local * n;
            let mut phi = l.y.atan2(l.x);
            if phi < 0.0 {
                phi += 2.0 * PI;
            }
            let uv = Vec2::new(phi * (0.5 / PI), l.z.clamp(-1.0, 1.0).acos() * (1.0 / PI));
            if s.flip_normals {
                n = -n;
            }
            Hit {
                t,
                p,
                ng: n,
                ns: n,
                uv,
                shape: ShapeRef::Sphere(si),
                material: s.material,
                light: s.light,
            }
        } else {
            let m = &self.meshes[prim.shape as usize];
            let (b1, b2) = (raw.u, raw.v);
            let b0 = 1.0 - b1 - b2;
            let p = prim.a * b0 + prim.b * b1 + prim.c * b2;
            let ng = prim.ng;
            let ns = match self.prim_normals.get(raw.prim as usize) {
                Some(n) if m.has_normals => {
                    let v = n[0] * b0 + n[1] * b1 + n[2] * b2;
                    let v = v.normalize_or_zero();
                    if v == Vec3::ZERO { ng } else { v }
                }
                _ => ng,
            };
            let uv = match self.prim_uvs.get(raw.prim as usize) {
                Some(uv) if m.has_uvs => uv[0] * b0 + uv[1] * b1 + uv[2] * b2,
                _ => Vec2::new(b1, b2),
            };
            Hit {
                t,
                p,
                ng,
                ns,
                uv,
                shape: ShapeRef::Mesh {
                    mesh: prim.shape,
                    triangle: prim.index,
                },
                material: m.material,
                light: m.light,
            }
        }
    }
}

/// Whether every vertex normal of every triangle of `mesh` equals the triangle's face normal
/// to within [`FLAT_NORMAL_TOLERANCE`] per component (planar meshes: walls, quads, boxes with
/// per-face vertices). Then `finish_hit` shades with the face normal and skips interpolating
/// and renormalising: the interpolated normal differs from it only by rounding.
fn normals_are_flat(mesh: &scene::Mesh) -> bool {
    let Some(normals) = &mesh.normals else {
        return true;
    };
    mesh.indices.iter().all(|idx| {
        let [Some(&p0), Some(&p1), Some(&p2)] = idx.map(|i| mesh.positions.get(i as usize)) else {
            return false;
        };
        let ng = (p1 - p0).cross(p2 - p0).normalize();
        idx.iter().all(|&i| {
            normals
                .get(i as usize)
                .is_some_and(|n| (*n - ng).abs().max_element() <= FLAT_NORMAL_TOLERANCE)
        })
    })
}

/// Largest per-component difference between a vertex normal and the face normal for which a
/// triangle counts as flat (a few ulps of a unit vector).
const FLAT_NORMAL_TOLERANCE: f32 = 4.0 * f32::EPSILON;

/// The obvhs ray for `o + t·d`, `t ∈ (0, t_max)`.
///
/// Negative zeros in `d` are turned into positive ones: obvhs picks the octant from
/// `d < 0` but the reciprocal's sign from `signum(d)`, which disagree for `−0.0` and would
/// make every box test miss (found as `-Vec3::Z` rays missing everything).
#[inline(always)]
fn obvhs_ray(o: Vec3, d: Vec3, t_max: f32) -> obvhs::ray::Ray {
    let d = d + Vec3::ZERO;
    obvhs::ray::Ray::new(Vec3A::from(o), Vec3A::from(d), 0.0, t_max)
}

/// Per-ray constants of the watertight triangle test: the axis permutation making the
/// ray direction's largest component `z`, and the shear `(Sx, Sy, Sz)` [Woop et al. 2013];
/// also the reciprocal direction for box tests.
#[derive(Clone, Copy, Debug)]
struct RayShear {
    o: Vec3,
    d: Vec3,
    k: [usize; 3],
    s: Vec3,
    /// The origin in the permuted axes `(o[kx], o[ky], o[kz])`.
    o_perm: Vec3,
    /// `1 / d` per axis, `f32::MAX` for zero components (finite: no `0 · ∞` in box tests).
    inv_d: Vec3,
}

impl RayShear {
    #[inline(always)]
    fn new(o: Vec3, d: Vec3) -> Self {
        const NEXT: [usize; 3] = [1, 2, 0];
        let a = d.abs();
        // Branch-free choice of the dominant axis (random directions defeat prediction):
        // x if it beats y and z, else y if it beats z, else z.
        let x_beats_y = a.x > a.y;
        // (`&` rather than `&&`: with `&&` the compiler emitted branches.)
        let x_max = x_beats_y & (a.x > a.z);
        let y_max = !x_beats_y & (a.y > a.z);
        let kz = usize::from(y_max) + 2 * usize::from(!x_max & !y_max);
        let kx = NEXT[kz];
        let ky = NEXT[kx];
        let dv = d.to_array();
        let ov = o.to_array();
        // Keep the winding: swap when the dominant component is negative.
        let (kx, ky) = if dv[kz] < 0.0 { (ky, kx) } else { (kx, ky) };
        let recip = Vec3A::ONE / Vec3A::from(d);
        let inv_d = Vec3::from(Vec3A::select(
            Vec3A::from(d).cmpeq(Vec3A::ZERO),
            Vec3A::splat(f32::MAX),
            recip,
        ));
        // Equal to `1 / d[kz]`: the dominant component is never zero for a unit direction.
        let sz = inv_d.to_array()[kz];
        Self {
            o,
            d,
            k: [kx, ky, kz],
            s: Vec3::new(dv[kx] * sz, dv[ky] * sz, sz),
            o_perm: Vec3::new(ov[kx], ov[ky], ov[kz]),
            inv_d,
        }
    }
}

/// `(t, b1, b2)` of a primitive hit with `t ∈ (0, t_max)`; for spheres `b1 = b2 = 0`.
#[inline(always)]
fn intersect_prim(prim: &Prim, ray: &RayShear, t_max: f32) -> Option<(f32, f32, f32)> {
    if prim.shape & SPHERE_BIT != 0 {
        return intersect_sphere(prim.a, prim.b.x, ray.o, ray.d, t_max).map(|t| (t, 0.0, 0.0));
    }
    let [kx, ky, kz] = ray.k;
    let (a, b, c) = (
        (prim.a - ray.o).to_array(),
        (prim.b - ray.o).to_array(),
        (prim.c - ray.o).to_array(),
    );
    // Shear and scale the vertices into ray space (ray along +z from the origin).
    let (ax, ay) = (a[kx] - ray.s.x * a[kz], a[ky] - ray.s.y * a[kz]);
    let (bx, by) = (b[kx] - ray.s.x * b[kz], b[ky] - ray.s.y * b[kz]);
    let (cx, cy) = (c[kx] - ray.s.x * c[kz], c[ky] - ray.s.y * c[kz]);
    let mut u = cx * by - cy * bx;
    let mut v = ax * cy - ay * cx;
    let mut w = bx * ay - by * ax;
    if u == 0.0 || v == 0.0 || w == 0.0 {
        // Exactly on an edge in f32: decide in f64 so neighbours agree.
        let f = |p: f32, q: f32, r: f32, s: f32| {
            (f64::from(p) * f64::from(q) - f64::from(r) * f64::from(s)) as f32
        };
        u = f(cx, by, cy, bx);
        v = f(ax, cy, ay, cx);
        w = f(bx, ay, by, ax);
    }
    if (u < 0.0 || v < 0.0 || w < 0.0) && (u > 0.0 || v > 0.0 || w > 0.0) {
        return None;
    }
    let det = u + v + w;
    if det == 0.0 {
        return None;
    }
    let (az, bz, cz) = (ray.s.z * a[kz], ray.s.z * b[kz], ray.s.z * c[kz]);
    let t_scaled = u * az + v * bz + w * cz;
    let inv_det = 1.0 / det;
    let t = t_scaled * inv_det;
    if !(t > 0.0 && t < t_max) {
        return None;
    }
    Some((t, v * inv_det, w * inv_det))
}

/// Nearest `t ∈ (0, t_max)` on a sphere, solved in f64 (as Mitsuba's scalar variants) with the
/// numerically stable quadratic formula.
#[inline]
fn intersect_sphere(c: Vec3, radius: f32, o: Vec3, d: Vec3, t_max: f32) -> Option<f32> {
    let oc = (o - c).as_dvec3();
    let d = d.as_dvec3();
    let r = f64::from(radius);
    let a = d.length_squared();
    let b = oc.dot(d);
    let cc = oc.length_squared() - r * r;
    let disc = b * b - a * cc;
    if disc < 0.0 {
        return None;
    }
    let q = -(b + disc.sqrt().copysign(b));
    if q == 0.0 {
        return None;
    }
    let (t0, t1) = {
        let (x, y) = (q / a, cc / q);
        if x <= y { (x, y) } else { (y, x) }
    };
    let t_max = f64::from(t_max);
    for t in [t0, t1] {
        if t > 0.0 && t < t_max {
            let tf = t as f32;
            if tf > 0.0 && tf < t_max as f32 {
                return Some(tf);
            }
        }
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn flat_normal_detection_accepts_only_face_normals() {
        let mesh = |normals: Option<Vec<Vec3>>| scene::Mesh {
            positions: vec![
                Vec3::new(-1.0, -1.0, 0.0),
                Vec3::new(1.0, -1.0, 0.0),
                Vec3::new(1.0, 1.0, 0.0),
                Vec3::new(-1.0, 1.0, 0.0),
            ],
            normals,
            uvs: None,
            indices: vec![[0, 1, 2], [0, 2, 3]],
            material: 0,
            emitter: None,
        };
        assert!(normals_are_flat(&mesh(None)));
        assert!(normals_are_flat(&mesh(Some(vec![Vec3::Z; 4]))));
        // A vertex normal off by one ulp-scale rounding still counts; a real tilt or the back
        // side does not.
        let nearly = Vec3::new(f32::EPSILON, 0.0, 1.0);
        assert!(normals_are_flat(&mesh(Some(vec![
            Vec3::Z,
            nearly,
            Vec3::Z,
            Vec3::Z
        ]))));
        let tilted = Vec3::new(0.1, 0.0, 1.0).normalize();
        assert!(!normals_are_flat(&mesh(Some(vec![
            Vec3::Z,
            Vec3::Z,
            tilted,
            Vec3::Z
        ]))));
        assert!(!normals_are_flat(&mesh(Some(vec![-Vec3::Z; 4]))));
    }

    #[test]
    fn sphere_quadratic_finds_near_and_far_roots() {
        let t = intersect_sphere(
            Vec3::ZERO,
            1.0,
            Vec3::new(0.0, 0.0, -5.0),
            Vec3::Z,
            f32::INFINITY,
        );
        assert!((t.unwrap() - 4.0).abs() < 1e-6);
        let t = intersect_sphere(Vec3::ZERO, 1.0, Vec3::ZERO, Vec3::Z, f32::INFINITY);
        assert!((t.unwrap() - 1.0).abs() < 1e-6);
        assert!(
            intersect_sphere(Vec3::ZERO, 1.0, Vec3::new(0.0, 2.0, -5.0), Vec3::Z, 100.0).is_none()
        );
    }
}
