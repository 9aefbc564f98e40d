//! Tiles: the farm's unit of work, and parallel rendering of a whole image.
//!
//! A task is `(tile rectangle, sample range)`: [`render_tile`] renders samples
//! `samples.start..samples.end` of every pixel of the tile into a [`Film`]. Because the
//! sampler is a pure function of (seed, pixel, sample index, dimension) and each pixel sums its
//! samples in sample-index order, the result does not depend on how the image is cut into
//! tiles or on which thread renders what. Films of different sample ranges of the same pixels
//! must be merged in canonical (ascending sample range) order for bitwise reproducibility.
//!
//! [`render_image`] renders all tiles on a local rayon pool and merges them in row-major tile
//! order; same job + seed ⇒ bitwise-identical film for any tile size and thread count.
//!
//! | option | type | default | meaning |
//! |---|---|---|---|
//! | `tile_size` | u32 | 32 | tile edge in pixels |
//! | `threads` | usize | 0 | worker threads (0 = all cores) |

use std::ops::Range;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Instant;

use rayon::prelude::*;

use crate::film::Film;
use crate::integrator::{Estimator, RenderError, RenderScene, RenderSettings, ocv, path};

/// A rectangle of the image, in pixels.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct TileRect {
    /// Left column.
    pub x0: u32,
    /// Top row.
    pub y0: u32,
    /// Width.
    pub width: u32,
    /// Height.
    pub height: u32,
}

impl TileRect {
    /// The tiles of a `width × height` image with edge `tile_size`, in row-major order
    /// (border tiles are clipped).
    pub fn grid(width: u32, height: u32, tile_size: u32) -> Vec<TileRect> {
        let ts = tile_size.max(1);
        let mut tiles = Vec::new();
        for y0 in (0..height).step_by(ts as usize) {
            for x0 in (0..width).step_by(ts as usize) {
                tiles.push(TileRect {
                    x0,
                    y0,
                    width: ts.min(width - x0),
                    height: ts.min(height - y0),
                });
            }
        }
        tiles
    }

    /// Number of pixels.
    pub fn pixel_count(&self) -> u64 {
        u64::from(self.width) * u64::from(self.height)
    }
}

/// How to run a local render.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RenderOptions {
    /// Tile edge in pixels.
    pub tile_size: u32,
    /// Worker threads (0 = rayon's default, all cores).
    pub threads: usize,
}

impl Default for RenderOptions {
    fn default() -> Self {
        Self {
            tile_size: 32,
            threads: 0,
        }
    }
}

/// What a render cost.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct RenderStats {
    /// Camera samples taken.
    pub samples: u64,
    /// Rays traced (camera, shadow, continuation).
    pub rays: u64,
    /// Wall-clock seconds.
    pub seconds: f64,
}

/// Renders samples `samples` of every pixel of `tile` (see the module docs).
pub fn render_tile(
    rs: &RenderScene,
    st: &RenderSettings,
    tile: TileRect,
    samples: Range<u32>,
) -> Result<Film, RenderError> {
    render_tile_counted(rs, st, tile, samples).map(|(film, _)| film)
}

