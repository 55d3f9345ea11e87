//! The far view's summary nodes drawn as forest (issue 15), pure (no GPU, no clock, no threads): from the scene's
//! [`SceneFar`], the ground, the species' canopy tiles and the camera, a [`ForestPlan`] — which node draws which
//! of its sub-squares (not those its held children or the records draw), cross-fades as that changes, culling, and
//! the frame's [`ForestPatch`] instances front to back with the ground under them.
//!
//! On the GPU one summary node and one species is one instance: a proxy box over the node raymarched
//! (`shaders/forest.wgsl`) through the species' canopy tile ([`super::tile`]), repeated over the ground in world
//! coordinates (so patches of one species join without seams, and a node and its children show the same trees;
//! each repetition shifted at random, so the stand does not repeat in rows a far view turns into moiré),
//! on the sub-squares the instance draws, following the ground through a 9 × 9 grid of heights at the
//! sub-squares' corners; scaled by the species' mean height over its representative's, thinned to the summary's
//! density (count over covered area, ramping toward the neighbours' at the node's edges) by density classes, and
//! feathered toward uncovered sub-squares by the
//! coverage mask interpolated between sub-square centres. A ray marches the tile resolution whose voxels are about a
//! pixel where it enters each sub-square; where trees stand closer than `RenderConfig::forest_layer` pixels it
//! crosses the species' uniform layer ([`super::tile::CanopyProfile`]) instead.
//!
//! Work per frame is linear in the nodes held (the per-node tables are rebuilt only when the scene's far
//! generation changes); a node smaller on screen than [`LodConfig::cull_px`](super::LodConfig) is dropped with its
//! sub-squares (they are merged into its one instance). Fades are keyed by (node, species): when the sub-squares
//! a node draws change (children arrive or go, record cells cover it, the node arrives or is released), the new
//! set fades in and the old one out with complementary dither masks, over the usual fade time.

use std::sync::Arc;

use bytemuck::{Pod, Zeroable};
use canopy_protocol::CellCoord;
use canopy_protocol::summary::{COVER_SIDE, NodeKey, NodeSummary, SpeciesCover};
use canopy_worlds::world::Ground;
use glam::Vec3;

use super::lod::projected_size;
use super::scene::SceneFar;
use super::select::View;
use super::stats::FrameStats;
use super::tile::TILE_TREES;

/// Corners per node edge of a node's ground grid (the sub-squares' corners).
pub(crate) const GROUND_SIDE: usize = COVER_SIDE as usize + 1;
/// Heights in a node's ground grid.
pub(crate) const GROUND_POINTS: usize = GROUND_SIDE * GROUND_SIDE;
/// Nodes whose ground grids are computed per frame at most (nearest first; the rest wait for later frames). A grid
/// of a fractal ground costs about 11 µs (one lattice patch per node): about 3 ms a frame at most.
pub(crate) const GROUND_NODES_PER_FRAME: usize = 256;
/// A patch whose density keeps less than one of its tile's trees a repetition on average is not marched (the
/// march keeps whole classes, each repetition of the tile rounding at its own random phase, so the stand keeps
/// its density on average; this sparse it would march a whole patch for a tree in many repetitions): it is drawn
/// only where rays take the uniform layer, which thins continuously.
const MIN_KEEP: f32 = 1.0 / (TILE_TREES * TILE_TREES) as f32;

/// The tile resolution a patch marches has voxels of about this many pixels (0.5: the finest detail; 1: half the
/// samples — on an H200 at 1920×1080 from 1,500 m up, 0.5 cost 70 ms a frame).
pub(crate) const VOXEL_PX: f32 = 1.0;

/// A species' canopy tile, resident in the atlas.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct TileVol {
    /// Volume index of the tile's finest resolution; the [`TILE_MIPS`](super::tile::TILE_MIPS) − 1 coarser ones
    /// follow it (the forest shader takes the one at the finest's index plus its level).
    pub volume: u32,
    /// Tile edge, metres at scale 1.
    pub period: f32,
    /// Tile height, metres at scale 1.
    pub top: f32,
    /// Horizontal voxel edge of the finest resolution, metres at scale 1.
    pub voxel: f32,
    /// Trees per square metre at full density, scale 1.
    pub density: f32,
    /// The representative's `height` parameter (summaries' heights scale the tile by their mean over it); `None`
    /// for a species without one.
    pub reference: Option<f32>,
    /// Index of the tile's [`super::tile::CanopyProfile`] in the profiles buffer (its first `vec4`).
    pub profile: u32,
}

/// Where a species' canopy tile stands.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) enum TileState {
    /// Being baked (or its far volume is).
    Pending,
    /// Resident.
    Ready(TileVol),
    /// No far volume or no room: the species is not drawn in the far field.
    Failed,
}

