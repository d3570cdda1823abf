//! The words of `persist diagnose`: its verdict and its printed ranking, built from
//! the decisions ([`super::finding`]) once the reference is resolved
//! ([`super::reference`]).
//!
//! # Invariants
//! - Nothing here decides: every sentence reads fields of a [`Diagnosis`] (or of the
//!   model diagnosed) and no number is computed but for display.
//! - The verdict names the first significant candidate of the ranking, else a
//!   significant pair of the joint check, else the covariate the residual depends on
//!   (with the data-driven term offered or refused), else a decay shape that depends
//!   on the fluence ([`super::shape`], with its term offered or refused), else where the
//!   largest residuals are.

use super::command::margin_note;
use super::config::{Decide, Refit};
use super::contrast;
use super::finding::{Candidate, Diagnosis, Joint};
use super::refit::PERMUTATIONS;
use super::separate::{Separation, Told};
use crate::model::params::ModelParams;

/// The verdict of `d`, a diagnosis of the model `params`. `held`: the commands that
/// add an effect to the user's model carry its values measured against the
/// measurements' description, held (`persist diagnose --reference measured`, module
/// docs of [`super::reference`]); each is printed with the command that measures them.
pub fn verdict(d: &Diagnosis, params: &ModelParams, held: bool) -> String {
    let winner = super::separate::leading(&d.dependences, d.separation.as_ref());
    match d.ranking.iter().find(|c| c.significant) {
        None if d.joint.first().is_some_and(|j| j.significant) => {
            joint_sentence(&d.joint[0], params)
        }
        Some(c) => {
            let class = contrast::class_of(&c.effect, &c.covariate);
            candidate_sentence(c, params, held, d.pixel_reference.per_event_rms)
                + &separation_sentence(d.separation.as_ref(), class)
        }
        None if winner.is_some() && d.decide == Decide::Contrast => {
            let w = winner.expect("checked");
            confounded_prefix(d.separation.as_ref(), &w.class)
                + &dependence_sentence(w, &outpredicted(d), &uncalibrated(d))
                + &separation_sentence(d.separation.as_ref(), &w.class)
                + &match (&d.offer, &d.shape_term) {
                    (_, Some(t)) => {
                        data_term_sentence(d.data_term.as_ref(), &w.class, params)
                            + ". Besides, "
                            + &shape_sentence(d, Some(t), params, held)
                    }
                    (Some(o), None) => offer_sentence(o, d, params, held),
                    (None, None) => data_term_sentence(d.data_term.as_ref(), &w.class, params),
                }
        }
        None if d.decide == Decide::Contrast
            && d.decay_shape.as_ref().is_some_and(|s| s.depends) =>
        {
            shape_sentence(d, d.data_term.as_ref(), params, held)
        }
        None => format!(
            "no library effect is significant; the residual RMS is {:.2}, largest at: {}{}",
            d.residual_rms_normalised,
            largest_sentence(d),
            field_sentence(d.spatial.as_ref())
        ),
    }
}

