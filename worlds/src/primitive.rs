//! The primitive stream: what traversal of a species graph emits, one entry per primitive node visited.

use canopy_protocol::LeafTopology;

use crate::nearfield::TrunkBase;
use crate::transform::Transform;

/// The shape and size of one primitive, in its local frame (axis +Y, see [`canopy_protocol::Node`]).
#[derive(Clone, Debug, PartialEq)]
pub enum Shape {
    /// A cone or frustum on the origin along +Y.
    Cone {
        /// Radius at y = 0.
        bottom: f32,
        /// Radius at the top.
        top: f32,
        /// Height.
        height: f32,
    },
    /// A cylinder on the origin along +Y.
    Cylinder {
        /// Radius.
        radius: f32,
        /// Height.
        height: f32,
    },
    /// A sphere centred on the origin.
    Sphere {
        /// Radius.
        radius: f32,
    },
    /// A box centred on the origin.
    Box {
        /// Edge lengths.
        size: [f32; 3],
    },
    /// A leaf polygon or strip; its local points are `stream.leaf_points[start..end]`.
    Leaf {
        /// Polygon or strip.
        topology: LeafTopology,
        /// First point in [`PrimitiveStream::leaf_points`].
        start: u32,
        /// One past the last point.
        end: u32,
    },
    /// A trunk–root junction on the origin along +Y (seed 002; see [`crate::nearfield::trunkbase`]).
    TrunkBase(TrunkBase),
}

/// The kinds of primitive, for counting.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum PrimitiveKind {
    /// Cone or frustum.
    Cone,
    /// Cylinder.
    Cylinder,
    /// Sphere.
    Sphere,
    /// Box.
    Box,
    /// Leaf polygon or strip.
    Leaf,
}

impl PrimitiveKind {
    /// All kinds, in display order.
    pub const ALL: [PrimitiveKind; 5] =
        [PrimitiveKind::Cone, PrimitiveKind::Cylinder, PrimitiveKind::Sphere, PrimitiveKind::Box, PrimitiveKind::Leaf];

    /// Lowercase name.
    pub fn name(self) -> &'static str {
        match self {
            PrimitiveKind::Cone => "cone",
            PrimitiveKind::Cylinder => "cylinder",
            PrimitiveKind::Sphere => "sphere",
            PrimitiveKind::Box => "box",
            PrimitiveKind::Leaf => "leaf",
        }
    }
}

impl Shape {
    /// The size values of the shape in declaration order (cone: bottom, top, height; cylinder: radius, height;
    /// sphere: radius; box: x, y, z; leaf: none — its points live in the stream; trunk base: its eleven parameters
    /// in [`TrunkBase`] field order): the first `n` of the array.
    pub fn sizes(&self) -> ([f32; Shape::MAX_SIZES], usize) {
        let mut a = [0.0; Shape::MAX_SIZES];
        let n = match self {
            Shape::Cone { bottom, top, height } => put(&mut a, &[*bottom, *top, *height]),
            Shape::Cylinder { radius, height } => put(&mut a, &[*radius, *height]),
            Shape::Sphere { radius } => put(&mut a, &[*radius]),
            Shape::Box { size } => put(&mut a, size),
            Shape::Leaf { .. } => 0,
            Shape::TrunkBase(b) => put(&mut a, &b.to_array()),
        };
        (a, n)
    }

    /// Most size values of any shape (the trunk base's parameters).
    pub const MAX_SIZES: usize = TrunkBase::LEN;

    /// The primitive's kind. A trunk base counts as a cone: a frustum from its base radius to its top radius.
    pub fn kind(&self) -> PrimitiveKind {
        match self {
            Shape::Cone { .. } | Shape::TrunkBase(_) => PrimitiveKind::Cone,
            Shape::Cylinder { .. } => PrimitiveKind::Cylinder,
            Shape::Sphere { .. } => PrimitiveKind::Sphere,
            Shape::Box { .. } => PrimitiveKind::Box,
            Shape::Leaf { .. } => PrimitiveKind::Leaf,
        }
    }
}

/// One emitted primitive: shape, world transform (species space) and material colour.
#[derive(Clone, Debug, PartialEq)]
pub struct Primitive {
    /// Shape and local size.
    pub shape: Shape,
    /// Accumulated transform at the primitive node.
    pub transform: Transform,
    /// Linear RGB colour of the current material.
    pub color: [f32; 3],
}

/// Everything one traversal emitted, in traversal order (depth first, left to right).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PrimitiveStream {
    /// The primitives.
    pub primitives: Vec<Primitive>,
    /// Local points of all leaves, referenced by [`Shape::Leaf`].
    pub leaf_points: Vec<[f32; 3]>,
}

