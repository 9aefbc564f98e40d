//! Mitsuba XML features one by one: spectra, named IORs, referenced emitters, spheres,
//! focal length, integrator flags, `$param`s and `<include>` through the file system.

use glam::Vec3;
use scene::desc::{
    ColorDesc, Distribution, FovAxis, GeometryDesc, MaterialDesc, MaterialRef, TextureDesc,
};
use scene::{MemoryAssets, SceneError};

fn import(body: &str) -> Result<scene::SceneDesc, SceneError> {
    let x = format!(
        "<scene version=\"3.0.0\"><sensor type=\"perspective\"><float name=\"fov\" value=\"40\"/>\
         <film type=\"hdrfilm\"><rfilter type=\"box\"/></film></sensor>{body}</scene>"
    );
    scene::mitsuba::import(&x, &MemoryAssets::new(), &[])
}

fn inline(d: &scene::SceneDesc, i: usize) -> &MaterialDesc {
    match &d.shapes[i].material {
        Some(MaterialRef::Inline(m)) => m,
        other => panic!("{other:?}"),
    }
}

#[test]
fn spectra_floats_and_named_iors() {
    let d = import(
        "<shape type=\"cube\"><bsdf type=\"roughplastic\"><string name=\"int_ior\" value=\"bk7\"/>\
         <string name=\"ext_ior\" value=\"air\"/><spectrum name=\"diffuse_reflectance\" value=\"0.3\"/>\
         <float name=\"specular_reflectance\" value=\"0.7\"/></bsdf></shape>\
         <shape type=\"cube\"><bsdf type=\"roughconductor\"><spectrum name=\"eta\" value=\"1.5\"/>\
         <rgb name=\"k\" value=\"1 2 3\"/><float name=\"alpha_u\" value=\"0.2\"/><float name=\"alpha_v\" value=\"0.2\"/>\
         <boolean name=\"sample_visible\" value=\"true\"/></bsdf></shape>",
    )
    .unwrap();
    let MaterialDesc::RoughPlastic {
        int_ior,
        ext_ior,
        diffuse_reflectance,
        specular_reflectance,
        distribution,
        alpha,
        ..
    } = inline(&d, 0)
    else {
        panic!()
    };
    assert_eq!((*int_ior, *ext_ior), (1.5046, 1.000_277));
    assert_eq!(
        (diffuse_reflectance, specular_reflectance),
        (&ColorDesc::Gray(0.3), &ColorDesc::Gray(0.7))
    );
    // Mitsuba's default distribution is Beckmann, default alpha 0.1.
    assert_eq!((*distribution, *alpha), (Distribution::Beckmann, 0.1));
    let MaterialDesc::RoughConductor { eta, k, alpha, .. } = inline(&d, 1) else {
        panic!()
    };
    assert_eq!((*eta, *k, *alpha), ([1.5; 3], [1.0, 2.0, 3.0], 0.2));
    let e = import("<shape type=\"cube\"><bsdf type=\"roughplastic\"><string name=\"int_ior\" value=\"unobtainium\"/></bsdf></shape>")
        .unwrap_err();
    assert!(e.to_string().contains("unknown IOR name"), "{e}");
}

#[test]
fn referenced_emitters_spheres_and_flags() {
    let d = import(
        "<integrator type=\"path\"><integer name=\"max_depth\" value=\"2\"/><boolean name=\"hide_emitters\" value=\"true\"/></integrator>\
         <emitter type=\"area\" id=\"lamp\"><rgb name=\"radiance\" value=\"4, 5, 6\"/></emitter>\
         <bsdf type=\"diffuse\" id=\"white\"/>\
         <shape type=\"sphere\"><point name=\"center\" x=\"1\" y=\"2\" z=\"3\"/><float name=\"radius\" value=\"0.5\"/>\
         <boolean name=\"flip_normals\" value=\"true\"/><ref id=\"lamp\"/><ref id=\"white\"/></shape>\
         <emitter type=\"constant\"><rgb name=\"radiance\" value=\"0.1\"/></emitter>",
    )
    .unwrap();
    assert_eq!(
        (
            d.integrator.max_depth,
            d.integrator.hide_emitters,
            d.integrator.rr_depth
        ),
        (2, true, 5)
    );
    let s = &d.shapes[0];
    assert_eq!(
        s.geometry,
        GeometryDesc::Sphere {
            center: [1.0, 2.0, 3.0],
            radius: 0.5
        }
    );
    assert!(s.flip_normals);
    assert_eq!(s.emitter.as_ref().unwrap().radiance, [4.0, 5.0, 6.0]);
    assert_eq!(s.material, Some(MaterialRef::Named("white".into())));
    assert_eq!(
        d.environment,
        Some(scene::desc::EnvironmentDesc::Constant { radiance: [0.1; 3] })
    );
    let l = scene::load(&d, &MemoryAssets::new()).unwrap();
    assert_eq!(l.scene.spheres[0].center, Vec3::new(1.0, 2.0, 3.0));
    assert!(l.scene.spheres[0].flip_normals);
    let f = scene::Features::of(&l.scene);
    assert_eq!(
        (f.emitters, f.area_emitters, f.spheres, f.triangles),
        (2, 1, 1, 0)
    );
    // An unreferenced top-level area emitter without id is an error; two environments too.
    assert!(
        import("<emitter type=\"area\"><rgb name=\"radiance\" value=\"1\"/></emitter>").is_err()
    );
    let e = import("<emitter type=\"constant\"/><emitter type=\"constant\"/>").unwrap_err();
    assert!(e.to_string().contains("more than one environment"), "{e}");
}

