//! `path` — the reference estimator: unidirectional path tracing with next-event estimation
//! (one light sample per vertex) and BSDF sampling, combined by MIS. It estimates exactly
//! what Mitsuba 3's `path` integrator estimates, and is the baseline of every speedup.
//!
//! | parameter | meaning |
//! |---|---|
//! | `max_depth` | path segments incl. the camera ray (1: emitters seen directly, 2: direct lighting, −1: unbounded) |
//! | `rr_depth` | Russian roulette from this many scattering vertices on |
//! | `hide_emitters` | camera rays pass through area emitters; the env is black when seen directly |
//! | `mis` | `power` (default, Mitsuba) or `balance` |
//!
//! ```json
//! { "estimator": { "kind": "path" }, "max_depth": 5, "rr_depth": 5, "mis": "power" }
//! ```
//!
//! Per vertex (Mitsuba 3 `path.cpp`, in the same order):
//! 1. emission of the surface/env reached by the previous BSDF sample, weighted
//!    `w_bsdf = mis(p_bsdf, p_light)` (1 after a delta lobe or at the camera hit);
//! 2. if the vertex may scatter (`depth + 1 < max_depth`): NEE unless the BSDF is purely
//!    delta — `f·Le·V·w_light / p_light` with `w_light = mis(p_light, p_bsdf)`, `p_light`
//!    including the selection pmf;
//! 3. BSDF sample, throughput `β *= f·cos/p`;
//! 4. Russian roulette once `depth ≥ rr_depth`: continue with `q = min(max β·η², 0.95)`,
//!    `β /= q` (η = 1: no BSDF here transmits); stop when `β` is zero.
//!
//! Pdfs are solid-angle densities at the shading point.
//!
//! An observer with `VertexObserver::CONTROLS_DIRECT` (the CV estimators, `cv.rs`) takes
//! over the direct lighting of the scattering vertices it controls (`VertexObserver::controls`,
//! asked per vertex; steps 1–2 for emission found by the BSDF sample and NEE); `trace` then
//! also traces zero-weight BSDF samples (and stops) and
//! the shadow rays of zero-valued NEE samples with `p_bsdf > 0`, so every technique's pdf
//! is known for every sample [Hua §8]. An observer whose base estimate is `path`'s own
//! (`VertexObserver::adds_to_path`) leaves steps 1–2 to `trace` on controlled vertices too
//! and returns only what it adds (a CV term); the others return the whole direct lighting.
//! With the default observer nothing changes: `path` results are bit-identical.
//!
//! Sampler dimensions (aligned to the sampler's 4-dimension sets): 0–1 pixel position (2–3
//! unused); vertex `k` uses the 8 dimensions from `4 + 8k`: light selection (1), light
//! position (2), BSDF lobe (1), BSDF direction (2), roulette (1), one unused — fixed whether a
//! technique runs or not.

use glam::{Vec2, Vec3};

use super::{
    BsdfTechnique, LightTechnique, RenderScene, RenderSettings, VertexObserver, VertexRecord,
};
use crate::accel::Hit;
use crate::math::{Frame, Ray};
use crate::sampler::Sampler;

/// Sampler dimensions reserved for the camera (pixel position + 2 spare).
pub const CAMERA_DIMS: u32 = 4;
/// Sampler dimensions per path vertex (7 used + 1 spare, two 4-dimension sets).
pub const DIMS_PER_VERTEX: u32 = 8;
/// Most emitters a camera ray passes through with `hide_emitters` before giving up.
const MAX_HIDDEN_EMITTERS: u32 = 64;

/// The result of one camera path.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PathSample {
    /// Radiance estimate.
    pub radiance: Vec3,
    /// First-hit albedo AOV (zero on a miss).
    pub albedo: Vec3,
    /// First-hit shading normal AOV (zero on a miss).
    pub normal: Vec3,
    /// Rays traced (camera, shadow and continuation rays).
    pub rays: u32,
}

/// The first dimension of vertex `depth`.
#[inline]
pub fn vertex_dimension(depth: u32) -> u32 {
    CAMERA_DIMS.saturating_add(depth.saturating_mul(DIMS_PER_VERTEX))
}

