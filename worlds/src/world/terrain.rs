//! The world's ground: the fractal terrain species (`worlds/species/terrain.species`, seed 001 §5 and §7) amplified
//! tile by tile into a height grid at load, and the height of its triangle surface anywhere.
//!
//! The grid is read off the amplified triangles themselves — every vertex, and which diagonal splits every grid
//! square — so [`Terrain::height`] is the mesh a client amplifies from the same species and tile instances, never a
//! second implementation of the midpoint displacement that could drift from it: at a vertex it is the vertex's
//! height bit for bit, in between it lies on the triangle's plane.

use canopy_protocol::SpeciesGraph;

use crate::amplify::{AmplifyError, Budget, Instance, amplify_into};
use crate::primitive::{PrimitiveStream, Shape};

/// Traversal steps a terrain species may take per grid square (the library's takes about 180): with the vertex
/// limit, this bounds the work of building any terrain, however hostile its species.
pub const STEPS_PER_SQUARE: u64 = 512;

/// The parameters a terrain species must declare, which the world sets for every tile.
pub const TILE_PARAMS: [&str; 8] = ["h00", "h10", "h01", "h11", "size", "depth", "ox", "oz"];

/// Why a terrain could not be built.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum TerrainError {
    /// The species lacks one of [`TILE_PARAMS`].
    #[error("the terrain species lacks parameter `{0}` (a terrain species takes h00 h10 h01 h11 size depth ox oz)")]
    MissingParam(&'static str),
    /// The height grid would have too many vertices (or none, or a depth beyond the limit).
    #[error(
        "the terrain grid would have {0} vertices, more than {max} (or a depth above {depth}, or no tiles)",
        max = super::MAX_TERRAIN_VERTICES,
        depth = super::MAX_TERRAIN_DEPTH
    )]
    TooLarge(u64),
    /// The corner heights do not match the tiles.
    #[error("{got} corner heights for the tiles, expected {expected}")]
    Corners {
        /// `(tiles x + 1) · (tiles z + 1)`.
        expected: usize,
        /// Given.
        got: usize,
    },
    /// Grid lines `origin + k · spacing` are not exact in f32 (an odd tile size far from the origin).
    #[error("terrain grid lines ({origin} + k × {spacing} m) are not exact in f32; use a power-of-two tile size")]
    Inexact {
        /// Grid origin on the axis.
        origin: f32,
        /// Grid spacing.
        spacing: f32,
    },
    /// Amplifying a tile failed.
    #[error("amplifying terrain tile ({}, {}): {source}", tile[0], tile[1])]
    Amplify {
        /// The tile.
        tile: [u32; 2],
        /// What went wrong.
        source: AmplifyError,
    },
    /// The species emitted something other than triangles.
    #[error("terrain tile ({}, {}) emitted a {kind} with {points} points; a terrain species emits triangles only", tile[0], tile[1])]
    NotTriangle {
        /// The tile.
        tile: [u32; 2],
        /// Kind of the primitive.
        kind: &'static str,
        /// Its point count.
        points: usize,
    },
    /// A vertex lies off the grid of spacing `size / 2^depth`.
    #[error("terrain vertex ({x}, {z}) of tile ({}, {}) is off the {spacing} m grid", tile[0], tile[1])]
    OffGrid {
        /// The tile.
        tile: [u32; 2],
        /// Local x.
        x: f32,
        /// Local z.
        z: f32,
        /// Grid spacing.
        spacing: f32,
    },
    /// A height is NaN or infinite.
    #[error("terrain height at ({x}, {z}) is not finite")]
    NotFinite {
        /// World x.
        x: f32,
        /// World z.
        z: f32,
    },
    /// Two triangles give one vertex two heights.
    #[error("terrain crack at ({x}, {z}): heights {a} and {b}")]
    Crack {
        /// World x.
        x: f32,
        /// World z.
        z: f32,
        /// First height.
        a: f32,
        /// Second height.
        b: f32,
    },
    /// A grid square is not covered by exactly two triangles sharing a diagonal.
    #[error("terrain grid square at ({x}, {z}) is not two triangles split along a diagonal")]
    Coverage {
        /// World x of the square's corner.
        x: f32,
        /// World z of the square's corner.
        z: f32,
    },
}

