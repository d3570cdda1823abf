//! Truth against model for single pixels through a laboratory sequence: for every
//! exposure after an illumination, the simulator's noise-free persistence current
//! (`truth/*.truth.hdf5` `/true_persistence`) and the model's prediction, with the
//! illumination event, the time since it and the pixel's fluence in that event. Shows
//! how the model carries one pixel's history (repeated illuminations, temperature).
//!
//! ```sh
//! target/release/examples/pixel_track LAB_DIR MODEL.json Y,X [Y,X ...]
//! ```
use persist::diag::compare::read_truth;
use persist::diag::data::Sequence;
use persist::diag::eval::{self, Samples};
use persist::sim::output::truth_path;
use std::path::Path;

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let dir = Path::new(&a[1]);
    let seq = Sequence::load(dir).expect("sequence");
    let model = persist::model_file::load(Path::new(&a[2])).expect("model");
    let pixels: Vec<(usize, usize)> = a[3..]
        .iter()
        .map(|s| {
            let (y, x) = s.split_once(',').expect("Y,X");
            (y.parse().expect("Y"), x.parse().expect("X"))
        })
        .collect();
    let s = Samples::with_pixels(&seq, pixels.clone(), 1);
    let pr = eval::predict(&model, &seq, &s, false).expect("predict");
    let np = s.npix();
    // the truth at the pixels, each exposure's file read once: [row * np + pixel]
    let truth: Vec<f64> = s
        .exposures
        .iter()
        .flat_map(|&k| {
            let meta = &seq.exposures[k].meta;
            let path = truth_path(dir, meta.detector.0, meta.exposure_index);
            let plane = read_truth(&path, (seq.ny, seq.nx)).expect("truth file");
            pixels
                .iter()
                .map(move |&(y, x)| f64::from(plane[[y, x]]))
                .collect::<Vec<f64>>()
        })
        .collect();
    for (p, &(y, x)) in pixels.iter().enumerate() {
        println!("pixel ({y}, {x})");
        println!(
            "{:>5} {:>9} {:>11} {:>10} {:>10} {:>6}",
            "event", "t_s", "fluence_e", "truth", "model", "ratio"
        );
        for row in 0..s.exposures.len() {
            let i = row * np + p;
            let t = truth[i];
            println!(
                "{:>5} {:>9.0} {:>11.4e} {:>10.4} {:>10.4} {:>6.2}",
                s.event[row],
                s.t_since_s[row],
                s.fluence_e[i],
                t,
                pr.current[i],
                t / pr.current[i]
            );
        }
    }
}
