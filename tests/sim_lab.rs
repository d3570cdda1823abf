//! The laboratory scenario analysed as in the paper (section 2.2, Table 1, Fig. 4, 5).

use persist::flags::bits;
use persist::sim::analysis::density_peaks;
use persist::sim::lab::{self, LabConfig};
use persist::sim::SimExposure;
use persist::stats::{clipped_median, loglog_slope, median};
use std::sync::OnceLock;

const DARK: f64 = 0.01;

struct Run {
    fluence: Vec<f64>,
    /// dark-subtracted line-fit currents of each dark integration, per pixel
    darks: Vec<Vec<f64>>,
    usable: Vec<bool>,
}

fn run() -> &'static Run {
    static RUN: OnceLock<Run> = OnceLock::new();
    RUN.get_or_init(|| {
        let cfg = LabConfig {
            size: 256,
            darks: 101,
            seed: 3,
            ..LabConfig::default()
        };
        let mut all: Vec<SimExposure> = Vec::new();
        lab::run(&cfg, |e| {
            all.push(e);
            Ok(())
        })
        .unwrap();
        analyse(&all)
    })
}

fn analyse(all: &[SimExposure]) -> Run {
    let ill = &all[0].exposure;
    let t_ill = ill.meta.t_illuminated_s();
    let fluence: Vec<f64> = ill.image.iter().map(|v| f64::from(*v) * t_ill).collect();
    let mut usable: Vec<bool> = ill
        .flags
        .iter()
        .zip(ill.image.iter())
        .map(|(f, v)| f & (bits::NONFUNC | bits::TRANSIENT) == 0 && v.is_finite())
        .collect();
    let mut darks = Vec::new();
    for e in &all[1..] {
        let img: Vec<f64> = e.exposure.image.iter().map(|v| f64::from(*v)).collect();
        for (u, f) in usable.iter_mut().zip(e.exposure.flags.iter()) {
            if f & bits::TRANSIENT != 0 && darks.is_empty() {
                *u = false;
            }
        }
        // dark subtraction with the detector's dark current (a dark calibration)
        let bg = DARK;
        darks.push(img.iter().map(|v| v - bg).collect());
    }
    Run {
        fluence,
        darks,
        usable,
    }
}

fn bin(r: &Run, lo: f64, hi: f64, k: usize) -> Vec<f64> {
    (0..r.fluence.len())
        .filter(|&i| r.usable[i] && r.fluence[i] >= lo && r.fluence[i] < hi)
        .map(|i| r.darks[k][i])
        .collect()
}

/// Paper Table 1 "Average Slope" of the first dark integration, within 25 %.
#[test]
fn table1_slopes_within_25_percent() {
    let r = run();
    let table = [
        (101e3, 1.4),
        (201e3, 3.6),
        (401e3, 17.2),
        (1.54e6, 16.3),
        (3.833e6, 20.3),
    ];
    let mut bad = Vec::new();
    for (f, want) in table {
        let v = bin(r, f * 0.98, f * 1.02, 0);
        let (m, _) = clipped_median(&v, 3.0);
        println!(
            "fluence {f:>9.0}: {:>4} px, clipped median {m:6.2} e-/s, paper {want}",
            v.len()
        );
        assert!(v.len() >= 50, "bin {f}: only {} pixels", v.len());
        if m.is_nan() || (m / want - 1.0).abs() > 0.25 {
            bad.push((f, m, want));
        }
    }
    assert!(bad.is_empty(), "{bad:?}");
}

/// Paper Fig. 4b: three peaks near 3, 17 and 22.5 e-/s in the 260k-270k e- bin.
#[test]
fn three_peaks_in_260k_bin() {
    let r = run();
    let v = bin(r, 260e3, 270e3, 0);
    let p = density_peaks(&v, 0.7, 0.0, 40.0, 0.1);
    println!("{} px, peaks {p:?}", v.len());
    assert_eq!(p.len(), 3, "{p:?}");
    let want = [3.0, 17.0, 22.5];
    for (a, b) in p.iter().zip(want) {
        assert!((a - b).abs() < 0.2 * b + 0.5, "peak {a} vs {b}");
    }
}

/// Paper Fig. 5: close to 1/t between 10 min and 5 h.
#[test]
fn dark_sequence_decays_close_to_one_over_t() {
    let r = run();
    let mut t = Vec::new();
    let mut c = Vec::new();
    for k in 0..r.darks.len() {
        let mid = 180.0 * k as f64 + 90.0;
        if !(600.0..=18_000.0).contains(&mid) {
            continue;
        }
        let v = bin(r, 4e5, 4e6, k);
        t.push(mid);
        c.push(median(&v));
    }
    let s = loglog_slope(&t, &c);
    println!(
        "log-log slope {s:.3} over {} darks, {:.3} -> {:.4} e-/s",
        t.len(),
        c[0],
        c[c.len() - 1]
    );
    assert!((-1.2..=-0.8).contains(&s), "slope {s}");
}

/// `--campaign`: several illuminations (durations, fluxes, temperatures, a repeat) with
/// shorter dark gaps; persistence from a repeated illumination does not simply add.
#[test]
fn campaign_chains_illuminations() {
    let cfg = LabConfig {
        size: 48,
        seed: 2,
        campaign: Some(lab::Illumination::default_campaign()),
        ..LabConfig::default()
    };
    let mut all: Vec<SimExposure> = Vec::new();
    lab::run(&cfg, |e| {
        all.push(e);
        Ok(())
    })
    .unwrap();
    let ill: Vec<usize> = (0..all.len())
        .filter(|&k| all[k].kind == "illuminated")
        .collect();
    assert_eq!(ill.len(), 5);
    assert_eq!(all.len(), 5 + 20 + 10 + 10 + 20 + 60);
    let t: Vec<f64> = ill
        .iter()
        .map(|&k| all[k].exposure.meta.t_illuminated_s.unwrap())
        .collect();
    assert_eq!(t, vec![481.0, 240.0, 240.0, 120.0, 481.0]);
    let temps: Vec<f64> = ill
        .iter()
        .map(|&k| all[k].exposure.meta.focal_plane_temp_k.unwrap().round())
        .collect();
    assert_eq!(temps, vec![80.0, 80.0, 80.0, 78.0, 82.0]);
    // consecutive indices, contiguous times
    for w in all.windows(2) {
        let (a, b) = (&w[0].exposure.meta, &w[1].exposure.meta);
        assert_eq!(b.exposure_index, a.exposure_index + 1);
        assert!((b.t_start.0 - a.t_reset().0).abs() < 1e-3);
    }
    // the repeat (3rd illumination) leaves about the same first-dark persistence as the
    // 2nd: traps fill towards the same equilibrium, they do not add up
    let m = |k: usize| {
        median(
            &all[k + 1]
                .true_persistence
                .iter()
                .map(|v| f64::from(*v))
                .collect::<Vec<_>>(),
        )
    };
    let (p2, p3) = (m(ill[1]), m(ill[2]));
    println!("first-dark median truth after illuminations 2 and 3: {p2:.4} {p3:.4}");
    assert!((p3 / p2 - 1.0).abs() < 0.15, "{p2} {p3}");
}