/// One vertex of an amplified terrain triangle in tile-local coordinates, or a primitive that is not a triangle.
#[derive(Clone, Copy, Debug)]
enum Vertex {
    Point([f32; 3]),
    NotTriangle { kind: &'static str, points: usize },
}

/// Amplify every tile instance; three [`Vertex`] per primitive. Tiles are independent pure functions, so they
/// run on the available cores ([`super::par::map`]) with the same result.
fn amplify_tiles(graph: &SpeciesGraph, tiles: &[Instance], depth: u32) -> Vec<Result<Vec<Vertex>, AmplifyError>> {
    let squares = 4u64.pow(depth);
    let budget = Budget {
        max_primitives: (2 * squares) as u32,
        max_steps: STEPS_PER_SQUARE * squares + 1024,
        ..Budget::default()
    };
    super::par::map(tiles, PrimitiveStream::default, |stream, instance| {
        stream.primitives.clear();
        stream.leaf_points.clear();
        amplify_into(graph, instance, &budget, stream)?;
        let mut out = Vec::with_capacity(stream.primitives.len() * 3);
        for p in &stream.primitives {
            let points = stream.leaf(p);
            if matches!(p.shape, Shape::Leaf { .. }) && points.len() == 3 {
                out.extend(points.iter().map(|&q| Vertex::Point(p.transform.point(q))));
            } else {
                let bad = Vertex::NotTriangle { kind: p.shape.kind().name(), points: points.len() };
                out.extend([bad; 3]);
            }
        }
        Ok(out)
    })
}

/// Slots of [`TILE_PARAMS`] in the terrain species.
#[derive(Clone, Copy, Debug, PartialEq)]
struct TileSlots {
    corners: [u16; 4],
    size: u16,
    depth: u16,
    ox: u16,
    oz: u16,
}

/// The terrain: its species and tiling, and the height grid amplified from them.
#[derive(Clone, Debug, PartialEq)]
pub struct Terrain {
    /// The terrain species; `None` for flat ground at height 0 (a manifest without `terrain`).
    pub species: Option<SpeciesGraph>,
    /// Where the species came from (as in [`super::WorldSpecies::source`]).
    pub source: String,
    /// The instance seed of every tile (tiles share it, so the noise along shared edges agrees).
    pub seed: u64,
    /// World (x, z) of the corner of tile (0, 0).
    pub origin: [f32; 2],
    /// Tile edge, metres.
    pub tile_size: f32,
    /// Tiles per axis (x, z).
    pub tiles: [u32; 2],
    /// Recursion depth of every tile: `2^depth` grid squares per tile edge.
    pub depth: u32,
    /// Heights at the tile corners, `(tiles[0] + 1) × (tiles[1] + 1)`, rows of increasing z.
    pub corners: Vec<f32>,
    /// The other parameter values the manifest sets (dimension, relief, …), sorted by slot.
    pub params: Vec<(u16, f32)>,
    slots: Option<TileSlots>,
    /// Grid spacing: `tile_size / 2^depth`.
    spacing: f32,
    /// Grid squares per axis.
    squares: [u32; 2],
    /// Vertex heights, `(squares[0] + 1) × (squares[1] + 1)`, rows of increasing z.
    heights: Vec<f32>,
    /// Per square: `false` when split along (0, 0)–(1, 1), `true` along (1, 0)–(0, 1).
    anti_diagonal: Vec<bool>,
    range: (f32, f32),
}

impl Terrain {
    /// Flat ground at height 0 over a square covering `min .. min + size`.
    pub fn flat(min: [f32; 2], size: f32) -> Terrain {
        Terrain {
            species: None,
            source: String::from("flat"),
            seed: 0,
            origin: min,
            tile_size: size,
            tiles: [1, 1],
            depth: 0,
            corners: vec![0.0; 4],
            params: Vec::new(),
            slots: None,
            spacing: size,
            squares: [1, 1],
            heights: vec![0.0; 4],
            anti_diagonal: vec![false],
            range: (0.0, 0.0),
        }
    }

