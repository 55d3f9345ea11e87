//! What the harness measures and how: bytes by message class with the transport's overhead as the remainder of
//! the UDP totals (so the classes add up to the bytes on the wire exactly), visible completeness against the
//! world's ground truth, and the per-bot time series and summaries.

use std::ops::Range;
use std::sync::Arc;

use canopy_protocol::aoi::Grid;
use canopy_protocol::messages::ByKind;
use canopy_protocol::{CellCoord, InstanceId};
use canopy_worlds::world::{CellKey, World};

use canopy_client::state::ClientState;

/// One client's bytes, both directions, split by what they carried. The classes sum to `udp_rx + udp_tx`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Bytes {
    /// Species programs (procedural) — frames of species messages.
    pub species: u64,
    /// Instance records — frames of cell batches.
    pub records: u64,
    /// Explicit geometry (baselines) — frames of geometry chunks: meshes, species meshes, transforms.
    pub geometry: u64,
    /// Far-view summaries — frames of summaries messages.
    pub summaries: u64,
    /// Control: the welcome, releases, and everything the client sent (hello, ready, viewpoints).
    pub control: u64,
    /// Transport overhead: UDP payload bytes beyond the frames (QUIC headers, acknowledgements, handshake,
    /// retransmissions, padding), both directions.
    pub overhead: u64,
    /// UDP payload bytes received by the client.
    pub udp_rx: u64,
    /// UDP payload bytes sent by the client.
    pub udp_tx: u64,
}

impl Bytes {
    /// Split a client's counters: frame bytes received by class (welcome, species, cells, release, geometry, edit
    /// results, deltas, summaries: edit results and deltas count as control and records), frame bytes it sent, and
    /// its connection's UDP totals.
    pub fn split(frames_rx: ByKind<u64>, frames_tx: u64, udp_rx: u64, udp_tx: u64) -> Bytes {
        let ByKind([welcome, species, cells, release, geometry, edit_results, deltas, summaries]) = frames_rx;
        let (records, welcome) = (cells + deltas, welcome + edit_results);
        let rx = frames_rx.total();
        Bytes {
            species,
            records,
            geometry,
            summaries,
            control: welcome + release + frames_tx,
            overhead: udp_rx.saturating_sub(rx) + udp_tx.saturating_sub(frames_tx),
            udp_rx: udp_rx.max(rx),
            udp_tx: udp_tx.max(frames_tx),
        }
    }

    /// All bytes on the wire, both directions.
    pub fn total(&self) -> u64 {
        self.udp_rx + self.udp_tx
    }

    /// The sum of the classes (equal to [`Bytes::total`]).
    pub fn class_sum(&self) -> u64 {
        self.species + self.records + self.geometry + self.summaries + self.control + self.overhead
    }

    /// Add another client's bytes.
    pub fn add(&mut self, o: &Bytes) {
        self.species += o.species;
        self.records += o.records;
        self.geometry += o.geometry;
        self.summaries += o.summaries;
        self.control += o.control;
        self.overhead += o.overhead;
        self.udp_rx += o.udp_rx;
        self.udp_tx += o.udp_tx;
    }
}

/// The ground truth visible completeness is measured against: the world itself, read cell by cell over the cells
/// within view distance (the area of interest's [`Grid`]).
#[derive(Clone, Debug)]
pub struct GroundTruth {
    world: Arc<World>,
    grid: Grid,
}

impl GroundTruth {
    /// The ground truth of a world.
    pub fn new(world: Arc<World>) -> GroundTruth {
        let (first, dims) = (world.first_cell(), world.cell_dims());
        let grid = Grid {
            origin: world.cell_origin(CellKey { x: 0, z: 0 }),
            cell_size: world.cell_size,
            min: CellCoord::new(first.x, first.z),
            max: CellCoord::new(first.x + dims[0] as i32 - 1, first.z + dims[1] as i32 - 1),
        };
        GroundTruth { world, grid }
    }

    /// Instances in the world.
    pub fn len(&self) -> usize {
        self.world.instances.len()
    }

    /// Whether the world has no instances.
    pub fn is_empty(&self) -> bool {
        self.world.instances.is_empty()
    }

