//! Options of the CV estimators and their phase plan: the one definition shared by the
//! renderer (`render::integrator::Estimator`), the wire format (`protocol::EstimatorSpec`)
//! and the coordinator's task plan.
//!
//! Every options struct is `serde(default, deny_unknown_fields)`: a misspelt option is an
//! error naming it, an absent one takes the default of the tables below. `validate`
//! returns the offending field and why.
//!
//! # Phases (DESIGN §1, [Hua §6.1])
//! A CV job splits the sample indices `0..spp` of every pixel into consecutive ranges
//! ([`PhaseSamples`]): surrogate `[0, s)` (1–2 spp for the relative-variance surrogate,
//! `cms` with `relative` only), train `[s, s+T)` (cell accumulators) and render
//! `[s+T, spp)` (with the solved coefficients). All samples of all phases stay in the image.
//! Training tiles have the fixed edge [`TRAIN_TILE`] and are never split in samples, so the
//! canonical merge order of their accumulators (row-major tiles) does not depend on the
//! job's tile size or on how many workers render them.

use std::ops::Range;

use serde::{Deserialize, Serialize};

use crate::cell::ColorMode;

/// Fixed tile edge of the training phase (canonical accumulator merge order). Every training
/// tile carries the accumulators of all cells its paths touch, and indirect bounces touch most
/// of the grid, so the volume a farm uploads, stores, decodes and merges scales with the tile
/// count (many-lights 256², 64 lights: 32-pixel tiles 100 k records / 79 MiB, 64-pixel tiles
/// 26 k / 48 MiB, 128-pixel tiles ≈ 6.6 k / 12 MiB). 128 keeps that a small share of a farm
/// job while a 256² image still has 4 training tasks and a 1080p one 135.
pub const TRAIN_TILE: u32 = 128;

/// Colour handling of the CV coefficients [Hua §4.3].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CvColor {
    /// One coefficient per RGB channel.
    #[default]
    Rgb,
    /// One coefficient for the channel mean.
    Mono,
}

impl CvColor {
    /// The accumulator colour mode.
    pub fn mode(self) -> ColorMode {
        match self {
            CvColor::Rgb => ColorMode::Rgb,
            CvColor::Mono => ColorMode::Mono,
        }
    }
}

/// The base estimator of the controlled direct lighting: the values `F_s` the fits are
/// trained on and the render phase corrects in cells with coefficients (the correction
/// `Σα − Σ_s Σ_k α_k λ_k(x_s)/p(x_s)` has zero mean for any base, see
/// `render::integrator::cv`). Vertices in cells without coefficients, and the training
/// samples' image contributions, are `path`'s (the job's heuristic) whatever the base.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CvBase {
    /// The job's MIS heuristic (`mis`, power by default): the render phase adds only the CV
    /// term to `path`'s estimate.
    Mis,
    /// The balance heuristic, whatever the job's `mis` [Hua eq. 6], the paper's
    /// `F_s = f/p`: with the optimal `α` the CV can cancel the integrand exactly
    /// [Hua eq. 19]. `cms`'s default: at equal spp it gains more than the power base on
    /// every scene whose fits are kept (`docs/bench/README.md`, "Latest (2026-12-06)").
    #[default]
    Balance,
}

/// Sample-index ranges of the phases of one job (see the module docs).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct PhaseSamples {
    /// Surrogate samples `[0, s)` (empty without a surrogate).
    pub surrogate: Range<u32>,
    /// Training samples `[s, s+T)`.
    pub train: Range<u32>,
    /// Render samples `[s+T, spp)`.
    pub render: Range<u32>,
}

impl PhaseSamples {
    /// Splits `0..spp`: the surrogate gets `min(surrogate_spp, spp)`, training
    /// `min(training_spp, rest)`, render the remainder.
    pub fn split(spp: u32, surrogate_spp: u32, training_spp: u32) -> Self {
        let s = surrogate_spp.min(spp);
        let t = training_spp.min(spp - s);
        Self {
            surrogate: 0..s,
            train: s..s + t,
            render: s + t..spp,
        }
    }
}

/// Options of the `ocv` estimator [Fan 2006].
///
/// | parameter | type | default | meaning |
/// |---|---|---|---|
/// | `spe` | u32 | 8 | samples per estimate (per vertex gather), ≥ 2 (8, not Fan's 64: at equal time on `checkers` 8 beats 16 and 4, `docs/bench/README.md`); with fewer than two per mixture component a vertex's estimate is the plain deterministic mixture (`estimators::ocv::MIN_SAMPLES_PER_COMPONENT`) |
/// | `lambda` | f64 | 1.0 | ridge penalty λ [Fan eq. 11] |
/// | `bsdf_share` | f64 | 0.5 | mixture weight α of the BSDF component (the rest is split equally among the light components), in [0, 1] |
/// | `penalize_intercept` | bool | false | literal [Fan eq. 11]: also penalise β0 (shrinks each estimate by ≈ λ/(N+λ); see [`crate::ocv`]) |
/// | `optimize` | bool | true | false: plain deterministic-mixture estimate [Fan eq. 6] (Fan's MIS baseline) |
/// | `max_light_components` | u32 | 16 | with more lights than this, or fewer than two `spe` per light and BSDF component, all lights form **one** component sampled by the light selection (Fan §7's advice for many lights) |
/// | `min_speedup` | f64 or `null` | 1.2 | the gather runs only where a pilot (one pixel in 576, at least 64 pixels; both estimators, two seeds of half the job's samples) predicts at least this equal-time speedup over `path` less one standard error of its own; else the job renders `path`'s image; `null`: always the gather (`render::integrator::ocv`, "Choosing `path` or the gather") |
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct OcvOptions {
    /// Samples per estimate.
    pub spe: u32,
    /// Ridge penalty λ [Fan eq. 11].
    pub lambda: f64,
    /// Mixture weight of the BSDF component.
    pub bsdf_share: f64,
    /// Also penalise the intercept (literal eq. 11).
    pub penalize_intercept: bool,
    /// Fit the CV (false: plain deterministic-mixture estimate, eq. 6).
    pub optimize: bool,
    /// Above this many lights, one combined light component.
    pub max_light_components: u32,
    /// The gather runs where the pilot predicts at least this equal-time speedup over
    /// `path` (`None`: always).
    pub min_speedup: Option<f64>,
}

impl Default for OcvOptions {
    fn default() -> Self {
        Self {
            spe: 8,
            lambda: 1.0,
            bsdf_share: 0.5,
            penalize_intercept: false,
            optimize: true,
            max_light_components: 16,
            min_speedup: Some(1.2),
        }
    }
}

