//! `persist fuzz` in CI: 1,000 mutants of an HDF5 input, a FITS input, a checkpoint and a
//! model file, read through the reader guard and run through the real stage among the
//! 24 good fixtures. No stage death, no hang, no good exposure lost, no parser panic.

mod common;

#[test]
fn a_thousand_mutants_kill_nothing_and_lose_no_good_exposure() {
    let tmp = tempfile::tempdir().unwrap();
    let json = tmp.path().join("fuzz.json");
    let out = common::bin()
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .args(["fuzz", "--mutants", "1000", "--seed", "2", "--batch", "100"])
        .args(["--stage-checkpoints", "8", "--read-timeout-s", "20"])
        .arg("--work")
        .arg(tmp.path().join("work"))
        .arg("--json")
        .arg(&json)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    // The counts, for the CI log.
    println!("{stdout}");
    assert!(
        out.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let r = common::read_json(&json);
    assert_eq!(r["stage_deaths"], 0);
    assert_eq!(r["hangs"], 0);
    assert_eq!(r["good_lost"], 0);
    let readers = r["readers"].as_array().unwrap();
    assert_eq!(readers.len(), 4);
    let total: u64 = readers.iter().map(|c| c["mutants"].as_u64().unwrap()).sum();
    assert_eq!(total, 1000);
    for c in readers {
        assert_eq!(c["mutants"], 250, "{c}");
        assert_eq!(c["panics"], 0, "{c}");
        // Most mutants are refused: the fuzzer does reach the checks.
        assert!(c["refused"].as_u64().unwrap() > 100, "{c}");
    }
    // Every input mutant went through a stage run (5 of 100), good exposures counted.
    assert_eq!(r["stage_runs"], 5 + 8);
    assert_eq!(r["good_expected"], 24 * 13);
}
