//! Pass 2 of the `.lsys` parser: items to the species DCG (seed 001 §3.2; the shape is in the module docs of
//! [`crate::lsystem`]).

use std::collections::{HashMap, HashSet};
use std::ops::Range;

use canopy_protocol::{Expr, Node, NodeId, Op, ParamDecl, ParamScope, SpeciesGraph, limits};

use crate::amplify::{DEPTH_PARAM, MAX_DEPTH_LIMIT};
use crate::diag::SourceFile;
use crate::expr::{Ast, BinOp, compile};
use crate::nodes::{NODE_CALLS, parse_node_call};
use crate::text::{Cursor, ParseError};

use super::parse::{Ghost, Item, KEYWORDS, Production, RESERVED, RawSucc, Section, at_line_end, ghost, parse_line};
use super::{
    DEFAULT_WIDTH, LSystem, MAX_CHOOSE, MAX_PRODUCTIONS, MAX_SOURCE_LEN, MAX_SPECIES_PARAMS, MAX_SYMBOLS, Successor,
    Symbol, SymbolId, SymbolKind, Turtle, WIDTH_DECREASE,
};

struct Names {
    params: HashMap<String, u16>,
    ghost_params: HashSet<String>,
}

impl Names {
    fn resolver<'a>(
        &'a self,
        formals: &'a [(String, u16)],
        internal: &'a [(&'static str, u16)],
    ) -> impl FnMut(&str) -> Option<u16> + 'a {
        move |n: &str| {
            formals
                .iter()
                .find(|f| f.0 == n)
                .map(|f| f.1)
                .or_else(|| self.params.get(n).copied())
                .or_else(|| internal.iter().find(|f| f.0 == n).map(|f| f.1))
                .or_else(|| self.ghost_params.contains(n).then_some(0))
        }
    }
}

fn compile_at(ast: &Ast, resolve: &mut dyn FnMut(&str) -> Option<u16>, at: &Range<usize>) -> Result<Expr, ParseError> {
    compile(ast, resolve).map_err(|mut e| {
        if e.span == (0..0) {
            e.span = at.clone();
        }
        e
    })
}

pub(super) struct Builder {
    pub(super) nodes: Vec<Node>,
    pub(super) calcs: HashMap<String, NodeId>,
}

impl Builder {
    pub(super) fn push(&mut self, n: Node) -> NodeId {
        self.nodes.push(n);
        (self.nodes.len() - 1) as NodeId
    }

    /// A calculation node, shared with every identical one.
    fn calc(&mut self, assignments: Vec<(u16, Expr)>) -> NodeId {
        // Keyed by exact bits (Debug would print every NaN alike).
        let mut key = String::new();
        for (slot, e) in &assignments {
            key.push_str(&format!("{slot}="));
            for op in &e.ops {
                match op {
                    Op::Const(v) => key.push_str(&format!("c{:08x},", v.to_bits())),
                    op => key.push_str(&format!("{op:?},")),
                }
            }
            key.push(';');
        }
        if let Some(&id) = self.calcs.get(&key) {
            return id;
        }
        let id = self.push(Node::Calculation(assignments));
        self.calcs.insert(key, id);
        id
    }

    /// A container; children beyond the per-node limit are grouped (groups do not change traversal).
    fn container(&mut self, make: fn(Vec<NodeId>) -> Node, mut children: Vec<NodeId>) -> NodeId {
        while children.len() > limits::MAX_CHILDREN {
            children = children.chunks(limits::MAX_CHILDREN).map(|c| self.push(Node::Group(c.to_vec()))).collect();
        }
        self.push(make(children))
    }
}

struct Compiler<'s> {
    src: &'s str,
    errors: &'s mut Vec<ParseError>,
    names: Names,
    params: Vec<ParamDecl>,
    b: Builder,
    symbols: Vec<Symbol>,
    by_name: HashMap<String, SymbolId>,
    ghost_symbols: HashSet<String>,
    palette: Option<Vec<[Ast; 3]>>,
    palette_broken: bool,
    d: u16,
    w: u16,
    c: u16,
    /// `_x`, the cut flag, if the L-system uses `%`.
    cut: Option<u16>,
    /// The turtle's frame (the columns X, Y, Z: left is -X, heading Y, up Z), if the L-system uses `$`.
    frame: Option<[u16; 9]>,
    /// A shared empty group: what a guarded body becomes after a cut.
    empty: Option<NodeId>,
    /// Symbols with an interpretation rule, and the rule.
    interps: Vec<(SymbolId, usize)>,
    max_depth: u32,
}

fn expr_param(slot: u16) -> Expr {
    Expr::param(slot)
}

fn neg_param(slot: u16) -> Expr {
    Expr { ops: vec![Op::Param(slot), Op::Neg] }
}

fn axis(i: usize) -> [Expr; 3] {
    std::array::from_fn(|j| Expr::constant(if i == j { 1.0 } else { 0.0 }))
}

pub(super) fn parse_inner(src: &SourceFile, errors: &mut Vec<ParseError>) -> Option<LSystem> {
    let text = src.text.as_str();
    if text.len() > MAX_SOURCE_LEN {
        errors.push(ParseError::new(0..0, format!("source of {} bytes exceeds {MAX_SOURCE_LEN}", text.len())));
        return None;
    }
    // Pass 1: every line on its own, so one bad line does not hide the others.
    let mut items = Vec::new();
    let mut ghosts = Vec::new();
    let mut pos = 0;
    let mut section = Section::Productions;
    while pos < text.len() {
        let end = text[pos..].find('\n').map_or(text.len(), |i| pos + i);
        let mut cur = Cursor { src: text, pos, newlines_are_space: false };
        match parse_line(&mut cur) {
            Ok(Some(Item::Section(kind, span))) => {
                if kind == Section::Decomposition {
                    errors.push(ParseError::new(
                        span,
                        "`decomposition:` sections are not supported: decomposition rules rewrite a module again and \
                         again within one derivation step, and a species DCG (seed 001 §3.2) applies one production \
                         per module per step; write the decomposed structure into the productions",
                    ));
                }
                section = kind;
            }
            // The rules of an unsupported section: their symbols count as declared, so no follow-up errors.
            Ok(Some(Item::Production(p))) if section == Section::Decomposition => ghosts.push(Ghost::Symbol(p.pred)),
            Err(_) if section == Section::Decomposition => ghosts.extend(ghost(text, pos)),
            Ok(Some(Item::Production(p))) if section == Section::Interpretation => {
                items.push(Item::Interpretation(p));
            }
            Ok(Some(item)) => items.push(item),
            Ok(None) => {}
            Err(e) => {
                errors.push(e);
                ghosts.extend(ghost(text, pos));
            }
        }
        pos = end + 1;
    }

    let mut c = Compiler {
        src: text,
        errors,
        names: Names { params: HashMap::new(), ghost_params: HashSet::new() },
        params: Vec::new(),
        b: Builder { nodes: Vec::new(), calcs: HashMap::new() },
        symbols: Vec::new(),
        by_name: HashMap::new(),
        ghost_symbols: HashSet::new(),
        palette: None,
        palette_broken: false,
        d: 0,
        w: 0,
        c: 0,
        cut: None,
        frame: None,
        empty: None,
        interps: Vec::new(),
        max_depth: crate::amplify::Budget::default().max_depth,
    };
    let mut broken_directives = HashSet::new();
    for g in ghosts {
        match g {
            Ghost::Symbol(s) => {
                c.ghost_symbols.insert(s);
            }
            Ghost::Param(p) => {
                c.names.ghost_params.insert(p);
            }
            Ghost::Directive(d) => {
                broken_directives.insert(d);
            }
        }
    }
    c.palette_broken = broken_directives.contains("palette");
    c.run(src, &items, &broken_directives)
}

