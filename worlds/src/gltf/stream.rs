//! Streaming `.glb` export: the file laid out in a first pass over its meshes and written in a second, so that only
//! one item's meshes (one tree of a grove) are in memory at a time, however large the file.
//!
//! A GLB's JSON chunk comes before its data and holds every mesh's counts, bounds and buffer offsets, so no data can
//! be written before every mesh is known. [`lay_out`] asks for each item's meshes, keeps what the JSON says of them
//! (a [`GlbLayout`]) and drops them; [`GlbLayout::write`] asks for them again and writes the header, the JSON and
//! each mesh's data as it comes. The items must come out the same both times (amplification and meshing are
//! deterministic); a mesh whose counts or bounds differ from the first pass's is an error
//! ([`GlbStreamError::Changed`]), never a file whose JSON does not describe its data.
//!
//! Size: [`lay_out`] stops as soon as the data of the meshes made so far is over the limit, before asking for the
//! next item. With [`SizeCheck::Estimate`] it also refuses right after the first item when that item's data times
//! the number of items is more than [`ESTIMATE_MARGIN_PERCENT`] over the limit; closer than that it goes on and
//! counts exactly, as the trees of a grove differ (monopodial's seeds 1–100 give 44.5 to 52.3 MB of data, median
//! 47.9 MB; seed 1 gives 49.4 MB, so 89 of them, 4.27 GB, would be estimated at 4.40 GB, over 4 GiB).
//!
//! [`crate::gltf::glb`] is this code with every mesh given by reference: one writer, in memory or streamed.

use std::borrow::Cow;
use std::io::{self, Write};

use serde_json::{Map, Value, json};

use super::{
    ARRAY_BUFFER, CHUNK_BIN, CHUNK_JSON, ELEMENT_ARRAY_BUFFER, FLOAT, GlbError, MAGIC, MAX_GLB_BYTES, TRIANGLES,
    UNSIGNED_INT, VERSION, glb_len, total_len,
};
use crate::mesh::Mesh;

/// How far over the limit the first item's estimate must be for [`SizeCheck::Estimate`] to refuse at once, percent.
pub const ESTIMATE_MARGIN_PERCENT: u64 = 10;

/// One node of the file: a named mesh at a translation. A mesh without triangles is left out of the file.
#[derive(Clone, Debug)]
pub struct Node<'a> {
    /// The node's (and its mesh's) name.
    pub name: String,
    /// The mesh, made for this pass or borrowed.
    pub mesh: Cow<'a, Mesh>,
    /// Where the node stands; non-finite components are written as 0.
    pub translation: [f32; 3],
}

impl Node<'static> {
    /// A node that owns its mesh (made for this pass and dropped after it).
    pub fn owned(name: impl Into<String>, mesh: Mesh, translation: [f32; 3]) -> Node<'static> {
        Node { name: name.into(), mesh: Cow::Owned(mesh), translation }
    }
}

impl<'a> Node<'a> {
    /// A node that borrows its mesh.
    pub fn borrowed(name: impl Into<String>, mesh: &'a Mesh, translation: [f32; 3]) -> Node<'a> {
        Node { name: name.into(), mesh: Cow::Borrowed(mesh), translation }
    }
}

/// How [`lay_out`] checks the file's size against the limit.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SizeCheck {
    /// Make every item: refuse once the data made so far is over the limit, or when the whole file is.
    Exact,
    /// As [`SizeCheck::Exact`], and refuse right after the first item when the file estimated from it (its data
    /// times the number of items) is more than [`ESTIMATE_MARGIN_PERCENT`] over the limit.
    Estimate,
}

/// Why a streamed `.glb` was not laid out or written.
#[derive(Debug, thiserror::Error)]
pub enum GlbStreamError<E> {
    /// The file would be over the size limit, or is estimated to be ([`GlbError`]); found after making `made` of
    /// the `items` (nothing was written).
    #[error("after making {made} of {items} item(s): {error}")]
    TooLarge {
        /// Items made when the size was found over the limit.
        made: u64,
        /// Items asked for.
        items: u64,
        /// The size error.
        error: GlbError,
    },
    /// The meshes of item `item` (counted from 0) could not be made.
    #[error("item {item}: {error}")]
    Source {
        /// The item.
        item: u64,
        /// Why it could not be made.
        error: E,
    },
    /// The second pass did not give the meshes of the first.
    #[error(
        "item {item}: mesh `{node}` differs from the first pass (its counts or bounds changed, or it came or went): \
         the meshes must come out the same both times"
    )]
    Changed {
        /// The item.
        item: u64,
        /// The mesh that differs, or is missing.
        node: String,
    },
    /// The output refused the bytes.
    #[error("writing the .glb: {0}")]
    Write(#[source] io::Error),
}

