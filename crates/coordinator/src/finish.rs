//! The phase machine: what happens when the last task of a job's active phase is done.
//!
//! - **Barrier** (a CV job's `surrogate` or `train` phase is complete): the phase's results
//!   are read in canonical task order and turned into the next phase's input with the shared
//!   functions of [`protocol::cv`] — the surrogate image [Hua §4.2.1] after `surrogate`; the
//!   training tables (stored apart from the pixels), checked, merged key-range-parallel (the
//!   bits of the sequential merge) and solved per cell [Hua eq. 32–33] on a blocking thread
//!   with all cores, after `train`. The blob is stored content-addressed, then one transaction moves
//!   the job to the next phase and records the address on that phase's row
//!   (`phases.surrogate` / `phases.coefficients`), where its leases read it.
//! - **Finish** (the last phase is complete): the image is assembled from **all** phases'
//!   pixel blocks in (phase, task) order (so the EXR is bitwise-identical for any number of
//!   workers), then `image.exr` (layers beauty, variance, albedo, normal), `preview.png` and
//!   `stats.json` are stored and the job is marked done.
//!
//! - **Rounds** (the render phase of a `time_budget_s` / `target_rel_mse` job, planned
//!   round-major by [`protocol::job::plan_phases_ordered`]): each round — one sample range
//!   of every tile — is checked **in order** once it and all earlier rounds are done
//!   ([`check_rounds`]); after the first round whose image meets the error target (or whose
//!   last result arrived after the time budget was spent) the remaining tasks are `skipped`
//!   and the job finishes with the rounds so far. `spp` is the cap. For `target_rel_mse` the
//!   stop round, hence the image, is a function of the job alone.
//!
//! Idempotent and restart-safe: barrier blobs and outputs are deterministic and inserted
//! with `ON CONFLICT DO NOTHING`; the phase moves on (and the job turns `done`) only after
//! they are stored, in a conditional update that exactly one caller wins. Whoever gets there
//! first — the upload that completed the phase, the reaper after a crash, another
//! coordinator on the same PostgreSQL — does it; the others change nothing.

use std::time::Instant;

use protocol::assemble::ImageAccumulator;
use protocol::cv;
use protocol::hash::sha256_hex;
use protocol::job::{JobSpec, PhasedEstimator, ResolvedJob};
use protocol::lease::{BarrierStats, JobState, JobStats, PhaseKind, PhaseStats};
use protocol::{TileResult, frame};

use crate::AppState;
use crate::store::{JobRow, PhaseRow, StoreError, StoredTable, now_ms};

/// Why advancing failed.
#[derive(Debug, thiserror::Error)]
pub enum FinishError {
    /// The store failed.
    #[error(transparent)]
    Store(#[from] StoreError),
    /// A stored result does not decode or fit (should be impossible: uploads are validated).
    #[error("stored result: {0}")]
    Corrupt(String),
    /// Writing the image failed.
    #[error("image: {0}")]
    Image(String),
}

/// Content type of each output.
pub const OUTPUTS: [(&str, &str); 3] = [
    ("image.exr", "image/x-exr"),
    ("preview.png", "image/png"),
    ("stats.json", "application/json"),
];

/// What [`advance_job`] did.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Advance {
    /// Nothing: the job is not running, its phase is incomplete, or another caller won.
    Nothing,
    /// The job moved on to the next phase.
    NextPhase,
    /// The job finished.
    Finished,
}

/// The jobs one coordinator process is advancing, each with a flag "asked again meanwhile".
///
/// A barrier or an assembly is CPU work of a fraction of a second to seconds; without this,
/// the reaper's pass and the upload that completed a phase (or two uploads) would both do it
/// at once, the loser's work thrown away by the conditional update — on a farm whose
/// coordinator shares cores with workers that is CPU taken from rendering. A second caller
/// in the same process therefore only raises the flag and returns; the caller doing the
/// work looks again before it lets go, so no request to advance is lost (when that caller
/// fails, the reaper's next pass advances the job, as after a crash). Correctness never
/// depends on it (coordinators on one PostgreSQL still race safely, as documented above),
/// and it holds nothing a restart would need.
#[derive(Debug, Default)]
pub struct Advancing(std::sync::Mutex<std::collections::HashMap<i64, bool>>);

