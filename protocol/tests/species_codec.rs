//! The species graph encoding: byte snapshot, round trip, and rejection of malformed or hostile bytes.

use canopy_protocol::expr::ExprError;
use canopy_protocol::{
    DecodeError, Expr, Node, Op, ParamDecl, ParamRole, ParamScope, SpeciesGraph, ValidateError, limits,
};

/// Worm(4) of seed 001 Figure 2, built by hand.
fn worm() -> SpeciesGraph {
    let g = SpeciesGraph {
        name: "Worm".into(),
        params: vec![ParamDecl {
            name: "c".into(),
            default: Expr::constant(4.0),
            scope: ParamScope::Local,
            role: ParamRole::Parameter,
        }],
        nodes: vec![
            Node::Selection { expr: Expr { ops: vec![Op::Param(0), Op::Const(0.0), Op::Gt] }, children: vec![1, 2] },
            Node::Cone { bottom: Expr::constant(0.5), top: Expr::constant(0.0), height: Expr::constant(1.0) },
            Node::Separator(vec![3, 4, 5, 6]),
            Node::Sphere { radius: Expr::constant(0.5) },
            Node::Translate([Expr::constant(1.0), Expr::constant(0.0), Expr::constant(0.0)]),
            Node::Calculation(vec![(0, Expr { ops: vec![Op::Param(0), Op::Const(1.0), Op::Sub] })]),
            Node::RecursionSeparator(vec![0]),
        ],
        root: 0,
    };
    assert_eq!(g.validate(), Ok(()));
    g
}

#[test]
fn worm_encoding_is_pinned() {
    // postcard is not self-describing: this snapshot pins the wire form of every node used here.
    let bytes = worm().encode();
    let hex: String = bytes.iter().map(|b| format!("{b:02x}")).collect();
    assert_eq!(hex, WORM_HEX, "the species wire format changed; bump the protocol version if intended");
    assert_eq!(SpeciesGraph::decode(&bytes), Ok(worm()));
}

const WORM_HEX: &str = "04576f726d0101630100000080400000070303010000000000000d0201020a01000000003f01000000000001000000803f0104030405060c01000000003f0501000000803f010000000000010000000000040100030100000000803f0602010000";

#[test]
fn every_node_kind_round_trips() {
    let k = || Expr::constant(1.0);
    let g = SpeciesGraph {
        name: "all".into(),
        params: vec![ParamDecl {
            name: "w".into(),
            default: Expr { ops: vec![Op::Call(canopy_protocol::Func::Rand)] },
            scope: ParamScope::Turtle,
            role: ParamRole::Working,
        }],
        nodes: vec![
            Node::Group((1..=15).collect()),
            Node::Separator(vec![]),
            Node::RecursionSeparator(vec![]),
            Node::Selection { expr: k(), children: vec![1] },
            Node::Calculation(vec![(0, k())]),
            Node::Translate([k(), k(), k()]),
            Node::Rotate { axis: [k(), k(), k()], angle: k() },
            Node::Scale([k(), k(), k()]),
            Node::Matrix(Box::new(std::array::from_fn(|_| k()))),
            Node::Material([k(), k(), k()]),
            Node::Cone { bottom: k(), top: k(), height: k() },
            Node::Cylinder { radius: k(), height: k() },
            Node::Sphere { radius: k() },
            Node::Box { size: [k(), k(), k()] },
            Node::Leaf { topology: canopy_protocol::LeafTopology::Strip, points: vec![[k(), k(), k()]; 4] },
            Node::Lod(vec![1, 2]),
        ],
        root: 0,
    };
    assert_eq!(SpeciesGraph::decode(&g.encode()), Ok(g));
}

#[test]
fn invalid_graphs_are_rejected() {
    let mut g = worm();
    g.nodes[6] = Node::RecursionSeparator(vec![99]);
    assert_eq!(
        SpeciesGraph::decode(&g.encode()),
        Err(DecodeError::Invalid(ValidateError::Child { node: 6, child: 99 }))
    );
    let mut g = worm();
    g.nodes[0] = Node::Selection { expr: Expr { ops: vec![Op::Add] }, children: vec![1] };
    assert!(matches!(g.validate(), Err(ValidateError::Expr { node: 0, error: ExprError::Underflow(0) })));
    let mut g = worm();
    g.nodes[0] = Node::Selection { expr: Expr { ops: vec![Op::Param(3)] }, children: vec![1] };
    assert!(matches!(g.validate(), Err(ValidateError::Expr { error: ExprError::Slot { slot: 3, .. }, .. })));
    let mut g = worm();
    g.nodes[0] = Node::Selection { expr: Expr { ops: vec![Op::Const(1.0), Op::Jump(5)] }, children: vec![1] };
    assert!(matches!(g.validate(), Err(ValidateError::Expr { error: ExprError::Jump(1), .. })));
    let mut g = worm();
    g.nodes[0] = Node::Selection { expr: Expr::constant(0.0), children: vec![] };
    assert!(matches!(g.validate(), Err(ValidateError::ChildCount { node: 0, count: 0 })));
    let mut g = worm();
    g.root = 7;
    assert_eq!(g.validate(), Err(ValidateError::Root(7)));
    // Constants are finite: a NaN would make decode(encode(g)) != g and has no use (found by the fuzzer:
    // fuzz/artifacts/species, Cylinder { radius: [Const(NaN), Choose(1)] }).
    for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
        let mut g = worm();
        g.nodes[0] = Node::Selection { expr: Expr { ops: vec![Op::Const(bad), Op::Choose(1)] }, children: vec![1] };
        assert!(matches!(g.validate(), Err(ValidateError::Expr { node: 0, error: ExprError::Constant(0) })));
        assert!(SpeciesGraph::decode(&g.encode()).is_err());
    }
    let deep = Expr { ops: vec![Op::Const(1.0); limits::MAX_EXPR_STACK + 1] };
    assert!(matches!(deep.validate(0), Err(ExprError::TooDeep(_))));
}

#[test]
fn oversized_truncated_and_trailing_input_is_rejected() {
    let bytes = worm().encode();
    assert_eq!(
        SpeciesGraph::decode(&vec![0u8; limits::MAX_SPECIES_BYTES + 1]),
        Err(DecodeError::TooLarge(limits::MAX_SPECIES_BYTES + 1))
    );
    for cut in 0..bytes.len() {
        assert!(SpeciesGraph::decode(&bytes[..cut]).is_err(), "truncated at {cut}");
    }
    let mut extra = bytes.clone();
    extra.push(0);
    assert_eq!(SpeciesGraph::decode(&extra), Err(DecodeError::Trailing(1)));
    // A huge length prefix must not allocate: a name claiming 2^32 bytes.
    let hostile = [0x80, 0x80, 0x80, 0x80, 0x10, b'a'];
    assert!(SpeciesGraph::decode(&hostile).is_err());
}

#[test]
fn random_bytes_never_panic() {
    // A deterministic xorshift stream of mutations of a valid encoding; decode must return, never panic.
    let base = worm().encode();
    let mut x = canopy_protocol::xorshift::XorShift64::new(0x2545_f491_4f6c_dd1d);
    let mut next = || x.next();
    for _ in 0..20_000 {
        let mut b = base.clone();
        for _ in 0..1 + next() % 4 {
            let i = (next() as usize) % b.len();
            b[i] = next() as u8;
        }
        let _ = SpeciesGraph::decode(&b);
        let len = (next() % 64) as usize;
        let junk: Vec<u8> = (0..len).map(|_| next() as u8).collect();
        let _ = SpeciesGraph::decode(&junk);
    }
}