/// The verdict on a decay shape that depends on the fluence ([`super::shape`]), with the
/// data-driven term along it (`term`) offered or refused ([`super::offer::shape_term`]).
fn shape_sentence(
    d: &Diagnosis,
    term: Option<&super::data_term::DataTerm>,
    params: &ModelParams,
    held: bool,
) -> String {
    let Some(s) = d.decay_shape.as_ref() else {
        return String::new();
    };
    let bins = s
        .bins
        .iter()
        .map(|b| format!("10^{:.1} e-: {:+.3}", b.log10_fluence_e, b.tilt))
        .collect::<Vec<_>>()
        .join("; ");
    let faintest = s.bins.first().map_or(f64::NAN, |b| b.log10_fluence_e);
    let head = format!(
        "the decay's shape depends on the fluence (fluence_x_time): after the first \
         illumination (exposure {}), the log-log slope of the decay of pixels of 10^{:.1} \
         e- stands {:.2} per decade of time above that of pixels of 10^{:.1} e- ({:.0} \
         standard errors): brighter pixels decay more slowly, which a model with one \
         decay law for every fluence cannot follow (filling the traps by itself tends \
         the other way: the traps that empty fastest fill least at low flux). Each \
         fluence's slope against that of 10^{faintest:.1} e-: {bins}",
        s.illumination_exposure, s.to_log10_fluence_e, s.rise, s.from_log10_fluence_e, s.rise_z
    );
    let Some(t) = term else {
        return match super::data_term::held("fluence_x_time", params) {
            Some(def) => format!(
                "{head}. The model already holds the data-driven term along it ({}), whose \
                 own tilt is divided out before the shape is measured: the tilt above is \
                 what it leaves",
                def.name
            ),
            None => head + ". No data-driven term follows it",
        };
    };
    let (before, after) = t
        .held_out
        .as_ref()
        .map_or((f64::NAN, f64::NAN), |h| (h.rms_before, h.rms_after));
    let pixel = t.held_out.as_ref().and_then(|h| h.pixel_reference.as_ref());
    match &d.offer {
        None if super::offer::shape_term(Some(t)).is_some() => format!(
            "{head}. The data-driven term along it ({}) predicts each held-out half \
             better than the measurements' description (RMS {before:.2} -> {after:.2}; \
             dBIC {:.1}) but is not offered: the pixel reference, which takes in every \
             function of fluence and time and so would not move with a change of the \
             decay's shape alone, does worse with it held out (RMS {:.2} -> {:.2}): it \
             changes how the pixel's illuminations differ, which the kind named above \
             stands for",
            t.effect,
            t.delta_bic,
            pixel.map_or(f64::NAN, |p| p.rms_before),
            pixel.map_or(f64::NAN, |p| p.rms_after),
        ),
        Some(o) if o.data_term => format!(
            "{head}. Offered: the data-driven term along it ({}: each term's response \
             tilted by a smooth function of the fluence, fitted from these data), which \
             predicts each held-out half better than the measurements' description (RMS \
             {before:.2} -> {after:.2}; dBIC {:.1}); the pixel reference takes in every \
             function of fluence and time, so it cannot judge it; add it with: {}",
            t.effect,
            t.delta_bic,
            add_clause(
                &t.command,
                t.measure_command.as_deref(),
                held && t.measured_with.is_some(),
                params,
                &t.effect
            )
        ),
        _ => format!(
            "{head}. The data-driven term along it ({}) is not offered: held out against \
             the measurements' description it does not gain in each half, or lowers the \
             BIC by less than {} (RMS {before:.2} -> {after:.2}; dBIC {:.1})",
            t.effect,
            -super::refit::DBIC_MAX,
            t.delta_bic
        ),
    }
}

/// The command that adds an effect, and how its values were come by: held at the
/// values measured against the description and refined against `effect`'s judge
/// ([`super::polish`], [`super::marked::Judge`]; `held`, `measure` the command that
/// measures them against the description alone), or with the note on the flagging
/// margin ([`margin_note`]).
fn add_clause(
    command: &str,
    measure: Option<&str>,
    held: bool,
    params: &ModelParams,
    effect: &str,
) -> String {
    match measure {
        Some(m) if held => format!(
            "{command} (the effect at the values measured against the measurements' \
             description and refined against {}, held, so the model keeps its flagging \
             calibration; to measure it against the description alone, with its \
             uncertainty: {m})",
            super::marked::Judge::of(&[effect]).phrase()
        ),
        _ => format!("{command}{}", margin_note(measure, params)),
    }
}

/// The verdict on a significant pair of the joint check.
fn joint_sentence(j: &Joint, params: &ModelParams) -> String {
    format!(
        "no library effect is significant alone, but {} and {} are together \
         (dBIC {:.1} against the model, {:.1} against {} alone; held-out gain {:.2}): \
         neither accounts for the residual without the other, so they act \
         together; add both with: {}{}",
        j.effects[0],
        j.effects[1],
        j.delta_bic,
        j.delta_bic_over_leader,
        j.effects[0],
        j.held_out.as_ref().map_or(f64::NAN, |h| h.gain),
        j.command,
        margin_note(j.measure_command.as_deref(), params)
    )
}

/// The verdict on a significant candidate; `per_event`: the pixel reference fitted to
/// each illumination event alone ([`floor_clause`]).
fn candidate_sentence(
    c: &Candidate,
    params: &ModelParams,
    held: bool,
    per_event: Option<f64>,
) -> String {
    let (no_split, evidence) = match &c.held_out {
        None => (
            "; no held-out check: too few sampled pixels to split into halves",
            String::new(),
        ),
        Some(h) => (
            "",
            h.pixel_reference.as_ref().map_or(String::new(), |p| {
                format!(", which {}", held_out_clause(p, per_event))
            }),
        ),
    };
    format!(
        "missing effect: {} (the evidence is in the residual against {}{no_split}){evidence}; \
         add it with: {}",
        c.effect,
        c.covariate,
        add_clause(
            &c.command,
            c.measure_command.as_deref(),
            held && c.measured_with.is_some(),
            params,
            &c.effect
        )
    )
}

