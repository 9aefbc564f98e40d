//! A job's convergence series (DESIGN §6, `GET /v1/jobs/{id}/convergence.csv`): how the
//! estimated error fell as sample rounds completed. Computed on read from the stored task
//! rows and results, so it needs no state of its own and works for running jobs (it then
//! lists the rounds completed so far).
//!
//! # Definition
//! A **round** is the set of tasks of one phase with one sample range, over all tiles. Done
//! tasks are taken in completion order (`done_ms`, ties by phase and canonical `seq`); when
//! the last task of a round is done, one row is written from the image assembled from **every
//! task done so far** (whatever its round), merged **in canonical order** (phase, `seq`) with
//! [`ImageAccumulator`]:
//!
//! | column | meaning |
//! |---|---|
//! | `seconds` | completion time of the round's last task − job submission, in seconds |
//! | `spp` | mean samples per pixel of that image ([`AssembledImage::mean_spp`]) |
//! | `rel_mse_est` | its relMSE estimated from per-pixel variance ([`AssembledImage::estimated_rel_mse`]) |
//! | `tasks_done` | tasks merged into it |
//!
//! Because the merge order is canonical, the row of the last round of a finished single-phase
//! job is computed from exactly the sums `finish` assembles, so its `rel_mse_est` equals
//! `stats.json`'s `estimated_rel_mse` bit for bit. A phased CV job's rows merge its render
//! rounds plainly with the earlier phases' samples; its final image weighs them by variance
//! ([`ImageAccumulator::add_controlled`]), so there the last row overstates the image's error
//! (by the gain of that weighting: ≈ 10 % of relMSE where the CV pays).
//!
//! # Cost
//! Re-merging every done task at every round would cost O(rounds² × pixels). Instead, when the
//! tasks' rectangles do not overlap one another (the canonical plan: every phase uses the same
//! tiles), each tile keeps its own accumulator of its done tasks in canonical order (appended
//! to in place when a task arrives in order, re-merged from that tile's tasks only when one
//! arrives out of order), and a row composes the tiles into the image. Adding a tile's sums to
//! a zero image reproduces them exactly (`0.0 + s == s`; sums are never `-0.0`), so the
//! composed image equals the canonical full merge bit for bit. Overlapping rectangles fall back
//! to the full merge per row.

use std::collections::{BTreeMap, HashMap};
use std::fmt::Write as _;

use protocol::TileResult;
use protocol::assemble::{AssembledImage, ImageAccumulator};
use protocol::frame::{self, TileHeader};
use protocol::job::TileRect;

/// One task of a job as the series needs it: identity, extent, and its result when done.
#[derive(Clone, Debug)]
pub struct TaskSample {
    /// Phase index.
    pub phase_idx: i64,
    /// Canonical position within the phase.
    pub seq: i64,
    /// Pixels.
    pub rect: TileRect,
    /// First sample index.
    pub sample_start: u32,
    /// End sample index (exclusive).
    pub sample_end: u32,
    /// Completion time (ms since the epoch); `None` while not done.
    pub done_ms: Option<i64>,
    /// The accepted result's frame stream; `None` while not done.
    pub data: Option<Vec<u8>>,
}

/// One row of `convergence.csv` (see the module docs).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ConvergenceRow {
    /// Seconds since submission when the round completed.
    pub seconds: f64,
    /// Mean samples per pixel merged so far.
    pub spp: f64,
    /// relMSE estimated from per-pixel variance.
    pub rel_mse_est: f64,
    /// Tasks merged so far.
    pub tasks_done: u64,
}

/// Why a series could not be computed (stored results are validated on upload, so these mean
/// a corrupt store).
#[derive(Debug, thiserror::Error)]
pub enum ConvergenceError {
    /// A done task has no stored result.
    #[error("task {phase_idx}/{seq} is done but has no stored result")]
    MissingResult {
        /// Phase index.
        phase_idx: i64,
        /// Canonical position.
        seq: i64,
    },
    /// A stored result does not decode.
    #[error("result of task {phase_idx}/{seq}: {message}")]
    Decode {
        /// Phase index.
        phase_idx: i64,
        /// Canonical position.
        seq: i64,
        /// The decoder's message.
        message: String,
    },
    /// A result does not fit its task's rectangle or the image.
    #[error("result of task {phase_idx}/{seq} does not fit: {message}")]
    Geometry {
        /// Phase index.
        phase_idx: i64,
        /// Canonical position.
        seq: i64,
        /// What does not fit.
        message: String,
    },
}

