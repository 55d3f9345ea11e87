//! The far view's summaries drawn as forest (issue 15): the embedded `highlands` seen from 1,500 m above its
//! ground toward the horizon, offscreen on whatever wgpu adapter is present (CI: Mesa lavapipe), with the summary
//! nodes a far view selects (`Refine`, computed by `canopy_worlds::world::Summaries`) and with none. No records are
//! held, so without summaries no forest may show; with them the slopes are forest. The picture with summaries is
//! compared with `tests/reference/far-summaries.png` (`CANOPY_BLESS=1` writes a missing one); `CANOPY_FAR_PNG=DIR`
//! saves both pictures as `DIR/far-with.png` and `DIR/far-without.png`.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use canopy_protocol::CellCoord;
use canopy_protocol::summary::{FarView, NodeKey, NodeSummary, Refine};
use canopy_render::camera::Frustum;
use canopy_render::compare::{Tolerance, check_reference};
use canopy_render::offscreen::{Offscreen, RenderedImage};
use canopy_render::{Camera, FarPath, FrameStats, RenderConfig, Scene, SceneFar, SceneInstance};
use canopy_worlds::world::{CellKey, InstanceId, Summaries, World};
use glam::Vec3;

const W: u32 = 160;
const H: u32 = 100;
const ALTITUDE: f32 = 1_500.0;
/// How far summaries are asked for: the fractal ground's window drawn from this altitude reaches about as far.
const RANGE: f32 = 9_000.0;
const FOV: f32 = 60.0;

fn reference(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/reference").join(name)
}

/// From 1,500 m above the conifer slopes north of the southern massif, south toward its bare tops (the sun behind,
/// to the right).
fn camera(world: &World) -> Camera {
    let (x, z) = (2_000.0, -30_000.0);
    let eye = Vec3::new(x, world.height(x, z) + ALTITUDE, z);
    let (tx, tz) = (x + 300.0, z - 8_000.0);
    Camera::looking_at(eye, Vec3::new(tx, world.height(tx, tz), tz), FOV)
}

/// The nodes a client would hold for this view: every node `Refine` selects down from the roots, parents
/// included (the renderer draws a parent only where its children are not held), skipping subtrees out of view.
fn summaries(world: &Arc<World>, cam: &Camera, height_px: u16) -> Vec<Arc<NodeSummary>> {
    let altitude = cam.position.y - world.height(cam.position.x, cam.position.z);
    let view = FarView { error_px: 4.0, height_px, fov_y: FOV.to_radians(), range: RANGE, altitude };
    let eye = [cam.position.x, cam.position.z];
    let refine =
        Refine { view, eye, origin: [0.0, 0.0], cell_size: world.cell_size, root_level: 6, record_radius: 0.0 };
    let frustum = Frustum::from_matrix(cam.view_projection(W as f32 / H as f32, 1.0));
    let mut cache = Summaries::new(Arc::clone(world));
    let mut held = Vec::new();
    let mut stack: Vec<NodeKey> = refine.roots(false);
    while let Some(k) = stack.pop() {
        let [x0, z0, x1, z1] = refine.rect(k);
        let (cx, cz) = (0.5 * (x0 + x1), 0.5 * (z0 + z1));
        let half = 0.5 * (x1 - x0);
        let centre = Vec3::new(cx, world.height(cx, cz), cz);
        if !frustum.sphere_visible(centre, half * std::f32::consts::SQRT_2 + 600.0) {
            continue;
        }
        let node = cache.get(k);
        if refine.refines(k, node.error, false) {
            stack.extend(k.children().expect("refined nodes have children"));
        }
        held.push(node);
    }
    held
}

/// The records of `n × n` cells from `c0` as scene instances (sorted by id), and the cells (sorted).
fn records(world: &World, c0: CellKey, n: i32) -> (Vec<SceneInstance>, Vec<CellCoord>) {
    let (mut instances, mut cells) = (Vec::new(), Vec::new());
    for (cell, list) in world.expand_cells(c0, CellKey { x: c0.x + n - 1, z: c0.z + n - 1 }) {
        let cc = CellCoord::new(cell.x, cell.z);
        cells.push(cc);
        for (i, p) in list.iter().enumerate() {
            let id = InstanceId::new(cc, i as u16).expect("a cell's index");
            let (x, z) = (p.x as f32, p.z as f32);
            let position = [x, world.height(x, z), z];
            let seed = world.instance_seed(id);
            instances.push(SceneInstance { id, species: p.species, position, seed, params: p.params.clone() });
        }
    }
    instances.sort_by_key(|i| i.id);
    cells.sort();
    (instances, cells)
}

struct Shot {
    image: RenderedImage,
    stats: FrameStats,
    render_ms: f64,
}

fn shoot(scene: &Scene, cam: &Camera, w: u32, h: u32) -> Shot {
    shoot_with(scene, cam, w, h, FarPath::Auto)
}

