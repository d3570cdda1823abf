//! The stage on the committed-fixture scene: resumption gives identical bytes, bad
//! inputs are refused with the field named while everything else is processed.

#[path = "../examples/make_fixtures.rs"]
#[allow(dead_code)]
mod make_fixtures;

use persist::checkpoint::{self, Retention};
use persist::flags::pbits;
use persist::model::{Model, ModelParams};
use persist::stage::{self, RunConfig, RunReport};
use persist::units::DetectorId;
use std::path::{Path, PathBuf};

fn config(input: &Path, root: &Path, from: Option<(DetectorId, u64)>) -> RunConfig {
    RunConfig {
        input: input.to_path_buf(),
        output: root.join("out"),
        checkpoints: root.join("ckpt"),
        model: Model::new(ModelParams::default()).unwrap(),
        from_checkpoint: from,
        allow_model_change: false,
        checkpoint_every: 1,
        checkpoint_idle: std::time::Duration::ZERO,
        retention: Retention {
            keep_latest: 1000,
            ..Retention::default()
        },
        processed_utc: "2026-03-02T00:00:00.000000Z".into(),
    }
}

fn run(cfg: &RunConfig) -> RunReport {
    stage::run(cfg, &|_| {})
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in walkdir::WalkDir::new(from) {
        let e = e.unwrap();
        let rel = e.path().strip_prefix(from).unwrap();
        if e.file_type().is_dir() {
            std::fs::create_dir_all(to.join(rel)).unwrap();
        } else {
            std::fs::copy(e.path(), to.join(rel)).unwrap();
        }
    }
}

fn output(root: &Path, det: u8, k: u64) -> PathBuf {
    root.join("out").join(format!("l1_det{det}_exp{k:04}.h5"))
}

/// `/persistence/current` (as bits) and `/persistence/flags` of an output.
fn persistence(path: &Path) -> (Vec<u32>, Vec<u8>) {
    let f = hdf5::File::open(path)
        .map(persist::h5io::close_on_exec)
        .unwrap();
    let c: Vec<f32> = f
        .dataset("persistence/current")
        .unwrap()
        .read_raw()
        .unwrap();
    let p: Vec<u8> = f.dataset("persistence/flags").unwrap().read_raw().unwrap();
    (c.into_iter().map(f32::to_bits).collect(), p)
}

fn fixtures() -> (tempfile::TempDir, PathBuf) {
    let tmp = tempfile::tempdir().unwrap();
    let input = tmp.path().join("in");
    make_fixtures::write_all(&input).unwrap();
    (tmp, input)
}

/// 24 exposures straight through, then again from every checkpoint in turn: the
/// reprocessed outputs are byte-identical (whole files, and so their `/persistence`).
#[test]
fn resuming_from_each_checkpoint_gives_identical_bytes() {
    let (tmp, input) = fixtures();
    let a = tmp.path().join("a");
    let report = run(&config(&input, &a, None));
    assert!(report.errors.is_empty(), "{:?}", report.errors);
    assert_eq!(report.exposures.len(), 24);
    // The scene flags something: the star, the saturated patch and the transient.
    let flagged: u64 = report.exposures.iter().map(|r| r.summary.above_high).sum();
    assert!(flagged > 50, "{flagged}");

    for det in [1u8, 2] {
        let ck = checkpoint::list(&a.join("ckpt"), DetectorId(det)).unwrap();
        assert_eq!(
            ck.iter().map(|c| c.0).collect::<Vec<_>>(),
            (0..12).collect::<Vec<u64>>()
        );
        for i in 0..11u64 {
            let b = tmp.path().join(format!("b{det}_{i}"));
            copy_dir(&a.join("ckpt"), &b.join("ckpt"));
            let report = run(&config(&input, &b, Some((DetectorId(det), i))));
            assert!(report.errors.is_empty(), "{:?}", report.errors);
            assert_eq!(report.exposures.len() as u64, 11 - i, "det {det} from {i}");
            for k in (i + 1)..12 {
                let (pa, pb) = (output(&a, det, k), output(&b, det, k));
                assert_eq!(
                    persistence(&pa),
                    persistence(&pb),
                    "det {det} from {i}: exposure {k}"
                );
                assert_eq!(std::fs::read(&pa).unwrap(), std::fs::read(&pb).unwrap());
            }
            std::fs::remove_dir_all(&b).unwrap();
        }
    }
}

/// A run that stops half way and resumes from its checkpoints writes what one run does.
#[test]
fn a_later_run_resumes_where_the_first_stopped() {
    let (tmp, all) = fixtures();
    let a = tmp.path().join("a");
    assert!(run(&config(&all, &a, None)).errors.is_empty());
    let part = tmp.path().join("part");
    std::fs::create_dir_all(&part).unwrap();
    let b = tmp.path().join("b");
    for k in 0..12u64 {
        for det in [1u8, 2] {
            let name = format!("l1_det{det}_exp{k:04}.h5");
            std::fs::copy(all.join(&name), part.join(&name)).unwrap();
        }
        if k == 4 || k == 11 {
            let report = run(&config(&part, &b, None));
            assert!(report.errors.is_empty(), "{:?}", report.errors);
            // Only the new exposures are stepped: resumed from the checkpoints.
            assert_eq!(report.exposures.len(), if k == 4 { 10 } else { 14 });
        }
    }
    for det in [1u8, 2] {
        for k in 0..12 {
            assert_eq!(
                std::fs::read(output(&a, det, k)).unwrap(),
                std::fs::read(output(&b, det, k)).unwrap()
            );
        }
    }
    // A third run has nothing to do.
    assert!(run(&config(&part, &b, None)).exposures.is_empty());
}

