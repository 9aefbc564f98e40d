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
//! [`SamplerKind::Independent`] takes every number from that hashed stream: independent
//! uniform numbers per sample and dimension, the baseline of Mitsuba's `independent` sampler
//! and of the papers' comparisons [Hua Table 1]. It is a job option (`sampler`), never the
//! default: on the bench scenes the scrambled Sobol points lower `path`'s error at equal
//! samples by 10–40× (`docs/bench/README.md`, "the baseline").
//!
//! Integrators address dimensions explicitly ([`Sampler::set_dimension`]) with a fixed
//! layout per path vertex, so that a technique that is skipped (e.g. no light sampling on a
//! delta BSDF) does not shift the numbers of the next vertex.
//!
//! All values lie in `[0, 1)`.

use std::sync::OnceLock;

pub use estimators::spec::SamplerKind;
use glam::Vec2;
use sobol_burley::parts::Int4;

/// Dimensions covered by the Sobol tables of `sobol_burley`.
const SOBOL_DIMENSIONS: u32 = sobol_burley::NUM_DIMENSION_SETS_4D * 4;
/// Sample indices covered by `sobol_burley` (2¹⁶).
const SOBOL_MAX_SAMPLES: u32 = 1 << 16;

/// Sobol direction vectors of two consecutive dimension sets, combined by nibbles of the
/// index: `[set][j][n]` is the XOR of the contributions (bit-reversed, as `sobol_burley` stores
/// them) to the 8 dimensions `4·set .. 4·set + 7` (zero beyond the last set) of the bits
/// `31 − 4j − b` (`b = 0..4`) of the bit-reversed sample index for which bit `3 − b` of `n` is
/// set. Only the 16 high bits of that index can be set (at most 2¹⁶ samples), so a point is the
/// XOR of four entries, one per nibble ([`nibbles`]).
type Directions = [[[Dir8; 16]; 4]];

/// Eight direction words, aligned for one 256-bit load.
#[derive(Clone, Copy, Debug)]
#[repr(C, align(32))]
struct Dir8([u32; 8]);

/// The direction table, read off `sobol_burley::parts::sobol_int4_rev` once: a Sobol point is
/// the XOR of the direction vectors of the index's set bits, so index `1 << (31 − k)` yields
/// vector `k`; the table holds the XOR of every subset of each group of four consecutive
/// vectors, so that [`Sampler`] needs four look-ups instead of sixteen masked XORs (128 KiB
/// for all 64 sets; a render touches the 2 KiB of each set its paths use).
fn directions() -> &'static Directions {
    static TABLE: OnceLock<Box<Directions>> = OnceLock::new();
    TABLE.get_or_init(|| {
        let sets = sobol_burley::NUM_DIMENSION_SETS_4D;
        let dir = |set: u32, k: usize| -> [u32; 4] {
            if set < sets {
                sobol_burley::parts::sobol_int4_rev(1u32 << (31 - k), set).into()
            } else {
                [0; 4]
            }
        };
        (0..sets)
            .map(|set| {
                let words: [[u32; 8]; 16] = std::array::from_fn(|k| {
                    let (a, b) = (dir(set, k), dir(set + 1, k));
                    [a[0], a[1], a[2], a[3], b[0], b[1], b[2], b[3]]
                });
                std::array::from_fn(|j| {
                    std::array::from_fn(|n| {
                        let mut acc = [0u32; 8];
                        for b in 0..4 {
                            if (n >> (3 - b)) & 1 != 0 {
                                for (x, w) in acc.iter_mut().zip(words[4 * j + b]) {
                                    *x ^= w;
                                }
                            }
                        }
                        Dir8(acc)
                    })
                })
            })
            .collect()
    })
}

/// `sobol_burley`'s per-lane scramble constants of a 4-dimension set.
const LANE_SCRAMBLE: [u32; 4] = [0x912f_69ba, 0x174f_18ab, 0x691e_72ca, 0xb40c_c1b8];

/// The four table indices of a bit-reversed sample index (see [`Directions`]): nibble `j` is
/// bits `28 − 4j ..= 31 − 4j`.
#[inline(always)]
fn nibbles(rev_index: u32) -> [u8; 4] {
    std::array::from_fn(|j| ((rev_index >> (28 - 4 * j)) & 0xf) as u8)
}

