//! The terrain mesh: the world's height grid (the fractal terrain species' triangles, seed 001 §5) in square chunks,
//! each with index ranges at 1, 2, 4 and 8 grid squares per step chosen by projected size, and skirts hanging from
//! chunk borders so that neighbours at different steps leave no cracks. Each vertex carries its ground's colour: the
//! world's cover where the scene has one ([`GroundCover`]: forest floor, meadow, scree, rock, snow), else a green
//! by relative height and slope.

use std::ops::Range;

use canopy_worlds::world::{GroundCover, Terrain};
use glam::Vec3;

use super::geometry::{MeshVertex, pack_snorm, pack_unorm};

/// Grid squares per chunk edge (or the whole grid when smaller).
const CHUNK: u32 = 32;
/// Steps of the chunk levels of detail, in grid squares.
pub(crate) const STEPS: [u32; 4] = [1, 2, 4, 8];

/// One chunk: its bounding sphere and an index range per step.
#[derive(Clone, Debug)]
pub(crate) struct Chunk {
    /// Centre of the bounding sphere.
    pub center: Vec3,
    /// Radius.
    pub radius: f32,
    /// Indices of each level in [`TerrainMesh::indices`] (`STEPS` order; levels the chunk cannot take repeat the
    /// finest one).
    pub levels: [Range<u32>; 4],
}

/// The CPU terrain mesh.
#[derive(Clone, Debug)]
pub(crate) struct TerrainMesh {
    /// Grid vertices, then skirt vertices.
    pub vertices: Vec<MeshVertex>,
    /// Triangles of every chunk and level.
    pub indices: Vec<u32>,
    /// The chunks.
    pub chunks: Vec<Chunk>,
    /// Grid spacing, metres.
    pub spacing: f32,
}

/// Ground colour from height, slope and a little per-vertex variation.
fn ground_color(h: f32, slope_deg: f32, lo: f32, hi: f32, jitter: f32) -> Vec3 {
    let t = if hi > lo { ((h - lo) / (hi - lo)).clamp(0.0, 1.0) } else { 0.5 };
    let grass = MEADOW.lerp(Vec3::new(0.24, 0.32, 0.15), t);
    let r = ((slope_deg - 28.0) / 14.0).clamp(0.0, 1.0);
    grass.lerp(Vec3::new(0.42, 0.40, 0.36), r) * (0.92 + 0.16 * jitter)
}

/// The ground's materials under its cover.
const MEADOW: Vec3 = Vec3::new(0.30, 0.42, 0.16);
const FOREST_FLOOR: Vec3 = Vec3::new(0.25, 0.26, 0.13);
const SCREE: Vec3 = Vec3::new(0.40, 0.39, 0.37);
const ROCK: Vec3 = Vec3::new(0.31, 0.30, 0.29);
const SNOW: Vec3 = Vec3::new(0.92, 0.94, 0.98);

