//! Per cell of one illumination (the library's default cells and paired statistic):
//! what the residuals `d = measured - predicted` are made of. Under the model's reading
//! (the prediction is the 95th percentile of a Gaussian population of spread `s`, plus
//! each sample's Gaussian noise `sigma`), the median of `d` is `-1.645 s` and its 95th
//! percentile `1.645 (sqrt(s^2 + sigma^2) - s)`. The paired statistic's reference, the
//! 95th percentile of the noise alone (`1.645 sigma`), is that only when `s = 0`.
//!
//! Prints, per cell: n, sigma (the samples' exposure noise, RMS), median(d), the MAD
//! spread of d, P95(d), the paired reference (`ref0`), the reference with the spread
//! `s = max(0, -median(d)) / 1.645` (`ref_s`), `z` as the library computes it and `z_s`
//! against `ref_s`; then the RMS of both over the illumination's cells. This is what
//! tells how much of the residual floor is the population's own spread `s`.
//!
//! ```sh
//! target/release/examples/cell_parts LAB_DIR MODEL.json ILLUMINATION_EXPOSURE
//! ```
use persist::diag::data::Sequence;
use persist::diag::eval::{self, Samples};
use persist::stats::median;
use std::collections::BTreeMap;
use std::path::Path;

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let seq = Sequence::load(Path::new(&a[1])).expect("sequence");
    let model = persist::model_file::load(Path::new(&a[2])).expect("model");
    let event: usize = a[3].parse().expect("illumination exposure");
    let s = Samples::new(&seq, 2);
    let pr = eval::predict(&model, &seq, &s, false).expect("predict");
    let np = s.npix();
    let mut cells: BTreeMap<(i64, i64), (Vec<f64>, Vec<f64>)> = BTreeMap::new();
    for i in 0..s.len() {
        let row = i / np;
        if s.event[row] != event || !s.measured[i].is_finite() || !pr.current[i].is_finite() {
            continue;
        }
        let (Some(f), Some(t)) = (eval::bin_of(&s, "fluence", i), eval::bin_of(&s, "time", i))
        else {
            continue;
        };
        let c = cells.entry((f, t)).or_default();
        c.0.push(s.measured[i] - pr.current[i]);
        c.1.push(s.noise[row]);
    }
    println!("log10F  t_s      n   sigma   med(d)  sd(d)   P95(d)  ref0    ref_s   z      z_s");
    let (mut z2, mut zs2, mut k) = (0.0, 0.0, 0.0);
    for ((f, t), (d, sg)) in &cells {
        if d.len() < 10 {
            continue;
        }
        let sigma = (sg.iter().map(|v| v * v).sum::<f64>() / sg.len() as f64).sqrt();
        let np95 = eval::noise_p95(sg);
        let (p, sq, z) = eval::paired_z(d, sigma, np95);
        let med = median(d);
        let dev: Vec<f64> = d.iter().map(|x| (x - med).abs()).collect();
        let sd = 1.4826 * median(&dev);
        let spread = (-med).max(0.0) / 1.645;
        let ref_s = -1.645 * spread + 1.645 * (spread * spread + sigma * sigma).sqrt();
        let z_s = (p - ref_s) / sq;
        z2 += z * z;
        zs2 += z_s * z_s;
        k += 1.0;
        println!(
            "{:5.1} {:7.0} {:6} {:7.4} {:7.4} {:7.4} {:7.4} {:7.4} {:7.4} {:6.2} {:6.2}",
            *f as f64 / 5.0,
            eval::bin_value("time", *t),
            d.len(),
            sigma,
            med,
            sd,
            p,
            np95,
            ref_s,
            z,
            z_s
        );
    }
    println!(
        "cells {k}: rms z {:.2}, rms z_s {:.2}",
        (z2 / k).sqrt(),
        (zs2 / k).sqrt()
    );
}
