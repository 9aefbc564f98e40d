//! `cvfarm render --estimator/--opt/--estimator-json/--time-budget` and `cvfarm bench`.

mod common;

use common::{fails_with, ok, run, s, scene, scratch};

#[test]
fn unknown_estimator_option_is_named_with_the_valid_ones() {
    let dir = scratch("bench_bad_opt");
    let out = dir.join("x.exr");
    let sc = scene("checkers");
    let o = run(&[
        "render",
        s(&sc),
        "--estimator",
        "ocv",
        "--opt",
        "speed=3",
        "-o",
        s(&out),
    ]);
    fails_with(&o, 2, "speed");
    assert!(
        common::stderr(&o).contains("spe"),
        "valid options not listed"
    );
    fails_with(
        &run(&[
            "render",
            s(&sc),
            "--estimator",
            "ocv",
            "--opt",
            "spe",
            "-o",
            s(&out),
        ]),
        2,
        "KEY=VALUE",
    );
    fails_with(
        &run(&[
            "render",
            s(&sc),
            "--estimator",
            "ocv",
            "--opt",
            "spe=0",
            "-o",
            s(&out),
        ]),
        2,
        "spe",
    );
    fails_with(
        &run(&[
            "render",
            s(&sc),
            "--estimator-json",
            "{\"kind\":\"ocv\",\"lambda\":\"x\"}",
            "-o",
            s(&out),
        ]),
        2,
        "lambda",
    );
    fails_with(
        &run(&[
            "render",
            s(&sc),
            "--estimator",
            "path",
            "--estimator-json",
            "{\"kind\":\"ocv\"}",
            "-o",
            s(&out),
        ]),
        2,
        "disagrees",
    );
    fails_with(
        &run(&["render", s(&sc), "--time-budget", "0", "-o", s(&out)]),
        2,
        "time-budget",
    );
    fails_with(
        &run(&[
            "render",
            s(&sc),
            "--time-budget",
            "1",
            "--spp",
            "4",
            "-o",
            s(&out),
        ]),
        2,
        "--spp",
    );
    fails_with(
        &run(&[
            "bench",
            s(&sc),
            "--estimators",
            "path,magic",
            "--out",
            s(&dir),
        ]),
        2,
        "magic",
    );
    assert!(!out.exists());
}

#[test]
fn estimator_json_file_and_time_budget_render() {
    let dir = scratch("bench_render_json");
    let json = dir.join("est.json");
    std::fs::write(&json, r#"{ "kind": "ocv", "spe": 4 }"#).unwrap();
    let out = dir.join("o.exr");
    let stats = dir.join("o.json");
    let arg = format!("@{}", s(&json));
    ok(&run(&[
        "render",
        s(&scene("checkers")),
        "--res",
        "32x24",
        "--estimator-json",
        &arg,
        "--time-budget",
        "0.5",
        "-o",
        s(&out),
        "--stats",
        s(&stats),
    ]));
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&stats).unwrap()).unwrap();
    assert_eq!(v["estimator"], "ocv");
    assert_eq!(v["estimator_options"]["spe"], 4);
    assert!(v["spp"].as_u64().unwrap() >= 1);
    assert_eq!(v["time_budget"], 0.5);
    let img = imageio::read_exr(&out).unwrap();
    assert_eq!((img.width, img.height), (32, 24));
}

#[test]
fn tiny_bench_writes_csv_markdown_and_svg() {
    let dir = scratch("bench_tiny");
    let sc = scene("checkers");
    // A small reference first, as a user would make one.
    let reference = dir.join("ref.exr");
    ok(&run(&[
        "render",
        s(&sc),
        "--res",
        "24x18",
        "--spp",
        "64",
        "-o",
        s(&reference),
    ]));
    let out = dir.join("out");
    let stdout = ok(&run(&[
        "bench",
        s(&sc),
        "--res",
        "24x18",
        "--estimators",
        "path,ocv:spe=4",
        "--reference",
        s(&reference),
        "--spp-series",
        "1,2,4",
        "--max-seconds",
        "30",
        "--out",
        s(&out),
    ]));
    assert!(stdout.contains("equal-time speedup"), "{stdout}");
    let csv = std::fs::read_to_string(out.join("bench.csv")).unwrap();
    let mut lines = csv.lines();
    assert_eq!(
        lines.next(),
        Some("estimator,spp,seconds,relmse,mse,wall_seconds,cpu_seconds")
    );
    let rows: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
    assert_eq!(rows.len(), 6, "{csv}");
    for r in &rows {
        assert_eq!(r.len(), 7);
        let relmse: f64 = r[3].parse().unwrap();
        assert!(relmse.is_finite() && relmse > 0.0, "{csv}");
    }
    // Error falls with samples for both.
    for est in ["path", "ocv:spe=4"] {
        let e: Vec<f64> = rows
            .iter()
            .filter(|r| r[0] == est)
            .map(|r| r[3].parse().unwrap())
            .collect();
        assert!(e[2] < e[0], "{est}: {e:?}");
    }
    let md = std::fs::read_to_string(out.join("bench.md")).unwrap();
    assert!(
        md.contains("equal-time speedup") && md.contains("| ocv:spe=4 |"),
        "{md}"
    );
    assert!(md.contains("load average"), "machine-load note missing");
    let svg = std::fs::read_to_string(out.join("bench.svg")).unwrap();
    assert!(
        svg.starts_with("<svg") && svg.matches("<polyline").count() == 2,
        "{svg}"
    );

    // Without a reference: error estimated from the pixel variance.
    let out2 = dir.join("noref");
    ok(&run(&[
        "bench",
        s(&sc),
        "--res",
        "16x12",
        "--estimators",
        "ocv:spe=4",
        "--spp-series",
        "2,4",
        "--out",
        s(&out2),
    ]));
    let csv = std::fs::read_to_string(out2.join("bench.csv")).unwrap();
    assert_eq!(csv.lines().count(), 5, "path is always the baseline: {csv}");

    // With `--seeds 3`: the seed-to-seed variance of one render, falling with samples.
    let out3 = dir.join("seeds");
    ok(&run(&[
        "bench",
        s(&sc),
        "--res",
        "24x18",
        "--estimators",
        "path",
        "--spp-series",
        "2,32",
        "--seeds",
        "3",
        "--reference",
        s(&reference),
        "--out",
        s(&out3),
    ]));
    let csv = std::fs::read_to_string(out3.join("bench.csv")).unwrap();
    let e: Vec<f64> = csv
        .lines()
        .skip(1)
        .map(|l| l.split(',').nth(3).unwrap().parse().unwrap())
        .collect();
    assert_eq!(e.len(), 2, "{csv}");
    assert!(e.iter().all(|x| x.is_finite() && *x > 0.0), "{csv}");
    assert!(e[1] < e[0], "{csv}");
    let md = std::fs::read_to_string(out3.join("bench.md")).unwrap();
    assert!(
        md.contains("seed-to-seed variance") && md.contains("--seeds 3"),
        "{md}"
    );
    // Fewer than one seed is a usage error.
    let bad = run(&["bench", s(&sc), "--seeds", "0", "--out", s(&out3)]);
    assert!(!bad.status.success());
}
