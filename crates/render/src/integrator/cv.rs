//! Shared machinery of the pdf-based CV estimators `cms`, `per_light_cv` and `optimal_mis`:
//! CV components, the spatial grid, the vertex policy that records and modifies the
//! direct lighting of every path vertex, and the in-process phase driver
//! [`render_estimator_image`].
//!
//! # The vertex integral and its measures
//! At a scattering vertex the direct lighting is one integral over the points `x` the two
//! techniques can produce, estimated with one NEE sample and one BSDF sample combined by the
//! balance heuristic [Hua eq. 6]: `F(x) = f(x)/p(x)` with the effective density
//! `p = p_light + p_bsdf` [Hua eq. 16]. Densities are handled as densities of *points*
//! (area measure on surfaces, solid angle towards the environment), which makes the
//! zero-contribution samples of [Hua §8] exact without extra rays:
//! - an NEE sample behind an occluder is a point the BSDF technique cannot reach:
//!   `p = p_light`, `λ_bsdf = 0` (the shadow ray is traced whenever `p_bsdf > 0`);
//! - a BSDF sample that hits a non-emitter has `λ_light = 0`, `p = p_bsdf`;
//! - a BSDF sample that hits emitter `l` (front side) has `p = p_light(l) + p_bsdf`;
//! - failed samples (the BSDF sampler or the light sampler returned nothing) and delta
//!   lobes are point masses only their own technique produces: `λ/p = 1` for the BSDF
//!   component, `1/S_C` for the cluster `C` of the selected light.
//!
//! Only ratios `λ_k/p` enter, so solid-angle values are used throughout. Components
//! [Hua eq. 18]: one per light cluster `C` (`λ_C = Σ_{l∈C} c_l p_l / S_C`, `S_C = Σ_{l∈C}
//! c_l`, `c_l` the selection pmf; the env map is its own cluster) and, for `cms` and
//! `optimal_mis`, the BSDF (`λ_bsdf = p_bsdf`). The vertex estimate is
//! `β (Σα + Σ_s R_s (F_s − Σ_k α_k λ_k(x_s)/p(x_s)))` [Hua eq. 17, 27] with `β` the
//! prefix throughput and `R_s = 1/q` the Russian-roulette factor of the BSDF sample (a
//! BSDF sample whose path roulette ended is dropped, `R = 0`, which keeps the estimator
//! unbiased).
//!
//! # Base estimator
//! The sample value the fits are trained on and a controlled vertex corrects is
//! `F_s = w_s(x_s) f(x_s)/p_s(x_s)`: with `cms`'s default `base: "balance"` the balance
//! heuristic, `F_s = f/p` [Hua eq. 6]; with `base: "mis"` the **job's heuristic** (`mis`,
//! power by default). The CV correction `Σ_k α_k (1 − Σ_s R_s λ_k(x_s)/p(x_s))` has zero
//! mean for any fixed `α` whatever the base weights, because the samples are one per
//! technique and `p` is their sum: `E[Σ_s λ_k(x_s)/p(x_s)] = ∫ λ_k Σ_s p_s/p = 1`. So the
//! estimator stays unbiased. A vertex that is not controlled (a cell without coefficients,
//! shallower than `min_depth`, a training sample's image contribution) is `path`'s, with the
//! job's heuristic, whatever the base ([`VertexObserver::controls`],
//! [`VertexObserver::adds_to_path`]); choosing by the vertex's cell keeps it unbiased.
//!
//! Training regresses each sample's `F_s` on its `λ_k(x_s)/p(x_s)` (one observation per
//! sample, [Hua eq. 21, 23]). With MIS weights `w_s` summing to one, the per-point sum
//! `Σ_s p_s (F_s − h)² = p (h − f/p)² + const(x)` for any `h = Σ α_k λ_k/p`, so the normal
//! equations have the same expectation for the power and the balance base: the fitted `α`
//! targets `α·λ ≈ f` either way. With the balance base a perfect fit cancels the integrand
//! [Hua eq. 19]; with the power base it leaves the (small) residual `f (w_s/p_s − 1/p)`. The regression minimises the variance of a
//! *random* mixture; the deterministic one-sample-per-technique estimator differs by the
//! spread of the techniques' expected contributions, which the fit also penalises (see
//! `docs/bench/README.md`; the ridge shrinks `α` toward the base where the fit is weak).
//!
//! Cells are grid cells split by the dominant axis and sign of the shading normal
//! ([`NORMAL_BINS`]), so differently oriented surfaces never share coefficients.
//!
//! # Controlled vertices (`min_depth`)
//! `cms` trains and applies the CV only at vertices of depth ≥ `min_depth` (default by the
//! sampler: 1 with Sobol, not at the camera hit; 0 with independent numbers); shallower
//! vertices are `path`'s. The regression measures
//! i.i.d. variance, but `path` samples each pixel with an Owen-scrambled Sobol sequence,
//! whose error at the camera hit (the dimensions stratified per pixel) falls faster than
//! `1/N`; the CV term `α·(1 − Σ_s λ/p)` jumps with visibility and light hits and spoils that
//! stratification, so there the fitted CV lost to `path` at equal samples (many-lights d2
//! 0.74×, veach-mis d5 0.98× with `min_depth` 0; 1.00× / 1.005× with 1; numbers in
//! `docs/bench/README.md`). Deeper vertices use high, poorly stratified sampler dimensions,
//! where the variance the fit sees is the error the image gets.
//!
//! Where the policy would change nothing (the surrogate phase; jobs whose `max_depth`
//! leaves no vertex at `min_depth` or deeper; a render phase without coefficients), tiles
//! are traced with `path` itself, whatever the base: no policy work per vertex and none of
//! the extra rays a CV needs.
//!
//! # Phases and determinism
//! surrogate (cms with `relative`) → train → solve → render, sample indices
//! `[0, s)`, `[s, s+T)`, `[s+T, spp)` of the job's sampler, all kept in the image.
//! Training tiles are fixed ([`TRAIN_TILE`] pixels, independent of
//! [`RenderOptions::tile_size`]) and their cell accumulators are merged in row-major tile
//! order (a tile's own table: its bands' samples added in band order, [`BAND_ROWS`], first
//! for its [`TRAIN_PROBE_SPP`] probe samples, then for the rest unless the probe stopped it);
//! every pixel sums its samples in index order; so the same job and seed give
//! bitwise-identical images for any thread count and tile size.
//!
//! # Grid
//! `grid_resolution = [nx, ny, nz]` regular cells over the scene bounds; the adaptive
//! default gives the longest axis `max(width, height)/16` cells (clamped to
//! 8…[`ADAPTIVE_GRID_MAX_AXIS`]) and the others proportionally ([`adaptive_grid`]).
//! `cms` subdivides each cell `grid_levels` times (default 2, one more per doubling of
//! `max(width, height)/16` past the cap: [`PhasedEstimator::for_image`]) for the camera's hits on glossy
//! surfaces, 2×2×2 per level; every other vertex stays in the undivided cell, and the table
//! solve fits each subdivided cell against its ancestors ([`Grid`],
//! [`estimators::solve::SolvePolicy::levels`]).

use std::collections::{BTreeMap, HashMap};
use std::ops::Range;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Instant;

use estimators::cell::{
    CellAccumulator, ColorMode, ComponentLayout, CvSample, Technique, prefetch_lines,
    prefetch_read, training_weight,
};
use estimators::composite::{combine_phases, controlled_scale, phase_weight};
use estimators::perlight::MeanContributionAccumulator;
use estimators::solve::{CellCoefficients, CellHalves, SolvePolicy, SolveStatus};
pub use estimators::spec::{
    ADAPTIVE_GRID_MAX_AXIS, CvBase, CvColor, MAX_GRID_CELLS, MAX_GRID_INDICES, MAX_GRID_LEVELS,
    PhaseSamples, PhasedEstimator, TRAIN_TILE, adaptive_grid, grid_fits,
};
use estimators::surrogate::{PixelMoments, surrogate_image};
use estimators::table::AccumulatorTable;
use glam::{Vec2, Vec3, Vec3A};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::{Estimator, RenderError, RenderScene, RenderSettings, VertexObserver, VertexRecord};
use crate::film::{Film, FilmLayer, Pixel};
use crate::light::Lights;
use crate::sampler::Sampler;
use crate::tile::{RenderOptions, RenderStats, TileRect};

/// Each grid cell is split by the dominant axis and sign of the shading normal, so that
/// surfaces of different orientation (floor vs. plate vs. wall: incompatible integrals
/// [Hua §4.2]) never share coefficients.
pub const NORMAL_BINS: u32 = estimators::spec::NORMAL_BINS;

/// Dominant axis and sign of `n`: `0..6` (ties go to the lower axis; a NaN component loses
/// every comparison).
///
/// Branch-free: the dominant axis of the surfaces a path meets is random, and the `if`
/// chain this replaces mispredicted often enough that computing the cell of every vertex
/// cost ≈ 6 % of a render phase's time (many-lights d5, `cv_overhead`). The sign is the
/// axis's bit of one vector comparison (`n < 0` per lane, so `-0.0` and NaN count as
/// positive), not a component picked by index (a store and a reload per vertex).
#[inline]
fn normal_bin(n: Vec3) -> u32 {
    let n = Vec3A::from(n);
    let a = n.abs();
    let x_wins = (a.x >= a.y) & (a.x >= a.z);
    // NaN comparisons are false: as in the `if` chain, a NaN makes `z` the axis.
    let y_over_z = a.y >= a.z;
    let axis = u32::from(!x_wins) * (1 + u32::from(!y_over_z));
    let negative = n.cmplt(Vec3A::ZERO).bitmask();
    2 * axis + ((negative >> axis) & 1)
}

/// Seconds spent per phase.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct PhaseTimings {
    /// Surrogate render + denoise.
    pub surrogate: f64,
    /// Training render with accumulation, and the tiles' merges (made as the tiles finish).
    pub train: f64,
    /// Solve of all cells.
    pub solve: f64,
    /// Render with the CV applied.
    pub render: f64,
}

/// What an estimator run did (serialisable; the CLI writes it into its stats).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct EstimatorReport {
    /// `estimator.kind`.
    pub estimator: String,
    /// Phase wall-clock seconds.
    pub phases: PhaseTimings,
    /// Samples per pixel per phase.
    pub surrogate_spp: u32,
    /// Training samples per pixel.
    pub training_spp: u32,
    /// Render-phase samples per pixel.
    pub render_spp: u32,
    /// Grid resolution of the finest cells (`[0, 0, 0]` when cells are pixels or no CV).
    pub grid_resolution: [u32; 3],
    /// Subdivisions of the undivided grid cells fitted hierarchically (`grid_levels`).
    #[serde(default)]
    pub grid_levels: u32,
    /// Cells that received training data.
    pub cells: u64,
    /// Cells whose system was solved.
    pub cells_solved: u64,
    /// Cells that fell back to the plain estimator, by reason.
    pub cells_fallback: BTreeMap<String, u64>,
    /// Training samples rejected (non-finite).
    pub rejected_training_samples: u64,
    /// Training tiles, and of them those that stopped recording after their first
    /// [`TRAIN_PROBE_SPP`] samples per pixel ([`TrainTile::stopped`]).
    pub training_tiles: u32,
    /// See [`Self::training_tiles`].
    pub training_tiles_stopped: u32,
    /// Training tiles whose fits failed the split-half check of `optimal_mis`
    /// ([`TrainTile::dropped`]): their pixels were rendered as `path`.
    pub training_tiles_dropped: u32,
    /// Predicted fraction of the image's per-sample variance the fits remove
    /// ([`estimators::table::predicted_image_gain`]); `null` when not computed. Below the
    /// job's `min_image_gain` every cell falls back (`LowImageGain`).
    pub predicted_image_gain: Option<f64>,
    /// Predicted fraction of the controlled vertices' variance the fits remove
    /// ([`estimators::table::predicted_fit_gain`]); `null` when not computed. Below the
    /// job's `min_fit_gain` every cell falls back (`LowFitGain`).
    pub predicted_fit_gain: Option<f64>,
    /// The fit gain held out: each cell's two halves fitted apart, each fit judged on the
    /// other half ([`estimators::table::SolvedTable::held_out_gain`]); `null` when not
    /// computed (`cms` and `per_light_cv` only).
    pub predicted_held_out_gain: Option<f64>,
    /// The share of the fits' in-sample gain that the held-out check keeps
    /// ([`estimators::table::SolvedTable::held_out_share`]); `null` when not computed. Below
    /// the job's `min_held_out_share`, with a held-out gain below `min_fit_gain` (for
    /// `per_light_cv` whatever the gain), every cell falls back (`Overfitted`).
    pub predicted_held_out_share: Option<f64>,
    /// Emitters of the scene.
    pub lights: u32,
    /// Partitioned CV components (lights or light clusters, env included).
    pub light_components: u32,
    /// Overlapping CV components (BSDF).
    pub overlapping_components: u32,
    /// Techniques simulated (see [`RenderScene::techniques`]) and CV components built.
    pub effects: Vec<String>,
    /// CV-specific seconds outside the sample loops (denoise + merge + solve).
    pub cv_overhead_seconds: f64,
    /// Weight of the samples rendered without the CV (surrogate and training phases) in the
    /// image, the rest the render phase's ([`estimators::composite::phase_weight`]); `null`
    /// when the phases were merged plainly (no cell controlled, or too few samples).
    pub uncontrolled_weight: Option<f64>,
    /// Extra EXR layers: `cv_term` (per-pixel CV correction in the image: the render phase's
    /// mean of controlled − plain times its weight, so `beauty − cv_term` is the same
    /// combination of the plain estimates from the same samples) and `cell` (cell id of
    /// the camera hit of the pixel's first render-phase sample that found one, −1 for
    /// none). Not serialised.
    #[serde(skip)]
    pub layers: Vec<FilmLayer>,
}

/// CV components of the lights: light → partition (cluster) and `1/S_C` per partition.
#[derive(Clone, Debug, PartialEq)]
pub struct Components {
    partition_of: Vec<u32>,
    inv_sel_sum: Vec<f64>,
}

impl Components {
    /// One partition per light, or at most `max_components` clusters by spatial proximity
    /// (recursive median splits of representative light points; the env light is its own
    /// cluster).
    pub fn new(lights: &Lights, max_components: u32, bounds: (Vec3, Vec3)) -> Self {
        let n = lights.len();
        let max = max_components.max(1) as usize;
        let mut partition_of: Vec<u32> = (0..n as u32).collect();
        if n > max {
            let env = lights.env_light();
            let area: Vec<u32> = (0..n as u32).filter(|&l| Some(l) != env).collect();
            let mut next = 0u32;
            if let Some(e) = env {
                partition_of[e as usize] = 0;
                next = 1;
            }
            let k = (max - usize::from(env.is_some())).max(1);
            let pts: Vec<(u32, Vec3)> = area
                .iter()
                .map(|&l| (l, representative_point(lights, l, bounds)))
                .collect();
            let mut clusters = Vec::new();
            split_clusters(pts, k, &mut clusters);
            for c in clusters {
                for l in c {
                    partition_of[l as usize] = next;
                }
                next += 1;
            }
        }
        let parts = partition_of.iter().map(|&p| p + 1).max().unwrap_or(0) as usize;
        let mut sel = vec![0.0f64; parts];
        for (l, &p) in partition_of.iter().enumerate() {
            sel[p as usize] += f64::from(lights.selection_pmf(l as u32));
        }
        let inv_sel_sum = sel
            .iter()
            .map(|&s| if s > 0.0 { 1.0 / s } else { 0.0 })
            .collect();
        Self {
            partition_of,
            inv_sel_sum,
        }
    }

    /// Number of partitions `P`.
    pub fn partitions(&self) -> u32 {
        self.inv_sel_sum.len() as u32
    }

    /// `(partition, 1/S_C)` of `light`.
    #[inline]
    pub fn of(&self, light: u32) -> Option<(u32, f64)> {
        let p = *self.partition_of.get(light as usize)?;
        Some((p, self.inv_sel_sum[p as usize]))
    }
}

/// A point on light `l` (for clustering), sampled towards the scene centre or a corner.
fn representative_point(lights: &Lights, l: u32, (lo, hi): (Vec3, Vec3)) -> Vec3 {
    let centre = if lo.cmple(hi).all() {
        0.5 * (lo + hi)
    } else {
        Vec3::ZERO
    };
    let probes = [
        centre,
        lo,
        hi,
        Vec3::new(lo.x, hi.y, lo.z),
        Vec3::new(hi.x, lo.y, hi.z),
    ];
    for p in probes {
        if let Some(s) = lights.sample_light(l, p, Vec2::splat(0.5))
            && s.dist.is_finite()
        {
            return p + s.wi * s.dist;
        }
    }
    centre
}

/// Splits `pts` into `k` spatially compact clusters (median split on the longest axis).
fn split_clusters(mut pts: Vec<(u32, Vec3)>, k: usize, out: &mut Vec<Vec<u32>>) {
    if pts.is_empty() {
        return;
    }
    if k <= 1 || pts.len() <= 1 {
        out.push(pts.into_iter().map(|p| p.0).collect());
        return;
    }
    let (mut lo, mut hi) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
    for (_, p) in &pts {
        lo = lo.min(*p);
        hi = hi.max(*p);
    }
    let ext = hi - lo;
    let axis = if ext.x >= ext.y && ext.x >= ext.z {
        0
    } else if ext.y >= ext.z {
        1
    } else {
        2
    };
    pts.sort_by(|a, b| a.1[axis].total_cmp(&b.1[axis]).then(a.0.cmp(&b.0)));
    let k1 = k / 2;
    let cut = (pts.len() * k1 / k).clamp(1, pts.len() - 1);
    let right = pts.split_off(cut);
    split_clusters(pts, k1, out);
    split_clusters(right, k - k1, out);
}

/// Children of a subdivided cell ([`estimators::spec::CELL_CHILDREN`]): octants `0..8`, then
/// [`OTHER_CHILD`].
const CHILDREN: u32 = estimators::spec::CELL_CHILDREN as u32;
/// The child of a subdivided cell that holds its vertices other than glossy camera hits.
const OTHER_CHILD: u32 = 8;