/// CSV header line (without newline).
pub const CSV_HEADER: &str = "seconds,spp,rel_mse_est,tasks_done";

/// Canonical merge key of a task.
type Key = (i64, i64);

/// A done task's pixels, shifted to its rectangle's origin (`header.rect.x0 = y0 = 0`).
struct Done {
    key: Key,
    tile: TileResult,
}

/// The done tasks of one rectangle and their canonical-order sums.
struct TileSums {
    rect: TileRect,
    /// Sorted by key.
    done: Vec<Done>,
    acc: ImageAccumulator,
    /// `acc` no longer equals the canonical merge of `done` (a task arrived out of order).
    dirty: bool,
}

impl TileSums {
    fn new(rect: TileRect) -> Self {
        Self {
            rect,
            done: Vec::new(),
            acc: ImageAccumulator::new(rect.width, rect.height),
            dirty: false,
        }
    }

    fn insert(&mut self, d: Done) -> Result<(), ConvergenceError> {
        let in_order = self.done.last().is_none_or(|last| last.key < d.key);
        if in_order {
            // Appending in canonical order: the same additions the full merge makes.
            if !self.dirty {
                add(&mut self.acc, &d.tile, d.key)?;
            }
            self.done.push(d);
        } else {
            let at = self.done.partition_point(|x| x.key < d.key);
            self.done.insert(at, d);
            self.dirty = true;
        }
        Ok(())
    }

    /// The canonical-order sums of the done tasks.
    fn sums(&mut self) -> Result<&ImageAccumulator, ConvergenceError> {
        if self.dirty {
            self.acc = ImageAccumulator::new(self.rect.width, self.rect.height);
            for d in &self.done {
                add(&mut self.acc, &d.tile, d.key)?;
            }
            self.dirty = false;
        }
        Ok(&self.acc)
    }
}

fn add(acc: &mut ImageAccumulator, tile: &TileResult, key: Key) -> Result<(), ConvergenceError> {
    acc.add(tile).map_err(|e| ConvergenceError::Geometry {
        phase_idx: key.0,
        seq: key.1,
        message: e.to_string(),
    })
}

/// Whether the distinct rectangles of `rects` are pairwise disjoint (and inside the image).
fn disjoint(rects: &[TileRect], width: u32, height: u32) -> bool {
    let mut owner = vec![u32::MAX; width as usize * height as usize];
    for (i, r) in rects.iter().enumerate() {
        if !r.fits_in(width, height) {
            return false;
        }
        for y in r.y0..r.y0 + r.height {
            let row = y as usize * width as usize;
            for x in r.x0..r.x0 + r.width {
                let o = &mut owner[row + x as usize];
                if *o != u32::MAX {
                    return false;
                }
                *o = i as u32;
            }
        }
    }
    true
}

/// How a row's image is assembled.
enum Assembly {
    /// Disjoint rectangles: per-tile sums, composed per row.
    Tiles(Vec<TileSums>, HashMap<TileRect, usize>),
    /// Overlapping rectangles: every done task, merged from scratch per row.
    Full(Vec<Done>),
}

impl Assembly {
    fn insert(&mut self, rect: TileRect, d: Done) -> Result<(), ConvergenceError> {
        match self {
            Self::Tiles(tiles, index) => {
                let i = *index.get(&rect).ok_or(ConvergenceError::Geometry {
                    phase_idx: d.key.0,
                    seq: d.key.1,
                    message: "rectangle of no task".into(),
                })?;
                tiles[i].insert(d)
            }
            Self::Full(done) => {
                let at = done.partition_point(|x| x.key < d.key);
                done.insert(at, d);
                Ok(())
            }
        }
    }

