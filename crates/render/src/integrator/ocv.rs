//! `ocv` — Optimizing Control Variates for the direct-lighting gather [Fan 2006].
//!
//! At every scattering vertex the direct illumination `∫ f(wo, wi) |cos θi| Le(wi) V dwi` is
//! estimated from `spe` samples drawn by **deterministic mixture sampling** [Fan §4]: component
//! `j` (the BSDF, then one per light) gets exactly `n_j ≈ spe·α_j` samples
//! ([`estimators::mis::deterministic_counts`]), `α_BSDF = bsdf_share` and the rest split
//! equally among the light components [Fan §5.1]. The samples are fitted by penalised least
//! squares with an intercept, dropping the last component [Fan eq. 9–11]
//! ([`estimators::ocv::ocv_estimate`]), and the vertex estimate is `β0 + Σ β_j` [Fan eq. 10].
//! With `optimize: false` the estimate is the plain deterministic-mixture (balance heuristic)
//! estimate [Fan eq. 6] — Fan's "MIS" column of Table 1 — from the very same samples.
//!
//! Global illumination continues as in `path`: one BSDF-sampled direction per vertex (same
//! sampler dimensions, same Russian roulette). Emission found by that continuation ray is
//! **not** added after a vertex that gathered (the gather already integrated it); it is added
//! with weight 1 at the camera hit and after a delta (conductor) vertex, where no gather runs.
//!
//! # Parameters (`estimator.kind = "ocv"`)
//! Options (defaults, ranges, meaning): the table of [`OcvOptions`] (defined once, in
//! `estimators::spec`, for the CLI, the farm's API and the renderer).
//!
//! ```json
//! { "estimator": { "kind": "ocv", "spe": 64, "lambda": 1.0, "bsdf_share": 0.5 }, "max_depth": 2 }
//! ```
//!
//! # Measures and the mixture density
//! All densities are solid-angle densities at the shading point, in **path space**: a sample
//! is the point its ray reaches first. A light sample whose shadow ray is blocked is a point
//! on the light the BSDF technique cannot produce (`p_BSDF = 0` there); a BSDF sample that
//! hits light `k` has density `p_k` = light `k`'s sampling density of that point, and 0 for
//! every other light (lights overlapping as seen from the vertex are thereby handled
//! exactly). A failed draw (BSDF sample below the surface, back side of a one-sided light) is
//! the component's "null point": value 0, density 1 for its own component and 0 for the
//! others, so that every component density integrates to one and eq. 7 stays unbiased.
//!
//! # Choosing `path` or the gather
//! A gather costs `spe` samples at every vertex, and where the direct light is not what makes
//! the image noisy (indirect light in a closed room, `path`'s MIS already good) that cost buys
//! nothing: the fit's promise is to regress to the baseline. With `min_speedup` set (default
//! 1.2) a **pilot** ([`choose`]) decides per job whether the gather runs at all; if not, the
//! job renders `path`'s image (same sampler dimensions, same bits). The pilot renders one
//! pixel in [`PILOT_STEP`]² (at least [`MIN_PILOT_PIXELS`] on a small image: [`pilot_step`])
//! with both estimators, twice, from two seeds of its own, half the
//! job's samples each: half the squared difference of the two is the error of a half-budget
//! image with the sampler's stratification in it. (A pilot of a few samples per pixel, or
//! the i.i.d. variance of its samples, does not predict the gather's gain: the gather's
//! consecutive stratified points converge much faster than its first few samples say — on
//! `checkers` such a pilot predicted 0.6–1.5× where the image gained 10–50× at equal
//! samples, `docs/bench/README.md`.) It predicts the equal-time speedup
//! `(E_path · C_path) / (E_ocv · C_ocv)` from the relative errors `E = Σ_pixels Σ_c d_c² / 2 /
//! (m_c² + ε)` (ε = 0.01 as in the benches' relMSE) and the rays `C` each traced (an `ocv` ray
//! weighted by `OCV_RAY_COST`, measured). Each pixel's `d²` is one or a few degrees of
//! freedom, so a pilot of few pixels is noisy: the prediction less one jackknife standard
//! error over the pixels (`Choice::speedup_low`) is what must reach `min_speedup`. A wrong
//! `path` loses the gather's gain; a wrong gather can cost 4× (Cornell box: 0.24×).
//!
//! **Pixels that see emitters.** Where the camera sees small bright emitters, the image's
//! error can sit in the few pixels a lamp partly covers. There it is the error of the
//! camera-hit emission (which part of the pixel the camera samples find the lamp in), the
//! same for both estimators, and a lattice of 64 pixels usually holds none of those pixels
//! (a room of 256 lamps, 128×128: 60 % of the gather's error in 0.5 % of the pixels, the
//! lattice's prediction 0.9–2.7× where the image got 0.65×). So the pilot estimates that
//! shared part apart, as a difference estimator: the pixels whose square may hold part of a
//! finite emitter ([`emitter_pixels`]: projected triangles and spheres, occlusion ignored)
//! get an **emission pass** of the camera-hit emission alone (one ray per sample, up to
//! one pixel in [`EMISSION_PASS_SHARE`] of the image, evenly spread over them), whose scaled
//! sum is added to both estimators' errors; the lattice's pixels among them count their
//! error less the same emission error from their own samples. The jackknife is the
//! stratified one (lattice and pass, each left out pixel by pixel).
//!
//! The choice is a pure function of the job (its seed
//! and spp included), the same for any tile size, sample range, thread or worker; it is
//! independent of the image's own samples, which stay unbiased given it. Its cost: about
//! `(1 + 1.2 r) / PILOT_STEP²` of the job, `r` the gather's cost over `path`'s (≈ 1 % at
//! `r` = 4; 1.5–2.1 % measured on 128×128 images, where the pilot takes 64 pixels), plus
//! the emission pass (0.5–1 %). The lattice is measured in chunks of [`PILOT_CHUNK`] pixels
//! in a fixed pseudo-random order; from half of it on, a prediction whose upper
//! two-standard-error bound is below `min_speedup` stops the pilot (`path`): where the gather
//! clearly cannot pay (a room of 256 lamps at depth 5, the Cornell box) that halves its cost.
//! [`RenderScene::ocv_choice`] makes it once per prepared scene and settings: a local render
//! runs it once on all threads before its tiles, a farm worker once per job
//! (its first task). A time-budget render (`cvfarm render --time-budget`) sizes it by the
//! settings' `spp`.
//!
//! # Sampler
//! The continuation uses `path`'s per-vertex dimensions. Gather sample `i` of component `j`
//! at vertex `d` is point `spp_index · n_j + i` of a sequence seeded by `(seed, d, j)`, so the
//! `n_j` samples of one estimate are consecutive (stratified) points.

