//! Per-cell accumulators of the CV normal equations [Hua eq. 21, 23, 25, 29].
//!
//! A spatial cell collects, over every training sample that lands in it, the sums of the
//! weighted least-squares system whose solution are the CV coefficients `α`:
//!
//! ```text
//! A_kl = Σ w λ_k λ_l / p²        b_k = Σ w F λ_k / p        (F = f / p)
//! ```
//!
//! [Hua eq. 21] for one integral, summed over all integrals of the cell [Hua eq. 23], with
//! the sample weight `w` = squared prefix throughput [Hua eq. 29], divided by
//! `(surrogate + 0.01)²` when optimising relative variance [Hua eq. 25]
//! (see [`training_weight`]).
//!
//! # Contracts
//! - `p` is the effective mixture density of the vertex [Hua eq. 16] and every `λ_k` is a
//!   normalised mixture of sampling pdfs [Hua eq. 18], **all in the same measure** as `p`.
//!   Only the ratios `λ_k / p` enter the sums, so the measure itself does not matter.
//! - `F` is the sample's balance-heuristic value `f/p` per RGB channel. With
//!   [`ColorMode::Mono`] the channels are averaged before accumulation [Hua §4.3].
//! - Components come in two kinds ([`ComponentLayout`]): `P` **partitioned** components
//!   (one per light or light cluster, the env map) whose pdfs never overlap, so a sample has
//!   a nonzero `λ_k` for at most one of them, and `K` **overlapping** components (BSDF,
//!   guiding lobes). The matrix `A` is therefore stored sparsely: the diagonal of the
//!   partition block, the `P × K` cross block and the small dense `K × K` block. A sorted
//!   list of the sampled partitions' indices points at their storage slots, so every
//!   reader (iteration, merge, encoding, equality) sees them in increasing index order:
//!   with at most [`SLOT_IS_PARTITION_MAX`] partitions, a bit set per sampled partition
//!   and a byte per partition give its slot, up to [`DIRECT_MAP_MAX`] a direct map from
//!   every partition to its slot (unsampled: none), else a sorted index list does; either way
//!   slots are appended in first-touch order (nothing moves) and only sampled partitions
//!   have one (but for a few partitions: all at the first sample, slot = partition).
//! - Accumulation is in `f64` whatever the caller's precision. A sample with a NaN/Inf
//!   anywhere, a non-positive pdf or an out-of-range index is **rejected and counted**
//!   ([`CellAccumulator::rejected`]) and leaves every sum untouched.
//! - [`CellAccumulator::merge`] is a plain element-wise `f64` addition (commutative, and
//!   associative up to rounding): merging a fixed list of accumulators in a canonical
//!   order always gives bitwise-identical sums, whatever the number of workers.
//! - [`CellAccumulator::encode`] / [`CellAccumulator::decode`] round-trip bit-exactly;
//!   decoding validates sizes, ordering and finiteness and never panics.
//!
//! # Hot loop
//! [`CellAccumulator::add`] allocates only when a partition is first seen in the cell (an
//! appended slot, in a list that grows by doubling; with `P > DIRECT_MAP_MAX` it also
//! inserts the index into the sorted `u32` list, else it sets a map entry, or a bit and a
//! byte). It
//! touches the accumulator itself (the overlapping components' sums are kept inside it for
//! small `K`) and the one sampled partition's entry, which holds its count: its slot is in
//! the accumulator's byte map for `P <= SLOT_IS_PARTITION_MAX`, else found through a direct
//! index map when `P <= DIRECT_MAP_MAX`, else by binary search with a one-entry cache for
//! runs of samples from the same light. In a training pass the cells are far larger than the
//! caches, so what a sample costs is the cache lines it touches (many-lights d5: one miss,
//! on the partition entry, where there were four).
//! Measured: 18–28 ns per sample for `P = 64`, `K = 2`, RGB (`benches/cells.rs`, warm).

use thiserror::Error;

/// Number of colour channels of sample values.
pub const CHANNELS: usize = 3;

/// Largest supported number of overlapping components `K` (the dense block is `K × K`).
pub const MAX_OVERLAPPING: u32 = 64;

/// The ε of relative-variance training weights [Hua eq. 25]: `w = t² / (s + ε)²`.
pub const SURROGATE_EPSILON: f64 = 0.01;

/// Training weight of a sample [Hua eq. 25, 29].
///
/// `throughput` is the (scalar, e.g. channel-mean) prefix path throughput `g(x)/p(x)` up to
/// the vertex; `surrogate` is the surrogate pixel value (e.g. luminance of a denoised
/// first-pass image) when optimising relative variance. A negative or non-finite surrogate
/// is treated as zero, so the weight stays finite.
#[inline]
pub fn training_weight(throughput: f64, surrogate: Option<f64>) -> f64 {
    let t2 = throughput * throughput;
    match surrogate {
        None => t2,
        Some(s) => {
            let s = if s.is_finite() && s > 0.0 { s } else { 0.0 };
            t2 / ((s + SURROGATE_EPSILON) * (s + SURROGATE_EPSILON))
        }
    }
}

/// Number and kinds of CV components of a cell.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct ComponentLayout {
    /// Partitioned (non-overlapping) components `P`: one per light/cluster, env map.
    pub partitions: u32,
    /// Overlapping components `K`: BSDF, guiding lobes (at most [`MAX_OVERLAPPING`]).
    pub overlapping: u32,
}

impl ComponentLayout {
    /// A layout, checking `overlapping <= MAX_OVERLAPPING`.
    pub fn new(partitions: u32, overlapping: u32) -> Result<Self, CellError> {
        if overlapping > MAX_OVERLAPPING {
            return Err(CellError::TooManyOverlapping(overlapping));
        }
        Ok(Self {
            partitions,
            overlapping,
        })
    }

    /// Total number of components `P + K`.
    pub fn components(&self) -> usize {
        self.partitions as usize + self.overlapping as usize
    }
}

/// Whether coefficients are fitted per RGB channel or once for the channel mean [Hua §4.3].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum ColorMode {
    /// One coefficient per channel (`b` has three columns).
    Rgb,
    /// One coefficient shared by all channels (`b` is fitted to the channel mean).
    Mono,
}

impl ColorMode {
    /// Number of right-hand-side columns: 3 or 1.
    pub fn channels(self) -> usize {
        match self {
            ColorMode::Rgb => CHANNELS,
            ColorMode::Mono => 1,
        }
    }
}

/// The CV components of one sample: its mixture density and component densities.
///
/// All densities in the same measure (see the module contract).
#[derive(Clone, Copy, Debug)]
pub struct CvSample<'a> {
    /// Effective mixture density `p(x)` [Hua eq. 16]; must be positive and finite.
    pub pdf: f64,
    /// The partitioned component whose `λ_k(x)` may be nonzero, with that value
    /// (`None` when the sample lies in no partition, e.g. a BSDF sample that escaped with
    /// no env map).
    pub partition: Option<(u32, f64)>,
    /// `λ_j(x)` of the `K` overlapping components, in layout order.
    pub overlapping: &'a [f64],
}

