//! Products, checkpoints and model files on disk: round trips, byte identity, and every
//! kind of malformed file refused with an error naming the file and the field.

mod common;

use ndarray::{Array1, Array2, Array3};
use persist::checkpoint::{self, CheckpointMeta};
use persist::flags::{bits, pbits};
use persist::model::{ModelParams, State};
use persist::product::synthetic::tiny_exposure;
use persist::product::{
    read_exposure, read_output, write_exposure, write_output, Exposure, PersistenceAttrs,
    PersistencePlanes,
};
use persist::units::DetectorId;
use persist::validate::{validate_path, ProductKind};
use persist::{Error, ErrorKind};
use std::path::{Path, PathBuf};

const T0: &str = "2026-03-01T00:02:31.500000Z";

fn exposure() -> Exposure {
    tiny_exposure(3, 12, 16, 12, T0, 112.0)
}

fn lab_exposure() -> Exposure {
    let mut e = tiny_exposure(1, 0, 8, 8, T0, 100.0);
    e.meta.t_illuminated_s = Some(40.0);
    e.ramp = Some(Array3::from_shape_fn((4, 8, 8), |(s, y, x)| {
        (s * 100 + y * 8 + x) as f32
    }));
    e.ramp_times_s = Some(Array1::from(vec![1.5, 26.5, 51.5, 76.5]));
    e
}

fn planes_for(e: &Exposure) -> (Exposure, PersistencePlanes, PersistenceAttrs) {
    let mut out = e.clone();
    let current = Array2::from_shape_fn(e.image.dim(), |(y, x)| (y * x) as f32 * 0.01);
    let flags = current.mapv(|c| {
        let mut f = 0;
        if c > 0.1 {
            f |= pbits::HIGH;
        }
        if c > 0.01 {
            f |= pbits::LOW;
        }
        f
    });
    out.flags.zip_mut_with(&flags, |f, p| {
        if p & pbits::HIGH != 0 {
            *f |= bits::PERSIST;
        }
    });
    let model = ModelParams::default();
    let attrs = PersistenceAttrs {
        model_id: model.identity(),
        model_name: model.name.clone(),
        threshold_high_e_per_s: 0.1,
        threshold_low_e_per_s: 0.01,
        t_meas_s: 86.0,
        previous_exposure_index: 11,
        software_version: persist::VERSION.into(),
        processed_utc: "2026-03-02T10:00:00.000000Z".into(),
        stats: None,
        warmup: None,
    };
    (
        out,
        PersistencePlanes {
            current_e_per_s: current,
            flags,
        },
        attrs,
    )
}

/// Equality with NaN pixels compared by bit pattern.
fn assert_same(a: &Exposure, b: &Exposure) {
    assert_eq!(a.meta, b.meta);
    let bits_of = |x: &Array2<f32>| x.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits_of(&a.image), bits_of(&b.image));
    assert_eq!(a.image.dim(), b.image.dim());
    assert_eq!(a.flags, b.flags);
    assert_eq!(a.ramp, b.ramp);
    assert_eq!(a.ramp_times_s, b.ramp_times_s);
}

fn only_file(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    v.sort();
    v
}

/// A valid input product modified in place with `f`.
fn modified(dir: &Path, name: &str, e: &Exposure, f: impl FnOnce(&hdf5::File)) -> PathBuf {
    let path = dir.join(name);
    write_exposure(&path, e).unwrap();
    let file = persist::h5io::open_rw_unlocked(&path).unwrap();
    f(&file);
    file.close().unwrap();
    path
}

fn assert_refused(path: &Path, field: &str) -> Error {
    let e = read_exposure(path).unwrap_err();
    let text = e.to_string();
    assert!(
        text.starts_with(&path.display().to_string()),
        "error does not name the file: {text}"
    );
    assert!(
        text.contains(&format!("`{field}`")) || text.contains(&format!("{field},")),
        "error does not name `{field}`: {text}"
    );
    // validate_path agrees and also names the field.
    let errors = validate_path(path).unwrap_err();
    assert!(
        errors.iter().any(|e| e
            .context
            .field
            .as_deref()
            .is_some_and(|f| f.contains(field))),
        "{errors:?}"
    );
    e
}

