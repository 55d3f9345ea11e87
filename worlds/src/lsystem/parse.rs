//! Pass 1 of the `.lsys` parser: each line on its own into an [`Item`] (directive, module, axiom or production),
//! so one bad line does not hide the others.

use std::ops::Range;

use crate::expr::{Ast, parse_expr};
use crate::nodes::parse_args;
use crate::text::{Cursor, ParseError, is_ident_start};

use super::{MAX_BRACKET_NESTING, MAX_FORMALS, MAX_IDENT_LEN, MAX_PALETTE, MAX_SUCCESSOR_LEN};

/// The section a line belongs to: L-Py's `production:`, `interpretation:` (`homomorphism:`) and
/// `decomposition:` headers switch between them.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Section {
    /// Productions applied in the derivation (the default).
    Productions,
    /// Interpretation rules, applied only when the final string is drawn.
    Interpretation,
    /// Decomposition rules: not supported (an error at the header); the section's lines are skipped.
    Decomposition,
}

pub(super) struct RawSucc {
    pub(super) name: String,
    pub(super) span: Range<usize>,
    pub(super) args: Option<(Vec<Ast>, Range<usize>)>,
}

pub(super) struct Production {
    pub(super) pred: String,
    pub(super) pred_span: Range<usize>,
    pub(super) formals: Vec<(String, Range<usize>)>,
    pub(super) cond: Option<Ast>,
    pub(super) terminal: bool,
    pub(super) succ: Vec<RawSucc>,
    pub(super) weight: Option<Ast>,
}

pub(super) enum Item {
    Name(String, Range<usize>),
    Derive(Ast, Range<usize>),
    Width(Ast, Range<usize>),
    Param(String, Range<usize>, Ast),
    Palette(Vec<[Ast; 3]>, Range<usize>),
    Module {
        name: String,
        span: Range<usize>,
        formals: Vec<(String, Range<usize>)>,
        body: usize,
    },
    Axiom(Vec<RawSucc>, Range<usize>),
    Production(Production),
    /// A production in an `interpretation:` section (turned from [`Item::Production`] by the line loop).
    Interpretation(Production),
    Section(Section, Range<usize>),
    MaxDepth(Ast, Range<usize>),
}

pub(super) const KEYWORDS: [&str; 10] =
    ["lsystem", "derive", "angle", "width", "param", "palette", "module", "axiom", "Axiom", "maxdepth"];
pub(super) const RESERVED: [&str; 4] = ["detail", "pi", "true", "false"];
const TURTLE_CHARS: &str = "+-&^\\/|!'[]%$;,";

pub(super) fn at_line_end(cur: &mut Cursor<'_>) -> bool {
    matches!(cur.peek(), None | Some('\n'))
}

fn end_of_line(cur: &mut Cursor<'_>) -> Result<(), ParseError> {
    if at_line_end(cur) { Ok(()) } else { Err(cur.unexpected("end of line")) }
}

fn name(cur: &mut Cursor<'_>, what: &str) -> Result<(String, Range<usize>), ParseError> {
    let Some((n, span)) = cur.ident() else {
        return Err(cur.unexpected(what));
    };
    if n.len() > MAX_IDENT_LEN {
        return Err(ParseError::new(span, format!("name of {} bytes (at most {MAX_IDENT_LEN})", n.len())));
    }
    Ok((n.to_string(), span))
}

fn formal_list(cur: &mut Cursor<'_>) -> Result<Vec<(String, Range<usize>)>, ParseError> {
    let mut out: Vec<(String, Range<usize>)> = Vec::new();
    cur.expect("(")?;
    if cur.eat(")") {
        return Ok(out);
    }
    loop {
        let (n, span) = name(cur, "a parameter name")?;
        if RESERVED.contains(&n.as_str()) {
            return Err(ParseError::new(span, format!("`{n}` is reserved and cannot be a parameter name")));
        }
        if out.iter().any(|(m, _)| *m == n) {
            return Err(ParseError::new(span, format!("parameter `{n}` appears twice")));
        }
        if out.len() == MAX_FORMALS {
            return Err(ParseError::new(span, format!("more than {MAX_FORMALS} parameters")));
        }
        out.push((n, span));
        if cur.eat(")") {
            return Ok(out);
        }
        cur.expect(",")?;
    }
}