/// A regular grid over the scene bounds, its cells subdivided `levels` times for the
/// camera's hits on glossy surfaces (2×2×2 children per level, and a ninth child for the
/// other vertices: [`estimators::spec::CELL_CHILDREN`]).
///
/// A cell index is `coarse · 9^levels + sub`, `coarse` the row-major index of the
/// undivided cell and `sub` the path from it down to the finest cell in base-9 digits (the
/// coarsest in the highest digit): octants `0..8` for a glossy camera hit
/// ([`Self::cell`]), and for any other vertex digit 8 then zeros
/// ([`Self::undivided_cell`]). So the parent of index `i` is `i / 9` at every level, and an
/// undivided cell's index is its vertices' common ancestor: what lets the table solve fit
/// each cell against its ancestors without knowing the grid
/// ([`estimators::solve::SolvePolicy::levels`]). Glossy camera hits are subdivided because
/// the image resolves them at pixel scale and their direct light varies at that scale (a
/// highlight across a cell: veach-mis d2 1.26× → 1.75× `path` at equal spp with 2 levels);
/// a diffuse surface's varies slowly, and a deeper vertex's reaches the image averaged over
/// its path's footprint, so their cells stay few and well sampled (subdividing every
/// vertex's cell cost colour-lamp d5 +40 % time for +2 % gain, many-lights +75 % for none;
/// `docs/bench/README.md`). With `levels` 0 the index is the plain row-major one for all.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Grid {
    /// The padded bounds' low corner and the finest cells per unit length, in SIMD lanes.
    lo: Vec3A,
    scale: Vec3A,
    /// Finest cells per axis (`coarse << levels`).
    res: [u32; 3],
    /// Undivided cells per axis.
    coarse: [u32; 3],
    levels: u32,
    /// `res - 1` per axis (exact in `f32`: at most 2^20 cells).
    last: Vec3A,
    /// `9^levels`: an undivided cell's first index is its row-major index times this.
    undivided_stride: u32,
    /// Offset of the other vertices' child in an undivided cell's indices: digit 8, then
    /// `levels − 1` zeros (0 with `levels` 0).
    other_offset: u32,
    /// `scale / 2^levels` (exact: a power of two) and `coarse − 1` per axis: the undivided
    /// cell of every deeper vertex ([`Self::undivided_cell`]).
    coarse_scale: Vec3A,
    coarse_last: Vec3A,
    /// Row-major strides of the undivided cells, `[1, cx, cx·cy]` (exact in `f32`: at most
    /// 2^20 cells).
    coarse_strides: Vec3A,
}

impl Grid {
    /// A grid of `res` cells (or the adaptive default for an image of `width × height`),
    /// each subdivided `levels` times, within [`grid_fits`]'s limits (the adaptive default
    /// is within them for any `levels` up to [`MAX_GRID_LEVELS`]).
    pub fn new(
        bounds: (Vec3, Vec3),
        res: Option<[u32; 3]>,
        levels: u32,
        width: u32,
        height: u32,
    ) -> Result<Self, RenderError> {
        let (lo, hi) = bounds;
        let valid = lo.is_finite() && hi.is_finite() && lo.cmple(hi).all();
        let (lo, hi) = if valid {
            (lo, hi)
        } else {
            (Vec3::ZERO, Vec3::ONE)
        };
        let ext = (hi - lo).max(Vec3::splat(1e-6));
        let pad = ext * 1e-4;
        let (lo, ext) = (lo - pad, ext + 2.0 * pad);
        let res = match res {
            Some(r) => {
                if r.contains(&0) {
                    return Err(RenderError::InvalidSetting {
                        field: "grid_resolution",
                        reason: "every axis needs at least one cell",
                    });
                }
                r
            }
            None => {
                // At most `ADAPTIVE_GRID_MAX_AXIS` (+ 1 by rounding) cells per axis: within the
                // limits with any valid `levels` (asserted where the cap is defined).
                let longest = ext.max_element();
                let n = adaptive_grid(width, height).0 as f32;
                let r = |e: f32| ((n * e / longest).ceil() as u32).max(1);
                [r(ext.x), r(ext.y), r(ext.z)]
            }
        };
        if !grid_fits(res, levels) {
            return Err(RenderError::InvalidSetting {
                field: "grid_resolution",
                reason: "more than 2^20 cells, or 2^28 cell indices after grid_levels",
            });
        }
        let coarse = res;
        let res = res.map(|r| r << levels);
        let resf = Vec3A::new(res[0] as f32, res[1] as f32, res[2] as f32);
        let scale = resf / Vec3A::from(ext);
        let coarsef = Vec3A::new(coarse[0] as f32, coarse[1] as f32, coarse[2] as f32);
        Ok(Self {
            lo: lo.into(),
            scale,
            res,
            coarse,
            levels,
            last: resf - Vec3A::ONE,
            coarse_scale: scale / (1u32 << levels) as f32,
            coarse_last: coarsef - Vec3A::ONE,
            coarse_strides: Vec3A::new(1.0, coarsef.x, coarsef.x * coarsef.y),
            undivided_stride: CHILDREN.pow(levels),
            other_offset: match levels {
                0 => 0,
                l => OTHER_CHILD * CHILDREN.pow(l - 1),
            },
        })
    }

    /// Finest cells per axis.
    pub fn resolution(&self) -> [u32; 3] {
        self.res
    }

    /// Subdivisions of the undivided cells.
    pub fn levels(&self) -> u32 {
        self.levels
    }

    /// Cell indices (`0..cells`): undivided cells × `9^levels`.
    pub fn cells(&self) -> usize {
        estimators::spec::finest_grid_cells(self.coarse, self.levels) as usize
    }

    /// Index of the undivided cell containing `p`, as a deeper vertex's cell (digit 8, then
    /// zeros; the plain row-major index with `levels` 0).
    ///
    /// The same index as the finest cell's coordinates shifted by `levels`
    /// ([`Self::undivided_index`]), computed at the undivided resolution in SIMD lanes:
    /// `floor(q / 2^levels) = floor(q) >> levels` for `q ≥ 0`, and the clamp to `coarse − 1`
    /// keeps what clamping to the finest `res − 1` kept. Every deeper vertex looks its cell
    /// up here; the per-axis scalar clamps and conversions this replaces, with the normal
    /// bin's indexed pick, cost 13 M more of 3 611 M instructions (colour-lamp 96² d5,
    /// 49 spp, `cms`).
    #[inline]
    pub fn undivided_cell(&self, p: Vec3) -> u32 {
        let q = (Vec3A::from(p) - self.lo) * self.coarse_scale;
        // NaN and +∞ to 0, as [`Self::coords`].
        let q = Vec3A::select(q.cmplt(Vec3A::INFINITY), q, Vec3A::ZERO);
        let c = q.max(Vec3A::ZERO).min(self.coarse_last).floor();
        // Integers below 2^20 and their row-major sum: exact in `f32`.
        let index = c.dot(self.coarse_strides) as u32;
        // `(index · 9 + 8) · 9^(levels−1)`, with both factors precomputed (the power was a
        // loop per vertex).
        index * self.undivided_stride + self.other_offset
    }

    /// Row-major index of the undivided cell of finest cell coordinates `c`.
    #[inline]
    fn undivided_index(&self, c: glam::UVec3) -> u32 {
        let k = c >> self.levels;
        k.x + self.coarse[0] * (k.y + self.coarse[1] * k.z)
    }

    /// Index of the finest cell containing `p` (clamped to the grid), as a camera hit's
    /// cell.
    #[inline]
    pub fn cell(&self, p: Vec3) -> u32 {
        let c = self.coords(p);
        let mut index = self.undivided_index(c);
        for l in (0..self.levels).rev() {
            let b = (c >> l) & 1;
            index = index * CHILDREN + (b.x | (b.y << 1) | (b.z << 2));
        }
        index
    }

    /// The finest cell coordinates of `p` (clamped to the grid).
    #[inline]
    fn coords(&self, p: Vec3) -> glam::UVec3 {
        let q = (Vec3A::from(p) - self.lo) * self.scale;
        // NaN and +∞ go to cell 0, negatives to 0, the rest is clamped to the last cell: in
        // the float domain, lane-parallel and without branches (the cast then sees only
        // `0..=res-1`).
        let q = Vec3A::select(q.cmplt(Vec3A::INFINITY), q, Vec3A::ZERO);
        q.max(Vec3A::ZERO).min(self.last).as_uvec3()
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Kind {
    Cms,
    PerLight,
    OptimalMis,
}

/// Everything the vertex policy needs, fixed for a job.
struct CvContext<'a> {
    rs: &'a RenderScene,
    st: RenderSettings,
    kind: Kind,
    comps: Components,
    grid: Grid,
    layout: ComponentLayout,
    color: ColorMode,
    /// MIS heuristic of the base values `F_s` (trained on, and corrected at controlled
    /// vertices); uncontrolled vertices use the job's.
    base: super::MisHeuristic,
    /// Vertices shallower than this are not controlled (`cms`'s `min_depth`).
    min_depth: u32,
    /// Whether any vertex is controlled ([`PhasedEstimator::controls_any_vertex`]).
    controls: bool,
    /// Records a training band logs before adding them to its own cells
    /// ([`TRAIN_LOG_MAX`]; smaller in tests, to exercise the spill).
    train_log_max: usize,
    /// `optimal_mis`'s `min_split_gain` (`None`: no check; always `None` for the other kinds).
    min_split_gain: Option<f64>,
    /// Whether training records each cell's halves apart (the job's
    /// [`SolvePolicy::halves`]): sample `s` of cell `c` under key `2c + s mod 2`.
    halves: bool,
}

impl CvContext<'_> {
    /// See [`CvJob::controls_any_vertex`].
    fn controls_any_vertex(&self) -> bool {
        self.controls
    }
}

/// Solved coefficients indexed by cell (grid cell or pixel); built by
/// [`CvJob::coefficient_table`].
///
/// The render phase reads one row per controlled vertex, at a random cell and light, so the
/// table is laid out for cache misses rather than for generality: per slot one contiguous
/// row of `bfloat16` coefficients `[α_bsdf, α_partition 0, …, α_partition P−1]` (three
/// channels each; half the bytes of `f32`, so a many-light table stays in the core's cache
/// more often), and apart from the rows, in a small dense array, `Σα` as an `f32` hi/lo pair.
/// The coefficients are rounded to `bfloat16` *before* `Σα` is summed (in `f64`, stored as
/// the hi/lo pair, exact to ~2⁻⁴⁸ relative), so the added `Σα` is the sum of exactly the `α`
/// whose terms are subtracted and the estimator stays unbiased [Hua eq. 17] — any fixed `α`
/// does; the rounding only moves each `α` by at most 2⁻⁸ relative, which adds at most
/// 2⁻¹⁶ (15 ppm) of the CV term's own variance.
#[derive(Debug)]
pub struct CoefficientTable {
    slot: SlotMap,
    /// Per slot: the coefficients (the general route of [`Self::term`]; the render phase reads
    /// the rows where there are any).
    coeffs: Vec<CellCoefficients>,
    /// Per slot `stride` `bfloat16` bit patterns (see the type docs) when the rows fit
    /// ([`DENSE_ROW_MAX`], [`DENSE_TOTAL_MAX`]), else empty (`stride = 0`) and the terms come
    /// from [`CellCoefficients::cv_term`]'s binary search in `f64`.
    rows: Vec<u16>,
    /// Per slot (with rows): `Σα` per channel as `f32` hi and lo parts.
    sums: Vec<[f32; 6]>,
    stride: usize,
}

/// Entries of a row before the partition coefficients: `α_bsdf`.
const ROW_HEAD: usize = 3;
/// Largest dense coefficient row (components per cell) of a [`CoefficientTable`]: the
/// default 1 024 light clusters and more fit (a row of 1 025 components is 6 KiB; the total
/// is bounded by [`DENSE_TOTAL_MAX`]). With 1 024 clusters the binary search of the sparse
/// coefficients cost +30 % render time over `path`, the rows +9 % (10 080 triangle lights,
/// 384×256, depth 2).
const DENSE_ROW_MAX: usize = 4097;
/// Largest number of row entries of a [`CoefficientTable`] (48 MiB); above it (e.g.
/// `optimal_mis` on a large image with many lights) terms come from the sparse coefficients.
const DENSE_TOTAL_MAX: usize = 24 << 20;

/// `x` rounded to the nearest `bfloat16` (ties to even), as its bit pattern; a finite `x`
/// whose rounding would overflow is truncated toward zero instead (stays finite).
#[inline]
fn to_bf16(x: f32) -> u16 {
    let bits = x.to_bits();
    let rounded = bits.wrapping_add(0x7fff + ((bits >> 16) & 1)) >> 16;
    if x.is_finite() && !from_bf16(rounded as u16).is_finite() {
        (bits >> 16) as u16
    } else {
        rounded as u16
    }
}

/// The `f32` value of a `bfloat16` bit pattern (exact).
#[inline]
fn from_bf16(b: u16) -> f32 {
    f32::from_bits(u32::from(b) << 16)
}

/// Cell key → slot of a [`CoefficientTable`]: open addressing with linear probing over
/// `2^bits ≥ 2·len` packed entries (`key << 32 | slot`, [`SlotMap::EMPTY`] free), so the
/// table has the size of the cells with coefficients, not of the key range (a subdivided
/// grid's keys span `9^levels` times the undivided cells: a dense slot array was 22 MB for
/// veach-mis, allocated and zeroed per render phase, 0.6 % of its CPU time in page clearing;
/// the render times of an A/B on one thread show no difference through this VM's noise).
#[derive(Clone, Debug)]
struct SlotMap {
    entries: Vec<u64>,
    shift: u32,
}

impl SlotMap {
    const EMPTY: u64 = u64::MAX;

    /// A map with room for `len` keys.
    fn with_capacity(len: usize) -> Self {
        let bits = (2 * len.max(8)).next_power_of_two().trailing_zeros();
        Self {
            entries: vec![Self::EMPTY; 1 << bits],
            shift: 32 - bits,
        }
    }

    #[inline]
    fn home(&self, key: u32) -> usize {
        (key.wrapping_mul(0x9E37_79B1) >> self.shift) as usize
    }

    /// A map of one key.
    #[cfg(test)]
    fn one(key: u32, slot: u32) -> Self {
        let mut m = Self::with_capacity(1);
        m.insert(key, slot);
        m
    }

    /// Maps `key` to `slot` (`key` not yet present; at most the capacity's keys).
    fn insert(&mut self, key: u32, slot: u32) {
        let mask = self.entries.len() - 1;
        let mut i = self.home(key);
        while self.entries[i] != Self::EMPTY {
            i = (i + 1) & mask;
        }
        self.entries[i] = (u64::from(key) << 32) | u64::from(slot);
    }

    #[inline]
    fn get(&self, key: u32) -> Option<u32> {
        let mask = self.entries.len() - 1;
        let mut i = self.home(key);
        loop {
            let e = self.entries[i];
            if e == Self::EMPTY {
                return None;
            }
            if (e >> 32) as u32 == key {
                return Some(e as u32);
            }
            i = (i + 1) & mask;
        }
    }
}

impl CoefficientTable {
    /// Slot of `cell`, `None` for a cell without coefficients (`α ≡ 0`).
    #[inline]
    fn get(&self, cell: u32) -> Option<usize> {
        self.slot.get(cell).map(|s| s as usize)
    }

    fn push(&mut self, co: &CellCoefficients) {
        if self.stride > 0 {
            let start = self.rows.len();
            self.rows.resize(start + self.stride, 0);
            let row = &mut self.rows[start..];
            let mut sum = [0.0f64; 3];
            let mut put = |dst: &mut [u16], a: [f64; 3]| {
                for c in 0..3 {
                    dst[c] = to_bf16(a[c] as f32);
                    sum[c] += f64::from(from_bf16(dst[c]));
                }
            };
            put(&mut row[0..3], co.alpha_overlapping(0));
            for (id, a) in co.partitions() {
                let at = ROW_HEAD + 3 * id as usize;
                if let Some(d) = row.get_mut(at..at + 3) {
                    put(d, a);
                }
            }
            let mut head = [0.0f32; 6];
            for c in 0..3 {
                let hi = sum[c] as f32;
                head[c] = hi;
                head[3 + c] = (sum[c] - f64::from(hi)) as f32;
            }
            self.sums.push(head);
        }
        self.coeffs.push(co.clone());
    }

    /// Starts loading what a controlled vertex in `slot` reads first: its row's head
    /// (`α_bsdf`) and its `Σα` (a hint; a no-op without rows). Many-light rows (≈ 400 bytes
    /// each, more than fits in L2 over the table) missed the cache here.
    #[inline(always)]
    fn prefetch_head(&self, slot: usize) {
        if let Some(h) = self.rows.get(slot * self.stride) {
            prefetch_read(h);
        }
        if let Some(s) = self.sums.get(slot) {
            prefetch_read(s);
        }
    }

    /// Starts loading partition `c`'s `α` in `slot`'s row (a hint; a no-op without rows).
    #[inline(always)]
    fn prefetch_partition(&self, slot: usize, c: u32) {
        if self.stride != 0
            && let Some(a) = self
                .rows
                .get(slot * self.stride + ROW_HEAD + 3 * c as usize)
        {
            prefetch_read(a);
        }
    }

    /// `Σ_k α_k` of slot `slot` from its coefficients (the general route, with [`Self::term`]).
    #[inline]
    fn alpha_sum(&self, slot: usize) -> [f64; 3] {
        self.coeffs[slot].alpha_sum()
    }

    /// Slot `slot`'s dense row and its `Σα` (`f32` hi and lo parts per channel); `None`
    /// without rows (`stride = 0`).
    #[inline]
    fn dense(&self, slot: usize) -> Option<(&[u16], &[f32; 6])> {
        if self.stride == 0 {
            return None;
        }
        let row = self
            .rows
            .get(slot * self.stride..(slot + 1) * self.stride)?;
        Some((row, self.sums.get(slot)?))
    }

