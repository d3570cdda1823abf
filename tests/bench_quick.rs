//! `persist bench --quick` on tiny images: the benchmark code runs end to end (every
//! case in its child process, the table, the JSON), so it cannot rot.

mod common;

#[test]
fn quick_bench_runs_every_case_and_writes_the_table_and_json() {
    let tmp = tempfile::tempdir().unwrap();
    let json = tmp.path().join("bench.json");
    let out = common::persist_cmd()
        .args([
            "bench",
            "--quick",
            "--sizes",
            "32",
            "--thread-counts",
            "1,2",
        ])
        .arg("--scratch")
        .arg(tmp.path().join("scratch"))
        .arg("--json")
        .arg(&json)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(stdout.contains("| image | threads |"), "{stdout}");
    assert!(stdout.contains("| 32^2 | 1 |") && stdout.contains("| 32^2 | 2 |"));
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let rows = report["rows"].as_array().unwrap();
    assert_eq!(rows.len(), 2);
    for r in rows {
        for k in [
            "step_s", "memory_s", "stage_s", "io_s", "copy_s", "a_over_b", "c_over_d", "c_over_e",
        ] {
            let v = r[k].as_f64().unwrap();
            assert!(v.is_finite() && v > 0.0, "{k} = {v}");
        }
        assert!(r["stage_peak_bytes"].as_u64().unwrap() > 0);
    }
    // Every case ran: 5 cases + the checkpoint-cadence row, for each thread count.
    assert_eq!(report["results"].as_array().unwrap().len(), 12);
}