impl OcvOptions {
    /// The option names (for error messages listing the valid ones).
    pub const FIELDS: &'static [&'static str] = &[
        "spe",
        "lambda",
        "bsdf_share",
        "penalize_intercept",
        "optimize",
        "max_light_components",
        "min_speedup",
    ];

    /// Checks the ranges; returns the offending field and why.
    pub fn validate(&self) -> Result<(), (&'static str, &'static str)> {
        if self.spe < 2 {
            // A deterministic mixture [Fan §4] of one sample is the BSDF sample alone: the
            // lights would be found by BSDF hits only.
            return Err((
                "spe",
                "must be ≥ 2 (one BSDF and one light sample per estimate at least)",
            ));
        }
        if !(self.lambda >= 0.0 && self.lambda.is_finite()) {
            return Err(("lambda", "must be finite and ≥ 0"));
        }
        if !(0.0..=1.0).contains(&self.bsdf_share) {
            return Err(("bsdf_share", "must lie in [0, 1]"));
        }
        if self
            .min_speedup
            .is_some_and(|m| !(m >= 0.0 && m.is_finite()))
        {
            return Err(("min_speedup", "must be finite and ≥ 0, or null"));
        }
        Ok(())
    }
}

/// Default [`CmsOptions::min_image_gain`].
pub const DEFAULT_MIN_IMAGE_GAIN: f64 = 3e-4;

/// Default [`CmsOptions::min_fit_gain`]: a fit that removes a fraction `g` of the controlled
/// vertices' variance gives at most `1/(1 − g)` at equal samples (1.25× at 0.2), about what
/// the CV's per-sample cost takes back at equal time where the fits are kept; the scenes
/// measured fall on either side with a margin of 1.35× or more (`docs/bench/README.md`,
/// "Within a technique").
pub const DEFAULT_MIN_FIT_GAIN: f64 = 0.2;

/// Where a job's sample numbers come from (job option `sampler`; the renderer's
/// `render::sampler::SamplerKind` and the wire's `sampler` alike).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SamplerKind {
    /// Owen-scrambled Sobol points per pixel (white noise past 256 dimensions or 2¹⁶
    /// samples).
    #[default]
    Sobol,
    /// Independent uniform numbers: the hashed stream at every dimension and sample.
    Independent,
}

impl SamplerKind {
    /// Whether this is the default (`sobol`), which the wire omits.
    pub fn is_default(&self) -> bool {
        *self == Self::default()
    }
}

/// `cms`'s `min_depth` with a per-pixel stratified (Sobol) sampler: the camera hit keeps the
/// base estimate ([`CmsOptions`]).
pub const MIN_DEPTH_STRATIFIED: u32 = 1;

/// `cms`'s `ridge` with a per-pixel stratified (Sobol) sampler ([`CmsOptions`]).
pub const RIDGE_STRATIFIED: f64 = 0.5;

/// `cms`'s `min_held_out_share` with a per-pixel stratified (Sobol) sampler
/// ([`CmsOptions`]; with independent numbers 0, no check). Fits whose held-out gain is below
/// `min_fit_gain` must keep at least this share of their in-sample gain on held-out samples.
/// Measured (`docs/bench/README.md`, "Fits that follow their samples' noise", 20-spp jobs,
/// 6–8 seeds): 0.07–0.30 on 128×128 rooms with 256 small lights, whose fits gave 1.03–1.07×
/// at equal spp and lost 12–15 % at equal time; 0.40–0.50 on `many-lights` and the 64-light
/// room, whose fits pay (1.26×, 1.39× at equal spp).
pub const HELD_OUT_SHARE_STRATIFIED: f64 = 0.35;

/// `cms`'s `ridge` with independent numbers ([`CmsOptions`]).
pub const RIDGE_INDEPENDENT: f64 = 0.1;

/// `cms`'s default `min_group_samples` ([`CmsOptions`]).
pub const CMS_GROUP_SAMPLES: u64 = 16;

