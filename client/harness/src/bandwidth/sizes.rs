//! Seed 001 §7's size table for Canopy's species: the encoded species (what is sent once) against its instances as
//! explicit geometry — counted as the paper counts it ([`canopy_worlds::mesh::explicit_bytes`]) and as a
//! quantised, meshoptimizer-compressed mesh ([`super::geometry::encode_mesh`]) — plus the fractal terrain against
//! a 1024² float height field (4 MiB).

use canopy_protocol::SpeciesGraph;
use canopy_worlds::amplify::{Budget, Instance, amplify};
use canopy_worlds::library;
use canopy_worlds::mesh::{MeshOptions, explicit_bytes, mesh};
use canopy_worlds::world::World;

use super::geometry::encode_mesh;

/// A 1024 × 1024 height field of 32-bit floats, bytes.
pub const HEIGHT_FIELD_BYTES: u64 = 1024 * 1024 * 4;

/// One row of the table: a species averaged over its first seeds, or the terrain.
#[derive(Clone, Debug, PartialEq)]
pub struct SizeRow {
    /// The species (or `terrain (world)`).
    pub name: String,
    /// Encoded bytes (postcard): what is streamed once.
    pub encoded: u64,
    /// Primitives per instance (mean).
    pub primitives: u64,
    /// Explicit bytes per instance as seed 001 §7 counts them (mean).
    pub explicit: u64,
    /// Triangles per instance mesh (mean).
    pub triangles: u64,
    /// Quantised mesh bytes per instance (mean): 16 bytes per vertex, 4 per index.
    pub quantised: u64,
    /// Quantised + meshopt-compressed + deflated bytes per instance (mean).
    pub compressed: u64,
    /// A fixed explicit alternative to compare with instead (the terrain's height field), if any.
    pub alternative: Option<(&'static str, u64)>,
}

impl SizeRow {
    /// Explicit (§7 count) over encoded.
    pub fn explicit_ratio(&self) -> f64 {
        self.explicit as f64 / self.encoded.max(1) as f64
    }

    /// Compressed mesh over encoded.
    pub fn compressed_ratio(&self) -> f64 {
        self.compressed as f64 / self.encoded.max(1) as f64
    }
}

/// One species' row, averaged over seeds `1..=seeds`.
pub fn species_row(name: &str, g: &SpeciesGraph, seeds: u32) -> SizeRow {
    let seeds = seeds.max(1);
    let encoded = g.encode().len() as u64;
    let mut sum = [0u64; 5];
    for seed in 1..=u64::from(seeds) {
        let Ok(s) = amplify(g, &Instance::new(seed), &Budget::default()) else { continue };
        let m = mesh(&s, &MeshOptions::default());
        let (_, size) = encode_mesh(&m).unwrap_or_default();
        for (acc, v) in sum.iter_mut().zip([
            s.primitives.len() as u64,
            explicit_bytes(&s) as u64,
            m.triangle_count() as u64,
            size.quantised as u64,
            size.compressed as u64,
        ]) {
            *acc += v;
        }
    }
    let n = u64::from(seeds);
    let alternative = (name == "terrain").then_some(("1024² f32 height field", HEIGHT_FIELD_BYTES));
    SizeRow {
        name: name.to_string(),
        encoded,
        primitives: sum[0] / n,
        explicit: sum[1] / n,
        triangles: sum[2] / n,
        quantised: sum[3] / n,
        compressed: sum[4] / n,
        alternative,
    }
}

/// The table: every embedded species averaged over seeds `1..=seeds`, then the world's terrain as the welcome
/// carries it (its species, tiling and corner heights) against a 1024² float height field.
pub fn table(world: &World, seeds: u32) -> Vec<SizeRow> {
    let mut rows: Vec<SizeRow> = library::SPECIES
        .iter()
        .filter_map(|entry| entry.load().ok().map(|g| species_row(entry.name(), &g, seeds)))
        .collect();
    let desc = canopy_server::session::terrain_desc(world);
    let encoded = postcard::to_allocvec(&desc).map(|v| v.len() as u64).unwrap_or(0);
    let squares = world.terrain.squares();
    let triangles = world.terrain.triangle_count();
    rows.push(SizeRow {
        name: format!("terrain (world, {}×{} squares)", squares[0], squares[1]),
        encoded,
        primitives: triangles,
        explicit: triangles * 36,
        triangles,
        quantised: 0,
        compressed: 0,
        alternative: Some(("1024² f32 height field", HEIGHT_FIELD_BYTES)),
    });
    rows
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_row_counts_the_encoding_and_the_geometry_of_its_instances() {
        let g = library::find("bush").unwrap().load().unwrap();
        let r = species_row("bush", &g, 2);
        assert_eq!(r.encoded, g.encode().len() as u64);
        let s = amplify(&g, &Instance::new(1), &Budget::default()).unwrap();
        assert!(r.primitives > 0 && r.explicit > 0 && r.triangles > 0);
        assert!(r.quantised > r.compressed && r.compressed > 0);
        assert_eq!(r.alternative, None);
        // Seed 1 alone gives that seed's counts.
        let one = species_row("bush", &g, 1);
        assert_eq!(one.explicit, explicit_bytes(&s) as u64);
        assert_eq!(one.primitives, s.primitives.len() as u64);
        assert!((r.explicit_ratio() - r.explicit as f64 / r.encoded as f64).abs() < 1e-9);
        let t = species_row("terrain", &library::find("terrain").unwrap().load().unwrap(), 1);
        assert_eq!(t.alternative, Some(("1024² f32 height field", HEIGHT_FIELD_BYTES)));
    }
}