    fn image(&mut self, width: u32, height: u32) -> Result<AssembledImage, ConvergenceError> {
        let mut img = ImageAccumulator::new(width, height);
        match self {
            Self::Tiles(tiles, _) => {
                for t in tiles.iter_mut().filter(|t| !t.done.is_empty()) {
                    let rect = t.rect;
                    let key = t.done[0].key;
                    let block = TileResult {
                        header: TileHeader {
                            job_id: 0,
                            task_id: 0,
                            attempt: 0,
                            rect,
                            sample_start: 0,
                            sample_end: 0,
                        },
                        pixels: t.sums()?.pixels().to_vec(),
                        cells: Vec::new(),
                    };
                    add(&mut img, &block, key)?;
                }
            }
            Self::Full(done) => {
                for d in done.iter() {
                    add(&mut img, &d.tile, d.key)?;
                }
            }
        }
        Ok(img.finish())
    }
}

/// The convergence series of a `width`×`height` job submitted at `created_ms`, from all of
/// its tasks (done or not: a round's size counts every task). `max_pixels` bounds a decoded
/// tile, as on upload. Pure: the same rows give the same series.
pub fn series(
    width: u32,
    height: u32,
    created_ms: i64,
    tasks: &[TaskSample],
    max_pixels: usize,
) -> Result<Vec<ConvergenceRow>, ConvergenceError> {
    // Round sizes.
    let mut round_total: BTreeMap<(i64, u32, u32), u64> = BTreeMap::new();
    for t in tasks {
        *round_total
            .entry((t.phase_idx, t.sample_start, t.sample_end))
            .or_default() += 1;
    }
    let mut rects: Vec<TileRect> = tasks.iter().map(|t| t.rect).collect();
    rects.sort_by_key(|r| (r.y0, r.x0, r.height, r.width));
    rects.dedup();
    let mut assembly = if disjoint(&rects, width, height) {
        let index = rects.iter().enumerate().map(|(i, r)| (*r, i)).collect();
        Assembly::Tiles(rects.iter().map(|r| TileSums::new(*r)).collect(), index)
    } else {
        Assembly::Full(Vec::new())
    };

    let mut done: Vec<&TaskSample> = tasks.iter().filter(|t| t.done_ms.is_some()).collect();
    done.sort_by_key(|t| (t.done_ms, t.phase_idx, t.seq));
    let mut round_done: BTreeMap<(i64, u32, u32), u64> = BTreeMap::new();
    let mut rows = Vec::new();
    for (n, t) in done.iter().enumerate() {
        let key = (t.phase_idx, t.seq);
        let data = t.data.as_deref().ok_or(ConvergenceError::MissingResult {
            phase_idx: key.0,
            seq: key.1,
        })?;
        let mut tile = frame::decode(data, max_pixels).map_err(|e| ConvergenceError::Decode {
            phase_idx: key.0,
            seq: key.1,
            message: e.to_string(),
        })?;
        if tile.header.rect != t.rect {
            return Err(ConvergenceError::Geometry {
                phase_idx: key.0,
                seq: key.1,
                message: format!("result covers {:?}, task {:?}", tile.header.rect, t.rect),
            });
        }
        tile.cells = Vec::new();
        if matches!(assembly, Assembly::Tiles(..)) {
            tile.header.rect.x0 = 0;
            tile.header.rect.y0 = 0;
        }
        assembly.insert(t.rect, Done { key, tile })?;

        let round = (t.phase_idx, t.sample_start, t.sample_end);
        let d = round_done.entry(round).or_default();
        *d += 1;
        if Some(&*d) == round_total.get(&round) {
            let img = assembly.image(width, height)?;
            rows.push(ConvergenceRow {
                seconds: (t.done_ms.unwrap_or(created_ms) - created_ms).max(0) as f64 / 1000.0,
                spp: img.mean_spp(),
                rel_mse_est: img.estimated_rel_mse(),
                tasks_done: n as u64 + 1,
            });
        }
    }
    Ok(rows)
}