    /// `Σ_k α_k λ_k(x)/p(x)` of one sample (the BSDF component only with `bsdf`), from the
    /// cell's coefficients in `f64` ([`CellCoefficients::cv_term`]): the general route of a
    /// controlled vertex (a table without dense rows); [`Policy::apply_dense`] reads the rows.
    #[inline]
    fn term(&self, slot: usize, s: &TechSample, bsdf: bool) -> [f64; 3] {
        let lb = [s.lambda_bsdf];
        self.coeffs[slot].cv_term(&s.cv(if bsdf { &lb } else { &[] }))
    }
}

/// A cell's training accumulator.
// `Moments` is the common variant (every estimator but `per_light_cv`) and is added to on
// every training sample: boxing it would put a pointer chase on that path to save memory only
// in `per_light_cv` jobs.
#[allow(clippy::large_enum_variant)]
#[derive(Clone, Debug)]
enum CellAcc {
    Moments(CellAccumulator),
    Mean(MeanContributionAccumulator),
}

/// Multiplicative hash of `u32` cell keys (the std SipHash costs more than an accumulator
/// update on the per-vertex path).
#[derive(Clone, Copy, Default)]
struct KeyHasher(u64);

impl std::hash::Hasher for KeyHasher {
    #[inline]
    fn finish(&self) -> u64 {
        self.0
    }
    #[inline]
    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.0 = (self.0.rotate_left(8) ^ u64::from(b)).wrapping_mul(0x9E37_79B9_7F4A_7C15);
        }
    }
    #[inline]
    fn write_u32(&mut self, k: u32) {
        self.0 = u64::from(k).wrapping_mul(0x9E37_79B9_7F4A_7C15);
    }
}

type KeyMap = HashMap<u32, usize, std::hash::BuildHasherDefault<KeyHasher>>;

/// One training sample of a moments accumulator: [`CellAccumulator::add_from`]'s arguments
/// and the cell (64 bytes). A `per_light_cv` vertex uses it for
/// [`MeanContributionAccumulator::record`]'s: `weight`, `value`, the selected light in
/// `partition` and its `1/c` in `lambda_partition`.
#[derive(Clone, Copy, Debug)]
struct TrainRecord {
    key: u32,
    /// Partition index ([`NO_PARTITION`] for none) in the low 31 bits, and
    /// [`BSDF_TECHNIQUE`] set when the BSDF sample drew it (else NEE).
    partition: u32,
    weight: f64,
    value: [f64; 3],
    pdf: f64,
    lambda_partition: f64,
    lambda_bsdf: f64,
}

/// [`TrainRecord::partition`] of a sample in no partition.
const NO_PARTITION: u32 = u32::MAX >> 1;
/// [`TrainRecord::partition`]'s technique bit.
const BSDF_TECHNIQUE: u32 = 1 << 31;

/// Records a band logs at most before adding them to its own cells (64 MiB; a default job's
/// band logs ≈ 32 000). The spill points depend only on the record count, so the
/// sums stay the same for any thread count.
const TRAIN_LOG_MAX: usize = 1 << 20;

/// Largest record log (capacity, records: 32 MiB) a thread keeps for its next training band.
const POOLED_LOG_MAX: usize = 1 << 19;

/// Samples whose partition entries [`TileCells::add_records`] prefetches before adding them.
const PREFETCH_BATCH: usize = 32;

thread_local! {
    /// A finished band's record log, emptied, for this thread's next band: a band logs
    /// ≈ 1–2 MiB ([`BAND_ROWS`] rows of a [`TRAIN_TILE`] tile, 16 training spp, ≈ 8 records
    /// per path sample), and a new log grew to its size by reallocations and copies and
    /// faulted in every page (with 16-row bands, many-lights d5, 256², one thread: 0.1 s of
    /// 1.4 s).
    static SPARE_LOG: std::cell::RefCell<Vec<TrainRecord>> = const { std::cell::RefCell::new(Vec::new()) };
}

/// An empty record log, with this thread's spare allocation if it has one.
fn take_log() -> Vec<TrainRecord> {
    SPARE_LOG.with(|l| std::mem::take(&mut *l.borrow_mut()))
}

/// Keeps `log`'s allocation (emptied) for this thread's next band, unless it is larger than
/// [`POOLED_LOG_MAX`] or smaller than the spare the thread already has.
fn return_log(mut log: Vec<TrainRecord>) {
    if log.capacity() > POOLED_LOG_MAX {
        return;
    }
    log.clear();
    SPARE_LOG.with(|l| {
        let mut spare = l.borrow_mut();
        if log.capacity() > spare.capacity() {
            *spare = log;
        }
    });
}

/// Training accumulators of a band or a tile (in first-touch order, or in key order after a
/// probe's round trip through [`cells_table`]: no sum depends on it), and a band's log of
/// samples not yet added.
///
/// A band of a training tile logs its samples and the tile adds the bands' logs in band order
/// to one set of cells ([`InOrderFold`]), rather than each band accumulating its own cells and
/// the tile merging them: a band touches a few thousand cells a few times each, and the
/// per-band cells cost a first touch (allocations, partition inserts) per cell, light and
/// band plus a merge of every band — 18 points of the 70 % a many-lights training sample
/// costs over `path` (`cv_overhead`, one thread: the same count as one band per tile).
#[derive(Clone, Default)]
struct TileCells {
    index: KeyMap,
    cells: Vec<(u32, CellAcc)>,
    last: Option<(u32, usize)>,
    log: Vec<TrainRecord>,
}

impl TileCells {
    /// Logs one moments sample (a full log is first added to the band's own cells).
    #[inline]
    fn record(&mut self, r: TrainRecord, ctx: &CvContext<'_>) {
        if self.log.len() >= ctx.train_log_max {
            let mut log = std::mem::take(&mut self.log);
            self.add_records(&log, ctx);
            // Keep the allocation for the rest of the band.
            log.clear();
            self.log = log;
        }
        self.log.push(r);
    }

    /// Adds logged samples to the cells, in order.
    ///
    /// In batches of [`PREFETCH_BATCH`]: the batch's cells are found (and made, in the
    /// samples' order) and their accumulators prefetched, then their partition entries
    /// ([`CellAccumulator::prefetch_partition`], which reads the accumulator), then the
    /// samples are added in order. The sums are the same; the cache misses overlap. (A
    /// large image's tile meets tens of thousands of cells: reading each accumulator to
    /// find its partition entry missed the cache once a record, one miss after another.)
    fn add_records(&mut self, log: &[TrainRecord], ctx: &CvContext<'_>) {
        let mut slots = [0usize; PREFETCH_BATCH];
        for batch in log.chunks(PREFETCH_BATCH) {
            for (r, slot) in batch.iter().zip(&mut slots) {
                *slot = self.slot(r.key, ctx);
                prefetch_lines(&self.cells[*slot]);
            }
            for (r, &slot) in batch.iter().zip(&slots) {
                let partition = r.partition & !BSDF_TECHNIQUE;
                if partition != NO_PARTITION
                    && let CellAcc::Moments(acc) = &self.cells[slot].1
                {
                    acc.prefetch_partition(partition);
                }
            }
            for (r, &slot) in batch.iter().zip(&slots) {
                self.add_record(slot, r);
            }
        }
    }

    /// Adds one logged sample to the cell in `slot`.
    #[inline]
    fn add_record(&mut self, slot: usize, r: &TrainRecord) {
        let partition = r.partition & !BSDF_TECHNIQUE;
        let selected = || (partition != NO_PARTITION).then_some((partition, r.lambda_partition));
        match &mut self.cells[slot].1 {
            // A `per_light_cv` vertex: its selected light (`lambda_partition` = `1/c`).
            CellAcc::Mean(acc) => {
                acc.record(r.weight, selected(), r.value);
            }
            CellAcc::Moments(acc) => {
                let lb = [r.lambda_bsdf];
                // Built in place (an `Option` made first and copied in was read back across
                // its two stores: a store-forwarding stall per sample).
                let sample = CvSample {
                    pdf: r.pdf,
                    partition: selected(),
                    overlapping: &lb,
                };
                let technique = if r.partition & BSDF_TECHNIQUE != 0 {
                    Technique::Bsdf
                } else {
                    Technique::Light
                };
                let _ = acc.add_from(technique, r.weight, r.value, &sample);
            }
        }
    }

    /// Adds a band: its own cells (what it spilled), then its log, in the band's sample
    /// order.
    fn absorb(&mut self, band: TileCells, ctx: &CvContext<'_>) {
        for (key, acc) in &band.cells {
            // Same job, same layout: a merge cannot fail.
            let _ = match (self.get(*key, ctx), acc) {
                (CellAcc::Moments(a), CellAcc::Moments(b)) => a.merge(b),
                (CellAcc::Mean(a), CellAcc::Mean(b)) => a.merge(b),
                _ => Ok(()),
            };
        }
        self.add_records(&band.log, ctx);
        return_log(band.log);
    }

    /// The cells of a table made by [`cells_table`] (moved back; their order is the
    /// table's, which no sum depends on).
    fn from_table(table: AccumulatorTable) -> Self {
        let cells: Vec<(u32, CellAcc)> = match table {
            AccumulatorTable::Moments(m, _) => m
                .into_iter()
                .map(|(k, a)| (k as u32, CellAcc::Moments(a)))
                .collect(),
            AccumulatorTable::Mean(m, _) => m
                .into_iter()
                .map(|(k, a)| (k as u32, CellAcc::Mean(a)))
                .collect(),
        };
        let index = cells
            .iter()
            .enumerate()
            .map(|(i, (k, _))| (*k, i))
            .collect();
        Self {
            index,
            cells,
            last: None,
            log: Vec::new(),
        }
    }

    /// The moments accumulator of cell `key`, if it has one.
    fn moments(&self, key: u32) -> Option<&CellAccumulator> {
        match self.index.get(&key).map(|&s| &self.cells[s].1) {
            Some(CellAcc::Moments(acc)) => Some(acc),
            _ => None,
        }
    }

    #[inline]
    fn get(&mut self, key: u32, ctx: &CvContext<'_>) -> &mut CellAcc {
        let slot = self.slot(key, ctx);
        &mut self.cells[slot].1
    }

    /// Index in `cells` of cell `key`'s accumulator, made (empty) if it has none.
    #[inline]
    fn slot(&mut self, key: u32, ctx: &CvContext<'_>) -> usize {
        match self.last {
            Some((k, s)) if k == key => s,
            _ => {
                let n = self.cells.len();
                let s = *self.index.entry(key).or_insert(n);
                if s == n {
                    let acc = match ctx.kind {
                        Kind::PerLight => {
                            CellAcc::Mean(MeanContributionAccumulator::new(ctx.layout.partitions))
                        }
                        _ => CellAcc::Moments(CellAccumulator::new(ctx.layout, ctx.color)),
                    };
                    self.cells.push((key, acc));
                }
                self.last = Some((key, s));
                s
            }
        }
    }
}

enum Phase<'t> {
    Plain,
    Train(&'t mut TileCells),
    Apply(&'t CoefficientTable),
}

/// One technique's sample in CV terms.
#[derive(Clone, Copy, Debug)]
struct TechSample {
    /// `F = w f/p_tech` per channel (`w` the base MIS weight; `f/p` for balance).
    value: [f64; 3],
    /// Effective density `p` (1 for point masses).
    pdf: f64,
    /// Light cluster and its `λ`.
    partition: Option<(u32, f64)>,
    /// `λ_bsdf`.
    lambda_bsdf: f64,
    /// Roulette factor `R`.
    scale: f64,
}

impl TechSample {
    #[inline]
    fn cv<'a>(&self, overlapping: &'a [f64]) -> CvSample<'a> {
        CvSample {
            pdf: self.pdf,
            partition: self.partition,
            overlapping,
        }
    }
}

/// The vertex policy: records (train) or modifies (apply) the direct lighting.
struct Policy<'c, 't> {
    ctx: &'c CvContext<'c>,
    phase: Phase<'t>,
    pixel: u32,
    /// Surrogate pixel value of relative training [Hua eq. 25], or `None`.
    surrogate: Option<f64>,
    /// Σ over vertices of (controlled − plain) contributions.
    cv_delta: Vec3,
    /// Cell of the first vertex, found only where it is read (`keeps_first_cell`) or
    /// controlled.
    first_cell: Option<u32>,
    /// Whether the sample's first cell is kept: in the render phase until a sample of the
    /// pixel finds one (its `cell` layer). Below `min_depth` the camera hit's cell is not
    /// looked up for any other sample.
    keeps_first_cell: bool,
    /// Cell of the current vertex when it is controlled (set by `controls`).
    cell: Option<u32>,
    /// The render phase's coefficient slot of `cell` (set by `controls`: looked up once
    /// per vertex).
    slot: Option<usize>,
    /// The training sample's half (its index's parity) when the job records halves
    /// ([`CvContext::halves`]): its records go to key `2 · cell + half`.
    half: Option<u32>,
}

#[inline]
fn v3(v: Vec3) -> [f64; 3] {
    [f64::from(v.x), f64::from(v.y), f64::from(v.z)]
}

impl Policy<'_, '_> {
    /// The NEE and BSDF samples of a vertex; `None` when NEE did not run (delta BSDF or no
    /// lights: the vertex is not controlled).
    /// `values`: whether the samples' values are wanted (else they are left zero).
    #[inline]
    fn samples(&self, r: &VertexRecord, values: bool) -> Option<[Option<TechSample>; 2]> {
        let nee_light = r.nee_light?;
        let comps = &self.ctx.comps;
        let nee_only = self.ctx.kind == Kind::PerLight;
        let nee = match r.light {
            Some(lt) => {
                let (c, inv_s) = comps.of(lt.light)?;
                let pl = f64::from(lt.pdf_light);
                let pb = if lt.visible {
                    f64::from(lt.pdf_bsdf)
                } else {
                    0.0
                };
                let p = pl + pb;
                // Base value: the job's MIS weight against the BSDF density of the
                // direction, exactly as `path` weighs it (zero when occluded anyway).
                let value = if values {
                    let w = f64::from(self.ctx.base.weight(lt.pdf_light, lt.pdf_bsdf)) / pl;
                    v3(lt.value).map(|x| x * w)
                } else {
                    [0.0; 3]
                };
                Some(TechSample {
                    value,
                    pdf: if nee_only { pl } else { p },
                    partition: Some((c, pl * inv_s)),
                    lambda_bsdf: pb,
                    scale: 1.0,
                })
            }
            None => comps.of(nee_light).map(|(c, inv_s)| TechSample {
                value: [0.0; 3],
                pdf: 1.0,
                partition: Some((c, inv_s)),
                lambda_bsdf: 0.0,
                scale: 1.0,
            }),
        };
        let bsdf = match r.bsdf {
            None => Some(TechSample {
                value: [0.0; 3],
                pdf: 1.0,
                partition: None,
                lambda_bsdf: 1.0,
                scale: 1.0,
            }),
            Some(b) if !b.traced => None,
            Some(b) => {
                // No roulette before `rr_depth`: skip the division.
                let scale = if b.rr_q == 1.0 {
                    1.0
                } else {
                    1.0 / f64::from(b.rr_q)
                };
                if b.delta {
                    Some(TechSample {
                        value: if values {
                            v3(b.weight * b.emitted)
                        } else {
                            [0.0; 3]
                        },
                        pdf: 1.0,
                        partition: None,
                        lambda_bsdf: 1.0,
                        scale,
                    })
                } else {
                    let pb = f64::from(b.pdf_bsdf);
                    let pl = f64::from(b.pdf_light);
                    let p = pb + pl;
                    let partition = match b.hit_light {
                        Some(l) if pl > 0.0 => comps.of(l).map(|(c, inv_s)| (c, pl * inv_s)),
                        _ => None,
                    };
                    let value = if values {
                        let w = f64::from(self.ctx.base.weight(b.pdf_bsdf, b.pdf_light));
                        v3(b.weight * b.emitted).map(|x| x * w)
                    } else {
                        [0.0; 3]
                    };
                    Some(TechSample {
                        value,
                        pdf: p,
                        partition,
                        lambda_bsdf: pb,
                        scale,
                    })
                }
            }
        };
        Some([nee, bsdf])
    }

    /// A controlled vertex of the render phase through its cell's dense coefficient `row`:
    /// the base estimate `Σ_s R_s F_s` (zero unless `values`) and the subtracted term
    /// `Σ_s R_s Σ_k α_k λ_k(x_s)/p(x_s)` [Hua eq. 17], in `f32` — the samples of
    /// [`Self::samples`] without their `f64` records. `None` where NEE did not run or its
    /// light (sampled or selected) is in no partition: the general route handles those.
    #[inline(always)]
    fn apply_dense(&self, row: &[u16], r: &VertexRecord, values: bool) -> Option<(Vec3A, Vec3A)> {
        let nee_light = r.nee_light?;
        let comps = &self.ctx.comps;
        let per_light = self.ctx.kind == Kind::PerLight;
        let alpha = |at: usize| {
            row.get(at..at + 3).map_or(Vec3A::ZERO, |a| {
                Vec3A::new(from_bf16(a[0]), from_bf16(a[1]), from_bf16(a[2]))
            })
        };
        let partition = |c: u32| alpha(ROW_HEAD + 3 * c as usize);
        let ok = |p: f32| (p > 0.0) & (p < f32::INFINITY);
        let mut plain = Vec3A::ZERO;
        let mut term = Vec3A::ZERO;
        match r.light {
            Some(lt) => {
                let (c, inv_s) = comps.of(lt.light)?;
                let pl = lt.pdf_light;
                let pb = if lt.visible { lt.pdf_bsdf } else { 0.0 };
                let p = if per_light { pl } else { pl + pb };
                if values {
                    plain += Vec3A::from(lt.value) * (self.ctx.base.weight(pl, lt.pdf_bsdf) / pl);
                }
                if ok(p) {
                    let inv_p = 1.0 / p;
                    if !per_light && pb != 0.0 {
                        term += alpha(0) * (pb * inv_p);
                    }
                    let l = pl * inv_s as f32;
                    if l != 0.0 {
                        term += partition(c) * (l * inv_p);
                    }
                }
            }
            // A failed light sample: no value, `p = 1`.
            None => {
                let (c, inv_s) = comps.of(nee_light)?;
                let l = inv_s as f32;
                if l != 0.0 {
                    term += partition(c) * l;
                }
            }
        }
        match r.bsdf {
            // No BSDF sample: `λ_bsdf/p = 1`.
            None if !per_light => term += alpha(0),
            None => {}
            Some(b) if !b.traced => {}
            Some(b) => {
                let scale = if b.rr_q == 1.0 { 1.0 } else { 1.0 / b.rr_q };
                let f = Vec3A::from(b.weight * b.emitted);
                if b.delta {
                    if values {
                        plain += f * scale;
                    }
                    if !per_light {
                        term += alpha(0) * scale;
                    }
                } else {
                    let (pb, pl) = (b.pdf_bsdf, b.pdf_light);
                    if values {
                        plain += f * (scale * self.ctx.base.weight(pb, pl));
                    }
                    let p = pb + pl;
                    // `per_light_cv` controls the NEE sample only [Hua §7.2].
                    if !per_light && ok(p) {
                        let r = scale / p;
                        let mut t = Vec3A::ZERO;
                        if pb != 0.0 {
                            t += alpha(0) * pb;
                        }
                        if let Some(l) = b.hit_light
                            && pl > 0.0
                            && let Some((c, inv_s)) = comps.of(l)
                        {
                            t += partition(c) * (pl * inv_s as f32);
                        }
                        term += t * r;
                    }
                }
            }
        }
        Some((plain, term))
    }

