//! The compiler's turtle side: the shared body of each turtle symbol (moves, turns, width, colour, `%` cut and
//! `$` roll to horizontal, with the orientation frame it tracks), as DCG nodes.

use super::*;

impl Compiler<'_> {
    /// The shared body of a turtle symbol, built on first use.
    pub(super) fn turtle_body(&mut self, t: Turtle, span: &Range<usize>) -> Option<()> {
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
                let channels = self.palette_channels(span)?;
                let index = self.color_index(t, c, formals.first().copied(), span)?;
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
    pub(super) fn guard(&mut self, body: NodeId) -> NodeId {
        let Some(x) = self.cut else { return body };
        let empty = self.empty_group();
        self.b.push(Node::Selection { expr: Expr::param(x), children: vec![body, empty] })
    }

    pub(super) fn empty_group(&mut self) -> NodeId {
        match self.empty {
            Some(e) => e,
            None => {
                let e = self.b.push(Node::Group(Vec::new()));
                self.empty = Some(e);
                e
            }
        }
    }

    /// The new colour index of `;`, `,`, `'` or `;(i)` (`i` in slot `arg`). With a `palette`: one up, one down
    /// (not below 1) or `i`. With L-Py's materials, as L-Py's turtle: an index outside `0..=6` leaves it unchanged.
    fn color_index(&mut self, t: Turtle, c: u16, arg: Option<u16>, span: &Range<usize>) -> Option<Expr> {
        let (low, high) = if self.lpy_colors { (0.0, (LPY_MATERIALS.len() - 1) as f32) } else { (1.0, f32::MAX) };
        let ast = match t {
            Turtle::SetColorIndex if self.lpy_colors => {
                let i = Ast::var("$i");
                let inside = Ast::And(
                    Box::new(Ast::bin(BinOp::Ge, i.clone(), Ast::Num(low))),
                    Box::new(Ast::bin(BinOp::Le, i.clone(), Ast::Num(high))),
                );
                Ast::cond(inside, i, Ast::var("$c"))
            }
            Turtle::SetColorIndex => Ast::var("$i"),
            Turtle::ColorDown => Ast::Call(
                canopy_protocol::Func::Max,
                vec![Ast::bin(BinOp::Sub, Ast::var("$c"), Ast::Num(1.0)), Ast::Num(low)],
            ),
            _ if self.lpy_colors => Ast::Call(
                canopy_protocol::Func::Min,
                vec![Ast::bin(BinOp::Add, Ast::var("$c"), Ast::Num(1.0)), Ast::Num(high)],
            ),
            _ => Ast::bin(BinOp::Add, Ast::var("$c"), Ast::Num(1.0)),
        };
        let internal = [("$c", c), ("$i", arg.unwrap_or(c))];
        match compile_at(&ast, &mut self.names.resolver(&[], &internal), span) {
            Ok(e) => Some(e),
            Err(e) => {
                self.errors.push(e);
                None
            }
        }
    }

    /// The palette entry `_c` selects, per channel: `_c <= 1 ? p1 : _c <= 2 ? p2 : … : p_last`; without a
    /// `palette`, L-Py's materials, 0-based: `_c <= 0 ? m0 : _c <= 1 ? m1 : … : m6`.
    pub(super) fn palette_channels(&mut self, span: &Range<usize>) -> Option<[Expr; 3]> {
        let (palette, base) = match self.palette.clone() {
            Some(p) => (p, 1),
            None if self.palette_broken => return None,
            None => {
                self.lpy_colors = true;
                (LPY_MATERIALS.iter().map(|m| m.map(Ast::Num)).collect(), 0)
            }
        };
        let mut channels = Vec::new();
        for k in 0..3 {
            let mut ast = palette[palette.len() - 1][k].clone();
            for i in (0..palette.len() - 1).rev() {
                let test = Ast::bin(BinOp::Le, Ast::var("$c"), Ast::Num((i + base) as f32));
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
    pub(super) fn frame_update(
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
    pub(super) fn roll_to_horizontal(&mut self) -> Option<()> {
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
}