use glam::{Vec2, Vec3};

use super::path::{self, PathSample, camera_hit, vertex_dimension};
use super::{RenderScene, RenderSettings};
use crate::accel::Hit;
use crate::bsdf::Bsdf;
use crate::math::{Frame, Ray};
use crate::sampler::Sampler;
use estimators::ocv::MIN_SAMPLES_PER_COMPONENT;

pub use estimators::spec::OcvOptions;

/// What the gather draws its samples from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Component {
    /// BSDF sampling.
    Bsdf,
    /// Sampling light `k` alone (pdf excludes the selection pmf).
    Light(u32),
    /// All lights by the light selection (pdf includes the pmf).
    AllLights,
}

/// The gather's component layout for one job and its buffers, reused across vertices, camera
/// samples and pixels (one per tile renderer; [`Scratch::new`] once, then no allocation).
#[derive(Default)]
pub struct Scratch {
    /// Active components (count > 0).
    components: Vec<(Component, usize)>,
    /// Light → column in the pdf table (per-light mode), `usize::MAX` if inactive.
    light_column: Vec<usize>,
    values: Vec<[f64; 3]>,
    pdfs: Vec<f64>,
    mixture: Vec<f64>,
    /// The OCV fit's buffers.
    solver: estimators::ocv::OcvSolver,
}

