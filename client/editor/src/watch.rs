//! The file on disk, watched with `notify`: a change by any text editor (written in place or renamed over) reaches
//! the editor, which parses it again, so it works beside whatever editor a person prefers.

use std::path::{Path, PathBuf};
use std::sync::mpsc::{Receiver, channel};

use notify::{EventKind, RecursiveMode, Watcher};

/// Watches one file (through its directory, so a rename over it is seen too).
pub(crate) struct FileWatch {
    _watcher: notify::RecommendedWatcher,
    changes: Receiver<()>,
}

impl std::fmt::Debug for FileWatch {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FileWatch").finish_non_exhaustive()
    }
}

impl FileWatch {
    /// Start watching `file`.
    pub(crate) fn new(file: &Path) -> Result<FileWatch, notify::Error> {
        let file: PathBuf = std::path::absolute(file).unwrap_or_else(|_| file.to_path_buf());
        let dir = file.parent().map_or_else(|| PathBuf::from("."), Path::to_path_buf);
        let name = file.file_name().map(|n| n.to_os_string());
        let (tx, changes) = channel();
        let mut watcher = notify::recommended_watcher(move |e: notify::Result<notify::Event>| {
            let Ok(e) = e else { return };
            let ours = e.paths.iter().any(|p| p.file_name().map(|n| n.to_os_string()) == name);
            if ours && matches!(e.kind, EventKind::Create(_) | EventKind::Modify(_)) {
                let _ = tx.send(());
            }
        })?;
        watcher.watch(&dir, RecursiveMode::NonRecursive)?;
        Ok(FileWatch { _watcher: watcher, changes })
    }

    /// Whether the file changed since the last call (several events count once).
    pub(crate) fn changed(&self) -> bool {
        let mut any = false;
        while self.changes.try_recv().is_ok() {
            any = true;
        }
        any
    }

    /// Wait up to `timeout` for a change (tests).
    #[cfg(test)]
    pub(crate) fn wait(&self, timeout: std::time::Duration) -> bool {
        let got = self.changes.recv_timeout(timeout).is_ok();
        got | self.changed()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::Editor;
    use std::time::Duration;

    #[test]
    fn a_change_on_disk_is_seen_and_parsed() {
        let dir = tempfile::tempdir().expect("temp dir");
        let path = dir.path().join("w.species");
        let worm = canopy_worlds::library::find("worm").expect("worm");
        std::fs::write(&path, worm.text).expect("write");
        let mut ed = Editor::open(&path).expect("opens");
        let w = FileWatch::new(&path).expect("watches");
        let before = ed.amplified().expect("amplified").hash;
        std::fs::write(&path, worm.text.replace("param c = 4", "param c = 6")).expect("write");
        assert!(w.wait(Duration::from_secs(10)), "no change seen");
        assert!(ed.reload().expect("reads"));
        assert_ne!(ed.amplified().expect("amplified").hash, before);
        assert!(!ed.modified());
    }
}
