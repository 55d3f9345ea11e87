//! Far-view summaries (issue 15): a quadtree over the cell grid whose nodes say, per species, how much forest a
//! region holds, how tall it is and where it stands, in a few bytes, so that a client can draw the forest to the
//! horizon without the records of its trees (3D Tiles' HLOD, seed 000 §10's hyperforests).
//!
//! A node at level `L` covers `2^L × 2^L` cells: node `(L, x, z)` spans cells `x·2^L ..< (x+1)·2^L` along x and the
//! same along z (a level-0 node is one cell). Its four children are the nodes `(L−1, 2x + i, 2z + j)`. A node carries,
//! per species present, the instance count, the height distribution (mean and spread, in decimetres) and an 8 × 8
//! coverage mask over its area, plus a geometric error: the largest deviation, in metres, of drawing the region
//! from this node instead of from its records. A parent's counts are the sums of its children's.
//!
//! Wire size (postcard varints): a node is its key (1 + ≤ 5 + ≤ 5 bytes), its error (4) and per species ≤ 3 + 5 +
//! 3 + 3 + 10 bytes;
//! at most [`MAX_NODE_SPECIES`] species, so a node is at most [`MAX_NODE_BYTES`] bytes. Typical forest nodes of 2–4
//! species are 40–90 bytes.

use serde::{Deserialize, Serialize};

use crate::aoi::Grid;
use crate::netlimits;
use crate::record::{CellCoord, InstanceId};

/// Coverage mask resolution: `COVER_SIDE × COVER_SIDE` bits over a node.
pub const COVER_SIDE: u32 = 8;
/// Most species one node lists (the most numerous ones; ties by species id).
pub const MAX_NODE_SPECIES: usize = 32;
/// Highest level a node may have (a level-`MAX_LEVEL` node covers 2^16 × 2^16 cells: a whole world of the largest
/// grid a world may have).
pub const MAX_LEVEL: u8 = 16;
/// Largest encoded node, bytes (key, error, `MAX_NODE_SPECIES` full entries).
pub const MAX_NODE_BYTES: usize = 16 + MAX_NODE_SPECIES * 24;
/// Most nodes in one summaries message (a message stays well under a server frame).
pub const MAX_BATCH_NODES: usize = 64;
/// Most released keys in one summaries message.
pub const MAX_BATCH_RELEASES: usize = 256;

/// A quadtree node's name: its level and its column and row at that level.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
pub struct NodeKey {
    /// Level: the node covers `2^level × 2^level` cells.
    pub level: u8,
    /// Column at this level (cells `x · 2^level ..`).
    pub x: i32,
    /// Row at this level.
    pub z: i32,
}

impl NodeKey {
    /// The node at `level` that holds `cell`.
    pub fn of_cell(cell: CellCoord, level: u8) -> NodeKey {
        NodeKey { level, x: cell.x >> level, z: cell.z >> level }
    }

    /// The first cell (lowest x and z) the node covers.
    pub fn first_cell(self) -> CellCoord {
        CellCoord::new(self.x << self.level, self.z << self.level)
    }

    /// Cells per axis: `2^level`.
    pub fn side(self) -> i32 {
        1 << self.level
    }

    /// The node one level up that holds this one; `None` at [`MAX_LEVEL`].
    pub fn parent(self) -> Option<NodeKey> {
        (self.level < MAX_LEVEL).then(|| NodeKey { level: self.level + 1, x: self.x >> 1, z: self.z >> 1 })
    }

    /// The four children, in the order `(0,0), (1,0), (0,1), (1,1)` (x first); `None` at level 0.
    pub fn children(self) -> Option<[NodeKey; 4]> {
        if self.level == 0 {
            return None;
        }
        let (l, x, z) = (self.level - 1, self.x * 2, self.z * 2);
        let k = |i, j| NodeKey { level: l, x: x + i, z: z + j };
        Some([k(0, 0), k(1, 0), k(0, 1), k(1, 1)])
    }

