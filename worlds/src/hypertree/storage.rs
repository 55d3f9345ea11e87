//! Hypertree storage (§5): the dense 3D array, the sorted index list with its density list, and the index list
//! with a bit array of non-empty voxels; optionally partitioned per first-level subpart. Also hit recording during
//! generation, the validation that compacts hits (sort, dedupe, count), density classes (§4, Figure 3) and the
//! occupancy brick map used for empty-space skipping.
//!
//! Every structure answers the same query — [`VoxelQuery::voxel`] by index — and the tests hold them equal voxel
//! for voxel. Memory is reported by [`VoxelStore::memory_bytes`].

use super::{Hypervolume, StorageType, Voxel, VoxelBox};

/// Answers "what is in voxel `index`?".
pub trait VoxelQuery {
    /// The voxel at `index` ([`Voxel::EMPTY`] if nothing is there; `index` need not be inside the volume).
    fn voxel(&self, index: u32) -> Voxel;

    /// The voxel at coordinates `v` (inside the volume) whose index is `index`: the renderer's query, which lets a
    /// structure use whichever of the two it addresses by.
    #[inline]
    fn voxel_at(&self, v: [u32; 3], index: u32) -> Voxel {
        let _ = v;
        self.voxel(index)
    }
}

/// Non-empty voxels sorted by index, without duplicates: the validated form every structure is built from.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct VoxelList {
    /// Voxel indices, strictly increasing.
    pub indices: Vec<u32>,
    /// Densities (non-zero), parallel to `indices`.
    pub densities: Vec<u8>,
    /// Levels, parallel to `indices`.
    pub levels: Vec<u8>,
}

impl VoxelList {
    /// Number of voxels.
    pub fn len(&self) -> usize {
        self.indices.len()
    }

    /// Whether the list is empty.
    pub fn is_empty(&self) -> bool {
        self.indices.is_empty()
    }

    /// Append a voxel (its index must exceed every index already present).
    pub fn push(&mut self, index: u32, v: Voxel) {
        debug_assert!(self.indices.last().is_none_or(|&l| l < index));
        self.indices.push(index);
        self.densities.push(v.density);
        self.levels.push(v.level);
    }

    /// Position of `index` by bisection (§5).
    #[inline]
    pub fn position(&self, index: u32) -> Option<usize> {
        let ix = &self.indices;
        let mut lo = 0usize;
        let mut len = ix.len();
        if len == 0 {
            return None;
        }
        // Branch-light bisection: halve the window until one candidate remains.
        while len > 1 {
            let half = len / 2;
            if ix[lo + half] <= index {
                lo += half;
            }
            len -= half;
        }
        (ix[lo] == index).then_some(lo)
    }

    fn bytes(&self) -> usize {
        self.indices.len() * 4 + self.densities.len() + self.levels.len()
    }
}

impl VoxelQuery for VoxelList {
    #[inline]
    fn voxel(&self, index: u32) -> Voxel {
        match self.position(index) {
            Some(p) => Voxel { density: self.densities[p], level: self.levels[p] },
            None => Voxel::EMPTY,
        }
    }
}

/// The index list + density list structure (§5), looked up by bisection.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct IndexList {
    /// The voxels.
    pub list: VoxelList,
}

impl VoxelQuery for IndexList {
    #[inline]
    fn voxel(&self, index: u32) -> Voxel {
        self.list.voxel(index)
    }
}

/// Indices per block of a [`PackedList`] (one byte of an index is stored per voxel).
const PACK_BLOCK: usize = 256;
/// Blocks per super-block of a [`PackedList`] (block offsets are 16-bit inside a super-block).
const PACK_SUPER: usize = 256;

/// The index list + density list structure (§5), packed: per voxel the low byte of its index (relative to the
/// lowest index) and a one-byte code into a palette of the (density, level) pairs that occur (two bytes when more
/// than 256 occur); the rest of the index comes from its block of 256 indices, whose first entry is a 16-bit
/// offset from its super-block's (65 536 indices) 32-bit first entry. A lookup reads two table entries and scans
/// the few entries of one block. About 2–3 bytes a voxel instead of 6; the same voxels as the list it is built from.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct PackedList {
    /// Lowest index.
    lo: u32,
    /// First entry of each super-block, and the entry count after the last.
    supers: Vec<u32>,
    /// First entry of each block, from its super-block's first entry; one more block than the span needs.
    blocks: Vec<u16>,
    /// `(index − lo) mod 256` per voxel.
    low: Vec<u8>,
    /// Palette codes per voxel.
    codes: Codes,
    /// The distinct (density, level) pairs, sorted.
    palette: Vec<Voxel>,
}

#[derive(Clone, Debug, PartialEq, Eq)]
enum Codes {
    Narrow(Vec<u8>),
    Wide(Vec<u16>),
}

impl Default for Codes {
    fn default() -> Self {
        Codes::Narrow(Vec::new())
    }
}

impl PackedList {
    /// Pack a validated list.
    pub fn new(list: &VoxelList) -> PackedList {
        let (Some(&lo), Some(&hi)) = (list.indices.first(), list.indices.last()) else {
            return PackedList { supers: vec![0], blocks: vec![0], ..PackedList::default() };
        };
        let nblocks = ((hi - lo) as usize + 1).div_ceil(PACK_BLOCK) + 1;
        let mut supers = vec![0u32; nblocks.div_ceil(PACK_SUPER) + 1];
        let mut blocks = vec![0u16; nblocks];
        // Entries per block, then prefix sums (per super-block for the blocks).
        let mut counts = vec![0u32; nblocks];
        for &i in &list.indices {
            counts[(i - lo) as usize / PACK_BLOCK] += 1;
        }
        let mut total = 0u32;
        for (s, chunk) in counts.chunks(PACK_SUPER).enumerate() {
            supers[s] = total;
            let mut within = 0u32;
            for (k, &c) in chunk.iter().enumerate() {
                blocks[s * PACK_SUPER + k] = within as u16;
                within += c;
            }
            total += within;
        }
        for s in supers.iter_mut().skip(nblocks.div_ceil(PACK_SUPER)) {
            *s = total;
        }
        let low = list.indices.iter().map(|&i| (i - lo) as u8).collect();
        let mut seen = vec![false; 1 << 16];
        for k in 0..list.len() {
            seen[usize::from(list.densities[k]) << 8 | usize::from(list.levels[k])] = true;
        }
        let palette: Vec<Voxel> =
            (0..1usize << 16).filter(|&p| seen[p]).map(|p| Voxel { density: (p >> 8) as u8, level: p as u8 }).collect();
        let mut code_of = vec![0u16; 1 << 16];
        for (c, v) in palette.iter().enumerate() {
            code_of[usize::from(v.density) << 8 | usize::from(v.level)] = c as u16;
        }
        let code = |k: usize| code_of[usize::from(list.densities[k]) << 8 | usize::from(list.levels[k])];
        let codes = if palette.len() <= 256 {
            Codes::Narrow((0..list.len()).map(|k| code(k) as u8).collect())
        } else {
            Codes::Wide((0..list.len()).map(code).collect())
        };
        PackedList { lo, supers, blocks, low, codes, palette }
    }

