//! `persist bench`: what one exposure costs, against what moving its bytes costs.
//!
//! Four cases, each run in a child process of the `persist` executable (so that the
//! peak memory, `VmHWM` of `/proc/self/status`, and the rayon thread count are those of
//! the case alone), all in one run so that their ratios hold on a noisy, shared machine:
//!
//! - **(a) `step`**: [`Model::step`] on one `ny x nx` exposure with the default
//!   six-term model, the state already warm (several exposures absorbed). In memory only.
//! - **(b) `memory`**: the memory bound of (a): one pass that reads and writes exactly
//!   the bytes the step moves (reads amplitudes, release counters, pending bits, image,
//!   flags; writes amplitudes, counters, pending bits, current, persistence flags, flags),
//!   in the same parallel row layout, with trivial arithmetic.
//! - **(c) `stage`**: the whole stage per exposure, through [`crate::stage::run()`] itself
//!   (no copy of its code): read and validate an input product, step, publish the
//!   output (write, validate, fsync, rename), checkpoint (at the stage's default
//!   cadence, or `checkpoint_every`) and prune. The time per exposure is the interval
//!   between consecutive exposure reports of one detector's stream, which holds exactly
//!   one of each; the median over the stream is reported.
//! - **(d) `io`**: the I/O bound of (c): a raw HDF5 read of the input's `/image` and
//!   `/flags`, and a raw write of the datasets the stage writes, with the same layout
//!   (the output product's four planes, flag planes compressed as the stage does, and
//!   the checkpoint's state), each file `fsync`ed as the stage does, and the same files
//!   left on disk (every output, the two newest checkpoints); no validation, no model,
//!   no rename. The checkpoint goes through HDF5 and the page cache, every exposure;
//!   the stage writes its amplitudes with direct I/O, at its cadence.
//!
//! - **(g) `guarded`**: (c) with the reader guard on ([`crate::guard`], as `persist run`
//!   has it): every input's metadata and arrays read in a child process first.
//!   Interleaved with (c) in the same rounds; g/c is what isolating the reader costs.
//!
//! - **(e) `copy`**: a plain copy of the bytes (c) moves through files: read each input
//!   file, write the bytes of its output product (as the `stage` case published them,
//!   read beforehand, not timed) to a new file and `fsync` it. No HDF5, no checkpoint.
//!
//! - **(f) `verify`**: `persist verify` ([`crate::verify::run`] and its report) over
//!   the stage's outputs of a simulated sky (the simulator's default survey, seed 1,
//!   one detector; its truth removed, as in flight), timed whole. Run on a few
//!   exposures of the full frame and on one detector-day (571 exposures) of a smaller
//!   frame at the same density of stars per pixel, and on that day's first few
//!   exposures; a day of the full frame is projected from these ([`VerifyProjection`]:
//!   the rule).
//!
//! (c) runs at the stage's default checkpoint cadence
//! ([`crate::checkpoint::DEFAULT_CADENCE`]); its samples are means over whole cadence
//! periods, so each holds its share of one checkpoint. (c)/(e) is what the stage costs
//! beyond moving its input and output bytes.
//!
//! The table gives exposures per second (1 / median time per exposure), the ratios
//! a/b, c/d and c/e, and the peak memory of the `stage` child (one detector's stream) against
//! the bound `1.5 x (state + three images)`, an image being `ny x nx` float32.

use crate::checkpoint::{Retention, DEFAULT_CADENCE};
use crate::error::{Error, ErrorKind, Result};
use crate::flags::bits;
use crate::h5io;
use crate::model::{Input, Model, ModelParams, Output, State};
use crate::product::{self, Exposure, ExposureMeta};
use crate::stage::{self, RunConfig};
use crate::stats::median;
use crate::units::{DetectorId, UtcSeconds};
use ndarray::Array2;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

/// Exposure length and cadence of the synthetic streams (SPHEREx-like).
const T_EXPOSURE_S: f64 = 112.0;
const CADENCE_S: f64 = 150.0;
/// First exposure start: 2026-03-01T00:00:00Z.
const T0_UNIX_S: f64 = 1_772_323_200.0;

/// The measured cases.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Case {
    Step,
    Memory,
    Stage,
    Io,
    Copy,
    Verify,
    Guarded,
}

impl Case {
    pub fn name(self) -> &'static str {
        match self {
            Case::Step => "step",
            Case::Memory => "memory",
            Case::Stage => "stage",
            Case::Io => "io",
            Case::Copy => "copy",
            Case::Verify => "verify",
            Case::Guarded => "guarded",
        }
    }

    pub fn parse(s: &str) -> Option<Case> {
        [
            Case::Step,
            Case::Memory,
            Case::Stage,
            Case::Io,
            Case::Copy,
            Case::Verify,
            Case::Guarded,
        ]
        .into_iter()
        .find(|c| c.name() == s)
    }
}

/// One case in one configuration (what a child measures).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct CaseSpec {
    pub case: Case,
    pub size: usize,
    pub threads: usize,
    /// Timed repetitions (exposures) after the warm-up.
    pub reps: usize,
    /// For `stage`: checkpoint every this many exposures.
    pub checkpoint_every: u64,
    /// Scratch directory (inputs under `in_{size}`, written by the parent).
    pub scratch: PathBuf,
}

/// What a child reports.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct CaseResult {
    pub case: Case,
    pub size: usize,
    pub threads: usize,
    pub checkpoint_every: u64,
    /// Seconds per exposure, each timed repetition.
    pub samples_s: Vec<f64>,
    pub median_s: f64,
    /// `VmHWM` of the child, bytes.
    pub peak_rss_bytes: u64,
    /// For `verify`: what the run measured.
    #[serde(default)]
    pub verify: Option<VerifyCounts>,
    /// For `stage` and `guarded`: the whole run (the scan of the input included) over
    /// its exposures, seconds, one per run.
    #[serde(default)]
    pub whole_s: Vec<f64>,
}