/// The library effects that passed the gate but yield to the data-driven term
/// ([`super::offer::settle`]), joined.
fn outpredicted(d: &Diagnosis) -> String {
    d.ranking
        .iter()
        .filter(|c| c.outpredicted_by_term)
        .map(|c| c.effect.as_str())
        .collect::<Vec<_>>()
        .join(", ")
}

/// Whether a held-out check gains but cannot be calibrated
/// ([`super::refit::PixelHeldOut::gains_uncalibrated`]).
fn gains_uncalibrated(h: Option<&super::refit::HeldOut>) -> bool {
    h.and_then(|h| h.pixel_reference.as_ref())
        .is_some_and(super::refit::PixelHeldOut::gains_uncalibrated)
}

/// The candidates (library effects, then the data-driven term) that gain held out but
/// whose check cannot be calibrated ([`gains_uncalibrated`]), joined.
fn uncalibrated(d: &Diagnosis) -> String {
    let library = d
        .ranking
        .iter()
        .filter(|c| gains_uncalibrated(c.held_out.as_ref()));
    let term = d
        .data_term
        .iter()
        .filter(|t| gains_uncalibrated(t.held_out.as_ref()));
    library
        .map(|c| c.effect.as_str())
        .chain(term.map(|t| t.effect.as_str()))
        .collect::<Vec<_>>()
        .join(", ")
}

/// The verdict when the residual depends on `w`'s covariate and no library effect is
/// declared: none predicts held-out data better than the pixel reference beyond the
/// permutations of its change, or those that do (`outpredicted`) take less than half
/// of the data-driven term's gain; `uncalibrated`: those that gain held out but whose
/// check cannot be calibrated on these data's temperatures ([`uncalibrated`]).
fn dependence_sentence(w: &contrast::Dependence, outpredicted: &str, uncalibrated: &str) -> String {
    let too_few = if uncalibrated.is_empty() {
        String::new()
    } else {
        format!(
            ". {uncalibrated} gain held out in each half, but the focal-plane temperatures \
             have fewer than {PERMUTATIONS} other arrangements among these illumination \
             events, so that gain cannot be told from chance: illumination events at more \
             temperatures would test it"
        )
    };
    let why = if outpredicted.is_empty() {
        let judge = super::marked::Judge::of_covariate(&w.class);
        format!(
            "no library effect acting on it ({}) predicts held-out data better than {} \
             beyond {PERMUTATIONS} permutations of its change (or, for a rate hook, of \
             the temperatures) by at least {:.0} % of its RMS",
            w.effects.join(", "),
            judge.phrase(),
            100.0 * super::refit::PIXEL_HELD_OUT_MIN_GAIN
        )
    } else {
        format!(
            "{outpredicted} predicts held-out data beyond {PERMUTATIONS} permutations, but \
             with less than half of the gain of the data-driven term along it"
        )
    };
    format!(
        "the residual of {} depends on {} (it explains {:.1} % of the residual's sum \
         of squares inside the fluence x time cells, {:.1} % at most over {} \
         permutations; z {:.1}{}), but {why}: the missing physics may be of this kind in \
         another form. The residual by {}: {}{too_few}",
        contrast::base_name(&w.class),
        w.class,
        100.0 * w.r2,
        100.0 * w.r2_null_max,
        w.permutations,
        w.z,
        sharp_clause(w),
        w.class,
        w.by_bin
            .iter()
            .map(|(b, n, e)| format!("{b}: {e:+.2} ({n} pixel-events)"))
            .collect::<Vec<_>>()
            .join("; ")
    )
}

/// "; the N pixel-events next to far brighter pixels ..." when they carry an excess
/// of their own ([`contrast::SharpExcess`]).
fn sharp_clause(w: &contrast::Dependence) -> String {
    match w.sharp {
        Some(x) if x.depends => format!(
            "; the {} pixel-events next to far brighter pixels lie {:+.2} of their \
             cells' spread from the cells' mean, z {:.1}",
            x.blocks, x.mean, x.z
        ),
        _ => String::new(),
    }
}

/// "A or B: confounded in these data. " when `class` is one of a confounded pair.
fn confounded_prefix(sep: Option<&Separation>, class: &str) -> String {
    match sep {
        Some(p) if p.told == Told::Confounded && p.classes.iter().any(|c| c == class) => {
            format!(
                "{} or {}: confounded in these data. ",
                p.classes[0], p.classes[1]
            )
        }
        _ => String::new(),
    }
}

