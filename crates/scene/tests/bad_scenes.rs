//! Bad scenes give clear errors (naming the field, element/line or file), never a panic.

use proptest::prelude::*;
use scene::desc::{GeometryDesc, SceneDesc, ShapeDesc, TransformOp};
use scene::{AssetError, MemoryAssets, SceneError};

fn base() -> SceneDesc {
    scene::from_json_str(
        r#"{ "camera": { "fov": 40 }, "film": { "width": 8, "height": 8 }, "shapes": [] }"#,
    )
    .unwrap()
}

fn shape(geometry: GeometryDesc) -> ShapeDesc {
    ShapeDesc {
        geometry,
        material: None,
        transform: vec![],
        emitter: None,
        flip_normals: false,
    }
}

fn load_err(desc: &SceneDesc, assets: &MemoryAssets) -> String {
    match scene::load(desc, assets) {
        Ok(_) => panic!("expected an error"),
        Err(e) => e.to_string(),
    }
}

fn xml(body: &str) -> String {
    format!(
        "<scene version=\"3.0.0\">\n<sensor type=\"perspective\"><float name=\"fov\" value=\"40\"/>\
         <film type=\"hdrfilm\"><rfilter type=\"box\"/></film></sensor>\n{body}\n</scene>"
    )
}

/// A UV sphere as an inline mesh, with the degenerate (zero-area) triangles at the poles that
/// naive generators produce: every quad of a ring is split in two, so each pole ring has
/// `segments` triangles with two coincident vertices.
fn uv_sphere(segments: u32, rings: u32) -> GeometryDesc {
    let mut positions = Vec::new();
    for r in 0..=rings {
        let theta = std::f32::consts::PI * r as f32 / rings as f32;
        for s in 0..=segments {
            let phi = 2.0 * std::f32::consts::PI * s as f32 / segments as f32;
            // Exact poles (sin π is not 0 in f32), as mesh exporters write them.
            let (st, ct) = if r == 0 || r == rings {
                (0.0, theta.cos().round())
            } else {
                (theta.sin(), theta.cos())
            };
            positions.push([st * phi.cos(), ct, st * phi.sin()]);
        }
    }
    let row = segments + 1;
    let mut indices = Vec::new();
    for r in 0..rings {
        for s in 0..segments {
            let (a, b, c, d) = (
                r * row + s,
                r * row + s + 1,
                (r + 1) * row + s,
                (r + 1) * row + s + 1,
            );
            indices.push([a, b, d]);
            indices.push([a, d, c]);
        }
    }
    GeometryDesc::Mesh {
        positions,
        indices,
        normals: None,
        uvs: None,
    }
}

#[test]
fn zero_axis_rotation_names_the_operation() {
    let mut d = base();
    for _ in 0..4 {
        d.shapes.push(shape(GeometryDesc::Cube));
    }
    d.shapes[3].transform = vec![
        TransformOp::Translate([0.0; 3]),
        TransformOp::Rotate {
            axis: [0.0; 3],
            angle: 30.0,
        },
    ];
    assert_eq!(
        load_err(&d, &MemoryAssets::new()),
        "shapes[3].transform[1].rotate.axis: zero vector"
    );
}

#[test]
fn nan_in_a_transform() {
    let mut d = base();
    d.shapes.push(shape(GeometryDesc::Cube));
    d.shapes[0].transform = vec![TransformOp::Scale([1.0, f32::NAN, 1.0])];
    assert_eq!(
        load_err(&d, &MemoryAssets::new()),
        "shapes[0].transform[0].scale: non-finite value"
    );
    let mut d = base();
    d.camera.transform = vec![TransformOp::Translate([f32::INFINITY, 0.0, 0.0])];
    assert!(load_err(&d, &MemoryAssets::new()).starts_with("camera.transform[0].translate"));
    // In XML the number itself is rejected, with element and line.
    let x = xml(
        "<shape type=\"cube\"><transform name=\"to_world\"><scale value=\"NaN\"/></transform></shape>",
    );
    let e = scene::mitsuba::import(&x, &MemoryAssets::new(), &[])
        .unwrap_err()
        .to_string();
    assert!(
        e.contains(":3:") && e.contains("<scale>") && e.contains("non-finite"),
        "{e}"
    );
}

