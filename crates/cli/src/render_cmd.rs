//! `cvfarm render SCENE -o OUT.exr`: render a scene locally with the embedded renderer.
//!
//! The scene is a native JSON scene (`scenes/README.md`) or a Mitsuba 3 XML file (by
//! extension). Settings not given on the command line come from the scene's `integrator`
//! block (max depth, Russian roulette depth, hidden emitters) or the defaults below. The
//! output EXR has the layers `beauty` (plain R, G, B), `variance` (per-pixel variance of
//! the mean), `albedo` and `normal`; `--png` adds an 8-bit sRGB preview (clamped).
//!
//! | flag | env | default | meaning |
//! |---|---|---|---|
//! | `--spp N` | `CVFARM_SPP` | 16 | samples per pixel |
//! | `--max-depth D` | `CVFARM_MAX_DEPTH` | scene's (5) | path segments incl. the camera ray; 2 = direct lighting, −1 = unbounded |
//! | `--rr-depth D` | `CVFARM_RR_DEPTH` | scene's (5) | depth from which Russian roulette applies |
//! | `--seed S` | `CVFARM_SEED` | 0 | sampler seed (same seed ⇒ bitwise-identical image) |
//! | `--threads T` | `CVFARM_THREADS` | 0 = all cores | render threads |
//! | `--res WxH` | `CVFARM_RES` | scene's | override the film size (`fov` stays along the scene's `fov_axis`) |
//! | `-D, --define K=V` | `CVFARM_DEFINES` (comma-separated) | none | value of a Mitsuba XML `$K` parameter |
//! | `--estimator E` | `CVFARM_ESTIMATOR` | `path` | estimator: `path`, `ocv`, `cms`, `per_light_cv`, `optimal_mis` |
//! | `--opt K=V` | — | none | an estimator option (repeatable), e.g. `--opt spe=32`; unknown names are errors listing the valid ones |
//! | `--estimator-json J` | `CVFARM_ESTIMATOR_JSON` | none | the estimator as JSON (`{"kind":"ocv","spe":32}`) or `@file.json` |
//! | `--time-budget S` | `CVFARM_TIME_BUDGET` | none | render sample batches until S seconds are spent (instead of `--spp`) |
//! | `--mis H` | `CVFARM_MIS` | `power` | MIS heuristic: `power` or `balance` |
//! | `--light-selection L` | `CVFARM_LIGHT_SELECTION` | `uniform` | NEE light choice: `uniform` or `power` |
//! | `--hide-emitters` | `CVFARM_HIDE_EMITTERS` | scene's | directly visible emitters are black |
//! | `--tile-size N` | `CVFARM_TILE_SIZE` | 32 | tile edge in pixels (does not change the image) |
//! | `-o, --output F` | `CVFARM_OUTPUT` | — | EXR file to write (parent directories are created) |
//! | `--png F` | `CVFARM_PNG` | none | also write an sRGB PNG preview |
//! | `--stats F` | `CVFARM_STATS` | none | also write the render statistics (and the scene's `Features`) as JSON |
//!
//! ```text
//! $ cvfarm render scenes/cornell-box/scene.json --spp 64 -o out/cbox.exr --png out/cbox.png
//! rendered scenes/cornell-box/scene.json: 256x256, 64 spp (path, max_depth 5) in 2.41 s: 1.74 M samples/s, 6.9 M rays/s -> out/cbox.exr
//! ```
//! The progress bar (stderr) is shown only when stderr is a terminal.
//!
//! Estimator options are those of the option structs in `render::integrator` (see
//! [`crate::estimator_opts`]); the stats JSON records the estimator with all its options and
//! the estimator's report, and the EXR gets the extra layers the estimator provides.

use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::str::FromStr;

use anyhow::{Context, Result, bail};
use clap::{Args, ValueEnum};
use indicatif::{ProgressBar, ProgressState, ProgressStyle};
use render::integrator::{MisHeuristic, RenderScene, RenderSettings};
use render::light::LightSelection;
use render::tile::RenderOptions;
use serde_json::json;

use crate::estimator_opts;
use crate::local_render;

/// Largest accepted film edge (pixels) for `--res`.
pub const MAX_RES: u32 = 1 << 15;
/// Largest accepted image (pixels) for `--res`.
pub const MAX_PIXELS: u64 = 1 << 27;

