//! Reading untrusted files: only regular files (a symbolic link is followed only to one), and never more than a
//! size limit, whatever `metadata` says — a device reports length 0 and never ends, a FIFO blocks its reader.

use std::io::Read;
use std::path::Path;

/// Why a file was not read.
#[derive(Debug, thiserror::Error)]
pub enum ReadError {
    /// A device, FIFO, socket or directory (or a link to one).
    #[error("not a regular file")]
    NotRegular,
    /// Longer than the limit.
    #[error("file exceeds {limit} bytes")]
    TooLarge {
        /// The limit, bytes.
        limit: u64,
    },
    /// A text file that is not UTF-8.
    #[error("not UTF-8 text")]
    NotUtf8,
    /// The operating system refused.
    #[error("cannot read: {0}")]
    Io(#[from] std::io::Error),
}

/// The bytes of the regular file at `path`, at most `limit` of them. The type is checked before opening (opening a
/// FIFO would block) and again on the opened file (the path may have changed in between); at most `limit + 1`
/// bytes are read, so a file that grows or lies about its length costs no more.
pub fn read_bounded(path: &Path, limit: u64) -> Result<Vec<u8>, ReadError> {
    if !std::fs::metadata(path)?.is_file() {
        return Err(ReadError::NotRegular);
    }
    let file = std::fs::File::open(path)?;
    let meta = file.metadata()?;
    if !meta.is_file() {
        return Err(ReadError::NotRegular);
    }
    if meta.len() > limit {
        return Err(ReadError::TooLarge { limit });
    }
    let mut bytes = Vec::with_capacity(meta.len() as usize);
    file.take(limit.saturating_add(1)).read_to_end(&mut bytes)?;
    if bytes.len() as u64 > limit {
        return Err(ReadError::TooLarge { limit });
    }
    Ok(bytes)
}

/// The UTF-8 text of the regular file at `path`, at most `limit` bytes ([`read_bounded`]).
pub fn read_text(path: &Path, limit: u64) -> Result<String, ReadError> {
    String::from_utf8(read_bounded(path, limit)?).map_err(|_| ReadError::NotUtf8)
}

#[cfg(all(test, unix))]
mod tests {
    use super::*;

    #[test]
    fn regular_files_within_the_limit_only() {
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("a.txt");
        std::fs::write(&f, "hello").unwrap();
        assert_eq!(read_text(&f, 5).unwrap(), "hello");
        assert!(matches!(read_text(&f, 4), Err(ReadError::TooLarge { limit: 4 })));
        std::fs::write(&f, [0xff, 0xfe]).unwrap();
        assert!(matches!(read_text(&f, 5), Err(ReadError::NotUtf8)));
        // A link to a regular file is followed; to a device or a directory it is refused.
        let link = dir.path().join("link");
        std::os::unix::fs::symlink(&f, &link).unwrap();
        assert_eq!(read_bounded(&link, 5).unwrap(), [0xff, 0xfe]);
        let dev = dir.path().join("dev");
        std::os::unix::fs::symlink("/dev/zero", &dev).unwrap();
        assert!(matches!(read_bounded(&dev, 5), Err(ReadError::NotRegular)));
        assert!(matches!(read_bounded(Path::new("/dev/zero"), 5), Err(ReadError::NotRegular)));
        assert!(matches!(read_bounded(dir.path(), 5), Err(ReadError::NotRegular)));
        assert!(matches!(read_bounded(&dir.path().join("missing"), 5), Err(ReadError::Io(_))));
    }
}