    /// The vertex's cell key: its finest grid cell where `fine` (a glossy camera hit), else
    /// its undivided one ([`Grid`]); its pixel for `optimal_mis`'s camera hits.
    // Always inlined: called out of line, `p` and `ns` went through the stack (≈ 7 % of a
    // colour-lamp d5 render's CPU samples in this function).
    #[inline(always)]
    fn cell_of(&self, fine: bool, depth: u32, p: Vec3, ns: Vec3) -> Option<u32> {
        match self.ctx.kind {
            Kind::Cms | Kind::PerLight => {
                let cell = if fine {
                    self.ctx.grid.cell(p)
                } else {
                    self.ctx.grid.undivided_cell(p)
                };
                Some(cell * NORMAL_BINS + normal_bin(ns))
            }
            Kind::OptimalMis => (depth == 0).then_some(self.pixel),
        }
    }
}

impl VertexObserver for Policy<'_, '_> {
    const CONTROLS_DIRECT: bool = true;
    /// An uncontrolled vertex is `path`'s: nothing to record or add.
    const SEES_UNCONTROLLED: bool = false;

    /// A vertex is left to `path` (no policy work, none of the extra rays a CV needs) unless
    /// the policy records it (training, in a cell) or controls it (render phase, in a cell
    /// with coefficients): shallower than `min_depth`, outside the training phase's cells, or
    /// in a cell without coefficients (`α ≡ 0`), the estimate is `path`'s, whatever the
    /// base. With `base: "balance"` that makes a cell whose fits fell back, and a job whose
    /// fits were all switched off, exactly `path` (the balance base alone is worse than the
    /// job's heuristic); the estimate stays unbiased, the choice depending only on the
    /// vertex's cell.
    #[inline]
    fn controls(&mut self, depth: u32, p: Vec3, ns: Vec3, glossy: bool) -> bool {
        let min_depth = self.ctx.min_depth;
        let cell = if depth >= min_depth || (depth == 0 && self.keeps_first_cell) {
            self.cell_of(depth == 0 && glossy, depth, p, ns)
        } else {
            None
        };
        if depth == 0 {
            self.first_cell = cell;
        }
        // Shallower than `min_depth`: not controlled, `path`'s estimate, no training sample.
        self.cell = cell.filter(|_| depth >= min_depth);
        self.slot = None;
        match (&self.phase, self.cell) {
            (_, None) | (Phase::Plain, _) => false,
            (Phase::Train(_), Some(_)) => true,
            (Phase::Apply(table), Some(key)) => {
                self.slot = table.get(key);
                if let Some(slot) = self.slot {
                    table.prefetch_head(slot);
                }
                self.slot.is_some()
            }
        }
    }

    /// The row entry of the selected light's partition, loaded while NEE samples it.
    #[inline]
    fn nee_selected(&self, light: u32) {
        if let (Phase::Apply(table), Some(slot)) = (&self.phase, self.slot)
            && let Some((c, _)) = self.ctx.comps.of(light)
        {
            table.prefetch_partition(slot, c);
        }
    }

    /// While training, and in the render phase with the job's heuristic as the base,
    /// [`path::trace`](super::path::trace) adds the vertex's MIS-weighted direct lighting
    /// itself: a training sample is bit for bit `path`'s (the records carry the base's
    /// values for the fits), and a controlled vertex adds only the CV term
    /// `Σ_k α_k − Σ_s R_s Σ_k α_k λ_k(x_s)/p(x_s)` [Hua eq. 17]. With `base: "balance"` the
    /// render phase's controlled vertices return the whole estimate (balance values plus the
    /// term).
    #[inline]
    fn adds_to_path(&self) -> bool {
        matches!(self.phase, Phase::Train(_)) || self.ctx.base == self.ctx.st.mis
    }

    #[inline]
    fn controlled_vertex(&mut self, r: &VertexRecord) -> Vec3 {
        let adds_to_path = self.adds_to_path();
        // The render phase's common case: a dense row, in `f32`.
        if let (Phase::Apply(table), Some(slot)) = (&self.phase, self.slot)
            && let Some((row, sums)) = table.dense(slot)
            && let Some((plain, term)) = self.apply_dense(row, r, !adds_to_path)
        {
            // `Σα − Σ_s R_s Σ_k α_k λ_k/p` [Hua eq. 17], the hi part first.
            let d = (Vec3A::new(sums[0], sums[1], sums[2]) - term)
                + Vec3A::new(sums[3], sums[4], sums[5]);
            let d = r.throughput * Vec3::from(d);
            self.cv_delta += d;
            return if adds_to_path {
                d
            } else {
                r.throughput * Vec3::from(plain) + d
            };
        }
        // Set by `controls` for this vertex.
        let cell = self.cell;
        let training = matches!((&self.phase, cell), (Phase::Train(_), Some(_)));
        // Sample values are read by the records, and by the estimate when it is not `path`'s
        // plus a term.
        let Some(samples) = self.samples(r, training || !adds_to_path) else {
            // Only the BSDF technique ran: its full (w = 1) contribution.
            return match r.bsdf {
                Some(b) if b.traced && !adds_to_path => {
                    r.throughput * b.weight / b.rr_q * b.emitted
                }
                _ => Vec3::ZERO,
            };
        };
        let kind = self.ctx.kind;
        // The base estimate `Σ_s R_s F_s`, unless `trace` adds it.
        let mut plain = [0.0f64; 3];
        if !adds_to_path {
            for s in samples.iter().flatten() {
                for (p, v) in plain.iter_mut().zip(s.value) {
                    *p += s.scale * v;
                }
            }
        }
        let mut out = plain;
        match (&mut self.phase, cell) {
            (Phase::Train(cells), Some(key)) => {
                let key = self.half.map_or(key, |h| 2 * key + h);
                let w0 = if kind == Kind::OptimalMis {
                    1.0
                } else {
                    let t = r.throughput;
                    training_weight(f64::from(t.x + t.y + t.z) / 3.0, self.surrogate)
                };
                if kind == Kind::PerLight {
                    // One record per vertex: its NEE sample's light with the `1/c` its CV term
                    // is scaled by in the render phase (`λ/p`, as `CoefficientTable::term`),
                    // and its value (zero for a failed or occluded sample).
                    let (partition, inv_c, value) = match samples[0] {
                        Some(nee) => match nee.partition {
                            Some((c, l)) => (c, l * (1.0 / nee.pdf), nee.value),
                            None => (NO_PARTITION, 0.0, nee.value),
                        },
                        None => (NO_PARTITION, 0.0, [0.0; 3]),
                    };
                    let rec = TrainRecord {
                        key,
                        partition,
                        weight: w0,
                        value,
                        pdf: 1.0,
                        lambda_partition: inv_c,
                        lambda_bsdf: 0.0,
                    };
                    cells.record(rec, self.ctx);
                } else {
                    // `samples` is `[NEE, BSDF]`.
                    for (s, technique) in samples.iter().zip([0, BSDF_TECHNIQUE]) {
                        let Some(s) = s else { continue };
                        let (partition, lambda_partition) =
                            s.partition.unwrap_or((NO_PARTITION, 0.0));
                        let rec = TrainRecord {
                            key,
                            partition: partition | technique,
                            weight: w0 * s.scale * s.scale,
                            value: s.value,
                            pdf: s.pdf,
                            lambda_partition,
                            lambda_bsdf: s.lambda_bsdf,
                        };
                        cells.record(rec, self.ctx);
                    }
                }
            }
            (Phase::Apply(table), Some(_)) => {
                if let Some(slot) = self.slot {
                    let alpha = table.alpha_sum(slot);
                    for c in 0..3 {
                        out[c] += alpha[c];
                    }
                    // `per_light_cv` controls the NEE sample only [Hua §7.2].
                    let per_light = kind == Kind::PerLight;
                    for (i, s) in samples.iter().enumerate() {
                        let Some(s) = s else { continue };
                        if per_light && i == 1 {
                            continue;
                        }
                        let t = table.term(slot, s, !per_light);
                        for c in 0..3 {
                            out[c] -= s.scale * t[c];
                        }
                    }
                    let d = Vec3::new(
                        (out[0] - plain[0]) as f32,
                        (out[1] - plain[1]) as f32,
                        (out[2] - plain[2]) as f32,
                    );
                    self.cv_delta += r.throughput * d;
                    if adds_to_path {
                        return r.throughput * d;
                    }
                }
            }
            _ => {}
        }
        r.throughput * Vec3::new(out[0] as f32, out[1] as f32, out[2] as f32)
    }
}

/// What a tile of any phase produced: its film and the rays traced.
#[derive(Debug)]
pub struct TileFilm {
    /// Per-pixel sums of the tile's samples.
    pub film: Film,
    /// Rays traced.
    pub rays: u64,
}

/// What a training tile produced: film, rays and the tile's cell accumulators.
#[derive(Debug)]
pub struct TrainTile {
    /// Film and rays.
    pub out: TileFilm,
    /// Cell accumulators of the tile (keys: [`CvJob::table_len`] cell indices).
    pub cells: AccumulatorTable,
    /// Whether the tile stopped recording after its first [`TRAIN_PROBE_SPP`] samples per
    /// pixel (its own fits were predicted not to pay; the rest was traced as `path`).
    pub stopped: bool,
    /// Whether the tile's fits failed the split-half check ([`split_half_gain`], `optimal_mis`'s
    /// `min_split_gain`): it reports no cells, and its pixels are rendered as `path`.
    pub dropped: bool,
}

/// The tile probe's minima: each of the job's lowered by [`PROBE_MARGIN`] of its size, since
/// a tile's few samples per cell make its in-sample gains noisy and a tile stopped by mistake
/// loses most of its training data.
fn probe_policy(mut policy: SolvePolicy) -> SolvePolicy {
    for m in [&mut policy.min_image_gain, &mut policy.min_fit_gain] {
        if m.is_finite() {
            *m -= PROBE_MARGIN * m.abs();
        }
    }
    // The probe's halves have a sample per pixel each: too few to cross-fit. Its fits are
    // grouped as the job's are (ungrouped, a many-light tile's in-sample gain is its fits'
    // overfitting).
    if policy.halves != CellHalves::None {
        policy.halves = CellHalves::Merged;
    }
    policy
}

/// See [`probe_policy`].
const PROBE_MARGIN: f64 = 0.5;

/// Whether a training tile stops recording after its probe ([`TRAIN_PROBE_SPP`]): its
/// table's fits are switched off under [`probe_policy`] both with the cells taking their
/// undivided ancestors' fits and with every cell fitted on its own
/// ([`AccumulatorTable::fits_pay_pooled_or_alone`]). The job's solve chooses between the two
/// per node (held out), so a tile stops only when neither would pay. Judged by the pooled
/// fits alone, the veach-mis tiles of the glossy plates, whose highlights the subdivided
/// cells are for, stopped (4 of 6 training tiles, and the job lost 7–8 % at equal spp:
/// `docs/bench/README.md`); judged by the finest cells alone, thinly sampled cells stopped
/// checkers tiles that the pooled fits keep. Both solves are of the tile's own samples, so
/// the decision is the same on every worker and for any thread count. Where most of the
/// probe's light-partition samples sit in thin partitions ([`PROBE_THIN_SHARE`]) its fit
/// gain is not judged, only its image gain.
fn probe_stops(probe: &AccumulatorTable, policy: SolvePolicy) -> bool {
    let mut p = probe_policy(policy);
    let halves = policy.halves != CellHalves::None;
    if probe
        .thin_partition_share(policy.min_group_samples, halves)
        .is_some_and(|s| s >= PROBE_THIN_SHARE)
    {
        p.min_fit_gain = f64::NEG_INFINITY;
    }
    !probe.fits_pay_pooled_or_alone(&p, 1)
}

/// The share of a probe's light-partition samples in thin partitions
/// ([`AccumulatorTable::thin_partition_share`], below `min_group_samples`) from which the
/// probe no longer judges its fit gain, only its image gain. Its 2-spp fits are then
/// grouped far more coarsely than the job's 16-spp fits will be, and their gain says little
/// about them: every `many-lights` tile (64 lamps) has a share of 1.0 and a probe fit gain of
/// 0.016–0.15, below the probe's 0.1 at 2–4 of its 4 tiles over seeds 1–6. Stopped, the job
/// lost its fits at 2 of 6 seeds (1.00× at equal spp where they give 1.25–1.28×), and kept
/// them with a quarter of their data at the rest (1.11× at seed 2). Measured shares of the
/// scenes the probe stops or keeps on its fit gain: envmap 0.04–0.31 (and 1.0 in a tile
/// whose image gain is 0), cornell-box 0.05–0.11, the shared spheres 0.09–0.16, the shared
/// Cornell box 0.003, colour-lamp 0.50–0.53, veach-mis 0.33–0.68; the shared `manylights-4`
/// 0.91 and `many-lights-256` 1.0 (seed 1, d5).
const PROBE_THIN_SHARE: f64 = 0.75;

/// Training samples per pixel a training tile records before it checks its own table
/// against the job's `min_image_gain` / `min_fit_gain` (the table-wide switch of
/// [`AccumulatorTable::solve`], applied to the tile's cells alone, with each minimum lowered
/// by half its size, pooled and cell by cell: [`probe_stops`]). Below either, whichever way
/// the cells are fitted, the tile traces the rest of its training samples as
/// `path` and reports only these: on a scene whose fits cannot pay, the whole job would fall
/// back at the train barrier anyway, and recording costs +25…+45 % per training sample (most
/// of such a job's overhead). The decision depends only on the tile's own samples (fixed by
/// the job), so it is the same on every worker and for any thread count. A training tile
/// (every CV estimator: `cms`, `optimal_mis` and, with its per-cell predictions,
/// `per_light_cv`) with more training samples than these is always recorded in these two
/// passes, each pixel adding all its samples in index order, so the bits do not depend on
/// whether a minimum is set (with none, no probe decision is made).
pub const TRAIN_PROBE_SPP: u32 = 2;

/// What a render-phase tile produced: film, rays, and per pixel the summed CV term
/// (controlled − plain) and the cell of the first vertex (−1 for none), row-major.
#[derive(Debug)]
pub struct RenderTile {
    /// Film and rays.
    pub out: TileFilm,
    /// Σ over samples of (controlled − plain), per pixel.
    pub cv_sum: Vec<[f64; 3]>,
    /// Cell id of the first vertex per pixel (−1: none).
    pub cell_id: Vec<f32>,
}

#[derive(Clone, Copy, PartialEq, Eq)]
enum PhaseKind {
    Plain,
    Train,
    Apply,
}

/// A CV job prepared for its phases (grid, components, layout, sample split): the public
/// phase API used by the in-process driver [`render_estimator_image`] and by farm workers,
/// so both produce the same bits.
///
/// Farm flow: surrogate tiles ([`Self::surrogate_tile`]) → the coordinator assembles them
/// and computes [`estimators::surrogate::surrogate_image`] → training tiles
/// ([`Self::train_tile`], tiles of [`TRAIN_TILE`], whole training range) → the coordinator
/// merges their [`AccumulatorTable`]s in row-major tile order and solves
/// ([`AccumulatorTable::solve`] with [`Self::solve_policy`]) → render tiles
/// ([`Self::render_tile`]) with the table built by [`Self::coefficient_table`].
pub struct CvJob<'a> {
    ctx: CvContext<'a>,
    estimator: PhasedEstimator,
    phases: PhaseSamples,
    table_len: usize,
}

impl std::fmt::Debug for CvJob<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("CvJob")
            .field("estimator", &self.estimator)
            .field("phases", &self.phases)
            .field("grid", &self.ctx.grid)
            .field("layout", &self.ctx.layout)
            .finish()
    }
}

impl<'a> CvJob<'a> {
    /// Prepares the phases of `settings.estimator`; `Ok(None)` for estimators without phases
    /// (`path`, `ocv`).
    pub fn new(
        scene: &'a RenderScene,
        settings: &RenderSettings,
    ) -> Result<Option<Self>, RenderError> {
        settings.validate()?;
        let Some(estimator) = settings.estimator.phased() else {
            return Ok(None);
        };
        let estimator = estimator
            .for_sampler(settings.sampler)
            .for_image(scene.width, scene.height);
        if let Err((field, reason)) = estimator.validate() {
            return Err(RenderError::InvalidSetting { field, reason });
        }
        if scene.width == 0 || scene.height == 0 {
            return Err(RenderError::EmptyFilm {
                width: scene.width,
                height: scene.height,
            });
        }
        let (kind, color, grid_res, max_lights) = match estimator {
            PhasedEstimator::Cms(o) => (
                Kind::Cms,
                o.color,
                o.grid_resolution,
                o.max_light_components,
            ),
            PhasedEstimator::PerLightCv(o) => (
                Kind::PerLight,
                CvColor::Rgb,
                o.grid_resolution,
                o.max_light_components,
            ),
            PhasedEstimator::OptimalMis(o) => (
                Kind::OptimalMis,
                o.color,
                Some([1, 1, 1]),
                o.max_light_components,
            ),
        };
        let bounds = scene.accel.bounds();
        let comps = Components::new(&scene.lights, max_lights, bounds);
        let overlapping = u32::from(kind != Kind::PerLight);
        let layout = ComponentLayout::new(comps.partitions(), overlapping).map_err(|_| {
            RenderError::InvalidSetting {
                field: "estimator",
                reason: "invalid component layout",
            }
        })?;
        let grid = Grid::new(
            bounds,
            grid_res,
            estimator.grid_levels(),
            scene.width,
            scene.height,
        )?;
        let table_len = match kind {
            Kind::OptimalMis => scene.width as usize * scene.height as usize,
            _ => grid.cells() * NORMAL_BINS as usize,
        };
        Ok(Some(Self {
            ctx: CvContext {
                rs: scene,
                st: *settings,
                kind,
                comps,
                grid,
                layout,
                color: color.mode(),
                min_depth: estimator.min_depth(),
                controls: estimator.controls_any_vertex(settings.max_depth_u32()),
                train_log_max: TRAIN_LOG_MAX,
                min_split_gain: match estimator {
                    PhasedEstimator::OptimalMis(o) => o.min_split_gain,
                    _ => None,
                },
                halves: estimator.solve_policy().halves != CellHalves::None,
                base: match estimator.base() {
                    CvBase::Mis => settings.mis,
                    CvBase::Balance => super::MisHeuristic::Balance,
                },
            },
            estimator,
            phases: estimator.phases(settings.spp, settings.max_depth_u32()),
            table_len,
        }))
    }

