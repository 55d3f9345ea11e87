//! `canopy world plant|fell|set|cell`: change a running server's world as an editor, or look at one cell as a
//! client receives it. Each connects like any client (the area of interest is the cell concerned), fetches the
//! species table's programs to resolve species and parameter names, and prints what the server answered: the
//! instance's id and the cell's new version.

use std::process::ExitCode;
use std::time::Duration;

use anyhow::{Context, bail};
use canopy_client::state::Event;
use canopy_client::{ClientError, Connection};
use canopy_protocol::aoi::Viewpoint;
use canopy_protocol::edit::{EditOp, EditOutcome};
use canopy_protocol::{CellCoord, InstanceId, SpeciesGraph};
use clap::Args;

/// How to reach the server, and as whom.
#[derive(Args, Debug, Clone)]
pub(super) struct ServerArgs {
    #[command(flatten)]
    connect: super::ConnectArgs,
    /// The editor token (64 hexadecimal digits, as `canopy-server --add-editor` printed it); also read from
    /// `CANOPY_TOKEN`.
    #[arg(long, env = "CANOPY_TOKEN", hide_env_values = true)]
    token: Option<String>,
    /// How long to wait for the server, seconds.
    #[arg(long, default_value_t = 20.0)]
    timeout: f64,
}

/// An instance id: the number `canopy` prints, or `X:Z:INDEX` (cell and index in the cell).
pub(super) fn parse_id(s: &str) -> Result<InstanceId, String> {
    if let Ok(n) = s.parse::<u64>() {
        return Ok(InstanceId(n));
    }
    let parts: Vec<&str> = s.split(':').collect();
    let [x, z, i] = parts[..] else { return Err(format!("`{s}`: expected an id number or X:Z:INDEX")) };
    let num = |p: &str| p.trim().parse::<i64>().map_err(|e| format!("`{p}`: {e}"));
    let (x, z, i) = (num(x)?, num(z)?, num(i)?);
    let cell = CellCoord::new(
        i32::try_from(x).map_err(|_| format!("{x} is out of range"))?,
        i32::try_from(z).map_err(|_| format!("{z} is out of range"))?,
    );
    let index = u16::try_from(i).map_err(|_| format!("index {i} is out of range"))?;
    InstanceId::new(cell, index).ok_or_else(|| format!("cell ({x}, {z}) is beyond the cells ids can name"))
}

/// `NAME=VALUE` (a parameter name or slot number, and a finite number).
pub(super) fn parse_param(s: &str) -> Result<(String, f32), String> {
    let (k, v) = s.split_once('=').ok_or_else(|| format!("`{s}`: expected NAME=VALUE"))?;
    let v: f32 = v.trim().parse().map_err(|e| format!("`{v}`: {e}"))?;
    if !v.is_finite() || k.trim().is_empty() {
        return Err(format!("`{s}`: expected NAME=VALUE with a finite value"));
    }
    Ok((k.trim().to_owned(), v))
}

/// How an instance id reads: `X:Z:INDEX (N)`.
pub(super) fn show_id(id: InstanceId) -> String {
    let c = id.cell();
    format!("{}:{}:{} ({})", c.x, c.z, id.index(), id.0)
}

/// A connected client for one command, its area of interest around `at`.
struct Client {
    rt: tokio::runtime::Runtime,
    conn: Connection,
    timeout: Duration,
}

impl Client {
    fn connect(
        args: &ServerArgs,
        at: impl Fn(&canopy_protocol::messages::Welcome) -> [f32; 2],
    ) -> anyhow::Result<Client> {
        let trust = args.connect.trust()?;
        let edges = args.connect.edges();
        let mut cfg = args.connect.config(&edges, trust);
        cfg.client_name = "canopy-world".into();
        let timeout = Duration::from_secs_f64(args.timeout.clamp(0.1, 3600.0));
        cfg.timeout = timeout;
        cfg.token = match &args.token {
            Some(t) => Some(canopy_server::session::unhex(t.trim()).context("--token: expected hexadecimal digits")?),
            None => None,
        };
        let rt = tokio::runtime::Builder::new_current_thread().enable_all().build()?;
        let conn = rt.block_on(async {
            let endpoint = canopy_client::net::endpoint(canopy_client::net::loopback_for(edges.first()))?;
            let mut conn = Connection::connect_any(&endpoint, &cfg, None, |w| {
                // A radius of a metre: the cell under the point, and what the server's rules add.
                Viewpoint::at(1, at(w), 1.0)
            })
            .await?;
            conn.fetch_all_species(timeout).await?;
            conn.wait_complete(timeout).await?;
            Ok::<_, ClientError>(conn)
        })?;
        Ok(Client { rt, conn, timeout })
    }

