//! The preview's ground grid: lines on the flat ground every metre (every 2, 5, 10, … metres for a larger model or
//! grove), drawn by the renderer like any species — a tiny one of thin boxes, [`GRID_SOURCE`] — so the renderer
//! needs nothing new. The grid spans about twice what the preview shows, centred under it.

use canopy_protocol::SpeciesGraph;
use canopy_worlds::diag::SourceFile;

/// The grid as a species: `n + 1` lines along each axis, `step` metres apart, `width` wide, centred on the origin
/// and half sunk into the ground.
pub const GRID_SOURCE: &str = "species grid\n\
param n = 40\n\
param step = 1\n\
param width = 0.03\n\
param i = 0\n\
material(0.3, 0.3, 0.27)\n\
def Lines select(i <= n) {\n\
  group { }\n\
  group {\n\
    separator { translate(i * step - n * step / 2, 0, 0) box(width, width, n * step) }\n\
    separator { translate(0, 0, i * step - n * step / 2) box(n * step, width, width) }\n\
    calc { i = i + 1 }\n\
    recurse { use Lines }\n\
  }\n\
}\n";

/// Lines along each axis at most (spacings grow instead).
pub const MAX_LINES: u32 = 80;

/// The grid's species graph (the source is a constant: `None` would be a bug, which the tests below catch; the
/// preview then draws no grid).
pub fn graph() -> Option<SpeciesGraph> {
    canopy_worlds::load::parse_source(&SourceFile::new("grid.species", GRID_SOURCE)).0
}

/// Where the grid lies and how fine it is.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GridLayout {
    /// Metres between lines: 1, 2 or 5 times a power of ten, at least 1.
    pub step: f32,
    /// Squares along each side.
    pub n: u32,
    /// The grid's centre on the ground (x, z), on a line crossing.
    pub centre: [f32; 2],
}

impl GridLayout {
    /// A grid about twice as wide as the box `lo..hi` (and at least 8 m), centred under it.
    pub fn around(lo: [f32; 3], hi: [f32; 3]) -> GridLayout {
        let size = (hi[0] - lo[0]).max(hi[1] - lo[1]).max(hi[2] - lo[2]);
        let span = if size.is_finite() { (size * 2.0).clamp(8.0, 1e5) } else { 8.0 };
        let mut step = 1.0f32;
        'find: for decade in [1.0f32, 10.0, 100.0, 1000.0, 10_000.0] {
            for m in [1.0, 2.0, 5.0] {
                step = m * decade;
                if span / step <= MAX_LINES as f32 {
                    break 'find;
                }
            }
        }
        let n = ((span / step).ceil() as u32).clamp(2, MAX_LINES);
        let n = n + n % 2; // even: the centre is a crossing
        let snap = |v: f32| if v.is_finite() { (v / step).round() * step } else { 0.0 };
        GridLayout { step, n, centre: [snap((lo[0] + hi[0]) / 2.0), snap((lo[2] + hi[2]) / 2.0)] }
    }

    /// The grid species' parameter values for this layout, by slot.
    pub fn params(&self, graph: &SpeciesGraph) -> Vec<(u16, f32)> {
        [("n", self.n as f32), ("step", self.step), ("width", self.step * 0.03)]
            .into_iter()
            .filter_map(|(name, v)| graph.param_slot(name).map(|s| (s, v)))
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use canopy_worlds::amplify::{Budget, Instance, amplify};
    use canopy_worlds::primitive::PrimitiveKind;

    #[test]
    fn the_grid_is_thin_boxes_every_step_across_the_span() {
        let g = graph().expect("the grid parses");
        let l = GridLayout::around([-3.0, 0.0, -2.0], [3.0, 20.0, 2.0]);
        assert_eq!((l.step, l.n, l.centre), (1.0, 40, [0.0, 0.0]), "a 20 m tree: a line every metre");
        let inst = Instance { seed: 0, params: l.params(&g), detail: 0 };
        let s = amplify(&g, &inst, &Budget::default()).expect("amplifies");
        assert_eq!(s.primitives.len(), 2 * 41);
        assert_eq!(s.counts()[PrimitiveKind::Box as usize], 2 * 41);
        let (lo, hi) = s.bounds();
        assert!((lo[0] + 20.0).abs() < 0.1 && (hi[2] - 20.0).abs() < 0.1, "{lo:?} {hi:?}");
        assert!(hi[1] <= 0.02 && lo[1] >= -0.02, "flat on the ground: {lo:?} {hi:?}");
    }

    #[test]
    fn larger_models_get_coarser_lines() {
        let l = GridLayout::around([0.0, 0.0, 0.0], [130.0, 25.0, 130.0]);
        assert_eq!(l.step, 5.0);
        assert!(l.n <= MAX_LINES && l.n as f32 * l.step >= 260.0, "{l:?}");
        assert_eq!(l.centre, [65.0, 65.0]);
        let tiny = GridLayout::around([0.0; 3], [0.5; 3]);
        assert_eq!((tiny.step, tiny.n), (1.0, 8));
        let broken = GridLayout::around([f32::NAN; 3], [f32::NAN; 3]);
        assert_eq!((broken.step, broken.n, broken.centre), (1.0, 8, [0.0, 0.0]));
    }
}
