//! Job submission: what a client asks the farm to render.
//!
//! A [`JobSpec`] is the body of `POST /v1/jobs`. Unknown fields are rejected everywhere
//! (`deny_unknown_fields`), so a misspelt option is an error, not a silent default.
//!
//! | field | type | default | meaning |
//! |---|---|---|---|
//! | `scene` | `{ "inline": SceneDesc }` or `{ "bundle": sha256 }` | — | the scene, inline native JSON or an uploaded scene document by content address |
//! | `assets` | map name → sha256 | `{}` | asset files the scene names (meshes, textures), uploaded with `PUT /v1/assets/{sha256}` |
//! | `estimator` | [`EstimatorSpec`] | `{ "kind": "path" }` | which estimator renders the job, with its options (`path`, `ocv`, `cms`, `per_light_cv`, `optimal_mis`) |
//! | `spp` | int | 16 | samples per pixel |
//! | `time_budget_s` | seconds | — | stop adding render rounds once this much time has passed since submission (`spp` is the cap) |
//! | `target_rel_mse` | number | — | stop adding render rounds once the estimated relMSE is at most this (`spp` is the cap) |
//! | `resolution` | `[w, h]` | scene's film | output size override |
//! | `max_depth` | int | scene's | path-length override (Mitsuba meaning, −1 = unbounded) |
//! | `seed` | int | 0 | sampler seed: same spec + seed ⇒ same image bits |
//! | `sampler` | `"sobol"` \| `"independent"` | `"sobol"` | Owen-scrambled Sobol points per pixel, or independent numbers (Mitsuba's `independent` sampler, the papers' baseline); a scene file's `<sampler type>` is not used |
//! | `tile_size` | int | 32 | tile edge in pixels (8..=512) |
//! | `samples_per_task` | int | `spp` | sample range length per task (splits tiles in time) |
//! | `priority` | int | 0 | higher runs first; FIFO within a priority |
//!
//! ```json
//! { "scene": { "inline": { "camera": {"fov": 40}, "film": {"width": 32, "height": 32}, "shapes": [] } },
//!   "estimator": { "kind": "path", "mis": "power" }, "spp": 16, "seed": 7, "tile_size": 16 }
//! ```
//!
//! The phase plan ([`plan_phases`]) is a pure function of the spec: per phase, tiles in
//! row-major order, each split into sample ranges in ascending order. It never depends on the
//! number of workers. A CV job (`cms`, `per_light_cv`, `optimal_mis`) has the phases
//! surrogate → train → render of DESIGN §1; `path` and `ocv` have one render phase.

use std::collections::BTreeMap;

use std::ops::Range;

pub use estimators::spec::{
    CmsOptions, CvColor, OcvOptions, OptimalMisOptions, PerLightCvOptions, PhasedEstimator,
    SamplerKind, TRAIN_TILE,
};
use serde::{Deserialize, Serialize};

use crate::hash::is_content_address;
use crate::lease::PhaseKind;

/// The body of `POST /v1/jobs`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct JobSpec {
    /// The scene to render.
    pub scene: SceneSource,
    /// Asset name (as written in the scene) → content address of the uploaded file.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub assets: BTreeMap<String, String>,
    /// The estimator.
    #[serde(default)]
    pub estimator: EstimatorSpec,
    /// Samples per pixel.
    #[serde(default = "default_spp")]
    pub spp: u32,
    /// Wall-clock budget in seconds: no render round starts being counted after it is spent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub time_budget_s: Option<f64>,
    /// Keep adding render rounds until the estimated relMSE is at most this.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub target_rel_mse: Option<f64>,
    /// Output resolution `[width, height]`; the scene's film when absent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub resolution: Option<[u32; 2]>,
    /// Path-length override (segments including the camera ray; −1 = unbounded).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_depth: Option<i32>,
    /// Sampler seed.
    #[serde(default)]
    pub seed: u64,
    /// Where the sample numbers come from.
    #[serde(default, skip_serializing_if = "SamplerKind::is_default")]
    pub sampler: SamplerKind,
    /// Tile edge in pixels.
    #[serde(default = "default_tile_size")]
    pub tile_size: u32,
    /// Samples per task (the sample range of one task); `spp` when absent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub samples_per_task: Option<u32>,
    /// Scheduling priority: higher first, FIFO within a priority.
    #[serde(default)]
    pub priority: i32,
}

fn default_spp() -> u32 {
    16
}
fn default_tile_size() -> u32 {
    32
}

/// Where the scene comes from.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum SceneSource {
    /// The native scene JSON written inline.
    Inline(Box<scene::SceneDesc>),
    /// A native scene JSON document uploaded with `PUT /v1/assets/{sha256}`.
    Bundle(String),
}