    /// Call `f` with each cell within `distance` of `p` and the indices in the cell of its instances within
    /// `distance` of `p` (on the ground plane; the boundary counts), cells in row-major order, indices increasing.
    fn each_cell(&self, p: [f32; 2], distance: f32, mut f: impl FnMut(CellCoord, &mut dyn Iterator<Item = u16>)) {
        let d2 = distance * distance;
        let mut cells = Vec::new();
        self.grid.cells_within(p, distance, &mut cells);
        for c in cells {
            let range = self.world.cell_instances(CellKey { x: c.x, z: c.z });
            let cell = &self.world.instances[range.start as usize..range.end as usize];
            // A cell the protocol can stream holds at most 65,535 instances (`GridStore` refuses more).
            let mut near = cell.iter().take(usize::from(u16::MAX)).enumerate().filter_map(|(i, q)| {
                let (dx, dz) = (q.x - p[0], q.z - p[1]);
                (dx * dx + dz * dz <= d2).then_some(i as u16)
            });
            f(c, &mut near);
        }
    }

    /// The instances within `distance` of `p` (on the ground plane): cells in row-major order, each cell's by index.
    pub fn visible(&self, p: [f32; 2], distance: f32) -> Vec<InstanceId> {
        let mut out = Vec::new();
        self.each_cell(p, distance, |c, indices| {
            out.extend(indices.map(|i| InstanceId::new(c, i).expect("a world's cells can be named")));
        });
        out
    }
}

/// The indices in cell `c` of the instances a client holds (their ids are `(c, index)`): the cell's records that
/// have arrived (empty if the cell is not held).
pub fn held_indices(state: &ClientState, c: CellCoord) -> Range<u16> {
    state.cells().get(&c).map_or(0..0, |h| 0..h.records.len() as u16)
}

/// Visible completeness: of the instances within `distance` of `p`, how many the client holds, where `held(c)`
/// gives the indices it holds in cell `c` (as [`held_indices`] reads them from a client's state; asked once per
/// cell). Returns `(visible, held)`.
pub fn completeness(
    truth: &GroundTruth,
    p: [f32; 2],
    distance: f32,
    held: impl Fn(CellCoord) -> Range<u16>,
) -> (usize, usize) {
    let (mut visible, mut n) = (0, 0);
    truth.each_cell(p, distance, |c, indices| {
        let have = held(c);
        for i in indices {
            visible += 1;
            n += usize::from(have.contains(&i));
        }
    });
    (visible, n)
}

/// The fraction `held / visible` (1 when nothing is visible).
pub fn fraction(visible: usize, held: usize) -> f64 {
    if visible == 0 { 1.0 } else { held as f64 / visible as f64 }
}

/// One sample of one bot.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Sample {
    /// Seconds since the scenario started.
    pub t: f64,
    /// The bot's phase: walking, refilling after the start or a teleport, or settling at the end.
    pub phase: SamplePhase,
    /// Position on the ground.
    pub position: [f32; 2],
    /// Bytes so far.
    pub bytes: Bytes,
    /// Instances within view distance.
    pub visible: usize,
    /// Of those, held.
    pub held: usize,
    /// Whether the area of interest was complete.
    pub aoi_complete: bool,
}

impl Sample {
    /// Visible completeness of this sample.
    pub fn completeness(&self) -> f64 {
        fraction(self.visible, self.held)
    }
}

/// What a bot was doing when a sample was taken.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SamplePhase {
    /// Filling its first area of interest (not yet complete once).
    Start,
    /// Walking with its area of interest complete at least once since the last jump.
    Walking,
    /// Refilling after a teleport (not yet complete since).
    Teleported,
    /// Stopped at the end, waiting for a complete area of interest.
    Settling,
}

impl SamplePhase {
    /// Its label in CSV files.
    pub fn label(self) -> &'static str {
        match self {
            SamplePhase::Start => "start",
            SamplePhase::Walking => "walking",
            SamplePhase::Teleported => "teleported",
            SamplePhase::Settling => "settling",
        }
    }
}

/// Summary statistics of visible completeness over samples.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct CompletenessStats {
    /// Samples counted.
    pub samples: usize,
    /// Instances visible, summed over samples.
    pub visible: u64,
    /// Of those, held.
    pub held: u64,
    /// The lowest per-sample completeness.
    pub min: f64,
}

