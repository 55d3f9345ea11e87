//! Database amplification (seed 001 §3.3–3.4): traverse a species graph for one instance and emit its primitive
//! stream. Pure: no clock, no IO, no GPU, no native recursion.
//!
//! Traversal is depth first, left to right, driven by an explicit task stack. State — the transform, the material
//! colour, the parameter values and the RNG context — accumulates along the way; [`Node::Separator`] saves and
//! restores all of it except the RNG context, [`Node::RecursionSeparator`] saves and restores the
//! [`ParamScope::Local`] parameters and opens a child RNG context (see [`crate::rng`]). Every instance runs under
//! a [`Budget`]: a hostile graph ends in an [`AmplifyError`] after bounded work and memory.
//!
//! Every emitted primitive is finite: its sizes, leaf points, transform and colour. A primitive node whose values
//! are not (a parameter that makes `1 / (n - 1)` divide by zero, an overflowing scale) ends the traversal in
//! [`AmplifyError::NonFinite`] naming the node; nothing non-finite reaches a mesh, a renderer or the wire.

use canopy_protocol::{Node, NodeId, ParamScope, SpeciesGraph};

use crate::eval::{eval, eval_simple, eval_stack};
use crate::primitive::{Primitive, PrimitiveStream, Shape};
use crate::rng::{BlockCache, Context, InstanceRng, ROOT_KEY, child_key};
use crate::transform::Transform;

/// One instance of a species: the seed, parameter values that override the defaults, and the detail level.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Instance {
    /// Seeds the instance RNG; same seed, same tree, on every machine.
    pub seed: u64,
    /// `(slot, value)` pairs overriding the declared defaults.
    pub params: Vec<(u16, f32)>,
    /// 0 is full detail; each step up selects coarser substitutes in LOD nodes and is visible to expressions as
    /// `detail` (seed 001 §5).
    pub detail: u8,
}

impl Instance {
    /// An instance with this seed, default parameters and full detail.
    pub fn new(seed: u64) -> Instance {
        Instance { seed, params: Vec::new(), detail: 0 }
    }

    /// The same instance at another detail level.
    pub fn with_detail(mut self, detail: u8) -> Instance {
        self.detail = detail;
        self
    }
}

/// Work and size limits for one traversal.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Budget {
    /// Most primitives emitted.
    pub max_primitives: u32,
    /// Deepest nesting of separators and recursion separators.
    pub max_depth: u32,
    /// Most steps: node visits, scheduled children and expression operations together.
    pub max_steps: u64,
    /// Most tasks waiting on the traversal stack at once (bounds memory for wide cycles without separators).
    pub max_pending: u32,
}

/// The species parameter through which a species asks for more nesting than the budget's `max_depth` (an
/// L-system's `maxdepth` directive): its default, a constant, is honoured up to [`MAX_DEPTH_LIMIT`].
pub const DEPTH_PARAM: &str = "_maxdepth";
/// The most nesting a species may ask for through [`DEPTH_PARAM`] (bounds the saved state: one parameter vector
/// per level).
pub const MAX_DEPTH_LIMIT: u32 = 8_192;

impl Budget {
    /// The nesting allowed when traversing `graph`: `max_depth`, or what the graph asks for through
    /// [`DEPTH_PARAM`] if that is more (at most [`MAX_DEPTH_LIMIT`]).
    pub fn depth_for(&self, graph: &SpeciesGraph) -> u32 {
        let asked = graph.param_slot(DEPTH_PARAM).and_then(|s| graph.params[s as usize].default.as_constant());
        match asked {
            Some(d) if d.is_finite() && d > self.max_depth as f32 => {
                (d as u32).min(MAX_DEPTH_LIMIT).max(self.max_depth)
            }
            _ => self.max_depth,
        }
    }
}

impl Default for Budget {
    fn default() -> Self {
        Budget { max_primitives: 1_000_000, max_depth: 1_024, max_steps: 100_000_000, max_pending: 1 << 20 }
    }
}

