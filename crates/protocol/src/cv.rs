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

use estimators::solve::{CellHalves, SolveStatus};
use estimators::spec::{
    MAX_GRID_CELLS, MAX_GRID_INDICES, MAX_GRID_LEVELS, PhasedEstimator, finest_grid_cells,
    grid_indices,
};
use estimators::surrogate::{encode_surrogate, surrogate_image};
use estimators::table::{
    AccumulatorTable, KIND_CELL_ACCUMULATORS, KIND_MEAN_CONTRIBUTIONS, MergeRecord, SolvedTable,
};

use crate::assemble::{ImageAccumulator, OutOfBounds};
use crate::frame::TileResult;
use crate::job::ResolvedJob;

/// Cells per grid cell: the renderer splits every grid cell by the dominant axis and sign of
/// the shading normal (`render::integrator::cv::NORMAL_BINS`).
pub const NORMAL_BINS: u64 = estimators::spec::NORMAL_BINS as u64;

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

/// Exclusive bound of the cell keys of a job's training tables: pixels for `optimal_mis`
/// (cells = pixels [Hua §7.4]), else cell indices × [`NORMAL_BINS`] (grid cells ×
/// 9^`grid_levels`, the grid's own or [`MAX_GRID_CELLS`] for the adaptive one; at most
/// [`MAX_GRID_INDICES`]), twice that when the job's solve policy records
/// each cell's two halves apart (`cms`).
pub fn cell_key_limit(est: &PhasedEstimator, job: &ResolvedJob) -> u64 {
    let grid = match est {
        PhasedEstimator::OptimalMis(_) => None,
        PhasedEstimator::Cms(o) => Some(o.grid_resolution),
        PhasedEstimator::PerLightCv(o) => Some(o.grid_resolution),
    };
    let cells = match grid {
        None => u64::from(job.width) * u64::from(job.height),
        Some(g) => {
            // The cell indices: `grid_levels` subdivisions of `CELL_CHILDREN` each.
            let levels = est.grid_levels().min(MAX_GRID_LEVELS);
            let cells = match g {
                Some(g) => finest_grid_cells(g, levels),
                None => grid_indices(MAX_GRID_CELLS, levels),
            };
            cells.min(MAX_GRID_INDICES) * NORMAL_BINS
        }
    };
    // A job whose policy records each cell's two halves apart (`CellHalves`, `cms`).
    if est.solve_policy().halves == CellHalves::None {
        cells
    } else {
        2 * cells
    }
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
        AccumulatorTable::Moments(t, _) => uniform(
            t.values(),
            |a| {
                let l = a.layout();
                (l.partitions, l.overlapping, a.color())
            },
            |(p, o, c)| format!("cells(partitions={p}, overlapping={o}, {c:?})"),
        ),
        AccumulatorTable::Mean(t, _) => uniform(
            t.values(),
            |a| a.lights(),
            |n| format!("mean_contributions(lights={n})"),
        ),
    }
}

/// Validates the cell block of a `train` result: exactly one block, of the job's kind, whose
/// table passes [`check_train_table`]. Returns the decoded table.
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
    check_train_table(est, job, &block.data)
}

