//! A fast subset of the `diagnose` proof matrix (docs/validation/diagnose_matrix.md; the full
//! matrix: `cargo run --release --example diagnose_matrix`). 64 x 64 laboratory
//! campaigns, in memory.
//!
//! The test of data drawn from the fitted model was written with the defaults of then
//! (pooled cells, levels statistic, candidate-only refit) and passes them
//! ([`pooled_score_config`]); the paired-reference tests pass theirs.

use persist::calib::{self, CalibConfig};
use persist::diag::data::Sequence;
use persist::diag::diagnose::{self, Config};
use persist::sim::effect::EffectSpec;
use persist::sim::lab::{self, Illumination, LabConfig, Spots, Temperatures};
use std::path::Path;

const SIZE: usize = 64;

/// `diagnose` with pooled cells, the levels statistic, the candidate-only refit and the
/// score decision (the library's defaults are per-illumination cells, paired, a full
/// refit and the contrast decision).
fn pooled_score_config() -> Config {
    use persist::diag::eval::{CellStatistic, Cells};
    Config {
        cells: Cells::Pooled,
        cell_statistic: CellStatistic::Levels,
        refit: diagnose::Refit::Candidate,
        decide: diagnose::Decide::Score,
        ..Config::default()
    }
}

fn campaign(seed: u64, effects: &[&str]) -> Sequence {
    campaign_with_truth(seed, effects).0
}

/// The campaign and its true persistence current, one plane per exposure.
fn campaign_with_truth(seed: u64, effects: &[&str]) -> (Sequence, Vec<ndarray::Array2<f32>>) {
    campaign_of(seed, effects, Spots::Centred)
}

/// [`campaign_with_truth`] with the spots of `persist simulate lab --campaign --spots`.
fn campaign_of(seed: u64, effects: &[&str], spots: Spots) -> (Sequence, Vec<ndarray::Array2<f32>>) {
    campaign_from(seed, effects, spots.campaign())
}

/// The campaign of `illuminations` with `effects` hidden, and its true persistence
/// current.
fn campaign_from(
    seed: u64,
    effects: &[&str],
    illuminations: Vec<Illumination>,
) -> (Sequence, Vec<ndarray::Array2<f32>>) {
    let cfg = LabConfig {
        size: SIZE,
        seed,
        campaign: Some(illuminations),
        effects: effects
            .iter()
            .map(|e| e.parse::<EffectSpec>().unwrap())
            .collect(),
        ..LabConfig::default()
    };
    let (mut ex, mut truth) = (Vec::new(), Vec::new());
    lab::run(&cfg, |s| {
        ex.push(s.exposure);
        truth.push(s.true_persistence);
        Ok(())
    })
    .unwrap();
    (Sequence::from_exposures(ex).unwrap(), truth)
}