impl CompletenessStats {
    /// Over the samples `keep` selects.
    pub fn over<'a>(
        samples: impl IntoIterator<Item = &'a Sample>,
        keep: impl Fn(&Sample) -> bool,
    ) -> CompletenessStats {
        let mut s = CompletenessStats { min: 1.0, ..CompletenessStats::default() };
        for x in samples.into_iter().filter(|x| keep(x)) {
            s.samples += 1;
            s.visible += x.visible as u64;
            s.held += x.held as u64;
            s.min = s.min.min(x.completeness());
        }
        s
    }

    /// Held over visible, pooled over samples (1 when nothing was visible).
    pub fn mean(&self) -> f64 {
        if self.visible == 0 { 1.0 } else { self.held as f64 / self.visible as f64 }
    }

    /// Add another bot's statistics.
    pub fn merge(&mut self, o: &CompletenessStats) {
        self.samples += o.samples;
        self.visible += o.visible;
        self.held += o.held;
        self.min = self.min.min(o.min);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn byte_classes_add_up_to_the_wire() {
        let b = Bytes::split(ByKind([300, 2_000, 10_000, 50, 7, 0, 0, 0]), 400, 14_000, 1_000);
        assert_eq!(b.class_sum(), b.total());
        assert_eq!(b.total(), 15_000);
        assert_eq!((b.species, b.records, b.geometry, b.control), (2_000, 10_000, 7, 300 + 50 + 400));
        assert_eq!(b.overhead, (14_000 - 12_357) + (1_000 - 400));
        // Counters read a moment apart can see frames before their datagrams: the totals never fall below them.
        let odd = Bytes::split(ByKind([0, 0, 500, 0, 0, 0, 0, 0]), 10, 400, 5);
        assert_eq!(odd.class_sum(), odd.total());
        let mut sum = b;
        sum.add(&odd);
        assert_eq!(sum.class_sum(), sum.total());
        assert_eq!(sum.total(), b.total() + odd.total());
    }

    /// A small world of 8 m cells: a species and one instance per `(x, z)`, in that order.
    fn world(bounds: &str, at: &[[f32; 2]]) -> Arc<World> {
        let mut src = format!("seed 1\nbounds {bounds}\ncell 8\nspecies worm worm\n");
        for [x, z] in at {
            src += &format!("instance worm at {x} {z}\n");
        }
        let file = canopy_worlds::diag::SourceFile::new("test.world", &src);
        Arc::new(World::parse(&file, None).unwrap_or_else(|d| panic!("{d}")))
    }

    fn truth() -> GroundTruth {
        // 3 × 3 cells of 8 m from (-1, 0): ids 0..2 in the first, 2 in the next, 3 in (0, 1), 4 in (1, 2).
        let w = world("-8 0 16 24", &[[-5.0, 5.0], [-1.0, 1.0], [5.0, 5.0], [1.0, 11.0], [9.0, 19.0]]);
        for (id, cell) in [(0, (-1, 0)), (1, (-1, 0)), (2, (0, 0)), (3, (0, 1)), (4, (1, 2))] {
            assert!(w.cell_instances(CellKey { x: cell.0, z: cell.1 }).contains(&id), "instance {id} in cell {cell:?}");
        }
        GroundTruth::new(w)
    }

    #[test]
    fn ground_truth_finds_cells_and_visible_instances() {
        let t = truth();
        assert_eq!(t.len(), 5);
        // By the world's index: the ids are (cell, index in the cell).
        let ids = |v: &[u32]| v.iter().map(|&i| t.world.instance_id(i)).collect::<Vec<_>>();
        assert_eq!(ids(&[0, 1, 2]), [(-1, 0, 0), (-1, 0, 1), (0, 0, 0)].map(|(x, z, i)| id(x, z, i)));
        assert_eq!(t.visible([0.0, 0.0], 2.0), ids(&[1]));
        assert_eq!(t.visible([0.0, 5.0], 6.0), ids(&[0, 1, 2]));
        // (1, 11) is √37 > 6 away; from a little higher up it is in.
        assert_eq!(t.visible([0.0, 6.0], 6.0), ids(&[0, 1, 2, 3]));
        assert_eq!(t.visible([0.0, 0.0], 100.0), ids(&[0, 1, 2, 3, 4]));
        assert!(t.visible([500.0, 500.0], 10.0).is_empty());
        // The boundary counts as visible.
        assert_eq!(t.visible([5.0, 0.0], 5.0), ids(&[2]));
    }

    fn id(x: i32, z: i32, index: u16) -> InstanceId {
        InstanceId::new(CellCoord::new(x, z), index).unwrap()
    }

    #[test]
    fn completeness_counts_what_is_held_of_what_is_visible() {
        let t = truth();
        // Of the visible 0..4: the even ones (the first of cell (-1, 0), cell (0, 0)'s only one).
        let even = |c: CellCoord| match (c.x, c.z) {
            (-1, 0) | (0, 0) => 0..1,
            _ => 0..0,
        };
        assert_eq!(completeness(&t, [0.0, 6.0], 6.0, even), (4, 2));
        assert_eq!(completeness(&t, [0.0, 6.0], 6.0, |_| 0..u16::MAX), (4, 4));
        assert_eq!(completeness(&t, [0.0, 6.0], 6.0, |_| 0..0), (4, 0));
        assert_eq!(fraction(4, 2), 0.5);
        assert_eq!(fraction(0, 0), 1.0);
        let s = |t, visible, held| Sample {
            t,
            phase: SamplePhase::Walking,
            position: [0.0; 2],
            bytes: Bytes::default(),
            visible,
            held,
            aoi_complete: false,
        };
        let samples = [s(0.0, 10, 10), s(1.0, 10, 5), s(2.0, 0, 0), s(3.0, 20, 20)];
        let c = CompletenessStats::over(&samples, |x| x.t >= 1.0);
        assert_eq!((c.samples, c.visible, c.held), (3, 30, 25));
        assert!((c.mean() - 25.0 / 30.0).abs() < 1e-12);
        assert_eq!(c.min, 0.5);
    }

    #[test]
    fn held_indices_read_the_client_state() {
        use canopy_protocol::aoi::{AoiParams, Viewpoint};
        use canopy_protocol::messages::SpeciesEntry;
        use canopy_protocol::messages::{ServerHandshake, ServerStreaming, TerrainDesc, Welcome, WorldInfo};
        use canopy_protocol::{CellBatch, InstanceRecord, POSITION_STEPS, PROTOCOL_VERSION, ServerMsg, SpeciesHash};
        let worm = canopy_worlds::library::find("worm").unwrap().load().unwrap().encode();
        // Cell (-1, 0) holds 10 instances, cell (0, 0) 4.
        let at: Vec<[f32; 2]> = [[-5.0, 5.0]; 10].into_iter().chain([[5.0, 5.0]; 4]).collect();
        let t = GroundTruth::new(world("-8 0 8 8", &at));
        let grid = Grid { origin: [0.0, 0.0], cell_size: 8.0, min: CellCoord::new(-1, 0), max: CellCoord::new(0, 0) };
        assert_eq!(grid, t.grid);
        let terrain = TerrainDesc::flat([-8.0, 0.0], 16.0);
        let welcome = Welcome {
            version: PROTOCOL_VERSION,
            world: WorldInfo {
                name: "t".into(),
                seed: 1,
                grid,
                position_steps: POSITION_STEPS,
                instances: 14,
                terrain,
            },
            species: vec![SpeciesEntry { hash: SpeciesHash::of(&worm), size: worm.len() as u32 }],
            aoi: AoiParams { max_radius: 100.0, hysteresis: 10.0, lookahead_s: 0.0, max_lookahead: 0.0 },
        };
        let mut state = ClientState::new();
        state.hello("t").unwrap();
        state.on_welcome(ServerMsg::Handshake(ServerHandshake::Welcome(welcome))).unwrap();
        // Radius 3 at the centre of cell (0, 0): the area of interest is that cell alone.
        state.ready(Viewpoint::at(0, [4.0, 4.0], 3.0)).unwrap();
        let cells = [CellCoord::new(-1, 0), CellCoord::new(0, 0)];
        assert!(cells.iter().all(|&c| held_indices(&state, c).is_empty()));
        let records: Vec<InstanceRecord> = (0..2).map(|i| InstanceRecord::new(0, i, i)).collect();
        let batch = CellBatch::new(CellCoord::new(0, 0), 1, 4, 0, records, &[]);
        state.handle(ServerMsg::Streaming(ServerStreaming::Cells(batch))).unwrap();
        assert_eq!(cells.map(|c| held_indices(&state, c)), [0..0, 0..2]);
        // Everything visible from the cell's centre within 8 m is in that cell: 2 of 4 held.
        assert_eq!(completeness(&t, [4.0, 4.0], 8.0, |c| held_indices(&state, c)), (4, 2));
    }
}