/// What one timed `verify` run went through.
#[derive(Debug, Clone, Copy, Serialize, Deserialize)]
pub struct VerifyCounts {
    pub exposures: usize,
    /// Track samples measured (pixel-exposures followed after an event).
    pub samples: usize,
    pub events: u64,
    /// Wall time of the whole run (reading, tracking, stacking, report), s.
    pub total_s: f64,
}

/// The whole run (`persist bench`).
#[derive(Debug, Clone)]
pub struct BenchConfig {
    pub sizes: Vec<usize>,
    pub threads: Vec<usize>,
    /// Timed repetitions of the in-memory cases (a, b).
    pub reps: usize,
    /// Exposures per stream for the I/O cases (c, d).
    pub exposures: usize,
    /// Interleaved rounds of (a, b, c, d), samples pooled.
    pub rounds: usize,
    /// Extra `stage` rows with this checkpoint cadence (> 1), at every size and thread count.
    pub checkpoint_every: Vec<u64>,
    pub scratch: PathBuf,
    /// The `persist` executable that runs each case.
    pub exe: PathBuf,
    /// The `verify` case (f), at each thread count; `None`: not run.
    pub verify: Option<VerifyBenchConfig>,
    /// Only the `verify` case.
    pub verify_only: bool,
}

/// The sizes of the `verify` case (f).
#[derive(Debug, Clone, Copy, Serialize, Deserialize)]
pub struct VerifyBenchConfig {
    /// The full frame (square) and how many exposures of it are verified.
    pub size: usize,
    pub exposures: usize,
    /// The smaller frame whose whole day is verified, and the day's exposures.
    pub day_size: usize,
    pub day_exposures: usize,
}

impl VerifyBenchConfig {
    /// A detector-day: 86,400 s at the survey's cadence (112 s exposures, 39 s mean slew).
    pub const DAY_EXPOSURES: usize = 571;

    pub fn full() -> Self {
        VerifyBenchConfig {
            size: 2040,
            exposures: 6,
            day_size: 512,
            day_exposures: Self::DAY_EXPOSURES,
        }
    }

    pub fn quick() -> Self {
        VerifyBenchConfig {
            size: 64,
            exposures: 4,
            day_size: 32,
            day_exposures: 30,
        }
    }
}

impl BenchConfig {
    /// The full run for the README.
    pub fn full(exe: PathBuf, scratch: PathBuf) -> Self {
        BenchConfig {
            sizes: vec![256, 1024, 2040],
            threads: vec![1, 2],
            reps: 11,
            exposures: 10,
            rounds: 3,
            checkpoint_every: vec![4],
            scratch,
            exe,
            verify: Some(VerifyBenchConfig::full()),
            verify_only: false,
        }
    }

    /// Seconds, small sizes: keeps the code from rotting.
    pub fn quick(exe: PathBuf, scratch: PathBuf) -> Self {
        BenchConfig {
            sizes: vec![64, 128],
            threads: vec![1, 2],
            reps: 3,
            exposures: 4,
            rounds: 1,
            checkpoint_every: vec![2],
            scratch,
            exe,
            verify: Some(VerifyBenchConfig::quick()),
            verify_only: false,
        }
    }
}

/// Everything measured, and the table.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct BenchReport {
    pub results: Vec<CaseResult>,
    pub rows: Vec<Row>,
    pub markdown: String,
    pub machine: String,
    pub date_utc: String,
    /// The `verify` case's runs, one row each.
    #[serde(default)]
    pub verify_rows: Vec<VerifyRow>,
    /// A detector-day of the full frame, one per thread count.
    #[serde(default)]
    pub verify_projections: Vec<VerifyProjection>,
}

/// One timed `verify` run.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct VerifyRow {
    pub size: usize,
    pub exposures: usize,
    pub threads: usize,
    pub total_s: f64,
    pub s_per_exposure: f64,
    pub samples: usize,
    pub events: u64,
    /// Wall time per pixel-exposure, microseconds.
    pub us_per_pixel_exposure: f64,
    pub peak_bytes: u64,
}

/// One detector-day of the full frame, projected from the measured day of the smaller
/// frame. The rule: at the same density of stars per pixel (the simulator's `n12` is
/// per 2040 x 2040 array, so a smaller frame sees the same density), events, tracks and
/// control pixels, hence every cost of `verify`, scale with the pixel count; the day's
/// time at the smaller size is multiplied by the larger of the pixel ratio and the
/// measured ratio of the same first exposures at the two sizes (which holds what the
/// pixel count does not: caches, the files' fixed costs).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct VerifyProjection {
    pub size: usize,
    pub day_size: usize,
    pub day_exposures: usize,
    pub threads: usize,
    /// The measured day at `day_size`, s.
    pub day_s: f64,
    /// `(size / day_size)^2`.
    pub pixel_ratio: f64,
    /// Time of the first `exposures` at `size` over the same at `day_size`.
    pub measured_ratio: f64,
    pub exposures: usize,
    /// `day_s * max(pixel_ratio, measured_ratio)`, s.
    pub projected_day_s: f64,
    /// Full-frame exposures per second over the projected day.
    pub projected_s_per_exposure: f64,
}

