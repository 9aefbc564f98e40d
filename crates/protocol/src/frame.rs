//! The `TileResult` binary stream a worker uploads for one task attempt.
//!
//! # Format (version 1, all integers and floats little-endian)
//!
//! The stream is a sequence of **frames**, each `len: u32` (bytes that follow, ≥ 1) then
//! `type: u8` then `len − 1` payload bytes. Frames, in this order:
//!
//! | type | name | payload |
//! |---|---|---|
//! | 1 | header (once, first) | `magic "CVTR"`, `version: u16`, `job_id: i64`, `task_id: i64`, `attempt: u32`, `x0, y0, width, height: u32`, `sample_start, sample_end: u32` |
//! | 2 | pixel rows (≥ 1) | `row_start: u32`, `rows: u32`, then `rows × width` [`PixelRecord`]s of 104 bytes |
//! | 3 | cell accumulators (≥ 0) | `kind: u16` then opaque bytes (encoding owned by `estimators`) |
//! | 4 | end (once, last) | `frames: u32` — number of frames before this one |
//!
//! Pixel-row frames must cover the tile's rows exactly once, in ascending order (so a stream
//! can be produced and consumed row block by row block). A [`PixelRecord`] is 12 `f64`
//! (sum RGB, sum of squares RGB, albedo sum RGB, normal sum RGB) and a `u64` sample count.
//!
//! # Validation
//! [`decode`] rejects (never panics on) arbitrary bytes: wrong magic or version, frames out of
//! order, truncation (no end frame, short frame), sizes over [`MAX_FRAME_BYTES`], rows
//! missing/overlapping, non-finite values, negative sums of squares, sample counts over the
//! sample range, trailing bytes. Consistency with the lease (ids, attempt, rect, samples) is
//! the coordinator's check.

use crate::job::TileRect;

/// Magic bytes at the start of the header payload.
pub const MAGIC: [u8; 4] = *b"CVTR";
/// Version written by this crate; the only one [`decode`] accepts.
pub const VERSION: u16 = 1;
/// Largest single frame (type + payload), so a hostile length cannot make us allocate much.
pub const MAX_FRAME_BYTES: u32 = 16 << 20;
/// Encoded size of one [`PixelRecord`].
pub const PIXEL_RECORD_BYTES: usize = 13 * 8;
/// Pixel rows per frame written by [`encode`] (keeps frames well under [`MAX_FRAME_BYTES`]).
const ROWS_PER_FRAME: u32 = 16;

const T_HEADER: u8 = 1;
const T_PIXELS: u8 = 2;
const T_CELLS: u8 = 3;
const T_END: u8 = 4;
const HEADER_BYTES: usize = 4 + 2 + 8 + 8 + 4 + 4 * 4 + 4 * 2;

/// Per-pixel accumulators of one tile over its sample range (Σ radiance, Σ radiance², Σ albedo,
/// Σ shading normal, sample count): the moments `estimators` computes the surrogate from, so
/// the renderer, the worker and the coordinator share one type.
pub type PixelRecord = estimators::surrogate::PixelMoments;

/// A block of per-cell accumulator records, opaque to the protocol until `estimators`
/// defines the encoding; `kind` says which encoding.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct CellBlock {
    /// Encoding tag.
    pub kind: u16,
    /// Encoded records.
    pub data: Vec<u8>,
}

/// Header of a tile result.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TileHeader {
    /// Job id.
    pub job_id: i64,
    /// Task id.
    pub task_id: i64,
    /// Attempt the result belongs to.
    pub attempt: u32,
    /// Pixels covered.
    pub rect: TileRect,
    /// First sample index.
    pub sample_start: u32,
    /// End sample index (exclusive).
    pub sample_end: u32,
}

/// A decoded, validated tile result.
#[derive(Clone, Debug, PartialEq)]
pub struct TileResult {
    /// Identity and extent.
    pub header: TileHeader,
    /// `rect.width × rect.height` records, row-major.
    pub pixels: Vec<PixelRecord>,
    /// Per-cell accumulator blocks (empty for the `path` estimator).
    pub cells: Vec<CellBlock>,
}

