//! A compiled species as the editor holds it: the graph, and the L-system it came from when it was one (so an
//! L-system that derives too deep says so in its own terms), with one `amplify` for both.

use std::sync::Arc;

use canopy_protocol::{ParamRole, SpeciesGraph};
use canopy_worlds::amplify::{AmplifyError, Budget, DEPTH_PARAM, Instance, amplify};
use canopy_worlds::diag::{Diagnostic, SourceFile};
use canopy_worlds::load::{Format, parse_source};
use canopy_worlds::lsystem::{DeriveError, LSystem};
use canopy_worlds::primitive::PrimitiveStream;

/// Why an instance could not be amplified.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum AmplifyFailure {
    /// The traversal failed (over budget, a non-finite primitive, a bad parameter slot).
    #[error(transparent)]
    Amplify(#[from] AmplifyError),
    /// The L-system's derivation nests deeper than the traversal allows.
    #[error(transparent)]
    Derive(#[from] DeriveError),
}

/// A species that parsed: its graph, and its L-system when the source was one.
#[derive(Clone, Debug)]
pub struct Species {
    /// The compiled species graph.
    pub graph: Arc<SpeciesGraph>,
    /// The L-system the graph was compiled from, if it was one.
    pub lsystem: Option<Arc<LSystem>>,
}

impl Species {
    /// A species from a graph alone.
    pub fn from_graph(graph: SpeciesGraph) -> Species {
        Species { graph: Arc::new(graph), lsystem: None }
    }

    /// A species from a graph and, when it came from one, its L-system.
    pub fn new(graph: SpeciesGraph, lsystem: Option<LSystem>) -> Species {
        Species { graph: Arc::new(graph), lsystem: lsystem.map(Arc::new) }
    }

    /// Parse a `.species` or `.lsys` source (the format from its name). Returns the species if it parsed, and
    /// every diagnostic.
    pub fn parse(src: &SourceFile) -> (Option<Species>, Vec<Diagnostic>) {
        match Format::of(&src.name) {
            Some(Format::LSystem) => {
                let (l, diags) = LSystem::parse(src);
                (l.map(|l| Species::new(l.graph.clone(), Some(l))), diags)
            }
            _ => {
                let (g, diags) = parse_source(src);
                (g.map(Species::from_graph), diags)
            }
        }
    }

    /// Amplify `instance` under `budget`.
    pub fn amplify(&self, instance: &Instance, budget: &Budget) -> Result<PrimitiveStream, AmplifyFailure> {
        Ok(match &self.lsystem {
            Some(l) => l.amplify(instance, budget)?,
            None => amplify(&self.graph, instance, budget)?,
        })
    }

    /// The species' parameters (not its working values: `let` values, an L-system's module arguments and
    /// internal values): their slots and names, in declaration order.
    pub fn declared_params(&self) -> Vec<(u16, &str)> {
        self.graph.of_role(ParamRole::Parameter).map(|(s, p)| (s, p.name.as_str())).collect()
    }

    /// The working values a person declared (`let` in a species file; an L-system's internal ones, named `_…`, and
    /// its depth limit left out): slots and names, in declaration order.
    pub fn working_values(&self) -> Vec<(u16, &str)> {
        let working = self.graph.of_role(ParamRole::Working).map(|(s, p)| (s, p.name.as_str()));
        working.filter(|(_, name)| !name.starts_with('_') && *name != DEPTH_PARAM).collect()
    }
}
