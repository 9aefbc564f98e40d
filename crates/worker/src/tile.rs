//! Rendering a leased task, and the same phases in-process.
//!
//! [`Prepared`] is a loaded scene with the job's overrides applied (resolution, path lengths)
//! and the [`render::integrator::RenderScene`] built once per job; [`Prepared::render_task`]
//! renders one `(tile, sample range)` of one phase and packs the f64 film (and, for a
//! `train` task, the tile's cell accumulator table) into a [`protocol::TileResult`]:
//!
//! | estimator | phase | renderer call |
//! |---|---|---|
//! | `path`, `ocv` | render | [`render::tile::render_tile`] |
//! | `cms` (relative) | surrogate | [`CvJob::surrogate_tile`] |
//! | `cms`, `per_light_cv`, `optimal_mis` | train | [`CvJob::train_tile`] with the surrogate image; one cell block |
//! | `cms`, `per_light_cv`, `optimal_mis` | render | [`CvJob::render_tile`] with the solved coefficient table |
//!
//! [`render_local`] runs a whole job's phase plan ([`protocol::job::plan_phases`])
//! in-process and performs the barriers with the coordinator's own functions
//! ([`protocol::cv`]), the blobs going through their wire encodings; that is what the farm's
//! output is compared with (same spec + seed ⇒ same bits).

use std::collections::{BTreeMap, HashMap};
use std::sync::{Arc, Mutex};

use estimators::solve::CellCoefficients;
use estimators::table::decode_table;
use protocol::TileResult;
use protocol::assemble::{AssembledImage, ImageAccumulator};
use protocol::cv;
use protocol::frame::{CellBlock, TileHeader};
use protocol::job::{
    EstimatorSpec, LightSelection, MisHeuristic, ResolvedJob, TileRect, plan_phases,
};
use protocol::lease::PhaseKind;
use render::integrator::cv::{CoefficientTable, CvJob};
use render::integrator::{Estimator, RenderScene, RenderSettings};

