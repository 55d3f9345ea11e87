//! Worker threads for the renderer's CPU work — amplifying instances into geometry, voxelising species into
//! far-field volumes and baking their canopy tiles — so the render loop never waits: it submits jobs with a priority and collects whatever has
//! finished with [`Workers::try_recv`]. Where there are no threads (a browser page: wasm32) the same queue is
//! run on the calling thread instead, a few jobs a frame ([`Workers::inline`], [`Workers::run_inline`]).

use std::collections::BinaryHeap;
use std::sync::mpsc;
use std::sync::{Arc, Condvar, Mutex};
use std::thread::JoinHandle;
use std::time::Duration;

use canopy_protocol::SpeciesGraph;
use canopy_protocol::sync::Locked;
#[cfg(not(target_arch = "wasm32"))]
use canopy_protocol::sync::Waited;
use canopy_worlds::amplify::{Budget, Instance};

use super::clock::Instant;
use super::geometry::{TreeGeometry, build_tree};
use super::scene::SceneVolume;
use super::tile::{CanopyTile, bake_tile};
use super::volume::{FarVolume, SpeciesVolumes, species_volumes, volumes_of};
use super::{Lighting, NearMode};

/// The geometry cache key: one instance at one detail level (instances are identified by species and seed).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub(crate) struct TreeKey {
    /// Species id.
    pub species: u16,
    /// Instance seed.
    pub seed: u64,
    /// Detail level.
    pub detail: u8,
    /// A hash of the instance's parameter values ([`TreeKey::params_hash`]): an instance whose parameters an
    /// edit changed is amplified again, not drawn from the old geometry.
    pub params: u64,
}

impl TreeKey {
    /// FNV-1a over `(slot, value bits)` pairs; 0 for none.
    pub(crate) fn params_hash(params: &[(u16, f32)]) -> u64 {
        if params.is_empty() {
            return 0;
        }
        let mut h = 0xcbf2_9ce4_8422_2325u64;
        for (slot, v) in params {
            for b in slot.to_le_bytes().into_iter().chain(v.to_bits().to_le_bytes()) {
                h = (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3);
            }
        }
        h
    }
}

/// Work for a worker.
#[derive(Clone, Debug)]
pub(crate) enum Job {
    /// Amplify one instance at one detail level.
    Tree {
        /// Cache key.
        key: TreeKey,
        /// The species.
        graph: Arc<SpeciesGraph>,
        /// Seed, parameters, detail.
        instance: Instance,
        /// Instancing or merged meshes.
        mode: NearMode,
        /// Work bound.
        budget: Budget,
    },
    /// Make a species' far-field volumes.
    Volume {
        /// Species id.
        species: u16,
        /// The species (voxelised when `given` is `None`; its `height` parameter scales instances).
        graph: Arc<SpeciesGraph>,
        /// A volume the scene provides.
        given: Option<SceneVolume>,
        /// Voxels along the longest axis when voxelising.
        resolution: u32,
        /// Amplification bound for the representative instance.
        budget: Budget,
        /// Shading to bake.
        lighting: Lighting,
    },
    /// Bake a species' canopy tile from its far volume (summary patches, [`super::tile`]).
    Tile {
        /// Species id.
        species: u16,
        /// The species' full-resolution far volume.
        volume: Arc<FarVolume>,
        /// Voxels along the tile's edge.
        resolution: u32,
    },
}

/// What a job produced.
#[derive(Debug)]
pub(crate) enum JobResult {
    /// A tree's geometry, or why there is none.
    Tree {
        /// Cache key.
        key: TreeKey,
        /// The geometry.
        result: Result<TreeGeometry, String>,
    },
    /// A species' volumes, or why there are none.
    Volume {
        /// Species id.
        species: u16,
        /// The volumes.
        result: Result<SpeciesVolumes, String>,
        /// Time the job took.
        took: Duration,
    },
    /// A species' canopy tile, or why there is none.
    Tile {
        /// Species id.
        species: u16,
        /// The tile.
        result: Result<Box<CanopyTile>, String>,
        /// Time the job took.
        took: Duration,
    },
}

struct Queued {
    priority: f32,
    order: u64,
    job: Job,
}

impl PartialEq for Queued {
    fn eq(&self, o: &Self) -> bool {
        self.cmp(o) == std::cmp::Ordering::Equal
    }
}
impl Eq for Queued {}
impl PartialOrd for Queued {
    fn partial_cmp(&self, o: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(o))
    }
}
impl Ord for Queued {
    /// Highest priority first; among equals, first submitted first.
    fn cmp(&self, o: &Self) -> std::cmp::Ordering {
        self.priority.total_cmp(&o.priority).then(o.order.cmp(&self.order))
    }
}

