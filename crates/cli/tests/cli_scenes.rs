//! Every shipped scene (`scenes/<name>/scene.json`) is small, loads, and renders at a tiny
//! resolution without NaN/Inf and without being black.

mod common;

use common::*;

const EXPECTED: [&str; 7] = [
    "checkers",
    "colour-lamp",
    "cornell-box",
    "envmap",
    "many-lights",
    "many-lights-256",
    "veach-mis",
];

#[test]
fn the_example_scenes_are_shipped_and_small() {
    let names = shipped_scenes();
    for name in EXPECTED {
        assert!(
            names.iter().any(|n| n == name),
            "scenes/{name}/scene.json missing (have {names:?})"
        );
    }
    for name in &names {
        let dir = scenes_dir().join(name);
        let total: u64 = std::fs::read_dir(&dir)
            .unwrap()
            .filter_map(|e| e.ok()?.metadata().ok())
            .map(|m| m.len())
            .sum();
        assert!(
            total < 2 << 20,
            "scenes/{name} is {total} bytes (limit 2 MB)"
        );
    }
    let readme = std::fs::read_to_string(scenes_dir().join("README.md")).expect("scenes/README.md");
    for name in &names {
        assert!(
            readme.contains(&format!("`{name}`")),
            "scenes/README.md has no provenance line for {name}"
        );
    }
}

#[test]
fn every_shipped_scene_renders_finite_and_not_black() {
    let dir = scratch("all_scenes");
    for name in shipped_scenes() {
        let exr = dir.join(format!("{name}.exr"));
        let stats = dir.join(format!("{name}.json"));
        let o = run(&[
            "render",
            s(&scene(&name)),
            "--res",
            "32x24",
            "--spp",
            "4",
            "--seed",
            "1",
            "-o",
            s(&exr),
            "--stats",
            s(&stats),
        ]);
        ok(&o);
        let img = imageio::read_exr(&exr).unwrap();
        let beauty = img.layer(imageio::BEAUTY).unwrap();
        let bad = beauty
            .data
            .iter()
            .flatten()
            .filter(|v| !v.is_finite())
            .count();
        assert_eq!(bad, 0, "{name}: {bad} non-finite values");
        let st: serde_json::Value =
            serde_json::from_slice(&std::fs::read(&stats).unwrap()).unwrap();
        assert_eq!(
            st["rejected_samples"].as_u64(),
            Some(0),
            "{name}: rejected samples"
        );
        let emitters = st["features"]["emitters"].as_u64().unwrap_or(0);
        let expected_emitters = match name.as_str() {
            "cornell-box" | "envmap" => 1,
            "checkers" => 2,
            "colour-lamp" => 3,
            "veach-mis" => 4,
            "many-lights" => 64,
            "many-lights-256" => 256,
            _ => emitters,
        };
        assert_eq!(
            emitters, expected_emitters,
            "{name}: emitters in --stats features"
        );
        let mean: f64 = beauty
            .data
            .iter()
            .flatten()
            .map(|&v| f64::from(v))
            .sum::<f64>()
            / (beauty.data.len() * 3) as f64;
        assert!(mean > 1e-3, "{name}: image is black (mean {mean})");
    }
}

/// cvfarm's image mean of every shipped scene agrees with Mitsuba 3's (rendered from the
/// identical XML twin, `tests/data/mitsuba_scene_means.json`) within 5 standard errors of the
/// difference: ours from the EXR's per-pixel `variance` layer, Mitsuba's from its 4 passes.
#[test]
fn every_shipped_scene_matches_mitsuba_image_mean() {
    let dir = scratch("mitsuba_means");
    let data = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data/mitsuba_scene_means.json");
    let doc: serde_json::Value = serde_json::from_slice(&std::fs::read(data).unwrap()).unwrap();
    let mut failures = Vec::new();
    for e in doc["entries"].as_array().unwrap() {
        let name = e["scene"].as_str().unwrap();
        let (w, h) = (e["width"].as_u64().unwrap(), e["height"].as_u64().unwrap());
        let (depth, rr) = (
            e["max_depth"].as_i64().unwrap(),
            e["rr_depth"].as_i64().unwrap(),
        );
        let exr = dir.join(format!("{name}.exr"));
        ok(&run(&[
            "render",
            s(&scene(name)),
            "--res",
            &format!("{w}x{h}"),
            "--spp",
            "64",
            "--seed",
            "2",
            "--max-depth",
            &depth.to_string(),
            "--rr-depth",
            &rr.to_string(),
            "-o",
            s(&exr),
        ]));
        let img = imageio::read_exr(&exr).unwrap();
        let (beauty, var) = (
            &img.layer("beauty").unwrap().data,
            &img.layer("variance").unwrap().data,
        );
        let n = beauty.len() as f64;
        for c in 0..3 {
            let ours = beauty.iter().map(|p| f64::from(p[c])).sum::<f64>() / n;
            let se_ours = var.iter().map(|p| f64::from(p[c])).sum::<f64>().sqrt() / n;
            let theirs = e["mean"][c].as_f64().unwrap();
            let se_theirs = e["rel_se"][c].as_f64().unwrap() * theirs;
            let tol = 5.0 * (se_ours * se_ours + se_theirs * se_theirs).sqrt() + 1e-6;
            if (ours - theirs).abs() > tol {
                failures.push(format!(
                    "{name} channel {c}: cvfarm {ours:.5} vs Mitsuba {theirs:.5} (|Δ| {:.5} > 5σ = {tol:.5}, ratio {:.4})",
                    (ours - theirs).abs(),
                    ours / theirs
                ));
            }
        }
    }
    assert!(
        failures.is_empty(),
        "image means differ from Mitsuba:\n{}",
        failures.join("\n")
    );
}