/// Data simulated from the fitted model itself (its prediction plus each exposure's
/// noise, on the simulator's illuminations): nothing is missing, so nothing may be
/// declared, and the score of every effect stays at the bootstrap's noise level. Same
/// seed, same diagnosis (byte-identical JSON).
#[test]
fn data_from_the_fitted_model_declare_nothing() {
    use persist::diag::eval::{self, Samples};
    use rand::{Rng, SeedableRng};
    let seq = campaign(3, &[]);
    let (m0, _) = calib::calibrate(&seq, &CalibConfig::default()).unwrap();
    let px: Vec<(usize, usize)> = (0..SIZE)
        .flat_map(|y| (0..SIZE).map(move |x| (y, x)))
        .collect();
    let all = Samples::with_pixels(&seq, px.clone(), 1);
    let pr = eval::predict(&m0, &seq, &all, false).unwrap();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    let mut ex = seq.exposures.clone();
    for (row, &k) in all.exposures.iter().enumerate() {
        let (b, sd) = (seq.background_e_per_s[k], seq.noise_e_per_s[k]);
        for (j, &p) in px.iter().enumerate() {
            let v = pr.current[row * px.len() + j];
            if v.is_finite() {
                let n: f64 = rng.sample(rand_distr::StandardNormal);
                ex[k].image[p] = (b + v + sd * n) as f32;
            }
        }
    }
    let model_world = Sequence::from_exposures(ex).unwrap();
    let cfg = Config {
        seed: 3,
        bootstrap: 39,
        pixels: 1024,
        ..pooled_score_config()
    };
    let run = || {
        diagnose::diagnose(
            &m0,
            &model_world,
            &cfg,
            Path::new("lab"),
            Path::new("m0.json"),
        )
        .unwrap()
    };
    let d = run();
    let text = diagnose::render(&d);
    assert!(d.ranking.iter().all(|c| !c.significant), "{text}");
    assert!(d.verdict.starts_with("no library effect"), "{text}");
    assert!(d.threshold > 1.0 && d.threshold < 20.0, "{text}");
    // Measured 2.42 (3.29 before the cells compared the measured 95th percentile with
    // the predictions' plus each sample's noise, `noisy_quantile`; on samples drawn
    // directly from a prediction the statistic now gives ~1, `eval` unit test
    // `cells_of_data_drawn_from_the_model_have_unit_rms`). What keeps this world above
    // 1 was not traced; one candidate: its measurement is `image - b_k`, with `b_k` the
    // median over background pixels, which carry the model's own small persistence.
    // Against 55-76 for the paper's model on the trap-level truth.
    assert!(d.residual_rms_normalised < 3.0, "{text}");
    assert_eq!(
        serde_json::to_string(&d).unwrap(),
        serde_json::to_string(&run()).unwrap()
    );
}

/// The normalised residual RMS of `p` over the cells of `s` (what `persist fit`
/// reports), as `spread::rss_cells` sums it.
fn cell_rms(
    p: &persist::model::ModelParams,
    seq: &Sequence,
    s: &persist::diag::eval::Samples,
) -> f64 {
    let (rss, n) = persist::diag::spread::rss_cells(p, seq, s).unwrap();
    (rss / n as f64).sqrt()
}

/// The paired reference (measured with examples/diagnose_matrix): the
/// paper's calibration with the knots' level at amplification 1.0 and thirteen terms
/// 0.4 decade apart from 1 s, plus refill, chord and `extra`, fitted jointly on the
/// stride-2 cells per illumination with the paired cell statistic (`persist fit
/// --with refill --with chord [--with EXTRA] --amplification 1.0 --rates-per-s ...
/// --t-min-s 1 --cells illumination --cell-statistic paired`).
fn paired_reference(seq: &Sequence, extra: &[&str]) -> persist::model::ModelParams {
    fit_reference(seq, &paired_config(), &["refill", "chord"], extra)
}

/// The calibration `cfg` of `seq`, then `effects` and `extra` (`--with` arguments)
/// fitted jointly on its stride-2 samples.
fn fit_reference(
    seq: &Sequence,
    cfg: &CalibConfig,
    effects: &[&str],
    extra: &[&str],
) -> persist::model::ModelParams {
    let (m0, _) = calib::calibrate(seq, cfg).unwrap();
    let names: Vec<String> = effects.iter().chain(extra).map(|s| s.to_string()).collect();
    persist::calib::effects::fit(&m0, &names, seq, &cfg.samples(seq))
        .unwrap()
        .0
}

/// The calibration options of [`paired_reference`].
fn paired_config() -> CalibConfig {
    use persist::diag::eval::{CellStatistic, Cells};
    CalibConfig {
        amplification: 1.0,
        t_min_s: 1.0,
        rates_per_s: (0..13).map(|k| 10f64.powf(-0.4 * k as f64)).collect(),
        cells: Cells::Illumination,
        cell_statistic: CellStatistic::Paired,
        ..CalibConfig::default()
    }
}

