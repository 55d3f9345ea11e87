//! Hypertree definitions (seed 000, Strnad & Guid, "Modeling Trees with Hypertextures"): the few-KB IFS program
//! that a client iterates into a hypervolume to draw a distant tree.
//!
//! A [`HypertreeDef`] is what travels: resolution, iterations, tree and branch depth, density classes, depth colour
//! spans, noise perturbation, the hypervolume and the displacement of the tree inside it, the generator (a point or a
//! line segment), one or two [`Condensation`]s (cone mappings that form the stem) and the [`IfsTransformation`]s.
//! Each IFS transformation is a list of [`Elementary`] transformations — translate, rotate, scale and the nonlinear
//! shear of §3.1 — whose parameters may differ for the first, second and third-and-deeper levels of execution
//! (§3.4, §10) and may be random ranges, fixed once per tree from the instance seed (§3.2).
//!
//! Levels: the condensation is level 0; the generator produced by the `s`-th transformation selected after a
//! condensation is at level `s` (§3.3's "level of execution"). Parameter values are indexed the other way, as in
//! Figure 2: inside the pipeline that produces a level-`s` generator, the transformation applied last (to the whole
//! tree) uses its first-level values and the one applied first uses its level-`s` values.

use serde::{Deserialize, Serialize};

/// Largest encoded hypertree definition accepted from the wire or a file, in bytes.
pub const MAX_HYPERTREE_BYTES: usize = 64 * 1024;
/// Highest resolution along one axis of a hypervolume.
pub const MAX_RESOLUTION: u32 = 1024;
/// Most IFS iterations (generators produced) of one hypertree.
pub const MAX_ITERATIONS: u64 = 200_000_000;
/// Deepest tree (fractal) depth: condensation plus this many minus one transformations per cycle.
pub const MAX_TREE_DEPTH: u8 = 32;
/// Most density classes, including the empty class (§4: "we use up to 128 density classes").
pub const MAX_DENSITY_CLASSES: u8 = 128;
/// Most IFS transformations in one definition.
pub const MAX_TRANSFORMATIONS: usize = 64;
/// Most condensations in one definition.
pub const MAX_CONDENSATIONS: usize = 8;
/// Most elementary transformations in one IFS transformation or condensation.
pub const MAX_ELEMENTARY: usize = 32;
/// Most depth colour spans.
pub const MAX_DEPTH_COLORS: usize = 64;
/// Most per-level values of one parameter: first, second, third and deeper.
pub const MAX_PARAM_LEVELS: usize = 3;
/// Largest magnitude of any number in a definition (keeps every product finite in f32).
pub const MAX_MAGNITUDE: f32 = 1.0e6;
/// Largest shear bending exponent.
pub const MAX_EXPONENT: f32 = 64.0;
/// Longest hypertree name, in bytes.
pub const MAX_NAME_LEN: usize = 128;

/// One of the three major axes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Axis {
    /// The x axis.
    X,
    /// The y axis (up, by convention of the shipped trees).
    Y,
    /// The z axis.
    Z,
}

impl Axis {
    /// The coordinate index: 0, 1 or 2.
    pub fn index(self) -> usize {
        match self {
            Axis::X => 0,
            Axis::Y => 1,
            Axis::Z => 2,
        }
    }

    /// The two other axes' indices, in cyclic order (for Y: z then x).
    pub fn others(self) -> [usize; 2] {
        let a = self.index();
        [(a + 1) % 3, (a + 2) % 3]
    }
}

/// A number that may be random: drawn uniformly from `[mean − spread, mean + spread]` once per tree (§3.2).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct RandomValue {
    /// The mean value.
    pub mean: f32,
    /// Half the width of the range; 0 for a fixed value.
    pub spread: f32,
}

/// A transformation parameter with values per level of execution (§10): one value for every level, a pair
/// (first level, second and deeper) or a triplet (first, second, third and deeper).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Param(pub Vec<RandomValue>);