    /// Number of voxels.
    pub fn len(&self) -> usize {
        self.low.len()
    }

    /// Whether the list is empty.
    pub fn is_empty(&self) -> bool {
        self.low.is_empty()
    }

    /// The first entry of block `b` (`b` up to the block count).
    #[inline]
    fn start(&self, b: usize) -> usize {
        self.supers[b / PACK_SUPER] as usize + usize::from(self.blocks[b])
    }

    #[inline]
    fn at(&self, pos: usize) -> Voxel {
        match &self.codes {
            Codes::Narrow(c) => self.palette[usize::from(c[pos])],
            Codes::Wide(c) => self.palette[usize::from(c[pos])],
        }
    }

    /// Position of `index` in the list.
    #[inline]
    pub fn position(&self, index: u32) -> Option<usize> {
        let o = index.checked_sub(self.lo)? as usize;
        let b = o / PACK_BLOCK;
        if b + 1 >= self.blocks.len() {
            return None;
        }
        let (start, end) = (self.start(b), self.start(b + 1));
        let want = o as u8;
        self.low[start..end].iter().position(|&l| l >= want).filter(|&k| self.low[start + k] == want).map(|k| start + k)
    }

    /// Visit every voxel in increasing index order.
    pub fn for_each(&self, mut f: impl FnMut(u32, Voxel)) {
        for b in 0..self.blocks.len() - 1 {
            let base = self.lo + (b * PACK_BLOCK) as u32;
            for pos in self.start(b)..self.start(b + 1) {
                f(base + u32::from(self.low[pos]), self.at(pos));
            }
        }
    }

    /// The voxels as a validated list.
    pub fn to_list(&self) -> VoxelList {
        let mut out = VoxelList::default();
        self.for_each(|i, v| out.push(i, v));
        out
    }

    /// Bytes of the payload: low bytes, codes, palette and the two block tables.
    pub fn bytes(&self) -> usize {
        let codes = match &self.codes {
            Codes::Narrow(c) => c.len(),
            Codes::Wide(c) => c.len() * 2,
        };
        self.low.len() + codes + self.palette.len() * 2 + self.supers.len() * 4 + self.blocks.len() * 2
    }
}

impl VoxelQuery for PackedList {
    #[inline]
    fn voxel(&self, index: u32) -> Voxel {
        match self.position(index) {
            Some(p) => self.at(p),
            None => Voxel::EMPTY,
        }
    }
}

/// Words of the bit array per rank-directory entry.
const RANK_WORDS: usize = 8;

/// The index list plus a bit array of non-empty voxels between the lowest and highest index (§5). An empty voxel is
/// answered from the bit array alone; a non-empty one by its rank in the bit array (a popcount directory every 512
/// bits), which gives its position in the lists without bisection.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct IndexBits {
    /// The voxels.
    pub list: VoxelList,
    /// Lowest non-empty index (bit 0).
    pub lo: u32,
    /// Bit `i` is set if voxel `lo + i` is not empty.
    pub bits: Vec<u64>,
    /// Set bits before each group of [`RANK_WORDS`] words.
    pub rank: Vec<u32>,
}

impl IndexBits {
    /// Build from a validated list.
    pub fn new(list: VoxelList) -> IndexBits {
        let (lo, hi) = match (list.indices.first(), list.indices.last()) {
            (Some(&a), Some(&b)) => (a, b),
            _ => return IndexBits { list, lo: 0, bits: Vec::new(), rank: Vec::new() },
        };
        let span = (hi - lo) as usize + 1;
        let mut bits = vec![0u64; span.div_ceil(64)];
        for &i in &list.indices {
            let o = (i - lo) as usize;
            bits[o >> 6] |= 1 << (o & 63);
        }
        let mut rank = Vec::with_capacity(bits.len().div_ceil(RANK_WORDS));
        let mut acc = 0u32;
        for chunk in bits.chunks(RANK_WORDS) {
            rank.push(acc);
            acc += chunk.iter().map(|w| w.count_ones()).sum::<u32>();
        }
        IndexBits { list, lo, bits, rank }
    }

    /// Whether voxel `index` is non-empty (the bit array alone).
    #[inline]
    pub fn occupied(&self, index: u32) -> bool {
        let Some(o) = index.checked_sub(self.lo) else { return false };
        let o = o as usize;
        self.bits.get(o >> 6).is_some_and(|w| w >> (o & 63) & 1 == 1)
    }
}

impl VoxelQuery for IndexBits {
    #[inline]
    fn voxel(&self, index: u32) -> Voxel {
        let Some(o) = index.checked_sub(self.lo) else { return Voxel::EMPTY };
        let o = o as usize;
        let w = o >> 6;
        let Some(&word) = self.bits.get(w) else { return Voxel::EMPTY };
        let bit = o & 63;
        if word >> bit & 1 == 0 {
            return Voxel::EMPTY;
        }
        let group = w / RANK_WORDS;
        let mut pos = self.rank[group] as usize;
        for &x in &self.bits[group * RANK_WORDS..w] {
            pos += x.count_ones() as usize;
        }
        pos += (word & ((1u64 << bit) - 1)).count_ones() as usize;
        Voxel { density: self.list.densities[pos], level: self.list.levels[pos] }
    }
}

/// The dense 3D array: per voxel one density byte and, beside it, one level byte. Cells are laid out in bricks of
/// 8³ voxels (x fastest inside a brick, bricks in x, y, z order), so the samples of a ray stay within a few cache
/// lines and pages instead of striding a whole slice per step along z.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct DenseArray {
    /// `[density, level]` per voxel, brick-major (density 0 is empty; the level is meaningless there).
    pub cells: Vec<[u8; 2]>,
    /// The volume's resolution.
    pub resolution: [u32; 3],
    /// Bricks along x and y.
    pub bricks: [u32; 2],
    /// Number of non-empty voxels.
    pub count: usize,
}

impl DenseArray {
    /// An empty array for a volume of `resolution`.
    pub fn new(resolution: [u32; 3]) -> DenseArray {
        let b = resolution.map(|r| r.div_ceil(8));
        let n = b.iter().map(|&x| x as usize).product::<usize>() * 512;
        DenseArray { cells: vec![[0u8; 2]; n], resolution, bricks: [b[0], b[1]], count: 0 }
    }

    /// The cell offset of voxel `v`.
    #[inline]
    pub fn offset(&self, v: [u32; 3]) -> usize {
        let brick = ((v[2] >> 3) * self.bricks[1] + (v[1] >> 3)) * self.bricks[0] + (v[0] >> 3);
        ((brick as usize) << 9) | (((v[2] & 7) << 6 | (v[1] & 7) << 3 | (v[0] & 7)) as usize)
    }

