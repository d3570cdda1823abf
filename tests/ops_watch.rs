//! `persist run --watch` with the real binary: arrivals in shuffled order, some written
//! slowly through `.part` names; gaps crossed after the timeout; late products and
//! duplicates; the directory lock; `persist status`.

mod common;

use common::*;
use persist::flags::pbits;
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{Child, Stdio};
use std::time::Duration;

const N: usize = 16;

/// Start a watching stage logging JSON lines to `root/log.jsonl`; waits until it watches.
fn start_watch(input: &Path, root: &Path, extra: &[&str]) -> Child {
    std::fs::create_dir_all(root).unwrap();
    let log = std::fs::File::create(root.join("log.jsonl")).unwrap();
    let mut args = run_args(input, root);
    args.retain(|a| a != "--quiet");
    let child = bin()
        .arg("--log-json")
        .args(args)
        .arg("--watch")
        // Checkpoint as soon as the queue is drained: these tests read the newest
        // checkpoint after each burst of arrivals.
        .args(["--checkpoint-idle-s", "0"])
        .args(extra)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(log)
        .spawn()
        .unwrap();
    assert!(
        wait_until(Duration::from_secs(30), || !log_events(
            &root.join("log.jsonl"),
            "watching"
        )
        .is_empty()),
        "the stage did not start watching"
    );
    child
}

fn stop(mut child: Child) {
    signal(&child, libc::SIGTERM);
    let status = wait_exit(&mut child, Duration::from_secs(30));
    assert!(status.success(), "{status}");
}

/// Write `bytes` to `dir/tmp_name` in chunks with pauses, sync, then rename to `dir/name`.
fn write_slowly(bytes: &[u8], dir: &Path, tmp_name: &str, name: &str) {
    let tmp = dir.join(tmp_name);
    let mut f = std::fs::File::create(&tmp).unwrap();
    for chunk in bytes.chunks(bytes.len() / 4 + 1) {
        f.write_all(chunk).unwrap();
        f.flush().unwrap();
        std::thread::sleep(Duration::from_millis(60));
    }
    f.sync_all().unwrap();
    drop(f);
    std::fs::rename(&tmp, dir.join(name)).unwrap();
}

fn processed(root: &Path) -> Vec<(u64, u64)> {
    log_events(&root.join("log.jsonl"), "processed")
        .iter()
        .map(|v| {
            (
                v["detector"].as_u64().unwrap(),
                v["exposure_index"].as_u64().unwrap(),
            )
        })
        .collect()
}

fn shuffled_arrivals(events: bool) {
    let tmp = tempfile::tempdir().unwrap();
    let staging = tmp.path().join("staging");
    let files = write_stream(&staging, &[1, 2], 0..10, N);
    // The reference: a batch run over the complete set.
    let reference = tmp.path().join("reference");
    let (code, err) = run_batch(&staging, &reference, &[]);
    assert_eq!(code, 0, "{err}");

    let input = tmp.path().join("in");
    std::fs::create_dir_all(&input).unwrap();
    let root = tmp.path().join("watch");
    let mut extra = vec!["--gap-timeout-s", "120", "--poll-interval-s", "0.3"];
    if !events {
        extra.push("--no-events");
    }
    let child = start_watch(&input, &root, &extra);
    let mut order: Vec<PathBuf> = files.clone();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(if events { 7 } else { 8 });
    order.shuffle(&mut rng);
    for (i, p) in order.iter().enumerate() {
        let name = p.file_name().unwrap().to_string_lossy().into_owned();
        match i % 3 {
            // Slowly, under `.NAME.part` (hidden and .part), then renamed.
            0 => write_slowly(
                &std::fs::read(p).unwrap(),
                &input,
                &format!(".{name}.part"),
                &name,
            ),
            // Slowly, under `NAME.part`, then renamed.
            1 => write_slowly(
                &std::fs::read(p).unwrap(),
                &input,
                &format!("{name}.part"),
                &name,
            ),
            // Moved in from elsewhere on the same file system.
            _ => std::fs::rename(p, input.join(&name)).unwrap(),
        }
        std::thread::sleep(Duration::from_millis(rng.random_range(0..80)));
    }
    let done = wait_until(Duration::from_secs(60), || {
        [1u8, 2]
            .iter()
            .all(|&d| newest_checkpoint(&root, d).is_some_and(|c| c.0 == 9))
    });
    assert!(done, "not all processed: {:?}", processed(&root));
    stop(child);

    // Every product processed once, each detector in index order.
    let seen = processed(&root);
    for d in [1u64, 2] {
        let ks: Vec<u64> = seen.iter().filter(|x| x.0 == d).map(|x| x.1).collect();
        assert_eq!(ks, (0..10).collect::<Vec<_>>(), "detector {d}");
    }
    // Byte-identical to the batch run: same order, no gap crossed.
    assert_eq!(tree(&root.join("out")), tree(&reference.join("out")));
    assert_eq!(tree(&root.join("ckpt")), tree(&reference.join("ckpt")));
    assert!(!input.join(".quarantine").exists());
    assert!(temporaries(&root.join("out")).is_empty());

    // `persist status` on the result.
    let out = bin()
        .args(["status", "--json", "--input"])
        .arg(&input)
        .arg("--output")
        .arg(root.join("out"))
        .arg("--checkpoints")
        .arg(root.join("ckpt"))
        .output()
        .unwrap();
    assert!(out.status.success());
    let st: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let dets = st["detectors"].as_array().unwrap();
    assert_eq!(dets.len(), 2);
    for d in dets {
        assert_eq!(d["last_processed"], 9);
        assert_eq!(d["backlog"], 0);
        assert!(d["checkpoint_age_s"].as_f64().unwrap() < 120.0);
    }
    assert_eq!(st["outputs"], 20);
}

