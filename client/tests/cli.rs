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
    assert!(out.contains("encoded     166 bytes"), "{out}");
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

#[test]
fn export_over_the_size_limit_fails_before_writing() {
    let out = temp("too-large.glb");
    let _ = std::fs::remove_file(&out);
    // The same check as the 4 GiB GLB limit, under a limit a test can reach: the grove needs far more than 10 kB.
    let o = canopy(&["species", "export", "worm", "--grove", "4", "--max-bytes", "10000", "-o", out.to_str().unwrap()]);
    let msg = text(&o);
    assert!(!o.status.success(), "{msg}");
    assert!(msg.contains("not writing") && msg.contains("over the limit of 10000 bytes"), "{msg}");
    assert!(msg.contains("4294967295 bytes: its lengths are u32"), "{msg}");
    assert!(msg.contains("--grove") && msg.contains("--detail") && msg.contains("--lod"), "{msg}");
    assert!(!out.exists(), "no file is written");
    // The limit cannot be raised past the GLB's.
    let o = canopy(&["species", "export", "worm", "--max-bytes", "5000000000", "-o", out.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(out.exists());
}

#[test]
fn export_refuses_a_grove_estimated_too_large_at_once_and_keeps_the_old_file() {
    let dir = temp("export-keep");
    std::fs::create_dir_all(&dir).unwrap();
    let out = dir.join("grove.glb");
    std::fs::write(&out, b"the old file").unwrap();
    let o = out.to_str().unwrap();
    // A worm is about 16 kB of mesh data: 100 of them are estimated far over 200 kB after the first.
    let r = canopy(&["species", "export", "worm", "--grove", "100", "--max-bytes", "200000", "-o", o]);
    let msg = text(&r);
    assert!(!r.status.success(), "{msg}");
    assert!(msg.contains("estimated from the first of 100 instances") && msg.contains("--no-estimate"), "{msg}");
    // Counting exactly, it stops at the first instance over the limit.
    let r = canopy(&["species", "export", "worm", "--grove", "100", "--max-bytes", "200000", "--no-estimate", "-o", o]);
    let msg = text(&r);
    assert!(!r.status.success(), "{msg}");
    assert!(msg.contains("the first ") && msg.contains(" of 100 instances") && !msg.contains("estimated"), "{msg}");
    assert_eq!(std::fs::read(&out).unwrap(), b"the old file", "the old file is untouched");
    let names: Vec<_> = std::fs::read_dir(&dir).unwrap().map(|e| e.unwrap().file_name()).collect();
    assert_eq!(names, ["grove.glb"], "no temporary file is left");
    // What fits replaces it; a directory is refused.
    let r = canopy(&["species", "export", "worm", "--grove", "9", "-o", o]);
    assert!(r.status.success(), "{}", text(&r));
    let (json, _) = canopy_worlds::gltf::parse_glb_header(&std::fs::read(&out).unwrap()).unwrap();
    assert_eq!(json["nodes"].as_array().unwrap().len(), 9);
    let r = canopy(&["species", "export", "worm", "-o", dir.to_str().unwrap()]);
    assert!(!r.status.success() && text(&r).contains("a directory: refusing to write over it"), "{}", text(&r));
}

#[test]
fn check_reports_non_finite_constants_and_species_that_cannot_finish() {
    let nan = temp("nan.species");
    std::fs::write(&nan, "species Nan\nparam c = 0/0\nsphere(c)\n").unwrap();
    let inf = temp("inf.lsys");
    std::fs::write(&inf, "lsystem Inf\nderive 2\nparam len = 1/0\naxiom: A\nA -> F(1) A\n").unwrap();
    let runaway = temp("runaway.species");
    std::fs::write(&runaway, "species Runaway\ndef A separator { sphere(1) use A }\n").unwrap();
    let div = temp("div.species");
    std::fs::write(&div, "species Div\nparam n = 1\ncylinder(1 / (n - 1), 2)\n").unwrap();
    let good = concat!(env!("CARGO_MANIFEST_DIR"), "/../worlds/species/worm.species");
    let files = [&nan, &inf, &runaway, &div].map(|p| p.to_str().unwrap().to_string());
    let mut args = vec!["species", "check", good];
    args.extend(files.iter().map(String::as_str));
    let o = canopy(&args);
    let out = text(&o);
    assert!(!o.status.success(), "{out}");
    assert!(out.contains("nan.species:2:11: error: constant expression evaluates to NaN"), "{out}");
    assert!(out.contains("inf.lsys:3:13: error: constant expression evaluates to inf"), "{out}");
    assert!(
        out.contains("runaway.species:1:1: error: species `Runaway` cannot finish with its default parameters"),
        "{out}"
    );
    assert!(out.contains("div.species:1:1: error: species `Div` cannot finish"), "{out}");
    assert!(out.contains("non-finite"), "{out}");
    assert!(out.contains("seed 0 with default parameters: 5 primitives"), "worm(4) is 4 spheres and a cone: {out}");
    assert!(out.contains("5 file(s) checked, 4 failed"), "{out}");
}

#[test]
fn stats_prints_the_real_ratio_below_one() {
    // Worm(0) is one cone: 28 explicit bytes against a 165-byte species.
    let o = canopy(&["species", "stats", "worm", "--param", "c=0", "--repeat", "1"]);
    let out = text(&o);
    assert!(o.status.success(), "{out}");
    let line = |prefix: &str| out.lines().find(|l| l.starts_with(prefix)).unwrap_or_else(|| panic!("{prefix}: {out}"));
    let number = |prefix: &str| -> f64 {
        line(prefix)[prefix.len()..].split_whitespace().next().unwrap().replace(',', "").parse().unwrap()
    };
    let (explicit, encoded) = (number("explicit"), number("encoded"));
    assert!(explicit > 0.0 && explicit < encoded, "{out}");
    let printed: f64 = line("explicit").rsplit(": ").next().unwrap().split('×').next().unwrap().trim().parse().unwrap();
    let real = explicit / encoded;
    assert!(printed > 0.0 && (printed - real).abs() <= 0.005, "printed {printed}×, real {real}: {out}");
    assert!(out.contains(&format!("{real:.2}× the species")), "{out}");
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
    assert!(out.contains("instances: 177241"), "{out}");
    assert!(out.contains("the walkthrough window failed"), "{out}");
    assert!(out.contains("AOI complete 3/3"), "{out}");
    assert!(out.contains("checked against the world: 3 of 3 exact"), "{out}");
    assert!(out.contains("species: ") && out.contains(", 0 received twice"), "{out}");
}

/// Bots that fly over a world that exists only cell by cell: the in-process server on the embedded highlands,
/// two flights at 250 m/s and 1500 m (the radius they ask for capped by `--max-radius`), checked at the end against
/// the world's function.
#[test]
fn demo_flies_bots_over_the_highlands_and_checks_them_against_the_function() {
    let o = Command::new(env!("CARGO_BIN_EXE_canopy"))
        .args(["demo", "--world", "highlands", "--path", "flight", "--speed", "250", "--altitude", "1500"])
        .args(["--max-radius", "160", "--bots", "2", "--duration", "3", "--no-window"])
        .output()
        .expect("canopy runs");
    let out = text(&o);
    assert!(o.status.success(), "{out}");
    assert!(out.contains("world highlands"), "{out}");
    assert!(out.contains("2 bots flying (flight, 250 m/s, 1500 m above the terrain, AOI radius 160 m)"), "{out}");
    assert!(out.contains("checked against the world: 2 of 2 exact"), "{out}");
    let bad = canopy(&["demo", "--world", "atlantis", "--no-window"]);
    assert!(!bad.status.success() && text(&bad).contains("no embedded world of that name (forest, highlands)"));
}

#[test]
fn an_l_system_too_deep_is_reported_in_its_own_terms_by_every_command() {
    let deep = temp("deep.lsys");
    std::fs::write(&deep, "lsystem Deep\nderive 2000\nangle 30\naxiom: A\nA -> F [ + A ]\n").unwrap();
    let path = deep.to_str().unwrap();
    for cmd in
        [&["species", "amplify", path, "--out", "-"][..], &["species", "stats", path], &["species", "check", path]]
    {
        let o = canopy(cmd);
        assert!(!o.status.success(), "{cmd:?}");
        let t = text(&o);
        assert!(t.contains("derivation depth 2000") && t.contains("maxdepth"), "{cmd:?}: {t}");
        assert!(!t.contains("separators nested"), "{cmd:?}: {t}");
    }
}

/// `canopy world stats` on the large world estimates it from sampled cells without expanding it, and `--cells`
/// expands a rectangle exactly; a malformed rectangle is refused with the reason.
#[test]
fn world_stats_samples_a_large_world_and_expands_a_rectangle_exactly() {
    let manifest = concat!(env!("CARGO_MANIFEST_DIR"), "/../worlds/highlands/highlands.world");
    let o = canopy(&["world", "stats", manifest, "--samples", "16", "--cells", "-320,382,-319,383"]);
    let out = text(&o);
    assert!(o.status.success(), "{out}");
    assert!(out.contains("10485.76 km²") && out.contains("expanded on demand"), "{out}");
    assert!(out.contains("terrain: fractal"), "{out}");
    assert!(out.contains("instances (estimated from 16 of 2560000 cells)"), "{out}");
    assert!(out.contains("cells -320,382 ..= -319,383: 4 cells"), "{out}");
    // The rectangle's count is the world function's, whatever else was expanded first.
    let world = canopy_worlds::world::World::load(std::path::Path::new(manifest)).unwrap();
    let exact: usize = world
        .expand_cells(
            canopy_worlds::world::CellKey { x: -320, z: 382 },
            canopy_worlds::world::CellKey { x: -319, z: 383 },
        )
        .iter()
        .map(|(_, l)| l.len())
        .sum();
    assert!(out.contains(&format!("4 cells, {exact} instances")), "{exact} in\n{out}");
    let bad = canopy(&["world", "stats", manifest, "--cells", "5,5,1,1"]);
    assert_eq!(bad.status.code(), Some(2));
    assert!(text(&bad).contains("expected X0 ≤ X1 and Z0 ≤ Z1"), "{}", text(&bad));
}

/// `canopy bots --edit-rate` needs an editor token, and says so before connecting anywhere; a token that is not
/// hexadecimal is refused too.
#[test]
fn bots_that_edit_need_a_token() {
    let run = |extra: &[&str]| {
        let args = [&["bots", "--edit-rate", "1", "--server", "127.0.0.1:9", "--no-verify"], extra].concat();
        Command::new(env!("CARGO_BIN_EXE_canopy")).args(args).env_remove("CANOPY_TOKEN").output().unwrap()
    };
    let o = run(&[]);
    assert!(!o.status.success());
    assert!(text(&o).contains("--edit-rate needs an editor token: --token HEX or CANOPY_TOKEN"), "{}", text(&o));
    let o = run(&["--token", "not-hex"]);
    assert!(!o.status.success());
    assert!(text(&o).contains("--token: expected hexadecimal digits"), "{}", text(&o));
}

/// `canopy bots --processes 2` (issue 31): six bots in two processes of the command against a server in this process
/// on the default world, and one summary over both: every bot run, complete and exact against the world. What
/// cannot be split over processes is refused, and a process that fails fails the run, named.
#[test]
fn bots_in_two_processes_sum_up_to_one_run() {
    use canopy_server::{ServeOptions, ServerConfig, serve};
    let refused = |extra: &[&str], why: &str| {
        let o = canopy(&[&["bots", "--server", "127.0.0.1:9", "--insecure"], extra].concat());
        assert!(!o.status.success() && text(&o).contains(why), "{extra:?}: {}", text(&o));
    };
    refused(&["--processes", "0"], "--processes must be at least 1");
    refused(&["--processes", "2", "--edit-rate", "1", "--token", "00"], "not with --edit-rate or --check-edits");
    refused(&["--processes", "2", "--check-edits", "nats://127.0.0.1:9"], "not with --edit-rate or --check-edits");
    refused(&["--processes", "2", "--count", "2", "--world", "atlantis"], "2 of 2 bot processes failed");
    refused(&["--processes", "2", "--count", "2", "--world", "atlantis"], "bot process 2 of 2 (bots 1..2): exit");

    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build().unwrap();
    let server = ServerConfig { listen: "127.0.0.1:0".parse().unwrap(), ..ServerConfig::default() };
    let opts = ServeOptions { server, ..ServeOptions::default() };
    let served = rt.block_on(serve(canopy_worlds::world::World::default_world(), opts)).expect("server starts");
    let (addr, fingerprint) = (served.local_addr().to_string(), served.fingerprint().to_string());
    let o = canopy(&[
        "bots",
        "--processes",
        "2",
        "--count",
        "6",
        "--duration",
        "2",
        "--radius",
        "120",
        "--path",
        "random",
        "--server",
        &addr,
        "--cert-fingerprint",
        &fingerprint,
    ]);
    let out = text(&o);
    eprintln!("--- canopy bots --processes 2\n{out}");
    assert!(o.status.success(), "{out}");
    assert!(
        out.contains("process 1 of 2 (bots 0..3) ended") && out.contains("process 2 of 2 (bots 3..6) ended"),
        "{out}"
    );
    assert!(out.contains("bots: 6 run, 6 complete at the end, 0 failed"), "{out}");
    assert!(out.contains("checked against the world: 6 of 6 exact"), "{out}");
    assert!(out.contains("connect → first complete AOI: p50 "), "{out}");
    rt.block_on(served.shutdown(std::time::Duration::from_secs(1)));
}

/// `canopy species edit --screenshot` renders the editor window offscreen (lavapipe is enough) and exits; a file of
/// no known format is refused; `species stats` prints the LOD levels the editor shows.
#[test]
fn species_edit_screenshot_writes_the_window() {
    let out = temp("edit.png");
    let o = canopy(&[
        "species",
        "edit",
        "worm",
        "--param",
        "c=6",
        "--width",
        "640",
        "--height",
        "400",
        "--screenshot",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", text(&o));
    let img = image::open(&out).expect("a PNG").to_rgba8();
    assert_eq!(img.dimensions(), (640, 400));
    let bad = canopy(&["species", "edit", "notes.txt", "--screenshot", out.to_str().unwrap()]);
    assert!(!bad.status.success());
    assert!(text(&bad).contains("unknown format"), "{}", text(&bad));
    let o = canopy(&["species", "stats", "conifer", "--repeat", "1"]);
    assert!(text(&o).contains("lod         4 level(s): detail 0 "), "{}", text(&o));
    assert!(text(&o).contains("(77 nodes, 3 parameter(s), 11 working value(s))"), "{}", text(&o));
    // A working value is the species' own: not for --param.
    let o = canopy(&["species", "stats", "monopodial", "--param", "m=2"]);
    assert!(!o.status.success());
    let want = "`m` is a working value of species `monopodial`, not a parameter (its parameters: height, branch_length, branching)";
    assert!(text(&o).contains(want), "{}", text(&o));
}

/// `canopy render --world highlands` from altitude (issue 15): the records around the camera expanded from the world
/// function and, beyond them, the far view's summary nodes drawn as forest; `--no-summaries` draws only the ground
/// beyond the records, so the picture loses its forest.
#[test]
fn render_from_altitude_draws_the_far_view_from_summaries() {
    let camera = "position 2000 ~1500 -30000; look-at 2600 ~0 -22000; fov 60";
    let run = |out: &PathBuf, extra: &[&str]| {
        let mut args = vec!["render", "--world", "highlands", "--camera", camera, "--width", "160", "--height", "90"];
        args.extend(["--far-range", "6000", "--record-radius", "128", "--out", out.to_str().unwrap()]);
        args.extend(extra);
        let o = canopy(&args);
        assert!(o.status.success(), "{}", text(&o));
        (text(&o), image::open(out).expect("a PNG").to_rgba8())
    };
    let (with, a) = run(&temp("far.png"), &[]);
    let (without, b) = run(&temp("near.png"), &["--no-summaries"]);
    let nodes = |out: &str| {
        let at = out.find(" summary nodes").unwrap_or_else(|| panic!("{out}"));
        out[..at].rsplit(' ').next().unwrap().parse::<usize>().unwrap()
    };
    assert!(nodes(&with) > 10 && nodes(&without) == 0, "{with}\n{without}");
    assert!(with.contains("forest patches") && !with.contains("as 0 forest patches"), "{with}");
    // Forest is dark green: green well above red and blue, and dark.
    let forest =
        |img: &image::RgbaImage| img.pixels().filter(|p| p[1] > p[0] + 10 && p[1] > p[2] + 10 && p[1] < 90).count();
    assert!(forest(&a) > 1000 && forest(&b) < forest(&a) / 10, "{} vs {}", forest(&a), forest(&b));
}

/// The names in the `Commands:` section of a `--help` text (without `help`).
fn subcommands(help: &str) -> Vec<String> {
    help.lines()
        .skip_while(|l| !l.starts_with("Commands:"))
        .skip(1)
        .take_while(|l| l.starts_with("  "))
        .filter_map(|l| l.split_whitespace().next())
        .filter(|n| *n != "help")
        .map(str::to_owned)
        .collect()
}

#[test]
fn help_names_every_subcommand_and_every_help_renders() {
    let top = canopy(&["--help"]);
    assert!(top.status.success(), "{}", text(&top));
    let top = text(&top);
    let commands = subcommands(&top);
    for c in ["species", "hypertree", "world", "bandwidth", "bots", "demo", "render", "walk"] {
        assert!(commands.iter().any(|n| n == c), "`canopy --help` lists {c}: {top}");
    }
    for command in &commands {
        let o = canopy(&[command, "--help"]);
        assert!(o.status.success(), "canopy {command} --help: {}", text(&o));
        let help = text(&o);
        // A command with subcommands: its one line in `canopy --help` names every one of them.
        let line = top.lines().find(|l| l.split_whitespace().next() == Some(command)).expect("the command's line");
        for sub in subcommands(&help) {
            assert!(line.contains(&sub), "`canopy --help` says of {command}: {line:?}, without `{sub}`");
            let o = canopy(&[command, &sub, "--help"]);
            assert!(o.status.success(), "canopy {command} {sub} --help: {}", text(&o));
        }
    }
}

#[test]
fn client_commands_share_the_connection_flags() {
    for args in [&["walk", "--help"][..], &["bots", "--help"], &["bandwidth", "--help"], &["world", "plant", "--help"]]
    {
        let o = canopy(args);
        let help = text(&o);
        for flag in ["--server <HOST:PORT[,…]>", "--cert-fingerprint <CERT_FINGERPRINT>", "--insecure"] {
            assert!(help.contains(flag), "canopy {} lacks {flag}: {help}", args.join(" "));
        }
    }
    // Trust flags without a server to trust are refused where a server would run in process.
    let o = canopy(&["bandwidth", "--insecure", "--duration", "1"]);
    assert!(!o.status.success() && text(&o).contains("--insecure name the trust of a --server"), "{}", text(&o));
}
