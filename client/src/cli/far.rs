//! The far view of `canopy render` and `canopy walk` (issue 15): the options, and for an offline render the scene
//! around a camera straight from the world function — the records of the cells near the camera, expanded, and the
//! summary nodes beyond them that the far view's refinement rule wants ([`Refine`], the rule a server applies).

use std::sync::Arc;

use canopy_protocol::CellCoord;
use canopy_protocol::summary::{FarView, NodeKey, NodeSummary, Refine};
use canopy_render::{Scene, SceneFar, SceneInstance};
use canopy_worlds::world::far::Summaries;
use canopy_worlds::world::{CellKey, Ground, InstanceId, World};
use clap::Args;

/// Far-view options shared by `canopy render` and `canopy walk`.
#[derive(Args, Debug, Clone)]
pub(super) struct FarArgs {
    /// Screen-space error of the far view, pixels: summary nodes beyond the records are refined while their
    /// geometric error projects larger (Cesium's default is 16).
    #[arg(long, default_value_t = 16.0)]
    pub far_error: f32,
    /// How far the far view reaches, metres.
    #[arg(long, default_value_t = 20_000.0)]
    pub far_range: f32,
    /// No far view: only the records are drawn (and nothing beyond them).
    #[arg(long)]
    pub no_summaries: bool,
}

impl FarArgs {
    /// The far view for a viewport `height_px` high with vertical field of view `fov_y_deg`, at `altitude` metres
    /// above the ground; `None` with `--no-summaries`.
    pub(super) fn view(&self, height_px: u32, fov_y_deg: f32, altitude: f32) -> anyhow::Result<Option<FarView>> {
        if self.no_summaries {
            return Ok(None);
        }
        let view = FarView {
            error_px: self.far_error,
            height_px: height_px.clamp(1, u32::from(u16::MAX)) as u16,
            fov_y: fov_y_deg.to_radians(),
            range: self.far_range,
            altitude: altitude.max(2.0),
        };
        view.validate().map_err(|e| {
            anyhow::anyhow!("--far-error/--far-range: {e} (error at least 0.5 px, range at most 65,536 m)")
        })?;
        Ok(Some(view))
    }
}

/// The far view of bots (`canopy bots`, `canopy bandwidth`, `canopy demo`): flights ask for one by default.
#[derive(Args, Debug, Clone)]
pub(super) struct BotFarArgs {
    /// Screen-space error of the far view, pixels: summary nodes beyond the records, refined while their error
    /// projects larger on a 1080-pixel-high, 60° view (Cesium's default is 16). Flights ask for a far view of 16
    /// by default, walkers only with this.
    #[arg(long)]
    pub far_error: Option<f32>,
    /// How far the far view reaches, metres.
    #[arg(long, default_value_t = 20_000.0)]
    pub far_range: f32,
    /// No far view, even flying.
    #[arg(long, conflicts_with = "far_error")]
    pub no_far: bool,
}

impl Default for BotFarArgs {
    fn default() -> Self {
        BotFarArgs { far_error: None, far_range: 20_000.0, no_far: false }
    }
}

impl BotFarArgs {
    /// The far view bots ask for: `--far-error` if given, 16 px flying, none walking or with `--no-far`.
    pub(super) fn view(&self, flying: bool, altitude: f32) -> anyhow::Result<Option<FarView>> {
        let args = FarArgs {
            far_error: match (self.far_error, flying) {
                (Some(e), _) => e,
                (None, true) => 16.0,
                (None, false) => return Ok(None),
            },
            far_range: self.far_range,
            no_summaries: self.no_far,
        };
        args.view(1080, 60.0, altitude)
    }
}

/// The summary nodes the far view wants around `eye` (x, z), records covering `record_radius`, computed through
/// `summaries` (which keeps what it computed for the next call).
pub(super) fn wanted_nodes(
    summaries: &mut Summaries,
    view: FarView,
    eye: [f32; 2],
    record_radius: f32,
) -> Vec<Arc<NodeSummary>> {
    let world = Arc::clone(summaries.world());
    let refine = Refine {
        view,
        eye,
        origin: [0.0, 0.0],
        cell_size: world.cell_size,
        root_level: canopy_protocol::summary::root_level(world.cell_size),
        record_radius,
    };
    let mut out = Vec::new();
    refine.reach(|k| {
        if !overlaps(&world, k) {
            return None;
        }
        let node = summaries.get(k);
        let error = node.error;
        out.push(node);
        Some(error)
    });
    out.sort_by_key(|n| n.key);
    out
}

