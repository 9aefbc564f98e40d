//! `cvfarm bench SCENE --estimators path,ocv,cms --reference REF.exr --out DIR`: accuracy vs
//! time of several estimators on one scene (DESIGN §6, the layout of [Hua Table 1]).
//!
//! Each estimator renders the scene at a geometric series of sample counts (1, 2, 4, … spp,
//! i.e. roughly doubling time budgets; or `--spp-series`) until its next render would push
//! its total past `--max-seconds` (wall time). The estimators take turns render by render
//! (at each spp, seed by seed), so a drift of the machine's speed moves all of them alike.
//! Every run records `(spp, seconds, relMSE, MSE)` plus its wall and CPU seconds; `seconds` is the clock the comparisons use (`--clock`):
//! by default the **process CPU time** of rendering (all threads, from `/proc/self/stat`),
//! which is far less disturbed than wall time when other jobs share the machine; `wall` is
//! the alternative. Scene preparation is excluded (it is the same for all).
//! Without `--reference` the error is estimated from the per-pixel variance of the mean
//! (`estimators::metrics::estimated_rel_mse`; exact in expectation for unbiased estimators
//! with independent samples). With `--seeds N` (N ≥ 2) every point renders N seeds and the
//! error is the seed-to-seed variance of one render (`estimators::metrics::seed_variance_error`):
//! no reference noise in it — a reference's own error is a floor under every figure measured
//! against it, which pulls speedups toward 1 — and right for the Sobol sampler, whose samples
//! within a pixel are not independent; the reference, if given, only normalises.
//!
//! Outputs in `--out DIR`:
//! - `bench.csv`: `estimator,spp,seconds,relmse,mse,wall_seconds,cpu_seconds`, one row per run;
//! - `bench.md`: per estimator vs `path` — **equal-time speedup** `relMSE_path(t)/relMSE_X(t)`
//!   at `t` = the smaller of both longest run times (log-log interpolation of the series,
//!   extrapolated along the Monte Carlo rate `1/t`), **equal-sample speedup**
//!   `relMSE_path(s)/relMSE_X(s)` at the largest common spp `s`, and **time overhead**
//!   `t_X(s)/t_path(s) − 1`; then the raw series;
//! - `bench.svg`: relMSE vs seconds, log-log, one line per estimator.
//!
//! | flag | default | meaning |
//! |---|---|---|
//! | `--estimators LIST` | `path,cms` | comma-separated kinds; options as `ocv:spe=32:lambda=1`; `path` is always run (the baseline) |
//! | `--reference F` | none | reference EXR (e.g. `cvfarm render --spp 4096`); else variance-based error |
//! | `--max-depth D` | scene's | path length |
//! | `--out DIR` | `bench` | output directory |
//! | `--max-seconds S` | 60 | render-time budget per estimator (the series stops before exceeding it) |
//! | `--spp-series LIST` | 1,2,4,… | explicit sample counts |
//! | `--clock C` | `cpu` | `cpu` (process CPU seconds) or `wall` for the comparisons |
//! | `--seeds N` | 1 | renders per point (seeds `seed…seed+N−1`); N ≥ 2: seed-variance error, mean seconds |
//! | `--seed`, `--sampler`, `--threads`, `--res`, `--tile-size`, `-D` | as `render` | |
//!
//! ```text
//! $ cvfarm bench scenes/checkers/scene.json --estimators path,ocv:spe=64 --reference ref.exr --out docs/bench/checkers_d2
//! ```

use std::fmt::Write as _;
use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result, bail};
use clap::Args;
use render::integrator::{Estimator, RenderScene, RenderSettings};
use render::tile::RenderOptions;

use crate::estimator_opts::{self, UsageError};
use crate::local_render;
use crate::render_cmd::{Resolution, load_scene_file};

