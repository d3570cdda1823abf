//! Flag quality on the simulator's truth (docs/validation/flag_quality.md;
//! `scripts/validation.sh flag_quality` writes the page with its generated header): one
//! simulated detector's laboratory sequence (`persist::pixmap::eval::lab_sequence`)
//! gives the lab-calibrated model (the paper's 95th percentile x 1.2) and the same
//! calibrated to 95 % coverage (`persist::calib::coverage`), each with and without the
//! per-pixel map; the sky run of the same detector is flagged by them, by the paper's
//! default model, by time-window flaggers (a pixel saturated in the last W s) and by HST
//! WFC3's persistence model with its published constants and 16 h look-back
//! (`persist::flag_quality::Wfc3Flagger`; kslong/Persistence `subtract_persist.py`,
//! `calc_persist` and `do_dataset`; Long, Baggett & MacKenty, WFC3 ISR 2015-15),
//! counted from exposure 200 on against the true persistence current
//! (`persist::flag_quality`); and `persist fit --with refill` calibrated to the same
//! coverage. Where the errors of the default `fit` and of `fit --with refill` are:
//! `persist::flag_causes`.
//!
//! The rows "+ transient rule measured in flight" give a model the transient rule the
//! way operations would ([`measured_rule`]): the sky's exposures before the counted
//! ones (0 to `FROM_EXPOSURE - 1`) written as products, flagged by the stage with that
//! model, measured by `persist verify` and turned into the rule by `persist fit
//! --from-verify` (`persist::verify::transient::run`, the CLI's function); then the whole
//! run is flagged with the model that carries the rule and counted from `FROM_EXPOSURE`
//! on. Nothing there reads the simulator's cosmic-ray charges or its truth.
//!
//! ```sh
//! target/release/examples/flag_quality [--size 128] [--seed 1] [--exposures 1143]
//!     [--windows 2500,5000,10000,20000,40000] [--lab-darks 30] [--release-consecutive N]
//!     [--release-rule consecutive] [--release-sigma Z] [--no-causes]
//! ```
//! Prints the page's body (markdown) on stdout (`--no-causes`: without the tables of
//! where the errors are).
use ndarray::Array2;
use persist::calib::coverage::{self, CoverageConfig};
use persist::flag_causes::{CauseInput, CauseTally};
use persist::flag_quality::{table, TruthTally, FROM_EXPOSURE};
use persist::model::{Model, ModelParams};
use persist::sim::sky::SkyConfig;
use std::path::Path;

/// The model `persist fit` writes by default (`persist::calib::Preset::Paper`).
const DEFAULT_FIT: &str =
    "`persist fit`, its default: `refill`, 95 % coverage, release keeps the threshold";
/// The paper's calibration at 95 % coverage without `refill`, released pixels reset to
/// zero (the paper's sum and release).
const NO_REFILL: &str = "no `refill`, 95 % coverage";
/// HST WFC3's model ([`Flagger::Wfc3`]).
const WFC3: &str = "WFC3 A-gamma (closed form, published constants, 16 h look-back)";

enum Flagger {
    Model {
        model: Box<Model>,
        state: Option<persist::model::State>,
    },
    /// Flag a pixel saturated (`OVERFLOW`) within the last `window_s`.
    Window {
        window_s: f64,
        last_s: Option<Array2<f64>>,
    },
    /// HST WFC3's persistence model with its published constants and 16 h look-back
    /// (kslong/Persistence `subtract_persist.py`, `calc_persist` and `do_dataset`; Long,
    /// Baggett & MacKenty, WFC3 ISR 2015-15): `persist::flag_quality::Wfc3Flagger`.
    Wfc3(Box<persist::flag_quality::Wfc3Flagger>),
}

