//! The command line: parse, call the library, map the outcome to an exit code.
//! Exit codes: 0 all went well, or the run was stopped by SIGINT/SIGTERM (after
//! finishing the exposure in hand and writing its checkpoint); 1 some input or output
//! failed (the rest was processed, every failure reported, bad inputs quarantined);
//! 2 the command could not run at all (usage, model file, the directories are locked by
//! another stage).
//!
//! Logs go to stderr through `tracing`: human-readable by default, JSON lines with
//! `--log-json`; the level is `--log-level` (or the `PERSIST_LOG` filter). A batch run
//! on a terminal draws a progress bar on stderr (the logs are printed above it).

use clap::{Args, Parser, Subcommand};
use persist::calib::Preset;
use persist::diag::data::Background;
use persist::diag::diagnose::{Refit, Statistic};
use persist::diag::eval::{CellStatistic, Cells};
use persist::model::{Model, ModelParams};
use persist::stage::{self, ExposureReport, Ops, RunConfig, RunReport, WatchOpts};
use persist::units::DetectorId;
use persist::{Error, ErrorKind};
use std::io::{IsTerminal, Write};
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::atomic::AtomicBool;
use std::sync::{Arc, OnceLock};
use std::time::Duration;

/// `println!` to stdout that does not panic when stdout is gone (`persist ... | head`):
/// what the command printed is a report, and the work it reports on (files written,
/// checkpoints) must not depend on whether anyone still reads it. Any other write error
/// (a full disk under `persist model default > m.json`) is reported and exits 1
/// ([`stdout_failed`]).
macro_rules! out {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        if let Err(e) = writeln!(std::io::stdout().lock(), $($arg)*) {
            stdout_failed(e);
        }
    }};
}

/// `print!` without the newline, as [`out!`].
macro_rules! out_nonl {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        if let Err(e) = write!(std::io::stdout().lock(), $($arg)*) {
            stdout_failed(e);
        }
    }};
}

/// A write to stdout failed: a reader that went away is not an error; anything else is
/// (what was written is incomplete), reported on stderr with exit code 1.
fn stdout_failed(e: std::io::Error) {
    if e.kind() != std::io::ErrorKind::BrokenPipe {
        eprintln!("persist: writing to standard output: {e}");
        std::process::exit(1);
    }
}

#[derive(Parser, Debug)]
#[command(
    name = "persist",
    version,
    about = "Predict and flag image persistence in HAWAII-2RG arrays (SPHEREx)",
    after_help = "Exit codes: 0 done, or stopped by SIGINT/SIGTERM after the exposure in hand \
                  and its checkpoint; 1 some input or output failed (the rest was processed, \
                  every failure reported, bad inputs quarantined); 2 the command could not \
                  run (usage, model file, directories locked by another stage).\n\
                  Environment: PERSIST_LOG (a log filter, overrides --log-level), \
                  SOURCE_DATE_EPOCH (pins the processing time recorded in outputs)."
)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
    /// Logs as JSON lines (one object per event) instead of human-readable text.
    #[arg(long, global = true)]
    pub log_json: bool,
    /// Log level: error, warn, info, debug, trace (`PERSIST_LOG` overrides, as a filter).
    #[arg(long, global = true, default_value = "info")]
    pub log_level: String,
}

#[derive(Subcommand, Debug)]
pub enum Command {
    /// Flag persistence in every Level-1 product of a directory.
    Run(RunArgs),
    /// Model files: print the default, check one, print its identity.
    Model {
        #[command(subcommand)]
        action: ModelAction,
    },
    /// Check files against the ICD and their schemas: input and output products,
    /// checkpoints (`.h5`), model files (`.json`). Prints `ok <kind> <path>` per valid
    /// file and every error on stderr; exits 1 if any file failed.
    Validate {
        /// Files to check (all are checked, whatever fails).
        #[arg(required = true)]
        files: Vec<PathBuf>,
    },
    /// Simulate Level-1 products from a trap-physics truth (truth under `OUT/truth/`).
    Simulate {
        #[command(subcommand)]
        scenario: SimScenario,
    },
    /// Per detector: last exposure processed, backlog, gaps, quarantined files, age of
    /// the newest checkpoint. Reads the directories only; safe while a stage runs.
    Status(StatusArgs),
    /// Summarise the table of a run (`persist run --table FILE`) per detector: the
    /// fraction of pixels above each threshold and the pixels flagged; `--plot` draws
    /// the fractions per exposure into a PNG.
    Fractions {
        /// The CSV written by `persist run --table`.
        table: PathBuf,
        /// Draw the fractions above each threshold per exposure into this PNG.
        #[arg(long)]
        plot: Option<PathBuf>,
    },
    /// Calibrate a model from a laboratory sequence (the paper's fit), optionally with
    /// effects, and write the model file and a fit report.
    Fit(FitArgs),
    /// Predicted against measured persistence, residuals by covariate, flag quality;
    /// writes OUT/report.html and OUT/summary.json.
    Compare(CompareArgs),
    /// Score test of every library effect against a fitted model, threshold by
    /// parametric bootstrap, refit (delta BIC) and held-out check of the leaders.
    Diagnose(DiagnoseArgs),
    /// The main job on a built-in default: simulate two days of SPHEREx-like sky (one
    /// detector, 128 x 128), run the stage, print and plot what it flags.
    Demo(DemoArgs),
    /// Benchmark the model step, the memory bound, the whole stage and the HDF5 I/O
    /// bound, each case in a child process; prints a markdown table and writes JSON.
    Bench(BenchArgs),
    /// Export HDF5 products (inputs or outputs) as FITS files in SPHEREx's Level-2
    /// layout (docs/fits.md).
    Export(ExportArgs),
    /// Print the command-line reference (docs/cli.md) as markdown.
    #[command(hide = true)]
    HelpMarkdown,
    /// Development: the mutation fuzzer over every reader, against the real stage
    /// (`make fuzz`; docs/operations.md).
    #[command(hide = true)]
    Fuzz(FuzzArgs),
    /// Internal: read one file in an isolated child of `persist run` (the reader guard).
    #[command(hide = true, name = "guarded-read")]
    GuardedRead {
        /// `meta`, `exposure` or `checkpoint`.
        what: String,
        path: PathBuf,
        /// The FITS reading options, JSON.
        #[arg(long, default_value = "")]
        fits: String,
        /// Address-space limit, bytes.
        #[arg(long, default_value_t = persist::guard::DEFAULT_MEMORY_MIB << 20)]
        memory_bytes: u64,
        /// CPU-time limit, seconds.
        #[arg(long, default_value_t = persist::guard::DEFAULT_TIMEOUT_S as u64)]
        cpu_s: u64,
        /// The process that must stay this one's parent.
        #[arg(long)]
        parent: Option<u32>,
    },
    /// Persistence measured in flight (no shutter): follow pixels after bright events
    /// through later sky exposures, stack their excess over the surrounding sky by
    /// fluence and time, set it beside the stage's predictions and flags; writes
    /// REPORT/report.html and REPORT/report.json.
    Verify(VerifyArgs),
    /// Reprocess on a Slurm cluster: write the plan and batch scripts of an exact split
    /// (one array task per detector x pixel tile, then an assembly job with afterok),
    /// and submit them with --submit (docs/slurm.md).
    Slurm(persist::slurm::SlurmArgs),
    /// One task of a split run: one pixel tile of one detector's history.
    Tile(persist::slurm::TileArgs),
    /// Assemble a split run's tiles into whole-array outputs and final checkpoints.
    Assemble(persist::slurm::AssembleArgs),
    /// Measure a detector's per-pixel response map from a laboratory sequence against a
    /// model (empirical Bayes; docs/pixel_map.md), and optionally write the model naming it.
    Pixelmap(persist::pixmap::command::PixelmapArgs),
}

