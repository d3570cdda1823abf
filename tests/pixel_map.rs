//! Per-pixel response maps (docs/pixel_map.md): on a small simulated detector the map
//! learned from its laboratory sequence finds the simulator's trap populations and
//! lowers the sky's over-flagging; the `persist pixelmap` command writes a map and a
//! model naming it, which `persist run` applies; a map whose bytes changed is refused.

use persist::pixmap::eval::Experiment;
use std::path::Path;
use std::process::Command;

/// 32 x 32 pixels, 200 sky exposures (7.4 h), no cosmic rays (their flags are the
/// early-release rule's, which no map changes; docs/validation/pixel_map.md): at margin
/// 0.8 the map flags fewer pixel-exposures whose truth is below 0.1 e-/s than the global
/// model and misses none above 0.3 e-/s. Reference: docs/validation/pixel_map.md (the
/// 128 x 128 two-day run: 0.50 of the global's over-flagging at margin 0.8).
#[test]
fn map_finds_populations_and_lowers_over_flagging() {
    let r = Experiment {
        size: 32,
        seed: 3,
        sky_exposures: 200,
        t_skip_s: 3600.0,
        margins: vec![0.8],
        cosmic_rate_per_cm2_s: Some(0.0),
    }
    .run()
    .expect("experiment");
    // the map against the truth: above full well the low population (no forward-bias
    // traps) sits far below the others, the high one above the mid one
    let by: Vec<f64> = r
        .saturated_ratio_by_population
        .iter()
        .map(|p| p.1)
        .collect();
    assert!(by[0] < 0.3 && by[0] < by[1] && by[1] < by[2], "{by:?}");
    let (g, m) = (&r.global.0, &r.with_map[0].1);
    assert!(g.over_flagged > 0, "{g:?}");
    assert!(
        (m.over_flagged as f64) < 0.8 * g.over_flagged as f64,
        "map {} vs global {}",
        m.over_flagged,
        g.over_flagged
    );
    assert_eq!(m.missed[3], 0, "{m:?}");
}

fn persist() -> Command {
    Command::new(env!("CARGO_BIN_EXE_persist"))
}

fn ok(c: &mut Command) -> String {
    let o = c.output().expect("run persist");
    assert!(
        o.status.success(),
        "{c:?}: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    String::from_utf8_lossy(&o.stdout).into_owned()
}

/// `persist simulate lab --spots paper` + `persist fit` + `persist pixelmap
/// --write-model`, then `persist run` with that model; tampering with the map is
/// refused with the field named.
#[test]
fn pixelmap_command_writes_map_and_model_the_stage_applies() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let lab = d.join("lab");
    ok(persist()
        .args([
            "simulate", "lab", "--size", "24", "--darks", "40", "--spots", "paper", "--out",
        ])
        .arg(&lab));
    let fit = d.join("fit.json");
    ok(persist()
        .args(["fit", "--input"])
        .arg(&lab)
        .arg("--out")
        .arg(&fit));
    let map = d.join("maps/det1.h5");
    let model = d.join("maps/model.json");
    let out = ok(persist()
        .args(["pixelmap", "--input"])
        .arg(&lab)
        .arg("--model")
        .arg(&fit)
        .arg("--out")
        .arg(&map)
        .arg("--write-model")
        .arg(&model));
    assert!(out.contains("pixels measured"), "{out}");
    let text = std::fs::read_to_string(&model).unwrap();
    assert!(text.contains("\"path\": \"det1.h5\""), "{text}");
    ok(persist().args(["validate"]).arg(&model));
    // the stage applies it: flags differ from the model without the map
    let run = |m: &Path, o: &str| {
        ok(persist()
            .args(["run", "--quiet", "--input"])
            .arg(&lab)
            .arg("--output")
            .arg(d.join(o))
            .arg("--checkpoints")
            .arg(d.join(format!("{o}_ck")))
            .arg("--model")
            .arg(m));
    };
    run(&fit, "global");
    run(&model, "mapped");
    let cur = |o: &str| {
        let f = persist::product::read::read_output(&d.join(o).join("d1_e000001.h5")).unwrap();
        f.1.current_e_per_s
    };
    assert_ne!(cur("global"), cur("mapped"));
    // a changed map is refused, naming the model file's field
    let mut bytes = std::fs::read(&map).unwrap();
    let n = bytes.len();
    bytes[n - 1] ^= 0xff;
    std::fs::write(&map, bytes).unwrap();
    let o2 = persist()
        .args(["run", "--quiet", "--input"])
        .arg(&lab)
        .arg("--output")
        .arg(d.join("x"))
        .arg("--checkpoints")
        .arg(d.join("x_ck"))
        .arg("--model")
        .arg(&model)
        .output()
        .unwrap();
    assert!(!o2.status.success());
    let err = String::from_utf8_lossy(&o2.stderr);
    assert!(err.contains("sha256"), "{err}");
}
