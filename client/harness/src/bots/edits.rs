//! Bots that edit the world while they walk, and the numbers of live edits: how long an editor waits for its
//! answer, and how long an edit takes to become visible on the other bots holding its cell (fan-out).
//!
//! An editing bot ([`Editing`]) plants instances of a random species at random points near where it walks (within
//! half its area-of-interest radius), and every third edit fells one of its own acknowledged plants, paced at its
//! rate. Every bot of the process shares one [`FanOut`]: editors record when each acknowledged edit — a cell and the
//! version it made — was sent; every bot, when a delta takes a cell it holds from one version to a later one
//! ([`HeldVersions`]), records when it saw each version the delta covers. Each (bot, cell, version) counts once, and
//! an editor's own edits are never its samples. The record is bounded ([`FanOut::new`]): the oldest edits are
//! folded into the samples and forgotten.

use std::collections::{HashMap, VecDeque};
use std::ops::RangeInclusive;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use canopy_client::state::{Event, HeldCell};
use canopy_protocol::aoi::Grid;
use canopy_protocol::edit::{EditOp, EditOutcome, EditResult};
use canopy_protocol::sync::Locked;
use canopy_protocol::xorshift::XorShift64;
use canopy_protocol::{CellCoord, InstanceId};

use crate::numbers::percentile;

/// How a run's bots edit.
#[derive(Clone, Debug)]
pub struct EditPlan {
    /// Edits a second each editing bot makes.
    pub rate: f64,
    /// How many bots edit: the first `editors`; the others only watch.
    pub editors: usize,
    /// The editor token the editing bots connect with (the watchers connect read-only).
    pub token: Vec<u8>,
    /// When edits start: this long after the last bot of the ramp started to connect (so every bot holds its area
    /// of interest when the first edit is made).
    pub warmup: Duration,
    /// When edits stop: this long before the walk ends (so the last answers and deltas arrive while every bot still
    /// listens).
    pub grace: Duration,
    /// The shared record of edits sent and seen.
    pub fanout: Arc<FanOut>,
}

impl EditPlan {
    /// `rate` edits a second on each of the first `editors` bots, with `token`.
    pub fn new(rate: f64, editors: usize, token: Vec<u8>) -> EditPlan {
        EditPlan {
            rate,
            editors,
            token,
            warmup: Duration::from_secs(2),
            grace: Duration::from_secs(2),
            fanout: Arc::new(FanOut::new(FanOut::DEFAULT_CAPACITY)),
        }
    }
}

/// What one editing bot's edits came to.
#[derive(Clone, Debug, Default)]
pub struct EditStats {
    /// Plants sent.
    pub plants: u64,
    /// Fells sent.
    pub fells: u64,
    /// Answers by outcome: ok, denied, invalid, conflict.
    pub outcomes: [u64; 4],
    /// Edits sent and never answered.
    pub unanswered: u64,
    /// Send → answer latencies, every answered edit.
    pub answer: Vec<Duration>,
    /// The first reason given for a denied edit and for an invalid one, for the summary.
    pub refusals: [Option<String>; 2],
    /// When the first edit was sent.
    pub first_sent: Option<Instant>,
    /// When the last answer arrived.
    pub last_answer: Option<Instant>,
    /// Every acknowledged edit: what was asked, and the instance and cell version the answer named (checked
    /// against the store by [`super::ledger`]).
    pub acknowledged: Vec<Acknowledged>,
}

/// An edit a server acknowledged: durable from then on.
#[derive(Clone, Debug, PartialEq)]
pub struct Acknowledged {
    /// What the bot asked for.
    pub op: EditOp,
    /// The instance planted, felled or set.
    pub id: InstanceId,
    /// The version of the cell it made.
    pub version: u32,
}

impl EditStats {
    /// Edits sent.
    pub fn sent(&self) -> u64 {
        self.plants + self.fells
    }

    /// Edits answered.
    pub fn answered(&self) -> u64 {
        self.outcomes.iter().sum()
    }
}

