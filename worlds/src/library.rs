//! The embedded species library: the files under `worlds/species/`, compiled into the binary so a fresh machine
//! (or a wasm build) has every species without touching the filesystem.

use canopy_protocol::SpeciesGraph;

use crate::diag::{Diagnostics, SourceFile};
use crate::load::parse_source;

/// One embedded species source file.
#[derive(Clone, Copy, Debug)]
pub struct LibraryEntry {
    /// File name under `worlds/species/`.
    pub file: &'static str,
    /// The source text.
    pub text: &'static str,
}

impl LibraryEntry {
    /// The short name: the file name without its extension.
    pub fn name(&self) -> &'static str {
        self.file.split('.').next().unwrap_or(self.file)
    }

    /// Parse the entry (library files are tested to parse without diagnostics).
    pub fn load(&self) -> Result<SpeciesGraph, Diagnostics> {
        let (g, d) = parse_source(&SourceFile::new(self.file, self.text));
        g.ok_or(Diagnostics(d))
    }
}

macro_rules! entries {
    ($($file:literal),* $(,)?) => {
        &[$(LibraryEntry { file: $file, text: include_str!(concat!("../species/", $file)) }),*]
    };
}

/// Every embedded species, in a fixed order.
pub const SPECIES: &[LibraryEntry] = entries![
    "worm.species",
    "monopodial.species",
    "conifer.species",
    "terrain.species",
    "morpho.species",
    "bush.lsys",
    "stochastic_weed.lsys",
];

/// Find an entry by short name (`worm`) or file name (`worm.species`).
pub fn find(name: &str) -> Option<&'static LibraryEntry> {
    SPECIES.iter().find(|e| e.file == name || e.name() == name)
}