/// Why a task could not be rendered.
#[derive(Debug, thiserror::Error)]
pub enum TaskError {
    /// The scene document does not parse or load.
    #[error("scene: {0}")]
    Scene(String),
    /// The estimator is not one this worker implements.
    #[error("estimator `{0}` is not supported by this worker")]
    Unsupported(&'static str),
    /// The renderer refused.
    #[error("render: {0}")]
    Render(#[from] render::integrator::RenderError),
    /// A phase input (surrogate image, coefficient table) is missing or invalid, or the
    /// phase does not exist for the estimator.
    #[error("phase input: {0}")]
    Input(String),
    /// An in-process barrier failed (see [`protocol::cv::CvError`]).
    #[error("barrier: {0}")]
    Barrier(#[from] protocol::cv::CvError),
}

/// What a task of a CV phase needs besides its tile: the surrogate image (train phase of
/// relative `cms`) and the coefficient table (render phase).
#[derive(Clone, Debug, Default)]
pub struct PhaseInputs {
    /// Per-pixel surrogate, `width × height`.
    pub surrogate: Option<Arc<Vec<f64>>>,
    /// Solved coefficients, checked against the job's layout.
    pub coefficients: Option<Arc<CoefficientTable>>,
}

/// A job's scene, prepared for rendering its tasks.
#[derive(Debug)]
pub struct Prepared {
    /// The prepared scene (BVH, lights, materials, camera).
    pub scene: RenderScene,
    /// The job's settings.
    pub settings: RenderSettings,
    /// The job's estimator, as on the wire.
    pub estimator: EstimatorSpec,
    /// Decoded phase inputs by content address (a job's blobs never change).
    inputs: Mutex<HashMap<String, Input>>,
}

#[derive(Clone, Debug)]
enum Input {
    Surrogate(Arc<Vec<f64>>),
    Coefficients(Arc<CoefficientTable>),
}

/// The renderer's estimator and MIS settings for a wire estimator.
pub fn render_estimator(
    estimator: &EstimatorSpec,
) -> Result<
    (
        Estimator,
        render::integrator::MisHeuristic,
        render::light::LightSelection,
    ),
    TaskError,
> {
    let (mis, sel) = match estimator {
        EstimatorSpec::Path(o) => (o.mis, o.light_selection),
        _ => (MisHeuristic::Power, LightSelection::Uniform),
    };
    let est = match estimator {
        EstimatorSpec::Path(_) => Estimator::Path,
        EstimatorSpec::Ocv(o) => Estimator::Ocv(*o),
        EstimatorSpec::Cms(o) => Estimator::Cms(*o),
        EstimatorSpec::PerLightCv(o) => Estimator::PerLightCv(*o),
        EstimatorSpec::OptimalMis(o) => Estimator::OptimalMis(*o),
        EstimatorSpec::Rerender(_) | EstimatorSpec::Gradient(_) => {
            return Err(TaskError::Unsupported(estimator.name()));
        }
    };
    let mis = match mis {
        MisHeuristic::Power => render::integrator::MisHeuristic::Power,
        MisHeuristic::Balance => render::integrator::MisHeuristic::Balance,
    };
    let sel = match sel {
        LightSelection::Uniform => render::light::LightSelection::Uniform,
        LightSelection::Power => render::light::LightSelection::Power,
    };
    Ok((est, mis, sel))
}

fn rtile(r: TileRect) -> render::tile::TileRect {
    render::tile::TileRect {
        x0: r.x0,
        y0: r.y0,
        width: r.width,
        height: r.height,
    }
}

impl Prepared {
    /// Loads `scene_json` over `assets` (name → bytes), applies the job's overrides and
    /// builds the render structures.
    pub fn new(
        scene_json: &[u8],
        assets: BTreeMap<String, Vec<u8>>,
        job: &ResolvedJob,
        estimator: &EstimatorSpec,
    ) -> Result<Self, TaskError> {
        let (est, mis, light_selection) = render_estimator(estimator)?;
        let desc: scene::SceneDesc =
            serde_json::from_slice(scene_json).map_err(|e| TaskError::Scene(e.to_string()))?;
        let mut mem = scene::MemoryAssets::new();
        for (name, bytes) in assets {
            mem.insert(&name, bytes)
                .map_err(|e| TaskError::Scene(e.to_string()))?;
        }
        let mut loaded = scene::load(&desc, &mem).map_err(|e| TaskError::Scene(e.to_string()))?;
        loaded.scene.film.width = job.width;
        loaded.scene.film.height = job.height;
        let settings = RenderSettings {
            spp: job.spp,
            seed: job.seed,
            max_depth: job.max_depth,
            rr_depth: job.rr_depth,
            hide_emitters: job.hide_emitters,
            mis,
            light_selection,
            estimator: est,
            sampler: job.sampler,
        };
        let scene = RenderScene::new(&loaded.scene, &settings)?;
        let p = Self {
            scene,
            settings,
            estimator: estimator.clone(),
            inputs: Mutex::new(HashMap::new()),
        };
        // Fail early (before any task) when the CV setup is invalid for this scene.
        p.cv_job()?;
        Ok(p)
    }

    /// The CV phase API of the job (`None` for `path` and `ocv`).
    fn cv_job(&self) -> Result<Option<CvJob<'_>>, TaskError> {
        Ok(CvJob::new(&self.scene, &self.settings)?)
    }

    fn cached(&self, hash: &str) -> Option<Input> {
        self.inputs.lock().ok()?.get(hash).cloned()
    }

    fn cache(&self, hash: &str, input: Input) {
        if let Ok(mut m) = self.inputs.lock() {
            m.insert(hash.to_owned(), input);
        }
    }

    /// Decodes (once per address) the surrogate image blob `bytes` with content address
    /// `hash`, checking its size against the film.
    pub fn surrogate(&self, hash: &str, bytes: &[u8]) -> Result<Arc<Vec<f64>>, TaskError> {
        if let Some(Input::Surrogate(s)) = self.cached(hash) {
            return Ok(s);
        }
        let (values, w, h) = estimators::surrogate::decode_surrogate(bytes)
            .map_err(|e| TaskError::Input(e.to_string()))?;
        if (w, h) != (self.scene.width, self.scene.height) {
            return Err(TaskError::Input(format!(
                "surrogate image is {w}x{h}, the film {}x{}",
                self.scene.width, self.scene.height
            )));
        }
        let s = Arc::new(values);
        self.cache(hash, Input::Surrogate(s.clone()));
        Ok(s)
    }

    /// Decodes (once per address) the coefficient table blob `bytes` with content address
    /// `hash`, checking every key and the layout against the job.
    pub fn coefficients(
        &self,
        hash: &str,
        bytes: &[u8],
    ) -> Result<Arc<CoefficientTable>, TaskError> {
        if let Some(Input::Coefficients(t)) = self.cached(hash) {
            return Ok(t);
        }
        let job = self.cv_job()?.ok_or_else(|| {
            TaskError::Input("coefficients for an estimator without phases".into())
        })?;
        let map: BTreeMap<u64, CellCoefficients> =
            decode_table(bytes).map_err(|e| TaskError::Input(format!("coefficients: {e}")))?;
        let t = Arc::new(job.coefficient_table(&map)?);
        self.cache(hash, Input::Coefficients(t.clone()));
        Ok(t)
    }

    /// Renders samples `sample_start..sample_end` of `rect` in `phase` into a tile result.
    pub fn render_task(
        &self,
        header: TileHeader,
        phase: PhaseKind,
        inputs: &PhaseInputs,
    ) -> Result<TileResult, TaskError> {
        let tile = rtile(header.rect);
        let samples = header.sample_start..header.sample_end;
        let job = self.cv_job()?;
        let (film, cells) = match (&job, phase) {
            (None, PhaseKind::Render) => (
                render::tile::render_tile(&self.scene, &self.settings, tile, samples)?,
                Vec::new(),
            ),
            (None, _) => {
                return Err(TaskError::Input(format!(
                    "estimator `{}` has no {} phase",
                    self.estimator.name(),
                    phase.as_str()
                )));
            }
            (Some(j), PhaseKind::Surrogate) => (j.surrogate_tile(tile, samples).film, Vec::new()),
            (Some(j), PhaseKind::Train) => {
                if j.needs_surrogate() && inputs.surrogate.is_none() {
                    return Err(TaskError::Input("the train phase needs a surrogate".into()));
                }
                let t = j.train_tile(
                    tile,
                    samples,
                    inputs.surrogate.as_deref().map(Vec::as_slice),
                )?;
                let block = CellBlock {
                    kind: t.cells.kind(),
                    data: t.cells.encode(),
                };
                (t.out.film, vec![block])
            }
            (Some(j), PhaseKind::Render) => {
                // Without a train phase (no vertex is controlled) the table is empty, as the
                // in-process driver's solve of no accumulators gives it.
                let empty;
                let table = match inputs.coefficients.as_deref() {
                    Some(t) => t,
                    None if j.phases().train.is_empty() => {
                        empty = j.coefficient_table(&Default::default())?;
                        &empty
                    }
                    None => {
                        return Err(TaskError::Input(
                            "the render phase needs a coefficient table".into(),
                        ));
                    }
                };
                (j.render_tile(tile, samples, table).out.film, Vec::new())
            }
        };
        Ok(TileResult {
            header,
            pixels: render::integrator::cv::film_moments(&film),
            cells,
        })
    }
}

/// Renders every task of a job's phase plan in-process, in canonical order, performs the
/// barriers the way the coordinator does (surrogate image, merge in task order, solve, each
/// blob through its wire encoding) and assembles all phases' pixels in (phase, task) order,
/// a render phase with the CV apart ([`ImageAccumulator::add_controlled`]).
pub fn render_local(prepared: &Prepared, job: &ResolvedJob) -> Result<AssembledImage, TaskError> {
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    let mut acc = ImageAccumulator::new(job.width, job.height);
    let mut inputs = PhaseInputs::default();
    // Whether the render phase runs with the CV (its samples are then combined by variance).
    let mut controlled = false;
    for phase in plan_phases(job, &prepared.estimator) {
        let mut results = Vec::with_capacity(phase.tasks.len());
        for t in &phase.tasks {
            let header = TileHeader {
                job_id: 0,
                task_id: i64::from(t.seq),
                attempt: 1,
                rect: t.rect,
                sample_start: t.sample_start,
                sample_end: t.sample_end,
            };
            results.push(prepared.render_task(header, phase.kind, &inputs)?);
        }
        let phased = prepared.estimator.phased_for(job);
        match (phase.kind, phased) {
            (PhaseKind::Surrogate, Some(_)) => {
                let blob = cv::surrogate_blob(job, &results)?;
                let hash = protocol::hash::sha256_hex(&blob);
                inputs.surrogate = Some(prepared.surrogate(&hash, &blob)?);
            }
            (PhaseKind::Train, Some(p)) => {
                let tables = results
                    .iter()
                    .map(|r| cv::check_train_block(&p, job, r))
                    .collect::<Result<Vec<_>, _>>()?;
                let merged = cv::merge_train(cv::table_kind(&p), tables, threads)?;
                let solved = merged.solve(&p.solve_policy(), threads);
                controlled = solved.controls_any();
                let blob = solved.encode();
                let hash = protocol::hash::sha256_hex(&blob);
                inputs.coefficients = Some(prepared.coefficients(&hash, &blob)?);
            }
            _ => {}
        }
        for r in &results {
            if phase.kind == PhaseKind::Render && controlled {
                acc.add_controlled(r)
            } else {
                acc.add(r)
            }
            .map_err(cv::CvError::from)?;
        }
    }
    Ok(acc.finish())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cornell() -> Vec<u8> {
        std::fs::read(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../../scenes/cornell-box/scene.json"
        ))
        .unwrap()
    }

    fn job(spp: u32, samples_per_task: u32) -> ResolvedJob {
        ResolvedJob {
            width: 16,
            height: 12,
            spp,
            seed: 3,
            sampler: Default::default(),
            max_depth: 5,
            rr_depth: 5,
            hide_emitters: false,
            tile_size: 8,
            samples_per_task,
        }
    }

    #[test]
    fn task_covers_its_rect_with_its_sample_count() {
        let p = Prepared::new(
            &cornell(),
            BTreeMap::new(),
            &job(4, 4),
            &EstimatorSpec::default(),
        )
        .unwrap();
        let rect = TileRect {
            x0: 8,
            y0: 8,
            width: 8,
            height: 4,
        };
        let header = TileHeader {
            job_id: 1,
            task_id: 2,
            attempt: 1,
            rect,
            sample_start: 1,
            sample_end: 4,
        };
        let r = p
            .render_task(header, PhaseKind::Render, &PhaseInputs::default())
            .unwrap();
        assert_eq!(r.pixels.len(), 32);
        assert!(r.pixels.iter().all(|px| px.count == 3));
        // The encoded result passes the coordinator's validation.
        assert_eq!(protocol::frame::decode(&r.encode(), 32).unwrap(), r);
    }

    #[test]
    fn same_job_same_bits_and_sample_split_covers_all_samples() {
        let whole = job(4, 4);
        let p = Prepared::new(
            &cornell(),
            BTreeMap::new(),
            &whole,
            &EstimatorSpec::default(),
        )
        .unwrap();
        let a = render_local(&p, &whole).unwrap();
        let b = render_local(&p, &whole).unwrap();
        assert_eq!(a, b);
        let split = job(4, 1);
        let c = render_local(&p, &split).unwrap();
        assert!(c.spp.iter().all(|&n| n == 4));
        // Splitting the sample range changes only the f64 summation order.
        for (x, y) in a.beauty.iter().zip(&c.beauty) {
            assert!((x - y).abs() <= 1e-5 * x.abs().max(1.0), "{x} vs {y}");
        }
    }

    /// The farm's plan with the coordinator's barriers gives the bits of `cvfarm render`
    /// (`render_estimator_image`) for a CV job with the default `samples_per_task`.
    fn local_equals_in_process_driver(est: EstimatorSpec, seed: u64) {
        local_equals_in_process_driver_at(est, seed, 5);
    }

    fn local_equals_in_process_driver_at(est: EstimatorSpec, seed: u64, max_depth: i32) {
        local_equals_in_process_driver_with(est, seed, max_depth, Default::default());
    }

    /// Checks the farm's bits against the in-process driver's; returns the farm's beauty.
    fn local_equals_in_process_driver_with(
        est: EstimatorSpec,
        seed: u64,
        max_depth: i32,
        sampler: protocol::job::SamplerKind,
    ) -> Vec<f32> {
        local_equals_in_process_driver_sized(&cornell(), est, seed, max_depth, sampler, (48, 32))
    }

    /// The job of [`local_equals_in_process_driver_sized`]: 24 spp in one task per tile.
    fn cv_job(
        (width, height): (u32, u32),
        seed: u64,
        max_depth: i32,
        sampler: protocol::job::SamplerKind,
    ) -> ResolvedJob {
        ResolvedJob {
            width,
            height,
            spp: 24,
            seed,
            sampler,
            max_depth,
            rr_depth: 5,
            hide_emitters: false,
            tile_size: 16,
            samples_per_task: 24,
        }
    }

    /// [`local_equals_in_process_driver_with`] for a `width × height` image of `scene`.
    fn local_equals_in_process_driver_sized(
        scene: &[u8],
        est: EstimatorSpec,
        seed: u64,
        max_depth: i32,
        sampler: protocol::job::SamplerKind,
        (width, height): (u32, u32),
    ) -> Vec<f32> {
        let j = cv_job((width, height), seed, max_depth, sampler);
        let p = Prepared::new(scene, BTreeMap::new(), &j, &est).unwrap();
        let farm = render_local(&p, &j).unwrap();
        let opts = render::tile::RenderOptions {
            tile_size: 16,
            threads: 2,
        };
        let (film, _, report) = render::integrator::cv::render_estimator_image(
            &p.scene,
            &p.settings,
            &opts,
            &|_, _| {},
        )
        .unwrap();
        let controls = est
            .phased_for(&j)
            .is_some_and(|p| p.controls_any_vertex(max_depth as u32));
        assert_eq!(report.cells > 0, controls, "{report:?}");
        let layers = film.layers();
        let flat = |i: usize| -> Vec<u32> {
            layers[i]
                .data
                .iter()
                .flatten()
                .map(|v| v.to_bits())
                .collect()
        };
        let bits = |v: &[f32]| -> Vec<u32> { v.iter().map(|x| x.to_bits()).collect() };
        assert_eq!(layers[0].name, "beauty");
        assert!(bits(&farm.beauty) == flat(0), "beauty differs");
        assert!(bits(&farm.variance) == flat(1), "variance differs");
        assert!(bits(&farm.albedo) == flat(2), "albedo differs");
        assert!(bits(&farm.normal) == flat(3), "normal differs");
        assert!(farm.spp.iter().all(|&n| n == 24));
        assert!(farm.beauty.iter().any(|&v| v > 0.0));
        farm.beauty
    }

    #[test]
    fn cms_render_local_equals_render_estimator_image_bitwise() {
        local_equals_in_process_driver(EstimatorSpec::Cms(Default::default()), 9);
    }

    /// An image wider than 512 pixels gets `cms`'s adaptive grid with an extra level for the
    /// glossy camera hits (`estimators::spec::adaptive_grid`): the farm's plan, solve and key
    /// checks resolve it as the renderer does, so the bits are the driver's.
    #[test]
    fn a_wide_images_extra_grid_level_is_resolved_alike_on_the_farm() {
        use estimators::spec::{CMS_GRID_LEVELS, CmsOptions};
        use protocol::job::SamplerKind;
        let (width, height) = (1040, 24);
        assert_eq!(estimators::spec::adaptive_grid(width, height).1, 1);
        let applied = CmsOptions {
            min_image_gain: None,
            min_fit_gain: None,
            ..CmsOptions::default()
        };
        let j = cv_job((width, height), 9, 5, SamplerKind::Independent);
        let est = EstimatorSpec::Cms(applied);
        let levels = est.phased_for(&j).map(|p| p.grid_levels());
        assert_eq!(levels, Some(CMS_GRID_LEVELS + 1));
        // veach-mis: the camera sees its glossy plates.
        let scene = std::fs::read(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../../scenes/veach-mis/scene.json"
        ))
        .unwrap();
        local_equals_in_process_driver_sized(
            &scene,
            est,
            9,
            5,
            SamplerKind::Independent,
            (width, height),
        );
    }

