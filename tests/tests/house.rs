//! House rules, checked over the whole tree (rust-analyzer's tidy test in spirit): the crate dependency rules that
//! ARCHITECTURE.md states, read from `cargo metadata`; every Rust file opens with a `//!` line; every file in a
//! `tests/` directory is compiled; the sans-IO cores read no clock and use no tokio or quinn; no `#[ignore]` without
//! a reason; no file over 1,000 lines unless it is listed below with its reason.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::process::Command;

/// The workspace root.
fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).parent().expect("tests/ has a parent").to_path_buf()
}

/// What each crate may not depend on, directly or through any normal (non-dev, non-build) dependency.
const FORBIDDEN: &[(&str, &[&str])] = &[
    ("canopy-protocol", &["tokio", "quinn", "wgpu", "winit", "clap", "anyhow", "canopy-worlds", "canopy-server"]),
    ("canopy-worlds", &["tokio", "quinn", "wgpu", "winit", "clap", "anyhow", "indicatif", "canopy-server"]),
    (
        "canopy-edits",
        &["tokio", "quinn", "wgpu", "winit", "clap", "anyhow", "canopy-worlds", "canopy-server", "canopy-client"],
    ),
    // The sans-IO core: no runtime, no transport, no engine, no database (quinn-proto's rule).
    (
        "canopy-session",
        &[
            "tokio",
            "quinn",
            "async-nats",
            "rusqlite",
            "wgpu",
            "winit",
            "clap",
            "anyhow",
            "canopy-edits",
            "canopy-server",
            "canopy-client",
        ],
    ),
    // The server library: its binary's options, logging set-up and allocator live in canopy-server-app.
    (
        "canopy-server",
        &[
            "wgpu",
            "winit",
            "indicatif",
            "clap",
            "anyhow",
            "tracing-subscriber",
            "tikv-jemallocator",
            "canopy-client",
            "canopy-render",
            "canopy-harness",
        ],
    ),
    (
        "canopy-client",
        &["wgpu", "winit", "clap", "indicatif", "anyhow", "canopy-server", "canopy-render", "canopy-harness"],
    ),
    (
        "canopy-render",
        &["quinn", "tokio", "winit", "clap", "indicatif", "anyhow", "canopy-server", "canopy-client", "canopy-harness"],
    ),
    (
        "canopy-editor",
        &["quinn", "tokio", "clap", "indicatif", "anyhow", "canopy-server", "canopy-client", "canopy-harness"],
    ),
    // The harness runs a canopy-server in process (through canopy_server::serve).
    ("canopy-harness", &["wgpu", "winit", "canopy-render", "canopy-server-app"]),
];

/// `cargo metadata` of the workspace, resolved for the host only: other platforms' dependencies (Android, Windows)
/// need not be downloaded.
fn metadata() -> serde_json::Value {
    let rustc = std::env::var("RUSTC").unwrap_or_else(|_| "rustc".into());
    let version = Command::new(rustc).arg("-vV").output().expect("rustc -vV runs");
    let version = String::from_utf8(version.stdout).expect("UTF-8");
    let host = version.lines().find_map(|l| l.strip_prefix("host: ")).expect("rustc names its host").to_owned();
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let out = Command::new(cargo)
        .args(["metadata", "--format-version", "1", "--offline", "--filter-platform", &host])
        .current_dir(root())
        .output()
        .expect("cargo metadata runs");
    assert!(out.status.success(), "cargo metadata failed: {}", String::from_utf8_lossy(&out.stderr));
    serde_json::from_slice(&out.stdout).expect("cargo metadata prints JSON")
}