    /// A height grid from its vertex heights: `squares[0] × squares[1]` squares of edge `spacing` with vertex
    /// (0, 0) at `origin`, `heights` by rows of increasing z (`(squares[0] + 1) × (squares[1] + 1)` of them), every
    /// square split along its `(0, 0)–(1, 1)` diagonal (the split [`super::Fractal`] uses). No species: it reads as
    /// one tile of depth 0 per square whose corners are the heights. `None` when the counts do not match, a square
    /// count is 0, or a number is not finite (or the spacing not positive).
    pub fn from_heights(origin: [f32; 2], spacing: f32, squares: [u32; 2], heights: Vec<f32>) -> Option<Terrain> {
        let count = (u64::from(squares[0]) + 1) * (u64::from(squares[1]) + 1);
        let numbers = spacing.is_finite() && spacing > 0.0 && origin.iter().all(|v| v.is_finite());
        if squares.contains(&0) || count != heights.len() as u64 || !numbers || !heights.iter().all(|h| h.is_finite()) {
            return None;
        }
        let lo = heights.iter().copied().fold(f32::INFINITY, f32::min);
        let hi = heights.iter().copied().fold(f32::NEG_INFINITY, f32::max);
        Some(Terrain {
            species: None,
            source: String::from("heights"),
            seed: 0,
            origin,
            tile_size: spacing,
            tiles: squares,
            depth: 0,
            corners: heights.clone(),
            params: Vec::new(),
            slots: None,
            spacing,
            squares,
            heights,
            anti_diagonal: vec![false; squares[0] as usize * squares[1] as usize],
            range: (lo, hi),
        })
    }

