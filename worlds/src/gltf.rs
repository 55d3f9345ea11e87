//! glTF 2.0 binary export (`.glb`): one scene, one node per mesh, that the Khronos glTF validator accepts
//! without errors or warnings.
//!
//! Layout: a 12-byte header, a JSON chunk (padded with spaces to 4 bytes) and a BIN chunk (zero-padded; all
//! data is 4-byte floats and `u32` indices, so no padding is ever needed inside it). Each mesh has four buffer
//! views, one per accessor, in this order: POSITION (with the `min`/`max` the spec requires), NORMAL, COLOR_0
//! (all `FLOAT VEC3`, target `ARRAY_BUFFER`) and the indices (`UNSIGNED_INT SCALAR`, target
//! `ELEMENT_ARRAY_BUFFER`). All meshes share one material: white, metallic 0, roughness 1, double-sided because
//! leaves are single-sided geometry; the vertex colours carry the primitives' colours.
//!
//! The JSON is built with `serde_json` (sorted keys) and the binary data is little-endian, so the same meshes give
//! the same bytes everywhere.
//!
//! A GLB's lengths are `u32` (glTF 2.0 §4.4, "GLB file format specification"), so a file holds at most
//! [`MAX_GLB_BYTES`], 4 GiB − 1. [`glb`] computes the file's length before it writes a byte of the BIN chunk and
//! returns [`GlbError::TooLarge`] instead of a file whose header has wrapped around.
//!
//! The writer streams ([`stream`]): a first pass over the meshes lays the file out (the JSON needs every mesh's
//! counts and bounds before any data), a second writes it mesh by mesh, so a grove of any size is never in memory
//! at once. [`glb`] and [`glb_within`] are that writer over a slice of meshes, into memory.

use std::convert::Infallible;

use serde_json::Value;

use crate::mesh::Mesh;

pub mod stream;

pub use stream::{GlbLayout, GlbStreamError, Node, SizeCheck, lay_out};

/// `glTF` in little-endian.
const MAGIC: u32 = 0x4654_6C67;
/// The container version.
const VERSION: u32 = 2;
/// Chunk type `JSON`.
const CHUNK_JSON: u32 = 0x4E4F_534A;
/// Chunk type `BIN\0`.
const CHUNK_BIN: u32 = 0x004E_4942;
/// `bufferView.target` for vertex attributes.
const ARRAY_BUFFER: u32 = 34962;
/// `bufferView.target` for indices.
const ELEMENT_ARRAY_BUFFER: u32 = 34963;
/// `accessor.componentType` FLOAT.
const FLOAT: u32 = 5126;
/// `accessor.componentType` UNSIGNED_INT.
const UNSIGNED_INT: u32 = 5125;
/// `primitive.mode` TRIANGLES.
const TRIANGLES: u32 = 4;

/// The largest `.glb` there can be: the header's total length is a `u32`.
pub const MAX_GLB_BYTES: u64 = u32::MAX as u64;

/// Why [`glb`] writes no file.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum GlbError {
    /// The file would be longer than `limit` ([`MAX_GLB_BYTES`] at most: GLB lengths are `u32`).
    #[error(
        "the .glb would be at least {bytes} bytes, over the limit of {limit} bytes (a GLB file holds at most \
         4 GiB − 1 = {MAX_GLB_BYTES} bytes: its lengths are u32, glTF 2.0 §4.4); export fewer trees, coarser meshes \
         (a higher detail level) or the continuous/LOD mesh"
    )]
    TooLarge {
        /// The file's length (or a lower bound of it, from the meshes made so far).
        bytes: u64,
        /// The limit it exceeds.
        limit: u64,
    },
    /// `items` items like the first, whose mesh data is `first` bytes, would make a file of about `bytes` bytes:
    /// more than [`stream::ESTIMATE_MARGIN_PERCENT`] over `limit` ([`SizeCheck::Estimate`]).
    #[error(
        "the .glb would be about {bytes} bytes ({items} × the first's {first} bytes of mesh data), more than \
         {margin}% over the limit of {limit} bytes (a GLB file holds at most 4 GiB − 1 = {MAX_GLB_BYTES} bytes: its \
         lengths are u32, glTF 2.0 §4.4); export fewer trees, coarser meshes (a higher detail level) or the \
         continuous/LOD mesh",
        margin = stream::ESTIMATE_MARGIN_PERCENT
    )]
    Estimated {
        /// The estimated length.
        bytes: u64,
        /// The first item's bytes of mesh data.
        first: u64,
        /// The number of items.
        items: u64,
        /// The limit it exceeds.
        limit: u64,
    },
}

