//! The native JSON format: one snippet per feature parses, loads (assets from memory) and
//! means what the docs say; malformed documents give line/column errors.

use glam::{Vec2, Vec3};
use scene::desc::{ColorDesc, GeometryDesc, MaterialDesc, TextureDesc};
use scene::{
    BsdfKind, Color, Environment, EnvironmentKind, Features, Material, MemoryAssets, SceneError,
    Texture,
};

/// A scene around `body` (a JSON fragment with shapes etc.).
fn doc(extra: &str) -> String {
    format!(
        r#"{{ "camera": {{ "fov": 45, "transform": [ {{ "look_at": {{ "origin": [0, 0, 5], "target": [0, 0, 0], "up": [0, 1, 0] }} }} ] }},
             "film": {{ "width": 16, "height": 8 }}, {extra} }}"#
    )
}

fn assets() -> MemoryAssets {
    let obj =
        "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nf 1/1 2/2 3/3 4/4\n";
    let ply = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n\
               element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n";
    let png =
        imageio::encode_png_preview(2, 1, &[[0.214_041, 0.214_041, 0.214_041], [1.0, 0.0, 0.0]])
            .unwrap();
    let exr = imageio::encode_exr(
        4,
        2,
        &[imageio::RgbLayer {
            name: "beauty".into(),
            data: vec![[2.0, 3.0, 4.0]; 8],
        }],
    )
    .unwrap();
    MemoryAssets::new()
        .with("meshes/quad.obj", obj.as_bytes().to_vec())
        .unwrap()
        .with("meshes/tri.ply", ply.as_bytes().to_vec())
        .unwrap()
        .with("tex/wood.png", png)
        .unwrap()
        .with("env/sky.exr", exr)
        .unwrap()
}

fn load(extra: &str) -> Result<scene::LoadedScene, SceneError> {
    let desc = scene::from_json_str(&doc(extra))?;
    scene::load(&desc, &assets())
}

#[test]
fn the_desc_module_example_loads() {
    // The example at the top of `desc.rs`.
    let json = r#"{
      "camera": { "fov": 39.3, "fov_axis": "x",
                  "transform": [ { "look_at": { "origin": [0, 1, 3.5], "target": [0, 1, 0], "up": [0, 1, 0] } } ] },
      "film": { "width": 256, "height": 256 },
      "integrator": { "max_depth": 5 },
      "materials": { "white": { "type": "diffuse", "reflectance": [0.8, 0.8, 0.8] } },
      "shapes": [
        { "type": "rectangle", "material": "white", "transform": [ { "rotate": { "axis": [1, 0, 0], "angle": -90 } } ] },
        { "type": "sphere", "center": [0, 1.9, 0], "radius": 0.1, "material": "white",
          "emitter": { "radiance": [10, 10, 10] } }
      ]
    }"#;
    let desc = scene::from_json_str(json).unwrap();
    let s = scene::load(&desc, &MemoryAssets::new()).unwrap().scene;
    // rotate −90° about x turns the rectangle's +Z normal into +Y: a floor.
    let floor = &s.meshes[0];
    assert!(floor.positions.iter().all(|p| p.y.abs() < 1e-6));
    assert!((floor.normals.as_ref().unwrap()[0] - Vec3::Y).length() < 1e-6);
    assert_eq!(s.spheres[0].center, Vec3::new(0.0, 1.9, 0.0));
    assert_eq!(s.spheres[0].radius, 0.1);
    let f = Features::of(&s);
    assert_eq!(
        (f.emitters, f.area_emitters, f.triangles, f.spheres),
        (1, 1, 2, 1)
    );
    assert_eq!(s.integrator.max_depth, 5);
}

