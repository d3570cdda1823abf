//! The command line: parse, call the library, map the outcome to an exit code.
//! Exit codes: 0 all went well; 1 some input or output failed (the rest was processed,
//! every failure reported); 2 the command could not run at all.

use clap::{Args, Parser, Subcommand};
use persist::checkpoint::Retention;
use persist::model::{Model, ModelParams};
use persist::stage::{self, ExposureReport, RunConfig, RunReport};
use persist::units::DetectorId;
use persist::{Error, ErrorKind};
use std::path::{Path, PathBuf};
use std::process::ExitCode;

#[derive(Parser, Debug)]
#[command(
    name = "persist",
    version,
    about = "Predict and flag image persistence in HAWAII-2RG arrays (SPHEREx)"
)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
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
    /// The main job on a built-in default: run the stage on the committed fixtures.
    Demo {
        /// Where to write outputs and checkpoints (replaced if it exists).
        #[arg(long, default_value = "demo-out")]
        out: PathBuf,
    },
    /// Benchmark the model step, the memory bound, the whole stage and the HDF5 I/O
    /// bound, each case in a child process; prints a markdown table and writes JSON.
    Bench(BenchArgs),
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
    /// Write a checkpoint every N exposures (and always at the end).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u64).range(1..))]
    pub checkpoint_every: u64,
    /// Keep this many newest checkpoints per detector (plus one per hour of data).
    #[arg(long, default_value_t = 20)]
    pub keep_latest: usize,
    /// Do not keep one checkpoint per hour of data beyond the newest ones.
    #[arg(long)]
    pub no_hourly_checkpoints: bool,
    /// Print nothing per exposure.
    #[arg(long, short)]
    pub quiet: bool,
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
    let params = match path {
        Some(p) => persist::model_file::load(p)?,
        None => ModelParams::default(),
    };
    Model::new(params)
}

pub fn run(cli: Cli) -> persist::Result<ExitCode> {
    match cli.command {
        Command::Run(args) => run_stage(&args),
        Command::Model { action } => match action {
            ModelAction::Default => {
                println!("{}", ModelParams::default().to_json_pretty());
                Ok(ExitCode::SUCCESS)
            }
            ModelAction::Id { file } => {
                let m = load_model(Some(&file))?;
                println!("{}  {}", m.identity(), m.params().name);
                Ok(ExitCode::SUCCESS)
            }
        },
        Command::Validate { files } => Ok(validate(&files)),
        Command::Demo { out } => demo(&out),
        Command::Bench(args) => bench(&args),
    }
}

/// `persist validate FILE...`: every file is checked; exit 1 if any failed.
fn validate(files: &[PathBuf]) -> ExitCode {
    let mut failed = false;
    for path in files {
        match persist::product::validate_path(path) {
            Ok(kind) => println!("ok {kind} {}", path.display()),
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

fn run_stage(args: &RunArgs) -> persist::Result<ExitCode> {
    let cfg = RunConfig {
        input: args.input.clone(),
        output: args.output.clone(),
        checkpoints: args.checkpoints.clone(),
        model: load_model(args.model.as_deref())?,
        from_checkpoint: args.from_checkpoint,
        allow_model_change: args.allow_model_change,
        checkpoint_every: args.checkpoint_every,
        retention: Retention {
            keep_latest: args.keep_latest,
            keep_one_per_hour: !args.no_hourly_checkpoints,
        },
        processed_utc: stage::processing_time(),
    };
    let report = stage::run(&cfg, &|_| {});
    if !args.quiet {
        print_summary(&report);
    }
    Ok(finish(&report))
}

/// Per-exposure table, sorted by (detector, exposure), then the errors.
fn print_summary(report: &RunReport) {
    let mut rows: Vec<&ExposureReport> = report.exposures.iter().collect();
    rows.sort_by_key(|r| (r.detector, r.exposure_index));
    println!(
        "{:>3} {:>8} {:>10} {:>9} {:>7} {:>9} {:>7} {:>8}  notes",
        "det", "exposure", "t_meas_s", ">0.1e/s", "%", ">0.01e/s", "%", "released"
    );
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
        println!(
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
            report.exposures.len(),
            report.errors.len()
        );
        ExitCode::from(1)
    }
}

fn demo(out: &Path) -> persist::Result<ExitCode> {
    let fixtures = Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures");
    if out.exists() {
        std::fs::remove_dir_all(out).map_err(|e| Error::io(out, e))?;
    }
    let args = RunArgs {
        input: fixtures,
        output: out.join("output"),
        checkpoints: out.join("checkpoints"),
        model: None,
        from_checkpoint: None,
        allow_model_change: false,
        checkpoint_every: 1,
        keep_latest: 20,
        no_hourly_checkpoints: false,
        quiet: false,
    };
    if !args.input.is_dir() {
        return Err(Error::new(ErrorKind::Usage, "fixtures directory not found").path(&args.input));
    }
    println!(
        "persist demo: default model on {} -> {}",
        args.input.display(),
        out.display()
    );
    run_stage(&args)
}

fn bench(args: &BenchArgs) -> persist::Result<ExitCode> {
    use persist::bench::{self, BenchConfig, Case, CaseSpec};
    let default_scratch =
        || std::env::temp_dir().join(format!("persist-bench-{}", std::process::id()));
    if let Some(count) = args.prepare {
        let scratch = args.scratch.clone().unwrap_or_else(default_scratch);
        let dir = bench::prepare_inputs(&scratch, args.size, count)?;
        println!("{}", dir.display());
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
        println!(
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
    println!("{}", report.markdown);
    println!("{} ({})", report.date_utc, report.machine);
    if let Some(path) = &args.json {
        let text = serde_json::to_string_pretty(&report)
            .map_err(|e| Error::new(ErrorKind::Io, e.to_string()))?;
        std::fs::write(path, text).map_err(|e| Error::io(path, e))?;
    }
    Ok(ExitCode::SUCCESS)
}
