//! `cvfarm compare TEST.exr REF.exr`: how far a rendered image is from a reference.
//!
//! Metrics (DESIGN §6, the same definitions as `scenes-mitsuba/tools/compare.py`):
//!
//! | output | meaning |
//! |---|---|
//! | `relMSE` | mean over pixels and channels of (x − ref)² / (ref² + ε), ε = 0.01 |
//! | `MSE` | mean over pixels and channels of (x − ref)² |
//! | `mean ratio` | per channel: mean(test) / mean(ref) over pixels finite in both images |
//! | `non-finite` | NaN/Inf values (and pixels) of the test image; they are left out of the means |
//!
//! | flag | env | default | meaning |
//! |---|---|---|---|
//! | `--json` | `CVFARM_JSON` | off | print one JSON object instead of the table |
//! | `--layer NAME` | `CVFARM_LAYER` | `beauty` (else the first layer) | which EXR layer of both files to compare |
//! | `--max-rel-mse X` | `CVFARM_MAX_REL_MSE` | none | exit with status 3 if relMSE > X or any value is non-finite |
//!
//! ```text
//! $ cvfarm compare out/cbox.exr ref/cbox.exr --json
//! {"rel_mse":0.00123,"mse":0.00045,"mean_ratio":[1.001,0.998,1.0],...}
//! ```

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{Context, Result, bail};
use clap::Args;
use estimators::metrics::{self, REL_MSE_EPSILON};
use serde_json::json;

/// Exit status when `--max-rel-mse` is exceeded.
pub const EXIT_TOO_DIFFERENT: u8 = 3;

/// Arguments of `cvfarm compare`.
#[derive(Debug, Args)]
pub struct CompareArgs {
    /// The image to test (EXR).
    pub test: PathBuf,
    /// The reference image (EXR, same size).
    pub reference: PathBuf,
    /// Print the result as one JSON object on stdout.
    #[arg(long, env = "CVFARM_JSON", value_parser = clap::builder::BoolishValueParser::new())]
    pub json: bool,
    /// EXR layer to compare in both files (default: `beauty`, else the first layer).
    #[arg(long, env = "CVFARM_LAYER")]
    pub layer: Option<String>,
    /// Fail (exit status 3) when relMSE exceeds this value or the test has NaN/Inf values.
    #[arg(long, env = "CVFARM_MAX_REL_MSE", allow_negative_numbers = true)]
    pub max_rel_mse: Option<f64>,
}

/// The comparison of two RGB images.
#[derive(Clone, Debug, PartialEq)]
pub struct Comparison {
    /// Image width.
    pub width: u32,
    /// Image height.
    pub height: u32,
    /// relMSE with ε = 0.01 over finite values.
    pub rel_mse: f64,
    /// MSE over finite values.
    pub mse: f64,
    /// Per-channel image means of the test, over pixels finite in both images.
    pub mean_test: [f64; 3],
    /// Per-channel image means of the reference, over the same pixels.
    pub mean_ref: [f64; 3],
    /// NaN/Inf values in the test image.
    pub non_finite_values: usize,
    /// Pixels of the test image with at least one NaN/Inf channel.
    pub non_finite_pixels: usize,
}

impl Comparison {
    /// mean(test) / mean(ref) per channel (NaN where the reference mean is 0).
    pub fn mean_ratio(&self) -> [f64; 3] {
        std::array::from_fn(|c| {
            if self.mean_ref[c] != 0.0 {
                self.mean_test[c] / self.mean_ref[c]
            } else {
                f64::NAN
            }
        })
    }

    /// The JSON form printed by `--json` (non-finite numbers become `null`).
    pub fn to_json(&self) -> serde_json::Value {
        json!({
            "width": self.width,
            "height": self.height,
            "rel_mse": self.rel_mse,
            "rel_mse_epsilon": REL_MSE_EPSILON,
            "mse": self.mse,
            "mean_ratio": self.mean_ratio(),
            "mean_test": self.mean_test,
            "mean_ref": self.mean_ref,
            "non_finite_values": self.non_finite_values,
            "non_finite_pixels": self.non_finite_pixels,
        })
    }
}

/// Compares two images of `width × height` RGB pixels. Errors if their sizes differ.
pub fn compare_images(
    (width, height): (u32, u32),
    test: &[[f32; 3]],
    (ref_width, ref_height): (u32, u32),
    reference: &[[f32; 3]],
) -> Result<Comparison> {
    if (width, height) != (ref_width, ref_height) {
        bail!(
            "images have different sizes: test is {width}x{height}, reference is {ref_width}x{ref_height}"
        );
    }
    if test.len() != reference.len() {
        bail!(
            "images have different pixel counts: {} vs {}",
            test.len(),
            reference.len()
        );
    }
    let flat = |img: &[[f32; 3]]| img.iter().flatten().copied().collect::<Vec<f32>>();
    let stats = metrics::compare(&flat(test), &flat(reference));
    let (mut sum_t, mut sum_r, mut n) = ([0.0f64; 3], [0.0f64; 3], 0usize);
    let mut bad_pixels = 0usize;
    for (t, r) in test.iter().zip(reference) {
        let t_ok = t.iter().all(|v| v.is_finite());
        if !t_ok {
            bad_pixels += 1;
        }
        if t_ok && r.iter().all(|v| v.is_finite()) {
            for c in 0..3 {
                sum_t[c] += f64::from(t[c]);
                sum_r[c] += f64::from(r[c]);
            }
            n += 1;
        }
    }
    let n = n.max(1) as f64;
    Ok(Comparison {
        width,
        height,
        rel_mse: stats.rel_mse,
        mse: stats.mse,
        mean_test: sum_t.map(|s| s / n),
        mean_ref: sum_r.map(|s| s / n),
        non_finite_values: stats.non_finite,
        non_finite_pixels: bad_pixels,
    })
}

