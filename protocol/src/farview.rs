//! Which far-view summary nodes a viewer holds, wants and must forget: the selection both sides run (issue 30).
//! A server session runs it over the nodes its cache computes and sends them; a client that computes the nodes
//! itself runs it over its own. Sans-IO: what a node's state is comes from the caller.
//!
//! The rule is [`Refine`]: from the roots within range, a node's children are wanted while its geometric error
//! projects larger than the threshold. A walk visits that tree over the nodes the source has (a node not computed
//! yet is noted as waited for and its subtree waits: coarse first), queues the nodes the viewer does not hold by
//! projected error (the most visible first; a node out of the view cone counts half), and hands a node out only
//! after its parent. Held nodes are released under the looser keep rule (hysteresis), coarse before fine.
//!
//! A held node the source changed (a cell's edits corrected it) is marked stale ([`Selection::stale`]) and handed
//! out again as the source has it, waited for like a new one while the source computes it anew.
//!
//! Memory and work are bounded: at most [`MAX_SESSION_NODES`] nodes held, queued or waited for (stale nodes queued
//! again besides: they are held ones), and a walk visits at most [`MAX_VISITS`] nodes.

use std::collections::{BTreeMap, BTreeSet};
use std::time::Duration;

use crate::aoi::{Aoi, Grid};
use crate::summary::{COVER_SIDE, FarView, NodeKey, Refine};

/// Most summary nodes a viewer holds or has queued.
pub const MAX_SESSION_NODES: usize = 16_384;
/// Most nodes one walk visits.
pub const MAX_VISITS: usize = 65_536;
/// A whole walk ([`Selection::rebuild`]) happens at most this often for one viewer (viewpoints come up to 50 a
/// second).
pub const REBUILD_INTERVAL: Duration = Duration::from_millis(200);
/// The view cone's angle a viewer is taken to have, degrees (what orders the queue, not what is selected).
pub const DEFAULT_FOV_DEG: f32 = 120.0;
/// A node whose centre lies outside the view cone is queued as if its projected error were this much smaller.
pub const OUT_OF_VIEW_FACTOR: f32 = 0.5;

/// Where the viewer stands, as the far view needs it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Eye {
    /// Position on the ground plane (x, z).
    pub position: [f32; 2],
    /// Unit heading on the ground plane.
    pub heading: [f32; 2],
    /// Cosine of half the view cone's angle.
    pub cos_half_fov: f32,
    /// Radius the records cover.
    pub record_radius: f32,
}

impl Eye {
    /// The eye of a viewer whose area of interest is `aoi`, heading along `heading`, with a view cone of `fov_deg`
    /// degrees: at the area's centre, its records covering the area's radius.
    pub fn new(aoi: &Aoi, heading: [f32; 2], fov_deg: f32) -> Eye {
        Eye {
            position: aoi.position,
            heading,
            cos_half_fov: (fov_deg.to_radians() * 0.5).cos(),
            record_radius: aoi.radius,
        }
    }

    /// The rule for `view` from this eye over `grid`, whose roots are at `root_level`: what a server session and
    /// a client computing its own nodes both walk, so they select the same nodes.
    pub fn refine(&self, view: FarView, grid: &Grid, root_level: u8) -> Refine {
        Refine {
            view,
            eye: self.position,
            origin: grid.origin,
            cell_size: grid.cell_size,
            root_level,
            record_radius: self.record_radius,
        }
    }
}

/// What the source of nodes says about one.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum NodeState {
    /// Computed, with its geometric error.
    Ready(f32),
    /// Not computed yet (asked for: the walk goes on from it once it is).
    Pending,
    /// Not available at all.
    Unavailable,
}

/// One viewer's selection (see the module docs).
#[derive(Debug, Default)]
pub struct Selection {
    /// Nodes the viewer holds, with their geometric errors.
    held: BTreeMap<NodeKey, f32>,
    /// Nodes to hand out, least important first (the next at the end).
    queue: Vec<(f32, NodeKey)>,
    /// Nodes to tell the viewer to forget.
    releases: Vec<NodeKey>,
    /// Nodes the last walks found pending (wanted, not computed yet).
    waiting: Vec<NodeKey>,
    /// Held nodes the source changed since they were handed out ([`Selection::stale`]): handed out again.
    stale: BTreeSet<NodeKey>,
}

