//! `canopy world bake`: a world with the edits a server stored, folded into a manifest that loads and holds, cell
//! for cell, what the server serves.

use std::process::Command;

use canopy_protocol::record::ParamOverride;
use canopy_protocol::{CellCoord, InstanceRecord};
use canopy_server::edits::{CellEdit, EditStore, Overlay, SqliteEditStore, StoredEdit};
use canopy_server::session::{CellData, StoreHead};
use canopy_worlds::world::{CellKey, Placement, World};

const MANIFEST: &str = "seed 7\nbounds -64 -64 64 64\ncell 32\nspecies conifer conifer\nspecies bush bush\n\
scatter conifer {\n  spacing 6\n  param height = 10 .. 20 step 1\n}\nscatter bush {\n  spacing 4\n  avoid conifer 2\n}\n";

/// A cell's live instances as `(species, qx, qz, params)`, sorted.
type Live = Vec<(u8, u16, u16, Vec<(u16, u32)>)>;

fn quantised(world: &World, c: CellKey, placements: &[Placement]) -> (Vec<InstanceRecord>, Vec<ParamOverride>) {
    // As a server holds the cell.
    let grid = StoreHead::of_world(world).unwrap().world().grid;
    let d = CellData::from_placements(&grid, CellCoord::new(c.x, c.z), world.species.len(), placements).unwrap();
    (d.records.clone(), d.overrides.clone())
}

fn live(records: &[InstanceRecord], overrides: &[ParamOverride], felled: &[u16]) -> Live {
    let mut v: Live = records
        .iter()
        .enumerate()
        .filter(|(i, _)| !felled.contains(&(*i as u16)))
        .map(|(i, r)| {
            let p =
                overrides.iter().filter(|o| usize::from(o.record) == i).map(|o| (o.slot, o.value.to_bits())).collect();
            (r.species, r.qx(), r.qz(), p)
        })
        .collect();
    v.sort();
    v
}

#[test]
fn bake_folds_plants_fells_and_sets_into_a_manifest_that_serves_the_same() {
    let dir = tempfile::tempdir().unwrap();
    let manifest = dir.path().join("small.world");
    std::fs::write(&manifest, MANIFEST).unwrap();
    let world = World::load(&manifest).unwrap();
    let c = CellKey { x: 0, z: 0 };
    let placements = world.expand_cell(c);
    let n = placements.len() as u16;
    let conifers: Vec<u16> = (0..n).filter(|&i| placements[usize::from(i)].species == 0).collect();
    let height = world.species[0].graph.param_slot("height").unwrap();
    let cell = CellCoord::new(0, 0);
    let ops = [
        CellEdit::Fell { index: conifers[0] },
        CellEdit::Set { index: conifers[1], params: vec![(height, 30.0)] },
        CellEdit::Plant { index: n, record: InstanceRecord::new(1, 1000, 2000), params: vec![] },
        CellEdit::Plant { index: n + 1, record: InstanceRecord::new(0, 3000, 100), params: vec![(height, 12.5)] },
        CellEdit::Set { index: n + 1, params: vec![(height, 14.0)] },
        CellEdit::Plant { index: n + 2, record: InstanceRecord::new(0, 50, 50), params: vec![] },
        CellEdit::Fell { index: n + 2 },
    ];
    let log: Vec<StoredEdit> =
        ops.into_iter().enumerate().map(|(v, op)| StoredEdit { cell, version: v as u32 + 1, op }).collect();
    let data = dir.path().join("data");
    SqliteEditStore::open(&data).unwrap().append(&log).unwrap();

    let out = dir.path().join("elsewhere/baked.world");
    let o = Command::new(env!("CARGO_BIN_EXE_canopy"))
        .args([
            "world",
            "bake",
            manifest.to_str().unwrap(),
            "--data",
            data.to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
        ])
        .output()
        .unwrap();
    let text = format!("{}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr));
    assert!(o.status.success(), "{text}");
    assert!(text.contains("1 felled, 1 set, 2 planted"), "{text}");

    // The server's view of the cell: the world function's records under the overlay.
    let (records, overrides) = quantised(&world, c, &placements);
    let overlay = Overlay::from_log(n, &log).unwrap();
    let a = overlay.apply_to(&records, &overrides);
    let served = live(&a.records, &a.overrides, &a.felled);
    // The baked world, loaded from another directory (its species paths were made absolute).
    let baked = World::load(&out).unwrap();
    let bp = baked.expand_cell(c);
    let (br, bo) = quantised(&baked, c, &bp);
    assert_eq!(live(&br, &bo, &[]), served);
    assert_eq!(bp.len(), usize::from(n) - 1 + 2);
    for other in [CellKey { x: -1, z: 0 }, CellKey { x: 1, z: 1 }] {
        assert_eq!(baked.expand_cell(other), world.expand_cell(other));
    }

    // No store there: a clear error, nothing written.
    let none = dir.path().join("none.world");
    let o = Command::new(env!("CARGO_BIN_EXE_canopy"))
        .args(["world", "bake", "--data", dir.path().join("nothing").to_str().unwrap(), "-o", none.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("no edits stored there"));
    assert!(!none.exists());
}
