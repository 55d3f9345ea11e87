//! Loading species from files and from the embedded library, by format: `.species` (species text) or `.lsys`
//! (parametric L-system). Loading many files collects every file's diagnostics; one bad file never hides another.
//! [`check_source`] is `canopy species check`: parsing, then one amplification with the default parameters.

use std::path::Path;

use canopy_protocol::SpeciesGraph;

use crate::amplify::{Budget, Instance, amplify};
use crate::diag::{Diagnostic, Diagnostics, SourceFile};
use crate::lsystem::parse_lsystem;
use crate::species_text::parse_species;

/// The species source formats.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Format {
    /// The species text format (`.species`), see [`crate::species_text`].
    Species,
    /// The parametric L-system format (`.lsys`), see [`crate::lsystem`].
    LSystem,
}

impl Format {
    /// The format a file name's extension names, if any.
    pub fn of(name: &str) -> Option<Format> {
        if name.ends_with(".species") {
            Some(Format::Species)
        } else if name.ends_with(".lsys") {
            Some(Format::LSystem)
        } else {
            None
        }
    }
}

/// Parse a source in the format its name's extension names.
pub fn parse_source(src: &SourceFile) -> (Option<SpeciesGraph>, Vec<Diagnostic>) {
    match Format::of(&src.name) {
        Some(Format::Species) => parse_species(src),
        Some(Format::LSystem) => parse_lsystem(src),
        None => (None, vec![src.diag(0..0, "unknown species format: expected a `.species` or `.lsys` file")]),
    }
}

/// Bytes of source text accepted in one file of any text format (species, L-system, world manifest, hypertree,
/// hyperforest).
pub const MAX_SOURCE_BYTES: usize = 1 << 20;

/// Read one source file of at most [`MAX_SOURCE_BYTES`], named by its path: a regular file only (a device, FIFO or
/// socket is refused before it is opened; see [`crate::fsread`]). The error says why not, without the name (the
/// caller's diagnostic names the file).
pub fn read_source(path: &Path) -> Result<SourceFile, String> {
    let text = crate::fsread::read_text(path, MAX_SOURCE_BYTES as u64).map_err(|e| e.to_string())?;
    Ok(SourceFile::new(path.display().to_string(), text))
}

/// A diagnostic at the start of the file `path` (one that could not be read).
pub(crate) fn file_diag(path: &Path, message: String) -> Diagnostic {
    SourceFile::new(path.display().to_string(), "").diag(0..0, message)
}

/// Read and parse one file; an unreadable or oversized file is a diagnostic too.
pub fn load_file(path: &Path) -> (Option<SpeciesGraph>, Vec<Diagnostic>) {
    match read_source(path) {
        Ok(src) => parse_source(&src),
        Err(e) => (None, vec![file_diag(path, e)]),
    }
}

/// Load a species named by a path, or else by a name in the embedded [`crate::library`].
pub fn load(name_or_path: &str) -> Result<SpeciesGraph, Diagnostics> {
    let path = Path::new(name_or_path);
    let (graph, diags) =
        if path.exists() || Format::of(name_or_path).is_some() && crate::library::find(name_or_path).is_none() {
            load_file(path)
        } else if let Some(entry) = crate::library::find(name_or_path) {
            parse_source(&SourceFile::new(entry.file, entry.text))
        } else {
            let known: Vec<&str> = crate::library::SPECIES.iter().map(|e| e.name()).collect();
            let msg = format!("no such file, and no library species of that name (library: {})", known.join(", "));
            (None, vec![SourceFile::new(name_or_path, "").diag(0..0, msg)])
        };
    graph.ok_or(Diagnostics(diags))
}

/// The seed of the instance [`check_source`] amplifies (with the declared default parameters, at full detail).
pub const CHECK_SEED: u64 = 0;

/// A species that parsed and amplified once with its default parameters.
#[derive(Clone, Debug, PartialEq)]
pub struct Checked {
    /// The compiled species.
    pub graph: SpeciesGraph,
    /// Primitives of the instance with seed [`CHECK_SEED`], default parameters and full detail.
    pub primitives: usize,
}

/// Check a species source as `canopy species check` does: parse it, then amplify one instance — seed
/// [`CHECK_SEED`], the declared default parameters, full detail — under `budget` (the CLI passes
/// [`Budget::default`], the budget everything else amplifies under). A species that parses but cannot finish (over
/// the budget: runaway recursion, too many primitives; or a non-finite primitive) gets an error diagnostic at the
/// start of the file and no [`Checked`], like one that does not parse: a server would otherwise serve a species
/// that no client can amplify.
pub fn check_source(src: &SourceFile, budget: &Budget) -> (Option<Checked>, Vec<Diagnostic>) {
    let instance = Instance::new(CHECK_SEED);
    // An L-system reports a derivation too deep in its own terms (the derivation depth and the production), not
    // as nested separators its author never wrote.
    let (graph, mut diags, amplified) = match Format::of(&src.name) {
        Some(Format::LSystem) => {
            let (l, diags) = crate::lsystem::LSystem::parse(src);
            let amplified = l.as_ref().map(|l| l.amplify(&instance, budget).map_err(|e| e.to_string()));
            (l.map(|l| l.graph), diags, amplified)
        }
        _ => {
            let (graph, diags) = parse_source(src);
            let amplified = graph.as_ref().map(|g| amplify(g, &instance, budget).map_err(|e| e.to_string()));
            (graph, diags, amplified)
        }
    };
    let (Some(graph), Some(amplified)) = (graph, amplified) else { return (None, diags) };
    match amplified {
        Ok(stream) => (Some(Checked { graph, primitives: stream.primitives.len() }), diags),
        Err(e) => {
            diags.push(src.diag(
                0..0,
                format!(
                    "species `{}` cannot finish with its default parameters (seed {CHECK_SEED}, detail 0): {e}",
                    graph.name
                ),
            ));
            (None, diags)
        }
    }
}

/// [`check_source`] on a file; an unreadable or oversized file is a diagnostic too.
pub fn check_file(path: &Path, budget: &Budget) -> (Option<Checked>, Vec<Diagnostic>) {
    match read_source(path) {
        Ok(src) => check_source(&src, budget),
        Err(e) => (None, vec![file_diag(path, e)]),
    }
}
