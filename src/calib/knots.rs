//! Knots consistent with the model's effects.
//!
//! The paper's calibration turns each fluence bin's first-dark ramp into an amplitude:
//! `A_bin = amplification * A_0`, `A_0` from the fit `q(t) = A_0 ln(t + tau) + q_0`
//! ([`super::logfit`]). That inversion assumes the paper's model, in which a pixel of
//! amplitude `A` releases `A sum_n C_n exp(-t/tau_n)` whatever its fluence. An effect
//! that changes the per-term response of the illuminated exposure (its response hook,
//! e.g. `short_tau_boost`: the fast terms multiplied by a factor in a fluence window)
//! changes the first-dark ramp that one unit of `A_k` predicts; the knots must then
//! change too, or they keep the effect's signature (the ramp's extra charge read as a
//! larger `A_0`) and the fitted effect double-counts it.
//!
//! # Rule
//! For a knot at fluence `F`, predict the first-dark ramp of one unit of amplitude with
//! the model's effects and without them,
//! `q_E(t) = sum_n g_n(F) C_n tau_n (exp(-t_0/tau_n) - exp(-t/tau_n))`
//! (`g_n` the per-term response factors of the effects, `t_0` the first dark's reset
//! and `t` its read times, both after the end of the illuminated exposure, as in
//! [`super::calibrate`]), fit both with Eq. (logfit) and scale the knot by
//! `s(F) = A_0[q_without] / A_0[q_E]`. Since `A_0` is linear in the ramp's scale, a
//! measured ramp `A q_E` then calibrates to the knot the paper's rule gives for a ramp
//! `A q_without`: the knot keeps the paper's meaning and the effect carries the rest.
//! With no effect (or an effect at its null) every `g_n` is 1 and `s` is exactly 1, so
//! the paper's calibration and every model without such effects are unchanged.
//!
//! Only effects whose response depends on a pixel's own fluence and the exposure
//! ([`crate::model::effect::Effect::response_is_per_pixel`]: `short_tau_boost`,
//! `soak`) enter this rule; rate hooks (`temperature`: the calibration illumination's
//! temperature) and accumulation rules (which act only on charge carried from earlier
//! illuminations, or saturate it) are left to the knots as the paper calibrates them.
//!
//! # Spatial effects
//! An effect that scales a pixel's response by its place or its neighbours (`ipc`,
//! `populations`, `blooming`, `smooth_neighbour`: fluence hooks and response hooks that
//! are not per pixel) changes what one knot predicts from pixel to pixel. The knots'
//! 95th percentile over a bin's pixels already holds that spread; with the effect in the
//! model it would be counted twice, and where the effect lowers a pixel's response the
//! pixel falls below the flagging margin. [`spatial_factor`] gives each pixel of the
//! calibration illumination the ratio `w` of the first dark's charge the model predicts
//! with these hooks to the charge without them, and the calibration
//! ([`super::calibrate_with`]) measures the bins' median, 95th percentile and ramp on
//! the pixels' values divided by `w`: the knot is the level at `w = 1`, and the margin
//! is measured with the effect in place. Without such an effect (or at its null) every
//! `w` is 1 and nothing changes.

use super::logfit;
use crate::error::{Error, Result};
use crate::measure::data::Sequence;
use crate::model::effect::ResponseCtx;
use crate::model::effects;
use crate::model::params::ModelParams;
use crate::model::Response;
use ndarray::{Array2, Array3};

/// The calibration's first dark: its read times after the end of the illuminated
/// exposure (the model's reference for the decay) and the illuminated exposure's timing.
#[derive(Debug, Clone, PartialEq)]
pub struct CalibRamp {
    /// Index of the illuminated exposure in the sequence.
    pub illumination: usize,
    /// Index of the first dark integration (the one with the ramp).
    pub dark: usize,
    /// Reset of the first dark, s after the end of the illuminated exposure.
    pub t_reset_s: f64,
    /// The first dark's read times, s after the same reference.
    pub t_s: Vec<f64>,
    pub t_illuminated_s: f64,
    pub t_exposure_s: f64,
}

