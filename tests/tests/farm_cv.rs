//! CV estimators on the farm (issue #5): a `cms` job rendered by 1 and by 3 workers gives a
//! bitwise-identical EXR, equal to `cvfarm render`'s in-process driver
//! (`render_estimator_image`), on SQLite and on PostgreSQL; `per_light_cv` and `optimal_mis`
//! jobs complete with the in-process bits too; bad training uploads are 4xx JSON and the task
//! is re-leasable; a coordinator restarted between train and render finishes identically.

use std::time::Duration;

use e2e::{
    Backend, FakeWorker, Farm, Worker, film_exr, local_options, local_scene, prepared,
    run_on_two_coordinators, scene_json,
};
use protocol::job::{EstimatorSpec, ResolvedJob};
use protocol::lease::{JobState, JobStatus, PhaseKind};

fn spec(scene: &serde_json::Value, estimator: serde_json::Value, seed: u64) -> serde_json::Value {
    serde_json::json!({
        "scene": { "inline": scene },
        "estimator": estimator,
        "resolution": [80, 32],
        "spp": 24,
        "tile_size": 16,
        "seed": seed,
    })
}

/// [`spec`] at a resolution of two training tiles ([`estimators::spec::TRAIN_TILE`] + 8 × 24).
fn spec_two_train_tiles(
    scene: &serde_json::Value,
    estimator: serde_json::Value,
    seed: u64,
) -> serde_json::Value {
    let mut s = spec(scene, estimator, seed);
    s["resolution"] = serde_json::json!([estimators::spec::TRAIN_TILE + 8, 24]);
    s
}

/// What `cvfarm render --estimator … -o x.exr` writes for the same job: the estimator parsed
/// from the job's JSON into the renderer's own type, `render_estimator_image`, the film's
/// layers. (The CLI adds estimator layers; the farm image has the film's four.)
fn local_cv_exr(
    scene: &serde_json::Value,
    estimator: &serde_json::Value,
    job: &ResolvedJob,
) -> Vec<u8> {
    local_cv(scene, estimator, job).0
}

/// [`local_cv_exr`] and the in-process run's predicted image and fit gains and the weight of
/// its uncontrolled samples.
fn local_cv(
    scene: &serde_json::Value,
    estimator: &serde_json::Value,
    job: &ResolvedJob,
) -> (Vec<u8>, [Option<f64>; 3]) {
    let (loaded, settings) = local_scene(scene, &[], job);
    let est: render::integrator::Estimator =
        serde_json::from_value(estimator.clone()).expect("render estimator");
    let settings = render::integrator::RenderSettings {
        estimator: est,
        ..settings
    };
    let rs = render::integrator::RenderScene::new(&loaded.scene, &settings).expect("prepare");
    let (film, _, report) = render::integrator::cv::render_estimator_image(
        &rs,
        &settings,
        &local_options(),
        &|_, _| {},
    )
    .expect("render");
    if est.has_phases() {
        assert!(report.cells > 0, "{report:?}");
    }
    (
        film_exr(&film, job),
        [
            report.predicted_image_gain,
            report.predicted_fit_gain,
            report.uncontrolled_weight,
        ],
    )
}

/// The train barrier's stats of a CV job.
fn train_barrier(run: &Run) -> &serde_json::Value {
    &run.stats["phases"]
        .as_array()
        .expect("phases")
        .iter()
        .find(|p| p["name"] == "train")
        .expect("train phase")["barrier"]
}

struct Run {
    exr: Vec<u8>,
    status: JobStatus,
    stats: serde_json::Value,
    coefficients: Vec<u8>,
}

fn run_job(backend: Backend, workers: usize, spec: &serde_json::Value) -> Run {
    let farm = Farm::start(backend);
    let client = &farm.client;
    let id = client.submit(spec);
    // Before the train barrier there is no coefficient table.
    let early = client.request("GET", &format!("/v1/jobs/{id}/coefficients"), None);
    assert_eq!(
        early.status,
        404,
        "{}",
        String::from_utf8_lossy(&early.body)
    );
    assert_eq!(early.api_error().code, "not_found");
    let status = farm.finish(id, workers, Duration::from_secs(300));
    Run {
        exr: client.download(id, "image.exr"),
        stats: client.stats(id),
        coefficients: client.download(id, "coefficients"),
        status,
    }
}