#[derive(Args, Debug)]
pub struct ExportArgs {
    /// HDF5 products to export (`NAME.h5` -> `OUT/NAME.fits`).
    #[arg(long = "fits", required = true, num_args = 1..)]
    pub files: Vec<PathBuf>,
    /// Output directory.
    #[arg(long)]
    pub out: PathBuf,
    /// Write the image of detector D in MJy/sr, FACTOR e-/s per MJy/sr (recorded as
    /// ESCONV); repeatable. Without it the image is written in e-/s.
    #[arg(long = "fits-gain", value_parser = persist::fits::parse_gain)]
    pub fits_gain: Vec<(u8, f64)>,
    /// Add VARIANCE, ZODI, PSF and WCS-WAVE placeholders and a spatial WCS (SPHEREx's
    /// full layout, synthetic values).
    #[arg(long)]
    pub placeholders: bool,
}

#[derive(Args, Debug)]
pub struct VerifyArgs {
    /// The stage's input directory (sky exposures; a simulator's `truth/` in it is used).
    #[arg(long)]
    pub input: PathBuf,
    /// The stage's output directory (its products carry the input image and flags).
    #[arg(long)]
    pub output: PathBuf,
    /// Where to write report.html and report.json.
    #[arg(long)]
    pub report: PathBuf,
    /// Extrapolated fluence from which a pixel's exposure is an event, e- [default: 2e5,
    /// the paper's saturation level; OVERFLOW pixels always are].
    #[arg(long)]
    pub event_fluence_e: Option<f64>,
    /// Reject a track's sample that rises more than this many standard deviations of the
    /// difference above its last accepted one floored at zero (a source in the pixel).
    #[arg(long, default_value_t = 3.0)]
    pub spike_nsigma: f64,
    /// Inner and outer Chebyshev radii of the sky annulus, pixels.
    #[arg(long, value_delimiter = ',', default_values_t = [3, 6])]
    pub annulus_px: Vec<usize>,
    /// Seed of the bootstrap over events.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Also learn each pixel's response from the tracks and write it as a per-pixel map
    /// (HDF5, the laboratory map's format; one detector: the first found). Needs
    /// `--map-model`.
    #[arg(long)]
    pub flight_map: Option<PathBuf>,
    /// The model the stage ran with, without a map: the flight map is measured against it.
    #[arg(long)]
    pub map_model: Option<PathBuf>,
    /// A laboratory map of the same detector to start the flight map from.
    #[arg(long)]
    pub prior_map: Option<PathBuf>,
}

#[derive(Subcommand, Debug)]
pub enum SimScenario {
    /// The paper's laboratory test: a 613 s integration lit for 481 s through a pinhole,
    /// then 180 s dark integrations (the first keeps its ramp).
    Lab(LabArgs),
    /// A SPHEREx-like survey: 112 s integrations, slews, zodiacal light, stars.
    Sky(SkyArgs),
    /// A laboratory sequence from the second, independent truth generator
    /// (`persist::trapgen`: continuous emission-time densities, finite capture, each
    /// seed its own detector), optionally with hidden effects.
    Family(FamilyArgs),
}

#[derive(Args, Debug)]
pub struct FamilyArgs {
    /// Output directory (products; truth in OUT/truth).
    #[arg(long)]
    pub out: PathBuf,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Array size N (N x N pixels).
    #[arg(long, default_value_t = 64)]
    pub size: usize,
    /// `single` (the paper's: one 481 s illumination, then darks) or `campaign` (six
    /// illuminations: durations, a repeat, temperatures; `persist::trapgen`).
    #[arg(long, default_value_t = persist::trapgen::scene::SequenceKind::Single,
          value_parser = parse_flag::<persist::trapgen::scene::SequenceKind>)]
    pub sequence: persist::trapgen::scene::SequenceKind,
    /// Dark integrations after a single illumination (180 s each).
    #[arg(long, default_value_t = persist::trapgen::DEFAULT_DARKS)]
    pub darks: usize,
    /// Leave the right-hand quarter unlit (otherwise every pixel is lit).
    #[arg(long)]
    pub dark_pixels: bool,
    /// Add the grid of one-pixel pinholes: `on`, `off` [default: drawn by the seed].
    #[arg(long)]
    pub pinholes: Option<OnOff>,
    /// A hidden effect CLASS:FORM (repeatable), e.g. `soak:capture`; see
    /// `persist::trapgen` for the forms and their physics.
    #[arg(long = "hidden", value_parser = parse_flag::<persist::trapgen::hidden::Hidden>)]
    pub hidden: Vec<persist::trapgen::hidden::Hidden>,
}

/// `on` or `off`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum OnOff {
    On,
    Off,
}

#[derive(Args, Debug)]
pub struct LabArgs {
    /// Output directory (products; truth in OUT/truth).
    #[arg(long)]
    pub out: PathBuf,
    /// Array size N (N x N pixels).
    #[arg(long, default_value_t = 256)]
    pub size: usize,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Dark integrations after the illumination (default 280 = 14 h; ignored with
    /// --campaign).
    #[arg(long, default_value_t = 280)]
    pub darks: usize,
    /// Chain several illuminations of different durations, fluxes and temperatures
    /// (see `persist::sim::lab` for the default campaign).
    #[arg(long)]
    pub campaign: bool,
    /// Where the campaign's spot is: `centred` (every illumination the same pattern,
    /// scaled), `shifted` (the spot moved for illuminations 2-5, so that radius and
    /// fluence do not go together; `persist::sim::lab`, "Shifted spots") or `pinholes`
    /// (the centred campaign plus a grid of one-pixel pinholes, for effects that couple
    /// neighbours; "Sharp pinholes"), or `paper` (the centred spots with every pixel
    /// lit at 30 e-/s or more, like the paper's laboratory data, so that no pixel stays
    /// below 3000 e-; also without --campaign; "The paper's pattern").
    #[arg(long, default_value_t = persist::sim::lab::Spots::default(),
          value_parser = parse_flag::<persist::sim::lab::Spots>)]
    pub spots: persist::sim::lab::Spots,
    /// With `--spots paper`: keep a corner of size/8 x size/8 pixels unlit, so that the
    /// sequence has pixels that were never lit.
    #[arg(long)]
    pub dark_pixels: bool,
    /// How long the campaign's dark integrations are: `uniform` (180 s) or `varied`
    /// (illumination 2's darks 60 s; its repeat's 540 s, after a reset 12 s after the
    /// shutter, so that the on-board line fit's bias, which grows with the
    /// integration's length and the decay's curvature, differs between two otherwise
    /// equal illuminations; `persist::sim::lab`, "Dark lengths").
    #[arg(long, default_value_t = persist::sim::lab::DarkLengths::default(),
          value_parser = parse_flag::<persist::sim::lab::DarkLengths>, requires = "campaign")]
    pub dark_lengths: persist::sim::lab::DarkLengths,
    /// Where the campaign's temperatures are: `mixed` (illuminations 4 and 5 at 78 and
    /// 82 K, each also of another length or flux) or `apart` (illumination 4 at 80 K
    /// followed by 3 h of darks, and a sixth illumination, 5's twin at 78 K, so that an
    /// effect of the illumination's length and one of the temperature each show on their
    /// own; `persist::sim::lab`, "Temperatures apart").
    #[arg(long, default_value_t = persist::sim::lab::Temperatures::default(),
          value_parser = parse_flag::<persist::sim::lab::Temperatures>, requires = "campaign")]
    pub temperatures: persist::sim::lab::Temperatures,
    /// Add N more 240 s illuminations at 80 K after illumination 3, each followed by
    /// five darks (15 min), so that the traps still hold the last one's charge when the
    /// next begins (an effect that limits what a full pixel can take in, the
    /// simulator's `capacity`, then acts at every repeat; `persist::sim::lab`,
    /// "Repeated illuminations"). At most 20.
    #[arg(long, default_value_t = 0, requires = "campaign",
          value_parser = clap::builder::RangedU64ValueParser::<usize>::new()
              .range(0..=persist::sim::lab::MAX_REPEATS as u64))]
    pub repeats: usize,
    /// Switch on a truth effect: NAME[:param=value,...] (repeatable). Names: blooming,
    /// capacity, ipc, linefit_bias, populations, short_tau_boost, soak, temperature.
    #[arg(long = "effect")]
    pub effects: Vec<String>,
}