/// Each workspace package's name and its normal dependencies' closure, from `cargo metadata`.
fn dependency_closures() -> BTreeMap<String, BTreeSet<String>> {
    let meta = metadata();
    let names: BTreeMap<String, String> = meta["packages"]
        .as_array()
        .expect("packages")
        .iter()
        .map(|p| (p["id"].as_str().expect("id").to_owned(), p["name"].as_str().expect("name").to_owned()))
        .collect();
    // Normal dependency edges by package id (a dependency used only in tests or build scripts is not an edge).
    let mut edges: BTreeMap<String, Vec<String>> = BTreeMap::new();
    for node in meta["resolve"]["nodes"].as_array().expect("resolve.nodes") {
        let id = node["id"].as_str().expect("node id").to_owned();
        let deps = node["deps"]
            .as_array()
            .expect("deps")
            .iter()
            .filter(|d| d["dep_kinds"].as_array().expect("dep_kinds").iter().any(|k| k["kind"].is_null()));
        edges.insert(id, deps.map(|d| d["pkg"].as_str().expect("pkg").to_owned()).collect());
    }
    let members: Vec<String> = meta["workspace_members"]
        .as_array()
        .expect("workspace_members")
        .iter()
        .map(|m| m.as_str().expect("member").to_owned())
        .collect();
    members
        .iter()
        .map(|m| {
            let mut seen = BTreeSet::new();
            let mut stack = vec![m.clone()];
            while let Some(id) = stack.pop() {
                for d in edges.get(&id).into_iter().flatten() {
                    if seen.insert(d.clone()) {
                        stack.push(d.clone());
                    }
                }
            }
            (names[m].clone(), seen.iter().map(|id| names[id].clone()).collect())
        })
        .collect()
}

#[test]
fn crates_depend_only_on_what_architecture_allows() {
    let closures = dependency_closures();
    let mut broken = Vec::new();
    for (krate, forbidden) in FORBIDDEN {
        let deps = closures.get(*krate).unwrap_or_else(|| panic!("{krate} is not a workspace member"));
        for f in *forbidden {
            if deps.contains(*f) {
                broken.push(format!("{krate} depends on {f}"));
            }
        }
    }
    assert!(broken.is_empty(), "dependency rules of ARCHITECTURE.md broken:\n{}", broken.join("\n"));
    // The rule has teeth: the app really does pull what the libraries may not.
    let app = &closures["canopy-app"];
    assert!(app.contains("wgpu") && app.contains("clap") && app.contains("canopy-server"), "{app:?}");
    let server_app = &closures["canopy-server-app"];
    assert!(server_app.contains("clap") && server_app.contains("tokio") && server_app.contains("canopy-session"));
}

/// The browser client as it is built, for wasm32 on its own (the workspace's unified features would give it
/// canopy-client's native driver): no runtime, transport, window or server.
#[test]
fn the_browser_client_builds_without_a_runtime_or_a_transport() {
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let args = ["tree", "-p", "canopy-web", "-e", "normal", "--target", "wasm32-unknown-unknown", "--offline"];
    let out = Command::new(cargo)
        .args(args)
        .args(["--prefix", "none", "--format", "{p}"])
        .current_dir(root())
        .output()
        .expect("cargo tree runs");
    assert!(out.status.success(), "cargo tree failed: {}", String::from_utf8_lossy(&out.stderr));
    let tree = String::from_utf8(out.stdout).expect("UTF-8");
    let names: BTreeSet<&str> = tree.lines().filter_map(|l| l.split_whitespace().next()).collect();
    assert!(names.contains("canopy-client") && names.contains("wasm-bindgen"), "{names:?}");
    let forbidden = ["tokio", "quinn", "web-transport-quinn", "socket2", "winit", "clap", "anyhow", "canopy-server"];
    let broken: Vec<_> = forbidden.iter().filter(|f| names.contains(*f)).collect();
    assert!(broken.is_empty(), "canopy-web for wasm32 depends on {broken:?}");
}

/// Every `.rs` file git knows (the tree as committed or staged, plus new files not ignored).
fn rust_files() -> Vec<PathBuf> {
    let out = Command::new("git")
        .args(["ls-files", "--cached", "--others", "--exclude-standard", "*.rs"])
        .current_dir(root())
        .output()
        .expect("git ls-files runs");
    assert!(out.status.success(), "git ls-files failed");
    let files: Vec<PathBuf> = String::from_utf8(out.stdout)
        .expect("paths are UTF-8")
        .lines()
        .map(|l| root().join(l))
        .filter(|p| p.is_file())
        .collect();
    assert!(files.len() > 100, "found only {} Rust files", files.len());
    files
}

fn relative(p: &Path) -> String {
    p.strip_prefix(root()).unwrap_or(p).display().to_string()
}

