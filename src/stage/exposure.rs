//! One exposure of a detector's history through the model: the one path that
//! `persist run` ([`mod@super::run`]), `persist slurm`'s tile jobs ([`crate::tile`]) and the
//! Python `persist.run` (which calls the stage) share.
//!
//! [`step_exposure`] takes the detector's state and bookkeeping and one exposure, applies
//! the stage's gap rule (the "history incomplete" deadline, [`mod@super::run`] module docs),
//! steps the model over a [`Window`] of the array, and leaves the state, the output
//! planes, the exposure's flags (with the `PERSIST` bits) and the bookkeeping (crossed
//! gaps, first index, input digests) advanced; [`output_attrs`] is the provenance every
//! output records. A tile job differs from the whole-array stage only in its window.
//!
//! Invariants: the step validates before it changes anything, so an error leaves the
//! state and the bookkeeping as they were; nothing here reads or writes files.

use crate::error::Result;
use crate::model::{Input, Model, Output, State, StepContext, StepSummary};
use crate::product::{Exposure, FlagStats, PersistenceAttrs, PersistencePlanes, WarmupAttrs};
use ndarray::{s, Array2};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::ops::Range;

/// How many processed exposures per detector keep their input digest in the checkpoint
/// bookkeeping, to tell an identical re-delivery from a different-content duplicate.
pub const DUPLICATE_WINDOW: usize = 64;

/// The stage's own bookkeeping carried in each checkpoint (`stage_json`).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Bookkeeping {
    /// Mark outputs "history incomplete" while their mid-exposure time is before this.
    pub history_incomplete_until_unix_s: Option<f64>,
    /// Inclusive ranges of exposure indices the history crossed without them (missing
    /// or rejected): a product for one of them that turns up later is late.
    #[serde(default)]
    pub crossed: Vec<(u64, u64)>,
    /// The first exposure index of this history (products below it are late).
    #[serde(default)]
    pub first_index: Option<u64>,
    /// SHA-256 (hex) of the input file of each of the last [`DUPLICATE_WINDOW`]
    /// processed exposures, by index.
    #[serde(default)]
    pub digests: BTreeMap<u64, String>,
    /// Whether this history's exposure indices are start times (FITS exposures without
    /// a sequence number) rather than sequence numbers; set by the first product
    /// offered. The two are never mixed in one history. Written only when true, so
    /// that sequence-number checkpoints carry no such field; a resumed history without
    /// it that has processed anything is one of sequence numbers.
    #[serde(default, skip_serializing_if = "is_not_true")]
    pub by_start_time: Option<bool>,
}

fn is_not_true(v: &Option<bool>) -> bool {
    *v != Some(true)
}

impl Bookkeeping {
    pub fn was_crossed(&self, index: u64) -> bool {
        self.crossed.iter().any(|&(a, b)| (a..=b).contains(&index))
    }

    /// Whether this history is ordered by start time. The first product offered fixes
    /// it (a resumed history that has none is one of sequence numbers); a product of
    /// the other kind gets `Err` with the sentence that refuses it.
    pub fn admit_order(
        &mut self,
        resumed: bool,
        by_start_time: bool,
    ) -> std::result::Result<(), String> {
        let history = self.by_start_time.unwrap_or(!resumed && by_start_time);
        self.by_start_time = Some(history);
        if history == by_start_time {
            return Ok(());
        }
        let (this, history) = if by_start_time {
            (
                "has no sequence number (ordered by its start time)",
                "sequence numbers",
            )
        } else {
            (
                "has a sequence number",
                "start times (FITS without a sequence number)",
            )
        };
        Err(format!(
            "this product {this}, but the detector's history is ordered by {history}: \
             the two are not mixed"
        ))
    }
}

/// Whether exposure `index` follows a gap in a history whose last processed exposure is
/// `last` (the gap rule, [`mod@super::run`] module docs): never in a history ordered by
/// start time, which has no successor index.
pub fn gap_before(book: &Bookkeeping, last: Option<u64>, index: u64) -> bool {
    book.by_start_time != Some(true) && last.is_some_and(|l| index != l + 1)
}

/// The pixels a path steps: rows and columns of the detector's array, and which of
/// them it keeps (row-major over the window; `None`: all).
#[derive(Debug, Clone)]
pub struct Window<'a> {
    pub rows: Range<usize>,
    pub cols: Range<usize>,
    pub active: Option<&'a [bool]>,
}

impl Window<'_> {
    /// The whole array of `shape`.
    pub fn whole(shape: (usize, usize)) -> Window<'static> {
        Window {
            rows: 0..shape.0,
            cols: 0..shape.1,
            active: None,
        }
    }

    pub fn shape(&self) -> (usize, usize) {
        (self.rows.len(), self.cols.len())
    }

    fn is_whole(&self, shape: (usize, usize)) -> bool {
        self.rows == (0..shape.0) && self.cols == (0..shape.1)
    }
}

