//! Operator metrics of `persist run --watch` in Prometheus's text exposition format
//! (version 0.0.4): a textfile for node_exporter's textfile collector
//! (`--metrics-file`), and/or a plain HTTP endpoint on localhost (`--metrics-addr`).
//!
//! | metric | type | labels |
//! |---|---|---|
//! | `persist_exposures_processed_total` | counter | `detector` |
//! | `persist_backlog_exposures` | gauge | |
//! | `persist_quarantined_files_total` | counter | `kind` (the error kind of the reason) |
//! | `persist_reader_crashes_total` | counter | |
//! | `persist_checkpoint_age_seconds` | gauge | `detector` |
//! | `persist_exposure_seconds` | histogram | |
//! | `persist_metrics_timestamp_seconds` | gauge | |
//!
//! Invariants:
//! - Counters count from the start of this process (Prometheus handles the reset).
//! - The checkpoint age is read from the checkpoint directory when the metrics are
//!   rendered (the newest checkpoint's modification time per detector), so it is right
//!   across restarts and keeps growing while the stage is idle or stuck.
//! - A reader crash is a quarantine whose error kind is `reader_crash`, or whose reason
//!   says "reader crashed" / "reader exceeded" (a crash, a hang or a runaway allocation
//!   of the library that read it); it is also counted under its kind.
//! - The textfile is replaced atomically (written under `.NAME.part`, renamed): the
//!   collector never reads half a file. The endpoint needs no dependency beyond
//!   `std::net`: any request on the socket gets the metrics.

use crate::error::{Error, ErrorKind, Result};
use crate::units::DetectorId;
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::io::{Read, Write as _};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant, SystemTime};

/// Upper bounds (seconds) of the buckets of `persist_exposure_seconds`: from a small
/// test exposure to minutes at 2040 x 2040 on a slow node.
pub const EXPOSURE_SECONDS_BUCKETS: [f64; 12] = [
    0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0,
];

/// The textfile is rewritten at most this often (and when the stage stops).
const FILE_INTERVAL: Duration = Duration::from_secs(1);

#[derive(Debug, Default)]
struct Counts {
    processed: BTreeMap<u8, u64>,
    backlog: u64,
    quarantined: BTreeMap<String, u64>,
    reader_crashes: u64,
    /// Per bucket of [`EXPOSURE_SECONDS_BUCKETS`] (not cumulative), then `+Inf`.
    seconds_buckets: [u64; EXPOSURE_SECONDS_BUCKETS.len() + 1],
    seconds_sum: f64,
    seconds_count: u64,
}

/// The stage's metrics, shared by the stage, the textfile writer and the endpoint.
#[derive(Debug)]
pub struct Metrics {
    checkpoints: PathBuf,
    file: Option<PathBuf>,
    counts: Mutex<Counts>,
    last_file_write: Mutex<Option<Instant>>,
}

impl Metrics {
    /// Metrics of a stage writing its checkpoints under `checkpoints`; `file`: the
    /// textfile to keep up to date.
    pub fn new(checkpoints: &Path, file: Option<PathBuf>) -> Self {
        Metrics {
            checkpoints: checkpoints.to_path_buf(),
            file,
            counts: Mutex::new(Counts::default()),
            last_file_write: Mutex::new(None),
        }
    }

    fn counts(&self) -> std::sync::MutexGuard<'_, Counts> {
        self.counts.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// One exposure of `detector` processed in `seconds` (read, step, output written).
    pub fn processed(&self, detector: u8, seconds: f64) {
        let mut c = self.counts();
        *c.processed.entry(detector).or_default() += 1;
        let bucket = EXPOSURE_SECONDS_BUCKETS
            .iter()
            .position(|&b| seconds <= b)
            .unwrap_or(EXPOSURE_SECONDS_BUCKETS.len());
        c.seconds_buckets[bucket] += 1;
        c.seconds_sum += seconds;
        c.seconds_count += 1;
    }

