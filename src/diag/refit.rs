//! Refitting candidate effects and holding them out ([`super::diagnose`] module docs,
//! "Refit" and "Held-out check"): the model's own effects refitted alone, a candidate
//! fitted with them, the change in BIC, and the held-out split by illumination events
//! or by pixels.
//!
//! Invariant: a candidate is compared with the model's own effects refitted on the
//! same samples ([`Refit::Full`]) or with the model as it is ([`Refit::Candidate`]),
//! never with a fit on other samples.

use super::base::View;
use super::config::Refit;
use super::data::Sequence;
use super::eval::{self, Samples};
pub use super::marked::Judge;
use super::spread;
use crate::error::Result;
use crate::model::params::ModelParams;
use serde::Serialize;
use std::borrow::Cow;
use std::sync::OnceLock;

/// The refit must lower the BIC by more than this ("very strong" evidence).
pub const DBIC_MAX: f64 = -10.0;

/// The effect fitted on some illuminations must remove this fraction of the
/// normalised residual RMS of the others.
pub const HELD_OUT_MIN_GAIN: f64 = 0.2;

/// `delta_BIC = m ln(RSS_1/RSS_0) + k ln m` of adding `k` parameters (module docs) over
/// `m` cells.
pub fn delta_bic(rss0: f64, rss1: f64, k: usize, m: usize) -> f64 {
    let m = m as f64;
    m * (rss1 / rss0).ln() + k as f64 * m.ln()
}

/// A held-out test cell is "moved" by the candidate when its normalised residual
/// changes by at least this much (one unit of the cell's own sampling error).
pub const MOVED_Z: f64 = 1.0;

/// The fewest sampled pixels in each half of a held-out split by pixels (one
/// illumination event).
pub const MIN_HELD_OUT_PIXELS: usize = 50;

/// How many times the candidate's predicted change is moved to other samples
/// (`permuted_change`) to calibrate the pixel reference's held-out gain: a gain
/// larger than every permuted one has a chance of at most `1 / (PERMUTATIONS + 1)`
/// (0.05) when the change carries nothing about where it is applied.
pub const PERMUTATIONS: usize = 19;

/// The least pooled held-out gain against the pixel reference (or the judge that stands
/// for it, [`Judge`]) that counts: 1 % of its RMS. Beyond the permutations a gain is
/// not chance, but a candidate that takes less than 1 % of the residual RMS (about 2 %
/// of its sum of squares) changes nothing a flag could show, and the permutations'
/// chance of 1 in 20 per candidate still lets one through now and then. Measured on the
/// second generator's campaigns (64 x 64): a soak refined to no effect on a
/// nothing-hidden campaign with dark pixels (seed 3) beat its 19 permutations with a gain
/// of 0.00006; the effects found where they are hidden gain 0.14-0.26 (`soak:capture`,
/// seeds 1-5), 0.15 and 0.48 (`temperature:arrhenius`, seeds 1-2), 0.06
/// (`capacity:ceiling`, seed 2), 0.53 (`populations:smooth`, seed 1, by tile).
pub const PIXEL_HELD_OUT_MIN_GAIN: f64 = 0.01;

/// The seed of the permutations (ChaCha8; the fold's index is added).
const PERMUTATION_SEED: u64 = 0x005e_ed0f_9e71;

/// The model's own effects that a [`Refit::Full`] refits (those with fitted
/// parameters); none for [`Refit::Candidate`].
pub(super) fn own_effects(params: &ModelParams, refit: Refit) -> Vec<String> {
    if refit == Refit::Candidate {
        return Vec::new();
    }
    params
        .effects
        .iter()
        .filter(|e| {
            crate::model::effects::lookup(&e.name)
                .is_some_and(|d| d.params.iter().any(|p| e.fits(p)))
        })
        .map(|e| e.name.clone())
        .collect()
}

/// The model's own effects (`own`) refitted on `samples`, or the model itself when
/// there are none.
pub(super) fn refit_own(
    params: &ModelParams,
    own: &[String],
    seq: &Sequence,
    samples: &Samples,
) -> Result<ModelParams> {
    if own.is_empty() {
        return Ok(params.clone());
    }
    Ok(crate::calib::effects::fit(params, own, seq, samples)?.0)
}

/// The samples a candidate is fitted on: `samples`, with the per-illumination cells
/// split by the neighbour contrast ([`eval::Cells::Neighbours`]) for a candidate acting
/// on the neighbours ([`super::marked::acts_on_neighbours`]), so that its fit sees the
/// few pixels next to far brighter ones it acts on most, in cells of their own, instead
/// of a small share of their fluence's cells (measured on the second generator's
/// `blooming:field` campaign, 64 x 64, seed 1: `blooming` fitted on the
/// per-illumination cells moves no cell; on the split ones, `fraction` 0.0015 halves
/// the excess of the pixels next to the pinholes over the flexible base).
pub(super) fn fitting_samples<'a>(
    names: &[&str],
    samples: &'a Samples,
) -> std::borrow::Cow<'a, Samples> {
    if samples.cells == eval::Cells::Illumination && super::marked::acts_on_neighbours(names) {
        std::borrow::Cow::Owned(samples.clone().with_cells(eval::Cells::Neighbours))
    } else {
        std::borrow::Cow::Borrowed(samples)
    }
}

/// [`fit_described`], then the candidates' fitted values refined against their judge
/// ([`super::polish`], [`Judge`]) on the same samples: the refined model, and the
/// least-squares fit's report (its RSS the description's minimum, what a change in BIC
/// compares; its values those before the refinement).
pub(super) fn fit_candidate(
    base: &ModelParams,
    own: &[String],
    start: Option<&ModelParams>,
    names: &[&str],
    seq: &Sequence,
    samples: &Samples,
) -> Result<(ModelParams, crate::calib::effects::EffectFit)> {
    // split once: `fit_described` keeps samples already split as they are
    let samples = fitting_samples(names, samples);
    let (fitted, fit) = fit_described(base, own, start, names, seq, &samples)?;
    Ok((super::polish::polish(fitted, names, seq, &samples)?, fit))
}

