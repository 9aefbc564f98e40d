//! Per-light mean-contribution coefficients: the `per_light_cv` baseline [Hua §7.2]
//! (Vévoda et al. 2018).
//!
//! Per spatial cell and light `i`, the coefficient is the mean MIS-weighted next-event
//! contribution of light `i` over the cell's vertices; there is no solve. Hua shows these
//! are the optimal coefficients when the CV is formed from the light-sampling pdfs only and
//! fitted to the MIS-weighted NEE integral, so the baseline is never worse than plain NEE.
//!
//! # Contract
//! - Call [`MeanContributionAccumulator::add_vertex`] once per shading vertex that performs
//!   NEE in the cell, and [`MeanContributionAccumulator::add`] for the light it selected with
//!   that vertex's unbiased estimate of the light's MIS-weighted contribution,
//!   `w_nee · f / (c_i p_i)` (`c_i` selection probability, `p_i` the light's pdf).
//!   Averaging over all vertices (selected or not) gives an unbiased estimate of each
//!   light's mean contribution.
//! - [`mean_contribution_coefficients`] turns the sums into a [`CellCoefficients`] with one
//!   partition per light and no overlapping component; apply it with `λ_i = p_i` and the NEE
//!   density as `p` (see [`crate::solve`]).
//! - Merge is element-wise addition; the encoding (magic `CVML`, version 1) round-trips
//!   bit-exactly and decoding validates like [`crate::cell`].

use crate::cell::{CHANNELS, CellError, ColorMode, ComponentLayout, Reader};
use crate::solve::CellCoefficients;

/// Magic bytes of an encoded [`MeanContributionAccumulator`].
pub const MAGIC: [u8; 4] = *b"CVML";
/// Encoding version.
pub const VERSION: u16 = 1;

/// Sums of per-light NEE contributions of one cell (sparse over lights).
#[derive(Clone, Debug, PartialEq)]
pub struct MeanContributionAccumulator {
    lights: u32,
    vertices: u64,
    rejected: u64,
    ids: Vec<u32>,
    sums: Vec<[f64; CHANNELS]>,
}

