//! Lights: area lights (emitting meshes and spheres), the environment (lat-long map or
//! constant) and light selection, with Mitsuba 3's conventions.
//!
//! # Contract
//! - [`Lights`] is built once per scene by [`Lights::new`]; it holds only what the scene has
//!   (no env tables without an environment, nothing per light when there is no emitter).
//! - Light indices: emitting meshes in scene order, then emitting spheres, then the
//!   environment. Each emitting **shape** is one light, the environment is one light
//!   (Mitsuba's uniform emitter selection counts emitters the same way).
//! - Every pdf is a **solid-angle density at the shading point** `p`. [`Lights::sample_light`]
//!   and the `pdf_*` queries exclude the selection pmf; [`Lights::sample`] includes it.
//! - A sample whose point emits nothing towards `p` for geometric reasons (back side of a
//!   one-sided emitter, degenerate distance) is `None`, and the matching `pdf_*` query
//!   returns 0 for such points, so `pdf_*` is exactly the density of the `Some` samples.
//!   Zero-radiance emitters still produce samples (with zero radiance and a valid pdf): the
//!   CV estimators need every technique's pdf also for zero-contribution samples [Hua §8].
//! - Visibility is not tested here: the integrator traces the shadow ray (to `dist` along `wi`).
//! - Per-sample calls allocate nothing and cost `O(log n)` (binary searches in CDF tables).
//!
//! # Light selection
//! | [`LightSelection`] | pmf of light `k` |
//! |---|---|
//! | `Uniform` (Mitsuba's default) | `1 / n_lights` |
//! | `Power` | `Φ_k / Σ Φ`, `Φ = π · A · luminance(L)` for area lights, `Φ = π R² ∫ luminance(L) dω` for the environment (`R`: radius of the scene's bounding sphere, pbrt-v4's estimate); uniform if every `Φ` is 0 |
//!
//! # Layout
//! - [`area`]: mesh and sphere emitters (`area.rs`).
//! - [`environment`]: lat-long env map and constant environment (`environment.rs`).
//! - [`distribution`]: tabulated 1-D discrete distributions (CDF + binary search).

use glam::{Vec2, Vec3};

pub mod area;
pub mod distribution;
pub mod environment;

use area::{MeshLight, SphereLight};
use distribution::Distribution1D;
use environment::EnvLight;

/// Mitsuba 3's luminance of linear sRGB (Rec. 709 primaries).
#[inline]
pub fn luminance(c: Vec3) -> f32 {
    c.dot(Vec3::new(0.212_671, 0.715_160, 0.072_169))
}

/// One light sample as seen from a shading point.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LightSample {
    /// World-space unit direction from the shading point towards the light.
    pub wi: Vec3,
    /// Distance to the sampled point; `f32::INFINITY` for the environment.
    pub dist: f32,
    /// Emitted radiance arriving along `−wi` (not divided by the pdf).
    pub radiance: Vec3,
    /// Solid-angle pdf at the shading point (see [`Lights::sample_light`] / [`Lights::sample`]
    /// for whether the selection pmf is included).
    pub pdf: f32,
    /// Index of the light.
    pub light: u32,
    /// Whether the light is a delta light (point/directional; always false for now).
    pub delta: bool,
    /// Oriented geometric normal at the sampled point (its emitting side faces `−wi`);
    /// `−wi` for the environment. Useful to offset the shadow ray's far end.
    pub n: Vec3,
}

/// How [`Lights::select`] picks a light.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum LightSelection {
    /// Every light with the same probability (Mitsuba).
    #[default]
    Uniform,
    /// Proportional to emitted power.
    Power,
}

/// What a light index refers to (see [`Lights::kind`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LightKind {
    /// Emitting mesh `Scene::meshes[mesh]`.
    Mesh {
        /// Index into [`scene::Scene::meshes`].
        mesh: u32,
    },
    /// Emitting sphere `Scene::spheres[sphere]`.
    Sphere {
        /// Index into [`scene::Scene::spheres`].
        sphere: u32,
    },
    /// The environment (map or constant).
    Environment,
}