/// One line of the table: one size, one thread count.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Row {
    pub size: usize,
    pub threads: usize,
    pub step_s: f64,
    pub memory_s: f64,
    pub stage_s: f64,
    pub io_s: f64,
    /// (e) a plain copy of the input and output bytes, seconds per exposure.
    pub copy_s: f64,
    /// `(checkpoint_every, seconds per exposure)` of the extra stage rows.
    pub stage_every_s: Vec<(u64, f64)>,
    pub a_over_b: f64,
    pub c_over_d: f64,
    /// The whole stage against a plain copy of its input and output bytes (target <= 2).
    pub c_over_e: f64,
    /// (g) the stage with the reader guard, seconds per exposure.
    #[serde(default)]
    pub guarded_s: f64,
    /// (g)/(c): the cost of isolating the reader (target <= 1.1).
    #[serde(default)]
    pub g_over_c: f64,
    /// (g)/(c) of the whole runs (the scan of the input, one metadata read per file,
    /// included).
    #[serde(default)]
    pub g_over_c_whole: f64,
    pub stage_peak_bytes: u64,
    /// `1.5 x (state + three images)`.
    pub memory_bound_bytes: u64,
}

fn bench_error(msg: impl Into<String>) -> Error {
    Error::new(ErrorKind::Io, msg)
}

/// `1.5 x (state + three float32 images)` for one detector of `size^2`, six terms.
pub fn memory_bound_bytes(size: usize, n_terms: usize) -> u64 {
    let px = (size * size) as u64;
    let state = px * (8 * n_terms as u64 + 2);
    let images = 3 * px * 4;
    (state + images) * 3 / 2
}

/// Peak resident set of this process (`VmHWM`), bytes; 0 where unknown.
pub fn peak_rss_bytes() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmHWM:"))
                .and_then(|l| l.split_whitespace().nth(1))
                .and_then(|kb| kb.parse::<u64>().ok())
        })
        .map_or(0, |kb| kb * 1024)
}

/// SplitMix64: a cheap deterministic per-pixel hash (no RNG state to thread through).
fn mix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// A synthetic exposure `k` of a `size^2` array: sky 0.5-10 e-/s, 1% bright pixels
/// (10^3-10^5 e-/s, moving from exposure to exposure, so flags, releases and maximum
/// amplitudes all happen), 0.01% NaN, 0.1% TRANSIENT, 0.01% NONFUNC.
pub fn synthetic_frame(size: usize, k: u64) -> (Array2<f32>, Array2<u32>) {
    let mut image = Array2::<f32>::zeros((size, size));
    let mut flags = Array2::<u32>::zeros((size, size));
    image
        .as_slice_mut()
        .expect("standard layout")
        .par_iter_mut()
        .zip(
            flags
                .as_slice_mut()
                .expect("standard layout")
                .par_iter_mut(),
        )
        .enumerate()
        .for_each(|(i, (v, f))| {
            let h = mix(i as u64 ^ k.wrapping_mul(0x5851_f42d_4c95_7f2d));
            let u = (h & 0xffff) as f32 / 65536.0;
            let sel = (h >> 16) % 10_000;
            *v = 0.5 + 9.5 * u;
            if sel < 100 {
                *v = 1e3 * 100f32.powf(u);
            } else if sel < 101 {
                *v = f32::NAN;
            } else if sel < 111 {
                *f = bits::TRANSIENT;
            } else if sel < 112 {
                *f = bits::NONFUNC;
            }
        });
    (image, flags)
}

fn input_dir(scratch: &Path, size: usize) -> PathBuf {
    scratch.join(format!("in_{size}"))
}

fn input_meta(k: u64) -> ExposureMeta {
    let t = UtcSeconds(T0_UNIX_S + k as f64 * CADENCE_S);
    ExposureMeta {
        detector: DetectorId(1),
        exposure_index: k,
        t_start_utc: t.to_iso(),
        t_start: t,
        t_exposure_s: T_EXPOSURE_S,
        focal_plane_temp_k: Some(80.0),
        t_illuminated_s: None,
    }
}

/// Write `count` input products of `size^2` for detector 1 (not timed).
pub fn prepare_inputs(scratch: &Path, size: usize, count: usize) -> Result<PathBuf> {
    let dir = input_dir(scratch, size);
    if dir.exists() {
        std::fs::remove_dir_all(&dir).map_err(|e| Error::io(&dir, e))?;
    }
    std::fs::create_dir_all(&dir).map_err(|e| Error::io(&dir, e))?;
    for k in 0..count as u64 {
        let (image, flags) = synthetic_frame(size, k);
        let e = Exposure {
            meta: input_meta(k),
            image,
            flags,
            ramp: None,
            ramp_times_s: None,
        };
        product::write_exposure(&dir.join(format!("l1_det1_exp{k:04}.h5")), &e)?;
    }
    Ok(dir)
}

fn model() -> Model {
    Model::new(ModelParams::default()).expect("the default model is valid")
}

/// Run one case in this process (the child side), with a rayon pool of `spec.threads`.
pub fn run_case(spec: &CaseSpec) -> Result<CaseResult> {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(spec.threads.max(1))
        .build()
        .map_err(|e| bench_error(format!("rayon pool: {e}")))?;
    let mut whole_s = Vec::new();
    let (samples, verify) = pool.install(|| match spec.case {
        Case::Step => case_step(spec).map(|s| (s, None)),
        Case::Memory => Ok((case_memory(spec), None)),
        Case::Stage | Case::Guarded => {
            let guard = match spec.case {
                Case::Guarded => Some(
                    crate::guard::Guard::located()
                        .ok_or_else(|| bench_error("the persist executable is not found"))?,
                ),
                _ => None,
            };
            let (s, whole) = case_stage(spec, guard)?;
            whole_s.push(whole);
            Ok((s, None))
        }
        Case::Io => case_io(spec).map(|s| (s, None)),
        Case::Copy => case_copy(spec).map(|s| (s, None)),
        Case::Verify => case_verify(spec).map(|c| (vec![c.total_s / c.exposures as f64], Some(c))),
    })?;
    Ok(CaseResult {
        case: spec.case,
        size: spec.size,
        threads: spec.threads,
        checkpoint_every: spec.checkpoint_every,
        median_s: median(&samples),
        samples_s: samples,
        peak_rss_bytes: peak_rss_bytes(),
        verify,
        whole_s,
    })
}