/// stats.json of a CV job: every phase with its spp, the train barrier with its cells and
/// the address of the coefficient table served at `/coefficients`.
fn check_stats(run: &Run, phases: &[(&str, u64)]) {
    let ph = run.stats["phases"].as_array().expect("phases");
    let names: Vec<(&str, u64)> = ph
        .iter()
        .map(|p| {
            (
                p["name"].as_str().expect("name"),
                p["spp"].as_u64().expect("spp"),
            )
        })
        .collect();
    assert_eq!(names, phases, "{}", run.stats);
    assert_eq!(
        run.stats["spp"].as_f64(),
        Some(f64::from(run.status.job.spp))
    );
    let barrier = train_barrier(run);
    let cells = barrier["cells"].as_u64().expect("cells");
    let solved = barrier["cells_solved"].as_u64().expect("solved");
    let fallback: u64 = barrier["cells_fallback"]
        .as_object()
        .expect("fallback")
        .values()
        .map(|v| v.as_u64().expect("count"))
        .sum();
    assert!(cells > 0 && solved + fallback == cells, "{barrier}");
    assert_eq!(
        barrier["blob"].as_str(),
        Some(protocol::hash::sha256_hex(&run.coefficients).as_str())
    );
    assert_eq!(&run.coefficients[..4], b"CVCT");
}

fn cms_one_vs_three(backend: Backend) {
    let scene = scene_json("cornell-box/scene.json");
    // The fits applied whatever their predicted gain, so the render phase controls vertices
    // (a table-wide fallback would render it as `path`).
    let est = serde_json::json!({ "kind": "cms", "min_image_gain": null, "min_fit_gain": null });
    let spec = spec(&scene, est.clone(), 7);
    let one = run_job(backend, 1, &spec);
    let three = run_job(backend, 3, &spec);
    assert!(one.exr == three.exr, "1-worker and 3-worker EXRs differ");
    assert!(
        one.coefficients == three.coefficients,
        "coefficient tables differ"
    );
    let (local, local_gain) = local_cv(&scene, &est, &one.status.job);
    assert!(
        one.exr == local,
        "farm EXR differs from the in-process render"
    );
    // cms with `relative` (the default): surrogate 0..1, train 1..17, render 17..24.
    check_stats(&one, &[("surrogate", 1), ("train", 16), ("render", 7)]);
    // The image variance travels with the training tables: the farm predicts the same gains
    // as the in-process driver, to the bit (compared as the stats carry them, through JSON).
    let barrier = train_barrier(&one);
    let [image_gain, fit_gain, weight] = serde_json::from_str::<[Option<f64>; 3]>(
        &serde_json::to_string(&local_gain).expect("json"),
    )
    .expect("json");
    // The render phase ran with the CV: its samples and the training phases' were combined
    // by variance, with the in-process driver's weight (below the 17 of 24 samples' share).
    let w = one.stats["uncontrolled_weight"].as_f64();
    assert!(w.is_some_and(|w| w > 0.0 && w < 1.0), "{}", one.stats);
    assert_eq!(
        w.map(f64::to_bits),
        weight.map(f64::to_bits),
        "{}",
        one.stats
    );
    for (name, local) in ["predicted_image_gain", "predicted_fit_gain"]
        .into_iter()
        .zip([image_gain, fit_gain])
    {
        // Computed, whatever its sign (the Cornell box's fits add a little variance within
        // the techniques: both gains are negative there).
        let gain = barrier[name].as_f64();
        assert!(gain.is_some_and(|g| g != 0.0), "{name}: {barrier}");
        assert_eq!(
            gain.map(f64::to_bits),
            local.map(f64::to_bits),
            "{name}: {barrier}"
        );
        assert_eq!(train_barrier(&three)[name].as_f64(), gain, "{name}");
    }
    assert!(barrier["cells_solved"].as_u64() > Some(0), "{barrier}");
    let img = imageio::read_exr_bytes(&one.exr).expect("exr decodes");
    let beauty = img.main_layer().expect("beauty");
    assert!(beauty.data.iter().any(|p| p[0] > 0.0));
}