/// One summary patch as the forest pipeline reads it (a vertex buffer entry, per instance).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub(crate) struct ForestPatch {
    /// The node's first corner (x, z), its edge and the canopy's height above the ground, metres.
    pub rect: [f32; 4],
    /// The proxy box's lowest and highest y.
    pub span: [f32; 2],
    /// Sub-squares this instance marches (bit `j · 8 + i`), low word first.
    pub cover: [u32; 2],
    /// The species' coverage of the node (the field its trees thin toward the edges by), low word first.
    pub field: [u32; 2],
    /// Index of the node's first height in the frame's ground list ([`GROUND_POINTS`] of them, row-major, x first).
    pub ground: u32,
    /// The volume index of the tile's finest resolution (the others follow it).
    pub volume: u32,
    /// Tile scale: the species' mean height over its representative's.
    pub scale: f32,
    /// Fraction of the tile's trees kept in the node's middle (the summary's density over the tile's).
    pub keep: f32,
    /// Dither mask (see [`super::lod::LodDraw::mask`]).
    pub mask: f32,
    /// The tile's profile (its first `vec4` in the profiles buffer): the stand as a uniform layer.
    pub profile: u32,
    /// Distance from the eye beyond which a ray takes the profile rather than the tile's voxels, metres (dithered
    /// over ±25 %; infinite: never).
    pub layer_from: f32,
    /// Per metre from the eye, the tile resolution's level the march takes: `⌊log₂(t · mip_scale)⌋`, clamped (voxels
    /// of about [`VOXEL_PX`] pixels where a ray enters each sub-square).
    pub mip_scale: f32,
    /// The fraction kept at the node's −x and +x edges: `keep` ramps to them from the middle (`keep_at`).
    pub edges_x: [f32; 2],
    /// The same at its −z and +z edges.
    pub edges_z: [f32; 2],
}

/// The sub-squares of quadrant `q` (children order: `(0,0), (1,0), (0,1), (1,1)`).
pub(crate) fn quadrant_mask(q: usize) -> u64 {
    let half = COVER_SIDE / 2;
    let (qi, qj) = ((q as u32 & 1) * half, (q as u32 >> 1) * half);
    let mut m = 0u64;
    for j in qj..qj + half {
        for i in qi..qi + half {
            m |= 1 << (j * COVER_SIDE + i);
        }
    }
    m
}

/// A mask grown by one sub-square in all eight directions.
pub(crate) fn dilate(m: u64) -> u64 {
    const NOT_FIRST: u64 = !0x0101_0101_0101_0101;
    const NOT_LAST: u64 = !0x8080_8080_8080_8080;
    let rows = m | (m << 1 & NOT_FIRST) | (m >> 1 & NOT_LAST);
    rows | rows << 8 | rows >> 8
}

/// What one (node, species) draws while its sub-squares change: the set shown (fading in while `fade < 1`) and the
/// set before it (fading out).
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct MaskFade {
    /// Sub-squares shown.
    pub shown: u64,
    /// Sub-squares shown before the current fade.
    pub old: u64,
    /// Fade progress of `shown`, 0..=1.
    pub fade: f32,
}

impl Default for MaskFade {
    fn default() -> MaskFade {
        MaskFade { shown: 0, old: 0, fade: 1.0 }
    }
}

impl MaskFade {
    /// Advance by `progress` of a fade (≥ 1 finishes at once) toward showing `wanted`; a change asked for during a
    /// fade waits for it to end.
    pub(crate) fn step(&mut self, wanted: u64, progress: f32) {
        if self.fade < 1.0 {
            self.fade = (self.fade + progress).min(1.0);
        }
        if self.fade >= 1.0 {
            self.old = self.shown;
        }
        if self.shown == wanted || self.fade < 1.0 {
            return;
        }
        self.old = self.shown;
        self.shown = wanted;
        self.fade = progress.clamp(0.0, 1.0);
        if self.fade >= 1.0 {
            self.old = wanted;
        }
    }

    /// The draws: (sub-squares, dither mask) — those in both sets whole, the new ones fading in, the old ones
    /// fading out with the complementary mask.
    pub(crate) fn parts(&self) -> impl Iterator<Item = (u64, f32)> {
        let f = self.fade;
        let parts = if f >= 1.0 {
            [(self.shown, 1.0), (0, 0.0), (0, 0.0)]
        } else if f <= 0.0 {
            [(self.old, 1.0), (0, 0.0), (0, 0.0)]
        } else {
            [(self.shown & self.old, 1.0), (self.shown & !self.old, f), (self.old & !self.shown, -f)]
        };
        parts.into_iter().filter(|(m, _)| *m != 0)
    }

    /// Whether nothing is drawn, now or while fading.
    pub(crate) fn idle(&self) -> bool {
        self.shown == 0 && (self.fade >= 1.0 || self.old == 0)
    }
}

/// One species of a node, with its fade.
#[derive(Clone, Copy, Debug)]
struct SpeciesFade {
    cover: SpeciesCover,
    fade: MaskFade,
    /// Whether the node (still) lists the species.
    listed: bool,
    /// Its density beyond each edge (−x, +x, −z, +z; trees a square metre): the node drawing the far side of the
    /// edge's midpoint, or this node's own where records or nothing draw there.
    beyond: [f32; 4],
}

/// A node's ground: heights at its sub-squares' corners and their range.
#[derive(Clone, Debug)]
struct NodeGround {
    heights: Box<[f32; GROUND_POINTS]>,
    lo: f32,
    hi: f32,
}

/// One node held (or fading out after it went), carried across frames and generations by key.
#[derive(Clone, Debug)]
struct NodeEntry {
    key: NodeKey,
    /// Whether the scene holds it now.
    present: bool,
    /// Sub-squares others draw: its held children's and the record cells'.
    hidden: u64,
    ground: Option<NodeGround>,
    species: Vec<SpeciesFade>,
}

/// Everything the forest plan of a frame reads.
#[derive(Clone, Copy, Debug)]
pub(crate) struct ForestInputs<'a> {
    /// The far field.
    pub far: &'a SceneFar,
    /// The ground patches stand on.
    pub ground: &'a Ground,
    /// Canopy tiles by species id (`None`: not asked for, and not waited for: a species without a graph).
    pub tiles: &'a [Option<TileState>],
    /// The camera and fade progress.
    pub view: View,
    /// Nodes smaller than this on screen, pixels, are not drawn.
    pub cull_px: f32,
    /// Tree spacings a pixel spans beyond which the canopy is drawn as its uniform layer (0: never).
    pub layer: f32,
}

