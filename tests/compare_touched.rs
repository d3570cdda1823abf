//! `persist compare --touched-baseline`: the flag quality over the pixels a hidden effect
//! touches (src/diag/compare.rs module docs).

fn persist(args: &[&str]) -> std::process::Output {
    common::persist_cmd().args(args).output().unwrap()
}

mod common;
use common::persist_ok as ok;

fn summary(dir: &std::path::Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(dir.join("summary.json")).unwrap()).unwrap()
}

#[test]
fn touched_pixels_come_from_the_truth_or_the_measurement_and_the_fractions_are_consistent() {
    let tmp = tempfile::tempdir().unwrap();
    let d = |n: &str| tmp.path().join(n).display().to_string();
    let sim = |out: &str, seed: &str, effect: Option<&str>| {
        let o = d(out);
        let mut a = vec![
            "simulate", "lab", "--size", "32", "--darks", "20", "--seed", seed, "--out", &o,
        ];
        if let Some(e) = effect {
            a.extend(["--effect", e]);
        }
        ok(&a);
    };
    sim("lab", "4", Some("populations:length_px=16"));
    sim("base", "4", None);
    sim("other", "5", None);
    std::fs::write(d("paper.json"), ok(&["model", "default"])).unwrap();
    let compare = |baseline: &str, report: &str| {
        persist(&[
            "compare",
            "--input",
            &d("lab"),
            "--model",
            &d("paper.json"),
            "--touched-baseline",
            &d(baseline),
            "--report",
            &d(report),
        ])
    };

    // the same scenario and seed without the effect: populations change trap densities,
    // so most pixels with persistence are touched
    let o = compare("base", "cmp");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let s = summary(&tmp.path().join("cmp"));
    let t = &s["touched"];
    let n_touched = t["touched_pixels"].as_u64().unwrap();
    let n_px = t["pixels_sampled"].as_u64().unwrap();
    assert!(n_touched > 0 && n_touched <= n_px, "{t}");
    assert!(t["max_difference_e_per_s"].as_f64().unwrap() > 0.01);
    assert_eq!(t["input_effects"], serde_json::json!(["populations"]));
    let m = &s["models"][0];
    for th in ["0.1", "0.01"] {
        let q = &m["flag_quality_touched"][th];
        assert_eq!(q["touched_pixels"].as_u64().unwrap(), n_touched);
        let n = q["touched_samples"].as_f64().unwrap();
        assert!(n > 0.0 && n <= m["flag_quality"][th]["samples"].as_f64().unwrap());
        let f = q["missed_flag_fraction_touched"].as_f64().unwrap();
        assert!((f - q["missed"].as_f64().unwrap() / n).abs() < 1e-12);
        assert!(q["missed"].as_u64().unwrap() <= m["flag_quality"][th]["missed"].as_u64().unwrap());
    }
    // the existing fields are still there
    assert!(m["flag_quality"]["0.1"]["missed_flag_fraction"].is_number());

    assert_eq!(t["by"], "truth");

    // a readout-only effect leaves the truths equal: the measured currents are compared
    // (it touched nothing before, so its flag quality over touched pixels was empty)
    sim("lfb", "4", Some("linefit_bias"));
    let o = persist(&[
        "compare",
        "--input",
        &d("lfb"),
        "--model",
        &d("paper.json"),
        "--touched-baseline",
        &d("base"),
        "--report",
        &d("cmp_lfb"),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let t = &summary(&tmp.path().join("cmp_lfb"))["touched"];
    assert_eq!(t["by"], "measured", "{t}");
    assert!(t["touched_pixels"].as_u64().unwrap() > 0, "{t}");
    assert!(t["max_difference_e_per_s"].as_f64().unwrap() > 0.01, "{t}");
    assert_eq!(t["input_effects"], serde_json::json!(["linefit_bias"]));

    // the input as its own baseline touches nothing
    let o = compare("lab", "self");
    assert!(o.status.success());
    let s = summary(&tmp.path().join("self"));
    assert_eq!(s["touched"]["touched_pixels"], 0);
    assert_eq!(s["touched"]["max_difference_e_per_s"], 0.0);
    assert_eq!(s["touched"]["by"], "measured");
    assert_eq!(
        s["models"][0]["flag_quality_touched"]["0.1"]["touched_samples"],
        0
    );

    // another seed is refused, naming the field and the files
    let o = compare("other", "bad");
    assert!(!o.status.success());
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(e.contains("config.seed") && e.contains("truth.json"), "{e}");

    // no summary without a baseline keeps the old layout
    ok(&[
        "compare",
        "--input",
        &d("lab"),
        "--model",
        &d("paper.json"),
        "--report",
        &d("plain"),
    ]);
    let s = summary(&tmp.path().join("plain"));
    assert!(s.get("touched").is_none());
    assert!(s["models"][0].get("flag_quality_touched").is_none());
}
