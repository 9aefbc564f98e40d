//! The architecture's invariants, phrased as absences (ARCHITECTURE.md), checked on the real
//! crate graph from `cargo metadata`.

use std::collections::{BTreeMap, BTreeSet};
use std::process::Command;

/// Workspace package name → the workspace packages it depends on (normal dependencies only).
fn workspace_graph() -> BTreeMap<String, BTreeSet<String>> {
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let out = Command::new(cargo)
        .args([
            "metadata",
            "--format-version",
            "1",
            "--no-deps",
            "--offline",
        ])
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .expect("cargo metadata runs");
    assert!(
        out.status.success(),
        "cargo metadata failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let meta: serde_json::Value = serde_json::from_slice(&out.stdout).expect("metadata is JSON");
    let packages = meta["packages"].as_array().expect("packages");
    let names: BTreeSet<String> = packages
        .iter()
        .map(|p| p["name"].as_str().unwrap().to_string())
        .collect();
    packages
        .iter()
        .map(|p| {
            let deps = p["dependencies"]
                .as_array()
                .unwrap()
                .iter()
                .filter(|d| d["kind"].is_null()) // normal deps, not dev/build
                .map(|d| d["name"].as_str().unwrap().to_string())
                .filter(|d| names.contains(d))
                .collect();
            (p["name"].as_str().unwrap().to_string(), deps)
        })
        .collect()
}

/// Every workspace package reachable from `root` through normal dependencies.
fn reachable(graph: &BTreeMap<String, BTreeSet<String>>, root: &str) -> BTreeSet<String> {
    let mut seen = BTreeSet::new();
    let mut stack = vec![root.to_string()];
    while let Some(p) = stack.pop() {
        for d in graph.get(&p).into_iter().flatten() {
            if seen.insert(d.clone()) {
                stack.push(d.clone());
            }
        }
    }
    seen
}

#[test]
fn estimators_depends_on_nothing_of_ours() {
    let g = workspace_graph();
    assert_eq!(reachable(&g, "estimators"), BTreeSet::new());
}

#[test]
fn scene_depends_only_on_imageio() {
    let g = workspace_graph();
    let deps = reachable(&g, "scene");
    assert!(
        deps.iter().all(|d| d == "imageio"),
        "scene depends on {deps:?}"
    );
}

#[test]
fn render_never_depends_on_the_farm() {
    let g = workspace_graph();
    let deps = reachable(&g, "render");
    for farm in ["protocol", "coordinator", "worker", "cli"] {
        assert!(!deps.contains(farm), "render depends on {farm}");
    }
}

#[test]
fn coordinator_never_links_the_renderer() {
    let g = workspace_graph();
    assert!(
        g.contains_key("coordinator"),
        "the coordinator crate exists"
    );
    let deps = reachable(&g, "coordinator");
    for forbidden in ["render", "worker", "cli"] {
        assert!(
            !deps.contains(forbidden),
            "coordinator depends on {forbidden}: {deps:?}"
        );
    }
}

#[test]
fn protocol_is_plain_data_without_the_renderer() {
    let g = workspace_graph();
    let deps = reachable(&g, "protocol");
    for forbidden in ["render", "coordinator", "worker", "cli"] {
        assert!(
            !deps.contains(forbidden),
            "protocol depends on {forbidden}: {deps:?}"
        );
    }
}