/// The CSV text of a series: [`CSV_HEADER`], then one line per row. Floats are written in
/// Rust's shortest round-trip form, so parsing them gives back the exact values.
pub fn to_csv(rows: &[ConvergenceRow]) -> String {
    let mut out = String::with_capacity(32 * (rows.len() + 1));
    out.push_str(CSV_HEADER);
    out.push('\n');
    for r in rows {
        let _ = writeln!(
            out,
            "{},{},{},{}",
            r.seconds, r.spp, r.rel_mse_est, r.tasks_done
        );
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use protocol::frame::PixelRecord;

    const W: u32 = 8;
    const H: u32 = 4;

    /// A pseudo-random but fixed pixel block for (tile, range): values differ per pixel and
    /// per range so that merge order would show in the low bits.
    fn result(rect: TileRect, start: u32, end: u32) -> Vec<u8> {
        let n = u64::from(end - start);
        let pixels = (0..rect.pixel_count())
            .map(|i| {
                let v = 0.1 + ((i as f64 + 1.3) * (f64::from(start) + 0.7)).sin().abs();
                let mut p = PixelRecord {
                    count: n,
                    ..PixelRecord::default()
                };
                for c in 0..3 {
                    let x = v * (1.0 + c as f64 / 7.0);
                    p.sum[c] = x * n as f64;
                    p.sum_sq[c] = x * x * n as f64 * 1.37;
                    p.albedo[c] = 0.5 * n as f64;
                }
                p
            })
            .collect();
        TileResult {
            header: TileHeader {
                job_id: 1,
                task_id: 1,
                attempt: 1,
                rect,
                sample_start: start,
                sample_end: end,
            },
            pixels,
            cells: vec![],
        }
        .encode()
    }

    /// Two 4×4 tiles × `ranges` ranges of 2 samples, canonical order tile-major; `done_at`
    /// gives each task's completion time (None: not done).
    fn plan(ranges: u32, done_at: impl Fn(i64) -> Option<i64>) -> Vec<TaskSample> {
        let mut out = Vec::new();
        let mut seq = 0;
        for tile in 0..2u32 {
            let rect = TileRect {
                x0: tile * 4,
                y0: 0,
                width: 4,
                height: H,
            };
            for r in 0..ranges {
                let (s, e) = (2 * r, 2 * r + 2);
                let done_ms = done_at(seq);
                out.push(TaskSample {
                    phase_idx: 0,
                    seq,
                    rect,
                    sample_start: s,
                    sample_end: e,
                    done_ms,
                    data: done_ms.map(|_| result(rect, s, e)),
                });
                seq += 1;
            }
        }
        out
    }

    /// The canonical full merge of every done task (what `finish` does).
    fn full_merge(tasks: &[TaskSample]) -> AssembledImage {
        let mut sorted: Vec<&TaskSample> = tasks.iter().filter(|t| t.done_ms.is_some()).collect();
        sorted.sort_by_key(|t| (t.phase_idx, t.seq));
        let mut acc = ImageAccumulator::new(W, H);
        for t in sorted {
            acc.add(&frame::decode(t.data.as_ref().unwrap(), 1 << 20).unwrap())
                .unwrap();
        }
        acc.finish()
    }

    #[test]
    fn one_row_per_round_with_spp_increasing_and_the_last_equal_to_the_full_merge() {
        // Completion order interleaves tiles and ranges out of canonical order.
        let order = [5i64, 0, 3, 1, 4, 2];
        let tasks = plan(3, |seq| {
            Some(1_000 + 100 * order.iter().position(|&s| s == seq).unwrap() as i64)
        });
        let rows = series(W, H, 1_000, &tasks, 1 << 20).unwrap();
        assert_eq!(rows.len(), 3);
        for w in rows.windows(2) {
            assert!(w[1].spp > w[0].spp, "{rows:?}");
            assert!(w[1].seconds >= w[0].seconds);
            assert!(w[1].tasks_done > w[0].tasks_done);
        }
        let last = rows.last().unwrap();
        let full = full_merge(&tasks);
        assert_eq!(
            last.rel_mse_est.to_bits(),
            full.estimated_rel_mse().to_bits()
        );
        assert_eq!(last.spp, 6.0);
        assert_eq!(last.tasks_done, 6);
        assert_eq!(last.seconds, 0.5);
    }

    #[test]
    fn every_row_equals_the_full_merge_of_the_tasks_done_by_then() {
        let order = [4i64, 3, 0, 5, 2, 1];
        let t_of = |seq: i64| 10 * order.iter().position(|&s| s == seq).unwrap() as i64;
        let tasks = plan(3, |seq| Some(t_of(seq)));
        let rows = series(W, H, 0, &tasks, 1 << 20).unwrap();
        for row in &rows {
            let cut = (row.seconds * 1000.0).round() as i64;
            let prefix: Vec<TaskSample> = tasks
                .iter()
                .filter(|t| t.done_ms.is_some_and(|d| d <= cut))
                .cloned()
                .collect();
            assert_eq!(prefix.len() as u64, row.tasks_done);
            let img = full_merge(&prefix);
            assert_eq!(row.rel_mse_est.to_bits(), img.estimated_rel_mse().to_bits());
            assert_eq!(row.spp.to_bits(), img.mean_spp().to_bits());
        }
    }

    #[test]
    fn overlapping_rectangles_use_the_full_merge() {
        let mut tasks = plan(1, Some);
        // A second phase over the whole image overlaps both tiles.
        let whole = TileRect {
            x0: 0,
            y0: 0,
            width: W,
            height: H,
        };
        tasks.push(TaskSample {
            phase_idx: 1,
            seq: 0,
            rect: whole,
            sample_start: 2,
            sample_end: 4,
            done_ms: Some(10),
            data: Some(result(whole, 2, 4)),
        });
        let rows = series(W, H, 0, &tasks, 1 << 20).unwrap();
        assert_eq!(rows.len(), 2);
        assert_eq!(
            rows[1].rel_mse_est.to_bits(),
            full_merge(&tasks).estimated_rel_mse().to_bits()
        );
        assert_eq!(rows[1].spp, 4.0);
    }

    #[test]
    fn running_job_lists_completed_rounds_only() {
        // Range 0 done on both tiles, range 1 on one tile only.
        let tasks = plan(2, |seq| (seq != 3).then_some(seq * 5));
        let rows = series(W, H, 0, &tasks, 1 << 20).unwrap();
        assert_eq!(rows.len(), 1);
        assert_eq!(rows[0].tasks_done, 3);
        assert!(
            series(W, H, 0, &plan(2, |_| None), 1 << 20)
                .unwrap()
                .is_empty()
        );
    }

    #[test]
    fn corrupt_rows_are_errors_not_panics() {
        let mut tasks = plan(1, Some);
        tasks[0].data = None;
        assert!(matches!(
            series(W, H, 0, &tasks, 1 << 20),
            Err(ConvergenceError::MissingResult { .. })
        ));
        let mut tasks = plan(1, Some);
        tasks[1].data = Some(b"garbage".to_vec());
        assert!(matches!(
            series(W, H, 0, &tasks, 1 << 20),
            Err(ConvergenceError::Decode { .. })
        ));
        let mut tasks = plan(1, Some);
        tasks[1].data = tasks[0].data.clone();
        assert!(matches!(
            series(W, H, 0, &tasks, 1 << 20),
            Err(ConvergenceError::Geometry { .. })
        ));
    }

    #[test]
    fn csv_round_trips_the_values() {
        let rows = [ConvergenceRow {
            seconds: 1.25,
            spp: 3.0,
            rel_mse_est: 0.1 + 0.2,
            tasks_done: 7,
        }];
        let csv = to_csv(&rows);
        let mut lines = csv.lines();
        assert_eq!(lines.next(), Some(CSV_HEADER));
        let f: Vec<&str> = lines.next().unwrap().split(',').collect();
        assert_eq!(f[2].parse::<f64>().unwrap(), 0.1 + 0.2);
        assert_eq!(f[3], "7");
    }
}
