//! The stage loop: for each detector, in exposure-index order,
//! read -> `Model::step` -> publish the output -> checkpoint.
//!
//! # One code path for batch and watch
//!
//! A [`Stage`] owns one long-lived `Processor` per detector (its state, bookkeeping,
//! buffers and the queue of products waiting for their turn). Products are *observed*
//! (root attributes read, routed to their detector's queue), then processors *advance*:
//! each processes its queued products while the next one is ready (module rules below).
//! Batch (`persist run`) is one scan of the input directory followed by one advance in
//! which every gap is crossed at once (nothing more will arrive). Watch
//! (`persist run --watch`, [`super::watch`]) observes products as they arrive and
//! advances after every event or rescan, crossing a gap only after the gap timeout.
//! Detectors advance in parallel (rayon), pixels in parallel inside the step; HDF5 calls
//! are serialised by the library's global lock, so only the computation overlaps.
//!
//! # Resumption and crash safety
//!
//! Each detector starts from the newest checkpoint (or the one named with
//! `--from-checkpoint`), and steps every later exposure. An exposure whose output is
//! already published is stepped (the state needs it) but its output is not rewritten,
//! except when reprocessing from a named checkpoint. Outputs are published before the
//! checkpoint that includes them (both atomically: `.NAME.part`, validated, synced,
//! renamed), so a crash anywhere replays at most the exposures after the newest
//! checkpoint and rewrites the same bytes. The stop flag ([`Ops::stop`], set by
//! SIGINT/SIGTERM) is checked between exposures: the exposure in hand is finished and a
//! checkpoint written before the stage returns.
//!
//! # Checkpoint publication
//!
//! A checkpoint is checked and written (straight from the state in memory) on the
//! detector's own thread; its publication (fsync, rename, directory fsync) and the
//! pruning of old checkpoints then run on a helper thread while the next exposures are
//! read, stepped and published. A detector's checkpoints are published in order (the
//! next waits for the previous), always after the outputs they include, and every pass
//! of the processor ends with its last checkpoint published.
//!
//! Outputs are published the same way: written and validated under their temporary
//! name on the detector's thread, then synced and renamed on a helper thread while the
//! next exposure is read and stepped. The next output's publication, and any
//! checkpoint's, first waits for it, so outputs appear in exposure order and always
//! before the checkpoint that includes them; every pass ends with its outputs
//! published. A failed publication stops the detector as a failed write does, before
//! any checkpoint that would include the exposure.
//!
//! # Ordering and the gap rule
//!
//! Within a detector, the next product is processed when its index is the last
//! processed index + 1. A product further ahead *waits* while an index before it is
//! missing. The gap is *crossed* (the product processed anyway) when
//! - the run is a batch run (nothing more will arrive), or
//! - every missing index in between was refused in this run (quarantined), or
//! - the waiting product was first seen more than the gap timeout ago ([`Ops::gap_timeout`]).
//!
//! A fresh detector (no checkpoint) starts at index 0 at once, or at its lowest index
//! after the gap timeout (watch) / at once (batch); indices below the start are late.
//! Crossing a gap decays the state over the real elapsed time (the step decays from the
//! previous reset to the new one) and records the crossed range in the bookkeeping.
//!
//! **History incomplete (bit 4).** After a crossed gap or a refused exposure, outputs are
//! marked while their mid-exposure time is before the deadline `t_start(first exposure
//! after the gap) + T`. `T` is the time the largest amplitude the missing exposure could
//! have added (the knot table's maximum, added just before the next exposure started)
//! takes to decay below the low threshold (65,300 s for the default model): after that
//! the missing exposure cannot change any flag. The deadline is carried in the
//! checkpoint, so it survives restarts.
//!
//! # Start-time order (FITS without a sequence number)
//!
//! SPHEREx's FITS files carry no exposure sequence number: their exposure index is the
//! start time in milliseconds since 1970 UTC ([`crate::product::fits::Sequence::StartTime`]),
//! deterministic per file and recorded in the output (`EXPINDEX`, `IDXSRC`). Such a
//! detector's history (the bookkeeping's `by_start_time`, kept in the checkpoint, never
//! mixed with sequence numbers) has no successor index to wait for: the earliest queued
//! product is processed at once, no gap is crossed or marked (a missing exposure cannot
//! be told from a pause; a refused one still marks history incomplete), and a product
//! that starts before the last processed one, within the digest window, is late.
//!
//! # Duplicates and late products
//!
//! - Two queued products with the same (detector, exposure index): identical bytes -> the
//!   later-observed copy is ignored; different bytes -> the later one is refused loudly.
//! - A product for an index already processed: the checkpoint's bookkeeping keeps the
//!   SHA-256 of the file bytes of the last [`DUPLICATE_WINDOW`] processed exposures.
//!   Same digest -> ignored (it is the same product seen again, e.g. by a rerun); other
//!   digest -> refused as a different-content duplicate. Older than the window (and not
//!   in a crossed gap) -> it cannot be compared: ignored, logged at debug level.
//! - A product whose index lies in a crossed gap, or below the start of the history,
//!   is *late*: refused, never mixed into the history.
//!
//! # Quarantine rule
//!
//! Every product refused for its content (HDF5 cannot read it, it breaks the ICD or the
//! schema, it does not fit the history, a different-content duplicate, a late product)
//! is moved to the quarantine directory (when [`Ops::quarantine`] is set) with a
//! `NAME.reason.json` beside it ([`super::quarantine`]). A product that is not ready
//! (still open for writing elsewhere: HDF5 "unable to lock file"; or its size or time
//! changes between two looks) is retried, never quarantined. Failures to *write* (an
//! output or checkpoint) stop that detector without a checkpoint, so that a restart
//! replays from the last good one.