    /// Count one hit of voxel `v` (index `index`) at `level`: the shallowest level wins, and a voxel's first hit
    /// adds its index to `touched`.
    #[inline]
    fn hit(&mut self, v: [u32; 3], index: u32, level: u8, touched: &mut Vec<u32>) {
        let o = self.offset(v);
        let c = &mut self.cells[o];
        if c[0] == 0 {
            touched.push(index);
            *c = [1, level];
        } else {
            c[0] = c[0].saturating_add(1);
            c[1] = c[1].min(level);
        }
    }

    /// The coordinates of voxel `index`.
    #[inline]
    fn coords(&self, index: u32) -> [u32; 3] {
        let [rx, ry, _] = self.resolution;
        [index % rx, (index / rx) % ry, index / (rx * ry)]
    }
}

impl VoxelQuery for DenseArray {
    #[inline]
    fn voxel(&self, index: u32) -> Voxel {
        let [rx, ry, rz] = self.resolution;
        if u64::from(index) >= u64::from(rx) * u64::from(ry) * u64::from(rz) {
            return Voxel::EMPTY;
        }
        self.voxel_at(self.coords(index), index)
    }

    #[inline]
    fn voxel_at(&self, v: [u32; 3], _: u32) -> Voxel {
        match self.cells.get(self.offset(v)) {
            Some(&[d, l]) if d != 0 => Voxel { density: d, level: l },
            _ => Voxel::EMPTY,
        }
    }
}

/// The lists of one first-level subpart.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Part {
    /// Which subpart: 0 is the condensation (stem), `j + 1` the subparts made by transformation `j`.
    pub subpart: u8,
    /// Lowest voxel coordinates in the part.
    pub min: [u32; 3],
    /// Highest voxel coordinates in the part.
    pub max: [u32; 3],
    /// The part's voxels: an index list, or an index list with bit array.
    pub store: PartStore,
}

/// The structure of one part.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum PartStore {
    /// Index list.
    IndexList(IndexList),
    /// Index list with bit array.
    IndexBits(IndexBits),
}

impl PartStore {
    fn list(&self) -> &VoxelList {
        match self {
            PartStore::IndexList(l) => &l.list,
            PartStore::IndexBits(b) => &b.list,
        }
    }
}

/// Separate lists per first-level subpart (§5). A voxel hit by several subparts is in each of their lists, with the
/// same density; a lookup returns that density and the shallowest level among the parts that hold it.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Partitioned {
    /// The parts, by subpart number.
    pub parts: Vec<Part>,
    /// The volume's resolution (to test part bounds).
    pub resolution: [u32; 3],
    /// Distinct non-empty voxels.
    pub count: usize,
}

impl Partitioned {
    /// Build from per-subpart lists (each sorted; a voxel in several parts must carry the same density).
    pub fn from_parts(parts: Vec<(u8, VoxelList)>, ty: StorageType, volume: &Hypervolume) -> Partitioned {
        let mut all: Vec<u32> = parts.iter().flat_map(|p| p.1.indices.iter().copied()).collect();
        all.sort_unstable();
        all.dedup();
        let parts = parts
            .into_iter()
            .map(|(subpart, list)| {
                let (mut min, mut max) = ([u32::MAX; 3], [0u32; 3]);
                for &i in &list.indices {
                    let v = volume.coords(i);
                    for a in 0..3 {
                        min[a] = min[a].min(v[a]);
                        max[a] = max[a].max(v[a]);
                    }
                }
                let store = match ty {
                    StorageType::IndexBits => PartStore::IndexBits(IndexBits::new(list)),
                    _ => PartStore::IndexList(IndexList { list }),
                };
                Part { subpart, min, max, store }
            })
            .collect();
        Partitioned { parts, resolution: volume.resolution, count: all.len() }
    }
}

impl PartStore {
    /// The part's voxel list.
    pub fn voxels(&self) -> &VoxelList {
        self.list()
    }
}

impl VoxelQuery for Partitioned {
    #[inline]
    fn voxel(&self, index: u32) -> Voxel {
        let [rx, ry, _] = self.resolution;
        let v = [index % rx, (index / rx) % ry, index / (rx * ry)];
        let mut out = Voxel::EMPTY;
        for p in &self.parts {
            if (0..3).any(|i| v[i] < p.min[i] || v[i] > p.max[i]) {
                continue;
            }
            let got = match &p.store {
                PartStore::IndexList(l) => l.voxel(index),
                PartStore::IndexBits(b) => b.voxel(index),
            };
            if got.density != 0 && (out.density == 0 || got.level < out.level) {
                out = got;
            }
        }
        out
    }
}

/// A hypertree's voxels in one of the storage structures.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum VoxelStore {
    /// Dense 3D array.
    Dense(DenseArray),
    /// Index list (packed).
    IndexList(PackedList),
    /// Index list and bit array.
    IndexBits(IndexBits),
    /// Index lists (with or without bit arrays) per first-level subpart.
    Partitioned(Partitioned),
}

impl VoxelQuery for VoxelStore {
    #[inline]
    fn voxel_at(&self, v: [u32; 3], index: u32) -> Voxel {
        match self {
            VoxelStore::Dense(d) => d.voxel_at(v, index),
            other => other.voxel(index),
        }
    }

    #[inline]
    fn voxel(&self, index: u32) -> Voxel {
        match self {
            VoxelStore::Dense(d) => d.voxel(index),
            VoxelStore::IndexList(l) => l.voxel(index),
            VoxelStore::IndexBits(b) => b.voxel(index),
            VoxelStore::Partitioned(p) => p.voxel(index),
        }
    }
}

impl VoxelStore {
    /// Build a store of `ty` from a validated list (`volume` sizes the dense array).
    pub fn from_list(list: VoxelList, ty: StorageType, volume: &Hypervolume) -> VoxelStore {
        match ty {
            StorageType::IndexList => VoxelStore::IndexList(PackedList::new(&list)),
            StorageType::IndexBits => VoxelStore::IndexBits(IndexBits::new(list)),
            StorageType::Dense => {
                let mut d = DenseArray::new(volume.resolution);
                for (k, &i) in list.indices.iter().enumerate() {
                    let o = d.offset(d.coords(i));
                    d.cells[o] = [list.densities[k], list.levels[k]];
                }
                d.count = list.len();
                VoxelStore::Dense(d)
            }
        }
    }

    /// The storage structure (a partitioned store reports its parts' structure).
    pub fn storage_type(&self) -> StorageType {
        match self {
            VoxelStore::Dense(_) => StorageType::Dense,
            VoxelStore::IndexList(_) => StorageType::IndexList,
            VoxelStore::IndexBits(_) => StorageType::IndexBits,
            VoxelStore::Partitioned(p) => match p.parts.first().map(|p| &p.store) {
                Some(PartStore::IndexBits(_)) => StorageType::IndexBits,
                _ => StorageType::IndexList,
            },
        }
    }

    /// Whether the store is partitioned per first-level subpart.
    pub fn is_partitioned(&self) -> bool {
        matches!(self, VoxelStore::Partitioned(_))
    }

