//! The species text format (`.species`), in the spirit of seed 001 §6's RECURSIV files: parameters, then a node
//! tree in which `def NAME` names a node and `use NAME` links to it again — from anywhere, so a link back to an
//! enclosing node is a cycle.
//!
//! ```text
//! species Worm                      # optional; defaults to the file name
//! param c = 4                       # a Local parameter and its default (may draw: uniform(3, 5))
//! state w = 0.1                     # a Turtle-scope parameter (flows across recursion separators)
//! let r = c * 0.1                   # a working value: evaluated like a parameter, never set from outside
//! def Worm select(c > 0) {          # traverses child `c > 0` (0 or 1)
//!   cone(0.5, 0, 1)                 # child 0: terminal
//!   separator {                     # child 1: recursive branch
//!     sphere(0.5)
//!     translate(1, 0, 0)
//!     calc { c = c - 1 }
//!     recurse { use Worm }          # RecursionSeparator around the cycle
//!   }
//! }
//! ```
//! Containers: `group`, `separator`, `recurse`, `select(expr)`, `lod` take `{ nodes }`; `defs { … }` holds
//! named nodes that are only reached through `use`; `calc { a = e, b = e }`
//! assigns simultaneously; the transformation, material and primitive calls are those of [`crate::nodes`].
//! The top-level nodes form the root group. Parameters must be declared before the nodes that use them. A species'
//! *parameters* (`param`, `state`) are what an instance, a world or an edit may set; its *working values* (`let`,
//! `let state`: counters, radii carried down a branch) are its program's own ([`canopy_protocol::ParamRole`]). An
//! expression ends with its line (a node call's arguments may span lines).
//!
//! Errors recover (rust-analyzer's "parsing never fails"): one diagnostic per mistake. A name used but not declared
//! is reported once, at its first use, with a near name if the file has one; a misspelt keyword or node is read as
//! the word it is nearest to; a construct cut off at the end of its line is reported there; a broken construct is
//! skipped to the end of its line and of the blocks it opened, and a `def` inside it is not missed again by its uses.

use std::collections::BTreeMap;
use std::ops::Range;

use canopy_protocol::{Node, NodeId, ParamDecl, ParamRole, ParamScope, SpeciesGraph, limits};

use crate::diag::{Diagnostic, SourceFile, did_you_mean};
use crate::expr::{compile, parse_expr};
use crate::nodes::parse_node_call;
use crate::text::{Cursor, ParseError};

/// Deepest nesting of `{ }` blocks accepted.
pub const MAX_BLOCK_NESTING: usize = 256;

/// Parse a species text file. Returns the graph if there were no errors, and the diagnostics found (at most
/// [`crate::diag::MAX_DIAGNOSTICS`], then one with a count of the rest): one per mistake (a name that is not known is reported once, at its first use, with how many more uses it has; a
/// construct cut off at the end of its line is reported there, not at the next line's first token).
pub fn parse_species(src: &SourceFile) -> (Option<SpeciesGraph>, Vec<Diagnostic>) {
    let mut p = Parser {
        cur: Cursor::new(&src.text, true),
        params: Vec::new(),
        param_spans: Vec::new(),
        nodes: Vec::new(),
        defs: BTreeMap::new(),
        uses: Vec::new(),
        errors: Vec::new(),
        unknown: Vec::new(),
        broken_defs: Vec::new(),
        name: None,
    };
    let root_children = p.node_list(0, true);
    p.finish(src, root_children)
}

struct Use {
    node: usize,
    index: usize,
    name: String,
    span: Range<usize>,
}

/// A name used but not declared: where first, and how many uses in all.
struct Unknown {
    name: String,
    span: Range<usize>,
    uses: usize,
}

