//! `persist diagnose`'s spatial coherence (src/diag/spatial.rs): trap populations that
//! vary across the array in patches (the simulator's `populations`, hidden) are a field
//! that a map of one illumination's residual carries to another; without them there is
//! none. Neither the cells nor a library effect see such a field, so this is how
//! `diagnose` says that the residual matches no library effect, and where it is;
//! `compare` reports the same per model. The model's `populations`, a quadratic surface
//! over the array, is not declared on patches a few pixels across (the simulator's
//! default correlation length, 8 px): held out against the flexible base by tile of
//! the array (`persist::diag::marked`), the surface the description fits makes the
//! tiles worse and the refinement ends at its null (measured: gain 0.014, permutations'
//! largest 0.059), while the description's own held-out gain passes (0.58): that gain
//! is the spread of each pooled cell, not where the field lies. Nor is it declared
//! without the field (regression: it was declared on the 32 x 32 campaign without the
//! hidden effect).
//! 32 x 32 laboratory campaigns, seed 1, `persist fit`'s default calibration. Measured
//! at this size: best R^2 0.06 without, 0.46 with the effect.

mod common;

use common::{persist_ok, read_json};

/// The spatial block of `diagnose --json` on a 32 x 32 campaign with `extra` simulator
/// arguments, and the printed text.
fn spatial(extra: &[&str]) -> (serde_json::Value, String) {
    let tmp = tempfile::tempdir().unwrap();
    let path = |n: &str| tmp.path().join(n).to_str().unwrap().to_string();
    let lab = path("lab");
    common::lab_campaign(&lab, 32, 1, extra);
    let model = path("m.json");
    persist_ok(&[
        "fit",
        "--input",
        &lab,
        "--out",
        &model,
        "--log-level",
        "warn",
    ]);
    // the model file itself (not the measurements' description `diagnose` would fit
    // for a flagging model), so that `compare` of the same file can be set beside it
    let (d, text) =
        common::diagnose_quick_with(&lab, &model, &path("d.json"), &["--reference", "model"]);
    // compare reports the same for the model (its summary and its report's table)
    let report = path("cmp");
    persist_ok(&[
        "compare",
        "--input",
        &lab,
        "--model",
        &model,
        "--report",
        &report,
        "--log-level",
        "warn",
    ]);
    let sum = read_json(tmp.path().join("cmp").join("summary.json"));
    assert_eq!(sum["models"][0]["spatial"], d["spatial"]);
    let html = std::fs::read_to_string(tmp.path().join("cmp").join("report.html")).unwrap();
    assert!(html.contains("spatial coherence"));
    // and draws where the field is: 32 x 32 blocks of 1 px
    assert!(html.contains("Where the residual is on the array"));
    let f = &d["spatial"]["field"];
    assert_eq!(
        (f["block_px"].as_u64(), f["rows"].as_u64()),
        (Some(1), Some(32))
    );
    assert_eq!(f["log_ratio"].as_array().unwrap().len(), 32 * 32);
    (d, text)
}

#[test]
#[ignore = "long: make validation PAGES=long_tests"]
fn hidden_populations_are_a_field_shared_by_neighbours_that_the_surface_does_not_predict() {
    let (with, text) = spatial(&["--effect", "populations"]);
    let c = &with["spatial"];
    assert_eq!(c["events"], 5, "{c}");
    assert_eq!(c["pairs"], 20, "{c}");
    assert_eq!(c["coherent"], true, "{c}");
    let best = c["best_r2"].as_f64().unwrap();
    assert!(best > 0.3, "{c}");
    assert!(text.contains("a field shared by neighbours"), "{text}");
    // the model's populations (a surface over the array) is judged by tile and not
    // declared on patches of 8 px (module docs)
    let pop = |d: &serde_json::Value| {
        d["ranking"]
            .as_array()
            .unwrap()
            .iter()
            .find(|c| c["effect"] == "populations")
            .unwrap()
            .clone()
    };
    let p = pop(&with);
    assert_eq!(p["held_out"]["pixel_reference"]["judge"], "position", "{p}");
    assert_eq!(p["held_out"]["passes"], true, "{p}");
    assert_eq!(p["significant"], false, "{p}");

    let (without, text) = spatial(&[]);
    let c0 = &without["spatial"];
    assert_eq!(c0["coherent"], false, "{c0}");
    assert!(c0["best_r2"].as_f64().unwrap() < 0.15, "{c0}");
    // the pixels' own traps repeat from one illumination to the next either way
    assert!(c0["r2_raw"].as_f64().unwrap() > 0.5, "{c0}");
    assert!(text.contains("none shared by neighbours"), "{text}");
    // without the field, populations is not declared. Its score is the spread score
    // (neighbouring pixels' spread correlated; src/diag/spread.rs), about N(0, 1)
    // squared where positive without the field: under the threshold here. (A score
    // from the LM test of a quadratic surface instead passes the other gates against
    // `fit`'s paper calibration and is held back by the spatial gate alone.)
    let p0 = pop(&without);
    assert_eq!(p0["significant"], false, "{p0}");
    assert_eq!(p0["passes_score"], false, "{p0}");
    assert!(
        p0["score"].as_f64().unwrap() < p0["threshold"].as_f64().unwrap(),
        "{p0}"
    );
}

/// `fit --with populations` measures how the pixels' spread is correlated between
/// neighbours on the fitted model's residuals (src/diag/spread.rs; a noise statement,
/// the predictions unchanged by it): a positive correlation over a few pixels with the
/// hidden field, none without it, and the cells widened by it lower the RMS. 32 x 32
/// campaigns, seed 1, `fit`'s defaults; measured: 0.071 +- 0.031
/// over 3.0 px with the field (RMS 8.34 -> 4.82), 0 without (7.48 -> 7.42).
#[test]
#[ignore = "long: make validation PAGES=long_tests"]
fn fit_with_populations_measures_the_spread_correlation_only_where_the_field_is() {
    let tmp = tempfile::tempdir().unwrap();
    let path = |n: &str| tmp.path().join(n).to_str().unwrap().to_string();
    let spread_of = |extra: &[&str], name: &str| {
        let lab = path(name);
        common::lab_campaign(&lab, 32, 1, extra);
        let model = path(&format!("{name}.json"));
        persist_ok(&[
            "fit",
            "--input",
            &lab,
            "--out",
            &model,
            "--with",
            "populations",
            "--log-level",
            "warn",
        ]);
        let m = read_json(&model);
        let e = m["effects"]
            .as_array()
            .unwrap()
            .iter()
            .find(|e| e["name"] == "populations")
            .unwrap()
            .clone();
        let p = |k: &str| e["params"][k].as_f64().unwrap();
        (p("spread_corr"), p("spread_length_px"))
    };
    let (c1, l1) = spread_of(&["--effect", "populations"], "with");
    assert!(c1 > 0.02 && (1.0..8.0).contains(&l1), "{c1} {l1}");
    let (c0, _) = spread_of(&[], "without");
    assert!(c0 < 0.02, "{c0}");
}