/// The estimator of a job: `{ "kind": NAME, ...options }`.
///
/// The CV estimators carry the option structs of [`estimators::spec`] — the same types the
/// renderer (`render::integrator::Estimator`) and `cvfarm render` use, so a job's options mean
/// the same thing locally and on the farm. Every option struct rejects unknown fields and
/// fills absent ones with its defaults. `rerender` and `gradient` parse (with any options)
/// so that the coordinator can answer `422 unsupported` naming the estimator, instead of a
/// confusing "unknown variant".
///
/// | kind | options | phases ([`plan_phases`]) |
/// |---|---|---|
/// | `path` | [`PathOptions`] | render |
/// | `ocv` | [`OcvOptions`] [Fan 2006] | render |
/// | `cms` | [`CmsOptions`] [Hua 2023] | surrogate (with `relative`), train, render |
/// | `per_light_cv` | [`PerLightCvOptions`] [Hua §7.2] | surrogate (with `relative`), train, render |
/// | `optimal_mis` | [`OptimalMisOptions`] [Hua §7.4] | train, render |
///
/// The CV estimators use the power heuristic and uniform light selection for the parts
/// outside the controlled direct lighting (the defaults of `cvfarm render`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum EstimatorSpec {
    /// Baseline NEE + BSDF MIS path tracer.
    Path(PathOptions),
    /// Fan et al. 2006 optimizing control variates.
    Ocv(OcvOptions),
    /// Hua et al. 2023 controlled mixture sampling.
    Cms(CmsOptions),
    /// Per-light CV as compared in [Hua §7.2].
    PerLightCv(PerLightCvOptions),
    /// Optimal MIS, cells = pixels [Hua §7.4].
    OptimalMis(OptimalMisOptions),
    /// Rousselle re-rendering (not yet supported).
    Rerender(OpaqueOptions),
    /// Rousselle gradient-domain (not yet supported).
    Gradient(OpaqueOptions),
}

impl Default for EstimatorSpec {
    fn default() -> Self {
        Self::Path(PathOptions::default())
    }
}

impl EstimatorSpec {
    /// The spec name (`estimator.kind`).
    pub fn name(&self) -> &'static str {
        match self {
            Self::Path(_) => "path",
            Self::Ocv(_) => "ocv",
            Self::Cms(_) => "cms",
            Self::PerLightCv(_) => "per_light_cv",
            Self::OptimalMis(_) => "optimal_mis",
            Self::Rerender(_) => "rerender",
            Self::Gradient(_) => "gradient",
        }
    }

    /// Whether the farm can run this estimator.
    pub fn is_supported(&self) -> bool {
        matches!(
            self,
            Self::Path(_) | Self::Ocv(_) | Self::Cms(_) | Self::PerLightCv(_) | Self::OptimalMis(_)
        )
    }

    /// The phase-structured form for `job` (`cms`, `per_light_cv`, `optimal_mis`), its
    /// sampler- and image-dependent defaults filled in ([`PhasedEstimator::for_sampler`],
    /// [`PhasedEstimator::for_image`]); `None` for the estimators rendered in one pass.
    /// The only way out of the spec, so the planner, the worker's and the coordinator's
    /// solves and upload checks resolve a job's defaults alike.
    pub fn phased_for(&self, job: &ResolvedJob) -> Option<PhasedEstimator> {
        self.phased()
            .map(|p| p.for_sampler(job.sampler).for_image(job.width, job.height))
    }

    /// The phase-structured form as written (sampler defaults unresolved: for range checks).
    fn phased(&self) -> Option<PhasedEstimator> {
        match *self {
            Self::Cms(o) => Some(PhasedEstimator::Cms(o)),
            Self::PerLightCv(o) => Some(PhasedEstimator::PerLightCv(o)),
            Self::OptimalMis(o) => Some(PhasedEstimator::OptimalMis(o)),
            _ => None,
        }
    }

    /// Checks the option ranges; the error names the option (`estimator.NAME`).
    pub fn validate(&self) -> Result<(), SpecError> {
        let r = match self {
            Self::Ocv(o) => o.validate(),
            _ => match self.phased() {
                Some(p) => p.validate(),
                None => Ok(()),
            },
        };
        r.map_err(|(field, why)| {
            SpecError::invalid(
                &format!("estimator.{field}"),
                format!("estimator `{}` option `{field}` {why}", self.name()),
            )
        })
    }
}

/// Options of an estimator that is not implemented yet: kept verbatim.
pub type OpaqueOptions = serde_json::Map<String, serde_json::Value>;

/// Options of the `path` estimator.
///
/// | field | values | default |
/// |---|---|---|
/// | `mis` | `power`, `balance` | `power` (as Mitsuba) |
/// | `light_selection` | `uniform`, `power` | `uniform` |
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PathOptions {
    /// MIS heuristic combining NEE and BSDF sampling.
    #[serde(default)]
    pub mis: MisHeuristic,
    /// How NEE picks a light.
    #[serde(default)]
    pub light_selection: LightSelection,
}