    /// Sample ranges of the phases.
    pub fn phases(&self) -> &PhaseSamples {
        &self.phases
    }

    /// The estimator and its options.
    pub fn estimator(&self) -> PhasedEstimator {
        self.estimator
    }

    /// Whether the training phase needs a surrogate image [Hua eq. 25].
    pub fn needs_surrogate(&self) -> bool {
        self.estimator.relative() && !self.phases.surrogate.is_empty()
    }

    /// Whether any vertex of a path can be controlled: false when `max_depth` leaves no
    /// scattering vertex at or below `min_depth` (e.g. `cms` at depth 2 with the default
    /// `min_depth` 1). Then training accumulates nothing, every cell falls back and the job is
    /// its base estimator; the surrogate image (which only weighs training samples) is not
    /// needed.
    pub fn controls_any_vertex(&self) -> bool {
        self.ctx.controls_any_vertex()
    }

    /// Solve policy of the cell systems.
    pub fn solve_policy(&self) -> SolvePolicy {
        self.estimator.solve_policy()
    }

    /// Number of cell keys (`0..table_len`): grid cells × normal bins, or pixels.
    pub fn table_len(&self) -> usize {
        self.table_len
    }

    /// Component layout of the cell systems.
    pub fn layout(&self) -> ComponentLayout {
        self.ctx.layout
    }

    /// Grid resolution (`[0, 0, 0]` when cells are pixels).
    pub fn grid_resolution(&self) -> [u32; 3] {
        if self.ctx.kind == Kind::OptimalMis {
            [0; 3]
        } else {
            self.ctx.grid.resolution()
        }
    }

    /// Renders `samples` of `tile` without CV (surrogate phase).
    pub fn surrogate_tile(&self, tile: TileRect, samples: Range<u32>) -> TileFilm {
        let input = PhaseInput {
            kind: PhaseKind::Plain,
            table: None,
            surrogate: None,
            pixels: Pixels::All,
        };
        let t = Banded::run(&self.ctx, tile, samples, input, None, None);
        TileFilm {
            film: t.film,
            rays: t.rays,
        }
    }

    /// Renders training `samples` of `tile`, accumulating the cell systems; `surrogate` is
    /// the whole image's surrogate (`width × height`, required when
    /// [`Self::needs_surrogate`]).
    pub fn train_tile(
        &self,
        tile: TileRect,
        samples: Range<u32>,
        surrogate: Option<&[f64]>,
    ) -> Result<TrainTile, RenderError> {
        let n = self.ctx.rs.width as usize * self.ctx.rs.height as usize;
        if surrogate.is_some_and(|s| s.len() != n) {
            return Err(RenderError::InvalidSetting {
                field: "surrogate",
                reason: "surrogate image size does not match the film",
            });
        }
        let input = PhaseInput {
            kind: PhaseKind::Train,
            table: None,
            surrogate,
            pixels: Pixels::All,
        };
        let width = self.ctx.rs.width;
        let policy = self.solve_policy();
        // Tables are recorded in two passes, the probe's samples and the rest (the same bits
        // whether or not a minimum asks for the probe's decision).
        let split = samples.len() > TRAIN_PROBE_SPP as usize;
        let probe_end = if split {
            samples.start + TRAIN_PROBE_SPP
        } else {
            samples.end
        };
        // Training `range` on top of the tile's film `start`: every band's samples, added in
        // band order (see [`BAND_ROWS`]) to `cells` after what they hold, and the film.
        let record = |range: Range<u32>, start: Option<&Film>, pixels: Pixels, cells: TileCells| {
            let fold = InOrderFold::new(cells);
            let input = PhaseInput { pixels, ..input };
            let t = Banded::run(&self.ctx, tile, range, input, Some(&fold), start);
            (fold.finish().unwrap_or_default(), t)
        };
        // `path`'s own samples for `pixels`: no records, none of the CV's extra rays.
        let plain = |pixels: Pixels| PhaseInput {
            kind: PhaseKind::Plain,
            table: None,
            surrogate: None,
            pixels,
        };
        // `optimal_mis` records its two halves apart, for the split-half check (always, so the
        // bits do not depend on whether `min_split_gain` is set).
        let halves =
            self.ctx.kind == Kind::OptimalMis && samples.len() >= 2 * TRAIN_PROBE_SPP as usize;
        // With the check, the pixels it reads record all their training samples first. A tile
        // it drops traces its other pixels' training samples as `path`, so it pays the records
        // of one pixel in `SPLIT_CHECK_STRIDE` only; a tile it keeps records the others in the
        // same three passes (probe, first half, second half), so every pixel's cells and film
        // are added in the same passes whether the check runs or not (cells are pixels: no two
        // sets share one).
        let check = self.ctx.min_split_gain.filter(|_| halves);
        let set = if check.is_some() {
            Pixels::Checked
        } else {
            Pixels::All
        };
        let (mut cells, t) = record(samples.start..probe_end, None, set, TileCells::default());
        let (mut film, mut rays) = (t.film, t.rays);
        let (mut stopped, mut dropped) = (false, false);
        if split {
            let rest = probe_end..samples.end;
            if policy.min_image_gain > f64::NEG_INFINITY || policy.min_fit_gain > f64::NEG_INFINITY
            {
                // The cells move into the probe's table and back (a copy of every
                // accumulator was 2 % of a many-lights training pass).
                let probe = cells_table(
                    self.ctx.kind,
                    std::mem::take(&mut cells),
                    image_variance(&film, width, surrogate),
                );
                stopped = probe_stops(&probe, policy);
                if stopped {
                    // The rest as `path`. The probe covered every pixel: only `optimal_mis`
                    // has the split check, and its policy sets no table minimum
                    // (`PhasedEstimator::solve_policy`), so the probe never decides there.
                    debug_assert_eq!(set, Pixels::All);
                    let r =
                        Banded::run(&self.ctx, tile, rest, plain(Pixels::All), None, Some(&film));
                    return Ok(TrainTile {
                        out: TileFilm {
                            film: r.film,
                            rays: rays + r.rays,
                        },
                        cells: probe,
                        stopped,
                        dropped: false,
                    });
                }
                cells = TileCells::from_table(probe);
            }
            let mid = if halves {
                samples.start + samples.len() as u32 / 2
            } else {
                probe_end
            };
            // The two halves of `pixels` on top of `film`, the first half's samples added to
            // `cells` (none when the probe is the first half), the second half's too unless
            // the job records `halves`: the film after the first half, the second half's own
            // cells (with `halves`), the film after both, and their rays. Recorded straight
            // into `cells`, a sample adds to the sums already there: the probe's cells are not
            // remade and merged (≈ 5 % of a 960×540 training pass). `optimal_mis`'s halves keep
            // the second apart (then merged) whether or not its split-half check reads it, so
            // that the bits do not depend on the check.
            let halves_of = |pixels: Pixels, film: Film, cells: &mut TileCells| {
                let (film, rays) = if mid > probe_end {
                    let (c, r) = record(probe_end..mid, Some(&film), pixels, std::mem::take(cells));
                    *cells = c;
                    (r.film, r.rays)
                } else {
                    (film, 0)
                };
                let into = if halves {
                    TileCells::default()
                } else {
                    std::mem::take(cells)
                };
                let (second, r) = record(mid..samples.end, Some(&film), pixels, into);
                let second = if halves {
                    Some(second)
                } else {
                    *cells = second;
                    None
                };
                (film, second, r.film, rays + r.rays)
            };
            let (first_film, second, f, r) = halves_of(set, film, &mut cells);
            (film, rays) = (f, rays + r);
            dropped = match (check, &second) {
                (Some(min), Some(second)) => {
                    split_half_gain(&self.ctx, &policy, &cells, second, &first_film, &film)
                        .is_some_and(|g| g < min)
                }
                _ => false,
            };
            if dropped {
                cells = TileCells::default();
                let r = Banded::run(
                    &self.ctx,
                    tile,
                    samples.clone(),
                    plain(Pixels::Unchecked),
                    None,
                    Some(&film),
                );
                (film, rays) = (r.film, rays + r.rays);
            } else {
                if let Some(second) = second {
                    cells.absorb(second, &self.ctx);
                }
                if check.is_some() {
                    let probe = samples.start..probe_end;
                    let (c, r) = record(
                        probe,
                        Some(&film),
                        Pixels::Unchecked,
                        std::mem::take(&mut cells),
                    );
                    (cells, film, rays) = (c, r.film, rays + r.rays);
                    let (_, second, f, r) = halves_of(Pixels::Unchecked, film, &mut cells);
                    (film, rays) = (f, rays + r);
                    if let Some(second) = second {
                        cells.absorb(second, &self.ctx);
                    }
                }
            }
        }
        let image = image_variance(&film, width, surrogate);
        Ok(TrainTile {
            out: TileFilm { film, rays },
            cells: cells_table(self.ctx.kind, cells, image),
            stopped,
            dropped,
        })
    }

    /// Builds the lookup table of solved coefficients, checking every key and layout (a
    /// table from the wire is untrusted).
    pub fn coefficient_table(
        &self,
        solved: &BTreeMap<u64, CellCoefficients>,
    ) -> Result<CoefficientTable, RenderError> {
        let bad = |reason| RenderError::InvalidSetting {
            field: "coefficients",
            reason,
        };
        let comps = self.ctx.layout.partitions as usize + 1;
        let row = ROW_HEAD + 3 * (comps - 1);
        let mut table = CoefficientTable {
            slot: SlotMap::with_capacity(solved.len()),
            coeffs: Vec::with_capacity(solved.len()),
            rows: Vec::new(),
            sums: Vec::new(),
            stride: if comps <= DENSE_ROW_MAX && solved.len().saturating_mul(row) <= DENSE_TOTAL_MAX
            {
                row
            } else {
                0
            },
        };
        for (&key, co) in solved {
            if co.layout() != self.ctx.layout || co.color() != self.ctx.color {
                return Err(bad("coefficient layout does not match the job"));
            }
            let key = u32::try_from(key)
                .ok()
                .filter(|&k| (k as usize) < self.table_len)
                .ok_or(bad("cell key out of range"))?;
            if co.is_zero() {
                // α ≡ 0 gives the base estimate bit for bit: skip the per-sample CV terms.
                continue;
            }
            // Keys come strictly increasing from the map: each is inserted once.
            table.slot.insert(key, table.coeffs.len() as u32);
            table.push(co);
        }
        Ok(table)
    }

    /// Renders `samples` of `tile` with the CV applied.
    pub fn render_tile(
        &self,
        tile: TileRect,
        samples: Range<u32>,
        table: &CoefficientTable,
    ) -> RenderTile {
        // Nothing to control (a switched-off job, or no controllable vertex): what
        // [`Banded::run`] would trace is `path`'s pixel samples ([`traces_as_path`]), in the
        // same order; `path`'s own driver traces them without the bands and their per-band
        // films (the same bits: a band's pixels are copied into the tile's film).
        if traces_as_path(&self.ctx, PhaseKind::Apply, Some(table))
            && let Ok((film, rays)) =
                crate::tile::render_tile_counted(self.ctx.rs, &self.ctx.st, tile, samples.clone())
        {
            let n = tile.pixel_count() as usize;
            return RenderTile {
                out: TileFilm { film, rays },
                cv_sum: vec![[0.0; 3]; n],
                cell_id: vec![-1.0; n],
            };
        }
        let input = PhaseInput {
            kind: PhaseKind::Apply,
            table: Some(table),
            surrogate: None,
            pixels: Pixels::All,
        };
        let t = Banded::run(&self.ctx, tile, samples, input, None, None);
        RenderTile {
            out: TileFilm {
                film: t.film,
                rays: t.rays,
            },
            cv_sum: t.cv_sum,
            cell_id: t.cell_id,
        }
    }
}

/// The per-pixel moments of a film, as [`estimators::surrogate::surrogate_image`] takes them.
pub fn film_moments(film: &Film) -> Vec<PixelMoments> {
    film.pixels.iter().map(Pixel::moments).collect()
}

/// What a tile of a phase is rendered with, besides its rectangle and samples: the phase,
/// the coefficient table (render phase), the whole image's surrogate (training) and which of
/// the tile's pixels get the samples.
#[derive(Clone, Copy)]
struct PhaseInput<'a> {
    kind: PhaseKind,
    table: Option<&'a CoefficientTable>,
    surrogate: Option<&'a [f64]>,
    pixels: Pixels,
}

/// Which pixels of a tile a pass renders (the others keep their film as it was): the split-half
/// check's pixels ([`split_checked`]) are recorded first, so that a tile the check drops traces
/// its other pixels' training samples as `path` (see [`CvJob::train_tile`]).
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum Pixels {
    /// Every pixel.
    All,
    /// Only the pixels [`split_half_gain`] reads.
    Checked,
    /// Every pixel but those.
    Unchecked,
}

impl Pixels {
    fn includes(self, x: u32, y: u32) -> bool {
        match self {
            Pixels::All => true,
            Pixels::Checked => split_checked(x, y),
            Pixels::Unchecked => !split_checked(x, y),
        }
    }
}

/// Rows of the bands a tile of any phase is rendered in: the bands of a tile run in
/// parallel (rayon, in whatever pool is current: the in-process driver's, a farm worker's
/// global one) and are joined in band order. Fixed — never derived from a thread count — so
/// a training tile's table (each band's samples, added in band order) has the same bits for
/// any thread count, in-process and on every worker; the pixels do not depend on the bands
/// at all (each pixel sums its own samples in index order). A worker renders a 128-pixel
/// training tile on all its cores, which keeps the few large tasks of a training phase from
/// leaving cores idle before the barrier.
///
/// The bands' logs concatenated in band order are the tile's samples in row-major pixel
/// order whatever the band height, so the table depends on it only where a band's log spills
/// ([`TRAIN_LOG_MAX`] records: above ≈ 500 training spp with 2 rows). Two rows keep a band's
/// log (≈ 2 MiB at 16 training spp) in the core's L2 until the fold reads it back: with
/// 16-row bands (≈ 16 MiB) those reads came from memory, and a training pass took 4–7 %
/// longer (colour-lamp and many-lights d5, one thread; same bits).
pub const BAND_ROWS: u32 = 2;

/// Rows of the bands of a surrogate or render tile. Their pixels do not depend on the bands
/// (each pixel sums its own samples in index order) and they carry no cells, so the bands can
/// be as fine as load balance wants: a worker renders one tile at a time, and with
/// [`BAND_ROWS`]-row bands the two bands of a 32-pixel tile left one core idle while the other
/// finished (the farm's render phase ran ≈ 8 % longer than the in-process one, whose tiles
/// keep every core busy; `docs/bench/farm.md` §7).
pub const PIXEL_BAND_ROWS: u32 = 2;

/// A tile's outputs joined from its bands (row-major over the tile, like [`TileOut`]); a
/// training tile's cells go to its [`InOrderFold`].
struct Banded {
    film: Film,
    rays: u64,
    cv_sum: Vec<[f64; 3]>,
    cell_id: Vec<f32>,
}

/// Folds items numbered `0, 1, 2, …` into one accumulator in number order while they are
/// produced in any order: a finished item is queued, and whichever thread finds the next
/// item in line adds it (and any queued successors) while the others go on producing. The
/// fold's result is the same for any thread count; an item is dropped as soon as it is
/// added.
///
/// Used for a training tile's bands (their logs added to the tile's cells, [`TileCells`])
/// and for a job's training tiles (their tables merged into the job's in row-major tile
/// order).
struct InOrder<T, A> {
    state: std::sync::Mutex<InOrderState<T, A>>,
}

struct InOrderState<T, A> {
    /// The item to add next.
    next: usize,
    /// Finished items waiting for their predecessors.
    pending: BTreeMap<usize, T>,
    /// The accumulator; `None` while a thread is adding to it.
    acc: Option<A>,
}

impl<T, A> InOrder<T, A> {
    fn new(acc: A) -> Self {
        Self {
            state: std::sync::Mutex::new(InOrderState {
                next: 0,
                pending: BTreeMap::new(),
                acc: Some(acc),
            }),
        }
    }

    /// Hands over item `index`; `add` adds an item to the accumulator.
    fn submit(&self, index: usize, item: T, add: impl Fn(&mut A, T)) {
        let lock = || self.state.lock().unwrap_or_else(|e| e.into_inner());
        let mut st = lock();
        st.pending.insert(index, item);
        loop {
            // Another thread is adding: it takes this item too when it comes next in line.
            let Some(mut acc) = st.acc.take() else {
                return;
            };
            let mut batch = Vec::new();
            while let Some(b) = {
                let next = st.next;
                st.pending.remove(&next)
            } {
                batch.push(b);
                st.next += 1;
            }
            if batch.is_empty() {
                st.acc = Some(acc);
                return;
            }
            drop(st);
            for b in batch {
                add(&mut acc, b);
            }
            st = lock();
            st.acc = Some(acc);
        }
    }

