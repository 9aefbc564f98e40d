//! `SceneDesc` + assets → validated [`Scene`].
//!
//! Contract (what [`load`] guarantees, see [`crate::model`]): every number finite, indices in
//! range, camera transform invertible, `0 < fov < 180`, `0 < near < far`, every kept triangle
//! has a finite non-zero area, every emitter a positive finite area and finite radiance ≥ 0,
//! shading normals unit length, sphere transforms similarity transforms.
//!
//! Policy for **degenerate triangles** (zero or non-finite area after the transform): they are
//! dropped and counted per shape in [`LoadReport`] (UV spheres have them at the poles); a shape
//! left with no triangle is an error naming it. Vertex normals: the file's (transformed by the
//! inverse transpose), or — when the file has none and `face_normals` is false — smooth
//! angle-weighted normals computed in world space, as Mitsuba does; a mesh whose normals
//! cannot be normalised falls back to face normals with a warning.

use std::collections::BTreeMap;

use glam::{Affine2, Mat2, Mat3, Mat4, Vec2, Vec3};
use serde::Serialize;

use crate::desc::{
    ColorDesc, EnvironmentDesc, GeometryDesc, MaterialDesc, MaterialRef, SceneDesc, TextureDesc,
};
use crate::meshfile::{self, RawMesh};
use crate::model::*;
use crate::transform::{normal_matrix, to_matrix};
use crate::{AssetSource, SceneError};

/// Largest accepted film side in pixels.
pub const MAX_FILM_SIDE: u32 = 1 << 15;

/// A loaded scene and what the loader had to say about it.
#[derive(Clone, Debug)]
pub struct LoadedScene {
    /// The validated scene.
    pub scene: Scene,
    /// Dropped triangles and warnings.
    pub report: LoadReport,
}

/// Degenerate triangles dropped from one shape.
#[derive(Clone, Debug, PartialEq, Eq, Serialize)]
pub struct DroppedTriangles {
    /// Index into `SceneDesc::shapes`.
    pub shape: usize,
    /// Number of triangles dropped.
    pub count: usize,
}

/// What loading changed or noticed; serialisable so jobs can record it.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize)]
pub struct LoadReport {
    /// Total degenerate triangles dropped.
    pub dropped_triangles: usize,
    /// Per shape (only shapes that lost triangles).
    pub dropped_per_shape: Vec<DroppedTriangles>,
    /// Human-readable warnings (importer and loader).
    pub warnings: Vec<String>,
}

fn finite3(v: [f32; 3]) -> bool {
    v.iter().all(|x| x.is_finite())
}

fn check_rgb(v: [f32; 3], path: &str) -> Result<Vec3, SceneError> {
    if !finite3(v) {
        return Err(SceneError::invalid(path, "non-finite value"));
    }
    if v.iter().any(|x| *x < 0.0) {
        return Err(SceneError::invalid(path, "negative value"));
    }
    Ok(Vec3::from(v))
}

fn positive(x: f32, path: &str) -> Result<f32, SceneError> {
    if !x.is_finite() || x <= 0.0 {
        return Err(SceneError::invalid(
            path,
            format!("must be finite and > 0 (got {x})"),
        ));
    }
    Ok(x)
}

/// Reads an image asset as linear RGB: EXR as stored, PNG/JPEG through the sRGB curve unless `raw`.
fn load_image(assets: &dyn AssetSource, name: &str, raw: bool) -> Result<RgbImage, SceneError> {
    let bytes = assets.read(name)?;
    let img_err = |source| SceneError::Image {
        file: name.to_string(),
        source,
    };
    let is_exr = bytes.starts_with(&[0x76, 0x2f, 0x31, 0x01]);
    let (width, height, data) = if is_exr {
        let exr = imageio::read_exr_bytes(&bytes).map_err(img_err)?;
        let layer = exr.main_layer().ok_or_else(|| {
            img_err(imageio::ImageError::NoColorChannels {
                channels: String::new(),
            })
        })?;
        (
            exr.width,
            exr.height,
            layer
                .data
                .iter()
                .map(|p| Vec3::from(*p))
                .collect::<Vec<_>>(),
        )
    } else {
        let (w, h, px) = imageio::decode_ldr(&bytes).map_err(img_err)?;
        let conv = |v: f32| if raw { v } else { imageio::srgb_to_linear(v) };
        (
            w,
            h,
            px.iter()
                .map(|p| Vec3::new(conv(p[0]), conv(p[1]), conv(p[2])))
                .collect(),
        )
    };
    Ok(RgbImage {
        width,
        height,
        data,
    })
}

