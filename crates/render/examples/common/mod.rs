//! Setup shared by the speed examples (`render_speed`, `image_hash`): a scene file prepared
//! with the settings of `docs/perf/compare_mitsuba.sh` (max_depth 5, rr_depth 6 — no Russian
//! roulette —, seed 1, the scene's resolution) and, on request, a forced BVH kind.

use std::path::Path;

use render::accel::{Accel, AccelKind};
use render::{RenderScene, RenderSettings};

/// The BVH kind named by a command-line word (`wide`, `cwbvh`; anything else: `Auto`).
pub fn accel_kind(word: Option<&str>) -> AccelKind {
    match word {
        Some("wide") => AccelKind::Wide,
        Some("cwbvh") => AccelKind::Cwbvh,
        _ => AccelKind::Auto,
    }
}

/// Loads `path` and builds its render structures for `spp` samples with BVH `kind`; prints
/// the error and exits with status 1 on a bad scene.
pub fn prepare(path: &str, spp: u32, kind: AccelKind) -> (RenderScene, RenderSettings) {
    let fail = |e: &dyn std::fmt::Display| -> ! {
        eprintln!("{path}: {e}");
        std::process::exit(1);
    };
    let loaded = scene::load_file(Path::new(path)).unwrap_or_else(|e| fail(&e));
    let mut scene = loaded.scene;
    scene.integrator.max_depth = 5;
    scene.integrator.rr_depth = 6;
    let st = RenderSettings {
        spp,
        seed: 1,
        max_depth: 5,
        rr_depth: 6,
        ..RenderSettings::from_scene(&scene)
    };
    let mut rs = RenderScene::new(&scene, &st).unwrap_or_else(|e| fail(&e));
    if kind != AccelKind::Auto {
        let mesh_lights: Vec<_> = (0..scene.meshes.len())
            .map(|i| rs.lights.mesh_light(i))
            .collect();
        let sphere_lights: Vec<_> = (0..scene.spheres.len())
            .map(|i| rs.lights.sphere_light(i))
            .collect();
        rs.accel = Accel::with_kind(&scene, &mesh_lights, &sphere_lights, kind);
    }
    (rs, st)
}
