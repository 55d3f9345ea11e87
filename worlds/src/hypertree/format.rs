//! The hypertree definition format (`.hyp`, §10 and Figure 6) and the hyperforest file (`.hyf`), parsed with
//! `file:line:col` diagnostics; every error on every line is reported, not just the first.
//!
//! ```text
//! NAME apple                          # optional; defaults to the file name
//! RESOLUTION 300                      # one value, or one per axis
//! ITERATIONS 500000                   # generators to produce (N)
//! TREEDEPTH 10                        # a condensation every 10 generators: levels 0..=9
//! BRANCHDEPTH 1                       # levels 0..=1 are branches (full density)
//! DENSITYCLASSES 64                   # 2 = binary (solid) hypertree
//! DEPTHCOLOR 0 1 0.30 0.20 0.12 0.35 0.25 0.15   # levels, RGB at the first level, RGB at the last
//! PERTURB 0.005 0.01 0.005 8          # amplitude per axis, optional noise frequency (default 8)
//! HYPERVOLUME 1.2 1.2 1.2             # box extent, tree units
//! DISPLACEMENT 0.6 0.02 0.6           # where the tree origin sits in the box
//! POINTINIT 0 0 0                     # or LINEINIT x0 y0 z0 x1 y1 z1
//! CONDENSATION 1                      # optional weight; then CONE and optional elementary transformations
//!   CONE Y 0 0.35 0.03 0.015          # axis, bottom, top, bottom radius, top radius
//! TRANSFORM 1 255 DUMMY 4             # probability, last allowed level, optional dummy-from level
//!   SCALE 0.6                         # one value or three
//!   ROTATE Z (40 30 25)               # per level: first, second, third and deeper
//!   ROTATE Y 120~15                   # mean~spread: drawn once per tree from the instance seed
//!   SHEAR Y 0.1 0 2                   # bending axis, two maximum displacements, exponent
//!   TRANSLATE 0 0.35 0
//! ```
//! Keywords are case-insensitive. Elementary transformations belong to the `CONDENSATION` or `TRANSFORM` above
//! them and are applied to the generator in the order written.
//!
//! A hyperforest file names a common volume and the hypertrees in it:
//! ```text
//! NAME grove
//! RESOLUTION 300 150 300
//! STORAGETYPE INDEXBITS               # DENSE | INDEXLIST | INDEXBITS, optionally PARTITIONED
//! HYPERVOLUME 4 2 4
//! TREE apple.hyp 1 0 1 SEED 3         # file (relative to the forest file), origin in the box, optional seed
//! ```

use std::ops::Range;
use std::path::{Path, PathBuf};

use canopy_protocol::hypertree::{
    Axis, Condensation, Cone, DepthColor, Elementary, Generator, HypertreeDef, IfsTransformation, MAX_CONDENSATIONS,
    MAX_DENSITY_CLASSES, MAX_DEPTH_COLORS, MAX_ELEMENTARY, MAX_EXPONENT, MAX_ITERATIONS, MAX_MAGNITUDE, MAX_NAME_LEN,
    MAX_PARAM_LEVELS, MAX_RESOLUTION, MAX_TRANSFORMATIONS, MAX_TREE_DEPTH, Param, Perturbation, RandomValue,
};

use crate::diag::{Diagnostic, SourceFile};
use crate::hypertree::StorageType;
use crate::load::{MAX_SOURCE_BYTES, file_diag, read_source};
use crate::text::{Cursor, ParseError};

/// Most trees in one hyperforest.
pub const MAX_FOREST_TREES: usize = 256;

/// Default noise frequency when `PERTURB` gives none.
pub const DEFAULT_FREQUENCY: f32 = 8.0;

/// Parse a hypertree definition. Returns the definition if there were no errors, and every diagnostic found.
pub fn parse_hypertree(src: &SourceFile) -> (Option<HypertreeDef>, Vec<Diagnostic>) {
    let mut p = DefParser::new(src);
    p.run();
    p.finish()
}

