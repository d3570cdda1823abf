//! `persist compare`: every model of `--model` against the measurements of a sequence.
//!
//! Definitions (measured current, background, samples, normalised residuals, flag
//! quality) are those of [`super::data`] and [`super::eval`]. Writes
//! `OUT/summary.json` (every number of the report) and `OUT/report.html`
//! (self-contained; [`super::report`]).
//!
//! # Flag quality over the pixels an effect touches (`--touched-baseline DIR`)
//! On simulated data, `DIR` is the same scenario and seed simulated without the hidden
//! effect. A sampled pixel is *touched* when, at any sampled exposure (every exposure
//! after an illumination), the true persistence current of the input's truth
//! (`truth/*.truth.hdf5`, passed through the readout hooks of the input's truth effects,
//! e.g. `ipc`'s coupling, so that an effect acting on the measurement counts) differs
//! from the baseline's by more than `--touched-min-e-per-s` (default
//! [`TOUCHED_MIN_E_PER_S`] = 0.01 e-/s, a tenth of the 0.1 e-/s flag threshold).
//! The flag quality of every model and threshold is then also given over the samples of
//! the touched pixels (`flag_quality_touched`: `missed_flag_fraction_touched` = missed
//! samples of touched pixels / usable samples of touched pixels). An effect that changes
//! neither the truth nor the readout hooks (`linefit_bias` changes how the on-board line
//! fit reads it) leaves the two truths equal; the measured currents of the two runs are
//! then compared instead, with the same threshold (the same scenario and seed draw the
//! same noise, so they differ only by the effect). `touched.by` says which
//! (`truth` or `measured`).

use super::data::Sequence;
use super::eval::{self, FlagQuality, GroupStat, Samples};
use crate::error::{Error, ErrorKind, Result};
use crate::h5io;
use crate::sim::effect::{EffectSet, EffectSpec as SimEffectSpec};
use rayon::prelude::*;
use serde::Serialize;
use std::collections::BTreeMap;
use std::path::Path;

/// Pixel stride of the sample (eval docs): every 2nd pixel in x and y.
pub const STRIDE: usize = 2;

#[derive(Debug, Clone, Serialize)]
pub struct Bin {
    pub bin: i64,
    /// Lower edge of the bin in the covariate's unit.
    pub value: f64,
    #[serde(flatten)]
    pub stat: GroupStat,
}

/// One cell of the map: where it is and what it compares.
#[derive(Debug, Clone, Serialize)]
pub struct Cell {
    #[serde(flatten)]
    pub place: CellPlace,
    #[serde(flatten)]
    pub stat: GroupStat,
}

/// Where a cell of the map is: its illumination, fluence and time since (the bins'
/// centres), and its neighbour contrast.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct CellPlace {
    /// With `--cells illumination`: the exposure index of the cell's illumination.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub illumination: Option<u64>,
    pub fluence_e: f64,
    pub time_s: f64,
    /// With `--cells neighbours`: the cell of the pixels next to a far brighter one
    /// (`eval::cell_next_to_brighter`; written only when true).
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub next_to_brighter: bool,
}

/// One cell's flag quality at one threshold ([`eval::flag_quality_by_cell`]): the
/// cell as in [`Cell`], the counts and fractions as in `flag_quality`.
#[derive(Debug, Clone, Serialize)]
pub struct CellFlags {
    #[serde(flatten)]
    pub place: CellPlace,
    #[serde(flatten)]
    pub quality: FlagQuality,
}

