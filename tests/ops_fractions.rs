//! The per-exposure statistics (fraction of pixels above each threshold, pixels flagged)
//! agree with the output planes: recounted here from `/persistence/flags` and `/flags`
//! of every output, against the attributes of `/persistence` and the run's CSV table
//! (written by the worker processes of two detectors); `persist fractions` summarises
//! and plots the table.

mod common;

use common::*;
use persist::flags::{bits, pbits};
use persist::product::FlagStats;

#[test]
fn fractions_in_attributes_and_table_match_a_recount_of_the_planes() {
    let tmp = tempfile::tempdir().unwrap();
    let input = tmp.path().join("in");
    write_stream(&input, &[1, 2], 0..12, 24);
    let table = tmp.path().join("tables/run.csv");
    let (code, err) = run_batch(
        &input,
        tmp.path(),
        &["--table", &table.display().to_string()],
    );
    assert_eq!(code, 0, "{err}");
    let rows = persist::stage::table::read(&table).unwrap();
    assert_eq!(rows.len(), 24, "one row per detector and exposure");
    assert!(rows
        .windows(2)
        .all(|w| (w[0].detector, w[0].exposure_index) < (w[1].detector, w[1].exposure_index)));
    let mut flagged_somewhere = false;
    for row in &rows {
        let path = tmp
            .path()
            .join("out")
            .join(name(row.detector, row.exposure_index));
        let (_, planes, attrs) = persist::product::read::read_output(&path).unwrap();
        let f = persist::h5io::open(&path).unwrap();
        let flags = f.dataset("flags").unwrap().read_2d::<u32>().unwrap();
        let pflags = f
            .dataset("persistence/flags")
            .unwrap()
            .read_2d::<u8>()
            .unwrap();
        assert_eq!(pflags, planes.flags);
        // The recount, independent of the library's counting code.
        let n = pflags.len() as f64;
        let high = pflags.iter().filter(|&&b| b & pbits::HIGH != 0).count();
        let low = pflags.iter().filter(|&&b| b & pbits::LOW != 0).count();
        let persist_bits = flags.iter().filter(|&&b| b & bits::PERSIST != 0).count();
        assert_eq!(persist_bits, high, "PERSIST is bit 0");
        let want = FlagStats {
            fraction_above_high: high as f64 / n,
            fraction_above_low: low as f64 / n,
            n_flagged: high as u64,
        };
        assert_eq!(attrs.stats, Some(want), "{}", path.display());
        assert_eq!(row.stats, want, "table row of {}", path.display());
        assert_eq!(row.pixels, pflags.len() as u64);
        flagged_somewhere |= high > 0 && low > high;
    }
    assert!(
        flagged_somewhere,
        "the stream flags pixels at both thresholds"
    );

    let png = tmp.path().join("fractions.png");
    let out = persist_ok(&[
        "fractions",
        &table.display().to_string(),
        "--plot",
        &png.display().to_string(),
    ]);
    assert_eq!(out.lines().count(), 4, "{out}");
    assert!(
        out.lines()
            .nth(1)
            .unwrap()
            .trim_start()
            .starts_with("1        12"),
        "{out}"
    );
    assert!(std::fs::metadata(&png).unwrap().len() > 1000);
}
