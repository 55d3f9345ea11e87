//! Terrain as a function, drawn: a window of `N × N` lattice squares of a [`Fractal`] around the viewer, at a
//! recursion depth chosen for the viewer's height above the ground (recursion-depth LOD: a coarser depth is the
//! same surface with fewer levels, its lattice heights equal to the finer ones'), turned into a height grid
//! ([`Terrain::from_heights`]) that the terrain mesh and its chunked levels of detail draw as they draw any grid.
//!
//! The window is re-centred when the viewer moves more than an eighth of it (at least [`ALIGN`] squares) from its
//! centre, and its corner snaps to a multiple of [`ALIGN`] lattice squares, so the chunks and their coarser steps
//! sample the same lattice points before and after: only the squares entering and leaving the window change. Every rebuild is a new `Arc`, which
//! the renderer notices (`Arc::ptr_eq`) and uploads. The rebuild runs on the renderer's thread: a 256² window is
//! about 88,000 lattice heights over all levels and a 66,049-vertex mesh.

use std::sync::Arc;

use canopy_worlds::world::{Fractal, Terrain};
use glam::Vec3;

/// Lattice squares per window edge by default.
pub(crate) const WINDOW_SQUARES: u32 = 256;
/// The window's corner is a multiple of this many lattice squares (a terrain chunk's edge).
pub(crate) const ALIGN: i64 = 32;
/// The window covers at least this many metres per edge, however low the viewer.
pub(crate) const MIN_EXTENT: f64 = 1_500.0;
/// … and at least this many times the viewer's height above the ground: 28 reaches 21 km from 1,500 m up, the far
/// view's default range, so the forest of summary nodes stands on drawn ground to the horizon.
pub(crate) const EXTENT_PER_HEIGHT: f64 = 28.0;

/// A window of a fractal's lattice around the viewer, as a height grid.
#[derive(Clone, Debug)]
pub(crate) struct FractalWindow {
    fractal: Arc<Fractal>,
    squares: u32,
    depth: u32,
    lo: [i64; 2],
    terrain: Arc<Terrain>,
}

impl FractalWindow {
    /// A window of `squares` (at least [`ALIGN`], rounded down to a multiple of it) lattice squares per edge
    /// around `eye`.
    pub(crate) fn new(fractal: Arc<Fractal>, squares: u32, eye: Vec3) -> FractalWindow {
        let squares = (squares / ALIGN as u32).max(1) * ALIGN as u32;
        let depth = depth_for(&fractal, squares, eye, None);
        let lo = corner_for(&fractal, squares, depth, eye);
        let terrain = grid(&fractal, squares, depth, lo);
        FractalWindow { fractal, squares, depth, lo, terrain }
    }

    /// The fractal drawn.
    pub(crate) fn fractal(&self) -> &Arc<Fractal> {
        &self.fractal
    }

    /// The height grid of the window now.
    pub(crate) fn terrain(&self) -> &Arc<Terrain> {
        &self.terrain
    }

    /// The recursion depth drawn.
    #[cfg(test)]
    pub(crate) fn depth(&self) -> u32 {
        self.depth
    }

    /// Lattice indices of the window's corner with the smallest x and z (at [`FractalWindow::depth`]).
    #[cfg(test)]
    pub(crate) fn corner(&self) -> [i64; 2] {
        self.lo
    }

    /// Follow the viewer: rebuild the window when the viewer's height asks for another depth or the viewer has
    /// moved more than an eighth of the window (at least [`ALIGN`] squares) from its centre. True when rebuilt.
    pub(crate) fn update(&mut self, eye: Vec3) -> bool {
        let depth = depth_for(&self.fractal, self.squares, eye, Some(self.depth));
        let s = self.fractal.spacing(depth);
        let centre = |axis: usize, lo: i64| self.fractal.origin[axis] + (lo as f64 + f64::from(self.squares) / 2.0) * s;
        // The snapped corner leaves the viewer up to ALIGN squares off centre, so the slack is at least that.
        let slack = (f64::from(self.squares) / 8.0).max(ALIGN as f64) * s;
        let off =
            (f64::from(eye.x) - centre(0, self.lo[0])).abs().max((f64::from(eye.z) - centre(1, self.lo[1])).abs());
        let lo = corner_for(&self.fractal, self.squares, depth, eye);
        if depth == self.depth && (off <= slack || lo == self.lo) {
            return false;
        }
        self.depth = depth;
        self.lo = lo;
        self.terrain = grid(&self.fractal, self.squares, depth, self.lo);
        true
    }
}

/// The depth for a viewer at `eye`: the finest whose window covers [`MIN_EXTENT`] and [`EXTENT_PER_HEIGHT`] times
/// the height above the ground. The current depth is kept while it still covers that and is at most two levels
/// coarser than needed (hysteresis).
fn depth_for(f: &Fractal, squares: u32, eye: Vec3, current: Option<u32>) -> u32 {
    let above = (f64::from(eye.y) - f64::from(f.height(f64::from(eye.x), f64::from(eye.z)))).max(0.0);
    let wanted = (above * EXTENT_PER_HEIGHT).max(MIN_EXTENT);
    let extent = |d: u32| f64::from(squares) * f.spacing(d);
    if let Some(d) = current
        && extent(d) >= wanted
        && extent(d) <= 4.0 * wanted
    {
        return d;
    }
    (0..=f.depth).rev().find(|&d| extent(d) >= wanted).unwrap_or(0)
}

/// The window's corner for a viewer at `eye`: the viewer at its centre, snapped to [`ALIGN`].
fn corner_for(f: &Fractal, squares: u32, depth: u32, eye: Vec3) -> [i64; 2] {
    let s = f.spacing(depth);
    let at = |axis: usize, v: f32| {
        let i = ((f64::from(v) - f.origin[axis]) / s).floor() as i64 - i64::from(squares / 2);
        i.div_euclid(ALIGN) * ALIGN
    };
    [at(0, eye.x), at(1, eye.z)]
}

