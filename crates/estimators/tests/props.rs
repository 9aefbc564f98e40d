//! Property tests: merge algebra, encoding round trips, decoding arbitrary bytes, solve
//! stability.

use estimators::cell::{
    CellAccumulator, CellError, ColorMode, ComponentLayout, CvSample, Technique,
};
use estimators::solve::{SolvePolicy, solve, solve_dense};
use proptest::prelude::*;

#[derive(Clone, Debug)]
struct Smp {
    w: f64,
    v: [f64; 3],
    pdf: f64,
    part: Option<(u32, f64)>,
    lam: Vec<f64>,
    light: bool,
}

const P: u32 = 7;
const K: u32 = 2;

fn layout() -> ComponentLayout {
    ComponentLayout::new(P, K).unwrap()
}

fn smp() -> impl Strategy<Value = Smp> {
    smp_in(P)
}

/// A sample whose partition (if any) is below `parts`.
fn smp_in(parts: u32) -> impl Strategy<Value = Smp> {
    (
        0.0f64..10.0,
        prop::array::uniform3(-100.0f64..100.0),
        0.01f64..50.0,
        prop::option::of((0..parts, 0.0f64..20.0)),
        prop::collection::vec(0.0f64..20.0, K as usize),
        any::<bool>(),
    )
        .prop_map(|(w, v, pdf, part, lam, light)| Smp {
            w,
            v,
            pdf,
            part,
            lam,
            light,
        })
}

fn build(samples: &[Smp], color: ColorMode) -> CellAccumulator {
    build_in(samples, P, K, color)
}

fn color() -> impl Strategy<Value = ColorMode> {
    prop_oneof![Just(ColorMode::Rgb), Just(ColorMode::Mono)]
}

