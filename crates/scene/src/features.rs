//! [`Features`]: which effects a loaded scene calls for, so the renderer and the estimators
//! build only those ("simulate only the effects a scene calls for", DESIGN §1).
//!
//! ```json
//! { "emitters": 17, "area_emitters": 16, "emissive_triangles": 32, "environment": "none",
//!   "bsdf_kinds": ["diffuse", "roughconductor", "roughplastic"], "textures": 0,
//!   "delta_lobes": false, "two_sided": true, "triangles": 58, "spheres": 0,
//!   "max_depth": 5, "direct_only": false }
//! ```

use std::collections::BTreeSet;

use serde::{Deserialize, Serialize};

use crate::model::{Color, Environment, Material, Scene};

/// Kind of light from infinity.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum EnvironmentKind {
    /// No light from infinity.
    None,
    /// Lat-long environment map (needs an importance-sampling technique).
    Envmap,
    /// Uniform radiance.
    Constant,
}

/// A BSDF family present in the scene (the inner kind for `twosided`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum BsdfKind {
    /// Lambertian.
    Diffuse,
    /// Smooth conductor (delta lobe).
    Conductor,
    /// Rough conductor.
    #[serde(rename = "roughconductor")]
    RoughConductor,
    /// Rough plastic.
    #[serde(rename = "roughplastic")]
    RoughPlastic,
}

/// Summary of a loaded scene's effects.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Features {
    /// Light sources: emitting shapes (each mesh or sphere counts once) + 1 for an environment.
    pub emitters: usize,
    /// Emitting shapes (meshes and spheres).
    pub area_emitters: usize,
    /// Triangles of emitting meshes.
    pub emissive_triangles: usize,
    /// Environment light kind.
    pub environment: EnvironmentKind,
    /// BSDF families used by some shape (unused materials are not counted).
    pub bsdf_kinds: BTreeSet<BsdfKind>,
    /// Number of textures referenced by used materials.
    pub textures: usize,
    /// Some used material has a delta (perfectly specular) lobe.
    pub delta_lobes: bool,
    /// Some used material is `twosided`.
    pub two_sided: bool,
    /// Triangles in all meshes.
    pub triangles: usize,
    /// Analytic spheres.
    pub spheres: usize,
    /// The scene's `max_depth` (−1 = unbounded).
    pub max_depth: i32,
    /// `max_depth == 2`: direct illumination only, no indirect bounces to build.
    pub direct_only: bool,
}

fn visit(
    m: &Material,
    kinds: &mut BTreeSet<BsdfKind>,
    tex: &mut BTreeSet<u32>,
    delta: &mut bool,
    two: &mut bool,
) {
    let mut color = |c: &Color| {
        if let Color::Texture(id) = c {
            tex.insert(*id);
        }
    };
    match m {
        Material::Diffuse { reflectance } => {
            kinds.insert(BsdfKind::Diffuse);
            color(reflectance);
        }
        Material::Conductor {
            specular_reflectance,
            ..
        } => {
            kinds.insert(BsdfKind::Conductor);
            *delta = true;
            color(specular_reflectance);
        }
        Material::RoughConductor {
            specular_reflectance,
            ..
        } => {
            kinds.insert(BsdfKind::RoughConductor);
            color(specular_reflectance);
        }
        Material::RoughPlastic {
            diffuse_reflectance,
            specular_reflectance,
            ..
        } => {
            kinds.insert(BsdfKind::RoughPlastic);
            color(diffuse_reflectance);
            color(specular_reflectance);
        }
        Material::TwoSided(inner) => {
            *two = true;
            visit(inner, kinds, tex, delta, two);
        }
    }
}

impl Features {
    /// Summarises `scene`.
    pub fn of(scene: &Scene) -> Features {
        let mut used = BTreeSet::new();
        used.extend(scene.meshes.iter().map(|m| m.material));
        used.extend(scene.spheres.iter().map(|s| s.material));
        let (mut kinds, mut tex, mut delta, mut two) =
            (BTreeSet::new(), BTreeSet::new(), false, false);
        for id in used {
            if let Some(m) = scene.materials.get(id as usize) {
                visit(m, &mut kinds, &mut tex, &mut delta, &mut two);
            }
        }
        let area_meshes: Vec<_> = scene
            .meshes
            .iter()
            .filter(|m| m.emitter.is_some())
            .collect();
        let area_emitters =
            area_meshes.len() + scene.spheres.iter().filter(|s| s.emitter.is_some()).count();
        let environment = match scene.environment {
            None => EnvironmentKind::None,
            Some(Environment::Envmap { .. }) => EnvironmentKind::Envmap,
            Some(Environment::Constant { .. }) => EnvironmentKind::Constant,
        };
        Features {
            emitters: area_emitters + usize::from(environment != EnvironmentKind::None),
            area_emitters,
            emissive_triangles: area_meshes.iter().map(|m| m.indices.len()).sum(),
            environment,
            bsdf_kinds: kinds,
            textures: tex.len(),
            delta_lobes: delta,
            two_sided: two,
            triangles: scene.meshes.iter().map(|m| m.indices.len()).sum(),
            spheres: scene.spheres.len(),
            max_depth: scene.integrator.max_depth,
            direct_only: scene.integrator.max_depth == 2,
        }
    }

    /// Whether an environment technique is needed.
    pub fn has_environment(&self) -> bool {
        self.environment != EnvironmentKind::None
    }
}
