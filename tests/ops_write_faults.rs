//! Write faults and cuts at the system-call level, through the real binary under strace.
//!
//! The run under test processes the next exposure (detector 1, exposure 3) on top of a
//! checkpoint of exposures 0..2. A traced clean run lists every `openat`, `write`,
//! `pwrite64`, `fsync`, `fdatasync` and `rename*` it makes on a file or directory under
//! its root (`in/`, `out/`, `ckpt/`), per thread. Then, for every (system call, file)
//! and every `when=N` up to the most calls one thread makes, and for ENOSPC and EIO:
//!
//! `strace -f -P FILE --inject=SYSCALL:error=ERRNO:when=N persist run ...`
//!
//! strace counts `when` per thread: a cell faults the N-th such call of every thread
//! that makes N of them (the number faulted is counted from strace's log, and must be at
//! least 1). Each faulted run must exit 1 (2 when the run cannot start: a lock, a
//! directory) with an error naming the file (no panic), leave
//! no temporary file, quarantine nothing; or, *absorbed*, exit 0 with everything already
//! byte-identical to the reference (never a success that lost something). A restart
//! without faults must then publish outputs and checkpoints byte-identical to an
//! unfaulted reference run (`SOURCE_DATE_EPOCH` fixed).
//!
//! The cut points on either side of each rename (a process killed with SIGKILL at the
//! rename, which is not made, and at the `fsync` of the directory after it, which is
//! not made) must recover the same way. The order fsync(file) < rename < fsync(dir) is
//! checked on the clean trace for both published files.
//!
//! `PERSIST_FAULT_TABLE=FILE` writes the matrix as Markdown (scripts/fault_matrix.sh
//! puts it in docs/operations.md).

mod common;

use common::*;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;

const N: usize = 16;
const KINDS: [&str; 6] = [
    "openat",
    "write",
    "pwrite64",
    "fsync",
    "fdatasync",
    "rename",
];
const TRACED: &str = "openat,write,pwrite64,fsync,fdatasync,rename,renameat,renameat2";

fn strace_available() -> bool {
    Command::new("strace").arg("-V").output().is_ok()
}

/// Copy a directory tree.
fn copy_tree(from: &Path, to: &Path) {
    for e in walkdir::WalkDir::new(from) {
        let e = e.unwrap();
        let rel = e.path().strip_prefix(from).unwrap();
        let dst = to.join(rel);
        if e.file_type().is_dir() {
            std::fs::create_dir_all(&dst).unwrap();
        } else if e.file_name() != ".persist.lock" {
            std::fs::copy(e.path(), &dst).unwrap();
        }
    }
}

/// A fresh root: the base (exposures 0..2 processed) plus exposure 3 in the input.
fn fresh(base: &Path, root: &Path) {
    let _ = std::fs::remove_dir_all(root);
    copy_tree(base, root);
}

fn run_args_abs(root: &Path) -> Vec<String> {
    run_args(&root.join("in"), root)
}

