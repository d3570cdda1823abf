//! Exact splits of a reprocessing: each detector's history processed per pixel tile by
//! independent jobs ([`run_tile`]), then one assembly ([`assemble`]) that builds the
//! whole-array output products and final checkpoints from the tiles.
//!
//! # The plan
//! A [`Plan`] (JSON, `WORK/plan.json`) fixes everything the jobs share: the
//! directories, the detectors found in the input, the tile grid, the model (its
//! canonical JSON: every job steps the same model even if the model file changes), the
//! processing time recorded in every output, and the checkpoint retention. Job `n` of
//! [`Plan::tasks`] is tile `n % tiles` of detector `n / tiles`.
//!
//! # Why the split is exact
//! A tile job steps the detector's whole history, exposure by exposure, through the
//! stage's own exposure path ([`crate::stage::exposure::step_exposure`]: same start
//! checkpoint, same order, same gap rule and bookkeeping; the tile is only the window it
//! reads and writes), and keeps only its tile's pixels. Products are read and written
//! through [`crate::product::format`], so FITS inputs give FITS outputs as in
//! `persist run`. Where a tile's pixels are computed
//! ([`Placement`]):
//! - a model whose pixels are independent ([`Model::is_pixel_local`]: no neighbour
//!   effect, no background estimated over the array) is stepped on the tile alone
//!   (`Crop` with no halo): a pixel-local model predicts any selection of its pixels,
//!   laid out anew, bit for bit as on the whole array;
//! - any other model is stepped on the whole array with the tile as its active pixels
//!   (`Frame`, [`crate::model::StepContext::active_pixels`]): the step advances the tile, and builds
//!   the response planes on the tile widened by the halo its effects declare
//!   ([`halo_px`], the sum of [`crate::model::effect::Effect::response_reach_px`]:
//!   `ipc` 1, `blooming` 0), plus the rows the early-release background samples.
//!   The whole-array parts of a step (the fluence deconvolution of `ipc`, which stops on
//!   an array-wide criterion; the background's sample) are computed as the whole run
//!   computes them. The halo pixels are computed and not kept.
//!
//! A crop with a halo (the tile and its neighbours' pixels, stepped as an array of
//! their own) is *not* exact for such a model: the background and the deconvolution
//! would see only the crop. `tests/split_exact.rs` shows that the assembled outputs
//! differ from a single run when the halo is too small, and are byte-identical with
//! the placement above.
//!
//! # Work files
//! Under `WORK/det{D}/`: per processed exposure `x{index:010}/t{k:03}.h5` (the tile's
//! `/current`, `/pflags`, `/flags` and a JSON `record` of the exposure), and per tile
//! `state_t{k:03}.h5` (its final state, the stage's bookkeeping and the list of
//! exposures processed). All are written atomically (temporary name, synced, renamed),
//! so a job killed half way leaves complete files or none; a rerun overwrites them.
//!
//! # Assembly
//! [`assemble`] checks that every tile of every detector finished with the same history
//! (same exposures, bookkeeping, reset time), then per exposure reads the input
//! product, fills the whole-array planes from the tiles, and writes the output product
//! with the stage's writer (validated against the schemas, `.NAME.part`, fsync, rename,
//! directory fsync; an output already published is left alone, as `persist run`
//! does), then the final checkpoint with the stage's checkpoint writer, prunes the
//! checkpoints by the plan's retention, and removes the detector's work files. It goes
//! through the stage's start-up first ([`crate::stage::startup`]: the directory lock,
//! held while it writes; stray temporaries removed).
//!
//! The split is for reprocessing a clean input: a product the stage would refuse or
//! quarantine (unreadable, outside the ICD, a duplicate index, not following the
//! history) stops the tile job with that product's error; `persist run` handles them.

use crate::checkpoint::{self, CheckpointMeta, Retention};
use crate::error::{Error, ErrorKind, Result};
use crate::h5io;
use crate::model::{Model, ModelParams, State};
use crate::product::fits::FitsConfig;
use crate::product::format;
use crate::product::{ExposureMeta, PersistencePlanes};
use crate::stage::exposure::{
    gap_before, output_attrs, step_exposure, Bookkeeping, ExposureStep, Window,
};
use crate::stage::run::file_digest;
use crate::timesplit::{Span, SpanStart, TimeSplit};
use crate::units::DetectorId;
use ndarray::{s, Array2, Array3, ArrayView2};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// `format` of a plan file.
pub const PLAN_FORMAT: &str = "persist.split-plan/1";
/// The plan's file name in the work directory.
pub const PLAN_FILE: &str = "plan.json";

/// Tiles per detector: `rows` x `cols` (`RxC` on the command line).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Grid {
    pub rows: usize,
    pub cols: usize,
}

impl Grid {
    pub fn count(&self) -> usize {
        self.rows * self.cols
    }