// ------------------------------------------------------------------------------------
// Round trips and byte identity

#[test]
fn input_round_trip() {
    let dir = tempfile::tempdir().unwrap();
    for (name, e) in [("a.h5", exposure()), ("lab.h5", lab_exposure())] {
        let path = dir.path().join(name);
        write_exposure(&path, &e).unwrap();
        assert_same(&read_exposure(&path).unwrap(), &e);
        assert_eq!(validate_path(&path).unwrap(), ProductKind::L1Exposure);
    }
    assert_eq!(
        only_file(dir.path()),
        ["a.h5", "lab.h5"],
        "temporary files left"
    );
}

#[test]
fn output_round_trip() {
    let dir = tempfile::tempdir().unwrap();
    let (e, planes, attrs) = planes_for(&lab_exposure());
    let path = dir.path().join("out.h5");
    write_output(&path, &e, &planes, &attrs).unwrap();
    let (e2, planes2, attrs2) = read_output(&path).unwrap();
    assert_same(&e2, &e);
    assert_eq!(planes2, planes);
    assert_eq!(attrs2, attrs);
    assert_eq!(validate_path(&path).unwrap(), ProductKind::L2Persistence);
    // An output is not an input.
    let err = read_exposure(&path).unwrap_err().to_string();
    assert!(err.contains("/persistence"), "{err}");
    // No previous exposure: t_meas_s NaN, previous index -1.
    let mut first = attrs.clone();
    first.t_meas_s = f64::NAN;
    first.previous_exposure_index = -1;
    let p2 = dir.path().join("first.h5");
    write_output(&p2, &e, &planes, &first).unwrap();
    let (_, _, a) = read_output(&p2).unwrap();
    assert!(a.t_meas_s.is_nan() && a.previous_exposure_index == -1);
}

#[test]
fn rewrite_is_byte_identical() {
    let dir = tempfile::tempdir().unwrap();
    let e = lab_exposure();
    let (a, b) = (dir.path().join("a.h5"), dir.path().join("b.h5"));
    write_exposure(&a, &e).unwrap();
    write_exposure(&b, &e).unwrap();
    let bytes = std::fs::read(&a).unwrap();
    assert!(!bytes.is_empty());
    assert_eq!(bytes, std::fs::read(&b).unwrap(), "input products differ");

    let (o, planes, attrs) = planes_for(&exposure());
    let (c, d) = (dir.path().join("c.h5"), dir.path().join("d.h5"));
    write_output(&c, &o, &planes, &attrs).unwrap();
    std::thread::sleep(std::time::Duration::from_millis(1100)); // a new second
    write_output(&d, &o, &planes, &attrs).unwrap();
    assert_eq!(std::fs::read(&c).unwrap(), std::fs::read(&d).unwrap());

    // Rewriting in place (replay after a crash) gives the same bytes too.
    write_output(&c, &o, &planes, &attrs).unwrap();
    assert_eq!(std::fs::read(&c).unwrap(), std::fs::read(&d).unwrap());
}