/// Whether node `k` covers a cell of the world.
fn overlaps(world: &World, k: NodeKey) -> bool {
    let (first, dims) = (world.first_cell(), world.cell_dims());
    let c = k.first_cell();
    let side = i64::from(k.side());
    let (x0, z0) = (i64::from(c.x), i64::from(c.z));
    x0 < i64::from(first.x) + i64::from(dims[0])
        && x0 + side > i64::from(first.x)
        && z0 < i64::from(first.z) + i64::from(dims[1])
        && z0 + side > i64::from(first.z)
}

/// A scene of `world` around `eye` (x, y, z) from its function: every instance of the cells within
/// `record_radius` (a materialised world: every instance), and the far view's summary nodes beyond them.
pub(super) fn scene_around(world: &Arc<World>, eye: [f32; 3], record_radius: f32, view: Option<FarView>) -> Scene {
    let mut scene = if world.is_materialised() {
        Scene::from_world(world)
    } else {
        let mut scene = Scene::from_world(world);
        scene.instances = records_around(world, [eye[0], eye[2]], record_radius);
        scene
    };
    let record_cells: Vec<CellCoord> = {
        let mut cells: Vec<CellCoord> = scene.instances.iter().map(|i| i.id.cell()).collect();
        if !world.is_materialised() {
            cells.extend(cells_within(world, [eye[0], eye[2]], record_radius));
        } else {
            cells.extend(world.cells().map(|c| CellCoord::new(c.x, c.z)));
        }
        cells.sort_unstable();
        cells.dedup();
        cells
    };
    if let Some(view) = view {
        let mut summaries = Summaries::new(Arc::clone(world));
        let nodes = wanted_nodes(&mut summaries, view, [eye[0], eye[2]], record_radius);
        scene.far = SceneFar { nodes, cell_size: world.cell_size, record_cells, generation: 1 };
    }
    scene
}

/// The cells of the world whose centres lie within `radius` of `p`.
fn cells_within(world: &World, p: [f32; 2], radius: f32) -> Vec<CellCoord> {
    let s = world.cell_size;
    let lo = world.cell_of(f64::from(p[0] - radius), f64::from(p[1] - radius));
    let hi = world.cell_of(f64::from(p[0] + radius), f64::from(p[1] + radius));
    let mut out = Vec::new();
    for z in lo.z..=hi.z {
        for x in lo.x..=hi.x {
            let (cx, cz) = ((x as f32 + 0.5) * s - p[0], (z as f32 + 0.5) * s - p[1]);
            if cx * cx + cz * cz <= radius * radius && world.contains_cell(CellKey { x, z }) {
                out.push(CellCoord::new(x, z));
            }
        }
    }
    out.sort_unstable();
    out
}

/// Every instance of the cells within `radius` of `p`, expanded from the world function, sorted by id.
fn records_around(world: &World, p: [f32; 2], radius: f32) -> Vec<SceneInstance> {
    let cells = cells_within(world, p, radius);
    let Some((lo, hi)) = cells.iter().fold(None, |acc: Option<(CellCoord, CellCoord)>, c| {
        Some(acc.map_or((*c, *c), |(lo, hi)| {
            (CellCoord::new(lo.x.min(c.x), lo.z.min(c.z)), CellCoord::new(hi.x.max(c.x), hi.z.max(c.z)))
        }))
    }) else {
        return Vec::new();
    };
    let ground = Ground::of_world(world);
    let mut out = Vec::new();
    for (k, placements) in world.expand_cells(CellKey { x: lo.x, z: lo.z }, CellKey { x: hi.x, z: hi.z }) {
        let cell = CellCoord::new(k.x, k.z);
        if cells.binary_search(&cell).is_err() {
            continue;
        }
        for (i, p) in placements.iter().enumerate() {
            let Some(id) = u16::try_from(i).ok().and_then(|i| InstanceId::new(cell, i)) else { continue };
            // The renderer's f32 world metres (exact within ±4,096 cells of the origin).
            let (x, z) = (p.x as f32, p.z as f32);
            out.push(SceneInstance {
                id,
                species: p.species,
                position: [x, ground.height(x, z), z],
                seed: world.instance_seed(id),
                params: p.params.clone(),
            });
        }
    }
    out.sort_by_key(|i| i.id);
    out
}
