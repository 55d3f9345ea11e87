//! Building a [`World`] from a parsed manifest: the species table, the terrain, and the populations — explicit
//! instances and `scatter` rules expanded by grid-accelerated Poisson-disk dart throwing, thinned by density over
//! altitude and slope (the algorithm and its random streams are described in [`crate::world`]).

use canopy_protocol::SpeciesGraph;

use super::manifest::{Manifest, Population, SourceRef, Span};
use super::source::Resolver;
use super::terrain::{Summary, TILE_PARAMS, Terrain};
use super::{
    Bounds, MAX_CELLS, MAX_INSTANCES, MAX_RULE_CELLS, MAX_RULES, MAX_SPECIES, MAX_TERRAIN_VERTICES, POSITION_STEPS,
    Placement, SCATTER_ATTEMPTS, World, WorldSpecies,
};
use crate::amplify::unknown_param;
use crate::diag::{Diagnostic, SourceFile};
use crate::eval::unit_f32;
use crate::load::parse_source;
use crate::primitive::Fnv;
use crate::rng::{InstanceRng, child_key, mix64};

/// Salt of the default terrain seed: `mix64(world seed ^ TERRAIN_SALT)`.
pub const TERRAIN_SALT: u64 = 0x7465_7272_6169_6e00;

/// The default terrain depth (the terrain species' own default at full detail).
pub const DEFAULT_TERRAIN_DEPTH: u32 = 7;

/// A density ramp over a value (altitude in metres, slope in degrees): 0 below `a`, rising linearly to 1 at `b`,
/// 1 up to `c`, falling linearly to 0 at `d`. Ends may be infinite.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Ramp {
    /// Where the ramp starts rising.
    pub a: f32,
    /// Where it reaches 1.
    pub b: f32,
    /// Where it starts falling.
    pub c: f32,
    /// Where it reaches 0.
    pub d: f32,
}

impl Ramp {
    /// 1 everywhere.
    pub const ALL: Ramp = Ramp { a: f32::NEG_INFINITY, b: f32::NEG_INFINITY, c: f32::INFINITY, d: f32::INFINITY };

    /// The greatest value over `[lo, hi]` (monotone on each side of the plateau `[b, c]`).
    pub fn max_over(&self, [lo, hi]: [f32; 2]) -> f32 {
        if lo <= self.c && hi >= self.b {
            1.0
        } else if hi < self.b {
            self.at(hi)
        } else {
            self.at(lo)
        }
    }

    /// The ramp's value at `v`, in [0, 1].
    pub fn at(&self, v: f32) -> f32 {
        if !(v >= self.a && v <= self.d) {
            0.0
        } else if v < self.b {
            (v - self.a) / (self.b - self.a)
        } else if v > self.c {
            (self.d - v) / (self.d - self.c)
        } else {
            1.0
        }
    }
}

/// A parameter value of a `scatter` rule.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum ParamValue {
    /// The same value for every instance.
    Constant(f32),
    /// Uniform over `lo ..= hi` (with a step: on `lo + k · step`, k = 0, 1, … while ≤ hi).
    Range {
        /// Low end.
        lo: f32,
        /// High end.
        hi: f32,
        /// Spacing of the values, if quantised.
        step: Option<f32>,
    },
}

/// Most distinct values of a stepped range.
pub const MAX_RANGE_STEPS: f64 = 16_777_216.0;

impl ParamValue {
    /// The value drawn by ChaCha8 word `bits`: with `u = unit_f32(bits)` in [0, 1), `lo + (hi - lo) · u` in f32,
    /// or with a step `lo + floor(u · n) · step` in f64 rounded to f32, `n = floor((hi - lo) / step) + 1`.
    pub fn value(&self, bits: u32) -> f32 {
        match *self {
            ParamValue::Constant(v) => v,
            ParamValue::Range { lo, hi, step: None } => lo + (hi - lo) * unit_f32(bits),
            ParamValue::Range { lo, hi, step: Some(step) } => {
                let n = Self::levels(lo, hi, step);
                let k = (f64::from(unit_f32(bits)) * n).floor();
                (f64::from(lo) + k * f64::from(step)) as f32
            }
        }
    }

