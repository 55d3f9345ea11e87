//! Expressions in the text formats: parsing to an [`Ast`] with spans, and compiling it to the compact
//! [`canopy_protocol::Expr`] that traversal evaluates.
//!
//! Grammar, loosest binding first: `c ? a : b` (right-associative), `||`, `&&`, comparisons
//! (`< <= > >= == !=`), `+ -`, `* / %`, unary `- !`, `^` (right-associative, binds tighter than unary minus),
//! then numbers, names, calls `f(a, b)` and parentheses. `pi` is a constant and `detail` the instance's detail
//! level; every other name is a parameter, resolved when compiling. Constant sub-expressions are folded with the
//! same evaluator traversal uses, so folding never changes a result. A constant sub-expression whose value is not
//! finite (`0 / 0`, `1 / 0`, `sqrt(-1)`, `1e30 * 1e30`) is an error: [`parse_expr`] reports it at the expression's
//! span, [`compile`] for expressions built in code.

use std::ops::Range;

use canopy_protocol::{Expr, Func, Op, limits};

use crate::eval::{NoDraw, eval};
use crate::text::{Cursor, ParseError};

/// Deepest nesting of parentheses and operators the parser accepts before giving up (no stack overflow on
/// hostile input).
pub(crate) const MAX_NESTING: usize = 64;

/// A unary operator.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum UnOp {
    /// `-a`.
    Neg,
    /// `!a`.
    Not,
}

/// A binary operator with eager operands.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum BinOp {
    /// `+`.
    Add,
    /// `-`.
    Sub,
    /// `*`.
    Mul,
    /// `/`.
    Div,
    /// `%`.
    Rem,
    /// `^`.
    Pow,
    /// `<`.
    Lt,
    /// `<=`.
    Le,
    /// `>`.
    Gt,
    /// `>=`.
    Ge,
    /// `==`.
    Eq,
    /// `!=`.
    Ne,
}

/// A parsed expression.
#[derive(Clone, Debug, PartialEq)]
pub(crate) enum Ast {
    /// A number literal.
    Num(f32),
    /// A parameter name, resolved at compile time.
    Var(String, Range<usize>),
    /// The instance's detail level.
    Detail,
    /// A unary operation.
    Unary(UnOp, Box<Ast>),
    /// A binary operation.
    Binary(BinOp, Box<Ast>, Box<Ast>),
    /// Short-circuit `a && b` (1 or 0).
    And(Box<Ast>, Box<Ast>),
    /// Short-circuit `a || b` (1 or 0).
    Or(Box<Ast>, Box<Ast>),
    /// `c ? a : b`; only the taken branch is evaluated.
    Cond(Box<Ast>, Box<Ast>, Box<Ast>),
    /// A built-in function call with the right number of arguments.
    Call(Func, Vec<Ast>),
    /// A weighted choice among the weights (see [`Op::Choose`]).
    Choose(Vec<Ast>),
}

impl Ast {
    /// `a op b`.
    pub(crate) fn bin(op: BinOp, a: Ast, b: Ast) -> Ast {
        Ast::Binary(op, Box::new(a), Box::new(b))
    }

    /// `c ? a : b`.
    pub(crate) fn cond(c: Ast, a: Ast, b: Ast) -> Ast {
        Ast::Cond(Box::new(c), Box::new(a), Box::new(b))
    }

    /// A reference to a parameter by name (with an empty span).
    pub(crate) fn var(name: &str) -> Ast {
        Ast::Var(name.to_string(), 0..0)
    }
}

/// Parse one expression at the cursor. The cursor stops after the expression. An expression with a constant
/// sub-expression that folds to a non-finite value is an error at the expression's span (see
/// [`non_finite_constant`]).
pub(crate) fn parse_expr(cur: &mut Cursor<'_>) -> Result<Ast, ParseError> {
    cur.skip_trivia();
    let start = cur.pos;
    let ast = Parser { cur: &mut *cur, depth: 0 }.cond()?;
    if let Some(v) = non_finite_constant(&ast) {
        return Err(ParseError::new(start..cur.pos, non_finite_message(v)));
    }
    Ok(ast)
}

