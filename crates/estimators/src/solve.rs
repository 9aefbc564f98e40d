//! Solving a cell's CV system and applying the coefficients [Hua eq. 14, 21, 32–33].
//!
//! # The `cms` estimator (and `optimal_mis`, which uses pixels as cells)
//! Training samples are accumulated per spatial cell ([`crate::cell`]), the coordinator
//! merges and solves every cell with [`solve`], and the render pass applies the
//! coefficients. Parameters that reach this crate:
//!
//! | name | type | default | meaning |
//! |---|---|---|---|
//! | `color` | `"rgb"` \| `"mono"` | `"rgb"` | per-channel or shared coefficients [Hua §4.3] |
//! | `relative` | bool | true | weight samples by `1/(surrogate + 0.01)²` [Hua eq. 25] |
//! | `ridge` | f64 | `0.5` for `cms`, `1e-6` for `optimal_mis` (SolvePolicy default `1e-6`) | [`SolvePolicy::ridge`] |
//! | `min_samples` | u64 | 16 | [`SolvePolicy::min_samples`] |
//! | `min_effective_samples` | f64 | 4 | [`SolvePolicy::min_effective_samples`] |
//! | `min_partition_samples` | u64 | 1 | [`SolvePolicy::min_partition_samples`] |
//! | `min_group_samples` | u64 | 1 (`cms`: [`crate::spec::CMS_GROUP_SAMPLES`]) | [`SolvePolicy::min_group_samples`] |
//! | `max_condition` | f64 | `1e12` | [`SolvePolicy::max_condition`] |
//!
//! ```json
//! { "kind": "cms", "color": "rgb", "relative": true, "training_spp": 16, "ridge": 0.5 }
//! ```
//!
//! # What is solved
//! `A α = b` with the sums of a [`CellAccumulator`] (one right-hand side per channel).
//! The partition block of `A` is diagonal because per-light pdfs never overlap
//! [Hua eq. 30], so [`solve`] eliminates it with the Schur complement [Hua eq. 32]:
//! a `K × K` system for the overlapping coefficients, then each partition coefficient by
//! back-substitution [Hua eq. 33]. Time and memory are linear in the number of sampled
//! partitions. [`solve_dense`] assembles and factorises the full matrix; it is the test
//! oracle and fine for small systems.
//!
//! # Policy for hard cells (both solvers apply it identically)
//! | step | rule | default |
//! |---|---|---|
//! | empty cell | no accepted sample → fallback | |
//! | too few samples | `samples < min_samples` → fallback | 16 |
//! | too few effective samples | Kish `(Σw)²/Σw² < min_effective_samples` → fallback | 4 |
//! | thinly sampled partitions | partitions are solved in groups along the tree of partition index ranges, a range split only while each half with samples has `≥ min_group_samples` of them; a group is the mixture of its members' pdfs, weighted by their sample counts, and its `α` the members' `α_k = (n_k/n_G) α_G` ([`partition_groups`]) | 1 |
//! | inactive components | a partition (group) with `< min_partition_samples` samples or zero diagonal, or an overlapping component with zero diagonal, gets `α = 0` and is removed from the system (never poisons it) | 1 |
//! | regularisation | Tikhonov on the Jacobi-scaled system: `A + ridge · diag(A)`; shrinks `α` toward the plain estimator and bounds the scaled condition number by about `(k + ridge)/ridge` | `1e-6` |
//! | ill-conditioned | condition estimate `(max Lᵢᵢ / min Lᵢᵢ)²` of the scaled Cholesky factor above `max_condition` → fallback | `1e12` |
//! | failure | Cholesky fails or any `α` is NaN/Inf → fallback | |
//!
//! The **fallback is the plain estimator**, `α ≡ 0`. By [Hua eq. 14] it is equivalent to
//! any shifted set `α_k = s · n_k c_k` (`n_k c_k` = effective sample count of the
//! component, summed over its pdfs), which gives the same estimate; this module therefore
//! only ever returns `α ≡ 0` on fallback.
//!
//! # Applying
//! Per sample the CV subtracts [`CellCoefficients::cv_term`] = `Σ_k α_k λ_k / p` from the
//! sample value `F`; per vertex it adds [`CellCoefficients::alpha_sum`] = `Σ_k α_k` once
//! (each `λ_k` integrates to one) [Hua eq. 17].
//!
//! The ridge changes `α`, never the expectation of the CV estimator: any fixed `α`
//! (computed from independent training samples) gives an unbiased estimate.

use nalgebra::{DMatrix, DVector};

use crate::cell::{
    CHANNELS, CellAccumulator, CellError, ColorMode, ComponentLayout, CvSample, PartitionMoments,
    Reader,
};

