//! Parametric L-systems: parsing and diagnostics, the shape of the compiled DCG (seed 001 §3.2), and the DCG
//! derivation agreeing bit for bit with ordinary string rewriting.

use canopy_protocol::{Node, ParamScope};
use canopy_worlds::amplify::{Budget, Instance, amplify};
use canopy_worlds::diag::{Diagnostic, SourceFile};
use canopy_worlds::lsystem::{
    DeriveError, LSystem, MAX_BRACKET_NESTING, MAX_FORMALS, MAX_PRODUCTIONS, MAX_SUCCESSOR_LEN, SymbolKind, Turtle,
    interpret, parse_lsystem, reference_stream, rewrite,
};
use canopy_worlds::primitive::{PrimitiveKind, PrimitiveStream, Shape};

fn render(d: &[Diagnostic]) -> String {
    d.iter().map(|d| d.to_string()).collect::<Vec<_>>().join("\n")
}

fn lsys(text: &str) -> LSystem {
    let (l, d) = LSystem::parse(&SourceFile::new("test.lsys", text));
    assert!(d.is_empty(), "{}", render(&d));
    let l = l.unwrap();
    l.graph.validate().unwrap();
    l
}

fn errors(text: &str) -> Vec<Diagnostic> {
    let (l, d) = LSystem::parse(&SourceFile::new("bad.lsys", text));
    assert!(l.is_none() && !d.is_empty(), "expected errors for:\n{text}");
    d
}

/// The library's `.lsys` files (every `.lsys` file of `worlds/species/` is embedded).
fn species_files() -> Vec<(String, String)> {
    let lsys = canopy_worlds::library::SPECIES.iter().filter(|e| e.file.ends_with(".lsys"));
    lsys.map(|e| (e.file.to_string(), e.text.to_string())).collect()
}

fn dcg(l: &LSystem, inst: &Instance) -> PrimitiveStream {
    amplify(&l.graph, inst, &Budget::default()).unwrap()
}

const SEEDS: [u64; 4] = [0, 1, 7, 0x5eed_cafe_f00d];

/// The DCG's primitive stream equals the string-rewriting reference, bit for bit, for every seed and detail level.
fn assert_equivalent(name: &str, l: &LSystem, details: &[u8]) {
    for &seed in &SEEDS {
        for &detail in details {
            let inst = Instance::new(seed).with_detail(detail);
            let graph = dcg(l, &inst);
            let string = reference_stream(l, &inst, &Budget::default()).unwrap();
            assert_eq!(graph.primitives.len(), string.primitives.len(), "{name}: seed {seed} detail {detail}");
            assert_eq!(graph.hash(), string.hash(), "{name}: seed {seed} detail {detail}");
            assert!(graph == string, "{name}: seed {seed} detail {detail}");
        }
    }
}

fn origin(s: &PrimitiveStream, i: usize) -> [f32; 3] {
    let m = s.primitives[i].transform.m;
    [m[3], m[7], m[11]]
}

// ---------------------------------------------------------------------------------------------------------------
// Equivalence with string rewriting.

const DETERMINISTIC: &str = "
derive 4
angle 30
axiom: A(1)
A(x) -> F(x) [ + A(x*0.7) ] [ - A(x*0.7) ] A(x*0.8)
A(x) => F(x*0.5)
";

/// The example of the format's documentation, verbatim.
const CONDITIONAL: &str = "
lsystem Bush                 # name (optional; default from file name)
derive 5                     # derivation depth: an expression, may use `detail` (e.g. `derive 6 - detail`) and params
angle 22.5                   # default turning angle (degrees) for + - & ^ \\ / when written without argument
width 0.1                    # initial line width (turtle state)
param len = 1.0              # species parameter (ParamScope::Local), default expression may draw: uniform(0.8, 1.2)
palette (0.4,0.3,0.2) (0.2,0.6,0.2)   # colours for the ' symbol (colour index), optional
module L(s) = material(0.2, 0.7, 0.2) leaf((0,0,0), (0.1*s, 0.5*s, 0), (0, s, 0), (-0.1*s, 0.5*s, 0))
axiom: A(1) B
A(x) : x > 0.5 -> F(x) [ +(angle) A(x*0.7) ] [ -(angle) A(x*0.7) ]      # condition
A(x) -> F(x) L(1)                                                         # another production
B -> F B : 0.3          # stochastic: probability/weight after the successor
B -> f B : 0.7
A(x) => L(x)            # the terminal (\"all-terminal\") production used once the depth is reached
";

const STOCHASTIC: &str = "
derive 5 - detail
param a = uniform(10, 40)
param shrink = normal(0.7, 0.05)
axiom: X(uniform(0.8, 1.2)) Y
X(l) -> F(l) [ +(a + uniform(-5, 5)) X(l * uniform(0.5, 0.8)) ] &(normal(0, 10)) X(l * shrink) : 2
X(l) : l > 0.3 -> F(l * 0.5) [ -(uniform(0, 90)) X(l * 0.6) ] X(l * 0.7) : 1
X(l) -> F(l) ^(rand() * 20) X(l) : 0.5
X(l) => F(uniform(0.1, 0.2)) '(rand(), 0.5, 0.2) F(l)
Y -> f(uniform(0, 1)) Y F(0.1)
";

const NESTED: &str = "
derive 3
angle 45
axiom: [ [ A ] + [ & [ A ] ] ] A
A -> F [ + F [ - F [ & A ] ] ^ A ] [ [ [ ] ] ] A
A => F
";