/// The verdict's clause on the separation of the two leading kinds
/// ([`super::separate`]) when `class` is one of them: which the data name, or that no
/// illuminations tell them apart and the measurement that would.
fn separation_sentence(sep: Option<&Separation>, class: &str) -> String {
    let Some(p) = sep.filter(|p| p.classes.iter().any(|c| c == class)) else {
        return String::new();
    };
    let [a, b] = &p.classes;
    let (ga, gb) = (&p.first_given_second, &p.second_given_first);
    let given = |x: &str, y: &str, g: &super::separate::Given| {
        format!(
            "{x} given {y}: {:+.1} % beyond its permutations (z {:.1}, {} pixel-events \
             where it varies)",
            100.0 * g.excess_r2,
            g.z,
            g.blocks_with_contrast
        )
    };
    let (ta, tb) = (given(a, b, ga), given(b, a, gb));
    match p.told {
        Told::First | Told::Second => {
            let (named, other) = if p.told == Told::First {
                (a, b)
            } else {
                (b, a)
            };
            format!(
                ". Of {a} and {b}, on which the residual depends alike, the data name \
                 {named}: it explains the residual among illuminations alike in {other}, \
                 and {other} does not among those alike in {named} ({ta}; {tb})"
            )
        }
        Told::Both => format!(
            ". The residual depends on {a} and on {b}, each beyond the other ({ta}; {tb}): \
             one effect acting through both, or one of each. The measurement that shows \
             each on its own: {}",
            separating_measurement(a, b)
        ),
        Told::Confounded => format!(
            ". The residual depends on {a} and on {b}, and neither explains it among \
             illuminations alike in the other ({ta}; {tb}): these illuminations cannot \
             tell them apart. The measurement that separates them: {}",
            separating_measurement(a, b)
        ),
    }
}

/// The measurement that tells two event-level kinds apart.
fn separating_measurement(a: &str, b: &str) -> String {
    let has = |x: &str| a == x || b == x;
    if has("integration_length") {
        "equal illuminations followed by dark integrations of different lengths \
         (persist simulate lab --campaign --dark-lengths varied writes such a campaign)"
            .into()
    } else if has("temperature") {
        format!(
            "illuminations alike but for the temperature, and alike but for the {} \
             (persist simulate lab --campaign --temperatures apart writes such a campaign)",
            if has("illumination_time") {
                "duration"
            } else {
                "history"
            }
        )
    } else {
        "illuminations of equal fluence and equal history (each after darks long enough \
         to empty the traps, or after equally bright ones at the same gap) that differ in \
         duration, for example 481 s at one flux and 120 s at four times it (persist \
         simulate lab --campaign --durations apart writes such a campaign)"
            .into()
    }
}

/// Where the largest cell residuals are, for the verdict with nothing found.
fn largest_sentence(d: &Diagnosis) -> String {
    let w: Vec<String> = d
        .largest_residuals
        .iter()
        .zip(&d.largest_residual_cells)
        .zip(&d.largest_residual_places)
        .map(|((g, (f, t)), place)| {
            let mut after = place
                .illumination_exposure
                .map_or(String::new(), |i| format!(" after the illumination at exposure {i}"));
            if place.next_to_brighter {
                after.push_str(", next to a far brighter pixel");
            }
            format!(
                "fluence >= {f:.3e} e-, t >= {t:.0} s{after}: measured {:.3} vs predicted {:.3} e-/s (z {:.1})",
                g.measured_p95_e_per_s, g.predicted_p95_e_per_s, g.z
            )
        })
        .collect();
    w.join("; ")
}

/// The verdict's clause on a field shared by neighbouring pixels, empty without one.
fn field_sentence(spatial: Option<&super::spatial::Coherence>) -> String {
    spatial.filter(|c| c.coherent).map_or(String::new(), |c| {
        format!(
            "; and the residuals carry a field shared by neighbouring pixels: a {:.0}-pixel \
             map of one illumination's residual predicts {:.0} % of another's (R^2; \
             threshold {:.2}), so the trap density varies across the array in patches, \
             which no library effect carries (the model's populations is a quadratic \
             surface over the whole array){}",
            c.best_length_px,
            100.0 * c.best_r2,
            c.threshold,
            match (c.highest, c.lowest) {
                (Some(((y, x), hi)), Some(((y0, x0), lo))) => format!(
                    "; measured against predicted, x{hi:.2} around (y {y}, x {x}) and \
                     x{lo:.2} around (y {y0}, x {x0}) (the map averaged over the \
                     illuminations, relative to its fluence bin)"
                ),
                _ => String::new(),
            }
        )
    })
}