impl CalibRamp {
    /// The first illumination of `seq` and the dark after it (which must keep its ramp).
    pub fn of(seq: &Sequence) -> Result<CalibRamp> {
        let &i0 = seq.illuminations.first().ok_or_else(|| {
            Error::invalid("t_illuminated_s", "no illuminated exposure in the input")
        })?;
        let d = i0 + 1;
        let dark = seq.exposures.get(d).ok_or_else(|| {
            Error::invalid("exposure_index", "no dark exposure after the illumination")
        })?;
        let times = dark.ramp_times_s.as_ref().filter(|_| dark.ramp.is_some());
        let times = times.ok_or_else(|| {
            Error::invalid(
                "ramp",
                format!(
                    "exposure {}: the first dark integration has no /ramp (laboratory data needed)",
                    dark.meta.exposure_index
                ),
            )
        })?;
        let t_reset_s = seq.t_mid_after_s(i0, d) - 0.5 * dark.meta.t_exposure_s;
        let ill = &seq.exposures[i0].meta;
        Ok(CalibRamp {
            illumination: i0,
            dark: d,
            t_reset_s,
            t_s: times.iter().map(|x| x + t_reset_s).collect(),
            t_illuminated_s: ill.t_illuminated_s(),
            t_exposure_s: ill.t_exposure_s,
        })
    }
}

/// The calibration ramp of `seq` and `model`'s knot scale on it (what [`rescale`] takes);
/// None when `seq` has no ramp to calibrate from (sky data).
pub fn scale_of(model: &ModelParams, seq: &Sequence) -> Result<Option<(Vec<f64>, CalibRamp)>> {
    match CalibRamp::of(seq) {
        Ok(ramp) => Ok(Some((scale(model, &ramp)?, ramp))),
        Err(_) => Ok(None),
    }
}

/// Run the response hooks of `built` on `planes` (`[y, x, term]`) for the calibration
/// illumination of `ramp`, every pixel with a slope, the rates held as the model's.
fn apply_responses(
    built: &[Box<dyn crate::model::effect::Effect>],
    fluence: &Array2<f64>,
    ramp: &CalibRamp,
    rates: &[f64],
    response: &Response,
    planes: &mut Array3<f64>,
) {
    let no_slope = Array2::from_elem(fluence.dim(), false);
    let ctx = ResponseCtx {
        needed: None,
        fluence_e: fluence,
        no_slope: &no_slope,
        t_illuminated_s: ramp.t_illuminated_s,
        t_exposure_s: ramp.t_exposure_s,
        rate_per_s: rates,
        rate_held_per_s: rates,
        response,
    };
    for e in built {
        e.response(&ctx, planes);
    }
}

/// `s(F)` of the module docs for each knot of `model`; 1 where the effects leave the
/// response unchanged. Errors name the effect entry that cannot be built.
pub fn scale(model: &ModelParams, ramp: &CalibRamp) -> Result<Vec<f64>> {
    let k = model.amplitude_knots.len();
    let mut built = Vec::new();
    for (i, spec) in model.effects.iter().enumerate() {
        let e = effects::build(spec).map_err(|r| Error::invalid(format!("effects[{i}]"), r))?;
        if e.response_is_per_pixel() {
            built.push(e);
        }
    }
    if built.is_empty() || k == 0 {
        return Ok(vec![1.0; k]);
    }
    let rates: Vec<f64> = model.terms.iter().map(|t| t.rate_per_s).collect();
    let n = rates.len();
    let fluence = Array2::from_shape_fn((1, k), |(_, j)| model.amplitude_knots[j].fluence_e);
    let mut g = Array3::<f64>::ones((1, k, n));
    let response = Response::new(&model.amplitude_knots);
    apply_responses(&built, &fluence, ramp, &rates, &response, &mut g);
    let unit = term_ramps(&model.terms, ramp);
    let ramp_of = |w: &dyn Fn(usize) -> f64| -> Vec<f64> {
        (0..ramp.t_s.len())
            .map(|s| (0..n).map(|m| w(m) * unit[m][s]).sum())
            .collect()
    };
    let a0 = |q: &[f64]| {
        logfit::fit(&ramp.t_s, q)
            .map(|f| f.a0_e)
            .filter(|a| a.is_finite() && *a > 0.0)
    };
    let plain = a0(&ramp_of(&|_| 1.0));
    Ok((0..k)
        .map(|j| {
            if (0..n).all(|m| g[[0, j, m]] == 1.0) {
                return 1.0;
            }
            let with = a0(&ramp_of(&|m| g[[0, j, m]]));
            match (plain, with) {
                (Some(p), Some(w)) => p / w,
                // a ramp the log fit cannot describe: the paper's knot is kept
                _ => 1.0,
            }
        })
        .collect())
}

