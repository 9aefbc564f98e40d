//! Keyed tables of per-cell records and their wire encoding: the opaque payload of the
//! protocol's cell-accumulator frames and of the coefficient table the coordinator
//! broadcasts.
//!
//! # Format (version 2, little endian)
//! magic `CVCT`, `u16` version, `u16` kind ([`KIND_CELL_ACCUMULATORS`],
//! [`KIND_MEAN_CONTRIBUTIONS`], [`KIND_COEFFICIENTS`]), `u32` record count, then per record
//! `u64` cell key, `u32` byte length and the record's own encoding
//! ([`CellAccumulator::encode`], [`MeanContributionAccumulator::encode`],
//! [`CellCoefficients::encode`]), then one `f64`: the image variance of an accumulator
//! table ([`AccumulatorTable::Moments`]), `NaN` for unknown and for the other kinds. Keys
//! are strictly increasing, so one table has one canonical encoding. Version 1 (read, not
//! written) had no trailing `f64`: its image variance is unknown.
//!
//! # Contracts
//! - Cell keys are the caller's (e.g. a linear index into the sparse grid); this module only
//!   requires them unique.
//! - [`merge_tables`] adds records key by key; merging the tables of a job's tasks in
//!   canonical task order gives bitwise-reproducible sums.
//! - Decoding validates everything ([`CellError`]) and never panics on arbitrary bytes.

use std::borrow::Cow;
use std::collections::BTreeMap;

use crate::cell::{CellAccumulator, CellError, Reader};
use crate::perlight::MeanContributionAccumulator;
use crate::solve::{
    CellCoefficients, CellHalves, FallbackReason, SolvePolicy, solve, variance_reduction,
};
use crate::spec::cell_ancestor;

/// Magic bytes of an encoded table.
pub const TABLE_MAGIC: [u8; 4] = *b"CVCT";
/// Table encoding version.
pub const TABLE_VERSION: u16 = 2;
/// Kind tag: [`CellAccumulator`] records (`cms`, `optimal_mis`).
pub const KIND_CELL_ACCUMULATORS: u16 = 1;
/// Kind tag: [`MeanContributionAccumulator`] records (`per_light_cv`).
pub const KIND_MEAN_CONTRIBUTIONS: u16 = 2;
/// Kind tag: [`CellCoefficients`] records (the solved table).
pub const KIND_COEFFICIENTS: u16 = 3;

/// A record type that can live in a table.
pub trait CellRecord: Sized {
    /// Kind tag written in the table header.
    const KIND: u16;
    /// Encodes one record.
    fn encode_record(&self) -> Vec<u8>;
    /// Decodes one record.
    fn decode_record(bytes: &[u8]) -> Result<Self, CellError>;
}

/// A record type whose tables can be merged (accumulators, not coefficients).
pub trait MergeRecord: CellRecord + Clone {
    /// Adds `other` into `self`.
    fn merge_record(&mut self, other: &Self) -> Result<(), CellError>;
}

impl CellRecord for CellAccumulator {
    const KIND: u16 = KIND_CELL_ACCUMULATORS;
    fn encode_record(&self) -> Vec<u8> {
        self.encode()
    }
    fn decode_record(bytes: &[u8]) -> Result<Self, CellError> {
        Self::decode(bytes)
    }
}

impl MergeRecord for CellAccumulator {
    fn merge_record(&mut self, other: &Self) -> Result<(), CellError> {
        self.merge(other)
    }
}

impl CellRecord for MeanContributionAccumulator {
    const KIND: u16 = KIND_MEAN_CONTRIBUTIONS;
    fn encode_record(&self) -> Vec<u8> {
        self.encode()
    }
    fn decode_record(bytes: &[u8]) -> Result<Self, CellError> {
        Self::decode(bytes)
    }
}

impl MergeRecord for MeanContributionAccumulator {
    fn merge_record(&mut self, other: &Self) -> Result<(), CellError> {
        self.merge(other)
    }
}

impl CellRecord for CellCoefficients {
    const KIND: u16 = KIND_COEFFICIENTS;
    fn encode_record(&self) -> Vec<u8> {
        self.encode()
    }
    fn decode_record(bytes: &[u8]) -> Result<Self, CellError> {
        Self::decode(bytes)
    }
}

/// Encodes a table (keys ascending by construction of the map) with an unknown image
/// variance.
pub fn encode_table<T: CellRecord>(table: &BTreeMap<u64, T>) -> Vec<u8> {
    encode_table_with(table, None)
}

/// Encodes a table and its image variance (`None`: unknown, written as `NaN`).
pub fn encode_table_with<T: CellRecord>(table: &BTreeMap<u64, T>, image: Option<f64>) -> Vec<u8> {
    let mut out = Vec::new();
    out.extend_from_slice(&TABLE_MAGIC);
    out.extend_from_slice(&TABLE_VERSION.to_le_bytes());
    out.extend_from_slice(&T::KIND.to_le_bytes());
    out.extend_from_slice(&(table.len() as u32).to_le_bytes());
    for (key, rec) in table {
        let bytes = rec.encode_record();
        out.extend_from_slice(&key.to_le_bytes());
        out.extend_from_slice(&(bytes.len() as u32).to_le_bytes());
        out.extend_from_slice(&bytes);
    }
    out.extend_from_slice(&image.unwrap_or(f64::NAN).to_le_bytes());
    out
}

/// The kind tag of an encoded table, without decoding the records.
pub fn table_kind(bytes: &[u8]) -> Result<u16, CellError> {
    let mut r = Reader::new(bytes);
    if r.take(4)? != TABLE_MAGIC {
        return Err(CellError::BadMagic);
    }
    let version = r.u16()?;
    if !(1..=TABLE_VERSION).contains(&version) {
        return Err(CellError::UnsupportedVersion(version));
    }
    r.u16()
}

/// Decodes and validates a table of `T` records.
pub fn decode_table<T: CellRecord>(bytes: &[u8]) -> Result<BTreeMap<u64, T>, CellError> {
    decode_table_with(bytes).map(|(t, _)| t)
}

/// Decodes and validates a table of `T` records and its image variance (`None` when
/// unknown: `NaN`, or a version-1 table). A negative or infinite variance is refused.
pub fn decode_table_with<T: CellRecord>(
    bytes: &[u8],
) -> Result<(BTreeMap<u64, T>, Option<f64>), CellError> {
    if table_kind(bytes)? != T::KIND {
        return Err(CellError::BadHeader);
    }
    let mut r = Reader::new(bytes);
    r.take(4)?;
    let version = r.u16()?;
    r.take(2)?;
    let count = u64::from(r.u32()?);
    // Every record needs at least its 12-byte key and length.
    if count * 12 > r.remaining() as u64 {
        return Err(CellError::BadEntryCount(count));
    }
    let mut table = BTreeMap::new();
    let mut prev: Option<u64> = None;
    for _ in 0..count {
        let at = r.pos();
        let key = r.u64()?;
        if prev.is_some_and(|p| key <= p) {
            return Err(CellError::BadPartition(at));
        }
        prev = Some(key);
        let len = r.u32()? as usize;
        let rec = T::decode_record(r.take(len)?)?;
        table.insert(key, rec);
    }
    let image = if version >= 2 {
        let at = r.pos();
        let v = f64::from_le_bytes(
            r.take(8)?
                .try_into()
                .map_err(|_| CellError::InvalidValue(at))?,
        );
        if !(v.is_nan() || (v >= 0.0 && v.is_finite())) {
            return Err(CellError::InvalidValue(at));
        }
        (!v.is_nan()).then_some(v)
    } else {
        None
    };
    if !r.at_end() {
        return Err(CellError::Trailing(r.remaining()));
    }
    Ok((table, image))
}

