//! `canopy walk`'s editing keys: the crosshair's ground point (the camera's forward ray onto the ground's height
//! function), the instance `F` fells near it, the species `P` plants and `[`/`]` select, and the network side:
//! requests sent through [`Connection::edit`] and the server's answers turned into the window's status line.
//!
//! The pure parts ([`ray_ground`], [`nearest`], [`cycle`]) are unit-tested here; the window and the network thread
//! in `walk.rs` only call them.

use std::collections::HashMap;
use std::time::{Duration, Instant};

use canopy_client::state::Event;
use canopy_protocol::InstanceId;
use canopy_protocol::edit::{EditOp, EditOutcome, EditResult};
use canopy_render::camera::Camera;
use canopy_render::{Scene, SceneInstance};
use glam::Vec3;
use tokio::sync::mpsc::{UnboundedReceiver, UnboundedSender};
use winit::keyboard::KeyCode;

use crate::cli::edit::show_id;

/// How far the crosshair reaches along the view, metres.
pub(super) const REACH: f32 = 2000.0;
/// How far (horizontally) from the crosshair's ground point `F` looks for an instance to fell, metres.
pub(super) const FELL_RADIUS: f32 = 4.0;
/// How long an instance this window asked to fell is passed over by the next `F` (the answer and the delta
/// usually arrive well within it), so a second press fells the next tree rather than asking twice for one.
const FELLING: Duration = Duration::from_secs(3);

/// Where the ray from `origin` along `dir` first meets the ground `height(x, z)` within `max_dist` metres: the
/// ray is marched in steps that grow with the distance (a quarter metre near the camera, at most 4 m), and the
/// first step that ends below the ground is bisected. The point returned lies on the ground (its y is the height
/// at its x, z). `None` when the ray stays above the ground (looking up or at the horizon) or is not finite; a
/// camera below the ground hits the point under it.
pub(super) fn ray_ground(origin: Vec3, dir: Vec3, height: &dyn Fn(f32, f32) -> f32, max_dist: f32) -> Option<Vec3> {
    let dir = dir.normalize_or_zero();
    if dir == Vec3::ZERO || !origin.is_finite() || max_dist.is_nan() || max_dist <= 0.0 {
        return None;
    }
    let on_ground = |p: Vec3| Vec3::new(p.x, height(p.x, p.z), p.z);
    let above = |t: f32| {
        let p = origin + dir * t;
        p.y - height(p.x, p.z)
    };
    let first = above(0.0);
    if !first.is_finite() {
        return None;
    }
    if first <= 0.0 {
        return Some(on_ground(origin));
    }
    let mut t0 = 0.0f32;
    while t0 < max_dist {
        let t1 = (t0 + (0.01 * t0).clamp(0.25, 4.0)).min(max_dist);
        if above(t1) <= 0.0 {
            // Above at t0, at or below at t1: halve the bracket to well under a millimetre.
            let (mut lo, mut hi) = (t0, t1);
            for _ in 0..24 {
                let mid = 0.5 * (lo + hi);
                if above(mid) > 0.0 {
                    lo = mid;
                } else {
                    hi = mid;
                }
            }
            return Some(on_ground(origin + dir * hi));
        }
        t0 = t1;
    }
    None
}

/// The crosshair's ground point: the screen centre, i.e. the camera's forward ray, onto the scene's ground.
pub(super) fn aim(camera: &Camera, scene: &Scene) -> Option<Vec3> {
    let ground = &scene.ground;
    ray_ground(camera.position, camera.forward(), &|x, z| ground.height(x, z), REACH)
}

/// The instance standing nearest to world `(x, z)` — horizontal distance, ties to the smaller id — among those
/// within `radius` metres and not passed over by `skip`; `None` when there is none.
pub(super) fn nearest<'a>(
    instances: impl IntoIterator<Item = &'a SceneInstance>,
    at: [f32; 2],
    radius: f32,
    skip: impl Fn(InstanceId) -> bool,
) -> Option<&'a SceneInstance> {
    let mut best: Option<(f32, &SceneInstance)> = None;
    for i in instances {
        let (dx, dz) = (i.position[0] - at[0], i.position[2] - at[1]);
        let d2 = dx * dx + dz * dz;
        if d2 > radius * radius || skip(i.id) {
            continue;
        }
        if best.is_none_or(|(b, bi)| d2 < b || (d2 == b && i.id < bi.id)) {
            best = Some((d2, i));
        }
    }
    best.map(|(_, i)| i)
}