#[test]
fn shuffled_arrivals_with_events_are_processed_in_order_once() {
    shuffled_arrivals(true);
}

#[test]
fn shuffled_arrivals_polling_only_are_processed_in_order_once() {
    shuffled_arrivals(false);
}

fn reason(q: &Path, name: &str) -> serde_json::Value {
    let p = q.join(format!("{name}.reason.json"));
    assert!(q.join(name).exists(), "{name} not in quarantine");
    serde_json::from_str(&std::fs::read_to_string(&p).unwrap()).unwrap()
}

/// Exposure 2 never arrives: exposure 3 waits, the gap is crossed after the timeout
/// (outputs marked history incomplete), and exposure 2 arriving afterwards is late:
/// quarantined. Duplicates: an identical copy is ignored, a different one quarantined.
#[test]
fn gap_crossed_after_timeout_then_late_and_duplicates_are_kept_aside() {
    let tmp = tempfile::tempdir().unwrap();
    let staging = tmp.path().join("staging");
    write_stream(&staging, &[1], 0..6, N);
    let input = tmp.path().join("in");
    std::fs::create_dir_all(&input).unwrap();
    let root = tmp.path().join("watch");
    let child = start_watch(
        &input,
        &root,
        &["--gap-timeout-s", "1.5", "--poll-interval-s", "0.3"],
    );
    let put = |k: u64| std::fs::rename(staging.join(name(1, k)), input.join(name(1, k))).unwrap();
    let out = |k: u64| root.join("out").join(name(1, k));
    put(0);
    put(1);
    put(3);
    put(4);
    assert!(wait_until(Duration::from_secs(20), || out(1).exists()));
    // Exposure 3 waits for the missing 2 (timeout 1.5 s).
    std::thread::sleep(Duration::from_millis(500));
    assert!(!out(3).exists(), "exposure 3 did not wait for the gap");
    assert!(wait_until(Duration::from_secs(20), || out(4).exists()));
    let pf = |k: u64| {
        let f = hdf5::File::open(out(k))
            .map(persist::h5io::close_on_exec)
            .unwrap();
        let p: Vec<u8> = f.dataset("persistence/flags").unwrap().read_raw().unwrap();
        p
    };
    assert!(pf(1).iter().all(|b| b & pbits::HISTORY_INCOMPLETE == 0));
    assert!(pf(3).iter().all(|b| b & pbits::HISTORY_INCOMPLETE != 0));
    assert!(pf(4).iter().all(|b| b & pbits::HISTORY_INCOMPLETE != 0));

    // Late: exposure 2 arrives after its gap was crossed.
    put(2);
    // An identical copy of exposure 1 under another name: ignored.
    std::fs::copy(input.join(name(1, 1)), tmp.path().join("copy.h5")).unwrap();
    std::fs::rename(
        tmp.path().join("copy.h5"),
        input.join("again_det1_exp0001.h5"),
    )
    .unwrap();
    // A different product claiming exposure 4: refused.
    let mut e = exposure(1, 4, N);
    e.image.fill(2.5);
    persist::product::write::write_exposure(&tmp.path().join("other.h5"), &e).unwrap();
    std::fs::rename(
        tmp.path().join("other.h5"),
        input.join("other_det1_exp0004.h5"),
    )
    .unwrap();
    put(5);
    let q = input.join(".quarantine");
    assert!(wait_until(Duration::from_secs(20), || {
        out(5).exists()
            && q.join("other_det1_exp0004.h5.reason.json").exists()
            && q.join(format!("{}.reason.json", name(1, 2))).exists()
    }));
    stop(child);

    let late = reason(&q, &name(1, 2));
    assert_eq!(late["field"], "exposure_index");
    assert!(late["message"].as_str().unwrap().contains("late"), "{late}");
    let dup = reason(&q, "other_det1_exp0004.h5");
    assert_eq!(dup["field"], "exposure_index");
    assert!(
        dup["message"]
            .as_str()
            .unwrap()
            .contains("different content"),
        "{dup}"
    );
    // The identical copy stayed where it was, produced nothing, and was not quarantined.
    assert!(input.join("again_det1_exp0001.h5").exists());
    assert!(!root.join("out/again_det1_exp0001.h5").exists());
    assert!(!q.join("again_det1_exp0001.h5").exists());
    assert!(!out(2).exists());
    let seen = processed(&root);
    assert_eq!(seen, vec![(1, 0), (1, 1), (1, 3), (1, 4), (1, 5)]);

    // `persist status` names the crossed gap and the quarantined files.
    let st = bin()
        .args(["status", "--json", "--input"])
        .arg(&input)
        .arg("--output")
        .arg(root.join("out"))
        .arg("--checkpoints")
        .arg(root.join("ckpt"))
        .output()
        .unwrap();
    let st: serde_json::Value = serde_json::from_slice(&st.stdout).unwrap();
    let d = &st["detectors"][0];
    assert_eq!(d["last_processed"], 5);
    assert_eq!(d["crossed_gaps"], serde_json::json!([[2, 2]]));
    assert_eq!(d["quarantined"].as_array().unwrap().len(), 2);
}