/// The value of the first constant sub-expression of `ast` (depth first) that folds to a non-finite value — NaN or
/// an infinity, as in `0 / 0`, `1 / 0`, `sqrt(-1)`, `ln(0)` or `1e30 * 1e30` — if any. Sub-expressions fold as
/// [`compile`] folds them: bottom-up, with the evaluator traversal uses, and never across `?:`, `&&`, `||`, a
/// random draw or `noise`.
pub(crate) fn non_finite_constant(ast: &Ast) -> Option<f32> {
    fold(ast).err()
}

/// The message for a constant sub-expression that folds to `v` (not finite).
fn non_finite_message(v: f32) -> String {
    format!(
        "constant expression evaluates to {v}, not a finite number (division by zero, a root or logarithm out of \
         range, or overflow)"
    )
}

/// `Ok(Some(v))` for a constant sub-expression with the finite value `v`, `Ok(None)` for one that is not constant,
/// `Err(v)` for the first constant part, depth first, that folds to the non-finite `v`.
fn fold(ast: &Ast) -> Result<Option<f32>, f32> {
    let eval_ops = |ops: Vec<Op>| -> Result<Option<f32>, f32> {
        let v = eval(&Expr { ops }, &[], 0.0, &mut NoDraw);
        if v.is_finite() { Ok(Some(v)) } else { Err(v) }
    };
    match ast {
        Ast::Num(v) if v.is_finite() => Ok(Some(*v)),
        Ast::Num(v) => Err(*v),
        Ast::Var(..) | Ast::Detail => Ok(None),
        Ast::Unary(op, a) => match fold(a)? {
            Some(x) => eval_ops(vec![Op::Const(x), unary_op(*op)]),
            None => Ok(None),
        },
        Ast::Binary(op, a, b) => match (fold(a)?, fold(b)?) {
            (Some(x), Some(y)) => eval_ops(vec![Op::Const(x), Op::Const(y), binary_op(*op)]),
            _ => Ok(None),
        },
        Ast::And(a, b) | Ast::Or(a, b) => {
            fold(a)?;
            fold(b)?;
            Ok(None)
        }
        Ast::Cond(c, a, b) => {
            fold(c)?;
            fold(a)?;
            fold(b)?;
            Ok(None)
        }
        Ast::Call(f, args) => {
            let mut ops = Vec::with_capacity(args.len() + 1);
            for a in args {
                if let Some(x) = fold(a)? {
                    ops.push(Op::Const(x));
                }
            }
            if ops.len() == args.len() && !args.is_empty() && !f.draws() && *f != Func::Noise {
                ops.push(Op::Call(*f));
                eval_ops(ops)
            } else {
                Ok(None)
            }
        }
        Ast::Choose(ws) => {
            for w in ws {
                fold(w)?;
            }
            Ok(None)
        }
    }
}

fn unary_op(op: UnOp) -> Op {
    match op {
        UnOp::Neg => Op::Neg,
        UnOp::Not => Op::Not,
    }
}

fn binary_op(op: BinOp) -> Op {
    match op {
        BinOp::Add => Op::Add,
        BinOp::Sub => Op::Sub,
        BinOp::Mul => Op::Mul,
        BinOp::Div => Op::Div,
        BinOp::Rem => Op::Rem,
        BinOp::Pow => Op::Pow,
        BinOp::Lt => Op::Lt,
        BinOp::Le => Op::Le,
        BinOp::Gt => Op::Gt,
        BinOp::Ge => Op::Ge,
        BinOp::Eq => Op::Eq,
        BinOp::Ne => Op::Ne,
    }
}

/// Parse a whole string as one expression (for tests and command-line parameter values).
pub(crate) fn parse_str(src: &str) -> Result<Ast, ParseError> {
    let mut cur = Cursor::new(src, true);
    let ast = parse_expr(&mut cur)?;
    if !cur.at_end() {
        return Err(cur.unexpected("end of expression"));
    }
    Ok(ast)
}

