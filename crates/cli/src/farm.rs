//! The farm subcommands: `cvfarm serve` (coordinator), `cvfarm worker`, `cvfarm submit`.
//!
//! Every flag has an environment variable (shown by `--help`), as farm operators expect;
//! tokens are normally given by environment only (`CVFARM_CLIENT_TOKEN`,
//! `CVFARM_WORKER_TOKEN`). Logs go to stderr, filtered by `RUST_LOG` (default `info`).
//!
//! ```text
//! CVFARM_CLIENT_TOKEN=c CVFARM_WORKER_TOKEN=w cvfarm serve --listen 127.0.0.1:8080 --data-dir farm-data
//! CVFARM_WORKER_TOKEN=w cvfarm worker --coordinator http://127.0.0.1:8080
//! CVFARM_CLIENT_TOKEN=c cvfarm submit scenes/cornell-box/scene.json --coordinator http://127.0.0.1:8080 \
//!     --spp 64 --res 256x256 --wait -o out.exr
//! CVFARM_CLIENT_TOKEN=c cvfarm submit scenes/cornell-box/scene.json --coordinator http://127.0.0.1:8080 \
//!     --estimator cms --opt training_spp=32 --spp 128 --wait -o cms.exr
//! ```
//!
//! `submit` parses `--estimator`, `--opt` and `--estimator-json` exactly like `cvfarm render`
//! (same option structs, same errors, exit status 2 for a bad option); the progress bar
//! names the job's current phase (surrogate, train, render for the CV estimators).
//!
//! `serve` and `worker` stop gracefully on SIGTERM or ctrl-c: the coordinator drains its
//! requests (all state is already in the store), a worker finishes the tile in hand.

use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, anyhow, bail};
use clap::Args;
use protocol::lease::{JobState, JobStatus, SubmitResponse};

/// Arguments of `cvfarm serve`.
#[derive(Debug, Args)]
pub struct ServeArgs {
    /// Address to listen on.
    #[arg(long, env = "CVFARM_LISTEN", default_value = "127.0.0.1:8080")]
    pub listen: SocketAddr,
    /// Database URL: `postgres://…` for a farm; default: SQLite file in --data-dir.
    #[arg(long, env = "DATABASE_URL")]
    pub database: Option<String>,
    /// Directory of the SQLite database.
    #[arg(long, env = "CVFARM_DATA_DIR", default_value = "cvfarm-data")]
    pub data_dir: PathBuf,
    /// Bearer token clients must send.
    #[arg(long, env = "CVFARM_CLIENT_TOKEN", hide_env_values = true)]
    pub client_token: String,
    /// Enrollment token workers register with.
    #[arg(long, env = "CVFARM_WORKER_TOKEN", hide_env_values = true)]
    pub worker_token: String,
    /// Lease duration in milliseconds (heartbeats extend it).
    #[arg(long, env = "CVFARM_LEASE_MS", default_value_t = 30_000)]
    pub lease_ms: u64,
    /// Heartbeat period asked of workers, in milliseconds.
    #[arg(long, env = "CVFARM_HEARTBEAT_MS", default_value_t = 10_000)]
    pub heartbeat_ms: u64,
    /// Failed attempts of one task before its job fails.
    #[arg(long, env = "CVFARM_MAX_ATTEMPTS", default_value_t = 5)]
    pub max_attempts: u32,
}

/// Arguments of `cvfarm worker`.
#[derive(Debug, Args)]
pub struct WorkerArgs {
    /// Coordinator base URL.
    #[arg(long, env = "CVFARM_COORDINATOR")]
    pub coordinator: String,
    /// Enrollment token.
    #[arg(long, env = "CVFARM_WORKER_TOKEN", hide_env_values = true)]
    pub worker_token: String,
    /// Name shown in the coordinator's logs [default: host name].
    #[arg(long, env = "CVFARM_WORKER_NAME")]
    pub name: Option<String>,
    /// Tiles rendered at once [default: number of cores].
    #[arg(long, env = "CVFARM_SLOTS")]
    pub slots: Option<usize>,
}