#[derive(Debug, Clone, Serialize)]
pub struct ModelSummary {
    pub path: String,
    pub name: String,
    pub identity: String,
    pub effects: Vec<String>,
    pub residual_rms_normalised: f64,
    /// With `--cells illumination`: the RMS of `z` over each illumination's cells (where
    /// a campaign's residual sits), in the order of the illuminations.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub residual_rms_by_illumination: Vec<IlluminationRms>,
    pub cells: usize,
    pub map: Vec<Cell>,
    pub breakdown: BTreeMap<String, Vec<Bin>>,
    /// Keyed by the threshold in e-/s, e.g. "0.1".
    pub flag_quality: BTreeMap<String, FlagQuality>,
    /// Where the missed and over-flagged samples are: per threshold (keyed as
    /// `flag_quality`), the cells of the map with at least one of either, in the map's
    /// order.
    pub flag_quality_by_cell: BTreeMap<String, Vec<CellFlags>>,
    /// The same over the touched pixels (module docs), when a baseline is given.
    #[serde(skip_serializing_if = "BTreeMap::is_empty")]
    pub flag_quality_touched: BTreeMap<String, TouchedQuality>,
    /// The residuals' spatial coherence ([`super::spatial`]), with two illuminations or
    /// more.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub spatial: Option<super::spatial::Coherence>,
    /// Whether the cells' pixels move together, and the cells' RMS if the statistic
    /// knew how much ([`super::spread`]).
    pub spread: super::spread::SpreadCheck,
    /// Every model after the first: its flags at 0.1 e-/s with its knots scaled to the
    /// first model's coverage ([`at_coverage_of`]); None for the first model, or when
    /// no factor in [`MATCH_RANGE`] reaches it.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub flags_at_first_coverage: Option<MatchedFlags>,
    /// The pixel reference of the model's prediction, as `persist diagnose` reports it
    /// on its default samples ([`super::finding::PixelReference::fit`]): what is left
    /// when the flexible base and each pixel's own terms have taken in every function of
    /// fluence and time since illumination, so that an addition that makes it fall
    /// predicts what the reference could not. Set by `persist compare`; None elsewhere.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub pixel_reference: Option<super::finding::PixelReference>,
}

/// The threshold, e-/s, at which [`at_coverage_of`] matches coverages: the flags'.
pub const MATCH_THRESHOLD_E_PER_S: f64 = 0.1;

/// The knots' factors [`at_coverage_of`] searches (smallest, largest).
pub const MATCH_RANGE: (f64, f64) = (0.25, 4.0);

/// A model's flags with its knots scaled so that it misses no more of the samples
/// measured above the threshold than another model does: two models compared at one
/// coverage, where the over-flagging says which predicts better (at a coverage of its
/// own, a model's over-flagging also carries its margin's choice).
#[derive(Debug, Clone, Copy, Serialize, PartialEq)]
pub struct MatchedFlags {
    /// The factor on the model's knots (amplitudes), the smallest found that reaches
    /// the target.
    pub knot_factor: f64,
    /// The other model's missed samples: the target.
    pub target_missed: usize,
    /// The flags at that factor.
    pub quality: FlagQuality,
    /// Its over-flagged samples against the other model's, paired by pixel.
    pub over_flagged_vs_first: PairedDifference,
}

/// Two models' counts on the same samples, paired by sampled pixel: a pixel's samples
/// rise and fall together (one bright pixel is over-flagged in many darks), so the
/// noise of the difference is the pixels', not the samples'.
#[derive(Debug, Clone, Copy, Serialize, PartialEq)]
pub struct PairedDifference {
    /// The second count minus the first, over all pixels.
    pub difference: i64,
    /// Its standard error: `sqrt(n / (n - 1) * sum_p (d_p - mean d)^2)` over the `n`
    /// pixels' differences `d_p`; 0 when the counts differ nowhere.
    pub standard_error: f64,
    /// The pixels whose counts differ.
    pub pixels_differing: usize,
}

impl PairedDifference {
    /// `second - first`, per pixel (equal lengths).
    pub fn of(first: &[u32], second: &[u32]) -> Self {
        let d: Vec<f64> = first
            .iter()
            .zip(second)
            .map(|(&a, &b)| f64::from(b) - f64::from(a))
            .collect();
        let n = d.len() as f64;
        let sum: f64 = d.iter().sum();
        let mean = sum / n.max(1.0);
        let ss: f64 = d.iter().map(|x| (x - mean).powi(2)).sum();
        PairedDifference {
            difference: sum as i64,
            standard_error: if n > 1.0 {
                (n / (n - 1.0) * ss).sqrt()
            } else {
                0.0
            },
            pixels_differing: d.iter().filter(|&&x| x != 0.0).count(),
        }
    }

    /// "higher beyond the noise" or "lower beyond the noise" when the difference is
    /// more than twice its standard error from zero, else "within the noise".
    pub fn against_noise(&self) -> &'static str {
        let d = self.difference as f64;
        if d > 2.0 * self.standard_error {
            "higher beyond the noise"
        } else if -d > 2.0 * self.standard_error {
            "lower beyond the noise"
        } else {
            "within the noise"
        }
    }
}