/// Why amplification stopped.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum AmplifyError {
    /// The graph emits more primitives than the budget allows.
    #[error("more than {0} primitives")]
    Primitives(u32),
    /// Separators nest deeper than the budget allows (runaway recursion).
    #[error("separators nested deeper than {0}")]
    Depth(u32),
    /// Traversal took more steps than the budget allows (infinite or exponential recursion).
    #[error("more than {0} traversal steps")]
    Steps(u64),
    /// Too many tasks are waiting at once (a wide cycle without separators).
    #[error("more than {0} pending traversal tasks")]
    Pending(u32),
    /// An instance parameter names a slot the species does not declare.
    #[error("instance sets parameter slot {0}, which the species does not declare")]
    Param(u16),
    /// A primitive node evaluated to a non-finite size, leaf point, transform or colour (an expression divided by
    /// zero, took a root or logarithm out of range, or overflowed).
    #[error(
        "node {node} makes a {kind} with a non-finite size, point, transform or colour (NaN or infinity: a division \
         by zero, a root or logarithm out of range, or an overflow in its expressions or the transforms above it)"
    )]
    NonFinite {
        /// The primitive node.
        node: NodeId,
        /// Its kind, as [`crate::primitive::PrimitiveKind::name`] names it.
        kind: &'static str,
    },
}

#[derive(Clone, Copy)]
enum Task {
    Visit(NodeId),
    EndSeparator,
    EndRecursion,
}

struct SavedSeparator {
    transform: Transform,
    color: [f32; 3],
    params_at: usize,
}

struct SavedRecursion {
    key: u64,
    counter: u64,
    params_at: usize,
    /// The caller's RNG block, so its next draw after the call costs nothing.
    cache: BlockCache,
}

/// Evaluate the instance's parameters in declaration order in the root RNG context: each default is always
/// evaluated (so drawing is the same whether or not a value is overridden), then replaced by the instance's value
/// if it has one, so later defaults see the override (`param s = height / n`). Returns the values and the root
/// context's next counter.
pub fn instance_params(
    graph: &SpeciesGraph,
    instance: &Instance,
    rng: &mut InstanceRng,
) -> Result<(Vec<f32>, u64), AmplifyError> {
    let mut params = vec![0.0f32; graph.params.len()];
    let detail = f32::from(instance.detail);
    let mut ctx = Context { rng, key: ROOT_KEY, counter: 0 };
    if let Some(&(slot, _)) = instance.params.iter().find(|(s, _)| *s as usize >= params.len()) {
        return Err(AmplifyError::Param(slot));
    }
    for (i, p) in graph.params.iter().enumerate() {
        let v = eval(&p.default, &params, detail, &mut ctx);
        params[i] = instance.params.iter().rev().find(|(s, _)| *s as usize == i).map_or(v, |&(_, o)| o);
    }
    Ok((params, ctx.counter))
}

/// Traverse `graph` for `instance` within `budget`.
pub fn amplify(graph: &SpeciesGraph, instance: &Instance, budget: &Budget) -> Result<PrimitiveStream, AmplifyError> {
    let mut out = PrimitiveStream::default();
    amplify_into(graph, instance, budget, &mut out)?;
    Ok(out)
}