#[derive(Args, Debug)]
pub struct SkyArgs {
    /// Output directory (products; truth in OUT/truth).
    #[arg(long)]
    pub out: PathBuf,
    #[arg(long, default_value_t = 2040)]
    pub size: usize,
    #[arg(long, default_value_t = 6)]
    pub detectors: u8,
    #[arg(long, default_value_t = 1143)]
    pub exposures: u64,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Switch on a truth effect: NAME[:param=value,...] (repeatable).
    #[arg(long = "effect")]
    pub effects: Vec<String>,
    #[command(flatten)]
    pub sky: SkyOptions,
    /// Product format: `h5` (the ICD), or `fits` (SPHEREx's Level-2 layout with
    /// placeholder VARIANCE, ZODI, PSF and WCS-WAVE; docs/fits.md).
    #[arg(long, default_value = "h5", value_parser = ["h5", "fits"])]
    pub format: String,
    /// With --format fits: write detector D's image in MJy/sr, FACTOR e-/s per MJy/sr
    /// (recorded as ESCONV); repeatable.
    #[arg(long = "fits-gain", value_parser = persist::fits::parse_gain)]
    pub fits_gain: Vec<(u8, f64)>,
}

/// Sky and detector parameters of the sky survey (defaults: `persist::sim::sky::SkyConfig`
/// and `persist::sim::detector::DetectorParams`; docs/validation/floor_scan.md scans them).
#[derive(Args, Debug, Clone, Default)]
pub struct SkyOptions {
    /// Stars brighter than magnitude 12 (the saturation magnitude) per 2040 x 2040 array
    /// at high latitude [default 30].
    #[arg(long)]
    pub n12: Option<f64>,
    /// Slope of the cumulative star counts, dex per magnitude [default 0.35].
    #[arg(long)]
    pub count_slope: Option<f64>,
    /// Faintest star drawn, magnitude [default 18].
    #[arg(long)]
    pub m_faint: Option<f64>,
    /// Fraction of the non-deep pointings that are Galactic-plane fields [default 0.1].
    #[arg(long)]
    pub plane_fraction: Option<f64>,
    /// Star density of a Galactic-plane field relative to high latitude [default 30].
    #[arg(long)]
    pub plane_density: Option<f64>,
    /// Cosmic-ray rate, hits per cm^2 per s [default 5].
    #[arg(long)]
    pub cosmic_rate: Option<f64>,
}

impl SkyOptions {
    /// Overwrite the parameters given on the command line.
    pub fn apply(&self, cfg: &mut persist::sim::sky::SkyConfig) {
        let set = |dst: &mut f64, v: Option<f64>| {
            if let Some(v) = v {
                *dst = v;
            }
        };
        set(&mut cfg.n12_per_array, self.n12);
        set(&mut cfg.count_slope, self.count_slope);
        set(&mut cfg.m_faint, self.m_faint);
        set(&mut cfg.plane_fraction, self.plane_fraction);
        set(&mut cfg.plane_density, self.plane_density);
        set(&mut cfg.detector.cosmic_rate_per_cm2_s, self.cosmic_rate);
    }
}

#[derive(Args, Debug)]
pub struct BenchArgs {
    /// Small sizes and few repetitions: runs in seconds.
    #[arg(long)]
    pub quick: bool,
    /// Image sizes (square), comma-separated; default 256,1024,2040 (quick: 64,128).
    #[arg(long, value_delimiter = ',')]
    pub sizes: Option<Vec<usize>>,
    /// rayon thread counts, comma-separated; default 1,2.
    #[arg(long = "thread-counts", value_delimiter = ',')]
    pub thread_counts: Option<Vec<usize>>,
    /// Timed repetitions of the in-memory cases.
    #[arg(long)]
    pub reps: Option<usize>,
    /// Exposures per stream of the I/O cases.
    #[arg(long)]
    pub exposures: Option<usize>,
    /// Interleaved rounds of the four cases (samples pooled).
    #[arg(long)]
    pub rounds: Option<usize>,
    /// Scratch directory for products, outputs and checkpoints (removed afterwards).
    #[arg(long)]
    pub scratch: Option<PathBuf>,
    /// Write the whole report as JSON here.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Only the `verify` case: `persist verify` on a simulated sky, a few full frames
    /// and one detector-day of a smaller frame, projected to a full-frame day.
    #[arg(long)]
    pub verify_only: bool,
    /// The `verify` case's sizes: FULL,DAY (the full frame, the frame of the measured
    /// day); default 2040,512 (quick: 64,32).
    #[arg(long, value_delimiter = ',', num_args = 1)]
    pub verify_sizes: Option<Vec<usize>>,
    /// The `verify` case's exposures: FIRST,DAY (of the full frame, of the day);
    /// default 6,571 (quick: 4,30).
    #[arg(long, value_delimiter = ',', num_args = 1)]
    pub verify_exposures: Option<Vec<usize>>,
    /// Child mode: run one case (`step`, `memory`, `stage`, `io`), print its JSON.
    #[arg(long, hide = true)]
    pub case: Option<String>,
    #[arg(long, hide = true, default_value_t = 2040)]
    pub size: usize,
    #[arg(long, hide = true, default_value_t = 1)]
    pub threads: usize,
    #[arg(long, hide = true, default_value_t = 1)]
    pub checkpoint_every: u64,
    /// Only write this many input products of `--size` under `--scratch` (for profiling
    /// one case by hand with `--case`).
    #[arg(long, hide = true)]
    pub prepare: Option<usize>,
}

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

