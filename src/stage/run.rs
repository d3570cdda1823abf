//! The stage loop: for each detector, in exposure-index order,
//! read -> `Model::step` -> publish the output -> checkpoint.
//!
//! Detectors run in parallel (rayon), pixels in parallel inside the step. HDF5 calls are
//! serialised by the library's global lock, so only the computation overlaps.
//!
//! Resumption: each detector starts from the newest checkpoint (or the one named with
//! `--from-checkpoint`), and steps every later exposure. An exposure whose output is
//! already published is stepped (the state needs it) but its output is not rewritten,
//! except when reprocessing from a named checkpoint. Outputs are published before the
//! checkpoint that includes them, so a crash between the two replays one exposure.
//!
//! A checkpoint is checked and written (HDF5, straight from the state in memory) on the
//! detector's own thread; its publication (fsync, rename, directory fsync) and the
//! pruning of old checkpoints then run on a helper thread while the next exposures are
//! read, stepped and published. Checkpoints of a detector are published in order (the
//! next one waits for the previous publication), and always after the outputs they
//! include; a failed publication is reported and retried at the end of the stream.
//!
//! History incomplete (bit 4): when an exposure is missing (its index is skipped) or
//! was rejected, the exposures after it are marked until the largest amplitude the
//! missing one could have added -- the knot table's maximum, added just before the next
//! good exposure started -- has decayed below the low threshold (65,300 s for the
//! default model). The deadline is carried in the checkpoint.

use crate::checkpoint::{self, CheckpointMeta, Retention};
use crate::error::{Error, ErrorKind, Result};
use crate::model::{Input, Model, Output, State, StepSummary};
use crate::product::{self, Exposure, PersistenceAttrs, PersistencePlanes};
use crate::stage::queue::{self, Entry};
use crate::units::DetectorId;
use ndarray::Array2;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// Everything a run needs.
#[derive(Debug, Clone)]
pub struct RunConfig {
    pub input: PathBuf,
    pub output: PathBuf,
    pub checkpoints: PathBuf,
    pub model: Model,
    /// Reprocess one detector from this checkpoint (rewriting its later outputs).
    pub from_checkpoint: Option<(DetectorId, u64)>,
    /// Continue from checkpoints made with another model.
    pub allow_model_change: bool,
    /// Write a checkpoint every this many exposures (>= 1), and always at the end.
    pub checkpoint_every: u64,
    pub retention: Retention,
    /// Recorded as the processing time in every output of this run.
    pub processed_utc: String,
}

/// What happened to one exposure.
#[derive(Debug, Clone, Serialize)]
pub struct ExposureReport {
    pub detector: u8,
    pub exposure_index: u64,
    pub path: PathBuf,
    pub summary: StepSummary,
    pub history_incomplete: bool,
    /// false when an identical-key output was already published and left alone.
    pub written: bool,
}

#[derive(Debug, Default)]
pub struct RunReport {
    pub exposures: Vec<ExposureReport>,
    pub errors: Vec<Error>,
    pub ignored_copies: Vec<PathBuf>,
}

/// The stage's own bookkeeping carried in each checkpoint (`stage_json`).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Bookkeeping {
    /// Mark outputs "history incomplete" while their mid-exposure time is before this.
    pub history_incomplete_until_unix_s: Option<f64>,
    /// Inclusive ranges of exposure indices the history crossed without them (missing
    /// or rejected): a product for one of them that turns up later is late.
    #[serde(default)]
    pub crossed: Vec<(u64, u64)>,
}

impl Bookkeeping {
    pub fn was_crossed(&self, index: u64) -> bool {
        self.crossed.iter().any(|&(a, b)| (a..=b).contains(&index))
    }
}

/// The processing time to record: `SOURCE_DATE_EPOCH` (reproducible runs) or now.
pub fn processing_time() -> String {
    let t = std::env::var("SOURCE_DATE_EPOCH")
        .ok()
        .and_then(|s| s.trim().parse::<i64>().ok())
        .and_then(|s| chrono::DateTime::<chrono::Utc>::from_timestamp(s, 0))
        .unwrap_or_else(chrono::Utc::now);
    t.to_rfc3339_opts(chrono::SecondsFormat::Micros, true)
}