/// Arguments of `cvfarm submit`.
#[derive(Debug, Args)]
pub struct SubmitArgs {
    /// Scene file: native JSON (.json) or Mitsuba 3 XML (.xml); its assets are uploaded.
    pub scene: PathBuf,
    /// Coordinator base URL.
    #[arg(long, env = "CVFARM_COORDINATOR")]
    pub coordinator: String,
    /// Client bearer token.
    #[arg(long, env = "CVFARM_CLIENT_TOKEN", hide_env_values = true)]
    pub client_token: String,
    /// Estimator selection.
    #[command(flatten)]
    pub estimator: crate::estimator_opts::EstimatorArgs,
    /// Sample range length per task (splits tiles in time) [default: spp].
    #[arg(long, env = "CVFARM_SAMPLES_PER_TASK")]
    pub samples_per_task: Option<u32>,
    /// Samples per pixel [default: 16]; the cap of a --time-budget or --target-rel-mse job.
    #[arg(long, env = "CVFARM_SPP")]
    pub spp: Option<u32>,
    /// Stop adding render rounds (of --samples-per-task) once this many seconds have passed
    /// since submission.
    #[arg(long, env = "CVFARM_TIME_BUDGET", value_name = "SECONDS",
          value_parser = crate::render_cmd::parse_budget, conflicts_with = "target_rel_mse")]
    pub time_budget: Option<f64>,
    /// Stop adding render rounds once the estimated relMSE is at most this.
    #[arg(long, env = "CVFARM_TARGET_REL_MSE", value_name = "X",
          value_parser = crate::render_cmd::parse_budget)]
    pub target_rel_mse: Option<f64>,
    /// Max path segments incl. the camera ray (-1 = unbounded) [default: the scene's].
    #[arg(long, env = "CVFARM_MAX_DEPTH", allow_negative_numbers = true)]
    pub max_depth: Option<i32>,
    /// Sampler seed.
    #[arg(long, env = "CVFARM_SEED", default_value_t = 0)]
    pub seed: u64,
    /// Where the sample numbers come from.
    #[arg(long, env = "CVFARM_SAMPLER", value_enum, default_value_t = crate::render_cmd::SamplerArg::Sobol)]
    pub sampler: crate::render_cmd::SamplerArg,
    /// Film size override, e.g. 320x240.
    #[arg(long, env = "CVFARM_RES", value_name = "WxH")]
    pub res: Option<String>,
    /// Tile edge in pixels.
    #[arg(long, env = "CVFARM_TILE_SIZE", default_value_t = 32)]
    pub tile_size: u32,
    /// Priority (higher first).
    #[arg(
        long,
        env = "CVFARM_PRIORITY",
        default_value_t = 0,
        allow_negative_numbers = true
    )]
    pub priority: i32,
    /// Mitsuba XML `$parameter` value (repeatable).
    #[arg(
        short = 'D',
        long,
        env = "CVFARM_DEFINES",
        value_name = "KEY=VALUE",
        value_delimiter = ','
    )]
    pub define: Vec<String>,
    /// Wait for the job (progress bar) and download its results.
    #[arg(long, env = "CVFARM_WAIT", value_parser = clap::builder::BoolishValueParser::new())]
    pub wait: bool,
    /// With --wait: write the EXR here.
    #[arg(short, long, env = "CVFARM_OUTPUT")]
    pub output: Option<PathBuf>,
    /// With --wait: also write the PNG preview here.
    #[arg(long, env = "CVFARM_PNG")]
    pub png: Option<PathBuf>,
    /// With --wait: also write stats.json here.
    #[arg(long, env = "CVFARM_STATS")]
    pub stats: Option<PathBuf>,
}

fn init_logging() {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .try_init();
}

fn runtime() -> Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("starting the async runtime")
}

/// Resolves on SIGTERM or ctrl-c.
async fn shutdown_signal() {
    let ctrl_c = async {
        let _ = tokio::signal::ctrl_c().await;
    };
    #[cfg(unix)]
    let term = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    #[cfg(not(unix))]
    let term = std::future::pending::<()>();
    tokio::select! {
        _ = ctrl_c => {}
        _ = term => {}
    }
    tracing::info!("shutdown requested");
}

