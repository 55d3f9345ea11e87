//! The manifest parser: lines and blocks of the `.world` format (see [`crate::world`]) into a syntax tree with
//! spans. It checks what a line can tell alone (numbers, ranges, duplicates); what needs the whole world (species
//! names, bounds, terrain sizes) is checked when the world is built. Every problem is recorded and parsing goes on
//! with the next line, so one bad line never hides another.

use std::ops::Range;

use super::populate::{ParamValue, Ramp};
use super::{CELL_SIZE_RANGE, MAX_AVOID, MAX_TERRAIN_DEPTH};
use crate::diag::{Diagnostic, SourceFile};
use crate::text::{Cursor, ParseError, is_ident_continue};

/// A byte range in the manifest.
pub(crate) type Span = Range<usize>;

/// Where a species comes from.
#[derive(Clone, Debug)]
pub(crate) enum SourceRef {
    /// A name in the embedded library ([`crate::library`]).
    Library(String),
    /// A path relative to the manifest.
    File(String),
}

/// `species NAME SOURCE`.
#[derive(Clone, Debug)]
pub(crate) struct SpeciesDecl {
    pub name: String,
    pub name_span: Span,
    pub source: SourceRef,
    pub source_span: Span,
}

/// `NAME = VALUE` (an instance's parameter) or `param NAME = VALUE` (a terrain parameter).
#[derive(Clone, Debug)]
pub(crate) struct Setting {
    pub name: String,
    pub span: Span,
    pub value: f32,
}

/// The `terrain` block.
#[derive(Clone, Debug)]
pub(crate) struct TerrainDecl {
    pub span: Span,
    pub source: SourceRef,
    pub source_span: Span,
    pub tile: Option<(f32, Span)>,
    pub depth: Option<(u32, Span)>,
    pub seed: Option<(u64, Span)>,
    pub corners: Vec<(Vec<f32>, Span)>,
    pub params: Vec<Setting>,
}

/// `instance NAME at X Z [param=value …]`.
#[derive(Clone, Debug)]
pub(crate) struct InstanceDecl {
    pub species: String,
    pub species_span: Span,
    pub at: [f32; 2],
    pub at_span: Span,
    pub params: Vec<Setting>,
}

/// A `param NAME = …` line of a `scatter` block.
#[derive(Clone, Debug)]
pub(crate) struct ParamRule {
    pub name: String,
    pub span: Span,
    pub value: ParamValue,
}

/// An `avoid NAME DISTANCE` line.
#[derive(Clone, Debug)]
pub(crate) struct Avoid {
    pub species: String,
    pub span: Span,
    pub distance: f32,
}

/// A `scatter NAME { … }` block.
#[derive(Clone, Debug)]
pub(crate) struct ScatterDecl {
    pub species: String,
    pub species_span: Span,
    pub span: Span,
    pub spacing: Option<(f32, Span)>,
    pub density: Option<(f32, Span)>,
    pub altitude: Option<(Ramp, Span)>,
    pub slope: Option<(Ramp, Span)>,
    pub region: Option<([f32; 4], Span)>,
    pub avoid: Vec<Avoid>,
    pub params: Vec<ParamRule>,
}

/// A population statement, in file order.
#[derive(Clone, Debug)]
pub(crate) enum Population {
    /// One explicit instance.
    Instance(InstanceDecl),
    /// A distribution rule.
    Scatter(ScatterDecl),
    /// `fell NAME at X Z`: the instance of that species at exactly that position, placed by an earlier statement,
    /// is removed (a baked edit).
    Fell(InstanceDecl),
    /// `set NAME at X Z name=value …`: that instance takes these parameter values (a baked edit).
    Set(InstanceDecl),
}

/// The parsed manifest.
#[derive(Clone, Debug, Default)]
pub(crate) struct Manifest {
    pub name: Option<(String, Span)>,
    pub seed: Option<(u64, Span)>,
    pub bounds: Option<([f32; 4], Span)>,
    pub cell: Option<(f32, Span)>,
    pub terrain: Option<TerrainDecl>,
    pub species: Vec<SpeciesDecl>,
    pub populations: Vec<Population>,
    /// Statement keywords that appeared, valid or not (so a bad `cell` line is not also reported missing).
    pub seen: Vec<String>,
}

