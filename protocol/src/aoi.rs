//! The area of interest (seed 001 §4): which cells of the world a client's viewpoint needs, with look-ahead along
//! its velocity and hysteresis at the border. Pure geometry shared by the server (what to send, what to release)
//! and the client (what to keep, when its area of interest is complete), so both sides compute the same sets
//! bit for bit from the same viewpoint.
//!
//! A cell enters the area of interest when its square comes within the radius of the viewpoint or of the
//! look-ahead point (position + velocity × look-ahead time, capped); it leaves only when it is farther than the
//! radius plus the hysteresis from both, so walking along the border does not churn.

use serde::{Deserialize, Serialize};

use crate::netlimits;
use crate::record::CellCoord;

/// The world's cell grid on (x, z): cell `(i, j)` spans `origin + [i, i + 1) × [j, j + 1)` cell sizes; only cells
/// in `min..=max` exist.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Grid {
    /// Where cell `(0, 0)` starts, metres.
    pub origin: [f32; 2],
    /// Edge length of a cell, metres.
    pub cell_size: f32,
    /// The lowest cell on both axes.
    pub min: CellCoord,
    /// The highest cell on both axes (inclusive).
    pub max: CellCoord,
}

/// Why a grid is not acceptable.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum GridError {
    /// The cell size is not a positive finite number, or the origin is not finite.
    #[error("cell size {0} or origin is not positive and finite")]
    CellSize(f32),
    /// The cell range is empty or larger than [`netlimits::MAX_CELLS_PER_AXIS`] on an axis.
    #[error("cell range {min:?}..={max:?} is empty or too large")]
    Range {
        /// Lowest cell.
        min: CellCoord,
        /// Highest cell.
        max: CellCoord,
    },
}

impl Grid {
    /// Check the grid's numbers (decoders call this).
    pub fn validate(&self) -> Result<(), GridError> {
        if !(self.cell_size.is_finite() && self.cell_size > 0.0 && self.origin.iter().all(|v| v.is_finite())) {
            return Err(GridError::CellSize(self.cell_size));
        }
        let span = |a: i32, b: i32| i64::from(b) - i64::from(a);
        let max = i64::from(netlimits::MAX_CELLS_PER_AXIS);
        let (sx, sz) = (span(self.min.x, self.max.x), span(self.min.z, self.max.z));
        if !(0..max).contains(&sx) || !(0..max).contains(&sz) {
            return Err(GridError::Range { min: self.min, max: self.max });
        }
        Ok(())
    }

    /// Whether the cell exists.
    pub fn contains(&self, c: CellCoord) -> bool {
        (self.min.x..=self.max.x).contains(&c.x) && (self.min.z..=self.max.z).contains(&c.z)
    }

    /// Where the cell starts, metres.
    pub fn cell_origin(&self, c: CellCoord) -> [f32; 2] {
        [self.origin[0] + c.x as f32 * self.cell_size, self.origin[1] + c.z as f32 * self.cell_size]
    }

    /// Position `(x, z)`'s steps within cell `c`, as a record carries them ([`crate::record::quantize`] of each
    /// coordinate from the cell's origin, in f64: exact however far out the cell lies).
    pub fn steps(&self, c: CellCoord, x: f64, z: f64) -> [u16; 2] {
        let [ox, oz] = self.cell_origin(c);
        let q = |v: f64, o: f32| crate::record::quantize(v, o.into(), self.cell_size);
        [q(x, ox), q(z, oz)]
    }

    /// The cell holding point `(x, z)` (which may lie outside `min..=max`).
    pub fn cell_of(&self, x: f32, z: f32) -> CellCoord {
        let f = |v: f32, o: f32| {
            let i = ((v - o) / self.cell_size).floor();
            i.clamp(i32::MIN as f32, i32::MAX as f32) as i32
        };
        CellCoord { x: f(x, self.origin[0]), z: f(z, self.origin[1]) }
    }