/// The 2-D affine map a uv transform applies to (u, v, 0, 1).
fn uv_affine(ops: &crate::desc::TransformDesc, path: &str) -> Result<Affine2, SceneError> {
    let m = to_matrix(ops, path)?;
    Ok(Affine2::from_mat2_translation(
        Mat2::from_cols(
            m.x_axis.truncate().truncate(),
            m.y_axis.truncate().truncate(),
        ),
        Vec2::new(m.w_axis.x, m.w_axis.y),
    ))
}

struct Loader<'a> {
    desc: &'a SceneDesc,
    assets: &'a dyn AssetSource,
    report: LoadReport,
    texture_ids: BTreeMap<String, TextureId>,
    material_ids: BTreeMap<String, MaterialId>,
    materials: Vec<Material>,
    default_material: Option<MaterialId>,
}

impl Loader<'_> {
    fn color(&self, c: &ColorDesc, path: &str) -> Result<Color, SceneError> {
        match c {
            ColorDesc::Rgb(v) => Ok(Color::Rgb(check_rgb(*v, path)?)),
            ColorDesc::Gray(g) => Ok(Color::Rgb(check_rgb([*g; 3], path)?)),
            ColorDesc::Texture { texture } => self
                .texture_ids
                .get(texture)
                .map(|id| Color::Texture(*id))
                .ok_or_else(|| SceneError::invalid(path, format!("unknown texture {texture:?}"))),
        }
    }

    fn material(&self, m: &MaterialDesc, path: &str) -> Result<Material, SceneError> {
        let sub = |f: &str| format!("{path}.{f}");
        Ok(match m {
            MaterialDesc::Diffuse { reflectance } => Material::Diffuse {
                reflectance: self.color(reflectance, &sub("reflectance"))?,
            },
            MaterialDesc::Conductor {
                eta,
                k,
                specular_reflectance,
            } => Material::Conductor {
                eta: check_rgb(*eta, &sub("eta"))?,
                k: check_rgb(*k, &sub("k"))?,
                specular_reflectance: self
                    .color(specular_reflectance, &sub("specular_reflectance"))?,
            },
            MaterialDesc::RoughConductor {
                distribution,
                alpha,
                eta,
                k,
                specular_reflectance,
            } => Material::RoughConductor {
                distribution: *distribution,
                alpha: positive(*alpha, &sub("alpha"))?,
                eta: check_rgb(*eta, &sub("eta"))?,
                k: check_rgb(*k, &sub("k"))?,
                specular_reflectance: self
                    .color(specular_reflectance, &sub("specular_reflectance"))?,
            },
            MaterialDesc::RoughPlastic {
                distribution,
                alpha,
                int_ior,
                ext_ior,
                diffuse_reflectance,
                specular_reflectance,
                nonlinear,
            } => {
                let eta =
                    positive(*int_ior, &sub("int_ior"))? / positive(*ext_ior, &sub("ext_ior"))?;
                if (eta - 1.0).abs() < 1e-6 {
                    return Err(SceneError::invalid(
                        sub("int_ior"),
                        "int_ior equals ext_ior: the coating would be invisible",
                    ));
                }
                Material::RoughPlastic {
                    distribution: *distribution,
                    alpha: positive(*alpha, &sub("alpha"))?,
                    eta,
                    diffuse_reflectance: self
                        .color(diffuse_reflectance, &sub("diffuse_reflectance"))?,
                    specular_reflectance: self
                        .color(specular_reflectance, &sub("specular_reflectance"))?,
                    nonlinear: *nonlinear,
                }
            }
            MaterialDesc::TwoSided { bsdf } => {
                if matches!(**bsdf, MaterialDesc::TwoSided { .. }) {
                    return Err(SceneError::invalid(sub("bsdf"), "twosided inside twosided"));
                }
                Material::TwoSided(Box::new(self.material(bsdf, &sub("bsdf"))?))
            }
        })
    }

    fn shape_material(
        &mut self,
        m: Option<&MaterialRef>,
        path: &str,
    ) -> Result<MaterialId, SceneError> {
        match m {
            Some(MaterialRef::Named(name)) => {
                self.material_ids.get(name).copied().ok_or_else(|| {
                    SceneError::invalid(
                        format!("{path}.material"),
                        format!("unknown material {name:?}"),
                    )
                })
            }
            Some(MaterialRef::Inline(desc)) => {
                let mat = self.material(desc, &format!("{path}.material"))?;
                self.materials.push(mat);
                Ok((self.materials.len() - 1) as MaterialId)
            }
            None => Ok(*self.default_material.get_or_insert_with(|| {
                self.materials.push(Material::Diffuse {
                    reflectance: Color::Rgb(Vec3::splat(0.5)),
                });
                (self.materials.len() - 1) as MaterialId
            })),
        }
    }

    fn raw_mesh(
        &self,
        g: &GeometryDesc,
        path: &str,
    ) -> Result<(RawMesh, bool, String), SceneError> {
        Ok(match g {
            GeometryDesc::Obj {
                filename,
                face_normals,
            } => {
                let bytes = self.assets.read(filename)?;
                (
                    meshfile::obj::parse(filename, &bytes)?,
                    *face_normals,
                    filename.clone(),
                )
            }
            GeometryDesc::Ply {
                filename,
                face_normals,
            } => {
                let bytes = self.assets.read(filename)?;
                (
                    meshfile::ply::parse(filename, &bytes)?,
                    *face_normals,
                    filename.clone(),
                )
            }
            GeometryDesc::Rectangle => (meshfile::rectangle(), false, "rectangle".into()),
            GeometryDesc::Cube => (meshfile::cube(), false, "cube".into()),
            GeometryDesc::Mesh {
                positions,
                indices,
                normals,
                uvs,
            } => {
                let n = positions.len();
                for (j, t) in indices.iter().enumerate() {
                    if t.iter().any(|&i| i as usize >= n) {
                        return Err(SceneError::invalid(
                            format!("{path}.indices[{j}]"),
                            format!("index out of range (mesh has {n} positions)"),
                        ));
                    }
                }
                if normals.as_ref().is_some_and(|v| v.len() != n) {
                    return Err(SceneError::invalid(
                        format!("{path}.normals"),
                        "length differs from positions",
                    ));
                }
                if uvs.as_ref().is_some_and(|v| v.len() != n) {
                    return Err(SceneError::invalid(
                        format!("{path}.uvs"),
                        "length differs from positions",
                    ));
                }
                let raw = RawMesh {
                    positions: positions.iter().map(|p| Vec3::from(*p)).collect(),
                    normals: normals
                        .as_ref()
                        .map(|v| v.iter().map(|p| Vec3::from(*p)).collect()),
                    uvs: uvs
                        .as_ref()
                        .map(|v| v.iter().map(|p| Vec2::from(*p)).collect()),
                    indices: indices.clone(),
                };
                (raw, false, "inline mesh".into())
            }
            GeometryDesc::Sphere { .. } => {
                return Err(SceneError::invalid(
                    path,
                    "internal: a sphere is not a triangle mesh",
                ));
            }
        })
    }

    fn sphere(
        &self,
        center: [f32; 3],
        radius: f32,
        to_world: Mat4,
        path: &str,
    ) -> Result<(Vec3, f32, Mat3), SceneError> {
        if !finite3(center) {
            return Err(SceneError::invalid(
                format!("{path}.center"),
                "non-finite value",
            ));
        }
        positive(radius, &format!("{path}.radius"))?;
        let m = to_world
            * Mat4::from_translation(Vec3::from(center))
            * Mat4::from_scale(Vec3::splat(radius));
        let l = Mat3::from_mat4(m);
        let cols = [l.x_axis, l.y_axis, l.z_axis];
        let lens = cols.map(Vec3::length);
        let r = lens[0];
        let similar = lens.iter().all(|x| (x - r).abs() <= 1e-4 * r)
            && cols[0].dot(cols[1]).abs() <= 1e-4 * r * r
            && cols[0].dot(cols[2]).abs() <= 1e-4 * r * r
            && cols[1].dot(cols[2]).abs() <= 1e-4 * r * r;
        if !similar {
            return Err(SceneError::invalid(
                format!("{path}.transform"),
                "a sphere allows only translation, rotation and uniform scale",
            ));
        }
        if !(r.is_finite() && r > 0.0) {
            return Err(SceneError::invalid(
                format!("{path}.radius"),
                "zero or non-finite world-space radius",
            ));
        }
        let frame = Mat3::from_cols(cols[0] / r, cols[1] / r, cols[2] / r);
        Ok((m.w_axis.truncate(), r, frame))
    }
}

