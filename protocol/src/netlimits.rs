//! Explicit limits on every size and count of the streaming protocol, checked before allocation and on decode.
//! (The species graph's own limits are in [`crate::limits`].)

/// Largest frame a client may send, in bytes (its messages are small: a hello, a have-list, a viewpoint).
pub const MAX_CLIENT_FRAME: usize = 1024;
/// Largest frame a server may send, in bytes: one encoded species plus its envelope.
pub const MAX_SERVER_FRAME: usize = crate::limits::MAX_SPECIES_BYTES + 1024;
/// Most records in one cell batch (4 bytes each: a batch fits about one QUIC packet).
pub const MAX_BATCH_RECORDS: usize = 256;
/// Most parameter overrides in one cell batch.
pub const MAX_BATCH_OVERRIDES: usize = 1024;
/// Most species in one world's table (species ids are a byte).
pub const MAX_SPECIES: usize = 256;
/// Longest client label in a hello, in bytes.
pub const MAX_CLIENT_NAME: usize = 64;
/// Longest world name, in bytes.
pub const MAX_WORLD_NAME: usize = 128;
/// Most terrain tiles per axis (the corner heights are `(tiles + 1)²` floats).
pub const MAX_TERRAIN_TILES: u32 = 64;
/// Deepest terrain tile recursion (`2^depth` grid squares per tile edge).
pub const MAX_TERRAIN_DEPTH: u32 = 10;
/// Deepest subdivision of a fractal terrain (`canopy_worlds::world::MAX_FRACTAL_DEPTH`).
pub const MAX_FRACTAL_DEPTH: u32 = 20;
/// Smallest fractal lattice spacing at full depth, metres (`tile / 2^depth`).
pub const MIN_FRACTAL_SPACING: f64 = 0.25;
/// Most control heights of a fractal terrain (4 bytes each on the wire).
pub const MAX_CONTROL_HEIGHTS: usize = 1 << 16;
/// The fractal dimension's range, `[2, 3)`.
pub const FRACTAL_DIMENSION: (f32, f32) = (2.0, 3.0);
/// Largest area-of-interest radius a server may offer, in metres.
pub const MAX_AOI_RADIUS: f32 = 4096.0;
/// Largest coordinate magnitude accepted in a viewpoint, in metres: past ±2^20 cells of 64 m (±6.7 · 10^7 m), the
/// coordinate range of a world. Far out an f32 viewpoint is good to a few metres, plenty for choosing 64 m cells;
/// the records themselves travel as a cell and steps within it, exact everywhere.
pub const MAX_COORDINATE: f32 = 1.0e8;
/// Largest speed accepted in a viewpoint, in metres per second.
pub const MAX_SPEED: f32 = 1.0e4;
/// Largest grid of cells a world may have per axis: 2^21, the coordinate range of ±2^20 cells (keeps cell
/// coordinates inside what instance ids name; AOI scans are bounded by the radius, not the grid).
pub const MAX_CELLS_PER_AXIS: i32 = 1 << 21;
/// Largest chunk of explicit geometry in one message, bytes (the bandwidth baselines; fits a server frame).
pub const MAX_GEOMETRY_CHUNK: usize = 64 * 1024;
/// Largest explicit-geometry blob (one mesh or one batch's transforms), bytes.
pub const MAX_GEOMETRY_BYTES: usize = 64 * 1024 * 1024;
/// Most `(slot, value)` pairs in one edit (a plant's parameters, a set's).
pub const MAX_EDIT_PARAMS: usize = 32;
/// Most entries (plants, removals, updates) in one cell delta; a larger change is sent as the whole cell.
pub const MAX_DELTA_ENTRIES: usize = 1024;
/// Most cells named in one resume message (a client frame is at most [`MAX_CLIENT_FRAME`] bytes).
pub const MAX_RESUME_PER_MESSAGE: usize = 64;
/// Most cells a reconnecting client may name in all its resume messages.
pub const MAX_RESUME_CELLS: usize = 4096;
/// Longest editor token in a hello, bytes.
pub const MAX_TOKEN_BYTES: usize = 64;
/// Longest reason in an edit result, bytes.
pub const MAX_EDIT_REASON: usize = 256;
/// Farthest a client may ask for the far field, metres (a far view's range).
pub const MAX_FAR_RANGE: f32 = 65_536.0;
/// Smallest screen-space error threshold a client may ask for, pixels (finer would ask for every leaf in range).
pub const MIN_FAR_ERROR_PX: f32 = 0.5;
/// Largest world function (its manifest) a server sends to clients that expand cells; a larger world is served
/// as records.
pub const MAX_FUNCTION_BYTES: usize = 128 * 1024;
