//! The knots of a model with a spatial effect (`crate::calib::knots`, "Spatial
//! effects"): each pixel's calibration values divided by the factor the effect gives
//! it, so that the 95th percentile is measured with the effect in place.

use persist::calib::{self, knots, CalibConfig};
use persist::diag::data::Sequence;
use persist::model::params::EffectSpec;
use persist::sim::lab::LabConfig;

mod common;

fn lab_single(size: usize) -> Sequence {
    common::lab_sequence(&LabConfig {
        size,
        seed: 3,
        ..LabConfig::default()
    })
}

fn populations(gx: f64) -> EffectSpec {
    let mut p = serde_json::Map::new();
    p.insert("gx".into(), serde_json::json!(gx));
    EffectSpec {
        params: p,
        ..EffectSpec::named("populations")
    }
}

/// `populations`' factor is its surface, `exp(gx u)` with `u` from -1 at the left edge
/// to +1 at the right (its module docs); at its null, and without effects, there is no
/// factor and the calibration is the paper's, bit for bit.
#[test]
fn populations_factor_is_its_surface_and_nothing_at_its_null() {
    let seq = lab_single(48);
    let cfg = CalibConfig::default();
    let (plain, _) = calib::calibrate(&seq, &cfg).unwrap();
    let ramp = knots::CalibRamp::of(&seq).unwrap();
    assert!(knots::spatial_factor(&plain, &seq, &ramp)
        .unwrap()
        .is_none());
    let mut null = plain.clone();
    null.effects.push(populations(0.0));
    assert!(knots::spatial_factor(&null, &seq, &ramp).unwrap().is_none());
    let mut m = plain.clone();
    m.effects.push(populations(0.7));
    let w = knots::spatial_factor(&m, &seq, &ramp)
        .unwrap()
        .expect("a factor");
    let nx = seq.nx as f64;
    // a pixel lit above the first knot (a zero amplitude has no ratio: factor 1)
    let f = persist::diag::data::fluence(&seq.exposures[ramp.illumination]);
    let mut checked = 0;
    for ((y, x), v) in w.indexed_iter() {
        if f[(y, x)] > plain.amplitude_knots[0].fluence_e {
            let u = (x as f64 - (nx - 1.0) / 2.0) / (nx / 2.0);
            assert!((v - (0.7 * u).exp()).abs() < 1e-9, "({y}, {x}): {v}");
            checked += 1;
        }
    }
    assert!(checked > 100, "{checked}");
    let (same, _) = calib::calibrate_with(&seq, &cfg, None).unwrap();
    assert_eq!(same.amplitude_knots, plain.amplitude_knots);
}

/// A uniform factor of 2 halves every knot: the bins' median, 95th percentile, noise
/// and ramp are all divided by it (the knot is the level at factor 1).
#[test]
fn a_uniform_factor_scales_the_knots() {
    let seq = lab_single(48);
    let cfg = CalibConfig::default();
    let (plain, _) = calib::calibrate(&seq, &cfg).unwrap();
    let two = ndarray::Array2::from_elem((seq.ny, seq.nx), 2.0);
    let (half, _) = calib::calibrate_with(&seq, &cfg, Some(&two)).unwrap();
    assert_eq!(half.amplitude_knots.len(), plain.amplitude_knots.len());
    for (a, b) in plain.amplitude_knots.iter().zip(&half.amplitude_knots) {
        assert_eq!(a.fluence_e, b.fluence_e);
        let r = b.amplitude_e / a.amplitude_e;
        assert!((r - 0.5).abs() < 1e-3, "{} e-: {r}", a.fluence_e);
    }
}