const IDENTITY: &str = "
derive 5
angle 30
param p = 0.5
module S = sphere(0.1)
axiom: B(1) C D(2) F
B(t) : t > 100 -> F B(t)           # never applies: B stays B(1) until the end
B(t) => S F(t)
C : chance(p) -> F(0.2) + C        # applies at random, otherwise C stays
C => S
D(t) : t > 5 -> F D(t) : 1         # stochastic, but no condition ever holds: identity, one draw per step
D(t) : t < 0 -> f D(t) : 2
D(t) => F(t) S
";

const NO_FINAL: &str = "
derive 4
angle 20
axiom: A E
A -> F [ + A ] E A
E -> F(0.3) ! E
";

const TURTLE: &str = "
derive 4 - detail
angle 15
width 0.2
palette (1,0,0) (0,1,0) (0,0,1)
axiom: A
A -> F ' [ & ! A ] | [ ^ !(0.05) A ] \\ / ' ' A f(0.5) \\(10) /(5)
A => F(0.2) '(0.5, 0.5, 0.5) F
";

#[test]
fn lsystem_small_grammars_equal_string_rewriting() {
    for (name, text) in [
        ("deterministic", DETERMINISTIC),
        ("conditional", CONDITIONAL),
        ("stochastic", STOCHASTIC),
        ("nested brackets", NESTED),
        ("identity", IDENTITY),
        ("no terminal production", NO_FINAL),
        ("turtle", TURTLE),
    ] {
        let l = lsys(text);
        assert!(!dcg(&l, &Instance::new(3)).primitives.is_empty(), "{name} draws something");
        assert_equivalent(name, &l, &[0, 1, 2]);
    }
}

#[test]
fn lsystem_species_files_equal_string_rewriting() {
    let files = species_files();
    assert!(files.len() >= 2);
    for (name, text) in files {
        let (l, d) = LSystem::parse(&SourceFile::new(&name, text));
        assert!(d.is_empty(), "{}", render(&d));
        assert_equivalent(&name, &l.unwrap(), &[0, 2]);
    }
}

#[test]
fn lsystem_stochastic_choice_follows_the_weights() {
    // B -> F B : 0.3 | f B : 0.7 — count cylinders (F) against moves over many seeds.
    let l = lsys("derive 50\naxiom: B\nB -> F B : 0.3\nB -> f B : 0.7\n");
    let mut f = 0usize;
    let n = 40u64;
    for seed in 0..n {
        f += dcg(&l, &Instance::new(seed)).primitives.len();
    }
    let share = f as f64 / (n as f64 * 50.0);
    assert!((share - 0.3).abs() < 0.05, "share of F is {share}");
    // Different seeds give different plants, the same seed the same plant.
    assert_ne!(dcg(&l, &Instance::new(1)).hash(), dcg(&l, &Instance::new(2)).hash());
    assert_eq!(dcg(&l, &Instance::new(1)).hash(), dcg(&l, &Instance::new(1)).hash());
}

#[test]
fn lsystem_worm_primitive_count_equals_the_strings() {
    // Seed 001, Figure 1: Worm(c) -> Sphere Translation Worm(c-1) while c > 0, else Cone.
    let worm = "
lsystem Worm
param c0 = 4
param depth = 10
derive depth
module Cone = cone(0.5, 0, 1)
module Sphere = sphere(0.5)
axiom: Worm(c0)
Worm(c) : c > 0 -> Sphere f(1) Worm(c - 1)
Worm(c) -> Cone
Worm(c) => Cone
";
    let l = lsys(worm);
    let (c0, depth) = (l.graph.param_slot("c0").unwrap(), l.graph.param_slot("depth").unwrap());
    for c in [0.0f32, 1.0, 4.0, 9.0] {
        for d in [0.0f32, 1.0, 3.0, 6.0, 12.0] {
            let inst = Instance { seed: 5, params: vec![(c0, c), (depth, d)], detail: 0 };
            let graph = dcg(&l, &inst);
            let string = rewrite(&l, &inst, None).unwrap();
            assert_eq!(graph.primitives.len(), l.primitive_count(&string), "c = {c}, depth = {d}");
            // Spheres while both the counter and the depth last, then one cone.
            assert_eq!(graph.primitives.len(), c.min(d) as usize + 1, "c = {c}, depth = {d}");
            assert_eq!(graph.primitives.last().unwrap().shape.kind(), PrimitiveKind::Cone);
            assert_eq!(interpret(&l, &inst, &string, &Budget::default()).unwrap(), graph);
        }
    }
    // The same worm drawn with the turtle: F is a cylinder and a move.
    let l = lsys("derive 9\naxiom: W(4)\nW(c) : c > 0 -> F(0.5) W(c - 1)\nW(c) => F(2)\n");
    let inst = Instance::new(0);
    let s = dcg(&l, &inst);
    assert_eq!(s.primitives.len(), l.primitive_count(&rewrite(&l, &inst, None).unwrap()));
    assert_eq!(s.primitives.len(), 5, "W(0) has no applicable production: it stays, and its `=>` is used at the end");
}