    /// The accumulator once every item was submitted (`None` only after a panic in `add`).
    fn finish(self) -> Option<A> {
        let st = self.state.into_inner().unwrap_or_else(|e| e.into_inner());
        debug_assert!(st.pending.is_empty());
        st.acc
    }
}

/// A training tile's bands, added to its cells in band order ([`TileCells::absorb`]).
type InOrderFold = InOrder<TileCells, TileCells>;

impl Banded {
    /// Renders `tile` as bands of full-width rows in parallel: [`BAND_ROWS`] rows for a
    /// training tile (its table depends on them where a log spills), [`PIXEL_BAND_ROWS`]
    /// otherwise. A training tile hands each band's cells to `fold`. The samples are added to
    /// `start` (the tile's film of its earlier samples) when given.
    fn run(
        ctx: &CvContext<'_>,
        tile: TileRect,
        samples: Range<u32>,
        input: PhaseInput<'_>,
        fold: Option<&InOrderFold>,
        start: Option<&Film>,
    ) -> Self {
        let rows = match input.kind {
            PhaseKind::Train => BAND_ROWS,
            PhaseKind::Plain | PhaseKind::Apply => PIXEL_BAND_ROWS,
        };
        let bands: Vec<TileRect> = (0..tile.height.div_ceil(rows))
            .map(|b| TileRect {
                x0: tile.x0,
                y0: tile.y0 + b * rows,
                width: tile.width,
                height: rows.min(tile.height - b * rows),
            })
            .collect();
        let outs: Vec<TileOut> = bands
            .par_iter()
            .enumerate()
            .map(|(i, &b)| {
                let base = start.map(|f| {
                    let w = f.width as usize;
                    let at = (b.y0 - f.y0) as usize * w;
                    Film {
                        x0: b.x0,
                        y0: b.y0,
                        width: b.width,
                        height: b.height,
                        pixels: f.pixels[at..at + b.height as usize * w].to_vec(),
                        rejected: 0,
                    }
                });
                let mut out = run_tile(ctx, b, samples.clone(), input, base);
                if let Some(f) = fold {
                    f.submit(i, std::mem::take(&mut out.cells), |acc, band| {
                        acc.absorb(band, ctx)
                    });
                }
                out
            })
            .collect();
        // Full-width bands of a row-major tile: the tile's arrays are the bands' arrays
        // one after the other.
        let mut joined = Banded {
            film: Film {
                x0: tile.x0,
                y0: tile.y0,
                width: tile.width,
                height: tile.height,
                pixels: Vec::with_capacity(tile.pixel_count() as usize),
                rejected: start.map_or(0, |f| f.rejected),
            },
            rays: 0,
            cv_sum: Vec::new(),
            cell_id: Vec::new(),
        };
        for o in outs {
            joined.film.pixels.extend_from_slice(&o.film.pixels);
            joined.film.rejected += o.film.rejected;
            joined.rays += o.rays;
            joined.cv_sum.extend_from_slice(&o.cv_sum);
            joined.cell_id.extend_from_slice(&o.cell_id);
        }
        joined
    }
}

/// Whether a tile of phase `kind` (with `table` in the render phase) traces `path`'s own pixel
/// samples: where the vertex policy would change nothing — no sample is controlled or trained
/// on (uncontrolled vertices are `path`'s whatever the base) — the same estimator without the policy's
/// per-vertex work and the extra rays a CV needs [Hua §8] (the `cell` layer then stays −1).
/// Farm workers run the same code: same bits.
fn traces_as_path(ctx: &CvContext<'_>, kind: PhaseKind, table: Option<&CoefficientTable>) -> bool {
    match kind {
        PhaseKind::Plain => true,
        PhaseKind::Train => !ctx.controls_any_vertex(),
        PhaseKind::Apply => !ctx.controls_any_vertex() || table.is_none_or(|t| t.coeffs.is_empty()),
    }
}

/// A job's training tiles, merged in row-major tile order ([`InOrder`]).
struct TrainFold {
    film: Film,
    rays: u64,
    stopped: u32,
    dropped: u32,
    /// The tiles' tables merged so far (`None` before the first).
    table: Option<AccumulatorTable>,
    /// The first error in tile order; the tiles after it are not added.
    error: Option<RenderError>,
    /// Seconds spent merging (CV overhead outside the sample loops).
    seconds: f64,
}

impl TrainFold {
    /// Nothing merged yet: the job's `film` so far.
    fn new(film: Film) -> Self {
        Self {
            film,
            rays: 0,
            stopped: 0,
            dropped: 0,
            table: None,
            error: None,
            seconds: 0.0,
        }
    }

    /// Adds the next tile.
    fn add(&mut self, tile: Result<TrainTile, RenderError>) {
        let t0 = Instant::now();
        self.merge(tile);
        self.seconds += t0.elapsed().as_secs_f64();
    }

    /// [`Self::add`] without the timing.
    fn merge(&mut self, tile: Result<TrainTile, RenderError>) {
        if self.error.is_some() {
            return;
        }
        let o = match tile {
            Ok(o) => o,
            Err(e) => {
                self.error = Some(e);
                return;
            }
        };
        self.stopped += u32::from(o.stopped);
        self.dropped += u32::from(o.dropped);
        self.film.merge(&o.out.film);
        self.rays += o.out.rays;
        match &mut self.table {
            None => self.table = Some(o.cells),
            Some(t) => {
                if t.merge_owned(o.cells).is_err() {
                    self.error = Some(RenderError::InvalidSetting {
                        field: "estimator",
                        reason: "training accumulators of different layouts",
                    });
                }
            }
        }
    }
}

/// The image variance of a training tile's film, in the units of its cells' sums (see
/// [`AccumulatorTable::Moments`]): `Σ_pixels Σ_c w_p n_p/(n_p − 1) Σ (L − L̄)²` (each pixel's
/// [`Pixel::squared_deviations`](crate::film::Pixel::squared_deviations) over its `n_p`
/// samples, made unbiased: `n_p` times the sample variance, as the cells' sums are `n`
/// samples' worth, so a tile probed after 2 spp and a 16-spp tile give the same figure in
/// expectation), with `w_p = training_weight(1, surrogate_p)` — `1/(s_p + ε)²` with a
/// surrogate, else 1 — as a training sample of the pixel is weighted besides its throughput
/// [Hua eq. 25]. Pixels in row-major order, so the bits depend only on the film.
fn image_variance(film: &Film, image_width: u32, surrogate: Option<&[f64]>) -> f64 {
    let mut total = 0.0;
    for (row, y) in film
        .pixels
        .chunks(film.width.max(1) as usize)
        .zip(film.y0..)
    {
        for (p, x) in row.iter().zip(film.x0..) {
            let at = y as usize * image_width as usize + x as usize;
            let w = training_weight(1.0, surrogate.and_then(|s| s.get(at).copied()));
            let ss: f64 = p.squared_deviations().iter().map(|d| d.max(0.0)).sum();
            if p.count >= 2 {
                let n = p.count as f64;
                total += w * (n / (n - 1.0)) * ss;
            }
        }
    }
    if total.is_finite() { total } else { 0.0 }
}

/// One pixel in this many of a training tile enters [`split_half_gain`] (chosen by image
/// position, `(x + 3y) mod 8 = 0`, so every worker checks the same pixels): the check solves
/// its pixels twice, and a whole tile's worth would cost as much as the job's solve phase.
const SPLIT_CHECK_STRIDE: u32 = 8;

/// Whether pixel `(x, y)` enters [`split_half_gain`] (see [`SPLIT_CHECK_STRIDE`]).
fn split_checked(x: u32, y: u32) -> bool {
    (x + 3 * y).is_multiple_of(SPLIT_CHECK_STRIDE)
}

/// The split-half check of an `optimal_mis` training tile: the fraction of the squared
/// difference between the two halves' pixel estimates that the fits remove, each half's CV
/// fitted on the other half's samples (cross-fitting: no in-sample optimism), weighted per
/// channel by `1/(m² + ε)` with `m` the pixel's training mean (relMSE's weighting, ε = 0.01).
///
/// Why the halves: the variance a per-pixel fit removes is the iid per-sample variance of
/// the camera hit's direct light, but the plain estimate is a mean over the Sobol sampler's
/// stratified samples, whose error falls faster than that (docs/bench/README.md: 0.94–0.99×
/// at equal spp where the in-sample fit gains were 0.69–0.98). The two halves of the training
/// range (samples `0..n/2` and `n/2..n`, each a stratified set) are two estimates of the
/// pixel, so `E[(ȳ_A − ȳ_B)²]` is the error of a stratified half-estimate (with the halves'
/// covariance, which has the same sign for the plain and the controlled estimate), and the
/// same difference of the controlled estimates is what the fits make of it. A half's
/// controlled sum is its plain sum plus `n_h Σα − Σ_k α_k g_k` ([`CellCoefficients::summed_term`];
/// `n_h` = its NEE samples, one per controlled vertex, of weight 1 in `optimal_mis`). The
/// half fits have half the samples of the job's (`min_samples` halved too), so the check is
/// conservative. `None` when no checked pixel has both halves.
fn split_half_gain(
    ctx: &CvContext<'_>,
    policy: &SolvePolicy,
    first_cells: &TileCells,
    second_cells: &TileCells,
    first: &Film,
    film: &Film,
) -> Option<f64> {
    const EPS: f64 = 0.01;
    let half = policy.for_half();
    // The change a half's samples get from coefficients fitted on the other half.
    let change = |acc: Option<&CellAccumulator>, other: Option<&CellAccumulator>| {
        let (Some(acc), Some(other)) = (acc, other) else {
            return [0.0; 3];
        };
        let co = estimators::solve::solve(other, &half);
        if co.is_fallback() {
            return [0.0; 3];
        }
        let n = acc.technique_sums().0;
        let (a, t) = (co.alpha_sum(), co.summed_term(acc));
        [0, 1, 2].map(|c| n * a[c] - t[c])
    };
    let (mut plain, mut controlled) = (0.0f64, 0.0f64);
    let mut any = false;
    for y in film.y0..film.y0 + film.height {
        for x in film.x0..film.x0 + film.width {
            if !split_checked(x, y) {
                continue;
            }
            let (pa, pt) = (first.pixel(x, y), film.pixel(x, y));
            let (na, nt) = (pa.count, pt.count);
            if na == 0 || nt <= na {
                continue;
            }
            let (na, nb, nt) = (na as f64, (nt - na) as f64, nt as f64);
            let key = y * ctx.rs.width + x;
            let (a, b) = (first_cells.moments(key), second_cells.moments(key));
            let (da, db) = (change(a, b), change(b, a));
            for c in 0..3 {
                let d_plain = pa.sum[c] / na - (pt.sum[c] - pa.sum[c]) / nb;
                let d_cv = d_plain + da[c] / na - db[c] / nb;
                let m = pt.sum[c] / nt;
                let w = 1.0 / (m * m + EPS);
                if (w * d_plain * d_plain).is_finite() && (w * d_cv * d_cv).is_finite() {
                    plain += w * d_plain * d_plain;
                    controlled += w * d_cv * d_cv;
                    any = true;
                }
            }
        }
    }
    (any && plain > 0.0).then(|| 1.0 - controlled / plain)
}

/// Training cells (a tile's, or none) as a table keyed by cell (of the job's kind, also when
/// empty), with the tile's image variance for moments. `cells` has no pending log: a tile's
/// cells are bands absorbed in order ([`InOrderFold`]), their logs added on the way.
fn cells_table(kind: Kind, cells: TileCells, image: f64) -> AccumulatorTable {
    debug_assert!(cells.log.is_empty(), "a table would drop logged samples");
    match kind {
        Kind::PerLight => {
            let mut m = BTreeMap::new();
            for (k, a) in cells.cells {
                if let CellAcc::Mean(a) = a {
                    m.insert(u64::from(k), a);
                }
            }
            AccumulatorTable::Mean(m, Some(image))
        }
        _ => {
            let mut m = BTreeMap::new();
            for (k, a) in cells.cells {
                if let CellAcc::Moments(a) = a {
                    m.insert(u64::from(k), a);
                }
            }
            AccumulatorTable::Moments(m, Some(image))
        }
    }
}

/// What one tile of a phase produced (internal).
struct TileOut {
    film: Film,
    rays: u64,
    cells: TileCells,
    cv_sum: Vec<[f64; 3]>,
    cell_id: Vec<f32>,
}

/// Renders `samples` of `tile`, adding them to `start` (the tile's film of earlier samples,
/// so that every pixel sums all its samples in index order) or to a new film.
fn run_tile(
    ctx: &CvContext<'_>,
    tile: TileRect,
    samples: Range<u32>,
    input: PhaseInput<'_>,
    start: Option<Film>,
) -> TileOut {
    let PhaseInput {
        kind,
        table,
        surrogate,
        pixels,
    } = input;
    let rs = ctx.rs;
    let st = &ctx.st;
    let mut film =
        start.unwrap_or_else(|| Film::new_rect(tile.x0, tile.y0, tile.width, tile.height));
    let mut cells = TileCells::default();
    if kind == PhaseKind::Train {
        cells.log = take_log();
    }
    let n = tile.pixel_count() as usize;
    let mut cv_sum = vec![[0.0f64; 3]; if kind == PhaseKind::Apply { n } else { 0 }];
    let mut cell_id = vec![-1.0f32; if kind == PhaseKind::Apply { n } else { 0 }];
    let mut rays = 0u64;
    let mut i = 0usize;
    let plain_path = traces_as_path(ctx, kind, table);
    for y in tile.y0..tile.y0 + tile.height {
        for x in tile.x0..tile.x0 + tile.width {
            if !pixels.includes(x, y) {
                i += 1;
                continue;
            }
            let pixel = y * rs.width + x;
            let sur = surrogate.map(|s| s[pixel as usize]);
            let mut rejected = 0u64;
            for s in samples.clone() {
                if plain_path {
                    // Exactly `path`'s pixel sample (same sampler state and numbers).
                    let sample = super::path::sample_pixel(rs, st, x, y, s);
                    rays += u64::from(sample.rays);
                    let px = film.pixel_mut(x, y);
                    if sample.radiance.is_finite() {
                        px.add(sample.radiance, sample.albedo, sample.normal);
                    } else {
                        px.add(Vec3::ZERO, sample.albedo, sample.normal);
                        rejected += 1;
                    }
                    continue;
                }
                let mut sampler = Sampler::of_kind(st.sampler, st.seed, pixel, s);
                let ray = super::path::camera_ray(rs, &mut sampler, x, y);
                let phase = match (kind, table) {
                    (PhaseKind::Train, _) => Phase::Train(&mut cells),
                    (PhaseKind::Apply, Some(t)) => Phase::Apply(t),
                    _ => Phase::Plain,
                };
                let mut pol = Policy {
                    ctx,
                    phase,
                    pixel,
                    surrogate: sur,
                    cv_delta: Vec3::ZERO,
                    first_cell: None,
                    keeps_first_cell: kind == PhaseKind::Apply && cell_id[i] < 0.0,
                    cell: None,
                    slot: None,
                    half: (kind == PhaseKind::Train && ctx.halves).then_some(s & 1),
                };
                let sample = super::path::trace(rs, st, ray, &mut sampler, &mut pol);
                rays += u64::from(sample.rays);
                let px = film.pixel_mut(x, y);
                if sample.radiance.is_finite() {
                    px.add(sample.radiance, sample.albedo, sample.normal);
                    if kind == PhaseKind::Apply {
                        let d = pol.cv_delta;
                        if d.is_finite() {
                            for c in 0..3 {
                                cv_sum[i][c] += f64::from(d[c]);
                            }
                        }
                    }
                } else {
                    px.add(Vec3::ZERO, sample.albedo, sample.normal);
                    rejected += 1;
                }
                // The `cell` layer: the first cell a sample of the pixel found.
                if pol.keeps_first_cell
                    && let Some(c) = pol.first_cell
                {
                    cell_id[i] = c as f32;
                }
            }
            film.rejected += rejected;
            i += 1;
        }
    }
    TileOut {
        film,
        rays,
        cells,
        cv_sum,
        cell_id,
    }
}

/// Runs `f` over `tiles` on `pool` in parallel, returning outputs in tile order and ticking
/// `progress` with the samples of each finished tile.
fn par_tiles<T: Send>(
    pool: &rayon::ThreadPool,
    tiles: &[TileRect],
    samples: &Range<u32>,
    progress: &(dyn Fn(u64) + Sync),
    f: impl Fn(TileRect) -> T + Sync,
) -> Vec<T> {
    pool.install(|| {
        tiles
            .par_iter()
            .map(|&t| {
                let out = f(t);
                progress(t.pixel_count() * u64::from(samples.end - samples.start));
                out
            })
            .collect()
    })
}

