//! Deterministic sampler: every number is a pure function of
//! `(job seed, pixel index, sample index, dimension)`.
//!
//! Nothing depends on tile size, thread or worker, so the same job and seed give a
//! bitwise-identical image however the work is split (DESIGN §3 "Sampler").
//!
//! Numbers come from an Owen-scrambled Sobol sequence (`sobol_burley`, Burley 2020) seeded per
//! pixel by a hash of `(seed, pixel)`: sample index `i` of pixel `p` is point `i` of that
//! pixel's scrambled sequence. Beyond what the sequence supports (256 dimensions, 2¹⁶ samples
//! per pixel) the sampler falls back to a hashed stream keyed by
//! `(seed, pixel, sample, dimension)` — still deterministic, just white noise.
//!
//! Integrators address dimensions explicitly ([`Sampler::set_dimension`]) with a fixed
//! layout per path vertex, so that a technique that is skipped (e.g. no light sampling on a
//! delta BSDF) does not shift the numbers of the next vertex.
//!
//! All values lie in `[0, 1)`.

use std::sync::OnceLock;

use glam::Vec2;
use sobol_burley::parts::Int4;

/// Dimensions covered by the Sobol tables of `sobol_burley`.
const SOBOL_DIMENSIONS: u32 = sobol_burley::NUM_DIMENSION_SETS_4D * 4;
/// Sample indices covered by `sobol_burley` (2¹⁶).
const SOBOL_MAX_SAMPLES: u32 = 1 << 16;

/// Sobol direction vectors: `[set][k]` is the contribution (bit-reversed, as `sobol_burley`
/// stores it) of bit `31 − k` of the bit-reversed sample index to the set's 4 dimensions.
type Directions = [[[u32; 4]; 16]];

/// The direction table, read off `sobol_burley::parts::sobol_int4_rev` once: a Sobol point is
/// the XOR of the direction vectors of the index's set bits, so index `1 << (31 − k)` yields
/// vector `k`. Lets [`Sampler`] XOR all 16 with masks (no data-dependent loop exit).
fn directions() -> &'static Directions {
    static TABLE: OnceLock<Box<Directions>> = OnceLock::new();
    TABLE.get_or_init(|| {
        (0..sobol_burley::NUM_DIMENSION_SETS_4D)
            .map(|set| {
                std::array::from_fn(|k| {
                    sobol_burley::parts::sobol_int4_rev(1u32 << (31 - k), set).into()
                })
            })
            .collect()
    })
}

/// A sampler positioned at one (pixel, sample index); cheap to create (no allocation).
///
/// Sobol points are computed four dimensions at a time and cached, so sequential draws cost a
/// quarter of a point evaluation each. The values are exactly `sobol_burley::sample_4d`'s
/// (checked in the tests); the part of it that depends only on (pixel, sample index) — the
/// Owen-shuffled sample index — is computed once per sampler instead of once per 4 dimensions.
#[derive(Clone, Copy, Debug)]
pub struct Sampler {
    seed: u64,
    pixel: u32,
    sample_index: u32,
    /// `sobol_burley`'s bit-reversed, Owen-shuffled sample index for `scramble`.
    shuffled_rev_index: u32,
    /// `sobol_burley`'s per-dimension scramble base (`scramble · 0x9c8f2d3b`).
    scramble_mul: u32,
    dimension: u32,
    /// Dimension set (dimensions `4·set .. 4·set + 3`) held in `cache`; `u32::MAX` = none.
    cached_set: u32,
    cache: [f32; 4],
    table: Table,
}

/// The shared direction table, debug-printed by name only.
#[derive(Clone, Copy)]
struct Table(&'static Directions);

impl std::fmt::Debug for Table {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("<sobol directions>")
    }
}

impl Sampler {
    /// The sampler of sample `sample_index` of pixel `pixel` (row-major index `y·width + x`)
    /// in a job with seed `seed`, positioned at dimension 0.
    #[inline]
    pub fn new(seed: u64, pixel: u32, sample_index: u32) -> Self {
        let scramble = pixel_scramble(seed, pixel);
        Self {
            seed,
            pixel,
            sample_index,
            shuffled_rev_index: sobol_burley::parts::owen_scramble_rev(
                sample_index.reverse_bits(),
                sobol_burley::parts::hash(scramble ^ 0x79c6_8e4a),
            ),
            scramble_mul: scramble.wrapping_mul(0x9c8f_2d3b),
            dimension: 0,
            cached_set: u32::MAX,
            cache: [0.0; 4],
            table: Table(directions()),
        }
    }

    /// The current dimension (the next number drawn uses it).
    #[inline]
    pub fn dimension(&self) -> u32 {
        self.dimension
    }

    /// Jumps to dimension `dim` (integrators use a fixed dimension layout per vertex).
    #[inline]
    pub fn set_dimension(&mut self, dim: u32) {
        self.dimension = dim;
    }