/// The forest plan (see the module docs), kept between frames.
#[derive(Debug, Default)]
pub(crate) struct ForestPlan {
    nodes: Vec<NodeEntry>,
    spare: Vec<NodeEntry>,
    generation: Option<u64>,
    ground_of: Option<Ground>,
    /// Species listed by the nodes held, each once, ascending (their tiles are wanted).
    pub species: Vec<u16>,
    /// Patches with their distance and height, before sorting.
    unsorted: Vec<(f32, f32, ForestPatch)>,
    /// This frame's patches, front to back (the taller species of a node first).
    pub patches: Vec<ForestPatch>,
    /// This frame's ground grids, [`GROUND_POINTS`] per drawn node.
    pub ground: Vec<f32>,
}

impl ForestPlan {
    /// Nodes held or fading out.
    #[cfg(test)]
    fn nodes(&self) -> usize {
        self.nodes.len()
    }

    /// Plan a frame: follow the scene's far field, compute missing ground grids (a bounded number), step the
    /// fades, cull, and list the patches front to back; counts in `stats`.
    pub(crate) fn plan(&mut self, input: &ForestInputs, stats: &mut FrameStats) {
        self.unsorted.clear();
        self.patches.clear();
        self.ground.clear();
        let cell = input.far.cell_size;
        if !(cell.is_finite() && cell > 0.0) {
            return;
        }
        let ground_changed = !self.ground_of.as_ref().is_some_and(|g| g.ptr_eq(input.ground));
        if ground_changed {
            self.nodes.iter_mut().for_each(|n| n.ground = None);
            self.ground_of = Some(input.ground.clone());
        }
        if self.generation != Some(input.far.generation) {
            self.sync(input.far);
        }
        self.compute_ground(input, stats);
        self.step_and_list(input, stats);
        self.nodes.retain(|n| n.present || n.species.iter().any(|s| !s.fade.idle()));
        self.unsorted.sort_unstable_by(|a, b| a.0.total_cmp(&b.0).then(b.1.total_cmp(&a.1)));
        self.patches.clear();
        self.patches.extend(self.unsorted.iter().map(|p| p.2));
        stats.summary_nodes = input.far.nodes.len();
        stats.forest_patches = self.patches.len();
        stats.forest_squares =
            self.patches.iter().map(|p| u64::from(p.cover[0].count_ones() + p.cover[1].count_ones())).sum();
    }

    /// Follow a new generation: merge the nodes by key (states carried over; a node no longer held stays, fading
    /// out), and work out which sub-squares each node leaves to its held children and to the record cells.
    fn sync(&mut self, far: &SceneFar) {
        let mut incoming: Vec<&Arc<NodeSummary>> = far.nodes.iter().collect();
        incoming.sort_by_key(|n| n.key);
        incoming.dedup_by_key(|n| n.key);
        let keys: Vec<NodeKey> = incoming.iter().map(|n| n.key).collect();
        let mut old = std::mem::replace(&mut self.nodes, std::mem::take(&mut self.spare)).into_iter().peekable();
        self.nodes.clear();
        let carried = |e: &mut NodeEntry, n: Option<&NodeSummary>| {
            e.present = n.is_some();
            for s in &mut e.species {
                s.listed = false;
            }
            for c in n.map_or(&[][..], |n| &n.species) {
                match e.species.iter_mut().find(|s| s.cover.species == c.species) {
                    Some(s) => (s.cover, s.listed) = (*c, true),
                    None => e.species.push(SpeciesFade {
                        cover: *c,
                        fade: MaskFade::default(),
                        listed: true,
                        beyond: [0.0; 4],
                    }),
                }
            }
        };
        for n in &incoming {
            while let Some(o) = old.next_if(|o| o.key < n.key) {
                let mut o = o;
                carried(&mut o, None);
                self.nodes.push(o);
            }
            let mut e = match old.next_if(|o| o.key == n.key) {
                Some(o) => o,
                None => NodeEntry { key: n.key, present: true, hidden: 0, ground: None, species: Vec::new() },
            };
            carried(&mut e, Some(n));
            self.nodes.push(e);
        }
        for mut o in old {
            carried(&mut o, None);
            self.nodes.push(o);
        }
        // What others draw: held children take their quadrants; record cells the sub-squares whose centre they hold.
        let bbox = far.record_cells.iter().fold(None, |b: Option<[i32; 4]>, c| {
            Some(b.map_or([c.x, c.z, c.x, c.z], |b| [b[0].min(c.x), b[1].min(c.z), b[2].max(c.x), b[3].max(c.z)]))
        });
        for e in self.nodes.iter_mut().filter(|e| e.present) {
            let mut hidden = 0;
            if let Some(children) = e.key.children() {
                for (q, c) in children.iter().enumerate() {
                    if keys.binary_search(c).is_ok() {
                        hidden |= quadrant_mask(q);
                    }
                }
            }
            if let Some(b) = bbox {
                hidden |= record_mask(e.key, &far.record_cells, b);
            }
            e.hidden = hidden;
        }
        self.densities_beyond(far, &incoming);
        self.species = self.nodes.iter().flat_map(|e| e.species.iter().map(|s| s.cover.species)).collect();
        self.species.sort_unstable();
        self.species.dedup();
        self.generation = Some(far.generation);
    }

