//! The native scene format: a JSON document (serde) that *describes* a scene.
//!
//! A [`SceneDesc`] refers to asset files (meshes, textures, env maps) by relative name; it is
//! turned into a renderable [`crate::Scene`] by [`crate::load()`], which resolves those names
//! through an [`crate::AssetSource`]. The Mitsuba 3 XML importer produces a `SceneDesc` too, so
//! both formats share one loader and one validator.
//!
//! Every type here is documented with its fields, defaults and a JSON snippet per feature
//! (each snippet is parsed by `tests/native_json.rs`); the shipped example scenes are in
//! `scenes/` with their README.
//!
//! ```json
//! {
//!   "camera": { "fov": 39.3, "fov_axis": "x",
//!               "transform": [ { "look_at": { "origin": [0, 1, 3.5], "target": [0, 1, 0], "up": [0, 1, 0] } } ] },
//!   "film": { "width": 256, "height": 256 },
//!   "integrator": { "max_depth": 5 },
//!   "materials": { "white": { "type": "diffuse", "reflectance": [0.8, 0.8, 0.8] } },
//!   "shapes": [
//!     { "type": "rectangle", "material": "white", "transform": [ { "rotate": { "axis": [1, 0, 0], "angle": -90 } } ] },
//!     { "type": "sphere", "center": [0, 1.9, 0], "radius": 0.1, "material": "white",
//!       "emitter": { "radiance": [10, 10, 10] } }
//!   ]
//! }
//! ```

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

/// A whole scene in the native format. Field order is the order of the JSON document.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SceneDesc {
    /// The (single) perspective camera.
    pub camera: CameraDesc,
    /// Output resolution. The pixel filter is always a box: a pixel is the mean of its samples.
    pub film: FilmDesc,
    /// Path-tracing settings stored with the scene; a job or the CLI may override them.
    #[serde(default)]
    pub integrator: IntegratorDesc,
    /// Named textures, referenced from material colours as `{ "texture": "name" }`.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub textures: BTreeMap<String, TextureDesc>,
    /// Named materials, referenced from shapes by name.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub materials: BTreeMap<String, MaterialDesc>,
    /// The geometry. A shape with an `emitter` is an area light.
    pub shapes: Vec<ShapeDesc>,
    /// Light arriving from infinity (env map or constant), if any.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub environment: Option<EnvironmentDesc>,
}

/// `camera`: a pinhole perspective camera with Mitsuba 3's conventions — it looks along +Z of
/// its frame, +Y is up and **+X is left**.
///
/// | field | type | default | meaning |
/// |---|---|---|---|
/// | `fov` | degrees | — | field of view along `fov_axis` |
/// | `fov_axis` | `x`, `y`, `diagonal`, `smaller`, `larger` | `x` | which image extent `fov` spans |
/// | `transform` | [`TransformDesc`] | identity | camera-to-world |
/// | `near_clip`, `far_clip` | length | 0.01, 10000 | ray extent |
///
/// ```json
/// "camera": { "fov": 39.3077, "fov_axis": "smaller", "near_clip": 10, "far_clip": 2800,
///             "transform": [ { "look_at": { "origin": [278, 273, -800], "target": [278, 273, -799], "up": [0, 1, 0] } } ] }
/// ```
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraDesc {
    /// Field of view in degrees, measured along `fov_axis`.
    pub fov: f32,
    /// Which image extent `fov` spans.
    #[serde(default)]
    pub fov_axis: FovAxis,
    /// Camera-to-world transform.
    #[serde(default)]
    pub transform: TransformDesc,
    /// Distance of the near clip plane along the ray.
    #[serde(default = "default_near_clip")]
    pub near_clip: f32,
    /// Distance of the far clip plane along the ray.
    #[serde(default = "default_far_clip")]
    pub far_clip: f32,
}

fn default_near_clip() -> f32 {
    0.01
}
fn default_far_clip() -> f32 {
    10_000.0
}

/// Which image extent the camera's `fov` spans (Mitsuba's `fov_axis`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FovAxis {
    /// Horizontal extent.
    #[default]
    X,
    /// Vertical extent.
    Y,
    /// Image diagonal.
    Diagonal,
    /// The shorter side.
    Smaller,
    /// The longer side.
    Larger,
}

