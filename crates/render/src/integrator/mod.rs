//! Integrators: the prepared scene ([`RenderScene`]), the per-job settings
//! ([`RenderSettings`]) and the estimator dispatch ([`Estimator`]).
//!
//! # Estimators
//!
//! | `estimator.kind` | file | what |
//! |---|---|---|
//! | `path` | `path.rs` | reference unidirectional path tracer: NEE + BSDF sampling with MIS (Mitsuba 3 `path`) |
//! | `cms` | `cms.rs` | controlled mixture sampling: per-cell optimal CV at every vertex [Hua 2023] |
//! | `per_light_cv` | `per_light_cv.rs` | per-cell mean per-light NEE contribution as CV (Vévoda 2018) [Hua §7.2] |
//! | `optimal_mis` | `optimal_mis.rs` | the CMS system per pixel for direct illumination (Kondapaneni 2019) [Hua §7.4] |
//! | `ocv` | `ocv.rs` | Fan 2006: deterministic mixture sampling + optimizing CV for the direct-lighting gather at each vertex |
//!
//! `cms`, `per_light_cv` and `optimal_mis` share `cv.rs` (grid, components, phases); their
//! entry point (which also renders every other estimator) is [`cv::render_estimator_image`].
//!
//! The CV estimators (DESIGN §4) plug in at the path vertex: [`path::trace`] reports every
//! vertex as a [`VertexRecord`] carrying both techniques' samples with **every technique's
//! pdf for every sample** (also zero-contribution samples, [Hua §8]) to a
//! [`VertexObserver`]. Observers are generic parameters (monomorphised, no trait objects on
//! the per-sample path); the plain `path` estimator uses [`NoObserver`].
//!
//! # Settings
//!
//! | name | type | default | meaning |
//! |---|---|---|---|
//! | `spp` | u32 | 16 | samples per pixel |
//! | `seed` | u64 | 0 | job seed (sampler) |
//! | `max_depth` | i32 | scene's | path segments incl. the camera ray; 1 = emitters seen directly, 2 = direct lighting, −1 = unbounded |
//! | `rr_depth` | i32 | scene's | vertex count from which Russian roulette applies (Mitsuba) |
//! | `hide_emitters` | bool | scene's | directly visible emitters are skipped (area lights) or black (env) |
//! | `mis` | `power` \| `balance` | `power` | MIS heuristic for NEE vs BSDF sampling |
//! | `light_selection` | `uniform` \| `power` | `uniform` | how NEE picks an emitter |
//! | `sampler` | `sobol` \| `independent` | `sobol` | Owen-scrambled Sobol points per pixel, or independent numbers (Mitsuba's `independent`, the papers' baseline) ([`crate::sampler::SamplerKind`]) |
//!
//! ```json
//! { "spp": 256, "seed": 7, "max_depth": 5, "rr_depth": 6, "mis": "power" }
//! ```

pub mod cms;
pub mod cv;
pub mod ocv;
pub mod optimal_mis;
pub mod path;
pub mod per_light_cv;

use glam::Vec3;
use thiserror::Error;

use crate::accel::Accel;
use crate::bsdf::MaterialTable;
use crate::camera::Camera;
use crate::light::{LightSelection, Lights};
use crate::sampler::SamplerKind;

/// The estimator a job renders with (closed set; dispatched with `match`).
///
/// JSON: internally tagged by `kind`, the variant's options beside it, e.g.
/// `{ "kind": "path" }`, `{ "kind": "ocv", "spe": 32 }`.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Estimator {
    /// The reference NEE + BSDF MIS path tracer.
    #[default]
    Path,
    /// Optimizing control variates for the direct-lighting gather [Fan 2006].
    Ocv(ocv::OcvOptions),
    /// Controlled mixture sampling [Hua 2023] (see [`cms`]).
    Cms(cms::CmsOptions),
    /// Vévoda-style per-light CV [Hua §7.2] (see [`per_light_cv`]).
    PerLightCv(per_light_cv::PerLightCvOptions),
    /// Optimal MIS per pixel for direct illumination [Hua §7.4] (see [`optimal_mis`]).
    OptimalMis(optimal_mis::OptimalMisOptions),
}