/// (a) The fused step on a warm state.
fn case_step(spec: &CaseSpec) -> Result<Vec<f64>> {
    let m = model();
    let n = spec.size;
    let mut state = m.new_state(n, n);
    let frames: Vec<_> = (0..2).map(|k| synthetic_frame(n, k)).collect();
    let mut flags = Array2::<u32>::zeros((n, n));
    let mut current = Array2::<f32>::zeros((n, n));
    let mut pflags = Array2::<u8>::zeros((n, n));
    let warm = 3;
    let mut samples = Vec::new();
    for k in 0..(warm + spec.reps) as u64 {
        let (image, f) = &frames[(k % 2) as usize];
        flags.assign(f);
        let input = Input {
            image_e_per_s: image.view(),
            exposure_index: k,
            t_start_unix_s: T0_UNIX_S + k as f64 * CADENCE_S,
            t_exposure_s: T_EXPOSURE_S,
            t_illuminated_s: T_EXPOSURE_S,
            history_incomplete: false,
            background_e_per_s: None,
        };
        let t = Instant::now();
        let s = m.step(
            &mut state,
            &input,
            &mut Output {
                flags: &mut flags,
                current_e_per_s: &mut current,
                pflags: &mut pflags,
            },
        )?;
        let dt = t.elapsed().as_secs_f64();
        std::hint::black_box(s);
        if k >= warm as u64 {
            samples.push(dt);
        }
    }
    Ok(samples)
}

/// (b) One pass moving the step's bytes, trivial arithmetic, same row layout.
fn case_memory(spec: &CaseSpec) -> Vec<f64> {
    const N: usize = 6;
    let n = spec.size;
    let px = n * n;
    let (image, flags0) = synthetic_frame(n, 0);
    let image = image.as_slice().expect("standard layout").to_vec();
    let mut flags = flags0.as_slice().expect("standard layout").to_vec();
    let mut amps = vec![1.0f64; px * N];
    let mut count = vec![0u8; px];
    let mut pending = vec![0u8; px];
    let mut current = vec![0f32; px];
    let mut pflags = vec![0u8; px];
    let decay = [0.5f64; N];
    let warm = 3;
    let mut samples = Vec::new();
    for k in 0..warm + spec.reps {
        let t = Instant::now();
        (
            amps.par_chunks_mut(n * N),
            count.par_chunks_mut(n),
            pending.par_chunks_mut(n),
            image.par_chunks(n),
            flags.par_chunks_mut(n),
            current.par_chunks_mut(n),
            pflags.par_chunks_mut(n),
        )
            .into_par_iter()
            .for_each(|(a, c, p, img, f, cur, pf)| {
                for (x, a) in a.chunks_exact_mut(N).enumerate() {
                    let m = f64::from(img[x]);
                    for (aj, dj) in a.iter_mut().zip(&decay) {
                        *aj = *aj * dj + m;
                    }
                    c[x] = c[x].wrapping_add(1);
                    p[x] ^= 1;
                    cur[x] = img[x];
                    pf[x] = c[x] ^ p[x];
                    f[x] ^= bits::PERSIST;
                }
            });
        let dt = t.elapsed().as_secs_f64();
        std::hint::black_box((&amps, &current, &pflags, &flags, &count, &pending));
        if k >= warm {
            samples.push(dt);
        }
    }
    samples
}

/// (c) The stage itself on a stream of `reps` products of one detector; (g) with
/// `guard`. Also returns the whole run's time over its exposures.
fn case_stage(spec: &CaseSpec, guard: Option<crate::guard::Guard>) -> Result<(Vec<f64>, f64)> {
    let input = input_dir(&spec.scratch, spec.size);
    let mut root = stage_root(
        &spec.scratch,
        spec.size,
        spec.threads,
        spec.checkpoint_every,
    );
    if guard.is_some() {
        root.as_mut_os_string().push("_guarded");
    }
    if root.exists() {
        std::fs::remove_dir_all(&root).map_err(|e| Error::io(&root, e))?;
    }
    let cfg = RunConfig {
        input,
        output: root.join("out"),
        checkpoints: root.join("ckpt"),
        model: model(),
        from_checkpoint: None,
        allow_model_change: false,
        checkpoint_every: spec.checkpoint_every.max(1),
        checkpoint_idle: std::time::Duration::ZERO,
        // Few files on disk; pruning still runs after every checkpoint.
        retention: Retention {
            keep_latest: 2,
            ..Retention::default()
        },
        processed_utc: "2026-03-02T00:00:00.000000Z".into(),
    };
    let stamps = std::sync::Mutex::new(Vec::new());
    let ops = stage::Ops {
        guard,
        ..Default::default()
    };
    let t0 = Instant::now();
    let report = stage::run_with(&cfg, &ops, &|_| {
        if let Ok(mut s) = stamps.lock() {
            s.push(Instant::now());
        }
    });
    let whole = t0.elapsed().as_secs_f64() / report.exposures.len().max(1) as f64;
    // The outputs stay for the `copy` case (the parent removes the scratch directory).
    let _ = std::fs::remove_dir_all(&cfg.checkpoints);
    if let Some(e) = report.errors.into_iter().next() {
        return Err(e);
    }
    let stamps = stamps
        .into_inner()
        .map_err(|_| bench_error("poisoned lock"))?;
    let diffs: Vec<f64> = stamps
        .windows(2)
        .map(|w| (w[1] - w[0]).as_secs_f64())
        .collect();
    let every = spec.checkpoint_every.max(1) as usize;
    if every == 1 {
        return Ok((diffs, whole));
    }
    // Average over whole checkpoint periods (each holds exactly one checkpoint).
    Ok((
        diffs
            .chunks_exact(every)
            .map(|c| c.iter().sum::<f64>() / every as f64)
            .collect(),
        whole,
    ))
}