    /// Tile `k` (row-major) of an `ny` x `nx` array: rows `y0..y1`, columns `x0..x1`.
    /// Boundaries at `r ny / rows` (every tile at least one pixel when the grid fits).
    pub fn tile(&self, k: usize, ny: usize, nx: usize) -> Result<Rect> {
        if self.rows > ny || self.cols > nx {
            return Err(Error::new(
                ErrorKind::Usage,
                format!(
                    "tile grid {}x{} does not fit a {ny} x {nx} array",
                    self.rows, self.cols
                ),
            )
            .field("tiles"));
        }
        let (r, c) = (k / self.cols, k % self.cols);
        Ok(Rect {
            y0: r * ny / self.rows,
            y1: (r + 1) * ny / self.rows,
            x0: c * nx / self.cols,
            x1: (c + 1) * nx / self.cols,
        })
    }
}

impl std::str::FromStr for Grid {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        let (r, c) = s
            .split_once(['x', 'X'])
            .ok_or_else(|| format!("`{s}`: expected ROWSxCOLS, e.g. 2x2"))?;
        let n = |v: &str| {
            v.trim()
                .parse::<usize>()
                .ok()
                .filter(|&n| (1..=256).contains(&n))
                .ok_or_else(|| format!("`{s}`: rows and columns must be 1..=256"))
        };
        Ok(Grid {
            rows: n(r)?,
            cols: n(c)?,
        })
    }
}

/// A rectangle of pixels: rows `y0..y1`, columns `x0..x1`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Rect {
    pub y0: usize,
    pub y1: usize,
    pub x0: usize,
    pub x1: usize,
}

impl Rect {
    pub fn shape(&self) -> (usize, usize) {
        (self.y1 - self.y0, self.x1 - self.x0)
    }
    /// Widened by `h` pixels on every side, clipped to `ny` x `nx`.
    pub fn grow(&self, h: usize, ny: usize, nx: usize) -> Rect {
        Rect {
            y0: self.y0.saturating_sub(h),
            y1: (self.y1 + h).min(ny),
            x0: self.x0.saturating_sub(h),
            x1: (self.x1 + h).min(nx),
        }
    }
}

/// Where a tile's pixels are computed (module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Placement {
    /// The whole array is stepped with the tile as the active pixels.
    Frame,
    /// The tile widened by `halo_px` is stepped as an array of its own.
    Crop { halo_px: usize },
}

/// The placement that is exact for `model` (module docs).
pub fn placement(model: &Model) -> Placement {
    if model.is_pixel_local() {
        Placement::Crop { halo_px: 0 }
    } else {
        Placement::Frame
    }
}

/// How far the model's response hooks reach, in steps between 4-neighbours (the halo
/// the step builds around a tile's pixels); `None` when an effect does not say.
pub fn halo_px(model: &Model) -> Option<usize> {
    model.effects().iter().map(|e| e.response_reach_px()).sum()
}

/// Everything the jobs of one split share (module docs).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Plan {
    pub format: String,
    pub input: PathBuf,
    pub output: PathBuf,
    pub checkpoints: PathBuf,
    pub work: PathBuf,
    pub detectors: Vec<u8>,
    pub grid: Grid,
    pub model_json: String,
    pub model_id: String,
    pub processed_utc: String,
    pub allow_model_change: bool,
    pub keep_latest: usize,
    pub keep_one_per_hour: bool,
    /// Time spans of each detector ([`crate::timesplit`]); `None`: each detector's
    /// history in one piece.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub time: Option<TimeSplit>,
}

/// One job of a plan: a tile of a detector, over one time span (`None`: the whole
/// history after the start).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Job {
    pub det: DetectorId,
    pub span: Option<usize>,
    pub tile: usize,
}

