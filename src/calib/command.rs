//! `persist fit` as a command: calibrate ([`super::algorithm`]), fit the `--with`
//! effects ([`super::effects`]), calibrate the flags to a coverage ([`super::coverage`]),
//! then write the model file and the report. Files are read and written here only.

use super::algorithm::{calibrate, calibrate_with, CalibConfig, CalibReport, Preset};
use super::{coverage, effects, knots, readout};
use crate::error::{Error, Result};
use crate::measure::data::Sequence;
use crate::model::params::ModelParams;
use crate::textfile::write_text;
use serde::Serialize;

/// Everything `persist fit` writes beside the model file.
#[derive(Debug, Clone, Serialize)]
pub struct FitReport {
    pub input: String,
    pub calibration: CalibReport,
    /// The on-board slope measured on the first dark (`--preset readout`, [`readout`]).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub readout: Option<readout::Readout>,
    pub effects: Option<effects::EffectFit>,
    /// The flags calibrated to a coverage (`--coverage`, [`coverage`]).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub coverage: Option<coverage::CoverageReport>,
    /// RMS of the normalised cell residuals of the written model (diag::eval docs).
    pub residual_rms_normalised: f64,
    pub cells: usize,
    /// What the cells compare.
    pub cell_statistic: crate::measure::eval::CellStatistic,
    /// How each exposure's background was measured.
    pub background: crate::measure::data::Background,
    /// The background and noise of the exposures with no background pixel, measured
    /// from the darks ([`crate::measure::data`], "Every pixel lit").
    #[serde(skip_serializing_if = "crate::measure::data::LitMeasured::is_empty")]
    pub lit: crate::measure::data::LitMeasured,
    pub model_identity: String,
}

/// Appended to the description of a model whose `C_n` `persist fit --fit-cn` fitted
/// to its campaign; [`cn_fitted_to_campaign`] reads it back.
pub const FIT_CN_NOTE: &str = "; C_n then fitted to this campaign (--fit-cn)";

/// Whether `params`' `C_n` were fitted to a campaign (`--fit-cn`: its calibration
/// record, or its description for a model without one): such a model has already taken the decay-shape part of any effect in
/// that campaign, which `diagnose` then cannot see (docs/validation/diagnose_matrix.md).
pub fn cn_fitted_to_campaign(params: &ModelParams) -> bool {
    params
        .calibration
        .as_ref()
        .map_or_else(|| params.description.ends_with(FIT_CN_NOTE), |c| c.fit_cn)
}

/// In the description of a model whose knots' level `persist fit --fit-amplification`
/// fitted to its campaign (followed by the factor); [`level_fitted_to_campaign`] reads
/// it back.
pub const FIT_AMPLIFICATION_NOTE: &str = "; knots then scaled by ";

/// Whether `params`' knot level was fitted to a campaign (`--fit-amplification`: its
/// calibration record, or its description for a model without one): such a
/// model has taken in the level part of any effect in that campaign (a hidden
/// `short_tau_boost` was declared at 1 of 3 seeds against such a reference, 3 of 3
/// against the level fixed at 0.85; docs/validation/diagnose_matrix.md).
pub fn level_fitted_to_campaign(params: &ModelParams) -> bool {
    params.calibration.as_ref().map_or_else(
        || params.description.contains(FIT_AMPLIFICATION_NOTE),
        |c| c.fit_amplification,
    )
}

/// What `persist fit` computes before it writes anything: the calibration of `seq`
/// with `cfg`, then the `with` effects (and what `free` frees) fitted on it. Returns
/// the model, the calibration report and the effects' fit (`None` when nothing was
/// fitted beyond the calibration).
pub fn fit_params(
    seq: &Sequence,
    cfg: &CalibConfig,
    with: &[String],
    free: effects::Free,
) -> Result<(ModelParams, CalibReport, Option<effects::EffectFit>)> {
    let (mut params, mut cal) = calibrate(seq, cfg)?;
    let samples = cfg.samples(seq);
    let mut ef = None;
    if !with.is_empty() || free != effects::Free::default() {
        let (p, f) = effects::fit_with(&params, with, free, seq, &samples)?;
        params = p;
        // spatial effects: the knots measured with them in place (knots module docs,
        // "Spatial effects")
        let ramp = knots::CalibRamp::of(seq)?;
        if let Some(w) = knots::spatial_factor(&params, seq, &ramp)? {
            let (plain, c) = calibrate_with(seq, cfg, Some(&w))?;
            params.amplitude_knots = plain.amplitude_knots;
            knots::rescale(&vec![1.0; params.amplitude_knots.len()], &mut params, &ramp)?;
            cal = c;
        }
        let exponent = f
            .params
            .iter()
            .find(|q| q.effect == "terms" && q.name == "exponent")
            .map(|q| q.value);
        if let Some(c) = params.calibration.as_mut() {
            c.fit_cn = free.c_n;
            c.fit_amplification = free.knot_scale;
            c.decay_exponent = exponent;
        }
        if let Some(p) = exponent {
            params.description += &format!(
                "; C_n then refitted to (t + {} s)^-{p:.4}, the first dark's level held \
                 (--fit-decay-exponent)",
                cfg.decay_offset_s
            );
        }
        if free.c_n {
            params.description += FIT_CN_NOTE;
        }
        if let Some(k) = f.params.iter().find(|q| q.effect == "knots") {
            params.description += &format!(
                "{FIT_AMPLIFICATION_NOTE}{:.4} (--fit-amplification: amplification {:.4})",
                k.value,
                cfg.amplification * k.value
            );
        }
        ef = Some(f);
    }
    Ok((params, cal, ef))
}

