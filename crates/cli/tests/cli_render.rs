//! `cvfarm render` and `cvfarm compare` end to end: the real binary, real files.

mod common;

use common::*;

/// Reads the `beauty` layer of an EXR written by `cvfarm render`.
fn beauty(path: &std::path::Path) -> (u32, u32, Vec<[f32; 3]>) {
    let img = imageio::read_exr(path).expect("readable EXR");
    let layer = img.layer(imageio::BEAUTY).expect("beauty layer");
    (img.width, img.height, layer.data.clone())
}

#[test]
fn renders_cornell_box_to_exr_and_png_and_compares_with_itself() {
    let dir = scratch("render_cbox");
    let (exr, png, stats) = (
        dir.join("out/cbox.exr"),
        dir.join("out/cbox.png"),
        dir.join("stats.json"),
    );
    let o = run(&[
        "render",
        s(&scene("cornell-box")),
        "--spp",
        "4",
        "--res",
        "40x30",
        "--max-depth",
        "3",
        "--seed",
        "3",
        "--threads",
        "2",
        "-o",
        s(&exr),
        "--png",
        s(&png),
        "--stats",
        s(&stats),
    ]);
    let out = ok(&o);
    // not a terminal: no progress bar, nothing on stderr; one summary line (time, samples/s, rays/s)
    assert_eq!(stderr(&o), "", "stderr should be empty when not a TTY");
    assert_eq!(out.lines().count(), 1, "one summary line: {out}");
    assert!(
        out.contains("samples/s") && out.contains("rays/s"),
        "summary: {out}"
    );

    let (w, h, px) = beauty(&exr);
    assert_eq!((w, h), (40, 30));
    assert!(
        px.iter().flatten().all(|v| v.is_finite() && *v >= 0.0),
        "negative or non-finite pixel"
    );
    let mean: f64 = px.iter().map(|p| f64::from(p[0])).sum::<f64>() / px.len() as f64;
    assert!(
        mean > 0.01,
        "cornell box should not be black (mean R {mean})"
    );
    let img = imageio::read_exr(&exr).unwrap();
    for layer in ["variance", "albedo", "normal"] {
        assert!(img.layer(layer).is_some(), "layer {layer} missing");
    }
    let png_bytes = std::fs::read(&png).expect("png written");
    assert_eq!(&png_bytes[1..4], b"PNG");

    let st: serde_json::Value = serde_json::from_slice(&std::fs::read(&stats).unwrap()).unwrap();
    assert_eq!(st["samples"].as_u64(), Some(40 * 30 * 4));
    assert!(
        st["rays"].as_u64().unwrap() >= 40 * 30 * 4,
        "at least one ray per sample"
    );
    assert_eq!(st["max_depth"].as_i64(), Some(3));

    // compare with itself: zero error, table and JSON forms
    let table = ok(&run(&["compare", s(&exr), s(&exr)]));
    assert!(
        table.contains("relMSE") && table.contains("0.000000e0"),
        "{table}"
    );
    let json: serde_json::Value =
        serde_json::from_str(&ok(&run(&["compare", s(&exr), s(&exr), "--json"])))
            .expect("compare --json is JSON");
    assert_eq!(json["rel_mse"].as_f64(), Some(0.0));
    assert_eq!(json["non_finite_values"].as_u64(), Some(0));
    assert_eq!(json["mean_ratio"][0].as_f64(), Some(1.0));
}

#[test]
fn same_seed_gives_identical_image_whatever_threads_and_tiles() {
    let dir = scratch("determinism");
    let common = [
        "--spp",
        "3",
        "--res",
        "37x21",
        "--seed",
        "11",
        "--max-depth",
        "4",
    ];
    let a = dir.join("a.exr");
    let b = dir.join("b.exr");
    let c = dir.join("c.exr");
    let sc = scene("cornell-box");
    let mut args = vec!["render", s(&sc)];
    args.extend(common);
    ok(&run(&[
        &args[..],
        &["--threads", "1", "--tile-size", "8", "-o", s(&a)],
    ]
    .concat()));
    ok(&run(&[
        &args[..],
        &["--threads", "2", "--tile-size", "13", "-o", s(&b)],
    ]
    .concat()));
    assert_eq!(
        beauty(&a).2,
        beauty(&b).2,
        "image depends on threads/tile size"
    );
    // a different seed gives a different (noisy) image
    ok(&run(&[
        "render",
        s(&sc),
        "--spp",
        "3",
        "--res",
        "37x21",
        "--seed",
        "12",
        "--max-depth",
        "4",
        "-o",
        s(&c),
    ]));
    assert_ne!(beauty(&a).2, beauty(&c).2, "seed has no effect");
}

/// `--sampler independent` (also `CVFARM_SAMPLER`) gives another image, the same for any
/// thread count, and the statistics name it.
#[test]
fn the_independent_sampler_is_deterministic_and_recorded() {
    let dir = scratch("sampler");
    let sc = scene("cornell-box");
    let render_with = |out: &std::path::Path, threads: &str, sampler: Option<&str>| {
        let mut cmd = cvfarm();
        cmd.args([
            "render",
            s(&sc),
            "--spp",
            "3",
            "--res",
            "24x16",
            "--threads",
            threads,
        ])
        .args(["-o", s(out), "--stats", s(&out.with_extension("json"))]);
        if let Some(k) = sampler {
            cmd.env("CVFARM_SAMPLER", k);
        }
        ok(&cmd.output().unwrap());
        let st: serde_json::Value =
            serde_json::from_slice(&std::fs::read(out.with_extension("json")).unwrap()).unwrap();
        (beauty(out).2, st["sampler"].as_str().unwrap().to_string())
    };
    let (sobol, k0) = render_with(&dir.join("sobol.exr"), "1", None);
    let (a, k1) = render_with(&dir.join("a.exr"), "1", Some("independent"));
    let (b, _) = render_with(&dir.join("b.exr"), "2", Some("independent"));
    assert_eq!((k0.as_str(), k1.as_str()), ("sobol", "independent"));
    assert_eq!(a, b, "the independent image depends on the thread count");
    assert_ne!(a, sobol, "--sampler has no effect");
    let o = cvfarm()
        .args([
            "render",
            s(&sc),
            "--sampler",
            "halton",
            "-o",
            s(&dir.join("x.exr")),
        ])
        .output()
        .unwrap();
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("halton"));
}