/// Merges `from` into `into` key by key (records of new keys are inserted).
///
/// On error (layout mismatch) `into` may be partially merged; callers validate layouts
/// against the job first or discard the result.
pub fn merge_tables<T: MergeRecord>(
    into: &mut BTreeMap<u64, T>,
    from: &BTreeMap<u64, T>,
) -> Result<(), CellError> {
    merge_records(into, from.iter().map(|(k, r)| (*k, Cow::Borrowed(r))))
}

/// [`merge_tables`] of a table the caller gives up: the records of new keys are moved
/// rather than copied (the same sums).
pub fn merge_tables_owned<T: MergeRecord>(
    into: &mut BTreeMap<u64, T>,
    from: BTreeMap<u64, T>,
) -> Result<(), CellError> {
    merge_records(into, from.into_iter().map(|(k, r)| (k, Cow::Owned(r))))
}

/// The records of `from`, in its order, merged into `into` (new keys inserted).
fn merge_records<'a, T: MergeRecord + 'a>(
    into: &mut BTreeMap<u64, T>,
    from: impl Iterator<Item = (u64, Cow<'a, T>)>,
) -> Result<(), CellError> {
    for (key, rec) in from {
        match into.get_mut(&key) {
            Some(acc) => acc.merge_record(&rec)?,
            None => {
                into.insert(key, rec.into_owned());
            }
        }
    }
    Ok(())
}

/// Solves every cell of a merged accumulator table ([`solve`]).
pub fn solve_table(
    cells: &BTreeMap<u64, CellAccumulator>,
    policy: &SolvePolicy,
) -> BTreeMap<u64, CellCoefficients> {
    cells
        .iter()
        .map(|(k, acc)| (*k, solve(acc, policy)))
        .collect()
}

/// A cell's two halves ([`CellHalves`]): the even and the odd training samples' sums.
type Halves<'a, A = CellAccumulator> = (Option<&'a A>, Option<&'a A>);

/// Pairs the halves of a table recorded with halves (key `2 · cell + half`): each cell's
/// merged accumulator and its two halves, merged on up to `threads` threads.
fn pair_halves(
    t: &BTreeMap<u64, CellAccumulator>,
    threads: usize,
) -> BTreeMap<u64, (CellAccumulator, Halves<'_>)> {
    pair_halves_by(t, threads, |a, b| a.merge(b).is_ok())
}

/// [`pair_halves`] for any accumulator that `merge`s (`false`: the layouts differ, and the
/// odd half is dropped from the cell, never merged wrongly). Each cell's sums are its even
/// half's plus its odd half's, whatever `threads` (cells are independent).
fn pair_halves_by<A: Clone + Send + Sync>(
    t: &BTreeMap<u64, A>,
    threads: usize,
    merge: impl Fn(&mut A, &A) -> bool + Sync,
) -> BTreeMap<u64, (A, Halves<'_, A>)> {
    // Each cell's first half (its sums' start) and both halves; keys come in order, so the
    // even half (if any) is in before the odd one.
    let mut cells: BTreeMap<u64, (&A, Halves<'_, A>)> = BTreeMap::new();
    for (&key, acc) in t {
        match cells.get_mut(&(key / 2)) {
            Some((_, halves)) => halves.1 = Some(acc),
            None => {
                let halves = if key % 2 == 1 {
                    (None, Some(acc))
                } else {
                    (Some(acc), None)
                };
                cells.insert(key / 2, (acc, halves));
            }
        }
    }
    let merged = par_map(&cells, threads, |_, &(first, (even, odd))| {
        let mut m = first.clone();
        let odd = match (even, odd) {
            // Both halves are of one job: their layouts agree (else the odd half is
            // dropped from the fit, never merged wrongly).
            (Some(_), Some(o)) => merge(&mut m, o).then_some(o),
            (_, o) => o,
        };
        (m, (even, odd))
    });
    cells.into_keys().zip(merged).collect()
}

/// `f` of every entry of `cells`, in key order, on up to `threads` threads. The threads take
/// runs of [`PAR_MAP_RUN`] entries in turn until none is left (cells differ in cost: a fixed
/// split left one thread idle while the other solved its heavier half), and each result lands
/// at its entry's place: the result does not depend on `threads`.
fn par_map<T: Sync, R: Send>(
    cells: &BTreeMap<u64, T>,
    threads: usize,
    f: impl Fn(u64, &T) -> R + Sync,
) -> Vec<R> {
    let items: Vec<(u64, &T)> = cells.iter().map(|(k, v)| (*k, v)).collect();
    let threads = threads.clamp(1, items.len().div_ceil(PAR_MAP_RUN).max(1));
    if threads == 1 {
        return items.iter().map(|&(k, v)| f(k, v)).collect();
    }
    let next = std::sync::atomic::AtomicUsize::new(0);
    let runs: Vec<Vec<(usize, Vec<R>)>> = std::thread::scope(|s| {
        let handles: Vec<_> = (0..threads)
            .map(|_| {
                let (f, next, items) = (&f, &next, &items);
                s.spawn(move || {
                    let mut done = Vec::new();
                    loop {
                        let start =
                            next.fetch_add(PAR_MAP_RUN, std::sync::atomic::Ordering::Relaxed);
                        if start >= items.len() {
                            break;
                        }
                        let run = &items[start..(start + PAR_MAP_RUN).min(items.len())];
                        done.push((start, run.iter().map(|&(k, v)| f(k, v)).collect()));
                    }
                    done
                })
            })
            .collect();
        handles
            .into_iter()
            .map(|h| h.join().unwrap_or_else(|e| std::panic::resume_unwind(e)))
            .collect()
    });
    let mut runs: Vec<(usize, Vec<R>)> = runs.into_iter().flatten().collect();
    runs.sort_unstable_by_key(|&(start, _)| start);
    runs.into_iter().flat_map(|(_, r)| r).collect()
}

/// Entries a [`par_map`] thread takes at a time.
const PAR_MAP_RUN: usize = 32;

/// The cells' undivided ancestors ([`SolvePolicy::levels`] up): each one's sums (its
/// members added in key order) and its member cells' keys.
fn undivided(
    cells: impl Iterator<Item = (u64, CellAccumulator)>,
    policy: &SolvePolicy,
) -> (BTreeMap<u64, CellAccumulator>, BTreeMap<u64, Vec<u64>>) {
    let levels = policy.levels.min(crate::spec::MAX_GRID_LEVELS);
    let (mut sums, mut members) = (BTreeMap::new(), BTreeMap::<u64, Vec<u64>>::new());
    for (k, a) in cells {
        let up = cell_ancestor(k, policy.bins, levels);
        match sums.get_mut(&up) {
            // One job's cells: their layouts agree (else the cell is left out of the fit).
            Some(m) => {
                if CellAccumulator::merge(m, &a).is_ok() {
                    members.entry(up).or_default().push(k);
                }
            }
            None => {
                sums.insert(up, a);
                members.insert(up, vec![k]);
            }
        }
    }
    (sums, members)
}

/// A node of the cell hierarchy ([`SolvePolicy::levels`]): its samples and their halves.
struct Node<'a> {
    merged: Cow<'a, CellAccumulator>,
    even: Option<Cow<'a, CellAccumulator>>,
    odd: Option<Cow<'a, CellAccumulator>>,
}

impl<'a> Node<'a> {
    /// A parent's node with its first child's sums: the child's own (borrowed where the child
    /// borrows them, so a chain of only children shares one accumulator; copied on the first
    /// [`absorb`](Self::absorb) of a sibling).
    fn first_child(child: &Node<'a>) -> Self {
        Node {
            merged: child.merged.clone(),
            even: child.even.clone(),
            odd: child.odd.clone(),
        }
    }

    /// Adds a child's sums (keys in order, so the sums are reproducible). A layout
    /// mismatch (not within one job) drops the child's half, as [`pair_halves`] does.
    fn absorb(&mut self, child: &Node<'a>) {
        let _ = self.merged.to_mut().merge(&child.merged);
        for (mine, theirs) in [(&mut self.even, &child.even), (&mut self.odd, &child.odd)] {
            if let Some(t) = theirs {
                match mine {
                    Some(m) => {
                        let _ = m.to_mut().merge(t);
                    }
                    None => *mine = Some(t.clone()),
                }
            }
        }
    }
}

/// A node's fit and, when it has both halves and a fit, each half's fit (for the
/// held-out checks of itself and its descendants).
struct Fit {
    full: CellCoefficients,
    halves: Option<(CellCoefficients, CellCoefficients)>,
}

impl Fit {
    /// The variance the halves' fits remove from the other half of `node` (held out);
    /// `None` when either side lacks them.
    fn held_out(&self, node: &Node<'_>) -> Option<f64> {
        let (fit_even, fit_odd) = self.halves.as_ref()?;
        let (even, odd) = (node.even.as_deref()?, node.odd.as_deref()?);
        Some(variance_reduction(odd, fit_even) + variance_reduction(even, fit_odd))
    }
}

/// Solves the cells of a cross-fitted table ([`CellHalves::CrossFitted`]) over their
/// hierarchy ([`SolvePolicy::levels`]; 0: the cells alone). Also returns, per cell whose
/// kept fit was judged on its two halves, the variance each half's fit removes from the
/// other half ([`Fit::held_out`]; [`SolvedTable::held_out_gain`]).
///
/// Every node (cell or ancestor) is fitted on its samples and on each half. From the
/// coarsest level down, a node keeps, of its own fit and the fit its parent kept, the one
/// whose half fits remove the most variance from the node's other half (held out; cross-
/// fitted: each half's fit on the other half, as with one level), and none when neither removes any
/// ([`FallbackReason::HeldOutLoss`]). A node without both halves cannot be checked: it
/// keeps its own fit, else its parent's. So a small cell whose samples support a fit of its
/// own gets it, and one whose own fit follows noise (few samples, many lights) gets the
/// shared fit of a larger region [Hua §4.2] where that still removes variance. The
/// coefficients are the kept fit's, on all of its node's samples.
///
/// The halves' fits have half the samples, so they overfit more than the node's own fit: the
/// check is conservative, as a held-out estimate of a fit on fewer samples is, and equally
/// so for a node's own fit and its parent's (each half fit has half of its node's samples).
fn solve_hierarchy(
    cells: &BTreeMap<u64, (CellAccumulator, Halves<'_>)>,
    policy: &SolvePolicy,
    threads: usize,
) -> (SolvedTable, BTreeMap<u64, f64>) {
    let parent = |id: u64| cell_ancestor(id, policy.bins, 1);
    let mut levels: Vec<BTreeMap<u64, Node<'_>>> = vec![
        cells
            .iter()
            .map(|(&k, (a, (even, odd)))| {
                let node = Node {
                    merged: Cow::Borrowed(a),
                    even: even.map(Cow::Borrowed),
                    odd: odd.map(Cow::Borrowed),
                };
                (k, node)
            })
            .collect(),
    ];
    // Per level below the top: how many children each node's parent has.
    let mut siblings: Vec<BTreeMap<u64, u32>> = Vec::new();
    for _ in 0..policy.levels.min(crate::spec::MAX_GRID_LEVELS) {
        let mut up: BTreeMap<u64, Node<'_>> = BTreeMap::new();
        let mut count: BTreeMap<u64, u32> = BTreeMap::new();
        for (&k, child) in levels.last().into_iter().flatten() {
            *count.entry(parent(k)).or_default() += 1;
            match up.get_mut(&parent(k)) {
                Some(node) => node.absorb(child),
                None => {
                    up.insert(parent(k), Node::first_child(child));
                }
            }
        }
        siblings.push(count);
        levels.push(up);
    }
    let half = policy.for_half();
    let mut held_out = BTreeMap::new();
    // Decisions by node key, level by level from the top.
    let mut kept: BTreeMap<u64, Decision> = BTreeMap::new();
    let mut out = SolvedTable::default();
    for (depth, nodes) in levels.iter().enumerate().rev() {
        let above = &kept;
        // An only child has its parent's sums, so its fits, scores and decision are its
        // parent's (e.g. a cell of vertices other than glossy camera hits, alone under its
        // undivided cell): not solved again.
        let only_child = |k: u64| {
            siblings
                .get(depth)
                .is_some_and(|c| c.get(&parent(k)) == Some(&1))
        };
        let decisions = par_map(nodes, threads, |k, node| {
            let up = above.get(&parent(k));
            if let Some(same) = up.filter(|_| only_child(k)) {
                return same.clone();
            }
            let full = solve(&node.merged, policy);
            let halves = match (&node.even, &node.odd) {
                (Some(e), Some(o)) if !full.is_fallback() => {
                    Some((solve(e, &half), solve(o, &half)))
                }
                _ => None,
            };
            decide(Fit { full, halves }, up, node)
        });
        let mut next = BTreeMap::new();
        for ((&k, node), decision) in nodes.iter().zip(decisions) {
            if depth == 0 {
                out.rejected += node.merged.rejected();
                // A kept fit judged on the cell's halves: what it removes held out.
                if let Decision::Fit(_, Some(h)) = decision {
                    held_out.insert(k, h);
                }
                let co = match decision {
                    Decision::Fit(f, _) => f.full.clone(),
                    Decision::Fallback(co) => co.as_ref().clone(),
                };
                out.coefficients.insert(k, co);
            } else {
                next.insert(k, decision);
            }
        }
        kept = next;
    }
    (out, held_out)
}

/// A node's decision ([`solve_hierarchy`]): `own`, its parent's `up`, or neither.
fn decide(own: Fit, up: Option<&Decision>, node: &Node<'_>) -> Decision {
    let inherited = match up {
        Some(Decision::Fit(f, _)) => Some(f),
        _ => None,
    };
    let own_score = own.held_out(node);
    let inherited_score = inherited.and_then(|f| f.held_out(node));
    let checked = node.even.is_some() && node.odd.is_some();
    let choice = if checked {
        // Both candidates are judged on this node's halves; ties keep the node's own.
        let own_ok = own_score.filter(|&v| v > 0.0);
        let up_ok = inherited_score.filter(|&v| v > 0.0);
        match (own_ok, up_ok) {
            (Some(a), Some(b)) if b > a => Keep::Inherited,
            (Some(_), _) => Keep::Own,
            (None, Some(_)) => Keep::Inherited,
            (None, None) => Keep::Neither,
        }
    } else if !own.full.is_fallback() {
        Keep::Own
    } else if inherited.is_some() {
        Keep::Inherited
    } else {
        Keep::Neither
    };
    match (choice, inherited) {
        (Keep::Own, _) => Decision::Fit(std::sync::Arc::new(own), own_score),
        (Keep::Inherited, Some(f)) => Decision::Fit(f.clone(), inherited_score),
        _ if own.full.is_fallback() => Decision::Fallback(std::sync::Arc::new(own.full)),
        _ => Decision::Fallback(std::sync::Arc::new(CellCoefficients::fallen_back(
            own.full.layout(),
            own.full.color(),
            *own.full.diagnostics(),
            FallbackReason::HeldOutLoss,
        ))),
    }
}

/// What a node of the hierarchy keeps: a fit (its own or an ancestor's) with what it removes
/// from the node held out ([`Fit::held_out`] on the node, scored when the fit was chosen: an
/// only child has its parent's sums, so the score is its parent's too), or the plain
/// estimator with the reason ([`solve_hierarchy`]).
#[derive(Clone)]
enum Decision {
    Fit(std::sync::Arc<Fit>, Option<f64>),
    Fallback(std::sync::Arc<CellCoefficients>),
}

/// Which fit a node of the hierarchy keeps ([`solve_hierarchy`]).
enum Keep {
    Own,
    Inherited,
    Neither,
}

/// A merged accumulator table of either record kind: what a training phase produces and
/// the coordinator merges (in canonical task order) and solves.
#[derive(Clone, Debug, PartialEq)]
pub enum AccumulatorTable {
    /// [`CellAccumulator`] records (`cms`, `optimal_mis`) and the image variance of the
    /// training samples behind them: `Σ_pixels Σ_samples Σ_c w_p (L − L̄_p)²`, each pixel's
    /// samples `L` about their own mean, weighted as a training sample of that pixel is
    /// (`w_p = 1/(surrogate_p + ε)²` with relative weights [Hua eq. 25], else 1), i.e. the
    /// same units as the cells' sums ([`crate::solve::variance_reduction`]). `None` when
    /// unknown (a version-1 table, or a merge with one); then no
    /// [`SolvePolicy::min_image_gain`] decision is made.
    Moments(BTreeMap<u64, CellAccumulator>, Option<f64>),
    /// [`MeanContributionAccumulator`] records (`per_light_cv`) and the image variance of
    /// their training samples, as for [`Self::Moments`].
    Mean(BTreeMap<u64, MeanContributionAccumulator>, Option<f64>),
}

/// A solved table: coefficients per cell and how many training samples were rejected.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SolvedTable {
    /// Coefficients by cell key.
    pub coefficients: BTreeMap<u64, CellCoefficients>,
    /// Training samples rejected as non-finite, over all cells.
    pub rejected: u64,
    /// Predicted image gain of the fits ([`predicted_image_gain`]) when the table's image
    /// variance was known (not part of the wire encoding).
    pub image_gain: Option<f64>,
    /// Predicted fit gain ([`predicted_fit_gain`]) when the cells recorded their value
    /// moments (not part of the wire encoding).
    pub fit_gain: Option<f64>,
    /// The held-out side of the fit gain, for a cross-fitted table
    /// ([`CellHalves::CrossFitted`]; not part of the wire encoding):
    /// `Σ_cells held-out reduction / Σ_cells value_variance`, the variance each half's fit
    /// removes from the other half (over the fitted cells that have both halves), against
    /// the fit gain's denominator ([`predicted_fit_gain`]). Summed in key order in the
    /// table's solve, so the same bits on one worker or many.
    pub held_out_gain: Option<f64>,
    /// `Σ held-out reduction / Σ in-sample reduction` over the same cells: the part of the
    /// fits' in-sample gain that survives out of sample. The halves' fits have half the
    /// samples, so it is conservative. A small share says the fits follow their training
    /// samples' noise (many lights, a few samples of each per cell): the in-sample fit gain
    /// then overstates what the render phase gets ([`SolvePolicy::min_held_out_share`];
    /// measured per scene in `docs/bench/README.md`). Not part of the wire encoding.
    pub held_out_share: Option<f64>,
    /// Why every fitted cell fell back table-wide ([`FallbackReason::LowImageGain`],
    /// [`FallbackReason::LowFitGain`] or [`FallbackReason::Overfitted`]), `None` when the
    /// fits stand (not part of the wire encoding).
    pub switched_off: Option<FallbackReason>,
}

