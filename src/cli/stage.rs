//! `persist run` (the stage, or one worker process per detector), `persist status` and
//! `persist fractions`: the options, the configuration built from them, what is printed.

use super::load_model;
use super::logging::BAR;
use super::parse::{nonnegative_seconds, parse_checkpoint_key, positive_seconds};
use clap::Args;
use persist::stage::{self, ExposureReport, Ops, RunConfig, RunReport, WatchOpts};
use persist::units::DetectorId;
use persist::{Error, ErrorKind};
use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::Duration;

#[derive(Args, Debug)]
pub struct RunArgs {
    /// Directory of Level-1 exposure products (`*.h5`, searched recursively).
    #[arg(long)]
    pub input: PathBuf,
    /// Directory for the output products.
    #[arg(long)]
    pub output: PathBuf,
    /// Directory for the checkpoints.
    #[arg(long)]
    pub checkpoints: PathBuf,
    /// Model file (JSON); the built-in default (the paper's constants) if absent.
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Reprocess one detector from its checkpoint at an exposure: `DETECTOR:INDEX`.
    #[arg(long, value_parser = parse_checkpoint_key)]
    pub from_checkpoint: Option<(DetectorId, u64)>,
    /// Continue from checkpoints made with a different model.
    #[arg(long)]
    pub allow_model_change: bool,
    #[command(flatten)]
    pub ckpt: stage::options::CheckpointArgs,
    /// With --watch: write a checkpoint once no exposure was processed for this many
    /// seconds (between, one every --checkpoint-every exposures).
    #[arg(long, default_value_t = 600.0, value_parser = nonnegative_seconds)]
    pub checkpoint_idle_s: f64,
    /// Write one CSV row per detector and exposure processed to this file (replaced by
    /// each run): the fraction of pixels above each threshold, the pixels flagged, ...
    /// (`persist fractions FILE` summarises and plots it).
    #[arg(long)]
    pub table: Option<PathBuf>,
    /// Print nothing per exposure (no table, no progress bar, warnings and errors only).
    #[arg(long, short)]
    pub quiet: bool,
    /// Keep running: pick up products as they arrive (file system events plus a periodic
    /// rescan) until SIGINT/SIGTERM.
    #[arg(long)]
    pub watch: bool,
    /// With --watch: rescan the input directory every this many seconds.
    #[arg(long, default_value_t = 10.0, value_parser = positive_seconds)]
    pub poll_interval_s: f64,
    /// With --watch: do not use file system events (polling only, e.g. on NFS).
    #[arg(long)]
    pub no_events: bool,
    /// With --watch: a product waiting behind a missing exposure waits at most this many
    /// seconds (from when it was first seen); then the gap is crossed.
    #[arg(long, default_value_t = 600.0, value_parser = nonnegative_seconds)]
    pub gap_timeout_s: f64,
    /// With --watch: keep Prometheus metrics (docs/operations.md) in this file, replaced
    /// atomically at most every second: a textfile for node_exporter (`*.prom`).
    #[arg(long, requires = "watch")]
    pub metrics_file: Option<PathBuf>,
    /// With --watch: serve the same metrics over HTTP on this address (e.g.
    /// 127.0.0.1:9464).
    #[arg(long, requires = "watch")]
    pub metrics_addr: Option<std::net::SocketAddr>,
    /// Process every detector in this one process (threads) rather than one worker
    /// process per detector (HDF5 serialises the I/O of one process).
    #[arg(long)]
    pub one_process: bool,
    /// Internal: the worker of one detector under a parent that holds the lock.
    #[arg(long, hide = true)]
    pub worker: Option<u8>,
    /// Internal: this worker also refuses products whose detector cannot be read.
    #[arg(long, hide = true)]
    pub worker_unattributed: bool,
    /// Where refused inputs are moved, each with a `NAME.reason.json` [default:
    /// INPUT/.quarantine, on the input's file system so the move is a rename; hidden
    /// directories are never scanned].
    #[arg(long)]
    pub quarantine: Option<PathBuf>,
    /// FITS inputs: a JSON file renaming the header keywords and extensions read
    /// (docs/fits.md); SPHEREx's names by default.
    #[arg(long)]
    pub fits_keywords: Option<PathBuf>,
    /// FITS inputs: e-/s per image unit for detector D (`D:FACTOR`, repeatable); wins
    /// over the header's ESCONV.
    #[arg(long = "fits-gain", value_parser = persist::fits::parse_gain)]
    pub fits_gain: Vec<(u8, f64)>,
    #[command(flatten)]
    pub reader: ReaderGuardArgs,
}