fn smoothstep(e0: f32, e1: f32, x: f32) -> f32 {
    let t = ((x - e0) / (e1 - e0)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

/// Ground colour from the world's cover at height `h` and squared gradient `g2`: bare ground is scree, rock where
/// it steepens past 20° (all rock by 35°); low plants turn it to meadow, trees to forest floor; snow lies on top
/// where the ground is under 35° (none past 50°).
fn covered_color(cover: &GroundCover, h: f32, g2: f64, jitter: f32) -> Vec3 {
    let c = cover.at(h, g2);
    let slope = canopy_worlds::world::slope_degrees(g2);
    let bare = SCREE.lerp(ROCK, smoothstep(20.0, 35.0, slope));
    let grown = bare.lerp(MEADOW, c.plants).lerp(FOREST_FLOOR, c.trees);
    let snowed = grown.lerp(SNOW, c.snow * (1.0 - smoothstep(35.0, 50.0, slope)));
    snowed * (0.92 + 0.16 * jitter)
}

fn hash(i: u32, j: u32) -> f32 {
    let mut x = i.wrapping_mul(0x9e37_79b1) ^ j.wrapping_mul(0x85eb_ca77);
    x ^= x >> 15;
    x = x.wrapping_mul(0x2c1b_3c6d);
    x ^= x >> 12;
    (x & 0xffff) as f32 / 65535.0
}

impl TerrainMesh {
    /// Build the mesh of a terrain, its vertices coloured by `cover` where given.
    pub(crate) fn build(t: &Terrain, cover: Option<&GroundCover>) -> TerrainMesh {
        let [sx, sz] = t.squares();
        let (nx, nz) = (sx + 1, sz + 1);
        let s = t.spacing();
        let (lo, hi) = t.height_range();
        let at = |i: u32, j: u32| j * nx + i;
        let mut vertices = Vec::with_capacity((nx * nz) as usize);
        for j in 0..nz {
            for i in 0..nx {
                let [x, z] = t.vertex_position(i, j);
                let h = t.vertex_height(i, j);
                let (i0, i1) = (i.saturating_sub(1), (i + 1).min(sx));
                let (j0, j1) = (j.saturating_sub(1), (j + 1).min(sz));
                let dx = (t.vertex_height(i1, j) - t.vertex_height(i0, j)) / ((i1 - i0).max(1) as f32 * s);
                let dz = (t.vertex_height(i, j1) - t.vertex_height(i, j0)) / ((j1 - j0).max(1) as f32 * s);
                let n = Vec3::new(-dx, 1.0, -dz).normalize_or(Vec3::Y);
                let color = match cover {
                    Some(c) => covered_color(c, h, f64::from(dx * dx + dz * dz), hash(i, j)),
                    None => ground_color(h, n.y.clamp(-1.0, 1.0).acos().to_degrees(), lo, hi, hash(i, j)),
                };
                vertices.push(MeshVertex {
                    position: [x, h, z],
                    normal: pack_snorm(n.to_array()),
                    color: pack_unorm(color.to_array()),
                });
            }
        }
        let chunk = CHUNK.min(sx).min(sz).max(1);
        let skirt_depth = 4.0 * s * STEPS[3] as f32;
        let mut indices = Vec::new();
        let mut chunks = Vec::new();
        let mut skirt_of = std::collections::HashMap::new();
        for cj in (0..sz).step_by(chunk as usize) {
            for ci in (0..sx).step_by(chunk as usize) {
                let (i1, j1) = ((ci + chunk).min(sx), (cj + chunk).min(sz));
                let (mut ymin, mut ymax) = (f32::INFINITY, f32::NEG_INFINITY);
                for j in cj..=j1 {
                    for i in ci..=i1 {
                        let h = t.vertex_height(i, j);
                        ymin = ymin.min(h);
                        ymax = ymax.max(h);
                    }
                }
                let p0 = t.vertex_position(ci, cj);
                let p1 = t.vertex_position(i1, j1);
                let a = Vec3::new(p0[0], ymin - skirt_depth, p0[1]);
                let b = Vec3::new(p1[0], ymax, p1[1]);
                let mut levels: [Range<u32>; 4] = Default::default();
                for (k, &step) in STEPS.iter().enumerate() {
                    let fits = (i1 - ci) % step == 0 && (j1 - cj) % step == 0;
                    if !fits {
                        levels[k] = levels[0].clone();
                        continue;
                    }
                    let start = indices.len() as u32;
                    for j in (cj..j1).step_by(step as usize) {
                        for i in (ci..i1).step_by(step as usize) {
                            let (v00, v10, v01, v11) =
                                (at(i, j), at(i + step, j), at(i, j + step), at(i + step, j + step));
                            // The terrain's own split at full resolution (heights match `Terrain::height` exactly).
                            if step == 1 && t.anti_diagonal(i, j) {
                                indices.extend([v00, v01, v10, v10, v01, v11]);
                            } else {
                                indices.extend([v00, v01, v11, v00, v11, v10]);
                            }
                        }
                    }
                    // Skirts along the four borders.
                    let mut skirt = |v: u32, vertices: &mut Vec<MeshVertex>| -> u32 {
                        *skirt_of.entry(v).or_insert_with(|| {
                            let mut x = vertices[v as usize];
                            x.position[1] -= skirt_depth;
                            vertices.push(x);
                            vertices.len() as u32 - 1
                        })
                    };
                    let borders: [Vec<u32>; 4] = [
                        (ci..=i1).step_by(step as usize).map(|i| at(i, cj)).collect(),
                        (ci..=i1).step_by(step as usize).map(|i| at(i, j1)).collect(),
                        (cj..=j1).step_by(step as usize).map(|j| at(ci, j)).collect(),
                        (cj..=j1).step_by(step as usize).map(|j| at(i1, j)).collect(),
                    ];
                    for line in borders {
                        for w in line.windows(2) {
                            let (a0, a1) = (w[0], w[1]);
                            let (b0, b1) = (skirt(a0, &mut vertices), skirt(a1, &mut vertices));
                            indices.extend([a0, a1, b1, a0, b1, b0]);
                        }
                    }
                    levels[k] = start..indices.len() as u32;
                }
                chunks.push(Chunk { center: (a + b) * 0.5, radius: (b - a).length() * 0.5, levels });
            }
        }
        TerrainMesh { vertices, indices, chunks, spacing: s }
    }

    /// The level (index into [`STEPS`]) for a chunk seen from `distance` when a metre at unit distance covers
    /// `px_per_rad` pixels: the coarsest step whose squares stay under `max_px` pixels.
    pub(crate) fn level_for(&self, distance: f32, px_per_rad: f32, max_px: f32) -> usize {
        let square_px = |step: u32| step as f32 * self.spacing * px_per_rad / distance.max(1e-3);
        STEPS.iter().rposition(|&st| square_px(st) <= max_px).unwrap_or(0)
    }
}

#[cfg(test)]
mod tests {
    use canopy_worlds::world::World;

    use super::*;

    #[test]
    fn the_mesh_follows_the_terrain_and_every_level_covers_the_chunk() {
        let w = World::default_world();
        let m = TerrainMesh::build(&w.terrain, None);
        let [sx, sz] = w.terrain.squares();
        assert_eq!(m.chunks.len() as u32, sx.div_ceil(CHUNK) * sz.div_ceil(CHUNK));
        // Grid vertices carry the exact heights.
        let v = m.vertices[(7 * (sx + 1) + 9) as usize];
        assert_eq!(v.position[1], w.terrain.vertex_height(9, 7));
        assert_eq!(v.position[1], w.height(v.position[0], v.position[2]));
        for c in &m.chunks {
            // Level k has 4^(-k) as many grid triangles as level 0, plus its skirts.
            let tri = |k: usize| (c.levels[k].end - c.levels[k].start) / 3;
            let per_side = CHUNK / STEPS[3];
            assert_eq!(tri(3), 2 * per_side * per_side + 2 * 4 * per_side);
            assert!(tri(0) > tri(1) && tri(1) > tri(2) && tri(2) > tri(3));
        }
        assert!(m.indices.iter().all(|&i| (i as usize) < m.vertices.len()));
        // Near chunks are fine, far ones coarse.
        assert_eq!(m.level_for(10.0, 1000.0, 12.0), 0);
        assert_eq!(m.level_for(100_000.0, 1000.0, 12.0), 3);
    }

    #[test]
    fn flat_terrain_is_one_small_chunk() {
        let t = Terrain::flat([-10.0, -10.0], 20.0);
        let m = TerrainMesh::build(&t, None);
        assert_eq!(m.chunks.len(), 1);
        assert_eq!(m.vertices[..4].iter().map(|v| v.position[1]).sum::<f32>(), 0.0);
    }
}