impl MeanContributionAccumulator {
    /// Empty accumulator for `lights` lights (partitions).
    pub fn new(lights: u32) -> Self {
        Self {
            lights,
            vertices: 0,
            rejected: 0,
            ids: Vec::new(),
            sums: Vec::new(),
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

    /// Rejected contributions (non-finite or out-of-range light).
    pub fn rejected(&self) -> u64 {
        self.rejected
    }

    /// Counts one NEE vertex of the cell.
    pub fn add_vertex(&mut self) {
        self.vertices += 1;
    }

    /// Adds one vertex's contribution estimate for light `light`. Returns `false` (and
    /// counts a rejection) for a non-finite value or an out-of-range light.
    pub fn add(&mut self, light: u32, contribution: [f64; CHANNELS]) -> bool {
        if light >= self.lights || contribution.iter().any(|c| !c.is_finite()) {
            self.rejected += 1;
            return false;
        }
        let slot = match self.ids.binary_search(&light) {
            Ok(s) => s,
            Err(s) => {
                self.ids.insert(s, light);
                self.sums.insert(s, [0.0; CHANNELS]);
                s
            }
        };
        for (a, c) in self.sums[slot].iter_mut().zip(contribution) {
            *a += c;
        }
        true
    }

    /// Adds `other` into `self` (element-wise); fails if the light counts differ.
    pub fn merge(&mut self, other: &Self) -> Result<(), CellError> {
        if self.lights != other.lights {
            return Err(CellError::LayoutMismatch);
        }
        self.vertices += other.vertices;
        self.rejected += other.rejected;
        for (&id, s) in other.ids.iter().zip(&other.sums) {
            match self.ids.binary_search(&id) {
                Ok(k) => {
                    for (a, b) in self.sums[k].iter_mut().zip(s) {
                        *a += b;
                    }
                }
                Err(k) => {
                    self.ids.insert(k, id);
                    self.sums.insert(k, *s);
                }
            }
        }
        Ok(())
    }

    /// Encodes: magic, `u16` version, `u32` lights, `u64` vertices, `u64` rejected,
    /// `u32` entries, then per light `u32` index and 3 `f64` (little endian).
    pub fn encode(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(30 + self.ids.len() * 28);
        out.extend_from_slice(&MAGIC);
        out.extend_from_slice(&VERSION.to_le_bytes());
        out.extend_from_slice(&self.lights.to_le_bytes());
        out.extend_from_slice(&self.vertices.to_le_bytes());
        out.extend_from_slice(&self.rejected.to_le_bytes());
        out.extend_from_slice(&(self.ids.len() as u32).to_le_bytes());
        for (id, s) in self.ids.iter().zip(&self.sums) {
            out.extend_from_slice(&id.to_le_bytes());
            for v in s {
                out.extend_from_slice(&v.to_le_bytes());
            }
        }
        out
    }

    /// Decodes and validates; never panics.
    pub fn decode(bytes: &[u8]) -> Result<Self, CellError> {
        let mut r = Reader::new(bytes);
        if r.take(4)? != MAGIC {
            return Err(CellError::BadMagic);
        }
        let version = r.u16()?;
        if version != VERSION {
            return Err(CellError::UnsupportedVersion(version));
        }
        let mut acc = Self::new(r.u32()?);
        acc.vertices = r.u64()?;
        acc.rejected = r.u64()?;
        let n = u64::from(r.u32()?);
        if n > u64::from(acc.lights) || n * 28 > r.remaining() as u64 {
            return Err(CellError::BadEntryCount(n));
        }
        for _ in 0..n {
            let at = r.pos();
            let id = r.u32()?;
            if id >= acc.lights || acc.ids.last().is_some_and(|&p| id <= p) {
                return Err(CellError::BadPartition(at));
            }
            acc.ids.push(id);
            acc.sums
                .push([r.finite_f64()?, r.finite_f64()?, r.finite_f64()?]);
        }
        if !r.at_end() {
            return Err(CellError::Trailing(r.remaining()));
        }
        Ok(acc)
    }
}

/// Coefficients `α_i = Σ contributions_i / vertices` [Hua §7.2]; the plain estimator for a
/// cell without vertices.
pub fn mean_contribution_coefficients(acc: &MeanContributionAccumulator) -> CellCoefficients {
    let layout = ComponentLayout {
        partitions: acc.lights,
        overlapping: 0,
    };
    if acc.vertices == 0 {
        return CellCoefficients::plain(layout, ColorMode::Rgb);
    }
    let n = acc.vertices as f64;
    let parts: Vec<(u32, [f64; CHANNELS])> = acc
        .ids
        .iter()
        .zip(&acc.sums)
        .map(|(&id, s)| (id, s.map(|v| v / n)))
        .collect();
    CellCoefficients::from_values(layout, ColorMode::Rgb, &parts, &[])
        .unwrap_or_else(|| CellCoefficients::plain(layout, ColorMode::Rgb))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn coefficients_are_mean_contributions_per_vertex() {
        let mut acc = MeanContributionAccumulator::new(4);
        for i in 0..10 {
            acc.add_vertex();
            assert!(acc.add(i % 2, [1.0, 2.0, 3.0]));
        }
        assert!(!acc.add(9, [1.0; 3]));
        assert!(!acc.add(1, [f64::NAN; 3]));
        let c = mean_contribution_coefficients(&acc);
        assert_eq!(c.alpha_partition(0), [0.5, 1.0, 1.5]);
        assert_eq!(c.alpha_partition(3), [0.0; 3]);
        assert_eq!(c.alpha_sum(), [1.0, 2.0, 3.0]);
        assert_eq!(acc.rejected(), 2);
    }

    #[test]
    fn merge_and_encoding_round_trip() {
        let mut a = MeanContributionAccumulator::new(5);
        let mut b = MeanContributionAccumulator::new(5);
        a.add_vertex();
        a.add(3, [1.0, 0.0, 0.5]);
        b.add_vertex();
        b.add(1, [0.25, 0.0, 0.0]);
        b.add(3, [1.0, 1.0, 1.0]);
        a.merge(&b).unwrap();
        assert_eq!(a.vertices(), 2);
        let bytes = a.encode();
        assert_eq!(MeanContributionAccumulator::decode(&bytes).unwrap(), a);
        for n in 0..bytes.len() {
            assert!(MeanContributionAccumulator::decode(&bytes[..n]).is_err());
        }
        assert!(a.merge(&MeanContributionAccumulator::new(2)).is_err());
        assert!(
            mean_contribution_coefficients(&MeanContributionAccumulator::new(3)).alpha_sum()
                == [0.0; 3]
        );
    }
}
