//! Image assembly: pixel blocks of a phase merged into one image.
//!
//! Contract: blocks are added **in canonical task order** ([`crate::job::plan_tasks`]), so each
//! pixel's f64 sums are formed in the same order whatever worker rendered what and however
//! often a task was retried; the image is therefore bitwise-identical for any number of
//! workers. The beauty value is the box-filtered mean `sum / count` (DESIGN §3), the variance
//! layer the estimated variance of that mean, `(Σx² − n·mean²) / (n − 1) / n` — the formulas
//! and operation order of `render::film::Pixel`, so a farm image equals a local render bit for bit.
//!
//! A phased CV job's render-phase blocks, when the phase ran with the CV, go in with
//! [`ImageAccumulator::add_controlled`]: they are summed apart and combined with the other
//! phases' samples by one image-wide inverse-variance weight
//! ([`estimators::composite::phase_weight`], [`estimators::composite::combine_phases`]), as
//! `render::integrator::cv::combine_phase_films` combines a local render's films.

use estimators::composite::combine_phase_images;

use crate::frame::{PixelRecord, TileResult};

/// Running per-pixel sums of a whole image.
#[derive(Clone, Debug, PartialEq)]
pub struct ImageAccumulator {
    width: u32,
    height: u32,
    pixels: Vec<PixelRecord>,
    /// The sums of the blocks rendered with the CV, once one was added.
    controlled: Option<Vec<PixelRecord>>,
}

/// The assembled image: interleaved RGB (or XYZ for normals) `f32` layers, row-major, top row first.
#[derive(Clone, Debug, PartialEq)]
pub struct AssembledImage {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Mean radiance, RGB.
    pub beauty: Vec<f32>,
    /// Estimated variance of the mean, RGB.
    pub variance: Vec<f32>,
    /// Mean albedo AOV, RGB.
    pub albedo: Vec<f32>,
    /// Mean normal AOV, XYZ.
    pub normal: Vec<f32>,
    /// Samples per pixel.
    pub spp: Vec<u64>,
    /// Weight of the samples added with [`ImageAccumulator::add`] when blocks were added with
    /// [`ImageAccumulator::add_controlled`] ([`estimators::composite::phase_weight`]); `None` when all were merged
    /// plainly.
    pub uncontrolled_weight: Option<f64>,
}

/// A block that does not fit the image.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("tile {x0},{y0} {width}x{height} does not fit the {iw}x{ih} image")]
pub struct OutOfBounds {
    x0: u32,
    y0: u32,
    width: u32,
    height: u32,
    iw: u32,
    ih: u32,
}

impl ImageAccumulator {
    /// An all-zero image.
    pub fn new(width: u32, height: u32) -> Self {
        Self {
            width,
            height,
            pixels: vec![PixelRecord::default(); width as usize * height as usize],
            controlled: None,
        }
    }

    /// Adds one tile's sums. Call in canonical task order.
    pub fn add(&mut self, block: &TileResult) -> Result<(), OutOfBounds> {
        let (w, h) = (self.width, self.height);
        add_block(&mut self.pixels, w, h, block)
    }

    /// Adds one tile of a render phase that ran with the CV: summed apart from the other
    /// phases' samples and combined with them by variance in [`Self::finish`]. Call in
    /// canonical task order.
    pub fn add_controlled(&mut self, block: &TileResult) -> Result<(), OutOfBounds> {
        let (w, h, n) = (self.width, self.height, self.pixels.len());
        let sums = self
            .controlled
            .get_or_insert_with(|| vec![PixelRecord::default(); n]);
        add_block(sums, w, h, block)
    }

    /// The per-pixel sums so far (without the blocks added with [`Self::add_controlled`]).
    pub fn pixels(&self) -> &[PixelRecord] {
        &self.pixels
    }