impl Advancing {
    fn lock(&self) -> std::sync::MutexGuard<'_, std::collections::HashMap<i64, bool>> {
        // The map is consistent after every statement: a poisoned lock is still usable.
        self.0
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// Claims `job_id`; `None` (and the flag raised) when this process is advancing it.
    fn claim(&self, job_id: i64) -> Option<AdvanceClaim<'_>> {
        let mut m = self.lock();
        if let Some(again) = m.get_mut(&job_id) {
            *again = true;
            return None;
        }
        m.insert(job_id, false);
        Some(AdvanceClaim {
            set: self,
            job_id,
            held: true,
        })
    }
}

/// A claim of [`Advancing`]; released by [`AdvanceClaim::release`] or when dropped (on
/// error or cancellation).
struct AdvanceClaim<'a> {
    set: &'a Advancing,
    job_id: i64,
    held: bool,
}

impl AdvanceClaim<'_> {
    /// Releases the claim unless somebody asked to advance the job meanwhile; then clears
    /// the flag, keeps the claim and returns `false` (the caller looks again). Check and
    /// release happen under one lock, so no request falls between them.
    fn release(&mut self) -> bool {
        let mut m = self.set.lock();
        if let Some(again) = m.get_mut(&self.job_id)
            && std::mem::take(again)
        {
            return false;
        }
        m.remove(&self.job_id);
        self.held = false;
        true
    }
}

impl Drop for AdvanceClaim<'_> {
    fn drop(&mut self) {
        if self.held {
            self.set.lock().remove(&self.job_id);
        }
    }
}

/// Advances `job_id` if it is running and its active phase is complete: runs the phase
/// barrier, or finishes the job after its last phase. When this process is already
/// advancing the job, returns [`Advance::Nothing`] at once and the running call looks
/// again when it is done ([`Advancing`]).
#[tracing::instrument(skip_all, fields(job = job_id))]
pub async fn advance_job(state: &AppState, job_id: i64) -> Result<Advance, FinishError> {
    let Some(mut claim) = state.advancing.claim(job_id) else {
        return Ok(Advance::Nothing);
    };
    let mut outcome = Advance::Nothing;
    loop {
        let step = advance_once(state, job_id).await?;
        if outcome == Advance::Nothing {
            outcome = step;
        }
        if claim.release() {
            return Ok(outcome);
        }
    }
}

async fn advance_once(state: &AppState, job_id: i64) -> Result<Advance, FinishError> {
    let store = &state.store;
    let Some(job) = store.job(job_id).await? else {
        return Ok(Advance::Nothing);
    };
    if job.state != JobState::Running {
        return Ok(Advance::Nothing);
    }
    let progress = store.progress(job_id, job.phase_idx).await?;
    if progress.done < progress.total {
        return Ok(Advance::Nothing);
    }
    let phases = store.phases(job_id).await?;
    let Some(active) = phases.iter().find(|p| p.idx == job.phase_idx).cloned() else {
        return Err(FinishError::Corrupt(format!(
            "job {job_id} has no phase {}",
            job.phase_idx
        )));
    };
    if phases.iter().any(|p| p.idx > active.idx) {
        barrier(state, &job, &active).await
    } else {
        // An adaptive phase may have met its target before its last round (e.g. when the
        // coordinator died before checking): decide that first, it changes the image.
        let phases = if check_rounds(state, job_id).await? {
            store.phases(job_id).await?
        } else {
            phases
        };
        finish(state, &job, &phases).await
    }
}

/// Tiles of the render phase, i.e. tasks per round.
fn tiles_per_round(r: &ResolvedJob) -> i64 {
    i64::from(r.width.div_ceil(r.tile_size)) * i64::from(r.height.div_ceil(r.tile_size))
}

