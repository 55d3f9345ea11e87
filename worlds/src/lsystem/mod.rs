//! Parametric L-systems (`.lsys`) and their translation into a species DCG (seed 001 §3.1–3.2), plus the
//! string-rewriting reference derivation the translation is tested against.
//!
//! # The format
//!
//! Line oriented; `#` starts a comment (except `#define`). Directives and productions, in any order:
//!
//! ```text
//! lsystem Bush                 # name (optional; default: the file name without extension)
//! derive 6 - detail            # derivation depth (required): an expression of the params and `detail`
//! angle 22.5                   # default turning angle in degrees; the same as `param angle = 22.5`
//! width 0.1                    # initial line width (default 0.05)
//! param len = uniform(0.8, 1.2)  # a species parameter; its default may draw and read earlier params
//! #define LEAF 0.3             # cpfg's constants: the same as `param LEAF = 0.3`
//! palette (0.4,0.3,0.2) (0.2,0.6,0.2)   # colours for `'`, `;` and `,`
//! maxdepth 2048                # nesting the traversal must allow (default 1024, at most 8192), see below
//! module L(s) = material(0.2, 0.7, 0.2) leaf((0,0,0), (0.1*s, 0.5*s, 0), (0, s, 0), (-0.1*s, 0.5*s, 0))
//! axiom: A(1) B
//! A(x) : x > 0.5 -> F(x) [ +(angle) A(x*0.7) ] [ -(angle) A(x*0.7) ]    # condition after `:`
//! A(x) -> F(x) L(1)
//! B -> F B : 0.3               # stochastic: weight after the successor
//! B --> (0.7) f B              # or on the arrow, as ABOP writes it
//! A(x) => L(x)                 # terminal production, used once the depth is reached
//! interpretation:              # (or `homomorphism:`) rules applied only when the final string is drawn
//! B --> F(0.1) $ ;             # `-->` is L-Py's `->`
//! production:                  # back to productions
//! ignore: + -                  # L-Py's; no effect here (no context is matched)
//! endlsystem                   # L-Py's end of the rules: nothing after it is read
//! ```
//!
//! * L-Py's spellings `Axiom:`, `derivation length: N`, `-->` and the section headers `production:`,
//!   `interpretation:`, `homomorphism:` are accepted. What a DCG cannot express is an error that says why:
//!   context-sensitive productions (`A < B > C -> …`: the traversal sees no neighbours, seed 001 §3.2 compiles
//!   context-free L-systems) and `decomposition:` sections (rules applied again and again within one step).
//! * **L-Py files.** `endlsystem` ends the rules: what follows is L-Py's Python (the editor's
//!   `__initialiseContext__` with its materials and options) and is not read. `ignore: …` and `consider: …` are
//!   accepted and have no effect: they only choose which modules L-Py's context matching skips, and no context is
//!   matched here (the diagnostics have no warning level to say so at the line). `A(x) : * -> …` (cpfg's and
//!   ABOP's `*`, "always") is a production without a condition. Python is not run: an assignment such as
//!   `R = 1.456`, `import`, `from`, `def`, `class`, `if`, `extern(…)` and the like (with their indented bodies and
//!   bracketed continuation lines), and a production with a Python body (`A(x) :` followed by `produce …` or
//!   indented lines) are each one error that says so and points to `#define R 1.456` / `param R = 1.456` (or to
//!   productions with conditions and probabilities); the name they would define is not reported again where it
//!   is used. L-Py writes a random choice in Python (`if random() < p: produce …`); here it is several
//!   productions of one module with probabilities.
//! * **L-Py's defaults.** Without `angle` (or `param angle`), `+ - & ^ \ /` without an argument turn by
//!   [`LPY_DEFAULT_ANGLE`] (60°, the `angle_increment` of L-Py's turtle), a constant rather than a parameter.
//!   Without a `palette`, `;`, `,`, `'` and `;(i)`/`,(i)` use L-Py's materials [`LPY_MATERIALS`] (PlantGL's
//!   `Color_0` … `Color_6`: grey, brown, green, red, yellow, blue, purple, as diffuse colours ambient × diffuse)
//!   as L-Py's turtle does: it starts at material [`LPY_START_COLOR`] (brown, set at the root), `;` and `'` go up
//!   to 6 at most, `,` down to 0 at least, `;(i)` sets `i` if it is from 0 to 6 and is ignored otherwise. A file
//!   that uses none of them keeps the species' default colour.
//! * **Diagnostics.** One per mistake, at the token that is wrong (`file:line:col`): a line that fails still
//!   declares what it names (a `param`, `#define` or `module`, a rewritten symbol, `derive`, `axiom`, a section),
//!   so its uses are not reported again; a misspelt directive or section header (one edit from one) is named as
//!   such ("unknown directive `edrive`: did you mean `derive`?") and declares what the directive would have.
//! * **Non-terminals** are the symbols with productions (`->` or `=>`); **terminals** are the turtle symbols,
//!   `module`-defined symbols and symbols with only an interpretation rule. A symbol that is used but neither
//!   defined nor produced is an error, and so is a non-terminal in a terminal production (`=>`). A non-terminal
//!   without `=>` is erased at the end, unless it has an interpretation rule.
//! * **Interpretation rules** `X(p…) -> successor` (in an `interpretation:` or `homomorphism:` section) say how
//!   `X` is drawn; they are not rewritten further. The successor holds turtle symbols and `module`s only (no
//!   symbol with an interpretation rule of its own) and draws no random numbers; no condition, weight or `=>`.
//!   A symbol with only an interpretation rule is a terminal; a non-terminal with one (and no `=>`) keeps the
//!   occurrences left when the depth is reached, and they are drawn by the rule.
//! * Successor modules are names (`A`, `Apex(x, 2)`, separated by spaces or punctuation) or the turtle symbols (heading
//!   = local +Y, the primitives' axis): `F(l)` cylinder of radius = width and height `l`, then move `l` (default 1);
//!   `f(l)` move; `+(a)`/`-(a)` rotate ±a about Z; `&(a)`/`^(a)` ±a about X; `\(a)`/`/(a)` ±a about Y (default `angle`,
//!   or L-Py's 60° without one); `|` turn 180° about Z; `[` `]` push/pop the turtle; `!(w)` set the width, `!` multiply
//!   it by 0.7; `'(r,g,b)` set the colour, `'` advance the colour index (starting at 0) and take that palette entry
//!   (1-based, clamped to the last); `;` is the same as `'`, `,` lowers the index (not below 1) and takes that entry,
//!   `;(i)` and `,(i)` set it to `i` (without a `palette`: L-Py's materials, see below). Width and colour index are
//!   turtle state: `]` restores them. `$` rolls the turtle about its heading so that its left vector (-X) is horizontal
//!   (ABOP §1.6; up = the species' +Y; no roll while the heading is vertical). `%` cuts the branch: what follows it up
//!   to the `]` that closes its branch (or the end of the string) is removed (the cut of cpfg and L-Py).
//! * A `module` body is a list of the node calls of [`crate::nodes`] (`material`, `translate`, `cone`, `leaf`, …)
//!   whose expressions read the module's formals and the species params. It is drawn in the turtle's frame and
//!   leaves the turtle unchanged (it is a separator). Module bodies may not draw random numbers: randomness
//!   belongs in the arguments, where it is drawn in the derivation's RNG context.
//! * Productions of one symbol are tried in order: the first whose condition holds applies, or — if any of them
//!   carries a weight (`A -> succ : w`, or on the arrow, `A -> (w) succ`) — one is chosen among those whose
//!   condition holds with probability proportional to its weight (default 1). If none applies the module is left
//!   unchanged.
//! * Expressions are those of [`crate::expr`]: the predecessor's formals, the species params, `detail`.
//! * Limits: [`MAX_SYMBOLS`] symbols, [`MAX_PRODUCTIONS`] productions and interpretation rules, [`MAX_FORMALS`]
//!   formals per module, [`MAX_SUCCESSOR_LEN`] modules per successor, [`MAX_BRACKET_NESTING`] nested brackets,
//!   [`MAX_CHOOSE`] productions for a stochastic symbol.
//! * **Depth.** Every derivation step nests one call (plus the brackets around it) deeper in the traversal, which
//!   allows the budget's `max_depth` (1024 by default). `maxdepth N` asks for more, up to
//!   [`MAX_DEPTH_LIMIT`]; the graph carries it as the parameter
//!   [`DEPTH_PARAM`](crate::amplify::DEPTH_PARAM), so every amplifier honours it. [`LSystem::amplify`] reports a
//!   derivation that still nests too deep with its depth and the production that nests deepest per step.
//!
//! # The DCG (seed 001 §3.2)
//!
//! Parameter slots: the species params, `_d` (remaining derivation steps), `_w` and `_c` (width and colour
//! index, [`ParamScope::Turtle`]); if the file uses them, `_x` (the cut flag, turtle), `_X.x … _Z.z` (the
//! turtle's frame for `$`, turtle) and `_maxdepth`; then one local slot `Sym.formal` per formal of every module. One
//! [`Node::Selection`] per non-terminal with children `[rhs_1 … rhs_n, identity, final]`, selected by
//! `_d <= 0 ? n+1 : choice`. `rhs_i = Group[Calc(_d = _d - 1), successors…]`; a non-terminal successor
//! `B(e…)` is `RecursionSeparator[Calc(B.p… = e…), <B's selection>]` (the cycle); a terminal is
//! `Calc(T.p… = e…)` followed by a link to the symbol's one shared body node; `[…]` is a [`Node::Separator`].
//! The root is `Group[Calc(_d = derive, _w = width, _c = 0), axiom…]`. A symbol with an interpretation rule and
//! no productions has the rule's successor nodes as its shared body; a non-terminal's interpretation rule is its
//! `final` child.
//!
//! `%` is `Calc(_x = 1)`; `_x` is turtle state, so it flows out of calls and only the `]` that closes the branch
//! restores it. With `%` in the file every terminal body is `Selection(_x)[body, Group[]]` and every selection
//! node's expression is `_x > 0 ? n+2 : …` with an empty child `n+2`: after a cut nothing is drawn or expanded,
//! while the argument calculations still draw, so the RNG stays aligned with the reference, which removes the
//! branch from the string after every step. With `$` in the file every rotation body also turns the frame slots
//! (`libm` sines and cosines), and `$` is a `Matrix` roll about Y computed from them.
//!
//! # The reference
//!
//! [`rewrite`] derives the module string by ordinary parallel rewriting, giving every non-terminal occurrence the
//! RNG context the DCG traversal gives its recursion separator (see [`crate::rng`]) and cutting at every `%`;
//! [`interpret`] applies the interpretation rules and draws the terminal string with the turtle. The two agree
//! with [`amplify`] of the DCG bit for bit.
//!
//! [`ParamScope::Turtle`]: canopy_protocol::ParamScope::Turtle
//! [`Node::Selection`]: canopy_protocol::Node::Selection
//! [`Node::Separator`]: canopy_protocol::Node::Separator
//! [`amplify`]: crate::amplify::amplify