impl Param {
    /// A fixed value for every level.
    pub fn fixed(v: f32) -> Param {
        Param(vec![RandomValue { mean: v, spread: 0.0 }])
    }

    /// The value entry used at parameter level `level` (1-based; deeper levels use the last entry).
    pub fn at(&self, level: usize) -> RandomValue {
        self.0[level.clamp(1, self.0.len()) - 1]
    }
}

/// An elementary transformation: the building blocks of IFS transformations and condensations (§3.1).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Elementary {
    /// Adds a vector.
    Translate([Param; 3]),
    /// Rotates about a major axis by an angle in degrees (right-handed).
    Rotate {
        /// The rotation axis.
        axis: Axis,
        /// The angle in degrees.
        angle: Param,
    },
    /// Scales each axis.
    Scale([Param; 3]),
    /// The nonlinear shear of §3.1: the two coordinates other than `axis` (in [`Axis::others`] order) are displaced
    /// by `d = d_max · |h|^e`, where `h` is the coordinate along `axis` (the generator's height in tree units,
    /// clamped to [−1, 1]) and `e` the bending exponent.
    Shear {
        /// The bending ("height") axis.
        axis: Axis,
        /// The maximum displacements in the two bending directions.
        max: [Param; 2],
        /// The bending exponent `e`.
        exponent: Param,
    },
}

/// A cone mapping (§3.3, §10): maps the generator into the conical region along one major axis.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Cone {
    /// The cone's axis.
    pub axis: Axis,
    /// Coordinate of the bottom along the axis.
    pub bottom: f32,
    /// Coordinate of the top along the axis.
    pub top: f32,
    /// Radius at the bottom.
    pub bottom_radius: f32,
    /// Radius at the top.
    pub top_radius: f32,
}

/// A condensation transformation (§3.3): maps any generator into the stem volume, resetting the iteration.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Condensation {
    /// Relative probability of choosing this condensation when there are several (dichotomous branching).
    pub weight: f32,
    /// The cone mapping.
    pub cone: Cone,
    /// Elementary transformations applied after the cone (e.g. a shear that bends one of two forked stems).
    pub then: Vec<Elementary>,
}

/// An IFS transformation `w_j` (§2.2, §3, §10: `TRANSFORM p c [DUMMY d]`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct IfsTransformation {
    /// Relative selection probability `p_j` (§10: they need not sum to one).
    pub probability: f32,
    /// Last allowed level of execution `c_j` (§3.4): the transformation is not selected at deeper levels.
    pub last_level: u8,
    /// Dummy from this level on (§3.4): at these levels the transformed generator is computed but not recorded.
    pub dummy_from: Option<u8>,
    /// The elementary transformations, applied to the generator in this order.
    pub steps: Vec<Elementary>,
}

/// The generator that the IFS transforms (§4).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum Generator {
    /// A point (`POINTINIT`).
    Point([f32; 3]),
    /// A line segment whose length is preserved under the transformations (`LINEINIT`).
    Line {
        /// One end.
        from: [f32; 3],
        /// The other end.
        to: [f32; 3],
    },
}

/// A colour span over a range of voxel levels (§8.3, §10 `DEPTHCOLOR`): level `levels[0]` gets `from`, level
/// `levels[1]` gets `to`, levels between are interpolated.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct DepthColor {
    /// First and last level of the span (inclusive).
    pub levels: [u8; 2],
    /// Linear RGB colour at the first level, 0..1.
    pub from: [f32; 3],
    /// Linear RGB colour at the last level, 0..1.
    pub to: [f32; 3],
}

/// Noise perturbation of generator positions (§3.5, §10 `PERTURB`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Perturbation {
    /// Amplitude per axis, tree units (0 disables the axis).
    pub amplitude: [f32; 3],
    /// Spatial frequency of the noise, cycles per tree unit.
    pub frequency: f32,
}