/// (d) Raw HDF5: read the input planes, write the same output and checkpoint datasets.
fn case_io(spec: &CaseSpec) -> Result<Vec<f64>> {
    let input = input_dir(&spec.scratch, spec.size);
    let root = spec
        .scratch
        .join(format!("io_{}_{}", spec.size, spec.threads));
    if root.exists() {
        std::fs::remove_dir_all(&root).map_err(|e| Error::io(&root, e))?;
    }
    std::fs::create_dir_all(&root).map_err(|e| Error::io(&root, e))?;
    let n = spec.size;
    // A state of the same size and the persistence planes, as the stage holds them.
    let mut state = State::zeros(n, n, model().n_terms());
    state.amplitudes_e.fill(1.5);
    let current = Array2::<f32>::from_elem((n, n), 0.25);
    let pflags = Array2::<u8>::zeros((n, n));
    let h5 = |e: hdf5::Error| Error::from(e).path(&root);
    let mut samples = Vec::new();
    for k in 0..spec.reps as u64 {
        let path = input.join(format!("l1_det1_exp{k:04}.h5"));
        let t = Instant::now();
        let f = hdf5::File::open(&path)
            .map(crate::h5io::close_on_exec)
            .map_err(h5)?;
        let image = f
            .dataset("image")
            .and_then(|d| d.read::<f32, ndarray::Ix2>())
            .map_err(h5)?;
        let flags = f
            .dataset("flags")
            .and_then(|d| d.read::<u32, ndarray::Ix2>())
            .map_err(h5)?;
        drop(f);
        let out = root.join(format!("out_{k:04}.h5"));
        let file = h5io::create(&out).map_err(h5)?;
        h5io::write_plain(&file, "image", image.view()).map_err(h5)?;
        h5io::write_flags(&file, "flags", flags.view()).map_err(h5)?;
        let g = h5io::create_group(&file, "persistence").map_err(h5)?;
        h5io::write_plain(&g, "current", current.view()).map_err(h5)?;
        h5io::write_flags(&g, "flags", pflags.view()).map_err(h5)?;
        drop(g);
        file.close().map_err(h5)?;
        sync(&out)?;
        let ck = root.join(format!("ckpt_{k:04}.h5"));
        let file = h5io::create(&ck).map_err(h5)?;
        h5io::write_plain(&file, "amplitudes_e", state.amplitudes_e.view()).map_err(h5)?;
        h5io::write_plain(&file, "release_count", state.release_count.view()).map_err(h5)?;
        h5io::write_plain(&file, "pending", state.pending.view()).map_err(h5)?;
        file.close().map_err(h5)?;
        sync(&ck)?;
        samples.push(t.elapsed().as_secs_f64());
        // Leave on disk what the stage leaves (its page-cache footprint matters on a
        // VM): every output, the two newest checkpoints (the `stage` case's retention).
        if k >= 2 {
            let _ = std::fs::remove_file(root.join(format!("ckpt_{:04}.h5", k - 2)));
        }
    }
    let _ = std::fs::remove_dir_all(&root);
    // The first exposure opens the library and warms the page cache: drop it.
    if samples.len() > 2 {
        samples.remove(0);
    }
    Ok(samples)
}

/// The directory where the `stage` case at the default cadence left its outputs.
fn stage_root(scratch: &Path, size: usize, threads: usize, every: u64) -> PathBuf {
    scratch.join(format!("stage_{size}_{threads}_{every}"))
}

/// (e) A plain copy: read each input file, write its output product's bytes, fsync.
fn case_copy(spec: &CaseSpec) -> Result<Vec<f64>> {
    let input = input_dir(&spec.scratch, spec.size);
    let outputs = stage_root(&spec.scratch, spec.size, spec.threads, DEFAULT_CADENCE).join("out");
    let root = spec
        .scratch
        .join(format!("copy_{}_{}", spec.size, spec.threads));
    if root.exists() {
        std::fs::remove_dir_all(&root).map_err(|e| Error::io(&root, e))?;
    }
    std::fs::create_dir_all(&root).map_err(|e| Error::io(&root, e))?;
    let mut samples = Vec::new();
    for k in 0..spec.reps as u64 {
        let name = format!("l1_det1_exp{k:04}.h5");
        let out_path = outputs.join(&name);
        let out_bytes = std::fs::read(&out_path).map_err(|e| {
            Error::io(&out_path, e).field("the `stage` case's output (run it first)")
        })?;
        let in_path = input.join(&name);
        let dst = root.join(&name);
        let t = Instant::now();
        let in_bytes = std::fs::read(&in_path).map_err(|e| Error::io(&in_path, e))?;
        std::hint::black_box(&in_bytes);
        let mut f = std::fs::File::create(&dst).map_err(|e| Error::io(&dst, e))?;
        std::io::Write::write_all(&mut f, &out_bytes).map_err(|e| Error::io(&dst, e))?;
        f.sync_all().map_err(|e| Error::io(&dst, e))?;
        samples.push(t.elapsed().as_secs_f64());
    }
    let _ = std::fs::remove_dir_all(&root);
    if samples.len() > 2 {
        samples.remove(0);
    }
    Ok(samples)
}

fn sync(path: &Path) -> Result<()> {
    std::fs::File::open(path)
        .and_then(|f| f.sync_all())
        .map_err(|e| Error::io(path, e))
}

