//! The species text format (`.species`), in the spirit of seed 001 §6's RECURSIV files: parameters, then a node
//! tree in which `def NAME` names a node and `use NAME` links to it again — from anywhere, so a link back to an
//! enclosing node is a cycle.
//!
//! ```text
//! species Worm                      # optional; defaults to the file name
//! param c = 4                       # a Local parameter and its default (may draw: uniform(3, 5))
//! state w = 0.1                     # a Turtle-scope parameter (flows across recursion separators)
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
//! The top-level nodes form the root group. Parameters must be declared before the nodes that use them.

use std::collections::BTreeMap;
use std::ops::Range;

use canopy_protocol::{Node, NodeId, ParamDecl, ParamScope, SpeciesGraph, limits};

use crate::diag::{Diagnostic, SourceFile};
use crate::expr::{compile, parse_expr};
use crate::nodes::parse_node_call;
use crate::text::{Cursor, ParseError};

/// Deepest nesting of `{ }` blocks accepted.
pub const MAX_BLOCK_NESTING: usize = 256;

/// Parse a species text file. Returns the graph if there were no errors, and every diagnostic found.
pub fn parse_species(src: &SourceFile) -> (Option<SpeciesGraph>, Vec<Diagnostic>) {
    let mut p = Parser {
        cur: Cursor::new(&src.text, true),
        params: Vec::new(),
        nodes: Vec::new(),
        defs: BTreeMap::new(),
        uses: Vec::new(),
        errors: Vec::new(),
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

struct Parser<'a> {
    cur: Cursor<'a>,
    params: Vec<ParamDecl>,
    nodes: Vec<Node>,
    defs: BTreeMap<String, (NodeId, Range<usize>)>,
    uses: Vec<Use>,
    errors: Vec<ParseError>,
    name: Option<String>,
}

/// A child slot: a node built here, or a `use` to patch once every `def` is known.
enum Child {
    Node(NodeId),
    Use(String, Range<usize>),
}

const PLACEHOLDER: NodeId = NodeId::MAX;

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

    /// Parse nodes until `}` (or end of file at top level). Errors are recorded and parsing resumes on the next
    /// line, so one mistake does not hide the rest.
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
                self.recover();
                continue;
            }
            match self.item(depth, top) {
                Ok(Some(c)) => out.push(c),
                Ok(None) => {}
                Err(e) => {
                    self.errors.push(e);
                    self.recover();
                }
            }
        }
    }

    /// Skip the rest of the line and any block opened on it, stopping before a `}` that closes the current block.
    fn recover(&mut self) {
        let mut open = 0i64;
        while let Some(c) = self.cur.rest().chars().next() {
            match c {
                '}' if open == 0 => return,
                '}' => open -= 1,
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
        match word {
            "species" if top => {
                let (name, nspan) = self.cur.ident().ok_or_else(|| self.cur.unexpected("a species name"))?;
                if self.name.is_some() {
                    return Err(ParseError::new(span.start..nspan.end, "species named twice"));
                }
                self.name = Some(name.to_string());
                Ok(None)
            }
            "param" | "state" if top => {
                self.param(word, span)?;
                Ok(None)
            }
            "param" | "state" | "species" => {
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
                let id = match self.item(depth, false)? {
                    Some(Child::Node(id)) => id,
                    _ => return Err(ParseError::new(nspan, "`def` must name a node, not a `use`")),
                };
                if let Some((_, first)) = self.defs.get(name) {
                    let (l, c) = line_col(self.cur.src, first.start);
                    return Err(ParseError::new(nspan, format!("`{name}` is already defined at {l}:{c}")));
                }
                self.defs.insert(name.to_string(), (id, nspan));
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
                        let ast = parse_expr(&mut self.cur)?;
                        self.cur.expect(")")?;
                        let expr = self.compile(&ast)?;
                        Node::Selection { expr, children: vec![] }
                    }
                };
                self.cur.expect("{")?;
                let id = self.push(node, span.clone())?;
                let children = self.node_list(depth + 1, false);
                if children.is_empty() && matches!(word, "select" | "lod") {
                    return Err(ParseError::new(span, format!("`{word}` needs at least one child")));
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
                    let slot = self
                        .slot(name)
                        .ok_or_else(|| ParseError::new(nspan.clone(), format!("unknown parameter `{name}`")))?;
                    self.cur.expect("=")?;
                    let ast = parse_expr(&mut self.cur)?;
                    if assignments.len() == limits::MAX_ASSIGNMENTS {
                        return Err(ParseError::new(
                            nspan,
                            format!("more than {} assignments", limits::MAX_ASSIGNMENTS),
                        ));
                    }
                    assignments.push((slot, self.compile(&ast)?));
                    let _ = self.cur.eat(",") || self.cur.eat(";");
                }
                let id = self.push(Node::Calculation(assignments), span)?;
                Ok(Some(Child::Node(id)))
            }
            _ => {
                let params = &self.params;
                let mut resolve = |n: &str| params.iter().position(|p| p.name == n).map(|i| i as u16);
                match parse_node_call(word, span.clone(), &mut self.cur, &mut resolve) {
                    Some(node) => {
                        let id = self.push(node?, span)?;
                        Ok(Some(Child::Node(id)))
                    }
                    None => Err(ParseError::new(span, format!("unknown node `{word}`"))),
                }
            }
        }
    }

    fn slot(&self, name: &str) -> Option<u16> {
        self.params.iter().position(|p| p.name == name).map(|i| i as u16)
    }

    fn compile(&self, ast: &crate::expr::Ast) -> Result<canopy_protocol::Expr, ParseError> {
        compile(ast, &mut |n| self.slot(n))
    }

    fn param(&mut self, word: &str, span: Range<usize>) -> Result<(), ParseError> {
        let (name, nspan) = self.cur.ident().ok_or_else(|| self.cur.unexpected("a parameter name"))?;
        if matches!(name, "detail" | "pi" | "true" | "false") {
            return Err(ParseError::new(nspan, format!("`{name}` is reserved")));
        }
        if self.slot(name).is_some() {
            return Err(ParseError::new(nspan, format!("parameter `{name}` declared twice")));
        }
        if self.params.len() == limits::MAX_PARAMS {
            return Err(ParseError::new(span, format!("more than {} parameters", limits::MAX_PARAMS)));
        }
        self.cur.expect("=")?;
        let ast = parse_expr(&mut self.cur)?;
        let default = self.compile(&ast)?;
        let scope = if word == "state" { ParamScope::Turtle } else { ParamScope::Local };
        self.params.push(ParamDecl { name: name.to_string(), default, scope });
        Ok(())
    }

    fn finish(mut self, src: &SourceFile, root_children: Vec<Child>) -> (Option<SpeciesGraph>, Vec<Diagnostic>) {
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
        for u in std::mem::take(&mut self.uses) {
            match self.defs.get(&u.name) {
                Some(&(id, _)) => match &mut self.nodes[u.node] {
                    Node::Group(c) | Node::Separator(c) | Node::RecursionSeparator(c) | Node::Lod(c) => c[u.index] = id,
                    Node::Selection { children, .. } => children[u.index] = id,
                    _ => unreachable!("uses are recorded for containers only"),
                },
                None => self.errors.push(ParseError::new(u.span, format!("`use {}` names no `def`", u.name))),
            }
        }
        let mut diags: Vec<Diagnostic> =
            self.errors.iter().map(|e| src.diag(e.span.clone(), e.message.clone())).collect();
        diags.sort_by_key(|d| (d.line, d.col));
        let Some(root) = root.filter(|_| diags.is_empty()) else { return (None, diags) };
        let name = self.name.unwrap_or_else(|| file_stem(&src.name));
        let graph = SpeciesGraph { name, params: self.params, nodes: self.nodes, root };
        match graph.validate() {
            Ok(()) => (Some(graph), diags),
            Err(e) => (None, vec![src.diag(0..0, format!("invalid species graph: {e}"))]),
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