e2e::backend_tests!(cms_one_vs_three: cms_one_and_three_workers_bitwise_identical_and_equal_to_local_sqlite, cms_one_and_three_workers_bitwise_identical_and_equal_to_local_postgres);

#[test]
fn per_light_cv_and_optimal_mis_jobs_complete_with_local_bits() {
    let scene = scene_json("cornell-box/scene.json");
    for (est, seed) in [
        (serde_json::json!({ "kind": "per_light_cv" }), 3),
        (
            // The fits applied whatever the split-half check says, so the render phase
            // controls pixels (a dropped tile renders as `path`).
            serde_json::json!({
                "kind": "optimal_mis", "training_spp": 8, "min_samples": 4, "min_split_gain": null
            }),
            5,
        ),
    ] {
        let run = run_job(Backend::Sqlite, 2, &spec(&scene, est.clone(), seed));
        // `per_light_cv` weighs its training vertices by a 1-spp surrogate (relative
        // variance, as `cms`); `optimal_mis` has no surrogate phase.
        if est["kind"] == "per_light_cv" {
            check_stats(&run, &[("surrogate", 1), ("train", 16), ("render", 7)]);
        } else {
            check_stats(&run, &[("train", 8), ("render", 16)]);
        }
        assert!(
            run.exr == local_cv_exr(&scene, &est, &run.status.job),
            "{est}: farm EXR differs from the in-process render"
        );
    }
}

#[test]
fn ocv_job_renders_in_one_phase_with_local_bits() {
    let scene = scene_json("cornell-box/scene.json");
    let est = serde_json::json!({ "kind": "ocv", "spe": 4 });
    let farm = Farm::start(Backend::Sqlite);
    let client = &farm.client;
    let id = client.submit(&spec(&scene, est.clone(), 6));
    let status = farm.finish(id, 1, Duration::from_secs(300));
    assert_eq!(status.phase, PhaseKind::Render);
    // One-pass estimators have no coefficient table.
    let r = client.request("GET", &format!("/v1/jobs/{id}/coefficients"), None);
    assert_eq!(r.status, 404);
    assert!(client.download(id, "image.exr") == local_cv_exr(&scene, &est, &status.job));
}

/// A job whose fits are predicted not to pay (here: a minimum above any prediction) is
/// switched off at the farm's train barrier as in-process: every cell `LowImageGain`, the
/// same bits as the local render.
#[test]
fn a_switched_off_cms_job_has_the_local_bits() {
    let scene = scene_json("cornell-box/scene.json");
    let est = serde_json::json!({ "kind": "cms", "min_image_gain": 0.9 });
    let run = run_job(Backend::Sqlite, 2, &spec(&scene, est.clone(), 3));
    assert!(run.exr == local_cv_exr(&scene, &est, &run.status.job));
    // Traced as `path`: the phases merged plainly.
    assert!(
        run.stats.get("uncontrolled_weight").is_none(),
        "{}",
        run.stats
    );
    let barrier = train_barrier(&run);
    assert_eq!(barrier["cells_solved"].as_u64(), Some(0), "{barrier}");
    assert!(
        barrier["cells_fallback"]["LowImageGain"].as_u64() > Some(0),
        "{barrier}"
    );
    assert!(
        barrier["predicted_image_gain"]
            .as_f64()
            .is_some_and(|g| g < 0.9),
        "{barrier}"
    );
}

