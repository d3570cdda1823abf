//! The data-driven term `diagnose` offers when the base's residual depends on a
//! covariate and no library effect acting on it predicts held-out data.
//!
//! The term is the covariate's smooth function ([`crate::model::effects::smooth`]):
//! three knots over the range of the covariate the data hold, their values fitted
//! jointly with the model's own effects on the same samples and cells as the library
//! candidates, judged by the same held-out check. It is offered (its `fit` command in the
//! verdict and in `data_term`) when [`super::offer`] chooses it among the refitted
//! candidates: the best held-out gain against the pixel reference. (Against the
//! measurements' description, with its gates of a held-out gain of at least
//! [`super::refit::HELD_OUT_MIN_GAIN`] and a `delta_BIC` below
//! [`super::refit::DBIC_MAX`], measured with examples/family_matrix at 64 x 64: with any
//! positive gain accepted, a term was offered on a campaign with nothing hidden, gain
//! 0.065, and on the weak soak form, 0.056; the capacity and capture forms gave 0.37 to
//! 0.51.) It is never declared a missing *effect*: it names no physics, only where the
//! data want more or less than the model gives, along the covariate that was found.
//! Knot ranges from the data: illumination durations and focal-plane temperatures
//! from the sampled events, the fluences (from [`super::shape::MIN_FLUENCE_E`]) from
//! the sampled pixels (a single value gives no term: the class is then
//! untestable); the held charge and the neighbours' excess keep the term's defaults
//! (held charge 1 % to all of the pixel's saturated charge; neighbours' excess
//! 1 to 1000 times the own fluence). The
//! fit starts from the best of a few common knot values
//! ([`crate::calib::effects::SMOOTH_START_VALUES`]).

use super::command::{fit_command, measure_command};
use super::config::Config;
use super::data::Sequence;
use super::eval::Samples;
use super::refit::{
    delta_bic, fit_candidate, held_out, held_with_arg, own_effects, Footing, HeldOut,
};
use crate::error::Result;
use crate::model::effect::EffectDef;
use crate::model::effects::smooth;
use crate::model::params::ModelParams;
use serde::Serialize;
use std::path::Path;

/// The offered term and what its fit gave.
#[derive(Debug, Clone, Serialize)]
pub struct DataTerm {
    /// The contrast class whose covariate it follows.
    pub class: String,
    pub effect: String,
    /// Its `--with` argument as fitted here: the knot range pinned.
    pub with: String,
    pub delta_bic: f64,
    pub rms_before: f64,
    pub rms_after: f64,
    pub held_out: Option<HeldOut>,
    /// Whether the verdict offers it: set by [`super::offer`]'s choice (module docs).
    pub offered: bool,
    /// The term at the values fitted here, every value held (`fit --with` form).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub measured_with: Option<String>,
    /// The `persist fit` command that adds it to the model.
    pub command: String,
    /// As [`super::diagnose::Candidate::measure_command`].
    #[serde(skip_serializing_if = "Option::is_none")]
    pub measure_command: Option<String>,
}

/// `v` to four decimals, as a `--with` value.
fn short(v: f64) -> String {
    format!("{}", (v * 1e4).round() / 1e4)
}

/// The `--with` argument of the term following `class`'s covariate, its knots over
/// the range the samples hold; None when no term follows it or the range is one value.
pub fn with_arg(class: &str, seq: &Sequence, samples: &Samples) -> Option<String> {
    let def = smooth::for_covariate(class)?;
    // the covariate's values at the samples' rows (finite only)
    let values: Vec<f64> = match def.covariate {
        "illumination_time" => samples
            .event
            .iter()
            .map(|&a| seq.exposures[a].meta.t_illuminated_s().log10())
            .collect(),
        "temperature" => samples.temperature_k.clone(),
        "fluence_x_time" => samples
            .fluence_e
            .iter()
            .filter(|&&f| f >= super::shape::MIN_FLUENCE_E)
            .map(|f| f.log10())
            .collect(),
        _ => return Some(def.name.to_string()),
    };
    let values: Vec<f64> = values.into_iter().filter(|x| x.is_finite()).collect();
    let lo = values.iter().copied().fold(f64::INFINITY, f64::min);
    let hi = values.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    if lo >= hi {
        return None;
    }
    let (lo_name, hi_name) = smooth::axis_of(def.name)?.range_names();
    let mut arg = format!(
        "{}:{lo_name}={},{hi_name}={}",
        def.name,
        short(lo),
        short(hi)
    );
    // a midpoint knot with no measured value between the ends is not fitted: held at 0
    let inner = |x: f64| x > lo + 1e-3 * (hi - lo) && x < hi - 1e-3 * (hi - lo);
    let mid_fitted = def.params.iter().any(|p| p.name == "at_mid" && p.fitted);
    if mid_fitted && !values.iter().any(|&x| inner(x)) {
        arg.push_str(",at_mid=0");
    }
    Some(arg)
}