/// The reader guard's switch and limits ([`persist::guard`]), for `persist run` and
/// `persist status`.
#[derive(Args, Debug, Clone)]
pub struct ReaderGuardArgs {
    /// Read every input and checkpoint in-process, without first reading it in an
    /// isolated child process (the reader guard, docs/operations.md).
    #[arg(long)]
    pub no_reader_guard: bool,
    /// The reader guard's limit of wall time (and CPU time) per file read, seconds.
    #[arg(long, default_value_t = persist::guard::DEFAULT_TIMEOUT_S, value_parser = positive_seconds)]
    pub reader_timeout_s: f64,
    /// The reader guard's limit of address space per file read, MiB.
    #[arg(long, default_value_t = persist::guard::DEFAULT_MEMORY_MIB, value_parser = clap::value_parser!(u64).range(64..))]
    pub reader_memory_mib: u64,
}

impl ReaderGuardArgs {
    /// The guard these options ask for, run through this executable; `None` with
    /// `--no-reader-guard`.
    pub fn guard(&self) -> persist::Result<Option<persist::guard::Guard>> {
        if self.no_reader_guard {
            return Ok(None);
        }
        let exe = std::env::current_exe().map_err(|e| Error::new(ErrorKind::Io, e.to_string()))?;
        Ok(Some(persist::guard::Guard {
            exe,
            timeout: Duration::from_secs_f64(self.reader_timeout_s),
            memory_bytes: self.reader_memory_mib << 20,
        }))
    }
}

#[derive(Args, Debug)]
pub struct StatusArgs {
    /// The stage's output directory.
    #[arg(long)]
    pub output: PathBuf,
    /// The stage's checkpoint directory.
    #[arg(long)]
    pub checkpoints: PathBuf,
    /// The input directory (to count the backlog and the missing exposures).
    #[arg(long)]
    pub input: Option<PathBuf>,
    /// The quarantine directory [default: INPUT/.quarantine when --input is given].
    #[arg(long)]
    pub quarantine: Option<PathBuf>,
    /// Print JSON instead of a table.
    #[arg(long)]
    pub json: bool,
    /// Also print the checkpoint footprint one detector would reach after
    /// --project-exposures exposures under the retention given (the options of
    /// `persist run`), at the mean size of the checkpoints on disk.
    #[arg(long)]
    pub projection: bool,
    /// The retention to project the checkpoint footprint with (as `persist run`'s).
    #[command(flatten)]
    pub ckpt: stage::options::CheckpointArgs,
    /// Project the footprint after this many exposures per detector (SPHEREx: about
    /// 4 x 10^5 in two years).
    #[arg(long, default_value_t = 400_000)]
    pub project_exposures: u64,
    /// ... taken every this many seconds (two years / 4 x 10^5).
    #[arg(long, default_value_t = 157.8, value_parser = positive_seconds)]
    pub project_interval_s: f64,
    // the checkpoints are read as `persist run` reads them (checked first in the reader
    // guard's child process)
    #[command(flatten)]
    pub reader: ReaderGuardArgs,
}

/// `persist status`.
pub(super) fn status(args: &StatusArgs) -> persist::Result<ExitCode> {
    let quarantine = args
        .quarantine
        .clone()
        .or_else(|| args.input.as_ref().map(|i| i.join(".quarantine")));
    let mut st = stage::status::status(
        &args.output,
        &args.checkpoints,
        args.input.as_deref(),
        quarantine.as_deref(),
        args.reader.guard()?.as_ref(),
    );
    if args.projection {
        st.projection = stage::status::project(
            &st,
            &args.ckpt.retention(),
            args.project_exposures,
            args.project_interval_s,
        );
        if st.projection.is_none() {
            st.problems
                .push("no checkpoint on disk: nothing to project the footprint from".into());
        }
    }
    if args.json {
        let text = serde_json::to_string_pretty(&st)
            .map_err(|e| Error::new(ErrorKind::Io, format!("status as JSON: {e}")))?;
        out!("{text}");
    } else {
        out_nonl!("{}", stage::status::render(&st));
    }
    Ok(ExitCode::SUCCESS)
}

