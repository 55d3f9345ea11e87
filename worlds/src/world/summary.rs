//! What a world holds, in words: the content summary of `canopy world stats`, and the estimate of a world too
//! large to expand from a sample of its cells (stratified over the bounds, chosen by ChaCha8 from the world seed).

use std::fmt::Write as _;

use super::{CellKey, Placement, World};
use crate::rng::{InstanceRng, child_key};

/// Salt of the sample's random stream.
const SAMPLE_SALT: u64 = 0x7361_6d70_6c65_0000;

/// Instances per species estimated from sampled cells.
#[derive(Clone, Debug, PartialEq)]
pub struct Estimate {
    /// Cells sampled.
    pub samples: usize,
    /// Cells in the bounds.
    pub cells: u64,
    /// Per species id: estimated instances in the whole world and its standard error.
    pub per_species: Vec<(f64, f64)>,
}

impl Estimate {
    /// Estimated instances of every species together.
    pub fn total(&self) -> f64 {
        self.per_species.iter().map(|e| e.0).sum()
    }

    /// The estimate, one line per species: `name  N ± SE`.
    pub fn describe(&self, world: &World) -> String {
        let mut s = String::new();
        let area = world.bounds.area() / 1e6;
        let _ = writeln!(
            s,
            "instances (estimated from {} of {} cells): {:.0} ({:.0} per km²)",
            self.samples,
            self.cells,
            self.total(),
            self.total() / area.max(f64::MIN_POSITIVE)
        );
        let width = world.species.iter().map(|sp| sp.name.len()).max().unwrap_or(0);
        for (id, (sp, (n, se))) in world.species.iter().zip(&self.per_species).enumerate() {
            let _ = writeln!(s, "  {id:>3} {:width$}  {n:>14.0} ± {se:.0}  ({})", sp.name, sp.source);
        }
        s
    }
}

impl World {
    /// `n` cells spread over the bounds: the bounds split into about `√n × √n` strata, one cell drawn uniformly in
    /// each (ChaCha8 from the world seed), so the same world always samples the same cells.
    pub fn sample_cells(&self, n: u32) -> Vec<CellKey> {
        let k = f64::from(n.max(1)).sqrt().ceil() as u64;
        let [w, d] = self.cell_dims.map(u64::from);
        let mut rng = InstanceRng::new(self.seed);
        let stream = child_key(self.seed ^ SAMPLE_SALT, 0);
        let mut out = Vec::new();
        for b in 0..k {
            for a in 0..k {
                if out.len() as u32 >= n {
                    break;
                }
                let (x0, x1) = (a * w / k, ((a + 1) * w / k).max(a * w / k + 1).min(w));
                let (z0, z1) = (b * d / k, ((b + 1) * d / k).max(b * d / k + 1).min(d));
                let word = rng.word(stream, b * k + a);
                let x = x0 + u64::from(word & 0xffff) * (x1 - x0) / 0x1_0000;
                let z = z0 + u64::from(word >> 16) * (z1 - z0) / 0x1_0000;
                out.push(CellKey { x: self.cell_min.x + x as i32, z: self.cell_min.z + z as i32 });
            }
        }
        out
    }

    /// The estimate from the placements of sampled cells: mean per cell × cells, per species, with the standard
    /// error of that mean.
    pub fn estimate(&self, sampled: &[Vec<Placement>]) -> Estimate {
        let cells = self.cell_count();
        let m = sampled.len().max(1) as f64;
        let per_species = (0..self.species.len())
            .map(|sp| {
                let counts: Vec<f64> =
                    sampled.iter().map(|l| l.iter().filter(|p| usize::from(p.species) == sp).count() as f64).collect();
                let mean = counts.iter().sum::<f64>() / m;
                let var = counts.iter().map(|c| (c - mean) * (c - mean)).sum::<f64>() / (m - 1.0).max(1.0);
                (mean * cells as f64, (var / m).sqrt() * cells as f64)
            })
            .collect();
        Estimate { samples: sampled.len(), cells, per_species }
    }

