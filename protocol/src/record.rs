//! Compact instance records (seed 001 §4: "later instances can be specified by parameters only") and the cell
//! batches that carry them.
//!
//! A record is 4 bytes on the wire: the species id and the instance's position within its cell, 12 bits per axis on
//! the [`POSITION_STEPS`] grid. Everything else is implicit or derived: an instance is identified by its cell and
//! its index within the cell ([`InstanceId`]: the batch's cell, its `start` plus the record's index), the seed is
//! derived from the world seed and that id, the height comes from the terrain, and parameters travel only where they
//! differ from the species defaults, as [`ParamOverride`]s after the records. No number is global to the world, so
//! a world can be expanded cell by cell.

use serde::{Deserialize, Serialize};

use crate::netlimits;

/// Positions are snapped to `cell_size / POSITION_STEPS` per axis within their cell: 12 bits per axis.
pub const POSITION_STEPS: u32 = 4096;

/// A cell of the world's square grid on (x, z), named by its integer coordinates (cell `(i, j)` spans
/// `[i, i + 1) × [j, j + 1)` cell sizes).
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
pub struct CellCoord {
    /// Column along x.
    pub x: i32,
    /// Row along z.
    pub z: i32,
}

impl CellCoord {
    /// The cell at column `x`, row `z`.
    pub const fn new(x: i32, z: i32) -> CellCoord {
        CellCoord { x, z }
    }
}

/// An instance's identity: its cell and its index within the cell, packed into 64 bits. There is no global
/// numbering, so an unbounded world expanded lazily per cell names every instance without knowing the others.
///
/// Bit layout, most significant first:
///
/// | bits    | field                                                                   |
/// | ------- | ----------------------------------------------------------------------- |
/// | 63..40  | cell `x` + 2²³ (24 bits, offset binary: `x` in `CELL_MIN..=CELL_MAX`)   |
/// | 39..16  | cell `z` + 2²³ (24 bits, the same)                                       |
/// | 15..0   | index within the cell (16 bits; a cell holds at most 65,535 records)    |
///
/// Cells from −2²³ to 2²³ − 1 per axis can be named (more than ±2²⁰ cells, ±8.6 × 10⁹ m at 1 km cells). The offset
/// makes the numeric order of ids the order of `(cell, index)` ([`CellCoord`]'s order: x, then z). Every `u64` is
/// the id of some (cell, index). The instance seed is `child_key(world seed, id.0)`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
pub struct InstanceId(pub u64);

impl InstanceId {
    /// Lowest cell coordinate an id can name, per axis: −2²³.
    pub const CELL_MIN: i32 = -(1 << 23);
    /// Highest cell coordinate an id can name, per axis: 2²³ − 1.
    pub const CELL_MAX: i32 = (1 << 23) - 1;
    const AXIS_MASK: u64 = (1 << 24) - 1;

    /// The id of record `index` of `cell`; `None` for a cell outside `CELL_MIN..=CELL_MAX` on an axis.
    pub const fn new(cell: CellCoord, index: u16) -> Option<InstanceId> {
        if !InstanceId::names(cell) {
            return None;
        }
        let x = (cell.x as i64 - InstanceId::CELL_MIN as i64) as u64;
        let z = (cell.z as i64 - InstanceId::CELL_MIN as i64) as u64;
        Some(InstanceId((x << 40) | (z << 16) | index as u64))
    }

    /// Whether ids can name the instances of `cell` (both coordinates within `CELL_MIN..=CELL_MAX`).
    pub const fn names(cell: CellCoord) -> bool {
        cell.x >= InstanceId::CELL_MIN
            && cell.x <= InstanceId::CELL_MAX
            && cell.z >= InstanceId::CELL_MIN
            && cell.z <= InstanceId::CELL_MAX
    }