fn outcome_index(o: &EditOutcome) -> usize {
    match o {
        EditOutcome::Ok { .. } => 0,
        EditOutcome::Denied(_) => 1,
        EditOutcome::Invalid(_) => 2,
        EditOutcome::Conflict => 3,
    }
}

/// One editing bot's edits: what it planted, what waits for an answer.
#[derive(Debug)]
pub struct Editing {
    bot: usize,
    rng: XorShift64,
    species: u8,
    reach: f32,
    made: u64,
    /// Acknowledged plants not felled yet.
    planted: Vec<InstanceId>,
    /// Requests sent and not answered: when, and what.
    pending: HashMap<u32, (Instant, EditOp)>,
    fanout: Arc<FanOut>,
    /// The counts and latencies so far.
    pub stats: EditStats,
}

impl Editing {
    /// Bot `bot`'s edits, seeded by `seed`, in a world of `species` species, planting within `reach` metres of
    /// where it walks.
    pub fn new(bot: usize, seed: u64, species: u8, reach: f32, fanout: Arc<FanOut>) -> Editing {
        Editing {
            bot,
            rng: XorShift64::new(seed ^ 0x5eed_ed17),
            species: species.max(1),
            reach,
            made: 0,
            planted: Vec::new(),
            pending: HashMap::new(),
            fanout,
            stats: EditStats::default(),
        }
    }

    fn unit(&mut self) -> f32 {
        (self.rng.next() >> 40) as f32 / (1u64 << 24) as f32
    }

    /// The next edit for a bot at `at` on `grid`: every third one fells one of its acknowledged plants (when it has
    /// one), the others plant a random species at a uniform point within `reach` of `at`, inside the grid.
    pub fn next_op(&mut self, at: [f32; 2], grid: &Grid) -> EditOp {
        self.made += 1;
        if self.made.is_multiple_of(3) && !self.planted.is_empty() {
            let i = (self.rng.next() % self.planted.len() as u64) as usize;
            return EditOp::Fell { id: self.planted.swap_remove(i) };
        }
        let species = (self.rng.next() % u64::from(self.species)) as u8;
        let r = self.reach * self.unit().sqrt();
        let a = std::f32::consts::TAU * self.unit();
        let (lo, hi) = super::grid_rect(grid, 0.5);
        let x = (at[0] + r * a.cos()).clamp(lo[0], hi[0]);
        let z = (at[1] + r * a.sin()).clamp(lo[1], hi[1]);
        EditOp::Plant { species, x, z, params: Vec::new() }
    }

    /// `op` went out as `request` at `at`.
    pub fn sent(&mut self, request: u32, op: &EditOp, at: Instant) {
        let plant = matches!(op, EditOp::Plant { .. });
        if plant {
            self.stats.plants += 1;
        } else {
            self.stats.fells += 1;
        }
        self.stats.first_sent.get_or_insert(at);
        self.pending.insert(request, (at, op.clone()));
    }

    /// An answer arrived at `now`; answers to requests this bot did not send are ignored.
    pub fn answered(&mut self, r: &EditResult, now: Instant) {
        let Some((at, op)) = self.pending.remove(&r.request) else { return };
        self.stats.answer.push(now.saturating_duration_since(at));
        self.stats.outcomes[outcome_index(&r.outcome)] += 1;
        self.stats.last_answer = Some(now);
        match &r.outcome {
            EditOutcome::Ok { id, version } => {
                if matches!(op, EditOp::Plant { .. }) {
                    self.planted.push(*id);
                }
                self.fanout.acknowledged(self.bot, id.cell(), *version, at);
                self.stats.acknowledged.push(Acknowledged { op, id: *id, version: *version });
            }
            EditOutcome::Denied(why) => drop(self.stats.refusals[0].get_or_insert_with(|| why.clone())),
            EditOutcome::Invalid(why) => drop(self.stats.refusals[1].get_or_insert_with(|| why.clone())),
            EditOutcome::Conflict => {}
        }
    }