/// Options of the `cms` estimator [Hua 2023].
///
/// | parameter | type | default | meaning |
/// |---|---|---|---|
/// | `relative` | bool | `true` | optimise relative variance: weight training samples by `1/(surrogate + 0.01)²` [Hua eq. 25] |
/// | `color` | `"rgb"` \| `"mono"` | `"rgb"` | coefficients per channel or shared [Hua §4.3] |
/// | `training_spp` | u32 | 16 | samples per pixel of the training phase (kept in the image, weighed against the render phase's by their variance: [`crate::composite::phase_weight`]) |
/// | `surrogate_spp` | u32 | 1 | samples per pixel of the surrogate image (only with `relative`; kept in the image) |
/// | `grid_resolution` | `[nx, ny, nz]` \| null | null | cells per axis over the scene bounds; null = adaptive ([`adaptive_grid`]: ≈ 16×16 pixels per cell, at most [`ADAPTIVE_GRID_MAX_AXIS`] cells on the longest axis) |
/// | `grid_levels` | u32 \| null | null | each grid cell is subdivided this many times (2×2×2 children per level, at most [`MAX_GRID_LEVELS`]; grid cells × `9^levels` at most [`MAX_GRID_INDICES`]) where the camera's rays hit glossy surfaces (other vertices keep the undivided cells: `render::integrator::cv::Grid`); every cell keeps the fit of its own samples or of an ancestor's, whichever removes the most variance out of sample ([`crate::solve::SolvePolicy::levels`]). 0 = one level (the cells of `grid_resolution`). null = [`CMS_GRID_LEVELS`], fewer where a given `grid_resolution` would exceed that limit, more on the adaptive grid of an image wider than 512 pixels ([`adaptive_grid`], [`PhasedEstimator::for_image`]). Chosen by equal-spp measurements (`docs/bench/README.md`) |
/// | `max_light_components` | u32 | 1024 | more emitters than this are clustered by spatial proximity |
/// | `ridge` | f64 \| null | null | relative Tikhonov regularisation of each cell system: `A + ridge·diag(A)` shrinks `α` toward the base estimator (`path` with the default `base`); 0.5 scales an uncorrelated coefficient by 2/3. null = by the job's sampler ([`PhasedEstimator::for_sampler`]): **0.5 with the Sobol sampler** ([`RIDGE_STRATIFIED`]: the fits minimise the variance of independent samples, which overstates the per-pixel stratified `path`'s, so they are shrunk toward it; 1 shrank colour-lamp's fits too far, 1.42× → 1.53× at 0.5, and below 0.5 many-lights' sparsely sampled lights lose), **0.1 with the independent one** ([`RIDGE_INDEPENDENT`]: there the fits' objective is the estimator's variance, and less shrinking gains 3–10 % at equal spp on colour-lamp, `manylights-4` and veach-mis d2). Chosen by equal-spp measurements (`docs/bench/README.md`) |
/// | `min_samples` | u64 | 16 | cells with fewer training samples fall back to the plain estimator |
/// | `min_group_samples` | u64 | 16 | a cell's light partitions are fitted in groups of at least this many training samples where it has fewer per partition: a range of the light clustering's tree is split while each half with samples has as many ([`crate::solve::SolvePolicy::min_group_samples`]); 1 fits every sampled partition alone. With many lights and few samples per light in a cell, lone fits follow single samples' noise (a scene of 10 080 emissive triangles: 0.18× `path` at equal spp; grouped 1.16×, and 1.35× with the held-out check of each cell's fits, [`crate::solve::CellHalves::CrossFitted`]). Chosen by equal-spp measurements ([`CMS_GROUP_SAMPLES`], `docs/bench/README.md`) |
/// | `base` | `"mis"` \| `"balance"` | `"balance"` | values the fits are trained on and the render phase corrects in cells with coefficients: the job's MIS heuristic (= `path`) or balance, the paper's `f/p` ([`CvBase`]); elsewhere, and in the training samples' image, `path`'s either way. Balance by equal-spp measurements, both samplers (`docs/bench/README.md`) |
/// | `min_image_gain` | f64 \| null | `3e-4` | the fits are applied only when they are predicted to remove at least this fraction of the image's per-sample (relative) variance, measured on the training samples ([`crate::table::predicted_image_gain`]); below it every cell falls back and the render phase is traced as `path`; a training tile whose own first 2 spp predict less than half of it (or less than half of `min_fit_gain`), with its cells' fits pooled in their undivided cells and fitted alone alike, stops recording (`render::integrator::cv::TRAIN_PROBE_SPP`, [`crate::table::AccumulatorTable::fits_pay_pooled_or_alone`]). null always applies them. Chosen by equal-spp and equal-time measurements (`docs/bench/README.md`) |
/// | `min_fit_gain` | f64 \| null | `0.2` | the fits are applied only when they remove at least this fraction of the variance at the vertices they control (within each technique: the estimator takes one NEE and one BSDF sample, so the spread between the two techniques is no variance of it), over all cells, measured on the training samples ([`crate::table::predicted_fit_gain`]); below it every cell falls back and the render phase is traced as `path`. It bounds the equal-spp gain at `1/(1 − g)` whatever the image's noise is made of, so a small one cannot pay for the CV's per-sample cost; a training tile whose own first 2 spp predict less than half of it (or less than half of `min_image_gain`), pooled and fitted alone alike, stops recording (as for `min_image_gain`). null always applies them. Chosen by equal-spp and equal-time measurements (`docs/bench/README.md`) |
/// | `min_held_out_share` | f64 \| null | null | where the fits' held-out gain (each cell's two halves fitted apart, each fit judged on the other half: [`crate::table::SolvedTable::held_out_gain`]) is below `min_fit_gain`, they are applied only when it keeps at least this share of their in-sample gain ([`crate::table::SolvedTable::held_out_share`]); below it every cell falls back (`Overfitted`) and the render phase is traced as `path`. It catches fits that follow their training samples' noise (many lights, a few samples of each per cell), whose in-sample fit gain overstates what the image gets. 0 never switches off. null = by the job's sampler ([`PhasedEstimator::for_sampler`]): **0.35 with the Sobol sampler** ([`HELD_OUT_SHARE_STRATIFIED`]), **0 with the independent one** (there such fits still gave 1.22× at equal spp, about their cost: rooms of 256 lights, `docs/bench/README.md`). Chosen by equal-spp and equal-time measurements |
/// | `min_depth` | u32 \| null | null | the CV is trained and applied only at path vertices of at least this depth (0 = the camera hit); shallower vertices use the base estimator. null = by the job's sampler ([`PhasedEstimator::for_sampler`]): **1 with the Sobol sampler** (depth-2, direct-lighting jobs are then exactly `path`: the CV at the camera hit costs more than it gains against the per-pixel stratified Sobol samples), **0 with the independent one** (there the camera hit's direct lighting is where colour noise is: colour-lamp d2 3.58× at equal time). Chosen by equal-spp and equal-time measurements (`docs/bench/README.md`) |
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CmsOptions {
    /// Optimise relative variance [Hua eq. 25].
    pub relative: bool,
    /// Per-channel or shared coefficients [Hua §4.3].
    pub color: CvColor,
    /// Training samples per pixel.
    pub training_spp: u32,
    /// Surrogate samples per pixel (with `relative`).
    pub surrogate_spp: u32,
    /// Grid cells per axis; `None` = adaptive.
    pub grid_resolution: Option<[u32; 3]>,
    /// Subdivisions of each grid cell, fitted hierarchically; `None` = by the grid
    /// ([`PhasedEstimator::grid_levels`]).
    pub grid_levels: Option<u32>,
    /// Clustering threshold for emitters.
    pub max_light_components: u32,
    /// Relative ridge of the cell solves; `None` = by the sampler
    /// ([`PhasedEstimator::for_sampler`]).
    pub ridge: Option<f64>,
    /// Minimum training samples per cell.
    pub min_samples: u64,
    /// Light partitions are fitted in groups of at least this many samples.
    pub min_group_samples: u64,
    /// Base estimator of the controlled direct lighting.
    pub base: CvBase,
    /// Shallowest vertex depth the CV is trained and applied at; `None` = by the sampler
    /// ([`PhasedEstimator::for_sampler`]).
    pub min_depth: Option<u32>,
    /// Smallest predicted image gain for the fits to be applied; `None` always applies them.
    pub min_image_gain: Option<f64>,
    /// Smallest predicted fit gain for the fits to be applied; `None` always applies them.
    pub min_fit_gain: Option<f64>,
    /// Smallest held-out share of the fits' gain, where their held-out gain is below
    /// `min_fit_gain` (0: no check); `None` = by the sampler
    /// ([`PhasedEstimator::for_sampler`]).
    pub min_held_out_share: Option<f64>,
}

impl Default for CmsOptions {
    fn default() -> Self {
        Self {
            relative: true,
            color: CvColor::Rgb,
            training_spp: 16,
            surrogate_spp: 1,
            grid_resolution: None,
            grid_levels: None,
            max_light_components: 1024,
            ridge: None,
            min_samples: 16,
            min_group_samples: CMS_GROUP_SAMPLES,
            base: CvBase::Balance,
            min_depth: None,
            min_image_gain: Some(DEFAULT_MIN_IMAGE_GAIN),
            min_fit_gain: Some(DEFAULT_MIN_FIT_GAIN),
            min_held_out_share: None,
        }
    }
}

