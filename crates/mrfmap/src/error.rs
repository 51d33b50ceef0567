//! The library's error type.
//!
//! Every error that comes from a file names that file, so a user reading
//! `mrfmap: dataset/camera.toml: missing field `fx`` knows where to look.

use std::path::{Path, PathBuf};

/// Everything that can go wrong in `mrfmap`.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The operating system refused a read or write.
    ///
    /// The operating system's message is part of this error's text, not a separate `source`,
    /// so that printing the error chain (`{:#}`) says it once.
    #[error("{}: {error}", path.display())]
    Io {
        /// The file or folder that was being accessed.
        path: PathBuf,
        /// What the operating system said.
        error: std::io::Error,
    },
    /// A file was read but its content is wrong (bad key, wrong size, corrupt, ...).
    #[error("{}: {message}", path.display())]
    File {
        /// The offending file.
        path: PathBuf,
        /// What is wrong with it.
        message: String,
    },
    /// An argument or parameter is out of range (resolution <= 0, unknown engine, ...).
    #[error("{0}")]
    Invalid(String),
    /// The work would need more memory than the limit ([`crate::limits::max_memory`]) allows:
    /// refused before it starts, or as soon as it outgrows the limit. The message says what
    /// the work was, the estimate or resident size, the limit and what to change.
    #[error("{0}")]
    Memory(String),
}

impl Error {
    /// An I/O error on `path`.
    pub fn io(path: impl AsRef<Path>, source: std::io::Error) -> Self {
        Error::Io { path: path.as_ref().to_path_buf(), error: source }
    }

    /// A content error in the file `path`.
    pub fn file(path: impl AsRef<Path>, message: impl Into<String>) -> Self {
        Error::File { path: path.as_ref().to_path_buf(), message: message.into() }
    }
}

/// `Result` with [`Error`].
pub type Result<T, E = Error> = std::result::Result<T, E>;

/// Reads a whole text file, naming it in the error.
pub(crate) fn read_text(path: &Path) -> Result<String> {
    std::fs::read_to_string(path).map_err(|e| Error::io(path, e))
}

/// Parses TOML into `T`, naming the file in the error (toml's messages give line and key).
pub(crate) fn parse_toml<T: serde::de::DeserializeOwned>(text: &str, path: &Path) -> Result<T> {
    toml::from_str(text).map_err(|e| Error::file(path, e.to_string().trim_end().to_string()))
}