#[derive(Args, Debug)]
pub struct FuzzArgs {
    /// Mutants in all (the readers in turn).
    #[arg(long, default_value_t = 1000)]
    pub mutants: usize,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// The repository's fixtures.
    #[arg(long, default_value = "fixtures")]
    pub fixtures: PathBuf,
    /// Scratch directory (emptied first) [default: a directory under the system's].
    #[arg(long)]
    pub work: Option<PathBuf>,
    /// Input mutants per stage run.
    #[arg(long, default_value_t = 50)]
    pub batch: usize,
    /// Checkpoint mutants that also get a stage restart each.
    #[arg(long, default_value_t = 10)]
    pub stage_checkpoints: usize,
    /// The reader guard's limit per read, seconds.
    #[arg(long, default_value_t = 10.0, value_parser = positive_seconds)]
    pub read_timeout_s: f64,
    /// A stage run still going after this many seconds is a hang.
    #[arg(long, default_value_t = 600.0, value_parser = positive_seconds)]
    pub stage_timeout_s: f64,
    /// Write the report as JSON to this file.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Replace the figures between `<!-- fuzz:begin -->` and `<!-- fuzz:end -->` here.
    #[arg(long)]
    pub markdown_into: Option<PathBuf>,
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
}

fn positive_seconds(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(x) if x.is_finite() && x > 0.0 => Ok(x),
        _ => Err(format!("`{s}`: expected a number of seconds > 0")),
    }
}

fn nonnegative_seconds(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(x) if x.is_finite() && x >= 0.0 => Ok(x),
        _ => Err(format!("`{s}`: expected a number of seconds >= 0")),
    }
}

/// The progress bar of a batch run, when one is drawn: logs are printed above it.
static BAR: OnceLock<indicatif::ProgressBar> = OnceLock::new();

struct LogWriter;

impl Write for LogWriter {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        match BAR.get() {
            Some(pb) if !pb.is_hidden() => pb.suspend(|| std::io::stderr().write_all(buf))?,
            _ => std::io::stderr().write_all(buf)?,
        }
        Ok(buf.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        std::io::stderr().flush()
    }
}

/// Install the log subscriber (once, before anything logs).
pub fn init_logging(cli: &Cli) {
    use tracing_subscriber::EnvFilter;
    let quiet = matches!(&cli.command, Command::Run(a) if a.quiet);
    let level = if quiet {
        "warn"
    } else {
        cli.log_level.as_str()
    };
    let filter = EnvFilter::try_from_env("PERSIST_LOG")
        .or_else(|_| EnvFilter::try_new(level))
        .unwrap_or_else(|_| EnvFilter::new("info"));
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(|| LogWriter)
        .with_target(false);
    let _ = if cli.log_json {
        builder
            .json()
            .flatten_event(true)
            .with_current_span(false)
            .try_init()
    } else {
        builder
            .with_ansi(std::io::stderr().is_terminal())
            .try_init()
    };
}

#[derive(Args, Debug)]
pub struct DemoArgs {
    /// Where to write the simulation, outputs, checkpoints and plots (replaced).
    #[arg(long, default_value = "demo-out")]
    pub out: PathBuf,
    /// Image size in pixels (square).
    #[arg(long, default_value_t = 128)]
    pub size: usize,
    /// Exposures (1143 = the paper's two days).
    #[arg(long, default_value_t = 1143)]
    pub exposures: u64,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Model file (JSON); without it the demo fits the model on a laboratory sequence of
    /// the same simulated detector, calibrated to 95 % coverage (`persist::demo`, "The
    /// paper's workflow"). `--model default` takes the built-in default (the paper's
    /// constants).
    #[arg(long)]
    pub model: Option<PathBuf>,
    #[command(flatten)]
    pub sky: SkyOptions,
}

#[derive(Args, Debug)]
pub struct FitArgs {
    /// Directory of a laboratory sequence (products; the first dark keeps its ramp).
    #[arg(long)]
    pub input: PathBuf,
    /// The model file to write.
    #[arg(long)]
    pub out: PathBuf,
    /// Also fit this effect's parameters (repeatable). Names: see `persist diagnose`.
    /// `NAME:param=value,...` sets those parameters and holds them (a value known from
    /// elsewhere, e.g. the readout: `chord:strength=1,first_read_s=1.5`); the model file
    /// records them as `fixed`, and `diagnose`'s refits keep them.
    #[arg(long = "with")]
    pub with: Vec<String>,
    /// Also fit the six C_n (the decay shape; the tau_n stay) to the data, jointly with
    /// the `--with` effects, from the paper's 1/(t+1) fit (the A_k knots are kept).
    #[arg(long)]
    pub fit_cn: bool,
    /// Also fit one common factor of the A_k knots (the amplification 1.2 of the paper is
    /// a flagging margin; this is the level the data want), jointly with the `--with`
    /// effects. Not with --fit-cn.
    #[arg(long)]
    pub fit_amplification: bool,
    /// Also fit the exponent p of the decay law the C_n follow, (t + t0)^-p instead of
    /// the paper's 1/(t + t0), fitted on the first illumination, the first dark's level
    /// held (`persist::calib::exponent`). Not with --fit-cn.
    #[arg(long)]
    pub fit_decay_exponent: bool,
    /// Fit report (JSON); default: OUT with extension `.fit.json`.
    #[arg(long)]
    pub report: Option<PathBuf>,
    /// Starting point: `paper` (the paper's calibration, for flagging: the options'
    /// defaults below) or `readout` (for comparing with measurements, the reference of
    /// the hidden-effect matrix: `--amplification 1 --t-min-s 1 --decay-offset-s 0.2`,
    /// thirteen rates 10^(-0.4 k) 1/s, `--with refill` and the on-board slope measured on
    /// the first dark: `--with
    /// chord:strength=1,first_read_s=1.5`, plus `--with linefit_bias:strength=S` where
    /// the image is a least-squares line; `persist::calib::Preset`). Options given
    /// alongside override the preset's, a `--with` of an effect it has replaces that one.
    #[arg(long, default_value_t = Preset::Paper, value_parser = parse_flag::<Preset>)]
    pub preset: Preset,
    /// Amplification of A_0 into A_bin [default: the preset's; paper: 1.2].
    #[arg(long, allow_negative_numbers = true)]
    pub amplification: Option<f64>,
    /// Start of the span over which the C_n follow 1/(t+1): the shortest slew, s
    /// [default: the preset's; paper: 10].
    #[arg(long, allow_negative_numbers = true)]
    pub t_min_s: Option<f64>,
    /// The C_n follow 1/(t + T0) with this T0, s [default: the preset's; paper: 1].
    /// Eq. (logfit)'s fitted tau per bin (the report's bins[].logfit.tau_s) is the
    /// data's own offset (`persist::calib`, "Decay offset").
    #[arg(long, allow_negative_numbers = true)]
    pub decay_offset_s: Option<f64>,
    /// Decay rates 1/tau_n of the terms, 1/s, comma-separated [default: the preset's;
    /// paper: its six, 0.1,0.0158,0.00251,0.000398,6.31e-5,1e-5].
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub rates_per_s: Vec<f64>,
    /// Calibrate the flags to this coverage: the knots' margin set so that this share
    /// of the laboratory samples measured above 0.1 and above 0.01 e-/s is flagged in
    /// every time bin and band the data cover, after the `--with` effects
    /// (`persist::calib::coverage`) [default: the preset's; paper: 0.95, the paper's
    /// design, skipped with a warning when the data have too few samples above a
    /// threshold; readout: none].
    #[arg(long, conflicts_with = "no_coverage")]
    pub coverage: Option<f64>,
    /// Keep the knots at the amplification (no coverage calibration).
    #[arg(long)]
    pub no_coverage: bool,
    #[command(flatten)]
    pub cells: CellArgs,
}