/// One tree of a hyperforest.
#[derive(Clone, Debug, PartialEq)]
pub struct ForestTree {
    /// The definition file, relative to the forest file as written.
    pub path: PathBuf,
    /// Where the tree's origin stands in the forest's hypervolume.
    pub origin: [f32; 3],
    /// The instance seed (defaults to the tree's position in the list).
    pub seed: u64,
    /// Byte span of the file name (for diagnostics while loading it).
    pub span: Range<usize>,
}

/// A hyperforest file: a common volume and the hypertrees generated into it (§10).
#[derive(Clone, Debug, PartialEq)]
pub struct ForestDef {
    /// The forest's name.
    pub name: String,
    /// Voxels along x, y, z of the common volume.
    pub resolution: [u32; 3],
    /// How the common volume is stored.
    pub storage: StorageType,
    /// Whether index lists are kept per first-level subpart.
    pub partitioned: bool,
    /// Extent of the common hypervolume.
    pub hypervolume: [f32; 3],
    /// The trees.
    pub trees: Vec<ForestTree>,
}

/// Parse a hyperforest file (the tree files are not read here; see [`load_forest`]).
pub fn parse_forest(src: &SourceFile) -> (Option<ForestDef>, Vec<Diagnostic>) {
    let mut cur = Cursor::new(&src.text, false);
    let mut errors: Vec<ParseError> = Vec::new();
    let mut name = None;
    let mut resolution = None;
    let mut storage = None;
    let mut hypervolume = None;
    let mut trees = Vec::new();
    if src.text.len() > MAX_SOURCE_BYTES {
        return (None, vec![src.diag(0..0, format!("file larger than {MAX_SOURCE_BYTES} bytes"))]);
    }
    loop {
        cur.skip_trivia();
        if cur.at_end() {
            break;
        }
        if cur.eat("\n") {
            continue;
        }
        let r = (|| -> Result<(), ParseError> {
            let (kw, span) = cur.ident().ok_or_else(|| cur.unexpected("a keyword"))?;
            match kw.to_ascii_uppercase().as_str() {
                "NAME" => set_once(&mut name, parse_name(&mut cur)?, &span)?,
                "RESOLUTION" => set_once(&mut resolution, parse_resolution(&mut cur)?, &span)?,
                "HYPERVOLUME" => set_once(&mut hypervolume, positive3(&mut cur, "a hypervolume extent")?, &span)?,
                "STORAGETYPE" => {
                    let (w, s) = cur.ident().ok_or_else(|| cur.unexpected("DENSE, INDEXLIST or INDEXBITS"))?;
                    let ty = storage_type(w).ok_or_else(|| {
                        ParseError::new(s.clone(), format!("unknown storage type `{w}` (DENSE, INDEXLIST, INDEXBITS)"))
                    })?;
                    let partitioned = match cur.ident() {
                        None => false,
                        Some((w, _)) if w.eq_ignore_ascii_case("PARTITIONED") => true,
                        Some((w, s)) => return Err(ParseError::new(s, format!("expected PARTITIONED, found `{w}`"))),
                    };
                    if partitioned && ty == StorageType::Dense {
                        return Err(ParseError::new(s, "a dense array cannot be partitioned"));
                    }
                    set_once(&mut storage, (ty, partitioned), &span)?;
                }
                "TREE" => {
                    if trees.len() >= MAX_FOREST_TREES {
                        return Err(ParseError::new(span, format!("more than {MAX_FOREST_TREES} trees")));
                    }
                    cur.skip_trivia();
                    let start = cur.pos;
                    let rest = cur.rest();
                    let len = rest.find(|c: char| c.is_whitespace() || c == '#').unwrap_or(rest.len());
                    if len == 0 {
                        return Err(cur.unexpected("a hypertree file name"));
                    }
                    cur.pos += len;
                    let path = PathBuf::from(&src.text[start..cur.pos]);
                    let origin = [number(&mut cur)?, number(&mut cur)?, number(&mut cur)?];
                    for (v, s) in &origin {
                        in_range(*v, s, -MAX_MAGNITUDE, MAX_MAGNITUDE, "a tree origin")?;
                    }
                    let mut seed = trees.len() as u64 + 1;
                    if cur.eat_keyword("SEED") || cur.eat_keyword("seed") {
                        let (v, s) = integer(&mut cur)?;
                        seed = v;
                        let _ = s;
                    }
                    trees.push(ForestTree { path, origin: origin.map(|o| o.0), seed, span: start..start + len });
                }
                other => {
                    return Err(ParseError::new(
                        span,
                        format!("unknown keyword `{other}` (NAME, RESOLUTION, STORAGETYPE, HYPERVOLUME, TREE)"),
                    ));
                }
            }
            end_of_line(&mut cur)
        })();
        if let Err(e) = r {
            errors.push(e);
            cur.skip_line();
        }
    }
    if trees.is_empty() && errors.is_empty() {
        errors.push(ParseError::new(0..0, "a hyperforest needs at least one TREE"));
    }
    let diags: Vec<Diagnostic> = errors.into_iter().map(|e| src.diag(e.span, e.message)).collect();
    if !diags.is_empty() {
        return (None, diags);
    }
    let (storage, partitioned) = storage.unwrap_or((StorageType::IndexBits, false));
    let def = ForestDef {
        name: name.unwrap_or_else(|| file_stem(&src.name)),
        resolution: resolution.unwrap_or([300, 300, 300]),
        storage,
        partitioned,
        hypervolume: hypervolume.unwrap_or([1.0, 1.0, 1.0]),
        trees,
    };
    (Some(def), diags)
}

