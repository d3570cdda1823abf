//! The second truth generator (`persist simulate family`, `persist::trapgen`):
//! determinism, physics against hand-computed values, valid products, and `fit` on
//! its all-lit single illumination.

use persist::trapgen::engine::{Engine, CEILING_SITES};
use persist::trapgen::hidden::Hidden;
use persist::trapgen::scene::Nuisance;
use std::path::Path;
use std::process::Command;

fn persist(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_persist"))
        .args(args)
        .env("PERSIST_LOG", "error")
        .output()
        .expect("run persist")
}

fn simulate(dir: &Path, extra: &[&str]) {
    let mut a = vec!["simulate", "family", "--out", dir.to_str().unwrap()];
    a.extend_from_slice(extra);
    let o = persist(&a);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
}

fn files(dir: &Path) -> Vec<std::path::PathBuf> {
    let mut v = Vec::new();
    for sub in [dir.to_path_buf(), dir.join("truth")] {
        for e in std::fs::read_dir(sub).unwrap().flatten() {
            if e.path().is_file() {
                v.push(e.path());
            }
        }
    }
    v.sort();
    v
}

#[test]
fn same_seed_gives_identical_bytes_and_valid_products() {
    let t = tempfile::tempdir().unwrap();
    let (a, b, c) = (t.path().join("a"), t.path().join("b"), t.path().join("c"));
    let args = [
        "--seed",
        "3",
        "--size",
        "16",
        "--darks",
        "4",
        "--hidden",
        "soak:capture",
    ];
    simulate(&a, &args);
    simulate(&b, &args);
    let (fa, fb) = (files(&a), files(&b));
    assert_eq!(fa.len(), fb.len());
    assert_eq!(fa.len(), 5 + 5 + 1, "5 products, 5 truths, truth.json");
    for (x, y) in fa.iter().zip(&fb) {
        assert_eq!(
            std::fs::read(x).unwrap(),
            std::fs::read(y).unwrap(),
            "{} differs",
            x.display()
        );
    }
    // another seed gives other bytes
    simulate(&c, &["--seed", "4", "--size", "16", "--darks", "4"]);
    assert_ne!(
        std::fs::read(a.join("d1_e000001.h5")).unwrap(),
        std::fs::read(c.join("d1_e000001.h5")).unwrap()
    );
    // every product validates; the first dark keeps its ramp
    let products: Vec<String> = fa
        .iter()
        .filter(|p| p.extension().is_some_and(|e| e == "h5"))
        .map(|p| p.display().to_string())
        .collect();
    let mut v = vec!["validate"];
    v.extend(products.iter().map(|s| s.as_str()));
    let o = persist(&v);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_eq!(
        String::from_utf8_lossy(&o.stdout)
            .matches("ok l1_exposure")
            .count(),
        5
    );
    let e = persist::product::read_exposure(&a.join("d1_e000001.h5")).unwrap();
    assert!(e.ramp.is_some() && e.ramp_times_s.is_some());
    assert_eq!(e.meta.t_exposure_s, 180.0);
    let e0 = persist::product::read_exposure(&a.join("d1_e000000.h5")).unwrap();
    assert_eq!(e0.meta.t_illuminated_s, Some(481.0));
    // the truth records the generator, the hidden form and no simulator effect
    let tj: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(a.join("truth/truth.json")).unwrap())
            .unwrap();
    assert_eq!(tj["scenario"], "family");
    assert_eq!(tj["hidden"][0], "soak:capture");
    assert_eq!(tj["effects"].as_array().unwrap().len(), 0);
}

#[test]
fn campaign_products_validate() {
    let t = tempfile::tempdir().unwrap();
    let d = t.path().join("c");
    simulate(
        &d,
        &[
            "--seed",
            "2",
            "--size",
            "16",
            "--sequence",
            "campaign",
            "--dark-pixels",
            "--hidden",
            "temperature:arrhenius",
        ],
    );
    let products: Vec<String> = files(&d)
        .iter()
        .filter(|p| p.extension().is_some_and(|e| e == "h5"))
        .map(|p| p.display().to_string())
        .collect();
    assert_eq!(products.len(), 6 + 125);
    let mut v = vec!["validate"];
    v.extend(products.iter().map(|s| s.as_str()));
    let o = persist(&v);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
}

/// A uniform flux over a small array, for the engine's physics checks.
fn flat(n: usize, flux: f32) -> ndarray::Array2<f32> {
    ndarray::Array2::from_elem((n, n), flux)
}

fn engine(hidden: &[Hidden]) -> Engine {
    let n = 4;
    Engine::new(Nuisance::draw(7, n, Some(false)), n, 7, hidden)
}

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len() as f64
}