    /// Number of distinct non-empty voxels.
    pub fn len(&self) -> usize {
        match self {
            VoxelStore::Dense(d) => d.count,
            VoxelStore::IndexList(l) => l.len(),
            VoxelStore::IndexBits(b) => b.list.len(),
            VoxelStore::Partitioned(p) => p.count,
        }
    }

    /// Whether no voxel is set.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Bytes the structure occupies (the payload: arrays and lists, not the struct headers).
    pub fn memory_bytes(&self) -> usize {
        match self {
            VoxelStore::Dense(d) => d.cells.len() * 2,
            VoxelStore::IndexList(l) => l.bytes(),
            VoxelStore::IndexBits(b) => b.list.bytes() + b.bits.len() * 8 + b.rank.len() * 4,
            VoxelStore::Partitioned(p) => p
                .parts
                .iter()
                .map(|part| {
                    28 + match &part.store {
                        PartStore::IndexList(l) => l.list.bytes(),
                        PartStore::IndexBits(b) => b.list.bytes() + b.bits.len() * 8 + b.rank.len() * 4,
                    }
                })
                .sum(),
        }
    }

    /// Visit every non-empty voxel in increasing index order.
    pub fn for_each(&self, mut f: impl FnMut(u32, Voxel)) {
        match self {
            VoxelStore::Dense(d) => {
                let [rx, ry, rz] = d.resolution;
                let mut i = 0u32;
                for z in 0..rz {
                    for y in 0..ry {
                        for x in 0..rx {
                            let [density, level] = d.cells[d.offset([x, y, z])];
                            if density != 0 {
                                f(i, Voxel { density, level });
                            }
                            i += 1;
                        }
                    }
                }
            }
            VoxelStore::IndexList(l) => l.for_each(f),
            VoxelStore::IndexBits(IndexBits { list, .. }) => {
                for k in 0..list.len() {
                    f(list.indices[k], Voxel { density: list.densities[k], level: list.levels[k] });
                }
            }
            VoxelStore::Partitioned(_) => {
                let l = self.to_list();
                for k in 0..l.len() {
                    f(l.indices[k], Voxel { density: l.densities[k], level: l.levels[k] });
                }
            }
        }
    }

    /// The voxels as one validated list.
    pub fn to_list(&self) -> VoxelList {
        match self {
            VoxelStore::IndexList(l) => l.to_list(),
            VoxelStore::IndexBits(b) => b.list.clone(),
            VoxelStore::Dense(_) => {
                let mut out = VoxelList::default();
                self.for_each(|i, v| out.push(i, v));
                out
            }
            VoxelStore::Partitioned(p) => {
                // Merge the parts: equal indices carry equal densities; keep the shallowest level.
                let mut all: Vec<(u32, u8, u8)> =
                    Vec::with_capacity(p.parts.iter().map(|x| x.store.list().len()).sum());
                for part in &p.parts {
                    let l = part.store.list();
                    all.extend((0..l.len()).map(|k| (l.indices[k], l.levels[k], l.densities[k])));
                }
                all.sort_unstable();
                let mut out = VoxelList::default();
                for (i, level, density) in all {
                    if out.indices.last() != Some(&i) {
                        out.push(i, Voxel { density, level });
                    }
                }
                out
            }
        }
    }
}

/// The mapping from hit counts to densities (§4, Figure 3): hit counts are distributed into classes so that each
/// class holds about the same number of voxels — histogram equalisation: hit count `n` goes to class
/// `⌈F(n) · (C − 1)⌉`, where `F` is the cumulative share of voxels hit at most `n` times. A hit count shared by more
/// than a class's share of the voxels (the many voxels hit once) fills its class alone and the classes it spans
/// stay empty. Class `c` of `C − 1` non-empty classes has density `round(255 · c / (C − 1))`; two classes make a
/// binary (solid) hypertree.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct DensityClasses {
    /// Density for each hit count 0..=255 (0 hits → 0).
    pub density: [u8; 256],
    /// Class index for each hit count.
    pub class: [u8; 256],
}

impl DensityClasses {
    /// Equalise `histogram` (voxels per hit count) into `classes` classes, the empty one included.
    pub fn equalise(histogram: &[u64; 256], classes: u8) -> DensityClasses {
        let nonempty = u64::from(classes.max(2) - 1);
        let total: u64 = histogram[1..].iter().sum::<u64>().max(1);
        let mut density = [0u8; 256];
        let mut class = [0u8; 256];
        let mut cum = 0u64;
        for n in 1..256 {
            cum += histogram[n];
            let c = (cum * nonempty).div_ceil(total).clamp(1, nonempty);
            class[n] = c as u8;
            density[n] = ((255 * c + nonempty / 2) / nonempty) as u8;
        }
        DensityClasses { density, class }
    }
}

/// Bricks of 8³ voxels, one bit each: set if any voxel of the brick is non-empty.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct BrickMap {
    /// Bricks along x, y, z.
    pub dims: [u32; 3],
    /// One bit per brick, brick index `bx + dims_x · (by + dims_y · bz)`.
    pub bits: Vec<u64>,
}

/// log2 of the brick side, in voxels.
pub const BRICK_SHIFT: u32 = 3;

impl BrickMap {
    /// The brick map and the voxel box of a store.
    pub fn build(volume: &Hypervolume, store: &VoxelStore) -> (BrickMap, Option<VoxelBox>) {
        match store {
            VoxelStore::IndexBits(IndexBits { list, .. }) => {
                BrickMap::from_indices(volume, list.indices.iter().copied())
            }
            _ => {
                let mut all = Vec::with_capacity(store.len());
                store.for_each(|i, _| all.push(i));
                BrickMap::from_indices(volume, all.into_iter())
            }
        }
    }

    /// The brick map and voxel box of the non-empty voxels `indices` (any order).
    pub fn from_indices(volume: &Hypervolume, indices: impl Iterator<Item = u32>) -> (BrickMap, Option<VoxelBox>) {
        let dims = volume.resolution.map(|r| r.div_ceil(1 << BRICK_SHIFT));
        let n = dims.iter().map(|&d| d as usize).product::<usize>();
        let mut map = BrickMap { dims, bits: vec![0u64; n.div_ceil(64)] };
        let mut lo = [u32::MAX; 3];
        let mut hi = [0u32; 3];
        let mut any = false;
        for i in indices {
            let v = volume.coords(i);
            any = true;
            for a in 0..3 {
                lo[a] = lo[a].min(v[a]);
                hi[a] = hi[a].max(v[a]);
            }
            let b = map.brick_index(v);
            map.bits[b >> 6] |= 1 << (b & 63);
        }
        (map, any.then_some((lo, hi)))
    }

    /// The brick index holding voxel `v`.
    #[inline]
    pub fn brick_index(&self, v: [u32; 3]) -> usize {
        let [bx, by, bz] = v.map(|c| (c >> BRICK_SHIFT) as usize);
        bx + self.dims[0] as usize * (by + self.dims[1] as usize * bz)
    }

