//! The report of a bandwidth run: `report.md` (settings, a table per scenario, far-view summaries beside records,
//! the procedural-vs-explicit comparison, seed 001 §7's size table, method notes), `scenarios.csv` (per bot and per
//! scenario), `samples.csv` (every sample), `sizes.csv`, and hand-written SVG line plots: bytes over time (with
//! records and summaries when a far view was asked for) and visible completeness over time per scenario, and
//! cumulative bytes of all scenarios on a log scale.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use canopy_protocol::summary::FarView;
use canopy_server::session::PayloadMode;

use super::measure::{Bytes, SamplePhase};
use super::{BandwidthConfig, Outcome, ScenarioResult, tables};

use crate::numbers::{group, human_bytes as human};

fn secs(t: Option<f64>) -> String {
    t.map_or("never".to_string(), |t| format!("{t:.2} s"))
}

fn pct(v: f64) -> String {
    format!("{:.2} %", v * 100.0)
}

/// One line summarising a scenario (printed as it finishes).
pub fn scenario_line(r: &ScenarioResult) -> String {
    let b = r.bytes();
    format!(
        "{:<22} {:>9} on the wire, {:>6} records, {:>8}/instance{}, visible completeness walking {} overall {}, first complete {}, after teleport {}{}",
        r.scenario.name,
        human(b.total() as f64),
        r.records(),
        r.bytes_per_instance().map_or("-".into(), human),
        if b.summaries > 0 {
            format!(
                ", far view {} of summaries beside {} of records",
                human(b.summaries as f64),
                human(b.records as f64)
            )
        } else {
            String::new()
        },
        if r.walking().samples == 0 { "n/a".into() } else { pct(r.walking().mean()) },
        pct(r.overall().mean()),
        secs(r.first_complete()),
        secs(r.teleport_complete()),
        match r.bots.iter().filter_map(|b| b.bot.error.as_ref()).next() {
            Some(e) => format!(" (error: {e})"),
            None => String::new(),
        }
    )
}

/// The procedural scenario and the two baselines over the same link, if the run has all three.
pub fn comparisons(o: &Outcome) -> Vec<[&ScenarioResult; 3]> {
    let mut out = Vec::new();
    for p in o.scenarios.iter().filter(|s| s.scenario.mode == PayloadMode::Procedural && !s.scenario.expand) {
        let find = |m| o.scenarios.iter().find(|s| s.scenario.mode == m && s.scenario.link == p.scenario.link);
        if let (Some(u), Some(i)) = (find(PayloadMode::UniqueMesh), find(PayloadMode::Instanced)) {
            out.push([p, u, i]);
        }
    }
    out
}

/// What a payload costs to deliver instances: a fixed part and a part per instance, wire bytes per client.
#[derive(Clone, Debug, PartialEq)]
pub struct Projection {
    /// Fixed bytes (species programs or species meshes).
    pub fixed: f64,
    /// Bytes per instance.
    pub per_instance: f64,
    /// Bytes per instance without the harness's records (explicit modes).
    pub per_instance_bare: f64,
    /// How it was computed, for the report.
    pub how: String,
}

impl Projection {
    /// Bytes to deliver `n` instances.
    pub fn bytes(&self, n: f64) -> f64 {
        self.fixed + self.per_instance * n
    }

    /// Likewise, without the harness's records.
    pub fn bytes_bare(&self, n: f64) -> f64 {
        self.fixed + self.per_instance_bare * n
    }
}