    /// Whether the node covers `cell`.
    pub fn contains(self, cell: CellCoord) -> bool {
        NodeKey::of_cell(cell, self.level) == self
    }

    /// Whether the key names cells an [`InstanceId`] can name and its level is at most [`MAX_LEVEL`].
    pub fn is_valid(self) -> bool {
        if self.level > MAX_LEVEL {
            return false;
        }
        let lo = i64::from(InstanceId::CELL_MIN) >> self.level;
        let hi = i64::from(InstanceId::CELL_MAX) >> self.level;
        (lo..=hi).contains(&i64::from(self.x)) && (lo..=hi).contains(&i64::from(self.z))
    }
}

/// What a node says about one species.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct SpeciesCover {
    /// Species id (index into the welcome's table).
    pub species: u16,
    /// Instances of the species in the node's area.
    pub count: u32,
    /// Mean of the instances' `height` parameter, decimetres; 0 when the species has no `height` parameter (its
    /// default shape stands for every instance).
    pub height_dm: u16,
    /// Standard deviation of the `height` parameter, decimetres.
    pub spread_dm: u16,
    /// Coverage: bit `j · 8 + i` is set where the species stands in sub-square `(i, j)` of the node (x first).
    pub cover: u64,
}

impl SpeciesCover {
    /// Whether sub-square `(i, j)` (each `0..8`) is covered.
    pub fn covers(&self, i: u32, j: u32) -> bool {
        self.cover >> (j * COVER_SIDE + i) & 1 == 1
    }
}

/// One node of the summary hierarchy.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct NodeSummary {
    /// Which node.
    pub key: NodeKey,
    /// Geometric error, metres: how far drawing the region from this node may be from drawing its records (0 for a
    /// node with nothing in it, which never needs refining).
    pub error: f32,
    /// The species present, strictly increasing by species id, at most [`MAX_NODE_SPECIES`], none with a zero count.
    pub species: Vec<SpeciesCover>,
}

impl NodeSummary {
    /// All instances in the node.
    pub fn total(&self) -> u64 {
        self.species.iter().map(|s| u64::from(s.count)).sum()
    }

    /// Check the key, the error and the species list.
    pub fn validate(&self) -> Result<(), SummaryError> {
        if !self.key.is_valid() {
            return Err(SummaryError::Key);
        }
        if !(self.error.is_finite() && self.error >= 0.0) {
            return Err(SummaryError::Error);
        }
        if self.species.len() > MAX_NODE_SPECIES {
            return Err(SummaryError::TooManySpecies(self.species.len()));
        }
        let ordered = self.species.windows(2).all(|w| w[0].species < w[1].species);
        let ids = self.species.iter().all(|s| usize::from(s.species) < netlimits::MAX_SPECIES && s.count > 0);
        if !(ordered && ids) {
            return Err(SummaryError::Species);
        }
        Ok(())
    }
}

/// Summary nodes sent, and nodes the client should forget.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct SummaryBatch {
    /// Nodes, coarse before fine (a node's parent, where wanted, went before it).
    pub nodes: Vec<NodeSummary>,
    /// Nodes no longer wanted.
    pub released: Vec<NodeKey>,
}

impl SummaryBatch {
    /// Check counts and every node.
    pub fn validate(&self) -> Result<(), SummaryError> {
        if self.nodes.len() > MAX_BATCH_NODES || self.released.len() > MAX_BATCH_RELEASES {
            return Err(SummaryError::TooMany);
        }
        if !self.released.iter().all(|k| k.is_valid()) {
            return Err(SummaryError::Key);
        }
        self.nodes.iter().try_for_each(NodeSummary::validate)
    }
}

/// How a client wants the far field: sent while streaming; a session sends no summaries before it.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct FarView {
    /// Screen-space error threshold, pixels: a node is refined while its geometric error projects larger
    /// (Cesium's default is 16).
    pub error_px: f32,
    /// Viewport height, pixels.
    pub height_px: u16,
    /// Vertical field of view, radians.
    pub fov_y: f32,
    /// How far the client draws, metres (at most [`netlimits::MAX_FAR_RANGE`]).
    pub range: f32,
    /// The eye's height above the ground under it, metres: distances to nodes are taken in 3D with it.
    pub altitude: f32,
}

