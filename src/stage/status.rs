//! `persist status`: what the stage has done and what waits, per detector, read from the
//! directories only (safe while a stage runs: it reads final names, never temporaries,
//! and takes no lock).
//!
//! Per detector: the last exposure processed (the newest checkpoint's key), the age of
//! that checkpoint (from its file time), the gaps the history crossed and how long the
//! outputs stay "history incomplete" (its bookkeeping), the backlog (inputs with a later
//! index, with `--input`) and the indices missing before them, and the quarantined files
//! (their reason files: refused inputs, and checkpoints a resume set aside as unreadable,
//! under `CHECKPOINTS/.quarantine`).
//!
//! A checkpoint is read as the stage reads it: with a guard, checked whole in the reader
//! guard's child process first ([`crate::guard::load_checkpoint_meta`]), so a library
//! crash on a malformed checkpoint is a problem listed, not the end of `status`.

use crate::checkpoint;
use crate::error::Error;
use crate::product;
use crate::stage::queue;
use crate::stage::run::Bookkeeping;
use crate::units::{DetectorId, UtcSeconds};
use serde::Serialize;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

#[derive(Debug, Clone, Serialize)]
pub struct Quarantined {
    pub file: PathBuf,
    pub kind: String,
    pub field: Option<String>,
    pub message: String,
}

#[derive(Debug, Clone, Default, Serialize)]
pub struct DetectorStatus {
    pub detector: u8,
    pub last_processed: Option<u64>,
    pub checkpoint: Option<PathBuf>,
    pub checkpoint_age_s: Option<f64>,
    pub checkpoints: usize,
    /// Bytes of this detector's checkpoint files.
    pub checkpoint_bytes: u64,
    pub crossed_gaps: Vec<(u64, u64)>,
    pub history_incomplete_until_utc: Option<String>,
    /// Inputs with an index after the last processed one (needs `--input`).
    pub backlog: usize,
    /// Index ranges missing before the newest queued input (what the backlog waits for).
    pub missing: Vec<(u64, u64)>,
    pub quarantined: Vec<Quarantined>,
}

#[derive(Debug, Clone, Default, Serialize)]
pub struct Status {
    pub detectors: Vec<DetectorStatus>,
    /// Quarantined files that could not be attributed to a detector.
    pub quarantined_unattributed: Vec<Quarantined>,
    /// Output products published (files `*.h5` in the output directory).
    pub outputs: usize,
    /// Input products whose header cannot be read (needs `--input`).
    pub unreadable_inputs: usize,
    pub problems: Vec<String>,
    /// The checkpoint footprint a long history would leave ([`project`]).
    pub projection: Option<Projection>,
}

/// The checkpoint footprint of one detector after `exposures` exposures taken every
/// `interval_s` seconds, under a retention rule, at the mean size of the checkpoints on
/// disk.
#[derive(Debug, Clone, Serialize)]
pub struct Projection {
    pub exposures: u64,
    pub interval_s: f64,
    pub checkpoints: usize,
    /// Mean bytes of one checkpoint file (all detectors' files on disk).
    pub checkpoint_bytes: u64,
    pub total_bytes: u64,
}

/// Project the footprint of `retention` from the checkpoints `st` found (none: `None`).
pub fn project(
    st: &Status,
    retention: &crate::checkpoint::Retention,
    exposures: u64,
    interval_s: f64,
) -> Option<Projection> {
    let files: usize = st.detectors.iter().map(|d| d.checkpoints).sum();
    let bytes: u64 = st.detectors.iter().map(|d| d.checkpoint_bytes).sum();
    let mean = bytes.checked_div(files as u64)?;
    let n = retention.projected_count(exposures, interval_s);
    Some(Projection {
        exposures,
        interval_s,
        checkpoints: n,
        checkpoint_bytes: mean,
        total_bytes: mean * n as u64,
    })
}

fn missing_ranges(from: u64, present: &[u64]) -> Vec<(u64, u64)> {
    let mut out = Vec::new();
    let mut expect = from;
    for &i in present {
        if i > expect {
            out.push((expect, i - 1));
        }
        expect = expect.max(i + 1);
    }
    out
}