#[test]
fn focal_length_and_fov_axis() {
    let x = "<scene version=\"3.0.0\"><sensor type=\"perspective\"><string name=\"focal_length\" value=\"35mm\"/>\
             <film type=\"hdrfilm\"><integer name=\"width\" value=\"300\"/><integer name=\"height\" value=\"200\"/>\
             <rfilter type=\"box\"/></film></sensor></scene>";
    let d = scene::mitsuba::import(x, &MemoryAssets::new(), &[]).unwrap();
    assert_eq!(d.camera.fov_axis, FovAxis::Diagonal);
    let s = scene::load(&d, &MemoryAssets::new()).unwrap().scene;
    // 35 mm on a 36 × 24 film back, 3:2 image: the horizontal fov spans the 36 mm side.
    let want = (2.0 * (18.0f32 / 35.0).atan()).to_degrees();
    assert!(
        (s.camera.fov_x_deg - want).abs() < 1e-3,
        "{} vs {want}",
        s.camera.fov_x_deg
    );
    let x = x.replace(
        "<string name=\"focal_length\" value=\"35mm\"/>",
        "<float name=\"fov\" value=\"30\"/><string name=\"fov_axis\" value=\"y\"/>",
    );
    let d = scene::mitsuba::import(&x, &MemoryAssets::new(), &[]).unwrap();
    let s = scene::load(&d, &MemoryAssets::new()).unwrap().scene;
    let want = (2.0 * (1.5 * (15f32).to_radians().tan()).atan()).to_degrees();
    assert!((s.camera.fov_x_deg - want).abs() < 1e-4);
}

#[test]
fn files_params_and_includes_on_disk() {
    let dir = std::env::temp_dir().join(format!("scene-test-{}", std::process::id()));
    std::fs::create_dir_all(dir.join("parts")).unwrap();
    std::fs::write(
        dir.join("scene.xml"),
        "<scene version=\"3.0.0\">\n<default name=\"res\" value=\"32\"/>\n<default name=\"depth\" value=\"3\"/>\n\
         <integrator type=\"path\"><integer name=\"max_depth\" value=\"$depth\"/></integrator>\n\
         <sensor type=\"perspective\"><float name=\"fov\" value=\"40\"/><sampler type=\"independent\"/>\
         <film type=\"hdrfilm\"><integer name=\"width\" value=\"$res\"/><integer name=\"height\" value=\"$res\"/>\
         <rfilter type=\"box\"/></film></sensor>\n<include filename=\"parts/geo.xml\"/>\n</scene>",
    )
    .unwrap();
    std::fs::write(dir.join("parts/geo.xml"), "<scene version=\"3.0.0\"><shape type=\"obj\"><string name=\"filename\" value=\"parts/tri.obj\"/></shape></scene>").unwrap();
    std::fs::write(
        dir.join("parts/tri.obj"),
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
    )
    .unwrap();
    let l = scene::load_file(&dir.join("scene.xml")).unwrap();
    assert_eq!((l.scene.film.width, l.scene.integrator.max_depth), (32, 3));
    assert_eq!(
        l.scene.integrator.sample_count,
        Some(4),
        "Mitsuba's default sample_count"
    );
    assert_eq!(l.scene.meshes.len(), 1);
    let l = scene::load_file_with_params(&dir.join("scene.xml"), &[("res".into(), "8".into())])
        .unwrap();
    assert_eq!(l.scene.film.width, 8);
    // The same scene as native JSON next to it.
    let (desc, _) = scene::read_desc_file(&dir.join("scene.xml"), &[]).unwrap();
    std::fs::write(dir.join("scene.json"), scene::to_json_string(&desc)).unwrap();
    let j = scene::load_file(&dir.join("scene.json")).unwrap();
    assert_eq!(
        j.scene.meshes,
        scene::load_file(&dir.join("scene.xml"))
            .unwrap()
            .scene
            .meshes
    );
    assert!(matches!(
        scene::load_file(&dir.join("scene.txt")),
        Err(SceneError::Io { .. } | SceneError::UnknownFormat { .. })
    ));
    std::fs::write(dir.join("scene.txt"), "x").unwrap();
    assert!(matches!(
        scene::load_file(&dir.join("scene.txt")),
        Err(SceneError::UnknownFormat { .. })
    ));
    assert!(matches!(
        scene::load_file(&dir.join("missing.json")),
        Err(SceneError::Io { .. })
    ));
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn textures_by_id_are_shared() {
    let d = import(
        "<texture type=\"checkerboard\" id=\"c\"/>\
         <shape type=\"cube\"><bsdf type=\"diffuse\"><ref name=\"reflectance\" id=\"c\"/></bsdf></shape>\
         <shape type=\"cube\"><bsdf type=\"roughplastic\"><ref name=\"diffuse_reflectance\" id=\"c\"/></bsdf></shape>",
    )
    .unwrap();
    assert_eq!(d.textures.len(), 1);
    assert!(matches!(
        d.textures["c"],
        TextureDesc::Checkerboard {
            color0: [0.4, 0.4, 0.4],
            color1: [0.2, 0.2, 0.2],
            ..
        }
    ));
    let l = scene::load(&d, &MemoryAssets::new()).unwrap();
    assert_eq!(scene::Features::of(&l.scene).textures, 1);
}