/// Every `.rs` file directly in a package's `tests/` directory is compiled: it is the root of a test target, or a
/// module (`mod name;`) of a root beside it. A package whose integration tests are one binary of modules
/// (`autotests = false`) would otherwise leave a new file out without a word.
#[test]
fn every_test_file_is_compiled() {
    let meta = metadata();
    let members: BTreeSet<&str> =
        meta["workspace_members"].as_array().expect("members").iter().filter_map(|m| m.as_str()).collect();
    let roots: BTreeSet<PathBuf> = meta["packages"]
        .as_array()
        .expect("packages")
        .iter()
        .filter(|p| members.contains(p["id"].as_str().expect("id")))
        .flat_map(|p| p["targets"].as_array().expect("targets"))
        .filter(|t| t["kind"].as_array().expect("kind").iter().any(|k| k == "test"))
        .map(|t| PathBuf::from(t["src_path"].as_str().expect("src_path")))
        .collect();
    assert!(roots.len() > 10, "found only {} test targets", roots.len());
    // What the test targets compile: their roots, and the files their roots name as `mod x;` beside them.
    let mut compiled: BTreeSet<PathBuf> = roots.iter().cloned().collect();
    for root in &roots {
        let text = std::fs::read_to_string(root).expect("readable");
        let modules = text.lines().filter_map(|l| l.trim().strip_prefix("mod ")?.strip_suffix(';'));
        compiled.extend(modules.map(|m| root.with_file_name(format!("{m}.rs"))));
    }
    // A package's own `tests/` directory (beside its Cargo.toml), not a `tests` module inside `src/`.
    let in_tests_dir = |p: &Path| {
        p.parent().is_some_and(|d| {
            d.file_name().is_some_and(|n| n == "tests")
                && d.parent().is_some_and(|pkg| pkg.join("Cargo.toml").is_file())
        })
    };
    let files: Vec<PathBuf> = rust_files().into_iter().filter(|p| in_tests_dir(p)).collect();
    assert!(files.len() > 40, "found only {} files in tests/ directories", files.len());
    let loose: Vec<String> = files.iter().filter(|f| !compiled.contains(*f)).map(|f| relative(f)).collect();
    assert!(
        loose.is_empty(),
        "test files no target compiles (name them `mod x;` in their binary):\n{}",
        loose.join("\n")
    );
}

#[test]
fn every_rust_file_opens_with_a_doc_line() {
    let missing: Vec<String> = rust_files()
        .into_iter()
        .filter(|p| !std::fs::read_to_string(p).expect("readable").starts_with("//!"))
        .map(|p| relative(&p))
        .collect();
    assert!(missing.is_empty(), "files that do not open with a `//!` line:\n{}", missing.join("\n"));
}

/// Files allowed past 1,000 lines, with the reason.
const LONG_FILES: &[(&str, &str)] = &[];

#[test]
fn no_file_is_over_a_thousand_lines_unless_listed() {
    let listed: BTreeSet<&str> = LONG_FILES.iter().map(|(f, _)| *f).collect();
    let long: Vec<String> = rust_files()
        .into_iter()
        .map(|p| (relative(&p), std::fs::read_to_string(&p).expect("readable").lines().count()))
        .filter(|(f, n)| *n > 1000 && !listed.contains(f.as_str()))
        .map(|(f, n)| format!("{f}: {n} lines"))
        .collect();
    assert!(long.is_empty(), "files over 1,000 lines (split them, or list them with a reason):\n{}", long.join("\n"));
}

/// The code of a file without line comments and without its `#[cfg(test)]` part (tests may read the clock).
fn code_outside_tests(text: &str) -> String {
    let body = text.split("#[cfg(test)]").next().unwrap_or("");
    body.lines().map(|l| l.split("//").next().unwrap_or("")).collect::<Vec<_>>().join("\n")
}

/// The sans-IO cores: fed `now` and messages by their drivers, they never read a clock or touch a socket. Every
/// file under a directory listed here is one.
const SANS_IO: &[&str] = &["server/session/src/", "protocol/src/", "client/net/src/state.rs", "client/net/src/state/"];