/// Checks the completed rounds of an adaptive job's render phase in order (see the module
/// docs) and stops the phase after the first that meets the budget or target. Returns
/// whether this call stopped it. A no-op for other jobs and phases.
pub async fn check_rounds(state: &AppState, job_id: i64) -> Result<bool, FinishError> {
    let store = &state.store;
    let Some(job) = store.job_spec(job_id).await? else {
        return Ok(false);
    };
    let spec: JobSpec = serde_json::from_str(&job.spec)
        .map_err(|e| FinishError::Corrupt(format!("stored spec: {e}")))?;
    if !spec.is_adaptive() {
        return Ok(false);
    }
    let Some(current) = store.job(job_id).await? else {
        return Ok(false);
    };
    let phases = store.phases(job_id).await?;
    let Some(last) = phases.last() else {
        return Ok(false);
    };
    if current.phase_idx != last.idx
        || last.kind != PhaseKind::Render
        || last.stop_round.is_some()
        || !matches!(current.state, JobState::Running | JobState::Paused)
    {
        return Ok(false);
    }
    let per_round = tiles_per_round(&job.resolved).max(1);
    let tasks = store.task_states(job_id, last.idx).await?;
    let rounds = (tasks.len() as i64 + per_round - 1) / per_round;
    // Rounds 0..=complete are done.
    let mut complete = -1;
    for r in 0..rounds {
        let lo = (r * per_round) as usize;
        let hi = (((r + 1) * per_round) as usize).min(tasks.len());
        if tasks[lo..hi].iter().all(|t| t.state == "done") {
            complete = r;
        } else {
            break;
        }
    }
    for r in (last.rounds_checked + 1)..=complete {
        if r == rounds - 1 {
            // The last round ends the phase anyway.
            break;
        }
        let end_seq = (r + 1) * per_round;
        let stop = if let Some(budget) = spec.time_budget_s {
            let round_done = tasks[..end_seq as usize]
                .iter()
                .filter_map(|t| t.done_ms)
                .max()
                .unwrap_or(0);
            (round_done - job.created_ms) as f64 >= budget * 1000.0
        } else if let Some(target) = spec.target_rel_mse {
            rel_mse_through(state, &job, &phases, end_seq).await? <= target
        } else {
            false
        };
        if stop {
            let stopped = store.stop_after_round(job_id, last.idx, r, end_seq).await?;
            if stopped {
                tracing::info!(round = r, rounds, "adaptive render phase stopped");
            }
            return Ok(stopped);
        }
        store.set_rounds_checked(job_id, last.idx, r).await?;
    }
    Ok(false)
}

/// Estimated relMSE of the image of every earlier phase plus the last phase's tasks
/// `0..end_seq`, merged in canonical order.
async fn rel_mse_through(
    state: &AppState,
    job: &JobRow,
    phases: &[PhaseRow],
    end_seq: i64,
) -> Result<f64, FinishError> {
    let mut blobs = PhaseBlobs::default();
    for (i, p) in phases.iter().enumerate() {
        let mut b = state.store.phase_results(job.id, p.idx).await?;
        if i + 1 == phases.len() {
            b.truncate(end_seq.max(0) as usize);
        }
        blobs.push(state, p, b).await?;
    }
    let max_pixels = state.config.limits.max_pixels as usize;
    let r = job.resolved;
    tokio::task::spawn_blocking(move || {
        Ok(blobs
            .assemble(r.width, r.height, max_pixels)?
            .estimated_rel_mse())
    })
    .await
    .map_err(|e| FinishError::Image(e.to_string()))?
}

/// A job's stored results in canonical (phase, task) order, those of a render phase that ran
/// with the CV apart ([`ImageAccumulator::add_controlled`]).
#[derive(Default)]
struct PhaseBlobs {
    plain: Vec<Vec<u8>>,
    controlled: Vec<Vec<u8>>,
}

impl PhaseBlobs {
    /// Appends `blobs`, the results of `phase`.
    async fn push(
        &mut self,
        state: &AppState,
        phase: &PhaseRow,
        blobs: Vec<Vec<u8>>,
    ) -> Result<(), FinishError> {
        if renders_with_cv(state, phase).await? {
            self.controlled.extend(blobs);
        } else {
            self.plain.extend(blobs);
        }
        Ok(())
    }

    fn len(&self) -> usize {
        self.plain.len() + self.controlled.len()
    }

    /// The image: decoded on all cores, summed in canonical order (the bits do not depend on
    /// threads).
    fn assemble(
        &self,
        width: u32,
        height: u32,
        max_pixels: usize,
    ) -> Result<protocol::assemble::AssembledImage, FinishError> {
        let corrupt = |e: protocol::assemble::OutOfBounds| FinishError::Corrupt(e.to_string());
        let mut acc = ImageAccumulator::new(width, height);
        for t in decode_parallel(&self.plain, max_pixels)? {
            acc.add(&t).map_err(corrupt)?;
        }
        for t in decode_parallel(&self.controlled, max_pixels)? {
            acc.add_controlled(&t).map_err(corrupt)?;
        }
        Ok(acc.finish())
    }
}

