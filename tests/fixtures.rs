//! The committed fixtures are exactly what their generator writes.

#[path = "../examples/make_fixtures.rs"]
#[allow(dead_code)]
mod make_fixtures;

use std::path::Path;

#[test]
fn committed_fixtures_are_reproducible() {
    let tmp = tempfile::tempdir().unwrap();
    let paths = make_fixtures::write_all(tmp.path()).unwrap();
    assert_eq!(paths.len(), 24);
    let committed = Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures");
    for p in paths {
        let name = p.file_name().unwrap();
        let want = std::fs::read(committed.join(name)).unwrap();
        let got = std::fs::read(&p).unwrap();
        assert!(
            want == got,
            "{}: differs from its generator's output",
            name.to_string_lossy()
        );
    }
}

#[test]
fn committed_fixtures_validate() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures");
    let mut n = 0;
    for e in std::fs::read_dir(&dir).unwrap() {
        let p = e.unwrap().path();
        if p.extension().is_some_and(|x| x == "h5") {
            assert_eq!(
                persist::validate::validate_path(&p).unwrap(),
                persist::validate::ProductKind::L1Exposure
            );
            n += 1;
        }
    }
    assert_eq!(n, 24);
}
