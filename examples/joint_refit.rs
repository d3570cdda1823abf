//! `diagnose`'s refit gates (delta BIC, held-out gain) for one candidate effect computed
//! two ways: the candidate fitted alone with the reference model's effects held fixed
//! (what `diagnose` does) and fitted jointly with the reference's effects (what
//! `fit --with` does). Cells: the stride-2 fluence x time cells of `persist fit`, not
//! `diagnose`'s random pixels, so the numbers are indicative, not `diagnose`'s own.
//!
//! ```sh
//! target/release/examples/joint_refit LAB_DIR REFERENCE.json CANDIDATE
//! ```
use persist::calib::effects as ceffects;
use persist::diag::data::Sequence;
use persist::diag::eval::Samples;
use persist::model::ModelParams;
use std::path::Path;

fn rss(p: &ModelParams, seq: &Sequence, s: &Samples) -> (f64, usize) {
    persist::diag::spread::rss_cells(p, seq, s).expect("predict")
}

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let seq = Sequence::load(Path::new(&a[1])).expect("sequence");
    let reference = persist::model_file::load(Path::new(&a[2])).expect("model");
    let cand = a[3].clone();
    let k = persist::model::effects::lookup(&cand)
        .expect("effect")
        .params
        .iter()
        .filter(|p| p.fitted)
        .count();
    // the cells of the figures measured with this example (docs/validation/diagnose_matrix.md),
    // the library's defaults then; the defaults are now per illumination and paired
    let s = Samples::new(&seq, 2)
        .with_cells(persist::diag::eval::Cells::Pooled)
        .with_statistic(persist::diag::eval::CellStatistic::Levels);
    let (r0, m) = rss(&reference, &seq, &s);
    let mut joint: Vec<String> = reference.effects.iter().map(|e| e.name.clone()).collect();
    joint.push(cand.clone());
    let mut events = s.event.clone();
    events.sort_unstable();
    events.dedup();
    let half: Vec<Vec<usize>> = (0..2)
        .map(|h| events.iter().copied().skip(h).step_by(2).collect())
        .collect();
    for (label, names) in [("alone", vec![cand.clone()]), ("joint", joint)] {
        let (full, _) = ceffects::fit(&reference, &names, &seq, &s).expect("fit");
        let (r1, _) = rss(&full, &seq, &s);
        let dbic = persist::diag::diagnose::delta_bic(r0, r1, k, m);
        let (mut b, mut af) = (0.0, 0.0);
        for h in 0..2 {
            let fs = s.rows_where(|e| half[h].contains(&e));
            let ts = s.rows_where(|e| half[1 - h].contains(&e));
            let (f, _) = ceffects::fit(&full, &names, &seq, &fs).expect("fit");
            b += rss(&reference, &seq, &ts).0;
            af += rss(&f, &seq, &ts).0;
        }
        let gain = 1.0 - (af / b).sqrt();
        let vals: Vec<String> = full
            .effects
            .iter()
            .flat_map(|e| {
                e.params
                    .iter()
                    .map(move |(p, v)| format!("{}.{p}={v}", e.name))
            })
            .collect();
        println!(
            "{cand} {label}: RMS {:.3} -> {:.3} over {m} cells, dBIC {dbic:.1}, held-out gain {gain:.3}; {}",
            (r0 / m as f64).sqrt(),
            (r1 / m as f64).sqrt(),
            vals.join(" ")
        );
    }
}