impl SolvedTable {
    /// Whether a render phase with these coefficients controls any vertex: some cell's `α`
    /// is not zero ([`CellCoefficients::is_zero`]). Without, the phase is traced as `path`
    /// and its samples merge plainly with the others.
    pub fn controls_any(&self) -> bool {
        self.coefficients.values().any(|c| !c.is_zero())
    }
}

/// The image variance of two merged accumulator tables ([`AccumulatorTable::Moments`]):
/// their sum, unknown as soon as one is.
pub fn add_image_variances(a: Option<f64>, b: Option<f64>) -> Option<f64> {
    a.zip(b).map(|(x, y)| x + y)
}

/// Predicted fraction of the image's per-sample variance that the fits remove:
/// `Σ_cells variance_reduction / image`, summed in key order ([`variance_reduction`];
/// in-sample, over the training samples). `None` without a positive image variance.
///
/// The vertex-level fit of a cell only sees the variance of the vertex estimates it
/// controls, not how much of a pixel's error they make up: a scene whose noise is at
/// uncontrolled vertices (the camera hit, with `min_depth` 1) or in the path prefix gets a
/// small figure however well the cells fit. Measured against the equal-spp relMSE gain in
/// `docs/bench/README.md`.
pub fn predicted_image_gain(
    cells: &BTreeMap<u64, CellAccumulator>,
    coefficients: &BTreeMap<u64, CellCoefficients>,
    image: Option<f64>,
) -> Option<f64> {
    FitSums::of(cells, coefficients, &BTreeMap::new()).image_gain(image)
}