#[test]
fn shapes_of_every_type() {
    let l = load(
        r#""shapes": [
            { "type": "obj", "filename": "meshes/quad.obj" },
            { "type": "ply", "filename": "meshes/tri.ply", "face_normals": true },
            { "type": "rectangle", "flip_normals": true },
            { "type": "cube", "transform": [ { "scale": [2, 2, 2] } ] },
            { "type": "sphere", "radius": 2, "transform": [ { "translate": [1, 0, 0] } ] },
            { "type": "mesh", "positions": [[0,0,0],[1,0,0],[0,0,1]], "indices": [[0,2,1]], "uvs": [[0,0],[1,0],[0,1]] }
        ]"#,
    )
    .unwrap();
    let s = &l.scene;
    assert_eq!(s.meshes.len(), 5);
    assert_eq!(s.spheres.len(), 1);
    // OBJ: v flipped, quad fanned, smooth normals computed (flat quad → +Z).
    let obj = &s.meshes[0];
    assert_eq!(obj.indices.len(), 2);
    assert_eq!(obj.uvs.as_ref().unwrap()[0], Vec2::new(0.0, 1.0));
    assert!(
        obj.normals
            .as_ref()
            .unwrap()
            .iter()
            .all(|n| (*n - Vec3::Z).length() < 1e-6)
    );
    // PLY with face_normals: no vertex normals.
    assert!(s.meshes[1].normals.is_none());
    // flip_normals: winding reversed and normals negated.
    let rect = &s.meshes[2];
    let [a, b, c] = rect.indices[0].map(|i| rect.positions[i as usize]);
    assert!((b - a).cross(c - a).z < 0.0);
    assert!(
        rect.normals
            .as_ref()
            .unwrap()
            .iter()
            .all(|n| *n == Vec3::NEG_Z)
    );
    // Cube scaled by 2: extent ±2.
    assert!(
        s.meshes[3]
            .positions
            .iter()
            .all(|p| p.abs().max_element() == 2.0)
    );
    assert_eq!((s.spheres[0].center, s.spheres[0].radius), (Vec3::X, 2.0));
    // Every shape without a material gets the one default grey diffuse.
    assert_eq!(
        s.materials,
        vec![Material::Diffuse {
            reflectance: Color::Rgb(Vec3::splat(0.5))
        }]
    );
    assert_eq!(Features::of(s).triangles, 2 + 1 + 2 + 12 + 1);
}

#[test]
fn materials_and_textures() {
    let l = load(
        r#""textures": {
              "wood": { "type": "bitmap", "filename": "tex/wood.png", "filter": "nearest", "wrap": "clamp" },
              "sky": { "type": "bitmap", "filename": "env/sky.exr" },
              "checks": { "type": "checkerboard", "color0": [0.9, 0.9, 0.9], "color1": [0.1, 0.1, 0.1],
                          "uv_transform": [ { "scale": [8, 8, 1] }, { "translate": [0.5, 0, 0] } ] } },
           "materials": {
              "a": { "type": "diffuse", "reflectance": { "texture": "wood" } },
              "b": { "type": "conductor" },
              "c": { "type": "roughconductor", "distribution": "beckmann", "alpha": 0.2, "specular_reflectance": 0.9 },
              "d": { "type": "roughplastic", "int_ior": 1.5, "ext_ior": 1.0, "diffuse_reflectance": { "texture": "checks" } },
              "e": { "type": "twosided", "bsdf": { "type": "diffuse", "reflectance": { "texture": "sky" } } } },
           "shapes": [
              { "type": "rectangle", "material": "a" }, { "type": "rectangle", "material": "b" },
              { "type": "rectangle", "material": "c" }, { "type": "rectangle", "material": "d" },
              { "type": "rectangle", "material": "e" },
              { "type": "cube", "material": { "type": "diffuse", "reflectance": 0.25 } } ]"#,
    )
    .unwrap();
    let s = &l.scene;
    // Textures are indexed in name order: checks, sky, wood.
    let Texture::Bitmap {
        image,
        filter,
        wrap,
        ..
    } = &s.textures[2]
    else {
        panic!()
    };
    assert_eq!((image.width, image.height), (2, 1));
    // PNG is sRGB: encoded 0.5 → linear 0.214.
    assert!(
        (image.data[0].x - 0.214_041).abs() < 3e-3,
        "{}",
        image.data[0]
    );
    assert_eq!(
        (*filter, *wrap),
        (scene::TextureFilter::Nearest, scene::TextureWrap::Clamp)
    );
    // EXR is linear, as stored.
    let Texture::Bitmap { image, .. } = &s.textures[1] else {
        panic!()
    };
    assert_eq!(image.data[0], Vec3::new(2.0, 3.0, 4.0));
    let Texture::Checkerboard {
        uv_transform,
        color0,
        ..
    } = &s.textures[0]
    else {
        panic!()
    };
    assert_eq!(*color0, Vec3::splat(0.9));
    assert_eq!(
        uv_transform.transform_point2(Vec2::new(0.5, 0.25)),
        Vec2::new(4.5, 2.0)
    );
    // Materials: named ones in name order, then the inline one.
    assert_eq!(
        s.materials[0],
        Material::Diffuse {
            reflectance: Color::Texture(2)
        }
    );
    assert!(matches!(s.materials[1], Material::Conductor { .. }));
    assert!(matches!(
        s.materials[2],
        Material::RoughConductor {
            alpha: 0.2,
            distribution: scene::Distribution::Beckmann,
            ..
        }
    ));
    let Material::RoughPlastic {
        eta,
        diffuse_reflectance,
        ..
    } = &s.materials[3]
    else {
        panic!()
    };
    assert_eq!((*eta, *diffuse_reflectance), (1.5, Color::Texture(0)));
    assert!(
        matches!(&s.materials[4], Material::TwoSided(inner) if **inner == Material::Diffuse { reflectance: Color::Texture(1) })
    );
    assert_eq!(
        s.materials[5],
        Material::Diffuse {
            reflectance: Color::Rgb(Vec3::splat(0.25))
        }
    );
    let f = Features::of(s);
    assert_eq!(f.bsdf_kinds.len(), 4);
    assert!(f.bsdf_kinds.contains(&BsdfKind::Conductor));
    assert!(f.delta_lobes && f.two_sided);
    assert_eq!(f.textures, 3);
    assert_eq!(f.emitters, 0);
}