use canopy_protocol::{Expr, NodeId, SpeciesGraph, limits};

use crate::amplify::{AmplifyError, Budget, Instance, MAX_DEPTH_LIMIT, amplify};
use crate::diag::{Diagnostic, SourceFile};
use crate::primitive::PrimitiveStream;

mod compile;
mod lpy;
mod parse;
mod reference;

pub use lpy::{LPY_DEFAULT_ANGLE, LPY_MATERIALS, LPY_START_COLOR};
pub use reference::{ModuleOcc, RewriteError, interpret, reference_stream, rewrite};

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
pub const MAX_REWRITE_STEPS: u32 = MAX_DEPTH_LIMIT;
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
    /// `;`: the same as `'` (ABOP's and L-Py's spelling).
    ColorUp,
    /// `,`: lower the colour index (not below 1) and take that palette entry.
    ColorDown,
    /// `;(i)` or `,(i)`: set the colour index to `i` and take that palette entry.
    SetColorIndex,
    /// `$`: roll about the heading so that the left vector is horizontal (ABOP §1.6).
    RollToHorizontal,
    /// `%`: cut the rest of the branch, up to its closing `]` (the cut of cpfg and L-Py).
    Cut,
    /// `[`: save the turtle.
    Push,
    /// `]`: restore the turtle.
    Pop,
}