    fn levels(lo: f32, hi: f32, step: f32) -> f64 {
        ((f64::from(hi) - f64::from(lo)) / f64::from(step)).floor() + 1.0
    }
}

/// A `scatter` rule, resolved against the species table.
#[derive(Clone, Debug, PartialEq)]
pub struct ScatterRule {
    /// Species id.
    pub species: u16,
    /// Poisson-disk minimum distance between the rule's instances, metres.
    pub spacing: f32,
    /// Fraction of a full packing kept where the ramps are 1.
    pub density: f32,
    /// Density ramp over terrain height.
    pub altitude: Ramp,
    /// Density ramp over terrain slope, degrees.
    pub slope: Ramp,
    /// Where the rule places instances (inside the world's bounds).
    pub region: Bounds,
    /// `(species id, distance)`: keep this far from instances of that species placed before the rule.
    pub avoid: Vec<(u16, f32)>,
    /// Parameter values by slot.
    pub params: Vec<(u16, ParamValue)>,
    /// The rule's random stream key `R` (see [`crate::world`]).
    pub key: u64,
}

impl ScatterRule {
    /// The probability that a dart at (x, z) is kept: `density · altitude(height) · slope(slope)`.
    pub fn density_at(&self, terrain: &Terrain, x: f32, z: f32) -> f32 {
        let (height, slope) = terrain.height_and_slope(x, z);
        self.density * self.altitude.at(height) * self.slope.at(slope)
    }
}

/// Snap (x, z) down onto the [`POSITION_STEPS`] grid of its cell: `floor(v / step) · step` with the power-of-two
/// `step = cell_size / POSITION_STEPS` (the cell size is a power of two and cells start at multiples of it, so
/// this is the cell's grid). Exact in f32 within the bounds a world allows.
pub(crate) fn snap(cell_size: f32, x: f64, z: f64) -> [f32; 2] {
    let (step, inv_step) = position_step(cell_size);
    [((x * inv_step).floor() * step) as f32, ((z * inv_step).floor() * step) as f32]
}

/// A species table entry while building: the graph, if it loaded.
struct Entry {
    name: String,
    graph: Option<SpeciesGraph>,
    source: String,
}

/// Load one species source, reporting problems at `span` of the manifest (or in the species file itself).
fn load_species(
    src: &SourceFile,
    source: &SourceRef,
    span: &Span,
    files: &dyn Resolver,
    diags: &mut Vec<Diagnostic>,
) -> Option<(SpeciesGraph, String)> {
    let (file, text, shown) = match source {
        SourceRef::Library(name) => match crate::library::find(name) {
            Some(e) => (e.file.to_string(), e.text.to_string(), format!("library:{}", e.name())),
            None => {
                let known: Vec<&str> = crate::library::SPECIES.iter().map(|e| e.name()).collect();
                let msg =
                    format!("no library species `{name}` (library: {}; a file path goes in quotes)", known.join(", "));
                diags.push(src.diag(span.clone(), msg));
                return None;
            }
        },
        SourceRef::File(rel) => match files.read(rel) {
            Ok((name, text)) => (name.clone(), text, name),
            Err(msg) => {
                diags.push(src.diag(span.clone(), msg));
                return None;
            }
        },
    };
    let (graph, found) = parse_source(&SourceFile::new(file, text));
    diags.extend(found);
    graph.map(|g| (g, shown))
}

/// Placed instances to keep away from, each with its distance, in buckets of a uniform grid.
struct Buckets {
    origin: [f64; 2],
    size: f64,
    dims: [usize; 2],
    starts: Vec<u32>,
    /// x, z and the distance to keep.
    points: Vec<[f32; 3]>,
}

