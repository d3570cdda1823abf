//! The model's counterpart of `examples/truth_ratios`: what effects change in a
//! model's predictions, illumination by illumination. For a laboratory sequence, the
//! model file without the named effects and with each set of them (each `NAME:param=value,...`
//! as `persist fit --with` takes it, joined by `+`), the mean predicted persistence
//! current over every pixel of chosen dark integrations after each illumination, as the
//! ratio with the set to without. Set beside `truth_ratios` on the same campaign, a
//! ratio the model does not reproduce is an interaction between effects that the model
//! states differently from the truth (for example `soak` and `temperature` at 82 K).
//!
//! ```sh
//! target/release/examples/model_ratios LAB_DIR MODEL.json [--fluence LO,HI] SET [SET ...]
//! ```
//! `--fluence LO,HI` averages only the samples whose measured fluence in the last
//! illumination lies in `[LO, HI)` e- (`truth_ratios --fluence` takes the true one); a
//! pixel of unknown fluence (a ramp without a slope) is in no band. Name in the sets
//! every effect of the model file that the comparison should leave out of "without":
//! the others stay in it (e.g. `temperature:activation_ev=0` beside a `soak` set, when
//! the truth's `soak` column has no temperature effect).
//! e.g. `... st128 m.json soak:capture_ratio=0.02 temperature:activation_ev=0.25
//! soak:capture_ratio=0.02+temperature:activation_ev=0.25`.
use persist::calib::effects::parse_with;
use persist::diag::data::Sequence;
use persist::diag::eval::{self, Samples};
use persist::model::params::{EffectSpec, ModelParams};
use std::path::Path;

/// One `--with` argument: the effect's name and its parameters.
type With = (String, Vec<(String, f64)>);

/// Per sequence exposure row of `s`: the mean prediction over the sampled pixels whose
/// fluence lies in `band` (every pixel without one, those of unknown fluence included).
fn means(params: &ModelParams, seq: &Sequence, s: &Samples, band: Option<(f64, f64)>) -> Vec<f64> {
    let pr = eval::predict(params, seq, s, false).expect("predict");
    let np = s.npix();
    pr.current
        .chunks(np)
        .zip(s.fluence_e.chunks(np))
        .map(|(row, fl)| {
            let (mut sum, mut n) = (0.0, 0usize);
            for (&v, f) in row.iter().zip(fl) {
                if band.is_none_or(|(lo, hi)| (lo..hi).contains(f)) {
                    sum += v;
                    n += 1;
                }
            }
            sum / n.max(1) as f64
        })
        .collect()
}

fn main() {
    let mut a: Vec<String> = std::env::args().collect();
    let mut band = None;
    if let Some(i) = a.iter().position(|x| x == "--fluence") {
        let v = a.get(i + 1).expect("--fluence LO,HI").clone();
        let (lo, hi) = v.split_once(',').expect("--fluence LO,HI");
        band = Some((
            lo.parse::<f64>().expect("LO"),
            hi.parse::<f64>().expect("HI"),
        ));
        a.drain(i..i + 2);
    }
    if a.len() < 4 {
        eprintln!("usage: model_ratios LAB_DIR MODEL.json [--fluence LO,HI] SET [SET ...]");
        std::process::exit(2);
    }
    let seq = Sequence::load(Path::new(&a[1])).expect("sequence");
    let model = persist::model_file::load(Path::new(&a[2])).expect("model");
    let sets: Vec<Vec<With>> = a[3..]
        .iter()
        .map(|s| {
            s.split('+')
                .map(|e| parse_with(e).expect("effect"))
                .collect()
        })
        .collect();
    let named: Vec<&str> = sets.iter().flatten().map(|(n, _)| n.as_str()).collect();
    let mut base = model.clone();
    base.effects.retain(|e| !named.contains(&e.name.as_str()));
    let (ny, nx) = (seq.ny, seq.nx);
    let pixels = (0..ny).flat_map(|y| (0..nx).map(move |x| (y, x))).collect();
    let s = Samples::with_pixels(&seq, pixels, 1);
    let without = means(&base, &seq, &s, band);
    let with: Vec<Vec<f64>> = sets
        .iter()
        .map(|set| {
            let mut p = base.clone();
            for (name, params) in set {
                p.effects.push(EffectSpec {
                    name: name.clone(),
                    params: params
                        .iter()
                        .map(|(k, v)| (k.clone(), serde_json::json!(v)))
                        .collect(),
                    fixed: Vec::new(),
                });
            }
            means(&p, &seq, &s, band)
        })
        .collect();
    println!(
        "| illumination | dark | T (K) | model without (e-/s) | {} |",
        a[3..].join(" | ")
    );
    println!("|---|---|---|---|{}", "---|".repeat(sets.len()));
    for (row, &k) in s.exposures.iter().enumerate() {
        let Some(last) = seq.last_illumination[k] else {
            continue;
        };
        let ill = seq.illuminations_before(k);
        let dark = k - last;
        if [1, 2, 5, 10, 20, 40, 60].contains(&dark) {
            let r: Vec<String> = with
                .iter()
                .map(|w| format!("{:.3}", w[row] / without[row]))
                .collect();
            println!(
                "| {ill} | {dark} | {:.1} | {:.4} | {} |",
                s.temperature_k[row],
                without[row],
                r.join(" | ")
            );
        }
    }
}
