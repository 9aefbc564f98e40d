//! Pinhole camera with Mitsuba 3's `perspective` conventions.
//!
//! - Camera space: looks along **+Z**, **+Y** up, **+X left** (so image x grows towards −X).
//! - `fov_x_deg` is the full horizontal field of view (the scene loader already converted
//!   Mitsuba's `fov_axis`); the vertical extent follows from the aspect ratio.
//! - Pixel (0, 0) is the top-left pixel; a film position `(x + u, y + v)` with `(u, v)` from
//!   the sampler is a uniformly distributed point in the pixel (box filter).
//! - Near clip as Mitsuba: the ray starts at `near_clip / d.z` along the camera-space unit
//!   direction `d`, and ends at `far_clip / d.z`.
//!
//! Rays are returned in world space with a unit direction.

use glam::{Mat4, Vec2, Vec3};

use crate::math::Ray;

/// A prepared perspective camera.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    to_world: Mat4,
    /// `to_world`'s inverse ([`Self::film_position`]).
    to_camera: Mat4,
    origin: Vec3,
    /// tan(fov_x / 2).
    tan_half_x: f32,
    /// tan(fov_y / 2).
    tan_half_y: f32,
    near_clip: f32,
    far_clip: f32,
    width: u32,
    height: u32,
}

impl Camera {
    /// Prepares the camera of a scene for an image of `film` size.
    pub fn new(camera: &scene::Camera, film: &scene::Film) -> Self {
        let tan_half_x = (camera.fov_x_deg.to_radians() * 0.5).tan();
        let aspect = film.width as f32 / film.height as f32;
        Self {
            to_world: camera.to_world,
            to_camera: camera.to_world.inverse(),
            origin: camera.to_world.transform_point3(Vec3::ZERO),
            tan_half_x,
            tan_half_y: tan_half_x / aspect,
            near_clip: camera.near_clip,
            far_clip: camera.far_clip,
            width: film.width,
            height: film.height,
        }
    }

    /// Image width in pixels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Image height in pixels.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// The camera position in world space.
    pub fn origin(&self) -> Vec3 {
        self.origin
    }

    /// The primary ray through film position `film_pos` (pixels, `(0,0)` = top-left corner of
    /// the image, `(width, height)` = bottom-right).
    #[inline]
    pub fn ray(&self, film_pos: Vec2) -> Ray {
        let sx = film_pos.x / self.width as f32;
        let sy = film_pos.y / self.height as f32;
        // +X is left: the left image border (sx = 0) is at +tan_half_x.
        let d_cam = Vec3::new(
            (1.0 - 2.0 * sx) * self.tan_half_x,
            (1.0 - 2.0 * sy) * self.tan_half_y,
            1.0,
        )
        .normalize();
        let inv_z = 1.0 / d_cam.z;
        let near_t = self.near_clip * inv_z;
        let far_t = self.far_clip * inv_z;
        let o_cam = d_cam * near_t;
        let o = self.to_world.transform_point3(o_cam);
        let d = self.to_world.transform_vector3(d_cam).normalize();
        // World-space length of the clipped segment (to_world may scale).
        let scale = self.to_world.transform_vector3(d_cam).length();
        Ray {
            o,
            d,
            t_max: (far_t - near_t) * scale,
        }
    }
}

impl Camera {
    /// The film position (pixels, as [`Self::ray`] takes them) that world point `p` projects
    /// to: the inverse of [`Self::ray`] along its ray. `None` for a point in or behind the
    /// camera's plane (or a non-finite one). Positions outside `[0, width) × [0, height)` are
    /// off the image.
    pub fn film_position(&self, p: Vec3) -> Option<Vec2> {
        let q = self.to_camera.transform_point3(p);
        if !q.is_finite() || q.z <= 0.0 {
            return None;
        }
        // `ray`: d_cam ∝ ((1 − 2 sx) · tan_half_x, (1 − 2 sy) · tan_half_y, 1).
        let sx = 0.5 * (1.0 - q.x / (q.z * self.tan_half_x));
        let sy = 0.5 * (1.0 - q.y / (q.z * self.tan_half_y));
        Some(Vec2::new(sx * self.width as f32, sy * self.height as f32))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cam(fov: f32, w: u32, h: u32, near: f32) -> Camera {
        Camera::new(
            &scene::Camera {
                to_world: Mat4::IDENTITY,
                fov_x_deg: fov,
                near_clip: near,
                far_clip: 1e4,
            },
            &scene::Film {
                width: w,
                height: h,
            },
        )
    }

    /// `film_position` inverts `ray`: points along the ray through a film position project
    /// back to it, under a scaling, rotating and translating `to_world`; points behind the
    /// camera have none.
    #[test]
    fn film_position_inverts_the_ray() {
        let (w, h) = (64, 48);
        let to_world = Mat4::from_scale_rotation_translation(
            Vec3::splat(2.0),
            glam::Quat::from_euler(glam::EulerRot::XYZ, 0.3, -1.1, 0.4),
            Vec3::new(1.0, -2.0, 3.0),
        );
        let c = Camera::new(
            &scene::Camera {
                to_world,
                fov_x_deg: 50.0,
                near_clip: 0.1,
                far_clip: 1e4,
            },
            &scene::Film {
                width: w,
                height: h,
            },
        );
        for (x, y) in [
            (0.0, 0.0),
            (32.0, 24.0),
            (63.9, 0.5),
            (10.25, 47.75),
            (-5.0, 60.0),
        ] {
            let f = Vec2::new(x, y);
            let r = c.ray(f);
            for t in [0.5, 3.0, 40.0] {
                let back = c.film_position(r.o + r.d * t).expect("in front");
                assert!((back - f).length() < 1e-3, "{f} -> {back} at t = {t}");
            }
            assert_eq!(c.film_position(c.origin() - r.d * 2.0), None);
        }
        assert_eq!(c.film_position(Vec3::NAN), None);
    }

    #[test]
    fn centre_ray_looks_along_plus_z_and_starts_at_near_clip() {
        let c = cam(60.0, 64, 32, 0.5);
        let r = c.ray(Vec2::new(32.0, 16.0));
        assert!((r.d - Vec3::Z).length() < 1e-6);
        assert!((r.o - Vec3::new(0.0, 0.0, 0.5)).length() < 1e-6);
    }

    #[test]
    fn left_image_border_is_plus_x_and_top_is_plus_y() {
        let c = cam(90.0, 100, 50, 0.0);
        let left = c.ray(Vec2::new(0.0, 25.0));
        // fov 90° ⇒ the left border direction is (1, 0, 1)/√2.
        assert!((left.d - Vec3::new(1.0, 0.0, 1.0).normalize()).length() < 1e-6);
        let top = c.ray(Vec2::new(50.0, 0.0));
        assert!(top.d.y > 0.0 && top.d.x.abs() < 1e-6);
        // Vertical half-extent tan = 0.5 for a 2:1 image.
        assert!((top.d.y / top.d.z - 0.5).abs() < 1e-6);
    }
}
