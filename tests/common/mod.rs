//! Shared by the integration tests: a deterministic product stream, the real binary,
//! and directory comparisons.
#![allow(dead_code)]

use ndarray::Array2;
use persist::flags::bits;
use persist::product::synthetic::tiny_exposure;
use persist::product::Exposure;
use persist::units::{DetectorId, UtcSeconds};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// Fixed processing time, so that outputs are byte-comparable between runs.
pub const SOURCE_DATE_EPOCH: &str = "1772409600";

pub const T_EXPOSURE_S: f64 = 112.0;
pub const SLEW_S: f64 = 30.0;

pub fn t_start(det: u8, k: u64) -> f64 {
    let t0 = UtcSeconds::parse("2026-03-01T00:00:00Z").unwrap().0;
    t0 + f64::from(det) * 7.5 + k as f64 * (T_EXPOSURE_S + SLEW_S)
}

/// A small exposure with something to flag: a bright spot that moves, a saturated pixel
/// with no slope, a transient every seventh exposure, a dead pixel.
pub fn exposure(det: u8, k: u64, n: usize) -> Exposure {
    let mut image = Array2::from_shape_fn((n, n), |(y, x)| {
        1.0 + ((y * 7 + x * 3 + k as usize * 5 + det as usize) % 13) as f32 * 0.1
    });
    let mut flags = Array2::<u32>::zeros((n, n));
    let ku = k as usize;
    image[((ku * 3) % n, (ku * 5 + 1) % n)] = 3.0e4;
    image[((ku * 5 + 2) % n, (ku * 3) % n)] = 800.0;
    let sat = ((ku * 7 + 3) % n, (ku * 11 + 2) % n);
    image[sat] = f32::NAN;
    flags[sat] |= bits::SUR_ERROR | bits::OVERFLOW;
    if k % 7 == 3 {
        image[(n / 2, n / 3)] = 50.0;
        flags[(n / 2, n / 3)] |= bits::TRANSIENT;
    }
    image[(n - 1, 0)] = f32::NAN;
    flags[(n - 1, 0)] |= bits::NONFUNC;
    let mut e = tiny_exposure(
        det,
        k,
        n,
        n,
        &UtcSeconds(t_start(det, k)).to_iso(),
        T_EXPOSURE_S,
    );
    e.image = image;
    e.flags = flags;
    e
}

pub fn name(det: u8, k: u64) -> String {
    format!("l1_det{det}_exp{k:04}.h5")
}

/// Write exposures `ks` of each detector into `dir`; returns the paths.
pub fn write_stream(dir: &Path, dets: &[u8], ks: std::ops::Range<u64>, n: usize) -> Vec<PathBuf> {
    std::fs::create_dir_all(dir).unwrap();
    let mut out = Vec::new();
    for &d in dets {
        for k in ks.clone() {
            let p = dir.join(name(d, k));
            persist::product::write::write_exposure(&p, &exposure(d, k, n)).unwrap();
            out.push(p);
        }
    }
    out
}

/// The real binary, spawned without the test process's leaked descriptors: libhdf5
/// opens files without O_CLOEXEC and flocks them, and the tests mark them close-on-exec
/// only after the open returns; a child forked by a parallel test thread in between
/// kept the lock for its lifetime ("unable to lock file", CI flake in
/// `products::ramp_times_not_increasing`, twice). In the child, before exec, every
/// descriptor above stderr that is not close-on-exec is closed.
pub fn persist_cmd() -> Command {
    use std::os::unix::process::CommandExt;
    let mut c = Command::new(env!("CARGO_BIN_EXE_persist"));
    // SAFETY: between fork and exec only async-signal-safe calls (fcntl, close), on
    // descriptors of the child's own table.
    unsafe {
        c.pre_exec(|| {
            for fd in 3..4096 {
                let flags = libc::fcntl(fd, libc::F_GETFD);
                if flags >= 0 && flags & libc::FD_CLOEXEC == 0 {
                    libc::close(fd);
                }
            }
            Ok(())
        });
    }
    c
}

pub fn bin() -> Command {
    let mut c = persist_cmd();
    c.env("SOURCE_DATE_EPOCH", SOURCE_DATE_EPOCH)
        .env_remove("PERSIST_LOG")
        .env_remove("RUST_LOG");
    c
}

/// `persist run` arguments for a root holding `out/` and `ckpt/`.
pub fn run_args(input: &Path, root: &Path) -> Vec<String> {
    vec![
        "run".into(),
        "--input".into(),
        input.display().to_string(),
        "--output".into(),
        root.join("out").display().to_string(),
        "--checkpoints".into(),
        root.join("ckpt").display().to_string(),
        "--quiet".into(),
    ]
}