impl Buckets {
    fn new(bounds: &Bounds, points: Vec<[f32; 3]>) -> Buckets {
        let [w, d] = bounds.size().map(f64::from);
        let distance = points.iter().map(|p| f64::from(p[2])).fold(0.0, f64::max);
        // Buckets at least the largest distance wide (so a query reads 3 × 3), and at most about 1024 per axis.
        let size = distance.max(w.max(d) / 1024.0);
        let dims = [(w / size).ceil() as usize + 1, (d / size).ceil() as usize + 1];
        let origin = bounds.min.map(f64::from);
        let bucket = |p: &[f32; 3]| {
            let i = ((f64::from(p[0]) - origin[0]) / size) as usize;
            let j = ((f64::from(p[1]) - origin[1]) / size) as usize;
            j.min(dims[1] - 1) * dims[0] + i.min(dims[0] - 1)
        };
        let mut starts = vec![0u32; dims[0] * dims[1] + 1];
        for p in &points {
            starts[bucket(p) + 1] += 1;
        }
        for i in 1..starts.len() {
            starts[i] += starts[i - 1];
        }
        let mut fill = starts.clone();
        let mut sorted = vec![[0.0f32; 3]; points.len()];
        for p in points {
            let b = bucket(&p);
            sorted[fill[b] as usize] = p;
            fill[b] += 1;
        }
        Buckets { origin, size, dims, starts, points: sorted }
    }

    /// Whether (x, z) is closer to any point than that point's distance.
    fn near(&self, x: f32, z: f32) -> bool {
        let (x, z) = (f64::from(x), f64::from(z));
        let i = ((x - self.origin[0]) / self.size) as i64;
        let j = ((z - self.origin[1]) / self.size) as i64;
        for bj in (j - 1).max(0)..=(j + 1).min(self.dims[1] as i64 - 1) {
            let row = bj as usize * self.dims[0];
            let (b0, b1) = ((i - 1).max(0) as usize, (i + 1).min(self.dims[0] as i64 - 1) as usize);
            // The buckets of a row are contiguous.
            for p in &self.points[self.starts[row + b0] as usize..self.starts[row + b1 + 1] as usize] {
                let (dx, dz, d) = (f64::from(p[0]) - x, f64::from(p[1]) - z, f64::from(p[2]));
                if dx * dx + dz * dz < d * d {
                    return true;
                }
            }
        }
        false
    }
}

/// The background grid of one rule: cells of `spacing / √2` over its region.
struct DartGrid<'a> {
    rule: &'a ScatterRule,
    nx: usize,
    nz: usize,
    r2: f64,
    step: f64,
    /// Per column: the grid positions `(first k, count)` and the terrain blocks under them.
    columns: Vec<((i64, i64), (usize, usize))>,
    /// Per row: the same.
    rows: Vec<((i64, i64), (usize, usize))>,
    summary: Option<&'a Summary>,
    avoid: Option<&'a Buckets>,
    stream: u64,
}

impl DartGrid<'_> {
    /// Throw the darts of every cell in row-major order into `grid` (one slot per cell, NaN where there is no
    /// dart). Returns `(cell index, dart)` in that order.
    fn throw(&self, rng: &mut InstanceRng, grid: &mut [[f32; 2]]) -> Vec<(u32, [f32; 2])> {
        let nx = self.nx;
        let mut darts = Vec::new();
        for j in 0..self.nz {
            let ((kz0, cz), row_blocks) = self.rows[j];
            for (i, &((kx0, cx), column_blocks)) in self.columns.iter().enumerate() {
                if cx < 1 || cz < 1 {
                    continue;
                }
                if let Some(s) = self.summary {
                    let (height, slope) = s.bounds(column_blocks, row_blocks);
                    let rule = self.rule;
                    if rule.density * rule.altitude.max_over(height) * rule.slope.max_over(slope) <= 0.0 {
                        continue;
                    }
                }
                // Darts closer than `spacing` lie at most two cells away (the corner cells are included as a
                // margin for rounding); only earlier cells hold darts yet: the two rows above, two cells left.
                let mut near = [[0.0f64; 2]; 12];
                let mut n = 0;
                for cj in j.saturating_sub(2)..=j {
                    let columns = if cj < j { i.saturating_sub(2)..(i + 3).min(nx) } else { i.saturating_sub(2)..i };
                    for q in &grid[cj * nx + columns.start..cj * nx + columns.end] {
                        if !q[0].is_nan() {
                            near[n] = [f64::from(q[0]), f64::from(q[1])];
                            n += 1;
                        }
                    }
                }
                let near = &near[..n];
                let cell = (j * nx + i) as u64;
                for a in 0..u64::from(SCATTER_ATTEMPTS) {
                    let w = rng.word(self.stream, cell * u64::from(SCATTER_ATTEMPTS) + a);
                    let px = (kx0 + ((i64::from(w & 0xffff) * cx) >> 16)) as f64 * self.step;
                    let pz = (kz0 + ((i64::from(w >> 16) * cz) >> 16)) as f64 * self.step;
                    let clear = near.iter().all(|q| {
                        let (dx, dz) = (q[0] - px, q[1] - pz);
                        dx * dx + dz * dz >= self.r2
                    });
                    let (sx, sz) = (px as f32, pz as f32);
                    if !clear || self.avoid.is_some_and(|b| b.near(sx, sz)) {
                        continue;
                    }
                    grid[j * nx + i] = [sx, sz];
                    darts.push((cell as u32, [sx, sz]));
                    break;
                }
            }
        }
        darts
    }
}