use crate::checkpoint::{self, CheckpointMeta, Retention};
use crate::error::{Error, ErrorKind, Result};
use crate::model::{Model, State, StepSummary};
use crate::product::format::{self, InputProduct};
use crate::product::{ExposureMeta, PersistencePlanes};
use crate::stage::exposure::{self as exposure_step, ExposureStep, Window};
use crate::stage::{quarantine, queue};
use crate::units::DetectorId;
use ndarray::Array2;
use rayon::prelude::*;
use serde::Serialize;
use sha2::{Digest, Sha256};
use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant, SystemTime};

pub use super::exposure::{Bookkeeping, DUPLICATE_WINDOW};

/// How long a product that HDF5 could not lock waits before it is tried again.
const RETRY_NOT_READY: Duration = Duration::from_millis(500);

/// Everything a run needs.
#[derive(Debug, Clone)]
pub struct RunConfig {
    pub input: PathBuf,
    pub output: PathBuf,
    pub checkpoints: PathBuf,
    pub model: Model,
    /// Reprocess one detector from this checkpoint (rewriting its later outputs).
    pub from_checkpoint: Option<(DetectorId, u64)>,
    /// Continue from checkpoints made with another model.
    pub allow_model_change: bool,
    /// Write a checkpoint after every exposure whose `(index + 1)` is a multiple of this
    /// (>= 1: the cadence grid), and a tail checkpoint when a batch ends, when stopping,
    /// and when a watch has been idle for `checkpoint_idle`.
    pub checkpoint_every: u64,
    /// With `watch`: write a tail checkpoint once no exposure was processed for this
    /// long (at most `checkpoint_every - 1` exposures are replayed after a crash).
    pub checkpoint_idle: Duration,
    pub retention: Retention,
    /// Recorded as the processing time in every output of this run.
    pub processed_utc: String,
}

impl RunConfig {
    /// The retention rule with this run's cadence (what tells a tail checkpoint).
    pub fn retention(&self) -> Retention {
        Retention {
            cadence: self.checkpoint_every.max(1),
            ..self.retention
        }
    }
}

/// How the stage is operated (beyond what it computes).
#[derive(Debug, Clone)]
pub struct Ops {
    /// Move refused products here (with a reason file); `None`: leave them in place and
    /// only report them.
    pub quarantine: Option<PathBuf>,
    /// Watch the input directory instead of one batch scan.
    pub watch: Option<WatchOpts>,
    /// A product waiting behind a missing index waits at most this long (watch only)
    /// from when it was first seen.
    pub gap_timeout: Duration,
    /// Set (by a signal handler) to stop after the exposure in hand.
    pub stop: Arc<AtomicBool>,
    /// Progress of a batch run (its length is set once the products are queued).
    pub progress: Option<indicatif::ProgressBar>,
    /// How FITS inputs (`*.fits`) are read: keyword names, conversion factors.
    pub fits: crate::product::fits::FitsConfig,
    /// Worker mode ([`super::workers`]): process this detector only; the products of
    /// other detectors are left alone.
    pub only: Option<OnlyDetector>,
    /// Operator metrics to keep up to date (`--metrics-file`, `--metrics-addr`).
    pub metrics: Option<Arc<super::metrics::Metrics>>,
    /// Read every input and checkpoint in an isolated child process first
    /// ([`crate::guard`]); `None`: read in-process.
    pub guard: Option<crate::guard::Guard>,
}

/// One detector of a run split into worker processes.
#[derive(Debug, Clone, Copy)]
pub struct OnlyDetector {
    pub detector: DetectorId,
    /// This worker also refuses (and quarantines) the products whose detector cannot be
    /// read; exactly one worker of a run does.
    pub unattributed: bool,
}

impl Default for Ops {
    fn default() -> Self {
        Ops {
            quarantine: None,
            watch: None,
            gap_timeout: Duration::from_secs(600),
            stop: Arc::new(AtomicBool::new(false)),
            progress: None,
            fits: Default::default(),
            only: None,
            metrics: None,
            guard: None,
        }
    }
}

/// Watch mode settings.
#[derive(Debug, Clone)]
pub struct WatchOpts {
    /// Rescan the input directory this often (the polling fallback, and the check on
    /// files written in place).
    pub poll_interval: Duration,
    /// Use file system events (inotify through `notify`); `false`: polling only.
    pub events: bool,
}

/// What happened to one exposure.
#[derive(Debug, Clone, Serialize)]
pub struct ExposureReport {
    pub detector: u8,
    pub exposure_index: u64,
    pub path: PathBuf,
    pub summary: StepSummary,
    pub history_incomplete: bool,
    /// false when an identical-key output was already published and left alone.
    pub written: bool,
    /// Seconds to read, step and write it (not reproducible: not serialised).
    #[serde(skip)]
    pub seconds: f64,
}

#[derive(Debug, Default)]
pub struct RunReport {
    pub exposures: Vec<ExposureReport>,
    pub errors: Vec<Error>,
    pub ignored_copies: Vec<PathBuf>,
    /// Where refused products were moved.
    pub quarantined: Vec<PathBuf>,
    /// The run was stopped by [`Ops::stop`].
    pub stopped: bool,
    /// Exposures processed (in watch mode `exposures` is not kept, this count is).
    pub processed: u64,
}

/// The processing time to record: `SOURCE_DATE_EPOCH` (reproducible runs) or now.
pub fn processing_time() -> String {
    let t = std::env::var("SOURCE_DATE_EPOCH")
        .ok()
        .and_then(|s| s.trim().parse::<i64>().ok())
        .and_then(|s| chrono::DateTime::<chrono::Utc>::from_timestamp(s, 0))
        .unwrap_or_else(chrono::Utc::now);
    t.to_rfc3339_opts(chrono::SecondsFormat::Micros, true)
}

