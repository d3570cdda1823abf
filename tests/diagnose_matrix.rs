//! A fast subset of the `diagnose` proof matrix (docs/diagnose_matrix.md; the full
//! matrix: `cargo run --release --example diagnose_matrix`). 64 x 64 laboratory
//! campaigns, in memory.

use persist::calib::{self, CalibConfig};
use persist::diag::data::Sequence;
use persist::diag::diagnose::{self, Config};
use persist::sim::effect::EffectSpec;
use persist::sim::lab::{self, Illumination, LabConfig};
use std::path::Path;

const SIZE: usize = 64;

fn campaign(seed: u64, effects: &[&str]) -> Sequence {
    let cfg = LabConfig {
        size: SIZE,
        seed,
        campaign: Some(Illumination::default_campaign()),
        effects: effects
            .iter()
            .map(|e| e.parse::<EffectSpec>().unwrap())
            .collect(),
        ..LabConfig::default()
    };
    let mut ex = Vec::new();
    lab::run(&cfg, |s| {
        ex.push(s.exposure);
        Ok(())
    })
    .unwrap();
    Sequence::from_exposures(ex).unwrap()
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
        ..Config::default()
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

/// The reference of docs/diagnose_matrix.md ("the matrix against the reference without
/// fitted `C_n`"): the paper's calibration plus refill, capacity and chord, fitted
/// jointly on the stride-2 cells with the paper's `C_n` (`persist fit --with refill
/// --with capacity --with chord`).
fn reference(seq: &Sequence) -> persist::model::ModelParams {
    let (m0, _) = calib::calibrate(seq, &CalibConfig::default()).unwrap();
    let names: Vec<String> = ["refill", "capacity", "chord"].map(String::from).to_vec();
    let s2 = persist::diag::eval::Samples::new(seq, 2);
    persist::calib::effects::fit(&m0, &names, seq, &s2)
        .unwrap()
        .0
}

/// `diagnose` (bootstrap 49 replicas instead of 199; otherwise its defaults) of the
/// seed-1 campaign with `effects` hidden, against its own [`reference`].
fn diagnose_against_reference(effects: &[&str]) -> diagnose::Diagnosis {
    let seq = campaign(1, effects);
    let m = reference(&seq);
    let cfg = Config {
        seed: 1,
        bootstrap: 49,
        ..Config::default()
    };
    diagnose::diagnose(&m, &seq, &cfg, Path::new("lab"), Path::new("m.json")).unwrap()
}

/// A hidden `short_tau_boost` (seed 1) is declared first and significant against the
/// reference with the paper's `C_n` (measured in the sixth session: score 67.4 against
/// a threshold of 3.2, refit dBIC -125.7, held-out gain 0.33; the same campaign declared
/// nothing against the reference with fitted `C_n`). Its specificity is pinned by
/// [`baseline_declares_nothing_against_the_paper_c_n_reference`].
#[test]
fn hidden_short_tau_boost_is_declared_first_against_the_paper_c_n_reference() {
    let d = diagnose_against_reference(&["short_tau_boost"]);
    let text = diagnose::render(&d);
    println!("{text}");
    let first = &d.ranking[0];
    assert_eq!(first.effect, "short_tau_boost", "{text}");
    assert!(first.significant, "{text}");
    assert!(first.delta_bic.is_some_and(|b| b < -50.0), "{text}");
    let h = first
        .held_out
        .as_ref()
        .expect("several illumination events");
    assert!(h.gain >= 0.25 && h.gain_moved_cells > h.gain, "{text}");
}

/// The baseline criterion at one seed: the campaign of the same seed with
/// nothing hidden declares nothing against its own reference (9 of 10 seeds in the
/// sixth session's matrix; seed 5 declares `populations`).
#[test]
fn baseline_declares_nothing_against_the_paper_c_n_reference() {
    let d = diagnose_against_reference(&[]);
    let text = diagnose::render(&d);
    println!("{text}");
    assert!(d.ranking.iter().all(|c| !c.significant), "{text}");
}
