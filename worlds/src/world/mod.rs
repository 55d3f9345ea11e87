//! Worlds: a manifest (bounds, cells, seed, fractal terrain, species table, populations) loaded into a [`World`]
//! whose instances are placed deterministically, sorted by cell and addressed by id (seed 001 §3.4 and §4).
//!
//! # The manifest format (`.world`)
//!
//! Line oriented; `#` starts a comment; blocks open with `{` at the end of a line and close with `}` on a line of
//! its own. Statements may come in any order, except that populations are expanded in file order.
//!
//! ```text
//! world forest                          # name (optional; default: the file name without extension)
//! seed 48879                            # world seed: a u64, decimal or 0x… hexadecimal (required)
//! bounds -1024 -1024 1024 1024          # min x, min z, max x, max z in metres; +Y is up (required)
//! cell 64                               # cell size in metres, a power of two from 1 to 4096 (required)
//!
//! terrain terrain {                     # the terrain species: a library name, or a "path" relative to the file
//!   tile 512                            # tile edge in metres (default: one square tile over the bounds)
//!   depth 7                             # recursion depth of every tile: 2·4^depth triangles per tile
//!   seed 7                              # the terrain's instance seed (default: derived from the world seed)
//!   corners 20 40 60 80 90              # heights at the tile corners: one line per row from min z,
//!   corners 30 50 ...                   #   min x to max x (default: all 0)
//!   param dimension = 2.2               # any other parameter of the terrain species
//!   param relief = 80
//! }
//!
//! species conifer "../species/conifer.species"   # table name, then a "path" (relative) or a library name;
//! species broadleaf monopodial                   # the table order is the species id
//!
//! instance broadleaf at 12.5 -40 height=25       # one instance at (x, z), with parameter values
//!
//! scatter conifer {                     # a distribution rule, expanded at load
//!   spacing 5                           # Poisson-disk minimum distance between this rule's instances, metres
//!   density 0.9                         # fraction of a full Poisson-disk packing kept, 0..1 (default 1)
//!   altitude 90 140 ..                  # density ramp over terrain height (below)
//!   slope .. 25 40                      # density ramp over terrain slope in degrees
//!   region -1024 -1024 0 1024           # restrict to a rectangle (default: the bounds)
//!   avoid broadleaf 3                   # stay 3 m from instances of `broadleaf` placed before this rule
//!   param height = 10 .. 24 step 0.5    # per instance: uniform in the range (on multiples of `step` from 10)
//!   param spread = 0.3                  # or a constant
//! }
//! ```
//!
//! Edits baked into a manifest (`canopy world bake`) change what the statements placed, after all of them:
//!
//! ```text
//! fell conifer at 31.390625 4.21875     # remove the conifer at exactly this position (on the position grid)
//! set conifer at 12 40 height=30        # give it these parameter values (others keep theirs)
//! ```
//!
//! Each applies to the first instance of that species at exactly that position in its cell; one that finds none
//! changes nothing. A felled instance still spaced its neighbours (the statements placed it before it was felled).
//!
//! A ramp `A B .. C D` is 0 below A, rises linearly to 1 at B, stays 1 to C and falls to 0 at D; one number on a
//! side is a hard edge (`A .. D`), none an open end (`.. 200`).
//!
//! Cells are aligned to the origin: cell `(i, j)` covers `[i·s, (i+1)·s) × [j·s, (j+1)·s)`. The bounds must be
//! multiples of the position step `s / POSITION_STEPS` and lie within `±s · POSITION_STEPS`, where every position
//! on that grid is exact in f32. Without a `terrain` the ground is flat at height 0. A terrain species must declare
//! the tile parameters `h00 h10 h01 h11 size depth ox oz` (as `worlds/species/terrain.species` does) and emit a
//! crack-free grid of triangles; the world sets them for every tile. Species and terrain paths are relative to the
//! manifest; a manifest parsed without a directory may use library names only.
//!
//! # Expansion: cells as a function
//!
//! A cell's placements are a pure function of the manifest and the cell ([`World::expand_cell`]): no pass over
//! the whole world, no global numbering, the same bits on every machine whatever cells were expanded before, in
//! what order, on which thread, alone or in a block ([`World::expand_cells`]). Worlds of at most [`EAGER_CELLS`]
//! cells are also expanded whole at load into [`World::instances`] (by the same function); larger ones only on
//! demand. An instance is identified by its cell and its index in the cell ([`InstanceId`]), and its seed derives
//! from that identity ([`World::instance_seed`]).
//!
//! Within a cell, placements come in file order of their statements: `instance` lines (indexed by cell at load),
//! then each `scatter` rule's darts in row-major order of their background cells.
//!
//! A `scatter` rule is a Poisson-disk process on a background grid of cells of `g = ⌈spacing / √2⌉` (rounded up
//! to the position grid) anchored at the world's origin, run in [`ROUNDS`] rounds of proposals and priorities — a
//! local rule, so a bounded neighbourhood (its halo, at most [`MARGIN`] background cells) decides every dart:
//! - in each round, every background cell without a dart tries up to [`ATTEMPTS`] positions on the position grid
//!   inside it and proposes the first that keeps `spacing` from every placed dart;
//! - a proposal is placed if it outranks every other proposal closer than `spacing` (by a 32-bit priority, then
//!   by background cell in row-major order), so two placed darts are never closer than `spacing`.
//!
//! The process is read through corner-coloured tiles (Lagae & Dutré's procedural object distribution function):
//! tiles of `2 · MARGIN` background cells whose corners get one of [`COLOURS`] colours from a hash of the corner's
//! lattice position; the random words of the background cells in the square of one tile side centred on a corner
//! depend only on its colour, so a tile's darts are a function of its four corner colours — `COLOURS⁴` variants
//! per rule, each computed once, on first use, over the 2 × 2 corner squares around it. Neighbouring tiles read
//! the same corner squares: one process over the whole plane, spacing across every tile border. Expanding a
//! rectangle looks its darts up, with no halo.
//!
//! Each dart inside a rule's region is then dropped if it lies closer than an `avoid` distance to an instance of
//! an earlier statement, and kept with probability `density · altitude(height) · slope(slope)` — a dropped or
//! thinned-out dart still spaced its neighbours, so the density is the fraction of a full packing kept (about 0.62
//! darts per spacing² on open ground). A rule whose density is 0 over all the ground it could reach places nothing.
//! Expanding a rectangle computes every rule an `avoid` names over the rectangle grown by that distance (the chain
//! is followed back through the file). One cell's work is bounded at load ([`MAX_CELL_WORK`] background cells, the
//! tile variants it may compute included), and so is the number of instances a cell can hold
//! ([`MAX_CELL_INSTANCES`]).
//!
//! Randomness is ChaCha8 keyed by the world seed ([`crate::rng::InstanceRng`]) and read by address: rule key
//! `R = child_key(fnv1a64(species name), n)` for the `n`-th rule of that species (editing a rule moves no other
//! rule's instances, except through `avoid`). Corner `(a, b)` has colour
//! `mix64(child_key(child_key(R, 2), a) ^ b) mod COLOURS`; background cell `(i, j)` of a corner square of colour `c`
//! reads stream `child_key(child_key(child_key(R, 0), c), i << 32 | j)`: round `r`'s positions are words
//! `8r .. 8r + 7` (low and high 16 bits pick one of the `g` grid positions per axis: `(bits · g) >> 16`), its
//! priority word `8r + 7`. A dart at steps `(x, z)` reads stream `child_key(child_key(child_key(R, 1), x), z)`: its
//! keep draw is word 0 and its `n`-th parameter rule word `1 + n`. Floats come from words by
//! [`crate::eval::unit_f32`]. Parameter values equal to a constant species default are not stored. (Until issue 30
//! the process ran over every expansion's halo, and `avoid` moved a dart instead of dropping it: a cell cost ~11
//! ms, and the embedded worlds' understory `avoid` distances were longer.)
//!
//! # Terrain
//!
//! `terrain NAME { … }` names a terrain species, amplified tile by tile into a height grid at load (bounded by
//! [`MAX_TERRAIN_VERTICES`]). `terrain fractal { … }` is the terrain as a function ([`Fractal`]): `tile` is the
//! control lattice's spacing, `depth` its levels of subdivision (up to [`MAX_FRACTAL_DEPTH`]), `corners` rows the
//! control heights (from min z, min x to max x; the edge values extend beyond them), `seed`, and `param
//! dimension = …` and `param relief = …`; heights anywhere are computed on demand, by client and server alike.
//! Every count, size and extent read from the file is bounded (the `MAX_` constants below).