    /// Whether the brick holding voxel `v` has anything in it.
    #[inline]
    pub fn occupied(&self, v: [u32; 3]) -> bool {
        let b = self.brick_index(v);
        self.bits[b >> 6] >> (b & 63) & 1 == 1
    }

    /// Bytes of the bit array.
    pub fn memory_bytes(&self) -> usize {
        self.bits.len() * 8
    }
}

/// Raw hits flushed to the compact list once this many have accumulated (bounds memory for any iteration count).
const CHUNK: usize = 1 << 22;

/// One compacted hit record: voxel, subpart, hit count (saturating at 255) and the shallowest level.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Compact {
    /// `subpart << 32 | index`: records sort by subpart, then voxel.
    key: u64,
    hits: u8,
    level: u8,
}

/// Where generation records voxel hits (§6 steps c and v): straight into a dense array, or as an index list that
/// validation compacts (§5: sort, remove duplicates, count).
pub struct HitRecorder {
    mode: Mode,
    /// Hits recorded (including repeats).
    pub hits: u64,
}

enum Mode {
    Dense {
        array: DenseArray,
        touched: Vec<u32>,
    },
    /// Narrow keys `index << LEVEL_BITS | level` (subpart 0, index below 2²⁷, level below 32): half the memory
    /// traffic of the wide keys and fewer radix passes. A hit that does not fit widens every key for good.
    Keys32 {
        raw: Vec<u32>,
        compact: Vec<Compact>,
        scratch: Vec<u32>,
    },
    /// Hit counts and levels in bricks of 8³ allocated on first touch (subpart 0 only; for coherent hits such as
    /// line generators', which cross runs of neighbouring voxels): no sort at all. A hit of another subpart turns
    /// the bricks into compact records and switches to wide keys for good.
    Bricks(BrickGrid),
    Keys {
        raw: Vec<u64>,
        compact: Vec<Compact>,
        scratch: Vec<u64>,
    },
}

/// Level bits of a narrow key.
const LEVEL_BITS: u32 = 5;

/// Most voxels of a volume recorded in bricks (the brick slot table is 4 bytes per 512 voxels).
const BRICK_GRID_VOXELS: u64 = 1 << 30;

impl HitRecorder {
    /// A recorder for a volume of `resolution` that will be stored as `ty`.
    pub fn new(ty: StorageType, resolution: [u32; 3]) -> HitRecorder {
        let mode = match ty {
            StorageType::Dense => Mode::Dense { array: DenseArray::new(resolution), touched: Vec::new() },
            _ if resolution.iter().map(|&r| u64::from(r)).product::<u64>() <= 1 << (32 - LEVEL_BITS) => {
                Mode::Keys32 { raw: Vec::with_capacity(1 << 16), compact: Vec::new(), scratch: Vec::new() }
            }
            _ => Mode::Keys { raw: Vec::with_capacity(1 << 16), compact: Vec::new(), scratch: Vec::new() },
        };
        HitRecorder { mode, hits: 0 }
    }

    /// A recorder for hits that come in runs of neighbouring voxels (line generators): index lists of a volume
    /// of at most 2³⁰ voxels count them in bricks allocated on first touch instead of sorting the raw hits. The
    /// result is the same as [`HitRecorder::new`]'s.
    pub fn new_coherent(ty: StorageType, resolution: [u32; 3]) -> HitRecorder {
        if ty != StorageType::Dense && resolution.iter().map(|&r| u64::from(r)).product::<u64>() <= BRICK_GRID_VOXELS {
            return HitRecorder { mode: Mode::Bricks(BrickGrid::new(resolution)), hits: 0 };
        }
        HitRecorder::new(ty, resolution)
    }

    /// Record one hit of voxel `index` by a generator at `level` belonging to `subpart`.
    #[inline]
    pub fn record(&mut self, index: u32, level: u8, subpart: u8) {
        let v = match &self.mode {
            Mode::Dense { array, .. } => array.coords(index),
            Mode::Bricks(g) => {
                let [rx, ry, _] = g.resolution;
                [index % rx, (index / rx) % ry, index / (rx * ry)]
            }
            _ => [0; 3],
        };
        self.record_at(v, index, level, subpart);
    }

