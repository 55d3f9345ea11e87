//! Who may edit the world: editor tokens, kept hashed at rest, each with an optional region and a rate.
//!
//! The editors file (`canopy-server --editors FILE`) has one editor a line; `#` starts a comment:
//!
//! ```text
//! editor alice sha256:9f86d081884c7d659a2feaa0c55ad015a3bf4f1b2b0b822cd15d6c15b0f00a08 region -512 -512 512 512 rate 20
//! editor bots  sha256:…
//! ```
//!
//! `sha256:` is the SHA-256 of the token's bytes: the file never holds a token, so reading it does not let anyone
//! edit. A token is 32 random bytes, written as 64 hexadecimal characters; `canopy-server --add-editor NAME`
//! makes one, appends its line and prints the token once. `region X0 Z0 X1 Z1` limits the editor to that
//! rectangle of world (x, z); `rate N` to N edits a second (a burst of 2N; default [`DEFAULT_RATE`]). A session
//! whose hello carries no token, or one not in the file, is read-only.

use std::collections::HashMap;
use std::path::Path;
use std::sync::{Arc, Mutex};
use std::time::Instant;

use canopy_protocol::sync::Locked;
use sha2::{Digest, Sha256};

/// Edits a second an editor may make when its line names no rate.
pub(crate) const DEFAULT_RATE: u32 = 50;
/// Largest editors file read, bytes.
const MAX_FILE: u64 = 1 << 20;
/// Bytes of a token.
pub const TOKEN_BYTES: usize = 32;

/// One editor.
#[derive(Debug)]
pub struct Editor {
    /// The editor's name (for logs).
    pub name: String,
    /// World `[x0, z0, x1, z1]` the editor may change; `None`: anywhere.
    pub region: Option<[f32; 4]>,
    /// Edits a second.
    pub rate: u32,
    /// Edits it may still make now and when that was counted, shared by every session of the editor.
    bucket: Mutex<Option<(f64, Instant)>>,
}

impl Editor {
    /// Whether world `(x, z)` lies in the editor's region.
    pub fn may_edit_at(&self, x: f32, z: f32) -> bool {
        self.region.is_none_or(|[x0, z0, x1, z1]| x >= x0 && x <= x1 && z >= z0 && z <= z1)
    }

    /// Whether the editor's region meets the world rectangle `[x0, z0, x1, z1]` (a cell: checked before any of
    /// its records are built).
    pub fn may_edit_in(&self, [x0, z0, x1, z1]: [f32; 4]) -> bool {
        self.region.is_none_or(|[rx0, rz0, rx1, rz1]| x0 <= rx1 && rx0 <= x1 && z0 <= rz1 && rz0 <= z1)
    }

    /// Take one edit from the editor's rate at `now`; `false` when it is spent.
    pub fn take(&self, now: Instant) -> bool {
        let (rate, burst) = (f64::from(self.rate), 2.0 * f64::from(self.rate));
        let mut b = self.bucket.locked();
        let (tokens, last) = b.get_or_insert((burst, now));
        *tokens = (*tokens + now.saturating_duration_since(*last).as_secs_f64() * rate).min(burst);
        *last = now.max(*last);
        // One whole token an edit: a token bucket that never goes into debt.
        if *tokens < 1.0 {
            return false;
        }
        *tokens -= 1.0;
        true
    }
}

/// The editors of a server, by the hash of their token.
#[derive(Debug, Default)]
pub struct Editors {
    by_hash: HashMap<[u8; 32], Arc<Editor>>,
}

impl PartialEq for Editors {
    fn eq(&self, other: &Editors) -> bool {
        std::ptr::eq(self, other)
    }
}

/// An editors file that cannot be used, with where.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum EditorsError {
    /// The file could not be read (missing, not a regular file, too large, not UTF-8).
    #[error("{file}: {message}")]
    Read {
        /// The file.
        file: String,
        /// Why.
        message: String,
    },
    /// A line does not parse.
    #[error("{file}:{line}:{col}: {message}")]
    Syntax {
        /// The file.
        file: String,
        /// 1-based line.
        line: usize,
        /// 1-based column.
        col: usize,
        /// What is wrong.
        message: String,
    },
}

