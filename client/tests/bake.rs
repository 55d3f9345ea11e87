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

#[test]
fn a_manifest_with_species_files_bakes_to_another_directory_and_loads_there() {
    // The default world's manifest names its species by paths relative to it.
    let source = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../worlds/forest/forest.world");
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let cell = CellCoord::new(0, 0);
    let n = World::load(&source).unwrap().expand_cell(CellKey { x: 0, z: 0 }).len() as u16;
    // A fell, and a plant of a species this world does not have (a store written by another world).
    let alien = CellEdit::Plant { index: n, record: InstanceRecord::new(99, 10, 10), params: vec![] };
    let log =
        [StoredEdit { cell, version: 1, op: CellEdit::Fell { index: 0 } }, StoredEdit { cell, version: 2, op: alien }];
    SqliteEditStore::open(&data).unwrap().append(&log).unwrap();
    let out = dir.path().join("a/b/forest-baked.world");
    let o = Command::new(env!("CARGO_BIN_EXE_canopy"))
        .args(["world", "bake", source.to_str().unwrap(), "--data", data.to_str().unwrap(), "-o"])
        .arg(&out)
        .output()
        .unwrap();
    let text = format!("{}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr));
    assert!(o.status.success(), "{text}");
    assert!(text.contains("cell 0:0 version 2: the world cannot take it (species 99"), "{text}");
    let baked_text = std::fs::read_to_string(&out).unwrap();
    assert!(baked_text.contains("\"../../"), "species paths relative to the baked manifest:\n{baked_text}");
    let (world, baked) = (World::load(&source).unwrap(), World::load(&out).unwrap());
    let other = CellKey { x: 3, z: -2 };
    assert_eq!(baked.expand_cell(other), world.expand_cell(other));
    assert_eq!(baked.expand_cell(CellKey { x: 0, z: 0 }).len() + 1, world.expand_cell(CellKey { x: 0, z: 0 }).len());
    // Nothing but the manifest is left in its directory.
    let names: Vec<_> = std::fs::read_dir(out.parent().unwrap()).unwrap().map(|e| e.unwrap().file_name()).collect();
    assert_eq!(names, vec![std::ffi::OsString::from("forest-baked.world")]);
}
