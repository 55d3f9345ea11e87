//! L-Py's forms around the L-system: its turtle defaults (the angle, PlantGL's material list), and the lines of an
//! `.lpy` file that are not L-system rules: `endlsystem`, `ignore:`/`consider:`, and Python, which is refused with
//! one diagnostic per statement (its indented body and bracketed continuation lines included).

use std::ops::Range;

use crate::text::{ParseError, is_ident_continue, is_ident_start};

use super::parse::{KEYWORDS, misspelt_directive};

/// The turning angle of `+ - & ^ \ /` without an argument when the file sets no `angle`: L-Py's turtle's
/// `angle_increment` (PlantGL), in degrees.
pub const LPY_DEFAULT_ANGLE: f32 = 60.0;

/// L-Py's default materials (PlantGL's `PglTurtle::defaultValue`), as diffuse colours (ambient × diffuse / 255):
/// 0 grey, 1 brown, 2 green, 3 red, 4 yellow, 5 blue, 6 purple. `;`, `,` and `'` without a `palette` step through
/// them; the turtle starts at [`LPY_START_COLOR`].
pub const LPY_MATERIALS: [[f32; 3]; 7] = [
    [160.0 / 255.0, 160.0 / 255.0, 160.0 / 255.0],
    [195.0 / 255.0, 135.0 / 255.0, 45.0 / 255.0],
    [90.0 / 255.0, 180.0 / 255.0, 30.0 / 255.0],
    [180.0 / 255.0, 0.0, 0.0],
    [180.0 / 255.0, 180.0 / 255.0, 45.0 / 255.0],
    [0.0, 0.0, 180.0 / 255.0],
    [180.0 / 255.0, 0.0, 180.0 / 255.0],
];

/// The material index L-Py's turtle starts at (brown).
pub const LPY_START_COLOR: usize = 1;

/// What an L-Py line that is not an L-system rule is.
pub(super) enum LpyLine {
    /// `endlsystem`: the rules end; the rest of the file is L-Py's Python (usually the editor's
    /// `__initialiseContext__`) and is not read. Misspelt, it still ends the rules, with an error.
    End(Option<ParseError>),
    /// `ignore: …` or `consider: …`: they only change which modules context matching skips, and a DCG matches no
    /// context (context-sensitive productions are refused), so they have no effect. Ends at `end`.
    ContextFilter { end: usize },
    /// A Python statement (with its indented body and bracketed continuation lines, up to `end`): the error, and
    /// the name it would have defined (a value or a module rewritten by a Python production), so that its uses
    /// are not reported again.
    Python { error: ParseError, end: usize, declares: Option<Declared> },
}

/// A name a refused Python statement would have defined.
pub(super) enum Declared {
    /// `R = 1.456`: a value.
    Value(String),
    /// `A(x) :` with a Python body: a production of `A`.
    Module(String),
}

/// Python statement keywords (and L-Py's `produce`, `nproduce`, `extern`) that start a line.
const PYTHON_KEYWORDS: [&str; 27] = [
    "import",
    "from",
    "def",
    "class",
    "if",
    "elif",
    "else",
    "for",
    "while",
    "with",
    "try",
    "except",
    "finally",
    "global",
    "nonlocal",
    "return",
    "print",
    "assert",
    "del",
    "pass",
    "raise",
    "lambda",
    "yield",
    "produce",
    "nproduce",
    "extern",
    "makestring",
];

/// Lines that continue the compound statement before them at the same indentation.
const CONTINUATIONS: [&str; 4] = ["else", "elif", "except", "finally"];

/// Words that start our own lines: directives and section headers are never Python.
const OWN_WORDS: [&str; 9] = [
    "production",
    "productions",
    "interpretation",
    "homomorphism",
    "decomposition",
    "derivation",
    "ignore",
    "consider",
    "endlsystem",
];

/// The line starting at `pos` (up to, not including, its newline) without its `#` comment.
fn code(text: &str, pos: usize) -> (&str, usize) {
    let end = text[pos..].find('\n').map_or(text.len(), |i| pos + i);
    let line = &text[pos..end];
    let line = line.split('#').next().unwrap_or("").trim_end_matches(['\r', ' ', '\t']);
    (line, end)
}

/// The first identifier of `s` after leading blanks, and the rest after it.
fn first_word(s: &str) -> Option<(&str, &str)> {
    let t = s.trim_start_matches([' ', '\t']);
    if !t.starts_with(is_ident_start) {
        return None;
    }
    let len = t.find(|c: char| !is_ident_continue(c)).unwrap_or(t.len());
    Some((&t[..len], &t[len..]))
}