    /// Each present node's species' densities beyond its four edges ([`SpeciesFade::beyond`]), from `incoming`
    /// (the scene's nodes by key): a patch's density ramps from its own in the middle to the mean of both at each
    /// edge (`forest.wgsl` `keep_at`), so neighbouring nodes of different densities meet without a step. (Each node
    /// one density over its area drew the forest as blocks a node wide, lighter and darker, sharpest where finer
    /// nodes meet coarser ones.) What one node gains toward an edge its neighbour of the same size loses.
    fn densities_beyond(&mut self, far: &SceneFar, incoming: &[&Arc<NodeSummary>]) {
        let cell = far.cell_size;
        // The finest node held that contains `c`, unless records draw it.
        let drawer = |c: CellCoord| -> Option<&NodeSummary> {
            if far.record_cells.binary_search(&c).is_ok() {
                return None;
            }
            (0..=canopy_protocol::summary::MAX_LEVEL).find_map(|level| {
                let k = NodeKey::of_cell(c, level);
                incoming.binary_search_by_key(&k, |n| n.key).ok().map(|i| &**incoming[i])
            })
        };
        let density = |n: &NodeSummary, species: u16| {
            let edge = node_rect(n.key, cell)[2];
            let sub_area = (edge / COVER_SIDE as f32).powi(2);
            n.species.iter().find(|s| s.species == species).map_or(0.0, |s| own_density(s, sub_area))
        };
        for e in self.nodes.iter_mut().filter(|e| e.present) {
            let (first, side) = (e.key.first_cell(), e.key.side());
            let mid = side / 2;
            let across = [
                CellCoord::new(first.x - 1, first.z + mid),
                CellCoord::new(first.x + side, first.z + mid),
                CellCoord::new(first.x + mid, first.z - 1),
                CellCoord::new(first.x + mid, first.z + side),
            ];
            let nodes = across.map(drawer);
            let sub_area = (node_rect(e.key, cell)[2] / COVER_SIDE as f32).powi(2);
            for s in &mut e.species {
                let own = own_density(&s.cover, sub_area);
                s.beyond = nodes.map(|n| n.map_or(own, |n| density(n, s.cover.species)));
            }
        }
    }

    /// Ground grids for nodes without one, nearest first, at most [`GROUND_NODES_PER_FRAME`]; the nodes still
    /// without count as waiting.
    fn compute_ground(&mut self, input: &ForestInputs, stats: &mut FrameStats) {
        let cell = input.far.cell_size;
        let eye = input.view.eye;
        let mut missing: Vec<(f32, usize)> = (self.nodes.iter().enumerate())
            .filter(|(_, e)| e.ground.is_none())
            .map(|(i, e)| {
                let [x0, z0, edge] = node_rect(e.key, cell);
                let (dx, dz) = (x0 + 0.5 * edge - eye.x, z0 + 0.5 * edge - eye.z);
                ((dx * dx + dz * dz).sqrt() - 0.71 * edge, i)
            })
            .collect();
        if missing.len() > GROUND_NODES_PER_FRAME {
            missing.select_nth_unstable_by(GROUND_NODES_PER_FRAME, |a, b| a.0.total_cmp(&b.0));
            missing.truncate(GROUND_NODES_PER_FRAME);
        }
        for (_, i) in missing {
            let e = &mut self.nodes[i];
            e.ground = Some(ground_grid(input.ground, node_rect(e.key, cell)));
        }
        stats.forest_waiting += self.nodes.iter().filter(|e| e.ground.is_none()).count();
    }