impl FarView {
    /// Check every number.
    pub fn validate(&self) -> Result<(), SummaryError> {
        let ok = self.error_px.is_finite()
            && self.error_px >= netlimits::MIN_FAR_ERROR_PX
            && self.error_px <= 1.0e4
            && self.height_px >= 1
            && self.fov_y.is_finite()
            && self.fov_y > 0.01
            && self.fov_y < 3.1
            && self.range.is_finite()
            && self.range >= 0.0
            && self.range <= netlimits::MAX_FAR_RANGE
            && self.altitude.is_finite()
            && self.altitude.abs() <= netlimits::MAX_COORDINATE;
        if ok { Ok(()) } else { Err(SummaryError::FarView) }
    }

    /// Pixels per metre of error at distance `d` (metres): `height_px / (2 · d · tan(fov_y / 2))`.
    pub fn px_per_metre(&self, d: f32) -> f32 {
        f32::from(self.height_px) / (2.0 * d.max(1.0) * (self.fov_y * 0.5).tan())
    }
}

/// The rule both sides apply to choose summary nodes (like [`crate::aoi::Aoi`] for cells): from the roots at
/// [`Refine::root_level`] within range, a node's children are wanted while the node's geometric error projects to
/// more than the far view's threshold, down to level 0. A node is *kept* (not released) under a looser rule — the
/// threshold times [`KEEP_FACTOR`] and the range times [`KEEP_RANGE`] — so that nodes do not flicker in and out at
/// the boundary (hysteresis). Nodes wholly inside the record radius are not wanted: records draw them.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Refine {
    /// The client's far view.
    pub view: FarView,
    /// The viewer's position on the ground plane (x, z), metres.
    pub eye: [f32; 2],
    /// Where cell (0, 0) starts, metres (the grid's origin).
    pub origin: [f32; 2],
    /// The world's cell edge, metres.
    pub cell_size: f32,
    /// The coarsest level: its nodes are the roots.
    pub root_level: u8,
    /// Records cover the disc of this radius around the eye.
    pub record_radius: f32,
}

/// Edge of a root node at least, metres: the roots are the coarsest nodes whose edge reaches this.
pub const ROOT_EDGE: f32 = 4096.0;

/// The level whose nodes first reach [`ROOT_EDGE`] for cells of `cell_size` metres.
pub fn root_level(cell_size: f32) -> u8 {
    let mut level = 0u8;
    while level < MAX_LEVEL && f64::from(cell_size) * f64::from(1u32 << level) < f64::from(ROOT_EDGE) {
        level += 1;
    }
    level
}

/// Whether node `key` covers at least one cell of the grid.
pub fn overlaps(grid: &Grid, key: NodeKey) -> bool {
    let c = key.first_cell();
    let side = i64::from(key.side());
    let (x0, z0) = (i64::from(c.x), i64::from(c.z));
    x0 <= i64::from(grid.max.x)
        && x0 + side > i64::from(grid.min.x)
        && z0 <= i64::from(grid.max.z)
        && z0 + side > i64::from(grid.min.z)
}

/// The threshold is multiplied by this for keeping a node (hysteresis: a node goes when its parent's error
/// projects to less than three quarters of the threshold, and comes at the threshold).
pub const KEEP_FACTOR: f32 = 0.75;
/// The range is multiplied by this for keeping a node.
pub const KEEP_RANGE: f32 = 1.125;

impl Refine {
    /// The node's rectangle on the ground, `[x0, z0, x1, z1]` metres.
    pub fn rect(&self, key: NodeKey) -> [f32; 4] {
        let c = key.first_cell();
        let side = self.cell_size * key.side() as f32;
        let (x0, z0) = (self.origin[0] + c.x as f32 * self.cell_size, self.origin[1] + c.z as f32 * self.cell_size);
        [x0, z0, x0 + side, z0 + side]
    }