pub(super) fn fractions(table: &Path, plot: Option<&Path>) -> persist::Result<ExitCode> {
    let rows = stage::table::read(table)?;
    out_nonl!("{}", stage::table::summary(&rows));
    if let Some(png) = plot {
        stage::table::plot(&rows, png)?;
        out!("plot {}", png.display());
    }
    Ok(ExitCode::SUCCESS)
}

pub(super) fn run_stage(args: &RunArgs) -> persist::Result<ExitCode> {
    let model = load_model(args.model.as_deref())?;
    // One stage per set of directories; then nothing else writes there, so every
    // temporary left is from an interrupted write of ours.
    let worker = args
        .worker
        .map(|d| {
            DetectorId::new(i64::from(d))
                .ok_or_else(|| Error::invalid("--worker", format!("detector {d} is not in 1..=6")))
        })
        .transpose()?;
    // A worker runs under its parent's lock (module docs of `stage::workers`).
    let started = stage::startup::start(
        &[&args.output, &args.checkpoints],
        stage::startup::Startup {
            lock: worker.is_none(),
            signals: true,
        },
    )?;
    let stop = Arc::clone(&started.stop);
    if worker.is_some() {
        // Blocked since the worker started: a stop forwarded before now is handled now.
        stage::workers::unblock_stop_signals();
    }
    // The parent starts the table; its workers append to it.
    let table = match (&args.table, worker) {
        (None, _) => None,
        (Some(t), None) => Some(stage::table::RunTable::create(t)?),
        (Some(t), Some(_)) => Some(stage::table::RunTable::append_to(t)?),
    };
    let fits = persist::fits::FitsConfig {
        keywords: match &args.fits_keywords {
            Some(p) => persist::fits::Keywords::load(p)?,
            None => Default::default(),
        },
        gains: args.fits_gain.iter().copied().collect(),
    };
    let guard = args.reader.guard()?;
    // A missing input is the stage's error to report (exit 1), not a usage error.
    if worker.is_none() && !args.watch && !args.one_process && args.input.is_dir() {
        let dets = stage::workers::detectors(&args.input, &fits, guard.as_ref())?;
        if dets.len() > 1 {
            drop(table);
            return run_workers(args, &dets, &stop);
        }
    }
    let progress =
        (worker.is_none() && !args.watch && !args.quiet && std::io::stderr().is_terminal()).then(
            || {
                let pb = indicatif::ProgressBar::new(0);
                pb.set_style(
                    indicatif::ProgressStyle::with_template(
                        "{elapsed_precise} [{bar:40}] {pos}/{len} exposures ({eta} left)",
                    )
                    .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
                );
                let _ = BAR.set(pb.clone());
                pb
            },
        );
    let metrics = (args.metrics_file.is_some() || args.metrics_addr.is_some()).then(|| {
        Arc::new(stage::metrics::Metrics::new(
            &args.checkpoints,
            args.metrics_file.clone(),
        ))
    });
    if let (Some(addr), Some(m)) = (args.metrics_addr, &metrics) {
        stage::metrics::serve(addr, Arc::clone(m))?;
    }
    let ops = Ops {
        metrics,
        quarantine: Some(
            args.quarantine
                .clone()
                .unwrap_or_else(|| args.input.join(".quarantine")),
        ),
        watch: args.watch.then(|| WatchOpts {
            poll_interval: Duration::from_secs_f64(args.poll_interval_s),
            events: !args.no_events,
        }),
        gap_timeout: Duration::from_secs_f64(args.gap_timeout_s),
        stop,
        progress,
        fits: fits.clone(),
        only: worker.map(|detector| stage::OnlyDetector {
            detector,
            unattributed: args.worker_unattributed,
        }),
        guard,
    };
    let cfg = RunConfig {
        input: args.input.clone(),
        output: args.output.clone(),
        checkpoints: args.checkpoints.clone(),
        model,
        from_checkpoint: args.from_checkpoint,
        allow_model_change: args.allow_model_change,
        checkpoint_every: args.ckpt.checkpoint_every,
        checkpoint_idle: Duration::from_secs_f64(args.checkpoint_idle_s),
        retention: args.ckpt.retention(),
        processed_utc: stage::processing_time(),
    };
    let report = stage::run_with(&cfg, &ops, &|r| {
        if let Some(pb) = &ops.progress {
            pb.inc(1);
        }
        if let Some(Err(e)) = table.as_ref().map(|t| t.append(r)) {
            tracing::error!(error = %e, "cannot append to the table");
        }
    });
    if let (Some(t), None) = (&args.table, worker) {
        stage::table::sort(t)?;
    }
    if let Some(pb) = &ops.progress {
        pb.finish_and_clear();
    }
    if !args.quiet && !args.watch {
        print_summary(&report, worker.is_none());
    }
    Ok(finish(&report))
}