/// Arguments of `cvfarm render`.
#[derive(Debug, Args)]
pub struct RenderArgs {
    /// Scene file: native JSON (.json) or Mitsuba 3 XML (.xml).
    pub scene: PathBuf,
    /// Samples per pixel.
    #[arg(long, env = "CVFARM_SPP", default_value_t = RenderSettings::DEFAULT_SPP,
          value_parser = clap::value_parser!(u32).range(1..))]
    pub spp: u32,
    /// Max path segments incl. the camera ray (2 = direct lighting, -1 = unbounded) [default: the scene's].
    #[arg(long, env = "CVFARM_MAX_DEPTH", allow_negative_numbers = true)]
    pub max_depth: Option<i32>,
    /// Depth from which Russian roulette applies [default: the scene's].
    #[arg(long, env = "CVFARM_RR_DEPTH")]
    pub rr_depth: Option<i32>,
    /// Sampler seed.
    #[arg(long, env = "CVFARM_SEED", default_value_t = 0)]
    pub seed: u64,
    /// Render threads (0 = all cores).
    #[arg(long, env = "CVFARM_THREADS", default_value_t = 0)]
    pub threads: usize,
    /// Film size override, e.g. 320x240.
    #[arg(
        long,
        env = "CVFARM_RES",
        value_name = "WxH",
        allow_hyphen_values = true
    )]
    pub res: Option<Resolution>,
    /// Estimator selection.
    #[command(flatten)]
    pub estimator: crate::estimator_opts::EstimatorArgs,
    /// Render until this many seconds are spent (sample batches) instead of a fixed --spp.
    #[arg(long, env = "CVFARM_TIME_BUDGET", value_name = "SECONDS", conflicts_with = "spp",
          value_parser = parse_budget)]
    pub time_budget: Option<f64>,
    /// MIS heuristic for NEE vs BSDF sampling.
    #[arg(long, env = "CVFARM_MIS", value_enum, default_value_t = MisArg::Power)]
    pub mis: MisArg,
    /// How NEE picks a light.
    #[arg(long, env = "CVFARM_LIGHT_SELECTION", value_enum, default_value_t = LightSelectionArg::Uniform)]
    pub light_selection: LightSelectionArg,
    /// Where the sample numbers come from.
    #[arg(long, env = "CVFARM_SAMPLER", value_enum, default_value_t = SamplerArg::Sobol)]
    pub sampler: SamplerArg,
    /// Hide directly visible emitters [default: the scene's].
    #[arg(long, env = "CVFARM_HIDE_EMITTERS", value_parser = clap::builder::BoolishValueParser::new())]
    pub hide_emitters: bool,
    /// Tile edge in pixels (affects speed only, never the image).
    #[arg(long, env = "CVFARM_TILE_SIZE", default_value_t = 32,
          value_parser = clap::value_parser!(u32).range(1..=4096))]
    pub tile_size: u32,
    /// Value for a Mitsuba XML `$parameter` (repeatable; env: comma-separated).
    #[arg(
        short = 'D',
        long,
        env = "CVFARM_DEFINES",
        value_name = "KEY=VALUE",
        value_delimiter = ','
    )]
    pub define: Vec<String>,
    /// Output EXR file.
    #[arg(short, long, env = "CVFARM_OUTPUT")]
    pub output: PathBuf,
    /// Also write an 8-bit sRGB PNG preview here.
    #[arg(long, env = "CVFARM_PNG")]
    pub png: Option<PathBuf>,
    /// Also write render statistics (time, samples/s, rays/s, image mean) as JSON here.
    #[arg(long, env = "CVFARM_STATS")]
    pub stats: Option<PathBuf>,
}

/// The `--estimator` values (the `kind`s of `render::integrator::Estimator`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum EstimatorArg {
    /// NEE + BSDF MIS path tracer (the baseline).
    Path,
    /// Optimizing control variates for the direct-lighting gather (Fan 2006).
    Ocv,
    /// Controlled mixture sampling (Hua 2023).
    Cms,
    /// Per-cell per-light CV (Vévoda-style, Hua §7.2).
    #[value(name = "per_light_cv", alias = "per-light-cv")]
    PerLightCv,
    /// Optimal MIS per pixel (Kondapaneni 2019, Hua §7.4).
    #[value(name = "optimal_mis", alias = "optimal-mis")]
    OptimalMis,
}