/// The bytes one mesh adds to the BIN chunk: positions, normals and colours (3 floats each) per vertex, three `u32`
/// indices per triangle; nothing for a mesh without triangles (left out of the file).
pub fn bin_bytes(vertices: u64, triangles: u64) -> u64 {
    if triangles == 0 { 0 } else { vertices.saturating_mul(36).saturating_add(triangles.saturating_mul(12)) }
}

/// [`bin_bytes`] of a mesh.
pub fn mesh_bin_bytes(mesh: &Mesh) -> u64 {
    bin_bytes(mesh.vertex_count() as u64, mesh.triangle_count() as u64)
}

/// The length of a GLB file with `json` bytes of JSON (before padding) and `bin` bytes of BIN data: the 12-byte
/// header, the JSON chunk padded to 4 bytes and, when there is data, the BIN chunk; an error when it is over
/// `limit` (capped at [`MAX_GLB_BYTES`]).
pub fn glb_len(json: u64, bin: u64, limit: u64) -> Result<u64, GlbError> {
    let bytes = total_len(json, bin);
    let limit = limit.min(MAX_GLB_BYTES);
    if bytes > limit { Err(GlbError::TooLarge { bytes, limit }) } else { Ok(bytes) }
}

/// The length of a GLB file with `json` bytes of JSON and `bin` bytes of BIN data, however long (saturating).
fn total_len(json: u64, bin: u64) -> u64 {
    let chunk = |len: u64| len.div_ceil(4).saturating_mul(4).saturating_add(8);
    12u64.saturating_add(chunk(json)).saturating_add(if bin == 0 { 0 } else { chunk(bin) })
}

