//! The barriers of a CV job's phases as pure functions, shared by the coordinator (which runs
//! them on uploaded results) and the worker's in-process assembly (`worker::tile::render_local`),
//! so that both produce the same bits (DESIGN §1, §5).
//!
//! - after `surrogate`: the phase's pixel blocks are summed **in canonical task order**
//!   ([`crate::assemble::ImageAccumulator`]) and turned into the denoised surrogate image
//!   [Hua §4.2.1] by [`estimators::surrogate::surrogate_image`] ([`surrogate_blob`]);
//! - after `train`: every task's accumulator table is checked ([`check_train_block`]),
//!   merged **in canonical task order** ([`merge_train`]) and solved per cell
//!   ([`estimators::table::AccumulatorTable::solve`], [Hua eq. 32–33], or the mean
//!   contributions of `per_light_cv` [Hua §7.2]).
//!
//! The blobs are stored content-addressed and handed to the next phase's leases.

use std::collections::BTreeMap;

use estimators::solve::SolveStatus;
use estimators::spec::{MAX_GRID_CELLS, PhasedEstimator};
use estimators::surrogate::{encode_surrogate, surrogate_image};
use estimators::table::{
    AccumulatorTable, KIND_CELL_ACCUMULATORS, KIND_MEAN_CONTRIBUTIONS, SolvedTable,
};

use crate::assemble::{ImageAccumulator, OutOfBounds};
use crate::frame::TileResult;
use crate::job::ResolvedJob;

/// Cells per grid cell: the renderer splits every grid cell by the dominant axis and sign of
/// the shading normal (`render::integrator::cv::NORMAL_BINS`).
pub const NORMAL_BINS: u64 = 6;