    /// A file moved to quarantine for `why`.
    pub fn quarantined(&self, why: &Error) {
        let kind = kind_label(why.kind);
        let mut c = self.counts();
        if kind == "reader_crash"
            || why.message.starts_with("reader crashed")
            || why.message.starts_with("reader exceeded")
        {
            c.reader_crashes += 1;
        }
        *c.quarantined.entry(kind).or_default() += 1;
    }

    /// Products queued and not processed yet.
    pub fn set_backlog(&self, backlog: usize) {
        self.counts().backlog = backlog as u64;
    }

    /// The metrics in the text exposition format.
    pub fn render(&self) -> String {
        let now = SystemTime::now();
        let ages = checkpoint_ages(&self.checkpoints, now);
        let c = self.counts();
        let mut s = String::new();
        let head = |s: &mut String, name: &str, kind: &str, help: &str| {
            let _ = writeln!(s, "# HELP {name} {help}\n# TYPE {name} {kind}");
        };
        head(
            &mut s,
            "persist_exposures_processed_total",
            "counter",
            "Exposures processed by this process, per detector.",
        );
        for (d, n) in &c.processed {
            let _ = writeln!(
                s,
                "persist_exposures_processed_total{{detector=\"{d}\"}} {n}"
            );
        }
        head(
            &mut s,
            "persist_backlog_exposures",
            "gauge",
            "Products queued and not processed yet.",
        );
        let _ = writeln!(s, "persist_backlog_exposures {}", c.backlog);
        head(
            &mut s,
            "persist_quarantined_files_total",
            "counter",
            "Input files moved to quarantine by this process, by error kind.",
        );
        for (k, n) in &c.quarantined {
            let _ = writeln!(s, "persist_quarantined_files_total{{kind=\"{k}\"}} {n}");
        }
        head(
            &mut s,
            "persist_reader_crashes_total",
            "counter",
            "Inputs quarantined because the library reading them crashed, hung or ran away.",
        );
        let _ = writeln!(s, "persist_reader_crashes_total {}", c.reader_crashes);
        head(
            &mut s,
            "persist_checkpoint_age_seconds",
            "gauge",
            "Seconds since the newest checkpoint of each detector was written.",
        );
        for (d, age) in &ages {
            let _ = writeln!(
                s,
                "persist_checkpoint_age_seconds{{detector=\"{d}\"}} {age:.3}"
            );
        }
        head(
            &mut s,
            "persist_exposure_seconds",
            "histogram",
            "Seconds to read, step and write one exposure.",
        );
        let mut cumulative = 0;
        for (i, n) in c.seconds_buckets.iter().enumerate() {
            cumulative += n;
            let le = EXPOSURE_SECONDS_BUCKETS
                .get(i)
                .map_or("+Inf".to_string(), |b| b.to_string());
            let _ = writeln!(
                s,
                "persist_exposure_seconds_bucket{{le=\"{le}\"}} {cumulative}"
            );
        }
        let _ = writeln!(s, "persist_exposure_seconds_sum {:.6}", c.seconds_sum);
        let _ = writeln!(s, "persist_exposure_seconds_count {}", c.seconds_count);
        head(
            &mut s,
            "persist_metrics_timestamp_seconds",
            "gauge",
            "When these metrics were rendered (Unix seconds): a stale value means a stuck stage.",
        );
        let unix = now
            .duration_since(SystemTime::UNIX_EPOCH)
            .map_or(0.0, |d| d.as_secs_f64());
        let _ = writeln!(s, "persist_metrics_timestamp_seconds {unix:.3}");
        s
    }

    /// Rewrite the textfile if it is due (`force`: now).
    pub fn write_file(&self, force: bool) -> Result<()> {
        let Some(path) = &self.file else {
            return Ok(());
        };
        let mut last = self
            .last_file_write
            .lock()
            .unwrap_or_else(|e| e.into_inner());
        if !force && last.is_some_and(|t| t.elapsed() < FILE_INTERVAL) {
            return Ok(());
        }
        *last = Some(Instant::now());
        let tmp = crate::h5io::temp_path(path);
        std::fs::write(&tmp, self.render())
            .and_then(|()| std::fs::rename(&tmp, path))
            .map_err(|e| {
                let _ = std::fs::remove_file(&tmp);
                Error::io(path, e)
            })
    }
}

