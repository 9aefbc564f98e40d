//! Reads the Mitsuba 3 reference images and the env map shipped in `shared/scenes-mitsuba`.

use std::path::PathBuf;

fn shared() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared/scenes-mitsuba")
}

#[test]
fn mitsuba_references_decode_with_the_documented_means() {
    // Means from shared/scenes-mitsuba/README.md (4096 spp references).
    let cases = [
        ("cbox_d5.exr", [0.2083, 0.1024, 0.0256]),
        ("manylights-4_d2.exr", [0.1061, 0.0664, 0.0662]),
        ("roughplastic-ggx_d5.exr", [0.1673, 0.1538, 0.0742]),
    ];
    for (name, want) in cases {
        let img = imageio::read_exr(shared().join("refs").join(name)).unwrap();
        assert_eq!((img.width, img.height), (128, 128), "{name}");
        let beauty = img
            .layer(imageio::BEAUTY)
            .expect("R,G,B channels form the beauty layer");
        let n = beauty.data.len() as f64;
        for c in 0..3 {
            let mean = beauty.data.iter().map(|p| f64::from(p[c])).sum::<f64>() / n;
            // The README rounds to 4 digits.
            assert!(
                (mean - want[c]).abs() <= 6e-5 + 1e-3 * want[c],
                "{name} channel {c}: {mean}"
            );
            assert!(beauty.data.iter().all(|p| p[c].is_finite()));
        }
    }
}

#[test]
fn museum_env_map_decodes() {
    let bytes = std::fs::read(shared().join("bsdf-spheres/roughplastic-ggx/museum.exr")).unwrap();
    let img = imageio::read_exr_bytes(&bytes).unwrap();
    assert_eq!((img.width, img.height), (512, 256)); // half-float lat-long map
    let main = img.main_layer().unwrap();
    assert_eq!(
        main.data.len() as u64,
        u64::from(img.width) * u64::from(img.height)
    );
    assert!(main.data.iter().all(|p| p.iter().all(|v| v.is_finite())));
    assert!(main.data.iter().any(|p| p[0] > 0.0));
}

#[test]
fn written_file_round_trips_through_the_file_system() {
    let dir = std::env::temp_dir().join(format!("imageio-test-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("two.exr");
    let layers = vec![
        imageio::RgbLayer {
            name: "beauty".into(),
            data: vec![[1.0, 2.0, 3.0]; 6],
        },
        imageio::RgbLayer {
            name: "variance".into(),
            data: vec![[0.5, 0.25, 0.125]; 6],
        },
    ];
    imageio::write_exr(&path, 3, 2, &layers).unwrap();
    let back = imageio::read_exr(&path).unwrap();
    assert_eq!(back.layers, layers);
    let png = dir.join("p.png");
    imageio::write_png_preview(&png, 3, 2, &layers[0].data).unwrap();
    let (w, h, px) = imageio::decode_ldr(&std::fs::read(&png).unwrap()).unwrap();
    assert_eq!((w, h), (3, 2));
    assert!(px.iter().all(|p| *p == [1.0, 1.0, 1.0]));
    std::fs::remove_dir_all(&dir).ok();
}