#[test]
fn lsystem_rewrite_steps_override_the_depth() {
    let l = lsys(DETERMINISTIC);
    let inst = Instance::new(0);
    let a = |s: &str| l.symbol(s).unwrap();
    // No steps: the axiom's A(1) is replaced by its terminal production F(0.5).
    let s0 = rewrite(&l, &inst, Some(0)).unwrap();
    assert_eq!(s0.len(), 1);
    assert_eq!((s0[0].symbol, s0[0].args.clone()), (Turtle::Forward.id(), vec![0.5]));
    // One step: F(1) [ + F(0.35) ] [ - F(0.35) ] F(0.4).
    let s1 = rewrite(&l, &inst, Some(1)).unwrap();
    let names: Vec<&str> = s1.iter().map(|m| l.symbols[m.symbol as usize].name.as_str()).collect();
    assert_eq!(names.join(""), "F[+F][-F]F");
    assert_eq!(l.primitive_count(&s1), 4);
    // The derive expression's own depth gives the DCG's result.
    assert_eq!(rewrite(&l, &inst, None).unwrap(), rewrite(&l, &inst, Some(4)).unwrap());
    assert_ne!(a("A"), Turtle::Forward.id());
}

// ---------------------------------------------------------------------------------------------------------------
// The shape of the DCG.

#[test]
fn lsystem_graph_has_the_seed_001_shape() {
    let l = lsys(CONDITIONAL);
    let g = &l.graph;
    // Slots: species params (angle), then _d, _w, _c, then one per formal.
    let slot = |n: &str| g.param_slot(n).unwrap_or_else(|| panic!("no slot {n}"));
    assert_eq!((slot("angle"), slot("len")), (0, 1));
    assert_eq!((slot("_d"), slot("_w"), slot("_c")), (2, 3, 4));
    assert_eq!(g.params[slot("_d") as usize].scope, ParamScope::Local);
    assert_eq!(g.params[slot("_w") as usize].scope, ParamScope::Turtle);
    assert_eq!(g.params[slot("_c") as usize].scope, ParamScope::Turtle);
    assert_eq!(g.params[slot("A.x") as usize].scope, ParamScope::Local);
    assert!(g.param_slot("L.s").is_some() && g.param_slot("F.l").is_some());

    // Root: Group[Calc(_d = derive, _w = width, _c = 0), axiom…].
    let Node::Group(root) = &g.nodes[g.root as usize] else { panic!("root is a group") };
    let Node::Calculation(init) = &g.nodes[root[0] as usize] else { panic!("root starts with a calculation") };
    assert_eq!(init.iter().map(|a| a.0).collect::<Vec<_>>(), [slot("_d"), slot("_w"), slot("_c")]);

    // A: two productions, identity, final.
    let a = &l.symbols[l.symbol("A").unwrap() as usize];
    assert_eq!(a.kind, SymbolKind::NonTerminal);
    let sel = a.selection.unwrap();
    let Node::Selection { children, expr } = &g.nodes[sel as usize] else { panic!("A is a selection") };
    assert_eq!(children.len(), 4);
    assert_eq!(Some(expr), a.select.as_ref());
    // rhs_0 = Group[Calc(_d = _d - 1), F…, Separator[…RecursionSeparator[Calc(A.x = …), A]], Separator[…]].
    let Node::Group(rhs) = &g.nodes[children[0] as usize] else { panic!("rhs is a group") };
    assert!(matches!(&g.nodes[rhs[0] as usize], Node::Calculation(c) if c.len() == 1 && c[0].0 == slot("_d")));
    let Node::Separator(branch) = &g.nodes[rhs[3] as usize] else { panic!("[ ] is a separator: {:?}", rhs) };
    let Node::RecursionSeparator(call) = &g.nodes[*branch.last().unwrap() as usize] else { panic!("a call") };
    assert!(matches!(&g.nodes[call[0] as usize], Node::Calculation(c) if c[0].0 == slot("A.x")));
    assert_eq!(call[1], sel, "the link back to A's selection node is the cycle");
    // identity = Group[Calc(_d = _d - 1), RecursionSeparator[Calc(A.x = A.x), A]].
    let Node::Group(id) = &g.nodes[children[2] as usize] else { panic!("identity is a group") };
    assert_eq!(id[0], rhs[0], "the decrement is one shared node");
    let Node::RecursionSeparator(call) = &g.nodes[id[1] as usize] else { panic!("identity calls A") };
    assert_eq!(call[1], sel);
    // final = Group[Calc(L.s = A.x), L].
    let Node::Group(fin) = &g.nodes[children[3] as usize] else { panic!("final is a group") };
    assert_eq!(fin.len(), 2);
    assert_eq!(Some(fin[1]), l.symbols[l.symbol("L").unwrap() as usize].body);

    // F is drawn by one shared body node, however often it appears.
    let cylinders = g.nodes.iter().filter(|n| matches!(n, Node::Cylinder { .. })).count();
    assert_eq!(cylinders, 1);
    let leaves = g.nodes.iter().filter(|n| matches!(n, Node::Leaf { .. })).count();
    assert_eq!(leaves, 1);
}

#[test]
fn lsystem_arguments_are_evaluated_once() {
    // F(l) uses l for the cylinder and for the move: one draw, both places.
    let l = lsys("derive 1\nmodule S = sphere(0.1)\naxiom: F(uniform(1, 2)) S\n");
    for seed in 0..8 {
        let s = dcg(&l, &Instance::new(seed));
        let Shape::Cylinder { height, .. } = s.primitives[0].shape else { panic!("a cylinder") };
        assert!((1.0..2.0).contains(&height));
        assert_eq!(origin(&s, 1), [0.0, height, 0.0]);
    }
}

