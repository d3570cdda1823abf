//! A fault corpus through the real binary: every kind of bad input is quarantined with
//! a reason naming the problem, nothing panics, and the other products' outputs and
//! checkpoints are byte-identical to a run without the bad inputs.
//!
//! Clean products: detector 1, exposures 0..6; detector 3, exposures 0 and 6. The bad
//! products either cannot be attributed (their header fails: they claim detector 4, or
//! nothing readable) or are detector 3's exposures 1..5 (refused while reading or
//! stepping), so the clean run, where 1..5 are simply missing, is the comparison.

mod common;

use common::*;
use hdf5::types::VarLenUnicode;
use std::path::Path;

const N: usize = 16;

fn tamper(path: &Path, f: impl FnOnce(&hdf5::File)) {
    let file = persist::h5io::open_rw_unlocked(path).unwrap();
    f(&file);
}

fn set_str(f: &hdf5::File, name: &str, v: &str) {
    let _ = f.delete_attr(name);
    f.new_attr::<VarLenUnicode>()
        .create(name)
        .unwrap()
        .write_scalar(&v.parse::<VarLenUnicode>().unwrap())
        .unwrap();
}

fn set_f64(f: &hdf5::File, name: &str, v: f64) {
    let _ = f.delete_attr(name);
    f.new_attr::<f64>()
        .create(name)
        .unwrap()
        .write_scalar(&v)
        .unwrap();
}

fn set_i64(f: &hdf5::File, name: &str, v: i64) {
    let _ = f.delete_attr(name);
    f.new_attr::<i64>()
        .create(name)
        .unwrap()
        .write_scalar(&v)
        .unwrap();
}

fn replace<T: hdf5::H5Type + Clone>(f: &hdf5::File, path: &str, data: &ndarray::Array2<T>) {
    f.unlink(path).unwrap();
    f.new_dataset_builder()
        .with_data(data)
        .create(path)
        .unwrap();
}

/// A valid product of (det, k) written to `dir/file`.
fn valid(dir: &Path, file: &str, det: u8, k: u64) -> std::path::PathBuf {
    let p = dir.join(file);
    persist::product::write::write_exposure(&p, &exposure(det, k, N)).unwrap();
    p
}

/// (file name, what its reason must say: a field, or a word of the message).
type Fault = (&'static str, &'static str);