/// The SHA-256 of a token's bytes.
pub fn token_hash(token: &[u8]) -> [u8; 32] {
    Sha256::digest(token).into()
}

/// Lowercase hexadecimal.
pub fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// Bytes from hexadecimal (`None` unless an even number of hex digits).
pub fn unhex(s: &str) -> Option<Vec<u8>> {
    if !s.len().is_multiple_of(2) || !s.is_ascii() {
        return None;
    }
    (0..s.len()).step_by(2).map(|i| u8::from_str_radix(&s[i..i + 2], 16).ok()).collect()
}

impl Editors {
    /// No editors: every session is read-only.
    pub fn none() -> Editors {
        Editors::default()
    }

    /// Read an editors file.
    pub fn load(path: &Path) -> Result<Editors, EditorsError> {
        let file = path.display().to_string();
        let text = canopy_worlds::fsread::read_text(path, MAX_FILE)
            .map_err(|e| EditorsError::Read { file: file.clone(), message: e.to_string() })?;
        Editors::parse(&file, &text)
    }

    /// Parse an editors file's text (`file` names it in errors).
    pub fn parse(file: &str, text: &str) -> Result<Editors, EditorsError> {
        let mut by_hash = HashMap::new();
        for (n, raw) in text.lines().enumerate() {
            let line = raw.split('#').next().unwrap_or("");
            // Words with their 1-based columns.
            let mut words = Vec::new();
            let mut start = None;
            for (i, ch) in line.char_indices().chain(std::iter::once((line.len(), ' '))) {
                match (ch.is_whitespace(), start) {
                    (false, None) => start = Some(i),
                    (true, Some(s)) => {
                        words.push((&line[s..i], line[..s].chars().count() + 1));
                        start = None;
                    }
                    _ => {}
                }
            }
            if words.is_empty() {
                continue;
            }
            let err =
                |col: usize, message: String| EditorsError::Syntax { file: file.to_owned(), line: n + 1, col, message };
            let end_col = line.chars().count() + 1;
            if words[0].0 != "editor" {
                return Err(err(words[0].1, format!("expected `editor`, found `{}`", words[0].0)));
            }
            let name = words.get(1).ok_or_else(|| err(end_col, "expected the editor's name".into()))?;
            let hash_word =
                words.get(2).ok_or_else(|| err(end_col, "expected `sha256:` and the token's hash".into()))?;
            let hash = hash_word
                .0
                .strip_prefix("sha256:")
                .and_then(unhex)
                .and_then(|h| <[u8; 32]>::try_from(h).ok())
                .ok_or_else(|| err(hash_word.1, "expected `sha256:` and 64 hexadecimal digits".into()))?;
            let mut region = None;
            let mut rate = DEFAULT_RATE;
            let mut i = 3;
            while i < words.len() {
                let (word, col) = words[i];
                let number = |j: usize| -> Result<f64, EditorsError> {
                    let (w, c) = *words.get(j).ok_or_else(|| err(end_col, format!("`{word}` needs more numbers")))?;
                    w.parse::<f64>()
                        .ok()
                        .filter(|v| v.is_finite())
                        .ok_or_else(|| err(c, format!("expected a number, found `{w}`")))
                };
                match word {
                    "region" => {
                        let v = [number(i + 1)?, number(i + 2)?, number(i + 3)?, number(i + 4)?];
                        if v[0] > v[2] || v[1] > v[3] {
                            return Err(err(col, "region X0 Z0 X1 Z1 needs X0 ≤ X1 and Z0 ≤ Z1".into()));
                        }
                        region = Some(v.map(|x| x as f32));
                        i += 5;
                    }
                    "rate" => {
                        let r = number(i + 1)?;
                        if !(1.0..=1_000_000.0).contains(&r) || r.fract() != 0.0 {
                            return Err(err(
                                words[i + 1].1,
                                "rate is a whole number of edits a second, 1 to 1000000".into(),
                            ));
                        }
                        rate = r as u32;
                        i += 2;
                    }
                    other => return Err(err(col, format!("expected `region` or `rate`, found `{other}`"))),
                }
            }
            let editor = Editor { name: name.0.to_owned(), region, rate, bucket: Mutex::new(None) };
            if by_hash.insert(hash, Arc::new(editor)).is_some() {
                return Err(err(hash_word.1, "this token is already listed".into()));
            }
        }
        Ok(Editors { by_hash })
    }

