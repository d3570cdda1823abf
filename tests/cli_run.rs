//! The real binary in temporary directories: `run`, `model`, model-change refusal.

mod common;

use std::path::Path;
use std::process::Output;

fn persist(args: &[&str], cwd: &Path) -> Output {
    common::persist_cmd()
        .args(args)
        .current_dir(cwd)
        .env("SOURCE_DATE_EPOCH", "1772323200")
        .output()
        .unwrap()
}

fn text(b: &[u8]) -> String {
    String::from_utf8_lossy(b).into_owned()
}

fn fixtures_copy(dir: &Path) {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures");
    std::fs::create_dir_all(dir).unwrap();
    for e in std::fs::read_dir(src).unwrap() {
        let p = e.unwrap().path();
        if p.extension().is_some_and(|x| x == "h5") {
            std::fs::copy(&p, dir.join(p.file_name().unwrap())).unwrap();
        }
    }
}

#[test]
fn model_default_is_a_valid_model_file_with_a_stable_identity() {
    let tmp = tempfile::tempdir().unwrap();
    let out = persist(&["model", "default"], tmp.path());
    assert!(out.status.success());
    std::fs::write(tmp.path().join("m.json"), &out.stdout).unwrap();
    let id = persist(&["model", "id", "m.json"], tmp.path());
    assert!(id.status.success(), "{}", text(&id.stderr));
    let want = persist::model::ModelParams::default().identity();
    assert!(text(&id.stdout).starts_with(&want), "{}", text(&id.stdout));
    let v = persist(&["validate", "m.json"], tmp.path());
    assert!(v.status.success(), "{}", text(&v.stderr));
}

#[test]
fn run_prints_a_summary_and_refuses_a_model_change_unless_asked() {
    let tmp = tempfile::tempdir().unwrap();
    fixtures_copy(&tmp.path().join("in"));
    let args = [
        "run",
        "--input",
        "in",
        "--output",
        "out",
        "--checkpoints",
        "ckpt",
    ];
    let out = persist(&args, tmp.path());
    assert!(out.status.success(), "{}", text(&out.stderr));
    let stdout = text(&out.stdout);
    assert_eq!(stdout.lines().count(), 1 + 24, "{stdout}");
    assert!(stdout.contains(">0.1e/s") && stdout.contains("released"));
    // Every output validates as an output product.
    for e in std::fs::read_dir(tmp.path().join("out")).unwrap() {
        let p = e.unwrap().path();
        if p.extension().is_some_and(|x| x == "h5") {
            assert_eq!(
                persist::validate::validate_path(&p).unwrap(),
                persist::validate::ProductKind::L2Persistence
            );
        }
    }

    // A new exposure arrives, and the model changed: refused, exit 1, named.
    let mut m = persist::model::ModelParams::default();
    m.thresholds.high_e_per_s = 0.2;
    std::fs::write(tmp.path().join("new.json"), m.to_json_pretty()).unwrap();
    let mut with_model = args.to_vec();
    with_model.extend(["--model", "new.json"]);
    let out = persist(&with_model, tmp.path());
    assert_eq!(out.status.code(), Some(1));
    let err = text(&out.stderr);
    assert!(
        err.contains("--allow-model-change") && err.contains("ckpt_det1"),
        "{err}"
    );

    // Reprocess detector 1 from exposure 7 (the default cadence's checkpoint: every 8th)
    // with the new model, explicitly allowed.
    with_model.extend(["--allow-model-change", "--from-checkpoint", "1:7"]);
    let out = persist(&with_model, tmp.path());
    assert!(out.status.success(), "{}", text(&out.stderr));
    assert_eq!(text(&out.stdout).lines().count(), 1 + 4);
    let f = hdf5::File::open(tmp.path().join("out/l1_det1_exp0009.h5"))
        .map(persist::h5io::close_on_exec)
        .unwrap();
    let id = f
        .group("persistence")
        .unwrap()
        .attr("model_id")
        .unwrap()
        .read_scalar::<hdf5::types::VarLenUnicode>()
        .unwrap();
    assert_eq!(id.as_str(), m.identity());
}

#[test]
fn bad_arguments_are_refused_clearly() {
    let tmp = tempfile::tempdir().unwrap();
    let out = persist(
        &[
            "run",
            "--input",
            "in",
            "--output",
            "o",
            "--checkpoints",
            "c",
            "--from-checkpoint",
            "9:1",
        ],
        tmp.path(),
    );
    assert_eq!(out.status.code(), Some(2));
    assert!(
        text(&out.stderr).contains("must be 1..=6"),
        "{}",
        text(&out.stderr)
    );
    let out = persist(
        &[
            "run",
            "--input",
            "missing",
            "--output",
            "o",
            "--checkpoints",
            "c",
        ],
        tmp.path(),
    );
    assert_eq!(out.status.code(), Some(1));
    assert!(
        text(&out.stderr).contains("missing: input is not a directory"),
        "{}",
        text(&out.stderr)
    );
}