fn make_corpus(dir: &Path) -> Vec<Fault> {
    let mut faults = Vec::new();
    let bytes = std::fs::read(valid(dir, "tmpl.h5", 4, 0)).unwrap();
    std::fs::remove_file(dir.join("tmpl.h5")).unwrap();

    // Not readable as HDF5 at all.
    std::fs::write(dir.join("bad_truncated.h5"), &bytes[..bytes.len() / 2]).unwrap();
    faults.push(("bad_truncated.h5", "hdf5"));
    let mut flipped = bytes.clone();
    for b in &mut flipped[8..64] {
        *b ^= 0xff;
    }
    std::fs::write(dir.join("bad_flipped.h5"), &flipped).unwrap();
    faults.push(("bad_flipped.h5", "hdf5"));
    let mut x: u64 = 0x9e37_79b9_7f4a_7c15;
    let random: Vec<u8> = (0..4096)
        .map(|_| {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            x as u8
        })
        .collect();
    std::fs::write(dir.join("bad_random.h5"), &random).unwrap();
    faults.push(("bad_random.h5", "hdf5"));
    std::fs::write(dir.join("bad_empty.h5"), b"").unwrap();
    faults.push(("bad_empty.h5", "hdf5"));

    // Layout and attributes (refused from the header, no detector history touched).
    let p = valid(dir, "bad_no_image.h5", 4, 1);
    tamper(&p, |f| f.unlink("image").unwrap());
    faults.push(("bad_no_image.h5", "/image"));
    let p = valid(dir, "bad_image_f64.h5", 4, 2);
    tamper(&p, |f| {
        replace(f, "image", &ndarray::Array2::<f64>::ones((N, N)))
    });
    faults.push(("bad_image_f64.h5", "/image"));
    let p = valid(dir, "bad_flags_i16.h5", 4, 3);
    tamper(&p, |f| {
        replace(f, "flags", &ndarray::Array2::<i16>::zeros((N, N)))
    });
    faults.push(("bad_flags_i16.h5", "/flags"));
    let p = valid(dir, "bad_shapes.h5", 4, 4);
    tamper(&p, |f| {
        replace(f, "flags", &ndarray::Array2::<u32>::zeros((N, N / 2)))
    });
    faults.push(("bad_shapes.h5", "/flags"));
    let p = valid(dir, "bad_absurd_dims.h5", 4, 5);
    tamper(&p, |f| {
        replace(f, "image", &ndarray::Array2::<f32>::ones((1, 9000)));
        replace(f, "flags", &ndarray::Array2::<u32>::zeros((1, 9000)));
    });
    faults.push(("bad_absurd_dims.h5", "/image"));
    let p = valid(dir, "bad_zero_size.h5", 4, 6);
    tamper(&p, |f| {
        replace(f, "image", &ndarray::Array2::<f32>::ones((0, N)));
        replace(f, "flags", &ndarray::Array2::<u32>::zeros((0, N)));
    });
    faults.push(("bad_zero_size.h5", "/image"));
    let p = valid(dir, "bad_no_texp.h5", 4, 7);
    tamper(&p, |f| f.delete_attr("t_exposure_s").unwrap());
    faults.push(("bad_no_texp.h5", "t_exposure_s"));
    let p = valid(dir, "bad_detector.h5", 4, 8);
    tamper(&p, |f| set_i64(f, "detector", 7));
    faults.push(("bad_detector.h5", "detector"));
    let p = valid(dir, "bad_texp_negative.h5", 4, 9);
    tamper(&p, |f| set_f64(f, "t_exposure_s", -5.0));
    faults.push(("bad_texp_negative.h5", "t_exposure_s"));
    let p = valid(dir, "bad_time_text.h5", 4, 10);
    tamper(&p, |f| set_str(f, "t_start_utc", "yesterday after lunch"));
    faults.push(("bad_time_text.h5", "t_start_utc"));
    let p = valid(dir, "bad_product.h5", 4, 11);
    tamper(&p, |f| set_str(f, "product", "spherex.l2.something"));
    faults.push(("bad_product.h5", "product"));

    // Content, refused while reading or stepping: detector 3, exposures 1..5.
    let p = valid(dir, "bad_det3_exp0001_time_backwards.h5", 3, 1);
    let early = persist::units::UtcSeconds(t_start(3, 0) + 10.0).to_iso();
    tamper(&p, |f| set_str(f, "t_start_utc", &early));
    faults.push(("bad_det3_exp0001_time_backwards.h5", "t_start_utc"));
    let p = valid(dir, "bad_det3_exp0002_nan_plane.h5", 3, 2);
    tamper(&p, |f| {
        replace(
            f,
            "image",
            &ndarray::Array2::<f32>::from_elem((N, N), f32::NAN),
        )
    });
    faults.push(("bad_det3_exp0002_nan_plane.h5", "/image"));
    let p = valid(dir, "bad_det3_exp0003_inf.h5", 3, 3);
    tamper(&p, |f| {
        let mut img = exposure(3, 3, N).image;
        img[(4, 4)] = f32::INFINITY;
        replace(f, "image", &img);
    });
    faults.push(("bad_det3_exp0003_inf.h5", "/image"));
    let p = valid(dir, "bad_det3_exp0004_persist_bit.h5", 3, 4);
    tamper(&p, |f| {
        let mut fl = exposure(3, 4, N).flags;
        fl[(2, 2)] |= persist::flags::bits::PERSIST;
        replace(f, "flags", &fl);
    });
    faults.push(("bad_det3_exp0004_persist_bit.h5", "/flags"));
    let p = valid(dir, "bad_det3_exp0005_ramp_times.h5", 3, 5);
    tamper(&p, |f| {
        f.new_dataset_builder()
            .with_data(&ndarray::Array3::<f32>::zeros((3, N, N)))
            .create("ramp")
            .unwrap();
        f.new_dataset_builder()
            .with_data(&ndarray::arr1(&[1.5f64, 3.0, 2.0]))
            .create("ramp_times_s")
            .unwrap();
    });
    faults.push(("bad_det3_exp0005_ramp_times.h5", "/ramp_times_s"));

    // A different-content duplicate of detector 1's exposure 3.
    let mut e = exposure(1, 3, N);
    e.image.fill(4.0);
    persist::product::write::write_exposure(&dir.join("zz_det1_exp0003_other.h5"), &e).unwrap();
    faults.push(("zz_det1_exp0003_other.h5", "exposure_index"));
    faults
}

