//! L-Py's forms in `.lsys` files (`endlsystem`, `ignore:`, `: *`, `(p)` probabilities, the default angle and
//! materials, Python refused), each against the string-rewriting reference; and error recovery: one typo in a
//! library file gives exactly one diagnostic, on the typo's line.

use canopy_worlds::amplify::{Budget, Instance, amplify};
use canopy_worlds::diag::{Diagnostic, SourceFile};
use canopy_worlds::lsystem::{LPY_DEFAULT_ANGLE, LPY_MATERIALS, LSystem, reference_stream};
use canopy_worlds::primitive::PrimitiveStream;

fn render(d: &[Diagnostic]) -> String {
    d.iter().map(|d| d.to_string()).collect::<Vec<_>>().join("\n")
}

fn parse(text: &str) -> (Option<LSystem>, Vec<Diagnostic>) {
    LSystem::parse(&SourceFile::new("lpy.lsys", text))
}

fn lsys(text: &str) -> LSystem {
    let (l, d) = parse(text);
    assert!(d.is_empty(), "{}", render(&d));
    l.unwrap()
}

/// Exactly one diagnostic, on `line`, containing every one of `want`.
fn one_error(text: &str, line: usize, want: &[&str]) -> Diagnostic {
    let (l, d) = parse(text);
    assert!(l.is_none(), "expected an error for:\n{text}");
    assert_eq!(d.len(), 1, "one diagnostic for:\n{text}\n{}", render(&d));
    assert_eq!(d[0].line, line, "{}", render(&d));
    for w in want {
        assert!(d[0].message.contains(w), "want `{w}`: {}", d[0].message);
    }
    d.into_iter().next().unwrap()
}

fn dcg(l: &LSystem, inst: &Instance) -> PrimitiveStream {
    amplify(&l.graph, inst, &Budget::default()).unwrap()
}

/// The DCG's primitive stream equals the string-rewriting reference, bit for bit, for several seeds and details.
fn assert_equivalent(name: &str, l: &LSystem) {
    for seed in [0u64, 1, 7, 0x5eed_cafe_f00d] {
        for detail in [0u8, 1] {
            let inst = Instance::new(seed).with_detail(detail);
            let graph = dcg(l, &inst);
            let string = reference_stream(l, &inst, &Budget::default()).unwrap();
            assert!(!graph.primitives.is_empty(), "{name} draws something");
            assert_eq!(graph.primitives.len(), string.primitives.len(), "{name}: seed {seed} detail {detail}");
            assert!(graph == string, "{name}: seed {seed} detail {detail}");
        }
    }
}

fn colors(s: &PrimitiveStream) -> Vec<[f32; 3]> {
    s.primitives.iter().map(|p| p.color).collect()
}

// ---------------------------------------------------------------------------------------------------------------
// L-Py's forms.

/// A file as L-Py's editor saves it: rules between `Axiom:` and `endlsystem`, then the editor's Python.
const LPY_FILE: &str = "
Axiom: A(1) B
derivation length: 4
ignore: +-
production:
A(x) : * --> F(x) [ + A(x * 0.7) ] ; [ - A(x * 0.6) ] , A(x * 0.9)
B --> (0.3) F(0.2) ; B
B --> (0.7) f(0.2) , B
consider: A
interpretation:
endlsystem
###### INITIALISATION ######

__lpy_code_version__ = 1.1

