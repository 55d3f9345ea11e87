//! What a bots run measured, summed over the bots: completeness, latencies, bytes, edits and their fan-out, the
//! check against the world and between bots, reconnects, and the edit ledger's one line. A [`Shard`] holds the
//! raw numbers of a group of bots, for runs split over processes.

use std::collections::HashMap;
use std::time::Duration;

use canopy_protocol::CellCoord;
use canopy_protocol::messages::ServerMsgKind;
use serde::{Deserialize, Serialize};

use super::{Acknowledged, AoiSamples, BotReport, EditLedger, EditsSummary, FanOut, FanOutReport};
use crate::numbers::percentile;

/// Everything a bots run measured.
#[derive(Clone, Debug)]
pub struct BotsSummary {
    /// Bots run.
    pub bots: usize,
    /// Bots that failed (connection or protocol error, or no complete area of interest at the end).
    pub failed: usize,
    /// Bots that ended with a complete area of interest.
    pub complete: usize,
    /// Bots whose final state matched the world (of those checked).
    pub verified: usize,
    /// Bots checked against the world.
    pub checked: usize,
    /// The first failures' messages.
    pub errors: Vec<String>,
    /// Latency percentiles (p50, p90, p99, max) of area-of-interest change → complete.
    pub latency: Option<[Duration; 4]>,
    /// Latency percentiles of connect → first complete area of interest.
    pub first_complete: Option<[Duration; 4]>,
    /// Connect → the last far-view node a bot got (p50, p90, p99, max): at rest, the time to a full horizon.
    pub far_settled: Option<[Duration; 4]>,
    /// Latency samples.
    pub samples: usize,
    /// Records received by all bots.
    pub records: u64,
    /// Frame bytes of cell batches per record received.
    pub batch_bytes_per_record: f64,
    /// UDP payload bytes per record received (species, releases, QUIC framing and acknowledgements included).
    pub udp_bytes_per_record: f64,
    /// Species received over the wire by all bots.
    pub species_received: u64,
    /// Far-view summary nodes received by all bots.
    pub summary_nodes: u64,
    /// Frame bytes of summaries messages, all bots.
    pub summary_bytes: u64,
    /// Frame bytes of cell batches, all bots.
    pub batch_bytes: u64,
    /// Species received twice by one bot.
    pub species_duplicates: u64,
    /// Every bot's area of interest sampled while walking.
    pub moving: AoiSamples,
    /// Wall time of the whole run.
    pub wall: Duration,
    /// Cells that edits changed, held at the end by the bots checked: compared with the world only as far as its
    /// function still decides them ([`verify_with`]).
    pub edited_checked: usize,
    /// What the bots' edits came to (`None`: no bot edited).
    pub edits: Option<EditsSummary>,
    /// How soon edits reached the other bots (`None`: not measured; [`BotsSummary::with_fanout`]).
    pub fanout: Option<FanOutReport>,
    /// Edited (cell, version) pairs held at the end by two bots or more, compared between them.
    pub edited_compared: usize,
    /// Of those, the pairs whose content differs between bots.
    pub edited_differ: usize,
    /// Sessions resumed on another edge after an edge was lost, all bots.
    pub reconnects: u64,
    /// How long those fail-overs took (error → resumed): p50, p90, p99, max.
    pub failover: Option<[Duration; 4]>,
    /// Every acknowledged edit checked against the edit store (`None`: not checked; [`BotsSummary::with_ledger`]).
    pub ledger: Option<EditLedger>,
}

/// How many failures' messages a summary (and a shard) keeps: the first ones, in the order of the bots' ids.
const ERRORS: usize = 10;

/// The percentiles a summary prints (p50, p90, p99, max) of samples in any order: sorted here, in place.
fn percentiles(v: &mut [Duration]) -> Option<[Duration; 4]> {
    v.sort_unstable();
    let at = |q: f64| percentile(v, q);
    Some([at(0.5)?, at(0.9)?, at(0.99)?, at(1.0)?])
}