impl EstimatorArg {
    /// The estimator's `kind`.
    pub fn name(self) -> &'static str {
        match self {
            EstimatorArg::Path => "path",
            EstimatorArg::Ocv => "ocv",
            EstimatorArg::Cms => "cms",
            EstimatorArg::PerLightCv => "per_light_cv",
            EstimatorArg::OptimalMis => "optimal_mis",
        }
    }
}

/// Parses a positive, finite number of seconds.
pub fn parse_budget(s: &str) -> Result<f64, String> {
    match s.trim().parse::<f64>() {
        Ok(v) if v > 0.0 && v.is_finite() => Ok(v),
        _ => Err(format!("expected a positive number of seconds, got `{s}`")),
    }
}

/// The `--mis` values.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum MisArg {
    /// Power heuristic (β = 2), as Mitsuba.
    Power,
    /// Balance heuristic.
    Balance,
}

/// The `--sampler` values (`render::sampler::SamplerKind`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, ValueEnum)]
pub enum SamplerArg {
    /// Owen-scrambled Sobol points per pixel (stratified; the default).
    #[default]
    Sobol,
    /// Independent uniform numbers (Mitsuba's `independent`; the papers' baseline).
    Independent,
}

impl SamplerArg {
    /// The renderer's sampler kind.
    pub fn kind(self) -> render::sampler::SamplerKind {
        match self {
            Self::Sobol => render::sampler::SamplerKind::Sobol,
            Self::Independent => render::sampler::SamplerKind::Independent,
        }
    }

    /// The name on the command line and in a job's `sampler`.
    pub fn name(self) -> &'static str {
        match self {
            Self::Sobol => "sobol",
            Self::Independent => "independent",
        }
    }
}

/// The `--light-selection` values.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum LightSelectionArg {
    /// Every emitter equally likely, as Mitsuba.
    Uniform,
    /// Proportional to emitted power.
    Power,
}

/// A film size `WxH`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Resolution {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
}

impl FromStr for Resolution {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let bad = || format!("expected WIDTHxHEIGHT like 320x240, got `{s}`");
        let (w, h) = s.trim().split_once(['x', 'X']).ok_or_else(bad)?;
        let width: u32 = w.trim().parse().map_err(|_| bad())?;
        let height: u32 = h.trim().parse().map_err(|_| bad())?;
        if width == 0 || height == 0 {
            return Err(format!("resolution must be at least 1x1, got `{s}`"));
        }
        if width > MAX_RES || height > MAX_RES || u64::from(width) * u64::from(height) > MAX_PIXELS
        {
            return Err(format!(
                "resolution `{s}` is too large (max {MAX_RES} per side, {MAX_PIXELS} pixels)"
            ));
        }
        Ok(Self { width, height })
    }
}

/// The settings of this render, from the scene and the arguments.
pub fn settings(scene: &scene::Scene, args: &RenderArgs) -> Result<RenderSettings> {
    let base = RenderSettings::from_scene(scene);
    let st = RenderSettings {
        spp: args.spp,
        seed: args.seed,
        max_depth: args.max_depth.unwrap_or(base.max_depth),
        rr_depth: args.rr_depth.unwrap_or(base.rr_depth),
        hide_emitters: args.hide_emitters || base.hide_emitters,
        mis: match args.mis {
            MisArg::Power => MisHeuristic::Power,
            MisArg::Balance => MisHeuristic::Balance,
        },
        light_selection: match args.light_selection {
            LightSelectionArg::Uniform => LightSelection::Uniform,
            LightSelectionArg::Power => LightSelection::Power,
        },
        estimator: args.estimator.build()?,
        sampler: args.sampler.kind(),
    };
    st.validate()?;
    Ok(st)
}

/// Parses `--define KEY=VALUE`s into Mitsuba XML parameters (`render` and `submit` alike).
pub fn parse_defines(define: &[String]) -> Result<Vec<(String, String)>> {
    define
        .iter()
        .map(|d| {
            let (k, v) = d
                .split_once('=')
                .with_context(|| format!("--define `{d}`: expected KEY=VALUE"))?;
            Ok((k.trim().to_string(), v.trim().to_string()))
        })
        .collect()
}

