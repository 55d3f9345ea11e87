//! The node vocabulary both text formats share: transformations, material and primitives written as calls,
//! `cone(bottom, top, height)`, with expression arguments.
//!
//! | call | node |
//! |---|---|
//! | `translate(x, y, z)` | [`Node::Translate`] |
//! | `rotate(ax, ay, az, degrees)`, `rotx(d)`, `roty(d)`, `rotz(d)` | [`Node::Rotate`] |
//! | `scale(x, y, z)`, `scale(s)` | [`Node::Scale`] |
//! | `matrix(m00, m01, m02, m03, m10, …, m23)` | [`Node::Matrix`] |
//! | `material(r, g, b)` | [`Node::Material`] |
//! | `cone(bottom, top, height)` | [`Node::Cone`] |
//! | `cylinder(radius, height)` | [`Node::Cylinder`] |
//! | `sphere(radius)` | [`Node::Sphere`] |
//! | `box(x, y, z)` | [`Node::Box`] |
//! | `leaf((x, y, z), (x, y, z), …)` | [`Node::Leaf`], polygon |
//! | `leafstrip((x, y, z), …)` | [`Node::Leaf`], triangle strip |
//! | `trunkbase(spread = …, height = …, …)` | [`Node::TrunkBase`] (seed 002 §4; see [`TRUNKBASE_ARGS`]) |
//! | `nearfield(continuous = …, contour = …, …)` | [`Node::NearField`] (see [`NEARFIELD_ARGS`]) |
//!
//! `trunkbase` and `nearfield` take named arguments (`name = expr`), optionally after positional ones in the
//! order of their tables; omitted ones take the table's default.

use std::ops::Range;

use canopy_protocol::species::{NearFieldNode, TrunkBaseNode};
use canopy_protocol::{Expr, LeafTopology, Node, limits};

use crate::expr::{Ast, compile, parse_expr};
use crate::text::{Cursor, ParseError};

/// Names of the calls this module parses.
pub(crate) const NODE_CALLS: [&str; 17] = [
    "translate",
    "rotate",
    "rotx",
    "roty",
    "rotz",
    "scale",
    "matrix",
    "material",
    "cone",
    "cylinder",
    "sphere",
    "box",
    "leaf",
    "leafstrip",
    "leaf_strip",
    "trunkbase",
    "nearfield",
];

/// The arguments of `trunkbase(...)` in positional order, with their defaults: seed 002 §4's base spread
/// factor, trunk height, base and top radii, tilt spread (degrees), cusps of the hypocycloid, generator ellipse
/// count, curve resolution, base randomiser factor, the transition (0 generator ellipses, 1 quadrifolium) and the
/// perturbation's seed (drawn per instance).
pub(crate) const TRUNKBASE_ARGS: [(&str, &str); TrunkBaseNode::LEN] = [
    ("spread", "2"),
    ("height", "1.5"),
    ("bottom", "0.4"),
    ("top", "0.3"),
    ("tilt", "0"),
    ("lobes", "4"),
    ("ellipses", "32"),
    ("resolution", "48"),
    ("randomiser", "0.3"),
    ("transition", "0"),
    ("seed", "rand()"),
];

/// The arguments of `nearfield(...)` in positional order, with their defaults: continuous mesh (non-zero: yes),
/// contour resolution, junction refinement by intervals (non-zero: yes), bark depth in metres (0: single bark),
/// chisel mode (1 shrink, 2 remove, 3 both) and the two chisel factors.
pub(crate) const NEARFIELD_ARGS: [(&str, &str); NearFieldNode::LEN] = [
    ("continuous", "1"),
    ("contour", "12"),
    ("refine", "1"),
    ("bark", "0"),
    ("chisel", "3"),
    ("shrink", "0.35"),
    ("removal", "0.1"),
];

/// Parse `(a, b, …)` at the cursor into expression ASTs.
pub(crate) fn parse_args(cur: &mut Cursor<'_>) -> Result<(Vec<Ast>, Range<usize>), ParseError> {
    cur.skip_trivia();
    let start = cur.pos;
    cur.expect("(")?;
    let mut args = Vec::new();
    if !cur.eat(")") {
        loop {
            args.push(parse_expr(cur)?);
            if cur.eat(")") {
                break;
            }
            cur.expect(",")?;
        }
    }
    Ok((args, start..cur.pos))
}