#[test]
fn checkpoint_round_trip_and_identity() {
    let dir = tempfile::tempdir().unwrap();
    let model = ModelParams::default();
    let meta = CheckpointMeta {
        detector: DetectorId(5),
        exposure_index: 41,
        model_id: model.identity(),
        model_name: model.name.clone(),
        model_json: model.canonical_json(),
        stage_json: r#"{"gaps":[3,4]}"#.into(),
        software_version: persist::VERSION.into(),
    };
    let mut state = State::zeros(9, 7, model.terms.len());
    state
        .amplitudes_e
        .indexed_iter_mut()
        .for_each(|((y, x, n), a)| {
            *a = (y as f64 + 0.1 * x as f64) * (n as f64 + 1.0);
        });
    state.release_count[[2, 3]] = 1;
    state.t_reset_unix_s = Some(1_772_323_351.5);
    state.last_index = Some(41);
    let path = checkpoint::save(dir.path(), &meta, &state).unwrap();
    assert!(path.ends_with("det5/ckpt_det5_0000000041.h5"));
    assert_eq!(
        checkpoint::load(&path).unwrap(),
        (meta.clone(), state.clone())
    );
    assert_eq!(validate_path(&path).unwrap(), ProductKind::Checkpoint);
    // The model can be recovered from the checkpoint.
    let (m, _) = checkpoint::load(&path).unwrap();
    assert_eq!(ModelParams::from_json(&m.model_json).unwrap(), model);
    // Same key and content written elsewhere: same bytes.
    let other = tempfile::tempdir().unwrap();
    let p2 = checkpoint::save(other.path(), &meta, &state).unwrap();
    assert_eq!(std::fs::read(&path).unwrap(), std::fs::read(&p2).unwrap());
    // A changed state under the same key replaces the file.
    state.release_count[[2, 3]] = 2;
    checkpoint::save(dir.path(), &meta, &state).unwrap();
    assert_eq!(checkpoint::load(&path).unwrap().1, state);
    assert_eq!(
        only_file(&dir.path().join("det5")),
        ["ckpt_det5_0000000041.h5"]
    );
}

// ------------------------------------------------------------------------------------
// Writers refuse what readers would refuse, and leave nothing behind

#[test]
fn writer_refuses_invalid_and_leaves_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("x.h5");
    let mut e = exposure();
    e.image[[3, 3]] = f32::INFINITY;
    let err = write_exposure(&path, &e).unwrap_err().to_string();
    assert!(err.contains("`/image`") && err.contains("Inf"), "{err}");
    assert!(err.starts_with(&path.display().to_string()), "{err}");
    let mut e = exposure();
    e.meta.t_illuminated_s = Some(200.0);
    let err = write_exposure(&path, &e).unwrap_err().to_string();
    assert!(err.contains("`t_illuminated_s`"), "{err}");
    let mut e = exposure();
    e.flags = Array2::zeros((3, 3));
    let err = write_exposure(&path, &e).unwrap_err().to_string();
    assert!(err.contains("`/flags`"), "{err}");
    assert!(
        only_file(dir.path()).is_empty(),
        "{:?}",
        only_file(dir.path())
    );
    // A failed rewrite leaves the published file untouched.
    write_exposure(&path, &exposure()).unwrap();
    let before = std::fs::read(&path).unwrap();
    let mut e = exposure();
    e.image.fill(f32::NAN);
    let err = write_exposure(&path, &e).unwrap_err().to_string();
    assert!(err.contains("NaN plane"), "{err}");
    assert_eq!(std::fs::read(&path).unwrap(), before);
    assert_eq!(only_file(dir.path()), ["x.h5"]);
}

// ------------------------------------------------------------------------------------
// Malformed inputs

#[test]
fn a_missing_attribute_is_refused_naming_it() {
    let dir = tempfile::tempdir().unwrap();
    let p = modified(dir.path(), "a.h5", &exposure(), |f| {
        f.delete_attr("t_exposure_s").unwrap();
    });
    let e = assert_refused(&p, "t_exposure_s");
    assert_eq!(e.kind, ErrorKind::Invalid);
    assert!(e.to_string().contains("missing"), "{e}");
}

#[test]
fn a_detector_written_as_a_string_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let p = modified(dir.path(), "a.h5", &exposure(), |f| {
        f.delete_attr("detector").unwrap();
        let v: hdf5::types::VarLenUnicode = "3".parse().unwrap();
        f.new_attr::<hdf5::types::VarLenUnicode>()
            .create("detector")
            .unwrap()
            .write_scalar(&v)
            .unwrap();
    });
    let e = assert_refused(&p, "detector");
    assert!(e.to_string().contains("integer"), "{e}");
}