/// SHA-256 (hex) of a file's bytes.
pub fn file_digest(path: &Path) -> Result<String> {
    use std::io::Read;
    let mut f = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let mut h = Sha256::new();
    let mut buf = vec![0u8; 1 << 20];
    loop {
        let n = f.read(&mut buf).map_err(|e| Error::io(path, e))?;
        if n == 0 {
            break;
        }
        h.update(&buf[..n]);
    }
    Ok(crate::model::params::to_hex(&h.finalize()))
}

/// (size, modification time) of a file: what tells a rescan that it changed.
pub(crate) type FileKey = (u64, Option<SystemTime>);

pub(crate) fn file_key(path: &Path) -> std::io::Result<FileKey> {
    let m = std::fs::metadata(path)?;
    Ok((m.len(), m.modified().ok()))
}

/// The stage: every detector's processor, and what has been seen of the input.
pub struct Stage<'a> {
    pub(crate) cfg: &'a RunConfig,
    pub(crate) ops: &'a Ops,
    on_exposure: &'a (dyn Fn(&ExposureReport) + Sync),
    detectors: BTreeMap<DetectorId, Processor<'a>>,
    /// Files already observed (queued, processed, ignored), by path: a rescan skips a
    /// file whose key did not change, so it does not re-read thousands of headers.
    seen: HashMap<PathBuf, FileKey>,
    /// Files found by a rescan (not announced by an event), waiting for a second look
    /// with the same key before they are read.
    unsettled: HashMap<PathBuf, FileKey>,
    /// Output file names in use, and the (detector, index) they belong to.
    names: HashMap<std::ffi::OsString, (DetectorId, u64)>,
    pub(crate) report: RunReport,
}

impl<'a> Stage<'a> {
    fn new(
        cfg: &'a RunConfig,
        ops: &'a Ops,
        on_exposure: &'a (dyn Fn(&ExposureReport) + Sync),
    ) -> Self {
        Stage {
            cfg,
            ops,
            on_exposure,
            detectors: BTreeMap::new(),
            seen: HashMap::new(),
            unsettled: HashMap::new(),
            names: HashMap::new(),
            report: RunReport::default(),
        }
    }

    /// A stage on `cfg`'s directories (the output and checkpoint directories created),
    /// or the report of why it cannot start.
    pub(crate) fn open(
        cfg: &'a RunConfig,
        ops: &'a Ops,
        on_exposure: &'a (dyn Fn(&ExposureReport) + Sync),
    ) -> std::result::Result<Self, RunReport> {
        let mut stage = Stage::new(cfg, ops, on_exposure);
        for dir in [&cfg.output, &cfg.checkpoints] {
            if let Err(e) = std::fs::create_dir_all(dir) {
                stage.report.errors.push(Error::io(dir, e));
                return Err(stage.report);
            }
        }
        if !cfg.input.is_dir() {
            stage
                .report
                .errors
                .push(Error::new(ErrorKind::Usage, "input is not a directory").path(&cfg.input));
            return Err(stage.report);
        }
        Ok(stage)
    }

    /// One batch: one scan, one advance crossing every gap; what is left is reported.
    pub(crate) fn batch(&mut self) {
        let ops = self.ops;
        self.scan(Instant::now(), true);
        if let Some(pb) = &ops.progress {
            pb.set_length(self.backlog() as u64);
        }
        self.advance(Instant::now(), true);
        for p in self.detectors.values() {
            if let Some((&next, _)) = p.pending.first_key_value() {
                if !p.dead && !ops.stop.load(Ordering::SeqCst) {
                    self.report.errors.push(
                        Error::new(
                            ErrorKind::NotReady,
                            format!(
                                "{} product(s) from exposure {next} on left for the next run",
                                p.pending.len()
                            ),
                        )
                        .detector(p.det),
                    );
                }
            }
        }
    }

    /// Refresh the backlog gauge and rewrite the metrics textfile if due (`force`: now).
    pub(crate) fn update_metrics(&mut self, force: bool) {
        let backlog = self.backlog();
        if let Some(m) = &self.ops.metrics {
            m.set_backlog(backlog);
            if let Err(e) = m.write_file(force) {
                tracing::warn!(error = %e, "cannot write the metrics file");
            }
        }
    }

    /// The run's report, with whether the stop flag ended it; the metrics written.
    pub(crate) fn finish(mut self) -> RunReport {
        self.report.stopped = self.ops.stop.load(Ordering::SeqCst);
        self.update_metrics(true);
        self.report
    }

    /// Products queued and not processed yet.
    pub(crate) fn backlog(&self) -> usize {
        self.detectors.values().map(|p| p.pending.len()).sum()
    }

    /// Walk the input directory. `settled`: read every new or changed file now (the
    /// first scan, and batch runs); otherwise a file found only by the scan is read once
    /// a second scan sees the same size and time (it may still be being written).
    pub(crate) fn scan(&mut self, now: Instant, settled: bool) {
        let files = match queue::candidates(&self.cfg.input) {
            Ok(f) => f,
            Err(e) => {
                tracing::error!(error = %e, "cannot scan the input directory");
                self.report.errors.push(e);
                return;
            }
        };
        for path in files {
            let Ok(key) = file_key(&path) else { continue };
            if self.seen.get(&path) == Some(&key) {
                continue;
            }
            if !settled && self.unsettled.get(&path) != Some(&key) {
                self.unsettled.insert(path, key);
                continue;
            }
            self.unsettled.remove(&path);
            self.observe(&path, key, now);
        }
    }

