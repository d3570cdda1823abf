//! The decay's shape against the fluence, as `persist diagnose` measures it
//! (`persist::diag::shape`) on its default sample of pixels: each fluence bin's tilt
//! against the faintest after the first illumination, and the largest rise. Needs no
//! model. Prints one line per bin with `-v`, then one summary line.
//!
//! ```sh
//! target/release/examples/shape_tilt LAB_DIR [-v]
//! ```
use persist::diag::config::Config;
use persist::diag::data::Sequence;
use persist::diag::eval::Samples;
use persist::diag::shape;
use std::path::Path;

fn main() {
    let a: Vec<String> = std::env::args().collect();
    if a.len() < 2 {
        eprintln!("usage: shape_tilt LAB_DIR [-v]");
        std::process::exit(2);
    }
    let seq = Sequence::load(Path::new(&a[1])).expect("sequence");
    let cfg = Config::default();
    let s = Samples::random(&seq, cfg.pixels, cfg.seed);
    let Some(d) = shape::measure(&s, 0) else {
        println!(
            "{}: fewer than two fluence bins span a decade of time",
            a[1]
        );
        return;
    };
    if a.get(2).is_some_and(|v| v == "-v") {
        for b in &d.bins {
            println!(
                "  10^{:.1} e-: tilt {:+.3} +- {:.3} ({} samples)",
                b.log10_fluence_e, b.tilt, b.tilt_se, b.samples
            );
        }
    }
    println!(
        "{}: rise {:.3} (z {:.1}) from 10^{:.1} to 10^{:.1} e-, depends: {}",
        a[1], d.rise, d.rise_z, d.from_log10_fluence_e, d.to_log10_fluence_e, d.depends
    );
}