/// `film`: the output image size in pixels (box pixel filter).
///
/// ```json
/// "film": { "width": 128, "height": 96 }
/// ```
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FilmDesc {
    /// Width in pixels (≥ 1).
    pub width: u32,
    /// Height in pixels (≥ 1).
    pub height: u32,
}

/// `integrator`: path-length settings with Mitsuba 3's meaning.
///
/// | field | type | default | meaning |
/// |---|---|---|---|
/// | `max_depth` | int | 5 | path segments incl. the camera ray: 1 = emitters only, 2 = direct lighting, −1 = unbounded |
/// | `rr_depth` | int | 5 | depth at which Russian roulette starts |
/// | `hide_emitters` | bool | false | camera rays that hit an emitter return black |
/// | `sample_count` | int | none | samples per pixel the scene file asks for (Mitsuba's `<sampler>`); recorded, a job's spp wins |
///
/// ```json
/// "integrator": { "max_depth": 2, "rr_depth": 100, "hide_emitters": false, "sample_count": 64 }
/// ```
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct IntegratorDesc {
    /// Maximum number of path segments including the camera ray; −1 = unbounded.
    #[serde(default = "default_max_depth")]
    pub max_depth: i32,
    /// Path depth from which Russian roulette may terminate paths.
    #[serde(default = "default_rr_depth")]
    pub rr_depth: i32,
    /// Whether directly visible emitters are hidden.
    #[serde(default)]
    pub hide_emitters: bool,
    /// Samples per pixel requested by the scene file, if any (informational).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sample_count: Option<u32>,
}

fn default_max_depth() -> i32 {
    5
}
fn default_rr_depth() -> i32 {
    5
}

impl Default for IntegratorDesc {
    fn default() -> Self {
        Self {
            max_depth: default_max_depth(),
            rr_depth: default_rr_depth(),
            hide_emitters: false,
            sample_count: None,
        }
    }
}

/// A transform: a list of operations applied in order (each one left-multiplies the result
/// so far, as Mitsuba's `<transform>` children do).
///
/// ```json
/// [ { "scale": [2, 2, 2] }, { "rotate": { "axis": [0, 1, 0], "angle": 30 } }, { "translate": [0, 1, 0] } ]
/// ```
///
/// A camera frame and a row-major matrix:
///
/// ```json
/// [ { "look_at": { "origin": [0, 1, 4], "target": [0, 1, 0], "up": [0, 1, 0] } } ]
/// ```
/// ```json
/// [ { "matrix": [1, 0, 0, 5,  0, 1, 0, 0,  0, 0, 1, 0,  0, 0, 0, 1] } ]
/// ```
pub type TransformDesc = Vec<TransformOp>;

/// One step of a [`TransformDesc`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum TransformOp {
    /// Translation by a vector.
    Translate([f32; 3]),
    /// Per-axis scale.
    Scale([f32; 3]),
    /// Rotation by `angle` degrees about `axis` (right-handed).
    Rotate {
        /// Rotation axis (normalised on load; must be non-zero).
        axis: [f32; 3],
        /// Angle in degrees.
        angle: f32,
    },
    /// A camera-style frame: +Z towards `target`, +Y close to `up`, +X = cross(up, dir).
    LookAt {
        /// Eye position.
        origin: [f32; 3],
        /// Point looked at.
        target: [f32; 3],
        /// Up hint (must not be parallel to the view direction).
        up: [f32; 3],
    },
    /// A 4×4 matrix in row-major order (the last row must be 0 0 0 1).
    Matrix([f32; 16]),
}

/// A colour value: an RGB triple, a single grey value, or a reference to a named texture.
///
/// ```json
/// [0.8, 0.2, 0.2]      0.5      { "texture": "checks" }
/// ```
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum ColorDesc {
    /// Linear RGB.
    Rgb([f32; 3]),
    /// Grey: the same value in every channel.
    Gray(f32),
    /// A named texture from `textures`.
    Texture {
        /// Name of the texture.
        texture: String,
    },
}