    /// The dense array's hit counting, for a caller that records voxel by voxel without batching; `None` for the
    /// lists.
    #[inline]
    pub(crate) fn dense_hits(&mut self) -> Option<DenseHits<'_>> {
        match &mut self.mode {
            Mode::Dense { array, touched } => Some(DenseHits { array, touched, hits: &mut self.hits }),
            _ => None,
        }
    }

    /// The brick grid's hit counting for hits of `subpart`, for a caller that records the voxels of one
    /// generator one at a time; `None` unless hits are counted in bricks and `subpart` is 0.
    #[inline]
    pub(crate) fn brick_hits(&mut self, subpart: u8) -> Option<BrickHits<'_>> {
        match &mut self.mode {
            Mode::Bricks(grid) if subpart == 0 => {
                Some(BrickHits { grid, hits: &mut self.hits, last: u32::MAX, base: 0 })
            }
            _ => None,
        }
    }

    /// Record one hit of each voxel in `hits` (coordinates and index), all by one generator: the same as calling
    /// [`HitRecorder::record_at`] for each in order, with the narrow keys' test made once. (A dense array or a
    /// brick grid is better fed one voxel at a time: [`HitRecorder::dense_hits`], [`HitRecorder::brick_hits`].)
    #[inline]
    pub fn record_many(&mut self, hits: &[([u32; 3], u32)], level: u8, subpart: u8) {
        match &mut self.mode {
            Mode::Keys32 { raw, compact, scratch } if subpart == 0 && u32::from(level) < 1 << LEVEL_BITS => {
                self.hits += hits.len() as u64;
                for &(_, index) in hits {
                    raw.push(index << LEVEL_BITS | u32::from(level));
                }
                if raw.len() >= CHUNK {
                    flush32(raw, compact, scratch);
                }
            }
            _ => {
                for &(v, index) in hits {
                    self.record_at(v, index, level, subpart);
                }
            }
        }
    }

    /// Record one hit of each voxel in `hits` (coordinates, index, level, subpart); the order of hits never changes
    /// the result.
    pub fn record_points(&mut self, hits: &[([u32; 3], u32, u8, u8)]) {
        match &mut self.mode {
            Mode::Dense { array, touched } => {
                self.hits += hits.len() as u64;
                for &(v, index, level, _) in hits {
                    array.hit(v, index, level, touched);
                }
            }
            _ => {
                for &(v, index, level, subpart) in hits {
                    self.record_at(v, index, level, subpart);
                }
            }
        }
    }

    /// Record one hit of voxel `v` whose index is `index` (the dense array addresses by coordinates, the lists by
    /// index, so a caller that knows both saves the divisions).
    #[inline]
    pub fn record_at(&mut self, v: [u32; 3], index: u32, level: u8, subpart: u8) {
        self.hits += 1;
        match &mut self.mode {
            Mode::Dense { array, touched } => array.hit(v, index, level, touched),
            Mode::Keys32 { raw, compact, scratch } => {
                if subpart != 0 || u32::from(level) >= 1 << LEVEL_BITS {
                    self.widen();
                    self.hits -= 1;
                    return self.record_at(v, index, level, subpart);
                }
                raw.push(index << LEVEL_BITS | u32::from(level));
                if raw.len() >= CHUNK {
                    flush32(raw, compact, scratch);
                }
            }
            Mode::Bricks(grid) => {
                if subpart != 0 {
                    self.widen();
                    self.hits -= 1;
                    return self.record_at(v, index, level, subpart);
                }
                grid.hit(v, level);
            }
            Mode::Keys { raw, compact, scratch } => {
                // Level in the low byte (the shallowest sorts first), the index above it and the subpart on top,
                // so an unpartitioned index list needs only the passes its index bits take.
                raw.push(u64::from(subpart) << 40 | u64::from(index) << 8 | u64::from(level));
                if raw.len() >= CHUNK {
                    flush(raw, compact, scratch);
                }
            }
        }
    }

    /// Validation (§6 steps 5–7): compact the hits, turn hit counts into densities by `classes` density classes
    /// (branch voxels, level ≤ `branch_depth`, get full density), and build the store, its occupancy brick map and
    /// voxel box (from the hits, so a dense array is never scanned).
    pub fn finish(
        self,
        ty: StorageType,
        partitioned: bool,
        volume: &Hypervolume,
        classes: u8,
        branch_depth: u8,
    ) -> (VoxelStore, BrickMap, Option<VoxelBox>) {
        match self.mode {
            Mode::Dense { mut array, touched } => {
                let mut histogram = [0u64; 256];
                let offsets: Vec<usize> = touched.iter().map(|&i| array.offset(array.coords(i))).collect();
                for &o in &offsets {
                    histogram[array.cells[o][0] as usize] += 1;
                }
                let dc = DensityClasses::equalise(&histogram, classes);
                for &o in &offsets {
                    let c = &mut array.cells[o];
                    c[0] = if c[1] <= branch_depth { 255 } else { dc.density[c[0] as usize] };
                }
                array.count = touched.len();
                let (map, vbox) = BrickMap::from_indices(volume, touched.iter().copied());
                (VoxelStore::Dense(array), map, vbox)
            }
            Mode::Keys32 { mut raw, mut compact, mut scratch } => {
                flush32(&mut raw, &mut compact, &mut scratch);
                drop(raw);
                drop(scratch);
                let store = build_lists(&compact, ty, partitioned, volume, classes, branch_depth);
                let (map, vbox) = BrickMap::build(volume, &store);
                (store, map, vbox)
            }
            Mode::Bricks(grid) if !partitioned => {
                let (list, hits_of, map, vbox) = grid.into_list();
                let list = classify(list, &hits_of, classes, branch_depth);
                (VoxelStore::from_list(list, ty, volume), map, vbox)
            }
            Mode::Bricks(grid) => {
                let (compact, map, vbox) = grid.into_compact();
                let store = build_lists(&compact, ty, partitioned, volume, classes, branch_depth);
                (store, map, vbox)
            }
            Mode::Keys { mut raw, mut compact, mut scratch } => {
                flush(&mut raw, &mut compact, &mut scratch);
                drop(raw);
                drop(scratch);
                let store = build_lists(&compact, ty, partitioned, volume, classes, branch_depth);
                let (map, vbox) = BrickMap::build(volume, &store);
                (store, map, vbox)
            }
        }
    }
}

impl HitRecorder {
    /// Switch from narrow keys or bricks to wide keys (a hit of a subpart other than 0, or a narrow key's level
    /// of 32 or more).
    #[cold]
    fn widen(&mut self) {
        if let Mode::Keys32 { raw, compact, .. } = &mut self.mode {
            let raw: Vec<u64> =
                raw.iter().map(|&k| u64::from(k >> LEVEL_BITS) << 8 | u64::from(k & ((1 << LEVEL_BITS) - 1))).collect();
            self.mode = Mode::Keys { raw, compact: std::mem::take(compact), scratch: Vec::new() };
        } else if let Mode::Bricks(grid) = &mut self.mode {
            let (compact, _, _) = std::mem::replace(grid, BrickGrid::new([0; 3])).into_compact();
            self.mode = Mode::Keys { raw: Vec::with_capacity(1 << 16), compact, scratch: Vec::new() };
        }
    }
}

/// A dense recorder's array, borrowed to count hits one at a time ([`HitRecorder::dense_hits`]).
pub(crate) struct DenseHits<'a> {
    array: &'a mut DenseArray,
    touched: &'a mut Vec<u32>,
    hits: &'a mut u64,
}

impl DenseHits<'_> {
    /// Count one hit of voxel `v` (index `index`) at `level`, as [`HitRecorder::record_at`] does.
    #[inline(always)]
    pub(crate) fn hit(&mut self, v: [u32; 3], index: u32, level: u8) {
        *self.hits += 1;
        self.array.hit(v, index, level, self.touched);
    }
}

/// A brick-counting recorder's grid, borrowed to count one generator's hits one at a time
/// ([`HitRecorder::brick_hits`]).
pub(crate) struct BrickHits<'a> {
    grid: &'a mut BrickGrid,
    hits: &'a mut u64,
    /// The brick of the last hit and its slot's first cell: neighbouring voxels of a segment mostly share a
    /// brick, so its slot is looked up once per brick.
    last: u32,
    base: usize,
}

impl BrickHits<'_> {
    /// Count one hit of voxel `v` at `level`, as [`HitRecorder::record_at`] does.
    #[inline(always)]
    pub(crate) fn hit(&mut self, v: [u32; 3], level: u8) {
        *self.hits += 1;
        let b = self.grid.brick(v);
        if b != self.last {
            self.last = b;
            self.base = self.grid.slot(b) << 9;
        }
        self.grid.bump(self.base | BrickGrid::local(v), level);
    }
}

/// Hit counts (saturating at 255) and shallowest levels of subpart 0, in bricks of 8³ voxels allocated on first
/// touch: the same counts as sorting the raw hits, without the sort.
pub struct BrickGrid {
    resolution: [u32; 3],
    dims: [u32; 3],
    /// Per brick (`bx + dims_x · (by + dims_y · bz)`), its slot or `u32::MAX`.
    slots: Vec<u32>,
    /// `[hits, level]`, 512 per slot, `z << 6 | y << 3 | x` inside the brick (level 255 where not hit).
    cells: Vec<[u8; 2]>,
    /// The brick of each slot.
    bricks: Vec<u32>,
}

