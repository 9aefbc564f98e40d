//! The four shared Mitsuba 3 scenes (`shared/scenes-mitsuba`) import, load and match what their
//! README documents: camera, counts, materials, emitters. Also the XML → desc → JSON → desc
//! round trip.

use std::path::PathBuf;

use glam::Vec3;
use scene::desc::{Distribution, FovAxis, GeometryDesc};
use scene::{BsdfKind, Color, EnvironmentKind, Features, Material};

fn shared(rel: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../../shared/scenes-mitsuba")
        .join(rel)
}

const SCENES: [&str; 4] = [
    "cbox/scene.xml",
    "manylights-4/scene.xml",
    "bsdf-spheres/roughplastic-ggx/scene.xml",
    "bsdf-spheres/roughconductor-ggx/scene.xml",
];

fn close(a: Vec3, b: Vec3) -> bool {
    (a - b).length() < 1e-4 * (1.0 + b.length())
}

#[test]
fn all_shared_scenes_round_trip_through_json() {
    for rel in SCENES {
        let (desc, _) = scene::read_desc_file(&shared(rel), &[]).unwrap();
        let json = scene::to_json_string(&desc);
        let back = scene::from_json_str(&json).unwrap_or_else(|e| panic!("{rel}: {e}\n{json}"));
        assert_eq!(back, desc, "{rel}");
    }
}

#[test]
fn cbox_camera_counts_and_materials() {
    let loaded = scene::load_file(&shared("cbox/scene.xml")).unwrap();
    let s = &loaded.scene;
    assert_eq!((s.film.width, s.film.height), (128, 128));
    assert_eq!(s.integrator.max_depth, 5);
    assert_eq!(s.integrator.rr_depth, 100);
    assert_eq!(s.integrator.sample_count, Some(64));
    // fov_axis smaller on a square film is the x fov.
    assert!((s.camera.fov_x_deg - 39.3077).abs() < 1e-4);
    assert_eq!((s.camera.near_clip, s.camera.far_clip), (10.0, 2800.0));
    let origin = s.camera.to_world.transform_point3(Vec3::ZERO);
    assert!(close(origin, Vec3::new(278.0, 273.0, -800.0)));
    assert!(close(s.camera.to_world.transform_vector3(Vec3::Z), Vec3::Z));
    // Camera +X is left = cross(up, dir) = Y × Z = world +X for this camera.
    assert!(close(
        s.camera.to_world.transform_vector3(Vec3::X),
        Vec3::Y.cross(Vec3::Z)
    ));

    assert_eq!(s.meshes.len(), 8);
    assert!(s.spheres.is_empty() && s.environment.is_none());
    let f = Features::of(s);
    assert_eq!(
        (f.emitters, f.area_emitters, f.emissive_triangles),
        (1, 1, 2)
    );
    assert_eq!(f.environment, EnvironmentKind::None);
    assert_eq!(
        f.bsdf_kinds.iter().copied().collect::<Vec<_>>(),
        vec![BsdfKind::Diffuse]
    );
    assert!(!f.two_sided && !f.delta_lobes && f.textures == 0);
    // 8 OBJ files: light 2, floor 2, ceiling 4 (two quads), back 2, walls 2+2, boxes 12+12.
    assert_eq!(f.triangles, 38);
    assert_eq!(f.max_depth, 5);

    let light = s.meshes.iter().find(|m| m.emitter.is_some()).unwrap();
    assert!(close(
        light.emitter.unwrap(),
        Vec3::new(18.387, 10.9873, 2.75357)
    ));
    // The luminaire is translated by y −0.5 and faces down (one-sided emitter).
    assert!(light.positions.iter().all(|p| (p.y - 548.3).abs() < 1e-3));
    let [a, b, c] = light.indices[0].map(|i| light.positions[i as usize]);
    assert!(
        (b - a).cross(c - a).y < 0.0,
        "luminaire front side faces down"
    );
    assert_eq!(
        s.materials[light.material as usize],
        Material::Diffuse {
            reflectance: Color::Rgb(Vec3::new(0.936461, 0.740433, 0.705267))
        }
    );
    // Only non-degenerate triangles; all meshes here are clean.
    assert_eq!(loaded.report.dropped_triangles, 0);
}

