//! The time split of one detector's history (`persist slurm --time-spans`): spans that
//! start from zero after a warm-up publish currents within the bound their outputs
//! record, and the flags of every pixel whose current is not within that bound of a
//! threshold; spans that start from a retained checkpoint give the sequential bytes.

mod common;

use persist::product::read_output;
use std::path::{Path, PathBuf};

const EXPOSURES: usize = 36;

/// 64 x 64, one detector, dense stars (saturated pixels), the default model.
fn sky(root: &Path) -> PathBuf {
    let input = root.join("sky");
    common::persist_ok(&[
        "simulate",
        "sky",
        "--size",
        "64",
        "--detectors",
        "1",
        "--exposures",
        &EXPOSURES.to_string(),
        "--seed",
        "5",
        "--n12",
        "3000",
        "--out",
        input.to_str().unwrap(),
    ]);
    input
}

/// `persist slurm` over `input` into `dir/{out,ckpt,work}` with `extra`, then the jobs
/// one after the other (`run_local.sh`); returns what `persist slurm` printed.
fn split(input: &Path, dir: &Path, extra: &[&str]) -> String {
    let d = |x: &str| dir.join(x).to_string_lossy().into_owned();
    let o = common::bin()
        .args(["slurm", "--input", input.to_str().unwrap()])
        .args(["--output", &d("out"), "--checkpoints", &d("ckpt")])
        .args(["--work", &d("work")])
        .args(extra)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let printed = String::from_utf8_lossy(&o.stdout).into_owned();
    let tiles = std::fs::read_to_string(dir.join("work/tiles.sbatch")).unwrap();
    assert!(
        tiles.contains("#SBATCH --array=0-2"),
        "one task per span\n{tiles}"
    );
    let o = std::process::Command::new("bash")
        .arg(dir.join("work/run_local.sh"))
        .env("SOURCE_DATE_EPOCH", common::SOURCE_DATE_EPOCH)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    printed
}

fn name(k: usize) -> String {
    format!("d1_e{k:06}.h5")
}

