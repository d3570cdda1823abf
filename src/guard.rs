//! Reader isolation: every file the stage reads through a C library (HDF5, CFITSIO) is
//! first read in a short-lived child process with time and memory limits, so that a
//! crash, abort, hang or runaway allocation of the library on a malformed file costs
//! that file (quarantined with a reason such as "reader crashed: SIGSEGV" or "reader
//! exceeded 30 s"), never the stage.
//!
//! # Invariants
//!
//! - The child is the `persist` executable itself, run as `persist guarded-read WHAT
//!   PATH`: it reads and validates the file with the same library functions the stage
//!   uses in-process ([`crate::product::read`], [`crate::fits`], [`crate::checkpoint`])
//!   and answers on its standard output with one frame (the private `Answer` as JSON,
//!   then the arrays' raw bytes). The stage uses the answer, never its own reading of
//!   the file: an input's arrays are handed back, bit for bit (floats travel as their
//!   bits), so a library fault that corrupts memory without crashing stays in the child.
//! - A checkpoint is only checked in the child (fully loaded, every array), then loaded
//!   in-process: the stage wrote it, and its state arrays are large.
//! - Limits, set by the child on itself before it opens the file (passed as arguments):
//!   `RLIMIT_AS` (address space), `RLIMIT_CPU` (then SIGXCPU, and SIGKILL one second
//!   later), `RLIMIT_CORE` 0; it dies with its parent (`PR_SET_PDEATHSIG`, then a check
//!   that the parent it was given is still its parent); the parent kills it after the
//!   wall-time limit. Setting them in the child rather than between `fork` and `exec`
//!   lets the standard library start it with `posix_spawn`: no copy of the page tables
//!   of a stage holding a 2040 x 2040 state, and no copy-on-write faults after.
//! - An error the library reports is the same [`Error`] (kind, field, message) as
//!   in-process. A child killed by a signal is retried once (a crash that does not
//!   repeat is not the file's); a second crash, a timeout or an unreadable answer is an
//!   [`ErrorKind::Crash`] error naming the file: the stage refuses the file for its
//!   content. Failing to start the child is an [`ErrorKind::Io`] error (not the file's
//!   fault: it is not refused).
//! - `None` as the guard reads in-process (the library's default, for tests and
//!   bindings that call the library without the executable).
//!
//! # Finding the executable
//!
//! [`Guard::locate`]: `$PERSIST_EXE` if set; else the running executable if it is
//! `persist` (`persist run`); else a `persist` beside the running executable or in its
//! parent directory (a test binary in `target/*/deps`); else none, and the caller reads
//! in-process (documented in docs/operations.md).

use crate::checkpoint;
use crate::error::{Error, ErrorKind, Result};
use crate::fits::{Conversion, FitsConfig, FitsInput, Keywords, Sequence};
use crate::product::{self, Exposure, ExposureMeta};
use crate::units::{DetectorId, UtcSeconds};
use ndarray::{Array1, Array2, Array3};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Duration;

/// The hidden subcommand the child runs.
pub const SUBCOMMAND: &str = "guarded-read";

/// Default wall-time and CPU-time limit of one read, seconds.
pub const DEFAULT_TIMEOUT_S: f64 = 30.0;
/// Default address-space limit of the child, MiB.
pub const DEFAULT_MEMORY_MIB: u64 = 4096;

const MAGIC: &[u8; 8] = b"PERSISTG";

/// How reads are isolated: the executable run as the child, and its limits.
#[derive(Debug, Clone, PartialEq)]
pub struct Guard {
    pub exe: PathBuf,
    /// Wall time (and, rounded up, CPU time) one read may take.
    pub timeout: Duration,
    /// Address space of the child, bytes.
    pub memory_bytes: u64,
}

impl Guard {
    /// The guard with the default limits, run through `exe`.
    pub fn new(exe: PathBuf) -> Self {
        Guard {
            exe,
            timeout: Duration::from_secs_f64(DEFAULT_TIMEOUT_S),
            memory_bytes: DEFAULT_MEMORY_MIB << 20,
        }
    }