/// `cvfarm serve`.
pub fn serve(args: &ServeArgs) -> Result<ExitCode> {
    init_logging();
    let mut config = coordinator::Config::new(&args.client_token, &args.worker_token);
    config.database_url = args.database.clone().filter(|s| !s.is_empty());
    config.data_dir = args.data_dir.clone();
    config.lease_ms = args.lease_ms;
    config.heartbeat_ms = args.heartbeat_ms;
    config.max_attempts = args.max_attempts;
    runtime()?.block_on(async {
        let app = coordinator::App::build(config)
            .await
            .context("starting the coordinator")?;
        let listener = tokio::net::TcpListener::bind(args.listen)
            .await
            .with_context(|| format!("listening on {}", args.listen))?;
        app.run(listener, shutdown_signal())
            .await
            .context("serving")?;
        Ok(ExitCode::SUCCESS)
    })
}

/// `cvfarm worker`.
pub fn worker(args: &WorkerArgs) -> Result<ExitCode> {
    init_logging();
    let mut cfg = worker::WorkerConfig::new(&args.coordinator, &args.worker_token);
    cfg.name = args.name.clone().unwrap_or_else(|| {
        std::fs::read_to_string("/etc/hostname")
            .map(|s| s.trim().to_owned())
            .unwrap_or_else(|_| "worker".into())
    });
    if let Some(s) = args.slots {
        if s == 0 {
            bail!("--slots must be at least 1");
        }
        cfg.slots = s;
    }
    let summary = runtime()?
        .block_on(worker::run(cfg, shutdown_signal()))
        .context("worker")?;
    tracing::info!(?summary, "worker stopped");
    Ok(ExitCode::SUCCESS)
}

fn parse_res(s: &str) -> Result<[u32; 2]> {
    let (w, h) = s
        .split_once(['x', 'X'])
        .ok_or_else(|| anyhow!("--res must look like 320x240, not `{s}`"))?;
    let w: u32 = w
        .trim()
        .parse()
        .with_context(|| format!("--res width `{w}`"))?;
    let h: u32 = h
        .trim()
        .parse()
        .with_context(|| format!("--res height `{h}`"))?;
    Ok([w, h])
}

/// The job's `estimator` object from `--estimator`, `--estimator-json` and the `--opt`s,
/// parsed and checked exactly as `cvfarm render` does ([`crate::estimator_opts::build`]), so
/// a job means the same thing locally and on the farm. Every option is written out.
fn estimator_json(args: &SubmitArgs) -> Result<serde_json::Value> {
    let est = args.estimator.build()?;
    Ok(serde_json::to_value(est)?)
}

/// A blocking-style HTTP client for `submit`.
struct Api {
    base: String,
    token: String,
    http: reqwest::Client,
}

impl Api {
    fn url(&self, path: &str) -> String {
        format!("{}{}", self.base.trim_end_matches('/'), path)
    }

    /// Turns a non-2xx answer into an error carrying the API's JSON message.
    async fn check(resp: reqwest::Response, what: &str) -> Result<reqwest::Response> {
        if resp.status().is_success() {
            return Ok(resp);
        }
        let status = resp.status();
        let body = resp.text().await.unwrap_or_default();
        let msg = match serde_json::from_str::<protocol::ApiErrorBody>(&body) {
            Ok(b) => b.error.to_string(),
            Err(_) => body,
        };
        bail!("{what}: {status}: {msg}")
    }

    async fn get(&self, path: &str, what: &str) -> Result<reqwest::Response> {
        let r = self
            .http
            .get(self.url(path))
            .bearer_auth(&self.token)
            .send()
            .await
            .with_context(|| what.to_owned())?;
        Self::check(r, what).await
    }
}

