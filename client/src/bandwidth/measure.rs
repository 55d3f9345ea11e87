//! What the harness measures and how: bytes by message class with the transport's overhead as the remainder of
//! the UDP totals (so the classes add up to the bytes on the wire exactly), visible completeness against the
//! world's ground truth, and the per-bot time series and summaries.

use canopy_protocol::CellCoord;
use canopy_worlds::world::{CellKey, World};

use crate::state::ClientState;

/// One client's bytes, both directions, split by what they carried. The classes sum to `udp_rx + udp_tx`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Bytes {
    /// Species programs (procedural) — frames of species messages.
    pub species: u64,
    /// Instance records — frames of cell batches.
    pub records: u64,
    /// Explicit geometry (baselines) — frames of geometry chunks: meshes, species meshes, transforms.
    pub geometry: u64,
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
    /// Split a client's counters: frame bytes received by class (welcome, species, cells, release, geometry),
    /// frame bytes it sent, and its connection's UDP totals.
    pub fn split(frames_rx: [u64; 5], frames_tx: u64, udp_rx: u64, udp_tx: u64) -> Bytes {
        let [welcome, species, records, release, geometry] = frames_rx;
        let rx: u64 = frames_rx.iter().sum();
        Bytes {
            species,
            records,
            geometry,
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
        self.species + self.records + self.geometry + self.control + self.overhead
    }

    /// Add another client's bytes.
    pub fn add(&mut self, o: &Bytes) {
        self.species += o.species;
        self.records += o.records;
        self.geometry += o.geometry;
        self.control += o.control;
        self.overhead += o.overhead;
        self.udp_rx += o.udp_rx;
        self.udp_tx += o.udp_tx;
    }
}

/// Where every instance of the world stands, by cell: the ground truth visible completeness is measured against.
#[derive(Clone, Debug)]
pub struct GroundTruth {
    cell_size: f32,
    min: CellKey,
    dims: [u32; 2],
    /// `starts[i]..starts[i + 1]`: the ids of the `i`-th cell in row-major order.
    starts: Vec<u32>,
    /// (x, z) by instance id.
    positions: Vec<[f32; 2]>,
}

impl GroundTruth {
    /// The ground truth of a world.
    pub fn from_world(world: &World) -> GroundTruth {
        let dims = world.cell_dims();
        let min = world.first_cell();
        let mut starts = Vec::with_capacity(dims[0] as usize * dims[1] as usize + 1);
        for z in 0..dims[1] as i32 {
            for x in 0..dims[0] as i32 {
                starts.push(world.cell_instances(CellKey { x: min.x + x, z: min.z + z }).start);
            }
        }
        starts.push(world.instances.len() as u32);
        let positions = world.instances.iter().map(|p| [p.x, p.z]).collect();
        GroundTruth { cell_size: world.cell_size, min, dims, starts, positions }
    }

    /// A ground truth from cells in row-major order (`dims[0]` per row) starting at cell `min`: each cell's
    /// instance positions, ids consecutive.
    pub fn new(cell_size: f32, min: CellKey, dims: [u32; 2], cells: &[Vec<[f32; 2]>]) -> GroundTruth {
        assert_eq!(cells.len(), dims[0] as usize * dims[1] as usize, "one entry per cell");
        let mut starts = vec![0u32];
        let mut positions = Vec::new();
        for c in cells {
            positions.extend_from_slice(c);
            starts.push(positions.len() as u32);
        }
        GroundTruth { cell_size, min, dims, starts, positions }
    }

    /// Instances in the world.
    pub fn len(&self) -> usize {
        self.positions.len()
    }