/// `diagnose --cells illumination --cell-statistic paired --refit full` (bootstrap 49
/// replicas) of `seq` against `m`, at seed 1.
fn diagnose_paired_seed_1(m: &persist::model::ModelParams, seq: &Sequence) -> diagnose::Diagnosis {
    diagnose_with(m, seq, &paired_diagnose())
}

/// `diagnose` of `seq` against `m` with `cfg`.
fn diagnose_with(
    m: &persist::model::ModelParams,
    seq: &Sequence,
    cfg: &Config,
) -> diagnose::Diagnosis {
    diagnose::diagnose(m, seq, cfg, Path::new("lab"), Path::new("m.json")).unwrap()
}

fn paired_diagnose() -> Config {
    use persist::diag::eval::{CellStatistic, Cells};
    Config {
        seed: 1,
        bootstrap: 49,
        cells: Cells::Illumination,
        cell_statistic: CellStatistic::Paired,
        refit: diagnose::Refit::Full,
        decide: diagnose::Decide::Score,
        ..Config::default()
    }
}

/// A hidden `temperature` (seed 1) against the paired reference: the issue's
/// three single-effect criteria. Declared first and significant; `fit --with` it lowers
/// the residual RMS of the stride-2 cells by about half; the missed flags at 0.1 e-/s
/// among the samples it touches are below 1 %. Measured here: score 304.9 against a
/// threshold of 7.3, dBIC -963, held-out gain 0.33, and `populations` second, also
/// significant (dBIC -521, held-out 0.37; with the rates rounded to 6 digits, as in the
/// matrix, -616 and 0.15, not significant: its fit is that fragile; with the
/// candidate-only refit it came first, dBIC -660 against temperature's -487,
/// docs/validation/diagnose_matrix.md); RMS 2.53 -> 1.21. Missed of touched after the fit: 1.4 %
/// with the image median as early release's background, 1.21 % with the quiet pixels
/// when the pixels `compare` does not read counted as quiet, 0.80 % since they do not
/// . Its specificity:
/// [`baseline_declares_nothing_against_the_paired_reference`].
#[test]
#[ignore = "long: make validation PAGES=long_tests"]
fn hidden_temperature_is_declared_against_the_paired_reference() {
    use persist::diag::eval;
    let (seq, truth) = campaign_with_truth(1, &["temperature"]);
    let m = paired_reference(&seq, &[]);
    let d = diagnose_paired_seed_1(&m, &seq);
    let text = diagnose::render(&d);
    println!("{text}");
    let first = &d.ranking[0];
    assert_eq!(first.effect, "temperature", "{text}");
    assert!(first.significant, "{text}");
    assert!(first.delta_bic.is_some_and(|b| b < -100.0), "{text}");
    let with = paired_reference(&seq, &["temperature"]);
    let s2 = paired_config().samples(&seq);
    let rms = |p: &persist::model::ModelParams| cell_rms(p, &seq, &s2);
    let (before, after) = (rms(&m), rms(&with));
    assert!(after <= 0.55 * before, "RMS {before} -> {after}");
    let (_, truth_without) = campaign_with_truth(1, &[]);
    let touched = eval::touched_samples(&s2, &truth, &truth_without);
    assert!(touched.iter().filter(|t| **t).count() > 100);
    let fl = eval::predict(&with, &seq, &s2, true).unwrap();
    let q = eval::flag_quality_of_samples(&s2, &fl.current, Some(&fl.flagged), 0.1, &touched);
    println!("{q:?}");
    assert!(q.missed_flag_fraction < 0.01, "{q:?}");
}

/// The baseline criterion at one seed against the paired reference.
#[test]
#[ignore = "long: make validation PAGES=long_tests"]
fn baseline_declares_nothing_against_the_paired_reference() {
    let seq = campaign(1, &[]);
    let d = diagnose_paired_seed_1(&paired_reference(&seq, &[]), &seq);
    let text = diagnose::render(&d);
    println!("{text}");
    assert!(d.ranking.iter().all(|c| !c.significant), "{text}");
    // the joint check runs only when asked (`--joint`)
    assert!(d.joint.is_empty(), "{text}");
}