    /// The guard with default limits through the executable [`Guard::locate`] finds.
    pub fn located() -> Option<Self> {
        Self::locate().map(Self::new)
    }

    /// The `persist` executable to run readers with (module docs: finding it).
    pub fn locate() -> Option<PathBuf> {
        if let Some(p) = std::env::var_os("PERSIST_EXE").filter(|p| !p.is_empty()) {
            return Some(PathBuf::from(p));
        }
        let me = std::env::current_exe().ok()?;
        if me.file_stem().is_some_and(|s| s == "persist") {
            return Some(me);
        }
        let dir = me.parent()?;
        [dir.join("persist"), dir.parent()?.join("persist")]
            .into_iter()
            .find(|p| p.is_file())
    }

    fn timeout_text(&self) -> String {
        format!("{} s", self.timeout.as_secs_f64())
    }
}

/// What the child is asked to read.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum What {
    /// An input's root attributes (and whether its index is a start time).
    Meta,
    /// A whole input (attributes and arrays).
    Exposure,
    /// A checkpoint, checked whole.
    Checkpoint,
}

impl What {
    pub fn name(self) -> &'static str {
        match self {
            What::Meta => "meta",
            What::Exposure => "exposure",
            What::Checkpoint => "checkpoint",
        }
    }

    pub fn parse(s: &str) -> Option<What> {
        [What::Meta, What::Exposure, What::Checkpoint]
            .into_iter()
            .find(|w| w.name() == s)
    }
}

/// An input's metadata, and whether its exposure index is a start time; in-process
/// when `guard` is `None`.
pub fn read_input_sequence(
    guard: Option<&Guard>,
    path: &Path,
    fits: &FitsConfig,
) -> Result<(ExposureMeta, bool)> {
    let Some(g) = guard else {
        return read_sequence_here(path, fits);
    };
    match ask(g, What::Meta, path, fits)? {
        (
            Answer::Meta {
                meta,
                by_start_time,
            },
            _,
        ) => Ok((meta.into(), by_start_time)),
        (a, _) => Err(unexpected(path, &a)),
    }
}

/// A whole input (and, for FITS, what its output records of the reading); in-process
/// when `guard` is `None`.
pub fn read_input(
    guard: Option<&Guard>,
    path: &Path,
    fits: &FitsConfig,
) -> Result<(Exposure, Option<FitsInput>)> {
    let Some(g) = guard else {
        return read_input_here(path, fits);
    };
    match ask(g, What::Exposure, path, fits)? {
        (Answer::Exposure(h), Some(e)) => Ok((e, h.fits.map(Into::into))),
        (a, _) => Err(unexpected(path, &a)),
    }
}

/// A whole input read ahead, on its own thread, while the stage steps the one before.
type Reading = std::thread::JoinHandle<Result<(Exposure, Option<FitsInput>)>>;

/// One input read ahead through the guard (what [`read_input_ahead`] keeps between
/// calls): its path, its (size, modification time) when the read started, the read.
#[derive(Default)]
pub struct Ahead(Option<(PathBuf, Option<FileKey>, Reading)>);

/// (size, modification time) of a file.
type FileKey = (u64, Option<std::time::SystemTime>);

fn file_key(path: &Path) -> Option<FileKey> {
    let m = std::fs::metadata(path).ok()?;
    Some((m.len(), m.modified().ok()))
}

/// [`read_input`] of `path`, taking the read started ahead for it if the file has not
/// changed since (same size and time); then, guarded, start reading `next` ahead, so
/// that its child runs while the stage steps this one. Unguarded: no read ahead.
pub fn read_input_ahead(
    guard: Option<&Guard>,
    ahead: &mut Ahead,
    path: &Path,
    next: Option<&Path>,
    fits: &FitsConfig,
) -> Result<(Exposure, Option<FitsInput>)> {
    let Some(g) = guard else {
        return read_input_here(path, fits);
    };
    let result = match ahead.0.take() {
        Some((p, key, reading)) if p == path => {
            let done = reading
                .join()
                .unwrap_or_else(|_| Err(crash("the thread reading ahead panicked").path(path)));
            if key.is_some() && key == file_key(path) {
                done
            } else {
                read_input(Some(g), path, fits)
            }
        }
        _ => read_input(Some(g), path, fits),
    };
    if let Some(next) = next.filter(|n| *n != path) {
        let (g, next, fits) = (g.clone(), next.to_path_buf(), fits.clone());
        let key = file_key(&next);
        let p = next.clone();
        let reading = std::thread::spawn(move || read_input(Some(&g), &p, &fits));
        ahead.0 = Some((next, key, reading));
    }
    result
}