impl Plan {
    /// A plan over the detectors found in `input` (their products' root attributes).
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        input: &Path,
        output: &Path,
        checkpoints: &Path,
        work: &Path,
        model: &Model,
        grid: Grid,
        processed_utc: String,
        retention: Retention,
        allow_model_change: bool,
    ) -> Result<Plan> {
        let abs = |p: &Path| std::path::absolute(p).map_err(|e| Error::io(p, e));
        let (input_abs, work_abs) = (abs(input)?, abs(work)?);
        if work_abs.starts_with(&input_abs) {
            return Err(Error::new(
                ErrorKind::Usage,
                "the work directory is inside the input directory: its files would be read as products",
            )
            .field("work")
            .path(work));
        }
        let mut detectors = std::collections::BTreeSet::new();
        for path in crate::stage::queue::candidates(input)? {
            detectors.insert(
                format::read_input_meta(&path, &FitsConfig::default())?
                    .detector
                    .0,
            );
        }
        if detectors.is_empty() {
            return Err(
                Error::new(ErrorKind::Usage, "no input products (*.h5, *.fits) found").path(input),
            );
        }
        Ok(Plan {
            format: PLAN_FORMAT.into(),
            input: input_abs,
            output: abs(output)?,
            checkpoints: abs(checkpoints)?,
            work: work_abs,
            detectors: detectors.into_iter().collect(),
            grid,
            model_json: model.params().canonical_json(),
            model_id: model.identity().to_string(),
            processed_utc,
            allow_model_change,
            keep_latest: retention.keep_latest,
            keep_one_per_hour: retention.keep_one_per_hour,
            time: None,
        })
    }

    /// Cut each detector's history into `n_spans` time spans ([`crate::timesplit`]),
    /// spans that start from zero stepping `warmup_s` of data first. With `from_start`,
    /// every detector starts from a zero state at its first product (its checkpoints are
    /// only used as the starts of later spans) and published outputs are rewritten.
    pub fn split_time(
        &mut self,
        model: &Model,
        n_spans: usize,
        warmup_s: f64,
        from_start: bool,
    ) -> Result<()> {
        if n_spans == 0 || !(warmup_s.is_finite() && warmup_s >= 0.0) {
            return Err(Error::new(
                ErrorKind::Usage,
                "time spans must be >= 1 and the warm-up a finite number of seconds >= 0",
            )
            .field("time-spans"));
        }
        let mut spans = BTreeMap::new();
        for &d in &self.detectors {
            let det = DetectorId::new(i64::from(d))
                .ok_or_else(|| Error::invalid("detectors", format!("{d}: must be 1..=6")))?;
            let products: BTreeMap<u64, ExposureMeta> = detector_products(&self.input, det)?
                .into_iter()
                .map(|(i, (_, m, _))| (i, m))
                .collect();
            let start = if from_start {
                None
            } else {
                checkpoint::list(&self.checkpoints, det)?.pop()
            };
            let start = start.as_ref().map(|(i, p)| (*i, p.as_path()));
            spans.insert(
                d,
                crate::timesplit::plan_detector(
                    model,
                    &self.checkpoints,
                    det,
                    &products,
                    start,
                    n_spans,
                    warmup_s,
                )?,
            );
        }
        self.time = Some(TimeSplit {
            spans_requested: n_spans,
            warmup_s,
            from_start,
            spans,
        });
        Ok(())
    }

    /// The time spans of `det` (`None`: not split in time).
    pub fn spans(&self, det: DetectorId) -> Option<&[Span]> {
        self.time
            .as_ref()
            .map(|t| t.spans.get(&det.0).map_or(&[][..], |v| v.as_slice()))
    }

    /// The jobs of the plan in task order: detector, then span, then tile.
    pub fn jobs(&self) -> Vec<Job> {
        let mut out = Vec::new();
        for &d in &self.detectors {
            let Some(det) = DetectorId::new(i64::from(d)) else {
                continue;
            };
            let spans: Vec<Option<usize>> = match self.spans(det) {
                None => vec![None],
                Some(s) => (0..s.len()).map(Some).collect(),
            };
            for span in spans {
                for tile in 0..self.grid.count() {
                    out.push(Job { det, span, tile });
                }
            }
        }
        out
    }

    /// Job `n` ([`Plan::jobs`]).
    pub fn job(&self, n: usize) -> Result<Job> {
        let jobs = self.jobs();
        jobs.get(n).copied().ok_or_else(|| {
            Error::new(
                ErrorKind::Usage,
                format!(
                    "task {n}: the plan has {} tasks (0..{})",
                    jobs.len(),
                    jobs.len()
                ),
            )
            .field("task")
        })
    }

    /// Number of tile jobs: detectors x tiles (x time spans).
    pub fn tasks(&self) -> usize {
        match &self.time {
            None => self.detectors.len() * self.grid.count(),
            Some(_) => self.jobs().len(),
        }
    }

    /// The (detector, tile) of job `n`.
    pub fn task(&self, n: usize) -> Result<(DetectorId, usize)> {
        self.job(n).map(|j| (j.det, j.tile))
    }

    /// The plan's model, checked against its recorded identity.
    pub fn model(&self) -> Result<Model> {
        let params = ModelParams::from_json(&self.model_json)
            .map_err(|e| Error::new(ErrorKind::Model, e).field("model_json"))?;
        let model = Model::new(params)?;
        if model.identity() != self.model_id {
            return Err(Error::new(
                ErrorKind::Model,
                "the model's identity differs from the plan's model_id",
            )
            .field("model_id"));
        }
        Ok(model)
    }

    pub fn retention(&self) -> Retention {
        Retention {
            keep_latest: self.keep_latest,
            keep_one_per_hour: self.keep_one_per_hour,
            ..Retention::default()
        }
    }

    /// Write `WORK/plan.json` (atomically); returns its path.
    pub fn save(&self) -> Result<PathBuf> {
        std::fs::create_dir_all(&self.work).map_err(|e| Error::io(&self.work, e))?;
        let path = self.work.join(PLAN_FILE);
        let text = serde_json::to_string_pretty(self)
            .map_err(|e| Error::new(ErrorKind::Io, e.to_string()).path(&path))?;
        crate::textfile::write_text(&path, &text)?;
        Ok(path)
    }

    pub fn load(path: &Path) -> Result<Plan> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        let plan: Plan = serde_json::from_str(&text)
            .map_err(|e| Error::invalid("plan", e.to_string()).path(path))?;
        if plan.format != PLAN_FORMAT {
            return Err(Error::invalid(
                "format",
                format!(
                    "`{}` is not a plan this build reads ({PLAN_FORMAT})",
                    plan.format
                ),
            )
            .path(path));
        }
        let g = plan.grid;
        if !(1..=256).contains(&g.rows) || !(1..=256).contains(&g.cols) {
            return Err(Error::invalid(
                "grid",
                format!("{}x{}: rows and columns must be 1..=256", g.rows, g.cols),
            )
            .path(path));
        }
        Ok(plan)
    }

    /// How FITS inputs are read: SPHEREx's keywords, the conversion their headers give
    /// (the defaults of `persist run`).
    pub fn fits(&self) -> FitsConfig {
        FitsConfig::default()
    }

    fn det_dir(&self, det: DetectorId) -> PathBuf {
        self.work.join(format!("det{}", det.0))
    }
    fn part_path(&self, det: DetectorId, index: u64, tile: usize) -> PathBuf {
        self.det_dir(det)
            .join(format!("x{index:010}"))
            .join(format!("t{tile:03}.h5"))
    }
    fn state_path(&self, det: DetectorId, span: Option<usize>, tile: usize) -> PathBuf {
        match span {
            None => self.det_dir(det).join(format!("state_t{tile:03}.h5")),
            Some(k) => self
                .det_dir(det)
                .join(format!("state_s{k:03}_t{tile:03}.h5")),
        }
    }
}

