//! Baked edits in a manifest: `fell` and `set` statements change the instance of that species at exactly that
//! position after every statement placed the cell (a felled instance still spaced its neighbours), and bad lines
//! say where.

use canopy_worlds::diag::SourceFile;
use canopy_worlds::world::{CellKey, World};

const BASE: &str = "seed 7\nbounds -64 -64 64 64\ncell 32\nspecies conifer conifer\nspecies bush bush\n\
scatter conifer {\n  spacing 6\n  param height = 10 .. 20 step 1\n}\nscatter bush {\n  spacing 4\n  avoid conifer 2\n}\n";

fn parse(text: &str) -> Result<World, String> {
    World::parse(&SourceFile::new("t.world", text), None).map_err(|d| d.to_string())
}

#[test]
fn fell_and_set_change_the_instance_at_that_position_only() {
    let base = parse(BASE).unwrap();
    let c = CellKey { x: 0, z: 0 };
    let before = base.expand_cell(c);
    let conifers: Vec<_> = before.iter().filter(|p| p.species == 0).collect();
    assert!(conifers.len() >= 3);
    let (a, b) = (conifers[0], conifers[1]);
    let height = base.species[0].graph.param_slot("height").unwrap();
    let spread = base.species[0].graph.param_slot("spread").unwrap();
    let edits = format!(
        "fell conifer at {} {}\nset conifer at {} {} spread=0.5 height=33\nfell bush at {} {}\n",
        a.x, a.z, b.x, b.z, a.x, a.z
    );
    let world = parse(&format!("{BASE}{edits}")).unwrap();
    let after = world.expand_cell(c);
    assert_eq!(after.len(), before.len() - 1, "one conifer felled; no bush stands exactly there");
    assert!(!after.iter().any(|p| p.species == 0 && p.x == a.x && p.z == a.z));
    let set = after.iter().find(|p| p.species == 0 && p.x == b.x && p.z == b.z).unwrap();
    let mut want = vec![(height, 33.0), (spread, 0.5)];
    want.sort_by_key(|p| p.0);
    assert_eq!(set.params, want);
    // Everything else, and every other cell, as before: the felled conifer still spaced the bushes around it.
    let rest: Vec<_> = before.iter().filter(|p| (p.x != a.x || p.z != a.z) && (p.x != b.x || p.z != b.z)).collect();
    let rest_after: Vec<_> = after.iter().filter(|p| !(p.x == b.x && p.z == b.z)).collect();
    assert_eq!(rest, rest_after);
    for other in [CellKey { x: -1, z: 0 }, CellKey { x: 1, z: -2 }] {
        assert_eq!(world.expand_cell(other), base.expand_cell(other));
    }
    // The whole world materialised holds the same.
    assert_eq!(world.instances.len(), base.instances.len() - 1);
}

#[test]
fn bad_edit_lines_say_where() {
    for (line, want) in [
        ("fell conifer at 1 2 height=3", "t.world:14:21: error: `fell` takes no parameters"),
        ("set conifer at 1 2", "t.world:14:16: error: `set` needs at least one name=value"),
        ("fell oak at 1 2", "t.world:14:6: error: unknown species `oak`"),
        ("set conifer at 1 2 girth=3", "t.world:14:20"),
        ("fell conifer at 100 2", "t.world:14:17: error: the position lies outside the world's bounds"),
    ] {
        let e = parse(&format!("{BASE}{line}\n")).unwrap_err();
        assert!(e.contains(want), "{line}: {e}");
    }
}