/// Smooth vertex normals weighted by the corner angle, over the given triangles.
fn smooth_normals(positions: &[Vec3], indices: &[[u32; 3]]) -> Vec<Vec3> {
    let mut acc = vec![Vec3::ZERO; positions.len()];
    for t in indices {
        let p = t.map(|i| positions[i as usize]);
        let n = (p[1] - p[0]).cross(p[2] - p[0]).normalize_or_zero();
        for k in 0..3 {
            let d0 = (p[(k + 1) % 3] - p[k]).normalize_or_zero();
            let d1 = (p[(k + 2) % 3] - p[k]).normalize_or_zero();
            let angle = d0.dot(d1).clamp(-1.0, 1.0).acos();
            acc[t[k] as usize] += n * angle;
        }
    }
    acc
}

/// Loads and validates `desc`, reading assets through `assets`.
pub fn load(desc: &SceneDesc, assets: &dyn AssetSource) -> Result<LoadedScene, SceneError> {
    let mut ld = Loader {
        desc,
        assets,
        report: LoadReport::default(),
        texture_ids: BTreeMap::new(),
        material_ids: BTreeMap::new(),
        materials: Vec::new(),
        default_material: None,
    };

    // --- film
    let film = desc.film;
    for (name, v) in [("width", film.width), ("height", film.height)] {
        if v == 0 || v > MAX_FILM_SIDE {
            return Err(SceneError::invalid(
                format!("film.{name}"),
                format!("must be in 1..={MAX_FILM_SIDE}"),
            ));
        }
    }

    // --- camera
    let cam = &desc.camera;
    if !(cam.fov.is_finite() && cam.fov > 0.0 && cam.fov < 180.0) {
        return Err(SceneError::invalid(
            "camera.fov",
            "must be in (0, 180) degrees",
        ));
    }
    if !(cam.near_clip.is_finite() && cam.near_clip > 0.0) {
        return Err(SceneError::invalid(
            "camera.near_clip",
            "must be finite and > 0",
        ));
    }
    if cam.far_clip.partial_cmp(&cam.near_clip) != Some(std::cmp::Ordering::Greater) {
        return Err(SceneError::invalid(
            "camera.far_clip",
            "must be greater than near_clip",
        ));
    }
    let cam_m = to_matrix(&cam.transform, "camera.transform")?;
    if normal_matrix(&cam_m).is_none() {
        return Err(SceneError::invalid("camera.transform", "singular matrix"));
    }
    let camera = Camera {
        to_world: cam_m,
        fov_x_deg: fov_x_deg(cam.fov, cam.fov_axis, film.width, film.height),
        near_clip: cam.near_clip,
        far_clip: cam.far_clip,
    };

    // --- integrator
    let integ = desc.integrator;
    if integ.max_depth < -1 {
        return Err(SceneError::invalid(
            "integrator.max_depth",
            "must be ≥ −1 (−1 = unbounded)",
        ));
    }
    if integ.rr_depth < 1 {
        return Err(SceneError::invalid("integrator.rr_depth", "must be ≥ 1"));
    }
    if integ.sample_count == Some(0) {
        return Err(SceneError::invalid(
            "integrator.sample_count",
            "must be ≥ 1",
        ));
    }
    let integrator = IntegratorSettings {
        max_depth: integ.max_depth,
        rr_depth: integ.rr_depth,
        hide_emitters: integ.hide_emitters,
        sample_count: integ.sample_count,
    };

    // --- textures
    let mut textures = Vec::new();
    for (name, t) in &desc.textures {
        let path = format!("textures.{name}");
        let tex = match t {
            TextureDesc::Bitmap {
                filename,
                raw,
                filter,
                wrap,
                uv_transform,
            } => {
                let image = load_image(assets, filename, *raw)?;
                if let Some(i) = image.data.iter().position(|p| !p.is_finite()) {
                    return Err(SceneError::invalid(
                        format!("{path}.filename"),
                        format!("{filename}: non-finite texel at index {i}"),
                    ));
                }
                Texture::Bitmap {
                    image,
                    filter: *filter,
                    wrap: *wrap,
                    uv_transform: uv_affine(uv_transform, &format!("{path}.uv_transform"))?,
                }
            }
            TextureDesc::Checkerboard {
                color0,
                color1,
                uv_transform,
            } => Texture::Checkerboard {
                color0: check_rgb(*color0, &format!("{path}.color0"))?,
                color1: check_rgb(*color1, &format!("{path}.color1"))?,
                uv_transform: uv_affine(uv_transform, &format!("{path}.uv_transform"))?,
            },
        };
        ld.texture_ids
            .insert(name.clone(), textures.len() as TextureId);
        textures.push(tex);
    }

    // --- named materials
    for (name, m) in &desc.materials {
        let mat = ld.material(m, &format!("materials.{name}"))?;
        ld.material_ids
            .insert(name.clone(), ld.materials.len() as MaterialId);
        ld.materials.push(mat);
    }

    // --- shapes
    let mut meshes = Vec::new();
    let mut spheres = Vec::new();
    for (i, shape) in desc.shapes.iter().enumerate() {
        let path = format!("shapes[{i}]");
        let material = ld.shape_material(shape.material.as_ref(), &path)?;
        let m = to_matrix(&shape.transform, &format!("{path}.transform"))?;
        let emitter = match &shape.emitter {
            Some(e) => Some(check_rgb(e.radiance, &format!("{path}.emitter.radiance"))?),
            None => None,
        };
        if let GeometryDesc::Sphere { center, radius } = &shape.geometry {
            let (center, radius, frame) = ld.sphere(*center, *radius, m, &path)?;
            spheres.push(Sphere {
                center,
                radius,
                flip_normals: shape.flip_normals,
                frame,
                material,
                emitter,
            });
            continue;
        }
        let (raw, face_normals, source) = ld.raw_mesh(&shape.geometry, &path)?;
        // A singular transform (e.g. a rectangle flattened along its normal) is allowed: the
        // file's normals cannot be transformed then, so smooth normals are computed instead.
        let nm = normal_matrix(&m);
        if nm.is_none() && raw.normals.is_some() && !face_normals {
            ld.report.warnings.push(format!(
                "{path} ({source}): singular transform; vertex normals recomputed from the geometry"
            ));
        }
        let positions: Vec<Vec3> = raw
            .positions
            .iter()
            .map(|p| m.transform_point3(*p))
            .collect();
        if let Some(uv) = &raw.uvs
            && let Some(j) = uv.iter().position(|u| !u.is_finite())
        {
            return Err(SceneError::invalid(
                &path,
                format!("{source}: non-finite texture coordinate at vertex {j}"),
            ));
        }
        // Drop degenerate triangles (zero or non-finite world-space area).
        let mut indices = Vec::with_capacity(raw.indices.len());
        let mut area = 0.0f64;
        for t in &raw.indices {
            let [a, b, c] = t.map(|k| positions[k as usize]);
            let ta = 0.5 * (b - a).cross(c - a).length();
            if ta.is_finite() && ta > 0.0 {
                area += f64::from(ta);
                indices.push(if shape.flip_normals {
                    [t[0], t[2], t[1]]
                } else {
                    *t
                });
            }
        }
        let dropped = raw.indices.len() - indices.len();
        if dropped > 0 {
            ld.report.dropped_triangles += dropped;
            ld.report.dropped_per_shape.push(DroppedTriangles {
                shape: i,
                count: dropped,
            });
        }
        if indices.is_empty() && shape.emitter.is_some() {
            return Err(SceneError::invalid(
                format!("{path}.emitter"),
                format!(
                    "{source}: emitter has zero total area (all {} triangles degenerate)",
                    raw.indices.len()
                ),
            ));
        }
        if indices.is_empty() {
            return Err(SceneError::invalid(
                &path,
                format!(
                    "{source}: no non-degenerate triangle left ({} dropped)",
                    raw.indices.len()
                ),
            ));
        }
        if emitter.is_some() && !(area.is_finite() && area > 0.0 && (area as f32).is_finite()) {
            return Err(SceneError::invalid(
                format!("{path}.emitter"),
                "emitter has zero or non-finite area",
            ));
        }
        let mut normals = if face_normals {
            None
        } else if let (Some(ns), Some(nm)) = (&raw.normals, nm) {
            Some(
                ns.iter()
                    .map(|n| (nm * *n).normalize_or_zero())
                    .collect::<Vec<_>>(),
            )
        } else {
            Some(
                smooth_normals(&positions, &indices)
                    .into_iter()
                    .map(Vec3::normalize_or_zero)
                    .collect(),
            )
        };
        if let Some(ns) = &mut normals {
            let bad = indices.iter().flatten().any(|&k| {
                let n = ns[k as usize];
                !(n.is_finite() && n.length_squared() > 0.5)
            });
            if bad {
                ld.report.warnings.push(format!(
                    "{path} ({source}): some vertex normals are zero or non-finite; using face normals"
                ));
                normals = None;
            } else {
                if shape.flip_normals {
                    ns.iter_mut().for_each(|n| *n = -*n);
                }
                // Unreferenced vertices may hold zero normals: give them any unit vector.
                ns.iter_mut()
                    .filter(|n| n.length_squared().is_nan() || n.length_squared() <= 0.5)
                    .for_each(|n| *n = Vec3::Z);
            }
        }
        meshes.push(Mesh {
            positions,
            normals,
            uvs: raw.uvs,
            indices,
            material,
            emitter,
        });
    }

    // --- environment
    let environment = match &desc.environment {
        None => None,
        Some(EnvironmentDesc::Constant { radiance }) => Some(Environment::Constant {
            radiance: check_rgb(*radiance, "environment.radiance")?,
        }),
        Some(EnvironmentDesc::Envmap {
            filename,
            scale,
            transform,
        }) => {
            if !(scale.is_finite() && *scale >= 0.0) {
                return Err(SceneError::invalid(
                    "environment.scale",
                    "must be finite and ≥ 0",
                ));
            }
            let m = to_matrix(transform, "environment.transform")?;
            let r = Mat3::from_mat4(m);
            let orthonormal = (r * r.transpose() - Mat3::IDENTITY)
                .to_cols_array()
                .iter()
                .all(|x| x.abs() < 1e-3);
            if !orthonormal || m.w_axis.truncate().length() > 0.0 {
                return Err(SceneError::invalid(
                    "environment.transform",
                    "must be a pure rotation",
                ));
            }
            let mut image = load_image(assets, filename, false)?;
            let mut clamped = 0usize;
            for (j, p) in image.data.iter_mut().enumerate() {
                if !p.is_finite() {
                    return Err(SceneError::invalid(
                        "environment.filename",
                        format!("{filename}: non-finite texel at index {j}"),
                    ));
                }
                if p.min_element() < 0.0 {
                    clamped += 1;
                    *p = p.max(Vec3::ZERO);
                }
                *p *= *scale;
            }
            if clamped > 0 {
                ld.report.warnings.push(format!(
                    "environment: {clamped} negative texels of {filename} clamped to 0"
                ));
            }
            Some(Environment::Envmap { image, to_world: r })
        }
    };

    let _ = ld.desc;
    let scene = Scene {
        camera,
        film: Film {
            width: film.width,
            height: film.height,
        },
        integrator,
        textures,
        materials: ld.materials,
        meshes,
        spheres,
        environment,
    };
    Ok(LoadedScene {
        scene,
        report: ld.report,
    })
}