/// Why a stream was rejected. The message names the problem (it is shown to the uploader).
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum FrameError {
    /// The stream ended inside a frame or before the end frame.
    #[error("truncated stream: {0}")]
    Truncated(&'static str),
    /// Magic or version wrong.
    #[error("not a cvfarm tile result (bad magic or unsupported version {0})")]
    BadVersion(u16),
    /// A frame has a length or type that is not allowed where it is.
    #[error("malformed frame: {0}")]
    Malformed(String),
    /// A value is NaN or infinite, or otherwise out of range.
    #[error("invalid value at pixel {pixel}: {what}")]
    BadValue {
        /// Index of the pixel in the tile (row-major).
        pixel: usize,
        /// What is wrong.
        what: &'static str,
    },
}

impl TileResult {
    /// Encodes as a frame stream (see the module docs).
    pub fn encode(&self) -> Vec<u8> {
        encode(self)
    }
}

fn push_frame(out: &mut Vec<u8>, ty: u8, payload: &[u8]) {
    let len = u32::try_from(payload.len() + 1).expect("frame too large");
    out.extend_from_slice(&len.to_le_bytes());
    out.push(ty);
    out.extend_from_slice(payload);
}

/// Encodes a tile result as a frame stream.
///
/// # Panics
/// If the tile is so wide that 16 rows exceed [`MAX_FRAME_BYTES`] (over 10 000 pixels wide;
/// tiles are at most 512 wide) or `pixels` does not match the rect (a caller bug).
pub fn encode(r: &TileResult) -> Vec<u8> {
    let h = &r.header;
    assert_eq!(
        r.pixels.len(),
        h.rect.pixel_count(),
        "pixel block does not match the tile"
    );
    let mut out = Vec::with_capacity(64 + r.pixels.len() * PIXEL_RECORD_BYTES);
    let mut p = Vec::with_capacity(HEADER_BYTES);
    p.extend_from_slice(&MAGIC);
    p.extend_from_slice(&VERSION.to_le_bytes());
    p.extend_from_slice(&h.job_id.to_le_bytes());
    p.extend_from_slice(&h.task_id.to_le_bytes());
    p.extend_from_slice(&h.attempt.to_le_bytes());
    for v in [
        h.rect.x0,
        h.rect.y0,
        h.rect.width,
        h.rect.height,
        h.sample_start,
        h.sample_end,
    ] {
        p.extend_from_slice(&v.to_le_bytes());
    }
    push_frame(&mut out, T_HEADER, &p);
    let mut frames = 1u32;
    let w = h.rect.width as usize;
    let mut row = 0u32;
    while row < h.rect.height {
        let rows = ROWS_PER_FRAME.min(h.rect.height - row);
        p.clear();
        p.extend_from_slice(&row.to_le_bytes());
        p.extend_from_slice(&rows.to_le_bytes());
        for px in &r.pixels[row as usize * w..(row + rows) as usize * w] {
            for v in px
                .sum
                .iter()
                .chain(&px.sum_sq)
                .chain(&px.albedo)
                .chain(&px.normal)
            {
                p.extend_from_slice(&v.to_le_bytes());
            }
            p.extend_from_slice(&px.count.to_le_bytes());
        }
        push_frame(&mut out, T_PIXELS, &p);
        frames += 1;
        row += rows;
    }
    for c in &r.cells {
        p.clear();
        p.extend_from_slice(&c.kind.to_le_bytes());
        p.extend_from_slice(&c.data);
        push_frame(&mut out, T_CELLS, &p);
        frames += 1;
    }
    push_frame(&mut out, T_END, &frames.to_le_bytes());
    out
}

/// A little-endian reader over a byte slice that reports truncation instead of panicking.
struct Reader<'a> {
    buf: &'a [u8],
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize) -> Option<&'a [u8]> {
        if self.buf.len() < n {
            return None;
        }
        let (a, b) = self.buf.split_at(n);
        self.buf = b;
        Some(a)
    }
    fn u16(&mut self) -> Option<u16> {
        self.take(2).map(|b| u16::from_le_bytes([b[0], b[1]]))
    }
    fn u32(&mut self) -> Option<u32> {
        self.take(4)
            .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    }
    fn u64(&mut self) -> Option<u64> {
        self.take(8)
            .map(|b| u64::from_le_bytes(b.try_into().unwrap_or([0; 8])))
    }
    fn f64(&mut self) -> Option<f64> {
        self.u64().map(f64::from_bits)
    }
}

/// Reads one frame: `None` at the end of the stream.
fn next_frame<'a>(stream: &mut Reader<'a>) -> Result<Option<(u8, &'a [u8])>, FrameError> {
    if stream.buf.is_empty() {
        return Ok(None);
    }
    let len = stream.u32().ok_or(FrameError::Truncated("frame length"))?;
    if len == 0 || len > MAX_FRAME_BYTES {
        return Err(FrameError::Malformed(format!(
            "frame length {len} out of range"
        )));
    }
    let body = stream
        .take(len as usize)
        .ok_or(FrameError::Truncated("frame body"))?;
    Ok(Some((body[0], &body[1..])))
}