impl BrickGrid {
    fn new(resolution: [u32; 3]) -> BrickGrid {
        let dims = resolution.map(|r| r.div_ceil(1 << BRICK_SHIFT));
        let n = dims.iter().map(|&d| d as usize).product::<usize>();
        BrickGrid { resolution, dims, slots: vec![u32::MAX; n], cells: Vec::new(), bricks: Vec::new() }
    }

    #[inline]
    fn brick(&self, v: [u32; 3]) -> u32 {
        (v[0] >> 3) + self.dims[0] * ((v[1] >> 3) + self.dims[1] * (v[2] >> 3))
    }

    #[inline]
    fn local(v: [u32; 3]) -> usize {
        ((v[2] & 7) << 6 | (v[1] & 7) << 3 | (v[0] & 7)) as usize
    }

    /// The slot of brick `b`, allocated on first touch.
    #[inline]
    fn slot(&mut self, b: u32) -> usize {
        let mut s = self.slots[b as usize];
        if s == u32::MAX {
            s = self.bricks.len() as u32;
            self.slots[b as usize] = s;
            self.bricks.push(b);
            // Levels start at 255 so a hit is the same branch-free update whether or not it is the first.
            self.cells.resize(self.cells.len() + 512, [0, u8::MAX]);
        }
        s as usize
    }

    #[inline]
    fn hit(&mut self, v: [u32; 3], level: u8) {
        let o = self.slot(self.brick(v)) << 9 | Self::local(v);
        self.bump(o, level);
    }

    /// One more hit of cell `o` at `level`.
    #[inline]
    fn bump(&mut self, o: usize, level: u8) {
        let c = &mut self.cells[o];
        c[0] = c[0].saturating_add(1);
        c[1] = c[1].min(level);
    }

    /// The compact records in index order, the occupancy brick map and the voxel box.
    fn into_compact(self) -> (Vec<Compact>, BrickMap, Option<VoxelBox>) {
        let mut out = Vec::new();
        let (map, vbox) = self.visit(|index, hits, level| out.push(Compact { key: u64::from(index), hits, level }));
        (out, map, vbox)
    }

    /// The voxels as a list (densities still 1), their hit counts, the occupancy brick map and the voxel box.
    fn into_list(self) -> (VoxelList, Vec<u8>, BrickMap, Option<VoxelBox>) {
        let mut list = VoxelList::default();
        let mut hits_of = Vec::new();
        let (map, vbox) = self.visit(|index, hits, level| {
            list.indices.push(index);
            list.levels.push(level);
            hits_of.push(hits);
        });
        list.densities = vec![1; list.indices.len()];
        (list, hits_of, map, vbox)
    }

    /// Visit every hit voxel in index order (index, hits, level); returns the brick map and the voxel box.
    fn visit(&self, mut emit: impl FnMut(u32, u8, u8)) -> (BrickMap, Option<VoxelBox>) {
        let mut any = false;
        let [rx, ry, rz] = self.resolution;
        let [nx, ny, _] = self.dims;
        let mut map = BrickMap { dims: self.dims, bits: vec![0u64; (self.slots.len()).div_ceil(64)] };
        let mut order: Vec<u32> = (0..self.bricks.len() as u32).collect();
        order.sort_unstable_by_key(|&s| self.bricks[s as usize]);
        let (mut lo, mut hi) = ([u32::MAX; 3], [0u32; 3]);
        // Slabs of bricks with equal bz; inside one, rows of bricks with equal by (bricks in x order).
        let mut k = 0;
        while k < order.len() {
            let bz = self.bricks[order[k] as usize] / (nx * ny);
            let mut end = k;
            while end < order.len() && self.bricks[order[end] as usize] / (nx * ny) == bz {
                end += 1;
            }
            let slab = &order[k..end];
            for lz in 0..8 {
                let z = bz * 8 + lz;
                if z >= rz {
                    break;
                }
                let mut r = 0;
                while r < slab.len() {
                    let by = self.bricks[slab[r] as usize] / nx % ny;
                    let mut rend = r;
                    while rend < slab.len() && self.bricks[slab[rend] as usize] / nx % ny == by {
                        rend += 1;
                    }
                    for ly in 0..8 {
                        let y = by * 8 + ly;
                        if y >= ry {
                            break;
                        }
                        for &s in &slab[r..rend] {
                            let bx = self.bricks[s as usize] % nx;
                            let base = (s as usize) << 9 | (lz << 6 | ly << 3) as usize;
                            // Most rows of a touched brick are empty: test the row's 8 cells at once.
                            if self.cells[base..base + 8].iter().fold(0u8, |a, c| a | c[0]) == 0 {
                                continue;
                            }
                            for lx in 0..8 {
                                let x = bx * 8 + lx;
                                if x >= rx {
                                    break;
                                }
                                let [hits, level] = self.cells[base | lx as usize];
                                if hits != 0 {
                                    emit(x + rx * (y + ry * z), hits, level);
                                    any = true;
                                    for (a, c) in [x, y, z].into_iter().enumerate() {
                                        lo[a] = lo[a].min(c);
                                        hi[a] = hi[a].max(c);
                                    }
                                }
                            }
                        }
                    }
                    r = rend;
                }
            }
            k = end;
        }
        for &b in &self.bricks {
            map.bits[b as usize >> 6] |= 1 << (b & 63);
        }
        (map, any.then_some((lo, hi)))
    }
}

/// [`flush`] for narrow keys: the same compact records.
fn flush32(raw: &mut Vec<u32>, compact: &mut Vec<Compact>, scratch: &mut Vec<u32>) {
    if raw.is_empty() {
        return;
    }
    radix_sort32(raw, scratch);
    let mut runs: Vec<Compact> = Vec::with_capacity(raw.len() / 2);
    let mut k = 0;
    while k < raw.len() {
        let key = raw[k] >> LEVEL_BITS;
        let level = (raw[k] & ((1 << LEVEL_BITS) - 1)) as u8;
        let start = k;
        k += 1;
        while k < raw.len() && raw[k] >> LEVEL_BITS == key {
            k += 1;
        }
        runs.push(Compact { key: u64::from(key), hits: (k - start).min(255) as u8, level });
    }
    raw.clear();
    merge_runs(compact, runs);
}

/// LSD radix sort of 32-bit keys over their significant bits, in as few passes of at most 11 bits as they take.
pub fn radix_sort32(keys: &mut Vec<u32>, scratch: &mut Vec<u32>) {
    let n = keys.len();
    if n < 2 {
        return;
    }
    let all_or = keys.iter().fold(0u32, |a, &k| a | k);
    let bits = 32 - all_or.leading_zeros();
    if bits == 0 {
        return;
    }
    let passes = bits.div_ceil(11);
    let width = bits.div_ceil(passes);
    let buckets = 1usize << width;
    let mask = (buckets - 1) as u32;
    let mut counts = vec![0usize; buckets * passes as usize];
    for &k in keys.iter() {
        for p in 0..passes {
            counts[p as usize * buckets + ((k >> (p * width)) & mask) as usize] += 1;
        }
    }
    scratch.clear();
    scratch.resize(n, 0);
    for p in 0..passes {
        let count = &mut counts[p as usize * buckets..(p as usize + 1) * buckets];
        if count.contains(&n) {
            continue; // every key has the same digit here
        }
        let shift = p * width;
        let mut sum = 0;
        for c in count.iter_mut() {
            let t = *c;
            *c = sum;
            sum += t;
        }
        for &k in keys.iter() {
            let b = ((k >> shift) & mask) as usize;
            scratch[count[b]] = k;
            count[b] += 1;
        }
        std::mem::swap(keys, scratch);
    }
}

