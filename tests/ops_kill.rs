//! Crash safety of the real binary: SIGKILL at random moments, SIGTERM mid-run.
//!
//! A 50-exposure stream (2 detectors x 25, 64 x 64 pixels: enough work per exposure that most kills land while
//! outputs are being published, not while the processes start) processed without
//! interruption is the reference. Twenty runs (more, up to sixty, until ten kills have
//! landed mid-processing) are each killed with SIGKILL at a moment
//! drawn from a seeded RNG (once or twice), then restarted until one completes: every
//! output file and every checkpoint file (the final one included) must be byte-identical
//! to the reference, and no temporary file may remain.

mod common;

use common::*;
use rand::{Rng, SeedableRng};
use std::process::Stdio;
use std::time::{Duration, Instant};

const N: usize = 64;

fn reference(tmp: &std::path::Path, input: &std::path::Path) -> (std::path::PathBuf, Duration) {
    let root = tmp.join("reference");
    let t0 = Instant::now();
    let (code, err) = run_batch(input, &root, &[]);
    let took = t0.elapsed();
    assert_eq!(code, 0, "{err}");
    assert_eq!(tree(&root.join("out")).len(), 50);
    (root, took)
}

#[test]
fn sigkill_at_random_moments_then_restart_gives_identical_bytes() {
    let tmp = tempfile::tempdir().unwrap();
    let input = tmp.path().join("in");
    write_stream(&input, &[1, 2], 0..25, N);
    let (reference, took) = reference(tmp.path(), &input);
    let ref_out = tree(&reference.join("out"));
    let ref_ckpt = tree(&reference.join("ckpt"));
    let ref_final: Vec<Vec<u8>> = [1u8, 2]
        .iter()
        .map(|&d| std::fs::read(newest_checkpoint(&reference, d).unwrap().1).unwrap())
        .collect();
    let span_ms = (took.as_millis() as u64).max(50);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(20260301);
    let mut killed_mid_run = 0;
    // Kills that left some but not all outputs published (mid-processing).
    let mut partial_kills = 0;
    // twenty trials, and more (up to sixty) until ten kills have landed mid-processing:
    // where a kill lands depends on the machine's timing
    let mut trials = 0;
    while trials < 20 || (partial_kills < 10 && trials < 60) {
        let trial = trials;
        trials += 1;
        let root = tmp.path().join(format!("trial{trial:02}"));
        let kills_wanted = rng.random_range(1..=2);
        let mut span = span_ms;
        let mut kills = 0;
        let mut runs = 0;
        loop {
            runs += 1;
            assert!(runs < 40, "trial {trial}: no run completed");
            let mut child = bin()
                .args(run_args(&input, &root))
                .stdin(Stdio::null())
                .stdout(Stdio::null())
                .stderr(Stdio::null())
                .spawn()
                .unwrap();
            if kills < kills_wanted {
                let delay = rng.random_range(0..span.max(10));
                std::thread::sleep(Duration::from_millis(delay));
                let finished = match child.try_wait().unwrap() {
                    Some(status) => {
                        assert!(status.success(), "trial {trial}: {status}");
                        true
                    }
                    None => {
                        child.kill().unwrap(); // SIGKILL
                                               // It may have finished just before the kill.
                        child.wait().unwrap().success()
                    }
                };
                if finished && kills == 0 {
                    // Every trial must be killed at least once: start it again from
                    // nothing, with a shorter span (the machine was faster than the
                    // reference run).
                    std::fs::remove_dir_all(&root).unwrap();
                    span = span * 3 / 4;
                    continue;
                }
                if !finished {
                    kills += 1;
                    let n = tree(&root.join("out")).len();
                    if n > 0 && n < 50 {
                        partial_kills += 1;
                    }
                    continue;
                }
                break;
            }
            let status = wait_exit(&mut child, Duration::from_secs(120));
            assert!(status.success(), "trial {trial}: {status}");
            break;
        }
        if kills > 0 {
            killed_mid_run += 1;
        }
        eprintln!("trial {trial}: {kills} kill(s), {runs} run(s)");
        let out = tree(&root.join("out"));
        let ckpt = tree(&root.join("ckpt"));
        assert_eq!(
            out.keys().collect::<Vec<_>>(),
            ref_out.keys().collect::<Vec<_>>(),
            "trial {trial}: output files"
        );
        for (k, v) in &out {
            assert!(v == &ref_out[k], "trial {trial}: {} differs", k.display());
        }
        assert_eq!(
            ckpt.keys().collect::<Vec<_>>(),
            ref_ckpt.keys().collect::<Vec<_>>(),
            "trial {trial}: checkpoint files"
        );
        for (k, v) in &ckpt {
            assert!(v == &ref_ckpt[k], "trial {trial}: {} differs", k.display());
        }
        for (i, &d) in [1u8, 2].iter().enumerate() {
            let (index, p) = newest_checkpoint(&root, d).unwrap();
            assert_eq!(index, 24);
            assert_eq!(std::fs::read(p).unwrap(), ref_final[i], "trial {trial}");
        }
        for dir in ["out", "ckpt"] {
            let t = temporaries(&root.join(dir));
            assert!(t.is_empty(), "trial {trial}: temporaries left: {t:?}");
        }
        assert!(temporaries(&input).is_empty());
        std::fs::remove_dir_all(&root).unwrap();
    }
    eprintln!(
        "reference run {took:?}; {killed_mid_run} of {trials} trials killed mid-run, \
         {partial_kills} kills with part of the outputs published"
    );
    assert!(
        partial_kills >= 10,
        "only {partial_kills} kills landed mid-processing"
    );
    // Most trials must really have been interrupted (the kill came before the end).
    assert!(
        4 * killed_mid_run >= 3 * trials,
        "only {killed_mid_run} of {trials} trials were killed mid-run"
    );
}