#[test]
fn lsystem_turtle_symbols_move_turn_and_restore() {
    let l = lsys("derive 0\nangle 90\nwidth 0.5\nmodule S = sphere(1)\naxiom: F(2) [ + F(1) S ] ! F(1) S\n");
    let s = dcg(&l, &Instance::new(0));
    let close = |a: [f32; 3], b: [f32; 3]| a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-6);
    assert!(close(origin(&s, 0), [0.0, 0.0, 0.0]));
    // `+` turns the heading (+Y) by 90° about Z towards -X.
    assert!(close(origin(&s, 2), [-1.0, 2.0, 0.0]), "{:?}", origin(&s, 2));
    // `]` restores position and width; `!` then thins the next cylinder.
    assert_eq!(s.primitives[1].shape, Shape::Cylinder { radius: 0.5, height: 1.0 });
    assert_eq!(s.primitives[3].shape, Shape::Cylinder { radius: 0.5 * 0.7, height: 1.0 });
    assert!(close(origin(&s, 4), [0.0, 3.0, 0.0]));
}

#[test]
fn lsystem_palette_colours_advance_and_clamp() {
    let l = lsys("derive 0\npalette (1,0,0) (0,1,0)\nmodule S = sphere(1)\naxiom: S ' S [ ' S ] S ' ' ' S\n");
    let s = dcg(&l, &Instance::new(0));
    let colors: Vec<[f32; 3]> = s.primitives.iter().map(|p| p.color).collect();
    assert_eq!(colors, [[0.8, 0.8, 0.8], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]);
}

#[test]
fn lsystem_width_and_colour_flow_across_recursion() {
    // `!` and `'` inside A's production affect what follows A's call: they are turtle state, not locals.
    let l = lsys("derive 1\nwidth 1\npalette (1,0,0)\naxiom: A F\nA -> ! '\n");
    let s = dcg(&l, &Instance::new(0));
    assert_eq!(s.primitives[0].shape, Shape::Cylinder { radius: 0.7, height: 1.0 });
    assert_eq!(s.primitives[0].color, [1.0, 0.0, 0.0]);
}

#[test]
fn lsystem_parse_lsystem_returns_the_graph() {
    let (g, d) = parse_lsystem(&SourceFile::new("dir/my_plant.lsys", DETERMINISTIC));
    assert!(d.is_empty());
    assert_eq!(g.unwrap().name, "my_plant");
    let (g, _) = parse_lsystem(&SourceFile::new("x.lsys", CONDITIONAL));
    assert_eq!(g.unwrap().name, "Bush");
}

// ---------------------------------------------------------------------------------------------------------------
// Diagnostics.

#[test]
fn lsystem_undefined_symbol_has_a_caret() {
    let d = errors("derive 2\naxiom: A\nA -> F Bee F\n");
    assert_eq!(d.len(), 1, "{}", render(&d));
    assert_eq!((d[0].line, d[0].col, d[0].width), (3, 8, 3));
    assert!(d[0].message.contains("undefined symbol `Bee`"), "{}", d[0].message);
    assert_eq!(
        d[0].to_string(),
        format!("bad.lsys:3:8: error: {}\n  |\n3 | A -> F Bee F\n  |        ^^^", d[0].message)
    );
    let d = errors("derive 2\naxiom: FF\n");
    assert!(d[0].message.contains("separate symbols with spaces: `F F`"), "{}", d[0].message);
}

#[test]
fn lsystem_errors_are_reported_per_line() {
    let d = errors(
        "derive 3\n\
         axiom: A(1)\n\
         A(x) -> F(x +) A(x)\n\
         A(x) => F A(x)\n\
         B(x, y) -> F(x, y)\n\
         C -> [ F ] ]\n\
         D -> [ F\n\
         E -> F B(1)\n\
         F -> F F\n\
         module M(s) = sphere(uniform(0, s))\n\
         G -> M(1) H\n",
    );
    let lines: Vec<usize> = d.iter().map(|d| d.line).collect();
    assert_eq!(lines, [3, 4, 5, 6, 7, 8, 9, 10, 11], "{}", render(&d));
    let has = |line: usize, text: &str| {
        assert!(d.iter().any(|d| d.line == line && d.message.contains(text)), "line {line}: {text}\n{}", render(&d))
    };
    has(3, "expected an expression");
    has(4, "may only contain terminals, but `A` is a non-terminal");
    has(5, "`F` takes 0 or 1 argument(s), got 2");
    has(6, "unmatched `]`");
    has(7, "unclosed `[`");
    has(8, "`B` takes 2 argument(s), got 1");
    has(9, "turtle symbol and cannot be rewritten");
    has(10, "may not draw random numbers");
    has(11, "undefined symbol `H`");
}

