//! Explicit geometry for the bandwidth baselines: meshes quantised and compressed with meshoptimizer (as glTF's
//! `KHR_mesh_quantization` + `EXT_meshopt_compression` would carry them, then deflated as a transport would),
//! per-instance transforms as `EXT_mesh_gpu_instancing` carries them, and [`MeshSource`], the server's
//! [`GeometrySource`] for the explicit payload modes: lazily encoded per instance and per species, cached under a
//! memory bound.
//!
//! Everything here is deterministic: amplification and meshing are bit-exact, meshoptimizer's encoders are
//! deterministic for the same input, and deflate runs at a fixed level.

use std::collections::BTreeMap;
use std::ops::Range;
use std::sync::{Arc, Mutex};

use canopy_protocol::lru::Lru;
use canopy_protocol::sync::Locked;
use canopy_protocol::{CellCoord, InstanceId};
use canopy_server::session::GeometrySource;
use canopy_worlds::amplify::{Budget, Instance, amplify};
use canopy_worlds::mesh::{Mesh, MeshOptions, mesh};
use canopy_worlds::world::World;

/// The deflate level applied on top of meshoptimizer's codecs (its documentation recommends a general-purpose
/// compressor after them).
pub const DEFLATE_LEVEL: u8 = 6;

/// Why a mesh could not be encoded.
#[derive(Debug, thiserror::Error)]
pub enum EncodeError {
    /// meshoptimizer refused the input.
    #[error("meshoptimizer: {0}")]
    Meshopt(String),
    /// The mesh has more vertices than a 32-bit index can name.
    #[error("mesh of {0} vertices is too large")]
    TooLarge(usize),
}

/// The sizes of one encoded mesh.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct EncodedSize {
    /// Vertices.
    pub vertices: usize,
    /// Triangles.
    pub triangles: usize,
    /// Bytes of the quantised, uncompressed buffers (16 bytes per vertex, 4 per index).
    pub quantised: usize,
    /// Bytes after meshoptimizer's codecs and deflate: what is sent.
    pub compressed: usize,
}

fn deflate(bytes: &[u8]) -> Vec<u8> {
    miniz_oxide::deflate::compress_to_vec(bytes, DEFLATE_LEVEL)
}

fn push_stream(out: &mut Vec<u8>, stream: &[u8]) {
    out.extend_from_slice(&(stream.len() as u32).to_le_bytes());
    out.extend_from_slice(stream);
}

/// Encode a mesh: positions quantised to 16 bits in its bounding box (4 × u16), normals to 8-bit snorm (4 × i8),
/// colours to 8-bit unorm (4 × u8); vertex cache and fetch order optimised; each attribute stream and the index
/// buffer through meshoptimizer's codecs; the whole deflated. Returns the blob and its sizes.
pub fn encode_mesh(m: &Mesh) -> Result<(Vec<u8>, EncodedSize), EncodeError> {
    let n = m.vertex_count();
    if n > u32::MAX as usize / 2 {
        return Err(EncodeError::TooLarge(n));
    }
    let (lo, hi) = if n == 0 { ([0.0; 3], [0.0; 3]) } else { m.bounds() };
    let scale: Vec<f32> = (0..3).map(|i| if hi[i] > lo[i] { 65535.0 / (hi[i] - lo[i]) } else { 0.0 }).collect();
    let snorm = |v: f32| ((v.clamp(-1.0, 1.0) * 127.0).round() as i8) as u8;
    let unorm = |v: f32| (v.clamp(0.0, 1.0) * 255.0).round() as u8;
    let vertices: Vec<[u8; 16]> = (0..n)
        .map(|i| {
            let mut v = [0u8; 16];
            for a in 0..3 {
                let q = ((m.positions[i][a] - lo[a]) * scale[a]).round().clamp(0.0, 65535.0) as u16;
                v[2 * a..2 * a + 2].copy_from_slice(&q.to_le_bytes());
                v[8 + a] = snorm(m.normals[i][a]);
                v[12 + a] = unorm(m.colors[i][a]);
            }
            v[15] = 255;
            v
        })
        .collect();
    let mut indices = meshopt::optimize_vertex_cache(&m.indices, n);
    let vertices = meshopt::optimize_vertex_fetch(&mut indices, &vertices);
    let split = |range: Range<usize>| -> Vec<[u8; 8]> {
        vertices
            .iter()
            .map(|v| {
                let mut o = [0u8; 8];
                o[..range.len()].copy_from_slice(&v[range.clone()]);
                o
            })
            .collect()
    };
    let positions = split(0..8);
    let normals: Vec<[u8; 4]> = vertices.iter().map(|v| [v[8], v[9], v[10], v[11]]).collect();
    let colors: Vec<[u8; 4]> = vertices.iter().map(|v| [v[12], v[13], v[14], v[15]]).collect();
    let err = |e: meshopt::Error| EncodeError::Meshopt(e.to_string());
    let mut blob = Vec::new();
    blob.extend_from_slice(b"CMSH");
    blob.extend_from_slice(&(n as u32).to_le_bytes());
    blob.extend_from_slice(&(indices.len() as u32).to_le_bytes());
    for v in lo.iter().chain(&hi) {
        blob.extend_from_slice(&v.to_le_bytes());
    }
    push_stream(&mut blob, &meshopt::encode_vertex_buffer(&positions).map_err(err)?);
    push_stream(&mut blob, &meshopt::encode_vertex_buffer(&normals).map_err(err)?);
    push_stream(&mut blob, &meshopt::encode_vertex_buffer(&colors).map_err(err)?);
    push_stream(&mut blob, &meshopt::encode_index_buffer(&indices, n).map_err(err)?);
    let out = deflate(&blob);
    let size = EncodedSize {
        vertices: n,
        triangles: m.triangle_count(),
        quantised: 16 * n + 4 * indices.len(),
        compressed: out.len(),
    };
    Ok((out, size))
}

