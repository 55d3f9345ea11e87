//! Building a [`World`] from a parsed manifest: the species table, the terrain, and the populations — explicit
//! instances and `scatter` rules expanded by grid-accelerated Poisson-disk dart throwing, thinned by density over
//! altitude and slope (the algorithm and its random streams are described in [`crate::world`]).

use std::sync::Arc;

use canopy_protocol::SpeciesGraph;

use super::cells::{MAX_CELL_INSTANCES, MAX_CELL_WORK, Populations};
use super::fractal::Fractal;
use super::manifest::{Manifest, Population, SourceRef, Span};
use super::source::{Resolver, Statement};
use super::terrain::{TILE_PARAMS, Terrain, slope_degrees};
use super::tiles::Tiles;
use super::{
    Bounds, CellKey, MAX_CELL_COORD, MAX_CELLS, MAX_RULES, MAX_SPECIES, MAX_TERRAIN_VERTICES, POSITION_STEPS,
    Placement, World, WorldSpecies,
};
use crate::diag::{Diagnostic, SourceFile};
use crate::eval::unit_f32;
use crate::load::parse_source;
use crate::primitive::Fnv;
use crate::rng::{child_key, mix64};

/// Salt of the default terrain seed: `mix64(world seed ^ TERRAIN_SALT)`.
pub(super) const TERRAIN_SALT: u64 = 0x7465_7272_6169_6e00;

/// The library name of the built-in fractal terrain function ([`Fractal`]): `terrain fractal { … }`.
pub const FRACTAL: &str = "fractal";
/// A fractal terrain's default depth, dimension and relief.
pub(super) const DEFAULT_FRACTAL_DEPTH: u32 = 10;
const DEFAULT_DIMENSION: f32 = 2.2;
const DEFAULT_RELIEF: f32 = 100.0;

/// The default terrain depth (the terrain species' own default at full detail).
pub(super) const DEFAULT_TERRAIN_DEPTH: u32 = 7;

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

/// A slope ramp read from `|∇h|²`: [`SlopeRamp::at`] is `ramp.at(slope_degrees(g2))` bit for bit, with the `atan`
/// taken only near the ramp's corners. Where `g2` lies inside the plateau or outside the ramp's support by a
/// relative margin of 10⁻⁴, the value is 1 or 0 without it: the slope then lies at least 6 f32 ulps from the corner
/// (the margin in degrees shrinks towards 90°: by 89° it is `½ · 10⁻⁴ · g / ((1 + g²) atan g)` relative, 5.6 · 10⁻⁷),
/// far more than `atan`'s error and the rounding to f32. Corners at or below 0° and at or past 89° are never decided
/// early.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SlopeRamp {
    /// The ramp over degrees.
    pub ramp: Ramp,
    /// `g2` below this: the ramp is 0 (the slope is under `a`).
    zero_below: f64,
    /// `g2` strictly between these: the ramp is 1 (the slope is inside `[b, c]`).
    one_above: f64,
    one_below: f64,
    /// `g2` above this: the ramp is 0 (the slope is past `d`).
    zero_above: f64,
}

impl SlopeRamp {
    /// Relative margin on `g2` around a corner.
    const MARGIN: f64 = 1e-4;

