//! What a session sends per instance and species: the procedural payload (species programs and instance records,
//! Canopy's own) or, for the bandwidth baselines of `canopy bandwidth`, explicit geometry decided by the same area of
//! interest, order and pacing.

use std::ops::Range;
use std::sync::Arc;

use canopy_protocol::{CellCoord, InstanceId};

/// What a session sends for instances and species.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum PayloadMode {
    /// Species programs once, then instance records (Canopy).
    #[default]
    Procedural,
    /// Baseline 1: every instance's own amplified mesh, before its record; no species programs.
    UniqueMesh,
    /// Baseline 2: one mesh per species instead of its program, and per-instance transforms before each batch.
    Instanced,
}

impl PayloadMode {
    /// Every mode.
    pub const ALL: [PayloadMode; 3] = [PayloadMode::Procedural, PayloadMode::UniqueMesh, PayloadMode::Instanced];

    /// A short label for reports and command lines.
    pub fn label(self) -> &'static str {
        match self {
            PayloadMode::Procedural => "procedural",
            PayloadMode::UniqueMesh => "unique-mesh",
            PayloadMode::Instanced => "instanced",
        }
    }
}

/// Where the explicit payloads come from: encoded blobs, each at most [`netlimits::MAX_GEOMETRY_BYTES`] bytes
/// (a larger blob is not sent and is counted in [`SessionStats::oversize`]). Called from the session's poll, so an
/// implementation should cache; it must be deterministic.
pub trait GeometrySource: Send + Sync {
    /// Instance `id`'s own mesh.
    fn instance_mesh(&self, id: InstanceId) -> Arc<Vec<u8>>;
    /// Species `id`'s one shared mesh.
    fn species_mesh(&self, species: u8) -> Arc<Vec<u8>>;
    /// The transforms of the instances of `cell` with indices `records` (one cell batch).
    fn transforms(&self, cell: CellCoord, records: Range<u16>) -> Vec<u8>;
}

/// The payload mode and, for the explicit modes, the geometry it sends. An explicit mode without a source sends
/// procedurally.
#[derive(Clone, Default)]
pub struct Payload {
    /// The mode.
    pub mode: PayloadMode,
    /// The geometry of the explicit modes.
    pub geometry: Option<Arc<dyn GeometrySource>>,
}

impl Payload {
    /// An explicit (or procedural) payload from `geometry`.
    pub fn new(mode: PayloadMode, geometry: Arc<dyn GeometrySource>) -> Payload {
        Payload { mode, geometry: Some(geometry) }
    }

    pub(crate) fn effective(&self) -> PayloadMode {
        if self.geometry.is_some() { self.mode } else { PayloadMode::Procedural }
    }
}

impl std::fmt::Debug for Payload {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Payload").field("mode", &self.mode).field("geometry", &self.geometry.is_some()).finish()
    }
}

impl PartialEq for Payload {
    fn eq(&self, other: &Payload) -> bool {
        self.mode == other.mode
            && match (&self.geometry, &other.geometry) {
                (Some(a), Some(b)) => Arc::ptr_eq(a, b),
                (None, None) => true,
                _ => false,
            }
    }
}