/// One light.
///
/// `repr(u8)`: an explicit tag byte, one compare per light sample (decoding the niche in
/// `MeshLight`'s vectors took ~8 instructions).
#[derive(Clone, Debug, PartialEq)]
#[repr(u8)]
enum Light {
    /// Emitting mesh (index into [`scene::Scene::meshes`]).
    Mesh(MeshLight),
    /// Emitting sphere.
    Sphere(SphereLight),
    /// The environment (its data lives in [`Lights::env`]).
    Env,
}

/// How lights are selected, resolved at build time.
#[derive(Clone, Debug, PartialEq)]
enum Selector {
    /// `1/n`.
    Uniform { inv_n: f32 },
    /// Tabulated pmf ∝ power.
    Power(Distribution1D),
}

/// Sentinel for "not an emitter" in the shape → light maps.
const NO_LIGHT: u32 = u32::MAX;

/// All lights of a scene, with light selection.
#[derive(Clone, Debug, PartialEq)]
pub struct Lights {
    lights: Vec<Light>,
    /// What each light is (parallel to `lights`).
    kinds: Vec<LightKind>,
    /// Light index per mesh (`NO_LIGHT` if not emitting); empty when there are no area lights.
    mesh_to_light: Vec<u32>,
    /// Light index per sphere; empty when there are no area lights.
    sphere_to_light: Vec<u32>,
    /// The environment and its light index.
    env: Option<(EnvLight, u32)>,
    /// `None` when there are no lights.
    selector: Option<Selector>,
}

impl Lights {
    /// Collects the scene's emitters and prepares light selection.
    pub fn new(scene: &scene::Scene, selection: LightSelection) -> Self {
        let mut lights = Vec::new();
        let mut kinds = Vec::new();
        let mut mesh_to_light = Vec::new();
        let mut sphere_to_light = Vec::new();
        let any_area = scene.meshes.iter().any(|m| m.emitter.is_some())
            || scene.spheres.iter().any(|s| s.emitter.is_some());
        if any_area {
            mesh_to_light = vec![NO_LIGHT; scene.meshes.len()];
            sphere_to_light = vec![NO_LIGHT; scene.spheres.len()];
            for (k, mesh) in scene.meshes.iter().enumerate() {
                if let Some(radiance) = mesh.emitter {
                    mesh_to_light[k] = lights.len() as u32;
                    lights.push(Light::Mesh(MeshLight::new(mesh, sanitize(radiance))));
                    kinds.push(LightKind::Mesh { mesh: k as u32 });
                }
            }
            for (k, s) in scene.spheres.iter().enumerate() {
                if let Some(radiance) = s.emitter {
                    sphere_to_light[k] = lights.len() as u32;
                    lights.push(Light::Sphere(SphereLight {
                        center: s.center,
                        radius: s.radius.abs(),
                        flip_normals: s.flip_normals,
                        radiance: sanitize(radiance),
                    }));
                    kinds.push(LightKind::Sphere { sphere: k as u32 });
                }
            }
        }
        let env = scene.environment.as_ref().map(|e| {
            let idx = lights.len() as u32;
            lights.push(Light::Env);
            kinds.push(LightKind::Environment);
            (EnvLight::new(e), idx)
        });

        let selector = if lights.is_empty() {
            None
        } else {
            let uniform = Selector::Uniform {
                inv_n: 1.0 / lights.len() as f32,
            };
            Some(match selection {
                LightSelection::Uniform => uniform,
                LightSelection::Power => {
                    let r = bounding_radius(scene) as f64;
                    let power = lights.iter().map(|l| match l {
                        Light::Mesh(m) => {
                            std::f64::consts::PI
                                * f64::from(m.area)
                                * f64::from(luminance(m.radiance))
                        }
                        Light::Sphere(s) => {
                            std::f64::consts::PI
                                * f64::from(s.area())
                                * f64::from(luminance(s.radiance))
                        }
                        Light::Env => env.as_ref().map_or(0.0, |(e, _)| {
                            std::f64::consts::PI * r * r * e.luminance_integral()
                        }),
                    });
                    Distribution1D::new(power).map_or(uniform, Selector::Power)
                }
            })
        };
        Self {
            lights,
            kinds,
            mesh_to_light,
            sphere_to_light,
            env,
            selector,
        }
    }