/// The residual cells of `fit` (its effect fit and report), `compare` (its map and RMS)
/// and `diagnose` (its score test, refits, held-out check and reported RMS). Defaults:
/// the library's ([`persist::diag::eval::Cells`], [`persist::diag::eval::CellStatistic`]).
#[derive(Args, Debug, Clone, Copy)]
pub struct CellArgs {
    /// Residual cells: `illumination` (one set of fluence x time cells per
    /// illumination; see `persist::diag::eval` "Why per illumination") or `pooled`
    /// (fluence x time, all illuminations together), or `neighbours` (the
    /// per-illumination cells, split by whether a nearest neighbour is far brighter
    /// than the pixel; "Neighbour contrast"). On one illumination `illumination` and
    /// `pooled` are the same cells.
    #[arg(long, default_value_t = Cells::default(), value_parser = parse_flag::<Cells>)]
    pub cells: Cells,
    /// What a residual cell compares: `paired` (the 95th percentile of each sample's
    /// measured minus predicted current; see `persist::diag::eval` "Paired statistic"),
    /// `population` (the same, against a reference with each sample's own shot noise
    /// and the pixels' spread below the predicted 95th percentile, measured in the
    /// first dark; "Population statistic") or `levels` (the cell's measured 95th
    /// percentile against its predictions').
    #[arg(long, default_value_t = CellStatistic::default(), value_parser = parse_flag::<CellStatistic>)]
    pub cell_statistic: CellStatistic,
    /// How each exposure's dark level is measured, in `fit`'s calibration too:
    /// `median` (the median of the background pixels, those never lit above 3000 e-)
    /// or `line` (the intercept at zero fluence of a line through the background
    /// pixels' values against their fluence in the last illumination, which leaves
    /// out their own persistence; see `persist::diag::data` "Background").
    #[arg(long, default_value_t = Background::default(), value_parser = parse_flag::<Background>)]
    pub background: Background,
}

/// A flag's value through the library's `FromStr` (whose error names the flag and the
/// values it takes).
fn parse_flag<T: std::str::FromStr<Err = Error>>(s: &str) -> Result<T, String> {
    s.parse().map_err(|e: Error| e.to_string())
}

#[derive(Args, Debug)]
pub struct CompareArgs {
    #[arg(long)]
    pub input: PathBuf,
    /// Model file (repeatable: every figure side by side).
    #[arg(long = "model", required = true)]
    pub models: Vec<PathBuf>,
    /// Output directory for report.html and summary.json.
    #[arg(long)]
    pub report: PathBuf,
    /// Simulated data only: the same scenario and seed without the hidden effect; adds
    /// the flag quality over the pixels the effect touches.
    #[arg(long)]
    pub touched_baseline: Option<PathBuf>,
    /// A pixel is touched when its true persistence differs by more than this, e-/s.
    #[arg(long, default_value_t = persist::diag::compare::TOUCHED_MIN_E_PER_S)]
    pub touched_min_e_per_s: f64,
    #[command(flatten)]
    pub cells: CellArgs,
}

#[derive(Args, Debug)]
pub struct DiagnoseArgs {
    #[arg(long)]
    pub input: PathBuf,
    #[arg(long)]
    pub model: PathBuf,
    /// Write the ranking as JSON here.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Parametric bootstrap replicas for the false-alarm threshold (their largest
    /// scores' 95 % point; at least 19).
    #[arg(long, default_value_t = persist::diag::diagnose::DEFAULT_BOOTSTRAP)]
    pub bootstrap: usize,
    /// Seed of the pixel subsample and of the bootstrap.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Pixels in the random subsample.
    #[arg(long, default_value_t = persist::diag::diagnose::DEFAULT_PIXELS)]
    pub pixels: usize,
    /// Residuals of the score test: `auto` (`within` with two illumination events or
    /// more, else `pooled`), `within` (illumination contrasts) or `pooled`.
    #[arg(long, default_value_t = Statistic::Auto, value_parser = parse_flag::<Statistic>)]
    pub statistic: Statistic,
    // the score test's groups are the `--statistic`'s; `--cells` keys the refits, the
    // held-out check and the reported RMS
    #[command(flatten)]
    pub cells: CellArgs,
    /// What the refit of a candidate frees: `full` (its parameters and the model's own
    /// effects' jointly, compared with the model's effects refitted alone; also in the
    /// held-out check) or `candidate` (its parameters only).
    #[arg(long, default_value_t = Refit::default(), value_parser = parse_flag::<Refit>)]
    pub refit: Refit,
    /// When no effect is significant alone, refit the leading candidate together with
    /// each other library effect and gate the best pair as one candidate (two effects
    /// that interact, so that neither alone accounts for the residual;
    /// `persist::diag::diagnose`, "Joint check"). Adds up to seven refits.
    #[arg(long)]
    pub joint: bool,
    /// What chooses the candidates refitted: `contrast` (what the data can test and what
    /// a flexible base's residual depends on) or `score` (the score test alone, as the
    /// matrix of docs/validation/diagnose_matrix.md measured).
    #[arg(long, default_value_t = persist::diag::diagnose::Decide::default(), value_parser = parse_flag::<persist::diag::diagnose::Decide>)]
    pub decide: persist::diag::diagnose::Decide,
    /// What the effects are tested against: `auto` (a model calibrated for flagging,
    /// knots off the measured level as the paper's 1.2 margin puts them, is replaced by
    /// a description of the measurements fitted from the input: `persist fit --preset
    /// readout --fit-decay-exponent` with the model's own effects; a model at the
    /// measured level is used as it is), `model` (the model file as given) or
    /// `measured` (always the description; `persist::diag::reference`).
    #[arg(long, default_value_t = persist::diag::reference::Reference::default(), value_parser = parse_flag::<persist::diag::reference::Reference>)]
    pub reference: persist::diag::reference::Reference,
}

#[derive(Subcommand, Debug)]
pub enum ModelAction {
    /// Print the default model file (the paper's constants).
    Default,
    /// Check a model file and print its identity (SHA-256 of its canonical form).
    Id { file: PathBuf },
}

fn parse_checkpoint_key(s: &str) -> Result<(DetectorId, u64), String> {
    let (d, i) = s
        .split_once(':')
        .ok_or_else(|| format!("`{s}`: expected DETECTOR:INDEX, e.g. 3:120"))?;
    let d: i64 = d
        .parse()
        .map_err(|_| format!("`{d}`: not a detector number"))?;
    let det = DetectorId::new(d).ok_or_else(|| format!("detector {d}: must be 1..=6"))?;
    let i = i
        .parse()
        .map_err(|_| format!("`{i}`: not an exposure index"))?;
    Ok((det, i))
}

fn load_model(path: Option<&Path>) -> persist::Result<Model> {
    match path {
        // with the per-pixel maps the model file names (none: the model alone)
        Some(p) => persist::pixmap::file::attach(p, persist::model_file::load(p)?),
        None => Model::new(ModelParams::default()),
    }
}