/// The model `persist fit` makes of a laboratory sequence, and how it was made.
#[derive(Debug, Clone)]
pub struct FittedModel {
    pub params: ModelParams,
    pub calibration: CalibReport,
    /// The effects' fit (`None` when nothing was fitted beyond the calibration).
    pub effects: Option<effects::EffectFit>,
    /// The flags' coverage calibration, when it was made.
    pub coverage: Option<coverage::CoverageReport>,
    /// Why the flags were not calibrated to the coverage (the preset's default coverage
    /// on data that cannot calibrate it).
    pub not_covered: Option<String>,
}

/// `persist fit`'s model, in its order: the calibration and the `with` effects
/// ([`fit_params`]), the flags' margin last, after every effect (coverage module docs;
/// a coverage `stated` by the user that the data cannot calibrate is an error), then
/// what early release keeps (`keep`). The flag counts of
/// docs/validation/flag_quality.md and `persist demo` are of models made this way.
pub fn fit_model(
    seq: &Sequence,
    cfg: &CalibConfig,
    with: &[String],
    free: effects::Free,
    keep: crate::model::params::ReleaseKeep,
    coverage_stated: bool,
) -> Result<FittedModel> {
    let (params, calibration, effects) = fit_params(seq, cfg, with, free)?;
    let (mut params, coverage, not_covered) = to_coverage(params, seq, cfg, coverage_stated)?;
    params.early_release.keep = keep;
    Ok(FittedModel {
        params,
        calibration,
        effects,
        coverage,
        not_covered,
    })
}

/// The flags' coverage as `persist fit` and `persist demo` print it: the calibration
/// made, or why none was (`not_covered`; "not asked" without a reason) and the
/// amplification the knots keep.
pub fn describe_coverage(
    coverage: Option<&coverage::CoverageReport>,
    not_covered: Option<&str>,
    cfg: &CalibConfig,
) -> String {
    match coverage {
        Some(c) => c.describe(),
        None => format!(
            "  flags not calibrated to a coverage ({}): the knots keep amplification {}\n",
            not_covered.unwrap_or("not asked"),
            cfg.amplification
        ),
    }
}

/// `persist fit`: calibrate, fit the preset's and the `--with` effects (and what `free`
/// frees: the `C_n` or the knots' level, [`effects`] module docs), calibrate the flags to
/// the coverage, set what early release keeps (`keep`), write the model and the report.
pub fn run(
    input: &std::path::Path,
    cfg: &CalibConfig,
    (preset, with, keep): (Preset, &[String], crate::model::params::ReleaseKeep),
    (free, coverage_stated): (effects::Free, bool),
    out: &std::path::Path,
    report_path: &std::path::Path,
) -> Result<String> {
    let seq = Sequence::load_with(input, cfg.background)?;
    let (with, readout) = preset.with_for(&seq, with);
    let FittedModel {
        params,
        calibration: cal,
        effects: ef,
        coverage: covered,
        not_covered,
    } = fit_model(&seq, cfg, &with, free, keep, coverage_stated).map_err(|e| e.path(input))?;
    if ef
        .as_ref()
        .is_some_and(|f| margin_taken_in(cfg, free, f, preset.effects()))
    {
        tracing::warn!(
            amplification = cfg.amplification,
            "effect parameters fitted against knots at {} times the measured level \
             (the paper's flagging margin): they take that margin and the terms' shape \
             in as a residual (on the simulator's temperature campaign, 64 x 64, \
             `temperature` fitted 0.137 eV where the truth has 0.25); to measure them fit with \
             --preset readout, and to flag with the margin hold them here \
             (--with NAME:param=value; README, \"Which model to compare\")",
            cfg.amplification
        );
    }
    let covered_text = describe_coverage(covered.as_ref(), not_covered.as_deref(), cfg);
    let samples = cfg.samples(&seq);
    let pr = crate::measure::eval::predict(&params, &seq, &samples, false)?;
    let cells = crate::measure::spread::model_cell_z(&params, &samples, &pr.current);
    let rep = FitReport {
        input: input.display().to_string(),
        calibration: cal,
        readout,
        effects: ef,
        coverage: covered,
        residual_rms_normalised: crate::measure::eval::rms(&cells),
        cells: cells.len(),
        cell_statistic: cfg.cell_statistic,
        background: cfg.background,
        lit: seq.lit.clone(),
        model_identity: params.identity(),
    };
    write_text(out, &(params.to_json_pretty() + "\n"))?;
    let text = serde_json::to_string_pretty(&rep)
        .map_err(|e| Error::new(crate::ErrorKind::Io, e.to_string()))?;
    write_text(report_path, &(text + "\n"))?;
    let mut s = format!(
        "persist fit: {} knots, C_n max relative error {:.3} over [{:.0}, {:.0}] s, \
         normalised residual RMS {:.2} over {} {} cells{}\n",
        rep.calibration.knots.len(),
        rep.calibration.c_n.max_relative_error,
        rep.calibration.c_n.t_min_s,
        rep.calibration.c_n.t_max_s,
        rep.residual_rms_normalised,
        rep.cells,
        cfg.cells.describe(),
        cfg.cell_statistic.note()
    );
    if let Some(f) = &rep.effects {
        for p in &f.params {
            s += &format!(
                "  {}.{} = {:.6e} +- {:.2e}\n",
                p.effect, p.name, p.value, p.sigma
            );
        }
        for m in &f.measured {
            s += &format!("  {m}\n");
        }
        if let Some(c) = &f.c_n {
            s += "  C_n fitted / start:";
            for p in &c.shape {
                s += &format!(" {:.0} s {:.3},", p.t_s, p.ratio_to_start);
            }
            s.pop();
            s += "\n";
        }
        s += &format!(
            "  residual RMS {:.2} -> {:.2} ({} evaluations)\n",
            f.residual_rms_normalised_before, f.residual_rms_normalised_after, f.evaluations
        );
    }
    if let Some(r) = &rep.readout {
        s += &format!(
            "  readout measured on the first dark: least-squares line share {:.3} against the \
             chord over {} pixels, first read {} s after the reset\n",
            r.line_fraction, r.pixels, r.first_read_s
        );
    }
    if !rep.lit.is_empty() {
        s += &format!("  {}\n", rep.lit.describe());
    }
    s += &covered_text;
    s += &format!("model {} , report {}", out.display(), report_path.display());
    Ok(s)
}