    /// Means and variances (pixels without samples are black with zero variance).
    pub fn finish(&self) -> AssembledImage {
        let combined;
        let mut weight = None;
        let pixels = match &self.controlled {
            None => &self.pixels,
            Some(c) => {
                (combined, weight) = combine_phase_images(&self.pixels, c);
                &combined
            }
        };
        let n = pixels.len();
        let mut out = AssembledImage {
            width: self.width,
            height: self.height,
            beauty: Vec::with_capacity(3 * n),
            variance: Vec::with_capacity(3 * n),
            albedo: Vec::with_capacity(3 * n),
            normal: Vec::with_capacity(3 * n),
            spp: Vec::with_capacity(n),
            uncontrolled_weight: weight,
        };
        for p in pixels {
            // The same formulas, in the same f64 operation order, as `render::film::Pixel`, so
            // a farm image equals a local render bit for bit.
            let n = p.count.max(1) as f64;
            for (c, var) in p.variance_of_mean().into_iter().enumerate() {
                out.beauty.push((p.sum[c] / n) as f32);
                out.variance.push(var as f32);
                out.albedo.push((p.albedo[c] / n) as f32);
                out.normal.push((p.normal[c] / n) as f32);
            }
            out.spp.push(p.count);
        }
        out
    }
}

/// Adds `block`'s sums to the `width × height` image `pixels`.
fn add_block(
    pixels: &mut [PixelRecord],
    width: u32,
    height: u32,
    block: &TileResult,
) -> Result<(), OutOfBounds> {
    let r = block.header.rect;
    if !r.fits_in(width, height) || block.pixels.len() != r.pixel_count() {
        return Err(OutOfBounds {
            x0: r.x0,
            y0: r.y0,
            width: r.width,
            height: r.height,
            iw: width,
            ih: height,
        });
    }
    for ty in 0..r.height as usize {
        let dst_row = (r.y0 as usize + ty) * width as usize + r.x0 as usize;
        let src_row = ty * r.width as usize;
        for tx in 0..r.width as usize {
            let d = &mut pixels[dst_row + tx];
            *d = d.merged(&block.pixels[src_row + tx]);
        }
    }
    Ok(())
}

impl AssembledImage {
    /// relMSE estimated from the variance layer (DESIGN §6): mean over pixels and channels of
    /// Var / (mean² + 0.01).
    pub fn estimated_rel_mse(&self) -> f64 {
        if self.beauty.is_empty() {
            return 0.0;
        }
        let s: f64 = self
            .beauty
            .iter()
            .zip(&self.variance)
            .map(|(&m, &v)| f64::from(v) / (f64::from(m) * f64::from(m) + 0.01))
            .sum();
        s / self.beauty.len() as f64
    }

    /// Mean samples per pixel.
    pub fn mean_spp(&self) -> f64 {
        if self.spp.is_empty() {
            return 0.0;
        }
        self.spp.iter().map(|&s| s as f64).sum::<f64>() / self.spp.len() as f64
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::TileHeader;
    use crate::job::TileRect;

    fn block(x0: u32, y0: u32, w: u32, h: u32, v: f64, count: u64) -> TileResult {
        TileResult {
            header: TileHeader {
                job_id: 1,
                task_id: 1,
                attempt: 1,
                rect: TileRect {
                    x0,
                    y0,
                    width: w,
                    height: h,
                },
                sample_start: 0,
                sample_end: count as u32,
            },
            pixels: vec![
                PixelRecord {
                    sum: [v * count as f64; 3],
                    sum_sq: [v * v * count as f64; 3],
                    albedo: [count as f64; 3],
                    normal: [0.0; 3],
                    count,
                };
                (w * h) as usize
            ],
            cells: vec![],
        }
    }

    #[test]
    fn means_and_bounds() {
        let mut acc = ImageAccumulator::new(4, 2);
        acc.add(&block(0, 0, 2, 2, 1.0, 2)).unwrap();
        acc.add(&block(2, 0, 2, 2, 3.0, 4)).unwrap();
        acc.add(&block(2, 0, 2, 2, 1.0, 4)).unwrap();
        assert!(acc.add(&block(3, 0, 2, 2, 1.0, 1)).is_err());
        let img = acc.finish();
        assert_eq!(img.beauty[0], 1.0);
        assert_eq!(img.beauty[3 * 2], 2.0);
        assert_eq!(img.spp, vec![2, 2, 8, 8, 2, 2, 8, 8]);
        assert_eq!(img.albedo[0], 1.0);
        // Constant samples have zero variance; mixed ones (3,3,3,3,1,1,1,1) have sample variance 8/7, so 8/7 / 8 for the mean.
        assert_eq!(img.variance[0], 0.0);
        assert!((f64::from(img.variance[6]) - 8.0 / 7.0 / 8.0).abs() < 1e-7);
        assert!(img.estimated_rel_mse() > 0.0);
    }
}