impl Selection {
    /// Nodes the viewer holds.
    pub fn held(&self) -> impl Iterator<Item = NodeKey> + '_ {
        self.held.keys().copied()
    }

    /// Nodes queued to hand out.
    pub fn queued(&self) -> usize {
        self.queue.len()
    }

    /// Whether there is something to hand out or release.
    pub fn has_work(&self) -> bool {
        !self.queue.is_empty() || !self.releases.is_empty()
    }

    /// Whether releases are due.
    pub fn has_releases(&self) -> bool {
        !self.releases.is_empty()
    }

    /// Whether the walks wait for nodes to be computed.
    pub fn is_waiting(&self) -> bool {
        !self.waiting.is_empty()
    }

    /// The source changed the nodes holding `cell` (its edits corrected them): each one held is handed out again,
    /// as the source has it by the next walk, whole or on ([`Selection::walk_on`] starts from them; a node the
    /// source computes anew is waited for, like a new one).
    pub fn stale(&mut self, cell: crate::CellCoord) {
        for level in 0..=crate::summary::MAX_LEVEL {
            let k = NodeKey::of_cell(cell, level);
            if self.held.contains_key(&k) && self.stale.insert(k) && self.waiting.len() < MAX_SESSION_NODES {
                self.waiting.push(k);
            }
        }
    }

    /// Every held node is handed out again by the next whole walk (the source cannot say which it changed).
    pub fn all_stale(&mut self) {
        self.stale.extend(self.held.keys().copied());
    }

    /// Held nodes waiting to be handed out again.
    pub fn stale_count(&self) -> usize {
        self.stale.len()
    }

    /// Walk the whole tree again for where the viewer stands: release what the keep rule no longer selects
    /// (coarse first; a node whose parent goes goes too), then queue what is wanted and not held.
    pub fn rebuild(&mut self, refine: &Refine, eye: &Eye, state: impl FnMut(NodeKey) -> NodeState) {
        let mut by_level: Vec<NodeKey> = self.held.keys().copied().collect();
        by_level.sort_unstable_by(|a, b| b.level.cmp(&a.level).then(a.cmp(b)));
        let mut gone = BTreeSet::new();
        for k in by_level {
            let parent_gone = k.parent().is_some_and(|p| gone.contains(&p));
            if parent_gone || !refine.selects(k, true, |p| self.held.get(&p).copied()) {
                gone.insert(k);
            }
        }
        for k in &gone {
            self.held.remove(k);
            self.stale.remove(k);
            self.releases.push(*k);
        }
        self.queue.clear();
        self.waiting.clear();
        self.walk(refine.roots(false), refine, eye, state);
    }

    /// Walk on from the nodes the last walks waited for (the work of the new nodes only).
    pub fn walk_on(&mut self, refine: &Refine, eye: &Eye, state: impl FnMut(NodeKey) -> NodeState) {
        let from = std::mem::take(&mut self.waiting);
        self.walk(from, refine, eye, state);
    }

    /// Queue what is wanted and not held from `stack` down, noting the nodes found pending, then order the queue.
    fn walk(
        &mut self,
        mut stack: Vec<NodeKey>,
        refine: &Refine,
        eye: &Eye,
        mut state: impl FnMut(NodeKey) -> NodeState,
    ) {
        let mut visits = 0;
        while let Some(k) = stack.pop() {
            visits += 1;
            if visits > MAX_VISITS {
                break;
            }
            let error = match self.held.get(&k) {
                Some(&e) if !self.stale.contains(&k) => e,
                held => match state(k) {
                    // A stale node is held already: queued again whatever the bound (stale nodes are held ones).
                    NodeState::Ready(error) => {
                        if held.is_some() || self.held.len() + self.queue.len() < MAX_SESSION_NODES {
                            self.queue.push((priority(refine, eye, k), k));
                        }
                        error
                    }
                    NodeState::Pending => {
                        if self.waiting.len() < MAX_SESSION_NODES {
                            self.waiting.push(k);
                        }
                        continue;
                    }
                    // A stale node the source no longer has stays as the viewer holds it.
                    NodeState::Unavailable => match held {
                        Some(&e) => e,
                        None => continue,
                    },
                },
            };
            if refine.refines(k, error, false) {
                stack.extend(k.children().into_iter().flatten().filter(|c| refine.in_range(*c, false)));
            }
        }
        // Least important first; ties by key, so the order is deterministic.
        self.queue.sort_unstable_by(|a, b| a.0.total_cmp(&b.0).then(b.1.cmp(&a.1)));
    }

    /// The most visible queued nodes whose parents the viewer holds (or roots of `root_level`), as `take` answers
    /// for each ([`Take`]: hand it out with its geometric error, skip it, or stop the batch). The nodes handed out
    /// are held from now on.
    pub fn next(&mut self, root_level: u8, mut take: impl FnMut(NodeKey) -> Take) {
        let mut deferred = Vec::new();
        while let Some((p, k)) = self.queue.pop() {
            let held = self.held.contains_key(&k);
            if held && !self.stale.contains(&k) {
                continue;
            }
            if !held && self.held.len() >= MAX_SESSION_NODES {
                self.queue.push((p, k));
                break;
            }
            let parent_held = k.level >= root_level || k.parent().is_some_and(|p| self.held.contains_key(&p));
            if !parent_held {
                deferred.push((p, k));
                continue;
            }
            match take(k) {
                Take::Node(error) => {
                    self.held.insert(k, error);
                    self.stale.remove(&k);
                }
                Take::Skip => {}
                Take::Stop => {
                    self.queue.push((p, k));
                    break;
                }
            }
        }
        self.queue.extend(deferred.into_iter().rev());
    }

    /// At most `max` releases, coarse first.
    pub fn releases(&mut self, max: usize) -> Vec<NodeKey> {
        let n = self.releases.len().min(max);
        self.releases.drain(..n).collect()
    }
}