/// The species after (`forward`) or before `selected` in a table of `n`, wrapping around.
pub(super) fn cycle(selected: usize, n: usize, forward: bool) -> usize {
    match n {
        0 => 0,
        _ if forward => (selected % n + 1) % n,
        _ => (selected % n + n - 1) % n,
    }
}

/// A species' name in the scene (its program's name once held, else its number).
fn species_name(scene: Option<&Scene>, id: usize) -> String {
    match scene.and_then(|s| s.species.get(id)).and_then(|g| g.as_ref()) {
        Some(g) => g.name.clone(),
        None => format!("species {id}"),
    }
}

/// An edit the window asks the network thread to send, with how to name it in the answer's line.
#[derive(Debug)]
pub(super) struct EditRequest {
    /// The edit.
    pub op: EditOp,
    /// What it is, for people: `plant conifer at (12.5, -40.2)`.
    pub what: String,
}

/// The window's side: the selected species, the instances it asked to fell, and the channel to the network
/// thread.
#[derive(Debug)]
pub(super) struct EditKeys {
    tx: UnboundedSender<EditRequest>,
    species: usize,
    felling: HashMap<InstanceId, Instant>,
}

impl EditKeys {
    /// Keys that send their edits on `tx`.
    pub(super) fn new(tx: UnboundedSender<EditRequest>) -> EditKeys {
        EditKeys { tx, species: 0, felling: HashMap::new() }
    }

    /// Whether `code` is one of the editing keys.
    pub(super) fn handles(code: KeyCode) -> bool {
        matches!(code, KeyCode::KeyP | KeyCode::KeyF | KeyCode::BracketLeft | KeyCode::BracketRight)
    }

    /// Act on an editing key with the camera and scene as they are; what to show and log.
    pub(super) fn key(&mut self, code: KeyCode, camera: &Camera, scene: Option<&Scene>) -> Option<String> {
        let n = scene.map_or(0, |s| s.species.len());
        match code {
            KeyCode::BracketLeft | KeyCode::BracketRight => {
                if n == 0 {
                    return Some("no species yet".into());
                }
                self.species = cycle(self.species, n, code == KeyCode::BracketRight);
                Some(format!("planting {}", species_name(scene, self.species)))
            }
            KeyCode::KeyP => {
                let Some(scene) = scene.filter(|_| n > 0) else { return Some("no world yet".into()) };
                let Some(p) = aim(camera, scene) else {
                    return Some("plant: no ground under the crosshair".into());
                };
                let species = self.species.min(n - 1);
                let what = format!("plant {} at ({:.1}, {:.1})", species_name(Some(scene), species), p.x, p.z);
                let op = EditOp::Plant { species: species as u8, x: p.x, z: p.z, params: Vec::new() };
                Some(self.send(op, what))
            }
            KeyCode::KeyF => {
                let Some(scene) = scene else { return Some("no world yet".into()) };
                let Some(p) = aim(camera, scene) else {
                    return Some("fell: no ground under the crosshair".into());
                };
                let now = Instant::now();
                self.felling.retain(|_, at| now.duration_since(*at) < FELLING);
                let felling = &self.felling;
                let Some(tree) = nearest(&scene.instances, [p.x, p.z], FELL_RADIUS, |id| felling.contains_key(&id))
                else {
                    return Some(format!("fell: nothing within {FELL_RADIUS} m of ({:.1}, {:.1})", p.x, p.z));
                };
                self.felling.insert(tree.id, now);
                let what =
                    format!("fell {} {}", species_name(Some(scene), usize::from(tree.species)), show_id(tree.id));
                Some(self.send(EditOp::Fell { id: tree.id }, what))
            }
            _ => None,
        }
    }

    fn send(&self, op: EditOp, what: String) -> String {
        let line = format!("{what}: sent");
        match self.tx.send(EditRequest { op, what }) {
            Ok(()) => line,
            Err(_) => "edit not sent: the network thread has stopped".into(),
        }
    }

    /// The status line's part: the species `P` plants and the crosshair's ground point.
    pub(super) fn hud(&self, camera: &Camera, scene: Option<&Scene>) -> String {
        let n = scene.map_or(0, |s| s.species.len());
        let name = if n == 0 { "…".into() } else { species_name(scene, self.species.min(n - 1)) };
        match scene.and_then(|s| aim(camera, s)) {
            Some(p) => format!("P plants {name} at ({:.0}, {:.0})", p.x, p.z),
            None => format!("P plants {name} (aim at the ground)"),
        }
    }
}

