//! `canopy species check`'s library side (issue 12): non-finite constant folds are diagnostics at their
//! `file:line:col` in both text formats, amplification never emits a non-finite primitive (a typed error instead),
//! and a species that cannot finish with its default parameters fails the check.

use canopy_worlds::amplify::{AmplifyError, Budget, Instance, amplify};
use canopy_worlds::diag::{Diagnostic, SourceFile};
use canopy_worlds::library::SPECIES;
use canopy_worlds::load::{CHECK_SEED, check_source, parse_source};

fn check(name: &str, text: &str) -> (Option<usize>, Vec<Diagnostic>) {
    let (checked, diags) = check_source(&SourceFile::new(name, text), &Budget::default());
    (checked.map(|c| c.primitives), diags)
}

/// Check `text` fails and its first diagnostic is at `line:col` with a message that contains `needle`.
fn fails_at(name: &str, text: &str, (line, col): (usize, usize), needle: &str) {
    let (checked, diags) = check(name, text);
    assert_eq!(checked, None, "{name} must fail the check");
    let d = diags.first().unwrap_or_else(|| panic!("{name}: no diagnostic"));
    assert_eq!((d.file.as_str(), d.line, d.col), (name, line, col), "{d}");
    assert!(d.message.contains(needle), "`{needle}` not in: {d}");
}

#[test]
fn non_finite_constant_folds_are_errors_at_their_position() {
    let text = "species Bad\nparam c = 0/0\nsphere(c)\n";
    fails_at("nan.species", text, (2, 11), "evaluates to NaN, not a finite number");
    let text = "species Bad\nparam c = 1\ncylinder(0.1, c * (1/0))\n";
    fails_at("inf.species", text, (3, 15), "evaluates to inf");
    let text = "species Bad\nparam c = 1\ncalc { c = sqrt(-1) }\nsphere(c)\n";
    fails_at("sqrt.species", text, (3, 12), "evaluates to NaN");
    // L-systems parse expressions with the same parser.
    let text = "lsystem Bad\nderive 2\nparam len = 1/0\naxiom: A\nA -> F(1) A\n";
    fails_at("inf.lsys", text, (3, 13), "evaluates to inf");
}

#[test]
fn an_unmatched_closing_brace_is_an_error_not_a_hang() {
    // Recovery after an error inside a block stops before its `}`, which then closes nothing at the top level.
    fails_at("brace.species", "species B\nsphere(1)\n}\ncone(1, 0, 1)\n", (3, 1), "unmatched `}`");
    let (_, diags) = check("calc.species", "species B\nparam c = 1\ncalc { c = 0/0 }\nsphere(c)\n");
    assert_eq!(
        diags[0].to_string().lines().next(),
        Some(
            "calc.species:3:12: error: constant expression evaluates to NaN, not a finite number (division by zero, a root or logarithm out of range, or overflow)"
        )
    );
}