    /// The instance's cell.
    pub const fn cell(self) -> CellCoord {
        let x = ((self.0 >> 40) & InstanceId::AXIS_MASK) as i32 + InstanceId::CELL_MIN;
        let z = ((self.0 >> 16) & InstanceId::AXIS_MASK) as i32 + InstanceId::CELL_MIN;
        CellCoord { x, z }
    }

    /// The instance's index within its cell.
    pub const fn index(self) -> u16 {
        self.0 as u16
    }
}

/// One instance of a species in a cell: 4 bytes, the species id and the quantised position within the cell.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct InstanceRecord {
    /// Index into the world's species table ([`crate::messages::Welcome::species`]).
    pub species: u8,
    /// `qx` in the low 12 bits and `qz` in the high 12 bits, little-endian: position
    /// `cell_origin + q * cell_size / POSITION_STEPS` per axis.
    pub position: [u8; 3],
}

impl InstanceRecord {
    /// A record of `species` at grid steps `(qx, qz)` within its cell; both must be below [`POSITION_STEPS`].
    pub fn new(species: u8, qx: u16, qz: u16) -> InstanceRecord {
        debug_assert!(u32::from(qx) < POSITION_STEPS && u32::from(qz) < POSITION_STEPS);
        let packed = u32::from(qx & 0xfff) | (u32::from(qz & 0xfff) << 12);
        let b = packed.to_le_bytes();
        InstanceRecord { species, position: [b[0], b[1], b[2]] }
    }

    /// Grid step along x within the cell, `0..POSITION_STEPS`.
    pub fn qx(&self) -> u16 {
        (u32::from_le_bytes([self.position[0], self.position[1], self.position[2], 0]) & 0xfff) as u16
    }

    /// Grid step along z within the cell, `0..POSITION_STEPS`.
    pub fn qz(&self) -> u16 {
        (u32::from_le_bytes([self.position[0], self.position[1], self.position[2], 0]) >> 12) as u16
    }
}

/// The edge of one position step in a cell of `cell_size` metres.
pub fn position_step(cell_size: f32) -> f32 {
    cell_size / POSITION_STEPS as f32
}

/// Quantise a coordinate to its grid step within the cell starting at `origin`: the step at or below it, so a
/// position already on the grid comes back bit for bit from [`dequantize`]. Values outside the cell clamp to its
/// edge steps. In f64, so that positions on the grid are exact however far from the origin their cell lies (an
/// f32 world coordinate holds the grid only within ±4,096 cells); f32 coordinates convert exactly.
pub fn quantize(value: f64, origin: f64, cell_size: f32) -> u16 {
    let q = ((value - origin) / f64::from(position_step(cell_size))).floor();
    if q.is_nan() { 0 } else { q.clamp(0.0, f64::from(POSITION_STEPS - 1)) as u16 }
}

/// The coordinate of grid step `q` within the cell starting at `origin`: `origin + q · cell_size / POSITION_STEPS`.
pub fn dequantize(q: u16, origin: f32, cell_size: f32) -> f32 {
    origin + f32::from(q) * position_step(cell_size)
}

/// A parameter value that differs from its species default, for one record: how stores and clients hold them.
/// On the wire they travel as [`ParamColumn`]s.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ParamOverride {
    /// Index of the record (within the batch, or within the cell where a store or client holds it).
    pub record: u16,
    /// The species' parameter slot.
    pub slot: u16,
    /// The value (finite).
    pub value: f32,
}

/// A float on the wire as the varint of its bits reversed: values with short mantissas — the usual parameter
/// values, `12.5`, `0.25`, `18` — take 1 to 3 bytes instead of 4; any other value takes at most 5. Lossless.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PackedF32(pub f32);

impl Serialize for PackedF32 {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_u32(self.0.to_bits().reverse_bits())
    }
}

impl<'de> Deserialize<'de> for PackedF32 {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<PackedF32, D::Error> {
        u32::deserialize(d).map(|v| PackedF32(f32::from_bits(v.reverse_bits())))
    }
}