/// What one exposure of a tile job recorded (the same in every tile of a detector).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ExposureRecord {
    pub exposure_index: u64,
    pub input: PathBuf,
    pub t_meas_s: Option<f64>,
    pub previous_index: Option<u64>,
    pub history_incomplete: bool,
}

/// What a tile job finished with (the same in every tile of a detector except `tile`
/// and `rect`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TileRecord {
    pub detector: u8,
    pub tile: usize,
    pub rect: Rect,
    /// The whole array's shape.
    pub shape: (usize, usize),
    /// The checkpoint it started from (exposure index), if any.
    pub started_from: Option<u64>,
    pub exposures: Vec<ExposureRecord>,
    /// The stage's bookkeeping after the last exposure (`stage_json` of the checkpoint).
    pub stage_json: String,
    pub t_reset_unix_s: Option<f64>,
    pub last_index: Option<u64>,
}

/// A product of a detector: its file, its metadata, and whether its index is a start
/// time ([`format::read_input_sequence`]).
type Product = (PathBuf, ExposureMeta, bool);

/// The detector's products in `input`, by exposure index (a repeated index is an error:
/// the split needs a clean input).
fn detector_products(input: &Path, det: DetectorId) -> Result<BTreeMap<u64, Product>> {
    let mut out: BTreeMap<u64, Product> = BTreeMap::new();
    for path in crate::stage::queue::candidates(input)? {
        let (meta, by_start_time) = format::read_input_sequence(&path, &FitsConfig::default())?;
        if meta.detector != det {
            continue;
        }
        let index = meta.exposure_index;
        if let Some((first, _, _)) = out.get(&index) {
            return Err(Error::new(
                ErrorKind::Sequence,
                format!(
                    "exposure {index} of detector {} also in {}: the split needs one product per exposure (`persist run` sorts duplicates out)",
                    det.0,
                    first.display()
                ),
            )
            .path(&path)
            .field("exposure_index"));
        }
        out.insert(index, (path, meta, by_start_time));
    }
    Ok(out)
}

/// The newest checkpoint of `det` (as `persist run` starts from), checked against the
/// model; with its bookkeeping.
fn start_state(
    plan: &Plan,
    model: &Model,
    det: DetectorId,
    span: Option<&Span>,
) -> Result<Option<(State, Bookkeeping)>> {
    let from_start = plan.time.as_ref().is_some_and(|t| t.from_start);
    let path = match span.map(|s| &s.start) {
        Some(SpanStart::Warmup { .. }) => return Ok(None),
        Some(SpanStart::Checkpoint { index }) => Some(
            checkpoint::find(&plan.checkpoints, det, *index).ok_or_else(|| {
                Error::new(
                    ErrorKind::Checkpoint,
                    format!("the plan's start checkpoint {index} is gone: write the plan again"),
                )
                .path(checkpoint::path_for(&plan.checkpoints, det, *index))
                .detector(det)
            })?,
        ),
        _ if from_start => None,
        _ => checkpoint::list(&plan.checkpoints, det)?
            .pop()
            .map(|(_, p)| p),
    };
    let Some(path) = path else {
        return Ok(None);
    };
    let (meta, state) = checkpoint::load(&path)?;
    if meta.model_id != model.identity() && !plan.allow_model_change {
        return Err(Error::new(
            ErrorKind::Checkpoint,
            format!(
                "made with model {}, the plan uses {}; plan with --allow-model-change to continue from it",
                meta.model_name,
                model.params().name
            ),
        )
        .path(&path));
    }
    crate::stage::run::resume_parts(&path, state, &meta, model).map(Some)
}

