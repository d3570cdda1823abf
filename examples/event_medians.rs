//! Per exposure after an illumination, medians over the stride-2 samples with fluence
//! in `[F_LO, F_HI)` of: the measured current of campaign A, of campaign B (the same
//! seed without the hidden effect), and the prediction of MODEL on A without and with
//! the model's `temperature` effect at its defaults. Shows where a model effect and the
//! truth's differ.
//!
//! ```sh
//! target/release/examples/event_medians LAB_A LAB_B MODEL.json F_LO F_HI
//! ```
use persist::diag::data::Sequence;
use persist::diag::eval::{self, Samples};
use std::path::Path;
fn med(mut v: Vec<f64>) -> f64 {
    v.retain(|x| x.is_finite());
    v.sort_by(|a, b| a.total_cmp(b));
    if v.is_empty() {
        f64::NAN
    } else {
        v[v.len() / 2]
    }
}
fn main() {
    let a: Vec<String> = std::env::args().collect();
    let sa = Sequence::load(Path::new(&a[1])).unwrap();
    let sb = Sequence::load(Path::new(&a[2])).unwrap();
    let m = persist::model_file::load(Path::new(&a[3])).unwrap();
    let (flo, fhi): (f64, f64) = (a[4].parse().unwrap(), a[5].parse().unwrap());
    let mut m1 = m.clone();
    m1.effects
        .push(persist::model::params::EffectSpec::named("temperature"));
    let s = Samples::new(&sa, 2);
    let sbm = Samples::new(&sb, 2);
    let p0 = eval::predict(&m, &sa, &s, false).unwrap().current;
    let p1 = eval::predict(&m1, &sa, &s, false).unwrap().current;
    let np = s.pixels.len();
    for r in 0..s.exposures.len() {
        let idx: Vec<usize> = (0..np)
            .map(|p| r * np + p)
            .filter(|&i| s.fluence_e[i] >= flo && s.fluence_e[i] < fhi)
            .collect();
        if idx.is_empty() {
            continue;
        }
        let g = |v: &Vec<f64>| med(idx.iter().map(|&i| v[i]).collect());
        println!("{:3} ev {:3} T {:.2} t {:8.0} n {:4} meas_a {:.4} meas_b {:.4} pred0 {:.4} pred_temp {:.4}",
            s.exposures[r], s.event[r], s.temperature_k[r], s.t_since_s[r], idx.len(), g(&s.measured), g(&sbm.measured), g(&p0), g(&p1));
    }
}
