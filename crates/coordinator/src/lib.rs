//! The cvfarm coordinator: REST API, task queue with leases, image assembly, downloads.
//!
//! [`App::build`] connects the store (SQLite file in the data directory by default, PostgreSQL
//! when the database URL says so), runs the embedded migrations and prepares the router;
//! [`App::run`] serves on a listener until a shutdown future resolves. Tests bind port 0.
//!
//! **The coordinator keeps no state outside the store**: jobs, tasks, leases, results,
//! workers and outputs are rows; the in-memory parts (a wake-up signal for long polls, the
//! reaper's timer) can be lost at any moment. Kill it, restart it, and jobs continue.
//! It never links the renderer (DESIGN §2): scenes are validated with `scene` only.
//!
//! # Layout
//! - [`config`]: [`Config`] and its documented limits.
//! - [`store`]: the sqlx store over SQLite/PostgreSQL (`sqlx::Any`), all queries.
//! - [`auth`]: bearer tokens for clients and workers.
//! - [`error`]: [`error::AppError`] → HTTP status + JSON error body.
//! - [`routes`]: one module per resource (`jobs`, `assets`, `workers`, `tasks`, `health`,
//!   `meta`: metrics, OpenAPI, docs).
//! - [`finish`]: the phase machine: CV barriers (surrogate image; merge in canonical order +
//!   solve → content-addressed coefficient table) and the finish (image assembly of all
//!   phases in canonical order, EXR/PNG/stats outputs).
//! - [`reaper`]: background loop expiring leases and advancing jobs whose phase is complete.
//! - [`convergence`]: a job's convergence series (`convergence.csv`), computed from stored results.

#![deny(missing_docs)]

pub mod auth;
pub mod config;
pub mod convergence;
pub mod error;
pub mod finish;
pub mod reaper;
pub mod routes;
pub mod store;
pub mod train_merge;

use std::future::Future;
use std::sync::Arc;

pub use config::Config;
use store::Store;
use tokio::net::TcpListener;
use tokio::sync::Notify;

/// Shared state of the handlers. Only the store is state; the rest is configuration and a
/// wake-up signal.
#[derive(Debug)]
pub struct AppState {
    /// Configuration.
    pub config: Config,
    /// The database.
    pub store: Store,
    /// Wakes long-polling lease requests when tasks may have become available.
    pub work_available: Notify,
    /// Turns `true` when [`App::run`]'s shutdown future resolves, so endless responses
    /// (the `/v1/events` stream) end and graceful shutdown can drain.
    pub stopping: tokio::sync::watch::Sender<bool>,
    /// Jobs this process is advancing right now ([`finish::advance_job`]); see
    /// [`finish::Advancing`]. Not state: a hint that keeps the reaper and an upload of one
    /// process from running the same barrier or assembly side by side.
    pub advancing: finish::Advancing,
    /// Train tables folded in canonical order as they are accepted
    /// ([`train_merge::TrainMerges`]). A cache of stored results: the barrier reads the
    /// store whenever it does not cover the whole phase.
    pub train_merges: train_merge::TrainMerges,
}

/// A built coordinator, ready to serve.
#[derive(Debug)]
pub struct App {
    state: Arc<AppState>,
}

/// Errors of building or serving.
#[derive(Debug, thiserror::Error)]
pub enum ServeError {
    /// The store could not be opened.
    #[error(transparent)]
    Store(#[from] store::StoreError),
    /// Data directory or socket failure.
    #[error("i/o: {0}")]
    Io(#[from] std::io::Error),
    /// Configuration is unusable.
    #[error("config: {0}")]
    Config(String),
}

impl App {
    /// Opens the store (running migrations) and prepares the app.
    pub async fn build(config: Config) -> Result<Self, ServeError> {
        if config.client_tokens.iter().any(String::is_empty) || config.enrollment_token.is_empty() {
            return Err(ServeError::Config(
                "client and worker enrollment tokens must not be empty".into(),
            ));
        }
        let url = match &config.database_url {
            Some(u) => u.clone(),
            None => {
                std::fs::create_dir_all(&config.data_dir)?;
                let path = config.data_dir.join("cvfarm.sqlite");
                format!("sqlite://{}?mode=rwc", path.display())
            }
        };
        let store = Store::connect(&url).await?;
        tracing::info!(backend = ?store.backend(), "store ready");
        Ok(Self {
            state: Arc::new(AppState {
                config,
                store,
                work_available: Notify::new(),
                stopping: tokio::sync::watch::Sender::new(false),
                advancing: finish::Advancing::default(),
                train_merges: train_merge::TrainMerges::default(),
            }),
        })
    }

    /// The shared state (tests inspect the store through it).
    pub fn state(&self) -> Arc<AppState> {
        self.state.clone()
    }

    /// The axum router with every route and layer.
    pub fn router(&self) -> axum::Router {
        routes::router(self.state.clone())
    }

    /// Serves on `listener` until `shutdown` resolves; the reaper runs alongside. Pending
    /// requests are drained; nothing needs saving because everything is already stored.
    pub async fn run(
        self,
        listener: TcpListener,
        shutdown: impl Future<Output = ()> + Send + 'static,
    ) -> Result<(), ServeError> {
        let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
        let reaper = tokio::spawn(reaper::run(self.state.clone(), stop_rx));
        let app = self.router();
        tracing::info!(addr = ?listener.local_addr().ok(), "coordinator listening");
        let state = self.state.clone();
        let shutdown = async move {
            shutdown.await;
            state.stopping.send_replace(true);
        };
        let result = axum::serve(listener, app)
            .with_graceful_shutdown(shutdown)
            .await;
        let _ = stop_tx.send(true);
        let _ = reaper.await;
        self.state.store.close().await;
        result.map_err(ServeError::Io)
    }
}
