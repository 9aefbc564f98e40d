//! Films: per-pixel f64 accumulators of a rectangle of the image.
//!
//! Each pixel keeps `sum[3]`, `sum_sq[3]` (of the RGB sample values), the sample `count`,
//! and the AOV sums `albedo_sum[3]`, `normal_sum[3]` (first-hit albedo and shading normal,
//! zero for samples that miss). With a box filter a pixel value is the plain mean of its
//! samples.
//!
//! Determinism: a film is a plain sum, so merging is exact only in a fixed order. Tiles of
//! one image cover disjoint pixels, so merging them is order-independent; films of the
//! *same* pixels (sample ranges of one tile split across tasks) must be merged in canonical
//! order (by sample range) to get bitwise-identical results.
//!
//! Statistics:
//! - mean `μ = sum / n`;
//! - variance of the mean `Var[μ] = s² / n`, with the unbiased sample variance
//!   `s² = (sum_sq − n μ²) / (n − 1)` (0 when `n < 2`).

use estimators::surrogate::PixelMoments;
use glam::Vec3;

/// The f64 accumulators of one pixel.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Pixel {
    /// Σ sample RGB.
    pub sum: [f64; 3],
    /// Σ sample RGB².
    pub sum_sq: [f64; 3],
    /// Number of samples.
    pub count: u64,
    /// Σ first-hit albedo.
    pub albedo_sum: [f64; 3],
    /// Σ first-hit shading normal.
    pub normal_sum: [f64; 3],
}

impl Pixel {
    /// Adds one sample.
    #[inline]
    pub fn add(&mut self, value: Vec3, albedo: Vec3, normal: Vec3) {
        for c in 0..3 {
            let v = f64::from(value[c]);
            self.sum[c] += v;
            self.sum_sq[c] += v * v;
            self.albedo_sum[c] += f64::from(albedo[c]);
            self.normal_sum[c] += f64::from(normal[c]);
        }
        self.count += 1;
    }

    /// Adds another pixel's accumulators.
    #[inline]
    pub fn merge(&mut self, other: &Pixel) {
        for c in 0..3 {
            self.sum[c] += other.sum[c];
            self.sum_sq[c] += other.sum_sq[c];
            self.albedo_sum[c] += other.albedo_sum[c];
            self.normal_sum[c] += other.normal_sum[c];
        }
        self.count += other.count;
    }

    /// Mean RGB (0 without samples).
    pub fn mean(&self) -> [f64; 3] {
        let n = self.count.max(1) as f64;
        self.sum.map(|s| s / n)
    }

    /// Sum of the samples' squared deviations from their mean per channel,
    /// `Σ x² − n·mean²` (rounding can take it slightly below 0; 0 with fewer than 2 samples).
    pub fn squared_deviations(&self) -> [f64; 3] {
        self.moments().squared_deviations()
    }

    /// Variance of the mean per channel (0 with fewer than 2 samples;
    /// [`PixelMoments::variance_of_mean`], the farm's formula).
    pub fn variance_of_mean(&self) -> [f64; 3] {
        self.moments().variance_of_mean()
    }

    /// The sums as the farm's records and the estimators take them.
    pub fn moments(&self) -> PixelMoments {
        PixelMoments {
            sum: self.sum,
            sum_sq: self.sum_sq,
            albedo: self.albedo_sum,
            normal: self.normal_sum,
            count: self.count,
        }
    }
}

impl From<PixelMoments> for Pixel {
    fn from(m: PixelMoments) -> Self {
        Pixel {
            sum: m.sum,
            sum_sq: m.sum_sq,
            count: m.count,
            albedo_sum: m.albedo,
            normal_sum: m.normal,
        }
    }
}

/// f64 → f32 for output, saturating at ±`f32::MAX` so that finite accumulators (e.g. the
/// variance of samples near the top of the f32 range) never become ∞ in an image.
#[inline]
fn saturate(v: f64) -> f32 {
    v.clamp(-f64::from(f32::MAX), f64::from(f32::MAX)) as f32
}

/// A named RGB layer for image output (`beauty`, `variance`, `albedo`, `normal`).
#[derive(Clone, Debug, PartialEq)]
pub struct FilmLayer {
    /// Layer name.
    pub name: &'static str,
    /// Row-major RGB values, top row first.
    pub data: Vec<[f32; 3]>,
}

/// Accumulators of the rectangle `[x0, x0 + width) × [y0, y0 + height)` of an image.
#[derive(Clone, Debug, PartialEq)]
pub struct Film {
    /// Left column in image pixels.
    pub x0: u32,
    /// Top row in image pixels.
    pub y0: u32,
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Row-major pixels.
    pub pixels: Vec<Pixel>,
    /// Non-finite samples that were replaced by zero (counted in `count`, not in the sums).
    pub rejected: u64,
}

impl Film {
    /// An empty film of a whole `width × height` image.
    pub fn new(width: u32, height: u32) -> Self {
        Self::new_rect(0, 0, width, height)
    }