/// Why bytes are not a well-formed GLB container (checked by [`parse_glb_header`]).
#[derive(Debug, thiserror::Error)]
pub enum GltfError {
    /// Fewer bytes than a header and a chunk header, or than a chunk claims.
    #[error("GLB truncated: {0}")]
    Truncated(&'static str),
    /// The first four bytes are not `glTF`.
    #[error("not a GLB file (magic {0:#010x})")]
    Magic(u32),
    /// The container version is not 2.
    #[error("GLB version {0}, expected 2")]
    Version(u32),
    /// The header's total length differs from the byte count.
    #[error("GLB header says {header} bytes, got {actual}")]
    Length {
        /// Length in the header.
        header: u32,
        /// Actual length.
        actual: usize,
    },
    /// A chunk has the wrong type for its place, or a length not a multiple of 4.
    #[error("bad GLB chunk {index}: type {kind:#010x}, length {length}")]
    Chunk {
        /// Chunk number, 0 for the JSON chunk.
        index: usize,
        /// Its type.
        kind: u32,
        /// Its length.
        length: u32,
    },
    /// Bytes follow the last chunk.
    #[error("{0} bytes after the last GLB chunk")]
    Trailing(usize),
    /// The JSON chunk does not parse.
    #[error("GLB JSON chunk: {0}")]
    Json(#[from] serde_json::Error),
}

/// Write a `.glb` with one scene holding one node per entry: `(name, mesh, translation)`. Each node has its own
/// mesh. Entries whose mesh has no triangles are left out; with none left, the file is still valid (a scene
/// without nodes, no buffer). Non-finite translation components are written as 0. Each mesh must be well formed, as
/// [`crate::mesh::mesh`] makes them: one normal and colour per position, finite values, colours in `0..=1`,
/// indices in range. A file longer than [`MAX_GLB_BYTES`] is an error, found before the BIN data is written.
pub fn glb(meshes: &[(String, &Mesh, [f32; 3])]) -> Result<Vec<u8>, GlbError> {
    glb_within(meshes, MAX_GLB_BYTES)
}

/// [`glb`] with a lower size limit: a file longer than `limit` bytes (or [`MAX_GLB_BYTES`]) is an error. The
/// streaming writer ([`stream`]) with every mesh given by reference, into memory.
pub fn glb_within(meshes: &[(String, &Mesh, [f32; 3])], limit: u64) -> Result<Vec<u8>, GlbError> {
    let item = |i: u64| -> Result<Vec<Node<'_>>, Infallible> {
        Ok(meshes
            .get(i as usize)
            .map(|(name, mesh, at)| Node::borrowed(name.as_str(), mesh, *at))
            .into_iter()
            .collect())
    };
    let layout = lay_out(meshes.len() as u64, limit, SizeCheck::Exact, item).map_err(in_memory)?;
    let mut out = Vec::with_capacity(layout.bytes() as usize);
    layout.write(&mut out, item).map_err(in_memory)?;
    debug_assert_eq!(out.len() as u64, layout.bytes());
    Ok(out)
}

/// The error of a GLB streamed into memory from a slice: only the size can be wrong.
fn in_memory(e: GlbStreamError<Infallible>) -> GlbError {
    match e {
        GlbStreamError::TooLarge { error, .. } => error,
        GlbStreamError::Source { error, .. } => match error {},
        // A `Vec<u8>` takes every write, and the same slice gives the same meshes twice.
        GlbStreamError::Write(e) => unreachable!("writing a .glb into memory failed: {e}"),
        GlbStreamError::Changed { node, .. } => unreachable!("mesh `{node}` of a slice changed between two reads"),
    }
}

/// Check a `.glb` container — magic, version, total length, a JSON chunk first and at most one BIN chunk after
/// it, chunk lengths that are multiples of 4 and fit — and return the parsed JSON and the BIN chunk's bytes
/// (empty when there is none).
pub fn parse_glb_header(bytes: &[u8]) -> Result<(Value, Vec<u8>), GltfError> {
    let word =
        |at: usize| -> Option<u32> { bytes.get(at..at + 4).map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]])) };
    let header = |at: usize| word(at).ok_or(GltfError::Truncated("header"));
    let magic = header(0)?;
    if magic != MAGIC {
        return Err(GltfError::Magic(magic));
    }
    let version = header(4)?;
    if version != VERSION {
        return Err(GltfError::Version(version));
    }
    let length = header(8)?;
    if length as usize != bytes.len() {
        return Err(GltfError::Length { header: length, actual: bytes.len() });
    }

    let mut at = 12;
    let mut chunks: Vec<&[u8]> = Vec::new();
    while at < bytes.len() {
        let index = chunks.len();
        let (Some(len), Some(kind)) = (word(at), word(at + 4)) else {
            return Err(GltfError::Truncated("chunk header"));
        };
        let expected = if index == 0 { CHUNK_JSON } else { CHUNK_BIN };
        if index > 1 {
            return Err(GltfError::Trailing(bytes.len() - at));
        }
        if kind != expected || len % 4 != 0 || (index == 0 && len == 0) {
            return Err(GltfError::Chunk { index, kind, length: len });
        }
        let data = bytes.get(at + 8..at + 8 + len as usize).ok_or(GltfError::Truncated("chunk data"))?;
        chunks.push(data);
        at += 8 + len as usize;
    }
    let Some(json_chunk) = chunks.first() else {
        return Err(GltfError::Truncated("no JSON chunk"));
    };
    let json = serde_json::from_slice(json_chunk)?;
    Ok((json, chunks.get(1).map(|b| b.to_vec()).unwrap_or_default()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::{MeshOptions, mesh};
    use crate::primitive::{Primitive, PrimitiveStream, Shape};
    use crate::transform::Transform;
    use canopy_protocol::LeafTopology;
    use serde_json::json;

    fn sample() -> PrimitiveStream {
        let mut s = PrimitiveStream::default();
        let p = |shape, transform| Primitive { shape, transform, color: [0.45, 0.3, 0.15] };
        s.primitives.push(p(Shape::Cylinder { radius: 0.1, height: 1.0 }, Transform::IDENTITY));
        s.primitives.push(p(Shape::Sphere { radius: 0.3 }, Transform::translation(0.0, 1.2, 0.0)));
        s.primitives.push(p(Shape::Box { size: [0.2, 0.1, 0.3] }, Transform::translation(0.5, 0.0, 0.0)));
        s.leaf_points.extend([[0.0, 0.0, 0.0], [0.1, 0.1, 0.0], [0.0, 0.3, 0.0], [-0.1, 0.1, 0.0]]);
        s.primitives.push(p(
            Shape::Leaf { topology: LeafTopology::Polygon, start: 0, end: 4 },
            Transform::translation(0.0, 1.0, 0.2),
        ));
        s
    }

    fn u32_at(b: &[u8], at: usize) -> u32 {
        u32::from_le_bytes([b[at], b[at + 1], b[at + 2], b[at + 3]])
    }

    #[test]
    fn header_and_chunk_lengths_are_consistent() {
        let m = mesh(&sample(), &MeshOptions::default());
        let bytes = glb(&[("tree".to_string(), &m, [1.0, 0.0, -2.0])]).unwrap();
        assert_eq!(&bytes[0..4], b"glTF");
        assert_eq!(u32_at(&bytes, 4), 2);
        assert_eq!(u32_at(&bytes, 8) as usize, bytes.len());
        let json_len = u32_at(&bytes, 12) as usize;
        assert_eq!(json_len % 4, 0);
        assert_eq!(&bytes[16..20], b"JSON");
        let bin_at = 20 + json_len;
        let bin_len = u32_at(&bytes, bin_at) as usize;
        assert_eq!(&bytes[bin_at + 4..bin_at + 8], b"BIN\0");
        assert_eq!(bin_len % 4, 0);
        assert_eq!(bin_at + 8 + bin_len, bytes.len());
        // Positions, normals and colours (3 floats each) plus the indices.
        assert_eq!(bin_len, m.vertex_count() * 36 + m.indices.len() * 4);
        // JSON padding is spaces.
        assert!(bytes[20..bin_at].iter().rev().take_while(|&&b| b != b'}').all(|&b| b == b' '));
    }

    #[test]
    fn json_round_trips_and_accessors_match_the_mesh() {
        let a = mesh(&sample(), &MeshOptions::default());
        let b = mesh(&sample(), &MeshOptions::for_detail(3));
        let empty = crate::mesh::Mesh::default();
        let bytes = glb(&[
            ("a".to_string(), &a, [0.0; 3]),
            ("empty".to_string(), &empty, [0.0; 3]),
            ("b".to_string(), &b, [3.0, 0.0, 0.0]),
        ])
        .unwrap();
        let (json, bin) = parse_glb_header(&bytes).expect("well-formed GLB");
        assert_eq!(json["asset"]["version"], "2.0");
        assert_eq!(json["asset"]["generator"], "canopy");
        assert_eq!(json["materials"][0]["doubleSided"], true);
        assert_eq!(json["buffers"][0]["byteLength"].as_u64(), Some(bin.len() as u64));
        let nodes = json["nodes"].as_array().unwrap();
        assert_eq!(nodes.len(), 2, "the empty mesh is skipped");
        assert_eq!(nodes[1]["name"], "b");
        assert_eq!(nodes[1]["translation"], json!([3.0, 0.0, 0.0]));
        assert_eq!(json["scenes"][0]["nodes"], json!([0, 1]));
        for (i, m) in [&a, &b].into_iter().enumerate() {
            let prim = &json["meshes"][i]["primitives"][0];
            let acc = |key: &str| &json["accessors"][prim["attributes"][key].as_u64().unwrap() as usize];
            for key in ["POSITION", "NORMAL", "COLOR_0"] {
                assert_eq!(acc(key)["count"].as_u64(), Some(m.vertex_count() as u64), "{key}");
                assert_eq!(acc(key)["type"], "VEC3");
            }
            let idx = &json["accessors"][prim["indices"].as_u64().unwrap() as usize];
            assert_eq!(idx["count"].as_u64(), Some(m.indices.len() as u64));
            assert_eq!(idx["componentType"], UNSIGNED_INT);
            let (lo, hi) = m.bounds();
            let pos = acc("POSITION");
            for k in 0..3 {
                assert_eq!(pos["min"][k].as_f64().unwrap() as f32, lo[k]);
                assert_eq!(pos["max"][k].as_f64().unwrap() as f32, hi[k]);
            }
            // The position data in BIN is the mesh's, bit for bit.
            let view = &json["bufferViews"][pos["bufferView"].as_u64().unwrap() as usize];
            assert_eq!(view["target"], ARRAY_BUFFER);
            let off = view["byteOffset"].as_u64().unwrap() as usize;
            assert_eq!(off % 4, 0);
            let first: Vec<f32> = (0..3).map(|k| f32::from_bits(u32_at(&bin, off + 4 * k))).collect();
            assert_eq!(first, m.positions[0]);
            let iview = &json["bufferViews"][idx["bufferView"].as_u64().unwrap() as usize];
            assert_eq!(iview["target"], ELEMENT_ARRAY_BUFFER);
        }
    }

    #[test]
    fn no_meshes_still_make_a_valid_container() {
        let empty = crate::mesh::Mesh::default();
        for bytes in [glb(&[]).unwrap(), glb(&[("e".to_string(), &empty, [0.0; 3])]).unwrap()] {
            let (json, bin) = parse_glb_header(&bytes).unwrap();
            assert!(bin.is_empty());
            assert!(json.get("buffers").is_none() && json.get("nodes").is_none());
            assert_eq!(json["scenes"].as_array().map(Vec::len), Some(1));
        }
    }

    #[test]
    fn export_is_deterministic() {
        let m = mesh(&sample(), &MeshOptions::default());
        let entry = [("tree".to_string(), &m, [0.5, 0.0, 0.5])];
        assert_eq!(glb(&entry).unwrap(), glb(&entry).unwrap());
    }

    #[test]
    fn the_length_is_known_before_writing_and_capped_at_4_gib() {
        // The grove of issue 12: 4,804,616,672 bytes, which a u32 header wrapped to 509,649,376.
        let err = glb_len(10_000, 4_804_606_000, MAX_GLB_BYTES).unwrap_err();
        assert_eq!(err, GlbError::TooLarge { bytes: 12 + 8 + 10_000 + 8 + 4_804_606_000, limit: MAX_GLB_BYTES });
        let msg = err.to_string();
        assert!(msg.contains("4294967295") && msg.contains("u32") && msg.contains("fewer trees"), "{msg}");
        // Exactly at the limit is fine, one 4-byte word more is not; a higher limit is capped at the GLB's.
        let fits = MAX_GLB_BYTES - 3 - 12 - 8 - 100 - 8;
        assert_eq!(fits % 4, 0);
        assert_eq!(glb_len(100, fits, u64::MAX), Ok(MAX_GLB_BYTES - 3));
        assert!(glb_len(100, fits + 4, u64::MAX).is_err());
        // Huge meshes: counts whose bytes overflow neither u32 nor u64 silently.
        assert_eq!(bin_bytes(120_000_000, 240_000_000), 120_000_000 * 36 + 240_000_000 * 12);
        assert!(glb_len(0, bin_bytes(120_000_000, 240_000_000), MAX_GLB_BYTES).is_err());
        assert_eq!(bin_bytes(u64::MAX, 1), u64::MAX);
        assert_eq!(bin_bytes(1_000, 0), 0, "a mesh without triangles is left out");
    }

    #[test]
    fn the_length_check_matches_the_bytes_written() {
        let m = mesh(&sample(), &MeshOptions::default());
        let entries = [("a".to_string(), &m, [0.0; 3]), ("b".to_string(), &m, [2.0, 0.0, 0.0])];
        let bytes = glb(&entries).unwrap();
        let (json, bin) = parse_glb_header(&bytes).unwrap();
        assert_eq!(bin.len() as u64, 2 * mesh_bin_bytes(&m));
        let json_len = serde_json::to_vec(&json).unwrap().len() as u64;
        assert_eq!(glb_len(json_len, bin.len() as u64, MAX_GLB_BYTES), Ok(bytes.len() as u64));
        // A limit one byte short refuses, and says by how much it is over.
        let short = bytes.len() as u64 - 1;
        assert_eq!(glb_within(&entries, short), Err(GlbError::TooLarge { bytes: bytes.len() as u64, limit: short }));
        assert_eq!(glb_within(&entries, bytes.len() as u64).unwrap(), bytes);
    }

    /// The bytes of a small grove, pinned: the writer's output is the format, so a change to it must be deliberate.
    /// (Recorded from the in-memory writer before the streaming one replaced its body.)
    #[test]
    fn the_bytes_of_a_small_grove_are_pinned() {
        let worm = crate::library::find("worm").expect("worm").load().expect("loads");
        let stream = crate::amplify::amplify(&worm, &crate::amplify::Instance::new(2), &Default::default()).unwrap();
        let (a, b) = (mesh(&sample(), &MeshOptions::default()), mesh(&sample(), &MeshOptions::for_detail(3)));
        let (w, empty) = (mesh(&stream, &MeshOptions::default()), crate::mesh::Mesh::default());
        let bytes = glb(&[
            ("a".to_string(), &a, [0.0; 3]),
            ("empty".to_string(), &empty, [1.0; 3]),
            ("b".to_string(), &b, [3.0, 0.0, 0.0]),
            ("worm-2".to_string(), &w, [1.5, 0.0, -2.25]),
        ])
        .unwrap();
        let mut h = crate::primitive::Fnv::new();
        h.bytes(&bytes);
        assert_eq!((bytes.len(), h.finish()), (27_048, 10_378_403_515_207_617_838));
    }

    #[test]
    fn parse_rejects_malformed_containers() {
        let m = mesh(&sample(), &MeshOptions::default());
        let good = glb(&[("tree".to_string(), &m, [0.0; 3])]).unwrap();
        assert!(matches!(parse_glb_header(&good[..8]), Err(GltfError::Truncated(_))));
        let mut bad = good.clone();
        bad[0] = b'x';
        assert!(matches!(parse_glb_header(&bad), Err(GltfError::Magic(_))));
        let mut bad = good.clone();
        bad[4] = 1;
        assert!(matches!(parse_glb_header(&bad), Err(GltfError::Version(1))));
        assert!(matches!(parse_glb_header(&good[..good.len() - 4]), Err(GltfError::Length { .. })));
        let mut bad = good.clone();
        bad[16] = b'j';
        assert!(matches!(parse_glb_header(&bad), Err(GltfError::Chunk { index: 0, .. })));
    }
}
