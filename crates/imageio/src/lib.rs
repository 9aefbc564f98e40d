//! Image files for cvfarm: multi-layer OpenEXR read/write, PNG/JPEG decode, PNG preview.
//!
//! Every function here is total on bad input: a truncated or corrupt file gives an
//! [`ImageError`], never a panic (the EXR decoder is additionally run under
//! `catch_unwind`, because a third-party decoder bug must not take a worker down).
//!
//! # Layout
//! - [`exr`](crate::write_exr) functions: [`write_exr`], [`encode_exr`], [`read_exr`],
//!   [`read_exr_bytes`] — linear RGB float images with named layers.
//! - LDR functions: [`decode_ldr`] (PNG/JPEG → raw 0..1 values), [`srgb_to_linear`],
//!   [`linear_to_srgb`], [`write_png_preview`], [`encode_png_preview`].
//!
//! # Layers in an EXR file
//! A cvfarm EXR is a **single-part** scan-line file with 32-bit float channels (ZIP
//! compression). The layer named [`BEAUTY`] is written as the plain channels `R`, `G`, `B`, so
//! any viewer or `OpenEXR.File(path).channels()["RGB"]` shows it; every other layer `name` is
//! written as channels `name.R`, `name.G`, `name.B` (the OpenEXR naming convention for layers in
//! one part). Reading reverses this: channels without a `.` prefix form the layer `beauty`,
//! `prefix.R/G/B` form layer `prefix`; a group with only `Y` is read as grey; groups without
//! colour channels (e.g. only `A` or `Z`) are skipped. Multi-part files are read too: a part's
//! name is prepended to its layer names (`part.layer`, or `part` for its default layer).
//!
//! Pixels are row-major, top row first (EXR's increasing-y order).

#![deny(missing_docs)]

use image::ImageEncoder;
use std::collections::BTreeMap;
use std::io::Cursor;
use std::path::{Path, PathBuf};

use exr::prelude::{
    AnyChannel, AnyChannels, Encoding, FlatSamples, Image, Layer, LayerAttributes, ReadChannels,
    ReadLayers, SmallVec, Vec2, WritableImage,
};

/// Name of the default (unprefixed `R`, `G`, `B`) layer of an EXR file.
pub const BEAUTY: &str = "beauty";

/// Largest image (in pixels) the readers accept; larger headers are treated as corrupt
/// rather than allocating gigabytes on a hostile file.
pub const MAX_PIXELS: u64 = 1 << 28;

/// Errors of this crate.
#[derive(Debug, thiserror::Error)]
pub enum ImageError {
    /// The file could not be read or written.
    #[error("{path}: {source}")]
    Io {
        /// File concerned.
        path: PathBuf,
        /// Underlying error.
        source: std::io::Error,
    },
    /// The bytes are not a valid (or supported) EXR file.
    #[error("invalid EXR: {0}")]
    Exr(String),
    /// The bytes are not a valid PNG or JPEG file.
    #[error("invalid PNG/JPEG image: {0}")]
    Ldr(String),
    /// The EXR file has no R/G/B (or Y) channels.
    #[error("EXR has no RGB or Y channels (channels: {channels})")]
    NoColorChannels {
        /// Comma-separated channel names found.
        channels: String,
    },
    /// The image is larger than [`MAX_PIXELS`] or has a zero size.
    #[error("unsupported image size {width}x{height}")]
    BadSize {
        /// Width in pixels.
        width: u64,
        /// Height in pixels.
        height: u64,
    },
    /// The caller passed inconsistent data (layer size, duplicate or bad layer name).
    #[error("invalid input: {0}")]
    InvalidInput(String),
}

/// One named RGB layer, `width * height` pixels, row-major, top row first.
#[derive(Clone, Debug, PartialEq)]
pub struct RgbLayer {
    /// Layer name (`beauty` is the default layer; no `.` allowed when writing).
    pub name: String,
    /// Linear RGB pixels.
    pub data: Vec<[f32; 3]>,
}

/// A decoded EXR image: all colour layers, same size.
#[derive(Clone, Debug, PartialEq)]
pub struct ExrImage {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Colour layers in file order (the default layer, if present, is named [`BEAUTY`] and first).
    pub layers: Vec<RgbLayer>,
}

impl ExrImage {
    /// The layer called `name`, if present.
    pub fn layer(&self, name: &str) -> Option<&RgbLayer> {
        self.layers.iter().find(|l| l.name == name)
    }