/// Parse a manifest, appending every problem to `diags`.
pub(crate) fn parse(src: &SourceFile, diags: &mut Vec<Diagnostic>) -> Manifest {
    let mut p = Parser { cur: Cursor::new(&src.text, false), m: Manifest::default(), errors: Vec::new() };
    loop {
        p.cur.skip_trivia();
        match p.cur.rest().chars().next() {
            None => break,
            Some('\n') => {
                p.cur.pos += 1;
                continue;
            }
            Some(_) => {}
        }
        let line_start = p.cur.pos;
        if let Err(e) = p.statement() {
            p.errors.push(e);
            p.recover(line_start);
        }
    }
    let mut found: Vec<Diagnostic> = p.errors.iter().map(|e| src.diag(e.span.clone(), e.message.clone())).collect();
    found.sort_by_key(|d| (d.line, d.col));
    diags.extend(found);
    p.m
}

struct Parser<'a> {
    cur: Cursor<'a>,
    m: Manifest,
    errors: Vec<ParseError>,
}

/// Record `v` in `slot` unless it is already set.
fn once<T>(slot: &mut Option<(T, Span)>, v: T, span: Span, what: &str, src: &str) -> Result<(), ParseError> {
    if let Some((_, first)) = slot {
        let (line, _) = SourceFile::new("", src).line_col(first.start);
        return Err(ParseError::new(span, format!("`{what}` given twice (first on line {line})")));
    }
    *slot = Some((v, span));
    Ok(())
}