fn successors(cur: &mut Cursor<'_>) -> Result<Vec<RawSucc>, ParseError> {
    let mut out = Vec::new();
    let mut open: Vec<Range<usize>> = Vec::new();
    loop {
        cur.skip_trivia();
        let start = cur.pos;
        let Some(c) = cur.rest().chars().next() else { break };
        if c == '\n' || c == ':' {
            break;
        }
        let name = if is_ident_start(c) {
            let (n, _) = cur.ident().expect("an identifier starts here");
            n.to_string()
        } else if TURTLE_CHARS.contains(c) {
            cur.pos += c.len_utf8();
            c.to_string()
        } else {
            return Err(cur.unexpected("a module (a name or one of `+ - & ^ \\ / | ! ' ; , $ % [ ]`)"));
        };
        let span = start..cur.pos;
        if out.len() == MAX_SUCCESSOR_LEN {
            return Err(ParseError::new(span, format!("a successor has at most {MAX_SUCCESSOR_LEN} modules")));
        }
        if name == "[" {
            if open.len() == MAX_BRACKET_NESTING {
                return Err(ParseError::new(span, format!("brackets nested deeper than {MAX_BRACKET_NESTING}")));
            }
            open.push(span.clone());
        } else if name == "]" && open.pop().is_none() {
            return Err(ParseError::new(span, "unmatched `]`"));
        }
        let args = if cur.peek() == Some('(') { Some(parse_args(cur)?) } else { None };
        out.push(RawSucc { name, span, args });
    }
    if let Some(span) = open.pop() {
        return Err(ParseError::new(span, "unclosed `[`"));
    }
    Ok(out)
}

fn production(pred: &str, pred_span: Range<usize>, cur: &mut Cursor<'_>) -> Result<Item, ParseError> {
    if pred == "F" || pred == "f" {
        return Err(ParseError::new(
            pred_span,
            format!("`{pred}` is a turtle symbol and cannot be rewritten; rewrite a non-terminal that produces it"),
        ));
    }
    if pred.len() > MAX_IDENT_LEN {
        return Err(ParseError::new(pred_span, format!("name of {} bytes (at most {MAX_IDENT_LEN})", pred.len())));
    }
    let formals = if cur.peek() == Some('(') {
        let open = cur.pos;
        cur.pos += 1;
        if cur.peek().is_some_and(|c| c.is_ascii_digit() || c == '.') {
            return Err(cur.unexpected(
                "a parameter name (a probability goes on the arrow, `A --> (0.3) B`, or after the successor, \
                 `A --> B : 0.3`)",
            ));
        }
        cur.pos = open;
        formal_list(cur)?
    } else {
        Vec::new()
    };
    if let Some(c @ ('<' | '>')) = cur.peek() {
        let at = cur.pos..cur.pos + 1;
        let side = if c == '<' { "left" } else { "right" };
        return Err(ParseError::new(
            at,
            format!(
                "context-sensitive productions are not supported (`{c}` gives a {side} context): a species DCG \
                 rewrites each module on its own, and its traversal sees no neighbours (seed 001 §3.2 compiles \
                 context-free L-systems); pass what the context would tell as a parameter instead"
            ),
        ));
    }
    // `: *` is the condition "always" (ABOP's and cpfg's `*`): the same as none.
    let cond = if cur.eat(":") && !cur.eat("*") { Some(parse_expr(cur)?) } else { None };
    cur.skip_trivia();
    let arrow = cur.pos..cur.pos + 2;
    // `-->` is L-Py's spelling of `->`.
    let terminal = if cur.eat("-->") || cur.eat("->") {
        false
    } else if cur.eat("=>") {
        true
    } else {
        return Err(cur.unexpected("`->` or `=>`"));
    };
    if terminal && cond.is_some() {
        return Err(ParseError::new(arrow, "a terminal production (`=>`) takes no condition"));
    }
    // `(p)` on the arrow: the probability where ABOP writes it (a successor cannot start with `(`).
    let mut weight = None;
    if cur.peek() == Some('(') {
        let open = cur.pos;
        cur.pos += 1;
        let p = parse_expr(cur)?;
        cur.expect(")")?;
        if terminal {
            return Err(ParseError::new(open..cur.pos, "a terminal production (`=>`) takes no probability"));
        }
        weight = Some(p);
    }
    let succ = successors(cur)?;
    cur.skip_trivia();
    let colon = cur.pos..cur.pos + 1;
    if cur.eat(":") {
        if terminal {
            return Err(ParseError::new(colon, "a terminal production (`=>`) takes no probability"));
        }
        if weight.is_some() {
            return Err(ParseError::new(colon, "the probability is given twice: on the arrow and after the successor"));
        }
        weight = Some(parse_expr(cur)?);
    }
    Ok(Item::Production(Production { pred: pred.to_string(), pred_span, formals, cond, terminal, succ, weight }))
}

