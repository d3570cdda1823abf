//! Small text files written atomically and durably: the text goes to a temporary name
//! beside the target, is synced to disk, then renamed over the target, and the
//! directory is synced. A reader never sees a half-written report, model file or
//! Slurm plan, and a crash after the call returns keeps the whole file.

use crate::error::{Error, Result};
use std::io::Write;
use std::path::Path;

/// Write a text file atomically and durably (parent folders, temporary name,
/// `sync_all`, rename, directory sync).
pub fn write_text(path: &Path, text: &str) -> Result<()> {
    if let Some(d) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(d).map_err(|e| Error::io(d, e))?;
    }
    let tmp = crate::h5io::temp_path(path);
    let mut f = std::fs::File::create(&tmp).map_err(|e| Error::io(&tmp, e))?;
    f.write_all(text.as_bytes())
        .and_then(|_| f.sync_all())
        .map_err(|e| Error::io(&tmp, e))?;
    std::fs::rename(&tmp, path).map_err(|e| Error::io(path, e))?;
    crate::h5io::sync_dir(path)
}