/// MIS heuristic.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum MisHeuristic {
    /// Power heuristic (β = 2).
    #[default]
    Power,
    /// Balance heuristic.
    Balance,
}

/// Light selection for NEE.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LightSelection {
    /// Uniform over emitters.
    #[default]
    Uniform,
    /// Proportional to emitted power.
    Power,
}

/// Server-side limits a spec must respect (explicit, documented, configurable).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Limits {
    /// Largest image width or height.
    pub max_dimension: u32,
    /// Largest pixel count (width × height).
    pub max_pixels: u64,
    /// Largest samples per pixel.
    pub max_spp: u32,
    /// Largest number of tasks one job may have.
    pub max_tasks: u64,
}

impl Default for Limits {
    fn default() -> Self {
        Self {
            max_dimension: 16_384,
            max_pixels: 64 << 20,
            max_spp: 1 << 16,
            max_tasks: 1 << 20,
        }
    }
}

/// Smallest and largest tile edge.
pub const TILE_SIZE_RANGE: std::ops::RangeInclusive<u32> = 8..=512;

/// A spec that breaks a rule, naming the field.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("{field}: {message}")]
pub struct SpecError {
    /// `invalid_spec` or `unsupported`.
    pub code: &'static str,
    /// JSON path of the offending field.
    pub field: String,
    /// What is wrong.
    pub message: String,
}

impl SpecError {
    fn invalid(field: &str, message: impl Into<String>) -> Self {
        Self {
            code: "invalid_spec",
            field: field.into(),
            message: message.into(),
        }
    }
    fn unsupported(field: &str, message: impl Into<String>) -> Self {
        Self {
            code: "unsupported",
            field: field.into(),
            message: message.into(),
        }
    }
}

impl From<SpecError> for crate::ApiError {
    fn from(e: SpecError) -> Self {
        crate::ApiError::new(e.code, e.message).with_field(e.field)
    }
}

/// The settings a job resolves to once the scene is known (scene defaults + overrides).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ResolvedJob {
    /// Image width.
    pub width: u32,
    /// Image height.
    pub height: u32,
    /// Samples per pixel.
    pub spp: u32,
    /// Sampler seed.
    pub seed: u64,
    /// Where the sample numbers come from (absent on the wire: `sobol`).
    #[serde(default, skip_serializing_if = "SamplerKind::is_default")]
    pub sampler: SamplerKind,
    /// Path-length limit.
    pub max_depth: i32,
    /// Russian-roulette start depth.
    pub rr_depth: i32,
    /// Hide directly visible emitters.
    pub hide_emitters: bool,
    /// Tile edge.
    pub tile_size: u32,
    /// Sample range length per task.
    pub samples_per_task: u32,
}

impl JobSpec {
    /// Whether the job's render phase is adaptive (a time budget or an error target): its
    /// tasks then come in **rounds** of `samples_per_task` over all tiles
    /// ([`plan_phases_ordered`]) and the coordinator stops after the first round that meets
    /// the budget or target.
    pub fn is_adaptive(&self) -> bool {
        self.time_budget_s.is_some() || self.target_rel_mse.is_some()
    }