/// Gather the status of the directories.
pub fn status(
    output: &Path,
    checkpoints: &Path,
    input: Option<&Path>,
    quarantine: Option<&Path>,
    guard: Option<&crate::guard::Guard>,
) -> Status {
    let mut st = Status::default();
    let mut dets: BTreeMap<u8, DetectorStatus> = BTreeMap::new();
    let now = std::time::SystemTime::now();
    for d in DetectorId::MIN..=DetectorId::MAX {
        let det = DetectorId(d);
        let list = match checkpoint::list(checkpoints, det) {
            Ok(l) => l,
            Err(e) => {
                st.problems.push(e.to_string());
                continue;
            }
        };
        let Some((index, path)) = list.last().cloned() else {
            continue;
        };
        let mut ds = DetectorStatus {
            detector: d,
            last_processed: Some(index),
            checkpoints: list.len(),
            checkpoint_bytes: list
                .iter()
                .filter_map(|(_, p)| std::fs::metadata(p).ok())
                .map(|m| m.len())
                .sum(),
            checkpoint_age_s: std::fs::metadata(&path)
                .and_then(|m| m.modified())
                .ok()
                .and_then(|t| now.duration_since(t).ok())
                .map(|a| a.as_secs_f64()),
            checkpoint: Some(path.clone()),
            ..Default::default()
        };
        match crate::guard::load_checkpoint_meta(guard, &path) {
            Ok((meta, _)) => match serde_json::from_str::<Bookkeeping>(&meta.stage_json) {
                Ok(b) => {
                    ds.crossed_gaps = b.crossed;
                    ds.history_incomplete_until_utc = b
                        .history_incomplete_until_unix_s
                        .map(|u| UtcSeconds(u).to_iso());
                }
                Err(e) => st
                    .problems
                    .push(format!("{}: stage_json: {e}", path.display())),
            },
            Err(e) => st.problems.push(e.to_string()),
        }
        dets.insert(d, ds);
    }
    st.outputs = queue::candidates(output).map_or(0, |v| v.len());
    if let Some(input) = input {
        match queue::candidates(input) {
            Ok(files) => {
                let mut queued: BTreeMap<u8, Vec<u64>> = BTreeMap::new();
                for f in files {
                    match product::read::read_meta(&f) {
                        Ok(m) => {
                            let last = dets.get(&m.detector.0).and_then(|d| d.last_processed);
                            if last.is_none_or(|l| m.exposure_index > l) {
                                queued
                                    .entry(m.detector.0)
                                    .or_default()
                                    .push(m.exposure_index);
                            }
                        }
                        Err(_) => st.unreadable_inputs += 1,
                    }
                }
                for (d, mut v) in queued {
                    v.sort_unstable();
                    v.dedup();
                    let ds = dets.entry(d).or_insert_with(|| DetectorStatus {
                        detector: d,
                        ..Default::default()
                    });
                    let from = ds.last_processed.map_or(v[0], |l| l + 1);
                    ds.backlog = v.len();
                    ds.missing = missing_ranges(from, &v);
                }
            }
            Err(e) => st.problems.push(e.to_string()),
        }
    }
    // Refused inputs, and checkpoints set aside on resume (`super::fallback`).
    let ckpt_q = super::fallback::quarantine_dir(checkpoints);
    for q in quarantine.into_iter().chain([ckpt_q.as_path()]) {
        add_quarantined(q, &mut st, &mut dets);
    }
    st.detectors = dets.into_values().collect();
    st
}