    /// A file announced complete (renamed into place): read it now.
    pub(crate) fn observe_path(&mut self, path: &Path, now: Instant) {
        let Ok(key) = file_key(path) else { return };
        if self.seen.get(path) == Some(&key) {
            return;
        }
        self.unsettled.remove(path);
        self.observe(path, key, now);
    }

    fn observe(&mut self, path: &Path, key: FileKey, now: Instant) {
        self.seen.insert(path.to_path_buf(), key);
        let (meta, by_start_time) = match crate::guard::read_input_sequence(
            self.ops.guard.as_ref(),
            path,
            &self.ops.fits,
        ) {
            Ok((m, _)) if self.ops.only.is_some_and(|o| o.detector != m.detector) => return,
            Ok(m) => m,
            Err(_) if self.ops.only.is_some_and(|o| !o.unattributed) => return,
            Err(e) if matches!(e.kind, ErrorKind::NotReady | ErrorKind::Io) => {
                self.not_ready(path, e);
                return;
            }
            Err(e) => {
                // A file that changed while being read was still being written.
                if file_key(path).ok() != Some(key) {
                    self.not_ready(path, e);
                } else {
                    self.refuse(path, e);
                }
                return;
            }
        };
        let key_of = (meta.detector, meta.exposure_index);
        let name = path.file_name().unwrap_or_default().to_os_string();
        if let Some(other) = self.names.get(&name).filter(|&&k| k != key_of) {
            let e = Error::new(
                ErrorKind::Sequence,
                format!(
                    "same file name as the product of detector {} exposure {}: the output names would collide",
                    other.0, other.1
                ),
            )
            .field("file name");
            self.refuse(path, e);
            return;
        }
        let cfg = self.cfg;
        let on_exposure = self.on_exposure;
        let ops = self.ops;
        let proc = self
            .detectors
            .entry(meta.detector)
            .or_insert_with(|| Processor::new(cfg, ops, meta.detector, on_exposure));
        proc.ensure_started();
        let offer = proc.offer(path, meta, by_start_time, now);
        self.collect();
        match offer {
            Offer::Queued => {
                self.names.insert(name, key_of);
            }
            Offer::Known => {}
            Offer::IgnoredCopy(of) => {
                tracing::info!(path = %path.display(), copy_of = %of.display(),
                    detector = key_of.0 .0, exposure_index = key_of.1,
                    "identical copy of a queued product: ignored");
                self.report.ignored_copies.push(path.to_path_buf());
            }
            Offer::AlreadyProcessed => {
                tracing::debug!(path = %path.display(), detector = key_of.0 .0,
                    exposure_index = key_of.1, "already processed: ignored");
            }
            Offer::Refused(e) => self.refuse(path, e),
            Offer::Failed(e) => {
                tracing::error!(error = %e, "cannot queue");
                self.report.errors.push(e.path(path));
            }
            Offer::Dead => {}
        }
    }

    /// Not ready (still being written, or vanished): forget it, a later look retries.
    fn not_ready(&mut self, path: &Path, e: Error) {
        let batch = self.ops.watch.is_none();
        tracing::debug!(path = %path.display(), error = %e, "not ready; will retry");
        self.seen.remove(path);
        if batch {
            self.report.errors.push(e.path(path));
        }
    }

    /// Refuse a product for its content: report it and move it aside.
    fn refuse(&mut self, path: &Path, e: Error) {
        let e = e.path(path);
        // Not moved aside: stays in the cache, so it is not refused again until it
        // changes.
        if let Some(q) = &self.ops.quarantine {
            match quarantine::quarantine(q, path, &e) {
                Ok(to) => {
                    self.seen.remove(path);
                    tracing::warn!(path = %path.display(), quarantined = %to.display(),
                        kind = ?e.kind, field = e.context.field.as_deref().unwrap_or(""),
                        reason = %e.message, "refused: quarantined");
                    self.report.quarantined.push(to);
                    if let Some(m) = &self.ops.metrics {
                        m.quarantined(&e);
                    }
                }
                Err(qe) => {
                    tracing::error!(path = %path.display(), error = %qe, "refused, and could not be quarantined");
                    self.report.errors.push(qe);
                }
            }
        } else {
            tracing::warn!(error = %e, "refused");
        }
        self.report.errors.push(e);
    }

    /// Move what the processors produced into the report; refuse what they refused.
    fn collect(&mut self) {
        let mut refused = Vec::new();
        let mut retry = Vec::new();
        let watching = self.ops.watch.is_some();
        for p in self.detectors.values_mut() {
            self.report.processed += p.reports.len() as u64;
            if let Some(m) = &self.ops.metrics {
                for r in &p.reports {
                    m.processed(r.detector, r.seconds);
                }
            }
            if watching {
                // Weeks of reports are not kept: the logs have them.
                p.reports.clear();
            }
            self.report.exposures.append(&mut p.reports);
            self.report.errors.append(&mut p.errors);
            refused.append(&mut p.refused_files);
            retry.append(&mut p.forget);
        }
        for path in retry {
            self.seen.remove(&path);
        }
        for (path, e) in refused {
            self.refuse(&path, e);
        }
    }

    /// Let every detector process what is ready (in parallel). `final_`: nothing more will
    /// arrive, cross every gap.
    pub(crate) fn advance(&mut self, now: Instant, final_: bool) {
        self.detectors
            .par_iter_mut()
            .for_each(|(_, p)| p.advance(now, final_));
        self.collect();
    }

    /// Per detector: (detector, last processed index, queued indices).
    pub(crate) fn waiting(&self) -> Vec<(DetectorId, Option<u64>, Vec<u64>)> {
        self.detectors
            .values()
            .map(|p| (p.det, p.last(), p.pending.keys().copied().collect()))
            .collect()
    }
}

