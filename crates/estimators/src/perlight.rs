//! Per-light mean-contribution coefficients: the `per_light_cv` baseline [Hua §7.2]
//! (Vévoda et al. 2018).
//!
//! Per spatial cell and light `i`, the coefficient is the mean MIS-weighted next-event
//! contribution of light `i` over the cell's vertices; there is no solve. Hua shows these
//! are the optimal coefficients when the CV is formed from the light-sampling pdfs only and
//! fitted to the MIS-weighted NEE integral, so the baseline is never worse than plain NEE
//! **in the cell's pooled, unweighted variance**.
//!
//! That is not the error of an image: a cell mixes vertices of bright and dark pixels (and
//! of large and small path throughput), and the CV term `α_i/c_i − Σα` it adds to every
//! vertex is the same size at all of them. At a dark pixel's vertex it is pure added
//! variance, and a relative error (relMSE) weighs those pixels most. So the accumulator also
//! sums each vertex's **training weight** `w` (squared throughput over the squared surrogate
//! with relative training [Hua eq. 25, 29], as `cms` weighs its samples) and
//! [`MeanContributionAccumulator::prediction`] gives the in-sample change of the weighted
//! variance; [`mean_contribution_coefficients`] keeps a cell's coefficients only where they
//! reduce it, and the table decides as `cms` does whether the rest pays
//! ([`crate::table::AccumulatorTable::solve`]).
//!
//! # The predicted change
//! Vertex `v` selects light `k_v` with probability `c_{k_v}` (`s_v = 1/c_{k_v}`) and
//! estimates `F_v` (zero when the sample failed or is occluded); the controlled estimate is
//! `F_v − α_{k_v} s_v + A`, `A = Σ_i α_i`, and `E[α_k s | vertex] = A`. Its change in the
//! weighted variance, per channel, is `Δ = Σ_v w_v [(A − α_{k_v} s_v)² + 2 F_v (A − α_{k_v} s_v)]`
//! `= A² W − 2A Σ_i α_i WS_i + Σ_i α_i² WSS_i + 2A WF − 2 Σ_i α_i WSF_i` with `W = Σ w`,
//! `WF = Σ w F` over the cell's vertices and `WS_i = Σ w s`, `WSS_i = Σ w s²`, `WSF_i = Σ w s F`
//! over those that selected light `i`. With equal weights and `α` the cell means it is
//! `−N (Σ_i α_i²/c_i − A²) ≤ 0` (Hua's statement); with training weights it can be positive.
//!
//! # Contract
//! - Call [`MeanContributionAccumulator::record`] once per shading vertex that performs NEE
//!   in the cell, with its training weight, the light its NEE sample selected (and that
//!   light's `1/c`) and the sample's unbiased estimate of the light's MIS-weighted
//!   contribution, `w_nee · f / (c_i p_i)` (`c_i` selection probability, `p_i` the light's
//!   pdf; zero for a failed or occluded sample). Averaging over all vertices (selected or not)
//!   gives an unbiased estimate of each light's mean contribution.
//! - [`mean_contribution_coefficients`] turns the sums into a [`CellCoefficients`] with one
//!   partition per light and no overlapping component; apply it with `λ_i = p_i` and the NEE
//!   density as `p` (see [`crate::solve`]).
//! - Merge is element-wise addition; the encoding (magic `CVML`, version 2) round-trips
//!   bit-exactly and decoding validates like [`crate::cell`]. Version 1 (no weighted sums)
//!   still decodes: such a cell makes no prediction.

use crate::cell::{CHANNELS, CellError, ColorMode, ComponentLayout, Reader};
use crate::solve::{CellCoefficients, FallbackReason};

/// Magic bytes of an encoded [`MeanContributionAccumulator`].
pub const MAGIC: [u8; 4] = *b"CVML";
/// Encoding version (2: with the weighted sums).
pub const VERSION: u16 = 2;

/// One light's sums in a cell (see the module docs for the names).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
struct Entry {
    /// `Σ F` over the vertices that selected the light (unweighted).
    sum: [f64; CHANNELS],
    /// `WS = Σ w s`.
    ws: f64,
    /// `WSS = Σ w s²`.
    wss: f64,
    /// `WSF = Σ w s F`.
    wsf: [f64; CHANNELS],
}