    /// Squared distance from point `p` to the nearest point of the cell's square (0 inside).
    pub fn distance2(&self, c: CellCoord, p: [f32; 2]) -> f32 {
        let o = self.cell_origin(c);
        let d = |v: f32, lo: f32| (lo - v).max(0.0).max(v - (lo + self.cell_size));
        let (dx, dz) = (d(p[0], o[0]), d(p[1], o[1]));
        dx * dx + dz * dz
    }

    /// The vector from point `p` to the cell's centre.
    pub fn centre_offset(&self, c: CellCoord, p: [f32; 2]) -> [f32; 2] {
        let o = self.cell_origin(c);
        let h = self.cell_size * 0.5;
        [o[0] + h - p[0], o[1] + h - p[1]]
    }

    /// Squared distance from point `p` to the cell's centre.
    pub fn centre_distance2(&self, c: CellCoord, p: [f32; 2]) -> f32 {
        let [dx, dz] = self.centre_offset(c, p);
        dx * dx + dz * dz
    }

    /// Push every existing cell whose square comes within `radius` of `p` onto `out`, row by row.
    pub fn cells_within(&self, p: [f32; 2], radius: f32, out: &mut Vec<CellCoord>) {
        let lo = self.cell_of(p[0] - radius, p[1] - radius);
        let hi = self.cell_of(p[0] + radius, p[1] + radius);
        let r2 = radius * radius;
        for z in lo.z.max(self.min.z)..=hi.z.min(self.max.z) {
            for x in lo.x.max(self.min.x)..=hi.x.min(self.max.x) {
                let c = CellCoord { x, z };
                if self.distance2(c, p) <= r2 {
                    out.push(c);
                }
            }
        }
    }
}

/// The server's area-of-interest rules, announced in the welcome so the client computes the same sets.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct AoiParams {
    /// Largest radius a client may ask for, metres.
    pub max_radius: f32,
    /// How much farther than the radius a held cell may be before it is released, metres.
    pub hysteresis: f32,
    /// Seconds of velocity the look-ahead point leads the position by.
    pub lookahead_s: f32,
    /// Farthest the look-ahead point may lead, metres.
    pub max_lookahead: f32,
}

impl Default for AoiParams {
    fn default() -> Self {
        AoiParams { max_radius: 512.0, hysteresis: 32.0, lookahead_s: 2.0, max_lookahead: 128.0 }
    }
}

/// Ground a flying client wants per metre of altitude: out to where its line of sight dips about 27° below the
/// horizon (`atan(1/2)`); farther out the trees are the far field's business, not the instance stream's.
pub const FLIGHT_GROUND_PER_ALTITUDE: f32 = 2.0;

/// The least radius a flying client asks for, metres (low flight still wants the cells around it).
pub const FLIGHT_MIN_RADIUS: f32 = 128.0;

/// The share of a link's rate that the records of a moving client's area of interest may take in
/// [`AoiParams::link_radius`]: the rest carries the far view's summaries, control, transport, turns (a turn sweeps
/// more new ground than a straight leg) and the filling of what the look-ahead point leads into.
pub const LINK_RECORD_SHARE: f64 = 0.6;

/// The least radius [`AoiParams::link_radius`] gives, metres: the cells under the client, however slow the link.
pub const LINK_MIN_RADIUS: f32 = 32.0;

impl AoiParams {
    /// The radius a client flying `altitude` metres above the terrain at `speed` metres per second asks for (the
    /// viewpoint carries no height: altitude enters the area of interest only through this rule):
    ///
    /// `min(max_radius, max(FLIGHT_MIN_RADIUS, FLIGHT_GROUND_PER_ALTITUDE · altitude) + max(0, speed ·
    /// lookahead_s − max_lookahead))`
    ///
    /// — the ground of interest below and around, plus the part of the velocity look-ahead that the cap on the
    /// look-ahead point cuts off, so the cells the aircraft reaches within `lookahead_s` are asked for even when
    /// the look-ahead point ([`Aoi::ahead`]) stops short of them. The server caps every radius at `max_radius`, so
    /// asking for more would change nothing. Not-a-number inputs count as 0.
    pub fn flight_radius(&self, altitude: f32, speed: f32) -> f32 {
        let ground = (altitude.max(0.0) * FLIGHT_GROUND_PER_ALTITUDE).max(FLIGHT_MIN_RADIUS);
        let cut = (speed.abs() * self.lookahead_s - self.max_lookahead).max(0.0);
        (ground + cut).min(self.max_radius)
    }