/// What became of an observed product.
enum Offer {
    Queued,
    /// The same file, already queued.
    Known,
    IgnoredCopy(PathBuf),
    AlreadyProcessed,
    Refused(Error),
    Failed(Error),
    /// The detector cannot go on (its checkpoint is unusable, or an output failed).
    Dead,
}

/// A product waiting for its turn.
struct Pending {
    path: PathBuf,
    meta: ExposureMeta,
    /// When it was first seen (the gap timeout counts from here).
    seen: Instant,
    digest: Option<String>,
    /// (size, mtime) when observed: a file that changed since was still being written.
    key: Option<FileKey>,
    /// Not ready: do not try before this.
    retry_at: Option<Instant>,
}

/// Why one exposure was not completed.
enum Failure {
    /// The input was refused; the state is unchanged; the stage goes on.
    Input(Error),
    /// Publishing failed after the state advanced; this detector stops.
    Output(Error),
}

/// One detector's history being processed: long-lived, fed products as they come.
struct Processor<'a> {
    cfg: &'a RunConfig,
    ops: &'a Ops,
    det: DetectorId,
    /// The run's model with this detector's per-pixel map, if the model names one.
    model: Model,
    on_exposure: &'a (dyn Fn(&ExposureReport) + Sync),
    started: bool,
    dead: bool,
    state: Option<State>,
    book: Bookkeeping,
    /// The output planes, reused from exposure to exposure.
    buffers: PersistencePlanes,
    pending: BTreeMap<u64, Pending>,
    /// Indices refused in this run: no need to wait for them.
    refused: BTreeSet<u64>,
    gap_before: bool,
    unsaved: u64,
    /// When the last exposure was processed (what a watch's idle checkpoint waits on).
    last_step: Option<Instant>,
    reprocess: bool,
    // Produced since the last collect:
    reports: Vec<ExposureReport>,
    errors: Vec<Error>,
    refused_files: Vec<(PathBuf, Error)>,
    forget: Vec<PathBuf>,
    /// The last checkpoint's publication (fsync, rename, prune), running on its own
    /// thread while the next exposures are processed.
    publishing: Option<std::thread::JoinHandle<Result<()>>>,
    /// The last output's publication (fsync, rename, directory fsync), running on its
    /// own thread while the next exposure is read and stepped.
    committing: Option<std::thread::JoinHandle<Result<()>>>,
    /// The next queued input, read ahead through the reader guard.
    ahead: crate::guard::Ahead,
}

impl<'a> Processor<'a> {
    fn new(
        cfg: &'a RunConfig,
        ops: &'a Ops,
        det: DetectorId,
        on_exposure: &'a (dyn Fn(&ExposureReport) + Sync),
    ) -> Self {
        Processor {
            cfg,
            ops,
            det,
            // Model::new built the same effects already, so this cannot fail; keep the
            // run's model if it did
            model: cfg
                .model
                .for_detector(det.0)
                .unwrap_or_else(|_| cfg.model.clone()),
            on_exposure,
            started: false,
            dead: false,
            state: None,
            book: Bookkeeping::default(),
            buffers: PersistencePlanes {
                current_e_per_s: Array2::zeros((0, 0)),
                flags: Array2::zeros((0, 0)),
            },
            pending: BTreeMap::new(),
            refused: BTreeSet::new(),
            gap_before: false,
            unsaved: 0,
            last_step: None,
            reprocess: matches!(cfg.from_checkpoint, Some((d, _)) if d == det),
            reports: Vec::new(),
            errors: Vec::new(),
            refused_files: Vec::new(),
            forget: Vec::new(),
            publishing: None,
            committing: None,
            ahead: Default::default(),
        }
    }

    fn last(&self) -> Option<u64> {
        self.state.as_ref().and_then(|s| s.last_index)
    }

    fn ensure_started(&mut self) {
        if self.started {
            return;
        }
        self.started = true;
        match self.start() {
            Ok(Some((s, b))) => {
                tracing::info!(
                    detector = self.det.0,
                    exposure_index = s.last_index,
                    "resuming from checkpoint"
                );
                self.state = Some(s);
                self.book = b;
                // A crash between a checkpoint and its pruning leaves old ones behind:
                // prune now, or a history with nothing left to process never would.
                if let Err(e) =
                    checkpoint::prune(&self.cfg.checkpoints, self.det, &self.cfg.retention())
                {
                    tracing::error!(error = %e, "pruning checkpoints failed");
                    self.errors.push(e.detector(self.det));
                }
            }
            Ok(None) => {}
            Err(e) => {
                tracing::error!(error = %e, "detector cannot start");
                self.errors.push(e.detector(self.det));
                self.dead = true;
            }
        }
    }

    /// The state to start from, if any checkpoint applies.
    fn start(&mut self) -> Result<Option<(State, Bookkeeping)>> {
        let cfg = self.cfg;
        let path = match cfg.from_checkpoint {
            Some((d, index)) if d == self.det => {
                Some(checkpoint::find(&cfg.checkpoints, d, index).ok_or_else(|| {
                    Error::new(
                        ErrorKind::Checkpoint,
                        format!("no checkpoint for detector {d} at exposure {index}"),
                    )
                    .path(&cfg.checkpoints)
                })?)
            }
            _ => {
                let newest = super::fallback::newest_readable(
                    &cfg.checkpoints,
                    self.ops.guard.as_ref(),
                    self.det,
                )?;
                self.errors.extend(newest.skipped);
                let Some((path, meta, state)) = newest.found else {
                    return Ok(None);
                };
                return self.resume(path, meta, state).map(Some);
            }
        };
        let Some(path) = path else { return Ok(None) };
        let (meta, state) = crate::guard::load_checkpoint(self.ops.guard.as_ref(), &path)?;
        self.resume(path, meta, state).map(Some)
    }

