//! Saved hypertree volumes (`.hvol`): the generated voxels with everything rendering needs, so `canopy hypertree
//! render|stats|reduce|union` can work on a volume generated once. A magic header, a version byte and postcard;
//! indices are delta-encoded (small varints). Loading bounds the input and validates every count, index and number
//! before building the storage structure.

use canopy_protocol::hypertree::{DepthColor, MAX_DEPTH_COLORS, MAX_NAME_LEN, MAX_RESOLUTION, MAX_TREE_DEPTH};
use serde::{Deserialize, Serialize};

use super::generate::MAX_DENSE_VOXELS;
use super::storage::{Partitioned, VoxelList, VoxelStore};
use super::{Aabb, BoundingSphere, Bounds, Flow, Hypertree, Hypervolume, StorageType, Voxel};

/// The first bytes of a saved volume.
pub const MAGIC: &[u8; 8] = b"CNPYHVOL";
/// The format version.
pub const VERSION: u8 = 1;
/// Largest saved volume accepted, bytes.
pub const MAX_VOLUME_BYTES: usize = 1 << 30;
/// Most bounding volumes or flows in a saved volume.
pub const MAX_BOUNDS: usize = 1 << 16;

#[derive(Serialize, Deserialize)]
struct SavedPart {
    subpart: u8,
    deltas: Vec<u32>,
    densities: Vec<u8>,
    levels: Vec<u8>,
}

#[derive(Serialize, Deserialize)]
struct Saved {
    name: String,
    resolution: [u32; 3],
    extent: [f32; 3],
    storage: u8,
    partitioned: bool,
    tree_depth: u8,
    branch_depth: u8,
    depth_colors: Vec<DepthColor>,
    spheres: Vec<([f32; 3], f32)>,
    boxes: Vec<([f32; 3], [f32; 3])>,
    flows: Vec<([f32; 3], [f32; 3])>,
    parts: Vec<SavedPart>,
}