/// What the JSON says of one mesh, and what the second pass checks its mesh against.
#[derive(Clone, Debug)]
struct Entry {
    item: u64,
    name: String,
    /// Positions, and the normals and colours written (at most one per position).
    vertices: usize,
    normals: usize,
    colors: usize,
    /// Indices written: three per whole triangle.
    indices: usize,
    lo: [f32; 3],
    hi: [f32; 3],
    translation: [f32; 3],
}

impl Entry {
    /// The entry of a node of `item`; `None` for a mesh without triangles (left out of the file).
    fn of(item: u64, node: &Node) -> Option<Entry> {
        let m: &Mesh = &node.mesh;
        if m.triangle_count() == 0 {
            return None;
        }
        let vertices = m.positions.len();
        let (lo, hi) = m.bounds();
        Some(Entry {
            item,
            name: node.name.clone(),
            vertices,
            normals: vertices.min(m.normals.len()),
            colors: vertices.min(m.colors.len()),
            indices: m.triangle_count() * 3,
            lo,
            hi,
            translation: node.translation,
        })
    }

    /// Its bytes in the BIN chunk: 12 per position, normal and colour, 4 per index.
    fn bin_bytes(&self) -> u64 {
        12 * (self.vertices as u64 + self.normals as u64 + self.colors as u64) + 4 * self.indices as u64
    }

    /// The same mesh, bit for bit in its bounds and translation.
    fn same(&self, other: &Entry) -> bool {
        let bits = |v: [f32; 3]| v.map(f32::to_bits);
        (self.item, &self.name, self.vertices, self.normals, self.colors, self.indices)
            == (other.item, &other.name, other.vertices, other.normals, other.colors, other.indices)
            && [self.lo, self.hi, self.translation].map(bits) == [other.lo, other.hi, other.translation].map(bits)
    }
}

/// A `.glb` laid out by [`lay_out`]: its JSON chunk, its length and what each mesh must be when it is written.
#[derive(Clone, Debug)]
pub struct GlbLayout {
    items: u64,
    entries: Vec<Entry>,
    /// The JSON chunk, padded with spaces to 4 bytes.
    json: Vec<u8>,
    bin: u64,
    total: u64,
}

/// Lay out a `.glb` of `items` items, each a list of nodes from `item(index)` (indices `0..items`, in order): ask
/// for each item once, keep what the JSON needs and drop the meshes. The file must fit in `limit` bytes (and
/// [`MAX_GLB_BYTES`]): past it, the error comes as soon as the data made so far is over, or — with
/// [`SizeCheck::Estimate`] — right after the first item when the estimate is (see the module docs).
pub fn lay_out<'a, E>(
    items: u64,
    limit: u64,
    check: SizeCheck,
    mut item: impl FnMut(u64) -> Result<Vec<Node<'a>>, E>,
) -> Result<GlbLayout, GlbStreamError<E>> {
    let limit = limit.min(MAX_GLB_BYTES);
    let too_large = |made, error| GlbStreamError::TooLarge { made, items, error };
    let (mut entries, mut bin) = (Vec::new(), 0u64);
    for i in 0..items {
        let nodes = item(i).map_err(|error| GlbStreamError::Source { item: i, error })?;
        for entry in nodes.iter().filter_map(|n| Entry::of(i, n)) {
            bin = bin.saturating_add(entry.bin_bytes());
            entries.push(entry);
        }
        drop(nodes);
        // At least the data so far, whatever the JSON adds.
        glb_len(0, bin, limit).map_err(|e| too_large(i + 1, e))?;
        if i == 0 && check == SizeCheck::Estimate {
            estimate(bin, items, limit).map_err(|e| too_large(1, e))?;
        }
    }
    GlbLayout::new(items, entries, limit).map_err(|e| too_large(items, e))
}