    /// Whether the world has no instances.
    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
    }

    /// The cell of instance `id`.
    pub fn cell_of(&self, id: u32) -> CellCoord {
        let i = self.starts.partition_point(|&s| s <= id) - 1;
        let w = self.dims[0] as usize;
        CellCoord::new(self.min.x + (i % w) as i32, self.min.z + (i / w) as i32)
    }

    /// Ids of the instances within `distance` of `p` (on the ground plane), in increasing order.
    pub fn visible(&self, p: [f32; 2], distance: f32) -> Vec<u32> {
        let d2 = distance * distance;
        let cell = |v: f32, lo: i32, n: u32| ((v / self.cell_size).floor() as i64 - i64::from(lo)).clamp(0, i64::from(n) - 1);
        if self.dims[0] == 0 || self.dims[1] == 0 {
            return Vec::new();
        }
        let (x0, x1) = (cell(p[0] - distance, self.min.x, self.dims[0]), cell(p[0] + distance, self.min.x, self.dims[0]));
        let (z0, z1) = (cell(p[1] - distance, self.min.z, self.dims[1]), cell(p[1] + distance, self.min.z, self.dims[1]));
        let mut out = Vec::new();
        for z in z0..=z1 {
            for x in x0..=x1 {
                let i = z as usize * self.dims[0] as usize + x as usize;
                for id in self.starts[i]..self.starts[i + 1] {
                    let q = self.positions[id as usize];
                    let (dx, dz) = (q[0] - p[0], q[1] - p[1]);
                    if dx * dx + dz * dz <= d2 {
                        out.push(id);
                    }
                }
            }
        }
        out
    }
}

/// Whether a client holds instance `id`: its cell is held and the record has arrived.
pub fn holds(state: &ClientState, truth: &GroundTruth, id: u32) -> bool {
    let cell = truth.cell_of(id);
    state.cells().get(&cell).is_some_and(|h| id >= h.first_id && ((id - h.first_id) as usize) < h.records.len())
}