    /// Horizontal distance from the eye to the nearest point of the node's rectangle (0 inside it).
    pub fn ground_distance(&self, key: NodeKey) -> f32 {
        let [x0, z0, x1, z1] = self.rect(key);
        let dx = (x0 - self.eye[0]).max(self.eye[0] - x1).max(0.0);
        let dz = (z0 - self.eye[1]).max(self.eye[1] - z1).max(0.0);
        (dx * dx + dz * dz).sqrt()
    }

    /// Horizontal distance from the eye to the node's farthest corner.
    fn far_distance(&self, key: NodeKey) -> f32 {
        let [x0, z0, x1, z1] = self.rect(key);
        let dx = (x0 - self.eye[0]).abs().max((x1 - self.eye[0]).abs());
        let dz = (z0 - self.eye[1]).abs().max((z1 - self.eye[1]).abs());
        (dx * dx + dz * dz).sqrt()
    }

    /// Distance from the eye to the node, metres (3D: the ground distance and the altitude).
    pub fn distance(&self, key: NodeKey) -> f32 {
        let g = self.ground_distance(key);
        (g * g + self.view.altitude * self.view.altitude).sqrt()
    }

    /// The node's geometric error `error` projected on screen, pixels.
    pub fn screen_error(&self, key: NodeKey, error: f32) -> f32 {
        error * self.view.px_per_metre(self.distance(key))
    }

    /// Whether a node at this key could be wanted at all: within range, and not wholly inside the record radius.
    pub fn in_range(&self, key: NodeKey, keep: bool) -> bool {
        let range = if keep { self.view.range * KEEP_RANGE } else { self.view.range };
        let inner = if keep { self.record_radius * 0.875 } else { self.record_radius };
        self.ground_distance(key) <= range && self.far_distance(key) > inner
    }

    /// Whether a node with geometric error `error` should be refined into its children (`keep`: the looser rule).
    pub fn refines(&self, key: NodeKey, error: f32, keep: bool) -> bool {
        let threshold = if keep { self.view.error_px * KEEP_FACTOR } else { self.view.error_px };
        key.level > 0 && self.screen_error(key, error) > threshold
    }

    /// The roots within range (keep: the looser range), in key order.
    pub fn roots(&self, keep: bool) -> Vec<NodeKey> {
        let range = if keep { self.view.range * KEEP_RANGE } else { self.view.range };
        let side = self.cell_size * (1u32 << self.root_level) as f32;
        let lo = |v: f32, o: f32| ((v - o - range) / side).floor() as i32;
        let hi = |v: f32, o: f32| ((v - o + range) / side).floor() as i32;
        let mut out = Vec::new();
        for x in lo(self.eye[0], self.origin[0])..=hi(self.eye[0], self.origin[0]) {
            for z in lo(self.eye[1], self.origin[1])..=hi(self.eye[1], self.origin[1]) {
                let k = NodeKey { level: self.root_level, x, z };
                if k.is_valid() && self.in_range(k, keep) {
                    out.push(k);
                }
            }
        }
        out
    }

    /// Whether `key` is wanted (`keep = false`) or kept (`keep = true`), given the errors of its ancestors:
    /// `error_of(k)` answers the geometric error of a node, `None` when it is not known (not computed yet: then
    /// its descendants are not wanted yet, coarse first).
    pub fn selects(&self, key: NodeKey, keep: bool, error_of: impl Fn(NodeKey) -> Option<f32>) -> bool {
        if key.level > self.root_level || !self.in_range(key, keep) {
            return false;
        }
        let mut k = key;
        while k.level < self.root_level {
            let Some(parent) = k.parent() else { return false };
            match error_of(parent) {
                Some(e) if self.refines(parent, e, keep) => k = parent,
                _ => return false,
            }
        }
        self.in_range(k, keep)
    }
}