/// Refuse `items` items of `first` bytes of data each when they would be more than [`ESTIMATE_MARGIN_PERCENT`]
/// over `limit`.
fn estimate(first: u64, items: u64, limit: u64) -> Result<(), GlbError> {
    let bytes = total_len(0, first.saturating_mul(items));
    let allowed = limit.saturating_add(limit.saturating_mul(ESTIMATE_MARGIN_PERCENT) / 100);
    if bytes > allowed { Err(GlbError::Estimated { bytes, first, items, limit }) } else { Ok(()) }
}

impl GlbLayout {
    /// Build the JSON of `entries` and check the whole file's length against `limit`.
    fn new(items: u64, entries: Vec<Entry>, limit: u64) -> Result<GlbLayout, GlbError> {
        let mut bin: u64 = 0;
        let (mut nodes, mut gl_meshes, mut accessors, mut views) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        for (m, e) in entries.iter().enumerate() {
            let pos_view = push_view(&mut bin, &mut views, 12 * e.vertices as u64, ARRAY_BUFFER);
            let normal_view = push_view(&mut bin, &mut views, 12 * e.normals as u64, ARRAY_BUFFER);
            let color_view = push_view(&mut bin, &mut views, 12 * e.colors as u64, ARRAY_BUFFER);
            let index_view = push_view(&mut bin, &mut views, 4 * e.indices as u64, ELEMENT_ARRAY_BUFFER);

            // f32 → f64 is exact, so the JSON numbers are exactly the stored floats.
            let exact = |v: [f32; 3]| json!([f64::from(v[0]), f64::from(v[1]), f64::from(v[2])]);
            let first = accessors.len();
            let vertices = e.vertices;
            accessors.push(json!({
                "bufferView": pos_view, "componentType": FLOAT, "count": vertices, "type": "VEC3",
                "min": exact(e.lo), "max": exact(e.hi),
            }));
            accessors
                .push(json!({ "bufferView": normal_view, "componentType": FLOAT, "count": vertices, "type": "VEC3" }));
            accessors
                .push(json!({ "bufferView": color_view, "componentType": FLOAT, "count": vertices, "type": "VEC3" }));
            accessors.push(json!({
                "bufferView": index_view, "componentType": UNSIGNED_INT, "count": e.indices, "type": "SCALAR",
            }));

            gl_meshes.push(json!({
                "name": e.name,
                "primitives": [{
                    "attributes": { "POSITION": first, "NORMAL": first + 1, "COLOR_0": first + 2 },
                    "indices": first + 3,
                    "material": 0,
                    "mode": TRIANGLES,
                }],
            }));
            let t = e.translation.map(|x| if x.is_finite() { f64::from(x) } else { 0.0 });
            let mut node = Map::new();
            node.insert("name".into(), json!(e.name));
            node.insert("mesh".into(), json!(m));
            if t != [0.0; 3] {
                node.insert("translation".into(), json!(t));
            }
            nodes.push(Value::Object(node));
        }

        let mut scene = Map::new();
        scene.insert("name".into(), json!("canopy"));
        if !nodes.is_empty() {
            scene.insert("nodes".into(), json!((0..nodes.len()).collect::<Vec<_>>()));
        }
        let mut root = Map::new();
        root.insert("asset".into(), json!({ "version": "2.0", "generator": "canopy" }));
        root.insert("scene".into(), json!(0));
        root.insert("scenes".into(), json!([Value::Object(scene)]));
        if !nodes.is_empty() {
            root.insert("nodes".into(), Value::Array(nodes));
            root.insert("meshes".into(), Value::Array(gl_meshes));
            root.insert(
                "materials".into(),
                json!([{
                    "name": "canopy",
                    "doubleSided": true,
                    "pbrMetallicRoughness": {
                        "baseColorFactor": [1.0, 1.0, 1.0, 1.0],
                        "metallicFactor": 0.0,
                        "roughnessFactor": 1.0,
                    },
                }]),
            );
            root.insert("accessors".into(), Value::Array(accessors));
            root.insert("bufferViews".into(), Value::Array(views));
            root.insert("buffers".into(), json!([{ "byteLength": bin }]));
        }

        let mut json = serde_json::to_vec(&Value::Object(root)).unwrap_or_default();
        let total = glb_len(json.len() as u64, bin, limit)?;
        while !json.len().is_multiple_of(4) {
            json.push(b' ');
        }
        Ok(GlbLayout { items, entries, json, bin, total })
    }