/// A parsed forest together with its trees' definitions, read relative to the forest file.
#[derive(Clone, Debug)]
pub struct Forest {
    /// The forest file.
    pub def: ForestDef,
    /// Each tree's definition, in the order of [`ForestDef::trees`].
    pub trees: Vec<HypertreeDef>,
}

/// Read and parse a hyperforest file and every hypertree file it names, collecting all diagnostics.
pub fn load_forest(path: &Path) -> (Option<Forest>, Vec<Diagnostic>) {
    let src = match read_source(path) {
        Ok(src) => src,
        Err(e) => return (None, vec![file_diag(path, e)]),
    };
    let (def, mut diags) = parse_forest(&src);
    let Some(def) = def else { return (None, diags) };
    let dir = path.parent().unwrap_or(Path::new("."));
    let mut trees = Vec::new();
    for t in &def.trees {
        let tree_path = dir.join(&t.path);
        match read_source(&tree_path) {
            Ok(tree_src) => {
                let (d, mut ds) = parse_hypertree(&tree_src);
                diags.append(&mut ds);
                if let Some(d) = d {
                    trees.push(d);
                }
            }
            Err(e) => diags.push(src.diag(t.span.clone(), format!("`{}`: {e}", tree_path.display()))),
        }
    }
    if diags.is_empty() { (Some(Forest { def, trees }), diags) } else { (None, diags) }
}

/// Read and parse one hypertree definition file.
pub fn load_hypertree(path: &Path) -> (Option<HypertreeDef>, Vec<Diagnostic>) {
    match read_source(path) {
        Ok(src) => parse_hypertree(&src),
        Err(e) => (None, vec![file_diag(path, e)]),
    }
}

/// The storage type a keyword names.
pub fn storage_type(word: &str) -> Option<StorageType> {
    match word.to_ascii_uppercase().as_str() {
        "DENSE" | "ARRAY" => Some(StorageType::Dense),
        "INDEXLIST" => Some(StorageType::IndexList),
        "INDEXBITS" => Some(StorageType::IndexBits),
        _ => None,
    }
}

fn file_stem(name: &str) -> String {
    let base = name.rsplit(['/', '\\']).next().unwrap_or(name);
    let stem = base.split('.').next().unwrap_or(base);
    let stem: String = stem.chars().take(MAX_NAME_LEN).collect();
    if stem.is_empty() { "hypertree".to_string() } else { stem }
}

fn set_once<T>(slot: &mut Option<T>, v: T, span: &Range<usize>) -> Result<(), ParseError> {
    if slot.is_some() {
        return Err(ParseError::new(span.clone(), "keyword given twice"));
    }
    *slot = Some(v);
    Ok(())
}