/// `textures.<name>`: a 2-D texture looked up with the surface's UV coordinates.
///
/// | type | fields |
/// |---|---|
/// | `bitmap` | `filename` (PNG/JPEG: sRGB → linear unless `raw`; EXR: linear), `raw` = false, `filter` = `bilinear`, `wrap` = `repeat`, `uv_transform` |
/// | `checkerboard` | `color0` = 0.4, `color1` = 0.2, `uv_transform` (Mitsuba's `to_uv`) |
///
/// ```json
/// "textures": { "checks": { "type": "checkerboard", "color0": [0.9, 0.9, 0.9], "color1": [0.1, 0.1, 0.1],
///                           "uv_transform": [ { "scale": [8, 8, 1] } ] },
///               "wood":   { "type": "bitmap", "filename": "textures/wood.jpg", "filter": "bilinear", "wrap": "repeat" },
///               "albedo": { "type": "bitmap", "filename": "textures/albedo.png", "raw": true, "filter": "nearest" } }
/// ```
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
pub enum TextureDesc {
    /// An image file.
    Bitmap {
        /// Asset name of the image (PNG, JPEG or EXR).
        filename: String,
        /// Treat 8-bit data as linear instead of sRGB.
        #[serde(default)]
        raw: bool,
        /// Lookup filter.
        #[serde(default)]
        filter: TextureFilter,
        /// Behaviour outside [0, 1].
        #[serde(default)]
        wrap: TextureWrap,
        /// Transform applied to the point (u, v, 0) before lookup (Mitsuba's `to_uv`).
        #[serde(default, skip_serializing_if = "Vec::is_empty")]
        uv_transform: TransformDesc,
    },
    /// Mitsuba's checkerboard on the transformed (u, v): `color0` where ⌊2u⌋ + ⌊2v⌋ is
    /// **even** (e.g. around uv = (0.25, 0.25)), `color1` where it is odd — checked against
    /// Mitsuba 3.9.1.
    Checkerboard {
        /// First colour.
        #[serde(default = "default_checker0")]
        color0: [f32; 3],
        /// Second colour.
        #[serde(default = "default_checker1")]
        color1: [f32; 3],
        /// Transform applied to (u, v, 0) before lookup.
        #[serde(default, skip_serializing_if = "Vec::is_empty")]
        uv_transform: TransformDesc,
    },
}

fn default_checker0() -> [f32; 3] {
    [0.4; 3]
}
fn default_checker1() -> [f32; 3] {
    [0.2; 3]
}

/// Texture lookup filter.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TextureFilter {
    /// Bilinear interpolation of the four nearest texels.
    #[default]
    Bilinear,
    /// The nearest texel.
    Nearest,
}

/// Texture coordinates outside [0, 1].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TextureWrap {
    /// Periodic.
    #[default]
    Repeat,
    /// Mirrored periodic.
    Mirror,
    /// Clamp to the border texel.
    Clamp,
}

/// Microfacet normal distribution.
#[derive(
    Clone, Copy, Debug, Default, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize,
)]
#[serde(rename_all = "snake_case")]
pub enum Distribution {
    /// Trowbridge–Reitz / GGX (our default, and what the shared Mitsuba scenes use).
    #[default]
    Ggx,
    /// Beckmann (Mitsuba's default when the XML does not say).
    Beckmann,
}