/// `#define NAME value` (cpfg's C preprocessor constants): the position after `#define` if the line starts with it.
fn define(cur: &Cursor<'_>) -> Option<usize> {
    let rest = cur.rest();
    let trimmed = rest.trim_start_matches([' ', '\t']);
    let after = trimmed.strip_prefix("#define")?;
    after.starts_with([' ', '\t']).then(|| cur.pos + (rest.len() - after.len()))
}

/// The section a header word names.
fn section_kind(word: &str) -> Option<Section> {
    Some(match word {
        "production" | "productions" => Section::Productions,
        "interpretation" | "homomorphism" => Section::Interpretation,
        "decomposition" => Section::Decomposition,
        _ => return None,
    })
}

/// A section header (`interpretation:` …) if the line is one; one with more after its `:` (and no arrow, which
/// would make it a production) is an error at what follows.
fn section(word: &str, span: &Range<usize>, cur: &mut Cursor<'_>) -> Option<Result<Item, ParseError>> {
    let kind = section_kind(word)?;
    let save = cur.pos;
    if cur.eat(":") {
        if at_line_end(cur) {
            return Some(Ok(Item::Section(kind, span.start..cur.pos)));
        }
        let line = cur.rest().split('\n').next().unwrap_or("");
        if !line.contains("->") && !line.contains("=>") {
            return Some(Err(cur.unexpected("end of line")));
        }
    }
    cur.pos = save;
    None
}

/// The words that start directives and section headers: what a misspelt first word is checked against.
const DIRECTIVES: [&str; 18] = [
    "lsystem",
    "derive",
    "derivation",
    "angle",
    "width",
    "param",
    "palette",
    "module",
    "axiom",
    "maxdepth",
    "production",
    "productions",
    "interpretation",
    "homomorphism",
    "decomposition",
    "endlsystem",
    "ignore",
    "consider",
];

/// The directive or section header `word` misspells: one edit away from it (a letter changed, added or dropped,
/// two neighbours swapped, or only the case differing), ignoring case; not for words shorter than 4 letters.
pub(super) fn misspelt_directive(word: &str) -> Option<&'static str> {
    let w: Vec<char> = word.to_lowercase().chars().collect();
    if w.len() < 4 || DIRECTIVES.contains(&word) || word == "Axiom" {
        return None;
    }
    DIRECTIVES.into_iter().find(|d| {
        let d: Vec<char> = d.chars().collect();
        edit_distance(&w, &d) <= 1
    })
}

/// The optimal-string-alignment distance: insertions, deletions, substitutions and swaps of neighbours.
fn edit_distance(a: &[char], b: &[char]) -> usize {
    let mut d = vec![vec![0usize; b.len() + 1]; a.len() + 1];
    for (i, row) in d.iter_mut().enumerate() {
        row[0] = i;
    }
    d[0] = (0..=b.len()).collect();
    for i in 1..=a.len() {
        for j in 1..=b.len() {
            let cost = usize::from(a[i - 1] != b[j - 1]);
            let mut v = (d[i - 1][j] + 1).min(d[i][j - 1] + 1).min(d[i - 1][j - 1] + cost);
            if i > 1 && j > 1 && a[i - 1] == b[j - 2] && a[i - 2] == b[j - 1] {
                v = v.min(d[i - 2][j - 2] + 1);
            }
            d[i][j] = v;
        }
    }
    d[a.len()][b.len()]
}