fn end_of_line(cur: &mut Cursor<'_>) -> Result<(), ParseError> {
    cur.skip_trivia();
    if cur.at_end() || cur.eat("\n") { Ok(()) } else { Err(cur.unexpected("end of line")) }
}

/// A signed decimal number with its span.
fn number(cur: &mut Cursor<'_>) -> Result<(f32, Range<usize>), ParseError> {
    cur.signed_number().unwrap_or_else(|| Err(cur.unexpected("a number")))
}

/// A non-negative integer.
fn integer(cur: &mut Cursor<'_>) -> Result<(u64, Range<usize>), ParseError> {
    let Some((v, span)) = cur.integer() else { return Err(cur.unexpected("a non-negative integer")) };
    match v {
        _ if cur.rest().starts_with('.') => Err(ParseError::new(span, "expected an integer")),
        Some(v) => Ok((v, span)),
        None if cur.src[span.clone()].bytes().all(|c| c.is_ascii_digit()) => {
            Err(ParseError::new(span, "integer too large"))
        }
        None => Err(ParseError::new(span, "expected an integer")),
    }
}

fn int_in(cur: &mut Cursor<'_>, lo: u64, hi: u64, what: &str) -> Result<(u64, Range<usize>), ParseError> {
    let (v, s) = integer(cur)?;
    if v < lo || v > hi {
        return Err(ParseError::new(s, format!("{what} {v} is out of range {lo}..={hi}")));
    }
    Ok((v, s))
}

fn in_range(v: f32, s: &Range<usize>, lo: f32, hi: f32, what: &str) -> Result<(), ParseError> {
    if v < lo || v > hi {
        return Err(ParseError::new(s.clone(), format!("{what} {v} is out of range {lo}..={hi}")));
    }
    Ok(())
}

fn positive3(cur: &mut Cursor<'_>, what: &str) -> Result<[f32; 3], ParseError> {
    let mut out = [0.0; 3];
    for o in &mut out {
        let (v, s) = number(cur)?;
        if v <= 0.0 || v > MAX_MAGNITUDE {
            return Err(ParseError::new(s, format!("{what} must be positive and at most 1e6")));
        }
        *o = v;
    }
    Ok(out)
}

fn finite3(cur: &mut Cursor<'_>, what: &str) -> Result<[f32; 3], ParseError> {
    let mut out = [0.0; 3];
    for o in &mut out {
        let (v, s) = number(cur)?;
        in_range(v, &s, -MAX_MAGNITUDE, MAX_MAGNITUDE, what)?;
        *o = v;
    }
    Ok(out)
}

fn parse_name(cur: &mut Cursor<'_>) -> Result<String, ParseError> {
    cur.skip_trivia();
    let start = cur.pos;
    let rest = cur.rest();
    let line = &rest[..rest.find(['\n', '#']).unwrap_or(rest.len())];
    let name = line.trim_end();
    if name.is_empty() {
        return Err(cur.unexpected("a name"));
    }
    cur.pos += name.len();
    if name.len() > MAX_NAME_LEN {
        return Err(ParseError::new(start..cur.pos, format!("name longer than {MAX_NAME_LEN} bytes")));
    }
    Ok(name.to_string())
}

fn parse_resolution(cur: &mut Cursor<'_>) -> Result<[u32; 3], ParseError> {
    let (x, _) = int_in(cur, 1, u64::from(MAX_RESOLUTION), "resolution")?;
    cur.skip_trivia();
    if cur.peek().is_some_and(|c| c.is_ascii_digit()) {
        let (y, _) = int_in(cur, 1, u64::from(MAX_RESOLUTION), "resolution")?;
        let (z, _) = int_in(cur, 1, u64::from(MAX_RESOLUTION), "resolution")?;
        Ok([x as u32, y as u32, z as u32])
    } else {
        Ok([x as u32; 3])
    }
}

fn axis(cur: &mut Cursor<'_>) -> Result<Axis, ParseError> {
    let (w, s) = cur.ident().ok_or_else(|| cur.unexpected("an axis (X, Y or Z)"))?;
    match w {
        "x" | "X" => Ok(Axis::X),
        "y" | "Y" => Ok(Axis::Y),
        "z" | "Z" => Ok(Axis::Z),
        _ => Err(ParseError::new(s, format!("expected an axis (X, Y or Z), found `{w}`"))),
    }
}