/// Arguments of `cvfarm bench`.
#[derive(Debug, Args)]
pub struct BenchArgs {
    /// Scene file: native JSON (.json) or Mitsuba 3 XML (.xml).
    pub scene: PathBuf,
    /// Estimators to compare (comma-separated; `kind:key=value:…` sets options).
    #[arg(long, value_delimiter = ',', default_value = "path,cms")]
    pub estimators: Vec<String>,
    /// Reference image (EXR); without it the error is estimated from the pixel variance.
    #[arg(long)]
    pub reference: Option<PathBuf>,
    /// Max path segments incl. the camera ray [default: the scene's].
    #[arg(long, allow_negative_numbers = true)]
    pub max_depth: Option<i32>,
    /// Output directory for bench.csv, bench.md, bench.svg.
    #[arg(long, default_value = "bench")]
    pub out: PathBuf,
    /// Render-time budget per estimator in seconds.
    #[arg(long, default_value_t = 60.0, value_parser = crate::render_cmd::parse_budget)]
    pub max_seconds: f64,
    /// Explicit sample counts (comma-separated) instead of 1, 2, 4, ….
    #[arg(long, value_delimiter = ',', value_parser = clap::value_parser!(u32).range(1..))]
    pub spp_series: Vec<u32>,
    /// Clock of the comparisons: process CPU seconds (robust on a shared machine) or wall.
    #[arg(long, value_enum, default_value_t = Clock::Cpu)]
    pub clock: Clock,
    /// Sampler seed (the first of `--seeds`).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Renders per point of a series, with seeds `seed, seed+1, …`; from 2 on, the error is
    /// the seed-to-seed variance of one render (reference-free numerator; the reference, if
    /// any, only normalises) and the seconds are the renders' mean.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=64))]
    pub seeds: u32,
    /// Where the sample numbers come from (every estimator alike).
    #[arg(long, value_enum, default_value_t = crate::render_cmd::SamplerArg::Sobol)]
    pub sampler: crate::render_cmd::SamplerArg,
    /// Render threads (0 = all cores).
    #[arg(long, default_value_t = 0)]
    pub threads: usize,
    /// Film size override, e.g. 160x120.
    #[arg(long, value_name = "WxH")]
    pub res: Option<Resolution>,
    /// Tile edge in pixels.
    #[arg(long, default_value_t = 32, value_parser = clap::value_parser!(u32).range(1..=4096))]
    pub tile_size: u32,
    /// Value for a Mitsuba XML `$parameter` (repeatable).
    #[arg(short = 'D', long, value_name = "KEY=VALUE")]
    pub define: Vec<String>,
}

/// The clock that the speedups and the plot use.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Clock {
    /// Process CPU seconds (user + system, all threads).
    Cpu,
    /// Wall-clock seconds.
    Wall,
}

/// CPU seconds (user + system) of this process so far, from `/proc/self/stat` (Linux;
/// `None` elsewhere). Resolution: one clock tick (10 ms).
pub fn process_cpu_seconds() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    // Fields after `(comm)`: state is field 3, utime field 14, stime field 15.
    let rest = stat.get(stat.rfind(')')? + 1..)?;
    let f: Vec<&str> = rest.split_whitespace().collect();
    let ticks = |i: usize| f.get(i).and_then(|v| v.parse::<f64>().ok());
    // USER_HZ, fixed at 100 for the /proc interface on Linux.
    Some((ticks(11)? + ticks(12)?) / 100.0)
}

/// The 1-minute load average from `/proc/loadavg` as printed there ("unknown" elsewhere).
fn load_average() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .ok()
        .and_then(|l| l.split_whitespace().next().map(str::to_owned))
        .unwrap_or_else(|| "unknown".into())
}

/// One render of the series.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Run {
    /// Samples per pixel.
    pub spp: u32,
    /// Seconds on the comparison clock (`--clock`).
    pub seconds: f64,
    /// Render wall seconds.
    pub wall_seconds: f64,
    /// Render CPU seconds of the process (NaN when unknown).
    pub cpu_seconds: f64,
    /// relMSE (ε = 0.01) against the reference, or estimated from variance.
    pub relmse: f64,
    /// MSE (or mean variance of the mean without a reference).
    pub mse: f64,
}

