//! The string-rewriting reference the DCG is tested against: [`rewrite`] derives the module string by parallel
//! rewriting with the RNG contexts the DCG traversal uses, [`interpret`] draws a terminal string with the turtle.

use std::collections::HashMap;

use canopy_protocol::{Expr, Node, NodeId, SpeciesGraph};

use crate::amplify::{AmplifyError, Budget, Instance, amplify, instance_params};
use crate::eval::eval;
use crate::primitive::PrimitiveStream;
use crate::rng::{Context, InstanceRng, ROOT_KEY, child_key};

use super::compile::Builder;
use super::{
    LPY_MATERIALS, LPY_START_COLOR, LSystem, MAX_REWRITE_STEPS, MAX_STRING_LEN, Successor, SymbolId, SymbolKind, Turtle,
};

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

pub(super) struct Root {
    rng: InstanceRng,
    env: Vec<f32>,
    counter: u64,
    pub(super) derive: f32,
    width: f32,
}

/// The instance's parameters and the root calculation `_d = derive, _w = width`, in the root RNG context.
pub(super) fn root(ls: &LSystem, instance: &Instance) -> Result<Root, RewriteError> {
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
/// every non-terminal takes its terminal production, or stays if it has an interpretation rule, or is erased.
/// After the axiom and after every step, each `%` is removed with the rest of its branch (ABOP's cut).
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
    r.env[ls.color_slot as usize] = start_color(ls).0;
    let mut string = Vec::new();
    let mut counter = counter;
    r.expand(&ls.axiom, ROOT_KEY, &mut counter, &mut string)?;
    string = cut(ls, string);
    let mut step = 0;
    let mut last = false;
    while !last && string.iter().any(|m| ls.symbols[m.symbol as usize].kind == SymbolKind::NonTerminal) {
        // One more pass than the limit: the last one only substitutes terminal productions.
        if step > MAX_REWRITE_STEPS {
            return Err(RewriteError::TooManySteps(MAX_REWRITE_STEPS));
        }
        step += 1;
        // Every non-terminal takes its final alternative in this pass: what stays after it is drawn as it is.
        last = d <= 0.0;
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
            } else if sym.interpretation.is_some() {
                // Left for the interpretation rule, which applies only when the string is drawn.
                next.push(m);
            } else {
                r.expand(&sym.terminal, m.key, &mut counter, &mut next)?;
            }
            if next.len() > MAX_STRING_LEN {
                return Err(RewriteError::TooLong(MAX_STRING_LEN));
            }
        }
        string = cut(ls, next);
        d -= 1.0;
    }
    Ok(string)
}

/// ABOP's cut: every `%` is removed together with the rest of its branch, up to (not including) the `]` that
/// closes it, or to the end of the string.
fn cut(ls: &LSystem, string: Vec<ModuleOcc>) -> Vec<ModuleOcc> {
    if ls.cut_slot.is_none() {
        return string;
    }
    let (cut, push, pop) = (Turtle::Cut.id(), Turtle::Push.id(), Turtle::Pop.id());
    let mut out = Vec::with_capacity(string.len());
    let mut depth = 0usize;
    // The bracket depth of the branch being cut.
    let mut cutting: Option<usize> = None;
    for m in string {
        if m.symbol == push {
            depth += 1;
        } else if m.symbol == pop {
            if cutting == Some(depth) {
                cutting = None;
            }
            depth = depth.saturating_sub(1);
        } else if m.symbol == cut && cutting.is_none() {
            cutting = Some(depth);
        }
        if cutting.is_none() {
            out.push(m);
        }
    }
    out
}

/// Draw a terminal string with the turtle: first every module with an interpretation rule is replaced by the
/// rule's terminals (the homomorphism), then a flat graph of the terminals' bodies, each after a calculation of
/// its argument values, `[ ]` as separators, is amplified for `instance` within `budget`.
pub fn interpret(
    ls: &LSystem,
    instance: &Instance,
    string: &[ModuleOcc],
    budget: &Budget,
) -> Result<PrimitiveStream, RewriteError> {
    let mut r = root(ls, instance)?;
    let detail = f32::from(instance.detail);
    let mut drawn: Vec<ModuleOcc> = Vec::with_capacity(string.len());
    for m in string {
        let interpretation = ls.symbols.get(m.symbol as usize).and_then(|s| Some((s, s.interpretation.as_ref()?)));
        match interpretation {
            Some((sym, succ)) if m.args.len() == sym.formals.len() => {
                for (&slot, &v) in sym.formals.iter().zip(&m.args) {
                    r.env[slot as usize] = v;
                }
                // Interpretation rules draw no random numbers; the context is the occurrence's for form's sake.
                let mut ctx = Context { rng: &mut r.rng, key: m.key, counter: m.counter };
                for s in succ {
                    let args = s.args.iter().map(|e| eval(e, &r.env, detail, &mut ctx)).collect();
                    drawn.push(ModuleOcc { symbol: s.symbol, args, key: m.key, counter: m.counter });
                }
            }
            _ => drawn.push(m.clone()),
        }
    }
    let string = &drawn;
    let mut b = Builder { nodes: ls.graph.nodes.clone(), calcs: HashMap::new() };
    let (color, material) = start_color(ls);
    let init = b.push(Node::Calculation(vec![
        (ls.depth_slot, Expr::constant(r.derive)),
        (ls.width_slot, Expr::constant(r.width)),
        (ls.color_slot, Expr::constant(color)),
    ]));
    let mut stack: Vec<Vec<NodeId>> = vec![vec![init]];
    if let Some(m) = material {
        let m = b.push(Node::Material(m.map(Expr::constant)));
        stack[0].push(m);
    }
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

/// The colour index the turtle starts at, and the material it starts with if it is not the default: L-Py's turtle
/// starts at its material 1 (see [`LPY_MATERIALS`]).
fn start_color(ls: &LSystem) -> (f32, Option<[f32; 3]>) {
    if ls.lpy_colors { (LPY_START_COLOR as f32, Some(LPY_MATERIALS[LPY_START_COLOR])) } else { (0.0, None) }
}

/// The reference primitive stream: [`rewrite`] with the `derive` depth, then [`interpret`].
pub fn reference_stream(ls: &LSystem, instance: &Instance, budget: &Budget) -> Result<PrimitiveStream, RewriteError> {
    let string = rewrite(ls, instance, None)?;
    interpret(ls, instance, &string, budget)
}