struct Parser<'c, 'a> {
    cur: &'c mut Cursor<'a>,
    depth: usize,
}

impl Parser<'_, '_> {
    fn enter(&mut self) -> Result<(), ParseError> {
        self.depth += 1;
        if self.depth > MAX_NESTING {
            let p = self.cur.pos;
            return Err(ParseError::new(p..p + 1, format!("expression nested deeper than {MAX_NESTING}")));
        }
        Ok(())
    }

    fn cond(&mut self) -> Result<Ast, ParseError> {
        self.enter()?;
        let c = self.or()?;
        let r = if self.cur.eat("?") {
            let a = self.cond()?;
            self.cur.expect(":")?;
            let b = self.cond()?;
            Ast::cond(c, a, b)
        } else {
            c
        };
        self.depth -= 1;
        Ok(r)
    }

    fn or(&mut self) -> Result<Ast, ParseError> {
        let mut a = self.and()?;
        while self.cur.eat("||") {
            let b = self.and()?;
            a = Ast::Or(Box::new(a), Box::new(b));
        }
        Ok(a)
    }

    fn and(&mut self) -> Result<Ast, ParseError> {
        let mut a = self.cmp()?;
        while self.cur.eat("&&") {
            let b = self.cmp()?;
            a = Ast::And(Box::new(a), Box::new(b));
        }
        Ok(a)
    }

    fn cmp(&mut self) -> Result<Ast, ParseError> {
        let mut a = self.add()?;
        loop {
            let op = if self.cur.eat("<=") {
                BinOp::Le
            } else if self.cur.eat(">=") {
                BinOp::Ge
            } else if self.cur.eat("==") {
                BinOp::Eq
            } else if self.cur.eat("!=") {
                BinOp::Ne
            } else if self.cur.eat("<") {
                BinOp::Lt
            } else if self.cur.eat(">") {
                BinOp::Gt
            } else {
                return Ok(a);
            };
            let b = self.add()?;
            a = Ast::bin(op, a, b);
        }
    }

    fn add(&mut self) -> Result<Ast, ParseError> {
        let mut a = self.mul()?;
        loop {
            let op = if self.cur.eat("+") {
                BinOp::Add
            } else if self.cur.peek() == Some('-') && !self.cur.rest().starts_with("->") {
                self.cur.pos += 1;
                BinOp::Sub
            } else {
                return Ok(a);
            };
            let b = self.mul()?;
            a = Ast::bin(op, a, b);
        }
    }

    fn mul(&mut self) -> Result<Ast, ParseError> {
        let mut a = self.unary()?;
        loop {
            let op = if self.cur.eat("*") {
                BinOp::Mul
            } else if self.cur.eat("/") {
                BinOp::Div
            } else if self.cur.eat("%") {
                BinOp::Rem
            } else {
                return Ok(a);
            };
            let b = self.unary()?;
            a = Ast::bin(op, a, b);
        }
    }

    fn unary(&mut self) -> Result<Ast, ParseError> {
        self.enter()?;
        let r = if self.cur.peek() == Some('-') {
            self.cur.pos += 1;
            Ast::Unary(UnOp::Neg, Box::new(self.unary()?))
        } else if self.cur.peek() == Some('!') && !self.cur.rest().starts_with("!=") {
            self.cur.pos += 1;
            Ast::Unary(UnOp::Not, Box::new(self.unary()?))
        } else {
            self.pow()?
        };
        self.depth -= 1;
        Ok(r)
    }

    fn pow(&mut self) -> Result<Ast, ParseError> {
        let base = self.primary()?;
        if self.cur.eat("^") {
            let exp = self.unary()?;
            return Ok(Ast::bin(BinOp::Pow, base, exp));
        }
        Ok(base)
    }