/// The model `own_refit` with the term `with` at its best start
/// ([`crate::calib::effects::smooth_start`]; `fit_candidate` rescales the knots for it).
fn start(
    own_refit: &ModelParams,
    with: &str,
    seq: &Sequence,
    samples: &Samples,
) -> Result<ModelParams> {
    let (name, pins) = crate::calib::effects::parse_with(with)?;
    if crate::model::effects::lookup(&name).is_none() {
        return Ok(own_refit.clone());
    }
    let mut m = own_refit.clone();
    let mut spec = crate::model::params::EffectSpec::named(name);
    for (k, x) in &pins {
        spec.params.insert(k.clone(), serde_json::json!(x));
        spec.fixed.push(k.clone());
    }
    m.push_effect(spec);
    let i = m.effects.len() - 1;
    m.effects[i] = crate::calib::effects::smooth_start(&m, i, seq, samples)?;
    Ok(m)
}

/// The term following `class`'s covariate when the model `params` already holds it.
pub fn held(class: &str, params: &ModelParams) -> Option<&'static EffectDef> {
    smooth::for_covariate(class).filter(|d| params.effects.iter().any(|e| e.name == d.name))
}

/// Fit and hold out the term following `class` against the footing's model (its own
/// effects refitted as the footing's `refit` says, `own_refit` those fitted on all
/// samples); None when no term follows that class's covariate, or the model already
/// holds it (its own effects are refitted with every candidate).
pub fn offer(
    class: &str,
    footing: &Footing,
    own_refit: &ModelParams,
    cfg: &Config,
    (input, model_path): (&Path, &Path),
) -> Result<Option<DataTerm>> {
    let (params, seq, samples) = (footing.params, footing.seq, footing.samples);
    if held(class, params).is_some() {
        return Ok(None);
    }
    let Some(with) = with_arg(class, seq, samples) else {
        return Ok(None);
    };
    let name = with.split(':').next().unwrap_or(&with).to_string();
    let own = own_effects(params, cfg.refit);
    let begin = start(own_refit, &with, seq, samples)?;
    let (fitted, f) = fit_candidate(
        own_refit,
        &own,
        Some(&begin),
        &[with.as_str()],
        seq,
        samples,
    )?;
    // against the model without the term (the fit's own "before" is its start), on the
    // samples it was fitted on
    let fitted_on = super::refit::fitting_samples(&[with.as_str()], samples);
    let (rss0, m) = crate::measure::spread::rss_cells(own_refit, seq, &fitted_on)?;
    let rss1 = f.rss_before_after().1;
    let k = f.params.iter().filter(|p| p.effect == name).count();
    let dbic = delta_bic(rss0, rss1, k, f.cells);
    let ho = held_out(footing, Some(&fitted), &[with.as_str()])?;
    Ok(Some(DataTerm {
        class: class.to_string(),
        effect: name.clone(),
        command: fit_command(input, model_path, params, &[with.as_str()], cfg),
        measure_command: measure_command(input, model_path, params, &[with.as_str()], cfg),
        with,
        delta_bic: dbic,
        rms_before: (rss0 / m.max(1) as f64).sqrt(),
        rms_after: f.residual_rms_normalised_after,
        held_out: ho,
        offered: false,
        measured_with: held_with_arg(&fitted, &name),
    }))
}