pub fn run(cli: Cli) -> persist::Result<ExitCode> {
    match cli.command {
        Command::Run(args) => run_stage(&args),
        Command::Model { action } => match action {
            ModelAction::Default => {
                out!("{}", ModelParams::default().to_json_pretty());
                Ok(ExitCode::SUCCESS)
            }
            ModelAction::Id { file } => {
                let m = load_model(Some(&file))?;
                out!("{}  {}", m.identity(), m.params().name);
                Ok(ExitCode::SUCCESS)
            }
        },
        Command::Validate { files } => Ok(validate(&files)),
        Command::Simulate { scenario } => simulate(scenario),
        Command::Status(args) => status(&args),
        Command::Fractions { table, plot } => fractions(&table, plot.as_deref()),
        Command::Demo(args) => demo(&args),
        Command::Fit(a) => fit(&a),
        Command::Compare(a) => compare(&a),
        Command::Diagnose(a) => diagnose(&a),
        Command::Bench(args) => bench(&args),
        Command::Export(a) => export(&a),
        Command::Fuzz(a) => fuzz(&a),
        Command::GuardedRead {
            what,
            path,
            fits,
            memory_bytes,
            cpu_s,
            parent,
        } => {
            let limits = persist::guard::Limits {
                memory_bytes,
                cpu_s,
                parent,
            };
            let code = persist::guard::serve(&what, &path, &fits, &limits);
            Ok(ExitCode::from(u8::try_from(code).unwrap_or(1)))
        }
        Command::HelpMarkdown => {
            use clap::CommandFactory;
            out_nonl!("{}", crate::cli_reference::markdown(Cli::command()));
            Ok(ExitCode::SUCCESS)
        }
        Command::Verify(a) => verify(&a),
        Command::Slurm(a) => {
            let model = load_model(a.model.as_deref())?;
            lines_out(persist::slurm::slurm_command(&a, &model)?)
        }
        Command::Tile(a) => lines_out(persist::slurm::tile_command(&a)?),
        Command::Assemble(a) => lines_out(persist::slurm::assemble_command(&a)?),
        Command::Pixelmap(a) => {
            for line in persist::pixmap::command::run(&a)? {
                out!("{line}");
            }
            Ok(ExitCode::SUCCESS)
        }
    }
}

/// Print a command's lines; success.
fn lines_out(lines: Vec<String>) -> persist::Result<ExitCode> {
    for l in lines {
        out!("{l}");
    }
    Ok(ExitCode::SUCCESS)
}

/// `persist verify`: exit code 1 when a check disagrees or a file could not be read.
fn verify(a: &VerifyArgs) -> persist::Result<ExitCode> {
    let mut p = persist::verify::VerifyParams {
        seed: a.seed,
        ..Default::default()
    };
    if let Some(f) = a.event_fluence_e {
        p.track.event_fluence_e = f;
    }
    p.track.spike_nsigma = a.spike_nsigma;
    if let [inner, outer] = a.annulus_px[..] {
        if inner == 0 || outer < inner {
            return Err(Error::new(
                ErrorKind::Usage,
                format!("--annulus-px {inner},{outer}: need 0 < inner <= outer"),
            ));
        }
        p.track.annulus_inner_px = inner;
        p.track.annulus_outer_px = outer;
    }
    let r = match &a.flight_map {
        None => persist::verify::run(&a.input, &a.output, &p)?,
        Some(out) => persist::pixmap::flight::learn_and_write(
            &a.input,
            &a.output,
            &p,
            out,
            a.map_model.as_deref(),
            a.prior_map.as_deref(),
        )?,
    };
    persist::verify::write_report(&r, &a.report)?;
    let c = &r.checks;
    out!(
        "{} exposures, {} events, {} samples; {}",
        r.exposures,
        r.events,
        r.samples,
        c.verdict()
    );
    if let Some((inside, n)) = c.truth_inside {
        out!("truth inside the measured 95 % interval in {inside} of {n} bins");
    }
    if let Some(q) = &r.flag_quality {
        out!(
            "flags against the truth, pixel-exposures from exposure {} on:\n{}",
            q.from_exposure,
            q.table().trim_end()
        );
    }
    for e in &r.errors {
        eprintln!("unreadable: {}: {}", e.file.display(), e.reason);
    }
    out!("report: {}", a.report.join("report.html").display());
    let ok = c.agree() && r.errors.is_empty();
    Ok(if ok {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(1)
    })
}

/// `persist export --fits FILE... --out DIR`.
fn export(a: &ExportArgs) -> persist::Result<ExitCode> {
    std::fs::create_dir_all(&a.out).map_err(|e| Error::io(&a.out, e))?;
    let opts = persist::fits::export::ExportOptions {
        gains: a.fits_gain.iter().copied().collect(),
        placeholders: a.placeholders,
    };
    let mut failed = false;
    for f in &a.files {
        match persist::fits::export::export_file(f, &a.out, &opts) {
            Ok(p) => out!("{} -> {}", f.display(), p.display()),
            Err(e) => {
                failed = true;
                tracing::error!("{e}");
            }
        }
    }
    Ok(if failed {
        ExitCode::FAILURE
    } else {
        ExitCode::SUCCESS
    })
}

/// `persist simulate lab|sky`: products and truth written as they are simulated.
fn simulate(scenario: SimScenario) -> persist::Result<ExitCode> {
    use persist::sim::{effect::EffectSpec, lab, output::Writer, sky};
    let specs = |v: &[String]| -> persist::Result<Vec<EffectSpec>> {
        v.iter().map(|s| s.parse()).collect()
    };
    let (out, n) = match scenario {
        SimScenario::Lab(a) => {
            let paper = a.spots == lab::Spots::Paper;
            if !a.campaign && !matches!(a.spots, lab::Spots::Centred | lab::Spots::Paper) {
                return Err(persist::Error::invalid(
                    "--spots",
                    format!("`{}` needs --campaign", a.spots),
                ));
            }
            if a.dark_pixels && !paper {
                return Err(persist::Error::invalid(
                    "--dark-pixels",
                    "needs --spots paper",
                ));
            }
            let cfg = lab::LabConfig {
                paper_pattern: paper.then_some(lab::PaperPattern {
                    dark_pixels: a.dark_pixels,
                }),
                size: a.size,
                seed: a.seed,
                darks: a.darks,
                campaign: a.campaign.then(|| {
                    lab::CampaignOptions {
                        spots: a.spots,
                        dark_lengths: a.dark_lengths,
                        temperatures: a.temperatures,
                        repeats: a.repeats,
                    }
                    .illuminations()
                }),
                effects: specs(&a.effects)?,
                ..lab::LabConfig::default()
            };
            lab::validate(&cfg)?;
            let mut w = Writer::new(&a.out)?;
            let desc = lab::run(&cfg, |e| w.write(&e))?;
            (a.out, w.finish(desc)?)
        }
        SimScenario::Sky(a) => {
            let mut cfg = sky::SkyConfig {
                size: a.size,
                detectors: a.detectors,
                exposures: a.exposures,
                seed: a.seed,
                effects: specs(&a.effects)?,
                ..sky::SkyConfig::default()
            };
            a.sky.apply(&mut cfg);
            sky::validate(&cfg)?;
            let mut w = Writer::new(&a.out)?;
            let desc = sky::run(&cfg, |e| w.write(&e))?;
            let n = w.finish(desc)?;
            if a.format == "fits" {
                let opts = persist::fits::export::ExportOptions {
                    gains: a.fits_gain.iter().copied().collect(),
                    placeholders: true,
                };
                persist::fits::export::convert_dir(&a.out, &opts)?;
            }
            (a.out, n)
        }
        SimScenario::Family(a) => {
            let cfg = persist::trapgen::FamilyConfig {
                size: a.size,
                seed: a.seed,
                sequence: a.sequence,
                darks: a.darks,
                dark_pixels: a.dark_pixels,
                pinholes: a.pinholes.map(|p| p == OnOff::On),
                hidden: a.hidden,
            };
            persist::trapgen::validate(&cfg)?;
            let mut w = Writer::new(&a.out)?;
            let desc = persist::trapgen::run(&cfg, |e| w.write(&e))?;
            (a.out, w.finish(desc)?)
        }
    };
    out!(
        "persist simulate: {n} products in {}, truth in {}",
        out.display(),
        out.join("truth").display()
    );
    Ok(ExitCode::SUCCESS)
}

