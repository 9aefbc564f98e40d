//! `cvfarm`: the command-line tool of the cvfarm render farm.
//!
//! This file only parses the command line and dispatches; each subcommand lives in its own
//! module with its arguments and its `run` function.
//!
//! # Layout
//! - [`render_cmd`]: `cvfarm render` — render a scene locally (embedded renderer) to EXR/PNG.
//! - [`compare_cmd`]: `cvfarm compare` — error of a test image against a reference (relMSE, …).
//! - [`bench_cmd`]: `cvfarm bench` — accuracy vs time of several estimators (CSV, markdown, SVG).
//! - [`estimator_opts`]: `--estimator`, `--opt key=value`, `--estimator-json` → `Estimator`.
//! - [`local_render`]: fixed-spp and time-budget local rendering shared by `render` and `bench`.
//! - [`farm`]: `cvfarm serve`, `cvfarm worker`, `cvfarm submit` — the render farm.
//! - [`cli_error`]: how errors are reported (one line on stderr, exit status).
//!
//! Every flag can also be given as an environment variable (`CVFARM_SPP`, `CVFARM_SEED`, …;
//! `cvfarm help render` lists them); an explicit flag wins over the variable.

#![deny(missing_docs)]

mod bench_cmd;
mod cli_error;
mod compare_cmd;
mod estimator_opts;
mod farm;
mod local_render;
mod render_cmd;

use std::process::ExitCode;

use clap::{Parser, Subcommand};

/// cvfarm: control-variate Monte Carlo rendering, locally or on a render farm.
#[derive(Debug, Parser)]
#[command(name = "cvfarm", version, about, propagate_version = true)]
struct Cli {
    /// What to do.
    #[command(subcommand)]
    command: Command,
}

/// The subcommands.
#[derive(Debug, Subcommand)]
enum Command {
    /// Render a scene (native .json or Mitsuba 3 .xml) to an EXR file (and a PNG preview).
    Render(render_cmd::RenderArgs),
    /// Compare a test EXR with a reference EXR: relMSE (ε = 0.01), MSE, mean ratio, NaN/Inf.
    Compare(compare_cmd::CompareArgs),
    /// Benchmark estimators against `path`: relMSE vs time, equal-time and equal-sample speedups.
    Bench(bench_cmd::BenchArgs),
    /// Run the farm coordinator (REST API, queue, SQLite or PostgreSQL store).
    Serve(farm::ServeArgs),
    /// Run a farm worker: lease tiles from a coordinator, render, upload.
    Worker(farm::WorkerArgs),
    /// Submit a scene to a farm; with --wait, show progress and download the results.
    Submit(farm::SubmitArgs),
}

fn main() -> ExitCode {
    let cli = match Cli::try_parse() {
        Ok(cli) => cli,
        Err(e) => return cli_error::report_clap(&e),
    };
    let result = match cli.command {
        Command::Render(args) => render_cmd::run(&args),
        Command::Compare(args) => compare_cmd::run(&args),
        Command::Bench(args) => bench_cmd::run(&args),
        Command::Serve(args) => farm::serve(&args),
        Command::Worker(args) => farm::worker(&args),
        Command::Submit(args) => farm::submit(&args),
    };
    match result {
        Ok(code) => code,
        Err(e) => cli_error::report(&e),
    }
}