    /// The `beauty` layer, or the first layer when there is none of that name.
    pub fn main_layer(&self) -> Option<&RgbLayer> {
        self.layer(BEAUTY).or_else(|| self.layers.first())
    }
}

// ---------------------------------------------------------------------------------------------
// EXR writing

fn check_layers(width: u32, height: u32, layers: &[RgbLayer]) -> Result<(), ImageError> {
    let n = u64::from(width) * u64::from(height);
    if n == 0 || n > MAX_PIXELS {
        return Err(ImageError::BadSize {
            width: width.into(),
            height: height.into(),
        });
    }
    if layers.is_empty() {
        return Err(ImageError::InvalidInput("no layers to write".into()));
    }
    let mut seen = std::collections::BTreeSet::new();
    for layer in layers {
        if layer.name.is_empty() || layer.name.contains('.') {
            return Err(ImageError::InvalidInput(format!(
                "layer name {:?} must be non-empty and contain no '.'",
                layer.name
            )));
        }
        if !seen.insert(layer.name.as_str()) {
            return Err(ImageError::InvalidInput(format!(
                "duplicate layer {:?}",
                layer.name
            )));
        }
        if layer.data.len() as u64 != n {
            return Err(ImageError::InvalidInput(format!(
                "layer {:?} has {} pixels, expected {width}x{height} = {n}",
                layer.name,
                layer.data.len()
            )));
        }
    }
    Ok(())
}

fn build_exr_image(
    width: u32,
    height: u32,
    layers: &[RgbLayer],
) -> Image<Layer<AnyChannels<FlatSamples>>> {
    let mut list: SmallVec<[AnyChannel<FlatSamples>; 4]> = SmallVec::new();
    for layer in layers {
        let prefix = if layer.name == BEAUTY {
            String::new()
        } else {
            format!("{}.", layer.name)
        };
        for (c, suffix) in ["R", "G", "B"].iter().enumerate() {
            let samples: Vec<f32> = layer.data.iter().map(|p| p[c]).collect();
            let name = format!("{prefix}{suffix}");
            list.push(AnyChannel::new(name.as_str(), FlatSamples::F32(samples)));
        }
    }
    let size = Vec2(width as usize, height as usize);
    let layer = Layer::new(
        size,
        LayerAttributes::default(),
        Encoding::SMALL_LOSSLESS,
        AnyChannels::sort(list),
    );
    Image::from_layer(layer)
}

/// Encodes `layers` (each `width * height` pixels) as one single-part EXR file in memory.
/// See the crate docs for the channel naming.
pub fn encode_exr(width: u32, height: u32, layers: &[RgbLayer]) -> Result<Vec<u8>, ImageError> {
    check_layers(width, height, layers)?;
    let image = build_exr_image(width, height, layers);
    let mut out = Cursor::new(Vec::new());
    image
        .write()
        .non_parallel()
        .to_buffered(&mut out)
        .map_err(|e| ImageError::Exr(e.to_string()))?;
    Ok(out.into_inner())
}

/// Writes `layers` as one multi-layer EXR file at `path` (see the crate docs).
pub fn write_exr(
    path: impl AsRef<Path>,
    width: u32,
    height: u32,
    layers: &[RgbLayer],
) -> Result<(), ImageError> {
    let bytes = encode_exr(width, height, layers)?;
    std::fs::write(path.as_ref(), bytes).map_err(|source| ImageError::Io {
        path: path.as_ref().to_path_buf(),
        source,
    })
}

// ---------------------------------------------------------------------------------------------
// EXR reading

/// Reads an EXR file (see [`read_exr_bytes`]).
pub fn read_exr(path: impl AsRef<Path>) -> Result<ExrImage, ImageError> {
    let bytes = std::fs::read(path.as_ref()).map_err(|source| ImageError::Io {
        path: path.as_ref().to_path_buf(),
        source,
    })?;
    read_exr_bytes(&bytes)
}