fn indent(line: &str) -> usize {
    line.len() - line.trim_start_matches([' ', '\t']).len()
}

/// Classify the line at `pos` if it is one of L-Py's non-rule lines (see [`LpyLine`]).
pub(super) fn classify(text: &str, pos: usize) -> Option<LpyLine> {
    let (line, end) = code(text, pos);
    let start = pos + indent(line);
    let span = start..pos + line.len();
    let statement = line.trim();
    if statement.starts_with('@') {
        return Some(python(text, pos, span, python_message(statement), None));
    }
    let (word, after) = first_word(line)?;
    if after.trim().is_empty() && (word == "endlsystem" || misspelt_directive(word) == Some("endlsystem")) {
        let error = (word != "endlsystem").then(|| {
            let at = pos + indent(line);
            ParseError::new(at..at + word.len(), format!("unknown directive `{word}`: did you mean `endlsystem`?"))
        });
        return Some(LpyLine::End(error));
    }
    if (word == "ignore" || word == "consider") && after.trim_start().starts_with(':') {
        return Some(LpyLine::ContextFilter { end });
    }
    if KEYWORDS.contains(&word) || OWN_WORDS.contains(&word) || misspelt_directive(word).is_some() {
        return None;
    }
    let arrow = line.contains("->") || line.contains("=>");
    if PYTHON_KEYWORDS.contains(&word) && !arrow {
        return Some(python(text, pos, span, python_message(statement), None));
    }
    if let Some((targets, value)) = assignment(line) {
        let name = targets.trim();
        let value = value.trim();
        let simple = name.chars().all(is_ident_continue);
        let shown = if value.is_empty() || value.len() > 40 { "value" } else { value };
        let how = if simple {
            format!("`#define {name} {shown}` or `param {name} = {shown}`")
        } else {
            "`#define NAME value` or `param NAME = value`".to_string()
        };
        let message = format!(
            "`{}` is a Python assignment, and Canopy does not run Python (L-Py runs the lines outside its rules as \
             Python): set the value with {how}",
            short(statement)
        );
        let declares = simple.then(|| Declared::Value(name.to_string()));
        return Some(python(text, pos, span, message, declares));
    }
    // `A(x) :` followed by a Python body (on the next, indented lines, or `produce …` on this one).
    let rest = after.trim_start();
    let rest = if rest.starts_with('(') { skip_parens(rest)? } else { rest };
    let body = rest.trim_start().strip_prefix(':')?.trim_start();
    let python_body = body.is_empty() || first_word(body).is_some_and(|(w, _)| PYTHON_KEYWORDS.contains(&w));
    if !python_body || body.contains("->") || body.contains("=>") {
        return None;
    }
    let message = format!(
        "`{}` starts an L-Py production with a Python body, and Canopy does not run Python: write it as \
         productions `{word}(x) : condition -> successor`; a random choice is several productions of `{word}` with \
         probabilities (`{word}(x) -> successor : 0.3`)",
        short(statement)
    );
    Some(python(text, pos, span, message, Some(Declared::Module(word.to_string()))))
}

/// The message for a Python statement other than an assignment.
fn python_message(statement: &str) -> String {
    format!(
        "`{}` is Python, and Canopy does not run Python (L-Py runs the lines outside its rules as Python): set a \
         value with `#define NAME value` or `param NAME = value`, and write what a function computes as an \
         expression where it is used",
        short(statement)
    )
}

/// `statement` cut to a readable length for a message.
fn short(statement: &str) -> String {
    match statement.char_indices().nth(48) {
        Some((i, _)) => format!("{}…", &statement[..i]),
        None => statement.to_string(),
    }
}

/// After a balanced `( … )` at the start of `s`.
fn skip_parens(s: &str) -> Option<&str> {
    let mut depth = 0usize;
    for (i, c) in s.char_indices() {
        match c {
            '(' => depth += 1,
            ')' => {
                depth = depth.checked_sub(1)?;
                if depth == 0 {
                    return Some(&s[i + 1..]);
                }
            }
            _ => {}
        }
    }
    None
}