#[test]
fn bad_train_uploads_are_4xx_json_and_the_task_is_redone() {
    let farm = Farm::start(Backend::Sqlite);
    let (coord, client) = (&farm.coord, &farm.client);
    let scene = scene_json("cornell-box/scene.json");
    // Without `relative` the train phase comes first.
    let est = serde_json::json!({ "kind": "cms", "relative": false });
    let id = client.submit(&spec_two_train_tiles(&scene, est.clone(), 2));
    let fake = FakeWorker::register(&coord.url(), 2_000);
    let l = fake.lease().expect("lease");
    assert_eq!(l.phase, PhaseKind::Train);
    assert_eq!(
        (l.surrogate.as_deref(), l.coefficients.as_deref()),
        (None, None)
    );
    // A genuine training result of the leased tile, rendered the way a worker does.
    let prepared = prepared(&scene, &l.job, &l.estimator);
    assert!(matches!(l.estimator, EstimatorSpec::Cms(_)));
    let header = l.tile_header();
    let good = prepared
        .render_task(header, PhaseKind::Train, &Default::default())
        .expect("train tile");
    assert_eq!(good.cells.len(), 1);
    let with = |f: &dyn Fn(&mut protocol::TileResult)| {
        let mut r = good.clone();
        f(&mut r);
        r.encode()
    };
    // Σw of the first record: table header 24 bytes, then the accumulator's 32-byte header.
    let nan_at = 24 + 32;
    let bad: Vec<(&str, Vec<u8>)> = vec![
        (
            "truncated",
            with(&|r| {
                let n = r.cells[0].data.len();
                r.cells[0].data.truncate(n - 5);
            }),
        ),
        (
            "non-finite",
            with(&|r| r.cells[0].data[nan_at..nan_at + 8].copy_from_slice(&f64::NAN.to_le_bytes())),
        ),
        ("wrong kind", with(&|r| r.cells[0].kind = 2)),
        ("no block", with(&|r| r.cells.clear())),
    ];
    for (what, body) in bad {
        let r = fake.upload(l.task_id, l.attempt, body);
        assert_eq!(
            r.status,
            422,
            "{what}: {}",
            String::from_utf8_lossy(&r.body)
        );
        let e = r.api_error();
        assert_eq!(e.code, "invalid_cells", "{what}: {e:?}");
    }
    assert_eq!(
        coord
            .block_on(coord.state.store.result_count(id))
            .expect("count"),
        0
    );
    // The task is still the fake's lease: its genuine result is accepted and fixes the
    // job's cell layout.
    let r = fake.upload(l.task_id, l.attempt, good.encode());
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    // The other training tile, with every record claiming one more light component: a
    // well-formed block of another layout than the accepted one.
    let l2 = fake.lease().expect("lease");
    assert_eq!(l2.phase, PhaseKind::Train);
    let header2 = protocol::frame::TileHeader {
        task_id: l2.task_id,
        attempt: l2.attempt,
        rect: l2.rect,
        ..header
    };
    let mut other = prepared
        .render_task(header2, PhaseKind::Train, &Default::default())
        .expect("train tile");
    let data = &mut other.cells[0].data;
    let records = u32::from_le_bytes(data[8..12].try_into().expect("count")) as usize;
    assert!(records > 0);
    let mut at = 12;
    for _ in 0..records {
        let len = u32::from_le_bytes(data[at + 8..at + 12].try_into().expect("len")) as usize;
        // Record: magic 4, version 2, colour 1, reserved 1, then `u32` partitions.
        let p = at + 12 + 8;
        let partitions = u32::from_le_bytes(data[p..p + 4].try_into().expect("P"));
        data[p..p + 4].copy_from_slice(&(partitions + 1).to_le_bytes());
        at += 12 + len;
    }
    let r = fake.upload(l2.task_id, l2.attempt, other.encode());
    assert_eq!(r.status, 422, "{}", String::from_utf8_lossy(&r.body));
    let e = r.api_error();
    assert!(
        e.code == "invalid_cells" && e.message.contains("layout"),
        "{e:?}"
    );
    // It gives up on that task (nothing of it was stored) and a real worker redoes it.
    assert_eq!(
        coord
            .block_on(coord.state.store.result_count(id))
            .expect("count"),
        1
    );
    fake.fail(&l2, "bad cells");
    let status = farm.finish(id, 1, Duration::from_secs(300));
    let t = coord
        .block_on(coord.state.store.task(l2.task_id))
        .expect("store")
        .expect("task");
    assert!(t.done_attempt.expect("done") > i64::from(l2.attempt));
    assert!(client.download(id, "image.exr") == local_cv_exr(&scene, &est, &status.job));
}