/// The first dark's ramp (charge at each read of `ramp`) of one unit of amplitude,
/// term by term: `C_n tau_n (exp(-t_0/tau_n) - exp(-t/tau_n))`.
pub fn term_ramps(terms: &[crate::model::params::Term], ramp: &CalibRamp) -> Vec<Vec<f64>> {
    terms
        .iter()
        .map(|t| {
            let r = t.rate_per_s;
            let tau = if r > 0.0 { 1.0 / r } else { 0.0 };
            let e0 = (-ramp.t_reset_s * r).exp();
            ramp.t_s
                .iter()
                .map(|ts| t.c_per_s * tau * (e0 - (-ts * r).exp()))
                .collect()
        })
        .collect()
}

/// Eq. (logfit)'s `A_0` of the first dark's ramp that one unit of amplitude gives
/// with `terms` (what a knot of 1 e- reads as); None where the log fit fails.
pub fn unit_a0(terms: &[crate::model::params::Term], ramp: &CalibRamp) -> Option<f64> {
    let per_term = term_ramps(terms, ramp);
    let q: Vec<f64> = (0..ramp.t_s.len())
        .map(|s| per_term.iter().map(|u| u[s]).sum())
        .collect();
    logfit::fit(&ramp.t_s, &q)
        .map(|f| f.a0_e)
        .filter(|a| a.is_finite() && *a > 0.0)
}

/// The least share of its measured fluence that a pixel's fluence hooks may leave it for
/// the calibration to measure its own response there ([`spatial_factor`]).
pub const OWN_SHARE_MIN: f64 = 0.5;

/// Per pixel of the calibration illumination, `w` of the module docs ("Spatial
/// effects"): the first dark's charge per unit amplitude with the model's fluence hooks
/// and its response hooks that are neither per pixel nor filling, over the charge
/// without them. None when no effect has such a hook or every `w` is 1; pixels without
/// a finite positive ratio get 1. NaN marks a pixel whose fluence hooks leave it less
/// than [`OWN_SHARE_MIN`] of its measured fluence (next to a pinhole under inter-pixel
/// capacitance, most of what it measured is its neighbour's): its first dark shows its
/// neighbours' persistence through the model's coupling, not its own response, and the
/// ratio then carries every error of the model's amplitude at the neighbour's fluence
/// (above the largest knot, where no bin measures it). The calibration leaves such
/// pixels out of its bins as neighbour-dominated.
pub fn spatial_factor(
    model: &ModelParams,
    seq: &Sequence,
    ramp: &CalibRamp,
) -> Result<Option<Array2<f64>>> {
    let mut built = Vec::new();
    for (i, spec) in model.effects.iter().enumerate() {
        let e = effects::build(spec).map_err(|r| Error::invalid(format!("effects[{i}]"), r))?;
        if !(e.response_is_per_pixel() || e.response_is_fill()) {
            built.push(e);
        }
    }
    if built.is_empty() || model.amplitude_knots.is_empty() {
        return Ok(None);
    }
    let fluence = crate::measure::data::fluence(&seq.exposures[ramp.illumination]);
    let fluence = fluence.mapv(|v| if v.is_finite() { v.max(0.0) } else { 0.0 });
    let mut adjusted = fluence.clone();
    for e in built.iter().filter(|e| e.has_fluence()) {
        e.fluence(&mut adjusted);
    }
    let response = Response::new(&model.amplitude_knots);
    let rates: Vec<f64> = model.terms.iter().map(|t| t.rate_per_s).collect();
    let n = rates.len();
    let (ny, nx) = fluence.dim();
    let mut ak = Array3::<f64>::zeros((ny, nx, n));
    for ((y, x), &g) in adjusted.indexed_iter() {
        let a = response.amplitude_e(if g.is_finite() { g.max(0.0) } else { 0.0 });
        for m in 0..n {
            ak[[y, x, m]] = a;
        }
    }
    apply_responses(&built, &adjusted, ramp, &rates, &response, &mut ak);
    // each term's charge over the first dark per unit amplitude
    let t_end = ramp.t_s.last().copied().unwrap_or(ramp.t_reset_s);
    let q: Vec<f64> = model
        .terms
        .iter()
        .map(|t| {
            let r = t.rate_per_s;
            if r > 0.0 {
                t.c_per_s / r * ((-ramp.t_reset_s * r).exp() - (-t_end * r).exp())
            } else {
                0.0
            }
        })
        .collect();
    let w = Array2::from_shape_fn((ny, nx), |(y, x)| {
        if adjusted[[y, x]] < OWN_SHARE_MIN * fluence[[y, x]] {
            return f64::NAN;
        }
        // summed in the same order, so that an unchanged pixel gives exactly 1
        let a = response.amplitude_e(fluence[[y, x]]);
        let plain: f64 = (0..n).map(|m| a * q[m]).sum();
        let with: f64 = (0..n).map(|m| ak[[y, x, m]] * q[m]).sum();
        let r = with / plain;
        if r.is_finite() && r > 0.0 {
            r
        } else {
            1.0
        }
    });
    Ok((!w.iter().all(|&v| v == 1.0)).then_some(w))
}