def __initialiseContext__(context):
\timport openalea.plantgl.all as pgl
\tColor_1 = pgl.Material(\"Color_1\" , ambient = (65,45,15) , diffuse = 3 , )
\tcontext.turtle.setMaterial(1,Color_1)
";

#[test]
fn lsystem_lpy_file_loads_and_equals_string_rewriting() {
    let l = lsys(LPY_FILE);
    assert!(l.lpy_colors, "no palette: `;` and `,` take L-Py's materials");
    assert_equivalent("L-Py file", &l);
    // The same L-system in this format's own spellings draws the same plant.
    let own = lsys(&format!(
        "derive 4\nangle {LPY_DEFAULT_ANGLE}\naxiom: A(1) B\n\
         A(x) -> F(x) [ + A(x * 0.7) ] ; [ - A(x * 0.6) ] , A(x * 0.9)\n\
         B -> F(0.2) ; B : 0.3\nB -> f(0.2) , B : 0.7\n"
    ));
    for seed in [0, 3, 11] {
        assert_eq!(dcg(&l, &Instance::new(seed)), dcg(&own, &Instance::new(seed)), "seed {seed}");
    }
}

#[test]
fn lsystem_endlsystem_ends_the_rules() {
    let base = "derive 3\naxiom: A\nA -> F [ + A ] A\n";
    let plain = lsys(base);
    // What follows `endlsystem` is L-Py's Python and is not read: not even rules or mistakes.
    let ended = lsys(&format!("{base}endlsystem   # the end\nA -> f A\nnot an L-system line (\n"));
    assert_eq!(dcg(&ended, &Instance::new(0)), dcg(&plain, &Instance::new(0)));
    assert_equivalent("endlsystem", &ended);
    // `endlsystem` must be the whole line.
    one_error(&format!("{base}endlsystem now\n"), 4, &["expected `->` or `=>`"]);
}

#[test]
fn lsystem_ignore_and_consider_change_nothing() {
    let base = "derive 4\nangle 25\naxiom: A\nA -> F [ + A ] [ - A ] ! A\nA => F\n";
    let plain = lsys(base);
    for line in ["ignore: +-", "ignore: + - / ! Elasticity", "consider: A F", "ignore:"] {
        let text = base.replace("axiom: A\n", &format!("axiom: A\n{line}\n"));
        let l = lsys(&text);
        assert_eq!(dcg(&l, &Instance::new(2)), dcg(&plain, &Instance::new(2)), "{line}");
        assert_equivalent(line, &l);
    }
}

#[test]
fn lsystem_star_condition_always_holds() {
    let star = lsys("derive 5\nangle 30\naxiom: A(1)\nA(x) : * -> F(x) [ + A(x * 0.6) ] A(x * 0.8)\nA(x) -> f\n");
    let none = lsys("derive 5\nangle 30\naxiom: A(1)\nA(x) -> F(x) [ + A(x * 0.6) ] A(x * 0.8)\nA(x) -> f\n");
    assert_eq!(dcg(&star, &Instance::new(0)), dcg(&none, &Instance::new(0)));
    assert_equivalent("star condition", &star);
    // Beside conditions and probabilities, cpfg style (`pred : * --> succ : p`).
    let mixed = lsys(
        "derive 6\nangle 20\naxiom: A(0)\nA(n) : n > 3 -> F A(n + 1)\nA(n) : * --> F [ + A(n + 1) ] A(n + 1) : 2\n\
         A(n) :* --> f A(n + 1) : 1\n",
    );
    assert_equivalent("star with probabilities", &mixed);
}

#[test]
fn lsystem_probability_on_the_arrow() {
    let head = "derive 5\nangle 30\naxiom: B(1)\nB(x) => F(x)\n";
    let arrow = format!("{head}B(x) --> (0.3) F(x) [ + B(x / 2) ] B(x)\nB(x) -> (x * 0.7) f B(x)\n");
    let colon = format!("{head}B(x) --> F(x) [ + B(x / 2) ] B(x) : 0.3\nB(x) -> f B(x) : x * 0.7\n");
    let (a, c) = (lsys(&arrow), lsys(&colon));
    for seed in 0..6 {
        assert_eq!(dcg(&a, &Instance::new(seed)), dcg(&c, &Instance::new(seed)), "seed {seed}");
    }
    assert_equivalent("probability on the arrow", &a);
    // The weights are followed: 30 % cylinders over a long derivation.
    let l = lsys("derive 50\naxiom: B\nB --> (0.3) F B\nB --> (0.7) f B\n");
    let drawn: usize = (0..40u64).map(|seed| dcg(&l, &Instance::new(seed)).primitives.len()).sum();
    let share = drawn as f64 / (40.0 * 50.0);
    assert!((share - 0.3).abs() < 0.05, "share of F is {share}");
    // Mistakes.
    one_error("derive 1\naxiom: B\nB -> (0.3) F : 0.3\nB -> f\n", 3, &["given twice"]);
    one_error("derive 1\naxiom: B\nB => (0.3) F\n", 3, &["takes no probability"]);
    let d = one_error("derive 1\naxiom: B\nB (0.3) -> F\n", 3, &["on the arrow, `A --> (0.3) B`"]);
    assert_eq!(d.col, 4);
    one_error("derive 1\naxiom: B\nB -> (0.3 F\n", 3, &["expected `)`"]);
}

#[test]
fn lsystem_default_angle_is_lpys() {
    assert_eq!(LPY_DEFAULT_ANGLE, 60.0);
    let implicit = lsys("derive 4\naxiom: A\nA -> F [ + A ] [ - A ] & ^ \\ / A\n");
    let explicit = lsys("derive 4\naxiom: A\nA -> F [ +(60) A ] [ -(60) A ] &(60) ^(60) \\(60) /(60) A\n");
    assert_eq!(dcg(&implicit, &Instance::new(0)), dcg(&explicit, &Instance::new(0)));
    assert_equivalent("default angle", &implicit);
    assert!(implicit.graph.param_slot("angle").is_none(), "the default is not a species parameter");
    // `+` turns 60° about Z: the second cylinder starts one unit up and leans 60° to -X.
    let s = dcg(&lsys("derive 0\naxiom: F + F F\n"), &Instance::new(0));
    let m = s.primitives[2].transform.m;
    let (x, y) = (m[3], m[7]);
    assert!((x + 60f32.to_radians().sin()).abs() < 1e-5 && (y - 1.0 - 60f32.to_radians().cos()).abs() < 1e-5);
    // An `angle` directive still sets it.
    let set = lsys("derive 0\nangle 10\naxiom: F + F F\n");
    assert_ne!(dcg(&set, &Instance::new(0)), s);
}

#[test]
fn lsystem_default_materials_are_lpys() {
    let l = lsys("derive 0\nmodule S = sphere(1)\naxiom: S ; S ; S ; ; ; ; S ; S , S [ ;(3) S ] S ;(9) S ,(0) S , S\n");
    assert!(l.lpy_colors);
    let m = |i: usize| LPY_MATERIALS[i];
    // L-Py's turtle starts at material 1 (brown), `;` goes up to 6 at most, `,` down to 0 at least, `;(i)` sets
    // it, an index past the list leaves it unchanged, and `]` restores it.
    assert_eq!(colors(&dcg(&l, &Instance::new(0))), [m(1), m(2), m(3), m(6), m(6), m(5), m(3), m(5), m(5), m(0), m(0)]);
    assert_eq!(m(1), [195.0 / 255.0, 135.0 / 255.0, 45.0 / 255.0], "PlantGL's Color_1: ambient (65,45,15) × 3");
    assert_equivalent("default materials", &l);
    // `'` is the same as `;`; in a recursive grammar, against the reference.
    let l = lsys("derive 5\nangle 30\naxiom: A\nA -> F ; [ + A , F ] ' A , F\nA => , F ; F\n");
    assert_equivalent("default materials, recursive", &l);
    // A file without `;`, `,` or `'` keeps the species' default colour; a `palette` replaces L-Py's materials.
    let plain = lsys("derive 0\naxiom: F\n");
    assert!(!plain.lpy_colors);
    assert_eq!(colors(&dcg(&plain, &Instance::new(0))), [[0.8, 0.8, 0.8]]);
    let own = lsys("derive 0\npalette (1,0,0) (0,1,0)\naxiom: F ; F\n");
    assert!(!own.lpy_colors);
    assert_eq!(colors(&dcg(&own, &Instance::new(0))), [[0.8, 0.8, 0.8], [1.0, 0.0, 0.0]]);
}

#[test]
fn lsystem_python_is_refused_once() {
    let rules = "Axiom: F(R) A\nderivation length: 2\nA --> F(R * 2) A\n";
    let d = one_error(&format!("R = 1.456\n{rules}"), 1, &["Python", "`#define R 1.456` or `param R = 1.456`"]);
    assert_eq!((d.col, d.width), (1, 9));
    // After rules too, and indented; its uses are not reported again.
    one_error(&format!("{rules}  R = 1.456   # radius\n"), 4, &["`R = 1.456` is a Python assignment"]);
    for (python, line) in [
        ("import math\n", 1),
        ("from random import *\n", 1),
        ("def f(x):\n    y = x * 2\n\n    return y\n", 1),
        ("if True:\n  R2 = 1\nelse:\n  R2 = 2\n", 1),
        ("scalars = [('R', 'Float', 1.456, 0, 5, 3),\n           ('S', 'Integer', 1, 0, 5)]\n", 1),
        ("extern(R2 = 1.456)\n", 1),
        ("@decorator\n", 1),
    ] {
        one_error(&format!("#define R 1\n{python}{rules}"), line + 1, &["Python"]);
    }
    // A production with a Python body: one diagnostic, and the module it would rewrite counts as defined.
    let body = "A(x) :\n\tif random() <= 0.5: produce F A(x)\n\telse: produce f A(x)\n";
    one_error(&format!("derive 2\naxiom: A(1) F\n{body}B -> A(2)\n"), 3, &["Python body", "A(x) -> successor : 0.3"]);
    one_error("derive 2\naxiom: I\nI : produce F(2)\n", 3, &["Python body"]);
    // Our own lines are not taken for Python.
    lsys("#define R 1.5\nparam S = 2\nderive 1\naxiom: A(R)\nA(x) : x == S -> F\nA(x) => F(x)\n");
}

// ---------------------------------------------------------------------------------------------------------------
// Error recovery: one typo, one diagnostic, on its line.

/// The library's `.lsys` files and the format doc's example.
fn library() -> Vec<(String, String)> {
    let lsys = canopy_worlds::library::SPECIES.iter().filter(|e| e.file.ends_with(".lsys"));
    let mut out: Vec<(String, String)> = lsys.map(|e| (e.file.to_string(), e.text.to_string())).collect();
    assert!(out.len() >= 2);
    let src = include_str!("../src/lsystem/mod.rs");
    let start = src.find("//! ```text\n").unwrap() + "//! ```text\n".len();
    let end = start + src[start..].find("//! ```\n").unwrap();
    let doc: String =
        src[start..end].lines().map(|l| format!("{}\n", l.trim_start_matches("//!").trim_start())).collect();
    out.push(("format doc example".to_string(), doc));
    out
}

/// Where a line's code ends: before its `#` comment (`#define` is code).
fn code_end(line: &str) -> usize {
    let skip = if line.trim_start().starts_with("#define") { line.find("#define").unwrap() + 1 } else { 0 };
    line[skip..].find('#').map_or(line.trim_end().len(), |i| line[..skip + i].trim_end().len())
}

/// The identifiers of a line's code, with their byte offsets.
fn words(code: &str) -> Vec<(usize, &str)> {
    let mut out = Vec::new();
    let mut i = 0;
    let b = code.as_bytes();
    while i < b.len() {
        let c = b[i] as char;
        if c.is_ascii_alphabetic() || c == '_' {
            let start = i;
            while i < b.len() && ((b[i] as char).is_ascii_alphanumeric() || b[i] == b'_') {
                i += 1;
            }
            out.push((start, &code[start..i]));
        } else if c.is_ascii_digit() || c == '.' {
            // Numbers, with exponents (`2e-3`), are not names.
            while i < b.len() && ((b[i] as char).is_ascii_alphanumeric() || b[i] == b'.') {
                i += 1;
            }
        } else {
            i += 1;
        }
    }
    out
}

/// The names a file declares: parameters (`param`, `#define`, `angle`), modules, and rewritten symbols.
fn declared(text: &str) -> Vec<String> {
    let mut out = vec!["angle".to_string()];
    for line in text.lines() {
        let code = &line[..code_end(line)];
        let w = words(code);
        match w.first().map(|w| w.1) {
            Some("param" | "module" | "define") => out.extend(w.get(1).map(|w| w.1.to_string())),
            Some(first) if code.contains("->") || code.contains("=>") => out.push(first.to_string()),
            _ => {}
        }
    }
    out.sort();
    out.dedup();
    out
}

/// The words that start directives and section headers (a misspelt `#define` is a comment, as in cpfg).
const KEYWORDS: [&str; 13] = [
    "lsystem",
    "derive",
    "angle",
    "width",
    "param",
    "palette",
    "module",
    "axiom",
    "maxdepth",
    "derivation",
    "production",
    "interpretation",
    "homomorphism",
];

/// The first two adjacent different letters of `name` swapped.
fn swapped(name: &str) -> Option<String> {
    let c: Vec<char> = name.chars().collect();
    let i = (0..c.len().saturating_sub(1))
        .find(|&i| c[i] != c[i + 1] && c[i].is_alphabetic() && c[i + 1].is_alphabetic())?;
    let mut s = c.clone();
    s.swap(i, i + 1);
    Some(s.into_iter().collect())
}

/// Every single-typo variant of `text`: (1-based line, 1-based column of the wrong token, what was done, the
/// changed text).
fn typos(text: &str) -> Vec<(usize, usize, String, String)> {
    let names = declared(text);
    let lines: Vec<&str> = text.split('\n').collect();
    let mut out = Vec::new();
    let offset = |n: usize| lines[..n].iter().map(|l| l.len() + 1).sum::<usize>();
    for (n, line) in lines.iter().enumerate() {
        let code = &line[..code_end(line)];
        let w = words(code);
        // The declaration itself is not a reference: the name after `param`/`module`/`#define`, a production's
        // predecessor and its formals (up to the arrow's `:` or `-`).
        let head_end = if code.contains("->") || code.contains("=>") {
            code.find([':', '-', '=']).unwrap_or(0)
        } else if matches!(w.first().map(|w| w.1), Some("param" | "module" | "define")) {
            w.get(1).map_or(0, |w| w.0 + w.1.len())
        } else if w.first().map(|w| w.1) == Some("angle") {
            w[0].0 + "angle".len()
        } else {
            0
        };
        let module_formals = if w.first().map(|w| w.1) == Some("module") { code.find('=').unwrap_or(0) } else { 0 };
        for &(at, word) in &w {
            if at < head_end.max(module_formals) || !names.iter().any(|d| d == word) {
                continue;
            }
            let Some(typo) = swapped(word) else { continue };
            if names.contains(&typo) {
                continue;
            }
            let pos = offset(n) + at;
            let changed = format!("{}{typo}{}", &text[..pos], &text[pos + word.len()..]);
            out.push((n + 1, at + 1, format!("`{word}` → `{typo}`"), changed));
        }
        // A misspelt directive or section header.
        if let Some(&(at, word)) = w.first().filter(|w| KEYWORDS.contains(&w.1) && !code.contains("->"))
            && let Some(typo) = swapped(word)
        {
            let pos = offset(n) + at;
            let changed = format!("{}{typo}{}", &text[..pos], &text[pos + word.len()..]);
            out.push((n + 1, at + 1, format!("keyword `{word}` → `{typo}`"), changed));
        }
        // A trailing `+` (where it is an error: not in a successor).
        if !code.trim().is_empty() {
            let pos = offset(n) + code.len();
            let changed = format!("{} +{}", &text[..pos], &text[pos..]);
            out.push((n + 1, code.len() + 2, "a trailing `+`".to_string(), changed));
        }
    }
    out
}

#[test]
fn lsystem_one_typo_gives_one_diagnostic_on_its_line() {
    let mut failures = Vec::new();
    let (mut misspelt, mut keywords, mut plus_errors) = (0, 0, 0);
    for (name, text) in library() {
        let (l, d) = LSystem::parse(&SourceFile::new(&name, text.as_str()));
        assert!(l.is_some() && d.is_empty(), "{name}: {}", render(&d));
        for (line, col, what, changed) in typos(&text) {
            let (_, d) = LSystem::parse(&SourceFile::new(&name, changed));
            if what.contains("trailing") {
                if d.is_empty() {
                    continue; // a turn at the end of a successor
                }
                plus_errors += 1;
            } else if what.starts_with("keyword") {
                keywords += 1;
            } else {
                misspelt += 1;
            }
            // At the wrong token; for a trailing `+`, at it or at the end of the line after it.
            let at_token =
                d.first().is_some_and(|d| if what.contains("trailing") { d.col >= col } else { d.col == col });
            if d.len() != 1 || d[0].line != line || !at_token {
                failures.push(format!("{name}:{line}:{col}: {what}: {} diagnostic(s)\n{}", d.len(), render(&d)));
            }
        }
    }
    assert!(
        failures.is_empty(),
        "{} typo(s) not reported once on their line:\n{}",
        failures.len(),
        failures.join("\n\n")
    );
    let counts =
        format!("{misspelt} misspelt names, {keywords} misspelt keywords, {plus_errors} erroneous trailing `+`");
    println!("{counts}");
    assert!(misspelt >= 15 && keywords >= 20 && plus_errors >= 25, "{counts}");
}

#[test]
fn lsystem_misspelt_directives_are_named_and_recovered() {
    // The word is wrong, not what follows it; what the directive declares still counts.
    let d = one_error("edrive 3\naxiom: A\nA -> F A\n", 1, &["unknown directive `edrive`: did you mean `derive`?"]);
    assert_eq!((d.col, d.width), (1, 6));
    one_error("derive 1\nparma len = 2\naxiom: F(len)\n", 2, &["did you mean `param`?"]);
    one_error("derive 1\nModule L = sphere(1)\naxiom: L F\n", 2, &["did you mean `module`?"]);
    one_error("derive 1\naxoim: F\n", 2, &["did you mean `axiom`?"]);
    // A misspelt section header still switches the section: `B` keeps its interpretation rule.
    let head = "derive 2\naxiom: A B\nA -> F A\n";
    one_error(&format!("{head}intrepretation:\nB -> F(0.5)\n"), 4, &["did you mean `interpretation:`?"]);
    one_error(&format!("{head}interpretation: +\nB -> F(0.5)\n"), 4, &["expected end of line, found `+`"]);
    let l = lsys(&format!("{head}interpretation:\nB -> F(0.5)\n"));
    assert!(l.symbols[l.symbol("B").unwrap() as usize].interpretation.is_some());
    // A misspelt `endlsystem` still ends the rules: the Python after it is not reported.
    let end = "derive 2\naxiom: A\nA -> F A\nendlsytem\n__lpy_code_version__ = 1.1\ndef f():\n  pass\n";
    one_error(end, 4, &["did you mean `endlsystem`?"]);
    // Productions whose predecessor looks like a directive are productions.
    lsys("derive 2\naxiom: Angle(1) Width\nAngle(x) -> F(x) Angle(x)\nWidth -> f\n");
}

#[test]
fn lsystem_mangled_lpy_never_panics() {
    // The L-Py forms with one character removed, and cut short at every character: diagnostics or an L-system.
    let python = "R = [1,\n  2]\ndef f(x):\n  return x\nA(x) :\n\tproduce F\nAxiom: A(1)\nA(x) --> (0.5) F : *\n";
    let typos = "edrive 2\nintrepretation: +\nendlsytem\n";
    for text in [LPY_FILE, python, typos] {
        for (i, c) in text.char_indices() {
            let removed = format!("{}{}", &text[..i], &text[i + c.len_utf8()..]);
            let _ = parse(&removed);
            let _ = parse(&text[..i]);
        }
    }
}