mod cells;
mod cover;
pub mod far;
mod far_edits;
mod fractal;
mod ground;
mod manifest;
pub mod par;
mod populate;
mod source;
mod summary;
mod terrain;
mod tiles;

use std::ops::Range;
use std::path::Path;
use std::sync::Arc;

use canopy_protocol::SpeciesGraph;

use crate::amplify::Instance;
use crate::diag::{Diagnostic, Diagnostics, SourceFile};

pub use cells::{MAX_CELL_INSTANCES, MAX_CELL_WORK, Populations, REGION_BLOCK, ROUNDS};
pub use cover::{Cover, GroundCover, SNOW_ABOVE, SNOW_FULL, TREE_HEIGHT};
pub use far::{
    DEFAULT_CACHE_NODES, LEAF_BLOCK_LEVEL, LeafEdit, MAX_CORRECTED_CELLS, PACKING, Summaries, aggregate, summary_bytes,
};
pub use fractal::{Fractal, FractalError, MAX_FRACTAL_DEPTH, Patch};
pub use ground::Ground;
pub use populate::{FRACTAL, ParamValue, Ramp, ScatterRule, SlopeRamp};
pub use summary::Estimate;
pub use terrain::{STEPS_PER_SQUARE, TILE_PARAMS, Terrain, TerrainError, slope_degrees};
pub use tiles::{ATTEMPTS, COLOURS, MARGIN};