/// `mean` or `mean~spread`.
fn random_value(cur: &mut Cursor<'_>) -> Result<(RandomValue, Range<usize>), ParseError> {
    let (mean, s) = number(cur)?;
    in_range(mean, &s, -MAX_MAGNITUDE, MAX_MAGNITUDE, "a value")?;
    if cur.rest().starts_with('~') {
        cur.pos += 1;
        let (spread, s2) = number(cur)?;
        in_range(spread, &s2, 0.0, MAX_MAGNITUDE, "a spread")?;
        return Ok((RandomValue { mean, spread }, s.start..s2.end));
    }
    Ok((RandomValue { mean, spread: 0.0 }, s))
}

/// A value, or `(first second)` / `(first second third)` per level.
fn param(cur: &mut Cursor<'_>) -> Result<(Param, Range<usize>), ParseError> {
    cur.skip_trivia();
    let start = cur.pos;
    if cur.eat("(") {
        let mut vals = Vec::new();
        loop {
            cur.skip_trivia();
            if cur.eat(")") {
                break;
            }
            if vals.len() == MAX_PARAM_LEVELS {
                return Err(ParseError::new(
                    cur.pos..cur.pos + 1,
                    format!("at most {MAX_PARAM_LEVELS} level values (first, second, third and deeper)"),
                ));
            }
            vals.push(random_value(cur)?.0);
        }
        if vals.len() < 2 {
            return Err(ParseError::new(start..cur.pos, "a per-level group needs two or three values"));
        }
        return Ok((Param(vals), start..cur.pos));
    }
    let (v, s) = random_value(cur)?;
    Ok((Param(vec![v]), s))
}

fn params_range(p: &Param, s: &Range<usize>, lo: f32, hi: f32, what: &str) -> Result<(), ParseError> {
    for v in &p.0 {
        in_range(v.mean - v.spread, s, lo, hi, what)?;
        in_range(v.mean + v.spread, s, lo, hi, what)?;
    }
    Ok(())
}

fn elementary(kw: &str, cur: &mut Cursor<'_>) -> Result<Option<Elementary>, ParseError> {
    Ok(Some(match kw {
        "TRANSLATE" => Elementary::Translate([param(cur)?.0, param(cur)?.0, param(cur)?.0]),
        "ROTATE" => Elementary::Rotate { axis: axis(cur)?, angle: param(cur)?.0 },
        "SCALE" => {
            let first = param(cur)?.0;
            cur.skip_trivia();
            if cur.peek().is_some_and(|c| c != '\n') {
                Elementary::Scale([first, param(cur)?.0, param(cur)?.0])
            } else {
                Elementary::Scale([first.clone(), first.clone(), first])
            }
        }
        "SHEAR" => {
            let axis = axis(cur)?;
            let max = [param(cur)?.0, param(cur)?.0];
            let (exponent, s) = param(cur)?;
            params_range(&exponent, &s, 0.0, MAX_EXPONENT, "a shear exponent")?;
            Elementary::Shear { axis, max, exponent }
        }
        _ => return Ok(None),
    }))
}

enum Block {
    None,
    Condensation { weight: f32, cone: Option<Cone>, then: Vec<Elementary>, span: Range<usize> },
    Transform(IfsTransformation),
}

struct DefParser<'a> {
    src: &'a SourceFile,
    cur: Cursor<'a>,
    errors: Vec<ParseError>,
    name: Option<String>,
    resolution: Option<[u32; 3]>,
    iterations: Option<u64>,
    tree_depth: Option<(u8, Range<usize>)>,
    branch_depth: Option<(u8, Range<usize>)>,
    classes: Option<u8>,
    colors: Vec<DepthColor>,
    perturb: Option<Perturbation>,
    hypervolume: Option<[f32; 3]>,
    displacement: Option<[f32; 3]>,
    generator: Option<Generator>,
    condensations: Vec<Condensation>,
    transforms: Vec<IfsTransformation>,
    block: Block,
    last_transform_span: Range<usize>,
}

