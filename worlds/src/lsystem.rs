//! Parametric L-systems (`.lsys`) and their translation into a species DCG (seed 001 §3.1–3.2), plus the
//! string-rewriting reference derivation the translation is tested against.
//!
//! # The format
//!
//! Line oriented; `#` starts a comment. Directives and productions, in any order:
//!
//! ```text
//! lsystem Bush                 # name (optional; default: the file name without extension)
//! derive 6 - detail            # derivation depth (required): an expression of the params and `detail`
//! angle 22.5                   # default turning angle in degrees; the same as `param angle = 22.5`
//! width 0.1                    # initial line width (default 0.05)
//! param len = uniform(0.8, 1.2)  # a species parameter; its default may draw and read earlier params
//! palette (0.4,0.3,0.2) (0.2,0.6,0.2)   # colours for `'`
//! module L(s) = material(0.2, 0.7, 0.2) leaf((0,0,0), (0.1*s, 0.5*s, 0), (0, s, 0), (-0.1*s, 0.5*s, 0))
//! axiom: A(1) B
//! A(x) : x > 0.5 -> F(x) [ +(angle) A(x*0.7) ] [ -(angle) A(x*0.7) ]    # condition after `:`
//! A(x) -> F(x) L(1)
//! B -> F B : 0.3               # stochastic: weight after the successor
//! B -> f B : 0.7
//! A(x) => L(x)                 # terminal production, used once the depth is reached
//! ```
//!
//! * **Non-terminals** are the symbols with productions (`->` or `=>`); **terminals** are the turtle symbols and
//!   `module`-defined symbols. A symbol that is used but neither defined nor produced is an error, and so is a
//!   non-terminal in a terminal production (`=>`). A non-terminal without `=>` is erased at the end.
//! * Successor modules are names (`A`, `Apex(x, 2)`, separated by spaces or punctuation) or the turtle symbols
//!   (heading = local +Y, the primitives' axis): `F(l)` cylinder of radius = width and height `l`, then move `l`
//!   (default 1); `f(l)` move; `+(a)`/`-(a)` rotate ±a about Z; `&(a)`/`^(a)` ±a about X; `\(a)`/`/(a)` ±a about
//!   Y (default `angle`); `|` turn 180° about Z; `[` `]` push/pop the turtle; `!(w)` set the width, `!` multiply
//!   it by 0.7; `'(r,g,b)` set the colour, `'` advance the colour index (starting at 0) and take that palette entry
//!   (1-based, clamped to the last). Width and colour index are turtle state: `]` restores them.
//! * A `module` body is a list of the node calls of [`crate::nodes`] (`material`, `translate`, `cone`, `leaf`, …)
//!   whose expressions read the module's formals and the species params. It is drawn in the turtle's frame and
//!   leaves the turtle unchanged (it is a separator). Module bodies may not draw random numbers: randomness
//!   belongs in the arguments, where it is drawn in the derivation's RNG context.
//! * Productions of one symbol are tried in order: the first whose condition holds applies, or — if any of them
//!   carries a weight — one is chosen among those whose condition holds with probability proportional to its
//!   weight (default 1). If none applies the module is left unchanged.
//! * Expressions are those of [`crate::expr`]: the predecessor's formals, the species params, `detail`.
//! * Limits: [`MAX_SYMBOLS`] symbols, [`MAX_PRODUCTIONS`] productions, [`MAX_FORMALS`] formals per module,
//!   [`MAX_SUCCESSOR_LEN`] modules per successor, [`MAX_BRACKET_NESTING`] nested brackets, [`MAX_CHOOSE`]
//!   productions for a stochastic symbol.
//!
//! # The DCG (seed 001 §3.2)
//!
//! Parameter slots: the species params, `_d` (remaining derivation steps), `_w` and `_c` (width and colour
//! index, [`ParamScope::Turtle`]), one local slot `Sym.formal` per formal of every module. One
//! [`Node::Selection`] per non-terminal with children `[rhs_1 … rhs_n, identity, final]`, selected by
//! `_d <= 0 ? n+1 : choice`. `rhs_i = Group[Calc(_d = _d - 1), successors…]`; a non-terminal successor
//! `B(e…)` is `RecursionSeparator[Calc(B.p… = e…), <B's selection>]` (the cycle); a terminal is
//! `Calc(T.p… = e…)` followed by a link to the symbol's one shared body node; `[…]` is a [`Node::Separator`].
//! The root is `Group[Calc(_d = derive, _w = width, _c = 0), axiom…]`.
//!
//! # The reference
//!
//! [`rewrite`] derives the module string by ordinary parallel rewriting, giving every non-terminal occurrence the
//! RNG context the DCG traversal gives its recursion separator (see [`crate::rng`]); [`interpret`] draws a
//! terminal string with the turtle. The two agree with [`amplify`] of the DCG bit for bit.