/// Predicted fraction of the controlled vertices' variance that the fits remove:
/// `Σ_cells variance_reduction / Σ_cells value_variance`, summed in key order
/// ([`variance_reduction`], [`crate::solve::value_variance`]; in-sample, over the training
/// samples; cells that fell back count in the denominator), both measured within each
/// technique (NEE, BSDF), as the one-sample-per-technique estimator's variance is. It is
/// negative when the fits add variance within the techniques (a fit that only separated the
/// techniques' means: one small light that NEE finds and the BSDF sample misses). `None`
/// without a positive denominator (no value moments: version-1 accumulators).
///
/// It bounds what the fits can do to the image whatever its noise is made of: a CV that
/// removes a fraction `g` of the variance where it acts gives at most `1/(1 − g)` at equal
/// samples, reached only when all of the pixels' error sits at controlled vertices. With
/// the CV's per-sample cost of +5…+25 % over `path`, a small `g` cannot pay at equal time;
/// [`predicted_image_gain`] gives the other side (how much of the image's variance is at
/// controlled vertices). Measured per scene in `docs/bench/README.md`.
pub fn predicted_fit_gain(
    cells: &BTreeMap<u64, CellAccumulator>,
    coefficients: &BTreeMap<u64, CellCoefficients>,
) -> Option<f64> {
    FitSums::of(cells, coefficients, &BTreeMap::new()).fit_gain()
}

