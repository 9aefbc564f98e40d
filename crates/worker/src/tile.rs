//! Rendering a leased task, and the same phases in-process.
//!
//! [`Prepared`] is a loaded scene with the job's overrides applied (resolution, path lengths)
//! and the [`render::integrator::RenderScene`] built once per job; [`Prepared::render_task`]
//! renders one `(tile, sample range)` with [`render::tile::render_tile`] and packs the f64
//! film into a [`protocol::TileResult`]. [`render_local`] runs a whole job's task plan
//! in-process and assembles it exactly as the coordinator does, which is what the farm's
//! output is compared with (same spec + seed ⇒ same bits).

use std::collections::BTreeMap;

use protocol::TileResult;
use protocol::assemble::{AssembledImage, ImageAccumulator};
use protocol::frame::{PixelRecord, TileHeader};
use protocol::job::{
    EstimatorSpec, LightSelection, MisHeuristic, ResolvedJob, TileRect, plan_tasks,
};
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
}

/// A job's scene, prepared for rendering its tasks.
#[derive(Debug)]
pub struct Prepared {
    /// The prepared scene (BVH, lights, materials, camera).
    pub scene: RenderScene,
    /// The job's settings.
    pub settings: RenderSettings,
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
        let EstimatorSpec::Path(opts) = estimator else {
            return Err(TaskError::Unsupported(estimator.name()));
        };
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
            mis: match opts.mis {
                MisHeuristic::Power => render::integrator::MisHeuristic::Power,
                MisHeuristic::Balance => render::integrator::MisHeuristic::Balance,
            },
            light_selection: match opts.light_selection {
                LightSelection::Uniform => render::light::LightSelection::Uniform,
                LightSelection::Power => render::light::LightSelection::Power,
            },
            estimator: Estimator::Path,
        };
        let scene = RenderScene::new(&loaded.scene, &settings)?;
        Ok(Self { scene, settings })
    }

    /// Renders samples `sample_start..sample_end` of `rect` into a tile result.
    pub fn render_task(&self, header: TileHeader) -> Result<TileResult, TaskError> {
        let r = header.rect;
        let tile = render::tile::TileRect {
            x0: r.x0,
            y0: r.y0,
            width: r.width,
            height: r.height,
        };
        let film = render::tile::render_tile(
            &self.scene,
            &self.settings,
            tile,
            header.sample_start..header.sample_end,
        )?;
        let pixels = film
            .pixels
            .iter()
            .map(|p| PixelRecord {
                sum: p.sum,
                sum_sq: p.sum_sq,
                albedo: p.albedo_sum,
                normal: p.normal_sum,
                count: p.count,
            })
            .collect();
        Ok(TileResult {
            header,
            pixels,
            cells: Vec::new(),
        })
    }
}

/// Renders every task of a job in-process, in canonical order, and assembles the image the
/// way the coordinator does.
pub fn render_local(prepared: &Prepared, job: &ResolvedJob) -> Result<AssembledImage, TaskError> {
    let mut acc = ImageAccumulator::new(job.width, job.height);
    for t in plan_tasks(job) {
        let header = TileHeader {
            job_id: 0,
            task_id: i64::from(t.seq),
            attempt: 1,
            rect: TileRect { ..t.rect },
            sample_start: t.sample_start,
            sample_end: t.sample_end,
        };
        let tile = prepared.render_task(header)?;
        acc.add(&tile)
            .map_err(|e| TaskError::Scene(e.to_string()))?;
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
        let r = p.render_task(header).unwrap();
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

    #[test]
    fn unsupported_estimator_and_bad_scene_are_errors() {
        let cms = EstimatorSpec::Cms(Default::default());
        assert!(matches!(
            Prepared::new(&cornell(), BTreeMap::new(), &job(1, 1), &cms),
            Err(TaskError::Unsupported("cms"))
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