/// `Sampler::cached_set` when nothing is cached: far from every set (`set − NO_SET ≥ 2`).
const NO_SET: u32 = u32::MAX / 2;

/// The first set of the cached pair holding `set`: pairs are `(0, 1)` and then `(2j + 1,
/// 2j + 2)`, so that each path vertex (8 dimensions from `4 + 8k`, sets `2k + 1` and `2k + 2`)
/// needs exactly one evaluation.
#[inline(always)]
fn pair_start(set: u32) -> u32 {
    set.saturating_sub(1) | u32::from(set != 0)
}

/// A sampler positioned at one (pixel, sample index); cheap to create (no allocation).
///
/// Sobol points are computed eight dimensions (two sets) at a time and cached, so sequential
/// draws cost an eighth of an evaluation each (one AVX2 evaluation on x86-64-v3). The values are exactly `sobol_burley::sample_4d`'s
/// (checked in the tests); the part of it that depends only on (pixel, sample index) — the
/// Owen-shuffled sample index — is computed once per sampler instead of once per 4 dimensions.
#[derive(Clone, Copy, Debug)]
pub struct Sampler {
    /// The white-noise hash's state after the seed and the pixel
    /// (`mix64(mix64(seed ^ C) ^ pixel)`, see [`Self::hashed`]): computed once per sampler,
    /// it was two of the three `mix64` of every number drawn (10 % of an independent-sampler
    /// render's instructions).
    hash_base: u64,
    sample_index: u32,
    /// Whether this sample's numbers below [`SOBOL_DIMENSIONS`] are Sobol points (the kind
    /// is [`SamplerKind::Sobol`] and the index below [`SOBOL_MAX_SAMPLES`]).
    sobol: bool,
    /// `sobol_burley`'s bit-reversed, Owen-shuffled sample index for `scramble`, as the four
    /// direction-table indices of its high 16 bits ([`nibbles`]).
    index_nibbles: [u8; 4],
    /// `sobol_burley`'s per-dimension scramble base (`scramble · 0x9c8f2d3b`).
    scramble_mul: u32,
    dimension: u32,
    /// First dimension set held in `cache` (dimensions `4·set .. 4·set + 7`); [`NO_SET`] = none.
    cached_set: u32,
    cache: [f32; 8],
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
    /// in a job with seed `seed`, positioned at dimension 0 (the [`SamplerKind::Sobol`] kind).
    #[inline]
    pub fn new(seed: u64, pixel: u32, sample_index: u32) -> Self {
        Self::of_kind(SamplerKind::Sobol, seed, pixel, sample_index)
    }