#[test]
fn malformed_json_and_xml() {
    let e = scene::from_json_str("{ \"camera\": { \"fov\": 40 }, \n\"film\": [").unwrap_err();
    assert!(matches!(e, SceneError::Json { line: 2, .. }), "{e}");
    let e = scene::mitsuba::import(
        "<scene>\n<shape type=\"cube\">\n</scene>",
        &MemoryAssets::new(),
        &[],
    )
    .unwrap_err();
    assert!(matches!(e, SceneError::Xml { .. }), "{e}");
    assert!(e.to_string().contains("line"), "{e}");
    let e = scene::mitsuba::import("<notascene/>", &MemoryAssets::new(), &[])
        .unwrap_err()
        .to_string();
    assert!(e.contains("<scene>"), "{e}");
    let e = scene::mitsuba::import(
        "<scene><shape type=\"cube\"/></scene>",
        &MemoryAssets::new(),
        &[],
    )
    .unwrap_err();
    assert!(e.to_string().contains("no <sensor>"), "{e}");
}

#[test]
fn missing_mesh_file() {
    let mut d = base();
    d.shapes.push(shape(GeometryDesc::Obj {
        filename: "meshes/gone.obj".into(),
        face_normals: false,
    }));
    let e = scene::load(&d, &MemoryAssets::new()).unwrap_err();
    assert!(
        matches!(&e, SceneError::Asset(AssetError::NotFound { name }) if name == "meshes/gone.obj"),
        "{e}"
    );
    // Through the file system too.
    let e = scene::load(&d, &scene::DirAssets::new(env!("CARGO_MANIFEST_DIR"))).unwrap_err();
    assert!(e.to_string().contains("meshes/gone.obj"), "{e}");
    // And a name escaping the scene directory is refused before any file access.
    d.shapes[0].geometry = GeometryDesc::Obj {
        filename: "../../etc/passwd".into(),
        face_normals: false,
    };
    let e = scene::load(&d, &MemoryAssets::new()).unwrap_err();
    assert!(
        matches!(e, SceneError::Asset(AssetError::InvalidName { .. })),
        "{e}"
    );
}

#[test]
fn zero_area_light() {
    let mut d = base();
    let mut s = shape(GeometryDesc::Rectangle);
    s.transform = vec![TransformOp::Scale([1.0, 0.0, 1.0])];
    s.emitter = Some(scene::desc::AreaEmitterDesc { radiance: [1.0; 3] });
    d.shapes.push(s.clone());
    let e = load_err(&d, &MemoryAssets::new());
    assert!(
        e.starts_with("shapes[0].emitter: rectangle: emitter has zero total area"),
        "{e}"
    );
    // A zero-radius emitting sphere.
    d.shapes[0] = shape(GeometryDesc::Sphere {
        center: [0.0; 3],
        radius: 0.0,
    });
    d.shapes[0].emitter = s.emitter.clone();
    assert!(load_err(&d, &MemoryAssets::new()).starts_with("shapes[0].radius"));
    d.shapes[0].geometry = GeometryDesc::Sphere {
        center: [0.0; 3],
        radius: 1.0,
    };
    d.shapes[0].transform = vec![TransformOp::Scale([0.0; 3])];
    assert!(load_err(&d, &MemoryAssets::new()).contains("zero or non-finite world-space radius"));
    // Flattening a rectangle along its normal (singular transform) is fine: area is kept.
    let mut d = base();
    let mut flat = shape(GeometryDesc::Rectangle);
    flat.transform = vec![TransformOp::Scale([2.0, 2.0, 0.0])];
    flat.emitter = s.emitter.clone();
    d.shapes.push(flat);
    let l = scene::load(&d, &MemoryAssets::new()).unwrap();
    assert_eq!(l.scene.meshes[0].indices.len(), 2);
}