impl Entry {
    fn add(&mut self, o: &Self) {
        for c in 0..CHANNELS {
            self.sum[c] += o.sum[c];
            self.wsf[c] += o.wsf[c];
        }
        self.ws += o.ws;
        self.wss += o.wss;
    }
}

/// The weighted sums over all of a cell's vertices.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
struct VertexSums {
    /// `W = Σ w`.
    w: f64,
    /// `WF = Σ w F`.
    wf: [f64; CHANNELS],
    /// `Σ w F²`.
    wff: [f64; CHANNELS],
}

/// Sums of per-light NEE contributions of one cell (sparse over lights).
#[derive(Clone, Debug, PartialEq)]
pub struct MeanContributionAccumulator {
    lights: u32,
    vertices: u64,
    rejected: u64,
    /// `None` for a version-1 record and after merging one: no prediction.
    weighted: Option<VertexSums>,
    ids: Vec<u32>,
    entries: Vec<Entry>,
}

/// The in-sample effect of a cell's per-light CV on the weighted variance of its NEE
/// estimates (module docs), summed over channels.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MeanPrediction {
    /// `−Δ`: how much weighted variance the CV removes (negative: it adds).
    pub reduction: f64,
    /// The weighted variance of the plain NEE estimates, `Σ w F² − (Σ w F)²/W`.
    pub variance: f64,
}

impl MeanContributionAccumulator {
    /// Empty accumulator for `lights` lights (partitions).
    pub fn new(lights: u32) -> Self {
        Self {
            lights,
            vertices: 0,
            rejected: 0,
            weighted: Some(VertexSums::default()),
            ids: Vec::new(),
            entries: Vec::new(),
        }
    }

    /// Number of lights.
    pub fn lights(&self) -> u32 {
        self.lights
    }

    /// Vertices counted.
    pub fn vertices(&self) -> u64 {
        self.vertices
    }

    /// Rejected vertices (non-finite or negative weight, non-finite value or inverse
    /// selection probability, out-of-range light).
    pub fn rejected(&self) -> u64 {
        self.rejected
    }

    /// Counts one NEE vertex of the cell with training weight `weight`: `selected` is the
    /// light its NEE sample selected and that light's inverse selection probability `1/c`
    /// (`None`: no light), `contribution` the sample's estimate (zero for a failed or
    /// occluded sample). Returns `false` (and counts a rejection; the vertex still counts,
    /// with nothing added) for a non-finite or negative weight, a non-finite value or `1/c`,
    /// or an out-of-range light.
    pub fn record(
        &mut self,
        weight: f64,
        selected: Option<(u32, f64)>,
        contribution: [f64; CHANNELS],
    ) -> bool {
        self.vertices += 1;
        let valid = weight.is_finite()
            && weight >= 0.0
            && contribution.iter().all(|c| c.is_finite())
            && selected.is_none_or(|(l, s)| l < self.lights && s.is_finite());
        if !valid {
            self.rejected += 1;
            return false;
        }
        if let Some(v) = &mut self.weighted {
            v.w += weight;
            for (c, &f) in contribution.iter().enumerate() {
                v.wf[c] += weight * f;
                v.wff[c] += weight * f * f;
            }
        }
        if let Some((light, s)) = selected {
            let e = self.entry(light);
            let ws = weight * s;
            for (c, &f) in contribution.iter().enumerate() {
                e.sum[c] += f;
                e.wsf[c] += ws * f;
            }
            e.ws += ws;
            e.wss += ws * s;
        }
        true
    }

    fn entry(&mut self, light: u32) -> &mut Entry {
        let slot = match self.ids.binary_search(&light) {
            Ok(s) => s,
            Err(s) => {
                self.ids.insert(s, light);
                self.entries.insert(s, Entry::default());
                s
            }
        };
        &mut self.entries[slot]
    }