pub(super) fn parse_line(cur: &mut Cursor<'_>) -> Result<Option<Item>, ParseError> {
    if let Some(pos) = define(cur) {
        cur.pos = pos;
        let (n, s) = name(cur, "a constant name")?;
        let item = Item::Param(n, s, parse_expr(cur)?);
        end_of_line(cur)?;
        return Ok(Some(item));
    }
    if at_line_end(cur) {
        return Ok(None);
    }
    let Some((word, span)) = cur.ident() else {
        return Err(cur.unexpected("a directive (`lsystem`, `derive`, `angle`, `width`, `param`, `palette`, `module`, `axiom:`) or a production `A(x) -> …`"));
    };
    if let Some(item) = section(word, &span, cur) {
        return item.map(Some);
    }
    // A misspelt directive: the word is wrong, not what follows it (a production line has an arrow).
    if let Some(meant) = misspelt_directive(word) {
        let line = cur.rest().split('\n').next().unwrap_or("");
        if !line.contains("->") && !line.contains("=>") {
            let shown = if section_kind(meant).is_some() { format!("{meant}:") } else { meant.to_string() };
            return Err(ParseError::new(span, format!("unknown directive `{word}`: did you mean `{shown}`?")));
        }
    }
    let item = match word {
        "lsystem" => {
            let (n, s) = name(cur, "a name")?;
            Item::Name(n, s)
        }
        "derive" => Item::Derive(parse_expr(cur)?, span),
        // L-Py's `derivation length: N`.
        "derivation" if cur.eat_keyword("length") => {
            cur.expect(":")?;
            Item::Derive(parse_expr(cur)?, span)
        }
        "maxdepth" => Item::MaxDepth(parse_expr(cur)?, span),
        "width" => Item::Width(parse_expr(cur)?, span),
        "angle" => Item::Param("angle".to_string(), span, parse_expr(cur)?),
        "param" => {
            let (n, s) = name(cur, "a parameter name")?;
            cur.expect("=")?;
            Item::Param(n, s, parse_expr(cur)?)
        }
        "palette" => {
            let mut entries = Vec::new();
            while !at_line_end(cur) {
                let (mut args, s) = parse_args(cur)?;
                if args.len() != 3 {
                    return Err(ParseError::new(s, format!("a palette colour has 3 components, got {}", args.len())));
                }
                if entries.len() == MAX_PALETTE {
                    return Err(ParseError::new(s, format!("a palette has at most {MAX_PALETTE} colours")));
                }
                let b = args.pop().expect("3 args");
                let g = args.pop().expect("3 args");
                let r = args.pop().expect("3 args");
                entries.push([r, g, b]);
            }
            if entries.is_empty() {
                return Err(cur.unexpected("a colour `(r, g, b)`"));
            }
            Item::Palette(entries, span)
        }
        "module" => {
            let (n, s) = name(cur, "a module name")?;
            let formals = if cur.peek() == Some('(') { formal_list(cur)? } else { Vec::new() };
            cur.expect("=")?;
            let body = cur.pos;
            if at_line_end(cur) {
                return Err(cur.unexpected("a node call such as `cylinder(r, h)`"));
            }
            // The body is compiled in pass 2, once every parameter slot is known.
            cur.pos += cur.rest().find('\n').unwrap_or(cur.rest().len());
            Item::Module { name: n, span: s, formals, body }
        }
        // `Axiom:` is L-Py's spelling.
        "axiom" | "Axiom" => {
            cur.expect(":")?;
            Item::Axiom(successors(cur)?, span)
        }
        _ => production(word, span, cur)?,
    };
    end_of_line(cur)?;
    Ok(Some(item))
}

/// What a line that failed to parse still declares, so its names do not cause follow-up errors.
pub(super) enum Ghost {
    Symbol(String),
    Param(String),
    Directive(&'static str),
    /// A section header: the lines after it are in that section.
    Section(Section),
}

pub(super) fn ghost(src: &str, pos: usize) -> Option<Ghost> {
    let mut cur = Cursor { src, pos, newlines_are_space: false };
    if let Some(p) = define(&cur) {
        cur.pos = p;
        return Some(Ghost::Param(cur.ident()?.0.to_string()));
    }
    let (word, _) = cur.ident()?;
    // A misspelt directive declares what the directive would have (unless the line is a production).
    let line = cur.rest().split('\n').next().unwrap_or("");
    let arrow = line.contains("->") || line.contains("=>");
    let word = misspelt_directive(word).filter(|_| !arrow).unwrap_or(word);
    if let Some(kind) = section_kind(word).filter(|_| line.trim_start().starts_with(':') && !arrow) {
        return Some(Ghost::Section(kind));
    }
    Some(match word {
        "module" => Ghost::Symbol(cur.ident()?.0.to_string()),
        "param" => Ghost::Param(cur.ident()?.0.to_string()),
        "angle" => Ghost::Param("angle".to_string()),
        w => match KEYWORDS.iter().find(|&&k| k == w) {
            Some(&"Axiom") => Ghost::Directive("axiom"),
            Some(k) => Ghost::Directive(k),
            None if w == "derivation" => Ghost::Directive("derive"),
            None => Ghost::Symbol(w.to_string()),
        },
    })
}
