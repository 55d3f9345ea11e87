//! A deterministic parallel map, for loading worlds and for the renderer's per-frame planning: independent pure jobs
//! run on the available cores and their results come back in job order, so the outcome never depends on the thread
//! count or the scheduling. Where no thread can be started (wasm32), the jobs run one after another on the calling
//! thread.

use std::sync::atomic::{AtomicUsize, Ordering};

/// Most threads one map uses.
const MAX_THREADS: usize = 16;

/// `jobs.iter().map(f)`, run on up to [`MAX_THREADS`] threads (the calling one included), results in job order.
/// `f` gets a per-thread scratch value made by `scratch`, so allocations can be reused across jobs.
pub fn map<T: Sync, S, R: Send>(
    jobs: &[T],
    scratch: impl Fn() -> S + Sync,
    f: impl Fn(&mut S, &T) -> R + Sync,
) -> Vec<R> {
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get()).min(jobs.len()).min(MAX_THREADS);
    let next = AtomicUsize::new(0);
    let work = || {
        let mut s = scratch();
        let mut done = Vec::new();
        loop {
            let k = next.fetch_add(1, Ordering::Relaxed);
            let Some(job) = jobs.get(k) else { return done };
            done.push((k, f(&mut s, job)));
        }
    };
    let mut results: Vec<(usize, R)> = std::thread::scope(|scope| {
        let helpers: Vec<_> =
            (1..threads).filter_map(|_| std::thread::Builder::new().spawn_scoped(scope, work).ok()).collect();
        let mut all = work();
        for h in helpers {
            all.extend(h.join().unwrap_or_else(|e| std::panic::resume_unwind(e)));
        }
        all
    });
    results.sort_by_key(|(k, _)| *k);
    results.into_iter().map(|(_, r)| r).collect()
}

#[cfg(test)]
mod tests {
    #[test]
    fn results_come_back_in_job_order() {
        let jobs: Vec<u64> = (0..1000).collect();
        let out = super::map(
            &jobs,
            || 0u64,
            |calls, &j| {
                *calls += 1;
                j * j
            },
        );
        assert_eq!(out, jobs.iter().map(|j| j * j).collect::<Vec<_>>());
        assert!(super::map(&[] as &[u8], || (), |_, &j| j).is_empty());
    }
}