    /// The ramp and its corners as squared gradients.
    pub fn new(ramp: Ramp) -> SlopeRamp {
        // tan² of a corner strictly inside (0°, 89°), else `None` (decided only through the atan).
        let g2 = |deg: f32| {
            (deg > 0.0 && deg < 89.0)
                .then(|| libm::pow(libm::tan(f64::from(deg) * (std::f64::consts::PI / 180.0)), 2.0))
        };
        let ordered = ramp.a <= ramp.b && ramp.b <= ramp.c && ramp.c <= ramp.d;
        let never = SlopeRamp {
            ramp,
            zero_below: f64::NEG_INFINITY,
            one_above: f64::INFINITY,
            one_below: f64::NEG_INFINITY,
            zero_above: f64::INFINITY,
        };
        if !ordered {
            return never;
        }
        SlopeRamp {
            zero_below: g2(ramp.a).map_or(f64::NEG_INFINITY, |t| t * (1.0 - Self::MARGIN)),
            // The plateau starts at `b ≤ 0`: every slope (≥ 0) is past it.
            one_above: if ramp.b <= 0.0 {
                f64::NEG_INFINITY
            } else {
                g2(ramp.b).map_or(f64::INFINITY, |t| t * (1.0 + Self::MARGIN))
            },
            // The plateau ends past 90° (or never): every slope (≤ 90) is before it.
            one_below: if ramp.c > 90.0 {
                f64::INFINITY
            } else {
                g2(ramp.c).map_or(f64::NEG_INFINITY, |t| t * (1.0 - Self::MARGIN))
            },
            zero_above: g2(ramp.d).map_or(f64::INFINITY, |t| t * (1.0 + Self::MARGIN)),
            ..never
        }
    }