impl Compiler<'_> {
    fn err(&mut self, span: Range<usize>, msg: impl Into<String>) {
        self.errors.push(ParseError::new(span, msg));
    }

    fn run(mut self, src: &SourceFile, items: &[Item], broken: &HashSet<&'static str>) -> Option<LSystem> {
        // The name.
        let mut name = None;
        for item in items {
            if let Item::Name(n, s) = item {
                if name.is_some() {
                    self.err(s.clone(), "`lsystem` name given twice");
                }
                name = Some(n.clone());
            }
        }
        let name = name.unwrap_or_else(|| {
            let base = src.name.rsplit(['/', '\\']).next().unwrap_or("");
            let stem = base.split('.').next().unwrap_or("");
            if stem.is_empty() || stem.len() > limits::MAX_NAME_LEN { "lsystem".to_string() } else { stem.to_string() }
        });

        // Species params, in declaration order; a default reads the params declared before it.
        for item in items {
            let Item::Param(n, span, ast) = item else { continue };
            if RESERVED.contains(&n.as_str()) || n == "width" || n == "derive" {
                self.err(span.clone(), format!("`{n}` is reserved and cannot be a parameter name"));
                continue;
            }
            if n.starts_with('_') {
                self.err(span.clone(), format!("parameter names may not start with `_` (`{n}`)"));
                continue;
            }
            if self.names.params.contains_key(n) {
                self.err(span.clone(), format!("parameter `{n}` declared twice"));
                continue;
            }
            if self.params.len() == MAX_SPECIES_PARAMS {
                self.err(span.clone(), format!("more than {MAX_SPECIES_PARAMS} parameters"));
                break;
            }
            let r = compile_at(ast, &mut self.names.resolver(&[], &[]), span);
            match r {
                Ok(default) => {
                    self.names.params.insert(n.clone(), self.params.len() as u16);
                    self.params.push(ParamDecl { name: n.clone(), default, scope: ParamScope::Local });
                }
                Err(e) => {
                    self.errors.push(e);
                    self.names.ghost_params.insert(n.clone());
                }
            }
        }
        let hidden = |name: &str, scope| ParamDecl { name: name.to_string(), default: Expr::constant(0.0), scope };
        self.d = self.params.len() as u16;
        self.params.push(hidden("_d", ParamScope::Local));
        self.w = self.params.len() as u16;
        self.params.push(hidden("_w", ParamScope::Turtle));
        self.c = self.params.len() as u16;
        self.params.push(hidden("_c", ParamScope::Turtle));
        // The slots only some L-systems need come after, so the others' graphs stay as they were.
        let uses = |name: &str| items.iter().any(|i| item_successors(i).iter().any(|r| r.name == name));
        if uses("%") {
            self.cut = Some(self.params.len() as u16);
            self.params.push(hidden("_x", ParamScope::Turtle));
        }
        if uses("$") {
            let mut slots = [0u16; 9];
            for (k, slot) in slots.iter_mut().enumerate() {
                *slot = self.params.len() as u16;
                let (col, row) = (k / 3, k % 3);
                let name = format!("_{}.{}", ["X", "Y", "Z"][col], ["x", "y", "z"][row]);
                let one = if col == row { 1.0 } else { 0.0 };
                self.params.push(ParamDecl { name, default: Expr::constant(one), scope: ParamScope::Turtle });
            }
            self.frame = Some(slots);
        }
        self.max_depth_directive(items);

        // The palette.
        for item in items {
            if let Item::Palette(entries, span) = item {
                if self.palette.is_some() {
                    self.err(span.clone(), "`palette` given twice");
                    continue;
                }
                self.palette = Some(entries.clone());
            }
        }

        // The alphabet: turtle symbols, then modules, then non-terminals.
        for t in Turtle::ALL {
            self.symbols.push(Symbol::blank(t.text(), SymbolKind::Turtle(t)));
        }
        // (symbol, formal names, span) of each user symbol, for slot naming and arity checks.
        let mut heads: Vec<(SymbolId, Vec<String>, Range<usize>)> = Vec::new();
        let mut user_symbols = 0usize;
        for item in items {
            let Item::Module { name: n, span, formals, .. } = item else { continue };
            if n == "F" || n == "f" {
                self.err(span.clone(), format!("`{n}` is a turtle symbol and cannot be redefined"));
                continue;
            }
            if KEYWORDS.contains(&n.as_str()) {
                self.err(span.clone(), format!("`{n}` is a keyword and cannot name a module"));
                continue;
            }
            if self.by_name.contains_key(n) {
                self.err(span.clone(), format!("module `{n}` defined twice"));
                continue;
            }
            if user_symbols == MAX_SYMBOLS {
                self.err(span.clone(), format!("more than {MAX_SYMBOLS} symbols"));
                break;
            }
            user_symbols += 1;
            let id = self.new_symbol(n, SymbolKind::Module);
            heads.push((id, formals.iter().map(|f| f.0.clone()).collect(), span.clone()));
        }
        let mut productions = 0usize;
        let mut prods: Vec<(SymbolId, &Production)> = Vec::new();
        for item in items {
            let Item::Production(p) = item else { continue };
            productions += 1;
            if productions > MAX_PRODUCTIONS {
                self.err(p.pred_span.clone(), format!("more than {MAX_PRODUCTIONS} productions"));
                break;
            }
            let id = match self.by_name.get(&p.pred) {
                Some(&id) if self.symbols[id as usize].kind == SymbolKind::Module => {
                    self.err(
                        p.pred_span.clone(),
                        format!("`{}` is defined by `module` and cannot have productions", p.pred),
                    );
                    continue;
                }
                Some(&id) => {
                    let head = heads.iter().find(|h| h.0 == id).expect("every user symbol has a head");
                    if head.1.len() != p.formals.len() {
                        let (line, _) = src.line_col(head.2.start);
                        let msg = format!(
                            "`{}` has {} parameter(s) in its first production (line {line}), here {}",
                            p.pred,
                            head.1.len(),
                            p.formals.len()
                        );
                        self.err(p.pred_span.clone(), msg);
                        continue;
                    }
                    id
                }
                None => {
                    if user_symbols == MAX_SYMBOLS {
                        self.err(p.pred_span.clone(), format!("more than {MAX_SYMBOLS} symbols"));
                        break;
                    }
                    user_symbols += 1;
                    let id = self.new_symbol(&p.pred, SymbolKind::NonTerminal);
                    heads.push((id, p.formals.iter().map(|f| f.0.clone()).collect(), p.pred_span.clone()));
                    id
                }
            };
            prods.push((id, p));
        }
        // Interpretation rules: a symbol without productions becomes a terminal drawn by its rule.
        let mut interps: Vec<(SymbolId, usize)> = Vec::new();
        for (k, item) in items.iter().enumerate() {
            let Item::Interpretation(p) = item else { continue };
            productions += 1;
            if productions > MAX_PRODUCTIONS {
                self.err(p.pred_span.clone(), format!("more than {MAX_PRODUCTIONS} productions"));
                break;
            }
            if p.terminal {
                self.err(
                    p.pred_span.clone(),
                    "an interpretation rule is written with `->` (`=>` is for the derivation)",
                );
                continue;
            }
            if p.cond.is_some() || p.weight.is_some() {
                let what = if p.cond.is_some() { "condition" } else { "probability" };
                self.err(p.pred_span.clone(), format!("an interpretation rule takes no {what}"));
                continue;
            }
            let id = match self.by_name.get(&p.pred) {
                Some(&id) if interps.iter().any(|i| i.0 == id) => {
                    self.err(p.pred_span.clone(), format!("`{}` has a second interpretation rule", p.pred));
                    continue;
                }
                Some(&id) if self.symbols[id as usize].kind == SymbolKind::Module => {
                    let msg = format!("`{}` is defined by `module` and cannot have an interpretation rule too", p.pred);
                    self.err(p.pred_span.clone(), msg);
                    continue;
                }
                Some(&id) => {
                    let head = heads.iter().find(|h| h.0 == id).expect("every user symbol has a head");
                    if head.1.len() != p.formals.len() {
                        let (line, _) = src.line_col(head.2.start);
                        let msg = format!(
                            "`{}` has {} parameter(s) in its first production (line {line}), here {}",
                            p.pred,
                            head.1.len(),
                            p.formals.len()
                        );
                        self.err(p.pred_span.clone(), msg);
                        continue;
                    }
                    id
                }
                None => {
                    if user_symbols == MAX_SYMBOLS {
                        self.err(p.pred_span.clone(), format!("more than {MAX_SYMBOLS} symbols"));
                        break;
                    }
                    user_symbols += 1;
                    let id = self.new_symbol(&p.pred, SymbolKind::Module);
                    heads.push((id, p.formals.iter().map(|f| f.0.clone()).collect(), p.pred_span.clone()));
                    id
                }
            };
            interps.push((id, k));
        }
        self.interps = interps;
        // Formal slots, `Sym.formal`, in symbol order.
        heads.sort_by_key(|h| h.0);
        for (id, formals, span) in &heads {
            if self.params.len() + formals.len() > limits::MAX_PARAMS {
                self.err(span.clone(), format!("more than {} parameter slots in all", limits::MAX_PARAMS));
                return None;
            }
            let sym = self.symbols[*id as usize].name.clone();
            let slots = formals.iter().map(|f| self.new_slot(format!("{sym}.{f}"))).collect();
            self.symbols[*id as usize].formals = slots;
        }

        // Module bodies.
        for item in items {
            let Item::Module { name: n, span, formals, body } = item else { continue };
            let Some(&id) = self.by_name.get(n) else { continue };
            if self.symbols[id as usize].kind != SymbolKind::Module || self.symbols[id as usize].body.is_some() {
                continue;
            }
            self.module_body(id, formals, *body, span);
        }

        // Interpretation rules' successors: terminals, drawn as they are.
        for (id, k) in self.interps.clone() {
            let Item::Interpretation(p) = &items[k] else { unreachable!("interps index interpretation items") };
            self.interpretation(id, p);
        }

        // Selection nodes first, so successors can link to them (cycles).
        for s in 0..self.symbols.len() {
            if self.symbols[s].kind == SymbolKind::NonTerminal {
                let id = self.b.push(Node::Selection { expr: Expr::constant(0.0), children: Vec::new() });
                self.symbols[s].selection = Some(id);
            }
        }
        // The productions of each non-terminal.
        for s in 0..self.symbols.len() {
            if self.symbols[s].kind != SymbolKind::NonTerminal {
                continue;
            }
            let mine: Vec<&Production> = prods.iter().filter(|p| p.0 as usize == s).map(|p| p.1).collect();
            self.symbols[s].production_at = mine
                .iter()
                .filter(|p| !p.terminal)
                .map(|p| {
                    let d = src.diag(p.pred_span.clone(), "");
                    format!("{}:{}:{} `{}`", d.file, d.line, d.col, strip_comment(&d.line_text))
                })
                .collect();
            self.non_terminal(s as SymbolId, &mine);
        }

        // The axiom and the root.
        let mut axiom = None;
        for item in items {
            if let Item::Axiom(succ, span) = item {
                if axiom.is_some() {
                    self.err(span.clone(), "`axiom` given twice");
                    continue;
                }
                axiom = Some(self.successors(succ, &[], false));
            }
        }
        let mut derive = None;
        let mut width = None;
        for item in items {
            match item {
                Item::Derive(ast, span) | Item::Width(ast, span) => {
                    let is_derive = matches!(item, Item::Derive(..));
                    let slot = if is_derive { &mut derive } else { &mut width };
                    if slot.is_some() {
                        let what = if is_derive { "derive" } else { "width" };
                        self.errors.push(ParseError::new(span.clone(), format!("`{what}` given twice")));
                        continue;
                    }
                    match compile_at(ast, &mut self.names.resolver(&[], &[]), span) {
                        Ok(e) => *slot = Some(e),
                        Err(e) => self.errors.push(e),
                    }
                }
                _ => {}
            }
        }
        if derive.is_none() && !broken.contains("derive") && !items.iter().any(|i| matches!(i, Item::Derive(..))) {
            self.err(0..0, "missing `derive N`: the derivation depth");
        }
        if axiom.is_none() && !broken.contains("axiom") {
            self.err(0..0, "missing `axiom: …`");
        }
        if !self.errors.is_empty() {
            return None;
        }
        let (derive, axiom) = (derive?, axiom?);
        let width = width.unwrap_or(Expr::constant(DEFAULT_WIDTH));
        let init = self.b.calc(vec![(self.d, derive.clone()), (self.w, width.clone()), (self.c, Expr::constant(0.0))]);
        let mut children = vec![init];
        children.extend(self.emit(&axiom));
        let root = self.b.container(Node::Group, children);

        let graph = SpeciesGraph { name, params: self.params, nodes: self.b.nodes, root };
        if let Err(e) = graph.validate() {
            self.errors.push(ParseError::new(0..0, format!("the compiled graph is too large or invalid: {e}")));
            return None;
        }
        Some(LSystem {
            graph,
            symbols: self.symbols,
            axiom,
            derive,
            width,
            depth_slot: self.d,
            width_slot: self.w,
            color_slot: self.c,
            cut_slot: self.cut,
            max_depth: self.max_depth,
        })
    }

    fn new_symbol(&mut self, name: &str, kind: SymbolKind) -> SymbolId {
        let id = self.symbols.len() as SymbolId;
        self.symbols.push(Symbol::blank(name, kind));
        self.by_name.insert(name.to_string(), id);
        id
    }

    fn new_slot(&mut self, name: String) -> u16 {
        self.params.push(ParamDecl { name, default: Expr::constant(0.0), scope: ParamScope::Local });
        (self.params.len() - 1) as u16
    }

    fn module_body(&mut self, id: SymbolId, formals: &[(String, Range<usize>)], body: usize, span: &Range<usize>) {
        let scope: Vec<(String, u16)> =
            formals.iter().map(|f| f.0.clone()).zip(self.symbols[id as usize].formals.iter().copied()).collect();
        let mut cur = Cursor { src: self.src, pos: body, newlines_are_space: false };
        let mut nodes = Vec::new();
        while !at_line_end(&mut cur) {
            let Some((call, call_span)) = cur.ident() else {
                let e = cur.unexpected("a node call such as `cylinder(r, h)`");
                self.errors.push(e);
                return;
            };
            let mut resolve = self.names.resolver(&scope, &[]);
            match parse_node_call(call, call_span.clone(), &mut cur, &mut resolve) {
                None => {
                    let msg = format!("unknown node call `{call}` (one of: {})", NODE_CALLS.join(", "));
                    self.errors.push(ParseError::new(call_span, msg));
                    return;
                }
                Some(Err(e)) => {
                    self.errors.push(e);
                    return;
                }
                Some(Ok(node)) => {
                    if node.exprs().iter().any(|e| e.draws()) {
                        let msg = "a module body may not draw random numbers; pass a random argument instead";
                        self.errors.push(ParseError::new(call_span, msg));
                        return;
                    }
                    nodes.push(node);
                }
            }
        }
        if nodes.len() > limits::MAX_CHILDREN {
            self.err(span.clone(), format!("a module body has at most {} calls", limits::MAX_CHILDREN));
            return;
        }
        let primitives = nodes.iter().filter(|n| n.is_primitive()).count();
        let children = nodes.into_iter().map(|n| self.b.push(n)).collect();
        let body = self.b.push(Node::Separator(children));
        let body = self.guard(body);
        let s = &mut self.symbols[id as usize];
        s.body = Some(body);
        s.primitives = primitives;
    }

    /// The shared body of a turtle symbol, built on first use.
    fn turtle_body(&mut self, t: Turtle, span: &Range<usize>) -> Option<()> {
        let id = t.id() as usize;
        if self.symbols[id].body.is_some() || matches!(t, Turtle::Push | Turtle::Pop) {
            return Some(());
        }
        let formals: Vec<u16> = t.formals().iter().map(|f| self.new_slot(format!("{}.{f}", t.text()))).collect();
        let (w, c) = (self.w, self.c);
        let body = match t {
            Turtle::Forward => {
                let l = formals[0];
                let cyl = self.b.push(Node::Cylinder { radius: expr_param(w), height: expr_param(l) });
                let mv = self.b.push(Node::Translate([Expr::constant(0.0), expr_param(l), Expr::constant(0.0)]));
                self.symbols[id].primitives = 1;
                Node::Group(vec![cyl, mv])
            }
            Turtle::Move => Node::Translate([Expr::constant(0.0), expr_param(formals[0]), Expr::constant(0.0)]),
            Turtle::TurnLeft => Node::Rotate { axis: axis(2), angle: expr_param(formals[0]) },
            Turtle::TurnRight => Node::Rotate { axis: axis(2), angle: neg_param(formals[0]) },
            Turtle::PitchDown => Node::Rotate { axis: axis(0), angle: expr_param(formals[0]) },
            Turtle::PitchUp => Node::Rotate { axis: axis(0), angle: neg_param(formals[0]) },
            Turtle::RollLeft => Node::Rotate { axis: axis(1), angle: expr_param(formals[0]) },
            Turtle::RollRight => Node::Rotate { axis: axis(1), angle: neg_param(formals[0]) },
            Turtle::TurnAround => Node::Rotate { axis: axis(2), angle: Expr::constant(180.0) },
            Turtle::SetWidth => Node::Calculation(vec![(w, expr_param(formals[0]))]),
            Turtle::ScaleWidth => {
                Node::Calculation(vec![(w, Expr { ops: vec![Op::Param(w), Op::Const(WIDTH_DECREASE), Op::Mul] })])
            }
            Turtle::SetColor => {
                Node::Material([expr_param(formals[0]), expr_param(formals[1]), expr_param(formals[2])])
            }
            Turtle::NextColor | Turtle::ColorUp | Turtle::ColorDown | Turtle::SetColorIndex => {
                let index = match t {
                    Turtle::SetColorIndex => expr_param(formals[0]),
                    Turtle::ColorDown => Expr {
                        ops: vec![
                            Op::Param(c),
                            Op::Const(1.0),
                            Op::Sub,
                            Op::Const(1.0),
                            Op::Call(canopy_protocol::Func::Max),
                        ],
                    },
                    _ => Expr { ops: vec![Op::Param(c), Op::Const(1.0), Op::Add] },
                };
                let channels = self.palette_channels(t, span)?;
                let calc = self.b.push(Node::Calculation(vec![(c, index)]));
                let mat = self.b.push(Node::Material(channels));
                Node::Group(vec![calc, mat])
            }
            Turtle::Cut => Node::Calculation(vec![(self.cut.expect("`%` is used"), Expr::constant(1.0))]),
            Turtle::RollToHorizontal => return self.roll_to_horizontal(),
            Turtle::Push | Turtle::Pop => unreachable!("brackets have no body"),
        };
        let mut body = self.b.push(body);
        // Rotations keep the turtle's frame up to date for `$`.
        let rotation = match t {
            Turtle::TurnLeft | Turtle::TurnRight | Turtle::TurnAround => Some(2),
            Turtle::PitchDown | Turtle::PitchUp => Some(0),
            Turtle::RollLeft | Turtle::RollRight => Some(1),
            _ => None,
        };
        if let (Some(axis), Some(frame)) = (rotation, self.frame) {
            let degrees = match t {
                Turtle::TurnAround => Ast::Num(180.0),
                Turtle::TurnRight | Turtle::PitchUp | Turtle::RollRight => {
                    Ast::Unary(crate::expr::UnOp::Neg, Box::new(Ast::var("$a")))
                }
                _ => Ast::var("$a"),
            };
            let radians = Ast::bin(BinOp::Mul, degrees, Ast::Num(std::f32::consts::PI / 180.0));
            let cos = Ast::Call(canopy_protocol::Func::Cos, vec![radians.clone()]);
            let sin = Ast::Call(canopy_protocol::Func::Sin, vec![radians]);
            let angle_slot = formals.first().copied().unwrap_or(self.d);
            let update = self.frame_update(frame, axis, cos, sin, angle_slot, span)?;
            body = self.b.push(Node::Group(vec![body, update]));
        }
        let body = if t == Turtle::Cut { body } else { self.guard(body) };
        self.symbols[id].formals = formals;
        self.symbols[id].body = Some(body);
        Some(())
    }

    /// `body`, or — if the L-system uses `%` — a selection that skips it once the branch is cut.
    fn guard(&mut self, body: NodeId) -> NodeId {
        let Some(x) = self.cut else { return body };
        let empty = self.empty_group();
        self.b.push(Node::Selection { expr: Expr::param(x), children: vec![body, empty] })
    }

    fn empty_group(&mut self) -> NodeId {
        match self.empty {
            Some(e) => e,
            None => {
                let e = self.b.push(Node::Group(Vec::new()));
                self.empty = Some(e);
                e
            }
        }
    }

    /// The palette entry `_c` selects, per channel: `_c <= 1 ? p1 : _c <= 2 ? p2 : … : p_last`.
    fn palette_channels(&mut self, t: Turtle, span: &Range<usize>) -> Option<[Expr; 3]> {
        let Some(palette) = self.palette.clone() else {
            if !self.palette_broken {
                let written = if t == Turtle::SetColorIndex { "with an index" } else { "without arguments" };
                self.err(span.clone(), format!("`{}` {written} needs a `palette`", &self.src[span.clone()]));
            }
            return None;
        };
        let mut channels = Vec::new();
        for k in 0..3 {
            let mut ast = palette[palette.len() - 1][k].clone();
            for i in (0..palette.len() - 1).rev() {
                let test = Ast::bin(BinOp::Le, Ast::var("$c"), Ast::Num((i + 1) as f32));
                ast = Ast::cond(test, palette[i][k].clone(), ast);
            }
            let internal = [("$c", self.c)];
            let r = compile_at(&ast, &mut self.names.resolver(&[], &internal), span);
            match r {
                Ok(e) if e.draws() => {
                    self.err(span.clone(), "palette colours may not draw random numbers");
                    return None;
                }
                Ok(e) => channels.push(e),
                Err(e) => {
                    self.errors.push(e);
                    return None;
                }
            }
        }
        Some(<[Expr; 3]>::try_from(channels).expect("three channels"))
    }

    /// A calculation turning the tracked frame by the angle whose cosine and sine are given, about local axis
    /// `axis`: with `(i, j)` the next two axes in cyclic order, `i' = c i + s j` and `j' = c j - s i`.
    fn frame_update(
        &mut self,
        frame: [u16; 9],
        axis: usize,
        cos: Ast,
        sin: Ast,
        angle_slot: u16,
        span: &Range<usize>,
    ) -> Option<NodeId> {
        const NAMES: [&str; 9] = ["$0", "$1", "$2", "$3", "$4", "$5", "$6", "$7", "$8"];
        let (i, j) = ((axis + 1) % 3, (axis + 2) % 3);
        let mut assign = Vec::new();
        for row in 0..3 {
            let (vi, vj) = (Ast::var(NAMES[i * 3 + row]), Ast::var(NAMES[j * 3 + row]));
            let ni = Ast::bin(
                BinOp::Add,
                Ast::bin(BinOp::Mul, cos.clone(), vi.clone()),
                Ast::bin(BinOp::Mul, sin.clone(), vj.clone()),
            );
            let nj = Ast::bin(BinOp::Sub, Ast::bin(BinOp::Mul, cos.clone(), vj), Ast::bin(BinOp::Mul, sin.clone(), vi));
            assign.push((frame[i * 3 + row], ni));
            assign.push((frame[j * 3 + row], nj));
        }
        let mut internal: Vec<(&'static str, u16)> = NAMES.iter().copied().zip(frame).collect();
        internal.push(("$a", angle_slot));
        let mut out = Vec::new();
        for (slot, ast) in assign {
            match compile_at(&ast, &mut self.names.resolver(&[], &internal), span) {
                Ok(e) => out.push((slot, e)),
                Err(e) => {
                    self.errors.push(e);
                    return None;
                }
            }
        }
        Some(self.b.push(Node::Calculation(out)))
    }

    /// The body of `$`: roll about the heading (local Y) by the angle that makes X, and so the left vector -X,
    /// horizontal: `cos = Z.y / r`, `sin = X.y / r` with `r = |(X.y, Z.y)|`; no roll when the heading is vertical.
    fn roll_to_horizontal(&mut self) -> Option<()> {
        let frame = self.frame.expect("`$` is used");
        let (xy, zy) = (Ast::var("$1"), Ast::var("$7"));
        let r = Ast::Call(
            canopy_protocol::Func::Sqrt,
            vec![Ast::bin(
                BinOp::Add,
                Ast::bin(BinOp::Mul, xy.clone(), xy.clone()),
                Ast::bin(BinOp::Mul, zy.clone(), zy.clone()),
            )],
        );
        let level = Ast::bin(BinOp::Gt, r.clone(), Ast::Num(1e-6));
        let cos = Ast::cond(level.clone(), Ast::bin(BinOp::Div, zy, r.clone()), Ast::Num(1.0));
        let sin = Ast::cond(level, Ast::bin(BinOp::Div, xy, r), Ast::Num(0.0));
        let span = 0..0;
        let update = self.frame_update(frame, 1, cos.clone(), sin.clone(), self.d, &span)?;
        // Rot_y(φ), 3 rows of 4: [c 0 s 0; 0 1 0 0; -s 0 c 0].
        const NAMES: [&str; 9] = ["$0", "$1", "$2", "$3", "$4", "$5", "$6", "$7", "$8"];
        let internal: Vec<(&'static str, u16)> = NAMES.iter().copied().zip(frame).collect();
        let neg_sin = Ast::Unary(crate::expr::UnOp::Neg, Box::new(sin.clone()));
        let zero = || Ast::Num(0.0);
        let m = [cos.clone(), zero(), sin, zero(), zero(), Ast::Num(1.0), zero(), zero(), neg_sin, zero(), cos, zero()];
        let mut exprs = Vec::new();
        for ast in &m {
            match compile_at(ast, &mut self.names.resolver(&[], &internal), &span) {
                Ok(e) => exprs.push(e),
                Err(e) => {
                    self.errors.push(e);
                    return None;
                }
            }
        }
        let m = <[Expr; 12]>::try_from(exprs).expect("twelve entries");
        let rot = self.b.push(Node::Matrix(Box::new(m)));
        let body = self.b.push(Node::Group(vec![rot, update]));
        let body = self.guard(body);
        self.symbols[Turtle::RollToHorizontal.id() as usize].body = Some(body);
        Some(())
    }

    /// Compile a symbol's interpretation rule: a terminal gets it as its body (it moves the turtle like the
    /// successor it stands for); a non-terminal keeps it for its final alternative.
    fn interpretation(&mut self, id: SymbolId, p: &Production) {
        let slots = self.symbols[id as usize].formals.clone();
        let scope: Vec<(String, u16)> = p.formals.iter().map(|f| f.0.clone()).zip(slots.iter().copied()).collect();
        let succ = self.successors(&p.succ, &scope, true);
        for r in &p.succ {
            if let Some(&other) = self.by_name.get(&r.name)
                && self.interps.iter().any(|i| i.0 == other)
            {
                let msg =
                    format!("an interpretation rule may not use `{}`, which has an interpretation rule itself", r.name);
                self.err(r.span.clone(), msg);
            }
        }
        if succ.iter().any(|s| s.args.iter().any(Expr::draws)) {
            let msg = "an interpretation rule may not draw random numbers; pass a random argument instead";
            self.err(p.pred_span.clone(), msg);
        }
        if !self.errors.is_empty() {
            // Bodies are pointless once there are errors (and a broken module has none to link to).
            return;
        }
        let primitives = succ.iter().map(|s| self.symbols[s.symbol as usize].primitives).sum();
        if self.symbols[id as usize].kind == SymbolKind::Module {
            let nodes = self.emit(&succ);
            let body = self.b.container(Node::Group, nodes);
            self.symbols[id as usize].body = Some(body);
        }
        let s = &mut self.symbols[id as usize];
        s.primitives = primitives;
        s.interpretation = Some(succ);
    }

    /// The `maxdepth N` directive: the nesting this species asks of the traversal, stored as [`DEPTH_PARAM`].
    fn max_depth_directive(&mut self, items: &[Item]) {
        let mut seen = false;
        for item in items {
            let Item::MaxDepth(ast, span) = item else { continue };
            if seen {
                self.err(span.clone(), "`maxdepth` given twice");
                continue;
            }
            seen = true;
            let v = match compile_at(ast, &mut |_: &str| None, span) {
                Ok(e) => e.as_constant(),
                Err(e) => {
                    self.errors.push(e);
                    continue;
                }
            };
            let default = self.max_depth;
            match v {
                Some(v) if v.fract() == 0.0 && v >= 1.0 && v <= MAX_DEPTH_LIMIT as f32 => {
                    self.max_depth = (v as u32).max(default);
                    let decl = ParamDecl {
                        name: DEPTH_PARAM.to_string(),
                        default: Expr::constant(v),
                        scope: ParamScope::Local,
                    };
                    self.params.push(decl);
                }
                _ => self.err(
                    span.clone(),
                    format!("`maxdepth` takes a whole number from 1 to {MAX_DEPTH_LIMIT} (the default is {default})"),
                ),
            }
        }
    }

    /// Resolve and compile one successor list in the scope of a predecessor's formals.
    fn successors(&mut self, raw: &[RawSucc], scope: &[(String, u16)], terminal_only: bool) -> Vec<Successor> {
        let mut out = Vec::new();
        for r in raw {
            let nargs = r.args.as_ref().map_or(0, |a| a.0.len());
            let arg_span = r.args.as_ref().map_or(r.span.clone(), |a| r.span.start..a.1.end);
            let turtle = match r.name.as_str() {
                "F" => Some(Ok(Turtle::Forward)),
                "f" => Some(Ok(Turtle::Move)),
                "+" => Some(Ok(Turtle::TurnLeft)),
                "-" => Some(Ok(Turtle::TurnRight)),
                "&" => Some(Ok(Turtle::PitchDown)),
                "^" => Some(Ok(Turtle::PitchUp)),
                "\\" => Some(Ok(Turtle::RollLeft)),
                "/" => Some(Ok(Turtle::RollRight)),
                "|" => Some(Ok(Turtle::TurnAround)),
                "!" => Some(match nargs {
                    0 => Ok(Turtle::ScaleWidth),
                    1 => Ok(Turtle::SetWidth),
                    _ => Err("0 or 1"),
                }),
                "%" => Some(Ok(Turtle::Cut)),
                "$" => Some(Ok(Turtle::RollToHorizontal)),
                ";" => Some(match nargs {
                    0 => Ok(Turtle::ColorUp),
                    1 => Ok(Turtle::SetColorIndex),
                    _ => Err("0 or 1"),
                }),
                "," => Some(match nargs {
                    0 => Ok(Turtle::ColorDown),
                    1 => Ok(Turtle::SetColorIndex),
                    _ => Err("0 or 1"),
                }),
                "'" => Some(match nargs {
                    0 => Ok(Turtle::NextColor),
                    3 => Ok(Turtle::SetColor),
                    _ => Err("0 or 3"),
                }),
                "[" => Some(Ok(Turtle::Push)),
                "]" => Some(Ok(Turtle::Pop)),
                _ => None,
            };
            let (symbol, arity_ok) = match turtle {
                Some(Err(want)) => {
                    self.err(arg_span, format!("`{}` takes {want} argument(s), got {nargs}", r.name));
                    continue;
                }
                Some(Ok(t)) => {
                    let n = t.formals().len();
                    let ok = nargs == n || (n == 1 && nargs == 0 && !matches!(t, Turtle::SetWidth));
                    if !ok {
                        let want = if n == 1 { "0 or 1".to_string() } else { n.to_string() };
                        self.err(arg_span, format!("`{}` takes {want} argument(s), got {nargs}", r.name));
                        continue;
                    }
                    if self.turtle_body(t, &r.span).is_none() {
                        continue;
                    }
                    (t.id(), true)
                }
                None => match self.by_name.get(&r.name) {
                    Some(&id) => {
                        let want = self.symbols[id as usize].formals.len();
                        (id, want == nargs)
                    }
                    None => {
                        if !self.ghost_symbols.contains(&r.name) {
                            self.err(
                                r.span.clone(),
                                format!(
                                    "undefined symbol `{}`: it has no productions and no `module` definition{}",
                                    r.name,
                                    split_hint(&r.name, &self.by_name)
                                ),
                            );
                        }
                        continue;
                    }
                },
            };
            let sym = &self.symbols[symbol as usize];
            if !arity_ok {
                let msg = format!("`{}` takes {} argument(s), got {nargs}", r.name, sym.formals.len());
                self.err(arg_span, msg);
                continue;
            }
            if terminal_only && sym.kind == SymbolKind::NonTerminal {
                let msg = format!(
                    "a terminal production (`=>`) may only contain terminals, but `{}` is a non-terminal",
                    r.name
                );
                self.err(r.span.clone(), msg);
                continue;
            }
            let mut args = Vec::new();
            let mut ok = true;
            if let Some((asts, _)) = &r.args {
                for a in asts {
                    match compile_at(a, &mut self.names.resolver(scope, &[]), &r.span) {
                        Ok(e) => args.push(e),
                        Err(e) => {
                            self.errors.push(e);
                            ok = false;
                        }
                    }
                }
            } else if let SymbolKind::Turtle(t) = sym.kind
                && t.formals().len() == 1
            {
                // The default argument: a length of 1, or the `angle` parameter.
                if matches!(t, Turtle::Forward | Turtle::Move) {
                    args.push(Expr::constant(1.0));
                } else {
                    let angle = self.names.params.get("angle").copied();
                    let angle = angle.or_else(|| self.names.ghost_params.contains("angle").then_some(0));
                    match angle {
                        Some(slot) => args.push(Expr::param(slot)),
                        None => {
                            let msg = format!("`{}` without an argument needs an `angle` directive", r.name);
                            self.err(r.span.clone(), msg);
                            ok = false;
                        }
                    }
                }
            }
            if ok {
                out.push(Successor { symbol, args });
            }
        }
        out
    }

    fn non_terminal(&mut self, id: SymbolId, prods: &[&Production]) {
        let slots = self.symbols[id as usize].formals.clone();
        let first_span = prods.first().map_or(0..0, |p| p.pred_span.clone());
        let mut rhs = Vec::new();
        let mut terminal: Option<Vec<Successor>> = None;
        // Per `->` production: condition and weight, already checked to compile on their own.
        let mut tests: Vec<(Option<Ast>, Option<Ast>)> = Vec::new();
        for p in prods {
            let scope: Vec<(String, u16)> = p.formals.iter().map(|f| f.0.clone()).zip(slots.iter().copied()).collect();
            if p.terminal {
                let succ = self.successors(&p.succ, &scope, true);
                if terminal.is_some() {
                    self.err(p.pred_span.clone(), format!("`{}` has a second terminal production (`=>`)", p.pred));
                } else {
                    terminal = Some(succ);
                }
                continue;
            }
            let succ = self.successors(&p.succ, &scope, false);
            // Rename the production's formals to the symbol's slots by compiling the ASTs with their own scope now
            // (for errors at the right place), then with `$f<i>` names in the combined selection expression.
            let mut renamed = [None, None];
            for (k, ast) in [&p.cond, &p.weight].into_iter().enumerate() {
                let Some(ast) = ast else { continue };
                match compile_at(ast, &mut self.names.resolver(&scope, &[]), &p.pred_span) {
                    Ok(_) => renamed[k] = Some(rename(ast, &p.formals)),
                    Err(e) => self.errors.push(e),
                }
            }
            let [cond, weight] = renamed;
            rhs.push(succ);
            tests.push((cond, weight));
        }
        let n = rhs.len();
        let stochastic = prods.iter().any(|p| !p.terminal && p.weight.is_some());
        let choice = if stochastic {
            if n > MAX_CHOOSE {
                self.err(first_span.clone(), format!("a stochastic symbol has at most {MAX_CHOOSE} productions"));
                return;
            }
            Ast::Choose(
                tests
                    .into_iter()
                    .map(|(c, w)| {
                        let w = w.unwrap_or(Ast::Num(1.0));
                        match c {
                            Some(c) => Ast::cond(c, w, Ast::Num(0.0)),
                            None => w,
                        }
                    })
                    .collect(),
            )
        } else {
            let mut acc = Ast::Num(n as f32);
            for (i, (c, _)) in tests.into_iter().enumerate().rev() {
                acc = match c {
                    Some(c) => Ast::cond(c, Ast::Num(i as f32), acc),
                    None => Ast::Num(i as f32),
                };
            }
            acc
        };
        let select = Ast::cond(Ast::bin(BinOp::Le, Ast::var("$d"), Ast::Num(0.0)), Ast::Num((n + 1) as f32), choice);
        let internal: Vec<(String, u16)> = slots.iter().enumerate().map(|(i, &s)| (format!("$f{i}"), s)).collect();
        let internal_d = [("$d", self.d), ("$x", self.cut.unwrap_or(self.d))];
        // After a cut, a call does nothing: `_x > 0 ? n + 2 : select` in the node, child n + 2 empty.
        let cut_select =
            Ast::cond(Ast::bin(BinOp::Gt, Ast::var("$x"), Ast::Num(0.0)), Ast::Num((n + 2) as f32), select.clone());
        let node_expr = match compile_at(&cut_select, &mut self.names.resolver(&internal, &internal_d), &first_span) {
            Ok(e) => e,
            Err(e) => {
                self.errors.push(e);
                return;
            }
        };
        let select = match compile_at(&select, &mut self.names.resolver(&internal, &internal_d), &first_span) {
            Ok(e) => e,
            Err(e) => {
                self.errors.push(e);
                return;
            }
        };
        if !self.errors.is_empty() {
            // Nodes are pointless once there are errors; keep checking the other symbols.
            return;
        }
        let interpretation = self.symbols[id as usize].interpretation.clone();
        if terminal.is_some() && interpretation.is_some() {
            let msg = format!(
                "`{}` has both a terminal production (`=>`) and an interpretation rule; keep one: the interpretation \
                 rule draws the occurrences left at the end",
                self.symbols[id as usize].name
            );
            self.err(first_span.clone(), msg);
            return;
        }
        let terminal = terminal.unwrap_or_default();
        let dec = self.b.calc(vec![(self.d, Expr { ops: vec![Op::Param(self.d), Op::Const(1.0), Op::Sub] })]);
        let mut children = Vec::new();
        for succ in &rhs {
            let mut c = vec![dec];
            c.extend(self.emit(succ));
            children.push(self.b.container(Node::Group, c));
        }
        let selection = self.symbols[id as usize].selection.expect("selection nodes are made first");
        let mut call = Vec::new();
        if !slots.is_empty() {
            call.push(self.b.calc(slots.iter().map(|&s| (s, Expr::param(s))).collect()));
        }
        call.push(selection);
        let call = self.b.push(Node::RecursionSeparator(call));
        children.push(self.b.push(Node::Group(vec![dec, call])));
        let fin = self.emit(interpretation.as_deref().unwrap_or(&terminal));
        children.push(self.b.container(Node::Group, fin));
        // After a cut, a call does nothing: `_x > 0 ? n + 2 : select`, child n + 2 empty.
        let node_expr = if self.cut.is_some() {
            children.push(self.empty_group());
            node_expr
        } else {
            select.clone()
        };
        self.b.nodes[selection as usize] = Node::Selection { expr: node_expr, children };
        let s = &mut self.symbols[id as usize];
        s.select = Some(select);
        s.productions = rhs;
        s.terminal = terminal;
    }

    /// The nodes of a successor list (see the module docs).
    fn emit(&mut self, succ: &[Successor]) -> Vec<NodeId> {
        let mut stack: Vec<Vec<NodeId>> = vec![Vec::new()];
        for s in succ {
            let sym = &self.symbols[s.symbol as usize];
            let assign: Vec<(u16, Expr)> = sym.formals.iter().copied().zip(s.args.iter().cloned()).collect();
            match sym.kind {
                SymbolKind::Turtle(Turtle::Push) => stack.push(Vec::new()),
                SymbolKind::Turtle(Turtle::Pop) => {
                    let inner = stack.pop().expect("brackets are balanced");
                    let sep = self.b.container(Node::Separator, inner);
                    stack.last_mut().expect("brackets are balanced").push(sep);
                }
                SymbolKind::NonTerminal => {
                    let selection = sym.selection.expect("selection nodes are made first");
                    let mut c = Vec::new();
                    if !assign.is_empty() {
                        c.push(self.b.calc(assign));
                    }
                    c.push(selection);
                    let rs = self.b.push(Node::RecursionSeparator(c));
                    stack.last_mut().expect("at least the outer list").push(rs);
                }
                SymbolKind::Turtle(_) | SymbolKind::Module => {
                    let body = sym.body.expect("terminals in successors have bodies");
                    if !assign.is_empty() {
                        let calc = self.b.calc(assign);
                        stack.last_mut().expect("at least the outer list").push(calc);
                    }
                    stack.last_mut().expect("at least the outer list").push(body);
                }
            }
        }
        debug_assert_eq!(stack.len(), 1, "brackets are balanced");
        stack.pop().unwrap_or_default()
    }
}

/// The successors an item holds (the axiom's, a production's or an interpretation rule's).
fn item_successors(item: &Item) -> &[RawSucc] {
    match item {
        Item::Axiom(s, _) => s,
        Item::Production(p) | Item::Interpretation(p) => &p.succ,
        _ => &[],
    }
}

/// A production's line without its comment.
fn strip_comment(line: &str) -> &str {
    line.split('#').next().unwrap_or("").trim()
}

/// Rename a production's formals to `$f<i>` so the combined selection expression resolves them to the symbol's
/// slots whatever this production called them.
fn rename(ast: &Ast, formals: &[(String, Range<usize>)]) -> Ast {
    let r = |a: &Ast| Box::new(rename(a, formals));
    match ast {
        Ast::Var(n, span) => match formals.iter().position(|f| f.0 == *n) {
            Some(i) => Ast::Var(format!("$f{i}"), span.clone()),
            None => ast.clone(),
        },
        Ast::Num(_) | Ast::Detail => ast.clone(),
        Ast::Unary(op, a) => Ast::Unary(*op, r(a)),
        Ast::Binary(op, a, b) => Ast::Binary(*op, r(a), r(b)),
        Ast::And(a, b) => Ast::And(r(a), r(b)),
        Ast::Or(a, b) => Ast::Or(r(a), r(b)),
        Ast::Cond(c, a, b) => Ast::Cond(r(c), r(a), r(b)),
        Ast::Call(f, args) => Ast::Call(*f, args.iter().map(|a| rename(a, formals)).collect()),
        Ast::Choose(ws) => Ast::Choose(ws.iter().map(|a| rename(a, formals)).collect()),
    }
}

/// A hint for `FF`-style names made of single-letter symbols written without spaces.
fn split_hint(name: &str, known: &HashMap<String, SymbolId>) -> String {
    let all_known = name.len() > 1
        && name.chars().all(|c| c == 'F' || c == 'f' || known.contains_key(c.encode_utf8(&mut [0; 4]) as &str));
    if all_known {
        let spaced: Vec<String> = name.chars().map(String::from).collect();
        format!(" (separate symbols with spaces: `{}`)", spaced.join(" "))
    } else {
        String::new()
    }
}