impl Estimator {
    /// Whether the estimator runs phases (surrogate/train/solve/render) and must be rendered
    /// with [`cv::render_estimator_image`] (a bare tile renders its plain, `α ≡ 0` form).
    pub fn has_phases(&self) -> bool {
        self.phased().is_some()
    }

    /// The phase-structured form of the estimator (`cms`, `per_light_cv`, `optimal_mis`).
    pub fn phased(&self) -> Option<estimators::spec::PhasedEstimator> {
        use estimators::spec::PhasedEstimator as P;
        match *self {
            Estimator::Cms(o) => Some(P::Cms(o)),
            Estimator::PerLightCv(o) => Some(P::PerLightCv(o)),
            Estimator::OptimalMis(o) => Some(P::OptimalMis(o)),
            Estimator::Path | Estimator::Ocv(_) => None,
        }
    }
}

/// MIS heuristic combining light and BSDF sampling.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum MisHeuristic {
    /// Power heuristic, β = 2 (Mitsuba's choice).
    #[default]
    Power,
    /// Balance heuristic.
    Balance,
}

impl MisHeuristic {
    /// Weight of technique `a` against `b` (one sample each).
    #[inline]
    pub fn weight(self, pdf_a: f32, pdf_b: f32) -> f32 {
        match self {
            MisHeuristic::Power => estimators::mis::power(pdf_a, pdf_b),
            MisHeuristic::Balance => estimators::mis::balance(pdf_a, pdf_b),
        }
    }
}

/// Per-job render settings (see the module docs for the table).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RenderSettings {
    /// Samples per pixel.
    pub spp: u32,
    /// Job seed.
    pub seed: u64,
    /// Max path segments incl. the camera ray; −1 = unbounded.
    pub max_depth: i32,
    /// Depth from which Russian roulette applies.
    pub rr_depth: i32,
    /// Hide directly visible emitters.
    pub hide_emitters: bool,
    /// MIS heuristic.
    pub mis: MisHeuristic,
    /// Light selection for NEE.
    pub light_selection: LightSelection,
    /// Estimator.
    pub estimator: Estimator,
    /// Where the sample numbers come from.
    pub sampler: SamplerKind,
}

impl RenderSettings {
    /// Default samples per pixel when neither scene nor job says.
    pub const DEFAULT_SPP: u32 = 16;

    /// Settings from the scene's integrator block (path lengths, `hide_emitters`, the
    /// sampler's `sample_count` as spp, else 16), with seed 0, power heuristic, uniform light selection, `path` estimator.
    /// Override fields with struct update syntax.
    pub fn from_scene(scene: &scene::Scene) -> Self {
        Self {
            spp: scene
                .integrator
                .sample_count
                .unwrap_or(Self::DEFAULT_SPP)
                .max(1),
            seed: 0,
            max_depth: scene.integrator.max_depth,
            rr_depth: scene.integrator.rr_depth,
            hide_emitters: scene.integrator.hide_emitters,
            mis: MisHeuristic::Power,
            light_selection: LightSelection::Uniform,
            estimator: Estimator::Path,
            sampler: SamplerKind::Sobol,
        }
    }

    /// Checks the settings.
    pub fn validate(&self) -> Result<(), RenderError> {
        if self.spp == 0 {
            return Err(RenderError::InvalidSetting {
                field: "spp",
                reason: "must be ≥ 1",
            });
        }
        if self.max_depth < -1 || self.max_depth == 0 {
            return Err(RenderError::InvalidSetting {
                field: "max_depth",
                reason: "must be −1 or ≥ 1",
            });
        }
        if self.rr_depth < 1 {
            return Err(RenderError::InvalidSetting {
                field: "rr_depth",
                reason: "must be ≥ 1",
            });
        }
        Ok(())
    }

    /// `max_depth` as an unsigned bound (−1 ⇒ `u32::MAX`).
    #[inline]
    pub fn max_depth_u32(&self) -> u32 {
        if self.max_depth < 0 {
            u32::MAX
        } else {
            self.max_depth as u32
        }
    }
}