impl Turtle {
    /// Every turtle symbol; the first symbols of every [`LSystem`] are these, in this order.
    pub const ALL: [Turtle; 20] = [
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
        Turtle::ColorUp,
        Turtle::ColorDown,
        Turtle::SetColorIndex,
        Turtle::RollToHorizontal,
        Turtle::Cut,
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
            Turtle::ColorUp | Turtle::SetColorIndex => ";",
            Turtle::ColorDown => ",",
            Turtle::RollToHorizontal => "$",
            Turtle::Cut => "%",
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
            Turtle::SetColorIndex => &["i"],
            Turtle::TurnAround
            | Turtle::ScaleWidth
            | Turtle::NextColor
            | Turtle::ColorUp
            | Turtle::ColorDown
            | Turtle::RollToHorizontal
            | Turtle::Cut
            | Turtle::Push
            | Turtle::Pop => &[],
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
    /// The symbol's interpretation rule (`interpretation:` section), if it has one: the terminals it is drawn as.
    /// Applied only when the final string is drawn; a non-terminal with one keeps its last occurrences (it has no
    /// `=>`) and they are drawn by it.
    pub interpretation: Option<Vec<Successor>>,
    /// Where each of a non-terminal's `->` productions is written: `file:line:col` and the line's text.
    pub production_at: Vec<String>,
}

impl Symbol {
    /// A symbol with no formals, body, productions or selection node yet.
    pub(super) fn blank(name: &str, kind: SymbolKind) -> Symbol {
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
            interpretation: None,
            production_at: Vec::new(),
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
    /// Slot of `_x`, set by `%` until the branch ends (only if the L-system uses `%`).
    pub cut_slot: Option<u16>,
    /// Whether `;`, `,` and `'` take L-Py's materials ([`LPY_MATERIALS`], there is no `palette`): then the turtle
    /// starts at material [`LPY_START_COLOR`], as L-Py's does.
    pub lpy_colors: bool,
    /// The nesting of separators and calls the traversal allows this species: the `maxdepth` directive (stored in
    /// the graph as the parameter [`crate::amplify::DEPTH_PARAM`], see [`crate::amplify`]) or the default budget's.
    pub max_depth: u32,
}

impl LSystem {
    /// Parse and compile an L-system. Returns it if there were no errors, and the diagnostics found (at most
    /// [`crate::diag::MAX_DIAGNOSTICS`], then one with a count of the rest).
    pub fn parse(src: &SourceFile) -> (Option<LSystem>, Vec<Diagnostic>) {
        let mut errors = Vec::new();
        let lsys = compile::parse_inner(src, &mut errors);
        errors.sort_by_key(|e| (e.span.start, e.span.end));
        let diags: Vec<Diagnostic> = errors.into_iter().map(|e| src.diag(e.span, e.message)).collect();
        if diags.is_empty() { (lsys, diags) } else { (None, crate::diag::cap(diags)) }
    }

