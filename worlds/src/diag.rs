//! Diagnostics for the text formats: `file:line:col` with the offending line and a caret under the span.
//!
//! Parsers never stop at the first problem they can recover from; they return what they built together with
//! every [`Diagnostic`] (rust-analyzer's "parsing never fails"), so one bad file or species never hides another's.

use std::fmt;
use std::ops::Range;

/// A source text with its name, able to turn byte offsets into line and column.
#[derive(Clone, Debug)]
pub struct SourceFile {
    /// The name shown in diagnostics (usually the path).
    pub name: String,
    /// The whole text.
    pub text: String,
}

/// One problem found in a source file.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Diagnostic {
    /// File name as given to [`SourceFile`].
    pub file: String,
    /// 1-based line.
    pub line: usize,
    /// 1-based column, in characters.
    pub col: usize,
    /// What is wrong, lowercase, no trailing period.
    pub message: String,
    /// The text of the offending line.
    pub line_text: String,
    /// Width of the caret underline, in characters (at least 1).
    pub width: usize,
}

impl SourceFile {
    /// A named source text.
    pub fn new(name: impl Into<String>, text: impl Into<String>) -> SourceFile {
        SourceFile { name: name.into(), text: text.into() }
    }

    /// 1-based line and column (in characters) of a byte offset.
    pub fn line_col(&self, offset: usize) -> (usize, usize) {
        let offset = offset.min(self.text.len());
        let before = &self.text[..floor_char_boundary(&self.text, offset)];
        let line = before.matches('\n').count() + 1;
        let line_start = before.rfind('\n').map_or(0, |i| i + 1);
        (line, before[line_start..].chars().count() + 1)
    }

    /// A diagnostic for the byte range `span`.
    pub fn diag(&self, span: Range<usize>, message: impl Into<String>) -> Diagnostic {
        let start = floor_char_boundary(&self.text, span.start.min(self.text.len()));
        let (line, col) = self.line_col(start);
        let line_start = self.text[..start].rfind('\n').map_or(0, |i| i + 1);
        let line_end = self.text[start..].find('\n').map_or(self.text.len(), |i| start + i);
        let line_text = self.text[line_start..line_end].trim_end_matches('\r').to_string();
        let end = floor_char_boundary(&self.text, span.end.clamp(start, line_end));
        let width = self.text[start..end].chars().count().max(1);
        Diagnostic { file: self.name.clone(), line, col, message: message.into(), line_text, width }
    }
}

fn floor_char_boundary(s: &str, mut i: usize) -> usize {
    while i > 0 && !s.is_char_boundary(i) {
        i -= 1;
    }
    i
}

impl fmt::Display for Diagnostic {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let gutter = self.line.to_string().len();
        writeln!(f, "{}:{}:{}: error: {}", self.file, self.line, self.col, self.message)?;
        writeln!(f, "{:gutter$} |", "")?;
        writeln!(f, "{} | {}", self.line, self.line_text)?;
        let pad: String =
            self.line_text.chars().take(self.col - 1).map(|c| if c == '\t' { '\t' } else { ' ' }).collect();
        write!(f, "{:gutter$} | {}{}", "", pad, "^".repeat(self.width))
    }
}

/// Most diagnostics reported for one file: past it, one last line says how many more there are (a file that is not
/// in the format at all would otherwise bury its first error under hundreds).
pub const MAX_DIAGNOSTICS: usize = 20;

/// Keep the first [`MAX_DIAGNOSTICS`] of `diags` (in line order) and, when there were more, a last diagnostic at the
/// next one's place that says "and N more".
pub fn cap(mut diags: Vec<Diagnostic>) -> Vec<Diagnostic> {
    if diags.len() > MAX_DIAGNOSTICS {
        let more = diags.len() - MAX_DIAGNOSTICS;
        let mut last = diags.swap_remove(MAX_DIAGNOSTICS);
        diags.truncate(MAX_DIAGNOSTICS);
        last.message = format!("and {more} more error(s) not shown; fix the ones above first");
        diags.push(last);
    }
    diags
}