/// Load a checkpoint, checked first in the child when guarded.
pub fn load_checkpoint(
    guard: Option<&Guard>,
    path: &Path,
) -> Result<(checkpoint::CheckpointMeta, crate::model::State)> {
    check_checkpoint(guard, path)?;
    checkpoint::load(path)
}

/// A checkpoint's metadata ([`checkpoint::load_meta`]), the file checked first in the
/// child when guarded (as [`load_checkpoint`] checks it).
pub fn load_checkpoint_meta(
    guard: Option<&Guard>,
    path: &Path,
) -> Result<(checkpoint::CheckpointMeta, f64)> {
    check_checkpoint(guard, path)?;
    checkpoint::load_meta(path)
}

/// With a guard, the whole checkpoint loaded in the child ([`What::Checkpoint`]).
fn check_checkpoint(guard: Option<&Guard>, path: &Path) -> Result<()> {
    let Some(g) = guard else {
        return Ok(());
    };
    match ask(g, What::Checkpoint, path, &FitsConfig::default())? {
        (Answer::Checked, _) => Ok(()),
        (a, _) => Err(unexpected(path, &a)),
    }
}

fn read_sequence_here(path: &Path, fits: &FitsConfig) -> Result<(ExposureMeta, bool)> {
    product::format::read_input_sequence(path, fits)
}

fn read_input_here(path: &Path, fits: &FitsConfig) -> Result<(Exposure, Option<FitsInput>)> {
    product::format::read_input(path, fits).map(|r| (r.exposure, r.fits))
}

fn unexpected(path: &Path, a: &Answer) -> Error {
    crash(format!("reader answered out of turn: {}", a.name())).path(path)
}

fn crash(message: impl Into<String>) -> Error {
    Error::new(ErrorKind::Crash, message)
}

// ---------------------------------------------------------------------------------
// The frame: MAGIC, u64 LE length of the JSON answer, the answer, the arrays' bytes.

/// The child's answer (the JSON part of the frame).
#[derive(Debug, Serialize, Deserialize)]
#[serde(tag = "answer", rename_all = "snake_case")]
enum Answer {
    Failed {
        kind: ErrorKind,
        message: String,
        field: Option<String>,
    },
    Meta {
        meta: MetaWire,
        by_start_time: bool,
    },
    /// Followed by the image (f32), flags (u32), ramp (f32) and ramp times (f64).
    Exposure(ExposureHead),
    Checked,
}

impl Answer {
    fn name(&self) -> &'static str {
        match self {
            Answer::Failed { .. } => "failed",
            Answer::Meta { .. } => "meta",
            Answer::Exposure(_) => "exposure",
            Answer::Checked => "checked",
        }
    }
}

#[derive(Debug, Serialize, Deserialize)]
struct ExposureHead {
    meta: MetaWire,
    ny: usize,
    nx: usize,
    /// Samples of the ramp (absent: no ramp).
    ramp_samples: Option<usize>,
    ramp_times: Option<usize>,
    fits: Option<FitsWire>,
}

/// [`ExposureMeta`] with every float as its bits (JSON would not carry NaN, and bits
/// travel exactly).
#[derive(Debug, Clone, Serialize, Deserialize)]
struct MetaWire {
    detector: u8,
    exposure_index: u64,
    t_start_utc: String,
    t_start_bits: u64,
    t_exposure_bits: u64,
    focal_plane_temp_bits: Option<u64>,
    t_illuminated_bits: Option<u64>,
}