    fn species(&self, id: u8) -> &SpeciesGraph {
        self.conn.state().species(id).expect("every species fetched")
    }

    /// A species by name or number.
    fn species_id(&self, name: &str) -> anyhow::Result<u8> {
        let n = self.conn.welcome().species.len();
        if let Ok(i) = name.parse::<u8>()
            && usize::from(i) < n
        {
            return Ok(i);
        }
        let names: Vec<&str> = (0..n).map(|i| self.species(i as u8).name.as_str()).collect();
        match names.iter().position(|s| *s == name) {
            Some(i) => Ok(i as u8),
            None => bail!("the world has no species `{name}`; it has {}", names.join(", ")),
        }
    }

    /// Parameters by name or slot number, sorted by slot.
    fn params(&self, species: u8, params: &[(String, f32)]) -> anyhow::Result<Vec<(u16, f32)>> {
        let g = self.species(species);
        let mut out = Vec::new();
        for (k, v) in params {
            // A slot number must be a parameter's too: working values are the species' own.
            let slot = match k.parse::<u16>() {
                Ok(s) if g.is_parameter(s) => s,
                _ => g.parameter_slot(k).map_err(|why| anyhow::anyhow!(why))?,
            };
            out.retain(|(s, _)| *s != slot);
            out.push((slot, *v));
        }
        out.sort_by_key(|p| p.0);
        Ok(out)
    }

    /// Send the edit and wait for its answer (and for the cell to show it).
    fn edit(&mut self, op: EditOp) -> anyhow::Result<ExitCode> {
        let timeout = self.timeout;
        let conn = &mut self.conn;
        let outcome = self.rt.block_on(async {
            let request = conn.edit(op).await?;
            let deadline = tokio::time::Instant::now() + timeout;
            loop {
                match tokio::time::timeout_at(deadline, conn.next_event()).await {
                    Ok(Ok(Event::EditResult(r))) if r.request == request => return Ok::<_, anyhow::Error>(r.outcome),
                    Ok(Ok(_)) => {}
                    Ok(Err(e)) => return Err(e.into()),
                    Err(_) => bail!("no answer from the server within {timeout:?}"),
                }
            }
        })?;
        match outcome {
            EditOutcome::Ok { id, version } => {
                println!("instance {}", show_id(id));
                println!("cell {}:{} version {version}", id.cell().x, id.cell().z);
                Ok(ExitCode::SUCCESS)
            }
            EditOutcome::Denied(why) => {
                eprintln!("denied: {why}");
                Ok(ExitCode::FAILURE)
            }
            EditOutcome::Invalid(why) => {
                eprintln!("invalid: {why}");
                Ok(ExitCode::FAILURE)
            }
            EditOutcome::Conflict => {
                eprintln!("conflict: the cell changed under the edit; try again");
                Ok(ExitCode::FAILURE)
            }
        }
    }
}

/// The centre of `id`'s cell, in world (x, z).
fn cell_centre(w: &canopy_protocol::messages::Welcome, c: CellCoord) -> [f32; 2] {
    let o = w.world.grid.cell_origin(c);
    let h = w.world.grid.cell_size / 2.0;
    [o[0] + h, o[1] + h]
}

/// `canopy world plant SPECIES --at X Z [--param NAME=VALUE …]`.
pub(super) fn plant(
    server: &ServerArgs,
    species: &str,
    at: [f32; 2],
    params: &[(String, f32)],
) -> anyhow::Result<ExitCode> {
    let mut c = Client::connect(server, |_| at)?;
    let id = c.species_id(species)?;
    let params = c.params(id, params)?;
    c.edit(EditOp::Plant { species: id, x: at[0], z: at[1], params })
}

/// `canopy world fell ID`.
pub(super) fn fell(server: &ServerArgs, id: InstanceId) -> anyhow::Result<ExitCode> {
    let mut c = Client::connect(server, |w| cell_centre(w, id.cell()))?;
    c.edit(EditOp::Fell { id })
}

