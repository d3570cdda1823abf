//! A two-day sky run at reduced size, processed by the stage with the default
//! model. The paper's simulation reports "a minimum of 2%" of pixels above 0.1 e-/s at
//! all times and a floor above 0.01 e-/s for every pixel; this checks the first (order of
//! magnitude) and that the second is *not* reproduced, neither by the prediction nor by
//! the simulator's truth (README, docs/validation/floor_scan.md: no realistic star count or cosmic-ray
//! rate gives both).

use persist::demo::{run, DemoConfig};

#[test]
fn two_day_sky_run_flags_a_steady_percent_or_two() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = DemoConfig {
        out: tmp.path().join("demo"),
        size: 64,
        exposures: 1143,
        seed: 3,
        model: Some(persist::model::ModelParams::default()),
        ..DemoConfig::default()
    };
    let r = run(&cfg, &|_| {}).unwrap();
    assert_eq!(r.errors, 0);
    assert_eq!(r.rows.len(), 1143);
    let last = r.rows.last().unwrap();
    assert!((47.0..49.0).contains(&last.t_hours), "{}", last.t_hours);
    // Steady fraction above 0.1 e-/s after 6 h: the paper's order, 2%.
    assert!(
        (0.002..0.06).contains(&r.steady_frac_high),
        "steady fraction above 0.1 e-/s: {}",
        r.steady_frac_high
    );
    // The low-threshold fraction is larger, and the flags never vanish after 6 h.
    assert!(r.steady_frac_low > r.steady_frac_high);
    assert!(r
        .rows
        .iter()
        .filter(|row| row.t_hours > 6.0)
        .all(|row| row.frac_high > 0.0));
    // The truth is counted too: the flagging is conservative (more pixels predicted above
    // 0.1 e-/s than truly are), and the median pixel's current, the "floor", comes from
    // the zodiacal light: predicted a few 1e-3 e-/s (the paper: "a minimum of 0.002"),
    // true lower still, both below 0.01 e-/s. So most pixels stay below 0.01 e-/s.
    assert!(
        r.steady_true_frac_high < r.steady_frac_high,
        "true {} predicted {}",
        r.steady_true_frac_high,
        r.steady_frac_high
    );
    assert!(
        (0.001..0.01).contains(&r.steady_median_pred_e_per_s),
        "predicted floor {}",
        r.steady_median_pred_e_per_s
    );
    assert!(
        r.steady_median_true_e_per_s < r.steady_median_pred_e_per_s,
        "true floor {}",
        r.steady_median_true_e_per_s
    );
    assert!(r.steady_frac_low < 0.5, "{}", r.steady_frac_low);
    assert!(r.steady_true_frac_low < 0.5, "{}", r.steady_true_frac_low);
    // Cosmic rays arrive at the configured rate (5 /cm^2/s on 18 um pixels, 112 s):
    // TRANSIENT on 0.18% of pixels per exposure.
    let p_cr = cfg.sky.detector.cosmic_probability(cfg.sky.t_exposure_s);
    let transient = r.rows.iter().map(|w| w.frac_transient).sum::<f64>() / r.rows.len() as f64;
    assert!(
        (transient / p_cr - 1.0).abs() < 0.1,
        "{transient} vs {p_cr}"
    );
    assert!(r.rows.iter().any(|w| w.frac_saturated > 0.0));
    // The traced pixel saturated, and the model saw it: predicted above 0.1 e-/s after.
    assert!(r.pixel_event_fluence_e > 2e5, "{}", r.pixel_event_fluence_e);
    let after = r
        .pixel_trace
        .iter()
        .skip(r.pixel_event_index as usize + 1)
        .take(5);
    assert!(
        after.clone().all(|t| t.1 > 0.1),
        "{:?}",
        after.collect::<Vec<_>>()
    );
    for p in &r.plots {
        assert!(std::fs::metadata(p).unwrap().len() > 10_000);
    }
}

/// Without a model the demo follows the paper's workflow into flight: the laboratory
/// model (`lab_model.json`, no transient rule) flags the sky's first 200 exposures,
/// `persist verify` measures what follows the cosmic-ray hits, and the sky is flagged
/// with the model that carries the rule it measured (`model.json`), whose provenance
/// names the report. Of its counted pixel-exposures truly at 0.2 e-/s or more, none
/// goes unflagged at 0.1 e-/s.
#[test]
fn the_paper_s_workflow_measures_the_transient_rule_in_flight() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("demo");
    let cfg = DemoConfig {
        out: out.clone(),
        size: 64,
        exposures: 1143,
        seed: 2,
        ..DemoConfig::default()
    };
    let r = run(&cfg, &|_| {}).unwrap();
    assert_eq!(r.errors, 0);
    let load = |name: &str| persist::model_file::load(&out.join(name)).unwrap();
    let (lab, flown) = (load("lab_model.json"), load("model.json"));
    assert!(lab.transient.is_none());
    let rule = flown.transient.as_ref().expect("a rule measured in flight");
    assert!(rule.measured.events >= 200, "{rule:?}");
    assert_eq!(rule.measured.flown_amplitude_e, lab.transient_amplitude_e());
    assert!(rule.measured.report.ends_with("report.json"), "{rule:?}");
    assert!(
        r.model_source.contains("transient rule measured in flight"),
        "{}",
        r.model_source
    );
    // the flags' promise at 0.1 e-/s, none missed above 0.2 e-/s: of the counted
    // pixel-exposures truly at twice the threshold or more, none goes unflagged
    let high = &r.flag_quality.high;
    assert!(high.above[2] + high.above[3] > 100, "{high:?}");
    assert_eq!(high.missed[2] + high.missed[3], 0, "{high:?}");
}