impl From<&ExposureMeta> for MetaWire {
    fn from(m: &ExposureMeta) -> Self {
        MetaWire {
            detector: m.detector.0,
            exposure_index: m.exposure_index,
            t_start_utc: m.t_start_utc.clone(),
            t_start_bits: m.t_start.0.to_bits(),
            t_exposure_bits: m.t_exposure_s.to_bits(),
            focal_plane_temp_bits: m.focal_plane_temp_k.map(f64::to_bits),
            t_illuminated_bits: m.t_illuminated_s.map(f64::to_bits),
        }
    }
}

impl From<MetaWire> for ExposureMeta {
    fn from(m: MetaWire) -> Self {
        ExposureMeta {
            detector: DetectorId(m.detector),
            exposure_index: m.exposure_index,
            t_start_utc: m.t_start_utc,
            t_start: UtcSeconds(f64::from_bits(m.t_start_bits)),
            t_exposure_s: f64::from_bits(m.t_exposure_bits),
            focal_plane_temp_k: m.focal_plane_temp_bits.map(f64::from_bits),
            t_illuminated_s: m.t_illuminated_bits.map(f64::from_bits),
        }
    }
}

#[derive(Debug, Serialize, Deserialize)]
struct FitsWire {
    factor_bits: u64,
    image_unit: String,
    source: String,
    input_persist_px: u64,
    /// The keyword the index came from, and whether it is a start time.
    sequence: (String, bool),
}

impl From<&FitsInput> for FitsWire {
    fn from(f: &FitsInput) -> Self {
        FitsWire {
            factor_bits: f.conversion.factor.to_bits(),
            image_unit: f.conversion.image_unit.clone(),
            source: f.conversion.source.clone(),
            input_persist_px: f.input_persist_px,
            sequence: match &f.sequence {
                Sequence::Keyword(k) => (k.clone(), false),
                Sequence::StartTime(k) => (k.clone(), true),
            },
        }
    }
}

impl From<FitsWire> for FitsInput {
    fn from(f: FitsWire) -> Self {
        FitsInput {
            conversion: Conversion {
                factor: f64::from_bits(f.factor_bits),
                image_unit: f.image_unit,
                source: f.source,
            },
            input_persist_px: f.input_persist_px,
            sequence: match f.sequence {
                (k, false) => Sequence::Keyword(k),
                (k, true) => Sequence::StartTime(k),
            },
        }
    }
}

/// The FITS reading options, as the child's argument.
#[derive(Debug, Serialize, Deserialize)]
struct FitsWireConfig {
    keywords: Keywords,
    gains: BTreeMap<u8, u64>,
}

fn fits_arg(fits: &FitsConfig) -> String {
    let w = FitsWireConfig {
        keywords: fits.keywords.clone(),
        gains: fits.gains.iter().map(|(&d, g)| (d, g.to_bits())).collect(),
    };
    serde_json::to_string(&w).unwrap_or_default()
}

fn fits_of_arg(s: &str) -> std::result::Result<FitsConfig, String> {
    if s.is_empty() {
        return Ok(FitsConfig::default());
    }
    let w: FitsWireConfig = serde_json::from_str(s).map_err(|e| e.to_string())?;
    Ok(FitsConfig {
        keywords: w.keywords,
        gains: w
            .gains
            .into_iter()
            .map(|(d, g)| (d, f64::from_bits(g)))
            .collect(),
    })
}

/// Plain numbers whose every bit pattern is a value: their bytes can be viewed and
/// filled directly.
trait Plain: Copy + Default {}
impl Plain for f32 {}
impl Plain for u32 {}
impl Plain for f64 {}

fn bytes_of<T: Plain>(v: &[T]) -> &[u8] {
    // SAFETY: T is a plain number (no padding, no invalid bit patterns); the slice is
    // viewed for its own length in bytes.
    unsafe { std::slice::from_raw_parts(v.as_ptr().cast::<u8>(), std::mem::size_of_val(v)) }
}