/// Why a training result (or a set of them) was rejected. The message names the problem.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum CvError {
    /// A train result must carry exactly one cell block.
    #[error("a train result must carry exactly one cell block, found {0}")]
    BlockCount(usize),
    /// Cell blocks in a result of a phase that has none.
    #[error("cell blocks are not expected in a {0} result")]
    Unexpected(&'static str),
    /// The block's kind tag is not the job's.
    #[error("cell block kind {found} is not the kind of this job's estimator ({expected})")]
    WrongKind {
        /// Tag in the frame or table header.
        found: u16,
        /// The job's tag.
        expected: u16,
    },
    /// The block does not decode (truncated, non-finite, malformed).
    #[error("cell block does not decode: {0}")]
    Decode(String),
    /// A cell key is outside the job's key range.
    #[error("cell key {key} is out of range (keys must be below {limit})")]
    KeyRange {
        /// Largest key found.
        key: u64,
        /// Exclusive bound.
        limit: u64,
    },
    /// Records of one block, or of two blocks of the job, have different layouts.
    #[error("cell layout {found} differs from {expected}")]
    Layout {
        /// Layout of the offending record.
        found: String,
        /// Layout seen before.
        expected: String,
    },
    /// A block does not fit the image.
    #[error(transparent)]
    Bounds(#[from] OutOfBounds),
}

/// The accumulator table kind of a phased estimator's training results.
pub fn table_kind(est: &PhasedEstimator) -> u16 {
    match est {
        PhasedEstimator::PerLightCv(_) => KIND_MEAN_CONTRIBUTIONS,
        PhasedEstimator::Cms(_) | PhasedEstimator::OptimalMis(_) => KIND_CELL_ACCUMULATORS,
    }
}

/// Exclusive bound of the cell keys of a job: pixels for `optimal_mis` (cells = pixels
/// [Hua §7.4]), else grid cells × [`NORMAL_BINS`] (the grid's resolution when given, at most
/// [`MAX_GRID_CELLS`]).
pub fn cell_key_limit(est: &PhasedEstimator, job: &ResolvedJob) -> u64 {
    let grid = match est {
        PhasedEstimator::OptimalMis(_) => {
            return u64::from(job.width) * u64::from(job.height);
        }
        PhasedEstimator::Cms(o) => o.grid_resolution,
        PhasedEstimator::PerLightCv(o) => o.grid_resolution,
    };
    let cells = grid.map_or(MAX_GRID_CELLS, |g| {
        g.iter().map(|&r| u64::from(r)).product::<u64>()
    });
    cells.min(MAX_GRID_CELLS) * NORMAL_BINS
}

/// The layout every record of `table` shares (`None` for an empty table), e.g.
/// `cells(partitions=3, overlapping=1, Rgb)`; records of different layouts are an error.
pub fn layout_signature(table: &AccumulatorTable) -> Result<Option<String>, CvError> {
    // Compare plain tuples per record; format only the first and an offender.
    fn uniform<T, K: PartialEq + Copy>(
        records: impl Iterator<Item = T>,
        key: impl Fn(&T) -> K,
        show: impl Fn(K) -> String,
    ) -> Result<Option<String>, CvError> {
        let mut first: Option<K> = None;
        for r in records {
            let k = key(&r);
            match first {
                None => first = Some(k),
                Some(f) if f != k => {
                    return Err(CvError::Layout {
                        found: show(k),
                        expected: format!("{} (in the same block)", show(f)),
                    });
                }
                Some(_) => {}
            }
        }
        Ok(first.map(show))
    }
    match table {
        AccumulatorTable::Moments(t) => uniform(
            t.values(),
            |a| {
                let l = a.layout();
                (l.partitions, l.overlapping, a.color())
            },
            |(p, o, c)| format!("cells(partitions={p}, overlapping={o}, {c:?})"),
        ),
        AccumulatorTable::Mean(t) => uniform(
            t.values(),
            |a| a.lights(),
            |n| format!("mean_contributions(lights={n})"),
        ),
    }
}

/// Validates the cell block of a `train` result: exactly one block, of the job's kind, that
/// decodes (sizes, finite values: [`AccumulatorTable::decode`]), with keys below
/// [`cell_key_limit`] and one layout. Returns the decoded table.
pub fn check_train_block(
    est: &PhasedEstimator,
    job: &ResolvedJob,
    result: &TileResult,
) -> Result<AccumulatorTable, CvError> {
    let [block] = result.cells.as_slice() else {
        return Err(CvError::BlockCount(result.cells.len()));
    };
    let expected = table_kind(est);
    if block.kind != expected {
        return Err(CvError::WrongKind {
            found: block.kind,
            expected,
        });
    }
    let table =
        AccumulatorTable::decode(&block.data).map_err(|e| CvError::Decode(e.to_string()))?;
    if table.kind() != expected {
        return Err(CvError::WrongKind {
            found: table.kind(),
            expected,
        });
    }
    let limit = cell_key_limit(est, job);
    if let Some(key) = table.max_key().filter(|&k| k >= limit) {
        return Err(CvError::KeyRange { key, limit });
    }
    layout_signature(&table)?;
    Ok(table)
}

/// The encoded surrogate image ([`encode_surrogate`]) of a job from its surrogate phase's
/// results, summed in the order given (canonical task order).
pub fn surrogate_blob<'a>(
    job: &ResolvedJob,
    results: impl IntoIterator<Item = &'a TileResult>,
) -> Result<Vec<u8>, CvError> {
    let mut acc = ImageAccumulator::new(job.width, job.height);
    for r in results {
        acc.add(r)?;
    }
    let img = surrogate_image(acc.pixels(), job.width as usize, job.height as usize);
    Ok(encode_surrogate(&img, job.width, job.height))
}

/// Merges training tables key by key in the order given (canonical task order), starting
/// from an empty table of `kind`; tables of another kind or layout are an error.
pub fn merge_train(
    kind: u16,
    tables: impl IntoIterator<Item = AccumulatorTable>,
) -> Result<AccumulatorTable, CvError> {
    let mut merged = AccumulatorTable::empty(kind).map_err(|e| CvError::Decode(e.to_string()))?;
    let mut layout: Option<String> = None;
    for t in tables {
        if t.kind() != kind {
            return Err(CvError::WrongKind {
                found: t.kind(),
                expected: kind,
            });
        }
        if let Some(sig) = layout_signature(&t)? {
            match &layout {
                Some(l) if *l != sig => {
                    return Err(CvError::Layout {
                        found: sig,
                        expected: l.clone(),
                    });
                }
                Some(_) => {}
                None => layout = Some(sig),
            }
        }
        merged
            .merge(&t)
            .map_err(|e| CvError::Decode(e.to_string()))?;
    }
    Ok(merged)
}

