//! Small text files written atomically (temporary name beside the target, then a
//! rename): a reader never sees a half-written report or model file.

use crate::error::{Error, Result};

/// Write a text file atomically (temporary name, rename).
pub fn write_text(path: &std::path::Path, text: &str) -> Result<()> {
    if let Some(d) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(d).map_err(|e| Error::io(d, e))?;
    }
    let tmp = crate::h5io::temp_path(path);
    std::fs::write(&tmp, text).map_err(|e| Error::io(&tmp, e))?;
    std::fs::rename(&tmp, path).map_err(|e| Error::io(path, e))
}
