//! The FITS round trip: simulated exposures in SPHEREx's Level-2 layout through the
//! stage, read back with astropy and compared with the HDF5 run on the same data
//! (tests/fits/check_roundtrip.py); a corrupt FITS file is quarantined with its reason.
//! Needs python3 with astropy, numpy and h5py (scripts/bootstrap.sh installs them).

mod common;

use common::{persist_ok as ok, run_batch};
use std::path::Path;
use std::process::Command;

/// `persist simulate sky` of one 16 x 16 detector, written as SPHEREx-layout FITS.
fn simulate_fits(out: &Path, exposures: u32) -> Vec<String> {
    let n = exposures.to_string();
    ok(&[
        "simulate",
        "sky",
        "--out",
        &s(out),
        "--size",
        "16",
        "--detectors",
        "1",
        "--exposures",
        &n,
        "--seed",
        "2",
        "--format",
        "fits",
    ]);
    let fits = files(out, "fits");
    assert_eq!(fits.len(), exposures as usize);
    assert!(files(out, "h5").is_empty());
    fits
}

fn s(p: &Path) -> String {
    p.display().to_string()
}

fn files(dir: &Path, ext: &str) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == ext))
        .map(|p| s(&p))
        .collect();
    v.sort();
    v
}

/// Run one cfitsio call on a status word; panic on a non-zero status.
fn cfitsio(call: impl FnOnce(&mut i32) -> i32) {
    let mut status = 0;
    call(&mut status);
    assert_eq!(status, 0, "cfitsio status {status}");
}

#[test]
fn fits_round_trip_matches_hdf5_and_astropy_reads_everything() {
    let tmp = tempfile::tempdir().unwrap();
    let t = tmp.path();
    let (h5in, fitsin) = (t.join("h5in"), t.join("fitsin"));
    // 64 x 64, one detector, dense bright stars so that the high threshold is crossed.
    ok(&[
        "simulate",
        "sky",
        "--out",
        &s(&h5in),
        "--size",
        "64",
        "--detectors",
        "1",
        "--exposures",
        "8",
        "--seed",
        "5",
        "--n12",
        "20000",
    ]);
    let h5_products = files(&h5in, "h5");
    assert_eq!(h5_products.len(), 8);
    // The same exposures as FITS: image in MJy/sr with 0.5 e-/s per MJy/sr in ESCONV.
    let mut args = vec!["export".to_string(), "--fits".into()];
    args.extend(h5_products.iter().cloned());
    args.extend(
        [
            "--out",
            &s(&fitsin),
            "--placeholders",
            "--fits-gain",
            "1:0.5",
        ]
        .map(String::from),
    );
    ok(&args.iter().map(String::as_str).collect::<Vec<_>>());
    assert_eq!(files(&fitsin, "fits").len(), 8);
    // As archive files vary: inputs 0-2 lack MP_PERSIST in FLAGS (the stage adds it),
    // inputs 2-4 carry CHECKSUM and DATASUM in every extension (the stage updates FLAGS's).
    for (i, p) in files(&fitsin, "fits").iter().enumerate() {
        let mut f = fitsio::FitsFile::edit(p).unwrap();
        if i <= 2 {
            f.hdu("FLAGS").unwrap();
            // SAFETY: the open file's pointer and a NUL-terminated name, for this call.
            cfitsio(|st| unsafe { fitsio::sys::ffdkey(f.as_raw(), c"MP_PERSIST".as_ptr(), st) });
        }
        if (2..=4).contains(&i) {
            for h in 0..f.num_hdus().unwrap() {
                f.hdu(h).unwrap();
                // SAFETY: the open file's pointer, for this call.
                cfitsio(|st| unsafe { fitsio::sys::ffpcks(f.as_raw(), st) });
            }
        }
    }

    let (code, err) = run_batch(&h5in, &t.join("h5run"), &[]);
    assert_eq!(code, 0, "{err}");
    let (code, err) = run_batch(&fitsin, &t.join("fitsrun"), &[]);
    assert_eq!(code, 0, "{err}");
    let h5out = t.join("h5run").join("out");
    let fitsout = t.join("fitsrun").join("out");
    assert_eq!(files(&fitsout, "fits").len(), 8);

    // Every HDF5 output exported to FITS, for astropy to open.
    let exported = t.join("exported");
    let mut args = vec!["export".to_string(), "--fits".into()];
    args.extend(files(&h5out, "h5"));
    args.extend(["--out".to_string(), s(&exported)]);
    ok(&args.iter().map(String::as_str).collect::<Vec<_>>());

    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fits/check_roundtrip.py");
    let o = Command::new("python3")
        .arg(&script)
        .args([&fitsin, &fitsout, &h5out, &exported].map(|p| s(p)))
        .args([&h5in, &t.join("h5run"), &t.join("fitsrun")].map(|p| s(p)))
        .output()
        .unwrap();
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(
        o.status.success(),
        "{out}\n{}",
        String::from_utf8_lossy(&o.stderr)
    );
    let counts: serde_json::Value = serde_json::from_str(out.trim()).unwrap();
    assert_eq!(counts["outputs"], 8);
    assert!(counts["high_pixels"].as_u64().unwrap() > 0, "{counts}");
    // PRIMARY, IMAGE, VARIANCE, ZODI, PSF, WCS-WAVE of 8 files.
    assert_eq!(counts["untouched_extensions_identical"], 48);
    assert_eq!(counts["mp_persist_added"], 3, "{counts}");
    assert_eq!(counts["flags_checksum_verified"], 3, "{counts}");
    assert!(
        counts["h5_opened"].as_u64().unwrap() >= 8 + 8 + 2,
        "{counts}"
    );
}