    /// Step every fade, cull nodes, and list the patches and their ground.
    fn step_and_list(&mut self, input: &ForestInputs, stats: &mut FrameStats) {
        let v = &input.view;
        self.unsorted.clear();
        self.ground.clear();
        let cell = input.far.cell_size;
        let footprint = 2.0 * v.tan_half / v.height_px;
        for e in &mut self.nodes {
            let [x0, z0, edge] = node_rect(e.key, cell);
            let sub_area = (edge / COVER_SIDE as f32).powi(2);
            // Tiles and scales of the node's species; the node's box.
            let mut top_max = 0.0f32;
            let mut ready_any = false;
            let tile_of = |s: u16| match input.tiles.get(usize::from(s)).copied().flatten() {
                Some(TileState::Ready(t)) => Some(t),
                _ => None,
            };
            for s in &e.species {
                if let Some(t) = tile_of(s.cover.species) {
                    top_max = top_max.max(t.top * tile_scale(&s.cover, &t));
                    ready_any = true;
                } else if s.listed
                    && e.present
                    && matches!(input.tiles.get(usize::from(s.cover.species)), Some(Some(TileState::Pending)))
                {
                    stats.forest_waiting += 1;
                }
            }
            let Some(g) = &e.ground else { continue };
            let (lo, hi) = (g.lo, g.hi + top_max);
            let center = Vec3::new(x0 + 0.5 * edge, 0.5 * (lo + hi), z0 + 0.5 * edge);
            let radius = Vec3::new(0.5 * edge, 0.5 * (hi - lo), 0.5 * edge).length();
            let visible = ready_any && v.frustum.sphere_visible(center, radius);
            let dist = (center - v.eye).length();
            let big_enough =
                projected_size(0.5 * edge, dist.max(0.5 * edge + 1e-3), v.tan_half, v.height_px) >= input.cull_px;
            let mut first_ground = None;
            for s in &mut e.species {
                let Some(t) = tile_of(s.cover.species) else { continue };
                let wanted = if e.present && s.listed { s.cover.cover & !e.hidden } else { 0 };
                s.fade.step(wanted, v.progress);
                if !(visible && big_enough) {
                    continue;
                }
                let scale = tile_scale(&s.cover, &t);
                // Densities as fractions of the tile's trees: the node's own, and at each edge the mean of its and
                // the neighbour's.
                let tile_density = t.density / (scale * scale);
                let own = own_density(&s.cover, sub_area);
                let keep = (own / tile_density).min(1.0);
                let edges = s.beyond.map(|b| (0.5 * (own + b) / tile_density).min(1.0));
                // The march takes the resolution whose voxels are about `VOXEL_PX` pixels (coarser ones lose the
                // sunlit sides) where each ray enters each sub-square.
                let mip_scale = VOXEL_PX * footprint / (t.voxel * scale);
                // Where a pixel spans `layer` tree spacings.
                let spacing = t.period * scale / TILE_TREES as f32;
                let layer_from = if input.layer > 0.0 { input.layer * spacing / footprint } else { f32::INFINITY };
                // Too sparse to march, and no ray reaches the layer (its dither starts at 0.75 × `layer_from`).
                if keep.max(edges.into_iter().fold(0.0, f32::max)) < MIN_KEEP && dist + radius < 0.75 * layer_from {
                    continue;
                }
                let covered_drawn = (wanted & s.cover.cover).count_ones();
                stats.forest_trees +=
                    f64::from(s.cover.count) * f64::from(covered_drawn) / f64::from(s.cover.cover.count_ones().max(1));
                for (m, mask) in s.fade.parts() {
                    // March the uncovered neighbours too: the stand thins into them.
                    let march = m | (dilate(m) & !s.cover.cover & !e.hidden);
                    let ground = *first_ground.get_or_insert_with(|| {
                        let at = self.ground.len() as u32;
                        self.ground.extend_from_slice(&g.heights[..]);
                        at
                    });
                    let patch = ForestPatch {
                        rect: [x0, z0, edge, t.top * scale],
                        span: [lo, hi],
                        cover: [march as u32, (march >> 32) as u32],
                        field: [s.cover.cover as u32, (s.cover.cover >> 32) as u32],
                        ground,
                        volume: t.volume,
                        scale,
                        keep,
                        mask,
                        edges_x: [edges[0], edges[1]],
                        edges_z: [edges[2], edges[3]],
                        profile: t.profile,
                        layer_from,
                        mip_scale,
                    };
                    self.unsorted.push((dist, t.top * scale, patch));
                }
            }
            if first_ground.is_some() {
                stats.forest_nodes += 1;
            }
        }
    }
}

/// A node's first corner (x, z) and edge, metres (the grid's origin at (0, 0)).
pub(crate) fn node_rect(key: NodeKey, cell_size: f32) -> [f32; 3] {
    let c = key.first_cell();
    [c.x as f32 * cell_size, c.z as f32 * cell_size, key.side() as f32 * cell_size]
}

/// A species' density in a node, trees a square metre: its count over the area its coverage bits cover.
fn own_density(s: &SpeciesCover, sub_area: f32) -> f32 {
    s.count as f32 / (s.cover.count_ones().max(1) as f32 * sub_area)
}

/// The tile scale of a species in a node: its mean height over the representative's, clamped as instance scales
/// are (1 without a height).
pub(crate) fn tile_scale(cover: &SpeciesCover, tile: &TileVol) -> f32 {
    match tile.reference {
        Some(r) if cover.height_dm > 0 && r > 0.0 => (f32::from(cover.height_dm) * 0.1 / r).clamp(0.05, 20.0),
        _ => 1.0,
    }
}

/// The sub-squares of `key` whose centre lies in a record cell (`cells` sorted, `bbox` their bounds).
fn record_mask(key: NodeKey, cells: &[CellCoord], bbox: [i32; 4]) -> u64 {
    let first = key.first_cell();
    let side = i64::from(key.side());
    let (x1, z1) = (i64::from(first.x) + side - 1, i64::from(first.z) + side - 1);
    if x1 < i64::from(bbox[0]) || z1 < i64::from(bbox[1]) || first.x > bbox[2] || first.z > bbox[3] {
        return 0;
    }
    let n = i64::from(COVER_SIDE);
    let mut m = 0;
    for j in 0..n {
        for i in 0..n {
            // The centre of sub-square (i, j) in cells: first + (i + ½) · side / 8, floored.
            let at = |f: i32, k: i64| (i64::from(f) + ((2 * k + 1) * side).div_euclid(2 * n)) as i32;
            if cells.binary_search(&CellCoord::new(at(first.x, i), at(first.z, j))).is_ok() {
                m |= 1 << (j * n + i);
            }
        }
    }
    m
}