    /// A human summary: area, cells, terrain, species and instance counts per species.
    pub fn content_summary(&self) -> String {
        let mut s = String::new();
        let [w, d] = self.bounds.extent();
        let area_km2 = self.bounds.area() / 1e6;
        let n = self.instances.len();
        let _ = writeln!(s, "world {}: {w} m × {d} m = {area_km2:.2} km², seed {}", self.name, self.seed);
        if self.is_materialised() {
            let per_cell = self.cell_starts.windows(2).map(|w| w[1] - w[0]);
            let max_cell = per_cell.clone().max().unwrap_or(0);
            let empty = per_cell.filter(|&c| c == 0).count();
            let _ = writeln!(
                s,
                "cells: {} × {} = {} of {} m; instances per cell: mean {:.1}, max {max_cell}, {empty} empty",
                self.cell_dims[0],
                self.cell_dims[1],
                self.cell_count(),
                self.cell_size,
                n as f64 / self.cell_count() as f64,
            );
        } else {
            let _ = writeln!(
                s,
                "cells: {} × {} = {} of {} m, expanded on demand (more than {} cells)",
                self.cell_dims[0],
                self.cell_dims[1],
                self.cell_count(),
                self.cell_size,
                super::EAGER_CELLS,
            );
        }
        if let Some(f) = &self.fractal {
            let _ = writeln!(
                s,
                "terrain: fractal, control lattice {} m ({} × {} heights), depth {} ({} m), dimension {}, relief {} m",
                f.tile,
                f.dims[0],
                f.dims[1],
                f.depth,
                f.spacing(f.depth),
                f.dimension,
                f.relief,
            );
            let _ = writeln!(
                s,
                "populations: {} explicit instances, {} scatter rules; the instances are estimated by sampling cells",
                self.explicit_instances,
                self.rules.len()
            );
        }
        if !self.is_materialised() {
            return s;
        }
        let t = &self.terrain;
        let (lo, hi) = t.height_range();
        match &t.species.as_ref().filter(|_| self.fractal.is_none()) {
            Some(g) => {
                let _ = writeln!(
                    s,
                    "terrain: {} ({}), {} × {} tiles of {} m at depth {}: {} triangles, {} m grid, heights {lo:.1} to {hi:.1} m",
                    g.name,
                    t.source,
                    t.tiles[0],
                    t.tiles[1],
                    t.tile_size,
                    t.depth,
                    t.triangle_count(),
                    t.spacing(),
                );
            }
            None if self.fractal.is_none() => {
                let _ = writeln!(s, "terrain: flat at 0 m");
            }
            None => {}
        }
        let counts = self.species_counts();
        let with_params = self.instances.iter().filter(|p| !p.params.is_empty()).count();
        let values: usize = self.instances.iter().map(|p| p.params.len()).sum();
        let _ = writeln!(
            s,
            "instances: {n} ({:.0} per km²; {} explicit, {} from {} scatter rules); {with_params} carry {values} parameter values",
            n as f64 / area_km2.max(f64::MIN_POSITIVE),
            self.explicit_instances,
            n - self.explicit_instances as usize,
            self.rules.len(),
        );
        let width = self.species.iter().map(|sp| sp.name.len()).max().unwrap_or(0);
        let _ = writeln!(s, "species: {}", self.species.len());
        for (id, (sp, count)) in self.species.iter().zip(&counts).enumerate() {
            // Which parameters the instances carry, and how many distinct values each takes.
            let mut slots: Vec<u16> = Vec::new();
            for p in self.instances.iter().filter(|p| usize::from(p.species) == id) {
                for &(slot, _) in &p.params {
                    if !slots.contains(&slot) {
                        slots.push(slot);
                    }
                }
            }
            slots.sort_unstable();
            let params: Vec<String> = slots
                .iter()
                .map(|&slot| {
                    let name = sp.graph.params.get(usize::from(slot)).map_or("?", |p| p.name.as_str());
                    format!("{name}: {} values", self.param_values(id as u16, slot).len())
                })
                .collect();
            let params = if params.is_empty() { String::new() } else { format!("; {}", params.join(", ")) };
            let _ = writeln!(s, "  {id:>3} {:width$}  {count:>9} instances  ({}{params})", sp.name, sp.source);
        }
        s
    }
}