/// The technique of a vertex's one-sample-per-technique estimator that drew a sample
/// [Hua eq. 17]: NEE (a light sample) or the BSDF sample.
///
/// The accumulator keeps the light technique's sums apart (`Σw`, `Σwy`, `Σw λ/p`), so that
/// [`crate::solve::variance_reduction`] can measure the variance the fits remove *within*
/// each technique: the deterministic estimator takes one sample of each, so the spread
/// between the techniques' means, which the pooled regression also sees, is no variance of
/// its (see [`CellAccumulator::technique_sums`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Technique {
    /// Next-event estimation: a point sampled on a light (or the env map).
    Light,
    /// The BSDF sample (and every sample whose technique is not told: [`CellAccumulator::add`]).
    Bsdf,
}

/// Why a sample was not accumulated (it is counted in [`CellAccumulator::rejected`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Error)]
pub enum SampleRejection {
    /// A value, weight or density is NaN/±Inf, or a product would overflow.
    #[error("non-finite sample")]
    NonFinite,
    /// The mixture density is zero or negative.
    #[error("non-positive mixture density")]
    NonPositivePdf,
    /// The weight is negative.
    #[error("negative sample weight")]
    NegativeWeight,
    /// The partition index is not below the layout's `P`.
    #[error("partition index out of range")]
    PartitionOutOfRange,
    /// The overlapping slice does not have `K` entries.
    #[error("wrong number of overlapping components")]
    WrongComponentCount,
}

/// Errors of layouts, merges and decoding.
#[derive(Clone, Debug, PartialEq, Eq, Error)]
pub enum CellError {
    /// More overlapping components than [`MAX_OVERLAPPING`].
    #[error("{0} overlapping components (max {MAX_OVERLAPPING})")]
    TooManyOverlapping(u32),
    /// Merging accumulators of different layouts or colour modes.
    #[error("cannot merge accumulators of different layouts or colour modes")]
    LayoutMismatch,
    /// The bytes end before the structure does.
    #[error("truncated accumulator: needed {needed} bytes at offset {offset}")]
    Truncated {
        /// Offset at which more bytes were needed.
        offset: usize,
        /// Bytes needed there.
        needed: usize,
    },
    /// The bytes do not start with the accumulator magic.
    #[error("not an accumulator (bad magic)")]
    BadMagic,
    /// An encoding version this build does not read.
    #[error("unsupported accumulator version {0}")]
    UnsupportedVersion(u16),
    /// Unknown colour-mode tag or non-zero reserved byte.
    #[error("bad header field")]
    BadHeader,
    /// A NaN/Inf or an impossible negative value in the payload.
    #[error("invalid value at offset {0}")]
    InvalidValue(usize),
    /// Partition entries not strictly increasing, out of range, or with zero count.
    #[error("invalid partition entry at offset {0}")]
    BadPartition(usize),
    /// More partition entries than the layout or the payload can hold.
    #[error("partition entry count {0} impossible")]
    BadEntryCount(u64),
    /// Bytes left after the structure.
    #[error("{0} trailing bytes")]
    Trailing(usize),
}

/// Moments of one sampled partition (a view into a [`CellAccumulator`]).
#[derive(Clone, Copy, Debug)]
pub struct PartitionMoments<'a> {
    /// Partition index `k < P`.
    pub id: u32,
    /// Number of accepted samples with `λ_k ≠ 0`.
    pub count: u64,
    /// `A_kk = Σ w (λ_k/p)²`.
    pub diag: f64,
    /// `A_{k,P+j} = Σ w (λ_k/p)(λ_j/p)` for the `K` overlapping components.
    pub cross: &'a [f64],
    /// `b_k = Σ w F (λ_k/p)` per channel of the colour mode.
    pub b: &'a [f64],
    /// `Σ w λ_k/p`.
    pub g: f64,
    /// The light technique's part of `g` ([`Technique::Light`]).
    pub g_light: f64,
}

/// Normal-equation sums of one spatial cell.
///
/// Equality compares the sums and counters (not the hot-loop cache).
#[derive(Clone, Debug)]
pub struct CellAccumulator {
    layout: ComponentLayout,
    color: ColorMode,
    samples: u64,
    rejected: u64,
    weight_sum: f64,
    weight_sq_sum: f64,
    /// `[Σ w y_c, Σ w y_c²]` per channel `c` of the colour mode (the first `2·C` entries),
    /// for the variance a fit removes (see [`CellAccumulator::value_moments`]).
    value: [f64; 2 * CHANNELS],
    /// The light technique's `[Σ w, Σ w y_c]` (the first `1 + C` entries; see [`Technique`]).
    light: [f64; 1 + CHANNELS],
    /// The overlapping components' sums ([`OverlapSums`]).
    over: OverlapSums,
    /// With `P <= SLOT_IS_PARTITION_MAX`: bit `k` set once partition `k` was sampled (its
    /// slot is `k` with `P <= FIRST_SLOTS`, else `slot_of[k]`). The bits are the sorted
    /// list of sampled partitions.
    sampled: u64,
    /// With `FIRST_SLOTS < P <= SLOT_IS_PARTITION_MAX`: the storage slot of each sampled
    /// partition (slots in first-touch order); meaningless where the bit in `sampled` is
    /// clear.
    slot_of: [u8; SLOT_IS_PARTITION_MAX as usize],
    /// With `P > DIRECT_MAP_MAX`: the sampled partition indices, strictly increasing (else
    /// empty: `slot_map` is the sorted list there).
    part_ids: Vec<u32>,
    /// Per entry of `part_ids`: the storage slot of its moments.
    part_slots: Vec<u32>,
    /// Per storage slot: `[diag, cross_0..K, b_0..C, g, g_light, count]` with
    /// `g = Σ w λ_k/p`, `g_light` its light-technique part and `count` the accepted samples
    /// of the partition (an integer in `f64`, exact below 2⁵³; decoding refuses larger): one
    /// slot per sampled partition, appended in first-touch order, or with
    /// `P <= FIRST_SLOTS` all `P` from the first partition sample on (zero for a partition
    /// not sampled).
    part_data: Vec<f64>,
    /// Partition and storage slot of the most recently used partition (`u32::MAX` = none;
    /// hot-loop cache, not part of equality; only with `P > SLOT_IS_PARTITION_MAX`).
    last: (u32, u32),
    /// Direct partition → storage slot map (`u32::MAX` = not sampled) when
    /// `SLOT_IS_PARTITION_MAX < P <= DIRECT_MAP_MAX`, else empty: slots come from `sampled`
    /// and `slot_of`, or by binary search in `part_ids`. Where it exists it is also the
    /// sorted list of sampled partitions (a new partition appends its slot, with no sorted
    /// insert: 256 lights made that insert ≈ 5 % of a training pass).
    slot_map: Vec<u32>,
}