/// The candidate a mistyped `name` most likely meant: the nearest by edit distance (a swap of two neighbours counts
/// one), within one edit for names of 3 or 4 characters and two beyond (none for shorter names: any one-letter name
/// is one edit from any other); the first of equals.
pub fn did_you_mean<'a>(name: &str, candidates: impl IntoIterator<Item = &'a str>) -> Option<&'a str> {
    let limit = match name.chars().count() {
        0..=2 => return None,
        3 | 4 => 1,
        _ => 2,
    };
    let mut best: Option<(usize, &str)> = None;
    for c in candidates {
        let d = edit_distance(name, c);
        if d > 0 && d <= limit && best.is_none_or(|(b, _)| d < b) {
            best = Some((d, c));
        }
    }
    best.map(|(_, c)| c)
}

/// Optimal string alignment distance: insertions, deletions, substitutions and swaps of neighbours, each one.
fn edit_distance(a: &str, b: &str) -> usize {
    let (a, b): (Vec<char>, Vec<char>) = (a.chars().collect(), b.chars().collect());
    if a.len().abs_diff(b.len()) > 2 {
        return 3;
    }
    let w = b.len() + 1;
    let mut d = vec![0usize; (a.len() + 1) * w];
    for i in 0..=a.len() {
        for j in 0..=b.len() {
            d[i * w + j] = if i == 0 || j == 0 {
                i + j
            } else {
                let sub = d[(i - 1) * w + j - 1] + usize::from(a[i - 1] != b[j - 1]);
                let mut v = sub.min(d[(i - 1) * w + j] + 1).min(d[i * w + j - 1] + 1);
                if i > 1 && j > 1 && a[i - 1] == b[j - 2] && a[i - 2] == b[j - 1] {
                    v = v.min(d[(i - 2) * w + j - 2] + 1);
                }
                v
            };
        }
    }
    d[a.len() * w + b.len()]
}

/// Diagnostics collected while loading one or more files; an error type for callers that want `Result`.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("{}", render(.0))]
pub struct Diagnostics(pub Vec<Diagnostic>);

fn render(d: &[Diagnostic]) -> String {
    d.iter().map(|d| d.to_string()).collect::<Vec<_>>().join("\n")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn caret_points_at_span() {
        let src = SourceFile::new("a.species", "param x = 1\nparam y = sine(x)\n");
        let d = src.diag(22..26, "unknown function `sine`");
        assert_eq!((d.line, d.col, d.width), (2, 11, 4));
        assert_eq!(
            d.to_string(),
            "a.species:2:11: error: unknown function `sine`\n  |\n2 | param y = sine(x)\n  |           ^^^^"
        );
    }

    #[test]
    fn near_names_are_suggested() {
        let names = ["height", "branch_length", "r", "s"];
        assert_eq!(did_you_mean("heigth", names), Some("height"));
        assert_eq!(did_you_mean("branch_lenght", names), Some("branch_length"));
        assert_eq!(did_you_mean("hieght", names), Some("height"));
        assert_eq!(did_you_mean("q", names), None, "one letter is near every other");
        assert_eq!(did_you_mean("cnoe", ["cone", "sphere"]), Some("cone"));
        assert_eq!(did_you_mean("width", names), None);
        assert_eq!(did_you_mean("height", names), None, "the name itself is no suggestion");
    }

    #[test]
    fn diagnostics_are_capped_with_a_count() {
        let src = SourceFile::new("c", "x\n".repeat(30));
        let diags: Vec<Diagnostic> = (0..30).map(|i| src.diag(2 * i..2 * i + 1, "bad")).collect();
        let capped = cap(diags);
        assert_eq!(capped.len(), MAX_DIAGNOSTICS + 1);
        assert_eq!(capped[MAX_DIAGNOSTICS].line, MAX_DIAGNOSTICS + 1);
        assert!(capped[MAX_DIAGNOSTICS].message.starts_with("and 10 more"), "{:?}", capped[MAX_DIAGNOSTICS]);
        assert_eq!(cap(capped[..3].to_vec()).len(), 3);
    }

    #[test]
    fn span_at_end_of_file_is_clamped() {
        let src = SourceFile::new("b", "x");
        let d = src.diag(5..9, "unexpected end of file");
        assert_eq!((d.line, d.col, d.width), (1, 2, 1));
    }
}
