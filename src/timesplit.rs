//! Time split of a detector's history: a long reprocessing cut into consecutive spans of
//! exposures, each run by its own jobs ([`crate::tile`]) at the same time.
//!
//! # How a span starts
//! The products a split processes (those after the run's start: the newest checkpoint,
//! or the first product with `--from-start`) are cut into spans of equal counts. Span 0
//! starts as an unsplit run does. A later span starts
//! - from the newest retained checkpoint before its first exposure (made with the same
//!   model, not before the run's start): exact, its outputs and final checkpoint are
//!   byte-identical to the sequential run's;
//! - otherwise from the run's start, when the warm-up would reach back to it (exact);
//! - otherwise from a zero state at the first product at most `warmup_s` before the
//!   span's first exposure. The exposures of the warm-up are stepped, not published.
//!
//! # The carry-in bound
//! A span started from zero misses the current that the history before its warm-up
//! still carries. One exposure adds at most the knot table's maximum amplitude to every
//! term, so an exposure whose reset was `age` seconds before a prediction adds at most
//! [`Model::carry_over_e_per_s`]`(age)` to it. The bound of a span is the sum of that
//! over every skipped exposure (ages from the span's earliest `t_start`), plus the
//! largest current the run's start checkpoint could give then. Every published output
//! of the span records it (`carry_in_bound_e_per_s`) and the warm-up (`warmup_s`).
//!
//! The bound holds for the persistence current of a pixel as long as both runs make the
//! same early-release decisions for it: a pixel that the sequential run releases
//! (zeroing its amplitudes) during or after the warm-up, and the span does not (or the
//! other way), can differ by more. Warm-up spans need a model whose exposures add at
//! most the knot table's maximum (no effects: an effect may scale the amplitudes); a
//! model with effects is refused (checkpoint starts still split it exactly).

use crate::checkpoint;
use crate::error::{Error, ErrorKind, Result};
use crate::model::decay::weighted_sum;
use crate::model::Model;
use crate::product::{ExposureMeta, WarmupAttrs};
use crate::units::DetectorId;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::Path;

/// How a split processes time: the spans of each detector.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TimeSplit {
    /// Spans per detector requested (fewer when a detector has fewer products).
    pub spans_requested: usize,
    /// The warm-up of spans that start from zero, seconds.
    pub warmup_s: f64,
    /// Every detector starts from a zero state at its first product (not its newest
    /// checkpoint), and published outputs are rewritten.
    pub from_start: bool,
    /// The spans of each detector, in time order.
    pub spans: BTreeMap<u8, Vec<Span>>,
}

/// One span: the exposures it publishes and where it starts.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Span {
    /// First published exposure index.
    pub first: u64,
    /// Last published exposure index (inclusive).
    pub last: u64,
    pub start: SpanStart,
}

/// Where a span's jobs start stepping.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SpanStart {
    /// As the unsplit run: the newest checkpoint (or zero with `from_start`), stepping
    /// every product after it. Exact.
    Run,
    /// The retained checkpoint at this exposure index. Exact.
    Checkpoint { index: u64 },
    /// A zero state at product `from`: outputs low by at most the bound.
    Warmup {
        from: u64,
        warmup_s: f64,
        carry_in_bound_e_per_s: f64,
    },
}

impl Span {
    /// True if the span's outputs and final state are those of the sequential run.
    pub fn exact(&self) -> bool {
        !matches!(self.start, SpanStart::Warmup { .. })
    }
    /// What its outputs record (`None` for an exact span).
    pub fn warmup_attrs(&self) -> Option<WarmupAttrs> {
        match self.start {
            SpanStart::Warmup {
                warmup_s,
                carry_in_bound_e_per_s,
                ..
            } => Some(WarmupAttrs {
                warmup_s,
                carry_in_bound_e_per_s,
            }),
            _ => None,
        }
    }
}

/// The default warm-up: the time one exposure's largest response takes to fall below
/// the low threshold ([`Model::carry_over_s`]).
pub fn default_warmup_s(model: &Model) -> f64 {
    model.carry_over_s()
}

/// The largest current `state` (the run's start checkpoint, reset at `t_reset_unix_s`)
/// gives at `t_unix_s`, over every pixel.
fn state_current_at(model: &Model, state: &crate::model::State, t_unix_s: f64) -> f64 {
    let Some(t_reset) = state.t_reset_unix_s else {
        return 0.0;
    };
    let w = model.exp_sum().weights_at((t_unix_s - t_reset).max(0.0));
    let n = state.n_terms();
    state
        .amplitudes_e
        .as_slice_memory_order()
        .map_or(f64::INFINITY, |a| {
            a.chunks_exact(n.max(1))
                .map(|px| weighted_sum(px, &w))
                .fold(0.0, f64::max)
        })
}