    /// The id of a user symbol (module or non-terminal) by name.
    pub fn symbol(&self, name: &str) -> Option<SymbolId> {
        self.symbols
            .iter()
            .position(|s| s.name == name && !matches!(s.kind, SymbolKind::Turtle(_)))
            .map(|i| i as SymbolId)
    }

    /// Amplify the L-system's graph for `instance` within `budget` (raised to the file's `maxdepth`, see
    /// [`Budget::depth_for`]). A derivation that nests too deep is reported in the file's terms: the derivation
    /// depth, the production that nests deepest per step and how to allow more.
    pub fn amplify(&self, instance: &Instance, budget: &Budget) -> Result<PrimitiveStream, DeriveError> {
        match amplify(&self.graph, instance, budget) {
            Err(AmplifyError::Depth(limit)) => {
                let depth = reference::root(self, instance).map_or(f32::NAN, |r| r.derive);
                Err(DeriveError::TooDeep {
                    depth: if depth.is_finite() { format!("{depth}") } else { "unbounded".to_string() },
                    limit,
                    production: self.deepest_production(),
                })
            }
            r => Ok(r?),
        }
    }

    /// The `->` production that nests deepest per derivation step: the most brackets around a non-terminal it
    /// calls, plus the call itself (ties: the first written).
    fn deepest_production(&self) -> String {
        let (push, pop) = (Turtle::Push.id(), Turtle::Pop.id());
        let mut best: Option<(usize, &str)> = None;
        for sym in &self.symbols {
            for (succ, at) in sym.productions.iter().zip(&sym.production_at) {
                let mut depth = 0usize;
                let mut most = None;
                for s in succ {
                    if s.symbol == push {
                        depth += 1;
                    } else if s.symbol == pop {
                        depth = depth.saturating_sub(1);
                    } else if self.symbols[s.symbol as usize].kind == SymbolKind::NonTerminal {
                        most = most.max(Some(depth + 1));
                    }
                }
                if let Some(m) = most
                    && best.is_none_or(|b| m > b.0)
                {
                    best = Some((m, at));
                }
            }
        }
        match best {
            Some((n, at)) => format!("{at} nests {n} level(s) deeper at every step"),
            None => "the axiom".to_string(),
        }
    }

    /// Primitives a terminal string emits when interpreted (the sum of its terminals' body primitives).
    pub fn primitive_count(&self, string: &[ModuleOcc]) -> usize {
        string.iter().map(|m| self.symbols[m.symbol as usize].primitives).sum()
    }
}

/// Why [`LSystem::amplify`] failed.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum DeriveError {
    /// The derivation nests calls and brackets deeper than the traversal allows.
    #[error(
        "derivation depth {depth} nests calls and brackets deeper than {limit}: {production}; lower `derive`, or \
         raise the limit with `maxdepth N` (at most {max})",
        max = MAX_DEPTH_LIMIT
    )]
    TooDeep {
        /// The `derive` value for the instance.
        depth: String,
        /// The nesting the traversal allowed.
        limit: u32,
        /// Where the production that nests deepest per step is written (`file:line:col` and its text), and how
        /// deep it nests.
        production: String,
    },
    /// Any other amplification error.
    #[error(transparent)]
    Amplify(#[from] AmplifyError),
}

/// Parse an L-system into its species graph (see the module docs). Returns the graph if there were no errors,
/// and every diagnostic found.
pub fn parse_lsystem(src: &SourceFile) -> (Option<SpeciesGraph>, Vec<Diagnostic>) {
    let (l, d) = LSystem::parse(src);
    (l.map(|l| l.graph), d)
}
