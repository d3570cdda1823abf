//! Two candidate effects compared nested, on `diagnose`'s own cells (its random pixel
//! subsample, default seed): each fitted alone on top of the reference (its other
//! effects held fixed, as `diagnose` refits), then both jointly, and the change in BIC
//! of adding each to the model that already has the other
//! (`m ln(RSS_joint / RSS_other) + k ln m`). The true effect should still lower the BIC
//! on top of a stand-in; a stand-in should not on top of the true effect.
//!
//! ```sh
//! target/release/examples/nested_refit LAB_DIR REFERENCE.json EFFECT_A EFFECT_B
//! ```
use persist::calib::effects as ceffects;
use persist::diag::data::Sequence;
use persist::diag::diagnose::{delta_bic, Config, DEFAULT_PIXELS};
use persist::diag::eval::Samples;
use std::path::Path;

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let seq = Sequence::load(Path::new(&a[1])).expect("sequence");
    let reference = persist::model_file::load(Path::new(&a[2])).expect("model");
    let (ea, eb) = (a[3].clone(), a[4].clone());
    // the cells of the figures measured with this example (docs/validation/diagnose_matrix.md),
    // the library's defaults then; the defaults are now per illumination and paired
    let s = Samples::random(&seq, DEFAULT_PIXELS, Config::default().seed)
        .with_cells(persist::diag::eval::Cells::Pooled)
        .with_statistic(persist::diag::eval::CellStatistic::Levels);
    let fit = |names: &[String]| {
        let (_, f) = ceffects::fit(&reference, names, &seq, &s).expect("fit");
        let (before, after) = f.rss_before_after();
        (before, after, f.params.len(), f.cells)
    };
    let (r0, ra, ka, m) = fit(std::slice::from_ref(&ea));
    let (_, rb, kb, _) = fit(std::slice::from_ref(&eb));
    let (_, rab, _, _) = fit(&[ea.clone(), eb.clone()]);
    let dbic = |r1: f64, r0: f64, k: usize| delta_bic(r0, r1, k, m);
    let rms = |r: f64| (r / m as f64).sqrt();
    println!(
        "cells {m}; RMS reference {:.3}, +{ea} {:.3}, +{eb} {:.3}, both {:.3}",
        rms(r0),
        rms(ra),
        rms(rb),
        rms(rab)
    );
    println!(
        "dBIC {ea} on the reference {:.1}; {eb} on the reference {:.1}",
        dbic(ra, r0, ka),
        dbic(rb, r0, kb)
    );
    println!(
        "dBIC {ea} on top of {eb} {:.1}; {eb} on top of {ea} {:.1}",
        dbic(rab, rb, ka),
        dbic(rab, ra, kb)
    );
}