/// Also covers training tables as stored: apart from the pixel frame (`results.cells`), and,
/// for the first task, rewritten to the layout of rows stored before that split (the whole
/// frame in `results.data`, `cells` NULL) — the barrier reads both.
#[test]
fn coordinator_restart_between_train_and_render_finishes_identically() {
    let mut farm = Farm::start(Backend::Sqlite);
    let scene = scene_json("cornell-box/scene.json");
    let est = serde_json::json!({ "kind": "cms", "relative": false, "training_spp": 8, "min_image_gain": null, "min_fit_gain": null });
    let id = farm
        .client
        .submit(&spec_two_train_tiles(&scene, est.clone(), 13));
    // Render the whole train phase with a fake worker, so the barrier is due with no
    // worker around; then kill the coordinator before or after it ran.
    let fake = FakeWorker::register(&farm.url(), 2_000);
    let first = fake.lease().expect("lease");
    let prepared = prepared(&scene, &first.job, &first.estimator);
    let train_tasks = protocol::job::plan_phases(&first.job, &first.estimator)[0]
        .tasks
        .len();
    assert!(train_tasks >= 2, "a legacy row and a split one");
    let mut lease = Some(first);
    let mut uploaded = 0;
    while let Some(l) = lease.take() {
        assert_eq!(l.phase, PhaseKind::Train);
        let r = prepared
            .render_task(l.tile_header(), PhaseKind::Train, &Default::default())
            .expect("train tile");
        let up = fake.upload(l.task_id, l.attempt, r.encode());
        assert_eq!(up.status, 200, "{}", String::from_utf8_lossy(&up.body));
        let pool = farm.coord.state.store.pool().clone();
        let (data, cells): (Vec<u8>, Option<Vec<u8>>) = farm
            .coord
            .block_on(
                sqlx::query_as("SELECT data, cells FROM results WHERE task_id = ? AND attempt = ?")
                    .bind(l.task_id)
                    .bind(i64::from(l.attempt))
                    .fetch_one(&pool),
            )
            .expect("stored result");
        let stored = protocol::frame::decode(&data, usize::MAX >> 1).expect("stored frame");
        assert!(stored.cells.is_empty() && stored.pixels == r.pixels);
        assert!(cells.as_deref() == Some(r.cells[0].data.as_slice()));
        if uploaded == 0 {
            farm.coord
                .block_on(
                    sqlx::query("UPDATE results SET data = ?, cells = NULL WHERE task_id = ?")
                        .bind(r.encode())
                        .bind(l.task_id)
                        .execute(&pool),
                )
                .expect("legacy row");
        }
        uploaded += 1;
        if uploaded < train_tasks {
            lease = Some(fake.lease().expect("lease"));
        }
    }
    // The restart comes with a fresh client: the old one's connection died with it.
    farm.restart();
    let status = farm.finish(id, 1, Duration::from_secs(300));
    assert!(farm.client.download(id, "image.exr") == local_cv_exr(&scene, &est, &status.job));
}

#[test]
fn cms_on_two_coordinators_sharing_one_postgres() {
    let scene = scene_json("cornell-box/scene.json");
    let est = serde_json::json!({ "kind": "cms", "min_image_gain": null, "min_fit_gain": null });
    // Both coordinators may run a barrier; exactly one advances the job each time.
    let run = run_on_two_coordinators(&spec(&scene, est.clone(), 21), Duration::from_secs(300));
    assert!(run.exr == local_cv_exr(&scene, &est, &run.status.job));
}