/// What [`Selection::next`]'s caller does with a node.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Take {
    /// Hand it out: it has this geometric error.
    Node(f32),
    /// Not available any more: skip it.
    Skip,
    /// The batch is full: keep it queued and stop.
    Stop,
}

/// How visible a node is: its nominal error (an eighth of its edge) projected, halved out of the view cone.
fn priority(refine: &Refine, eye: &Eye, k: NodeKey) -> f32 {
    let [x0, z0, x1, z1] = refine.rect(k);
    let (dx, dz) = ((x0 + x1) * 0.5 - eye.position[0], (z0 + z1) * 0.5 - eye.position[1]);
    let len = (dx * dx + dz * dz).sqrt();
    let inside = refine.ground_distance(k) == 0.0;
    let in_view = inside || len == 0.0 || dx * eye.heading[0] + dz * eye.heading[1] >= eye.cos_half_fov * len;
    let nominal = (x1 - x0) / COVER_SIDE as f32;
    let sse = refine.screen_error(k, nominal);
    if in_view { sse } else { sse * OUT_OF_VIEW_FACTOR }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::CellCoord;
    use crate::aoi::{AoiParams, Viewpoint};

    /// Hand out everything queued; the keys handed out.
    fn hand_out(s: &mut Selection, root: u8) -> Vec<NodeKey> {
        let mut out = Vec::new();
        s.next(root, |k| {
            out.push(k);
            Take::Node(k.level as f32 * 40.0)
        });
        out
    }

    #[test]
    fn stale_nodes_are_handed_out_again_once_the_source_has_them_anew() {
        let grid =
            Grid { origin: [0.0, 0.0], cell_size: 64.0, min: CellCoord::new(-64, -64), max: CellCoord::new(63, 63) };
        let aoi = Aoi::new(&Viewpoint::at(0, [0.0, 0.0], 100.0), &AoiParams::default());
        let eye = Eye::new(&aoi, [0.0, 1.0], DEFAULT_FOV_DEG);
        let view = FarView { error_px: 8.0, height_px: 720, fov_y: 1.0, range: 3000.0, altitude: 50.0 };
        let root = 6;
        let refine = eye.refine(view, &grid, root);
        let ready = |k: NodeKey| NodeState::Ready(k.level as f32 * 40.0);
        let mut s = Selection::default();
        s.rebuild(&refine, &eye, ready);
        let first = hand_out(&mut s, root);
        assert!(first.len() > 10 && !s.has_work(), "{} nodes", first.len());

        // A cell 1 km away: the held nodes over it go again, and only they.
        let cell = grid.cell_of(1000.0, 300.0);
        let over: Vec<NodeKey> = s.held().filter(|k| k.contains(cell)).collect();
        assert!(!over.is_empty());
        s.stale(cell);
        assert_eq!(s.stale_count(), over.len());
        assert!(s.is_waiting(), "a walk on starts from them");
        // The source computes them anew: waited for, not handed out, while pending; then walked on from.
        let anew = |k: NodeKey| if k.contains(cell) { NodeState::Pending } else { ready(k) };
        s.rebuild(&refine, &eye, anew);
        assert!(hand_out(&mut s, root).is_empty() && s.is_waiting());
        s.walk_on(&refine, &eye, anew);
        assert!(hand_out(&mut s, root).is_empty() && s.is_waiting());
        s.walk_on(&refine, &eye, ready);
        let mut again = hand_out(&mut s, root);
        again.sort();
        let mut want = over.clone();
        want.sort();
        // The coarsest stale node was waited for; its held descendants are handed out with it.
        assert_eq!(again, want);
        assert_eq!(s.stale_count(), 0);
        assert_eq!(s.held().count(), first.len(), "nothing released, nothing new");
        // Nothing stale: a walk hands nothing out.
        s.rebuild(&refine, &eye, ready);
        assert!(hand_out(&mut s, root).is_empty());
        // All stale: everything again.
        s.all_stale();
        s.rebuild(&refine, &eye, ready);
        assert_eq!(hand_out(&mut s, root).len(), first.len());
    }
}