/// Two hidden effects at once (the criterion: "both found, one per round, and the error falls
/// at each round"): `short_tau_boost` and `soak` hidden together (seed 1) against the
/// paired reference. Round 1 declares the boost; `fit --with` it; round 2, against
/// that model, declares soak; `fit --with` both. Measured by the matrix (199 bootstrap
/// replicas, measured with examples/diagnose_matrix): RMS 5.16 -> 1.80 -> 1.10, the
/// same order at seeds 2 and 3. The pair soak + temperature is found one per round on
/// the campaign with the temperatures apart
/// ([`soak_and_temperature_apart_are_found_one_per_round`]).
#[test]
#[ignore = "long: make validation PAGES=long_tests"]
fn two_hidden_effects_are_found_one_per_round() {
    let seq = campaign(1, &["short_tau_boost", "soak"]);
    let s2 = paired_config().samples(&seq);
    let rms = |p: &persist::model::ModelParams| cell_rms(p, &seq, &s2);
    let m0 = paired_reference(&seq, &[]);
    let d1 = diagnose_paired_seed_1(&m0, &seq);
    let text = diagnose::render(&d1);
    println!("{text}");
    assert_eq!(d1.ranking[0].effect, "short_tau_boost", "{text}");
    assert!(d1.ranking[0].significant, "{text}");
    let m1 = paired_reference(&seq, &["short_tau_boost"]);
    let d2 = diagnose_paired_seed_1(&m1, &seq);
    let text = diagnose::render(&d2);
    println!("{text}");
    assert_eq!(d2.ranking[0].effect, "soak", "{text}");
    assert!(d2.ranking[0].significant, "{text}");
    let m2 = paired_reference(&seq, &["short_tau_boost", "soak"]);
    let (r0, r1, r2) = (rms(&m0), rms(&m1), rms(&m2));
    println!("RMS {r0:.3} -> {r1:.3} -> {r2:.3}");
    assert!(r1 < 0.5 * r0 && r2 < 0.8 * r1, "RMS {r0} -> {r1} -> {r2}");
}

/// Two hidden effects that interact, found one per round on a campaign that shows each
/// on its own (`persist simulate lab --campaign --temperatures apart`: the 120 s x4
/// illumination at 80 K with 3 h of darks, and the 481 s x1/4 one at 82 K and at 78 K):
/// `soak` and `temperature` hidden together (seed 1) against [`readout_reference`].
/// Round 1 declares soak; `fit --with` it; round 2 declares temperature; the RMS falls
/// at each round. Measured by the matrix (199 replicas, examples/diagnose_matrix): 2.48 -> 1.46 -> 1.09, the same order at seeds 2 and 3. It
/// needs the model's soak to fill pixels with no slope and to follow the equilibrium at
/// the exposure's temperature (src/model/effects/soak.rs): without them round 2 declared
/// nothing (temperature's held-out gain 0.12).
#[test]
#[ignore = "long: make validation PAGES=long_tests"]
fn soak_and_temperature_apart_are_found_one_per_round() {
    let apart = Temperatures::Apart.apply(Spots::Centred.campaign());
    let (seq, _) = campaign_from(1, &["soak", "temperature"], apart);
    let s2 = readout_config().samples(&seq);
    let rms = |p: &persist::model::ModelParams| cell_rms(p, &seq, &s2);
    let m0 = readout_reference(&seq, &[]);
    let d1 = diagnose_paired_seed_1(&m0, &seq);
    let text = diagnose::render(&d1);
    println!("{text}");
    assert_eq!(d1.ranking[0].effect, "soak", "{text}");
    assert!(d1.ranking[0].significant, "{text}");
    let m1 = readout_reference(&seq, &["soak"]);
    let d2 = diagnose_paired_seed_1(&m1, &seq);
    let text = diagnose::render(&d2);
    println!("{text}");
    assert_eq!(d2.ranking[0].effect, "temperature", "{text}");
    assert!(d2.ranking[0].significant, "{text}");
    let m2 = readout_reference(&seq, &["soak", "temperature"]);
    let (r0, r1, r2) = (rms(&m0), rms(&m1), rms(&m2));
    println!("RMS {r0:.3} -> {r1:.3} -> {r2:.3}");
    assert!(r1 < 0.8 * r0 && r2 < 0.85 * r1, "RMS {r0} -> {r1} -> {r2}");
}