/// The raw numbers of a group of bots that a [`BotsSummary`] is computed from: counts and sums, and every sample
/// its percentiles are taken over, so that shards of disjoint groups [`merge`](Shard::merge) into the shard of
/// their union and the percentiles of the union are exact (not percentiles of percentiles).
///
/// `canopy bots --processes N` runs each group in its own process, which writes its shard ([`Shard::encode`]) for
/// the parent to merge. What edits measured (their answers, the edited cells compared between bots, fan-out, the
/// ledger) is not in a shard: bots that edit run in one process, and [`BotsSummary::new`] adds it from the reports.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Shard {
    /// Bots run.
    pub bots: usize,
    /// Bots that failed.
    pub failed: usize,
    /// Bots that ended with a complete area of interest.
    pub complete: usize,
    /// Bots whose final state matched the world.
    pub verified: usize,
    /// Bots checked against the world.
    pub checked: usize,
    /// Edited cells held by the bots checked, compared only as far as the world's function decides them.
    pub edited_checked: usize,
    /// The first failures' messages (at most ten), in the order of the bots' ids.
    pub errors: Vec<String>,
    /// Every area-of-interest change → complete latency, in any order.
    pub latencies: Vec<Duration>,
    /// Every bot's connect → first complete area of interest.
    pub first_complete: Vec<Duration>,
    /// Every bot's connect → last far-view node.
    pub far_settled: Vec<Duration>,
    /// Every fail-over's duration, error → resumed.
    pub failovers: Vec<Duration>,
    /// Records received.
    pub records: u64,
    /// Frame bytes of cell batches.
    pub batch_bytes: u64,
    /// UDP payload bytes.
    pub udp_bytes: u64,
    /// Species received over the wire.
    pub species_received: u64,
    /// Species received twice by one bot.
    pub species_duplicates: u64,
    /// Far-view summary nodes received.
    pub summary_nodes: u64,
    /// Frame bytes of summaries messages.
    pub summary_bytes: u64,
    /// Sessions resumed on another edge.
    pub reconnects: u64,
    /// The areas of interest sampled while walking.
    pub moving: AoiSamples,
}

impl Shard {
    /// What a shard's encoding starts with: a shard is told from anything else a process might have written.
    const MAGIC: &[u8; 8] = b"canopy\xb0\x01";

    /// The raw numbers of `reports`.
    pub fn new(reports: &[BotReport]) -> Shard {
        let errors = reports
            .iter()
            .filter_map(|r| {
                r.error.as_ref().map(|e| format!("bot {}: {e}", r.id)).or_else(|| match &r.verify {
                    Some(Err(e)) => Some(format!("bot {} check: {e}", r.id)),
                    _ => None,
                })
            })
            .take(ERRORS)
            .collect();
        let checked = || reports.iter().filter_map(|r| r.verify.as_ref());
        Shard {
            bots: reports.len(),
            failed: reports.iter().filter(|r| r.error.is_some()).count(),
            complete: reports.iter().filter(|r| r.complete).count(),
            verified: checked().filter(|v| v.is_ok()).count(),
            checked: checked().count(),
            edited_checked: checked().filter_map(|v| v.as_ref().ok()).map(|v| v.edited).sum(),
            errors,
            latencies: reports.iter().flat_map(|r| r.latencies.iter().copied()).collect(),
            first_complete: reports.iter().filter_map(|r| r.first_complete).collect(),
            far_settled: reports.iter().filter_map(|r| r.far_settled).collect(),
            failovers: reports.iter().flat_map(|r| r.failovers.iter().copied()).collect(),
            records: reports.iter().map(|r| r.records).sum(),
            batch_bytes: reports.iter().map(|r| r.frame_bytes[ServerMsgKind::Cells]).sum(),
            udp_bytes: reports.iter().map(|r| r.udp_bytes).sum(),
            species_received: reports.iter().map(|r| u64::from(r.species_received)).sum(),
            species_duplicates: reports.iter().map(|r| u64::from(r.species_duplicates)).sum(),
            summary_nodes: reports.iter().map(|r| r.summaries).sum(),
            summary_bytes: reports.iter().map(|r| r.frame_bytes[ServerMsgKind::Summaries]).sum(),
            reconnects: reports.iter().map(|r| u64::from(r.reconnects)).sum(),
            moving: reports.iter().fold(AoiSamples::default(), |mut a, r| {
                a.add(&r.moving);
                a
            }),
        }
    }