/// A hint to load the cache line of `x` (no architectural effect; nothing elsewhere than on
/// `x86_64`).
#[inline(always)]
pub fn prefetch_read<T>(x: &T) {
    prefetch_ptr(x as *const T);
}

/// A hint to load every cache line of `x` (its first line, then one per 64 bytes to its
/// end; no architectural effect).
#[inline(always)]
pub fn prefetch_lines<T>(x: &T) {
    let start = (x as *const T).cast::<u8>();
    let mut offset = 0;
    while offset < std::mem::size_of::<T>() {
        prefetch_ptr(start.wrapping_add(offset));
        offset += 64;
    }
    // The last byte: `x` need not start on a line boundary.
    if std::mem::size_of::<T>() > 0 {
        prefetch_ptr(start.wrapping_add(std::mem::size_of::<T>() - 1));
    }
}

/// A hint to load the cache line at `p`, which need not point to anything valid (a
/// prefetch cannot fault).
#[inline(always)]
fn prefetch_ptr<T>(p: *const T) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_MM_HINT_T0, _mm_prefetch};
        // SAFETY: a prefetch accesses no memory architecturally: it cannot fault, whatever
        // the address.
        unsafe { _mm_prefetch::<_MM_HINT_T0>(p.cast()) };
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = p;
}

/// Values [`OverlapSums`] keeps in the accumulator itself: the sums of a layout with one
/// overlapping component (the BSDF) in RGB take 6.
const INLINE_OVERLAP: usize = 8;

/// The sums of the `K` overlapping components, one array
/// `[dense | b | g | g_light]`: the packed upper triangle (row-major, `j >= i`) of the
/// `K × K` block, the `K × C` right-hand sides, `Σ w λ_j/p` (for centred residuals) and its
/// light-technique part ([`Technique`]).
///
/// Kept inside the accumulator when it fits ([`INLINE_OVERLAP`]): a training sample updates
/// them, and in their own allocations they were a cache miss of their own per sample
/// (many-lights d5 training: one of the four loads that made up ¾ of
/// [`CellAccumulator::add`]'s time, `perf annotate`).
#[derive(Clone, Debug)]
enum OverlapSums {
    Inline { len: u8, v: [f64; INLINE_OVERLAP] },
    Heap(Vec<f64>),
}

impl OverlapSums {
    fn zeros(len: usize) -> Self {
        if len <= INLINE_OVERLAP {
            Self::Inline {
                len: len as u8,
                v: [0.0; INLINE_OVERLAP],
            }
        } else {
            Self::Heap(vec![0.0; len])
        }
    }

    #[inline]
    fn as_slice(&self) -> &[f64] {
        match self {
            Self::Inline { len, v } => &v[..*len as usize],
            Self::Heap(v) => v,
        }
    }

    #[inline]
    fn as_mut_slice(&mut self) -> &mut [f64] {
        match self {
            Self::Inline { len, v } => &mut v[..*len as usize],
            Self::Heap(v) => v,
        }
    }
}

/// The four parts of an [`OverlapSums`] array of `k` components and `c` channels:
/// `(dense, b, g, g_light)`.
#[inline]
fn overlap_parts(v: &[f64], k: usize, c: usize) -> (&[f64], &[f64], &[f64], &[f64]) {
    let (dense, rest) = v.split_at(k * (k + 1) / 2);
    let (b, rest) = rest.split_at(k * c);
    let (g, g_light) = rest.split_at(k);
    (dense, b, g, g_light)
}

/// [`overlap_parts`], mutable. Always inlined: a training sample's update calls it with
/// constant `k` and `c`, and called out of line it cost ≈ 12 instructions per sample.
#[inline(always)]
fn overlap_parts_mut(
    v: &mut [f64],
    k: usize,
    c: usize,
) -> (&mut [f64], &mut [f64], &mut [f64], &mut [f64]) {
    let (dense, rest) = v.split_at_mut(k * (k + 1) / 2);
    let (b, rest) = rest.split_at_mut(k * c);
    let (g, g_light) = rest.split_at_mut(k);
    (dense, b, g, g_light)
}

/// The sampled partitions of an accumulator in increasing index order, with their storage
/// slots ([`CellAccumulator::sorted_slots`]).
enum SortedSlots<'a> {
    /// The set bits of [`CellAccumulator`]'s `sampled` and its slot bytes (`None`: slot =
    /// partition).
    Bits(u64, Option<&'a [u8; SLOT_IS_PARTITION_MAX as usize]>),
    /// Its sorted index list and the slots.
    Lists(std::iter::Zip<std::slice::Iter<'a, u32>, std::slice::Iter<'a, u32>>),
    /// Its direct map, from partition `next` on, with `left` sampled partitions to come.
    Map {
        map: &'a [u32],
        next: usize,
        left: usize,
    },
}

impl Iterator for SortedSlots<'_> {
    type Item = (u32, usize);

    #[inline]
    fn next(&mut self) -> Option<(u32, usize)> {
        match self {
            Self::Bits(b, slot_of) => {
                let k = (*b != 0).then(|| b.trailing_zeros())?;
                *b &= *b - 1;
                Some((
                    k,
                    slot_of.map_or(k as usize, |s| usize::from(s[k as usize])),
                ))
            }
            Self::Lists(l) => l.next().map(|(&id, &s)| (id, s as usize)),
            Self::Map { map, next, left } => {
                if *left == 0 {
                    return None;
                }
                let k = *next + map[*next..].iter().position(|&s| s != u32::MAX)?;
                *next = k + 1;
                *left -= 1;
                Some((k as u32, map[k] as usize))
            }
        }
    }

    fn size_hint(&self) -> (usize, Option<usize>) {
        let n = match self {
            Self::Bits(b, _) => b.count_ones() as usize,
            Self::Lists(l) => l.len(),
            Self::Map { left, .. } => *left,
        };
        (n, Some(n))
    }
}

impl ExactSizeIterator for SortedSlots<'_> {}

/// Largest `P` whose accumulators find partition `k`'s slot in a byte map inside the
/// accumulator (`slot_of[k]`), with a bit per partition set at its first sample that is
/// also the sorted list of sampled partitions (hence at most 64). A sample then finds its
/// entry through the accumulator's own cache lines, and its count in the same entry.
/// Many-lights d5 training (64 lights): a separate slot map and count array were two of the
/// four cache misses that made up ¾ of [`CellAccumulator::add`]'s time, and a partition's
/// first sample in a cell (an insertion into a sorted index list) 6 % of the training pass.
///
/// Only sampled partitions have slots. Until 2026-12-07 all `P` were allocated at a cell's
/// first partition sample (4 KiB for 64 lights): a large image's training tiles each touch
/// tens of thousands of cells a few times (deep vertices land everywhere), and zeroing,
/// merging and cloning those slots took more time than the samples (many-lights d5,
/// 960×540, 17 spp: see `docs/bench/README.md`).
pub const SLOT_IS_PARTITION_MAX: u32 = 64;