fn crop_state(s: &State, r: Rect) -> State {
    State {
        amplitudes_e: s
            .amplitudes_e
            .slice(s![r.y0..r.y1, r.x0..r.x1, ..])
            .to_owned(),
        release_count: s.release_count.slice(s![r.y0..r.y1, r.x0..r.x1]).to_owned(),
        pending: s.pending.slice(s![r.y0..r.y1, r.x0..r.x1]).to_owned(),
        t_reset_unix_s: s.t_reset_unix_s,
        last_index: s.last_index,
    }
}

/// Where one tile is computed: the array's shape, the tile, the region stepped, the
/// tile inside the region, and the active pixels of the region (none: all).
struct Geometry {
    full: (usize, usize),
    rect: Rect,
    region: Rect,
    core: Rect,
    mask: Option<Vec<bool>>,
}

impl Geometry {
    fn new(grid: Grid, tile: usize, full: (usize, usize), place: Placement) -> Result<Self> {
        let (ny, nx) = full;
        let rect = grid.tile(tile, ny, nx)?;
        let region = match place {
            Placement::Frame => Rect {
                y0: 0,
                y1: ny,
                x0: 0,
                x1: nx,
            },
            Placement::Crop { halo_px } => rect.grow(halo_px, ny, nx),
        };
        let core = Rect {
            y0: rect.y0 - region.y0,
            y1: rect.y1 - region.y0,
            x0: rect.x0 - region.x0,
            x1: rect.x1 - region.x0,
        };
        let mask = (region.shape() != rect.shape()).then(|| {
            let (ry, rx) = region.shape();
            let mut m = vec![false; ry * rx];
            for y in core.y0..core.y1 {
                m[y * rx + core.x0..y * rx + core.x1].fill(true);
            }
            m
        });
        Ok(Geometry {
            full,
            rect,
            region,
            core,
            mask,
        })
    }
}

/// Options of [`run_tile_with`] beyond the plan.
#[derive(Debug, Clone, Copy, Default)]
pub struct TileOptions {
    /// Override the exact placement ([`placement`]): for tests that show what a wrong
    /// one does.
    pub placement: Option<Placement>,
}

/// Run job `task` of the plan: one tile of one detector (module docs).
pub fn run_tile(plan: &Plan, model: &Model, task: usize) -> Result<TileRecord> {
    run_tile_with(plan, model, task, TileOptions::default())
}

