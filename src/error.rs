//! Errors: a small struct with a kind and the context it concerns (file, detector,
//! exposure, field), in the manner of ripgrep. Every error shown to a user names
//! what it is about; the stage reports one error per file and goes on.

use crate::units::{DetectorId, ExposureIndex};
use std::fmt;
use std::path::{Path, PathBuf};

/// What went wrong, coarsely: callers decide on this (quarantine, retry, stop).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ErrorKind {
    /// Reading or writing a file failed at the OS level.
    Io,
    /// The HDF5 library refused the file (truncated, corrupt, not HDF5).
    Hdf5,
    /// The reader of the file (the HDF5 or CFITSIO library, in its isolated child
    /// process, [`crate::guard`]) crashed, hung or exceeded its limits on it.
    Crash,
    /// A product or checkpoint does not match its JSON Schema / the ICD.
    Invalid,
    /// An exposure does not fit the detector's history (order, timing, duplicate).
    Sequence,
    /// A model file is malformed or inconsistent.
    Model,
    /// A checkpoint cannot be used (format, model identity, shape).
    Checkpoint,
    /// The file is still being written by someone else; try again later.
    NotReady,
    /// Another stage holds the lock on these directories.
    Locked,
    /// Command-line usage.
    Usage,
}

/// Where an error applies. Every part is optional; the more is known the better.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Context {
    pub path: Option<PathBuf>,
    pub detector: Option<DetectorId>,
    pub exposure: Option<ExposureIndex>,
    pub field: Option<String>,
}

#[derive(Debug)]
pub struct Error {
    pub kind: ErrorKind,
    pub context: Context,
    pub message: String,
}

pub type Result<T, E = Error> = std::result::Result<T, E>;

impl Error {
    pub fn new(kind: ErrorKind, message: impl Into<String>) -> Self {
        Error {
            kind,
            context: Context::default(),
            message: message.into(),
        }
    }

    pub fn invalid(field: impl Into<String>, message: impl Into<String>) -> Self {
        Error::new(ErrorKind::Invalid, message).field(field)
    }

    pub fn io(path: &Path, e: std::io::Error) -> Self {
        Error::new(ErrorKind::Io, e.to_string()).path(path)
    }

    /// Attach the file this error concerns (kept if already set).
    pub fn path(mut self, path: impl AsRef<Path>) -> Self {
        self.context
            .path
            .get_or_insert_with(|| path.as_ref().to_path_buf());
        self
    }

    pub fn field(mut self, field: impl Into<String>) -> Self {
        self.context.field.get_or_insert_with(|| field.into());
        self
    }

    pub fn detector(mut self, d: DetectorId) -> Self {
        self.context.detector.get_or_insert(d);
        self
    }

    pub fn exposure(mut self, i: ExposureIndex) -> Self {
        self.context.exposure.get_or_insert(i);
        self
    }
}

impl fmt::Display for Error {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let c = &self.context;
        if let Some(p) = &c.path {
            write!(f, "{}: ", p.display())?;
        }
        if let Some(d) = c.detector {
            write!(f, "detector {d}: ")?;
        }
        if let Some(i) = c.exposure {
            write!(f, "exposure {i}: ")?;
        }
        if let Some(field) = &c.field {
            write!(f, "field `{field}`: ")?;
        }
        f.write_str(&self.message)
    }
}

impl std::error::Error for Error {}

impl From<hdf5::Error> for Error {
    fn from(e: hdf5::Error) -> Self {
        let text = e.to_string();
        // A file still open for writing by another process cannot be locked (errno 11).
        let kind = if text.contains("unable to lock file") {
            ErrorKind::NotReady
        } else if os_errno(&text).is_some() {
            // A system call failed (EIO, ENOSPC, EMFILE, ...): the disk or the system,
            // not the file's content; the file is not refused for it.
            ErrorKind::Io
        } else {
            ErrorKind::Hdf5
        };
        Error::new(kind, text)
    }
}

/// The nonzero `errno = N` HDF5 writes into its message when a system call of its file
/// driver failed (`unable to open file: ..., errno = 5, error message = '...'`); HDF5
/// reports a malformed file without one.
fn os_errno(text: &str) -> Option<i32> {
    text.split("errno = ")
        .skip(1)
        .filter_map(|rest| {
            let digits: String = rest.chars().take_while(char::is_ascii_digit).collect();
            digits.parse::<i32>().ok()
        })
        .find(|&n| n != 0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hdf5_system_call_failures_are_io_not_content() {
        // The message of HDF5 1.10's sec2 driver (H5FDsec2.c) for a failed open.
        let text = "unable to open file: name = 'in/a.h5', errno = 5, error message = \
                    'Input/output error', flags = 0, o_flags = 0";
        assert_eq!(os_errno(text), Some(5));
        assert_eq!(os_errno("file signature not found"), None);
        assert_eq!(os_errno("errno = 0, error message = 'Success'"), None);
    }

    #[test]
    fn display_names_file_field_and_reason() {
        let e = Error::invalid("t_exposure_s", "must be > 0, got -1")
            .path("/in/a.h5")
            .detector(DetectorId(2))
            .exposure(7);
        assert_eq!(
            e.to_string(),
            "/in/a.h5: detector 2: exposure 7: field `t_exposure_s`: must be > 0, got -1"
        );
    }
}
