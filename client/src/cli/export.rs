//! `canopy species export`: one instance or a grove as a `.glb`, streamed (issue 35). The instances are made once
//! to lay the file out and again to write it ([`canopy_worlds::gltf::stream`]), so memory holds one instance's
//! meshes whatever the grove; the size is estimated from the first instance (a grove estimated more than 10% over
//! the limit is refused at once) and checked exactly before a byte is written; the bytes go into a temporary file
//! beside the output, renamed over it only once complete.

use std::io::{BufWriter, Write};
use std::path::Path;
use std::process::ExitCode;

use anyhow::{Context, bail};
use canopy_editor::EditorError;
use canopy_editor::save::{check_target, replace_with};
use canopy_harness::numbers::group;
use canopy_worlds::amplify::Instance;
use canopy_worlds::gltf::{GlbError, GlbLayout, GlbStreamError, MAX_GLB_BYTES, Node, SizeCheck, lay_out};
use canopy_worlds::mesh::{MeshOptions, mesh};

use super::InstanceConfig;
use super::nearfield;

/// A grove to export: instances of one species on a square grid.
struct Grove<'a> {
    cfg: &'a InstanceConfig,
    near: &'a nearfield::NearFieldArgs,
    /// Instances on a side of the grid.
    side: u64,
    /// Grid spacing, metres.
    spacing: f32,
}

impl Grove<'_> {
    /// The nodes of instance `i` (seed `seed + i`): one mesh, or its near-field parts with the LOD levels beside the
    /// tree along +X, coarser further out. `notes` prints what the near field has to say (once, on the first pass).
    fn instance(&self, i: u64, notes: bool) -> anyhow::Result<Vec<Node<'static>>> {
        let cfg = self.cfg;
        let inst = Instance { seed: cfg.instance.seed.wrapping_add(i), ..cfg.instance.clone() };
        let stream = cfg.amplify(&inst)?;
        let at = [(i % self.side) as f32 * self.spacing, 0.0, (i / self.side) as f32 * self.spacing];
        let plan = self.near.plan(&cfg.graph, &inst)?;
        let name = format!("{}-{}", cfg.graph.name, inst.seed);
        if matches!(plan.mode, nearfield::Mode::Primitives) && plan.bark.is_none() {
            return Ok(vec![Node::owned(name, mesh(&stream, &MeshOptions::for_detail(inst.detail)), at)]);
        }
        let nearfield::InstanceMeshes { parts, not_one_body } =
            nearfield::instance_meshes(&plan, &stream, inst.detail)?;
        if let (Some(why), true) = (not_one_body, notes) {
            eprintln!("note: {name}: not one body: {why}");
        }
        let width = parts.first().map(|(_, m)| m.bounds()).map_or(1.0, |(lo, hi)| (hi[0] - lo[0]).max(1.0));
        Ok(parts
            .into_iter()
            .map(|(part, m)| {
                let level = part.strip_prefix("lod").and_then(|k| k.parse::<f32>().ok()).unwrap_or(0.0);
                Node::owned(format!("{name}-{part}"), m, [at[0] + level * width * 1.2, at[1], at[2]])
            })
            .collect())
    }
}

/// `canopy species export`: `grove` instances (seeds seed, seed + 1, …) `spacing` metres apart, at most `max_bytes`
/// (and [`MAX_GLB_BYTES`]); `check` says whether the first instance's estimate may refuse the grove.
pub(super) fn export(
    cfg: &InstanceConfig,
    out: &Path,
    grove: u32,
    spacing: f32,
    max_bytes: u64,
    check: SizeCheck,
    near: &nearfield::NearFieldArgs,
) -> anyhow::Result<ExitCode> {
    if grove == 0 || grove > 10_000 {
        bail!("--grove must be between 1 and 10000, got {grove}");
    }
    let side = f64::from(grove).sqrt().ceil() as u64;
    let g = Grove { cfg, near, side, spacing };
    let layout = export_grove(out, grove, max_bytes, check, |i, first| g.instance(i, first))?;
    println!(
        "wrote {} ({} instance(s), {} triangles, {} bytes)",
        out.display(),
        grove,
        group(layout.triangles()),
        group(layout.bytes())
    );
    Ok(ExitCode::SUCCESS)
}