impl PrimitiveStream {
    /// Number of primitives of each kind, in [`PrimitiveKind::ALL`] order.
    pub fn counts(&self) -> [usize; 5] {
        let mut c = [0usize; 5];
        for p in &self.primitives {
            c[p.shape.kind() as usize] += 1;
        }
        c
    }

    /// The local points of a leaf primitive (empty for other shapes).
    pub fn leaf(&self, p: &Primitive) -> &[[f32; 3]] {
        match p.shape {
            Shape::Leaf { start, end, .. } => &self.leaf_points[start as usize..end as usize],
            _ => &[],
        }
    }

    /// The points bounding a primitive in its local frame: the 8 corners of its box (a trunk base as the frustum
    /// that holds its flares, `bottom · max(spread, 1)` to `top`), or a leaf's own points. The voxeliser and the
    /// renderer's bounds both take them.
    pub fn local_bounds(&self, p: &Primitive) -> Vec<[f32; 3]> {
        let corners = |lo: [f32; 3], hi: [f32; 3]| -> Vec<[f32; 3]> {
            (0..8)
                .map(|c| {
                    [
                        if c & 1 == 0 { lo[0] } else { hi[0] },
                        if c & 2 == 0 { lo[1] } else { hi[1] },
                        if c & 4 == 0 { lo[2] } else { hi[2] },
                    ]
                })
                .collect()
        };
        match &p.shape {
            Shape::Cone { bottom, top, height } => {
                let r = bottom.max(*top);
                corners([-r, 0.0, -r], [r, *height, r])
            }
            Shape::TrunkBase(b) => {
                let (bottom, top, height) = b.bounding_cone();
                let r = bottom.max(top);
                corners([-r, 0.0, -r], [r, height, r])
            }
            Shape::Cylinder { radius, height } => corners([-radius, 0.0, -radius], [*radius, *height, *radius]),
            Shape::Sphere { radius } => corners([-radius; 3], [*radius; 3]),
            Shape::Box { size } => corners(size.map(|s| -0.5 * s), size.map(|s| 0.5 * s)),
            Shape::Leaf { .. } => self.leaf(p).to_vec(),
        }
    }

    /// The box holding every primitive's [`Self::local_bounds`] in the stream's frame (`min > max` when empty).
    pub fn bounds(&self) -> ([f32; 3], [f32; 3]) {
        let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
        for p in &self.primitives {
            for c in self.local_bounds(p) {
                let w = p.transform.point(c);
                for i in 0..3 {
                    lo[i] = lo[i].min(w[i]);
                    hi[i] = hi[i].max(w[i]);
                }
            }
        }
        (lo, hi)
    }

    /// A stable 64-bit FNV-1a hash over the bit patterns of everything in the stream, for golden tests.
    pub fn hash(&self) -> u64 {
        let mut h = Fnv::new();
        for p in &self.primitives {
            h.u32(p.shape.kind() as u32);
            let (sizes, n) = p.shape.sizes();
            h.f32s(&sizes[..n]);
            if let Shape::Leaf { topology, .. } = p.shape {
                h.u32(topology as u32);
                for q in self.leaf(p) {
                    h.f32s(q);
                }
            }
            h.f32s(&p.transform.m);
            h.f32s(&p.color);
        }
        h.finish()
    }
}

/// 64-bit FNV-1a, for golden hashes of bit patterns (stable across platforms and Rust versions).
#[derive(Clone, Debug)]
pub struct Fnv(u64);

impl Fnv {
    /// A fresh hasher.
    pub fn new() -> Fnv {
        Fnv(0xcbf2_9ce4_8422_2325)
    }
    /// Hash bytes.
    pub fn bytes(&mut self, b: &[u8]) {
        for &x in b {
            self.0 ^= u64::from(x);
            self.0 = self.0.wrapping_mul(0x0000_0100_0000_01b3);
        }
    }
    /// Hash a u32, little-endian.
    pub fn u32(&mut self, v: u32) {
        self.bytes(&v.to_le_bytes());
    }
    /// Hash the bit patterns of floats.
    pub fn f32s(&mut self, v: &[f32]) {
        for x in v {
            self.u32(x.to_bits());
        }
    }
    /// The hash.
    pub fn finish(&self) -> u64 {
        self.0
    }
}

impl Default for Fnv {
    fn default() -> Self {
        Fnv::new()
    }
}

/// Copy `v` to the front of `a`; its length.
fn put(a: &mut [f32; Shape::MAX_SIZES], v: &[f32]) -> usize {
    a[..v.len()].copy_from_slice(v);
    v.len()
}
