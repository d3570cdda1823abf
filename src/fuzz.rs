//! `persist fuzz`: a mutation fuzzer over every reader of the stage, run against the
//! real stage.
//!
//! Templates: an HDF5 input (`fixtures/l1_det1_exp0005.h5`), a FITS input (the export
//! of `fixtures/l1_det2_exp0005.h5`), a checkpoint and the default model file (both made
//! by a reference run of `persist run` on the 24 fixtures). Mutant `k` (readers in turn:
//! HDF5, FITS, checkpoint, model) is its template with one to three of: random byte
//! overwrites, bit flips, a truncation, a zeroed block, a duplicated block; the random
//! stream is `crate::sim::rng::stream(seed, [k])`, so a mutant is the same for a seed
//! whatever else runs.
//!
//! Each mutant is read directly: inputs through the reader guard ([`crate::guard`]: its
//! metadata, then whole), checkpoints through the guard, model files in-process (their
//! parsing is ours: JSON, schema, [`crate::model::ModelParams::from_json`]; a panic is
//! caught and counted). Then the stage meets them:
//!
//! - inputs in batches: the 24 good fixtures plus `batch` mutants (named `zz_m*`, so
//!   observed after the good products) in one input directory, one `persist run`;
//! - checkpoints one run each (the first `stage_checkpoints`): the reference run's
//!   directories with its newest checkpoint of detector 1 replaced by the mutant, then
//!   `persist run` again (a restart).
//!
//! A **stage death** is a run killed by a signal or exiting with a status other than 0
//! or 1; a **hang** is a run still going after `stage_timeout` (killed); a **good
//! exposure lost** is one of the 24 good outputs missing or not byte-identical to the
//! reference run's. Runs with any of these keep their inputs under `WORK/failures/`.

use crate::error::{Error, ErrorKind, Result};
use crate::guard::{self, Guard};
use rand::{Rng, RngCore};
use serde::Serialize;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// The readers fuzzed, in the order mutants are assigned to them.
pub const READERS: [&str; 4] = ["hdf5 input", "fits input", "checkpoint", "model file"];

/// What a fuzz run does.
#[derive(Debug, Clone)]
pub struct FuzzConfig {
    pub mutants: usize,
    pub seed: u64,
    /// The repository's `fixtures/` (24 Level-1 products).
    pub fixtures: PathBuf,
    /// Scratch directory (emptied first).
    pub work: PathBuf,
    /// The `persist` executable (the stage runs, the guard's child).
    pub exe: PathBuf,
    /// Input mutants per stage run.
    pub batch: usize,
    /// Checkpoint mutants that also get a stage restart each.
    pub stage_checkpoints: usize,
    /// The reader guard's limit per read.
    pub read_timeout: Duration,
    /// A stage run still going after this is a hang.
    pub stage_timeout: Duration,
}

/// Counts of one reader.
#[derive(Debug, Clone, Default, Serialize)]
pub struct ReaderCounts {
    pub reader: String,
    pub mutants: usize,
    /// Read whole without an error.
    pub read_ok: usize,
    /// Refused with an error naming the file (the reader returned).
    pub refused: usize,
    /// The reader crashed, hung or ran out of its limits in its child (contained).
    pub contained: usize,
    /// Model files: panics of our parser (caught here; a bug).
    pub panics: usize,
    /// Mutants that also went through a stage run.
    pub in_stage: usize,
}

/// The whole run.
#[derive(Debug, Clone, Default, Serialize)]
pub struct FuzzReport {
    pub seed: u64,
    pub readers: Vec<ReaderCounts>,
    pub stage_runs: usize,
    pub stage_deaths: usize,
    pub hangs: usize,
    /// Good exposures expected across all stage runs, and those lost.
    pub good_expected: usize,
    pub good_lost: usize,
    pub elapsed_s: f64,
}

fn fuzz_error(msg: impl Into<String>) -> Error {
    Error::new(ErrorKind::Io, msg)
}