/// The renders of one estimator at one spp, one per seed, before they become a [`Run`].
#[derive(Default)]
struct Point {
    /// Mean images, one per seed.
    means: Vec<Vec<f32>>,
    /// Variance image of the last render (one seed without a reference only).
    last_var: Vec<f32>,
    /// Summed wall and CPU seconds.
    wall: f64,
    cpu: f64,
}

impl Point {
    /// The run: mean seconds and the error of the point (seed-to-seed with ≥ 2 seeds, else
    /// against the reference or from the per-pixel variance).
    fn finish(self, spp: u32, args: &BenchArgs, reference: Option<&[f32]>) -> Run {
        let n = f64::from(args.seeds);
        let (wall, cpu) = (self.wall / n, self.cpu / n);
        let (relmse, mse) = if args.seeds >= 2 {
            let views: Vec<&[f32]> = self.means.iter().map(Vec::as_slice).collect();
            estimators::metrics::seed_variance_error(&views, reference)
                .map_or((f64::NAN, f64::NAN), |e| (e.rel_mse, e.mse))
        } else {
            match reference {
                Some(rf) => {
                    let e = estimators::metrics::compare(&self.means[0], rf);
                    (e.rel_mse, e.mse)
                }
                None => {
                    let var = &self.last_var;
                    let rel = estimators::metrics::estimated_rel_mse(&self.means[0], var)
                        .unwrap_or(f64::NAN);
                    let mse =
                        var.iter().map(|v| f64::from(*v)).sum::<f64>() / var.len().max(1) as f64;
                    (rel, mse)
                }
            }
        };
        Run {
            spp,
            seconds: match args.clock {
                Clock::Cpu if cpu > 0.0 => cpu,
                _ => wall,
            },
            wall_seconds: wall,
            cpu_seconds: cpu,
            relmse,
            mse,
        }
    }
}

/// An estimator's series.
#[derive(Clone, Debug, PartialEq)]
pub struct Series {
    /// Label (the `--estimators` item).
    pub label: String,
    /// Runs in increasing spp.
    pub runs: Vec<Run>,
}

/// Parses one `--estimators` item `kind[:key=value…]`.
fn parse_item(item: &str) -> Result<Estimator, UsageError> {
    let mut parts = item.trim().split(':');
    let kind = parts.next().unwrap_or_default().trim();
    let opts: Vec<String> = parts.map(str::to_string).collect();
    estimator_opts::build(Some(kind), None, &opts)
        .map_err(|e| UsageError(format!("--estimators `{item}`: {e}")))
}

/// relMSE at time `t` by log-log interpolation of `runs`, extrapolated with slope −1.
pub fn relmse_at(runs: &[Run], t: f64) -> Option<f64> {
    let pts: Vec<(f64, f64)> = runs
        .iter()
        .filter(|r| r.seconds > 0.0 && r.relmse > 0.0 && r.relmse.is_finite())
        .map(|r| (r.seconds.ln(), r.relmse.ln()))
        .collect();
    let (first, last) = (pts.first()?, pts.last()?);
    let lt = t.ln();
    if lt <= first.0 {
        return Some((first.1 - (lt - first.0)).exp());
    }
    if lt >= last.0 {
        return Some((last.1 - (lt - last.0)).exp());
    }
    for w in pts.windows(2) {
        let ((t0, e0), (t1, e1)) = (w[0], w[1]);
        if lt >= t0 && lt <= t1 {
            let f = if t1 > t0 { (lt - t0) / (t1 - t0) } else { 0.0 };
            return Some((e0 + f * (e1 - e0)).exp());
        }
    }
    None
}

/// The comparison of one series with the baseline.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Speedups {
    /// relMSE_base / relMSE_x at equal time.
    pub equal_time: f64,
    /// relMSE_base / relMSE_x at the largest common spp.
    pub equal_sample: f64,
    /// The spp of the equal-sample comparison.
    pub common_spp: u32,
    /// t_x / t_base − 1 at that spp.
    pub overhead: f64,
}

