//! Pass 2 of the `.lsys` parser: items to the species DCG (seed 001 §3.2; the shape is in the module docs of
//! [`crate::lsystem`]).

use std::collections::{HashMap, HashSet};
use std::ops::Range;

use canopy_protocol::{Expr, Node, NodeId, Op, ParamDecl, ParamRole, ParamScope, SpeciesGraph, limits};

use crate::amplify::{DEPTH_PARAM, MAX_DEPTH_LIMIT};
use crate::diag::SourceFile;
use crate::expr::{Ast, BinOp, compile};
use crate::nodes::{NODE_CALLS, parse_node_call};
use crate::text::{Cursor, ParseError};

mod productions;
mod turtle;

use super::lpy::{self, Declared, LPY_DEFAULT_ANGLE, LPY_MATERIALS, LPY_START_COLOR, LpyLine};
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
    /// Whether `;`, `,` or `'` use L-Py's materials (there is no `palette`).
    lpy_colors: bool,
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
        // L-Py's lines that are not rules: the end of the rules, context filters and Python.
        match lpy::classify(text, pos) {
            Some(LpyLine::End(error)) => {
                errors.extend(error);
                break;
            }
            Some(LpyLine::ContextFilter { end }) => {
                pos = end + 1;
                continue;
            }
            Some(LpyLine::Python { error, end, declares }) => {
                errors.push(error);
                ghosts.extend(declares.map(|d| match d {
                    Declared::Value(name) => Ghost::Param(name),
                    Declared::Module(name) => Ghost::Symbol(name),
                }));
                pos = end + 1;
                continue;
            }
            None => {}
        }
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
            Err(_) if section == Section::Decomposition => match ghost(text, pos) {
                Some(Ghost::Section(kind)) => section = kind,
                g => ghosts.extend(g),
            },
            Ok(Some(Item::Production(p))) if section == Section::Interpretation => {
                items.push(Item::Interpretation(p));
            }
            Ok(Some(item)) => items.push(item),
            Ok(None) => {}
            Err(e) => {
                errors.push(e);
                match ghost(text, pos) {
                    Some(Ghost::Section(kind)) => section = kind,
                    g => ghosts.extend(g),
                }
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
        lpy_colors: false,
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
            Ghost::Section(_) => {}
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
                    self.params.push(ParamDecl {
                        name: n.clone(),
                        default,
                        scope: ParamScope::Local,
                        role: ParamRole::Parameter,
                    });
                }
                Err(e) => {
                    self.errors.push(e);
                    self.names.ghost_params.insert(n.clone());
                }
            }
        }
        let hidden = |name: &str, scope| ParamDecl {
            name: name.to_string(),
            default: Expr::constant(0.0),
            scope,
            role: ParamRole::Working,
        };
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
                self.params.push(ParamDecl {
                    name,
                    default: Expr::constant(one),
                    scope: ParamScope::Turtle,
                    role: ParamRole::Working,
                });
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
                _ => match self.rule_symbol(src, p, &mut heads, &mut user_symbols, SymbolKind::NonTerminal) {
                    Ok(id) => id,
                    Err(RuleSymbol::Skip) => continue,
                    Err(RuleSymbol::Stop) => break,
                },
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
                _ => match self.rule_symbol(src, p, &mut heads, &mut user_symbols, SymbolKind::Module) {
                    Ok(id) => id,
                    Err(RuleSymbol::Skip) => continue,
                    Err(RuleSymbol::Stop) => break,
                },
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
        // L-Py's turtle starts at its material 1 when its materials are in use.
        let color = if self.lpy_colors { LPY_START_COLOR as f32 } else { 0.0 };
        let init =
            self.b.calc(vec![(self.d, derive.clone()), (self.w, width.clone()), (self.c, Expr::constant(color))]);
        let mut children = vec![init];
        if self.lpy_colors {
            let m = LPY_MATERIALS[LPY_START_COLOR].map(Expr::constant);
            children.push(self.b.push(Node::Material(m)));
        }
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
            lpy_colors: self.lpy_colors,
            max_depth: self.max_depth,
        })
    }

    /// The symbol a production or interpretation rule `p` rewrites: an existing one whose first production takes
    /// as many parameters, or a new one of `kind` (`Stop` when the symbol table is full, `Skip` on an arity error).
    fn rule_symbol(
        &mut self,
        src: &SourceFile,
        p: &Production,
        heads: &mut Vec<(SymbolId, Vec<String>, Range<usize>)>,
        user_symbols: &mut usize,
        kind: SymbolKind,
    ) -> Result<SymbolId, RuleSymbol> {
        if let Some(&id) = self.by_name.get(&p.pred) {
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
                return Err(RuleSymbol::Skip);
            }
            return Ok(id);
        }
        if *user_symbols == MAX_SYMBOLS {
            self.err(p.pred_span.clone(), format!("more than {MAX_SYMBOLS} symbols"));
            return Err(RuleSymbol::Stop);
        }
        *user_symbols += 1;
        let id = self.new_symbol(&p.pred, kind);
        heads.push((id, p.formals.iter().map(|f| f.0.clone()).collect(), p.pred_span.clone()));
        Ok(id)
    }

    fn new_symbol(&mut self, name: &str, kind: SymbolKind) -> SymbolId {
        let id = self.symbols.len() as SymbolId;
        self.symbols.push(Symbol::blank(name, kind));
        self.by_name.insert(name.to_string(), id);
        id
    }

    fn new_slot(&mut self, name: String) -> u16 {
        self.params.push(ParamDecl {
            name,
            default: Expr::constant(0.0),
            scope: ParamScope::Local,
            role: ParamRole::Working,
        });
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
                        role: ParamRole::Working,
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
                // The default argument: a length of 1, or the `angle` parameter, or L-Py's default angle.
                if matches!(t, Turtle::Forward | Turtle::Move) {
                    args.push(Expr::constant(1.0));
                } else {
                    let angle = self.names.params.get("angle").copied();
                    let angle = angle.or_else(|| self.names.ghost_params.contains("angle").then_some(0));
                    args.push(angle.map_or(Expr::constant(LPY_DEFAULT_ANGLE), Expr::param));
                }
            }
            if ok {
                out.push(Successor { symbol, args });
            }
        }
        out
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

/// Why `Compiler::rule_symbol` found no symbol for a rule.
enum RuleSymbol {
    /// The rule has an error: skip it and go on.
    Skip,
    /// The symbol table is full: stop reading rules.
    Stop,
}