    /// `α_i = Σ F_i / vertices` per recorded light, in light order (empty without vertices).
    fn alphas(&self) -> impl Iterator<Item = (u32, [f64; CHANNELS])> + '_ {
        let n = self.vertices.max(1) as f64;
        self.ids
            .iter()
            .zip(&self.entries)
            .map(move |(&id, e)| (id, e.sum.map(|v| v / n)))
    }

    /// The in-sample change of the weighted variance that the coefficients
    /// [`mean_contribution_coefficients`] would fit (module docs); `None` for a version-1
    /// record. A cell without weight predicts no change.
    pub fn prediction(&self) -> Option<MeanPrediction> {
        let v = self.weighted?;
        let alphas: Vec<(u32, [f64; CHANNELS])> = self.alphas().collect();
        let mut variance = 0.0;
        for c in 0..CHANNELS {
            if v.w > 0.0 {
                variance += (v.wff[c] - v.wf[c] * v.wf[c] / v.w).max(0.0);
            }
        }
        Some(MeanPrediction {
            reduction: -self.change(&v, &alphas),
            variance,
        })
    }

    /// What the coefficients fitted on `fit` (its light means, as
    /// [`mean_contribution_coefficients`] would apply them) remove from this accumulator's
    /// weighted variance: `−Δ` of the module docs with `fit`'s `α` and these sums. Where the
    /// two are a cell's two halves this is a held-out reduction: the means carry none of
    /// these vertices' noise. `None` where either is a version-1 record.
    pub fn held_out_reduction(&self, fit: &Self) -> Option<f64> {
        let v = self.weighted?;
        fit.weighted?;
        let alphas: Vec<(u32, [f64; CHANNELS])> = fit.alphas().collect();
        Some(-self.change(&v, &alphas))
    }

    /// `Δ` over the channels (module docs) with the coefficients `alphas` (in light order)
    /// and this accumulator's sums `v` and entries; a light without an entry here has no
    /// `WS`, `WSS`, `WSF`.
    fn change(&self, v: &VertexSums, alphas: &[(u32, [f64; CHANNELS])]) -> f64 {
        let mut big_a = [0.0f64; CHANNELS];
        for (_, a) in alphas {
            for c in 0..CHANNELS {
                big_a[c] += a[c];
            }
        }
        let none = Entry::default();
        let entries: Vec<&Entry> = alphas
            .iter()
            .map(|(id, _)| {
                self.ids
                    .binary_search(id)
                    .map_or(&none, |slot| &self.entries[slot])
            })
            .collect();
        let mut delta = 0.0;
        for c in 0..CHANNELS {
            let ac = big_a[c];
            let mut d = ac * ac * v.w + 2.0 * ac * v.wf[c];
            for ((_, a), e) in alphas.iter().zip(&entries) {
                let a = a[c];
                d += a * (a * e.wss - 2.0 * ac * e.ws - 2.0 * e.wsf[c]);
            }
            delta += d;
        }
        delta
    }

    /// Adds `other` into `self` (element-wise); fails if the light counts differ.
    pub fn merge(&mut self, other: &Self) -> Result<(), CellError> {
        if self.lights != other.lights {
            return Err(CellError::LayoutMismatch);
        }
        self.vertices += other.vertices;
        self.rejected += other.rejected;
        self.weighted = match (self.weighted, other.weighted) {
            (Some(mut a), Some(b)) => {
                a.w += b.w;
                for c in 0..CHANNELS {
                    a.wf[c] += b.wf[c];
                    a.wff[c] += b.wff[c];
                }
                Some(a)
            }
            _ => None,
        };
        for (&id, e) in other.ids.iter().zip(&other.entries) {
            self.entry(id).add(e);
        }
        if self.weighted.is_none() {
            // Unknown stays unknown (and encodes without the weighted sums).
            for e in &mut self.entries {
                *e = Entry {
                    sum: e.sum,
                    ..Entry::default()
                };
            }
        }
        Ok(())
    }

    /// Encodes: magic, `u16` version, `u32` lights, `u64` vertices, `u64` rejected, `u8`
    /// weighted (0/1), then (weighted) 7 `f64` `W, WF, Σ w F²`, `u32` entries, then per light
    /// `u32` index and 3 `f64` `Σ F` and (weighted) 5 `f64` `WS, WSS, WSF` (little endian).
    pub fn encode(&self) -> Vec<u8> {
        let per = if self.weighted.is_some() { 68 } else { 28 };
        let mut out = Vec::with_capacity(87 + self.ids.len() * per);
        out.extend_from_slice(&MAGIC);
        out.extend_from_slice(&VERSION.to_le_bytes());
        out.extend_from_slice(&self.lights.to_le_bytes());
        out.extend_from_slice(&self.vertices.to_le_bytes());
        out.extend_from_slice(&self.rejected.to_le_bytes());
        let put = |out: &mut Vec<u8>, vs: &[f64]| {
            for v in vs {
                out.extend_from_slice(&v.to_le_bytes());
            }
        };
        out.push(u8::from(self.weighted.is_some()));
        if let Some(v) = &self.weighted {
            put(&mut out, &[v.w]);
            put(&mut out, &v.wf);
            put(&mut out, &v.wff);
        }
        out.extend_from_slice(&(self.ids.len() as u32).to_le_bytes());
        for (id, e) in self.ids.iter().zip(&self.entries) {
            out.extend_from_slice(&id.to_le_bytes());
            put(&mut out, &e.sum);
            if self.weighted.is_some() {
                put(&mut out, &[e.ws, e.wss]);
                put(&mut out, &e.wsf);
            }
        }
        out
    }

    /// Decodes and validates (version 1 or 2); never panics.
    pub fn decode(bytes: &[u8]) -> Result<Self, CellError> {
        let mut r = Reader::new(bytes);
        if r.take(4)? != MAGIC {
            return Err(CellError::BadMagic);
        }
        let version = r.u16()?;
        if version != 1 && version != VERSION {
            return Err(CellError::UnsupportedVersion(version));
        }
        let mut acc = Self::new(r.u32()?);
        acc.vertices = r.u64()?;
        acc.rejected = r.u64()?;
        let f3 = |r: &mut Reader<'_>| -> Result<[f64; CHANNELS], CellError> {
            Ok([r.finite_f64()?, r.finite_f64()?, r.finite_f64()?])
        };
        acc.weighted = match if version == 1 { 0 } else { r.u8()? } {
            0 => None,
            1 => Some(VertexSums {
                w: r.nonneg_f64()?,
                wf: f3(&mut r)?,
                wff: f3(&mut r)?,
            }),
            _ => return Err(CellError::InvalidValue(r.pos() - 1)),
        };
        let per: u64 = if acc.weighted.is_some() { 68 } else { 28 };
        let n = u64::from(r.u32()?);
        if n > u64::from(acc.lights) || n * per > r.remaining() as u64 {
            return Err(CellError::BadEntryCount(n));
        }
        for _ in 0..n {
            let at = r.pos();
            let id = r.u32()?;
            if id >= acc.lights || acc.ids.last().is_some_and(|&p| id <= p) {
                return Err(CellError::BadPartition(at));
            }
            let mut e = Entry {
                sum: f3(&mut r)?,
                ..Entry::default()
            };
            if acc.weighted.is_some() {
                e.ws = r.nonneg_f64()?;
                e.wss = r.nonneg_f64()?;
                e.wsf = f3(&mut r)?;
            }
            acc.ids.push(id);
            acc.entries.push(e);
        }
        if !r.at_end() {
            return Err(CellError::Trailing(r.remaining()));
        }
        Ok(acc)
    }
}