/// Errors of scene preparation and rendering.
#[derive(Debug, Error, PartialEq)]
pub enum RenderError {
    /// A setting is out of range.
    #[error("invalid render setting `{field}`: {reason}")]
    InvalidSetting {
        /// Field name.
        field: &'static str,
        /// What is wrong.
        reason: &'static str,
    },
    /// The film has no pixels.
    #[error("film has zero size ({width}×{height})")]
    EmptyFilm {
        /// Width.
        width: u32,
        /// Height.
        height: u32,
    },
    /// A tile lies (partly) outside the image.
    #[error("tile {x0},{y0} {width}×{height} is outside the {image_width}×{image_height} image")]
    TileOutOfBounds {
        /// Tile left.
        x0: u32,
        /// Tile top.
        y0: u32,
        /// Tile width.
        width: u32,
        /// Tile height.
        height: u32,
        /// Image width.
        image_width: u32,
        /// Image height.
        image_height: u32,
    },
    /// The thread pool could not be created.
    #[error("thread pool: {0}")]
    ThreadPool(String),
}

/// A scene prepared for rendering: BVH, materials, lights, camera.
///
/// Built once per (scene, light selection) and shared read-only by all threads.
pub struct RenderScene {
    /// Ray–scene intersection.
    pub accel: Accel,
    /// The emitting shapes alone ([`Accel::emitters`]), for gathers that need only the emitter
    /// a ray reaches (`ocv`'s BSDF samples). Built whenever the scene has area emitters,
    /// whatever the settings, so that an estimator's image does not depend on the settings a
    /// shared `RenderScene` was prepared with (`cvfarm bench` prepares one for all); it holds
    /// the emitters' primitives only.
    pub emitters: Option<Accel>,
    /// Per-material BSDF data.
    pub materials: MaterialTable,
    /// Emitters and their sampling structures.
    pub lights: Lights,
    /// The camera.
    pub camera: Camera,
    /// What the scene calls for (emitters, env, BSDF kinds, …); drives what gets built.
    pub features: scene::Features,
    /// Image width.
    pub width: u32,
    /// Image height.
    pub height: u32,
    /// `ocv`'s pilot choices made so far, per settings ([`Self::ocv_choice`]).
    ocv_choices: std::sync::Mutex<Vec<(RenderSettings, ocv::Choice)>>,
}

impl std::fmt::Debug for RenderScene {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RenderScene")
            .field("width", &self.width)
            .field("height", &self.height)
            .field("primitives", &self.accel.primitive_count())
            .field("lights", &self.lights.len())
            .finish_non_exhaustive()
    }
}

impl RenderScene {
    /// Prepares `scene` for rendering with `settings` (which choose the light selection).
    pub fn new(scene: &scene::Scene, settings: &RenderSettings) -> Result<Self, RenderError> {
        settings.validate()?;
        let (width, height) = (scene.film.width, scene.film.height);
        if width == 0 || height == 0 {
            return Err(RenderError::EmptyFilm { width, height });
        }
        let features = scene::Features::of(scene);
        // `Lights` builds env-map tables only for an env map, nothing per light for none.
        let lights = Lights::new(scene, settings.light_selection);
        let mesh_lights: Vec<Option<u32>> = (0..scene.meshes.len())
            .map(|i| lights.mesh_light(i))
            .collect();
        let sphere_lights: Vec<Option<u32>> = (0..scene.spheres.len())
            .map(|i| lights.sphere_light(i))
            .collect();
        let accel = Accel::new(scene, &mesh_lights, &sphere_lights);
        let emitters = (mesh_lights
            .iter()
            .chain(&sphere_lights)
            .any(Option::is_some))
        .then(|| Accel::emitters(scene, &mesh_lights, &sphere_lights));
        let materials = MaterialTable::new(&scene.materials, &scene.textures);
        let camera = Camera::new(&scene.camera, &scene.film);
        Ok(Self {
            accel,
            emitters,
            materials,
            lights,
            camera,
            features,
            width,
            height,
            ocv_choices: std::sync::Mutex::new(Vec::new()),
        })
    }

    /// `ocv`'s pilot choice for a job with settings `st` ([`ocv::choose`]), made once per
    /// distinct settings and kept (every tile and task of the job reads it; `cvfarm bench`
    /// shares one `RenderScene` among its renders). `None` unless `st.estimator` is `ocv`.
    pub fn ocv_choice(&self, st: &RenderSettings) -> Option<ocv::Choice> {
        let Estimator::Ocv(o) = &st.estimator else {
            return None;
        };
        let mut cache = self
            .ocv_choices
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        if let Some((_, c)) = cache.iter().find(|(k, _)| k == st) {
            return Some(*c);
        }
        let c = ocv::choose(self, st, o);
        cache.push((*st, c));
        Some(c)
    }