    /// Add the shard of other bots: afterwards this is the shard of both groups. Merged in the order of the
    /// groups' ids, the first failures are the ones one process would have kept.
    pub fn merge(&mut self, other: Shard) {
        self.bots += other.bots;
        self.failed += other.failed;
        self.complete += other.complete;
        self.verified += other.verified;
        self.checked += other.checked;
        self.edited_checked += other.edited_checked;
        let room = ERRORS.saturating_sub(self.errors.len());
        self.errors.extend(other.errors.into_iter().take(room));
        self.latencies.extend(other.latencies);
        self.first_complete.extend(other.first_complete);
        self.far_settled.extend(other.far_settled);
        self.failovers.extend(other.failovers);
        self.records += other.records;
        self.batch_bytes += other.batch_bytes;
        self.udp_bytes += other.udp_bytes;
        self.species_received += other.species_received;
        self.species_duplicates += other.species_duplicates;
        self.summary_nodes += other.summary_nodes;
        self.summary_bytes += other.summary_bytes;
        self.reconnects += other.reconnects;
        self.moving.add(&other.moving);
    }

    /// The shard as bytes: a magic number, then postcard.
    pub fn encode(&self) -> Vec<u8> {
        postcard::to_extend(self, Self::MAGIC.to_vec()).expect("a shard serialises into a vector")
    }

    /// A shard from [`Shard::encode`]'s bytes; an error says what is wrong with them (no magic number, not a
    /// shard, bytes left over).
    pub fn decode(bytes: &[u8]) -> Result<Shard, String> {
        let Some(body) = bytes.strip_prefix(Self::MAGIC.as_slice()) else {
            return Err(format!("not a shard of bots' results ({} bytes without its magic number)", bytes.len()));
        };
        match postcard::take_from_bytes::<Shard>(body) {
            Ok((shard, [])) => Ok(shard),
            Ok((_, rest)) => Err(format!("{} bytes after the shard", rest.len())),
            Err(e) => Err(format!("a shard that does not decode: {e}")),
        }
    }
}

impl BotsSummary {
    /// Summarise bot reports: their [`Shard`] ([`BotsSummary::from_shard`]), and what their edits came to.
    pub fn new(reports: &[BotReport], wall: Duration) -> BotsSummary {
        let mut summary = BotsSummary::from_shard(Shard::new(reports), wall);
        // Every bot holding an edited cell at one version must hold the same content.
        let mut digests: HashMap<(CellCoord, u32), (u64, usize, bool)> = HashMap::new();
        for (c, v, d) in reports.iter().flat_map(|r| &r.edited_cells) {
            let e = digests.entry((*c, *v)).or_insert((*d, 0, false));
            e.1 += 1;
            e.2 |= e.0 != *d;
        }
        let differ: Vec<_> = digests.iter().filter(|(_, e)| e.2).map(|(k, _)| *k).collect();
        if let Some((c, v)) = differ.first()
            && summary.errors.len() < ERRORS
        {
            summary.errors.push(format!("cell {c:?} at version {v} differs between bots"));
        }
        summary.edits = EditsSummary::new(reports.iter().filter_map(|r| r.edits.as_ref()));
        summary.edited_compared = digests.values().filter(|e| e.1 >= 2).count();
        summary.edited_differ = differ.len();
        summary
    }

    /// Summarise the raw numbers of a run that took `wall` (no edits: [`BotsSummary::new`] adds them).
    pub fn from_shard(mut shard: Shard, wall: Duration) -> BotsSummary {
        let per = |b: u64| if shard.records == 0 { 0.0 } else { b as f64 / shard.records as f64 };
        BotsSummary {
            bots: shard.bots,
            failed: shard.failed,
            complete: shard.complete,
            verified: shard.verified,
            checked: shard.checked,
            latency: percentiles(&mut shard.latencies),
            first_complete: percentiles(&mut shard.first_complete),
            far_settled: percentiles(&mut shard.far_settled),
            samples: shard.latencies.len(),
            records: shard.records,
            batch_bytes_per_record: per(shard.batch_bytes),
            udp_bytes_per_record: per(shard.udp_bytes),
            species_received: shard.species_received,
            summary_nodes: shard.summary_nodes,
            summary_bytes: shard.summary_bytes,
            batch_bytes: shard.batch_bytes,
            species_duplicates: shard.species_duplicates,
            moving: shard.moving,
            wall,
            edited_checked: shard.edited_checked,
            edits: None,
            fanout: None,
            edited_compared: 0,
            edited_differ: 0,
            reconnects: shard.reconnects,
            failover: percentiles(&mut shard.failovers),
            ledger: None,
            errors: shard.errors,
        }
    }