/// Slots an accumulator with `P <= SLOT_IS_PARTITION_MAX` makes room for at its first
/// partition sample (then the list doubles); with `P <= FIRST_SLOTS` all `P` are made
/// then, partition `k` in slot `k` (a few lights: every cell meets them all).
const FIRST_SLOTS: usize = 16;

/// Partitions an accumulator with `P > SLOT_IS_PARTITION_MAX` makes room for at its first
/// partition sample: a cell of a many-light scene meets many of its lights, and growing the
/// lists one partition at a time cost a reallocation and copy per doubling in every cell
/// (many-lights, 64 lights, 256², 16 training spp, one thread: training 1.45–1.49 s with
/// room for 8, 1.36–1.43 s with 64; `cv_overhead` harness).
const FIRST_RESERVE: usize = 64;

/// Largest `P` for which an accumulator keeps a direct partition → slot map (4 bytes per
/// partition per cell); above it, lookups are binary searches over the sampled partitions.
pub const DIRECT_MAP_MAX: u32 = 1024;

#[inline]
fn row_start(k: usize, i: usize) -> usize {
    // Σ_{r<i} (k - r) = i k - i (i - 1) / 2
    i * k - i * i.saturating_sub(1) / 2
}

impl PartialEq for CellAccumulator {
    fn eq(&self, o: &Self) -> bool {
        self.layout == o.layout
            && self.color == o.color
            && self.samples == o.samples
            && self.rejected == o.rejected
            && self.weight_sum == o.weight_sum
            && self.weight_sq_sum == o.weight_sq_sum
            && self.value == o.value
            && self.over.as_slice() == o.over.as_slice()
            && self.light == o.light
            && self.sampled_partitions() == o.sampled_partitions()
            && self
                .sorted_slots()
                .zip(o.sorted_slots())
                .all(|((i, a), (j, b))| i == j && self.stored_entry(a) == o.stored_entry(b))
    }
}

impl CellAccumulator {
    /// An empty accumulator.
    pub fn new(layout: ComponentLayout, color: ColorMode) -> Self {
        let k = layout.overlapping as usize;
        Self {
            layout,
            color,
            samples: 0,
            rejected: 0,
            weight_sum: 0.0,
            weight_sq_sum: 0.0,
            value: [0.0; 2 * CHANNELS],
            light: [0.0; 1 + CHANNELS],
            over: OverlapSums::zeros(k * (k + 1) / 2 + k * color.channels() + 2 * k),
            sampled: 0,
            slot_of: [0; SLOT_IS_PARTITION_MAX as usize],
            part_ids: Vec::new(),
            part_slots: Vec::new(),
            part_data: Vec::new(),
            last: (u32::MAX, 0),
            slot_map: if (SLOT_IS_PARTITION_MAX + 1..=DIRECT_MAP_MAX).contains(&layout.partitions) {
                vec![u32::MAX; layout.partitions as usize]
            } else {
                Vec::new()
            },
        }
    }

    /// The component layout.
    pub fn layout(&self) -> ComponentLayout {
        self.layout
    }

    /// The colour mode.
    pub fn color(&self) -> ColorMode {
        self.color
    }

    /// Accepted samples.
    pub fn samples(&self) -> u64 {
        self.samples
    }

    /// Rejected samples (non-finite or invalid; never merged into the sums).
    pub fn rejected(&self) -> u64 {
        self.rejected
    }

    /// `Σ w` over accepted samples.
    pub fn weight_sum(&self) -> f64 {
        self.weight_sum
    }

    /// `(Σ w y, Σ w y²)` of channel `ch` of the colour mode (`y` = the sample value `F`,
    /// or its channel mean for [`ColorMode::Mono`]): with `Σ w`, the weighted variance of
    /// the plain estimator in the cell, against which a fit's residual is measured.
    pub fn value_moments(&self, ch: usize) -> (f64, f64) {
        let c = self.color.channels();
        (self.value[ch], self.value[c + ch])
    }

    /// Kish effective sample count `(Σ w)² / Σ w²` (0 when empty).
    pub fn effective_samples(&self) -> f64 {
        if self.weight_sq_sum > 0.0 {
            // Divide before squaring so that huge weights do not overflow.
            let r = self.weight_sum / self.weight_sq_sum.sqrt();
            r * r
        } else {
            0.0
        }
    }

    /// True when no sample was accepted.
    pub fn is_empty(&self) -> bool {
        self.samples == 0
    }

    /// Number of partitions with at least one sample.
    pub fn sampled_partitions(&self) -> usize {
        if self.slot_is_partition() {
            self.sampled.count_ones() as usize
        } else {
            // One slot per sampled partition, appended.
            self.part_data.len() / self.slot_len()
        }
    }

    /// Values of a partition's moments `[diag, cross_0..K, b_0..C, g, g_light]`.
    fn stride(&self) -> usize {
        3 + self.layout.overlapping as usize + self.color.channels()
    }

    /// Values of a storage slot: the moments and the count.
    fn slot_len(&self) -> usize {
        self.stride() + 1
    }

    /// Whether the sampled partitions are the bits of `sampled` and their slots in
    /// `slot_of` ([`SLOT_IS_PARTITION_MAX`]).
    #[inline]
    fn slot_is_partition(&self) -> bool {
        self.layout.partitions <= SLOT_IS_PARTITION_MAX
    }

    /// Whether, with [`Self::slot_is_partition`], partition `k`'s slot is `k` ([`FIRST_SLOTS`]).
    #[inline]
    fn slot_is_id(&self) -> bool {
        self.layout.partitions as usize <= FIRST_SLOTS
    }

    /// The storage slot of sampled partition `id` (with [`Self::slot_is_partition`]).
    #[inline]
    fn sampled_slot(&self, id: u32) -> usize {
        if self.slot_is_id() {
            id as usize
        } else {
            usize::from(self.slot_of[id as usize])
        }
    }

    /// Storage slot `slot`: the moments `[diag, cross_0..K, b_0..C, g, g_light]` then the
    /// count.
    fn stored_entry(&self, slot: usize) -> &[f64] {
        let n = self.slot_len();
        &self.part_data[slot * n..(slot + 1) * n]
    }

    /// [`Self::stored_entry`], mutable.
    fn stored_entry_mut(&mut self, slot: usize) -> &mut [f64] {
        let n = self.slot_len();
        &mut self.part_data[slot * n..(slot + 1) * n]
    }

    /// The moments of storage slot `slot`.
    fn entry(&self, slot: usize) -> &[f64] {
        &self.stored_entry(slot)[..self.stride()]
    }

    /// The count of storage slot `slot`.
    fn count(&self, slot: usize) -> u64 {
        self.stored_entry(slot)[self.stride()] as u64
    }

