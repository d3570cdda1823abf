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
            "step_s",
            "memory_s",
            "stage_s",
            "io_s",
            "copy_s",
            "a_over_b",
            "c_over_d",
            "c_over_e",
            "guarded_s",
            "g_over_c",
            "g_over_c_whole",
        ] {
            let v = r[k].as_f64().unwrap();
            assert!(v.is_finite() && v > 0.0, "{k} = {v}");
        }
        assert!(r["stage_peak_bytes"].as_u64().unwrap() > 0);
    }
    // Every case ran: 6 cases + the checkpoint-cadence row, for each thread count.
    assert_eq!(report["results"].as_array().unwrap().len(), 14);
    // (f) verify: the full frame's first exposures, the day and its first exposures,
    // for each thread count, and one projected day per thread count.
    let v = report["verify_rows"].as_array().unwrap();
    assert_eq!(v.len(), 6, "{v:?}");
    for r in v {
        assert!(r["total_s"].as_f64().unwrap() > 0.0, "{r}");
        assert!(r["peak_bytes"].as_u64().unwrap() > 0, "{r}");
    }
    assert_eq!(
        (v[0]["size"].as_u64(), v[0]["exposures"].as_u64()),
        (Some(64), Some(4))
    );
    assert_eq!(
        (v[2]["size"].as_u64(), v[2]["exposures"].as_u64()),
        (Some(32), Some(30))
    );
    let p = report["verify_projections"].as_array().unwrap();
    assert_eq!(p.len(), 2);
    for p in p {
        let (day, ratio, projected) = (
            p["day_s"].as_f64().unwrap(),
            p["pixel_ratio"]
                .as_f64()
                .unwrap()
                .max(p["measured_ratio"].as_f64().unwrap()),
            p["projected_day_s"].as_f64().unwrap(),
        );
        assert_eq!(p["pixel_ratio"].as_f64(), Some(4.0));
        assert!((projected - day * ratio).abs() <= 1e-9 * projected, "{p}");
    }
    assert!(
        stdout.contains("| (f) verify |")
            && stdout.contains("exposures (a detector-day at 571) of 64^2")
    );
}