    fn primary(&mut self) -> Result<Ast, ParseError> {
        if let Some(n) = self.cur.number() {
            return Ok(Ast::Num(n?.0));
        }
        if self.cur.eat("(") {
            let e = self.cond()?;
            self.cur.expect(")")?;
            return Ok(e);
        }
        let Some((name, span)) = self.cur.ident() else {
            return Err(self.cur.unexpected("an expression"));
        };
        if self.cur.rest().starts_with('(') {
            self.cur.pos += 1;
            let mut args = Vec::new();
            if !self.cur.eat(")") {
                loop {
                    args.push(self.cond()?);
                    if self.cur.eat(")") {
                        break;
                    }
                    self.cur.expect(",")?;
                }
            }
            let call_span = span.start..self.cur.pos;
            if name == "choose" {
                if args.is_empty() || args.len() > limits::MAX_CHOOSE {
                    return Err(ParseError::new(
                        call_span,
                        format!("choose takes 1 to {} weights, got {}", limits::MAX_CHOOSE, args.len()),
                    ));
                }
                return Ok(Ast::Choose(args));
            }
            let Some(f) = Func::from_name(name) else {
                let names = Func::ALL.iter().map(|f| f.name()).chain(["choose"]);
                let hint = crate::diag::did_you_mean(name, names).map(|n| format!("; did you mean `{n}`?"));
                return Err(ParseError::new(span, format!("unknown function `{name}`{}", hint.unwrap_or_default())));
            };
            if args.len() != f.arity() {
                return Err(ParseError::new(
                    call_span,
                    format!("`{name}` takes {} argument(s), got {}", f.arity(), args.len()),
                ));
            }
            return Ok(Ast::Call(f, args));
        }
        Ok(match name {
            "pi" => Ast::Num(core::f32::consts::PI),
            "detail" => Ast::Detail,
            "true" => Ast::Num(1.0),
            "false" => Ast::Num(0.0),
            _ => Ast::Var(name.to_string(), span),
        })
    }
}

/// Compile an [`Ast`], resolving parameter names to slots with `resolve`. Unknown names are errors at their span.
pub(crate) fn compile(ast: &Ast, resolve: &mut dyn FnMut(&str) -> Option<u16>) -> Result<Expr, ParseError> {
    let mut ops = Vec::new();
    emit(ast, resolve, &mut ops)?;
    if ops.len() > limits::MAX_EXPR_OPS {
        return Err(ParseError::new(
            0..0,
            format!("expression compiles to {} operations (max {})", ops.len(), limits::MAX_EXPR_OPS),
        ));
    }
    let expr = Expr { ops };
    // Everything emitted here is well formed by construction; validation guards the stack-depth limit.
    expr.validate(usize::from(u16::MAX) + 1)
        .map_err(|e| ParseError::new(0..0, format!("expression too complex: {e}")))?;
    Ok(expr)
}

fn jump(len: usize) -> Result<u16, ParseError> {
    u16::try_from(len).map_err(|_| ParseError::new(0..0, "expression too long"))
}

