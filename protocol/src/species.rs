//! Species graphs: the directed cyclic graph (DCG) that is a plant species' program (seed 001 §3.2, §6).
//!
//! Nodes live in one vector and refer to their children by index, so a cycle is simply an index back to an
//! earlier node and sharing (DEF/USE) is two parents naming the same index. Recursion terminates in
//! [`Node::Selection`], which traverses one child chosen by an expression of the parameters.

use serde::{Deserialize, Serialize};

use crate::expr::{Expr, ExprError};
use crate::limits;

/// Index of a node in [`SpeciesGraph::nodes`].
pub type NodeId = u32;

/// A species: parameter declarations, the nodes, and the root where traversal starts.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SpeciesGraph {
    /// Human-readable name (not used for identity).
    pub name: String,
    /// Parameter slots, in declaration order; expressions refer to them by index.
    pub params: Vec<ParamDecl>,
    /// All nodes; children are indices into this vector.
    pub nodes: Vec<Node>,
    /// Where traversal starts.
    pub root: NodeId,
}

/// A declared parameter (seed 001 §3.4: user-specified general appearance, statistical details).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ParamDecl {
    /// Name, unique within the species.
    pub name: String,
    /// Default value, evaluated once per instance in declaration order before traversal; it may draw from the
    /// instance RNG (a random parameter) and read earlier parameters. An instance value overrides it.
    pub default: Expr,
    /// Which separators restore the parameter.
    pub scope: ParamScope,
    /// Whether it is one of the species' parameters or a working value of its program.
    pub role: ParamRole,
}

/// What a declared value is to the species' users.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum ParamRole {
    /// A parameter of the species (seed 001 §3.4: "user-specified general appearance"): what an instance, a
    /// world's population rule, an edit or the editor's slider may set.
    Parameter,
    /// A working value of the program (a counter, a radius carried down a branch, an L-system module's argument):
    /// computed by the species itself; nothing outside it sets one.
    Working,
}

/// Which separators save and restore a parameter.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum ParamScope {
    /// Restored by both [`Node::Separator`] and [`Node::RecursionSeparator`]: a procedure's local variable.
    Local,
    /// Part of the turtle state, like the transform and material: restored by [`Node::Separator`] only, so it
    /// flows across recursion separators (an L-system's line width and colour index).
    Turtle,
}

/// The topology of a leaf's points.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum LeafTopology {
    /// A convex polygon, fan-triangulated from the first point.
    Polygon,
    /// A triangle strip.
    Strip,
}

