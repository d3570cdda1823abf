//! `persist fit` on laboratory sequences where every pixel is lit (the paper's own
//! laboratory data: a pinhole spot, a leak along one edge, tens of e-/s everywhere
//! else; `persist simulate lab --spots paper`): the dark level comes from each pixel's
//! late darks (`persist::calib::dark`), and the paper's numbers come back within the
//! tolerances of tests/fit_paper.rs (Table 1 within 25 % below and deep in saturation,
//! C_n within 10 % of 1/(t+1)). What the data lack is said precisely: nothing lit, no
//! ramp, darks that stop too soon.

mod common;

use persist::calib::dark::DarkSource;
use persist::calib::{calibrate, CalibConfig};
use persist::diag::data::Sequence;
use persist::model::params::PAPER_TABLE1_A_BIN;

/// Every pixel lit, one illumination, 14 h of darks: the late plateau calibrates, and
/// Table 1 (below and deep in saturation) comes back within 25 %, as in
/// tests/fit_paper.rs; with a masked corner the background pixels are used instead.
#[test]
fn every_pixel_lit_calibrates_from_the_late_plateau() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("lab");
    common::simulate_lab(&dir, "128", &["--spots", "paper"]);
    let seq = Sequence::load(&dir).unwrap();
    let (params, rep) = calibrate(&seq, &CalibConfig::default()).unwrap();
    assert_eq!(rep.dark_level.source, DarkSource::LatePlateau);
    let r = rep.dark_level.late_fraction_max.unwrap();
    assert!(r > 0.0 && r < 0.02, "{r}");
    // the simulator's dark current is 0.01 e-/s
    assert!(
        rep.dark_level.median_e_per_s.abs() < 0.05,
        "{:?}",
        rep.dark_level
    );
    let mut worst: f64 = 0.0;
    for (f, a_paper) in PAPER_TABLE1_A_BIN {
        let a = common::a_bin_at(&rep.bins, f);
        let rel = a / a_paper - 1.0;
        println!(
            "Table 1 fluence {f:>9.0} e-: A_bin {a:7.1} e-, paper {a_paper:6.1} e-, {:+.1} %",
            100.0 * rel
        );
        if f == 401_000.0 || f == 3_833_000.0 {
            worst = worst.max(rel.abs());
        }
    }
    assert!(worst < 0.25, "{worst}");
    assert!(rep.c_n.max_relative_error < 0.10, "{:?}", rep.c_n);
    let rec = params.calibration.unwrap();
    assert!(rec.late_plateau_dark);

    let dir2 = tmp.path().join("lab_dark");
    common::simulate_lab(&dir2, "128", &["--spots", "paper", "--dark-pixels"]);
    let seq2 = Sequence::load(&dir2).unwrap();
    let (_, rep2) = calibrate(&seq2, &CalibConfig::default()).unwrap();
    assert_eq!(rep2.dark_level.source, DarkSource::BackgroundPixels);
    // the two dark levels give knots within 10 % of each other below saturation
    let (a, b) = (
        common::a_bin_at(&rep.bins, 101_000.0),
        common::a_bin_at(&rep2.bins, 101_000.0),
    );
    assert!((a / b - 1.0).abs() < 0.10, "{a} {b}");
}

/// Several illuminations, and darks of varying length after the later ones: the block
/// after the first illumination (1 h of 180 s darks) sets the dark level.
#[test]
fn campaigns_with_every_pixel_lit_calibrate() {
    let tmp = tempfile::tempdir().unwrap();
    for (name, extra) in [
        ("campaign", vec!["--campaign", "--spots", "paper"]),
        (
            "varied",
            vec!["--campaign", "--spots", "paper", "--dark-lengths", "varied"],
        ),
    ] {
        let dir = tmp.path().join(name);
        common::simulate_lab(&dir, "64", &extra);
        let seq = Sequence::load(&dir).unwrap();
        let (_, rep) =
            calibrate(&seq, &CalibConfig::default()).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!(rep.dark_level.source, DarkSource::LatePlateau, "{name}");
        let r = rep.dark_level.late_fraction_max.unwrap();
        assert!(r > 0.01 && r < 0.2, "{name}: {r}");
        assert!(!rep.knots.is_empty(), "{name}");
        let a = common::a_bin_at(&rep.bins, 101_000.0);
        assert!((a / 54.1 - 1.0).abs() < 0.35, "{name}: {a}");
    }
}

/// What the data lack, said precisely: nothing lit; no ramp in the first dark; darks
/// that stop before persistence has decayed, with no unlit pixel.
#[test]
fn missing_data_are_named() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("short");
    common::simulate_lab(&dir, "64", &["--spots", "paper", "--darks", "3"]);
    let seq = Sequence::load(&dir).unwrap();
    let e = calibrate(&seq, &CalibConfig::default())
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("no background pixel") && e.contains("darks"),
        "{e}"
    );

    // nothing lit
    let mut ex = Sequence::load(&dir).unwrap().exposures;
    ex[0].image.fill(0.01);
    let e = calibrate(
        &Sequence::from_exposures(ex).unwrap(),
        &CalibConfig::default(),
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("nothing was lit") && e.contains("image"), "{e}");

    // no ramp
    let mut ex = Sequence::load(&dir).unwrap().exposures;
    ex[1].ramp = None;
    ex[1].ramp_times_s = None;
    let e = calibrate(
        &Sequence::from_exposures(ex).unwrap(),
        &CalibConfig::default(),
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("ramp"), "{e}");
}

