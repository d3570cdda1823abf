//! Model effects through `Model::step`: a null effect changes nothing bit for bit, an
//! active one changes the prediction as its equation says, and bad entries are refused.

use ndarray::Array2;
use persist::model::params::EffectSpec;
use persist::model::{Input, Model, ModelParams, Output, StepContext};

fn spec(name: &str, params: serde_json::Value) -> EffectSpec {
    EffectSpec {
        name: name.into(),
        params: params.as_object().cloned().unwrap_or_default(),
    }
}

/// Run a 4x4 lab-like sequence (one bright exposure, then darks); predictions per step.
fn run(model: &Model, temps: &[f64]) -> Vec<Array2<f32>> {
    let mut st = model.new_state(4, 4);
    let mut out = Vec::new();
    let mut t = 0.0;
    for (k, temp) in temps.iter().enumerate() {
        let img = if k == 0 {
            Array2::from_shape_fn((4, 4), |(y, x)| (200.0 * (1 + y * 4 + x) as f32).powf(1.3))
        } else {
            Array2::from_elem((4, 4), 0.01f32)
        };
        let t_exp = if k == 0 { 613.0 } else { 180.0 };
        let input = Input {
            image_e_per_s: img.view(),
            exposure_index: k as u64,
            t_start_unix_s: 1e9 + t,
            t_exposure_s: t_exp,
            t_illuminated_s: if k == 0 { 481.0 } else { t_exp },
            history_incomplete: false,
            background_e_per_s: None,
        };
        let mut flags = Array2::<u32>::zeros((4, 4));
        let mut cur = Array2::<f32>::zeros((4, 4));
        let mut pf = Array2::<u8>::zeros((4, 4));
        model
            .step_with(
                &mut st,
                &input,
                &StepContext {
                    focal_plane_temp_k: Some(*temp),
                },
                &mut Output {
                    flags: &mut flags,
                    current_e_per_s: &mut cur,
                    pflags: &mut pf,
                },
            )
            .unwrap();
        out.push(cur);
        t += t_exp;
    }
    out
}

fn with(effects: Vec<EffectSpec>) -> Model {
    Model::new(ModelParams {
        effects,
        ..ModelParams::default()
    })
    .unwrap()
}

#[test]
fn null_effects_are_bit_identical_to_the_paper_model() {
    let temps = vec![80.0; 8];
    let base = run(&Model::new(ModelParams::default()).unwrap(), &temps);
    for (name, p) in [
        ("capacity", serde_json::json!({"inv_a_max_per_e": 0.0})),
        ("refill", serde_json::json!({"beta": 0.0})),
        ("chord", serde_json::json!({"strength": 0.0})),
        ("soak", serde_json::json!({"capture_ratio": 0.0})),
        ("temperature", serde_json::json!({})), // 80 K = t_ref
        ("linefit_bias", serde_json::json!({"strength": 0.0})),
        ("blooming", serde_json::json!({"gain_per_e": 0.0})),
        ("short_tau_boost", serde_json::json!({"factor": 1.0})),
    ] {
        let got = run(&with(vec![spec(name, p)]), &temps);
        assert_eq!(got, base, "{name}");
    }
}

#[test]
fn active_effects_change_the_prediction_as_documented() {
    let temps = vec![80.0; 8];
    let base = run(&Model::new(ModelParams::default()).unwrap(), &temps);
    // capacity lowers, the more the larger the amplitude
    let cap = run(
        &with(vec![spec(
            "capacity",
            serde_json::json!({"inv_a_max_per_e": 1e-3}),
        )]),
        &temps,
    );
    assert!(cap[1][[3, 3]] < base[1][[3, 3]]);
    // warmer array: faster decay -> higher early current? later lower
    let warm = run(
        &with(vec![spec("temperature", serde_json::json!({}))]),
        &[82.0; 8],
    );
    assert!(warm[7][[3, 3]] != base[7][[3, 3]]);
    // the least-squares slope of a convex decay weights the middle of the ramp: it reads
    // above the mid-exposure current (and below the mean current)
    let lf = run(
        &with(vec![spec("linefit_bias", serde_json::json!({}))]),
        &temps,
    );
    assert!(lf[1][[3, 3]] > base[1][[3, 3]]);
}

#[test]
fn bad_effect_entries_are_refused_with_their_field() {
    let e = ModelParams {
        effects: vec![spec("nope", serde_json::json!({}))],
        ..ModelParams::default()
    }
    .validate()
    .unwrap_err();
    assert!(
        e.starts_with("effects[0].name") && e.contains("nope"),
        "{e}"
    );
    let e = ModelParams {
        effects: vec![spec("soak", serde_json::json!({"capture_ratio": -1.0}))],
        ..ModelParams::default()
    }
    .validate()
    .unwrap_err();
    assert!(e.starts_with("effects[0].params.capture_ratio"), "{e}");
    let e = ModelParams {
        effects: vec![
            spec("soak", serde_json::json!({})),
            spec("soak", serde_json::json!({})),
        ],
        ..ModelParams::default()
    }
    .validate()
    .unwrap_err();
    assert!(e.contains("twice"), "{e}");
}