#[test]
fn degenerate_triangles_are_dropped_and_counted() {
    let mut d = base();
    d.shapes.push(shape(GeometryDesc::Cube));
    d.shapes.push(shape(uv_sphere(16, 8)));
    let l = scene::load(&d, &MemoryAssets::new()).unwrap();
    // Two pole rings of 16 quads each contribute one zero-area triangle per quad.
    assert_eq!(l.report.dropped_triangles, 32);
    assert_eq!(
        l.report.dropped_per_shape,
        vec![scene::DroppedTriangles {
            shape: 1,
            count: 32
        }]
    );
    assert_eq!(l.scene.meshes[1].indices.len(), 16 * 8 * 2 - 32);
    // Smooth normals at the sphere's vertices point outward.
    let m = &l.scene.meshes[1];
    for t in &m.indices {
        for &i in t {
            let (p, n) = (
                m.positions[i as usize],
                m.normals.as_ref().unwrap()[i as usize],
            );
            assert!(p.normalize().dot(n) > 0.95, "{p} {n}");
        }
    }
    // The report is serialisable for job records.
    let json = serde_json::to_string(&l.report).unwrap();
    assert!(json.contains("\"dropped_triangles\":32"), "{json}");
}

#[test]
fn mesh_with_only_degenerate_triangles_names_the_shape() {
    let mut d = base();
    d.shapes.push(shape(GeometryDesc::Cube));
    d.shapes.push(shape(GeometryDesc::Obj {
        filename: "flat.obj".into(),
        face_normals: false,
    }));
    let assets = MemoryAssets::new()
        .with(
            "flat.obj",
            b"v 0 0 0\nv 1 0 0\nv 2 0 0\nv nan 0 0\nf 1 2 3\nf 1 2 4\n".to_vec(),
        )
        .unwrap();
    let e = load_err(&d, &assets);
    assert_eq!(
        e,
        "shapes[1]: flat.obj: no non-degenerate triangle left (2 dropped)"
    );
}

#[test]
fn unknown_plugins_and_parameters_name_element_and_line() {
    let cases = [
        (
            "<shape type=\"cube\">\n<bsdf type=\"dielectric\"/></shape>",
            4,
            "bsdf type=\"dielectric\"",
        ),
        ("<shape type=\"cylinder\"/>", 3, "shape type=\"cylinder\""),
        ("<emitter type=\"point\"/>", 3, "emitter type=\"point\""),
        (
            "<integrator type=\"volpath\"/>",
            3,
            "integrator type=\"volpath\"",
        ),
        (
            "<shape type=\"cube\"><bsdf type=\"roughconductor\"><float name=\"alpha_u\" value=\"0.1\"/><float name=\"alpha_v\" value=\"0.3\"/></bsdf></shape>",
            3,
            "anisotropic",
        ),
        (
            "<shape type=\"cube\"><bsdf type=\"diffuse\"><float name=\"roughness\" value=\"1\"/></bsdf></shape>",
            3,
            "unsupported parameter `roughness`",
        ),
        (
            "<shape type=\"cube\"><ref id=\"nothing\"/></shape>",
            3,
            "no top-level object with id \"nothing\"",
        ),
    ];
    for (body, line, needle) in cases {
        let e = scene::mitsuba::import(&xml(body), &MemoryAssets::new(), &[]).unwrap_err();
        let SceneError::Mitsuba { line: l, .. } = &e else {
            panic!("{e}")
        };
        assert_eq!(*l, line, "{e}");
        assert!(e.to_string().contains(needle), "{e}");
    }
    // A non-box rfilter is a warning, not an error.
    let x = "<scene><sensor type=\"perspective\"><film type=\"hdrfilm\"><rfilter type=\"gaussian\"/></film></sensor></scene>";
    let (_, warnings) =
        scene::mitsuba::import_with_warnings(x, "s.xml", &MemoryAssets::new(), &[]).unwrap();
    assert!(
        warnings.iter().any(|w| w.contains("gaussian")),
        "{warnings:?}"
    );
}

