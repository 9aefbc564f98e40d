//! Times the pieces of a CV job's train barrier on a job already in a store: frame decode,
//! cell-block checks, merge in canonical order, solve, encode — the coordinator's
//! merge/solve throughput (DESIGN §8) without any rendering.
//!
//! ```text
//! cargo run -p coordinator --example barrier_timing -- sqlite:///tmp/farm/cvfarm.sqlite 1
//! ```

use std::time::Instant;

use coordinator::store::Store;
use protocol::JobSpec;
use protocol::cv;
use protocol::lease::PhaseKind;

#[tokio::main(flavor = "current_thread")]
async fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let (Some(url), Some(job)) = (args.next(), args.next()) else {
        return Err("usage: barrier_timing DATABASE_URL JOB_ID".into());
    };
    let job: i64 = job.parse()?;
    let store = Store::connect(&url).await?;
    let row = store.job(job).await?.ok_or("no such job")?;
    let spec: JobSpec = serde_json::from_str(&row.spec)?;
    let est = spec.estimator.phased().ok_or("not a CV job")?;
    let phases = store.phases(job).await?;
    let train = phases
        .iter()
        .find(|p| p.kind == PhaseKind::Train)
        .ok_or("no train phase")?;
    let blobs = store.phase_results(job, train.idx).await?;
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    let t = Instant::now();
    let tiles = blobs
        .iter()
        .map(|b| protocol::frame::decode(b, 1 << 26))
        .collect::<Result<Vec<_>, _>>()?;
    let t_frames = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let tables = tiles
        .iter()
        .map(|r| cv::check_train_block(&est, &row.resolved, r))
        .collect::<Result<Vec<_>, _>>()?;
    let records: usize = tables.iter().map(|t| t.len()).sum();
    let t_check = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let merged = cv::merge_train(cv::table_kind(&est), tables)?;
    let t_merge = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let solved = merged.solve(&est.solve_policy(), threads);
    let t_solve = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let blob = solved.encode();
    let t_encode = t.elapsed().as_secs_f64();
    let cells = solved.coefficients.len();
    println!(
        "job {job}: {} train results, {records} records, {cells} cells, table {} bytes, {threads} threads",
        blobs.len(),
        blob.len()
    );
    println!(
        "frames {t_frames:.4} s, check+decode cells {t_check:.4} s, merge {t_merge:.4} s, solve {t_solve:.4} s, encode {t_encode:.4} s"
    );
    let total = t_frames + t_check + t_merge + t_solve + t_encode;
    println!(
        "total {total:.4} s = {:.0} cells/s ({:.0} records/s)",
        cells as f64 / total,
        records as f64 / total
    );
    Ok(())
}
