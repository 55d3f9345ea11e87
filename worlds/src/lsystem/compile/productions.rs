//! The compiler's derivation side: a non-terminal's productions (conditions, probabilities, the derivation-depth
//! guard) as a selection over their successors, and successor strings emitted as DCG nodes.

use super::*;

impl Compiler<'_> {
    pub(super) fn non_terminal(&mut self, id: SymbolId, prods: &[&Production]) {
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
    pub(super) fn emit(&mut self, succ: &[Successor]) -> Vec<NodeId> {
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