/// A model's flags at one knot factor.
pub struct FactorFlags {
    quality: FlagQuality,
    /// Over-flagged samples per sampled pixel ([`eval::over_flagged_by_pixel`]).
    over_by_pixel: Vec<u32>,
}

/// The flag quality at `thr` of `params` with its knots times `factor`: the stage's
/// flags (early release included) when `thr` is the model's flag threshold, else the
/// predictions above `thr`, as in [`summarise`].
fn flags_at_factor(
    params: &crate::model::ModelParams,
    seq: &Sequence,
    samples: &Samples,
    factor: f64,
    thr: f64,
) -> Result<FactorFlags> {
    let mut p = params.clone();
    p.scale_knots(factor);
    let stage = thr == p.thresholds.high_e_per_s;
    let pr = eval::predict(&p, seq, samples, stage)?;
    let flags = stage.then_some(pr.flagged.as_slice());
    Ok(FactorFlags {
        quality: eval::flag_quality(samples, &pr.current, flags, thr),
        over_by_pixel: eval::over_flagged_by_pixel(samples, &pr.current, flags, thr),
    })
}

/// Steps of the log grid over [`MATCH_RANGE`] that [`at_coverage_of`] walks up before
/// it bisects: 24 steps of x 1.12.
pub const MATCH_GRID_STEPS: usize = 24;

/// [`MatchedFlags`] of `params` at `thr` against `first`, the other model's flags: the
/// smallest factor on the knots in [`MATCH_RANGE`] whose flags miss at most as many
/// samples ([`smallest_factor_reaching`]). None when no factor of the grid does.
pub fn at_coverage_of(
    params: &crate::model::ModelParams,
    seq: &Sequence,
    samples: &Samples,
    thr: f64,
    first: &FactorFlags,
) -> Result<Option<MatchedFlags>> {
    let at = |f: f64| flags_at_factor(params, seq, samples, f, thr);
    let target_missed = first.quality.missed;
    Ok(
        smallest_factor_reaching(at, |q| q.quality.missed, target_missed)?.map(|(factor, q)| {
            MatchedFlags {
                knot_factor: factor,
                target_missed,
                quality: q.quality,
                over_flagged_vs_first: PairedDifference::of(&first.over_by_pixel, &q.over_by_pixel),
            }
        }),
    )
}

/// The smallest factor in [`MATCH_RANGE`] at which `missed(at(factor))` is at most
/// `target`, and what `at` gave there; None when no point of the grid reaches it.
///
/// Missing falls as the knots rise, but not monotonically: early release zeroes the
/// amplitudes of pixels measured below the threshold, and near the noise floor of the
/// misses (samples measured above the threshold whose truth is below it) a few samples
/// come and go. Measured on the second generator's `soak:capture` campaign (64 x 64,
/// seed 3) with the soak effect added: 96 missed at x 1, 91 at x 1.5, 110 at x 2, 117
/// at x 4, 90 at x 4.7. A bisection over the whole range can then settle on a factor far above the smallest.
/// So the log grid of [`MATCH_GRID_STEPS`] steps is walked up from the smallest factor,
/// and the first grid point that reaches the target is refined by bisection in `ln
/// factor` against the grid point below it, to 0.01 %. A dip narrower than one grid
/// step (x 1.12) can be passed over.
pub fn smallest_factor_reaching<T>(
    mut at: impl FnMut(f64) -> Result<T>,
    missed: impl Fn(&T) -> usize,
    target: usize,
) -> Result<Option<(f64, T)>> {
    let (first, last) = (MATCH_RANGE.0.ln(), MATCH_RANGE.1.ln());
    let step = (last - first) / MATCH_GRID_STEPS as f64;
    for i in 0..=MATCH_GRID_STEPS {
        let x = first + step * i as f64;
        let q = at(x.exp())?;
        if missed(&q) > target {
            continue;
        }
        let (mut lo, mut hi, mut best) = (x - step, x, q);
        if i > 0 {
            while hi - lo > 1e-4 {
                let mid = 0.5 * (lo + hi);
                let q = at(mid.exp())?;
                if missed(&q) <= target {
                    (hi, best) = (mid, q);
                } else {
                    lo = mid;
                }
            }
        }
        return Ok(Some((hi.exp(), best)));
    }
    Ok(None)
}