struct Parser<'a> {
    cur: Cursor<'a>,
    params: Vec<ParamDecl>,
    /// Where each parameter is declared.
    param_spans: Vec<Range<usize>>,
    nodes: Vec<Node>,
    defs: BTreeMap<String, (NodeId, Range<usize>)>,
    uses: Vec<Use>,
    errors: Vec<ParseError>,
    /// Parameter names used but not declared before the use, in order of first use.
    unknown: Vec<Unknown>,
    /// Names of `def`s in text skipped by recovery: a `use` of one is not a mistake of its own.
    broken_defs: Vec<String>,
    name: Option<String>,
}

/// A child slot: a node built here, or a `use` to patch once every `def` is known.
enum Child {
    Node(NodeId),
    Use(String, Range<usize>),
}

const PLACEHOLDER: NodeId = NodeId::MAX;

/// The slot an unknown parameter name compiles to: the graph is never built when there is one, so any slot serves
/// to go on parsing (and find the file's other mistakes).
const UNKNOWN_SLOT: u16 = 0;

impl Parser<'_> {
    fn push(&mut self, node: Node, span: Range<usize>) -> Result<NodeId, ParseError> {
        if self.nodes.len() >= limits::MAX_NODES {
            return Err(ParseError::new(span, format!("more than {} nodes", limits::MAX_NODES)));
        }
        self.nodes.push(node);
        Ok((self.nodes.len() - 1) as NodeId)
    }

    /// Store children into a container node, recording `use` fixups.
    fn set_children(&mut self, id: NodeId, children: Vec<Child>) {
        let mut ids = Vec::with_capacity(children.len());
        for (index, c) in children.into_iter().enumerate() {
            match c {
                Child::Node(n) => ids.push(n),
                Child::Use(name, span) => {
                    ids.push(PLACEHOLDER);
                    self.uses.push(Use { node: id as usize, index, name, span });
                }
            }
        }
        match &mut self.nodes[id as usize] {
            Node::Group(c) | Node::Separator(c) | Node::RecursionSeparator(c) | Node::Lod(c) => *c = ids,
            Node::Selection { children, .. } => *children = ids,
            _ => unreachable!("only containers get children"),
        }
    }

    /// Parse nodes until `}` (or end of file at top level). A syntax error is recorded and parsing resumes after
    /// the broken construct (see [`Parser::recover`]), so one mistake does not hide the rest.
    fn node_list(&mut self, depth: usize, top: bool) -> Vec<Child> {
        let mut out = Vec::new();
        loop {
            self.cur.skip_trivia();
            if self.cur.at_end() {
                if !top {
                    let p = self.cur.pos;
                    self.errors.push(ParseError::new(p..p, "expected `}`, found end of file"));
                }
                return out;
            }
            if self.cur.eat("}") {
                if !top {
                    return out;
                }
                // A `}` at the top level closes nothing (recovery stops before one, so it must be consumed here).
                let p = self.cur.pos - 1;
                self.errors.push(ParseError::new(p..p + 1, "unmatched `}`"));
                continue;
            }
            if out.len() == limits::MAX_CHILDREN {
                let p = self.cur.pos;
                self.errors.push(ParseError::new(p..p + 1, format!("more than {} children", limits::MAX_CHILDREN)));
                self.recover(p);
                continue;
            }
            let start = self.cur.pos;
            match self.item(depth, top) {
                Ok(Some(c)) => out.push(c),
                Ok(None) => {}
                Err(e) => {
                    self.errors.push(e);
                    self.recover(start);
                }
            }
        }
    }

    /// Skip what is left of the construct that began at `start` and failed ([`Parser::skip_construct`]); the
    /// `def`s in the skipped text are remembered, so their uses elsewhere are not reported as mistakes of their own.
    fn recover(&mut self, start: usize) {
        self.skip_construct(start);
        let skipped = &self.cur.src[start..self.cur.pos.max(start)];
        let mut cur = Cursor::new(skipped, true);
        while !cur.at_end() {
            if cur.eat_keyword("def")
                && let Some((name, _)) = cur.ident()
            {
                self.broken_defs.push(name.to_string());
            } else if cur.ident().is_none() {
                cur.pos += cur.rest().chars().next().map_or(0, char::len_utf8);
            }
        }
    }

    /// Skip the rest of the construct's line and every block it opened (before or after the mistake), stopping
    /// before a `}` that closes the enclosing block. A block of the construct that closes ends the skip too
    /// (`calc { a = ) } sphere(1)` goes on at `sphere`).
    fn skip_construct(&mut self, start: usize) {
        let mut open = open_blocks(&self.cur.src[start..self.cur.pos.max(start)]);
        while let Some(c) = self.cur.rest().chars().next() {
            match c {
                '#' => {
                    self.cur.skip_trivia();
                    continue;
                }
                '}' if open == 0 => return,
                '}' => {
                    open -= 1;
                    if open == 0 {
                        self.cur.pos += 1;
                        return;
                    }
                }
                '{' => open += 1,
                '\n' if open == 0 => {
                    self.cur.pos += 1;
                    return;
                }
                _ => {}
            }
            self.cur.pos += c.len_utf8();
        }
    }

    fn item(&mut self, depth: usize, top: bool) -> Result<Option<Child>, ParseError> {
        self.cur.skip_trivia();
        let Some((word, span)) = self.cur.ident() else {
            return Err(self.cur.unexpected("a node"));
        };
        self.item_word(word, span, depth, top)
    }

    /// The item that starts with `word`.
    fn item_word(
        &mut self,
        word: &str,
        span: Range<usize>,
        depth: usize,
        top: bool,
    ) -> Result<Option<Child>, ParseError> {
        match word {
            "species" if top => {
                let (name, nspan) = self.cur.ident().ok_or_else(|| self.cur.unexpected("a species name"))?;
                if self.name.is_some() {
                    self.errors.push(ParseError::new(span.start..nspan.end, "species named twice"));
                }
                self.name = Some(name.to_string());
                Ok(None)
            }
            "param" | "state" | "let" if top => {
                self.param(word, span)?;
                Ok(None)
            }
            "param" | "state" | "let" | "species" => {
                Err(ParseError::new(span, format!("`{word}` is only allowed at the top level")))
            }
            "defs" => {
                // A block of definitions that is not traversed where it stands: its nodes exist only through `use`.
                self.cur.expect("{")?;
                let _ = self.node_list(depth + 1, false);
                Ok(None)
            }
            "use" => {
                let (name, nspan) = self.cur.ident().ok_or_else(|| self.cur.unexpected("a name after `use`"))?;
                Ok(Some(Child::Use(name.to_string(), nspan)))
            }
            "def" => {
                let (name, nspan) = self.cur.ident().ok_or_else(|| self.cur.unexpected("a name after `def`"))?;
                let child = self.item(depth, false)?;
                let Some(Child::Node(id)) = child else {
                    self.errors.push(ParseError::new(nspan, "`def` must name a node, not a `use`"));
                    return Ok(child);
                };
                match self.defs.get(name) {
                    Some((_, first)) => {
                        let (l, c) = line_col(self.cur.src, first.start);
                        self.errors.push(ParseError::new(nspan, format!("`{name}` is already defined at {l}:{c}")));
                    }
                    None => {
                        self.defs.insert(name.to_string(), (id, nspan));
                    }
                }
                Ok(Some(Child::Node(id)))
            }
            "group" | "separator" | "recurse" | "lod" | "select" => {
                if depth >= MAX_BLOCK_NESTING {
                    return Err(ParseError::new(span, format!("blocks nested deeper than {MAX_BLOCK_NESTING}")));
                }
                let node = match word {
                    "group" => Node::Group(vec![]),
                    "separator" => Node::Separator(vec![]),
                    "recurse" => Node::RecursionSeparator(vec![]),
                    "lod" => Node::Lod(vec![]),
                    _ => {
                        self.cur.expect("(")?;
                        let expr = self.expr()?;
                        self.cur.expect(")")?;
                        Node::Selection { expr, children: vec![] }
                    }
                };
                self.cur.expect("{")?;
                let id = self.push(node, span.clone())?;
                let children = self.node_list(depth + 1, false);
                if children.is_empty() && matches!(word, "select" | "lod") {
                    self.errors.push(ParseError::new(span, format!("`{word}` needs at least one child")));
                }
                self.set_children(id, children);
                Ok(Some(Child::Node(id)))
            }
            "calc" => {
                self.cur.expect("{")?;
                let mut assignments = Vec::new();
                while !self.cur.eat("}") {
                    let (name, nspan) =
                        self.cur.ident().ok_or_else(|| self.cur.unexpected("a parameter name or `}`"))?;
                    let slot = self.slot(name).unwrap_or_else(|| {
                        self.unknown_uses(&[name.to_string()], nspan.clone());
                        UNKNOWN_SLOT
                    });
                    self.cur.expect("=")?;
                    let value = self.expr()?;
                    if assignments.len() == limits::MAX_ASSIGNMENTS {
                        return Err(ParseError::new(
                            nspan,
                            format!("more than {} assignments", limits::MAX_ASSIGNMENTS),
                        ));
                    }
                    assignments.push((slot, value));
                    let _ = self.cur.eat(",") || self.cur.eat(";");
                }
                let id = self.push(Node::Calculation(assignments), span)?;
                Ok(Some(Child::Node(id)))
            }
            _ => {
                let start = self.cur.pos;
                let params = &self.params;
                let mut missing = Vec::new();
                let mut resolve = |n: &str| {
                    Some(params.iter().position(|p| p.name == n).map_or_else(
                        || {
                            missing.push(n.to_string());
                            UNKNOWN_SLOT
                        },
                        |i| i as u16,
                    ))
                };
                let call = parse_node_call(word, span.clone(), &mut self.cur, &mut resolve);
                self.unknown_uses(&missing, start..self.cur.pos);
                match call {
                    Some(node) => {
                        let id = self.push(node?, span)?;
                        Ok(Some(Child::Node(id)))
                    }
                    None => {
                        // A misspelt keyword or node: said once, and the item read as the word it is nearest to,
                        // so what it declares or holds is not lost (`pram x = 1`, `gruop { … }`).
                        let words = crate::nodes::NODE_CALLS.iter().copied().chain(KEYWORDS);
                        let Some(near) = did_you_mean(word, words) else {
                            return Err(ParseError::new(span, format!("unknown node `{word}`")));
                        };
                        let e = format!("unknown node `{word}`; did you mean `{near}`?");
                        self.errors.push(ParseError::new(span.clone(), e));
                        self.item_word(near, span, depth, top)
                    }
                }
            }
        }
    }

    fn slot(&self, name: &str) -> Option<u16> {
        self.params.iter().position(|p| p.name == name).map(|i| i as u16)
    }

    /// An expression at the cursor, compiled; a name that is not a parameter (yet) is recorded, not fatal.
    fn expr(&mut self) -> Result<canopy_protocol::Expr, ParseError> {
        let start = self.cur.pos;
        // An expression ends with its line (outside a node call's arguments): `param c = 4 +` then `def …` is a
        // trailing `+`, not a sum with a parameter named `def`.
        self.cur.newlines_are_space = false;
        let ast = parse_expr(&mut self.cur);
        self.cur.newlines_are_space = true;
        let ast = ast?;
        let mut missing = Vec::new();
        let compiled = compile(&ast, &mut |n| {
            Some(self.slot(n).unwrap_or_else(|| {
                missing.push(n.to_string());
                UNKNOWN_SLOT
            }))
        });
        self.unknown_uses(&missing, start..self.cur.pos);
        compiled
    }

    /// Record the uses of `names` (not declared) found in `within`, each name's uses counted once.
    fn unknown_uses(&mut self, names: &[String], within: Range<usize>) {
        let mut seen: Vec<&String> = Vec::new();
        for name in names {
            if seen.contains(&name) {
                continue;
            }
            seen.push(name);
            let spans = ident_spans(self.cur.src, within.clone(), name);
            let Some(first) = spans.first().cloned() else { continue };
            match self.unknown.iter_mut().find(|u| u.name == *name) {
                Some(u) => u.uses += spans.len(),
                None => self.unknown.push(Unknown { name: name.clone(), span: first, uses: spans.len() }),
            }
        }
    }

    /// `param NAME = e`, `state NAME = e` (a parameter), `let NAME = e` or `let state NAME = e` (a working value).
    fn param(&mut self, word: &str, span: Range<usize>) -> Result<(), ParseError> {
        let role = if word == "let" { ParamRole::Working } else { ParamRole::Parameter };
        let turtle = word == "state" || word == "let" && self.cur.eat_keyword("state");
        let (name, nspan) = self.cur.ident().ok_or_else(|| self.cur.unexpected("a name"))?;
        if matches!(name, "detail" | "pi" | "true" | "false") {
            return Err(ParseError::new(nspan, format!("`{name}` is reserved")));
        }
        if self.slot(name).is_some() {
            return Err(ParseError::new(nspan, format!("parameter `{name}` declared twice")));
        }
        if self.params.len() == limits::MAX_PARAMS {
            return Err(ParseError::new(span, format!("more than {} parameters", limits::MAX_PARAMS)));
        }
        let scope = if turtle { ParamScope::Turtle } else { ParamScope::Local };
        // Declared even when its default is broken, so its uses further on are not mistakes of their own.
        let default = self.cur.expect("=").and_then(|_| self.expr());
        let decl = |default| ParamDecl { name: name.to_string(), default, scope, role };
        self.params.push(decl(default.clone().unwrap_or_else(|_| canopy_protocol::Expr::constant(0.0))));
        self.param_spans.push(nspan);
        default.map(|_| ())
    }

    /// Names used but never declared, one diagnostic each: at the first use, with a near name the file has and how
    /// many other uses there are; a name declared only after its use is said to be.
    fn unknown_errors(&mut self) {
        for u in std::mem::take(&mut self.unknown) {
            let more = match u.uses {
                1 => String::new(),
                n => format!(" ({} more use(s))", n - 1),
            };
            let message = match self.slot(&u.name) {
                Some(slot) => {
                    let (l, c) = line_col(self.cur.src, self.param_spans[usize::from(slot)].start);
                    format!("parameter `{}` is used before its declaration at {l}:{c}{more}", u.name)
                }
                None => {
                    let names = self.params.iter().map(|p| p.name.as_str());
                    format!("unknown parameter `{}`{}{more}", u.name, hint(did_you_mean(&u.name, names)))
                }
            };
            self.errors.push(ParseError::new(u.span, message));
        }
    }

    fn finish(mut self, src: &SourceFile, root_children: Vec<Child>) -> (Option<SpeciesGraph>, Vec<Diagnostic>) {
        self.unknown_errors();
        // The root: the single top-level node, or a group of them.
        let root = match root_children.as_slice() {
            [] => {
                if self.errors.is_empty() {
                    self.errors.push(ParseError::new(0..0, "the species has no nodes"));
                }
                None
            }
            [Child::Node(id)] => Some(*id),
            _ => match self.push(Node::Group(vec![]), 0..0) {
                Ok(id) => {
                    self.set_children(id, root_children);
                    Some(id)
                }
                Err(e) => {
                    self.errors.push(e);
                    None
                }
            },
        };
        // A `use` of a name no `def` gives: one diagnostic a name, at its first use.
        let mut missing: BTreeMap<String, (Range<usize>, usize)> = BTreeMap::new();
        for u in std::mem::take(&mut self.uses) {
            match self.defs.get(&u.name) {
                Some(&(id, _)) => match &mut self.nodes[u.node] {
                    Node::Group(c) | Node::Separator(c) | Node::RecursionSeparator(c) | Node::Lod(c) => c[u.index] = id,
                    Node::Selection { children, .. } => children[u.index] = id,
                    _ => unreachable!("uses are recorded for containers only"),
                },
                None if self.broken_defs.contains(&u.name) => {}
                None => {
                    let m = missing.entry(u.name).or_insert((u.span.clone(), 0));
                    m.0 = if u.span.start < m.0.start { u.span } else { m.0.clone() };
                    m.1 += 1;
                }
            }
        }
        for (name, (span, uses)) in missing {
            let near = hint(did_you_mean(&name, self.defs.keys().map(String::as_str)));
            let more = if uses > 1 { format!(" ({} more use(s))", uses - 1) } else { String::new() };
            self.errors.push(ParseError::new(span, format!("`use {name}` names no `def`{near}{more}")));
        }
        let mut diags: Vec<Diagnostic> =
            self.errors.iter().map(|e| src.diag(e.span.clone(), e.message.clone())).collect();
        diags.sort_by_key(|d| (d.line, d.col));
        let Some(root) = root.filter(|_| diags.is_empty()) else { return (None, crate::diag::cap(diags)) };
        let name = self.name.unwrap_or_else(|| file_stem(&src.name));
        let graph = SpeciesGraph { name, params: self.params, nodes: self.nodes, root };
        match graph.validate() {
            Ok(()) => (Some(graph), diags),
            Err(e) => (None, vec![src.diag(0..0, format!("invalid species graph: {e}"))]),
        }
    }
}