/// If `name` is one of [`NODE_CALLS`], parse its arguments at the cursor (just after the name) and build the
/// node, resolving parameter names with `resolve`. Returns `None` for other names, leaving the cursor untouched.
pub(crate) fn parse_node_call(
    name: &str,
    name_span: Range<usize>,
    cur: &mut Cursor<'_>,
    resolve: &mut dyn FnMut(&str) -> Option<u16>,
) -> Option<Result<Node, ParseError>> {
    if !NODE_CALLS.contains(&name) {
        return None;
    }
    Some(node_call(name, name_span, cur, resolve))
}

fn node_call(
    name: &str,
    name_span: Range<usize>,
    cur: &mut Cursor<'_>,
    resolve: &mut dyn FnMut(&str) -> Option<u16>,
) -> Result<Node, ParseError> {
    if name == "leaf" || name == "leafstrip" || name == "leaf_strip" {
        return leaf(name, name_span, cur, resolve);
    }
    if name == "trunkbase" || name == "nearfield" {
        return named_call(name, name_span, cur, resolve);
    }
    let (args, span) = parse_args(cur)?;
    let span = name_span.start..span.end;
    let want: &[usize] = match name {
        "translate" | "material" | "box" | "cone" => &[3],
        "rotate" => &[4],
        "rotx" | "roty" | "rotz" | "sphere" => &[1],
        "scale" => &[1, 3],
        "matrix" => &[12],
        "cylinder" => &[2],
        _ => unreachable!("checked against NODE_CALLS"),
    };
    if !want.contains(&args.len()) {
        let want: Vec<String> = want.iter().map(|n| n.to_string()).collect();
        return Err(ParseError::new(
            span,
            format!("`{name}` takes {} argument(s), got {}", want.join(" or "), args.len()),
        ));
    }
    let e: Vec<Expr> = args.iter().map(|a| compile(a, resolve)).collect::<Result<_, _>>()?;
    let mut e = e.into_iter();
    let mut take = || e.next().expect("the argument count is checked above");
    Ok(match name {
        "translate" => Node::Translate([take(), take(), take()]),
        "rotate" => Node::Rotate { axis: [take(), take(), take()], angle: take() },
        "rotx" => Node::Rotate { axis: unit_axis(0), angle: take() },
        "roty" => Node::Rotate { axis: unit_axis(1), angle: take() },
        "rotz" => Node::Rotate { axis: unit_axis(2), angle: take() },
        "scale" if args.len() == 1 => {
            let s = take();
            Node::Scale([s.clone(), s.clone(), s])
        }
        "scale" => Node::Scale([take(), take(), take()]),
        "matrix" => Node::Matrix(Box::new(std::array::from_fn(|_| take()))),
        "material" => Node::Material([take(), take(), take()]),
        "cone" => Node::Cone { bottom: take(), top: take(), height: take() },
        "cylinder" => Node::Cylinder { radius: take(), height: take() },
        "sphere" => Node::Sphere { radius: take() },
        "box" => Node::Box { size: [take(), take(), take()] },
        _ => unreachable!("checked against NODE_CALLS"),
    })
}