/// Add the reason files of quarantine directory `q` to their detectors (or to the
/// unattributed list).
fn add_quarantined(q: &Path, st: &mut Status, dets: &mut BTreeMap<u8, DetectorStatus>) {
    if q.is_dir() {
        match std::fs::read_dir(q) {
            Ok(entries) => {
                let mut reasons: Vec<PathBuf> = entries
                    .filter_map(|e| e.ok().map(|e| e.path()))
                    .filter(|p| p.to_string_lossy().ends_with(".reason.json"))
                    .collect();
                reasons.sort();
                for r in reasons {
                    match read_reason(&r) {
                        Ok((det, item)) => {
                            match det.filter(|d| (DetectorId::MIN..=DetectorId::MAX).contains(d)) {
                                Some(d) => dets
                                    .entry(d)
                                    .or_insert_with(|| DetectorStatus {
                                        detector: d,
                                        ..Default::default()
                                    })
                                    .quarantined
                                    .push(item),
                                None => st.quarantined_unattributed.push(item),
                            }
                        }
                        Err(e) => st.problems.push(e.to_string()),
                    }
                }
            }
            Err(e) => st.problems.push(Error::io(q, e).to_string()),
        }
    }
}

fn read_reason(path: &Path) -> crate::Result<(Option<u8>, Quarantined)> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    let v: serde_json::Value = serde_json::from_str(&text)
        .map_err(|e| Error::invalid("reason", format!("not JSON: {e}")).path(path))?;
    let s = |k: &str| v.get(k).and_then(|x| x.as_str()).map(str::to_owned);
    let det = v
        .get("detector")
        .and_then(|x| x.as_u64())
        .and_then(|d| u8::try_from(d).ok());
    let name = path.to_string_lossy();
    let file = PathBuf::from(name.trim_end_matches(".reason.json"));
    Ok((
        det,
        Quarantined {
            file,
            kind: s("kind").unwrap_or_default(),
            field: s("field"),
            message: s("message").unwrap_or_default(),
        },
    ))
}

/// Human-readable rendering.
pub fn render(st: &Status) -> String {
    use std::fmt::Write;
    let mut out = String::new();
    let _ = writeln!(
        out,
        "{:>3} {:>10} {:>12} {:>6} {:>10} {:>8} {:<20} {:<20} {:>11}",
        "det",
        "last",
        "ckpt age",
        "ckpts",
        "ckpt MB",
        "backlog",
        "missing",
        "crossed gaps",
        "quarantined"
    );
    let ranges = |v: &[(u64, u64)]| {
        if v.is_empty() {
            "-".to_string()
        } else {
            v.iter()
                .map(|(a, b)| {
                    if a == b {
                        format!("{a}")
                    } else {
                        format!("{a}-{b}")
                    }
                })
                .collect::<Vec<_>>()
                .join(",")
        }
    };
    for d in &st.detectors {
        let _ = writeln!(
            out,
            "{:>3} {:>10} {:>12} {:>6} {:>10.1} {:>8} {:<20} {:<20} {:>11}",
            d.detector,
            d.last_processed.map_or("-".into(), |i| i.to_string()),
            d.checkpoint_age_s
                .map_or("-".into(), |a| format!("{a:.0} s")),
            d.checkpoints,
            d.checkpoint_bytes as f64 / 1e6,
            d.backlog,
            ranges(&d.missing),
            ranges(&d.crossed_gaps),
            d.quarantined.len()
        );
    }
    for d in &st.detectors {
        for q in &d.quarantined {
            let _ = writeln!(
                out,
                "quarantined (detector {}): {}: {} {}: {}",
                d.detector,
                q.file.display(),
                q.kind,
                q.field.as_deref().unwrap_or("-"),
                q.message
            );
        }
    }
    for q in &st.quarantined_unattributed {
        let _ = writeln!(
            out,
            "quarantined: {}: {} {}: {}",
            q.file.display(),
            q.kind,
            q.field.as_deref().unwrap_or("-"),
            q.message
        );
    }
    let _ = writeln!(out, "outputs published: {}", st.outputs);
    if let Some(p) = &st.projection {
        let _ = writeln!(
            out,
            "projected checkpoints per detector after {} exposures every {:.0} s under this \
             retention: {} x {:.1} MB = {:.1} GB",
            p.exposures,
            p.interval_s,
            p.checkpoints,
            p.checkpoint_bytes as f64 / 1e6,
            p.total_bytes as f64 / 1e9
        );
    }
    if st.unreadable_inputs > 0 {
        let _ = writeln!(out, "unreadable inputs: {}", st.unreadable_inputs);
    }
    for p in &st.problems {
        let _ = writeln!(out, "problem: {p}");
    }
    out
}