/// Most entries in the species table (ids fit a byte): the protocol's per-world species limit.
pub use canopy_protocol::netlimits::MAX_SPECIES;
/// Deepest terrain recursion: the protocol's limit for the terrain it describes.
pub use canopy_protocol::netlimits::MAX_TERRAIN_DEPTH;
/// An instance's identity: its cell and its index within the cell (no global numbering).
pub use canopy_protocol::record::InstanceId;
/// Positions are snapped to `cell_size / POSITION_STEPS` per axis within their cell: a position is its cell and
/// two integers below `POSITION_STEPS` (12 bits each), as the protocol's instance records carry them.
pub use canopy_protocol::record::POSITION_STEPS;

/// Most cells in a world's bounds: 2^21 per axis (±2^20 around the origin).
pub const MAX_CELLS: u64 = 1 << 42;
/// A world's bounds lie within ±`MAX_CELL_COORD` cells of the origin on each axis (64 m cells: ±67,108 km), where
/// instance ids ([`InstanceId`]: 24 bits per axis) name every cell and positions are exact in f64.
pub const MAX_CELL_COORD: u32 = 1 << 20;
/// Worlds of at most this many cells are expanded whole at load ([`World::instances`]); larger ones only cell by
/// cell, on demand ([`World::expand_cell`]).
pub const EAGER_CELLS: usize = 4096;
/// Most `scatter` rules.
pub const MAX_RULES: usize = 1024;
/// Most vertices in the terrain's height grid.
pub const MAX_TERRAIN_VERTICES: u64 = 1 << 22;
/// Smallest and largest cell size, metres.
pub const CELL_SIZE_RANGE: (f32, f32) = (1.0, 4096.0);
/// Largest `avoid` distance, metres.
pub const MAX_AVOID: f32 = 1000.0;

/// The world's extent on the ground plane (x, z), metres: `min` inclusive, `max` exclusive.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Bounds {
    /// Smallest x and z.
    pub min: [f32; 2],
    /// Largest x and z (exclusive).
    pub max: [f32; 2],
}

