//! Compiled expressions: the compact postfix form that calculation, selection, transformation, material and
//! primitive nodes carry, evaluated by a stack machine during traversal.
//!
//! An [`Expr`] is a sequence of [`Op`]s for a value stack. Control flow exists only as forward jumps (for the
//! conditional and the short-circuit `&&`/`||`), so every evaluation ends after at most `ops.len()` steps;
//! [`Expr::validate`] proves statically that the stack never underflows, never exceeds
//! [`crate::limits::MAX_EXPR_STACK`], that jumps land inside the expression with a consistent stack depth, and
//! that the expression leaves exactly one value.

use serde::{Deserialize, Serialize};

use crate::limits;

/// One stack-machine operation. Binary operators pop `b` then `a` and push `a op b`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum Op {
    /// Push a constant.
    Const(f32),
    /// Push the value of parameter slot `n`.
    Param(u16),
    /// Push the instance's detail level (0 = full detail; higher = coarser, seed 001 §5).
    Detail,
    /// Negate the top value.
    Neg,
    /// Logical not: 1 if the top value is false (zero or NaN), else 0.
    Not,
    /// `a + b`.
    Add,
    /// `a - b`.
    Sub,
    /// `a * b`.
    Mul,
    /// `a / b`.
    Div,
    /// `a % b` with the sign of `a` (C `fmod`).
    Rem,
    /// `a ^ b`, through `libm::powf`.
    Pow,
    /// `a < b` as 1 or 0.
    Lt,
    /// `a <= b` as 1 or 0.
    Le,
    /// `a > b` as 1 or 0.
    Gt,
    /// `a >= b` as 1 or 0.
    Ge,
    /// `a == b` as 1 or 0.
    Eq,
    /// `a != b` as 1 or 0.
    Ne,
    /// Call a built-in function; it pops [`Func::arity`] arguments (the first argument deepest).
    Call(Func),
    /// Pop a condition; if it is false (zero or NaN) skip forward by `n` operations after this one.
    JumpIfFalse(u16),
    /// Skip forward by `n` operations after this one.
    Jump(u16),
    /// Weighted choice (stochastic productions): pop `n` weights, draw one uniform number from the instance RNG
    /// and push the index of the chosen weight, or `n` when no weight is positive. The draw happens either way.
    Choose(u8),
}

/// Built-in functions. Angles are radians; the transcendental ones go through `libm`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Func {
    /// `sin(x)`.
    Sin,
    /// `cos(x)`.
    Cos,
    /// `tan(x)`.
    Tan,
    /// `asin(x)`.
    Asin,
    /// `acos(x)`.
    Acos,
    /// `atan(x)`.
    Atan,
    /// `atan2(y, x)`.
    Atan2,
    /// `sqrt(x)`.
    Sqrt,
    /// `exp(x)`.
    Exp,
    /// Natural logarithm `ln(x)`.
    Ln,
    /// `abs(x)`.
    Abs,
    /// `sign(x)`: -1, 0 or 1.
    Sign,
    /// `floor(x)`.
    Floor,
    /// `ceil(x)`.
    Ceil,
    /// `round(x)`, half away from zero.
    Round,
    /// `fract(x) = x - floor(x)`.
    Fract,
    /// `min(a, b)`.
    Min,
    /// `max(a, b)`.
    Max,
    /// `clamp(x, lo, hi)`.
    Clamp,
    /// `lerp(a, b, t) = a + (b - a) * t`.
    Lerp,
    /// `step(edge, x)`: 0 if `x < edge`, else 1.
    Step,
    /// `smoothstep(e0, e1, x)`.
    Smoothstep,
    /// `rad(deg)`: degrees to radians.
    Rad,
    /// `deg(rad)`: radians to degrees.
    Deg,
    /// `rand()`: a uniform draw in [0, 1) from the instance RNG.
    Rand,
    /// `uniform(a, b)`: a uniform draw in [a, b) from the instance RNG.
    Uniform,
    /// `normal(mean, sd)`: a normal draw (Box–Muller) from the instance RNG.
    Normal,
    /// `chance(p)`: 1 with probability `p`, else 0, from the instance RNG.
    Chance,
    /// `noise(x, y)`: a uniform value in [0, 1) that depends only on the instance seed and the exact bits of
    /// `x` and `y`, not on traversal order (so neighbouring terrain tiles agree on shared edges).
    Noise,
}

