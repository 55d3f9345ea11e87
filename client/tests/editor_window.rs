//! The species editor's real window end to end: `canopy species edit FILE --exit-after SECONDS` in an X window
//! under Xvfb (CI installs `xvfb` and `mesa-vulkan-drivers`), winit + egui-winit + a wgpu surface on whatever
//! Vulkan adapter there is (lavapipe without a GPU). The test checks that it exits 0 by itself having presented
//! frames with the preview settled, and that it left the file alone. No display, no Xvfb or no adapter fails it.

use std::io::Read;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// Ends a child process when dropped (the test's own children only).
struct Reap(Child);

impl Drop for Reap {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn find_xvfb() -> PathBuf {
    for dir in std::env::var("PATH").unwrap_or_default().split(':').chain(["/usr/bin"]) {
        let p = Path::new(dir).join("Xvfb");
        if p.is_file() {
            return p;
        }
    }
    panic!("Xvfb not found: install it (`apt-get install -y xvfb xauth`) to run the editor window's test");
}

/// Start Xvfb on a free display; returns the display name and the process.
fn start_xvfb() -> (String, Reap) {
    let xvfb = find_xvfb();
    // Away from render_walk.rs's displays (:90..:189), so the two tests can run at once.
    for n in (200..250).map(|k| k + (std::process::id() % 50)) {
        let socket = PathBuf::from(format!("/tmp/.X11-unix/X{n}"));
        let lock = PathBuf::from(format!("/tmp/.X{n}-lock"));
        if socket.exists() || lock.exists() {
            continue;
        }
        let child = Command::new(&xvfb)
            .args([format!(":{n}").as_str(), "-screen", "0", "800x600x24", "-nolisten", "tcp"])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("starting Xvfb");
        let mut child = Reap(child);
        let deadline = Instant::now() + Duration::from_secs(20);
        while Instant::now() < deadline {
            if socket.exists() {
                return (format!(":{n}"), child);
            }
            if let Ok(Some(_)) = child.0.try_wait() {
                break;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
    }
    panic!("could not start Xvfb on any display :200..:299");
}

/// The number just before `key` on the last line that has it (`12 frames, preview settled` → 12).
fn number_before(out: &str, key: &str) -> Option<u64> {
    let line = out.lines().rev().find(|l| l.contains(key))?;
    line[..line.find(key)?].split_whitespace().last()?.parse().ok()
}

#[test]
fn the_editor_window_runs_under_xvfb_and_exits_by_itself_having_drawn_frames() {
    let (display, _xvfb) = start_xvfb();
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
}