impl Bounds {
    /// Whether (x, z) lies inside (in f64: positions far from the origin are not f32s).
    pub fn contains(&self, x: f64, z: f64) -> bool {
        let [x0, z0] = self.min.map(f64::from);
        let [x1, z1] = self.max.map(f64::from);
        x >= x0 && x < x1 && z >= z0 && z < z1
    }

    /// Width (x) and depth (z), metres.
    pub fn size(&self) -> [f32; 2] {
        [self.max[0] - self.min[0], self.max[1] - self.min[1]]
    }

    /// Width and depth in f64, exact: an f32 size rounds bounds as wide as the coordinate range (134,217,728 m).
    pub fn extent(&self) -> [f64; 2] {
        [0, 1].map(|a| f64::from(self.max[a]) - f64::from(self.min[a]))
    }

    /// Area, square metres.
    pub fn area(&self) -> f64 {
        let [w, d] = self.extent();
        w * d
    }
}

/// One entry of the species table; its index is the species id.
#[derive(Clone, Debug, PartialEq)]
pub struct WorldSpecies {
    /// The table name (`species NAME …`).
    pub name: String,
    /// The compiled species.
    pub graph: SpeciesGraph,
    /// Where it came from: the file as shown in diagnostics, or `library:NAME`.
    pub source: String,
}

/// One instance record: species, position on the ground and the parameter values that differ from the defaults.
#[derive(Clone, Debug, PartialEq)]
pub struct Placement {
    /// Species id (index into [`World::species`]).
    pub species: u16,
    /// Position, on the [`POSITION_STEPS`] grid of its cell: in f64, exact in every cell a world may have (±2^20
    /// cells per axis; f32 holds the grid only within ±4,096 cells).
    pub x: f64,
    /// Position, on the [`POSITION_STEPS`] grid of its cell.
    pub z: f64,
    /// `(slot, value)` sorted by slot: only values that differ from the species defaults.
    pub params: Vec<(u16, f32)>,
}

/// A cell of the world's grid: cell `(x, z)` covers `[x·s, (x+1)·s) × [z·s, (z+1)·s)` for cell size `s`.
#[derive(Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Debug)]
pub struct CellKey {
    /// Column.
    pub x: i32,
    /// Row.
    pub z: i32,
}

/// A loaded world: everything the server streams and clients amplify.
#[derive(Clone, Debug)]
pub struct World {
    /// Name (the manifest's `world` statement or its file name).
    pub name: String,
    /// World seed.
    pub seed: u64,
    /// Extent on the ground plane.
    pub bounds: Bounds,
    /// Cell edge, metres; cells are the unit of area of interest.
    pub cell_size: f32,
    /// The species table; the index is the species id.
    pub species: Vec<WorldSpecies>,
    /// Every instance of a world of at most [`EAGER_CELLS`] cells, sorted by (cell.z, cell.x, then index in the
    /// cell); empty for a larger world, which is expanded cell by cell ([`World::expand_cell`]).
    pub instances: Vec<Placement>,
    /// The terrain species' height grid (flat for a world whose terrain is a [`Fractal`]).
    pub terrain: Terrain,
    /// The terrain as a function, for `terrain fractal { … }`.
    pub fractal: Option<Fractal>,
    /// The populations indexed for expansion cell by cell.
    pub populations: Populations,
    /// The `scatter` rules, in file order.
    pub rules: Vec<ScatterRule>,
    /// Number of `instance` statements.
    pub explicit_instances: u32,
    /// The manifest text the world was parsed from: its world function, which a client holding the species table
    /// builds the same world from ([`World::from_function`]).
    pub function: Arc<str>,
    /// The first cell in bounds (smallest x and z).
    cell_min: CellKey,
    /// Cells in bounds per axis.
    cell_dims: [u32; 2],
    /// `cell_starts[i]..cell_starts[i + 1]`: the instances of the `i`-th cell in row-major order.
    cell_starts: Vec<u32>,
}