/// `base` (the model, its own effects refitted as [`Refit`] says) with the candidate
/// effects `names` (`--with` arguments: one, or a pair in the joint check) fitted on
/// `samples` together with `own` by least squares against the measurements'
/// description; `start` holds the candidates at the values to start from (else their
/// defaults). Fitted on [`fitting_samples`]. The report's RSS is the description's
/// minimum over the values freed, what a change in BIC compares.
pub(super) fn fit_described(
    base: &ModelParams,
    own: &[String],
    start: Option<&ModelParams>,
    names: &[&str],
    seq: &Sequence,
    samples: &Samples,
) -> Result<(ModelParams, crate::calib::effects::EffectFit)> {
    let mut m = base.clone();
    let started: Vec<_> = start
        .map(|s| {
            s.effects
                .iter()
                .filter(|e| {
                    names
                        .iter()
                        .any(|n| n.split(':').next() == Some(e.name.as_str()))
                })
                .cloned()
                .collect()
        })
        .unwrap_or_default();
    if !started.is_empty() {
        // `base`'s knots were calibrated without the candidates: rescale them for
        // their start values, as the fit does for every value it tries
        let from = crate::calib::knots::scale_of(base, seq)?;
        m.effects.extend(started);
        if let Some((s_from, ramp)) = from {
            crate::calib::knots::rescale(&s_from, &mut m, &ramp)?;
        }
    }
    let mut all = own.to_vec();
    all.extend(names.iter().map(|n| n.to_string()));
    crate::calib::effects::fit(&m, &all, seq, &fitting_samples(names, samples))
}

/// The `--with` argument that adds effect `name` of `fitted` with every fitted
/// or pinned parameter held at its value (four significant digits).
pub(super) fn held_with_arg(fitted: &ModelParams, name: &str) -> Option<String> {
    let e = fitted.effects.iter().find(|e| e.name == name)?;
    let def = crate::model::effects::lookup(name)?;
    let held: Vec<String> = def
        .params
        .iter()
        .filter(|p| p.fitted || e.fixed.iter().any(|f| f == p.name))
        .filter_map(|p| {
            let v = e.params.get(p.name)?.as_f64()?;
            Some(format!("{}={}", p.name, significant(v, 4)))
        })
        .collect();
    Some(if held.is_empty() {
        name.to_string()
    } else {
        format!("{name}:{}", held.join(","))
    })
}

/// `v` rounded to `digits` significant digits.
fn significant(v: f64, digits: i32) -> f64 {
    if v == 0.0 || !v.is_finite() {
        return v;
    }
    let scale = 10f64.powi(digits - 1 - v.abs().log10().floor() as i32);
    (v * scale).round() / scale
}

/// One half of the held-out check.
#[derive(Debug, Clone, Serialize)]
pub struct Fold {
    /// What the halves split: `events` (illumination events alternately) or `pixels`
    /// (their sampled pixels alternately: one event, or an event-level covariate whose
    /// values the event halves do not both hold).
    pub split: &'static str,
    pub fit_events: Vec<u64>,
    pub test_events: Vec<u64>,
    pub test_cells: usize,
    pub rms_before: f64,
    pub rms_after: f64,
    /// Test cells whose `z` the fitted effect moves by at least [`MOVED_Z`].
    pub moved_cells: usize,
    pub rms_before_moved: f64,
    pub rms_after_moved: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct HeldOut {
    pub folds: Vec<Fold>,
    /// Pooled over the folds' test cells.
    pub rms_before: f64,
    pub rms_after: f64,
    /// The gated gain: `1 - rms_after / rms_before` over all test cells.
    pub gain: f64,
    pub passes: bool,
    /// Pooled over the folds' moved cells (NaN when there are none); reported, not
    /// gated (module docs).
    pub moved_cells: usize,
    pub rms_before_moved: f64,
    pub rms_after_moved: f64,
    pub gain_moved_cells: f64,
    /// The same halves against the pixel reference ([`super::base::predict_scaled`],
    /// fitted on each test half alone on the prediction without and with the
    /// candidate); None when a fold's cells differ.
    pub pixel_reference: Option<PixelHeldOut>,
}

impl HeldOut {
    /// The gain against the pixel reference held out (NaN without one).
    pub fn pixel_gain(&self) -> f64 {
        self.pixel_reference.as_ref().map_or(f64::NAN, |p| p.gain)
    }
}

/// The held-out check against the pixel reference: what the candidate fitted on one
/// half does to the pixel reference of the other half ([`HeldOut::pixel_reference`]).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PixelHeldOut {
    /// Pooled over the folds' test cells.
    pub rms_before: f64,
    pub rms_after: f64,
    /// `1 - rms_after / rms_before`.
    pub gain: f64,
    /// Each fold's gain, in fold order.
    pub fold_gains: Vec<f64>,
    /// The pooled gain on the footing of the permutations (NaN when not computed): for
    /// [`Permuted::Change`], with the shared correction held at the fit without the
    /// candidate ([`super::base::predict_scaled_held`]), each pixel's own terms
    /// refitted; for [`Permuted::Temperature`], `gain`.
    pub gain_held: f64,
    /// The pooled gain of each of the [`PERMUTATIONS`] permutations, on the footing of
    /// `gain_held`; empty when a fold does not gain (not computed) or, for
    /// [`Permuted::Temperature`], when the sequence's temperatures have fewer
    /// arrangements.
    pub permuted_gains: Vec<f64>,
    /// What was permuted.
    pub permuted: Permuted,
    /// What the candidate is judged against: the rest of this record is on its cells.
    pub judge: Judge,
    /// The candidate moves the model's clock ([`Permuted::Temperature`]) and the
    /// sequence's temperatures have fewer than [`PERMUTATIONS`] other arrangements
    /// among its illumination events (`permuted_temperatures`): its null cannot be
    /// drawn, so it does not pass, whatever it gains.
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub too_few_arrangements: bool,
}

/// What the permutations of a held-out check move.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Permuted {
    /// The candidate's predicted change, to other pixels and illumination events
    /// (`permuted_change`).
    Change,
    /// The focal-plane temperatures, among the illumination events
    /// (`permuted_temperatures`): for a candidate whose rate hooks change the model's
    /// clock ([`super::base::Clock`]), which the pixel reference's decay follows, so that no change
    /// of the prediction alone stands for it. The candidate is run at each arrangement
    /// and the pixel reference fitted on it in full.
    Temperature,
}

impl Permuted {
    /// "permutations of its change", as the verdict says it.
    pub fn phrase(self) -> &'static str {
        match self {
            Permuted::Change => "permutations of its change",
            Permuted::Temperature => {
                "arrangements of the focal-plane temperatures among the illumination events"
            }
        }
    }
}

impl PixelHeldOut {
    /// The candidate gains, pooled and in each fold.
    pub fn gains_in_each_fold(&self) -> bool {
        self.gain > 0.0 && self.fold_gains.iter().all(|&g| g > 0.0)
    }

