//! The start-up every writer of a stage's directories goes through: `persist run`, its
//! worker processes, the Python `persist.run` and `persist assemble` (the end of a
//! `persist slurm` split).
//!
//! 1. **Lock** the output and checkpoint directories (created if missing,
//!    [`super::lock::DirLock`]): one stage per set of directories.
//! 2. **Clean temporaries**: with the lock held nothing else writes there, so every
//!    `.NAME.part` left is from an interrupted write of ours
//!    ([`crate::checkpoint::clean_temporaries`]).
//! 3. **Signals** (the command line only; Python keeps its own): SIGINT and SIGTERM set
//!    the stop flag the stage checks between exposures; a second one exits at once
//!    (status 130).
//!
//! A worker process runs under its parent's lock ([`super::workers`]): it takes neither
//! the lock nor the cleaning, only the signals.

use super::lock::DirLock;
use crate::error::{Error, ErrorKind, Result};
use std::path::Path;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

/// What a start-up takes.
#[derive(Debug, Clone, Copy)]
pub struct Startup {
    /// Lock the directories and clean their temporaries (false: a worker under its
    /// parent's lock).
    pub lock: bool,
    /// Install the SIGINT/SIGTERM handlers.
    pub signals: bool,
}

/// What a start-up holds until the stage ends: the lock (released on drop) and the
/// stop flag the signal handlers set.
#[derive(Debug)]
pub struct Started {
    _lock: Option<DirLock>,
    pub stop: Arc<AtomicBool>,
}

/// Start a stage on `dirs` (the output and checkpoint directories), as `how` says.
pub fn start(dirs: &[&Path], how: Startup) -> Result<Started> {
    let lock = if how.lock {
        let lock = DirLock::acquire(dirs)?;
        for dir in dirs {
            let n = crate::checkpoint::clean_temporaries(dir)?;
            if n > 0 {
                tracing::info!(dir = %dir.display(), removed = n, "stray temporary files removed");
            }
        }
        Some(lock)
    } else {
        None
    };
    let stop = Arc::new(AtomicBool::new(false));
    if how.signals {
        for sig in [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM] {
            // A second signal while stopping exits at once (status 130).
            signal_hook::flag::register_conditional_shutdown(sig, 130, Arc::clone(&stop))
                .and_then(|_| signal_hook::flag::register(sig, Arc::clone(&stop)))
                .map_err(|e| {
                    Error::new(ErrorKind::Io, format!("cannot install signal handler: {e}"))
                })?;
        }
    }
    Ok(Started { _lock: lock, stop })
}