/// Whether `phase` rendered with the CV: a render phase whose coefficient table controls
/// some cell ([`estimators::table::SolvedTable::controls_any`], the test the workers' tiles
/// make); its samples are then combined with the others by variance.
async fn renders_with_cv(state: &AppState, phase: &PhaseRow) -> Result<bool, FinishError> {
    let (PhaseKind::Render, Some(hash)) = (phase.kind, &phase.coefficients) else {
        return Ok(false);
    };
    let blob = state
        .store
        .get_blob(hash)
        .await?
        .ok_or_else(|| FinishError::Corrupt(format!("coefficient table {hash} is missing")))?;
    let solved = estimators::table::SolvedTable::decode(&blob)
        .map_err(|e| FinishError::Corrupt(format!("coefficient table {hash}: {e}")))?;
    Ok(solved.controls_any())
}

/// Finishes `job_id` if its last phase is complete (the reaper's and the upload's entry
/// point; the same as [`advance_job`]). Returns whether this call changed the job.
pub async fn finish_job(state: &AppState, job_id: i64) -> Result<bool, FinishError> {
    Ok(advance_job(state, job_id).await? != Advance::Nothing)
}

fn estimator_of(job: &JobRow) -> Result<Option<PhasedEstimator>, FinishError> {
    let spec: JobSpec = serde_json::from_str(&job.spec)
        .map_err(|e| FinishError::Corrupt(format!("stored spec: {e}")))?;
    Ok(spec.estimator.phased_for(&job.resolved))
}

/// A stored result frame (validated at upload: a failure here means a corrupt store).
fn decode_stored(blob: &[u8], max_pixels: usize) -> Result<TileResult, FinishError> {
    frame::decode(blob, max_pixels).map_err(|e| FinishError::Corrupt(e.to_string()))
}

/// [`decode_stored`] of every blob on all cores, results in order.
fn decode_parallel(blobs: &[Vec<u8>], max_pixels: usize) -> Result<Vec<TileResult>, FinishError> {
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    cv::map_ordered(blobs, threads, |b| decode_stored(b, max_pixels))
}

/// The barrier after `phase` (a surrogate or train phase of a CV job).
async fn barrier(state: &AppState, job: &JobRow, phase: &PhaseRow) -> Result<Advance, FinishError> {
    let store = &state.store;
    let Some(est) = estimator_of(job)? else {
        return Err(FinishError::Corrupt(format!(
            "job {} has several phases but estimator `{}` has none",
            job.id, job.estimator
        )));
    };
    tracing::debug!(phase = phase.kind.as_str(), "barrier: reading results");
    // The surrogate reads the pixel frames, training the stored tables — unless this
    // process folded every one of them as they were accepted ([`crate::train_merge`]).
    let folded = match phase.kind {
        PhaseKind::Train => {
            state
                .train_merges
                .take(job.id, phase.idx, phase.tasks)
                .await
        }
        _ => None,
    };
    let (blobs, tables) = match (phase.kind, &folded) {
        (_, Some(_)) => (Vec::new(), Vec::new()),
        (PhaseKind::Train, None) => (Vec::new(), store.phase_tables(job.id, phase.idx).await?),
        _ => (store.phase_results(job.id, phase.idx).await?, Vec::new()),
    };
    tracing::debug!(folded = folded.is_some(), "barrier: inputs ready");
    let results = blobs.len() + tables.len();
    if folded.is_none() && results as i64 != phase.tasks {
        return Err(FinishError::Corrupt(format!(
            "{results} results for {} tasks",
            phase.tasks
        )));
    }
    let resolved = job.resolved;
    let kind = phase.kind;
    let max_pixels = state.config.limits.max_pixels as usize;
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    // Decoding, denoising, merging and solving are CPU work: off the async threads.
    let (blob, stats) = tokio::task::spawn_blocking(move || {
        let t0 = Instant::now();
        let corrupt = |e: cv::CvError| FinishError::Corrupt(e.to_string());
        match kind {
            PhaseKind::Surrogate => {
                let tiles = decode_parallel(&blobs, max_pixels)?;
                let blob = cv::surrogate_blob(&resolved, &tiles).map_err(corrupt)?;
                let stats = BarrierStats {
                    seconds: t0.elapsed().as_secs_f64(),
                    blob: sha256_hex(&blob),
                    ..BarrierStats::default()
                };
                Ok((blob, stats))
            }
            PhaseKind::Train => {
                let merged = match folded {
                    Some(m) => m,
                    None => merge_stored(&est, &resolved, tables, max_pixels, threads)?,
                };
                let solved = merged.solve(&est.solve_policy(), threads);
                let blob = solved.encode();
                let (cells, cells_solved, cells_fallback) = cv::solve_summary(&solved);
                let stats = BarrierStats {
                    seconds: t0.elapsed().as_secs_f64(),
                    blob: sha256_hex(&blob),
                    cells,
                    cells_solved,
                    cells_fallback,
                    rejected_samples: solved.rejected,
                    predicted_image_gain: solved.image_gain,
                    predicted_fit_gain: solved.fit_gain,
                    predicted_held_out_gain: solved.held_out_gain,
                    predicted_held_out_share: solved.held_out_share,
                };
                Ok((blob, stats))
            }
            PhaseKind::Render => Err(FinishError::Corrupt(
                "a render phase is followed by another phase".into(),
            )),
        }
    })
    .await
    .map_err(|e| FinishError::Image(e.to_string()))??;
    // The blob first: a lease of the next phase must never name a missing blob.
    store.put_blob(&stats.blob, &blob).await?;
    let stats_json =
        serde_json::to_string(&stats).map_err(|e| FinishError::Image(e.to_string()))?;
    let (surrogate, coefficients) = match kind {
        PhaseKind::Surrogate => (Some(stats.blob.as_str()), None),
        _ => (None, Some(stats.blob.as_str())),
    };
    let advanced = store
        .advance_phase(job.id, phase.idx, &stats_json, surrogate, coefficients)
        .await?;
    if !advanced {
        return Ok(Advance::Nothing);
    }
    tracing::info!(
        phase = kind.as_str(),
        blob = %stats.blob,
        cells = stats.cells,
        solved = stats.cells_solved,
        seconds = stats.seconds,
        "phase barrier passed"
    );
    state.work_available.notify_waiters();
    Ok(Advance::NextPhase)
}