/// Options of the `per_light_cv` estimator (Vévoda-style, [Hua §7.2]).
///
/// | parameter | type | default | meaning |
/// |---|---|---|---|
/// | `training_spp` | u32 | 16 | samples per pixel of the training phase (kept in the image, weighed against the render phase's by their variance: [`crate::composite::phase_weight`]) |
/// | `grid_resolution` | `[nx, ny, nz]` \| null | null | cells per axis; null = adaptive ([`adaptive_grid`]: ≈ 16×16 pixels per cell, at most [`ADAPTIVE_GRID_MAX_AXIS`] cells on the longest axis) |
/// | `max_light_components` | u32 | 1024 | more emitters than this are clustered by spatial proximity |
/// | `relative` | bool | `true` | weigh each training vertex by `1/(surrogate + 0.01)²` [Hua eq. 25] (times its squared throughput [Hua eq. 29]) when predicting whether a cell's coefficients reduce its variance ([`crate::perlight`]); the coefficients themselves stay the cell means [Hua §7.2] |
/// | `surrogate_spp` | u32 | 1 | samples per pixel of the surrogate image (only with `relative`; kept in the image) |
/// | `min_image_gain` | f64 \| null | `3e-4` | as `cms`'s: the cells' coefficients are applied only when the cells that keep them are predicted to remove at least this fraction of the image's per-sample (relative) variance; below it every cell falls back and the render phase is traced as `path`. null always applies them |
/// | `min_fit_gain` | f64 \| null | `0.2` | as `cms`'s, over the NEE estimates the CV controls: below it every cell falls back. null always applies them |
/// | `min_held_out_share` | f64 \| null | `0.8` | training records each cell's two halves; each half's light means are judged on the other half's vertices ([`crate::perlight::MeanContributionAccumulator::held_out_reduction`]). Where the kept cells' held-out reduction is below this share of their in-sample one ([`crate::table::SolvedTable::held_out_share`]), every cell falls back (`Overfitted`, whatever the gains): the means follow their few vertices' noise (many lights, a few samples of each per cell). null never switches off. Measured: 0.64–0.73 on a room of 256 small lamps (1.07× at equal spp, 0.86× at equal time), 0.87–1.0 where the means pay (`docs/bench/README.md`, [`PER_LIGHT_HELD_OUT_SHARE`]) |
///
/// A cell keeps its coefficients only where its own training vertices predict they reduce
/// its weighted variance ([`crate::solve::FallbackReason::NoReduction`] otherwise): the
/// cell mean of a light's contribution, subtracted at every vertex of the cell, adds
/// variance at its dark pixels' vertices (`docs/bench/README.md`: 0.11× on veach-mis
/// without this).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PerLightCvOptions {
    /// Training samples per pixel.
    pub training_spp: u32,
    /// Grid cells per axis; `None` = adaptive.
    pub grid_resolution: Option<[u32; 3]>,
    /// Clustering threshold for emitters.
    pub max_light_components: u32,
    /// Weigh training vertices by the surrogate [Hua eq. 25].
    pub relative: bool,
    /// Surrogate samples per pixel (with `relative`).
    pub surrogate_spp: u32,
    /// Smallest predicted image gain for the coefficients to be applied; `None` always.
    pub min_image_gain: Option<f64>,
    /// Smallest predicted fit gain for the coefficients to be applied; `None` always.
    pub min_fit_gain: Option<f64>,
    /// Smallest held-out share of the kept cells' reduction; `None`: no check.
    pub min_held_out_share: Option<f64>,
}

/// `per_light_cv`'s default `min_held_out_share`. Measured (`cvfarm render --estimator
/// per_light_cv --max-depth 5 --spp 20…32 --stats`, seeds 3 and 20–22): 0.64–0.78 on
/// `scenes/many-lights-256` (256 lamps, 128×128; 0.61–0.65 at 256×256, 0.34–0.50 at 96×96),
/// whose means gave 1.07× at equal spp for +19 % of time; 0.86–0.88 on `many-lights` (64
/// lamps, 256×256, 1.28× at equal spp; 0.81–0.83 at 128×128, 0.79–0.81 at 96×96), 0.94–0.96
/// on Mitsuba's `manylights-4`, 0.97–1.0 on `colour-lamp` and `veach-mis`. A false switch
/// costs the surrogate and the training's recording (≈ 2 %), a false keep up to 14 %.
pub const PER_LIGHT_HELD_OUT_SHARE: f64 = 0.8;

impl Default for PerLightCvOptions {
    fn default() -> Self {
        Self {
            training_spp: 16,
            grid_resolution: None,
            max_light_components: 1024,
            relative: true,
            surrogate_spp: 1,
            min_image_gain: Some(DEFAULT_MIN_IMAGE_GAIN),
            min_fit_gain: Some(DEFAULT_MIN_FIT_GAIN),
            min_held_out_share: Some(PER_LIGHT_HELD_OUT_SHARE),
        }
    }
}

/// Options of the `optimal_mis` estimator (cells = pixels, direct illumination, [Hua §7.4]).
///
/// | parameter | type | default | meaning |
/// |---|---|---|---|
/// | `training_spp` | u32 | 16 | samples per pixel of the training phase (kept in the image, weighed against the render phase's by their variance: [`crate::composite::phase_weight`]) |
/// | `color` | `"rgb"` \| `"mono"` | `"rgb"` | coefficients per channel or shared |
/// | `max_light_components` | u32 | 1024 | more emitters than this are clustered by spatial proximity |
/// | `ridge` | f64 | `1e-6` | relative Tikhonov regularisation |
/// | `min_samples` | u64 | 16 | pixels with fewer training samples fall back to the plain estimator |
/// | `min_split_gain` | f64 \| null | `0.25` | a training tile keeps its pixels' fits only when, fitted on one half of its training samples and applied to the other (both ways), they remove at least this fraction of the (relative) squared difference between the two halves' pixel estimates: the error of the sampler's stratified pixel means, which the in-sample moments cannot see (`render::integrator::cv`'s split-half check). Below it the tile's pixels are rendered as `path`. null always keeps them. Chosen by equal-spp and equal-time measurements (`docs/bench/README.md`) |
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct OptimalMisOptions {
    /// Training samples per pixel.
    pub training_spp: u32,
    /// Per-channel or shared coefficients.
    pub color: CvColor,
    /// Clustering threshold for emitters.
    pub max_light_components: u32,
    /// Relative ridge of the pixel solves.
    pub ridge: f64,
    /// Minimum training samples per pixel.
    pub min_samples: u64,
    /// Smallest split-half gain of a training tile's fits (`None`: always keep them).
    pub min_split_gain: Option<f64>,
}

/// Default [`OptimalMisOptions::min_split_gain`].
pub const DEFAULT_MIN_SPLIT_GAIN: f64 = 0.25;

impl Default for OptimalMisOptions {
    fn default() -> Self {
        Self {
            training_spp: 16,
            color: CvColor::Rgb,
            max_light_components: 1024,
            ridge: 1e-6,
            min_samples: 16,
            min_split_gain: Some(DEFAULT_MIN_SPLIT_GAIN),
        }
    }
}

/// The phase-structured CV estimators (closed set), with their options.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum PhasedEstimator {
    /// `cms`.
    Cms(CmsOptions),
    /// `per_light_cv`.
    PerLightCv(PerLightCvOptions),
    /// `optimal_mis`.
    OptimalMis(OptimalMisOptions),
}