    /// The editor a hello's token names, if any.
    pub fn find(&self, token: &[u8]) -> Option<Arc<Editor>> {
        self.by_hash.get(&token_hash(token)).cloned()
    }

    /// How many editors there are.
    pub fn len(&self) -> usize {
        self.by_hash.len()
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.by_hash.is_empty()
    }
}

/// A new random token: [`TOKEN_BYTES`] bytes from the operating system.
pub fn new_token() -> std::io::Result<[u8; TOKEN_BYTES]> {
    let mut t = [0u8; TOKEN_BYTES];
    getrandom::fill(&mut t).map_err(|e| std::io::Error::other(e.to_string()))?;
    Ok(t)
}

/// The editors-file line for an editor with this token.
pub fn editor_line(name: &str, token: &[u8], region: Option<[f32; 4]>, rate: Option<u32>) -> String {
    let mut line = format!("editor {name} sha256:{}", hex(&token_hash(token)));
    if let Some([x0, z0, x1, z1]) = region {
        line += &format!(" region {x0} {z0} {x1} {z1}");
    }
    if let Some(r) = rate {
        line += &format!(" rate {r}");
    }
    line
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn editors_are_found_by_token_and_bounded_by_region_and_rate() {
        let (a, b) = ([7u8; 32], [9u8; 32]);
        let text = format!(
            "# editors\n{}\n\n{}  # the bots\n",
            editor_line("alice", &a, Some([-10.0, -10.0, 10.0, 10.0]), Some(2)),
            editor_line("bots", &b, None, None)
        );
        let e = Editors::parse("editors", &text).unwrap();
        assert_eq!(e.len(), 2);
        let alice = e.find(&a).unwrap();
        assert_eq!((alice.name.as_str(), alice.rate), ("alice", 2));
        assert!(alice.may_edit_at(0.0, 10.0) && !alice.may_edit_at(11.0, 0.0));
        assert!(e.find(&b).unwrap().may_edit_at(1e6, -1e6));
        assert!(alice.may_edit_in([10.0, -40.0, 42.0, -8.0]) && alice.may_edit_in([-5.0, -5.0, 5.0, 5.0]));
        assert!(!alice.may_edit_in([10.5, 0.0, 42.0, 32.0]) && !alice.may_edit_in([-9.0, -43.0, -8.0, -11.0]));
        assert!(e.find(&b).unwrap().may_edit_in([1e6, 1e6, 1e6 + 32.0, 1e6 + 32.0]));
        assert!(e.find(&[1u8; 32]).is_none());
        let t0 = Instant::now();
        let taken = (0..10).filter(|_| alice.take(t0)).count();
        assert_eq!(taken, 4, "a burst of twice the rate");
        assert!(alice.take(t0 + std::time::Duration::from_millis(600)));
    }

    #[test]
    fn bad_lines_say_where() {
        let cases = [
            ("editr a sha256:00", "f:1:1: expected `editor`"),
            ("editor a", "f:1:9: expected `sha256:`"),
            ("editor a sha256:zz", "f:1:10: expected `sha256:` and 64"),
            (&format!("{} region 1 2 3", editor_line("a", &[1; 32], None, None)), "needs more numbers"),
            (&format!("{} rate 0", editor_line("a", &[1; 32], None, None)), ":1:87: rate is a whole number"),
            (
                &format!("\n  {} colour 3", editor_line("a", &[1; 32], None, None)),
                "f:2:84: expected `region` or `rate`",
            ),
        ];
        for (text, want) in cases {
            let e = Editors::parse("f", text).unwrap_err().to_string();
            assert!(e.contains(want), "{text:?}: {e}");
        }
    }
}