/// soak and temperature interact in the truth (examples/truth_ratios: in the 82 K
/// illumination they nearly cancel), so neither is declared alone: temperature leads by
/// score but its refit fails the gates, and soak scores nothing. `diagnose --joint`
/// refits the leader with each other library effect and must put soak first, with a
/// BIC change far past the gate against the model and against temperature alone.
/// Measured at seed 1 (release, 49 replicas): dBIC -926 and -911, RMS 3.46 -> 1.53;
/// its held-out gain is 0.19, below 0.2, so the pair is not declared (the model's soak
/// and temperature do not carry the truth's interaction). The BIC changes are those of
/// the description's least-squares fits: refined against the pixel reference the pair
/// drops `soak` (`capture_ratio` 0) and its dBIC is +35. Without `--joint` there is no
/// joint check.
#[test]
#[ignore = "long: make validation PAGES=long_tests"]
fn interacting_soak_and_temperature_are_paired_by_the_joint_check() {
    let seq = campaign(1, &["soak", "temperature"]);
    let m0 = paired_reference(&seq, &[]);
    let cfg = Config {
        joint: true,
        ..paired_diagnose()
    };
    let d = diagnose::diagnose(&m0, &seq, &cfg, Path::new("lab"), Path::new("m.json")).unwrap();
    let text = diagnose::render(&d);
    println!("{text}");
    assert!(!d.ranking.iter().any(|c| c.significant), "{text}");
    assert_eq!(d.ranking[0].effect, "temperature", "{text}");
    let j = &d.joint[0];
    assert_eq!(j.effects, ["temperature", "soak"], "{text}");
    assert!(
        j.delta_bic < -200.0 && j.delta_bic_over_leader < -200.0,
        "{text}"
    );
    assert!(j.rms_after < 0.75 * j.rms_before, "{text}");
    assert_eq!(d.joint.len(), 7, "{text}");
    assert!(j.held_out.is_some(), "{text}");
    assert!(
        j.command.contains("--with soak") && j.command.contains("--with temperature"),
        "{}",
        j.command
    );
}

/// The readout reference (measured with examples/diagnose_matrix):
/// [`paired_reference`]'s, with the `C_n` fitted to `1/(t + 0.2 s)` (Eq. (logfit)'s own
/// offset on these data, `persist::calib` "Decay offset") and the readout pinned, not
/// fitted: `chord` at strength 1 from the first read 1.5 s after the reset (`persist
/// fit --with refill --with chord:strength=1,first_read_s=1.5 --decay-offset-s 0.2 ...`).
/// `persist fit --preset readout` ([`persist::calib::Preset::Readout`]).
fn readout_reference(seq: &Sequence, extra: &[&str]) -> persist::model::ModelParams {
    let preset = persist::calib::Preset::Readout;
    fit_reference(seq, &readout_config(), preset.effects(), extra)
}

fn readout_config() -> CalibConfig {
    persist::calib::Preset::Readout.config()
}

/// The three single-effect criteria for `effect` hidden at seed 1, against
/// [`readout_reference`]: `diagnose` declares it first and significant with a refit
/// dBIC below `max_dbic`; `fit --with` it at least halves the RMS of `fit`'s stride-2
/// cells; its missed flags at 0.1 e-/s are under 1 % of the samples it touches (true
/// current changed by > 10 % and 0.01 e-/s; for an effect of the readout alone, whose
/// true current is that of the same seed without it, the measured current, same noise
/// draws).
fn meets_the_three_criteria_against_the_readout_reference(effect: &str, max_dbic: f64) {
    use persist::diag::eval::Cells;
    meets_the_three_criteria(effect, max_dbic, Spots::Centred, Cells::Illumination);
}

