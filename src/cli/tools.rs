//! `persist demo`, `persist bench` and `persist fuzz`.

use super::load_model;
use super::parse::positive_seconds;
use super::simulate::SkyOptions;
use clap::Args;
use persist::model::ModelParams;
use persist::{Error, ErrorKind};
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Duration;

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
    /// the same simulated detector, calibrated to 95 % coverage, and measures its
    /// transient rule in flight on the sky's first 200 exposures (`persist::demo`, "The
    /// paper's workflow"). `--model default` takes the built-in default (the paper's
    /// constants).
    #[arg(long)]
    pub model: Option<PathBuf>,
    #[command(flatten)]
    pub sky: SkyOptions,
}

pub(super) fn demo(args: &DemoArgs) -> persist::Result<ExitCode> {
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

pub(super) fn fuzz(args: &FuzzArgs) -> persist::Result<ExitCode> {
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

pub(super) fn bench(args: &BenchArgs) -> persist::Result<ExitCode> {
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
