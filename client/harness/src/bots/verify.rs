//! The check of a client's state against the world: the world as a function ([`World::expand_cell`]), so it works
//! on worlds that are never materialised (the highlands) as on small ones, by one code path.
//!
//! Live edits change cells away from the function (a cell's version counts its edits): [`verify_with`] then checks
//! an edited cell only as far as the function still decides it.

use std::collections::{BTreeMap, HashSet};

use canopy_protocol::aoi::Aoi;
use canopy_protocol::{CellCoord, SpeciesHash};
use canopy_worlds::world::{CellKey, Placement, World};

use canopy_client::state::ClientState;

/// What the check against the world found.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct VerifySummary {
    /// Cells held.
    pub cells: usize,
    /// Instances held.
    pub instances: usize,
    /// Species held.
    pub species: usize,
    /// Cells held that edits changed (version > 0), checked only as far as the world's function decides them (with
    /// [`verify_with`]`(.., true)`; 0 otherwise).
    pub edited: usize,
}

/// The world's placements of `cells`, each cell's in its order (index in the cell = position in the vector). A
/// materialised world answers from [`World::instances`] (the same function, computed at load); any other expands
/// the bounding rectangle of the cells in one call ([`World::expand_cells`] shares the neighbourhood's work).
pub fn expected_cells(world: &World, cells: &[CellCoord]) -> BTreeMap<CellCoord, Vec<Placement>> {
    let key = |c: &CellCoord| CellKey { x: c.x, z: c.z };
    if world.is_materialised() || cells.len() <= 1 {
        return cells.iter().map(|c| (*c, world.expand_cell(key(c)))).collect();
    }
    let (mut lo, mut hi) = (cells[0], cells[0]);
    for c in cells {
        (lo.x, lo.z, hi.x, hi.z) = (lo.x.min(c.x), lo.z.min(c.z), hi.x.max(c.x), hi.z.max(c.z));
    }
    let wanted: HashSet<CellCoord> = cells.iter().copied().collect();
    world
        .expand_cells(key(&lo), key(&hi))
        .into_iter()
        .map(|(k, p)| (CellCoord::new(k.x, k.z), p))
        .filter(|(c, _)| wanted.contains(c))
        .collect()
}

/// Check a client's final state against the world: it holds every cell of its area of interest and nothing
/// beyond radius + hysteresis, every held cell in full, each instance exactly once and exactly as the world's
/// function computes it ([`World::expand_cell`]: species, position on the grid, seed from the identity,
/// parameters; the height follows from the position and the terrain, which client and world share), and each
/// species it needs once.
pub fn verify(state: &ClientState, world: &World) -> Result<VerifySummary, String> {
    verify_with(state, world, false)
}

/// [`verify`], and with `edited` cells that live edits changed (version > 0) are expected: each edit appends a
/// planted instance, leaves a felled one's index taken, or sets parameters, so such a cell must hold at least the
/// world's records, and each of its instances at an index the world has must have the world's species, position and
/// seed (its parameters may have been set); instances past them were planted and are not compared. Without
/// `edited`, an edited cell differs from the world and fails the check.
pub fn verify_with(state: &ClientState, world: &World, edited: bool) -> Result<VerifySummary, String> {
    let is_edited = |c: &CellCoord| edited && state.cells().get(c).is_some_and(|h| h.version > 0);
    let w = state.welcome().ok_or("no welcome")?;
    if w.world.name != world.name || w.world.seed != world.seed {
        return Err(format!("the server's world `{}` is not the world checked against", w.world.name));
    }
    if world.is_materialised() && w.world.instances as usize != world.instances.len() {
        return Err(format!(
            "the server's world has {} instances, this one {}",
            w.world.instances,
            world.instances.len()
        ));
    }
    if w.species.len() != world.species.len()
        || w.species.iter().zip(&world.species).any(|(e, s)| e.hash != SpeciesHash::of(&s.graph.encode()))
    {
        return Err("the species table differs from the world's".into());
    }
    if !state.is_complete() {
        return Err(format!("area of interest incomplete: {} cells missing", state.missing()));
    }
    let vp = state.viewpoint().ok_or("no viewpoint")?;
    let grid = &w.world.grid;
    let aoi = Aoi::new(vp, &w.aoi);
    let inner = aoi.inner_cells(grid);
    if let Some(c) = inner.iter().find(|c| !state.cells().contains_key(c)) {
        return Err(format!("cell {c:?} of the area of interest is not held"));
    }
    if let Some(c) = state.cells().keys().find(|c| !aoi.is_kept(grid, **c)) {
        return Err(format!("cell {c:?} is held beyond radius + hysteresis"));
    }
    // Every held cell is near the viewpoint, so their bounding rectangle is small.
    let held: Vec<CellCoord> = state.cells().keys().copied().collect();
    let expected = expected_cells(world, &held);
    let mut edited_cells = 0;
    for (c, h) in state.cells() {
        let n = expected.get(c).map_or(0, Vec::len);
        let total_ok = if is_edited(c) { usize::from(h.total) >= n } else { usize::from(h.total) == n };
        if !h.is_complete() || !total_ok {
            return Err(format!("cell {c:?}: holds {} of {}, the world has {n}", h.records.len(), h.total));
        }
        edited_cells += usize::from(is_edited(c));
        for r in &h.records {
            if state.species(r.species).is_none() {
                return Err(format!("cell {c:?} needs species {}, which is not held", r.species));
            }
        }
    }
    let mut ids = HashSet::new();
    let no_height = |_: f32, _: f32| 0.0;
    for inst in state.instances(&no_height) {
        if !ids.insert(inst.id) {
            return Err(format!("instance {:?} held twice", inst.id));
        }
        // The same (cell, index in the cell) in the world's function.
        let edited = is_edited(&inst.id.cell());
        let p = expected.get(&inst.id.cell()).and_then(|v| v.get(usize::from(inst.id.index())));
        let p = match p {
            Some(p) => p,
            // Past the world's records of an edited cell: planted.
            None if edited => continue,
            None => return Err(format!("instance {:?} is not in the world", inst.id)),
        };
        // Positions lie on the position grid, so the record's steps are the placement's exactly (compared as steps
        // in the cell: far from the origin an f32 world coordinate does not hold the grid); `Placement::params` is
        // sorted by slot, as the records' overrides are.
        let c = inst.id.cell();
        let record = state.cells().get(&c).and_then(|h| h.records.get(usize::from(inst.id.index())));
        let steps = world.steps(CellKey { x: c.x, z: c.z }, p);
        if u16::from(inst.species) != p.species
            || record.is_none_or(|r| [r.qx(), r.qz()] != steps)
            || (!edited && inst.params[..] != p.params[..])
            || inst.seed != canopy_worlds::world::instance_seed(world.seed, inst.id)
        {
            return Err(format!("instance {:?} differs from the world: {inst:?} vs {p:?}", inst.id));
        }
    }
    if state.stats().species_duplicates != 0 {
        return Err(format!("{} species received twice", state.stats().species_duplicates));
    }
    Ok(VerifySummary {
        cells: state.cells().len(),
        instances: ids.len(),
        species: state.species_held(),
        edited: edited_cells,
    })
}