/// Two stages on the same directories: the second refuses with a clear message and
/// exit code 2; the first is unaffected and stops cleanly.
#[test]
fn a_second_stage_on_the_same_directories_refuses() {
    let tmp = tempfile::tempdir().unwrap();
    let input = tmp.path().join("in");
    write_stream(&input, &[1], 0..3, N);
    let root = tmp.path().join("stage");
    let first = start_watch(&input, &root, &[]);
    assert!(wait_until(Duration::from_secs(20), || {
        newest_checkpoint(&root, 1).is_some_and(|c| c.0 == 2)
    }));
    let other_input = tmp.path().join("other");
    write_stream(&other_input, &[2], 0..2, N);
    let (code, err) = run_batch(&other_input, &root, &[]);
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("another persist stage is using this directory") && err.contains("pid"),
        "{err}"
    );
    // Also when only the checkpoint directory is shared.
    let o = bin()
        .args(["run", "--quiet", "--input"])
        .arg(&other_input)
        .arg("--output")
        .arg(tmp.path().join("o2"))
        .arg("--checkpoints")
        .arg(root.join("ckpt"))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("ckpt"), "{err}");
    assert!(!root.join("out").join(name(2, 0)).exists());
    stop(first);
    // Once the first has stopped, a stage may start.
    let (code, err) = run_batch(&other_input, &root, &[]);
    assert_eq!(code, 0, "{err}");
}

/// A product written in place under its final name and held open by its writer (HDF5
/// refuses to open it: "unable to lock file") is not ready: retried, never quarantined,
/// and processed once the writer closes it.
#[test]
fn a_file_still_open_for_writing_is_retried_not_quarantined() {
    use hdf5::types::VarLenUnicode;
    let tmp = tempfile::tempdir().unwrap();
    let input = tmp.path().join("in");
    std::fs::create_dir_all(&input).unwrap();
    let root = tmp.path().join("watch");
    let child = start_watch(
        &input,
        &root,
        &["--poll-interval-s", "0.2", "--log-level", "debug"],
    );
    let e = exposure(1, 0, N);
    let path = input.join(name(1, 0));
    let file = hdf5::File::create(&path)
        .map(persist::h5io::close_on_exec)
        .unwrap();
    let s = |k: &str, v: &str| {
        file.new_attr::<VarLenUnicode>()
            .create(k)
            .unwrap()
            .write_scalar(&v.parse::<VarLenUnicode>().unwrap())
            .unwrap()
    };
    s("product", "spherex.l1.exposure");
    s("schema_version", "1.0");
    s("t_start_utc", &e.meta.t_start_utc);
    for (k, v) in [("detector", 1i64), ("exposure_index", 0)] {
        file.new_attr::<i64>()
            .create(k)
            .unwrap()
            .write_scalar(&v)
            .unwrap();
    }
    file.new_attr::<f64>()
        .create("t_exposure_s")
        .unwrap()
        .write_scalar(&e.meta.t_exposure_s)
        .unwrap();
    file.new_dataset_builder()
        .with_data(&e.image)
        .create("image")
        .unwrap();
    file.new_dataset_builder()
        .with_data(&e.flags)
        .create("flags")
        .unwrap();
    file.flush().unwrap();
    // Several rescans see it, stable in size, but cannot open it.
    let log = root.join("log.jsonl");
    assert!(wait_until(Duration::from_secs(20), || !log_events(
        &log,
        "not ready; will retry"
    )
    .is_empty()));
    std::thread::sleep(Duration::from_millis(600));
    assert!(!root.join("out").join(name(1, 0)).exists());
    drop(file);
    assert!(wait_until(Duration::from_secs(20), || root
        .join("out")
        .join(name(1, 0))
        .exists()));
    stop(child);
    assert!(!input.join(".quarantine").exists());
    assert!(log_events(&log, "refused: quarantined").is_empty());
    assert_eq!(processed(&root), vec![(1, 0)]);
    let retried = log_events(&log, "not ready; will retry");
    assert!(
        retried.iter().all(|v| v["error"]
            .as_str()
            .is_some_and(|m| m.contains("unable to lock file"))),
        "{retried:?}"
    );
}
