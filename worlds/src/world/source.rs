//! Where a manifest's species files come from: the filesystem (relative to the manifest), nowhere (a manifest
//! parsed without a directory may name library species only), or the embedded copy of `worlds/` that the default
//! world is compiled with.

use std::path::Path;

use canopy_protocol::SpeciesGraph;

use crate::load::read_source;

/// Reads the files a manifest names by relative path.
pub(crate) trait Resolver {
    /// The display name and text of the file at `rel`, relative to the manifest, or why not.
    fn read(&self, rel: &str) -> Result<(String, String), String>;

    /// A graph already compiled for this statement, used in place of its source (a world function's species
    /// come from the welcome's table); `None` to load the source.
    fn compiled(&self, statement: Statement) -> Option<(SpeciesGraph, String)> {
        let _ = statement;
        None
    }

    /// Whether every species must come from [`Resolver::compiled`] (a world function: no file, no library).
    fn compiled_only(&self) -> bool {
        false
    }
}

/// A statement of a manifest that names a species.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Statement {
    /// The `i`-th `species` statement (species id `i`).
    Species(usize),
    /// The `terrain` statement.
    Terrain,
}

/// A world function's species: statement `i` is the table's species `i`, the terrain the welcome's terrain graph;
/// no file is read.
pub(crate) struct Table<'a> {
    /// The species table, by id.
    pub species: &'a [SpeciesGraph],
    /// The terrain species, if the world has one.
    pub terrain: Option<&'a SpeciesGraph>,
}

impl Resolver for Table<'_> {
    fn read(&self, rel: &str) -> Result<(String, String), String> {
        Err(format!("cannot read `{rel}`: a world function takes its species from the species table"))
    }

    fn compiled(&self, statement: Statement) -> Option<(SpeciesGraph, String)> {
        match statement {
            Statement::Species(i) => self.species.get(i).map(|g| (g.clone(), format!("table:{i}"))),
            Statement::Terrain => self.terrain.map(|g| (g.clone(), "table:terrain".to_string())),
        }
    }

    fn compiled_only(&self) -> bool {
        true
    }
}

/// Files relative to a directory on disk.
pub(crate) struct Files<'a> {
    /// The manifest's directory.
    pub base: &'a Path,
}

impl Resolver for Files<'_> {
    fn read(&self, rel: &str) -> Result<(String, String), String> {
        let path = self.base.join(rel);
        let src = read_source(&path).map_err(|e| format!("`{}`: {e}", path.display()))?;
        Ok((src.name, src.text))
    }
}

/// No files at all.
pub(crate) struct NoFiles;

impl Resolver for NoFiles {
    fn read(&self, rel: &str) -> Result<(String, String), String> {
        Err(format!("cannot read `{rel}`: a manifest parsed without a directory may name library species only"))
    }
}

/// The embedded copy of `worlds/`: the species library (`species/…`) and the default world's directory.
pub(crate) struct Embedded {
    /// The manifest's directory under `worlds/`.
    pub dir: &'static str,
}

/// Files of `worlds/` compiled in besides the species library, by path under `worlds/`.
const EMBEDDED_FILES: &[(&str, &str)] =
    &[("forest/forest.world", super::DEFAULT_WORLD), ("highlands/highlands.world", super::HIGHLANDS_WORLD)];

impl Resolver for Embedded {
    fn read(&self, rel: &str) -> Result<(String, String), String> {
        let path =
            normalize(self.dir, rel).ok_or_else(|| format!("`{rel}` leaves the embedded `worlds/` directory"))?;
        let text = match path.strip_prefix("species/") {
            Some(file) => crate::library::SPECIES.iter().find(|e| e.file == file).map(|e| e.text),
            None => EMBEDDED_FILES.iter().find(|(p, _)| *p == path).map(|(_, t)| *t),
        };
        text.map(|t| (format!("worlds/{path}"), t.to_string()))
            .ok_or_else(|| format!("cannot read `{rel}`: `worlds/{path}` is not embedded"))
    }
}

/// `dir/rel` with `.` and `..` resolved, or `None` if it climbs out of the root.
fn normalize(dir: &str, rel: &str) -> Option<String> {
    let mut parts: Vec<&str> = Vec::new();
    for part in dir.split('/').chain(rel.split(['/', '\\'])) {
        match part {
            "" | "." => {}
            ".." => {
                parts.pop()?;
            }
            p => parts.push(p),
        }
    }
    Some(parts.join("/"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn embedded_paths_resolve_like_files() {
        assert_eq!(normalize("forest", "../species/conifer.species").as_deref(), Some("species/conifer.species"));
        assert_eq!(normalize("forest", "./a/../b.species").as_deref(), Some("forest/b.species"));
        assert_eq!(normalize("forest", "../../x"), None);
        let e = Embedded { dir: "forest" };
        let (name, text) = e.read("../species/conifer.species").unwrap();
        assert_eq!(name, "worlds/species/conifer.species");
        assert!(text.contains("species conifer"));
        assert!(e.read("../species/nothing.species").unwrap_err().contains("not embedded"));
        assert!(e.read("../../etc/passwd").unwrap_err().contains("leaves"));
    }
}
