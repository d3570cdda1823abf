//! One exposure path: `persist run` (the stage) and `persist slurm`'s tile jobs and
//! assembly (run one after the other by the scripts' own `run_local.sh`) give the same
//! output and final checkpoint bytes, on the committed fixtures (the default model,
//! pixel-local: each tile stepped on its own) and on a 2-detector simulated sky in HDF5
//! and in SPHEREx-layout FITS (a model with neighbour effects: the whole array stepped
//! with the tile active). The Python `persist.run` is compared with both in
//! python/tests/test_one_path.py.

mod common;
mod split_common;

use split_common::*;
use std::path::Path;

/// `persist slurm` (tiles `ROWSxCOLS`) into `ROOT/NAME`, then its jobs on this machine.
fn split(input: &Path, model: Option<&Path>, root: &Path, name: &str, tiles: &str) {
    let dir = root.join(name);
    let o = common::bin()
        .args(slurm_args_for(input, model, &dir, tiles))
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let o = std::process::Command::new("bash")
        .arg(dir.join("work/run_local.sh"))
        .env("SOURCE_DATE_EPOCH", common::SOURCE_DATE_EPOCH)
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
}

#[test]
fn the_stage_and_the_tiles_give_the_same_bytes_on_the_fixtures() {
    let root = tempfile::tempdir().unwrap();
    let input = root.path().join("in");
    std::fs::create_dir_all(&input).unwrap();
    let fixtures = Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures");
    let mut n = 0;
    for e in std::fs::read_dir(&fixtures).unwrap() {
        let p = e.unwrap().path();
        if p.extension().is_some_and(|x| x == "h5") {
            std::fs::copy(&p, input.join(p.file_name().unwrap())).unwrap();
            n += 1;
        }
    }
    assert_eq!(n, 24, "fixtures/: 2 detectors x 12 exposures");
    let stage = root.path().join("stage");
    let (code, err) = common::run_batch(&input, &stage, &[]);
    assert_eq!(code, 0, "{err}");
    split(&input, None, root.path(), "tiles", "2x3");
    assert_same_n(&stage, &root.path().join("tiles"), 24);
}

#[test]
fn the_stage_and_the_tiles_give_the_same_bytes_on_a_simulated_sky() {
    for s in [sky(), sky_fits()] {
        let stage = reference(&s, "stage");
        split(&s.input, Some(&s.model), s.root.path(), "tiles", "2x2");
        let tiles = s.root.path().join("tiles");
        assert_same(&stage, &tiles);
    }
}

#[test]
fn a_fits_sky_is_ordered_by_start_time_in_the_tiles_as_in_the_stage() {
    // The FITS sky's outputs are FITS, and their checkpoints record a history ordered by
    // start time (what makes the tile jobs follow the stage's start-time rules).
    let s = sky_fits();
    let stage = reference(&s, "stage");
    let names: Vec<String> = outputs(&stage)
        .keys()
        .map(|p| p.to_string_lossy().into_owned())
        .collect();
    assert!(
        names.iter().all(|n| n.ends_with(".fits")),
        "outputs: {names:?}"
    );
    split(&s.input, Some(&s.model), s.root.path(), "tiles", "1x2");
    let (_, ckpt) = common::newest_checkpoint(&s.root.path().join("tiles"), 1).unwrap();
    let meta = persist::checkpoint::load(&ckpt).unwrap().0;
    assert!(
        meta.stage_json.contains("\"by_start_time\":true"),
        "{}",
        meta.stage_json
    );
    assert_same(&stage, &s.root.path().join("tiles"));
}
