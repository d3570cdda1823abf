//! `persist run --watch --metrics-file --metrics-addr` with the real binary: the metrics
//! are scraped over HTTP and read from the textfile while the stage runs, and checked
//! against what the stage logged (exposures processed per detector, backlog drained,
//! a bad file quarantined by kind, checkpoints written, seconds per exposure counted).

mod common;

use common::*;
use std::io::{Read, Write};
use std::path::Path;
use std::process::Stdio;
use std::time::Duration;

const N: usize = 16;

/// The value of the sample `series` (name and labels, exactly as exposed).
fn sample(text: &str, series: &str) -> Option<f64> {
    text.lines().filter(|l| !l.starts_with('#')).find_map(|l| {
        l.strip_prefix(series)?
            .strip_prefix(' ')?
            .trim()
            .parse()
            .ok()
    })
}

fn scrape(port: u16) -> String {
    let mut s = std::net::TcpStream::connect(("127.0.0.1", port)).unwrap();
    s.write_all(b"GET /metrics HTTP/1.1\r\nHost: localhost\r\n\r\n")
        .unwrap();
    let mut r = String::new();
    s.read_to_string(&mut r).unwrap();
    let (head, body) = r.split_once("\r\n\r\n").unwrap();
    assert!(head.starts_with("HTTP/1.1 200"), "{head}");
    assert!(head.contains("text/plain; version=0.0.4"), "{head}");
    body.to_string()
}

fn processed_by(root: &Path, det: u64) -> usize {
    log_events(&root.join("log.jsonl"), "processed")
        .iter()
        .filter(|v| v["detector"].as_u64() == Some(det))
        .count()
}

#[test]
fn watch_metrics_are_scraped_and_match_the_stage() {
    let tmp = tempfile::tempdir().unwrap();
    let input = tmp.path().join("in");
    let root = tmp.path().join("run");
    std::fs::create_dir_all(&root).unwrap();
    write_stream(&input, &[1], 0..5, N);
    write_stream(&input, &[2], 0..3, N);
    let port = {
        let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        l.local_addr().unwrap().port()
    };
    let prom = root.join("persist.prom");
    let log = std::fs::File::create(root.join("log.jsonl")).unwrap();
    let mut args = run_args(&input, &root);
    args.retain(|a| a != "--quiet");
    let mut child = bin()
        .arg("--log-json")
        .args(args)
        .args([
            "--watch",
            "--checkpoint-idle-s",
            "0",
            "--poll-interval-s",
            "0.5",
        ])
        .arg("--metrics-file")
        .arg(&prom)
        .args(["--metrics-addr", &format!("127.0.0.1:{port}")])
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(log)
        .spawn()
        .unwrap();

    // Everything queued is processed; the endpoint and the file say so.
    let drained = |text: &str| {
        sample(text, "persist_exposures_processed_total{detector=\"1\"}") == Some(5.0)
            && sample(text, "persist_exposures_processed_total{detector=\"2\"}") == Some(3.0)
            && sample(text, "persist_backlog_exposures") == Some(0.0)
            && text.contains("persist_checkpoint_age_seconds{detector=\"2\"}")
    };
    assert!(
        wait_until(Duration::from_secs(60), || std::net::TcpStream::connect((
            "127.0.0.1",
            port
        ))
        .is_ok()
            && drained(&scrape(port))),
        "metrics never showed the 8 exposures processed"
    );
    let text = scrape(port);
    assert_eq!(processed_by(&root, 1), 5);
    assert_eq!(processed_by(&root, 2), 3);
    assert_eq!(sample(&text, "persist_exposure_seconds_count"), Some(8.0));
    assert_eq!(
        sample(&text, "persist_exposure_seconds_bucket{le=\"+Inf\"}"),
        Some(8.0)
    );
    let sum = sample(&text, "persist_exposure_seconds_sum").unwrap();
    assert!(sum > 0.0 && sum < 60.0, "{sum}");
    for d in ["1", "2"] {
        let age = sample(
            &text,
            &format!("persist_checkpoint_age_seconds{{detector=\"{d}\"}}"),
        )
        .unwrap();
        assert!((0.0..60.0).contains(&age), "detector {d}: age {age}");
    }
    assert_eq!(sample(&text, "persist_reader_crashes_total"), Some(0.0));
    assert!(!text.contains("persist_quarantined_files_total{"), "{text}");
    assert!(
        wait_until(Duration::from_secs(10), || drained(
            &std::fs::read_to_string(&prom).unwrap_or_default()
        )),
        "the textfile never showed the 8 exposures"
    );

    // A bad file: quarantined, counted by kind; then one more good exposure.
    std::fs::write(input.join("l1_det1_exp0050.h5"), b"not an HDF5 file at all").unwrap();
    assert!(
        wait_until(Duration::from_secs(30), || sample(
            &scrape(port),
            "persist_quarantined_files_total{kind=\"hdf5\"}"
        ) == Some(1.0)),
        "the bad file was never counted as quarantined"
    );
    assert!(input.join(".quarantine/l1_det1_exp0050.h5").exists());
    write_stream(&input, &[1], 5..6, N);
    assert!(
        wait_until(Duration::from_secs(30), || sample(
            &scrape(port),
            "persist_exposures_processed_total{detector=\"1\"}"
        ) == Some(6.0)),
        "exposure 5 never counted"
    );
    let text = scrape(port);
    assert_eq!(processed_by(&root, 1), 6);
    assert_eq!(sample(&text, "persist_backlog_exposures"), Some(0.0));
    assert_eq!(sample(&text, "persist_exposure_seconds_count"), Some(9.0));

    signal(&child, libc::SIGTERM);
    let status = wait_exit(&mut child, Duration::from_secs(30));
    assert!(status.success(), "{status}");
    // The textfile is whole (written under a temporary name, renamed) and final.
    let file = std::fs::read_to_string(&prom).unwrap();
    assert_eq!(
        sample(&file, "persist_exposures_processed_total{detector=\"1\"}"),
        Some(6.0)
    );
    assert_eq!(
        sample(&file, "persist_quarantined_files_total{kind=\"hdf5\"}"),
        Some(1.0)
    );
    assert!(file.ends_with('\n') && file.contains("persist_metrics_timestamp_seconds "));
    assert!(temporaries(&root).is_empty(), "{:?}", temporaries(&root));
}

#[test]
fn metrics_options_need_watch() {
    let tmp = tempfile::tempdir().unwrap();
    let input = tmp.path().join("in");
    write_stream(&input, &[1], 0..1, N);
    let mut args = run_args(&input, tmp.path());
    args.push("--metrics-file".into());
    args.push(tmp.path().join("m.prom").display().to_string());
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let (code, err) = persist_status(&args);
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("--watch"), "{err}");
}
