//! A moving client's record radius fitted to its link ([`link_radius`]): on a link too slow for the
//! radius it would like, a client asks for what the link carries at its speed over the records around it, so that
//! what it asks for arrives in time and the far view draws the rest. Bots, the bandwidth harness and `canopy walk`
//! use it.
//!
//! [`link_radius`]: canopy_protocol::aoi::AoiParams::link_radius

use canopy_protocol::messages::{ServerMsgKind, Welcome};

use crate::net::Connection;

/// A radius fitted to a link ([`link_radius`]).
///
/// [`link_radius`]: canopy_protocol::aoi::AoiParams::link_radius
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LinkFit {
    /// The link's rate, bits a second.
    pub link_bits: f64,
}

/// Bytes a record takes on the wire until enough have arrived to measure it (the highlands measured 7.44).
const PRIOR_RECORD_BYTES: f64 = 7.5;

/// Records received before their bytes on the wire are measured rather than assumed.
const MEASURED_AFTER_RECORDS: u64 = 1000;

impl LinkFit {
    /// The radius to ask for now, at most `cap`: [`link_radius`] at `speed` over the density of the
    /// cells held (the world's mean before any) with the bytes a record took on the wire so far.
    pub fn radius(&self, conn: &Connection, speed: f32, cap: f32) -> f32 {
        let records = conn.state().stats().records;
        let bytes = (records >= MEASURED_AFTER_RECORDS)
            .then(|| conn.frame_bytes_received()[ServerMsgKind::Cells] as f64 / records as f64);
        self.fitted(conn.welcome(), speed, cap, conn.state().record_density(), bytes)
    }

    /// The radius of the first viewpoint, before anything arrived: over the world's mean density.
    pub fn first_radius(&self, welcome: &Welcome, speed: f32, cap: f32) -> f32 {
        self.fitted(welcome, speed, cap, None, None)
    }

    fn fitted(&self, w: &Welcome, speed: f32, cap: f32, density: Option<f64>, bytes: Option<f64>) -> f32 {
        let g = &w.world.grid;
        let density = density.unwrap_or_else(|| {
            let cells =
                (f64::from(g.max.x) - f64::from(g.min.x) + 1.0) * (f64::from(g.max.z) - f64::from(g.min.z) + 1.0);
            f64::from(w.world.instances) / (cells * f64::from(g.cell_size) * f64::from(g.cell_size))
        });
        w.aoi.link_radius(self.link_bits, speed, density, bytes.unwrap_or(PRIOR_RECORD_BYTES)).min(cap)
    }

    /// The radius to ask for next, moving at `velocity` and asking for `current` now: [`LinkFit::radius`] once it
    /// moved by more than a tenth ([`LinkFit::settle`]).
    pub fn next(&self, conn: &Connection, current: f32, velocity: [f32; 2], cap: f32) -> f32 {
        let [vx, vz] = velocity;
        Self::settle(current, self.radius(conn, (vx * vx + vz * vz).sqrt(), cap))
    }

    /// The radius to ask for next: `fitted` if it moved by more than a tenth from `current`, else `current` (a
    /// changed radius re-plans the area of interest on both sides, so small changes are not worth it).
    pub fn settle(current: f32, fitted: f32) -> f32 {
        if (fitted - current).abs() > 0.1 * current { fitted } else { current }
    }
}

#[cfg(test)]
mod tests {
    use super::LinkFit;

    #[test]
    fn a_fitted_radius_changes_only_by_more_than_a_tenth() {
        assert_eq!(LinkFit::settle(200.0, 215.0), 200.0);
        assert_eq!(LinkFit::settle(200.0, 185.0), 200.0);
        assert_eq!(LinkFit::settle(200.0, 221.0), 221.0);
        assert_eq!(LinkFit::settle(200.0, 150.0), 150.0);
    }
}