/// A DCG node. Transform arguments and primitive sizes are expressions of the parameters, evaluated when the node
/// is traversed. Angles in nodes are degrees; lengths are metres; the primitives' axis is local +Y.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Node {
    /// Traverses all children left to right; state changes propagate to later siblings.
    Group(Vec<NodeId>),
    /// Like a group, but saves the transform, material and all parameters first and restores them after.
    Separator(Vec<NodeId>),
    /// A call frame (seed 001 §6 RecursionSeparator): saves the [`ParamScope::Local`] parameters and restores them
    /// after, leaving transform, material and turtle parameters to flow on. It also opens a fresh RNG context
    /// derived from the caller's, so random draws depend on the derivation path, not on traversal order.
    RecursionSeparator(Vec<NodeId>),
    /// Traverses exactly one child: the expression's value, truncated and clamped to the child range
    /// (NaN selects child 0). Recursion terminates here.
    Selection {
        /// Chooses the child.
        expr: Expr,
        /// The alternatives.
        children: Vec<NodeId>,
    },
    /// Assigns parameters from expressions, all evaluated first and then stored (simultaneous assignment).
    Calculation(Vec<(u16, Expr)>),
    /// Post-multiplies the current transform by a translation.
    Translate([Expr; 3]),
    /// Post-multiplies the current transform by a rotation of `angle` degrees about `axis` (normalised).
    Rotate {
        /// Rotation axis; need not be unit length.
        axis: [Expr; 3],
        /// Angle in degrees, counter-clockwise looking down the axis.
        angle: Expr,
    },
    /// Post-multiplies the current transform by a scale.
    Scale([Expr; 3]),
    /// Post-multiplies the current transform by a general affine matrix, 3 rows of 4, row-major.
    Matrix(Box<[Expr; 12]>),
    /// Sets the current material colour (linear RGB, 0..1).
    Material([Expr; 3]),
    /// A cone or frustum standing on the origin along +Y.
    Cone {
        /// Radius at y = 0.
        bottom: Expr,
        /// Radius at y = height (0 for a cone).
        top: Expr,
        /// Height.
        height: Expr,
    },
    /// A cylinder standing on the origin along +Y.
    Cylinder {
        /// Radius.
        radius: Expr,
        /// Height.
        height: Expr,
    },
    /// A sphere centred on the origin.
    Sphere {
        /// Radius.
        radius: Expr,
    },
    /// A box centred on the origin.
    Box {
        /// Edge lengths along x, y, z.
        size: [Expr; 3],
    },
    /// A leaf: a polygon or triangle strip of points in local coordinates.
    Leaf {
        /// How the points form triangles.
        topology: LeafTopology,
        /// The points, each three expressions.
        points: Vec<[Expr; 3]>,
    },
    /// Level of detail (seed 001 §5): child `min(detail, len - 1)` is traversed; child 0 is full detail, later
    /// children are hand-made substitutes. The chosen child runs in a call frame like a
    /// [`Node::RecursionSeparator`] (local parameters restored, a child RNG context), so which substitute is chosen
    /// changes nothing outside it.
    Lod(Vec<NodeId>),
    /// A trunk–root junction (seed 002 §3.1, §4): cross-sections from a hypocycloid at the ground to a circle up
    /// the trunk, built as the envelope of generator ellipses; a primitive standing on the origin along +Y.
    TrunkBase(Box<TrunkBaseNode>),
    /// Species-level near-field options (seeds 002 and 004): continuous mesh, contour resolution, junction
    /// refinement and double bark. Not traversed for geometry; readers find it in the node vector.
    NearField(Box<NearFieldNode>),
}

/// The parameters of a [`Node::TrunkBase`], as seed 002 §4 names them; each is an expression of the parameters.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrunkBaseNode {
    /// Base spread factor: how far the root flares (the cusps) reach, as a multiple of the base radius.
    pub spread: Expr,
    /// Height of the trunk base, metres.
    pub height: Expr,
    /// Base radius: the trunk's radius at the ground, between the root flares.
    pub bottom: Expr,
    /// Top radius: the radius of the circular cross-section at the top.
    pub top: Expr,
    /// Tilt spread, degrees: the base leans towards +Z by this angle.
    pub tilt: Expr,
    /// Cusps of the hypocycloid at the ground (3 deltoid, 4 astroid, more lobes).
    pub lobes: Expr,
    /// Generator ellipse count.
    pub ellipses: Expr,
    /// Curve resolution: points on each cross-section contour.
    pub resolution: Expr,
    /// Base randomiser factor: the strength of the semi-random perturbation of the roots (0 = none).
    pub randomiser: Expr,
    /// Transition: 0 the envelope of generator ellipses, 1 hypocycloid → quadrifolium (rose) → circle.
    pub transition: Expr,
    /// A value in [0, 1) that seeds the semi-random perturbation (the text formats default it to `rand()`, so
    /// every instance gets its own roots).
    pub seed: Expr,
}

impl TrunkBaseNode {
    /// How many expressions a trunk base has.
    pub const LEN: usize = 11;

