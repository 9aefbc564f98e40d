//! The farm as operators run it: real `cvfarm serve`, `cvfarm worker` and `cvfarm submit`
//! processes on loopback. A worker is SIGKILLed mid-job, the other finishes; the downloaded
//! EXR equals `cvfarm render` of the same scene and settings bit for bit; SIGTERM stops the
//! coordinator and the workers cleanly (exit status 0).

use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// The `cvfarm` binary Cargo built for this package's tests (always current).
fn cvfarm() -> PathBuf {
    PathBuf::from(env!("CARGO_BIN_EXE_cvfarm"))
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .expect("bind")
        .local_addr()
        .expect("addr")
        .port()
}

struct Proc(Child);

impl Proc {
    fn signal(&self, sig: &str) {
        let _ = Command::new("kill")
            .args([sig, &self.0.id().to_string()])
            .status();
    }
    fn wait_exit(&mut self, timeout: Duration) -> Option<i32> {
        let start = Instant::now();
        while start.elapsed() < timeout {
            if let Ok(Some(s)) = self.0.try_wait() {
                return s.code();
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        None
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

#[test]
fn serve_worker_submit_processes_with_a_sigkilled_worker_match_cvfarm_render() {
    let bin = cvfarm();
    let dir = std::env::temp_dir().join(format!(
        "cvfarm_proc_{}_{:08x}",
        std::process::id(),
        rand::random::<u32>()
    ));
    std::fs::create_dir_all(&dir).expect("dir");
    let port = free_port();
    let url = format!("http://127.0.0.1:{port}");
    let env = [
        ("CVFARM_CLIENT_TOKEN", "pc"),
        ("CVFARM_WORKER_TOKEN", "pw"),
        ("RUST_LOG", "warn"),
    ];
    let spawn = |args: &[&str]| {
        let mut c = Command::new(&bin);
        c.args(args)
            .envs(env)
            .stdout(Stdio::null())
            .stderr(Stdio::null());
        Proc(c.spawn().expect("spawn cvfarm"))
    };
    let mut serve = spawn(&[
        "serve",
        "--listen",
        &format!("127.0.0.1:{port}"),
        "--data-dir",
        dir.join("data").to_str().expect("utf8"),
        "--lease-ms",
        "1500",
        "--heartbeat-ms",
        "300",
    ]);
    let t0 = Instant::now();
    while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
        assert!(
            t0.elapsed() < Duration::from_secs(60),
            "cvfarm serve never listened"
        );
        assert!(
            serve.0.try_wait().expect("serve status").is_none(),
            "cvfarm serve exited"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    let victim = spawn(&[
        "worker",
        "--coordinator",
        &url,
        "--slots",
        "1",
        "--name",
        "victim",
    ]);
    let scene = e2e::scene_path("cornell-box/scene.json");
    let scene = scene.to_str().expect("utf8");
    let out = dir.join("farm.exr");
    let submit = Command::new(&bin)
        .args([
            "submit",
            scene,
            "--coordinator",
            &url,
            "--res",
            "48x48",
            "--spp",
            "256",
            "--tile-size",
            "8",
        ])
        .args(["--seed", "9", "--wait", "-o", out.to_str().expect("utf8")])
        .envs(env)
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("submit");
    // Kill the first worker abruptly once the job is under way; a second one finishes it.
    let client = e2e::Client::with_token(&url, Some("pc"));
    let start = Instant::now();
    loop {
        assert!(
            start.elapsed() < Duration::from_secs(60),
            "the job never started"
        );
        let r = client.request("GET", "/v1/jobs/1", None);
        if r.status == 200 && r.json()["tasks_done"].as_u64().unwrap_or(0) >= 1 {
            assert_eq!(
                r.json()["state"],
                "running",
                "job finished before the kill; make it heavier"
            );
            break;
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    victim.signal("-KILL");
    let mut rescuer = spawn(&[
        "worker",
        "--coordinator",
        &url,
        "--slots",
        "1",
        "--name",
        "rescuer",
    ]);
    let submitted = submit.wait_with_output().expect("submit runs");
    assert!(
        submitted.status.success(),
        "submit failed: {}",
        String::from_utf8_lossy(&submitted.stderr)
    );

    let local = dir.join("local.exr");
    let st = Command::new(&bin)
        .args([
            "render",
            scene,
            "--res",
            "48x48",
            "--spp",
            "256",
            "--seed",
            "9",
            "-o",
            local.to_str().expect("utf8"),
        ])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .expect("render runs");
    assert!(st.success());
    let (a, b) = (
        std::fs::read(&out).expect("farm exr"),
        std::fs::read(&local).expect("local exr"),
    );
    assert!(a == b, "farm EXR differs from cvfarm render");

    // A CV job through the CLI: same estimator flags as `cvfarm render`, same image layers
    // bit for bit (the local EXR has the estimator's extra layers besides).
    let cms_args = [
        "--estimator",
        "cms",
        "--opt",
        "training_spp=8",
        "--res",
        "32x32",
        "--spp",
        "16",
        "--seed",
        "4",
    ];
    let (farm_cms, local_cms) = (dir.join("farm_cms.exr"), dir.join("local_cms.exr"));
    let st = Command::new(&bin)
        .args(["submit", scene, "--coordinator", &url, "--tile-size", "16"])
        .args(cms_args)
        .args(["--wait", "-o", farm_cms.to_str().expect("utf8")])
        .envs(env)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .expect("submit runs");
    assert!(st.success());
    let st = Command::new(&bin)
        .args(["render", scene])
        .args(cms_args)
        .args(["-o", local_cms.to_str().expect("utf8")])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .expect("render runs");
    assert!(st.success());
    let read = |p: &std::path::Path| {
        imageio::read_exr_bytes(&std::fs::read(p).expect("exr")).expect("exr decodes")
    };
    let (f, l) = (read(&farm_cms), read(&local_cms));
    for name in ["beauty", "variance", "albedo", "normal"] {
        let bits = |img: &imageio::ExrImage| -> Vec<u32> {
            img.layer(name)
                .unwrap_or_else(|| panic!("layer {name}"))
                .data
                .iter()
                .flatten()
                .map(|v| v.to_bits())
                .collect()
        };
        assert!(
            bits(&f) == bits(&l),
            "cms layer {name}: farm differs from cvfarm render"
        );
    }

    // Bad input from the CLI: one error line naming the problem, non-zero exit.
    // A bad option value is the coordinator's 422 (exit 1); an unknown option or estimator is
    // a usage error found before anything is sent (exit 2), as for `cvfarm render`.
    for (args, needle, code) in [
        (
            vec!["--estimator", "cms", "--opt", "grid_resolution=[0,1,1]"],
            "grid_resolution",
            1,
        ),
        (vec!["--opt", "bogus=1"], "bogus", 2),
        (
            vec!["--estimator", "cms", "--opt", "trainig_spp=3"],
            "trainig_spp",
            2,
        ),
        (vec!["--res", "999999x2"], "resolution", 1),
    ] {
        let r = Command::new(&bin)
            .args(["submit", scene, "--coordinator", &url])
            .args(&args)
            .envs(env)
            .output()
            .expect("submit runs");
        let err = String::from_utf8_lossy(&r.stderr);
        assert_eq!(r.status.code(), Some(code), "{args:?}: {err}");
        assert!(
            err.contains(needle) && err.lines().count() == 1,
            "{args:?}: {err}"
        );
    }
    let r = Command::new(&bin)
        .args(["submit", scene, "--coordinator", &url])
        .env("CVFARM_CLIENT_TOKEN", "wrong")
        .output()
        .expect("submit runs");
    assert!(String::from_utf8_lossy(&r.stderr).contains("401"), "{r:?}");

    // SIGTERM: clean exits.
    rescuer.signal("-TERM");
    assert_eq!(
        rescuer.wait_exit(Duration::from_secs(30)),
        Some(0),
        "worker did not stop cleanly"
    );
    serve.signal("-TERM");
    assert_eq!(
        serve.wait_exit(Duration::from_secs(30)),
        Some(0),
        "coordinator did not stop cleanly"
    );
    let _ = std::fs::remove_dir_all(&dir);
}