use std::collections::{HashMap, HashSet};
use std::ops::Range;

use canopy_protocol::{Expr, Node, NodeId, Op, ParamDecl, ParamScope, SpeciesGraph, limits};

use crate::amplify::{AmplifyError, Budget, Instance, amplify, instance_params};
use crate::diag::{Diagnostic, SourceFile};
use crate::eval::eval;
use crate::expr::{Ast, BinOp, compile, parse_expr};
use crate::nodes::{NODE_CALLS, parse_args, parse_node_call};
use crate::primitive::PrimitiveStream;
use crate::rng::{Context, InstanceRng, ROOT_KEY, child_key};
use crate::text::{Cursor, ParseError, is_ident_start};

/// Most user symbols (non-terminals and modules) in one L-system.
pub const MAX_SYMBOLS: usize = 256;
/// Most productions (`->` and `=>`) in one L-system.
pub const MAX_PRODUCTIONS: usize = 256;
/// Most formal parameters of one module.
pub const MAX_FORMALS: usize = 64;
/// Most modules in one successor (brackets included).
pub const MAX_SUCCESSOR_LEN: usize = 4096;
/// Deepest nesting of `[ ]` in one successor.
pub const MAX_BRACKET_NESTING: usize = 256;
/// Most `param` declarations (the `angle` directive included).
pub const MAX_SPECIES_PARAMS: usize = 256;
/// Most palette entries.
pub const MAX_PALETTE: usize = 64;
/// Most productions of one stochastic symbol (the weights of one `choose`).
pub const MAX_CHOOSE: usize = limits::MAX_CHOOSE;
/// Longest symbol, formal or parameter name, in bytes (so `Sym.formal` fits a parameter name).
pub const MAX_IDENT_LEN: usize = 63;
/// Largest source accepted, in bytes.
pub const MAX_SOURCE_LEN: usize = 1 << 20;
/// Most parallel rewriting steps of the reference derivation.
pub const MAX_REWRITE_STEPS: u32 = 1024;
/// Longest module string of the reference derivation.
pub const MAX_STRING_LEN: usize = 1 << 21;

/// Width multiplier of `!` without an argument.
pub const WIDTH_DECREASE: f32 = 0.7;
/// Initial line width when no `width` directive is given.
pub const DEFAULT_WIDTH: f32 = 0.05;

/// Index of a symbol in [`LSystem::symbols`].
pub type SymbolId = u16;

