//! The pixel reference (`persist diagnose`'s "pixel reference" line) of the measurements'
//! description `diagnose` fits for a model, fitted to all illumination events together
//! and to each event alone (`persist::diag::base::per_event_rms`: the floor of what an
//! addition acting between a pixel's illuminations can take), with `diagnose`'s default
//! sampling; then, given an effect, one of its parameters and a list of values, the
//! pixel reference's RMS with the effect added to the description at each value (a
//! profile: how far any value of the effect brings the pixel reference).
//!
//! ```sh
//! target/release/examples/per_event_floor LAB_DIR MODEL.json [EFFECT PARAM v1,v2,...]
//! ```
//!
//! `EXTRA_WITH="name:k=v,...;name2:..."` adds effects (the `--with` form) to the
//! description first. `JUDGE=position` also prints the RMS of the tiles' cells, the
//! judge of candidates on the position (`persist::diag::marked`), at each model.
use persist::diag::config::Config;
use persist::diag::data::Sequence;
use persist::diag::eval::{self, Samples};
use persist::model::params::{EffectSpec, ModelParams};
use persist::model::response::Response;
use std::path::Path;

/// The pixel reference's RMS of `m`'s prediction at `s`, all events together, and per
/// event (None with one event).
fn rms(m: &ModelParams, seq: &Sequence, s: &Samples) -> (f64, Option<f64>) {
    let base = eval::predict(m, seq, s, false).expect("predict");
    let response = Response::new(&m.amplitude_knots);
    let view = persist::diag::base::View::of_model(m, seq);
    let all = persist::diag::base::predict_scaled(seq, &view, s, &base.current, &response);
    let floor = persist::diag::base::per_event_rms(seq, &view, s, &base.current, &response);
    if std::env::var("JUDGE").as_deref() == Ok("position") {
        let tiles = persist::diag::marked::rms(persist::diag::marked::Judge::Position, m, seq, s)
            .expect("tiles");
        println!("  tiles' RMS (the position's judge) {tiles:.3}");
    }
    (eval::rms(&all.cells(s)), floor.map(|f| f.0))
}

/// `m` with the effect `name` (added with its defaults when absent) at `param = v`.
fn with_value(m: &ModelParams, name: &str, param: &str, v: f64) -> ModelParams {
    let mut q = m.clone();
    if !q.effects.iter().any(|e| e.name == name) {
        q.push_effect(EffectSpec::named(name.to_string()));
    }
    for e in q.effects.iter_mut().filter(|e| e.name == name) {
        e.params.insert(param.to_string(), serde_json::json!(v));
    }
    q
}

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let seq = Sequence::load(Path::new(&a[1])).expect("sequence");
    let model = persist::model_file::load(Path::new(&a[2])).expect("model");
    let cfg = Config::default();
    let s = Samples::random(&seq, cfg.pixels, cfg.seed)
        .with_cells(cfg.cells)
        .with_statistic(cfg.cell_statistic);
    let mut d = persist::diag::reference::describe(&model, &seq, &cfg).expect("description");
    if let Ok(extra) = std::env::var("EXTRA_WITH") {
        for w in extra.split(';') {
            let (name, pins) = persist::calib::effects::parse_with(w).expect("--with form");
            let mut spec = EffectSpec::named(name);
            for (k, v) in &pins {
                spec.params.insert(k.clone(), serde_json::json!(v));
            }
            d.push_effect(spec);
        }
    }
    // the noise as `diagnose` scales it, on the described model's reference
    let mut s = s;
    let base = eval::predict(&d, &seq, &s, false).expect("predict");
    let view = persist::diag::base::View::of_model(&d, &seq);
    let response = Response::new(&d.amplitude_knots);
    persist::diag::base::scale_noise(&seq, &view, &mut s, &base.current, &response);
    let (all, floor) = rms(&d, &seq, &s);
    let floor = floor.map_or("-".to_string(), |f| format!("{f:.3}"));
    println!("pixel reference RMS {all:.3}; fitted to each event alone {floor}");
    let (Some(name), Some(param), Some(values)) = (a.get(3), a.get(4), a.get(5)) else {
        return;
    };
    for v in values.split(',') {
        let v: f64 = v.parse().expect("a value");
        let (r, _) = rms(&with_value(&d, name, param, v), &seq, &s);
        println!("{name}:{param}={v:e} pixel reference RMS {r:.3}");
    }
}