/// The model file that `persist fit` writes from all-lit data (it records where the
/// dark level came from) is a valid model file: `persist compare` reads it back.
#[test]
fn the_all_lit_model_file_is_read_back() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("lab");
    common::simulate_lab(&dir, "48", &["--spots", "paper"]);
    let model = tmp.path().join("m.json");
    common::persist_ok(&[
        "fit",
        "--input",
        dir.to_str().unwrap(),
        "--out",
        model.to_str().unwrap(),
    ]);
    let m = common::read_json(&model);
    assert_eq!(m["calibration"]["late_plateau_dark"], true, "{m}");
    common::persist_ok(&[
        "compare",
        "--input",
        dir.to_str().unwrap(),
        "--model",
        model.to_str().unwrap(),
        "--report",
        tmp.path().join("report").to_str().unwrap(),
    ]);
}

/// The dark level and read noise of one exposure from the truth: the median and 1.4826
/// MAD of `image - true_persistence` over its unflagged pixels.
fn truth_dark_and_noise(dir: &std::path::Path, k: u64) -> (f64, f64) {
    let name = format!("d1_e{k:06}");
    let img = hdf5::File::open(dir.join(format!("{name}.h5"))).unwrap();
    let image = img.dataset("image").unwrap().read_2d::<f32>().unwrap();
    let flags = img.dataset("flags").unwrap().read_2d::<u32>().unwrap();
    let truth = hdf5::File::open(dir.join("truth").join(format!("{name}.truth.hdf5"))).unwrap();
    let pers = truth
        .dataset("true_persistence")
        .unwrap()
        .read_2d::<f32>()
        .unwrap();
    let r: Vec<f64> = image
        .iter()
        .zip(&pers)
        .zip(&flags)
        .filter(|((v, _), f)| **f == 0 && v.is_finite())
        .map(|((v, p), _)| f64::from(*v - *p))
        .collect();
    let med = persist::stats::median(&r);
    let dev: Vec<f64> = r.iter().map(|v| (v - med).abs()).collect();
    (med, 1.4826 * persist::stats::median(&dev))
}

/// With every pixel lit there is no background pixel: the read noise comes from pairs
/// of consecutive late darks and the dark level from the lowest-fluence pixels' late
/// darks tending as 1/t (`persist::measure::data`, "Every pixel lit"). Both agree with
/// the truth of the two generators (the simulator's paper pattern, and the second
/// generator's single illumination at two seeds, each its own detector): noise within
/// 15 %, dark level within 0.003 e-/s (a tenth of the read noise).
#[test]
fn lit_sequences_measure_noise_and_dark_level_from_the_darks() {
    let tmp = tempfile::tempdir().unwrap();
    let bin = env!("CARGO_BIN_EXE_persist");
    let runs: Vec<(String, Vec<String>)> = vec![
        (
            "lab".into(),
            [
                "simulate", "lab", "--size", "64", "--spots", "paper", "--darks", "120",
            ]
            .map(String::from)
            .to_vec(),
        ),
        (
            "family1".into(),
            ["simulate", "family", "--size", "64", "--seed", "1"]
                .map(String::from)
                .to_vec(),
        ),
        (
            "family2".into(),
            ["simulate", "family", "--size", "64", "--seed", "2"]
                .map(String::from)
                .to_vec(),
        ),
    ];
    for (name, args) in runs {
        let dir = tmp.path().join(&name);
        let st = std::process::Command::new(bin)
            .args(&args)
            .arg("--out")
            .arg(&dir)
            .output()
            .unwrap();
        assert!(
            st.status.success(),
            "{name}: {}",
            String::from_utf8_lossy(&st.stderr)
        );
        let seq = Sequence::load(&dir).unwrap();
        assert!(!seq.lit.is_empty(), "{name}: every pixel is lit");
        let last = seq.exposures.len() - 1;
        let (dark, noise) = truth_dark_and_noise(&dir, seq.exposures[last].meta.exposure_index);
        let (b, s) = (seq.background_e_per_s[last], seq.noise_e_per_s[last]);
        println!("{name}: dark {b:.4} (truth {dark:.4}), noise {s:.4} (truth {noise:.4})");
        assert!(
            (s / noise - 1.0).abs() < 0.15,
            "{name}: noise {s} against {noise}"
        );
        assert!((b - dark).abs() < 0.003, "{name}: dark {b} against {dark}");
        let text = seq.lit.describe();
        assert!(
            text.contains("pairs of consecutive late darks") && text.contains("exposures 61-120"),
            "{name}: {text}"
        );
    }
}

/// An exposure whose only background pixel measures no spread (a single pixel left dark
/// in every illumination) is measured as if it had none: its noise comes from the pairs
/// of darks, as in the sequence without that pixel, never from a constant.
#[test]
fn a_background_without_spread_is_measured_from_the_darks() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("family1");
    common::simulate(&dir, &["family", "--size", "64", "--seed", "1"]);
    let seq = Sequence::load(&dir).unwrap();
    let mut exposures = seq.exposures.clone();
    for &a in &seq.illuminations {
        exposures[a].image[[0, 0]] = 0.0;
    }
    let one_dark = Sequence::from_exposures(exposures).unwrap();
    let last = seq.exposures.len() - 1;
    let (s, s_all_lit) = (one_dark.noise_e_per_s[last], seq.noise_e_per_s[last]);
    println!("noise {s:.5} with one background pixel, {s_all_lit:.5} without");
    assert!(
        (s / s_all_lit - 1.0).abs() < 0.05,
        "{s} against {s_all_lit}"
    );
    assert!(one_dark
        .lit
        .describe()
        .contains("pairs of consecutive late darks"));
}
