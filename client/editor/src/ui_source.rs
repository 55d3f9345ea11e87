//! The source text editor: line numbers in a gutter with a mark on every line that has a diagnostic, and the
//! diagnostic's span underlined in the text (its line and column as `file:line:col` reports them).

use std::sync::Arc;

use canopy_worlds::diag::Diagnostic;
use egui::text::{LayoutJob, TextFormat};
use egui::{Color32, FontId, Stroke, TextBuffer, Ui};

/// The colour of error marks and underlines.
pub(crate) const ERROR: Color32 = Color32::from_rgb(230, 70, 60);

/// Byte ranges of `text` that the diagnostics point at (a zero-width span at the end of a line marks its last
/// character, or nothing on an empty line).
pub(crate) fn spans(text: &str, diags: &[Diagnostic]) -> Vec<std::ops::Range<usize>> {
    let starts: Vec<usize> = std::iter::once(0).chain(text.match_indices('\n').map(|(i, _)| i + 1)).collect();
    let mut out = Vec::new();
    for d in diags {
        let Some(&ls) = starts.get(d.line.saturating_sub(1)) else { continue };
        let line_end = text[ls..].find('\n').map_or(text.len(), |i| ls + i);
        let line = &text[ls..line_end];
        let byte_at = |chars: usize| line.char_indices().nth(chars).map_or(line.len(), |(i, _)| i);
        let mut a = byte_at(d.col.saturating_sub(1));
        let b = byte_at(d.col.saturating_sub(1) + d.width.max(1));
        if a == b && a > 0 {
            a = byte_at(d.col.saturating_sub(2));
        }
        if a < b {
            out.push(ls + a..ls + b);
        }
    }
    out.sort_by_key(|r| (r.start, r.end));
    out
}

/// Lay the text out in the monospace font with the diagnostic spans underlined.
fn layout(text: &str, diags: &[Diagnostic], font: &FontId, color: Color32) -> LayoutJob {
    let plain = TextFormat { font_id: font.clone(), color, ..TextFormat::default() };
    let marked = TextFormat {
        font_id: font.clone(),
        color,
        underline: Stroke::new(2.0, ERROR),
        background: ERROR.gamma_multiply(0.15),
        ..TextFormat::default()
    };
    let mut job = LayoutJob::default();
    let mut at = 0;
    for r in spans(text, diags) {
        let start = r.start.max(at);
        if start >= r.end {
            continue;
        }
        job.append(&text[at..start], 0.0, plain.clone());
        job.append(&text[start..r.end], 0.0, marked.clone());
        at = r.end;
    }
    job.append(&text[at..], 0.0, plain);
    job
}

/// The editor: gutter and text side by side in one scroll area. Returns true when the text changed.
pub(crate) fn show(ui: &mut Ui, text: &mut String, diags: &[Diagnostic]) -> bool {
    let font = egui::TextStyle::Monospace.resolve(ui.style());
    let color = ui.visuals().text_color();
    let lines = text.matches('\n').count() + 1;
    let marked: std::collections::BTreeSet<usize> = diags.iter().map(|d| d.line).collect();
    let mut changed = false;
    egui::ScrollArea::both().id_salt("source").auto_shrink([false, false]).show(ui, |ui| {
        ui.horizontal_top(|ui| {
            let width = lines.to_string().len();
            let mut gutter = LayoutJob::default();
            for n in 1..=lines {
                let mark = if marked.contains(&n) { "!" } else { " " };
                let c = if marked.contains(&n) { ERROR } else { ui.visuals().weak_text_color() };
                let nl = if n < lines { "\n" } else { "" };
                gutter.append(
                    &format!("{mark}{n:>width$}{nl}"),
                    0.0,
                    TextFormat { font_id: font.clone(), color: c, ..TextFormat::default() },
                );
            }
            // The gutter is a label laid out like the text edit's rows (same font, same top margin).
            ui.add_space(2.0);
            ui.vertical(|ui| {
                ui.add_space(2.0);
                ui.label(gutter);
            });
            // No wrapping: one text row per line, so the gutter's numbers stay beside their lines.
            let mut layouter = |ui: &Ui, buf: &dyn TextBuffer, _wrap: f32| -> Arc<egui::Galley> {
                let mut job = layout(buf.as_str(), diags, &font, color);
                job.wrap.max_width = f32::INFINITY;
                ui.ctx().fonts_mut(|f| f.layout_job(job))
            };
            let r = ui.add(
                egui::TextEdit::multiline(text)
                    .id_salt("source-text")
                    .code_editor()
                    .desired_width(f32::INFINITY)
                    .desired_rows(lines.max(24))
                    .lock_focus(true)
                    .layouter(&mut layouter),
            );
            r.widget_info(|| egui::WidgetInfo::labeled(egui::accesskit::Role::MultilineTextInput, true, "source"));
            changed = r.changed();
        });
    });
    changed
}

#[cfg(test)]
mod tests {
    use super::*;
    use canopy_worlds::diag::SourceFile;

    #[test]
    fn spans_follow_line_and_column() {
        let src = SourceFile::new("a.species", "param x = 1\nparam y = sine(x)\n");
        let d = src.diag(22..26, "unknown function `sine`");
        let r = spans(&src.text, &[d]);
        assert_eq!(r, vec![22..26]);
        assert_eq!(&src.text[r[0].clone()], "sine");
        // At the end of a line: the last character.
        let d = src.diag(11..11, "expected a value");
        assert_eq!(spans(&src.text, &[d]), vec![10..11]);
    }
}