fn shoot_with(scene: &Scene, cam: &Camera, w: u32, h: u32, far_path: FarPath) -> Shot {
    let mut cfg = RenderConfig { workers: 2, volume_resolution: 48, far_path, ..RenderConfig::default() };
    cfg.lighting.fog_density = 0.0;
    let mut off = Offscreen::new(cfg, w, h).unwrap_or_else(|e| panic!("offscreen renderer: {e}"));
    let stats = off.settle(scene, cam, Duration::from_secs(300)).unwrap_or_else(|e| panic!("settling: {e}"));
    let image = off.render().unwrap_or_else(|e| panic!("render: {e}"));
    let started = Instant::now();
    off.render_and_wait().unwrap_or_else(|e| panic!("render: {e}"));
    Shot { image, stats, render_ms: started.elapsed().as_secs_f64() * 1e3 }
}

/// Forest green: darker than the sunlit meadows and rock the terrain shades, green over red and blue.
fn forest(p: [u8; 4]) -> bool {
    let [r, g, b] = [p[0], p[1], p[2]].map(i32::from);
    g > r + 6 && g > b + 6 && r + g + b < 120
}

fn count(img: &RenderedImage, rows: std::ops::Range<u32>, f: impl Fn([u8; 4]) -> bool) -> u32 {
    rows.flat_map(|y| (0..img.width).map(move |x| (x, y))).filter(|&(x, y)| f(img.pixel(x, y))).count() as u32
}

#[test]
fn summaries_draw_forest_to_the_horizon_and_nothing_without_them() {
    let world = Arc::new(World::embedded("highlands").expect("embedded"));
    let cam = camera(&world);
    let started = Instant::now();
    let nodes = summaries(&world, &cam, H as u16);
    let summarised = started.elapsed();
    let levels = nodes.iter().fold([0u32; 8], |mut a, n| {
        a[usize::from(n.key.level).min(7)] += 1;
        a
    });
    eprintln!("{} summary nodes in {summarised:?}, by level {levels:?}", nodes.len());
    assert!(nodes.len() > 20 && nodes.iter().any(|n| !n.species.is_empty()), "{} nodes", nodes.len());

    let mut scene = Scene::from_world(&world);
    assert!(scene.instances.is_empty(), "no records: the highlands are expanded on demand");
    let bare = shoot(&scene, &cam, W, H);
    scene.far = SceneFar { nodes: nodes.clone(), cell_size: world.cell_size, record_cells: Vec::new(), generation: 1 };
    let with = shoot(&scene, &cam, W, H);
    eprintln!("with summaries: {:?}\nrender {:.1} ms (without: {:.1} ms)", with.stats, with.render_ms, bare.render_ms);
    if let Some(dir) = std::env::var_os("CANOPY_FAR_PNG") {
        let dir = PathBuf::from(dir);
        with.image.save_png(&dir.join("far-with.png")).expect("saved");
        bare.image.save_png(&dir.join("far-without.png")).expect("saved");
    }

    // Optional: the same view larger (CANOPY_FAR_HD=WIDTHxHEIGHT, e.g. 1920x1080), for numbers and a closer look.
    if let Some(size) = std::env::var("CANOPY_FAR_HD").ok().and_then(|s| {
        let (w, h) = s.split_once('x')?;
        Some((w.parse::<u32>().ok()?, h.parse::<u32>().ok()?))
    }) {
        let nodes = summaries(&world, &cam, size.1 as u16);
        // CANOPY_FAR_RECORDS=1: records of 6 × 6 cells 3 km ahead too (the far band beside the summaries).
        let (instances, record_cells) = match std::env::var_os("CANOPY_FAR_RECORDS") {
            Some(_) => {
                let f = cam.forward();
                let ahead = cam.position + f * 3_000.0 / (f.x * f.x + f.z * f.z).sqrt();
                let c = world.cell_of(ahead.x.into(), ahead.z.into());
                records(&world, CellKey { x: c.x - 3, z: c.z - 3 }, 6)
            }
            None => (Vec::new(), Vec::new()),
        };
        eprintln!("{} records", instances.len());
        scene.instances = instances;
        scene.generation += 1;
        scene.far = SceneFar { nodes, cell_size: world.cell_size, record_cells, generation: 2 };
        let hd = shoot(&scene, &cam, size.0, size.1);
        eprintln!("{}×{}: {:?}\nrender {:.1} ms", size.0, size.1, hd.stats, hd.render_ms);
        if let Some(dir) = std::env::var_os("CANOPY_FAR_PNG") {
            hd.image.save_png(&PathBuf::from(dir).join("far-hd.png")).expect("saved");
        }
    }

    let s = &with.stats;
    assert_eq!(s.summary_nodes, nodes.len());
    assert!(s.forest_nodes >= 10 && s.forest_patches >= s.forest_nodes, "{s:?}");
    assert!(s.forest_nodes < nodes.len(), "refined parents are not drawn: {s:?}");
    // The trees' worth drawn: some, and no more than the nodes drawn hold (a refined parent's trees are its
    // children's).
    let held: f64 = nodes.iter().flat_map(|n| &n.species).map(|c| f64::from(c.count)).sum();
    assert!(s.forest_trees > 1000.0 && s.forest_trees <= held, "{} of {held}", s.forest_trees);
    assert_eq!((s.forest_waiting, s.waiting), (0, 0));
    assert_eq!((bare.stats.forest_patches, bare.stats.summary_nodes), (0, 0));
    // Forest pixels over the ground beyond the (empty) record area: many with summaries, none without.
    let rows = 0..H;
    let (forest_with, forest_without) = (count(&with.image, rows.clone(), forest), count(&bare.image, rows, forest));
    eprintln!("forest pixels: {forest_with} with summaries, {forest_without} without");
    assert!(forest_with > W * H / 8, "{forest_with} forest pixels with summaries");
    assert!(forest_without < W * H / 200, "{forest_without} forest pixels without summaries");
    check_reference(&with.image, &reference("far-summaries.png"), &Tolerance::default())
        .unwrap_or_else(|e| panic!("{e}"));
    // Both ways of drawing the far field draw this picture: the compute pass over screen tiles and the boxes.
    for far_path in [FarPath::Compute, FarPath::Raster] {
        let shot = shoot_with(&scene_with(&world, &nodes), &cam, W, H, far_path);
        check_reference(&shot.image, &reference("far-summaries.png"), &Tolerance::default())
            .unwrap_or_else(|e| panic!("{far_path}: {e}"));
    }
}

