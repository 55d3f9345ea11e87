//! The client's species cache: content-addressed (SHA-256 of the encoding), in memory and on disk, bounded in
//! entries and bytes. Across sessions it is what lets a client tell the server "I already hold this species", so
//! nothing is sent again (seed 001 §4: a species' description is transmitted once).
//!
//! On disk each species is `<dir>/<hash>.species`, the graph's encoding; a file whose bytes do not hash to its
//! name or do not decode is removed and treated as a miss. Writes go through a temporary file and a rename, so a
//! crash never leaves a torn entry under a valid name. Over its bounds the oldest files (by modification time) go.

use std::collections::{HashMap, VecDeque};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use canopy_protocol::sync::Locked;
use canopy_protocol::{SpeciesGraph, SpeciesHash, limits};

/// Bounds of a species cache.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct CacheLimits {
    /// Most species held in memory.
    pub memory_entries: usize,
    /// Most species files on disk.
    pub disk_entries: usize,
    /// Most bytes of species files on disk.
    pub disk_bytes: u64,
}

impl Default for CacheLimits {
    fn default() -> Self {
        CacheLimits { memory_entries: 1024, disk_entries: 4096, disk_bytes: 64 << 20 }
    }
}

/// Why the on-disk cache could not be opened or written.
#[derive(Debug, thiserror::Error)]
pub enum CacheError {
    /// A filesystem operation failed.
    #[error("{path}: {source}")]
    Io {
        /// The file or directory.
        path: PathBuf,
        /// What failed.
        source: std::io::Error,
    },
    /// The directory belongs to another user, or is a link: its entries could be planted or read by others.
    #[error("{0}: the cache directory is not this user's own (owner or link); refusing to use it")]
    NotOwned(PathBuf),
}

#[derive(Debug, Default)]
struct Memory {
    map: HashMap<SpeciesHash, Arc<SpeciesGraph>>,
    order: VecDeque<SpeciesHash>,
}

/// Counters of cache use.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct CacheStats {
    /// Lookups answered from memory.
    pub memory_hits: u64,
    /// Lookups answered from disk.
    pub disk_hits: u64,
    /// Lookups that found nothing.
    pub misses: u64,
    /// Disk entries removed because they were corrupt.
    pub corrupt: u64,
}

/// A species cache (see the module docs). Shared between connections: all methods take `&self`.
#[derive(Debug)]
pub struct SpeciesCache {
    dir: Option<PathBuf>,
    limits: CacheLimits,
    memory: Mutex<Memory>,
    stats: Mutex<CacheStats>,
}

impl SpeciesCache {
    /// A cache in memory only.
    pub fn in_memory(limits: CacheLimits) -> SpeciesCache {
        SpeciesCache { dir: None, limits, memory: Mutex::default(), stats: Mutex::default() }
    }

    /// A cache in memory backed by `dir`, created with mode 700 if missing. A directory that is a link or belongs
    /// to another user is refused: whoever can write it could plant entries.
    pub fn open(dir: &Path, limits: CacheLimits) -> Result<SpeciesCache, CacheError> {
        let io = |source| CacheError::Io { path: dir.to_path_buf(), source };
        let mut builder = std::fs::DirBuilder::new();
        builder.recursive(true);
        #[cfg(unix)]
        std::os::unix::fs::DirBuilderExt::mode(&mut builder, 0o700);
        builder.create(dir).map_err(io)?;
        let meta = std::fs::symlink_metadata(dir).map_err(io)?;
        if !meta.is_dir() {
            return Err(CacheError::NotOwned(dir.to_path_buf()));
        }
        #[cfg(unix)]
        {
            use std::os::unix::fs::MetadataExt;
            // A file this process creates is owned by its effective user: compare the directory's owner with it.
            let probe = tempfile::NamedTempFile::new_in(dir).map_err(io)?;
            let me = probe.as_file().metadata().map_err(io)?.uid();
            if meta.uid() != me {
                return Err(CacheError::NotOwned(dir.to_path_buf()));
            }
        }
        Ok(SpeciesCache { dir: Some(dir.to_path_buf()), limits, memory: Mutex::default(), stats: Mutex::default() })
    }

