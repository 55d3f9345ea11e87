//! The scripted paths bots walk (and fly): [`PathKind`], [`Walker`] (position, velocity and heading over time,
//! inside a rectangle), and the small deterministic generator that seeds them.
//!
//! A flight ([`PathKind::Flight`]) is straight legs joined by turns at a bounded rate, at `speed` and a constant
//! `altitude` above the terrain (terrain following: the height over the ground is the altitude wherever it flies).
//! Within two turning radii of an edge, heading outward, it turns back toward the middle of its rectangle; the turn
//! rate is at least the standard rate (3°/s) and at least `speed / (extent / 8)`, so a U-turn fits a quarter of the
//! rectangle however fast it flies. Position is clamped to the rectangle as a last resort.

use canopy_protocol::CellCoord;
use canopy_protocol::aoi::Grid;

use super::Mover;

/// The scripted path a bot walks.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PathKind {
    /// Straight lines, turning back at the world's edge.
    Line,
    /// A circle of 50–250 m radius.
    Circle,
    /// A random walk: a new heading every few seconds.
    Random,
    /// Stand still, then jump to a random place, again and again.
    Teleport,
    /// An aircraft: straight legs and turns at a bounded rate, at an altitude above the terrain.
    Flight,
}

impl PathKind {
    /// The paths with their names (the values of `--path`).
    pub const NAMES: [(&'static str, PathKind); 5] = [
        ("line", PathKind::Line),
        ("circle", PathKind::Circle),
        ("random", PathKind::Random),
        ("teleport", PathKind::Teleport),
        ("flight", PathKind::Flight),
    ];
}

impl std::fmt::Display for PathKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let name = PathKind::NAMES.iter().find(|(_, k)| k == self).map_or("?", |(n, _)| n);
        f.write_str(name)
    }
}

impl std::str::FromStr for PathKind {
    type Err = String;
    fn from_str(s: &str) -> Result<PathKind, String> {
        PathKind::NAMES.iter().find(|(n, _)| *n == s).map(|(_, k)| *k).ok_or_else(|| format!("no path `{s}`"))
    }
}

/// A small deterministic generator for paths and link losses (SplitMix64).
#[derive(Clone, Debug)]
pub(crate) struct Rng(pub(crate) u64);

impl Rng {
    pub(crate) fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        canopy_worlds::rng::mix64(self.0)
    }

    /// Uniform in `0..1` with 53 bits.
    pub(crate) fn unit_f64(&mut self) -> f64 {
        (self.next() >> 11) as f64 / (1u64 << 53) as f64
    }

    fn unit(&mut self) -> f32 {
        (self.next() >> 40) as f32 / (1u64 << 24) as f32
    }

    fn range(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * self.unit()
    }
}

/// A bot's walk: position, velocity and heading over time.
#[derive(Clone, Debug)]
pub struct Walker {
    kind: PathKind,
    speed: f32,
    lo: [f32; 2],
    hi: [f32; 2],
    rng: Rng,
    pos: [f32; 2],
    dir: [f32; 2],
    centre: [f32; 2],
    ring: f32,
    angle: f32,
    timer: f32,
    /// Flight: the heading being turned to (radians, as `yaw`), the turn rate (radians per second) and the height
    /// above the terrain (metres).
    target: f32,
    turn_rate: f32,
    altitude: f32,
}

/// The slowest turn of a flight: the standard rate, 3° a second.
pub const STANDARD_TURN_RATE: f32 = 3.0 * std::f32::consts::PI / 180.0;

/// `a` minus `b` as an angle in `-π..=π`.
fn angle_diff(a: f32, b: f32) -> f32 {
    let d = (a - b).rem_euclid(std::f32::consts::TAU);
    if d > std::f32::consts::PI { d - std::f32::consts::TAU } else { d }
}

impl Walker {
    /// A walker of `kind` at `speed` inside the rectangle `lo..hi`, seeded by `seed`.
    pub fn new(kind: PathKind, speed: f32, lo: [f32; 2], hi: [f32; 2], seed: u64) -> Walker {
        let mut rng = Rng(seed);
        let pos = [rng.range(lo[0], hi[0]), rng.range(lo[1], hi[1])];
        let a = rng.range(0.0, std::f32::consts::TAU);
        let ring = rng.range(50.0, 250.0).min((hi[0] - lo[0]).min(hi[1] - lo[1]) * 0.4);
        let centre = [pos[0].clamp(lo[0] + ring, hi[0] - ring), pos[1].clamp(lo[1] + ring, hi[1] - ring)];
        let extent = (hi[0] - lo[0]).min(hi[1] - lo[1]).max(1.0);
        let turn_rate = STANDARD_TURN_RATE.max(speed / (extent / 8.0));
        let mut w = Walker {
            kind,
            speed,
            lo,
            hi,
            rng,
            pos,
            dir: [a.sin(), a.cos()],
            centre,
            ring,
            angle: a,
            timer: 0.0,
            target: a,
            turn_rate,
            altitude: 0.0,
        };
        if kind == PathKind::Circle {
            w.pos = [centre[0] + ring * a.cos(), centre[1] + ring * a.sin()];
        }
        w
    }