/// Open a product for editing (the tests' way to make malformed inputs).
fn tamper(path: &Path, f: impl FnOnce(&hdf5::File)) {
    let file = persist::h5io::open_rw_unlocked(path).unwrap();
    f(&file);
}

fn errors_about(report: &RunReport, file: &str) -> Vec<String> {
    report
        .errors
        .iter()
        .filter(|e| e.context.path.as_ref().is_some_and(|p| p.ends_with(file)))
        .map(|e| e.to_string())
        .collect()
}

/// Each malformed input of detector 2 is refused with a message naming the field; the
/// rest of detector 2 goes on (marked history incomplete) and detector 1 is untouched.
#[test]
fn malformed_inputs_are_refused_by_field_and_the_rest_is_processed() {
    let (tmp, input) = fixtures();
    let clean = tmp.path().join("clean");
    assert!(run(&config(&input, &clean, None)).errors.is_empty());

    let name = |k: u64| format!("l1_det2_exp{k:04}.h5");
    // exp 2: a missing attribute.
    tamper(&input.join(name(2)), |f| {
        f.delete_attr("t_exposure_s").unwrap()
    });
    // exp 4: a wrong dtype (float64 image).
    tamper(&input.join(name(4)), |f| {
        f.unlink("image").unwrap();
        f.new_dataset::<f64>()
            .shape((64, 64))
            .create("image")
            .unwrap();
    });
    // exp 6: image and flags of different shapes.
    tamper(&input.join(name(6)), |f| {
        f.unlink("flags").unwrap();
        f.new_dataset::<u32>()
            .shape((32, 64))
            .create("flags")
            .unwrap();
    });
    // exp 9: starts before the reset that ended exp 8 (exp 8 started 30 s after exp 7
    // ended and lasted 112 s; this start is 60 s before exp 8's reset).
    let t8 = hdf5::File::open(input.join(name(8)))
        .map(persist::h5io::close_on_exec)
        .unwrap()
        .attr("t_start_utc")
        .unwrap()
        .read_scalar::<hdf5::types::VarLenUnicode>()
        .unwrap();
    let t8 = persist::units::UtcSeconds::parse(t8.as_str()).unwrap();
    let early = persist::units::UtcSeconds(t8.0 + 112.0 - 60.0).to_iso();
    tamper(&input.join(name(9)), |f| {
        f.delete_attr("t_start_utc").unwrap();
        f.new_attr::<hdf5::types::VarLenUnicode>()
            .create("t_start_utc")
            .unwrap()
            .write_scalar(&early.parse::<hdf5::types::VarLenUnicode>().unwrap())
            .unwrap();
    });
    // A second product claiming exposure 10 of detector 2, with different content.
    std::fs::copy(input.join(name(10)), input.join("zz_det2_dup.h5")).unwrap();
    tamper(&input.join("zz_det2_dup.h5"), |f| {
        f.unlink("image").unwrap();
        f.new_dataset_builder()
            .with_data(&ndarray::Array2::<f32>::from_elem((64, 64), 7.0))
            .create("image")
            .unwrap();
    });

    let bad = tmp.path().join("bad");
    let report = run(&config(&input, &bad, None));
    for (file, field) in [
        (name(2), "t_exposure_s"),
        (name(4), "image"),
        (name(6), "flags"),
        (name(9), "t_start_utc"),
        ("zz_det2_dup.h5".to_string(), "exposure_index"),
    ] {
        let errs = errors_about(&report, &file);
        assert_eq!(errs.len(), 1, "{file}: {errs:?} in {:?}", report.errors);
        assert!(
            errs[0].contains(field),
            "{file}: `{}` does not name {field}",
            errs[0]
        );
    }
    assert_eq!(report.errors.len(), 5, "{:?}", report.errors);

    // Detector 1: all 12 outputs, byte-identical to the clean run.
    for k in 0..12 {
        assert_eq!(
            std::fs::read(output(&clean, 1, k)).unwrap(),
            std::fs::read(output(&bad, 1, k)).unwrap()
        );
    }
    // Detector 2: the 8 good exposures are published; those after a rejected one are
    // marked history incomplete.
    let published: Vec<u64> = (0..12).filter(|&k| output(&bad, 2, k).exists()).collect();
    assert_eq!(published, vec![0, 1, 3, 5, 7, 8, 10, 11]);
    for k in [3u64, 5, 7, 8, 10, 11] {
        let (_, p) = persistence(&output(&bad, 2, k));
        assert!(
            p.iter().all(|b| b & pbits::HISTORY_INCOMPLETE != 0),
            "exposure {k}"
        );
    }
    let (_, p1) = persistence(&output(&bad, 2, 1));
    assert!(p1.iter().all(|b| b & pbits::HISTORY_INCOMPLETE == 0));

    // Exposure 2 of detector 2 was rejected and its place crossed: a corrected copy
    // arriving now is late, refused. Exposure 3, processed, is silently known.
    let late = tmp.path().join("late");
    make_fixtures::write_all(&tmp.path().join("fresh")).unwrap();
    std::fs::create_dir_all(&late).unwrap();
    std::fs::copy(
        tmp.path().join("fresh").join(name(2)),
        late.join("late_det2_exp2.h5"),
    )
    .unwrap();
    std::fs::copy(
        tmp.path().join("fresh").join(name(3)),
        late.join("again_det2_exp3.h5"),
    )
    .unwrap();
    let report = run(&config(&late, &bad, None));
    assert_eq!(report.errors.len(), 1, "{:?}", report.errors);
    let e = report.errors[0].to_string();
    assert!(
        e.contains("late_det2_exp2.h5") && e.contains("exposure_index") && e.contains("late"),
        "{e}"
    );
}