impl Func {
    /// How many arguments the function pops.
    pub const fn arity(self) -> usize {
        match self {
            Func::Rand => 0,
            Func::Sin
            | Func::Cos
            | Func::Tan
            | Func::Asin
            | Func::Acos
            | Func::Atan
            | Func::Sqrt
            | Func::Exp
            | Func::Ln
            | Func::Abs
            | Func::Sign
            | Func::Floor
            | Func::Ceil
            | Func::Round
            | Func::Fract
            | Func::Rad
            | Func::Deg
            | Func::Chance => 1,
            Func::Atan2 | Func::Min | Func::Max | Func::Step | Func::Uniform | Func::Normal | Func::Noise => 2,
            Func::Clamp | Func::Lerp | Func::Smoothstep => 3,
        }
    }

    /// Whether evaluating the function consumes draws from the instance RNG.
    pub const fn draws(self) -> bool {
        matches!(self, Func::Rand | Func::Uniform | Func::Normal | Func::Chance)
    }

    /// The name used in the text formats.
    pub const fn name(self) -> &'static str {
        match self {
            Func::Sin => "sin",
            Func::Cos => "cos",
            Func::Tan => "tan",
            Func::Asin => "asin",
            Func::Acos => "acos",
            Func::Atan => "atan",
            Func::Atan2 => "atan2",
            Func::Sqrt => "sqrt",
            Func::Exp => "exp",
            Func::Ln => "ln",
            Func::Abs => "abs",
            Func::Sign => "sign",
            Func::Floor => "floor",
            Func::Ceil => "ceil",
            Func::Round => "round",
            Func::Fract => "fract",
            Func::Min => "min",
            Func::Max => "max",
            Func::Clamp => "clamp",
            Func::Lerp => "lerp",
            Func::Step => "step",
            Func::Smoothstep => "smoothstep",
            Func::Rad => "rad",
            Func::Deg => "deg",
            Func::Rand => "rand",
            Func::Uniform => "uniform",
            Func::Normal => "normal",
            Func::Chance => "chance",
            Func::Noise => "noise",
        }
    }

    /// Every function, for lookup by name.
    pub const ALL: [Func; 29] = [
        Func::Sin,
        Func::Cos,
        Func::Tan,
        Func::Asin,
        Func::Acos,
        Func::Atan,
        Func::Atan2,
        Func::Sqrt,
        Func::Exp,
        Func::Ln,
        Func::Abs,
        Func::Sign,
        Func::Floor,
        Func::Ceil,
        Func::Round,
        Func::Fract,
        Func::Min,
        Func::Max,
        Func::Clamp,
        Func::Lerp,
        Func::Step,
        Func::Smoothstep,
        Func::Rad,
        Func::Deg,
        Func::Rand,
        Func::Uniform,
        Func::Normal,
        Func::Chance,
        Func::Noise,
    ];

    /// Look a function up by its text-format name.
    pub fn from_name(name: &str) -> Option<Func> {
        Func::ALL.iter().copied().find(|f| f.name() == name)
    }
}

/// A compiled expression: postfix operations for a value stack (see the module docs).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Expr {
    /// The operations, in evaluation order.
    pub ops: Vec<Op>,
}

/// Why a compiled expression was rejected.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ExprError {
    /// The expression has no operations or more than the limit.
    #[error("expression has {0} operations (allowed 1..={max})", max = limits::MAX_EXPR_OPS)]
    Length(usize),
    /// An operation pops more values than the stack holds.
    #[error("stack underflow at operation {0}")]
    Underflow(usize),
    /// The stack would grow past the limit.
    #[error("stack deeper than {max} at operation {0}", max = limits::MAX_EXPR_STACK)]
    TooDeep(usize),
    /// A parameter slot is out of range.
    #[error("parameter slot {slot} at operation {at} is out of range ({count} declared)")]
    Slot {
        /// The offending slot.
        slot: u16,
        /// Operation index.
        at: usize,
        /// Declared parameter count.
        count: usize,
    },
    /// A jump lands outside the expression or where the stack depth disagrees.
    #[error("bad jump at operation {0}")]
    Jump(usize),
    /// A `Choose` takes no weights or more than the limit.
    #[error("choose of {0} weights at operation {1} (allowed 1..={max})", max = limits::MAX_CHOOSE)]
    Choose(usize, usize),
    /// The expression leaves other than one value.
    #[error("expression leaves {0} values instead of 1")]
    Result(usize),
    /// A constant is NaN or infinite.
    #[error("constant at operation {0} is not finite")]
    Constant(usize),
}