/// `canopy world set ID NAME=VALUE …`.
pub(super) fn set(server: &ServerArgs, id: InstanceId, params: &[(String, f32)]) -> anyhow::Result<ExitCode> {
    let mut c = Client::connect(server, |w| cell_centre(w, id.cell()))?;
    let held = c.conn.state().cells().get(&id.cell()).context("the server did not send the instance's cell")?;
    let record = held.records.get(usize::from(id.index())).filter(|_| !held.felled.contains(&id.index()));
    let Some(record) = record else { bail!("no instance {} in its cell", show_id(id)) };
    let params = c.params(record.species, params)?;
    c.edit(EditOp::Set { id, params })
}

/// `canopy world cell X Z`: the instances of the cell at world (x, z) as a client receives them.
pub(super) fn cell(server: &ServerArgs, at: [f32; 2]) -> anyhow::Result<ExitCode> {
    let c = Client::connect(server, |_| at)?;
    let w = c.conn.welcome();
    let cell = w.world.grid.cell_of(at[0], at[1]);
    let Some(held) = c.conn.state().cells().get(&cell) else { bail!("({}, {}) is outside the world", at[0], at[1]) };
    let height =
        canopy_client::world::ground(&w.world.terrain).map_err(|e| anyhow::anyhow!("the world's ground: {e}"))?;
    let live = held.records.len() - held.felled.len();
    let mut out = format!(
        "cell {}:{} version {}: {live} instances ({} felled)\n",
        cell.x,
        cell.z,
        held.version,
        held.felled.len()
    );
    let mut instances: Vec<_> =
        c.conn.state().instances(&|x, z| height.height(x, z)).filter(|i| i.id.cell() == cell).collect();
    instances.sort_by_key(|i| i.id);
    for i in instances {
        let g = c.species(i.species);
        let params: Vec<String> = i
            .params
            .iter()
            .map(|(s, v)| format!("{}={v}", g.params.get(usize::from(*s)).map_or("?", |p| p.name.as_str())))
            .collect();
        let [x, y, z] = i.position;
        out += &format!("{}  {}  {x:.2} {y:.2} {z:.2}  {}\n", show_id(i.id), g.name, params.join(" "));
    }
    // A reader that stopped early (`| head`) is no error.
    match std::io::Write::write_all(&mut std::io::stdout().lock(), out.as_bytes()) {
        Err(e) if e.kind() != std::io::ErrorKind::BrokenPipe => Err(e.into()),
        _ => Ok(ExitCode::SUCCESS),
    }
}