/// Run one case in a child process: `persist bench --case ... --json`.
fn spawn(cfg: &BenchConfig, spec: &CaseSpec) -> Result<CaseResult> {
    let out = Command::new(&cfg.exe)
        .args([
            "bench",
            "--case",
            spec.case.name(),
            "--size",
            &spec.size.to_string(),
            "--threads",
            &spec.threads.to_string(),
            "--reps",
            &spec.reps.to_string(),
            "--checkpoint-every",
            &spec.checkpoint_every.to_string(),
            "--scratch",
        ])
        .arg(&spec.scratch)
        .env("RAYON_NUM_THREADS", spec.threads.to_string())
        .output()
        .map_err(|e| Error::io(&cfg.exe, e))?;
    if !out.status.success() {
        return Err(bench_error(format!(
            "bench case {} size {} threads {} failed: {}",
            spec.case.name(),
            spec.size,
            spec.threads,
            String::from_utf8_lossy(&out.stderr).trim()
        )));
    }
    let text = String::from_utf8_lossy(&out.stdout);
    let line = text.lines().last().unwrap_or_default();
    serde_json::from_str(line).map_err(|e| bench_error(format!("bench child output `{line}`: {e}")))
}

/// The whole benchmark: every case, size and thread count, each in a child process.
/// `progress` is told of each result as it comes.
pub fn run(cfg: &BenchConfig, progress: &dyn Fn(&CaseResult)) -> Result<BenchReport> {
    std::fs::create_dir_all(&cfg.scratch).map_err(|e| Error::io(&cfg.scratch, e))?;
    let mut results = Vec::new();
    let mut rows = Vec::new();
    // The stage case needs whole checkpoint periods: at least one at the default cadence.
    let mut stage_exposures = cfg.exposures.max(2 * DEFAULT_CADENCE as usize + 1);
    for &e in &cfg.checkpoint_every {
        stage_exposures = stage_exposures.max(e as usize * 3 + 1);
    }
    let sizes = if cfg.verify_only {
        &[][..]
    } else {
        &cfg.sizes[..]
    };
    for &size in sizes {
        let _ = prepare_inputs(&cfg.scratch, size, stage_exposures)?;
        for &threads in &cfg.threads {
            let spec = |case, reps, every| CaseSpec {
                case,
                size,
                threads,
                reps,
                checkpoint_every: every,
                scratch: cfg.scratch.clone(),
            };
            // Interleaved rounds per size and thread count, so that drifts in the
            // machine's load hit the numerator and the denominator of each ratio alike;
            // each case's samples of all rounds are pooled into one median.
            let mut merged: Vec<Option<CaseResult>> = vec![None; 6];
            for _ in 0..cfg.rounds.max(1) {
                // (e) copies what (c) just wrote, so it runs right after it.
                let runs = [
                    (Case::Step, cfg.reps, 1),
                    (Case::Memory, cfg.reps, 1),
                    (Case::Stage, stage_exposures, DEFAULT_CADENCE),
                    (Case::Copy, stage_exposures, 1),
                    (Case::Guarded, stage_exposures, DEFAULT_CADENCE),
                    (Case::Io, cfg.exposures, 1),
                ];
                for (slot, (case, reps, every)) in merged.iter_mut().zip(runs) {
                    let r = spawn(cfg, &spec(case, reps, every))?;
                    progress(&r);
                    *slot = Some(match slot.take() {
                        None => r,
                        Some(mut m) => {
                            m.samples_s.extend(r.samples_s);
                            m.whole_s.extend(r.whole_s);
                            m.median_s = median(&m.samples_s);
                            m.peak_rss_bytes = m.peak_rss_bytes.max(r.peak_rss_bytes);
                            m
                        }
                    });
                }
            }
            let [Some(a), Some(b), Some(c), Some(e), Some(g), Some(d)] = merged
                .try_into()
                .unwrap_or([None, None, None, None, None, None])
            else {
                return Err(bench_error("no result"));
            };
            let mut every = Vec::new();
            for &e in &cfg.checkpoint_every {
                let r = spawn(cfg, &spec(Case::Stage, stage_exposures, e))?;
                progress(&r);
                every.push((e, r.median_s));
                results.push(r);
            }
            rows.push(Row {
                size,
                threads,
                step_s: a.median_s,
                memory_s: b.median_s,
                stage_s: c.median_s,
                io_s: d.median_s,
                copy_s: e.median_s,
                stage_every_s: every,
                a_over_b: a.median_s / b.median_s,
                c_over_d: c.median_s / d.median_s,
                c_over_e: c.median_s / e.median_s,
                guarded_s: g.median_s,
                g_over_c: g.median_s / c.median_s,
                g_over_c_whole: median(&g.whole_s) / median(&c.whole_s),
                stage_peak_bytes: c.peak_rss_bytes,
                memory_bound_bytes: memory_bound_bytes(size, model().n_terms()),
            });
            results.extend([a, b, c, d, e, g]);
            for every in std::iter::once(DEFAULT_CADENCE).chain(cfg.checkpoint_every.clone()) {
                let root = stage_root(&cfg.scratch, size, threads, every);
                let mut guarded = root.clone();
                guarded.as_mut_os_string().push("_guarded");
                let _ = std::fs::remove_dir_all(root);
                let _ = std::fs::remove_dir_all(guarded);
            }
        }
        let dir = input_dir(&cfg.scratch, size);
        let _ = std::fs::remove_dir_all(&dir);
    }
    let (mut verify_rows, mut verify_projections) = (Vec::new(), Vec::new());
    if let Some(v) = &cfg.verify {
        run_verify(cfg, v, progress, &mut verify_rows, &mut verify_projections)?;
    }
    let mut markdown = if rows.is_empty() {
        String::new()
    } else {
        table(&rows)
    };
    if !verify_rows.is_empty() {
        if !markdown.is_empty() {
            markdown.push('\n');
        }
        markdown.push_str(&verify_table(&verify_rows, &verify_projections));
    }
    Ok(BenchReport {
        results,
        rows,
        markdown,
        machine: machine(),
        date_utc: chrono::Utc::now().to_rfc3339_opts(chrono::SecondsFormat::Secs, true),
        verify_rows,
        verify_projections,
    })
}

