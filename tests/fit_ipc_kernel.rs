//! `persist fit --with ipc` measures the coupling's 3 x 3 kernel on the illuminations'
//! isolated bright pixels (`persist::measure::coupling`) and writes it into the model
//! (`alpha`, `alpha_split`, `alpha_diag`: `persist::model::effects::ipc`), on the
//! second generator's campaigns with the grid of one-pixel pinholes (`persist simulate
//! family --pinholes on`, 64 x 64; the generator's kernels in `src/trapgen/mod.rs`:
//! `ipc:cross4` 2 % to each nearest neighbour, `ipc:aniso8` 2.5 % along rows, 1 % along
//! columns, 0.4 % to each diagonal). Measured when written: cross4 seed 1 `alpha`
//! 0.0200, `alpha_split` -0.00001, `alpha_diag` 0.0001 from 102 pixels; aniso8 seed 2
//! `alpha` 0.0175, `alpha_split` 0.0075, `alpha_diag` 0.0041 from 71 pixels; each of 6
//! illuminations. Without the grid there is nothing to measure on and the
//! kernel stays four-neighbour and isotropic, `alpha` fitted.

mod common;

use common::{family_campaign, persist_ok, read_json};

/// The `ipc` parameters of a model file: `alpha`, `alpha_split`, `alpha_diag`.
fn kernel(path: &str) -> [f64; 3] {
    let m = read_json(path);
    let e = m["effects"]
        .as_array()
        .unwrap()
        .iter()
        .find(|e| e["name"] == "ipc")
        .expect("ipc in the model")
        .clone();
    ["alpha", "alpha_split", "alpha_diag"].map(|k| e["params"][k].as_f64().unwrap())
}

/// Simulates `hidden` on `seed`, fits the default model and then `--with ipc`; the
/// kernel written and `fit`'s printed text.
fn fitted(hidden: &str, seed: u64, pinholes: &str) -> ([f64; 3], String) {
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path().join("d");
    let d = d.to_str().unwrap();
    family_campaign(d, 64, seed, &["--hidden", hidden, "--pinholes", pinholes]);
    let (plain, with) = (format!("{d}.json"), format!("{d}+ipc.json"));
    persist_ok(&["fit", "--input", d, "--out", &plain]);
    let text = persist_ok(&[
        "fit", "--input", d, "--model", &plain, "--out", &with, "--with", "ipc",
    ]);
    (kernel(&with), text)
}

#[test]
fn the_kernel_is_measured_on_lone_pinholes_along_each_axis_and_the_diagonals() {
    let ([a, split, diag], text) = fitted("ipc:aniso8", 2, "on");
    assert!(text.contains("ipc's kernel measured on"), "{text}");
    assert!((a - 0.0175).abs() < 0.0015, "alpha {a}");
    assert!((split - 0.0075).abs() < 0.0015, "alpha_split {split}");
    assert!((diag - 0.004).abs() < 0.001, "alpha_diag {diag}");
    let ([a, split, diag], _) = fitted("ipc:cross4", 1, "on");
    assert!((a - 0.02).abs() < 0.0015, "alpha {a}");
    assert!(split.abs() < 0.001 && diag < 0.001, "{split} {diag}");
}

#[test]
fn without_lone_bright_pixels_the_kernel_stays_isotropic_and_says_why() {
    let ([_, split, diag], text) = fitted("ipc:cross4", 1, "off");
    assert_eq!((split, diag), (0.0, 0.0));
    assert!(
        text.contains("isolated bright pixels in the illuminations"),
        "{text}"
    );
}