/// splitmix64 finaliser.
#[inline]
fn mix64(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

impl Scratch {
    /// Sets up the components and their deterministic counts for this scene and options.
    pub fn new(rs: &RenderScene, opts: &OcvOptions) -> Self {
        let mut s = Scratch::default();
        let n_lights = rs.lights.len();
        if n_lights == 0 {
            return s;
        }
        // One component per light only when the gather can give each of them, and the BSDF,
        // the samples a fit needs (`MIN_SAMPLES_PER_COMPONENT`): else a light would get none
        // (reached by BSDF hits alone) or too few, and all lights form one component sampled
        // by the light selection, as with more lights than `max_light_components` [Fan §7].
        let per_light = n_lights <= opts.max_light_components as usize
            && opts.spe as usize >= MIN_SAMPLES_PER_COMPONENT * (n_lights + 1);
        let mut comps = vec![Component::Bsdf];
        let mut weights = vec![opts.bsdf_share];
        let light_share = 1.0 - opts.bsdf_share;
        if per_light {
            for k in 0..n_lights {
                comps.push(Component::Light(k as u32));
                weights.push(light_share / n_lights as f64);
            }
        } else {
            comps.push(Component::AllLights);
            weights.push(light_share);
        }
        let counts = estimators::mis::deterministic_counts(&weights, opts.spe.max(1) as usize)
            .unwrap_or_else(|| vec![0; weights.len()]);
        s.light_column = vec![usize::MAX; n_lights];
        for (c, n) in comps.into_iter().zip(counts) {
            if n > 0 {
                if let Component::Light(k) = c {
                    s.light_column[k as usize] = s.components.len();
                }
                s.components.push((c, n));
            }
        }
        let total: usize = s.components.iter().map(|c| c.1).sum();
        s.mixture = s
            .components
            .iter()
            .map(|c| c.1 as f64 / total.max(1) as f64)
            .collect();
        s
    }

    /// Column of the pdf table that light `k` contributes to, if its component is active.
    #[inline]
    fn column_of_light(&self, k: u32) -> Option<usize> {
        match self
            .components
            .iter()
            .position(|c| c.0 == Component::AllLights)
        {
            Some(col) => Some(col),
            None => self
                .light_column
                .get(k as usize)
                .copied()
                .filter(|&c| c != usize::MAX),
        }
    }
}

/// One deterministic-mixture gather at hit `h` with local outgoing direction `wo`: the OCV
/// (or plain) estimate of the reflected direct illumination (not multiplied by the path
/// throughput). Also returns the rays traced. `None` when no sample was valid.
#[allow(clippy::too_many_arguments)]
fn gather(
    rs: &RenderScene,
    st: &RenderSettings,
    opts: &OcvOptions,
    scratch: &mut Scratch,
    h: &Hit,
    bsdf: &Bsdf,
    frame: &Frame,
    wo: Vec3,
    depth: u32,
    pixel: u32,
    sample_index: u32,
) -> (Option<Vec3>, u32) {
    let lights = &rs.lights;
    let m = scratch.components.len();
    let mut rays = 0u32;
    scratch.values.clear();
    scratch.pdfs.clear();
    for j in 0..m {
        let (comp, n_j) = scratch.components[j];
        let seed = st.seed ^ mix64(0x0cf5_0000 ^ (u64::from(depth) << 32) ^ j as u64);
        for i in 0..n_j {
            let index = sample_index.wrapping_mul(n_j as u32).wrapping_add(i as u32);
            let mut sampler = Sampler::of_kind(st.sampler, seed, pixel, index);
            let u0 = sampler.next_1d();
            let u = sampler.next_2d();
            let row = scratch.pdfs.len();
            scratch.pdfs.resize(row + m, 0.0);
            let mut value = Vec3::ZERO;
            match comp {
                Component::Bsdf => match bsdf.sample(wo, u0, u) {
                    None => scratch.pdfs[row + j] = 1.0, // null point of the BSDF
                    Some(bs) => {
                        scratch.pdfs[row + j] = f64::from(bs.pdf);
                        let wi = frame.to_world(bs.wi);
                        let ray = h.spawn_ray(wi);
                        match reach(rs, h, &ray, &mut rays) {
                            Reach::Blocked => {}
                            Reach::Escaped => {
                                let le = lights.env_radiance(wi);
                                if let Some(l) = lights.env_light() {
                                    value = bs.weight * bs.pdf * le;
                                    if let Some(col) = scratch.column_of_light(l) {
                                        scratch.pdfs[row + col] += light_pdf(
                                            rs,
                                            comp_of(scratch, col),
                                            l,
                                            lights.pdf_env(wi),
                                        );
                                    }
                                }
                            }
                            Reach::Emitter(n, l) => {
                                value = bs.weight * bs.pdf * lights.area_radiance(l, n.ns, -wi);
                                if let Some(col) = scratch.column_of_light(l) {
                                    scratch.pdfs[row + col] += light_pdf(
                                        rs,
                                        comp_of(scratch, col),
                                        l,
                                        lights.pdf_area(l, h.p, n.p, n.ns),
                                    );
                                }
                            }
                        }
                    }
                },
                Component::Light(_) | Component::AllLights => {
                    let ls = match comp {
                        Component::Light(k) => lights.sample_light(k, h.p, u),
                        _ => lights.sample(h.p, u0, u),
                    };
                    match ls {
                        Some(ls) if ls.pdf > 0.0 && ls.pdf.is_finite() => {
                            scratch.pdfs[row + j] = f64::from(ls.pdf);
                            let (f, pdf_bsdf) = bsdf.eval_pdf(wo, frame.to_local(ls.wi));
                            if f != Vec3::ZERO || pdf_bsdf > 0.0 {
                                let shadow = if ls.dist.is_finite() {
                                    h.spawn_ray_to(h.p + ls.wi * ls.dist)
                                } else {
                                    h.spawn_ray(ls.wi)
                                };
                                rays += 1;
                                // Blocked: a point on the light the BSDF technique cannot
                                // reach (p_BSDF = 0), value 0.
                                if !rs.accel.occluded(shadow.o, shadow.d, shadow.t_max) {
                                    value = f * ls.radiance;
                                    if let Some(col) = scratch
                                        .components
                                        .iter()
                                        .position(|c| c.0 == Component::Bsdf)
                                    {
                                        scratch.pdfs[row + col] = f64::from(pdf_bsdf);
                                    }
                                }
                            }
                        }
                        _ => scratch.pdfs[row + j] = 1.0, // null point of this light component
                    }
                }
            }
            scratch.values.push(value.to_array().map(f64::from));
        }
    }
    if scratch.values.is_empty() {
        return (None, rays);
    }
    let est = if opts.optimize {
        let o = estimators::ocv::OcvOptions {
            lambda: opts.lambda,
            penalize_intercept: opts.penalize_intercept,
            ..estimators::ocv::OcvOptions::default()
        };
        scratch
            .solver
            .fit(&scratch.values, &scratch.pdfs, &scratch.mixture, &o)
            .ok()
            .map(|r| r.estimate)
    } else {
        plain_estimate(&scratch.values, &scratch.pdfs, &scratch.mixture)
    };
    let est = est.map(|e| Vec3::new(e[0] as f32, e[1] as f32, e[2] as f32));
    (est.filter(|e| e.is_finite()), rays)
}

/// The component at pdf-table column `col`.
#[inline]
fn comp_of(scratch: &Scratch, col: usize) -> Component {
    scratch.components[col].0
}

/// What a gather's BSDF ray reaches first, as far as the gather needs to know.
enum Reach {
    /// Nothing: the environment (if any) is seen.
    Escaped,
    /// Area light `l` at this hit.
    Emitter(Hit, u32),
    /// A surface that does not emit.
    Blocked,
}

/// What `ray` (from `h`) reaches first; counts the rays traced into `rays`. The emitter comes
/// from [`RenderScene::emitters`] (`None`: the scene has no area emitter), so a ray that
/// reaches no emitter needs no search of the scene, and one that does needs a shadow test of
/// the segment to it (the next-event convention, [`Hit::spawn_ray_to`]) instead of a
/// closest-hit search: most of a gather's BSDF samples miss the lights.
fn reach(rs: &RenderScene, h: &Hit, ray: &Ray, rays: &mut u32) -> Reach {
    *rays += 1;
    match rs.emitters.as_ref().and_then(|e| e.intersect(ray)) {
        Some(n) => {
            // Every shape of `emitters` emits.
            let Some(l) = n.light else {
                return Reach::Blocked;
            };
            let shadow = h.spawn_ray_to(n.p);
            *rays += 1;
            if rs.accel.occluded(shadow.o, shadow.d, shadow.t_max) {
                Reach::Blocked
            } else {
                Reach::Emitter(n, l)
            }
        }
        None if rs.lights.env_light().is_some() => {
            *rays += 1;
            if rs.accel.occluded(ray.o, ray.d, ray.t_max) {
                Reach::Blocked
            } else {
                Reach::Escaped
            }
        }
        None => Reach::Blocked,
    }
}

/// Density of component `comp` for a point on light `l` whose per-light solid-angle pdf
/// (excluding selection) is `pdf`.
#[inline]
fn light_pdf(rs: &RenderScene, comp: Component, l: u32, pdf: f32) -> f64 {
    match comp {
        Component::AllLights => f64::from(rs.lights.selection_pmf(l) * pdf),
        _ => f64::from(pdf),
    }
}

/// Deterministic-mixture (balance heuristic) estimate `mean(f/p)` [Fan eq. 6].
fn plain_estimate(values: &[[f64; 3]], pdfs: &[f64], mixture: &[f64]) -> Option<[f64; 3]> {
    let m = mixture.len();
    let mut sum = [0.0; 3];
    let mut n = 0usize;
    for (v, row) in values.iter().zip(pdfs.chunks_exact(m)) {
        let p: f64 = row.iter().zip(mixture).map(|(a, b)| a * b).sum();
        if p > 0.0 && p.is_finite() {
            for c in 0..3 {
                sum[c] += v[c] / p;
            }
            n += 1;
        }
    }
    (n > 0).then(|| sum.map(|s| s / n as f64))
}

/// Traces one camera path with OCV direct lighting at each vertex (see the module docs).
/// `scratch` is [`Scratch::new`] of the same scene and options.
#[allow(clippy::too_many_arguments)]
pub fn trace(
    rs: &RenderScene,
    st: &RenderSettings,
    opts: &OcvOptions,
    scratch: &mut Scratch,
    camera_ray: Ray,
    sampler: &mut Sampler,
    pixel: u32,
    sample_index: u32,
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
    loop {
        let bsdf = rs.materials.bsdf(h.material, h.uv);
        if depth == 0 {
            out.albedo = bsdf.albedo();
            out.normal = h.ns;
        }
        if depth.saturating_add(1) >= max_depth {
            break;
        }
        let frame = Frame::from_normal(h.ns);
        let wo = frame.to_local(-ray.d);
        let gathered = !bsdf.is_delta() && !scratch.components.is_empty();
        if gathered {
            let (est, rays) = gather(
                rs,
                st,
                opts,
                scratch,
                &h,
                &bsdf,
                &frame,
                wo,
                depth,
                pixel,
                sample_index,
            );
            out.rays += rays;
            if let Some(e) = est {
                radiance += beta * e;
            }
        }

        // ---- continuation: one BSDF sample, as in `path` ----
        sampler.set_dimension(vertex_dimension(depth) + 3);
        let u_lobe = sampler.next_1d();
        let u_bsdf: Vec2 = sampler.next_2d();
        let u_rr = sampler.next_1d();
        let Some(bs) = bsdf.sample(wo, u_lobe, u_bsdf) else {
            break;
        };
        let wi = frame.to_world(bs.wi);
        beta *= bs.weight;
        depth += 1;
        let beta_max = beta.max_element();
        if !(beta_max > 0.0 && beta.is_finite()) {
            break;
        }
        if depth as i64 >= i64::from(st.rr_depth) {
            let q = beta_max.min(0.95);
            if u_rr < q {
                beta /= q;
            } else {
                break;
            }
        }
        // After a gather the emission reached by the continuation is already integrated;
        // after a delta vertex it is counted here with weight 1.
        let count_emission = !gathered;
        if !count_emission && depth.saturating_add(1) >= max_depth {
            // The next vertex would neither scatter nor count emission: no ray needed.
            break;
        }
        ray = h.spawn_ray(wi);
        out.rays += 1;
        match rs.accel.intersect(&ray) {
            None => {
                if count_emission {
                    radiance += beta * lights.env_radiance(wi);
                }
                break;
            }
            Some(n) => {
                if count_emission && let Some(l) = n.light {
                    radiance += beta * lights.area_radiance(l, n.ns, -wi);
                }
                h = n;
            }
        }
    }
    out.radiance = radiance;
    out
}

/// One sample of pixel `(x, y)` with the `ocv` estimator (`scratch` as in [`trace`]).
#[inline]
pub fn sample_pixel(
    rs: &RenderScene,
    st: &RenderSettings,
    opts: &OcvOptions,
    scratch: &mut Scratch,
    x: u32,
    y: u32,
    sample_index: u32,
) -> PathSample {
    let pixel = y * rs.width + x;
    let mut sampler = Sampler::of_kind(st.sampler, st.seed, pixel, sample_index);
    let ray = path::camera_ray(rs, &mut sampler, x, y);
    trace(
        rs,
        st,
        opts,
        scratch,
        ray,
        &mut sampler,
        pixel,
        sample_index,
    )
}

/// Pilot pixels sit at the centre of each `step × step` square of the image; the step is
/// `PILOT_STEP` unless that leaves fewer than [`MIN_PILOT_PIXELS`] pixels ([`pilot_step`]).
pub const PILOT_STEP: u32 = 24;

/// The fewest pixels a pilot takes (as far as the image has them). With 25 (a 128×128 image
/// at `PILOT_STEP`) the prediction spread over job seeds from 0.35× to 2.6× on Mitsuba's
/// `manylights-4` (measured: `cv_measure::ocv_pilot_choices`, `CV_PILOT_SEEDS`).
pub const MIN_PILOT_PIXELS: u32 = 64;

/// Cost of one of `ocv`'s rays in units of one of `path`'s: a gather's samples also evaluate
/// the BSDF and the fit. Measured (`cvfarm render`, 8 spp, 1 thread, `path`'s Mrays/s over
/// `ocv`'s): checkers d2 1.23, colour-lamp d5 1.14, veach-mis d5 1.33, cornell-box d5 1.18,
/// many-lights d5 1.13, envmap d5 0.89.
const OCV_RAY_COST: f64 = 1.2;

/// Which pixels (row-major) may see a finite emitter directly: those whose square holds
/// part of the projection of an emitter's hull ([`crate::light::Lights::for_each_emitter_hull`];
/// occlusion ignored, so a superset). A hull reaching into or behind the camera's plane may
/// cover any pixel: then every pixel is marked.
pub fn emitter_pixels(rs: &RenderScene) -> Vec<bool> {
    let (w, h) = (rs.width as usize, rs.height as usize);
    let mut seen = vec![false; w * h];
    let mut everywhere = false;
    rs.lights.for_each_emitter_hull(|pts| {
        if everywhere {
            return;
        }
        let (mut lo, mut hi) = (Vec2::splat(f32::INFINITY), Vec2::splat(f32::NEG_INFINITY));
        for &p in pts {
            let Some(f) = rs.camera.film_position(p) else {
                everywhere = true;
                return;
            };
            lo = lo.min(f);
            hi = hi.max(f);
        }
        // Pixel `x` covers film positions `[x, x + 1)`; a little slack for rounding.
        const SLACK: f32 = 1e-3;
        let span = |a: f32, b: f32, n: usize| {
            let first = (a - SLACK).floor().max(0.0);
            let last = (b + SLACK).floor().min(n as f32 - 1.0);
            (first <= last).then_some((first as usize, last as usize))
        };
        if let (Some((x0, x1)), Some((y0, y1))) = (span(lo.x, hi.x, w), span(lo.y, hi.y, h)) {
            for row in seen[y0 * w..=y1 * w + x1].chunks_mut(w) {
                for px in row.iter_mut().take(x1 + 1).skip(x0) {
                    *px = true;
                }
            }
        }
    });
    if everywhere {
        seen.fill(true);
    }
    seen
}

/// The pilot's lattice ([`pilot_pixels`]): its pixels measured whole, less their camera-hit
/// emission where they may see an emitter.
const LATTICE: usize = 0;
/// The emission pass ([`pilot_pixels`]): pixels that may see an emitter, their camera-hit
/// emission alone.
const EMISSION: usize = 1;

/// A pilot pixel `(x, y)`, its stratum ([`LATTICE`] or [`EMISSION`]) and whether it may see
/// an emitter.
type PilotSite = (u32, u32, usize, bool);

/// The pilot's pixels, each with its stratum ([`LATTICE`] or [`EMISSION`]), whether it may
/// see an emitter ([`emitter_pixels`]), and the strata. The lattice of [`pilot_step`] is
/// measured whole; where the camera may see emitters, the emission pass adds up to one in
/// [`EMISSION_PASS_SHARE`] of the image's pixels, evenly spaced in raster order over those
/// that may see one (all of them if there are no more). With fewer than two such pixels
/// there is no pass.
fn pilot_pixels(rs: &RenderScene) -> (Vec<PilotSite>, Vec<Stratum>) {
    let (w, h) = (rs.width, rs.height);
    let step = pilot_step(w, h);
    let all = u64::from(w) * u64::from(h);
    let seen = emitter_pixels(rs);
    let mut pixels: Vec<PilotSite> = (0..h)
        .flat_map(|y| (0..w).map(move |x| (x, y)))
        .filter(|&(x, y)| is_pilot_pixel(x, y, step))
        .map(|(x, y)| (x, y, LATTICE, seen[(y * w + x) as usize]))
        .collect();
    let marked: Vec<u32> = (0..w * h).filter(|&i| seen[i as usize]).collect();
    let mut strata = vec![Stratum::new(all as f64)];
    if marked.len() >= 2 {
        let n = (all / EMISSION_PASS_SHARE).max(2) as usize;
        let k = marked.len().div_ceil(n);
        pixels.extend(
            marked
                .iter()
                .skip(k / 2)
                .step_by(k)
                .map(|&i| (i % w, i / w, EMISSION, true)),
        );
        strata.push(Stratum::new(marked.len() as f64));
    }
    (pixels, strata)
}

/// One stratum of the pilot's pixels: its pixel count in the image and, once measured, its
/// pilot pixels' count and sums.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Stratum {
    /// Pixels of the image in the stratum.
    population: f64,
    /// Pilot pixels in it.
    count: usize,
    /// Σ over its pilot pixels of each estimator's error.
    var: [f64; 2],
    /// Σ over its pilot pixels of each estimator's rays.
    rays: [f64; 2],
}