    fn moments(&self, id: u32, slot: usize) -> PartitionMoments<'_> {
        let (k, c) = (self.layout.overlapping as usize, self.color.channels());
        let d = self.entry(slot);
        PartitionMoments {
            id,
            count: self.count(slot),
            diag: d[0],
            cross: &d[1..1 + k],
            b: &d[1 + k..1 + k + c],
            g: d[1 + k + c],
            g_light: d[2 + k + c],
        }
    }

    /// `(partition, storage slot)` of the sampled partitions in increasing index order.
    fn sorted_slots(&self) -> SortedSlots<'_> {
        if self.slot_is_partition() {
            SortedSlots::Bits(self.sampled, (!self.slot_is_id()).then_some(&self.slot_of))
        } else if !self.slot_map.is_empty() {
            SortedSlots::Map {
                map: &self.slot_map,
                next: 0,
                left: self.sampled_partitions(),
            }
        } else {
            SortedSlots::Lists(self.part_ids.iter().zip(&self.part_slots))
        }
    }

    /// `A_{P+i, P+j}` of the overlapping block.
    pub fn dense(&self, i: usize, j: usize) -> f64 {
        let k = self.layout.overlapping as usize;
        let (i, j) = if i <= j { (i, j) } else { (j, i) };
        self.overlap().0[row_start(k, i) + (j - i)]
    }

    /// `(dense, b, g, g_light)` of the overlapping components ([`OverlapSums`]).
    fn overlap(&self) -> (&[f64], &[f64], &[f64], &[f64]) {
        let (k, c) = (self.layout.overlapping as usize, self.color.channels());
        overlap_parts(self.over.as_slice(), k, c)
    }

    /// `b_{P+i}` of overlapping component `i`, one value per channel of the colour mode.
    pub fn b_overlapping(&self, i: usize) -> &[f64] {
        let c = self.color.channels();
        &self.overlap().1[i * c..(i + 1) * c]
    }

    /// `Σ w λ_i/p` of overlapping component `i`.
    pub fn g_overlapping(&self, i: usize) -> f64 {
        self.overlap().2[i]
    }

    /// The light technique's sums ([`Technique`]): `Σ w`, `Σ w y_c` per channel of the colour
    /// mode (first `C` entries of the array) and `Σ w λ_j/p` of the overlapping components (the
    /// partitions' parts are [`PartitionMoments::g_light`]). The BSDF technique's are the
    /// totals minus these. All zero for an accumulator fed only through
    /// [`add`](Self::add), or decoded from an encoding older than version 3.
    pub fn technique_sums(&self) -> (f64, [f64; CHANNELS], &[f64]) {
        let mut y = [0.0; CHANNELS];
        y.copy_from_slice(&self.light[1..]);
        (self.light[0], y, self.overlap().3)
    }

    /// The sampled partitions in increasing index order.
    pub fn partitions(&self) -> impl ExactSizeIterator<Item = PartitionMoments<'_>> + '_ {
        self.sorted_slots()
            .map(move |(id, slot)| self.moments(id, slot))
    }

    /// Moments of partition `id`, if it was sampled.
    pub fn partition(&self, id: u32) -> Option<PartitionMoments<'_>> {
        let slot = self.stored_slot(id)?;
        Some(self.moments(id, slot))
    }

    /// Asks the CPU to start loading partition `id`'s stored moments, ahead of an
    /// [`add_from`](Self::add_from) of a sample in it; changes nothing else. A no-op where
    /// the partition has no storage yet, or where finding its slot would need a search.
    ///
    /// A training sample's partition entry is the one load of its update that misses the
    /// caches: a tile's cells hold far more entries than the caches (many-lights d5: that
    /// load was ≈ 70 % of `add_from`'s time). A caller adding a batch of samples prefetches
    /// the batch's entries first, and their misses overlap instead of queueing one by one.
    #[inline]
    pub fn prefetch_partition(&self, id: u32) {
        let slot = if self.slot_is_partition() {
            match self.stored_slot(id) {
                Some(s) => s,
                // A few partitions: all slots exist once the first was sampled.
                None if self.slot_is_id() => id as usize,
                // Its slot will be the next one: the end of the list, when there is room.
                None if self.part_data.len() < self.part_data.capacity() => {
                    let end = self.part_data.as_ptr().wrapping_add(self.part_data.len());
                    prefetch_ptr(end);
                    prefetch_ptr(end.wrapping_add(self.slot_len() - 1));
                    return;
                }
                None => return,
            }
        } else {
            match self.slot_map.get(id as usize) {
                Some(&s) if s != u32::MAX => s as usize,
                _ => return,
            }
        };
        let len = self.slot_len();
        if let Some(entry) = self.part_data.get(slot * len..(slot + 1) * len) {
            // The count (the last value) may sit on the next cache line.
            prefetch_read(&entry[0]);
            prefetch_read(&entry[len - 1]);
        }
    }

    /// Storage slot of partition `id` (`id < P`), with a zeroed entry the first time it is
    /// seen.
    #[inline]
    fn slot_for(&mut self, id: u32) -> usize {
        if self.slot_is_partition() {
            if self.sampled & (1 << id) == 0 {
                return self.insert_partition(id);
            }
            return self.sampled_slot(id);
        }
        match self.slot_map.get(id as usize) {
            Some(&s) if s != u32::MAX => return s as usize,
            Some(_) => {}
            None if self.last.0 == id => return self.last.1 as usize,
            None => {}
        }
        self.find_or_insert(id)
    }

    /// Storage slot of partition `id` when it was sampled.
    #[inline]
    fn stored_slot(&self, id: u32) -> Option<usize> {
        if self.slot_is_partition() {
            return (id < self.layout.partitions && self.sampled & (1 << id) != 0)
                .then(|| self.sampled_slot(id));
        }
        match self.slot_map.get(id as usize) {
            Some(&s) => (s != u32::MAX).then_some(s as usize),
            None => self
                .part_ids
                .binary_search(&id)
                .ok()
                .map(|i| self.part_slots[i] as usize),
        }
    }

    /// Marks partition `id` (`id < P <= SLOT_IS_PARTITION_MAX`, not yet sampled) sampled
    /// and returns its storage slot (zeroed): with `P <= FIRST_SLOTS` slot `id`, all `P`
    /// made at the first partition sample; else the next slot, appended.
    #[cold]
    fn insert_partition(&mut self, id: u32) -> usize {
        let n = self.slot_len();
        let slot = if self.slot_is_id() {
            if self.part_data.is_empty() {
                self.part_data = vec![0.0; self.layout.partitions as usize * n];
            }
            id as usize
        } else {
            let slot = self.part_data.len() / n;
            if slot == 0 {
                self.part_data.reserve(FIRST_SLOTS * n);
            }
            self.part_data.resize((slot + 1) * n, 0.0);
            slot
        };
        self.slot_of[id as usize] = slot as u8;
        self.sampled |= 1 << id;
        slot
    }

    #[cold]
    fn find_or_insert(&mut self, id: u32) -> usize {
        let n = self.slot_len();
        if let Some(&m) = self.slot_map.get(id as usize) {
            // The map is the sorted list: a new partition only appends its slot.
            let slot = if m != u32::MAX {
                m as usize
            } else {
                let s = self.part_data.len() / n;
                if s == 0 {
                    let r = (self.layout.partitions as usize).min(FIRST_RESERVE);
                    self.part_data.reserve(r * n);
                }
                self.part_data.resize(self.part_data.len() + n, 0.0);
                self.slot_map[id as usize] = s as u32;
                s
            };
            self.last = (id, slot as u32);
            return slot;
        }
        let slot = match self.part_ids.binary_search(&id) {
            Ok(i) => self.part_slots[i] as usize,
            Err(i) => {
                let s = self.part_data.len() / n;
                if s == 0 {
                    // Skip the growth steps of the three lists (allocator calls and copies).
                    let r = (self.layout.partitions as usize).min(FIRST_RESERVE);
                    self.part_ids.reserve(r);
                    self.part_slots.reserve(r);
                    self.part_data.reserve(r * n);
                }
                self.part_ids.insert(i, id);
                self.part_slots.insert(i, s as u32);
                self.part_data.resize(self.part_data.len() + n, 0.0);
                s
            }
        };
        self.last = (id, slot as u32);
        slot
    }

    /// Adds one training sample with weight `weight` (see [`training_weight`]) and RGB value
    /// `value` = `F = f/p`, whose technique is not told: it is counted with
    /// [`Technique::Bsdf`]'s sums, so an accumulator fed only through `add` has no
    /// between-technique spread (see [`add_from`](Self::add_from)).
    ///
    /// On rejection nothing but the rejection counter changes.
    pub fn add(
        &mut self,
        weight: f64,
        value: [f64; CHANNELS],
        sample: &CvSample<'_>,
    ) -> Result<(), SampleRejection> {
        self.add_from(Technique::Bsdf, weight, value, sample)
    }

    /// [`add`](Self::add) of a sample drawn by `technique`.
    pub fn add_from(
        &mut self,
        technique: Technique,
        weight: f64,
        value: [f64; CHANNELS],
        sample: &CvSample<'_>,
    ) -> Result<(), SampleRejection> {
        let r = self.check_and_add(technique == Technique::Light, weight, value, sample);
        if r.is_err() {
            self.rejected += 1;
        }
        r
    }

    /// [`add`](Self::add) for single-precision renderer values (accumulated in `f64`).
    pub fn add_f32(
        &mut self,
        weight: f32,
        value: [f32; CHANNELS],
        pdf: f32,
        partition: Option<(u32, f32)>,
        overlapping: &[f32],
    ) -> Result<(), SampleRejection> {
        let mut lam = [0.0f64; MAX_OVERLAPPING as usize];
        if overlapping.len() > lam.len() {
            self.rejected += 1;
            return Err(SampleRejection::WrongComponentCount);
        }
        for (d, &s) in lam.iter_mut().zip(overlapping) {
            *d = f64::from(s);
        }
        let sample = CvSample {
            pdf: f64::from(pdf),
            partition: partition.map(|(k, l)| (k, f64::from(l))),
            overlapping: &lam[..overlapping.len()],
        };
        self.add(f64::from(weight), value.map(f64::from), &sample)
    }

    fn check_and_add(
        &mut self,
        light: bool,
        w: f64,
        value: [f64; CHANNELS],
        s: &CvSample<'_>,
    ) -> Result<(), SampleRejection> {
        if s.overlapping.len() != self.layout.overlapping as usize {
            return Err(SampleRejection::WrongComponentCount);
        }
        // The common layouts get a copy of the body whose slice lengths are constants, so
        // the loops over components and channels unroll (same arithmetic, same bits).
        match (s.overlapping.len(), self.color) {
            (1, ColorMode::Rgb) => {
                self.add_checked(light, w, value, s, &s.overlapping[..1], ColorMode::Rgb)
            }
            (1, ColorMode::Mono) => {
                self.add_checked(light, w, value, s, &s.overlapping[..1], ColorMode::Mono)
            }
            (0, c) => self.add_checked(light, w, value, s, &[], c),
            (2, c) => self.add_checked(light, w, value, s, &s.overlapping[..2], c),
            (_, c) => self.add_checked(light, w, value, s, s.overlapping, c),
        }
    }

    /// The body of [`add`](Self::add) after the component count check; `lam` is
    /// `s.overlapping`, `color` is `self.color`, `light` whether [`Technique::Light`] drew it.
    #[inline(always)]
    fn add_checked(
        &mut self,
        light: bool,
        w: f64,
        value: [f64; CHANNELS],
        s: &CvSample<'_>,
        lam: &[f64],
        color: ColorMode,
    ) -> Result<(), SampleRejection> {
        let k = lam.len();
        if !w.is_finite()
            || !s.pdf.is_finite()
            || value.iter().any(|v| !v.is_finite())
            || lam.iter().any(|l| !l.is_finite())
            || s.partition.is_some_and(|(_, l)| !l.is_finite())
        {
            return Err(SampleRejection::NonFinite);
        }
        if w < 0.0 {
            return Err(SampleRejection::NegativeWeight);
        }
        if s.pdf <= 0.0 {
            return Err(SampleRejection::NonPositivePdf);
        }
        let inv_p = 1.0 / s.pdf;
        // Ratios λ_j/p are recomputed where used (same expression, same bits) rather than
        // stored: no per-sample scratch array to initialise.
        let mut max_r = 0.0f64;
        for &l in lam {
            max_r = max_r.max((l * inv_p).abs());
        }
        let part = match s.partition {
            Some((id, l)) => {
                if id >= self.layout.partitions {
                    return Err(SampleRejection::PartitionOutOfRange);
                }
                let rk = l * inv_p;
                max_r = max_r.max(rk.abs());
                (rk != 0.0).then_some((id, rk))
            }
            None => None,
        };
        let y_mono;
        let y: &[f64] = match color {
            ColorMode::Rgb => &value,
            ColorMode::Mono => {
                y_mono = [(value[0] + value[1] + value[2]) / 3.0];
                &y_mono
            }
        };
        let max_y = y.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        // Every product added below is bounded by these two; NaN ratios fail too.
        if !(w * max_r * max_r).is_finite()
            || !(w * max_r * max_y).is_finite()
            || !(w * max_y * max_y).is_finite()
        {
            return Err(SampleRejection::NonFinite);
        }

        self.samples += 1;
        self.weight_sum += w;
        self.weight_sq_sum += w * w;
        let c = y.len();
        for (ch, &yc) in y.iter().enumerate() {
            let wy = w * yc;
            self.value[ch] += wy;
            self.value[c + ch] += wy * yc;
        }
        let (dense, b_over, g_over, g_light) = overlap_parts_mut(self.over.as_mut_slice(), k, c);
        if light {
            self.light[0] += w;
            for (ch, &yc) in y.iter().enumerate() {
                self.light[1 + ch] += w * yc;
            }
            for (g, &l) in g_light.iter_mut().zip(lam) {
                *g += w * (l * inv_p);
            }
        }
        for i in 0..k {
            let wri = w * (lam[i] * inv_p);
            let row = row_start(k, i);
            for (d, &lj) in dense[row..row + (k - i)].iter_mut().zip(&lam[i..k]) {
                *d += wri * (lj * inv_p);
            }
            for (ch, &yc) in y.iter().enumerate() {
                b_over[i * c + ch] += wri * yc;
            }
            g_over[i] += wri;
        }
        if let Some((id, rk)) = part {
            // [`Self::stored_entry_mut`] with the stride from this body's constant `k` and
            // `c` (the layout's), so the loops below unroll.
            let stride = 3 + k + c;
            let slot = self.slot_for(id);
            let d = &mut self.part_data[slot * (stride + 1)..(slot + 1) * (stride + 1)];
            d[stride] += 1.0;
            let wrk = w * rk;
            d[0] += wrk * rk;
            for (dj, &lj) in d[1..1 + k].iter_mut().zip(lam) {
                *dj += wrk * (lj * inv_p);
            }
            for (ch, &yc) in y.iter().enumerate() {
                d[1 + k + ch] += wrk * yc;
            }
            d[1 + k + c] += wrk;
            if light {
                d[2 + k + c] += wrk;
            }
        }
        Ok(())
    }

    /// Adds `other`'s sums into `self` (plain element-wise `f64` addition).
    ///
    /// Fails without changing `self` if layouts or colour modes differ.
    pub fn merge(&mut self, other: &CellAccumulator) -> Result<(), CellError> {
        if self.layout != other.layout || self.color != other.color {
            return Err(CellError::LayoutMismatch);
        }
        self.samples += other.samples;
        self.rejected += other.rejected;
        self.weight_sum += other.weight_sum;
        self.weight_sq_sum += other.weight_sq_sum;
        for (a, b) in self.value.iter_mut().zip(&other.value) {
            *a += b;
        }
        for (a, b) in self.light.iter_mut().zip(&other.light) {
            *a += b;
        }
        for (a, b) in self
            .over
            .as_mut_slice()
            .iter_mut()
            .zip(other.over.as_slice())
        {
            *a += b;
        }
        if other.sampled_partitions() == 0 {
            return Ok(());
        }
        // In place: a partition both have is summed where `self` stores it (`p + q`, the
        // addition a merge-join of the two sorted lists makes), one only `other` has gets a
        // new slot ([`Self::slot_for`]: appended, or its own) with its entry copied, as a
        // merge-join copies it. Same sums, counts and sorted view (equality, encoding) as a
        // merge-join, without rebuilding every list on each merge: the band and tile tables of
        // a training phase are merged cell by cell, mostly into partitions already present.
        let n = self.slot_len();
        if self.part_data.is_empty() && !self.slot_is_partition() {
            let r = other.sampled_partitions();
            if self.slot_map.is_empty() {
                self.part_ids.reserve(r);
                self.part_slots.reserve(r);
            }
            self.part_data.reserve(r * n);
        }
        for (id, j) in other.sorted_slots() {
            // The moments and the count: summed alike.
            let src = other.stored_entry(j);
            match self.stored_slot(id) {
                Some(s) => {
                    for (p, q) in self.stored_entry_mut(s).iter_mut().zip(src) {
                        *p += q;
                    }
                }
                // A new slot (zeroed), then a copy: not an addition to zeros, which is
                // not a copy for `-0.0`.
                None => {
                    let s = self.slot_for(id);
                    self.stored_entry_mut(s).copy_from_slice(src);
                }
            }
        }
        Ok(())
    }

    /// Merges `parts` in the given (canonical) order into an accumulator of `layout`.
    pub fn merge_all<'a>(
        layout: ComponentLayout,
        color: ColorMode,
        parts: impl IntoIterator<Item = &'a CellAccumulator>,
    ) -> Result<Self, CellError> {
        let mut acc = Self::new(layout, color);
        for p in parts {
            acc.merge(p)?;
        }
        Ok(acc)
    }
}

