//! Residual RMS (normalised, `persist fit`'s stride-2 fluence x time cells) of a model
//! file with one effect parameter set to each of a list of values (the effect is added
//! with its defaults when the model does not have it). A profile of the fit objective.
//!
//! ```sh
//! target/release/examples/effect_scan LAB_DIR MODEL.json EFFECT PARAM v1,v2,...
//! ```
use persist::diag::data::Sequence;
use persist::diag::eval::{self, Samples};
use std::path::Path;
fn main() {
    let a: Vec<String> = std::env::args().collect();
    let seq = Sequence::load(Path::new(&a[1])).unwrap();
    let m = persist::model_file::load(Path::new(&a[2])).unwrap();
    let (eff, par) = (a[3].clone(), a[4].clone());
    // the cells of the figures measured with this example (docs/validation/diagnose_matrix.md),
    // the library's defaults then; the defaults are now per illumination and paired
    let s2 = Samples::new(&seq, 2)
        .with_cells(eval::Cells::Pooled)
        .with_statistic(eval::CellStatistic::Levels);
    for v in a[5].split(',') {
        let v: f64 = v.parse().unwrap();
        let mut q = m.clone();
        if !q.effects.iter().any(|e| e.name == eff) {
            q.effects
                .push(persist::model::params::EffectSpec::named(eff.clone()));
        }
        for e in q.effects.iter_mut().filter(|e| e.name == eff) {
            e.params.insert(par.clone(), serde_json::json!(v));
        }
        let pr = eval::predict(&q, &seq, &s2, false).unwrap();
        println!(
            "{eff}.{par} = {v}: rms {:.3}",
            eval::rms(&persist::diag::spread::model_cell_z(&q, &s2, &pr.current))
        );
    }
}
