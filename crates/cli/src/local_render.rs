//! Local rendering shared by `cvfarm render` and `cvfarm bench`: a fixed sample count or a
//! time budget, any estimator.
//!
//! - **Fixed spp** ([`render_spp`]): one call of the renderer's image entry point.
//! - **Time budget** ([`render_budget`]): single-pass estimators (`path`, `ocv`) render sample
//!   batches `[s0, s0 + b)` over all tiles until the budget is spent; the batch sizes grow
//!   (1, then up to twice the previous, capped by the time left at the measured cost per
//!   sample), and batch films are merged in sample order, so a given batch sequence always
//!   gives the same image. Estimators with phases (train + render) cannot add samples after
//!   their solve: complete pilot renders at 1, 2, 4, … spp fit a fixed + per-spp cost, then
//!   one render with the spp that fits the rest of the budget (the image is that render's;
//!   `seconds` counts all of them).

use std::time::Instant;

use anyhow::{Context, Result};
use rayon::prelude::*;
use render::Film;
use render::integrator::{RenderScene, RenderSettings};
use render::tile::{RenderOptions, RenderStats, TileRect, render_tile_counted};

/// A finished local render.
#[derive(Debug)]
pub struct Rendered {
    /// The accumulated film.
    pub film: Film,
    /// Cost (samples, rays, wall seconds of rendering).
    pub stats: RenderStats,
    /// Samples per pixel actually rendered.
    pub spp: u32,
    /// What the estimator reports (solve statistics, …), if anything.
    pub report: Option<serde_json::Value>,
    /// Extra EXR layers the estimator provides (CV term, cell id, …).
    pub extra_layers: Vec<imageio::RgbLayer>,
}

/// Renders `st.spp` samples per pixel with `st.estimator`.
pub fn render_spp(
    rs: &RenderScene,
    st: &RenderSettings,
    options: &RenderOptions,
    progress: &(dyn Fn(u64, u64) + Sync),
) -> Result<Rendered> {
    let (film, stats, report) =
        render::integrator::cv::render_estimator_image(rs, st, options, progress)?;
    let extra_layers = report
        .layers
        .iter()
        .map(|l| imageio::RgbLayer {
            name: l.name.to_string(),
            data: l.data.clone(),
        })
        .collect();
    Ok(Rendered {
        film,
        stats,
        spp: st.spp,
        report: serde_json::to_value(&report).ok(),
        extra_layers,
    })
}

/// Renders until `budget` seconds are spent (see the module docs). `progress(elapsed_ms,
/// budget_ms)` is called after each batch.
pub fn render_budget(
    rs: &RenderScene,
    st: &RenderSettings,
    options: &RenderOptions,
    budget: f64,
    progress: &(dyn Fn(u64, u64) + Sync),
) -> Result<Rendered> {
    let start = Instant::now();
    let budget_ms = (budget * 1e3) as u64;
    if st.estimator.has_phases() {
        // Pilots at 1, 2, 4, … spp (each a complete render) until one takes a tenth of the
        // budget; the last two fit `t(s) = fixed + s · per_spp` (phases have fixed costs:
        // surrogate, solve); then one render with the spp that fits the rest of the budget.
        let mut prev: Option<(u32, f64)> = None;
        let mut spp = 1u32;
        let mut last = render_spp(rs, &RenderSettings { spp, ..*st }, options, &|_, _| {})?;
        loop {
            let t = last.stats.seconds;
            let left = budget - start.elapsed().as_secs_f64();
            if t >= budget / 10.0 || 2.0 * t > left || spp >= 1 << 20 {
                let per_spp = match prev {
                    Some((s0, t0)) if t > t0 => (t - t0) / f64::from(spp - s0),
                    _ => t / f64::from(spp),
                };
                let fixed = (t - per_spp * f64::from(spp)).max(0.0);
                let fits = ((left - fixed) / per_spp.max(1e-9)).floor();
                if fits > f64::from(spp) {
                    let s_final = fits.min(f64::from(u32::MAX)) as u32;
                    last = render_spp(
                        rs,
                        &RenderSettings {
                            spp: s_final,
                            ..*st
                        },
                        options,
                        &|_, _| {},
                    )?;
                }
                break;
            }
            prev = Some((spp, t));
            spp *= 2;
            last = render_spp(rs, &RenderSettings { spp, ..*st }, options, &|_, _| {})?;
            progress(start.elapsed().as_millis() as u64, budget_ms);
        }
        let mut r = last;
        progress(start.elapsed().as_millis() as u64, budget_ms);
        r.stats.seconds = start.elapsed().as_secs_f64();
        return Ok(r);
    }
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(options.threads)
        .build()
        .context("creating the thread pool")?;
    let tiles = TileRect::grid(rs.width, rs.height, options.tile_size);
    let mut film = Film::new(rs.width, rs.height);
    // `ocv`'s pilot on the whole pool, once, before the batches (sized by `st.spp`).
    let pilot_rays = pool.install(|| rs.ocv_choice(st)).map_or(0, |c| c.rays);
    let (mut s0, mut batch, mut rays) = (0u32, 1u32, pilot_rays);
    loop {
        let t0 = Instant::now();
        let range = s0..s0.saturating_add(batch);
        let results: Vec<_> = pool.install(|| {
            tiles
                .par_iter()
                .map(|&t| render_tile_counted(rs, st, t, range.clone()))
                .collect()
        });
        for r in results {
            let (tile_film, tile_rays) = r?;
            film.merge(&tile_film);
            rays += tile_rays;
        }
        s0 = range.end;
        progress(start.elapsed().as_millis() as u64, budget_ms);
        let per_spp = t0.elapsed().as_secs_f64() / f64::from(batch);
        let left = budget - start.elapsed().as_secs_f64();
        if left < per_spp || s0 == u32::MAX {
            break;
        }
        let fits = (left / per_spp.max(1e-9))
            .floor()
            .min(f64::from(u32::MAX - s0));
        batch = (fits as u32).clamp(1, batch.saturating_mul(2));
    }
    let stats = RenderStats {
        samples: film.sample_count(),
        rays,
        seconds: start.elapsed().as_secs_f64(),
    };
    Ok(Rendered {
        film,
        stats,
        spp: s0,
        report: None,
        extra_layers: Vec::new(),
    })
}