impl PhasedEstimator {
    /// The phase split of a job with `spp` samples per pixel and paths of at most
    /// `max_depth` vertices (Mitsuba's meaning; `u32::MAX` for unbounded). When no vertex can
    /// be controlled ([`Self::controls_any_vertex`]) every sample is a render sample: there is
    /// nothing to train, and a job without phase barriers costs what `path` costs.
    pub fn phases(&self, spp: u32, max_depth: u32) -> PhaseSamples {
        if !self.controls_any_vertex(max_depth) {
            return PhaseSamples::split(spp, 0, 0);
        }
        match self {
            Self::Cms(o) => {
                let s = if o.relative {
                    o.surrogate_spp.max(1)
                } else {
                    0
                };
                PhaseSamples::split(spp, s, o.training_spp)
            }
            Self::PerLightCv(o) => {
                let s = if o.relative {
                    o.surrogate_spp.max(1)
                } else {
                    0
                };
                PhaseSamples::split(spp, s, o.training_spp)
            }
            Self::OptimalMis(o) => PhaseSamples::split(spp, 0, o.training_spp),
        }
    }

    /// Base estimator of the controlled direct lighting (`cms` option; the job's MIS
    /// heuristic for the others).
    pub fn base(&self) -> CvBase {
        match self {
            Self::Cms(o) => o.base,
            Self::PerLightCv(_) | Self::OptimalMis(_) => CvBase::Mis,
        }
    }

    /// Whether training samples are weighted by a surrogate image [Hua eq. 25].
    pub fn relative(&self) -> bool {
        match self {
            Self::Cms(o) => o.relative,
            Self::PerLightCv(o) => o.relative,
            Self::OptimalMis(_) => false,
        }
    }

    /// Shallowest vertex depth the CV is trained and applied at (`cms`'s `min_depth`, a
    /// `None` read as the Sobol sampler's 1; 0 for the others). Resolve a job's `None` with
    /// [`Self::for_sampler`] first.
    pub fn min_depth(&self) -> u32 {
        match self {
            Self::Cms(o) => o.min_depth.unwrap_or(MIN_DEPTH_STRATIFIED),
            _ => 0,
        }
    }

    /// The estimator with its sampler-dependent defaults filled in: `cms`'s `min_depth`
    /// `None` becomes [`MIN_DEPTH_STRATIFIED`] with the Sobol sampler (stratified per pixel)
    /// and 0 with independent numbers, its `ridge` `None` [`RIDGE_STRATIFIED`] and
    /// [`RIDGE_INDEPENDENT`], its `min_held_out_share` `None` [`HELD_OUT_SHARE_STRATIFIED`]
    /// and 0 (no check). Every consumer of a job (phase planner, renderer, worker and
    /// coordinator solves) resolves through this, so they agree.
    pub fn for_sampler(self, sampler: SamplerKind) -> Self {
        let stratified = sampler == SamplerKind::Sobol;
        match self {
            Self::Cms(o) => Self::Cms(CmsOptions {
                min_depth: Some(o.min_depth.unwrap_or(if stratified {
                    MIN_DEPTH_STRATIFIED
                } else {
                    0
                })),
                ridge: Some(o.ridge.unwrap_or(if stratified {
                    RIDGE_STRATIFIED
                } else {
                    RIDGE_INDEPENDENT
                })),
                min_held_out_share: Some(o.min_held_out_share.unwrap_or(if stratified {
                    HELD_OUT_SHARE_STRATIFIED
                } else {
                    0.0
                })),
                ..o
            }),
            other => other,
        }
    }

    /// The estimator with its image-dependent defaults filled in: `cms` on the adaptive grid
    /// (`grid_resolution` and `grid_levels` both `None`) gets `grid_levels`
    /// [`CMS_GRID_LEVELS`] plus the extra subdivisions of [`adaptive_grid`] for a
    /// `width × height` image (at most [`MAX_GRID_LEVELS`]); every other estimator and option
    /// is unchanged. Like [`Self::for_sampler`], every consumer of a job resolves through
    /// this (`protocol::EstimatorSpec::phased_for`, `render::integrator::cv::CvJob`), so the
    /// grid, the solve's hierarchy and the key checks agree.
    pub fn for_image(self, width: u32, height: u32) -> Self {
        match self {
            Self::Cms(o) if o.grid_resolution.is_none() && o.grid_levels.is_none() => {
                let (_, extra) = adaptive_grid(width, height);
                Self::Cms(CmsOptions {
                    grid_levels: Some(CMS_GRID_LEVELS.saturating_add(extra).min(MAX_GRID_LEVELS)),
                    ..o
                })
            }
            other => other,
        }
    }

    /// Whether a path of at most `max_depth` vertices has a vertex the CV controls: vertex `d`
    /// scatters (has direct lighting and a bounce to control) when `d + 1 < max_depth`, and
    /// the CV starts at [`Self::min_depth`]. False e.g. for `cms` at depth 2 with the default
    /// `min_depth` 1: the job is then its base estimator.
    pub fn controls_any_vertex(&self, max_depth: u32) -> bool {
        u64::from(self.min_depth()) + 1 < u64::from(max_depth)
    }

    /// Checks the ranges; returns the offending field and why.
    pub fn validate(&self) -> Result<(), (&'static str, &'static str)> {
        let (ridge, grid) = match self {
            Self::Cms(o) => (o.ridge, o.grid_resolution),
            Self::PerLightCv(o) => (None, o.grid_resolution),
            Self::OptimalMis(o) => (Some(o.ridge), None),
        };
        if let Some(r) = ridge
            && !(r >= 0.0 && r.is_finite())
        {
            return Err(("ridge", "must be finite and ≥ 0"));
        }
        let gains = match self {
            Self::Cms(o) => Some((o.min_image_gain, o.min_fit_gain)),
            Self::PerLightCv(o) => Some((o.min_image_gain, o.min_fit_gain)),
            Self::OptimalMis(_) => None,
        };
        if let Self::Cms(o) = self
            && o.min_held_out_share.is_some_and(|g| !g.is_finite())
        {
            return Err((
                "min_held_out_share",
                "must be finite (or null for the sampler's default)",
            ));
        }
        if let Self::PerLightCv(o) = self
            && o.min_held_out_share.is_some_and(|g| !g.is_finite())
        {
            return Err((
                "min_held_out_share",
                "must be finite (or null to always apply the means)",
            ));
        }
        if let Some((image, fit)) = gains {
            for (name, gain) in [("min_image_gain", image), ("min_fit_gain", fit)] {
                if gain.is_some_and(|g| !g.is_finite()) {
                    return Err((name, "must be finite (or null to always apply the fits)"));
                }
            }
        }
        if let Self::OptimalMis(o) = self
            && o.min_split_gain.is_some_and(|g| !g.is_finite())
        {
            return Err((
                "min_split_gain",
                "must be finite (or null to always keep the fits)",
            ));
        }
        let levels = self.grid_levels();
        if levels > MAX_GRID_LEVELS {
            return Err(("grid_levels", "at most 4 subdivisions"));
        }
        if let Some(g) = grid {
            if g.contains(&0) {
                return Err(("grid_resolution", "every axis needs at least one cell"));
            }
            if finest_grid_cells(g, 0) > MAX_GRID_CELLS {
                return Err(("grid_resolution", "more than 2^20 cells"));
            }
            if !grid_fits(g, levels) {
                return Err((
                    "grid_levels",
                    "more than 2^28 cell indices (grid cells × 9^grid_levels)",
                ));
            }
        }
        Ok(())
    }