    /// The expressions in field order (the order they are encoded, hashed and evaluated in).
    pub fn exprs(&self) -> [&Expr; TrunkBaseNode::LEN] {
        let TrunkBaseNode {
            spread,
            height,
            bottom,
            top,
            tilt,
            lobes,
            ellipses,
            resolution,
            randomiser,
            transition,
            seed,
        } = self;
        [spread, height, bottom, top, tilt, lobes, ellipses, resolution, randomiser, transition, seed]
    }

    /// The node from its expressions in field order (the inverse of [`TrunkBaseNode::exprs`]).
    pub fn from_array(e: [Expr; TrunkBaseNode::LEN]) -> TrunkBaseNode {
        let [spread, height, bottom, top, tilt, lobes, ellipses, resolution, randomiser, transition, seed] = e;
        TrunkBaseNode { spread, height, bottom, top, tilt, lobes, ellipses, resolution, randomiser, transition, seed }
    }
}

/// Species-level near-field meshing options (see [`Node::NearField`]); each is an expression of the parameters.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct NearFieldNode {
    /// Non-zero: mesh the branching structure as one continuous surface (seed 004).
    pub continuous: Expr,
    /// Contour resolution: vertices on each branch contour.
    pub contour: Expr,
    /// Non-zero: refine junctions by intervals (seed 004 §3.3); zero: the direct method.
    pub refine: Expr,
    /// Bark depth, metres: the outer bark stands this far off the inner one (0 = single bark).
    pub bark: Expr,
    /// Chisel mode: 1 shrink the outer bark's triangles, 2 remove some at random, 3 both.
    pub chisel: Expr,
    /// First chisel factor: how much outer bark triangles shrink (0..1).
    pub shrink: Expr,
    /// Second chisel factor: the fraction of outer bark triangles removed (0..1).
    pub removal: Expr,
}

impl NearFieldNode {
    /// How many expressions the node has.
    pub const LEN: usize = 7;

    /// The expressions in field order (the order they are encoded, hashed and evaluated in).
    pub fn exprs(&self) -> [&Expr; NearFieldNode::LEN] {
        let NearFieldNode { continuous, contour, refine, bark, chisel, shrink, removal } = self;
        [continuous, contour, refine, bark, chisel, shrink, removal]
    }

    /// The node from its expressions in field order (the inverse of [`NearFieldNode::exprs`]).
    pub fn from_array(e: [Expr; NearFieldNode::LEN]) -> NearFieldNode {
        let [continuous, contour, refine, bark, chisel, shrink, removal] = e;
        NearFieldNode { continuous, contour, refine, bark, chisel, shrink, removal }
    }
}

/// Why a species graph was rejected.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ValidateError {
    /// Too many nodes, or none.
    #[error("species has {0} nodes (allowed 1..={max})", max = limits::MAX_NODES)]
    NodeCount(usize),
    /// Too many parameters.
    #[error("species has {0} parameters (allowed {max})", max = limits::MAX_PARAMS)]
    ParamCount(usize),
    /// A name is empty or too long.
    #[error("name of {0} bytes (allowed 1..={max})", max = limits::MAX_NAME_LEN)]
    Name(usize),
    /// Two parameters share a name.
    #[error("parameter `{0}` declared twice")]
    DuplicateParam(String),
    /// The root index is out of range.
    #[error("root {0} is not a node")]
    Root(NodeId),
    /// A child index is out of range.
    #[error("node {node} links to {child}, which is not a node")]
    Child {
        /// The parent.
        node: NodeId,
        /// The bad child index.
        child: NodeId,
    },
    /// A node has too many children, or a selection/LOD node has none.
    #[error("node {node} has {count} children")]
    ChildCount {
        /// The node.
        node: NodeId,
        /// How many children it has.
        count: usize,
    },
    /// A leaf has too few or too many points, or a calculation too many assignments.
    #[error("node {node} has {count} entries")]
    EntryCount {
        /// The node.
        node: NodeId,
        /// How many entries it has.
        count: usize,
    },
    /// A calculation assigns to a slot that does not exist.
    #[error("node {node} assigns slot {slot}, which is not declared")]
    AssignSlot {
        /// The node.
        node: NodeId,
        /// The slot.
        slot: u16,
    },
    /// An expression is malformed.
    #[error("node {node}: {error}")]
    Expr {
        /// The node holding it (`u32::MAX` for a parameter default).
        node: NodeId,
        /// What is wrong.
        error: ExprError,
    },
}