/// Like [`amplify`], but appends to `out` (reuse its allocations across instances).
pub fn amplify_into(
    graph: &SpeciesGraph,
    instance: &Instance,
    budget: &Budget,
    out: &mut PrimitiveStream,
) -> Result<(), AmplifyError> {
    let mut rng = InstanceRng::new(instance.seed);
    let (mut params, root_counter) = instance_params(graph, instance, &mut rng)?;
    let detail = f32::from(instance.detail);
    let local_slots: Vec<usize> =
        graph.params.iter().enumerate().filter(|(_, p)| p.scope == ParamScope::Local).map(|(i, _)| i).collect();
    let all_local = local_slots.len() == params.len();
    let np = params.len();
    let max_depth = budget.depth_for(graph);

    let mut transform = Transform::IDENTITY;
    let mut color = [0.8f32, 0.8, 0.8];
    let mut key = ROOT_KEY;
    let mut counter = root_counter;

    let fixed: Vec<Option<Transform>> = graph.nodes.iter().map(constant_transform).collect();
    let mut rotations: Vec<(Option<[u32; 4]>, Transform)> = vec![(None, Transform::IDENTITY); graph.nodes.len()];
    let mut tasks: Vec<Task> = vec![Task::Visit(graph.root)];
    let mut separators: Vec<SavedSeparator> = Vec::new();
    let mut recursions: Vec<SavedRecursion> = Vec::new();
    let mut saved_params: Vec<f32> = Vec::new();
    let mut scratch: Vec<f32> = Vec::new();
    let mut steps: u64 = 0;
    let first_primitive = out.primitives.len();

    // Evaluate one expression in the current state, charging its length to the step budget.
    macro_rules! ev {
        ($e:expr) => {{
            let e = $e;
            steps += e.ops.len() as u64;
            match eval_simple(e, &params) {
                Some(v) => v,
                None => {
                    let mut ctx = Context { rng: &mut rng, key, counter };
                    let v = eval_stack(e, &params, detail, &mut ctx);
                    counter = ctx.counter;
                    v
                }
            }
        }};
    }

    // Open a call frame: save the local parameters, the caller's RNG context and block, and enter the child
    // context `(child_key(key, counter), 0)` (see `crate::rng`). `Task::EndRecursion` closes it.
    macro_rules! enter_frame {
        () => {{
            if (separators.len() + recursions.len()) as u32 >= max_depth {
                return Err(AmplifyError::Depth(max_depth));
            }
            recursions.push(SavedRecursion {
                key,
                counter: counter + 1,
                params_at: saved_params.len(),
                cache: rng.cache,
            });
            saved_params.extend_from_slice(&params);
            key = child_key(key, counter);
            counter = 0;
        }};
    }

    while let Some(task) = tasks.pop() {
        steps += 1;
        if steps > budget.max_steps {
            return Err(AmplifyError::Steps(budget.max_steps));
        }
        let id = match task {
            Task::Visit(id) => id,
            Task::EndSeparator => {
                let s = separators.pop().expect("separator end without start");
                transform = s.transform;
                color = s.color;
                params.copy_from_slice(&saved_params[s.params_at..s.params_at + np]);
                saved_params.truncate(s.params_at);
                continue;
            }
            Task::EndRecursion => {
                let s = recursions.pop().expect("recursion end without start");
                key = s.key;
                counter = s.counter;
                rng.cache = s.cache;
                let saved = &saved_params[s.params_at..s.params_at + np];
                if all_local {
                    params.copy_from_slice(saved);
                } else {
                    for &i in &local_slots {
                        params[i] = saved[i];
                    }
                }
                saved_params.truncate(s.params_at);
                continue;
            }
        };
        match &graph.nodes[id as usize] {
            Node::Group(children) => {
                steps += children.len() as u64;
                tasks.extend(children.iter().rev().map(|&c| Task::Visit(c)));
            }
            Node::Separator(children) => {
                if (separators.len() + recursions.len()) as u32 >= max_depth {
                    return Err(AmplifyError::Depth(max_depth));
                }
                separators.push(SavedSeparator { transform, color, params_at: saved_params.len() });
                saved_params.extend_from_slice(&params);
                steps += children.len() as u64;
                tasks.push(Task::EndSeparator);
                tasks.extend(children.iter().rev().map(|&c| Task::Visit(c)));
            }
            Node::RecursionSeparator(children) => {
                enter_frame!();
                steps += children.len() as u64;
                tasks.push(Task::EndRecursion);
                tasks.extend(children.iter().rev().map(|&c| Task::Visit(c)));
            }
            Node::Selection { expr, children } => {
                let v = ev!(expr);
                let last = children.len() - 1;
                let i = if v.is_nan() { 0 } else { (v as i64).clamp(0, last as i64) as usize };
                tasks.push(Task::Visit(children[i]));
            }
            Node::Lod(children) => {
                // The chosen substitute runs in its own call frame and RNG context, like a recursion separator,
                // so switching substitutes changes nothing outside them (no popping elsewhere in the tree).
                enter_frame!();
                let i = usize::from(instance.detail).min(children.len() - 1);
                tasks.push(Task::EndRecursion);
                tasks.push(Task::Visit(children[i]));
            }
            Node::Calculation(assignments) => {
                scratch.clear();
                for (_, e) in assignments {
                    let v = ev!(e);
                    scratch.push(v);
                }
                for ((slot, _), &v) in assignments.iter().zip(&scratch) {
                    params[*slot as usize] = v;
                }
            }
            Node::Translate([x, y, z]) => {
                let (x, y, z) = (ev!(x), ev!(y), ev!(z));
                transform = transform.translated(x, y, z);
            }
            Node::Rotate { .. } | Node::Scale(_) | Node::Matrix(_) if fixed[id as usize].is_some() => {
                // A transformation whose arguments are all constants: computed once per traversal.
                transform = transform.mul(fixed[id as usize].as_ref().expect("checked by the guard"));
            }
            Node::Rotate { axis: [x, y, z], angle } => {
                let args = [ev!(x), ev!(y), ev!(z), ev!(angle)];
                // Rotations by a parameter (an L-system's `+` turns by `angle`) repeat their arguments: keep the
                // last matrix per node (compared bit for bit, so the result is the same as recomputing).
                let memo = &mut rotations[id as usize];
                let bits = args.map(f32::to_bits);
                if memo.0 != Some(bits) {
                    *memo = (Some(bits), Transform::rotation([args[0], args[1], args[2]], args[3]));
                }
                transform = transform.mul(&memo.1);
            }
            Node::Scale([x, y, z]) => {
                let (x, y, z) = (ev!(x), ev!(y), ev!(z));
                transform = transform.mul(&Transform::scale(x, y, z));
            }
            Node::Matrix(m) => {
                let mut t = [0.0f32; 12];
                for (dst, e) in t.iter_mut().zip(m.iter()) {
                    *dst = ev!(e);
                }
                transform = transform.mul(&Transform { m: t });
            }
            Node::Material([r, g, b]) => {
                color = [ev!(r), ev!(g), ev!(b)];
            }
            // Species-level near-field options: read by `crate::nearfield::options`, no geometry.
            Node::NearField(_) => {}
            node => {
                if (out.primitives.len() - first_primitive) as u32 >= budget.max_primitives {
                    return Err(AmplifyError::Primitives(budget.max_primitives));
                }
                let shape = match node {
                    Node::Cone { bottom, top, height } => {
                        Shape::Cone { bottom: ev!(bottom), top: ev!(top), height: ev!(height) }
                    }
                    Node::Cylinder { radius, height } => Shape::Cylinder { radius: ev!(radius), height: ev!(height) },
                    Node::Sphere { radius } => Shape::Sphere { radius: ev!(radius) },
                    Node::Box { size: [x, y, z] } => Shape::Box { size: [ev!(x), ev!(y), ev!(z)] },
                    Node::Leaf { topology, points } => {
                        let start = out.leaf_points.len() as u32;
                        for [x, y, z] in points {
                            let p = [ev!(x), ev!(y), ev!(z)];
                            out.leaf_points.push(p);
                        }
                        Shape::Leaf { topology: *topology, start, end: out.leaf_points.len() as u32 }
                    }
                    Node::TrunkBase(b) => {
                        let mut v = [0.0; crate::nearfield::TrunkBase::LEN];
                        for (v, e) in v.iter_mut().zip(b.exprs()) {
                            *v = ev!(e);
                        }
                        Shape::TrunkBase(crate::nearfield::TrunkBase::from_array(v))
                    }
                    _ => unreachable!("every non-primitive node is matched above"),
                };
                let p = Primitive { shape, transform, color };
                if !finite(&p, out) {
                    return Err(AmplifyError::NonFinite { node: id, kind: p.shape.kind().name() });
                }
                out.primitives.push(p);
            }
        }
        if tasks.len() as u32 > budget.max_pending {
            return Err(AmplifyError::Pending(budget.max_pending));
        }
    }
    Ok(())
}