impl Parser<'_> {
    /// After an error on the line starting at `line_start`: skip the rest of the line and, if the line opened a
    /// block, the block too.
    fn recover(&mut self, line_start: usize) {
        let line_end = self.cur.src[line_start..].find('\n').map_or(self.cur.src.len(), |i| line_start + i);
        self.cur.pos = self.cur.pos.max(line_start).min(line_end);
        self.cur.skip_line();
        let line = &self.cur.src[line_start..line_end];
        let code = line.split('#').next().unwrap_or("").trim_end();
        if code.ends_with('{') {
            while !self.cur.rest().is_empty() {
                let start = self.cur.pos;
                self.cur.skip_line();
                let l = self.cur.src[start..self.cur.pos].split('#').next().unwrap_or("").trim();
                if l == "}" {
                    break;
                }
            }
        }
    }

    /// The end of a statement: only trivia before the newline.
    fn eol(&mut self) -> Result<(), ParseError> {
        match self.cur.peek() {
            None | Some('\n') => Ok(()),
            Some(_) => Err(self.cur.unexpected("end of line")),
        }
    }

    fn at_eol(&mut self) -> bool {
        matches!(self.cur.peek(), None | Some('\n'))
    }

    fn ident(&mut self, what: &str) -> Result<(String, Span), ParseError> {
        self.cur.ident().map(|(w, s)| (w.to_string(), s)).ok_or_else(|| self.cur.unexpected(what))
    }

    /// A decimal number with an optional sign; `1..2` reads as `1`, `..`, `2`. A number run into a word (`2x`,
    /// `1.5.2`) is not one.
    fn number(&mut self, what: &str) -> Result<(f32, Span), ParseError> {
        self.cur.skip_trivia();
        let start = self.cur.pos;
        let Some(n) = self.cur.signed_number() else { return Err(self.cur.unexpected(what)) };
        let b = self.cur.rest().as_bytes();
        if b.first().is_some_and(|&c| is_ident_continue(c as char) || c == b'.' && b.get(1) != Some(&b'.')) {
            self.cur.pos = start;
            return Err(self.cur.unexpected(what));
        }
        n
    }

    /// A non-negative integer, decimal or `0x` hexadecimal, at most `max`.
    fn integer(&mut self, what: &str, max: u64) -> Result<(u64, Span), ParseError> {
        let Some((v, span)) = self.cur.integer() else { return Err(self.cur.unexpected(what)) };
        let Some(v) = v else {
            return Err(ParseError::new(span.clone(), format!("expected {what}, found `{}`", &self.cur.src[span])));
        };
        if v > max {
            return Err(ParseError::new(span, format!("{what} {v} is more than {max}")));
        }
        Ok((v, span))
    }

    /// A species source: a library name, or a quoted relative path.
    fn source(&mut self) -> Result<(SourceRef, Span), ParseError> {
        self.cur.skip_trivia();
        let start = self.cur.pos;
        if self.cur.eat("\"") {
            let rest = self.cur.rest();
            let end = rest.find(['"', '\n']).filter(|&i| rest.as_bytes()[i] == b'"');
            let Some(end) = end else {
                return Err(ParseError::new(start..start + 1, "unterminated string"));
            };
            let path = rest[..end].to_string();
            self.cur.pos += end + 1;
            if path.is_empty() {
                return Err(ParseError::new(start..self.cur.pos, "empty path"));
            }
            if path.starts_with('/') || path.starts_with('\\') || path.contains(':') {
                return Err(ParseError::new(start..self.cur.pos, "species paths are relative to the manifest"));
            }
            return Ok((SourceRef::File(path), start..self.cur.pos));
        }
        let (name, span) = self.ident("a library species name or a \"path\"")?;
        Ok((SourceRef::Library(name), span))
    }

    /// Four numbers `min x, min z, max x, max z` with min < max.
    fn rect(&mut self) -> Result<([f32; 4], Span), ParseError> {
        let (x0, s) = self.number("min x")?;
        let (z0, _) = self.number("min z")?;
        let (x1, _) = self.number("max x")?;
        let (z1, e) = self.number("max z")?;
        let span = s.start..e.end;
        if x0 >= x1 || z0 >= z1 {
            return Err(ParseError::new(span, "expected min x, min z, max x, max z with min < max"));
        }
        Ok(([x0, z0, x1, z1], span))
    }

    /// `[A [B]] .. [C [D]]`.
    fn ramp(&mut self) -> Result<(Ramp, Span), ParseError> {
        self.cur.skip_trivia();
        let start = self.cur.pos;
        let mut lower = Vec::new();
        while lower.len() < 2
            && !{
                self.cur.skip_trivia();
                self.cur.rest().starts_with("..")
            }
        {
            lower.push(self.number("a number or `..`")?.0);
        }
        self.cur.expect("..")?;
        let mut upper = Vec::new();
        while upper.len() < 2 && !self.at_eol() {
            upper.push(self.number("a number or end of line")?.0);
        }
        let span = start..self.cur.pos;
        let (a, b) = match lower[..] {
            [] => (f32::NEG_INFINITY, f32::NEG_INFINITY),
            [a] => (a, a),
            [a, b] => (a, b),
            _ => unreachable!("at most two"),
        };
        let (c, d) = match upper[..] {
            [] => (f32::INFINITY, f32::INFINITY),
            [c] => (c, c),
            [c, d] => (c, d),
            _ => unreachable!("at most two"),
        };
        if !(a <= b && b <= c && c <= d) {
            return Err(ParseError::new(span, "a ramp `A B .. C D` needs A <= B <= C <= D"));
        }
        Ok((Ramp { a, b, c, d }, span))
    }

    /// `NAME = VALUE`.
    fn setting(&mut self) -> Result<Setting, ParseError> {
        let (name, span) = self.ident("a parameter name")?;
        self.cur.expect("=")?;
        let (value, _) = self.number("a number")?;
        Ok(Setting { name, span, value })
    }

    /// Lines of a block up to its `}`, each handed to `line`; errors are recorded and the next line is parsed.
    /// A header error (no `{` at the end of the line) is returned, before any line of the block is read.
    fn block(
        &mut self,
        open: Span,
        mut line: impl FnMut(&mut Self, String, Span) -> Result<(), ParseError>,
    ) -> Result<(), ParseError> {
        self.cur.expect("{")?;
        self.eol()?;
        self.cur.skip_line();
        loop {
            self.cur.skip_trivia();
            match self.cur.rest().chars().next() {
                None => {
                    self.errors.push(ParseError::new(open, "block is not closed: expected `}` on a line of its own"));
                    return Ok(());
                }
                Some('\n') => {
                    self.cur.pos += 1;
                    continue;
                }
                Some(_) => {}
            }
            if self.cur.eat("}") {
                if let Err(e) = self.eol() {
                    self.errors.push(e);
                }
                self.cur.skip_line();
                return Ok(());
            }
            let result = self.ident("a block entry or `}`").and_then(|(w, s)| {
                line(self, w, s)?;
                self.eol()
            });
            if let Err(e) = result {
                self.errors.push(e);
            }
            self.cur.skip_line();
        }
    }

    fn statement(&mut self) -> Result<(), ParseError> {
        if self.cur.eat("}") {
            let p = self.cur.pos;
            return Err(ParseError::new(p - 1..p, "`}` without a block"));
        }
        let (word, span) = self.ident("a statement")?;
        if !self.m.seen.contains(&word) {
            self.m.seen.push(word.clone());
        }
        let src = self.cur.src;
        match word.as_str() {
            "world" => {
                let (name, nspan) = self.ident("a world name")?;
                self.eol()?;
                once(&mut self.m.name, name, nspan, "world", src)
            }
            "seed" => {
                let (seed, s) = self.integer("a seed", u64::MAX)?;
                self.eol()?;
                once(&mut self.m.seed, seed, s, "seed", src)
            }
            "bounds" => {
                let (r, s) = self.rect()?;
                self.eol()?;
                once(&mut self.m.bounds, r, s, "bounds", src)
            }
            "cell" => {
                let (v, s) = self.number("a cell size")?;
                self.eol()?;
                let (lo, hi) = CELL_SIZE_RANGE;
                if !(lo..=hi).contains(&v) || (v.to_bits() & 0x007f_ffff) != 0 {
                    return Err(ParseError::new(
                        s,
                        format!("the cell size must be a power of two from {lo} to {hi} metres"),
                    ));
                }
                once(&mut self.m.cell, v, s, "cell", src)
            }
            "species" => {
                let (name, name_span) = self.ident("a species name")?;
                let (source, source_span) = self.source()?;
                self.eol()?;
                if let Some(first) = self.m.species.iter().find(|s| s.name == name) {
                    let (line, _) = SourceFile::new("", src).line_col(first.name_span.start);
                    return Err(ParseError::new(
                        name_span,
                        format!("species `{name}` declared twice (first on line {line})"),
                    ));
                }
                self.m.species.push(SpeciesDecl { name, name_span, source, source_span });
                Ok(())
            }
            "instance" | "fell" | "set" => {
                let (species, species_span) = self.ident("a species name")?;
                if !self.cur.eat_keyword("at") {
                    return Err(self.cur.unexpected("`at`"));
                }
                let (x, xs) = self.number("x")?;
                let (z, zs) = self.number("z")?;
                let mut params = Vec::new();
                while !self.at_eol() {
                    params.push(self.setting()?);
                }
                let at = [x, z];
                let decl = InstanceDecl { species, species_span, at, at_span: xs.start..zs.end, params };
                let population = match word.as_str() {
                    "fell" if !decl.params.is_empty() => {
                        return Err(ParseError::new(decl.params[0].span.clone(), "`fell` takes no parameters"));
                    }
                    "fell" => Population::Fell(decl),
                    "set" if decl.params.is_empty() => {
                        return Err(ParseError::new(decl.at_span, "`set` needs at least one name=value"));
                    }
                    "set" => Population::Set(decl),
                    _ => Population::Instance(decl),
                };
                self.m.populations.push(population);
                Ok(())
            }
            "terrain" => {
                let (source, source_span) = self.source()?;
                if self.m.terrain.is_some() {
                    self.errors.push(ParseError::new(span.clone(), "`terrain` given twice"));
                    return self.block(span, |_, _, _| Ok(()));
                }
                let mut t = TerrainDecl {
                    span: span.start..source_span.end,
                    source,
                    source_span,
                    tile: None,
                    depth: None,
                    seed: None,
                    corners: Vec::new(),
                    params: Vec::new(),
                };
                self.block(span, |p, word, wspan| p.terrain_line(&mut t, word, wspan))?;
                self.m.terrain = Some(t);
                Ok(())
            }
            "scatter" => {
                let (species, species_span) = self.ident("a species name")?;
                let mut r = ScatterDecl {
                    species,
                    span: span.start..species_span.end,
                    species_span,
                    spacing: None,
                    density: None,
                    altitude: None,
                    slope: None,
                    region: None,
                    avoid: Vec::new(),
                    params: Vec::new(),
                };
                let errors = self.errors.len();
                self.block(span, |p, word, wspan| p.scatter_line(&mut r, word, wspan))?;
                // Missing, not merely wrong (a bad `spacing` line is reported already).
                if r.spacing.is_none() && self.errors.len() == errors {
                    self.errors.push(ParseError::new(r.span.clone(), "a `scatter` block needs a `spacing`"));
                }
                self.m.populations.push(Population::Scatter(r));
                Ok(())
            }
            _ => Err(ParseError::new(
                span,
                format!(
                    "unknown statement `{word}` (expected world, seed, bounds, cell, terrain, species, instance, scatter, fell or set)"
                ),
            )),
        }
    }

    fn terrain_line(&mut self, t: &mut TerrainDecl, word: String, span: Span) -> Result<(), ParseError> {
        let src = self.cur.src;
        match word.as_str() {
            "tile" => {
                let (v, s) = self.number("a tile size")?;
                if v <= 0.0 {
                    return Err(ParseError::new(s, "the tile size must be positive"));
                }
                once(&mut t.tile, v, s, "tile", src)
            }
            "depth" => {
                let (v, s) =
                    self.integer("a depth", u64::from(MAX_TERRAIN_DEPTH.max(super::fractal::MAX_FRACTAL_DEPTH)))?;
                once(&mut t.depth, v as u32, s, "depth", src)
            }
            "seed" => {
                let (v, s) = self.integer("a seed", u64::MAX)?;
                once(&mut t.seed, v, s, "seed", src)
            }
            "corners" => {
                let mut row = Vec::new();
                let start = self.cur.pos;
                while !self.at_eol() {
                    row.push(self.number("a corner height")?.0);
                }
                if row.is_empty() {
                    return Err(self.cur.unexpected("corner heights"));
                }
                t.corners.push((row, span.start.min(start)..self.cur.pos));
                Ok(())
            }
            "param" => {
                let s = self.setting()?;
                if let Some(first) = t.params.iter().find(|p| p.name == s.name) {
                    let (line, _) = SourceFile::new("", src).line_col(first.span.start);
                    return Err(ParseError::new(s.span, format!("`{}` set twice (first on line {line})", s.name)));
                }
                t.params.push(s);
                Ok(())
            }
            _ => Err(ParseError::new(
                span,
                format!("unknown terrain entry `{word}` (expected tile, depth, seed, corners or param)"),
            )),
        }
    }

    fn scatter_line(&mut self, r: &mut ScatterDecl, word: String, span: Span) -> Result<(), ParseError> {
        let src = self.cur.src;
        match word.as_str() {
            "spacing" => {
                let (v, s) = self.number("a spacing in metres")?;
                if v <= 0.0 {
                    return Err(ParseError::new(s, "the spacing must be positive"));
                }
                once(&mut r.spacing, v, s, "spacing", src)
            }
            "density" => {
                let (v, s) = self.number("a density")?;
                if !(0.0..=1.0).contains(&v) {
                    return Err(ParseError::new(s, "the density must be between 0 and 1"));
                }
                once(&mut r.density, v, s, "density", src)
            }
            "altitude" => {
                let (ramp, s) = self.ramp()?;
                once(&mut r.altitude, ramp, s, "altitude", src)
            }
            "slope" => {
                let (ramp, s) = self.ramp()?;
                once(&mut r.slope, ramp, s, "slope", src)
            }
            "region" => {
                let (rect, s) = self.rect()?;
                once(&mut r.region, rect, s, "region", src)
            }
            "avoid" => {
                let (species, sspan) = self.ident("a species name")?;
                let (distance, ds) = self.number("a distance in metres")?;
                if !(distance > 0.0 && distance <= MAX_AVOID) {
                    return Err(ParseError::new(ds, format!("the distance must be above 0 and at most {MAX_AVOID} m")));
                }
                r.avoid.push(Avoid { species, span: sspan, distance });
                Ok(())
            }
            "param" => {
                let (name, nspan) = self.ident("a parameter name")?;
                self.cur.expect("=")?;
                let (lo, lspan) = self.number("a number")?;
                let value = if self.cur.eat("..") {
                    let (hi, hspan) = self.number("the upper end of the range")?;
                    if hi < lo {
                        return Err(ParseError::new(lspan.start..hspan.end, "the range must not decrease"));
                    }
                    let step = if self.cur.eat_keyword("step") {
                        let (step, s) = self.number("a step")?;
                        if step <= 0.0 {
                            return Err(ParseError::new(s, "the step must be positive"));
                        }
                        Some(step)
                    } else {
                        None
                    };
                    ParamValue::Range { lo, hi, step }
                } else {
                    ParamValue::Constant(lo)
                };
                if let Some(first) = r.params.iter().find(|p| p.name == name) {
                    let (line, _) = SourceFile::new("", src).line_col(first.span.start);
                    return Err(ParseError::new(nspan, format!("`{name}` set twice (first on line {line})")));
                }
                r.params.push(ParamRule { name, span: nspan, value });
                Ok(())
            }
            _ => Err(ParseError::new(
                span,
                format!(
                    "unknown scatter entry `{word}` (expected spacing, density, altitude, slope, region, avoid or param)"
                ),
            )),
        }
    }
}