/// Reads the scene description (JSON or Mitsuba XML with `--define`s), applies `--res` to it
/// (so that `fov_axis` is resolved for the new size, as Mitsuba does) and loads its assets.
/// Load warnings are printed on stderr.
pub fn load_scene(args: &RenderArgs) -> Result<scene::Scene> {
    load_scene_file(&args.scene, &args.define, args.res)
}

/// [`load_scene`] from its parts: scene path, `--define`s, `--res`.
pub fn load_scene_file(
    path: &Path,
    define: &[String],
    res: Option<Resolution>,
) -> Result<scene::Scene> {
    let params = parse_defines(define)?;
    let (mut desc, mut warnings) = scene::read_desc_file(path, &params)
        .with_context(|| format!("loading {}", path.display()))?;
    if let Some(res) = res {
        desc.film = scene::desc::FilmDesc {
            width: res.width,
            height: res.height,
        };
    }
    let dir = path
        .parent()
        .filter(|d| !d.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    let loaded = scene::load(&desc, &scene::DirAssets::new(dir))
        .with_context(|| format!("loading {}", path.display()))?;
    warnings.extend(loaded.report.warnings.iter().cloned());
    if loaded.report.dropped_triangles > 0 {
        warnings.push(format!(
            "{} degenerate triangles dropped",
            loaded.report.dropped_triangles
        ));
    }
    for w in &warnings {
        eprintln!("warning: {}: {w}", path.display());
    }
    Ok(loaded.scene)
}

/// Creates the parent directory of `path` if needed.
fn ensure_parent(path: &Path) -> Result<()> {
    if let Some(dir) = path.parent()
        && !dir.as_os_str().is_empty()
    {
        std::fs::create_dir_all(dir)
            .with_context(|| format!("creating directory {}", dir.display()))?;
    }
    Ok(())
}

/// A rate with an SI prefix: `1.74 M`.
fn si(rate: f64) -> String {
    if !rate.is_finite() {
        return "-".into();
    }
    let (v, p) = match rate {
        r if r >= 1e9 => (r / 1e9, "G"),
        r if r >= 1e6 => (r / 1e6, "M"),
        r if r >= 1e3 => (r / 1e3, "k"),
        r => (r, ""),
    };
    format!("{v:.2} {p}")
}

/// Runs `cvfarm render`.
pub fn run(args: &RenderArgs) -> Result<ExitCode> {
    if args.output.as_os_str().is_empty() {
        bail!("--output must not be empty");
    }
    // Create output directories first: a bad output path should fail before a long render.
    for path in [Some(&args.output), args.png.as_ref(), args.stats.as_ref()]
        .into_iter()
        .flatten()
    {
        ensure_parent(path)?;
    }
    let mut scene = load_scene(args)?;
    let st = settings(&scene, args)?;
    // The effects this render simulates (with the command line's path length).
    scene.integrator.max_depth = st.max_depth;
    scene.integrator.rr_depth = st.rr_depth;
    scene.integrator.hide_emitters = st.hide_emitters;
    let features = scene::Features::of(&scene);
    let options = RenderOptions {
        tile_size: args.tile_size,
        threads: args.threads,
    };
    let rs = RenderScene::new(&scene, &st)
        .with_context(|| format!("preparing {}", args.scene.display()))?;
    let (width, height) = (rs.width, rs.height);

    let total = match args.time_budget {
        Some(b) => (b * 1e3) as u64,
        None => u64::from(width) * u64::from(height) * u64::from(st.spp),
    };
    let bar = if std::io::stderr().is_terminal() {
        let bar = ProgressBar::new(total);
        let style = ProgressStyle::with_template(
            "{spinner} {elapsed_precise} [{wide_bar}] {percent:>3}% {rate} ETA {eta}",
        )
        .map(|s| {
            s.progress_chars("=> ").with_key(
                "rate",
                |st: &ProgressState, w: &mut dyn std::fmt::Write| {
                    let _ = write!(w, "{}samples/s", si(st.per_sec()));
                },
            )
        })
        .unwrap_or_else(|_| ProgressStyle::default_bar());
        bar.set_style(style);
        bar
    } else {
        ProgressBar::hidden()
    };
    let progress = |done: u64, _total: u64| bar.set_position(done);
    let rendered = match args.time_budget {
        Some(budget) => local_render::render_budget(&rs, &st, &options, budget, &progress),
        None => local_render::render_spp(&rs, &st, &options, &progress),
    }
    .with_context(|| format!("rendering {}", args.scene.display()))?;
    bar.finish_and_clear();
    let (film, stats) = (&rendered.film, rendered.stats);
    let st = RenderSettings {
        spp: rendered.spp,
        ..st
    };
    let kind = estimator_opts::kind_of(&st.estimator);

    let mut layers: Vec<imageio::RgbLayer> = film
        .layers()
        .into_iter()
        .map(|l| imageio::RgbLayer {
            name: l.name.to_string(),
            data: l.data,
        })
        .collect();
    layers.extend(rendered.extra_layers.iter().cloned());
    imageio::write_exr(&args.output, width, height, &layers)
        .with_context(|| format!("writing {}", args.output.display()))?;
    if let Some(png) = &args.png {
        imageio::write_png_preview(png, width, height, &film.mean_image())
            .with_context(|| format!("writing {}", png.display()))?;
    }

    let secs = stats.seconds.max(1e-9);
    let (samples_per_s, rays_per_s) = (stats.samples as f64 / secs, stats.rays as f64 / secs);
    let mean = film.image_mean();
    // `ocv`'s pilot choice (made by the render, kept by the prepared scene).
    let pilot = rs.ocv_choice(&st);
    if let Some(path) = &args.stats {
        let doc = json!({
            "scene": args.scene.display().to_string(),
            "output": args.output.display().to_string(),
            "width": width,
            "height": height,
            "spp": st.spp,
            "seed": st.seed,
            "sampler": args.sampler.name(),
            "max_depth": st.max_depth,
            "rr_depth": st.rr_depth,
            "estimator": kind,
            "estimator_options": serde_json::to_value(st.estimator).unwrap_or_default(),
            "estimator_report": rendered.report.clone().unwrap_or_default(),
            "ocv_pilot": pilot.map(|c| json!({
                "predicted_speedup": c.speedup,
                "predicted_speedup_low": c.speedup_low,
                "gather": c.use_ocv,
                "rays": c.rays,
            })),
            "time_budget": args.time_budget,
            "threads": args.threads,
            "tile_size": args.tile_size,
            "samples": stats.samples,
            "rays": stats.rays,
            "seconds": stats.seconds,
            "samples_per_s": samples_per_s,
            "rays_per_s": rays_per_s,
            "rejected_samples": film.rejected,
            "mean": mean,
            "features": serde_json::to_value(&features).unwrap_or_default(),
        });
        std::fs::write(path, format!("{doc:#}\n"))
            .with_context(|| format!("writing {}", path.display()))?;
    }
    println!(
        "rendered {}: {width}x{height}, {} spp ({}, max_depth {}) in {:.2} s: {}samples/s, {}rays/s, mean RGB [{:.4}, {:.4}, {:.4}]{}{} -> {}",
        args.scene.display(),
        st.spp,
        kind,
        st.max_depth,
        stats.seconds,
        si(samples_per_s),
        si(rays_per_s),
        mean[0],
        mean[1],
        mean[2],
        if film.rejected > 0 {
            format!(", {} non-finite samples rejected", film.rejected)
        } else {
            String::new()
        },
        match pilot {
            Some(c) if c.speedup.is_nan() && c.use_ocv => String::new(),
            Some(c) => format!(
                ", ocv pilot: {:.2}x predicted over path (less one s.e.: {:.2}x) -> {}",
                c.speedup,
                c.speedup_low,
                if c.use_ocv { "gather" } else { "path" }
            ),
            None => String::new(),
        },
        args.output.display(),
    );
    Ok(ExitCode::SUCCESS)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn resolution_parses_and_rejects_garbage() {
        assert_eq!(
            "320x240".parse::<Resolution>(),
            Ok(Resolution {
                width: 320,
                height: 240
            })
        );
        assert_eq!(
            "16X9".parse::<Resolution>(),
            Ok(Resolution {
                width: 16,
                height: 9
            })
        );
        for bad in [
            "",
            "320",
            "x240",
            "0x10",
            "10x0",
            "-1x5",
            "axb",
            "100000x100000",
            "320x240x2",
        ] {
            assert!(bad.parse::<Resolution>().is_err(), "`{bad}` accepted");
        }
    }

    #[test]
    fn si_prefixes() {
        assert_eq!(si(1.5e6), "1.50 M");
        assert_eq!(si(999.0), "999.00 ");
        assert_eq!(si(f64::NAN), "-");
    }
}