#[test]
fn a_corrupt_fits_file_is_quarantined_and_the_rest_processed() {
    let tmp = tempfile::tempdir().unwrap();
    let t = tmp.path();
    let h5in = t.join("h5in");
    let fits = simulate_fits(&h5in, 2);
    // Exposure 1 cut in half, and a file that is not FITS at all.
    let bytes = std::fs::read(&fits[1]).unwrap();
    std::fs::write(&fits[1], &bytes[..bytes.len() / 2]).unwrap();
    std::fs::write(h5in.join("junk.fits"), b"SIMPLE  =  nonsense").unwrap();
    let (code, err) = run_batch(&h5in, &t.join("run"), &[]);
    assert_ne!(code, 0, "refusals must show in the exit code: {err}");
    let q = h5in.join(".quarantine");
    for name in [
        Path::new(&fits[1]).file_name().unwrap().to_str().unwrap(),
        "junk.fits",
    ] {
        assert!(q.join(name).exists(), "{name} not quarantined: {err}");
        let reason = std::fs::read_to_string(q.join(format!("{name}.reason.json"))).unwrap();
        assert!(reason.contains(name), "{reason}");
        assert!(reason.contains("field"), "{reason}");
    }
    assert_eq!(files(&t.join("run").join("out"), "fits").len(), 1);
}

/// Read a FITS image extension as i32 (the `FLAGS` and `PERSIST_FLAGS` planes).
fn plane_i32(path: &Path, ext: &str) -> Vec<i32> {
    let mut f = fitsio::FitsFile::open(path).unwrap();
    let hdu = f.hdu(ext).unwrap();
    hdu.read_image(&mut f).unwrap()
}