/// Trapped charge after one illumination of `t_ill` s at `flux` (+132 s held).
fn trapped_after(hidden: &[Hidden], flux: f32, t_ill: f64) -> f64 {
    let mut e = engine(hidden);
    e.illuminate(0, &flat(4, flux), t_ill, t_ill + 132.0, 80.0);
    mean(&e.trapped())
}

#[test]
fn capacity_ceiling_holds_a_pixel_at_its_ceiling() {
    // two saturating illuminations 15 min apart
    let run = |hidden: &[Hidden]| {
        let mut e = engine(hidden);
        e.illuminate(0, &flat(4, 1.0e5), 481.0, 613.0, 80.0);
        e.dark(1, 900.0, 80.0, false);
        e.illuminate(2, &flat(4, 1.0e5), 481.0, 613.0, 80.0);
        let sites = e.sites();
        e.trapped()
            .iter()
            .zip(&sites)
            .map(|(q, s)| q / s)
            .fold(0.0f64, f64::max)
    };
    let with = run(&[Hidden::CapacityCeiling]);
    let without = run(&[]);
    // saturated: exposure fraction 1 + jump > 1.1, capture complete within 481 s
    assert!(
        without > 0.9,
        "without a ceiling a saturated pixel holds {without} of its sites"
    );
    assert!(
        with <= CEILING_SITES + 1e-9,
        "ceiling {CEILING_SITES}, held {with}"
    );
    assert!(
        with > CEILING_SITES - 0.01,
        "the ceiling is reached: {with}"
    );
}

#[test]
fn a_shorter_illumination_at_equal_fluence_fills_less_under_a_soak_form() {
    // 96,200 e- (below full well) in 481 s or in 120 s
    let ratio = |hidden: &[Hidden]| {
        trapped_after(hidden, 200.0 * 481.0 / 120.0, 120.0) / trapped_after(hidden, 200.0, 481.0)
    };
    let base = ratio(&[]);
    let capture = ratio(&[Hidden::SoakCapture]);
    let diffusion = ratio(&[Hidden::SoakDiffusion]);
    // without soak, capture at ~0.2/s is complete either way: equal fills within 10 %
    assert!((base - 1.0).abs() < 0.1, "nothing hidden: ratio {base}");
    // slow nodes capture at 1/400 s: 1 - e^(-252/400) = 0.47 vs 1 - e^(-613/400) = 0.78
    assert!(capture < base - 0.1, "soak:capture: {capture} vs {base}");
    // deep layer: sqrt(252/2000) = 0.35 vs sqrt(613/2000) = 0.55 of its sites
    assert!(
        diffusion < base - 0.05,
        "soak:diffusion: {diffusion} vs {base}"
    );
}

#[test]
fn langmuir_blocks_a_repeat_but_not_a_first_fill() {
    let run = |hidden: &[Hidden]| {
        let mut e = engine(hidden);
        e.illuminate(0, &flat(4, 1.0e5), 481.0, 613.0, 80.0);
        let first = mean(&e.trapped());
        e.dark(1, 900.0, 80.0, false);
        let held = mean(&e.trapped());
        e.illuminate(2, &flat(4, 1.0e5), 481.0, 613.0, 80.0);
        (first, mean(&e.trapped()) - held)
    };
    let (f0, add0) = run(&[]);
    let (f1, add1) = run(&[Hidden::CapacityLangmuir]);
    assert!((f1 / f0 - 1.0).abs() < 1e-9, "a fresh pixel fills the same");
    assert!(add1 < 0.5 * add0, "a repeat adds {add1} e- against {add0}");
}

#[test]
fn arrhenius_makes_a_warm_dark_release_faster() {
    let released = |hidden: &[Hidden], temp: f64| {
        let mut e = engine(hidden);
        e.illuminate(0, &flat(4, 1.0e3), 481.0, 613.0, 80.0);
        let o = e.dark(1, 180.0, temp, false);
        o.true_persistence.mean().unwrap()
    };
    let (a, b) = (released(&[], 82.0), released(&[], 80.0));
    assert_eq!(a, b, "no temperature dependence unless hidden");
    let (w, c) = (
        released(&[Hidden::TemperatureArrhenius], 82.0),
        released(&[Hidden::TemperatureArrhenius], 80.0),
    );
    // rates x1.6 from 80 to 82 K: more of the charge falls within the first 180 s
    assert!(w > 1.02 * c, "82 K {w} vs 80 K {c}");
}

#[test]
fn fit_calibrates_an_all_lit_single_illumination() {
    let t = tempfile::tempdir().unwrap();
    let d = t.path().join("s");
    simulate(&d, &["--seed", "1", "--size", "32", "--darks", "40"]);
    let m = t.path().join("m.json");
    let o = persist(&[
        "fit",
        "--input",
        d.to_str().unwrap(),
        "--out",
        m.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(m.exists());
}