/// The values one parameter slot takes in a batch, for the records that override it: a bitmap over the batch's
/// records (bit `i % 8` of byte `i / 8` for record `i`) and one value per set bit, in record order. A batch where
/// half the trees override `height` pays one bit per record and about two bytes per value.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ParamColumn {
    /// The species' parameter slot.
    pub slot: u16,
    /// Which records override it: `ceil(records / 8)` bytes, unused high bits zero.
    pub present: Vec<u8>,
    /// The values, one per set bit.
    pub values: Vec<PackedF32>,
}

/// A run of consecutive records of one cell. A cell's records are sent in one or more batches; all batches of one
/// grant travel on one ordered stream, followed by the grant's [`crate::messages::Release`] if the cell leaves the
/// area of interest, so a client never sees a batch after its grant's release.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CellBatch {
    /// The cell.
    pub cell: CellCoord,
    /// Which grant of the cell this batch belongs to: the server numbers grants per session, increasing, so a
    /// client that holds an older grant of the cell knows the older one was released.
    pub grant: u32,
    /// How many records the whole cell has; 0 for an empty cell (a batch with no records says so).
    pub total: u16,
    /// Index within the cell of `records[0]`.
    pub start: u16,
    /// The records, consecutive from `start`.
    pub records: Vec<InstanceRecord>,
    /// Parameters that differ from the species defaults, one column per slot, slots increasing.
    pub params: Vec<ParamColumn>,
    /// The cell's version these records belong to (0: the world function alone; every edit adds one,
    /// [`crate::edit`]). Every batch of a grant carries the same.
    pub version: u32,
    /// Records felled by edits: a bitmap over the batch's records like a parameter column's, or empty when none
    /// is. A felled record still takes its index (and 4 bytes); the client skips it.
    pub felled: Vec<u8>,
}

/// Why a cell batch is not acceptable.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum BatchError {
    /// More records than [`netlimits::MAX_BATCH_RECORDS`].
    #[error("batch of {0} records (allowed {max})", max = netlimits::MAX_BATCH_RECORDS)]
    TooManyRecords(usize),
    /// More parameter values or columns than [`netlimits::MAX_BATCH_OVERRIDES`].
    #[error("batch of {0} parameter values (allowed {max})", max = netlimits::MAX_BATCH_OVERRIDES)]
    TooManyOverrides(usize),
    /// The records run past the cell's total.
    #[error("records {start}..{end} outside the cell's {total}")]
    Range {
        /// First index.
        start: u32,
        /// One past the last index.
        end: u32,
        /// The cell's record count.
        total: u16,
    },
    /// The cell lies outside the cells an [`InstanceId`] can name.
    #[error("cell {0:?} outside the cells instance ids can name")]
    Cell(CellCoord),
    /// An empty batch of a non-empty cell, which carries nothing.
    #[error("empty batch of a cell with {0} records")]
    Empty(u16),
    /// A parameter column's slot repeats or is out of order, its bitmap does not fit the records, its values do
    /// not match the bitmap, or a value is not finite.
    #[error("parameter column {0} is malformed")]
    Column(usize),
    /// The felled bitmap does not fit the records.
    #[error("felled bitmap does not fit the batch")]
    Felled,
}

impl CellBatch {
    /// A batch carrying `overrides` (`record` = index within this batch, sorted by `(record, slot)`) as columns.
    pub fn new(
        cell: CellCoord,
        grant: u32,
        total: u16,
        start: u16,
        records: Vec<InstanceRecord>,
        overrides: &[ParamOverride],
    ) -> CellBatch {
        let mut slots: Vec<u16> = overrides.iter().map(|o| o.slot).collect();
        slots.sort_unstable();
        slots.dedup();
        let bytes = records.len().div_ceil(8);
        let params = slots
            .into_iter()
            .map(|slot| {
                let mut present = vec![0u8; bytes];
                let mut values = Vec::new();
                for o in overrides.iter().filter(|o| o.slot == slot) {
                    present[usize::from(o.record) / 8] |= 1 << (o.record % 8);
                    values.push(PackedF32(o.value));
                }
                ParamColumn { slot, present, values }
            })
            .collect();
        CellBatch { cell, grant, total, start, records, params, version: 0, felled: Vec::new() }
    }