/// The verdict's sentence on the offer ([`super::offer`]): what it is, what it does to
/// the pixel reference held out, and the command that adds it (the candidate's, or the
/// data-driven term's).
fn offer_sentence(
    o: &super::offer::Offer,
    d: &Diagnosis,
    params: &ModelParams,
    held: bool,
) -> String {
    let (what, command, measure, measured) = if o.data_term {
        let Some(t) = d.data_term.as_ref() else {
            return String::new();
        };
        (
            format!(
                "the data-driven term along it ({}: a smooth function of the covariate \
                 fitted from these data)",
                t.effect
            ),
            &t.command,
            t.measure_command.as_deref(),
            t.measured_with.is_some(),
        )
    } else {
        let Some(c) = d.ranking.iter().find(|c| c.effect == o.effect) else {
            return String::new();
        };
        (
            format!(
                "the library effect {} (acting on {})",
                c.effect, c.covariate
            ),
            &c.command,
            c.measure_command.as_deref(),
            c.measured_with.is_some(),
        )
    };
    format!(
        ". Offered: {what}, which {}; add it with: {}",
        held_out_clause(&o.pixel_reference, d.pixel_reference.per_event_rms),
        add_clause(command, measure, held && measured, params, &o.effect)
    )
}

/// What a candidate held out does to its judge ([`super::refit::PixelHeldOut`]): the
/// pixel reference, with the floor's share ([`floor_clause`]), or for a candidate on the
/// neighbours the flexible base on the pixels next to far brighter ones
/// ([`super::marked`]).
fn held_out_clause(p: &super::refit::PixelHeldOut, per_event: Option<f64>) -> String {
    use super::refit::Judge;
    let (against, rms_of, floor) = match p.judge {
        Judge::PixelReference => (
            "the pixel reference alone",
            "the pixel reference's RMS",
            floor_clause(p, per_event),
        ),
        Judge::NextToBrighter => (
            "the flexible base alone on the pixels next to far brighter ones",
            "the RMS of their cells' z",
            String::new(),
        ),
        Judge::Position => (
            "the flexible base alone by tile of the array",
            "the RMS of the tiles' cells' z",
            String::new(),
        ),
    };
    format!(
        "predicts held-out data better than {against} (fitted on one half, {rms_of} on \
         the other {:.2} -> {:.2}, gain {:.2}, the largest of {PERMUTATIONS} {} {:.2}{floor})",
        p.rms_before,
        p.rms_after,
        p.gain,
        p.permuted.phrase(),
        p.permuted_max(),
    )
}

/// The share of the excess of the held-out pixel reference over its fit per
/// illumination event (`per_event`, [`super::base::per_event_rms`]) that the offer `p`
/// takes away: `(before - after) / (before - per_event)`; None without the floor or
/// with no excess over it.
pub(super) fn floor_share(p: &super::refit::PixelHeldOut, per_event: Option<f64>) -> Option<f64> {
    if p.judge != super::refit::Judge::PixelReference {
        return None;
    }
    let floor = per_event.filter(|f| f.is_finite())?;
    let excess = p.rms_before - floor;
    (excess > 0.0).then(|| (p.rms_before - p.rms_after) / excess)
}

/// The offer's clause on the floor ([`floor_share`]): how much of what the
/// illuminations' differences leave it takes, and when less than half, that the rest is
/// in no offered form.
fn floor_clause(p: &super::refit::PixelHeldOut, per_event: Option<f64>) -> String {
    let (Some(share), Some(floor)) = (floor_share(p, per_event), per_event) else {
        return String::new();
    };
    let rest = if share < 0.5 {
        "; most of how a pixel's illuminations differ here is in none of the forms tried \
         (the library effects refitted and the data-driven term): the missing physics \
         changes them in another form"
    } else {
        ""
    };
    format!(
        "; it takes {:.0} % of the excess over the pixel reference fitted to each \
         illumination event alone (RMS {floor:.2}){rest}",
        100.0 * share
    )
}