#[test]
fn lsystem_other_mistakes_are_diagnosed() {
    let one = |text: &str, want: &str| {
        let d = errors(text);
        assert!(d.iter().any(|d| d.message.contains(want)), "want `{want}`:\n{}", render(&d));
    };
    one("axiom: F\n", "missing `derive");
    one("derive 1\n", "missing `axiom");
    // (`+` without an `angle` and `;` without a `palette` take L-Py's defaults: see tests/lsystem_lpy.rs.)
    one("derive 1\naxiom: ;(1, 2)\n", "`;` takes 0 or 1 argument(s), got 2");
    one("derive 1\naxiom: A\nA(x) -> F\n", "`A` takes 1 argument(s), got 0");
    one("derive 1\naxiom: A(1)\nA(x) -> F\nA(x, y) -> F\n", "parameter(s) in its first production (line 3)");
    one("derive 1\naxiom: A\nA -> F\nA => F\nA => f\n", "second terminal production");
    one("derive 1\naxiom: L\nmodule L = sphere(1)\nL -> F\n", "cannot have productions");
    one("derive 1\naxiom: A\nA(x, x) -> F\n", "appears twice");
    one("derive 1\nparam a = 1\nparam a = 2\naxiom: F\n", "declared twice");
    one("derive 1\nparam a = b\nparam b = 1\naxiom: F\n", "unknown parameter `b`");
    one("derive 1\naxiom: F(q)\n", "unknown parameter `q`");
    one("derive 1\naxiom: A\nA => F : 0.5\n", "takes no probability");
    one("derive 1\naxiom: A\nA : 1 => F\n", "takes no condition");
    one("derive 1\naxiom: F\nmodule S = sphere(1) frobnicate(2)\n", "unknown node call `frobnicate`");
    one("derive 1\naxiom: F\nwhat is this\n", "expected `->` or `=>`");
    one("derive 1\naxiom: F ?\n", "expected a module");
}

#[test]
fn lsystem_limits_are_enforced() {
    let one = |text: String, want: &str| {
        let d = errors(&text);
        assert!(d.iter().any(|d| d.message.contains(want)), "want `{want}`:\n{}", render(&d));
    };
    let n = MAX_BRACKET_NESTING + 1;
    one(format!("derive 1\naxiom: {}F{}\n", "[".repeat(n), "]".repeat(n)), "nested deeper");
    let formals: Vec<String> = (0..=MAX_FORMALS).map(|i| format!("p{i}")).collect();
    one(format!("derive 1\naxiom: F\nA({}) -> F\n", formals.join(", ")), "more than 64 parameters");
    one(format!("derive 1\naxiom: {}\n", "F ".repeat(MAX_SUCCESSOR_LEN + 1)), "at most 4096 modules");
    one(format!("derive 1\naxiom: A\n{}", "A -> F\n".repeat(MAX_PRODUCTIONS + 1)), "more than 256 productions");
    let many: String = (0..300).map(|i| format!("module S{i} = sphere(1)\n")).collect();
    one(format!("derive 1\naxiom: F\n{many}"), "more than 256 symbols");
    one(format!("derive 1\naxiom: A\n{}", "A -> F : 1\n".repeat(65)), "at most 64 productions");
    // At the limits everything still works: the longest successor and the deepest brackets.
    let l = lsys(&format!("derive 1\naxiom: {}\n", "F ".repeat(MAX_SUCCESSOR_LEN)));
    assert_eq!(dcg(&l, &Instance::new(0)).primitives.len(), MAX_SUCCESSOR_LEN);
    let n = MAX_BRACKET_NESTING;
    let l = lsys(&format!("derive 1\naxiom: {}F{}\n", "[".repeat(n), "]".repeat(n)));
    assert_eq!(dcg(&l, &Instance::new(0)).primitives.len(), 1);
}

#[test]
fn lsystem_runaway_depth_ends_in_an_error() {
    let l = lsys("derive 1e9\naxiom: A\nA -> F A\n");
    assert!(amplify(&l.graph, &Instance::new(0), &Budget::default()).is_err());
    assert!(rewrite(&l, &Instance::new(0), None).is_err());
}

// ---------------------------------------------------------------------------------------------------------------
// The species files.

/// Height range (metres) each species file is meant to have.
fn expected_height(name: &str) -> (f32, f32) {
    match name {
        "bush.lsys" => (2.0, 5.0),
        "stochastic_weed.lsys" => (0.6, 1.5),
        _ => (0.1, 100.0),
    }
}

#[test]
fn lsystem_species_files_parse_and_amplify() {
    for (name, text) in species_files() {
        let (l, d) = LSystem::parse(&SourceFile::new(&name, text));
        assert!(d.is_empty(), "{}", render(&d));
        let l = l.unwrap();
        println!(
            "{name}: {} nodes, {} parameter slots, {} bytes encoded",
            l.graph.nodes.len(),
            l.graph.params.len(),
            l.graph.encode().len()
        );
        for seed in [0u64, 1, 2, 3] {
            let full = amplify(&l.graph, &Instance::new(seed), &Budget::default()).unwrap();
            let coarse = amplify(&l.graph, &Instance::new(seed).with_detail(2), &Budget::default()).unwrap();
            let n = full.primitives.len();
            assert!((1_000..=20_000).contains(&n), "{name}: {n} primitives");
            assert!(coarse.primitives.len() < n, "{name}: detail 2 has {} >= {n}", coarse.primitives.len());
            let top = full.primitives.iter().map(|p| p.transform.m[7]).fold(f32::MIN, f32::max);
            let (lo, hi) = expected_height(&name);
            assert!(top > lo && top < hi, "{name}: {top} m tall");
            println!(
                "{name} seed {seed}: {n} primitives {:?}, detail 2: {}, {top:.2} m",
                full.counts(),
                coarse.primitives.len()
            );
        }
    }
}

// ---------------------------------------------------------------------------------------------------------------
// Syntax users bring from ABOP and L-Py.