/// Why a saved volume did not load.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum VolumeFileError {
    /// Not a saved hypertree volume.
    #[error("not a hypertree volume (bad magic)")]
    Magic,
    /// A version this build does not read.
    #[error("volume format version {0} (this build reads {VERSION})")]
    Version(u8),
    /// Larger than [`MAX_VOLUME_BYTES`].
    #[error("volume of {0} bytes exceeds {MAX_VOLUME_BYTES}")]
    TooLarge(usize),
    /// postcard could not decode it.
    #[error("malformed volume: {0}")]
    Postcard(#[from] postcard::Error),
    /// Bytes after the volume.
    #[error("{0} trailing bytes after the volume")]
    Trailing(usize),
    /// Decoded, but inconsistent.
    #[error("invalid volume: {0}")]
    Invalid(&'static str),
}

fn storage_code(t: StorageType) -> u8 {
    match t {
        StorageType::Dense => 0,
        StorageType::IndexList => 1,
        StorageType::IndexBits => 2,
    }
}

fn saved_part(subpart: u8, list: &VoxelList) -> SavedPart {
    let mut prev = 0u32;
    let deltas = list
        .indices
        .iter()
        .map(|&i| {
            let d = i - prev;
            prev = i;
            d
        })
        .collect();
    SavedPart { subpart, deltas, densities: list.densities.clone(), levels: list.levels.clone() }
}

/// Encode a hypertree volume.
pub fn save(t: &Hypertree) -> Vec<u8> {
    let parts = match &t.store {
        VoxelStore::Partitioned(p) => {
            p.parts.iter().map(|part| saved_part(part.subpart, part.store.voxels())).collect()
        }
        other => vec![saved_part(0, &other.to_list())],
    };
    let saved = Saved {
        name: t.name.clone(),
        resolution: t.volume.resolution,
        extent: t.volume.extent,
        storage: storage_code(t.store.storage_type()),
        partitioned: t.store.is_partitioned(),
        tree_depth: t.tree_depth,
        branch_depth: t.branch_depth,
        depth_colors: t.depth_colors.clone(),
        spheres: t.bounds.spheres.iter().map(|s| (s.center, s.radius)).collect(),
        boxes: t.bounds.boxes.iter().map(|b| (b.min, b.max)).collect(),
        flows: t.flows.iter().map(|f| (f.from, f.to)).collect(),
        parts,
    };
    let mut out = MAGIC.to_vec();
    out.push(VERSION);
    out.extend(postcard::to_allocvec(&saved).expect("encoding into a Vec cannot fail"));
    out
}

fn finite(v: &[f32]) -> bool {
    v.iter().all(|x| x.is_finite() && x.abs() <= 1e9)
}

/// Decode untrusted bytes into a hypertree: bounded, checked to the end, every index and count validated.
pub fn load(bytes: &[u8]) -> Result<Hypertree, VolumeFileError> {
    if bytes.len() > MAX_VOLUME_BYTES {
        return Err(VolumeFileError::TooLarge(bytes.len()));
    }
    if bytes.len() < 9 || &bytes[..8] != MAGIC {
        return Err(VolumeFileError::Magic);
    }
    if bytes[8] != VERSION {
        return Err(VolumeFileError::Version(bytes[8]));
    }
    let (s, rest): (Saved, &[u8]) = postcard::take_from_bytes(&bytes[9..])?;
    if !rest.is_empty() {
        return Err(VolumeFileError::Trailing(rest.len()));
    }
    let bad = VolumeFileError::Invalid;
    if s.name.is_empty() || s.name.len() > MAX_NAME_LEN {
        return Err(bad("name length"));
    }
    if s.resolution.iter().any(|&r| r == 0 || r > MAX_RESOLUTION) {
        return Err(bad("resolution"));
    }
    if !finite(&s.extent) || s.extent.iter().any(|&e| e <= 0.0) {
        return Err(bad("extent"));
    }
    let storage = match s.storage {
        0 => StorageType::Dense,
        1 => StorageType::IndexList,
        2 => StorageType::IndexBits,
        _ => return Err(bad("storage type")),
    };
    if s.tree_depth == 0 || s.tree_depth > MAX_TREE_DEPTH || s.branch_depth >= s.tree_depth {
        return Err(bad("tree or branch depth"));
    }
    if s.depth_colors.len() > MAX_DEPTH_COLORS
        || s.depth_colors.iter().any(|c| c.levels[0] > c.levels[1] || !finite(&c.from) || !finite(&c.to))
    {
        return Err(bad("depth colours"));
    }
    if s.spheres.len() > MAX_BOUNDS || s.boxes.len() > MAX_BOUNDS || s.flows.len() > MAX_BOUNDS {
        return Err(bad("too many bounds or flows"));
    }
    if !s.spheres.iter().all(|(c, r)| finite(c) && finite(&[*r]) && *r >= 0.0)
        || !s.boxes.iter().all(|(a, b)| finite(a) && finite(b))
        || !s.flows.iter().all(|(a, b)| finite(a) && finite(b))
    {
        return Err(bad("non-finite bounds or flows"));
    }
    let volume = Hypervolume { resolution: s.resolution, extent: s.extent };
    let voxels = volume.voxel_count();
    if storage == StorageType::Dense && (voxels > MAX_DENSE_VOXELS || s.partitioned) {
        return Err(bad("dense array too large or partitioned"));
    }
    if s.parts.is_empty() || s.parts.len() > 256 || (!s.partitioned && s.parts.len() != 1) {
        return Err(bad("part count"));
    }
    let mut lists = Vec::with_capacity(s.parts.len());
    for p in s.parts {
        let n = p.deltas.len();
        if p.densities.len() != n || p.levels.len() != n || n as u64 > voxels {
            return Err(bad("list lengths"));
        }
        let mut list = VoxelList::default();
        let mut index = 0u64;
        for k in 0..n {
            if k > 0 && p.deltas[k] == 0 {
                return Err(bad("indices not strictly increasing"));
            }
            index += u64::from(p.deltas[k]);
            if index >= voxels {
                return Err(bad("index outside the volume"));
            }
            if p.densities[k] == 0 {
                return Err(bad("zero density in a list"));
            }
            list.push(index as u32, Voxel { density: p.densities[k], level: p.levels[k] });
        }
        lists.push((p.subpart, list));
    }
    let store = if s.partitioned {
        VoxelStore::Partitioned(Partitioned::from_parts(lists, storage, &volume))
    } else {
        let (_, list) = lists.pop().expect("one part");
        VoxelStore::from_list(list, storage, &volume)
    };
    let bounds = Bounds {
        spheres: s.spheres.into_iter().map(|(center, radius)| BoundingSphere { center, radius }).collect(),
        boxes: s.boxes.into_iter().map(|(min, max)| Aabb { min, max }).collect(),
    };
    let flows = s.flows.into_iter().map(|(from, to)| Flow { from, to }).collect();
    Ok(Hypertree::new(s.name, volume, store, s.depth_colors, s.tree_depth, s.branch_depth, bounds, flows))
}