/// The verdict's sentence on the data-driven term when nothing is offered (an offered
/// term is [`offer_sentence`]'s): held by the model already, absent, or why not offered.
/// `class`: the covariate's class.
fn data_term_sentence(
    t: Option<&super::data_term::DataTerm>,
    class: &str,
    params: &ModelParams,
) -> String {
    let Some(t) = t else {
        return match super::data_term::held(class, params) {
            Some(d) => format!(
                ". The model already holds the data-driven term along it ({}): the \
                 residual it leaves still depends on this covariate",
                d.name
            ),
            None => ". No data-driven term follows this covariate".into(),
        };
    };
    if gains_uncalibrated(t.held_out.as_ref()) {
        return format!(
            ". The data-driven term along it ({}) is not offered: its held-out check \
             cannot be calibrated on these temperatures (above)",
            t.effect
        );
    }
    let gain = t
        .held_out
        .as_ref()
        .map_or("no held-out check".to_string(), |h| {
            format!("held-out gain {:.2}", h.gain)
        });
    format!(
        ". A data-driven term along it ({}) does not predict held-out data either \
         (dBIC {:.1}, {gain}; against {}, no refitted candidate gains held out more \
         than every one of {PERMUTATIONS} permutations of its change by at least {:.0} % \
         of its RMS): not offered",
        t.effect,
        t.delta_bic,
        t.held_out
            .as_ref()
            .and_then(|h| h.pixel_reference.as_ref())
            .map_or(super::refit::Judge::PixelReference, |p| p.judge)
            .phrase(),
        100.0 * super::refit::PIXEL_HELD_OUT_MIN_GAIN
    )
}

/// What is known to limit a diagnosis against `params`.
pub fn cautions(params: &ModelParams) -> Vec<String> {
    let mut c = Vec::new();
    if crate::calib::cn_fitted_to_campaign(params) {
        c.push(
            "the model's C_n were fitted to this campaign (persist fit --fit-cn): they have \
             taken in the decay-shape part of any missing effect (a hidden short_tau_boost \
             was found at 3 of 3 seeds against a model without --fit-cn, at none with it \
             before the capacity fix; docs/validation/diagnose_matrix.md); diagnose against a model \
             fitted without --fit-cn too"
                .to_string(),
        );
    }
    if crate::calib::level_fitted_to_campaign(params) {
        c.push(
            "the model's knot level was fitted to this campaign (persist fit \
             --fit-amplification): it has taken in the level part of any missing effect (a \
             hidden short_tau_boost was declared at 1 of 3 seeds against such a model, at 3 \
             of 3 with the level fixed; measured with examples/diagnose_matrix); diagnose \
             against a model with a fixed --amplification too"
                .to_string(),
        );
    }
    c
}