    /// The largest radius whose records a link carries while the client moves: moving at `speed` metres per second,
    /// an area of interest of radius `r` takes in `2 · r · speed` square metres of new ground a second (its leading
    /// edge), holding `density` records a square metre at `record_bytes` bytes each on the wire, so
    ///
    /// `r = LINK_RECORD_SHARE · link_bits / 8 / (2 · speed · density · record_bytes)`
    ///
    /// within `LINK_MIN_RADIUS ..= max_radius` (at rest, or over an empty world, `max_radius`). A client on a slow
    /// link asks for this instead of more (with [`AoiParams::flight_radius`]: the smaller of the two), so that the
    /// records it asks for arrive in time and the far view draws the rest. Not-a-number inputs count as 0.
    pub fn link_radius(&self, link_bits: f64, speed: f32, density: f64, record_bytes: f64) -> f32 {
        let swept = 2.0 * f64::from(speed.abs()) * density.max(0.0) * record_bytes.max(0.0);
        let cap = self.max_radius.max(LINK_MIN_RADIUS);
        // Not moving, nothing to carry, or not a number: nothing limits the radius.
        if swept.is_nan() || swept <= 0.0 {
            return cap;
        }
        let r = LINK_RECORD_SHARE * link_bits.max(0.0) / 8.0 / swept;
        if r.is_nan() { LINK_MIN_RADIUS } else { (r.min(f64::from(cap)) as f32).max(LINK_MIN_RADIUS) }
    }
}

/// Why area-of-interest rules are not acceptable.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum AoiParamsError {
    /// A number is negative, not finite, or over its limit.
    #[error("area-of-interest parameters out of range: {0:?}")]
    Range(AoiParams),
}

impl AoiParams {
    /// Check the numbers (decoders call this).
    pub fn validate(&self) -> Result<(), AoiParamsError> {
        let ok = |v: f32, max: f32| v.is_finite() && (0.0..=max).contains(&v);
        if ok(self.max_radius, netlimits::MAX_AOI_RADIUS)
            && self.max_radius > 0.0
            && ok(self.hysteresis, netlimits::MAX_AOI_RADIUS)
            && ok(self.lookahead_s, 60.0)
            && ok(self.max_lookahead, netlimits::MAX_AOI_RADIUS)
        {
            Ok(())
        } else {
            Err(AoiParamsError::Range(*self))
        }
    }
}

/// Where a client looks from: sent whenever its viewpoint moves enough to matter.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Viewpoint {
    /// Increases with every viewpoint a client sends in one session.
    pub seq: u32,
    /// Position on (x, z), metres.
    pub position: [f32; 2],
    /// Heading on (x, z): direction `(sin yaw, cos yaw)`, radians.
    pub yaw: f32,
    /// Velocity on (x, z), metres per second (drives the look-ahead).
    pub velocity: [f32; 2],
    /// The radius the client asks for, metres (the server caps it at [`AoiParams::max_radius`]).
    pub radius: f32,
}

/// Why a viewpoint is not acceptable.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ViewpointError {
    /// A coordinate, speed, angle or radius is not finite or over its limit.
    #[error("viewpoint out of range")]
    Range,
}

impl Viewpoint {
    /// A viewpoint at rest at `position` looking along +z.
    pub fn at(seq: u32, position: [f32; 2], radius: f32) -> Viewpoint {
        Viewpoint { seq, position, yaw: 0.0, velocity: [0.0, 0.0], radius }
    }

