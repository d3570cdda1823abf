//! Shared by the split tests: a small simulated sky, a model with neighbour effects,
//! a reference `persist run`, and byte-for-byte comparisons.
#![allow(dead_code)]

use crate::common;
use persist::model::params::EffectSpec;
use persist::model::ModelParams;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// 64 x 64 pixels, 2 detectors, 6 exposures, stars dense enough to saturate pixels
/// (so blooming acts), and the default model with `blooming` and `ipc`.
pub struct Sky {
    pub root: tempfile::TempDir,
    pub input: PathBuf,
    pub model: PathBuf,
}

pub fn sky() -> Sky {
    sky_as("h5")
}

/// [`sky`] written as SPHEREx-layout FITS (`persist simulate sky --format fits`: no
/// sequence number, each detector's history ordered by start time).
pub fn sky_fits() -> Sky {
    sky_as("fits")
}

fn sky_as(format: &str) -> Sky {
    let root = tempfile::tempdir().unwrap();
    let input = root.path().join("sky");
    common::persist_ok(&[
        "simulate",
        "sky",
        "--size",
        "64",
        "--detectors",
        "2",
        "--exposures",
        "6",
        "--seed",
        "5",
        "--n12",
        "3000",
        "--out",
        input.to_str().unwrap(),
        "--format",
        format,
    ]);
    let mut p = ModelParams::default();
    p.push_effect(EffectSpec::named("blooming"));
    p.push_effect(EffectSpec::named("ipc"));
    let model = root.path().join("model.json");
    std::fs::write(&model, p.to_json_pretty()).unwrap();
    Sky { root, input, model }
}

/// `persist run` over the sky into `ROOT/NAME/{out,ckpt}`; returns `ROOT/NAME`.
pub fn reference(s: &Sky, name: &str) -> PathBuf {
    let dir = s.root.path().join(name);
    let (code, err) = common::run_batch(&s.input, &dir, &["--model", s.model.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    dir
}

/// `persist slurm` arguments for `ROOT/NAME/{out,ckpt,work}`.
pub fn slurm_args(s: &Sky, name: &str, tiles: &str) -> Vec<String> {
    slurm_args_for(&s.input, Some(&s.model), &s.root.path().join(name), tiles)
}

/// `persist slurm` arguments of `input` for `DIR/{out,ckpt,work}` (`model`: none, the
/// default model).
pub fn slurm_args_for(input: &Path, model: Option<&Path>, dir: &Path, tiles: &str) -> Vec<String> {
    let d = |x: &str| dir.join(x).to_string_lossy().into_owned();
    let mut args: Vec<String> = vec![
        "slurm".into(),
        "--input".into(),
        input.to_string_lossy().into_owned(),
        "--output".into(),
        d("out"),
        "--checkpoints".into(),
        d("ckpt"),
        "--work".into(),
        d("work"),
        "--tiles".into(),
        tiles.into(),
    ];
    if let Some(m) = model {
        args.extend(["--model".into(), m.to_string_lossy().into_owned()]);
    }
    args
}

/// Output products by file name.
pub fn outputs(dir: &Path) -> BTreeMap<PathBuf, Vec<u8>> {
    common::tree(&dir.join("out"))
}

/// The newest checkpoint of each detector: (detector, index) -> bytes.
pub fn final_checkpoints(dir: &Path) -> BTreeMap<(u8, u64), Vec<u8>> {
    (1..=6u8)
        .filter_map(|d| {
            common::newest_checkpoint(dir, d).map(|(i, p)| ((d, i), std::fs::read(p).unwrap()))
        })
        .collect()
}

/// The same output files and final checkpoints, byte for byte.
pub fn assert_same(reference: &Path, split: &Path) {
    assert_same_n(reference, split, 12);
}

/// [`assert_same`] for a run of `n_outputs` outputs of 2 detectors.
pub fn assert_same_n(reference: &Path, split: &Path, n_outputs: usize) {
    let (a, b) = (outputs(reference), outputs(split));
    assert_eq!(
        a.keys().collect::<Vec<_>>(),
        b.keys().collect::<Vec<_>>(),
        "output file names"
    );
    assert_eq!(a.len(), n_outputs, "2 detectors' outputs");
    for (name, bytes) in &a {
        assert!(b[name] == *bytes, "{}: bytes differ", name.display());
    }
    let (a, b) = (final_checkpoints(reference), final_checkpoints(split));
    assert_eq!(a.keys().collect::<Vec<_>>(), b.keys().collect::<Vec<_>>());
    assert_eq!(a.len(), 2);
    for (key, bytes) in &a {
        assert!(b[key] == *bytes, "final checkpoint {key:?}: bytes differ");
    }
}