/// The sums behind [`predicted_image_gain`], [`predicted_fit_gain`] and the held-out
/// figures ([`SolvedTable::held_out_gain`], [`SolvedTable::held_out_share`]), made in one
/// pass over the cells in key order.
#[derive(Default)]
struct FitSums {
    /// `Σ_cells variance_reduction` (cells with coefficients).
    reduction: f64,
    /// `Σ_cells value_variance` (all cells).
    variance: f64,
    /// `Σ` held-out reduction over the cells judged on their halves.
    held_out: f64,
    /// `Σ variance_reduction` over the same cells.
    held_out_in_sample: f64,
}

impl FitSums {
    /// `held_out`: per cell judged on its halves, what its kept fit removes held out (empty
    /// for a table without halves).
    fn of(
        cells: &BTreeMap<u64, CellAccumulator>,
        coefficients: &BTreeMap<u64, CellCoefficients>,
        held_out: &BTreeMap<u64, f64>,
    ) -> Self {
        let mut sums = Self::default();
        for (k, a) in cells {
            sums.variance += crate::solve::value_variance(a);
            if let Some(co) = coefficients.get(k) {
                let r = variance_reduction(a, co);
                sums.reduction += r;
                if let Some(h) = held_out.get(k) {
                    sums.held_out += h;
                    sums.held_out_in_sample += r;
                }
            }
        }
        sums
    }

    /// The sums of a `per_light_cv` table: each cell's
    /// [`MeanContributionAccumulator::prediction`] (its reduction where the cell kept its
    /// coefficients) and, per cell judged on its halves, its held-out reduction; `None` when
    /// a cell has no prediction (a version-1 record).
    fn of_means(
        cells: &BTreeMap<u64, MeanContributionAccumulator>,
        coefficients: &BTreeMap<u64, CellCoefficients>,
        held_out: &BTreeMap<u64, f64>,
    ) -> Option<Self> {
        let mut sums = Self::default();
        for (k, a) in cells {
            let p = a.prediction()?;
            sums.variance += p.variance;
            if coefficients.get(k).is_some_and(|co| !co.is_fallback()) {
                sums.reduction += p.reduction;
                if let Some(h) = held_out.get(k) {
                    sums.held_out += h;
                    sums.held_out_in_sample += p.reduction;
                }
            }
        }
        Some(sums)
    }

    fn image_gain(&self, image: Option<f64>) -> Option<f64> {
        let image = image.filter(|&v| v > 0.0)?;
        Some(self.reduction / image)
    }

    fn fit_gain(&self) -> Option<f64> {
        (self.variance > 0.0).then(|| self.reduction / self.variance)
    }

    /// `(held-out gain, held-out share)` ([`SolvedTable::held_out_gain`],
    /// [`SolvedTable::held_out_share`]); both `None` without a positive variance.
    fn held_out_gains(&self) -> (Option<f64>, Option<f64>) {
        if !(self.variance > 0.0) {
            return (None, None);
        }
        let share =
            (self.held_out_in_sample > 0.0).then(|| self.held_out / self.held_out_in_sample);
        (Some(self.held_out / self.variance), share)
    }
}

impl SolvedTable {
    /// The wire encoding ([`KIND_COEFFICIENTS`]).
    pub fn encode(&self) -> Vec<u8> {
        encode_table(&self.coefficients)
    }

    /// Decodes [`Self::encode`]'s bytes (validating everything): the coefficients; the
    /// fields the wire does not carry are their defaults.
    pub fn decode(bytes: &[u8]) -> Result<Self, CellError> {
        Ok(Self {
            coefficients: decode_table(bytes)?,
            ..Self::default()
        })
    }
}

impl AccumulatorTable {
    /// An empty table of `kind` ([`KIND_CELL_ACCUMULATORS`] or [`KIND_MEAN_CONTRIBUTIONS`]).
    pub fn empty(kind: u16) -> Result<Self, CellError> {
        match kind {
            KIND_CELL_ACCUMULATORS => Ok(Self::Moments(BTreeMap::new(), Some(0.0))),
            KIND_MEAN_CONTRIBUTIONS => Ok(Self::Mean(BTreeMap::new(), Some(0.0))),
            _ => Err(CellError::BadHeader),
        }
    }

    /// The kind tag.
    pub fn kind(&self) -> u16 {
        match self {
            Self::Moments(..) => KIND_CELL_ACCUMULATORS,
            Self::Mean(..) => KIND_MEAN_CONTRIBUTIONS,
        }
    }

    /// Number of cells.
    pub fn len(&self) -> usize {
        match self {
            Self::Moments(t, _) => t.len(),
            Self::Mean(t, _) => t.len(),
        }
    }