// ---------------------------------------------------------------------------------------
// Binary encoding.

/// Magic bytes opening an encoded accumulator.
pub const MAGIC: [u8; 4] = *b"CVAC";
/// Current encoding version (2 added the value moments and the component sums `Σ w λ/p`;
/// 3 the light technique's sums, [`Technique`]). Versions 1 and 2 are still read, with the
/// sums they lack zero: a version-1 cell removes no variance in
/// [`crate::solve::variance_reduction`], a version-2 cell has no between-technique spread
/// (its within-technique figures are the pooled ones).
pub const VERSION: u16 = 3;
/// Largest partition count an accumulator holds (its counts are `f64`, exact up to 2⁵³).
const MAX_PARTITION_COUNT: u64 = 1 << 53;
/// Size of the fixed header in bytes.
const HEADER_LEN: usize = 4 + 2 + 1 + 1 + 4 + 4 + 8 + 8 + 8 + 8;

impl CellAccumulator {
    /// Encodes the accumulator (little endian, version [`VERSION`]).
    ///
    /// Layout: magic `CVAC`, `u16` version, `u8` colour (0 RGB, 1 mono), `u8` 0,
    /// `u32` P, `u32` K, `u64` samples, `u64` rejected, `f64` Σw, `f64` Σw²,
    /// `C` `f64` Σwy, `C` `f64` Σwy², `K(K+1)/2` `f64` (packed upper dense block), `K·C` `f64`
    /// (overlapping `b`), `K` `f64` (overlapping `Σ w λ/p`), the light technique's `f64` Σw,
    /// `C` `f64` Σwy and `K` `f64` overlapping `Σ w λ/p`, `u32` entry count, then per
    /// sampled partition `u32` index, `u64` count and `3 + K + C` `f64` (diag, cross, `b`,
    /// `Σ w λ/p`, its light-technique part). Only sampled partitions are written.
    pub fn encode(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(self.encoded_len());
        out.extend_from_slice(&MAGIC);
        out.extend_from_slice(&VERSION.to_le_bytes());
        out.push(match self.color {
            ColorMode::Rgb => 0,
            ColorMode::Mono => 1,
        });
        out.push(0);
        out.extend_from_slice(&self.layout.partitions.to_le_bytes());
        out.extend_from_slice(&self.layout.overlapping.to_le_bytes());
        out.extend_from_slice(&self.samples.to_le_bytes());
        out.extend_from_slice(&self.rejected.to_le_bytes());
        out.extend_from_slice(&self.weight_sum.to_le_bytes());
        out.extend_from_slice(&self.weight_sq_sum.to_le_bytes());
        for v in &self.value[..2 * self.color.channels()] {
            out.extend_from_slice(&v.to_le_bytes());
        }
        let (dense, b_over, g_over, g_light) = self.overlap();
        for v in dense
            .iter()
            .chain(b_over)
            .chain(g_over)
            .chain(&self.light[..1 + self.color.channels()])
            .chain(g_light)
        {
            out.extend_from_slice(&v.to_le_bytes());
        }
        out.extend_from_slice(&(self.sampled_partitions() as u32).to_le_bytes());
        for (id, slot) in self.sorted_slots() {
            out.extend_from_slice(&id.to_le_bytes());
            out.extend_from_slice(&self.count(slot).to_le_bytes());
            for v in self.entry(slot) {
                out.extend_from_slice(&v.to_le_bytes());
            }
        }
        out
    }