/// How a cell system is regularised and when it falls back (see the module table).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SolvePolicy {
    /// Relative Tikhonov regularisation: `A + ridge · diag(A)`.
    pub ridge: f64,
    /// Minimum accepted samples in the cell.
    pub min_samples: u64,
    /// Minimum Kish effective sample count `(Σw)²/Σw²`.
    pub min_effective_samples: f64,
    /// Minimum samples for a partition (or a group of them) to get a fitted coefficient
    /// (else `α_k = 0`).
    pub min_partition_samples: u64,
    /// Partitions are solved in groups of at least this many samples where the cell has
    /// fewer per partition ([`partition_groups`]); 1 solves every sampled partition alone.
    pub min_group_samples: u64,
    /// Whether a table's keys are cells or the halves of cells ([`CellHalves`]). Used by
    /// [`crate::table::AccumulatorTable::solve`]; [`solve`] itself ignores it.
    pub halves: CellHalves,
    /// Subdivisions of the grid the cells come from: with [`CellHalves::CrossFitted`] and
    /// `levels > 0`, the cells (`key / 2`) are the finest of a hierarchy whose parent of
    /// cell `c·bins + b` is `(c / 9)·bins + b` ([`crate::spec::cell_ancestor`]), and every
    /// cell keeps, of its own fit and the fit its parent kept, the one that removes the
    /// most variance out of sample ([`crate::table::AccumulatorTable::solve`]). Used by the
    /// table solve; [`solve`] itself ignores it.
    pub levels: u32,
    /// Table keys per grid cell (normal bins) of the hierarchy of [`Self::levels`].
    pub bins: u32,
    /// Largest accepted condition estimate of the scaled, regularised system.
    pub max_condition: f64,
    /// Smallest predicted image gain of a table's fits ([`crate::table::predicted_image_gain`])
    /// for them to be applied; below it every cell of the table falls back
    /// ([`FallbackReason::LowImageGain`]). `-∞` (the default) never falls back for this
    /// reason. Used by [`crate::table::AccumulatorTable::solve`]; [`solve`] itself ignores it.
    pub min_image_gain: f64,
    /// Smallest predicted fit gain of a table ([`crate::table::predicted_fit_gain`]: the
    /// fraction of the controlled vertices' variance the fits remove) for them to be
    /// applied; below it every cell of the table falls back ([`FallbackReason::LowFitGain`]).
    /// `-∞` (the default) never falls back for this reason. Used by
    /// [`crate::table::AccumulatorTable::solve`]; [`solve`] itself ignores it.
    pub min_fit_gain: f64,
    /// Smallest held-out share of a cross-fitted table's fits
    /// ([`crate::table::SolvedTable::held_out_share`]) for them to be applied when their
    /// held-out gain ([`crate::table::SolvedTable::held_out_gain`]) is below
    /// [`Self::min_fit_gain`]; below both every cell of the table falls back
    /// ([`FallbackReason::Overfitted`]). Fits whose held-out gain alone clears
    /// `min_fit_gain` pay whatever their in-sample optimism. `-∞` (the default) never falls
    /// back for this reason. Used by [`crate::table::AccumulatorTable::solve`]; [`solve`]
    /// itself ignores it.
    pub min_held_out_share: f64,
    /// Whether a held-out share below [`Self::min_held_out_share`] switches the fits off
    /// whatever their held-out gain (`per_light_cv`: its gain is over the NEE estimates it
    /// controls, a part of the image's variance that can be small while the gain is large).
    pub held_out_share_alone: bool,
}

impl Default for SolvePolicy {
    fn default() -> Self {
        Self {
            ridge: 1e-6,
            min_samples: 16,
            min_effective_samples: 4.0,
            min_partition_samples: 1,
            min_group_samples: 1,
            halves: CellHalves::None,
            levels: 0,
            bins: 1,
            max_condition: 1e12,
            min_image_gain: f64::NEG_INFINITY,
            min_fit_gain: f64::NEG_INFINITY,
            min_held_out_share: f64::NEG_INFINITY,
            held_out_share_alone: false,
        }
    }
}

impl SolvePolicy {
    /// The policy for fits on half of a cell's training samples (split-half and held-out
    /// checks): `min_samples` halved, the rest unchanged.
    pub fn for_half(&self) -> Self {
        Self {
            min_samples: self.min_samples.div_ceil(2),
            ..*self
        }
    }
}

/// What the keys of an accumulator table are ([`SolvePolicy::halves`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum CellHalves {
    /// Every key is a cell.
    #[default]
    None,
    /// Keys `2c` and `2c + 1` are the two halves of cell `c` (its training samples of even
    /// and odd sample index); each cell is solved on both halves merged.
    Merged,
    /// As [`Self::Merged`], and a cell keeps its coefficients only where they remove
    /// variance out of sample: the fit of each half, applied to the other half's samples
    /// ([`variance_reduction`]), must remove some in sum ([`FallbackReason::HeldOutLoss`]).
    CrossFitted,
}

/// Why a cell fell back to the plain estimator (`α ≡ 0`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum FallbackReason {
    /// No accepted sample.
    Empty,
    /// Fewer accepted samples than [`SolvePolicy::min_samples`].
    TooFewSamples,
    /// Effective sample count below [`SolvePolicy::min_effective_samples`].
    TooFewEffectiveSamples,
    /// Every component has a zero diagonal (e.g. all `λ` zero: full occlusion).
    NoActiveComponents,
    /// Cholesky factorisation failed.
    NotPositiveDefinite,
    /// Condition estimate above [`SolvePolicy::max_condition`].
    IllConditioned,
    /// A coefficient came out NaN or infinite.
    NonFinite,
    /// The fits of the whole table are predicted to remove less of the image's variance than
    /// [`SolvePolicy::min_image_gain`] (a decision for the table, not for this cell).
    LowImageGain,
    /// The fits of the whole table are predicted to remove less of the controlled vertices'
    /// variance than [`SolvePolicy::min_fit_gain`] (a decision for the table, not for this
    /// cell).
    LowFitGain,
    /// The cell's training samples predict that its coefficients would not reduce the
    /// weighted variance of the estimates they control (`per_light_cv`, whose coefficients
    /// are not fitted: [`crate::perlight::MeanContributionAccumulator::prediction`]).
    NoReduction,
    /// Cross-fitted on the cell's two halves ([`CellHalves::CrossFitted`]), the fits add
    /// variance to the samples they were not fitted on: they follow the training samples'
    /// noise (e.g. many lights with a few samples each).
    HeldOutLoss,
    /// The fits of the whole cross-fitted table keep less than
    /// [`SolvePolicy::min_held_out_share`] of their in-sample gain on held-out samples, and
    /// their held-out gain is below [`SolvePolicy::min_fit_gain`] (or the share decides
    /// alone: [`SolvePolicy::held_out_share_alone`], `per_light_cv`'s cell means): they follow
    /// the training samples' noise (a decision for the table, not for this cell).
    Overfitted,
}

/// Outcome of a cell solve.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum SolveStatus {
    /// Coefficients were fitted.
    Solved,
    /// The plain estimator is used (`α ≡ 0`).
    Fallback(FallbackReason),
}

/// Diagnostics of a cell solve.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SolveDiagnostics {
    /// Solved or why not.
    pub status: SolveStatus,
    /// Condition estimate of the scaled, regularised system (`NaN` if not factorised).
    pub condition: f64,
    /// Partition groups that entered the system (partitions when each is its own group:
    /// [`SolvePolicy::min_group_samples`]).
    pub active_partitions: usize,
    /// Overlapping components that entered the system.
    pub active_overlapping: usize,
    /// Kish effective sample count of the cell.
    pub effective_samples: f64,
}

