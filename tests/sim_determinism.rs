//! Same seed, same bytes; different seed, different data (products and truth files).

use persist::sim::lab::{self, LabConfig};
use persist::sim::output::Writer;
use persist::sim::sky::{self, SkyConfig};
use std::collections::BTreeMap;
use std::path::Path;

fn files(dir: &Path) -> BTreeMap<String, Vec<u8>> {
    let mut m = BTreeMap::new();
    for sub in ["", "truth"] {
        for e in std::fs::read_dir(dir.join(sub)).unwrap() {
            let p = e.unwrap().path();
            if p.is_file() {
                let name = format!("{sub}/{}", p.file_name().unwrap().to_string_lossy());
                m.insert(name, std::fs::read(&p).unwrap());
            }
        }
    }
    m
}

fn sky_to(dir: &Path, seed: u64) -> BTreeMap<String, Vec<u8>> {
    let cfg = SkyConfig {
        size: 64,
        detectors: 2,
        exposures: 4,
        seed,
        ..SkyConfig::default()
    };
    let mut w = Writer::new(dir).unwrap();
    let d = sky::run(&cfg, |e| w.write(&e)).unwrap();
    w.finish(d).unwrap();
    files(dir)
}

#[test]
fn sky_same_seed_same_bytes_different_seed_different_data() {
    let t = tempfile::tempdir().unwrap();
    let a = sky_to(&t.path().join("a"), 5);
    let b = sky_to(&t.path().join("b"), 5);
    let c = sky_to(&t.path().join("c"), 6);
    assert_eq!(a.len(), 2 * 4 * 2 + 1);
    assert!(a == b, "same seed gave different bytes");
    let differ = a
        .iter()
        .filter(|(k, v)| k.ends_with(".h5") && c.get(*k) != Some(*v))
        .count();
    assert_eq!(differ, 8, "a different seed must change every product");
    // products hold no truth
    let text = String::from_utf8_lossy(&a["/d1_e000000.h5"]);
    assert!(!text.contains("true_persistence"));
}

#[test]
fn lab_same_seed_same_bytes_and_ramp_kept() {
    let t = tempfile::tempdir().unwrap();
    let run = |name: &str, seed: u64| {
        let cfg = LabConfig {
            size: 32,
            darks: 2,
            seed,
            ..LabConfig::default()
        };
        let dir = t.path().join(name);
        let mut w = Writer::new(&dir).unwrap();
        let d = lab::run(&cfg, |e| w.write(&e)).unwrap();
        w.finish(d).unwrap();
        files(&dir)
    };
    let (a, b, c) = (run("a", 1), run("b", 1), run("c", 2));
    assert!(a == b);
    assert!(a["/d1_e000001.h5"] != c["/d1_e000001.h5"]);
    let e = persist::product::read::read_exposure(&t.path().join("a/d1_e000001.h5")).unwrap();
    assert!(e.ramp.is_some() && e.ramp_times_s.is_some());
    assert_eq!(e.meta.t_exposure_s, 180.0);
    let e0 = persist::product::read::read_exposure(&t.path().join("a/d1_e000000.h5")).unwrap();
    assert_eq!(e0.meta.t_illuminated_s, Some(481.0));
    assert!(e0.ramp.is_none());
    let truth: serde_json::Value = serde_json::from_slice(&a["truth/truth.json"]).unwrap();
    assert_eq!(truth["scenario"], "lab");
    assert_eq!(truth["config"]["seed"], 1);
}