/// Compares `x` with the baseline `base`.
pub fn speedups(base: &Series, x: &Series) -> Option<Speedups> {
    let t = base.runs.last()?.seconds.min(x.runs.last()?.seconds);
    let equal_time = relmse_at(&base.runs, t)? / relmse_at(&x.runs, t)?;
    let (b, r) = x
        .runs
        .iter()
        .rev()
        .find_map(|r| base.runs.iter().find(|b| b.spp == r.spp).map(|b| (b, r)))?;
    Some(Speedups {
        equal_time,
        equal_sample: b.relmse / r.relmse,
        common_spp: r.spp,
        overhead: r.seconds / b.seconds - 1.0,
    })
}

/// The CSV text.
pub fn csv(series: &[Series]) -> String {
    let mut s = String::from("estimator,spp,seconds,relmse,mse,wall_seconds,cpu_seconds\n");
    for se in series {
        for r in &se.runs {
            let _ = writeln!(
                s,
                "{},{},{:.6},{:.6e},{:.6e},{:.6},{:.6}",
                se.label, r.spp, r.seconds, r.relmse, r.mse, r.wall_seconds, r.cpu_seconds
            );
        }
    }
    s
}

/// The markdown report.
pub fn markdown(title: &str, notes: &[String], series: &[Series]) -> String {
    let mut s = format!("# {title}\n\n");
    for n in notes {
        let _ = writeln!(s, "- {n}");
    }
    s.push_str(
        "\n| estimator | equal-time speedup | equal-sample speedup (spp) | time overhead | relMSE (longest run) | seconds | spp |\n|---|---|---|---|---|---|---|\n",
    );
    let base = &series[0];
    for se in series {
        let last = se.runs.last();
        let (rel, secs, spp) =
            last.map_or((f64::NAN, f64::NAN, 0), |r| (r.relmse, r.seconds, r.spp));
        let cols = if std::ptr::eq(se, base) {
            "1.00× | 1.00× | +0.0 %".to_string()
        } else {
            match speedups(base, se) {
                Some(sp) => format!(
                    "{:.2}× | {:.2}× ({}) | {:+.1} %",
                    sp.equal_time,
                    sp.equal_sample,
                    sp.common_spp,
                    sp.overhead * 100.0
                ),
                None => "– | – | –".to_string(),
            }
        };
        let _ = writeln!(
            s,
            "| {} | {cols} | {rel:.4e} | {secs:.2} | {spp} |",
            se.label
        );
    }
    s.push_str(
        "\n## Series\n\n| estimator | spp | seconds | relMSE | MSE | wall s | CPU s |\n|---|---|---|---|---|---|---|\n",
    );
    for se in series {
        for r in &se.runs {
            let _ = writeln!(
                s,
                "| {} | {} | {:.3} | {:.4e} | {:.4e} | {:.3} | {:.3} |",
                se.label, r.spp, r.seconds, r.relmse, r.mse, r.wall_seconds, r.cpu_seconds
            );
        }
    }
    s.push_str("\n![relMSE vs time](bench.svg)\n");
    s
}

/// XML-escapes text for the SVG.
fn esc(t: &str) -> String {
    t.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
}

