//! The coverage calibration of `persist fit` (`persist::calib::coverage`) on a simulated
//! laboratory sequence, and what its time bins hold against the simulator's truth.
//!
//! ```sh
//! target/release/examples/coverage_bins [DARKS 280] [SIZE 64] [SEED 1] [truth]
//! ```
//! The laboratory campaign of `persist::pixmap::eval::lab_campaign` with `DARKS` darks of
//! 180 s after the first illumination (the demo's 30, the paper's 280), a corner of
//! `SIZE/8 x SIZE/8` pixels kept dark. Prints the coverage report of the calibrated
//! model (as `persist fit` does) and with the decay reshaped. With `truth`, per threshold
//! and time bin, the single samples (one pixel, one dark) of the calibrated model before
//! the margin: how many are measured above the threshold by 2 noise sigmas, how many of
//! those the truth has above it, how many the model flags, and the factor on the
//! predictions that would flag 95 % of them (all of them, or only the truly above).
use persist::calib::coverage::{self, CoverageConfig};
use persist::measure::eval::{predict, Samples};
use persist::sim::lab;
use std::collections::BTreeMap;

fn main() -> persist::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let darks: usize = args.get(1).and_then(|v| v.parse().ok()).unwrap_or(280);
    let size: usize = args.get(2).and_then(|v| v.parse().ok()).unwrap_or(64);
    let seed: u64 = args.get(3).and_then(|v| v.parse().ok()).unwrap_or(1);
    let with_truth = args.get(4).is_some_and(|a| a == "truth");
    let mut campaign = persist::pixmap::eval::lab_campaign();
    campaign[0].darks_after = darks;
    let cfg = lab::LabConfig {
        size,
        seed,
        campaign: Some(campaign),
        paper_pattern: Some(lab::PaperPattern { dark_pixels: true }),
        ..lab::LabConfig::default()
    };
    let mut exposures = Vec::new();
    let mut truth = Vec::new();
    lab::run(&cfg, |s| {
        exposures.push(s.exposure);
        truth.push(s.true_persistence);
        Ok(())
    })?;
    let seq = persist::measure::data::Sequence::from_exposures(exposures)?;
    let (lab, _) = persist::calib::calibrate(&seq, &persist::calib::CalibConfig::default())?;
    let (_, rep) = coverage::apply(&lab, &seq, &CoverageConfig::default())?;
    println!(
        "{darks} darks, {size} x {size}, seed {seed}:\n{}",
        rep.describe()
    );
    let shaped = CoverageConfig {
        shape: true,
        ..Default::default()
    };
    let (_, rep) = coverage::apply(&lab, &seq, &shaped)?;
    println!("decay reshaped:\n{}", rep.describe());
    if !with_truth {
        return Ok(());
    }
    let samples = Samples::new(&seq, 1);
    let np = samples.npix();
    let pr = predict(&lab, &seq, &samples, false)?;
    let bins_per_decade = CoverageConfig::default().bins_per_decade;
    println!("single samples of the calibrated model against the truth:");
    for thr in [0.1, 0.01] {
        // per bin: (all samples, mean noise sum), and the measured above: (predicted, truth)
        let mut all: BTreeMap<i64, (usize, f64)> = BTreeMap::new();
        let mut above: BTreeMap<i64, Vec<(f64, f64)>> = BTreeMap::new();
        for r in 0..samples.exposures.len() {
            let (t, sigma) = (samples.t_since_s[r], samples.noise[r]);
            if t.is_nan() || t <= 0.0 {
                continue;
            }
            let b = (t.log10() * bins_per_decade).floor() as i64;
            for (j, &(y, x)) in samples.pixels.iter().enumerate() {
                let m = samples.measured[r * np + j];
                if !m.is_finite() {
                    continue;
                }
                let a = all.entry(b).or_default();
                a.0 += 1;
                a.1 += sigma;
                if m > thr + 2.0 * sigma {
                    let tr = f64::from(truth[samples.exposures[r]][[y, x]]);
                    above
                        .entry(b)
                        .or_default()
                        .push((pr.current[r * np + j], tr));
                }
            }
        }
        for (b, v) in &above {
            let (n_all, sigma_sum) = all[b];
            let n = v.len();
            let truly = v.iter().filter(|s| s.1 > thr).count();
            let flagged = v.iter().filter(|s| s.0 > thr).count();
            let scale = |mut p: Vec<f64>| {
                p.sort_by(f64::total_cmp);
                p.get((0.05 * p.len() as f64).floor() as usize)
                    .map_or(f64::NAN, |pk| thr / pk)
            };
            let edge = |k: i64| 10f64.powf(k as f64 / bins_per_decade);
            println!(
                "  {thr} e-/s, {:.0}-{:.0} s: {n_all} samples, noise {:.4} e-/s; measured above \
                 {n} ({:.2} %), truly above {truly} ({:.1} %), flagged {flagged} ({:.1} %); \
                 95 % flagged at x {:.2} (truly above only: x {:.2})",
                edge(*b),
                edge(b + 1),
                sigma_sum / n_all as f64,
                100.0 * n as f64 / n_all as f64,
                100.0 * truly as f64 / n as f64,
                100.0 * flagged as f64 / n as f64,
                scale(v.iter().map(|s| s.0).collect()),
                scale(v.iter().filter(|s| s.1 > thr).map(|s| s.0).collect()),
            );
        }
    }
    Ok(())
}