    /// Checks every field against `limits` and resolves the job against the scene's own
    /// film and integrator settings. Errors name the field.
    pub fn resolve(
        &self,
        scene: &scene::SceneDesc,
        limits: &Limits,
    ) -> Result<ResolvedJob, SpecError> {
        if !self.estimator.is_supported() {
            return Err(SpecError::unsupported(
                "estimator.kind",
                format!(
                    "estimator `{}` is not yet supported by this farm (supported: path, ocv, cms, per_light_cv, optimal_mis)",
                    self.estimator.name()
                ),
            ));
        }
        self.estimator.validate()?;
        for (field, v) in [
            ("time_budget_s", self.time_budget_s),
            ("target_rel_mse", self.target_rel_mse),
        ] {
            if v.is_some_and(|v| !(v > 0.0 && v.is_finite())) {
                return Err(SpecError::invalid(
                    field,
                    "must be a positive finite number",
                ));
            }
        }
        if self.time_budget_s.is_some() && self.target_rel_mse.is_some() {
            return Err(SpecError::invalid(
                "target_rel_mse",
                "give either time_budget_s or target_rel_mse, not both",
            ));
        }
        for (name, hash) in &self.assets {
            if !is_content_address(hash) {
                return Err(SpecError::invalid(
                    &format!("assets.{name}"),
                    "asset address must be 64 lower-case hex digits (sha256)",
                ));
            }
        }
        let [width, height] = self
            .resolution
            .unwrap_or([scene.film.width, scene.film.height]);
        let field = if self.resolution.is_some() {
            "resolution"
        } else {
            "scene.film"
        };
        if width == 0 || height == 0 {
            return Err(SpecError::invalid(
                field,
                "width and height must be at least 1",
            ));
        }
        if width > limits.max_dimension || height > limits.max_dimension {
            return Err(SpecError::invalid(
                field,
                format!(
                    "{width}x{height} exceeds the limit of {} pixels per side",
                    limits.max_dimension
                ),
            ));
        }
        if u64::from(width) * u64::from(height) > limits.max_pixels {
            return Err(SpecError::invalid(
                field,
                format!(
                    "{width}x{height} exceeds the limit of {} pixels",
                    limits.max_pixels
                ),
            ));
        }
        if self.spp == 0 || self.spp > limits.max_spp {
            return Err(SpecError::invalid(
                "spp",
                format!("spp must be in 1..={}", limits.max_spp),
            ));
        }
        if !TILE_SIZE_RANGE.contains(&self.tile_size) {
            return Err(SpecError::invalid(
                "tile_size",
                format!(
                    "tile_size must be in {}..={}",
                    TILE_SIZE_RANGE.start(),
                    TILE_SIZE_RANGE.end()
                ),
            ));
        }
        let samples_per_task = self.samples_per_task.unwrap_or(self.spp);
        if samples_per_task == 0 || samples_per_task > self.spp {
            return Err(SpecError::invalid(
                "samples_per_task",
                "samples_per_task must be in 1..=spp",
            ));
        }
        let max_depth = self.max_depth.unwrap_or(scene.integrator.max_depth);
        if max_depth < -1 || max_depth == 0 {
            return Err(SpecError::invalid(
                "max_depth",
                "max_depth must be -1 (unbounded) or at least 1",
            ));
        }
        let resolved = ResolvedJob {
            width,
            height,
            spp: self.spp,
            seed: self.seed,
            sampler: self.sampler,
            max_depth,
            rr_depth: scene.integrator.rr_depth,
            hide_emitters: scene.integrator.hide_emitters,
            tile_size: self.tile_size,
            samples_per_task,
        };
        let tasks = plan_task_count(&resolved, &self.estimator);
        if tasks > limits.max_tasks {
            return Err(SpecError::invalid(
                "tile_size",
                format!(
                    "the job would have {tasks} tasks, more than the limit of {}",
                    limits.max_tasks
                ),
            ));
        }
        Ok(resolved)
    }
}

/// A rectangle of pixels: columns `x0..x0+width`, rows `y0..y0+height` (row 0 at the top).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TileRect {
    /// First column.
    pub x0: u32,
    /// First row.
    pub y0: u32,
    /// Columns.
    pub width: u32,
    /// Rows.
    pub height: u32,
}

impl TileRect {
    /// Number of pixels.
    pub fn pixel_count(&self) -> usize {
        self.width as usize * self.height as usize
    }

    /// Whether the rectangle lies inside a `w`×`h` image (and is not empty).
    pub fn fits_in(&self, w: u32, h: u32) -> bool {
        self.width > 0
            && self.height > 0
            && u64::from(self.x0) + u64::from(self.width) <= u64::from(w)
            && u64::from(self.y0) + u64::from(self.height) <= u64::from(h)
    }
}

/// One task of a job's phase: a tile and a sample range. `seq` is the canonical order.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct TaskPlan {
    /// Position in canonical order (0-based, dense).
    pub seq: u32,
    /// Pixels.
    pub rect: TileRect,
    /// First sample index (inclusive).
    pub sample_start: u32,
    /// Last sample index (exclusive).
    pub sample_end: u32,
}

/// One phase of a job's plan: its kind, the sample indices it renders and its tasks in
/// canonical order (`seq` dense from 0 within the phase).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct PhasePlan {
    /// Which phase.
    pub kind: PhaseKind,
    /// Sample indices of every pixel rendered in this phase.
    pub samples: Range<u32>,
    /// Tile edge of the phase's tasks.
    pub tile_size: u32,
    /// Tasks: tiles in row-major order, each tile's sample ranges ascending.
    pub tasks: Vec<TaskPlan>,
}

impl ResolvedJob {
    /// Number of tasks of the `path` plan ([`plan_tasks`]).
    pub fn task_count(&self) -> u64 {
        range_task_count(self, self.tile_size, &(0..self.spp), self.samples_per_task)
    }
}

fn tiles_of(job: &ResolvedJob, tile: u32) -> u64 {
    u64::from(job.width.div_ceil(tile)) * u64::from(job.height.div_ceil(tile))
}