/// `materials.<name>`: a BSDF. All BSDFs are **one-sided** (black unless both directions are
/// above the shading normal's side of the surface) unless wrapped in `twosided`.
///
/// | type | fields (default) |
/// |---|---|
/// | `diffuse` | `reflectance` (0.5) |
/// | `conductor` | `eta` (Al-like), `k`, `specular_reflectance` (1) — a perfect mirror with conductor Fresnel |
/// | `roughconductor` | `distribution` (ggx), `alpha` (0.1), `eta`, `k`, `specular_reflectance` (1) |
/// | `roughplastic` | `distribution` (ggx), `alpha` (0.1), `int_ior` (1.49), `ext_ior` (1.000277), `diffuse_reflectance` (0.5), `specular_reflectance` (1), `nonlinear` (false) — Mitsuba's layered model |
/// | `twosided` | `bsdf`: the material used on both sides |
///
/// ```json
/// "materials": {
///   "white":  { "type": "diffuse", "reflectance": [0.8, 0.8, 0.8] },
///   "wood":   { "type": "diffuse", "reflectance": { "texture": "wood" } },
///   "mirror": { "type": "conductor", "eta": [0, 0, 0], "k": [1, 1, 1] },
///   "gold":   { "type": "roughconductor", "alpha": 0.15, "eta": [0.143, 0.374, 1.442], "k": [3.983, 2.385, 1.603] },
///   "blue":   { "type": "roughplastic", "distribution": "beckmann", "alpha": 0.1, "int_ior": 1.5, "ext_ior": 1.0,
///               "diffuse_reflectance": [0.1, 0.3, 0.6] },
///   "paper":  { "type": "twosided", "bsdf": { "type": "diffuse", "reflectance": 0.7 } }
/// }
/// ```
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
pub enum MaterialDesc {
    /// Lambertian reflector.
    Diffuse {
        /// Albedo.
        #[serde(default = "default_half")]
        reflectance: ColorDesc,
    },
    /// Smooth conductor (a delta lobe).
    Conductor {
        /// Real part of the complex IOR, per channel.
        #[serde(default = "default_eta")]
        eta: [f32; 3],
        /// Imaginary part of the complex IOR, per channel.
        #[serde(default = "default_k")]
        k: [f32; 3],
        /// Multiplier on the reflection.
        #[serde(default = "default_one")]
        specular_reflectance: ColorDesc,
    },
    /// Rough conductor (microfacet).
    #[serde(rename = "roughconductor")]
    RoughConductor {
        /// Microfacet distribution.
        #[serde(default)]
        distribution: Distribution,
        /// Roughness α (not squared).
        #[serde(default = "default_alpha")]
        alpha: f32,
        /// Real part of the complex IOR, per channel.
        #[serde(default = "default_eta")]
        eta: [f32; 3],
        /// Imaginary part of the complex IOR, per channel.
        #[serde(default = "default_k")]
        k: [f32; 3],
        /// Multiplier on the reflection.
        #[serde(default = "default_one")]
        specular_reflectance: ColorDesc,
    },
    /// Rough dielectric coating over a diffuse base (Mitsuba's `roughplastic`).
    #[serde(rename = "roughplastic")]
    RoughPlastic {
        /// Microfacet distribution.
        #[serde(default)]
        distribution: Distribution,
        /// Roughness α (not squared).
        #[serde(default = "default_alpha")]
        alpha: f32,
        /// Interior index of refraction.
        #[serde(default = "default_int_ior")]
        int_ior: f32,
        /// Exterior index of refraction.
        #[serde(default = "default_ext_ior")]
        ext_ior: f32,
        /// Albedo of the diffuse base.
        #[serde(default = "default_half")]
        diffuse_reflectance: ColorDesc,
        /// Multiplier on the specular reflection.
        #[serde(default = "default_one")]
        specular_reflectance: ColorDesc,
        /// Mitsuba's `nonlinear` option (colour shift by internal scattering).
        #[serde(default)]
        nonlinear: bool,
    },
    /// Use the inner material on both sides of the surface.
    #[serde(rename = "twosided")]
    TwoSided {
        /// The wrapped material.
        bsdf: Box<MaterialDesc>,
    },
}

fn default_half() -> ColorDesc {
    ColorDesc::Gray(0.5)
}
fn default_one() -> ColorDesc {
    ColorDesc::Gray(1.0)
}
fn default_alpha() -> f32 {
    0.1
}
fn default_int_ior() -> f32 {
    1.49
}
fn default_ext_ior() -> f32 {
    1.000_277
}
/// Aluminium's RGB eta (Mitsuba's default conductor material, as its RGB variants see it).
fn default_eta() -> [f32; 3] {
    [1.657_46, 0.880_369, 0.521_229]
}
/// Aluminium's RGB k.
fn default_k() -> [f32; 3] {
    [9.223_869, 6.269_523, 4.837_001]
}

/// A shape's material: the name of an entry in `materials`, or a material written inline.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum MaterialRef {
    /// Name of an entry in `materials`.
    Named(String),
    /// An inline material.
    Inline(MaterialDesc),
}

/// `emitter` on a shape: it emits `radiance` from its front side (CCW winding / along the
/// normal; the inside of a sphere is its back).
///
/// ```json
/// "emitter": { "radiance": [17, 12, 4] }
/// ```
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AreaEmitterDesc {
    /// Emitted radiance (linear RGB), uniform over the surface.
    pub radiance: [f32; 3],
}