/// Rescale the knots of `to` (a copy of a model `from` with other effects or
/// parameters; `s_from = scale(from, ramp)`, computed once by the caller) so that they
/// carry `to`'s effects instead of `from`'s: `A_k *= s_to(F_k) / s_from(F_k)`. Knots
/// are untouched (bit for bit) where both scales are equal. `to` must have the same
/// knots as `from`.
pub fn rescale(s_from: &[f64], to: &mut ModelParams, ramp: &CalibRamp) -> Result<()> {
    let s_to = scale(to, ramp)?;
    for ((kn, a), b) in to.amplitude_knots.iter_mut().zip(s_from).zip(&s_to) {
        if a != b {
            kn.amplitude_e *= b / a;
        }
    }
    Ok(())
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::model::params::{EffectSpec, Knot};

    /// The first dark of `persist simulate lab`'s laboratory timing.
    pub(crate) fn ramp() -> CalibRamp {
        // the laboratory timing: 613 s integration lit 481 s, a 10 s slew, then a 180 s
        // dark read every 1.5 s (times after the illuminated exposure's end, as
        // `Sequence::t_mid_after_s` counts them)
        CalibRamp {
            illumination: 0,
            dark: 1,
            t_reset_s: 10.0,
            t_s: (1..=120).map(|i| 10.0 + 1.5 * i as f64).collect(),
            t_illuminated_s: 481.0,
            t_exposure_s: 613.0,
        }
    }

    fn model(effects: Vec<EffectSpec>) -> ModelParams {
        ModelParams {
            amplitude_knots: [1e5, 3e5, 1e6]
                .iter()
                .map(|&f| Knot {
                    fluence_e: f,
                    amplitude_e: 1000.0,
                })
                .collect(),
            effects,
            ..ModelParams::default()
        }
    }

    fn boost(factor: f64) -> EffectSpec {
        let mut p = serde_json::Map::new();
        p.insert("factor".into(), serde_json::json!(factor));
        EffectSpec {
            params: p,
            ..EffectSpec::named("short_tau_boost")
        }
    }

    #[test]
    fn no_effect_or_null_effect_leaves_knots_bit_identical() {
        let r = ramp();
        assert_eq!(scale(&model(vec![]), &r).unwrap(), vec![1.0; 3]);
        assert_eq!(scale(&model(vec![boost(1.0)]), &r).unwrap(), vec![1.0; 3]);
        let from = model(vec![]);
        let mut to = model(vec![boost(1.0)]);
        rescale(&scale(&from, &r).unwrap(), &mut to, &r).unwrap();
        assert_eq!(to.amplitude_knots, from.amplitude_knots);
    }

    #[test]
    fn boost_lowers_only_the_knots_in_its_window() {
        // short_tau_boost's window is 200,000-500,000 e-: only the 300,000 e- knot moves,
        // and down (a boosted ramp per unit amplitude is steeper, so less amplitude
        // explains the same measured ramp)
        let r = ramp();
        let s = scale(&model(vec![boost(3.0)]), &r).unwrap();
        assert_eq!(s[0], 1.0);
        assert_eq!(s[2], 1.0);
        assert!(s[1] < 1.0 && s[1] > 0.0, "{s:?}");
        // and the rescaled knot predicts the unit ramp's A_0 again
        let from = model(vec![]);
        let mut to = model(vec![boost(3.0)]);
        rescale(&scale(&from, &r).unwrap(), &mut to, &r).unwrap();
        assert!((to.amplitude_knots[1].amplitude_e - 1000.0 * s[1]).abs() < 1e-9);
        let mut back = to.clone();
        back.effects.clear();
        rescale(&scale(&to, &r).unwrap(), &mut back, &r).unwrap();
        assert!((back.amplitude_knots[1].amplitude_e - 1000.0).abs() < 1e-9);
    }
}
