//! Discover input products: the candidate files of a directory.
//!
//! A file is a candidate when its name ends in `.h5` (or is a FITS exposure, `.fits`,
//! [`crate::product::fits::is_fits`]) and neither starts with `.` nor
//! ends in `.part` (ICD: upstream writes under such temporary names and renames when
//! done); folders whose names start with `.` (the quarantine among them) are not
//! searched. Ordering, gaps and duplicates are the stage's ([`super::run()`]).

use crate::error::{Error, ErrorKind, Result};
use std::path::{Path, PathBuf};

/// Whether a path names a complete product (not a temporary being written).
pub fn is_candidate(path: &Path) -> bool {
    let Some(name) = path.file_name().and_then(|n| n.to_str()) else {
        return false;
    };
    (name.ends_with(".h5") || crate::product::fits::is_fits(path))
        && !name.starts_with('.')
        && !name.ends_with(".part")
}

/// All candidate files under `dir`, sorted by path (deterministic).
pub fn candidates(dir: &Path) -> Result<Vec<PathBuf>> {
    if !dir.is_dir() {
        return Err(Error::new(ErrorKind::Usage, "input is not a directory").path(dir));
    }
    let mut files = Vec::new();
    let walk = walkdir::WalkDir::new(dir)
        .follow_links(true)
        .into_iter()
        .filter_entry(|e| e.depth() == 0 || !e.file_name().to_string_lossy().starts_with('.'));
    for entry in walk {
        match entry {
            Ok(e) if e.file_type().is_file() && is_candidate(e.path()) => files.push(e.into_path()),
            Ok(_) => {}
            // A directory that cannot be read (EIO, EMFILE, ...) hides its products: an
            // error, not an empty listing. Vanished entries and symlink loops are skipped.
            Err(err) => match err.io_error() {
                Some(io) if io.kind() != std::io::ErrorKind::NotFound => {
                    let at = err.path().unwrap_or(dir).to_path_buf();
                    let io = std::io::Error::new(io.kind(), io.to_string());
                    return Err(Error::io(&at, io));
                }
                _ => {}
            },
        }
    }
    files.sort();
    Ok(files)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn temporaries_are_not_candidates() {
        assert!(is_candidate(Path::new("/a/x.h5")));
        assert!(!is_candidate(Path::new("/a/.x.h5")));
        assert!(!is_candidate(Path::new("/a/x.h5.part")));
        assert!(!is_candidate(Path::new("/a/x.part")));
        assert!(is_candidate(Path::new("/a/x.fits")));
        assert!(!is_candidate(Path::new("/a/.x.fits")));
        assert!(!is_candidate(Path::new("/a/x.fits.part")));
        assert!(!is_candidate(Path::new("/a/x.txt")));
    }
}