/// `%` inside branches, at the top level, after random draws and inside a terminal production.
const CUT: &str = "
derive 5 - detail
angle 25
axiom: A(0) [ & F % F A(0) ] F(0.5)
A(n) : n > 2 -> F(uniform(0.5, 1)) % F A(n + 1)
A(n) -> F(uniform(0.5, 1)) [ + A(n + 1) % F(uniform(0, 1)) A(n) ] [ - F A(n + 1) ] F(uniform(0.5, 1)) A(n + 1)
A(n) => F(0.2) [ % F ] F
";

#[test]
fn lsystem_cut_equals_string_rewriting() {
    let l = lsys(CUT);
    assert_equivalent("cut", &l, &[0, 1, 2]);
    // The reference removes every `%` with the rest of its branch during the derivation.
    let string = rewrite(&l, &Instance::new(3), None).unwrap();
    assert!(string.iter().all(|m| m.symbol != Turtle::Cut.id()));
    // Without the cuts the plant is bigger.
    let uncut = lsys(&CUT.replace('%', ""));
    let (a, b) = (dcg(&l, &Instance::new(3)), dcg(&uncut, &Instance::new(3)));
    assert!(a.primitives.len() < b.primitives.len(), "{} >= {}", a.primitives.len(), b.primitives.len());
}

#[test]
fn lsystem_cut_removes_the_rest_of_the_branch() {
    let l = lsys("derive 0\naxiom: F(1) [ F(2) [ F(3) ] % F(4) [ F(5) ] F(6) ] F(7) % F(8) [ F(9) ]\n");
    let s = dcg(&l, &Instance::new(0));
    let heights: Vec<f32> =
        s.primitives.iter().map(|p| if let Shape::Cylinder { height, .. } = p.shape { height } else { 0.0 }).collect();
    assert_eq!(heights, [1.0, 2.0, 3.0, 7.0]);
    assert_eq!(reference_stream(&l, &Instance::new(0), &Budget::default()).unwrap(), s);
    // A cut branch calls nothing: the non-terminal after `%` is not expanded (its `=>` would draw).
    let l = lsys("derive 3\naxiom: [ % A ] F\nA -> F A\nA => F\n");
    assert_eq!(dcg(&l, &Instance::new(0)).primitives.len(), 1);
}

/// `$` after turns, pitches and rolls, in branches and across recursion.
const ROLL: &str = "
derive 4
angle 30
axiom: A
A -> F [ & + A $ F ] / / & A $ [ ^ - F A ] \\ | F
A => F $ F
";

#[test]
fn lsystem_roll_to_horizontal_equals_string_rewriting() {
    let l = lsys(ROLL);
    assert_equivalent("roll to horizontal", &l, &[0, 1]);
}

#[test]
fn lsystem_roll_to_horizontal_levels_the_left_vector() {
    let l = lsys("derive 0\nangle 35\naxiom: & + / / & - F(1) $ F(1) [ ^ ^ $ F(1) ] | & $ F(1)\n");
    let s = dcg(&l, &Instance::new(0));
    // Column j of the rotation is the local axis j; left is -X, the heading Y.
    let col = |i: usize, j: usize| {
        let m = s.primitives[i].transform.m;
        [m[j], m[4 + j], m[8 + j]]
    };
    assert!(col(0, 0)[1].abs() > 0.1, "the first cylinder's left vector is tilted: {:?}", col(0, 0));
    for i in 1..4 {
        assert!(col(i, 0)[1].abs() < 1e-5, "cylinder {i}: left vector {:?} not horizontal", col(i, 0));
        let x = col(i, 0);
        assert!((x[0] * x[0] + x[2] * x[2] - 1.0).abs() < 1e-5, "cylinder {i}: still a unit vector");
    }
    // `$` rolls about the heading: the heading does not change.
    let (h0, h1) = (col(0, 1), col(1, 1));
    assert!(h0.iter().zip(h1).all(|(a, b)| (a - b).abs() < 1e-5), "{h0:?} -> {h1:?}");
    // Left is horizontal and up points up: the heading's side of the frame faces the sky.
    assert!(col(1, 2)[1] > 0.0, "up vector {:?}", col(1, 2));
}