/// Traces the camera ray to the first scattering vertex (shared by every estimator).
///
/// With `hide_emitters`, camera rays pass through area lights (Mitsuba's
/// `skip_area_emitters`). Adds the traced rays to `out.rays`. Returns `None` when the ray
/// escapes — then `out.radiance` already holds the env radiance (unless hidden) — else the
/// hit, the ray that found it and the emission seen directly at the hit (no MIS: the
/// camera is a delta "BSDF", Mitsuba's `prev_bsdf_delta = true`).
///
/// Always inlined: as a call, its `Option<(Hit, Ray, Vec3)>` went through memory and the
/// caller reloaded and spilled its whole loop state around it once per path.
#[inline(always)]
pub(crate) fn camera_hit(
    rs: &RenderScene,
    st: &RenderSettings,
    camera_ray: Ray,
    out: &mut PathSample,
) -> Option<(Hit, Ray, Vec3)> {
    let lights = &rs.lights;
    let mut ray = camera_ray;
    let mut hit = rs.accel.intersect(&ray);
    if st.hide_emitters {
        let mut skipped = 0;
        while let Some(h) = hit {
            if h.light.is_none() || skipped >= MAX_HIDDEN_EMITTERS {
                break;
            }
            ray = Ray {
                o: h.offset_origin(ray.d),
                d: ray.d,
                t_max: ray.t_max - h.t,
            };
            hit = rs.accel.intersect(&ray);
            out.rays += 1;
            skipped += 1;
        }
    }
    let Some(h) = hit else {
        if !st.hide_emitters {
            out.radiance += lights.env_radiance(ray.d);
        }
        return None;
    };
    let emitted = match h.light {
        Some(l) => lights.area_radiance(l, h.ns, -ray.d),
        None => Vec3::ZERO,
    };
    Some((h, ray, emitted))
}

/// Traces one camera path starting with `camera_ray` (unit direction), reporting each
/// scattering vertex to `observer`.
pub fn trace<O: VertexObserver>(
    rs: &RenderScene,
    st: &RenderSettings,
    camera_ray: Ray,
    sampler: &mut Sampler,
    observer: &mut O,
) -> PathSample {
    let max_depth = st.max_depth_u32();
    let lights = &rs.lights;
    let mut out = PathSample {
        rays: 1,
        ..PathSample::default()
    };
    let Some((mut h, mut ray, radiance)) = camera_hit(rs, st, camera_ray, &mut out) else {
        return out;
    };
    let mut radiance = radiance;

    let mut beta = Vec3::ONE;
    let mut depth = 0u32;
    let adds_to_path = O::CONTROLS_DIRECT && observer.adds_to_path();
    loop {
        let bsdf = rs.materials.bsdf(h.material, h.uv);
        if depth == 0 {
            out.albedo = bsdf.albedo();
            out.normal = h.ns;
        }
        if depth.saturating_add(1) >= max_depth {
            break;
        }
        // Whether the observer owns this vertex's direct lighting (needs every technique's
        // pdf, [Hua §8]); an uncontrolled vertex is exactly `path`'s.
        let controls = O::CONTROLS_DIRECT && observer.controls(depth, h.p, h.ns, bsdf.is_glossy());
        // Whether this vertex's MIS-weighted direct lighting is added here (`path`'s).
        let adds_direct = !controls || adds_to_path;
        let frame = Frame::from_normal(h.ns);
        let wo = frame.to_local(-ray.d);

        sampler.set_dimension(vertex_dimension(depth));
        let u = sampler.next_8d();
        let u_select = u[0];
        let u_light = Vec2::new(u[1], u[2]);
        let u_lobe = u[3];
        let u_bsdf = Vec2::new(u[4], u[5]);
        let u_rr = u[6];

        // The BSDF sample does not depend on NEE: taking it first lets its arithmetic overlap
        // the light sample's.
        let bsdf_sample = bsdf.sample(wo, u_lobe, u_bsdf);

        // ---- emitter sampling (NEE) ----
        let mut light_tech = None;
        // Selection then sampling, exactly as `Lights::sample`, keeping the selected light
        // for observers when the sample fails.
        let nee_sel = if !bsdf.is_delta() && !lights.is_empty() {
            lights.select(u_select)
        } else {
            None
        };
        if controls && let Some((sel_light, _)) = nee_sel {
            observer.nee_selected(sel_light);
        }
        if let Some((sel_light, sel_pmf)) = nee_sel
            && let Some(mut ls) = lights.sample_light(sel_light, h.p, u_light)
            && {
                ls.pdf *= sel_pmf;
                // `pdf > 0 && pdf.is_finite()` as two comparisons (that form compiled to a
                // ~20-instruction floating-point class test).
                (ls.pdf > 0.0) & (ls.pdf < f32::INFINITY)
            }
        {
            let wi_local = frame.to_local(ls.wi);
            let (f, pdf_bsdf) = bsdf.eval_pdf(wo, wi_local);
            let mut value = Vec3::ZERO;
            let mut visible = false;
            let contributes = f != Vec3::ZERO && ls.radiance != Vec3::ZERO;
            if contributes || (controls && pdf_bsdf > 0.0) {
                let shadow = if ls.dist.is_finite() {
                    h.spawn_ray_to(h.p + ls.wi * ls.dist)
                } else {
                    h.spawn_ray(ls.wi)
                };
                out.rays += 1;
                if !rs.accel.occluded(shadow.o, shadow.d, shadow.t_max) {
                    visible = true;
                    if contributes {
                        value = f * ls.radiance;
                    }
                }
            }
            if adds_direct && value != Vec3::ZERO {
                let w = if ls.delta {
                    1.0
                } else {
                    st.mis.weight(ls.pdf, pdf_bsdf)
                };
                radiance += beta * value * (w / ls.pdf);
            }
            light_tech = Some(LightTechnique {
                light: ls.light,
                pdf_light: ls.pdf,
                pdf_bsdf,
                value,
                visible,
            });
        }
        // What the observer gets for this vertex, with the BSDF technique below: built at
        // each report, and only where the observer reads it.
        let throughput = beta;
        let record = |bsdf| VertexRecord {
            throughput,
            light: light_tech,
            nee_light: nee_sel.map(|(l, _)| l),
            bsdf,
        };

        // ---- BSDF sampling ----
        let Some(bs) = bsdf_sample else {
            if reports::<O>(controls) {
                report(observer, controls, &mut radiance, &record(None));
            }
            break;
        };
        let wi = frame.to_world(bs.wi);
        beta *= bs.weight;

        // ---- Russian roulette (before tracing, as Mitsuba) ----
        depth += 1;
        let beta_max = beta.max_element();
        let mut alive = beta_max > 0.0 && beta.is_finite();
        // A CV needs the pdfs of a zero-weight BSDF sample too: trace it, then stop.
        let zero_weight_trace = controls && !alive && beta == Vec3::ZERO;
        let mut rr_q = 1.0;
        if alive && depth as i64 >= i64::from(st.rr_depth) {
            rr_q = beta_max.min(0.95);
            if u_rr < rr_q {
                beta /= rr_q;
            } else {
                alive = false;
            }
        }

        let mut tech = BsdfTechnique {
            pdf_bsdf: bs.pdf,
            pdf_light: 0.0,
            weight: bs.weight,
            emitted: Vec3::ZERO,
            hit_light: None,
            delta: bs.delta,
            traced: false,
            rr_q,
        };
        if !alive && !zero_weight_trace {
            if reports::<O>(controls) {
                report(observer, controls, &mut radiance, &record(Some(tech)));
            }
            break;
        }

        // ---- trace the continuation ray; emission found by BSDF sampling ----
        ray = h.spawn_ray(wi);
        out.rays += 1;
        let next = rs.accel.intersect(&ray);
        tech.traced = true;
        match &next {
            None => {
                tech.emitted = lights.env_radiance(wi);
                tech.hit_light = lights.env_light();
                if !bs.delta
                    && (controls || tech.emitted != Vec3::ZERO)
                    && let Some(l) = lights.env_light()
                {
                    tech.pdf_light = lights.selection_pmf(l) * lights.pdf_env(wi);
                }
            }
            Some(n) => {
                if let Some(l) = n.light {
                    tech.hit_light = Some(l);
                    tech.emitted = lights.area_radiance(l, n.ns, -wi);
                    if !bs.delta {
                        tech.pdf_light =
                            lights.selection_pmf(l) * lights.pdf_area(l, h.p, n.p, n.ns);
                    }
                }
            }
        }
        if adds_direct && tech.emitted != Vec3::ZERO {
            let w = if bs.delta {
                1.0
            } else {
                st.mis.weight(bs.pdf, tech.pdf_light)
            };
            radiance += beta * tech.emitted * w;
        }
        if reports::<O>(controls) {
            report(observer, controls, &mut radiance, &record(Some(tech)));
        }
        if zero_weight_trace {
            break;
        }
        match next {
            Some(n) => h = n,
            None => break,
        }
    }
    out.radiance = radiance;
    out
}