/// Visible completeness: of the instances within `distance` of `p`, how many `held` says the client holds.
/// Returns `(visible, held)`.
pub fn completeness(truth: &GroundTruth, p: [f32; 2], distance: f32, held: impl Fn(u32) -> bool) -> (usize, usize) {
    let visible = truth.visible(p, distance);
    let n = visible.iter().filter(|&&id| held(id)).count();
    (visible.len(), n)
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
    pub fn over<'a>(samples: impl IntoIterator<Item = &'a Sample>, keep: impl Fn(&Sample) -> bool) -> CompletenessStats {
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
        let b = Bytes::split([300, 2_000, 10_000, 50, 7], 400, 14_000, 1_000);
        assert_eq!(b.class_sum(), b.total());
        assert_eq!(b.total(), 15_000);
        assert_eq!((b.species, b.records, b.geometry, b.control), (2_000, 10_000, 7, 300 + 50 + 400));
        assert_eq!(b.overhead, (14_000 - 12_357) + (1_000 - 400));
        // Counters read a moment apart can see frames before their datagrams: the totals never fall below them.
        let odd = Bytes::split([0, 0, 500, 0, 0], 10, 400, 5);
        assert_eq!(odd.class_sum(), odd.total());
        let mut sum = b;
        sum.add(&odd);
        assert_eq!(sum.class_sum(), sum.total());
        assert_eq!(sum.total(), b.total() + odd.total());
    }

    fn truth() -> GroundTruth {
        // 2 × 2 cells of 10 m from (-1, 0): ids 0..2 in the first, 2 in the second, none, 3..5 in the last.
        let cells = vec![
            vec![[-5.0, 5.0], [-1.0, 1.0]],
            vec![[5.0, 5.0]],
            vec![],
            vec![[1.0, 11.0], [9.0, 19.0]],
        ];
        GroundTruth::new(10.0, CellKey { x: -1, z: 0 }, [2, 2], &cells)
    }

    #[test]
    fn ground_truth_finds_cells_and_visible_instances() {
        let t = truth();
        assert_eq!(t.len(), 5);
        assert_eq!(t.cell_of(0), CellCoord::new(-1, 0));
        assert_eq!(t.cell_of(1), CellCoord::new(-1, 0));
        assert_eq!(t.cell_of(2), CellCoord::new(0, 0));
        assert_eq!(t.cell_of(3), CellCoord::new(0, 1));
        assert_eq!(t.cell_of(4), CellCoord::new(0, 1));
        assert_eq!(t.visible([0.0, 0.0], 2.0), vec![1]);
        assert_eq!(t.visible([0.0, 5.0], 6.0), vec![0, 1, 2]);
        // (1, 11) is √37 > 6 away; from a little higher up it is in.
        assert_eq!(t.visible([0.0, 6.0], 6.0), vec![0, 1, 2, 3]);
        assert_eq!(t.visible([0.0, 0.0], 100.0), vec![0, 1, 2, 3, 4]);
        assert!(t.visible([500.0, 500.0], 10.0).is_empty());
        // The boundary counts as visible.
        assert_eq!(t.visible([5.0, 0.0], 5.0), vec![2]);
    }

    #[test]
    fn completeness_counts_what_is_held_of_what_is_visible() {
        let t = truth();
        assert_eq!(completeness(&t, [0.0, 6.0], 6.0, |id| id % 2 == 0), (4, 2));
        assert_eq!(completeness(&t, [0.0, 6.0], 6.0, |_| true), (4, 4));
        assert_eq!(completeness(&t, [0.0, 6.0], 6.0, |_| false), (4, 0));
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
    fn holds_reads_the_client_state() {
        use canopy_protocol::aoi::{AoiParams, Grid, Viewpoint};
        use canopy_protocol::messages::{ServerHandshake, ServerStreaming, TerrainDesc, Welcome, WorldInfo};
        use canopy_protocol::messages::SpeciesEntry;
        use canopy_protocol::{CellBatch, InstanceRecord, POSITION_STEPS, PROTOCOL_VERSION, ServerMsg, SpeciesHash};
        let worm = canopy_worlds::library::find("worm").unwrap().load().unwrap().encode();
        // Cell (-1, 0) holds ids 0..10, cell (0, 0) ids 10..14.
        let cells = vec![vec![[-5.0, 5.0]; 10], vec![[5.0, 5.0]; 4]];
        let t = GroundTruth::new(10.0, CellKey { x: -1, z: 0 }, [2, 1], &cells);
        let grid = Grid { origin: [0.0, 0.0], cell_size: 10.0, min: CellCoord::new(-1, 0), max: CellCoord::new(0, 0) };
        let terrain = TerrainDesc {
            graph: None,
            seed: 0,
            origin: [-10.0, 0.0],
            tile_size: 20.0,
            tiles: [1, 1],
            depth: 0,
            corners: vec![0.0; 4],
            params: vec![],
        };
        let welcome = Welcome {
            version: PROTOCOL_VERSION,
            world: WorldInfo { name: "t".into(), seed: 1, grid, position_steps: POSITION_STEPS, instances: 14, terrain },
            species: vec![SpeciesEntry { hash: SpeciesHash::of(&worm), size: worm.len() as u32 }],
            aoi: AoiParams { max_radius: 100.0, hysteresis: 10.0, lookahead_s: 0.0, max_lookahead: 0.0 },
        };
        let mut state = ClientState::new();
        state.hello("t").unwrap();
        state.on_welcome(ServerMsg::Handshake(ServerHandshake::Welcome(welcome))).unwrap();
        // Radius 4 at the centre of cell (0, 0): the area of interest is that cell alone.
        state.ready(Viewpoint::at(0, [5.0, 5.0], 4.0)).unwrap();
        assert!(!(0..14).any(|id| holds(&state, &t, id)));
        let records: Vec<InstanceRecord> = (0..2).map(|i| InstanceRecord::new(0, i, i)).collect();
        let batch = CellBatch::new(CellCoord::new(0, 0), 1, 10, 4, 0, records, &[]);
        state.handle(ServerMsg::Streaming(ServerStreaming::Cells(batch))).unwrap();
        let held: Vec<u32> = (0..14).filter(|&id| holds(&state, &t, id)).collect();
        assert_eq!(held, vec![10, 11]);
        // Everything visible from the cell's centre within 8 m is in that cell: 2 of 4 held.
        assert_eq!(completeness(&t, [5.0, 5.0], 8.0, |id| holds(&state, &t, id)), (4, 2));
    }
}