/// Counts of a solved table for `stats.json`: (cells, solved, fallbacks by reason).
pub fn solve_summary(solved: &SolvedTable) -> (u64, u64, BTreeMap<String, u64>) {
    let mut ok = 0;
    let mut fallback = BTreeMap::new();
    for co in solved.coefficients.values() {
        match co.diagnostics().status {
            SolveStatus::Solved => ok += 1,
            SolveStatus::Fallback(r) => *fallback.entry(format!("{r:?}")).or_insert(0) += 1,
        }
    }
    (solved.coefficients.len() as u64, ok, fallback)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::{CellBlock, PixelRecord, TileHeader};
    use crate::job::{CmsOptions, TileRect};
    use estimators::cell::{CellAccumulator, ColorMode, ComponentLayout, CvSample};

    fn job() -> ResolvedJob {
        ResolvedJob {
            width: 4,
            height: 2,
            spp: 4,
            seed: 0,
            max_depth: 5,
            rr_depth: 5,
            hide_emitters: false,
            tile_size: 8,
            samples_per_task: 4,
        }
    }

    fn table(partitions: u32, key: u64) -> AccumulatorTable {
        let mut a =
            CellAccumulator::new(ComponentLayout::new(partitions, 1).unwrap(), ColorMode::Rgb);
        let s = CvSample {
            pdf: 2.0,
            partition: Some((0, 1.0)),
            overlapping: &[0.5],
        };
        a.add(1.0, [0.5, 0.25, 1.0], &s).unwrap();
        AccumulatorTable::Moments(BTreeMap::from([(key, a)]))
    }

    fn result(cells: Vec<CellBlock>) -> TileResult {
        TileResult {
            header: TileHeader {
                job_id: 1,
                task_id: 1,
                attempt: 1,
                rect: TileRect {
                    x0: 0,
                    y0: 0,
                    width: 4,
                    height: 2,
                },
                sample_start: 0,
                sample_end: 1,
            },
            pixels: vec![
                PixelRecord {
                    sum: [0.5; 3],
                    sum_sq: [0.25; 3],
                    albedo: [1.0; 3],
                    normal: [0.0, 0.0, 1.0],
                    count: 1,
                };
                8
            ],
            cells,
        }
    }

    fn block(t: &AccumulatorTable) -> CellBlock {
        CellBlock {
            kind: t.kind(),
            data: t.encode(),
        }
    }

    #[test]
    fn train_blocks_are_checked() {
        let est = PhasedEstimator::Cms(CmsOptions::default());
        let good = table(2, 5);
        assert_eq!(
            check_train_block(&est, &job(), &result(vec![block(&good)])).unwrap(),
            good
        );
        assert_eq!(
            check_train_block(&est, &job(), &result(vec![])).unwrap_err(),
            CvError::BlockCount(0)
        );
        let mut truncated = block(&good);
        truncated.data.truncate(truncated.data.len() - 3);
        assert!(matches!(
            check_train_block(&est, &job(), &result(vec![truncated])),
            Err(CvError::Decode(_))
        ));
        let mut wrong = block(&good);
        wrong.kind = KIND_MEAN_CONTRIBUTIONS;
        assert!(matches!(
            check_train_block(&est, &job(), &result(vec![wrong])),
            Err(CvError::WrongKind { .. })
        ));
        let far = table(2, MAX_GRID_CELLS * NORMAL_BINS);
        assert!(matches!(
            check_train_block(&est, &job(), &result(vec![block(&far)])),
            Err(CvError::KeyRange { .. })
        ));
        // optimal_mis: cells are pixels.
        let om = PhasedEstimator::OptimalMis(Default::default());
        assert!(matches!(
            check_train_block(&om, &job(), &result(vec![block(&table(2, 8))])),
            Err(CvError::KeyRange { key: 8, limit: 8 })
        ));
    }

    #[test]
    fn merge_rejects_mixed_layouts_and_is_order_defined() {
        let m = merge_train(
            KIND_CELL_ACCUMULATORS,
            [table(2, 1), table(2, 1), table(2, 3)],
        )
        .unwrap();
        assert_eq!(m.len(), 2);
        assert!(matches!(
            merge_train(KIND_CELL_ACCUMULATORS, [table(2, 1), table(3, 4)]),
            Err(CvError::Layout { .. })
        ));
        let solved = m.solve(&Default::default(), 2);
        let (cells, ok, fb) = solve_summary(&solved);
        assert_eq!(cells, 2);
        assert_eq!(ok + fb.values().sum::<u64>(), 2);
    }

    #[test]
    fn surrogate_of_constant_pixels_is_constant() {
        let blob = surrogate_blob(&job(), [&result(vec![])]).unwrap();
        let (v, w, h) = estimators::surrogate::decode_surrogate(&blob).unwrap();
        assert_eq!((w, h), (4, 2));
        assert!(v.iter().all(|x| (x - 0.5).abs() < 1e-6), "{v:?}");
    }
}