#[test]
fn archive_persist_bits_are_replaced_and_foreign_bit_names_and_outputs_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let t = tmp.path();
    let input = t.join("in");
    let fits = simulate_fits(&input, 4);
    // Exposure 0 as an archive file: its pipeline set PERSIST (bit 17) on every pixel.
    let before = plane_i32(Path::new(&fits[0]), "FLAGS");
    {
        let mut f = fitsio::FitsFile::edit(&fits[0]).unwrap();
        let hdu = f.hdu("FLAGS").unwrap();
        let set: Vec<i32> = before.iter().map(|b| b | 1 << 17).collect();
        hdu.write_image(&mut f, &set).unwrap();
    }
    // Exposure 2 names OVERFLOW at bit 5: its flags do not mean what the model reads.
    {
        let mut f = fitsio::FitsFile::edit(&fits[2]).unwrap();
        f.hdu("FLAGS").unwrap();
        let (key, comment) = (c"MP_OVERFLOW", c"another mission's bit");
        let mut status = 0;
        // SAFETY: the open file's pointer and two NUL-terminated strings, for this call.
        unsafe { fitsio::sys::ffukyj(f.as_raw(), key.as_ptr(), 5, comment.as_ptr(), &mut status) };
        assert_eq!(status, 0);
    }
    let (code, err) = run_batch(&input, &t.join("run"), &[]);
    assert_ne!(code, 0, "the refusal must show in the exit code: {err}");
    let name2 = Path::new(&fits[2]).file_name().unwrap().to_str().unwrap();
    let reason = std::fs::read_to_string(input.join(format!(".quarantine/{name2}.reason.json")))
        .unwrap_or_else(|e| panic!("{name2} not quarantined ({e}): {err}"));
    assert!(reason.contains("FLAGS/MP_OVERFLOW"), "{reason}");
    let out = t.join("run").join("out");
    let outputs = files(&out, "fits");
    assert_eq!(outputs.len(), 3, "exposures 0, 1 and 3: {outputs:?}\n{err}");

    // The output of exposure 0: bit 17 is this stage's (the high plane), every other bit
    // the input's, and PERSIN counts the archive's PERSIST pixels.
    let out0 = out.join(Path::new(&fits[0]).file_name().unwrap());
    let flags = plane_i32(&out0, "FLAGS");
    let pflags = plane_i32(&out0, "PERSIST_FLAGS");
    for ((f, p), b) in flags.iter().zip(&pflags).zip(&before) {
        assert_eq!((f >> 17) & 1, p & 1);
        assert_eq!(f & !(1 << 17), *b);
    }
    let mut f = fitsio::FitsFile::open(&out0).unwrap();
    let hdu = f.hdu("PERSIST_FLAGS").unwrap();
    assert_eq!(hdu.read_key::<i64>(&mut f, "PERSIN").unwrap(), 16 * 16);

    // The stage's own outputs are not exposures to flag, and a 16-bit FLAGS plane cannot
    // take bit 17.
    let again = t.join("again");
    std::fs::create_dir(&again).unwrap();
    std::fs::copy(&out0, again.join("x.fits")).unwrap();
    let y = again.join("y.fits");
    std::fs::copy(&fits[1], &y).unwrap();
    {
        let mut f = fitsio::FitsFile::edit(&y).unwrap();
        f.hdu("FLAGS").unwrap().delete(&mut f).unwrap();
        let desc = fitsio::images::ImageDescription {
            data_type: fitsio::images::ImageType::Short,
            dimensions: &[16, 16],
        };
        let hdu = f.create_image("FLAGS", &desc).unwrap();
        hdu.write_image(&mut f, &[0i16; 256]).unwrap();
    }
    let (code, err) = run_batch(&again, &t.join("run2"), &[]);
    assert_ne!(code, 0, "{err}");
    let quarantined = |name: &str| {
        std::fs::read_to_string(again.join(format!(".quarantine/{name}.reason.json")))
            .unwrap_or_else(|e| panic!("{name} not quarantined ({e}): {err}"))
    };
    let reason = quarantined("x.fits");
    assert!(reason.contains("PERSIST_CURRENT"), "{reason}");
    let reason = quarantined("y.fits");
    assert!(reason.contains("FLAGS/BITPIX"), "{reason}");
}

/// Update (or add) a string card in extension `ext`.
fn set_key_str(path: &Path, ext: &str, key: &str, value: &str) {
    let mut f = fitsio::FitsFile::edit(path).unwrap();
    f.hdu(ext).unwrap();
    let (k, v) = (
        std::ffi::CString::new(key).unwrap(),
        std::ffi::CString::new(value).unwrap(),
    );
    // SAFETY: the open file's pointer and NUL-terminated strings, for this call.
    cfitsio(|st| unsafe {
        fitsio::sys::ffukys(f.as_raw(), k.as_ptr(), v.as_ptr(), c"".as_ptr(), st)
    });
}

/// Delete a card from extension `ext`.
fn delete_key(path: &Path, ext: &str, key: &str) {
    let mut f = fitsio::FitsFile::edit(path).unwrap();
    f.hdu(ext).unwrap();
    let k = std::ffi::CString::new(key).unwrap();
    // SAFETY: the open file's pointer and a NUL-terminated name, for this call.
    cfitsio(|st| unsafe { fitsio::sys::ffdkey(f.as_raw(), k.as_ptr(), st) });
}

fn key_i64(path: &Path, ext: &str, key: &str) -> i64 {
    let mut f = fitsio::FitsFile::open(path).unwrap();
    let hdu = f.hdu(ext).unwrap();
    hdu.read_key::<i64>(&mut f, key)
        .unwrap_or_else(|e| panic!("{}: {ext}/{key}: {e}", path.display()))
}

fn key_str(path: &Path, ext: &str, key: &str) -> String {
    let mut f = fitsio::FitsFile::open(path).unwrap();
    let hdu = f.hdu(ext).unwrap();
    hdu.read_key::<String>(&mut f, key)
        .unwrap_or_else(|e| panic!("{}: {ext}/{key}: {e}", path.display()))
}

