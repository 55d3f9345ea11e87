//! A character cursor shared by the text formats: trivia (whitespace, `#` comments), identifiers, numbers and
//! punctuation, all with byte spans for diagnostics.

use std::ops::Range;

/// A parse problem at a byte span, turned into a [`crate::diag::Diagnostic`] by the format's parser.
#[derive(Clone, Debug, PartialEq, Eq)]
pub(crate) struct ParseError {
    /// Where.
    pub span: Range<usize>,
    /// What, lowercase without a trailing period.
    pub message: String,
}

impl ParseError {
    /// A parse error at `span`.
    pub(crate) fn new(span: Range<usize>, message: impl Into<String>) -> ParseError {
        ParseError { span, message: message.into() }
    }
}

/// A position in a source text.
#[derive(Clone, Debug)]
pub(crate) struct Cursor<'a> {
    /// The whole text.
    pub src: &'a str,
    /// Byte offset of the next character.
    pub pos: usize,
    /// Whether newlines count as whitespace (false for line-oriented formats).
    pub newlines_are_space: bool,
}

impl<'a> Cursor<'a> {
    /// A cursor at the start of `src`.
    pub(crate) fn new(src: &'a str, newlines_are_space: bool) -> Cursor<'a> {
        Cursor { src, pos: 0, newlines_are_space }
    }

    /// The text from the cursor on.
    pub(crate) fn rest(&self) -> &'a str {
        &self.src[self.pos..]
    }

    /// Skip whitespace and `#` comments (and newlines, if they count as whitespace).
    pub(crate) fn skip_trivia(&mut self) {
        loop {
            let rest = self.rest();
            let Some(c) = rest.chars().next() else { return };
            if c == '#' {
                self.pos += rest.find('\n').unwrap_or(rest.len());
            } else if c == '\n' && !self.newlines_are_space {
                return;
            } else if c.is_whitespace() {
                self.pos += c.len_utf8();
            } else {
                return;
            }
        }
    }

    /// The next character after trivia, without consuming it.
    pub(crate) fn peek(&mut self) -> Option<char> {
        self.skip_trivia();
        self.rest().chars().next()
    }

    /// Whether only trivia remains.
    pub(crate) fn at_end(&mut self) -> bool {
        self.peek().is_none()
    }

    /// Consume `s` if the text continues with it after trivia.
    pub(crate) fn eat(&mut self, s: &str) -> bool {
        self.skip_trivia();
        if self.rest().starts_with(s) {
            self.pos += s.len();
            true
        } else {
            false
        }
    }

    /// Consume `s` or fail with "expected `s`".
    pub(crate) fn expect(&mut self, s: &str) -> Result<Range<usize>, ParseError> {
        self.skip_trivia();
        let start = self.pos;
        if self.eat(s) { Ok(start..self.pos) } else { Err(self.unexpected(&format!("`{s}`"))) }
    }

    /// An error "expected WHAT, found ..." at the next token.
    pub(crate) fn unexpected(&mut self, what: &str) -> ParseError {
        self.skip_trivia();
        let rest = self.rest();
        match rest.chars().next() {
            None => ParseError::new(self.pos..self.pos, format!("expected {what}, found end of file")),
            Some('\n') => ParseError::new(self.pos..self.pos + 1, format!("expected {what}, found end of line")),
            Some(c) => {
                let len = if is_ident_start(c) || c.is_ascii_digit() {
                    rest.find(|c: char| !is_ident_continue(c) && c != '.').unwrap_or(rest.len())
                } else {
                    c.len_utf8()
                };
                ParseError::new(self.pos..self.pos + len, format!("expected {what}, found `{}`", &rest[..len]))
            }
        }
    }

    /// An identifier `[A-Za-z_][A-Za-z0-9_]*` after trivia, with its span.
    pub(crate) fn ident(&mut self) -> Option<(&'a str, Range<usize>)> {
        self.skip_trivia();
        let rest = self.rest();
        let first = rest.chars().next()?;
        if !is_ident_start(first) {
            return None;
        }
        let len = rest.find(|c: char| !is_ident_continue(c)).unwrap_or(rest.len());
        let start = self.pos;
        self.pos += len;
        Some((&rest[..len], start..self.pos))
    }