    /// Resume from a loaded checkpoint, if this run's model accepts it.
    fn resume(
        &self,
        path: PathBuf,
        meta: CheckpointMeta,
        state: State,
    ) -> Result<(State, Bookkeeping)> {
        let cfg = self.cfg;
        if meta.model_id != cfg.model.identity() && !cfg.allow_model_change {
            return Err(Error::new(
                ErrorKind::Checkpoint,
                format!(
                    "made with model {} ({}), this run uses {} ({}); pass --allow-model-change to continue from it",
                    meta.model_name,
                    &meta.model_id[..meta.model_id.len().min(12)],
                    cfg.model.params().name,
                    &cfg.model.identity()[..12],
                ),
            )
            .path(&path));
        }
        resume_parts(&path, state, &meta, &cfg.model)
    }

    /// Whether this detector's indices are start times (module docs: start-time order).
    fn by_start_time(&self) -> bool {
        self.book.by_start_time == Some(true)
    }

    /// Decide what to do with a newly observed product (module docs: duplicates, late).
    fn offer(
        &mut self,
        path: &Path,
        meta: ExposureMeta,
        by_start_time: bool,
        now: Instant,
    ) -> Offer {
        if self.dead {
            return Offer::Dead;
        }
        let index = meta.exposure_index;
        let err = |kind: ErrorKind, msg: String| {
            Error::new(kind, msg)
                .path(path)
                .field("exposure_index")
                .detector(self.det)
                .exposure(index)
        };
        let resumed = self.last().is_some();
        if let Err(why) = self.book.admit_order(resumed, by_start_time) {
            return Offer::Refused(err(ErrorKind::Sequence, why));
        }
        if let Some(last) = self.last().filter(|&l| index <= l) {
            if let Some(d) = self.book.digests.get(&index) {
                return match file_digest(path) {
                    Ok(x) if &x == d => Offer::AlreadyProcessed,
                    Ok(_) => Offer::Refused(err(
                        ErrorKind::Sequence,
                        format!(
                            "duplicate of exposure {index}, already processed, with different content (SHA-256 differs): refused"
                        ),
                    )),
                    Err(e) => Offer::Failed(e),
                };
            }
            if self.book.was_crossed(index) {
                return Offer::Refused(err(
                    ErrorKind::Sequence,
                    format!(
                        "late product: arrived after its gap was crossed (exposure {last} already processed): refused"
                    ),
                ));
            }
            // Ordered by start time, a product starting between two processed ones (or
            // before the last) that was not processed itself is late.
            let within_window = self.book.digests.keys().next().is_some_and(|&f| index > f);
            if self.by_start_time() && within_window {
                return Offer::Refused(err(
                    ErrorKind::Sequence,
                    format!(
                        "late product: starts before exposure {last} (already processed, exposures ordered by start time): refused"
                    ),
                ));
            }
            if self.book.first_index.is_some_and(|f| index < f) {
                return Offer::Refused(err(
                    ErrorKind::Sequence,
                    format!(
                        "late product: before the first exposure of this history ({}): refused",
                        self.book.first_index.unwrap_or_default()
                    ),
                ));
            }
            return Offer::AlreadyProcessed;
        }
        if let Some(p) = self.pending.get_mut(&index) {
            if p.path == path {
                // The same file seen again (changed in place): take its new attributes.
                p.meta = meta;
                p.digest = None;
                p.key = file_key(path).ok();
                return Offer::Known;
            }
            let first = match &p.digest {
                Some(d) => Ok(d.clone()),
                None => file_digest(&p.path),
            };
            return match (first, file_digest(path)) {
                (Ok(a), Ok(b)) if a == b => {
                    p.digest = Some(a);
                    Offer::IgnoredCopy(p.path.clone())
                }
                (Ok(a), Ok(_)) => {
                    p.digest = Some(a);
                    Offer::Refused(err(
                        ErrorKind::Sequence,
                        format!(
                            "duplicate of {} (same detector and exposure index) with different content: refused",
                            p.path.display()
                        ),
                    ))
                }
                (Err(e), _) | (_, Err(e)) => Offer::Failed(e),
            };
        }
        self.pending.insert(
            index,
            Pending {
                path: path.to_path_buf(),
                meta,
                seen: now,
                digest: None,
                key: file_key(path).ok(),
                retry_at: None,
            },
        );
        Offer::Queued
    }

    /// Is the first queued product's turn? (module docs: the gap rule)
    fn ready(&self, next: u64, p: &Pending, now: Instant, final_: bool) -> bool {
        if p.retry_at.is_some_and(|t| now < t) {
            return false;
        }
        let timed_out = now.saturating_duration_since(p.seen) >= self.ops.gap_timeout;
        if self.by_start_time() {
            // Start times have no successor to wait for: the earliest queued goes now.
            return true;
        }
        match self.last() {
            Some(l) if next == l + 1 => true,
            Some(l) => final_ || timed_out || (l + 1..next).all(|i| self.refused.contains(&i)),
            None => {
                next == 0 || final_ || timed_out || (0..next).all(|i| self.refused.contains(&i))
            }
        }
    }

