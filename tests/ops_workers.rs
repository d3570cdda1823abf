//! `persist run` over several detectors as one worker process per detector: the same
//! bytes as one process, the table in detector order, one quarantine of a product whose
//! detector cannot be read, exit status 1 when a worker fails; checkpoint cadence and
//! retention as the operator sees them (`persist status`).

mod common;

use common::*;

#[test]
fn workers_match_one_process_and_keep_order_and_exit_status() {
    let tmp = tempfile::tempdir().unwrap();
    let input = tmp.path().join("in");
    write_stream(&input, &[1, 2, 3], 0..10, 16);
    // Not HDF5: its detector cannot be read; exactly one worker refuses it.
    std::fs::write(input.join("broken.h5"), b"not hdf5").unwrap();
    let (a, b) = (tmp.path().join("workers"), tmp.path().join("one"));
    let out = bin()
        .args(run_args(&input, &a))
        .arg("--no-hourly-checkpoints")
        .output()
        .unwrap();
    let table = String::from_utf8_lossy(&out.stdout).to_string();
    let err = String::from_utf8_lossy(&out.stderr).to_string();
    // The broken product is an error of the run: exit 1, reported once.
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert_eq!(err.matches("persist: quarantined: ").count(), 1, "{err}");
    let q = input.join(".quarantine");
    assert!(q.join("broken.h5").exists());
    std::fs::rename(q.join("broken.h5"), input.join("broken.h5")).unwrap();
    std::fs::remove_dir_all(&q).unwrap();
    let (code, err1) = run_batch(&input, &b, &["--one-process", "--no-hourly-checkpoints"]);
    assert_eq!(code, 1, "{err1}");
    for d in ["out", "ckpt"] {
        let (ta, tb) = (tree(&a.join(d)), tree(&b.join(d)));
        assert_eq!(ta.keys().collect::<Vec<_>>(), tb.keys().collect::<Vec<_>>());
        assert!(ta == tb, "{d} differs");
    }
    // --quiet is in run_args: no table. Without it, rows in detector order.
    assert!(table.is_empty(), "{table}");
    let c = tmp.path().join("table");
    let mut args = run_args(&input, &c);
    args.retain(|x| x != "--quiet");
    let out = bin().args(args).output().unwrap();
    assert!(out.status.success());
    let text = String::from_utf8_lossy(&out.stdout);
    let dets: Vec<&str> = text
        .lines()
        .skip(1)
        .filter_map(|l| l.split_whitespace().next())
        .collect();
    assert_eq!(dets.len(), 30, "{text}");
    assert!(dets.windows(2).all(|w| w[0] <= w[1]), "{text}");
    assert_eq!(text.lines().filter(|l| l.contains("exposure")).count(), 1);

    // Cadence 8 on indices 0..9: grid checkpoints 7, tail 9 (the newest).
    for d in [1u8, 2, 3] {
        let l = persist::checkpoint::list(&c.join("ckpt"), persist::units::DetectorId(d)).unwrap();
        assert_eq!(l.iter().map(|x| x.0).collect::<Vec<_>>(), [7, 9]);
    }
    // 10 more: grid 15, the tail 9 removed once superseded, new tail 19.
    write_stream(&input, &[1, 2, 3], 10..20, 16);
    assert_eq!(run_batch(&input, &c, &[]).0, 0);
    let l = persist::checkpoint::list(&c.join("ckpt"), persist::units::DetectorId(2)).unwrap();
    assert_eq!(l.iter().map(|x| x.0).collect::<Vec<_>>(), [7, 15, 19]);
    let st = persist_ok(&[
        "status",
        "--output",
        &c.join("out").display().to_string(),
        "--checkpoints",
        &c.join("ckpt").display().to_string(),
        "--json",
        "--projection",
    ]);
    let v: serde_json::Value = serde_json::from_str(&st).unwrap();
    let bytes: u64 = l
        .iter()
        .map(|x| std::fs::metadata(&x.1).unwrap().len())
        .sum();
    assert_eq!(v["detectors"][1]["checkpoint_bytes"].as_u64(), Some(bytes));
    assert!(v["projection"]["checkpoints"].as_u64().unwrap() > 100);
}