impl Flagger {
    /// The persistence flags and the predicted current (zero for a window).
    fn step(
        &mut self,
        e: &persist::product::Exposure,
    ) -> persist::Result<(Array2<u8>, Array2<f32>)> {
        let (ny, nx) = e.image.dim();
        match self {
            Flagger::Model { model, state } => {
                let st = state.get_or_insert_with(|| model.new_state(ny, nx));
                let mut cur = Array2::<f32>::zeros((ny, nx));
                let mut pf = Array2::<u8>::zeros((ny, nx));
                persist::pixmap::step_exposure(model, st, e, None, &mut cur, &mut pf)?;
                Ok((pf, cur))
            }
            Flagger::Window { window_s, last_s } => {
                let last = last_s.get_or_insert_with(|| Array2::from_elem((ny, nx), f64::MIN));
                let t = e.meta.t_start.0;
                let both = persist::flags::pbits::HIGH | persist::flags::pbits::LOW;
                let pf = Array2::from_shape_fn((ny, nx), |p| {
                    if t - last[p] <= *window_s {
                        both
                    } else {
                        0
                    }
                });
                let end = t + e.meta.t_exposure_s;
                for (p, f) in e.flags.indexed_iter() {
                    if f & persist::flags::bits::OVERFLOW != 0 {
                        last[p] = end;
                    }
                }
                Ok((pf, Array2::zeros((ny, nx))))
            }
            Flagger::Wfc3(w) => Ok(w.step(e)),
        }
    }
}

fn arg<T: std::str::FromStr>(args: &[String], name: &str, default: T) -> T {
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1))
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