/// Flag quality over the samples of the touched pixels (module docs).
#[derive(Debug, Clone, Copy, Serialize, PartialEq)]
pub struct TouchedQuality {
    pub threshold_e_per_s: f64,
    pub touched_pixels: usize,
    /// Usable samples (finite measurement) of the touched pixels.
    pub touched_samples: usize,
    pub measured_above: usize,
    pub flagged: usize,
    pub missed: usize,
    pub over_flagged: usize,
    pub missed_flag_fraction_touched: f64,
    pub missed_of_measured_above_touched: f64,
    pub over_flag_fraction_touched: f64,
}

/// Which pixels the hidden effect touches (module docs).
#[derive(Debug, Clone, Serialize)]
pub struct Touched {
    pub baseline: String,
    /// What was compared: `truth`, or `measured` when the two truths are equal.
    pub by: &'static str,
    pub definition: String,
    pub min_difference_e_per_s: f64,
    /// The input's truth effects, whose readout hooks were applied to its truth.
    pub input_effects: Vec<String>,
    /// Touched pixels among the sampled pixels.
    pub touched_pixels: usize,
    pub pixels_sampled: usize,
    /// Largest difference found, e-/s.
    pub max_difference_e_per_s: f64,
}

/// Default of `--touched-min-e-per-s`, e-/s.
pub const TOUCHED_MIN_E_PER_S: f64 = 0.01;

/// Options of `persist compare` beyond the input and models.
#[derive(Debug, Clone)]
pub struct Options {
    pub touched_baseline: Option<std::path::PathBuf>,
    pub touched_min_e_per_s: f64,
    /// The residual cells (`--cells`, [`eval::Cells`]).
    pub cells: eval::Cells,
    /// What they compare (`--cell-statistic`, [`eval::CellStatistic`]).
    pub cell_statistic: eval::CellStatistic,
    /// How each exposure's background is measured (`--background`,
    /// [`super::data::Background`]).
    pub background: super::data::Background,
}

impl Default for Options {
    fn default() -> Self {
        Options {
            touched_baseline: None,
            touched_min_e_per_s: TOUCHED_MIN_E_PER_S,
            cells: eval::Cells::default(),
            cell_statistic: eval::CellStatistic::default(),
            background: super::data::Background::default(),
        }
    }
}

#[derive(Debug, Clone, Serialize)]
pub struct Summary {
    pub input: String,
    pub definitions: BTreeMap<String, String>,
    /// How the map's cells (and `residual_rms_normalised`) group the samples.
    pub cells: eval::Cells,
    /// What a cell's `z` compares.
    pub cell_statistic: eval::CellStatistic,
    /// How each exposure's background was measured (`definitions.measured`).
    pub background: super::data::Background,
    pub exposures_compared: usize,
    pub pixels_sampled: usize,
    pub pixel_stride: usize,
    pub samples: usize,
    /// Present with `--touched-baseline`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub touched: Option<Touched>,
    pub models: Vec<ModelSummary>,
}

pub const BREAKDOWNS: [&str; 7] = [
    "time",
    "fluence",
    "neighbour_excess_fluence",
    "illumination_time",
    "temperature",
    "earlier_illuminations",
    "position",
];

/// Compare already-loaded models (used by the CLI, `diagnose` and tests).
pub fn summarise(
    seq: &Sequence,
    samples: &Samples,
    models: &[(String, crate::model::ModelParams)],
) -> Result<Vec<ModelSummary>> {
    summarise_touched(seq, samples, models, None)
}