    /// It gains in each fold, but its null could not be drawn
    /// ([`PixelHeldOut::too_few_arrangements`]): a gain that cannot be told from chance.
    pub fn gains_uncalibrated(&self) -> bool {
        self.too_few_arrangements && self.gains_in_each_fold()
    }

    /// The largest permuted gain (NaN when none was computed).
    pub fn permuted_max(&self) -> f64 {
        self.permuted_gains.iter().copied().fold(f64::NAN, f64::max)
    }

    /// Whether the candidate predicts the held-out halves: it gains in each fold and,
    /// on the footing of the permutations (`gain_held`), more than every permutation
    /// of its change (a chance of at most `1 / (PERMUTATIONS + 1)` when the change is
    /// unrelated to where it is applied).
    pub fn beats_permutations(&self) -> bool {
        self.gains_in_each_fold()
            && self.permuted_gains.len() == PERMUTATIONS
            && self.gain_held > self.permuted_max()
    }

    /// Whether the candidate predicts the held-out halves by enough to count: it beats
    /// the permutations ([`PixelHeldOut::beats_permutations`]) with a pooled gain of at
    /// least [`PIXEL_HELD_OUT_MIN_GAIN`].
    pub fn predicts_held_out(&self) -> bool {
        self.beats_permutations() && self.gain >= PIXEL_HELD_OUT_MIN_GAIN
    }
}

/// One fold's pixel-reference sums: the candidate's change, and with the shared
/// correction held ([`super::base::predict_scaled_held`]) the change and its
/// permutations (in permutation order; None and empty when not computed).
struct PixelFold {
    permuted: Permuted,
    real: Option<HeldOutSums>,
    /// The candidate's change with the shared correction held (what the permutations
    /// are compared with).
    held: Option<HeldOutSums>,
    null: Vec<Option<HeldOutSums>>,
}

/// The folds' pixel-reference sums, pooled; a fold without them spoils the pool.
#[derive(Debug, Clone, Default)]
struct PixelSums {
    permuted: Option<Permuted>,
    all: HeldOutSums,
    fold_gains: Vec<f64>,
    /// Per permutation, pooled over the folds (None once a fold lacks it).
    null: Vec<Option<HeldOutSums>>,
    /// The candidate's change with the correction held, pooled (None once a fold lacks
    /// it).
    held: Option<HeldOutSums>,
    incomplete: bool,
}

impl PixelSums {
    fn add(&mut self, fold: PixelFold) {
        let first = self.fold_gains.is_empty() && !self.incomplete;
        // the folds' permutations pool only when they move the same thing
        if self.permuted.is_some_and(|p| p != fold.permuted) {
            self.null.clear();
        }
        self.permuted = Some(fold.permuted);
        match fold.real {
            Some(f) => {
                self.fold_gains.push(f.gain());
                self.all.add(&f);
            }
            None => self.incomplete = true,
        }
        if first {
            self.held = fold.held;
            self.null = fold.null;
            return;
        }
        self.held = HeldOutSums::pooled(self.held.take(), fold.held);
        if self.null.len() == fold.null.len() {
            for (pooled, f) in self.null.iter_mut().zip(fold.null) {
                *pooled = HeldOutSums::pooled(pooled.take(), f);
            }
        } else {
            self.null.clear();
        }
    }

    fn result(&self) -> Option<PixelHeldOut> {
        if self.incomplete || self.all.cells == 0 {
            return None;
        }
        let (rms_before, rms_after) = self.all.rms_all();
        let permuted_gains = self
            .null
            .iter()
            .map(|n| n.as_ref().map(HeldOutSums::gain))
            .collect::<Option<Vec<f64>>>()
            .unwrap_or_default();
        Some(PixelHeldOut {
            rms_before,
            rms_after,
            gain: self.all.gain(),
            fold_gains: self.fold_gains.clone(),
            gain_held: self.held.as_ref().map_or(f64::NAN, HeldOutSums::gain),
            permuted_gains,
            permuted: self.permuted.unwrap_or(Permuted::Change),
            judge: Judge::PixelReference,
            too_few_arrangements: false,
        })
    }
}

/// The candidate's predicted change `after - before` moved to other samples of `s`
/// and added to `before`: the pixels' changes permuted at random among the pixels
/// and, when `s` holds more than one illumination event, the events' changes shifted
/// cyclically by a random nonzero step (a row takes the change of the row at the same
/// position after the other event's illumination, or that event's last row). A
/// candidate's change that follows its covariate (fluence, neighbours, duration,
/// history) lands where the covariate differs; one that carries nothing about where it
/// applies predicts as well moved as in place. A change that is not finite moves as
/// zero; a `before` that is not finite stays so.
fn permuted_change(
    s: &Samples,
    before: &[f64],
    after: &[f64],
    rng: &mut rand_chacha::ChaCha8Rng,
) -> Vec<f64> {
    use rand::seq::SliceRandom;
    use rand::Rng;
    let np = s.npix();
    let mut events = s.event.clone();
    events.sort_unstable();
    events.dedup();
    let blocks: Vec<Vec<usize>> = events
        .iter()
        .map(|&e| (0..s.event.len()).filter(|&r| s.event[r] == e).collect())
        .collect();
    let shift = if blocks.len() > 1 {
        rng.random_range(1..blocks.len())
    } else {
        0
    };
    let mut source_row = vec![0; s.event.len()];
    for (b, rows) in blocks.iter().enumerate() {
        let from = &blocks[(b + shift) % blocks.len()];
        for (k, &r) in rows.iter().enumerate() {
            source_row[r] = from[k.min(from.len() - 1)];
        }
    }
    let mut pixel: Vec<usize> = (0..np).collect();
    pixel.shuffle(rng);
    (0..before.len())
        .map(|i| {
            let j = source_row[i / np] * np + pixel[i % np];
            let d = after[j] - before[j];
            before[i] + if d.is_finite() { d } else { 0.0 }
        })
        .collect()
}

