//! Discover input products and order each detector's history.
//!
//! A file is a candidate when its name ends in `.h5` and neither starts with `.` nor
//! ends in `.part` (ICD: upstream writes under such temporary names and renames when
//! done). Each detector's products are ordered by exposure index. Two files with the
//! same (detector, exposure index): identical bytes -> the copy is ignored; different
//! bytes -> the copy is refused loudly (the first by path order is kept, the other is
//! reported as an error of kind `Sequence`). Output names are the input file names, so
//! two inputs with the same file name in different folders are refused too.

use crate::error::{Error, ErrorKind, Result};
use crate::product::ExposureMeta;
use crate::units::DetectorId;
use sha2::{Digest, Sha256};
use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};

/// One input product found on disk, with its root attributes.
#[derive(Debug, Clone)]
pub struct Entry {
    pub path: PathBuf,
    pub meta: ExposureMeta,
}

/// Each detector's products in exposure-index order, and what could not be queued.
#[derive(Debug, Default)]
pub struct Plan {
    pub detectors: BTreeMap<DetectorId, Vec<Entry>>,
    pub errors: Vec<Error>,
    /// Exact copies of a queued product, ignored.
    pub ignored_copies: Vec<PathBuf>,
}

/// Whether a path names a complete product (not a temporary being written).
pub fn is_candidate(path: &Path) -> bool {
    let Some(name) = path.file_name().and_then(|n| n.to_str()) else {
        return false;
    };
    name.ends_with(".h5") && !name.starts_with('.') && !name.ends_with(".part")
}

/// All candidate files under `dir`, sorted by path (deterministic).
pub fn candidates(dir: &Path) -> Result<Vec<PathBuf>> {
    if !dir.is_dir() {
        return Err(Error::new(ErrorKind::Usage, "input is not a directory").path(dir));
    }
    let mut files: Vec<PathBuf> = walkdir::WalkDir::new(dir)
        .follow_links(true)
        .into_iter()
        .filter_entry(|e| e.depth() == 0 || !e.file_name().to_string_lossy().starts_with('.'))
        .filter_map(|e| e.ok())
        .filter(|e| e.file_type().is_file() && is_candidate(e.path()))
        .map(|e| e.into_path())
        .collect();
    files.sort();
    Ok(files)
}

fn file_digest(path: &Path) -> Result<[u8; 32]> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    Ok(Sha256::digest(&bytes).into())
}

/// Read every candidate's root attributes with `read_meta` and order the histories.
pub fn plan(files: &[PathBuf], read_meta: impl Fn(&Path) -> Result<ExposureMeta>) -> Plan {
    let mut plan = Plan::default();
    let mut by_key: HashMap<(DetectorId, u64), PathBuf> = HashMap::new();
    let mut by_name: HashMap<std::ffi::OsString, PathBuf> = HashMap::new();
    for path in files {
        let meta = match read_meta(path) {
            Ok(m) => m,
            Err(e) => {
                plan.errors.push(e.path(path));
                continue;
            }
        };
        let key = (meta.detector, meta.exposure_index);
        if let Some(first) = by_key.get(&key) {
            match (file_digest(first), file_digest(path)) {
                (Ok(a), Ok(b)) if a == b => plan.ignored_copies.push(path.clone()),
                (Err(e), _) | (_, Err(e)) => plan.errors.push(e),
                _ => plan.errors.push(
                    Error::new(
                        ErrorKind::Sequence,
                        format!(
                            "duplicate of {} (same detector and exposure index) with different content: refused",
                            first.display()
                        ),
                    )
                    .path(path)
                    .field("exposure_index")
                    .detector(meta.detector)
                    .exposure(meta.exposure_index),
                ),
            }
            continue;
        }
        let name = path.file_name().unwrap_or_default().to_os_string();
        if let Some(other) = by_name.get(&name) {
            plan.errors.push(
                Error::new(
                    ErrorKind::Sequence,
                    format!(
                        "same file name as {}: the output names would collide",
                        other.display()
                    ),
                )
                .path(path),
            );
            continue;
        }
        by_name.insert(name, path.clone());
        by_key.insert(key, path.clone());
        plan.detectors
            .entry(meta.detector)
            .or_default()
            .push(Entry {
                path: path.clone(),
                meta,
            });
    }
    for entries in plan.detectors.values_mut() {
        entries.sort_by_key(|e| e.meta.exposure_index);
    }
    plan
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
        assert!(!is_candidate(Path::new("/a/x.fits")));
    }
}