/// Interpretation rules: a non-terminal drawn by its rule at the end, a terminal that is only interpreted.
const HOMOMORPHISM: &str = "
derive 4 - detail
angle 20
palette (0.3,0.2,0.1) (0.2,0.6,0.2)
Axiom: A(1)
production:
A(s) -> I(s) [ + A(s * 0.8) Bud(s) ] [ - A(s * 0.7) ] I(s) A(s * 0.9)
I(s) -> I(s) I(s * 0.5)
interpretation:
I(l) --> F(l * 0.3) !
A(s) --> [ ' & F(0.1 * s) ]
homomorphism:
Bud(r) -> , f(r * 0.1) ' F(0.05)
";

#[test]
fn lsystem_interpretation_rules_equal_string_rewriting() {
    let l = lsys(HOMOMORPHISM);
    assert_equivalent("homomorphism", &l, &[0, 1, 2]);
    // The rules apply only when drawing: the derived string still holds `I`, `A` and `Bud`.
    let inst = Instance::new(1);
    let string = rewrite(&l, &inst, None).unwrap();
    for name in ["I", "A", "Bud"] {
        let id = l.symbol(name).unwrap();
        assert!(string.iter().any(|m| m.symbol == id), "`{name}` is left in the string");
    }
    assert_eq!(l.primitive_count(&string), dcg(&l, &inst).primitives.len());
    // `I(s)` is still rewritten by its production: after one step the three `A`s make two each and the two `I`s
    // double.
    let i = l.symbol("I").unwrap();
    let count = |steps| rewrite(&l, &inst, Some(steps)).unwrap().iter().filter(|m| m.symbol == i).count();
    assert_eq!((count(1), count(2)), (2, 10));
    // An interpretation rule of a non-terminal draws what a terminal production would.
    let terminal =
        lsys(&HOMOMORPHISM.replace("I(l) --> F(l * 0.3) !\n", "").replace("production:\n", "I(l) => F(l * 0.3) !\n"));
    assert_eq!(dcg(&terminal, &inst), dcg(&l, &inst));
}

#[test]
fn lsystem_colour_index_up_and_down() {
    let l = lsys(
        "derive 0\npalette (1,0,0) (0,1,0) (0,0,1)\nmodule S = sphere(1)\naxiom: S ; S ; S , S , , S ;(3) S ,(2) S [ ; S ] S\n",
    );
    let s = dcg(&l, &Instance::new(0));
    let colors: Vec<[f32; 3]> = s.primitives.iter().map(|p| p.color).collect();
    let (r, g, b) = ([1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]);
    assert_eq!(colors, [[0.8, 0.8, 0.8], r, g, r, r, b, g, b, g]);
    // In a recursive grammar, against the reference.
    let l = lsys(
        "derive 4\nangle 30\npalette (1,0,0) (0,1,0) (0,0,1) (1,1,0)\naxiom: A\nA -> F ; [ + A , F ] ;(2) A , F\nA => , F ; F\n",
    );
    assert_equivalent("colour index", &l, &[0, 1]);
}

#[test]
fn lsystem_define_constants() {
    let text = "#define LEN 0.5\n  #define\tANG 10 * 3   # a comment\nderive 3\naxiom: A\nA -> F(LEN) [ +(ANG) A ] A\n";
    let l = lsys(text);
    assert!(l.graph.param_slot("LEN").is_some() && l.graph.param_slot("ANG").is_some());
    assert_equivalent("define", &l, &[0]);
    let spelled = lsys("param LEN = 0.5\nparam ANG = 10 * 3\nderive 3\naxiom: A\nA -> F(LEN) [ +(ANG) A ] A\n");
    assert_eq!(dcg(&l, &Instance::new(0)), dcg(&spelled, &Instance::new(0)));
    // A broken `#define` is an error on its line, and its name is not reported again where it is used.
    let d = errors("derive 1\n#define LEN\naxiom: F(LEN)\n");
    assert_eq!(d.len(), 1, "{}", render(&d));
    assert_eq!((d[0].line, d[0].message.contains("expected an expression")), (2, true), "{}", render(&d));
    // `#` followed by anything else is still a comment.
    lsys("#defined behaviour\n#include nothing\nderive 1\naxiom: F\n");
}

#[test]
fn lsystem_lpy_spellings_are_accepted() {
    let a = lsys("derivation length: 3\nangle 30\nAxiom: A\nA --> F [ + A ] A\n");
    let b = lsys("derive 3\nangle 30\naxiom: A\nA -> F [ + A ] A\n");
    assert_eq!(dcg(&a, &Instance::new(0)), dcg(&b, &Instance::new(0)));
}

#[test]
fn lsystem_context_sensitive_rules_are_explained() {
    let d = errors("derive 1\naxiom: A B\nA < B > C -> F\nB -> F\n");
    assert_eq!(d.len(), 1, "{}", render(&d));
    assert_eq!((d[0].line, d[0].col), (3, 3));
    assert!(d[0].message.contains("context-sensitive productions are not supported"), "{}", d[0].message);
    assert!(d[0].message.contains("left context") && d[0].message.contains("seed 001 §3.2"), "{}", d[0].message);
    let d = errors("derive 1\naxiom: A(1) B\nA(x) > B -> F\nB -> F\n");
    assert_eq!((d[0].line, d[0].col), (3, 6));
    assert!(d[0].message.contains("right context"), "{}", d[0].message);
}

#[test]
fn lsystem_decomposition_sections_are_explained() {
    let d = errors("derive 1\naxiom: A\nA -> F A\ndecomposition:\nA -> F F\nB(x) < C -> F\ninterpretation:\nA -> F\n");
    assert_eq!(d.len(), 1, "only the header is reported:\n{}", render(&d));
    assert_eq!((d[0].line, d[0].col, d[0].width), (4, 1, 14));
    assert!(d[0].message.contains("`decomposition:` sections are not supported"), "{}", d[0].message);
}

#[test]
fn lsystem_interpretation_mistakes_are_diagnosed() {
    let one = |text: &str, line: usize, want: &str| {
        let d = errors(text);
        assert!(d.iter().any(|d| d.line == line && d.message.contains(want)), "want `{want}`:\n{}", render(&d));
    };
    let head = "derive 1\naxiom: A B\nA -> F A\nB -> F\n";
    one(&format!("{head}interpretation:\nA => F\n"), 6, "written with `->`");
    one(&format!("{head}interpretation:\nA : 1 -> F\n"), 6, "takes no condition");
    one(&format!("{head}interpretation:\nA -> F(uniform(1, 2))\n"), 6, "may not draw random numbers");
    one(&format!("{head}interpretation:\nA -> F\nA -> f\n"), 7, "second interpretation rule");
    one(&format!("{head}interpretation:\nA -> B\n"), 6, "may only contain terminals");
    one(&format!("{head}module M = sphere(1)\ninterpretation:\nM -> F\n"), 7, "defined by `module`");
    one(&format!("{head}A => F\ninterpretation:\nA -> F\n"), 3, "both a terminal production");
    one(
        "derive 1\naxiom: L(1)\ninterpretation:\nL(s) -> F(s) P\nP -> f\n",
        4,
        "which has an interpretation rule itself",
    );
    one(&format!("{head}interpretation:\nA(x) -> F\n"), 6, "parameter(s) in its first production");
    // A broken module used by an interpretation rule: errors, no panic.
    one("derive 1\naxiom: X\nmodule M = frobnicate(1)\ninterpretation:\nX -> M F\n", 3, "unknown node call");
}

// ---------------------------------------------------------------------------------------------------------------
// Derivation depth.

#[test]
fn lsystem_depth_error_names_the_derivation_and_the_production() {
    let l = lsys("derive 2000\nangle 10\naxiom: B A\nA -> F A   # apex\nB -> F [ + B ] B\n");
    let e = l.amplify(&Instance::new(0), &Budget::default()).unwrap_err();
    let msg = e.to_string();
    assert!(matches!(e, DeriveError::TooDeep { limit: 1024, .. }), "{msg}");
    assert!(msg.contains("derivation depth 2000"), "{msg}");
    assert!(msg.contains("test.lsys:5:1 `B -> F [ + B ] B` nests 2 level(s)"), "{msg}");
    assert!(msg.contains("`maxdepth N` (at most 8192)"), "{msg}");
    assert!(!msg.contains("separator"), "{msg}");
    // Within the limit nothing changes.
    let l = lsys("derive 1000\naxiom: A\nA -> F A\n");
    assert_eq!(l.amplify(&Instance::new(0), &Budget::default()).unwrap().primitives.len(), 1000);
}

#[test]
fn lsystem_maxdepth_raises_the_limit() {
    let text = "derive 3000\nmaxdepth 4000\naxiom: A\nA -> F(0.01) A\nA => F\n";
    let l = lsys(text);
    assert_eq!(l.max_depth, 4000);
    // The graph carries the request, so plain amplification honours it too, and agrees with string rewriting.
    let s = amplify(&l.graph, &Instance::new(0), &Budget::default()).unwrap();
    assert_eq!(s.primitives.len(), 3001);
    assert_eq!(l.amplify(&Instance::new(0), &Budget::default()).unwrap(), s);
    assert_eq!(reference_stream(&l, &Instance::new(0), &Budget::default()).unwrap(), s);
    // Still bounded: past the file's limit the error names it.
    let l = lsys("derive 5000\nmaxdepth 4000\naxiom: A\nA -> F A\n");
    let e = l.amplify(&Instance::new(0), &Budget::default()).unwrap_err();
    assert!(matches!(e, DeriveError::TooDeep { limit: 4000, .. }), "{e}");
    // A larger budget is not lowered by a smaller `maxdepth`.
    let l = lsys("derive 10\nmaxdepth 5\naxiom: A\nA -> F A\n");
    assert_eq!(l.max_depth, 1024);
    assert_eq!(dcg(&l, &Instance::new(0)).primitives.len(), 10);
    for bad in ["0", "8193", "1.5", "-3", "len"] {
        let d = errors(&format!("derive 1\nmaxdepth {bad}\naxiom: F\n"));
        assert!(d.iter().any(|d| d.line == 2), "{bad}: {}", render(&d));
    }
    let d = errors("derive 1\nmaxdepth 9000\naxiom: F\n");
    assert!(d[0].message.contains("whole number from 1 to 8192"), "{}", d[0].message);
    let d = errors("derive 1\nmaxdepth 2000\nmaxdepth 3000\naxiom: F\n");
    assert!(d[0].message.contains("`maxdepth` given twice"), "{}", d[0].message);
}

#[test]
fn lsystem_format_doc_example_compiles_and_equals_string_rewriting() {
    let src = include_str!("../src/lsystem/mod.rs");
    let start = src.find("//! ```text\n").expect("the format doc has an example") + "//! ```text\n".len();
    let end = start + src[start..].find("//! ```\n").expect("the example ends");
    let text: String =
        src[start..end].lines().map(|l| format!("{}\n", l.trim_start_matches("//!").trim_start())).collect();
    assert!(text.contains("interpretation:") && text.contains("#define"), "{text}");
    let (l, d) = LSystem::parse(&SourceFile::new("doc.lsys", text));
    assert!(d.is_empty(), "{}", render(&d));
    let l = l.unwrap();
    assert_eq!(l.max_depth, 2048);
    assert!(l.symbols[l.symbol("B").unwrap() as usize].interpretation.is_some());
    assert_equivalent("format doc", &l, &[0, 1]);
}

#[test]
fn lsystem_mangled_new_syntax_never_panics() {
    // Every grammar above with one character removed, and cut short at every character: diagnostics or an
    // L-system, never a panic.
    for text in
        [CUT, ROLL, HOMOMORPHISM, "#define A 1\nmaxdepth 2000\nderive A\naxiom: B ; , $ %\ndecomposition:\nB -> F\n"]
    {
        let chars: Vec<(usize, char)> = text.char_indices().collect();
        for &(i, c) in &chars {
            let removed = format!("{}{}", &text[..i], &text[i + c.len_utf8()..]);
            let _ = LSystem::parse(&SourceFile::new("m.lsys", removed));
            let _ = LSystem::parse(&SourceFile::new("m.lsys", &text[..i]));
        }
    }
}