/// The projections of a comparison's procedural, unique-mesh and instanced scenarios (see the report's text).
pub fn projections(o: &Outcome, [p, u, i]: [&ScenarioResult; 3]) -> [Option<Projection>; 3] {
    let bots = |r: &ScenarioResult| r.bots.len().max(1) as f64;
    let procedural = p.per_instance_payload(true).map(|m| {
        let w = p.wire_ratio();
        Projection {
            fixed: p.bytes().species as f64 / bots(p) * w,
            per_instance: m * w,
            per_instance_bare: m * w,
            how: format!(
                "procedural: species programs {:.0} bytes per client and records {m:.2} bytes per instance, × wire/frame {w:.3}.",
                p.bytes().species as f64 / bots(p)
            ),
        }
    });
    let unique = o.mesh_sample.as_ref().and_then(|m| m.mean()).map(|mesh| {
        let w = u.wire_ratio();
        let records = p.per_instance_payload(true).unwrap_or(0.0);
        Projection {
            fixed: 0.0,
            per_instance: (mesh + records) * w,
            per_instance_bare: mesh * w,
            how: format!(
                "unique-mesh: the mean compressed mesh of {} instances spread evenly over the world, {mesh:.0} bytes, plus the procedural run's records per instance ({records:.2}), × wire/frame {w:.3} measured in its scenario.",
                o.mesh_sample.as_ref().map_or(0, |m| m.count)
            ),
        }
    });
    // The species meshes of the species the procedural bots needed, per bot on average.
    let needed: f64 = p
        .bots
        .iter()
        .map(|b| {
            b.species_ids.iter().map(|&id| o.species_meshes.get(usize::from(id)).copied().unwrap_or(0)).sum::<u64>()
                as f64
        })
        .sum::<f64>()
        / bots(p);
    let instanced = (!o.species_meshes.is_empty())
        .then(|| i.per_instance_payload(true).zip(i.per_instance_payload(false)))
        .flatten()
        .map(|(m, bare)| {
            let w = i.wire_ratio();
            Projection {
                fixed: needed * w,
                per_instance: m * w,
                per_instance_bare: bare * w,
                how: format!(
                    "instanced: the species meshes of the species the procedural bots needed, {needed:.0} bytes per client, and records + transforms {m:.2} bytes per instance (transforms alone {bare:.2}), × wire/frame {w:.3} measured in its scenario."
                ),
            }
        });
    [procedural, unique, instanced]
}

/// The area-of-interest radius the bots asked for: a flight's from the server's rules (the first bot that
/// connected says), a walker's as configured.
fn radius_asked(cfg: &BandwidthConfig, o: &Outcome) -> f32 {
    o.scenarios.iter().flat_map(|r| &r.bots).map(|b| b.radius).find(|&r| r > 0.0).unwrap_or(cfg.radius)
}

fn far_view(f: &FarView) -> String {
    format!(
        "far view {} px on a {}-pixel, {:.0}° view out to {} m",
        f.error_px,
        f.height_px,
        f.fov_y.to_degrees(),
        group(f.range as u64)
    )
}

/// The far view's bytes beside the records', per bot, for the scenarios that received summaries (or all, when
/// the bots asked for a far view).
fn far_section(s: &mut String, cfg: &BandwidthConfig, o: &Outcome) {
    let far: Vec<&ScenarioResult> =
        o.scenarios.iter().filter(|r| cfg.far.is_some() || r.bytes().summaries > 0).collect();
    if far.is_empty() {
        return;
    }
    let radius = radius_asked(cfg, o);
    let _ = writeln!(s, "\n## The far view: summaries beside records\n");
    let _ = writeln!(
        s,
        "{} the bots asked for the far view{} — summary nodes of the world beyond their records — beside the instance records of their area of interest ({radius} m{}). Per bot, on the wire's frames: far-view summaries against records; visible completeness is of the records within {} of the bot ({}).\n",
        if cfg.flying() { "Flying," } else { "Walking," },
        cfg.far.map_or(String::new(), |f| format!(" ({})", far_view(&f))),
        if cfg.fit { " at most: while moving, the radius the link carries at their speed" } else { "" },
        match cfg.view {
            Some(v) => format!("{v} m"),
            None if cfg.fit => "the radius asked at each sample".to_string(),
            None => format!("{radius} m"),
        },
        if cfg.flying() {
            "flying: the samples taken in flight once the area of interest had filled; overall: every sample before the stop"
        } else {
            "walking and overall as above"
        }
    );
    let _ = writeln!(
        s,
        "| scenario | link | summary nodes per bot | summaries per bot | records per bot | summaries : records | species per bot | control per bot | transport per bot | record radius {0} (mean) | {0} completeness (samples) | overall (samples) |",
        if cfg.flying() { "flying" } else { "walking" }
    );
    let _ = writeln!(s, "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    for r in far {
        let (b, n) = (r.bytes(), r.bots.len().max(1) as f64);
        let per = |v: u64| human(v as f64 / n);
        let (w, all) = (r.walking(), r.overall());
        let nodes = r.bots.iter().map(|b| b.bot.summaries).sum::<u64>() as f64 / n;
        // The radius judged at the samples taken while moving (fitted to the link, or the one asked for).
        let moving: Vec<f32> = r
            .bots
            .iter()
            .flat_map(|b| &b.samples)
            .filter(|s| s.phase == SamplePhase::Walking)
            .map(|s| s.view)
            .collect();
        let view = if moving.is_empty() {
            "-".to_string()
        } else {
            format!("{:.0} m", moving.iter().map(|&v| f64::from(v)).sum::<f64>() / moving.len() as f64)
        };
        let _ = writeln!(
            s,
            "| {} | {} | {nodes:.0} | {} | {} | {} | {} | {} | {} | {view} | {} ({}) | {} ({}) |",
            r.scenario.name,
            r.scenario.link.label(),
            per(b.summaries),
            per(b.records),
            if b.records > 0 { format!("{:.2}", b.summaries as f64 / b.records as f64) } else { "-".into() },
            per(b.species),
            per(b.control),
            per(b.overhead),
            if w.samples == 0 { "n/a".into() } else { pct(w.mean()) },
            w.samples,
            pct(all.mean()),
            all.samples
        );
    }
    if o.truth.expanded > 0 {
        let t = &o.truth;
        let _ = writeln!(
            s,
            "\nThe ground truth of `{}` (never materialised) came from its function cell by cell: {} cells expanded ({:.1} s of expansion after the bots were done), {} look-ups found in its memo.",
            o.world,
            group(t.expanded),
            t.seconds,
            group(t.hits)
        );
    }
}

