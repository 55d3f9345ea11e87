//! A species instance's numbers — primitives by kind, encoded bytes, explicit bytes as seed 001 §7 counts them,
//! traversal time, the mesh, LOD levels — measured once here for both `canopy species stats` and the editor's
//! stats panel. [`StatsWorker`] measures off the UI thread: the editor sends it the instance of each model
//! revision and shows what comes back for the revision still current (a stale result is dropped).

use std::sync::mpsc::{Receiver, RecvTimeoutError, Sender, channel};
use std::time::{Duration, Instant};

use canopy_protocol::ParamRole;
use canopy_worlds::amplify::{Budget, Instance};
use canopy_worlds::mesh::{MeshOptions, explicit_bytes, mesh};
use canopy_worlds::primitive::{PrimitiveKind, PrimitiveStream};

use crate::species::{AmplifyFailure, Species};

/// Detail levels looked at for LOD substitutes (levels stop at the first that draws the same as the one before).
pub const MAX_LOD_LEVELS: u8 = 8;

/// One detail level that differs from the one before it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct LodLevel {
    /// The detail level (0 is full detail).
    pub detail: u8,
    /// Primitives the instance emits at this level.
    pub primitives: usize,
}

/// What `canopy species stats` prints and the editor shows.
#[derive(Clone, Debug, PartialEq)]
pub struct SpeciesStats {
    /// The species' name.
    pub name: String,
    /// Nodes in its graph.
    pub nodes: usize,
    /// Parameters it declares (what an instance may set).
    pub params: usize,
    /// Working values its program declares (`let`, an L-system's module arguments and internal values).
    pub working: usize,
    /// The instance's seed.
    pub seed: u64,
    /// The instance's detail level.
    pub detail: u8,
    /// Primitives by [`PrimitiveKind`].
    pub counts: [usize; 5],
    /// Primitives in all.
    pub primitives: usize,
    /// Bytes of the species graph as sent (postcard).
    pub encoded: usize,
    /// Bytes of the instance as explicit geometry, counted as seed 001 §7 counts it.
    pub explicit: usize,
    /// The median traversal time, milliseconds.
    pub traversal_ms: f64,
    /// Traversals timed.
    pub repeat: u32,
    /// Mesh triangles.
    pub triangles: usize,
    /// Mesh vertices.
    pub vertices: usize,
    /// Time to mesh the stream, milliseconds.
    pub mesh_ms: f64,
    /// The hash of the primitive stream (the golden-hash function).
    pub stream_hash: u64,
    /// The detail levels that differ, from 0 up (one entry: the species has no LOD substitutes).
    pub lod: Vec<LodLevel>,
}

/// Amplify `instance` of `species` `repeat` times (at least once), time the traversals, mesh the stream and find its
/// LOD levels. Returns the numbers and the stream.
pub fn measure(
    species: &Species,
    instance: &Instance,
    budget: &Budget,
    repeat: u32,
) -> Result<(SpeciesStats, PrimitiveStream), AmplifyFailure> {
    let repeat = repeat.max(1);
    let mut times = Vec::with_capacity(repeat as usize);
    let mut stream = PrimitiveStream::default();
    for _ in 0..repeat {
        let t = Instant::now();
        stream = species.amplify(instance, budget)?;
        times.push(t.elapsed().as_secs_f64() * 1e3);
    }
    times.sort_by(f64::total_cmp);
    let traversal_ms = times[times.len() / 2];
    let t = Instant::now();
    let m = mesh(&stream, &MeshOptions::for_detail(instance.detail));
    let mesh_ms = t.elapsed().as_secs_f64() * 1e3;
    let g = &species.graph;
    let stats = SpeciesStats {
        name: g.name.clone(),
        nodes: g.nodes.len(),
        params: g.of_role(ParamRole::Parameter).count(),
        working: g.of_role(ParamRole::Working).count(),
        seed: instance.seed,
        detail: instance.detail,
        counts: stream.counts(),
        primitives: stream.primitives.len(),
        encoded: g.encode().len(),
        explicit: explicit_bytes(&stream),
        traversal_ms,
        repeat,
        triangles: m.triangle_count(),
        vertices: m.positions.len(),
        mesh_ms,
        stream_hash: stream.hash(),
        lod: lod_levels(species, instance, budget, &stream)?,
    };
    Ok((stats, stream))
}

/// The detail levels from `instance.detail` up whose streams differ from the level before, up to
/// [`MAX_LOD_LEVELS`]; `stream` is the instance's own.
pub fn lod_levels(
    species: &Species,
    instance: &Instance,
    budget: &Budget,
    stream: &PrimitiveStream,
) -> Result<Vec<LodLevel>, AmplifyFailure> {
    let mut levels = vec![LodLevel { detail: instance.detail, primitives: stream.primitives.len() }];
    let mut last = stream.hash();
    for detail in instance.detail.saturating_add(1)..MAX_LOD_LEVELS {
        let s = species.amplify(&Instance { detail, ..instance.clone() }, budget)?;
        let h = s.hash();
        if h == last {
            break;
        }
        last = h;
        levels.push(LodLevel { detail, primitives: s.primitives.len() });
    }
    Ok(levels)
}