/// Expand one `scatter` rule: grid-accelerated dart throwing (Poisson-disk darts, at most one per background
/// cell of `spacing / √2`, so at most [`MAX_RULE_CELLS`]), then thinning by density. Returns the kept instances
/// in row-major order of their background cells.
///
/// Background cell `c` (row-major index) tries up to [`SCATTER_ATTEMPTS`] darts on the position grid inside
/// it: attempt `a` reads word `c · SCATTER_ATTEMPTS + a` of stream `child_key(R, 0)`, whose low and high 16 bits
/// pick one of the `n` grid positions per axis (`(bits · n) >> 16`); a dart is accepted if it keeps `spacing` from
/// every dart already placed and the `avoid` distances. Cells where the terrain's height and slope bounds make the
/// density 0 throw nothing (their darts could only be thinned out); words are addressed by cell, so skipping
/// changes no other cell's draws. Cells are visited in row-major order over the whole region.
///
/// The dart of cell `c` is kept if `unit_f32(word 0 of stream child_key(R, c + 1))` is below
/// [`ScatterRule::density_at`]; the kept instance's `n`-th parameter rule draws word `n + 1` of that stream. Thinning
/// runs on as many threads as there are cores, with the same result.
fn scatter(
    rule: &ScatterRule,
    cell_size: f32,
    seed: u64,
    terrain: &Terrain,
    graph: &SpeciesGraph,
    avoid: Option<&Buckets>,
    summary: Option<&Summary>,
) -> Vec<Placement> {
    let (x0, z0) = (f64::from(rule.region.min[0]), f64::from(rule.region.min[1]));
    let (x1, z1) = (f64::from(rule.region.max[0]), f64::from(rule.region.max[1]));
    let g = f64::from(rule.spacing) / std::f64::consts::SQRT_2;
    let (nx, nz) = rule_cells(rule);
    let (step, inv_step) = position_step(cell_size);
    // Background cell `i` spans `[o + i·g, o + (i + 1)·g)`: grid positions `k · step` for `k` in `lo..hi`, as
    // `(lo, hi - lo)`, and the terrain blocks under them.
    let positions = |axis: usize, o: f64, end: f64, i: usize| {
        let edge = |i: usize| (o + i as f64 * g).min(end);
        let lo = (edge(i) * inv_step).ceil() as i64;
        let n = (edge(i + 1) * inv_step).ceil() as i64 - lo;
        let at = |k: i64| k as f64 * step;
        (lo, n, summary.map_or((0, 0), |s| s.blocks(axis, at(lo), at(lo + n - 1))))
    };
    let columns = (0..nx).map(|i| positions(0, x0, x1, i)).map(|(lo, n, b)| ((lo, n), b)).collect();
    let rows = (0..nz).map(|j| positions(1, z0, z1, j)).map(|(lo, n, b)| ((lo, n), b)).collect();
    let darts = DartGrid {
        rule,
        nx,
        nz,
        r2: f64::from(rule.spacing) * f64::from(rule.spacing),
        step,
        columns,
        rows,
        summary,
        avoid,
        stream: child_key(rule.key, 0),
    };
    // Dart throwing is sequential (row-major over the whole region: splitting it into independently filled bands
    // packs their first rows denser and leaves stripes); thinning is independent per dart and runs in parallel.
    let mut grid = vec![[f32::NAN; 2]; nx * nz];
    let placed = darts.throw(&mut InstanceRng::new(seed), &mut grid);
    drop(grid);
    let chunks: Vec<&[(u32, [f32; 2])]> = placed.chunks(THINNING_CHUNK).collect();
    let kept = super::par::map(
        &chunks,
        || InstanceRng::new(seed),
        |rng, chunk| {
            chunk
                .iter()
                .filter_map(|&(cell, [x, z])| {
                    let stream = child_key(rule.key, u64::from(cell) + 1);
                    if unit_f32(rng.word(stream, 0)) >= rule.density_at(terrain, x, z) {
                        return None;
                    }
                    let mut params = Vec::new();
                    for (n, &(slot, value)) in rule.params.iter().enumerate() {
                        let v = value.value(rng.word(stream, n as u64 + 1));
                        if !is_default(graph, slot, v) {
                            params.push((slot, v));
                        }
                    }
                    Some(Placement { species: rule.species, x, z, params })
                })
                .collect::<Vec<_>>()
        },
    );
    kept.concat()
}