/// Where the `verify` case's data of `exposures` exposures of `size^2` are.
fn verify_root(scratch: &Path, size: usize, exposures: usize) -> PathBuf {
    scratch.join(format!("verify_{size}_{exposures}"))
}

/// Simulate `exposures` sky exposures of `size^2` (the default survey, seed 1, one
/// detector), run the stage on them with the default model, and remove the truth: the
/// `verify` case's data (not timed).
pub fn prepare_verify(scratch: &Path, size: usize, exposures: usize) -> Result<PathBuf> {
    use crate::sim::sky;
    let root = verify_root(scratch, size, exposures);
    if root.exists() {
        std::fs::remove_dir_all(&root).map_err(|e| Error::io(&root, e))?;
    }
    let sky_dir = root.join("sky");
    let cfg = sky::SkyConfig {
        size,
        detectors: 1,
        exposures: exposures as u64,
        seed: 1,
        ..sky::SkyConfig::default()
    };
    sky::write(&cfg, &sky_dir)?;
    let truth = sky_dir.join("truth");
    std::fs::remove_dir_all(&truth).map_err(|e| Error::io(&truth, e))?;
    let run = RunConfig {
        input: sky_dir,
        output: root.join("out"),
        checkpoints: root.join("ckpt"),
        model: model(),
        from_checkpoint: None,
        allow_model_change: false,
        checkpoint_every: DEFAULT_CADENCE,
        checkpoint_idle: std::time::Duration::ZERO,
        retention: Retention {
            keep_latest: 1,
            ..Retention::default()
        },
        processed_utc: "2026-03-02T00:00:00.000000Z".into(),
    };
    let report = stage::run(&run, &|_| {});
    if let Some(e) = report.errors.into_iter().next() {
        return Err(e);
    }
    let _ = std::fs::remove_dir_all(&run.checkpoints);
    Ok(root)
}

/// The first `k` exposures of the data at `from` (inputs and outputs copied), as the
/// data of a run of `k` exposures.
fn verify_subset(scratch: &Path, from: &Path, size: usize, k: usize) -> Result<PathBuf> {
    let root = verify_root(scratch, size, k);
    if root.exists() {
        std::fs::remove_dir_all(&root).map_err(|e| Error::io(&root, e))?;
    }
    for sub in ["sky", "out"] {
        let src = from.join(sub);
        let dst = root.join(sub);
        std::fs::create_dir_all(&dst).map_err(|e| Error::io(&dst, e))?;
        let mut names: Vec<PathBuf> = std::fs::read_dir(&src)
            .map_err(|e| Error::io(&src, e))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.is_file() && p.extension().is_some_and(|x| x == "h5"))
            .collect();
        // the simulator's names, `d{det}_e{index:06}.h5`, sort in exposure order
        names.sort();
        for p in names.iter().take(k) {
            let to = dst.join(p.file_name().unwrap_or_default());
            std::fs::copy(p, &to).map_err(|e| Error::io(&to, e))?;
        }
    }
    Ok(root)
}

/// (f) `verify` over the prepared data of `spec.reps` exposures of `spec.size^2`.
fn case_verify(spec: &CaseSpec) -> Result<VerifyCounts> {
    let root = verify_root(&spec.scratch, spec.size, spec.reps);
    let t = Instant::now();
    let r = crate::verify::run(
        &root.join("sky"),
        &root.join("out"),
        &crate::verify::VerifyParams::default(),
    )?;
    crate::verify::write_report(&r, &root.join(format!("report_{}", spec.threads)))?;
    let total_s = t.elapsed().as_secs_f64();
    if let Some(e) = r.errors.first() {
        return Err(bench_error(format!(
            "verify: {}: {}",
            e.file.display(),
            e.reason
        )));
    }
    if r.exposures == 0 {
        return Err(bench_error(format!(
            "verify: no exposures under {}",
            root.display()
        )));
    }
    Ok(VerifyCounts {
        exposures: r.exposures,
        samples: r.samples,
        events: r.events,
        total_s,
    })
}

