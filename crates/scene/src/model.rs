//! The loaded, validated scene the renderer consumes: every asset read, every transform
//! applied (geometry is in world space), every reference resolved to an index.
//!
//! Contract: a [`Scene`] returned by [`crate::load()`] has only finite numbers, non-degenerate
//! camera and film, triangles with non-zero area, emitters with positive area and radiance
//! ≥ 0, valid indices everywhere. The renderer may rely on that and does not re-check.

use glam::{Mat3, Mat4, Vec2, Vec3};

pub use crate::desc::{Distribution, FovAxis, TextureFilter, TextureWrap};

/// Index into [`Scene::textures`].
pub type TextureId = u32;
/// Index into [`Scene::materials`].
pub type MaterialId = u32;

/// A renderable scene.
#[derive(Clone, Debug)]
pub struct Scene {
    /// The camera.
    pub camera: Camera,
    /// Output size.
    pub film: Film,
    /// Path-length settings from the scene file (jobs may override).
    pub integrator: IntegratorSettings,
    /// Textures, referenced by [`Color::Texture`].
    pub textures: Vec<Texture>,
    /// Materials, referenced by shapes.
    pub materials: Vec<Material>,
    /// Triangle meshes in world space.
    pub meshes: Vec<Mesh>,
    /// Analytic spheres in world space.
    pub spheres: Vec<Sphere>,
    /// Environment light, if any.
    pub environment: Option<Environment>,
}

/// Pinhole camera (Mitsuba 3 `perspective`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    /// Camera-to-world; the camera looks along its +Z, +Y up, +X left.
    pub to_world: Mat4,
    /// Horizontal field of view in degrees (already converted from the scene's `fov_axis`).
    pub fov_x_deg: f32,
    /// Near clip distance along the ray direction's z.
    pub near_clip: f32,
    /// Far clip distance.
    pub far_clip: f32,
}

/// Output image size.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Film {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
}

/// Path-length settings (Mitsuba meaning; see [`crate::desc::IntegratorDesc`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct IntegratorSettings {
    /// Max path segments incl. the camera ray; −1 = unbounded.
    pub max_depth: i32,
    /// Depth from which Russian roulette applies.
    pub rr_depth: i32,
    /// Hide directly visible emitters.
    pub hide_emitters: bool,
    /// Samples per pixel the scene file asks for (informational; jobs choose their own spp).
    pub sample_count: Option<u32>,
}

/// A colour parameter: constant linear RGB or a texture lookup.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Color {
    /// Constant linear RGB.
    Rgb(Vec3),
    /// Look up [`Scene::textures`]`[id]` at the hit's UV.
    Texture(TextureId),
}

/// A linear-RGB image stored row-major, top row first.
#[derive(Clone, Debug, PartialEq)]
pub struct RgbImage {
    /// Width in texels.
    pub width: u32,
    /// Height in texels.
    pub height: u32,
    /// `width * height` linear RGB texels.
    pub data: Vec<Vec3>,
}

/// A texture.
#[derive(Clone, Debug, PartialEq)]
pub enum Texture {
    /// Image texture.
    Bitmap {
        /// Linear RGB texels.
        image: RgbImage,
        /// Lookup filter.
        filter: TextureFilter,
        /// Wrap mode.
        wrap: TextureWrap,
        /// Applied to (u, v) before the lookup (the desc transform applied to (u, v, 0, 1)).
        /// Lookup convention (Mitsuba's): u runs along columns left → right, v along rows
        /// **top → bottom** (v = 0 is the first, top row; OBJ uvs are flipped on load for this).
        uv_transform: glam::Affine2,
    },
    /// Mitsuba checkerboard: with (u, v) = `uv_transform`(uv), `color0` where ⌊2u⌋ + ⌊2v⌋ is
    /// even, `color1` where it is odd (checked against Mitsuba 3.9.1).
    Checkerboard {
        /// First colour.
        color0: Vec3,
        /// Second colour.
        color1: Vec3,
        /// Applied to (u, v) before the lookup.
        uv_transform: glam::Affine2,
    },
}

/// A resolved material (BSDF parameters). One-sided unless [`Material::TwoSided`].
#[derive(Clone, Debug, PartialEq)]
pub enum Material {
    /// Lambertian.
    Diffuse {
        /// Albedo.
        reflectance: Color,
    },
    /// Smooth conductor (delta reflection).
    Conductor {
        /// Complex IOR, real part.
        eta: Vec3,
        /// Complex IOR, imaginary part.
        k: Vec3,
        /// Reflection multiplier.
        specular_reflectance: Color,
    },
    /// Rough conductor.
    RoughConductor {
        /// Normal distribution.
        distribution: Distribution,
        /// α, not squared.
        alpha: f32,
        /// Complex IOR, real part.
        eta: Vec3,
        /// Complex IOR, imaginary part.
        k: Vec3,
        /// Reflection multiplier.
        specular_reflectance: Color,
    },
    /// Mitsuba's layered rough plastic.
    RoughPlastic {
        /// Normal distribution.
        distribution: Distribution,
        /// α, not squared.
        alpha: f32,
        /// Relative IOR int_ior / ext_ior.
        eta: f32,
        /// Diffuse base albedo.
        diffuse_reflectance: Color,
        /// Specular multiplier.
        specular_reflectance: Color,
        /// Mitsuba's `nonlinear`.
        nonlinear: bool,
    },
    /// Both sides use the inner material (with the normal flipped on the back side).
    TwoSided(Box<Material>),
}

/// A triangle mesh in world space.
#[derive(Clone, Debug, PartialEq)]
pub struct Mesh {
    /// World-space vertex positions.
    pub positions: Vec<Vec3>,
    /// World-space unit shading normals per vertex (None: use face normals).
    pub normals: Option<Vec<Vec3>>,
    /// Texture coordinates per vertex (None: barycentric-style defaults).
    pub uvs: Option<Vec<Vec2>>,
    /// Triangles (counter-clockwise = front when seen from the side the normal points to).
    pub indices: Vec<[u32; 3]>,
    /// Material index.
    pub material: MaterialId,
    /// Emitted radiance from the front side, if this mesh is an area light.
    pub emitter: Option<Vec3>,
}

/// An analytic sphere in world space.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Sphere {
    /// Centre.
    pub center: Vec3,
    /// Radius (> 0).
    pub radius: f32,
    /// Normals point inward (front side = inside).
    pub flip_normals: bool,
    /// Rotation part of the object-to-world transform (for UV parametrisation).
    pub frame: Mat3,
    /// Material index.
    pub material: MaterialId,
    /// Emitted radiance from the front side, if this sphere is an area light.
    pub emitter: Option<Vec3>,
}

/// Light from infinity.
#[derive(Clone, Debug, PartialEq)]
pub enum Environment {
    /// Latitude–longitude map.
    Envmap {
        /// Linear RGB radiance, already multiplied by `scale`.
        image: RgbImage,
        /// Map-to-world rotation; a world direction d is looked up as `to_world⁻¹ d`.
        to_world: Mat3,
    },
    /// Uniform radiance.
    Constant {
        /// Radiance.
        radiance: Vec3,
    },
}