/// The turtle's built-in symbols; each is its own terminal (`!` and `'` come in two arities).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Turtle {
    /// `F(l)`: draw a cylinder of the current width and height `l`, then move `l` along +Y.
    Forward,
    /// `f(l)`: move `l` along +Y.
    Move,
    /// `+(a)`: rotate by `a` degrees about Z.
    TurnLeft,
    /// `-(a)`: rotate by `-a` degrees about Z.
    TurnRight,
    /// `&(a)`: rotate by `a` degrees about X.
    PitchDown,
    /// `^(a)`: rotate by `-a` degrees about X.
    PitchUp,
    /// `\(a)`: rotate by `a` degrees about Y (the heading).
    RollLeft,
    /// `/(a)`: rotate by `-a` degrees about Y.
    RollRight,
    /// `|`: rotate 180 degrees about Z.
    TurnAround,
    /// `!(w)`: set the width.
    SetWidth,
    /// `!`: multiply the width by [`WIDTH_DECREASE`].
    ScaleWidth,
    /// `'(r, g, b)`: set the material colour.
    SetColor,
    /// `'`: advance the colour index and take that palette entry.
    NextColor,
    /// `[`: save the turtle.
    Push,
    /// `]`: restore the turtle.
    Pop,
}

impl Turtle {
    /// Every turtle symbol; the first symbols of every [`LSystem`] are these, in this order.
    pub const ALL: [Turtle; 15] = [
        Turtle::Forward,
        Turtle::Move,
        Turtle::TurnLeft,
        Turtle::TurnRight,
        Turtle::PitchDown,
        Turtle::PitchUp,
        Turtle::RollLeft,
        Turtle::RollRight,
        Turtle::TurnAround,
        Turtle::SetWidth,
        Turtle::ScaleWidth,
        Turtle::SetColor,
        Turtle::NextColor,
        Turtle::Push,
        Turtle::Pop,
    ];

    /// How the symbol is written.
    pub const fn text(self) -> &'static str {
        match self {
            Turtle::Forward => "F",
            Turtle::Move => "f",
            Turtle::TurnLeft => "+",
            Turtle::TurnRight => "-",
            Turtle::PitchDown => "&",
            Turtle::PitchUp => "^",
            Turtle::RollLeft => "\\",
            Turtle::RollRight => "/",
            Turtle::TurnAround => "|",
            Turtle::SetWidth | Turtle::ScaleWidth => "!",
            Turtle::SetColor | Turtle::NextColor => "'",
            Turtle::Push => "[",
            Turtle::Pop => "]",
        }
    }

    /// The names of its formal parameters.
    pub const fn formals(self) -> &'static [&'static str] {
        match self {
            Turtle::Forward | Turtle::Move => &["l"],
            Turtle::TurnLeft
            | Turtle::TurnRight
            | Turtle::PitchDown
            | Turtle::PitchUp
            | Turtle::RollLeft
            | Turtle::RollRight => &["a"],
            Turtle::SetWidth => &["w"],
            Turtle::SetColor => &["r", "g", "b"],
            Turtle::TurnAround | Turtle::ScaleWidth | Turtle::NextColor | Turtle::Push | Turtle::Pop => &[],
        }
    }

    /// The symbol's id in every [`LSystem`].
    pub fn id(self) -> SymbolId {
        Turtle::ALL.iter().position(|&t| t == self).expect("every turtle symbol is in ALL") as SymbolId
    }
}

/// What a symbol is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SymbolKind {
    /// A built-in turtle symbol (terminal).
    Turtle(Turtle),
    /// A `module`-defined terminal.
    Module,
    /// A symbol with productions.
    NonTerminal,
}

/// One module of a successor: a symbol and its argument expressions (one per formal; turtle defaults filled in).
#[derive(Clone, Debug, PartialEq)]
pub struct Successor {
    /// The symbol.
    pub symbol: SymbolId,
    /// One expression per formal of the symbol.
    pub args: Vec<Expr>,
}

/// A symbol of the alphabet, with what the DCG made of it.
#[derive(Clone, Debug, PartialEq)]
pub struct Symbol {
    /// As written.
    pub name: String,
    /// Turtle, module or non-terminal.
    pub kind: SymbolKind,
    /// The parameter slots of its formals.
    pub formals: Vec<u16>,
    /// A terminal's shared body node (none for `[`, `]`, or a turtle symbol the L-system does not use).
    pub body: Option<NodeId>,
    /// Primitives one occurrence of a terminal emits.
    pub primitives: usize,
    /// A non-terminal's selection node.
    pub selection: Option<NodeId>,
    /// A non-terminal's selection expression (also in the selection node): `n` productions, then identity (`n`)
    /// and final (`n + 1`).
    pub select: Option<Expr>,
    /// A non-terminal's productions' successors, in order.
    pub productions: Vec<Vec<Successor>>,
    /// A non-terminal's terminal (`=>`) successors.
    pub terminal: Vec<Successor>,
}