#[test]
fn manylights_counts_and_materials() {
    let loaded = scene::load_file(&shared("manylights-4/scene.xml")).unwrap();
    let s = &loaded.scene;
    let f = Features::of(s);
    assert_eq!(
        (f.emitters, f.area_emitters, f.emissive_triangles),
        (16, 16, 32)
    );
    assert_eq!(
        f.bsdf_kinds.iter().copied().collect::<Vec<_>>(),
        vec![
            BsdfKind::Diffuse,
            BsdfKind::RoughConductor,
            BsdfKind::RoughPlastic
        ]
    );
    assert!(f.two_sided);
    // 5 walls × 2 + 2 cubes × 12 + 16 lights × 2.
    assert_eq!(f.triangles, 10 + 24 + 32);
    assert!((s.camera.fov_x_deg - 39.3).abs() < 1e-5);
    let gold = s
        .meshes
        .iter()
        .find_map(|m| match &s.materials[m.material as usize] {
            Material::RoughConductor {
                distribution,
                alpha,
                eta,
                k,
                ..
            } => Some((*distribution, *alpha, *eta, *k)),
            _ => None,
        });
    let (dist, alpha, eta, k) = gold.unwrap();
    assert_eq!((dist, alpha), (Distribution::Ggx, 0.15));
    assert!(
        close(eta, Vec3::new(0.2004, 0.9240, 1.1022))
            && close(k, Vec3::new(3.9129, 2.4528, 2.1422))
    );
    let plastic = s.materials.iter().find_map(|m| match m {
        Material::RoughPlastic {
            eta,
            alpha,
            diffuse_reflectance,
            ..
        } => Some((*eta, *alpha, *diffuse_reflectance)),
        _ => None,
    });
    let (eta, alpha, diffuse) = plastic.unwrap();
    assert!((eta - 1.5).abs() < 1e-6 && alpha == 0.1);
    assert_eq!(diffuse, Color::Rgb(Vec3::new(0.1, 0.3, 0.6)));
    // The gold cube: scale 0.3, rotate y 20°, translate (−0.4, 0.3, −0.3): centred there, 0.6 wide.
    let cube = s
        .meshes
        .iter()
        .find(|m| {
            matches!(
                s.materials[m.material as usize],
                Material::RoughConductor { .. }
            )
        })
        .unwrap();
    let centre = cube.positions.iter().copied().sum::<Vec3>() / cube.positions.len() as f32;
    assert!(close(centre, Vec3::new(-0.4, 0.3, -0.3)));
    let (lo, hi) = cube
        .positions
        .iter()
        .fold((f32::MAX, f32::MIN), |(lo, hi), p| {
            (lo.min(p.y), hi.max(p.y))
        });
    assert!((lo - 0.0).abs() < 1e-5 && (hi - 0.6).abs() < 1e-5);
    // Rotation by +20° about y maps the +x face normal to (cos 20°, 0, −sin 20°).
    let n = cube.normals.as_ref().unwrap();
    let want = Vec3::new(20f32.to_radians().cos(), 0.0, -20f32.to_radians().sin());
    assert!(n.iter().any(|v| close(*v, want)), "rotated face normal");
    // Black lights (reflectance 0) still emit.
    assert!(
        s.meshes
            .iter()
            .filter(|m| m.emitter.is_some())
            .all(|m| m.emitter.unwrap().max_element() > 1.0)
    );
}

#[test]
fn bsdf_spheres_load_with_env_map() {
    for (rel, kind, n_spheres) in [
        (
            "bsdf-spheres/roughplastic-ggx/scene.xml",
            BsdfKind::RoughPlastic,
            4,
        ),
        (
            "bsdf-spheres/roughconductor-ggx/scene.xml",
            BsdfKind::RoughConductor,
            1,
        ),
    ] {
        let (desc, warnings) = scene::read_desc_file(&shared(rel), &[]).unwrap();
        assert!(warnings.is_empty(), "{warnings:?}");
        assert_eq!(desc.camera.fov_axis, FovAxis::X);
        assert_eq!(
            desc.shapes
                .iter()
                .filter(|s| matches!(s.geometry, GeometryDesc::Ply { .. }))
                .count(),
            n_spheres
        );
        let loaded = scene::load_file(&shared(rel)).unwrap();
        let s = &loaded.scene;
        let f = Features::of(s);
        assert_eq!(f.environment, EnvironmentKind::Envmap, "{rel}");
        assert_eq!((f.emitters, f.area_emitters), (2, 1), "{rel}");
        assert!(f.bsdf_kinds.contains(&kind) && f.bsdf_kinds.contains(&BsdfKind::Diffuse));
        assert!((s.camera.fov_x_deg - 34.0221).abs() < 1e-4);
        let origin = s.camera.to_world.transform_point3(Vec3::ZERO);
        assert!(close(origin, Vec3::new(-4.0, 0.0, 0.0)));
        // up = +z, dir = +x ⇒ left = up × dir = +y.
        assert!(close(s.camera.to_world.transform_vector3(Vec3::X), Vec3::Y));
        let Some(scene::Environment::Envmap { image, to_world }) = &s.environment else {
            panic!()
        };
        assert_eq!((image.width, image.height), (512, 256));
        assert_eq!(*to_world, glam::Mat3::IDENTITY);
        // 3968 faces per sphere PLY + 2 for the light; any degenerate ones are dropped and counted.
        assert_eq!(
            f.triangles + loaded.report.dropped_triangles,
            n_spheres * 3968 + 2,
            "{rel}"
        );
        let sphere = s.meshes.iter().find(|m| m.emitter.is_none()).unwrap();
        assert!(sphere.normals.is_some() && sphere.uvs.is_some());
        // PLY normals point outward from the sphere centre.
        let centre = sphere.positions.iter().copied().sum::<Vec3>() / sphere.positions.len() as f32;
        for (p, n) in sphere
            .positions
            .iter()
            .zip(sphere.normals.as_ref().unwrap())
            .take(200)
        {
            assert!((*p - centre).normalize().dot(*n) > 0.99);
        }
        // The area light: rectangle.obj rotated 120° about y, scaled 2, moved to (−4, 0, 6).
        let light = s.meshes.iter().find(|m| m.emitter.is_some()).unwrap();
        let lc = light.positions.iter().copied().sum::<Vec3>() / light.positions.len() as f32;
        assert!(close(lc, Vec3::new(-4.0, 0.0, 6.0)), "{lc}");
        assert!(close(
            light.emitter.unwrap(),
            Vec3::new(20.7108, 10.8546, 2.77115)
        ));
    }
}