/// `shapes[i]`: one piece of geometry. Common fields: `material` (name or inline; default a
/// grey diffuse), `transform`, `emitter`, `flip_normals` (false).
///
/// | type | own fields |
/// |---|---|
/// | `obj` / `ply` | `filename`, `face_normals` (false: use the file's vertex normals, or compute smooth angle-weighted ones when the file has none, as Mitsuba does) |
/// | `rectangle` | — the square [−1,1]² in the z = 0 plane, normal +Z |
/// | `cube` | — the cube [−1,1]³ as 12 triangles |
/// | `sphere` | `center` (`[0, 0, 0]`), `radius` (1); analytic, intersected exactly |
/// | `mesh` | `positions`, `indices`, optional `normals`, `uvs` — geometry written inline |
///
/// ```json
/// "shapes": [
///   { "type": "obj", "filename": "meshes/bunny.obj", "material": "gold", "transform": [ { "scale": [2, 2, 2] } ] },
///   { "type": "ply", "filename": "meshes/sphere.ply", "face_normals": true, "material": "blue" },
///   { "type": "rectangle", "transform": [ { "rotate": { "axis": [1, 0, 0], "angle": 90 } } ], "flip_normals": true,
///     "emitter": { "radiance": [17, 12, 4] } },
///   { "type": "cube", "material": { "type": "diffuse", "reflectance": [0.5, 0.2, 0.2] } },
///   { "type": "sphere", "center": [0, 1, 0], "radius": 0.25, "emitter": { "radiance": [5, 5, 5] } },
///   { "type": "mesh", "positions": [[0, 0, 0], [1, 0, 0], [0, 1, 0]], "indices": [[0, 1, 2]], "uvs": [[0, 0], [1, 0], [0, 1]] }
/// ]
/// ```
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "ShapeRepr")]
pub struct ShapeDesc {
    /// What the geometry is.
    #[serde(flatten)]
    pub geometry: GeometryDesc,
    /// Material (default: grey diffuse, as in Mitsuba).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub material: Option<MaterialRef>,
    /// Object-to-world transform.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub transform: TransformDesc,
    /// Makes the shape an area light.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub emitter: Option<AreaEmitterDesc>,
    /// Flip the geometric and shading normals (and so which side is the front).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub flip_normals: bool,
}

/// The flat JSON form of a shape, checked field by field when converted into a [`ShapeDesc`]
/// (serde cannot combine `flatten` with `deny_unknown_fields`, so unknown keys and keys of
/// another shape type are rejected here).
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct ShapeRepr {
    #[serde(rename = "type")]
    kind: String,
    filename: Option<String>,
    face_normals: Option<bool>,
    center: Option<[f32; 3]>,
    radius: Option<f32>,
    positions: Option<Vec<[f32; 3]>>,
    indices: Option<Vec<[u32; 3]>>,
    normals: Option<Vec<[f32; 3]>>,
    uvs: Option<Vec<[f32; 2]>>,
    #[serde(default)]
    material: Option<MaterialRef>,
    #[serde(default)]
    transform: TransformDesc,
    #[serde(default)]
    emitter: Option<AreaEmitterDesc>,
    #[serde(default)]
    flip_normals: bool,
}

impl TryFrom<ShapeRepr> for ShapeDesc {
    type Error = String;