/// The words that start a species item besides the node calls (for "did you mean").
const KEYWORDS: [&str; 12] =
    ["species", "param", "state", "let", "defs", "use", "def", "group", "separator", "recurse", "lod", "select"];

/// "; did you mean `x`?" for a suggestion, nothing without one.
fn hint(near: Option<&str>) -> String {
    near.map(|n| format!("; did you mean `{n}`?")).unwrap_or_default()
}

/// `{` opened and not closed in `text` (comments skipped).
fn open_blocks(text: &str) -> usize {
    let mut cur = Cursor::new(text, true);
    let mut open = 0usize;
    loop {
        cur.skip_trivia();
        let Some(c) = cur.rest().chars().next() else { return open };
        match c {
            '{' => open += 1,
            '}' => open = open.saturating_sub(1),
            _ => {}
        }
        cur.pos += c.len_utf8();
    }
}

/// The spans of the identifier `name` in `src[within]`, comments skipped.
fn ident_spans(src: &str, within: Range<usize>, name: &str) -> Vec<Range<usize>> {
    let mut cur = Cursor::new(&src[..within.end.min(src.len())], true);
    cur.pos = within.start.min(cur.src.len());
    let mut out = Vec::new();
    loop {
        cur.skip_trivia();
        let Some(c) = cur.rest().chars().next() else { return out };
        match cur.ident() {
            Some((w, span)) if w == name => out.push(span),
            Some(_) => {}
            // Numbers such as `2e3` are skipped whole, so their letters are never names.
            None if c.is_ascii_digit() || c == '.' => {
                let _ = cur.number();
                if cur.rest().starts_with(c) {
                    cur.pos += c.len_utf8();
                }
            }
            None => cur.pos += c.len_utf8(),
        }
    }
}