/// Darts per thinning job.
const THINNING_CHUNK: usize = 8192;

/// The position step `cell_size / POSITION_STEPS` and its inverse, both powers of two (so exact).
fn position_step(cell_size: f32) -> (f64, f64) {
    let step = f64::from(cell_size) / f64::from(POSITION_STEPS);
    (step, 1.0 / step)
}

/// Background cells of a rule's dart grid per axis, in f64: a tiny spacing must not overflow the count before
/// [`MAX_RULE_CELLS`] refuses it.
fn rule_grid(rule: &ScatterRule) -> [f64; 2] {
    let g = f64::from(rule.spacing) / std::f64::consts::SQRT_2;
    rule.region.size().map(|s| (f64::from(s) / g).ceil().max(1.0))
}

/// Background cells of a rule's dart grid per axis.
fn rule_cells(rule: &ScatterRule) -> (usize, usize) {
    let [w, d] = rule_grid(rule);
    (w as usize, d as usize)
}

/// Resolve `name = value` settings against a species: sorted by slot, values equal to a constant default
/// dropped. Unknown names are reported.
fn resolve_settings(
    src: &SourceFile,
    graph: &SpeciesGraph,
    settings: &[super::manifest::Setting],
    diags: &mut Vec<Diagnostic>,
) -> Vec<(u16, f32)> {
    let mut out = Vec::new();
    for s in settings {
        match graph.param_slot(&s.name) {
            Some(slot) if out.iter().any(|&(o, _)| o == slot) => {
                diags.push(src.diag(s.span.clone(), format!("parameter `{}` set twice", s.name)));
            }
            Some(slot) => out.push((slot, s.value)),
            None => diags.push(src.diag(s.span.clone(), unknown_param(graph, &s.name))),
        }
    }
    out.sort_by_key(|&(s, _)| s);
    out.retain(|&(slot, v)| !is_default(graph, slot, v));
    out
}

/// Whether `v` is bit for bit the species' constant default for `slot`.
fn is_default(graph: &SpeciesGraph, slot: u16, v: f32) -> bool {
    graph.params[slot as usize].default.as_constant().is_some_and(|d| d.to_bits() == v.to_bits())
}

/// A population resolved against the species table, ready to expand.
enum Resolved {
    Instance(Placement),
    Scatter(usize, Span),
}