/// Runs every phase of `settings.estimator` in-process and returns the final film (all
/// samples of all phases), its stats and the estimator report. Estimators without phases
/// (`path`, `ocv`) and CV jobs that control no vertex (rendered as `path`) go through
/// [`crate::tile::render_image`] and get a report without phases.
/// `progress(done, total)` counts samples over all phases.
///
/// The phases go through [`CvJob`] exactly as on the farm: surrogate and render tiles of
/// `opts.tile_size` over their whole sample range, training tiles of [`TRAIN_TILE`],
/// accumulators merged in row-major training-tile order, [`AccumulatorTable::solve`].
pub fn render_estimator_image(
    scene: &RenderScene,
    settings: &RenderSettings,
    opts: &RenderOptions,
    progress: &(dyn Fn(u64, u64) + Sync),
) -> Result<(Film, RenderStats, EstimatorReport), RenderError> {
    let start = Instant::now();
    let rs = scene;
    let job = CvJob::new(rs, settings)?;
    // A CV job that controls no vertex (e.g. `cms` at depth 2 with `min_depth` 1) *is*
    // `path`, whatever its base: one render phase with `path`'s bits, as on the farm
    // ([`PhasedEstimator::phases`]). `path`'s own driver renders it, without the CV driver's
    // banded tiles and per-tile layers (≈ 4 % of CPU time on colour-lamp at depth 2).
    let plain = job.as_ref().is_some_and(|j| !j.controls_any_vertex());
    let job = match job {
        Some(j) if !plain => j,
        _ => {
            let st = RenderSettings {
                estimator: if plain {
                    Estimator::Path
                } else {
                    settings.estimator
                },
                ..*settings
            };
            let (film, stats) = crate::tile::render_image(rs, &st, opts, progress)?;
            let report = EstimatorReport {
                estimator: estimator_name(&settings.estimator).to_string(),
                render_spp: settings.spp,
                lights: rs.lights.len() as u32,
                effects: rs
                    .techniques(settings)
                    .into_iter()
                    .map(String::from)
                    .collect(),
                phases: PhaseTimings {
                    render: stats.seconds,
                    ..PhaseTimings::default()
                },
                ..EstimatorReport::default()
            };
            return Ok((film, stats, report));
        }
    };
    let ph = job.phases().clone();
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(opts.threads)
        .build()
        .map_err(|e| RenderError::ThreadPool(e.to_string()))?;
    let total = u64::from(rs.width) * u64::from(rs.height) * u64::from(settings.spp);
    let done = AtomicU64::new(0);
    let tick = |n: u64| {
        let d = done.fetch_add(n, Ordering::Relaxed) + n;
        progress(d, total);
    };
    let tiles = TileRect::grid(rs.width, rs.height, opts.tile_size);
    let mut film = Film::new(rs.width, rs.height);
    let mut rays = 0u64;
    let mut timings = PhaseTimings::default();
    let mut overhead = 0.0;

    // ---- surrogate [Hua §4.2.1, §6.1] ----
    let t0 = Instant::now();
    let mut surrogate: Option<Vec<f64>> = None;
    if job.needs_surrogate() {
        // (Without a controllable vertex the surrogate would weigh no training sample: the
        // samples are rendered, the denoise is skipped — same bits.)
        let outs = par_tiles(&pool, &tiles, &ph.surrogate, &tick, |t| {
            job.surrogate_tile(t, ph.surrogate.clone())
        });
        for o in &outs {
            film.merge(&o.film);
            rays += o.rays;
        }
        let td = Instant::now();
        if job.controls_any_vertex() {
            // The film holds the surrogate's samples alone so far.
            surrogate = Some(surrogate_image(
                &film_moments(&film),
                rs.width as usize,
                rs.height as usize,
            ));
        }
        overhead += td.elapsed().as_secs_f64();
    }
    timings.surrogate = t0.elapsed().as_secs_f64();

    // ---- train ----
    let t0 = Instant::now();
    // Each tile's table is merged into the job's as soon as the tiles before it are, and
    // dropped: the job holds its merged table and the tiles in flight, not every tile's.
    let train_tiles = TileRect::grid(rs.width, rs.height, TRAIN_TILE);
    let fold = InOrder::new(TrainFold::new(film));
    pool.install(|| {
        train_tiles.par_iter().enumerate().for_each(|(i, &t)| {
            let out = job.train_tile(t, ph.train.clone(), surrogate.as_deref());
            tick(t.pixel_count() * ph.train.len() as u64);
            fold.submit(i, out, TrainFold::add);
        })
    });
    let trained = fold.finish().ok_or(RenderError::InvalidSetting {
        field: "estimator",
        reason: "a training tile's merge panicked",
    })?;
    timings.train = t0.elapsed().as_secs_f64();
    if let Some(e) = trained.error {
        return Err(e);
    }
    film = trained.film;
    rays += trained.rays;
    overhead += trained.seconds;
    let training_tiles = train_tiles.len() as u32;
    let (training_tiles_stopped, training_tiles_dropped) = (trained.stopped, trained.dropped);

    // ---- solve ----
    let t0 = Instant::now();
    let merged = trained
        .table
        .unwrap_or_else(|| cells_table(job.ctx.kind, TileCells::default(), 0.0));
    let solved = merged.solve(&job.solve_policy(), opts.threads.max(1));
    let table = job.coefficient_table(&solved.coefficients)?;
    let layout = job.layout();
    let mut report = EstimatorReport {
        estimator: estimator_name(&settings.estimator).to_string(),
        surrogate_spp: ph.surrogate.len() as u32,
        training_spp: ph.train.len() as u32,
        render_spp: ph.render.len() as u32,
        training_tiles,
        training_tiles_stopped,
        training_tiles_dropped,
        grid_resolution: job.grid_resolution(),
        grid_levels: job.ctx.grid.levels(),
        cells: solved.coefficients.len() as u64,
        lights: rs.lights.len() as u32,
        light_components: layout.partitions,
        overlapping_components: layout.overlapping,
        rejected_training_samples: solved.rejected,
        predicted_image_gain: solved.image_gain,
        predicted_fit_gain: solved.fit_gain,
        predicted_held_out_gain: solved.held_out_gain,
        predicted_held_out_share: solved.held_out_share,
        ..EstimatorReport::default()
    };
    for co in solved.coefficients.values() {
        match co.diagnostics().status {
            SolveStatus::Solved => report.cells_solved += 1,
            SolveStatus::Fallback(r) => {
                *report.cells_fallback.entry(format!("{r:?}")).or_insert(0) += 1;
            }
        }
    }
    timings.solve = t0.elapsed().as_secs_f64();
    overhead += timings.solve;

    // ---- render with the CV ----
    let t0 = Instant::now();
    let n = rs.width as usize * rs.height as usize;
    let mut cv_sum = vec![[0.0f64; 3]; n];
    let mut cell_id = vec![-1.0f32; n];
    if !ph.render.is_empty() {
        let outs = par_tiles(&pool, &tiles, &ph.render, &tick, |t| {
            job.render_tile(t, ph.render.clone(), &table)
        });
        let mut rfilm = Film::new(rs.width, rs.height);
        for (o, t) in outs.iter().zip(&tiles) {
            rfilm.merge(&o.out.film);
            rays += o.out.rays;
            let mut i = 0;
            for y in t.y0..t.y0 + t.height {
                for x in t.x0..t.x0 + t.width {
                    let p = (y * rs.width + x) as usize;
                    cv_sum[p] = o.cv_sum[i];
                    cell_id[p] = o.cell_id[i];
                    i += 1;
                }
            }
        }
        // Samples rendered with the CV weigh by their variance; a render phase traced as
        // `path` (no cell controlled) is merged plainly: the job then *is* `path`, bit for bit.
        if traces_as_path(&job.ctx, PhaseKind::Apply, Some(&table)) {
            film.merge(&rfilm);
        } else {
            report.uncontrolled_weight = combine_phase_films(&mut film, &rfilm, &mut cv_sum);
        }
    }
    timings.render = t0.elapsed().as_secs_f64();

    let cv_layer = cv_sum
        .iter()
        .zip(&film.pixels)
        .map(|(s, p)| s.map(|v| (v / p.count.max(1) as f64) as f32))
        .collect();
    report.layers = vec![
        FilmLayer {
            name: "cv_term",
            data: cv_layer,
        },
        FilmLayer {
            name: "cell",
            data: cell_id.into_iter().map(|c| [c; 3]).collect(),
        },
    ];
    report.phases = timings;
    report.cv_overhead_seconds = overhead;
    report.effects = job.effects();
    let stats = RenderStats {
        samples: film.sample_count(),
        rays,
        seconds: start.elapsed().as_secs_f64(),
    };
    Ok((film, stats, report))
}

/// The image of a phased job, in place: `film` holds `path`'s samples (surrogate and
/// training) and becomes their combination with `controlled`'s (the render phase with the
/// CV) by one image-wide inverse-variance weight
/// ([`estimators::composite::phase_weight`], then
/// [`estimators::composite::combine_phases`] per pixel, in row-major order: the farm's
/// assembly combines them with the same arithmetic, so the bits agree). Each pixel's
/// render-phase CV sum in `cv_sum` is scaled to its share of the combined mean
/// ([`controlled_scale`]). Returns the weight of `film`'s samples (`None`: merged plainly).
/// Both films cover the image; `cv_sum` has a value per pixel.
///
/// Two passes over the pixels and no copy of the image (at 1920×1080 copying both films'
/// sums out, combining them into a third copy and a new film took ≈ 2 s of one thread).
pub fn combine_phase_films(
    film: &mut Film,
    controlled: &Film,
    cv_sum: &mut [[f64; 3]],
) -> Option<f64> {
    debug_assert_eq!(film.pixels.len(), controlled.pixels.len());
    debug_assert_eq!(film.pixels.len(), cv_sum.len());
    let w = phase_weight(
        film.pixels
            .iter()
            .zip(&controlled.pixels)
            .map(|(u, c)| (u.moments(), c.moments())),
    );
    for ((u, c), s) in film.pixels.iter_mut().zip(&controlled.pixels).zip(cv_sum) {
        let (um, cm) = (u.moments(), c.moments());
        let k = controlled_scale(&um, &cm, w);
        *s = s.map(|v| v * k);
        *u = Pixel::from(combine_phases(&um, &cm, w));
    }
    film.rejected += controlled.rejected;
    w
}

impl CvJob<'_> {
    /// Techniques simulated and CV components built (for stats).
    pub fn effects(&self) -> Vec<String> {
        let rs = self.ctx.rs;
        let mut effects: Vec<String> = rs
            .techniques(&self.ctx.st)
            .into_iter()
            .map(String::from)
            .collect();
        if self.ctx.layout.partitions > 0 {
            effects.push(format!("cv_lights:{}", self.ctx.layout.partitions));
        }
        if rs.lights.env_light().is_some() {
            effects.push("cv_env".into());
        }
        if self.ctx.layout.overlapping > 0 {
            effects.push("cv_bsdf".into());
        }
        effects
    }
}