/// Decodes an EXR file held in memory: every colour layer of every part, as f32 linear RGB
/// (half and u32 channels are converted). All parts must have the same size.
pub fn read_exr_bytes(bytes: &[u8]) -> Result<ExrImage, ImageError> {
    // Check the header first so that a hostile size cannot trigger a huge allocation.
    let meta = exr::meta::MetaData::read_from_buffered(Cursor::new(bytes), false)
        .map_err(|e| ImageError::Exr(e.to_string()))?;
    for header in &meta.headers {
        let (w, h) = (header.layer_size.0 as u64, header.layer_size.1 as u64);
        if w == 0 || h == 0 || w * h > MAX_PIXELS {
            return Err(ImageError::BadSize {
                width: w,
                height: h,
            });
        }
    }
    let decoded = std::panic::catch_unwind(|| {
        exr::prelude::read()
            .no_deep_data()
            .largest_resolution_level()
            .all_channels()
            .all_layers()
            .all_attributes()
            .non_parallel()
            .from_buffered(Cursor::new(bytes))
    })
    .map_err(|_| ImageError::Exr("decoder panicked on corrupt data".into()))?
    .map_err(|e| ImageError::Exr(e.to_string()))?;

    let mut size: Option<(usize, usize)> = None;
    let mut layers = Vec::new();
    let mut all_channels = Vec::new();
    for part in &decoded.layer_data {
        let (w, h) = (part.size.0, part.size.1);
        match size {
            None => size = Some((w, h)),
            Some(s) if s != (w, h) => {
                return Err(ImageError::Exr(format!(
                    "parts of different sizes ({}x{} and {w}x{h})",
                    s.0, s.1
                )));
            }
            Some(_) => {}
        }
        let part_name = part.attributes.layer_name.as_ref().map(|t| t.to_string());
        // prefix -> (R, G, B, Y) channel indices
        let mut groups: BTreeMap<String, [Option<usize>; 4]> = BTreeMap::new();
        let mut order: Vec<String> = Vec::new();
        for (i, ch) in part.channel_data.list.iter().enumerate() {
            let name = ch.name.to_string();
            all_channels.push(name.clone());
            let (prefix, suffix) = match name.rfind('.') {
                Some(p) => (name[..p].to_string(), &name[p + 1..]),
                None => (String::new(), name.as_str()),
            };
            let slot = match suffix {
                "R" | "r" => 0,
                "G" | "g" => 1,
                "B" | "b" => 2,
                "Y" | "y" => 3,
                _ => continue,
            };
            if !groups.contains_key(&prefix) {
                order.push(prefix.clone());
            }
            groups.entry(prefix).or_default()[slot] = Some(i);
        }
        // The default layer first.
        order.sort_by_key(|p| !p.is_empty());
        for prefix in order {
            let slots = groups[&prefix];
            let pick = |i: usize| -> Vec<f32> {
                part.channel_data.list[i]
                    .sample_data
                    .values_as_f32()
                    .collect()
            };
            let data: Vec<[f32; 3]> = match slots {
                [Some(r), Some(g), Some(b), _] => {
                    let (r, g, b) = (pick(r), pick(g), pick(b));
                    r.iter()
                        .zip(&g)
                        .zip(&b)
                        .map(|((r, g), b)| [*r, *g, *b])
                        .collect()
                }
                [_, _, _, Some(y)] => pick(y).into_iter().map(|v| [v; 3]).collect(),
                _ => continue,
            };
            if data.len() != w * h {
                return Err(ImageError::Exr(format!(
                    "channel has {} samples, expected {}",
                    data.len(),
                    w * h
                )));
            }
            let name = match (&part_name, prefix.is_empty()) {
                (None, true) => BEAUTY.to_string(),
                (None, false) => prefix,
                (Some(p), true) => p.clone(),
                (Some(p), false) => format!("{p}.{prefix}"),
            };
            layers.push(RgbLayer { name, data });
        }
    }
    let Some((w, h)) = size else {
        return Err(ImageError::Exr("file has no parts".into()));
    };
    if layers.is_empty() {
        return Err(ImageError::NoColorChannels {
            channels: all_channels.join(", "),
        });
    }
    Ok(ExrImage {
        width: w as u32,
        height: h as u32,
        layers,
    })
}

// ---------------------------------------------------------------------------------------------
// LDR