    /// [`Self::new`] for a sampler of kind `kind`.
    #[inline]
    pub fn of_kind(kind: SamplerKind, seed: u64, pixel: u32, sample_index: u32) -> Self {
        let hash_base = mix64(mix64(seed ^ HASH_SEED_KEY) ^ u64::from(pixel));
        let sobol = kind == SamplerKind::Sobol && sample_index < SOBOL_MAX_SAMPLES;
        // The Sobol state is only read when `sobol` (the white-noise draws skip it).
        let (index_nibbles, scramble_mul, table) = if sobol {
            let scramble = pixel_scramble(seed, pixel);
            (
                nibbles(sobol_burley::parts::owen_scramble_rev(
                    sample_index.reverse_bits(),
                    sobol_burley::parts::hash(scramble ^ 0x79c6_8e4a),
                )),
                scramble.wrapping_mul(0x9c8f_2d3b),
                Table(directions()),
            )
        } else {
            ([0; 4], 0, Table(&[]))
        };
        Self {
            hash_base,
            sample_index,
            sobol,
            index_nibbles,
            scramble_mul,
            dimension: 0,
            cached_set: NO_SET,
            cache: [0.0; 8],
            table,
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
        if dim < SOBOL_DIMENSIONS && self.sobol {
            // Decorrelate dimensions of the same pixel: sobol_burley scrambles each dimension
            // with `hash(seed, dimension)`, so one seed per pixel suffices.
            self.sobol_8d(dim / 4)[(dim % 4) as usize]
        } else {
            self.hashed(dim)
        }
    }

    /// The next number in `[0, 1)` (equal to `get(dimension)`).
    #[inline(always)]
    pub fn next_1d(&mut self) -> f32 {
        let dim = self.dimension;
        self.dimension += 1;
        if dim < SOBOL_DIMENSIONS && self.sobol {
            if (dim / 4).wrapping_sub(self.cached_set) >= 2 {
                self.refill(dim / 4);
            }
            // `dim − 4·cached_set < 8` here; the mask keeps the index check away.
            self.cache[(dim.wrapping_sub(4 * self.cached_set) & 7) as usize]
        } else {
            self.hashed(dim)
        }
    }

    /// The next eight numbers (dimensions `d .. d + 8` from the current one `d`), equal to
    /// eight [`Self::next_1d`] draws; one evaluation when `d` starts a cached pair (`d = 4 +
    /// 8k`, a path vertex's block) without touching the cache.
    #[inline(always)]
    pub fn next_8d(&mut self) -> [f32; 8] {
        let dim = self.dimension;
        if dim % 8 == 4 && dim + 8 <= SOBOL_DIMENSIONS && self.sobol {
            self.dimension += 8;
            self.sobol_8d(dim / 4)
        } else {
            std::array::from_fn(|_| self.next_1d())
        }
    }

    /// Caches the pair of sets holding `set` (see [`pair_start`]).
    #[inline(never)]
    fn refill(&mut self, set: u32) {
        let first = pair_start(set);
        self.cache = self.sobol_8d(first);
        self.cached_set = first;
    }

    /// [`Self::next_2d`] for a sampler fresh from [`Self::new`] (the camera's pixel position):
    /// the first pair of sets evaluated and cached in line, without the out-of-line
    /// [`Self::refill`] (same numbers, same state afterwards); any other state takes
    /// `next_2d`.
    #[inline(always)]
    pub fn first_2d(&mut self) -> Vec2 {
        if self.dimension == 0 && self.cached_set == NO_SET && self.sobol {
            // What `next_1d` does at dimensions 0 and 1: `refill(0)` (pair 0), then two reads.
            self.cache = self.sobol_8d(pair_start(0));
            self.cached_set = pair_start(0);
            self.dimension = 2;
            Vec2::new(self.cache[0], self.cache[1])
        } else {
            self.next_2d()
        }
    }

    /// The next two numbers as a point of `[0, 1)²`.
    #[inline]
    pub fn next_2d(&mut self) -> Vec2 {
        let x = self.next_1d();
        let y = self.next_1d();
        Vec2::new(x, y)
    }

    /// Dimensions `4·set .. 4·set + 7` (sets `set` and `set + 1`) of this sample's
    /// Owen-scrambled Sobol point: the steps of `sobol_burley::sample_4d(sample_index, set,
    /// scramble)` after the index shuffle, for both sets at once. `set` must be below
    /// `NUM_DIMENSION_SETS_4D` (the second half is meaningless for the last set).
    #[inline]
    fn sobol_8d(&self, set: u32) -> [f32; 8] {
        let Some(dirs) = self.table.0.get(set as usize) else {
            return [0.0; 8];
        };
        #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
        {
            avx2::sobol_8d(dirs, self.index_nibbles, self.scramble_mul, set)
        }
        #[cfg(not(all(target_arch = "x86_64", target_feature = "avx2")))]
        {
            let mut out = [0.0; 8];
            for half in 0..2 {
                out[4 * half..4 * half + 4].copy_from_slice(&self.sobol_4d_portable(
                    dirs,
                    half,
                    set + half as u32,
                ));
            }
            out
        }
    }

    /// One half of [`Self::sobol_8d`] with `sobol_burley`'s 4-lane helpers.
    #[cfg_attr(all(target_arch = "x86_64", target_feature = "avx2"), allow(dead_code))]
    #[inline]
    fn sobol_4d_portable(&self, dirs: &[[Dir8; 16]; 4], half: usize, set: u32) -> [f32; 4] {
        use sobol_burley::parts::{hash_int4, owen_scramble_int4_rev};
        // `sobol_int4_rev(shuffled_rev_index, set)`: one table entry per index nibble.
        let mut sobol = Int4::from([0u32; 4]);
        for (group, &n) in dirs.iter().zip(&self.index_nibbles) {
            let d: [u32; 4] = std::array::from_fn(|i| group[usize::from(n)].0[4 * half + i]);
            sobol ^= Int4::from(d);
        }
        let base = self.scramble_mul ^ set;
        let scramble: Int4 = LANE_SCRAMBLE.map(|c| base ^ c).into();
        owen_scramble_int4_rev(sobol, hash_int4(scramble))
            .reverse_bits()
            .to_f32_norm()
    }

    /// White-noise fallback keyed by (seed, pixel, sample, dimension):
    /// `mix64(mix64(mix64(seed ^ C) ^ pixel) ^ (sample << 32 | dim))`, the first two steps
    /// precomputed ([`Self::hash_base`]).
    #[inline]
    fn hashed(&self, dim: u32) -> f32 {
        let h = mix64(self.hash_base ^ (u64::from(self.sample_index) << 32 | u64::from(dim)));
        // 24 high bits → exactly representable in f32, strictly below 1.
        (h >> 40) as f32 * (1.0 / (1u64 << 24) as f32)
    }
}

/// `sobol_burley`'s 4-lane steps (`sobol_int4_rev`, `hash_int4`, `owen_scramble_int4_rev`,
/// `reverse_bits`, `to_f32_norm`) on 8 lanes: the same integer operations, so the same bits.
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
mod avx2 {
    use std::arch::x86_64::*;