/// Sort the raw hits, count repeats and merge them into the compact list.
fn flush(raw: &mut Vec<u64>, compact: &mut Vec<Compact>, scratch: &mut Vec<u64>) {
    if raw.is_empty() {
        return;
    }
    radix_sort(raw, scratch);
    let mut runs: Vec<Compact> = Vec::new();
    let mut k = 0;
    while k < raw.len() {
        let key = raw[k] >> 8;
        let level = (raw[k] & 0xff) as u8;
        let mut n = 0usize;
        while k < raw.len() && raw[k] >> 8 == key {
            n += 1;
            k += 1;
        }
        runs.push(Compact { key, hits: n.min(255) as u8, level });
    }
    raw.clear();
    merge_runs(compact, runs);
}

/// Merge freshly counted runs (sorted by key) into the compact list.
fn merge_runs(compact: &mut Vec<Compact>, runs: Vec<Compact>) {
    if compact.is_empty() {
        *compact = runs;
        return;
    }
    let old = std::mem::take(compact);
    let mut out = Vec::with_capacity(old.len() + runs.len());
    let (mut a, mut b) = (0, 0);
    while a < old.len() || b < runs.len() {
        let take_a = b == runs.len() || (a < old.len() && old[a].key <= runs[b].key);
        let take_b = a == old.len() || (b < runs.len() && runs[b].key <= old[a].key);
        if take_a && take_b {
            let (x, y) = (old[a], runs[b]);
            out.push(Compact { key: x.key, hits: x.hits.saturating_add(y.hits), level: x.level.min(y.level) });
            a += 1;
            b += 1;
        } else if take_a {
            out.push(old[a]);
            a += 1;
        } else {
            out.push(runs[b]);
            b += 1;
        }
    }
    *compact = out;
}

/// LSD radix sort of 64-bit keys by 11-bit digits, skipping digits that are equal in every key. The histograms of
/// all digits are counted in one pass over the keys.
pub fn radix_sort(keys: &mut Vec<u64>, scratch: &mut Vec<u64>) {
    const BITS: u32 = 11;
    const BUCKETS: usize = 1 << BITS;
    const DIGITS: usize = 64_usize.div_ceil(BITS as usize);
    let n = keys.len();
    if n < 2 {
        return;
    }
    let all_or = keys.iter().fold(0u64, |a, &k| a | k);
    let all_and = keys.iter().fold(u64::MAX, |a, &k| a & k);
    let varying = all_or ^ all_and;
    let digits: Vec<usize> =
        (0..DIGITS).filter(|&d| varying & (((BUCKETS as u64) - 1) << (d as u32 * BITS)) != 0).collect();
    let mut counts = vec![[0usize; BUCKETS]; digits.len()];
    for &k in keys.iter() {
        for (c, &d) in counts.iter_mut().zip(&digits) {
            c[((k >> (d as u32 * BITS)) as usize) & (BUCKETS - 1)] += 1;
        }
    }
    scratch.clear();
    scratch.resize(n, 0);
    for (count, &d) in counts.iter_mut().zip(&digits) {
        let shift = d as u32 * BITS;
        let mut sum = 0;
        for c in count.iter_mut() {
            let t = *c;
            *c = sum;
            sum += t;
        }
        for &k in keys.iter() {
            let b = ((k >> shift) as usize) & (BUCKETS - 1);
            scratch[count[b]] = k;
            count[b] += 1;
        }
        std::mem::swap(keys, scratch);
    }
}

/// Densities from hit counts: equalised density classes, full density for branch levels (≤ `branch_depth`).
fn classify(mut list: VoxelList, hits_of: &[u8], classes: u8, branch_depth: u8) -> VoxelList {
    let mut histogram = [0u64; 256];
    for &h in hits_of {
        histogram[h as usize] += 1;
    }
    let dc = DensityClasses::equalise(&histogram, classes);
    for (d, (&h, &l)) in list.densities.iter_mut().zip(hits_of.iter().zip(&list.levels)) {
        *d = if l <= branch_depth { 255 } else { dc.density[h as usize] };
    }
    list
}

/// Build index lists (per part if `partitioned`) from compact records sorted by (subpart, index).
fn build_lists(
    compact: &[Compact],
    ty: StorageType,
    partitioned: bool,
    volume: &Hypervolume,
    classes: u8,
    branch_depth: u8,
) -> VoxelStore {
    // Combine subparts per voxel: total hits (saturating) and shallowest level. Unpartitioned records are already
    // in index order; partitioned ones are re-sorted by index first.
    let mut merged: Vec<u64>;
    let records: &mut dyn Iterator<Item = (u32, u8, u8)> = if partitioned {
        merged =
            compact.iter().map(|c| (c.key & 0xffff_ffff) << 16 | u64::from(c.level) << 8 | u64::from(c.hits)).collect();
        let mut scratch = Vec::new();
        radix_sort(&mut merged, &mut scratch);
        &mut merged.iter().map(|&k| ((k >> 16) as u32, (k & 0xff) as u8, (k >> 8 & 0xff) as u8))
    } else {
        &mut compact.iter().map(|c| (c.key as u32, c.hits, c.level))
    };
    let mut combined = VoxelList::default();
    let mut hits_of: Vec<u8> = Vec::new();
    for (index, hits, level) in records {
        if combined.indices.last() == Some(&index) {
            let h = hits_of.last_mut().expect("parallel to the list");
            *h = h.saturating_add(hits);
            let l = combined.levels.last_mut().expect("non-empty");
            *l = (*l).min(level);
        } else {
            hits_of.push(hits);
            combined.push(index, Voxel { density: 1, level });
        }
    }
    let combined = classify(combined, &hits_of, classes, branch_depth);
    if !partitioned || ty == StorageType::Dense {
        return VoxelStore::from_list(combined, ty, volume);
    }
    // One list per subpart: records of a subpart are contiguous and in index order.
    let mut parts: Vec<(u8, VoxelList)> = Vec::new();
    for rec in compact {
        let sub = (rec.key >> 32) as u8;
        let index = rec.key as u32;
        if parts.last().is_none_or(|p| p.0 != sub) {
            parts.push((sub, VoxelList::default()));
        }
        let density = combined.position(index).map_or(1, |p| combined.densities[p]);
        parts.last_mut().expect("pushed").1.push(index, Voxel { density, level: rec.level });
    }
    VoxelStore::Partitioned(Partitioned::from_parts(parts, ty, volume))
}