/// The embedded default world's manifest.
pub const DEFAULT_WORLD: &str = include_str!("../../forest/forest.world");
/// The embedded large world's manifest (102.4 km × 102.4 km, expanded cell by cell).
pub const HIGHLANDS_WORLD: &str = include_str!("../../highlands/highlands.world");
/// The worlds compiled in, by name: `(name, manifest)`; the first is the default.
pub const EMBEDDED_WORLDS: [(&str, &str); 2] = [("forest", DEFAULT_WORLD), ("highlands", HIGHLANDS_WORLD)];

impl World {
    /// Load a manifest file; species paths are relative to its directory.
    pub fn load(path: &Path) -> Result<World, Diagnostics> {
        let src = crate::load::read_source(path).map_err(|e| Diagnostics(vec![crate::load::file_diag(path, e)]))?;
        let base = path.parent().unwrap_or(Path::new("."));
        World::parse(&src, Some(base))
    }

    /// Parse a manifest. Species paths resolve against `base_dir`; without one, only library names are allowed.
    pub fn parse(src: &SourceFile, base_dir: Option<&Path>) -> Result<World, Diagnostics> {
        match base_dir {
            Some(dir) => World::parse_with(src, &source::Files { base: dir }, true),
            None => World::parse_with(src, &source::NoFiles, true),
        }
    }

    /// The world of a world function (the manifest a server sends clients that expand cells themselves): its
    /// species statements are `species` in order (the welcome's table, by id) and its terrain species, if any,
    /// `terrain`; no file is read. Never materialised: cells are expanded as they are asked for.
    pub fn from_function(
        name: &str,
        manifest: &str,
        species: &[SpeciesGraph],
        terrain: Option<&SpeciesGraph>,
    ) -> Result<World, Diagnostics> {
        let src = SourceFile::new(format!("{name}.world"), manifest);
        World::parse_with(&src, &source::Table { species, terrain }, false)
    }

    /// The embedded default world, `worlds/forest/` (compiled in: touches no filesystem).
    pub fn default_world() -> World {
        World::embedded("forest").expect("the embedded default world is tested to load")
    }

    /// An embedded world by name ([`EMBEDDED_WORLDS`]: `worlds/NAME/NAME.world`, compiled in with its species);
    /// `None` for a name that is not embedded.
    pub fn embedded(name: &str) -> Option<World> {
        let (dir, text) = EMBEDDED_WORLDS.iter().find(|(n, _)| *n == name)?;
        let src = SourceFile::new(format!("worlds/{dir}/{dir}.world"), *text);
        let world = World::parse_with(&src, &source::Embedded { dir }, true)
            .unwrap_or_else(|d| panic!("the embedded world `{name}` is tested to load:\n{d}"));
        Some(world)
    }

    /// Parse with species from `files`; `eager`: materialise a small world ([`EAGER_CELLS`]) at once.
    fn parse_with(src: &SourceFile, files: &dyn source::Resolver, eager: bool) -> Result<World, Diagnostics> {
        let mut diags = Vec::new();
        let m = manifest::parse(src, &mut diags);
        let world = populate::build(src, &m, files, &mut diags);
        // The manifest's own diagnostics first, in order of position; then each species file's.
        diags.sort_by(|a, b| {
            let key = |d: &Diagnostic| (d.file != src.name, d.file.clone(), d.line, d.col);
            key(a).cmp(&key(b))
        });
        match world {
            Some(mut w) if diags.is_empty() => {
                w.function = Arc::from(src.text.as_str());
                Ok(if eager { w.materialise() } else { w })
            }
            _ => {
                if diags.is_empty() {
                    diags.push(src.diag(0..0, "the world could not be built"));
                }
                Err(Diagnostics(diags))
            }
        }
    }