    /// The counts at the end: what is still pending is unanswered.
    pub fn finish(mut self) -> EditStats {
        self.stats.unanswered = self.pending.len() as u64;
        self.stats
    }
}

/// The version each held cell is at, as far as a bot's events tell: what a delta took a cell from.
#[derive(Debug, Default)]
pub struct HeldVersions {
    versions: HashMap<CellCoord, u32>,
}

impl HeldVersions {
    /// Note an event just applied; `held` is the cell as the state holds it after the event. Returns the versions a
    /// delta made visible (from the one held before it, exclusive, to the one held now), if the event was a delta.
    pub fn apply(&mut self, ev: &Event, held: impl FnOnce(CellCoord) -> Option<u32>) -> Option<RangeInclusive<u32>> {
        match ev {
            Event::Records { cell, .. } => {
                // A batch: the cell is at the batch's version (a new grant may carry a newer one than a delta saw).
                if let Some(v) = held(*cell) {
                    self.versions.insert(*cell, v);
                }
                None
            }
            Event::Released(cell) => {
                self.versions.remove(cell);
                None
            }
            Event::Changed { cell, version } => {
                let before = self.versions.insert(*cell, *version);
                // A delta applies only from the version held; a cell seen first in a delta shows just its version.
                let from = before.map_or(*version, |b| b.saturating_add(1));
                (from <= *version).then_some(from..=*version)
            }
            _ => None,
        }
    }
}

/// One edit in the [`FanOut`] record.
#[derive(Debug, Default)]
struct Entry {
    /// The editor and when it sent the edit (once its answer came).
    sent: Option<(usize, Instant)>,
    /// Which bots saw the version, and when (each bot once).
    seen: Vec<(usize, Instant)>,
}

#[derive(Debug, Default)]
struct Inner {
    entries: HashMap<(CellCoord, u32), Entry>,
    order: VecDeque<(CellCoord, u32)>,
    samples: Vec<Duration>,
    per_edit: Vec<(Duration, u32)>,
    unmatched: u64,
}

impl Inner {
    fn entry(&mut self, key: (CellCoord, u32), capacity: usize) -> &mut Entry {
        if !self.entries.contains_key(&key) {
            while self.entries.len() >= capacity.max(1) {
                let Some(old) = self.order.pop_front() else { break };
                if let Some(e) = self.entries.remove(&old) {
                    self.fold(e);
                }
            }
            self.order.push_back(key);
        }
        self.entries.entry(key).or_default()
    }

    /// An edit leaves the record: its samples are taken.
    fn fold(&mut self, e: Entry) {
        let Some((editor, sent)) = e.sent else {
            // Versions seen but never acknowledged here: another process's edits, or an answer that never came.
            self.unmatched += e.seen.len() as u64;
            return;
        };
        let mut last = None;
        let mut watchers = 0;
        for (bot, at) in e.seen {
            if bot == editor {
                continue;
            }
            let d = at.saturating_duration_since(sent);
            self.samples.push(d);
            last = last.max(Some(d));
            watchers += 1;
        }
        if let Some(last) = last {
            self.per_edit.push((last, watchers));
        }
    }
}

/// The shared record of edits sent and seen (see the module docs).
#[derive(Debug)]
pub struct FanOut {
    inner: Mutex<Inner>,
    capacity: usize,
}

impl FanOut {
    /// How many edits the record keeps by default.
    pub const DEFAULT_CAPACITY: usize = 1 << 18;