/// [`meets_the_three_criteria_against_the_readout_reference`] on the campaign with
/// `spots`, with `cells` for the reference, the refit and `diagnose`. Returns the
/// campaign and the same seed's campaign without the effect.
fn meets_the_three_criteria(
    effect: &str,
    max_dbic: f64,
    spots: Spots,
    cells: persist::diag::eval::Cells,
) -> (Sequence, Sequence) {
    use persist::diag::eval;
    let (seq, truth) = campaign_of(1, &[effect], spots);
    let cfg = CalibConfig {
        cells,
        ..readout_config()
    };
    let preset = persist::calib::Preset::Readout;
    let m = fit_reference(&seq, &cfg, preset.effects(), &[]);
    let d = diagnose_with(
        &m,
        &seq,
        &Config {
            cells,
            ..paired_diagnose()
        },
    );
    let text = diagnose::render(&d);
    println!("{text}");
    let first = &d.ranking[0];
    assert_eq!(first.effect, effect, "{text}");
    assert!(first.significant, "{text}");
    assert!(first.delta_bic.is_some_and(|b| b < max_dbic), "{text}");
    let with = fit_reference(&seq, &cfg, preset.effects(), &[effect]);
    let s2 = cfg.samples(&seq);
    let rms = |p: &persist::model::ModelParams| cell_rms(p, &seq, &s2);
    let (before, after) = (rms(&m), rms(&with));
    println!("RMS {before} -> {after}");
    assert!(after <= 0.5 * before, "RMS {before} -> {after}");
    let (without, truth_without) = campaign_of(1, &[], spots);
    let touched = if truth == truth_without {
        let measured = |q: &Sequence| -> Vec<ndarray::Array2<f32>> {
            q.exposures.iter().map(|e| e.image.clone()).collect()
        };
        eval::touched_samples(&s2, &measured(&seq), &measured(&without))
    } else {
        eval::touched_samples(&s2, &truth, &truth_without)
    };
    let n_touched = touched.iter().filter(|t| **t).count();
    println!("touched {n_touched} of {}", touched.len());
    assert!(n_touched > 100);
    let fl = eval::predict(&with, &seq, &s2, true).unwrap();
    let q = eval::flag_quality_of_samples(&s2, &fl.current, Some(&fl.flagged), 0.1, &touched);
    println!("{q:?}");
    assert!(q.missed_flag_fraction < 0.01, "{q:?}");
    (seq, without)
}

/// A hidden `linefit_bias` (the on-board least-squares slope instead of the chord) at
/// seed 1 against [`readout_reference`]: the three single-effect criteria.
/// Against the paired reference it was not found (its fitted `chord` strength,
/// 0.86 on the baseline, fell to 0.24 and took the least-squares slope in). Measured
/// here: score 189.7 against a threshold of 6.6, dBIC -1,732, held-out gain 0.77 (the
/// CLI, 199 replicas); RMS of the stride-2 cells 4.53 -> ~1.0.
#[test]
#[ignore = "long: make validation PAGES=long_tests"]
fn hidden_linefit_bias_is_declared_against_the_readout_reference() {
    // the effect changes the readout, not the true current: touched by the measured one
    meets_the_three_criteria_against_the_readout_reference("linefit_bias", -500.0);
}

/// The baseline criterion at one seed against [`readout_reference`].
#[test]
#[ignore = "long: make validation PAGES=long_tests"]
fn baseline_declares_nothing_against_the_readout_reference() {
    let seq = campaign(1, &[]);
    let d = diagnose_paired_seed_1(&readout_reference(&seq, &[]), &seq);
    let text = diagnose::render(&d);
    println!("{text}");
    assert!(d.ranking.iter().all(|c| !c.significant), "{text}");
}