    /// Whether no cell has a record.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Share of the table's light-partition samples in partitions with fewer than `min`
    /// samples in their cell (with `halves`, keys `2c` and `2c + 1` count as cell `c`): the
    /// samples a solve with `min_group_samples = min` fits in pooled groups of partitions
    /// ([`crate::solve::partition_groups`]) rather than partition by partition. `None` for
    /// a table of mean contributions or one without partition samples.
    ///
    /// A few samples per pixel of a many-light scene leave most partitions thin, and their
    /// grouped fits remove a fraction of what the same cells' fits remove once the
    /// partitions fill: on `many-lights` (64 lamps) the training probe's fit gain is
    /// 0.016–0.15 at 2 spp, the job's 0.26–0.30 at 16.
    pub fn thin_partition_share(&self, min: u64, halves: bool) -> Option<f64> {
        let Self::Moments(t, _) = self else {
            return None;
        };
        let (mut total, mut thin) = (0u64, 0u64);
        let mut count = |c: u64| {
            total += c;
            if c < min {
                thin += c;
            }
        };
        // A cell's halves `2c` and `2c + 1` are neighbours in key order, and each lists its
        // partitions by increasing id: a merge-join per cell (a map over every cell and
        // partition was 14 M of a many-light training pass's 511 M instructions).
        let mut cells = t.iter().peekable();
        while let Some((&k, a)) = cells.next() {
            let other = match cells.peek() {
                Some((k2, _)) if halves && **k2 >> 1 == k >> 1 => cells.next().map(|(_, b)| b),
                _ => None,
            };
            let ids = |p: crate::cell::PartitionMoments<'_>| (p.id, p.count);
            let mut pa = a.partitions().map(ids).peekable();
            let mut pb = other
                .into_iter()
                .flat_map(|b| b.partitions())
                .map(ids)
                .peekable();
            loop {
                let n = match (pa.peek().copied(), pb.peek().copied()) {
                    (None, None) => break,
                    (Some((i, x)), Some((j, y))) if i == j => {
                        pa.next();
                        pb.next();
                        x + y
                    }
                    (Some((i, x)), Some((j, _))) if i < j => {
                        pa.next();
                        x
                    }
                    (Some((_, x)), None) => {
                        pa.next();
                        x
                    }
                    (_, Some((_, y))) => {
                        pb.next();
                        y
                    }
                };
                count(n);
            }
        }
        (total > 0).then(|| thin as f64 / total as f64)
    }

    /// Largest cell key, if any.
    pub fn max_key(&self) -> Option<u64> {
        match self {
            Self::Moments(t, _) => t.keys().next_back().copied(),
            Self::Mean(t, _) => t.keys().next_back().copied(),
        }
    }

    /// Decodes a table of either accumulator kind (validating everything).
    pub fn decode(bytes: &[u8]) -> Result<Self, CellError> {
        match table_kind(bytes)? {
            KIND_CELL_ACCUMULATORS => {
                let (t, image) = decode_table_with(bytes)?;
                Ok(Self::Moments(t, image))
            }
            KIND_MEAN_CONTRIBUTIONS => {
                let (t, image) = decode_table_with(bytes)?;
                Ok(Self::Mean(t, image))
            }
            _ => Err(CellError::BadHeader),
        }
    }

    /// The wire encoding.
    pub fn encode(&self) -> Vec<u8> {
        match self {
            Self::Moments(t, image) => encode_table_with(t, *image),
            Self::Mean(t, image) => encode_table_with(t, *image),
        }
    }

    /// Merges `other` into `self` key by key ([`merge_tables`]); different kinds are a
    /// [`CellError::LayoutMismatch`].
    pub fn merge(&mut self, other: &Self) -> Result<(), CellError> {
        self.merge_cow(Cow::Borrowed(other))
    }

    /// [`Self::merge`] of a table the caller gives up: its new cells are moved, not copied
    /// (the same sums).
    pub fn merge_owned(&mut self, other: Self) -> Result<(), CellError> {
        self.merge_cow(Cow::Owned(other))
    }

    /// [`Self::merge`] (`other` borrowed) or [`Self::merge_owned`] (owned).
    fn merge_cow(&mut self, other: Cow<'_, Self>) -> Result<(), CellError> {
        let (Self::Moments(_, image) | Self::Mean(_, image)) = other.as_ref();
        let image = *image;
        match (&mut *self, other) {
            (Self::Moments(a, _), Cow::Borrowed(Self::Moments(b, _))) => merge_tables(a, b)?,
            (Self::Moments(a, _), Cow::Owned(Self::Moments(b, _))) => merge_tables_owned(a, b)?,
            (Self::Mean(a, _), Cow::Borrowed(Self::Mean(b, _))) => merge_tables(a, b)?,
            (Self::Mean(a, _), Cow::Owned(Self::Mean(b, _))) => merge_tables_owned(a, b)?,
            _ => return Err(CellError::LayoutMismatch),
        }
        let (Self::Moments(_, mine) | Self::Mean(_, mine)) = self;
        *mine = add_image_variances(*mine, image);
        Ok(())
    }

    /// Whether [`Self::solve`] keeps the fits under `policy` (does not switch them off:
    /// [`SolvedTable::switched_off`]) either as given or with every cell fitted on its own
    /// samples (`levels` 0).
    ///
    /// For a check without held-out halves to choose a level by ([`CellHalves::Merged`]: a
    /// subdivided table's cells take their undivided ancestors' fits), which the table
    /// solve with halves makes per node ([`CellHalves::CrossFitted`]): where the cells'
    /// integrands differ within an undivided cell (a glossy highlight) only their own fits
    /// pay, and where each cell has few samples only the pooled ones do. Without levels the
    /// two are one solve.
    pub fn fits_pay_pooled_or_alone(&self, policy: &SolvePolicy, threads: usize) -> bool {
        if self.solve(policy, threads).switched_off.is_none() {
            return true;
        }
        policy.levels > 0
            && self
                .solve(
                    &SolvePolicy {
                        levels: 0,
                        ..*policy
                    },
                    threads,
                )
                .switched_off
                .is_none()
    }