#[test]
fn environment_variables_set_flags() {
    let dir = scratch("env_vars");
    let (exr, stats) = (dir.join("env.exr"), dir.join("env.json"));
    let o = cvfarm()
        .args(["render", s(&scene("checkers"))])
        .env("CVFARM_SPP", "2")
        .env("CVFARM_RES", "16x8")
        .env("CVFARM_SEED", "5")
        .env("CVFARM_OUTPUT", s(&exr))
        .env("CVFARM_STATS", s(&stats))
        .output()
        .unwrap();
    ok(&o);
    let st: serde_json::Value = serde_json::from_slice(&std::fs::read(&stats).unwrap()).unwrap();
    assert_eq!(
        (
            st["spp"].as_u64(),
            st["width"].as_u64(),
            st["seed"].as_u64()
        ),
        (Some(2), Some(16), Some(5))
    );
    // an explicit flag wins over the variable
    let o = cvfarm()
        .args([
            "render",
            s(&scene("checkers")),
            "--spp",
            "1",
            "-o",
            s(&exr),
            "--stats",
            s(&stats),
        ])
        .env("CVFARM_SPP", "2")
        .env("CVFARM_RES", "16x8")
        .output()
        .unwrap();
    ok(&o);
    let st: serde_json::Value = serde_json::from_slice(&std::fs::read(&stats).unwrap()).unwrap();
    assert_eq!(st["spp"].as_u64(), Some(1));
    // boolean flags accept the usual spellings (1/0, yes/no, true/false)
    for (value, is_json) in [("1", true), ("yes", true), ("0", false), ("false", false)] {
        let o = cvfarm()
            .args(["compare", s(&exr), s(&exr)])
            .env("CVFARM_JSON", value)
            .output()
            .unwrap();
        let text = ok(&o);
        assert_eq!(
            serde_json::from_str::<serde_json::Value>(&text).is_ok(),
            is_json,
            "CVFARM_JSON={value}: {text}"
        );
    }
}

#[test]
fn compare_reports_error_of_a_noisy_image_against_a_better_one() {
    let dir = scratch("compare_noisy");
    let (noisy, better) = (dir.join("noisy.exr"), dir.join("better.exr"));
    let sc = scene("cornell-box");
    ok(&run(&[
        "render",
        s(&sc),
        "--spp",
        "1",
        "--res",
        "24x24",
        "--seed",
        "1",
        "-o",
        s(&noisy),
    ]));
    ok(&run(&[
        "render",
        s(&sc),
        "--spp",
        "16",
        "--res",
        "24x24",
        "--seed",
        "2",
        "-o",
        s(&better),
    ]));
    let json: serde_json::Value =
        serde_json::from_str(&ok(&run(&["compare", s(&noisy), s(&better), "--json"]))).unwrap();
    let rel = json["rel_mse"].as_f64().unwrap();
    assert!(rel > 0.0 && rel.is_finite(), "relMSE {rel}");
    // --max-rel-mse: a generous limit passes, a tiny one fails with status 3
    let o = run(&[
        "compare",
        s(&noisy),
        s(&better),
        "--max-rel-mse",
        &format!("{}", rel * 2.0),
    ]);
    ok(&o);
    let o = run(&[
        "compare",
        s(&noisy),
        s(&better),
        "--max-rel-mse",
        &format!("{}", rel / 2.0),
    ]);
    assert_eq!(o.status.code(), Some(3), "stderr: {}", stderr(&o));
    assert!(stderr(&o).contains("too different"));
}

/// The Mitsuba 3 XML twin of `scenes/checkers` (`tests/data/checkers-twin.xml`) imports to the
/// same scene: same seed ⇒ the very same image as the native JSON; `-D` sets XML parameters.
#[test]
fn mitsuba_xml_twin_renders_exactly_like_the_native_scene() {
    let dir = scratch("xml_twin");
    let xml = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/checkers-twin.xml");
    let (a, b, c) = (
        dir.join("json.exr"),
        dir.join("xml.exr"),
        dir.join("defined.exr"),
    );
    let flags = ["--spp", "2", "--res", "40x30", "--seed", "9"];
    ok(&run(&[
        &["render", s(&scene("checkers"))][..],
        &flags,
        &["-o", s(&a)],
    ]
    .concat()));
    ok(&run(
        &[&["render", s(&xml)][..], &flags, &["-o", s(&b)]].concat()
    ));
    assert_eq!(
        beauty(&a).2,
        beauty(&b).2,
        "XML twin renders differently from the JSON scene"
    );
    // `$width` defaults to 320; -D overrides it (no --res here)
    ok(&run(&[
        "render",
        s(&xml),
        "-D",
        "width=24",
        "--spp",
        "1",
        "-o",
        s(&c),
    ]));
    assert_eq!((beauty(&c).0, beauty(&c).1), (24, 240));
    fails_with(
        &run(&["render", s(&xml), "-D", "width", "--spp", "1", "-o", s(&c)]),
        1,
        "KEY=VALUE",
    );
}