impl Expr {
    /// A constant expression.
    pub fn constant(v: f32) -> Expr {
        Expr { ops: vec![Op::Const(v)] }
    }

    /// A reference to one parameter slot.
    pub fn param(slot: u16) -> Expr {
        Expr { ops: vec![Op::Param(slot)] }
    }

    /// The constant value, if the expression is a single constant.
    pub fn as_constant(&self) -> Option<f32> {
        match self.ops.as_slice() {
            [Op::Const(v)] => Some(*v),
            _ => None,
        }
    }

    /// Whether evaluating the expression may draw from the instance RNG.
    pub fn draws(&self) -> bool {
        self.ops.iter().any(|op| matches!(op, Op::Choose(_)) || matches!(op, Op::Call(f) if f.draws()))
    }

    /// Check the expression statically against `param_count` declared slots (see the module docs).
    pub fn validate(&self, param_count: usize) -> Result<(), ExprError> {
        let n = self.ops.len();
        if n == 0 || n > limits::MAX_EXPR_OPS {
            return Err(ExprError::Length(n));
        }
        // Stack depth expected on entry to each operation, set by fall-through or a forward jump.
        let mut entry: Vec<Option<usize>> = vec![None; n + 1];
        entry[0] = Some(0);
        for (at, op) in self.ops.iter().enumerate() {
            // An operation reached by no path (after an unconditional jump) is still checked from the jump target.
            let Some(depth) = entry[at] else { continue };
            let (pops, pushes) = match *op {
                Op::Const(_) | Op::Param(_) | Op::Detail => (0, 1),
                Op::Neg | Op::Not => (1, 1),
                Op::Add
                | Op::Sub
                | Op::Mul
                | Op::Div
                | Op::Rem
                | Op::Pow
                | Op::Lt
                | Op::Le
                | Op::Gt
                | Op::Ge
                | Op::Eq
                | Op::Ne => (2, 1),
                Op::Call(f) => (f.arity(), 1),
                Op::JumpIfFalse(_) => (1, 0),
                Op::Jump(_) => (0, 0),
                Op::Choose(k) => {
                    let k = k as usize;
                    if k == 0 || k > limits::MAX_CHOOSE {
                        return Err(ExprError::Choose(k, at));
                    }
                    (k, 1)
                }
            };
            if let Op::Const(v) = *op
                && !v.is_finite()
            {
                return Err(ExprError::Constant(at));
            }
            if let Op::Param(slot) = *op
                && slot as usize >= param_count
            {
                return Err(ExprError::Slot { slot, at, count: param_count });
            }
            if depth < pops {
                return Err(ExprError::Underflow(at));
            }
            let after = depth - pops + pushes;
            if after > limits::MAX_EXPR_STACK {
                return Err(ExprError::TooDeep(at));
            }
            let mut flow = |target: usize, d: usize| -> Result<(), ExprError> {
                if target > n {
                    return Err(ExprError::Jump(at));
                }
                match entry[target] {
                    None => entry[target] = Some(d),
                    Some(e) if e == d => {}
                    Some(_) => return Err(ExprError::Jump(at)),
                }
                Ok(())
            };
            match *op {
                Op::Jump(off) => flow(at + 1 + off as usize, after)?,
                Op::JumpIfFalse(off) => {
                    flow(at + 1 + off as usize, after)?;
                    flow(at + 1, after)?;
                }
                _ => flow(at + 1, after)?,
            }
        }
        match entry[n] {
            Some(1) => Ok(()),
            Some(d) => Err(ExprError::Result(d)),
            None => Err(ExprError::Result(0)),
        }
    }
}
