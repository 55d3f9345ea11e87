//! The ground a client stands on: a height grid ([`Terrain`]: a terrain species amplified, or flat) or the terrain
//! as a function ([`Fractal`]). Both answer the height at any point exactly as [`World::height`] does.

use std::sync::Arc;

use super::{Fractal, Terrain, World};

/// A world's ground, shared cheaply.
#[derive(Clone, Debug)]
pub enum Ground {
    /// A height grid.
    Grid(Arc<Terrain>),
    /// A fractal terrain, computed where needed.
    Fractal(Arc<Fractal>),
}

impl Ground {
    /// The ground of a loaded world: its fractal when it has one, else its terrain.
    pub fn of_world(world: &World) -> Ground {
        match &world.fractal {
            Some(f) => Ground::Fractal(Arc::new(f.clone())),
            None => Ground::Grid(Arc::new(world.terrain.clone())),
        }
    }

    /// Height at (x, z), bit for bit [`World::height`].
    pub fn height(&self, x: f32, z: f32) -> f32 {
        match self {
            Ground::Grid(t) => t.height(x, z),
            Ground::Fractal(f) => f.height(f64::from(x), f64::from(z)),
        }
    }

    /// Height and slope (degrees) at (x, z), bit for bit [`World::height_and_slope`].
    pub fn height_and_slope(&self, x: f32, z: f32) -> (f32, f32) {
        match self {
            Ground::Grid(t) => t.height_and_slope(x, z),
            Ground::Fractal(f) => f.height_and_slope(f64::from(x), f64::from(z)),
        }
    }

    /// Whether two grounds are the same shared value (the same `Arc`).
    pub fn ptr_eq(&self, other: &Ground) -> bool {
        match (self, other) {
            (Ground::Grid(a), Ground::Grid(b)) => Arc::ptr_eq(a, b),
            (Ground::Fractal(a), Ground::Fractal(b)) => Arc::ptr_eq(a, b),
            _ => false,
        }
    }
}

impl From<Arc<Terrain>> for Ground {
    fn from(t: Arc<Terrain>) -> Ground {
        Ground::Grid(t)
    }
}

impl From<Arc<Fractal>> for Ground {
    fn from(f: Arc<Fractal>) -> Ground {
        Ground::Fractal(f)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_grid_from_fractal_lattice_heights_is_the_fractal_on_its_triangles() {
        let f = Fractal::new(3, [-1024.0, -1024.0], 1024.0, 6, 2.3, 40.0, &[vec![10.0, 50.0], vec![30.0, 5.0]])
            .expect("valid");
        let patch = f.patch([-200.0, -100.0], [100.0, 150.0], f.depth);
        let ([i0, j0], [i1, j1]) = patch.window();
        let heights: Vec<f32> =
            (j0..=j1).flat_map(|j| (i0..=i1).map(move |i| (j, i))).map(|(j, i)| patch.lattice(i, j) as f32).collect();
        let s = f.spacing(f.depth);
        let origin = [(f.origin[0] + i0 as f64 * s) as f32, (f.origin[1] + j0 as f64 * s) as f32];
        let squares = [(i1 - i0) as u32, (j1 - j0) as u32];
        let grid = Terrain::from_heights(origin, s as f32, squares, heights).expect("a grid");
        assert_eq!(grid.squares(), squares);
        for k in 0..300 {
            let (x, z) = (-200.0 + k as f32 * 0.997, -100.0 + k as f32 * 0.831);
            let (a, b) = (grid.height(x, z), f.height(f64::from(x), f64::from(z)));
            assert!((a - b).abs() < 1e-3, "({x}, {z}): {a} vs {b}");
        }
        // At lattice points, exactly.
        for (i, j) in [(i0, j0), (i0 + 3, j0 + 5), (i1, j1)] {
            let [x, z] = grid.vertex_position((i - i0) as u32, (j - j0) as u32);
            assert_eq!(grid.height(x, z).to_bits(), f.height(f64::from(x), f64::from(z)).to_bits());
        }
        assert!(Terrain::from_heights(origin, 1.0, [2, 2], vec![0.0; 8]).is_none());
        assert!(Terrain::from_heights(origin, 1.0, [0, 2], Vec::new()).is_none());
        assert!(Terrain::from_heights(origin, f32::NAN, [1, 1], vec![0.0; 4]).is_none());
    }
}