/// Decodes and validates a frame stream. `max_pixels` bounds the tile size the caller
/// accepts (so a header cannot announce a huge allocation).
pub fn decode(bytes: &[u8], max_pixels: usize) -> Result<TileResult, FrameError> {
    let mut stream = Reader { buf: bytes };

    // Header.
    let (ty, payload) = next_frame(&mut stream)?.ok_or(FrameError::Truncated("empty stream"))?;
    if ty != T_HEADER {
        return Err(FrameError::Malformed(format!(
            "first frame has type {ty}, expected header"
        )));
    }
    if payload.len() < 6 || payload[..4] != MAGIC {
        return Err(FrameError::BadVersion(0));
    }
    let mut r = Reader { buf: payload };
    r.take(4);
    let version = r.u16().unwrap_or(0);
    if version != VERSION {
        return Err(FrameError::BadVersion(version));
    }
    if payload.len() != HEADER_BYTES {
        return Err(FrameError::Malformed(format!(
            "header of {} bytes, expected {HEADER_BYTES}",
            payload.len()
        )));
    }
    let trunc = FrameError::Truncated("header");
    let job_id = r.u64().ok_or(trunc.clone())? as i64;
    let task_id = r.u64().ok_or(trunc.clone())? as i64;
    let attempt = r.u32().ok_or(trunc.clone())?;
    let mut v = [0u32; 6];
    for x in &mut v {
        *x = r.u32().ok_or(trunc.clone())?;
    }
    let rect = TileRect {
        x0: v[0],
        y0: v[1],
        width: v[2],
        height: v[3],
    };
    let header = TileHeader {
        job_id,
        task_id,
        attempt,
        rect,
        sample_start: v[4],
        sample_end: v[5],
    };
    if rect.width == 0 || rect.height == 0 {
        return Err(FrameError::Malformed("empty tile".into()));
    }
    let n_pixels = u64::from(rect.width) * u64::from(rect.height);
    if n_pixels > max_pixels as u64 {
        return Err(FrameError::Malformed(format!(
            "tile of {n_pixels} pixels exceeds the limit of {max_pixels}"
        )));
    }
    if header.sample_end <= header.sample_start {
        return Err(FrameError::Malformed("empty sample range".into()));
    }
    let max_count = u64::from(header.sample_end - header.sample_start);

    let mut pixels = Vec::with_capacity(n_pixels as usize);
    let mut cells = Vec::new();
    let mut frames = 1u32;
    let mut rows_done = 0u32;
    loop {
        let (ty, payload) =
            next_frame(&mut stream)?.ok_or(FrameError::Truncated("missing end frame"))?;
        match ty {
            T_PIXELS => {
                if !cells.is_empty() {
                    return Err(FrameError::Malformed(
                        "pixel rows after cell accumulators".into(),
                    ));
                }
                let mut r = Reader { buf: payload };
                let row_start = r.u32().ok_or(FrameError::Truncated("pixel frame"))?;
                let rows = r.u32().ok_or(FrameError::Truncated("pixel frame"))?;
                if row_start != rows_done
                    || rows == 0
                    || u64::from(rows) + u64::from(row_start) > u64::from(rect.height)
                {
                    return Err(FrameError::Malformed(format!(
                        "pixel rows {row_start}+{rows} do not continue row {rows_done} of {}",
                        rect.height
                    )));
                }
                let expect = rows as usize * rect.width as usize * PIXEL_RECORD_BYTES;
                if r.buf.len() != expect {
                    return Err(FrameError::Malformed(format!(
                        "pixel frame has {} bytes of records, expected {expect}",
                        r.buf.len()
                    )));
                }
                for _ in 0..rows as usize * rect.width as usize {
                    let pixel = pixels.len();
                    let mut vals = [0f64; 12];
                    for x in &mut vals {
                        *x = r.f64().ok_or(FrameError::Truncated("pixel record"))?;
                    }
                    let count = r.u64().ok_or(FrameError::Truncated("pixel record"))?;
                    if vals.iter().any(|x| !x.is_finite()) {
                        return Err(FrameError::BadValue {
                            pixel,
                            what: "non-finite value",
                        });
                    }
                    if vals[3..6].iter().any(|&x| x < 0.0) {
                        return Err(FrameError::BadValue {
                            pixel,
                            what: "negative sum of squares",
                        });
                    }
                    if count > max_count {
                        return Err(FrameError::BadValue {
                            pixel,
                            what: "sample count exceeds the sample range",
                        });
                    }
                    let t = |i: usize| [vals[i], vals[i + 1], vals[i + 2]];
                    pixels.push(PixelRecord {
                        sum: t(0),
                        sum_sq: t(3),
                        albedo: t(6),
                        normal: t(9),
                        count,
                    });
                }
                rows_done += rows;
            }
            T_CELLS => {
                if rows_done != rect.height {
                    return Err(FrameError::Malformed(
                        "cell accumulators before all pixel rows".into(),
                    ));
                }
                let mut r = Reader { buf: payload };
                let kind = r.u16().ok_or(FrameError::Truncated("cell frame"))?;
                cells.push(CellBlock {
                    kind,
                    data: r.buf.to_vec(),
                });
            }
            T_END => {
                let mut r = Reader { buf: payload };
                let n = r.u32().ok_or(FrameError::Truncated("end frame"))?;
                if !r.buf.is_empty() || n != frames {
                    return Err(FrameError::Malformed(format!(
                        "end frame counts {n} frames, stream had {frames}"
                    )));
                }
                if rows_done != rect.height {
                    return Err(FrameError::Truncated(
                        "pixel rows missing before the end frame",
                    ));
                }
                if !stream.buf.is_empty() {
                    return Err(FrameError::Malformed("bytes after the end frame".into()));
                }
                return Ok(TileResult {
                    header,
                    pixels,
                    cells,
                });
            }
            other => {
                return Err(FrameError::Malformed(format!(
                    "unexpected frame type {other}"
                )));
            }
        }
        frames += 1;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn sample(w: u32, h: u32) -> TileResult {
        let pixels = (0..w * h)
            .map(|i| {
                let x = f64::from(i);
                PixelRecord {
                    sum: [x, x * 0.5, 1e-300],
                    sum_sq: [x * x, 0.0, 1e300],
                    albedo: [0.5; 3],
                    normal: [0.0, -1.0, 0.0],
                    count: 4,
                }
            })
            .collect();
        TileResult {
            header: TileHeader {
                job_id: 7,
                task_id: 42,
                attempt: 3,
                rect: TileRect {
                    x0: 16,
                    y0: 32,
                    width: w,
                    height: h,
                },
                sample_start: 4,
                sample_end: 8,
            },
            pixels,
            cells: vec![CellBlock {
                kind: 9,
                data: vec![1, 2, 3],
            }],
        }
    }

    #[test]
    fn roundtrip_is_exact() {
        let r = sample(5, 37);
        let bytes = r.encode();
        assert_eq!(decode(&bytes, 1 << 20).unwrap(), r);
    }

    #[test]
    fn truncated_stream_rejected_at_every_length() {
        let bytes = sample(3, 20).encode();
        for n in 0..bytes.len() {
            assert!(
                decode(&bytes[..n], 1 << 20).is_err(),
                "prefix of {n} bytes accepted"
            );
        }
    }

    #[test]
    fn non_finite_value_rejected() {
        for bad in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
            let mut r = sample(2, 2);
            r.pixels[3].normal[1] = bad;
            let e = decode(&r.encode(), 1 << 20).unwrap_err();
            assert_eq!(
                e,
                FrameError::BadValue {
                    pixel: 3,
                    what: "non-finite value"
                }
            );
        }
    }

    #[test]
    fn count_over_range_and_negative_square_rejected() {
        let mut r = sample(2, 2);
        r.pixels[0].count = 5;
        assert!(matches!(
            decode(&r.encode(), 1 << 20),
            Err(FrameError::BadValue { pixel: 0, .. })
        ));
        let mut r = sample(2, 2);
        r.pixels[1].sum_sq[0] = -1.0;
        assert!(matches!(
            decode(&r.encode(), 1 << 20),
            Err(FrameError::BadValue { pixel: 1, .. })
        ));
    }

    #[test]
    fn wrong_version_and_oversized_tile_rejected() {
        let mut bytes = sample(2, 2).encode();
        bytes[5 + 4] = 2; // version low byte
        assert_eq!(decode(&bytes, 1 << 20), Err(FrameError::BadVersion(2)));
        assert!(matches!(
            decode(&sample(4, 4).encode(), 15),
            Err(FrameError::Malformed(_))
        ));
    }

    #[test]
    fn trailing_bytes_rejected() {
        let mut bytes = sample(2, 2).encode();
        bytes.push(0);
        assert!(decode(&bytes, 1 << 20).is_err());
    }

    proptest! {
        #[test]
        fn arbitrary_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..2048)) {
            let _ = decode(&bytes, 1 << 16);
        }

        #[test]
        fn mutated_streams_never_panic(pos in 0usize..400, val in any::<u8>(), cut in 0usize..500) {
            let mut bytes = sample(3, 1).encode();
            let p = pos % bytes.len();
            bytes[p] = val;
            bytes.truncate(cut.max(1).min(bytes.len()));
            let _ = decode(&bytes, 1 << 16);
        }
    }
}
