//! The surrogate image of relative-variance training [Hua §4.2.1, eq. 25]: the denoised
//! channel mean of a low-spp render, computed from per-pixel moments.
//!
//! One implementation for the in-process renderer and the coordinator (which assembles the
//! surrogate phase of a farm job from uploaded pixel records): the same moments give the
//! same surrogate bits.

use crate::denoise::{AtrousOptions, atrous};

/// Per-pixel sums of one phase: radiance, its square, the albedo and normal AOVs, and the
/// sample count.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PixelMoments {
    /// Σ radiance (RGB).
    pub sum: [f64; 3],
    /// Σ radiance² per channel.
    pub sum_sq: [f64; 3],
    /// Σ albedo AOV.
    pub albedo: [f64; 3],
    /// Σ shading-normal AOV.
    pub normal: [f64; 3],
    /// Samples summed.
    pub count: u64,
}

impl PixelMoments {
    /// Variance of the mean per radiance channel, `((Σx² − n·mean²)/(n − 1)).max(0)/n` in
    /// this operation order (the film's formula); 0 with fewer than 2 samples.
    pub fn variance_of_mean(&self) -> [f64; 3] {
        if self.count < 2 {
            return [0.0; 3];
        }
        let n = self.count as f64;
        self.squared_deviations()
            .map(|d| (d / (n - 1.0)).max(0.0) / n)
    }

    /// Sum of the samples' squared deviations from their mean per radiance channel,
    /// `Σx² − n·mean²` (rounding can take it slightly below 0; 0 with fewer than 2 samples).
    pub fn squared_deviations(&self) -> [f64; 3] {
        if self.count < 2 {
            return [0.0; 3];
        }
        let n = self.count as f64;
        std::array::from_fn(|c| {
            let mean = self.sum[c] / n;
            self.sum_sq[c] - n * mean * mean
        })
    }

    /// Both pixels' samples as one set (every sum added).
    pub fn merged(&self, other: &PixelMoments) -> PixelMoments {
        let add = |a: [f64; 3], b: [f64; 3]| std::array::from_fn(|c| a[c] + b[c]);
        PixelMoments {
            sum: add(self.sum, other.sum),
            sum_sq: add(self.sum_sq, other.sum_sq),
            albedo: add(self.albedo, other.albedo),
            normal: add(self.normal, other.normal),
            count: self.count + other.count,
        }
    }
}

fn f32c(v: f64) -> f32 {
    v.clamp(-f64::from(f32::MAX), f64::from(f32::MAX)) as f32
}

/// The denoised per-pixel surrogate (channel mean), `width × height` values, row-major.
///
/// Guided à-trous filtering ([`atrous`]) of the pixel means with the albedo and normal AOVs
/// and the per-pixel variance of the mean; with fewer than 2 samples in a pixel the 3×3
/// spatial variance of the channel mean stands in for it (SVGF's spatial fallback), else the
/// colour edge-stopping would keep the noise. Non-finite or mismatched input falls back to
/// the undenoised means.
pub fn surrogate_image(pixels: &[PixelMoments], width: usize, height: usize) -> Vec<f64> {
    let (w, h) = (width, height);
    let mean = |p: &PixelMoments, v: [f64; 3]| v.map(|x| f32c(x / p.count.max(1) as f64));
    let color: Vec<f32> = pixels.iter().flat_map(|p| mean(p, p.sum)).collect();
    let lum: Vec<f32> = color
        .chunks_exact(3)
        .map(|c| (c[0] + c[1] + c[2]) / 3.0)
        .collect();
    let var: Vec<f32> = pixels
        .iter()
        .enumerate()
        .map(|(i, p)| {
            if p.count >= 2 {
                let n = p.count as f64;
                let mut acc = 0.0f32;
                for c in 0..3 {
                    let m = p.sum[c] / n;
                    let s2 = ((p.sum_sq[c] - n * m * m) / (n - 1.0)).max(0.0);
                    acc += f32c(s2 / n);
                }
                return (acc / 3.0).max(0.0);
            }
            let (x, y) = ((i % w.max(1)) as isize, (i / w.max(1)) as isize);
            let (mut s, mut s2, mut k) = (0.0f32, 0.0f32, 0.0f32);
            for dy in -1..=1 {
                for dx in -1..=1 {
                    let (xx, yy) = (x + dx, y + dy);
                    if xx >= 0 && yy >= 0 && (xx as usize) < w && (yy as usize) < h {
                        let l = lum[yy as usize * w + xx as usize];
                        s += l;
                        s2 += l * l;
                        k += 1.0;
                    }
                }
            }
            let m = s / k;
            (s2 / k - m * m).max(0.0)
        })
        .collect();
    let albedo: Vec<f32> = pixels.iter().flat_map(|p| mean(p, p.albedo)).collect();
    let normal: Vec<f32> = pixels.iter().flat_map(|p| mean(p, p.normal)).collect();
    // Only the channel mean is wanted, and the filter's weights see only the mean: filter it
    // alone ([`atrous`] with one channel).
    let den = atrous::<1>(
        &lum,
        &var,
        Some(&albedo),
        Some(&normal),
        w,
        h,
        &AtrousOptions::default(),
    )
    .unwrap_or(lum);
    den.into_iter().map(f64::from).collect()
}