/// Whether `trace` hands the vertex to the observer: every vertex it controls, and the
/// others when it [sees them](VertexObserver::SEES_UNCONTROLLED).
#[inline(always)]
fn reports<O: VertexObserver>(controls: bool) -> bool {
    controls || O::SEES_UNCONTROLLED
}

/// Hands a vertex record to the observer; a controlling observer's contribution is added.
#[inline]
fn report<O: VertexObserver>(
    observer: &mut O,
    controls: bool,
    radiance: &mut Vec3,
    record: &VertexRecord,
) {
    if controls {
        *radiance += observer.controlled_vertex(record);
    } else {
        observer.vertex(record);
    }
}

/// One sample of pixel `(x, y)`: camera ray through a uniformly sampled point of the pixel,
/// then [`trace`] with the plain observer.
#[inline]
pub fn sample_pixel(
    rs: &RenderScene,
    st: &RenderSettings,
    x: u32,
    y: u32,
    sample_index: u32,
) -> PathSample {
    let mut sampler = Sampler::of_kind(
        st.sampler,
        st.seed,
        y.wrapping_mul(rs.width).wrapping_add(x),
        sample_index,
    );
    let ray = camera_ray(rs, &mut sampler, x, y);
    trace(rs, st, ray, &mut sampler, &mut super::NoObserver)
}

/// The camera ray of a sample of pixel `(x, y)` through a uniformly sampled point of the
/// pixel: the first two dimensions of the sample's fresh `sampler`. Every estimator starts
/// its pixel samples with it, so that they share their camera rays.
#[inline(always)]
pub fn camera_ray(rs: &RenderScene, sampler: &mut Sampler, x: u32, y: u32) -> Ray {
    let u = sampler.first_2d();
    rs.camera.ray(Vec2::new(x as f32 + u.x, y as f32 + u.y))
}