impl<'a> DefParser<'a> {
    fn new(src: &'a SourceFile) -> DefParser<'a> {
        DefParser {
            src,
            cur: Cursor::new(&src.text, false),
            errors: Vec::new(),
            name: None,
            resolution: None,
            iterations: None,
            tree_depth: None,
            branch_depth: None,
            classes: None,
            colors: Vec::new(),
            perturb: None,
            hypervolume: None,
            displacement: None,
            generator: None,
            condensations: Vec::new(),
            transforms: Vec::new(),
            block: Block::None,
            last_transform_span: 0..0,
        }
    }

    fn run(&mut self) {
        if self.src.text.len() > MAX_SOURCE_BYTES {
            self.errors.push(ParseError::new(0..0, format!("file larger than {MAX_SOURCE_BYTES} bytes")));
            return;
        }
        loop {
            self.cur.skip_trivia();
            if self.cur.at_end() {
                break;
            }
            if self.cur.eat("\n") {
                continue;
            }
            let r = self.line().and_then(|()| end_of_line(&mut self.cur));
            if let Err(e) = r {
                self.errors.push(e);
                self.cur.skip_line();
            }
        }
        self.close_block();
    }

    fn close_block(&mut self) {
        match std::mem::replace(&mut self.block, Block::None) {
            Block::None => {}
            Block::Condensation { weight, cone, then, span } => match cone {
                Some(cone) => self.condensations.push(Condensation { weight, cone, then }),
                None => self.errors.push(ParseError::new(span, "condensation without a CONE")),
            },
            Block::Transform(t) => self.transforms.push(t),
        }
    }

    fn line(&mut self) -> Result<(), ParseError> {
        let cur = &mut self.cur;
        let (word, span) = cur.ident().ok_or_else(|| cur.unexpected("a keyword"))?;
        let kw = word.to_ascii_uppercase();
        if let Some(e) = elementary(&kw, &mut self.cur)? {
            return match &mut self.block {
                Block::None => Err(ParseError::new(span, format!("{kw} outside a CONDENSATION or TRANSFORM block"))),
                Block::Condensation { then, .. } => {
                    if then.len() >= MAX_ELEMENTARY {
                        return Err(ParseError::new(span, format!("more than {MAX_ELEMENTARY} transformations")));
                    }
                    if e.params().iter().any(|p| p.0.len() > 1) {
                        return Err(ParseError::new(span, "condensation parameters cannot vary by level"));
                    }
                    then.push(e);
                    Ok(())
                }
                Block::Transform(t) => {
                    if t.steps.len() >= MAX_ELEMENTARY {
                        return Err(ParseError::new(span, format!("more than {MAX_ELEMENTARY} transformations")));
                    }
                    t.steps.push(e);
                    Ok(())
                }
            };
        }
        let cur = &mut self.cur;
        match kw.as_str() {
            "NAME" => set_once(&mut self.name, parse_name(cur)?, &span),
            "RESOLUTION" => set_once(&mut self.resolution, parse_resolution(cur)?, &span),
            "ITERATIONS" => set_once(&mut self.iterations, int_in(cur, 1, MAX_ITERATIONS, "iterations")?.0, &span),
            "TREEDEPTH" => {
                let (v, s) = int_in(cur, 1, u64::from(MAX_TREE_DEPTH), "tree depth")?;
                set_once(&mut self.tree_depth, (v as u8, s), &span)
            }
            "BRANCHDEPTH" => {
                let (v, s) = int_in(cur, 0, u64::from(MAX_TREE_DEPTH) - 1, "branch depth")?;
                set_once(&mut self.branch_depth, (v as u8, s), &span)
            }
            "DENSITYCLASSES" => {
                let (v, _) = int_in(cur, 2, u64::from(MAX_DENSITY_CLASSES), "density classes")?;
                set_once(&mut self.classes, v as u8, &span)
            }
            "DEPTHCOLOR" => {
                if self.colors.len() >= MAX_DEPTH_COLORS {
                    return Err(ParseError::new(span, format!("more than {MAX_DEPTH_COLORS} depth colour spans")));
                }
                let (a, sa) = int_in(cur, 0, 255, "level")?;
                let (b, sb) = int_in(cur, 0, 255, "level")?;
                if a > b {
                    return Err(ParseError::new(sa.start..sb.end, "depth colour span runs backwards"));
                }
                let mut rgb = [0.0f32; 6];
                for c in &mut rgb {
                    let (v, s) = number(cur)?;
                    in_range(v, &s, 0.0, 1.0, "a colour component")?;
                    *c = v;
                }
                self.colors.push(DepthColor {
                    levels: [a as u8, b as u8],
                    from: [rgb[0], rgb[1], rgb[2]],
                    to: [rgb[3], rgb[4], rgb[5]],
                });
                Ok(())
            }
            "PERTURB" => {
                let mut amplitude = [0.0f32; 3];
                for a in &mut amplitude {
                    let (v, s) = number(cur)?;
                    in_range(v, &s, 0.0, MAX_MAGNITUDE, "a perturbation amplitude")?;
                    *a = v;
                }
                cur.skip_trivia();
                let mut frequency = DEFAULT_FREQUENCY;
                if cur.peek().is_some_and(|c| c != '\n') {
                    let (v, s) = number(cur)?;
                    if v <= 0.0 || v > MAX_MAGNITUDE {
                        return Err(ParseError::new(s, "the noise frequency must be positive and at most 1e6"));
                    }
                    frequency = v;
                }
                set_once(&mut self.perturb, Perturbation { amplitude, frequency }, &span)
            }
            "HYPERVOLUME" => set_once(&mut self.hypervolume, positive3(cur, "a hypervolume extent")?, &span),
            "DISPLACEMENT" => set_once(&mut self.displacement, finite3(cur, "a displacement")?, &span),
            "POINTINIT" => set_once(&mut self.generator, Generator::Point(finite3(cur, "a coordinate")?), &span),
            "LINEINIT" => {
                let from = finite3(cur, "a coordinate")?;
                let to = finite3(cur, "a coordinate")?;
                set_once(&mut self.generator, Generator::Line { from, to }, &span)
            }
            "CONDENSATION" => {
                self.close_block();
                if self.condensations.len() >= MAX_CONDENSATIONS {
                    return Err(ParseError::new(span, format!("more than {MAX_CONDENSATIONS} condensations")));
                }
                let cur = &mut self.cur;
                cur.skip_trivia();
                let mut weight = 1.0;
                if cur.peek().is_some_and(|c| c != '\n') {
                    let (v, s) = number(cur)?;
                    in_range(v, &s, 0.0, MAX_MAGNITUDE, "a condensation weight")?;
                    weight = v;
                }
                self.block = Block::Condensation { weight, cone: None, then: Vec::new(), span };
                Ok(())
            }
            "CONE" => {
                let Block::Condensation { cone, then, .. } = &mut self.block else {
                    return Err(ParseError::new(span, "CONE outside a CONDENSATION block"));
                };
                if cone.is_some() {
                    return Err(ParseError::new(span, "a condensation has one CONE"));
                }
                if !then.is_empty() {
                    return Err(ParseError::new(
                        span,
                        "CONE must come before the condensation's other transformations",
                    ));
                }
                let axis = axis(cur)?;
                let (bottom, sb) = number(cur)?;
                in_range(bottom, &sb, -MAX_MAGNITUDE, MAX_MAGNITUDE, "a cone bottom")?;
                let (top, st) = number(cur)?;
                in_range(top, &st, -MAX_MAGNITUDE, MAX_MAGNITUDE, "a cone top")?;
                let (bottom_radius, s) = number(cur)?;
                in_range(bottom_radius, &s, 0.0, MAX_MAGNITUDE, "a cone radius")?;
                let (top_radius, s) = number(cur)?;
                in_range(top_radius, &s, 0.0, MAX_MAGNITUDE, "a cone radius")?;
                *cone = Some(Cone { axis, bottom, top, bottom_radius, top_radius });
                Ok(())
            }
            "TRANSFORM" => {
                self.close_block();
                if self.transforms.len() >= MAX_TRANSFORMATIONS {
                    return Err(ParseError::new(span, format!("more than {MAX_TRANSFORMATIONS} transformations")));
                }
                let cur = &mut self.cur;
                let (probability, s) = number(cur)?;
                in_range(probability, &s, 0.0, MAX_MAGNITUDE, "a probability")?;
                let (last, _) = int_in(cur, 1, 255, "last allowed level")?;
                let mut dummy_from = None;
                if cur.eat_keyword("DUMMY") || cur.eat_keyword("dummy") {
                    cur.skip_trivia();
                    dummy_from = Some(if cur.peek().is_some_and(|c| c.is_ascii_digit()) {
                        int_in(cur, 1, 255, "dummy level")?.0 as u8
                    } else {
                        1
                    });
                }
                self.last_transform_span = span;
                self.block = Block::Transform(IfsTransformation {
                    probability,
                    last_level: last as u8,
                    dummy_from,
                    steps: Vec::new(),
                });
                Ok(())
            }
            _ => Err(ParseError::new(
                span,
                format!(
                    "unknown keyword `{word}` (NAME, RESOLUTION, ITERATIONS, TREEDEPTH, BRANCHDEPTH, DENSITYCLASSES, \
                     DEPTHCOLOR, PERTURB, HYPERVOLUME, DISPLACEMENT, POINTINIT, LINEINIT, CONDENSATION, CONE, \
                     TRANSFORM, TRANSLATE, ROTATE, SCALE, SHEAR)"
                ),
            )),
        }
    }

    fn finish(mut self) -> (Option<HypertreeDef>, Vec<Diagnostic>) {
        let end = self.src.text.len();
        let tree_depth = self.tree_depth.clone().map_or(6, |t| t.0);
        if let Some((b, s)) = &self.branch_depth
            && *b >= tree_depth
        {
            let msg = format!("branch depth {b} is not below tree depth {tree_depth}");
            self.errors.push(ParseError::new(s.clone(), msg));
        }
        if self.errors.is_empty() {
            if self.condensations.is_empty() {
                self.errors.push(ParseError::new(end..end, "a hypertree needs at least one CONDENSATION"));
            }
            if self.transforms.is_empty() {
                self.errors.push(ParseError::new(end..end, "a hypertree needs at least one TRANSFORM"));
            } else if self.transforms.iter().map(|t| t.probability).sum::<f32>() <= 0.0 {
                self.errors.push(ParseError::new(
                    self.last_transform_span.clone(),
                    "transformation probabilities sum to zero",
                ));
            }
            if !self.condensations.is_empty() && self.condensations.iter().map(|c| c.weight).sum::<f32>() <= 0.0 {
                self.errors.push(ParseError::new(end..end, "condensation weights sum to zero"));
            }
        }
        if !self.errors.is_empty() {
            let d = self.errors.into_iter().map(|e| self.src.diag(e.span, e.message)).collect();
            return (None, d);
        }
        let def = HypertreeDef {
            name: self.name.unwrap_or_else(|| file_stem(&self.src.name)),
            resolution: self.resolution.unwrap_or([100; 3]),
            iterations: self.iterations.unwrap_or(100_000),
            tree_depth,
            branch_depth: self.branch_depth.map_or(1.min(tree_depth - 1), |b| b.0),
            density_classes: self.classes.unwrap_or(64),
            depth_colors: self.colors,
            perturbation: self.perturb.unwrap_or(Perturbation { amplitude: [0.0; 3], frequency: DEFAULT_FREQUENCY }),
            hypervolume: self.hypervolume.unwrap_or([1.0; 3]),
            displacement: self.displacement.unwrap_or([0.5, 0.0, 0.5]),
            generator: self.generator.unwrap_or(Generator::Point([0.0; 3])),
            condensations: self.condensations,
            transformations: self.transforms,
        };
        match def.validate() {
            Ok(()) => (Some(def), Vec::new()),
            Err(e) => (None, vec![self.src.diag(end..end, format!("invalid hypertree: {e}"))]),
        }
    }
}