    /// Check the numbers (decoders call this).
    pub fn validate(&self) -> Result<(), ViewpointError> {
        let within = |v: f32, max: f32| v.is_finite() && v.abs() <= max;
        let ok = self.position.iter().all(|&v| within(v, netlimits::MAX_COORDINATE))
            && self.velocity.iter().all(|&v| within(v, netlimits::MAX_SPEED))
            && within(self.yaw, 1.0e3)
            && self.radius.is_finite()
            && self.radius >= 0.0;
        if ok { Ok(()) } else { Err(ViewpointError::Range) }
    }

    /// The heading as a unit vector on (x, z).
    pub fn heading(&self) -> [f32; 2] {
        [self.yaw.sin(), self.yaw.cos()]
    }
}

/// A viewpoint resolved under the server's rules: the radius capped, the look-ahead point placed.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Aoi {
    /// The viewpoint's position.
    pub position: [f32; 2],
    /// Where the viewpoint will be after the look-ahead time (equal to `position` at rest).
    pub ahead: [f32; 2],
    /// The effective radius.
    pub radius: f32,
    /// Radius plus hysteresis: held cells farther than this from both points are released.
    pub outer: f32,
}

impl Aoi {
    /// Resolve a (validated) viewpoint under `params`.
    pub fn new(vp: &Viewpoint, params: &AoiParams) -> Aoi {
        let radius = vp.radius.min(params.max_radius).max(0.0);
        let mut lead = [vp.velocity[0] * params.lookahead_s, vp.velocity[1] * params.lookahead_s];
        let len2 = lead[0] * lead[0] + lead[1] * lead[1];
        let max2 = params.max_lookahead * params.max_lookahead;
        if len2 > max2 {
            let k = params.max_lookahead / len2.sqrt();
            lead = [lead[0] * k, lead[1] * k];
        }
        let ahead = [vp.position[0] + lead[0], vp.position[1] + lead[1]];
        Aoi { position: vp.position, ahead, radius, outer: radius + params.hysteresis }
    }

    fn within(&self, grid: &Grid, c: CellCoord, r: f32) -> bool {
        let r2 = r * r;
        grid.contains(c) && (grid.distance2(c, self.position) <= r2 || grid.distance2(c, self.ahead) <= r2)
    }

    /// Whether the cell belongs to the area of interest (it must be sent).
    pub fn is_inner(&self, grid: &Grid, c: CellCoord) -> bool {
        self.within(grid, c, self.radius)
    }

    /// Whether a held cell may be kept (it is not farther than the radius plus the hysteresis).
    pub fn is_kept(&self, grid: &Grid, c: CellCoord) -> bool {
        self.within(grid, c, self.outer)
    }