#[derive(Default)]
struct Shared {
    heap: BinaryHeap<Queued>,
    stop: bool,
    next: u64,
}

/// A pool of worker threads (see the module docs), or none ([`Workers::inline`]). Dropping it stops and joins them.
pub(crate) struct Workers {
    shared: Arc<(Mutex<Shared>, Condvar)>,
    results: mpsc::Receiver<JobResult>,
    threads: Vec<JoinHandle<()>>,
    outstanding: usize,
    /// Where results go when jobs run on the calling thread ([`Workers::inline`]); `None` for threads.
    inline: Option<mpsc::Sender<JobResult>>,
}

impl std::fmt::Debug for Workers {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Workers").field("threads", &self.threads.len()).field("outstanding", &self.outstanding).finish()
    }
}

fn run(job: Job) -> JobResult {
    let started = Instant::now();
    match job {
        Job::Tree { key, graph, instance, mode, budget } => {
            let result = std::panic::catch_unwind(|| build_tree(&graph, &instance, mode, &budget))
                .map_err(|_| "amplification panicked".to_string())
                .and_then(|r| r.map_err(|e| e.to_string()));
            JobResult::Tree { key, result }
        }
        Job::Volume { species, graph, given, resolution, budget, lighting } => {
            let result = std::panic::catch_unwind(|| match &given {
                Some(v) => volumes_of(&v.tree, v.origin, v.units, resolution, &lighting).map(|mut s| {
                    s.height = super::volume::height_param(&graph);
                    s
                }),
                None => species_volumes(&graph, resolution, &budget, &lighting),
            })
            .map_err(|_| "voxelisation panicked".to_string())
            .and_then(|r| r.map_err(|e| e.to_string()));
            JobResult::Volume { species, result, took: started.elapsed() }
        }
        Job::Tile { species, volume, resolution } => {
            let result = std::panic::catch_unwind(|| bake_tile(&volume, resolution))
                .map_err(|_| "baking the canopy tile panicked".to_string())
                .and_then(|r| r.map(Box::new).map_err(|e| e.to_string()));
            JobResult::Tile { species, result, took: started.elapsed() }
        }
    }
}

impl Workers {
    /// Start `n` workers (at least one).
    #[cfg(not(target_arch = "wasm32"))]
    pub(crate) fn new(n: usize) -> std::io::Result<Workers> {
        let shared: Arc<(Mutex<Shared>, Condvar)> = Arc::default();
        let (tx, results) = mpsc::channel();
        let mut threads = Vec::new();
        for i in 0..n.max(1) {
            let shared = Arc::clone(&shared);
            let tx = tx.clone();
            threads.push(std::thread::Builder::new().name(format!("canopy-amplify-{i}")).spawn(move || {
                loop {
                    let job = {
                        let (lock, cv) = &*shared;
                        let mut s = lock.locked();
                        loop {
                            if s.stop {
                                return;
                            }
                            if let Some(q) = s.heap.pop() {
                                break q.job;
                            }
                            s = cv.waited(s);
                        }
                    };
                    if tx.send(run(job)).is_err() {
                        return;
                    }
                }
            })?);
        }
        Ok(Workers { shared, results, threads, outstanding: 0, inline: None })
    }

    /// Workers without threads (a browser page: wasm32 has none): jobs wait in the queue until
    /// [`Workers::run_inline`] runs them on the calling thread.
    #[cfg(any(test, target_arch = "wasm32"))]
    pub(crate) fn inline() -> Workers {
        let (tx, results) = mpsc::channel();
        Workers { shared: Arc::default(), results, threads: Vec::new(), outstanding: 0, inline: Some(tx) }
    }

    /// Whether jobs run on the calling thread ([`Workers::inline`]).
    pub(crate) fn is_inline(&self) -> bool {
        self.inline.is_some()
    }

    /// For inline workers: run queued jobs on this thread, highest priority first, while `more()` says so (asked
    /// before each job, so a job started runs to its end); how many ran. Worker threads run nothing here.
    pub(crate) fn run_inline(&mut self, more: &mut dyn FnMut() -> bool) -> usize {
        let Some(tx) = &self.inline else { return 0 };
        let mut ran = 0;
        while more() {
            let next = self.shared.0.locked().heap.pop();
            let Some(q) = next else { break };
            // The receiver lives as long as `self`.
            let _ = tx.send(run(q.job));
            ran += 1;
        }
        ran
    }

    /// Queue a job; higher priorities run first.
    pub(crate) fn submit(&mut self, job: Job, priority: f32) {
        let (lock, cv) = &*self.shared;
        let mut s = lock.locked();
        let order = s.next;
        s.next += 1;
        s.heap.push(Queued { priority, order, job });
        self.outstanding += 1;
        cv.notify_one();
    }