/// A hypertree definition: the IFS program and the hypervolume it fills.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct HypertreeDef {
    /// The tree's name (`NAME`).
    pub name: String,
    /// Voxels along x, y and z (`RESOLUTION`).
    pub resolution: [u32; 3],
    /// Generators to produce (`ITERATIONS`, the paper's N).
    pub iterations: u64,
    /// Fractal depth `k` (`TREEDEPTH`): a condensation is enforced every `k` generators, so levels run 0..k.
    pub tree_depth: u8,
    /// Levels 0..=this are branches (`BRANCHDEPTH`): they get full density and usually a wood colour.
    pub branch_depth: u8,
    /// Density classes including the empty one (`DENSITYCLASSES`, 2 = binary/solid hypertree, §4).
    pub density_classes: u8,
    /// Colour spans by level (`DEPTHCOLOR`).
    pub depth_colors: Vec<DepthColor>,
    /// Noise perturbation (`PERTURB`).
    pub perturbation: Perturbation,
    /// Extent of the hypervolume box, tree units (`HYPERVOLUME`).
    pub hypervolume: [f32; 3],
    /// Where the tree's origin lies inside the box (`DISPLACEMENT`): tree point `p` is at box point `p + d`.
    pub displacement: [f32; 3],
    /// The generator (`POINTINIT` or `LINEINIT`).
    pub generator: Generator,
    /// Condensations (`CONDENSATION` … `CONE`).
    pub condensations: Vec<Condensation>,
    /// IFS transformations (`TRANSFORM`).
    pub transformations: Vec<IfsTransformation>,
}