    /// An empty film covering a rectangle of the image.
    pub fn new_rect(x0: u32, y0: u32, width: u32, height: u32) -> Self {
        Self {
            x0,
            y0,
            width,
            height,
            pixels: vec![Pixel::default(); width as usize * height as usize],
            rejected: 0,
        }
    }

    /// The pixel at image coordinates `(x, y)` (must lie in the rectangle).
    #[inline]
    pub fn pixel_mut(&mut self, x: u32, y: u32) -> &mut Pixel {
        let i = (y - self.y0) as usize * self.width as usize + (x - self.x0) as usize;
        &mut self.pixels[i]
    }

    /// The pixel at image coordinates `(x, y)` (must lie in the rectangle).
    #[inline]
    pub fn pixel(&self, x: u32, y: u32) -> &Pixel {
        &self.pixels[(y - self.y0) as usize * self.width as usize + (x - self.x0) as usize]
    }

    /// Adds the accumulators of `other` to the overlapping pixels of `self` (images
    /// coordinates; parts of `other` outside `self` are ignored).
    pub fn merge(&mut self, other: &Film) {
        let xa = self.x0.max(other.x0);
        let xb = (self.x0 + self.width).min(other.x0 + other.width);
        let ya = self.y0.max(other.y0);
        let yb = (self.y0 + self.height).min(other.y0 + other.height);
        for y in ya..yb {
            for x in xa..xb {
                let o = *other.pixel(x, y);
                self.pixel_mut(x, y).merge(&o);
            }
        }
        self.rejected += other.rejected;
    }

    /// Every pixel's sums (radiance, its square, albedo, normal) as `f64` bit patterns and
    /// its sample count, pixel by pixel: what "the same bits" compares.
    pub fn to_bits(&self) -> Vec<u64> {
        self.pixels
            .iter()
            .flat_map(|p| {
                p.sum
                    .iter()
                    .chain(&p.sum_sq)
                    .chain(&p.albedo_sum)
                    .chain(&p.normal_sum)
                    .map(|v| v.to_bits())
                    .chain([p.count])
            })
            .collect()
    }

    /// Total number of samples in the film.
    pub fn sample_count(&self) -> u64 {
        self.pixels.iter().map(|p| p.count).sum()
    }

    /// Mean image (row-major RGB, f32).
    pub fn mean_image(&self) -> Vec<[f32; 3]> {
        self.pixels.iter().map(|p| p.mean().map(saturate)).collect()
    }

    /// Per-pixel variance of the mean.
    pub fn variance_image(&self) -> Vec<[f32; 3]> {
        self.pixels
            .iter()
            .map(|p| p.variance_of_mean().map(saturate))
            .collect()
    }

    /// Mean first-hit albedo per pixel.
    pub fn albedo_image(&self) -> Vec<[f32; 3]> {
        self.pixels
            .iter()
            .map(|p| p.albedo_sum.map(|v| saturate(v / p.count.max(1) as f64)))
            .collect()
    }

    /// Mean first-hit shading normal per pixel (not renormalised).
    pub fn normal_image(&self) -> Vec<[f32; 3]> {
        self.pixels
            .iter()
            .map(|p| p.normal_sum.map(|v| saturate(v / p.count.max(1) as f64)))
            .collect()
    }

    /// The EXR layers: `beauty`, `variance` (of the mean), `albedo`, `normal`.
    pub fn layers(&self) -> Vec<FilmLayer> {
        vec![
            FilmLayer {
                name: "beauty",
                data: self.mean_image(),
            },
            FilmLayer {
                name: "variance",
                data: self.variance_image(),
            },
            FilmLayer {
                name: "albedo",
                data: self.albedo_image(),
            },
            FilmLayer {
                name: "normal",
                data: self.normal_image(),
            },
        ]
    }

    /// Image mean per channel (f64) of the mean image.
    pub fn image_mean(&self) -> [f64; 3] {
        let mut s = [0.0; 3];
        for p in &self.pixels {
            let m = p.mean();
            for c in 0..3 {
                s[c] += m[c];
            }
        }
        let n = self.pixels.len().max(1) as f64;
        s.map(|v| v / n)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mean_and_variance_of_mean_match_definitions() {
        let mut p = Pixel::default();
        for v in [1.0f32, 2.0, 3.0, 4.0] {
            p.add(Vec3::splat(v), Vec3::ONE, Vec3::Z);
        }
        assert_eq!(p.mean(), [2.5; 3]);
        // s² = 5/3, Var[mean] = s²/4.
        assert!((p.variance_of_mean()[0] - 5.0 / 12.0).abs() < 1e-12);
    }

    #[test]
    fn merging_tiles_places_pixels() {
        let mut img = Film::new(4, 4);
        let mut tile = Film::new_rect(2, 1, 2, 2);
        tile.pixel_mut(3, 2).add(Vec3::ONE, Vec3::ZERO, Vec3::ZERO);
        img.merge(&tile);
        assert_eq!(img.pixel(3, 2).count, 1);
        assert_eq!(img.sample_count(), 1);
    }
}