/// [`PERMUTATIONS`] arrangements of `seq`'s focal-plane temperatures among its
/// illumination events, each different from the one recorded and from one another in
/// some exposure's temperature bin ([`super::contrast::temperature_bin`]),
/// drawn at random (seeded): an event's block (its illumination and the exposures
/// until the next one) takes another block's temperatures, exposure by exposure (the
/// other block's last where it is shorter); exposures before the first illumination
/// keep theirs. A real candidate beats all of them by chance at most once in
/// `PERMUTATIONS + 1` when where the temperatures stand carries nothing. Empty when the
/// temperatures have fewer such arrangements (or none was found in
/// `ARRANGEMENT_DRAWS` draws): the check then cannot be calibrated.
fn permuted_temperatures(seq: &Sequence) -> Vec<Vec<Option<f64>>> {
    use rand::seq::SliceRandom;
    const ARRANGEMENT_DRAWS: usize = 50 * PERMUTATIONS;
    let recorded = seq.temperatures_k();
    let n = recorded.len();
    let starts = &seq.illuminations;
    let blocks: Vec<std::ops::Range<usize>> = (0..starts.len())
        .map(|b| starts[b]..starts.get(b + 1).copied().unwrap_or(n))
        .collect();
    let mut rng = <rand_chacha::ChaCha8Rng as rand::SeedableRng>::seed_from_u64(PERMUTATION_SEED);
    // arrangements alike in every exposure's temperature bin are one
    let bins = |t: &[Option<f64>]| -> Vec<Option<i64>> {
        t.iter()
            .map(|x| x.map(super::contrast::temperature_bin))
            .collect()
    };
    let mut seen = vec![bins(&recorded)];
    let mut out = Vec::new();
    let mut order: Vec<usize> = (0..blocks.len()).collect();
    for _ in 0..ARRANGEMENT_DRAWS {
        if out.len() == PERMUTATIONS {
            break;
        }
        order.shuffle(&mut rng);
        let mut temps = recorded.clone();
        for (to, &from) in blocks.iter().zip(&order) {
            let from = &blocks[from];
            for (j, k) in to.clone().enumerate() {
                temps[k] = recorded[(from.start + j).min(from.end - 1)];
            }
        }
        let key = bins(&temps);
        if !seen.contains(&key) {
            seen.push(key);
            out.push(temps);
        }
    }
    if out.len() < PERMUTATIONS {
        out.clear();
    }
    out
}

/// One fold's test half, its predictions without and with the candidate (each with
/// its model's view), for the judge's sums: the candidate's change, on the
/// permutations' footing, and the permutations (None and empty where the fold does not
/// gain).
struct Judged<'a> {
    ts: &'a Samples,
    before: (&'a View, &'a [f64]),
    /// The pixel reference fitted on the prediction without the candidate, shared by
    /// every candidate held out on the same fold ([`Footing`]).
    before_scaled: &'a OnceLock<super::base::Scaled>,
    after: (&'a View, &'a [f64]),
    fitted: &'a ModelParams,
    response: &'a crate::model::response::Response,
    arrangements: &'a OnceLock<Vec<Vec<Option<f64>>>>,
    seed: u64,
}

type JudgedSums = (
    Option<HeldOutSums>,
    Option<HeldOutSums>,
    Vec<Option<HeldOutSums>>,
);

impl Judged<'_> {
    fn clock_moved(&self) -> bool {
        self.after.0.clock != self.before.0.clock
    }

    fn rng(&self) -> rand_chacha::ChaCha8Rng {
        <rand_chacha::ChaCha8Rng as rand::SeedableRng>::seed_from_u64(self.seed)
    }

    /// Against the pixel reference fitted on the test half alone, on either
    /// prediction, each on its model's clock; the permutations only where the fold
    /// gains (a fold that does not gain fails the gate whatever they give), compared
    /// with the candidate on one footing, the shared correction held at the fit without
    /// the candidate.
    fn pixel_reference(&self, seq: &Sequence) -> Result<JudgedSums> {
        let (ts, response) = (self.ts, self.response);
        let (before_view, before_current) = self.before;
        let (after_view, after_current) = self.after;
        let scaled_before = self.before_scaled.get_or_init(|| {
            super::base::predict_scaled(seq, before_view, ts, before_current, response)
        });
        let pixel_before = scaled_before.cells(ts);
        let real = HeldOutSums::of(
            &pixel_before,
            &super::base::predict_scaled(seq, after_view, ts, after_current, response).cells(ts),
        );
        Ok(match real {
            Some(r) if r.after < r.before && self.clock_moved() => {
                // the candidate at each arrangement of the temperatures, on a full fit
                let null = self
                    .arrangements
                    .get_or_init(|| permuted_temperatures(seq))
                    .iter()
                    .map(|temps_k| {
                        let current =
                            eval::predict_at_temperatures(self.fitted, seq, ts, false, temps_k)?
                                .current;
                        let view = View::of_model_at_temperatures(self.fitted, seq, temps_k);
                        let scaled =
                            super::base::predict_scaled(seq, &view, ts, &current, response);
                        Ok(HeldOutSums::of(&pixel_before, &scaled.cells(ts)))
                    })
                    .collect::<Result<Vec<_>>>()?;
                (Some(r), Some(r), null)
            }
            Some(r) if r.after < r.before => {
                let held = |current: &[f64]| {
                    super::base::predict_scaled_held(seq, ts, current, response, scaled_before)
                        .cells(ts)
                };
                let held_before = held(before_current);
                let mut rng = self.rng();
                let null = (0..PERMUTATIONS)
                    .map(|_| {
                        let moved = permuted_change(ts, before_current, after_current, &mut rng);
                        HeldOutSums::of(&held_before, &held(&moved))
                    })
                    .collect();
                (
                    real,
                    HeldOutSums::of(&held_before, &held(after_current)),
                    null,
                )
            }
            _ => (real, None, Vec::new()),
        })
    }

    /// Against the flexible base on the cells of `judge` ([`super::marked`]: the
    /// pixels next to far brighter ones, or the tiles of the array), fitted on the test
    /// half on each prediction (a fit cheap enough to repeat for every permutation, so
    /// the candidate's own change is the permutations' footing).
    fn flexible(&self, seq: &Sequence, judge: Judge) -> JudgedSums {
        let ts = self.ts;
        let (before_view, before_current) = self.before;
        let (after_view, after_current) = self.after;
        let cells =
            |view: &View, current: &[f64]| super::marked::cells(judge, seq, view, ts, current);
        let judged_before = cells(before_view, before_current);
        let real = HeldOutSums::of(&judged_before, &cells(after_view, after_current));
        let null = match real {
            Some(r) if r.after < r.before => {
                let mut rng = self.rng();
                (0..PERMUTATIONS)
                    .map(|_| {
                        let moved = permuted_change(ts, before_current, after_current, &mut rng);
                        HeldOutSums::of(&judged_before, &cells(after_view, &moved))
                    })
                    .collect()
            }
            _ => Vec::new(),
        };
        (real, real, null)
    }
}

