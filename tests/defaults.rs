//! The defaults of `fit`, `compare` and `diagnose`: residual cells per illumination,
//! each sample compared with its own prediction (`--cells illumination
//! --cell-statistic paired`), and `diagnose`'s candidates refitted jointly with the
//! model's own effects (`--refit full`), as the outputs record them. With these the
//! ten-seed baseline campaign (nothing hidden) declares nothing at 10 of 10 seeds; the
//! pooled cells with the `levels` statistic stay available when asked for.

mod common;

use common::{persist_ok, read_json};

#[test]
fn fit_compare_and_diagnose_default_to_illumination_paired_full() {
    let tmp = tempfile::tempdir().unwrap();
    let path = |name: &str| tmp.path().join(name).to_str().unwrap().to_string();
    let (lab, m) = (path("lab"), path("m.json"));
    common::lab_campaign(&lab, 32, 1, &[]);

    let text = persist_ok(&["fit", "--input", &lab, "--out", &m]);
    assert!(
        text.contains("illumination x fluence x time cells, paired"),
        "{text}"
    );
    assert_eq!(read_json(path("m.fit.json"))["cell_statistic"], "paired");

    let cmp = path("cmp");
    let text = persist_ok(&["compare", "--input", &lab, "--model", &m, "--report", &cmp]);
    assert!(
        text.contains("illumination x fluence x time cells, paired"),
        "{text}"
    );
    let s = read_json(format!("{cmp}/summary.json"));
    assert_eq!(s["cells"], "illumination");
    assert_eq!(s["cell_statistic"], "paired");
    // per-illumination cells: several illuminations, each with its share
    assert!(s["models"][0]["residual_rms_by_illumination"]
        .as_array()
        .is_some_and(|v| v.len() > 1));

    let d = path("d.json");
    let text = persist_ok(&[
        "diagnose",
        "--input",
        &lab,
        "--model",
        &m,
        "--json",
        &d,
        "--bootstrap",
        "19",
        "--pixels",
        "256",
    ]);
    assert!(text.contains("(--refit full)"), "{text}");
    let dj = read_json(&d);
    assert_eq!(dj["residual_cells"], "illumination");
    assert_eq!(dj["cell_statistic"], "paired");
    assert_eq!(dj["refit"], "full");
    // `fit`'s default model flags with the paper's margin: the effects are tested
    // against the measurements' description fitted from the input, and the output
    // says so and how to write that description
    assert_eq!(dj["reference"]["kind"], "measured", "{text}");
    assert!(text.starts_with("tested against: the measurements' description"));
    assert!(dj["reference"]["fit_command"]
        .as_str()
        .is_some_and(|c| c.contains("--preset readout") && c.contains("m.measured.json")));
    assert!(
        dj["reference"]["effects"].as_array().is_some_and(|e| e
            .iter()
            .any(|e| e.as_str().unwrap().starts_with("refill:beta="))),
        "{dj}"
    );

    // the pooled cells and the levels statistic are there when asked for, and recorded
    let cmp_old = path("cmp_old");
    let mut a = vec![
        "compare", "--input", &lab, "--model", &m, "--report", &cmp_old,
    ];
    a.extend(common::POOLED_LEVELS_CELLS);
    let text = persist_ok(&a);
    assert!(text.contains("(fluence x time cells, levels"), "{text}");
    let s = read_json(format!("{cmp_old}/summary.json"));
    assert_eq!(s["cells"], "pooled");
    assert_eq!(s["cell_statistic"], "levels");
}