/// `targets = value` (or `+=`, `-=`, `*=`, `/=`) where the targets are names (`a`, `a.b`, `a, b`): a Python
/// assignment. Not `==`, and not `=>` (a terminal production).
fn assignment(line: &str) -> Option<(&str, &str)> {
    let t = line.trim_start();
    let mut i = 0;
    let bytes = t.as_bytes();
    loop {
        if !t[i..].starts_with(is_ident_start) {
            return None;
        }
        i += t[i..].find(|c: char| !is_ident_continue(c) && c != '.').unwrap_or(t.len() - i);
        let rest = t[i..].trim_start_matches([' ', '\t']);
        i = t.len() - rest.len();
        if rest.starts_with(',') {
            i += 1;
            i += t[i..].len() - t[i..].trim_start_matches([' ', '\t']).len();
            continue;
        }
        break;
    }
    let targets = &t[..i];
    let op = if bytes.get(i) == Some(&b'=') {
        1
    } else if matches!(bytes.get(i), Some(b'+' | b'-' | b'*' | b'/')) && bytes.get(i + 1) == Some(&b'=') {
        2
    } else {
        return None;
    };
    if op == 1 && matches!(bytes.get(i + 1), Some(b'=' | b'>')) {
        return None;
    }
    Some((targets, &t[i + op..]))
}

/// A refused Python statement starting at `pos`: it runs on while brackets are open, and a statement whose line
/// ends with `:` takes the following blank and more indented lines, and `else:`/`elif`/`except`/`finally` at its
/// own indentation.
fn python(text: &str, pos: usize, span: Range<usize>, message: String, declares: Option<Declared>) -> LpyLine {
    let (first, mut end) = code(text, pos);
    let base = indent(first);
    let mut open = brackets(first);
    let mut compound = first.trim_end().ends_with(':');
    let mut body_end = end;
    while end < text.len() {
        let next = end + 1;
        let (line, line_end) = code(text, next);
        if open > 0 {
            open += brackets(line);
            end = line_end;
            body_end = end;
            continue;
        }
        if line.trim().is_empty() {
            // Blank lines belong to the block only if it goes on after them.
            end = line_end;
            continue;
        }
        let more_indented = indent(line) > base;
        let continues = indent(line) == base && first_word(line).is_some_and(|(w, _)| CONTINUATIONS.contains(&w));
        if compound && more_indented || continues {
            open = brackets(line);
            compound = compound || line.trim_end().ends_with(':');
            end = line_end;
            body_end = end;
            continue;
        }
        break;
    }
    LpyLine::Python { error: ParseError::new(span, message), end: body_end, declares }
}

/// Open brackets minus closed ones on a line (strings are not looked into; a rough count is enough to find the
/// end of a statement).
fn brackets(line: &str) -> isize {
    line.chars().fold(0, |n, c| match c {
        '(' | '[' | '{' => n + 1,
        ')' | ']' | '}' => n - 1,
        _ => n,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn python_end(text: &str) -> usize {
        match classify(text, 0) {
            Some(LpyLine::Python { end, .. }) => end,
            _ => panic!("not Python: {text:?}"),
        }
    }

    #[test]
    fn python_statements_are_recognised_with_their_bodies() {
        assert_eq!(python_end("R = 1.456\nAxiom: A\n"), 9);
        assert_eq!(python_end("def f(x):\n    y = 2\n\n    return y\nAxiom: A\n"), 33);
        assert_eq!(python_end("if a:\n  b = 1\nelse:\n  b = 2\nAxiom: A\n"), 27);
        assert_eq!(python_end("s = [1,\n 2]\nA -> F\n"), 11);
        assert_eq!(python_end("A(x) :\n\tproduce B\n\n# end\nB -> F\n"), 17);
        assert_eq!(python_end("from random import *\n  x\n"), 20);
        for not_python in
            ["A => F", "A -> F", "A(x) : x > 1 -> F", "param a = 1", "production:", "#define R 1", "A == B", "Axiom: A"]
        {
            assert!(!matches!(classify(not_python, 0), Some(LpyLine::Python { .. })), "{not_python}");
        }
        assert!(matches!(classify("endlsystem  # done", 0), Some(LpyLine::End(None))));
        assert!(matches!(classify("endlsytem", 0), Some(LpyLine::End(Some(_)))));
        assert!(matches!(classify("ignore: +-/", 0), Some(LpyLine::ContextFilter { end: 11 })));
        assert!(matches!(classify("a, b = 1, 2", 0), Some(LpyLine::Python { declares: None, .. })));
        assert!(matches!(classify("x += 1", 0), Some(LpyLine::Python { declares: Some(Declared::Value(_)), .. })));
    }
}
