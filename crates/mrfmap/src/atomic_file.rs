//! Atomic file output: write to a temporary file in the same folder, then rename.
//!
//! A crash or an error half-way through never leaves a truncated map, PLY or PNG
//! where the user expects a complete one.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use crate::error::{Error, Result};

/// Writes `path` through `fill`; the file appears (by rename) only if `fill` succeeds.
///
/// ```
/// # let tmp = tempfile::tempdir().unwrap();
/// # let dir = tmp.path();
/// use std::io::Write;
/// let path = dir.join("hello.txt");
/// mrfmap::atomic_file::write_atomic(&path, |w| w.write_all(b"hello")).unwrap();
/// assert_eq!(std::fs::read(&path).unwrap(), b"hello");
/// ```
pub fn write_atomic(path: &Path, fill: impl FnOnce(&mut BufWriter<File>) -> std::io::Result<()>) -> Result<()> {
    let (mut writer, pending) = create_atomic(path)?;
    fill(&mut writer).map_err(|e| Error::io(path, e))?;
    pending.commit(writer)
}

/// A file written over time (a log, a timeline) that appears at its path only when
/// [`Pending::commit`] succeeds: the writer goes to a temporary file beside it, which is
/// removed if the `Pending` is dropped uncommitted.
pub fn create_atomic(path: &Path) -> Result<(BufWriter<File>, Pending)> {
    let tmp = temp_path(path);
    let file = File::create(&tmp).map_err(|e| Error::io(path, e))?;
    Ok((BufWriter::new(file), Pending { path: path.to_path_buf(), tmp, done: false }))
}

/// The temporary file of [`create_atomic`], waiting to be renamed into place.
#[derive(Debug)]
pub struct Pending {
    path: PathBuf,
    tmp: PathBuf,
    done: bool,
}

impl Pending {
    /// Flushes and syncs `writer` (the one [`create_atomic`] gave) and renames its file into
    /// place.
    pub fn commit(mut self, mut writer: BufWriter<File>) -> Result<()> {
        let result = (|| {
            writer.flush()?;
            writer.get_ref().sync_all()?;
            drop(writer);
            std::fs::rename(&self.tmp, &self.path)
        })();
        self.done = result.is_ok();
        result.map_err(|e| Error::io(&self.path, e))
    }
}

impl Drop for Pending {
    fn drop(&mut self) {
        if !self.done {
            let _ = std::fs::remove_file(&self.tmp);
        }
    }
}

/// `dir/.name.PID.tmp`: same folder (so the rename is atomic), hidden, unique per process.
fn temp_path(path: &Path) -> PathBuf {
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    path.with_file_name(format!(".{name}.{}.tmp", std::process::id()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn failed_fill_leaves_no_file() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path();
        let path = dir.join("out.bin");
        let err = write_atomic(&path, |w| {
            w.write_all(b"partial")?;
            Err(std::io::Error::other("boom"))
        })
        .unwrap_err();
        assert!(err.to_string().contains("out.bin"), "{err}");
        assert!(!path.exists());
        assert_eq!(std::fs::read_dir(dir).unwrap().count(), 0, "temporary file left behind");
    }
}