/// A hidden `short_tau_boost` at seed 1 against [`readout_reference`]: the three
/// single-effect criteria. (Until 2026-11-24 this was pinned against the refill reference, the paper's calibration plus refill, capacity and chord with
/// the pooled levels cells; the model's `capacity` then limited each term by its own
/// held charge, and with the held-charge `capacity` that reference declares `soak` on
/// the baseline: measured with examples/diagnose_matrix.) Measured when written:
/// score 347.2 against a threshold of 8.2 (49 replicas), dBIC -1,638, held-out gain
/// 0.72; RMS of the stride-2 cells 3.47 -> 1.02; no missed flag among 462 touched
/// samples.
#[test]
#[ignore = "long: make validation PAGES=long_tests"]
fn hidden_short_tau_boost_is_declared_against_the_readout_reference() {
    meets_the_three_criteria_against_the_readout_reference("short_tau_boost", -100.0);
}

/// A hidden `blooming` (its uncollected spill: charge a saturated pinhole injects into
/// its neighbours' trap region, in no ramp; `src/sim/effects/blooming.rs`) at seed 1, on
/// the campaign with one-pixel pinholes and neighbour-contrast cells, against
/// [`readout_reference`]: the three single-effect criteria. Measured when
/// written (release, the CLI, 49 replicas): score 345.3 against a threshold of 9.5,
/// dBIC -2,539, held-out gain 0.77; `fit`'s RMS 4.54 -> 1.06, fitted `fraction` 0.215
/// (the truth's `trapped_fraction` 0.2). Also the regression it needed
/// (`neighbour_dominated_pixels_do_not_raise_the_knots`): the calibration leaves the
/// pinholes' neighbours out of its bins, so the knots below saturation are the
/// baseline's.
#[test]
#[ignore = "long: make validation PAGES=long_tests"]
fn hidden_blooming_is_declared_on_pinholes_against_the_readout_reference() {
    use persist::diag::eval::Cells;
    let (seq, without) =
        meets_the_three_criteria("blooming", -500.0, Spots::Pinholes, Cells::Neighbours);
    neighbour_dominated_pixels_do_not_raise_the_knots(&seq, &without);
}

/// The knots below saturation of the campaign with hidden blooming are within 10 % of
/// the same seed's without it. Before the calibration left neighbour-dominated pixels
/// out, the pinholes' neighbours (a quarter of the pixels of the pinhole grid) raised
/// the 95th percentile of the dim bins, the reference over-predicted every other pixel
/// (measured with examples/diagnose_matrix: at 128 x 128 the fitted `blooming`
/// then lowered the RMS 10.2 -> 10.1 only).
fn neighbour_dominated_pixels_do_not_raise_the_knots(seq: &Sequence, without: &Sequence) {
    let cfg = readout_config();
    let (hidden, rh) = calib::calibrate(seq, &cfg).unwrap();
    let (base, rb) = calib::calibrate(without, &cfg).unwrap();
    assert!(
        rh.neighbour_dominated_left_out > 100,
        "{}",
        rh.neighbour_dominated_left_out
    );
    // fewer with the effect: its collected spill raises some neighbours' own fluence
    assert!(rb.neighbour_dominated_left_out >= rh.neighbour_dominated_left_out);
    let below = |m: &persist::model::ModelParams| -> Vec<(f64, f64)> {
        m.amplitude_knots
            .iter()
            .filter(|k| k.fluence_e > 2e4 && k.fluence_e < 1.5e5)
            .map(|k| (k.fluence_e, k.amplitude_e))
            .collect()
    };
    let (h, b) = (below(&hidden), below(&base));
    assert!(h.len() > 5 && h.len() == b.len(), "{h:?} {b:?}");
    for (x, y) in h.iter().zip(&b) {
        assert!(
            (x.1 / y.1 - 1.0).abs() < 0.1,
            "knot at {} e-: {} vs {}",
            x.0,
            x.1,
            y.1
        );
    }
}
