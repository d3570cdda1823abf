//! Versioned HDF5 checkpoints of the model state, keyed by (detector, exposure index).
//!
//! Layout: `DIR/det{D}/ckpt_det{D}_{index:010}.h5`, one file per (detector, exposure
//! index): the state *after* absorbing that exposure. Format version 1:
//!
//! - root attributes: `product = "persist.checkpoint"`, `format_version = 1`,
//!   `detector`, `exposure_index`, `model_id`, `model_name`, `model_json` (the model's
//!   canonical JSON, so a reprocessing can recover it; `model_id` is its SHA-256),
//!   `t_reset_unix_s` (the reset ending the exposure, the instant the state is valid
//!   at), `t_reset_utc` (the same, ISO 8601, for humans), `software_version`, and
//!   `stage_json` (opaque JSON text the stage owns);
//! - datasets, uncompressed (deflate measured 8x slower on a full state):
//!   `amplitudes_e` float64 `[ny, nx, n_terms]`, **term index fastest**, so one
//!   pixel's amplitudes are contiguous, exactly as [`State::amplitudes_e`];
//!   `release_count` uint8 `[ny, nx]`; `pending` uint8 `[ny, nx]`. Objects of 1 MiB
//!   or more start at multiples of 4096 bytes, and `amplitudes_e` is allocated when
//!   created (contiguous, never filled) and its values written straight to the disk
//!   (`write_amplitudes`); any HDF5 reader reads the file as usual.
//!
//! Invariants: a checkpoint holds a state that passed [`State::check`], whose
//! `last_index` is its `exposure_index` and whose `t_reset_unix_s` is set; it is
//! published atomically like products (temporary `.NAME.part`, validated, synced,
//! renamed, directory synced); [`load`] refuses unknown format versions before looking
//! further, and re-checks everything (schema, shapes, `model_id` against `model_json`,
//! [`State::check`]).

use crate::error::{Error, ErrorKind, Result};
use crate::h5io::{self, attr_f64, attr_i64, attr_str};
use crate::model::params::sha256_hex;
use crate::model::State;
use crate::product::schema::{self, Schema, View};
use crate::units::{DetectorId, UtcSeconds};
use ndarray::{Array2, Array3};
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// Root attribute `product` of a checkpoint.
pub const PRODUCT: &str = "persist.checkpoint";
/// The checkpoint layout this build reads and writes.
pub const FORMAT_VERSION: i64 = 1;

/// Everything a checkpoint records besides the state arrays.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CheckpointMeta {
    pub detector: DetectorId,
    /// The last exposure absorbed into the state (the key, with the detector).
    pub exposure_index: u64,
    /// SHA-256 (hex) of `model_json`.
    pub model_id: String,
    pub model_name: String,
    /// The model file in canonical form ([`crate::model::ModelParams::canonical_json`]).
    pub model_json: String,
    /// Opaque JSON text owned by the stage.
    pub stage_json: String,
    pub software_version: String,
}

/// Which checkpoints [`prune`] keeps (module docs of [`Retention`]'s fields).
///
/// A checkpoint is *on the cadence grid* when `(exposure_index + 1) % cadence == 0`;
/// others are *tails* (written when a batch ends, the stage stops, or a watch goes idle)
/// and are removed as soon as a newer checkpoint exists. Among the grid checkpoints older
/// than the newest, the `keep_latest` newest are kept; older ones thin with their age
/// (data time: the newest checkpoint's `t_reset_unix_s` minus theirs): the first of each
/// hour while younger than `hourly_for_s`, the first of each day while younger than
/// `daily_for_s`, then the first of each week (with `weekly`), buckets counted from the
/// Unix epoch (`floor(t / 3600)`, `/ 86400`, `/ 604800`), which nest, so the kept set does
/// not depend on how often pruning ran: the first of a week is the first of its day and
/// of its hour. The newest checkpoint is always kept.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Retention {
    /// The newest checkpoints always kept: the newest, and the `keep_latest - 1` grid
    /// checkpoints before it.
    pub keep_latest: usize,
    /// Thin older checkpoints by age (hourly, daily, weekly); `false`: keep only the
    /// newest `keep_latest`.
    pub keep_one_per_hour: bool,
    /// Keep the first checkpoint of each hour while younger than this (seconds of data).
    pub hourly_for_s: f64,
    /// Keep the first checkpoint of each day while younger than this.
    pub daily_for_s: f64,
    /// Keep the first checkpoint of each week beyond `daily_for_s`, forever.
    pub weekly: bool,
    /// The stage's checkpoint cadence (exposures, >= 1): what tells a tail.
    pub cadence: u64,
}

/// The stage's default checkpoint cadence: one checkpoint every 8 exposures, so a crash
/// replays at most 7 exposures (about 2 s at 2040 x 2040) and rewrites nothing.
pub const DEFAULT_CADENCE: u64 = 8;

