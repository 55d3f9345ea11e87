//! The stack machine that evaluates compiled expressions during traversal.
//!
//! Determinism: only IEEE-exact operations (`+ - * /`, `sqrt`, `floor`, comparisons) come from the platform;
//! every transcendental function goes through `libm`, and random draws come from a [`Draw`] source whose floats
//! are made from bits by the explicit formulas in [`unit_f32`] and [`open_unit_f32`].

use canopy_protocol::{Expr, Func, Op, limits};

/// A source of random bits for the drawing functions (`rand`, `uniform`, `normal`, `chance`, `choose`) and of
/// position-keyed noise.
pub(crate) trait Draw {
    /// The next 32 random bits in the current context.
    fn next_u32(&mut self) -> u32;
    /// A uniform value in [0, 1) that depends only on the instance seed and the bits of `x` and `y`.
    fn noise(&mut self, x: f32, y: f32) -> f32;
}

/// A [`Draw`] for contexts with no instance (constant folding): draws yield 0.
pub(crate) struct NoDraw;

impl Draw for NoDraw {
    fn next_u32(&mut self) -> u32 {
        0
    }
    fn noise(&mut self, _x: f32, _y: f32) -> f32 {
        0.0
    }
}

/// A float in [0, 1) from the top 24 bits: `(bits >> 8) · 2⁻²⁴`, exact in f32.
#[inline]
pub(crate) fn unit_f32(bits: u32) -> f32 {
    (bits >> 8) as f32 * (1.0 / 16_777_216.0)
}

/// A float in (0, 1] from the top 24 bits: `((bits >> 8) + 1) · 2⁻²⁴`, exact in f32 (safe for `ln`).
#[inline]
pub(crate) fn open_unit_f32(bits: u32) -> f32 {
    ((bits >> 8) + 1) as f32 * (1.0 / 16_777_216.0)
}

/// Truthiness in expressions: false is zero or NaN.
#[inline]
pub(crate) fn truthy(v: f32) -> bool {
    v != 0.0 && !v.is_nan()
}

#[inline]
fn b(v: bool) -> f32 {
    if v { 1.0 } else { 0.0 }
}

/// Evaluate a validated expression. `params` must hold at least as many values as the expression's slots refer
/// to (guaranteed for expressions of a validated species graph). The work is at most `expr.ops.len()` steps.
#[inline(always)]
pub(crate) fn eval<D: Draw + ?Sized>(expr: &Expr, params: &[f32], detail: f32, draw: &mut D) -> f32 {
    match eval_simple(expr, params) {
        Some(v) => v,
        None => eval_stack(expr, params, detail, draw),
    }
}

/// The commonest shapes without the stack machine: a constant, a parameter, and one arithmetic or comparison
/// operator on two of them. `None` for anything else. Computes exactly what [`eval_stack`] computes.
#[inline(always)]
pub(crate) fn eval_simple(expr: &Expr, params: &[f32]) -> Option<f32> {
    #[inline(always)]
    fn leaf(op: &Op, params: &[f32]) -> Option<f32> {
        match op {
            Op::Const(v) => Some(*v),
            Op::Param(s) => Some(params[*s as usize]),
            _ => None,
        }
    }
    match expr.ops.as_slice() {
        [a] => leaf(a, params),
        [a, c, op] => {
            let (x, y) = (leaf(a, params)?, leaf(c, params)?);
            Some(match op {
                Op::Add => x + y,
                Op::Sub => x - y,
                Op::Mul => x * y,
                Op::Div => x / y,
                Op::Lt => b(x < y),
                Op::Le => b(x <= y),
                Op::Gt => b(x > y),
                Op::Ge => b(x >= y),
                Op::Eq => b(x == y),
                Op::Ne => b(x != y),
                _ => return None,
            })
        }
        _ => None,
    }
}

/// The general stack machine (see [`eval`]).
#[inline(never)]
pub(crate) fn eval_stack<D: Draw + ?Sized>(expr: &Expr, params: &[f32], detail: f32, draw: &mut D) -> f32 {
    // The stack never holds more values than there are operations: short expressions get a small stack, which
    // is cheaper to set up.
    if expr.ops.len() <= 16 {
        run::<D, 16>(expr, params, detail, draw)
    } else {
        run::<D, { limits::MAX_EXPR_STACK }>(expr, params, detail, draw)
    }
}