/// Apply one to three random mutations to `bytes`.
pub fn mutate(template: &[u8], rng: &mut impl RngCore) -> Vec<u8> {
    let mut b = template.to_vec();
    let ops = rng.random_range(1..=3);
    for _ in 0..ops {
        if b.is_empty() {
            break;
        }
        let n = b.len();
        match rng.random_range(0..5) {
            0 => {
                for _ in 0..rng.random_range(1..=16) {
                    let i = rng.random_range(0..n);
                    b[i] = rng.random();
                }
            }
            1 => {
                for _ in 0..rng.random_range(1..=8) {
                    let i = rng.random_range(0..n);
                    b[i] ^= 1 << rng.random_range(0..8);
                }
            }
            2 => b.truncate(rng.random_range(0..n)),
            3 => {
                let at = rng.random_range(0..n);
                let len = rng.random_range(1..=4096).min(n - at);
                b[at..at + len].fill(0);
            }
            _ => {
                let from = rng.random_range(0..n);
                let len = rng.random_range(1..=4096).min(n - from);
                let to = rng.random_range(0..n);
                let len = len.min(n - to);
                let block = b[from..from + len].to_vec();
                b[to..to + len].copy_from_slice(&block);
            }
        }
    }
    b
}

/// What one direct read did.
enum Outcome {
    Ok,
    Refused,
    Contained,
    Panic,
}

fn classify<T>(r: Result<T>) -> Outcome {
    match r {
        Ok(_) => Outcome::Ok,
        Err(e) if e.kind == ErrorKind::Crash => Outcome::Contained,
        Err(_) => Outcome::Refused,
    }
}

/// The worse of two outcomes (a refused metadata read is the mutant's outcome).
fn worse(a: Outcome, b: impl FnOnce() -> Outcome) -> Outcome {
    match a {
        Outcome::Ok => b(),
        other => other,
    }
}

fn write(path: &Path, bytes: &[u8]) -> Result<()> {
    std::fs::write(path, bytes).map_err(|e| Error::io(path, e))
}

fn copy_dir(from: &Path, to: &Path) -> Result<()> {
    for e in walkdir::WalkDir::new(from) {
        let e = e.map_err(|e| fuzz_error(e.to_string()))?;
        let rel = e.path().strip_prefix(from).unwrap_or(e.path());
        let dst = to.join(rel);
        if e.file_type().is_dir() {
            std::fs::create_dir_all(&dst).map_err(|x| Error::io(&dst, x))?;
        } else if e.file_name() != ".persist.lock" {
            std::fs::copy(e.path(), &dst).map_err(|x| Error::io(&dst, x))?;
        }
    }
    Ok(())
}

/// How a stage run ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Ended {
    Clean,
    Death,
    Hang,
}