/// [`render_tile`] that also returns the number of rays traced.
pub fn render_tile_counted(
    rs: &RenderScene,
    st: &RenderSettings,
    tile: TileRect,
    samples: Range<u32>,
) -> Result<(Film, u64), RenderError> {
    let inside = u64::from(tile.x0) + u64::from(tile.width) <= u64::from(rs.width)
        && u64::from(tile.y0) + u64::from(tile.height) <= u64::from(rs.height);
    if !inside {
        return Err(RenderError::TileOutOfBounds {
            x0: tile.x0,
            y0: tile.y0,
            width: tile.width,
            height: tile.height,
            image_width: rs.width,
            image_height: rs.height,
        });
    }
    let mut film = Film::new_rect(tile.x0, tile.y0, tile.width, tile.height);
    let mut rays = 0u64;
    let mut ocv_scratch = match &st.estimator {
        Estimator::Ocv(o) => ocv::Scratch::new(rs, o),
        _ => ocv::Scratch::default(),
    };
    // `ocv`'s pilot choice (made once per job: `RenderScene::ocv_choice`).
    let use_ocv = rs.ocv_choice(st).is_some_and(|c| c.use_ocv);
    for y in tile.y0..tile.y0 + tile.height {
        for x in tile.x0..tile.x0 + tile.width {
            let px = film.pixel_mut(x, y);
            let mut rejected = 0u64;
            for s in samples.clone() {
                let sample = match st.estimator {
                    Estimator::Path => path::sample_pixel(rs, st, x, y, s),
                    Estimator::Ocv(o) if use_ocv => {
                        ocv::sample_pixel(rs, st, &o, &mut ocv_scratch, x, y, s)
                    }
                    Estimator::Ocv(_) => path::sample_pixel(rs, st, x, y, s),
                    // Phased CV estimators need their coefficients (see
                    // `cv::render_estimator_image`); a bare tile renders the baseline.
                    Estimator::Cms(_) | Estimator::PerLightCv(_) | Estimator::OptimalMis(_) => {
                        path::sample_pixel(rs, st, x, y, s)
                    }
                };
                rays += u64::from(sample.rays);
                if sample.radiance.is_finite() {
                    px.add(sample.radiance, sample.albedo, sample.normal);
                } else {
                    // Non-finite samples are rejected and counted, never merged (DESIGN §7);
                    // they still count as taken so the estimator stays unbiased where finite.
                    px.add(glam::Vec3::ZERO, sample.albedo, sample.normal);
                    rejected += 1;
                }
            }
            film.rejected += rejected;
        }
    }
    Ok((film, rays))
}

/// Renders the whole image with `st.spp` samples per pixel on a local pool of
/// `options.threads` threads. `progress(done, total)` is called (from worker threads) after
/// each tile with the number of samples done so far.
pub fn render_image(
    rs: &RenderScene,
    st: &RenderSettings,
    options: &RenderOptions,
    progress: &(dyn Fn(u64, u64) + Sync),
) -> Result<(Film, RenderStats), RenderError> {
    if st.estimator.has_phases() {
        // All phases in-process (surrogate, train, solve, render).
        return crate::integrator::cv::render_estimator_image(rs, st, options, progress)
            .map(|(film, stats, _)| (film, stats));
    }
    let start = Instant::now();
    let tiles = TileRect::grid(rs.width, rs.height, options.tile_size);
    let total = u64::from(rs.width) * u64::from(rs.height) * u64::from(st.spp);
    let done = AtomicU64::new(0);
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(options.threads)
        .build()
        .map_err(|e| RenderError::ThreadPool(e.to_string()))?;
    // `ocv`'s pilot, on the whole pool before the tiles (which then read its choice).
    let pilot_rays = pool.install(|| rs.ocv_choice(st)).map_or(0, |c| c.rays);
    let results: Vec<Result<(Film, u64), RenderError>> = pool.install(|| {
        tiles
            .par_iter()
            .map(|&tile| {
                let r = render_tile_counted(rs, st, tile, 0..st.spp);
                let d = done.fetch_add(tile.pixel_count() * u64::from(st.spp), Ordering::Relaxed)
                    + tile.pixel_count() * u64::from(st.spp);
                progress(d, total);
                r
            })
            .collect()
    });
    let mut film = Film::new(rs.width, rs.height);
    let mut rays = pilot_rays;
    for r in results {
        let (tile_film, tile_rays) = r?;
        film.merge(&tile_film);
        rays += tile_rays;
    }
    let stats = RenderStats {
        samples: film.sample_count(),
        rays,
        seconds: start.elapsed().as_secs_f64(),
    };
    Ok((film, stats))
}