fn bytes_of_mut<T: Plain>(v: &mut [T]) -> &mut [u8] {
    // SAFETY: as `bytes_of`; any bytes written form valid values of T.
    unsafe { std::slice::from_raw_parts_mut(v.as_mut_ptr().cast::<u8>(), std::mem::size_of_val(v)) }
}

fn write_array<T: Plain, W: Write>(
    w: &mut W,
    a: impl Iterator<Item = T>,
    s: Option<&[T]>,
) -> std::io::Result<()> {
    match s {
        Some(s) => w.write_all(bytes_of(s)),
        None => {
            let v: Vec<T> = a.collect();
            w.write_all(bytes_of(&v))
        }
    }
}

fn read_vec<T: Plain, R: Read>(r: &mut R, n: usize) -> std::io::Result<Vec<T>> {
    let mut v = vec![T::default(); n];
    r.read_exact(bytes_of_mut(&mut v))?;
    Ok(v)
}

/// Write one frame: the answer, then (for an exposure) its arrays.
fn write_frame<W: Write>(w: &mut W, answer: &Answer, e: Option<&Exposure>) -> std::io::Result<()> {
    let json = serde_json::to_vec(answer).map_err(std::io::Error::other)?;
    w.write_all(MAGIC)?;
    w.write_all(&(json.len() as u64).to_le_bytes())?;
    w.write_all(&json)?;
    if let Some(e) = e {
        write_array(w, e.image.iter().copied(), e.image.as_slice())?;
        write_array(w, e.flags.iter().copied(), e.flags.as_slice())?;
        if let Some(r) = &e.ramp {
            write_array(w, r.iter().copied(), r.as_slice())?;
        }
        if let Some(t) = &e.ramp_times_s {
            write_array(w, t.iter().copied(), t.as_slice())?;
        }
    }
    w.flush()
}

/// The largest answer header accepted, bytes.
const MAX_HEAD: u64 = 1 << 24;
/// The largest axis accepted in an answer (the products' own limit is 8192).
const MAX_AXIS: usize = 1 << 16;
/// The most array values accepted in one answer (16 GiB of 4-byte values).
const MAX_VALUES: usize = 1 << 32;

/// Read one frame.
fn read_frame<R: Read>(r: &mut R) -> std::result::Result<(Answer, Option<Exposure>), String> {
    let mut magic = [0u8; 8];
    r.read_exact(&mut magic)
        .map_err(|e| format!("no answer ({e})"))?;
    if &magic != MAGIC {
        return Err("answer without the frame's mark".into());
    }
    let mut len = [0u8; 8];
    r.read_exact(&mut len).map_err(|e| e.to_string())?;
    let len = u64::from_le_bytes(len);
    if len > MAX_HEAD {
        return Err(format!("answer of {len} bytes"));
    }
    let mut json = vec![0u8; len as usize];
    r.read_exact(&mut json).map_err(|e| e.to_string())?;
    let answer: Answer = serde_json::from_slice(&json).map_err(|e| e.to_string())?;
    let Answer::Exposure(h) = &answer else {
        return Ok((answer, None));
    };
    let n =
        h.ny.checked_mul(h.nx)
            .filter(|_| h.ny <= MAX_AXIS && h.nx <= MAX_AXIS);
    let samples = h.ramp_samples.unwrap_or(0);
    let total = n.and_then(|n| n.checked_mul(samples.checked_add(2)?));
    let (Some(n), Some(total)) = (n, total) else {
        return Err(format!("arrays of {} x {} x {samples}", h.ny, h.nx));
    };
    if total > MAX_VALUES || h.ramp_times.unwrap_or(0) > MAX_AXIS {
        return Err(format!("arrays of {total} values"));
    }
    let mut arrays = || -> std::io::Result<Exposure> {
        let shape = |v, what| {
            Array2::from_shape_vec((h.ny, h.nx), v)
                .map_err(|e| std::io::Error::other(format!("{what}: {e}")))
        };
        let image = shape(read_vec::<f32, _>(r, n)?, "image")?;
        let flags = Array2::from_shape_vec((h.ny, h.nx), read_vec::<u32, _>(r, n)?)
            .map_err(std::io::Error::other)?;
        let ramp = match h.ramp_samples {
            Some(s) => Some(
                Array3::from_shape_vec((s, h.ny, h.nx), read_vec::<f32, _>(r, s * n)?)
                    .map_err(std::io::Error::other)?,
            ),
            None => None,
        };
        let ramp_times_s = match h.ramp_times {
            Some(k) => Some(Array1::from_vec(read_vec::<f64, _>(r, k)?)),
            None => None,
        };
        Ok(Exposure {
            meta: h.meta.clone().into(),
            image,
            flags,
            ramp,
            ramp_times_s,
        })
    };
    let e = arrays().map_err(|e| format!("arrays: {e}"))?;
    Ok((answer, Some(e)))
}

