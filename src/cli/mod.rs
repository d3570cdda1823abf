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
//!
//! One file a group of commands, each with its options and what it prints: [`stage`]
//! (`run`, `status`, `fractions`), [`simulate`], [`analysis`] (`fit`, `compare`,
//! `diagnose`), [`products`] (`verify`, `export`, `validate`), [`tools`] (`demo`,
//! `bench`, `fuzz`); [`logging`] and [`parse`] serve them all. This file parses and
//! dispatches.

use clap::{Parser, Subcommand};
use persist::model::{Model, ModelParams};
use std::path::{Path, PathBuf};
use std::process::ExitCode;

/// `println!` to stdout that does not panic when stdout is gone (`persist ... | head`):
/// what the command printed is a report, and the work it reports on (files written,
/// checkpoints) must not depend on whether anyone still reads it. Any other write error
/// (a full disk under `persist model default > m.json`) is reported and exits 1
/// ([`stdout_failed`]).
macro_rules! out {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        if let Err(e) = writeln!(std::io::stdout().lock(), $($arg)*) {
            $crate::cli::stdout_failed(e);
        }
    }};
}

/// `print!` without the newline, as [`out!`].
macro_rules! out_nonl {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        if let Err(e) = write!(std::io::stdout().lock(), $($arg)*) {
            $crate::cli::stdout_failed(e);
        }
    }};
}

mod analysis;
mod logging;
mod parse;
mod products;
mod simulate;
mod stage;
mod tools;

use analysis::{CompareArgs, DiagnoseArgs, FitArgs};
pub use logging::init_logging;
use products::{ExportArgs, VerifyArgs};
use simulate::SimScenario;
use stage::{RunArgs, StatusArgs};
use tools::{BenchArgs, DemoArgs, FuzzArgs};

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

#[derive(Subcommand, Debug)]
pub enum ModelAction {
    /// Print the default model file (the paper's constants).
    Default,
    /// Check a model file and print its identity (SHA-256 of its canonical form).
    Id { file: PathBuf },
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
        Command::Run(args) => stage::run_stage(&args),
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
        Command::Validate { files } => Ok(products::validate(&files)),
        Command::Simulate { scenario } => simulate::simulate(scenario),
        Command::Status(args) => stage::status(&args),
        Command::Fractions { table, plot } => stage::fractions(&table, plot.as_deref()),
        Command::Demo(args) => tools::demo(&args),
        Command::Fit(a) => analysis::fit(&a),
        Command::Compare(a) => analysis::compare(&a),
        Command::Diagnose(a) => analysis::diagnose(&a),
        Command::Bench(args) => tools::bench(&args),
        Command::Export(a) => products::export(&a),
        Command::Fuzz(a) => tools::fuzz(&a),
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
        Command::Verify(a) => products::verify(&a),
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
