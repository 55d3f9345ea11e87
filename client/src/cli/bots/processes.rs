//! `canopy bots --processes N`: the bots split over N processes of this command, in contiguous ranges of ids, each
//! writing its bots' raw results (a [`Shard`]) to its standard output; the parent merges the shards into one
//! summary, so that the client side scales with the server and is never what is measured.

use std::ffi::OsString;
use std::io::Read;
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::Instant;

use anyhow::{Context, bail};
use canopy_harness::bots::{BotsSummary, Shard};

/// The most a process's shard may take: every sample of a few thousand bots takes a few megabytes.
const MAX_SHARD: u64 = 256 << 20;

/// One process's bots: ids `first..first + count`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Share {
    first: usize,
    count: usize,
}

impl std::fmt::Display for Share {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "bots {}..{}", self.first, self.first + self.count)
    }
}

/// `count` bots over `processes` processes (at most one a bot), as evenly as possible, in contiguous ranges of ids
/// from 0: together exactly the bots one process would run.
fn shares(count: usize, processes: usize) -> Vec<Share> {
    let n = processes.clamp(1, count.max(1));
    let mut first = 0;
    (0..n)
        .map(|i| {
            let share = Share { first, count: count / n + usize::from(i < count % n) };
            first += share.count;
            share
        })
        .collect()
}

/// Run `count` bots in `processes` processes of this command, each started with this command's own options
/// ([`std::env::args_os`]) followed by its share: `--count`, `--first-id`, `connect_rate` divided between them,
/// `--processes 1 --quiet --shard-out`. Returns the summary over every process's shard, the wall time the
/// parent's; fails, naming the process, when one could not start, exited with a failure or wrote no shard.
pub(super) fn run(count: usize, processes: usize, connect_rate: f64) -> anyhow::Result<BotsSummary> {
    let exe = std::env::current_exe().context("--processes: finding this program to start it again")?;
    let options: Vec<OsString> = std::env::args_os().skip(1).collect();
    let shares = shares(count, processes);
    let n = shares.len();
    let rate = connect_rate / n as f64;
    eprintln!("bots: {count} in {n} processes, each ramping up at {rate} connections a second");
    let started = Instant::now();
    let mut children: Vec<Child> = Vec::with_capacity(n);
    for (i, share) in shares.iter().enumerate() {
        let spawned = Command::new(&exe)
            .args(&options)
            .args(["--count", &share.count.to_string(), "--first-id", &share.first.to_string()])
            .args(["--connect-rate", &rate.to_string(), "--processes", "1", "--quiet", "--shard-out"])
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn();
        match spawned {
            Ok(child) => children.push(child),
            Err(e) => {
                // The processes started so far would run without anyone to read their shards.
                for mut c in children {
                    let _ = c.kill();
                    let _ = c.wait();
                }
                bail!("starting bot process {} of {n} ({share}) as {}: {e}", i + 1, exe.display());
            }
        }
    }
    // A thread a process reads its shard as it comes (a pipe holds only so much) and waits for it; a line as each
    // one ends.
    let (tx, rx) = mpsc::channel();
    let results = std::thread::scope(|scope| {
        for (i, child) in children.iter_mut().enumerate() {
            let tx = tx.clone();
            // The receiver below lives until every sender is gone.
            scope.spawn(move || drop(tx.send((i, collect(child)))));
        }
        drop(tx);
        let mut results: Vec<Option<Result<Shard, String>>> = (0..n).map(|_| None).collect();
        for (i, result) in rx {
            let (at, share) = (started.elapsed().as_secs_f64(), shares[i]);
            match &result {
                Ok(s) => eprintln!(
                    "bots: process {} of {n} ({share}) ended after {at:.1} s: {} run, {} failed",
                    i + 1,
                    s.bots,
                    s.failed
                ),
                Err(e) => eprintln!("bots: process {} of {n} ({share}) failed after {at:.1} s: {e}", i + 1),
            }
            results[i] = Some(result);
        }
        results
    });
    let wall = started.elapsed();
    // Merged in the order of the ids: the first failures are those one process would have listed.
    let mut merged = Shard::default();
    let mut failed = Vec::new();
    for (i, result) in results.into_iter().enumerate() {
        match result.unwrap_or_else(|| Err("no answer from its reader thread".into())) {
            Ok(shard) => merged.merge(shard),
            Err(e) => failed.push(format!("bot process {} of {n} ({}): {e}", i + 1, shares[i])),
        }
    }
    if !failed.is_empty() {
        bail!("{} of {n} bot processes failed:\n  {}", failed.len(), failed.join("\n  "));
    }
    Ok(BotsSummary::from_shard(merged, wall))
}

/// Read a process's shard (at most [`MAX_SHARD`] bytes: past that the process is stopped) and wait for it to exit.
fn collect(child: &mut Child) -> Result<Shard, String> {
    let mut bytes = Vec::new();
    let read = child.stdout.take().expect("stdout is piped").take(MAX_SHARD + 1).read_to_end(&mut bytes);
    let too_large = bytes.len() as u64 > MAX_SHARD;
    if read.is_err() || too_large {
        // Nobody reads the rest of what it writes.
        let _ = child.kill();
    }
    let status = child.wait().map_err(|e| format!("waiting for it: {e}"))?;
    if too_large {
        return Err(format!("it wrote more than the {} MiB a shard may take", MAX_SHARD >> 20));
    }
    read.map_err(|e| format!("reading its shard: {e}"))?;
    if !status.success() {
        return Err(status.to_string());
    }
    Shard::decode(&bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shares_are_contiguous_even_and_cover_every_bot() {
        for (count, processes) in [(10, 3), (6, 2), (7, 7), (3, 8), (50_000, 16), (1, 1)] {
            let s = shares(count, processes);
            assert_eq!(s.len(), processes.min(count));
            assert_eq!(s[0].first, 0);
            for w in s.windows(2) {
                assert_eq!(w[0].first + w[0].count, w[1].first, "{count} over {processes}: contiguous");
                assert!(w[0].count >= w[1].count && w[0].count - w[1].count <= 1, "{count} over {processes}: even");
            }
            assert!(s.iter().all(|s| s.count > 0));
            assert_eq!(s.iter().map(|s| s.count).sum::<usize>(), count);
        }
        assert_eq!(shares(10, 3)[1], Share { first: 4, count: 3 });
    }
}