/// The image of a `path` job of `spp` samples split by `spt`, assembled in-process.
fn local_path_image(
    scene: &serde_json::Value,
    job: &ResolvedJob,
    spp: u32,
    spt: u32,
) -> protocol::assemble::AssembledImage {
    let j = ResolvedJob {
        spp,
        samples_per_task: spt,
        ..*job
    };
    let p = prepared(scene, &j, &EstimatorSpec::default());
    worker::tile::render_local(&p, &j).expect("render")
}

e2e::backend_tests!(target_rel_mse_stops: target_rel_mse_stops_after_the_first_round_that_meets_it_sqlite, target_rel_mse_stops_after_the_first_round_that_meets_it_postgres);

fn target_rel_mse_stops(backend: Backend) {
    let farm = Farm::start(backend);
    let client = &farm.client;
    let scene = scene_json("cornell-box/scene.json");
    let mut s = serde_json::json!({
        "scene": { "inline": scene },
        "resolution": [32, 32],
        "spp": 64,
        "samples_per_task": 4,
        "tile_size": 16,
        "seed": 5,
    });
    // The target: the estimated error of the first 32 samples, so the farm must stop at or
    // before round 8 of 16 (earlier if the noisy estimate dips below it sooner).
    let resolved = ResolvedJob {
        width: 32,
        height: 32,
        spp: 64,
        seed: 5,
        sampler: Default::default(),
        max_depth: 5,
        rr_depth: 5,
        hide_emitters: false,
        tile_size: 16,
        samples_per_task: 4,
    };
    let target = local_path_image(&scene, &resolved, 32, 4).estimated_rel_mse();
    s["target_rel_mse"] = serde_json::json!(target);
    let id = client.submit(&s);
    let status = farm.finish(id, 2, Duration::from_secs(300));
    assert_eq!(status.job.max_depth, resolved.max_depth);
    let stats = client.stats(id);
    let spp = stats["spp"].as_f64().expect("spp") as u32;
    assert!(spp.is_multiple_of(4) && (4..=32).contains(&spp), "{stats}");
    assert!(stats["estimated_rel_mse"].as_f64().expect("rel") <= target);
    assert_eq!(
        stats["phases"][0]["spp"].as_u64(),
        Some(u64::from(spp)),
        "{stats}"
    );
    // The farm image is exactly the first spp/4 rounds, and every earlier round missed the
    // target (the stop is the first round that meets it, whatever the workers did).
    let local = local_path_image(&scene, &status.job, spp, 4);
    let exr = coordinator::finish::encode_exr(&local).expect("exr");
    assert!(
        client.download(id, "image.exr") == exr,
        "image differs from the first {spp} samples"
    );
    for earlier in (4..spp).step_by(4) {
        let e = local_path_image(&scene, &status.job, earlier, 4).estimated_rel_mse();
        assert!(
            e > target,
            "{earlier} spp already met the target ({e} <= {target})"
        );
    }
}

#[test]
fn time_budget_ends_the_job_before_the_spp_cap() {
    let farm = Farm::start(Backend::Sqlite);
    let client = &farm.client;
    let scene = scene_json("cornell-box/scene.json");
    let id = client.submit(&serde_json::json!({
        "scene": { "inline": scene },
        "resolution": [16, 16],
        "spp": 65536,
        "samples_per_task": 4,
        "tile_size": 16,
        "time_budget_s": 1.0,
    }));
    let w = Worker::start(&farm.url(), "w");
    let mut saw_eta = false;
    let status = loop {
        let st = client.status(id);
        saw_eta |= st.eta_s.is_some();
        if st.state != JobState::Running {
            break st;
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    assert_eq!(status.state, JobState::Done, "{status:?}");
    w.stop();
    assert!(saw_eta, "a running budget job has an ETA");
    let stats = client.stats(id);
    let spp = stats["spp"].as_f64().expect("spp");
    assert!((4.0..65536.0).contains(&spp) && spp % 4.0 == 0.0, "{stats}");
}