    fn advance(&mut self, now: Instant, final_: bool) {
        if self.dead || !self.started {
            return;
        }
        loop {
            if self.ops.stop.load(Ordering::SeqCst) {
                break;
            }
            let Some((&next, p)) = self.pending.first_key_value() else {
                break;
            };
            if !self.ready(next, p, now, final_) {
                break;
            }
            let Some(mut entry) = self.pending.remove(&next) else {
                break;
            };
            if let Some(l) = self
                .last()
                .filter(|_| exposure_step::gap_before(&self.book, self.last(), next))
            {
                self.gap_before = true;
                if !(l + 1..next).all(|i| self.refused.contains(&i)) {
                    tracing::warn!(
                        detector = self.det.0,
                        from = l + 1,
                        to = next - 1,
                        "gap crossed: exposures missing; going on, history incomplete"
                    );
                }
            }
            let t0 = Instant::now();
            match self.one(&mut entry) {
                Ok(mut report) => {
                    report.seconds = t0.elapsed().as_secs_f64();
                    self.gap_before = false;
                    tracing::info!(detector = self.det.0, exposure_index = next,
                        path = %entry.path.display(),
                        above_high = report.summary.above_high,
                        above_low = report.summary.above_low,
                        history_incomplete = report.history_incomplete,
                        written = report.written, "processed");
                    (self.on_exposure)(&report);
                    self.reports.push(report);
                    self.unsaved += 1;
                    self.last_step = Some(Instant::now());
                    if self.cfg.retention().on_grid(next) {
                        self.save_now();
                    }
                }
                Err(Failure::Input(e))
                    if e.kind != ErrorKind::NotReady
                        && entry.key.is_some()
                        && file_key(&entry.path).ok() != entry.key =>
                {
                    // It changed since it was observed: still being written, not bad.
                    tracing::debug!(path = %entry.path.display(), error = %e,
                        "changed since observed; will retry");
                    if final_ {
                        self.errors
                            .push(e.path(&entry.path).detector(self.det).exposure(next));
                    } else {
                        self.forget.push(entry.path);
                    }
                    break;
                }
                Err(Failure::Input(e)) if e.kind == ErrorKind::NotReady => {
                    if final_ {
                        self.errors
                            .push(e.path(&entry.path).detector(self.det).exposure(next));
                        break;
                    }
                    tracing::debug!(path = %entry.path.display(), error = %e, "not ready; will retry");
                    if e.message.contains("changed while being queued") {
                        self.forget.push(entry.path);
                    } else {
                        entry.retry_at = Some(now + RETRY_NOT_READY);
                        self.pending.insert(next, entry);
                    }
                    break;
                }
                Err(Failure::Input(e)) if e.kind == ErrorKind::Io => {
                    // Vanished or unreadable: not its content; forget it (a reappearance
                    // is observed anew), the gap rule decides about its place. A batch
                    // stops this detector here: it does not cross a product that exists.
                    tracing::error!(error = %e, "cannot read");
                    self.errors
                        .push(e.path(&entry.path).detector(self.det).exposure(next));
                    self.forget.push(entry.path);
                    if final_ {
                        break;
                    }
                }
                Err(Failure::Input(e)) => {
                    self.gap_before = true;
                    self.refused.insert(next);
                    self.refused_files
                        .push((entry.path.clone(), e.detector(self.det).exposure(next)));
                }
                Err(Failure::Output(e)) => {
                    self.output_failed(e.exposure(next));
                    return;
                }
            }
        }
        // Every pass ends with its outputs published; a failed one stops the detector
        // before any checkpoint that would include it.
        if let Err(e) = self.finish_committing() {
            self.output_failed(e);
            return;
        }
        let idle = self
            .last_step
            .is_none_or(|t| t.elapsed() >= self.cfg.checkpoint_idle);
        if self.unsaved > 0 && (final_ || idle || self.ops.stop.load(Ordering::SeqCst)) {
            self.save_now();
        }
        // Every pass ends with its checkpoints published; a failed publication is
        // retried once (the state in memory is still the one to save).
        if !self.finish_publishing() {
            self.save_now();
            self.finish_publishing();
        }
    }

    /// Checkpoint the state: checked and written here (HDF5, from the state in memory,
    /// no copy), then published (fsync, rename, directory fsync) and the old checkpoints
    /// pruned on another thread, so that syncing a 200 MB file does not stall the next
    /// exposures. A detector's checkpoints are published in order, always after the
    /// outputs they include: the previous publication is waited for first.
    fn save_now(&mut self) {
        self.finish_publishing();
        let Some(state) = &self.state else { return };
        match self.write_checkpoint(state) {
            Ok((staged, index)) => {
                // The outputs this checkpoint includes are published first.
                if let Err(e) = self.finish_committing() {
                    drop(staged);
                    self.output_failed(e);
                    return;
                }
                self.unsaved = 0;
                let (dir, det, retention) =
                    (self.cfg.checkpoints.clone(), self.det, self.cfg.retention());
                self.publishing = Some(std::thread::spawn(move || {
                    if let checkpoint::Staged::Written(s) = staged {
                        s.commit().map_err(|e| e.exposure(index))?;
                    }
                    checkpoint::prune(&dir, det, &retention)?;
                    Ok(())
                }));
            }
            Err(e) => {
                tracing::error!(error = %e, "checkpoint failed");
                self.errors.push(e);
            }
        }
    }

    /// The state already holds an exposure whose output is not published: stop this
    /// detector without a checkpoint, so that the next run replays from the last one.
    fn output_failed(&mut self, e: Error) {
        tracing::error!(error = %e, detector = self.det.0, "output failed: detector stopped");
        self.errors.push(e.detector(self.det));
        self.dead = true;
        let _ = self.finish_committing();
        self.finish_publishing();
    }

    /// Wait for the last output's publication.
    fn finish_committing(&mut self) -> Result<()> {
        let Some(handle) = self.committing.take() else {
            return Ok(());
        };
        handle.join().unwrap_or_else(|_| {
            Err(Error::new(
                ErrorKind::Io,
                "the thread publishing an output panicked",
            ))
        })
    }

