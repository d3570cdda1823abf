//! Regression tests named after the problem they pin.

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