/// (f) at every thread count: the full frame's first exposures, the smaller frame's day
/// and its first exposures, and the projection.
fn run_verify(
    cfg: &BenchConfig,
    v: &VerifyBenchConfig,
    progress: &dyn Fn(&CaseResult),
    rows: &mut Vec<VerifyRow>,
    projections: &mut Vec<VerifyProjection>,
) -> Result<()> {
    if v.exposures == 0 || v.exposures > v.day_exposures || v.day_size == 0 || v.size == 0 {
        return Err(Error::new(
            ErrorKind::Usage,
            format!(
                "verify benchmark: need 0 < exposures {} <= day exposures {} and sizes > 0",
                v.exposures, v.day_exposures
            ),
        ));
    }
    let full = prepare_verify(&cfg.scratch, v.size, v.exposures)?;
    let day = prepare_verify(&cfg.scratch, v.day_size, v.day_exposures)?;
    let first = verify_subset(&cfg.scratch, &day, v.day_size, v.exposures)?;
    for &threads in &cfg.threads {
        let mut time = |size: usize, exposures: usize| -> Result<f64> {
            let r = spawn(
                cfg,
                &CaseSpec {
                    case: Case::Verify,
                    size,
                    threads,
                    reps: exposures,
                    checkpoint_every: 1,
                    scratch: cfg.scratch.clone(),
                },
            )?;
            progress(&r);
            let c = r
                .verify
                .ok_or_else(|| bench_error("verify case: no counts in the child's result"))?;
            rows.push(VerifyRow {
                size,
                exposures: c.exposures,
                threads,
                total_s: c.total_s,
                s_per_exposure: c.total_s / c.exposures as f64,
                samples: c.samples,
                events: c.events,
                us_per_pixel_exposure: c.total_s * 1e6 / (c.exposures * size * size) as f64,
                peak_bytes: r.peak_rss_bytes,
            });
            Ok(c.total_s)
        };
        let full_s = time(v.size, v.exposures)?;
        let first_s = time(v.day_size, v.exposures)?;
        let day_s = time(v.day_size, v.day_exposures)?;
        let pixel_ratio = (v.size as f64 / v.day_size as f64).powi(2);
        let measured_ratio = full_s / first_s;
        let projected_day_s = day_s * pixel_ratio.max(measured_ratio);
        projections.push(VerifyProjection {
            size: v.size,
            day_size: v.day_size,
            day_exposures: v.day_exposures,
            threads,
            day_s,
            pixel_ratio,
            measured_ratio,
            exposures: v.exposures,
            projected_day_s,
            projected_s_per_exposure: projected_day_s / v.day_exposures as f64,
        });
    }
    for root in [full, day, first] {
        let _ = std::fs::remove_dir_all(root);
    }
    Ok(())
}

/// The markdown of the `verify` case: its runs, then the projected day.
pub fn verify_table(rows: &[VerifyRow], projections: &[VerifyProjection]) -> String {
    let mut s = String::from(
        "| (f) verify | exposures | threads | s | s/exposure | track samples | events | us/pixel-exposure | peak MiB |\n|---|---|---|---|---|---|---|---|---|\n",
    );
    for r in rows {
        s.push_str(&format!(
            "| {0}^2 | {1} | {2} | {3:.2} | {4:.3} | {5} | {6} | {7:.3} | {8:.0} |\n",
            r.size,
            r.exposures,
            r.threads,
            r.total_s,
            r.s_per_exposure,
            r.samples,
            r.events,
            r.us_per_pixel_exposure,
            mib(r.peak_bytes)
        ));
    }
    for p in projections {
        s.push_str(&format!(
            "\n{0} exposures (a detector-day at 571) of {1}^2 with {2} thread(s): **{3:.1} s** \
             ({4:.2} s an exposure), projected from the measured day of {5}^2 ({6:.1} s) \
             times {7:.2}, the larger of the pixel ratio ({8:.2}) and the measured ratio of \
             the first {9} exposures at the two sizes ({10:.2}).\n",
            p.day_exposures,
            p.size,
            p.threads,
            p.projected_day_s,
            p.projected_s_per_exposure,
            p.day_size,
            p.day_s,
            p.pixel_ratio.max(p.measured_ratio),
            p.pixel_ratio,
            p.exposures,
            p.measured_ratio
        ));
    }
    s
}

fn mib(b: u64) -> f64 {
    b as f64 / (1024.0 * 1024.0)
}

/// The markdown table of the rows.
pub fn table(rows: &[Row]) -> String {
    let every: Vec<u64> = rows
        .first()
        .map(|r| r.stage_every_s.iter().map(|e| e.0).collect())
        .unwrap_or_default();
    let mut s = String::from(
        "| image | threads | (a) step exp/s | (b) memory exp/s | a/b | (c) stage exp/s | (d) I/O exp/s | c/d | (e) copy exp/s | c/e | (g) guarded exp/s | g/c | g/c whole run |",
    );
    for e in &every {
        s.push_str(&format!(" (c) ckpt/{e} exp/s |"));
    }
    s.push_str(
        " stage peak MiB | bound MiB |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    );
    for _ in &every {
        s.push_str("---|");
    }
    s.push_str("---|---|\n");
    for r in rows {
        s.push_str(&format!(
            "| {0}^2 | {1} | {2:.1} | {3:.1} | {4:.2} | {5:.2} | {6:.2} | {7:.2} | {8:.2} | {9:.2} | {10:.2} | {11:.3} | {12:.3} |",
            r.size,
            r.threads,
            1.0 / r.step_s,
            1.0 / r.memory_s,
            r.a_over_b,
            1.0 / r.stage_s,
            1.0 / r.io_s,
            r.c_over_d,
            1.0 / r.copy_s,
            r.c_over_e,
            1.0 / r.guarded_s,
            r.g_over_c,
            r.g_over_c_whole
        ));
        for (_, t) in &r.stage_every_s {
            s.push_str(&format!(" {:.2} |", 1.0 / t));
        }
        s.push_str(&format!(
            " {:.0} | {:.0} |\n",
            mib(r.stage_peak_bytes),
            mib(r.memory_bound_bytes)
        ));
    }
    s
}

/// CPU model, core count and memory, for the record.
pub fn machine() -> String {
    let cpu = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split_once(':'))
                .map(|(_, v)| v.trim().to_owned())
        })
        .unwrap_or_else(|| "unknown CPU".into());
    let cores = std::thread::available_parallelism().map_or(0, |n| n.get());
    let mem = std::fs::read_to_string("/proc/meminfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("MemTotal:"))
                .and_then(|l| l.split_whitespace().nth(1))
                .and_then(|kb| kb.parse::<u64>().ok())
        })
        .map_or(0.0, |kb| kb as f64 / (1024.0 * 1024.0));
    format!("{cpu}, {cores} cores, {mem:.0} GiB")
}