/// Why a hypertree definition was rejected.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum HypertreeError {
    /// The name is empty or too long.
    #[error("name of {0} bytes (allowed 1..={MAX_NAME_LEN})")]
    Name(usize),
    /// A resolution is zero or too high.
    #[error("resolution {0:?} (allowed 1..={MAX_RESOLUTION} per axis)")]
    Resolution([u32; 3]),
    /// Too many or zero iterations.
    #[error("{0} iterations (allowed 1..={MAX_ITERATIONS})")]
    Iterations(u64),
    /// The tree depth is out of range.
    #[error("tree depth {0} (allowed 1..={MAX_TREE_DEPTH})")]
    TreeDepth(u8),
    /// The branch depth is not below the tree depth.
    #[error("branch depth {branch} is not below tree depth {tree}")]
    BranchDepth {
        /// The branch depth.
        branch: u8,
        /// The tree depth.
        tree: u8,
    },
    /// The number of density classes is out of range.
    #[error("{0} density classes (allowed 2..={MAX_DENSITY_CLASSES})")]
    DensityClasses(u8),
    /// Too many of something.
    #[error("{count} {what} (allowed {max})")]
    Count {
        /// What was counted.
        what: &'static str,
        /// How many there are.
        count: usize,
        /// The most allowed.
        max: usize,
    },
    /// No condensation, or no transformation.
    #[error("no {0}")]
    Missing(&'static str),
    /// A number is not finite, too large, or outside its allowed range.
    #[error("{what} is {value} (allowed {range})")]
    Number {
        /// Which number.
        what: &'static str,
        /// Its value.
        value: f32,
        /// The allowed range, in words.
        range: &'static str,
    },
    /// A parameter has no values or more than three levels.
    #[error("a parameter has {0} level values (allowed 1..={MAX_PARAM_LEVELS})")]
    ParamLevels(usize),
    /// Probabilities or condensation weights sum to zero.
    #[error("{0} sum to zero")]
    ZeroWeights(&'static str),
    /// A depth colour span runs backwards.
    #[error("depth colour span {0}..{1} runs backwards")]
    DepthSpan(u8, u8),
    /// A condensation has a per-level parameter (condensations have no level of execution).
    #[error("condensation parameters cannot vary by level")]
    CondensationLevels,
}

/// Why bytes did not decode to a hypertree definition.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum HypertreeDecodeError {
    /// The input is larger than [`MAX_HYPERTREE_BYTES`].
    #[error("hypertree encoding of {0} bytes exceeds {MAX_HYPERTREE_BYTES}")]
    TooLarge(usize),
    /// postcard could not decode the bytes.
    #[error("malformed hypertree encoding: {0}")]
    Postcard(#[from] postcard::Error),
    /// Bytes were left over after the definition.
    #[error("{0} trailing bytes after the hypertree definition")]
    Trailing(usize),
    /// The definition decoded but is not valid.
    #[error("invalid hypertree definition: {0}")]
    Invalid(#[from] HypertreeError),
}

fn check(what: &'static str, value: f32, ok: bool, range: &'static str) -> Result<(), HypertreeError> {
    if value.is_finite() && value.abs() <= MAX_MAGNITUDE && ok {
        Ok(())
    } else {
        Err(HypertreeError::Number { what, value, range })
    }
}

fn finite(what: &'static str, value: f32) -> Result<(), HypertreeError> {
    check(what, value, true, "finite, magnitude at most 1e6")
}

fn count(what: &'static str, n: usize, max: usize) -> Result<(), HypertreeError> {
    if n > max { Err(HypertreeError::Count { what, count: n, max }) } else { Ok(()) }
}

impl Elementary {
    /// Every parameter of the transformation.
    pub fn params(&self) -> Vec<&Param> {
        match self {
            Elementary::Translate(v) | Elementary::Scale(v) => v.iter().collect(),
            Elementary::Rotate { angle, .. } => vec![angle],
            Elementary::Shear { max, exponent, .. } => vec![&max[0], &max[1], exponent],
        }
    }

    fn validate(&self) -> Result<(), HypertreeError> {
        for p in self.params() {
            if p.0.is_empty() || p.0.len() > MAX_PARAM_LEVELS {
                return Err(HypertreeError::ParamLevels(p.0.len()));
            }
            for v in &p.0 {
                finite("a parameter mean", v.mean)?;
                check("a parameter spread", v.spread, v.spread >= 0.0, "0..=1e6")?;
            }
        }
        if let Elementary::Shear { exponent, .. } = self {
            for v in &exponent.0 {
                let (lo, hi) = (v.mean - v.spread, v.mean + v.spread);
                check("a shear exponent", lo, lo >= 0.0 && hi <= MAX_EXPONENT, "0..=64 over its whole range")?;
            }
        }
        Ok(())
    }
}

impl HypertreeDef {
    /// The most per-level values any transformation parameter has: 1, 2 or 3. Parameters are constant from this
    /// level on, which is what lets generation recompute only the last `m` transformations of each pipeline row
    /// (§3.4, Figure 2).
    pub fn param_levels(&self) -> usize {
        self.transformations
            .iter()
            .flat_map(|t| t.steps.iter())
            .flat_map(|e| e.params())
            .map(|p| p.0.len())
            .max()
            .unwrap_or(1)
            .max(1)
    }

    /// Check every limit and range (see the module docs). Decoders call this; so should builders.
    pub fn validate(&self) -> Result<(), HypertreeError> {
        if self.name.is_empty() || self.name.len() > MAX_NAME_LEN {
            return Err(HypertreeError::Name(self.name.len()));
        }
        if self.resolution.iter().any(|&r| r == 0 || r > MAX_RESOLUTION) {
            return Err(HypertreeError::Resolution(self.resolution));
        }
        if self.iterations == 0 || self.iterations > MAX_ITERATIONS {
            return Err(HypertreeError::Iterations(self.iterations));
        }
        if self.tree_depth == 0 || self.tree_depth > MAX_TREE_DEPTH {
            return Err(HypertreeError::TreeDepth(self.tree_depth));
        }
        if self.branch_depth >= self.tree_depth {
            return Err(HypertreeError::BranchDepth { branch: self.branch_depth, tree: self.tree_depth });
        }
        if self.density_classes < 2 || self.density_classes > MAX_DENSITY_CLASSES {
            return Err(HypertreeError::DensityClasses(self.density_classes));
        }
        count("depth colour spans", self.depth_colors.len(), MAX_DEPTH_COLORS)?;
        for c in &self.depth_colors {
            if c.levels[0] > c.levels[1] {
                return Err(HypertreeError::DepthSpan(c.levels[0], c.levels[1]));
            }
            for v in c.from.iter().chain(&c.to) {
                check("a colour component", *v, (0.0..=1.0).contains(v), "0..=1")?;
            }
        }
        for a in self.perturbation.amplitude {
            check("a perturbation amplitude", a, a >= 0.0, "0..=1e6")?;
        }
        let f = self.perturbation.frequency;
        check("the perturbation frequency", f, f > 0.0, "positive")?;
        for v in self.hypervolume {
            check("a hypervolume extent", v, v > 0.0, "positive")?;
        }
        for v in self.displacement {
            finite("a displacement", v)?;
        }
        match self.generator {
            Generator::Point(p) => p.iter().try_for_each(|&v| finite("a generator coordinate", v))?,
            Generator::Line { from, to } => {
                from.iter().chain(&to).try_for_each(|&v| finite("a generator coordinate", v))?
            }
        }
        if self.condensations.is_empty() {
            return Err(HypertreeError::Missing("condensation"));
        }
        count("condensations", self.condensations.len(), MAX_CONDENSATIONS)?;
        let mut weights = 0.0f32;
        for c in &self.condensations {
            check("a condensation weight", c.weight, c.weight >= 0.0, "0..=1e6")?;
            weights += c.weight;
            let cone = &c.cone;
            finite("a cone bottom", cone.bottom)?;
            finite("a cone top", cone.top)?;
            check("a cone radius", cone.bottom_radius, cone.bottom_radius >= 0.0, "0..=1e6")?;
            check("a cone radius", cone.top_radius, cone.top_radius >= 0.0, "0..=1e6")?;
            count("elementary transformations in a condensation", c.then.len(), MAX_ELEMENTARY)?;
            for e in &c.then {
                e.validate()?;
                if e.params().iter().any(|p| p.0.len() > 1) {
                    return Err(HypertreeError::CondensationLevels);
                }
            }
        }
        if weights <= 0.0 {
            return Err(HypertreeError::ZeroWeights("condensation weights"));
        }
        if self.transformations.is_empty() {
            return Err(HypertreeError::Missing("transformation"));
        }
        count("transformations", self.transformations.len(), MAX_TRANSFORMATIONS)?;
        let mut probabilities = 0.0f32;
        for t in &self.transformations {
            check("a probability", t.probability, t.probability >= 0.0, "0..=1e6")?;
            probabilities += t.probability;
            if t.last_level == 0 {
                return Err(HypertreeError::Number { what: "a last level", value: 0.0, range: "1..=255" });
            }
            if t.dummy_from == Some(0) {
                return Err(HypertreeError::Number { what: "a dummy level", value: 0.0, range: "1..=255" });
            }
            count("elementary transformations in a transformation", t.steps.len(), MAX_ELEMENTARY)?;
            t.steps.iter().try_for_each(Elementary::validate)?;
        }
        if probabilities <= 0.0 {
            return Err(HypertreeError::ZeroWeights("transformation probabilities"));
        }
        Ok(())
    }

    /// Encode with postcard (the wire and cache form).
    pub fn encode(&self) -> Vec<u8> {
        postcard::to_allocvec(self).expect("encoding a hypertree definition into a Vec cannot fail")
    }

    /// Decode untrusted bytes: bounded in size, checked to the end, and validated.
    pub fn decode(bytes: &[u8]) -> Result<HypertreeDef, HypertreeDecodeError> {
        if bytes.len() > MAX_HYPERTREE_BYTES {
            return Err(HypertreeDecodeError::TooLarge(bytes.len()));
        }
        let (def, rest): (HypertreeDef, &[u8]) = postcard::take_from_bytes(bytes)?;
        if !rest.is_empty() {
            return Err(HypertreeDecodeError::Trailing(rest.len()));
        }
        def.validate()?;
        Ok(def)
    }
}
