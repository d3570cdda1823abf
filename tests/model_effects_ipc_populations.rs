//! The model effects `ipc` and `populations` (src/model/effects/): bit-identical to the
//! paper's model at their null values, the documented direction and size when active,
//! and used by `persist run` when a model file lists them.

mod common;

use ndarray::Array2;
use persist::model::params::EffectSpec;
use persist::model::response::Response;
use persist::model::{Input, Model, ModelParams, Output, StepContext};
use persist::product::synthetic::tiny_exposure;
use persist::units::UtcSeconds;
use std::path::Path;

const N: usize = 9;
const C: usize = 4; // the centre
const T_EXP: f64 = 112.0;
/// True fluence of the isolated bright pixel, e-.
const F_STAR: f64 = 1e8;
const ALPHA: f64 = 0.01;

fn spec(name: &str, params: serde_json::Value) -> EffectSpec {
    EffectSpec {
        params: params.as_object().cloned().unwrap_or_default(),
        ..EffectSpec::named(name)
    }
}

/// What an IPC readout shows of an isolated pixel of `F_STAR` e- in `T_EXP` s: the
/// pixel `(1 - 4 alpha)`, each nearest neighbour `alpha` of it (e-/s), 0.01 elsewhere.
fn star_image() -> Array2<f32> {
    let flux = F_STAR / T_EXP;
    let mut img = Array2::from_elem((N, N), 0.01f32);
    img[[C, C]] = ((1.0 - 4.0 * ALPHA) * flux) as f32;
    for (y, x) in [(C - 1, C), (C + 1, C), (C, C - 1), (C, C + 1)] {
        img[[y, x]] = (ALPHA * flux) as f32;
    }
    img
}

fn t_start(k: usize) -> f64 {
    1.7e9 + k as f64 * (T_EXP + 30.0)
}

/// The star, then darks; the predicted current of every step.
fn run(model: &Model, steps: usize) -> Vec<Array2<f32>> {
    run_after(model, steps, star_image())
}

/// `first`, then darks; the predicted current of every step.
fn run_after(model: &Model, steps: usize, first: Array2<f32>) -> Vec<Array2<f32>> {
    let mut st = model.new_state(N, N);
    let mut out = Vec::new();
    let dark = Array2::from_elem((N, N), 0.01f32);
    for k in 0..steps {
        let img = if k == 0 { &first } else { &dark };
        let input = Input {
            image_e_per_s: img.view(),
            exposure_index: k as u64,
            t_start_unix_s: t_start(k),
            t_exposure_s: T_EXP,
            t_illuminated_s: T_EXP,
            history_incomplete: false,
            background_e_per_s: None,
        };
        let mut flags = Array2::<u32>::zeros((N, N));
        let mut cur = Array2::<f32>::zeros((N, N));
        let mut pf = Array2::<u8>::zeros((N, N));
        model
            .step_with(
                &mut st,
                &input,
                &StepContext {
                    focal_plane_temp_k: Some(80.0),
                    ..Default::default()
                },
                &mut Output {
                    flags: &mut flags,
                    current_e_per_s: &mut cur,
                    pflags: &mut pf,
                },
            )
            .unwrap();
        out.push(cur);
    }
    out
}

/// The default model with early release counting three exposures in a row
/// (`rule: consecutive`): the darks here have no noise, so the evidence rule (the
/// default) would release the star at the first dark, zeroing what these tests compare.
fn paper() -> ModelParams {
    let mut p = ModelParams::default();
    p.early_release.rule = persist::model::ReleaseRule::Consecutive;
    p
}

fn with(effects: Vec<EffectSpec>) -> Model {
    Model::new(ModelParams { effects, ..paper() }).unwrap()
}

fn close(a: f64, b: f64, rel: f64) -> bool {
    (a - b).abs() <= rel * b.abs().max(1e-30)
}

#[test]
fn at_their_null_values_both_are_bit_identical_to_the_paper_model() {
    let base = run(&Model::new(paper()).unwrap(), 6);
    assert!(base[1][[C, C]] > 1.0, "the star leaves persistence");
    let ipc0 = run(
        &with(vec![spec("ipc", serde_json::json!({"alpha": 0.0}))]),
        6,
    );
    assert_eq!(ipc0, base);
    let pop0 = run(&with(vec![spec("populations", serde_json::json!({}))]), 6);
    assert_eq!(pop0, base);
    let both = run(
        &with(vec![
            spec("ipc", serde_json::json!({"alpha": 0.0})),
            spec(
                "populations",
                serde_json::json!({"gx": 0.0, "gy": 0.0, "gxx": 0.0, "gxy": 0.0, "gyy": 0.0}),
            ),
        ]),
        6,
    );
    assert_eq!(both, base);
}