#[test]
fn detector_out_of_range_and_bad_time() {
    let dir = tempfile::tempdir().unwrap();
    let p = modified(dir.path(), "a.h5", &exposure(), |f| {
        f.delete_attr("detector").unwrap();
        f.new_attr::<i32>()
            .create("detector")
            .unwrap()
            .write_scalar(&7)
            .unwrap();
    });
    assert_refused(&p, "detector");
    let mut e = exposure();
    e.meta.t_start_utc = "2026-03-01 noon".into();
    let p = dir.path().join("t.h5");
    let err = write_exposure(&p, &e).unwrap_err().to_string();
    assert!(err.contains("`t_start_utc`"), "{err}");
}

#[test]
fn a_float64_image_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let p = modified(dir.path(), "a.h5", &exposure(), |f| {
        f.unlink("image").unwrap();
        f.new_dataset_builder()
            .with_data(&Array2::<f64>::ones((16, 12)))
            .create("image")
            .unwrap();
    });
    let e = assert_refused(&p, "/image");
    assert!(e.to_string().contains("float64"), "{e}");
}

#[test]
fn image_flags_shape_mismatch() {
    let dir = tempfile::tempdir().unwrap();
    let p = modified(dir.path(), "a.h5", &exposure(), |f| {
        f.unlink("flags").unwrap();
        f.new_dataset_builder()
            .with_data(&Array2::<u32>::zeros((16, 13)))
            .create("flags")
            .unwrap();
    });
    let e = assert_refused(&p, "/flags");
    assert!(e.to_string().contains("differs"), "{e}");
}

#[test]
fn absurd_or_empty_dimensions_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    for (name, shape) in [("big.h5", (9000, 2)), ("empty.h5", (0, 12))] {
        let p = modified(dir.path(), name, &exposure(), |f| {
            f.unlink("image").unwrap();
            f.unlink("flags").unwrap();
            f.new_dataset_builder()
                .with_data(&Array2::<f32>::ones(shape))
                .create("image")
                .unwrap();
            f.new_dataset_builder()
                .with_data(&Array2::<u32>::zeros(shape))
                .create("flags")
                .unwrap();
        });
        let e = assert_refused(&p, "/image");
        assert!(e.to_string().contains("absurd"), "{e}");
        assert!(e.to_string().contains("8192"), "{e}");
    }
}

#[test]
fn a_truncated_file_is_refused_naming_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("a.h5");
    write_exposure(&p, &lab_exposure()).unwrap();
    let bytes = std::fs::read(&p).unwrap();
    for cut in [bytes.len() / 2, 100, 0] {
        std::fs::write(&p, &bytes[..cut]).unwrap();
        let e = read_exposure(&p).unwrap_err();
        assert!(e.to_string().starts_with(&p.display().to_string()), "{e}");
        assert!(validate_path(&p).is_err());
    }
}

#[test]
fn random_bytes_are_an_hdf5_error_naming_the_file() {
    use rand::{RngCore, SeedableRng};
    let dir = tempfile::tempdir().unwrap();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    let p = dir.path().join("noise.h5");
    for len in [1usize, 512, 8192] {
        let mut buf = vec![0u8; len];
        rng.fill_bytes(&mut buf);
        std::fs::write(&p, &buf).unwrap();
        let e = read_exposure(&p).unwrap_err();
        assert_eq!(e.kind, ErrorKind::Hdf5, "{e}");
        assert!(e.to_string().starts_with(&p.display().to_string()), "{e}");
    }
    // HDF5 signature followed by garbage.
    let mut buf = b"\x89HDF\r\n\x1a\n".to_vec();
    buf.extend((0..4096u32).map(|i| (i.wrapping_mul(2654435761) >> 13) as u8));
    std::fs::write(&p, &buf).unwrap();
    assert!(read_exposure(&p).is_err());
    // And a file that is not there.
    let e = read_exposure(&dir.path().join("absent.h5")).unwrap_err();
    assert_eq!(e.kind, ErrorKind::Io);
}