    /// Exact length of [`encode`](Self::encode)'s output.
    pub fn encoded_len(&self) -> usize {
        HEADER_LEN
            + 8 * (3 * self.color.channels() + 1 + self.over.as_slice().len())
            + 4
            + self.sampled_partitions() * (12 + 8 * self.stride())
    }

    /// Decodes and validates an accumulator; never panics on arbitrary bytes.
    pub fn decode(bytes: &[u8]) -> Result<Self, CellError> {
        let mut r = Reader { bytes, pos: 0 };
        if r.take(4)? != MAGIC {
            return Err(CellError::BadMagic);
        }
        let version = r.u16()?;
        if !(1..=VERSION).contains(&version) {
            return Err(CellError::UnsupportedVersion(version));
        }
        let color = match r.u8()? {
            0 => ColorMode::Rgb,
            1 => ColorMode::Mono,
            _ => return Err(CellError::BadHeader),
        };
        if r.u8()? != 0 {
            return Err(CellError::BadHeader);
        }
        let partitions = r.u32()?;
        let overlapping = r.u32()?;
        let layout = ComponentLayout::new(partitions, overlapping)?;
        let mut acc = Self::new(layout, color);
        acc.samples = r.u64()?;
        acc.rejected = r.u64()?;
        acc.weight_sum = r.nonneg_f64()?;
        acc.weight_sq_sum = r.nonneg_f64()?;
        if version >= 2 {
            let c = color.channels();
            for v in &mut acc.value[..c] {
                *v = r.finite_f64()?;
            }
            for v in &mut acc.value[c..2 * c] {
                *v = r.nonneg_f64()?;
            }
        }
        let (k, c) = (overlapping as usize, color.channels());
        let (dense, b_over, g_over, g_light) = overlap_parts_mut(acc.over.as_mut_slice(), k, c);
        for v in dense.iter_mut().chain(b_over.iter_mut()) {
            *v = r.finite_f64()?;
        }
        if version >= 2 {
            for v in g_over.iter_mut() {
                *v = r.finite_f64()?;
            }
        }
        if version >= 3 {
            acc.light[0] = r.nonneg_f64()?;
            for v in &mut acc.light[1..1 + c] {
                *v = r.finite_f64()?;
            }
            for v in g_light.iter_mut() {
                *v = r.finite_f64()?;
            }
        }
        for i in 0..k {
            let at = r.pos;
            if acc.dense(i, i) < 0.0 {
                return Err(CellError::InvalidValue(at));
            }
        }
        let entries = r.u32()? as u64;
        let stride = acc.stride();
        // Version 1 entries have no `Σ w λ/p`, version 2 ones no light-technique part of
        // it (read as 0).
        let stored = match version {
            1 => stride - 2,
            2 => stride - 1,
            _ => stride,
        };
        let entry_len = 12 + 8 * stored as u64;
        let remaining = (bytes.len() - r.pos) as u64;
        if entries > u64::from(partitions) || entries * entry_len > remaining {
            return Err(CellError::BadEntryCount(entries));
        }
        let n = entries as usize;
        let mut entry = Vec::with_capacity(stride + 1);
        let mut prev: Option<u32> = None;
        for _ in 0..n {
            let at = r.pos;
            let id = r.u32()?;
            let count = r.u64()?;
            // Counts are kept in `f64` (exact below 2⁵³).
            if id >= partitions
                || prev.is_some_and(|p| id <= p)
                || count == 0
                || count > MAX_PARTITION_COUNT
            {
                return Err(CellError::BadPartition(at));
            }
            prev = Some(id);
            entry.clear();
            entry.push(r.nonneg_f64()?);
            for _ in 1..stride - 2 {
                entry.push(r.finite_f64()?);
            }
            for present in [version >= 2, version >= 3] {
                entry.push(if present { r.finite_f64()? } else { 0.0 });
            }
            entry.push(count as f64);
            // Increasing ids, none stored yet: the slot is new, and the entry is copied into
            // it (an addition to its zeros would not be a copy for `-0.0`).
            let s = acc.slot_for(id);
            acc.stored_entry_mut(s).copy_from_slice(&entry);
        }
        if r.pos != bytes.len() {
            return Err(CellError::Trailing(bytes.len() - r.pos));
        }
        Ok(acc)
    }
}

