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
//! Memory and work are bounded: at most [`MAX_SESSION_NODES`] nodes held, queued or waited for, and a walk visits
//! at most [`MAX_VISITS`] nodes.

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
                Some(&e) => e,
                None => match state(k) {
                    NodeState::Ready(error) => {
                        if self.held.len() + self.queue.len() < MAX_SESSION_NODES {
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
                    NodeState::Unavailable => continue,
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
        while self.held.len() < MAX_SESSION_NODES {
            let Some((p, k)) = self.queue.pop() else { break };
            if self.held.contains_key(&k) {
                continue;
            }
            let parent_held = k.level >= root_level || k.parent().is_some_and(|p| self.held.contains_key(&p));
            if !parent_held {
                deferred.push((p, k));
                continue;
            }
            match take(k) {
                Take::Node(error) => {
                    self.held.insert(k, error);
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