    /// The same walk at `altitude` metres above the terrain (what a flight flies at; the others walk on the ground
    /// whatever it is).
    pub fn with_altitude(mut self, altitude: f32) -> Walker {
        self.altitude = altitude;
        self
    }

    /// Where the walker is in 3-D, on terrain `ground(x, z)`: at its altitude above the ground.
    pub fn position3(&self, ground: impl Fn(f32, f32) -> f32) -> [f32; 3] {
        let [x, z] = self.pos;
        [x, ground(x, z) + self.altitude, z]
    }

    /// How fast a flight turns, radians per second.
    pub fn turn_rate(&self) -> f32 {
        self.turn_rate
    }

    /// Jump to another walk of the same kind and speed in the same rectangle: a new start and heading, seeded
    /// from this walk's generator (deterministic for a given seed).
    pub fn jump(&mut self) {
        let seed = self.rng.next();
        *self = Walker::new(self.kind, self.speed, self.lo, self.hi, seed).with_altitude(self.altitude);
    }

    /// One step of a flight (see the module docs).
    fn fly(&mut self, h: f32) {
        let margin = 2.0 * self.speed / self.turn_rate;
        let outward = (0..2).any(|a| {
            (self.pos[a] - self.lo[a] < margin && self.dir[a] < 0.0)
                || (self.hi[a] - self.pos[a] < margin && self.dir[a] > 0.0)
        });
        self.timer -= h;
        if outward {
            let mid = [(self.lo[0] + self.hi[0]) * 0.5, (self.lo[1] + self.hi[1]) * 0.5];
            self.target = (mid[0] - self.pos[0]).atan2(mid[1] - self.pos[1]);
        } else if self.timer <= 0.0 {
            // A new leg: turn by 30°–150° either way, then fly straight for 8–30 s.
            self.timer = self.rng.range(8.0, 30.0);
            let turn = self.rng.range(0.52, 2.62);
            self.target = if self.rng.next() & 1 == 0 { self.angle + turn } else { self.angle - turn };
        }
        let most = self.turn_rate * h;
        self.angle += angle_diff(self.target, self.angle).clamp(-most, most);
        self.angle = angle_diff(self.angle, 0.0);
        self.dir = [self.angle.sin(), self.angle.cos()];
        for axis in 0..2 {
            let p = self.pos[axis] + self.dir[axis] * self.speed * h;
            self.pos[axis] = p.clamp(self.lo[axis], self.hi[axis]);
        }
    }
}

impl Mover for Walker {
    /// Advance by `dt` seconds; returns whether it teleported.
    fn step(&mut self, dt: f32) -> bool {
        let mut teleported = false;
        match self.kind {
            PathKind::Line | PathKind::Random => {
                if self.kind == PathKind::Random {
                    self.timer -= dt;
                    if self.timer <= 0.0 {
                        self.timer = self.rng.range(3.0, 8.0);
                        let a = self.rng.range(0.0, std::f32::consts::TAU);
                        self.dir = [a.sin(), a.cos()];
                    }
                }
                for axis in 0..2 {
                    let mut p = self.pos[axis] + self.dir[axis] * self.speed * dt;
                    if p < self.lo[axis] || p > self.hi[axis] {
                        self.dir[axis] = -self.dir[axis];
                        p = p.clamp(self.lo[axis], self.hi[axis]);
                    }
                    self.pos[axis] = p;
                }
            }
            PathKind::Circle => {
                self.angle += self.speed / self.ring.max(1.0) * dt;
                let (s, c) = self.angle.sin_cos();
                self.pos = [self.centre[0] + self.ring * c, self.centre[1] + self.ring * s];
                self.dir = [-s, c];
            }
            PathKind::Flight => {
                // Sub-steps of at most 0.1 s, so a long tick turns as a short one would.
                let mut left = dt.max(0.0);
                while left > 0.0 {
                    let h = left.min(0.1);
                    left -= h;
                    self.fly(h);
                }
            }
            PathKind::Teleport => {
                self.timer += dt;
                if self.timer >= 8.0 {
                    self.timer = 0.0;
                    self.pos = [self.rng.range(self.lo[0], self.hi[0]), self.rng.range(self.lo[1], self.hi[1])];
                    teleported = true;
                }
            }
        }
        teleported
    }
    /// Where the walker is.
    fn position(&self) -> [f32; 2] {
        self.pos
    }
    /// The heading (yaw, radians; direction `(sin yaw, cos yaw)`).
    fn yaw(&self) -> f32 {
        self.dir[0].atan2(self.dir[1])
    }
    /// The velocity, metres per second (zero for a teleporter).
    fn velocity(&self) -> [f32; 2] {
        match self.kind {
            PathKind::Teleport => [0.0, 0.0],
            _ => [self.dir[0] * self.speed, self.dir[1] * self.speed],
        }
    }
    /// The height above the terrain, metres.
    fn altitude(&self) -> f32 {
        self.altitude
    }
}