/// Heights at a node's sub-square corners: a height grid read directly; a fractal from one patch of the lattice
/// at the depth whose spacing is at most a sub-square (coarser detail than the sub-squares would not show).
fn ground_grid(ground: &Ground, [x0, z0, edge]: [f32; 3]) -> NodeGround {
    let sub = edge / COVER_SIDE as f32;
    let at = |k: usize| k as f32 * sub;
    let mut heights = Box::new([0.0f32; GROUND_POINTS]);
    match ground {
        Ground::Grid(t) => {
            for (k, h) in heights.iter_mut().enumerate() {
                *h = t.height(x0 + at(k % GROUND_SIDE), z0 + at(k / GROUND_SIDE));
            }
        }
        Ground::Fractal(f) => {
            let depth = (f.spacing(0) / f64::from(sub)).log2().ceil().clamp(0.0, 30.0) as u32;
            let (lo, hi) = ([f64::from(x0), f64::from(z0)], [f64::from(x0 + edge), f64::from(z0 + edge)]);
            let p = f.patch(lo, hi, depth);
            for (k, h) in heights.iter_mut().enumerate() {
                let (x, z) = (x0 + at(k % GROUND_SIDE), z0 + at(k / GROUND_SIDE));
                *h = p.height_and_slope(f64::from(x), f64::from(z)).0;
            }
        }
    }
    let lo = heights.iter().copied().fold(f32::INFINITY, f32::min);
    let hi = heights.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    NodeGround { heights, lo, hi }
}

#[cfg(test)]
mod tests {
    use canopy_worlds::world::Terrain;

    use super::*;
    use crate::camera::Camera;
    use crate::lod::LodConfig;

    const CELL: f32 = 64.0;

    fn flat() -> Ground {
        Ground::Grid(Arc::new(Terrain::flat([-1.0e5, -1.0e5], 2.0e5)))
    }

    fn tiles() -> Vec<Option<TileState>> {
        let t = TileVol {
            volume: 7,
            period: 20.0,
            top: 20.0,
            voxel: 0.3,
            density: 0.04,
            reference: Some(17.0),
            profile: 0,
        };
        vec![Some(TileState::Ready(t)), Some(TileState::Pending)]
    }

    fn node(level: u8, x: i32, z: i32, cover: u64) -> Arc<NodeSummary> {
        let side = f32::from(1u16 << level) * CELL;
        let count = (0.04 * side * side * cover.count_ones() as f32 / 64.0) as u32;
        Arc::new(NodeSummary {
            key: NodeKey { level, x, z },
            error: side / 8.0,
            species: vec![SpeciesCover { species: 0, count: count.max(1), height_dm: 170, spread_dm: 20, cover }],
        })
    }

    fn far(nodes: Vec<Arc<NodeSummary>>, record_cells: Vec<CellCoord>, generation: u64) -> SceneFar {
        SceneFar { nodes, cell_size: CELL, record_cells, generation }
    }

    /// From 1,500 m above the origin looking along +z and down 20°.
    fn view(progress: f32) -> View {
        let cam = Camera { position: Vec3::new(0.0, 1500.0, 0.0), yaw: 0.0, pitch: -0.35, fov_y: 60.0 };
        let lod = LodConfig { fade_seconds: 1.0, ..LodConfig::default() };
        View::new(&cam, (320, 200), 0.25, &lod, progress, progress >= 1.0)
    }

    struct Run {
        plan: ForestPlan,
        stats: FrameStats,
        layer: f32,
    }

    impl Run {
        fn new() -> Run {
            Run { plan: ForestPlan::default(), stats: FrameStats::default(), layer: 1.0 }
        }

        fn frame(&mut self, far: &SceneFar, progress: f32) {
            let (ground, tiles) = (flat(), tiles());
            let (view, layer) = (view(progress), self.layer);
            let input = ForestInputs { far, ground: &ground, tiles: &tiles, view, cull_px: 1.0, layer };
            self.stats = FrameStats::default();
            self.plan.plan(&input, &mut self.stats);
        }

        /// (node x, z, level, drawn sub-squares, mask) of every patch, sorted.
        fn drawn(&self) -> Vec<(i32, i32, u32, u64, f32)> {
            let mut v: Vec<_> = self
                .plan
                .patches
                .iter()
                .map(|p| {
                    let level = (p.rect[2] / CELL).log2() as u32;
                    let (x, z) = ((p.rect[0] / p.rect[2]) as i32, (p.rect[1] / p.rect[2]) as i32);
                    (x, z, level, u64::from(p.cover[0]) | u64::from(p.cover[1]) << 32, p.mask)
                })
                .collect();
            v.sort_by(|a, b| a.partial_cmp(b).unwrap());
            v
        }
    }

    const ALL: u64 = u64::MAX;

    #[test]
    fn masks_and_dilation() {
        assert_eq!(quadrant_mask(0), 0x0f0f_0f0f);
        assert_eq!(quadrant_mask(3), 0xf0f0_f0f0_0000_0000);
        assert_eq!((0..4).map(quadrant_mask).fold(0, |a, m| a | m), ALL);
        // A lone sub-square grows into its 3 × 3 block; at an edge it does not wrap around.
        assert_eq!(dilate(1 << 9), 0x07_0707);
        assert_eq!(dilate(1 << 7), 0xc0c0);
        assert_eq!(dilate(1 << 8), 0x03_0303);
    }

    #[test]
    fn a_node_whose_four_children_are_held_is_not_drawn_and_partial_refinement_draws_the_rest() {
        // A level-5 node 2 km ahead, its four children, then only two of them.
        let parent = node(5, 0, 1, ALL);
        let kids: Vec<_> = parent.key.children().unwrap().iter().map(|k| node(k.level, k.x, k.z, ALL)).collect();
        let mut r = Run::new();
        let mut all = vec![parent.clone()];
        all.extend(kids.iter().cloned());
        r.frame(&far(all, vec![], 1), 1.0);
        let drawn = r.drawn();
        assert_eq!(drawn.len(), 4, "{drawn:?}");
        assert!(drawn.iter().all(|d| d.2 == 4 && d.3 == ALL && d.4 == 1.0), "{drawn:?}");
        assert_eq!((r.stats.summary_nodes, r.stats.forest_nodes, r.stats.forest_patches), (5, 4, 4));
        assert_eq!(r.stats.forest_squares, 4 * 64);
        r.frame(&far(vec![parent.clone(), kids[0].clone(), kids[3].clone()], vec![], 2), 1.0);
        let drawn = r.drawn();
        let parents: Vec<_> = drawn.iter().filter(|d| d.2 == 5).collect();
        assert_eq!(parents.len(), 1);
        assert_eq!(parents[0].3, quadrant_mask(1) | quadrant_mask(2), "the parent draws the quadrants of absent kids");
        assert_eq!(drawn.iter().filter(|d| d.2 == 4).count(), 2);
        assert_eq!(r.stats.forest_waiting, 0);
    }

