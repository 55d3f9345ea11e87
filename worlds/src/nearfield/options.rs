//! Species-level near-field options: what a species file asks for with `nearfield(...)` (a
//! [`canopy_protocol::Node::NearField`]), and what command lines may override.

use canopy_protocol::{Node, SpeciesGraph};

use crate::amplify::{AmplifyError, Instance, instance_params};
use crate::eval::eval;
use crate::nearfield::bark::{BarkOptions, ChiselMode};
use crate::nearfield::continuous::ContinuousOptions;
use crate::rng::{Context, InstanceRng, ROOT_KEY, child_key};

/// The near-field options of one species instance (by default: primitives, no bark).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct NearFieldOptions {
    /// Mesh the branches as one continuous surface (seed 004) instead of one mesh per primitive.
    pub continuous: bool,
    /// Contour resolution and junction refinement of the continuous mesh.
    pub mesh: ContinuousOptions,
    /// The double bark's outer layer, if any.
    pub bark: Option<BarkOptions>,
}

/// The options a species asks for: the first [`Node::NearField`] in its node vector, evaluated with the
/// instance's parameters (its draws, if any, come from a context of their own, so they disturb no other draw).
/// `None` when the species has no such node.
pub fn species_options(graph: &SpeciesGraph, instance: &Instance) -> Result<Option<NearFieldOptions>, AmplifyError> {
    let Some(node) = graph.nodes.iter().find_map(|n| match n {
        Node::NearField(n) => Some(n),
        _ => None,
    }) else {
        return Ok(None);
    };
    let mut rng = InstanceRng::new(instance.seed);
    let (params, _) = instance_params(graph, instance, &mut rng)?;
    let mut ctx = Context { rng: &mut rng, key: child_key(ROOT_KEY, u64::MAX), counter: 0 };
    let detail = f32::from(instance.detail);
    // In field order, as before the node had `exprs`: the draws of `rand()` arguments depend on it.
    let [continuous, contour, refine, depth, chisel, shrink, removal] =
        node.exprs().map(|e| eval(e, &params, detail, &mut ctx));
    let (continuous, refine) = (continuous != 0.0, refine != 0.0);
    let contour = if contour.is_finite() { contour.round().clamp(3.0, 256.0) as u32 } else { 12 };
    let bark = (depth > 0.0 && depth.is_finite()).then(|| BarkOptions {
        depth,
        chisel: ChiselMode::from_number(chisel),
        shrink: if shrink.is_finite() { shrink.clamp(0.0, 0.95) } else { 0.0 },
        removal: if removal.is_finite() { removal.clamp(0.0, 1.0) } else { 0.0 },
        seed: instance.seed,
    });
    Ok(Some(NearFieldOptions {
        continuous,
        mesh: ContinuousOptions { contour, refine, ..ContinuousOptions::default() },
        bark,
    }))
}
