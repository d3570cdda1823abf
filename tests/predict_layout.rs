//! The diagnostics' predictions (`eval::predict`) run a pixel-local model on the sampled
//! pixels gathered into an array of their own, and any other model on the whole array.
//! The two layouts must give the same predictions and flags bit for bit, for every
//! effect of the library, so that `fit`, `compare` and `diagnose` do not depend on
//! which one ran.

mod common;

use common::persist_ok;
use persist::diag::data::Sequence;
use persist::diag::eval::{predict_in, Layout, Samples};
use persist::model::params::EffectSpec;
use persist::model::{Model, ModelParams};

fn spec(name: &str, p: serde_json::Value) -> EffectSpec {
    EffectSpec {
        params: p.as_object().unwrap().clone(),
        ..EffectSpec::named(name)
    }
}

#[test]
fn gathered_pixels_predict_bit_identically_to_the_whole_array() {
    let tmp = tempfile::tempdir().unwrap();
    let lab = tmp.path().join("lab");
    persist_ok(&[
        "simulate",
        "lab",
        "--size",
        "32",
        "--darks",
        "12",
        "--seed",
        "3",
        "--out",
        lab.to_str().unwrap(),
    ]);
    let seq = Sequence::load(&lab).unwrap();
    // 150 of 1024 pixels: 64 to a row, the last row padded
    let samples = Samples::random(&seq, 150, 1);
    assert_eq!(samples.npix(), 150);
    let local = [
        ("capacity", serde_json::json!({"inv_q_max_per_e": 1e-4})),
        ("soak", serde_json::json!({"capture_ratio": 0.5})),
        ("temperature", serde_json::json!({})),
        ("linefit_bias", serde_json::json!({})),
        ("chord", serde_json::json!({})),
        ("refill", serde_json::json!({})),
        ("short_tau_boost", serde_json::json!({"factor": 2.0})),
        // spatial effects that couple nothing are local too
        ("ipc", serde_json::json!({"alpha": 0.0})),
        ("blooming", serde_json::json!({"fraction": 0.0})),
    ];
    let spatial = [
        ("blooming", serde_json::json!({"fraction": 0.1})),
        ("ipc", serde_json::json!({"alpha": 0.02})),
        ("populations", serde_json::json!({"gx": 0.3, "gyy": -0.2})),
    ];
    let mut models: Vec<(String, Vec<EffectSpec>, bool)> = vec![("none".into(), vec![], true)];
    for (name, p) in &local {
        models.push((name.to_string(), vec![spec(name, p.clone())], true));
    }
    for (name, p) in &spatial {
        models.push((name.to_string(), vec![spec(name, p.clone())], false));
    }
    models.push((
        "soak+capacity+refill".into(),
        vec![
            spec("soak", serde_json::json!({"capture_ratio": 0.5})),
            spec("refill", serde_json::json!({})),
            spec("capacity", serde_json::json!({"inv_q_max_per_e": 1e-4})),
        ],
        true,
    ));
    for (name, effects, is_local) in models {
        let params = ModelParams {
            effects,
            ..ModelParams::default()
        };
        let mut off = params.clone();
        off.early_release.enabled = false;
        // the layout the diagnostics' residuals take (early release off)
        assert_eq!(
            Model::new(off).unwrap().is_pixel_local(),
            is_local,
            "{name}"
        );
        for early_release in [false, true] {
            let g = predict_in(&params, &seq, &samples, early_release, Layout::Gathered).unwrap();
            let w = predict_in(&params, &seq, &samples, early_release, Layout::Whole).unwrap();
            assert_eq!(g.current.len(), samples.len(), "{name}");
            let first_diff = g
                .current
                .iter()
                .zip(&w.current)
                .position(|(a, b)| a.to_bits() != b.to_bits());
            assert_eq!(
                first_diff.map(|i| (i, g.current[i], w.current[i])),
                None,
                "{name}, early release {early_release}: (sample, gathered, whole)"
            );
            assert_eq!(
                g.flagged, w.flagged,
                "{name}, early release {early_release}"
            );
            // the illumination's persistence is there to compare
            assert!(g.current.iter().any(|c| *c > 1.0), "{name}");
        }
    }
}