impl Symbol {
    /// A symbol with no formals, body, productions or selection node yet.
    fn blank(name: &str, kind: SymbolKind) -> Symbol {
        Symbol {
            name: name.to_string(),
            kind,
            formals: Vec::new(),
            body: None,
            primitives: 0,
            selection: None,
            select: None,
            productions: Vec::new(),
            terminal: Vec::new(),
        }
    }
}

/// A parsed and compiled L-system: the DCG and what the reference rewriter needs.
#[derive(Clone, Debug, PartialEq)]
pub struct LSystem {
    /// The compiled species graph (valid).
    pub graph: SpeciesGraph,
    /// The alphabet: [`Turtle::ALL`] first, then modules and non-terminals in order of appearance.
    pub symbols: Vec<Symbol>,
    /// The axiom.
    pub axiom: Vec<Successor>,
    /// The derivation depth expression.
    pub derive: Expr,
    /// The initial width expression.
    pub width: Expr,
    /// Slot of `_d`, the remaining derivation steps.
    pub depth_slot: u16,
    /// Slot of `_w`, the width.
    pub width_slot: u16,
    /// Slot of `_c`, the colour index.
    pub color_slot: u16,
}

impl LSystem {
    /// Parse and compile an L-system. Returns it if there were no errors, and every diagnostic found.
    pub fn parse(src: &SourceFile) -> (Option<LSystem>, Vec<Diagnostic>) {
        let mut errors = Vec::new();
        let lsys = parse_inner(src, &mut errors);
        errors.sort_by_key(|e| (e.span.start, e.span.end));
        let diags: Vec<Diagnostic> = errors.into_iter().map(|e| src.diag(e.span, e.message)).collect();
        if diags.is_empty() { (lsys, diags) } else { (None, diags) }
    }

    /// The id of a user symbol (module or non-terminal) by name.
    pub fn symbol(&self, name: &str) -> Option<SymbolId> {
        self.symbols
            .iter()
            .position(|s| s.name == name && !matches!(s.kind, SymbolKind::Turtle(_)))
            .map(|i| i as SymbolId)
    }

    /// Primitives a terminal string emits when interpreted (the sum of its terminals' body primitives).
    pub fn primitive_count(&self, string: &[ModuleOcc]) -> usize {
        string.iter().map(|m| self.symbols[m.symbol as usize].primitives).sum()
    }
}

/// Parse an L-system into its species graph (see the module docs). Returns the graph if there were no errors,
/// and every diagnostic found.
pub fn parse_lsystem(src: &SourceFile) -> (Option<SpeciesGraph>, Vec<Diagnostic>) {
    let (l, d) = LSystem::parse(src);
    (l.map(|l| l.graph), d)
}

// ---------------------------------------------------------------------------------------------------------------
// Pass 1: lines to items.

struct RawSucc {
    name: String,
    span: Range<usize>,
    args: Option<(Vec<Ast>, Range<usize>)>,
}

struct Production {
    pred: String,
    pred_span: Range<usize>,
    formals: Vec<(String, Range<usize>)>,
    cond: Option<Ast>,
    terminal: bool,
    succ: Vec<RawSucc>,
    weight: Option<Ast>,
}

enum Item {
    Name(String, Range<usize>),
    Derive(Ast, Range<usize>),
    Width(Ast, Range<usize>),
    Param(String, Range<usize>, Ast),
    Palette(Vec<[Ast; 3]>, Range<usize>),
    Module { name: String, span: Range<usize>, formals: Vec<(String, Range<usize>)>, body: usize },
    Axiom(Vec<RawSucc>, Range<usize>),
    Production(Production),
}