    use super::{Dir8, LANE_SCRAMBLE};

    #[inline(always)]
    pub(super) fn sobol_8d(
        dirs: &[[Dir8; 16]; 4],
        index_nibbles: [u8; 4],
        scramble_mul: u32,
        set: u32,
    ) -> [f32; 8] {
        // SAFETY: AVX2 is enabled for the whole build (cfg); `Dir8` is 8 u32s aligned to 32.
        unsafe {
            let splat = |v: u32| _mm256_set1_epi32(v as i32);
            // Sobol point: XOR of the direction words of the index's set bits, four at a time
            // (see `Directions`).
            let load = |j: usize| {
                _mm256_load_si256(
                    dirs[j][usize::from(index_nibbles[j] & 0xf)]
                        .0
                        .as_ptr()
                        .cast(),
                )
            };
            let sobol = _mm256_xor_si256(
                _mm256_xor_si256(load(0), load(1)),
                _mm256_xor_si256(load(2), load(3)),
            );
            // Per-lane scramble seeds: the lane's set base XOR the lane constant, and XOR
            // `hash_int4`'s first constant (folded into the lane constants).
            let c = LANE_SCRAMBLE.map(|c| (c ^ 0xe6fe_3beb) as i32);
            let (b0, b1) = (scramble_mul ^ set, scramble_mul ^ set.wrapping_add(1));
            let mut h = _mm256_xor_si256(
                _mm256_set_m128i(_mm_set1_epi32(b1 as i32), _mm_set1_epi32(b0 as i32)),
                _mm256_setr_epi32(c[0], c[1], c[2], c[3], c[0], c[1], c[2], c[3]),
            );
            // hash_int4 (after its first XOR)
            h = _mm256_xor_si256(h, _mm256_srli_epi32::<16>(h));
            h = _mm256_mullo_epi32(h, splat(0x7feb_352d));
            h = _mm256_xor_si256(h, _mm256_srli_epi32::<15>(h));
            h = _mm256_mullo_epi32(h, splat(0x846c_a68b));
            h = _mm256_xor_si256(h, _mm256_srli_epi32::<16>(h));
            // owen_scramble_int4_rev
            let mut n = sobol;
            n = _mm256_xor_si256(n, _mm256_mullo_epi32(n, splat(0x3d20_adea)));
            n = _mm256_add_epi32(n, h);
            n = _mm256_mullo_epi32(n, _mm256_or_si256(_mm256_srli_epi32::<16>(h), splat(1)));
            n = _mm256_xor_si256(n, _mm256_mullo_epi32(n, splat(0x0552_6c56)));
            n = _mm256_xor_si256(n, _mm256_mullo_epi32(n, splat(0x53a2_2864)));
            // reverse_bits: bytes reversed per lane by a shuffle, then the bits of each byte by
            // two nibble look-ups.
            let byte_rev = _mm256_setr_epi8(
                3, 2, 1, 0, 7, 6, 5, 4, 11, 10, 9, 8, 15, 14, 13, 12, 3, 2, 1, 0, 7, 6, 5, 4, 11,
                10, 9, 8, 15, 14, 13, 12,
            );
            let nibble_rev = _mm256_setr_epi8(
                0x0, 0x8, 0x4, 0xc, 0x2, 0xa, 0x6, 0xe, 0x1, 0x9, 0x5, 0xd, 0x3, 0xb, 0x7, 0xf,
                0x0, 0x8, 0x4, 0xc, 0x2, 0xa, 0x6, 0xe, 0x1, 0x9, 0x5, 0xd, 0x3, 0xb, 0x7, 0xf,
            );
            let low4 = _mm256_set1_epi8(0x0f);
            n = _mm256_shuffle_epi8(n, byte_rev);
            let lo = _mm256_shuffle_epi8(nibble_rev, _mm256_and_si256(n, low4));
            let hi = _mm256_shuffle_epi8(
                nibble_rev,
                _mm256_and_si256(_mm256_srli_epi16::<4>(n), low4),
            );
            n = _mm256_or_si256(_mm256_slli_epi16::<4>(lo), hi);
            // to_f32_norm
            let f = _mm256_sub_ps(
                _mm256_castsi256_ps(_mm256_or_si256(
                    _mm256_srli_epi32::<9>(n),
                    splat(0x3f80_0000),
                )),
                _mm256_set1_ps(1.0),
            );
            let mut out = [0.0f32; 8];
            _mm256_storeu_ps(out.as_mut_ptr(), f);
            out
        }
    }
}

/// Key of the white-noise hash's first step ([`Sampler::hashed`]).
const HASH_SEED_KEY: u64 = 0xd1b5_4a32_d192_ed03;

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
    fn pair_cache_follows_any_access_order() {
        assert_eq!(
            (0..8).map(pair_start).collect::<Vec<_>>(),
            [0, 1, 1, 3, 3, 5, 5, 7]
        );
        let b = Sampler::new(3, 77, 5);
        let mut a = b;
        // Forward, backward and jumping draws all equal random access.
        for d in (0..40)
            .chain((0..40).rev())
            .chain([3, 250, 4, 251, 255, 0, 9])
        {
            a.set_dimension(d);
            assert_eq!(a.next_1d().to_bits(), b.get(d).to_bits(), "dim {d}");
        }
    }