    /// A job's `sampler` reaches the renderer: the independent sampler's farm image is the
    /// in-process one bit for bit and not the Sobol image; the planner resolves `cms`'s
    /// sampler-dependent `min_depth` as the renderer does.
    #[test]
    fn the_jobs_sampler_reaches_the_renderer() {
        use protocol::job::SamplerKind;
        let cms = EstimatorSpec::Cms(Default::default());
        let sobol = local_equals_in_process_driver_with(cms.clone(), 9, 5, SamplerKind::Sobol);
        let independent = local_equals_in_process_driver_with(cms, 9, 5, SamplerKind::Independent);
        assert!(sobol != independent);
        // At depth 2 the independent sampler's default `min_depth` 0 controls the camera
        // hit: the farm plans a training phase and its bits are still the driver's.
        let cms = EstimatorSpec::Cms(Default::default());
        local_equals_in_process_driver_with(cms, 9, 2, SamplerKind::Independent);
        // With the fits always applied, the sampler-dependent `ridge` shows in the bits: the
        // farm's solve resolves it as the driver's does, and not as the Sobol default.
        use estimators::spec::CmsOptions;
        let applied = CmsOptions {
            min_image_gain: None,
            min_fit_gain: None,
            ..CmsOptions::default()
        };
        let by_sampler = local_equals_in_process_driver_with(
            EstimatorSpec::Cms(applied),
            9,
            5,
            SamplerKind::Independent,
        );
        let stratified_ridge = local_equals_in_process_driver_with(
            EstimatorSpec::Cms(CmsOptions {
                ridge: Some(estimators::spec::RIDGE_STRATIFIED),
                ..applied
            }),
            9,
            5,
            SamplerKind::Independent,
        );
        assert!(by_sampler != stratified_ridge);
    }