/// [`run_tile`] with options.
pub fn run_tile_with(
    plan: &Plan,
    model: &Model,
    task: usize,
    opts: TileOptions,
) -> Result<TileRecord> {
    let Job {
        det,
        span: span_k,
        tile,
    } = plan.job(task)?;
    let span = span_k.and_then(|k| plan.spans(det).and_then(|s| s.get(k)));
    let products = detector_products(&plan.input, det)?;
    let (mut state, mut book) = match start_state(plan, model, det, span)? {
        Some((s, b)) => (Some(s), b),
        None => (None, Bookkeeping::default()),
    };
    let started_from = state.as_ref().and_then(|s| s.last_index);
    // A span steps from its start and publishes from its first exposure to its last.
    let from = match span.map(|s| &s.start) {
        Some(SpanStart::Warmup { from, .. }) => *from,
        _ => started_from.map_or(0, |l| l + 1),
    };
    let (publish_from, last) = span.map_or((0, u64::MAX), |s| (s.first, s.last));
    let place = opts.placement.unwrap_or_else(|| placement(model));
    let fits = plan.fits();
    // Fixed by the first exposure, with the state of the region it steps.
    let mut work: Option<(Geometry, State)> = None;
    let mut exposures = Vec::new();
    let mut planes = PersistencePlanes {
        current_e_per_s: Array2::zeros((0, 0)),
        flags: Array2::zeros((0, 0)),
    };
    for (&index, (path, queued, by_start_time)) in products.range(from..=last.max(from)) {
        let fail = |e: Error| e.path(path).detector(det).exposure(index);
        let resumed = work.as_ref().map_or(started_from, |(_, s)| s.last_index);
        book.admit_order(resumed.is_some(), *by_start_time)
            .map_err(|why| fail(Error::new(ErrorKind::Sequence, why).field("exposure_index")))?;
        let digest = file_digest(path).map_err(fail)?;
        let mut read = format::read_input(path, &fits).map_err(fail)?;
        if read.exposure.meta != *queued {
            return Err(fail(Error::new(
                ErrorKind::NotReady,
                "changed while the job ran; run the job again",
            )));
        }
        let shape = read.exposure.image.dim();
        if work.is_none() {
            let g = Geometry::new(plan.grid, tile, shape, place)?;
            let st = match state.take() {
                Some(s) if s.shape() == shape => crop_state(&s, g.region),
                Some(s) => {
                    return Err(fail(Error::invalid(
                        "image",
                        format!(
                            "shape {shape:?} differs from the checkpoint's {:?}",
                            s.shape()
                        ),
                    )))
                }
                None => {
                    let (ry, rx) = g.region.shape();
                    model.new_state(ry, rx)
                }
            };
            work = Some((g, st));
        }
        let Some((g, st)) = work.as_mut() else {
            return Err(fail(Error::new(ErrorKind::Usage, "no geometry")));
        };
        if shape != g.full {
            return Err(fail(Error::invalid(
                "image",
                format!("shape {shape:?} differs from the detector's {:?}", g.full),
            )));
        }
        // The stage's own step: in a batch every gap is crossed (crate::stage::run).
        let step = ExposureStep {
            window: Window {
                rows: g.region.y0..g.region.y1,
                cols: g.region.x0..g.region.x1,
                active: g.mask.as_deref(),
            },
            gap_before: gap_before(&book, st.last_index, index),
            digest,
        };
        let stepped = step_exposure(model, st, &mut book, &mut read.exposure, step, &mut planes)
            .map_err(fail)?;
        if index < publish_from {
            // The warm-up (or the replay up to the span): stepped, not published.
            continue;
        }
        let record = ExposureRecord {
            exposure_index: index,
            input: path.clone(),
            t_meas_s: stepped.summary.t_meas_s,
            previous_index: stepped.summary.previous_index,
            history_incomplete: stepped.history_incomplete,
        };
        let (core, rect) = (g.core, g.rect);
        let c = s![core.y0..core.y1, core.x0..core.x1];
        write_part(
            &plan.part_path(det, index, tile),
            &record,
            planes.current_e_per_s.slice(c).to_owned().view(),
            planes.flags.slice(c),
            read.exposure
                .flags
                .slice(s![rect.y0..rect.y1, rect.x0..rect.x1]),
        )?;
        exposures.push(record);
    }
    let stage_json = serde_json::to_string(&book)
        .map_err(|e| Error::new(ErrorKind::Checkpoint, format!("bookkeeping: {e}")))?;
    let empty = Rect {
        y0: 0,
        y1: 0,
        x0: 0,
        x1: 0,
    };
    let (shape, rect) = work
        .as_ref()
        .map_or(((0, 0), empty), |(g, _)| (g.full, g.rect));
    let record = TileRecord {
        detector: det.0,
        tile,
        rect,
        shape,
        started_from,
        exposures,
        stage_json,
        t_reset_unix_s: work.as_ref().and_then(|(_, s)| s.t_reset_unix_s),
        last_index: work.as_ref().and_then(|(_, s)| s.last_index),
    };
    let kept = work.as_ref().map(|(g, s)| crop_state(s, g.core));
    write_state(&plan.state_path(det, span_k, tile), &record, kept.as_ref())?;
    Ok(record)
}

fn record_attr<T: Serialize>(file: &hdf5::File, value: &T) -> Result<()> {
    let text = serde_json::to_string(value)
        .map_err(|e| Error::new(ErrorKind::Io, e.to_string()).field("record"))?;
    h5io::attr_str(file, "record", &text)
}

fn read_record<T: serde::de::DeserializeOwned>(file: &hdf5::File, path: &Path) -> Result<T> {
    let text = file
        .attr("record")
        .and_then(|a| a.read_scalar::<hdf5::types::VarLenUnicode>())
        .map_err(|e| Error::from(e).field("record").path(path))?;
    serde_json::from_str(text.as_str())
        .map_err(|e| Error::invalid("record", e.to_string()).path(path))
}

fn mkdir_for(path: &Path) -> Result<()> {
    let dir = path.parent().unwrap_or(Path::new("."));
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))
}

/// Publish a work file (module docs): the JSON `record` attribute, then the datasets
/// `data` writes; validated by reading the record back.
fn publish_work<R>(
    path: &Path,
    record: &R,
    data: impl FnOnce(&hdf5::File) -> Result<()>,
) -> Result<()>
where
    R: Serialize + serde::de::DeserializeOwned + PartialEq,
{
    mkdir_for(path)?;
    h5io::publish(
        path,
        |tmp| {
            let f = h5io::create(tmp)?;
            record_attr(&f, record)?;
            data(&f)?;
            f.close()?;
            Ok(())
        },
        |tmp| {
            let f = h5io::open_as(tmp, path)?;
            let r: R = read_record(&f, path)?;
            (r == *record).then_some(()).ok_or_else(|| {
                Error::invalid("record", "read back differs from what was written").path(path)
            })
        },
    )
}

/// `write_plain` with the dataset named in the error.
fn plain<T: hdf5::H5Type + Clone, D: ndarray::Dimension>(
    f: &hdf5::File,
    name: &str,
    data: ndarray::ArrayView<'_, T, D>,
) -> Result<()> {
    h5io::write_plain(f, name, data).map_err(|e| Error::from(e).field(format!("/{name}")))
}