    /// Solves every cell ([`solve`] for moments [Hua eq. 32–33], the mean contributions for
    /// `per_light_cv` [Hua §7.2]) on up to `threads` threads. Cells are independent, so the
    /// result does not depend on `threads`. The table's [`predicted_image_gain`] (with a
    /// known image variance) and [`predicted_fit_gain`] are recorded (for `per_light_cv` the
    /// same two ratios of its cells' [`MeanContributionAccumulator::prediction`]s, over the
    /// cells that kept their coefficients); when the first
    /// is below [`SolvePolicy::min_image_gain`] every fitted cell falls back
    /// ([`FallbackReason::LowImageGain`]), else when the second is below
    /// [`SolvePolicy::min_fit_gain`] ([`FallbackReason::LowFitGain`]), else, for a
    /// cross-fitted table, when its held-out share is below
    /// [`SolvePolicy::min_held_out_share`] and its held-out gain below `min_fit_gain` (or the
    /// share decides alone, [`SolvePolicy::held_out_share_alone`])
    /// ([`FallbackReason::Overfitted`]; [`SolvedTable::held_out_share`]): the render then pays
    /// no CV work anywhere. An
    /// unknown gain makes no decision.
    pub fn solve(&self, policy: &SolvePolicy, threads: usize) -> SolvedTable {
        fn par<T: Sync>(
            cells: &BTreeMap<u64, T>,
            threads: usize,
            f: impl Fn(&T) -> (CellCoefficients, u64) + Sync,
        ) -> SolvedTable {
            let mut out = SolvedTable::default();
            for (k, (co, r)) in cells.keys().zip(par_map(cells, threads, |_, v| f(v))) {
                out.rejected += r;
                out.coefficients.insert(*k, co);
            }
            out
        }
        let (mut out, sums, image) = match self {
            Self::Moments(t, image) if policy.halves == CellHalves::CrossFitted => {
                let cells = pair_halves(t, threads);
                let (mut out, held_out) = solve_hierarchy(&cells, policy, threads);
                let merged: BTreeMap<u64, CellAccumulator> =
                    cells.into_iter().map(|(k, (a, _))| (k, a)).collect();
                let sums = FitSums::of(&merged, &out.coefficients, &held_out);
                (out.held_out_gain, out.held_out_share) = sums.held_out_gains();
                (out, Some(sums), *image)
            }
            Self::Moments(t, image) if policy.halves == CellHalves::Merged => {
                // Without a held-out check to choose a level by, the cells of a hierarchy
                // take their undivided ancestor's fit.
                let (merged, members) = undivided(
                    pair_halves(t, threads)
                        .into_iter()
                        .map(|(k, (a, _))| (k, a)),
                    policy,
                );
                let coarse = par(&merged, threads, |a| (solve(a, policy), a.rejected()));
                let sums = FitSums::of(&merged, &coarse.coefficients, &BTreeMap::new());
                let mut out = SolvedTable {
                    rejected: coarse.rejected,
                    ..SolvedTable::default()
                };
                for (ancestor, co) in &coarse.coefficients {
                    for &k in &members[ancestor] {
                        out.coefficients.insert(k, co.clone());
                    }
                }
                (out, Some(sums), *image)
            }
            Self::Moments(t, image) => {
                let out = par(t, threads, |a| (solve(a, policy), a.rejected()));
                let sums = FitSums::of(t, &out.coefficients, &BTreeMap::new());
                (out, Some(sums), *image)
            }
            Self::Mean(t, image) => {
                // Recorded with halves: the cells' means are fitted on both halves; with
                // `CrossFitted` each kept cell's halves are also judged on each other.
                let (merged, halves): (Cow<'_, BTreeMap<u64, _>>, BTreeMap<u64, Halves<'_, _>>) =
                    if policy.halves == CellHalves::None {
                        (Cow::Borrowed(t), BTreeMap::new())
                    } else {
                        let (m, h) = pair_halves_by(t, threads, |a, b| a.merge(b).is_ok())
                            .into_iter()
                            .map(|(k, (a, halves))| ((k, a), (k, halves)))
                            .unzip();
                        (Cow::Owned(m), h)
                    };
                let mut out = par(&merged, threads, |a| {
                    (
                        crate::perlight::mean_contribution_coefficients(a, policy.min_samples),
                        a.rejected(),
                    )
                });
                let cross_fitted = policy.halves == CellHalves::CrossFitted;
                let mut held_out = BTreeMap::new();
                for (k, (even, odd)) in halves.iter().filter(|_| cross_fitted) {
                    let kept = out.coefficients.get(k).is_some_and(|c| !c.is_fallback());
                    if let (true, Some(even), Some(odd)) = (kept, even, odd)
                        && let (Some(a), Some(b)) =
                            (odd.held_out_reduction(even), even.held_out_reduction(odd))
                    {
                        held_out.insert(*k, a + b);
                    }
                }
                let sums = FitSums::of_means(&merged, &out.coefficients, &held_out);
                if cross_fitted && let Some(s) = &sums {
                    (out.held_out_gain, out.held_out_share) = s.held_out_gains();
                }
                (out, sums, *image)
            }
        };
        if let Some(sums) = sums {
            out.image_gain = sums.image_gain(image);
            out.fit_gain = sums.fit_gain();
        }
        let below = |gain: Option<f64>, min: f64| {
            gain.is_some_and(|g| min > f64::NEG_INFINITY && !(g >= min))
        };
        let reason = if below(out.image_gain, policy.min_image_gain) {
            Some(FallbackReason::LowImageGain)
        } else if below(out.fit_gain, policy.min_fit_gain) {
            Some(FallbackReason::LowFitGain)
        } else if below(out.held_out_share, policy.min_held_out_share)
            && (policy.held_out_share_alone || below(out.held_out_gain, policy.min_fit_gain))
        {
            Some(FallbackReason::Overfitted)
        } else {
            None
        };
        out.switched_off = reason;
        if let Some(reason) = reason {
            for co in out.coefficients.values_mut() {
                if !co.is_fallback() {
                    *co = CellCoefficients::fallen_back(
                        co.layout(),
                        co.color(),
                        *co.diagnostics(),
                        reason,
                    );
                }
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cell::{ColorMode, ComponentLayout, CvSample};

    fn acc(v: f64) -> CellAccumulator {
        let mut a = CellAccumulator::new(ComponentLayout::new(3, 1).unwrap(), ColorMode::Rgb);
        for i in 0..20u32 {
            let s = CvSample {
                pdf: 1.0 + f64::from(i),
                partition: Some((i % 3, 1.0)),
                overlapping: &[0.5],
            };
            a.add(1.0, [v, v * 2.0, 1.0], &s).unwrap();
        }
        a
    }

    #[test]
    fn tables_round_trip_merge_and_solve() {
        let t1: BTreeMap<u64, CellAccumulator> = [(5, acc(1.0)), (9, acc(2.0))].into();
        let t2: BTreeMap<u64, CellAccumulator> = [(9, acc(3.0)), (12, acc(0.5))].into();
        let bytes = encode_table(&t1);
        assert_eq!(table_kind(&bytes), Ok(KIND_CELL_ACCUMULATORS));
        let back: BTreeMap<u64, CellAccumulator> = decode_table(&bytes).unwrap();
        assert_eq!(back, t1);
        for n in 0..bytes.len() {
            assert!(decode_table::<CellAccumulator>(&bytes[..n]).is_err());
        }
        assert_eq!(
            decode_table::<CellCoefficients>(&bytes),
            Err(CellError::BadHeader)
        );
        let mut merged = t1.clone();
        merge_tables(&mut merged, &t2).unwrap();
        assert_eq!(merged.len(), 3);
        assert_eq!(merged[&9].samples(), 40);
        let coeffs = solve_table(&merged, &SolvePolicy::default());
        let cb = encode_table(&coeffs);
        let back: BTreeMap<u64, CellCoefficients> = decode_table(&cb).unwrap();
        assert_eq!(encode_table(&back), cb);
    }

    #[test]
    fn par_map_gives_every_entry_its_result_in_key_order_for_any_thread_count() {
        // More entries than runs of every thread count, and fewer than one run.
        for n in [
            0u64,
            1,
            5,
            PAR_MAP_RUN as u64 + 1,
            10 * PAR_MAP_RUN as u64 + 7,
        ] {
            let cells: BTreeMap<u64, u64> = (0..n).map(|k| (3 * k + 1, k * k)).collect();
            let want: Vec<(u64, u64)> = cells.iter().map(|(&k, &v)| (k, v + k)).collect();
            for threads in [0, 1, 2, 3, 8] {
                let got = par_map(&cells, threads, |k, &v| (k, v + k));
                assert_eq!(got, want, "{n} entries, {threads} threads");
            }
        }
    }

    #[test]
    fn thin_partition_share_counts_each_cells_partitions_with_halves_merged() {
        // Each `acc` has 20 samples in partitions 0, 1, 2: 7, 7 and 6 of them.
        let t = AccumulatorTable::Moments([(4, acc(1.0)), (5, acc(2.0))].into(), None);
        // Two cells: every partition thin below 8, the two 6s below 7.
        assert_eq!(t.thin_partition_share(8, false), Some(1.0));
        assert_eq!(t.thin_partition_share(7, false), Some(12.0 / 40.0));
        assert_eq!(t.thin_partition_share(6, false), Some(0.0));
        // Keys 4 and 5 are the halves of cell 2: 14, 14 and 12 samples.
        assert_eq!(t.thin_partition_share(13, true), Some(12.0 / 40.0));
        assert_eq!(t.thin_partition_share(15, true), Some(1.0));
        let empty = AccumulatorTable::Moments(BTreeMap::new(), None);
        assert_eq!(empty.thin_partition_share(8, false), None);
        let means = AccumulatorTable::empty(KIND_MEAN_CONTRIBUTIONS).unwrap();
        assert_eq!(means.thin_partition_share(8, false), None);
    }

    proptest::proptest! {
        /// The per-cell merge-join counts what a map over every (cell, partition) counts,
        /// with halves that sample different partitions, lone halves and neighbouring cells.
        #[test]
        fn thin_partition_share_matches_a_map_over_cells_and_partitions(
            cells in proptest::collection::btree_map(
                0u64..24,
                proptest::collection::vec(0u32..6, 0..12),
                0..10,
            ),
            min in 0u64..5,
        ) {
            let layout = ComponentLayout::new(6, 1).unwrap();
            let table: BTreeMap<u64, CellAccumulator> = cells
                .iter()
                .map(|(&k, parts)| {
                    let mut a = CellAccumulator::new(layout, ColorMode::Rgb);
                    for &p in parts {
                        let s = CvSample { pdf: 1.0, partition: Some((p, 1.0)), overlapping: &[0.5] };
                        a.add(1.0, [1.0, 0.5, 0.25], &s).unwrap();
                    }
                    (k, a)
                })
                .collect();
            for halves in [false, true] {
                let mut counts: BTreeMap<(u64, u32), u64> = BTreeMap::new();
                for (&k, a) in &table {
                    let cell = if halves { k >> 1 } else { k };
                    for p in a.partitions() {
                        *counts.entry((cell, p.id)).or_default() += p.count;
                    }
                }
                let total: u64 = counts.values().sum();
                let thin: u64 = counts.values().filter(|&&c| c < min).sum();
                let expected = (total > 0).then(|| thin as f64 / total as f64);
                let t = AccumulatorTable::Moments(table.clone(), None);
                proptest::prop_assert_eq!(t.thin_partition_share(min, halves), expected);
            }
        }
    }

    #[test]
    fn the_image_variance_rides_with_the_table_and_unknown_stays_unknown() {
        let t: BTreeMap<u64, CellAccumulator> = [(5, acc(1.0)), (9, acc(2.0))].into();
        let a = AccumulatorTable::Moments(t.clone(), Some(0.75));
        let bytes = a.encode();
        assert_eq!(AccumulatorTable::decode(&bytes).unwrap(), a);
        for n in 0..bytes.len() {
            assert!(AccumulatorTable::decode(&bytes[..n]).is_err());
        }
        // Version 1 (no trailing f64): unknown.
        let mut v1 = bytes[..bytes.len() - 8].to_vec();
        v1[4..6].copy_from_slice(&1u16.to_le_bytes());
        let old = AccumulatorTable::decode(&v1).unwrap();
        assert_eq!(old, AccumulatorTable::Moments(t.clone(), None));
        // A negative or infinite variance is refused; NaN is unknown.
        let at = bytes.len() - 8;
        for (v, ok) in [
            (-1.0, false),
            (f64::INFINITY, false),
            (f64::NAN, true),
            (0.0, true),
        ] {
            let mut b = bytes.clone();
            b[at..].copy_from_slice(&f64::to_le_bytes(v));
            assert_eq!(AccumulatorTable::decode(&b).is_ok(), ok, "{v}");
        }
        // Merges add the variances in order; one unknown makes the sum unknown.
        let mut m = AccumulatorTable::empty(KIND_CELL_ACCUMULATORS).unwrap();
        m.merge(&a).unwrap();
        m.merge(&AccumulatorTable::Moments(t.clone(), Some(0.5)))
            .unwrap();
        assert!(matches!(m, AccumulatorTable::Moments(_, Some(v)) if v == 1.25));
        m.merge(&old).unwrap();
        assert!(matches!(m, AccumulatorTable::Moments(_, None)));
        // A merge of an owned table (its new cells moved) is the same merge.
        let mut owned = AccumulatorTable::empty(KIND_CELL_ACCUMULATORS).unwrap();
        owned.merge_owned(a.clone()).unwrap();
        owned
            .merge_owned(AccumulatorTable::Moments(t.clone(), Some(0.5)))
            .unwrap();
        let mut borrowed = AccumulatorTable::empty(KIND_CELL_ACCUMULATORS).unwrap();
        borrowed.merge(&a).unwrap();
        borrowed
            .merge(&AccumulatorTable::Moments(t.clone(), Some(0.5)))
            .unwrap();
        assert_eq!(owned, borrowed);
        assert_eq!(owned.encode(), borrowed.encode());
        // Tables of different kinds do not merge, either way.
        let mean = AccumulatorTable::Mean(BTreeMap::new(), None);
        assert!(owned.merge(&mean).is_err());
        assert!(owned.merge_owned(mean).is_err());
        // Coefficient and mean tables carry no variance (NaN) and still decode strictly.
        let co = solve_table(&t, &SolvePolicy::default());
        let cb = encode_table(&co);
        assert!(f64::from_le_bytes(cb[cb.len() - 8..].try_into().unwrap()).is_nan());
        assert_eq!(decode_table_with::<CellCoefficients>(&cb).unwrap().1, None);
    }
}
