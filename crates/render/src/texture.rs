//! Texture lookups with Mitsuba 3's conventions (`bitmap` and `checkerboard` plugins).
//!
//! | type | parameters | lookup at (u, v) |
//! |---|---|---|
//! | `bitmap` | `filename`, `raw`, `filter` (`bilinear`\|`nearest`), `wrap` (`repeat`\|`mirror`\|`clamp`), `uv_transform` | (u', v') = T·(u, v); texel row 0 (the **top** row of the image) is at v' = 0, column 0 at u' = 0 |
//! | `checkerboard` | `color0` (0.4), `color1` (0.2), `uv_transform` | (u', v') = T·(u, v); `color0` where (frac(u') > ½) == (frac(v') > ½), else `color1` |
//!
//! ```json
//! "textures": { "wood": { "type": "bitmap", "filename": "wood.png", "filter": "bilinear", "wrap": "repeat",
//!                         "uv_transform": [ { "scale": [4, 4, 1] } ] } }
//! ```
//!
//! Bitmap sampling (as Dr.Jit's `Texture` that Mitsuba uses): with a W×H image,
//! - `nearest`: texel (⌊u'W⌋, ⌊v'H⌋), wrapped;
//! - `bilinear`: continuous position (u'W − ½, v'H − ½); the four surrounding texel indices are
//!   wrapped independently, weights are the fractional parts.
//!
//! Wrap modes act on integer texel indices: `repeat` is i mod n, `clamp` is clamp(i, 0, n−1),
//! `mirror` reflects with period 2n (… 1 0 | 0 1 … n−1 | n−1 n−2 …).
//!
//! Colours are linear RGB; the scene loader has already converted sRGB images.

use glam::{Vec2, Vec3};
use scene::{Color, RgbImage, Texture, TextureFilter, TextureWrap};

/// Evaluate a colour parameter at texture coordinates `uv`. A texture id out of range (never
/// present in a validated scene) evaluates to black.
#[inline]
pub fn eval_color(color: &Color, textures: &[Texture], uv: Vec2) -> Vec3 {
    match color {
        Color::Rgb(c) => *c,
        Color::Texture(id) => textures
            .get(*id as usize)
            .map_or(Vec3::ZERO, |t| eval_texture(t, uv)),
    }
}

/// Evaluate one texture at `uv`.
#[inline]
pub fn eval_texture(texture: &Texture, uv: Vec2) -> Vec3 {
    match texture {
        Texture::Bitmap {
            image,
            filter,
            wrap,
            uv_transform,
        } => {
            let p = uv_transform.transform_point2(uv);
            match filter {
                TextureFilter::Nearest => nearest(image, *wrap, p),
                TextureFilter::Bilinear => bilinear(image, *wrap, p),
            }
        }
        Texture::Checkerboard {
            color0,
            color1,
            uv_transform,
        } => {
            let p = uv_transform.transform_point2(uv);
            let fu = p.x - p.x.floor() > 0.5;
            let fv = p.y - p.y.floor() > 0.5;
            if fu == fv { *color0 } else { *color1 }
        }
    }
}

/// Mean of a colour parameter over channels (and texels / area for textures): Mitsuba's
/// `Texture::mean()`, used for rough plastic's specular sampling weight.
pub fn mean_color(color: &Color, textures: &[Texture]) -> f32 {
    let c = match color {
        Color::Rgb(c) => *c,
        Color::Texture(id) => match textures.get(*id as usize) {
            Some(Texture::Bitmap { image, .. }) => {
                let sum: glam::DVec3 = image.data.iter().map(|t| t.as_dvec3()).sum();
                (sum / image.data.len().max(1) as f64).as_vec3()
            }
            Some(Texture::Checkerboard { color0, color1, .. }) => 0.5 * (*color0 + *color1),
            None => Vec3::ZERO,
        },
    };
    (c.x + c.y + c.z) / 3.0
}

/// Wrap an integer texel index into [0, n).
#[inline]
fn wrap_index(i: i64, n: u32, wrap: TextureWrap) -> usize {
    let n = n.max(1) as i64;
    let j = match wrap {
        TextureWrap::Repeat => i.rem_euclid(n),
        TextureWrap::Clamp => i.clamp(0, n - 1),
        TextureWrap::Mirror => {
            let k = i.rem_euclid(2 * n);
            if k < n { k } else { 2 * n - 1 - k }
        }
    };
    j as usize
}

#[inline]
fn texel(image: &RgbImage, x: i64, y: i64, wrap: TextureWrap) -> Vec3 {
    let xi = wrap_index(x, image.width, wrap);
    let yi = wrap_index(y, image.height, wrap);
    image
        .data
        .get(yi * image.width as usize + xi)
        .copied()
        .unwrap_or(Vec3::ZERO)
}

/// Float → integer texel coordinate, saturating (NaN → 0) so that huge UVs cannot misbehave.
#[inline]
fn to_index(x: f32) -> i64 {
    x.floor().clamp(-1e15, 1e15) as i64
}

#[inline]
fn nearest(image: &RgbImage, wrap: TextureWrap, p: Vec2) -> Vec3 {
    texel(
        image,
        to_index(p.x * image.width as f32),
        to_index(p.y * image.height as f32),
        wrap,
    )
}

