//! Baking: the edits a server stored, folded back into the world's manifest language — `fell` and `set` lines for the
//! world function's instances, `instance` lines for planted ones — from the cells exactly as a server holds them
//! (the world function's placements quantised in the cell, the cell's edit log laid over them). `canopy world bake`
//! writes them after the source manifest.

use canopy_edits::{EditRules, EditStore, EditStoreError, Overlay};
use canopy_protocol::record::dequantize;
use canopy_session::{CellData, StoreError, StoreHead};
use canopy_worlds::world::{CellKey, World};

/// Why edits could not be baked.
#[derive(Debug, thiserror::Error)]
pub enum BakeError {
    /// The world's grid or a cell could not be quantised.
    #[error(transparent)]
    Store(#[from] StoreError),
    /// The edit store could not be read.
    #[error(transparent)]
    Edits(#[from] EditStoreError),
    /// A cell's log does not apply to its records.
    #[error("cell {x}:{z}: {message}")]
    Log {
        /// The cell.
        x: i32,
        /// The cell.
        z: i32,
        /// What does not apply.
        message: String,
    },
}

/// The edits of a store as manifest lines.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Baked {
    /// Manifest lines: a `# cell X:Z at version V` comment, then its `fell`, `set` and `instance` lines, cell by cell.
    pub lines: Vec<String>,
    /// Instances felled.
    pub fells: usize,
    /// Instances whose parameters were set.
    pub sets: usize,
    /// Instances planted (and not felled since).
    pub plants: usize,
    /// Cells with edits that lie outside the world (left out).
    pub outside: Vec<(i32, i32)>,
    /// Stored edits the world cannot take (a species it lacks, an undeclared slot, a value out of range), left out
    /// as a server skips them: `(x, z, version, why)`.
    pub skipped: Vec<(i32, i32, u32, String)>,
}

/// Bake the edits of `store` over `world`.
pub fn bake(world: &World, store: &dyn EditStore) -> Result<Baked, BakeError> {
    // The server's grid of the world: cells are quantised exactly as a server holds them.
    let grid = StoreHead::of_world(world)?.world().grid;
    let mut baked = Baked::default();
    let rules = EditRules::of_species(world.species.iter().map(|s| &s.graph));
    let name = |species: u8| world.species[usize::from(species)].name.as_str();
    let params = |species: u8, params: &[(u16, f32)]| -> String {
        let g = &world.species[usize::from(species)].graph;
        params.iter().map(|&(s, v)| format!(" {}={v}", g.params[usize::from(s)].name)).collect()
    };
    for (cell, version) in store.cells()? {
        let key = CellKey { x: cell.x, z: cell.z };
        if !world.contains_cell(key) {
            baked.outside.push((cell.x, cell.z));
            continue;
        }
        // The cell as the server holds it: the world function's placements, quantised in the cell.
        let placements = world.expand_cell(key);
        let base = CellData::from_placements(&grid, cell, world.species.len(), &placements)?;
        let (records, overrides) = (&base.records, &base.overrides);
        let species = |i: u16| records.get(usize::from(i)).map(|r| r.species);
        let (overlay, skipped) = Overlay::from_log_checked(records.len() as u16, species, &rules, &store.load(cell)?)
            .map_err(|e| BakeError::Log { x: cell.x, z: cell.z, message: e.to_string() })?;
        baked.skipped.extend(skipped.into_iter().map(|(v, why)| (cell.x, cell.z, v, why)));
        let applied = overlay.apply_to(records, overrides);
        let origin = grid.cell_origin(cell);
        baked.lines.push(format!("# cell {}:{} at version {version}", cell.x, cell.z));
        // Overrides are sorted by record: each record's are one run.
        let own = |i: usize| -> Vec<(u16, f32)> {
            let lo = applied.overrides.partition_point(|o| usize::from(o.record) < i);
            let hi = applied.overrides.partition_point(|o| usize::from(o.record) <= i);
            applied.overrides[lo..hi].iter().map(|o| (o.slot, o.value)).collect()
        };
        for (i, r) in applied.records.iter().enumerate() {
            let felled = applied.felled.binary_search(&(i as u16)).is_ok();
            if i < placements.len() {
                let p = &placements[i];
                if felled {
                    baked.lines.push(format!("fell {} at {} {}", name(r.species), p.x, p.z));
                    baked.fells += 1;
                } else if own(i) != p.params {
                    let line = format!("set {} at {} {}{}", name(r.species), p.x, p.z, params(r.species, &own(i)));
                    baked.lines.push(line);
                    baked.sets += 1;
                }
            } else if !felled {
                let s = grid.cell_size;
                let (x, z) = (dequantize(r.qx(), origin[0], s), dequantize(r.qz(), origin[1], s));
                baked.lines.push(format!("instance {} at {x} {z}{}", name(r.species), params(r.species, &own(i))));
                baked.plants += 1;
            }
        }
    }
    Ok(baked)
}