/// Build the world, appending every problem to `diags`; `None` if there were any.
pub(crate) fn build(
    src: &SourceFile,
    m: &Manifest,
    files: &dyn Resolver,
    diags: &mut Vec<Diagnostic>,
) -> Option<World> {
    let end = src.text.len()..src.text.len();
    let mut required = |present: bool, what: &str| {
        if !present && !m.seen.iter().any(|s| s == what) {
            diags.push(src.diag(end.clone(), format!("the manifest has no `{what}` statement")));
        }
    };
    required(m.seed.is_some(), "seed");
    required(m.bounds.is_some(), "bounds");
    required(m.cell.is_some(), "cell");
    let seed = m.seed.as_ref().map_or(0, |s| s.0);

    // Bounds and cells.
    let mut geometry = None;
    if let (Some((b, bspan)), Some((cell_size, _))) = (&m.bounds, &m.cell) {
        let cell_size = *cell_size;
        let step = cell_size / POSITION_STEPS as f32;
        let limit = f64::from(cell_size) * f64::from(POSITION_STEPS);
        let bounds = Bounds { min: [b[0], b[1]], max: [b[2], b[3]] };
        let on_grid = b.iter().all(|&v| (f64::from(v) / f64::from(step)).fract() == 0.0);
        let cells = |lo: f32, hi: f32| {
            ((f64::from(hi) - f64::from(step)) / f64::from(cell_size)).floor()
                - (f64::from(lo) / f64::from(cell_size)).floor()
                + 1.0
        };
        let count = cells(b[0], b[2]) * cells(b[1], b[3]);
        if b.iter().any(|&v| f64::from(v).abs() > limit) {
            diags.push(src.diag(
                bspan.clone(),
                format!(
                    "bounds must lie within ±{limit} m (cell size × {POSITION_STEPS}), where positions are exact in f32"
                ),
            ));
        } else if !on_grid {
            diags.push(src.diag(bspan.clone(), format!("bounds must be multiples of the position step, {step} m")));
        } else if count > MAX_CELLS as f64 {
            diags.push(src.diag(bspan.clone(), format!("the bounds hold {count} cells, more than {MAX_CELLS}")));
        } else {
            geometry = Some((bounds, cell_size));
        }
    }

    // The species table.
    if m.species.len() > MAX_SPECIES {
        diags.push(src.diag(m.species[MAX_SPECIES].name_span.clone(), format!("more than {MAX_SPECIES} species")));
    }
    let mut table: Vec<Entry> = Vec::new();
    for decl in m.species.iter().take(MAX_SPECIES) {
        let loaded = load_species(src, &decl.source, &decl.source_span, files, diags);
        let (graph, source) = match loaded {
            Some((g, s)) => (Some(g), s),
            None => (None, String::new()),
        };
        table.push(Entry { name: decl.name.clone(), graph, source });
    }
    if m.species.is_empty() && !m.seen.iter().any(|s| s == "species") {
        diags.push(src.diag(end.clone(), "the manifest declares no `species`"));
    }

    // The terrain.
    let mut terrain = None;
    if let Some(t) = &m.terrain {
        let loaded = load_species(src, &t.source, &t.source_span, files, diags);
        let mut ok = true;
        let mut params = Vec::new();
        if let Some((graph, _)) = &loaded {
            for s in &t.params {
                if TILE_PARAMS.contains(&s.name.as_str()) {
                    let msg = format!("`{}` is set by the world for every tile (tile, depth, corners)", s.name);
                    diags.push(src.diag(s.span.clone(), msg));
                    ok = false;
                } else if let Some(slot) = graph.param_slot(&s.name) {
                    params.push((slot, s.value));
                } else {
                    diags.push(src.diag(s.span.clone(), unknown_param(graph, &s.name)));
                    ok = false;
                }
            }
        }
        if let (Some((graph, shown)), Some((bounds, _))) = (loaded, geometry) {
            let [w, d] = bounds.size();
            let tile = t.tile.as_ref().map_or(w.max(d), |t| t.0);
            let tiles = [(f64::from(w) / f64::from(tile)).ceil(), (f64::from(d) / f64::from(tile)).ceil()];
            let depth = t.depth.as_ref().map_or(DEFAULT_TERRAIN_DEPTH, |d| d.0);
            let vertices = (tiles[0] * f64::from(1u32 << depth) + 1.0) * (tiles[1] * f64::from(1u32 << depth) + 1.0);
            let span = t.tile.as_ref().map_or(t.span.clone(), |t| t.1.clone());
            let within = vertices <= MAX_TERRAIN_VERTICES as f64;
            if !within {
                let msg = format!("the terrain grid would have {vertices} vertices, more than {MAX_TERRAIN_VERTICES}");
                diags.push(src.diag(span, msg));
                ok = false;
            }
            let tiles = [tiles[0] as u32, tiles[1] as u32];
            let (cx, cz) = (tiles[0] as usize + 1, tiles[1] as usize + 1);
            // The tile count is bounded (by the vertex count) before anything is allocated.
            let mut corners = if within { vec![0.0f32; cx * cz] } else { Vec::new() };
            if within && !t.corners.is_empty() {
                if t.corners.len() != cz {
                    let msg = format!(
                        "{} rows of `corners` for {} × {} tiles: expected {cz} rows of {cx} heights",
                        t.corners.len(),
                        tiles[0],
                        tiles[1]
                    );
                    diags.push(src.diag(t.corners[0].1.clone(), msg));
                    ok = false;
                }
                for (row, (heights, span)) in t.corners.iter().enumerate() {
                    if heights.len() != cx {
                        let msg = format!("{} corner heights in this row: expected {cx} (tiles + 1)", heights.len());
                        diags.push(src.diag(span.clone(), msg));
                        ok = false;
                    } else if row < cz {
                        corners[row * cx..(row + 1) * cx].copy_from_slice(heights);
                    }
                }
            }
            if ok {
                let tseed = t.seed.as_ref().map_or(mix64(seed ^ TERRAIN_SALT), |s| s.0);
                match Terrain::build(graph, shown, tseed, bounds.min, tile, tiles, depth, corners, params) {
                    Ok(built) => terrain = Some(built),
                    Err(e) => diags.push(src.diag(t.span.clone(), e.to_string())),
                }
            }
        }
    } else if let Some((bounds, _)) = geometry {
        let [w, d] = bounds.size();
        terrain = Some(Terrain::flat(bounds.min, w.max(d)));
    }

    // Resolve the populations.
    let mut rules: Vec<ScatterRule> = Vec::new();
    let mut resolved: Vec<Resolved> = Vec::new();
    let lookup = |name: &str, span: &Span, diags: &mut Vec<Diagnostic>| -> Option<(u16, Option<&SpeciesGraph>)> {
        match table.iter().position(|e| e.name == name) {
            Some(i) => Some((i as u16, table[i].graph.as_ref())),
            None => {
                let known: Vec<&str> = table.iter().map(|e| e.name.as_str()).collect();
                diags
                    .push(src.diag(span.clone(), format!("unknown species `{name}` (declared: {})", known.join(", "))));
                None
            }
        }
    };
    let mut ordinals: Vec<u64> = vec![0; table.len()];
    for pop in &m.populations {
        match pop {
            Population::Instance(inst) => {
                let Some((id, graph)) = lookup(&inst.species, &inst.species_span, diags) else { continue };
                let params = graph.map(|g| resolve_settings(src, g, &inst.params, diags));
                let Some((bounds, cell_size)) = geometry else { continue };
                let [x, z] = snap(cell_size, f64::from(inst.at[0]), f64::from(inst.at[1]));
                if !bounds.contains(inst.at[0], inst.at[1]) || !bounds.contains(x, z) {
                    diags.push(src.diag(inst.at_span.clone(), "the instance lies outside the world's bounds"));
                    continue;
                }
                if let Some(params) = params {
                    resolved.push(Resolved::Instance(Placement { species: id, x, z, params }));
                }
            }
            Population::Scatter(r) => {
                if rules.len() == MAX_RULES {
                    diags.push(src.diag(r.span.clone(), format!("more than {MAX_RULES} scatter rules")));
                    continue;
                }
                let Some((id, graph)) = lookup(&r.species, &r.species_span, diags) else { continue };
                let mut ok = true;
                let mut avoid = Vec::new();
                for a in &r.avoid {
                    match lookup(&a.species, &a.span, diags) {
                        Some((other, _)) => avoid.push((other, a.distance)),
                        None => ok = false,
                    }
                }
                let mut params = Vec::new();
                if let Some(g) = graph {
                    for p in &r.params {
                        match g.param_slot(&p.name) {
                            Some(slot) => params.push((slot, p.value)),
                            None => {
                                diags.push(src.diag(p.span.clone(), unknown_param(g, &p.name)));
                                ok = false;
                            }
                        }
                        if let ParamValue::Range { lo, hi, step: Some(step) } = p.value
                            && ParamValue::levels(lo, hi, step) > MAX_RANGE_STEPS
                        {
                            diags.push(src.diag(p.span.clone(), format!("more than {MAX_RANGE_STEPS} steps")));
                            ok = false;
                        }
                    }
                    params.sort_by_key(|&(s, _)| s);
                }
                let Some((bounds, _)) = geometry else { continue };
                let region = match &r.region {
                    Some((q, span)) => {
                        let region = Bounds { min: [q[0], q[1]], max: [q[2], q[3]] };
                        let inside = region.min[0] >= bounds.min[0]
                            && region.min[1] >= bounds.min[1]
                            && region.max[0] <= bounds.max[0]
                            && region.max[1] <= bounds.max[1];
                        if !inside {
                            diags.push(src.diag(span.clone(), "the region must lie within the world's bounds"));
                            ok = false;
                        }
                        region
                    }
                    None => bounds,
                };
                let Some((spacing, spacing_span)) = r.spacing.clone() else { continue };
                let mut h = Fnv::new();
                h.bytes(r.species.as_bytes());
                let rule = ScatterRule {
                    species: id,
                    spacing,
                    density: r.density.as_ref().map_or(1.0, |d| d.0),
                    altitude: r.altitude.as_ref().map_or(Ramp::ALL, |a| a.0),
                    slope: r.slope.as_ref().map_or(Ramp::ALL, |a| a.0),
                    region,
                    avoid,
                    params,
                    key: child_key(h.finish(), ordinals[id as usize]),
                };
                ordinals[id as usize] += 1;
                let [w, d] = rule_grid(&rule);
                let cells = w * d;
                if cells > MAX_RULE_CELLS as f64 {
                    let msg = format!(
                        "spacing {spacing} m over this region needs {cells} sampling cells, more than {MAX_RULE_CELLS}"
                    );
                    diags.push(src.diag(spacing_span, msg));
                    ok = false;
                }
                if ok {
                    resolved.push(Resolved::Scatter(rules.len(), r.span.clone()));
                    rules.push(rule);
                }
            }
        }
    }
    if !diags.is_empty() {
        return None;
    }
    let (bounds, cell_size) = geometry?;
    let terrain = terrain?;
    let species: Vec<WorldSpecies> = table
        .into_iter()
        .map(|e| Some(WorldSpecies { name: e.name, graph: e.graph?, source: e.source }))
        .collect::<Option<_>>()?;

    // Expand, in file order.
    let mut placed: Vec<Placement> = Vec::new();
    let mut summary: Option<Summary> = None;
    let explicit = resolved.iter().filter(|r| matches!(r, Resolved::Instance(_))).count();
    if explicit > MAX_INSTANCES {
        diags.push(src.diag(end, format!("{explicit} `instance` statements, more than {MAX_INSTANCES}")));
        return None;
    }
    let explicit = explicit as u32;
    for item in resolved {
        match item {
            Resolved::Instance(p) => placed.push(p),
            Resolved::Scatter(index, span) => {
                let rule = &rules[index];
                let avoid = (!rule.avoid.is_empty()).then(|| {
                    let distance = |s: u16| rule.avoid.iter().filter(|a| a.0 == s).map(|a| a.1).reduce(f32::max);
                    let points = placed.iter().filter_map(|p| distance(p.species).map(|d| [p.x, p.z, d])).collect();
                    Buckets::new(&bounds, points)
                });
                let trivial = rule.altitude == Ramp::ALL && rule.slope == Ramp::ALL;
                if !trivial && summary.is_none() {
                    summary = Some(terrain.summary());
                }
                let graph = &species[rule.species as usize].graph;
                let kept = scatter(
                    rule,
                    cell_size,
                    seed,
                    &terrain,
                    graph,
                    avoid.as_ref(),
                    summary.as_ref().filter(|_| !trivial),
                );
                if placed.len() + kept.len() > MAX_INSTANCES {
                    let msg = format!("the world would have more than {MAX_INSTANCES} instances");
                    diags.push(src.diag(span.clone(), msg));
                    return None;
                }
                placed.extend(kept);
            }
        }
    }

    let name = match &m.name {
        Some((n, _)) => n.clone(),
        None => crate::species_text::file_stem(&src.name),
    };
    Some(World::assemble(name, seed, bounds, cell_size, species, placed, terrain, rules, explicit))
}