/// The train barrier's merge from the store: the stored tables (checked again) merged in
/// canonical order on `threads` threads.
fn merge_stored(
    est: &PhasedEstimator,
    resolved: &ResolvedJob,
    tables: Vec<StoredTable>,
    max_pixels: usize,
    threads: usize,
) -> Result<estimators::table::AccumulatorTable, FinishError> {
    let corrupt = |e: cv::CvError| FinishError::Corrupt(e.to_string());
    // Rows stored before tables were kept apart carry them inside the frame.
    let tables = tables
        .into_iter()
        .map(|t| match t {
            StoredTable::Table(b) => Ok(b),
            StoredTable::Frame(f) => {
                let tile = decode_stored(&f, max_pixels)?;
                match <[_; 1]>::try_from(tile.cells) {
                    Ok([block]) => Ok(block.data),
                    Err(c) => Err(corrupt(cv::CvError::BlockCount(c.len()))),
                }
            }
        })
        .collect::<Result<Vec<_>, _>>()?;
    let tables = cv::check_train_tables(est, resolved, &tables, threads).map_err(corrupt)?;
    cv::merge_train(cv::table_kind(est), tables, threads).map_err(corrupt)
}

/// Assembles and stores the outputs after the last phase, then marks the job done.
async fn finish(
    state: &AppState,
    job: &JobRow,
    phases: &[PhaseRow],
) -> Result<Advance, FinishError> {
    let store = &state.store;
    let mut blobs = PhaseBlobs::default();
    let mut attempts = 0;
    for p in phases {
        let b = store.phase_results(job.id, p.idx).await?;
        if b.len() as i64 != p.tasks {
            return Err(FinishError::Corrupt(format!(
                "phase {}: {} results for {} tasks",
                p.kind.as_str(),
                b.len(),
                p.tasks
            )));
        }
        attempts += store.progress(job.id, p.idx).await?.attempts;
        blobs.push(state, p, b).await?;
    }
    tracing::debug!(results = blobs.len(), "assembly: results read");
    let max_pixels = state.config.limits.max_pixels as usize;
    let (job2, phases2) = (job.clone(), phases.to_vec());
    // Decoding, summing and EXR encoding are CPU work: keep them off the async workers.
    let outputs = tokio::task::spawn_blocking(move || {
        build_outputs(&job2, &blobs, max_pixels, attempts, &phases2)
    })
    .await
    .map_err(|e| FinishError::Image(e.to_string()))??;
    tracing::debug!("assembly: outputs encoded");
    for ((name, ctype), data) in OUTPUTS.iter().zip(&outputs) {
        store.put_artifact(job.id, name, ctype, data).await?;
    }
    if let Some(last) = phases.last() {
        store.finish_phase(job.id, last.idx).await?;
    }
    let finished = store.end_job(job.id, JobState::Done, None).await?;
    if finished {
        tracing::info!("job finished");
        Ok(Advance::Finished)
    } else {
        Ok(Advance::Nothing)
    }
}

