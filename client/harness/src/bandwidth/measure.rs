//! What the harness measures and how: bytes by message class with the transport's overhead as the remainder of
//! the UDP totals (so the classes add up to the bytes on the wire exactly), visible completeness against the
//! world's ground truth ([`super::truth`], re-exported here), and the per-bot time series and summaries.

use canopy_protocol::messages::ByKind;

pub use super::truth::{GroundTruth, HeldSnapshot, completeness, held_indices};

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
    /// results, deltas, summaries, grants, world function, far cells: edit results count as control, deltas and
    /// grants as records, the world function as species, far cells as summaries), frame bytes it sent, and its
    /// connection's UDP totals.
    pub fn split(frames_rx: ByKind<u64>, frames_tx: u64, udp_rx: u64, udp_tx: u64) -> Bytes {
        let ByKind(
            [welcome, species, cells, release, geometry, edit_results, deltas, summaries, grants, function, far_cells],
        ) = frames_rx;
        let summaries = summaries + far_cells;
        let (records, welcome) = (cells + deltas + grants, welcome + edit_results);
        let species = species + function;
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
    /// The view distance visible completeness is judged within, metres: the configured one, or the radius asked
    /// for at the sample.
    pub view: f32,
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
        let b = Bytes::split(ByKind([300, 2_000, 10_000, 50, 7, 0, 0, 0, 0, 0, 0]), 400, 14_000, 1_000);
        assert_eq!(b.class_sum(), b.total());
        assert_eq!(b.total(), 15_000);
        assert_eq!((b.species, b.records, b.geometry, b.control), (2_000, 10_000, 7, 300 + 50 + 400));
        assert_eq!(b.overhead, (14_000 - 12_357) + (1_000 - 400));
        // Counters read a moment apart can see frames before their datagrams: the totals never fall below them.
        let odd = Bytes::split(ByKind([0, 0, 500, 0, 0, 0, 0, 0, 0, 0, 0]), 10, 400, 5);
        assert_eq!(odd.class_sum(), odd.total());
        let mut sum = b;
        sum.add(&odd);
        assert_eq!(sum.class_sum(), sum.total());
        assert_eq!(sum.total(), b.total() + odd.total());
        // Far-view summaries are a class of their own.
        let far = Bytes::split(ByKind([0, 0, 1_000, 0, 0, 0, 0, 3_000, 0, 0, 0]), 10, 4_500, 50);
        assert_eq!((far.records, far.summaries, far.overhead), (1_000, 3_000, 500 + 40));
        assert_eq!(far.class_sum(), far.total());
    }
}