/// Validates an encoded training table (a `train` result's cell block, as the coordinator
/// stores it): it decodes (sizes, finite values: [`AccumulatorTable::decode`]), is of the
/// job's kind, has keys below [`cell_key_limit`] and one layout. Returns the decoded table.
pub fn check_train_table(
    est: &PhasedEstimator,
    job: &ResolvedJob,
    bytes: &[u8],
) -> Result<AccumulatorTable, CvError> {
    let expected = table_kind(est);
    let table = AccumulatorTable::decode(bytes).map_err(|e| CvError::Decode(e.to_string()))?;
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

/// [`check_train_table`] of every encoded table, on up to `threads` threads; the tables come
/// back in the order given, the first error (in that order) wins.
pub fn check_train_tables<B: AsRef<[u8]> + Sync>(
    est: &PhasedEstimator,
    job: &ResolvedJob,
    blobs: &[B],
    threads: usize,
) -> Result<Vec<AccumulatorTable>, CvError> {
    map_ordered(blobs, threads, |b| check_train_table(est, job, b.as_ref()))
}

/// `f` of every item on up to `threads` threads (contiguous chunks, one scoped thread each);
/// the outputs come back in the order given and the first error (in that order) wins. For
/// the decoding and checking of uploaded results, where each item is independent.
pub fn map_ordered<T: Sync, U: Send, E: Send>(
    items: &[T],
    threads: usize,
    f: impl Fn(&T) -> Result<U, E> + Sync,
) -> Result<Vec<U>, E> {
    let chunk = items.len().div_ceil(threads.max(1)).max(1);
    let f = &f;
    let parts: Vec<Result<Vec<U>, E>> = std::thread::scope(|s| {
        let handles: Vec<_> = items
            .chunks(chunk)
            .map(|c| s.spawn(move || c.iter().map(f).collect()))
            .collect();
        handles
            .into_iter()
            .map(|h| h.join().expect("worker thread panicked"))
            .collect()
    });
    let mut out = Vec::with_capacity(items.len());
    for p in parts {
        out.extend(p?);
    }
    Ok(out)
}

/// Merges training tables **in the order given** (canonical task order) into one table of
/// `kind`, on up to `threads` threads. Each cell's record is the fold of that cell's records
/// over the tables in order ([`estimators::table::merge_tables`]), so the key space can be
/// split among threads without changing a bit: the result is the sequential merge's for any
/// `threads`. All tables must be of `kind` and share one layout.
pub fn merge_train(
    kind: u16,
    tables: impl IntoIterator<Item = AccumulatorTable>,
    threads: usize,
) -> Result<AccumulatorTable, CvError> {
    let tables: Vec<AccumulatorTable> = tables.into_iter().collect();
    let mut layout: Option<String> = None;
    for t in &tables {
        if t.kind() != kind {
            return Err(CvError::WrongKind {
                found: t.kind(),
                expected: kind,
            });
        }
        if let Some(sig) = layout_signature(t)? {
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
    }
    let decode = |e: estimators::cell::CellError| CvError::Decode(e.to_string());
    let mut moments = Vec::new();
    let mut means = Vec::new();
    // The image variances summed in the tables' order, as `AccumulatorTable::merge` does.
    let mut image = Some(0.0);
    for t in tables {
        match t {
            AccumulatorTable::Moments(m, v) => {
                moments.push(m);
                image = estimators::table::add_image_variances(image, v);
            }
            AccumulatorTable::Mean(m, v) => {
                means.push(m);
                image = estimators::table::add_image_variances(image, v);
            }
        }
    }
    Ok(match AccumulatorTable::empty(kind).map_err(decode)? {
        AccumulatorTable::Moments(..) => {
            AccumulatorTable::Moments(merge_maps(&moments, threads).map_err(decode)?, image)
        }
        AccumulatorTable::Mean(..) => {
            AccumulatorTable::Mean(merge_maps(&means, threads).map_err(decode)?, image)
        }
    })
}

/// The key-by-key merge of `maps` in order, the key space split into up to `threads` ranges
/// of about equal record counts (taken from the largest map), one thread per range.
fn merge_maps<T: MergeRecord + Send + Sync>(
    maps: &[BTreeMap<u64, T>],
    threads: usize,
) -> Result<BTreeMap<u64, T>, estimators::cell::CellError> {
    let merge_range = |lo: u64, hi: Option<u64>| {
        let mut into = BTreeMap::new();
        for m in maps {
            let part = match hi {
                Some(hi) => m.range(lo..hi),
                None => m.range(lo..),
            };
            for (key, rec) in part {
                match into.get_mut(key) {
                    Some(acc) => MergeRecord::merge_record(acc, rec)?,
                    None => {
                        into.insert(*key, rec.clone());
                    }
                }
            }
        }
        Ok::<_, estimators::cell::CellError>(into)
    };
    let largest = maps.iter().max_by_key(|m| m.len());
    let threads = threads.max(1);
    let bounds: Vec<u64> = match largest {
        Some(m) if threads > 1 && m.len() >= 2 * threads => {
            let step = m.len() / threads;
            m.keys()
                .skip(step)
                .step_by(step)
                .take(threads - 1)
                .copied()
                .collect()
        }
        _ => Vec::new(),
    };
    if bounds.is_empty() {
        return merge_range(0, None);
    }
    let mut ranges: Vec<(u64, Option<u64>)> = Vec::with_capacity(bounds.len() + 1);
    let mut lo = 0;
    for &b in &bounds {
        ranges.push((lo, Some(b)));
        lo = b;
    }
    ranges.push((lo, None));
    let parts: Vec<Result<BTreeMap<u64, T>, _>> = std::thread::scope(|s| {
        let handles: Vec<_> = ranges
            .iter()
            .map(|&(lo, hi)| {
                let f = &merge_range;
                s.spawn(move || f(lo, hi))
            })
            .collect();
        handles
            .into_iter()
            .map(|h| h.join().expect("merge thread panicked"))
            .collect()
    });
    let mut out = BTreeMap::new();
    for p in parts {
        // Ranges are disjoint and ascending: appending keeps the map's order.
        out.append(&mut p?);
    }
    Ok(out)
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
            sampler: Default::default(),
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
        AccumulatorTable::Moments(BTreeMap::from([(key, a)]), Some(1.0))
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
        // `cms` keys are cell halves: twice the cell indices (81 per grid cell with the
        // default two levels).
        let far = table(2, 2 * MAX_GRID_CELLS * 81 * NORMAL_BINS);
        let near = table(2, 2 * MAX_GRID_CELLS * 81 * NORMAL_BINS - 1);
        assert!(check_train_block(&est, &job(), &result(vec![block(&near)])).is_ok());
        assert!(matches!(
            check_train_block(&est, &job(), &result(vec![block(&far)])),
            Err(CvError::KeyRange { .. })
        ));
        // A given grid: its cells subdivided `grid_levels` times, 9 indices per level
        // (`render::integrator::cv::Grid`), by default as many as fit the cell limit.
        let grid = |g: [u32; 3], levels: Option<u32>| {
            PhasedEstimator::Cms(estimators::spec::CmsOptions {
                grid_resolution: Some(g),
                grid_levels: levels,
                ..Default::default()
            })
        };
        let limit = |e: &PhasedEstimator| cell_key_limit(e, &job());
        assert_eq!(limit(&grid([4, 4, 4], None)), 64 * 81 * NORMAL_BINS * 2);
        assert_eq!(limit(&grid([4, 4, 4], Some(0))), 64 * NORMAL_BINS * 2);
        assert_eq!(limit(&grid([4, 4, 4], Some(1))), 64 * 9 * NORMAL_BINS * 2);
        assert_eq!(
            limit(&grid([64, 64, 64], None)),
            64 * 64 * 64 * 81 * NORMAL_BINS * 2
        );
        let adaptive = PhasedEstimator::Cms(Default::default());
        assert_eq!(limit(&adaptive), MAX_GRID_CELLS * 81 * NORMAL_BINS * 2);
        assert!(limit(&adaptive) <= 1 << 32);
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
            1,
        )
        .unwrap();
        assert_eq!(m.len(), 2);
        assert!(matches!(
            merge_train(KIND_CELL_ACCUMULATORS, [table(2, 1), table(3, 4)], 2),
            Err(CvError::Layout { .. })
        ));
        let solved = m.solve(&Default::default(), 2);
        let (cells, ok, fb) = solve_summary(&solved);
        assert_eq!(cells, 2);
        assert_eq!(ok + fb.values().sum::<u64>(), 2);
    }

    /// A table of tile `t`: keys overlapping the neighbouring tiles', each record with
    /// tile-dependent values so that merging in another order would change the bits.
    fn tile_table(t: u64) -> AccumulatorTable {
        let mut map = BTreeMap::new();
        for k in (t * 7)..(t * 7 + 23) {
            let mut a = CellAccumulator::new(ComponentLayout::new(3, 1).unwrap(), ColorMode::Rgb);
            for i in 0..3u32 {
                let x = 0.1 + ((k * 31 + t * 17 + u64::from(i)) % 97) as f64 / 13.0;
                let s = CvSample {
                    pdf: 0.7 + x,
                    partition: Some((i % 3, 0.3 + x / 7.0)),
                    overlapping: &[x / 3.0],
                };
                a.add(1.0 / 3.0, [x, x * x, 1.0 / x], &s).unwrap();
            }
            map.insert(k, a);
        }
        // Tile-dependent, so that a sum in another order would have other bits too.
        AccumulatorTable::Moments(map, Some(1.0 / (t as f64 + 3.0)))
    }

    #[test]
    fn merge_on_threads_gives_the_sequential_bits() {
        let tables: Vec<_> = (0..9).map(tile_table).collect();
        let mut sequential = AccumulatorTable::empty(KIND_CELL_ACCUMULATORS).unwrap();
        for t in &tables {
            sequential.merge(t).unwrap();
        }
        for threads in 1..=5 {
            let m = merge_train(KIND_CELL_ACCUMULATORS, tables.clone(), threads).unwrap();
            assert_eq!(m.len(), sequential.len());
            assert!(m.encode() == sequential.encode(), "{threads} threads");
        }
        // The order matters (so the test can fail): reversed input gives other bits.
        let mut rev = tables.clone();
        rev.reverse();
        let r = merge_train(KIND_CELL_ACCUMULATORS, rev, 3).unwrap();
        assert!(r.encode() != sequential.encode());
    }

    #[test]
    fn tables_are_checked_on_threads_in_order() {
        let est = PhasedEstimator::Cms(CmsOptions::default());
        let blobs: Vec<Vec<u8>> = (0..5).map(|t| tile_table(t).encode()).collect();
        let tables = check_train_tables(&est, &job(), &blobs, 2).unwrap();
        assert!(tables.iter().zip(0..).all(|(t, i)| *t == tile_table(i)));
        let mut bad = blobs.clone();
        bad[3].truncate(10);
        assert!(matches!(
            check_train_tables(&est, &job(), &bad, 2),
            Err(CvError::Decode(_))
        ));
    }

    #[test]
    fn surrogate_of_constant_pixels_is_constant() {
        let blob = surrogate_blob(&job(), [&result(vec![])]).unwrap();
        let (v, w, h) = estimators::surrogate::decode_surrogate(&blob).unwrap();
        assert_eq!((w, h), (4, 2));
        assert!(v.iter().all(|x| (x - 0.5).abs() < 1e-6), "{v:?}");
    }
}
