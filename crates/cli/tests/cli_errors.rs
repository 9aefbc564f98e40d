//! Bad input never panics: one `error:` line on stderr and a non-zero exit status
//! (1 = the command failed, 2 = bad command line).

mod common;

use common::*;

#[test]
fn missing_scene_file() {
    let dir = scratch("err_missing");
    let o = run(&[
        "render",
        s(&dir.join("nope.json")),
        "-o",
        s(&dir.join("x.exr")),
    ]);
    fails_with(&o, 1, "nope.json");
    assert!(!dir.join("x.exr").exists());
}

#[test]
fn malformed_scene_json() {
    let dir = scratch("err_malformed");
    let bad = dir.join("bad.json");
    std::fs::write(&bad, "{ \"camera\": { \"fov\": 40 }, \"film\": ").unwrap();
    fails_with(
        &run(&["render", s(&bad), "-o", s(&dir.join("x.exr"))]),
        1,
        "bad.json",
    );
    // valid JSON, invalid scene: unknown field / wrong type
    std::fs::write(&bad, r#"{ "camera": { "fov": 40 }, "film": { "width": 8, "height": 8 }, "shapes": [], "bogus": 1 }"#)
        .unwrap();
    fails_with(
        &run(&["render", s(&bad), "-o", s(&dir.join("x.exr"))]),
        1,
        "bad.json",
    );
    // not JSON at all, and an empty file
    std::fs::write(&bad, [0xffu8, 0x00, 0x12]).unwrap();
    fails_with(
        &run(&["render", s(&bad), "-o", s(&dir.join("x.exr"))]),
        1,
        "bad.json",
    );
    std::fs::write(&bad, "").unwrap();
    fails_with(
        &run(&["render", s(&bad), "-o", s(&dir.join("x.exr"))]),
        1,
        "bad.json",
    );
}

#[test]
fn bad_resolution() {
    let dir = scratch("err_res");
    let sc = scene("cornell-box");
    for res in ["0x10", "abc", "10", "10x", "-5x5", "99999999x2"] {
        let o = run(&["render", s(&sc), "--res", res, "-o", s(&dir.join("x.exr"))]);
        fails_with(&o, 2, "--res");
    }
}

#[test]
fn bad_numbers_and_unknown_estimator() {
    let dir = scratch("err_flags");
    let sc = scene("cornell-box");
    let out = dir.join("x.exr");
    fails_with(
        &run(&["render", s(&sc), "--estimator", "magic", "-o", s(&out)]),
        2,
        "magic",
    );
    fails_with(
        &run(&["render", s(&sc), "--spp", "0", "-o", s(&out)]),
        2,
        "--spp",
    );
    fails_with(
        &run(&["render", s(&sc), "--spp", "many", "-o", s(&out)]),
        2,
        "--spp",
    );
    fails_with(
        &run(&["render", s(&sc), "--tile-size", "0", "-o", s(&out)]),
        2,
        "--tile-size",
    );
    fails_with(&run(&["render", s(&sc)]), 2, "--output");
    fails_with(&run(&["frobnicate"]), 2, "frobnicate");
    // out-of-range depth is caught by the renderer's settings validation
    fails_with(
        &run(&[
            "render",
            s(&sc),
            "--max-depth",
            "-3",
            "--res",
            "4x4",
            "-o",
            s(&out),
        ]),
        1,
        "max_depth",
    );
    // bad value from the environment is reported like a bad flag
    let o = cvfarm()
        .args(["render", s(&sc), "-o", s(&out)])
        .env("CVFARM_SPP", "lots")
        .output()
        .unwrap();
    fails_with(&o, 2, "--spp");
}

#[test]
fn unwritable_output() {
    let dir = scratch("err_output");
    // the output's parent is a regular file, so the directory cannot be created
    let blocker = dir.join("file");
    std::fs::write(&blocker, "x").unwrap();
    let o = run(&[
        "render",
        s(&scene("cornell-box")),
        "--res",
        "4x4",
        "--spp",
        "1",
        "-o",
        s(&blocker.join("x.exr")),
    ]);
    fails_with(&o, 1, "file");
}

#[test]
fn compare_missing_corrupt_and_different_sizes() {
    let dir = scratch("err_compare");
    let sc = scene("cornell-box");
    let (a, b) = (dir.join("a.exr"), dir.join("b.exr"));
    ok(&run(&[
        "render",
        s(&sc),
        "--res",
        "8x8",
        "--spp",
        "1",
        "-o",
        s(&a),
    ]));
    ok(&run(&[
        "render",
        s(&sc),
        "--res",
        "8x4",
        "--spp",
        "1",
        "-o",
        s(&b),
    ]));
    fails_with(&run(&["compare", s(&a), s(&b)]), 1, "different sizes");
    fails_with(
        &run(&["compare", s(&a), s(&dir.join("missing.exr"))]),
        1,
        "missing.exr",
    );
    let junk = dir.join("junk.exr");
    std::fs::write(&junk, b"this is not an EXR file").unwrap();
    fails_with(&run(&["compare", s(&junk), s(&a)]), 1, "junk.exr");
    // a truncated EXR
    let bytes = std::fs::read(&a).unwrap();
    let cut = dir.join("cut.exr");
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
    fails_with(&run(&["compare", s(&cut), s(&a)]), 1, "cut.exr");
    fails_with(
        &run(&["compare", s(&a), s(&a), "--layer", "nope"]),
        1,
        "nope",
    );
    fails_with(
        &run(&["compare", s(&a), s(&a), "--max-rel-mse", "-1"]),
        1,
        "max-rel-mse",
    );
}