/// The network thread's side: edits sent and not answered yet, by request number.
#[derive(Debug)]
pub(super) struct EditLink {
    rx: UnboundedReceiver<EditRequest>,
    pending: HashMap<u32, String>,
}

impl EditLink {
    /// Requests from `rx`.
    pub(super) fn new(rx: UnboundedReceiver<EditRequest>) -> EditLink {
        EditLink { rx, pending: HashMap::new() }
    }

    /// The window's next request, if one waits.
    pub(super) fn try_next(&mut self) -> Option<EditRequest> {
        self.rx.try_recv().ok()
    }

    /// Request `request` was sent for `what`: remembered for its answer.
    pub(super) fn sent(&mut self, request: u32, what: String) {
        self.pending.insert(request, what);
    }

    /// The line for an event that answers one of this window's edits.
    pub(super) fn answer(&mut self, ev: &Event) -> Option<String> {
        let Event::EditResult(EditResult { request, outcome }) = ev else { return None };
        let what = self.pending.remove(request).unwrap_or_else(|| format!("edit {request}"));
        Some(describe(&what, outcome))
    }
}

/// How an edit ended, for the status line and the log.
pub(super) fn describe(what: &str, outcome: &EditOutcome) -> String {
    match outcome {
        EditOutcome::Ok { id, version } => format!("{what}: ok, instance {} (cell version {version})", show_id(*id)),
        EditOutcome::Denied(why) => format!("{what}: denied: {why}"),
        EditOutcome::Invalid(why) => format!("{what}: invalid: {why}"),
        EditOutcome::Conflict => format!("{what}: conflict (the cell changed under the edit; try again)"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use canopy_protocol::CellCoord;

    fn close(a: Vec3, b: Vec3) -> bool {
        (a - b).length() < 1e-3
    }

    #[test]
    fn a_known_camera_hits_flat_ground_where_it_looks() {
        let flat = |_: f32, _: f32| 2.0;
        let cam = Camera::looking_at(Vec3::new(5.0, 22.0, -30.0), Vec3::new(5.0, 2.0, 10.0), 60.0);
        let hit = ray_ground(cam.position, cam.forward(), &flat, REACH).expect("looking down hits the ground");
        assert!(close(hit, Vec3::new(5.0, 2.0, 10.0)), "{hit}");
        // Straight down from 10 m: the point underneath.
        let hit = ray_ground(Vec3::new(3.0, 12.0, 4.0), Vec3::NEG_Y, &flat, REACH).unwrap();
        assert!(close(hit, Vec3::new(3.0, 2.0, 4.0)), "{hit}");
        // Level or upward never meets flat ground; nor does a ray shorter than the distance to it.
        assert_eq!(ray_ground(cam.position, Vec3::Z, &flat, REACH), None);
        assert_eq!(ray_ground(cam.position, Vec3::new(0.0, 1.0, 1.0), &flat, REACH), None);
        assert_eq!(ray_ground(cam.position, cam.forward(), &flat, 40.0), None);
        assert_eq!(ray_ground(cam.position, Vec3::ZERO, &flat, REACH), None);
    }

    #[test]
    fn a_ray_meets_sloped_ground_at_the_intersection_not_under_the_camera() {
        // A slope rising towards +x: y = x / 2.
        let slope = |x: f32, _: f32| 0.5 * x;
        // From (0, 10, 0) along (1, −1, 0): 10 − t = t / 2 at t = 20/3.
        let hit = ray_ground(Vec3::new(0.0, 10.0, 0.0), Vec3::new(1.0, -1.0, 0.0), &slope, REACH).unwrap();
        assert!(close(hit, Vec3::new(20.0 / 3.0, 10.0 / 3.0, 0.0)), "{hit}");
        // Looking level into the rising slope hits it where it reaches the eye: x = 20.
        let hit = ray_ground(Vec3::new(0.0, 10.0, 7.0), Vec3::X, &slope, REACH).unwrap();
        assert!(close(hit, Vec3::new(20.0, 10.0, 7.0)), "{hit}");
        // A camera aimed at a point of the slope far away hits that point (the march does not overshoot).
        let target = Vec3::new(300.0, 150.0, 400.0);
        let cam = Camera::looking_at(Vec3::new(-100.0, 180.0, -50.0), target, 60.0);
        let hit = ray_ground(cam.position, cam.forward(), &slope, REACH).unwrap();
        assert!((hit - target).length() < 0.05, "{hit}");
        // Under the ground: the point above the camera.
        let hit = ray_ground(Vec3::new(10.0, 1.0, 0.0), Vec3::Z, &slope, REACH).unwrap();
        assert!(close(hit, Vec3::new(10.0, 5.0, 0.0)), "{hit}");
    }

    #[test]
    fn a_hill_in_front_is_hit_before_the_ground_behind_it() {
        // Flat at 0 with a 10 m wall-like hill between x = 50 and x = 52.
        let hill = |x: f32, _: f32| if (50.0..52.0).contains(&x) { 10.0 } else { 0.0 };
        let hit = ray_ground(Vec3::new(0.0, 6.0, 0.0), Vec3::new(100.0, -6.0, 0.0), &hill, REACH).unwrap();
        assert!((hit.x - 50.0).abs() < 0.01 && hit.y == 10.0, "{hit}");
    }

    fn tree(index: u16, x: f32, z: f32) -> SceneInstance {
        SceneInstance {
            id: InstanceId::new(CellCoord::new(0, 0), index).unwrap(),
            species: 0,
            position: [x, 100.0, z],
            seed: u64::from(index),
            params: Vec::new(),
        }
    }

    #[test]
    fn the_pick_is_the_nearest_instance_within_the_radius() {
        let trees = [tree(0, 3.0, 0.0), tree(1, 0.0, -1.5), tree(2, 10.0, 10.0), tree(3, 1.0, 1.0)];
        let none = |_: InstanceId| false;
        assert_eq!(nearest(&trees, [0.0, 0.0], 4.0, none).map(|t| t.id.index()), Some(3));
        assert_eq!(nearest(&trees, [0.0, -1.0], 4.0, none).map(|t| t.id.index()), Some(1));
        // Height plays no part: only the horizontal distance.
        assert_eq!(nearest(&trees, [9.0, 9.0], 4.0, none).map(|t| t.id.index()), Some(2));
        // Nothing beyond the radius.
        assert!(nearest(&trees, [0.0, 0.0], 1.4, none).is_none());
        assert!(nearest(&trees, [-20.0, 5.0], FELL_RADIUS, none).is_none());
        assert!(nearest(&[], [0.0, 0.0], FELL_RADIUS, none).is_none());
        // One already asked to fell is passed over for the next nearest.
        let asked = |id: InstanceId| id.index() == 3;
        assert_eq!(nearest(&trees, [0.0, 0.0], 4.0, asked).map(|t| t.id.index()), Some(1));
        // Ties go to the smaller id whatever the order.
        let tied = [tree(7, 1.0, 0.0), tree(5, -1.0, 0.0)];
        assert_eq!(nearest(&tied, [0.0, 0.0], 4.0, none).map(|t| t.id.index()), Some(5));
    }

    #[test]
    fn species_selection_wraps_both_ways() {
        assert_eq!(cycle(0, 3, true), 1);
        assert_eq!(cycle(2, 3, true), 0);
        assert_eq!(cycle(0, 3, false), 2);
        assert_eq!(cycle(1, 3, false), 0);
        assert_eq!(cycle(5, 3, true), 0, "a selection past a shorter table wraps");
        assert_eq!(cycle(0, 0, true), 0);
    }

    #[test]
    fn answers_name_the_edit_and_the_outcome() {
        let (tx, rx) = tokio::sync::mpsc::unbounded_channel();
        let mut link = EditLink::new(rx);
        link.pending.insert(4, "plant conifer at (1.0, 2.0)".into());
        drop(tx);
        let id = InstanceId::new(CellCoord::new(-1, 2), 9).unwrap();
        let ok = Event::EditResult(EditResult { request: 4, outcome: EditOutcome::Ok { id, version: 3 } });
        let line = link.answer(&ok).unwrap();
        assert!(line.starts_with("plant conifer at (1.0, 2.0): ok, instance -1:2:9"), "{line}");
        assert!(line.ends_with("(cell version 3)"), "{line}");
        let denied = Event::EditResult(EditResult { request: 5, outcome: EditOutcome::Denied("read-only".into()) });
        assert_eq!(link.answer(&denied).unwrap(), "edit 5: denied: read-only");
        assert_eq!(link.answer(&Event::Dropped), None);
    }
}