fn markdown(cfg: &BandwidthConfig, o: &Outcome) -> String {
    let mut s = String::new();
    let _ = writeln!(s, "# Bandwidth: procedural streaming against explicit geometry\n");
    let _ = writeln!(s, "Command: `{}`  ", cfg.command);
    let radius = radius_asked(cfg, o);
    let path = if cfg.flying() {
        format!(
            "{} s flight at {} m/s, {} m above the terrain{}, over `{}`; area of interest {radius} m (the flight radius of that altitude and speed, capped by the server)",
            cfg.duration.as_secs_f64(),
            cfg.speed,
            cfg.altitude,
            if cfg.teleport { ", with a teleport half-way" } else { "" },
            o.world,
        )
    } else {
        format!(
            "{} s straight walk at {} m/s{} on `{}`; area of interest {radius} m",
            cfg.duration.as_secs_f64(),
            cfg.speed,
            if cfg.teleport { " with a teleport half-way" } else { "" },
            o.world,
        )
    };
    let far = cfg.far.map_or(String::new(), |f| format!(", {}", far_view(&f)));
    let _ = writeln!(
        s,
        "{} bots per scenario, {path}{far}, view distance {} m, samples every {} ms, settle ≤ {} s; server pacing {}. Wall time {:.0} s.\n",
        cfg.bots,
        cfg.view.unwrap_or(radius),
        cfg.sample.as_millis(),
        cfg.settle.as_secs_f64(),
        match (&cfg.external, cfg.pace > 0.0) {
            (Some(e), _) => format!("the external server's own ({})", e.server),
            (None, true) => format!("{:.0} % of the link rate", cfg.pace * 100.0),
            (None, false) => "off".into(),
        },
        o.wall
    );
    let _ = writeln!(s, "## Scenarios\n");
    let _ = writeln!(
        s,
        "| scenario | payload | link | wire bytes | species | records | geometry | summaries | control | transport | instances | bytes/instance | walking completeness (min; samples) | overall | first complete | after teleport | complete at end |"
    );
    let _ = writeln!(s, "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    for r in &o.scenarios {
        let b = r.bytes();
        let w = r.walking();
        let _ = writeln!(
            s,
            "| {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} ({}; {}/{}) | {} | {} | {} | {}/{} |",
            r.scenario.name,
            r.scenario.label(),
            r.scenario.link.label(),
            group(b.total()),
            group(b.species),
            group(b.records),
            group(b.geometry),
            group(b.summaries),
            group(b.control),
            group(b.overhead),
            group(r.records()),
            r.bytes_per_instance().map_or("-".into(), |v| format!("{v:.1}")),
            if w.samples == 0 { "n/a".into() } else { pct(w.mean()) },
            if w.samples == 0 { "n/a".into() } else { pct(w.min) },
            w.samples,
            r.overall().samples,
            pct(r.overall().mean()),
            secs(r.first_complete()),
            secs(r.teleport_complete()),
            r.bots.iter().filter(|b| b.bot.complete).count(),
            r.bots.len()
        );
    }
    let errors: Vec<String> = o
        .scenarios
        .iter()
        .flat_map(|r| {
            r.bots
                .iter()
                .filter_map(move |b| b.bot.error.as_ref().map(|e| format!("{} bot {}: {e}", r.scenario.name, b.bot.id)))
        })
        .collect();
    if !errors.is_empty() {
        let _ = writeln!(s, "\nErrors:\n");
        for e in errors {
            let _ = writeln!(s, "- {e}");
        }
    }
    let links: Vec<String> = o
        .scenarios
        .iter()
        .filter_map(|r| {
            let l: Vec<_> = r.bots.iter().filter_map(|b| b.link).collect();
            if l.is_empty() {
                return None;
            }
            let sum = |f: &dyn Fn(&super::LinkTotals) -> u64| l.iter().map(f).sum::<u64>();
            Some(format!(
                "| {} | {} | {} | {} | {} | {} | {} |",
                r.scenario.name,
                sum(&|t| t.down[0]),
                sum(&|t| t.down[1]),
                sum(&|t| t.down[2]),
                sum(&|t| t.up[0]),
                sum(&|t| t.up[1] + t.up[2]),
                group(sum(&|t| t.down_bytes))
            ))
        })
        .collect();
    if !links.is_empty() {
        let _ = writeln!(
            s,
            "\nEmulated links (datagrams): server → client offered, lost, dropped at the bottleneck queue; client → server offered, dropped; server → client bytes offered.\n"
        );
        let _ = writeln!(s, "| scenario | down | lost | queue drops | up | up drops | down bytes offered |");
        let _ = writeln!(s, "|---|---:|---:|---:|---:|---:|---:|");
        for l in links {
            let _ = writeln!(s, "{l}");
        }
    }
    for r in o.scenarios.iter().filter(|r| r.source.is_some_and(|s| s.instance_meshes + s.hits > 0)) {
        let st = r.source.expect("filtered");
        let _ = writeln!(
            s,
            "\n{}: the server encoded {} instance meshes ({} vertices, {} compressed, {:.1} s), {} cache hits.",
            r.scenario.name,
            st.instance_meshes,
            group(st.instance_vertices),
            human(st.instance_bytes as f64),
            st.encode_seconds,
            st.hits
        );
    }
    far_section(&mut s, cfg, o);
    let _ = writeln!(s, "\n## Procedural against explicit geometry\n");
    let cmp = comparisons(o);
    if cmp.is_empty() {
        let _ = writeln!(s, "(This run has no link with all three payload modes.)");
    }
    for c in cmp {
        let p = c[0];
        let n = p.records() as f64 / p.bots.len().max(1) as f64;
        let _ = writeln!(
            s,
            "Link {}: the procedural bots received {:.0} instances each. Projected wire bytes for a client to receive \
             those instances in each payload: the fixed cost (species programs; species meshes of the species those \
             bots needed) plus the cost per instance (records, transforms, or a unique mesh), each times the wire/frame \
             ratio measured in its scenario (transport overhead, the client's messages). \"Without records\" leaves out \
             the instance records the explicit modes carry only so that the harness can count what a client holds.\n",
            p.scenario.link.label(),
            n
        );
        let _ = writeln!(
            s,
            "| payload | instances received | fixed bytes | bytes/instance | projected | ratio | without records | ratio |"
        );
        let _ = writeln!(s, "|---|---:|---:|---:|---:|---:|---:|---:|");
        let proj = projections(o, c);
        let base = proj[0].as_ref().map_or(1.0, |x| x.bytes(n).max(1.0));
        for (r, x) in c.iter().zip(&proj) {
            let Some(x) = x else {
                let _ = writeln!(s, "| {} | {} | - | - | - | - | - | - |", r.scenario.label(), r.records());
                continue;
            };
            let _ = writeln!(
                s,
                "| {} | {} | {} | {} | {} | {:.0}× | {} | {:.0}× |",
                r.scenario.label(),
                r.records(),
                human(x.fixed),
                if x.per_instance < 1000.0 { format!("{:.1}", x.per_instance) } else { group(x.per_instance as u64) },
                human(x.bytes(n)),
                x.bytes(n) / base,
                human(x.bytes_bare(n)),
                x.bytes_bare(n) / base
            );
        }
        for x in proj.iter().flatten() {
            let _ = writeln!(s, "\n{}", x.how);
        }
        if let Some((mean, k)) = c[1].announced_mesh() {
            let _ = writeln!(
                s,
                "\nunique-mesh, as sent: the {k} instance meshes whose first chunk arrived announce {} on average ({} arrived whole).",
                human(mean),
                c[1].records()
            );
        }
        let _ = writeln!(s);
    }
    if let Some(m) = &o.mesh_sample {
        let _ = writeln!(
            s,
            "Unique meshes of {} instances evenly spread over the world ({:.1} s to encode):\n",
            m.count, m.seconds
        );
        let _ = writeln!(s, "| species | instances | mean compressed mesh |");
        let _ = writeln!(s, "|---|---:|---:|");
        for (name, k, b) in &m.by_species {
            let _ = writeln!(s, "| {name} | {k} | {} |", group(b / (*k).max(1) as u64));
        }
        let _ = writeln!(s, "| all | {} | {} |\n", m.count, m.mean().map_or("-".into(), |v| group(v as u64)));
    }
    if !o.sizes.is_empty() {
        let _ = writeln!(s, "## Seed 001 §7: species against explicit geometry\n");
        let _ = writeln!(
            s,
            "Per instance, mean over the first seeds. explicit: as seed 001 §7 counts it (cones/cylinders 7 floats, spheres 4, triangles 9); mesh: 8-segment tessellation quantised to 16 bytes per vertex and 4 per index; compressed: meshoptimizer's codecs and deflate.\n"
        );
        let _ = writeln!(
            s,
            "| species | encoded | primitives | explicit (§7) | ratio | triangles | quantised mesh | compressed mesh | ratio |"
        );
        let _ = writeln!(s, "|---|---:|---:|---:|---:|---:|---:|---:|---:|");
        for r in &o.sizes {
            let (q, c, cr) = if r.compressed > 0 {
                (group(r.quantised), group(r.compressed), format!("{:.0}×", r.compressed_ratio()))
            } else {
                ("-".into(), "-".into(), "-".into())
            };
            let _ = writeln!(
                s,
                "| {} | {} | {} | {} | {:.0}× | {} | {q} | {c} | {cr} |",
                r.name,
                group(r.encoded),
                group(r.primitives),
                group(r.explicit),
                r.explicit_ratio(),
                group(r.triangles)
            );
        }
        for r in o.sizes.iter().filter(|r| r.alternative.is_some()) {
            let (what, bytes) = r.alternative.expect("filtered");
            let _ = writeln!(
                s,
                "\n{}: {} bytes encoded against a {what} of {} bytes: {:.0}× smaller.",
                r.name,
                group(r.encoded),
                group(bytes),
                bytes as f64 / r.encoded.max(1) as f64
            );
        }
    }
    let _ = writeln!(s, "\n## Plots\n");
    for r in &o.scenarios {
        let _ = writeln!(
            s,
            "- {}: ![bytes](bytes-{}.svg) ![completeness](completeness-{}.svg)",
            r.scenario.name, r.scenario.name, r.scenario.name
        );
    }
    let _ = writeln!(s, "- all scenarios: ![cumulative bytes](bytes-all.svg)");
    let _ = writeln!(s, "\n## Method\n");
    let _ = writeln!(
        s,
        "- Same server session core for every payload: the area of interest, priority order (nearest first, in view first), lanes, window and token bucket decide what goes next; only what is sent per instance and species differs. Unique meshes go one instance per unit (mesh chunks, then its record); instanced sends each species' mesh where procedural sends its program, and each batch's transforms before the batch.\n\
         - Bytes are the client's QUIC connection statistics (UDP payloads, both directions). Classes are frame bytes by message; transport overhead is the rest (QUIC headers, acknowledgements, handshake, retransmissions), so the classes add up to the wire.\n\
         - Links are a UDP relay per bot: random loss, a rate-limited bottleneck (IP/UDP headers counted) with a drop-tail queue of 250 ms, then the one-way latency, in each direction.\n\
         - Visible completeness: of the world's instances within the view distance of the bot's position (ground truth from the world itself: its instances when materialised at load, else its function cell by cell), the fraction the client holds; each sample notes what the client held, and the comparison with the world runs once the scenario's bots are done. Walking completeness excludes the initial fill and the refill after the teleport (those are the two times to complete).\n\
         - Far view: summary nodes (per species counts, heights and coverage over 2^L × 2^L cells) beyond the records, as much of the horizon as the client's screen-space error asks for; their bytes are the summaries class. A world never materialised is served through the server's cell cache, cold in each scenario.\n\
         - Meshes: full-detail amplification, 8 radial segments, positions quantised to 16 bits in the mesh's bounds, normals and colours to 8 bits, vertex cache and fetch optimised, meshoptimizer vertex and index codecs, then deflate (level 6). Transforms: translation 3 × f32, rotation 4 × snorm16, scale 3 × f32 per instance (EXT_mesh_gpu_instancing), meshoptimizer's vertex codec per stream, then deflate."
    );
    s
}