/// Whether every value of `p` is finite: sizes, transform, colour and, for a leaf, its points in `stream`.
fn finite(p: &Primitive, stream: &PrimitiveStream) -> bool {
    let (sizes, n) = p.shape.sizes();
    let points = match p.shape {
        Shape::Leaf { start, end, .. } => &stream.leaf_points[start as usize..end as usize],
        _ => &[],
    };
    sizes[..n].iter().chain(&p.transform.m).chain(&p.color).chain(points.iter().flatten()).all(|v| v.is_finite())
}

/// The matrix of a rotation, scale or general matrix node whose arguments are all constants (translations are
/// cheaper applied directly and are left out).
fn constant_transform(node: &Node) -> Option<Transform> {
    let c = |e: &canopy_protocol::Expr| e.as_constant();
    match node {
        Node::Rotate { axis: [x, y, z], angle } => Some(Transform::rotation([c(x)?, c(y)?, c(z)?], c(angle)?)),
        Node::Scale([x, y, z]) => Some(Transform::scale(c(x)?, c(y)?, c(z)?)),
        Node::Matrix(m) => {
            let mut t = [0.0f32; 12];
            for (dst, e) in t.iter_mut().zip(m.iter()) {
                *dst = c(e)?;
            }
            Some(Transform { m: t })
        }
        _ => None,
    }
}

/// Resolve `name=value` parameter settings against a species, for command lines and world files: parameters only
/// (a working value is the species' own, [`SpeciesGraph::parameter_slot`] says so).
pub fn resolve_params(graph: &SpeciesGraph, settings: &[(String, f32)]) -> Result<Vec<(u16, f32)>, String> {
    settings.iter().map(|(name, v)| graph.parameter_slot(name).map(|s| (s, *v))).collect()
}
