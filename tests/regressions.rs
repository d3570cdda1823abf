//! Regression tests named after the problem they pin.

mod common;

/// libhdf5 opens files without O_CLOEXEC and flocks them: a child process spawned while
/// a file was open inherited the descriptor and its lock, so re-opening the file after
/// closing it failed with "unable to lock file" for as long as the child lived (seen in
/// CI: a test writing products while another test thread spawned `persist`).
#[test]
fn child_processes_do_not_inherit_hdf5_file_locks() {
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("x.h5");
    let file = persist::h5io::create(&path).unwrap();
    file.new_attr::<i64>()
        .create("a")
        .unwrap()
        .write_scalar(&1i64)
        .unwrap();
    let mut child = std::process::Command::new("sleep")
        .arg("5")
        .spawn()
        .unwrap();
    drop(file);
    let reopened = persist::h5io::open(&path);
    child.kill().unwrap();
    child.wait().unwrap();
    assert!(reopened.is_ok(), "{:?}", reopened.err());
}

/// `persist fit ... | head -1` panicked ("failed printing to stdout: Broken pipe") once
/// `head` had closed the pipe: `println!` panics on a write error. What a command prints
/// is a report of work already done; a reader that went away must not turn it into a
/// panic. Here stdout is a pipe whose read end is closed before the command starts.
/// A full disk, though, is an error: the output is incomplete.
#[test]
fn a_closed_stdout_pipe_is_not_a_panic() {
    use std::os::fd::{FromRawFd, OwnedFd};
    let mut fds = [0i32; 2];
    // SAFETY: `fds` has room for the two descriptors `pipe` writes.
    assert_eq!(unsafe { libc::pipe(fds.as_mut_ptr()) }, 0);
    // SAFETY: both descriptors were just created by `pipe` and are owned here only.
    let (read, write) = unsafe { (OwnedFd::from_raw_fd(fds[0]), OwnedFd::from_raw_fd(fds[1])) };
    drop(read);
    // `persist model default` printing into `stdout`: exit code and standard error
    let model_default_into = |stdout: std::process::Stdio| {
        let out = common::bin()
            .args(["model", "default"])
            .stdout(stdout)
            .output()
            .unwrap();
        (
            out.status.code(),
            String::from_utf8_lossy(&out.stderr).to_string(),
        )
    };
    let (code, err) = model_default_into(write.into());
    assert!(!err.contains("panicked"), "{err}");
    assert_eq!(code, Some(0), "{err}");

    // any other write error is one: a full disk (/dev/full) gives exit 1 and says so
    let full = std::fs::OpenOptions::new()
        .write(true)
        .open("/dev/full")
        .unwrap();
    let (code, err) = model_default_into(full.into());
    assert!(!err.contains("panicked"), "{err}");
    assert_eq!(code, Some(1), "{err}");
    assert!(err.contains("standard output"), "{err}");
}

/// Seed 7 of the 64 x 64 baseline campaign: the 3,781 e- bin (22 pixels near 0.03
/// e-/s, a first-dark ramp that is a line within its noise) fitted the log law with
/// tau = 9,774 s, i.e. an undetermined A_0, and became a knot of 442 e- between
/// neighbours of 3 and 7 e-; the model over-predicted the lowest fluences 50-fold
/// (residual RMS 83.7 with refill + capacity + chord). Such a bin gives no knot now: no
/// knot below 1e4 e- is above 50 e-, and the paper's calibration alone scores below 60
/// (measured 54.3; 106.5 with the bad knot), on the pooled cells with the levels
/// statistic ([`common::POOLED_LEVELS_CELLS`]).
#[test]
fn a_straight_first_dark_ramp_does_not_become_a_knot() {
    let tmp = tempfile::tempdir().unwrap();
    let path = |n: &str| tmp.path().join(n).to_str().unwrap().to_string();
    let lab = path("lab");
    common::lab_campaign(&lab, 64, 7, &[]);
    let m = path("m.json");
    // the calibration's knots against the measurements: without the flags' coverage
    // margin, which raises the residual by design
    let mut a = vec!["fit", "--input", &lab, "--out", &m, "--no-coverage"];
    a.extend(common::POOLED_LEVELS_CELLS);
    common::persist_ok(&a);
    let model: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&m).unwrap()).unwrap();
    for k in model["amplitude_knots"].as_array().unwrap() {
        let (f, a) = (
            k["fluence_e"].as_f64().unwrap(),
            k["amplitude_e"].as_f64().unwrap(),
        );
        assert!(f >= 1e4 || a < 50.0, "knot {a} e- at {f} e-");
    }
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(path("m.fit.json")).unwrap()).unwrap();
    let rms = report["residual_rms_normalised"].as_f64().unwrap();
    assert!(rms < 60.0, "{rms}");
}