fn emit(ast: &Ast, resolve: &mut dyn FnMut(&str) -> Option<u16>, out: &mut Vec<Op>) -> Result<(), ParseError> {
    let start = out.len();
    match ast {
        Ast::Num(v) => out.push(Op::Const(*v)),
        Ast::Var(name, span) => match resolve(name) {
            Some(slot) => out.push(Op::Param(slot)),
            None => return Err(ParseError::new(span.clone(), format!("unknown parameter `{name}`"))),
        },
        Ast::Detail => out.push(Op::Detail),
        Ast::Unary(op, a) => {
            emit(a, resolve, out)?;
            out.push(unary_op(*op));
        }
        Ast::Binary(op, a, b) => {
            emit(a, resolve, out)?;
            emit(b, resolve, out)?;
            out.push(binary_op(*op));
        }
        Ast::Cond(c, a, b) => {
            emit(c, resolve, out)?;
            let jif = out.len();
            out.push(Op::JumpIfFalse(0));
            emit(a, resolve, out)?;
            let jmp = out.len();
            out.push(Op::Jump(0));
            out[jif] = Op::JumpIfFalse(jump(out.len() - jif - 1)?);
            emit(b, resolve, out)?;
            out[jmp] = Op::Jump(jump(out.len() - jmp - 1)?);
        }
        Ast::And(a, b) => {
            // a ? !!b : 0
            emit(a, resolve, out)?;
            let jif = out.len();
            out.push(Op::JumpIfFalse(0));
            emit(b, resolve, out)?;
            out.extend([Op::Not, Op::Not, Op::Jump(1)]);
            out[jif] = Op::JumpIfFalse(jump(out.len() - jif - 1)?);
            out.push(Op::Const(0.0));
        }
        Ast::Or(a, b) => {
            // a ? 1 : !!b
            emit(a, resolve, out)?;
            out.push(Op::JumpIfFalse(2));
            out.push(Op::Const(1.0));
            let jmp = out.len();
            out.push(Op::Jump(0));
            emit(b, resolve, out)?;
            out.extend([Op::Not, Op::Not]);
            out[jmp] = Op::Jump(jump(out.len() - jmp - 1)?);
        }
        Ast::Call(f, args) => {
            for a in args {
                emit(a, resolve, out)?;
            }
            out.push(Op::Call(*f));
        }
        Ast::Choose(ws) => {
            for w in ws {
                emit(w, resolve, out)?;
            }
            out.push(Op::Choose(ws.len() as u8));
        }
    }
    // Fold a constant sub-expression to one constant, with the evaluator itself so the value is identical.
    let code = &out[start..];
    let foldable = code.len() > 1
        && code.iter().all(|op| match op {
            Op::Const(_) => true,
            Op::Param(_) | Op::Detail | Op::Choose(_) | Op::Jump(_) | Op::JumpIfFalse(_) => false,
            Op::Call(f) => !f.draws() && *f != Func::Noise,
            _ => true,
        });
    if foldable {
        // A non-finite result (`0 / 0`, `1e30 * 1e30`) is an error: constants on the wire are finite, and a species
        // whose constant sizes or angles are NaN can only make non-finite primitives. `parse_expr` finds these
        // first and points at the expression; this catches expressions built in code (span filled in by the caller).
        let v = eval(&Expr { ops: code.to_vec() }, &[], 0.0, &mut NoDraw);
        if !v.is_finite() {
            return Err(ParseError::new(0..0, non_finite_message(v)));
        }
        out.truncate(start);
        out.push(Op::Const(v));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::eval::{NoDraw, eval};

    fn value(src: &str, params: &[(&str, f32)]) -> f32 {
        let ast = parse_str(src).unwrap();
        let names: Vec<&str> = params.iter().map(|p| p.0).collect();
        let values: Vec<f32> = params.iter().map(|p| p.1).collect();
        let e = compile(&ast, &mut |n| names.iter().position(|&m| m == n).map(|i| i as u16)).unwrap();
        e.validate(values.len()).unwrap();
        eval(&e, &values, 2.0, &mut NoDraw)
    }

    #[test]
    fn precedence_and_associativity() {
        let cases: &[(&str, f32)] = &[
            ("1 + 2 * 3", 7.0),
            ("(1 + 2) * 3", 9.0),
            ("2 ^ 3 ^ 2", 512.0),
            ("-2 ^ 2", -4.0),
            ("10 - 4 - 3", 3.0),
            ("7 % 4", 3.0),
            ("-7 % 4", -3.0),
            ("1 < 2 && 3 > 4", 0.0),
            ("1 < 2 || 3 > 4", 1.0),
            ("0 ? 5 : 1 ? 6 : 7", 6.0),
            ("!0 + !3", 1.0),
            ("1 != 2", 1.0),
            ("max(2, min(9, 4))", 4.0),
            ("clamp(5, 0, 1)", 1.0),
            ("lerp(2, 4, 0.5)", 3.0),
            ("floor(-1.5)", -2.0),
            ("detail * 10", 20.0),
            ("deg(pi)", 180.0),
            ("3 && 0.5", 1.0),
        ];
        for &(src, want) in cases {
            assert_eq!(value(src, &[]), want, "{src}");
        }
    }

    #[test]
    fn parameters_and_folding() {
        assert_eq!(value("c > 0 ? c - 1 : 0", &[("c", 4.0)]), 3.0);
        let e = compile(&parse_str("2 * 3 + sin(0)").unwrap(), &mut |_| None).unwrap();
        assert_eq!(e.ops, vec![Op::Const(6.0)]);
        let e = compile(&parse_str("x * (2 + 2)").unwrap(), &mut |_| Some(0)).unwrap();
        assert_eq!(e.ops, vec![Op::Param(0), Op::Const(4.0), Op::Mul]);
    }

    #[test]
    fn errors_point_at_the_problem() {
        let err = parse_str("1 + sine(2)").unwrap_err();
        assert_eq!((err.span, err.message.as_str()), (4..8, "unknown function `sine`; did you mean `sin`?"));
        let err = parse_str("max(1)").unwrap_err();
        assert_eq!(err.message, "`max` takes 2 argument(s), got 1");
        let err = parse_str("1 +").unwrap_err();
        assert_eq!(err.message, "expected an expression, found end of file");
        let ast = parse_str("a + bee").unwrap();
        let err = compile(&ast, &mut |n| (n == "a").then_some(0)).unwrap_err();
        assert_eq!((err.span, err.message.as_str()), (4..7, "unknown parameter `bee`"));
    }

    #[test]
    fn non_finite_constants_are_errors_at_the_expression() {
        // (source, span of the error): the whole expression, after leading whitespace.
        let cases: &[(&str, std::ops::Range<usize>)] = &[
            ("0/0", 0..3),
            ("  1 / 0", 2..7),
            ("x + 1/0", 0..7),
            ("sqrt(-1) * x", 0..12),
            ("ln(0)", 0..5),
            ("1e30 * 1e30", 0..11),
            ("x > 0 ? 0/0 : 1", 0..15),
            ("choose(1, 0/0)", 0..14),
            ("-(2 - 2) ^ -1", 0..13),
        ];
        for (src, span) in cases {
            let err = parse_str(src).unwrap_err();
            assert_eq!(&err.span, span, "{src}");
            assert!(err.message.contains("not a finite number"), "{src}: {}", err.message);
        }
        assert!(parse_str("0/0").unwrap_err().message.starts_with("constant expression evaluates to NaN"));
        assert!(parse_str("1/0").unwrap_err().message.starts_with("constant expression evaluates to inf"));
        // Not constant, or finite: fine. A parameter or a draw can make the value finite at traversal.
        for src in ["1 / x", "x / 0", "rand() / 0", "noise(0, 0) / 0", "1e30 * 10", "0 ? 1 : 2", "sqrt(4)"] {
            assert!(parse_str(src).is_ok(), "{src}");
        }
        // Built in code (no parser): compile reports it, with an empty span for the caller to fill in.
        let built = Ast::bin(BinOp::Div, Ast::Num(1.0), Ast::bin(BinOp::Sub, Ast::Num(2.0), Ast::Num(2.0)));
        assert_eq!(non_finite_constant(&built), Some(f32::INFINITY));
        let err = compile(&built, &mut |_| None).unwrap_err();
        assert_eq!(err.span, 0..0);
        assert!(err.message.contains("evaluates to inf"), "{}", err.message);
    }

    #[test]
    fn hostile_nesting_is_an_error_not_a_stack_overflow() {
        let deep = format!("{}1{}", "(".repeat(10_000), ")".repeat(10_000));
        assert!(parse_str(&deep).unwrap_err().message.contains("nested deeper"));
        let minus = format!("{}1", "-".repeat(10_000));
        assert!(parse_str(&minus).is_err());
    }
}
