//! The decay shape of the simulator's truth against a model's, per fluence band: for
//! every sampled pixel and exposure after an illumination, the truth's mean persistence
//! current (`truth/*.truth.hdf5` `/true_persistence`, noise-free) and the model's
//! prediction; per band (half decades of fluence) and time bin (quarter decades), the
//! median of each and their ratio, each band's ratio divided by its first time bin's.
//! A row of ones means the model's decay has the truth's shape at that fluence. Then
//! the same per-time products `t * i(t)` of the truth and of the model (1/t is a row of
//! ones). Medians, not `compare`'s 95th percentiles: above saturation the truth's
//! population mixture puts the median well below the 95th percentile the knots follow,
//! so compare the shapes of rows, not their levels. The first column (the first dark)
//! differs by definition (the truth's mean over the integration against the model's
//! observed current).
//!
//! This is how a model form that compounds over exposures shows: on a single 14 h
//! illumination the truth's `t * i(t)` is flat at every fluence, while a `capacity`
//! applied to the whole amplitude at every exposure falls fourfold over 14 h above
//! saturation and nowhere else.
//!
//! ```sh
//! target/release/examples/truth_shape LAB_DIR MODEL.json [EVENT]
//! ```
//! `EVENT` (0, 1, ...): only the exposures after that illumination; the first table is
//! then also printed without the division (the truth's median over the model's), and
//! the two medians themselves (e-/s).
//! ```
use persist::diag::compare::read_truth;
use persist::diag::data::Sequence;
use persist::diag::eval::{self, Samples};
use persist::sim::output::truth_path;
use std::collections::BTreeMap;
use std::path::Path;

/// Truth and model currents of one fluence x time cell, e-/s.
type Cell = (Vec<f64>, Vec<f64>);

fn med(mut v: Vec<f64>) -> f64 {
    v.retain(|x| x.is_finite());
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2]
}

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let dir = Path::new(&a[1]);
    let seq = Sequence::load(dir).expect("sequence");
    let model = persist::model_file::load(Path::new(&a[2])).expect("model");
    let only: Option<usize> = a.get(3).map(|s| s.parse().expect("EVENT"));
    let s = Samples::new(&seq, 1);
    let pr = eval::predict(&model, &seq, &s, false).expect("predict");
    let np = s.npix();
    let mut cells: BTreeMap<(i64, i64), Cell> = BTreeMap::new();
    for (row, &k) in s.exposures.iter().enumerate() {
        if only.is_some_and(|e| s.event[row] != seq.illuminations[e]) {
            continue;
        }
        let meta = &seq.exposures[k].meta;
        let path = truth_path(dir, meta.detector.0, meta.exposure_index);
        let truth = read_truth(&path, (seq.ny, seq.nx)).expect("truth file");
        let tb = (s.t_since_s[row].log10() * 4.0).floor() as i64;
        for (p, &(y, x)) in s.pixels.iter().enumerate() {
            let i = row * np + p;
            let fl = s.fluence_e[i];
            if fl.is_nan() || fl <= 1e3 || !pr.current[i].is_finite() {
                continue;
            }
            let fb = (fl.log10() * 2.0).floor() as i64;
            let c = cells.entry((fb, tb)).or_default();
            c.0.push(f64::from(truth[[y, x]]));
            c.1.push(pr.current[i]);
        }
    }
    // per cell with at least 5 samples: the truth's median and the model's
    let medians: BTreeMap<(i64, i64), (f64, f64)> = cells
        .into_iter()
        .filter(|(_, c)| c.0.len() >= 5)
        .map(|(k, (t, m))| (k, (med(t), med(m))))
        .collect();
    let tbs: Vec<i64> = {
        let mut v: Vec<i64> = medians.keys().map(|k| k.1).collect();
        v.sort();
        v.dedup();
        v
    };
    print!("{:>9}", "F \\ t s");
    for t in &tbs {
        print!("{:>7.0}", 10f64.powf((*t as f64 + 0.5) / 4.0));
    }
    println!("   (truth/model median, / first bin)");
    let fbs: Vec<i64> = {
        let mut v: Vec<i64> = medians.keys().map(|k| k.0).collect();
        v.sort();
        v.dedup();
        v
    };
    let table = |what: &dyn Fn((f64, f64), f64) -> f64, divide: bool, digits: usize| {
        for fb in &fbs {
            print!("{:>9.0}", 10f64.powf((*fb as f64 + 0.5) / 2.0));
            let mut first = None;
            for t in &tbs {
                match medians.get(&(*fb, *t)) {
                    Some(&c) => {
                        let r = what(c, 10f64.powf((*t as f64 + 0.5) / 4.0));
                        let f0 = if divide { *first.get_or_insert(r) } else { 1.0 };
                        print!("{:>7.digits$}", r / f0);
                    }
                    _ => print!("{:>7}", "."),
                }
            }
            println!();
        }
    };
    let ratio = |(truth, model): (f64, f64), _| truth / model;
    table(&ratio, true, 2);
    if only.is_some() {
        println!("truth/model median");
        table(&ratio, false, 2);
        println!("truth median, e-/s");
        table(&|(truth, _), _| truth, false, 3);
        println!("model median, e-/s");
        table(&|(_, model), _| model, false, 3);
    }
    println!("truth x t (/ first bin): 1/t decay is a row of ones");
    table(&|(truth, _), t| truth * t, true, 2);
    println!("model x t (/ first bin)");
    table(&|(_, model), t| model * t, true, 2);
}