/// [`summarise`], and the flag quality over the touched pixels when `touched` (one
/// entry per sampled pixel) is given.
pub fn summarise_touched(
    seq: &Sequence,
    samples: &Samples,
    models: &[(String, crate::model::ModelParams)],
    touched: Option<&[bool]>,
) -> Result<Vec<ModelSummary>> {
    let mut out = Vec::new();
    // the first model's flags at the threshold the others are matched at
    let mut first: Option<FactorFlags> = None;
    for (path, params) in models {
        // residuals (early release off) and flags (the model's setting) side by side
        let (pr, fl) = rayon::join(
            || eval::predict(params, seq, samples, false),
            || eval::predict(params, seq, samples, true),
        );
        let (pr, fl) = (pr?, fl?);
        // the cells, and each covariate's groups, in parallel
        let (plain, by) = rayon::join(
            || eval::cell_z(samples, &pr.current),
            || {
                BREAKDOWNS
                    .par_iter()
                    .map(|c| eval::groups(samples, &pr.current, &[c]))
                    .collect::<Vec<_>>()
            },
        );
        // the model's cells: widened by the spread correlation it states, if any
        let spread = super::spread::check(samples, &pr.current, &plain);
        let mut cells = plain;
        super::spread::widen_for_model(params, samples, &pr.current, &mut cells);
        let place = |k: &[i64]| {
            let (fluence_e, time_s) = eval::cell_fluence_time(k);
            CellPlace {
                illumination: eval::cell_illumination(k)
                    .map(|a| seq.exposures[a].meta.exposure_index),
                fluence_e,
                time_s,
                next_to_brighter: eval::cell_next_to_brighter(k),
            }
        };
        let map = cells
            .iter()
            .map(|(k, g)| Cell {
                place: place(k),
                stat: *g,
            })
            .collect();
        let mut breakdown = BTreeMap::new();
        for (c, g) in BREAKDOWNS.iter().zip(by) {
            breakdown.insert(
                c.to_string(),
                g.into_iter()
                    .map(|(k, st)| Bin {
                        bin: k[0],
                        value: eval::bin_value(c, k[0]),
                        stat: st,
                    })
                    .collect(),
            );
        }
        let mut fq = BTreeMap::new();
        let mut fqt = BTreeMap::new();
        let mut fqc = BTreeMap::new();
        let high = params.thresholds.high_e_per_s;
        let mut ths = vec![0.1, 0.01, high, params.thresholds.low_e_per_s];
        ths.sort_by(|a, b| a.total_cmp(b));
        ths.dedup();
        for t in ths {
            let flags = (t == high).then_some(fl.flagged.as_slice());
            let quality = eval::flag_quality(samples, &pr.current, flags, t);
            if out.is_empty() && t == MATCH_THRESHOLD_E_PER_S {
                first = Some(FactorFlags {
                    quality,
                    over_by_pixel: eval::over_flagged_by_pixel(samples, &pr.current, flags, t),
                });
            }
            fq.insert(format!("{t}"), quality);
            fqc.insert(
                format!("{t}"),
                eval::flag_quality_by_cell(samples, &pr.current, flags, t)
                    .into_iter()
                    .filter(|(_, q)| q.missed + q.over_flagged > 0)
                    .map(|(k, quality)| CellFlags {
                        place: place(&k),
                        quality,
                    })
                    .collect::<Vec<_>>(),
            );
            if let Some(mask) = touched {
                let q = eval::flag_quality_of(samples, &pr.current, flags, t, Some(mask));
                fqt.insert(
                    format!("{t}"),
                    TouchedQuality {
                        threshold_e_per_s: t,
                        touched_pixels: mask.iter().filter(|m| **m).count(),
                        touched_samples: q.samples,
                        measured_above: q.measured_above,
                        flagged: q.flagged,
                        missed: q.missed,
                        over_flagged: q.over_flagged,
                        missed_flag_fraction_touched: q.missed_flag_fraction,
                        missed_of_measured_above_touched: q.missed_of_measured_above,
                        over_flag_fraction_touched: q.over_flag_fraction,
                    },
                );
            }
        }
        out.push(ModelSummary {
            path: path.clone(),
            name: params.name.clone(),
            identity: params.identity(),
            effects: params.effects.iter().map(|e| e.name.clone()).collect(),
            residual_rms_normalised: eval::rms(&cells),
            residual_rms_by_illumination: rms_by_illumination(seq, &cells),
            cells: cells.len(),
            map,
            breakdown,
            flag_quality: fq,
            flag_quality_by_cell: fqc,
            flag_quality_touched: fqt,
            spatial: super::spatial::coherence(seq, params)?,
            spread,
            flags_at_first_coverage: None,
            pixel_reference: None,
        });
    }
    if let Some(first) = &first {
        for (m, (_, params)) in out.iter_mut().zip(models).skip(1) {
            m.flags_at_first_coverage =
                at_coverage_of(params, seq, samples, MATCH_THRESHOLD_E_PER_S, first)?;
        }
    }
    Ok(out)
}

