//! One stage per set of directories: an exclusive advisory lock (`flock`) on
//! `.persist.lock` in the output and the checkpoint directories. The kernel drops the
//! lock when the process ends, however it ends (SIGKILL included), so a stale lock file
//! never blocks a restart; the file's text (pid, start time) only helps a human.

use crate::error::{Error, ErrorKind, Result};
use std::fs::{File, OpenOptions, TryLockError};
use std::io::Write;
use std::path::{Path, PathBuf};

pub const LOCK_NAME: &str = ".persist.lock";

/// Held locks; released on drop.
#[derive(Debug)]
pub struct DirLock {
    _files: Vec<(PathBuf, File)>,
}

impl DirLock {
    /// Lock every directory (created if missing), or fail naming the one already held.
    pub fn acquire(dirs: &[&Path]) -> Result<DirLock> {
        let mut files = Vec::new();
        let mut seen: Vec<PathBuf> = Vec::new();
        for dir in dirs {
            std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
            let canon = dir.canonicalize().map_err(|e| Error::io(dir, e))?;
            if seen.contains(&canon) {
                continue;
            }
            seen.push(canon);
            let path = dir.join(LOCK_NAME);
            let mut file = OpenOptions::new()
                .create(true)
                .truncate(false)
                .read(true)
                .write(true)
                .open(&path)
                .map_err(|e| Error::io(&path, e))?;
            match file.try_lock() {
                Ok(()) => {}
                Err(TryLockError::WouldBlock) => {
                    let holder = std::fs::read_to_string(&path).unwrap_or_default();
                    return Err(Error::new(
                        ErrorKind::Locked,
                        format!(
                            "another persist stage is using this directory ({}); stop it first",
                            holder.trim()
                        ),
                    )
                    .path(dir));
                }
                Err(TryLockError::Error(e)) => return Err(Error::io(&path, e)),
            }
            file.set_len(0).map_err(|e| Error::io(&path, e))?;
            let _ = writeln!(
                file,
                "pid {} since {}",
                std::process::id(),
                chrono::Utc::now().to_rfc3339_opts(chrono::SecondsFormat::Secs, true)
            );
            files.push((path, file));
        }
        Ok(DirLock { _files: files })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn second_lock_is_refused_until_the_first_is_dropped() {
        let tmp = tempfile::tempdir().unwrap();
        let (a, b) = (tmp.path().join("out"), tmp.path().join("ckpt"));
        let first = DirLock::acquire(&[&a, &b]).unwrap();
        let err = DirLock::acquire(&[&b]).unwrap_err();
        assert_eq!(err.kind, ErrorKind::Locked);
        assert!(err.to_string().contains("another persist stage"), "{err}");
        drop(first);
        DirLock::acquire(&[&a, &b]).unwrap();
    }
}