impl Refine {
    /// Every node the rule reaches from the roots in range: a node's children (those in range) are reached while
    /// its error, `error_of(k)`, is known and projects past the threshold. Each node with its error, `None` where it
    /// is not known (its subtree is then not reached: coarse first). Roots first, then depth first.
    pub fn reach(&self, mut error_of: impl FnMut(NodeKey) -> Option<f32>) -> Vec<(NodeKey, Option<f32>)> {
        let mut out = Vec::new();
        let mut stack = self.roots(false);
        stack.reverse();
        while let Some(k) = stack.pop() {
            let error = error_of(k);
            out.push((k, error));
            if let Some(e) = error
                && self.refines(k, e, false)
            {
                stack.extend(k.children().into_iter().flatten().filter(|c| self.in_range(*c, false)));
            }
        }
        out
    }
}

/// Why a summary message is not acceptable.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum SummaryError {
    /// A key out of range.
    #[error("summary node key out of range")]
    Key,
    /// A negative or non-finite geometric error.
    #[error("summary node error not a finite non-negative number")]
    Error,
    /// More species than a node may list.
    #[error("summary node lists {0} species (allowed {MAX_NODE_SPECIES})")]
    TooManySpecies(usize),
    /// Species not strictly increasing, out of the table's range, or with a zero count.
    #[error("summary node species not in order, out of range or empty")]
    Species,
    /// More nodes or releases than a batch may carry.
    #[error("summary batch too long")]
    TooMany,
    /// A far view's numbers out of range.
    #[error("far view numbers out of range")]
    FarView,
}

#[cfg(test)]
mod tests {
    use super::*;

    fn node(level: u8, x: i32, z: i32) -> NodeKey {
        NodeKey { level, x, z }
    }

    #[test]
    fn keys_nest() {
        let c = CellCoord::new(-5, 9);
        let k = NodeKey::of_cell(c, 2);
        assert_eq!(k, node(2, -2, 2));
        assert_eq!(k.first_cell(), CellCoord::new(-8, 8));
        assert!(k.contains(c) && !k.contains(CellCoord::new(-4, 9)));
        let kids = k.children().unwrap();
        assert!(kids.iter().all(|ch| ch.parent() == Some(k)));
        assert_eq!(kids.iter().filter(|ch| ch.contains(c)).count(), 1);
        assert_eq!(node(0, 3, 3).children(), None);
        assert_eq!(node(MAX_LEVEL, 0, 0).parent(), None);
        assert!(node(16, 127, -128).is_valid());
        assert!(!node(16, 128, 0).is_valid() && !node(17, 0, 0).is_valid());
    }

    #[test]
    fn a_full_node_stays_within_its_stated_bytes() {
        let full = NodeSummary {
            key: node(MAX_LEVEL, -128, 127),
            error: f32::MAX,
            species: (0..MAX_NODE_SPECIES as u16)
                .map(|s| SpeciesCover {
                    species: s * 7,
                    count: u32::MAX,
                    height_dm: u16::MAX,
                    spread_dm: u16::MAX,
                    cover: u64::MAX,
                })
                .collect(),
        };
        full.validate().unwrap();
        let bytes = postcard::to_allocvec(&full).unwrap();
        assert!(bytes.len() <= MAX_NODE_BYTES, "{} > {MAX_NODE_BYTES}", bytes.len());
        let batch = SummaryBatch { nodes: vec![full; MAX_BATCH_NODES], released: vec![node(0, 0, 0); 256] };
        batch.validate().unwrap();
        assert!(postcard::to_allocvec(&batch).unwrap().len() < netlimits::MAX_SERVER_FRAME);
    }