/// One illumination's share of the residual (`--cells illumination`).
#[derive(Debug, Clone, Copy, Serialize)]
pub struct IlluminationRms {
    /// The illumination's exposure index.
    pub illumination: u64,
    pub cells: usize,
    pub residual_rms_normalised: f64,
}

/// RMS of `z` per illumination of per-illumination cells (empty for pooled ones). The
/// cells come sorted by key, whose first element is the illumination, so each
/// illumination's cells are one run.
fn rms_by_illumination(seq: &Sequence, cells: &[(Vec<i64>, GroupStat)]) -> Vec<IlluminationRms> {
    cells
        .chunk_by(|a, b| a.0[0] == b.0[0])
        .filter_map(|run| {
            let a = eval::cell_illumination(&run[0].0)?;
            Some(IlluminationRms {
                illumination: seq.exposures[a].meta.exposure_index,
                cells: run.len(),
                residual_rms_normalised: eval::rms(run),
            })
        })
        .collect()
}

pub fn definitions(
    cells: eval::Cells,
    statistic: eval::CellStatistic,
    background: super::data::Background,
) -> BTreeMap<String, String> {
    let rms = match cells {
        eval::Cells::Pooled => "RMS of z over cells fluence (5 per decade) x time since illumination (4 per decade), all illuminations together",
        eval::Cells::Illumination => "RMS of z over cells illumination x fluence (5 per decade) x time since illumination (4 per decade); the map figure shows, per fluence x time, the illumination with the largest |z|",
        eval::Cells::Neighbours => "RMS of z over cells illumination x neighbour contrast (1 where the four nearest neighbours' mean fluence above 2e5 e- exceeds the pixel's own) x fluence (5 per decade) x time since illumination (4 per decade); the map figure shows, per fluence x time, the cell with the largest |z|",
    };
    BTreeMap::from([
        ("measured".into(), background.describe().into()),
        ("samples".into(), "every 2nd pixel in x and y with fluence > 3000 e- in the last illumination, every exposure after an illumination".into()),
        ("z".into(), match statistic {
            eval::CellStatistic::Levels => "(P95 of measured - P95 of predicted plus each sample's noise) / (2.12 s / sqrt(n)), s = 1.4826 MAD of measured, at least the noise",
            eval::CellStatistic::Paired => "(P95 of measured - predicted, sample by sample - P95 of the samples' noise alone) / (2.12 s / sqrt(n)), s = 1.4826 MAD of measured - predicted, at least the noise; the figures' P95 are of measured and of predicted plus noise",
            eval::CellStatistic::Population => "(P95 of measured - predicted, sample by sample - P95 of the mixture N(-1.645 s_i, s_i^2 + sigma_i^2)) / (2.12 s / sqrt(n)), s_i = r(F_i) predicted_i the pixels' spread below the predicted 95th percentile (r from the first dark after the first illumination), sigma_i^2 = sigma_k^2 + 1.2 / t_exposure_s predicted_i the exposure noise plus the sample's own shot noise, s = 1.4826 MAD of measured - predicted, at least the median sigma_i; the figures' P95 are of measured and of predicted plus that mixture",
        }.into()),
        ("residual_rms_normalised".into(), rms.into()),
        ("missed".into(), "measured > threshold + 2 noise and not flagged".into()),
        ("over_flagged".into(), "flagged and measured < threshold - 2 noise".into()),
        ("flag_quality_by_cell".into(), "per threshold, the cells of the map (as residual_rms_normalised groups them) with at least one missed or over-flagged sample, and their counts; a sample counts when its measurement is finite, whatever its prediction".into()),
        ("flags".into(), "at the model's high threshold from the model as the stage runs it (early release on; on laboratory data against the sequence's measured dark level); other thresholds: prediction > threshold with early release off".into()),
        ("spatial".into(), format!("with two illuminations or more: per illumination, the first exposure after it, ln(measured / predicted) at pixels predicted above {} e-/s less the median of its fluence bin (20 per decade), smoothed over 4, 8, 16 and 32 px (three masked box passes); R^2 of one illumination's map against another's ratio, mean over the ordered pairs; at or above {} a field shared by neighbouring pixels (src/diag/spatial.rs)", super::spatial::MIN_PREDICTED_E_PER_S, super::spatial::COHERENT_R2)),
        ("spread".into(), format!("whether the pixels above each cell's 95th percentile come in patches (neighbouring pixels sharing their traps, which makes a cell's percentile move as if it had fewer pixels): per cell, each sample's indicator of the cell's top 5 % of (measured - predicted - offset) / sd, standardised; score: the pairwise score of a correlation over {} px between distinct pixels of one cell (each pixel's indicators averaged over the cell's exposures), about N(0, 1) for independent pixels; kernel: c exp(-d^2 / (2 l^2)) + level fitted to the mean centred products by distance (up to {} px); residual_rms_normalised_correlated: the cells' z divided by sqrt(design effect), deff = 1 + (2 / n) sum over the cell's pairs of c exp(-d^2 / (2 l^2)); a statement about the statistic's noise, not the predictions (src/diag/spread.rs)", super::spread::SCORE_LENGTH_PX, super::spread::MAX_LAG_PX)),
    ])
}