/// CV coefficients of one cell: `α` per component (per channel for RGB).
///
/// Partitions without a fitted coefficient are absent (their `α` is 0).
#[derive(Clone, Debug, PartialEq)]
pub struct CellCoefficients {
    layout: ComponentLayout,
    color: ColorMode,
    partition_ids: Vec<u32>,
    /// `len(partition_ids) × C`.
    partition_alpha: Vec<f64>,
    /// `K × C`.
    overlapping_alpha: Vec<f64>,
    alpha_sum: [f64; CHANNELS],
    diagnostics: SolveDiagnostics,
}

impl CellCoefficients {
    /// The plain estimator: every `α = 0`.
    pub fn zero(layout: ComponentLayout, color: ColorMode, diagnostics: SolveDiagnostics) -> Self {
        Self {
            layout,
            color,
            partition_ids: Vec::new(),
            partition_alpha: Vec::new(),
            overlapping_alpha: vec![0.0; layout.overlapping as usize * color.channels()],
            alpha_sum: [0.0; CHANNELS],
            diagnostics,
        }
    }

    /// The plain estimator as the fallback for `reason` (`α ≡ 0`), keeping the rest of
    /// `diagnostics`.
    pub fn fallen_back(
        layout: ComponentLayout,
        color: ColorMode,
        mut diagnostics: SolveDiagnostics,
        reason: FallbackReason,
    ) -> Self {
        diagnostics.status = SolveStatus::Fallback(reason);
        Self::zero(layout, color, diagnostics)
    }

    /// The plain estimator for `layout` (`α ≡ 0`, status `Solved` with no active component).
    pub fn plain(layout: ComponentLayout, color: ColorMode) -> Self {
        Self::zero(
            layout,
            color,
            SolveDiagnostics {
                status: SolveStatus::Solved,
                condition: 1.0,
                active_partitions: 0,
                active_overlapping: 0,
                effective_samples: 0.0,
            },
        )
    }

    /// Coefficients from explicit values: `partitions` are `(index, α per channel)` pairs
    /// (any order, indices `< P`, duplicates summed), `overlapping` has `K` entries.
    /// Returns `None` if an index or a length is out of range or a value is not finite.
    pub fn from_values(
        layout: ComponentLayout,
        color: ColorMode,
        partitions: &[(u32, [f64; CHANNELS])],
        overlapping: &[[f64; CHANNELS]],
    ) -> Option<Self> {
        if overlapping.len() != layout.overlapping as usize {
            return None;
        }
        let all_finite = partitions
            .iter()
            .flat_map(|p| p.1)
            .chain(overlapping.iter().flatten().copied())
            .all(f64::is_finite);
        if !all_finite || partitions.iter().any(|p| p.0 >= layout.partitions) {
            return None;
        }
        let c = color.channels();
        let mut sorted: Vec<(u32, [f64; CHANNELS])> = partitions.to_vec();
        sorted.sort_by_key(|p| p.0);
        let mut out = Self::zero(
            layout,
            color,
            SolveDiagnostics {
                status: SolveStatus::Solved,
                condition: f64::NAN,
                active_partitions: 0,
                active_overlapping: layout.overlapping as usize,
                effective_samples: 0.0,
            },
        );
        for (id, a) in sorted {
            if out.partition_ids.last() == Some(&id) {
                let n = out.partition_alpha.len();
                for (dst, src) in out.partition_alpha[n - c..].iter_mut().zip(&a) {
                    *dst += src;
                }
            } else {
                out.partition_ids.push(id);
                out.partition_alpha.extend_from_slice(&a[..c]);
            }
        }
        for (j, a) in overlapping.iter().enumerate() {
            out.overlapping_alpha[j * c..(j + 1) * c].copy_from_slice(&a[..c]);
        }
        out.diagnostics.active_partitions = out.partition_ids.len();
        out.finish();
        Some(out)
    }

    fn finish(&mut self) {
        let c = self.color.channels();
        let mut sum = [0.0; CHANNELS];
        for chunk in self
            .partition_alpha
            .chunks_exact(c)
            .chain(self.overlapping_alpha.chunks_exact(c))
        {
            for (ch, s) in sum.iter_mut().enumerate() {
                *s += chunk[if c == 1 { 0 } else { ch }];
            }
        }
        self.alpha_sum = sum;
    }

    /// The layout the coefficients were solved for.
    pub fn layout(&self) -> ComponentLayout {
        self.layout
    }

    /// The colour mode.
    pub fn color(&self) -> ColorMode {
        self.color
    }

    /// Solve diagnostics.
    pub fn diagnostics(&self) -> &SolveDiagnostics {
        &self.diagnostics
    }

    /// True when this is the plain estimator because the solve fell back.
    pub fn is_fallback(&self) -> bool {
        matches!(self.diagnostics.status, SolveStatus::Fallback(_))
    }

    /// True when the cell changes no estimate: a fallback, or every `α` zero (the base
    /// estimate bit for bit; a render phase skips such cells).
    pub fn is_zero(&self) -> bool {
        let k = self.layout.overlapping as usize;
        self.is_fallback()
            || (self.partitions().all(|(_, a)| a == [0.0; CHANNELS])
                && (0..k).all(|j| self.alpha_overlapping(j) == [0.0; CHANNELS]))
    }

    fn broadcast(&self, a: &[f64]) -> [f64; CHANNELS] {
        if a.len() == 1 {
            [a[0]; CHANNELS]
        } else {
            [a[0], a[1], a[2]]
        }
    }

    /// `α_k` of partition `id` (0 when not fitted).
    pub fn alpha_partition(&self, id: u32) -> [f64; CHANNELS] {
        let c = self.color.channels();
        match self.partition_ids.binary_search(&id) {
            Ok(s) => self.broadcast(&self.partition_alpha[s * c..(s + 1) * c]),
            Err(_) => [0.0; CHANNELS],
        }
    }

    /// `α` of overlapping component `j` (0 when `j >= K`).
    pub fn alpha_overlapping(&self, j: usize) -> [f64; CHANNELS] {
        let c = self.color.channels();
        self.overlapping_alpha
            .get(j * c..(j + 1) * c)
            .map_or([0.0; CHANNELS], |a| self.broadcast(a))
    }