    /// Assemble a world from its parts, expanding nothing yet.
    #[allow(clippy::too_many_arguments)]
    fn assemble(
        name: String,
        seed: u64,
        bounds: Bounds,
        cell_size: f32,
        species: Vec<WorldSpecies>,
        terrain: Terrain,
        fractal: Option<Fractal>,
        rules: Vec<ScatterRule>,
        populations: Populations,
        explicit_instances: u32,
    ) -> World {
        // In f64: `max` minus a step is not an f32 far from the origin.
        let cell = |v: f64| (v / f64::from(cell_size)).floor() as i32;
        let cell_min = CellKey { x: cell(bounds.min[0].into()), z: cell(bounds.min[1].into()) };
        // `max` is exclusive: the last cell holds `max` minus one position step.
        let step = f64::from(cell_size) / f64::from(POSITION_STEPS);
        let cell_max = CellKey { x: cell(f64::from(bounds.max[0]) - step), z: cell(f64::from(bounds.max[1]) - step) };
        let cell_dims = [(cell_max.x - cell_min.x + 1) as u32, (cell_max.z - cell_min.z + 1) as u32];
        World {
            name,
            seed,
            bounds,
            cell_size,
            species,
            instances: Vec::new(),
            terrain,
            fractal,
            populations,
            rules,
            explicit_instances,
            function: Arc::from(""),
            cell_min,
            cell_dims,
            cell_starts: Vec::new(),
        }
    }

    /// Expand every cell of a world of at most [`EAGER_CELLS`] cells into [`World::instances`] (in blocks of
    /// [`REGION_BLOCK`] cells, each worked on by the available cores: the result does not depend on either).
    fn materialise(mut self) -> World {
        if self.cell_count() > EAGER_CELLS as u64 {
            return self;
        }
        let (min, [w, d]) = (self.cell_min, self.cell_dims.map(|v| v as i32));
        let expanded = cells::expand(&self, min, CellKey { x: min.x + w - 1, z: min.z + d - 1 });
        let mut starts = vec![0u32];
        let mut instances = Vec::new();
        for (_, list) in expanded {
            instances.extend(list);
            starts.push(instances.len() as u32);
        }
        self.instances = instances;
        self.cell_starts = starts;
        self
    }

    /// Whether every instance is in [`World::instances`] (a world of at most [`EAGER_CELLS`] cells).
    pub fn is_materialised(&self) -> bool {
        !self.cell_starts.is_empty()
    }

    /// Number of cells in bounds (up to 2^42: a u64 on every target).
    pub fn cell_count(&self) -> u64 {
        u64::from(self.cell_dims[0]) * u64::from(self.cell_dims[1])
    }

    /// Cells in bounds per axis (x, z).
    pub fn cell_dims(&self) -> [u32; 2] {
        self.cell_dims
    }

    /// The cell in bounds with the smallest x and z.
    pub fn first_cell(&self) -> CellKey {
        self.cell_min
    }

    /// Row-major index of a cell in bounds.
    pub fn cell_index(&self, c: CellKey) -> Option<usize> {
        let dx = i64::from(c.x) - i64::from(self.cell_min.x);
        let dz = i64::from(c.z) - i64::from(self.cell_min.z);
        let [w, d] = self.cell_dims.map(i64::from);
        ((0..w).contains(&dx) && (0..d).contains(&dz)).then(|| (dz * w + dx) as usize)
    }

    /// Whether a cell lies (at least partly) in bounds.
    pub fn contains_cell(&self, c: CellKey) -> bool {
        self.cell_index(c).is_some()
    }

    /// The cell holding (x, z).
    pub fn cell_of(&self, x: f64, z: f64) -> CellKey {
        let s = f64::from(self.cell_size);
        CellKey { x: (x / s).floor() as i32, z: (z / s).floor() as i32 }
    }

    /// The corner of a cell with the smallest x and z (exact: a multiple of the cell size within ±2^26 cells).
    pub fn cell_origin(&self, c: CellKey) -> [f32; 2] {
        [c.x as f32 * self.cell_size, c.z as f32 * self.cell_size]
    }

