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
    fn span_at_end_of_file_is_clamped() {
        let src = SourceFile::new("b", "x");
        let d = src.diag(5..9, "unexpected end of file");
        assert_eq!((d.line, d.col, d.width), (1, 2, 1));
    }
}