fn read_json(path: &Path) -> Result<serde_json::Value> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    serde_json::from_str(&text)
        .map_err(|e| Error::new(ErrorKind::Invalid, format!("not JSON: {e}")).path(path))
}

/// The simulator's noise-free persistence current of one exposure
/// (`truth/*.truth.hdf5` `/true_persistence`), checked against the products' shape.
pub fn read_truth(path: &Path, shape: (usize, usize)) -> Result<ndarray::Array2<f32>> {
    let f = h5io::open(path)?;
    let a: ndarray::Array2<f32> = f
        .dataset("true_persistence")
        .and_then(|d| d.read_2d())
        .map_err(|e| Error::from(e).path(path).field("true_persistence"))?;
    if a.dim() != shape {
        return Err(Error::invalid(
            "true_persistence",
            format!("shape {:?}, the products' is {:?}", a.dim(), shape),
        )
        .path(path));
    }
    Ok(a)
}

/// Mark the sampled pixels where planes `a` and `b` differ by more than `min`, and
/// raise `max_diff` to the largest finite difference.
fn mark_differences(
    touched: &mut [bool],
    max_diff: &mut f64,
    samples: &Samples,
    a: &ndarray::Array2<f32>,
    b: &ndarray::Array2<f32>,
    min: f64,
) {
    for (t, &p) in touched.iter_mut().zip(&samples.pixels) {
        let d = (f64::from(a[p]) - f64::from(b[p])).abs();
        if d.is_finite() {
            *max_diff = max_diff.max(d);
            if d > min {
                *t = true;
            }
        }
    }
}