/// Amplify and mesh one instance (`world.instances[index]`) at full detail (default tessellation), as the client
/// would draw it near.
pub fn instance_mesh(world: &World, index: u32) -> Mesh {
    let species = usize::from(world.instances[index as usize].species);
    let graph = &world.species[species].graph;
    match amplify(graph, &world.instance(index, 0), &Budget::default()) {
        Ok(stream) => mesh(&stream, &MeshOptions::default()),
        // A budget overrun yields no geometry; the world's species are tested to amplify within the default budget.
        Err(_) => Mesh::new(),
    }
}

/// The one mesh of a species for instancing: its instance with seed 1 and default parameters, full detail.
pub fn species_mesh(world: &World, species: u8) -> Mesh {
    let Some(s) = world.species.get(usize::from(species)) else { return Mesh::new() };
    match amplify(&s.graph, &Instance::new(1), &Budget::default()) {
        Ok(stream) => mesh(&stream, &MeshOptions::default()),
        Err(_) => Mesh::new(),
    }
}

/// Bytes per instance of the uncompressed transform streams: translation 3 × f32, rotation 4 × snorm16,
/// scale 3 × f32 (`EXT_mesh_gpu_instancing`'s accessor types).
pub const TRANSFORM_BYTES: usize = 12 + 8 + 12;

/// The transforms of the instances of `cell` with indices `records` (those the world has): translation = the
/// instance's position (terrain height included), rotation = a yaw drawn from its seed, scale 1 (the instance's
/// parameters are not expressible as a transform; they are lost in this baseline); each attribute stream through
/// meshoptimizer's vertex codec, the whole deflated.
pub fn encode_transforms(world: &World, cell: CellCoord, records: Range<u16>) -> Vec<u8> {
    let ids: Vec<InstanceId> = records.filter_map(|i| InstanceId::new(cell, i)).collect();
    let indices: Vec<u32> = ids.iter().map_while(|&id| world.index_of(id)).collect();
    let translation: Vec<[f32; 3]> = indices.iter().map(|&index| world.position(index)).collect();
    let rotation: Vec<[i16; 4]> = ids[..indices.len()]
        .iter()
        .map(|&id| {
            let yaw = (world.instance_seed(id) >> 40) as f32 / (1u64 << 24) as f32 * std::f32::consts::TAU;
            let (s, c) = (yaw * 0.5).sin_cos();
            [0, (s * 32767.0).round() as i16, 0, (c * 32767.0).round() as i16]
        })
        .collect();
    let scale: Vec<[f32; 3]> = vec![[1.0; 3]; indices.len()];
    let mut blob = Vec::new();
    blob.extend_from_slice(b"CINS");
    blob.extend_from_slice(&(indices.len() as u32).to_le_bytes());
    for stream in [
        meshopt::encode_vertex_buffer(&translation),
        meshopt::encode_vertex_buffer(&rotation),
        meshopt::encode_vertex_buffer(&scale),
    ] {
        // The vertex codec only fails for vertex sizes that are not a multiple of 4 or above 256: not these.
        push_stream(&mut blob, &stream.unwrap_or_default());
    }
    deflate(&blob)
}

/// A byte-bounded cache of encoded blobs by instance, evicting the oldest first (a look-up is not a use).
#[derive(Default)]
pub struct BlobCache {
    blobs: Lru<InstanceId, Arc<Vec<u8>>>,
    limit: usize,
}

impl std::fmt::Debug for BlobCache {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("BlobCache").field("bytes", &self.blobs.cost()).field("limit", &self.limit).finish()
    }
}

impl BlobCache {
    /// A cache holding at most `limit` bytes (a single larger blob is returned but not kept).
    pub fn new(limit: usize) -> BlobCache {
        BlobCache { limit, ..BlobCache::default() }
    }

    /// The blob for `key`, if cached.
    pub fn get(&self, key: InstanceId) -> Option<Arc<Vec<u8>>> {
        self.blobs.peek(&key).cloned()
    }