impl Stratum {
    fn new(population: f64) -> Self {
        Self {
            population,
            count: 0,
            var: [0.0; 2],
            rays: [0.0; 2],
        }
    }

    /// Pixels of the image per pilot pixel.
    fn weight(&self) -> f64 {
        self.population / self.count.max(1) as f64
    }
}

/// The emission pass takes at most one in this many of the image's pixels
/// ([`pilot_pixels`]): its rays, one per sample, stay below 1/32 of the job's camera rays
/// (0.5–1 % of a job's time measured at depths 2–5).
pub const EMISSION_PASS_SHARE: u64 = 32;

/// The camera-hit emission of pixel `(x, y)`'s samples `0..n` under `st` (the part of
/// every estimator's sample its camera ray alone decides: [`path::camera_hit`]), averaged;
/// non-finite values count as zero, as the film counts them.
fn camera_emission(rs: &RenderScene, st: &RenderSettings, x: u32, y: u32, n: u32) -> [f64; 3] {
    let mut mean = [0.0f64; 3];
    for s in 0..n {
        let mut sampler = Sampler::of_kind(st.sampler, st.seed, y * rs.width + x, s);
        let ray = path::camera_ray(rs, &mut sampler, x, y);
        let mut out = PathSample::default();
        let e =
            camera_hit(rs, st, ray, &mut out).map_or(out.radiance, |(_, _, e)| e + out.radiance);
        let e = if e.is_finite() { e } else { Vec3::ZERO };
        for (m, v) in mean.iter_mut().zip(e.to_array()) {
            *m += f64::from(v) / f64::from(n);
        }
    }
    mean
}