/// `persist run` on `root` under strace with `strace_args`; (exit code, stderr).
fn run_traced(root: &Path, strace_args: &[String]) -> (Option<i32>, String) {
    let out = Command::new("strace")
        .args(strace_args)
        .arg("--")
        .arg(env!("CARGO_BIN_EXE_persist"))
        .args(run_args_abs(root))
        .env("SOURCE_DATE_EPOCH", SOURCE_DATE_EPOCH)
        .env_remove("PERSIST_LOG")
        .env_remove("RUST_LOG")
        .output()
        .unwrap();
    (
        out.status.code(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// One traced call: (thread, syscall kind, path under the root).
type Call = (String, String, PathBuf);

/// The calls of a clean run, from per-thread logs (`-ff`), with fds shown as paths (`-y`).
fn trace_calls(root: &Path, logs: &Path) -> Vec<Call> {
    std::fs::create_dir_all(logs).unwrap();
    let prefix = logs.join("t");
    let args: Vec<String> = [
        "-f",
        "-ff",
        "-qq",
        "-y",
        "-s",
        "0",
        "-e",
        &format!("trace={TRACED}"),
        "-o",
        &prefix.display().to_string(),
    ]
    .iter()
    .map(|s| s.to_string())
    .collect();
    let (code, err) = run_traced(root, &args);
    assert_eq!(code, Some(0), "clean traced run: {err}");
    let mut calls = Vec::new();
    let mut files: Vec<_> = std::fs::read_dir(logs)
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    files.sort();
    let root_s = root.display().to_string();
    for f in files {
        let tid = f.extension().unwrap().to_string_lossy().into_owned();
        for line in std::fs::read_to_string(&f).unwrap().lines() {
            let Some(open) = line.find('(') else { continue };
            let mut kind = line[..open].to_string();
            if kind.starts_with("rename") {
                kind = "rename".into();
            }
            if !KINDS.contains(&kind.as_str()) {
                continue;
            }
            let args = &line[open + 1..];
            // A path argument ("..."), else the first fd's path (5</path>).
            let by_name = kind == "openat" || kind == "rename";
            let path = if let Some(q) = args.find('"').filter(|_| by_name) {
                args[q + 1..].split('"').next().unwrap_or("").to_string()
            } else if let Some(lt) = args.find('<').filter(|&i| i < 8 && !by_name) {
                args[lt + 1..].split('>').next().unwrap_or("").to_string()
            } else {
                continue;
            };
            if let Some(rel) = path.strip_prefix(&root_s) {
                let rel = rel.trim_start_matches('/');
                calls.push((tid.clone(), kind, PathBuf::from(rel)));
            }
        }
    }
    calls
}

/// The name an error should give for a file: the final name of a temporary one.
fn named(rel: &Path) -> String {
    let n = rel
        .file_name()
        .map_or(String::new(), |n| n.to_string_lossy().into_owned());
    match n.strip_prefix('.').and_then(|m| m.strip_suffix(".part")) {
        Some(f) => f.to_string(),
        None => n,
    }
}

struct Outcome {
    injected: usize,
    absorbed: bool,
    ok: bool,
    note: String,
}

/// Fault (or cut) one run with `inject`, restart it, compare with the reference.
fn cell(
    base: &Path,
    root: &Path,
    target: &Path,
    inject: &str,
    kill: bool,
    reference: &Tree,
) -> Outcome {
    fresh(base, root);
    let log = root.with_extension("strace");
    let args: Vec<String> = [
        "-f",
        "-qq",
        "-e",
        &format!("trace={TRACED}"),
        "-P",
        &root.join(target).display().to_string(),
        &format!("--inject={inject}"),
        "-o",
        &log.display().to_string(),
    ]
    .iter()
    .map(|s| s.to_string())
    .collect();
    let (code, err) = run_traced(root, &args);
    // A call cut by SIGKILL never returns, so strace logs no "(INJECTED)" for it: the
    // process killed by the signal is the evidence.
    let injected = if kill {
        usize::from(code.is_none())
    } else {
        std::fs::read_to_string(&log)
            .unwrap_or_default()
            .matches("(INJECTED)")
            .count()
    };
    let mut problems = Vec::new();
    if injected == 0 {
        problems.push("nothing injected".to_string());
    }
    if err.contains("panicked") {
        problems.push(format!("panic: {err}"));
    }
    let mut absorbed = false;
    if !kill {
        match code {
            // Absorbed: a call whose failure the stage works around (the detector
            // listing before the run reads every header again); everything is already
            // published, byte-identical.
            Some(0) if Tree::of(root) == *reference => absorbed = true,
            Some(0) => problems.push(format!("silent success, outputs differ: {err}")),
            // 1: failures reported; 2: the run could not start (a lock, a directory).
            Some(1 | 2) if !err.contains(&named(target)) => {
                problems.push(format!("error does not name {}: {err}", named(target)))
            }
            Some(1 | 2) => {}
            _ => problems.push(format!("exit {code:?}, not 1 or 2: {err}")),
        }
        for d in ["out", "ckpt"] {
            let t = temporaries(&root.join(d));
            if !t.is_empty() {
                problems.push(format!("temporaries left: {t:?}"));
            }
        }
    }
    let (code2, err2) = run_batch(&root.join("in"), root, &[]);
    if code2 != 0 {
        problems.push(format!("restart exit {code2}: {err2}"));
    }
    let got = Tree::of(root);
    if got.out != reference.out {
        problems.push("outputs differ from the reference".into());
    }
    if got.ckpt != reference.ckpt {
        problems.push("checkpoints differ from the reference".into());
    }
    if !tree(&root.join("in/.quarantine")).is_empty() {
        problems.push("an input was quarantined".into());
    }
    let ok = problems.is_empty();
    Outcome {
        injected,
        absorbed,
        ok,
        note: problems.join("; "),
    }
}

#[derive(PartialEq)]
struct Tree {
    out: BTreeMap<PathBuf, Vec<u8>>,
    ckpt: BTreeMap<PathBuf, Vec<u8>>,
}

impl Tree {
    fn of(root: &Path) -> Tree {
        Tree {
            out: tree(&root.join("out")),
            ckpt: tree(&root.join("ckpt")),
        }
    }
}

/// `when=N` values for `max` calls: all up to 12, else 1..6, the last six and the
/// middle (the brief's "sample when there are hundreds").
fn whens(max: usize) -> Vec<usize> {
    if max <= 12 {
        return (1..=max).collect();
    }
    let mut v: Vec<usize> = (1..=6).chain(max - 5..=max).collect();
    v.push(max / 2);
    v.sort();
    v.dedup();
    v
}

#[test]
fn every_write_fsync_rename_and_open_fault_recovers_byte_identically() {
    if !strace_available() {
        panic!("strace not found: `make test` installs it (scripts/bootstrap.sh)");
    }
    let tmp = tempfile::tempdir().unwrap();
    let tmp_path = tmp.path().canonicalize().unwrap();
    // The base: exposures 0..2 processed; then exposure 3 arrives.
    let base = tmp_path.join("base");
    write_stream(&base.join("in"), &[1], 0..3, N);
    let (code, err) = run_batch(&base.join("in"), &base, &[]);
    assert_eq!(code, 0, "{err}");
    write_stream(&base.join("in3"), &[1], 3..4, N);
    std::fs::rename(
        base.join("in3").join(name(1, 3)),
        base.join("in").join(name(1, 3)),
    )
    .unwrap();
    std::fs::remove_dir(base.join("in3")).unwrap();
    // The reference: one clean run.
    let ref_root = tmp_path.join("reference");
    fresh(&base, &ref_root);
    let (code, err) = run_batch(&ref_root.join("in"), &ref_root, &[]);
    assert_eq!(code, 0, "{err}");
    let reference = Tree::of(&ref_root);
    assert!(reference.out.contains_key(Path::new(&name(1, 3))));

    // The calls of a clean traced run, per (kind, file): the most one thread makes.
    let traced = tmp_path.join("traced");
    fresh(&base, &traced);
    let calls = trace_calls(&traced, &tmp_path.join("logs"));
    assert!(
        Tree::of(&traced) == reference,
        "a traced run gives other bytes"
    );
    check_publication_order(&calls);
    let mut per_thread: BTreeMap<(String, PathBuf), BTreeMap<String, usize>> = BTreeMap::new();
    for (tid, kind, path) in &calls {
        *per_thread
            .entry((kind.clone(), path.clone()))
            .or_default()
            .entry(tid.clone())
            .or_default() += 1;
    }
    for kind in ["openat", "pwrite64", "fsync", "rename"] {
        assert!(
            per_thread.keys().any(|(k, _)| k == kind),
            "no {kind} traced: {calls:?}"
        );
    }

    let mut rows = Vec::new();
    let mut failures = Vec::new();
    let root = tmp_path.join("cell");
    let t0 = std::time::Instant::now();
    for ((kind, path), threads) in &per_thread {
        let total: usize = threads.values().sum();
        let max = threads.values().copied().max().unwrap_or(0);
        let ns = whens(max);
        let mut recovered = [0usize; 2];
        let mut absorbed = [0usize; 2];
        let mut injected = 0;
        for (i, errno) in ["ENOSPC", "EIO"].iter().enumerate() {
            for &n in &ns {
                let inject = format!("{kind}:error={errno}:when={n}");
                let o = cell(&base, &root, path, &inject, false, &reference);
                injected += o.injected;
                absorbed[i] += usize::from(o.absorbed);
                if o.ok {
                    recovered[i] += 1;
                } else {
                    failures.push(format!("{} {inject}: {}", path.display(), o.note));
                }
            }
        }
        rows.push(format!(
            "| `{kind}` | `{}` | {total} ({} thread{}) | {} | {} | {} | {injected} |",
            path.display(),
            threads.len(),
            if threads.len() == 1 { "" } else { "s" },
            span(&ns),
            score(recovered[0], absorbed[0], ns.len()),
            score(recovered[1], absorbed[1], ns.len()),
        ));
    }

    // Cuts on either side of each rename: killed at the rename (not made), and at the
    // directory's fsync right after it (not made).
    let mut cuts = Vec::new();
    let renamed: Vec<PathBuf> = per_thread
        .keys()
        .filter(|(k, _)| k == "rename")
        .map(|(_, p)| p.clone())
        .collect();
    for tmp_file in &renamed {
        let dir = tmp_file.parent().unwrap().to_path_buf();
        for (side, target, inject) in [
            (
                "before the rename",
                tmp_file.clone(),
                "rename:error=EIO:signal=SIGKILL:when=1".to_string(),
            ),
            (
                "after the rename, before the directory fsync",
                dir.clone(),
                "fsync:error=EIO:signal=SIGKILL:when=1".to_string(),
            ),
        ] {
            let o = cell(&base, &root, &target, &inject, true, &reference);
            if !o.ok {
                failures.push(format!("cut {side} of {}: {}", tmp_file.display(), o.note));
            }
            cuts.push(format!(
                "| `{}` | {side} | `{inject}` on `{}` | {} |",
                named(tmp_file),
                target.display(),
                if o.ok { "recovered" } else { "FAILED" }
            ));
        }
    }
    let took = t0.elapsed();
    eprintln!("{} rows, {} cuts in {took:.1?}", rows.len(), cuts.len());
    for r in rows.iter().chain(&cuts) {
        eprintln!("{r}");
    }
    if let Ok(out) = std::env::var("PERSIST_FAULT_TABLE") {
        let mut md = String::from(
            "| system call | file | calls (threads) | `when=N` | ENOSPC recovered | EIO recovered | calls faulted |\n\
             |---|---|---|---|---|---|---|\n",
        );
        for r in &rows {
            md.push_str(r);
            md.push('\n');
        }
        md.push_str("\n| file | cut | strace | restart |\n|---|---|---|---|\n");
        for c in &cuts {
            md.push_str(c);
            md.push('\n');
        }
        std::fs::write(out, md).unwrap();
    }
    assert!(
        failures.is_empty(),
        "{} cells failed:\n{}",
        failures.len(),
        failures.join("\n")
    );
}

/// `recovered/tried`, and how many of them the run absorbed (exit 0, nothing lost).
fn score(recovered: usize, absorbed: usize, tried: usize) -> String {
    if absorbed == 0 {
        format!("{recovered}/{tried}")
    } else {
        format!("{recovered}/{tried} ({absorbed} absorbed)")
    }
}

/// `1..12` or `1, 2, 3, ...`.
fn span(ns: &[usize]) -> String {
    let contiguous = ns.windows(2).all(|w| w[1] == w[0] + 1);
    match (ns.first(), ns.last()) {
        (Some(a), Some(b)) if contiguous && a != b => format!("{a}..{b}"),
        _ => ns
            .iter()
            .map(|n| n.to_string())
            .collect::<Vec<_>>()
            .join(", "),
    }
}

/// For each renamed file: its fsync comes before the rename, and the directory's fsync
/// after it, in the same thread.
fn check_publication_order(calls: &[Call]) {
    let mut renames = 0;
    for (i, (tid, kind, path)) in calls.iter().enumerate() {
        if kind != "rename" {
            continue;
        }
        renames += 1;
        let same = |c: &&Call| &c.0 == tid;
        let before = calls[..i]
            .iter()
            .filter(same)
            .any(|c| c.1 == "fsync" && &c.2 == path);
        let dir = path.parent().unwrap();
        let after = calls[i + 1..]
            .iter()
            .filter(same)
            .any(|c| c.1 == "fsync" && c.2 == dir);
        assert!(before, "{}: no fsync before its rename", path.display());
        assert!(
            after,
            "{}: no directory fsync after its rename",
            path.display()
        );
    }
    assert_eq!(
        renames, 2,
        "one output and one checkpoint renamed: {calls:?}"
    );
}