    /// The techniques a render with `settings` actually simulates in this scene (for the job
    /// record): `emission` (emitters seen along paths), `nee` (light sampling; not with only
    /// delta BSDFs or no emitters), `bsdf_sampling`, `indirect` (paths longer than direct
    /// lighting), `env` (an environment light), `russian_roulette`.
    pub fn techniques(&self, settings: &RenderSettings) -> Vec<&'static str> {
        let f = &self.features;
        let mut t = Vec::new();
        let depth = settings.max_depth_u32();
        if f.emitters > 0 {
            t.push("emission");
        }
        let smooth = f
            .bsdf_kinds
            .iter()
            .any(|k| *k != scene::BsdfKind::Conductor);
        if f.emitters > 0 && depth >= 2 && smooth {
            t.push("nee");
        }
        if depth >= 2 {
            t.push("bsdf_sampling");
        }
        if depth > 2 {
            t.push("indirect");
        }
        if f.environment != scene::EnvironmentKind::None {
            t.push("env");
        }
        if depth >= 2 && i64::from(settings.rr_depth) < i64::from(depth) {
            t.push("russian_roulette");
        }
        t
    }
}

/// One technique's sample at a vertex: NEE ([`LightTechnique`]) or BSDF ([`BsdfTechnique`]).
/// Pdfs are solid-angle densities at the vertex; light pdfs include the selection pmf.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LightTechnique {
    /// Light chosen.
    pub light: u32,
    /// Light-sampling pdf of the sampled direction (incl. selection).
    pub pdf_light: f32,
    /// BSDF-sampling pdf of the sampled direction.
    pub pdf_bsdf: f32,
    /// `f·|cos θ|·Le·V` (not divided by any pdf, not MIS-weighted); zero if occluded.
    pub value: Vec3,
    /// Whether the shadow ray was traced and found the sampled point unoccluded (false when
    /// occluded or not traced; an observer with [`VertexObserver::CONTROLS_DIRECT`] gets the
    /// shadow ray traced whenever `pdf_bsdf > 0`, so that the BSDF technique's density of
    /// the sampled *point* — zero behind an occluder — is known).
    pub visible: bool,
}

/// The BSDF-sampled direction `wi` at a vertex and what it found.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BsdfTechnique {
    /// BSDF-sampling pdf of `wi` (for a delta lobe: the lobe's probability).
    pub pdf_bsdf: f32,
    /// Light-sampling pdf of `wi` (incl. selection) for the emitter it hit; 0 if none.
    pub pdf_light: f32,
    /// `f·|cos θ|/pdf_bsdf` (the throughput factor).
    pub weight: Vec3,
    /// Radiance emitted towards the vertex by what `wi` hit (0 if nothing emits).
    pub emitted: Vec3,
    /// The emitter `wi` reached (area light hit, or the environment light when the ray
    /// escaped), whatever its emission towards the vertex; `None` if not traced.
    pub hit_light: Option<u32>,
    /// Whether a delta lobe produced `wi`.
    pub delta: bool,
    /// Whether the continuation ray was traced (false when Russian roulette ended the path
    /// first; then `emitted` and `pdf_light` are unknown and left at 0).
    pub traced: bool,
    /// Russian-roulette continuation probability applied after this sample (1 when roulette
    /// was inactive): the path continued with throughput `throughput · weight / rr_q`.
    pub rr_q: f32,
}

/// Everything a CV estimator needs at one path vertex: the techniques' samples, their
/// densities and values. Where the vertex is (depth, position, normal) the observer is told
/// by [`VertexObserver::controls`]; the record holds only what the estimate reads, since
/// `trace` writes it at every vertex an observer may control.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VertexRecord {
    /// Path throughput up to (excluding) this vertex's scattering.
    pub throughput: Vec3,
    /// The NEE sample, if one was drawn (non-delta BSDF, lights present, sample valid).
    pub light: Option<LightTechnique>,
    /// The light NEE selected, also when sampling it then failed (`light` is `None`);
    /// `None` when NEE did not run (delta BSDF or no lights).
    pub nee_light: Option<u32>,
    /// The BSDF sample, if valid (when the path continues, it continues along it).
    pub bsdf: Option<BsdfTechnique>,
}

