//! Every sample `persist verify` measures, one CSV line each, for looking at the
//! measurement's errors against the simulator's truth sample by sample.
//!
//! ```sh
//! target/release/examples/verify_samples SKY_DIR STAGE_OUTPUT_DIR > samples.csv
//! ```
use persist::verify::{run_observing, VerifyParams};
use std::io::Write;
use std::path::Path;

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let out = std::io::stdout();
    let mut w = std::io::BufWriter::new(out.lock());
    writeln!(
        w,
        "det,y,x,cluster,fluence_e,time_s,excess,sigma,control,control_truth,predicted_excess,flagged,truth_excess,first"
    )
    .expect("stdout");
    run_observing(
        Path::new(&a[1]),
        Path::new(&a[2]),
        &VerifyParams::default(),
        &mut |d, s| {
            writeln!(
                w,
                "{d},{},{},{},{:.0},{:.1},{:.5},{:.5},{:.5},{:.5},{:.5},{},{:.5},{}",
                s.y,
                s.x,
                s.cluster,
                s.event_fluence_e,
                s.time_s,
                s.excess_e_per_s,
                s.sigma_e_per_s,
                s.control_e_per_s,
                s.control_true_e_per_s,
                s.predicted_excess_e_per_s,
                u8::from(s.flagged),
                s.true_excess_e_per_s.unwrap_or(f64::NAN),
                u8::from(s.first)
            )
            .expect("stdout");
        },
    )
    .expect("verify");
}