impl Default for Retention {
    fn default() -> Self {
        Retention {
            keep_latest: 20,
            keep_one_per_hour: true,
            hourly_for_s: 86_400.0,
            daily_for_s: 30.0 * 86_400.0,
            weekly: true,
            cadence: DEFAULT_CADENCE,
        }
    }
}

impl Retention {
    /// Is `index` on the cadence grid?
    pub fn on_grid(&self, index: u64) -> bool {
        (index + 1).is_multiple_of(self.cadence.max(1))
    }

    /// The bucket a grid checkpoint of reset time `t` falls in when the newest is at
    /// `t_newest`: `(level, number)`, `None` when its age keeps nothing.
    fn bucket(&self, t: f64, t_newest: f64) -> Option<(u8, i64)> {
        let age = t_newest - t;
        let (level, width) = if age < self.hourly_for_s {
            (0, 3600.0)
        } else if age < self.daily_for_s {
            (1, 86_400.0)
        } else if self.weekly {
            (2, 604_800.0)
        } else {
            return None;
        };
        Some((level, (t / width).floor() as i64))
    }

    /// Which of `items` (exposure index, reset time; sorted by index, the last the
    /// newest) this rule keeps. `None` reset times (unreadable) are kept.
    pub fn keep(&self, items: &[(u64, Option<f64>)]) -> Vec<bool> {
        let n = items.len();
        let mut keep = vec![false; n];
        let Some(&(_, t_newest)) = items.last() else {
            return keep;
        };
        keep[n - 1] = true;
        let grid: Vec<usize> = (0..n - 1).filter(|&i| self.on_grid(items[i].0)).collect();
        let n_old = grid
            .len()
            .saturating_sub(self.keep_latest.saturating_sub(1));
        for &i in &grid[n_old..] {
            keep[i] = true;
        }
        if !self.keep_one_per_hour {
            return keep;
        }
        let t_newest = t_newest.or_else(|| grid.iter().rev().find_map(|&i| items[i].1));
        // The first (lowest index) grid checkpoint of every bucket at every level.
        let mut first: HashMap<(u8, i64), usize> = HashMap::new();
        for &i in &grid {
            if let Some(t) = items[i].1 {
                for (level, width) in [(0u8, 3600.0), (1, 86_400.0), (2, 604_800.0)] {
                    first
                        .entry((level, (t / width).floor() as i64))
                        .or_insert(i);
                }
            }
        }
        for &i in &grid[..n_old] {
            keep[i] = match (items[i].1, t_newest) {
                (Some(t), Some(tn)) => self
                    .bucket(t, tn)
                    .is_some_and(|b| first.get(&b) == Some(&i)),
                _ => true,
            };
        }
        keep
    }

    /// How many checkpoints this rule leaves after `n_exposures` exposures taken every
    /// `interval_s` seconds (the projection `persist status` prints).
    pub fn projected_count(&self, n_exposures: u64, interval_s: f64) -> usize {
        let items: Vec<(u64, Option<f64>)> = (0..n_exposures)
            .filter(|&i| self.on_grid(i) || i + 1 == n_exposures)
            .map(|i| (i, Some(1.0e9 + i as f64 * interval_s)))
            .collect();
        self.keep(&items).iter().filter(|&&k| k).count()
    }
}

/// `DIR/det{D}`.
pub fn detector_dir(dir: &Path, detector: DetectorId) -> PathBuf {
    dir.join(format!("det{}", detector.0))
}

/// `DIR/det{D}/ckpt_det{D}_{index:010}.h5`.
pub fn path_for(dir: &Path, detector: DetectorId, index: u64) -> PathBuf {
    detector_dir(dir, detector).join(format!("ckpt_det{}_{index:010}.h5", detector.0))
}

/// The metadata's own consistency, checked on saving and on loading: the identity is
/// the SHA-256 of the model's canonical JSON, and the stage's bookkeeping is JSON.
fn check_meta(meta: &CheckpointMeta) -> Result<()> {
    if sha256_hex(meta.model_json.as_bytes()) != meta.model_id {
        return Err(ckpt_error(
            "model_id",
            "is not the SHA-256 of model_json (the checkpoint was altered)",
        ));
    }
    if let Err(e) = serde_json::from_str::<serde_json::Value>(&meta.stage_json) {
        return Err(ckpt_error("stage_json", format!("not JSON: {e}")));
    }
    Ok(())
}

fn ckpt_error(field: &str, message: impl Into<String>) -> Error {
    Error::new(ErrorKind::Checkpoint, message).field(field)
}

/// Save the state after exposure `meta.exposure_index` of `meta.detector`, atomically.
/// When an identical checkpoint (same meta data and state) already exists for that key,
/// nothing is written. Returns the checkpoint's path.
pub fn save(dir: &Path, meta: &CheckpointMeta, state: &State) -> Result<PathBuf> {
    match stage(dir, meta, state)? {
        Staged::Existing(path) => Ok(path),
        Staged::Written(s) => {
            let path = s.path().to_path_buf();
            s.commit()
                .map_err(|e| e.detector(meta.detector).exposure(meta.exposure_index))?;
            Ok(path)
        }
    }
}