    /// Every cell in bounds, row-major (z, then x): the order of [`World::instances`].
    pub fn cells(&self) -> impl Iterator<Item = CellKey> + '_ {
        let (min, [w, d]) = (self.cell_min, self.cell_dims);
        (0..d as i32).flat_map(move |z| (0..w as i32).map(move |x| CellKey { x: min.x + x, z: min.z + z }))
    }

    /// The ids of the instances in a cell (contiguous; empty for a cell out of bounds).
    pub fn cell_instances(&self, c: CellKey) -> Range<u32> {
        match self.cell_index(c).filter(|_| self.is_materialised()) {
            Some(i) => self.cell_starts[i]..self.cell_starts[i + 1],
            None => 0..0,
        }
    }

    /// The placements of one cell, in the order of their index in the cell (an instance is identified by its
    /// cell and that index): a pure function of the manifest and the cell, the same whichever cells were asked for
    /// before. Empty for a cell out of bounds.
    pub fn expand_cell(&self, c: CellKey) -> Vec<Placement> {
        if self.is_materialised() {
            let r = self.cell_instances(c);
            return self.instances[r.start as usize..r.end as usize].to_vec();
        }
        self.expand_cells(c, c).pop().map(|(_, v)| v).unwrap_or_default()
    }

    /// The placements of every cell in `c0 ..= c1` (row-major), computed from the manifest — whether or not the
    /// world is materialised, so this is the function itself; cells out of bounds are empty.
    pub fn expand_cells(&self, c0: CellKey, c1: CellKey) -> Vec<(CellKey, Vec<Placement>)> {
        if c0.x > c1.x || c0.z > c1.z {
            return Vec::new();
        }
        cells::expand(self, c0, c1)
    }

    /// The edge of one position step, `cell_size / POSITION_STEPS` metres.
    pub fn position_step(&self) -> f32 {
        canopy_protocol::record::position_step(self.cell_size)
    }

    /// An instance's position as its cell and its steps within the cell (each below [`POSITION_STEPS`]):
    /// `dequantize` gives the position back bit for bit. Like every method taking an id, it panics if `id` is not
    /// below `instances.len()` (ids come from [`World::cell_instances`]).
    pub fn quantize(&self, id: u32) -> (CellKey, [u16; 2]) {
        let p = &self.instances[id as usize];
        let c = self.cell_of(p.x, p.z);
        (c, self.steps(c, p))
    }

    /// A placement's steps within cell `c` (each below [`POSITION_STEPS`]), as its record carries them: exact for
    /// a placement of that cell, wherever the cell lies.
    pub fn steps(&self, c: CellKey, p: &Placement) -> [u16; 2] {
        let [ox, oz] = self.cell_origin(c);
        let q = |v: f64, o: f32| canopy_protocol::record::quantize(v, o.into(), self.cell_size);
        [q(p.x, ox), q(p.z, oz)]
    }

    /// The position of steps `q` within cell `c`: `cell_origin + q · cell_size / POSITION_STEPS`, exact in f64 (in
    /// every cell a world may have; the protocol's f32 `dequantize` is exact within ±4,096 cells).
    pub fn dequantize(&self, c: CellKey, q: [u16; 2]) -> [f64; 2] {
        let [ox, oz] = self.cell_origin(c);
        let step = f64::from(self.position_step());
        [f64::from(ox) + f64::from(q[0]) * step, f64::from(oz) + f64::from(q[1]) * step]
    }

    /// The instance seed of the instance `id` names: [`instance_seed`]`(world seed, id)`.
    pub fn instance_seed(&self, id: InstanceId) -> u64 {
        instance_seed(self.seed, id)
    }

    /// The identity of [`World::instances`]`[index]`: its cell and its index in the cell (from
    /// [`World::cell_instances`]).
    ///
    /// # Panics
    ///
    /// If `index` is not below `instances.len()`, or the instance is not among the first 65,536 of its cell (the
    /// protocol's limit on a cell).
    pub fn instance_id(&self, index: u32) -> InstanceId {
        let p = &self.instances[index as usize];
        let c = self.cell_of(p.x, p.z);
        let range = self.cell_instances(c);
        debug_assert!(range.contains(&index), "instance {index} is not in its cell's range {range:?}");
        let in_cell = u16::try_from(index - range.start).expect("a cell holds at most 65,536 instances");
        // A world's cells lie within ±MAX_CELL_COORD cells of the origin, inside what ids can name.
        InstanceId::new(canopy_protocol::CellCoord::new(c.x, c.z), in_cell).expect("a world's cells can be named")
    }

    /// The index in [`World::instances`] of the instance `id` names; `None` if its cell has no such instance.
    /// The inverse of [`World::instance_id`].
    pub fn index_of(&self, id: InstanceId) -> Option<u32> {
        let c = id.cell();
        let range = self.cell_instances(CellKey { x: c.x, z: c.z });
        let index = range.start.checked_add(u32::from(id.index()))?;
        range.contains(&index).then_some(index)
    }

    /// [`World::instances`]`[index]` at a detail level: the seed of its [`World::instance_id`] and its stored
    /// parameter values.
    pub fn instance(&self, index: u32, detail: u8) -> Instance {
        let params = self.instances[index as usize].params.clone();
        Instance { seed: self.instance_seed(self.instance_id(index)), params, detail }
    }

    /// Terrain height at (x, z): the height of the terrain species' triangle surface (see [`Terrain::height`]).
    pub fn height(&self, x: f32, z: f32) -> f32 {
        match &self.fractal {
            Some(f) => f.height(f64::from(x), f64::from(z)),
            None => self.terrain.height(x, z),
        }
    }

    /// Terrain height and slope (degrees) at (x, z).
    pub fn height_and_slope(&self, x: f32, z: f32) -> (f32, f32) {
        let (h, g2) = self.height_and_gradient2(x, z);
        (h, slope_degrees(g2))
    }

    /// Height and `|∇h|²` at (x, z): the slope before its `atan` ([`slope_degrees`]), for [`SlopeRamp`]s.
    pub fn height_and_gradient2(&self, x: f32, z: f32) -> (f32, f64) {
        match &self.fractal {
            Some(f) => f.height_and_gradient2(f64::from(x), f64::from(z)),
            None => self.terrain.height_and_gradient2(x, z),
        }
    }

    /// An instance's position: x, the terrain height there, z, in f32 world metres (what a renderer draws; exact
    /// within ±4,096 cells of the origin, rounded farther out: materialised worlds lie well inside).
    pub fn position(&self, id: u32) -> [f32; 3] {
        let p = &self.instances[id as usize];
        let (x, z) = (p.x as f32, p.z as f32);
        [x, self.height(x, z), z]
    }

    /// The id of the species with this table name.
    pub fn species_id(&self, name: &str) -> Option<u16> {
        self.species.iter().position(|s| s.name == name).map(|i| i as u16)
    }

    /// Instances per species id.
    pub fn species_counts(&self) -> Vec<u32> {
        let mut counts = vec![0u32; self.species.len()];
        for p in &self.instances {
            counts[p.species as usize] += 1;
        }
        counts
    }

    /// The distinct stored values of parameter `slot` among the instances of `species`, ascending (a stepped
    /// `param` range gives a short list: a palette a compact encoding can index).
    pub fn param_values(&self, species: u16, slot: u16) -> Vec<f32> {
        let bits: std::collections::BTreeSet<u32> = self
            .instances
            .iter()
            .filter(|p| p.species == species)
            .flat_map(|p| p.params.iter().filter(|&&(s, _)| s == slot).map(|&(_, v)| v.to_bits()))
            .collect();
        let mut values: Vec<f32> = bits.into_iter().map(f32::from_bits).collect();
        values.sort_by(f32::total_cmp);
        values
    }
}

/// The seed of the instance `id` names in a world of seed `world_seed`: `rng::child_key(world seed, id.0)` =
/// `mix64(seed ^ mix64(id.0 + 0x9e37_79b9_7f4a_7c15))` with SplitMix64's finaliser `mix64` ([`crate::rng::mix64`]),
/// `id.0` packing the cell and the index in the cell ([`InstanceId`]). A pure function of the world seed and the
/// (cell, index), so a client that holds the world's seed (from the welcome) but not the world, and a server or
/// world that expands cells lazily, derive the same seed without any global numbering.
pub fn instance_seed(world_seed: u64, id: InstanceId) -> u64 {
    crate::rng::child_key(world_seed, id.0)
}