#[test]
fn three_spans_from_zero_stay_within_the_recorded_bound() {
    let root = tempfile::tempdir().unwrap();
    let input = sky(root.path());
    let seq = root.path().join("seq");
    let (code, err) = common::run_batch(&input, &seq, &["--keep-latest", "100"]);
    assert_eq!(code, 0, "{err}");

    // No checkpoints: spans 1 and 2 start from zero, 1,200 s (about 8 exposures)
    // before their first exposure.
    let warm = root.path().join("warm");
    let printed = split(&input, &warm, &["--time-spans", "3", "--warmup-s", "1200"]);
    assert!(
        printed.contains("span 0: exposures 0..=11 as the run starts")
            && printed.contains("span 1: exposures 12..=23 from zero at exposure")
            && printed.contains("span 2: exposures 24..=35 from zero at exposure"),
        "{printed}"
    );
    let (mut checked, mut near, mut apart, mut samples) = (0usize, 0usize, 0usize, 0usize);
    let mut worst = 0.0f64;
    // Pixels released in one run only since their span's first exposure.
    let mut released_apart = std::collections::BTreeSet::new();
    for k in 0..EXPOSURES {
        let a = seq.join("out").join(name(k));
        let b = warm.join("out").join(name(k));
        let (_, pa, aa) = read_output(&a).unwrap();
        let (_, pb, ab) = read_output(&b).unwrap();
        if k < 12 {
            // Span 0 starts as the run does: exact.
            assert!(ab.warmup.is_none(), "{k}");
            assert_eq!(
                std::fs::read(&a).unwrap(),
                std::fs::read(&b).unwrap(),
                "{k}"
            );
            continue;
        }
        if k % 12 == 0 {
            released_apart.clear();
        }
        let w = ab
            .warmup
            .unwrap_or_else(|| panic!("{k}: no warm-up recorded"));
        assert!(aa.warmup.is_none());
        assert!(w.warmup_s > 800.0 && w.warmup_s <= 1200.0, "{w:?}");
        let bound = w.carry_in_bound_e_per_s;
        assert!(bound > 0.0 && bound.is_finite(), "{w:?}");
        let (hi, lo) = (aa.threshold_high_e_per_s, aa.threshold_low_e_per_s);
        // float32 planes: the bound plus the rounding of the two values compared.
        let tol = |x: f64| bound + 1e-6 * x.abs() + 1e-9;
        for (px, ((&ca, &cb), (&fa, &fb))) in pa
            .current_e_per_s
            .iter()
            .zip(pb.current_e_per_s.iter())
            .zip(pa.flags.iter().zip(pb.flags.iter()))
            .enumerate()
        {
            samples += 1;
            // Early release (bit 3) is the model's one decision that is not a threshold
            // of this exposure's current: it follows the pixel's last flags and the
            // image's background (the median of the pixels predicted quiet), so a pixel
            // can be released in one run and not in the other, and its amplitudes (set
            // to zero) differ from then on by more than the carry-in.
            if (fa ^ fb) & 8 != 0 {
                released_apart.insert(px);
            }
            if released_apart.contains(&px) {
                apart += 1;
                continue;
            }
            let (ca, cb) = (f64::from(ca), f64::from(cb));
            worst = worst.max((ca - cb).abs() / bound);
            assert!(
                (ca - cb).abs() <= tol(ca),
                "exposure {k} pixel {px}: sequential {ca} e-/s, span {cb} e-/s, bound {bound}"
            );
            // Bits 0 and 1 (the thresholds) agree wherever the bound cannot cross one.
            if (ca - hi).abs() > tol(ca) && (ca - lo).abs() > tol(ca) {
                assert_eq!(fa & 3, fb & 3, "exposure {k} pixel {px}: current {ca} e-/s");
                checked += 1;
            } else {
                near += 1;
            }
        }
    }
    assert!(checked > 0, "no pixel far enough from a threshold");
    eprintln!(
        "pixel samples {samples}: flags compared {checked}, near a threshold {near}, released in one run only {apart}; largest current difference / bound {worst:.3}"
    );
    assert!(
        apart * 10 < samples,
        "{apart} of {samples} pixel samples released in one run only"
    );
    // Warm-up spans write no checkpoint (their state lacks the carry-in): the newest
    // is the end of span 0.
    let (index, _) = common::newest_checkpoint(&warm, 1).unwrap();
    assert_eq!(index, 11);
}

#[test]
fn spans_that_start_from_a_checkpoint_give_the_sequential_bytes() {
    let root = tempfile::tempdir().unwrap();
    let input = sky(root.path());
    let seq = root.path().join("seq");
    let (code, err) = common::run_batch(&input, &seq, &["--keep-latest", "100"]);
    assert_eq!(code, 0, "{err}");
    // The checkpoints of the earlier processing (7, 15, 23, 31, 35) are retained: a
    // reprocessing from the start splits on them.
    let re = root.path().join("re");
    std::fs::create_dir_all(re.join("ckpt")).unwrap();
    copy_tree(&seq.join("ckpt"), &re.join("ckpt"));
    let printed = split(
        &input,
        &re,
        &["--time-spans", "3", "--warmup-s", "2000", "--from-start"],
    );
    assert!(
        printed.contains("span 1: exposures 12..=23 from checkpoint 7 (exact)")
            && printed.contains("span 2: exposures 24..=35 from checkpoint 23 (exact)"),
        "{printed}"
    );
    let (a, b) = (
        common::tree(&seq.join("out")),
        common::tree(&re.join("out")),
    );
    assert_eq!(a.len(), EXPOSURES);
    assert!(a == b, "outputs differ from the sequential run");
    let (ia, pa) = common::newest_checkpoint(&seq, 1).unwrap();
    let (ib, pb) = common::newest_checkpoint(&re, 1).unwrap();
    assert_eq!((ia, ib), (35, 35));
    assert_eq!(std::fs::read(pa).unwrap(), std::fs::read(pb).unwrap());
}

fn copy_tree(from: &Path, to: &Path) {
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        let t = to.join(e.file_name());
        if e.file_type().unwrap().is_dir() {
            std::fs::create_dir_all(&t).unwrap();
            copy_tree(&e.path(), &t);
        } else if e.file_name() != ".persist.lock" {
            std::fs::copy(e.path(), t).unwrap();
        }
    }
}