pub(crate) struct Reader<'a> {
    bytes: &'a [u8],
    pos: usize,
}

impl<'a> Reader<'a> {
    pub(crate) fn new(bytes: &'a [u8]) -> Self {
        Self { bytes, pos: 0 }
    }
    pub(crate) fn at_end(&self) -> bool {
        self.pos == self.bytes.len()
    }
    pub(crate) fn remaining(&self) -> usize {
        self.bytes.len() - self.pos
    }
    pub(crate) fn pos(&self) -> usize {
        self.pos
    }
    pub(crate) fn take(&mut self, n: usize) -> Result<&'a [u8], CellError> {
        let end = self.pos.checked_add(n).filter(|&e| e <= self.bytes.len());
        match end {
            Some(e) => {
                let s = &self.bytes[self.pos..e];
                self.pos = e;
                Ok(s)
            }
            None => Err(CellError::Truncated {
                offset: self.pos,
                needed: n,
            }),
        }
    }
    fn array<const N: usize>(&mut self) -> Result<[u8; N], CellError> {
        let s = self.take(N)?;
        let mut a = [0u8; N];
        a.copy_from_slice(s);
        Ok(a)
    }
    pub(crate) fn u8(&mut self) -> Result<u8, CellError> {
        Ok(self.array::<1>()?[0])
    }
    pub(crate) fn u16(&mut self) -> Result<u16, CellError> {
        Ok(u16::from_le_bytes(self.array()?))
    }
    pub(crate) fn u32(&mut self) -> Result<u32, CellError> {
        Ok(u32::from_le_bytes(self.array()?))
    }
    pub(crate) fn u64(&mut self) -> Result<u64, CellError> {
        Ok(u64::from_le_bytes(self.array()?))
    }
    pub(crate) fn finite_f64(&mut self) -> Result<f64, CellError> {
        let at = self.pos;
        let v = f64::from_le_bytes(self.array()?);
        if v.is_finite() {
            Ok(v)
        } else {
            Err(CellError::InvalidValue(at))
        }
    }
    pub(crate) fn nonneg_f64(&mut self) -> Result<f64, CellError> {
        let at = self.pos;
        let v = self.finite_f64()?;
        if v >= 0.0 {
            Ok(v)
        } else {
            Err(CellError::InvalidValue(at))
        }
    }
}