    /// Fitted partitions in increasing index order with their `α` (per channel).
    pub fn partitions(&self) -> impl Iterator<Item = (u32, [f64; CHANNELS])> + '_ {
        let c = self.color.channels();
        self.partition_ids.iter().enumerate().map(move |(s, &id)| {
            (
                id,
                self.broadcast(&self.partition_alpha[s * c..(s + 1) * c]),
            )
        })
    }

    /// `Σ_k α_k` per channel: added once per vertex [Hua eq. 17].
    pub fn alpha_sum(&self) -> [f64; CHANNELS] {
        self.alpha_sum
    }

    /// The CV term of one sample, `Σ_k α_k λ_k(x) / p(x)` per channel.
    ///
    /// Zero for a non-positive or non-finite pdf, and for an overlapping slice of the wrong
    /// length (such a sample is not a valid CV sample; the caller keeps its plain value).
    pub fn cv_term(&self, sample: &CvSample<'_>) -> [f64; CHANNELS] {
        let mut out = [0.0; CHANNELS];
        if !(sample.pdf > 0.0)
            || !sample.pdf.is_finite()
            || sample.overlapping.len() != self.layout.overlapping as usize
        {
            return out;
        }
        let inv_p = 1.0 / sample.pdf;
        let c = self.color.channels();
        let mut add = |a: &[f64], r: f64| {
            for (ch, o) in out.iter_mut().enumerate() {
                *o += a[if c == 1 { 0 } else { ch }] * r;
            }
        };
        for (j, &l) in sample.overlapping.iter().enumerate() {
            if l != 0.0 {
                add(&self.overlapping_alpha[j * c..(j + 1) * c], l * inv_p);
            }
        }
        if let Some((id, l)) = sample.partition
            && l != 0.0
            && let Ok(s) = self.partition_ids.binary_search(&id)
        {
            add(&self.partition_alpha[s * c..(s + 1) * c], l * inv_p);
        }
        out
    }

    /// The CV terms of a cell's recorded samples, summed with their weights:
    /// `Σ_i w_i Σ_k α_k λ_k(x_i)/p(x_i) = Σ_k α_k g_k` per channel, `g_k = Σ w λ_k/p` the
    /// accumulator's first moments. With unit weights this is [`cv_term`](Self::cv_term)
    /// summed over the samples, so the controlled estimates of `n` vertices sum to their plain
    /// values plus `n Σα − summed_term` [Hua eq. 17]: what the coefficients would change in
    /// the pixel sums of those samples, without the samples. Components the accumulator did
    /// not sample contribute nothing; a layout mismatch gives zero.
    pub fn summed_term(&self, acc: &CellAccumulator) -> [f64; CHANNELS] {
        let mut out = [0.0; CHANNELS];
        if acc.layout() != self.layout {
            return out;
        }
        let mut add = |a: [f64; CHANNELS], g: f64| {
            for (o, a) in out.iter_mut().zip(a) {
                *o += a * g;
            }
        };
        for j in 0..self.layout.overlapping as usize {
            add(self.alpha_overlapping(j), acc.g_overlapping(j));
        }
        for p in acc.partitions() {
            add(self.alpha_partition(p.id), p.g);
        }
        out
    }

    /// The controlled sample value `F − Σ_k α_k λ_k / p` (add [`alpha_sum`](Self::alpha_sum)
    /// once per vertex).
    pub fn apply(&self, value: [f64; CHANNELS], sample: &CvSample<'_>) -> [f64; CHANNELS] {
        let t = self.cv_term(sample);
        [value[0] - t[0], value[1] - t[1], value[2] - t[2]]
    }
}

/// In-sample variance the coefficients `co` remove from the training samples of `acc`,
/// **within each technique**: `Σ_c (R₀ − R)` over the channels of the colour mode, with the
/// plain estimator's sum of squares `R₀` and the controlled one's `R` (below).
///
/// A vertex's estimate takes one sample of each technique (NEE and BSDF) [Hua eq. 17], so
/// its variance is the sum of the techniques' own variances: the spread *between* the
/// techniques' mean values — large wherever one technique does the work, e.g. a small light
/// that NEE finds and the BSDF sample misses — is no variance of the estimator, although the
/// pooled regression sees it and its fit "explains" it with the components' technique-like
/// `λ/p`. Hence the sums of squares are pooled minus between-technique:
///
/// ```text
/// R  = Σw(r − r̄)² − W_L W_B / W · (r̄_L − r̄_B)²,    r = y − αᵀg,  g = λ/p,
/// Σw(y − αᵀg)² = Σwy² − 2αᵀb + αᵀAα   [Hua eq. 21],   Σw(y − αᵀg) = Σwy − αᵀΣwg,
/// ```
///
/// `r̄_L`, `r̄_B` the light and BSDF techniques' weighted means (their sums:
/// [`CellAccumulator::technique_sums`]), `W_L`, `W_B` their weights; `R₀` is `R` at `α = 0`.
/// Centred (per technique) because a constant added to every sample's value does not
/// change the estimator's variance, and the ridge shrinks `α` toward zero, not toward the
/// shift [Hua eq. 14] that is equivalent to it. What remains pooled is the spread of each
/// technique's mean over the cell's vertices, which the fit may partly explain too: the
/// figure is an in-sample, optimistic one. In the units of the training weights [Hua eq. 25,
/// 29]: summed over the cells of a table and divided by the image's own sum of squares (the
/// image variance of [`crate::table::AccumulatorTable::Moments`]) it is the fraction of the
/// image's per-sample variance the fits remove. `0` for the plain estimator (every
/// `α = 0`). An accumulator without technique sums (fed only through
/// [`CellAccumulator::add`], or decoded from version 2) gives the pooled figure.
pub fn variance_reduction(acc: &CellAccumulator, co: &CellCoefficients) -> f64 {
    let c = acc.color().channels();
    let k = acc.layout().overlapping as usize;
    let sw = acc.weight_sum();
    let plain = co
        .partition_alpha
        .iter()
        .chain(&co.overlapping_alpha)
        .all(|&a| a == 0.0);
    if plain || !(sw > 0.0) || co.layout != acc.layout() || co.color != acc.color() {
        return 0.0;
    }
    let (wl, yl, gl_overlap) = acc.technique_sums();
    // Per channel: αᵀb, αᵀAα, αᵀΣwg and its light-technique part, summed over the
    // overlapping block, then each fitted partition's diagonal and cross terms (each
    // partition's moments looked up once for all channels: a lookup per channel and
    // partition was 4 % of a many-light training pass's instructions).
    let mut sums = [[0.0f64; 4]; CHANNELS];
    // A channel whose values are all zero, or whose moments were not recorded (a
    // version-1 accumulator): nothing to remove that the sums could show.
    let active: [bool; CHANNELS] =
        std::array::from_fn(|ch| ch < c && acc.value_moments(ch).1 != 0.0);
    let ao = |j: usize, ch: usize| co.overlapping_alpha[j * c + ch];
    for (ch, t) in sums.iter_mut().enumerate().filter(|(ch, _)| active[*ch]) {
        let [ab, aa, ag, ag_light] = t;
        for (i, &gl) in gl_overlap.iter().enumerate() {
            *ab += ao(i, ch) * acc.b_overlapping(i)[ch];
            *ag += ao(i, ch) * acc.g_overlapping(i);
            *ag_light += ao(i, ch) * gl;
            for j in 0..k {
                *aa += ao(i, ch) * acc.dense(i, j) * ao(j, ch);
            }
        }
    }
    for (s, &id) in co.partition_ids.iter().enumerate() {
        let Some(p) = acc.partition(id) else { continue };
        for (ch, t) in sums.iter_mut().enumerate().filter(|(ch, _)| active[*ch]) {
            let [ab, aa, ag, ag_light] = t;
            let a = co.partition_alpha[s * c + ch];
            let cross: f64 = (0..k).map(|j| p.cross[j] * ao(j, ch)).sum();
            *ab += a * p.b[ch];
            *ag += a * p.g;
            *ag_light += a * p.g_light;
            *aa += a * (a * p.diag + 2.0 * cross);
        }
    }
    let mut total = 0.0;
    for (ch, &yl) in yl.iter().enumerate().take(c) {
        if !active[ch] {
            continue;
        }
        let (sy, syy) = acc.value_moments(ch);
        let [ab, aa, ag, ag_light] = sums[ch];
        let r0 = within(centred(sy, syy, sw), sw, wl, sy, yl);
        let r = within(
            centred(sy - ag, syy - 2.0 * ab + aa, sw),
            sw,
            wl,
            sy - ag,
            yl - ag_light,
        );
        total += r0 - r;
    }
    if total.is_finite() { total } else { 0.0 }
}