/// Process every product in `cfg.input`.
pub fn run(cfg: &RunConfig, on_exposure: &(dyn Fn(&ExposureReport) + Sync)) -> RunReport {
    let mut report = RunReport::default();
    for dir in [&cfg.output, &cfg.checkpoints] {
        if let Err(e) = std::fs::create_dir_all(dir) {
            report.errors.push(Error::io(dir, e));
            return report;
        }
    }
    let files = match queue::candidates(&cfg.input) {
        Ok(f) => f,
        Err(e) => {
            report.errors.push(e);
            return report;
        }
    };
    let plan = queue::plan(&files, product::read::read_meta);
    report.errors.extend(plan.errors);
    report.ignored_copies = plan.ignored_copies;
    let results: Vec<(Vec<ExposureReport>, Vec<Error>)> = plan
        .detectors
        .into_par_iter()
        .map(|(det, entries)| {
            let mut d = Detector::new(cfg, det, on_exposure);
            d.run(&entries);
            (d.reports, d.errors)
        })
        .collect();
    for (r, e) in results {
        report.exposures.extend(r);
        report.errors.extend(e);
    }
    report
}

/// Why one exposure was not completed.
enum Failure {
    /// The input was refused; the state is unchanged; the stage goes on.
    Input(Error),
    /// Publishing failed after the state advanced; this detector stops.
    Output(Error),
}

/// One detector's history being processed.
struct Detector<'a> {
    cfg: &'a RunConfig,
    det: DetectorId,
    on_exposure: &'a (dyn Fn(&ExposureReport) + Sync),
    reports: Vec<ExposureReport>,
    errors: Vec<Error>,
    /// The last checkpoint's publication (sync, rename, prune), running on its own
    /// thread while the next exposures are processed.
    publishing: Option<std::thread::JoinHandle<Result<()>>>,
}

impl<'a> Detector<'a> {
    fn new(
        cfg: &'a RunConfig,
        det: DetectorId,
        on_exposure: &'a (dyn Fn(&ExposureReport) + Sync),
    ) -> Self {
        Detector {
            cfg,
            det,
            on_exposure,
            reports: Vec::new(),
            errors: Vec::new(),
            publishing: None,
        }
    }

    /// The state to start from, if any checkpoint applies.
    fn start(&self) -> Result<Option<(State, Bookkeeping)>> {
        let cfg = self.cfg;
        let path = match cfg.from_checkpoint {
            Some((d, index)) if d == self.det => {
                Some(checkpoint::find(&cfg.checkpoints, d, index).ok_or_else(|| {
                    Error::new(
                        ErrorKind::Checkpoint,
                        format!("no checkpoint for detector {d} at exposure {index}"),
                    )
                    .path(&cfg.checkpoints)
                })?)
            }
            _ => checkpoint::list(&cfg.checkpoints, self.det)?
                .pop()
                .map(|(_, p)| p),
        };
        let Some(path) = path else { return Ok(None) };
        let (meta, state) = checkpoint::load(&path)?;
        if meta.model_id != cfg.model.identity() && !cfg.allow_model_change {
            return Err(Error::new(
                ErrorKind::Checkpoint,
                format!(
                    "made with model {} ({}), this run uses {} ({}); pass --allow-model-change to continue from it",
                    meta.model_name,
                    &meta.model_id[..meta.model_id.len().min(12)],
                    cfg.model.params().name,
                    &cfg.model.identity()[..12],
                ),
            )
            .path(&path));
        }
        if state.n_terms() != cfg.model.n_terms() {
            return Err(Error::new(
                ErrorKind::Checkpoint,
                format!(
                    "holds {} terms, the model has {}",
                    state.n_terms(),
                    cfg.model.n_terms()
                ),
            )
            .path(&path));
        }
        let book: Bookkeeping = serde_json::from_str(&meta.stage_json).map_err(|e| {
            Error::new(ErrorKind::Checkpoint, format!("stage_json: {e}")).path(&path)
        })?;
        Ok(Some((state, book)))
    }