#[test]
fn inf_in_the_image_is_refused_naming_the_pixel() {
    let dir = tempfile::tempdir().unwrap();
    let p = modified(dir.path(), "a.h5", &exposure(), |f| {
        let mut img = exposure().image;
        img[[4, 5]] = f32::NEG_INFINITY;
        f.dataset("image").unwrap().write(&img).unwrap();
    });
    let e = assert_refused(&p, "/image");
    assert!(
        e.to_string().contains("Inf") && e.to_string().contains("[4, 5]"),
        "{e}"
    );
}

#[test]
fn an_all_nan_image_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let p = modified(dir.path(), "a.h5", &exposure(), |f| {
        let img = Array2::<f32>::from_elem((16, 12), f32::NAN);
        f.dataset("image").unwrap().write(&img).unwrap();
    });
    let e = assert_refused(&p, "/image");
    assert!(e.to_string().contains("NaN plane"), "{e}");
}

#[test]
fn a_persist_bit_in_the_input_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let p = modified(dir.path(), "a.h5", &exposure(), |f| {
        let mut flags = exposure().flags;
        flags[[0, 0]] |= bits::PERSIST;
        f.dataset("flags").unwrap().write(&flags).unwrap();
    });
    let e = assert_refused(&p, "/flags");
    assert!(e.to_string().contains("PERSIST"), "{e}");
}

#[test]
fn illuminated_longer_than_exposure() {
    let dir = tempfile::tempdir().unwrap();
    let p = modified(dir.path(), "a.h5", &exposure(), |f| {
        f.new_attr::<f64>()
            .create("t_illuminated_s")
            .unwrap()
            .write_scalar(&113.0)
            .unwrap();
    });
    let e = assert_refused(&p, "t_illuminated_s");
    assert!(e.to_string().contains("112"), "{e}");
}

#[test]
fn ramp_times_not_increasing() {
    let dir = tempfile::tempdir().unwrap();
    let p = modified(dir.path(), "a.h5", &lab_exposure(), |f| {
        let t = Array1::from(vec![1.5, 26.5, 26.5, 76.5]);
        f.dataset("ramp_times_s").unwrap().write(&t).unwrap();
    });
    assert_refused(&p, "/ramp_times_s");
    let p = modified(dir.path(), "b.h5", &lab_exposure(), |f| {
        f.unlink("ramp_times_s").unwrap();
        f.new_dataset_builder()
            .with_data(&Array1::from(vec![1.0, 2.0, 3.0]))
            .create("ramp_times_s")
            .unwrap();
    });
    assert_refused(&p, "/ramp_times_s");
}

#[test]
fn several_problems_are_all_named() {
    let dir = tempfile::tempdir().unwrap();
    let p = modified(dir.path(), "a.h5", &exposure(), |f| {
        f.delete_attr("exposure_index").unwrap();
        f.delete_attr("t_start_utc").unwrap();
    });
    let text = read_exposure(&p).unwrap_err().to_string();
    assert!(
        text.contains("exposure_index") && text.contains("t_start_utc"),
        "{text}"
    );
    assert_eq!(validate_path(&p).unwrap_err().len(), 2);
}