    /// The number at an explicit dimension, without moving the cursor.
    #[inline]
    pub fn get(&self, dim: u32) -> f32 {
        if dim < SOBOL_DIMENSIONS && self.sample_index < SOBOL_MAX_SAMPLES {
            // Decorrelate dimensions of the same pixel: sobol_burley scrambles each dimension
            // with `hash(seed, dimension)`, so one seed per pixel suffices.
            self.sobol_4d(dim / 4)[(dim % 4) as usize]
        } else {
            self.hashed(dim)
        }
    }

    /// The next number in `[0, 1)` (equal to `get(dimension)`).
    #[inline]
    pub fn next_1d(&mut self) -> f32 {
        let dim = self.dimension;
        self.dimension += 1;
        if dim < SOBOL_DIMENSIONS && self.sample_index < SOBOL_MAX_SAMPLES {
            let set = dim / 4;
            if set != self.cached_set {
                self.cache = self.sobol_4d(set);
                self.cached_set = set;
            }
            self.cache[(dim % 4) as usize]
        } else {
            self.hashed(dim)
        }
    }

    /// The next two numbers as a point of `[0, 1)²`.
    #[inline]
    pub fn next_2d(&mut self) -> Vec2 {
        let x = self.next_1d();
        let y = self.next_1d();
        Vec2::new(x, y)
    }

    /// Dimensions `4·set .. 4·set + 3` of this sample's Owen-scrambled Sobol point: the steps
    /// of `sobol_burley::sample_4d(sample_index, set, scramble)` after the index shuffle.
    #[inline]
    fn sobol_4d(&self, set: u32) -> [f32; 4] {
        use sobol_burley::parts::{hash_int4, owen_scramble_int4_rev};
        // `sobol_int4_rev(shuffled_rev_index, set)`, branch-free.
        let r = self.shuffled_rev_index;
        let mut sobol = Int4::from([0u32; 4]);
        if let Some(dirs) = self.table.0.get(set as usize) {
            for (k, d) in dirs.iter().enumerate() {
                let mask = 0u32.wrapping_sub((r >> (31 - k)) & 1);
                sobol ^= Int4::from(*d) & Int4::from([mask; 4]);
            }
        }
        let base = self.scramble_mul ^ set;
        let scramble: Int4 = [
            base ^ 0x912f_69ba,
            base ^ 0x174f_18ab,
            base ^ 0x691e_72ca,
            base ^ 0xb40c_c1b8,
        ]
        .into();
        owen_scramble_int4_rev(sobol, hash_int4(scramble))
            .reverse_bits()
            .to_f32_norm()
    }

    /// White-noise fallback keyed by (seed, pixel, sample, dimension).
    fn hashed(&self, dim: u32) -> f32 {
        let mut h = mix64(self.seed ^ 0xd1b5_4a32_d192_ed03);
        h = mix64(h ^ u64::from(self.pixel));
        h = mix64(h ^ (u64::from(self.sample_index) << 32 | u64::from(dim)));
        // 24 high bits → exactly representable in f32, strictly below 1.
        (h >> 40) as f32 * (1.0 / (1u64 << 24) as f32)
    }
}

/// Per-pixel scramble seed of the Sobol sequence (sobol_burley's `seed`).
#[inline]
fn pixel_scramble(seed: u64, pixel: u32) -> u32 {
    (mix64(seed ^ mix64(u64::from(pixel).wrapping_add(0x9e37_79b9_7f4a_7c15))) >> 32) as u32
}

/// A 64-bit finaliser (splitmix64 / Stafford variant 13): a bijective, well-mixing hash.
#[inline]
pub fn mix64(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn values_lie_in_unit_interval_including_fallback() {
        for &(s, d) in &[(0u32, 0u32), (5, 3), (70_000, 2), (3, 300), (65_535, 255)] {
            let smp = Sampler::new(42, 17, s);
            let v = smp.get(d);
            assert!((0.0..1.0).contains(&v), "{v} at sample {s} dim {d}");
        }
    }

    #[test]
    fn cached_sequential_draws_equal_random_access() {
        let mut a = Sampler::new(9, 4, 21);
        let b = Sampler::new(9, 4, 21);
        a.set_dimension(250);
        for d in 250..262 {
            assert_eq!(a.next_1d().to_bits(), b.get(d).to_bits(), "dim {d}");
        }
        a.set_dimension(1);
        assert_eq!(a.next_1d().to_bits(), b.get(1).to_bits());
    }

    #[test]
    fn cached_index_shuffle_gives_sobol_burley_values() {
        for (seed, pixel, sample) in [(0u64, 0u32, 0u32), (7, 123, 45), (99, 65_535, 65_535)] {
            let s = Sampler::new(seed, pixel, sample);
            for set in [0, 1, 7, SOBOL_DIMENSIONS / 4 - 1] {
                let want = sobol_burley::sample_4d(sample, set, pixel_scramble(seed, pixel));
                for k in 0..4 {
                    assert_eq!(s.get(4 * set + k).to_bits(), want[k as usize].to_bits());
                }
            }
        }
    }

    #[test]
    fn fallback_is_deterministic_and_distinct_per_dimension() {
        let a = Sampler::new(1, 2, 3);
        assert_eq!(
            a.get(400).to_bits(),
            Sampler::new(1, 2, 3).get(400).to_bits()
        );
        assert_ne!(a.get(400), a.get(401));
    }
}