/// Lay out and write the `.glb` of `grove` instances: `instance(i, first_pass)` makes instance `i`'s nodes, on
/// the first pass (laying out) and again on the second (writing). Nothing is written when the file would be over
/// `max_bytes`, and `out` is left as it was when anything fails.
fn export_grove(
    out: &Path,
    grove: u32,
    max_bytes: u64,
    check: SizeCheck,
    mut instance: impl FnMut(u64, bool) -> anyhow::Result<Vec<Node<'static>>>,
) -> anyhow::Result<GlbLayout> {
    // Refused before anything is made: the file is written beside it and renamed over it, which would replace a
    // directory, a link or a device, not write into it.
    check_target(out).map_err(|e| refused(out, e))?;
    let limit = max_bytes.min(MAX_GLB_BYTES);
    let layout = lay_out(u64::from(grove), limit, check, |i| instance(i, true)).map_err(|e| failed(out, grove, e))?;
    write_streamed(out, grove, &layout, |i| instance(i, false))?;
    Ok(layout)
}

/// A failure to write `out`, in the command's terms.
fn refused(out: &Path, e: EditorError) -> anyhow::Error {
    match e {
        EditorError::NotAFile { kind, .. } => {
            anyhow::anyhow!("{}: {kind}: refusing to write over it (export writes regular files only)", out.display())
        }
        e => e.into(),
    }
}

/// Write `layout` to `out` through a temporary file in its directory, renamed over `out` once complete (and
/// flushed to disk); on any failure the temporary file is removed and `out` is untouched.
fn write_streamed(
    out: &Path,
    grove: u32,
    layout: &GlbLayout,
    mut item: impl FnMut(u64) -> anyhow::Result<Vec<Node<'static>>>,
) -> anyhow::Result<()> {
    if let Some(dir) = out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    }
    let mut failure = None;
    let written = replace_with(out, |file| {
        let mut w = BufWriter::with_capacity(1 << 20, file);
        match layout.write(&mut w, &mut item) {
            Ok(()) => w.flush(),
            Err(GlbStreamError::Write(e)) => Err(e),
            Err(e) => {
                let why = std::io::Error::other(e.to_string());
                failure = Some(e);
                Err(why)
            }
        }
    });
    match (written, failure) {
        (_, Some(e)) => Err(failed(out, grove, e)),
        (Err(e), None) => Err(refused(out, e)),
        (Ok(()), None) => Ok(()),
    }
}

/// The error of a grove that was not written, in the command's terms.
fn failed(out: &Path, grove: u32, e: GlbStreamError<anyhow::Error>) -> anyhow::Error {
    match e {
        GlbStreamError::TooLarge { error: error @ GlbError::Estimated { .. }, .. } => {
            too_large(out, error, &format!("estimated from the first of {grove} instances"), ", --no-estimate")
        }
        GlbStreamError::TooLarge { made, items, error } if made < items => {
            too_large(out, error, &format!("the first {made} of {grove} instances"), "")
        }
        GlbStreamError::TooLarge { error, .. } => too_large(out, error, &format!("{grove} instance(s)"), ""),
        GlbStreamError::Source { error, .. } => error,
        e @ (GlbStreamError::Changed { .. } | GlbStreamError::Write(_)) => {
            anyhow::anyhow!("not writing {}: {e}", out.display())
        }
    }
}

