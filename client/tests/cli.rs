//! The `canopy` command line, run as a user runs it.

use std::path::PathBuf;
use std::process::{Command, Output};

fn canopy(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_canopy")).args(args).output().expect("canopy runs")
}

fn text(o: &Output) -> String {
    format!("{}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr))
}

/// A path in this test process's temporary directory.
fn temp(name: &str) -> PathBuf {
    static DIR: std::sync::OnceLock<tempfile::TempDir> = std::sync::OnceLock::new();
    DIR.get_or_init(|| tempfile::tempdir().expect("temp dir")).path().join(name)
}

#[test]
fn check_reports_every_file_with_positions_and_fails() {
    let bad = temp("bad.species");
    std::fs::write(&bad, "param x = 1\ncone(x, y, 1)\nfoo\n").unwrap();
    let bad_l = temp("bad.lsys");
    std::fs::write(&bad_l, "derive 2\naxiom: A\nA -> F Q\n").unwrap();
    let good = concat!(env!("CARGO_MANIFEST_DIR"), "/../worlds/species/worm.species");
    let o = canopy(&["species", "check", bad.to_str().unwrap(), good, bad_l.to_str().unwrap()]);
    let out = text(&o);
    assert!(!o.status.success());
    assert!(out.contains("bad.species:2:9: error: unknown parameter `y`"), "{out}");
    assert!(out.contains("bad.species:3:1: error: unknown node `foo`"), "{out}");
    assert!(out.contains("bad.lsys:3:8"), "{out}");
    assert!(out.contains("ok      ") && out.contains("species `Worm`"), "{out}");
    assert!(out.contains("3 file(s) checked, 2 failed"), "{out}");
}

#[test]
fn stats_reports_counts_sizes_and_time() {
    let o = canopy(&["species", "stats", "worm", "--param", "c=6", "--repeat", "1"]);
    let out = text(&o);
    assert!(o.status.success(), "{out}");
    assert!(out.contains("primitives  7  (cone 1  cylinder 0  sphere 6  box 0  leaf 0)"), "{out}");
    assert!(out.contains("encoded     165 bytes"), "{out}");
    assert!(out.contains("traversal"), "{out}");
    let o = canopy(&["species", "stats", "worm", "--param", "nope=1"]);
    assert!(!o.status.success());
    assert!(text(&o).contains("has no parameter `nope`"));
}

#[test]
fn amplify_is_deterministic_and_writes_the_stream() {
    let out = temp("stream.txt");
    let a = canopy(&["species", "amplify", "bush", "--seed", "5", "--out", out.to_str().unwrap()]);
    let b = canopy(&["species", "amplify", "bush", "--seed", "5"]);
    assert!(a.status.success() && b.status.success());
    assert_eq!(a.stdout, b.stdout, "same seed, same hashes");
    let stream = std::fs::read_to_string(&out).unwrap();
    assert_eq!(stream.lines().filter(|l| !l.starts_with('#')).count(), 2568, "one line per primitive");
}

#[test]
fn budgets_turn_runaway_work_into_an_error() {
    let o = canopy(&["species", "stats", "conifer", "--max-primitives", "100"]);
    assert!(!o.status.success());
    assert!(text(&o).contains("more than 100 primitives"), "{}", text(&o));
}

#[test]
fn export_writes_a_grove_glb() {
    let out = temp("grove.glb");
    let o = canopy(&["species", "export", "worm", "--grove", "4", "-o", out.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
    let bytes = std::fs::read(&out).unwrap();
    assert_eq!(&bytes[..4], b"glTF");
    let (json, _) = canopy_worlds::gltf::parse_glb_header(&bytes).unwrap();
    assert_eq!(json["nodes"].as_array().unwrap().len(), 4);
}

/// The README's main command, short: the in-process server on the default world, bots walking, the live summary,
/// and every bot checked against the world at the end. With `DISPLAY` pointing at no X server the window fails and
/// the demo goes on headless.
#[test]
fn demo_streams_the_default_world_to_bots_and_checks_them() {
    let o = Command::new(env!("CARGO_BIN_EXE_canopy"))
        .args(["demo", "--bots", "3", "--duration", "3", "--radius", "120"])
        .env("DISPLAY", ":987654")
        .env_remove("WAYLAND_DISPLAY")
        .output()
        .expect("canopy runs");
    let out = text(&o);
    assert!(o.status.success(), "{out}");
    assert!(out.contains("instances: 213042"), "{out}");
    assert!(out.contains("the walkthrough window failed"), "{out}");
    assert!(out.contains("AOI complete 3/3"), "{out}");
    assert!(out.contains("checked against the world: 3 of 3 exact"), "{out}");
    assert!(out.contains("species: ") && out.contains(", 0 received twice"), "{out}");
}