/// The rectangle of a grid's cells, inset by `margin` metres.
pub fn grid_rect(grid: &Grid, margin: f32) -> ([f32; 2], [f32; 2]) {
    let lo = grid.cell_origin(grid.min);
    let hi = grid.cell_origin(CellCoord::new(grid.max.x + 1, grid.max.z + 1));
    let m = margin.min((hi[0] - lo[0]) * 0.25).min((hi[1] - lo[1]) * 0.25);
    ([lo[0] + m, lo[1] + m], [hi[0] - m, hi[1] - m])
}

#[cfg(test)]
mod tests {
    use std::collections::HashSet;

    use canopy_worlds::world::{REGION_BLOCK, World};

    use super::*;

    fn dist(a: [f32; 2], b: [f32; 2]) -> f32 {
        ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)).sqrt()
    }

    /// Ten minutes at 250 m/s and 1500 m over the highlands (150 km of flight in a 102.4 km square): it keeps its
    /// speed and altitude, turns no faster than its rate, crosses cells and 2 km regions, turns back from the
    /// edges and never leaves the bounds.
    #[test]
    fn a_flight_keeps_speed_and_altitude_turns_at_its_rate_and_stays_in_bounds() {
        let world = World::embedded("highlands").unwrap();
        let (lo, hi) = (world.bounds.min, world.bounds.max.map(|v| v - 1.0));
        let mut w = Walker::new(PathKind::Flight, 250.0, lo, hi, 7).with_altitude(1500.0);
        assert_eq!(w.turn_rate(), STANDARD_TURN_RATE, "a 102 km square leaves room for the standard rate");
        let region = world.cell_size * REGION_BLOCK as f32;
        let (mut cells, mut regions) = (HashSet::new(), HashSet::new());
        let (mut turning, mut legs) = (0, 0);
        let dt = 0.1;
        for i in 0..6000 {
            let (p0, yaw0) = (w.position(), w.yaw());
            w.step(dt);
            let p = w.position();
            assert!((lo[0]..=hi[0]).contains(&p[0]) && (lo[1]..=hi[1]).contains(&p[1]), "left the bounds at {p:?}");
            assert!((dist(p0, p) - 250.0 * dt).abs() < 0.05, "step {i}: moved {} m", dist(p0, p));
            let v = w.velocity();
            assert!((dist(v, [0.0, 0.0]) - 250.0).abs() < 0.01);
            let turned = angle_diff(w.yaw(), yaw0).abs();
            assert!(turned <= STANDARD_TURN_RATE * dt * 1.001, "turned {turned} rad in {dt} s");
            if turned > 1e-6 {
                turning += 1;
            } else if turning > 0 {
                legs += 1;
                turning = 0;
            }
            if i % 20 == 0 {
                let ground = world.height(p[0], p[1]);
                let y = w.position3(|x, z| world.height(x, z))[1];
                assert!((y - ground - 1500.0).abs() < 0.01 && y > ground, "{y} over ground {ground}");
            }
            let c = world.cell_of(p[0].into(), p[1].into());
            cells.insert((c.x, c.z));
            regions.insert(((p[0] / region).floor() as i32, (p[1] / region).floor() as i32));
        }
        assert!(cells.len() > 2000, "{} cells crossed", cells.len());
        assert!(regions.len() > 40, "{} regions crossed", regions.len());
        assert!(legs >= 3, "{legs} turns completed: straight legs and turns");
    }

    /// The same speed in the 2 km default world: the turn rate rises so the U-turns fit, and it stays inside.
    #[test]
    fn a_fast_flight_in_a_small_world_turns_tighter_and_stays_inside() {
        let (lo, hi) = ([-1024.0, -1024.0], [1023.0, 1023.0]);
        for seed in 0..8 {
            let mut w = Walker::new(PathKind::Flight, 250.0, lo, hi, seed).with_altitude(300.0);
            assert!(w.turn_rate() > STANDARD_TURN_RATE);
            let mut clamped = 0;
            for _ in 0..1200 {
                let p0 = w.position();
                w.step(0.1);
                let p = w.position();
                assert!((lo[0]..=hi[0]).contains(&p[0]) && (lo[1]..=hi[1]).contains(&p[1]));
                if (dist(p0, p) - 25.0).abs() > 0.01 {
                    clamped += 1;
                }
            }
            assert_eq!(clamped, 0, "seed {seed}: the turns kept it off the edges");
        }
    }

    #[test]
    fn path_names_round_trip() {
        for (name, kind) in PathKind::NAMES {
            assert_eq!(name.parse::<PathKind>().unwrap(), kind);
            assert_eq!(kind.to_string(), name);
        }
        assert!("glide".parse::<PathKind>().is_err());
    }
}