#[inline(always)]
fn run<D: Draw + ?Sized, const N: usize>(expr: &Expr, params: &[f32], detail: f32, draw: &mut D) -> f32 {
    let mut stack = [0.0f32; N];
    let mut sp = 0usize;
    let ops = &expr.ops;
    let mut pc = 0usize;
    macro_rules! pop {
        () => {{
            sp -= 1;
            stack[sp]
        }};
    }
    macro_rules! push {
        ($v:expr) => {{
            let v = $v;
            stack[sp] = v;
            sp += 1;
        }};
    }
    macro_rules! bin {
        ($f:expr) => {{
            let y = pop!();
            let x = pop!();
            push!($f(x, y));
        }};
    }
    while pc < ops.len() {
        match ops[pc] {
            Op::Const(v) => push!(v),
            Op::Param(s) => push!(params[s as usize]),
            Op::Detail => push!(detail),
            Op::Neg => {
                let x = pop!();
                push!(-x)
            }
            Op::Not => {
                let x = pop!();
                push!(b(!truthy(x)))
            }
            Op::Add => bin!(|x: f32, y: f32| x + y),
            Op::Sub => bin!(|x: f32, y: f32| x - y),
            Op::Mul => bin!(|x: f32, y: f32| x * y),
            Op::Div => bin!(|x: f32, y: f32| x / y),
            Op::Rem => bin!(libm::fmodf),
            Op::Pow => bin!(libm::powf),
            Op::Lt => bin!(|x: f32, y: f32| b(x < y)),
            Op::Le => bin!(|x: f32, y: f32| b(x <= y)),
            Op::Gt => bin!(|x: f32, y: f32| b(x > y)),
            Op::Ge => bin!(|x: f32, y: f32| b(x >= y)),
            Op::Eq => bin!(|x: f32, y: f32| b(x == y)),
            Op::Ne => bin!(|x: f32, y: f32| b(x != y)),
            Op::JumpIfFalse(off) => {
                let c = pop!();
                if !truthy(c) {
                    pc += off as usize;
                }
            }
            Op::Jump(off) => pc += off as usize,
            Op::Choose(n) => {
                let n = n as usize;
                sp -= n;
                let weights = &stack[sp..sp + n];
                let u = unit_f32(draw.next_u32());
                let total: f32 = weights.iter().map(|&w| if w > 0.0 { w } else { 0.0 }).sum();
                let mut chosen = n;
                if total > 0.0 {
                    let target = u * total;
                    let mut acc = 0.0f32;
                    for (i, &w) in weights.iter().enumerate() {
                        if w > 0.0 {
                            acc += w;
                            chosen = i;
                            if target < acc {
                                break;
                            }
                        }
                    }
                }
                push!(chosen as f32)
            }
            Op::Call(f) => {
                let v = match f.arity() {
                    0 => call(f, [0.0; 3], draw),
                    1 => {
                        let x = pop!();
                        call(f, [x, 0.0, 0.0], draw)
                    }
                    2 => {
                        let y = pop!();
                        let x = pop!();
                        call(f, [x, y, 0.0], draw)
                    }
                    _ => {
                        let z = pop!();
                        let y = pop!();
                        let x = pop!();
                        call(f, [x, y, z], draw)
                    }
                };
                push!(v)
            }
        }
        pc += 1;
    }
    stack[0]
}

fn call<D: Draw + ?Sized>(f: Func, a: [f32; 3], draw: &mut D) -> f32 {
    let [x, y, z] = a;
    match f {
        Func::Sin => libm::sinf(x),
        Func::Cos => libm::cosf(x),
        Func::Tan => libm::tanf(x),
        Func::Asin => libm::asinf(x),
        Func::Acos => libm::acosf(x),
        Func::Atan => libm::atanf(x),
        Func::Atan2 => libm::atan2f(x, y),
        Func::Sqrt => libm::sqrtf(x),
        Func::Exp => libm::expf(x),
        Func::Ln => libm::logf(x),
        Func::Abs => libm::fabsf(x),
        Func::Sign => {
            if x > 0.0 {
                1.0
            } else if x < 0.0 {
                -1.0
            } else {
                0.0
            }
        }
        Func::Floor => libm::floorf(x),
        Func::Ceil => libm::ceilf(x),
        Func::Round => libm::roundf(x),
        Func::Fract => x - libm::floorf(x),
        Func::Min => libm::fminf(x, y),
        Func::Max => libm::fmaxf(x, y),
        Func::Clamp => libm::fminf(libm::fmaxf(x, y), z),
        Func::Lerp => x + (y - x) * z,
        Func::Step => b(y >= x),
        Func::Smoothstep => {
            let t = libm::fminf(libm::fmaxf((z - x) / (y - x), 0.0), 1.0);
            t * t * (3.0 - 2.0 * t)
        }
        Func::Rad => x * (core::f32::consts::PI / 180.0),
        Func::Deg => x * (180.0 / core::f32::consts::PI),
        Func::Rand => unit_f32(draw.next_u32()),
        Func::Uniform => x + (y - x) * unit_f32(draw.next_u32()),
        Func::Normal => {
            let u1 = open_unit_f32(draw.next_u32());
            let u2 = unit_f32(draw.next_u32());
            x + y * libm::sqrtf(-2.0 * libm::logf(u1)) * libm::cosf(2.0 * core::f32::consts::PI * u2)
        }
        Func::Chance => b(unit_f32(draw.next_u32()) < x),
        Func::Noise => draw.noise(x, y),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    struct Seq(Vec<u32>);
    impl Draw for Seq {
        fn next_u32(&mut self) -> u32 {
            self.0.remove(0)
        }
        fn noise(&mut self, _: f32, _: f32) -> f32 {
            0.5
        }
    }

    #[test]
    fn unit_floats_are_exact_and_in_range() {
        assert_eq!(unit_f32(0), 0.0);
        assert_eq!(unit_f32(u32::MAX), 1.0 - 1.0 / 16_777_216.0);
        assert_eq!(unit_f32(0x8000_0000), 0.5);
        assert_eq!(open_unit_f32(0), 1.0 / 16_777_216.0);
        assert_eq!(open_unit_f32(u32::MAX), 1.0);
    }

    #[test]
    fn choose_picks_by_weight_and_reports_none() {
        let e = Expr { ops: vec![Op::Const(1.0), Op::Const(0.0), Op::Const(3.0), Op::Choose(3)] };
        // u = 0.1 → target 0.4 < 1 → index 0; u = 0.5 → target 2 → index 2 (weight 0 is skipped).
        assert_eq!(eval(&e, &[], 0.0, &mut Seq(vec![0x1999_9999])), 0.0);
        assert_eq!(eval(&e, &[], 0.0, &mut Seq(vec![0x8000_0000])), 2.0);
        let none = Expr { ops: vec![Op::Const(0.0), Op::Const(-1.0), Op::Choose(2)] };
        let mut s = Seq(vec![7]);
        assert_eq!(eval(&none, &[], 0.0, &mut s), 2.0);
        assert!(s.0.is_empty(), "choose draws even when nothing is chosen");
    }
}
