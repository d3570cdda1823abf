//! The per-run table of what each exposure flagged (`persist run --table FILE`): one CSV
//! row per detector and exposure processed, with the statistics every output product
//! carries as attributes of `/persistence` ([`crate::product::FlagStats`]).
//!
//! Invariants: the file starts with [`HEADER`]; every row is appended with one `write`
//! of a whole line on a file opened for appending, so rows of several worker processes
//! of one run never interleave; a crash leaves complete rows only (at most the last one
//! missing). When the run ends the rows are sorted by (detector, exposure index) and the
//! file replaced atomically (written beside it, synced, renamed). Fractions are written
//! in Rust's shortest round-trip form, so a reader gets the attribute's exact value back.

use crate::error::{Error, ErrorKind, Result};
use crate::plot::{line_chart_png, Chart, Series};
use crate::product::FlagStats;
use crate::stage::ExposureReport;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Mutex;

/// The first line of every table.
pub const HEADER: &str = "detector,exposure_index,pixels,fraction_above_high,fraction_above_low,\
n_flagged,released,t_meas_s,history_incomplete,written";

/// One row of the table.
#[derive(Debug, Clone, PartialEq)]
pub struct Row {
    pub detector: u8,
    pub exposure_index: u64,
    pub pixels: u64,
    pub stats: FlagStats,
    /// Pixels released early (bit 3).
    pub released: u64,
    /// NaN for the first exposure of a history.
    pub t_meas_s: f64,
    pub history_incomplete: bool,
    /// false when the output was already published by an earlier run and left alone.
    pub written: bool,
}

impl Row {
    /// The row of one processed exposure.
    pub fn of(r: &ExposureReport) -> Row {
        let s = &r.summary;
        Row {
            detector: r.detector,
            exposure_index: r.exposure_index,
            pixels: s.pixels,
            stats: FlagStats::from_counts(s.pixels, s.above_high, s.above_low),
            released: s.released,
            t_meas_s: s.t_meas_s.unwrap_or(f64::NAN),
            history_incomplete: r.history_incomplete,
            written: r.written,
        }
    }

    fn line(&self) -> String {
        format!(
            "{},{},{},{:?},{:?},{},{},{:?},{},{}\n",
            self.detector,
            self.exposure_index,
            self.pixels,
            self.stats.fraction_above_high,
            self.stats.fraction_above_low,
            self.stats.n_flagged,
            self.released,
            self.t_meas_s,
            self.history_incomplete,
            self.written
        )
    }

    fn parse(line: &str) -> std::result::Result<Row, String> {
        let f: Vec<&str> = line.split(',').collect();
        if f.len() != 10 {
            return Err(format!("{} fields, expected 10", f.len()));
        }
        let int = |i: usize| {
            f[i].parse::<u64>()
                .map_err(|e| format!("field {}: {e}", i + 1))
        };
        let float = |i: usize| {
            f[i].parse::<f64>()
                .map_err(|e| format!("field {}: {e}", i + 1))
        };
        let boolean = |i: usize| {
            f[i].parse::<bool>()
                .map_err(|e| format!("field {}: {e}", i + 1))
        };
        Ok(Row {
            detector: f[0].parse().map_err(|e| format!("field 1: {e}"))?,
            exposure_index: int(1)?,
            pixels: int(2)?,
            stats: FlagStats {
                fraction_above_high: float(3)?,
                fraction_above_low: float(4)?,
                n_flagged: int(5)?,
            },
            released: int(6)?,
            t_meas_s: float(7)?,
            history_incomplete: boolean(8)?,
            written: boolean(9)?,
        })
    }
}

/// The table of a run, open for appending.
#[derive(Debug)]
pub struct RunTable {
    path: PathBuf,
    file: Mutex<std::fs::File>,
}

impl RunTable {
    /// Start the table of a new run: any earlier file at `path` is replaced by the header.
    pub fn create(path: &Path) -> Result<RunTable> {
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
        }
        std::fs::write(path, format!("{HEADER}\n")).map_err(|e| Error::io(path, e))?;
        Self::append_to(path)
    }

    /// Append to the table a parent process created ([`RunTable::create`]).
    pub fn append_to(path: &Path) -> Result<RunTable> {
        let file = std::fs::OpenOptions::new()
            .append(true)
            .open(path)
            .map_err(|e| Error::io(path, e))?;
        Ok(RunTable {
            path: path.to_path_buf(),
            file: Mutex::new(file),
        })
    }

    /// Append the row of one processed exposure (one `write` of the whole line).
    pub fn append(&self, r: &ExposureReport) -> Result<()> {
        let line = Row::of(r).line();
        let mut f = self
            .file
            .lock()
            .map_err(|_| Error::new(ErrorKind::Io, "table lock poisoned").path(&self.path))?;
        f.write_all(line.as_bytes())
            .map_err(|e| Error::io(&self.path, e))
    }
}

/// Read a table ([`HEADER`] and rows), naming the line of any malformed row.
pub fn read(path: &Path) -> Result<Vec<Row>> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    let mut lines = text.lines();
    if lines.next() != Some(HEADER) {
        return Err(Error::invalid("header", format!("line 1 is not `{HEADER}`")).path(path));
    }
    lines
        .enumerate()
        .filter(|(_, l)| !l.is_empty())
        .map(|(i, l)| {
            Row::parse(l).map_err(|m| Error::invalid(format!("line {}", i + 2), m).path(path))
        })
        .collect()
}