#[test]
fn ipc_gives_neighbours_alpha_of_the_star_instead_of_their_measured_fluence() {
    let p = paper();
    let resp = Response::new(&p.amplitude_knots);
    let base = run(&Model::new(p.clone()).unwrap(), 4);
    let ipc = run(
        &with(vec![spec("ipc", serde_json::json!({"alpha": ALPHA}))]),
        4,
    );
    let a_max = resp.amplitude_e(F_STAR);
    let f_nb_measured = f64::from((ALPHA * F_STAR / T_EXP) as f32) * T_EXP; // ~1e6 e-
    let a_nb = resp.amplitude_e(f_nb_measured);
    // Without the effect the neighbour is given A_k(1e6 e-) (~693 e-): it looks
    // saturated. With it, its own fluence is ~0 and it reads alpha of the star's
    // amplitude: the prediction falls by alpha A_max / A_k(1e6) = 0.0127.
    for k in 1..4 {
        let (nb, nb0) = (
            f64::from(ipc[k][[C - 1, C]]),
            f64::from(base[k][[C - 1, C]]),
        );
        let want = ALPHA * a_max / a_nb;
        assert!(close(nb / nb0, want, 2e-3), "k {k}: {} vs {want}", nb / nb0);
        // the star itself reads (1 - 4 alpha) of its (saturated, so unchanged) amplitude
        let (c, c0) = (f64::from(ipc[k][[C, C]]), f64::from(base[k][[C, C]]));
        assert!(close(c / c0, 1.0 - 4.0 * ALPHA, 1e-4), "{}", c / c0);
    }
    // the diagonal pixel: measured 0, truly 0, and the coupling gives it nothing
    // (second-order leftovers of the deconvolution only)
    assert!(f64::from(ipc[1][[C - 1, C - 1]]) < 1e-3 * f64::from(ipc[1][[C - 1, C]]));
    // charge conservation of the coupling: the 3x3 sum of amplitudes is the star's
    let s: f64 = (C - 1..=C + 1)
        .flat_map(|y| (C - 1..=C + 1).map(move |x| (y, x)))
        .map(|p| f64::from(ipc[1][p]))
        .sum();
    assert!(close(s, f64::from(base[1][[C, C]]), 2e-3), "{s}");
}

/// Regression: the model's coupling skipped pixels of unknown fluence as neighbours. A
/// star too bright for the on-board fit (fewer than three samples below half the full
/// well, so no slope and no fluence) is given the largest amplitude, and in the darks
/// after it the readout couples its persistence into its neighbours as it couples any
/// pixel's: the simulator's one-pixel pinholes brighter than ~22,000 e-/s left the
/// neighbours' first darks under-predicted by half.
#[test]
fn a_star_without_a_slope_still_leaks_its_persistence_into_its_neighbours() {
    // the star has no slope (NaN); its neighbours read what the readout adds of the
    // measured image: nothing from a NaN, so their faint own level only
    let mut first = Array2::from_elem((N, N), 0.01f32);
    first[[C, C]] = f32::NAN;
    let run_nan = |model: &Model| run_after(model, 3, first.clone());
    let base = run_nan(&Model::new(paper()).unwrap());
    let ipc = run_nan(&with(vec![spec(
        "ipc",
        serde_json::json!({"alpha": ALPHA}),
    )]));
    for k in 1..3 {
        let star = f64::from(base[k][[C, C]]);
        assert!(
            star > 1.0,
            "the star is predicted at the largest amplitude: {star}"
        );
        // the star keeps its own amplitude (the step restores it)
        assert_eq!(ipc[k][[C, C]], base[k][[C, C]]);
        for (y, x) in [(C - 1, C), (C + 1, C), (C, C - 1), (C, C + 1)] {
            let (nb, nb0) = (f64::from(ipc[k][[y, x]]), f64::from(base[k][[y, x]]));
            // alpha of the star's persistence plus (1 - 4 alpha) of its own faint level
            let want = ALPHA * star + (1.0 - 4.0 * ALPHA) * nb0;
            assert!(close(nb, want, 1e-3), "k {k} ({y},{x}): {nb} vs {want}");
            assert!(nb > 10.0 * nb0);
        }
        // the diagonal pixel is not a nearest neighbour
        assert!(close(
            f64::from(ipc[k][[C - 1, C - 1]]),
            f64::from(base[k][[C - 1, C - 1]]),
            1e-3
        ));
    }
}