/// SIGTERM (and SIGINT) mid-run: the exposure in hand is finished, its checkpoint
/// written, exit 0; the checkpoint is the last published output; a restart completes
/// the same bytes.
#[test]
fn sigterm_finishes_the_exposure_in_hand_checkpoints_and_exits_0() {
    let tmp = tempfile::tempdir().unwrap();
    let input = tmp.path().join("in");
    write_stream(&input, &[1, 2], 0..25, N);
    let (reference, took) = reference(tmp.path(), &input);
    for (i, sig) in [libc::SIGTERM, libc::SIGINT].into_iter().enumerate() {
        let root = tmp.path().join(format!("sig{i}"));
        let mut child = bin()
            .args(run_args(&input, &root))
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        // Stop once something is published, well before the end.
        assert!(wait_until(Duration::from_secs(60), || {
            tree(&root.join("out")).len() >= 4
        }));
        signal(&child, sig);
        let status = wait_exit(&mut child, Duration::from_secs(60));
        let mut err = String::new();
        std::io::Read::read_to_string(child.stderr.as_mut().unwrap(), &mut err).unwrap();
        assert!(status.success(), "{status}: {err}");
        let out = tree(&root.join("out"));
        assert!(out.len() < 50, "stopped too late to tell ({took:?})");
        for d in [1u8, 2] {
            let published: Vec<u64> = (0..25)
                .filter(|&k| root.join("out").join(name(d, k)).exists())
                .collect();
            let ck = newest_checkpoint(&root, d).map(|c| c.0);
            assert_eq!(ck, published.last().copied(), "detector {d}: {err}");
        }
        assert!(temporaries(&root.join("out")).is_empty());
        assert!(temporaries(&root.join("ckpt")).is_empty());
        let (code, err) = run_batch(&input, &root, &[]);
        assert_eq!(code, 0, "{err}");
        assert_eq!(tree(&root.join("out")), tree(&reference.join("out")));
        assert_eq!(tree(&root.join("ckpt")), tree(&reference.join("ckpt")));
    }
}