    /// Subdivisions of the grid cells: `cms`'s `grid_levels`, by default [`CMS_GRID_LEVELS`]
    /// or as many as a given `grid_resolution` allows within [`MAX_GRID_INDICES`]; 0 for the
    /// others.
    pub fn grid_levels(&self) -> u32 {
        match self {
            Self::Cms(o) => o.grid_levels.unwrap_or_else(|| match o.grid_resolution {
                None => CMS_GRID_LEVELS,
                Some(g) => (0..=CMS_GRID_LEVELS)
                    .rev()
                    .find(|&l| grid_fits(g, l))
                    .unwrap_or(0),
            }),
            Self::PerLightCv(_) | Self::OptimalMis(_) => 0,
        }
    }

    /// Solve policy of the cell systems (`cms`'s `ridge` `None` read as the Sobol sampler's
    /// [`RIDGE_STRATIFIED`]: resolve a job's with [`Self::for_sampler`] first).
    pub fn solve_policy(&self) -> crate::solve::SolvePolicy {
        match self {
            Self::Cms(o) => crate::solve::SolvePolicy {
                ridge: o.ridge.unwrap_or(RIDGE_STRATIFIED),
                min_samples: o.min_samples,
                min_image_gain: o.min_image_gain.unwrap_or(f64::NEG_INFINITY),
                min_fit_gain: o.min_fit_gain.unwrap_or(f64::NEG_INFINITY),
                min_held_out_share: o.min_held_out_share.unwrap_or(HELD_OUT_SHARE_STRATIFIED),
                min_group_samples: o.min_group_samples,
                // Training records each cell's halves apart; a cell keeps its fits only
                // where they remove variance out of sample.
                halves: crate::solve::CellHalves::CrossFitted,
                levels: self.grid_levels(),
                bins: NORMAL_BINS,
                ..crate::solve::SolvePolicy::default()
            },
            Self::OptimalMis(o) => crate::solve::SolvePolicy {
                ridge: o.ridge,
                min_samples: o.min_samples,
                ..crate::solve::SolvePolicy::default()
            },
            Self::PerLightCv(o) => crate::solve::SolvePolicy {
                min_image_gain: o.min_image_gain.unwrap_or(f64::NEG_INFINITY),
                min_fit_gain: o.min_fit_gain.unwrap_or(f64::NEG_INFINITY),
                min_held_out_share: o.min_held_out_share.unwrap_or(f64::NEG_INFINITY),
                held_out_share_alone: true,
                // Training records each cell's halves apart (merged for the means).
                halves: crate::solve::CellHalves::CrossFitted,
                ..crate::solve::SolvePolicy::default()
            },
        }
    }
}

/// Most grid cells a job may ask for (undivided; the adaptive default stays below it).
pub const MAX_GRID_CELLS: u64 = 1 << 20;

/// Most cell indices of a subdivided grid (grid cells × [`CELL_CHILDREN`]`^levels`): a
/// training key (`index · NORMAL_BINS · 2 + half`) stays below 2^32. Nothing is allocated
/// per index (the render phase looks cells up in a map of the cells with coefficients).
pub const MAX_GRID_INDICES: u64 = 1 << 28;

/// Whether a grid of `res` cells subdivided `levels` times is within the limits
/// ([`MAX_GRID_CELLS`], [`MAX_GRID_INDICES`], [`MAX_GRID_LEVELS`]).
pub fn grid_fits(res: [u32; 3], levels: u32) -> bool {
    levels <= MAX_GRID_LEVELS
        && finest_grid_cells(res, 0) <= MAX_GRID_CELLS
        && finest_grid_cells(res, levels) <= MAX_GRID_INDICES
}

/// Cell indices of a grid of `res` cells subdivided `levels` times, [`CELL_CHILDREN`]
/// children each (saturating).
pub fn finest_grid_cells(res: [u32; 3], levels: u32) -> u64 {
    grid_indices(
        res.iter()
            .fold(1u64, |n, &r| n.saturating_mul(u64::from(r))),
        levels,
    )
}

/// Cell indices of `cells` grid cells subdivided `levels` times: `cells ·`
/// [`CELL_CHILDREN`]`^levels` (saturating).
pub fn grid_indices(cells: u64, levels: u32) -> u64 {
    cells.saturating_mul(CELL_CHILDREN.saturating_pow(levels))
}

/// Most subdivisions of a grid cell (`cms`'s `grid_levels`).
pub const MAX_GRID_LEVELS: u32 = 4;

/// Children of a subdivided grid cell: its 2×2×2 octants, where the camera's hits are
/// recorded, and one child for the deeper vertices; the parent of cell index `i` is
/// `i / CELL_CHILDREN` (`render::integrator::cv::Grid`).
pub const CELL_CHILDREN: u64 = 9;

/// The index of cell `id`'s ancestor `up` levels above it, for keys `cell · bins + bin`
/// ([`CELL_CHILDREN`] children per cell, the normal bin kept).
pub fn cell_ancestor(id: u64, bins: u32, up: u32) -> u64 {
    let bins = u64::from(bins.max(1));
    (id / bins / CELL_CHILDREN.saturating_pow(up)) * bins + id % bins
}

/// Table keys per grid cell: the renderer splits every grid cell by the dominant axis and
/// sign of the shading normal, key = `cell · NORMAL_BINS + bin`.
pub const NORMAL_BINS: u32 = 6;

/// Default `grid_levels` of `cms`, chosen by equal-spp measurements (`docs/bench/README.md`).
pub const CMS_GRID_LEVELS: u32 = 2;

/// Most cells on the scene's longest axis of the adaptive grid ([`adaptive_grid`]).
pub const ADAPTIVE_GRID_MAX_AXIS: u32 = 32;

// The adaptive grid fits with any valid `grid_levels`: `(cap + 1)³` cells (an axis may round
// up by one) subdivided `MAX_GRID_LEVELS` times are within both limits.
const _: () = {
    let axis = ADAPTIVE_GRID_MAX_AXIS as u64 + 1;
    assert!(axis * axis * axis <= MAX_GRID_CELLS);
    assert!(axis * axis * axis * CELL_CHILDREN.pow(MAX_GRID_LEVELS) <= MAX_GRID_INDICES);
};

