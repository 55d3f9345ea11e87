//! The CSV files of a bandwidth run's report: `scenarios.csv` (per bot and per scenario), `samples.csv` (every
//! sample) and `sizes.csv` (seed 001 §7's size table).

use super::Outcome;
use super::measure::{Bytes, fraction};

/// A CSV file from a header and rows, quoted and escaped by the `csv` crate (names may hold commas, quotes or
/// newlines: an error message does).
fn csv_table(header: &[&str], rows: impl IntoIterator<Item = Vec<String>>) -> String {
    let mut w = csv::Writer::from_writer(Vec::new());
    // Writing into memory cannot fail on IO; a row with the wrong width is a bug in the caller.
    w.write_record(header).expect("in-memory CSV");
    for row in rows {
        assert_eq!(row.len(), header.len(), "a CSV row has as many fields as the header");
        w.write_record(&row).expect("in-memory CSV");
    }
    String::from_utf8(w.into_inner().expect("in-memory CSV")).expect("fields are UTF-8")
}

pub(super) fn csv_scenarios(o: &Outcome) -> String {
    const HEADER: &[&str] = &[
        "scenario",
        "payload",
        "rate_bps",
        "latency_ms",
        "loss",
        "bot",
        "wire_bytes",
        "udp_rx",
        "udp_tx",
        "species",
        "records",
        "geometry",
        "summaries",
        "control",
        "transport",
        "instance_mesh_bytes",
        "species_mesh_bytes",
        "transform_bytes",
        "summary_nodes",
        "instances_received",
        "instances_held",
        "bytes_per_instance",
        "walking_completeness",
        "walking_min",
        "overall_completeness",
        "first_complete_s",
        "teleport_complete_s",
        "complete_at_end",
        "error",
    ];
    let mut rows = Vec::new();
    for r in &o.scenarios {
        let sc = &r.scenario;
        let head = [
            sc.name.clone(),
            sc.label().to_string(),
            sc.link.rate.map_or(String::new(), |v| v.to_string()),
            sc.link.latency.as_millis().to_string(),
            sc.link.loss.to_string(),
        ];
        let opt = |v: Option<f64>| v.map_or(String::new(), |v| format!("{v:.3}"));
        let row = |bot: String, x: &Bytes, geometry: [u64; 3], tail: [String; 11]| {
            let mut row = head.to_vec();
            row.push(bot);
            row.extend(byte_columns(x));
            row.extend(geometry.map(|g| g.to_string()));
            row.extend(tail);
            row
        };
        for b in &r.bots {
            let x = &b.bytes;
            rows.push(row(
                b.bot.id.to_string(),
                x,
                b.geometry,
                [
                    b.bot.summaries.to_string(),
                    b.bot.records.to_string(),
                    b.bot.held.to_string(),
                    if b.bot.records > 0 {
                        format!("{:.3}", x.total() as f64 / b.bot.records as f64)
                    } else {
                        String::new()
                    },
                    format!("{:.6}", b.walking().mean()),
                    format!("{:.6}", b.walking().min),
                    format!("{:.6}", b.overall().mean()),
                    opt(b.first_complete()),
                    opt(b.teleport_complete),
                    b.bot.complete.to_string(),
                    b.bot.error.clone().unwrap_or_default(),
                ],
            ));
        }
        let g = |k: usize| r.bots.iter().map(|b| b.geometry[k]).sum::<u64>();
        rows.push(row(
            "all".into(),
            &r.bytes(),
            [g(0), g(1), g(2)],
            [
                r.bots.iter().map(|b| b.bot.summaries).sum::<u64>().to_string(),
                r.records().to_string(),
                r.bots.iter().map(|b| b.bot.held).sum::<usize>().to_string(),
                r.bytes_per_instance().map_or(String::new(), |v| format!("{v:.3}")),
                format!("{:.6}", r.walking().mean()),
                format!("{:.6}", r.walking().min),
                format!("{:.6}", r.overall().mean()),
                opt(r.first_complete()),
                opt(r.teleport_complete()),
                r.bots.iter().all(|b| b.bot.complete).to_string(),
                String::new(),
            ],
        ));
    }
    csv_table(HEADER, rows)
}

/// The byte columns of a scenarios row: `wire_bytes` (UDP both ways), `udp_rx`, `udp_tx`, then by class.
fn byte_columns(x: &Bytes) -> [String; 9] {
    [x.total(), x.udp_rx, x.udp_tx, x.species, x.records, x.geometry, x.summaries, x.control, x.overhead]
        .map(|v| v.to_string())
}

pub(super) fn csv_samples(o: &Outcome) -> String {
    const HEADER: &[&str] = &[
        "scenario",
        "bot",
        "t_s",
        "phase",
        "x",
        "z",
        "wire_bytes",
        "species",
        "records",
        "geometry",
        "summaries",
        "control",
        "transport",
        "visible",
        "held",
        "completeness",
        "aoi_complete",
    ];
    let rows = o.scenarios.iter().flat_map(|r| {
        r.bots.iter().flat_map(move |b| {
            b.samples.iter().map(move |x| {
                vec![
                    r.scenario.name.clone(),
                    b.bot.id.to_string(),
                    format!("{:.3}", x.t),
                    x.phase.label().to_string(),
                    format!("{:.1}", x.position[0]),
                    format!("{:.1}", x.position[1]),
                    x.bytes.total().to_string(),
                    x.bytes.species.to_string(),
                    x.bytes.records.to_string(),
                    x.bytes.geometry.to_string(),
                    x.bytes.summaries.to_string(),
                    x.bytes.control.to_string(),
                    x.bytes.overhead.to_string(),
                    x.visible.to_string(),
                    x.held.to_string(),
                    format!("{:.6}", fraction(x.visible, x.held)),
                    x.aoi_complete.to_string(),
                ]
            })
        })
    });
    csv_table(HEADER, rows)
}

pub(super) fn csv_sizes(o: &Outcome) -> String {
    const HEADER: &[&str] = &[
        "species",
        "encoded",
        "primitives",
        "explicit_s7",
        "triangles",
        "quantised_mesh",
        "compressed_mesh",
        "alternative",
        "alternative_bytes",
    ];
    let rows = o.sizes.iter().map(|r| {
        vec![
            r.name.clone(),
            r.encoded.to_string(),
            r.primitives.to_string(),
            r.explicit.to_string(),
            r.triangles.to_string(),
            r.quantised.to_string(),
            r.compressed.to_string(),
            r.alternative.map_or(String::new(), |a| a.0.to_string()),
            r.alternative.map_or(String::new(), |a| a.1.to_string()),
        ]
    });
    csv_table(HEADER, rows)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn csv_fields_with_commas_quotes_and_newlines_round_trip() {
        let awkward = vec!["a,b".to_string(), "say \"hi\"".to_string(), "two\nlines".to_string()];
        let text = csv_table(&["x", "y", "z"], [awkward.clone(), vec!["1".into(), "2".into(), "3".into()]]);
        let rows: Vec<Vec<String>> = csv::Reader::from_reader(text.as_bytes())
            .records()
            .map(|r| r.unwrap().iter().map(str::to_owned).collect())
            .collect();
        assert_eq!(rows, [awkward, vec!["1".to_string(), "2".into(), "3".into()]]);
    }
}