    /// The directory backing the cache, if any.
    pub fn dir(&self) -> Option<&Path> {
        self.dir.as_deref()
    }

    /// Counters so far.
    pub fn stats(&self) -> CacheStats {
        *self.stats.locked()
    }

    fn count(&self, f: impl FnOnce(&mut CacheStats)) {
        f(&mut self.stats.locked());
    }

    fn path(&self, hash: &SpeciesHash) -> Option<PathBuf> {
        self.dir.as_ref().map(|d| d.join(format!("{}.species", hash.hex())))
    }

    /// The species with this content address, from memory or disk.
    pub fn get(&self, hash: &SpeciesHash) -> Option<Arc<SpeciesGraph>> {
        if let Some(g) = self.memory.locked().map.get(hash) {
            let g = Arc::clone(g);
            self.count(|s| s.memory_hits += 1);
            return Some(g);
        }
        let Some(path) = self.path(hash) else {
            self.count(|s| s.misses += 1);
            return None;
        };
        match read_verified(&path, hash) {
            Some(graph) => {
                let graph = Arc::new(graph);
                self.remember(*hash, Arc::clone(&graph));
                self.count(|s| s.disk_hits += 1);
                Some(graph)
            }
            None => {
                if std::fs::symlink_metadata(&path).is_ok() {
                    let _ = std::fs::remove_file(&path);
                    self.count(|s| s.corrupt += 1);
                }
                self.count(|s| s.misses += 1);
                None
            }
        }
    }

    fn remember(&self, hash: SpeciesHash, graph: Arc<SpeciesGraph>) {
        let mut m = self.memory.locked();
        if m.map.insert(hash, graph).is_none() {
            m.order.push_back(hash);
        }
        while m.map.len() > self.limits.memory_entries.max(1) {
            let Some(old) = m.order.pop_front() else { break };
            m.map.remove(&old);
        }
    }

    /// Store a species received from the wire (its `encoded` bytes hash to `hash`; `graph` is their decoding).
    pub fn insert(&self, hash: SpeciesHash, encoded: &[u8], graph: Arc<SpeciesGraph>) -> Result<(), CacheError> {
        self.remember(hash, graph);
        let Some(path) = self.path(&hash) else { return Ok(()) };
        // A regular entry is already there; anything else at the name (a planted link) is replaced, not followed.
        if std::fs::symlink_metadata(&path).is_ok_and(|m| m.file_type().is_file()) {
            return Ok(());
        }
        let io = |path: &Path| {
            let path = path.to_path_buf();
            move |source| CacheError::Io { path, source }
        };
        // A fresh file with a random name, created exclusively (never through a planted link), then renamed into
        // place: a reader sees a whole entry or none.
        let dir = path.parent().unwrap_or(Path::new("."));
        let mut tmp = tempfile::NamedTempFile::new_in(dir).map_err(io(dir))?;
        std::io::Write::write_all(&mut tmp, encoded).map_err(io(tmp.path()))?;
        tmp.persist(&path).map_err(|e| CacheError::Io { path: path.clone(), source: e.error })?;
        self.trim_disk();
        Ok(())
    }

    /// Remove the oldest files until the disk bounds hold.
    fn trim_disk(&self) {
        let Some(dir) = &self.dir else { return };
        let Ok(entries) = std::fs::read_dir(dir) else { return };
        let mut files: Vec<(std::time::SystemTime, u64, PathBuf)> = entries
            .filter_map(Result::ok)
            .filter(|e| e.path().extension().is_some_and(|x| x == "species"))
            .filter_map(|e| {
                let m = e.metadata().ok()?;
                Some((m.modified().ok()?, m.len(), e.path()))
            })
            .collect();
        files.sort();
        let mut bytes: u64 = files.iter().map(|f| f.1).sum();
        let mut n = files.len();
        for (_, len, path) in files {
            if n <= self.limits.disk_entries && bytes <= self.limits.disk_bytes {
                break;
            }
            if std::fs::remove_file(&path).is_ok() {
                n -= 1;
                bytes -= len;
            }
        }
    }
}

