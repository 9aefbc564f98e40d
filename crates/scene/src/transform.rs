//! [`TransformDesc`] → matrix, with validation that names the offending operation.
//!
//! Semantics (Mitsuba's `<transform>`): the operations are applied in list order, each one
//! **left-multiplying** the matrix so far, so `[scale, rotate, translate]` scales first.
//! `rotate` is right-handed about the (normalised) axis, angle in degrees; `look_at` builds the
//! frame with columns (left, up, dir, origin) where dir = normalize(target − origin),
//! left = normalize(up × dir), up' = dir × left — Mitsuba's `Transform4f::look_at`; `matrix` is
//! row-major and must be affine (last row 0 0 0 1).

use glam::{Mat3, Mat4, Vec3, Vec4};

use crate::SceneError;
use crate::desc::{TransformDesc, TransformOp};

fn finite3(v: [f32; 3]) -> bool {
    v.iter().all(|x| x.is_finite())
}

/// The matrix of `ops`; `path` names the transform in errors (e.g. `shapes[3].transform`).
pub fn to_matrix(ops: &TransformDesc, path: &str) -> Result<Mat4, SceneError> {
    let mut m = Mat4::IDENTITY;
    for (i, op) in ops.iter().enumerate() {
        let at = |field: &str| format!("{path}[{i}].{field}");
        let step = match op {
            TransformOp::Translate(t) => {
                if !finite3(*t) {
                    return Err(SceneError::invalid(at("translate"), "non-finite value"));
                }
                Mat4::from_translation(Vec3::from(*t))
            }
            TransformOp::Scale(s) => {
                if !finite3(*s) {
                    return Err(SceneError::invalid(at("scale"), "non-finite value"));
                }
                Mat4::from_scale(Vec3::from(*s))
            }
            TransformOp::Rotate { axis, angle } => {
                if !finite3(*axis) {
                    return Err(SceneError::invalid(at("rotate.axis"), "non-finite value"));
                }
                if !angle.is_finite() {
                    return Err(SceneError::invalid(at("rotate.angle"), "non-finite value"));
                }
                let a = Vec3::from(*axis);
                if a.length_squared() <= 1e-20 {
                    return Err(SceneError::invalid(at("rotate.axis"), "zero vector"));
                }
                Mat4::from_axis_angle(a.normalize(), angle.to_radians())
            }
            TransformOp::LookAt { origin, target, up } => {
                for (name, v) in [("origin", origin), ("target", target), ("up", up)] {
                    if !finite3(*v) {
                        return Err(SceneError::invalid(
                            at(&format!("look_at.{name}")),
                            "non-finite value",
                        ));
                    }
                }
                look_at(Vec3::from(*origin), Vec3::from(*target), Vec3::from(*up))
                    .map_err(|msg| SceneError::invalid(at("look_at"), msg))?
            }
            TransformOp::Matrix(v) => {
                if v.iter().any(|x| !x.is_finite()) {
                    return Err(SceneError::invalid(at("matrix"), "non-finite value"));
                }
                let row_major = Mat4::from_cols_array(v);
                let mat = row_major.transpose();
                if mat.row(3) != Vec4::new(0.0, 0.0, 0.0, 1.0) {
                    return Err(SceneError::invalid(
                        at("matrix"),
                        "projective matrices are not supported (last row must be 0 0 0 1)",
                    ));
                }
                mat
            }
        };
        m = step * m;
    }
    if !m.is_finite() {
        return Err(SceneError::invalid(
            path,
            "transform overflows to a non-finite matrix",
        ));
    }
    Ok(m)
}

/// Mitsuba's look-at frame (camera-style: +Z towards the target, +X left).
pub fn look_at(origin: Vec3, target: Vec3, up: Vec3) -> Result<Mat4, &'static str> {
    let d = target - origin;
    if d.length_squared() <= 1e-30 {
        return Err("origin and target coincide");
    }
    let dir = d.normalize();
    let l = up.cross(dir);
    if l.length_squared() <= 1e-12 * up.length_squared().max(1e-30) || up.length_squared() == 0.0 {
        return Err("up is zero or parallel to the view direction");
    }
    let left = l.normalize();
    let new_up = dir.cross(left);
    Ok(Mat4::from_cols(
        left.extend(0.0),
        new_up.extend(0.0),
        dir.extend(0.0),
        origin.extend(1.0),
    ))
}

/// The inverse-transpose of the linear part: how normals transform. `None` if singular.
pub fn normal_matrix(m: &Mat4) -> Option<Mat3> {
    let l = Mat3::from_mat4(*m);
    let det = l.determinant();
    if !det.is_finite() || det.abs() < 1e-30 {
        return None;
    }
    Some(l.inverse().transpose())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn operations_left_multiply_in_order() {
        let ops = vec![
            TransformOp::Scale([2.0, 2.0, 2.0]),
            TransformOp::Rotate {
                axis: [0.0, 1.0, 0.0],
                angle: 90.0,
            },
            TransformOp::Translate([1.0, 0.0, 0.0]),
        ];
        let m = to_matrix(&ops, "t").unwrap();
        // (1,0,0) -> scale (2,0,0) -> rotate +90° about y: (0,0,-2) -> translate (1,0,-2)
        let p = m.transform_point3(Vec3::X);
        assert!((p - Vec3::new(1.0, 0.0, -2.0)).length() < 1e-5, "{p}");
    }

    #[test]
    fn look_at_matches_mitsuba_frame() {
        // Mitsuba: camera at (0,1,3.9) looking at (0,1,0): +Z maps to -z world, +X (left) to -x world.
        let m = look_at(Vec3::new(0.0, 1.0, 3.9), Vec3::new(0.0, 1.0, 0.0), Vec3::Y).unwrap();
        assert!((m.transform_vector3(Vec3::Z) - Vec3::NEG_Z).length() < 1e-6);
        assert!((m.transform_vector3(Vec3::X) - Vec3::NEG_X).length() < 1e-6);
        assert!((m.transform_vector3(Vec3::Y) - Vec3::Y).length() < 1e-6);
        assert!(look_at(Vec3::ZERO, Vec3::Y, Vec3::Y).is_err());
        assert!(look_at(Vec3::ZERO, Vec3::ZERO, Vec3::Y).is_err());
    }

    #[test]
    fn errors_name_the_operation() {
        let ops = vec![
            TransformOp::Translate([0.0; 3]),
            TransformOp::Rotate {
                axis: [0.0; 3],
                angle: 10.0,
            },
        ];
        let e = to_matrix(&ops, "shapes[3].transform")
            .unwrap_err()
            .to_string();
        assert_eq!(e, "shapes[3].transform[1].rotate.axis: zero vector");
        let ops = vec![TransformOp::Translate([f32::NAN, 0.0, 0.0])];
        let e = to_matrix(&ops, "camera.transform").unwrap_err().to_string();
        assert!(e.starts_with("camera.transform[0].translate"), "{e}");
    }

    #[test]
    fn matrix_is_row_major() {
        let mut v = [0.0f32; 16];
        v[0] = 1.0;
        v[5] = 1.0;
        v[10] = 1.0;
        v[15] = 1.0;
        v[3] = 5.0; // row 0, column 3: x translation
        let m = to_matrix(&vec![TransformOp::Matrix(v)], "m").unwrap();
        assert_eq!(m.transform_point3(Vec3::ZERO), Vec3::new(5.0, 0.0, 0.0));
        v[12] = 1.0; // projective row
        assert!(to_matrix(&vec![TransformOp::Matrix(v)], "m").is_err());
    }
}
