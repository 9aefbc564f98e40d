//! Loads a scene file (`.json` or Mitsuba `.xml`) and prints its features, load report, camera
//! and the first vertices of each mesh — for checking conventions against Mitsuba 3.
//!
//! `cargo run -p scene --example scene_info -- path/to/scene.xml [--vertices N]`
fn main() {
    let args: Vec<String> = std::env::args().collect();
    let Some(path) = args.get(1) else {
        eprintln!("usage: scene_info SCENE [--vertices N]");
        std::process::exit(2);
    };
    let n: usize = args
        .iter()
        .position(|a| a == "--vertices")
        .and_then(|i| args.get(i + 1)?.parse().ok())
        .unwrap_or(0);
    let start = std::time::Instant::now();
    let result = scene::load_file(std::path::Path::new(path));
    let elapsed = start.elapsed();
    let loaded = match result {
        Ok(l) => l,
        Err(e) => {
            eprintln!("error: {e}");
            std::process::exit(1);
        }
    };
    println!("load_time_ms: {:.2}", elapsed.as_secs_f64() * 1e3);
    let s = &loaded.scene;
    println!(
        "features: {}",
        serde_json::to_string(&scene::Features::of(s)).unwrap_or_default()
    );
    println!(
        "report: {}",
        serde_json::to_string(&loaded.report).unwrap_or_default()
    );
    println!("fov_x_deg: {}", s.camera.fov_x_deg);
    let m = s.camera.to_world;
    for r in 0..4 {
        println!("camera.to_world row {r}: {:?}", m.row(r).to_array());
    }
    for (i, mesh) in s.meshes.iter().enumerate() {
        let area: f32 = mesh
            .indices
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|k| mesh.positions[k as usize]);
                0.5 * (b - a).cross(c - a).length()
            })
            .sum();
        println!("mesh {i}: area {area}");
        println!(
            "mesh {i}: {} triangles, {} vertices, emitter {:?}",
            mesh.indices.len(),
            mesh.positions.len(),
            mesh.emitter
        );
        for v in 0..n.min(mesh.positions.len()) {
            let nrm = mesh.normals.as_ref().map(|ns| ns[v].to_array());
            let uv = mesh.uvs.as_ref().map(|u| u[v].to_array());
            println!(
                "  v{v}: p {:?} n {:?} uv {:?}",
                mesh.positions[v].to_array(),
                nrm,
                uv
            );
        }
    }
}