#[test]
fn output_with_inconsistent_persist_bits_refused() {
    let dir = tempfile::tempdir().unwrap();
    let (mut e, planes, attrs) = planes_for(&exposure());
    e.flags[[0, 0]] |= bits::PERSIST; // current 0 there: not HIGH
    let p = dir.path().join("o.h5");
    let err = write_output(&p, &e, &planes, &attrs)
        .unwrap_err()
        .to_string();
    assert!(err.contains("`/flags`") && err.contains("PERSIST"), "{err}");
    let (e, planes, mut attrs) = planes_for(&exposure());
    attrs.threshold_low_e_per_s = 1.0;
    let err = write_output(&p, &e, &planes, &attrs)
        .unwrap_err()
        .to_string();
    assert!(err.contains("/persistence@threshold_low_e_per_s"), "{err}");
    let (e, planes, mut attrs) = planes_for(&exposure());
    attrs.model_id = "not a hash".into();
    let err = write_output(&p, &e, &planes, &attrs)
        .unwrap_err()
        .to_string();
    assert!(err.contains("/persistence@model_id"), "{err}");
    assert!(only_file(dir.path()).is_empty());
}

#[test]
fn unknown_checkpoint_format_version() {
    let dir = tempfile::tempdir().unwrap();
    let model = ModelParams::default();
    let meta = CheckpointMeta {
        detector: DetectorId(1),
        exposure_index: 3,
        model_id: model.identity(),
        model_name: model.name.clone(),
        model_json: model.canonical_json(),
        stage_json: "{}".into(),
        software_version: persist::VERSION.into(),
    };
    let mut state = State::zeros(8, 8, 6);
    state.t_reset_unix_s = Some(1.7e9);
    state.last_index = Some(3);
    let path = checkpoint::save(dir.path(), &meta, &state).unwrap();
    let file = persist::h5io::open_rw_unlocked(&path).unwrap();
    file.delete_attr("format_version").unwrap();
    file.new_attr::<i64>()
        .create("format_version")
        .unwrap()
        .write_scalar(&2)
        .unwrap();
    file.close().unwrap();
    let e = checkpoint::load(&path).unwrap_err();
    assert_eq!(e.kind, ErrorKind::Checkpoint);
    let text = e.to_string();
    assert!(
        text.contains("`format_version`") && text.contains("2"),
        "{text}"
    );
    assert!(text.contains("not supported"), "{text}");
    // A negative amplitude is refused by State::check.
    let path = checkpoint::save(dir.path(), &meta, &state).unwrap();
    let file = persist::h5io::open_rw_unlocked(&path).unwrap();
    let mut a = state.amplitudes_e.clone();
    a[[1, 1, 1]] = -1.0;
    file.dataset("amplitudes_e").unwrap().write(&a).unwrap();
    file.close().unwrap();
    let text = checkpoint::load(&path).unwrap_err().to_string();
    assert!(text.contains("`/amplitudes_e`"), "{text}");
}

// ------------------------------------------------------------------------------------
// The real binary

#[test]
fn persist_validate_binary() {
    let dir = tempfile::tempdir().unwrap();
    let good = dir.path().join("good.h5");
    write_exposure(&good, &exposure()).unwrap();
    let bad = modified(dir.path(), "bad.h5", &exposure(), |f| {
        f.delete_attr("t_exposure_s").unwrap();
    });
    let model = dir.path().join("model.json");
    std::fs::write(&model, ModelParams::default().to_json_pretty()).unwrap();

    let run = |files: &[&Path]| {
        common::persist_cmd()
            .arg("validate")
            .args(files)
            .output()
            .unwrap()
    };
    let out = run(&[&good, &model]);
    assert_eq!(out.status.code(), Some(0), "{out:?}");
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        stdout.contains(&format!("ok l1_exposure {}", good.display())),
        "{stdout}"
    );
    assert!(
        stdout.contains(&format!("ok model {}", model.display())),
        "{stdout}"
    );

    let out = run(&[&bad, &good]);
    assert_eq!(out.status.code(), Some(1), "{out:?}");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains(&format!("{}: field `t_exposure_s`: missing", bad.display())),
        "{stderr}"
    );
    // Every file is checked, even after a failure.
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(stdout.contains("ok l1_exposure"), "{stdout}");
}