    /// Number of lights.
    #[inline]
    pub fn len(&self) -> usize {
        self.lights.len()
    }

    /// Whether the scene has no light at all.
    #[inline]
    pub fn is_empty(&self) -> bool {
        self.lights.is_empty()
    }

    /// Light index of mesh `mesh`, if it emits.
    #[inline]
    pub fn mesh_light(&self, mesh: usize) -> Option<u32> {
        self.mesh_to_light
            .get(mesh)
            .copied()
            .filter(|&l| l != NO_LIGHT)
    }

    /// Light index of sphere `sphere`, if it emits.
    #[inline]
    pub fn sphere_light(&self, sphere: usize) -> Option<u32> {
        self.sphere_to_light
            .get(sphere)
            .copied()
            .filter(|&l| l != NO_LIGHT)
    }

    /// Light index of the environment, if any.
    #[inline]
    pub fn env_light(&self) -> Option<u32> {
        self.env.as_ref().map(|(_, i)| *i)
    }

    /// What light `light` is (the inverse of [`Self::mesh_light`], [`Self::sphere_light`],
    /// [`Self::env_light`]); `None` for an invalid index.
    #[inline]
    pub fn kind(&self, light: u32) -> Option<LightKind> {
        self.kinds.get(light as usize).copied()
    }

    /// Probability that [`Self::select`] picks `light` (0 for an invalid index).
    #[inline]
    pub fn selection_pmf(&self, light: u32) -> f32 {
        if light as usize >= self.lights.len() {
            return 0.0;
        }
        match &self.selector {
            Some(Selector::Uniform { inv_n }) => *inv_n,
            Some(Selector::Power(d)) => d.pmf(light as usize),
            None => 0.0,
        }
    }

    /// Picks a light with `u ∈ [0, 1)`: `(light, pmf)`; `None` without lights.
    #[inline]
    pub fn select(&self, u: f32) -> Option<(u32, f32)> {
        match self.selector.as_ref()? {
            Selector::Uniform { inv_n } => {
                let n = self.lights.len();
                let k = ((u.max(0.0) * n as f32) as usize).min(n - 1);
                Some((k as u32, *inv_n))
            }
            Selector::Power(d) => {
                let (k, pmf, _) = d.sample(u);
                Some((k as u32, pmf))
            }
        }
    }

    /// Calls `f` with point sets whose convex hulls together contain every finite emitter's
    /// surface: each triangle of an emitting mesh (its three corners), each emitting
    /// sphere's bounding box (eight corners). The environment, at infinity, has none.
    pub fn for_each_emitter_hull(&self, mut f: impl FnMut(&[Vec3])) {
        for light in &self.lights {
            match light {
                Light::Mesh(m) => m.for_each_triangle(|t| f(&t)),
                Light::Sphere(s) => {
                    let r = Vec3::splat(s.radius.abs());
                    let (lo, hi) = (s.center - r, s.center + r);
                    let corners: [Vec3; 8] = std::array::from_fn(|i| {
                        Vec3::new(
                            if i & 1 == 0 { lo.x } else { hi.x },
                            if i & 2 == 0 { lo.y } else { hi.y },
                            if i & 4 == 0 { lo.z } else { hi.z },
                        )
                    });
                    f(&corners);
                }
                Light::Env => {}
            }
        }
    }