/// Weighted sum of squares of a cell's training values about their techniques' weighted
/// means, summed over the channels of its colour mode: `Σ_c R₀` of [`variance_reduction`],
/// the variance the plain estimator leaves at the cell's controlled vertices
/// (training-weight units [Hua eq. 25, 29]). `0` for an empty cell or a version-1
/// accumulator (no value moments).
pub fn value_variance(acc: &CellAccumulator) -> f64 {
    let sw = acc.weight_sum();
    if !(sw > 0.0) {
        return 0.0;
    }
    let (wl, yl, _) = acc.technique_sums();
    let total: f64 = (0..acc.color().channels())
        .map(|ch| {
            let (sy, syy) = acc.value_moments(ch);
            within(centred(sy, syy, sw), sw, wl, sy, yl[ch])
        })
        .sum();
    if total.is_finite() { total } else { 0.0 }
}

/// A pooled centred sum of squares `pooled` (total weight `w`, total weighted sum `sum`)
/// less its between-technique part `W_L W_B / W · (m_L − m_B)²`, the light technique having
/// weight `w_light` and weighted sum `sum_light`; clamped at 0 against rounding. Without
/// both techniques' weight the pooled figure is the within one.
fn within(pooled: f64, w: f64, w_light: f64, sum: f64, sum_light: f64) -> f64 {
    let w_bsdf = w - w_light;
    if !(w_light > 0.0 && w_bsdf > 0.0) {
        return pooled;
    }
    let d = sum_light / w_light - (sum - sum_light) / w_bsdf;
    (pooled - w_light * w_bsdf / w * d * d).max(0.0)
}

/// `Σwy² − (Σwy)²/Σw`, clamped at 0 against rounding.
fn centred(sum: f64, sum_sq: f64, weight_sum: f64) -> f64 {
    (sum_sq - sum * sum / weight_sum).max(0.0)
}

/// Sampled partitions solved as one component: a run `range` of a cell's partitions (in
/// [`CellAccumulator::partitions`] order) and its merged moments.
///
/// A group `G` is the component of the mixture `λ_G = Σ_{k∈G} t_k λ_k`, `t_k = n_k / n_G`
/// (`n` the samples with `λ ≠ 0`): a convex combination of the members' normalised pdfs,
/// so it integrates to one and is a valid CV [Hua eq. 17]. The partitions' pdfs never
/// overlap [Hua eq. 30], so a sample of member `k` has `λ_G/p = t_k λ_k/p` and the group's
/// sums follow from the members' exactly: `A_GG = Σ t_k² A_kk`, `A_{G,j} = Σ t_k A_{k,j}`,
/// `b_G = Σ t_k b_k`. Its coefficient `α_G` is the members' `α_k = t_k α_G` (the terms,
/// and `Σ_k α_k = α_G`, are the same), so the render phase needs nothing but the
/// members' coefficients. `t` is computed from the training samples: any fixed `t` keeps the
/// estimator unbiased, as any fixed `α` does.
struct Group {
    range: std::ops::Range<usize>,
    count: u64,
    diag: f64,
    /// `A_{G,j}` for the `K` overlapping components.
    cross: Vec<f64>,
    /// `b_G` per channel of the colour mode.
    b: Vec<f64>,
}

