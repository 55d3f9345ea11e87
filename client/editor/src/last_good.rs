//! The last good version of each file the editor opened or saved: a copy of the text the last time it parsed, kept in
//! the user's state directory (`$XDG_STATE_HOME/canopy/last-good`, else `~/.local/state/canopy/last-good`), so a
//! file that is broken when it is opened (edited elsewhere, a merge gone wrong) still shows the tree it last was,
//! beside its diagnostics. Never next to the user's files; one small file a source, named by a hash of its
//! absolute path and carrying its extension (the format).

use std::path::{Path, PathBuf};

use canopy_worlds::load::read_source;

/// Where last good versions are kept (see the module docs).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct LastGood {
    dir: PathBuf,
}

impl LastGood {
    /// Last good versions kept in `dir` (created on the first write).
    pub fn in_dir(dir: impl Into<PathBuf>) -> LastGood {
        LastGood { dir: dir.into() }
    }

    /// The user's state directory for them, if the environment names one.
    pub fn from_env() -> Option<LastGood> {
        let state = std::env::var_os("XDG_STATE_HOME").filter(|s| !s.is_empty()).map(PathBuf::from).or_else(|| {
            std::env::var_os("HOME").filter(|h| !h.is_empty()).map(|h| Path::new(&h).join(".local/state"))
        })?;
        Some(LastGood::in_dir(state.join("canopy").join("last-good")))
    }

    /// The copy's path for the source at `path`.
    fn slot(&self, path: &Path) -> PathBuf {
        let abs = std::path::absolute(path).unwrap_or_else(|_| path.to_path_buf());
        // FNV-1a over the path's bytes: stable across runs and machines, no order of any map involved.
        let mut h: u64 = 0xcbf2_9ce4_8422_2325;
        for b in abs.as_os_str().as_encoded_bytes() {
            h = (h ^ u64::from(*b)).wrapping_mul(0x0100_0000_01b3);
        }
        let ext = path.extension().and_then(|e| e.to_str()).unwrap_or("txt");
        self.dir.join(format!("{h:016x}.{ext}"))
    }

    /// Keep `text` as the last good version of `path` (written whole or not at all).
    pub fn remember(&self, path: &Path, text: &str) -> Result<(), crate::EditorError> {
        std::fs::create_dir_all(&self.dir)
            .map_err(|e| crate::EditorError::Write { path: self.dir.display().to_string(), reason: e.to_string() })?;
        crate::save::write_file(&self.slot(path), text.as_bytes())
    }

    /// The last good version of `path`, if one was kept (and can be read: a regular file, bounded like any
    /// source).
    pub fn recall(&self, path: &Path) -> Option<String> {
        read_source(&self.slot(path)).ok().map(|s| s.text)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_copy_a_path_in_the_state_directory() {
        let dir = tempfile::tempdir().unwrap();
        let lg = LastGood::in_dir(dir.path().join("lg"));
        assert_eq!(lg.recall(Path::new("/a/tree.species")), None);
        lg.remember(Path::new("/a/tree.species"), "one").unwrap();
        lg.remember(Path::new("/b/tree.species"), "two").unwrap();
        assert_eq!(lg.recall(Path::new("/a/tree.species")).as_deref(), Some("one"));
        assert_eq!(lg.recall(Path::new("/b/tree.species")).as_deref(), Some("two"));
        lg.remember(Path::new("/a/tree.species"), "three").unwrap();
        assert_eq!(lg.recall(Path::new("/a/tree.species")).as_deref(), Some("three"));
        let names: Vec<String> = std::fs::read_dir(dir.path().join("lg"))
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        assert_eq!(names.len(), 2);
        assert!(names.iter().all(|n| n.ends_with(".species")), "{names:?}");
    }
}