    fn try_from(r: ShapeRepr) -> Result<Self, String> {
        let kind = r.kind.as_str();
        let present = [
            ("filename", r.filename.is_some()),
            ("face_normals", r.face_normals.is_some()),
            ("center", r.center.is_some()),
            ("radius", r.radius.is_some()),
            ("positions", r.positions.is_some()),
            ("indices", r.indices.is_some()),
            ("normals", r.normals.is_some()),
            ("uvs", r.uvs.is_some()),
        ];
        let allowed: &[&str] = match kind {
            "obj" | "ply" => &["filename", "face_normals"],
            "rectangle" | "cube" => &[],
            "sphere" => &["center", "radius"],
            "mesh" => &["positions", "indices", "normals", "uvs"],
            _ => {
                return Err(format!(
                    "unknown shape type `{kind}` (expected obj, ply, rectangle, cube, sphere or mesh)"
                ));
            }
        };
        if let Some((field, _)) = present.iter().find(|(f, p)| *p && !allowed.contains(f)) {
            return Err(format!(
                "field `{field}` is not allowed for a shape of type `{kind}`"
            ));
        }
        let missing = |f: &str| format!("a shape of type `{kind}` needs `{f}`");
        let geometry = match kind {
            "obj" | "ply" => {
                let filename = r.filename.ok_or_else(|| missing("filename"))?;
                let face_normals = r.face_normals.unwrap_or(false);
                if kind == "obj" {
                    GeometryDesc::Obj {
                        filename,
                        face_normals,
                    }
                } else {
                    GeometryDesc::Ply {
                        filename,
                        face_normals,
                    }
                }
            }
            "rectangle" => GeometryDesc::Rectangle,
            "cube" => GeometryDesc::Cube,
            "sphere" => GeometryDesc::Sphere {
                center: r.center.unwrap_or_default(),
                radius: r.radius.unwrap_or_else(default_radius),
            },
            _ => GeometryDesc::Mesh {
                positions: r.positions.ok_or_else(|| missing("positions"))?,
                indices: r.indices.ok_or_else(|| missing("indices"))?,
                normals: r.normals,
                uvs: r.uvs,
            },
        };
        Ok(ShapeDesc {
            geometry,
            material: r.material,
            transform: r.transform,
            emitter: r.emitter,
            flip_normals: r.flip_normals,
        })
    }
}

/// The geometric part of a [`ShapeDesc`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum GeometryDesc {
    /// Wavefront OBJ mesh file (v is flipped on load, as Mitsuba does).
    Obj {
        /// Asset name.
        filename: String,
        /// Ignore vertex normals and shade with face normals.
        #[serde(default)]
        face_normals: bool,
    },
    /// Stanford PLY mesh file (ASCII or binary).
    Ply {
        /// Asset name.
        filename: String,
        /// Ignore vertex normals and shade with face normals.
        #[serde(default)]
        face_normals: bool,
    },
    /// The square `[−1, 1]²` at z = 0, facing +Z, with uv in `[0, 1]²`.
    Rectangle,
    /// The cube [−1,1]³ (12 triangles, outward faces).
    Cube,
    /// An analytic sphere (transform may translate, rotate and scale uniformly).
    Sphere {
        /// Centre before `transform`.
        #[serde(default)]
        center: [f32; 3],
        /// Radius before `transform`.
        #[serde(default = "default_radius")]
        radius: f32,
    },
    /// A triangle mesh written inline.
    Mesh {
        /// Vertex positions.
        positions: Vec<[f32; 3]>,
        /// Triangles as vertex index triples.
        indices: Vec<[u32; 3]>,
        /// Per-vertex shading normals.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        normals: Option<Vec<[f32; 3]>>,
        /// Per-vertex texture coordinates.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        uvs: Option<Vec<[f32; 2]>>,
    },
}

fn default_radius() -> f32 {
    1.0
}

/// `environment`: light from infinitely far away.
///
/// | type | fields |
/// |---|---|
/// | `envmap` | `filename` (lat-long EXR), `scale` (1), `transform` (rotation) — Mitsuba's mapping `u = atan2(d.x, −d.z)/2π`, `v = acos(d.y)/π` in the map's frame |
/// | `constant` | `radiance` |
///
/// ```json
/// "environment": { "type": "envmap", "filename": "textures/museum.exr", "scale": 1.0,
///                  "transform": [ { "rotate": { "axis": [0, 1, 0], "angle": 90 } } ] }
/// ```
/// ```json
/// "environment": { "type": "constant", "radiance": [0.2, 0.2, 0.25] }
/// ```
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
pub enum EnvironmentDesc {
    /// Latitude–longitude HDR image.
    Envmap {
        /// Asset name of the EXR image.
        filename: String,
        /// Radiance multiplier.
        #[serde(default = "default_scale")]
        scale: f32,
        /// Map-to-world transform (rotation only).
        #[serde(default, skip_serializing_if = "Vec::is_empty")]
        transform: TransformDesc,
    },
    /// The same radiance from every direction.
    Constant {
        /// Radiance (linear RGB).
        radiance: [f32; 3],
    },
}

fn default_scale() -> f32 {
    1.0
}