/// The `kind` label of an error kind (its snake_case name, as in the reason files).
fn kind_label(kind: ErrorKind) -> String {
    serde_json::to_value(kind)
        .ok()
        .and_then(|v| v.as_str().map(str::to_string))
        .unwrap_or_else(|| format!("{kind:?}").to_lowercase())
}

/// Per detector with a checkpoint directory: seconds since its newest checkpoint's
/// modification time.
fn checkpoint_ages(dir: &Path, now: SystemTime) -> BTreeMap<u8, f64> {
    let mut ages = BTreeMap::new();
    let Ok(entries) = std::fs::read_dir(dir) else {
        return ages;
    };
    for e in entries.flatten() {
        let name = e.file_name().to_string_lossy().into_owned();
        let Some(det) = name.strip_prefix("det").and_then(|d| d.parse::<u8>().ok()) else {
            continue;
        };
        let newest = crate::checkpoint::list(dir, DetectorId(det))
            .ok()
            .and_then(|mut l| l.pop())
            .and_then(|(_, p)| std::fs::metadata(p).and_then(|m| m.modified()).ok());
        if let Some(t) = newest {
            let age = now.duration_since(t).map_or(0.0, |d| d.as_secs_f64());
            ages.insert(det, age);
        }
    }
    ages
}

/// Serve the metrics on `addr` (HTTP/1.0-style: one response per connection) from a
/// thread of its own, for the life of the process. Fails if the address cannot be
/// bound.
pub fn serve(addr: std::net::SocketAddr, metrics: Arc<Metrics>) -> Result<()> {
    let listener = std::net::TcpListener::bind(addr).map_err(|e| {
        Error::new(ErrorKind::Io, format!("cannot listen on {addr}: {e}")).field("--metrics-addr")
    })?;
    std::thread::spawn(move || {
        for stream in listener.incoming().flatten() {
            let _ = respond(stream, &metrics);
        }
    });
    Ok(())
}

fn respond(mut stream: std::net::TcpStream, metrics: &Metrics) -> std::io::Result<()> {
    stream.set_read_timeout(Some(Duration::from_secs(2)))?;
    // The request is read up to its blank line (or 8 KiB) and not interpreted.
    let mut request = Vec::new();
    let mut buf = [0u8; 1024];
    while !request.windows(4).any(|w| w == b"\r\n\r\n") && request.len() < 8192 {
        match stream.read(&mut buf) {
            Ok(0) | Err(_) => break,
            Ok(n) => request.extend_from_slice(&buf[..n]),
        }
    }
    let body = metrics.render();
    write!(
        stream,
        "HTTP/1.1 200 OK\r\nContent-Type: text/plain; version=0.0.4; charset=utf-8\r\n\
         Content-Length: {}\r\nConnection: close\r\n\r\n{body}",
        body.len()
    )?;
    stream.flush()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counts_and_histogram_render() {
        let dir = tempfile::tempdir().unwrap();
        let m = Metrics::new(dir.path(), None);
        m.processed(2, 0.2);
        m.processed(2, 100.0);
        m.processed(1, 0.01);
        m.set_backlog(3);
        m.quarantined(&Error::new(ErrorKind::Hdf5, "not a readable HDF5 file"));
        m.quarantined(&Error::new(ErrorKind::Hdf5, "reader crashed: SIGSEGV"));
        let text = m.render();
        for line in [
            "persist_exposures_processed_total{detector=\"1\"} 1",
            "persist_exposures_processed_total{detector=\"2\"} 2",
            "persist_backlog_exposures 3",
            "persist_quarantined_files_total{kind=\"hdf5\"} 2",
            "persist_reader_crashes_total 1",
            "persist_exposure_seconds_bucket{le=\"0.01\"} 1",
            "persist_exposure_seconds_bucket{le=\"0.25\"} 2",
            "persist_exposure_seconds_bucket{le=\"60\"} 2",
            "persist_exposure_seconds_bucket{le=\"+Inf\"} 3",
            "persist_exposure_seconds_count 3",
        ] {
            assert!(text.lines().any(|l| l == line), "{line} not in\n{text}");
        }
    }
}