/// One measurement asked of the [`StatsWorker`]: the model revision it belongs to and what to measure.
#[derive(Clone, Debug)]
pub struct StatsJob {
    /// The editor model's revision (results carry it back).
    pub revision: u64,
    /// The species.
    pub species: Species,
    /// The previewed instance.
    pub instance: Instance,
    /// The budget of every traversal.
    pub budget: Budget,
    /// Traversals timed.
    pub repeat: u32,
}

/// What the worker measured for one revision.
#[derive(Clone, Debug, PartialEq)]
pub struct StatsResult {
    /// The revision of the job.
    pub revision: u64,
    /// The numbers, or why the instance could not be amplified.
    pub stats: Result<SpeciesStats, String>,
    /// The whole measurement (traversals, mesh, LOD levels), milliseconds, on the worker.
    pub millis: f64,
}

/// A thread that runs [`measure`] for the editor, so the UI thread never does (three traversals, meshing up to a
/// million triangles and the LOD levels take tens of milliseconds on a large tree). Jobs queued while it works
/// are skipped to the newest; the thread ends when the worker is dropped.
#[derive(Debug)]
pub struct StatsWorker {
    jobs: Sender<StatsJob>,
    results: Receiver<StatsResult>,
}

impl StatsWorker {
    /// Start the thread.
    pub fn new() -> std::io::Result<StatsWorker> {
        let (jobs, job_rx) = channel::<StatsJob>();
        let (result_tx, results) = channel();
        std::thread::Builder::new().name("editor-stats".into()).spawn(move || {
            while let Ok(mut job) = job_rx.recv() {
                // Only the newest job matters: the ones before it are stale already.
                while let Ok(newer) = job_rx.try_recv() {
                    job = newer;
                }
                let t = Instant::now();
                let stats = measure(&job.species, &job.instance, &job.budget, job.repeat)
                    .map(|(s, _)| s)
                    .map_err(|e| e.to_string());
                let r = StatsResult { revision: job.revision, stats, millis: t.elapsed().as_secs_f64() * 1e3 };
                if result_tx.send(r).is_err() {
                    break;
                }
            }
        })?;
        Ok(StatsWorker { jobs, results })
    }

    /// Queue a measurement; false when the thread has stopped.
    pub fn request(&self, job: StatsJob) -> bool {
        self.jobs.send(job).is_ok()
    }

    /// The newest result that has arrived, if any (older ones are dropped).
    pub fn try_result(&self) -> Option<StatsResult> {
        self.results.try_iter().last()
    }

    /// Wait up to `timeout` for a result of `revision` (older ones are dropped on the way).
    pub fn wait_for(&self, revision: u64, timeout: Duration) -> Option<StatsResult> {
        let deadline = Instant::now() + timeout;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.results.recv_timeout(left) {
                Ok(r) if r.revision == revision => return Some(r),
                Ok(_) => {}
                Err(RecvTimeoutError::Timeout | RecvTimeoutError::Disconnected) => return None,
            }
        }
    }
}

impl SpeciesStats {
    /// Primitives by kind: `cone 1  cylinder 0  sphere 6  box 0  leaf 0`.
    pub fn counts_line(&self) -> String {
        counts_line(&self.counts)
    }

    /// The report, one line each: species, instance, primitives, encoded, explicit, traversal, mesh, lod.
    pub fn lines(&self) -> Vec<String> {
        self.lines_timed(true)
    }

    /// [`Stats::lines`], with the times measured or (`times` false: a picture that must not change run to run)
    /// a dash in their place.
    pub fn lines_timed(&self, times: bool) -> Vec<String> {
        let ms = |v: f64| if times { format!("{v:.3}") } else { "–".into() };
        let n = self.primitives;
        let lod = self
            .lod
            .iter()
            .map(|l| format!("detail {} {}", l.detail, thousands(l.primitives as u64)))
            .collect::<Vec<_>>()
            .join(", ");
        vec![
            format!(
                "species     {} ({} nodes, {} parameter(s), {} working value(s))",
                self.name, self.nodes, self.params, self.working
            ),
            format!("instance    seed {}, detail {}", self.seed, self.detail),
            format!("primitives  {}  ({})", thousands(n as u64), self.counts_line()),
            format!("encoded     {} bytes (postcard species graph)", thousands(self.encoded as u64)),
            format!(
                "explicit    {} bytes as seed 001 §7 counts it (cones/cylinders 7 floats, triangle vertices 3 floats): {}× the species",
                thousands(self.explicit as u64),
                ratio(self.explicit as f64 / self.encoded as f64)
            ),
            format!(
                "traversal   {} ms median of {} ({} M primitives/s)",
                ms(self.traversal_ms),
                self.repeat,
                if times { format!("{:.2}", n as f64 / self.traversal_ms / 1e3) } else { "–".into() }
            ),
            format!(
                "mesh        {} triangles, {} vertices in {} ms",
                thousands(self.triangles as u64),
                thousands(self.vertices as u64),
                ms(self.mesh_ms)
            ),
            format!("lod         {} level(s): {lod}", self.lod.len()),
        ]
    }
}