    /// The file's length in bytes.
    pub fn bytes(&self) -> u64 {
        self.total
    }

    /// The nodes in the file (meshes with triangles).
    pub fn nodes(&self) -> usize {
        self.entries.len()
    }

    /// The triangles in the file.
    pub fn triangles(&self) -> u64 {
        self.entries.iter().map(|e| e.indices as u64 / 3).sum()
    }

    /// Write the file to `out`, asking `item` for the items again (the same meshes as for [`lay_out`]) and writing
    /// each mesh's data as it comes: the header and JSON, then item by item. A mesh that differs from the first
    /// pass's stops the writing with [`GlbStreamError::Changed`], the bytes so far written; write to a temporary
    /// file and keep it only on success.
    pub fn write<'a, E>(
        &self,
        out: &mut impl Write,
        mut item: impl FnMut(u64) -> Result<Vec<Node<'a>>, E>,
    ) -> Result<(), GlbStreamError<E>> {
        let io = GlbStreamError::Write;
        // `GlbLayout::new` bounds every length by `u32::MAX`.
        for word in [MAGIC, VERSION, self.total as u32, self.json.len() as u32, CHUNK_JSON] {
            out.write_all(&word.to_le_bytes()).map_err(io)?;
        }
        out.write_all(&self.json).map_err(io)?;
        if self.bin > 0 {
            out.write_all(&(self.bin as u32).to_le_bytes()).map_err(io)?;
            out.write_all(&CHUNK_BIN.to_le_bytes()).map_err(io)?;
        }
        let mut expected = self.entries.iter();
        let mut stage = Vec::with_capacity(STAGE);
        for i in 0..self.items {
            let nodes = item(i).map_err(|error| GlbStreamError::Source { item: i, error })?;
            for node in &nodes {
                let Some(entry) = Entry::of(i, node) else { continue };
                if !expected.next().is_some_and(|want| want.same(&entry)) {
                    return Err(GlbStreamError::Changed { item: i, node: entry.name });
                }
                write_data(out, &node.mesh, &entry, &mut stage).map_err(io)?;
            }
        }
        match expected.next() {
            Some(missing) => Err(GlbStreamError::Changed { item: missing.item, node: missing.name.clone() }),
            None => Ok(()),
        }
    }
}

/// Reserve `len` bytes of the buffer as a new buffer view at offset `bin`; returns the view's index.
fn push_view(bin: &mut u64, views: &mut Vec<Value>, len: u64, target: u32) -> usize {
    views.push(json!({ "buffer": 0, "byteOffset": *bin, "byteLength": len, "target": target }));
    // Everything is 4-byte data, so views stay 4-byte aligned without padding.
    *bin = bin.saturating_add(len);
    views.len() - 1
}

/// Bytes staged before each write (the data is converted to little-endian bytes a stage at a time).
const STAGE: usize = 1 << 16;