    /// Consume the keyword `kw` if the next identifier is exactly it.
    pub(crate) fn eat_keyword(&mut self, kw: &str) -> bool {
        let save = self.pos;
        match self.ident() {
            Some((w, _)) if w == kw => true,
            _ => {
                self.pos = save;
                false
            }
        }
    }

    /// An unsigned decimal number (`12`, `1.5`, `.5`, `2e-3`) after trivia, correctly rounded to f32. A `.` followed
    /// by another `.` is not part of it: `1..2` reads as `1`, `..`, `2`. `None` (nothing consumed but trivia) if
    /// no number starts here.
    pub(crate) fn number(&mut self) -> Option<Result<(f32, Range<usize>), ParseError>> {
        self.scan_number(false)
    }

    /// [`Cursor::number`] with an optional `-` or `+` directly in front, part of its span and text.
    pub(crate) fn signed_number(&mut self) -> Option<Result<(f32, Range<usize>), ParseError>> {
        self.scan_number(true)
    }

    fn scan_number(&mut self, signed: bool) -> Option<Result<(f32, Range<usize>), ParseError>> {
        self.skip_trivia();
        let rest = self.rest().as_bytes();
        let sign = usize::from(signed && matches!(rest.first(), Some(b'-' | b'+')));
        let mut i = sign;
        while i < rest.len() && rest[i].is_ascii_digit() {
            i += 1;
        }
        if i < rest.len() && rest[i] == b'.' && rest.get(i + 1) != Some(&b'.') {
            i += 1;
            while i < rest.len() && rest[i].is_ascii_digit() {
                i += 1;
            }
        }
        if i == sign || (i == sign + 1 && rest[sign] == b'.') {
            return None;
        }
        if i < rest.len() && (rest[i] == b'e' || rest[i] == b'E') {
            let mut j = i + 1;
            if j < rest.len() && (rest[j] == b'+' || rest[j] == b'-') {
                j += 1;
            }
            let digits = j;
            while j < rest.len() && rest[j].is_ascii_digit() {
                j += 1;
            }
            if j > digits {
                i = j;
            }
        }
        let start = self.pos;
        self.pos += i;
        let text = &self.src[start..self.pos];
        Some(match text.parse::<f32>() {
            Ok(v) if v.is_finite() => Ok((v, start..self.pos)),
            _ => Err(ParseError::new(start..self.pos, format!("number `{text}` is not a finite f32"))),
        })
    }

    /// A non-negative integer after trivia: decimal, or hexadecimal after `0x`, with `_` grouping digits as in Rust
    /// (`0x5eed_f0e5`). The token runs to the end of the word, so `12ab` is one token. `None` (nothing consumed but
    /// trivia) if no digit starts here; otherwise the token is consumed and comes back with its span and its value,
    /// `None` if it is not a valid u64.
    pub(crate) fn integer(&mut self) -> Option<(Option<u64>, Range<usize>)> {
        self.skip_trivia();
        let rest = self.rest();
        if !rest.starts_with(|c: char| c.is_ascii_digit()) {
            return None;
        }
        let len = rest.find(|c: char| !is_ident_continue(c)).unwrap_or(rest.len());
        let token = &rest[..len];
        let (digits, radix) = match token.strip_prefix("0x").or_else(|| token.strip_prefix("0X")) {
            Some(hex) => (hex, 16),
            None => (token, 10),
        };
        let digits: String = digits.chars().filter(|&c| c != '_').collect();
        let value = if digits.is_empty() { None } else { u64::from_str_radix(&digits, radix).ok() };
        let start = self.pos;
        self.pos += len;
        Some((value, start..self.pos))
    }

    /// Skip to just past the next newline (error recovery in line-oriented formats).
    pub(crate) fn skip_line(&mut self) {
        let rest = self.rest();
        self.pos += rest.find('\n').map_or(rest.len(), |i| i + 1);
    }
}

/// Whether `c` may start an identifier.
pub(crate) fn is_ident_start(c: char) -> bool {
    c.is_ascii_alphabetic() || c == '_'
}

/// Whether `c` may continue an identifier.
pub(crate) fn is_ident_continue(c: char) -> bool {
    c.is_ascii_alphanumeric() || c == '_'
}
