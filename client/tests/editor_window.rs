//! The species editor's real window end to end: `canopy species edit FILE --exit-after SECONDS` in an X window
//! under Xvfb (CI installs `xvfb` and `mesa-vulkan-drivers`), winit + egui-winit + a wgpu surface on whatever
//! Vulkan adapter there is (lavapipe without a GPU). The test checks that it exits 0 by itself having presented
//! frames with the preview settled, and that it left the file alone. No display, no Xvfb or no adapter fails it.

use std::io::Read;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use canopy_test_support::{Reap, start_xvfb};

/// The number just before `key` on the last line that has it (`12 frames, preview settled` → 12).
fn number_before(out: &str, key: &str) -> Option<u64> {
    let line = out.lines().rev().find(|l| l.contains(key))?;
    line[..line.find(key)?].split_whitespace().last()?.parse().ok()
}

#[test]
fn the_editor_window_runs_under_xvfb_and_exits_by_itself_having_drawn_frames() {
    // Displays away from render_walk.rs's (:90..:189), so the two tests can run at once.
    let (display, _xvfb) = start_xvfb(200, "800x600x24");
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("conifer.species");
    let source =
        std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("../worlds/species/conifer.species"))
            .expect("the conifer's source");
    std::fs::write(&file, &source).unwrap();
    let xdg = dir.path().join("xdg");
    std::fs::create_dir(&xdg).unwrap();
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(&xdg, std::fs::Permissions::from_mode(0o700)).unwrap();
    }
    let started = Instant::now();
    let mut child = Reap(
        Command::new(env!("CARGO_BIN_EXE_canopy"))
            .args(["species", "edit"])
            .arg(&file)
            .args(["--width", "640", "--height", "400", "--param", "height=12", "--exit-after", "8"])
            .env("DISPLAY", &display)
            .env("XDG_RUNTIME_DIR", &xdg)
            .env("XDG_STATE_HOME", dir.path().join("state"))
            .env("WGPU_BACKEND", std::env::var("WGPU_BACKEND").unwrap_or_else(|_| "vulkan".into()))
            .env_remove("WAYLAND_DISPLAY")
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("starting canopy species edit"),
    );
    let status = loop {
        if let Some(s) = child.0.try_wait().unwrap() {
            break s;
        }
        assert!(started.elapsed() < Duration::from_secs(300), "canopy species edit did not exit within 5 minutes");
        std::thread::sleep(Duration::from_millis(100));
    };
    let mut out = String::new();
    let mut err = String::new();
    child.0.stdout.take().unwrap().read_to_string(&mut out).unwrap();
    child.0.stderr.take().unwrap().read_to_string(&mut err).unwrap();
    eprintln!("--- canopy species edit stdout\n{out}\n--- stderr\n{err}");
    assert!(status.success(), "canopy species edit failed: {status}");
    assert!(out.contains("adapter: "), "the window's GPU is named");
    let frames = number_before(&out, "frames, preview").expect("a frame count");
    assert!(frames >= 2, "only {frames} frames presented");
    assert!(out.contains("frames, preview settled"), "the preview did not settle in the window");
    assert!(started.elapsed() >= Duration::from_secs(8), "it stayed open for --exit-after");
    assert_eq!(std::fs::read_to_string(&file).unwrap(), source, "the file is left alone");
    // The file parsed, so the editor kept it as its last good version, in the user's state directory only.
    let kept: Vec<_> = std::fs::read_dir(dir.path().join("state/canopy/last-good")).expect("the state dir").collect();
    assert_eq!(kept.len(), 1, "one last good version kept");
}