/// The flags of `params` calibrated to `cfg.coverage` ([`coverage::apply`]), recorded in
/// the model's calibration, with the report; `params` as they are without a coverage.
/// When the laboratory data cannot calibrate it (too few samples measured above a
/// threshold), an error if the coverage was `stated` (`--coverage`), else (the preset's
/// default) a warning, the knots kept at the amplification and the reason returned.
fn to_coverage(
    params: ModelParams,
    seq: &Sequence,
    cfg: &CalibConfig,
    stated: bool,
) -> Result<(
    ModelParams,
    Option<coverage::CoverageReport>,
    Option<String>,
)> {
    let Some(share) = cfg.coverage else {
        return Ok((params, None, None));
    };
    let c = coverage::CoverageConfig {
        coverage: share,
        ..Default::default()
    };
    match coverage::apply(&params, seq, &c) {
        Ok((mut p, r)) => {
            if let Some(cal) = p.calibration.as_mut() {
                cal.coverage = Some(share);
            }
            Ok((p, Some(r), None))
        }
        Err(e) if !stated && e.context.field.as_deref() == Some("coverage") => {
            tracing::warn!(
                "flags not calibrated to {:.0} % coverage: {e}; the knots keep amplification {}",
                100.0 * share,
                cfg.amplification
            );
            Ok((params, None, Some(e.to_string())))
        }
        Err(e) => Err(e),
    }
}

/// True when a fit `--with` an effect on top of this calibration would fit it against
/// knots held at `amplification` times the measured level with nothing else free to
/// carry the level (neither `--fit-cn` nor `--fit-amplification`): the effect's
/// parameters would take the margin in (`margin_taken_in`; `persist diagnose` then
/// also names the `--preset readout` fit that measures them).
pub fn knots_held_off_level(amplification: f64, fit_cn: bool, fit_amplification: bool) -> bool {
    amplification != 1.0 && !fit_cn && !fit_amplification
}

/// True when `persist fit` fitted effect parameters against knots held away from the
/// measured level with nothing else free to carry the level: the paper's amplification
/// is a margin for flagging, and compared with measurements it is a residual the
/// effects take in (module docs of [`effects`]). With `--fit-amplification` the knots'
/// factor, and with `--fit-cn` the `C_n`'s scale, carry it instead.
/// The preset's own effects (`preset_effects`, [`Preset::effects`]) are fitted with its
/// margin by design and not counted: the paper preset's `refill` measures `beta` 1.00
/// +- 0.17 on the demo's laboratory sequence (docs/validation/flag_quality.md), the
/// bound of its range, where the simulator's traps do not fill twice.
fn margin_taken_in(
    cfg: &CalibConfig,
    free: effects::Free,
    f: &effects::EffectFit,
    preset_effects: &[&str],
) -> bool {
    let own = |effect: &str| {
        preset_effects
            .iter()
            .any(|e| e.split(':').next() == Some(effect))
    };
    knots_held_off_level(cfg.amplification, free.c_n, free.knot_scale)
        && f.params
            .iter()
            .any(|p| p.effect != "knots" && p.effect != "terms" && !own(&p.effect))
}