/// Receives every path vertex (static dispatch).
pub trait VertexObserver {
    /// When `true` the observer *owns* the direct lighting of scattering vertices:
    /// [`path::trace`] adds neither the NEE contribution nor the emission found by the BSDF
    /// sample (unless [`adds_to_path`](Self::adds_to_path)), but the value
    /// [`controlled_vertex`](Self::controlled_vertex) returns; it also
    /// traces zero-weight BSDF samples (then stops) and shadow rays of zero-valued NEE
    /// samples with `pdf_bsdf > 0`, so every technique's pdf is known for every sample
    /// [Hua §8]. With `false` (the default) `trace` is exactly the `path` estimator.
    const CONTROLS_DIRECT: bool = false;

    /// Asked at each scattering vertex before its techniques are sampled when
    /// [`CONTROLS_DIRECT`](Self::CONTROLS_DIRECT) is set: whether the observer controls this
    /// vertex (`depth`, position `p`, shading normal `ns`, whether its BSDF has a glossy
    /// lobe: [`crate::bsdf::Bsdf::is_glossy`]). When `false`, [`path::trace`]
    /// treats the vertex exactly as `path` does (adds its MIS-weighted direct lighting
    /// itself, traces no extra ray) and reports it with [`vertex`](Self::vertex) if the
    /// observer [sees such vertices](Self::SEES_UNCONTROLLED).
    ///
    /// [`path::trace`]: path::trace
    #[inline]
    fn controls(&mut self, _depth: u32, _p: Vec3, _ns: Vec3, _glossy: bool) -> bool {
        Self::CONTROLS_DIRECT
    }

    /// Whether [`vertex`](Self::vertex) reads the vertices the observer does not control
    /// (all of them without [`CONTROLS_DIRECT`](Self::CONTROLS_DIRECT)). With `false`,
    /// [`path::trace`] builds a [`VertexRecord`] only for the vertices it reports to
    /// [`controlled_vertex`](Self::controlled_vertex): at the others the record's stores
    /// cost the CV estimators' render phase ≈ 0.7 M instructions per spp of colour-lamp
    /// 96² at depth 5 (of `path`'s 48.6 M).
    ///
    /// [`path::trace`]: path::trace
    const SEES_UNCONTROLLED: bool = true;

    /// Called once per scattering vertex after both techniques were evaluated, unless the
    /// vertex is controlled or [`SEES_UNCONTROLLED`](Self::SEES_UNCONTROLLED) is `false`.
    #[inline]
    fn vertex(&mut self, _record: &VertexRecord) {}

    /// On a controlled vertex ([`controls`](Self::controls) returned `true`), the light NEE
    /// selected, before it is sampled and before
    /// [`controlled_vertex`](Self::controlled_vertex) reports it: a hint to start loading
    /// what that report will read. Must not change any result.
    #[inline]
    fn nee_selected(&self, _light: u32) {}

    /// Asked once per path when [`CONTROLS_DIRECT`](Self::CONTROLS_DIRECT) is set: whether
    /// the observer's estimate of a controlled vertex is `path`'s MIS-weighted direct
    /// lighting plus a term of its own. Then [`path::trace`] adds the MIS-weighted direct
    /// lighting of controlled vertices itself, exactly as of the others, and
    /// [`controlled_vertex`](Self::controlled_vertex) returns only the added term.
    ///
    /// [`path::trace`]: path::trace
    #[inline]
    fn adds_to_path(&self) -> bool {
        false
    }

    /// Called instead of [`vertex`](Self::vertex) when
    /// [`CONTROLS_DIRECT`](Self::CONTROLS_DIRECT) is set: returns the vertex's
    /// direct-lighting contribution *including* the prefix throughput `record.throughput`
    /// (with [`adds_to_path`](Self::adds_to_path), only what it adds to `path`'s).
    #[inline]
    fn controlled_vertex(&mut self, record: &VertexRecord) -> Vec3 {
        self.vertex(record);
        Vec3::ZERO
    }
}

/// The observer of the plain `path` estimator: ignores vertices.
#[derive(Clone, Copy, Debug, Default)]
pub struct NoObserver;

impl VertexObserver for NoObserver {
    const SEES_UNCONTROLLED: bool = false;
}