/// Why bytes did not decode to a species graph.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum DecodeError {
    /// The input is larger than [`limits::MAX_SPECIES_BYTES`].
    #[error("species encoding of {0} bytes exceeds {max}", max = limits::MAX_SPECIES_BYTES)]
    TooLarge(usize),
    /// postcard could not decode the bytes.
    #[error("malformed species encoding: {0}")]
    Postcard(#[from] postcard::Error),
    /// Bytes were left over after the graph.
    #[error("{0} trailing bytes after the species graph")]
    Trailing(usize),
    /// The graph decoded but is not valid.
    #[error("invalid species graph: {0}")]
    Invalid(#[from] ValidateError),
}

impl Node {
    /// The node's children (empty for leaves of the graph).
    pub fn children(&self) -> &[NodeId] {
        match self {
            Node::Group(c) | Node::Separator(c) | Node::RecursionSeparator(c) | Node::Lod(c) => c,
            Node::Selection { children, .. } => children,
            _ => &[],
        }
    }

    /// Every expression the node holds, in evaluation order.
    pub fn exprs(&self) -> Vec<&Expr> {
        match self {
            Node::Group(_) | Node::Separator(_) | Node::RecursionSeparator(_) | Node::Lod(_) => vec![],
            Node::Selection { expr, .. } => vec![expr],
            Node::Calculation(a) => a.iter().map(|(_, e)| e).collect(),
            Node::Translate(v) | Node::Scale(v) | Node::Material(v) => v.iter().collect(),
            Node::Rotate { axis, angle } => axis.iter().chain(std::iter::once(angle)).collect(),
            Node::Matrix(m) => m.iter().collect(),
            Node::Cone { bottom, top, height } => vec![bottom, top, height],
            Node::Cylinder { radius, height } => vec![radius, height],
            Node::Sphere { radius } => vec![radius],
            Node::Box { size } => size.iter().collect(),
            Node::Leaf { points, .. } => points.iter().flatten().collect(),
            Node::TrunkBase(b) => b.exprs().to_vec(),
            Node::NearField(n) => n.exprs().to_vec(),
        }
    }

    /// Whether the node is a primitive (emits geometry).
    pub fn is_primitive(&self) -> bool {
        matches!(
            self,
            Node::Cone { .. }
                | Node::Cylinder { .. }
                | Node::Sphere { .. }
                | Node::Box { .. }
                | Node::Leaf { .. }
                | Node::TrunkBase(_)
        )
    }
}

impl SpeciesGraph {
    /// Find a declared value's slot by name (a parameter or a working value).
    pub fn param_slot(&self, name: &str) -> Option<u16> {
        self.params.iter().position(|p| p.name == name).map(|i| i as u16)
    }

    /// Whether `slot` is one of the species' parameters ([`ParamRole::Parameter`]).
    pub fn is_parameter(&self, slot: u16) -> bool {
        self.params.get(usize::from(slot)).is_some_and(|p| p.role == ParamRole::Parameter)
    }

    /// The declared values of one role with their slots, in declaration order.
    pub fn of_role(&self, role: ParamRole) -> impl Iterator<Item = (u16, &ParamDecl)> {
        self.params.iter().enumerate().filter(move |(_, p)| p.role == role).map(|(i, p)| (i as u16, p))
    }

    /// The slot of the parameter `name` (not a working value): what an instance may set. The error says why not
    /// and names the species' parameters.
    pub fn parameter_slot(&self, name: &str) -> Result<u16, String> {
        let names: Vec<&str> = self.of_role(ParamRole::Parameter).map(|(_, p)| p.name.as_str()).collect();
        let list =
            if names.is_empty() { "it has none".to_string() } else { format!("its parameters: {}", names.join(", ")) };
        match self.param_slot(name) {
            Some(slot) if self.is_parameter(slot) => Ok(slot),
            Some(_) => Err(format!("`{name}` is a working value of species `{}`, not a parameter ({list})", self.name)),
            None => Err(format!("species `{}` has no parameter `{name}` ({list})", self.name)),
        }
    }

    /// Check every limit and every index (see the module docs). Decoders call this; so should builders.
    pub fn validate(&self) -> Result<(), ValidateError> {
        let n = self.nodes.len();
        if n == 0 || n > limits::MAX_NODES {
            return Err(ValidateError::NodeCount(n));
        }
        if self.params.len() > limits::MAX_PARAMS {
            return Err(ValidateError::ParamCount(self.params.len()));
        }
        if self.name.is_empty() || self.name.len() > limits::MAX_NAME_LEN {
            return Err(ValidateError::Name(self.name.len()));
        }
        let np = self.params.len();
        for (i, p) in self.params.iter().enumerate() {
            if p.name.is_empty() || p.name.len() > limits::MAX_NAME_LEN {
                return Err(ValidateError::Name(p.name.len()));
            }
            if self.params[..i].iter().any(|q| q.name == p.name) {
                return Err(ValidateError::DuplicateParam(p.name.clone()));
            }
            p.default.validate(np).map_err(|error| ValidateError::Expr { node: u32::MAX, error })?;
        }
        if self.root as usize >= n {
            return Err(ValidateError::Root(self.root));
        }
        for (id, node) in self.nodes.iter().enumerate() {
            let id = id as NodeId;
            let children = node.children();
            let min_children = usize::from(matches!(node, Node::Selection { .. } | Node::Lod(_)));
            if children.len() > limits::MAX_CHILDREN || children.len() < min_children {
                return Err(ValidateError::ChildCount { node: id, count: children.len() });
            }
            if let Some(&child) = children.iter().find(|&&c| c as usize >= n) {
                return Err(ValidateError::Child { node: id, child });
            }
            match node {
                Node::Leaf { topology, points } => {
                    let min = match topology {
                        LeafTopology::Polygon | LeafTopology::Strip => 3,
                    };
                    if points.len() < min || points.len() > limits::MAX_LEAF_POINTS {
                        return Err(ValidateError::EntryCount { node: id, count: points.len() });
                    }
                }
                Node::Calculation(a) => {
                    if a.len() > limits::MAX_ASSIGNMENTS {
                        return Err(ValidateError::EntryCount { node: id, count: a.len() });
                    }
                    if let Some(&(slot, _)) = a.iter().find(|(s, _)| *s as usize >= np) {
                        return Err(ValidateError::AssignSlot { node: id, slot });
                    }
                }
                _ => {}
            }
            for e in node.exprs() {
                e.validate(np).map_err(|error| ValidateError::Expr { node: id, error })?;
            }
        }
        Ok(())
    }

    /// Encode with postcard (the wire and cache form).
    pub fn encode(&self) -> Vec<u8> {
        postcard::to_allocvec(self).expect("encoding a species graph into a Vec cannot fail")
    }

    /// Decode untrusted bytes: bounded in size, checked to the end, and validated.
    pub fn decode(bytes: &[u8]) -> Result<SpeciesGraph, DecodeError> {
        if bytes.len() > limits::MAX_SPECIES_BYTES {
            return Err(DecodeError::TooLarge(bytes.len()));
        }
        let (graph, rest): (SpeciesGraph, &[u8]) = postcard::take_from_bytes(bytes)?;
        if !rest.is_empty() {
            return Err(DecodeError::Trailing(rest.len()));
        }
        graph.validate()?;
        Ok(graph)
    }
}