/// What [`stage`] did.
#[derive(Debug)]
pub enum Staged {
    /// An identical checkpoint is already published under this path.
    Existing(PathBuf),
    /// Written and validated under its temporary name; [`h5io::Staged::commit`]
    /// publishes it (sync, rename) and needs neither the state nor HDF5, so it can run
    /// on another thread while processing goes on.
    Written(h5io::Staged),
}

/// The first half of [`save`]: every check, and the write under the temporary name.
/// The amplitudes are checked block by block as they are written
/// (`write_amplitudes`), not in a pass of their own (200 MB at 2040 x 2040).
pub fn stage(dir: &Path, meta: &CheckpointMeta, state: &State) -> Result<Staged> {
    let path = path_for(dir, meta.detector, meta.exposure_index);
    let fail = |e: Error| {
        e.path(&path)
            .detector(meta.detector)
            .exposure(meta.exposure_index)
    };
    state.check_with(true).map_err(|m| fail(state_error(&m)))?;
    if state.last_index != Some(meta.exposure_index) {
        return Err(fail(ckpt_error(
            "exposure_index",
            format!(
                "the state's last absorbed exposure is {:?}, not the key {}",
                state.last_index, meta.exposure_index
            ),
        )));
    }
    let t_reset = state.t_reset_unix_s.ok_or_else(|| {
        fail(ckpt_error(
            "t_reset_unix_s",
            "the state has absorbed no exposure (no reset time)",
        ))
    })?;
    check_meta(meta).map_err(fail)?;
    if path.exists() {
        if let Ok((m, s)) = load(&path) {
            if m == *meta && s == *state {
                return Ok(Staged::Existing(path));
            }
        }
    }
    let det_dir = detector_dir(dir, meta.detector);
    if !det_dir.is_dir() {
        std::fs::create_dir_all(&det_dir).map_err(|e| fail(Error::io(&det_dir, e)))?;
        h5io::sync_dir(&det_dir).map_err(fail)?;
    }
    let staged = h5io::write_temp(
        &path,
        |tmp| {
            let file = create_aligned(tmp)?;
            let offset = write_checkpoint(&file, meta, state, t_reset)?;
            file.close()?;
            write_amplitudes(tmp, offset, &state.amplitudes_e)
        },
        |tmp| {
            // The state was checked above; what was written is checked by its layout,
            // meta data and shapes (reading 200 MB back would double the I/O and the
            // peak memory).
            let file = h5io::open_as(tmp, &path)?;
            let (m, t) = check_layout(&file, &path).map_err(schema::combine)?;
            let shape = |d: &str| file.dataset(d).map(|d| d.shape()).unwrap_or_default();
            let (ny, nx) = state.shape();
            if m != *meta
                || t.to_bits() != t_reset.to_bits()
                || shape("amplitudes_e") != [ny, nx, state.n_terms()]
                || shape("release_count") != [ny, nx]
                || shape("pending") != [ny, nx]
            {
                return Err(ckpt_error(
                    "state",
                    "the checkpoint read back differs from what was written",
                )
                .path(&path));
            }
            Ok(())
        },
    )
    .map_err(fail)?;
    Ok(Staged::Written(staged))
}

/// Create a checkpoint file as [`h5io::create`] does, with every object of 1 MiB or
/// more at an offset that is a multiple of [`DIRECT_ALIGN`] (what a direct write needs).
fn create_aligned(path: &Path) -> Result<hdf5::File> {
    hdf5::File::with_options()
        .with_fcpl(|p| p.obj_track_times(false))
        .with_fapl(|p| {
            // No data sieving: h5io::create says why.
            p.file_locking(false)
                .sieve_buf_size(0)
                .alignment(1 << 20, DIRECT_ALIGN as u64)
        })
        .create(path)
        .map(h5io::close_on_exec)
        .map_err(Error::from)
}