    /// A record of at most `capacity` edits (the oldest are folded into the samples first).
    pub fn new(capacity: usize) -> FanOut {
        FanOut { inner: Mutex::new(Inner::default()), capacity }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Inner> {
        self.inner.locked()
    }

    /// `editor`'s edit sent at `sent` made `cell` `version` (its answer said so).
    pub fn acknowledged(&self, editor: usize, cell: CellCoord, version: u32, sent: Instant) {
        let mut inner = self.lock();
        let e = inner.entry((cell, version), self.capacity);
        e.sent.get_or_insert((editor, sent));
    }

    /// `bot` saw `cell` at each of `versions` at `at` (a delta covering them was applied).
    pub fn seen(&self, bot: usize, cell: CellCoord, versions: RangeInclusive<u32>, at: Instant) {
        let mut inner = self.lock();
        for v in versions {
            let e = inner.entry((cell, v), self.capacity);
            if !e.seen.iter().any(|(b, _)| *b == bot) {
                e.seen.push((bot, at));
            }
        }
    }

    /// Fold every edit still recorded and return the samples (the record is empty afterwards).
    pub fn report(&self) -> FanOutReport {
        let mut inner = self.lock();
        let entries: Vec<Entry> = {
            let Inner { entries, order, .. } = &mut *inner;
            order.drain(..).filter_map(|k| entries.remove(&k)).collect()
        };
        for e in entries {
            inner.fold(e);
        }
        let mut samples = std::mem::take(&mut inner.samples);
        samples.sort_unstable();
        let mut per_edit = std::mem::take(&mut inner.per_edit);
        per_edit.sort_unstable();
        FanOutReport { samples, per_edit, unmatched: std::mem::take(&mut inner.unmatched) }
    }
}

/// The fan-out samples of a run.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct FanOutReport {
    /// Send → visible on another bot, one per (bot, edit), sorted.
    pub samples: Vec<Duration>,
    /// Per edit seen by another bot: send → visible on the last bot that saw it, and how many saw it; sorted.
    pub per_edit: Vec<(Duration, u32)>,
    /// Versions bots saw whose edit no editor of the run had acknowledged while the record kept it: another
    /// client's edits, or answers (or deltas) later than the record's [`FanOut::DEFAULT_CAPACITY`] newest edits.
    pub unmatched: u64,
}

impl FanOutReport {
    /// p50, p99 and max of the per-(bot, edit) samples.
    pub fn visible(&self) -> Option<[Duration; 3]> {
        let at = |q| percentile(&self.samples, q);
        Some([at(0.5)?, at(0.99)?, at(1.0)?])
    }

    /// p50, p99 and max of the per-edit "visible on every bot that saw it" latencies.
    pub fn visible_on_all(&self) -> Option<[Duration; 3]> {
        let at = |q| percentile(&self.per_edit, q).map(|p| p.0);
        Some([at(0.5)?, at(0.99)?, at(1.0)?])
    }

    /// Mean and least number of bots that saw an edit (of the edits seen by any).
    pub fn watchers(&self) -> Option<(f64, u32)> {
        let n = self.per_edit.len();
        let min = self.per_edit.iter().map(|p| p.1).min()?;
        Some((self.per_edit.iter().map(|p| f64::from(p.1)).sum::<f64>() / n as f64, min))
    }
}

/// What every editing bot's edits came to.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct EditsSummary {
    /// Bots that edited.
    pub editors: usize,
    /// Plants sent.
    pub plants: u64,
    /// Fells sent.
    pub fells: u64,
    /// Answers by outcome: ok, denied, invalid, conflict.
    pub outcomes: [u64; 4],
    /// Edits never answered.
    pub unanswered: u64,
    /// Send → answer latency: p50, p90, p99, max.
    pub answer: Option<[Duration; 4]>,
    /// From the first edit sent to the last answer, over all bots.
    pub span: Duration,
    /// The first reason given for a denied edit and for an invalid one.
    pub refusals: [Option<String>; 2],
}