    /// Amplify every tile of `graph` and read the height grid off its triangles.
    #[allow(clippy::too_many_arguments)]
    pub fn build(
        graph: SpeciesGraph,
        source: String,
        seed: u64,
        origin: [f32; 2],
        tile_size: f32,
        tiles: [u32; 2],
        depth: u32,
        corners: Vec<f32>,
        mut params: Vec<(u16, f32)>,
    ) -> Result<Terrain, TerrainError> {
        let slot = |name: &'static str| graph.param_slot(name).ok_or(TerrainError::MissingParam(name));
        let slots = TileSlots {
            corners: [slot("h00")?, slot("h10")?, slot("h01")?, slot("h11")?],
            size: slot("size")?,
            depth: slot("depth")?,
            ox: slot("ox")?,
            oz: slot("oz")?,
        };
        if depth > super::MAX_TERRAIN_DEPTH || tiles[0] == 0 || tiles[1] == 0 {
            return Err(TerrainError::TooLarge(0));
        }
        let n = 1u32 << depth;
        let squares = [u64::from(tiles[0]) * u64::from(n), u64::from(tiles[1]) * u64::from(n)];
        let vertices = (squares[0] + 1).saturating_mul(squares[1] + 1);
        if vertices > super::MAX_TERRAIN_VERTICES {
            return Err(TerrainError::TooLarge(vertices));
        }
        let squares = squares.map(|s| s as u32);
        let expected = (tiles[0] as usize + 1) * (tiles[1] as usize + 1);
        if corners.len() != expected {
            return Err(TerrainError::Corners { expected, got: corners.len() });
        }
        if !corners.iter().all(|h| h.is_finite()) {
            return Err(TerrainError::NotFinite { x: origin[0], z: origin[1] });
        }
        let spacing = tile_size / n as f32;
        for axis in 0..2 {
            let exact = (0..=squares[axis]).all(|k| {
                let v = f64::from(origin[axis]) + f64::from(k) * f64::from(spacing);
                f64::from(v as f32) == v
            });
            if !exact {
                return Err(TerrainError::Inexact { origin: origin[axis], spacing });
            }
        }
        params.sort_by_key(|&(s, _)| s);
        let (vx, vz) = (squares[0] as usize + 1, squares[1] as usize + 1);
        let mut t = Terrain {
            species: None,
            source,
            seed,
            origin,
            tile_size,
            tiles,
            depth,
            corners,
            params,
            slots: Some(slots),
            spacing,
            squares,
            heights: vec![f32::NAN; vx * vz],
            anti_diagonal: vec![false; squares[0] as usize * squares[1] as usize],
            range: (0.0, 0.0),
        };
        let mut masks = vec![0u8; t.anti_diagonal.len()];
        let all: Vec<[u32; 2]> = (0..tiles[1]).flat_map(|tz| (0..tiles[0]).map(move |tx| [tx, tz])).collect();
        let instances: Vec<Instance> = all.iter().map(|&tile| t.tile_instance_with(&slots, tile, depth)).collect();
        let amplified = amplify_tiles(&graph, &instances, depth);
        // Merged in tile order, whatever the threads did, so the grid and the first error are deterministic.
        for (&tile, triangles) in all.iter().zip(amplified) {
            let [ox, oz] = t.tile_origin(tile);
            let [tx, tz] = tile;
            for triangle in triangles.map_err(|source| TerrainError::Amplify { tile, source })?.chunks_exact(3) {
                let mut corner = [[0u32; 2]; 3];
                for (c, v) in corner.iter_mut().zip(triangle) {
                    let [x, y, z] = match *v {
                        Vertex::Point(p) => p,
                        Vertex::NotTriangle { kind, points } => {
                            return Err(TerrainError::NotTriangle { tile, kind, points });
                        }
                    };
                    let (wx, wz) = (ox + x, oz + z);
                    if !y.is_finite() {
                        return Err(TerrainError::NotFinite { x: wx, z: wz });
                    }
                    let grid = |v: f32| {
                        let m = (f64::from(v) / f64::from(spacing)).round();
                        (m >= 0.0 && m <= f64::from(n) && m as f32 * spacing == v).then_some(m as u32)
                    };
                    let (Some(i), Some(j)) = (grid(x), grid(z)) else {
                        return Err(TerrainError::OffGrid { tile, x, z, spacing });
                    };
                    *c = [tx * n + i, tz * n + j];
                    let h = &mut t.heights[c[1] as usize * vx + c[0] as usize];
                    if h.is_nan() {
                        *h = y;
                    } else if h.to_bits() != y.to_bits() {
                        return Err(TerrainError::Crack { x: wx, z: wz, a: *h, b: y });
                    }
                }
                // The square the triangle covers, and which of its corners (00, 10, 01, 11) it leaves out.
                let i0 = corner.iter().map(|c| c[0]).min().expect("three corners");
                let j0 = corner.iter().map(|c| c[1]).min().expect("three corners");
                let square = |t: &Terrain| {
                    let [x, z] = t.vertex_position(i0, j0);
                    TerrainError::Coverage { x, z }
                };
                if corner.iter().any(|c| c[0] - i0 > 1 || c[1] - j0 > 1) || i0 >= squares[0] || j0 >= squares[1] {
                    return Err(square(&t));
                }
                let codes = corner.map(|c| (c[0] - i0) + 2 * (c[1] - j0));
                if codes[0] == codes[1] || codes[1] == codes[2] || codes[0] == codes[2] {
                    return Err(square(&t));
                }
                let missing = 6 - codes.iter().sum::<u32>();
                let m = &mut masks[j0 as usize * squares[0] as usize + i0 as usize];
                if *m & (1 << missing) != 0 {
                    return Err(square(&t));
                }
                *m |= 1 << missing;
            }
        }
        for (k, &m) in masks.iter().enumerate() {
            // Leaving out 10 and 01: both triangles hold the diagonal 00–11; leaving out 00 and 11: 10–01.
            match m {
                0b0110 => t.anti_diagonal[k] = false,
                0b1001 => t.anti_diagonal[k] = true,
                _ => {
                    let [x, z] = t.vertex_position(k as u32 % squares[0], k as u32 / squares[0]);
                    return Err(TerrainError::Coverage { x, z });
                }
            }
        }
        let lo = t.heights.iter().copied().fold(f32::INFINITY, f32::min);
        let hi = t.heights.iter().copied().fold(f32::NEG_INFINITY, f32::max);
        t.range = (lo, hi);
        t.species = Some(graph);
        Ok(t)
    }