fn plane_f32(path: &Path, ext: &str) -> Vec<f32> {
    let mut f = fitsio::FitsFile::open(path).unwrap();
    let hdu = f.hdu(ext).unwrap();
    hdu.read_image(&mut f).unwrap()
}

/// `DATE-OBS` of a FITS exposure, as Unix seconds (UTC).
fn date_obs_s(path: &Path) -> f64 {
    let s = key_str(path, "IMAGE", "DATE-OBS");
    persist::units::UtcSeconds::parse(&format!("{s}Z"))
        .unwrap()
        .0
}

/// Two FITS outputs with the same persistence planes and exposure index.
fn assert_same_persistence(a: &Path, b: &Path) {
    let what = format!("{} vs {}", a.display(), b.display());
    assert_eq!(
        plane_f32(a, "PERSIST_CURRENT"),
        plane_f32(b, "PERSIST_CURRENT"),
        "{what}"
    );
    assert_eq!(plane_i32(a, "PERSIST_FLAGS"), plane_i32(b, "PERSIST_FLAGS"));
    for ext in ["PERSIST_CURRENT", "PERSIST_FLAGS"] {
        assert_eq!(
            key_i64(a, ext, "EXPINDEX"),
            key_i64(b, ext, "EXPINDEX"),
            "{what}"
        );
    }
}

