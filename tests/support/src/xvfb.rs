//! Xvfb for the windowed tests (`canopy walk`, the species editor): a virtual X display started on a free
//! display number, and child processes ended when dropped. CI installs `xvfb`, `xauth` and `mesa-vulkan-drivers`.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// Ends a child process when dropped (the test's own children only).
pub struct Reap(pub Child);

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
    panic!("Xvfb not found: install it (`apt-get install -y xvfb xauth`) to run the windowed tests");
}

/// Start Xvfb with a `screen` (`WxHxD`) on a free display among `first..first + 50` (offset by the process id, so
/// test binaries running at once pick different ones); returns the display name and the process.
pub fn start_xvfb(first: u32, screen: &str) -> (String, Reap) {
    let xvfb = find_xvfb();
    for n in (first..first + 50).map(|k| k + (std::process::id() % 50)) {
        let socket = PathBuf::from(format!("/tmp/.X11-unix/X{n}"));
        let lock = PathBuf::from(format!("/tmp/.X{n}-lock"));
        if socket.exists() || lock.exists() {
            continue;
        }
        let child = Command::new(&xvfb)
            .args([format!(":{n}").as_str(), "-screen", "0", screen, "-nolisten", "tcp"])
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
    panic!("could not start Xvfb on any display :{first}..:{}", first + 99);
}
