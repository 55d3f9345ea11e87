//! Hostile files: a device, a FIFO, a socket or a link to one, given as a species, world, hypertree or hyperforest
//! file, is refused at once with `not a regular file` — never read until memory runs out, never waited on.
#![cfg(unix)]

use std::path::{Path, PathBuf};
use std::sync::mpsc;
use std::time::Duration;

use canopy_worlds::hypertree::format::{load_forest, load_hypertree};
use canopy_worlds::load::load_file;
use canopy_worlds::world::World;

/// Run `f` on a thread and give its answer, or fail if it takes more than five seconds (a FIFO that is opened
/// for reading blocks until a writer comes; the guard turns that hang into a failure).
fn within_seconds<T: Send + 'static>(what: &str, f: impl FnOnce() -> T + Send + 'static) -> T {
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        let _ = tx.send(f());
    });
    rx.recv_timeout(Duration::from_secs(5)).unwrap_or_else(|_| panic!("{what}: no answer within 5 s"))
}

/// The hostile paths: `/dev/zero`, a link to `/dev/urandom`, a FIFO and a socket, each with `ext`.
fn hostile(dir: &Path, ext: &str) -> Vec<PathBuf> {
    let link = dir.join(format!("urandom.{ext}"));
    std::os::unix::fs::symlink("/dev/urandom", &link).unwrap();
    let zero = dir.join(format!("zero.{ext}"));
    std::os::unix::fs::symlink("/dev/zero", &zero).unwrap();
    let fifo = dir.join(format!("fifo.{ext}"));
    let made = std::process::Command::new("mkfifo").arg(&fifo).status().expect("mkfifo runs");
    assert!(made.success(), "mkfifo failed");
    let socket = dir.join(format!("socket.{ext}"));
    let listener = std::os::unix::net::UnixListener::bind(&socket).unwrap();
    std::mem::forget(listener);
    vec![zero, link, fifo, socket]
}

#[test]
fn species_files_must_be_regular() {
    let dir = tempfile::tempdir().unwrap();
    for ext in ["species", "lsys"] {
        for path in hostile(dir.path(), ext) {
            let p = path.clone();
            let (graph, diags) = within_seconds(&path.display().to_string(), move || load_file(&p));
            assert!(graph.is_none());
            assert_eq!(diags.len(), 1, "{diags:?}");
            assert_eq!(diags[0].message, "not a regular file", "{}", path.display());
            assert!(diags[0].file.ends_with(&format!(".{ext}")));
        }
    }
}

#[test]
fn world_manifests_and_the_species_they_name_must_be_regular() {
    let dir = tempfile::tempdir().unwrap();
    for path in hostile(dir.path(), "world") {
        let p = path.clone();
        let err = within_seconds(&path.display().to_string(), move || World::load(&p)).expect_err("refused");
        assert!(err.0[0].message.contains("not a regular file"), "{err}");
    }
    // A manifest naming a device as a species file: the manifest's diagnostic says so.
    std::os::unix::fs::symlink("/dev/zero", dir.path().join("tree.species")).unwrap();
    let manifest = dir.path().join("w.world");
    std::fs::write(&manifest, "seed 1\nbounds 0 0 64 64\ncell 64\nspecies tree \"tree.species\"\n").unwrap();
    let err = within_seconds("manifest", move || World::load(&manifest)).expect_err("refused");
    assert!(err.to_string().contains("not a regular file"), "{err}");
}

#[test]
fn hypertree_and_hyperforest_files_must_be_regular() {
    let dir = tempfile::tempdir().unwrap();
    for path in hostile(dir.path(), "hyp") {
        let p = path.clone();
        let (def, diags) = within_seconds(&path.display().to_string(), move || load_hypertree(&p));
        assert!(def.is_none());
        assert_eq!(diags[0].message, "not a regular file");
    }
    for path in hostile(dir.path(), "hyf") {
        let p = path.clone();
        let (forest, diags) = within_seconds(&path.display().to_string(), move || load_forest(&p));
        assert!(forest.is_none());
        assert_eq!(diags[0].message, "not a regular file");
    }
}