/// `canopy world bake [MANIFEST] --data DIR -o OUT`: the world with the edits stored in `DIR` folded into a new
/// manifest — the source manifest (species paths made absolute, or library names for an embedded world), then one
/// line per edited instance: `fell` and `set` for the world function's instances, `instance` for planted ones. The
/// baked world is a new world: planted instances become explicit ones, so ids in edited cells may differ.
pub(super) fn bake(
    manifest: Option<&std::path::Path>,
    data: &std::path::Path,
    out: &std::path::Path,
) -> anyhow::Result<ExitCode> {
    use canopy_server::edits::{EditStore, SqliteEditStore};
    use canopy_worlds::world::EMBEDDED_WORLDS;

    let world = super::load_world(manifest).map_err(|d| anyhow::anyhow!("{d}"))?;
    // The manifest's text and where its relative paths lead.
    let (text, base) = match manifest {
        Some(path) if path.exists() => {
            let text = canopy_worlds::fsread::read_text(path, 16 << 20).with_context(|| path.display().to_string())?;
            let dir = path.parent().unwrap_or(std::path::Path::new(".")).canonicalize()?;
            (text, Base::Dir(dir))
        }
        other => {
            let name = other.and_then(|p| p.to_str()).unwrap_or("forest");
            let (_, text) = EMBEDDED_WORLDS.iter().find(|(n, _)| *n == name).context("no such embedded world")?;
            (text.to_string(), Base::Embedded)
        }
    };
    let db = data.join(canopy_server::edits::sqlite::FILE_NAME);
    if !db.is_file() {
        bail!("{}: no edits stored there", db.display());
    }
    let store = SqliteEditStore::open(data)?;
    let canopy_server::Baked { lines, fells, sets, plants, outside, skipped } = canopy_server::bake(&world, &store)?;
    for (x, z) in outside {
        eprintln!("warning: cell {x}:{z} has edits but lies outside the world; left out");
    }
    for (x, z, version, why) in skipped {
        eprintln!(
            "warning: {}: cell {x}:{z} version {version}: the world cannot take it ({why}); left out",
            db.display()
        );
    }
    // The baked manifest's relative paths lead from its own directory.
    let out_dir = match out.parent().filter(|d| !d.as_os_str().is_empty()) {
        Some(dir) => {
            std::fs::create_dir_all(dir).with_context(|| dir.display().to_string())?;
            dir.canonicalize()?
        }
        None => std::env::current_dir()?,
    };
    let mut baked = rebase(&text, &base, &out_dir)?;
    baked.push_str(&format!(
        "\n# Edits baked from {} ({} edits stored): {fells} felled, {sets} set, {plants} planted.\n",
        db.display(),
        store.count()?
    ));
    for l in lines {
        baked.push_str(&l);
        baked.push('\n');
    }
    // Written beside its destination and checked there: only a manifest that loads takes the name `out`.
    let name = out.file_name().context("the output names no file")?.to_string_lossy();
    let draft = out_dir.join(format!(".{name}.baking"));
    std::fs::write(&draft, &baked).with_context(|| draft.display().to_string())?;
    if let Err(d) = canopy_worlds::world::World::load(&draft) {
        let _ = std::fs::remove_file(&draft);
        bail!("the baked manifest does not load (nothing written):\n{d}");
    }
    std::fs::rename(&draft, out).with_context(|| out.display().to_string())?;
    println!("{}: {fells} felled, {sets} set, {plants} planted", out.display());
    Ok(ExitCode::SUCCESS)
}

/// The path of `to` relative to the directory `from` (both canonical: absolute, no `.` or `..`), with `..` where it
/// climbs; `None` when they share no root (another drive).
fn relative(from: &std::path::Path, to: &std::path::Path) -> Option<std::path::PathBuf> {
    use std::path::Component;
    let (a, b): (Vec<Component>, Vec<Component>) = (from.components().collect(), to.components().collect());
    if a.first() != b.first() {
        return None;
    }
    let common = a.iter().zip(&b).take_while(|(x, y)| x == y).count();
    let mut out = std::path::PathBuf::new();
    for _ in common..a.len() {
        out.push("..");
    }
    for c in &b[common..] {
        out.push(c);
    }
    Some(out)
}

/// Where a manifest's relative paths lead.
enum Base {
    /// A directory on disk.
    Dir(std::path::PathBuf),
    /// An embedded world (its species are the library's).
    Embedded,
}

/// The manifest text with each quoted `species` or `terrain` path made to load from `out_dir` (a canonical path):
/// the file's path relative to it, or for an embedded world, the library name of the species file it names.
fn rebase(text: &str, base: &Base, out_dir: &std::path::Path) -> anyhow::Result<String> {
    let mut out = String::with_capacity(text.len());
    for line in text.lines() {
        let code = line.split('#').next().unwrap_or("");
        let first = code.split_whitespace().next();
        let quoted = code.find('"').and_then(|a| code[a + 1..].find('"').map(|b| (a, a + 1 + b)));
        match (first, quoted) {
            (Some("species" | "terrain"), Some((a, b))) => {
                let rel = &code[a + 1..b];
                let new = match base {
                    Base::Dir(dir) => {
                        let p = dir.join(rel).canonicalize().with_context(|| format!("{rel}: in the manifest"))?;
                        let rel = relative(out_dir, &p).with_context(|| {
                            format!("{}: no relative path to it from {}", p.display(), out_dir.display())
                        })?;
                        format!("\"{}\"", rel.display())
                    }
                    Base::Embedded => {
                        let file = rel.rsplit(['/', '\\']).next().unwrap_or(rel);
                        let entry = canopy_worlds::library::find(file)
                            .with_context(|| format!("{rel}: not a library species, cannot bake it"))?;
                        entry.name().to_string()
                    }
                };
                out.push_str(&line[..a]);
                out.push_str(&new);
                out.push_str(&line[b + 1..]);
            }
            _ => out.push_str(line),
        }
        out.push('\n');
    }
    Ok(out)
}
