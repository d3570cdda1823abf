//! The normalised residual RMS of the fluence x time cells when the measurements are
//! drawn from the model itself (its prediction plus each exposure's Gaussian noise):
//! what the statistic gives when nothing is missing. `RMS ~ 1` means the cells' `z`
//! are calibrated; more means the statistic itself has a floor.
//!
//! ```sh
//! target/release/examples/null_rms LAB_DIR MODEL.json [STRIDE] [SEED]
//! ```
use persist::diag::data::Sequence;
use persist::diag::eval::{self, Samples};
use rand::{Rng, SeedableRng};
use rand_distr::StandardNormal;
use std::path::Path;

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let seq = Sequence::load(Path::new(&a[1])).expect("sequence");
    let model = persist::model_file::load(Path::new(&a[2])).expect("model");
    let stride: usize = a.get(3).map_or(2, |s| s.parse().expect("stride"));
    let seed: u64 = a.get(4).map_or(1, |s| s.parse().expect("seed"));
    // the cells of the figures measured with this example (docs/validation/diagnose_matrix.md),
    // the library's defaults then; the defaults are now per illumination and paired
    let mut s = Samples::new(&seq, stride)
        .with_cells(eval::Cells::Pooled)
        .with_statistic(eval::CellStatistic::Levels);
    let pr = eval::predict(&model, &seq, &s, false).expect("predict");
    let real = eval::cell_z(&s, &pr.current);
    println!("measured: cells {} rms {:.3}", real.len(), eval::rms(&real));
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let np = s.npix();
    for i in 0..s.len() {
        if s.measured[i].is_finite() {
            let sd = s.noise[i / np];
            s.measured[i] = pr.current[i] + sd * rng.sample::<f64, _>(StandardNormal);
        }
    }
    let null = eval::cell_z(&s, &pr.current);
    println!(
        "drawn from the model: cells {} rms {:.3}",
        null.len(),
        eval::rms(&null)
    );
    let mut worst: Vec<_> = null.iter().collect();
    worst.sort_by(|x, y| y.1.z.abs().total_cmp(&x.1.z.abs()));
    for (k, g) in worst.iter().take(8) {
        println!(
            "  fluence >= {:.3e} t >= {:.0} s: n {} p95 meas {:.4} pred {:.4} median {:.4} sigma {:.5} z {:.2}",
            eval::bin_value("fluence", k[0]),
            eval::bin_value("time", k[1]),
            g.n,
            g.measured_p95_e_per_s,
            g.predicted_p95_e_per_s,
            g.measured_median_e_per_s,
            g.sigma_e_per_s,
            g.z
        );
    }
    let mean_z = null.iter().map(|(_, g)| g.z).sum::<f64>() / null.len() as f64;
    println!("mean z {mean_z:.3}");
}
