//! `persist fit`, `persist compare` and `persist diagnose`: the options and the calls.

use super::parse::parse_flag;
use clap::Args;
use persist::calib::Preset;
use persist::diag::data::Background;
use persist::diag::diagnose::{Refit, Statistic};
use persist::diag::eval::{CellStatistic, Cells};
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Args, Debug)]
pub struct FitArgs {
    /// Directory of a laboratory sequence (products; the first dark keeps its ramp).
    #[arg(long, required_unless_present = "from_verify")]
    pub input: Option<PathBuf>,
    /// Instead of a laboratory fit: set the transient rule of `--model` (the model the
    /// verified run was flagged with) from a `persist verify` report.json, and write the
    /// model to OUT (docs/verify.md, "The transient rule"). Refused when the report
    /// gives no rule (too few cosmic-ray hits).
    #[arg(long, conflicts_with = "input")]
    pub from_verify: Option<PathBuf>,
    /// With --from-verify: the model file the verified run was flagged with [default:
    /// the built-in default].
    #[arg(long, requires = "from_verify")]
    pub model: Option<PathBuf>,
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
    /// defaults below, with `--with refill` and the model's early release keeping the
    /// threshold, docs/model.md "Early release"; `--with refill:beta=0 --release-keep
    /// zero` is the paper's sum and release) or `readout` (for comparing with measurements, the reference of
    /// the hidden-effect matrix: `--amplification 1 --t-min-s 1 --decay-offset-s 0.2`,
    /// thirteen rates 10^(-0.4 k) 1/s, `--with refill` and the on-board slope measured on
    /// the first dark: `--with
    /// chord:strength=1,first_read_s=1.5`, plus `--with linefit_bias:strength=S` where
    /// the image is a least-squares line; `persist::calib::Preset`). Options given
    /// alongside override the preset's, a `--with` of an effect it has replaces that one.
    #[arg(long, default_value_t = Preset::Paper, value_parser = parse_flag::<Preset>)]
    pub preset: Preset,
    /// Amplification of A_0 into A_bin [default: the preset's; paper: 1.2]. Stated, it
    /// is the knots' margin: no coverage calibration unless `--coverage` is stated too.
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
    /// threshold; readout: none; none when `--amplification` or `--fit-amplification` is
    /// stated].
    #[arg(long, conflicts_with = "no_coverage")]
    pub coverage: Option<f64>,
    /// Keep the knots at the amplification (no coverage calibration).
    #[arg(long)]
    pub no_coverage: bool,
    /// What early release leaves of a released pixel in the model written
    /// (`early_release.keep`, docs/model.md "Early release"): `zero` (the paper's) or
    /// `threshold` [default: the preset's; paper: threshold, readout: zero].
    #[arg(long, value_parser = super::parse::release_keep)]
    pub release_keep: Option<persist::model::ReleaseKeep>,
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

/// `persist fit`.
pub(super) fn fit(a: &FitArgs) -> persist::Result<ExitCode> {
    if let Some(report) = &a.from_verify {
        let model = match &a.model {
            Some(m) => persist::model_file::load(m)?,
            None => persist::model::ModelParams::default(),
        };
        out!(
            "{}",
            persist::verify::transient::run(report, &model, &a.out)?
        );
        return Ok(ExitCode::SUCCESS);
    }
    let input = a.input.as_deref().ok_or_else(|| {
        persist::Error::new(
            persist::ErrorKind::Usage,
            "--input: required without --from-verify",
        )
    })?;
    let stated = persist::calib::Stated {
        amplification: a.amplification,
        t_min_s: a.t_min_s,
        decay_offset_s: a.decay_offset_s,
        rates_per_s: a.rates_per_s.clone(),
        coverage: a.coverage,
        no_coverage: a.no_coverage,
        fit_amplification: a.fit_amplification,
    };
    let cfg = persist::calib::CalibConfig {
        cells: a.cells.cells,
        cell_statistic: a.cells.cell_statistic,
        background: a.cells.background,
        ..a.preset.config_stated(&stated)
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
        input,
        &cfg,
        (
            a.preset,
            &a.with,
            a.release_keep.unwrap_or(a.preset.release_keep()),
        ),
        (free, a.coverage.is_some()),
        &a.out,
        &report_path,
    )?;
    out!("{r}");
    Ok(ExitCode::SUCCESS)
}

/// `persist compare`.
pub(super) fn compare(a: &CompareArgs) -> persist::Result<ExitCode> {
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
pub(super) fn diagnose(a: &DiagnoseArgs) -> persist::Result<ExitCode> {
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
