//! Bad inputs are moved aside, never deleted: `QUARANTINE/NAME` plus
//! `QUARANTINE/NAME.reason.json` saying what was wrong (kind, field, message,
//! detector, exposure, time). A name already in quarantine gets a numeric suffix.

use crate::error::{Error, Result};
use serde::Serialize;
use std::path::{Path, PathBuf};

#[derive(Debug, Serialize)]
pub struct Reason<'a> {
    pub file: String,
    pub kind: crate::ErrorKind,
    pub field: Option<&'a str>,
    pub message: &'a str,
    pub detector: Option<u8>,
    pub exposure_index: Option<u64>,
    pub quarantined_utc: String,
}

/// Move `path` into `dir` with its reason; returns the new path.
pub fn quarantine(dir: &Path, path: &Path, why: &Error) -> Result<PathBuf> {
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "unnamed".into());
    let mut target = dir.join(&name);
    let mut n = 1;
    while target.exists() {
        target = dir.join(format!("{name}.{n}"));
        n += 1;
    }
    let reason = Reason {
        file: path.display().to_string(),
        kind: why.kind,
        field: why.context.field.as_deref(),
        message: &why.message,
        detector: why.context.detector.map(|d| d.0),
        exposure_index: why.context.exposure,
        quarantined_utc: chrono::Utc::now().to_rfc3339_opts(chrono::SecondsFormat::Secs, true),
    };
    let json_path = PathBuf::from(format!("{}.reason.json", target.display()));
    let text = serde_json::to_string_pretty(&reason).expect("reason serialises");
    std::fs::write(&json_path, text + "\n").map_err(|e| Error::io(&json_path, e))?;
    if std::fs::rename(path, &target).is_err() {
        // Another file system: copy then remove.
        std::fs::copy(path, &target).map_err(|e| Error::io(path, e))?;
        std::fs::remove_file(path).map_err(|e| Error::io(path, e))?;
    }
    Ok(target)
}