/// The relMSE-vs-seconds log-log plot, written by hand.
pub fn svg(title: &str, series: &[Series]) -> String {
    const COLOURS: [&str; 6] = [
        "#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b",
    ];
    let (w, h) = (640.0f64, 420.0f64);
    let (l, r, t, b) = (70.0, 160.0, 40.0, 50.0);
    let pts = || {
        series
            .iter()
            .flat_map(|s| s.runs.iter())
            .filter(|r| r.seconds > 0.0 && r.relmse > 0.0 && r.relmse.is_finite())
    };
    let dec = |v: f64, up: bool| {
        let x = v.log10();
        if up { x.ceil() } else { x.floor() }
    };
    let (mut x0, mut x1) = (f64::INFINITY, f64::NEG_INFINITY);
    let (mut y0, mut y1) = (f64::INFINITY, f64::NEG_INFINITY);
    for p in pts() {
        x0 = x0.min(p.seconds);
        x1 = x1.max(p.seconds);
        y0 = y0.min(p.relmse);
        y1 = y1.max(p.relmse);
    }
    if !x0.is_finite() {
        (x0, x1, y0, y1) = (0.1, 1.0, 0.1, 1.0);
    }
    let (lx0, mut lx1) = (dec(x0, false), dec(x1, true));
    let (ly0, mut ly1) = (dec(y0, false), dec(y1, true));
    if lx1 <= lx0 {
        lx1 = lx0 + 1.0;
    }
    if ly1 <= ly0 {
        ly1 = ly0 + 1.0;
    }
    let px = |v: f64| l + (v.log10() - lx0) / (lx1 - lx0) * (w - l - r);
    let py = |v: f64| t + (ly1 - v.log10()) / (ly1 - ly0) * (h - t - b);
    let mut s = format!(
        "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{w}\" height=\"{h}\" viewBox=\"0 0 {w} {h}\" font-family=\"sans-serif\" font-size=\"12\">\n<rect width=\"100%\" height=\"100%\" fill=\"white\"/>\n<text x=\"{}\" y=\"22\" text-anchor=\"middle\" font-size=\"14\">{}</text>\n",
        (l + w - r) / 2.0,
        esc(title)
    );
    // Decade grid and labels.
    let mut e = lx0;
    while e <= lx1 + 1e-9 {
        let x = px(10f64.powf(e));
        let _ = writeln!(
            s,
            "<line x1=\"{x:.1}\" y1=\"{t}\" x2=\"{x:.1}\" y2=\"{:.1}\" stroke=\"#ddd\"/><text x=\"{x:.1}\" y=\"{:.1}\" text-anchor=\"middle\">1e{e}</text>",
            h - b,
            h - b + 16.0
        );
        e += 1.0;
    }
    let mut e = ly0;
    while e <= ly1 + 1e-9 {
        let y = py(10f64.powf(e));
        let _ = writeln!(
            s,
            "<line x1=\"{l}\" y1=\"{y:.1}\" x2=\"{:.1}\" y2=\"{y:.1}\" stroke=\"#ddd\"/><text x=\"{:.1}\" y=\"{:.1}\" text-anchor=\"end\">1e{e}</text>",
            w - r,
            l - 6.0,
            y + 4.0
        );
        e += 1.0;
    }
    let _ = writeln!(
        s,
        "<rect x=\"{l}\" y=\"{t}\" width=\"{:.1}\" height=\"{:.1}\" fill=\"none\" stroke=\"black\"/>\n<text x=\"{:.1}\" y=\"{:.1}\" text-anchor=\"middle\">render time (s)</text>\n<text x=\"16\" y=\"{:.1}\" text-anchor=\"middle\" transform=\"rotate(-90 16 {:.1})\">relMSE</text>",
        w - l - r,
        h - t - b,
        (l + w - r) / 2.0,
        h - 12.0,
        (t + h - b) / 2.0,
        (t + h - b) / 2.0
    );
    for (i, se) in series.iter().enumerate() {
        let c = COLOURS[i % COLOURS.len()];
        let p: Vec<(f64, f64)> = se
            .runs
            .iter()
            .filter(|r| r.seconds > 0.0 && r.relmse > 0.0 && r.relmse.is_finite())
            .map(|r| (px(r.seconds), py(r.relmse)))
            .collect();
        let line: Vec<String> = p.iter().map(|(x, y)| format!("{x:.1},{y:.1}")).collect();
        let _ = writeln!(
            s,
            "<polyline fill=\"none\" stroke=\"{c}\" stroke-width=\"2\" points=\"{}\"/>",
            line.join(" ")
        );
        for (x, y) in &p {
            let _ = writeln!(
                s,
                "<circle cx=\"{x:.1}\" cy=\"{y:.1}\" r=\"3\" fill=\"{c}\"/>"
            );
        }
        let ly = t + 10.0 + 18.0 * i as f64;
        let _ = writeln!(
            s,
            "<line x1=\"{:.1}\" y1=\"{ly:.1}\" x2=\"{:.1}\" y2=\"{ly:.1}\" stroke=\"{c}\" stroke-width=\"2\"/><text x=\"{:.1}\" y=\"{:.1}\">{}</text>",
            w - r + 10.0,
            w - r + 30.0,
            w - r + 35.0,
            ly + 4.0,
            esc(&se.label)
        );
    }
    s.push_str("</svg>\n");
    s
}