    /// A finished job, if any (never blocks).
    pub(crate) fn try_recv(&mut self) -> Option<JobResult> {
        let r = self.results.try_recv().ok()?;
        self.outstanding -= 1;
        Some(r)
    }

    /// Wait up to `timeout` for a finished job (inline workers run the next job, if any, and never wait).
    pub(crate) fn recv_timeout(&mut self, timeout: Duration) -> Option<JobResult> {
        if self.is_inline() {
            let mut first = true;
            self.run_inline(&mut || std::mem::take(&mut first));
            return self.try_recv();
        }
        let r = self.results.recv_timeout(timeout).ok()?;
        self.outstanding -= 1;
        Some(r)
    }

    /// Jobs queued or running.
    pub(crate) fn outstanding(&self) -> usize {
        self.outstanding
    }
}

impl Drop for Workers {
    fn drop(&mut self) {
        {
            let (lock, cv) = &*self.shared;
            let mut s = lock.locked();
            s.stop = true;
            s.heap.clear();
            cv.notify_all();
        }
        for t in self.threads.drain(..) {
            let _ = t.join();
        }
    }
}

#[cfg(test)]
mod tests {
    use canopy_worlds::library;

    use super::*;

    #[test]
    fn workers_amplify_by_priority_and_report_errors() {
        let g = Arc::new(library::find("conifer").unwrap().load().unwrap());
        let mut w = Workers::new(2).unwrap();
        let key = |seed| TreeKey { species: 0, seed, detail: 2, params: 0 };
        let job = |seed, budget| Job::Tree {
            key: key(seed),
            graph: Arc::clone(&g),
            instance: Instance::new(seed).with_detail(2),
            mode: NearMode::Instanced,
            budget,
        };
        w.submit(job(1, Budget::default()), 1.0);
        w.submit(job(2, Budget { max_primitives: 1, ..Budget::default() }), 2.0);
        let mut got = Vec::new();
        while got.len() < 2 {
            got.push(w.recv_timeout(Duration::from_secs(60)).expect("a result within a minute"));
        }
        assert_eq!(w.outstanding(), 0);
        for r in got {
            match r {
                JobResult::Tree { key: k, result, .. } if k == key(1) => assert!(result.unwrap().prims.len() > 10),
                JobResult::Tree { key: k, result, .. } if k == key(2) => {
                    assert!(result.unwrap_err().contains("primitives"))
                }
                other => panic!("unexpected {other:?}"),
            }
        }
    }

    #[test]
    fn inline_workers_run_jobs_by_priority_on_the_calling_thread_within_the_budget_asked() {
        let g = Arc::new(library::find("conifer").unwrap().load().unwrap());
        let mut w = Workers::inline();
        assert!(w.is_inline() && w.threads.is_empty());
        for (seed, priority) in [(1, 1.0), (2, 3.0), (3, 2.0)] {
            let key = TreeKey { species: 0, seed, detail: 1, params: 0 };
            let instance = Instance::new(seed).with_detail(1);
            let job = Job::Tree {
                key,
                graph: Arc::clone(&g),
                instance,
                mode: NearMode::Instanced,
                budget: Budget::default(),
            };
            w.submit(job, priority);
        }
        assert!(w.try_recv().is_none(), "nothing runs until asked");
        let mut left = 2u32;
        let mut two = || {
            let more = left > 0;
            left = left.saturating_sub(1);
            more
        };
        assert_eq!(w.run_inline(&mut two), 2);
        let seeds: Vec<u64> = std::iter::from_fn(|| w.try_recv())
            .map(|r| match r {
                JobResult::Tree { key, result, .. } => {
                    assert!(result.is_ok());
                    key.seed
                }
                other => panic!("unexpected {other:?}"),
            })
            .collect();
        assert_eq!((seeds, w.outstanding()), (vec![2, 3], 1));
        assert!(matches!(w.recv_timeout(Duration::ZERO), Some(JobResult::Tree { key, .. }) if key.seed == 1));
        assert_eq!((w.outstanding(), w.run_inline(&mut || true)), (0, 0));
    }

    #[test]
    fn the_queue_orders_by_priority_then_submission() {
        let job = Job::Volume {
            species: 0,
            graph: Arc::new(library::find("worm").unwrap().load().unwrap()),
            given: None,
            resolution: 8,
            budget: Budget::default(),
            lighting: Lighting::default(),
        };
        let mut heap = BinaryHeap::new();
        for (i, p) in [1.0f32, 5.0, 5.0, -1.0].iter().enumerate() {
            heap.push(Queued { priority: *p, order: i as u64, job: job.clone() });
        }
        let order: Vec<u64> = std::iter::from_fn(|| heap.pop().map(|q| q.order)).collect();
        assert_eq!(order, vec![1, 2, 0, 3]);
    }
}