    /// The same with the acknowledged edits checked against the store ([`check_ledger`]).
    pub fn with_ledger(mut self, ledger: EditLedger) -> BotsSummary {
        if let Some(p) = &ledger.first_problem
            && self.errors.len() < 10
        {
            self.errors.push(p.clone());
        }
        self.ledger = Some(ledger);
        self
    }

    /// Every edit acknowledged to a bot of `reports`, for [`check_ledger`].
    pub fn acknowledged(reports: &[BotReport]) -> impl Iterator<Item = &Acknowledged> {
        reports.iter().filter_map(|r| r.edits.as_ref()).flat_map(|e| &e.acknowledged)
    }

    /// The scale-out run's one line: `edits acknowledged N, lost L, duplicated D, fan-out p50 X ms p99 Y ms,
    /// reconnects R` (`None` without a ledger).
    pub fn ledger_line(&self) -> Option<String> {
        let l = self.ledger.as_ref()?;
        let fanout = match self.fanout.as_ref().and_then(|f| f.visible()) {
            Some([p50, p99, _]) => {
                format!("p50 {:.1} ms p99 {:.1} ms", p50.as_secs_f64() * 1e3, p99.as_secs_f64() * 1e3)
            }
            None => "not measured".into(),
        };
        Some(format!(
            "edits acknowledged {}, lost {}, duplicated {}, fan-out {fanout}, reconnects {}",
            l.acknowledged, l.lost, l.duplicated, self.reconnects
        ))
    }

    /// The same with the run's fan-out samples ([`FanOut::report`]).
    pub fn with_fanout(mut self, fanout: FanOutReport) -> BotsSummary {
        self.fanout = Some(fanout);
        self
    }

    /// Whether every bot ended complete, every checked bot matched the world, bots holding an edited cell at one
    /// version held the same content, and (checked) no acknowledged edit was lost or duplicated.
    pub fn ok(&self) -> bool {
        self.failed == 0
            && self.complete == self.bots
            && self.verified == self.checked
            && self.edited_differ == 0
            && self.ledger.as_ref().is_none_or(|l| l.lost == 0 && l.duplicated == 0)
    }
}