/// The height grid of lattice squares `lo .. lo + squares` at `depth`: vertex heights are the fractal's lattice
/// heights (rounded to f32 as [`Fractal::height`] rounds them).
fn grid(f: &Fractal, squares: u32, depth: u32, lo: [i64; 2]) -> Arc<Terrain> {
    let s = f.spacing(depth);
    let n = i64::from(squares);
    let world = |axis: usize, i: f64| f.origin[axis] + i * s;
    // Half a square inside the window's edges: the patch's squares are exactly the window's.
    let a = [world(0, lo[0] as f64 + 0.5), world(1, lo[1] as f64 + 0.5)];
    let b = [world(0, (lo[0] + n) as f64 - 0.5), world(1, (lo[1] + n) as f64 - 0.5)];
    let patch = f.patch(a, b, depth);
    let heights: Vec<f32> = (lo[1]..=lo[1] + n)
        .flat_map(|j| (lo[0]..=lo[0] + n).map(move |i| (i, j)))
        .map(|(i, j)| patch.lattice(i, j) as f32)
        .collect();
    let origin = [world(0, lo[0] as f64) as f32, world(1, lo[1] as f64) as f32];
    let t = Terrain::from_heights(origin, s as f32, [squares, squares], heights)
        .unwrap_or_else(|| Terrain::flat(origin, s as f32 * squares as f32));
    Arc::new(t)
}

#[cfg(test)]
mod tests {
    use canopy_worlds::world::World;

    use super::*;

    fn highlands() -> Arc<Fractal> {
        Arc::new(World::embedded("highlands").expect("embedded").fractal.expect("a fractal"))
    }

    /// Lattice point (i, j) of the window's depth → its vertex in the grid, if inside.
    fn vertex(w: &FractalWindow, i: i64, j: i64) -> Option<f32> {
        let (di, dj) = (i - w.lo[0], j - w.lo[1]);
        let n = i64::from(w.squares);
        ((0..=n).contains(&di) && (0..=n).contains(&dj)).then(|| w.terrain.vertex_height(di as u32, dj as u32))
    }

    #[test]
    fn recentring_keeps_heights_at_shared_lattice_points() {
        let f = highlands();
        let mut eye = Vec3::new(1234.0, 0.0, -5678.0);
        eye.y = f.height(f64::from(eye.x), f64::from(eye.z)) + 2.0;
        let mut w = FractalWindow::new(Arc::clone(&f), 64, eye);
        // Low down: the finest depth whose window covers the minimum extent.
        assert!(f64::from(w.squares) * f.spacing(w.depth()) >= MIN_EXTENT);
        assert!(f64::from(w.squares) * f.spacing(w.depth() + 1) < MIN_EXTENT);
        let before = w.clone();
        // A small step stays in the window; a long one re-centres it at the same depth.
        assert!(!w.update(eye + Vec3::new(10.0, 0.0, 0.0)));
        let moved = eye + Vec3::new(500.0, 0.0, 300.0);
        let moved = Vec3::new(moved.x, f.height(f64::from(moved.x), f64::from(moved.z)) + 2.0, moved.z);
        assert!(w.update(moved));
        assert_eq!(w.depth(), before.depth());
        assert_ne!(w.corner(), before.corner());
        let mut shared = 0;
        let s = f.spacing(w.depth());
        for j in before.lo[1]..=before.lo[1] + 64 {
            for i in before.lo[0]..=before.lo[0] + 64 {
                let (Some(a), Some(b)) = (vertex(&before, i, j), vertex(&w, i, j)) else { continue };
                assert_eq!(a.to_bits(), b.to_bits(), "lattice ({i}, {j})");
                // And the vertex is the fractal's own height there.
                let (x, z) = (f.origin[0] + i as f64 * s, f.origin[1] + j as f64 * s);
                assert_eq!(a.to_bits(), f.height(x, z).to_bits());
                shared += 1;
            }
        }
        assert!(shared > 500, "{shared} shared points");
    }

    #[test]
    fn higher_viewers_get_coarser_wider_windows_with_the_same_lattice_heights() {
        let f = highlands();
        let ground = f.height(0.0, 0.0);
        let low = FractalWindow::new(Arc::clone(&f), WINDOW_SQUARES, Vec3::new(0.0, ground + 10.0, 0.0));
        let high = FractalWindow::new(Arc::clone(&f), WINDOW_SQUARES, Vec3::new(0.0, ground + 20_000.0, 0.0));
        assert!(high.depth() < low.depth(), "{} vs {}", high.depth(), low.depth());
        let extent = f64::from(WINDOW_SQUARES) * f.spacing(high.depth());
        assert!(extent >= 20_000.0 * EXTENT_PER_HEIGHT, "{extent}");
        // A lattice point of the coarse depth inside the fine window has one height at both depths.
        let k = 1 << (low.depth() - high.depth());
        let (ci, cj) = (high.lo[0] + i64::from(WINDOW_SQUARES / 2), high.lo[1] + i64::from(WINDOW_SQUARES / 2));
        let coarse = vertex(&high, ci, cj).expect("in the coarse window");
        if let Some(fine) = vertex(&low, ci * k, cj * k) {
            assert_eq!(coarse.to_bits(), fine.to_bits());
        }
        let s = f.spacing(high.depth());
        let (x, z) = (f.origin[0] + ci as f64 * s, f.origin[1] + cj as f64 * s);
        assert_eq!(coarse.to_bits(), f.height_at_depth(x, z, low.depth()).to_bits());
        assert!(high.terrain().triangle_count() > 0);
    }
}