/// The error for an export over the size limit: what was too large, and the flags that make it smaller.
fn too_large(out: &Path, err: GlbError, what: &str, more: &str) -> anyhow::Error {
    anyhow::anyhow!(
        "not writing {}: {what}: {err} (flags: a smaller --grove, a higher --detail, --continuous --lod N{more})",
        out.display()
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use canopy_worlds::gltf::parse_glb_header;

    /// The instances of `species` (a library name) on an 8 m grid, with their default near-field options.
    fn config(species: &str) -> InstanceConfig {
        let args = super::super::InstanceArgs {
            species: species.into(),
            seed: 1,
            detail: 0,
            params: Vec::new(),
            max_primitives: canopy_worlds::amplify::Budget::default().max_primitives,
            max_steps: canopy_worlds::amplify::Budget::default().max_steps,
        };
        args.config().expect("a library species")
    }

    fn entries(dir: &Path) -> Vec<String> {
        let mut v: Vec<String> = std::fs::read_dir(dir)
            .expect("lists")
            .map(|e| e.expect("entry").file_name().to_string_lossy().into())
            .collect();
        v.sort();
        v
    }

    #[test]
    fn the_issue_grove_over_4_gib_is_refused_after_meshing_one_tree() {
        // Issue 35: `canopy species export monopodial --grove 100` meshed 90 trees (4.5 GB) before refusing.
        let dir = tempfile::tempdir().expect("temp dir");
        let out = dir.path().join("g.glb");
        let (cfg, near) = (config("monopodial"), nearfield::NearFieldArgs::default());
        let g = Grove { cfg: &cfg, near: &near, side: 10, spacing: 8.0 };
        let mut made = Vec::new();
        let e = export_grove(&out, 100, MAX_GLB_BYTES, SizeCheck::Estimate, |i, first| {
            made.push((i, first));
            g.instance(i, first)
        })
        .expect_err("over 4 GiB");
        assert_eq!(made, [(0, true)], "one tree meshed");
        let msg = e.to_string();
        assert!(msg.contains("estimated from the first of 100 instances") && msg.contains("about"), "{msg}");
        assert!(msg.contains("4294967295") && msg.contains("--no-estimate"), "{msg}");
        assert!(entries(dir.path()).is_empty(), "nothing written: {:?}", entries(dir.path()));
    }

    #[test]
    fn a_grove_is_written_by_two_passes_and_a_failure_leaves_the_old_file_whole() {
        let dir = tempfile::tempdir().expect("temp dir");
        let out = dir.path().join("grove.glb");
        std::fs::write(&out, b"the old file").expect("write");
        let (cfg, near) = (config("worm"), nearfield::NearFieldArgs::default());
        let g = Grove { cfg: &cfg, near: &near, side: 2, spacing: 8.0 };

        // The second pass fails at the third instance, half-way through the data.
        let mut passes = Vec::new();
        let e = export_grove(&out, 4, MAX_GLB_BYTES, SizeCheck::Estimate, |i, first| {
            passes.push((i, first));
            if !first && i == 2 { Err(anyhow::anyhow!("amplification failed")) } else { g.instance(i, first) }
        })
        .expect_err("fails");
        assert_eq!(e.to_string(), "amplification failed");
        assert_eq!(passes.iter().filter(|p| p.1).count(), 4, "all four laid out");
        assert_eq!(passes.iter().filter(|p| !p.1).count(), 3, "the second pass stopped at the third");
        assert_eq!(std::fs::read(&out).expect("reads"), b"the old file");
        assert_eq!(entries(dir.path()), ["grove.glb"], "the temporary file is removed");

        // A second pass that makes other meshes than the first stops too.
        let e = export_grove(&out, 4, MAX_GLB_BYTES, SizeCheck::Estimate, |i, first| {
            g.instance(i ^ u64::from(!first), first)
        })
        .expect_err("changed");
        assert!(e.to_string().contains("differs from the first pass"), "{e}");
        assert_eq!(std::fs::read(&out).expect("reads"), b"the old file");
        assert_eq!(entries(dir.path()), ["grove.glb"]);

        // Both passes the same: the file is replaced, and it is the grove.
        let layout =
            export_grove(&out, 4, MAX_GLB_BYTES, SizeCheck::Estimate, |i, first| g.instance(i, first)).expect("writes");
        let bytes = std::fs::read(&out).expect("reads");
        assert_eq!(bytes.len() as u64, layout.bytes());
        let (json, _) = parse_glb_header(&bytes).expect("a GLB");
        let names: Vec<&str> = json["nodes"].as_array().unwrap().iter().map(|n| n["name"].as_str().unwrap()).collect();
        assert_eq!(names, ["Worm-1", "Worm-2", "Worm-3", "Worm-4"]);
        assert_eq!(json["nodes"][3]["translation"].to_string(), "[8.0,0.0,8.0]");
        assert_eq!(entries(dir.path()), ["grove.glb"]);
    }

    #[test]
    fn an_output_that_is_not_a_regular_file_is_refused_before_meshing() {
        let dir = tempfile::tempdir().expect("temp dir");
        let e = export_grove(dir.path(), 1, MAX_GLB_BYTES, SizeCheck::Estimate, |_, _| panic!("nothing is meshed"))
            .expect_err("a directory");
        assert!(e.to_string().contains("a directory: refusing to write over it"), "{e}");
    }
}
