//! `persist fit --fit-cn`: on a 64 x 64 simulated laboratory campaign (seed 1), fitting
//! the six `C_n` jointly with the reference effects (refill, capacity, chord) lowers the
//! fit's normalised residual RMS to at most 80 % of the paper's `C_n`'s (measured:
//! 8.15 -> 5.18), the fitted `C_n` are positive and finite, the `tau_n` unchanged, the
//! report says which were fitted and the model's description records `--fit-cn`.
//! Without `--fit-cn` the report has no `c_n` and the model keeps the paper's
//! calibration. Only the CLI opens the HDF5 files.
//!
//! `persist fit --fit-amplification` on the same campaign: one common factor of the
//! knots, below 1 (the paper's 1.2 is a flagging margin; measured 0.752, i.e. an
//! amplification of 0.90, with refill and chord), every knot the calibration's times
//! that factor, a lower residual than the reference's; refused with `--fit-cn`.
//!
//! Measured on the pooled cells with the levels statistic (passed here,
//! [`common::POOLED_LEVELS_CELLS`]).

mod common;

use common::{persist_ok, read_json};

#[test]
fn fit_cn_lowers_the_residual_with_positive_finite_cn() {
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path();
    let path = |name: &str| d.join(name).to_str().unwrap().to_string();
    let (lab, ref_json, cn_json) = (path("lab"), path("ref.json"), path("cn.json"));
    common::lab_campaign(&lab, 64, 1, &[]);
    // the calibration's fit of the measurements, not the flags' coverage margin
    let with = [
        "--with",
        "refill",
        "--with",
        "capacity",
        "--with",
        "chord",
        "--no-coverage",
    ];
    let mut a = vec!["fit", "--input", &lab, "--out", &ref_json];
    a.extend(with);
    a.extend(common::POOLED_LEVELS_CELLS);
    persist_ok(&a);
    let mut a = vec!["fit", "--input", &lab, "--out", &cn_json, "--fit-cn"];
    a.extend(with);
    a.extend(common::POOLED_LEVELS_CELLS);
    let text = persist_ok(&a);
    println!("{text}");

    let (r0, r1) = (
        read_json(d.join("ref.fit.json")),
        read_json(d.join("cn.fit.json")),
    );
    let rms0 = r0["residual_rms_normalised"].as_f64().unwrap();
    let rms1 = r1["residual_rms_normalised"].as_f64().unwrap();
    println!("residual RMS: paper C_n {rms0:.3}, fitted C_n {rms1:.3}");
    assert!(rms1.is_finite() && rms1 <= 0.8 * rms0, "{rms0} -> {rms1}");
    assert!(r0["effects"].get("c_n").is_none());

    // the report: the six terms, fitted from the paper's C_n, with an uncertainty
    let (m0, m1) = (read_json(d.join("ref.json")), read_json(d.join("cn.json")));
    let paper = r0["calibration"]["c_n"]["terms"].as_array().unwrap();
    let t0 = m0["terms"].as_array().unwrap();
    assert_eq!(
        t0, paper,
        "without --fit-cn the model keeps the paper's C_n"
    );
    let terms = m1["terms"].as_array().unwrap();
    let rep = r1["effects"]["c_n"]["terms"].as_array().unwrap();
    assert_eq!(terms.len(), 6);
    assert_eq!(rep.len(), 6);
    let mut moved = 0;
    for (n, ((t, r), p)) in terms.iter().zip(rep).zip(paper).enumerate() {
        let c = t["c_per_s"].as_f64().unwrap();
        assert!(c.is_finite() && c > 0.0, "C_{n} = {c}");
        assert_eq!(t["rate_per_s"], p["rate_per_s"], "tau_{n} must stay");
        assert_eq!(r["c_per_s"].as_f64().unwrap(), c);
        assert_eq!(r["c_start_per_s"], p["c_per_s"]);
        assert!(r["sigma_ln_c"].as_f64().is_some_and(|s| s >= 0.0), "{r}");
        if (c / p["c_per_s"].as_f64().unwrap() - 1.0).abs() > 0.05 {
            moved += 1;
        }
    }
    assert!(moved >= 2, "the C_n did not move: {rep:?}");
    // the model file says its C_n were fitted to the campaign (diagnose reads it)
    let desc = |m: &serde_json::Value| m["description"].as_str().unwrap().to_string();
    assert!(
        desc(&m1).ends_with(persist::calib::FIT_CN_NOTE),
        "{}",
        desc(&m1)
    );
    assert!(!desc(&m0).contains("--fit-cn"), "{}", desc(&m0));
    assert!(text.contains("terms.c_per_s[0]"), "{text}");

    // --fit-amplification
    let amp_json = path("amp.json");
    let mut a = vec![
        "fit",
        "--input",
        &lab,
        "--out",
        &amp_json,
        "--with",
        "refill",
        "--with",
        "chord",
        "--fit-amplification",
    ];
    a.extend(common::POOLED_LEVELS_CELLS);
    let text = persist_ok(&a);
    println!("{text}");
    let (ma, ra) = (
        read_json(d.join("amp.json")),
        read_json(d.join("amp.fit.json")),
    );
    let scale: Vec<&serde_json::Value> = ra["effects"]["params"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|p| p["effect"] == "knots" && p["name"] == "scale")
        .collect();
    assert_eq!(scale.len(), 1, "{ra}");
    let s = scale[0]["value"].as_f64().unwrap();
    assert!(s > 0.5 && s < 0.95, "knot scale {s}");
    assert!(scale[0]["sigma"]
        .as_f64()
        .is_some_and(|v| v > 0.0 && v < 0.1));
    // against the calibration's own knots (this fit's report)
    let calibrated = ra["calibration"]["knots"].as_array().unwrap();
    assert_eq!(
        calibrated.len(),
        ma["amplitude_knots"].as_array().unwrap().len()
    );
    for (k0, k1) in calibrated
        .iter()
        .zip(ma["amplitude_knots"].as_array().unwrap())
    {
        assert_eq!(k0["fluence_e"], k1["fluence_e"]);
        let (a0, a1) = (
            k0["amplitude_e"].as_f64().unwrap(),
            k1["amplitude_e"].as_f64().unwrap(),
        );
        assert!(
            (a1 - s * a0).abs() <= 1e-12 * a0.abs().max(1.0),
            "{a0} {a1} {s}"
        );
    }
    let rmsa = ra["residual_rms_normalised"].as_f64().unwrap();
    assert!(rmsa < rms0, "{rms0} -> {rmsa}");
    assert!(desc(&ma).contains("--fit-amplification"), "{}", desc(&ma));
    let x = path("x.json");
    let (code, err) = common::persist_status(&[
        "fit",
        "--input",
        &lab,
        "--out",
        &x,
        "--fit-amplification",
        "--fit-cn",
    ]);
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("--fit-amplification"), "{err}");
}