/// Primitives by kind from [`PrimitiveStream::counts`].
pub fn counts_line(counts: &[usize; 5]) -> String {
    PrimitiveKind::ALL
        .iter()
        .map(|k| format!("{} {}", k.name(), thousands(counts[*k as usize] as u64)))
        .collect::<Vec<_>>()
        .join("  ")
}

/// A count with thousands separators (`12,345`).
pub fn thousands(v: u64) -> String {
    let s = v.to_string();
    let mut out = String::with_capacity(s.len() + s.len() / 3);
    for (i, c) in s.chars().enumerate() {
        if i > 0 && (s.len() - i).is_multiple_of(3) {
            out.push(',');
        }
        out.push(c);
    }
    out
}

/// A size ratio for people: whole numbers from 10 up, two significant digits below (`0.14`, `3.5`), so a species
/// whose explicit geometry is smaller than its encoding does not read as `0`.
pub fn ratio(r: f64) -> String {
    if !r.is_finite() || r >= 9.95 {
        format!("{r:.0}")
    } else if r >= 0.995 {
        format!("{r:.1}")
    } else if r > 0.0 {
        let decimals = (1.0 - r.log10().floor()).clamp(2.0, 12.0) as usize;
        format!("{r:.decimals$}")
    } else {
        "0".to_string()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use canopy_worlds::library;

    #[test]
    fn worm_numbers_match_the_cli_contract() {
        let e = library::find("worm").expect("worm");
        let (s, _) = Species::parse(&e.source());
        let s = s.expect("parses");
        let slot = s.graph.param_slot("c").expect("c");
        let inst = Instance { seed: 1, params: vec![(slot, 6.0)], detail: 0 };
        let (st, stream) = measure(&s, &inst, &Budget::default(), 1).expect("amplifies");
        assert_eq!(st.primitives, stream.primitives.len());
        let lines = st.lines();
        assert_eq!(lines[2], "primitives  7  (cone 1  cylinder 0  sphere 6  box 0  leaf 0)");
        assert_eq!(lines[0], "species     Worm (11 nodes, 1 parameter(s), 0 working value(s))");
        assert!(lines[3].starts_with("encoded     166 bytes"), "{lines:?}");
        assert!(lines[7].starts_with("lod         1 level(s): detail 0 7"), "{lines:?}");
        assert_eq!((thousands(1234567), ratio(0.1388), ratio(3.46)), ("1,234,567".into(), "0.14".into(), "3.5".into()));
    }

    #[test]
    fn the_conifer_has_lod_levels() {
        let e = library::find("conifer").expect("conifer");
        let s = Species::parse(&e.source()).0.expect("parses");
        let inst = Instance::new(1);
        let stream = s.amplify(&inst, &Budget::default()).expect("amplifies");
        let lod = lod_levels(&s, &inst, &Budget::default(), &stream).expect("amplifies");
        assert!(lod.len() > 1, "{lod:?}");
        assert!(lod.windows(2).all(|w| w[1].primitives < w[0].primitives), "{lod:?}");
    }

    #[test]
    fn the_worker_measures_off_thread_and_tags_results_by_revision() {
        let e = library::find("worm").expect("worm");
        let s = Species::parse(&e.source()).0.expect("parses");
        let w = StatsWorker::new().expect("a thread");
        let job = |revision, seed| StatsJob {
            revision,
            species: s.clone(),
            instance: Instance::new(seed),
            budget: Budget::default(),
            repeat: 1,
        };
        assert!(w.request(job(1, 1)) && w.request(job(2, 2)));
        let r = w.wait_for(2, Duration::from_secs(30)).expect("revision 2 measured");
        let direct = measure(&s, &Instance::new(2), &Budget::default(), 1).expect("amplifies").0;
        let got = r.stats.expect("amplifies");
        assert_eq!((got.seed, got.stream_hash, got.primitives), (2, direct.stream_hash, direct.primitives));
        assert!(w.try_result().is_none(), "nothing newer is left");
        // A revision never asked for is not made up.
        assert!(w.wait_for(3, Duration::from_millis(50)).is_none());
    }
}