    /// Samples a point on `light` as seen from `p` with `u ∈ [0, 1)²`. The pdf is in solid
    /// angle at `p` and **excludes** the selection pmf. `None` for a failed sample (back side,
    /// degenerate geometry, invalid index, all-black env map).
    #[inline]
    pub fn sample_light(&self, light: u32, p: Vec3, u: Vec2) -> Option<LightSample> {
        match self.lights.get(light as usize)? {
            Light::Mesh(m) => m.sample(p, u).map(|s| LightSample {
                wi: s.wi,
                dist: s.dist,
                radiance: m.radiance,
                pdf: s.pdf,
                light,
                delta: false,
                n: s.n,
            }),
            Light::Sphere(sph) => sph.sample(p, u).map(|s| LightSample {
                wi: s.wi,
                dist: s.dist,
                radiance: sph.radiance,
                pdf: s.pdf,
                light,
                delta: false,
                n: s.n,
            }),
            Light::Env => {
                let (env, _) = self.env.as_ref()?;
                env.sample(u).map(|s| LightSample {
                    wi: s.wi,
                    dist: f32::INFINITY,
                    radiance: s.radiance,
                    pdf: s.pdf,
                    light,
                    delta: false,
                    n: -s.wi,
                })
            }
        }
    }

    /// [`Self::select`] with `u_sel`, then [`Self::sample_light`] with `u`; the returned pdf
    /// **includes** the selection pmf.
    #[inline]
    pub fn sample(&self, p: Vec3, u_sel: f32, u: Vec2) -> Option<LightSample> {
        let (light, pmf) = self.select(u_sel)?;
        let mut s = self.sample_light(light, p, u)?;
        s.pdf *= pmf;
        Some(s)
    }

    /// Solid-angle pdf (excluding selection) with which [`Self::sample_light`]`(light, p, ·)`
    /// produces the point `y` with oriented geometric normal `n_y` on area light `light`
    /// (0 for the back side, points a sphere's cone sampling cannot produce, or a non-area light).
    #[inline]
    pub fn pdf_area(&self, light: u32, p: Vec3, y: Vec3, n_y: Vec3) -> f32 {
        match self.lights.get(light as usize) {
            Some(Light::Mesh(m)) => m.pdf(p, y, n_y),
            Some(Light::Sphere(s)) => s.pdf(p, y, n_y),
            _ => 0.0,
        }
    }

    /// Radiance emitted by area light `light` at a point with oriented geometric normal `n_y`
    /// towards direction `w` (pointing away from the light); zero on the back side or for a
    /// non-area light.
    #[inline]
    pub fn area_radiance(&self, light: u32, n_y: Vec3, w: Vec3) -> Vec3 {
        let radiance = match self.lights.get(light as usize) {
            Some(Light::Mesh(m)) => m.radiance,
            Some(Light::Sphere(s)) => s.radiance,
            _ => return Vec3::ZERO,
        };
        if n_y.dot(w) > 0.0 {
            radiance
        } else {
            Vec3::ZERO
        }
    }

    /// Environment radiance arriving from world direction `d` (pointing away from the scene,
    /// i.e. the direction of the escaping ray); zero without an environment.
    #[inline]
    pub fn env_radiance(&self, d: Vec3) -> Vec3 {
        self.env.as_ref().map_or(Vec3::ZERO, |(e, _)| e.eval(d))
    }

    /// Solid-angle pdf (excluding selection) of sampling direction `d` from the environment;
    /// 0 without an environment.
    #[inline]
    pub fn pdf_env(&self, d: Vec3) -> f32 {
        self.env.as_ref().map_or(0.0, |(e, _)| e.pdf(d))
    }
}

/// Negative and non-finite radiance components are read as 0.
fn sanitize(c: Vec3) -> Vec3 {
    Vec3::from_array(
        c.to_array()
            .map(|x| if x.is_finite() && x > 0.0 { x } else { 0.0 }),
    )
}

/// Radius of the bounding sphere of the scene's geometry (1 for an empty scene).
fn bounding_radius(scene: &scene::Scene) -> f32 {
    let mut lo = Vec3::splat(f32::INFINITY);
    let mut hi = Vec3::splat(f32::NEG_INFINITY);
    for m in &scene.meshes {
        for &p in &m.positions {
            lo = lo.min(p);
            hi = hi.max(p);
        }
    }
    for s in &scene.spheres {
        lo = lo.min(s.center - Vec3::splat(s.radius.abs()));
        hi = hi.max(s.center + Vec3::splat(s.radius.abs()));
    }
    let r = 0.5 * (hi - lo).length();
    if r.is_finite() && r > 0.0 { r } else { 1.0 }
}