/// The relative weights `1/(m² + ε)` of a pixel whose channels' means are `mean` (ε as the
/// benches' relMSE).
fn relative_weights(mean: [f64; 3]) -> [f64; 3] {
    mean.map(|m| 1.0 / (m * m + estimators::metrics::REL_MSE_EPSILON))
}

/// A pixel's relative error from its two randomisations' means `a` and `b`: half their
/// squared difference per channel times the channel's `weight` ([`relative_weights`]),
/// summed over the channels.
fn relative_error(a: [f64; 3], b: [f64; 3], weight: [f64; 3]) -> f64 {
    (0..3)
        .map(|c| 0.5 * (a[c] - b[c]).powi(2) * weight[c])
        .sum()
}

/// Mixed into the job's seed for the pilot's two randomisations.
const PILOT_SEED: u64 = 0x7069_6c6f_7400_0001;

/// The pilot's lattice step for a `width × height` image: the largest step ≤ `PILOT_STEP`
/// whose lattice has [`MIN_PILOT_PIXELS`] pixels (1 if none has).
pub fn pilot_step(width: u32, height: u32) -> u32 {
    let count = |step: u32| {
        let along = |n: u32| n.saturating_sub(step / 2).div_ceil(step);
        along(width) * along(height)
    };
    (1..=PILOT_STEP)
        .rev()
        .find(|&step| count(step) >= MIN_PILOT_PIXELS)
        .unwrap_or(1)
}

/// Whether pixel `(x, y)` takes part in a pilot of lattice `step` ([`pilot_step`]).
#[inline]
pub fn is_pilot_pixel(x: u32, y: u32, step: u32) -> bool {
    x % step == step / 2 && y % step == step / 2
}

