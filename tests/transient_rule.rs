//! The transient rule measured in flight (`persist verify`'s `transients`, `persist fit
//! --from-verify`, docs/verify.md "The transient rule"): from a sky without cosmic rays
//! there is no rule, and the fit refuses and says why; from a sky with them, the rule
//! written into the model names the report it came from.

mod common;

use common::{bin, persist_ok, read_json};
use std::path::Path;

/// Simulate a 32 x 32 sky of 60 exposures at `cosmic_rate` hits per cm^2 per s, flag it
/// with the built-in default model and verify it; returns the report's path.
fn measured_sky(root: &Path, cosmic_rate: &str) -> std::path::PathBuf {
    let sky = root.join("sky");
    persist_ok(&[
        "simulate",
        "sky",
        "--out",
        sky.to_str().unwrap(),
        "--size",
        "32",
        "--detectors",
        "1",
        "--exposures",
        "60",
        "--seed",
        "3",
        "--cosmic-rate",
        cosmic_rate,
    ]);
    persist_ok(&[
        "run",
        "--input",
        sky.to_str().unwrap(),
        "--output",
        root.join("out").to_str().unwrap(),
        "--checkpoints",
        root.join("ckpt").to_str().unwrap(),
        "--quiet",
    ]);
    let report = root.join("report");
    // verify's exit code judges the saturating events; only its report is used here
    let o = bin()
        .args(["verify", "--input"])
        .arg(&sky)
        .arg("--output")
        .arg(root.join("out"))
        .arg("--report")
        .arg(&report)
        .output()
        .unwrap();
    assert!(o.status.code().is_some(), "{o:?}");
    report.join("report.json")
}

fn fit_from_verify(report: &Path, out: &Path) -> std::process::Output {
    bin()
        .args(["fit", "--from-verify"])
        .arg(report)
        .arg("--out")
        .arg(out)
        .output()
        .unwrap()
}

#[test]
fn without_cosmic_rays_the_fit_refuses_and_says_why() {
    let dir = tempfile::tempdir().unwrap();
    let report = measured_sky(dir.path(), "0");
    let r = read_json(&report);
    assert_eq!(r["transients"]["hits"], 0, "{}", r["transients"]);
    assert!(r["transients"]["rule"]
        .as_str()
        .unwrap()
        .starts_with("no rule"));
    let model = dir.path().join("model.json");
    let o = fit_from_verify(&report, &model);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "{err}");
    assert!(
        err.contains("0 hits") && err.contains("needs 200") && err.contains("report.json"),
        "{err}"
    );
    assert!(!model.exists(), "nothing written on refusal");
}

#[test]
fn with_cosmic_rays_the_rule_is_measured_and_names_its_report() {
    let dir = tempfile::tempdir().unwrap();
    // 50 hits per cm^2 per s: about 0.018 of the pixels per 112 s exposure, ~1000 hits
    let report = measured_sky(dir.path(), "50");
    let r = read_json(&report);
    let first = &r["transients"]["first"];
    assert!(first["events"].as_u64().unwrap() >= 200, "{first}");
    let model = dir.path().join("model.json");
    let o = fit_from_verify(&report, &model);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let m = read_json(&model);
    let t = &m["transient"];
    let bytes = std::fs::read(&report).unwrap();
    assert_eq!(
        t["measured"]["report_sha256"],
        persist::model::params::sha256_hex(&bytes)
    );
    assert_eq!(t["measured"]["events"], first["events"]);
    // the simulated hits leave no persistence of their own: what the first exposure
    // measures is noise and sources. The rule takes the noise out of the measured
    // quantile (its interval's upper end): it lands nearer the truth's quantile than
    // the noisy one, and far below the table's maximum (878 e-)
    let ratio = t["measured"]["ratio"].as_f64().unwrap();
    let noisy = first["ratio"][2].as_f64().unwrap();
    let truth = first["true_ratio"].as_f64().unwrap();
    assert!(ratio <= noisy, "{ratio} {first}");
    assert!(
        (ratio - truth).abs() < (noisy - truth).abs(),
        "{ratio} {first}"
    );
    let a = t["amplitude_e"].as_f64().unwrap();
    assert!((0.0..0.2 * 878.0).contains(&a), "{t}");
    // the model loads, and runs
    persist::model_file::load(&model).unwrap();
}