/// Read a cache file, bounded in size, and accept it only if it hashes to `hash` and decodes.
fn read_verified(path: &Path, hash: &SpeciesHash) -> Option<SpeciesGraph> {
    // An entry is a regular file, never a link (whoever can write the directory could plant one).
    if !std::fs::symlink_metadata(path).ok()?.file_type().is_file() {
        return None;
    }
    let bytes = canopy_worlds::fsread::read_bounded(path, limits::MAX_SPECIES_BYTES as u64).ok()?;
    if SpeciesHash::of(&bytes) != *hash {
        return None;
    }
    SpeciesGraph::decode(&bytes).ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn worm() -> (SpeciesHash, Vec<u8>, Arc<SpeciesGraph>) {
        let g = canopy_worlds::library::find("worm").unwrap().load().unwrap();
        let bytes = g.encode();
        (SpeciesHash::of(&bytes), bytes, Arc::new(g))
    }

    #[test]
    fn survives_a_restart_and_rejects_corrupt_files() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("cache");
        let (hash, bytes, graph) = worm();
        let a = SpeciesCache::open(&dir, CacheLimits::default()).unwrap();
        assert!(a.get(&hash).is_none());
        a.insert(hash, &bytes, Arc::clone(&graph)).unwrap();
        assert_eq!(a.get(&hash).as_deref(), Some(&*graph));
        // A new cache on the same directory (a new session) finds it on disk.
        let b = SpeciesCache::open(&dir, CacheLimits::default()).unwrap();
        assert_eq!(b.get(&hash).as_deref(), Some(&*graph));
        assert_eq!(b.stats().disk_hits, 1);
        // A corrupted file is a miss and is removed.
        std::fs::write(dir.join(format!("{}.species", hash.hex())), b"junk").unwrap();
        let c = SpeciesCache::open(&dir, CacheLimits::default()).unwrap();
        assert!(c.get(&hash).is_none());
        assert_eq!(c.stats().corrupt, 1);
        assert!(!dir.join(format!("{}.species", hash.hex())).exists());
    }

    #[test]
    fn bounded_in_memory_and_on_disk() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("cache");
        let limits = CacheLimits { memory_entries: 2, disk_entries: 3, disk_bytes: 1 << 20 };
        let cache = SpeciesCache::open(&dir, limits).unwrap();
        for name in ["worm", "monopodial", "conifer", "terrain", "morpho"] {
            let g = canopy_worlds::library::find(name).unwrap().load().unwrap();
            let bytes = g.encode();
            cache.insert(SpeciesHash::of(&bytes), &bytes, Arc::new(g)).unwrap();
        }
        assert_eq!(cache.memory.lock().unwrap().map.len(), 2);
        let files = std::fs::read_dir(&dir).unwrap().count();
        assert_eq!(files, 3);
    }

    #[cfg(unix)]
    #[test]
    fn planted_links_are_never_followed() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("cache");
        let cache = SpeciesCache::open(&dir, CacheLimits::default()).unwrap();
        {
            use std::os::unix::fs::PermissionsExt;
            assert_eq!(std::fs::metadata(&dir).unwrap().permissions().mode() & 0o777, 0o700);
        }
        // Someone plants the entry's name as a link to a file outside the cache.
        let victim = tmp.path().join("victim.txt");
        std::fs::write(&victim, "precious").unwrap();
        let (hash, bytes, graph) = worm();
        let entry = dir.join(format!("{}.species", hash.hex()));
        std::os::unix::fs::symlink(&victim, &entry).unwrap();
        // Reading does not follow it (and removes it); writing replaces the link, never the target.
        assert!(cache.get(&hash).is_none());
        std::os::unix::fs::symlink(&victim, &entry).unwrap();
        cache.insert(hash, &bytes, Arc::clone(&graph)).unwrap();
        assert_eq!(std::fs::read_to_string(&victim).unwrap(), "precious");
        assert!(std::fs::symlink_metadata(&entry).unwrap().file_type().is_file());
        let again = SpeciesCache::open(&dir, CacheLimits::default()).unwrap();
        assert_eq!(again.get(&hash).as_deref(), Some(&*graph));
        // A cache directory that is a link is refused.
        let link = tmp.path().join("link");
        std::os::unix::fs::symlink(&dir, &link).unwrap();
        assert!(matches!(SpeciesCache::open(&link, CacheLimits::default()), Err(CacheError::NotOwned(_))));
    }
}