/// Decodes a PNG or JPEG file (format sniffed from the bytes) to `(width, height, pixels)`,
/// pixels row-major top row first with the **raw** stored values scaled to 0..1 (8-bit / 255,
/// 16-bit / 65535; grey replicated, alpha dropped). No colour-space conversion: apply
/// [`srgb_to_linear`] for sRGB-encoded colour textures.
pub fn decode_ldr(bytes: &[u8]) -> Result<(u32, u32, Vec<[f32; 3]>), ImageError> {
    let reader = image::ImageReader::new(Cursor::new(bytes))
        .with_guessed_format()
        .map_err(|e| ImageError::Ldr(e.to_string()))?;
    let (w, h) = reader
        .into_dimensions()
        .map_err(|e| ImageError::Ldr(e.to_string()))?;
    let n = u64::from(w) * u64::from(h);
    if n == 0 || n > MAX_PIXELS {
        return Err(ImageError::BadSize {
            width: w.into(),
            height: h.into(),
        });
    }
    let img = image::ImageReader::new(Cursor::new(bytes))
        .with_guessed_format()
        .map_err(|e| ImageError::Ldr(e.to_string()))?
        .decode()
        .map_err(|e| ImageError::Ldr(e.to_string()))?;
    let rgb = img.to_rgb32f();
    let data = rgb.pixels().map(|p| p.0).collect();
    Ok((w, h, data))
}

/// The sRGB electro-optical transfer function (IEC 61966-2-1): encoded value in 0..1 →
/// linear value. Values outside 0..1 are extended symmetrically/linearly as the formula does.
pub fn srgb_to_linear(v: f32) -> f32 {
    if v <= 0.040_45 {
        v / 12.92
    } else {
        ((v + 0.055) / 1.055).powf(2.4)
    }
}

/// Inverse of [`srgb_to_linear`]: linear value → sRGB-encoded value (not clamped).
pub fn linear_to_srgb(v: f32) -> f32 {
    if v <= 0.003_130_8 {
        v * 12.92
    } else {
        1.055 * v.powf(1.0 / 2.4) - 0.055
    }
}

/// Encodes a preview PNG in memory: each channel clamped to 0..1 (NaN → 0), sRGB-encoded,
/// rounded to 8 bits.
pub fn encode_png_preview(
    width: u32,
    height: u32,
    rgb: &[[f32; 3]],
) -> Result<Vec<u8>, ImageError> {
    let n = u64::from(width) * u64::from(height);
    if n == 0 || n > MAX_PIXELS {
        return Err(ImageError::BadSize {
            width: width.into(),
            height: height.into(),
        });
    }
    if rgb.len() as u64 != n {
        return Err(ImageError::InvalidInput(format!(
            "{} pixels given for a {width}x{height} image",
            rgb.len()
        )));
    }
    let bytes: Vec<u8> = rgb
        .iter()
        .flat_map(|p| p.map(|v| (linear_to_srgb(v.clamp(0.0, 1.0)) * 255.0 + 0.5) as u8))
        .collect();
    // A preview is written once per job and downloaded rarely: fast deflate, not the
    // smallest file (the default level made it a visible share of a short farm job).
    let mut out = Vec::new();
    image::codecs::png::PngEncoder::new_with_quality(
        &mut out,
        image::codecs::png::CompressionType::Fast,
        image::codecs::png::FilterType::Adaptive,
    )
    .write_image(&bytes, width, height, image::ExtendedColorType::Rgb8)
    .map_err(|e| ImageError::Ldr(e.to_string()))?;
    Ok(out)
}