/// A series of a line chart.
#[derive(Clone, Debug)]
pub struct Series {
    /// Legend.
    pub name: String,
    /// Points, x increasing.
    pub points: Vec<(f64, f64)>,
}

const COLORS: [&str; 8] = ["#1b9e77", "#d95f02", "#7570b3", "#e7298a", "#66a61e", "#e6ab02", "#a6761d", "#666666"];

fn escape(s: &str) -> String {
    s.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;")
}

/// A line chart as SVG: axes with ticks, one polyline per series, a legend. `log_y` plots log10 of positive
/// values.
pub fn line_chart(title: &str, x_label: &str, y_label: &str, series: &[Series], log_y: bool) -> String {
    let (w, h, l, r, t, b) = (760.0, 420.0, 80.0, 20.0, 40.0, 50.0);
    let ty = |y: f64| if log_y { y.max(1.0).log10() } else { y };
    let pts = series.iter().flat_map(|s| s.points.iter());
    let (mut x0, mut x1, mut y0, mut y1) = (f64::INFINITY, f64::NEG_INFINITY, f64::INFINITY, f64::NEG_INFINITY);
    for &(x, y) in pts {
        x0 = x0.min(x);
        x1 = x1.max(x);
        y0 = y0.min(ty(y));
        y1 = y1.max(ty(y));
    }
    if !x0.is_finite() {
        (x0, x1, y0, y1) = (0.0, 1.0, 0.0, 1.0);
    }
    if !log_y {
        y0 = y0.min(0.0);
    } else {
        y0 = y0.floor();
        y1 = y1.ceil();
    }
    if x1 - x0 < 1e-9 {
        x1 = x0 + 1.0;
    }
    if y1 - y0 < 1e-9 {
        y1 = y0 + 1.0;
    }
    let px = |x: f64| l + (x - x0) / (x1 - x0) * (w - l - r);
    let py = |y: f64| h - b - (y - y0) / (y1 - y0) * (h - t - b);
    let mut s = String::new();
    let _ = writeln!(
        s,
        r#"<svg xmlns="http://www.w3.org/2000/svg" width="{w}" height="{h}" viewBox="0 0 {w} {h}" font-family="sans-serif" font-size="12">"#
    );
    let _ = writeln!(s, r#"<rect width="{w}" height="{h}" fill="white"/>"#);
    let _ = writeln!(s, r#"<text x="{}" y="22" text-anchor="middle" font-size="15">{}</text>"#, w / 2.0, escape(title));
    let _ = writeln!(s, r#"<line x1="{l}" y1="{}" x2="{}" y2="{}" stroke="black"/>"#, h - b, w - r, h - b);
    let _ = writeln!(s, r#"<line x1="{l}" y1="{t}" x2="{l}" y2="{}" stroke="black"/>"#, h - b);
    for i in 0..=5 {
        let x = x0 + (x1 - x0) * f64::from(i) / 5.0;
        let _ =
            writeln!(s, r#"<text x="{:.1}" y="{}" text-anchor="middle">{}</text>"#, px(x), h - b + 16.0, fmt_tick(x));
        let y = y0 + (y1 - y0) * f64::from(i) / 5.0;
        let label = if log_y { human(10f64.powf(y)) } else { fmt_tick(y) };
        let _ = writeln!(s, r##"<line x1="{l}" y1="{:.1}" x2="{}" y2="{:.1}" stroke="#ddd"/>"##, py(y), w - r, py(y));
        let _ =
            writeln!(s, r#"<text x="{}" y="{:.1}" text-anchor="end">{}</text>"#, l - 6.0, py(y) + 4.0, escape(&label));
    }
    let _ = writeln!(
        s,
        r#"<text x="{}" y="{}" text-anchor="middle">{}</text>"#,
        (l + w - r) / 2.0,
        h - 12.0,
        escape(x_label)
    );
    let _ = writeln!(
        s,
        r#"<text x="16" y="{}" text-anchor="middle" transform="rotate(-90 16 {})">{}</text>"#,
        (t + h - b) / 2.0,
        (t + h - b) / 2.0,
        escape(y_label)
    );
    for (i, se) in series.iter().enumerate() {
        let c = COLORS[i % COLORS.len()];
        let path: Vec<String> = se.points.iter().map(|&(x, y)| format!("{:.1},{:.1}", px(x), py(ty(y)))).collect();
        let _ = writeln!(s, r#"<polyline fill="none" stroke="{c}" stroke-width="1.6" points="{}"/>"#, path.join(" "));
        let ly = t + 8.0 + 16.0 * i as f64;
        let _ = writeln!(
            s,
            r#"<line x1="{}" y1="{ly}" x2="{}" y2="{ly}" stroke="{c}" stroke-width="3"/>"#,
            w - r - 200.0,
            w - r - 180.0
        );
        let _ = writeln!(s, r#"<text x="{}" y="{}">{}</text>"#, w - r - 175.0, ly + 4.0, escape(&se.name));
    }
    s.push_str("</svg>\n");
    s
}

fn fmt_tick(v: f64) -> String {
    if v.abs() >= 1e6 {
        format!("{:.1}M", v / 1e6)
    } else if v.abs() >= 1e4 {
        format!("{:.0}k", v / 1e3)
    } else if v.fract() == 0.0 || v.abs() >= 100.0 {
        format!("{v:.0}")
    } else {
        format!("{v:.2}")
    }
}

/// Write every file of the report into `cfg.out`; returns their paths.
pub fn write(cfg: &BandwidthConfig, o: &Outcome) -> std::io::Result<Vec<PathBuf>> {
    std::fs::create_dir_all(&cfg.out)?;
    let mut files = Vec::new();
    let mut put = |name: &str, text: String| -> std::io::Result<()> {
        let p: PathBuf = Path::new(&cfg.out).join(name);
        std::fs::write(&p, text)?;
        files.push(p);
        Ok(())
    };
    put("report.md", markdown(cfg, o))?;
    put("scenarios.csv", tables::csv_scenarios(o))?;
    put("samples.csv", tables::csv_samples(o))?;
    put("sizes.csv", tables::csv_sizes(o))?;
    let mut all = Vec::new();
    for r in &o.scenarios {
        let mut bytes: Vec<Series> = r
            .bots
            .iter()
            .map(|b| Series {
                name: format!("bot {}", b.bot.id),
                points: b.samples.iter().map(|x| (x.t, x.bytes.total() as f64)).collect(),
            })
            .collect();
        // With a far view: each bot's records and summaries beside its total.
        if r.bytes().summaries > 0 {
            for b in &r.bots {
                let class = |name: &str, f: fn(&Bytes) -> u64| Series {
                    name: format!("bot {} {name}", b.bot.id),
                    points: b.samples.iter().map(|x| (x.t, f(&x.bytes) as f64)).collect(),
                };
                bytes.push(class("records", |x| x.records));
                bytes.push(class("summaries", |x| x.summaries));
            }
        }
        let title = format!("{} — {}: bytes on the wire", r.scenario.name, r.scenario.link.label());
        put(
            &format!("bytes-{}.svg", r.scenario.name),
            line_chart(&title, "time (s)", "bytes (UDP, both ways)", &bytes, false),
        )?;
        let comp: Vec<Series> = r
            .bots
            .iter()
            .map(|b| Series {
                name: format!("bot {}", b.bot.id),
                points: b.samples.iter().map(|x| (x.t, 100.0 * x.completeness())).collect(),
            })
            .collect();
        let title = format!("{} — {}: visible completeness", r.scenario.name, r.scenario.link.label());
        put(
            &format!("completeness-{}.svg", r.scenario.name),
            line_chart(&title, "time (s)", "instances within view held (%)", &comp, false),
        )?;
        if let Some(b) = r.bots.first() {
            all.push(Series {
                name: r.scenario.name.clone(),
                points: b.samples.iter().map(|x| (x.t, x.bytes.total() as f64)).collect(),
            });
        }
    }
    put(
        "bytes-all.svg",
        line_chart("Bytes on the wire, bot 0 of each scenario", "time (s)", "bytes (log)", &all, true),
    )?;
    Ok(files)
}

#[cfg(test)]
mod tests {
    use super::*;
    use canopy_protocol::messages::ByKind;

    fn scenario(
        mode: PayloadMode,
        bytes: super::super::measure::Bytes,
        geometry: [u64; 3],
        records: u64,
        species: Vec<u8>,
    ) -> ScenarioResult {
        use super::super::link::LinkSpec;
        use super::super::{BotResult, Scenario};
        let report = crate::bots::BotReport { records, ..Default::default() };
        let bot = BotResult { bot: report, bytes, geometry, species_ids: species, ..BotResult::default() };
        ScenarioResult {
            scenario: Scenario::new(mode, LinkSpec::new(Some(1_000_000), 20, 0.0)),
            bots: vec![bot],
            wall: 1.0,
            source: None,
            server_bytes: None,
        }
    }

    #[test]
    fn projections_follow_their_definition() {
        use super::super::measure::Bytes;
        use super::super::{MeshSample, Outcome};
        // Procedural: 1,000 species bytes, 5,000 record bytes for 1,000 instances; 8,000 bytes on the wire in all.
        let p = Bytes::split(ByKind([500, 1_000, 5_000, 0, 0, 0, 0, 0, 0, 0, 0]), 500, 7_000, 1_000);
        let u = Bytes::split(ByKind([500, 0, 0, 0, 1_000_000, 0, 0, 0, 0, 0, 0]), 500, 1_049_500, 1_000);
        // Instanced: two species meshes started, 100 instances with 20 bytes of transforms each.
        let i = Bytes::split(ByKind([500, 0, 500, 0, 502_000, 0, 0, 0, 0, 0, 0]), 500, 504_000, 1_000);
        let o = Outcome {
            world: "forest".into(),
            scenarios: vec![
                scenario(PayloadMode::Procedural, p, [0; 3], 1_000, vec![0, 2]),
                scenario(PayloadMode::UniqueMesh, u, [1_000_000, 0, 0], 0, vec![]),
                scenario(PayloadMode::Instanced, i, [0, 500_000, 2_000], 100, vec![0, 1]),
            ],
            sizes: vec![],
            mesh_sample: Some(MeshSample { count: 4, bytes: 4_000_000, by_species: vec![], seconds: 0.0 }),
            species_meshes: vec![300_000, 200_000, 700_000],
            truth: Default::default(),
            files: vec![],
            wall: 1.0,
        };
        let c = comparisons(&o);
        assert_eq!(c.len(), 1);
        let [pp, up, ip] = projections(&o, c[0]);
        let (pp, up, ip) = (pp.unwrap(), up.unwrap(), ip.unwrap());
        let wp = 8_000.0 / 7_000.0;
        assert!((pp.fixed - 1_000.0 * wp).abs() < 1e-6);
        assert!((pp.per_instance - 5.0 * wp).abs() < 1e-9);
        // Unique meshes: the sample's mean mesh (plus the procedural records per instance), × its wire ratio.
        let wu = 1_050_500.0 / 1_001_000.0;
        assert!((up.per_instance - (1_000_000.0 + 5.0) * wu).abs() < 1e-6);
        assert!((up.per_instance_bare - 1_000_000.0 * wu).abs() < 1e-6);
        assert_eq!(up.fixed, 0.0);
        // Instanced: the meshes of the species procedural needed (0 and 2), records + transforms per instance.
        let wi = 505_000.0 / 503_500.0;
        assert!((ip.fixed - 1_000_000.0 * wi).abs() < 1e-6);
        assert!((ip.per_instance - (500.0 + 2_000.0) / 100.0 * wi).abs() < 1e-9);
        assert!((ip.per_instance_bare - 20.0 * wi).abs() < 1e-9);
        assert!((pp.bytes(1_000.0) - (pp.fixed + pp.per_instance * 1_000.0)).abs() < 1e-9);
    }

    #[test]
    fn numbers_format() {
        assert_eq!(group(1234567), "1,234,567");
        assert_eq!(group(12), "12");
        assert_eq!(human(1_500_000.0), "1.50 MB");
    }

    #[test]
    fn charts_are_svg_with_every_series() {
        let s = [
            Series { name: "a<b".into(), points: vec![(0.0, 1.0), (1.0, 10.0)] },
            Series { name: "c".into(), points: vec![(0.0, 100.0), (2.0, 1e6)] },
        ];
        for log in [false, true] {
            let svg = line_chart("t", "x", "y", &s, log);
            assert!(svg.starts_with("<svg") && svg.trim_end().ends_with("</svg>"));
            assert_eq!(svg.matches("<polyline").count(), 2);
            assert!(svg.contains("a&lt;b") && !svg.contains("NaN"));
        }
        let empty = line_chart("t", "x", "y", &[], false);
        assert!(!empty.contains("NaN"));
    }
}