#[test]
fn invalid_values_name_their_field() {
    type Edit = Box<dyn Fn(&mut SceneDesc)>;
    let cases: Vec<(Edit, &str)> = vec![
        (Box::new(|d| d.camera.fov = 0.0), "camera.fov"),
        (Box::new(|d| d.camera.far_clip = 0.001), "camera.far_clip"),
        (Box::new(|d| d.film.width = 0), "film.width"),
        (
            Box::new(|d| d.integrator.max_depth = -2),
            "integrator.max_depth",
        ),
        (
            Box::new(|d| {
                d.camera.transform = vec![TransformOp::LookAt {
                    origin: [0.0; 3],
                    target: [0.0, 1.0, 0.0],
                    up: [0.0, 1.0, 0.0],
                }]
            }),
            "camera.transform[0].look_at: up is zero or parallel",
        ),
        (
            Box::new(|d| {
                let mut s = shape(GeometryDesc::Cube);
                s.material = Some(scene::desc::MaterialRef::Named("nope".into()));
                d.shapes.push(s);
            }),
            "shapes[0].material: unknown material \"nope\"",
        ),
        (
            Box::new(|d| {
                let mut s = shape(GeometryDesc::Cube);
                s.emitter = Some(scene::desc::AreaEmitterDesc {
                    radiance: [1.0, -1.0, 0.0],
                });
                d.shapes.push(s);
            }),
            "shapes[0].emitter.radiance: negative value",
        ),
        (
            Box::new(|d| {
                let mut s = shape(GeometryDesc::Sphere {
                    center: [0.0; 3],
                    radius: 1.0,
                });
                s.transform = vec![TransformOp::Scale([1.0, 2.0, 1.0])];
                d.shapes.push(s);
            }),
            "shapes[0].transform: a sphere allows only translation, rotation and uniform scale",
        ),
        (
            Box::new(|d| {
                d.shapes.push(shape(GeometryDesc::Mesh {
                    positions: vec![[0.0; 3]; 3],
                    indices: vec![[0, 1, 2], [0, 1, 3]],
                    normals: None,
                    uvs: None,
                }))
            }),
            "shapes[0].indices[1]: index out of range",
        ),
        (
            Box::new(|d| {
                let mut s = shape(GeometryDesc::Cube);
                s.material = Some(scene::desc::MaterialRef::Inline(
                    scene::desc::MaterialDesc::RoughConductor {
                        distribution: scene::Distribution::Ggx,
                        alpha: 0.0,
                        eta: [1.0; 3],
                        k: [1.0; 3],
                        specular_reflectance: scene::desc::ColorDesc::Gray(1.0),
                    },
                ));
                d.shapes.push(s);
            }),
            "shapes[0].material.alpha",
        ),
    ];
    for (edit, want) in cases {
        let mut d = base();
        edit(&mut d);
        let e = load_err(&d, &MemoryAssets::new());
        assert!(e.starts_with(want), "{e} (wanted {want})");
    }
}

#[test]
fn corrupt_assets() {
    let mut d = base();
    d.shapes.push(shape(GeometryDesc::Ply {
        filename: "m.ply".into(),
        face_normals: false,
    }));
    let ply = b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nend_header\n\0\0";
    let e = load_err(
        &d,
        &MemoryAssets::new().with("m.ply", ply.to_vec()).unwrap(),
    );
    assert!(e.starts_with("mesh m.ply:"), "{e}");
    let mut d = base();
    d.environment = Some(scene::desc::EnvironmentDesc::Envmap {
        filename: "e.exr".into(),
        scale: 1.0,
        transform: vec![],
    });
    let e = load_err(
        &d,
        &MemoryAssets::new()
            .with("e.exr", vec![0x76, 0x2f, 0x31, 0x01, 2, 0, 0])
            .unwrap(),
    );
    assert!(e.starts_with("image e.exr:"), "{e}");
}

#[test]
fn every_prefix_of_a_real_scene_fails_cleanly() {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../../shared/scenes-mitsuba/cbox/scene.xml");
    let text = std::fs::read_to_string(path).unwrap();
    let assets = MemoryAssets::new();
    for cut in (0..text.len()).step_by(37) {
        if text.is_char_boundary(cut) {
            assert!(
                scene::mitsuba::import(&text[..cut], &assets, &[]).is_err(),
                "prefix {cut}"
            );
        }
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 200, ..ProptestConfig::default() })]

    #[test]
    fn random_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..400)) {
        let text = String::from_utf8_lossy(&bytes);
        let _ = scene::from_json_str(&text);
        let _ = scene::mitsuba::import(&text, &MemoryAssets::new(), &[]);
        let _ = scene::meshfile::obj::parse("r.obj", &bytes);
        let mut ply = b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n".to_vec();
        ply.extend_from_slice(&bytes);
        let _ = scene::meshfile::ply::parse("r.ply", &ply);
        let _ = scene::meshfile::ply::parse("r.ply", &bytes);
    }
}
