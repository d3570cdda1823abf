//! The sky survey: zodiacal light, saturating stars, persistence carried to the next
//! exposure, deep-field repeats, the zodiacal persistence floor (paper section 5).

use persist::flags::bits;
use persist::sim::sky::{self, FieldKind, SkyConfig};
use persist::sim::SimExposure;
use persist::stats::median;

fn run() -> (SkyConfig, Vec<SimExposure>) {
    let cfg = SkyConfig {
        size: 128,
        detectors: 1,
        exposures: 24,
        seed: 9,
        plane_fraction: 0.3,
        ..SkyConfig::default()
    };
    let mut all = Vec::new();
    sky::run(&cfg, |e| {
        all.push(e);
        Ok(())
    })
    .unwrap();
    (cfg, all)
}

#[test]
fn sky_has_zodi_saturating_stars_and_persistence() {
    let (cfg, all) = run();
    let plan = sky::plan(&cfg);
    let mut saturated = 0;
    let mut carried = Vec::new();
    for (k, e) in all.iter().enumerate() {
        let img: Vec<f64> = e.exposure.image.iter().map(|v| f64::from(*v)).collect();
        let m = median(&img);
        let z = plan[k].zodi_e_per_s;
        // faint Galactic-plane stars raise the median there; elsewhere it is the zodi
        assert!(
            plan[k].kind == FieldKind::Plane || (m - z - 0.01).abs() < 0.1 * z + 0.05,
            "exposure {k}: median {m} zodi {z}"
        );
        assert_eq!(e.exposure.meta.t_exposure_s, 112.0);
        let sat = e
            .exposure
            .flags
            .iter()
            .filter(|f| *f & bits::OVERFLOW != 0)
            .count();
        saturated += sat;
        if k + 1 < all.len() {
            let next = &all[k + 1].true_persistence;
            for ((f, _), p) in e
                .exposure
                .flags
                .iter()
                .zip(e.exposure.image.iter())
                .zip(next.iter())
            {
                if f & bits::OVERFLOW != 0 {
                    carried.push(f64::from(*p));
                }
            }
        }
    }
    assert!(saturated > 20, "{saturated}");
    let mc = median(&carried);
    println!("saturated pixels {saturated}, median persistence next exposure {mc:.3} e-/s");
    assert!(mc > 0.1, "{mc}");
    // zodiacal floor: unsaturated, faint pixels late in the run
    let last = &all[all.len() - 1];
    let floor: Vec<f64> = last
        .true_persistence
        .iter()
        .zip(last.true_flux.iter())
        .filter(|(_, f)| **f < 3.0)
        .map(|(p, _)| f64::from(*p))
        .collect();
    let mf = median(&floor);
    println!("zodiacal persistence floor {mf:.4} e-/s");
    // the paper quotes >= 0.002 e-/s from its conservative (95th percentile) model;
    // the median truth is lower
    assert!(mf > 0.0002 && mf < 0.02, "{mf}");
}

#[test]
fn deep_field_repeats_put_stars_on_the_same_pixels() {
    let (cfg, all) = run();
    let plan = sky::plan(&cfg);
    let deep: Vec<usize> = (0..plan.len())
        .filter(|&k| plan[k].kind == FieldKind::Deep && plan[k].field_id == 0)
        .collect();
    assert!(deep.len() >= 2);
    let (a, b) = (&all[deep[0]].true_flux, &all[deep[1]].true_flux);
    // correlation of log flux maps: the same stars within the half-pixel jitter
    let la: Vec<f64> = a.iter().map(|v| f64::from(*v).ln()).collect();
    let lb: Vec<f64> = b.iter().map(|v| f64::from(*v).ln()).collect();
    let n = la.len() as f64;
    let (ma, mb) = (la.iter().sum::<f64>() / n, lb.iter().sum::<f64>() / n);
    let cov: f64 = la.iter().zip(&lb).map(|(x, y)| (x - ma) * (y - mb)).sum();
    let va: f64 = la.iter().map(|x| (x - ma).powi(2)).sum();
    let vb: f64 = lb.iter().map(|y| (y - mb).powi(2)).sum();
    let r = cov / (va * vb).sqrt();
    // an ordinary field has unrelated stars
    let o = plan
        .iter()
        .position(|p| p.kind == FieldKind::Normal)
        .unwrap();
    let lo: Vec<f64> = all[o]
        .true_flux
        .iter()
        .map(|v| f64::from(*v).ln())
        .collect();
    let mo = lo.iter().sum::<f64>() / n;
    let vo: f64 = lo.iter().map(|x| (x - mo).powi(2)).sum();
    let ro = la
        .iter()
        .zip(&lo)
        .map(|(x, y)| (x - ma) * (y - mo))
        .sum::<f64>()
        / (va * vo).sqrt();
    println!("deep-field repeat correlation {r:.3}, against another field {ro:.3}");
    assert!(r > 0.5 && ro.abs() < 0.2, "{r} {ro}");
}