/// Everything but the amplitude values, through HDF5; returns the file offset of
/// `/amplitudes_e`, whose space is allocated (contiguous, never filled) and written by
/// [`write_amplitudes`] once the file is closed.
fn write_checkpoint(
    file: &hdf5::File,
    meta: &CheckpointMeta,
    state: &State,
    t_reset: f64,
) -> Result<u64> {
    let index = i64::try_from(meta.exposure_index)
        .map_err(|_| Error::invalid("exposure_index", "does not fit an int64"))?;
    attr_str(file, "product", PRODUCT)?;
    attr_i64(file, "format_version", FORMAT_VERSION)?;
    attr_i64(file, "detector", i64::from(meta.detector.0))?;
    attr_i64(file, "exposure_index", index)?;
    attr_str(file, "model_id", &meta.model_id)?;
    attr_str(file, "model_name", &meta.model_name)?;
    attr_str(file, "model_json", &meta.model_json)?;
    attr_f64(file, "t_reset_unix_s", t_reset)?;
    attr_str(file, "t_reset_utc", &UtcSeconds(t_reset).to_iso())?;
    attr_str(file, "software_version", &meta.software_version)?;
    attr_str(file, "hdf5_version", &h5io::library_version())?;
    attr_str(file, "stage_json", &meta.stage_json)?;
    let field = |f: &'static str| move |err: hdf5::Error| Error::from(err).field(f);
    let (ny, nx, n) = state.amplitudes_e.dim();
    let ds = file
        .new_dataset::<f64>()
        .obj_track_times(false)
        .shape([ny, nx, n])
        .alloc_time(Some(hdf5::dataset::AllocTime::Early))
        .fill_time(hdf5::dataset::FillTime::Never)
        .create("amplitudes_e")
        .map_err(field("/amplitudes_e"))?;
    let offset = ds
        .offset()
        .ok_or_else(|| Error::invalid("/amplitudes_e", "no contiguous storage was allocated"))?;
    drop(ds);
    h5io::write_plain(file, "release_count", state.release_count.view())
        .map_err(field("/release_count"))?;
    h5io::write_plain(file, "pending", state.pending.view()).map_err(field("/pending"))?;
    Ok(offset)
}

/// Alignment of file offsets, lengths and memory of a direct (`O_DIRECT`) write.
const DIRECT_ALIGN: usize = 4096;

/// Bytes of amplitudes checked, copied and written per write: a multiple of
/// [`DIRECT_ALIGN`].
const AMPLITUDE_BLOCK_BYTES: usize = 4 << 20;

/// The values of `/amplitudes_e` (contiguous, native float64, term index
/// fastest, exactly as HDF5 lays out [`State::amplitudes_e`]) written at `offset` of
/// the closed file `tmp`, block by block, each block checked finite and `>= 0`
/// ([`crate::model::state::amplitudes_ok`]) just before it is written: an invalid
/// state is refused, naming the value, and the check costs no extra pass over memory.
///
/// The blocks go to the disk with `O_DIRECT` through one aligned buffer: 200 MB of
/// state per checkpoint are not copied into the page cache (on this machine that
/// kernel copy cost more CPU time than the rest of a checkpoint), and the later
/// `fsync` has little left to do. Where the file system refuses direct I/O (tmpfs),
/// for states under 1 MiB (not aligned), and for the last bytes that do not fill an
/// aligned block, ordinary writes are used;
/// the file's bytes are the same either way.
fn write_amplitudes(tmp: &Path, offset: u64, a: &ndarray::Array3<f64>) -> Result<()> {
    use crate::model::state::amplitudes_ok;
    use std::os::unix::fs::{FileExt, OpenOptionsExt};
    let io = |e: std::io::Error| Error::io(tmp, e).field("/amplitudes_e");
    let values = a.as_slice().ok_or_else(|| {
        Error::invalid("/amplitudes_e", "state amplitudes not in standard layout")
    })?;
    let buffered = std::fs::OpenOptions::new()
        .write(true)
        .open(tmp)
        .map_err(io)?;
    // Objects under 1 MiB are not aligned (small states): ordinary writes only.
    let mut direct = if offset.is_multiple_of(DIRECT_ALIGN as u64) {
        std::fs::OpenOptions::new()
            .write(true)
            .custom_flags(libc::O_DIRECT)
            .open(tmp)
            .ok()
    } else {
        None
    };
    let mut storage = vec![0u8; AMPLITUDE_BLOCK_BYTES + DIRECT_ALIGN];
    let start = storage.as_ptr().align_offset(DIRECT_ALIGN);
    let buf = &mut storage[start..start + AMPLITUDE_BLOCK_BYTES];
    let mut pos = offset;
    for block in values.chunks(AMPLITUDE_BLOCK_BYTES / 8) {
        if !amplitudes_ok(block) {
            if let Some(bad) = block.iter().find(|v| !(v.is_finite() && **v >= 0.0)) {
                return Err(state_error(&format!(
                    "amplitudes_e: holds {bad}, must be finite and >= 0"
                )));
            }
        }
        let bytes = &mut buf[..block.len() * 8];
        for (b, v) in bytes.chunks_exact_mut(8).zip(block) {
            b.copy_from_slice(&v.to_ne_bytes());
        }
        let aligned = bytes.len() / DIRECT_ALIGN * DIRECT_ALIGN;
        let mut done = 0;
        if let Some(f) = &direct {
            match f.write_all_at(&bytes[..aligned], pos) {
                Ok(()) => done = aligned,
                // Direct I/O refused here: ordinary writes from now on.
                Err(e) if e.raw_os_error() == Some(libc::EINVAL) => direct = None,
                Err(e) => return Err(io(e)),
            }
        }
        buffered
            .write_all_at(&bytes[done..], pos + done as u64)
            .map_err(io)?;
        pos += bytes.len() as u64;
    }
    Ok(())
}

/// Load and fully check a checkpoint.
pub fn load(path: &Path) -> Result<(CheckpointMeta, State)> {
    let file = h5io::open(path)?;
    check_file(&file, path).map_err(schema::combine)
}