impl EditsSummary {
    /// Sum the editing bots' stats (`None` when no bot edited).
    pub fn new<'a>(stats: impl IntoIterator<Item = &'a EditStats>) -> Option<EditsSummary> {
        let mut s = EditsSummary::default();
        let mut answer = Vec::new();
        let (mut first, mut last) = (None::<Instant>, None::<Instant>);
        for e in stats {
            s.editors += 1;
            s.plants += e.plants;
            s.fells += e.fells;
            for (a, b) in s.outcomes.iter_mut().zip(e.outcomes) {
                *a += b;
            }
            s.unanswered += e.unanswered;
            answer.extend_from_slice(&e.answer);
            if let Some(t) = e.first_sent {
                first = Some(first.map_or(t, |f| f.min(t)));
            }
            last = last.max(e.last_answer);
            for (a, b) in s.refusals.iter_mut().zip(&e.refusals) {
                if a.is_none() {
                    a.clone_from(b);
                }
            }
        }
        if s.editors == 0 {
            return None;
        }
        answer.sort_unstable();
        let at = |q| percentile(&answer, q);
        s.answer = (|| Some([at(0.5)?, at(0.9)?, at(0.99)?, at(1.0)?]))();
        s.span = match (first, last) {
            (Some(a), Some(b)) => b.saturating_duration_since(a),
            _ => Duration::ZERO,
        };
        Some(s)
    }

    /// Edits sent.
    pub fn sent(&self) -> u64 {
        self.plants + self.fells
    }

    /// Acknowledged (applied and durable) edits a second over [`EditsSummary::span`].
    pub fn ok_per_second(&self) -> f64 {
        let s = self.span.as_secs_f64();
        if s > 0.0 { self.outcomes[0] as f64 / s } else { 0.0 }
    }
}

/// A digest of a held cell's content (records, parameter overrides in (record, slot) order, felled indices, total),
/// to compare the cell between clients: two clients holding a cell at one version must hold the same content,
/// however it reached them (one batch, or a batch and deltas).
pub fn cell_digest(h: &HeldCell) -> u64 {
    use std::hash::{Hash, Hasher};
    let mut s = std::hash::DefaultHasher::new();
    h.total.hash(&mut s);
    h.records.hash(&mut s);
    let mut o: Vec<(u16, u16, u32)> = h.overrides.iter().map(|o| (o.record, o.slot, o.value.to_bits())).collect();
    o.sort_unstable();
    o.hash(&mut s);
    h.felled.hash(&mut s);
    s.finish()
}

#[cfg(test)]
mod tests {
    use super::*;

    const C: CellCoord = CellCoord { x: 3, z: -2 };

    fn ms(n: u64) -> Duration {
        Duration::from_millis(n)
    }

    #[test]
    fn a_delta_covering_several_versions_counts_each_once_and_never_the_editors_own() {
        let f = FanOut::new(1024);
        let t0 = Instant::now();
        // Bot 0 made versions 1 and 2, bot 1 made version 3, sent 10 ms apart.
        f.acknowledged(0, C, 1, t0);
        f.acknowledged(0, C, 2, t0 + ms(10));
        // Bot 2 sees version 1 alone, then one delta covering 2 and 3, and (again) 1..=3.
        f.seen(2, C, 1..=1, t0 + ms(5));
        f.seen(2, C, 2..=3, t0 + ms(40));
        f.seen(2, C, 1..=3, t0 + ms(90));
        // Bot 0 sees its own versions (no samples) and bot 1's; bot 1 sees 1..=3 before its answer for 3 came.
        f.seen(0, C, 1..=3, t0 + ms(35));
        f.seen(1, C, 1..=3, t0 + ms(25));
        f.acknowledged(1, C, 3, t0 + ms(20));
        // A version nobody here made.
        f.seen(2, C, 7..=7, t0);
        let r = f.report();
        let mut want = vec![
            ms(5),  // bot 2, v1
            ms(30), // bot 2, v2 (40 − 10)
            ms(20), // bot 2, v3 (40 − 20)
            ms(15), // bot 0, v3 (35 − 20)
            ms(25), // bot 1, v1
            ms(15), // bot 1, v2 (25 − 10)
        ];
        want.sort();
        assert_eq!(r.samples, want);
        // Per edit, the last bot that saw it: v1 bot 1 at 25, v2 bot 2 at 30, v3 bot 2 at 20; two watchers each.
        assert_eq!(r.per_edit, vec![(ms(20), 2), (ms(25), 2), (ms(30), 2)]);
        assert_eq!(r.unmatched, 1);
        assert_eq!(r.watchers(), Some((2.0, 2)));
        assert_eq!(r.visible_on_all().unwrap(), [ms(25), ms(30), ms(30)]);
        assert_eq!(f.report(), FanOutReport::default(), "reported once");
    }