fn run_stage(cfg: &FuzzConfig, root: &Path) -> Result<Ended> {
    use std::os::unix::process::ExitStatusExt;
    let mut child = Command::new(&cfg.exe)
        .args(["run", "--quiet", "--checkpoint-every", "4", "--input"])
        .arg(root.join("in"))
        .arg("--output")
        .arg(root.join("out"))
        .arg("--checkpoints")
        .arg(root.join("ckpt"))
        .arg("--reader-timeout-s")
        .arg(cfg.read_timeout.as_secs_f64().to_string())
        .env("SOURCE_DATE_EPOCH", "1772409600")
        .env("PERSIST_LOG", "error")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .map_err(|e| Error::io(&cfg.exe, e))?;
    let t0 = Instant::now();
    loop {
        if let Some(st) = child.try_wait().map_err(|e| Error::io(&cfg.exe, e))? {
            return Ok(match (st.signal(), st.code()) {
                (None, Some(0 | 1)) => Ended::Clean,
                _ => Ended::Death,
            });
        }
        if t0.elapsed() > cfg.stage_timeout {
            let _ = child.kill();
            let _ = child.wait();
            return Ok(Ended::Hang);
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// The 24 good outputs of `root` against the reference: how many are missing or differ.
fn lost(reference: &BTreeMap<String, Vec<u8>>, root: &Path) -> usize {
    reference
        .iter()
        .filter(|(name, bytes)| {
            std::fs::read(root.join("out").join(name)).ok().as_ref() != Some(*bytes)
        })
        .count()
}

/// The reference run: the 24 fixtures through `persist run`; its outputs by name.
fn reference(cfg: &FuzzConfig, root: &Path) -> Result<BTreeMap<String, Vec<u8>>> {
    let input = root.join("in");
    std::fs::create_dir_all(&input).map_err(|e| Error::io(&input, e))?;
    let mut names = Vec::new();
    for e in std::fs::read_dir(&cfg.fixtures).map_err(|e| Error::io(&cfg.fixtures, e))? {
        let p = e.map_err(|e| Error::io(&cfg.fixtures, e))?.path();
        let name = p
            .file_name()
            .unwrap_or_default()
            .to_string_lossy()
            .into_owned();
        if name.starts_with("l1_det") && name.ends_with(".h5") {
            std::fs::copy(&p, input.join(&name)).map_err(|e| Error::io(&p, e))?;
            names.push(name);
        }
    }
    if names.len() != 24 {
        return Err(fuzz_error(format!(
            "{}: expected the 24 fixtures, found {}",
            cfg.fixtures.display(),
            names.len()
        )));
    }
    if run_stage(cfg, root)? != Ended::Clean {
        return Err(fuzz_error("the reference run on the good fixtures failed"));
    }
    let mut out = BTreeMap::new();
    for n in names {
        let p = root.join("out").join(&n);
        out.insert(n, std::fs::read(&p).map_err(|e| Error::io(&p, e))?);
    }
    Ok(out)
}

/// Run the fuzzer; `progress` is told of each stage run (done, total).
pub fn run(cfg: &FuzzConfig, progress: &dyn Fn(usize, usize)) -> Result<FuzzReport> {
    let t0 = Instant::now();
    if cfg.work.exists() {
        std::fs::remove_dir_all(&cfg.work).map_err(|e| Error::io(&cfg.work, e))?;
    }
    let templates = cfg.work.join("templates");
    std::fs::create_dir_all(&templates).map_err(|e| Error::io(&templates, e))?;
    let ref_root = cfg.work.join("reference");
    let reference = reference(cfg, &ref_root)?;
    let (_, newest_ckpt) =
        crate::checkpoint::list(&ref_root.join("ckpt"), crate::units::DetectorId(1))?
            .pop()
            .ok_or_else(|| fuzz_error("the reference run wrote no checkpoint"))?;
    let fits_template = crate::fits::export::export_file(
        &cfg.fixtures.join("l1_det2_exp0005.h5"),
        &templates,
        &Default::default(),
    )?;
    let read = |p: &Path| std::fs::read(p).map_err(|e| Error::io(p, e));
    let tmpl: [Vec<u8>; 4] = [
        read(&cfg.fixtures.join("l1_det1_exp0005.h5"))?,
        read(&fits_template)?,
        read(&newest_ckpt)?,
        crate::model::ModelParams::default()
            .to_json_pretty()
            .into_bytes(),
    ];
    let ext = ["h5", "fits", "h5", "json"];
    let g = Guard {
        timeout: cfg.read_timeout,
        ..Guard::new(cfg.exe.clone())
    };
    let fits = crate::fits::FitsConfig::default();
    let mut counts: Vec<ReaderCounts> = READERS
        .iter()
        .map(|r| ReaderCounts {
            reader: (*r).to_owned(),
            ..Default::default()
        })
        .collect();
    let direct = cfg.work.join("direct");
    std::fs::create_dir_all(&direct).map_err(|e| Error::io(&direct, e))?;
    // Input mutants wait here for their stage run; checkpoint mutants for theirs.
    let mut inputs: Vec<(usize, Vec<u8>)> = Vec::new();
    let mut ckpts: Vec<Vec<u8>> = Vec::new();
    for k in 0..cfg.mutants {
        let r = k % READERS.len();
        let mut rng = crate::sim::rng::stream(cfg.seed, &[k as u64]);
        let bytes = mutate(&tmpl[r], &mut rng);
        let path = direct.join(format!("m{k:06}.{}", ext[r]));
        write(&path, &bytes)?;
        let outcome = match r {
            0 | 1 => worse(
                classify(guard::read_input_sequence(Some(&g), &path, &fits)),
                || classify(guard::read_input(Some(&g), &path, &fits)),
            ),
            2 => classify(guard::load_checkpoint(Some(&g), &path)),
            _ => match std::panic::catch_unwind(|| crate::model_file::check(&path)) {
                Ok(Ok(_)) => Outcome::Ok,
                Ok(Err(_)) => Outcome::Refused,
                Err(_) => Outcome::Panic,
            },
        };
        let c = &mut counts[r];
        c.mutants += 1;
        match outcome {
            Outcome::Ok => c.read_ok += 1,
            Outcome::Refused => c.refused += 1,
            Outcome::Contained => c.contained += 1,
            Outcome::Panic => c.panics += 1,
        }
        let _ = std::fs::remove_file(&path);
        match r {
            0 | 1 => inputs.push((k, bytes)),
            2 if ckpts.len() < cfg.stage_checkpoints => ckpts.push(bytes),
            _ => {}
        }
    }
    let mut report = FuzzReport {
        seed: cfg.seed,
        ..Default::default()
    };
    let batches: Vec<&[(usize, Vec<u8>)]> = inputs.chunks(cfg.batch.max(1)).collect();
    let total = batches.len() + ckpts.len();
    for (b, batch) in batches.iter().enumerate() {
        let root = cfg.work.join("stage");
        let _ = std::fs::remove_dir_all(&root);
        copy_dir(&ref_root.join("in"), &root.join("in"))?;
        for (k, bytes) in *batch {
            write(
                &root
                    .join("in")
                    .join(format!("zz_m{k:06}.{}", ext[k % READERS.len()])),
                bytes,
            )?;
            counts[k % READERS.len()].in_stage += 1;
        }
        let keep = cfg.work.join("failures").join(format!("batch{b}"));
        account(cfg, &mut report, &reference, &root, &keep)?;
        progress(b + 1, total);
    }
    for (j, bytes) in ckpts.iter().enumerate() {
        let root = cfg.work.join("restart");
        let _ = std::fs::remove_dir_all(&root);
        copy_dir(&ref_root, &root)?;
        let rel = newest_ckpt.strip_prefix(&ref_root).unwrap_or(&newest_ckpt);
        write(&root.join(rel), bytes)?;
        counts[2].in_stage += 1;
        let keep = cfg.work.join("failures").join(format!("checkpoint{j}"));
        account(cfg, &mut report, &reference, &root, &keep)?;
        progress(batches.len() + j + 1, total);
    }
    report.readers = counts;
    report.elapsed_s = t0.elapsed().as_secs_f64();
    Ok(report)
}

/// One stage run over `root`, counted; a failed one keeps its directory as `keep`.
fn account(
    cfg: &FuzzConfig,
    report: &mut FuzzReport,
    reference: &BTreeMap<String, Vec<u8>>,
    root: &Path,
    keep: &Path,
) -> Result<()> {
    let ended = run_stage(cfg, root)?;
    let lost = lost(reference, root);
    report.stage_runs += 1;
    report.good_expected += reference.len();
    report.good_lost += lost;
    match ended {
        Ended::Clean => {}
        Ended::Death => report.stage_deaths += 1,
        Ended::Hang => report.hangs += 1,
    }
    if ended != Ended::Clean || lost > 0 {
        std::fs::create_dir_all(keep).map_err(|e| Error::io(keep, e))?;
        copy_dir(root, keep)?;
    }
    Ok(())
}

/// The figures as markdown (what docs/operations.md shows).
pub fn markdown(r: &FuzzReport, command: &str) -> String {
    let mut s = format!(
        "`{command}` (seed {}, {:.0} s):\n\n| reader | mutants | read whole | refused with a reason | reader crashes contained | parser panics | through the stage |\n|---|---|---|---|---|---|---|\n",
        r.seed, r.elapsed_s
    );
    for c in &r.readers {
        s.push_str(&format!(
            "| {} | {} | {} | {} | {} | {} | {} |\n",
            c.reader, c.mutants, c.read_ok, c.refused, c.contained, c.panics, c.in_stage
        ));
    }
    s.push_str(&format!(
        "\nStage runs: {}. Stage deaths: {}. Hangs: {}. Good exposures lost: {} of {}.\n",
        r.stage_runs, r.stage_deaths, r.hangs, r.good_lost, r.good_expected
    ));
    s
}

/// Replace the text between `<!-- fuzz:begin -->` and `<!-- fuzz:end -->` in `doc`.
pub fn insert_markdown(doc: &Path, text: &str) -> Result<()> {
    let (begin, end) = ("<!-- fuzz:begin -->", "<!-- fuzz:end -->");
    let old = std::fs::read_to_string(doc).map_err(|e| Error::io(doc, e))?;
    let (Some(a), Some(b)) = (old.find(begin), old.find(end)) else {
        return Err(
            Error::invalid("fuzz markers", format!("{begin} ... {end} not found")).path(doc),
        );
    };
    let new = format!("{}{begin}\n{text}{}", &old[..a], &old[b..]);
    std::fs::write(doc, new).map_err(|e| Error::io(doc, e))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mutants_are_deterministic_by_seed_and_differ_from_the_template() {
        let t: Vec<u8> = (0..10_000u32).map(|i| (i % 251) as u8).collect();
        let a = mutate(&t, &mut crate::sim::rng::stream(7, &[3]));
        let b = mutate(&t, &mut crate::sim::rng::stream(7, &[3]));
        let c = mutate(&t, &mut crate::sim::rng::stream(7, &[4]));
        assert_eq!(a, b);
        assert_ne!(a, c);
        let changed = (0..50)
            .filter(|&k| mutate(&t, &mut crate::sim::rng::stream(1, &[k])) != t)
            .count();
        // A zeroed block of zeros or a block copied onto itself can leave it unchanged.
        assert!(changed >= 45, "{changed} of 50 changed");
    }
}