/// The spans of one detector.
///
/// `products`: the detector's products by index (every product of the input);
/// `start`: the run's start checkpoint (index, path) or `None` (zero state).
pub fn plan_detector(
    model: &Model,
    checkpoints: &Path,
    det: DetectorId,
    products: &BTreeMap<u64, ExposureMeta>,
    start: Option<(u64, &Path)>,
    n_spans: usize,
    warmup_s: f64,
) -> Result<Vec<Span>> {
    let after: Vec<(u64, &ExposureMeta)> = products
        .range(start.map_or(0, |(i, _)| i + 1)..)
        .map(|(&i, m)| (i, m))
        .collect();
    if after.is_empty() {
        return Ok(Vec::new());
    }
    let n = n_spans.clamp(1, after.len());
    let retained: Vec<u64> = checkpoint::list(checkpoints, det)?
        .into_iter()
        .map(|(i, _)| i)
        .collect();
    let mut start_state = None;
    let mut spans = Vec::with_capacity(n);
    for k in 0..n {
        let (a, b) = (k * after.len() / n, (k + 1) * after.len() / n);
        let (first, last) = (after[a].0, after[b - 1].0);
        let span_start = if k == 0 {
            SpanStart::Run
        } else if let Some(index) =
            usable_checkpoint(model, checkpoints, det, &retained, start, first)?
        {
            SpanStart::Checkpoint { index }
        } else {
            let t_first = after[a..b]
                .iter()
                .map(|(_, m)| m.t_start.0)
                .fold(f64::INFINITY, f64::min);
            // The warm-up: the products starting at most `warmup_s` before the span.
            let w = after[..a]
                .iter()
                .position(|(_, m)| m.t_start.0 >= t_first - warmup_s)
                .unwrap_or(a);
            if w == 0 {
                SpanStart::Run
            } else {
                if !model.effects().is_empty() {
                    return Err(Error::new(
                        ErrorKind::Usage,
                        format!(
                            "detector {}: span {k} has no checkpoint before it and would start from zero, which needs a model without effects (an effect may add more than the knot table's maximum, so the carry-in bound would not hold); split with fewer spans, a longer warm-up, or checkpoints",
                            det.0
                        ),
                    )
                    .field("time-spans"));
                }
                let mut bound: f64 = after[..w]
                    .iter()
                    .map(|(_, m)| model.carry_over_e_per_s(t_first - m.t_reset().0))
                    .sum();
                if let Some((_, path)) = start {
                    if start_state.is_none() {
                        start_state = Some(checkpoint::load(path)?.1);
                    }
                    if let Some(s) = &start_state {
                        bound += state_current_at(model, s, t_first);
                    }
                }
                SpanStart::Warmup {
                    from: after[w].0,
                    warmup_s: t_first - after[w].1.t_start.0,
                    carry_in_bound_e_per_s: bound,
                }
            }
        };
        spans.push(Span {
            first,
            last,
            start: span_start,
        });
    }
    Ok(spans)
}

/// The newest retained checkpoint before `first`, not before the run's start, made with
/// this model.
fn usable_checkpoint(
    model: &Model,
    checkpoints: &Path,
    det: DetectorId,
    retained: &[u64],
    start: Option<(u64, &Path)>,
    first: u64,
) -> Result<Option<u64>> {
    let floor = start.map(|(i, _)| i);
    for &index in retained.iter().rev() {
        if index + 1 > first {
            continue;
        }
        if floor.is_some_and(|f| index < f) {
            break;
        }
        let Some(path) = checkpoint::find(checkpoints, det, index) else {
            continue;
        };
        let (meta, _) = checkpoint::load_meta(&path)?;
        if meta.model_id == model.identity() {
            return Ok(Some(index));
        }
    }
    Ok(None)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_bound_of_one_exposure_falls_to_the_low_threshold_at_the_carry_over_time() {
        let m = Model::new(Default::default()).unwrap();
        let t = m.carry_over_s();
        let low = m.params().thresholds.low_e_per_s;
        assert!((m.carry_over_e_per_s(t) - low).abs() < 1e-9 * low.max(1.0));
        assert!(m.carry_over_e_per_s(0.5 * t) > low);
        assert!(m.carry_over_e_per_s(2.0 * t) < low);
    }
}