/// `persist validate FILE...`: every file is checked; exit 1 if any failed.
fn validate(files: &[PathBuf]) -> ExitCode {
    let mut failed = false;
    for path in files {
        match persist::validate::validate_path(path) {
            Ok(kind) => out!("ok {kind} {}", path.display()),
            Err(errors) => {
                failed = true;
                for e in errors {
                    // Every error names its file; make sure of it.
                    eprintln!("{}", e.path(path));
                }
            }
        }
    }
    if failed {
        ExitCode::from(1)
    } else {
        ExitCode::SUCCESS
    }
}

/// `persist status`.
fn status(args: &StatusArgs) -> persist::Result<ExitCode> {
    let quarantine = args
        .quarantine
        .clone()
        .or_else(|| args.input.as_ref().map(|i| i.join(".quarantine")));
    let mut st = stage::status::status(
        &args.output,
        &args.checkpoints,
        args.input.as_deref(),
        quarantine.as_deref(),
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

fn fractions(table: &Path, plot: Option<&Path>) -> persist::Result<ExitCode> {
    let rows = stage::table::read(table)?;
    out_nonl!("{}", stage::table::summary(&rows));
    if let Some(png) = plot {
        stage::table::plot(&rows, png)?;
        out!("plot {}", png.display());
    }
    Ok(ExitCode::SUCCESS)
}

fn run_stage(args: &RunArgs) -> persist::Result<ExitCode> {
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
    let guard = if args.no_reader_guard {
        None
    } else {
        let exe = std::env::current_exe().map_err(|e| Error::new(ErrorKind::Io, e.to_string()))?;
        Some(persist::guard::Guard {
            exe,
            timeout: Duration::from_secs_f64(args.reader_timeout_s),
            memory_bytes: args.reader_memory_mib << 20,
        })
    };
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
fn run_workers(
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
fn print_summary(report: &RunReport, header: bool) {
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

fn finish(report: &RunReport) -> ExitCode {
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

fn demo(args: &DemoArgs) -> persist::Result<ExitCode> {
    let mut sky = persist::sim::sky::SkyConfig::default();
    args.sky.apply(&mut sky);
    let cfg = persist::demo::DemoConfig {
        out: args.out.clone(),
        size: args.size,
        exposures: args.exposures,
        seed: args.seed,
        model: match args.model.as_deref() {
            None => None,
            Some(p) if p == Path::new("default") => Some(ModelParams::default()),
            Some(p) => Some(load_model(Some(p))?.params().clone()),
        },
        coverage: Default::default(),
        sky,
    };
    let r = persist::demo::run(&cfg, &|m| eprintln!("persist demo: {m}"))?;
    out!("model: {}", r.model_source);
    out!(
        "{:>8} {:>8} {:>12} {:>12} {:>12} {:>12}",
        "exposure",
        "t [h]",
        "% >0.1 e/s",
        "% >0.01 e/s",
        "true % >0.1",
        "true % >0.01"
    );
    let step = (r.rows.len() / 24).max(1);
    for row in r.rows.iter().step_by(step) {
        out!(
            "{:>8} {:>8.2} {:>12.2} {:>12.2} {:>12.2} {:>12.2}",
            row.exposure_index,
            row.t_hours,
            100.0 * row.frac_high,
            100.0 * row.frac_low,
            100.0 * row.true_frac_high,
            100.0 * row.true_frac_low
        );
    }
    let mean = |f: fn(&persist::demo::Row) -> f64| {
        r.rows.iter().map(f).sum::<f64>() / r.rows.len().max(1) as f64
    };
    out!(
        "after the first 6 h (median over exposures): {:.2}% of pixels above 0.1 e-/s, {:.1}% above 0.01 e-/s",
        100.0 * r.steady_frac_high,
        100.0 * r.steady_frac_low
    );
    out!(
        "true persistence after the first 6 h (median over exposures): {:.2}% above 0.1 e-/s, {:.1}% above 0.01 e-/s",
        100.0 * r.steady_true_frac_high,
        100.0 * r.steady_true_frac_low
    );
    out!(
        "median pixel after the first 6 h (median over exposures): true {:.4} e-/s, predicted {:.4} e-/s",
        r.steady_median_true_e_per_s, r.steady_median_pred_e_per_s
    );
    out!(
        "per exposure (mean): {:.3}% of pixels saturated, {:.3}% hit by a cosmic ray",
        100.0 * mean(|w| w.frac_saturated),
        100.0 * mean(|w| w.frac_transient)
    );
    let above = r.pixel_trace.iter().filter(|t| t.1 > 0.1).count();
    out!(
        "pixel {:?}: brightest exposure {} ({:.3e} e-); predicted above 0.1 e-/s in {} exposures",
        r.pixel,
        r.pixel_event_index,
        r.pixel_event_fluence_e,
        above
    );
    out!(
        "flags against the simulator's truth, pixel-exposures from exposure {} on, \
         non-functional pixels left out (over-flagged: per pixel-exposure; missed: of the \
         truly above, by band of true current in units of the threshold):",
        r.flag_quality.from_exposure
    );
    out!("{}", r.flag_quality.table().trim_end());
    out!(
        "persist verify: {} (its exit code would be {})",
        r.verify.verdict(),
        u8::from(!r.verify.agree())
    );
    for p in &r.plots {
        out!("plot: {}", p.display());
    }
    Ok(if r.errors == 0 {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(1)
    })
}

/// `persist fit`.
fn fit(a: &FitArgs) -> persist::Result<ExitCode> {
    let p = a.preset.config();
    let cfg = persist::calib::CalibConfig {
        amplification: a.amplification.unwrap_or(p.amplification),
        t_min_s: a.t_min_s.unwrap_or(p.t_min_s),
        decay_offset_s: a.decay_offset_s.unwrap_or(p.decay_offset_s),
        rates_per_s: if a.rates_per_s.is_empty() {
            p.rates_per_s
        } else {
            a.rates_per_s.clone()
        },
        cells: a.cells.cells,
        cell_statistic: a.cells.cell_statistic,
        background: a.cells.background,
        coverage: if a.no_coverage {
            None
        } else {
            a.coverage.or(p.coverage)
        },
        ..p
    };
    let report_path = a
        .report
        .clone()
        .unwrap_or_else(|| a.out.with_extension("fit.json"));
    // checked before the data are read
    let free = persist::calib::effects::Free {
        c_n: a.fit_cn,
        knot_scale: a.fit_amplification,
        decay_exponent: a.fit_decay_exponent,
    }
    .check()?;
    if let Some(c) = a.coverage {
        persist::calib::coverage::CoverageConfig {
            coverage: c,
            ..Default::default()
        }
        .check()?;
    }
    let r = persist::calib::run(
        &a.input,
        &cfg,
        (a.preset, &a.with),
        (free, a.coverage.is_some()),
        &a.out,
        &report_path,
    )?;
    out!("{r}");
    Ok(ExitCode::SUCCESS)
}

/// `persist compare`.
fn compare(a: &CompareArgs) -> persist::Result<ExitCode> {
    let opts = persist::diag::compare::Options {
        touched_baseline: a.touched_baseline.clone(),
        touched_min_e_per_s: a.touched_min_e_per_s,
        cells: a.cells.cells,
        cell_statistic: a.cells.cell_statistic,
        background: a.cells.background,
    };
    let s = persist::diag::compare_command::run_with(&a.input, &a.models, &a.report, &opts)?;
    out!("{s}");
    Ok(ExitCode::SUCCESS)
}

/// `persist diagnose`.
fn diagnose(a: &DiagnoseArgs) -> persist::Result<ExitCode> {
    let cfg = persist::diag::diagnose::Config {
        pixels: a.pixels,
        bootstrap: a.bootstrap,
        seed: a.seed,
        statistic: a.statistic,
        cells: a.cells.cells,
        cell_statistic: a.cells.cell_statistic,
        background: a.cells.background,
        refit: a.refit,
        joint: a.joint,
        decide: a.decide,
    };
    let s =
        persist::diag::reference::run(&a.input, &a.model, a.json.as_deref(), &cfg, a.reference)?;
    out!("{s}");
    Ok(ExitCode::SUCCESS)
}

fn fuzz(args: &FuzzArgs) -> persist::Result<ExitCode> {
    let exe = std::env::current_exe().map_err(|e| Error::new(ErrorKind::Io, e.to_string()))?;
    let own_work = args.work.is_none();
    let work = args.work.clone().unwrap_or_else(|| {
        std::env::temp_dir().join(format!("persist-fuzz-{}", std::process::id()))
    });
    let cfg = persist::fuzz::FuzzConfig {
        mutants: args.mutants,
        seed: args.seed,
        fixtures: args.fixtures.clone(),
        work: work.clone(),
        exe,
        batch: args.batch,
        stage_checkpoints: args.stage_checkpoints,
        read_timeout: Duration::from_secs_f64(args.read_timeout_s),
        stage_timeout: Duration::from_secs_f64(args.stage_timeout_s),
    };
    let r = persist::fuzz::run(&cfg, &|done, total| {
        tracing::info!(done, total, "stage runs");
    })?;
    let command = format!(
        "persist fuzz --mutants {} --seed {}",
        args.mutants, args.seed
    );
    let md = persist::fuzz::markdown(&r, &command);
    out_nonl!("{md}");
    if let Some(j) = &args.json {
        let text = serde_json::to_string_pretty(&r)
            .map_err(|e| Error::new(ErrorKind::Io, e.to_string()))?;
        std::fs::write(j, text + "\n").map_err(|e| Error::io(j, e))?;
    }
    if let Some(doc) = &args.markdown_into {
        persist::fuzz::insert_markdown(doc, &md)?;
    }
    let bad =
        r.stage_deaths + r.hangs + r.good_lost + r.readers.iter().map(|c| c.panics).sum::<usize>();
    if own_work && bad == 0 {
        let _ = std::fs::remove_dir_all(&work);
    }
    Ok(if bad == 0 {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(1)
    })
}

fn bench(args: &BenchArgs) -> persist::Result<ExitCode> {
    use persist::bench::{self, BenchConfig, Case, CaseSpec};
    let default_scratch =
        || std::env::temp_dir().join(format!("persist-bench-{}", std::process::id()));
    if let Some(count) = args.prepare {
        let scratch = args.scratch.clone().unwrap_or_else(default_scratch);
        let dir = bench::prepare_inputs(&scratch, args.size, count)?;
        out!("{}", dir.display());
        return Ok(ExitCode::SUCCESS);
    }
    if let Some(case) = &args.case {
        let case = Case::parse(case)
            .ok_or_else(|| Error::new(ErrorKind::Usage, format!("unknown bench case `{case}`")))?;
        let spec = CaseSpec {
            case,
            size: args.size,
            threads: args.threads,
            reps: args.reps.unwrap_or(5),
            checkpoint_every: args.checkpoint_every,
            scratch: args.scratch.clone().unwrap_or_else(default_scratch),
        };
        let r = bench::run_case(&spec)?;
        out!(
            "{}",
            serde_json::to_string(&r).map_err(|e| Error::new(ErrorKind::Io, e.to_string()))?
        );
        return Ok(ExitCode::SUCCESS);
    }
    let exe = std::env::current_exe().map_err(|e| Error::new(ErrorKind::Io, e.to_string()))?;
    let own_scratch = args.scratch.is_none();
    let scratch = args.scratch.clone().unwrap_or_else(default_scratch);
    let mut cfg = if args.quick {
        BenchConfig::quick(exe, scratch.clone())
    } else {
        BenchConfig::full(exe, scratch.clone())
    };
    if let Some(s) = &args.sizes {
        cfg.sizes = s.clone();
    }
    if let Some(t) = &args.thread_counts {
        cfg.threads = t.clone();
    }
    if let Some(r) = args.reps {
        cfg.reps = r;
    }
    if let Some(e) = args.exposures {
        cfg.exposures = e;
    }
    if let Some(r) = args.rounds {
        cfg.rounds = r;
    }
    cfg.verify_only = args.verify_only;
    if let Some(v) = cfg.verify.as_mut() {
        let pair =
            |name: &str, a: &Option<Vec<usize>>| -> persist::Result<Option<(usize, usize)>> {
                match a.as_deref() {
                    None => Ok(None),
                    Some(&[a, b]) => Ok(Some((a, b))),
                    Some(other) => Err(Error::new(
                        ErrorKind::Usage,
                        format!("--{name}: need two numbers, got {other:?}"),
                    )),
                }
            };
        if let Some((a, b)) = pair("verify-sizes", &args.verify_sizes)? {
            (v.size, v.day_size) = (a, b);
        }
        if let Some((a, b)) = pair("verify-exposures", &args.verify_exposures)? {
            (v.exposures, v.day_exposures) = (a, b);
        }
    }
    let result = bench::run(&cfg, &|r| {
        eprintln!(
            "persist bench: {:>6} {:>5}^2 threads {} ckpt/{}: median {:.4} s/exposure, peak {:.0} MiB",
            r.case.name(),
            r.size,
            r.threads,
            r.checkpoint_every,
            r.median_s,
            r.peak_rss_bytes as f64 / 1048576.0
        )
    });
    if own_scratch {
        let _ = std::fs::remove_dir_all(&scratch);
    }
    let report = result?;
    out!("{}", report.markdown);
    out!("{} ({})", report.date_utc, report.machine);
    if let Some(path) = &args.json {
        let text = serde_json::to_string_pretty(&report)
            .map_err(|e| Error::new(ErrorKind::Io, e.to_string()))?;
        std::fs::write(path, text).map_err(|e| Error::io(path, e))?;
    }
    Ok(ExitCode::SUCCESS)
}