/// Reads one layer of an EXR file.
fn read_layer(path: &Path, layer: Option<&str>) -> Result<(u32, u32, Vec<[f32; 3]>)> {
    let img = imageio::read_exr(path).with_context(|| format!("reading {}", path.display()))?;
    let found = match layer {
        Some(name) => img.layer(name).with_context(|| {
            let names: Vec<&str> = img.layers.iter().map(|l| l.name.as_str()).collect();
            format!(
                "{}: no layer `{name}` (layers: {})",
                path.display(),
                names.join(", ")
            )
        })?,
        None => img
            .main_layer()
            .with_context(|| format!("{}: no colour layer", path.display()))?,
    };
    Ok((img.width, img.height, found.data.clone()))
}

/// Runs `cvfarm compare`.
pub fn run(args: &CompareArgs) -> Result<ExitCode> {
    if let Some(max) = args.max_rel_mse
        && (max.is_nan() || max < 0.0)
    {
        bail!("--max-rel-mse must be a number ≥ 0, got {max}");
    }
    let (tw, th, test) = read_layer(&args.test, args.layer.as_deref())?;
    let (rw, rh, reference) = read_layer(&args.reference, args.layer.as_deref())?;
    let cmp = compare_images((tw, th), &test, (rw, rh), &reference).with_context(|| {
        format!(
            "comparing {} with {}",
            args.test.display(),
            args.reference.display()
        )
    })?;
    if args.json {
        println!("{}", cmp.to_json());
    } else {
        let r = cmp.mean_ratio();
        println!("relMSE      {:.6e}   (ε = {REL_MSE_EPSILON})", cmp.rel_mse);
        println!("MSE         {:.6e}", cmp.mse);
        println!(
            "mean ratio  R {:.5}  G {:.5}  B {:.5}   (test/ref)",
            r[0], r[1], r[2]
        );
        println!(
            "non-finite  {} values in {} of {} pixels",
            cmp.non_finite_values,
            cmp.non_finite_pixels,
            u64::from(cmp.width) * u64::from(cmp.height)
        );
    }
    if let Some(max) = args.max_rel_mse
        && (cmp.non_finite_values > 0 || cmp.rel_mse.is_nan() || cmp.rel_mse > max)
    {
        eprintln!(
            "error: {} is too different from {}: relMSE {:.6e} (limit {max:e}), {} non-finite values",
            args.test.display(),
            args.reference.display(),
            cmp.rel_mse,
            cmp.non_finite_values
        );
        return Ok(ExitCode::from(EXIT_TOO_DIFFERENT));
    }
    Ok(ExitCode::SUCCESS)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn identical_images_compare_equal() {
        let img = vec![[0.5f32, 1.0, 0.0], [2.0, 0.1, 0.3]];
        let c = compare_images((2, 1), &img, (2, 1), &img).unwrap();
        assert_eq!((c.rel_mse, c.mse, c.non_finite_values), (0.0, 0.0, 0));
        assert_eq!(c.mean_ratio()[0], 1.0);
        assert!(c.mean_ratio()[2].is_finite());
    }

    #[test]
    fn different_sizes_are_an_error() {
        let img = vec![[0.5f32; 3]; 4];
        let e = compare_images((2, 2), &img, (4, 1), &img).unwrap_err();
        assert!(e.to_string().contains("different sizes"), "{e}");
    }

    #[test]
    fn nan_pixels_are_counted_and_excluded_from_means() {
        let test = vec![[f32::NAN, 1.0, 1.0], [2.0, 2.0, 2.0]];
        let reference = vec![[1.0f32; 3], [1.0; 3]];
        let c = compare_images((2, 1), &test, (2, 1), &reference).unwrap();
        assert_eq!((c.non_finite_values, c.non_finite_pixels), (1, 1));
        assert_eq!(c.mean_ratio(), [2.0, 2.0, 2.0]);
        // relMSE over the 5 finite values: (0 + 0 + 1 + 1 + 1) / 1.01 / 5
        assert!((c.rel_mse - 3.0 / 1.01 / 5.0).abs() < 1e-12);
        assert!(c.to_json()["mean_ratio"][0].as_f64().is_some());
    }

    #[test]
    fn black_reference_channel_gives_null_ratio_in_json() {
        let test = vec![[1.0f32, 0.0, 0.0]];
        let reference = vec![[1.0f32, 0.0, 0.0]];
        let c = compare_images((1, 1), &test, (1, 1), &reference).unwrap();
        assert!(c.to_json()["mean_ratio"][1].is_null());
    }
}
