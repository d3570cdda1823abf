//! Regression for the pooled residual cells:
//! on a 64 x 64 laboratory campaign (seed 1) with the simulator's `temperature` hidden
//! (activation 0.25 eV; illuminations at 80, 78 and 82 K), `persist fit --with
//! temperature` against a reference with the knots' level at 0.85 and thirteen terms
//! from 1 s recovers the activation energy when the cells are per illumination
//! (measured 0.215 +- 0.010 eV) and not when illuminations are pooled into the same
//! fluence x time cells (0.118 +- 0.011 eV): a pooled cell compares the 95th percentile
//! of a mixture of histories with the prediction's. Measured with the levels cell
//! statistic, then the default (passed here: `--cell-statistic levels`). Only the CLI
//! opens the HDF5 files.

mod common;

use common::persist_ok;

#[test]
fn illumination_cells_recover_the_hidden_activation_energy() {
    let tmp = tempfile::tempdir().unwrap();
    let path = |name: &str| tmp.path().join(name).to_str().unwrap().to_string();
    let lab = path("lab");
    common::lab_campaign(&lab, 64, 1, &["--effect", "temperature"]);
    let rates = common::rates_13_terms();
    let fit = |out: &str, cells: &str| -> (f64, f64) {
        let out = path(out);
        persist_ok(&[
            "fit",
            "--input",
            &lab,
            "--out",
            &out,
            "--with",
            "refill",
            "--with",
            "chord",
            "--with",
            "temperature",
            "--amplification",
            "0.85",
            "--rates-per-s",
            &rates,
            "--t-min-s",
            "1",
            "--cells",
            cells,
            "--cell-statistic",
            "levels",
        ]);
        let report: serde_json::Value = serde_json::from_str(
            &std::fs::read_to_string(out.replace(".json", ".fit.json")).unwrap(),
        )
        .unwrap();
        let p = report["effects"]["params"]
            .as_array()
            .unwrap()
            .iter()
            .find(|p| p["name"] == "activation_ev")
            .unwrap()
            .clone();
        (p["value"].as_f64().unwrap(), p["sigma"].as_f64().unwrap())
    };
    let (per, per_sigma) = fit("per.json", "illumination");
    let (pooled, _) = fit("pooled.json", "pooled");
    println!("activation: per illumination {per:.3} +- {per_sigma:.3} eV, pooled {pooled:.3} eV (truth 0.25)");
    assert!((0.2..=0.3).contains(&per), "{per}");
    assert!(per_sigma > 0.0 && per_sigma < 0.03, "{per_sigma}");
    assert!(pooled < 0.15, "{pooled}");
}

/// Regression: `persist fit --with
/// temperature` under the paper's preset fits the effect against knots at 1.2 times the
/// measured level, and the activation energy takes that flagging margin in: 0.137 eV on
/// this campaign with the preset's `refill` fitted jointly (the paper's calibration
/// alone: 1.25 eV, and 1.20 eV at 128 x 128, where the flags it gives miss 1.1 % of all
/// samples at 0.1 e-/s against 0.23 % for the readout preset's). `fit` warns, naming
/// the margin and the way out; against `--preset readout` (the knots at the measured
/// level) the same fit recovers the truth's 0.25 eV (measured 0.250) and does not warn.
#[test]
fn an_effect_fitted_against_the_paper_margin_takes_it_in_and_fit_warns() {
    let tmp = tempfile::tempdir().unwrap();
    let path = |name: &str| tmp.path().join(name).to_str().unwrap().to_string();
    let lab = path("lab");
    common::lab_campaign(&lab, 64, 1, &["--effect", "temperature"]);
    let fit = |out: &str, preset: &str| -> (f64, String) {
        let out = path(out);
        let (code, stderr) = common::persist_status(&[
            "fit",
            "--input",
            &lab,
            "--out",
            &out,
            "--preset",
            preset,
            "--with",
            "temperature",
        ]);
        assert_eq!(code, Some(0), "{stderr}");
        let report = common::read_json(out.replace(".json", ".fit.json"));
        let p = report["effects"]["params"]
            .as_array()
            .unwrap()
            .iter()
            .find(|p| p["name"] == "activation_ev")
            .unwrap()["value"]
            .as_f64()
            .unwrap();
        (p, stderr)
    };
    let (paper, warned) = fit("paper.json", "paper");
    let (readout, quiet) = fit("readout.json", "readout");
    println!("activation: paper preset {paper:.3} eV, readout {readout:.3} eV (truth 0.25)");
    assert!((paper - 0.25).abs() > 0.1, "{paper}");
    assert!(
        warned.contains("flagging margin") && warned.contains("--preset readout"),
        "{warned}"
    );
    assert!((readout - 0.25).abs() < 0.03, "{readout}");
    assert!(!quiet.contains("flagging margin"), "{quiet}");
}