/// The adaptive grid of a `width × height` image: `(n, extra)`, `n` cells on the scene's
/// longest axis (the others proportionally, `render::integrator::cv::Grid`) and `extra`
/// subdivisions for `cms`'s glossy camera hits on top of [`CMS_GRID_LEVELS`]
/// ([`PhasedEstimator::for_image`]).
///
/// `n = max(width, height)/16` (≈ 16×16 pixels per cell where the scene fills the frame),
/// clamped to 8…[`ADAPTIVE_GRID_MAX_AXIS`]. Past the cap (images wider than 512 pixels) the
/// cells stop shrinking with the pixels: a deeper vertex's light reaches the image averaged
/// over its path's footprint, and a finer grid only spread the training samples over more
/// cells, each made, merged and solved per training tile (960×540, 3 seeds, 64 spp:
/// many-lights d5 2.39× → 2.99× `path` at equal spp, 1.14× → 1.93× at equal time). The
/// camera's glossy hits, which the image resolves at pixel scale, keep their cells' pixel
/// footprint through `extra = round(log2(raw / n))` more levels (veach-mis d5 at 960×540:
/// 2.39× → 2.40× at equal spp with them, 2.14× without). Integer arithmetic only, so every
/// machine of a farm agrees.
pub fn adaptive_grid(width: u32, height: u32) -> (u32, u32) {
    let raw = u64::from((width.max(height) / 16).max(8));
    let n = raw.min(u64::from(ADAPTIVE_GRID_MAX_AXIS));
    // round(log2(raw/n)) = e where 2^(2e−1) ≤ (raw/n)² < 2^(2e+1).
    let mut extra = 0u32;
    while extra < 32 && raw * raw >= (n * n) << (2 * extra + 1) {
        extra += 1;
    }
    (n as u32, extra)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn split_covers_all_samples_in_order() {
        for spp in 0..40 {
            for s in 0..4 {
                for t in 0..20 {
                    let p = PhaseSamples::split(spp, s, t);
                    assert_eq!(p.surrogate.start, 0);
                    assert_eq!(p.surrogate.end, p.train.start);
                    assert_eq!(p.train.end, p.render.start);
                    assert_eq!(p.render.end, spp);
                    assert!(p.surrogate.len() as u32 <= s && p.train.len() as u32 <= t);
                }
            }
        }
    }

    #[test]
    fn cms_surrogate_only_when_relative() {
        let rel = PhasedEstimator::Cms(CmsOptions::default()).phases(64, 5);
        assert_eq!(
            (rel.surrogate, rel.train, rel.render),
            (0..1, 1..17, 17..64)
        );
        let abs = PhasedEstimator::Cms(CmsOptions {
            relative: false,
            ..CmsOptions::default()
        })
        .phases(8, 5);
        assert_eq!((abs.surrogate, abs.train, abs.render), (0..0, 0..8, 8..8));
    }

    #[test]
    fn nothing_to_control_means_one_render_range() {
        let cms = PhasedEstimator::Cms(CmsOptions::default());
        // min_depth 1: vertex 1 scatters only when max_depth ≥ 3.
        assert!(!cms.controls_any_vertex(2) && cms.controls_any_vertex(3));
        assert!(cms.controls_any_vertex(u32::MAX));
        let p = cms.phases(64, 2);
        assert_eq!((p.surrogate, p.train, p.render), (0..0, 0..0, 0..64));
        assert_eq!(cms.phases(64, 3).train, 1..17);
        let first_hit = PhasedEstimator::Cms(CmsOptions {
            min_depth: Some(0),
            ..CmsOptions::default()
        });
        assert_eq!(first_hit.phases(64, 2).train, 1..17);
        // The default by sampler: the independent one controls the camera hit, Sobol not;
        // an explicit value wins over both.
        let (sobol, independent) = (SamplerKind::Sobol, SamplerKind::Independent);
        assert_eq!(cms.for_sampler(independent).min_depth(), 0);
        assert_eq!(cms.for_sampler(independent).phases(64, 2).train, 1..17);
        assert_eq!(cms.for_sampler(sobol).min_depth(), 1);
        assert_eq!(first_hit.for_sampler(sobol).min_depth(), 0);
        let two = PhasedEstimator::Cms(CmsOptions {
            min_depth: Some(2),
            ..CmsOptions::default()
        });
        assert_eq!(two.for_sampler(independent).min_depth(), 2);
        // The ridge alike.
        assert_eq!(
            cms.for_sampler(sobol).solve_policy().ridge,
            RIDGE_STRATIFIED
        );
        assert_eq!(cms.solve_policy().ridge, RIDGE_STRATIFIED);
        assert_eq!(
            cms.for_sampler(independent).solve_policy().ridge,
            RIDGE_INDEPENDENT
        );
        let fixed = PhasedEstimator::Cms(CmsOptions {
            ridge: Some(2.0),
            ..CmsOptions::default()
        });
        assert_eq!(fixed.for_sampler(independent).solve_policy().ridge, 2.0);
        // The held-out share alike (0: no check with independent numbers).
        let share = |e: PhasedEstimator| e.solve_policy().min_held_out_share;
        assert_eq!(share(cms.for_sampler(sobol)), HELD_OUT_SHARE_STRATIFIED);
        assert_eq!(share(cms), HELD_OUT_SHARE_STRATIFIED);
        assert_eq!(share(cms.for_sampler(independent)), 0.0);
        let set = PhasedEstimator::Cms(CmsOptions {
            min_held_out_share: Some(0.6),
            ..CmsOptions::default()
        });
        assert_eq!(share(set.for_sampler(independent)), 0.6);
        // Resolving twice changes nothing.
        let once = cms.for_sampler(independent);
        assert_eq!(once.for_sampler(sobol), once);
        let om = PhasedEstimator::OptimalMis(Default::default());
        assert!(om.controls_any_vertex(2) && !om.controls_any_vertex(1));
    }

    #[test]
    fn options_reject_unknown_fields_and_bad_ranges() {
        let e = serde_json::from_str::<CmsOptions>(r#"{"trainig_spp": 3}"#).unwrap_err();
        assert!(e.to_string().contains("trainig_spp"), "{e}");
        let bad = PhasedEstimator::Cms(CmsOptions {
            grid_resolution: Some([0, 1, 1]),
            ..CmsOptions::default()
        });
        assert_eq!(bad.validate().unwrap_err().0, "grid_resolution");
        let bad = PhasedEstimator::OptimalMis(OptimalMisOptions {
            ridge: f64::NAN,
            ..OptimalMisOptions::default()
        });
        assert_eq!(bad.validate().unwrap_err().0, "ridge");
        let bad = PhasedEstimator::Cms(CmsOptions {
            ridge: Some(-1.0),
            ..CmsOptions::default()
        });
        assert_eq!(bad.validate().unwrap_err().0, "ridge");
        for g in [f64::NAN, f64::NEG_INFINITY] {
            let share = PhasedEstimator::Cms(CmsOptions {
                min_held_out_share: Some(g),
                ..CmsOptions::default()
            });
            assert_eq!(share.validate().unwrap_err().0, "min_held_out_share");
            let per_light = PhasedEstimator::PerLightCv(PerLightCvOptions {
                min_held_out_share: Some(g),
                ..PerLightCvOptions::default()
            });
            assert_eq!(per_light.validate().unwrap_err().0, "min_held_out_share");
        }
        // `per_light_cv` cross-fits its cell means and lets the share alone decide.
        let p = PhasedEstimator::PerLightCv(PerLightCvOptions::default()).solve_policy();
        assert_eq!(p.halves, crate::solve::CellHalves::CrossFitted);
        assert!(p.held_out_share_alone && p.min_held_out_share == PER_LIGHT_HELD_OUT_SHARE);
        let off = PhasedEstimator::PerLightCv(PerLightCvOptions {
            min_held_out_share: None,
            ..PerLightCvOptions::default()
        });
        assert_eq!(off.solve_policy().min_held_out_share, f64::NEG_INFINITY);
        for g in [f64::NAN, f64::INFINITY] {
            let image = PhasedEstimator::Cms(CmsOptions {
                min_image_gain: Some(g),
                ..CmsOptions::default()
            });
            assert_eq!(image.validate().unwrap_err().0, "min_image_gain");
            let fit = PhasedEstimator::Cms(CmsOptions {
                min_fit_gain: Some(g),
                ..CmsOptions::default()
            });
            assert_eq!(fit.validate().unwrap_err().0, "min_fit_gain");
            let split = PhasedEstimator::OptimalMis(OptimalMisOptions {
                min_split_gain: Some(g),
                ..OptimalMisOptions::default()
            });
            assert_eq!(split.validate().unwrap_err().0, "min_split_gain");
        }
        let off = PhasedEstimator::Cms(CmsOptions {
            min_image_gain: None,
            min_fit_gain: None,
            ..CmsOptions::default()
        });
        assert!(off.validate().is_ok());
        assert!(OcvOptions::default().validate().is_ok());
    }

    #[test]
    fn the_adaptive_grid_stops_at_its_cap_and_subdivides_glossy_hits_instead() {
        // ≈ 16 pixels per cell up to the cap: images up to 512 pixels wide are unchanged.
        assert_eq!(adaptive_grid(16, 16), (8, 0));
        assert_eq!(adaptive_grid(256, 256), (16, 0));
        assert_eq!(adaptive_grid(384, 256), (24, 0));
        assert_eq!(adaptive_grid(512, 100), (32, 0));
        assert_eq!(adaptive_grid(0, 0), (8, 0));
        // Past it, round(log2(raw/32)) more levels: 60/32 → 1, 80/32 → 1, 120/32 → 2
        // (log2 3.75 = 1.91), 90/32 → 1 (1.49), 91/32 → 2 (1.51).
        assert_eq!(adaptive_grid(960, 540), (32, 1));
        assert_eq!(adaptive_grid(1280, 720), (32, 1));
        assert_eq!(adaptive_grid(1920, 1080), (32, 2));
        assert_eq!(adaptive_grid(1440, 10), (32, 1));
        assert_eq!(adaptive_grid(1456, 10), (32, 2));
        assert_eq!(adaptive_grid(u32::MAX, 1).0, ADAPTIVE_GRID_MAX_AXIS);
        // The rounding against the floating-point formula, over every width.
        for w in (0..70_000u32).step_by(7) {
            let raw = f64::from((w / 16).max(8));
            let want = (raw / f64::from(ADAPTIVE_GRID_MAX_AXIS))
                .log2()
                .max(0.0)
                .round();
            assert_eq!(f64::from(adaptive_grid(w, 1).1), want, "width {w}");
        }

        let cms = |grid_resolution, grid_levels| {
            PhasedEstimator::Cms(CmsOptions {
                grid_resolution,
                grid_levels,
                ..CmsOptions::default()
            })
        };
        let levels = |e: PhasedEstimator| e.grid_levels();
        assert_eq!(levels(cms(None, None).for_image(256, 256)), CMS_GRID_LEVELS);
        assert_eq!(
            levels(cms(None, None).for_image(960, 540)),
            CMS_GRID_LEVELS + 1
        );
        assert_eq!(
            cms(None, None).for_image(1920, 1080).solve_policy().levels,
            CMS_GRID_LEVELS + 2
        );
        assert_eq!(
            levels(cms(None, None).for_image(60_000, 60_000)),
            MAX_GRID_LEVELS
        );
        // What the job sets is kept; a given grid is not the adaptive one.
        assert_eq!(levels(cms(None, Some(1)).for_image(1920, 1080)), 1);
        assert_eq!(levels(cms(Some([8, 8, 8]), None).for_image(1920, 1080)), 2);
        let once = cms(None, None).for_image(1920, 1080);
        assert_eq!(once.for_image(256, 256), once);
        assert!(once.validate().is_ok());
        let plm = PhasedEstimator::PerLightCv(PerLightCvOptions::default());
        assert_eq!(plm.for_image(1920, 1080), plm);
    }

    #[test]
    fn grid_levels_count_toward_the_cell_limit_and_default_to_what_fits() {
        let cms = |grid_resolution, grid_levels| {
            PhasedEstimator::Cms(CmsOptions {
                grid_resolution,
                grid_levels,
                ..CmsOptions::default()
            })
        };
        assert_eq!(cms(None, None).grid_levels(), CMS_GRID_LEVELS);
        assert_eq!(cms(None, None).solve_policy().levels, CMS_GRID_LEVELS);
        assert_eq!(cms(None, None).solve_policy().bins, NORMAL_BINS);
        assert_eq!(cms(Some([8, 8, 8]), None).grid_levels(), 2);
        // 2^20 cells · 9^3 > 2^28 indices: two levels by default, an error with three.
        let big = Some([1024, 1024, 1]);
        assert_eq!(cms(big, None).grid_levels(), 2);
        assert!(cms(big, None).validate().is_ok());
        assert_eq!(cms(big, Some(3)).validate().unwrap_err().0, "grid_levels");
        assert_eq!(
            cms(Some([2048, 1024, 1]), Some(0))
                .validate()
                .unwrap_err()
                .0,
            "grid_resolution"
        );
        assert!(grid_fits([1024, 1024, 1], 2) && !grid_fits([1, 1, 1], MAX_GRID_LEVELS + 1));
        assert_eq!(
            cms(None, Some(MAX_GRID_LEVELS + 1))
                .validate()
                .unwrap_err()
                .0,
            "grid_levels"
        );
        assert_eq!(finest_grid_cells([u32::MAX; 3], 4), u64::MAX);
        // The others never subdivide.
        let per_light = PhasedEstimator::PerLightCv(PerLightCvOptions::default());
        assert_eq!(per_light.grid_levels(), 0);
    }
}
