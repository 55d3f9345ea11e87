//! The far field matches the near tree where it takes over (issue 35.3): the same tree of the library rendered
//! near (amplify → mesh → software rasteriser) and far (voxelise → CPU raymarcher) with the same camera, at the
//! size where the renderer switches to the far field (`LodConfig::far_px`, 90 px of projected bounding-sphere
//! height in client/render/src/lod.rs), over the same sky; the fraction of pixels the tree covers and the mean
//! colour of the covered pixels are compared.

use canopy_worlds::amplify::{Budget, Instance, amplify};
use canopy_worlds::hypertree::render::{RenderOptions, render};
use canopy_worlds::hypertree::voxelise::{VoxeliseOptions, voxelise};
use canopy_worlds::mesh::{MeshOptions, mesh};
use canopy_worlds::nearfield::raster::{self, Camera};

/// The projected height (pixels) of a tree's bounding sphere where the renderer draws the far field
/// (`LodConfig::default().far_px` in client/render/src/lod.rs).
const SWITCH_PX: u32 = 90;
/// Voxels along the longest axis of the editor's far-field volume (`hyp::FAR_RESOLUTION`).
const FAR_RESOLUTION: u32 = 96;
const FOV: f32 = 35.0;
const ELEVATION: f32 = 8.0;
/// The rasteriser's sky, top and bottom, linear (it writes gamma-encoded pixels; the raymarcher's background is
/// given encoded, so both pictures have the same sky).
const SKY: [[f32; 3]; 2] = [[0.62, 0.74, 0.88], [0.87, 0.90, 0.94]];

/// The raymarcher's sky for `opts`, row by row as it draws it (the mean of each row's supersamples).
fn far_sky(opts: &RenderOptions) -> Vec<u8> {
    let (w, h, s) = (opts.width, opts.height, opts.supersample);
    let mut out = Vec::new();
    for py in 0..h {
        let mut c = [0.0f32; 3];
        for sy in 0..s {
            let fy = (py as f32 + (sy as f32 + 0.5) / s as f32) / h as f32;
            let [top, bottom] = opts.background;
            for (i, v) in c.iter_mut().enumerate() {
                *v += (top[i] + (bottom[i] - top[i]) * fy) / s as f32;
            }
        }
        for _ in 0..w {
            out.extend(c.map(|v| (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8));
        }
    }
    out
}

/// Coverage (fraction of pixels that differ from the sky) and mean colour of those pixels, 0..1.
fn measure(rgb: &[u8], sky: &[u8]) -> (f64, [f64; 3]) {
    let (mut n, mut sum) = (0u64, [0.0f64; 3]);
    let pixels = rgb.len() / 3;
    for (p, s) in rgb.chunks_exact(3).zip(sky.chunks_exact(3)) {
        let diff = (0..3).map(|i| (i32::from(p[i]) - i32::from(s[i])).abs()).max().unwrap_or(0);
        if diff > 12 {
            n += 1;
            for i in 0..3 {
                sum[i] += f64::from(p[i]) / 255.0;
            }
        }
    }
    let mean = sum.map(|v| v / n.max(1) as f64);
    (n as f64 / pixels as f64, mean)
}

struct Pair {
    near: (f64, [f64; 3]),
    far: (f64, [f64; 3]),
}

fn both(species: &str, seed: u64) -> Pair {
    let graph = canopy_worlds::library::find(species).expect("library species").load().expect("parses");
    let stream = amplify(&graph, &Instance::new(seed), &Budget::default()).expect("amplifies");
    // Far: the raymarcher's own camera around the volume's non-empty voxels.
    let tree =
        voxelise(&stream, species, &VoxeliseOptions { resolution: FAR_RESOLUTION, ..VoxeliseOptions::default() })
            .expect("voxelises");
    let opts = RenderOptions {
        width: SWITCH_PX,
        height: SWITCH_PX,
        supersample: 2,
        fov: FOV,
        elevation: ELEVATION,
        zoom_out: 1.0,
        background: SKY.map(|c| c.map(|v| libm::powf(v, 1.0 / 2.2))),
        ..RenderOptions::default()
    };
    let (far, _) = render(&tree, &opts, &mut |_, _| {}).expect("raymarches");
    // Near: the same view of the same box in world space (the volume starts at the stream's bounds less the pad).
    let (lo, hi) = stream.bounds();
    let camera = Camera::framing(lo, hi, 0.0, f64::from(ELEVATION), 1.0);
    let camera = Camera { fov: f64::from(FOV), ..camera };
    let m = mesh(&stream, &MeshOptions::default());
    let near = raster::render(&[&m], &camera, SWITCH_PX, SWITCH_PX);
    let sky = raster::render(&[], &camera, SWITCH_PX, SWITCH_PX);
    Pair { near: measure(&near.rgb, &sky.rgb), far: measure(&far.pixels, &far_sky(&opts)) }
}

/// The goal (issue 35.3, not reached yet): coverage within ±15 % (relative) of the near tree's, mean colour of the
/// covered pixels within 0.1 (Euclidean, RGB in 0..1). What it reaches today (measured 2026-11-27: monopodial +21 % / 0.74, conifer +45 % / 0.79 — the far tree is
/// far darker: the rasteriser lights linear colours and encodes them with gamma 2.2, the raymarcher writes its
/// lit colours unencoded and self-shadows): a guard that it gets no worse until it is calibrated. The raymarcher's
/// `density_scale` is not the lever for coverage: from 1 down to 0.1 it moves monopodial's from +21 % to +19 % and
/// conifer's not at all, for every voxel a branch or needle touches gets full density (`HitRecorder::finish` gives
/// levels up to the branch depth 255, opaque whatever part of the voxel the wood covers).
const TODAY: (f64, f64) = (0.60, 0.85);

/// Render `species` both ways, print the numbers, and check them against `(coverage, colour)` tolerances.
fn check(species: &str, (coverage, colour): (f64, f64)) {
    let p = both(species, 7);
    let dc = (0..3).map(|i| (p.near.1[i] - p.far.1[i]).powi(2)).sum::<f64>().sqrt();
    let rel = (p.far.0 - p.near.0) / p.near.0.max(1e-9);
    eprintln!(
        "{species}: near coverage {:.3} colour {:.3?}; far coverage {:.3} colour {:.3?}; coverage {:+.1} %, colour distance {dc:.3}",
        p.near.0,
        p.near.1,
        p.far.0,
        p.far.1,
        100.0 * rel
    );
    assert!(p.near.0 > 0.02 && p.far.0 > 0.02, "both renderings show the tree");
    assert!(rel.abs() <= coverage, "{species}: far coverage {:+.1} % off the near tree's", 100.0 * rel);
    assert!(dc <= colour, "{species}: far mean colour {dc:.3} away from the near tree's");
}

#[test]
fn monopodial_far_field_is_no_further_from_the_near_tree_than_today() {
    check("monopodial", TODAY);
}

#[test]
fn conifer_far_field_is_no_further_from_the_near_tree_than_today() {
    check("conifer", TODAY);
}