fn close(a: &[u8], b: &[u8]) -> bool {
    // Compare two encodings field by field: integers exactly, floats to 1e-12 relative.
    let (x, y) = (
        CellAccumulator::decode(a).unwrap(),
        CellAccumulator::decode(b).unwrap(),
    );
    if x.samples() != y.samples() || x.sampled_partitions() != y.sampled_partitions() {
        return false;
    }
    let near = |p: f64, q: f64| (p - q).abs() <= 1e-12 * (1.0 + p.abs().max(q.abs()));
    let mut ok = near(x.weight_sum(), y.weight_sum());
    for i in 0..K as usize {
        for j in 0..K as usize {
            ok &= near(x.dense(i, j), y.dense(i, j));
        }
        for (p, q) in x.b_overlapping(i).iter().zip(y.b_overlapping(i)) {
            ok &= near(*p, *q);
        }
    }
    for (p, q) in x.partitions().zip(y.partitions()) {
        ok &= p.id == q.id && p.count == q.count && near(p.diag, q.diag);
        for (a, b) in p.cross.iter().chain(p.b).zip(q.cross.iter().chain(q.b)) {
            ok &= near(*a, *b);
        }
    }
    ok
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(128))]

    #[test]
    fn merge_is_commutative_bitwise(a in prop::collection::vec(smp(), 0..40), b in prop::collection::vec(smp(), 0..40), c in color()) {
        let (x, y) = (build(&a, c), build(&b, c));
        let mut xy = x.clone();
        xy.merge(&y).unwrap();
        let mut yx = y.clone();
        yx.merge(&x).unwrap();
        prop_assert_eq!(xy.encode(), yx.encode());
    }

    #[test]
    fn merge_is_associative_up_to_rounding(a in prop::collection::vec(smp(), 0..30), b in prop::collection::vec(smp(), 0..30), d in prop::collection::vec(smp(), 0..30), c in color()) {
        let (x, y, z) = (build(&a, c), build(&b, c), build(&d, c));
        let mut left = x.clone();
        left.merge(&y).unwrap();
        left.merge(&z).unwrap();
        let mut yz = y.clone();
        yz.merge(&z).unwrap();
        let mut right = x.clone();
        right.merge(&yz).unwrap();
        prop_assert!(close(&left.encode(), &right.encode()));
        // A merge of per-sample accumulators equals accumulating the samples directly.
        let mut all = a.clone();
        all.extend(b.iter().cloned());
        all.extend(d.iter().cloned());
        prop_assert!(close(&left.encode(), &build(&all, c).encode()));
    }

    #[test]
    fn canonical_merge_is_reproducible(parts in prop::collection::vec(prop::collection::vec(smp(), 0..10), 1..8), c in color()) {
        let accs: Vec<_> = parts.iter().map(|p| build(p, c)).collect();
        let once = CellAccumulator::merge_all(layout(), c, &accs).unwrap().encode();
        // Re-decoding (as after the wire) and merging again in the same order: bitwise equal.
        let wire: Vec<_> = accs.iter().map(|a| CellAccumulator::decode(&a.encode()).unwrap()).collect();
        let twice = CellAccumulator::merge_all(layout(), c, &wire).unwrap().encode();
        prop_assert_eq!(once, twice);
    }

    #[test]
    fn encoding_round_trips_bit_exactly(a in prop::collection::vec(smp(), 0..50), c in color()) {
        let x = build(&a, c);
        let bytes = x.encode();
        prop_assert_eq!(bytes.len(), x.encoded_len());
        let y = CellAccumulator::decode(&bytes).unwrap();
        prop_assert_eq!(y.encode(), bytes);
        prop_assert_eq!(x, y);
    }

    #[test]
    fn decode_never_panics_on_arbitrary_bytes(bytes in prop::collection::vec(any::<u8>(), 0..400)) {
        let _ = CellAccumulator::decode(&bytes);
        let mut with_magic = b"CVAC\x01\x00".to_vec();
        with_magic.extend_from_slice(&bytes);
        let _ = CellAccumulator::decode(&with_magic);
    }

    #[test]
    fn decode_rejects_corrupted_encodings_without_panicking(a in prop::collection::vec(smp(), 1..20), flips in prop::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 1..4)) {
        let mut bytes = build(&a, ColorMode::Rgb).encode();
        for (i, v) in flips {
            let at = i.index(bytes.len());
            bytes[at] ^= v | 1;
        }
        if let Ok(acc) = CellAccumulator::decode(&bytes) {
            // Anything accepted is structurally valid and re-encodes to the same bytes.
            prop_assert_eq!(acc.encode(), bytes);
        }
    }

    #[test]
    fn solve_is_stable_and_matches_dense(a in prop::collection::vec(smp(), 0..200), c in color(), ridge in prop_oneof![Just(0.0), Just(1e-9), Just(1e-6), Just(1e-2)]) {
        let acc = build(&a, c);
        let policy = SolvePolicy { ridge, ..SolvePolicy::default() };
        let s = solve(&acc, &policy);
        let d = solve_dense(&acc, &policy);
        prop_assert!(s.alpha_sum().iter().all(|x| x.is_finite()));
        prop_assert!(d.alpha_sum().iter().all(|x| x.is_finite()));
        if ridge >= 1e-6 && !s.is_fallback() && !d.is_fallback() {
            for id in 0..P {
                let (x, y) = (s.alpha_partition(id), d.alpha_partition(id));
                for ch in 0..3 {
                    let tol = 1e-6 * (1.0 + x[ch].abs().max(y[ch].abs())) / ridge.min(1.0);
                    prop_assert!((x[ch] - y[ch]).abs() <= tol, "{} vs {}", x[ch], y[ch]);
                }
            }
        }
    }

    /// `summed_term` of an accumulator is its samples' CV terms summed with their weights,
    /// for coefficients fitted on other samples (the split-half check of `optimal_mis`).
    #[test]
    fn summed_term_is_the_weighted_sum_of_the_samples_terms(a in prop::collection::vec(smp(), 1..60), b in prop::collection::vec(smp(), 40..120), c in color()) {
        let acc = build(&a, c);
        let co = solve(&build(&b, c), &SolvePolicy { ridge: 1e-3, ..SolvePolicy::default() });
        let mut want = [0.0f64; 3];
        let mut scale = 0.0f64;
        for s in &a {
            let t = co.cv_term(&CvSample { pdf: s.pdf, partition: s.part, overlapping: &s.lam });
            for ch in 0..3 {
                want[ch] += s.w * t[ch];
                scale = scale.max((s.w * t[ch]).abs());
            }
        }
        let got = co.summed_term(&acc);
        for ch in 0..3 {
            prop_assert!((got[ch] - want[ch]).abs() <= 1e-9 * (1.0 + scale * a.len() as f64), "{got:?} vs {want:?}");
        }
    }
}