/// What every held-out check of one diagnosis stands on: the model diagnosed, its
/// prediction of the samples (early release off, [`eval::predict`]), the samples and
/// what a refit frees; and, per way of splitting the samples and per fold, what a
/// candidate is compared with there (the model's own effects refitted on the fit half,
/// their prediction of the test half and the pixel reference fitted on it), computed by
/// the first check that needs it and shared by the others.
///
/// # Invariants
/// - A fold's comparison depends only on the fields and on the fold (the split, the
///   cells the fit half is fitted on, the half), and the computation is deterministic,
///   so sharing it changes no number a check reports.
pub struct Footing<'a> {
    pub params: &'a ModelParams,
    pub base_current: &'a [f64],
    pub seq: &'a Sequence,
    pub samples: &'a Samples,
    pub refit: Refit,
    /// Per [`Footing::slot`].
    before: [OnceLock<Before>; 8],
}

impl<'a> Footing<'a> {
    pub fn new(
        params: &'a ModelParams,
        base_current: &'a [f64],
        seq: &'a Sequence,
        samples: &'a Samples,
        refit: Refit,
    ) -> Self {
        Footing {
            params,
            base_current,
            seq,
            samples,
            refit,
            before: Default::default(),
        }
    }

    /// The slot of a fold: split by pixels or by events, fitted on the neighbours'
    /// cells or the samples' own ([`fitting_samples`]), the half `h` it is fitted on.
    fn slot(by_pixels: bool, neighbour_cells: bool, h: usize) -> usize {
        4 * usize::from(by_pixels) + 2 * usize::from(neighbour_cells) + h.min(1)
    }
}

/// A fold's comparison without the candidate ([`Footing`]).
struct Before {
    /// The model's own effects refitted on the fit half; None: the model itself.
    model: Option<ModelParams>,
    /// Its cells' z on the test half.
    cells: Vec<(Vec<i64>, eval::GroupStat)>,
    /// Its prediction of the test half.
    current: Vec<f64>,
    view: View,
    /// The pixel reference fitted on `current`, when a judge needs it.
    scaled: OnceLock<super::base::Scaled>,
}

impl Before {
    fn new(
        model: Option<ModelParams>,
        cells: Vec<(Vec<i64>, eval::GroupStat)>,
        current: Vec<f64>,
        view: View,
    ) -> Self {
        Before {
            model,
            cells,
            current,
            view,
            scaled: OnceLock::new(),
        }
    }
}

/// Held-out check of the effects `names` (one candidate, or a pair in the joint check;
/// module docs): the halves are the events alternately, or the sampled pixels
/// alternately with one event or when an event half lacks a value of the effects'
/// event-level covariate (`halves_span`, over [`EVENT_LEVEL`]); None when split by
/// pixels with fewer than `2 MIN_HELD_OUT_PIXELS` pixels.
/// `start`: a model holding the effect at the values to start the fits from (the
/// full refit), else its defaults. The test halves' "before" is the footing's
/// `base_current` when its `refit` is [`Refit::Candidate`] (with [`Refit::Full`], the
/// model's own effects refitted on the fit half), computed once per fold for every
/// check on the same footing ([`Footing`]).
pub fn held_out(
    footing: &Footing,
    start: Option<&ModelParams>,
    names: &[&str],
) -> Result<Option<HeldOut>> {
    let Footing {
        params,
        base_current,
        seq,
        samples,
        refit,
        ..
    } = *footing;
    let own = own_effects(params, refit);
    let events = samples.events();
    // the two halves: illumination events alternately when each half holds every value
    // of the candidates' event-level covariates, else (one event, or a value that only
    // some events hold) the sampled pixels alternately (in raster order)
    let alternate = |all: Vec<usize>| -> [Vec<usize>; 2] {
        [0, 1].map(|h| all.iter().copied().skip(h).step_by(2).collect())
    };
    let by_pixels = events.len() < 2 || !halves_span(names, samples, &alternate(events.clone()));
    if by_pixels && samples.npix() < 2 * MIN_HELD_OUT_PIXELS {
        return Ok(None);
    }
    let half = alternate(if by_pixels {
        (0..samples.npix()).collect()
    } else {
        events.clone()
    });
    let idx = |v: &[usize]| -> Vec<u64> {
        v.iter()
            .map(|&e| seq.exposures[e].meta.exposure_index)
            .collect()
    };
    let split = |h: usize| -> (Samples, Samples, Vec<f64>) {
        let (fit, test) = (&half[h], &half[1 - h]);
        if by_pixels {
            (
                samples.columns(fit),
                samples.columns(test),
                samples.columns_of(base_current, test),
            )
        } else {
            let test_rows = samples.row_indices(|e| test.contains(&e));
            (
                samples.rows_where(|e| fit.contains(&e)),
                samples.rows(&test_rows),
                samples.rows_of(base_current, &test_rows),
            )
        }
    };
    // a rate hook's permutations: the temperatures' arrangements, the same in both
    // folds, drawn when a candidate moves the clock
    let arrangements = OnceLock::new();
    // the user's model's response weighs the illuminations in both pixel references
    let response = crate::model::response::Response::new(&params.amplitude_knots);
    let judge = Judge::of(names);
    // the two folds in parallel, combined in fold order
    let fold = |h: usize| -> Result<(Option<HeldOutSums>, PixelFold)> {
        let (fs, ts, ts_base) = split(h);
        let fs = fitting_samples(names, &fs);
        let slot = &footing.before[Footing::slot(by_pixels, matches!(fs, Cow::Owned(_)), h)];
        let before = match slot.get() {
            Some(b) => b,
            None => {
                let b = if own.is_empty() {
                    // `params`' own prediction of the test samples: already computed
                    let cells = spread::model_cell_z(params, &ts, &ts_base);
                    Before::new(None, cells, ts_base, View::of_model(params, seq))
                } else {
                    // the model's own effects refitted on the fit half's samples
                    // (from values fitted on all samples)
                    let base = refit_own(params, &own, seq, &fs)?;
                    let current = eval::predict(&base, seq, &ts, false)?.current;
                    let cells = spread::model_cell_z(&base, &ts, &current);
                    let view = View::of_model(&base, seq);
                    Before::new(Some(base), cells, current, view)
                };
                slot.get_or_init(|| b)
            }
        };
        let fitted = if own.is_empty() {
            let owned: Vec<String> = names.iter().map(|n| n.to_string()).collect();
            let (fitted, _) =
                crate::calib::effects::fit(start.unwrap_or(params), &owned, seq, &fs)?;
            super::polish::polish(fitted, names, seq, &fs)?
        } else {
            // the candidate with the model's own effects, refitted as they were alone
            let base = before.model.as_ref().unwrap_or(params);
            fit_candidate(base, &own, start, names, seq, &fs)?.0
        };
        let after_current = eval::predict(&fitted, seq, &ts, false)?.current;
        let after = spread::model_cell_z(&fitted, &ts, &after_current);
        let after_view = View::of_model(&fitted, seq);
        let judged = Judged {
            ts: &ts,
            before: (&before.view, &before.current),
            before_scaled: &before.scaled,
            after: (&after_view, &after_current),
            fitted: &fitted,
            response: &response,
            arrangements: &arrangements,
            seed: PERMUTATION_SEED + h as u64,
        };
        let (real, held, null) = match judge {
            Judge::PixelReference => judged.pixel_reference(seq)?,
            Judge::NextToBrighter | Judge::Position => judged.flexible(seq, judge),
        };
        let permuted = if judged.clock_moved() {
            Permuted::Temperature
        } else {
            Permuted::Change
        };
        Ok((
            HeldOutSums::of(&before.cells, &after),
            PixelFold {
                permuted,
                real,
                held,
                null,
            },
        ))
    };
    let (f0, f1) = rayon::join(|| fold(0), || fold(1));
    let mut folds = Vec::new();
    let mut all = HeldOutSums::default();
    let mut pixel = PixelSums::default();
    for (h, (r, p)) in [f0?, f1?].into_iter().enumerate() {
        pixel.add(p);
        let Some(r) = r else { continue };
        let (fit_ev, test_ev) = if by_pixels {
            (&events, &events)
        } else {
            (&half[h], &half[1 - h])
        };
        all.add(&r);
        folds.push(Fold {
            split: if by_pixels { "pixels" } else { "events" },
            fit_events: idx(fit_ev),
            test_events: idx(test_ev),
            test_cells: r.cells,
            rms_before: r.rms_all().0,
            rms_after: r.rms_all().1,
            moved_cells: r.moved,
            rms_before_moved: r.rms_moved().0,
            rms_after_moved: r.rms_moved().1,
        });
    }
    if all.cells == 0 {
        return Ok(None);
    }
    let ((rb, ra), (rbm, ram)) = (all.rms_all(), all.rms_moved());
    let gain = 1.0 - ra / rb;
    Ok(Some(HeldOut {
        folds,
        rms_before: rb,
        rms_after: ra,
        gain,
        passes: gain >= HELD_OUT_MIN_GAIN,
        pixel_reference: pixel.result().map(|p| PixelHeldOut {
            too_few_arrangements: p.permuted == Permuted::Temperature
                && arrangements.get().is_some_and(Vec::is_empty),
            judge,
            ..p
        }),
        moved_cells: all.moved,
        rms_before_moved: rbm,
        rms_after_moved: ram,
        gain_moved_cells: 1.0 - ram / rbm,
    }))
}

