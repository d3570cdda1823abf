//! The reader guard (`persist::guard`): a file on which the HDF5 library crashes, hangs
//! or fails costs that file, never the stage; a checkpoint that cannot be read falls
//! back to the one before it.

mod common;

use common::{bin, run_batch, tree};
use std::path::{Path, PathBuf};

fn fixtures() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures")
}

/// Detector 1's twelve fixture exposures (and detector 2's with `both`) in `dir/in`,
/// exposure 5 of detector 1 replaced by `bad`.
fn input_with(dir: &Path, bad: &Path, both: bool) -> PathBuf {
    let input = dir.join("in");
    std::fs::create_dir_all(&input).unwrap();
    for e in std::fs::read_dir(fixtures()).unwrap() {
        let p = e.unwrap().path();
        let name = p.file_name().unwrap().to_string_lossy().into_owned();
        if name.ends_with(".h5") && (both || name.starts_with("l1_det1_")) {
            std::fs::copy(&p, input.join(&name)).unwrap();
        }
    }
    std::fs::copy(bad, input.join("l1_det1_exp0005.h5")).unwrap();
    input
}

fn reason(input: &Path) -> serde_json::Value {
    common::read_json(input.join(".quarantine/l1_det1_exp0005.h5.reason.json"))
}

fn published(root: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(root.join("out"))
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.ends_with(".h5"))
        .collect();
    v.sort();
    v
}

/// The four inputs that crash HDF5 1.10.8 in-process (fixtures/fuzz, README there).
#[test]
fn each_crashing_input_is_quarantined_the_other_eleven_published_and_the_restart_clean() {
    for c in 1..=4 {
        let tmp = tempfile::tempdir().unwrap();
        let bad = fixtures().join(format!("fuzz/c{c}.h5"));
        // c1 also with detector 2's products: the run is split into worker processes,
        // whose parent lists the detectors through the guard too.
        let input = input_with(tmp.path(), &bad, c == 1);
        let root = tmp.path();
        let (code, err) = run_batch(&input, root, &[]);
        assert_eq!(
            code, 1,
            "c{c}: one refused input is an error of the run: {err}"
        );
        assert!(
            !input.join("l1_det1_exp0005.h5").exists(),
            "c{c}: not moved aside"
        );
        let r = reason(&input);
        let msg = r["message"].as_str().unwrap();
        assert!(!msg.is_empty(), "c{c}: no reason");
        assert!(
            ["hdf5", "crash", "invalid"].contains(&r["kind"].as_str().unwrap()),
            "c{c}: {r}"
        );
        let out = published(root);
        let want: Vec<String> = (0..12)
            .filter(|&k| k != 5)
            .map(|k| format!("l1_det1_exp{k:04}.h5"))
            .chain(
                (0..12)
                    .filter(|_| c == 1)
                    .map(|k| format!("l1_det2_exp{k:04}.h5")),
            )
            .collect();
        let mut want = want;
        want.sort();
        assert_eq!(out, want, "c{c}: {err}");
        // The restart: nothing left to do, nothing refused, nothing rewritten.
        let before = tree(&root.join("out"));
        let (code, err) = run_batch(&input, root, &[]);
        assert_eq!(code, 0, "c{c}: restart not clean: {err}");
        assert_eq!(
            tree(&root.join("out")),
            before,
            "c{c}: restart rewrote outputs"
        );
    }
}

/// A reader stand-in that crashes (SIGSEGV) on exposure 5, hangs on exposure 7 and
/// answers with the real reader otherwise.
fn faulty_reader(dir: &Path) -> PathBuf {
    reader_crashing_on(dir, "*exp0005*")
}

/// A reader stand-in that crashes (SIGSEGV) on the paths matching the shell pattern
/// `crash`, hangs on exposure 7 and answers with the real reader otherwise.
fn reader_crashing_on(dir: &Path, crash: &str) -> PathBuf {
    let script = dir.join("reader.sh");
    std::fs::write(
        &script,
        format!(
            "#!/bin/sh\ncase \"$3\" in\n{crash}) kill -SEGV $$ ;;\n*exp0007*) exec sleep 60 ;;\nesac\nexec '{}' \"$@\"\n",
            env!("CARGO_BIN_EXE_persist")
        ),
    )
    .unwrap();
    use std::os::unix::fs::PermissionsExt;
    std::fs::set_permissions(&script, std::fs::Permissions::from_mode(0o755)).unwrap();
    script
}

#[test]
fn a_crashing_and_a_hanging_reader_are_quarantined_with_their_reason() {
    let tmp = tempfile::tempdir().unwrap();
    let input = input_with(tmp.path(), &fixtures().join("l1_det1_exp0005.h5"), false);
    let cfg = persist::stage::RunConfig {
        input: input.clone(),
        output: tmp.path().join("out"),
        checkpoints: tmp.path().join("ckpt"),
        model: persist::model::Model::new(persist::model::ModelParams::default()).unwrap(),
        from_checkpoint: None,
        allow_model_change: false,
        checkpoint_every: 4,
        checkpoint_idle: std::time::Duration::ZERO,
        retention: Default::default(),
        processed_utc: "2026-03-02T00:00:00.000000Z".into(),
    };
    let guard = persist::guard::Guard {
        timeout: std::time::Duration::from_secs(2),
        ..persist::guard::Guard::new(faulty_reader(tmp.path()))
    };
    let ops = persist::stage::Ops {
        quarantine: Some(input.join(".quarantine")),
        guard: Some(guard),
        ..Default::default()
    };
    let t0 = std::time::Instant::now();
    let report = persist::stage::run_with(&cfg, &ops, &|_| {});
    assert!(t0.elapsed().as_secs() < 30, "{:?}", t0.elapsed());
    let mut done: Vec<u64> = report.exposures.iter().map(|r| r.exposure_index).collect();
    done.sort();
    assert_eq!(done, vec![0, 1, 2, 3, 4, 6, 8, 9, 10, 11]);
    let q = |k: u64| {
        common::read_json(input.join(format!(".quarantine/l1_det1_exp{k:04}.h5.reason.json")))
    };
    assert_eq!(q(5)["kind"], "crash");
    assert_eq!(q(5)["message"], "reader crashed: SIGSEGV");
    assert_eq!(q(7)["kind"], "crash");
    assert_eq!(q(7)["message"], "reader exceeded 2 s");
}

