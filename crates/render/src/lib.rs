//! CPU path tracer for cvfarm.
//!
//! Data flows one way: a loaded [`scene::Scene`] is prepared once (BVH, lights, materials),
//! then tiles are rendered into f64 films (and, for CV estimators, per-cell moment
//! accumulators). The crate does no I/O: files are read by `scene`, written by `imageio`.
//!
//! # Layout
//! - [`math`]: rays and orthonormal frames.
//! - [`sampler`]: deterministic sampler per (seed, pixel, sample index, dimension).
//! - [`camera`]: Mitsuba-compatible pinhole camera.
//! - [`accel`]: BVH over triangles + analytic spheres (our 8-wide packet BVH for scenes up to
//!   65536 primitives, obvhs CWBVH above); `Hit` records.
//! - [`texture`]: bitmap and checkerboard lookups.
//! - [`bsdf`]: diffuse, conductor, rough conductor, rough plastic (one file each).
//! - [`light`]: area lights (meshes, spheres), env map, constant; light selection.
//! - [`integrator`]: [`RenderScene`] (prepared scene), [`RenderSettings`], the
//!   [`Estimator`] enum and one file per estimator (`path` is the reference integrator).
//! - [`film`]: per-pixel f64 sums, sums of squares, counts and AOVs.
//! - [`tile`]: tiles ([`render_tile`], the farm's unit of work), parallel [`render_image`].
//!
//! # Entry points
//! ```ignore
//! let settings = RenderSettings { spp: 64, seed: 1, ..RenderSettings::from_scene(&scene) };
//! let rs = RenderScene::new(&scene, &settings)?;
//! let (film, stats) = render_image(&rs, &settings, &RenderOptions::default(), &|_, _| {})?;
//! ```
//! - [`chi2`]: χ² goodness-of-fit harness used by the sampling tests.

#![deny(missing_docs)]

pub mod accel;
pub mod bsdf;
pub mod camera;
pub mod chi2;
pub mod film;
pub mod integrator;
pub mod light;
pub mod math;
pub mod sampler;
pub mod texture;
pub mod tile;

pub use film::{Film, FilmLayer, Pixel};
pub use integrator::{Estimator, MisHeuristic, RenderError, RenderScene, RenderSettings};
pub use light::LightSelection;
pub use tile::{RenderOptions, RenderStats, TileRect, render_image, render_tile};