    /// World (x, z) of a tile's corner with the smallest x and z.
    pub fn tile_origin(&self, tile: [u32; 2]) -> [f32; 2] {
        [self.origin[0] + tile[0] as f32 * self.tile_size, self.origin[1] + tile[1] as f32 * self.tile_size]
    }

    /// The instance of tile `tile` at recursion depth `depth` (lower it for a coarser level of detail: coarser
    /// depths give exactly the vertices of finer ones). Amplified from [`Terrain::species`] its triangles are in
    /// tile-local coordinates: translate them by [`Terrain::tile_origin`]. `None` for flat ground.
    pub fn tile_instance(&self, tile: [u32; 2], depth: u32) -> Option<Instance> {
        self.slots.as_ref().map(|s| self.tile_instance_with(s, tile, depth))
    }

    fn tile_instance_with(&self, s: &TileSlots, tile: [u32; 2], depth: u32) -> Instance {
        let [ox, oz] = self.tile_origin(tile);
        let row = self.tiles[0] as usize + 1;
        let corner = |dx: u32, dz: u32| self.corners[(tile[1] + dz) as usize * row + (tile[0] + dx) as usize];
        let mut params = self.params.clone();
        params.extend([
            (s.corners[0], corner(0, 0)),
            (s.corners[1], corner(1, 0)),
            (s.corners[2], corner(0, 1)),
            (s.corners[3], corner(1, 1)),
            (s.size, self.tile_size),
            (s.depth, depth as f32),
            (s.ox, ox),
            (s.oz, oz),
        ]);
        params.sort_by_key(|&(slot, _)| slot);
        Instance { seed: self.seed, params, detail: 0 }
    }

    /// Grid spacing, metres.
    pub fn spacing(&self) -> f32 {
        self.spacing
    }

    /// Grid squares per axis.
    pub fn squares(&self) -> [u32; 2] {
        self.squares
    }

    /// Number of triangles in the terrain mesh.
    pub fn triangle_count(&self) -> u64 {
        2 * u64::from(self.squares[0]) * u64::from(self.squares[1])
    }

    /// Lowest and highest vertex.
    pub fn height_range(&self) -> (f32, f32) {
        self.range
    }

    /// World (x, z) of grid vertex (i, j).
    pub fn vertex_position(&self, i: u32, j: u32) -> [f32; 2] {
        [self.origin[0] + i as f32 * self.spacing, self.origin[1] + j as f32 * self.spacing]
    }

    /// Height of grid vertex (i, j).
    pub fn vertex_height(&self, i: u32, j: u32) -> f32 {
        self.heights[j as usize * (self.squares[0] as usize + 1) + i as usize]
    }

    /// Whether grid square (i, j) is split along the diagonal from (1, 0) to (0, 1) rather than (0, 0)–(1, 1).
    pub fn anti_diagonal(&self, i: u32, j: u32) -> bool {
        self.anti_diagonal[j as usize * self.squares[0] as usize + i as usize]
    }