    /// Wait for the last checkpoint's publication; false if it failed (recorded).
    fn finish_publishing(&mut self) -> bool {
        let Some(handle) = self.publishing.take() else {
            return true;
        };
        let result = handle.join().unwrap_or_else(|_| {
            Err(Error::new(
                ErrorKind::Checkpoint,
                "the thread publishing a checkpoint panicked",
            ))
        });
        match result {
            Ok(()) => true,
            Err(e) => {
                tracing::error!(error = %e, "checkpoint publication failed");
                self.errors.push(e.detector(self.det));
                false
            }
        }
    }

    /// Read, step, publish one exposure.
    fn one(&mut self, entry: &mut Pending) -> Result<ExposureReport, Failure> {
        // The duplicate digest reads the file's bytes with plain file I/O (no HDF5), on
        // its own thread while the product is read through HDF5.
        let digesting = entry.digest.is_none().then(|| {
            let path = entry.path.clone();
            std::thread::spawn(move || file_digest(&path))
        });
        let next = self.pending.first_key_value().map(|(_, p)| p.path.clone());
        let (exposure, fits) = crate::guard::read_input_ahead(
            self.ops.guard.as_ref(),
            &mut self.ahead,
            &entry.path,
            next.as_deref(),
            &self.ops.fits,
        )
        .map_err(Failure::Input)?;
        let mut read = InputProduct { exposure, fits };
        let meta = read.exposure.meta.clone();
        if meta != entry.meta {
            return Err(Failure::Input(
                Error::new(
                    ErrorKind::NotReady,
                    "changed while being queued; will be retried",
                )
                .path(&entry.path),
            ));
        }
        // Joined before the state changes, so that a failed digest leaves it untouched.
        if let Some(h) = digesting {
            let digest = h.join().unwrap_or_else(|_| {
                Err(Error::new(ErrorKind::Io, "the digest thread panicked").path(&entry.path))
            });
            entry.digest = Some(digest.map_err(Failure::Input)?);
        }
        let out_path = self.output_path(&entry.path);
        let shape = read.exposure.image.dim();
        let model = &self.model;
        let st = self
            .state
            .get_or_insert_with(|| model.new_state(shape.0, shape.1));
        let step = ExposureStep {
            window: Window::whole(shape),
            gap_before: self.gap_before,
            digest: entry.digest.clone().unwrap_or_default(),
        };
        let stepped = exposure_step::step_exposure(
            model,
            st,
            &mut self.book,
            &mut read.exposure,
            step,
            &mut self.buffers,
        )
        .map_err(Failure::Input)?;
        let summary = stepped.summary;
        let written = if out_path.exists() && !self.reprocess {
            // Published by a run that may have stopped before its directory fsync
            // (h5io::Staged::commit): made durable before a checkpoint includes it.
            crate::h5io::sync_dir(&out_path).map_err(Failure::Output)?;
            false
        } else {
            let planes = &self.buffers;
            let attrs = exposure_step::output_attrs(
                model,
                summary.t_meas_s,
                summary.previous_index,
                &self.cfg.processed_utc,
                planes,
                None,
            );
            let staged = format::stage_output(
                &entry.path,
                &out_path,
                &read,
                planes,
                &attrs,
                &self.ops.fits,
            )
            .map_err(Failure::Output)?;
            // Outputs are published in order: the previous one's publication (started
            // while this exposure was read and stepped) ends first.
            self.finish_committing().map_err(Failure::Output)?;
            if let Some(staged) = staged {
                let index = meta.exposure_index;
                self.committing = Some(std::thread::spawn(move || {
                    staged.commit().map_err(|e| e.exposure(index))
                }));
            }
            true
        };
        Ok(ExposureReport {
            detector: self.det.0,
            exposure_index: meta.exposure_index,
            path: entry.path.clone(),
            summary,
            history_incomplete: stepped.history_incomplete,
            written,
            seconds: 0.0,
        })
    }

    fn output_path(&self, input: &Path) -> PathBuf {
        self.cfg.output.join(input.file_name().unwrap_or_default())
    }

    /// Write (not yet publish) the checkpoint of `state`; returns it and its index.
    fn write_checkpoint(&self, state: &State) -> Result<(checkpoint::Staged, u64)> {
        let model = &self.cfg.model;
        let stage_json = serde_json::to_string(&self.book).map_err(|e| {
            Error::new(ErrorKind::Checkpoint, format!("bookkeeping: {e}")).field("stage_json")
        })?;
        let meta = CheckpointMeta {
            detector: self.det,
            exposure_index: state.last_index.unwrap_or(0),
            model_id: model.identity().to_string(),
            model_name: model.params().name.clone(),
            model_json: model.params().canonical_json(),
            stage_json,
            software_version: crate::VERSION.to_string(),
        };
        let index = meta.exposure_index;
        Ok((
            checkpoint::stage(&self.cfg.checkpoints, &meta, state)?,
            index,
        ))
    }
}

/// What every resume checks once the checkpoint's model is accepted: the state holds as
/// many terms as the model, and the stage's bookkeeping (`stage_json`) parses.
pub(crate) fn resume_parts(
    path: &Path,
    state: State,
    meta: &CheckpointMeta,
    model: &Model,
) -> Result<(State, Bookkeeping)> {
    if state.n_terms() != model.n_terms() {
        return Err(Error::new(
            ErrorKind::Checkpoint,
            format!(
                "holds {} terms, the model has {}",
                state.n_terms(),
                model.n_terms()
            ),
        )
        .path(path));
    }
    let book: Bookkeeping = serde_json::from_str(&meta.stage_json).map_err(|e| {
        Error::new(ErrorKind::Checkpoint, format!("stage_json: {e}"))
            .path(path)
            .field("stage_json")
    })?;
    Ok((state, book))
}
