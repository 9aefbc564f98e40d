//! Finishing a job once its last phase is complete: assemble the image from the stored pixel
//! blocks **in canonical task order** (so the EXR is bitwise-identical for any number of
//! workers), then store `image.exr` (layers beauty, variance, albedo, normal), `preview.png`
//! and `stats.json`, and mark the job done.
//!
//! Idempotent and restart-safe: outputs are deterministic and inserted with
//! `ON CONFLICT DO NOTHING`, and the job turns `done` only after they are stored. Whoever gets
//! there first (the upload that completed the phase, or the reaper after a crash) finishes.

use protocol::assemble::ImageAccumulator;
use protocol::lease::{JobState, JobStats, PhaseStats};
use protocol::{TileResult, frame};

use crate::AppState;
use crate::store::{JobRow, StoreError, now_ms};

/// Why finishing failed.
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

/// Finishes `job_id` if it is running and its active phase is complete. Returns whether this
/// call finished it.
#[tracing::instrument(skip_all, fields(job = job_id))]
pub async fn finish_job(state: &AppState, job_id: i64) -> Result<bool, FinishError> {
    let store = &state.store;
    let Some(job) = store.job(job_id).await? else {
        return Ok(false);
    };
    if job.state != JobState::Running {
        return Ok(false);
    }
    let progress = store.progress(job_id, job.phase_idx).await?;
    if progress.done < progress.total {
        return Ok(false);
    }
    let blobs = store.phase_results(job_id, job.phase_idx).await?;
    if blobs.len() as i64 != progress.total {
        return Err(FinishError::Corrupt(format!(
            "{} results for {} tasks",
            blobs.len(),
            progress.total
        )));
    }
    let phases = store.phase_times(job_id).await?;
    let max_pixels = state.config.limits.max_pixels as usize;
    let job2 = job.clone();
    // Decoding, summing and EXR encoding are CPU work: keep them off the async workers.
    let outputs = tokio::task::spawn_blocking(move || {
        build_outputs(&job2, &blobs, max_pixels, progress.attempts, &phases)
    })
    .await
    .map_err(|e| FinishError::Image(e.to_string()))??;
    for ((name, ctype), data) in OUTPUTS.iter().zip(&outputs) {
        store.put_artifact(job_id, name, ctype, data).await?;
    }
    let finished = store.end_job(job_id, JobState::Done, None).await?;
    if finished {
        tracing::info!(tasks = progress.total, "job finished");
    }
    Ok(finished)
}

fn build_outputs(
    job: &JobRow,
    blobs: &[Vec<u8>],
    max_pixels: usize,
    attempts: i64,
    phases: &[(String, Option<i64>, Option<i64>)],
) -> Result<[Vec<u8>; 3], FinishError> {
    let r = &job.resolved;
    let mut acc = ImageAccumulator::new(r.width, r.height);
    for b in blobs {
        let tile: TileResult =
            frame::decode(b, max_pixels).map_err(|e| FinishError::Corrupt(e.to_string()))?;
        acc.add(&tile)
            .map_err(|e| FinishError::Corrupt(e.to_string()))?;
    }
    let img = acc.finish();
    let exr = encode_exr(&img)?;
    let rgb = triples(&img.beauty);
    let png = imageio::encode_png_preview(img.width, img.height, &rgb)
        .map_err(|e| FinishError::Image(e.to_string()))?;
    let now = now_ms();
    let stats = JobStats {
        job_id: job.id,
        estimator: job.estimator.clone(),
        job: *r,
        phases: phases
            .iter()
            .map(|(name, start, end)| PhaseStats {
                name: name.clone(),
                seconds: match (start, end) {
                    (Some(s), Some(e)) => (e - s).max(0) as f64 / 1000.0,
                    _ => 0.0,
                },
                tasks: blobs.len() as u64,
            })
            .collect(),
        total_seconds: (now - job.created_ms).max(0) as f64 / 1000.0,
        spp: img.mean_spp(),
        estimated_rel_mse: img.estimated_rel_mse(),
        tasks: blobs.len() as u64,
        attempts: attempts.max(0) as u64,
        effects: job.effects.clone(),
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
