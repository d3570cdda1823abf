//! `persist simulate` through the real binary: products that validate, truth beside
//! them, clear errors for bad arguments.

mod common;

use std::process::Command;

fn persist() -> Command {
    common::persist_cmd()
}

#[test]
fn simulate_lab_and_sky_write_valid_products() {
    let t = tempfile::tempdir().unwrap();
    let lab = t.path().join("lab");
    let o = persist()
        .args([
            "simulate",
            "lab",
            "--size",
            "32",
            "--darks",
            "2",
            "--effect",
            "ipc:alpha=0.02",
            "--out",
        ])
        .arg(&lab)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let sky = t.path().join("sky");
    let o = persist()
        .args([
            "simulate",
            "sky",
            "--size",
            "48",
            "--detectors",
            "2",
            "--exposures",
            "3",
            "--seed",
            "4",
            "--out",
        ])
        .arg(&sky)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let mut files: Vec<_> = std::fs::read_dir(&lab)
        .unwrap()
        .chain(std::fs::read_dir(&sky).unwrap())
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "h5"))
        .collect();
    files.sort();
    assert_eq!(files.len(), 3 + 6);
    let v = persist().arg("validate").args(&files).output().unwrap();
    assert!(v.status.success(), "{}", String::from_utf8_lossy(&v.stderr));
    let truth: serde_json::Value =
        serde_json::from_slice(&std::fs::read(lab.join("truth/truth.json")).unwrap()).unwrap();
    assert_eq!(truth["effects"][0]["name"], "ipc");
    assert_eq!(truth["effects"][0]["params"]["alpha"], 0.02);
    assert!(sky.join("truth/d2_e000002.truth.hdf5").is_file());
}

#[test]
fn bad_arguments_are_named_and_nothing_is_written() {
    let t = tempfile::tempdir().unwrap();
    for (args, needle) in [
        (vec!["lab", "--effect", "nope"], "nope"),
        (
            vec!["lab", "--effect", "soak:capture_scale=-1"],
            "capture_scale",
        ),
        (vec!["lab", "--effect", "ipc:alpha=x"], "alpha"),
        (vec!["lab", "--size", "2"], "--size"),
        (vec!["lab", "--spots", "shifted"], "--campaign"),
        (vec!["lab", "--campaign", "--spots", "moved"], "moved"),
        (vec!["lab", "--dark-lengths", "varied"], "--campaign"),
        (vec!["lab", "--campaign", "--dark-lengths", "long"], "long"),
        (vec!["lab", "--repeats", "2"], "--campaign"),
        (vec!["lab", "--durations", "apart"], "--campaign"),
        (vec!["lab", "--campaign", "--durations", "long"], "long"),
        (vec!["lab", "--campaign", "--repeats", "21"], "21"),
        (vec!["sky", "--detectors", "7"], "--detectors"),
        (vec!["sky", "--exposures", "0"], "--exposures"),
    ] {
        let out = t.path().join("x");
        let o = persist()
            .arg("simulate")
            .args(&args)
            .arg("--out")
            .arg(&out)
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{args:?}: {err}");
        assert!(err.contains(needle), "{args:?}: {err}");
        assert!(!out.exists(), "{args:?} wrote {out:?}");
    }
}
