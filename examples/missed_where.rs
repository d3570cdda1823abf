//! Where a model's missed flags at 0.1 e-/s fall among the samples a hidden effect
//! touches (`examples/diagnose_matrix`'s "missed of touched": [`eval::touched_samples`]
//! on the truths of two `persist simulate lab` runs of one seed, with and without the
//! effect), per illumination x time bin x fluence bin; and the missed fraction under two
//! other definitions of touched: a relative change of 10 % alone, and every sample of a
//! pixel touched at any sample (`compare --touched-baseline`).
//!
//! ```sh
//! target/release/examples/missed_where WITH_DIR WITHOUT_DIR MODEL.json [line|median]
//! ```
use persist::diag::compare::read_truth;
use persist::diag::data::{Background, Sequence};
use persist::diag::eval::{self, Samples};
use persist::sim::output::truth_path;
use std::collections::BTreeMap;
use std::path::Path;

fn truths(dir: &Path, seq: &Sequence) -> Vec<ndarray::Array2<f32>> {
    seq.exposures
        .iter()
        .map(|e| {
            read_truth(
                &truth_path(dir, e.meta.detector.0, e.meta.exposure_index),
                (seq.ny, seq.nx),
            )
            .expect("truth")
        })
        .collect()
}

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let bg = match a.get(4).map(String::as_str) {
        Some("line") => Background::Line,
        _ => Background::default(),
    };
    let (with, without) = (Path::new(&a[1]), Path::new(&a[2]));
    let seq = Sequence::load_with(with, bg).expect("sequence");
    let seq0 = Sequence::load_with(without, bg).expect("sequence");
    let p = persist::model_file::load(Path::new(&a[3])).expect("model");
    let s = Samples::new(&seq, 2);
    let (tw, t0) = (truths(with, &seq), truths(without, &seq0));
    let t = eval::touched_samples(&s, &tw, &t0);
    let fl = eval::predict(&p, &seq, &s, true).expect("predict");
    let q = eval::flag_quality_of_samples(&s, &fl.current, Some(&fl.flagged), 0.1, &t);
    println!(
        "touched {} of {}; missed {} ({:.4}), measured above {}",
        t.iter().filter(|&&x| x).count(),
        t.len(),
        q.missed,
        q.missed_flag_fraction,
        q.measured_above
    );
    // the same with a relative criterion only (10 %, no absolute floor), and over every
    // sample of a pixel touched at any sample (compare's `--touched-baseline`)
    let np = s.npix();
    let rel: Vec<bool> = (0..s.len())
        .map(|i| {
            let (k, (y, x)) = (s.exposures[i / np], s.pixels[i % np]);
            let (a, b) = (f64::from(tw[k][[y, x]]), f64::from(t0[k][[y, x]]));
            (a - b).abs() > 0.1 * b.abs() && b.abs().max(a.abs()) > 1e-3
        })
        .collect();
    let qr = eval::flag_quality_of_samples(&s, &fl.current, Some(&fl.flagged), 0.1, &rel);
    let px = eval::pixels_of(&s, &t);
    let qp = eval::flag_quality_of(&s, &fl.current, Some(&fl.flagged), 0.1, Some(&px));
    println!(
        "relative only: {} samples, missed {:.4}; every sample of a touched pixel: {} samples, missed {:.4}",
        rel.iter().filter(|&&x| x).count(),
        qr.missed_flag_fraction,
        px.iter().filter(|&&x| x).count() * (s.len() / np),
        qp.missed_flag_fraction
    );
    // per (illumination, time bin, fluence bin): the touched samples, the missed, and
    // the mean prediction, truth and measurement over the touched
    let mut cells: BTreeMap<(usize, i64, i64), Tally> = BTreeMap::new();
    for (i, (&touched, &m)) in t.iter().zip(&s.measured).enumerate() {
        if !touched || !m.is_finite() {
            continue;
        }
        let row = i / np;
        let (y, x) = s.pixels[i % np];
        let key = (
            s.event[row],
            eval::bin_of(&s, "time", i).unwrap_or(-99),
            eval::bin_of(&s, "fluence", i).unwrap_or(-99),
        );
        let c = cells.entry(key).or_default();
        c.touched += 1;
        c.missed += usize::from(m > 0.1 + 2.0 * s.noise[row] && !fl.flagged[i]);
        c.predicted += fl.current[i];
        c.truth += f64::from(tw[s.exposures[row]][[y, x]]);
        c.measured += m;
        c.temperature_k = s.temperature_k[row];
    }
    println!("event time_bin flu_bin  T_K  touched missed  mean_pred mean_truth mean_meas");
    for ((e, tb, fb), c) in cells.iter().filter(|(_, c)| c.missed > 0) {
        let n = c.touched as f64;
        println!(
            "{e:5} {tb:8} {fb:7} {:5.1} {:7} {:6}  {:.4} {:.4} {:.4}",
            c.temperature_k,
            c.touched,
            c.missed,
            c.predicted / n,
            c.truth / n,
            c.measured / n
        );
    }
}

#[derive(Default)]
struct Tally {
    touched: usize,
    missed: usize,
    predicted: f64,
    truth: f64,
    measured: f64,
    temperature_k: f64,
}