/// Runs `cvfarm bench`.
pub fn run(args: &BenchArgs) -> Result<ExitCode> {
    let mut items: Vec<(String, Estimator)> = Vec::new();
    for it in &args.estimators {
        let it = it.trim();
        if it.is_empty() {
            continue;
        }
        items.push((it.to_string(), parse_item(it)?));
    }
    if !items.iter().any(|(_, e)| *e == Estimator::Path) {
        items.insert(0, ("path".into(), Estimator::Path));
    } else if let Some(i) = items.iter().position(|(_, e)| *e == Estimator::Path) {
        let p = items.remove(i);
        items.insert(0, p);
    }
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating directory {}", args.out.display()))?;
    let mut scene = load_scene_file(&args.scene, &args.define, args.res)?;
    let base = RenderSettings::from_scene(&scene);
    let st0 = RenderSettings {
        seed: args.seed,
        sampler: args.sampler.kind(),
        max_depth: args.max_depth.unwrap_or(base.max_depth),
        ..base
    };
    st0.validate()?;
    scene.integrator.max_depth = st0.max_depth;
    let rs = RenderScene::new(&scene, &st0)
        .with_context(|| format!("preparing {}", args.scene.display()))?;
    let mut ref_floor: Option<f64> = None;
    let reference = match &args.reference {
        Some(p) => {
            let img = imageio::read_exr(p).with_context(|| format!("reading {}", p.display()))?;
            if (img.width, img.height) != (rs.width, rs.height) {
                bail!(
                    "reference {} is {}x{}, the render is {}x{}",
                    p.display(),
                    img.width,
                    img.height,
                    rs.width,
                    rs.height
                );
            }
            let layer = img.main_layer().context("reference has no colour layer")?;
            let data: Vec<f32> = layer.data.iter().flatten().copied().collect();
            // The reference's own noise (from its variance layer) is a floor under every
            // measured relMSE: report it so speedups near the floor are read with care.
            ref_floor = img.layer("variance").and_then(|v| {
                let var: Vec<f32> = v.data.iter().flatten().copied().collect();
                estimators::metrics::estimated_rel_mse(&data, &var)
            });
            Some(data)
        }
        None => None,
    };
    let options = RenderOptions {
        tile_size: args.tile_size,
        threads: args.threads,
    };
    let series_spp: Vec<u32> = if args.spp_series.is_empty() {
        (0..16).map(|k| 1u32 << k).collect()
    } else {
        args.spp_series.clone()
    };
    let load_start = load_average();
    // One point of the series of each estimator, interleaved: at every spp, seed by seed,
    // the estimators take turns, so that a drift of the machine's speed (minutes long on a
    // VM) moves every estimator's times alike instead of whichever ran in that minute.
    let mut all: Vec<Series> = items
        .iter()
        .map(|(label, _)| Series {
            label: label.clone(),
            runs: Vec::new(),
        })
        .collect();
    let mut totals = vec![0.0f64; items.len()];
    let mut active = vec![true; items.len()];
    for &spp in &series_spp {
        for (i, se) in all.iter().enumerate() {
            if let Some(last) = se.runs.last() {
                let predicted = last.wall_seconds * f64::from(spp) / f64::from(last.spp)
                    * f64::from(args.seeds);
                if totals[i] + predicted > args.max_seconds {
                    active[i] = false;
                }
            }
        }
        if !active.iter().any(|&a| a) {
            break;
        }
        let mut points: Vec<Point> = items.iter().map(|_| Point::default()).collect();
        for k in 0..args.seeds {
            let seed = args.seed.wrapping_add(u64::from(k));
            for (i, (label, est)) in items.iter().enumerate() {
                if !active[i] {
                    continue;
                }
                let settings = RenderSettings {
                    estimator: *est,
                    spp,
                    seed,
                    ..st0
                };
                let cpu0 = process_cpu_seconds();
                let r = local_render::render_spp(&rs, &settings, &options, &|_, _| {})
                    .with_context(|| format!("rendering {label} at {spp} spp, seed {seed}"))?;
                let pt = &mut points[i];
                pt.cpu += match (cpu0, process_cpu_seconds()) {
                    (Some(a), Some(b)) => b - a,
                    _ => f64::NAN,
                };
                pt.wall += r.stats.seconds;
                pt.means
                    .push(r.film.mean_image().into_iter().flatten().collect());
                if args.seeds == 1 && reference.is_none() {
                    pt.last_var = r.film.variance_image().into_iter().flatten().collect();
                }
            }
        }
        for (i, pt) in points.into_iter().enumerate() {
            if !active[i] {
                continue;
            }
            let run = pt.finish(spp, args, reference.as_deref());
            totals[i] += run.wall_seconds * f64::from(args.seeds);
            eprintln!(
                "bench {}: {spp} spp in {:.2} s, relMSE {:.3e}",
                all[i].label, run.wall_seconds, run.relmse
            );
            all[i].runs.push(run);
        }
    }
    let name = args
        .scene
        .parent()
        .and_then(|d| d.file_name())
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| args.scene.display().to_string());
    let title = format!("{name}, max_depth {}", st0.max_depth);
    let notes = vec![
        format!(
            "scene `{}`, {}x{}, max_depth {}, seed {}, sampler {}",
            args.scene.display(),
            rs.width,
            rs.height,
            st0.max_depth,
            args.seed,
            args.sampler.name()
        ),
        match &args.reference {
            _ if args.seeds >= 2 => format!(
                "error = the seed-to-seed variance of one render over {} seeds ({}…): the expected squared error of an unbiased estimator, with no reference noise in it (valid for the Sobol sampler: seeds are independent randomisations); normalised by {} (relMSE ε = 0.01); seconds are the renders' mean",
                args.seeds,
                args.seed,
                args.reference
                    .as_ref()
                    .map_or("the seeds' mean".to_string(), |p| format!(
                        "the reference `{}`",
                        p.display()
                    ))
            ),
            Some(p) => format!(
                "error against the reference `{}` (relMSE ε = 0.01); the reference's own relMSE estimated from its variance layer (a noise floor under every figure; the estimate assumes independent samples, so it overstates the error of a Sobol-sampled reference) is {}",
                p.display(),
                ref_floor.map_or("unknown (no variance layer)".to_string(), |f| format!(
                    "{f:.2e}"
                ))
            ),
            None => "no reference: relMSE estimated from the per-pixel variance of the mean".into(),
        },
        format!(
            "seconds = {} of rendering (scene preparation excluded), the estimators taking turns render by render so that a drift of the machine's speed moves them alike; load average (1 min) at the start {}, at the end {}: where other jobs share the machine CPU time is much steadier than wall time, but cache and memory contention still move times, and with them equal-time speedups and overheads",
            match args.clock {
                Clock::Cpu => "process CPU seconds (all render threads)",
                Clock::Wall => "wall-clock seconds",
            },
            load_start,
            load_average(),
        ),
        format!(
            "rerun: `cvfarm bench {} --estimators {} --max-depth {} --max-seconds {} --clock {} --seed {} --seeds {}{}{}{}{}`",
            args.scene.display(),
            items
                .iter()
                .map(|i| i.0.as_str())
                .collect::<Vec<_>>()
                .join(","),
            st0.max_depth,
            args.max_seconds,
            match args.clock {
                Clock::Cpu => "cpu",
                Clock::Wall => "wall",
            },
            args.seed,
            args.seeds,
            match args.sampler {
                crate::render_cmd::SamplerArg::Sobol => String::new(),
                s => format!(" --sampler {}", s.name()),
            },
            args.res
                .map(|r| format!(" --res {}x{}", r.width, r.height))
                .unwrap_or_default(),
            if args.spp_series.is_empty() {
                String::new()
            } else {
                format!(
                    " --spp-series {}",
                    args.spp_series
                        .iter()
                        .map(u32::to_string)
                        .collect::<Vec<_>>()
                        .join(",")
                )
            },
            args.reference
                .as_ref()
                .map(|p| format!(" --reference {}", p.display()))
                .unwrap_or_default()
        ),
    ];
    let write = |file: &str, text: String| -> Result<()> {
        let p = args.out.join(file);
        std::fs::write(&p, text).with_context(|| format!("writing {}", p.display()))
    };
    write("bench.csv", csv(&all))?;
    write("bench.md", markdown(&title, &notes, &all))?;
    write("bench.svg", svg(&title, &all))?;
    for se in all.iter().skip(1) {
        if let Some(sp) = speedups(&all[0], se) {
            println!(
                "{}: equal-time speedup {:.2}x, equal-sample speedup {:.2}x at {} spp, time overhead {:+.1} %",
                se.label,
                sp.equal_time,
                sp.equal_sample,
                sp.common_spp,
                sp.overhead * 100.0
            );
        }
    }
    println!("wrote {}/bench.{{csv,md,svg}}", args.out.display());
    Ok(ExitCode::SUCCESS)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn run(spp: u32, seconds: f64, relmse: f64) -> Run {
        Run {
            spp,
            seconds,
            wall_seconds: seconds,
            cpu_seconds: seconds,
            relmse,
            mse: relmse,
        }
    }

    #[test]
    fn halved_error_at_equal_time_is_2x_and_overhead_is_time_ratio() {
        let base = Series {
            label: "path".into(),
            runs: vec![run(1, 1.0, 0.4), run(2, 2.0, 0.2), run(4, 4.0, 0.1)],
        };
        let x = Series {
            label: "x".into(),
            runs: vec![run(1, 1.1, 0.1), run(2, 2.2, 0.05)],
        };
        let sp = speedups(&base, &x).unwrap();
        // At t = 2.2: path ≈ 0.2 · 2/2.2, x = 0.05.
        assert!(
            (sp.equal_time - 0.2 * 2.0 / 2.2 / 0.05).abs() < 1e-9,
            "{sp:?}"
        );
        assert_eq!(sp.common_spp, 2);
        assert!((sp.equal_sample - 4.0).abs() < 1e-12);
        assert!((sp.overhead - 0.1).abs() < 1e-12);
    }

    #[test]
    fn csv_md_svg_have_every_run() {
        let s = vec![
            Series {
                label: "path".into(),
                runs: vec![run(1, 0.5, 0.3), run(2, 1.0, 0.15)],
            },
            Series {
                label: "ocv:spe=8".into(),
                runs: vec![run(1, 0.7, 0.1)],
            },
        ];
        let c = csv(&s);
        assert_eq!(c.lines().count(), 4);
        assert!(c.starts_with("estimator,spp,seconds,relmse,mse,wall_seconds,cpu_seconds\n"));
        let m = markdown("t", &[], &s);
        assert!(m.contains("| ocv:spe=8 |"), "{m}");
        let g = svg("t <&>", &s);
        assert_eq!(g.matches("<polyline").count(), 2);
        assert!(g.contains("t &lt;&amp;&gt;"));
    }
}