    /// Keep `blob` for `key`, evicting the oldest entries to stay within the limit.
    pub fn insert(&mut self, key: InstanceId, blob: Arc<Vec<u8>>) {
        if blob.len() > self.limit || self.blobs.contains(&key) {
            return;
        }
        let bytes = blob.len();
        self.blobs.insert(key, blob, bytes);
        self.blobs.evict_to(self.limit, Some(&key));
    }

    /// Bytes held.
    pub fn bytes(&self) -> usize {
        self.blobs.cost()
    }

    /// Entries held.
    pub fn len(&self) -> usize {
        self.blobs.len()
    }

    /// Whether it holds nothing.
    pub fn is_empty(&self) -> bool {
        self.blobs.is_empty()
    }
}

/// Counters of a [`MeshSource`].
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SourceStats {
    /// Instance meshes encoded (cache misses).
    pub instance_meshes: u64,
    /// Their compressed bytes.
    pub instance_bytes: u64,
    /// Their vertices.
    pub instance_vertices: u64,
    /// Cache hits.
    pub hits: u64,
    /// Seconds spent amplifying, meshing and encoding.
    pub encode_seconds: f64,
}

/// The server's explicit geometry, computed lazily from the world and cached per instance and per species.
pub struct MeshSource {
    world: Arc<World>,
    instances: Mutex<BlobCache>,
    species: Mutex<BTreeMap<u8, Arc<Vec<u8>>>>,
    stats: Mutex<SourceStats>,
}

impl std::fmt::Debug for MeshSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("MeshSource").field("stats", &self.stats()).finish()
    }
}

impl MeshSource {
    /// A source for `world` caching at most `cache_bytes` of instance meshes.
    pub fn new(world: Arc<World>, cache_bytes: usize) -> MeshSource {
        MeshSource {
            world,
            instances: Mutex::new(BlobCache::new(cache_bytes)),
            species: Mutex::new(BTreeMap::new()),
            stats: Mutex::new(SourceStats::default()),
        }
    }

    /// What it has encoded so far.
    pub fn stats(&self) -> SourceStats {
        *self.stats.locked()
    }
}

impl GeometrySource for MeshSource {
    fn instance_mesh(&self, id: InstanceId) -> Arc<Vec<u8>> {
        if let Some(b) = self.instances.locked().get(id) {
            self.stats.locked().hits += 1;
            return b;
        }
        let Some(index) = self.world.index_of(id) else { return Arc::new(Vec::new()) };
        let t = std::time::Instant::now();
        let m = instance_mesh(&self.world, index);
        let blob = Arc::new(encode_mesh(&m).map(|(b, _)| b).unwrap_or_default());
        {
            let mut s = self.stats.locked();
            s.instance_meshes += 1;
            s.instance_bytes += blob.len() as u64;
            s.instance_vertices += m.vertex_count() as u64;
            s.encode_seconds += t.elapsed().as_secs_f64();
        }
        self.instances.locked().insert(id, Arc::clone(&blob));
        blob
    }

    fn species_mesh(&self, species: u8) -> Arc<Vec<u8>> {
        if let Some(b) = self.species.locked().get(&species) {
            return Arc::clone(b);
        }
        let blob = Arc::new(encode_mesh(&species_mesh(&self.world, species)).map(|(b, _)| b).unwrap_or_default());
        self.species.locked().insert(species, Arc::clone(&blob));
        blob
    }

    fn transforms(&self, cell: CellCoord, records: Range<u16>) -> Vec<u8> {
        encode_transforms(&self.world, cell, records)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn quad() -> Mesh {
        Mesh {
            positions: vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]],
            normals: vec![[0.0, 0.0, 1.0]; 4],
            colors: vec![[0.5, 0.25, 0.0]; 4],
            indices: vec![0, 1, 2, 0, 2, 3],
        }
    }

    #[test]
    fn encoding_is_deterministic_and_counts_sizes() {
        let (a, sa) = encode_mesh(&quad()).unwrap();
        let (b, _) = encode_mesh(&quad()).unwrap();
        assert_eq!(a, b);
        assert_eq!(sa, EncodedSize { vertices: 4, triangles: 2, quantised: 16 * 4 + 4 * 6, compressed: a.len() });
        let (e, se) = encode_mesh(&Mesh::new()).unwrap();
        assert!(!e.is_empty() && se.vertices == 0);
    }

    #[test]
    fn cache_stays_within_its_bound() {
        let mut c = BlobCache::new(10);
        let k = |i: u16| InstanceId::new(CellCoord::new(-1, 2), i).unwrap();
        c.insert(k(1), Arc::new(vec![0; 4]));
        c.insert(k(2), Arc::new(vec![0; 4]));
        assert_eq!((c.len(), c.bytes()), (2, 8));
        c.insert(k(3), Arc::new(vec![0; 4]));
        assert_eq!((c.len(), c.bytes()), (2, 8));
        assert!(c.get(k(1)).is_none() && c.get(k(2)).is_some() && c.get(k(3)).is_some());
        c.insert(k(4), Arc::new(vec![0; 11]));
        assert!(c.get(k(4)).is_none());
        assert!(c.bytes() <= 10);
    }
}
