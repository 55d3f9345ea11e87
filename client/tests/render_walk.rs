//! The walkthrough window end to end: a `canopy-server` in this process on a small world over loopback QUIC, and
//! `canopy walk` in a real X window under Xvfb (CI installs `xvfb` and `mesa-vulkan-drivers`), flying on autopilot
//! for a few seconds. The test checks that frames were presented and that instances and species arrived; the
//! renderer runs on whatever Vulkan adapter there is (lavapipe without a GPU).

use std::io::Read;
use std::net::SocketAddr;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use canopy_server::{Cells, ServeOptions, Served, ServerConfig, serve};
use canopy_worlds::diag::SourceFile;
use canopy_worlds::world::World;

use canopy_test_support::{Reap, start_xvfb};

fn world() -> World {
    let text = r#"
world walkgrove
seed 5
bounds -256 -256 256 256
cell 32
terrain terrain {
  tile 256
  depth 4
  param relief = 4
}
species conifer conifer
species broadleaf monopodial
scatter conifer {
  spacing 10
  region -256 0 256 256
  param height = 10 .. 18 step 0.5
}
scatter broadleaf {
  spacing 14
  region -256 -256 256 0
}
"#;
    World::parse(&SourceFile::new("walkgrove.world", text), None).unwrap_or_else(|d| panic!("{d}"))
}

fn number_after(out: &str, key: &str) -> Option<u64> {
    let at = out.rfind(key)? + key.len();
    out[at..].trim_start().split(|c: char| !c.is_ascii_digit()).next()?.parse().ok()
}

#[test]
fn walk_window_presents_frames_of_a_streamed_world_under_xvfb() {
    let (display, _xvfb) = start_xvfb(90, "640x480x24");
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build().unwrap();
    let w = world();
    let expected = w.instances.len();
    let server = ServerConfig { listen: SocketAddr::from(([127, 0, 0, 1], 0)), ..ServerConfig::default() };
    let opts = ServeOptions { server, cells: Cells::Materialised, ..ServeOptions::default() };
    let server: Served = rt.block_on(serve(w, opts)).expect("server starts");
    let xdg_dir = tempfile::tempdir().unwrap();
    let xdg = xdg_dir.path();
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(xdg, std::fs::Permissions::from_mode(0o700)).unwrap();
    }
    let started = Instant::now();
    let mut child = Reap(
        Command::new(env!("CARGO_BIN_EXE_canopy"))
            .args([
                "walk",
                "--server",
                &server.local_addr().to_string(),
                "--cert-fingerprint",
                server.fingerprint(),
                "--camera",
                "position 0 ~25 -120; look-at 0 ~8 0",
                "--width",
                "320",
                "--height",
                "200",
                "--radius",
                "300",
                // The radius fitted to a link while the autopilot moves (fast enough that it stays 300 m).
                "--link",
                "100M",
                "--autopilot",
                "--exit-after",
                "8",
                "--workers",
                "1",
                "--geometry-mib",
                "32",
            ])
            .env("DISPLAY", &display)
            .env("XDG_RUNTIME_DIR", xdg)
            .env("WGPU_BACKEND", std::env::var("WGPU_BACKEND").unwrap_or_else(|_| "vulkan".into()))
            .env_remove("WAYLAND_DISPLAY")
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("starting canopy walk"),
    );
    let status = loop {
        if let Some(s) = child.0.try_wait().unwrap() {
            break s;
        }
        assert!(started.elapsed() < Duration::from_secs(300), "canopy walk did not exit within 5 minutes");
        std::thread::sleep(Duration::from_millis(100));
    };
    let mut out = String::new();
    let mut err = String::new();
    child.0.stdout.take().unwrap().read_to_string(&mut out).unwrap();
    child.0.stderr.take().unwrap().read_to_string(&mut err).unwrap();
    eprintln!("--- canopy walk stdout\n{out}\n--- stderr\n{err}");
    assert!(status.success(), "canopy walk failed: {status}");
    let frames = number_after(&out, "frames presented:").expect("a frame count");
    assert!(frames >= 3, "only {frames} frames presented");
    let held = number_after(&out, "instances held").expect("an instance count");
    assert!(held > 0 && held as usize <= expected, "{held} instances held of {expected}");
    assert!(out.contains("species 2/2"), "both species arrived");
    rt.block_on(server.shutdown(Duration::from_secs(1)));
}