    #[test]
    fn neighbouring_nodes_meet_at_the_mean_of_their_densities() {
        // Two level-4 nodes side by side ahead of the camera, the second a third as dense as the first.
        let mut a = node(4, 0, 1, ALL);
        Arc::make_mut(&mut a).species[0].count /= 8;
        let mut b = node(4, 1, 1, ALL);
        Arc::make_mut(&mut b).species[0].count /= 24;
        let mut r = Run::new();
        r.frame(&far(vec![a.clone(), b.clone()], vec![], 1), 1.0);
        let patch = |n: &NodeSummary| *r.plan.patches.iter().find(|p| p.rect[0] == node_rect(n.key, CELL)[0]).unwrap();
        let (pa, pb) = (patch(&a), patch(&b));
        assert!(pb.keep < 0.5 * pa.keep && pa.keep < 1.0, "{} {}", pa.keep, pb.keep);
        // At the shared edge both ramp to the mean of the two (the same tile at the same scale).
        let mean = 0.5 * (pa.keep + pb.keep);
        assert!((pa.edges_x[1] - mean).abs() < 1e-6 && (pb.edges_x[0] - mean).abs() < 1e-6, "{pa:?} {pb:?}");
        // Where no node is held beyond an edge, nothing to ramp to.
        assert_eq!((pa.edges_x[0], pa.edges_z), (pa.keep, [pa.keep; 2]));
        assert_eq!((pb.edges_x[1], pb.edges_z), (pb.keep, [pb.keep; 2]));
        // Records beyond an edge: the same.
        let first = b.key.first_cell();
        let records: Vec<CellCoord> = (0..16).map(|j| CellCoord::new(first.x, first.z + j)).collect();
        let mut r = Run::new();
        r.frame(&far(vec![a.clone(), b.clone()], records, 1), 1.0);
        let pa = *r.plan.patches.iter().find(|p| p.rect[0] == 0.0).unwrap();
        assert_eq!(pa.edges_x[1], pa.keep);
    }

    #[test]
    fn a_species_too_sparse_to_march_is_drawn_only_as_the_layer() {
        // A level-5 node 2 km ahead holding 3 trees over its 4 km²: far less than a class of the tile's.
        let mut n = node(5, 0, 1, ALL);
        Arc::make_mut(&mut n).species[0].count = 3;
        let mut r = Run::new();
        r.frame(&far(vec![n.clone()], vec![], 1), 1.0);
        let p = &r.plan.patches;
        assert_eq!(p.len(), 1, "beyond the layer's distance it is drawn");
        assert!(p[0].keep < MIN_KEEP && p[0].keep > 0.0, "{}", p[0].keep);
        assert!(p[0].layer_from < 1500.0, "{} m: every ray takes the layer", p[0].layer_from);
        // Marching everywhere, it would keep no class: nothing is drawn.
        let mut r = Run { layer: 0.0, ..Run::new() };
        r.frame(&far(vec![n], vec![], 1), 1.0);
        assert!(r.plan.patches.is_empty());
    }

    #[test]
    fn record_cells_hide_their_coverage() {
        // A level-3 node (8 × 8 cells: one cell per sub-square) with records in its first row of cells.
        let n = node(3, 0, 4, ALL);
        let first = n.key.first_cell();
        let cells: Vec<CellCoord> = (0..8).map(|i| CellCoord::new(first.x + i, first.z)).collect();
        let mut r = Run::new();
        r.frame(&far(vec![n.clone()], cells, 1), 1.0);
        assert_eq!(r.drawn().len(), 1);
        assert_eq!(r.drawn()[0].3, ALL & !0xff, "the first row is left to the records");
        // Records over the whole node: nothing.
        let mut cells: Vec<CellCoord> =
            (0..8).flat_map(|j| (0..8).map(move |i| CellCoord::new(first.x + i, first.z + j))).collect();
        cells.sort();
        r.frame(&far(vec![n], cells, 2), 1.0);
        assert!(r.drawn().is_empty());
        // A partly covered species marches one sub-square beyond its cover (the stand thins into it).
        let mut r = Run::new();
        r.frame(&far(vec![node(3, 0, 4, 1 << 9)], vec![], 1), 1.0);
        assert_eq!(r.drawn()[0].3, 0x07_0707);
        assert_eq!(r.plan.patches[0].field, [1 << 9, 0]);
    }