/// A laboratory sequence in which every pixel was lit above 3,000 e- leaves `compare` no
/// background pixel to measure the dark level on (`measure::data`, "Every pixel lit"):
/// the run says so, with how many exposures, and what it measured instead. At 8 x 8 the
/// edge leak lights every column.
#[test]
fn a_sequence_without_background_pixels_is_reported() {
    let t = tempfile::tempdir().unwrap();
    let p = |n: &str| t.path().join(n).to_string_lossy().to_string();
    let (lab, model, report) = (p("lab"), p("m.json"), p("cmp"));
    common::persist_ok(&[
        "simulate", "lab", "--size", "8", "--darks", "4", "--out", &lab,
    ]);
    std::fs::write(&model, common::persist_ok(&["model", "default"])).unwrap();
    let o = common::persist_cmd()
        .args([
            "compare", "--input", &lab, "--model", &model, "--report", &report,
        ])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(
        err.contains("no background pixel") && err.contains("exposures=5"),
        "{err}"
    );
    // a sequence with dark corners says nothing of the kind
    let lab16 = p("lab16");
    common::persist_ok(&[
        "simulate", "lab", "--size", "16", "--darks", "4", "--out", &lab16,
    ]);
    let o = common::persist_cmd()
        .args([
            "compare",
            "--input",
            &lab16,
            "--model",
            &model,
            "--report",
            &p("cmp16"),
        ])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(!err.contains("no background pixel"), "{err}");
}

/// `persist compare` on sky data (every exposure an illumination, so none after one)
/// wrote a report of nothing, "0 exposures" and a residual RMS of NaN (null in
/// `summary.json`), and exited 0. It is now refused, naming the input, the field and
/// why; no report is written.
#[test]
fn compare_on_sky_data_is_refused_not_an_empty_report() {
    let t = tempfile::tempdir().unwrap();
    let p = |n: &str| t.path().join(n).to_string_lossy().to_string();
    let (sky, model, report) = (p("sky"), p("m.json"), p("cmp"));
    common::persist_ok(&[
        "simulate",
        "sky",
        "--size",
        "16",
        "--exposures",
        "6",
        "--out",
        &sky,
    ]);
    std::fs::write(&model, common::persist_ok(&["model", "default"])).unwrap();
    let (code, text) = common::persist_status(&[
        "compare", "--input", &sky, "--model", &model, "--report", &report,
    ]);
    assert_eq!(code, Some(2), "{text}");
    assert!(
        text.contains(&sky)
            && text.contains("`t_illuminated_s`")
            && text.contains("no exposure follows an illumination"),
        "{text}"
    );
    assert!(!std::path::Path::new(&report).exists());
}

/// `persist diagnose --bootstrap 0` ran one replica and called its largest score the
/// 95 % threshold ("over 1 bootstrap replicas"); `--pixels 0` failed as "0 residual
/// cells". Both are refused now, naming the option and why.
#[test]
fn too_few_bootstrap_replicas_or_no_pixels_are_refused() {
    let t = tempfile::tempdir().unwrap();
    let p = |n: &str| t.path().join(n).to_string_lossy().to_string();
    let (lab, model) = (p("lab"), p("m.json"));
    common::lab_campaign(&lab, 16, 1, &[]);
    std::fs::write(&model, common::persist_ok(&["model", "default"])).unwrap();
    for (opt, val, expect) in [
        ("--bootstrap", "0", "at least 19 replicas"),
        ("--bootstrap", "18", "at least 19 replicas"),
        ("--pixels", "0", "at least one pixel"),
    ] {
        let (code, text) =
            common::persist_status(&["diagnose", "--input", &lab, "--model", &model, opt, val]);
        assert_eq!(code, Some(2), "{opt} {val}: {text}");
        assert!(
            text.contains(&format!("`{opt}`")) && text.contains(expect),
            "{opt} {val}: {text}"
        );
    }
}