impl Group {
    fn of(parts: &[PartitionMoments<'_>], range: std::ops::Range<usize>, c: usize) -> Self {
        let members = &parts[range.clone()];
        let count: u64 = members.iter().map(|p| p.count).sum();
        let k = members.first().map_or(0, |p| p.cross.len());
        let mut g = Self {
            range,
            count,
            diag: 0.0,
            cross: vec![0.0; k],
            b: vec![0.0; c],
        };
        for p in members {
            // A lone partition has `t = 1`: its own sums, bit for bit.
            let t = share(p.count, count);
            g.diag += t * t * p.diag;
            for (x, &y) in g.cross.iter_mut().zip(p.cross) {
                *x += t * y;
            }
            for (x, &y) in g.b.iter_mut().zip(p.b) {
                *x += t * y;
            }
        }
        g
    }

    fn is_active(&self, policy: &SolvePolicy) -> bool {
        self.count >= policy.min_partition_samples && self.diag > 0.0
    }

    /// Appends the members' coefficients `α_k = t_k α_G` (`alpha`: `α_G` per channel).
    fn expand(&self, parts: &[PartitionMoments<'_>], alpha: &[f64], out: &mut CellCoefficients) {
        for p in &parts[self.range.clone()] {
            if p.count == 0 {
                continue;
            }
            let t = share(p.count, self.count);
            out.partition_ids.push(p.id);
            out.partition_alpha.extend(alpha.iter().map(|a| t * a));
        }
    }
}

/// `t_k = n_k / n_G` (0 for an empty group).
fn share(n: u64, total: u64) -> f64 {
    if total == 0 {
        0.0
    } else {
        n as f64 / total as f64
    }
}

/// The groups a cell's sampled partitions are solved in: along the binary tree of partition
/// index ranges (`[lo, hi)` splits at `lo + (hi − lo)/2`, the order in which the light
/// clustering's median splits number their clusters, so a subtree is a spatially compact set
/// of lights), a range is split while each half that has samples has at least
/// `min_group_samples` of them. With 1 every sampled partition is its own group.
///
/// Why: a partition's coefficient is fitted from its own samples only (the partition block
/// is diagonal), so with many lights and few samples per light in a cell the fits follow
/// the noise of single samples; `Σ_k α_k` then adds the noise of every one of them to every
/// vertex of the cell. Merging such partitions trades the per-light resolution the data
/// cannot support for coefficients it can.
fn partition_groups<'a>(
    acc: &'a CellAccumulator,
    policy: &SolvePolicy,
) -> (Vec<PartitionMoments<'a>>, Vec<Group>) {
    fn split(
        parts: &[PartitionMoments<'_>],
        at: usize,
        (lo, hi): (u32, u32),
        min: u64,
        out: &mut Vec<std::ops::Range<usize>>,
    ) {
        let here = &parts[at..];
        if here.is_empty() {
            return;
        }
        if here.len() == 1 {
            out.push(at..at + 1);
            return;
        }
        let mid = lo + (hi - lo) / 2;
        let cut = here.partition_point(|p| p.id < mid);
        let (left, right) = here.split_at(cut);
        let enough = |s: &[PartitionMoments<'_>]| {
            s.is_empty() || s.iter().map(|p| p.count).sum::<u64>() >= min
        };
        if enough(left) && enough(right) {
            split(&parts[..at + cut], at, (lo, mid), min, out);
            split(parts, at + cut, (mid, hi), min, out);
        } else {
            out.push(at..parts.len());
        }
    }
    let parts: Vec<_> = acc.partitions().collect();
    let mut ranges = Vec::new();
    let top = acc
        .layout()
        .partitions
        .max(parts.last().map_or(0, |p| p.id + 1));
    split(
        &parts,
        0,
        (0, top),
        policy.min_group_samples.max(1),
        &mut ranges,
    );
    let c = acc.color().channels();
    let groups = ranges
        .into_iter()
        .map(|r| Group::of(&parts, r, c))
        .collect();
    (parts, groups)
}

/// Common pre-checks; returns the diagnostics skeleton or the fallback coefficients.
fn precheck(
    acc: &CellAccumulator,
    policy: &SolvePolicy,
) -> Result<SolveDiagnostics, Box<CellCoefficients>> {
    let diag = SolveDiagnostics {
        status: SolveStatus::Solved,
        condition: f64::NAN,
        active_partitions: 0,
        active_overlapping: 0,
        effective_samples: acc.effective_samples(),
    };
    let reason = if acc.is_empty() {
        Some(FallbackReason::Empty)
    } else if acc.samples() < policy.min_samples {
        Some(FallbackReason::TooFewSamples)
    } else if !(diag.effective_samples >= policy.min_effective_samples) {
        Some(FallbackReason::TooFewEffectiveSamples)
    } else {
        None
    };
    match reason {
        Some(r) => Err(Box::new(fallback(acc, diag, r))),
        None => Ok(diag),
    }
}

fn fallback(
    acc: &CellAccumulator,
    diag: SolveDiagnostics,
    reason: FallbackReason,
) -> CellCoefficients {
    CellCoefficients::fallen_back(acc.layout(), acc.color(), diag, reason)
}

fn active_overlapping(acc: &CellAccumulator) -> Vec<usize> {
    (0..acc.layout().overlapping as usize)
        .filter(|&j| acc.dense(j, j) > 0.0)
        .collect()
}

/// Condition estimate from a Cholesky factor's diagonal: `(max Lᵢᵢ / min Lᵢᵢ)²`,
/// extended by `extra` (the scaled diagonal of eliminated rows).
fn condition_from_l(l_diag: impl Iterator<Item = f64>, extra: Option<f64>) -> f64 {
    let (mut lo, mut hi) = (f64::INFINITY, 0.0f64);
    for d in l_diag.map(|d| d * d).chain(extra) {
        lo = lo.min(d);
        hi = hi.max(d);
    }
    if lo > 0.0 { hi / lo } else { f64::INFINITY }
}

/// Solves a cell with the Schur complement of the partition block [Hua eq. 32–33].
///
/// `O(P_sampled · K² + K³)` time, `O(K²)` extra memory. Applies [`SolvePolicy`].
pub fn solve(acc: &CellAccumulator, policy: &SolvePolicy) -> CellCoefficients {
    let mut diag = match precheck(acc, policy) {
        Ok(d) => d,
        Err(c) => return *c,
    };
    let eps = policy.ridge.max(0.0);
    let c = acc.color().channels();
    let ov = active_overlapping(acc);
    let q = ov.len();
    let (parts, groups) = partition_groups(acc, policy);
    let is_active = |g: &&Group| g.is_active(policy);
    let active_partitions = groups.iter().filter(is_active).count();
    diag.active_partitions = active_partitions;
    diag.active_overlapping = q;
    if q == 0 && active_partitions == 0 {
        return fallback(acc, diag, FallbackReason::NoActiveComponents);
    }

    // Scaled Schur complement S̃ = D (B' − Σ_k c_k c_kᵀ / d'_k) D, D = diag(B')^{-1/2}, and
    // its right-hand side D (b_o − Σ_k c_k b_k / d'_k) [Hua eq. 32].
    let scale: Vec<f64> = ov
        .iter()
        .map(|&j| 1.0 / (acc.dense(j, j) * (1.0 + eps)).sqrt())
        .collect();
    let mut s = DMatrix::<f64>::zeros(q, q);
    let mut rhs = DMatrix::<f64>::zeros(q, c);
    for (a, &ja) in ov.iter().enumerate() {
        for (b, &jb) in ov.iter().enumerate() {
            s[(a, b)] = acc.dense(ja, jb);
        }
        s[(a, a)] *= 1.0 + eps;
        for ch in 0..c {
            rhs[(a, ch)] = acc.b_overlapping(ja)[ch];
        }
    }
    if q > 0 {
        let mut u = vec![0.0; q];
        for p in groups.iter().filter(is_active) {
            let dk = p.diag * (1.0 + eps);
            for (a, &ja) in ov.iter().enumerate() {
                u[a] = p.cross[ja] / dk;
            }
            for (a, &ja) in ov.iter().enumerate() {
                for (b, &jb) in ov.iter().enumerate().skip(a) {
                    s[(a, b)] -= u[a] * p.cross[jb];
                }
                for ch in 0..c {
                    rhs[(a, ch)] -= p.cross[ja] * (p.b[ch] / dk);
                }
            }
        }
        for a in 0..q {
            for b in a..q {
                let v = s[(a, b)] * scale[a] * scale[b];
                s[(a, b)] = v;
                s[(b, a)] = v;
            }
            for ch in 0..c {
                rhs[(a, ch)] *= scale[a];
            }
        }
    }

    let alpha_o = if q > 0 {
        let Some(chol) = s.cholesky() else {
            return fallback(acc, diag, FallbackReason::NotPositiveDefinite);
        };
        let extra = (active_partitions > 0).then_some(1.0);
        diag.condition = condition_from_l(chol.l_dirty().diagonal().iter().copied(), extra);
        let mut x = chol.solve(&rhs);
        for a in 0..q {
            for ch in 0..c {
                x[(a, ch)] *= scale[a];
            }
        }
        x
    } else {
        diag.condition = 1.0;
        DMatrix::zeros(0, c)
    };
    if !(diag.condition <= policy.max_condition) {
        return fallback(acc, diag, FallbackReason::IllConditioned);
    }

    // Back-substitution for the partitions [Hua eq. 33].
    let k = acc.layout().overlapping as usize;
    let mut out = CellCoefficients::zero(acc.layout(), acc.color(), diag);
    let members: usize = groups.iter().filter(is_active).map(|g| g.range.len()).sum();
    out.partition_ids.reserve_exact(members);
    out.partition_alpha.reserve_exact(members * c);
    let mut alpha = [0.0; CHANNELS];
    for p in groups.iter().filter(is_active) {
        let dk = p.diag * (1.0 + eps);
        for (ch, x) in alpha.iter_mut().enumerate().take(c) {
            let mut num = p.b[ch];
            for (a, &ja) in ov.iter().enumerate() {
                num -= p.cross[ja] * alpha_o[(a, ch)];
            }
            *x = num / dk;
        }
        p.expand(&parts, &alpha[..c], &mut out);
    }
    for (a, &ja) in ov.iter().enumerate() {
        for ch in 0..c {
            out.overlapping_alpha[ja * c + ch] = alpha_o[(a, ch)];
        }
    }
    debug_assert_eq!(out.overlapping_alpha.len(), k * c);
    if out
        .partition_alpha
        .iter()
        .chain(&out.overlapping_alpha)
        .any(|a| !a.is_finite())
    {
        return fallback(acc, diag, FallbackReason::NonFinite);
    }
    out.finish();
    out
}

/// Solves a cell by assembling the full (active) matrix and factorising it (Cholesky of
/// the Jacobi-scaled, regularised system). Same policy and result as [`solve`] up to
/// rounding; `O((P+K)³)` — use for small systems and as a test oracle.
pub fn solve_dense(acc: &CellAccumulator, policy: &SolvePolicy) -> CellCoefficients {
    let mut diag = match precheck(acc, policy) {
        Ok(d) => d,
        Err(c) => return *c,
    };
    let eps = policy.ridge.max(0.0);
    let c = acc.color().channels();
    let ov = active_overlapping(acc);
    let (all, groups) = partition_groups(acc, policy);
    let parts: Vec<&Group> = groups.iter().filter(|g| g.is_active(policy)).collect();
    let (np, q) = (parts.len(), ov.len());
    diag.active_partitions = np;
    diag.active_overlapping = q;
    let n = np + q;
    if n == 0 {
        return fallback(acc, diag, FallbackReason::NoActiveComponents);
    }
    let mut a = DMatrix::<f64>::zeros(n, n);
    let mut b = DMatrix::<f64>::zeros(n, c);
    for (i, p) in parts.iter().enumerate() {
        a[(i, i)] = p.diag;
        for (jj, &j) in ov.iter().enumerate() {
            a[(i, np + jj)] = p.cross[j];
            a[(np + jj, i)] = p.cross[j];
        }
        for ch in 0..c {
            b[(i, ch)] = p.b[ch];
        }
    }
    for (ii, &i) in ov.iter().enumerate() {
        for (jj, &j) in ov.iter().enumerate() {
            a[(np + ii, np + jj)] = acc.dense(i, j);
        }
        for ch in 0..c {
            b[(np + ii, ch)] = acc.b_overlapping(i)[ch];
        }
    }
    let scale = DVector::from_iterator(n, (0..n).map(|i| 1.0 / (a[(i, i)] * (1.0 + eps)).sqrt()));
    for i in 0..n {
        for j in 0..n {
            a[(i, j)] *= scale[i] * scale[j];
        }
        a[(i, i)] = 1.0;
        for ch in 0..c {
            b[(i, ch)] *= scale[i];
        }
    }
    let Some(chol) = a.cholesky() else {
        return fallback(acc, diag, FallbackReason::NotPositiveDefinite);
    };
    diag.condition = condition_from_l(chol.l_dirty().diagonal().iter().copied(), None);
    if !(diag.condition <= policy.max_condition) {
        return fallback(acc, diag, FallbackReason::IllConditioned);
    }
    let x = chol.solve(&b);
    let mut out = CellCoefficients::zero(acc.layout(), acc.color(), diag);
    for (i, p) in parts.iter().enumerate() {
        let alpha: Vec<f64> = (0..c).map(|ch| x[(i, ch)] * scale[i]).collect();
        p.expand(&all, &alpha, &mut out);
    }
    for (jj, &j) in ov.iter().enumerate() {
        for ch in 0..c {
            out.overlapping_alpha[j * c + ch] = x[(np + jj, ch)] * scale[np + jj];
        }
    }
    if out
        .partition_alpha
        .iter()
        .chain(&out.overlapping_alpha)
        .any(|a| !a.is_finite())
    {
        return fallback(acc, diag, FallbackReason::NonFinite);
    }
    out.finish();
    out
}

// ---------------------------------------------------------------------------------------
// Binary encoding of coefficients (the table the coordinator broadcasts).

/// Magic bytes of encoded [`CellCoefficients`].
pub const COEFFICIENTS_MAGIC: [u8; 4] = *b"CVCO";
/// Encoding version of [`CellCoefficients`].
pub const COEFFICIENTS_VERSION: u16 = 1;

const FALLBACK_CODES: [FallbackReason; 12] = [
    FallbackReason::Empty,
    FallbackReason::TooFewSamples,
    FallbackReason::TooFewEffectiveSamples,
    FallbackReason::NoActiveComponents,
    FallbackReason::NotPositiveDefinite,
    FallbackReason::IllConditioned,
    FallbackReason::NonFinite,
    FallbackReason::LowImageGain,
    FallbackReason::LowFitGain,
    FallbackReason::NoReduction,
    FallbackReason::HeldOutLoss,
    FallbackReason::Overfitted,
];

impl CellCoefficients {
    /// Encodes (little endian): magic `CVCO`, `u16` version, `u8` colour (0 RGB, 1 mono),
    /// `u8` status (0 solved, 1 + index of the [`FallbackReason`] in declaration order),
    /// `u32` P, `u32` K, `f64` condition, `u32` active partitions, `u32` active overlapping,
    /// `f64` effective samples, `K·C` `f64` overlapping `α`, `u32` entry count, then per
    /// fitted partition `u32` index and `C` `f64`.
    pub fn encode(&self) -> Vec<u8> {
        let c = self.color.channels();
        let mut out = Vec::with_capacity(
            46 + 8 * self.overlapping_alpha.len() + self.partition_ids.len() * (4 + 8 * c),
        );
        out.extend_from_slice(&COEFFICIENTS_MAGIC);
        out.extend_from_slice(&COEFFICIENTS_VERSION.to_le_bytes());
        out.push(match self.color {
            ColorMode::Rgb => 0,
            ColorMode::Mono => 1,
        });
        out.push(match self.diagnostics.status {
            SolveStatus::Solved => 0,
            SolveStatus::Fallback(r) => {
                1 + FALLBACK_CODES.iter().position(|&x| x == r).unwrap_or(0) as u8
            }
        });
        out.extend_from_slice(&self.layout.partitions.to_le_bytes());
        out.extend_from_slice(&self.layout.overlapping.to_le_bytes());
        out.extend_from_slice(&self.diagnostics.condition.to_le_bytes());
        out.extend_from_slice(&(self.diagnostics.active_partitions as u32).to_le_bytes());
        out.extend_from_slice(&(self.diagnostics.active_overlapping as u32).to_le_bytes());
        out.extend_from_slice(&self.diagnostics.effective_samples.to_le_bytes());
        for a in &self.overlapping_alpha {
            out.extend_from_slice(&a.to_le_bytes());
        }
        out.extend_from_slice(&(self.partition_ids.len() as u32).to_le_bytes());
        for (s, id) in self.partition_ids.iter().enumerate() {
            out.extend_from_slice(&id.to_le_bytes());
            for a in &self.partition_alpha[s * c..(s + 1) * c] {
                out.extend_from_slice(&a.to_le_bytes());
            }
        }
        out
    }

    /// Decodes and validates (sizes, sorted in-range indices, finite `α`); never panics.
    pub fn decode(bytes: &[u8]) -> Result<Self, CellError> {
        let mut r = Reader::new(bytes);
        if r.take(4)? != COEFFICIENTS_MAGIC {
            return Err(CellError::BadMagic);
        }
        let version = r.u16()?;
        if version != COEFFICIENTS_VERSION {
            return Err(CellError::UnsupportedVersion(version));
        }
        let color = match r.u8()? {
            0 => ColorMode::Rgb,
            1 => ColorMode::Mono,
            _ => return Err(CellError::BadHeader),
        };
        let status = match r.u8()? {
            0 => SolveStatus::Solved,
            k => SolveStatus::Fallback(
                *FALLBACK_CODES
                    .get(usize::from(k) - 1)
                    .ok_or(CellError::BadHeader)?,
            ),
        };
        let layout = ComponentLayout::new(r.u32()?, r.u32()?)?;
        let condition = {
            let at = r.pos();
            let v = f64::from_le_bytes(
                r.take(8)?
                    .try_into()
                    .map_err(|_| CellError::InvalidValue(at))?,
            );
            if v.is_nan() || v < 0.0 { f64::NAN } else { v }
        };
        let active_partitions = r.u32()? as usize;
        let active_overlapping = r.u32()? as usize;
        let effective_samples = r.nonneg_f64()?;
        let diagnostics = SolveDiagnostics {
            status,
            condition,
            active_partitions,
            active_overlapping,
            effective_samples,
        };
        let mut out = CellCoefficients::zero(layout, color, diagnostics);
        for a in out.overlapping_alpha.iter_mut() {
            *a = r.finite_f64()?;
        }
        let c = color.channels();
        let n = u64::from(r.u32()?);
        if n > u64::from(layout.partitions) || n * (4 + 8 * c as u64) > r.remaining() as u64 {
            return Err(CellError::BadEntryCount(n));
        }
        for _ in 0..n {
            let at = r.pos();
            let id = r.u32()?;
            if id >= layout.partitions || out.partition_ids.last().is_some_and(|&p| id <= p) {
                return Err(CellError::BadPartition(at));
            }
            out.partition_ids.push(id);
            for _ in 0..c {
                let a = r.finite_f64()?;
                out.partition_alpha.push(a);
            }
        }
        if !r.at_end() {
            return Err(CellError::Trailing(r.remaining()));
        }
        out.finish();
        Ok(out)
    }
}
