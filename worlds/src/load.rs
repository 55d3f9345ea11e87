//! Loading species from files and from the embedded library, by format: `.species` (species text) or `.lsys`
//! (parametric L-system). Loading many files collects every file's diagnostics; one bad file never hides another.

use std::path::Path;

use canopy_protocol::SpeciesGraph;

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

/// Bytes of source text accepted in one species file.
pub const MAX_SOURCE_BYTES: u64 = 1 << 20;

/// Read and parse one file; an unreadable or oversized file is a diagnostic too.
pub fn load_file(path: &Path) -> (Option<SpeciesGraph>, Vec<Diagnostic>) {
    let name = path.display().to_string();
    let fail = |msg: String| (None, vec![SourceFile::new(name.clone(), "").diag(0..0, msg)]);
    match std::fs::metadata(path) {
        Ok(m) if m.len() > MAX_SOURCE_BYTES => return fail(format!("file of {} bytes exceeds {MAX_SOURCE_BYTES}", m.len())),
        Ok(_) => {}
        Err(e) => return fail(format!("cannot read: {e}")),
    }
    match std::fs::read_to_string(path) {
        Ok(text) => parse_source(&SourceFile::new(name, text)),
        Err(e) => fail(format!("cannot read: {e}")),
    }
}

/// Load a species named by a path, or else by a name in the embedded [`crate::library`].
pub fn load(name_or_path: &str) -> Result<SpeciesGraph, Diagnostics> {
    let path = Path::new(name_or_path);
    let (graph, diags) = if path.exists() || Format::of(name_or_path).is_some() && crate::library::find(name_or_path).is_none() {
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