fn range_task_count(job: &ResolvedJob, tile: u32, samples: &Range<u32>, per_task: u32) -> u64 {
    let n = samples.end.saturating_sub(samples.start);
    tiles_of(job, tile) * u64::from(n.div_ceil(per_task.max(1)))
}

/// Phase shapes of a job: (kind, tile edge, samples, samples per task), empty phases left out.
/// Smallest tile edge of a `surrogate` task. The phase takes 1–2 samples per pixel, so a
/// 32-pixel tile is a few milliseconds of rendering beside a lease and an upload with two
/// durable commits; 128-pixel tiles (16 k pixels) make the rendering dominate. A pixel's
/// sums, hence the surrogate, do not depend on the tiling.
pub const SURROGATE_TILE: u32 = 128;

fn phase_shapes(job: &ResolvedJob, est: &EstimatorSpec) -> Vec<(PhaseKind, u32, Range<u32>, u32)> {
    let spt = job.samples_per_task;
    let Some(p) = est.phased_for(job) else {
        return vec![(PhaseKind::Render, job.tile_size, 0..job.spp, spt)];
    };
    let max_depth = u32::try_from(job.max_depth).unwrap_or(u32::MAX); // −1: unbounded
    let ph = p.phases(job.spp, max_depth);
    let mut out = Vec::with_capacity(3);
    // The surrogate exists only for relative-variance training [Hua eq. 25] (as in
    // `render::integrator::cv::CvJob::needs_surrogate`).
    // Its tasks are 1–2 spp: tiles of at least SURROGATE_TILE keep the per-task cost (lease,
    // upload) small beside the rendering; a pixel's sums do not depend on the tiling.
    if p.relative() && !ph.surrogate.is_empty() {
        let tile = job.tile_size.max(SURROGATE_TILE);
        out.push((PhaseKind::Surrogate, tile, ph.surrogate, spt));
    }
    // Training tiles are fixed and never split in samples: the canonical merge order of
    // the accumulators is independent of the job's tile size and of `samples_per_task`.
    if !ph.train.is_empty() {
        let whole = ph.train.end - ph.train.start;
        out.push((PhaseKind::Train, TRAIN_TILE, ph.train, whole));
    }
    if !ph.render.is_empty() {
        out.push((PhaseKind::Render, job.tile_size, ph.render, spt));
    }
    out
}

/// Total number of tasks of [`plan_phases`], computed without building the plan.
pub fn plan_task_count(job: &ResolvedJob, est: &EstimatorSpec) -> u64 {
    phase_shapes(job, est)
        .iter()
        .map(|(_, tile, samples, spt)| range_task_count(job, *tile, samples, *spt))
        .sum()
}

/// The canonical phase plan of a job, a pure function of the resolved job and the estimator
/// (never of the worker count):
/// - `path`, `ocv`: one `render` phase, tiles of `tile_size`, `0..spp` split by
///   `samples_per_task` (= [`plan_tasks`]);
/// - `cms`, `per_light_cv`, `optimal_mis` (sample ranges from
///   [`PhasedEstimator::phases`]): `surrogate` (only for relative-variance `cms` and `per_light_cv`; tiles of
///   `max(tile_size, SURROGATE_TILE)`, split by `samples_per_task`), `train` (tiles of [`TRAIN_TILE`], the whole
///   training range, one task per tile), `render` (tiles of `tile_size`, split by
///   `samples_per_task`). Phases without samples are left out.
pub fn plan_phases(job: &ResolvedJob, est: &EstimatorSpec) -> Vec<PhasePlan> {
    plan_phases_ordered(job, est, false)
}

/// [`plan_phases`] with the last phase (render) in **round-major** order when `rounds` is
/// set: round `r` (the `r`-th sample range of every tile) is tasks `r·T .. (r+1)·T` for `T`
/// tiles, tiles row-major within a round. Each pixel still receives its sample ranges in
/// ascending order, so merging in `seq` order gives the same bits as the tile-major plan.
pub fn plan_phases_ordered(job: &ResolvedJob, est: &EstimatorSpec, rounds: bool) -> Vec<PhasePlan> {
    let shapes = phase_shapes(job, est);
    let last = shapes.len().saturating_sub(1);
    shapes
        .into_iter()
        .enumerate()
        .map(|(i, (kind, tile, samples, spt))| {
            let mut tasks = plan_range(job, tile, samples.clone(), spt);
            if rounds && i == last {
                // Stable sort by sample range start: rounds in order, tiles row-major within.
                tasks.sort_by_key(|t| t.sample_start);
                for (seq, t) in tasks.iter_mut().enumerate() {
                    t.seq = seq as u32;
                }
            }
            PhasePlan {
                kind,
                tasks,
                samples,
                tile_size: tile,
            }
        })
        .collect()
}

/// Tiles of a phase plan (tasks per round).
pub fn tiles_per_round(plan: &PhasePlan, job: &ResolvedJob) -> u64 {
    tiles_of(job, plan.tile_size)
}