// ---------------------------------------------------------------------------------
// The parent's side.

/// The name of a signal that kills a reader.
fn signal_name(sig: i32) -> String {
    let name = match sig {
        libc::SIGSEGV => "SIGSEGV",
        libc::SIGBUS => "SIGBUS",
        libc::SIGABRT => "SIGABRT",
        libc::SIGILL => "SIGILL",
        libc::SIGFPE => "SIGFPE",
        libc::SIGKILL => "SIGKILL",
        libc::SIGXCPU => "SIGXCPU",
        libc::SIGTRAP => "SIGTRAP",
        libc::SIGSYS => "SIGSYS",
        _ => return format!("signal {sig}"),
    };
    name.to_owned()
}

/// Ask the child, retrying once after a crash (module docs).
fn ask(
    g: &Guard,
    what: What,
    path: &Path,
    fits: &FitsConfig,
) -> Result<(Answer, Option<Exposure>)> {
    let first = ask_once(g, what, path, fits);
    let result = match first {
        Err(Fault::Signal(_)) => ask_once(g, what, path, fits),
        other => other,
    };
    match result {
        Ok((
            Answer::Failed {
                kind,
                message,
                field,
            },
            _,
        )) => {
            let mut e = Error::new(kind, message).path(path);
            if let Some(f) = field {
                e = e.field(f);
            }
            Err(e)
        }
        Ok(a) => Ok(a),
        Err(Fault::Start(e)) => Err(e.path(path)),
        Err(f) => Err(crash(f.describe(g)).path(path)),
    }
}

/// Why a read gave no answer.
#[derive(Debug)]
enum Fault {
    /// The child could not be started (not the file's fault).
    Start(Error),
    Signal(i32),
    Timeout,
    Exit(Option<i32>, String),
}

impl Fault {
    fn describe(&self, g: &Guard) -> String {
        match self {
            Fault::Start(e) => e.message.clone(),
            Fault::Signal(libc::SIGXCPU) => {
                format!("reader exceeded {} of CPU time", g.timeout_text())
            }
            Fault::Signal(s) => format!("reader crashed: {}", signal_name(*s)),
            Fault::Timeout => format!("reader exceeded {}", g.timeout_text()),
            Fault::Exit(code, why) => match code {
                Some(c) => format!("reader failed (exit status {c}): {why}"),
                None => format!("reader failed: {why}"),
            },
        }
    }
}

