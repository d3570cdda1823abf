//! Per fluence x time cell of one illumination of a simulated laboratory sequence: the
//! spread (1.4826 MAD) of `measured - truth`, the measurement noise alone (truth: the
//! noise-free `truth/*.truth.hdf5` `/true_persistence`), against the RMS of the
//! exposure noise `sigma_k` that `compare` and `diagnose` give every sample (from the
//! background pixels, docs of `persist::diag::data`) and against
//! `sqrt(sigma_k^2 + 1.2 / t_exposure_s * truth)`, which adds the persistence current's
//! own shot noise in an unweighted line fit of evenly spaced reads (`6 / (5 T)` per e-/s
//! for many reads; `persist::sim::detector`), and against the same with the current at
//! the line fit's level (the truth plus the cell's median of `measured - truth`).
//! In the first dark the truth is the mean over the integration, not the line fit's
//! value, so its median differs by definition.
//!
//! ```sh
//! target/release/examples/noise_check LAB_DIR ILLUMINATION   # 0, 1, ...
//! ```
use persist::diag::compare::read_truth;
use persist::diag::data::Sequence;
use persist::diag::eval::{self, Samples};
use persist::sim::analysis::median;
use persist::sim::output::truth_path;
use std::collections::BTreeMap;
use std::path::Path;

/// One fluence x time cell: per sample measured minus truth, the exposure noise and the
/// noise with shot noise; the integration's length; per sample the truth.
#[derive(Default)]
struct Cell(Vec<f64>, Vec<f64>, Vec<f64>, f64, Vec<f64>);

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let dir = Path::new(&a[1]);
    let seq = Sequence::load(dir).expect("sequence");
    let ev: usize = a[2].parse().expect("event");
    let s = Samples::new(&seq, 2);
    let np = s.npix();
    let mut cells: BTreeMap<(i64, i64), Cell> = BTreeMap::new();
    for (row, &k) in s.exposures.iter().enumerate() {
        if s.event[row] != seq.illuminations[ev] {
            continue;
        }
        let meta = &seq.exposures[k].meta;
        let truth = read_truth(
            &truth_path(dir, meta.detector.0, meta.exposure_index),
            (seq.ny, seq.nx),
        )
        .expect("truth");
        for (p, &(y, x)) in s.pixels.iter().enumerate() {
            let i = row * np + p;
            if !s.measured[i].is_finite() {
                continue;
            }
            let (Some(f), Some(t)) = (eval::bin_of(&s, "fluence", i), eval::bin_of(&s, "time", i))
            else {
                continue;
            };
            let c = cells.entry((f, t)).or_default();
            let tr = f64::from(truth[[y, x]]);
            c.0.push(s.measured[i] - tr);
            c.1.push(s.noise[row]);
            c.2.push((s.noise[row].powi(2) + 1.2 / meta.t_exposure_s * tr.max(0.0)).sqrt());
            c.3 = meta.t_exposure_s;
            c.4.push(tr);
        }
    }
    println!("log10F  t_s      n  T_s  med(m-t) sd(m-t)  sigma_k  with_shot  at_fit_level");
    for ((f, t), Cell(d, sk, ss, te, tr)) in &cells {
        if d.len() < 10 {
            continue;
        }
        let med = median(d);
        let dev: Vec<f64> = d.iter().map(|x| (x - med).abs()).collect();
        let sd = 1.4826 * median(&dev);
        let rms = |v: &Vec<f64>| (v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64).sqrt();
        // the shot term at the line fit's level (the truth shifted by the cell's median
        // of measured - truth), the current the statistic's prediction stands for
        let at_fit: Vec<f64> = tr
            .iter()
            .zip(sk)
            .map(|(c, n)| (n * n + 1.2 / te * (c + med).max(0.0)).sqrt())
            .collect();
        println!(
            "{:5.1} {:6.0} {:5} {:5.0} {:8.4} {:8.4} {:8.4} {:8.4} {:8.4}",
            *f as f64 / 5.0,
            eval::bin_value("time", *t),
            d.len(),
            te,
            med,
            sd,
            rms(sk),
            rms(ss),
            rms(&at_fit)
        );
    }
}