const KEYWORDS: [&str; 8] = ["lsystem", "derive", "angle", "width", "param", "palette", "module", "axiom"];
const RESERVED: [&str; 4] = ["detail", "pi", "true", "false"];
const TURTLE_CHARS: &str = "+-&^\\/|!'[]";

fn at_line_end(cur: &mut Cursor<'_>) -> bool {
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
            return Err(cur.unexpected("a module (a name or one of `+ - & ^ \\ / | ! ' [ ]`)"));
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
    let formals = if cur.peek() == Some('(') { formal_list(cur)? } else { Vec::new() };
    let cond = if cur.eat(":") { Some(parse_expr(cur)?) } else { None };
    cur.skip_trivia();
    let arrow = cur.pos..cur.pos + 2;
    let terminal = if cur.eat("->") {
        false
    } else if cur.eat("=>") {
        true
    } else {
        return Err(cur.unexpected("`->` or `=>`"));
    };
    if terminal && cond.is_some() {
        return Err(ParseError::new(arrow, "a terminal production (`=>`) takes no condition"));
    }
    let succ = successors(cur)?;
    cur.skip_trivia();
    let colon = cur.pos..cur.pos + 1;
    let weight = if cur.eat(":") {
        if terminal {
            return Err(ParseError::new(colon, "a terminal production (`=>`) takes no probability"));
        }
        Some(parse_expr(cur)?)
    } else {
        None
    };
    Ok(Item::Production(Production { pred: pred.to_string(), pred_span, formals, cond, terminal, succ, weight }))
}

fn parse_line(cur: &mut Cursor<'_>) -> Result<Option<Item>, ParseError> {
    if at_line_end(cur) {
        return Ok(None);
    }
    let Some((word, span)) = cur.ident() else {
        return Err(cur.unexpected("a directive (`lsystem`, `derive`, `angle`, `width`, `param`, `palette`, `module`, `axiom:`) or a production `A(x) -> …`"));
    };
    let item = match word {
        "lsystem" => {
            let (n, s) = name(cur, "a name")?;
            Item::Name(n, s)
        }
        "derive" => Item::Derive(parse_expr(cur)?, span),
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
        "axiom" => {
            cur.expect(":")?;
            Item::Axiom(successors(cur)?, span)
        }
        _ => production(word, span, cur)?,
    };
    end_of_line(cur)?;
    Ok(Some(item))
}

