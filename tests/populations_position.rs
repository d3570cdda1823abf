//! A field of trap density over the array, with the real binary and default commands on
//! the second generator's campaign (`persist simulate family --sequence campaign
//! --hidden populations:smooth`, 64 x 64, seed 1: the density `1 + 0.4 (cos th u + sin
//! th v) + 0.25 (u^2 - 1/3)`, `src/trapgen/engine.rs`). The residual depends on the
//! position and `diagnose` names it; the library effect `populations` is declared,
//! judged against the flexible base by tile of the array (`persist::diag::marked`),
//! which each pixel's own amplitude in the pixel reference would take in (measured when
//! written: held-out RMS of the tiles' cells 2.74 -> 1.28, gain 0.53, permutations'
//! largest 0.12). The command it prints, run as printed, leaves no field shared
//! between neighbouring pixels (R^2 at 4 px below 0.20, the line's own threshold;
//! measured: 0.73 -> 0.09, nothing hidden 0.03) and the flagging model's residual falls
//! (`fit`'s line "residual RMS": 19.1 -> 8.1).

mod common;

use common::{declared, diagnose_quick, family_campaign, persist_ok};

/// The first number of the spatial coherence's R^2 (4 px smoothing) in diagnose's text.
fn field_r2(text: &str) -> f64 {
    let line = text
        .lines()
        .find(|l| l.starts_with("spatial coherence:"))
        .expect("the spatial coherence line");
    let r2 = line
        .split("R^2 ")
        .nth(1)
        .unwrap()
        .split('/')
        .next()
        .unwrap();
    r2.parse().unwrap()
}

#[test]
#[ignore = "long: make validation PAGES=long_tests"]
fn a_field_of_trap_density_is_declared_by_tile_and_the_printed_command_removes_it() {
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path().join("pop");
    let d = d.to_str().unwrap();
    family_campaign(d, 64, 1, &["--hidden", "populations:smooth"]);
    let (m, json) = (format!("{d}.json"), format!("{d}.diag.json"));
    persist_ok(&["fit", "--input", d, "--out", &m]);
    let (j, text) = diagnose_quick(d, &m, &json);
    let pop = declared(&j)
        .into_iter()
        .find(|t| t["effect"] == "populations")
        .unwrap_or_else(|| panic!("populations declared: {text}"));
    let p = &pop["held_out"]["pixel_reference"];
    assert_eq!(p["judge"], "position", "{p}");
    let gain = p["gain"].as_f64().unwrap();
    let permuted = p["permuted_gains"]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(|g| g.as_f64())
        .fold(f64::NEG_INFINITY, f64::max);
    assert!(
        gain > 0.2 && gain > permuted,
        "gain {gain}, permutations {permuted}"
    );
    let before = field_r2(&text);
    assert!(before > 0.5, "{before}");
    // the command as printed
    let command = pop["command"].as_str().unwrap();
    let words: Vec<&str> = command.split_whitespace().skip(1).collect();
    persist_ok(&words);
    let after_model = words[words.iter().position(|w| *w == "--out").unwrap() + 1];
    let after = persist_ok(&["diagnose", "--input", d, "--model", after_model]);
    let after = field_r2(&after);
    assert!(after < 0.2, "R^2 {before} -> {after}");
}