    /// The ramp at the slope whose squared gradient is `g2`.
    #[inline]
    pub fn at(&self, g2: f64) -> f32 {
        if g2 > self.one_above && g2 < self.one_below {
            1.0
        } else if g2 < self.zero_below || g2 > self.zero_above {
            0.0
        } else {
            self.ramp.at(slope_degrees(g2))
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
pub(super) const MAX_RANGE_STEPS: f64 = 16_777_216.0;

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
    pub slope: SlopeRamp,
    /// Where the rule places instances (inside the world's bounds).
    pub region: Bounds,
    /// `(species id, distance)`: keep this far from instances of that species placed before the rule.
    pub avoid: Vec<(u16, f32)>,
    /// Parameter values by slot.
    pub params: Vec<(u16, ParamValue)>,
    /// The rule's random stream key `R` (see [`crate::world`]).
    pub key: u64,
    /// Its Poisson-disk pattern, tile by tile.
    pub(crate) tiles: Tiles,
}

impl ScatterRule {
    /// The probability that a dart at (x, z) is kept: `density · altitude(height) · slope(slope)`.
    pub fn density_at(&self, world: &World, x: f32, z: f32) -> f32 {
        let (height, g2) = world.height_and_gradient2(x, z);
        self.keep(height, g2)
    }

    /// The probability that a dart is kept on ground of `height` whose squared gradient is `g2` (the one formula
    /// of cell expansion and the far view's leaves).
    pub fn keep(&self, height: f32, g2: f64) -> f32 {
        self.density * self.altitude.at(height) * self.slope.at(g2)
    }

    /// Whether the keep probability depends on the ground (an altitude or slope ramp); without, it is `density`.
    pub fn has_ramps(&self) -> bool {
        self.altitude != Ramp::ALL || self.slope.ramp != Ramp::ALL
    }
}

/// Snap (x, z) down onto the [`POSITION_STEPS`] grid of its cell: `floor(v / step) · step` with the power-of-two
/// `step = cell_size / POSITION_STEPS` (the cell size is a power of two and cells start at multiples of it, so
/// this is the cell's grid). Exact in f64 within the bounds a world allows.
pub(crate) fn snap(cell_size: f32, x: f64, z: f64) -> [f64; 2] {
    let (step, inv_step) = position_step(cell_size);
    [(x * inv_step).floor() * step, (z * inv_step).floor() * step]
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
    statement: Statement,
    diags: &mut Vec<Diagnostic>,
) -> Option<(SpeciesGraph, String)> {
    if let Some(compiled) = files.compiled(statement) {
        return Some(compiled);
    }
    if files.compiled_only() {
        let msg = match statement {
            Statement::Species(i) => format!("species {i} is not in the species table this world function came with"),
            Statement::Terrain => "the terrain species did not come with this world function".to_string(),
        };
        diags.push(src.diag(span.clone(), msg));
        return None;
    }
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

/// The position step `cell_size / POSITION_STEPS` and its inverse, both powers of two (so exact).
pub(crate) fn position_step(cell_size: f32) -> (f64, f64) {
    let step = f64::from(cell_size) / f64::from(POSITION_STEPS);
    (step, 1.0 / step)
}

/// The most instances the rules can put in one cell: one dart per background cell of `spacing / √2`, and at most
/// `(cell / g + 2)²` background cells touch a cell.
fn darts_per_cell(rules: &[ScatterRule], cell_size: f32) -> f64 {
    rules
        .iter()
        .map(|r| {
            let g = f64::from(r.spacing) / std::f64::consts::SQRT_2;
            (f64::from(cell_size) / g + 2.0).powi(2)
        })
        .sum()
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
        match graph.parameter_slot(&s.name) {
            Ok(slot) if out.iter().any(|&(o, _)| o == slot) => {
                diags.push(src.diag(s.span.clone(), format!("parameter `{}` set twice", s.name)));
            }
            Ok(slot) => out.push((slot, s.value)),
            Err(why) => diags.push(src.diag(s.span.clone(), why)),
        }
    }
    out.sort_by_key(|&(s, _)| s);
    out.retain(|&(slot, v)| !is_default(graph, slot, v));
    out
}

/// Whether `v` is bit for bit the species' constant default for `slot`.
pub(crate) fn is_default(graph: &SpeciesGraph, slot: u16, v: f32) -> bool {
    graph.params[slot as usize].default.as_constant().is_some_and(|d| d.to_bits() == v.to_bits())
}

/// A population resolved against the species table, ready to expand.
enum Resolved {
    Instance(Placement),
    Scatter(Span),
    /// A baked edit: `true` fells, `false` sets the placement's parameters.
    Edit(bool, Placement),
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
        let limit = f64::from(cell_size) * f64::from(MAX_CELL_COORD);
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
                    "bounds must lie within ±{limit} m (cell size × {MAX_CELL_COORD}, the cells instance ids can name)"
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
    for (i, decl) in m.species.iter().take(MAX_SPECIES).enumerate() {
        let loaded = load_species(src, &decl.source, &decl.source_span, files, Statement::Species(i), diags);
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
    let mut fractal = None;
    let is_fractal = |t: &super::manifest::TerrainDecl| matches!(&t.source, SourceRef::Library(n) if n == FRACTAL);
    if let Some(t) = m.terrain.as_ref().filter(|t| is_fractal(t)) {
        if let Some((bounds, _)) = geometry {
            let [w, d] = bounds.size();
            let mut numbers = [(DEFAULT_DIMENSION, "dimension"), (DEFAULT_RELIEF, "relief")];
            let mut ok = true;
            for s in &t.params {
                match numbers.iter_mut().find(|(_, n)| *n == s.name) {
                    Some((v, _)) => *v = s.value,
                    None => {
                        let msg = format!("unknown fractal terrain parameter `{}` (dimension, relief)", s.name);
                        diags.push(src.diag(s.span.clone(), msg));
                        ok = false;
                    }
                }
            }
            let rows: Vec<Vec<f32>> = t.corners.iter().map(|(r, _)| r.clone()).collect();
            let tile = t.tile.as_ref().map_or(f64::from(w.max(d)), |t| f64::from(t.0));
            let depth = t.depth.as_ref().map_or(DEFAULT_FRACTAL_DEPTH, |d| d.0);
            let tseed = t.seed.as_ref().map_or(mix64(seed ^ TERRAIN_SALT), |s| s.0);
            let origin = bounds.min.map(f64::from);
            match Fractal::new(tseed, origin, tile, depth, numbers[0].0, numbers[1].0, &rows) {
                Ok(f) if ok => {
                    fractal = Some(f);
                    terrain = Some(Terrain::flat(bounds.min, w.max(d)));
                }
                Ok(_) => {}
                Err(e) => diags.push(src.diag(t.span.clone(), e.to_string())),
            }
        }
    } else if let Some(t) = &m.terrain {
        let loaded = load_species(src, &t.source, &t.source_span, files, Statement::Terrain, diags);
        let mut ok = true;
        let mut params = Vec::new();
        if let Some((graph, _)) = &loaded {
            for s in &t.params {
                if TILE_PARAMS.contains(&s.name.as_str()) {
                    let msg = format!("`{}` is set by the world for every tile (tile, depth, corners)", s.name);
                    diags.push(src.diag(s.span.clone(), msg));
                    ok = false;
                } else {
                    match graph.parameter_slot(&s.name) {
                        Ok(slot) => params.push((slot, s.value)),
                        Err(why) => {
                            diags.push(src.diag(s.span.clone(), why));
                            ok = false;
                        }
                    }
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
    // One budget for the tile caches of every rule of the world.
    let tile_budget = Tiles::budget();
    for pop in &m.populations {
        match pop {
            Population::Instance(inst) => {
                let Some((id, graph)) = lookup(&inst.species, &inst.species_span, diags) else { continue };
                let params = graph.map(|g| resolve_settings(src, g, &inst.params, diags));
                let Some((bounds, cell_size)) = geometry else { continue };
                let [x, z] = snap(cell_size, f64::from(inst.at[0]), f64::from(inst.at[1]));
                if !bounds.contains(inst.at[0].into(), inst.at[1].into()) || !bounds.contains(x, z) {
                    diags.push(src.diag(inst.at_span.clone(), "the instance lies outside the world's bounds"));
                    continue;
                }
                if let Some(params) = params {
                    resolved.push(Resolved::Instance(Placement { species: id, x, z, params }));
                }
            }
            Population::Fell(inst) | Population::Set(inst) => {
                let Some((id, graph)) = lookup(&inst.species, &inst.species_span, diags) else { continue };
                let params = graph.map(|g| resolve_settings(src, g, &inst.params, diags));
                let Some((bounds, cell_size)) = geometry else { continue };
                let [x, z] = snap(cell_size, f64::from(inst.at[0]), f64::from(inst.at[1]));
                if !bounds.contains(x, z) {
                    diags.push(src.diag(inst.at_span.clone(), "the position lies outside the world's bounds"));
                    continue;
                }
                if let Some(params) = params {
                    let fell = matches!(pop, Population::Fell(_));
                    resolved.push(Resolved::Edit(fell, Placement { species: id, x, z, params }));
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
                        match g.parameter_slot(&p.name) {
                            Ok(slot) => params.push((slot, p.value)),
                            Err(why) => {
                                diags.push(src.diag(p.span.clone(), why));
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
                let Some((bounds, cell)) = geometry else { continue };
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
                let key = child_key(h.finish(), ordinals[id as usize]);
                let rule = ScatterRule {
                    species: id,
                    spacing,
                    density: r.density.as_ref().map_or(1.0, |d| d.0),
                    altitude: r.altitude.as_ref().map_or(Ramp::ALL, |a| a.0),
                    slope: SlopeRamp::new(r.slope.as_ref().map_or(Ramp::ALL, |a| a.0)),
                    region,
                    avoid,
                    params,
                    key,
                    tiles: Tiles::new(seed, key, spacing, position_step(cell).0, Arc::clone(&tile_budget)),
                };
                ordinals[id as usize] += 1;
                let spacing = f64::from(spacing);
                if spacing.is_nan() || spacing < position_step(geometry.map_or(1.0, |g| g.1)).0 {
                    diags.push(src.diag(spacing_span.clone(), "the spacing must be at least one position step"));
                    ok = false;
                }
                if ok {
                    resolved.push(Resolved::Scatter(r.span.clone()));
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

    // Index the populations for expansion cell by cell: explicit instances by cell, every population's place in
    // file order.
    let mut populations = Populations::default();
    let mut explicit = 0u32;
    let mut spans = Vec::new();
    let cell_of = |p: &Placement| {
        let s = f64::from(cell_size);
        CellKey { x: (p.x / s).floor() as i32, z: (p.z / s).floor() as i32 }
    };
    for (order, item) in resolved.into_iter().enumerate() {
        match item {
            Resolved::Instance(p) => {
                let key = cell_of(&p);
                populations.explicit.entry(key).or_default().push((order as u32, p));
                explicit += 1;
            }
            Resolved::Scatter(span) => {
                populations.rule_order.push(order as u32);
                spans.push(span);
            }
            Resolved::Edit(fell, p) => {
                let key = cell_of(&p);
                populations.edits.entry(key).or_default().push((fell, p));
            }
        }
    }
    let most_explicit = populations.explicit.values().map(Vec::len).max().unwrap_or(0);
    let per_cell = darts_per_cell(&rules, cell_size) + most_explicit as f64;
    if per_cell > MAX_CELL_INSTANCES as f64 {
        let msg = format!(
            "the rules could put {per_cell:.0} instances in one {cell_size} m cell, more than {MAX_CELL_INSTANCES}: use larger spacings or smaller cells"
        );
        diags.push(src.diag(spans.first().cloned().unwrap_or(end), msg));
        return None;
    }
    let name = match &m.name {
        Some((n, _)) => n.clone(),
        None => crate::species_text::file_stem(&src.name),
    };
    let world = World::assemble(name, seed, bounds, cell_size, species, terrain, fractal, rules, populations, explicit);
    // One cell's expansion is bounded: its rules, their halos and `avoid` chains.
    let work = super::cells::cell_work(&world);
    if work > MAX_CELL_WORK {
        let msg = format!(
            "expanding one cell needs {work:.0} sampling cells (spacings, halos and avoid chains), more than {MAX_CELL_WORK}"
        );
        diags.push(src.diag(spans.first().cloned().unwrap_or(0..0), msg));
        return None;
    }
    Some(world)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `SlopeRamp::at` equals the ramp at `slope_degrees` bit for bit: over a sweep of gradients, and densely
    /// around every corner's squared tangent, for ramps with corners inside, at and outside (0°, 89°).
    #[test]
    fn a_slope_ramp_from_the_squared_gradient_is_the_ramp_at_the_slope() {
        let ramps = [
            Ramp::ALL,
            Ramp { a: f32::NEG_INFINITY, b: f32::NEG_INFINITY, c: 35.0, d: 45.0 },
            Ramp { a: 5.0, b: 12.5, c: 30.0, d: 30.0 },
            Ramp { a: 0.0, b: 0.0, c: 89.0, d: 90.0 },
            Ramp { a: -10.0, b: 0.5, c: 88.9, d: 120.0 },
            Ramp { a: 20.0, b: 20.0, c: f32::INFINITY, d: f32::INFINITY },
        ];
        let mut probes: Vec<f64> = (0..20_000).map(|k| f64::from(k) * 1e-3).collect();
        probes.extend([0.0, f64::MIN_POSITIVE, 1e300, f64::INFINITY]);
        let mut checked = 0;
        for ramp in ramps {
            let s = SlopeRamp::new(ramp);
            for corner in [ramp.a, ramp.b, ramp.c, ramp.d] {
                if corner.is_finite() && corner > 0.0 && corner < 90.0 {
                    let t = libm::pow(libm::tan(f64::from(corner) * (std::f64::consts::PI / 180.0)), 2.0);
                    probes.extend((-3000..=3000).map(|k| t * (1.0 + f64::from(k) * 1e-7)));
                }
            }
            for &g2 in &probes {
                assert_eq!(
                    s.at(g2).to_bits(),
                    ramp.at(slope_degrees(g2)).to_bits(),
                    "{ramp:?} at g2 = {g2:e} ({}°)",
                    slope_degrees(g2)
                );
                checked += 1;
            }
        }
        assert!(checked > 100_000);
        // The early answers are taken: inside the plateau and past the support the atan is skipped.
        let s = SlopeRamp::new(ramps[1]);
        assert!(s.one_above == f64::NEG_INFINITY && s.one_below > 0.48 && s.zero_above < 1.01);
    }
}