/// What the pilot measured and chose (see the module docs, "Choosing `path` or the gather").
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Choice {
    /// Predicted equal-time speedup of `ocv` over `path` (`+∞` if `ocv`'s pilot estimates
    /// did not vary and `path`'s did; `NaN` if neither varied or no pilot ran).
    pub speedup: f64,
    /// The prediction less one standard error: `speedup · exp(−σ)`, σ the jackknife standard
    /// error of `ln speedup` over the pilot's pixels (an infinite prediction stays infinite).
    /// This is what meets `min_speedup`.
    pub speedup_low: f64,
    /// Render the job with `ocv`'s gather (else as `path`).
    pub use_ocv: bool,
    /// Rays the pilot traced.
    pub rays: u64,
}

/// The pilot's squared differences of one pixel (per estimator, relative), its rays and its
/// stratum.
struct PilotPixel {
    var: [f64; 2],
    /// Each estimator's rays (none in the emission pass: not the estimators' cost).
    rays: [u64; 2],
    /// Rays the pilot traced for the pixel.
    traced: u64,
    stratum: usize,
}

/// The strata's scaled sums: the image's estimated error of each estimator.
fn stratified_totals(strata: &[Stratum]) -> [f64; 2] {
    [0, 1].map(|e| strata.iter().map(|s| s.weight() * s.var[e]).sum())
}

/// Stratified jackknife standard error of `ln(T_path / T_ocv)`, `T` the strata's scaled
/// sums ([`stratified_totals`]): each pilot pixel left out in turn, its stratum's sum
/// rescaled to the stratum's other pixels, the squared deviations of stratum `h` weighed
/// `(n_h − 1)/n_h` (the delete-one jackknife for stratified samples). `+∞` if a stratum has
/// fewer than two pilot pixels or a single pixel holds all of either estimator's sum; with one
/// stratum it is the plain delete-one jackknife.
fn jackknife_log_ratio_se(measured: &[PilotPixel], strata: &[Stratum]) -> f64 {
    if strata.is_empty() || strata.iter().any(|s| s.count < 2) {
        return f64::INFINITY;
    }
    let total = stratified_totals(strata);
    let mut var = 0.0;
    for (h, st) in strata.iter().enumerate() {
        let n = st.count as f64;
        let scale = st.population / (n - 1.0);
        let loo: Vec<f64> = measured
            .iter()
            .filter(|m| m.stratum == h)
            .map(|m| {
                let t = [0, 1]
                    .map(|e| total[e] - st.weight() * st.var[e] + scale * (st.var[e] - m.var[e]));
                (t[0] / t[1]).ln()
            })
            .collect();
        if loo.iter().any(|l| !l.is_finite()) {
            return f64::INFINITY;
        }
        let mean = loo.iter().sum::<f64>() / n;
        var += loo.iter().map(|l| (l - mean).powi(2)).sum::<f64>() * (n - 1.0) / n;
    }
    var.sqrt()
}

/// `speedup · exp(−se)`, the prediction less one standard error of its log. A finite
/// prediction of unknown error (`se` = ∞) falls to 0, which only `min_speedup` 0 accepts; an
/// infinite one (the gather's pilot estimates never varied, `path`'s did) stays infinite.
fn less_one_se(speedup: f64, se: f64) -> f64 {
    if speedup.is_infinite() {
        speedup
    } else {
        speedup * (-se).exp()
    }
}

/// Runs the pilot of a job (`st` with the `ocv` options `opts`) and chooses under
/// `opts.min_speedup` (see the module docs). With `min_speedup` `None` no pilot runs and the
/// job uses the gather. The pilot's pixels run on the current rayon pool and are summed in
/// pixel order, so the choice is the same for any thread count.
pub fn choose(rs: &RenderScene, st: &RenderSettings, opts: &OcvOptions) -> Choice {
    use rayon::prelude::*;
    let Some(min_speedup) = opts.min_speedup else {
        return Choice {
            speedup: f64::NAN,
            speedup_low: f64::NAN,
            use_ocv: true,
            rays: 0,
        };
    };
    // Two randomisations per job seed, disjoint from every other job seed's.
    let pilots = [0u64, 1].map(|r| RenderSettings {
        seed: mix64(mix64(st.seed ^ PILOT_SEED).wrapping_add(r)),
        ..*st
    });
    // Each randomisation takes half the job's samples: the difference of the two is the
    // error of a half-budget image, with the sampler's stratification in it at (about) the
    // job's own sample count.
    let half = (st.spp / 2).max(1);
    let (pixels, strata) = pilot_pixels(rs);
    // The emission pass first, then the lattice in a fixed pseudo-random order, a chunk at a
    // time: once half of it is measured, a prediction whose upper two-standard-error bound
    // is still below `min_speedup` stops the pilot (`path`). The chunks and their order
    // depend on the job alone, so the choice does on any thread count.
    let (mut lattice, pass): (Vec<PilotSite>, Vec<PilotSite>) =
        pixels.into_iter().partition(|p| p.2 == LATTICE);
    lattice.sort_by_key(|&(x, y, ..)| mix64(u64::from(y * rs.width + x) ^ PILOT_SEED));
    let measure = |sites: &[PilotSite]| -> Vec<PilotPixel> {
        sites
            .par_iter()
            .map_init(
                || Scratch::new(rs, opts),
                |scratch, site| measure_pixel(rs, &pilots, opts, scratch, half, site),
            )
            .collect()
    };
    let mut measured = measure(&pass);
    let mut done = 0;
    loop {
        let chunk = &lattice[done..(done + PILOT_CHUNK).min(lattice.len())];
        measured.extend(measure(chunk));
        done += chunk.len();
        let c = prediction(&measured, &strata, min_speedup);
        let hopeless = c.choice.speedup * (2.0 * c.log_se).exp() < min_speedup;
        if done >= lattice.len() || (2 * done >= lattice.len() && hopeless) {
            return c.choice;
        }
    }
}

/// How many lattice pixels the pilot measures between its checks ([`choose`]).
pub const PILOT_CHUNK: usize = 32;

/// A pilot's prediction from the pixels measured so far ([`choose`]).
struct Prediction {
    choice: Choice,
    /// The jackknife standard error of the log of `choice.speedup`.
    log_se: f64,
}