/// One exposure, as [`step_exposure`] takes it.
#[derive(Debug, Clone)]
pub struct ExposureStep<'a> {
    /// The pixels stepped.
    pub window: Window<'a>,
    /// An exposure before this one is missing or was refused ([`gap_before`], or a
    /// refusal in this run).
    pub gap_before: bool,
    /// SHA-256 (hex) of the input file's bytes.
    pub digest: String,
}

/// What one exposure gave besides the planes.
#[derive(Debug, Clone)]
pub struct Stepped {
    pub summary: StepSummary,
    pub history_incomplete: bool,
}

/// Step `model` over one exposure (module docs). `state` is the window's; `planes` are
/// (re)shaped to the window; the window's flags of `exposure` get the `PERSIST` bits.
pub fn step_exposure(
    model: &Model,
    state: &mut State,
    book: &mut Bookkeeping,
    exposure: &mut Exposure,
    step: ExposureStep<'_>,
    planes: &mut PersistencePlanes,
) -> Result<Stepped> {
    let meta = &exposure.meta;
    let shape = step.window.shape();
    if planes.current_e_per_s.dim() != shape || planes.flags.dim() != shape {
        *planes = PersistencePlanes {
            current_e_per_s: Array2::zeros(shape),
            flags: Array2::zeros(shape),
        };
    }
    let mut until = book.history_incomplete_until_unix_s;
    if step.gap_before {
        let u = meta.t_start.0 + model.carry_over_s();
        until = Some(until.map_or(u, |x| x.max(u)));
    }
    let history_incomplete = until.is_some_and(|u| meta.t_start.0 + 0.5 * meta.t_exposure_s < u);
    let whole = step.window.is_whole(exposure.image.dim());
    let (rows, cols) = (step.window.rows.clone(), step.window.cols.clone());
    // The whole array is stepped in place; a window on a copy of its pixels.
    let cut;
    let image = if whole {
        exposure.image.view()
    } else {
        cut = exposure
            .image
            .slice(s![rows.clone(), cols.clone()])
            .to_owned();
        cut.view()
    };
    let mut flags = if whole {
        std::mem::take(&mut exposure.flags)
    } else {
        exposure
            .flags
            .slice(s![rows.clone(), cols.clone()])
            .to_owned()
    };
    let input = Input {
        image_e_per_s: image,
        exposure_index: meta.exposure_index,
        t_start_unix_s: meta.t_start.0,
        t_exposure_s: meta.t_exposure_s,
        t_illuminated_s: meta.t_illuminated_s(),
        history_incomplete,
        background_e_per_s: None,
    };
    let ctx = StepContext {
        focal_plane_temp_k: meta.focal_plane_temp_k,
        active_pixels: step.window.active,
    };
    let last = state.last_index;
    let stepped = model.step_with(
        state,
        &input,
        &ctx,
        &mut Output {
            flags: &mut flags,
            current_e_per_s: &mut planes.current_e_per_s,
            pflags: &mut planes.flags,
        },
    );
    let index = meta.exposure_index;
    if whole {
        exposure.flags = flags;
    } else {
        exposure.flags.slice_mut(s![rows, cols]).assign(&flags);
    }
    let summary = stepped?;
    book.history_incomplete_until_unix_s = until;
    if let Some(prev) = summary
        .previous_index
        .filter(|&p| index > p + 1 && book.by_start_time != Some(true))
    {
        book.crossed.push((prev + 1, index - 1));
    }
    if book.first_index.is_none() && last.is_none() {
        book.first_index = Some(index);
    }
    book.digests.insert(index, step.digest);
    while book.digests.len() > DUPLICATE_WINDOW {
        book.digests.pop_first();
    }
    Ok(Stepped {
        summary,
        history_incomplete,
    })
}

/// The provenance an output records (`/persistence` attributes): the model, its
/// thresholds, the step's `t_meas_s` and previous exposure, the processing time, and the
/// flag statistics of the whole array's `planes`.
pub fn output_attrs(
    model: &Model,
    t_meas_s: Option<f64>,
    previous_index: Option<u64>,
    processed_utc: &str,
    planes: &PersistencePlanes,
    warmup: Option<WarmupAttrs>,
) -> PersistenceAttrs {
    PersistenceAttrs {
        model_id: model.identity().to_string(),
        model_name: model.params().name.clone(),
        threshold_high_e_per_s: model.params().thresholds.high_e_per_s,
        threshold_low_e_per_s: model.params().thresholds.low_e_per_s,
        t_meas_s: t_meas_s.unwrap_or(f64::NAN),
        previous_exposure_index: previous_index.map_or(-1, |i| i as i64),
        software_version: crate::VERSION.to_string(),
        processed_utc: processed_utc.to_string(),
        stats: Some(FlagStats::of_plane(&planes.flags)),
        warmup,
    }
}