/// One mesh's data, in the order of its buffer views: positions, normals, colours, indices.
fn write_data(out: &mut impl Write, mesh: &Mesh, entry: &Entry, stage: &mut Vec<u8>) -> io::Result<()> {
    let floats = |out: &mut dyn Write, data: &[[f32; 3]], stage: &mut Vec<u8>| -> io::Result<()> {
        for chunk in data.chunks(STAGE / 12) {
            stage.clear();
            stage.extend(chunk.iter().flatten().flat_map(|x| x.to_le_bytes()));
            out.write_all(stage)?;
        }
        Ok(())
    };
    floats(out, &mesh.positions[..entry.vertices], stage)?;
    floats(out, &mesh.normals[..entry.normals], stage)?;
    floats(out, &mesh.colors[..entry.colors], stage)?;
    for chunk in mesh.indices[..entry.indices].chunks(STAGE / 4) {
        stage.clear();
        stage.extend(chunk.iter().flat_map(|i| i.to_le_bytes()));
        out.write_all(stage)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::amplify::{Budget, Instance, amplify};
    use crate::gltf::{glb, mesh_bin_bytes, parse_glb_header};
    use crate::mesh::{MeshOptions, mesh};

    /// A worm of `seed` at `detail`: a small, real tree.
    fn worm(seed: u64, detail: u8) -> Mesh {
        let g = crate::library::find("worm").expect("worm").load().expect("loads");
        let s = amplify(&g, &Instance { detail, ..Instance::new(seed) }, &Budget::default()).expect("amplifies");
        mesh(&s, &MeshOptions::for_detail(detail))
    }

    /// Item `i` of a test grove: a tree, an empty mesh (left out) and a coarser copy beside it.
    fn tree(i: u64) -> Vec<Node<'static>> {
        let at = [i as f32 * 4.0, 0.0, 0.0];
        vec![
            Node::owned(format!("worm-{i}"), worm(i, 0), at),
            Node::owned(format!("none-{i}"), Mesh::default(), at),
            Node::owned(format!("worm-{i}-lod"), worm(i, 3), [at[0], 0.0, 4.0]),
        ]
    }

    fn stream(items: u64, limit: u64, check: SizeCheck) -> Result<Vec<u8>, GlbStreamError<String>> {
        let layout = lay_out(items, limit, check, |i| Ok(tree(i)))?;
        let mut out = Vec::new();
        layout.write(&mut out, |i| Ok(tree(i)))?;
        assert_eq!(out.len() as u64, layout.bytes());
        Ok(out)
    }

    #[test]
    fn a_streamed_grove_is_the_in_memory_file_byte_for_byte() {
        let bytes = stream(5, MAX_GLB_BYTES, SizeCheck::Estimate).expect("fits");
        let all: Vec<Node> = (0..5).flat_map(tree).collect();
        let refs: Vec<(String, &Mesh, [f32; 3])> =
            all.iter().map(|n| (n.name.clone(), n.mesh.as_ref(), n.translation)).collect();
        assert_eq!(bytes, glb(&refs).expect("fits"));
        let (json, bin) = parse_glb_header(&bytes).expect("well formed");
        assert_eq!(json["nodes"].as_array().map(Vec::len), Some(10), "the empty meshes are left out");
        assert_eq!(json["nodes"][3]["name"], "worm-1-lod");
        assert_eq!(bin.len() as u64, all.iter().map(|n| mesh_bin_bytes(&n.mesh)).sum::<u64>());
        let layout = lay_out(5, MAX_GLB_BYTES, SizeCheck::Exact, |i| Ok::<_, String>(tree(i))).unwrap();
        assert_eq!((layout.bytes(), layout.nodes()), (bytes.len() as u64, 10));
        assert_eq!(layout.triangles(), all.iter().map(|n| n.mesh.triangle_count() as u64).sum::<u64>());
    }

    /// Lay out `items` copies of one worm under `limit`, counting the items made.
    fn count_made(items: u64, limit: u64, check: SizeCheck) -> (u64, Result<GlbLayout, GlbStreamError<String>>) {
        let m = worm(1, 0);
        let mut made = 0;
        let r = lay_out(items, limit, check, |i| {
            made += 1;
            Ok(vec![Node::borrowed(format!("w{i}"), &m, [0.0; 3])])
        });
        (made, r)
    }

    #[test]
    fn a_grove_estimated_over_the_limit_is_refused_after_its_first_item() {
        let per = mesh_bin_bytes(&worm(1, 0));
        // 100 trees against room for 50: refused once the first is made, with the estimate.
        let (made, r) = count_made(100, 50 * per, SizeCheck::Estimate);
        assert_eq!(made, 1, "only the first item is made");
        match r {
            Err(GlbStreamError::TooLarge {
                made: 1,
                items: 100,
                error: GlbError::Estimated { bytes, first, items, limit },
            }) => {
                assert_eq!((first, items, limit), (per, 100, 50 * per));
                assert_eq!(bytes, 12 + 8 + 8 + 100 * per);
            }
            other => panic!("expected the estimate to refuse, got {other:?}"),
        }
        // Counting exactly, it stops at the first item over the limit: 50 trees are 28 bytes too many.
        let (made, r) = count_made(100, 50 * per, SizeCheck::Exact);
        assert_eq!(made, 50);
        assert!(
            matches!(r, Err(GlbStreamError::TooLarge { made: 50, error: GlbError::TooLarge { bytes, .. }, .. }) if bytes == 50 * per + 28),
            "{r:?}"
        );
        let msg = count_made(100, 50 * per, SizeCheck::Estimate).1.unwrap_err().to_string();
        assert!(msg.contains("after making 1 of 100 item(s)") && msg.contains("more than 10% over the limit"), "{msg}");
    }

    #[test]
    fn an_estimate_within_the_margin_is_counted_exactly() {
        let per = mesh_bin_bytes(&worm(1, 0));
        // 100 trees estimated 5% over the limit: not refused at the first; the exact count stops at the 96th.
        let (made, r) = count_made(100, 100 * per * 100 / 105, SizeCheck::Estimate);
        assert_eq!(made, 96);
        assert!(matches!(r, Err(GlbStreamError::TooLarge { error: GlbError::TooLarge { .. }, .. })), "{r:?}");
        let (made, r) = count_made(100, 100 * per + 100_000, SizeCheck::Estimate);
        assert_eq!(made, 100);
        assert!(r.is_ok(), "{r:?}");
        // A first tree much larger than the rest: its estimate refuses a grove that fits; counting exactly does not.
        let (big, small) = (worm(1, 0), worm(1, 3));
        assert!(mesh_bin_bytes(&big) > 2 * mesh_bin_bytes(&small));
        let grove = |i: u64| Ok::<_, String>(vec![Node::borrowed("w", if i == 0 { &big } else { &small }, [0.0; 3])]);
        let fits = mesh_bin_bytes(&big) + 9 * mesh_bin_bytes(&small) + 10_000;
        assert!(matches!(lay_out(10, fits, SizeCheck::Estimate, grove), Err(GlbStreamError::TooLarge { made: 1, .. })));
        assert!(lay_out(10, fits, SizeCheck::Exact, grove).is_ok());
    }

    #[test]
    fn a_second_pass_that_differs_is_an_error() {
        let layout = lay_out(3, MAX_GLB_BYTES, SizeCheck::Exact, |i| Ok::<_, String>(tree(i))).unwrap();
        let write = |f: &dyn Fn(u64) -> Vec<Node<'static>>| layout.write(&mut Vec::new(), |i| Ok::<_, String>(f(i)));
        // The second item's first mesh a triangle short.
        let other = |i: u64| {
            let mut t = tree(i);
            if i == 1 {
                let mut m = t[0].mesh.clone().into_owned();
                m.indices.truncate(m.indices.len() - 3);
                t[0].mesh = Cow::Owned(m);
            }
            t
        };
        assert!(matches!(write(&other), Err(GlbStreamError::Changed { item: 1, ref node }) if node == "worm-1"));
        // A mesh gone, one more, one moved.
        let fewer = |i: u64| tree(i).into_iter().take(if i == 2 { 1 } else { 3 }).collect();
        assert!(matches!(write(&fewer), Err(GlbStreamError::Changed { item: 2, ref node }) if node == "worm-2-lod"));
        let more = |i: u64| {
            let mut t = tree(i);
            t.push(Node::owned("extra", worm(1, 3), [0.0; 3]));
            t
        };
        assert!(matches!(write(&more), Err(GlbStreamError::Changed { item: 0, ref node }) if node == "extra"));
        let moved = |i: u64| tree(i).into_iter().map(|n| Node { translation: [9.0; 3], ..n }).collect();
        assert!(matches!(write(&moved), Err(GlbStreamError::Changed { item: 0, .. })));
        assert!(write(&tree).is_ok());
    }

    /// Takes `left` bytes, then refuses.
    struct Full {
        left: usize,
    }

    impl Write for Full {
        fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
            if self.left == 0 {
                return Err(io::Error::other("the disk is full"));
            }
            let n = buf.len().min(self.left);
            self.left -= n;
            Ok(n)
        }
        fn flush(&mut self) -> io::Result<()> {
            Ok(())
        }
    }

    #[test]
    fn failures_of_the_meshes_or_the_output_are_reported() {
        let r =
            lay_out(5, MAX_GLB_BYTES, SizeCheck::Exact, |i| if i == 3 { Err("boom".to_string()) } else { Ok(tree(i)) });
        let e = r.unwrap_err();
        assert!(matches!(&e, GlbStreamError::Source { item: 3, error } if error == "boom"));
        assert_eq!(e.to_string(), "item 3: boom");
        let layout = lay_out(2, MAX_GLB_BYTES, SizeCheck::Exact, |i| Ok::<_, String>(tree(i))).unwrap();
        let e = layout.write(&mut Full { left: 1000 }, |i| Ok::<_, String>(tree(i))).unwrap_err();
        assert!(matches!(&e, GlbStreamError::Write(io) if io.to_string() == "the disk is full"), "{e}");
    }
}