#[test]
fn amplification_never_emits_a_non_finite_primitive() {
    // Not constant, so it parses; with the default n = 1 the radius divides by zero at traversal.
    let text = "species Div\nparam n = 1\nsphere(0.5)\ncylinder(1 / (n - 1), 2)\n";
    let (g, d) = parse_source(&SourceFile::new("div.species", text));
    assert!(d.is_empty(), "{d:?}");
    let g = g.unwrap();
    let node = g.nodes.iter().position(|n| matches!(n, canopy_protocol::Node::Cylinder { .. })).unwrap() as u32;
    assert_eq!(
        amplify(&g, &Instance::new(1), &Budget::default()),
        Err(AmplifyError::NonFinite { node, kind: "cylinder" })
    );
    // Another value of the parameter makes it finite.
    let n = g.param_slot("n").unwrap();
    let ok = amplify(&g, &Instance { seed: 1, params: vec![(n, 3.0)], detail: 0 }, &Budget::default()).unwrap();
    assert_eq!(ok.primitives.len(), 2);

    // Transforms, colours and leaf points are checked too, not only sizes.
    for (what, body) in [
        ("transform", "scale(x, 1, 1)\nsphere(1)"),
        ("translation", "translate(0, x, 0)\nbox(1, 1, 1)"),
        ("colour", "material(x, 0, 0)\ncone(1, 0, 1)"),
        ("leaf point", "leaf((0, 0, 0), (1, 0, 0), (0, x, 0))"),
        ("overflow", "scale(1e30, 1e30, 1e30)\nscale(1e30, 1e30, 1e30)\nsphere(1)"),
    ] {
        let text = format!("species T\nparam z = 0\nparam x = 1 / z\n{body}\n");
        let (g, d) = parse_source(&SourceFile::new("t.species", &text));
        assert!(d.is_empty(), "{what}: {d:?}");
        let r = amplify(&g.unwrap(), &Instance::new(0), &Budget::default());
        assert!(matches!(r, Err(AmplifyError::NonFinite { .. })), "{what}: {r:?}");
    }

    // The check reports it for the default parameters, at the start of the file, naming the species.
    fails_at("div.species", text, (1, 1), "species `Div` cannot finish with its default parameters");
    let (_, diags) = check("div.species", text);
    assert!(diags[0].message.contains("non-finite"), "{}", diags[0]);
}

#[test]
fn a_species_that_cannot_finish_fails_the_check() {
    let budget = Budget::default();
    // Runaway recursion through separators: the depth bound of the default budget.
    let text = "species Runaway\ndef A separator { sphere(1) use A }\n";
    let g = parse_source(&SourceFile::new("runaway.species", text)).0.unwrap();
    let err = amplify(&g, &Instance::new(CHECK_SEED), &budget).unwrap_err();
    assert_eq!(err, AmplifyError::Depth(budget.max_depth));
    fails_at(
        "runaway.species",
        text,
        (1, 1),
        &format!("cannot finish with its default parameters (seed 0, detail 0): {err}"),
    );
    // Ten million primitives: over the default budget's million.
    let text = "species Many\nparam n = 7\ndef A select(n > 0) { sphere(1) recurse { calc { n = n - 1 } \
                use A use A use A use A use A use A use A use A use A use A } }\n";
    fails_at("many.species", text, (1, 1), &AmplifyError::Primitives(budget.max_primitives).to_string());
    // A loop that never ends: the steps bound (a small budget keeps the test quick; the CLI uses the default).
    let small = Budget { max_steps: 100_000, ..Budget::default() };
    let (checked, diags) =
        check_source(&SourceFile::new("loop.species", "species Loop\ndef A group { use A }\n"), &small);
    assert!(checked.is_none());
    assert!(diags[0].message.contains("more than 100000 traversal steps"), "{}", diags[0]);
}

#[test]
fn every_library_species_passes_the_check() {
    for entry in SPECIES {
        let (checked, diags) = check(entry.file, entry.text);
        assert!(diags.is_empty(), "{}: {diags:?}", entry.file);
        let checked = checked.unwrap_or_else(|| panic!("{} fails the check", entry.file));
        // The same instance as amplifying seed CHECK_SEED directly.
        let g = entry.load().unwrap();
        let s = amplify(&g, &Instance::new(CHECK_SEED), &Budget::default()).unwrap();
        assert_eq!(checked, s.primitives.len(), "{}", entry.file);
        assert!(checked > 0, "{}", entry.file);
    }
}

#[test]
fn an_l_system_too_deep_is_reported_in_its_own_terms() {
    // A derivation that nests a branch per step: 2,000 steps nest deeper than the default 1,024.
    let text = "lsystem Deep\nderive 2000\nangle 30\naxiom: A\nA -> F [ + A ] \n";
    let (checked, diags) = check("deep.lsys", text);
    assert_eq!(checked, None);
    let m = &diags.last().expect("a diagnostic").message;
    assert!(m.contains("derivation depth 2000") && m.contains("maxdepth"), "{m}");
    assert!(m.contains("A -> F [ + A ]"), "names the production: {m}");
    assert!(!m.contains("separators"), "{m}");
}