/// `cvfarm submit`.
pub fn submit(args: &SubmitArgs) -> Result<ExitCode> {
    let params = crate::render_cmd::parse_defines(&args.define)?;
    let (desc, _warnings) = scene::read_desc_file(&args.scene, &params)
        .with_context(|| format!("reading {}", args.scene.display()))?;
    let dir = args.scene.parent().unwrap_or(Path::new(".")).to_path_buf();
    let api = Api {
        base: args.coordinator.clone(),
        token: args.client_token.clone(),
        http: reqwest::Client::builder()
            .connect_timeout(Duration::from_secs(10))
            .build()?,
    };
    let rt = runtime()?;
    rt.block_on(async {
        // Upload every asset the scene names, by content address.
        let mut assets = BTreeMap::new();
        let source = scene::DirAssets::new(&dir);
        for name in coordinator::routes::jobs::referenced_assets(&desc) {
            let bytes = scene::AssetSource::read(&source, &name)
                .with_context(|| format!("reading asset {name}"))?;
            let hash = protocol::hash::sha256_hex(&bytes);
            let r = api
                .http
                .put(api.url(&format!("/v1/assets/{hash}")))
                .bearer_auth(&api.token)
                .body(bytes)
                .send()
                .await
                .with_context(|| format!("uploading asset {name}"))?;
            Api::check(r, &format!("uploading asset {name}")).await?;
            assets.insert(name, hash);
        }
        let mut spec = serde_json::json!({
            "scene": { "inline": desc },
            "assets": assets,
            "estimator": estimator_json(args)?,
            "seed": args.seed,
            "sampler": args.sampler.name(),
            "tile_size": args.tile_size,
            "priority": args.priority,
        });
        if let Some(spp) = args.spp {
            spec["spp"] = spp.into();
        }
        if let Some(t) = args.time_budget {
            spec["time_budget_s"] = t.into();
        }
        if let Some(t) = args.target_rel_mse {
            spec["target_rel_mse"] = t.into();
        }
        if let Some(n) = args.samples_per_task {
            spec["samples_per_task"] = n.into();
        }
        if let Some(d) = args.max_depth {
            spec["max_depth"] = d.into();
        }
        if let Some(res) = &args.res {
            spec["resolution"] = serde_json::json!(parse_res(res)?);
        }
        let r = api
            .http
            .post(api.url("/v1/jobs"))
            .bearer_auth(&api.token)
            .json(&spec)
            .send()
            .await
            .context("submitting")?;
        let sub: SubmitResponse = Api::check(r, "submitting")
            .await?
            .json()
            .await
            .context("submit answer")?;
        println!("job {} submitted ({} tasks)", sub.job_id, sub.tasks);
        if !args.wait {
            return Ok(ExitCode::SUCCESS);
        }
        let status = wait(&api, sub.job_id).await?;
        if status.state != JobState::Done {
            bail!(
                "job {} {}: {}",
                sub.job_id,
                status.state.as_str(),
                status.error.unwrap_or_default()
            );
        }
        for (name, path) in [
            ("image.exr", &args.output),
            ("preview.png", &args.png),
            ("stats.json", &args.stats),
        ] {
            if let Some(path) = path {
                let bytes = api
                    .get(
                        &format!("/v1/jobs/{}/{name}", sub.job_id),
                        &format!("downloading {name}"),
                    )
                    .await?
                    .bytes()
                    .await?;
                std::fs::write(path, &bytes)
                    .with_context(|| format!("writing {}", path.display()))?;
                println!("wrote {}", path.display());
            }
        }
        Ok(ExitCode::SUCCESS)
    })
}

async fn wait(api: &Api, id: i64) -> Result<JobStatus> {
    let bar = indicatif::ProgressBar::new(0);
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{elapsed_precise} {prefix} [{bar:40}] {pos}/{len} tasks {msg}",
        )
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    let start = Instant::now();
    loop {
        let status: JobStatus = api
            .get(&format!("/v1/jobs/{id}"), "job status")
            .await?
            .json()
            .await?;
        bar.set_prefix(status.phase.as_str());
        if let Some(eta) = status.eta_s {
            bar.set_message(format!("ETA {eta:.0} s"));
        }
        bar.set_length(status.tasks_total);
        bar.set_position(status.tasks_done);
        if !matches!(status.state, JobState::Running | JobState::Paused) {
            bar.finish_with_message(format!(
                "{} in {:.1} s",
                status.state.as_str(),
                start.elapsed().as_secs_f64()
            ));
            return Ok(status);
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
}