/// The meta data and reset time of a checkpoint, reading its attributes only (no
/// state arrays): for `persist status`.
pub fn load_meta(path: &Path) -> Result<(CheckpointMeta, f64)> {
    let file = h5io::open(path)?;
    let m = schema::manifest(&file).map_err(|e| e.path(path))?;
    let v = View(&m);
    if v.attr_str("product") != Some(PRODUCT) {
        return Err(Error::invalid("product", "not a checkpoint").path(path));
    }
    meta_of(v).map_err(|e| e.path(path))
}

/// The meta data and `t_reset_unix_s` in a checkpoint's root attributes (the error
/// without the file's path).
fn meta_of(v: View<'_>) -> Result<(CheckpointMeta, f64)> {
    let text = |f: &str| v.attr_str(f).unwrap_or_default().to_owned();
    let detector = v
        .attr_i64("detector")
        .and_then(DetectorId::new)
        .ok_or_else(|| Error::invalid("detector", "missing or out of 1..=6"))?;
    let exposure_index = v
        .attr("exposure_index")
        .and_then(serde_json::Value::as_u64)
        .ok_or_else(|| Error::invalid("exposure_index", "missing or negative"))?;
    let t_reset = v
        .attr_f64("t_reset_unix_s")
        .ok_or_else(|| Error::invalid("t_reset_unix_s", "missing or not finite"))?;
    let meta = CheckpointMeta {
        detector,
        exposure_index,
        model_id: text("model_id"),
        model_name: text("model_name"),
        model_json: text("model_json"),
        stage_json: text("stage_json"),
        software_version: text("software_version"),
    };
    Ok((meta, t_reset))
}

/// `State::check` messages look like `amplitudes_e: holds ...`: name the field.
fn state_error(message: &str) -> Error {
    let field = match message.split_once(':') {
        Some((f, _)) if f.starts_with("amplitudes_e") => "/amplitudes_e",
        Some((f, _)) if f.starts_with("pending") => "/pending",
        Some((f, _)) if f.starts_with("release_count") => "/release_count",
        Some((f, _)) if f.starts_with("t_reset") => "t_reset_unix_s",
        _ => "state",
    };
    ckpt_error(field, message)
}

/// Validate an open checkpoint (format version first, then schema, shapes, data) and
/// return its contents. Errors name `name`.
pub(crate) fn check_file(
    file: &hdf5::File,
    name: &Path,
) -> std::result::Result<(CheckpointMeta, State), Vec<Error>> {
    let one = |e: Error| vec![e.path(name)];
    let (meta, t_reset) = check_layout(file, name)?;
    let exposure_index = meta.exposure_index;
    let read =
        |path: &'static str| move |e: hdf5::Error| vec![Error::from(e).field(path).path(name)];
    let amplitudes_e = file
        .dataset("amplitudes_e")
        .and_then(|d| d.read::<f64, ndarray::Ix3>())
        .map_err(read("/amplitudes_e"))?;
    let release_count = file
        .dataset("release_count")
        .and_then(|d| d.read::<u8, ndarray::Ix2>())
        .map_err(read("/release_count"))?;
    let pending = file
        .dataset("pending")
        .and_then(|d| d.read::<u8, ndarray::Ix2>())
        .map_err(read("/pending"))?;
    let state = State {
        amplitudes_e: amplitudes_e as Array3<f64>,
        release_count: release_count as Array2<u8>,
        pending: pending as Array2<u8>,
        t_reset_unix_s: Some(t_reset),
        last_index: Some(exposure_index),
    };
    state.check().map_err(|m| one(state_error(&m)))?;
    Ok((meta, state))
}

/// Everything [`check_file`] checks except the values of the datasets: format version,
/// schema, shapes, attributes. Returns the meta data and `t_reset_unix_s`.
fn check_layout(
    file: &hdf5::File,
    name: &Path,
) -> std::result::Result<(CheckpointMeta, f64), Vec<Error>> {
    let one = |e: Error| vec![e.path(name)];
    let m = schema::manifest(file).map_err(one)?;
    let v = View(&m);
    if v.attr_str("product") != Some(PRODUCT) {
        return Err(one(Error::invalid(
            "product",
            format!("must be `{PRODUCT}`: not a checkpoint"),
        )));
    }
    match v.attr("format_version") {
        Some(fv) if fv.as_i64() == Some(FORMAT_VERSION) => {}
        other => {
            let shown = other.map_or_else(|| "missing".to_owned(), |x| x.to_string());
            return Err(one(ckpt_error(
                "format_version",
                format!(
                    "checkpoint format_version {shown} is not supported: this build reads \
                     format {FORMAT_VERSION} only (reprocess, or use the software that wrote it)"
                ),
            )));
        }
    }
    let mut errors = schema::validate(Schema::Checkpoint, &m, name);
    errors.extend(
        schema::check_dimensions(v)
            .into_iter()
            .map(|e| e.path(name)),
    );
    if let (Some(a), Some(rc), Some(p)) = (
        v.shape("/amplitudes_e"),
        v.shape("/release_count"),
        v.shape("/pending"),
    ) {
        for (field, s) in [("/release_count", rc), ("/pending", p)] {
            if a.len() != 3 || s[..] != a[..2] {
                errors.push(
                    Error::invalid(
                        field,
                        format!("shape {s:?} is not [ny, nx] of /amplitudes_e {a:?}"),
                    )
                    .path(name),
                );
            }
        }
    }
    if !errors.is_empty() {
        return Err(errors);
    }
    let (meta, t_reset) = meta_of(v).map_err(one)?;
    check_meta(&meta).map_err(one)?;
    Ok((meta, t_reset))
}