/// Coefficients `α_i = Σ contributions_i / vertices` [Hua §7.2]; the plain estimator for a
/// cell without vertices, and a fallback for a cell with fewer than `min_vertices` vertices
/// ([`FallbackReason::TooFewSamples`]: its means, and its in-sample prediction, are too
/// noisy) or whose [`MeanContributionAccumulator::prediction`] says they would not reduce
/// its weighted variance ([`FallbackReason::NoReduction`]).
pub fn mean_contribution_coefficients(
    acc: &MeanContributionAccumulator,
    min_vertices: u64,
) -> CellCoefficients {
    let layout = ComponentLayout {
        partitions: acc.lights,
        overlapping: 0,
    };
    let plain = CellCoefficients::plain(layout, ColorMode::Rgb);
    if acc.vertices == 0 {
        return plain;
    }
    let fallback = |reason| {
        CellCoefficients::fallen_back(layout, ColorMode::Rgb, *plain.diagnostics(), reason)
    };
    if acc.vertices < min_vertices {
        return fallback(FallbackReason::TooFewSamples);
    }
    if acc.prediction().is_some_and(|p| !(p.reduction > 0.0)) {
        return fallback(FallbackReason::NoReduction);
    }
    let parts: Vec<(u32, [f64; CHANNELS])> = acc.alphas().collect();
    CellCoefficients::from_values(layout, ColorMode::Rgb, &parts, &[]).unwrap_or(plain)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::solve::SolveStatus;
    use proptest::prelude::*;

    #[test]
    fn coefficients_are_mean_contributions_per_vertex() {
        // Light 0 lit (F = value/c with c = 1/2), light 1 occluded.
        let mut acc = MeanContributionAccumulator::new(4);
        for i in 0..10 {
            let f = if i % 2 == 0 {
                [2.0, 4.0, 6.0]
            } else {
                [0.0; 3]
            };
            assert!(acc.record(1.0, Some((i % 2, 2.0)), f));
        }
        assert!(!acc.record(1.0, Some((9, 2.0)), [1.0; 3]));
        assert!(!acc.record(1.0, Some((1, 2.0)), [f64::NAN; 3]));
        assert!(!acc.record(-1.0, None, [0.0; 3]));
        // 13 vertices (the rejected ones count, with nothing added): α₀ = 5·F/13.
        assert_eq!(acc.vertices(), 13);
        let c = mean_contribution_coefficients(&acc, 1);
        assert_eq!(c.diagnostics().status, SolveStatus::Solved);
        assert_eq!(
            c.alpha_partition(0),
            [10.0 / 13.0, 20.0 / 13.0, 30.0 / 13.0]
        );
        assert_eq!(c.alpha_partition(1), [0.0; 3]);
        assert_eq!(c.alpha_partition(3), [0.0; 3]);
        assert_eq!(acc.rejected(), 3);
        // Fewer vertices than asked for: too few samples.
        assert_eq!(
            mean_contribution_coefficients(&acc, 14)
                .diagnostics()
                .status,
            SolveStatus::Fallback(FallbackReason::TooFewSamples)
        );
        // A constant estimate has nothing to remove: the cell falls back.
        let mut flat = MeanContributionAccumulator::new(2);
        for i in 0..10 {
            flat.record(1.0, Some((i % 2, 2.0)), [1.0; 3]);
        }
        assert_eq!(
            mean_contribution_coefficients(&flat, 1)
                .diagnostics()
                .status,
            SolveStatus::Fallback(FallbackReason::NoReduction)
        );
    }

    /// A training vertex: weight, selected light and `1/c`, NEE value.
    type Vertex = (f64, Option<(u32, f64)>, [f64; 3]);

    /// Training vertices of a cell with 4 lights: weight in `[0, 100)`, a selected light with
    /// `1/c` in `[1, 8)` or none, NEE value per channel in `[0, 5)`.
    fn vertices(len: std::ops::Range<usize>) -> impl Strategy<Value = Vec<Vertex>> {
        proptest::collection::vec(
            (
                0.0f64..100.0,
                proptest::option::of((0u32..4, 1.0f64..8.0)),
                proptest::array::uniform3(0.0f64..5.0),
            ),
            len,
        )
    }

    /// `Δ` by its definition, vertex by vertex.
    fn direct_reduction(vertices: &[Vertex], lights: u32) -> f64 {
        direct_reduction_with(vertices, vertices, lights)
    }

    /// `Δ` over `vertices` with the light means of `fitted_on`, vertex by vertex.
    fn direct_reduction_with(vertices: &[Vertex], fitted_on: &[Vertex], lights: u32) -> f64 {
        let n = fitted_on.len() as f64;
        let mut alpha = vec![[0.0f64; 3]; lights as usize];
        for (_, sel, f) in fitted_on {
            if let Some((k, _)) = sel {
                for c in 0..3 {
                    alpha[*k as usize][c] += f[c] / n;
                }
            }
        }
        let mut delta = 0.0;
        for c in 0..3 {
            let big_a: f64 = alpha.iter().map(|a| a[c]).sum();
            for (w, sel, f) in vertices {
                let h = sel.map_or(0.0, |(k, s)| alpha[k as usize][c] * s);
                delta += w * ((big_a - h).powi(2) + 2.0 * f[c] * (big_a - h));
            }
        }
        -delta
    }

    proptest! {
        /// The prediction from the sums is the vertex-by-vertex definition, also after a
        /// merge and an encoding round trip.
        #[test]
        fn prediction_is_the_vertex_sum(
            vs in vertices(1..60),
            split in 0usize..60,
        ) {
            let mut a = MeanContributionAccumulator::new(4);
            let mut b = MeanContributionAccumulator::new(4);
            for (i, (w, sel, f)) in vs.iter().enumerate() {
                let acc = if i < split { &mut a } else { &mut b };
                prop_assert!(acc.record(*w, *sel, *f));
            }
            a.merge(&b).unwrap();
            let a = MeanContributionAccumulator::decode(&a.encode()).unwrap();
            let want = direct_reduction(&vs, 4);
            let got = a.prediction().map(|p| p.reduction);
            let total_w: f64 = vs.iter().map(|v| v.0).sum();
            let got = got.unwrap();
            // Terms are at most w·(A + α s)² + 2 w F (A + α s) with A, α ≤ 5, s ≤ 8.
            let scale = total_w * 5e3;
            prop_assert!((got - want).abs() <= 1e-9 * scale.max(1.0), "{} vs {}", got, want);
        }

        /// A held-out reduction is the definition over one half's vertices with the other
        /// half's light means (lights the fitting half never selected have `α = 0`), both
        /// ways; a version-1 record on either side gives none.
        #[test]
        fn held_out_reduction_is_the_vertex_sum_with_the_other_halfs_means(
            vs in vertices(2..60),
            split in 1usize..59,
        ) {
            let split = split.min(vs.len() - 1);
            let (first, second) = vs.split_at(split);
            let mut a = MeanContributionAccumulator::new(4);
            let mut b = MeanContributionAccumulator::new(4);
            for (w, sel, f) in first {
                prop_assert!(a.record(*w, *sel, *f));
            }
            for (w, sel, f) in second {
                prop_assert!(b.record(*w, *sel, *f));
            }
            let scale = vs.iter().map(|v| v.0).sum::<f64>() * 5e3;
            for (held, fit, want) in [
                (&b, &a, direct_reduction_with(second, first, 4)),
                (&a, &b, direct_reduction_with(first, second, 4)),
            ] {
                let got = held.held_out_reduction(fit).unwrap();
                prop_assert!((got - want).abs() <= 1e-9 * scale.max(1.0), "{} vs {}", got, want);
            }
            let mut old = a.clone();
            old.weighted = None;
            prop_assert!(old.held_out_reduction(&b).is_none());
            prop_assert!(b.held_out_reduction(&old).is_none());
        }
    }

    /// With equal weights and every light selected exactly in proportion to its selection
    /// probability, the reduction is Hua's `N (Σ α²/c − A²) ≥ 0`: the cell keeps its
    /// coefficients.
    #[test]
    fn equal_weights_never_add_variance_in_the_cell() {
        let pmf = [0.5, 0.25, 0.25];
        let values = [[1.0, 0.5, 0.2], [4.0, 4.0, 4.0], [0.0, 0.0, 0.0]];
        let mut acc = MeanContributionAccumulator::new(3);
        for v in 0..400u32 {
            let k = [0, 0, 1, 2][(v % 4) as usize];
            let f = values[k].map(|x| x / pmf[k] * (1.0 + f64::from(v % 7) / 7.0));
            acc.record(1.0, Some((k as u32, 1.0 / pmf[k])), f);
        }
        let p = acc.prediction().unwrap();
        let n = 400.0;
        let mut want = 0.0;
        let alphas: Vec<[f64; 3]> = acc.alphas().map(|(_, a)| a).collect();
        for c in 0..3 {
            let big_a: f64 = alphas.iter().map(|a| a[c]).sum();
            let s: f64 = alphas.iter().zip(pmf).map(|(a, q)| a[c] * a[c] / q).sum();
            want += n * (s - big_a * big_a);
        }
        assert!(p.reduction > 0.0);
        assert!(
            (p.reduction - want).abs() < 1e-9 * want,
            "{} vs {want}",
            p.reduction
        );
        assert_eq!(
            mean_contribution_coefficients(&acc, 1).diagnostics().status,
            SolveStatus::Solved
        );
    }

    /// Bright vertices of weight 1 and as many dark ones (nothing lit) of weight 10⁴, as a
    /// relative-variance weight gives the dark pixels of a cell: the CV term at the dark
    /// vertices is pure added variance, and the cell falls back. Equal weights keep it.
    #[test]
    fn a_cell_of_bright_and_heavily_weighted_dark_vertices_falls_back() {
        let build = |dark_weight: f64| {
            let mut acc = MeanContributionAccumulator::new(2);
            for v in 0..200u32 {
                let k = v % 2;
                acc.record(1.0, Some((k, 2.0)), [f64::from(k + 1) * 2.0; 3]);
                acc.record(dark_weight, Some((k, 2.0)), [0.0; 3]);
            }
            acc
        };
        let dark = build(1e4);
        assert!(dark.prediction().unwrap().reduction < 0.0);
        assert_eq!(
            mean_contribution_coefficients(&dark, 1)
                .diagnostics()
                .status,
            SolveStatus::Fallback(FallbackReason::NoReduction)
        );
        assert_eq!(
            mean_contribution_coefficients(&dark, 1).alpha_sum(),
            [0.0; 3]
        );
        let even = build(1.0);
        assert!(even.prediction().unwrap().reduction > 0.0);
        assert_eq!(
            mean_contribution_coefficients(&even, 1)
                .diagnostics()
                .status,
            SolveStatus::Solved
        );
    }

    #[test]
    fn merge_and_encoding_round_trip() {
        let mut a = MeanContributionAccumulator::new(5);
        let mut b = MeanContributionAccumulator::new(5);
        a.record(0.5, Some((3, 4.0)), [1.0, 0.0, 0.5]);
        b.record(2.0, Some((1, 4.0)), [0.25, 0.0, 0.0]);
        b.record(1.0, Some((3, 4.0)), [1.0, 1.0, 1.0]);
        b.record(1.0, None, [0.0; 3]);
        a.merge(&b).unwrap();
        assert_eq!(a.vertices(), 4);
        let bytes = a.encode();
        assert_eq!(MeanContributionAccumulator::decode(&bytes).unwrap(), a);
        for n in 0..bytes.len() {
            assert!(MeanContributionAccumulator::decode(&bytes[..n]).is_err());
        }
        assert!(a.merge(&MeanContributionAccumulator::new(2)).is_err());
        assert!(
            mean_contribution_coefficients(&MeanContributionAccumulator::new(3), 1).alpha_sum()
                == [0.0; 3]
        );
        // A negative weight sum is refused.
        let mut bad = bytes.clone();
        bad[27..35].copy_from_slice(&(-1.0f64).to_le_bytes());
        assert!(MeanContributionAccumulator::decode(&bad).is_err());
    }

    /// A version-1 record (no weighted sums) decodes, predicts nothing, keeps its
    /// coefficients, and makes a merge with it predict nothing.
    #[test]
    fn version_one_records_decode_without_a_prediction() {
        let mut v1 = Vec::new();
        v1.extend_from_slice(&MAGIC);
        v1.extend_from_slice(&1u16.to_le_bytes());
        v1.extend_from_slice(&4u32.to_le_bytes());
        v1.extend_from_slice(&2u64.to_le_bytes());
        v1.extend_from_slice(&0u64.to_le_bytes());
        v1.extend_from_slice(&1u32.to_le_bytes());
        v1.extend_from_slice(&2u32.to_le_bytes());
        for v in [1.0f64, 2.0, 3.0] {
            v1.extend_from_slice(&v.to_le_bytes());
        }
        let old = MeanContributionAccumulator::decode(&v1).unwrap();
        assert_eq!(old.vertices(), 2);
        assert_eq!(old.prediction(), None);
        let co = mean_contribution_coefficients(&old, 1);
        assert_eq!(co.alpha_partition(2), [0.5, 1.0, 1.5]);
        let mut new = MeanContributionAccumulator::new(4);
        new.record(1.0, Some((2, 1.0)), [1.0; 3]);
        assert!(new.prediction().is_some());
        new.merge(&old).unwrap();
        assert_eq!(new.prediction(), None);
        // It re-encodes as version 2 without weights and round-trips.
        assert_eq!(
            MeanContributionAccumulator::decode(&new.encode()).unwrap(),
            new
        );
    }
}