/// `trunkbase(...)` or `nearfield(...)`: positional arguments, then `name = expr` ones, defaults for the rest.
fn named_call(
    name: &str,
    name_span: Range<usize>,
    cur: &mut Cursor<'_>,
    resolve: &mut dyn FnMut(&str) -> Option<u16>,
) -> Result<Node, ParseError> {
    let table: &[(&str, &str)] = if name == "trunkbase" { &TRUNKBASE_ARGS } else { &NEARFIELD_ARGS };
    cur.expect("(")?;
    let mut values: Vec<Option<Ast>> = (0..table.len()).map(|_| None).collect();
    let (mut positional, mut named) = (0usize, false);
    if !cur.eat(")") {
        loop {
            cur.skip_trivia();
            let save = cur.pos;
            let mut key = None;
            if let Some((word, span)) = cur.ident() {
                let rest = cur.rest().trim_start_matches([' ', '\t']);
                if rest.starts_with('=') && !rest.starts_with("==") {
                    key = Some((word.to_string(), span));
                    cur.expect("=")?;
                } else {
                    cur.pos = save;
                }
            }
            let slot = match key {
                Some((word, span)) => {
                    let Some(i) = table.iter().position(|(k, _)| *k == word) else {
                        let known: Vec<&str> = table.iter().map(|(k, _)| *k).collect();
                        return Err(ParseError::new(
                            span,
                            format!("`{name}` has no argument `{word}` (it has: {})", known.join(", ")),
                        ));
                    };
                    if values[i].is_some() {
                        return Err(ParseError::new(span, format!("argument `{word}` given twice")));
                    }
                    named = true;
                    i
                }
                None => {
                    if named {
                        return Err(ParseError::new(save..save + 1, "a positional argument after a named one"));
                    }
                    if positional == table.len() {
                        return Err(ParseError::new(
                            save..save + 1,
                            format!("`{name}` takes at most {} arguments", table.len()),
                        ));
                    }
                    positional += 1;
                    positional - 1
                }
            };
            values[slot] = Some(parse_expr(cur)?);
            if cur.eat(")") {
                break;
            }
            cur.expect(",")?;
        }
    }
    let mut e = Vec::with_capacity(table.len());
    for (v, (_, default)) in values.into_iter().zip(table) {
        let ast = match v {
            Some(a) => a,
            None => crate::expr::parse_str(default).map_err(|d| ParseError::new(name_span.clone(), d.message))?,
        };
        e.push(compile(&ast, resolve)?);
    }
    // The tables have exactly the nodes' expression counts.
    Ok(if name == "trunkbase" {
        Node::TrunkBase(Box::new(TrunkBaseNode::from_array(e.try_into().expect("TRUNKBASE_ARGS has 11 entries"))))
    } else {
        Node::NearField(Box::new(NearFieldNode::from_array(e.try_into().expect("NEARFIELD_ARGS has 7 entries"))))
    })
}

fn unit_axis(i: usize) -> [Expr; 3] {
    std::array::from_fn(|j| Expr::constant(if i == j { 1.0 } else { 0.0 }))
}

fn leaf(
    name: &str,
    name_span: Range<usize>,
    cur: &mut Cursor<'_>,
    resolve: &mut dyn FnMut(&str) -> Option<u16>,
) -> Result<Node, ParseError> {
    let topology = if name == "leaf" { LeafTopology::Polygon } else { LeafTopology::Strip };
    cur.expect("(")?;
    let mut points = Vec::new();
    loop {
        cur.skip_trivia();
        let at = cur.pos;
        let (p, span) = parse_args(cur)?;
        if p.len() != 3 {
            return Err(ParseError::new(span, format!("a leaf point has 3 coordinates, got {}", p.len())));
        }
        if points.len() == limits::MAX_LEAF_POINTS {
            return Err(ParseError::new(at..cur.pos, format!("a leaf has at most {} points", limits::MAX_LEAF_POINTS)));
        }
        let [x, y, z] = [&p[0], &p[1], &p[2]].map(|a| compile(a, resolve));
        points.push([x?, y?, z?]);
        if cur.eat(")") {
            break;
        }
        cur.expect(",")?;
    }
    if points.len() < 3 {
        return Err(ParseError::new(
            name_span.start..cur.pos,
            format!("`{name}` needs at least 3 points, got {}", points.len()),
        ));
    }
    Ok(Node::Leaf { topology, points })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn node(src: &str) -> Result<Node, ParseError> {
        let mut cur = Cursor::new(src, true);
        let (name, span) = cur.ident().unwrap();
        parse_node_call(name, span, &mut cur, &mut |n| (n == "r").then_some(0)).unwrap()
    }

    #[test]
    fn calls_build_nodes() {
        assert_eq!(
            node("cone(r, 0, 2)").unwrap(),
            Node::Cone { bottom: Expr::param(0), top: Expr::constant(0.0), height: Expr::constant(2.0) }
        );
        assert!(matches!(node("scale(2)").unwrap(), Node::Scale(_)));
        assert!(matches!(node("leafstrip((0,0,0),(1,0,0),(0,1,0),(1,1,0))").unwrap(),
            Node::Leaf { topology: LeafTopology::Strip, ref points } if points.len() == 4));
    }

    #[test]
    fn wrong_arity_and_short_leaves_are_errors() {
        assert_eq!(node("cylinder(1)").unwrap_err().message, "`cylinder` takes 2 argument(s), got 1");
        assert_eq!(node("scale(1, 2)").unwrap_err().message, "`scale` takes 1 or 3 argument(s), got 2");
        assert_eq!(node("leaf((0,0,0),(1,0,0))").unwrap_err().message, "`leaf` needs at least 3 points, got 2");
        assert_eq!(node("leaf((0,0),(1,0,0),(0,1,0))").unwrap_err().message, "a leaf point has 3 coordinates, got 2");
    }
}