    /// The triangle under (x, z): its three grid vertices and barycentric weights, and the height gradient
    /// `(dh/du, dh/dv)` per grid square. Outside the grid, the nearest point on its edge.
    fn triangle(&self, x: f32, z: f32) -> ([[u32; 2]; 3], [f64; 3], [f64; 2]) {
        let locate = |v: f32, axis: usize| {
            let f = (f64::from(v) - f64::from(self.origin[axis])) / f64::from(self.spacing);
            let last = f64::from(self.squares[axis] - 1);
            let i = f.floor().clamp(0.0, last);
            (i as u32, (f - i).clamp(0.0, 1.0))
        };
        let ((i, u), (j, v)) = (locate(x, 0), locate(z, 1));
        let h = |di: u32, dj: u32| f64::from(self.vertex_height(i + di, j + dj));
        let c = |di: u32, dj: u32| [i + di, j + dj];
        if !self.anti_diagonal(i, j) {
            if v >= u {
                ([c(0, 0), c(0, 1), c(1, 1)], [1.0 - v, v - u, u], [h(1, 1) - h(0, 1), h(0, 1) - h(0, 0)])
            } else {
                ([c(0, 0), c(1, 0), c(1, 1)], [1.0 - u, u - v, v], [h(1, 0) - h(0, 0), h(1, 1) - h(1, 0)])
            }
        } else if u + v <= 1.0 {
            ([c(0, 0), c(1, 0), c(0, 1)], [1.0 - u - v, u, v], [h(1, 0) - h(0, 0), h(0, 1) - h(0, 0)])
        } else {
            ([c(1, 1), c(1, 0), c(0, 1)], [u + v - 1.0, 1.0 - v, 1.0 - u], [h(1, 1) - h(0, 1), h(1, 1) - h(1, 0)])
        }
    }

    /// Height of the triangle surface at (x, z): barycentric interpolation of the triangle's three vertex
    /// heights in f64, rounded to f32 — exactly the vertex's height at a vertex. Deterministic on every IEEE 754
    /// platform (no transcendental functions, a fixed order of operations).
    pub fn height(&self, x: f32, z: f32) -> f32 {
        let (v, w, _) = self.triangle(x, z);
        let h = |k: usize| f64::from(self.vertex_height(v[k][0], v[k][1]));
        (w[0] * h(0) + w[1] * h(1) + w[2] * h(2)) as f32
    }

    /// [`Terrain::height`] and [`Terrain::slope`] together, finding the triangle once.
    pub fn height_and_slope(&self, x: f32, z: f32) -> (f32, f32) {
        let (h, g2) = self.height_and_gradient2(x, z);
        (h, slope_degrees(g2))
    }

    /// [`Terrain::height`] and `|∇h|²` (the slope before its `atan`, see [`slope_degrees`]).
    pub fn height_and_gradient2(&self, x: f32, z: f32) -> (f32, f64) {
        let (v, w, g) = self.triangle(x, z);
        let h = |k: usize| f64::from(self.vertex_height(v[k][0], v[k][1]));
        ((w[0] * h(0) + w[1] * h(1) + w[2] * h(2)) as f32, self.gradient_squared(g))
    }

    /// The height gradient `(dh/dx, dh/dz)` of the triangle under (x, z).
    pub fn gradient(&self, x: f32, z: f32) -> [f32; 2] {
        let (_, _, g) = self.triangle(x, z);
        let s = f64::from(self.spacing);
        [(g[0] / s) as f32, (g[1] / s) as f32]
    }

    /// Slope of the triangle under (x, z), degrees from horizontal (`atan |∇h|`, through `libm`).
    pub fn slope(&self, x: f32, z: f32) -> f32 {
        let (_, _, g) = self.triangle(x, z);
        slope_degrees(self.gradient_squared(g))
    }

    /// `|∇h|²` in metres per metre from a gradient per grid square.
    fn gradient_squared(&self, g: [f64; 2]) -> f64 {
        let s = f64::from(self.spacing);
        let (gx, gz) = (g[0] / s, g[1] / s);
        gx * gx + gz * gz
    }
}

/// A slope in degrees from `|∇h|²`: `atan √g2 · 180 / π` in f64 through `libm`, rounded to f32.
pub fn slope_degrees(gradient2: f64) -> f32 {
    (libm::atan(gradient2.sqrt()) * (180.0 / std::f64::consts::PI)) as f32
}