/// A truncated newest checkpoint: the restart sets it aside, resumes from the one before
/// it, rewrites no output, and `persist status` lists it.
#[test]
fn an_unreadable_checkpoint_falls_back_to_the_one_before_it() {
    let tmp = tempfile::tempdir().unwrap();
    let input = input_with(tmp.path(), &fixtures().join("l1_det1_exp0005.h5"), false);
    let root = tmp.path();
    let (code, err) = run_batch(&input, root, &["--checkpoint-every", "4"]);
    assert_eq!(code, 0, "{err}");
    let newest = common::newest_checkpoint(root, 1).unwrap();
    assert_eq!(newest.0, 11);
    let good = std::fs::read(&newest.1).unwrap();
    // Provenance: the HDF5 library's version in the checkpoint and in every output.
    let version = persist::h5io::library_version();
    assert_eq!(version.split('.').count(), 3, "{version}");
    let attr = |f: &hdf5::Location| {
        f.attr("hdf5_version")
            .unwrap()
            .read_scalar::<hdf5::types::VarLenUnicode>()
            .unwrap()
            .to_string()
    };
    assert_eq!(attr(&hdf5::File::open(&newest.1).unwrap()), version);
    let out0 = hdf5::File::open(root.join("out/l1_det1_exp0000.h5")).unwrap();
    assert_eq!(attr(&out0.group("persistence").unwrap()), version);
    drop(out0);
    let outputs = tree(&root.join("out"));
    std::fs::write(&newest.1, &good[..good.len() / 3]).unwrap();
    let (code, err) = run_batch(&input, root, &["--checkpoint-every", "4"]);
    assert_eq!(code, 1, "the set-aside checkpoint is reported: {err}");
    assert!(err.contains("checkpoint unreadable"), "{err}");
    assert_eq!(tree(&root.join("out")), outputs, "outputs rewritten");
    // The replay from exposure 7 wrote exposure 11's checkpoint again, the same state.
    let again = common::newest_checkpoint(root, 1).unwrap();
    assert_eq!(again.0, 11);
    let (_, st_a) = persist::checkpoint::load(&again.1).unwrap();
    let kept = tmp.path().join("good.h5");
    std::fs::write(&kept, &good).unwrap();
    let (_, st_b) = persist::checkpoint::load(&kept).unwrap();
    assert!(st_a == st_b, "replayed state differs");
    let status = bin()
        .args([
            "status",
            "--output",
            &root.join("out").display().to_string(),
            "--checkpoints",
            &root.join("ckpt").display().to_string(),
            "--json",
        ])
        .output()
        .unwrap();
    let st: serde_json::Value = serde_json::from_slice(&status.stdout).unwrap();
    let q = &st["detectors"][0]["quarantined"];
    assert_eq!(q.as_array().unwrap().len(), 1, "{st}");
    assert!(
        q[0]["file"]
            .as_str()
            .unwrap()
            .contains("ckpt_det1_0000000011.h5"),
        "{st}"
    );
    // And the next restart is clean.
    let (code, err) = run_batch(&input, root, &["--checkpoint-every", "4"]);
    assert_eq!(code, 0, "{err}");
}

/// `persist status` reads a checkpoint as the stage does: a reader that crashes on it
/// makes a listed problem naming the file, and the rest of the status is still given;
/// without the guard the same checkpoint is read in-process.
#[test]
fn status_reads_checkpoints_through_the_guard() {
    let tmp = tempfile::tempdir().unwrap();
    let input = input_with(tmp.path(), &fixtures().join("l1_det1_exp0005.h5"), false);
    let root = tmp.path();
    let (code, err) = run_batch(&input, root, &["--checkpoint-every", "4"]);
    assert_eq!(code, 0, "{err}");
    let (out, ckpt) = (root.join("out"), root.join("ckpt"));
    let status = |guard: Option<&persist::guard::Guard>| {
        persist::stage::status::status(&out, &ckpt, Some(&input), None, guard)
    };
    let here = status(None);
    assert!(here.problems.is_empty(), "{:?}", here.problems);
    let guard = persist::guard::Guard::new(reader_crashing_on(root, "*ckpt_det1_*"));
    let crashed = status(Some(&guard));
    assert_eq!(crashed.problems.len(), 1, "{:?}", crashed.problems);
    let p = &crashed.problems[0];
    assert!(
        p.contains("reader crashed: SIGSEGV") && p.contains("ckpt_det1_0000000011.h5"),
        "{p}"
    );
    let d = &crashed.detectors[0];
    assert_eq!((d.detector, d.last_processed), (1, Some(11)));
    let real = persist::guard::Guard::new(env!("CARGO_BIN_EXE_persist").into());
    // the checkpoint's age is the clock's; the rest is the files'
    let ageless = |st: persist::stage::status::Status| {
        let mut d = st.detectors;
        d.iter_mut().for_each(|d| d.checkpoint_age_s = None);
        serde_json::to_value(&d).unwrap()
    };
    let guarded = status(Some(&real));
    assert!(guarded.problems.is_empty(), "{:?}", guarded.problems);
    assert_eq!(ageless(guarded), ageless(here));
}