    fn run(&mut self, entries: &[Entry]) {
        let (mut state, mut book) = match self.start() {
            Ok(Some((s, b))) => (Some(s), b),
            Ok(None) => (None, Bookkeeping::default()),
            Err(e) => {
                self.errors.push(e.detector(self.det));
                return;
            }
        };
        let reprocess = matches!(self.cfg.from_checkpoint, Some((d, _)) if d == self.det);
        let mut gap_before = false;
        let mut unsaved = 0u64;
        let mut buffers: Option<PersistencePlanes> = None;
        for entry in entries {
            let index = entry.meta.exposure_index;
            let last = state.as_ref().and_then(|s| s.last_index);
            if let Some(l) = last.filter(|&l| index <= l) {
                if book.was_crossed(index) {
                    // Its place in the history was passed as missing or rejected.
                    self.errors.push(
                        Error::new(
                            ErrorKind::Sequence,
                            format!(
                                "arrived after its gap was crossed (exposure {l} already processed): refused (late product)"
                            ),
                        )
                        .path(&entry.path)
                        .field("exposure_index")
                        .detector(self.det)
                        .exposure(index),
                    );
                }
                continue; // otherwise already part of the state we resumed from
            }
            if last.is_some_and(|l| index != l + 1) {
                gap_before = true;
            }
            match self.one(
                entry,
                &mut state,
                &mut book,
                &mut buffers,
                gap_before,
                reprocess,
            ) {
                Ok(report) => {
                    gap_before = false;
                    (self.on_exposure)(&report);
                    self.reports.push(report);
                    unsaved += 1;
                    if unsaved >= self.cfg.checkpoint_every.max(1) {
                        if let Some(s) = &state {
                            match self.save(s, &book) {
                                Ok(()) => unsaved = 0,
                                Err(e) => self.errors.push(e),
                            }
                        }
                    }
                }
                Err(Failure::Input(e)) => {
                    gap_before = true;
                    self.errors
                        .push(e.path(&entry.path).detector(self.det).exposure(index));
                }
                Err(Failure::Output(e)) => {
                    // The state already holds this exposure but its output is not
                    // published: stop this detector without a checkpoint, so that the
                    // next run replays from the last checkpoint.
                    self.errors.push(e.detector(self.det).exposure(index));
                    self.finish_publishing();
                    return;
                }
            }
        }
        let last_failed = !self.finish_publishing();
        if unsaved > 0 || last_failed {
            if let Some(s) = &state {
                if let Err(e) = self.save(s, &book) {
                    self.errors.push(e);
                }
                self.finish_publishing();
            }
        }
    }

    /// Wait for the last checkpoint's publication; false if it failed (the error is
    /// recorded).
    fn finish_publishing(&mut self) -> bool {
        let Some(handle) = self.publishing.take() else {
            return true;
        };
        let result = handle.join().unwrap_or_else(|_| {
            Err(Error::new(
                ErrorKind::Checkpoint,
                "the thread publishing a checkpoint panicked",
            ))
        });
        match result {
            Ok(()) => true,
            Err(e) => {
                self.errors.push(e.detector(self.det));
                false
            }
        }
    }