    /// The batch at cell version `version`, with the records at these indices (within the batch, increasing)
    /// felled.
    pub fn at_version(mut self, version: u32, felled: impl IntoIterator<Item = u16>) -> CellBatch {
        self.version = version;
        let mut bits = vec![0u8; self.records.len().div_ceil(8)];
        let mut any = false;
        for i in felled {
            if let Some(b) = bits.get_mut(usize::from(i) / 8) {
                *b |= 1 << (i % 8);
                any = true;
            }
        }
        self.felled = if any { bits } else { Vec::new() };
        self
    }

    /// Whether `records[i]` was felled.
    pub fn is_felled(&self, i: usize) -> bool {
        self.felled.get(i / 8).is_some_and(|b| b & (1 << (i % 8)) != 0)
    }

    /// Check counts, ranges and the parameter columns (decoders call this).
    pub fn validate(&self) -> Result<(), BatchError> {
        let n = self.records.len();
        if n > netlimits::MAX_BATCH_RECORDS {
            return Err(BatchError::TooManyRecords(n));
        }
        let values: usize = self.params.iter().map(|c| c.values.len()).sum();
        if self.params.len() > netlimits::MAX_BATCH_OVERRIDES || values > netlimits::MAX_BATCH_OVERRIDES {
            return Err(BatchError::TooManyOverrides(values.max(self.params.len())));
        }
        let start = u32::from(self.start);
        let end = start + n as u32;
        if end > u32::from(self.total) {
            return Err(BatchError::Range { start, end, total: self.total });
        }
        if !InstanceId::names(self.cell) {
            return Err(BatchError::Cell(self.cell));
        }
        if n == 0 && self.total != 0 {
            return Err(BatchError::Empty(self.total));
        }
        let fits = |bits: &[u8]| {
            bits.len() == n.div_ceil(8) && (n.is_multiple_of(8) || bits.last().is_none_or(|&b| b >> (n % 8) == 0))
        };
        if !self.felled.is_empty() && !fits(&self.felled) {
            return Err(BatchError::Felled);
        }
        for (i, c) in self.params.iter().enumerate() {
            let ordered = i == 0 || self.params[i - 1].slot < c.slot;
            let fits = fits(&c.present);
            let count: usize = c.present.iter().map(|b| b.count_ones() as usize).sum();
            if !ordered || !fits || count != c.values.len() || count == 0 || !c.values.iter().all(|v| v.0.is_finite()) {
                return Err(BatchError::Column(i));
            }
        }
        Ok(())
    }

    /// The instance id of `records[i]`: `(cell, start + i)`. The batch must be valid ([`CellBatch::validate`]: its
    /// cell can be named, `start + i` is below `total`); panics otherwise.
    pub fn id(&self, i: usize) -> InstanceId {
        let index = u16::try_from(usize::from(self.start) + i).expect("a record index within the cell");
        InstanceId::new(self.cell, index).expect("a validated batch's cell can be named")
    }

    /// The parameter overrides as `(record within the batch, slot, value)`, sorted by `(record, slot)`.
    pub fn overrides(&self) -> Vec<ParamOverride> {
        let mut out = Vec::with_capacity(self.params.iter().map(|c| c.values.len()).sum());
        for c in &self.params {
            let mut values = c.values.iter();
            for (byte, &bits) in c.present.iter().enumerate() {
                for bit in 0..8 {
                    if bits & (1 << bit) != 0
                        && let Some(v) = values.next()
                    {
                        out.push(ParamOverride { record: (byte * 8 + bit) as u16, slot: c.slot, value: v.0 });
                    }
                }
            }
        }
        out.sort_by_key(|o| (o.record, o.slot));
        out
    }
}
