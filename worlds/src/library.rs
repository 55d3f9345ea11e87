//! The embedded species library: the files under `worlds/species/`, compiled into the binary so a fresh machine
//! (or a wasm build) has every species without touching the filesystem.

use std::marker::PhantomData;

use canopy_protocol::SpeciesGraph;

use crate::diag::{Diagnostics, SourceFile};
use crate::load::parse_source;

/// One embedded source file; `K` says what it holds ([`SpeciesFile`], [`crate::hypertree::library::HypertreeFile`])
/// and so what its `load` parses.
#[derive(Clone, Copy, Debug)]
pub struct EmbeddedFile<K> {
    /// File name under its directory of `worlds/`.
    pub file: &'static str,
    /// The source text.
    pub text: &'static str,
    kind: PhantomData<K>,
}

impl<K> EmbeddedFile<K> {
    /// An entry for `file` with its text.
    pub const fn new(file: &'static str, text: &'static str) -> EmbeddedFile<K> {
        EmbeddedFile { file, text, kind: PhantomData }
    }

    /// The short name: the file name without its extension.
    pub fn name(&self) -> &'static str {
        self.file.split('.').next().unwrap_or(self.file)
    }

    /// The entry as a source file named by its file name.
    pub fn source(&self) -> SourceFile {
        SourceFile::new(self.file, self.text)
    }
}

/// Find an entry of `files` by short name (`worm`) or file name (`worm.species`).
pub fn find_in<K>(files: &'static [EmbeddedFile<K>], name: &str) -> Option<&'static EmbeddedFile<K>> {
    files.iter().find(|e| e.file == name || e.name() == name)
}

/// Embedded files: `embedded!["DIR/" => "a.x", "b.x"]`, each `include_str!("DIR/a.x")` relative to the calling file.
macro_rules! embedded {
    ($dir:literal => $($file:literal),* $(,)?) => {
        &[$($crate::library::EmbeddedFile::new($file, include_str!(concat!($dir, $file)))),*]
    };
}
pub(crate) use embedded;

/// What a [`LibraryEntry`] holds: species source (`.species` or `.lsys`).
#[derive(Clone, Copy, Debug)]
pub enum SpeciesFile {}

/// One embedded species source file.
pub type LibraryEntry = EmbeddedFile<SpeciesFile>;

impl LibraryEntry {
    /// Parse the entry (library files are tested to parse without diagnostics).
    pub fn load(&self) -> Result<SpeciesGraph, Diagnostics> {
        let (g, d) = parse_source(&self.source());
        g.ok_or(Diagnostics(d))
    }
}

/// Every embedded species, in a fixed order.
pub const SPECIES: &[LibraryEntry] = embedded![
    "../species/" =>
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
    find_in(SPECIES, name)
}