/// The prediction and choice from `measured` (each stratum of `strata` scaled by its pixels
/// over its measured pixels).
fn prediction(measured: &[PilotPixel], strata: &[Stratum], min_speedup: f64) -> Prediction {
    let mut strata = strata.to_vec();
    let mut traced = 0u64;
    for m in measured {
        let s = &mut strata[m.stratum];
        s.count += 1;
        for e in 0..2 {
            s.var[e] += m.var[e];
            s.rays[e] += m.rays[e] as f64;
        }
        traced += m.traced;
    }
    let var = stratified_totals(&strata);
    let rays = [0, 1].map(|e| strata.iter().map(|s| s.weight() * s.rays[e]).sum::<f64>());
    let cost = rays[0] / (rays[1] * OCV_RAY_COST);
    let speedup = var[0] / var[1] * cost;
    let log_se = jackknife_log_ratio_se(measured, &strata);
    let speedup_low = less_one_se(speedup, log_se);
    Prediction {
        choice: Choice {
            speedup,
            speedup_low,
            // NaN (nothing varied): the cheaper `path`.
            use_ocv: speedup_low >= min_speedup,
            rays: traced,
        },
        log_se,
    }
}

/// Measures one pilot pixel ([`PilotSite`]) with the two randomisations `pilots` of `half`
/// samples each: both estimators' relative squared differences (less the camera-hit
/// emission's where the pixel may see an emitter), or for the emission pass that emission's
/// error alone.
fn measure_pixel(
    rs: &RenderScene,
    pilots: &[RenderSettings; 2],
    opts: &OcvOptions,
    scratch: &mut Scratch,
    half: u32,
    &(x, y, stratum, sees_emitter): &PilotSite,
) -> PilotPixel {
    // The emission pass: relative to the emission's own mean, a lower bound of the pixel's
    // (the rest of its light is not traced), so the shared error is if anything overstated,
    // which favours `path`. (The lattice's mean of the rest in its place chose the gather at 2
    // of 10 seeds on a 256-lamp room at 256 spp, where it got 0.65×.)
    if stratum == EMISSION {
        let [a, b] = pilots.map(|pst| camera_emission(rs, &pst, x, y, half));
        let shared = relative_error(
            a,
            b,
            relative_weights([0, 1, 2].map(|c| 0.5 * (a[c] + b[c]))),
        );
        return PilotPixel {
            var: [shared; 2],
            rays: [0; 2],
            traced: 2 * u64::from(half),
            stratum,
        };
    }
    let mut means = [[[0.0f64; 3]; 2]; 2]; // [estimator][randomisation][channel]
    let mut rays = [0u64; 2];
    for (r, pst) in pilots.iter().enumerate() {
        for s in 0..half {
            let p = path::sample_pixel(rs, pst, x, y, s);
            let o = sample_pixel(rs, pst, opts, scratch, x, y, s);
            for (e, smp) in [p, o].into_iter().enumerate() {
                rays[e] += u64::from(smp.rays);
                // A non-finite sample counts as the film counts it: zero.
                let v = if smp.radiance.is_finite() {
                    smp.radiance
                } else {
                    Vec3::ZERO
                };
                for (m, vc) in means[e][r].iter_mut().zip(v.to_array()) {
                    *m += f64::from(vc) / f64::from(half);
                }
            }
        }
    }
    // Relative to the pixel's mean over both estimators and randomisations.
    let weight = relative_weights(
        [0, 1, 2]
            .map(|c| (means[0][0][c] + means[0][1][c] + means[1][0][c] + means[1][1][c]) / 4.0),
    );
    let mut var = means.map(|[a, b]| relative_error(a, b, weight));
    let mut traced = rays[0] + rays[1];
    if sees_emitter {
        // Less the part both estimators share, the error of their camera-hit emission from
        // these very samples: the emission pass measures it over many more pixels.
        let [a, b] = pilots.map(|pst| camera_emission(rs, &pst, x, y, half));
        let shared = relative_error(a, b, weight);
        var = var.map(|v| v - shared);
        traced += 2 * u64::from(half);
    }
    PilotPixel {
        var,
        rays,
        traced,
        stratum,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The lattice of [`pilot_step`] holds [`MIN_PILOT_PIXELS`] where the image has them,
    /// keeps `PILOT_STEP` on a large image, and [`is_pilot_pixel`] selects exactly the count
    /// the step was chosen by.
    #[test]
    fn the_pilot_lattice_has_enough_pixels() {
        let count = |w: u32, h: u32, step: u32| {
            (0..h)
                .flat_map(|y| (0..w).map(move |x| (x, y)))
                .filter(|&(x, y)| is_pilot_pixel(x, y, step))
                .count() as u32
        };
        assert_eq!(pilot_step(1920, 1080), PILOT_STEP);
        assert_eq!(count(1920, 1080, PILOT_STEP), 80 * 45);
        for (w, h) in [
            (128, 128),
            (100, 75),
            (256, 64),
            (37, 23),
            (8, 8),
            (1, 1),
            (3, 200),
        ] {
            let step = pilot_step(w, h);
            let n = count(w, h, step);
            if step > 1 {
                assert!(n >= MIN_PILOT_PIXELS, "{w}x{h}: step {step}, {n} pixels");
                // The largest such step: one more leaves too few.
                if step < PILOT_STEP {
                    assert!(count(w, h, step + 1) < MIN_PILOT_PIXELS, "{w}x{h}");
                }
            } else {
                assert_eq!(n, w * h, "{w}x{h}: every pixel");
            }
        }
    }

    /// Pilot pixels with the measured errors `(a, b)` of path and the gather.
    fn pixels(ab: &[(f64, f64)]) -> (Vec<PilotPixel>, Vec<Stratum>) {
        let m: Vec<PilotPixel> = ab
            .iter()
            .map(|&(a, b)| PilotPixel {
                var: [a, b],
                rays: [1, 1],
                traced: 2,
                stratum: 0,
            })
            .collect();
        let stratum = Stratum {
            population: 1000.0,
            count: ab.len(),
            var: [ab.iter().map(|p| p.0).sum(), ab.iter().map(|p| p.1).sum()],
            rays: [ab.len() as f64; 2],
        };
        (m, vec![stratum])
    }

    /// Over simulated pilots: the mean and standard deviation of `ln ratio` (the stratified
    /// totals') and the mean jackknife σ.
    fn spread_and_jackknife(pilots: &[(Vec<PilotPixel>, Vec<Stratum>)]) -> (f64, f64, f64) {
        let logs: Vec<f64> = pilots
            .iter()
            .map(|(_, strata)| {
                let t = stratified_totals(strata);
                (t[0] / t[1]).ln()
            })
            .collect();
        let n = logs.len() as f64;
        let mean = logs.iter().sum::<f64>() / n;
        let sd = (logs.iter().map(|l| (l - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt();
        let se = pilots
            .iter()
            .map(|(m, strata)| jackknife_log_ratio_se(m, strata))
            .sum::<f64>()
            / n;
        (mean, sd, se)
    }

    /// The jackknife's ends: pixels that all have one ratio leave no doubt; a pilot whose
    /// error is all in one pixel (or that has one pixel) leaves no confidence.
    #[test]
    fn the_jackknife_is_zero_for_one_ratio_and_infinite_for_one_pixel() {
        let (m, t) = pixels(&[(2.0, 1.0), (6.0, 3.0), (0.5, 0.25)]);
        assert!(jackknife_log_ratio_se(&m, &t) < 1e-12);
        let (m, t) = pixels(&[(2.0, 1.0), (0.0, 0.0), (0.0, 0.0)]);
        assert_eq!(jackknife_log_ratio_se(&m, &t), f64::INFINITY);
        let (m, t) = pixels(&[(2.0, 1.0)]);
        assert_eq!(jackknife_log_ratio_se(&m, &t), f64::INFINITY);
    }

    /// The margin's ends: a known error shrinks the prediction, an unknown one leaves 0 (only
    /// `min_speedup` 0 passes), a gather that never varied keeps its infinite prediction, and
    /// a pilot where nothing varied stays NaN (`path`).
    #[test]
    fn the_margin_keeps_the_ends_of_the_prediction() {
        assert!((less_one_se(2.0, 2f64.ln()) - 1.0).abs() < 1e-12);
        assert_eq!(less_one_se(2.0, f64::INFINITY), 0.0);
        assert_eq!(less_one_se(f64::INFINITY, f64::INFINITY), f64::INFINITY);
        assert!(less_one_se(f64::NAN, 0.1).is_nan());
    }

    /// A stream of uniform numbers in `(0, 1)` from `seed` (splitmix64, 53 bits).
    fn uniforms(seed: u64) -> impl FnMut() -> f64 {
        let mut state = seed;
        move || {
            state = mix64(state.wrapping_add(0x9e37_79b9_7f4a_7c15));
            ((state >> 11) as f64 + 0.5) / (1u64 << 53) as f64
        }
    }

    /// A standard normal number from two uniform ones (Box–Muller).
    fn box_muller(u: f64, v: f64) -> f64 {
        (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
    }

    /// The jackknife's standard error matches the spread it stands for. Pixels whose squared
    /// differences are χ²₁-distributed (as the pilot's two randomisations give) with scales
    /// spread over two decades: over 400 pilots of 64 pixels the mean jackknife σ agrees with
    /// the standard deviation of `ln ratio` within 20 % (the sampling error of a standard
    /// deviation from 400 draws is ≈ 3.5 %; the jackknife is itself a first-order method).
    #[test]
    fn the_jackknife_matches_the_spread_of_the_ratio() {
        let mut uniform = uniforms(7);
        let mut normal = || box_muller(uniform(), uniform());
        let mut pilots = Vec::new();
        for _ in 0..400 {
            let ab: Vec<(f64, f64)> = (0..64)
                .map(|i| {
                    let scale = 10f64.powf(2.0 * f64::from(i) / 63.0);
                    let (za, zb) = (normal(), normal());
                    (scale * za * za, 0.5 * scale * zb * zb)
                })
                .collect();
            let (m, t) = pixels(&ab);
            pilots.push((m, t));
        }
        let (mean, sd, se) = spread_and_jackknife(&pilots);
        let n = pilots.len() as f64;
        assert!((se / sd - 1.0).abs() < 0.2, "jackknife {se} vs spread {sd}");
        // `ln` of the ratio is symmetric about the truth (both sums have one shape): its mean
        // is ln 2 within four standard errors.
        assert!((mean - 2f64.ln()).abs() < 4.0 * sd / n.sqrt(), "{mean}");
    }

    /// The stratified jackknife matches the spread it stands for: a lattice stratum as above
    /// (64 of 10 000 pixels) and a stratum of rarely large errors both estimators share (32 of
    /// 1 000 pixels, one in eight holding an error 50× the rest): over 400 pilots the mean
    /// σ agrees with the standard deviation of `ln ratio` within 25 %.
    #[test]
    fn the_stratified_jackknife_matches_the_spread_of_the_ratio() {
        let mut uniform = uniforms(11);
        let mut pilots = Vec::new();
        for _ in 0..400 {
            let mut m = Vec::new();
            let mut strata = [Stratum::new(10_000.0), Stratum::new(1_000.0)];
            for i in 0..96 {
                let (stratum, var) = if i < 64 {
                    let mut chi2 = || {
                        let n = box_muller(uniform(), uniform());
                        n * n
                    };
                    let a = chi2();
                    let b = 0.2 * chi2();
                    (0, [a, b])
                } else {
                    let v = if uniform() < 0.125 { 50.0 } else { 1.0 } * uniform();
                    (1, [v, v])
                };
                let s = &mut strata[stratum];
                s.count += 1;
                for (t, v) in s.var.iter_mut().zip(var) {
                    *t += v;
                }
                m.push(PilotPixel {
                    var,
                    rays: [1, 1],
                    traced: 2,
                    stratum,
                });
            }
            pilots.push((m, strata.to_vec()));
        }
        let (_, sd, se) = spread_and_jackknife(&pilots);
        assert!(
            (se / sd - 1.0).abs() < 0.25,
            "jackknife {se} vs spread {sd}"
        );
        // A stratum of one pilot pixel leaves the error unknown.
        let mut strata = [Stratum::new(10.0), Stratum::new(10.0)];
        strata[0].count = 5;
        strata[1].count = 1;
        assert_eq!(jackknife_log_ratio_se(&[], &strata), f64::INFINITY);
    }
}