/// `persist run` as one worker process per detector (`stage::workers`).
pub(super) fn run_workers(
    args: &RunArgs,
    dets: &std::collections::BTreeSet<DetectorId>,
    stop: &AtomicBool,
) -> persist::Result<ExitCode> {
    let exe = std::env::current_exe().map_err(|e| Error::new(ErrorKind::Io, e.to_string()))?;
    let argv: Vec<std::ffi::OsString> = std::env::args_os().skip(1).collect();
    let outcomes = stage::workers::run_workers(&exe, &argv, dets, stop)?;
    if let Some(t) = &args.table {
        stage::table::sort(t)?;
    }
    if !args.quiet {
        print_summary(&RunReport::default(), true);
    }
    let mut failed = false;
    for o in &outcomes {
        out_nonl!("{}", o.stdout);
        if !o.status.success() {
            failed = true;
            // Exit status 1: the worker reported its failures itself.
            if o.status.code() != Some(1) {
                eprintln!("persist: worker of detector {}: {}", o.detector.0, o.status);
            }
        }
    }
    Ok(if failed {
        ExitCode::from(1)
    } else {
        ExitCode::SUCCESS
    })
}

/// Per-exposure table, sorted by (detector, exposure), then the errors.
pub(super) fn print_summary(report: &RunReport, header: bool) {
    let mut rows: Vec<&ExposureReport> = report.exposures.iter().collect();
    rows.sort_by_key(|r| (r.detector, r.exposure_index));
    if header {
        out!(
            "{:>3} {:>8} {:>10} {:>9} {:>7} {:>9} {:>7} {:>8}  notes",
            "det",
            "exposure",
            "t_meas_s",
            ">0.1e/s",
            "%",
            ">0.01e/s",
            "%",
            "released"
        );
    }
    for r in rows {
        let s = &r.summary;
        let pct = |n: u64| 100.0 * n as f64 / s.pixels.max(1) as f64;
        let mut notes = Vec::new();
        if s.max_amplitude > 0 {
            notes.push(format!("{} at max amplitude", s.max_amplitude));
        }
        if r.history_incomplete {
            notes.push("history incomplete".to_string());
        }
        if !r.written {
            notes.push("already published".to_string());
        }
        out!(
            "{:>3} {:>8} {:>10} {:>9} {:>7.2} {:>9} {:>7.2} {:>8}  {}",
            r.detector,
            r.exposure_index,
            s.t_meas_s.map_or("-".to_string(), |t| format!("{t:.1}")),
            s.above_high,
            pct(s.above_high),
            s.above_low,
            pct(s.above_low),
            s.released,
            notes.join("; ")
        );
    }
}

pub(super) fn finish(report: &RunReport) -> ExitCode {
    if report.stopped {
        eprintln!(
            "persist: stopped by signal after {} exposure(s); checkpoints written",
            report.processed
        );
        return ExitCode::SUCCESS;
    }
    for p in &report.quarantined {
        eprintln!("persist: quarantined: {}", p.display());
    }
    for p in &report.ignored_copies {
        eprintln!(
            "persist: {}: identical copy of a queued product, ignored",
            p.display()
        );
    }
    for e in &report.errors {
        eprintln!("persist: error: {e}");
    }
    if report.errors.is_empty() {
        ExitCode::SUCCESS
    } else {
        eprintln!(
            "persist: {} exposure(s) processed, {} error(s)",
            report.processed,
            report.errors.len()
        );
        ExitCode::from(1)
    }
}