/// What a line that failed to parse still declares, so its names do not cause follow-up errors.
enum Ghost {
    Symbol(String),
    Param(String),
    Directive(&'static str),
}

fn ghost(src: &str, pos: usize) -> Option<Ghost> {
    let mut cur = Cursor { src, pos, newlines_are_space: false };
    let (word, _) = cur.ident()?;
    Some(match word {
        "module" => Ghost::Symbol(cur.ident()?.0.to_string()),
        "param" => Ghost::Param(cur.ident()?.0.to_string()),
        "angle" => Ghost::Param("angle".to_string()),
        w => match KEYWORDS.iter().find(|&&k| k == w) {
            Some(k) => Ghost::Directive(k),
            None => Ghost::Symbol(w.to_string()),
        },
    })
}

// ---------------------------------------------------------------------------------------------------------------
// Pass 2: items to the DCG.

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

struct Builder {
    nodes: Vec<Node>,
    calcs: HashMap<String, NodeId>,
}

impl Builder {
    fn push(&mut self, n: Node) -> NodeId {
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

fn parse_inner(src: &SourceFile, errors: &mut Vec<ParseError>) -> Option<LSystem> {
    let text = src.text.as_str();
    if text.len() > MAX_SOURCE_LEN {
        errors.push(ParseError::new(0..0, format!("source of {} bytes exceeds {MAX_SOURCE_LEN}", text.len())));
        return None;
    }
    // Pass 1: every line on its own, so one bad line does not hide the others.
    let mut items = Vec::new();
    let mut ghosts = Vec::new();
    let mut pos = 0;
    while pos < text.len() {
        let end = text[pos..].find('\n').map_or(text.len(), |i| pos + i);
        let mut cur = Cursor { src: text, pos, newlines_are_space: false };
        match parse_line(&mut cur) {
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
            Turtle::NextColor => {
                let Some(palette) = self.palette.clone() else {
                    if !self.palette_broken {
                        self.err(span.clone(), "`'` without arguments needs a `palette`");
                    }
                    return None;
                };
                // Channel k: `_c <= 1 ? p1 : _c <= 2 ? p2 : … : p_last`.
                let mut channels = Vec::new();
                for k in 0..3 {
                    let mut ast = palette[palette.len() - 1][k].clone();
                    for i in (0..palette.len() - 1).rev() {
                        let test = Ast::bin(BinOp::Le, Ast::var("$c"), Ast::Num((i + 1) as f32));
                        ast = Ast::cond(test, palette[i][k].clone(), ast);
                    }
                    let internal = [("$c", c)];
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
                let advance = Expr { ops: vec![Op::Param(c), Op::Const(1.0), Op::Add] };
                let calc = self.b.push(Node::Calculation(vec![(c, advance)]));
                let [r, g, b] = <[Expr; 3]>::try_from(channels).expect("three channels");
                let mat = self.b.push(Node::Material([r, g, b]));
                Node::Group(vec![calc, mat])
            }
            Turtle::Push | Turtle::Pop => unreachable!("brackets have no body"),
        };
        let body = self.b.push(body);
        self.symbols[id].formals = formals;
        self.symbols[id].body = Some(body);
        Some(())
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
        let internal_d = [("$d", self.d)];
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
        let fin = self.emit(&terminal);
        children.push(self.b.container(Node::Group, fin));
        self.b.nodes[selection as usize] = Node::Selection { expr: select.clone(), children };
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

// ---------------------------------------------------------------------------------------------------------------
// The string-rewriting reference.

/// One module occurrence of a derived string.
#[derive(Clone, Debug, PartialEq)]
pub struct ModuleOcc {
    /// The symbol.
    pub symbol: SymbolId,
    /// Its evaluated arguments.
    pub args: Vec<f32>,
    /// RNG context key: a non-terminal's own context (where it will be rewritten); for a terminal, the context
    /// its arguments were drawn in.
    pub key: u64,
    /// The next word of that context.
    pub counter: u64,
}

/// Why the reference derivation stopped.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum RewriteError {
    /// The instance is not valid for the species, or amplifying the interpretation failed.
    #[error(transparent)]
    Amplify(#[from] AmplifyError),
    /// The string grew past [`MAX_STRING_LEN`].
    #[error("derived string longer than {0} modules")]
    TooLong(usize),
    /// The derivation did not end within [`MAX_REWRITE_STEPS`] steps.
    #[error("derivation did not end within {0} steps")]
    TooManySteps(u32),
    /// A string to interpret has a non-terminal or unbalanced brackets.
    #[error("not a drawable terminal string: {0}")]
    NotTerminal(String),
}

struct Root {
    rng: InstanceRng,
    env: Vec<f32>,
    counter: u64,
    derive: f32,
    width: f32,
}

/// The instance's parameters and the root calculation `_d = derive, _w = width`, in the root RNG context.
fn root(ls: &LSystem, instance: &Instance) -> Result<Root, RewriteError> {
    let mut rng = InstanceRng::new(instance.seed);
    let (env, counter) = instance_params(&ls.graph, instance, &mut rng)?;
    let detail = f32::from(instance.detail);
    let mut ctx = Context { rng: &mut rng, key: ROOT_KEY, counter };
    let derive = eval(&ls.derive, &env, detail, &mut ctx);
    let width = eval(&ls.width, &env, detail, &mut ctx);
    let counter = ctx.counter;
    Ok(Root { rng, env, counter, derive, width })
}

/// The state of a reference derivation: the parameter values in effect and the instance RNG.
struct Rewriter<'a> {
    ls: &'a LSystem,
    env: Vec<f32>,
    detail: f32,
    rng: InstanceRng,
}

impl Rewriter<'_> {
    /// Evaluate a successor list in the context `(key, *counter)`: terminals draw their arguments there; each
    /// non-terminal opens a child context, draws its arguments in it, and keeps it.
    fn expand(
        &mut self,
        succ: &[Successor],
        key: u64,
        counter: &mut u64,
        out: &mut Vec<ModuleOcc>,
    ) -> Result<(), RewriteError> {
        if out.len() + succ.len() > MAX_STRING_LEN {
            return Err(RewriteError::TooLong(MAX_STRING_LEN));
        }
        for s in succ {
            let nonterminal = self.ls.symbols[s.symbol as usize].kind == SymbolKind::NonTerminal;
            let mut ctx = if nonterminal {
                let child = child_key(key, *counter);
                *counter += 1;
                Context { rng: &mut self.rng, key: child, counter: 0 }
            } else {
                Context { rng: &mut self.rng, key, counter: *counter }
            };
            let args = s.args.iter().map(|e| eval(e, &self.env, self.detail, &mut ctx)).collect();
            let (k, c) = (ctx.key, ctx.counter);
            if !nonterminal {
                *counter = c;
            }
            out.push(ModuleOcc { symbol: s.symbol, args, key: k, counter: c });
        }
        Ok(())
    }
}

/// Derive the terminal string of `ls` for `instance` by parallel rewriting (see the module docs). The remaining
/// depth starts at the `derive` expression's value, or at `steps` if given (the expression is still evaluated,
/// so the draws stay aligned); every step rewrites every non-terminal and lowers it by one; once it is `<= 0`
/// every non-terminal takes its terminal production (or is erased).
pub fn rewrite(ls: &LSystem, instance: &Instance, steps: Option<u32>) -> Result<Vec<ModuleOcc>, RewriteError> {
    if let Some(s) = steps
        && s > MAX_REWRITE_STEPS
    {
        return Err(RewriteError::TooManySteps(MAX_REWRITE_STEPS));
    }
    let Root { rng, env, counter, derive, width } = root(ls, instance)?;
    let mut r = Rewriter { ls, env, detail: f32::from(instance.detail), rng };
    let mut d = steps.map_or(derive, |s| s as f32);
    r.env[ls.depth_slot as usize] = d;
    r.env[ls.width_slot as usize] = width;
    r.env[ls.color_slot as usize] = 0.0;
    let mut string = Vec::new();
    let mut counter = counter;
    r.expand(&ls.axiom, ROOT_KEY, &mut counter, &mut string)?;
    let mut step = 0;
    while string.iter().any(|m| ls.symbols[m.symbol as usize].kind == SymbolKind::NonTerminal) {
        // One more pass than the limit: the last one only substitutes terminal productions.
        if step > MAX_REWRITE_STEPS {
            return Err(RewriteError::TooManySteps(MAX_REWRITE_STEPS));
        }
        step += 1;
        let mut next = Vec::with_capacity(string.len());
        for m in string {
            let sym = &ls.symbols[m.symbol as usize];
            if sym.kind != SymbolKind::NonTerminal {
                next.push(m);
                continue;
            }
            for (&slot, &v) in sym.formals.iter().zip(&m.args) {
                r.env[slot as usize] = v;
            }
            r.env[ls.depth_slot as usize] = d;
            // The selection node's expression, in the occurrence's own context.
            let select = sym.select.as_ref().expect("non-terminals have a selection expression");
            let mut ctx = Context { rng: &mut r.rng, key: m.key, counter: m.counter };
            let v = eval(select, &r.env, r.detail, &mut ctx);
            let mut counter = ctx.counter;
            let n = sym.productions.len();
            let i = if v.is_nan() { 0 } else { (v as i64).clamp(0, n as i64 + 1) as usize };
            if i <= n {
                r.env[ls.depth_slot as usize] = d - 1.0;
            }
            if i < n {
                r.expand(&sym.productions[i], m.key, &mut counter, &mut next)?;
            } else if i == n {
                // Identity: the same module, called again with its own values.
                let child = child_key(m.key, counter);
                next.push(ModuleOcc { symbol: m.symbol, args: m.args, key: child, counter: 0 });
            } else {
                r.expand(&sym.terminal, m.key, &mut counter, &mut next)?;
            }
            if next.len() > MAX_STRING_LEN {
                return Err(RewriteError::TooLong(MAX_STRING_LEN));
            }
        }
        string = next;
        d -= 1.0;
    }
    Ok(string)
}

/// Draw a terminal string with the turtle: a flat graph of the terminals' bodies, each after a calculation of its
/// argument values, `[ ]` as separators, amplified for `instance` within `budget`.
pub fn interpret(
    ls: &LSystem,
    instance: &Instance,
    string: &[ModuleOcc],
    budget: &Budget,
) -> Result<PrimitiveStream, RewriteError> {
    let r = root(ls, instance)?;
    let mut b = Builder { nodes: ls.graph.nodes.clone(), calcs: HashMap::new() };
    let init = b.push(Node::Calculation(vec![
        (ls.depth_slot, Expr::constant(r.derive)),
        (ls.width_slot, Expr::constant(r.width)),
        (ls.color_slot, Expr::constant(0.0)),
    ]));
    let mut stack: Vec<Vec<NodeId>> = vec![vec![init]];
    for m in string {
        let sym = ls
            .symbols
            .get(m.symbol as usize)
            .ok_or_else(|| RewriteError::NotTerminal(format!("symbol {} does not exist", m.symbol)))?;
        match sym.kind {
            SymbolKind::Turtle(Turtle::Push) => stack.push(Vec::new()),
            SymbolKind::Turtle(Turtle::Pop) => {
                if stack.len() == 1 {
                    return Err(RewriteError::NotTerminal("unmatched `]`".to_string()));
                }
                let inner = stack.pop().expect("checked");
                let sep = b.push(Node::Separator(inner));
                stack.last_mut().expect("checked").push(sep);
            }
            SymbolKind::NonTerminal => {
                return Err(RewriteError::NotTerminal(format!("non-terminal `{}`", sym.name)));
            }
            SymbolKind::Turtle(_) | SymbolKind::Module => {
                let Some(body) = sym.body else {
                    return Err(RewriteError::NotTerminal(format!("`{}` has no body", sym.name)));
                };
                if m.args.len() != sym.formals.len() {
                    return Err(RewriteError::NotTerminal(format!("`{}` with {} arguments", sym.name, m.args.len())));
                }
                let top = stack.last_mut().expect("at least the outer list");
                if !sym.formals.is_empty() {
                    let assign = sym.formals.iter().zip(&m.args).map(|(&s, &v)| (s, Expr::constant(v))).collect();
                    b.nodes.push(Node::Calculation(assign));
                    top.push((b.nodes.len() - 1) as NodeId);
                }
                top.push(body);
            }
        }
    }
    if stack.len() != 1 {
        return Err(RewriteError::NotTerminal("unclosed `[`".to_string()));
    }
    let children = stack.pop().expect("checked");
    let root_id = b.push(Node::Group(children));
    let flat =
        SpeciesGraph { name: ls.graph.name.clone(), params: ls.graph.params.clone(), nodes: b.nodes, root: root_id };
    Ok(amplify(&flat, instance, budget)?)
}

/// The reference primitive stream: [`rewrite`] with the `derive` depth, then [`interpret`].
pub fn reference_stream(ls: &LSystem, instance: &Instance, budget: &Budget) -> Result<PrimitiveStream, RewriteError> {
    let string = rewrite(ls, instance, None)?;
    interpret(ls, instance, &string, budget)
}