/// Run to completion; returns (status code, stderr).
pub fn run_batch(input: &Path, root: &Path, extra: &[&str]) -> (i32, String) {
    let out = bin()
        .args(run_args(input, root))
        .args(extra)
        .stdin(Stdio::null())
        .output()
        .unwrap();
    (
        out.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// Every file under `dir` (relative path -> bytes), skipping the lock file. Also polled
/// while a stage runs: a file renamed or removed between the listing and the read (a
/// temporary being published) is skipped, any other error panics.
pub fn tree(dir: &Path) -> std::collections::BTreeMap<PathBuf, Vec<u8>> {
    let vanished = |e: &std::io::Error| e.kind() == std::io::ErrorKind::NotFound;
    let mut m = std::collections::BTreeMap::new();
    if !dir.exists() {
        return m;
    }
    for e in walkdir::WalkDir::new(dir) {
        let e = match e {
            Ok(e) => e,
            Err(err) if err.io_error().is_some_and(vanished) => continue,
            Err(err) => panic!("{}: {err}", dir.display()),
        };
        if e.file_type().is_file() && e.file_name() != ".persist.lock" {
            let bytes = match std::fs::read(e.path()) {
                Ok(b) => b,
                Err(err) if vanished(&err) => continue,
                Err(err) => panic!("{}: {err}", e.path().display()),
            };
            m.insert(e.path().strip_prefix(dir).unwrap().to_path_buf(), bytes);
        }
    }
    m
}

/// Temporary files (`.`-led or `*.part`) under `dir`, the lock file excepted.
pub fn temporaries(dir: &Path) -> Vec<PathBuf> {
    if !dir.exists() {
        return Vec::new();
    }
    walkdir::WalkDir::new(dir)
        .into_iter()
        .filter_map(|e| e.ok())
        .filter(|e| {
            let n = e.file_name().to_string_lossy();
            e.file_type().is_file()
                && n != ".persist.lock"
                && (n.starts_with('.') || n.ends_with(".part"))
        })
        .map(|e| e.into_path())
        .collect()
}

/// The newest checkpoint file of a detector.
pub fn newest_checkpoint(root: &Path, det: u8) -> Option<(u64, PathBuf)> {
    persist::checkpoint::list(&root.join("ckpt"), DetectorId(det))
        .unwrap()
        .pop()
}

pub fn signal(child: &Child, sig: i32) {
    // SAFETY: kill(2) on our own child's pid.
    let r = unsafe { libc::kill(child.id() as libc::pid_t, sig) };
    assert_eq!(r, 0, "kill failed");
}

/// Wait for a child to exit, at most `limit`; kills it and panics past that.
pub fn wait_exit(child: &mut Child, limit: Duration) -> std::process::ExitStatus {
    let t0 = Instant::now();
    loop {
        if let Some(s) = child.try_wait().unwrap() {
            return s;
        }
        if t0.elapsed() > limit {
            let _ = child.kill();
            panic!("child did not exit within {limit:?}");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// Poll `cond` every 50 ms until it holds; false after `limit`.
pub fn wait_until(limit: Duration, mut cond: impl FnMut() -> bool) -> bool {
    let t0 = Instant::now();
    while t0.elapsed() < limit {
        if cond() {
            return true;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    cond()
}

/// JSON log lines of a file whose `message` is `msg`.
pub fn log_events(path: &Path, msg: &str) -> Vec<serde_json::Value> {
    std::fs::read_to_string(path)
        .unwrap_or_default()
        .lines()
        .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
        .filter(|v| v.get("message").and_then(|m| m.as_str()) == Some(msg))
        .collect()
}

/// The candidates a `diagnose` JSON declares (`significant`), in ranking order.
pub fn declared(diagnosis: &serde_json::Value) -> Vec<&serde_json::Value> {
    diagnosis["ranking"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|c| c["significant"] == true)
        .collect()
}

/// A JSON file (a model, a fit report, a summary), parsed; it must exist and parse.
pub fn read_json(path: impl AsRef<Path>) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

/// Run the real binary with `args`; it must succeed. Its standard output.
pub fn persist_ok(args: &[&str]) -> String {
    let o = persist_cmd().args(args).output().unwrap();
    assert!(
        o.status.success(),
        "{args:?}: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    String::from_utf8_lossy(&o.stdout).to_string()
}

/// Run the real binary with `args` (as [`bin`]): its exit code and standard error, for
/// the tests of refusals.
pub fn persist_status(args: &[&str]) -> (Option<i32>, String) {
    let o = bin().args(args).output().unwrap();
    (
        o.status.code(),
        String::from_utf8_lossy(&o.stderr).to_string(),
    )
}

/// `persist diagnose --input LAB --model MODEL --bootstrap 19 --json JSON` (warnings
/// only): the JSON written and the printed text. 19 replicas: a quick threshold for the
/// tests that read the ranking's other fields.
pub fn diagnose_quick(lab: &str, model: &str, json: &str) -> (serde_json::Value, String) {
    diagnose_quick_with(lab, model, json, &[])
}

/// [`diagnose_quick`] with `extra` options.
pub fn diagnose_quick_with(
    lab: &str,
    model: &str,
    json: &str,
    extra: &[&str],
) -> (serde_json::Value, String) {
    let mut a = vec![
        "diagnose",
        "--input",
        lab,
        "--model",
        model,
        "--bootstrap",
        "19",
        "--json",
        json,
        "--log-level",
        "warn",
    ];
    a.extend(extra);
    let text = persist_ok(&a);
    (read_json(json), text)
}

/// `persist simulate lab --size SIZE --seed SEED --campaign [EXTRA...] --out OUT`: the
/// laboratory campaign of the fit / diagnose tests.
pub fn lab_campaign(out: &str, size: u32, seed: u64, extra: &[&str]) {
    let (size, seed) = (size.to_string(), seed.to_string());
    let mut a = vec![
        "simulate",
        "lab",
        "--size",
        &size,
        "--seed",
        &seed,
        "--campaign",
    ];
    a.extend(extra);
    a.extend(["--out", out]);
    persist_ok(&a);
}

/// `persist simulate family --size SIZE --seed SEED --sequence campaign [EXTRA...] --out
/// OUT`: a campaign of the second truth generator (`persist::trapgen`).
pub fn family_campaign(out: &str, size: u32, seed: u64, extra: &[&str]) {
    let (size, seed) = (size.to_string(), seed.to_string());
    let mut a = vec![
        "simulate",
        "family",
        "--size",
        &size,
        "--seed",
        &seed,
        "--sequence",
        "campaign",
    ];
    a.extend(extra);
    a.extend(["--out", out]);
    persist_ok(&a);
}

/// Residual cells pooled over the illuminations into the same fluence x time cells, each
/// compared by its 95th percentile (`levels`) rather than per illumination and paired
/// (the defaults): tests that pin a figure measured on these cells pass them.
pub const POOLED_LEVELS_CELLS: [&str; 4] = ["--cells", "pooled", "--cell-statistic", "levels"];

/// `diagnose` refitting only the candidate effect (the default, `full`, refits it
/// jointly with the model's own effects): tests that pin a figure measured that way pass
/// it (with [`POOLED_LEVELS_CELLS`]).
pub const CANDIDATE_REFIT: [&str; 2] = ["--refit", "candidate"];

/// `--rates-per-s` of the thirteen-term reference models: thirteen terms 0.4 decade
/// apart, 1 to 1.6e-5 per second.
pub fn rates_13_terms() -> String {
    (0..13)
        .map(|k| format!("{:e}", 10f64.powf(-0.4 * k as f64)))
        .collect::<Vec<_>>()
        .join(",")
}

/// `persist simulate ARGS... --out DIR`, which must succeed.
pub fn simulate(dir: &Path, args: &[&str]) {
    let st = persist_cmd()
        .arg("simulate")
        .args(args)
        .arg("--out")
        .arg(dir)
        .output()
        .unwrap();
    assert!(
        st.status.success(),
        "{}",
        String::from_utf8_lossy(&st.stderr)
    );
}

/// `persist simulate lab --size SIZE --seed 1 EXTRA... --out DIR`, which must succeed.
pub fn simulate_lab(dir: &Path, size: &str, extra: &[&str]) {
    let args: Vec<&str> = ["lab", "--size", size, "--seed", "1"]
        .into_iter()
        .chain(extra.iter().copied())
        .collect();
    simulate(dir, &args);
}

/// A_bin interpolated (linearly in fluence) between the fitted bins around `f`.
pub fn a_bin_at(bins: &[persist::calib::BinResult], f: f64) -> f64 {
    let b: Vec<(f64, f64)> = bins
        .iter()
        .filter_map(|b| b.a_bin_e.map(|a| (b.fluence_mean_e, a)))
        .collect();
    let i = b.iter().position(|p| p.0 >= f).unwrap();
    let (x0, y0) = b[i - 1];
    let (x1, y1) = b[i];
    y0 + (y1 - y0) * (f - x0) / (x1 - x0)
}

/// A laboratory sequence of the simulator, in memory.
pub fn lab_sequence(cfg: &persist::sim::lab::LabConfig) -> persist::diag::data::Sequence {
    let mut ex = Vec::new();
    persist::sim::lab::run(cfg, |s| {
        ex.push(s.exposure);
        Ok(())
    })
    .unwrap();
    persist::diag::data::Sequence::from_exposures(ex).unwrap()
}