    #[test]
    fn eight_at_once_equal_single_draws() {
        let b = Sampler::new(11, 5, 9);
        for start in [0, 3, 4, 12, 20, 252, 256, 300] {
            let mut a = b;
            a.set_dimension(start);
            let got = a.next_8d();
            assert_eq!(a.dimension(), start + 8);
            for (k, v) in got.iter().enumerate() {
                assert_eq!(
                    v.to_bits(),
                    b.get(start + k as u32).to_bits(),
                    "dim {start}+{k}"
                );
            }
        }
    }

    #[test]
    fn first_2d_equals_next_2d_and_leaves_the_same_state() {
        for sample in [0u32, 9, 65_535, 65_536, 70_000] {
            let fresh = Sampler::new(11, 5, sample);
            let (mut a, mut b) = (fresh, fresh);
            let (x, y) = (a.first_2d(), b.next_2d());
            assert_eq!(
                (x.x.to_bits(), x.y.to_bits()),
                (y.x.to_bits(), y.y.to_bits())
            );
            // The following draws (cache and cursor) agree too.
            for _ in 0..12 {
                assert_eq!(
                    a.next_1d().to_bits(),
                    b.next_1d().to_bits(),
                    "sample {sample}"
                );
            }
        }
        // Not fresh: the plain path.
        let mut a = Sampler::new(3, 1, 2);
        let mut b = a;
        a.set_dimension(5);
        b.set_dimension(5);
        let (x, y) = (a.first_2d(), b.next_2d());
        assert_eq!(
            (x.x.to_bits(), x.y.to_bits()),
            (y.x.to_bits(), y.y.to_bits())
        );
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

    /// The precomputed hash state gives the stream's defining formula, three `mix64` steps
    /// keyed by seed, pixel and (sample, dimension), bit for bit (renders and references made
    /// before the precomputation keep their bits).
    #[test]
    fn hashed_numbers_are_the_three_step_hash_of_seed_pixel_sample_and_dimension() {
        for (seed, pixel, sample) in [(0u64, 0u32, 0u32), (20, 4_321, 17), (u64::MAX, 1, 70_000)] {
            for kind in [SamplerKind::Sobol, SamplerKind::Independent] {
                let s = Sampler::of_kind(kind, seed, pixel, sample);
                for dim in [0u32, 1, 7, 255, 256, 1_000] {
                    let mut h = mix64(seed ^ 0xd1b5_4a32_d192_ed03);
                    h = mix64(h ^ u64::from(pixel));
                    h = mix64(h ^ (u64::from(sample) << 32 | u64::from(dim)));
                    let want = (h >> 40) as f32 * (1.0 / (1u64 << 24) as f32);
                    assert_eq!(
                        s.hashed(dim).to_bits(),
                        want.to_bits(),
                        "{seed} {pixel} {sample} {dim}"
                    );
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

    #[test]
    fn the_independent_kind_draws_every_number_from_the_hashed_stream() {
        for sample in [0u32, 9, 70_000] {
            let b = Sampler::of_kind(SamplerKind::Independent, 5, 33, sample);
            let (mut a, mut c, mut e) = (b, b, b);
            let first = c.first_2d();
            assert_eq!(first.x.to_bits(), b.hashed(0).to_bits());
            assert_eq!(first.y.to_bits(), b.hashed(1).to_bits());
            e.set_dimension(4);
            let eight = e.next_8d();
            for d in 0..300 {
                assert_eq!(b.get(d).to_bits(), b.hashed(d).to_bits(), "dim {d}");
                assert_eq!(a.next_1d().to_bits(), b.hashed(d).to_bits(), "dim {d}");
            }
            for (k, v) in eight.iter().enumerate() {
                assert_eq!(v.to_bits(), b.hashed(4 + k as u32).to_bits());
            }
        }
        // Past the Sobol range both kinds are the same stream.
        let (s, i) = (
            Sampler::new(5, 33, 70_000),
            Sampler::of_kind(SamplerKind::Independent, 5, 33, 70_000),
        );
        assert_eq!(s.get(3).to_bits(), i.get(3).to_bits());
    }

    /// The kinds differ in what matters: a pixel's mean over `n` samples of one dimension
    /// has the spread `1/√(12n)` of independent uniforms with [`SamplerKind::Independent`],
    /// and far less with the stratified Sobol points. Over 400 pixels the RMS deviation of
    /// the independent means has a relative standard error of `√(1/(2·400))` ≈ 3.5 %; the
    /// bound is 5 of those.
    #[test]
    fn independent_pixel_means_spread_as_white_noise_and_sobol_ones_do_not() {
        let n = 64u32;
        let rms = |kind: SamplerKind, dim: u32| {
            let sq: f64 = (0..400u32)
                .map(|pixel| {
                    let mean = (0..n)
                        .map(|i| f64::from(Sampler::of_kind(kind, 3, pixel, i).get(dim)))
                        .sum::<f64>()
                        / f64::from(n);
                    (mean - 0.5).powi(2)
                })
                .sum();
            (sq / 400.0).sqrt()
        };
        let white = 1.0 / (12.0 * f64::from(n)).sqrt();
        for dim in [0, 1, 17, 100] {
            let independent = rms(SamplerKind::Independent, dim);
            assert!(
                (independent / white - 1.0).abs() < 5.0 * (1.0f64 / 800.0).sqrt(),
                "dim {dim}: {independent} vs {white}"
            );
            let sobol = rms(SamplerKind::Sobol, dim);
            assert!(sobol < 0.1 * white, "dim {dim}: Sobol {sobol} vs {white}");
        }
    }
}