/// The covariates that take one value per illumination event (its cells' bins,
/// [`eval::bin_of`]).
pub const EVENT_LEVEL: [&str; 2] = ["illumination_time", "temperature"];

/// Whether each half of the events (`halves`) holds every value (binned as the cells
/// bin it) that the samples hold of the event-level covariates the effects `names`
/// act on (`--with` arguments allowed); true when none acts on one. A half without
/// some value would test the effect only where it extrapolates: fitted at 78 K and
/// 80 K, judged at 82 K.
fn halves_span(names: &[&str], samples: &Samples, halves: &[Vec<usize>; 2]) -> bool {
    let covariates = names.iter().filter_map(|n| {
        let def = crate::model::effects::lookup(n.split(':').next().unwrap_or(n))?;
        EVENT_LEVEL
            .contains(&def.covariate)
            .then_some(def.covariate)
    });
    let values = |c: &str, of: Option<&[usize]>| -> std::collections::BTreeSet<i64> {
        (0..samples.exposures.len())
            .filter(|&r| of.is_none_or(|ev| ev.contains(&samples.event[r])))
            .filter_map(|r| eval::bin_of(samples, c, r * samples.npix()))
            .collect()
    };
    covariates.into_iter().all(|c| {
        let all = values(c, None);
        halves.iter().all(|h| values(c, Some(h)) == all)
    })
}

/// Sums of squared normalised residuals of one held-out test half, before and after
/// the candidate, over all its cells and over the cells the candidate moves.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
struct HeldOutSums {
    cells: usize,
    before: f64,
    after: f64,
    moved: usize,
    before_moved: f64,
    after_moved: f64,
}

impl HeldOutSums {
    /// None when the two cell lists differ (a prediction not finite somewhere changed a
    /// cell's membership) or are empty.
    fn of(
        before: &[(Vec<i64>, eval::GroupStat)],
        after: &[(Vec<i64>, eval::GroupStat)],
    ) -> Option<Self> {
        if before.is_empty()
            || before.len() != after.len()
            || before.iter().zip(after).any(|(b, a)| b.0 != a.0)
        {
            return None;
        }
        let mut s = HeldOutSums::default();
        for ((_, b), (_, a)) in before.iter().zip(after) {
            let (b2, a2) = (b.z * b.z, a.z * a.z);
            s.cells += 1;
            s.before += b2;
            s.after += a2;
            if (a.z - b.z).abs() >= MOVED_Z {
                s.moved += 1;
                s.before_moved += b2;
                s.after_moved += a2;
            }
        }
        Some(s)
    }

    fn add(&mut self, o: &HeldOutSums) {
        self.cells += o.cells;
        self.before += o.before;
        self.after += o.after;
        self.moved += o.moved;
        self.before_moved += o.before_moved;
        self.after_moved += o.after_moved;
    }

    /// Two folds' sums together; None when either is missing.
    fn pooled(a: Option<Self>, b: Option<Self>) -> Option<Self> {
        let (mut a, b) = (a?, b?);
        a.add(&b);
        Some(a)
    }

    /// `1 - RMS_after / RMS_before` over all cells.
    fn gain(&self) -> f64 {
        let (b, a) = self.rms_all();
        1.0 - a / b
    }

    /// `(before, after)` RMS over all cells.
    fn rms_all(&self) -> (f64, f64) {
        (
            Self::rms(self.before, self.cells),
            Self::rms(self.after, self.cells),
        )
    }