#[test]
fn every_kind_of_bad_input_is_quarantined_with_its_reason_and_the_rest_is_unchanged() {
    let tmp = tempfile::tempdir().unwrap();
    let clean_in = tmp.path().join("clean_in");
    write_stream(&clean_in, &[1], 0..6, N);
    valid(&clean_in, &name(3, 0), 3, 0);
    valid(&clean_in, &name(3, 6), 3, 6);
    let clean = tmp.path().join("clean");
    let (code, err) = run_batch(&clean_in, &clean, &[]);
    assert_eq!(code, 0, "{err}");

    let input = tmp.path().join("in");
    write_stream(&input, &[1], 0..6, N);
    valid(&input, &name(3, 0), 3, 0);
    valid(&input, &name(3, 6), 3, 6);
    let faults = make_corpus(&input);
    assert!(faults.len() >= 15);
    let q = tmp.path().join("quarantine");
    let bad = tmp.path().join("bad");
    let (code, err) = run_batch(&input, &bad, &["--quarantine", q.to_str().unwrap()]);
    assert_eq!(code, 1, "{err}");
    assert!(!err.contains("panicked"), "{err}");

    for (file, what) in &faults {
        assert!(q.join(file).exists(), "{file} not quarantined: {err}");
        assert!(!input.join(file).exists(), "{file} still in the input");
        let text = std::fs::read_to_string(q.join(format!("{file}.reason.json")))
            .unwrap_or_else(|e| panic!("{file}: no reason file: {e}"));
        let r: serde_json::Value = serde_json::from_str(&text).unwrap();
        let kind = r["kind"].as_str().unwrap_or_default();
        let field = r["field"].as_str().unwrap_or_default();
        let message = r["message"].as_str().unwrap_or_default();
        assert!(!message.is_empty(), "{file}: {text}");
        eprintln!("{file}: {kind} `{field}`: {message}");
        assert!(
            kind == *what || field.contains(what) || message.contains(what),
            "{file}: the reason does not name `{what}`: {text}"
        );
        assert!(
            r["file"].as_str().unwrap_or_default().ends_with(file),
            "{file}: {text}"
        );
        // The error report names the file too.
        assert!(err.contains(file), "{file} not reported: {err}");
    }
    assert_eq!(
        std::fs::read_dir(&q).unwrap().count(),
        2 * faults.len(),
        "unexpected files in quarantine"
    );

    // Everything else: byte-identical to the clean run, checkpoints included.
    assert_eq!(tree(&bad.join("out")), tree(&clean.join("out")));
    assert_eq!(tree(&bad.join("ckpt")), tree(&clean.join("ckpt")));
    assert_eq!(tree(&bad.join("out")).len(), 8);

    // A second run finds nothing more to do and nothing to refuse.
    let (code, err) = run_batch(&input, &bad, &["--quarantine", q.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
}