    #[test]
    fn validation_refuses_bad_nodes() {
        let ok = NodeSummary {
            key: node(3, 1, 1),
            error: 24.0,
            species: vec![
                SpeciesCover { species: 0, count: 3, height_dm: 0, spread_dm: 0, cover: 1 },
                SpeciesCover { species: 2, count: 1, height_dm: 150, spread_dm: 20, cover: 2 },
            ],
        };
        ok.validate().unwrap();
        let mut bad = ok.clone();
        bad.species.swap(0, 1);
        assert_eq!(bad.validate(), Err(SummaryError::Species));
        let mut bad = ok.clone();
        bad.species[0].count = 0;
        assert_eq!(bad.validate(), Err(SummaryError::Species));
        let mut bad = ok.clone();
        bad.error = f32::NAN;
        assert_eq!(bad.validate(), Err(SummaryError::Error));
        let mut bad = ok;
        bad.key.level = 40;
        assert_eq!(bad.validate(), Err(SummaryError::Key));
        let view = FarView { error_px: 16.0, height_px: 1080, fov_y: 1.0, range: 20_000.0, altitude: 1500.0 };
        view.validate().unwrap();
        assert!(FarView { range: 1.0e9, ..view }.validate().is_err());
        assert!(FarView { error_px: 0.0, ..view }.validate().is_err());
    }

    #[test]
    fn refinement_is_finer_near_the_eye_and_keeps_with_hysteresis() {
        let view = FarView { error_px: 16.0, height_px: 1080, fov_y: 1.0, range: 20_000.0, altitude: 100.0 };
        let r =
            Refine { view, eye: [0.0, 0.0], origin: [0.0, 0.0], cell_size: 64.0, root_level: 8, record_radius: 512.0 };
        // Error: an eighth of the node's edge.
        let error = |k: NodeKey| Some(64.0 * k.side() as f32 / 8.0);
        let near = NodeKey::of_cell(CellCoord::new(12, 0), 3);
        let far = NodeKey::of_cell(CellCoord::new(250, 0), 3);
        assert!(r.selects(near, false, error), "a level-3 node 800 m away is wanted");
        assert!(!r.selects(far, false, error), "a level-3 node 16 km away is too fine");
        assert!(r.selects(NodeKey::of_cell(CellCoord::new(250, 0), 6), false, error));
        // Wholly inside the record radius: records draw it.
        assert!(!r.selects(NodeKey::of_cell(CellCoord::new(1, 1), 1), false, error));
        // Unknown parents: nothing finer is wanted yet.
        assert!(!r.selects(near, false, |k| (k.level > 5).then(|| 64.0 * k.side() as f32 / 8.0)));
        // An empty parent (error 0) is never refined.
        assert!(!r.selects(near, false, |k| if k.level == 4 { Some(0.0) } else { error(k) }));
        // Hysteresis: every wanted node is kept; some kept nodes are not wanted.
        let mut wanted = 0;
        let mut kept_only = 0;
        for x in -400..400 {
            let k = NodeKey { level: 3, x: x / 8, z: 0 };
            let (w, kp) = (r.selects(k, false, error), r.selects(k, true, error));
            assert!(!w || kp, "{k:?} wanted but not kept");
            wanted += u32::from(w);
            kept_only += u32::from(kp && !w);
        }
        assert!(wanted > 0 && kept_only > 0, "{wanted} {kept_only}");
        let (wanted_roots, kept_roots) = (r.roots(false), r.roots(true));
        assert!(!wanted_roots.is_empty() && wanted_roots.iter().all(|k| kept_roots.contains(k)));
    }

    #[test]
    fn roots_reach_four_kilometres() {
        assert_eq!(root_level(64.0), 6);
        assert_eq!(root_level(128.0), 5);
        assert_eq!(root_level(4096.0), 0);
        assert_eq!(root_level(0.001), MAX_LEVEL);
    }

    #[test]
    fn overlap_with_the_grid() {
        let grid =
            Grid { origin: [0.0, 0.0], cell_size: 64.0, min: CellCoord::new(-16, -16), max: CellCoord::new(15, 15) };
        assert!(overlaps(&grid, NodeKey { level: 6, x: 0, z: 0 }));
        assert!(overlaps(&grid, NodeKey { level: 6, x: -1, z: -1 }));
        assert!(!overlaps(&grid, NodeKey { level: 6, x: 1, z: 0 }));
        assert!(!overlaps(&grid, NodeKey { level: 2, x: 4, z: 0 }));
        assert!(overlaps(&grid, NodeKey { level: 2, x: 3, z: -4 }));
    }
}