/// The touched pixels of the sample (module docs): one entry per sampled pixel.
pub fn touched_pixels(
    seq: &Sequence,
    samples: &Samples,
    input: &Path,
    baseline: &Path,
    min_difference_e_per_s: f64,
) -> Result<(Vec<bool>, Touched)> {
    if !(min_difference_e_per_s.is_finite() && min_difference_e_per_s >= 0.0) {
        return Err(Error::invalid(
            "--touched-min-e-per-s",
            format!("must be finite and >= 0, got {min_difference_e_per_s}"),
        ));
    }
    let tj_in = input.join("truth").join("truth.json");
    let tj_base = baseline.join("truth").join("truth.json");
    let (a, b) = (read_json(&tj_in)?, read_json(&tj_base)?);
    for field in [
        "/scenario",
        "/config/seed",
        "/config/size",
        "/config/campaign",
    ] {
        if a.pointer(field) != b.pointer(field) {
            return Err(Error::invalid(
                field.trim_start_matches('/').replace('/', "."),
                format!(
                    "{} has {}, the baseline {} has {}: the baseline must be the same scenario and seed without the effect",
                    tj_in.display(),
                    a.pointer(field).map_or("nothing".into(), |v| v.to_string()),
                    tj_base.display(),
                    b.pointer(field).map_or("nothing".into(), |v| v.to_string()),
                ),
            ));
        }
    }
    let mut specs = Vec::new();
    for e in a
        .get("effects")
        .and_then(|v| v.as_array())
        .into_iter()
        .flatten()
    {
        let name = e.get("name").and_then(|v| v.as_str()).unwrap_or_default();
        let params = e
            .get("params")
            .and_then(|v| v.as_object())
            .into_iter()
            .flatten()
            .filter_map(|(k, v)| v.as_f64().map(|v| (k.clone(), v)))
            .collect();
        specs.push(SimEffectSpec {
            name: name.to_string(),
            params,
        });
    }
    let effects = EffectSet::from_specs(&specs).map_err(|e| e.path(&tj_in).field("effects"))?;
    let shape = (seq.ny, seq.nx);
    let mut touched = vec![false; samples.npix()];
    let mut max_diff = 0.0f64;
    for &k in &samples.exposures {
        let m = &seq.exposures[k].meta;
        let det = m.detector.0;
        let mut t_in = read_truth(
            &crate::sim::output::truth_path(input, det, m.exposure_index),
            shape,
        )?;
        for e in &effects.list {
            e.measured(&mut t_in, None);
        }
        let t_base = read_truth(
            &crate::sim::output::truth_path(baseline, det, m.exposure_index),
            shape,
        )?;
        mark_differences(
            &mut touched,
            &mut max_diff,
            samples,
            &t_in,
            &t_base,
            min_difference_e_per_s,
        );
    }
    // the truths equal: a readout-only effect, seen in the measured currents
    let by_measured = max_diff == 0.0;
    if by_measured {
        let base = Sequence::load(baseline)?;
        for &k in &samples.exposures {
            let (a, b) = (&seq.exposures[k], base.exposures.get(k));
            let Some(b) = b.filter(|b| b.meta.exposure_index == a.meta.exposure_index) else {
                return Err(Error::invalid(
                    "exposure_index",
                    format!(
                        "the baseline has no exposure {} at position {k}: the baseline must be the same scenario and seed without the effect",
                        a.meta.exposure_index
                    ),
                )
                .path(baseline));
            };
            mark_differences(
                &mut touched,
                &mut max_diff,
                samples,
                &a.image,
                &b.image,
                min_difference_e_per_s,
            );
        }
    }
    let info = Touched {
        baseline: baseline.display().to_string(),
        by: if by_measured { "measured" } else { "truth" },
        definition: if by_measured {
            format!(
                "the truths are equal: a sampled pixel whose measured current differs from the baseline's by more than {min_difference_e_per_s} e-/s at any sampled exposure"
            )
        } else {
            format!(
                "a sampled pixel whose true persistence current (input truth through its effects' readout) differs from the baseline's by more than {min_difference_e_per_s} e-/s at any sampled exposure"
            )
        },
        min_difference_e_per_s,
        input_effects: effects.list.iter().map(|e| e.name().to_string()).collect(),
        touched_pixels: touched.iter().filter(|t| **t).count(),
        pixels_sampled: samples.npix(),
        max_difference_e_per_s: max_diff,
    };
    Ok((touched, info))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Misses that fall, rise again and fall: the smallest factor that reaches the
    /// target lies below a stretch that does not.
    fn misses(f: f64) -> usize {
        match f {
            f if f < 1.5 => 100,
            f if f <= 1.8 => 90,
            f if f < 3.5 => 120,
            _ => 80,
        }
    }

    #[test]
    fn the_smallest_factor_is_found_below_a_stretch_that_misses_more() {
        let (f, m) = smallest_factor_reaching(|f| Ok(misses(f)), |&m| m, 95)
            .unwrap()
            .unwrap();
        assert!((f / 1.5 - 1.0).abs() < 2e-4, "factor {f}");
        assert_eq!(m, 90);
        // a target only the largest factors reach
        let (f, m) = smallest_factor_reaching(|f| Ok(misses(f)), |&m| m, 85)
            .unwrap()
            .unwrap();
        assert!((f / 3.5 - 1.0).abs() < 2e-4, "factor {f}");
        assert_eq!(m, 80);
    }

    #[test]
    fn the_range_bounds_the_search() {
        let first = smallest_factor_reaching(|f| Ok(misses(f)), |&m| m, 100).unwrap();
        assert_eq!(first.map(|(f, _)| f), Some(MATCH_RANGE.0));
        assert!(smallest_factor_reaching(|f| Ok(misses(f)), |&m| m, 79)
            .unwrap()
            .is_none());
    }
}