    /// With the default `min_depth` 1 a depth-2 `cms` job controls nothing: one render phase
    /// (no training, no barrier) whose image is `path`'s, bit for bit.
    #[test]
    fn cms_at_depth_two_is_one_render_phase_with_the_bits_of_path() {
        let cms = EstimatorSpec::Cms(Default::default());
        local_equals_in_process_driver_at(cms.clone(), 9, 2);
        let j = ResolvedJob {
            width: 48,
            height: 32,
            spp: 24,
            seed: 9,
            sampler: Default::default(),
            max_depth: 2,
            rr_depth: 5,
            hide_emitters: false,
            tile_size: 16,
            samples_per_task: 24,
        };
        let plan = protocol::job::plan_phases(&j, &cms);
        assert_eq!(plan.len(), 1);
        assert_eq!(plan[0].kind, PhaseKind::Render);
        let image = |est: &EstimatorSpec| {
            let p = Prepared::new(&cornell(), BTreeMap::new(), &j, est).unwrap();
            let img = render_local(&p, &j).unwrap();
            img.beauty.iter().map(|v| v.to_bits()).collect::<Vec<_>>()
        };
        let path = image(&EstimatorSpec::Path(Default::default()));
        assert!(image(&cms) == path);
        // At depth 3 the second vertex is controlled: phases, and other bits.
        let j3 = ResolvedJob { max_depth: 3, ..j };
        assert_eq!(protocol::job::plan_phases(&j3, &cms).len(), 3);
    }

    #[test]
    fn per_light_cv_render_local_equals_render_estimator_image_bitwise() {
        local_equals_in_process_driver(EstimatorSpec::PerLightCv(Default::default()), 4);
    }

    #[test]
    fn unsupported_estimator_and_bad_scene_are_errors() {
        let g = EstimatorSpec::Gradient(Default::default());
        assert!(matches!(
            Prepared::new(&cornell(), BTreeMap::new(), &job(1, 1), &g),
            Err(TaskError::Unsupported("gradient"))
        ));
        assert!(matches!(
            Prepared::new(
                b"{}",
                BTreeMap::new(),
                &job(1, 1),
                &EstimatorSpec::default()
            ),
            Err(TaskError::Scene(_))
        ));
    }
}
