//! Writing files without losing them: Save and Export .glb write into a temporary file in the target's directory
//! (the `tempfile` crate), flush it to disk and rename it over the target, so a failure half-way (a full disk, a
//! crash) leaves the old file whole. The target stays a regular file: one that exists must be one (a directory, a
//! symbolic link, a device or a pipe is refused with [`EditorError::NotAFile`]); its permissions are kept.

use std::fs::{File, Permissions};
use std::io::Write;
use std::path::Path;

use crate::EditorError;

/// What kind of thing a path is, for [`EditorError::NotAFile`].
fn kind(t: std::fs::FileType) -> &'static str {
    if t.is_dir() {
        "a directory"
    } else if t.is_symlink() {
        "a symbolic link"
    } else {
        "not a regular file"
    }
}

/// Write `bytes` to `path` through a temporary file renamed over it (see the module docs).
pub fn write_file(path: &Path, bytes: &[u8]) -> Result<(), EditorError> {
    replace_with(path, |f| f.write_all(bytes))
}

/// Replace `path` with what `write` puts into a temporary file beside it; when `write` (or anything after it)
/// fails, the temporary file is removed and `path` is untouched.
pub fn replace_with(path: &Path, write: impl FnOnce(&mut File) -> std::io::Result<()>) -> Result<(), EditorError> {
    let err = |reason: String| EditorError::Write { path: path.display().to_string(), reason };
    let keep = check_target(path)?;
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    let name = path.file_name().map_or_else(|| "file".into(), |n| n.to_string_lossy().into_owned());
    let mut tmp = tempfile::Builder::new()
        .prefix(&format!(".{name}."))
        .suffix(".tmp")
        .tempfile_in(dir)
        .map_err(|e| err(format!("creating a temporary file in {}: {e}", dir.display())))?;
    write(tmp.as_file_mut()).map_err(|e| err(e.to_string()))?;
    tmp.as_file().sync_all().map_err(|e| err(e.to_string()))?;
    if let Some(perms) = keep.or_else(new_file_permissions) {
        tmp.as_file().set_permissions(perms).map_err(|e| err(e.to_string()))?;
    }
    tmp.persist(path).map_err(|e| err(e.error.to_string()))?;
    // The rename is durable once the directory is on disk too (best effort: not every platform opens directories).
    if let Ok(d) = File::open(dir) {
        let _ = d.sync_all();
    }
    Ok(())
}

/// Whether [`replace_with`] may replace `path`: it does not exist yet (`None`), or it is a regular file (its
/// permissions, which the new file keeps); anything else is refused. A writer that works long before it writes
/// (an export) asks first, so it refuses before the work.
pub fn check_target(path: &Path) -> Result<Option<Permissions>, EditorError> {
    match std::fs::symlink_metadata(path) {
        Ok(m) if m.file_type().is_file() => Ok(Some(m.permissions())),
        Ok(m) => Err(EditorError::NotAFile { path: path.display().to_string(), kind: kind(m.file_type()) }),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        Err(e) => Err(EditorError::Write { path: path.display().to_string(), reason: e.to_string() }),
    }
}

/// A new file's permissions: readable by everyone, writable by its owner (a temporary file starts private); `None`
/// keeps the temporary file's where there are no Unix modes.
fn new_file_permissions() -> Option<Permissions> {
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        Some(Permissions::from_mode(0o644))
    }
    #[cfg(not(unix))]
    {
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::Editor;

    fn entries(dir: &Path) -> Vec<String> {
        let mut v: Vec<String> = std::fs::read_dir(dir)
            .expect("lists")
            .map(|e| e.expect("entry").file_name().to_string_lossy().into())
            .collect();
        v.sort();
        v
    }

    #[test]
    fn save_replaces_the_file_keeps_its_permissions_and_leaves_nothing_behind() {
        let dir = tempfile::tempdir().expect("temp dir");
        let path = dir.path().join("w.species");
        let worm = canopy_worlds::library::find("worm").expect("worm");
        std::fs::write(&path, worm.text).expect("write");
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            std::fs::set_permissions(&path, Permissions::from_mode(0o640)).expect("chmod");
        }
        let mut ed = Editor::open(&path).expect("opens");
        let text = ed.text().replace("param c = 4", "param c = 5");
        ed.set_text(&text);
        assert!(ed.modified());
        assert_eq!(ed.save().expect("saves"), path);
        assert!(!ed.modified());
        assert_eq!(std::fs::read_to_string(&path).expect("reads"), text);
        let m = std::fs::symlink_metadata(&path).expect("exists");
        assert!(m.file_type().is_file());
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            assert_eq!(m.permissions().mode() & 0o777, 0o640, "permissions kept");
        }
        assert_eq!(entries(dir.path()), ["w.species"], "no temporary file left");
    }

    #[test]
    fn a_failed_write_leaves_the_old_file_whole() {
        let dir = tempfile::tempdir().expect("temp dir");
        let path = dir.path().join("keep.species");
        std::fs::write(&path, "species Keep\n").expect("write");
        let r = replace_with(&path, |f| {
            f.write_all(b"species Ha")?;
            Err(std::io::Error::other("the disk is full"))
        });
        match r {
            Err(EditorError::Write { reason, .. }) => assert!(reason.contains("the disk is full"), "{reason}"),
            other => panic!("expected a write error, got {other:?}"),
        }
        assert_eq!(std::fs::read_to_string(&path).expect("reads"), "species Keep\n");
        assert_eq!(entries(dir.path()), ["keep.species"], "the temporary file is removed");
    }

    #[test]
    fn saving_or_exporting_over_a_directory_or_a_link_is_refused() {
        let dir = tempfile::tempdir().expect("temp dir");
        // A buffer whose file appears as a directory before it is saved.
        let path = dir.path().join("new.species");
        let mut ed = Editor::open(&path).expect("opens a template");
        std::fs::create_dir(&path).expect("mkdir");
        let e = ed.save().expect_err("refused");
        assert!(matches!(e, EditorError::NotAFile { kind: "a directory", .. }), "{e}");
        assert!(e.to_string().contains("new.species"), "{e}");
        assert!(path.is_dir(), "the directory is untouched");
        assert!(ed.modified(), "not saved");
        assert!(matches!(ed.export_glb(&path), Err(EditorError::NotAFile { kind: "a directory", .. })));
        #[cfg(unix)]
        {
            let target = dir.path().join("real.species");
            std::fs::write(&target, "species Real\n").expect("write");
            let link = dir.path().join("link.species");
            std::os::unix::fs::symlink(&target, &link).expect("symlink");
            let e = write_file(&link, b"species Other\n").expect_err("refused");
            assert!(matches!(e, EditorError::NotAFile { kind: "a symbolic link", .. }), "{e}");
            assert_eq!(std::fs::read_to_string(&target).expect("reads"), "species Real\n");
            assert!(std::fs::symlink_metadata(&link).expect("exists").file_type().is_symlink());
        }
        // A new export is a regular, readable file, and nothing temporary is left.
        let glb = dir.path().join("tree.glb");
        ed.export_glb(&glb).expect("exports");
        assert_eq!(&std::fs::read(&glb).expect("reads")[..4], b"glTF");
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            assert_eq!(std::fs::metadata(&glb).expect("exists").permissions().mode() & 0o777, 0o644);
        }
        assert!(entries(dir.path()).iter().all(|n| !n.ends_with(".tmp")), "{:?}", entries(dir.path()));
    }
}
