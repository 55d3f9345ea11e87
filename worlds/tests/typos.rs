//! One diagnostic per mistake (issue 35): every single typo in a library `.species` file — a name misspelt where it
//! is used, a keyword or node misspelt, a line cut off after a trailing `+` — gives exactly one diagnostic, on the
//! typo's line.

use canopy_worlds::diag::{Diagnostic, SourceFile};
use canopy_worlds::library::SPECIES;
use canopy_worlds::species_text::parse_species;

/// The code of a line (before its `#` comment) and its identifier tokens as byte ranges within the line.
fn idents(line: &str) -> Vec<std::ops::Range<usize>> {
    let code = &line[..line.find('#').unwrap_or(line.len())];
    let b = code.as_bytes();
    let mut out = Vec::new();
    let mut i = 0;
    while i < b.len() {
        if b[i].is_ascii_alphabetic() || b[i] == b'_' {
            let s = i;
            while i < b.len() && (b[i].is_ascii_alphanumeric() || b[i] == b'_') {
                i += 1;
            }
            out.push(s..i);
        } else if b[i].is_ascii_digit() || b[i] == b'.' {
            // A number, exponent included (`2e3` holds no name).
            while i < b.len() && (b[i].is_ascii_alphanumeric() || b[i] == b'.') {
                i += 1;
            }
        } else {
            i += 1;
        }
    }
    out
}

/// The word with its first two differing neighbours swapped (one letter more when it has none to swap).
fn misspell(word: &str) -> String {
    let c: Vec<char> = word.chars().collect();
    // Never a digit first: that would read as a number and a name, two mistakes.
    let swappable = |i: usize| c[i] != c[i + 1] && (i > 0 || !c[1].is_ascii_digit());
    match (0..c.len().saturating_sub(1)).find(|&i| swappable(i)) {
        Some(i) => {
            let mut c = c;
            c.swap(i, i + 1);
            c.into_iter().collect()
        }
        None => format!("{word}q"),
    }
}

fn parse(name: &str, text: &str) -> Vec<Diagnostic> {
    parse_species(&SourceFile::new(name, text)).1
}

fn show(d: &[Diagnostic]) -> String {
    d.iter().map(|d| d.to_string()).collect::<Vec<_>>().join("\n")
}

/// Every library `.species` file with each line changed by `change` (the line's text, its identifier tokens) into
/// zero or more variants: each variant must give exactly one diagnostic, on that line.
/// `change` also gets every word of the file (a typo that makes another of them is no mistake a parser can see).
fn each_variant(change: impl Fn(&str, &[std::ops::Range<usize>], &[&str]) -> Vec<String>) -> usize {
    let mut tried = 0;
    // The library's species files, and the one species file of `worlds/species/` it does not embed.
    let library = SPECIES.iter().filter(|e| e.file.ends_with(".species")).map(|e| (e.file, e.text));
    for (file, text) in library.chain([("fig.species", include_str!("../species/fig.species"))]) {
        assert!(parse(file, text).is_empty(), "{file} parses");
        let lines: Vec<&str> = text.lines().collect();
        let words: Vec<&str> = lines.iter().flat_map(|l| idents(l).into_iter().map(move |r| &l[r])).collect();
        for (n, line) in lines.iter().enumerate() {
            for variant in change(line, &idents(line), &words) {
                let mut changed: Vec<&str> = lines.clone();
                changed[n] = &variant;
                let d = parse(file, &(changed.join("\n") + "\n"));
                assert!(
                    d.len() == 1 && d[0].line == n + 1,
                    "{}:{}: `{}` gave {} diagnostic(s):\n{}",
                    file,
                    n + 1,
                    variant.trim(),
                    d.len(),
                    show(&d)
                );
                tried += 1;
            }
        }
    }
    tried
}

#[test]
fn a_misspelt_word_is_one_diagnostic_on_its_line() {
    // Names that declare (after `param`, `state`, `def`, `species`) are left alone: misspelling one makes its uses
    // elsewhere the mistake (tested below), not its line.
    let tried = each_variant(|line, idents, words| {
        let mut out = Vec::new();
        for (i, r) in idents.iter().enumerate() {
            if i > 0 && matches!(&line[idents[i - 1].clone()], "param" | "state" | "let" | "def" | "species") {
                continue;
            }
            let wrong = misspell(&line[r.clone()]);
            if words.contains(&wrong.as_str()) {
                continue;
            }
            out.push(format!("{}{wrong}{}", &line[..r.start], &line[r.end..]));
        }
        out
    });
    assert!(tried > 500, "only {tried} typos tried");
}

#[test]
fn a_line_cut_off_after_an_operator_is_reported_on_that_line() {
    let tried = each_variant(|line, _, _| {
        let code = line[..line.find('#').unwrap_or(line.len())].trim_end();
        if code.trim().is_empty() { vec![] } else { vec![format!("{code} +")] }
    });
    assert!(tried > 200, "only {tried} lines tried");
}

#[test]
fn the_reported_typo_gives_one_diagnostic_with_a_suggestion() {
    let text = SPECIES.iter().find(|e| e.file == "monopodial.species").expect("in the library").text;
    let line = text.lines().position(|l| l.starts_with("let r = height")).expect("r's declaration");
    let typo: Vec<String> = text
        .lines()
        .enumerate()
        .map(|(i, l)| if i == line { l.replacen("height", "heigth", 1) } else { l.to_string() })
        .collect();
    let d = parse("m.species", &typo.join("\n"));
    assert_eq!(d.len(), 1, "{}", show(&d));
    assert_eq!((d[0].line, d[0].col), (line + 1, 9));
    assert_eq!(d[0].message, "unknown parameter `heigth`; did you mean `height`?");
}

#[test]
fn a_misspelt_declaration_is_one_diagnostic_at_the_first_use() {
    let d = parse("t.species", "param heigth = 2\ncone(height, 1, height)\nsphere(height)\n");
    assert_eq!(d.len(), 1, "{}", show(&d));
    assert_eq!((d[0].line, d[0].col), (2, 6));
    assert_eq!(d[0].message, "unknown parameter `height`; did you mean `heigth`? (2 more use(s))");
    let d = parse("t.species", "sphere(r)\nparam r = 1\n");
    assert_eq!(d.len(), 1, "{}", show(&d));
    assert_eq!(d[0].message, "parameter `r` is used before its declaration at 2:7");
    let d = parse("t.species", "def Lef sphere(1)\nuse Leaf\nuse Leaf\n");
    assert_eq!(d.len(), 1, "{}", show(&d));
    assert_eq!(d[0].message, "`use Leaf` names no `def`; did you mean `Lef`? (1 more use(s))");
}

/// A file that is not in the format at all gets at most 20 diagnostics and a count of the rest, in both formats.
#[test]
fn a_file_full_of_mistakes_is_capped_with_a_count() {
    use canopy_worlds::diag::MAX_DIAGNOSTICS;
    use canopy_worlds::load::parse_source;
    let files =
        [("many.species", String::new(), "frobnicate(1)\n"), ("many.lsys", "derive 1\naxiom: A\n".into(), "A -> B(\n")];
    for (name, head, line) in files {
        let (g, d) = parse_source(&SourceFile::new(name, head + &line.repeat(30)));
        assert!(g.is_none());
        assert_eq!(d.len(), MAX_DIAGNOSTICS + 1, "{name}: {}", show(&d));
        assert!(d[MAX_DIAGNOSTICS].message.starts_with("and 10 more"), "{name}: {}", show(&d));
    }
}