fn main() -> persist::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let size: usize = arg(&args, "--size", 128);
    let seed: u64 = arg(&args, "--seed", 1);
    let exposures: u64 = arg(&args, "--exposures", 1143);
    let windows: Vec<f64> = arg(
        &args,
        "--windows",
        "2500,5000,10000,20000,40000".to_string(),
    )
    .split(',')
    .filter_map(|w| w.parse().ok())
    .collect();
    let started = std::time::Instant::now();
    // darks after the first illumination (the demo's 30, 1.5 h; the paper's 280, 14 h,
    // `persist::pixmap::eval::PAPER_DARKS_AFTER_FIRST`)
    let lab_darks: usize = arg(&args, "--lab-darks", 30);
    // early release of the coverage-calibrated model after this many exposures in a row
    // (`rule: consecutive`; the model's rule when absent)
    let release: Option<u8> = args
        .iter()
        .position(|a| a == "--release-consecutive")
        .and_then(|i| args.get(i + 1))
        .and_then(|v| v.parse().ok());
    // early release of every model by the paper-style count instead of the evidence sum
    // (`--release-rule consecutive`), or with this evidence (`--release-sigma`)
    let consecutive_rule = args
        .iter()
        .position(|a| a == "--release-rule")
        .and_then(|i| args.get(i + 1))
        .is_some_and(|v| v == "consecutive");
    let sigma: Option<f64> = args
        .iter()
        .position(|a| a == "--release-sigma")
        .and_then(|i| args.get(i + 1))
        .and_then(|v| v.parse().ok());
    let with_rule = |mut p: ModelParams| {
        if consecutive_rule {
            p.early_release.rule = persist::model::ReleaseRule::Consecutive;
        }
        if let Some(z) = sigma {
            p.early_release.evidence_sigma = z;
        }
        p
    };
    let mut campaign = persist::pixmap::eval::lab_campaign();
    campaign[0].darks_after = lab_darks;
    let (_, seq) = persist::pixmap::eval::lab_sequence_of(size, seed, true, campaign)?;
    let (lab, _) = persist::calib::calibrate(&seq, &persist::calib::CalibConfig::default())?;
    let lab = with_rule(lab);
    let cov = CoverageConfig::default();
    let (covered, rep) = coverage::apply(&lab, &seq, &cov)?;
    let mut covered = with_rule(covered);
    if let Some(n) = release {
        covered.early_release.rule = persist::model::ReleaseRule::Consecutive;
        covered.early_release.consecutive = n;
    }
    let reshaped_cfg = CoverageConfig {
        shape: true,
        ..cov.clone()
    };
    let (reshaped, rep_reshaped) = coverage::apply(&lab, &seq, &reshaped_cfg)?;
    let reshaped = with_rule(reshaped);
    // `persist fit --with refill`: the overlap of old and new filling measured on the
    // same laboratory sequence, then the coverage calibration
    let (refill_lab, _, refill_fit) = persist::calib::command::fit_params(
        &seq,
        &persist::calib::CalibConfig::default(),
        &["refill".to_string()],
        Default::default(),
    )?;
    let (refilled, _) = coverage::apply(&refill_lab, &seq, &cov)?;
    let refilled = with_rule(refilled);
    let beta = refill_fit
        .iter()
        .flat_map(|f| &f.params)
        .find(|q| q.effect == "refill" && q.name == "beta")
        .map_or_else(String::new, |q| format!("{:.2} +- {:.2}", q.value, q.sigma));
    let map = |p: &ModelParams| -> persist::Result<Model> {
        let m = persist::pixmap::build(&seq, p, &persist::pixmap::MapConfig::default())?;
        let r = persist::pixmap::file::response(&m, 1.0)
            .map_err(|e| persist::Error::invalid("margin", e))?;
        Model::new(p.clone())?
            .with_pixel_maps([(1u8, r)].into_iter().collect())
            .for_detector(1)
    };
    let model = |m: Model| Flagger::Model {
        model: Box::new(m),
        state: None,
    };
    let sky = SkyConfig {
        size,
        detectors: 1,
        exposures,
        seed,
        ..Default::default()
    };
    // early release keeping the threshold (`early_release.keep: threshold`)
    let keeping = |p: &ModelParams| ModelParams {
        early_release: persist::model::EarlyRelease {
            keep: persist::model::ReleaseKeep::Threshold,
            ..p.early_release
        },
        ..p.clone()
    };
    let covered_keep = keeping(&covered);
    let refilled_keep = keeping(&refilled);
    // the transient rule measured in flight on the exposures before the counted ones
    let work = tempfile::tempdir().map_err(|e| persist::Error::io(&std::env::temp_dir(), e))?;
    let span = measured_span(&sky, work.path())?;
    let covered_rule = measured_rule(&span, &covered, &work.path().join("fit"))?;
    let covered_keep_rule = measured_rule(&span, &covered_keep, &work.path().join("fit-keep"))?;
    let refilled_rule = measured_rule(&span, &refilled, &work.path().join("refill"))?;
    let refilled_keep_rule = measured_rule(&span, &refilled_keep, &work.path().join("keep"))?;
    let in_flight = " + transient rule measured in flight";
    let mut flaggers: Vec<(String, Flagger)> = vec![
        (
            "paper's default model".into(),
            model(Model::new(with_rule(ModelParams::default()))?),
        ),
        (
            "paper's default model, release keeps the threshold".into(),
            model(Model::new(keeping(&with_rule(ModelParams::default())))?),
        ),
        (
            "no `refill`, 95th percentile x 1.2 (`--no-coverage`)".into(),
            model(Model::new(lab.clone())?),
        ),
        (
            "no `refill`, 95th percentile x 1.2, + map".into(),
            model(map(&lab)?),
        ),
        (NO_REFILL.to_string(), model(Model::new(covered.clone())?)),
        (
            format!("{NO_REFILL}{in_flight}"),
            model(Model::new(covered_rule.0.clone())?),
        ),
        (
            format!("{NO_REFILL}, release keeps the threshold"),
            model(Model::new(covered_keep)?),
        ),
        (
            format!("{NO_REFILL}, release keeps the threshold{in_flight}"),
            model(Model::new(covered_keep_rule.0.clone())?),
        ),
        (format!("{NO_REFILL} + map"), model(map(&covered)?)),
        (
            format!("{NO_REFILL}, decay reshaped"),
            model(Model::new(reshaped)?),
        ),
        (
            "`refill`, 95 % coverage, release to zero".into(),
            model(Model::new(refilled.clone())?),
        ),
        (
            format!("`refill`, 95 % coverage, release to zero{in_flight}"),
            model(Model::new(refilled_rule.0.clone())?),
        ),
        (DEFAULT_FIT.into(), model(Model::new(refilled_keep)?)),
        (
            format!("{DEFAULT_FIT}{in_flight}"),
            model(Model::new(refilled_keep_rule.0.clone())?),
        ),
        (
            format!("{DEFAULT_FIT}{in_flight} + map"),
            model(map(&refilled_keep_rule.0)?),
        ),
    ];
    for w in &windows {
        flaggers.push((
            format!("window of {w} s"),
            Flagger::Window {
                window_s: *w,
                last_s: None,
            },
        ));
    }
    let th = ModelParams::default().thresholds;
    flaggers.push((
        WFC3.into(),
        Flagger::Wfc3(Box::new(persist::flag_quality::Wfc3Flagger::new(
            persist::flag_quality::Wfc3Params::PUBLISHED,
            th.high_e_per_s,
            th.low_e_per_s,
        ))),
    ));
    let mut tallies: Vec<TruthTally> = flaggers
        .iter()
        .map(|_| TruthTally::new(th.high_e_per_s, th.low_e_per_s, FROM_EXPOSURE))
        .collect();
    // where the errors are (`persist::flag_causes`): the coverage-calibrated model's,
    // without and with `refill`
    let explained: Vec<usize> = if args.iter().any(|a| a == "--no-causes") {
        vec![]
    } else {
        [NO_REFILL.to_string(), format!("{DEFAULT_FIT}{in_flight}")]
            .iter()
            .filter_map(|n| flaggers.iter().position(|(f, _)| f == n))
            .collect()
    };
    let mut causes: Vec<CauseTally> = explained
        .iter()
        .map(|_| {
            CauseTally::new(
                th.high_e_per_s,
                th.low_e_per_s,
                sky.detector.full_well_e,
                FROM_EXPOSURE,
            )
        })
        .collect();
    persist::sim::sky::run(&sky, |s| {
        let e = &s.exposure;
        let fluence = s.true_flux.mapv(|f| f * e.meta.t_exposure_s as f32);
        for (i, ((_, f), tally)) in flaggers.iter_mut().zip(tallies.iter_mut()).enumerate() {
            let (pf, cur) = f.step(e)?;
            tally.add_pflags(e.meta.exposure_index, &pf, &s.true_persistence, &e.flags);
            if let Some(j) = explained.iter().position(|&k| k == i) {
                causes[j].add(&CauseInput {
                    exposure_index: e.meta.exposure_index,
                    t_start_s: e.meta.t_start.0,
                    t_exposure_s: e.meta.t_exposure_s,
                    pflags: &pf,
                    predicted_e_per_s: &cur,
                    truth_e_per_s: &s.true_persistence,
                    true_fluence_e: &fluence,
                    flags: &e.flags,
                });
            }
        }
        Ok(())
    })?;
    println!(
        "Detector 1, {size} x {size} pixels, seed {seed}: the laboratory sequence of \
         `persist::pixmap::eval::lab_campaign` with {lab_darks} darks of 180 s after the first \
         illumination, then {exposures} sky exposures; early release {}; counted from \
         exposure {FROM_EXPOSURE} on, non-functional pixels left out. Computed in {:.0} s.\n",
        release_rule(
            &covered.early_release,
            if release.is_some() {
                "of the coverage-calibrated model"
            } else {
                "of every model"
            }
        ),
        started.elapsed().as_secs_f64()
    );
    println!(
        "Coverage calibration (`persist fit`, its default 95 %):\n\n```\n{}```\n",
        rep.describe()
    );
    println!(
        "Coverage calibration with the decay reshaped in time:\n\n```\n{}```\n",
        rep_reshaped.describe()
    );
    println!(
        "Over-flagged: flagged while the true current is below the threshold, per functional \
         pixel-exposure. Missed: truly above, not flagged, per band of true current in units \
         of the threshold (1-1.5x is 0.1-0.15 e-/s at 0.1 e-/s).\n"
    );
    let rows: Vec<(&str, &TruthTally)> = flaggers
        .iter()
        .zip(&tallies)
        .map(|((n, _), t)| (n.as_str(), t))
        .collect();
    println!("{}", table(&rows));
    println!(
        "`persist fit --with refill` measures on the laboratory sequence how much of an \
         illumination's filling adds to the charge its traps still hold (`refill`'s `beta`: \
         0 adds, the paper's sum; 1 takes the larger, a trap cannot fill twice): `beta` = \
         {beta}.\n"
    );
    println!(
        "The transient rule measured in flight (rows \"{in_flight}\"): the sky's exposures \
         0 to {} of the same run, flagged by the stage with the model, `persist verify` on \
         them and `persist fit --from-verify` on its report (the 95th percentile of \
         measured / predicted at the first exposure after each hit, the upper end of its \
         95 % interval, times the model's transient amplitude; with the rule, the exposure \
         after a hit follows the prediction):\n",
        FROM_EXPOSURE - 1
    );
    for (name, rule) in [
        (NO_REFILL, &covered_rule),
        (
            format!("{NO_REFILL}, release keeps the threshold").as_str(),
            &covered_keep_rule,
        ),
        ("`refill`, 95 % coverage, release to zero", &refilled_rule),
        (DEFAULT_FIT, &refilled_keep_rule),
    ] {
        println!("- {name}: {}", said(rule));
    }
    println!();
    for (j, c) in explained.iter().zip(&causes) {
        println!(
            "Where the errors of {} are: its over-flagged and missed pixel-exposures by the \
             kind of the pixel's last event (saturating: true fluence at least the full well; \
             bright: at least {} % of it; `TRANSIENT`: the on-board flag), the time since \
             that event, whether early release acted since, and the ratio of predicted to \
             true current (`persist::flag_causes`). Each cell: the category's share of the \
             threshold's over-flagged (or missed) pixel-exposures, and in brackets the \
             over-flagged fraction of the category's pixel-exposures (or the missed fraction \
             of its truly above ones).\n",
            flaggers[*j].0,
            100.0 * persist::flag_causes::BRIGHT_FRACTION
        );
        println!("{}", c.table());
    }
    Ok(())
}