/// Writes a tonemapped preview PNG (see [`encode_png_preview`]).
pub fn write_png_preview(
    path: impl AsRef<Path>,
    width: u32,
    height: u32,
    rgb: &[[f32; 3]],
) -> Result<(), ImageError> {
    let bytes = encode_png_preview(width, height, rgb)?;
    std::fs::write(path.as_ref(), bytes).map_err(|source| ImageError::Io {
        path: path.as_ref().to_path_buf(),
        source,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ramp(w: u32, h: u32, k: f32) -> Vec<[f32; 3]> {
        (0..w * h)
            .map(|i| [i as f32 * k, 1.0 - i as f32, -(i as f32) * 1e-3 + 1e20])
            .collect()
    }

    #[test]
    fn exr_round_trip_multi_layer() {
        let (w, h) = (7, 5);
        let layers = vec![
            RgbLayer {
                name: BEAUTY.into(),
                data: ramp(w, h, 0.25),
            },
            RgbLayer {
                name: "variance".into(),
                data: ramp(w, h, 3.0),
            },
            RgbLayer {
                name: "albedo".into(),
                data: ramp(w, h, -1.5),
            },
        ];
        let bytes = encode_exr(w, h, &layers).unwrap();
        let img = read_exr_bytes(&bytes).unwrap();
        assert_eq!((img.width, img.height), (w, h));
        assert_eq!(img.layers.len(), 3);
        assert_eq!(img.layers[0].name, BEAUTY);
        for l in &layers {
            assert_eq!(img.layer(&l.name).unwrap().data, l.data, "layer {}", l.name);
        }
    }

    #[test]
    fn exr_rejects_bad_input() {
        let l = RgbLayer {
            name: "a.b".into(),
            data: vec![[0.0; 3]; 4],
        };
        assert!(matches!(
            encode_exr(2, 2, &[l]),
            Err(ImageError::InvalidInput(_))
        ));
        let l = RgbLayer {
            name: BEAUTY.into(),
            data: vec![[0.0; 3]; 3],
        };
        assert!(matches!(
            encode_exr(2, 2, &[l]),
            Err(ImageError::InvalidInput(_))
        ));
        assert!(matches!(
            encode_exr(0, 2, &[]),
            Err(ImageError::BadSize { .. })
        ));
    }

    #[test]
    fn truncated_exr_is_an_error_not_a_panic() {
        let layers = vec![RgbLayer {
            name: BEAUTY.into(),
            data: ramp(16, 16, 0.1),
        }];
        let bytes = encode_exr(16, 16, &layers).unwrap();
        for cut in [0, 1, 4, 8, 20, 100, bytes.len() / 2, bytes.len() - 1] {
            assert!(read_exr_bytes(&bytes[..cut]).is_err(), "cut at {cut}");
        }
        let mut corrupt = bytes.clone();
        for b in corrupt.iter_mut().skip(300).step_by(7) {
            *b ^= 0x5a;
        }
        let _ = read_exr_bytes(&corrupt); // must not panic; may or may not decode
    }

    #[test]
    fn png_preview_round_trip() {
        let px = vec![
            [0.0, 0.5, 1.0],
            [2.0, -1.0, f32::NAN],
            [0.214, 0.0031308, 0.9],
            [1.0; 3],
        ];
        let bytes = encode_png_preview(2, 2, &px).unwrap();
        let (w, h, back) = decode_ldr(&bytes).unwrap();
        assert_eq!((w, h), (2, 2));
        for (a, b) in px.iter().zip(&back) {
            for c in 0..3 {
                let want = if a[c].is_nan() {
                    0.0
                } else {
                    a[c].clamp(0.0, 1.0)
                };
                let got = srgb_to_linear(b[c]);
                // 8-bit quantisation: half a step in the encoded domain.
                assert!(
                    (linear_to_srgb(want) - b[c]).abs() <= 0.5 / 255.0 + 1e-6,
                    "{want} vs {got}"
                );
            }
        }
    }

    #[test]
    fn jpeg_decodes_to_raw_values() {
        // A flat grey JPEG: lossy, but a constant image survives within a couple of levels.
        let raw = image::RgbImage::from_pixel(16, 8, image::Rgb([128, 64, 200]));
        let mut jpeg = Cursor::new(Vec::new());
        raw.write_to(&mut jpeg, image::ImageFormat::Jpeg).unwrap();
        let (w, h, px) = decode_ldr(jpeg.get_ref()).unwrap();
        assert_eq!((w, h, px.len()), (16, 8, 128));
        for p in &px {
            for (got, want) in p.iter().zip([128.0f32, 64.0, 200.0]) {
                assert!((got * 255.0 - want).abs() <= 3.0, "{got}");
            }
        }
        let bytes = jpeg.into_inner();
        assert!(decode_ldr(&bytes[..bytes.len() / 3]).is_err());
    }

    #[test]
    fn truncated_png_is_an_error() {
        let bytes = encode_png_preview(4, 4, &[[0.3; 3]; 16]).unwrap();
        for cut in [0, 3, 10, 40, bytes.len() - 5] {
            assert!(decode_ldr(&bytes[..cut]).is_err(), "cut at {cut}");
        }
        assert!(decode_ldr(b"not an image at all").is_err());
    }

    #[test]
    fn srgb_curve_is_inverse_and_matches_known_values() {
        assert!((srgb_to_linear(0.5) - 0.214_041).abs() < 1e-5);
        assert_eq!(srgb_to_linear(0.0), 0.0);
        assert!((srgb_to_linear(1.0) - 1.0).abs() < 1e-6);
        for i in 0..=100 {
            let v = i as f32 / 100.0;
            assert!((linear_to_srgb(srgb_to_linear(v)) - v).abs() < 1e-5);
        }
    }
}