#[test]
fn environments() {
    let l = load(
        r#""shapes": [ { "type": "cube" } ],
           "environment": { "type": "envmap", "filename": "env/sky.exr", "scale": 0.5,
                            "transform": [ { "rotate": { "axis": [0, 1, 0], "angle": 90 } } ] }"#,
    )
    .unwrap();
    let Some(Environment::Envmap { image, to_world }) = &l.scene.environment else {
        panic!()
    };
    assert_eq!(image.data[3], Vec3::new(1.0, 1.5, 2.0), "scale applied");
    assert!((*to_world * Vec3::X - Vec3::NEG_Z).length() < 1e-6);
    let f = Features::of(&l.scene);
    assert_eq!((f.emitters, f.environment), (1, EnvironmentKind::Envmap));

    let l = load(r#""shapes": [ { "type": "cube" } ], "environment": { "type": "constant", "radiance": [1, 2, 3] }"#).unwrap();
    assert_eq!(
        l.scene.environment,
        Some(Environment::Constant {
            radiance: Vec3::new(1.0, 2.0, 3.0)
        })
    );
    assert_eq!(
        Features::of(&l.scene).environment,
        EnvironmentKind::Constant
    );
    // A translated env map is rejected.
    let e = load(r#""shapes": [], "environment": { "type": "envmap", "filename": "env/sky.exr", "transform": [ { "translate": [1, 0, 0] } ] }"#)
        .unwrap_err();
    assert!(e.to_string().starts_with("environment.transform"), "{e}");
}

#[test]
fn integrator_and_camera_settings() {
    let d = scene::from_json_str(&doc(
        r#""integrator": { "max_depth": 2, "rr_depth": 3, "hide_emitters": true, "sample_count": 16 }, "shapes": []"#,
    ))
    .unwrap();
    let s = scene::load(&d, &MemoryAssets::new()).unwrap().scene;
    assert_eq!(
        (
            s.integrator.max_depth,
            s.integrator.rr_depth,
            s.integrator.hide_emitters
        ),
        (2, 3, true)
    );
    assert_eq!(s.integrator.sample_count, Some(16));
    assert!(Features::of(&s).direct_only);
    assert_eq!(s.camera.fov_x_deg, 45.0);
    assert_eq!((s.camera.near_clip, s.camera.far_clip), (0.01, 10_000.0));
    // Defaults when the integrator block is absent.
    let d = scene::from_json_str(&doc(r#""shapes": []"#)).unwrap();
    assert_eq!(d.integrator, scene::desc::IntegratorDesc::default());
}

#[test]
fn json_errors_carry_line_and_column() {
    let e = scene::from_json_str("{\n  \"camera\": { \"fov\": 45 },\n  \"film\": { \"width\": 16, \"height\": 8 }\n  \"shapes\": []\n}")
        .unwrap_err();
    let SceneError::Json { line, column, .. } = e else {
        panic!("{e}")
    };
    assert_eq!((line, column), (4, 3));
    // Unknown fields are rejected, in shapes too (where serde's flatten is replaced by a check).
    for (extra, needle) in [
        (r#""shapes": [], "colour": 1"#, "unknown field `colour`"),
        (
            r#""shapes": [ { "type": "cube", "radius": 2 } ]"#,
            "field `radius` is not allowed",
        ),
        (r#""shapes": [ { "type": "obj" } ]"#, "needs `filename`"),
        (
            r#""shapes": [ { "type": "torus" } ]"#,
            "unknown shape type `torus`",
        ),
        (
            r#""shapes": [ { "type": "cube", "materail": "x" } ]"#,
            "unknown field `materail`",
        ),
        (
            r#""shapes": [], "materials": { "m": { "type": "glass" } }"#,
            "unknown variant `glass`",
        ),
    ] {
        let e = scene::from_json_str(&doc(extra)).unwrap_err().to_string();
        assert!(e.contains(needle) && e.contains("line"), "{extra}: {e}");
    }
}

#[test]
fn desc_round_trips_through_json() {
    let d = scene::from_json_str(&doc(
        r#""textures": { "t": { "type": "checkerboard" } },
           "materials": { "m": { "type": "roughplastic", "diffuse_reflectance": { "texture": "t" } } },
           "shapes": [ { "type": "mesh", "positions": [[0,0,0],[1,0,0],[0,1,0]], "indices": [[0,1,2]],
                         "material": "m", "emitter": { "radiance": [1, 1, 1] }, "flip_normals": true },
                       { "type": "sphere", "material": { "type": "twosided", "bsdf": { "type": "diffuse" } } } ],
           "environment": { "type": "constant", "radiance": [0.1, 0.2, 0.3] }"#,
    ))
    .unwrap();
    let back = scene::from_json_str(&scene::to_json_string(&d)).unwrap();
    assert_eq!(back, d);
    assert!(matches!(
        d.shapes[1].geometry,
        GeometryDesc::Sphere { radius: 1.0, .. }
    ));
    assert!(matches!(
        &d.materials["m"],
        MaterialDesc::RoughPlastic {
            diffuse_reflectance: ColorDesc::Texture { .. },
            ..
        }
    ));
    assert!(matches!(
        d.textures["t"],
        TextureDesc::Checkerboard {
            color0: [0.4, 0.4, 0.4],
            ..
        }
    ));
}

/// Every JSON snippet in the format's docs (`src/desc.rs`) is valid and means what it says:
/// fragments `"key": value` are parsed as the field they show.
#[test]
fn doc_snippets_parse() {
    let src = include_str!("../src/desc.rs");
    let mut blocks = Vec::new();
    let mut current: Option<String> = None;
    for line in src.lines() {
        let t = line.trim_start();
        let Some(doc) = t.strip_prefix("///").or_else(|| t.strip_prefix("//!")) else {
            continue;
        };
        let doc = doc.strip_prefix(' ').unwrap_or(doc);
        match (&mut current, doc.trim()) {
            (None, "```json") => current = Some(String::new()),
            (Some(b), "```") => {
                blocks.push(std::mem::take(b));
                current = None;
            }
            (Some(b), _) => {
                b.push_str(doc);
                b.push('\n');
            }
            _ => {}
        }
    }
    assert!(blocks.len() >= 12, "found {} snippets", blocks.len());
    let mut checked = 0;
    for b in &blocks {
        let t = b.trim();
        if t.starts_with("{ \"camera\"") || t.starts_with("{\n") {
            scene::from_json_str(t).unwrap_or_else(|e| panic!("{e}\n{t}"));
            checked += 1;
            continue;
        }
        if t.starts_with('[')
            && !t.contains('\n')
            && t.contains("look_at") | t.contains("matrix") | t.contains("scale")
        {
            let ops: scene::desc::TransformDesc =
                serde_json::from_str(t).unwrap_or_else(|e| panic!("{e}\n{t}"));
            scene::transform::to_matrix(&ops, "snippet").unwrap();
            checked += 1;
            continue;
        }
        if let Some((key, value)) = t.split_once(':').filter(|(k, _)| k.starts_with('"')) {
            let key = key.trim().trim_matches('"');
            let v = value.trim();
            let r = match key {
                "camera" => serde_json::from_str::<scene::desc::CameraDesc>(v).map(drop),
                "film" => serde_json::from_str::<scene::desc::FilmDesc>(v).map(drop),
                "integrator" => serde_json::from_str::<scene::desc::IntegratorDesc>(v).map(drop),
                "textures" => {
                    serde_json::from_str::<std::collections::BTreeMap<String, TextureDesc>>(v)
                        .map(drop)
                }
                "materials" => {
                    serde_json::from_str::<std::collections::BTreeMap<String, MaterialDesc>>(v)
                        .map(drop)
                }
                "shapes" => serde_json::from_str::<Vec<scene::desc::ShapeDesc>>(v).map(drop),
                "emitter" => serde_json::from_str::<scene::desc::AreaEmitterDesc>(v).map(drop),
                "environment" => serde_json::from_str::<scene::desc::EnvironmentDesc>(v).map(drop),
                _ => continue,
            };
            r.unwrap_or_else(|e| panic!("snippet for {key}: {e}\n{t}"));
            checked += 1;
        }
    }
    assert!(
        checked >= 12,
        "checked {checked} of {} snippets",
        blocks.len()
    );
}