fn line_col(src: &str, offset: usize) -> (usize, usize) {
    SourceFile::new("", src).line_col(offset)
}

/// The file name without directories and extension (the default species name).
pub fn file_stem(path: &str) -> String {
    let base = path.rsplit(['/', '\\']).next().unwrap_or(path);
    let stem = base.split('.').next().unwrap_or(base);
    if stem.is_empty() { "species".to_string() } else { stem.to_string() }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> (Option<SpeciesGraph>, Vec<Diagnostic>) {
        parse_species(&SourceFile::new("t.species", text))
    }

    #[test]
    fn worm_parses_with_a_cycle() {
        let (g, d) = parse(
            "species Worm\nparam c = 4\ndef Worm select(c > 0) {\n  cone(0.5, 0, 1)\n  separator {\n    sphere(0.5)\n    translate(1, 0, 0)\n    calc { c = c - 1 }\n    recurse { use Worm }\n  }\n}\n",
        );
        assert!(d.is_empty(), "{d:?}");
        let g = g.unwrap();
        assert_eq!(g.name, "Worm");
        let Node::Selection { children, .. } = &g.nodes[g.root as usize] else { panic!("root is the selection") };
        let Node::Separator(sep) = &g.nodes[children[1] as usize] else { panic!() };
        let Node::RecursionSeparator(rec) = &g.nodes[*sep.last().unwrap() as usize] else { panic!() };
        assert_eq!(rec, &vec![g.root], "use links back to the selection: a cycle");
    }

    #[test]
    fn every_error_is_reported_with_position() {
        let (g, d) = parse("param a = 1\nsphere(b)\ncone(1, 2)\nuse Nowhere\nfoo(1)\ncylinder(a, a)\n");
        assert!(g.is_none());
        let got: Vec<(usize, usize, &str)> = d.iter().map(|d| (d.line, d.col, d.message.as_str())).collect();
        assert_eq!(
            got,
            vec![
                (2, 8, "unknown parameter `b`"),
                (3, 1, "`cone` takes 3 argument(s), got 2"),
                (4, 5, "`use Nowhere` names no `def`"),
                (5, 1, "unknown node `foo`"),
            ]
        );
    }

    /// `param`/`state` declare the species' parameters, `let`/`let state` its working values: same evaluation,
    /// but nothing outside the species may set a working value.
    #[test]
    fn let_declares_a_working_value() {
        let (g, d) =
            parse("param height = 2\nlet n = height * 2\nlet state w = 1\nstate colour = 0\ncone(n, w, colour)\n");
        assert!(d.is_empty(), "{d:?}");
        let g = g.unwrap();
        let roles: Vec<(&str, ParamRole, ParamScope)> =
            g.params.iter().map(|p| (p.name.as_str(), p.role, p.scope)).collect();
        assert_eq!(
            roles,
            vec![
                ("height", ParamRole::Parameter, ParamScope::Local),
                ("n", ParamRole::Working, ParamScope::Local),
                ("w", ParamRole::Working, ParamScope::Turtle),
                ("colour", ParamRole::Parameter, ParamScope::Turtle),
            ]
        );
        let set = |name: &str| crate::amplify::resolve_params(&g, &[(name.to_string(), 1.0)]);
        assert_eq!(set("height"), Ok(vec![(0, 1.0)]));
        assert_eq!(
            set("n").unwrap_err(),
            "`n` is a working value of species `t`, not a parameter (its parameters: height, colour)"
        );
        assert!(set("nope").unwrap_err().starts_with("species `t` has no parameter `nope`"));
    }

    #[test]
    fn recovery_skips_a_broken_block() {
        let (_, d) = parse("group { sphere(1) cone(\n}\nfoo\n");
        assert_eq!(d.len(), 2, "{d:?}");
        assert_eq!(d[1].message, "unknown node `foo`");
    }

    #[test]
    fn duplicates_and_reserved_names() {
        let (_, d) = parse("param x = 1\nparam x = 2\nparam detail = 3\ndef A sphere(1)\ndef A sphere(2)\n");
        let msgs: Vec<&str> = d.iter().map(|d| d.message.as_str()).collect();
        assert_eq!(msgs, vec!["parameter `x` declared twice", "`detail` is reserved", "`A` is already defined at 4:5"]);
    }

    #[test]
    fn hostile_nesting_is_bounded() {
        let text = "group {".repeat(10_000);
        let (g, d) = parse(&text);
        assert!(g.is_none());
        assert!(d.iter().any(|d| d.message.contains("nested deeper")));
    }
}