/// Converts Mitsuba's `fov` along `axis` to the horizontal field of view (degrees) for a
/// `width × height` film (Mitsuba's `parse_fov`).
pub fn fov_x_deg(fov: f32, axis: FovAxis, width: u32, height: u32) -> f32 {
    let aspect = width as f32 / height as f32;
    let axis = match axis {
        FovAxis::Smaller => {
            if aspect > 1.0 {
                FovAxis::Y
            } else {
                FovAxis::X
            }
        }
        FovAxis::Larger => {
            if aspect > 1.0 {
                FovAxis::X
            } else {
                FovAxis::Y
            }
        }
        a => a,
    };
    let half_tan = (0.5 * fov.to_radians()).tan();
    match axis {
        FovAxis::X => fov,
        FovAxis::Y => (2.0 * (half_tan * aspect).atan()).to_degrees(),
        _ => {
            // Diagonal: the half-width is the half-diagonal scaled by w / diag.
            let w_over_diag = aspect / (aspect * aspect + 1.0).sqrt();
            (2.0 * (half_tan * w_over_diag).atan()).to_degrees()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fov_axis_conversions() {
        assert_eq!(fov_x_deg(40.0, FovAxis::X, 200, 100), 40.0);
        // Square film: every axis is the same as x except the diagonal.
        assert!((fov_x_deg(39.3077, FovAxis::Smaller, 128, 128) - 39.3077).abs() < 1e-4);
        // Wide film: smaller = y; tan(x/2) = aspect·tan(y/2).
        let x = fov_x_deg(30.0, FovAxis::Smaller, 200, 100);
        assert!(((0.5 * x.to_radians()).tan() - 2.0 * (15f32.to_radians()).tan()).abs() < 1e-5);
        assert_eq!(fov_x_deg(30.0, FovAxis::Larger, 200, 100), 30.0);
        // Mitsuba 3.9.1's `x_fov` for fov 30 on a 300×200 film, fov_axis y and diagonal.
        assert!((fov_x_deg(30.0, FovAxis::Y, 300, 200) - 43.792_736).abs() < 1e-4);
        assert!((fov_x_deg(30.0, FovAxis::Diagonal, 300, 200) - 25.136_77).abs() < 1e-4);
        // Mitsuba's default 50 mm lens: diagonal fov 2·atan(√(36²+24²)/100) → x fov 34.0221° at 1:1.
        let diag = (2.0 * ((36.0f32 * 36.0 + 24.0 * 24.0).sqrt() / 100.0).atan()).to_degrees();
        assert!((fov_x_deg(diag, FovAxis::Diagonal, 128, 128) - 34.0221).abs() < 2e-3);
    }

    #[test]
    fn smooth_normals_of_a_flat_fan_are_the_face_normal() {
        let p = [Vec3::ZERO, Vec3::X, Vec3::new(1.0, 1.0, 0.0), Vec3::Y];
        let n = smooth_normals(&p, &[[0, 1, 2], [0, 2, 3]]);
        for v in n {
            assert!((v.normalize() - Vec3::Z).length() < 1e-6);
        }
    }
}