fn ask_once(
    g: &Guard,
    what: What,
    path: &Path,
    fits: &FitsConfig,
) -> std::result::Result<(Answer, Option<Exposure>), Fault> {
    use std::os::unix::process::ExitStatusExt;
    let cpu_s = g.timeout.as_secs_f64().ceil().max(1.0) as u64;
    let mut cmd = Command::new(&g.exe);
    cmd.arg(SUBCOMMAND)
        .arg(what.name())
        .arg(path)
        .arg("--fits")
        .arg(fits_arg(fits))
        .arg("--memory-bytes")
        .arg(g.memory_bytes.to_string())
        .arg("--cpu-s")
        .arg(cpu_s.to_string())
        .arg("--parent")
        .arg(std::process::id().to_string())
        .env("RAYON_NUM_THREADS", "1")
        .env("MALLOC_ARENA_MAX", "2")
        .env_remove("PERSIST_LOG")
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::null());
    let mut child = cmd.spawn().map_err(|e| {
        Fault::Start(Error::new(
            ErrorKind::Io,
            format!("cannot start the reader {}: {e}", g.exe.display()),
        ))
    })?;
    let Some(mut out) = child.stdout.take() else {
        let _ = child.kill();
        let _ = child.wait();
        return Err(Fault::Exit(None, "no pipe".into()));
    };
    let (tx, rx) = std::sync::mpsc::channel();
    let reader = std::thread::spawn(move || {
        let r = read_frame(&mut out);
        // Drain what is left, so that the child never blocks on a full pipe.
        let _ = std::io::copy(&mut out, &mut std::io::sink());
        let _ = tx.send(r);
    });
    let answer = rx.recv_timeout(g.timeout);
    let timed_out = answer.is_err();
    if timed_out {
        let _ = child.kill();
    }
    let status = child.wait();
    let _ = reader.join();
    let status = status.map_err(|e| Fault::Exit(None, e.to_string()))?;
    if timed_out {
        return Err(Fault::Timeout);
    }
    if let Some(sig) = status.signal() {
        return Err(Fault::Signal(sig));
    }
    match answer {
        Ok(Ok(a)) if status.success() => Ok(a),
        Ok(Ok(_)) => Err(Fault::Exit(status.code(), "answered, then failed".into())),
        Ok(Err(why)) => Err(Fault::Exit(status.code(), why)),
        Err(_) => Err(Fault::Timeout),
    }
}

// ---------------------------------------------------------------------------------
// The child's side.

/// The limits a child sets on itself (module docs).
#[derive(Debug, Clone, Copy)]
pub struct Limits {
    pub memory_bytes: u64,
    pub cpu_s: u64,
    /// The stage's process id: the child exits if it is no longer its parent.
    pub parent: Option<u32>,
}

/// Set `l` on this process. Exits (status 4) if it cannot, or if its parent is gone.
fn limit_self(l: &Limits) {
    let set = |res, soft: u64, hard: u64| {
        let lim = libc::rlimit {
            rlim_cur: soft as libc::rlim_t,
            rlim_max: hard as libc::rlim_t,
        };
        // SAFETY: setrlimit on this process with a local struct.
        unsafe { libc::setrlimit(res, &lim) == 0 }
    };
    let ok = set(libc::RLIMIT_AS, l.memory_bytes, l.memory_bytes)
        && set(libc::RLIMIT_CPU, l.cpu_s, l.cpu_s + 1)
        && set(libc::RLIMIT_CORE, 0, 0)
        // SAFETY: prctl on this process.
        && unsafe { libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL) } == 0;
    // The parent may have died before the prctl.
    // SAFETY: getppid has no preconditions.
    let orphan = l
        .parent
        .is_some_and(|p| i64::from(unsafe { libc::getppid() }) != i64::from(p));
    if !ok || orphan {
        std::process::exit(4);
    }
}

/// `persist guarded-read WHAT PATH --fits JSON ...`: set the limits, read, answer one
/// frame on standard output. Returns the exit status (0 whenever a frame was written).
pub fn serve(what: &str, path: &Path, fits: &str, limits: &Limits) -> i32 {
    limit_self(limits);
    let answer = std::panic::catch_unwind(|| serve_answer(what, path, fits)).unwrap_or_else(|p| {
        let why = p
            .downcast_ref::<&str>()
            .map(|s| (*s).to_owned())
            .or_else(|| p.downcast_ref::<String>().cloned())
            .unwrap_or_default();
        (
            Answer::Failed {
                kind: ErrorKind::Crash,
                message: format!("reader panicked: {why}"),
                field: None,
            },
            None,
        )
    });
    let stdout = std::io::stdout();
    let mut w = std::io::BufWriter::with_capacity(1 << 20, stdout.lock());
    match write_frame(&mut w, &answer.0, answer.1.as_ref()) {
        Ok(()) => 0,
        Err(_) => 3,
    }
}