#[inline]
fn bilinear(image: &RgbImage, wrap: TextureWrap, p: Vec2) -> Vec3 {
    let x = p.x * image.width as f32 - 0.5;
    let y = p.y * image.height as f32 - 0.5;
    let (x0, y0) = (x.floor(), y.floor());
    let (fx, fy) = (x - x0, y - y0);
    let (fx, fy) = (
        if fx.is_finite() { fx } else { 0.0 },
        if fy.is_finite() { fy } else { 0.0 },
    );
    let (ix, iy) = (to_index(x0), to_index(y0));
    let c00 = texel(image, ix, iy, wrap);
    let c10 = texel(image, ix + 1, iy, wrap);
    let c01 = texel(image, ix, iy + 1, wrap);
    let c11 = texel(image, ix + 1, iy + 1, wrap);
    (c00 * (1.0 - fx) + c10 * fx) * (1.0 - fy) + (c01 * (1.0 - fx) + c11 * fx) * fy
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Affine2;

    /// 2×2 image: top row red, green; bottom row blue, white.
    fn image() -> RgbImage {
        RgbImage {
            width: 2,
            height: 2,
            data: vec![Vec3::X, Vec3::Y, Vec3::Z, Vec3::ONE],
        }
    }

    fn bitmap(filter: TextureFilter, wrap: TextureWrap) -> Texture {
        Texture::Bitmap {
            image: image(),
            filter,
            wrap,
            uv_transform: Affine2::IDENTITY,
        }
    }

    #[test]
    fn nearest_v0_is_top_row() {
        let t = bitmap(TextureFilter::Nearest, TextureWrap::Repeat);
        assert_eq!(eval_texture(&t, Vec2::new(0.1, 0.1)), Vec3::X);
        assert_eq!(eval_texture(&t, Vec2::new(0.9, 0.1)), Vec3::Y);
        assert_eq!(eval_texture(&t, Vec2::new(0.1, 0.9)), Vec3::Z);
        assert_eq!(eval_texture(&t, Vec2::new(0.9, 0.9)), Vec3::ONE);
        // Repeat: u = 1.1 is u = 0.1.
        assert_eq!(eval_texture(&t, Vec2::new(1.1, -0.9)), Vec3::X);
    }

    #[test]
    fn bilinear_interpolates_between_texel_centres() {
        let t = bitmap(TextureFilter::Bilinear, TextureWrap::Clamp);
        // Texel centres reproduce texels.
        assert!((eval_texture(&t, Vec2::new(0.25, 0.25)) - Vec3::X).length() < 1e-6);
        // Midpoint of the image: average of all four.
        let mid = eval_texture(&t, Vec2::new(0.5, 0.5));
        assert!((mid - (Vec3::X + Vec3::Y + Vec3::Z + Vec3::ONE) / 4.0).length() < 1e-6);
        // Clamp: beyond the left edge equals the edge texel column.
        assert!((eval_texture(&t, Vec2::new(-3.0, 0.25)) - Vec3::X).length() < 1e-6);
        // Repeat: at u = 0 the left column blends with the right one (wrapped).
        let r = eval_texture(
            &bitmap(TextureFilter::Bilinear, TextureWrap::Repeat),
            Vec2::new(0.0, 0.25),
        );
        assert!((r - 0.5 * (Vec3::X + Vec3::Y)).length() < 1e-6);
        // Mirror: at u = 0 the left column meets itself.
        let m = eval_texture(
            &bitmap(TextureFilter::Bilinear, TextureWrap::Mirror),
            Vec2::new(0.0, 0.25),
        );
        assert!((m - Vec3::X).length() < 1e-6);
    }

    #[test]
    fn mirror_wrap_indices() {
        let got: Vec<usize> = (-4..6)
            .map(|i| wrap_index(i, 3, TextureWrap::Mirror))
            .collect();
        assert_eq!(got, vec![2, 2, 1, 0, 0, 1, 2, 2, 1, 0]);
        assert_eq!(wrap_index(-1, 3, TextureWrap::Repeat), 2);
        assert_eq!(wrap_index(7, 3, TextureWrap::Clamp), 2);
    }

    #[test]
    fn checkerboard_follows_mitsuba_rule() {
        let t = Texture::Checkerboard {
            color0: Vec3::ONE,
            color1: Vec3::ZERO,
            uv_transform: Affine2::IDENTITY,
        };
        assert_eq!(eval_texture(&t, Vec2::new(0.25, 0.25)), Vec3::ONE);
        assert_eq!(eval_texture(&t, Vec2::new(0.75, 0.75)), Vec3::ONE);
        assert_eq!(eval_texture(&t, Vec2::new(0.75, 0.25)), Vec3::ZERO);
        assert_eq!(eval_texture(&t, Vec2::new(0.25, 0.75)), Vec3::ZERO);
        // Exactly 0.5 is not "> 0.5".
        assert_eq!(eval_texture(&t, Vec2::new(0.5, 0.1)), Vec3::ONE);
        let scaled = Texture::Checkerboard {
            color0: Vec3::ONE,
            color1: Vec3::ZERO,
            uv_transform: Affine2::from_scale(Vec2::splat(4.0)),
        };
        assert_eq!(
            eval_texture(&scaled, Vec2::new(0.25 / 4.0 + 0.125, 0.01)),
            Vec3::ZERO
        );
    }

    #[test]
    fn non_finite_uv_does_not_panic() {
        for f in [TextureFilter::Nearest, TextureFilter::Bilinear] {
            for w in [TextureWrap::Repeat, TextureWrap::Mirror, TextureWrap::Clamp] {
                let t = bitmap(f, w);
                for uv in [Vec2::NAN, Vec2::splat(f32::INFINITY), Vec2::splat(-1e30)] {
                    let _ = eval_texture(&t, uv);
                }
            }
        }
        assert_eq!(eval_color(&Color::Texture(99), &[], Vec2::ZERO), Vec3::ZERO);
    }
}