/// Sort the rows by (detector, exposure index), replacing the file atomically. A row
/// repeated (an exposure replayed after a crash of the same run) is kept once.
pub fn sort(path: &Path) -> Result<()> {
    let mut rows = read(path)?;
    rows.sort_by_key(|r| (r.detector, r.exposure_index));
    rows.dedup_by_key(|r| (r.detector, r.exposure_index));
    let mut text = format!("{HEADER}\n");
    for r in &rows {
        text.push_str(&r.line());
    }
    let name = path.file_name().unwrap_or_default().to_string_lossy();
    let tmp = path.with_file_name(format!(".{name}.part"));
    let write = || -> std::io::Result<()> {
        let mut f = std::fs::File::create(&tmp)?;
        f.write_all(text.as_bytes())?;
        f.sync_all()?;
        std::fs::rename(&tmp, path)
    };
    write().map_err(|e| {
        let _ = std::fs::remove_file(&tmp);
        Error::io(path, e)
    })
}

/// Per detector: exposures, median and largest fraction above each threshold, the most
/// pixels flagged in one exposure. One line each, for `persist fractions`.
pub fn summary(rows: &[Row]) -> String {
    let mut out = format!(
        "{:>3} {:>9} {:>12} {:>12} {:>12} {:>12} {:>11}\n",
        "det", "exposures", "med >high", "max >high", "med >low", "max >low", "max flagged"
    );
    let mut dets: Vec<u8> = rows.iter().map(|r| r.detector).collect();
    dets.dedup();
    dets.sort_unstable();
    dets.dedup();
    for d in dets {
        let of: Vec<&Row> = rows.iter().filter(|r| r.detector == d).collect();
        let col = |f: fn(&Row) -> f64| of.iter().map(|r| f(r)).collect::<Vec<f64>>();
        let high = col(|r| r.stats.fraction_above_high);
        let low = col(|r| r.stats.fraction_above_low);
        let max = |v: &[f64]| v.iter().copied().fold(0.0, f64::max);
        let pct = |x: f64| format!("{:.3}%", 100.0 * x);
        out.push_str(&format!(
            "{:>3} {:>9} {:>12} {:>12} {:>12} {:>12} {:>11}\n",
            d,
            of.len(),
            pct(crate::stats::median(&high)),
            pct(max(&high)),
            pct(crate::stats::median(&low)),
            pct(max(&low)),
            of.iter().map(|r| r.stats.n_flagged).max().unwrap_or(0)
        ));
    }
    out
}

/// Draw the fractions above each threshold against the exposure index, one line per
/// detector and threshold, into a PNG (log axis when anything is above zero).
pub fn plot(rows: &[Row], png: &Path) -> Result<()> {
    let mut dets: Vec<u8> = rows.iter().map(|r| r.detector).collect();
    dets.sort_unstable();
    dets.dedup();
    let mut series = Vec::new();
    for d in dets {
        for (name, f) in [
            (
                "above high",
                (|r: &Row| r.stats.fraction_above_high) as fn(&Row) -> f64,
            ),
            ("above low", |r: &Row| r.stats.fraction_above_low),
        ] {
            series.push(Series {
                name: format!("det {d} {name}"),
                points: rows
                    .iter()
                    .filter(|r| r.detector == d)
                    .map(|r| (r.exposure_index as f64, 100.0 * f(r)))
                    .collect(),
            });
        }
    }
    let positive = series.iter().any(|s| s.points.iter().any(|p| p.1 > 0.0));
    let chart = Chart {
        title: "pixels above each threshold, per exposure".into(),
        x_label: "exposure index".into(),
        y_label: "% of pixels".into(),
        log_y: positive,
        series,
        hlines: Vec::new(),
    };
    line_chart_png(png, &chart, 900, 500)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn report(det: u8, k: u64, high: u64, low: u64) -> ExposureReport {
        ExposureReport {
            detector: det,
            exposure_index: k,
            path: PathBuf::from("x.h5"),
            summary: crate::model::StepSummary {
                pixels: 3000,
                above_high: high,
                above_low: low,
                released: 1,
                max_amplitude: 0,
                t_meas_s: (k > 0).then_some(38.0 + k as f64 / 3.0),
                previous_index: k.checked_sub(1),
            },
            history_incomplete: k == 2,
            written: true,
            seconds: 0.0,
        }
    }

    /// Rows appended in any order come back sorted, once each, with the exact values.
    #[test]
    fn append_sort_read_round_trip() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("sub/run.csv");
        let t = RunTable::create(&path).unwrap();
        let reports = [
            report(2, 1, 7, 70),
            report(1, 0, 1, 3),
            report(1, 1, 2, 9),
            report(1, 1, 2, 9),
        ];
        for r in &reports {
            t.append(r).unwrap();
        }
        drop(t);
        sort(&path).unwrap();
        let rows = read(&path).unwrap();
        assert_eq!(
            rows.iter()
                .map(|r| (r.detector, r.exposure_index))
                .collect::<Vec<_>>(),
            [(1, 0), (1, 1), (2, 1)]
        );
        assert_eq!(rows[2], Row::of(&reports[0]));
        assert_eq!(rows[2].stats.fraction_above_low, 70.0 / 3000.0);
        assert!(rows[0].t_meas_s.is_nan());
        let s = summary(&rows);
        assert_eq!(s.lines().count(), 3, "{s}");
        let png = dir.path().join("f.png");
        plot(&rows, &png).unwrap();
        assert!(std::fs::metadata(&png).unwrap().len() > 1000);
        // A malformed row is named by its line.
        std::fs::write(&path, format!("{HEADER}\n1,2,3\n")).unwrap();
        let e = read(&path).unwrap_err();
        assert_eq!(e.context.field.as_deref(), Some("line 2"), "{e}");
    }
}
