//! `soak` in the flagging model is relative to the calibration illumination
//! (`persist::model::effects::soak`, "Relative to the calibration illumination"):
//! `persist fit --with soak` on the paper's calibration records the first
//! illumination's timing as the reference; `persist run` then predicts the darks after
//! that illumination as without `soak` (its calibrated response and margin kept), and
//! lower after the shorter illumination. The absolute form (reference 0, as a fit
//! whose decay law is given, `--preset readout`, keeps it) lowers the calibration
//! illumination's darks too; a fit that measures the decay law on the first
//! illumination (`--fit-decay-exponent`, as `diagnose`'s description does) is relative
//! as well. 32 x 32 laboratory campaign, seed 1 (illuminations of
//! 481 s at exposure 0, 240 s at 21 and 32, 120 s at 43, 481 s at 64).

mod common;

use common::{persist_ok, read_json};
use std::path::Path;

/// The predicted persistence current of every output of `persist run` with `model`.
fn run_currents(lab: &str, dir: &Path, model: &str) -> Vec<ndarray::Array2<f32>> {
    let (out, ck) = (dir.join("out"), dir.join("ck"));
    persist_ok(&[
        "run",
        "--input",
        lab,
        "--output",
        out.to_str().unwrap(),
        "--checkpoints",
        ck.to_str().unwrap(),
        "--model",
        model,
        "--quiet",
    ]);
    // the outputs in exposure order (their names carry the index)
    walkdir::WalkDir::new(&out)
        .sort_by_file_name()
        .into_iter()
        .map(|e| e.unwrap().into_path())
        .filter(|p| p.extension().is_some_and(|x| x == "h5"))
        .map(|p| persist::product::read_output(&p).unwrap().1.current_e_per_s)
        .collect()
}

/// Median over exposures `ks` and pixels predicted above 0.01 e-/s by `base` of
/// `other / base`.
fn median_ratio(
    base: &[ndarray::Array2<f32>],
    other: &[ndarray::Array2<f32>],
    ks: std::ops::Range<usize>,
) -> f64 {
    let mut r: Vec<f64> = ks
        .flat_map(|k| {
            base[k]
                .iter()
                .zip(other[k].iter())
                .filter(|(b, _)| **b > 0.01)
                .map(|(b, o)| f64::from(*o) / f64::from(*b))
                .collect::<Vec<_>>()
        })
        .collect();
    assert!(r.len() > 100, "{} samples", r.len());
    r.sort_by(f64::total_cmp);
    r[r.len() / 2]
}

#[test]
fn the_flagging_model_keeps_the_calibration_illumination() {
    let tmp = tempfile::tempdir().unwrap();
    let path = |name: &str| tmp.path().join(name).to_str().unwrap().to_string();
    let lab = path("lab");
    common::lab_campaign(&lab, 32, 1, &[]);
    // the effect's reference illumination, not the flags' coverage margin (which each
    // model derives for itself)
    let quiet = ["--log-level", "warn", "--no-coverage"];
    let fit = |out: &str, extra: &[&str]| {
        persist_ok(&[&["fit", "--input", &lab, "--out", out][..], extra, &quiet].concat());
    };
    let (m0, rel, abs, md, mp) = (
        path("m0.json"),
        path("rel.json"),
        path("abs.json"),
        path("md.json"),
        path("mp.json"),
    );
    fit(&m0, &[]);
    fit(&rel, &["--with", "soak:capture_ratio=0.05"]);
    fit(
        &abs,
        &["--with", "soak:capture_ratio=0.05,reference_lit_s=0"],
    );
    fit(
        &md,
        &["--preset", "readout", "--with", "soak:capture_ratio=0.05"],
    );
    fit(
        &mp,
        &[
            "--preset",
            "readout",
            "--fit-decay-exponent",
            "--with",
            "soak:capture_ratio=0.05",
        ],
    );
    let soak = |m: &str| {
        read_json(m)["effects"]
            .as_array()
            .unwrap()
            .iter()
            .find(|e| e["name"] == "soak")
            .cloned()
            .unwrap()
    };
    // the reference: the first illumination, lit 481 s of a 613 s integration
    let p = &soak(&rel)["params"];
    assert_eq!(p["reference_lit_s"].as_f64(), Some(481.0), "{p}");
    assert_eq!(p["reference_exposure_s"].as_f64(), Some(613.0), "{p}");
    // the decay law given: absolute; measured on the first illumination: relative
    assert_eq!(soak(&md)["params"]["reference_lit_s"].as_f64(), Some(0.0));
    assert_eq!(soak(&mp)["params"]["reference_lit_s"].as_f64(), Some(481.0));

    let dir = |n: &str| {
        let d = tmp.path().join(n);
        std::fs::create_dir_all(&d).unwrap();
        d
    };
    let c0 = run_currents(&lab, &dir("r0"), &m0);
    let c_rel = run_currents(&lab, &dir("rrel"), &rel);
    let c_abs = run_currents(&lab, &dir("rabs"), &abs);
    // darks after the calibration illumination (exposures 2-20): relative kept (the
    // darks' own small charge is held for their whole integration, not as the
    // reference's, hence not exactly 1), absolute lowered
    let after_cal_rel = median_ratio(&c0, &c_rel, 2..21);
    let after_cal_abs = median_ratio(&c0, &c_abs, 2..21);
    assert!(
        (after_cal_rel - 1.0).abs() < 0.01,
        "relative: {after_cal_rel}"
    );
    assert!(after_cal_abs < 0.9, "absolute: {after_cal_abs}");
    // after the 120 s illumination (exposures 45-63): lower with the relative form
    let after_short = median_ratio(&c0, &c_rel, 45..64);
    assert!(after_short < 0.97, "after 120 s: {after_short}");
}
