//! `persist fit --preset readout` measures the on-board slope on the first dark, and
//! `--fit-decay-exponent` the decay law's exponent (`persist::calib::readout`,
//! `persist::calib::exponent`):
//! on the second truth generator, whose slope is a least-squares line, and on the
//! simulator, whose slope is the chord of the ramp (and, with its `linefit_bias`, the
//! line).

mod common;
use common::{persist_ok, read_json};
use std::path::Path;

/// `persist fit --preset readout` on `input`: the report's readout line share (None
/// when it was not measured), the model's effect names and its fitted decay exponent.
fn readout_fit(input: &Path) -> (Option<f64>, Vec<String>, f64) {
    let out = input.with_extension("readout.json");
    persist_ok(&[
        "fit",
        "--input",
        input.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--preset",
        "readout",
        "--fit-decay-exponent",
    ]);
    let rep = read_json(out.with_extension("fit.json"));
    let model = read_json(&out);
    let names = model["effects"]
        .as_array()
        .unwrap()
        .iter()
        .map(|e| e["name"].as_str().unwrap().to_string())
        .collect();
    let exponent = model["calibration"]["decay_exponent"].as_f64().unwrap();
    (rep["readout"]["line_fraction"].as_f64(), names, exponent)
}

#[test]
fn the_readout_and_the_decay_exponent_are_measured_from_the_data() {
    let tmp = tempfile::tempdir().unwrap();
    let family = tmp.path().join("family");
    persist_ok(&[
        "simulate",
        "family",
        "--out",
        family.to_str().unwrap(),
        "--seed",
        "1",
        "--size",
        "32",
        "--darks",
        "40",
    ]);
    let (line, names, p) = readout_fit(&family);
    let line = line.expect("measured on the first dark");
    assert!(line > 0.9, "the generator's slope is a line: share {line}");
    assert!(names.contains(&"linefit_bias".to_string()), "{names:?}");
    // the generator's exponent is drawn in 0.85..1.15; the bounds are 0.5..1.6
    assert!((0.7..1.4).contains(&p), "exponent {p}");

    let chord = tmp.path().join("sim");
    common::simulate_lab(&chord, "32", &[]);
    let (line, names, _) = readout_fit(&chord);
    let line = line.expect("measured on the first dark");
    assert!(
        line < 0.1,
        "the simulator's slope is the chord: share {line}"
    );
    assert!(!names.contains(&"linefit_bias".to_string()), "{names:?}");

    let lsq = tmp.path().join("sim_line");
    common::simulate_lab(&lsq, "32", &["--effect", "linefit_bias"]);
    let (line, names, _) = readout_fit(&lsq);
    let line = line.expect("measured on the first dark");
    assert!(line > 0.9, "the simulator's linefit_bias: share {line}");
    assert!(names.contains(&"linefit_bias".to_string()), "{names:?}");
}