fn write_part(
    path: &Path,
    record: &ExposureRecord,
    current: ArrayView2<'_, f32>,
    pflags: ArrayView2<'_, u8>,
    flags: ArrayView2<'_, u32>,
) -> Result<()> {
    publish_work(path, record, |f| {
        plain(f, "current", current)?;
        plain(f, "pflags", pflags)?;
        plain(f, "flags", flags)
    })
}

fn write_state(path: &Path, record: &TileRecord, state: Option<&State>) -> Result<()> {
    publish_work(path, record, |f| match state {
        Some(s) => {
            plain(f, "amplitudes_e", s.amplitudes_e.view())?;
            plain(f, "release_count", s.release_count.view())?;
            plain(f, "pending", s.pending.view())
        }
        None => Ok(()),
    })
}

fn read_plane<T: hdf5::H5Type>(file: &hdf5::File, name: &str, path: &Path) -> Result<Array2<T>> {
    file.dataset(name)
        .and_then(|d| d.read::<T, ndarray::Ix2>())
        .map_err(|e| Error::from(e).field(format!("/{name}")).path(path))
}

/// What [`assemble`] did for one detector.
#[derive(Debug, Clone, Default, Serialize)]
pub struct Assembled {
    pub detector: u8,
    /// Output products written (an output already published is left alone).
    pub written: usize,
    pub already_published: usize,
    /// The final checkpoint, when any exposure was processed.
    pub checkpoint: Option<PathBuf>,
}

/// Build the whole-array outputs and final checkpoints from the tiles of every detector
/// of the plan (module docs). With `keep_work`, the work files stay.
pub fn assemble(plan: &Plan, model: &Model, keep_work: bool) -> Result<Vec<Assembled>> {
    // The stage's start-up: never alongside a `persist run` on the same directories.
    let _started = crate::stage::startup::start(
        &[&plan.output, &plan.checkpoints],
        crate::stage::startup::Startup {
            lock: true,
            signals: false,
        },
    )?;
    // Every tile of every detector finished with one history, before anything is
    // published.
    let mut loaded = Vec::new();
    for &d in &plan.detectors {
        let det = DetectorId::new(i64::from(d))
            .ok_or_else(|| Error::invalid("detectors", format!("{d}: must be 1..=6")))?;
        let spans: Vec<Option<usize>> = match plan.spans(det) {
            None => vec![None],
            Some(s) => (0..s.len()).map(Some).collect(),
        };
        let mut per_span = Vec::with_capacity(spans.len());
        for k in spans {
            per_span.push((k, load_tiles(plan, det, k)?));
        }
        loaded.push((det, per_span));
    }
    let mut done = Vec::new();
    for (det, per_span) in &loaded {
        let mut total = Assembled {
            detector: det.0,
            ..Default::default()
        };
        // In time order: each exact span's final checkpoint is published after its
        // outputs, and before the next span's.
        for (k, tiles) in per_span {
            let span = k.and_then(|k| plan.spans(*det).and_then(|s| s.get(k)));
            let a = assemble_detector(plan, model, *det, span, tiles)?;
            total.written += a.written;
            total.already_published += a.already_published;
            total.checkpoint = a.checkpoint.or(total.checkpoint);
        }
        done.push(total);
    }
    drop(loaded);
    if !keep_work {
        for &d in &plan.detectors {
            let dir = plan.work.join(format!("det{d}"));
            std::fs::remove_dir_all(&dir).map_err(|e| Error::io(&dir, e))?;
        }
    }
    Ok(done)
}

/// A detector's tiles: (state file, open file, record), all with tile 0's history.
type Tiles = Vec<(PathBuf, hdf5::File, TileRecord)>;

fn load_tiles(plan: &Plan, det: DetectorId, span: Option<usize>) -> Result<Tiles> {
    let n = plan.grid.count();
    let mut tiles = Vec::with_capacity(n);
    for k in 0..n {
        let path = plan.state_path(det, span, k);
        let file = h5io::open(&path).map_err(|e| {
            Error::new(
                e.kind,
                format!(
                    "tile {k} of detector {}{} has not finished: {}",
                    det.0,
                    span.map_or(String::new(), |s| format!(" (time span {s})")),
                    e.message
                ),
            )
            .path(&path)
        })?;
        let record: TileRecord = read_record(&file, &path)?;
        tiles.push((path, file, record));
    }
    let first = tiles[0].2.clone();
    for (path, _, r) in &tiles[1..] {
        let same = r.exposures == first.exposures
            && r.stage_json == first.stage_json
            && r.shape == first.shape
            && r.started_from == first.started_from
            && r.last_index == first.last_index
            && r.t_reset_unix_s.map(f64::to_bits) == first.t_reset_unix_s.map(f64::to_bits);
        if !same {
            return Err(Error::new(
                ErrorKind::Sequence,
                "this tile processed another history than tile 0 (the input changed between the jobs?): run the jobs again",
            )
            .path(path)
            .detector(det));
        }
    }
    Ok(tiles)
}

