//! Helpers shared by the `cli_*` integration tests: run the real `cvfarm` binary with a clean
//! environment, in a per-test scratch directory.

#![allow(dead_code)] // each test file uses a different subset

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// The `cvfarm` binary built for this test run.
pub const BIN: &str = env!("CARGO_BIN_EXE_cvfarm");

/// The repository's `scenes/` directory.
pub fn scenes_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../scenes")
}

/// `scenes/<name>/scene.json`.
pub fn scene(name: &str) -> PathBuf {
    scenes_dir().join(name).join("scene.json")
}

/// The names of all shipped scenes (directories of `scenes/` holding a `scene.json`).
pub fn shipped_scenes() -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(scenes_dir())
        .expect("scenes/ exists")
        .filter_map(|e| e.ok())
        .filter(|e| e.path().join("scene.json").is_file())
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    names
}

/// A fresh, empty scratch directory for one test.
pub fn scratch(test: &str) -> PathBuf {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR"))
        .join("cli-tests")
        .join(test);
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("create scratch dir");
    dir
}

/// A `cvfarm` command with every `CVFARM_*` variable of the test environment removed, so
/// that an operator's settings cannot change what a test sees.
pub fn cvfarm() -> Command {
    let mut cmd = Command::new(BIN);
    for (k, _) in std::env::vars_os() {
        if k.to_string_lossy().starts_with("CVFARM_") {
            cmd.env_remove(k);
        }
    }
    cmd
}

/// Runs `cvfarm args…` and returns its output.
pub fn run(args: &[&str]) -> Output {
    cvfarm().args(args).output().expect("run cvfarm")
}

/// stdout as text.
pub fn stdout(o: &Output) -> String {
    String::from_utf8_lossy(&o.stdout).into_owned()
}

/// stderr as text.
pub fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// Asserts success and returns stdout.
pub fn ok(o: &Output) -> String {
    assert!(
        o.status.success(),
        "cvfarm failed ({}):\nstdout: {}\nstderr: {}",
        o.status,
        stdout(o),
        stderr(o)
    );
    stdout(o)
}

/// Asserts the failure contract: non-zero exit `code`, exactly one non-empty stderr line
/// starting with `error:` that mentions `needle`, no panic.
pub fn fails_with(o: &Output, code: i32, needle: &str) {
    let err = stderr(o);
    assert_eq!(o.status.code(), Some(code), "exit status; stderr: {err}");
    assert!(!err.contains("panicked"), "panicked: {err}");
    let lines: Vec<&str> = err.lines().filter(|l| !l.trim().is_empty()).collect();
    assert_eq!(lines.len(), 1, "expected one stderr line, got: {err:?}");
    assert!(
        lines[0].starts_with("error: "),
        "no `error:` prefix: {err:?}"
    );
    assert!(
        lines[0].to_lowercase().contains(&needle.to_lowercase()),
        "`{needle}` not in: {err:?}"
    );
}

/// Path as &str (tests use UTF-8 paths).
pub fn s(p: &Path) -> &str {
    p.to_str().expect("utf-8 path")
}