fn build_outputs(
    job: &JobRow,
    blobs: &PhaseBlobs,
    max_pixels: usize,
    attempts: i64,
    phases: &[PhaseRow],
) -> Result<[Vec<u8>; 3], FinishError> {
    let r = &job.resolved;
    let img = blobs.assemble(r.width, r.height, max_pixels)?;
    // The EXR and the preview are independent: encoded side by side.
    let (exr, png) = std::thread::scope(|s| {
        let png = s.spawn(|| {
            let rgb = triples(&img.beauty);
            imageio::encode_png_preview(img.width, img.height, &rgb)
                .map_err(|e| FinishError::Image(e.to_string()))
        });
        let exr = encode_exr(&img);
        (exr, png.join().expect("preview thread panicked"))
    });
    let (exr, png) = (exr?, png?);
    let now = now_ms();
    let stats = JobStats {
        job_id: job.id,
        estimator: job.estimator.clone(),
        job: *r,
        phases: phases
            .iter()
            .map(|p| PhaseStats {
                name: p.kind.as_str().to_owned(),
                seconds: match (p.started_ms, p.last_done_ms) {
                    (Some(s), Some(e)) => (e - s).max(0) as f64 / 1000.0,
                    _ => 0.0,
                },
                tasks: p.tasks.max(0) as u64,
                // An adaptive phase that stopped early rendered only its first rounds.
                spp: match p.stop_round {
                    Some(round) => {
                        let rounds = u64::try_from(round + 1).unwrap_or(0);
                        let done = rounds * u64::from(r.samples_per_task);
                        p.spp.min(u32::try_from(done).unwrap_or(u32::MAX))
                    }
                    None => p.spp,
                },
                barrier: p
                    .barrier
                    .as_deref()
                    .and_then(|b| serde_json::from_str::<BarrierStats>(b).ok()),
            })
            .collect(),
        total_seconds: (now - job.created_ms).max(0) as f64 / 1000.0,
        spp: img.mean_spp(),
        estimated_rel_mse: img.estimated_rel_mse(),
        tasks: blobs.len() as u64,
        attempts: attempts.max(0) as u64,
        effects: job.effects.clone(),
        uncontrolled_weight: img.uncontrolled_weight,
    };
    let stats = serde_json::to_vec_pretty(&stats).map_err(|e| FinishError::Image(e.to_string()))?;
    Ok([exr, png, stats])
}

fn triples(v: &[f32]) -> Vec<[f32; 3]> {
    v.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect()
}

/// Multi-layer EXR of an assembled image (beauty first, as `imageio` expects).
pub fn encode_exr(img: &protocol::assemble::AssembledImage) -> Result<Vec<u8>, FinishError> {
    let layers = [
        (imageio::BEAUTY, &img.beauty),
        ("variance", &img.variance),
        ("albedo", &img.albedo),
        ("normal", &img.normal),
    ]
    .map(|(name, data)| imageio::RgbLayer {
        name: name.to_owned(),
        data: triples(data),
    });
    imageio::encode_exr(img.width, img.height, &layers)
        .map_err(|e| FinishError::Image(e.to_string()))
}

#[cfg(test)]
mod tests {
    use super::Advancing;

    #[test]
    fn a_second_caller_is_turned_away_and_its_request_kept() {
        let set = Advancing::default();
        let mut first = set.claim(7).expect("free job");
        assert!(set.claim(7).is_none(), "claimed twice");
        // Another job is independent.
        assert!(set.claim(8).is_some());
        // The turned-away request makes the holder look again instead of letting go…
        assert!(!first.release());
        // …once: with nobody asking, it lets go.
        assert!(first.release());
        drop(first);
        let again = set.claim(7).expect("released");
        drop(again);
        assert!(set.claim(7).is_some(), "a dropped claim is released");
    }
}