fn assemble_detector(
    plan: &Plan,
    model: &Model,
    det: DetectorId,
    span: Option<&Span>,
    tiles: &Tiles,
) -> Result<Assembled> {
    let first = tiles[0].2.clone();
    let mut out = Assembled {
        detector: det.0,
        ..Default::default()
    };
    if first.exposures.is_empty() {
        return Ok(out);
    }
    let (ny, nx) = first.shape;
    let attrs_of = |r: &ExposureRecord, planes: &PersistencePlanes| {
        let warmup = span.and_then(Span::warmup_attrs);
        output_attrs(
            model,
            r.t_meas_s,
            r.previous_index,
            &plan.processed_utc,
            planes,
            warmup,
        )
    };
    let fits = plan.fits();
    let rewrite = plan.time.as_ref().is_some_and(|t| t.from_start);
    std::fs::create_dir_all(&plan.output).map_err(|e| Error::io(&plan.output, e))?;
    for r in &first.exposures {
        let out_path = plan.output.join(r.input.file_name().unwrap_or_default());
        if out_path.exists() && !rewrite {
            out.already_published += 1;
            continue;
        }
        let mut read = format::read_input(&r.input, &fits)?;
        let exposure = &mut read.exposure;
        if exposure.image.dim() != (ny, nx) {
            return Err(Error::invalid("image", "shape differs from the tiles'").path(&r.input));
        }
        let mut planes = PersistencePlanes {
            current_e_per_s: Array2::zeros((ny, nx)),
            flags: Array2::zeros((ny, nx)),
        };
        for (_, _, t) in tiles {
            let part = plan.part_path(det, r.exposure_index, t.tile);
            let f = h5io::open(&part)?;
            let rec: ExposureRecord = read_record(&f, &part)?;
            if rec != *r {
                return Err(
                    Error::invalid("record", "differs from the tile's state record").path(&part),
                );
            }
            let rect = t.rect;
            let win = s![rect.y0..rect.y1, rect.x0..rect.x1];
            let current: Array2<f32> = read_plane(&f, "current", &part)?;
            let pflags: Array2<u8> = read_plane(&f, "pflags", &part)?;
            let flags: Array2<u32> = read_plane(&f, "flags", &part)?;
            for (name, d) in [
                ("/current", current.dim()),
                ("/pflags", pflags.dim()),
                ("/flags", flags.dim()),
            ] {
                if d != rect.shape() {
                    return Err(Error::invalid(
                        name,
                        format!("shape {d:?}, the tile is {:?}", rect.shape()),
                    )
                    .path(&part));
                }
            }
            planes.current_e_per_s.slice_mut(win).assign(&current);
            planes.flags.slice_mut(win).assign(&pflags);
            exposure.flags.slice_mut(win).assign(&flags);
        }
        let attrs = attrs_of(r, &planes);
        if let Some(staged) =
            format::stage_output(&r.input, &out_path, &read, &planes, &attrs, &fits)?
        {
            staged.commit()?;
        }
        out.written += 1;
    }
    if span.is_some_and(|s| !s.exact()) {
        // Its state lacks the carry-in from before the warm-up: not a checkpoint.
        return Ok(out);
    }
    let mut state = model.new_state(ny, nx);
    for (path, f, t) in tiles {
        let rect = t.rect;
        let win = s![rect.y0..rect.y1, rect.x0..rect.x1];
        let a: Array3<f64> = f
            .dataset("amplitudes_e")
            .and_then(|d| d.read::<f64, ndarray::Ix3>())
            .map_err(|e| Error::from(e).field("/amplitudes_e").path(path))?;
        let rc: Array2<u8> = read_plane(f, "release_count", path)?;
        let p: Array2<u8> = read_plane(f, "pending", path)?;
        let (ty, tx) = rect.shape();
        if a.dim() != (ty, tx, model.n_terms()) || rc.dim() != (ty, tx) || p.dim() != (ty, tx) {
            return Err(Error::invalid("state", "shapes differ from the tile").path(path));
        }
        state
            .amplitudes_e
            .slice_mut(s![rect.y0..rect.y1, rect.x0..rect.x1, ..])
            .assign(&a);
        state.release_count.slice_mut(win).assign(&rc);
        state.pending.slice_mut(win).assign(&p);
    }
    state.t_reset_unix_s = first.t_reset_unix_s;
    state.last_index = first.last_index;
    let meta = CheckpointMeta {
        detector: det,
        exposure_index: first.last_index.unwrap_or(0),
        model_id: model.identity().to_string(),
        model_name: model.params().name.clone(),
        model_json: model.params().canonical_json(),
        stage_json: first.stage_json.clone(),
        software_version: crate::VERSION.to_string(),
    };
    out.checkpoint = Some(checkpoint::save(&plan.checkpoints, &meta, &state)?);
    checkpoint::prune(&plan.checkpoints, det, &plan.retention())?;
    Ok(out)
}
