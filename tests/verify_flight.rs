//! `persist verify` on a simulated sky run: the measured decay follows the simulator's
//! truth, the margin check tells a model that under-predicts this detector from one
//! scaled up to it, and an unreadable output is reported while the rest is measured.

mod common;

use common::{bin, persist_ok, read_json};
use std::path::Path;

fn run_stage(sky: &Path, root: &Path, model: &Path) {
    let out = bin()
        .args(["run", "--input"])
        .arg(sky)
        .arg("--output")
        .arg(root.join("out"))
        .arg("--checkpoints")
        .arg(root.join("ckpt"))
        .arg("--model")
        .arg(model)
        .arg("--quiet")
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

fn verify(sky: &Path, root: &Path) -> (Option<i32>, serde_json::Value, String) {
    let o = bin()
        .args(["verify", "--input"])
        .arg(sky)
        .arg("--output")
        .arg(root.join("out"))
        .arg("--report")
        .arg(root.join("report"))
        .output()
        .unwrap();
    let r = read_json(root.join("report/report.json"));
    assert!(root.join("report/report.html").is_file());
    (
        o.status.code(),
        r,
        String::from_utf8_lossy(&o.stderr).into_owned(),
    )
}

#[test]
fn verify_measures_the_truth_and_judges_the_margin_of_each_model() {
    let dir = tempfile::tempdir().unwrap();
    let sky = dir.path().join("sky");
    let s = sky.to_str().unwrap();
    persist_ok(&[
        "simulate",
        "sky",
        "--out",
        s,
        "--size",
        "96",
        "--detectors",
        "1",
        "--exposures",
        "500",
        "--seed",
        "5",
    ]);
    let default = dir.path().join("default.json");
    std::fs::write(&default, persist_ok(&["model", "default"])).unwrap();
    let mut m: serde_json::Value =
        serde_json::from_str(&persist_ok(&["model", "default"])).unwrap();
    m["name"] = "default-knots-x4".into();
    for k in m["amplitude_knots"].as_array_mut().unwrap() {
        k["amplitude_e"] = (k["amplitude_e"].as_f64().unwrap() * 4.0).into();
    }
    let scaled = dir.path().join("scaled.json");
    std::fs::write(&scaled, serde_json::to_string_pretty(&m).unwrap()).unwrap();

    let a = dir.path().join("a");
    run_stage(&sky, &a, &default);
    let (_, r, _) = verify(&sky, &a);
    assert!(r["events"].as_u64().unwrap() >= 20, "{}", r["events"]);
    assert!(r["samples"].as_u64().unwrap() >= 1000);
    let inside = r["checks"]["truth_inside"].as_array().unwrap();
    let (k, n) = (inside[0].as_f64().unwrap(), inside[1].as_f64().unwrap());
    assert!(
        n >= 10.0 && k / n >= 0.75,
        "truth inside the 95 % interval in {k} of {n} bins"
    );
    // The paper's knots (BBDet's median x 1.2) are low for the simulator's detector: its
    // true persistence in the first exposure after an event is several times the
    // prediction for more than 5 % of event pixels, and verify sees it without the truth.
    let true_p95 = r["margins"][0]["true_ratio_p95"].as_f64().unwrap();
    assert!(
        true_p95 > 2.0,
        "true 95th percentile of truth / prediction {true_p95}"
    );
    assert_eq!(
        r["checks"]["margin_verdict"], "under-predicts",
        "{}",
        r["checks"]
    );

    let b = dir.path().join("b");
    run_stage(&sky, &b, &scaled);
    let (_, r4, _) = verify(&sky, &b);
    let (m1, m4) = (
        r["checks"]["margin"][0].as_f64().unwrap(),
        r4["checks"]["margin"][0].as_f64().unwrap(),
    );
    assert!((m4 / m1 - 4.0).abs() < 0.6, "margins {m1} and {m4}");
    assert_ne!(
        r4["checks"]["margin_verdict"], "under-predicts",
        "{}",
        r4["checks"]
    );

    // One output replaced by garbage: named in the report, the rest still measured.
    let victim = std::fs::read_dir(b.join("out"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|x| x == "h5"))
        .max()
        .unwrap();
    std::fs::write(&victim, b"not hdf5").unwrap();
    let (code, r5, stderr) = verify(&sky, &b);
    assert_eq!(code, Some(1));
    let errors = r5["errors"].as_array().unwrap();
    assert_eq!(errors.len(), 1, "{errors:?}");
    assert!(
        stderr.contains(victim.file_name().unwrap().to_str().unwrap()),
        "{stderr}"
    );
    assert!(r5["samples"].as_u64().unwrap() >= 1000);
}