fn estimator_name(e: &Estimator) -> &'static str {
    match e {
        Estimator::Path => "path",
        Estimator::Cms(_) => "cms",
        Estimator::PerLightCv(_) => "per_light_cv",
        Estimator::OptimalMis(_) => "optimal_mis",
        #[allow(unreachable_patterns)]
        _ => "other",
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::integrator::{BsdfTechnique, LightTechnique};

    #[test]
    fn image_variance_weighs_each_pixel_by_its_own_surrogate() {
        // A 2×1 tile at (2, 1) of a 4×3 image: pixel (2, 1) gets samples 1, 3 (squared
        // deviations 1 + 1 per channel, times n/(n − 1) = 2), pixel (3, 1) gets 0, 4, 8 in red
        // only (16 + 0 + 16, times 3/2).
        let mut film = Film::new_rect(2, 1, 2, 1);
        for v in [1.0, 3.0] {
            film.pixel_mut(2, 1)
                .add(Vec3::splat(v), Vec3::ZERO, Vec3::Z);
        }
        for v in [0.0, 4.0, 8.0] {
            film.pixel_mut(3, 1)
                .add(Vec3::new(v, 0.0, 0.0), Vec3::ZERO, Vec3::Z);
        }
        assert_eq!(image_variance(&film, 4, None), 3.0 * 4.0 + 48.0);
        let mut surrogate = vec![f64::NAN; 12];
        surrogate[4 + 2] = 0.99; // w = 1
        surrogate[4 + 3] = 1.99; // w = 1/4
        let want = 12.0 + 48.0 / 4.0;
        let got = image_variance(&film, 4, Some(&surrogate));
        assert!((got - want).abs() < 1e-12, "{got} vs {want}");
        // A pixel with one sample has no spread to count.
        let mut one = Film::new_rect(0, 0, 1, 1);
        one.pixel_mut(0, 0).add(Vec3::ONE, Vec3::ZERO, Vec3::Z);
        assert_eq!(image_variance(&one, 4, None), 0.0);
    }

    /// `scenes/<name>` at `width × height`, with `cms` (defaults) at 24 spp, depth 5.
    fn cms_scene(name: &str, width: u32, height: u32, seed: u64) -> (RenderScene, RenderSettings) {
        let cms = Estimator::Cms(super::super::cms::CmsOptions::default());
        cv_scene(name, width, height, seed, cms)
    }

    /// Scene `name` of `scenes/` at `width × height`, depth 5, 24 spp, with `estimator`.
    fn cv_scene(
        name: &str,
        width: u32,
        height: u32,
        seed: u64,
        estimator: Estimator,
    ) -> (RenderScene, RenderSettings) {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join(format!("../../scenes/{name}/scene.json"));
        let mut scene = scene::load_file(&path).expect("scene loads").scene;
        scene.film.width = width;
        scene.film.height = height;
        let st = RenderSettings {
            spp: 24,
            seed,
            max_depth: 5,
            estimator,
            ..RenderSettings::from_scene(&scene)
        };
        (RenderScene::new(&scene, &st).unwrap(), st)
    }

    /// A band whose log fills up adds it to its own cells and goes on logging; the tile then
    /// takes the band's cells and the rest of its log. Nothing is lost or counted twice (every
    /// cell's sample count is exact), the sums agree with the unspilled ones to rounding, and
    /// the spilled table's bits do not depend on the thread count.
    #[test]
    fn a_spilled_training_log_keeps_every_sample() {
        let (rs, st) = cms_scene("many-lights", 32, 32, 5);
        // Every training sample recorded: no probe may stop the tile (a 32 × 32 tile's 2 spp
        // probe is no measure of the job's fits).
        let st = RenderSettings {
            estimator: Estimator::Cms(super::super::cms::CmsOptions {
                min_image_gain: None,
                min_fit_gain: None,
                ..Default::default()
            }),
            ..st
        };
        let mut job = CvJob::new(&rs, &st).unwrap().expect("a phased estimator");
        let tile = TileRect {
            x0: 0,
            y0: 0,
            width: 32,
            height: 32,
        };
        let train = job.phases().train.clone();
        let surrogate = vec![0.25; 32 * 32];
        let table = |job: &CvJob<'_>, threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            match pool
                .install(|| job.train_tile(tile, train.clone(), Some(&surrogate)))
                .unwrap()
                .cells
            {
                AccumulatorTable::Moments(m, _) => m,
                AccumulatorTable::Mean(..) => unreachable!("cms trains moments"),
            }
        };
        let whole = table(&job, 1);
        // A band of 2 × 32 pixels × 16 training samples logs thousands of records.
        job.ctx.train_log_max = 1000;
        let spilled = table(&job, 1);
        assert_eq!(
            estimators::table::encode_table(&table(&job, 3)),
            estimators::table::encode_table(&spilled)
        );
        assert_eq!(
            whole.keys().collect::<Vec<_>>(),
            spilled.keys().collect::<Vec<_>>()
        );
        let mut differs = false;
        for (k, a) in &whole {
            let b = &spilled[k];
            assert_eq!(a.samples(), b.samples(), "cell {k}");
            let (wa, wb) = (a.weight_sum(), b.weight_sum());
            assert!(
                (wa - wb).abs() <= 1e-12 * wa.abs().max(1e-300),
                "cell {k}: {wa} vs {wb}"
            );
            differs |= wa.to_bits() != wb.to_bits();
        }
        assert!(whole.values().map(|a| a.samples()).sum::<u64>() > 10_000);
        // The spill really happened: some sums were associated differently.
        assert!(differs, "no sum changed: the log never spilled");
    }

    /// A render tile without coefficients (a switched-off job) is traced by `path`'s own
    /// driver: the same film, to the bit, and the same rays as the banded CV driver gives,
    /// on 1 and 3 threads and for a tile whose height is not a multiple of the bands'.
    #[test]
    fn a_tile_without_coefficients_has_the_banded_drivers_bits() {
        let (rs, st) = cms_scene("veach-mis", 40, 29, 3);
        let job = CvJob::new(&rs, &st).unwrap().expect("a phased estimator");
        let table = job.coefficient_table(&BTreeMap::new()).unwrap();
        assert!(table.coeffs.is_empty());
        let tile = TileRect {
            x0: 3,
            y0: 2,
            width: 37,
            height: 27,
        };
        let render = job.phases().render.clone();
        let input = PhaseInput {
            kind: PhaseKind::Apply,
            table: Some(&table),
            surrogate: None,
            pixels: Pixels::All,
        };
        let banded = Banded::run(&job.ctx, tile, render.clone(), input, None, None);
        for threads in [1, 3] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            let t = pool.install(|| job.render_tile(tile, render.clone(), &table));
            assert!(
                t.out.film.to_bits() == banded.film.to_bits(),
                "{threads} threads"
            );
            assert_eq!(t.out.film.rejected, banded.film.rejected);
            assert_eq!(t.out.rays, banded.rays);
            assert_eq!(t.cv_sum, banded.cv_sum);
            assert_eq!(
                t.cell_id.iter().map(|c| c.to_bits()).collect::<Vec<_>>(),
                banded
                    .cell_id
                    .iter()
                    .map(|c| c.to_bits())
                    .collect::<Vec<_>>()
            );
            assert_eq!(
                (
                    t.out.film.x0,
                    t.out.film.y0,
                    t.out.film.width,
                    t.out.film.height
                ),
                (tile.x0, tile.y0, tile.width, tile.height)
            );
        }
        assert!(banded.rays > 0);
    }

    #[test]
    fn grid_cells_cover_the_bounds_and_clamp_outside() {
        let g = Grid::new(
            (Vec3::ZERO, Vec3::new(2.0, 1.0, 1.0)),
            Some([4, 2, 3]),
            0,
            8,
            8,
        )
        .unwrap();
        assert_eq!(g.cells(), 24);
        assert_eq!(g.cell(Vec3::splat(0.01)), 0);
        assert_eq!(g.cell(Vec3::new(1.99, 0.99, 0.99)), 23);
        assert_eq!(g.cell(Vec3::splat(-5.0)), 0);
        assert_eq!(g.cell(Vec3::splat(50.0)), 23);
        assert_eq!(g.cell(Vec3::splat(f32::NAN)), 0);
        assert!(Grid::new((Vec3::ZERO, Vec3::ONE), Some([2048, 2048, 1]), 0, 8, 8).is_err());
        // Adaptive: longest axis max(w, h)/16 clamped to ≥ 8, others proportional.
        let a = Grid::new((Vec3::ZERO, Vec3::new(4.0, 2.0, 0.0)), None, 0, 256, 128).unwrap();
        assert_eq!(a.resolution(), [16, 8, 1]);
        // Empty bounds (no geometry) still give a valid one-cell-per-axis grid.
        let e = Grid::new(
            (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)),
            Some([1, 1, 1]),
            0,
            4,
            4,
        )
        .unwrap();
        assert_eq!(e.cell(Vec3::ZERO), 0);
    }

    /// The slot map finds every inserted key's slot and no other key, at every fill up to
    /// its capacity (clustered and scattered keys, key 0 and the largest).
    #[test]
    fn slot_map_finds_exactly_its_keys() {
        let mut state = 0x9e37_79b9_7f4a_7c15_u64;
        let mut next = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        };
        for len in [0usize, 1, 7, 8, 100, 4096] {
            let mut keys: Vec<u32> = (0..len)
                .map(|i| match i % 3 {
                    0 => i as u32,
                    1 => (next() as u32) | 1,
                    _ => u32::MAX - 1 - i as u32,
                })
                .collect();
            keys.sort_unstable();
            keys.dedup();
            let mut map = SlotMap::with_capacity(keys.len());
            let want: HashMap<u32, u32> = keys.iter().map(|&k| (k, next() as u32 >> 1)).collect();
            for &k in &keys {
                map.insert(k, want[&k]);
            }
            for &k in &keys {
                assert_eq!(map.get(k), Some(want[&k]));
            }
            for _ in 0..10_000 {
                let k = next() as u32;
                assert_eq!(map.get(k), want.get(&k).copied());
            }
        }
    }

    /// Subdivided cells: camera hits' indices are one per finest cell, deeper vertices' one
    /// per undivided cell, all below `cells`, and dividing an index by 9 per level gives the
    /// index of the containing cell of the grid with fewer subdivisions (the parent the
    /// table solve fits against, [`estimators::solve::SolvePolicy::levels`]).
    #[test]
    fn subdivided_cells_are_numbered_so_that_the_parent_is_the_index_over_9() {
        let bounds = (Vec3::new(-1.0, 0.0, 2.0), Vec3::new(3.0, 1.0, 4.5));
        let grids: Vec<Grid> = (0..=2)
            .map(|l| Grid::new(bounds, Some([3, 2, 5]), l, 8, 8).unwrap())
            .collect();
        assert_eq!(grids[2].resolution(), [12, 8, 20]);
        assert_eq!(grids[2].cells(), 3 * 2 * 5 * 81);
        let mut seen = std::collections::HashSet::new();
        let res = grids[2].resolution();
        for z in 0..res[2] {
            for y in 0..res[1] {
                for x in 0..res[0] {
                    // The centre of finest cell (x, y, z).
                    let t = (Vec3::new(x as f32, y as f32, z as f32) + 0.5)
                        / Vec3::new(res[0] as f32, res[1] as f32, res[2] as f32);
                    let p = bounds.0 + t * (bounds.1 - bounds.0);
                    let i = grids[2].cell(p);
                    assert!((i as usize) < grids[2].cells());
                    assert!(seen.insert(i), "{i} twice");
                    assert_eq!(i / 9, grids[1].cell(p), "{x} {y} {z}");
                    assert_eq!(i / 81, grids[0].cell(p), "{x} {y} {z}");
                    // A deeper vertex: its own child of the undivided cell, at every level.
                    let d = grids[2].undivided_cell(p);
                    assert!((d as usize) < grids[2].cells());
                    assert_eq!(d / 9, grids[1].undivided_cell(p));
                    assert_eq!(d / 81, grids[0].undivided_cell(p));
                    assert_eq!(grids[0].undivided_cell(p), grids[0].cell(p));
                    assert_ne!(d / 9, i / 9);
                }
            }
        }
        assert_eq!(seen.len(), 12 * 8 * 20);
        // Subdivisions count toward the index limit; the adaptive default stays within it.
        assert!(Grid::new(bounds, Some([64, 64, 64]), 2, 8, 8).is_ok());
        assert!(Grid::new(bounds, Some([1024, 1024, 1]), 3, 8, 8).is_err());
        assert!(Grid::new(bounds, Some([1, 1, 1]), MAX_GRID_LEVELS + 1, 8, 8).is_err());
        assert!(Grid::new(bounds, None, MAX_GRID_LEVELS + 1, 4096, 4096).is_err());
        let a = Grid::new(bounds, None, 4, 4096, 4096).unwrap();
        assert!(a.cells() as u64 <= MAX_GRID_INDICES);
        // The adaptive default stops at `ADAPTIVE_GRID_MAX_AXIS` cells on the longest axis
        // (a 2048-pixel image's `2048/16` would be 128), so even a cube-shaped scene with
        // the most levels stays within the index limit.
        let cube = (Vec3::ZERO, Vec3::ONE);
        let g = Grid::new(bounds, None, 2, 2048, 1024).unwrap();
        assert_eq!(g.resolution()[0] >> 2, ADAPTIVE_GRID_MAX_AXIS);
        let c = Grid::new(cube, None, MAX_GRID_LEVELS, 2048, 2048).unwrap();
        assert_eq!(c.resolution()[0] >> MAX_GRID_LEVELS, ADAPTIVE_GRID_MAX_AXIS);
        assert!((c.cells() as u64) <= MAX_GRID_INDICES);
        let undivided: u64 = c
            .resolution()
            .iter()
            .map(|&r| u64::from(r >> MAX_GRID_LEVELS))
            .product();
        assert!(undivided <= MAX_GRID_CELLS);
        // Below the cap, `max(width, height)/16` cells, at least 8.
        let small = Grid::new(cube, None, 2, 384, 256).unwrap();
        assert_eq!(small.resolution()[0] >> 2, 24);
        assert_eq!(Grid::new(cube, None, 0, 20, 20).unwrap().resolution()[0], 8);
    }

    /// The render phase's dense route ([`Policy::apply_dense`], `f32` rows) and the general
    /// one (the samples' `f64` records and [`CellCoefficients::cv_term`]) give the same
    /// controlled estimate and CV term to `f32` rounding, for every kind of vertex record:
    /// NEE sampled, failed or occluded, the BSDF sample traced, untraced, missing, a point
    /// mass, rouletted, hitting a light or not — for `cms` and for `per_light_cv` (the NEE
    /// sample alone controlled). The coefficients are `bfloat16` values, so both routes use
    /// the same `α`.
    #[test]
    fn the_dense_route_agrees_with_the_general_one() {
        for estimator in [
            Estimator::Cms(super::super::cms::CmsOptions::default()),
            Estimator::PerLightCv(super::super::per_light_cv::PerLightCvOptions::default()),
        ] {
            dense_route_agrees_with_the_general_one(estimator);
        }
    }

    fn dense_route_agrees_with_the_general_one(estimator: Estimator) {
        let (rs, st) = cv_scene("veach-mis", 8, 8, 1, estimator);
        let job = CvJob::new(&rs, &st).unwrap().expect("a phased estimator");
        let layout = job.ctx.layout;
        assert!(layout.partitions >= 2, "{layout:?}");
        let bf = |x: f64| f64::from(from_bf16(to_bf16(x as f32)));
        let partitions: Vec<(u32, [f64; 3])> = (0..layout.partitions)
            .map(|c| {
                let c64 = f64::from(c);
                (c, [bf(0.3 + c64), bf(-0.7 * c64), bf(0.11 * c64 - 0.2)])
            })
            .collect();
        let co = CellCoefficients::from_values(
            layout,
            job.ctx.color,
            &partitions,
            &vec![[0.625, -1.25, 0.0390625]; layout.overlapping as usize],
        )
        .unwrap();
        let key = 7;
        let dense = job
            .coefficient_table(&BTreeMap::from([(u64::from(key), co)]))
            .unwrap();
        assert!(dense.dense(0).is_some());
        let mut sparse = job
            .coefficient_table(&BTreeMap::from([(u64::from(key), dense.coeffs[0].clone())]))
            .unwrap();
        sparse.stride = 0;
        assert!(sparse.dense(0).is_none());
        let run = |table: &CoefficientTable, r: &VertexRecord| {
            let mut policy = Policy {
                ctx: &job.ctx,
                phase: Phase::Apply(table),
                pixel: 0,
                surrogate: None,
                cv_delta: Vec3::ZERO,
                first_cell: None,
                keeps_first_cell: false,
                cell: Some(key),
                slot: Some(0),
                half: None,
            };
            let out = policy.controlled_vertex(r);
            (out, policy.cv_delta)
        };
        let mut state = 0x9E37_79B9_7F4A_7C15u64;
        let mut u = move || {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1);
            ((state >> 40) as f32) / (1u64 << 24) as f32
        };
        let lights = layout.partitions;
        let (mut compared, mut nonzero) = (0, 0);
        for i in 0..400u32 {
            let light = i % lights;
            let nee = match i % 4 {
                0 => None,
                n => Some(LightTechnique {
                    light,
                    pdf_light: 0.05 + 3.0 * u(),
                    pdf_bsdf: if n == 3 { 0.0 } else { 2.0 * u() },
                    value: Vec3::new(u(), 2.0 * u(), 0.5 * u()),
                    visible: n != 2,
                }),
            };
            let bsdf = match (i / 4) % 5 {
                0 => None,
                n => Some(BsdfTechnique {
                    pdf_bsdf: 0.1 + 4.0 * u(),
                    pdf_light: if n == 2 { 0.0 } else { 2.0 * u() },
                    weight: Vec3::new(u(), u(), u()),
                    emitted: if n == 2 {
                        Vec3::ZERO
                    } else {
                        Vec3::splat(1.0 + 5.0 * u())
                    },
                    hit_light: (n != 2).then_some((i / 3) % lights),
                    delta: n == 4,
                    traced: n != 1,
                    rr_q: if i % 3 == 0 { 1.0 } else { 0.25 + 0.7 * u() },
                }),
            };
            let r = VertexRecord {
                throughput: Vec3::new(0.5 + u(), 1.0, 0.25 + u()),
                light: nee,
                nee_light: Some(light),
                bsdf,
            };
            let (a, da) = run(&dense, &r);
            let (b, db) = run(&sparse, &r);
            for (x, y) in [(a, b), (da, db)] {
                let tol = 2e-5 * (1.0 + y.abs().max_element());
                assert!((x - y).abs().max_element() <= tol, "record {i}: {x} vs {y}");
                nonzero += usize::from(y.abs().max_element() > 0.1);
            }
            compared += 1;
        }
        assert_eq!(compared, 400);
        assert!(nonzero > 600, "{nonzero}");
    }

    /// A dense row's `Σα` is the sum of its `bfloat16`-rounded `α` (what the dense route
    /// subtracts terms of), to `f64` precision through the `f32` hi/lo pair.
    #[test]
    fn dense_rows_sum_their_rounded_alpha() {
        let layout = ComponentLayout::new(5, 1).unwrap();
        // Coefficients that are not `bfloat16` values: `Σα` is the sum of the rounded `α`.
        let odd = CellCoefficients::from_values(
            layout,
            ColorMode::Rgb,
            &[(0, [0.1, 1e-9, 3.3]), (3, [1e7 + 0.3, -0.7, 0.2])],
            &[[1.0 / 3.0, -2.0 / 3.0, 0.9]],
        )
        .unwrap();
        let mut t = CoefficientTable {
            slot: SlotMap::one(0, 0),
            coeffs: Vec::new(),
            rows: Vec::new(),
            sums: Vec::new(),
            stride: ROW_HEAD + 3 * 5,
        };
        t.push(&odd);
        let r32 = |a: [f64; 3]| a.map(|v| f64::from(from_bf16(to_bf16(v as f32))));
        let mut want = [0.0f64; 3];
        for a in [
            r32(odd.alpha_overlapping(0)),
            r32(odd.alpha_partition(0)),
            r32(odd.alpha_partition(3)),
        ] {
            for c in 0..3 {
                want[c] += a[c];
            }
        }
        let h = t.sums[0];
        let got = [0, 1, 2].map(|c| f64::from(h[c]) + f64::from(h[3 + c]));
        for c in 0..3 {
            assert!(
                (got[c] - want[c]).abs() <= 1e-14 * want[c].abs(),
                "{got:?} {want:?}"
            );
        }
        assert_ne!(
            got,
            odd.alpha_sum(),
            "the f64 sum differs from the rounded one"
        );
    }

    #[test]
    fn bfloat16_rounds_to_nearest_even_and_stays_finite() {
        // Representable values are exact; others round to the nearest of the two neighbours
        // (8 mantissa bits), ties to even; a finite value never becomes infinite.
        for x in [0.0f32, -0.0, 1.0, -2.5, 0.0009765625, 3.0e38, -1.0e-30] {
            let r = from_bf16(to_bf16(x));
            assert!(r.is_finite());
            assert!((r - x).abs() <= x.abs() * 2f32.powi(-8), "{x} -> {r}");
        }
        // bfloat16 spacing at 1 is 2⁻⁷: 1 + 2⁻⁸ is a tie (down to the even 1), 1 + 3·2⁻⁸ a
        // tie between 1 + 2⁻⁷ (odd) and 1 + 2⁻⁶ (even); off-tie values go to the nearest.
        let bf = |x: f32| from_bf16(to_bf16(x));
        assert_eq!(bf(1.0 + 2f32.powi(-8)), 1.0);
        assert_eq!(bf(1.0 + 3.0 * 2f32.powi(-8)), 1.0 + 2f32.powi(-6));
        assert_eq!(
            bf(1.0 + 2f32.powi(-8) + 2f32.powi(-12)),
            1.0 + 2f32.powi(-7)
        );
        assert_eq!(bf(1.0 + 2f32.powi(-9)), 1.0);
        assert_eq!(
            from_bf16(to_bf16(f32::MAX)),
            f32::from_bits(f32::MAX.to_bits() & 0xffff_0000)
        );
        assert!(from_bf16(to_bf16(f32::INFINITY)).is_infinite());
        // Relative error over many values: at most half an ulp of 8 bits, 2⁻⁸ of the value.
        let mut x = 1.0e-20f32;
        while x < 1.0e20 {
            let r = from_bf16(to_bf16(x));
            assert!((r - x).abs() <= x * 2f32.powi(-8) * 1.0001, "{x} -> {r}");
            x *= 1.37;
        }
    }

    #[test]
    fn normal_bins_are_distinct_per_axis_and_sign() {
        let bins: Vec<u32> = [Vec3::X, -Vec3::X, Vec3::Y, -Vec3::Y, Vec3::Z, -Vec3::Z]
            .into_iter()
            .map(normal_bin)
            .collect();
        assert_eq!(bins, vec![0, 1, 2, 3, 4, 5]);
        assert!(normal_bin(Vec3::splat(f32::NAN)) < NORMAL_BINS);
    }

    /// The branch-free cell index agrees with the plain `if` chains it replaced (kept here as
    /// the oracle) on random points and normals, ties, signed zeros, infinities and NaNs.
    #[test]
    fn branch_free_cell_index_matches_the_plain_one() {
        fn bin_oracle(n: Vec3) -> u32 {
            let a = n.abs();
            let (axis, v) = if a.x >= a.y && a.x >= a.z {
                (0, n.x)
            } else if a.y >= a.z {
                (1, n.y)
            } else {
                (2, n.z)
            };
            2 * axis + u32::from(v < 0.0)
        }
        fn cell_oracle(g: &Grid, p: Vec3) -> u32 {
            let q = (p - Vec3::from(g.lo)) * Vec3::from(g.scale);
            let c = |v: f32, r: u32| {
                let v = if v < f32::INFINITY { v } else { 0.0 };
                (v as u32).min(r - 1)
            };
            let (x, y, z) = (c(q.x, g.res[0]), c(q.y, g.res[1]), c(q.z, g.res[2]));
            x + g.res[0] * (y + g.res[1] * z)
        }
        let g = Grid::new(
            (Vec3::splat(-1.0), Vec3::new(3.0, 1.0, 2.0)),
            Some([7, 3, 5]),
            0,
            8,
            8,
        )
        .unwrap();
        let special = [
            0.0,
            -0.0,
            1.0,
            -1.0,
            0.5,
            -0.5,
            1e-30,
            1e30,
            -1e30,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
        ];
        let mut state = 0x1234_5678_u64;
        let mut next = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            let u = (state >> 40) as f32 / (1u64 << 24) as f32;
            if state >> 60 == 0 {
                special[(state >> 32) as usize % special.len()]
            } else {
                8.0 * u - 4.0
            }
        };
        // The undivided cell, computed at its own resolution, against the finest cell's
        // coordinates shifted by `levels` (the subdivided grids of glossy camera hits).
        let subdivided: Vec<Grid> = (0..=MAX_GRID_LEVELS)
            .map(|levels| {
                Grid::new(
                    (Vec3::new(-1.0, -0.3, 0.1), Vec3::new(3.0, 1.0, 2.0)),
                    Some([7, 3, 5]),
                    levels,
                    8,
                    8,
                )
                .unwrap()
            })
            .collect();
        let undivided_oracle = |g: &Grid, p: Vec3| {
            g.undivided_index(g.coords(p)) * g.undivided_stride + g.other_offset
        };
        let check = |v: Vec3| {
            assert_eq!(normal_bin(v), bin_oracle(v), "{v:?}");
            assert_eq!(g.cell(v), cell_oracle(&g, v), "{v:?}");
            for s in &subdivided {
                assert_eq!(
                    s.undivided_cell(v),
                    undivided_oracle(s, v),
                    "{v:?} {}",
                    s.levels
                );
            }
        };
        for _ in 0..200_000 {
            check(Vec3::new(next(), next(), next()));
        }
        for &a in &special {
            for &b in &special {
                for &c in &special {
                    check(Vec3::new(a, b, c));
                }
            }
        }
    }

    #[test]
    fn clusters_split_into_k_compact_groups() {
        let pts: Vec<(u32, Vec3)> = (0..100)
            .map(|i| (i, Vec3::new((i % 10) as f32, (i / 10) as f32, 0.0)))
            .collect();
        let mut out = Vec::new();
        split_clusters(pts, 7, &mut out);
        assert_eq!(out.len(), 7);
        let mut all: Vec<u32> = out.iter().flatten().copied().collect();
        all.sort_unstable();
        assert_eq!(all, (0..100).collect::<Vec<_>>());
        // More clusters than points: one point each.
        let mut few = Vec::new();
        split_clusters(vec![(0, Vec3::ZERO), (1, Vec3::ONE)], 5, &mut few);
        assert_eq!(few.len(), 2);
    }
}