fn scene_with(world: &World, nodes: &[Arc<NodeSummary>]) -> Scene {
    let mut scene = Scene::from_world(world);
    scene.far = SceneFar { nodes: nodes.to_vec(), cell_size: world.cell_size, record_cells: Vec::new(), generation: 1 };
    scene
}

/// From inside a node's canopy: 10 m above the conifer slopes, looking straight down, every ray starts inside the
/// box of the node under the eye (its inner faces are the ones drawn: the vertex shader reverses their winding
/// under back-face culling). With summaries the view is canopy; without, ground.
#[test]
fn from_inside_a_nodes_canopy_the_forest_is_drawn_around_the_eye() {
    let world = Arc::new(World::embedded("highlands").expect("embedded"));
    let (x, z) = (2_000.0, -30_000.0);
    let ground = world.height(x, z);
    let cam = Camera::looking_at(Vec3::new(x, ground + 10.0, z), Vec3::new(x, ground, z + 0.01), FOV);
    let nodes = summaries(&world, &cam, H as u16);
    let under = nodes.iter().filter(|n| n.key.level == 0).count();
    assert!(under > 0, "leaves are selected next to the eye: {:?}", nodes.iter().map(|n| n.key).collect::<Vec<_>>());
    // The ground in its sunlit green (no cover: the forest floor's dark would pass for canopy).
    let bare = shoot(&Scene { cover: None, ..Scene::from_world(&world) }, &cam, W, H);
    for far_path in [FarPath::Compute, FarPath::Raster] {
        let with = shoot_with(&Scene { cover: None, ..scene_with(&world, &nodes) }, &cam, W, H, far_path);
        if let Some(dir) = std::env::var_os("CANOPY_FAR_PNG") {
            let dir = PathBuf::from(dir);
            with.image.save_png(&dir.join(format!("inside-with-{far_path}.png"))).expect("saved");
            bare.image.save_png(&dir.join("inside-without.png")).expect("saved");
        }
        canopy_all_around(&with, &bare);
    }
}

fn canopy_all_around(with: &Shot, bare: &Shot) {
    assert!(with.stats.forest_patches > 0, "{:?}", with.stats);
    // Inside the canopy the rays meet shaded foliage at once: the view is dark green where the bare view is
    // sunlit ground. Were the inner faces culled, the two would be the same picture.
    let (mut canopy, mut ground) = (0, 0);
    for y in 0..H {
        for x in 0..W {
            let ([r, g, b, _], [br, bg, bb, _]) = (with.image.pixel(x, y), bare.image.pixel(x, y));
            let sum = |r: u8, g: u8, b: u8| u32::from(r) + u32::from(g) + u32::from(b);
            canopy += u32::from(g >= r && g >= b && sum(r, g, b) + 60 < sum(br, bg, bb));
            ground += u32::from(forest([br, bg, bb, 255]));
        }
    }
    eprintln!("from inside: {canopy} canopy pixels with summaries; {ground} forest pixels without");
    assert!(canopy > W * H * 9 / 10, "{canopy} of {} pixels are canopy with summaries", W * H);
    assert_eq!(ground, 0, "no forest without summaries");
}
