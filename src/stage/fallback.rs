//! Resuming past an unreadable checkpoint: a detector resumes from its newest checkpoint
//! that reads and checks whole (through the reader guard when the run has one,
//! [`crate::guard`]); each newer one that does not (its reader crashed, hung, or
//! refused it) is moved to `CHECKPOINTS/.quarantine/` with a reason file, as a refused
//! input is ([`super::quarantine`]), and reported as an error of the run. `persist
//! status` lists it among the detector's quarantined files; the stage replays the
//! exposures after the checkpoint it resumed from, rewriting no published output.
//!
//! A checkpoint that cannot be opened for a reason that is not its content (an I/O
//! error, or a lock held elsewhere) stops the detector instead: moving it aside would
//! lose a good checkpoint.

use crate::checkpoint::{self, CheckpointMeta};
use crate::error::{Error, ErrorKind, Result};
use crate::model::State;
use crate::units::DetectorId;
use std::path::{Path, PathBuf};

/// The newest usable checkpoint of a detector, and what was set aside on the way.
pub struct Newest {
    pub found: Option<(PathBuf, CheckpointMeta, State)>,
    /// One error per checkpoint moved aside (naming it and why).
    pub skipped: Vec<Error>,
}

/// Where unreadable checkpoints go: `CHECKPOINTS/.quarantine`.
pub fn quarantine_dir(checkpoints: &Path) -> PathBuf {
    checkpoints.join(".quarantine")
}

/// Walk `det`'s checkpoints under `checkpoints` from the newest back to the first that
/// loads, each read through `guard` when there is one.
pub fn newest_readable(
    checkpoints: &Path,
    guard: Option<&crate::guard::Guard>,
    det: DetectorId,
) -> Result<Newest> {
    let mut skipped = Vec::new();
    let mut list = checkpoint::list(checkpoints, det)?;
    while let Some((index, path)) = list.pop() {
        match crate::guard::load_checkpoint(guard, &path) {
            Ok((meta, state)) => {
                return Ok(Newest {
                    found: Some((path, meta, state)),
                    skipped,
                })
            }
            Err(e) if matches!(e.kind, ErrorKind::Io | ErrorKind::NotReady) => return Err(e),
            Err(e) => {
                let e = e.path(&path).detector(det).exposure(index);
                let moved = super::quarantine::quarantine(&quarantine_dir(checkpoints), &path, &e)?;
                tracing::warn!(path = %path.display(), quarantined = %moved.display(),
                    error = %e, "checkpoint unreadable: set aside, resuming from the one before it");
                skipped.push(Error::new(
                    e.kind,
                    format!(
                        "checkpoint unreadable ({}); moved to {}, resuming from the checkpoint before it",
                        e.message,
                        moved.display()
                    ),
                )
                .path(&path)
                .detector(det)
                .exposure(index));
            }
        }
    }
    Ok(Newest {
        found: None,
        skipped,
    })
}