/// Magic of an encoded surrogate image.
pub const SURROGATE_MAGIC: [u8; 4] = *b"CVSG";

/// Encodes a surrogate image: magic, `u32` width, `u32` height, then `width × height` f64
/// (little endian). The coordinator stores it content-addressed.
pub fn encode_surrogate(values: &[f64], width: u32, height: u32) -> Vec<u8> {
    let mut out = Vec::with_capacity(12 + values.len() * 8);
    out.extend_from_slice(&SURROGATE_MAGIC);
    out.extend_from_slice(&width.to_le_bytes());
    out.extend_from_slice(&height.to_le_bytes());
    for v in values {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out
}

/// Why a surrogate blob was rejected.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum SurrogateError {
    /// Wrong magic, size or a non-finite value.
    #[error("invalid surrogate image: {0}")]
    Invalid(&'static str),
}

/// Decodes [`encode_surrogate`]: `(values, width, height)`.
pub fn decode_surrogate(bytes: &[u8]) -> Result<(Vec<f64>, u32, u32), SurrogateError> {
    if bytes.len() < 12 || bytes[..4] != SURROGATE_MAGIC {
        return Err(SurrogateError::Invalid("bad magic"));
    }
    let w = u32::from_le_bytes([bytes[4], bytes[5], bytes[6], bytes[7]]);
    let h = u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]);
    let n = u64::from(w) * u64::from(h);
    if (bytes.len() as u64 - 12) != n * 8 {
        return Err(SurrogateError::Invalid(
            "size does not match width × height",
        ));
    }
    let values: Vec<f64> = bytes[12..]
        .chunks_exact(8)
        .map(|c| f64::from_le_bytes(c.try_into().unwrap_or([0; 8])))
        .collect();
    if values.iter().any(|v| !v.is_finite()) {
        return Err(SurrogateError::Invalid("non-finite value"));
    }
    Ok((values, w, h))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn px(v: f64, n: u64) -> PixelMoments {
        PixelMoments {
            sum: [v * n as f64; 3],
            sum_sq: [v * v * n as f64; 3],
            albedo: [0.5 * n as f64; 3],
            normal: [0.0, 0.0, n as f64],
            count: n,
        }
    }

    #[test]
    fn constant_image_stays_constant_and_round_trips() {
        let pixels = vec![px(0.25, 2); 12 * 9];
        let s = surrogate_image(&pixels, 12, 9);
        assert_eq!(s.len(), 108);
        for v in &s {
            assert!((v - 0.25).abs() < 1e-6, "{v}");
        }
        let (d, w, h) = decode_surrogate(&encode_surrogate(&s, 12, 9)).unwrap();
        assert_eq!((d, w, h), (s, 12, 9));
        assert!(decode_surrogate(&encode_surrogate(&[1.0], 2, 1)).is_err());
        assert!(decode_surrogate(&encode_surrogate(&[f64::NAN], 1, 1)).is_err());
        assert!(decode_surrogate(b"CVSG").is_err());
    }

    #[test]
    fn noise_is_reduced() {
        // One-sample pixels with alternating values: the filter must pull them together.
        let (w, h) = (16, 16);
        let pixels: Vec<_> = (0..w * h)
            .map(|i| px(if (i + i / w) % 2 == 0 { 0.2 } else { 0.6 }, 1))
            .collect();
        let s = surrogate_image(&pixels, w, h);
        let spread = |v: &[f64]| {
            let m = v.iter().sum::<f64>() / v.len() as f64;
            v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / v.len() as f64
        };
        let raw: Vec<f64> = pixels.iter().map(|p| p.sum[0]).collect();
        assert!(
            spread(&s) < 0.25 * spread(&raw),
            "{} vs {}",
            spread(&s),
            spread(&raw)
        );
    }
}