#[test]
fn populations_scales_the_prediction_by_its_surface() {
    let base = run(&Model::new(paper()).unwrap(), 3);
    let g = 0.5f64;
    let pop = run(
        &with(vec![spec("populations", serde_json::json!({"gx": g}))]),
        3,
    );
    // u = (x - 4) / 4.5; scale exp(g u); the star at x = 4 unchanged (u = 0)
    for x in [C - 1, C, C + 1] {
        let u = (x as f64 - 4.0) / 4.5;
        let r = f64::from(pop[1][[C, x]]) / f64::from(base[1][[C, x]]);
        assert!(close(r, (g * u).exp(), 1e-5), "x {x}: {r}");
    }
    assert!(pop[1][[C, C + 1]] > base[1][[C, C + 1]]);
    assert!(pop[1][[C, C - 1]] < base[1][[C, C - 1]]);
}

fn persist(args: &[&str]) -> std::process::Output {
    common::persist_cmd()
        .args(args)
        .env("SOURCE_DATE_EPOCH", "1772323200")
        .output()
        .unwrap()
}

/// `/persistence/current` of exposure `index` in an output directory.
fn current(dir: &Path, index: u64) -> Array2<f32> {
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        if p.extension().is_some_and(|x| x == "h5") {
            let (e, planes, _) = persist::product::read::read_output(&p).unwrap();
            if e.meta.exposure_index == index {
                return planes.current_e_per_s;
            }
        }
    }
    panic!("no output for exposure {index} in {}", dir.display());
}

#[test]
fn persist_run_uses_the_effects_of_a_model_file() {
    let tmp = tempfile::tempdir().unwrap();
    let input = tmp.path().join("in");
    std::fs::create_dir_all(&input).unwrap();
    for k in 0..3 {
        let mut e = tiny_exposure(1, k as u64, N, N, &UtcSeconds(t_start(k)).to_iso(), T_EXP);
        e.image = if k == 0 {
            star_image()
        } else {
            Array2::from_elem((N, N), 0.01f32)
        };
        e.flags = Array2::zeros((N, N));
        persist::product::write::write_exposure(&input.join(format!("d1_e{k:06}.h5")), &e).unwrap();
    }
    let model = |name: &str, effects: serde_json::Value| {
        let out = persist(&["model", "default"]);
        assert!(out.status.success());
        let mut m: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        m["effects"] = effects;
        let p = tmp.path().join(name);
        std::fs::write(&p, serde_json::to_string_pretty(&m).unwrap()).unwrap();
        p
    };
    let run = |tag: &str, m: &Path| {
        let out = tmp.path().join(format!("out-{tag}"));
        let ck = tmp.path().join(format!("ck-{tag}"));
        let o = persist(&[
            "run",
            "--input",
            input.to_str().unwrap(),
            "--output",
            out.to_str().unwrap(),
            "--checkpoints",
            ck.to_str().unwrap(),
            "--model",
            m.to_str().unwrap(),
            "--quiet",
        ]);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        current(&out, 1)
    };
    let plain = run("plain", &model("plain.json", serde_json::json!([])));
    let null = run(
        "null",
        &model(
            "null.json",
            serde_json::json!([{"name": "ipc", "params": {"alpha": 0.0}}, {"name": "populations"}]),
        ),
    );
    assert_eq!(null, plain, "null effects change nothing in the stage");
    let on = run(
        "on",
        &model(
            "on.json",
            serde_json::json!([{"name": "ipc", "params": {"alpha": ALPHA}}, {"name": "populations", "params": {"gy": 0.5}}]),
        ),
    );
    // the same numbers as the model core gives (the stage runs the same step)
    let core = run_core();
    assert_eq!(on, core);
    assert!(on[[C - 1, C]] < 0.05 * plain[[C - 1, C]]);
    // and the model identity in the output names the model with the effects
    let id = persist(&["model", "id", tmp.path().join("on.json").to_str().unwrap()]);
    assert!(id.status.success());
}

fn run_core() -> Array2<f32> {
    let m = with(vec![
        spec("ipc", serde_json::json!({"alpha": ALPHA})),
        spec("populations", serde_json::json!({"gy": 0.5})),
    ]);
    run(&m, 2).remove(1)
}

#[test]
fn bounds_are_enforced_with_the_field_named() {
    for (name, p, field) in [
        ("ipc", serde_json::json!({"alpha": 0.2}), "alpha"),
        ("populations", serde_json::json!({"gxy": 5.0}), "gxy"),
    ] {
        let e = ModelParams {
            effects: vec![spec(name, p)],
            ..ModelParams::default()
        }
        .validate()
        .unwrap_err();
        assert!(e.contains(field), "{e}");
    }
}