#[test]
fn spherex_files_are_ordered_by_start_time_and_the_order_and_conversion_recorded() {
    let tmp = tempfile::tempdir().unwrap();
    let t = tmp.path();
    let a = t.join("a");
    let fits: Vec<std::path::PathBuf> = simulate_fits(&a, 4)
        .iter()
        .map(std::path::PathBuf::from)
        .collect();
    // As SPHEREx's files: no sequence number in the headers.
    for p in &fits {
        let mut f = fitsio::FitsFile::open(p).unwrap();
        let hdu = f.hdu("IMAGE").unwrap();
        assert!(hdu.read_key::<i64>(&mut f, "EXPINDEX").is_err());
    }
    // The same exposures under names in the reverse of their time order, exposure 1's
    // start given in TAI (37 s later, TIMESYS = 'TAI'), plus three files to refuse.
    let b = t.join("b");
    std::fs::create_dir(&b).unwrap();
    let renamed: Vec<_> = (0..4).map(|k| b.join(format!("x{}.fits", 3 - k))).collect();
    for (from, to) in fits.iter().zip(&renamed) {
        std::fs::copy(from, to).unwrap();
    }
    let tai = persist::units::UtcSeconds(date_obs_s(&fits[1]) + 37.0).to_iso();
    set_key_str(&renamed[1], "IMAGE", "DATE-OBS", tai.trim_end_matches('Z'));
    set_key_str(&renamed[1], "IMAGE", "TIMESYS", "TAI");
    let nodate = b.join("bad_nodate.fits");
    std::fs::copy(&fits[0], &nodate).unwrap();
    delete_key(&nodate, "IMAGE", "DATE-OBS");
    delete_key(&nodate, "IMAGE", "MJD-OBS");
    let tcb = b.join("bad_tcb.fits");
    std::fs::copy(&fits[3], &tcb).unwrap();
    set_key_str(&tcb, "IMAGE", "TIMESYS", "TCB");
    let mixed = b.join("zz_mixed.fits");
    std::fs::copy(&fits[2], &mixed).unwrap();
    {
        let mut f = fitsio::FitsFile::edit(&mixed).unwrap();
        let hdu = f.hdu("IMAGE").unwrap();
        hdu.write_key(&mut f, "EXPINDEX", 2i64).unwrap();
    }

    // A: the factor given as an argument; B: from the unit (e-/s).
    let (code, err) = run_batch(&a, &t.join("runa"), &["--fits-gain", "1:1"]);
    assert_eq!(code, 0, "{err}");
    let (code, err) = run_batch(&b, &t.join("runb"), &[]);
    assert_ne!(code, 0, "the refusals must show in the exit code: {err}");

    let out_a: Vec<_> = fits
        .iter()
        .map(|p| t.join("runa/out").join(p.file_name().unwrap()))
        .collect();
    let mut prev = -1;
    for (input, out) in fits.iter().zip(&out_a) {
        // The index is the start in ms since 1970 UTC, recorded in both extensions, and
        // the previous exposure of each is the one before it in time.
        let ms = (date_obs_s(input) * 1e3).round() as i64;
        for ext in ["PERSIST_CURRENT", "PERSIST_FLAGS"] {
            assert_eq!(key_i64(out, ext, "EXPINDEX"), ms, "{}", out.display());
            assert_eq!(key_str(out, ext, "IDXSRC"), "DATE-OBS: ms since 1970 UTC");
            assert_eq!(key_i64(out, ext, "PREV_EXP"), prev);
        }
        prev = ms;
        assert_eq!(
            key_str(out, "PERSIST_CURRENT", "ESCONVSR"),
            "argument --fits-gain"
        );
        assert_eq!(key_str(out, "PERSIST_CURRENT", "IMGUNIT"), "e-/s");
    }
    // B: in time order despite the names and the time scale, so the same planes.
    for (k, out) in out_a.iter().enumerate() {
        let ob = t.join("runb/out").join(renamed[k].file_name().unwrap());
        assert_same_persistence(&ob, out);
        assert_eq!(key_str(&ob, "PERSIST_CURRENT", "ESCONVSR"), "unit BUNIT");
    }
    let reason = |dir: &Path, name: &str| {
        std::fs::read_to_string(dir.join(format!(".quarantine/{name}.reason.json")))
            .unwrap_or_else(|e| panic!("{name} not quarantined ({e})"))
    };
    assert!(reason(&b, "bad_nodate.fits").contains("IMAGE/MJD-OBS"));
    assert!(reason(&b, "bad_tcb.fits").contains("IMAGE/TIMESYS"));
    assert!(reason(&b, "zz_mixed.fits").contains("not mixed"));

    // Another mission's keywords through a mapping file: the start in `DATE-BEG`, no
    // `MJD-OBS`; the same order and indices, the source named.
    let c = t.join("c");
    std::fs::create_dir(&c).unwrap();
    for p in &fits {
        let to = c.join(p.file_name().unwrap());
        std::fs::copy(p, &to).unwrap();
        let mut f = fitsio::FitsFile::edit(&to).unwrap();
        f.hdu("IMAGE").unwrap();
        // SAFETY: the open file's pointer and two NUL-terminated names, for this call.
        cfitsio(|st| unsafe {
            fitsio::sys::ffmnam(f.as_raw(), c"DATE-OBS".as_ptr(), c"DATE-BEG".as_ptr(), st)
        });
        drop(f);
        delete_key(&to, "IMAGE", "MJD-OBS");
    }
    let mapping = t.join("keywords.json");
    std::fs::write(
        &mapping,
        r#"{"date_obs": "DATE-BEG", "mjd_obs": "MJD-BEG"}"#,
    )
    .unwrap();
    let (code, err) = run_batch(&c, &t.join("runc"), &[]);
    assert_ne!(code, 0, "without the mapping the start is missing: {err}");
    assert!(reason(&c, "d1_e000000.fits").contains("IMAGE/MJD-OBS"));
    for p in &fits {
        let name = p.file_name().unwrap();
        std::fs::rename(c.join(".quarantine").join(name), c.join(name)).unwrap();
    }
    let m = s(&mapping);
    let (code, err) = run_batch(&c, &t.join("runc2"), &["--fits-keywords", &m]);
    assert_eq!(code, 0, "{err}");
    for out in &out_a {
        let oc = t.join("runc2/out").join(out.file_name().unwrap());
        assert_same_persistence(&oc, out);
        assert_eq!(
            key_str(&oc, "PERSIST_FLAGS", "IDXSRC"),
            "DATE-BEG: ms since 1970 UTC"
        );
    }

    // A file that starts between exposures 1 and 2, arriving after they were processed:
    // late, refused; the rerun leaves the outputs as they were.
    let before: Vec<Vec<u8>> = out_a.iter().map(|p| std::fs::read(p).unwrap()).collect();
    let late = a.join("late.fits");
    std::fs::copy(&fits[1], &late).unwrap();
    let t_late = persist::units::UtcSeconds(date_obs_s(&fits[1]) + 10.0).to_iso();
    set_key_str(&late, "IMAGE", "DATE-OBS", t_late.trim_end_matches('Z'));
    let (code, err) = run_batch(&a, &t.join("runa"), &["--fits-gain", "1:1"]);
    assert_ne!(code, 0, "{err}");
    assert!(reason(&a, "late.fits").contains("late product"), "{err}");
    for (p, b) in out_a.iter().zip(&before) {
        assert_eq!(&std::fs::read(p).unwrap(), b);
    }
}