#[test]
fn sans_io_cores_read_no_clock_and_use_no_runtime() {
    let mut found = Vec::new();
    let files: Vec<PathBuf> =
        rust_files().into_iter().filter(|p| SANS_IO.iter().any(|core| relative(p).starts_with(core))).collect();
    assert!(files.len() > SANS_IO.len(), "the sans-IO cores' files are found: {files:?}");
    for p in files {
        let code = code_outside_tests(&std::fs::read_to_string(&p).expect("readable"));
        for word in ["Instant::now", "SystemTime", "tokio", "quinn", "std::net", "std::fs"] {
            if code.contains(word) {
                found.push(format!("{}: {word}", relative(&p)));
            }
        }
    }
    assert!(found.is_empty(), "sans-IO code that reaches for a clock or IO:\n{}", found.join("\n"));
    assert!(code_outside_tests("let t = Instant::now(); // x\n#[cfg(test)] SystemTime").contains("Instant::now"));
}

#[test]
fn no_ignored_test_without_a_reason() {
    let bare: Vec<String> = rust_files()
        .into_iter()
        .flat_map(|p| {
            let text = std::fs::read_to_string(&p).expect("readable");
            let f = relative(&p);
            text.lines()
                .enumerate()
                .filter(|(_, l)| l.trim() == "#[ignore]")
                .map(|(i, _)| format!("{f}:{}", i + 1))
                .collect::<Vec<_>>()
        })
        .collect();
    assert!(bare.is_empty(), "#[ignore] without a reason (write #[ignore = \"why\"]):\n{}", bare.join("\n"));
}

/// ARCHITECTURE.md stays a map, short and without numbers (rust-analyzer's `architecture.md`): what it cannot hold
/// lives in `docs/`, so every page there must be reachable from README.md, and every workspace member must have its
/// place in the map.
#[test]
fn architecture_doc_is_short_and_every_doc_is_linked() {
    const MAX_ARCHITECTURE_BYTES: u64 = 20 * 1024;
    let architecture_path = root().join("ARCHITECTURE.md");
    let size = std::fs::metadata(&architecture_path).expect("ARCHITECTURE.md exists").len();
    assert!(
        size <= MAX_ARCHITECTURE_BYTES,
        "ARCHITECTURE.md is {size} bytes, more than {MAX_ARCHITECTURE_BYTES}: move details and numbers into docs/*.md"
    );
    let architecture = std::fs::read_to_string(&architecture_path).expect("ARCHITECTURE.md is UTF-8 text");
    let readme = std::fs::read_to_string(root().join("README.md")).expect("README.md is UTF-8 text");

    // Every docs/NAME.md is linked from README.md by its relative path.
    let mut docs: Vec<String> = std::fs::read_dir(root().join("docs"))
        .expect("docs/ is readable")
        .map(|e| e.expect("a docs/ entry is readable").path())
        .filter(|p| p.is_file() && p.extension().is_some_and(|x| x == "md"))
        .map(|p| format!("docs/{}", p.file_name().expect("a file name").to_string_lossy()))
        .collect();
    docs.sort();
    assert!(!docs.is_empty(), "no docs/*.md found under {}", root().join("docs").display());
    let unlinked: Vec<&str> = docs.iter().map(String::as_str).filter(|d| !readme.contains(d)).collect();
    assert!(
        unlinked.is_empty(),
        "docs/ pages that README.md does not link (link each by its path, e.g. [docs/x.md](docs/x.md)):\n{}",
        unlinked.join("\n")
    );

    // Every workspace member directory is named in ARCHITECTURE.md as a path in backticks: `dir` or `dir/`.
    let manifest = std::fs::read_to_string(root().join("Cargo.toml")).expect("the root Cargo.toml is readable");
    let list = manifest
        .split_once("members = [")
        .and_then(|(_, rest)| rest.split_once(']'))
        .map(|(list, _)| list)
        .expect("the root Cargo.toml has `members = [...]`");
    let members: Vec<&str> = list.split(',').map(|m| m.trim().trim_matches('"')).filter(|m| !m.is_empty()).collect();
    assert!(members.len() > 1, "read too few workspace members from the root Cargo.toml: {members:?}");
    let missing: Vec<&str> = members
        .iter()
        .copied()
        .filter(|m| !architecture.contains(&format!("`{m}`")) && !architecture.contains(&format!("`{m}/`")))
        .collect();
    assert!(
        missing.is_empty(),
        "workspace members that ARCHITECTURE.md does not name (as `dir/` in its code map):\n{}",
        missing.join("\n")
    );
}