    #[test]
    fn culling_drops_nodes_behind_beside_and_below_a_pixel() {
        let nodes = vec![
            node(5, 0, 1, ALL),    // ahead
            node(5, 0, -3, ALL),   // behind
            node(5, 40, 1, ALL),   // far to the side
            node(0, 0, 3000, ALL), // 192 km ahead: a 64 m node is well under a pixel
        ];
        let mut r = Run::new();
        r.frame(&far(nodes, vec![], 1), 1.0);
        let drawn = r.drawn();
        assert_eq!(drawn.iter().map(|d| (d.0, d.1, d.2)).collect::<Vec<_>>(), vec![(0, 1, 5)]);
        assert_eq!(r.stats.summary_nodes, 4);
        // Front to back; both name the tile's finest resolution, and the march takes a coarser one where a voxel
        // of the finest would be under VOXEL_PX pixels: level ⌊log₂(t · mip_scale)⌋.
        let near = node(4, 0, 2, ALL);
        let mid = node(4, 0, 12, ALL);
        r.frame(&far(vec![near, mid], vec![], 2), 1.0);
        let p = &r.plan.patches;
        assert_eq!(p.len(), 2);
        assert!(p[0].rect[1] < p[1].rect[1], "the nearer first");
        assert_eq!((p[0].volume, p[1].volume), (7, 7));
        let v = view(1.0);
        let footprint = 2.0 * v.tan_half / v.height_px;
        for q in p {
            // The tile's finest voxel is 0.3 m at scale 1: it spans VOXEL_PX pixels at 1 / mip_scale metres.
            let t = 1.0 / q.mip_scale;
            assert!((0.3 * q.scale / (t * footprint) - VOXEL_PX).abs() < 1e-3, "{t} m");
        }
        // Ground: 81 heights per drawn node (flat ground at 0).
        assert_eq!(r.plan.ground.len(), 2 * GROUND_POINTS);
        assert!(r.plan.ground.iter().all(|&h| h == 0.0));
        assert_eq!(p[0].span, [0.0, 20.0]);
    }

    #[test]
    fn refinement_cross_fades_with_complementary_masks_and_released_nodes_fade_out() {
        let parent = node(5, 0, 1, ALL);
        let kids: Vec<_> = parent.key.children().unwrap().iter().map(|k| node(k.level, k.x, k.z, ALL)).collect();
        let mut r = Run::new();
        r.frame(&far(vec![parent.clone()], vec![], 1), 1.0);
        assert_eq!(r.drawn(), vec![(0, 1, 5, ALL, 1.0)]);
        // The children arrive: a quarter of the fade later, they fade in and the parent out, complementary.
        let mut all = vec![parent.clone()];
        all.extend(kids.iter().cloned());
        r.frame(&far(all.clone(), vec![], 2), 0.25);
        let drawn = r.drawn();
        assert_eq!(drawn.len(), 5, "{drawn:?}");
        assert_eq!(drawn.iter().filter(|d| d.2 == 5).map(|d| (d.3, d.4)).collect::<Vec<_>>(), vec![(ALL, -0.25)]);
        assert!(drawn.iter().filter(|d| d.2 == 4).all(|d| d.3 == ALL && d.4 == 0.25));
        // Three quarters later the fade is over: only the children.
        for _ in 0..3 {
            r.frame(&far(all.clone(), vec![], 2), 0.25);
        }
        assert!(r.drawn().iter().all(|d| d.2 == 4 && d.4 == 1.0) && r.drawn().len() == 4);
        // The children are released: the parent fades back in while they fade out (kept until then).
        r.frame(&far(vec![parent.clone()], vec![], 3), 0.5);
        let drawn = r.drawn();
        assert_eq!(drawn.len(), 5);
        assert!(drawn.iter().filter(|d| d.2 == 4).all(|d| d.4 == -0.5));
        assert_eq!(r.plan.nodes(), 5);
        r.frame(&far(vec![parent.clone()], vec![], 3), 0.5);
        assert_eq!(r.drawn(), vec![(0, 1, 5, ALL, 1.0)]);
        assert_eq!(r.plan.nodes(), 1, "faded-out nodes are forgotten");
        // A species whose tile is pending waits (and is not drawn).
        let mut pending = (*node(5, 0, 1, ALL)).clone();
        pending.species[0].species = 1;
        let mut w = Run::new();
        w.frame(&far(vec![Arc::new(pending)], vec![], 1), 1.0);
        assert!(w.drawn().is_empty());
        assert_eq!(w.stats.forest_waiting, 1);
        assert_eq!(w.plan.species, vec![1]);
    }

    #[test]
    fn the_mask_fade_waits_for_a_running_fade() {
        let mut f = MaskFade::default();
        f.step(0b11, 0.5);
        assert_eq!(f.parts().collect::<Vec<_>>(), vec![(0b11, 0.5)]);
        f.step(0b01, 0.25);
        assert_eq!((f.shown, f.fade), (0b11, 0.75), "the change waits");
        f.step(0b01, 0.25);
        assert_eq!(f.parts().collect::<Vec<_>>(), vec![(0b01, 1.0), (0b10, -0.25)]);
        f.step(0, 1.0);
        assert!(f.idle());
    }

    #[test]
    fn fractal_ground_grids_follow_the_ground() {
        let world = canopy_worlds::world::World::embedded("highlands").unwrap();
        let ground = Ground::of_world(&world);
        let key = NodeKey { level: 3, x: 4, z: -60 };
        let rect = node_rect(key, world.cell_size);
        let g = ground_grid(&ground, rect);
        for k in [0, 40, 80] {
            let (x, z) = (rect[0] + (k % 9) as f32 * rect[2] / 8.0, rect[1] + (k / 9) as f32 * rect[2] / 8.0);
            let exact = ground.height(x, z);
            assert!((g.heights[k] - exact).abs() < 20.0, "{} against {exact}", g.heights[k]);
        }
        assert!(g.lo <= g.hi);
    }
}