#[test]
fn every_truncation_is_a_typed_error() {
    let mut acc = CellAccumulator::new(layout(), ColorMode::Rgb);
    for i in 0..5u32 {
        acc.add(
            1.0,
            [1.0, 2.0, 3.0],
            &CvSample {
                pdf: 1.0,
                partition: Some((i, 1.0)),
                overlapping: &[0.5, 0.25],
            },
        )
        .unwrap();
    }
    let bytes = acc.encode();
    for n in 0..bytes.len() {
        assert!(
            CellAccumulator::decode(&bytes[..n]).is_err(),
            "prefix of {n} bytes accepted"
        );
    }
    let mut long = bytes.clone();
    long.push(0);
    assert_eq!(CellAccumulator::decode(&long), Err(CellError::Trailing(1)));
    let mut bad_version = bytes.clone();
    bad_version[4] = 9;
    assert_eq!(
        CellAccumulator::decode(&bad_version),
        Err(CellError::UnsupportedVersion(9))
    );
    assert_eq!(CellAccumulator::decode(b"nope"), Err(CellError::BadMagic));
    // A NaN smuggled into the payload is refused.
    let mut nan = bytes.clone();
    let at = nan.len() - 8;
    nan[at..].copy_from_slice(&f64::NAN.to_le_bytes());
    assert!(matches!(
        CellAccumulator::decode(&nan),
        Err(CellError::InvalidValue(_))
    ));
    // Merging different layouts is refused and leaves the target untouched.
    let other = CellAccumulator::new(ComponentLayout::new(3, 2).unwrap(), ColorMode::Rgb);
    let before = acc.encode();
    assert_eq!(acc.merge(&other), Err(CellError::LayoutMismatch));
    assert_eq!(acc.encode(), before);
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    #[test]
    fn coefficients_round_trip_and_decode_never_panics(a in prop::collection::vec(smp(), 0..100), c in color(), junk in prop::collection::vec(any::<u8>(), 0..200)) {
        let coeffs = solve(&build(&a, c), &SolvePolicy::default());
        let bytes = coeffs.encode();
        let back = estimators::solve::CellCoefficients::decode(&bytes).unwrap();
        prop_assert_eq!(back.encode(), bytes.clone());
        prop_assert_eq!(back.alpha_sum(), coeffs.alpha_sum());
        for n in 0..bytes.len() {
            prop_assert!(estimators::solve::CellCoefficients::decode(&bytes[..n]).is_err());
        }
        let _ = estimators::solve::CellCoefficients::decode(&junk);
        let mut with_magic = b"CVCO\x01\x00".to_vec();
        with_magic.extend_from_slice(&junk);
        let _ = estimators::solve::CellCoefficients::decode(&with_magic);
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    #[test]
    fn table_decode_never_panics(junk in prop::collection::vec(any::<u8>(), 0..300)) {
        use estimators::table::decode_table;
        let _ = decode_table::<CellAccumulator>(&junk);
        let mut with_header = b"CVCT\x01\x00\x01\x00".to_vec();
        with_header.extend_from_slice(&junk);
        let _ = decode_table::<CellAccumulator>(&with_header);
        let mut coeff_header = b"CVCT\x01\x00\x03\x00".to_vec();
        coeff_header.extend_from_slice(&junk);
        let _ = decode_table::<estimators::solve::CellCoefficients>(&coeff_header);
    }
}

/// The samples of `samples` (their partitions all below [`P`]) added to an accumulator of `p`
/// partitions and `k ≤ K` overlapping components (each sample's first `k` `λ`s).
fn build_in(samples: &[Smp], p: u32, k: u32, color: ColorMode) -> CellAccumulator {
    let mut acc = CellAccumulator::new(ComponentLayout::new(p, k).unwrap(), color);
    for s in samples {
        let technique = if s.light {
            Technique::Light
        } else {
            Technique::Bsdf
        };
        let sample = CvSample {
            pdf: s.pdf,
            partition: s.part,
            overlapping: &s.lam[..k as usize],
        };
        acc.add_from(technique, s.w, s.v, &sample).unwrap();
    }
    acc
}

/// Every sum of `acc` but the layout, bit for bit (the partitions by index).
fn sums(acc: &CellAccumulator) -> Vec<u64> {
    let k = acc.layout().overlapping as usize;
    let mut out = vec![acc.samples(), acc.weight_sum().to_bits()];
    for ch in 0..acc.color().channels() {
        let (s, s2) = acc.value_moments(ch);
        out.extend([s.to_bits(), s2.to_bits()]);
    }
    for i in 0..k {
        for j in 0..k {
            out.push(acc.dense(i, j).to_bits());
        }
        out.extend(acc.b_overlapping(i).iter().map(|v| v.to_bits()));
        out.push(acc.g_overlapping(i).to_bits());
    }
    let (w, y, g) = acc.technique_sums();
    out.push(w.to_bits());
    out.extend(y.iter().chain(g).map(|v| v.to_bits()));
    for m in acc.partitions() {
        out.extend([u64::from(m.id), m.count, m.diag.to_bits(), m.g.to_bits()]);
        out.push(m.g_light.to_bits());
        out.extend(m.cross.iter().chain(m.b).map(|v| v.to_bits()));
    }
    out
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    /// The accumulator's four ways of storing partitions (up to `SLOT_IS_PARTITION_MAX`
    /// partitions: slot = partition for a few, else appended slots found through a byte map;
    /// above it appended slots found through a direct map up to `DIRECT_MAP_MAX`, by binary
    /// search above) and its two of storing the overlapping sums (inline for small `K`, else
    /// allocated) keep the same sums, bit for bit, through accumulation, merges and the wire;
    /// [`CellAccumulator::prefetch_partition`] works on each.
    #[test]
    fn every_storage_layout_keeps_the_same_sums(a in prop::collection::vec(smp(), 0..40), b in prop::collection::vec(smp(), 0..40), c in color(), k in 1..=K) {
        use estimators::cell::{DIRECT_MAP_MAX, SLOT_IS_PARTITION_MAX};
        same_sums_in_every_layout(&a, &b, c, k, &[P, SLOT_IS_PARTITION_MAX, SLOT_IS_PARTITION_MAX + 1, DIRECT_MAP_MAX + 1])?;
    }

    /// The same with samples spread over all `SLOT_IS_PARTITION_MAX` partitions, met in
    /// random order: the appended slots outgrow their first allocation, and the byte map's
    /// slots differ from the partitions.
    #[test]
    fn many_partitions_keep_the_same_sums_in_every_layout(a in prop::collection::vec(smp_in(estimators::cell::SLOT_IS_PARTITION_MAX), 0..200), b in prop::collection::vec(smp_in(estimators::cell::SLOT_IS_PARTITION_MAX), 0..200), c in color()) {
        use estimators::cell::{DIRECT_MAP_MAX, SLOT_IS_PARTITION_MAX};
        same_sums_in_every_layout(&a, &b, c, K, &[SLOT_IS_PARTITION_MAX, SLOT_IS_PARTITION_MAX + 1, DIRECT_MAP_MAX + 1])?;
    }
}

/// `a`, `b` and their merge built with each partition count of `layouts` (all above the
/// samples' partitions): the same sums, bit for bit, also through the wire and a second
/// merge; prefetch hints on every id are harmless.
fn same_sums_in_every_layout(
    a: &[Smp],
    b: &[Smp],
    c: ColorMode,
    k: u32,
    layouts: &[u32],
) -> Result<(), TestCaseError> {
    let mut want: Option<(Vec<u64>, Vec<u64>)> = None;
    for &p in layouts {
        let (x, y) = (build_in(a, p, k, c), build_in(b, p, k, c));
        // A prefetch hint is safe for any partition id, sampled or not, in range or
        // not, and on an accumulator without partition storage.
        for id in (0..p + 2).chain([u32::MAX]) {
            x.prefetch_partition(id);
            CellAccumulator::new(x.layout(), c).prefetch_partition(id);
        }
        let mut xy = x.clone();
        xy.merge(&y).unwrap();
        let back = CellAccumulator::decode(&xy.encode()).unwrap();
        prop_assert_eq!(&back, &xy);
        // The wire copy merged again: the same as merging the originals.
        let mut twice = back.clone();
        twice.merge(&y).unwrap();
        let mut direct = xy.clone();
        direct.merge(&y).unwrap();
        prop_assert_eq!(&twice, &direct);
        let got = (sums(&x), sums(&xy));
        match &want {
            None => want = Some(got),
            Some(w) => prop_assert_eq!(w, &got, "P = {}", p),
        }
    }
    Ok(())
}