/// The sky's exposures before the counted ones (`FROM_EXPOSURE`), written as products
/// with their truth into `dir/sim`: the survey plan and the detector's draws are
/// sequential, so a run of `FROM_EXPOSURE` exposures is the full run's first ones.
fn measured_span(sky: &SkyConfig, dir: &Path) -> persist::Result<std::path::PathBuf> {
    let sim = dir.join("sim");
    let span = SkyConfig {
        exposures: FROM_EXPOSURE.min(sky.exposures),
        ..sky.clone()
    };
    persist::sim::sky::write(&span, &sim)?;
    Ok(sim)
}

/// `params` with the transient rule measured in flight the way operations would
/// (`persist::verify::transient::measure_in_flight`), and what the first exposures after
/// the hits measured against the truth, in words.
fn measured_rule(
    sim: &Path,
    params: &ModelParams,
    dir: &Path,
) -> persist::Result<(ModelParams, Option<String>, String)> {
    let m = persist::verify::transient::measure_in_flight(sim, params, dir)?;
    let first_bin = m.report.decay.first().map_or_else(String::new, |b| {
        format!(
            "; at {:.0}-{:.0} s after a hit, {} samples: measured excess {:.3} e-/s, true {}, \
             predicted by the flown model {:.2}",
            b.time_lo_s,
            b.time_hi_s,
            b.samples,
            b.measured.mean,
            b.truth
                .as_ref()
                .map_or_else(|| "-".into(), |t| format!("{:.4}", t.mean)),
            b.predicted.mean
        )
    });
    Ok((m.params, m.refused, first_bin))
}

/// The measured rule of `p` (or why there is none), in words (without the report's
/// temporary path).
fn said((p, refused, first_bin): &(ModelParams, Option<String>, String)) -> String {
    let rule = p.transient.as_ref().map_or_else(
        || {
            format!(
                "{}: the table's maximum stays",
                refused.as_deref().unwrap_or("no rule")
            )
        },
        |t| {
            format!(
                "{:.1} e- (the flown {:.1} e- x {:.4}, from {} hits at their first exposure)",
                t.amplitude_e, t.measured.flown_amplitude_e, t.measured.ratio, t.measured.events
            )
        },
    );
    format!("{rule}{first_bin}")
}

/// The early release of the coverage-calibrated model (that of `who`), in words.
fn release_rule(er: &persist::model::EarlyRelease, who: &str) -> String {
    match er.rule {
        persist::model::ReleaseRule::Consecutive => format!(
            "{who} after {} exposures in a row measured below its threshold \
             (`rule: consecutive`)",
            er.consecutive
        ),
        persist::model::ReleaseRule::Evidence => format!(
            "{who} at an evidence of {} noise sigma (`rule: evidence`)",
            er.evidence_sigma
        ),
    }
}