    #[test]
    fn the_record_is_bounded_and_folds_the_oldest_edits() {
        let f = FanOut::new(4);
        let t0 = Instant::now();
        for v in 1..=10 {
            f.acknowledged(0, C, v, t0);
            f.seen(1, C, v..=v, t0 + ms(u64::from(v)));
        }
        assert!(f.lock().entries.len() <= 4);
        let r = f.report();
        assert_eq!(r.samples, (1..=10).map(ms).collect::<Vec<_>>());
        // A version seen again after it was folded has no sending time any more: it is not a sample.
        f.seen(1, C, 1..=1, t0 + ms(500));
        assert_eq!(f.report().unmatched, 1);
    }

    #[test]
    fn held_versions_give_the_versions_a_delta_covers() {
        let mut h = HeldVersions::default();
        let records = Event::Records { cell: C, count: 4, complete: true };
        assert_eq!(h.apply(&records, |_| Some(2)), None);
        assert_eq!(h.apply(&Event::Changed { cell: C, version: 5 }, |_| Some(5)), Some(3..=5));
        assert_eq!(h.apply(&Event::Changed { cell: C, version: 6 }, |_| Some(6)), Some(6..=6));
        // Released, granted again at a later version by a batch: the next delta covers only what follows.
        assert_eq!(h.apply(&Event::Released(C), |_| None), None);
        assert_eq!(h.apply(&records, |_| Some(8)), None);
        assert_eq!(h.apply(&Event::Changed { cell: C, version: 9 }, |_| Some(9)), Some(9..=9));
        // A cell first seen in a delta: its version alone.
        let d = CellCoord::new(0, 0);
        assert_eq!(h.apply(&Event::Changed { cell: d, version: 4 }, |_| Some(4)), Some(4..=4));
    }

    #[test]
    fn editing_plants_near_the_walker_and_fells_only_its_own_acknowledged_plants() {
        let grid = Grid { origin: [0.0, 0.0], cell_size: 64.0, min: CellCoord::new(-8, -8), max: CellCoord::new(7, 7) };
        let fanout = Arc::new(FanOut::new(64));
        let mut e = Editing::new(3, 9, 5, 40.0, Arc::clone(&fanout));
        let t0 = Instant::now();
        let mut planted = Vec::new();
        for request in 0..30u32 {
            let op = e.next_op([100.0, -50.0], &grid);
            match &op {
                EditOp::Plant { species, x, z, params } => {
                    assert!(*species < 5 && params.is_empty());
                    assert!(((x - 100.0).powi(2) + (z + 50.0).powi(2)).sqrt() <= 40.0 + 1e-3, "({x}, {z})");
                }
                EditOp::Fell { id } => assert!(planted.contains(id), "fells only its own plants"),
                EditOp::Set { .. } => panic!("bots do not set"),
            }
            e.sent(request, &op, t0);
            // Every plant is acknowledged, at a new index of cell C.
            if let EditOp::Plant { .. } = op {
                let id = InstanceId::new(C, request as u16).unwrap();
                planted.push(id);
                let r = EditResult { request, outcome: EditOutcome::Ok { id, version: request + 1 } };
                e.answered(&r, t0 + ms(3));
            }
        }
        let s = e.finish();
        assert_eq!((s.plants, s.fells), (20, 10), "every third edit a fell once a plant is acknowledged");
        assert_eq!((s.outcomes[0], s.unanswered), (20, 10));
        assert!(s.answer.iter().all(|d| *d == ms(3)));
    }
}