    /// `(before, after)` RMS over the moved cells (NaN when none moved).
    fn rms_moved(&self) -> (f64, f64) {
        (
            Self::rms(self.before_moved, self.moved),
            Self::rms(self.after_moved, self.moved),
        )
    }

    fn rms(sum: f64, n: usize) -> f64 {
        if n == 0 {
            f64::NAN
        } else {
            (sum / n as f64).sqrt()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::params::EffectSpec;

    /// The temperatures' arrangements (`permuted_temperatures`) on a campaign of six
    /// illuminations at 78, 80, 80, 80, 80 and 82 K (the family generator's form): 30
    /// arrangements of the events' temperatures, so 19 that differ from the one recorded
    /// and from one another, each a reordering of the events' blocks (each block at
    /// one event's temperatures); two events at 78 and 82 K have one other arrangement
    /// only, too few to calibrate the check.
    #[test]
    fn temperature_arrangements_reorder_the_events_and_differ_from_the_record() {
        let temps = [78.0, 80.0, 80.0, 80.0, 80.0, 82.0];
        let seq = super::super::base::tests::campaign_at(&temps);
        let recorded = seq.temperatures_k();
        let arrangements = permuted_temperatures(&seq);
        assert_eq!(arrangements.len(), PERMUTATIONS);
        // an event's temperature: its first dark's (the simulator's, within 0.01 K)
        let of_events = |t: &[Option<f64>]| -> Vec<f64> {
            seq.illuminations
                .iter()
                .map(|&a| (t[a + 1].unwrap() * 10.0).round() / 10.0)
                .collect()
        };
        let mut sorted_record = of_events(&recorded);
        sorted_record.sort_by(f64::total_cmp);
        assert_eq!(sorted_record, temps.to_vec());
        for (i, a) in arrangements.iter().enumerate() {
            assert_eq!(a.len(), recorded.len());
            assert_ne!(a, &recorded);
            assert!(arrangements[..i].iter().all(|b| b != a));
            let mut events = of_events(a);
            assert_ne!(events, of_events(&recorded));
            events.sort_by(f64::total_cmp);
            assert_eq!(events, temps.to_vec());
        }
        assert!(
            permuted_temperatures(&super::super::base::tests::campaign_at(&[78.0, 82.0]))
                .is_empty()
        );
    }

    /// A footing shared by several checks gives each the numbers it gives alone: on the
    /// campaign of `a_rate_hook_gains_...` (measured with `temperature` at 0.25 eV),
    /// `temperature` held out on a fresh footing and after `capacity` and `soak` on a
    /// shared one, with the model's own effects refitted (`refill` fitted) and without.
    #[test]
    fn a_shared_footing_changes_no_number() {
        use super::super::base::tests::{campaign_at, measured_as, model_with_temperature};
        let seq = campaign_at(&[78.0, 82.0, 80.0]);
        let mut model = ModelParams::default();
        model.effects.push(EffectSpec {
            name: "refill".into(),
            params: [("beta".to_string(), serde_json::json!(0.8))]
                .into_iter()
                .collect(),
            fixed: Default::default(),
        });
        let (s, base) = measured_as(&seq, &model_with_temperature(0.25), &model);
        for refit in [Refit::Candidate, Refit::Full] {
            let json = |f: &Footing, name: &str| {
                serde_json::to_string(&held_out(f, None, &[name]).unwrap()).unwrap()
            };
            let alone = json(&Footing::new(&model, &base, &seq, &s, refit), "temperature");
            let shared = Footing::new(&model, &base, &seq, &s, refit);
            let others = [json(&shared, "capacity"), json(&shared, "soak")];
            assert_eq!(json(&shared, "temperature"), alone, "{refit:?}");
            assert!(others.iter().all(|o| *o != alone), "{refit:?}");
        }
    }

    /// A rate hook where the temperatures have too few arrangements: a campaign of
    /// three illuminations at 78, 82 and 80 K (`base::tests::campaign_at`, 5 other
    /// arrangements), measured as the default model with `temperature` at 0.25 eV plus
    /// each exposure's noise. Held out against the default model, `temperature` gains
    /// on the pixel reference in each half; its null cannot be drawn, so the check says
    /// so (`too_few_arrangements`) and does not pass.
    #[test]
    fn a_rate_hook_gains_but_does_not_pass_where_the_temperatures_have_too_few_arrangements() {
        use super::super::base::tests::{campaign_at, measured_as, model_with_temperature};
        let seq = campaign_at(&[78.0, 82.0, 80.0]);
        let model = ModelParams::default();
        let (s, base) = measured_as(&seq, &model_with_temperature(0.25), &model);
        let footing = Footing::new(&model, &base, &seq, &s, Refit::Candidate);
        let h = held_out(&footing, None, &["temperature"])
            .unwrap()
            .expect("a held-out check");
        let p = h.pixel_reference.expect("the pixel reference held out");
        assert_eq!(p.permuted, Permuted::Temperature);
        assert!(p.fold_gains.iter().all(|&g| g > 0.0), "{p:?}");
        assert!(p.too_few_arrangements, "{p:?}");
        assert!(p.permuted_gains.is_empty(), "{p:?}");
        assert!(!p.beats_permutations());
    }

    /// One sampled pixel, one row per illumination event of the campaign in the family
    /// generator (`src/trapgen/scene.rs`): 481 s at 80 K except the second (120 s) and
    /// the last two (78 K, 82 K).
    fn campaign_rows() -> Samples {
        let rows = 6;
        let v = |x: f64| vec![x; rows];
        Samples {
            cells: eval::Cells::Pooled,
            statistic: eval::CellStatistic::Levels,
            stride: 0,
            pixels: vec![(0, 0)],
            exposures: (0..rows).collect(),
            measured: v(1.0),
            noise: v(0.01),
            shot_var_per_e_per_s: v(0.0),
            noise_scale: Default::default(),
            spread_rel: v(0.0),
            fluence_e: v(1e5),
            neighbour_excess_e: v(0.0),
            t_since_s: v(100.0),
            event: (0..rows).collect(),
            illumination_time_s: vec![481.0, 120.0, 481.0, 481.0, 481.0, 481.0],
            temperature_k: vec![80.0, 80.0, 80.0, 80.0, 78.0, 82.0],
            earlier_illuminations: (0..rows).map(|r| r as f64).collect(),
            radius: vec![0.5],
        }
    }

    /// Alternate events hold 120 s in one half only and 78 K and 82 K in one half each:
    /// an effect on duration or temperature is split by pixels; one on earlier
    /// illuminations, or on nothing event-level, by events. A temperature split that
    /// puts 78 K and 82 K in both halves is kept.
    #[test]
    fn event_halves_must_hold_every_value_of_an_event_level_covariate() {
        let s = campaign_rows();
        let alternate = [vec![0, 2, 4], vec![1, 3, 5]];
        assert!(!halves_span(&["soak"], &s, &alternate));
        assert!(!halves_span(&["temperature"], &s, &alternate));
        assert!(!halves_span(
            &["smooth_temperature:temp_lo=78,temp_hi=82"],
            &s,
            &alternate
        ));
        assert!(!halves_span(&["capacity", "temperature"], &s, &alternate));
        assert!(halves_span(&["capacity"], &s, &alternate));
        assert!(halves_span(&["populations"], &s, &alternate));
        let spanning = [vec![0, 2, 4, 5], vec![1, 3, 4, 5]];
        assert!(halves_span(&["temperature"], &s, &spanning));
        assert!(!halves_span(&["soak"], &s, &spanning));
    }

    /// The permuted change keeps `before` and the set of changes: pixels permuted, and
    /// with several events each row takes the change of the same position after
    /// another event (never its own); a change that is not finite moves as zero.
    #[test]
    fn a_permuted_change_moves_the_change_to_other_pixels_and_events() {
        let mut s = campaign_rows();
        let np = 4;
        s.pixels = vec![(0, 0); np];
        let n = s.exposures.len() * np;
        let before: Vec<f64> = (0..n).map(|i| i as f64).collect();
        // the change codes its row (event) and pixel
        let change = |i: usize| 100.0 * (i / np) as f64 + (i % np) as f64;
        let after: Vec<f64> = (0..n).map(|i| before[i] + change(i)).collect();
        let mut rng = <rand_chacha::ChaCha8Rng as rand::SeedableRng>::seed_from_u64(1);
        let mut moved_pixel = false;
        for _ in 0..PERMUTATIONS {
            let m = permuted_change(&s, &before, &after, &mut rng);
            let d: Vec<f64> = m.iter().zip(&before).map(|(a, b)| a - b).collect();
            let mut pixels: Vec<usize> = (0..np).map(|p| (d[p] % 100.0) as usize).collect();
            moved_pixel |= pixels.iter().enumerate().any(|(p, &q)| p != q);
            pixels.sort_unstable();
            assert_eq!(pixels, [0, 1, 2, 3]);
            for r in 0..s.exposures.len() {
                // one row per event here: the source row is another event's
                let source = (d[r * np] / 100.0) as usize;
                assert_ne!(source, r);
                assert!(d[r * np..(r + 1) * np]
                    .iter()
                    .all(|&x| (x / 100.0) as usize == source));
            }
        }
        assert!(moved_pixel);
        // one event: rows keep their own change, only pixels move
        s.event = vec![0; s.exposures.len()];
        let mut nan_after = after.clone();
        nan_after[1] = f64::NAN;
        let m = permuted_change(&s, &before, &nan_after, &mut rng);
        for r in 0..s.exposures.len() {
            for p in 0..np {
                let d = m[r * np + p] - before[r * np + p];
                assert!(d == 0.0 || (d / 100.0) as usize == r, "{r} {p} {d}");
            }
        }
    }

    fn cell(key: i64, z: f64) -> (Vec<i64>, eval::GroupStat) {
        let g = eval::GroupStat {
            n: 10,
            measured_p95_e_per_s: 0.0,
            predicted_p95_e_per_s: 0.0,
            measured_median_e_per_s: 0.0,
            sigma_e_per_s: 1.0,
            z,
        };
        (vec![key, 0], g)
    }

    /// The held-out gain over moved cells: a candidate that removes a large residual in
    /// 2 of 10 cells and leaves the rest alone gains 0.8 there but 0.14 over all cells
    /// (what the gate sees); a cell moved by less than `MOVED_Z` is not moved.
    #[test]
    fn held_out_sums_count_only_the_cells_the_candidate_moves() {
        let before: Vec<_> = (0..10)
            .map(|k| cell(k, if k < 2 { 10.0 } else { 8.0 }))
            .collect();
        let mut after = before.clone();
        after[0].1.z = 2.0;
        after[1].1.z = -2.0;
        after[5].1.z = 8.0 + 0.5 * MOVED_Z;
        let s = HeldOutSums::of(&before, &after).unwrap();
        assert_eq!((s.cells, s.moved), (10, 2));
        assert_eq!((s.before_moved, s.after_moved), (200.0, 8.0));
        let moved = 1.0
            - HeldOutSums::rms(s.after_moved, s.moved) / HeldOutSums::rms(s.before_moved, s.moved);
        assert!((moved - 0.8).abs() < 1e-12, "{moved}");
        let all = 1.0 - HeldOutSums::rms(s.after, s.cells) / HeldOutSums::rms(s.before, s.cells);
        assert!(
            (all - (1.0 - (528.25f64 / 712.0).sqrt())).abs() < 1e-12,
            "{all}"
        );
        assert!(all < HELD_OUT_MIN_GAIN);
        // a cell missing on one side (a prediction not finite) voids the fold
        assert!(HeldOutSums::of(&before, &after[1..]).is_none());
        let mut other = after.clone();
        other[3].0 = vec![99, 0];
        assert!(HeldOutSums::of(&before, &other).is_none());
        assert!(HeldOutSums::of(&[], &[]).is_none());
    }

    /// `--refit full` frees the model's own effects that have fitted parameters (with
    /// the candidate's); `--refit candidate` none of them. Unknown modes name the flag.
    #[test]
    fn a_full_refit_frees_the_model_s_own_fitted_effects() {
        let mut p = ModelParams::default();
        for name in ["refill", "chord"] {
            p.effects.push(EffectSpec::named(name));
        }
        assert_eq!(own_effects(&p, Refit::Full), ["refill", "chord"]);
        assert!(own_effects(&p, Refit::Candidate).is_empty());
        // a chord whose only fitted parameter is pinned is not freed
        p.effects[1].fixed = vec!["strength".into()];
        assert_eq!(own_effects(&p, Refit::Full), ["refill"]);
        let e = "both".parse::<Refit>().unwrap_err().to_string();
        assert!(e.contains("--refit") && e.contains("both"), "{e}");
    }
}
