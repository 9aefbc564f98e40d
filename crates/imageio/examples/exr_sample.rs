//! Writes a small two-layer EXR (`beauty` + `variance`) to the path given as the first argument,
//! to check that other tools (e.g. Python's OpenEXR) read cvfarm's files.
fn main() -> Result<(), imageio::ImageError> {
    let path = std::env::args()
        .nth(1)
        .unwrap_or_else(|| "sample.exr".into());
    let (w, h) = (4u32, 3u32);
    let beauty = (0..w * h).map(|i| [i as f32, 0.5, 0.25]).collect();
    let variance = (0..w * h).map(|i| [0.01 * i as f32, 0.02, 0.03]).collect();
    imageio::write_exr(
        &path,
        w,
        h,
        &[
            imageio::RgbLayer {
                name: imageio::BEAUTY.into(),
                data: beauty,
            },
            imageio::RgbLayer {
                name: "variance".into(),
                data: variance,
            },
        ],
    )
}