impl std::fmt::Display for BotsSummary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let ms = |d: Duration| format!("{:.1} ms", d.as_secs_f64() * 1e3);
        writeln!(
            f,
            "bots: {} run, {} complete at the end, {} failed ({:.1} s)",
            self.bots,
            self.complete,
            self.failed,
            self.wall.as_secs_f64()
        )?;
        if self.checked > 0 {
            write!(f, "checked against the world: {} of {} exact", self.verified, self.checked)?;
            if self.edited_checked > 0 {
                write!(
                    f,
                    " ({} edited cells compared only where the world's function still decides them)",
                    self.edited_checked
                )?;
            }
            writeln!(f)?;
        }
        if let Some([p50, p90, p99, max]) = self.latency {
            writeln!(
                f,
                "AOI change → complete: p50 {} p90 {} p99 {} max {} ({} samples)",
                ms(p50),
                ms(p90),
                ms(p99),
                ms(max),
                self.samples
            )?;
        }
        if let Some([p50, _, p99, max]) = self.first_complete {
            writeln!(f, "connect → first complete AOI: p50 {} p99 {} max {}", ms(p50), ms(p99), ms(max))?;
        }
        writeln!(
            f,
            "records: {} received; {:.2} B/record in cell batches, {:.2} B/record on the wire (UDP, all included)",
            self.records, self.batch_bytes_per_record, self.udp_bytes_per_record
        )?;
        writeln!(f, "species: {} received, {} received twice", self.species_received, self.species_duplicates)?;
        if let Some([p50, _, p99, max]) = self.far_settled {
            writeln!(f, "connect → last far-view node: p50 {} p99 {} max {}", ms(p50), ms(p99), ms(max))?;
        }
        if self.summary_nodes > 0 {
            let per_bot = |b: u64| b as f64 / self.bots.max(1) as f64 / 1024.0;
            writeln!(
                f,
                "far view: {} summary nodes, {:.1} KiB of summaries beside {:.1} KiB of cell batches per bot ({:.1} B a node)",
                self.summary_nodes,
                per_bot(self.summary_bytes),
                per_bot(self.batch_bytes),
                self.summary_bytes as f64 / self.summary_nodes as f64
            )?;
        }
        let m = &self.moving;
        if m.samples > 0 {
            let pc = |n: u64| 100.0 * n as f64 / m.samples as f64;
            writeln!(
                f,
                "while moving ({} samples, from each bot's first complete AOI; {} before it): AOI cells held in full \
                 {:.1}% on average, whole AOI in {:.1}% of samples, the cell below in {:.1}%",
                m.samples,
                m.filling,
                100.0 * m.held_sum / m.samples as f64,
                pc(m.complete),
                pc(m.below)
            )?;
        }
        if let Some(e) = &self.edits {
            let [ok, denied, invalid, conflict] = e.outcomes;
            writeln!(
                f,
                "edits: {} bots editing; {} sent ({} plants, {} fells), {ok} acknowledged, {denied} denied, \
                 {invalid} invalid, {conflict} conflicts, {} unanswered; {:.1} acknowledged/s over {:.1} s",
                e.editors,
                e.sent(),
                e.plants,
                e.fells,
                e.unanswered,
                e.ok_per_second(),
                e.span.as_secs_f64()
            )?;
            if let Some([p50, p90, p99, max]) = e.answer {
                let n = e.outcomes.iter().sum::<u64>();
                writeln!(
                    f,
                    "edit send → answer: p50 {} p90 {} p99 {} max {} ({n} answers)",
                    ms(p50),
                    ms(p90),
                    ms(p99),
                    ms(max)
                )?;
            }
            for (what, why) in ["denied", "invalid"].iter().zip(&e.refusals) {
                if let Some(why) = why {
                    writeln!(f, "  first {what}: {why}")?;
                }
            }
        }
        if let Some(fo) = &self.fanout {
            match (fo.visible(), fo.visible_on_all(), fo.watchers()) {
                (Some([p50, p99, max]), Some([a50, a99, amax]), Some((mean, min))) => {
                    writeln!(
                        f,
                        "edit fan-out, send → visible on another bot holding the cell: p50 {} p99 {} max {} ({} \
                         samples)",
                        ms(p50),
                        ms(p99),
                        ms(max),
                        fo.samples.len()
                    )?;
                    writeln!(
                        f,
                        "edit fan-out, send → visible on every bot that received it (the last one): p50 {} p99 {} \
                         max {} ({} edits, {mean:.1} bots each on average, at least {min})",
                        ms(a50),
                        ms(a99),
                        ms(amax),
                        fo.per_edit.len()
                    )?;
                }
                _ => writeln!(f, "edit fan-out: no edit reached another bot")?,
            }
            if fo.unmatched > 0 {
                writeln!(
                    f,
                    "  {} (bot, version) sightings not counted: no bot of this run had its answer while the record \
                     kept the edit (another client's edits, or answers or deltas later than the record's newest \
                     {} edits)",
                    fo.unmatched,
                    FanOut::DEFAULT_CAPACITY
                )?;
            }
        }
        if self.edits.is_some() || self.edited_compared > 0 {
            writeln!(
                f,
                "edited cells at the end: {} (cell, version) held by two bots or more, {} differ between them",
                self.edited_compared, self.edited_differ
            )?;
        }
        if let Some([p50, _, p99, max]) = self.failover {
            writeln!(
                f,
                "reconnects: {} sessions resumed on another edge after theirs was lost; lost → resumed p50 {} p99 {} \
                 max {} (noticing the loss takes up to the idle timeout before that)",
                self.reconnects,
                ms(p50),
                ms(p99),
                ms(max)
            )?;
        }
        if let Some(l) = &self.ledger {
            writeln!(
                f,
                "edit store: {} edits in the {} cells the bots edited; of {} acknowledged, {} lost, {} duplicated",
                l.stored, l.cells, l.acknowledged, l.lost, l.duplicated
            )?;
        }
        for e in &self.errors {
            writeln!(f, "  {e}")?;
        }
        if let Some(line) = self.ledger_line() {
            writeln!(f, "{line}")?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::super::VerifySummary;
    use super::*;

    /// Bots with numbers of every kind a shard holds, the later ones slower, some failed or not matching the world.
    fn reports(count: usize) -> Vec<BotReport> {
        let ms = |n: u64| Duration::from_millis(n);
        (0..count)
            .map(|id| {
                let n = id as u64;
                let mut r = BotReport {
                    id,
                    first_complete: Some(ms(10 + 7 * n)),
                    far_settled: (id % 3 != 0).then(|| ms(500 + n * n)),
                    latencies: (0..1 + id % 5).map(|k| ms(1 + n * n + 13 * k as u64)).collect(),
                    complete: id % 4 != 1,
                    records: 1000 + 17 * n,
                    udp_bytes: 9000 + 5 * n,
                    species_received: 3 + (id % 2) as u32,
                    summaries: 2 * n,
                    species_duplicates: (id % 7 == 0) as u32,
                    moving: AoiSamples { samples: 4, held_sum: 3.5, complete: 3, below: 4, filling: 1 },
                    reconnects: (id % 3 == 2) as u32,
                    failovers: if id % 3 == 2 { vec![ms(40 + 3 * n)] } else { Vec::new() },
                    ..BotReport::default()
                };
                r.frame_bytes[ServerMsgKind::Cells] = 4000 + 11 * n;
                r.frame_bytes[ServerMsgKind::Summaries] = 300 * n;
                if id % 4 == 1 {
                    r.error = Some(format!("timed out ({id})"));
                } else if id % 5 == 3 {
                    r.verify = Some(Err(format!("cell {id} differs")));
                } else {
                    r.verify = Some(Ok(VerifySummary { cells: 9, instances: 90, species: 3, edited: id % 2 }));
                }
                r
            })
            .collect()
    }

    /// Merged shards of two groups of bots summarise to the numbers of one shard of them all: the percentiles are
    /// over every sample (the halves' own percentiles differ from the whole's), the first ten failures the same.
    #[test]
    fn merged_shards_give_the_numbers_of_one() {
        let all = reports(60);
        let wall = Duration::from_secs(3);
        let one = BotsSummary::new(&all, wall);
        let (a, b) = all.split_at(23);
        let mut merged = Shard::new(a);
        merged.merge(Shard::decode(&Shard::new(b).encode()).expect("a shard decodes"));
        assert_eq!(merged, Shard::new(&all), "a shard of the union");
        let two = BotsSummary::from_shard(merged, wall);
        assert_ne!(BotsSummary::new(a, wall).latency, one.latency, "the halves differ from the whole");
        assert_eq!(
            (two.latency, two.first_complete, two.far_settled),
            (one.latency, one.first_complete, one.far_settled)
        );
        assert_eq!((two.failover, two.samples, two.errors.len()), (one.failover, one.samples, 10));
        assert_eq!((two.bots, two.failed, two.complete, two.verified, two.checked), (60, 15, 45, 36, 45));
        assert_eq!(two.to_string(), one.to_string(), "the same summary, line for line");
        assert!(one.to_string().contains("checked against the world: 36 of 45 exact"), "{one}");
    }

    #[test]
    fn a_shard_decodes_only_from_its_own_bytes() {
        let bytes = Shard::new(&reports(5)).encode();
        assert_eq!(Shard::decode(&bytes), Ok(Shard::new(&reports(5))));
        assert!(Shard::decode(b"").unwrap_err().contains("magic number"));
        assert!(Shard::decode(&bytes[..bytes.len() - 3]).unwrap_err().contains("does not decode"));
        assert!(Shard::decode(&[&bytes[..], b"x"].concat()).unwrap_err().contains("1 bytes after the shard"));
    }
}