    /// Read, step, publish one exposure.
    fn one(
        &self,
        entry: &Entry,
        state: &mut Option<State>,
        book: &mut Bookkeeping,
        buffers: &mut Option<PersistencePlanes>,
        gap_before: bool,
        reprocess: bool,
    ) -> Result<ExposureReport, Failure> {
        let model = &self.cfg.model;
        let mut exposure: Exposure =
            product::read::read_exposure(&entry.path).map_err(Failure::Input)?;
        let meta = exposure.meta.clone();
        if meta != entry.meta {
            return Err(Failure::Input(Error::new(
                ErrorKind::NotReady,
                "changed while being queued; will be retried",
            )));
        }
        let shape = exposure.image.dim();
        let st = state.get_or_insert_with(|| model.new_state(shape.0, shape.1));
        let planes = buffers.get_or_insert_with(|| PersistencePlanes {
            current_e_per_s: Array2::zeros(shape),
            flags: Array2::zeros(shape),
        });
        if planes.current_e_per_s.dim() != shape {
            *planes = PersistencePlanes {
                current_e_per_s: Array2::zeros(shape),
                flags: Array2::zeros(shape),
            };
        }
        let t_mid = meta.t_start.0 + 0.5 * meta.t_exposure_s;
        if gap_before {
            let t_cross = model
                .exp_sum()
                .crossing_time_s(
                    model.response().max_e(),
                    model.params().thresholds.low_e_per_s,
                )
                .unwrap_or(f64::INFINITY);
            let until = meta.t_start.0 + t_cross;
            book.history_incomplete_until_unix_s = Some(
                book.history_incomplete_until_unix_s
                    .map_or(until, |u| u.max(until)),
            );
        }
        let history_incomplete = book
            .history_incomplete_until_unix_s
            .is_some_and(|u| t_mid < u);
        let input = Input {
            image_e_per_s: exposure.image.view(),
            exposure_index: meta.exposure_index,
            t_start_unix_s: meta.t_start.0,
            t_exposure_s: meta.t_exposure_s,
            t_illuminated_s: meta.t_illuminated_s(),
            history_incomplete,
        };
        let mut flags = std::mem::take(&mut exposure.flags);
        // The step validates before it changes anything: an error leaves the state as it was.
        let summary = model
            .step(
                st,
                &input,
                &mut Output {
                    flags: &mut flags,
                    current_e_per_s: &mut planes.current_e_per_s,
                    pflags: &mut planes.flags,
                },
            )
            .map_err(Failure::Input)?;
        exposure.flags = flags;
        if let Some(prev) = summary
            .previous_index
            .filter(|&p| meta.exposure_index > p + 1)
        {
            book.crossed.push((prev + 1, meta.exposure_index - 1));
        }
        let out_path = self.output_path(&entry.path);
        let written = if out_path.exists() && !reprocess {
            false
        } else {
            let attrs = PersistenceAttrs {
                model_id: model.identity().to_string(),
                model_name: model.params().name.clone(),
                threshold_high_e_per_s: model.params().thresholds.high_e_per_s,
                threshold_low_e_per_s: model.params().thresholds.low_e_per_s,
                t_meas_s: summary.t_meas_s.unwrap_or(f64::NAN),
                previous_exposure_index: summary.previous_index.map_or(-1, |i| i as i64),
                software_version: crate::VERSION.to_string(),
                processed_utc: self.cfg.processed_utc.clone(),
            };
            product::write::write_output(&out_path, &exposure, planes, &attrs)
                .map_err(Failure::Output)?;
            true
        };
        Ok(ExposureReport {
            detector: self.det.0,
            exposure_index: meta.exposure_index,
            path: entry.path.clone(),
            summary,
            history_incomplete,
            written,
        })
    }

    fn output_path(&self, input: &Path) -> PathBuf {
        self.cfg.output.join(input.file_name().unwrap_or_default())
    }

    /// Checkpoint `state`: checked and written here (HDF5, from the state in memory,
    /// no copy), then published and the old checkpoints pruned on another thread, so
    /// that the sync of a 200 MB file does not stall the next exposures. Checkpoints
    /// are published in order: the previous publication is waited for first.
    fn save(&mut self, state: &State, book: &Bookkeeping) -> Result<()> {
        self.finish_publishing();
        let model = &self.cfg.model;
        let meta = CheckpointMeta {
            detector: self.det,
            exposure_index: state.last_index.unwrap_or(0),
            model_id: model.identity().to_string(),
            model_name: model.params().name.clone(),
            model_json: model.params().canonical_json(),
            stage_json: serde_json::to_string(book).expect("bookkeeping serialises"),
            software_version: crate::VERSION.to_string(),
        };
        let staged = checkpoint::stage(&self.cfg.checkpoints, &meta, state)?;
        let (dir, det, retention) = (self.cfg.checkpoints.clone(), self.det, self.cfg.retention);
        let index = meta.exposure_index;
        self.publishing = Some(std::thread::spawn(move || {
            if let checkpoint::Staged::Written(s) = staged {
                s.commit().map_err(|e| e.exposure(index))?;
            }
            checkpoint::prune(&dir, det, &retention)?;
            Ok(())
        }));
        Ok(())
    }
}