fn plan_range(job: &ResolvedJob, tile: u32, samples: Range<u32>, per_task: u32) -> Vec<TaskPlan> {
    let per_task = per_task.max(1);
    let (tx, ty) = (job.width.div_ceil(tile), job.height.div_ceil(tile));
    let count = range_task_count(job, tile, &samples, per_task);
    let mut out = Vec::with_capacity(usize::try_from(count).unwrap_or(0));
    let mut seq = 0u32;
    for j in 0..ty {
        for i in 0..tx {
            let x0 = i * tile;
            let y0 = j * tile;
            let rect = TileRect {
                x0,
                y0,
                width: tile.min(job.width - x0),
                height: tile.min(job.height - y0),
            };
            let mut s = samples.start;
            while s < samples.end {
                let e = s.saturating_add(per_task).min(samples.end);
                out.push(TaskPlan {
                    seq,
                    rect,
                    sample_start: s,
                    sample_end: e,
                });
                seq += 1;
                s = e;
            }
        }
    }
    out
}

/// The canonical decomposition of a one-pass render phase: tiles in row-major order, each
/// tile's sample ranges ascending. A pure function of the resolved job.
pub fn plan_tasks(job: &ResolvedJob) -> Vec<TaskPlan> {
    plan_range(job, job.tile_size, 0..job.spp, job.samples_per_task)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scene_json() -> serde_json::Value {
        serde_json::json!({ "camera": {"fov": 40.0}, "film": {"width": 40, "height": 24}, "shapes": [] })
    }

    fn spec(extra: serde_json::Value) -> Result<JobSpec, serde_json::Error> {
        let mut v = serde_json::json!({ "scene": { "inline": scene_json() } });
        for (k, x) in extra.as_object().unwrap() {
            v[k] = x.clone();
        }
        serde_json::from_value(v)
    }

    fn scene() -> scene::SceneDesc {
        serde_json::from_value(scene_json()).unwrap()
    }

    #[test]
    fn defaults_and_resolution() {
        let s = spec(serde_json::json!({})).unwrap();
        assert_eq!(s.estimator, EstimatorSpec::Path(PathOptions::default()));
        let r = s.resolve(&scene(), &Limits::default()).unwrap();
        assert_eq!(
            (r.width, r.height, r.spp, r.samples_per_task, r.max_depth),
            (40, 24, 16, 16, 5)
        );
    }

    #[test]
    fn unknown_option_rejected() {
        let e = spec(serde_json::json!({"estimator": {"kind": "path", "bogus": 1}})).unwrap_err();
        assert!(e.to_string().contains("bogus"), "{e}");
        let e = spec(serde_json::json!({"sppp": 4})).unwrap_err();
        assert!(e.to_string().contains("sppp"), "{e}");
    }

    #[test]
    fn the_sampler_defaults_to_sobol_is_resolved_and_a_bad_one_is_named() {
        let s = spec(serde_json::json!({})).unwrap();
        assert_eq!(s.sampler, SamplerKind::Sobol);
        let r = s.resolve(&scene(), &Limits::default()).unwrap();
        assert_eq!(r.sampler, SamplerKind::Sobol);
        // The default is not written: a Sobol job's wire form is what it was before the
        // option existed.
        assert!(serde_json::to_value(r).unwrap().get("sampler").is_none());
        let s = spec(serde_json::json!({"sampler": "independent"})).unwrap();
        let r = s.resolve(&scene(), &Limits::default()).unwrap();
        assert_eq!(r.sampler, SamplerKind::Independent);
        let back: ResolvedJob = serde_json::from_value(serde_json::to_value(r).unwrap()).unwrap();
        assert_eq!(back, r);
        let e = spec(serde_json::json!({"sampler": "halton"})).unwrap_err();
        assert!(e.to_string().contains("halton"), "{e}");
    }

    #[test]
    fn unknown_estimator_rejected_at_parse() {
        let e = spec(serde_json::json!({"estimator": {"kind": "magic"}})).unwrap_err();
        assert!(e.to_string().contains("magic"), "{e}");
    }

    #[test]
    fn known_but_unimplemented_estimator_is_unsupported() {
        let s = spec(serde_json::json!({"estimator": {"kind": "gradient", "x": 16}})).unwrap();
        let e = s.resolve(&scene(), &Limits::default()).unwrap_err();
        assert_eq!(e.code, "unsupported");
        assert_eq!(e.field, "estimator.kind");
        assert!(e.message.contains("gradient"));
    }

    #[test]
    fn cv_options_are_typed_and_validated_naming_the_option() {
        let e =
            spec(serde_json::json!({"estimator": {"kind": "cms", "train_spp": 16}})).unwrap_err();
        assert!(e.to_string().contains("train_spp"), "{e}");
        let s = spec(
            serde_json::json!({"estimator": {"kind": "cms", "training_spp": 8, "color": "mono"}}),
        )
        .unwrap();
        let EstimatorSpec::Cms(o) = s.estimator else {
            panic!("not cms")
        };
        assert_eq!(
            (o.training_spp, o.color, o.relative),
            (8, CvColor::Mono, true)
        );
        let s =
            spec(serde_json::json!({"estimator": {"kind": "cms", "grid_resolution": [0, 2, 2]}}))
                .unwrap();
        let e = s.resolve(&scene(), &Limits::default()).unwrap_err();
        assert_eq!(
            (e.code, e.field.as_str()),
            ("invalid_spec", "estimator.grid_resolution")
        );
        for spe in [0, 1] {
            let s = spec(serde_json::json!({"estimator": {"kind": "ocv", "spe": spe}})).unwrap();
            let e = s.resolve(&scene(), &Limits::default()).unwrap_err();
            assert_eq!(e.field, "estimator.spe");
        }
        for kind in ["ocv", "cms", "per_light_cv", "optimal_mis"] {
            let s = spec(serde_json::json!({"estimator": {"kind": kind}})).unwrap();
            assert!(s.estimator.is_supported());
            s.resolve(&scene(), &Limits::default()).unwrap();
        }
    }

    #[test]
    fn budgets_are_validated_and_rounds_cover_the_same_samples() {
        let l = Limits::default();
        for (extra, field) in [
            (serde_json::json!({"time_budget_s": -1.0}), "time_budget_s"),
            (serde_json::json!({"target_rel_mse": 0.0}), "target_rel_mse"),
            (
                serde_json::json!({"time_budget_s": 1.0, "target_rel_mse": 0.1}),
                "target_rel_mse",
            ),
        ] {
            let e = spec(extra).unwrap().resolve(&scene(), &l).unwrap_err();
            assert_eq!(e.field, field);
        }
        let s = spec(
            serde_json::json!({"target_rel_mse": 0.01, "tile_size": 16, "spp": 10,
                                        "samples_per_task": 4}),
        )
        .unwrap();
        assert!(s.is_adaptive());
        let r = s.resolve(&scene(), &l).unwrap();
        let tile_major = plan_phases(&r, &s.estimator);
        let rounds = plan_phases_ordered(&r, &s.estimator, true);
        let t = tiles_per_round(&rounds[0], &r) as usize;
        assert_eq!(t, 6);
        for (i, task) in rounds[0].tasks.iter().enumerate() {
            assert_eq!(task.seq as usize, i);
            assert_eq!(task.sample_start, 4 * (i / t) as u32);
        }
        // The same tasks, each pixel's ranges still ascending in seq order.
        let mut a: Vec<_> = tile_major[0]
            .tasks
            .iter()
            .map(|t| (t.rect.x0, t.rect.y0, t.sample_start))
            .collect();
        let mut b: Vec<_> = rounds[0]
            .tasks
            .iter()
            .map(|t| (t.rect.x0, t.rect.y0, t.sample_start))
            .collect();
        a.sort_unstable();
        b.sort_unstable();
        assert_eq!(a, b);
    }

    #[test]
    fn cms_phase_plan_follows_the_estimator_split() {
        // 40x24, tile 16, spp 24, samples_per_task 3; cms relative: surrogate 0..1,
        // train 1..17, render 17..24.
        let s = spec(
            serde_json::json!({"estimator": {"kind": "cms"}, "tile_size": 16, "spp": 24,
                                        "samples_per_task": 3}),
        )
        .unwrap();
        let r = s.resolve(&scene(), &Limits::default()).unwrap();
        let plan = plan_phases(&r, &s.estimator);
        let kinds: Vec<_> = plan.iter().map(|p| p.kind).collect();
        assert_eq!(
            kinds,
            [PhaseKind::Surrogate, PhaseKind::Train, PhaseKind::Render]
        );
        // Surrogate: tiles of (at least) SURROGATE_TILE; training: tiles of TRAIN_TILE, the
        // whole range in one task per tile.
        let (sx, sy) = (
            40u32.div_ceil(SURROGATE_TILE),
            24u32.div_ceil(SURROGATE_TILE),
        );
        assert_eq!(plan[0].tasks.len(), (sx * sy) as usize);
        let (tx, ty) = (40u32.div_ceil(TRAIN_TILE), 24u32.div_ceil(TRAIN_TILE));
        assert_eq!(plan[1].tasks.len(), (tx * ty) as usize);
        assert!(
            plan[1]
                .tasks
                .iter()
                .all(|t| (t.sample_start, t.sample_end) == (1, 17))
        );
        let x0 = (tx - 1) * TRAIN_TILE;
        assert_eq!(
            plan[1].tasks[tx as usize - 1].rect,
            TileRect {
                x0,
                y0: 0,
                width: 40 - x0,
                height: 24.min(TRAIN_TILE)
            }
        );
        // Render: 7 samples split by 3 → 3 ranges per tile.
        assert_eq!(plan[2].tasks.len(), 3 * 2 * 3);
        assert_eq!(
            (plan[2].tasks[2].sample_start, plan[2].tasks[2].sample_end),
            (23, 24)
        );
        let total: usize = plan.iter().map(|p| p.tasks.len()).sum();
        assert_eq!(total as u64, plan_task_count(&r, &s.estimator));
        // Every pixel gets every sample index exactly once over the phases.
        let mut hits = vec![0u32; 40 * 24];
        for p in &plan {
            for (i, t) in p.tasks.iter().enumerate() {
                assert_eq!(t.seq as usize, i);
                for y in t.rect.y0..t.rect.y0 + t.rect.height {
                    for x in t.rect.x0..t.rect.x0 + t.rect.width {
                        hits[(y * 40 + x) as usize] += t.sample_end - t.sample_start;
                    }
                }
            }
        }
        assert!(hits.iter().all(|&h| h == 24));
        // Without `relative` there is no surrogate; path has one render phase.
        let s = spec(serde_json::json!({"estimator": {"kind": "cms", "relative": false}})).unwrap();
        let r = s.resolve(&scene(), &Limits::default()).unwrap();
        let kinds: Vec<_> = plan_phases(&r, &s.estimator)
            .iter()
            .map(|p| p.kind)
            .collect();
        assert_eq!(kinds, [PhaseKind::Train]);
        let s = spec(serde_json::json!({})).unwrap();
        let r = s.resolve(&scene(), &Limits::default()).unwrap();
        let plan = plan_phases(&r, &s.estimator);
        assert_eq!(plan.len(), 1);
        assert_eq!(plan[0].tasks, plan_tasks(&r));
    }

    #[test]
    fn limits_name_the_field() {
        let l = Limits::default();
        let e = spec(serde_json::json!({"spp": 0}))
            .unwrap()
            .resolve(&scene(), &l)
            .unwrap_err();
        assert_eq!(e.field, "spp");
        let e = spec(serde_json::json!({"spp": 1 << 20}))
            .unwrap()
            .resolve(&scene(), &l)
            .unwrap_err();
        assert_eq!(e.field, "spp");
        let e = spec(serde_json::json!({"resolution": [100000, 2]}))
            .unwrap()
            .resolve(&scene(), &l)
            .unwrap_err();
        assert_eq!(e.field, "resolution");
        let e = spec(serde_json::json!({"tile_size": 3}))
            .unwrap()
            .resolve(&scene(), &l)
            .unwrap_err();
        assert_eq!(e.field, "tile_size");
        let e = spec(serde_json::json!({"samples_per_task": 17}))
            .unwrap()
            .resolve(&scene(), &l)
            .unwrap_err();
        assert_eq!(e.field, "samples_per_task");
        let e = spec(serde_json::json!({"max_depth": 0}))
            .unwrap()
            .resolve(&scene(), &l)
            .unwrap_err();
        assert_eq!(e.field, "max_depth");
        let e = spec(serde_json::json!({"assets": {"a.obj": "xyz"}}))
            .unwrap()
            .resolve(&scene(), &l)
            .unwrap_err();
        assert_eq!(e.field, "assets.a.obj");
    }

    #[test]
    fn plan_covers_every_pixel_sample_once_in_canonical_order() {
        let s =
            spec(serde_json::json!({"tile_size": 16, "spp": 10, "samples_per_task": 4})).unwrap();
        let r = s.resolve(&scene(), &Limits::default()).unwrap();
        let plan = plan_tasks(&r);
        assert_eq!(plan.len() as u64, r.task_count());
        assert_eq!(plan.len(), 3 * 2 * 3);
        let mut hits = vec![0u32; 40 * 24];
        for (i, t) in plan.iter().enumerate() {
            assert_eq!(t.seq as usize, i);
            assert!(t.rect.fits_in(40, 24));
            for y in t.rect.y0..t.rect.y0 + t.rect.height {
                for x in t.rect.x0..t.rect.x0 + t.rect.width {
                    hits[(y * 40 + x) as usize] += t.sample_end - t.sample_start;
                }
            }
        }
        assert!(hits.iter().all(|&h| h == 10));
        // Sample ranges of one tile are consecutive and ascending.
        assert_eq!((plan[0].sample_start, plan[0].sample_end), (0, 4));
        assert_eq!((plan[2].sample_start, plan[2].sample_end), (8, 10));
        assert_eq!(plan[3].rect.x0, 16);
    }
}
