//! Near-field geometry for close-up trees, after seeds 002 and 004: trunk–root junctions built from hypocycloids
//! and generator ellipses, double bark, T/Y/I branch junctions, and one continuous triangle mesh of the whole
//! branching structure with junctions refined by intervals, decimated into a LOD chain.
//!
//! Everything here is pure and deterministic like amplification: plain `f64`/`f32` arithmetic in a fixed order,
//! `libm` for transcendental functions, randomness only from the crate's ChaCha8 ([`crate::rng`]) with explicit
//! bit→float formulas, and ordered containers wherever order reaches the output. The one exception is the LOD
//! chain (`lod`, behind the `meshopt` feature), which calls meshoptimizer's C++ simplifier: deterministic on one
//! platform, not pinned bit for bit across platforms.
//!
//! - [`curves`]: hypocycloids (deltoid, astroid), ellipses, generator ellipse envelopes, roses.
//! - [`trunkbase`]: the trunk–root junction primitive ([`crate::primitive::Shape::TrunkBase`]).
//! - [`skeleton`]: the branching structure (seed 004's node hierarchy) recovered from a primitive stream.
//! - [`contour`]: contours, stitching two contours, one contour to many (the crotch), merged ellipse sections.
//! - [`continuous`]: the continuous mesh, direct or refined by intervals.
//! - [`junction`]: seed 002's per-branch junctions (T and Y with sinusoidal embedded bases, I continuations,
//!   a spherical cap on Y).
//! - [`bark`]: the double bark's chiselled outer layer.
//! - [`raster`]: a small software rasteriser for close-up renders.
//! - [`options`]: the species-level options (`nearfield(...)` in species files).
//! - [`topology`]: welding coincident vertices and counting bodies, boundary and non-manifold edges.

pub mod bark;
pub mod continuous;
pub mod contour;
pub mod curves;
pub mod junction;
#[cfg(feature = "meshopt")]
pub mod lod;
pub mod options;
pub mod raster;
pub mod skeleton;
pub mod topology;
pub mod trunkbase;

pub use options::NearFieldOptions;
pub use trunkbase::TrunkBase;

use crate::mesh::Mesh;

/// Why near-field geometry could not be built.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum NearFieldError {
    /// A trunk base parameter is out of range (sizes must be positive and finite, spread at least 1, tilt below 60
    /// degrees, the randomiser in 0..=1).
    #[error("trunk base parameter `{name}` is {value}")]
    TrunkBase {
        /// The parameter.
        name: &'static str,
        /// Its value.
        value: f32,
    },
    /// A meshing option is out of range.
    #[error("near-field option `{name}` is {value}")]
    Option {
        /// The option.
        name: &'static str,
        /// Its value.
        value: f32,
    },
    /// The mesh would exceed the vertex or triangle budget.
    #[error("near-field mesh needs more than {0} triangles")]
    TooLarge(usize),
    /// A LOD chain was asked of a mesh without triangles.
    #[error("the mesh has no triangles to decimate")]
    Empty,
    /// A mesh handed in is not well formed (an index out of range, or per-vertex data of the wrong length).
    #[error("malformed mesh: {0}")]
    Malformed(&'static str),
}

/// A triangle surface in some local frame: positions, unit normals and counter-clockwise triangles.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Surface {
    /// Vertex positions.
    pub positions: Vec<[f32; 3]>,
    /// Unit vertex normals, one per position.
    pub normals: Vec<[f32; 3]>,
    /// Three indices per triangle, counter-clockwise seen from outside.
    pub indices: Vec<u32>,
}

impl Surface {
    /// Number of triangles.
    pub fn triangle_count(&self) -> usize {
        self.indices.len() / 3
    }

    /// The surface as a [`Mesh`] of one colour.
    pub fn to_mesh(&self, color: [f32; 3]) -> Mesh {
        Mesh {
            positions: self.positions.clone(),
            normals: self.normals.clone(),
            colors: vec![color; self.positions.len()],
            indices: self.indices.clone(),
        }
    }
}

/// Vertex normals as seed 002 §4 makes them: each triangle's normal is the cross product of its edges, and a
/// vertex's normal is the average of the unit normals of the triangles that share it. A vertex no non-degenerate
/// triangle touches gets +Y.
pub fn face_averaged_normals(positions: &[[f32; 3]], indices: &[u32]) -> Vec<[f32; 3]> {
    let mut sums = vec![[0.0f64; 3]; positions.len()];
    for t in indices.chunks_exact(3) {
        let [a, b, c] = [t[0], t[1], t[2]].map(|i| positions[i as usize].map(f64::from));
        let Some(n) = normalize(cross(sub(b, a), sub(c, a))) else { continue };
        for &i in t {
            let s = &mut sums[i as usize];
            for k in 0..3 {
                s[k] += n[k];
            }
        }
    }
    sums.iter().map(|s| normalize(*s).unwrap_or([0.0, 1.0, 0.0]).map(|x| x as f32)).collect()
}

pub(crate) type V3 = [f64; 3];

pub(crate) use crate::vec3::{add, cross, dot, norm, scale, sub};

pub(crate) fn normalize(a: V3) -> Option<V3> {
    let n = norm(a);
    (n > 1e-300 && n.is_finite()).then(|| scale(a, 1.0 / n))
}

/// A unit vector perpendicular to the unit vector `a` (deterministic choice).
pub(crate) fn perpendicular(a: V3) -> V3 {
    let helper = if libm::fabs(a[0]) < 0.9 { [1.0, 0.0, 0.0] } else { [0.0, 0.0, 1.0] };
    normalize(cross(helper, a)).unwrap_or([1.0, 0.0, 0.0])
}

/// The parts of an instance meshed as its species asks with `nearfield(continuous = 1, …)`: the continuous mesh of
/// the branches (with contours along long pieces where a bark is asked for, so the plates are about square) and the
/// foliage, both in [`NearParts::continuous`], and the outer bark over the trunk.
#[derive(Clone, Debug)]
pub struct NearParts {
    /// The branches (`mesh`) and the foliage (`foliage`), with what a LOD chain needs.
    pub continuous: continuous::ContinuousMesh,
    /// The outer bark, when one is asked for.
    pub bark: Option<Mesh>,
}

/// Mesh an instance's near-field parts (see [`NearParts`]); `canopy species export` writes them as named meshes.
pub fn species_near_parts(
    stream: &crate::primitive::PrimitiveStream,
    opts: &NearFieldOptions,
) -> Result<NearParts, NearFieldError> {
    let mesh_opts =
        if opts.bark.is_some() { continuous::ContinuousOptions { subdivide: true, ..opts.mesh } } else { opts.mesh };
    let cm = continuous::continuous_mesh(stream, &mesh_opts)?;
    let bark = match &opts.bark {
        Some(b) => Some(bark::outer_bark(&cm.mesh, &bark::trunk_places(&cm.tags), b)?),
        None => None,
    };
    Ok(NearParts { continuous: cm, bark })
}

/// An instance's near-field parts ([`species_near_parts`]) merged into one mesh: branches, bark, foliage. The
/// renderer's near band draws this.
pub fn species_near_mesh(
    stream: &crate::primitive::PrimitiveStream,
    opts: &NearFieldOptions,
) -> Result<Mesh, NearFieldError> {
    let NearParts { continuous: cm, bark } = species_near_parts(stream, opts)?;
    let mut out = cm.mesh;
    if let Some(b) = &bark {
        out.append(b, [0.0; 3]);
    }
    out.append(&cm.foliage, [0.0; 3]);
    Ok(out)
}