/// The checkpoints of `detector` under `dir`, sorted by exposure index. Temporary and
/// unrelated files are ignored; a missing directory is an empty list.
pub fn list(dir: &Path, detector: DetectorId) -> Result<Vec<(u64, PathBuf)>> {
    let det_dir = detector_dir(dir, detector);
    let entries = match std::fs::read_dir(&det_dir) {
        Ok(e) => e,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(Error::io(&det_dir, e)),
    };
    let prefix = format!("ckpt_det{}_", detector.0);
    let mut out = Vec::new();
    for entry in entries {
        let entry = entry.map_err(|e| Error::io(&det_dir, e))?;
        let name = entry.file_name();
        let Some(name) = name.to_str() else { continue };
        let index = name
            .strip_prefix(&prefix)
            .and_then(|r| r.strip_suffix(".h5"))
            // At least 10 digits: `{index:010}` grows for larger indices (start-time
            // indices of FITS exposures have 13).
            .filter(|d| d.len() >= 10 && d.bytes().all(|b| b.is_ascii_digit()))
            .and_then(|d| d.parse::<u64>().ok());
        if let Some(index) = index {
            out.push((index, entry.path()));
        }
    }
    out.sort();
    Ok(out)
}

/// The checkpoint of (`detector`, `index`), if there is one.
pub fn find(dir: &Path, detector: DetectorId, index: u64) -> Option<PathBuf> {
    let p = path_for(dir, detector, index);
    p.is_file().then_some(p)
}

/// `t_reset_unix_s` of a checkpoint, reading that one attribute.
fn t_reset_of(path: &Path) -> Option<f64> {
    let file = h5io::open(path).ok()?;
    let t = file
        .attr("t_reset_unix_s")
        .ok()?
        .read_scalar::<f64>()
        .ok()?;
    t.is_finite().then_some(t)
}

/// Delete the checkpoints of `detector` that `retention` does not keep ([`Retention`]:
/// tails once a newer checkpoint exists, old grid checkpoints thinned by age). A
/// checkpoint whose reset time cannot be read is kept when thinning (it is not
/// understood, so not deleted). Returns what was removed.
pub fn prune(dir: &Path, detector: DetectorId, retention: &Retention) -> Result<Vec<PathBuf>> {
    let all = list(dir, detector)?;
    if all.len() <= 1 {
        return Ok(Vec::new());
    }
    let items: Vec<(u64, Option<f64>)> = all
        .iter()
        .enumerate()
        .map(|(k, (index, path))| {
            let needed =
                retention.keep_one_per_hour && (k + 1 == all.len() || retention.on_grid(*index));
            let t = if needed { t_reset_of(path) } else { None };
            if needed && t.is_none() {
                tracing::warn!(path = %path.display(), "checkpoint reset time unreadable; kept");
            }
            (*index, t)
        })
        .collect();
    let keep = retention.keep(&items);
    let mut removed = Vec::new();
    for ((_, path), kept) in all.iter().zip(keep) {
        if kept {
            continue;
        }
        std::fs::remove_file(path).map_err(|e| Error::io(path, e))?;
        removed.push(path.clone());
    }
    if !removed.is_empty() {
        h5io::sync_dir(&all[0].1)?;
    }
    Ok(removed)
}