    /// Every cell of the area of interest, sorted and without repeats.
    pub fn inner_cells(&self, grid: &Grid) -> Vec<CellCoord> {
        let mut out = Vec::new();
        grid.cells_within(self.position, self.radius, &mut out);
        if self.ahead != self.position {
            grid.cells_within(self.ahead, self.radius, &mut out);
            out.sort_unstable();
            out.dedup();
        } else {
            out.sort_unstable();
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Viewpoints and grids reach the corners of the coordinate range (±2^20 cells of 64 m), and no farther.
    #[test]
    fn the_coordinate_range_reaches_two_to_the_twenty_cells() {
        let corner = 67_108_864.0;
        assert_eq!(Viewpoint::at(1, [corner, -corner], 160.0).validate(), Ok(()));
        assert_eq!(Viewpoint::at(1, [2.0 * corner, 0.0], 160.0).validate(), Err(ViewpointError::Range));
        let far = 1 << 20;
        let grid = |min: i32, max: i32| Grid {
            origin: [0.0, 0.0],
            cell_size: 64.0,
            min: CellCoord::new(min, min),
            max: CellCoord::new(max, max),
        };
        assert_eq!(grid(-far, far - 1).validate(), Ok(()));
        assert!(grid(-far, far).validate().is_err(), "one cell more than 2^21 per axis");
        // The cell of the far corner, from an f32 viewpoint there.
        assert_eq!(grid(-far, far - 1).cell_of(corner - 32.0, -corner), CellCoord::new(far - 1, -far));
    }

    #[test]
    fn the_link_radius_fits_the_records_of_the_leading_edge_into_a_share_of_the_link() {
        let p = AoiParams::default();
        // 1 Mbit/s, 250 m/s over 0.1 records a m² of 7.5 bytes: 0.6 · 125,000 / (2 · 250 · 0.1 · 7.5) = 200 m.
        assert_eq!(p.link_radius(1e6, 250.0, 0.1, 7.5), 200.0);
        assert_eq!(p.link_radius(1e6, -250.0, 0.1, 7.5), 200.0, "speed, not velocity");
        // Ten times the link: capped at the server's radius.
        assert_eq!(p.link_radius(1e7, 250.0, 0.1, 7.5), 512.0);
        // Slower or denser: smaller, but never under the cells below.
        assert_eq!(p.link_radius(1e6, 500.0, 0.1, 7.5), 100.0);
        assert_eq!(p.link_radius(1e3, 250.0, 0.1, 7.5), LINK_MIN_RADIUS);
        // At rest, over an empty world, or with nothing known: the cap.
        assert_eq!(p.link_radius(1e6, 0.0, 0.1, 7.5), 512.0);
        assert_eq!(p.link_radius(1e6, 250.0, 0.0, 7.5), 512.0);
        assert_eq!(p.link_radius(1e6, f32::NAN, 0.1, 7.5), 512.0);
        assert_eq!(p.link_radius(f64::NAN, 250.0, 0.1, 7.5), LINK_MIN_RADIUS);
        assert_eq!(p.link_radius(f64::INFINITY, 250.0, 0.1, 7.5), 512.0);
    }

    #[test]
    fn the_flight_radius_grows_with_altitude_and_the_cut_look_ahead_and_stops_at_the_cap() {
        let p = AoiParams { max_radius: 4096.0, hysteresis: 32.0, lookahead_s: 2.0, max_lookahead: 128.0 };
        assert_eq!(p.flight_radius(0.0, 0.0), FLIGHT_MIN_RADIUS, "on the ground, at rest");
        assert_eq!(p.flight_radius(40.0, 60.0), FLIGHT_MIN_RADIUS, "low and slow: the look-ahead point covers it");
        assert_eq!(p.flight_radius(1500.0, 0.0), 3000.0, "twice the altitude");
        // 250 m/s × 2 s = 500 m of look-ahead, 128 of them led by the look-ahead point: 372 m more radius.
        assert_eq!(p.flight_radius(1500.0, 250.0), 3372.0);
        assert_eq!(p.flight_radius(1500.0, -250.0), 3372.0, "speed, not velocity");
        assert_eq!(p.flight_radius(1e6, 250.0), 4096.0, "capped at max_radius");
        assert_eq!(AoiParams::default().flight_radius(1500.0, 250.0), AoiParams::default().max_radius);
        assert_eq!(p.flight_radius(f32::NAN, f32::NAN), FLIGHT_MIN_RADIUS);
        // The cells 2 s ahead at 250 m/s are inside the area of interest: within the radius of the position.
        let grid = Grid { origin: [0.0, 0.0], cell_size: 64.0, min: CellCoord::new(0, 0), max: CellCoord::new(99, 99) };
        let low = AoiParams { max_radius: 512.0, ..p };
        let r = low.flight_radius(100.0, 250.0);
        assert_eq!(r, 200.0 + 372.0_f32.min(512.0 - 200.0));
        let vp = Viewpoint { seq: 1, position: [1000.0, 1000.0], yaw: 0.0, velocity: [0.0, 250.0], radius: r };
        let aoi = Aoi::new(&vp, &low);
        assert_eq!(aoi.ahead, [1000.0, 1128.0]);
        assert!(aoi.is_inner(&grid, grid.cell_of(1000.0, 1000.0 + 250.0 * 2.0)));
    }
}