/// The printed ranking.
pub fn render(d: &Diagnosis) -> String {
    let mut s = format!(
        "persist diagnose: statistic {}, {} pixels, {} cells in {} groups, {} illumination events, \
         residual RMS {:.2} ({} cells{}{})\npixel reference (the flexible base with each pixel's own amplitude, \
         decay shape and response): residual RMS {:.2} over {} cells{}{}\nthreshold {:.2} (95 % of the largest score over {} bootstrap replicas \
         from the fitted model; median {:.2}; the score ranks, it does not decide)\n\
         {:<16} {:>10} {:>6} {:>9} {:>15} {:>9} {:>15} {:>15}  covariate\n",
        d.statistic_reason,
        d.pixels_sampled,
        d.cells,
        d.groups,
        d.events,
        d.residual_rms_normalised,
        d.residual_cells.describe(),
        d.cell_statistic.note(),
        match d.refit {
            Refit::Full => "; candidates refitted with the model's own effects (--refit full)",
            Refit::Candidate => "; candidates refitted alone (--refit candidate)",
        },
        d.pixel_reference.residual_rms_normalised,
        d.pixel_reference.cells,
        d.pixel_reference.per_event_rms.map_or(String::new(), |r| format!(
            "\n  fitted to each illumination event alone (its own correction and pixel terms: \
             the least an addition acting on how a pixel's illuminations differ can leave): \
             residual RMS {r:.2}"
        )),
        d.pixel_reference.noise_scale.map_or(
            "\n  noise: as measured (too few samples to scale it on the residuals)".to_string(),
            |n| format!(
                "\n  noise: the read-noise variance x{:.2} and the shot-noise variance x{:.2}, \
                 as its residuals show them ({} samples, each centred in its cell)",
                n.read_var, n.shot_var, d.pixel_reference.noise_scale_samples
            )
        ),
        d.threshold,
        d.bootstrap_replicas,
        d.bootstrap_median_max,
        "effect",
        "score",
        "pass",
        "dBIC",
        "RMS",
        "held-out",
        "(moved cells)",
        "pixel ref/perm"
    );
    for c in &d.ranking {
        s += &format!(
            "{:<16} {:>10.2} {:>6} {:>9} {:>15} {:>9} {:>15} {:>15}  {}{}\n",
            c.effect,
            c.score,
            c.passes_score,
            c.delta_bic.map_or("-".into(), |v| format!("{v:.1}")),
            match (c.rms_before, c.rms_after) {
                (Some(a), Some(b)) => format!("{a:.2}->{b:.2}"),
                _ => "-".into(),
            },
            c.held_out
                .as_ref()
                .map_or("-".into(), |h| format!("{:+.0}%", -100.0 * h.gain)),
            c.held_out.as_ref().map_or("-".into(), |h| {
                if h.moved_cells == 0 || !h.gain_moved_cells.is_finite() {
                    "none moved".into()
                } else {
                    format!("{:+.0}% of {}", -100.0 * h.gain_moved_cells, h.moved_cells)
                }
            }),
            c.held_out
                .as_ref()
                .and_then(|h| h.pixel_reference.as_ref())
                .map_or("-".into(), |p| if p.permuted_gains.is_empty() {
                    format!("{:+.0}%", -100.0 * p.gain)
                } else {
                    format!(
                        "{:+.0}%/{:+.0}%",
                        -100.0 * p.gain,
                        -100.0 * p.permuted_max()
                    )
                }),
            c.covariate,
            if c.significant {
                "  SIGNIFICANT"
            } else if c.outpredicted_by_term {
                "  (passes the gate, but takes less than half of the data-driven term's gain)"
            } else if c.refused_no_field {
                "  (passes the gates, but the residuals carry no field shared by neighbours)"
            } else {
                ""
            }
        );
    }
    for c in d.contrasts.iter().filter(|c| !c.testable) {
        s += &format!(
            "{:<16} untestable, needs {} ({})\n",
            c.effects.join(", "),
            c.needs.as_deref().unwrap_or("-"),
            c.why
        );
    }
    if !d.dependences.is_empty() {
        s += "what the residual depends on (share of its sum of squares inside the \
              fluence x time cells; permutations' largest; z; event-level kinds against \
              the pixel reference, pixel-level ones against the flexible base):\n";
        for x in &d.dependences {
            s += &format!(
                "  {:<26} {:>6.2} % {:>6.2} % {:>7.1}  {}{}\n",
                x.class,
                100.0 * x.r2,
                100.0 * x.r2_null_max,
                x.z,
                x.effects.join(", "),
                if x.depends { "  DEPENDS" } else { "" }
            );
            if let Some(e) = x.sharp {
                s += &format!(
                    "  {:<26} next to far brighter pixels: {} pixel-events, {:+.2} of \
                     their cells' spread, z {:.1}{}\n",
                    "",
                    e.blocks,
                    e.mean,
                    e.z,
                    if e.depends { "  DEPENDS" } else { "" }
                );
            }
        }
    }
    if !d.joint.is_empty() {
        s += "joint check (no effect significant alone; the leader refitted with each other):\n";
        for j in &d.joint {
            s += &format!(
                "{:<32} {:>9.1} {:>9.1} {:>15} {:>9}{}\n",
                format!("{} + {}", j.effects[0], j.effects[1]),
                j.delta_bic,
                j.delta_bic_over_leader,
                format!("{:.2}->{:.2}", j.rms_before, j.rms_after),
                j.held_out
                    .as_ref()
                    .map_or("-".into(), |h| format!("{:+.0}%", -100.0 * h.gain)),
                if j.significant { "  SIGNIFICANT" } else { "" }
            );
        }
    }
    if let Some(c) = &d.spatial {
        s += &format!(
            "spatial coherence: a map of one illumination's residual smoothed over {} px \
             predicts R^2 {} of another's (unsmoothed {:.2}; {} pairs, {} pixels per \
             illumination): {}\n",
            c.r2_smoothed
                .iter()
                .map(|(l, _)| format!("{l:.0}"))
                .collect::<Vec<_>>()
                .join("/"),
            c.r2_smoothed
                .iter()
                .map(|(_, r)| format!("{r:.2}"))
                .collect::<Vec<_>>()
                .join("/"),
            c.r2_raw,
            c.pairs,
            c.pixels_per_event,
            if c.coherent {
                format!("a field shared by neighbours (>= {:.2})", c.threshold)
            } else {
                format!("none shared by neighbours (< {:.2})", c.threshold)
            }
        );
    }
    s += &d.verdict;
    for c in &d.cautions {
        s += "\ncaution: ";
        s += c;
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::diag::separate::Given;

    fn pair(told: Told) -> Separation {
        let g = |depends| Given {
            excess_r2: if depends { 0.05 } else { 0.0 },
            z: if depends { 12.0 } else { 0.0 },
            depends,
            above_permutations: depends,
            blocks_with_contrast: 300,
        };
        Separation {
            classes: ["illumination_time".into(), "earlier_illuminations".into()],
            first_given_second: g(told == Told::First || told == Told::Both),
            second_given_first: g(told == Told::Second || told == Told::Both),
            told,
        }
    }

    /// Confounded kinds are named together with the measurement that separates them;
    /// a kind the data name is said to be named; a class outside the pair gets nothing.
    #[test]
    fn confounded_kinds_are_named_together_with_the_measurement_that_separates_them() {
        let c = pair(Told::Confounded);
        assert_eq!(
            confounded_prefix(Some(&c), "earlier_illuminations"),
            "illumination_time or earlier_illuminations: confounded in these data. "
        );
        let s = separation_sentence(Some(&c), "illumination_time");
        assert!(s.contains("equal fluence and equal history"), "{s}");
        assert!(s.contains("differ in duration"), "{s}");
        assert!(
            s.contains(
                "(persist simulate lab --campaign --durations apart writes such a campaign)"
            ),
            "{s}"
        );
        let named = separation_sentence(Some(&pair(Told::Second)), "illumination_time");
        assert!(
            named.contains("the data name earlier_illuminations"),
            "{named}"
        );
        assert_eq!(
            confounded_prefix(Some(&pair(Told::Second)), "illumination_time"),
            ""
        );
        assert_eq!(separation_sentence(Some(&c), "temperature"), "");
        assert_eq!(separation_sentence(None, "temperature"), "");
    }

    /// A candidate that gains held out where its null cannot be drawn is named with the
    /// reason and the data that would test it; without one the sentence says nothing
    /// of it.
    #[test]
    fn a_gain_that_cannot_be_calibrated_is_named_with_what_would_test_it() {
        let w = contrast::Dependence {
            class: "temperature".into(),
            effects: vec!["temperature".into()],
            r2: 0.04,
            r2_null_mean: 0.001,
            r2_null_max: 0.003,
            z: 40.0,
            permutations: 99,
            depends: true,
            above_permutations: true,
            by_bin: vec![("78 K".into(), 120, -0.4), ("82 K".into(), 120, 0.5)],
            sharp: None,
        };
        let s = dependence_sentence(&w, "", "temperature, smooth_temperature");
        assert!(
            s.contains(
                "temperature, smooth_temperature gain held out in each half, but the \
                 focal-plane temperatures have fewer than 19 other arrangements"
            ),
            "{s}"
        );
        assert!(
            s.ends_with("illumination events at more temperatures would test it"),
            "{s}"
        );
        let plain = dependence_sentence(&w, "", "");
        assert!(!plain.contains("arrangements"), "{plain}");
        assert!(plain.ends_with("82 K: +0.50 (120 pixel-events)"), "{plain}");
    }

    /// The offer's share of the excess over the per-event floor: capacity:ceiling's
    /// numbers (family campaign, 64 x 64, seed 1: held out 1.88 -> 1.80, per-event
    /// floor 1.02) take 9 % and say the rest is in no form tried; an offer that takes
    /// most of it does not; no floor, or none below the held-out RMS, says nothing.
    #[test]
    fn the_offer_says_what_share_of_the_illuminations_differences_it_takes() {
        let held = |before: f64, after: f64| crate::diag::refit::PixelHeldOut {
            rms_before: before,
            rms_after: after,
            gain: 1.0 - after / before,
            fold_gains: vec![0.04, 0.05],
            gain_held: 0.0,
            permuted_gains: Vec::new(),
            permuted: crate::diag::refit::Permuted::Change,
            judge: crate::diag::refit::Judge::PixelReference,
            too_few_arrangements: false,
        };
        let small = held(1.88, 1.80);
        let share = floor_share(&small, Some(1.02)).unwrap();
        assert!((share - 0.08 / 0.86).abs() < 1e-9, "{share}");
        let c = floor_clause(&small, Some(1.02));
        assert!(c.contains("it takes 9 %"), "{c}");
        assert!(c.contains("none of the forms tried"), "{c}");
        let large = floor_clause(&held(7.0, 2.0), Some(1.0));
        assert!(large.contains("it takes 83 %"), "{large}");
        assert!(!large.contains("none of the forms tried"), "{large}");
        assert_eq!(floor_share(&small, None), None);
        assert_eq!(floor_share(&small, Some(f64::NAN)), None);
        assert_eq!(floor_share(&small, Some(2.0)), None);
        assert_eq!(floor_clause(&small, None), "");
    }
}