/// Remove stray temporary files (`.*.part`) left by interrupted writes, in `dir` and
/// its `det*` subdirectories. Returns how many were removed.
pub fn clean_temporaries(dir: &Path) -> Result<usize> {
    if !dir.is_dir() {
        return Ok(0);
    }
    let mut removed = 0;
    for entry in walkdir::WalkDir::new(dir).max_depth(2) {
        let entry = entry
            .map_err(|e| Error::new(ErrorKind::Io, e.to_string()).path(e.path().unwrap_or(dir)))?;
        let name = entry.file_name().to_string_lossy();
        if entry.file_type().is_file() && name.starts_with('.') && name.ends_with(".part") {
            std::fs::remove_file(entry.path()).map_err(|e| Error::io(entry.path(), e))?;
            removed += 1;
        }
    }
    Ok(removed)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::ModelParams;

    pub(crate) fn meta(detector: u8, index: u64) -> CheckpointMeta {
        let p = ModelParams::default();
        CheckpointMeta {
            detector: DetectorId(detector),
            exposure_index: index,
            model_id: p.identity(),
            model_name: p.name.clone(),
            model_json: p.canonical_json(),
            stage_json: r#"{"history_incomplete":false}"#.into(),
            software_version: crate::VERSION.into(),
        }
    }

    pub(crate) fn state(index: u64, t_reset: f64) -> State {
        let mut s = State::zeros(4, 5, 6);
        for ((y, x, n), a) in s.amplitudes_e.indexed_iter_mut() {
            *a = (y * 100 + x * 10 + n) as f64 * 0.5;
        }
        s.release_count[[1, 2]] = 2;
        s.pending[[3, 4]] = crate::model::state::PENDING_MAX_AMPLITUDE;
        s.t_reset_unix_s = Some(t_reset);
        s.last_index = Some(index);
        s
    }

    /// The amplitudes go to the disk with direct I/O where the file system allows it
    /// and with ordinary writes where it does not (tmpfs): the same file bytes, the
    /// same state loaded back, and the values HDF5 itself reads. 300 x 301 x 6 float64
    /// are two 4 MiB blocks, the second ending in a partial 4096-byte page.
    #[test]
    fn direct_and_buffered_amplitudes_give_the_same_file() {
        let mut s = State::zeros(300, 301, 6);
        for (i, a) in s.amplitudes_e.iter_mut().enumerate() {
            *a = if i % 7 == 0 {
                0.0
            } else {
                (i as f64).sqrt() * 1e3
            };
        }
        s.release_count[[299, 300]] = 1;
        s.t_reset_unix_s = Some(1.0e9);
        s.last_index = Some(7);
        let m = meta(1, 7);
        let disk = tempfile::tempdir().unwrap();
        let p = save(disk.path(), &m, &s).unwrap();
        let (m2, back) = load(&p).unwrap();
        assert_eq!((m2, &back), (m.clone(), &s));
        let a: Array3<f64> = hdf5::File::open(&p)
            .map(h5io::close_on_exec)
            .unwrap()
            .dataset("amplitudes_e")
            .unwrap()
            .read()
            .unwrap();
        assert_eq!(a, s.amplitudes_e);
        if Path::new("/dev/shm").is_dir() {
            let shm = tempfile::tempdir_in("/dev/shm").unwrap();
            let q = save(shm.path(), &m, &s).unwrap();
            assert!(std::fs::read(&p).unwrap() == std::fs::read(&q).unwrap());
        }
    }

    #[test]
    fn round_trip_and_identical_skip() {
        let dir = tempfile::tempdir().unwrap();
        let (m, s) = (meta(2, 7), state(7, 1.77e9 + 0.25));
        let p = save(dir.path(), &m, &s).unwrap();
        assert_eq!(p, dir.path().join("det2/ckpt_det2_0000000007.h5"));
        let (m2, s2) = load(&p).unwrap();
        assert_eq!((m2, s2), (m.clone(), s.clone()));
        let mtime = std::fs::metadata(&p).unwrap().modified().unwrap();
        std::thread::sleep(std::time::Duration::from_millis(20));
        assert_eq!(save(dir.path(), &m, &s).unwrap(), p);
        assert_eq!(std::fs::metadata(&p).unwrap().modified().unwrap(), mtime);
        assert_eq!(find(dir.path(), DetectorId(2), 7), Some(p.clone()));
        assert_eq!(find(dir.path(), DetectorId(2), 8), None);
    }

    #[test]
    fn indices_longer_than_ten_digits_are_listed_in_order() {
        // FITS exposures without a sequence number: the index is the start in ms.
        let dir = tempfile::tempdir().unwrap();
        let (a, b) = (9_999_999_999u64, 1_772_323_707_916u64);
        for i in [b, a] {
            save(dir.path(), &meta(1, i), &state(i, 1.77e9)).unwrap();
        }
        let listed: Vec<u64> = list(dir.path(), DetectorId(1))
            .unwrap()
            .into_iter()
            .map(|(i, _)| i)
            .collect();
        assert_eq!(listed, vec![a, b]);
        assert!(find(dir.path(), DetectorId(1), b).is_some());
    }

    #[test]
    fn refuses_inconsistent_state() {
        let dir = tempfile::tempdir().unwrap();
        let mut s = state(7, 1.77e9);
        s.last_index = Some(6);
        let e = save(dir.path(), &meta(1, 7), &s).unwrap_err();
        assert_eq!(e.context.field.as_deref(), Some("exposure_index"));
        let mut s = state(7, 1.77e9);
        s.amplitudes_e[[0, 0, 0]] = f64::NAN;
        let e = save(dir.path(), &meta(1, 7), &s).unwrap_err();
        assert_eq!(e.context.field.as_deref(), Some("/amplitudes_e"), "{e}");
        let mut m = meta(1, 7);
        m.model_id = "0".repeat(64);
        let e = save(dir.path(), &m, &state(7, 1.77e9)).unwrap_err();
        assert_eq!(e.context.field.as_deref(), Some("model_id"));
        assert!(list(dir.path(), DetectorId(1)).unwrap().is_empty());
    }

    #[test]
    fn list_prune_and_clean() {
        let dir = tempfile::tempdir().unwrap();
        let d = DetectorId(3);
        // 10 checkpoints, 20 minutes apart: hours hold indices {0,1,2}, {3,4,5}, {6,7,8}, {9}.
        let t0 = 1_773_000_000.0 - 1_773_000_000.0 % 3600.0 + 60.0;
        for i in 0..10u64 {
            save(dir.path(), &meta(3, i), &state(i, t0 + i as f64 * 1200.0)).unwrap();
        }
        std::fs::write(
            detector_dir(dir.path(), d).join(".ckpt_det3_0000000010.h5.part"),
            b"x",
        )
        .unwrap();
        std::fs::write(detector_dir(dir.path(), d).join("notes.txt"), b"x").unwrap();
        let l = list(dir.path(), d).unwrap();
        assert_eq!(
            l.iter().map(|x| x.0).collect::<Vec<_>>(),
            (0..10).collect::<Vec<_>>()
        );
        let removed = prune(
            dir.path(),
            d,
            &Retention {
                keep_latest: 3,
                cadence: 1,
                ..Retention::default()
            },
        )
        .unwrap();
        let kept: Vec<u64> = list(dir.path(), d).unwrap().iter().map(|x| x.0).collect();
        assert_eq!(kept, [0, 3, 6, 7, 8, 9]);
        assert_eq!(removed.len(), 4);
        let removed = prune(
            dir.path(),
            d,
            &Retention {
                keep_latest: 2,
                keep_one_per_hour: false,
                cadence: 1,
                ..Retention::default()
            },
        )
        .unwrap();
        assert_eq!(removed.len(), 4);
        assert_eq!(clean_temporaries(dir.path()).unwrap(), 1);
        assert!(detector_dir(dir.path(), d).join("notes.txt").exists());
        assert_eq!(list(dir.path(), DetectorId(4)).unwrap(), vec![]);
    }

    /// Tails (off the cadence grid) go once a newer checkpoint exists; grid checkpoints
    /// thin hourly, daily, weekly with their age.
    #[test]
    fn retention_thins_with_age_and_drops_tails() {
        let r = Retention {
            keep_latest: 2,
            cadence: 4,
            ..Retention::default()
        };
        let day = 86_400.0;
        // Grid indices 3, 7, 11, ...; one exposure every 200 s for 60 days.
        let t0 = 1_000_000_000.0 - 1_000_000_000.0 % 604_800.0;
        let n = (60.0 * day / 200.0) as u64;
        let mut items: Vec<(u64, Option<f64>)> = (0..n)
            .filter(|&i| r.on_grid(i))
            .map(|i| (i, Some(t0 + i as f64 * 200.0)))
            .collect();
        // A tail in the middle, and the newest a tail.
        items.insert(10, (42, Some(t0 + 8400.0)));
        items.sort_by_key(|x| x.0);
        items.push((n, Some(t0 + n as f64 * 200.0)));
        let keep = r.keep(&items);
        let kept: Vec<(u64, f64)> = items
            .iter()
            .zip(&keep)
            .filter(|x| *x.1)
            .map(|(i, _)| (i.0, i.1.unwrap()))
            .collect();
        let t_new = kept.last().unwrap().1;
        assert_eq!(kept.last().unwrap().0, n, "the newest is kept");
        assert!(!kept.iter().any(|k| k.0 == 42), "a tail goes");
        let ages = |lo: f64, hi: f64| {
            kept.iter()
                .filter(|k| (lo..hi).contains(&(t_new - k.1)) && k.0 + 2 < n)
                .count()
        };
        // Besides the 2 newest: about 24 hourly within a day, 29 daily, weekly beyond.
        let hourly = ages(0.0, day);
        assert!((21..=25).contains(&hourly), "{hourly}");
        let daily = ages(day, 30.0 * day);
        assert!((28..=30).contains(&daily), "{daily}");
        let weekly = ages(30.0 * day, 61.0 * day);
        assert!((4..=6).contains(&weekly), "{weekly}");
        // Pruning after every checkpoint leaves the same set as pruning once.
        let mut held: Vec<(u64, Option<f64>)> = Vec::new();
        for it in &items {
            held.push(*it);
            let k = r.keep(&held);
            held = held
                .into_iter()
                .zip(k)
                .filter(|x| x.1)
                .map(|x| x.0)
                .collect();
        }
        assert_eq!(
            held.iter().map(|x| x.0).collect::<Vec<_>>(),
            kept.iter().map(|x| x.0).collect::<Vec<_>>()
        );
        // Two years of 4 x 10^5 exposures, default rule: the 20 newest (within the last
        // day), the other hours of that day, 29 days, about 100 weeks.
        let c = Retention::default().projected_count(400_000, 2.0 * 365.25 * day / 400_000.0);
        assert!((150..=190).contains(&c), "{c}");
    }
}
