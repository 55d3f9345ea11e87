//! The embedded hypertree definitions (`worlds/hypertrees/*.hyp`, in the spirit of Figure 7) and the paper's
//! Table 1, which the benchmark reproduces tree for tree.

use canopy_protocol::hypertree::HypertreeDef;

use super::format::parse_hypertree;
use crate::diag::Diagnostics;
use crate::library::{EmbeddedFile, embedded, find_in};

/// What a [`HypertreeEntry`] holds: a hypertree definition (`.hyp`).
#[derive(Clone, Copy, Debug)]
pub enum HypertreeFile {}

/// One embedded hypertree definition, a file under `worlds/hypertrees/`.
pub type HypertreeEntry = EmbeddedFile<HypertreeFile>;

impl HypertreeEntry {
    /// Parse the entry (library files are tested to parse without diagnostics).
    pub fn load(&self) -> Result<HypertreeDef, Diagnostics> {
        let (d, diags) = parse_hypertree(&self.source());
        d.ok_or(Diagnostics(diags))
    }
}

/// Every embedded hypertree, in Table 1 order (A, B, C, D) and then the others.
pub const HYPERTREES: &[HypertreeEntry] =
    embedded!["../../hypertrees/" => "apple.hyp", "spruce.hyp", "willow.hyp", "fork.hyp", "perturbed.hyp"];

/// Find an entry by short name (`apple`) or file name (`apple.hyp`).
pub fn find(name: &str) -> Option<&'static HypertreeEntry> {
    find_in(HYPERTREES, name)
}

/// One row of the paper's Table 1 (seconds and bytes, Athlon 1.4 GHz): per storage structure (index list, index
/// list + bit array, 3D array), creation time, rendering time and memory, at resolution 100 without supersampling
/// and at 300 with s = 2; image 300 × 300.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PaperRow {
    /// A, B, C or D (Figure 7: top left, top right, bottom left, bottom right).
    pub label: char,
    /// The embedded definition modelled on that tree.
    pub file: &'static str,
    /// `[storage][config]` creation time, seconds: storage in [`crate::hypertree::StorageType::ALL`] order, config
    /// 0 = resolution 100, 1 = resolution 300 with s = 2.
    pub creation: [[f64; 2]; 3],
    /// Rendering time, seconds, same layout.
    pub render: [[f64; 2]; 3],
    /// Memory, bytes, same layout.
    pub memory: [[f64; 2]; 3],
}

const K: f64 = 1024.0;
const M: f64 = 1024.0 * 1024.0;

/// Table 1 of the paper.
pub const TABLE1: [PaperRow; 4] = [
    PaperRow {
        label: 'A',
        file: "apple.hyp",
        creation: [[0.5, 0.5], [0.5, 0.5], [0.4, 1.9]],
        render: [[1.0, 16.7], [0.6, 8.0], [0.5, 7.7]],
        memory: [[209.0 * K, 860.0 * K], [331.0 * K, 4.0 * M], [2.9 * M, 80.0 * M]],
    },
    PaperRow {
        label: 'B',
        file: "spruce.hyp",
        creation: [[2.6, 2.3], [2.6, 2.4], [2.2, 3.7]],
        render: [[0.8, 11.5], [0.4, 5.7], [0.4, 5.6]],
        memory: [[80.0 * K, 350.0 * K], [202.0 * K, 3.5 * M], [2.9 * M, 80.0 * M]],
    },
    PaperRow {
        label: 'C',
        file: "willow.hyp",
        creation: [[0.4, 0.8], [0.4, 0.9], [0.3, 2.0]],
        render: [[1.0, 15.5], [0.5, 7.5], [0.5, 7.1]],
        memory: [[210.0 * K, 1.4 * M], [332.0 * K, 4.6 * M], [2.9 * M, 80.0 * M]],
    },
    PaperRow {
        label: 'D',
        file: "fork.hyp",
        creation: [[2.1, 1.4], [2.2, 1.5], [1.0, 2.5]],
        render: [[0.5, 7.8], [0.3, 4.1], [0.3, 4.1]],
        memory: [[56.0 * K, 315.0 * K], [178.0 * K, 3.5 * M], [2.9 * M, 80.0 * M]],
    },
];