fn failed(e: Error) -> (Answer, Option<Exposure>) {
    (
        Answer::Failed {
            kind: e.kind,
            message: e.message,
            field: e.context.field,
        },
        None,
    )
}

fn serve_answer(what: &str, path: &Path, fits: &str) -> (Answer, Option<Exposure>) {
    let Some(what) = What::parse(what) else {
        return failed(Error::new(
            ErrorKind::Usage,
            format!("unknown read `{what}`"),
        ));
    };
    let fits = match fits_of_arg(fits) {
        Ok(f) => f,
        Err(e) => return failed(Error::new(ErrorKind::Usage, format!("--fits: {e}"))),
    };
    match what {
        What::Meta => match read_sequence_here(path, &fits) {
            Ok((m, s)) => (
                Answer::Meta {
                    meta: MetaWire::from(&m),
                    by_start_time: s,
                },
                None,
            ),
            Err(e) => failed(e),
        },
        What::Exposure => match read_input_here(path, &fits) {
            Ok((e, f)) => {
                let (ny, nx) = e.image.dim();
                let head = ExposureHead {
                    meta: MetaWire::from(&e.meta),
                    ny,
                    nx,
                    ramp_samples: e.ramp.as_ref().map(|r| r.dim().0),
                    ramp_times: e.ramp_times_s.as_ref().map(|t| t.len()),
                    fits: f.as_ref().map(FitsWire::from),
                };
                if e.flags.dim() != (ny, nx)
                    || e.ramp
                        .as_ref()
                        .is_some_and(|r| (r.dim().1, r.dim().2) != (ny, nx))
                {
                    return failed(Error::invalid("flags", "planes of different shapes"));
                }
                (Answer::Exposure(head), Some(e))
            }
            Err(e) => failed(e),
        },
        What::Checkpoint => match checkpoint::load(path) {
            Ok(_) => (Answer::Checked, None),
            Err(e) => failed(e),
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_exposure_travels_bit_for_bit() {
        let meta = ExposureMeta {
            detector: DetectorId(3),
            exposure_index: 7,
            t_start_utc: "2026-03-01T00:00:00Z".into(),
            t_start: UtcSeconds(1_772_323_200.125),
            t_exposure_s: 112.0,
            focal_plane_temp_k: Some(f64::NAN),
            t_illuminated_s: None,
        };
        let image = Array2::from_shape_fn((3, 4), |(y, x)| {
            if y == 1 && x == 2 {
                f32::NAN
            } else {
                (y * 4 + x) as f32 * 0.1
            }
        });
        let e = Exposure {
            meta: meta.clone(),
            image,
            flags: Array2::from_shape_fn((3, 4), |(y, x)| (y * 31 + x) as u32),
            ramp: None,
            ramp_times_s: Some(Array1::from_vec(vec![1.5, 2.5])),
        };
        let head = ExposureHead {
            meta: MetaWire::from(&meta),
            ny: 3,
            nx: 4,
            ramp_samples: None,
            ramp_times: Some(2),
            fits: None,
        };
        let mut buf = Vec::new();
        write_frame(&mut buf, &Answer::Exposure(head), Some(&e)).unwrap();
        let (a, back) = read_frame(&mut buf.as_slice()).unwrap();
        assert_eq!(a.name(), "exposure");
        let back = back.unwrap();
        assert_eq!(
            back.image.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
            e.image.iter().map(|v| v.to_bits()).collect::<Vec<_>>()
        );
        assert_eq!(back.flags, e.flags);
        assert_eq!(back.ramp_times_s, e.ramp_times_s);
        assert!(back.meta.focal_plane_temp_k.unwrap().is_nan());
        assert_eq!(back.meta.t_start, meta.t_start);
    }

    #[test]
    fn a_truncated_frame_is_an_error_not_a_panic() {
        let mut buf = Vec::new();
        write_frame(&mut buf, &Answer::Checked, None).unwrap();
        for n in 0..buf.len() {
            assert!(read_frame(&mut &buf[..n]).is_err(), "{n} bytes accepted");
        }
        assert!(read_frame(&mut buf.as_slice()).is_ok());
    }
}
