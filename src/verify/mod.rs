//! `persist verify`: persistence measured in flight, with no shutter, against what the
//! stage predicted and flagged.
//!
//! The paper leaves the flight check as its next step ("cross correlations of sequential
//! exposures"). Here: in a sequence of sky exposures, pixels that saw a bright source
//! (an *event*: saturating, or above a fluence) are followed through the later exposures;
//! each later exposure gives the pixel's **excess current** over the sky the same exposure
//! shows around it ([`track`]: why the surroundings and not the pixel's own history). The
//! samples are stacked by the event's fluence and the time since it into measured decay
//! curves with uncertainties that respect their correlations ([`stack`]), next to the
//! stage's predictions for the same pixel-exposures, and split by whether the stage
//! flagged them.
//!
//! Three checks, each a number and a verdict in the report:
//! - **decay**: per fluence bin, the log-log slope of the measured decay over the time
//!   bins where it stands above three standard errors, against the prediction's over the
//!   same bins; their difference weighted over the fluence bins must be within
//!   [`VerifyParams::slope_tolerance`]. A slope and not a chi-square of the curves: with
//!   hundreds of thousands of samples any difference of shape between a conservative
//!   envelope and the pixels' mean is significant; what matters is whether the decay law
//!   is the data's.
//! - **margin**: the paper flags with the 95th percentile of the pixels' response times a
//!   margin (1.2). The first exposure after an event measures each pixel's response with a
//!   good signal-to-noise ratio; the 95th percentile of measured / predicted over event
//!   pixels is the fraction of the prediction that 95 % of pixels stay under, and its
//!   inverse the model's margin in flight. It agrees when within
//!   [`VerifyParams::margin_factor`] of the design margin; below, pixels are missed; above,
//!   the flags cost sky for nothing.
//! - **flags**: the measured excess of flagged and unflagged samples by time since the event.
//!
//! Cosmic-ray hits (`TRANSIENT` pixels) are followed the same way, and the report's
//! `transients` section measures the transient rule from them ([`transient`]: what
//! `persist fit --from-verify` writes into the model file).
//!
//! Where the input directory holds a simulator's truth (`truth/`), each bin also carries
//! the true mean persistence of the same samples, and the report says how often the truth
//! falls in the measured mean's 95 % interval.
//!
//! Files are read in exposure order per detector; one unreadable file is reported (file and
//! reason) and skipped, and the run goes on.

pub mod report;
pub mod stack;
pub mod track;
pub mod transient;

use crate::error::{Error, ErrorKind, Result};
use crate::product::read::read_output;
use ndarray::Array2;
use serde::Serialize;
use stack::{bin_of, Bin, Mean, QuantileBin};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use track::{Frame, Sample, TrackParams, Tracker};

/// What `verify` measures and how it judges.
#[derive(Debug, Clone, Serialize)]
pub struct VerifyParams {
    pub track: TrackParams,
    /// Edges of the event-fluence bins, e- (ascending; the last may be infinite).
    pub fluence_edges_e: Vec<f64>,
    /// Edges of the time-since-event bins, s.
    pub time_edges_s: Vec<f64>,
    /// The threshold the flags are judged at, e-/s.
    pub threshold_e_per_s: f64,
    /// The margin the model was made with: the paper's knots are the 95th percentile of
    /// the response times 1.2.
    pub design_margin: f64,
    /// The margin measured in flight agrees when it is within this factor of the design
    /// margin (its 95 % interval overlaps `[design / f, design * f]`).
    pub margin_factor: f64,
    /// The decay agrees when the predicted and measured log-log slopes differ by at most
    /// this (or by less than two standard errors). Over the two decades of time the check
    /// spans, 0.05 in slope is 26 % in current.
    pub slope_tolerance: f64,
    /// The decay's slope is fitted over the time bins whose measured mean is at least
    /// this fraction of the threshold (and above three standard errors): the decay
    /// where the flag is decided. Further down, the flight data measure what the flag
    /// does not depend on: a model fitted on a laboratory sequence of 30 darks (1.5 h)
    /// has no time constant for the tail beyond a few hours, and its prediction falls
    /// away there (on the simulated sky, from 0.05 e-/s measured to 0.003 predicted at
    /// 3 to 4 h), which says nothing about its flags at 0.1 e-/s.
    pub slope_floor_fraction: f64,
    /// The quantile of the transient rule ([`transient`]).
    pub transient_quantile: f64,
    /// Seed of the bootstraps.
    pub seed: u64,
}

impl Default for VerifyParams {
    fn default() -> Self {
        VerifyParams {
            track: TrackParams::default(),
            fluence_edges_e: vec![2e5, 5e5, 1e6, 3e6, 1e7, f64::INFINITY],
            // four per decade from 30 s to about 2 days
            time_edges_s: (0..=21)
                .map(|i| 30.0 * 10f64.powf(f64::from(i) / 4.0))
                .collect(),
            threshold_e_per_s: 0.1,
            design_margin: 1.2,
            margin_factor: std::f64::consts::SQRT_2,
            slope_tolerance: 0.05,
            slope_floor_fraction: 1.0,
            transient_quantile: transient::DEFAULT_QUANTILE,
            seed: 1,
        }
    }
}

/// One (fluence, time) bin of the measured decay.
#[derive(Debug, Clone, Serialize)]
pub struct DecayBin {
    pub fluence_lo_e: f64,
    pub fluence_hi_e: f64,
    pub time_lo_s: f64,
    pub time_hi_s: f64,
    pub samples: usize,
    pub events: usize,
    pub mean_time_s: f64,
    pub measured: Mean,
    pub predicted: Mean,
    /// Predicted minus measured over the same samples (its error is the bootstrap's of the
    /// difference, not the two errors added).
    pub difference: Mean,
    pub truth: Option<Mean>,
    /// The truth inside the measured mean's 95 % interval (`|truth - measured| <= 1.96`
    /// times the measured mean's standard error).
    pub truth_inside: Option<bool>,
}

/// Flagged or not, by time since the event.
#[derive(Debug, Clone, Serialize)]
pub struct FlagBin {
    pub time_lo_s: f64,
    pub time_hi_s: f64,
    pub flagged: bool,
    pub samples: usize,
    pub measured: Mean,
    pub truth: Option<Mean>,
    /// Fraction of the samples whose measured excess is above the threshold by more than
    /// two noise standard deviations.
    pub above_threshold_fraction: f64,
}

/// The response at the first exposure after events of one fluence bin.
#[derive(Debug, Clone, Serialize)]
pub struct MarginBin {
    pub fluence_lo_e: f64,
    pub fluence_hi_e: f64,
    pub pixels: usize,
    /// Median of measured / predicted.
    pub ratio_median: f64,
    /// 95th percentile of measured / predicted, with its bootstrap 95 % interval.
    pub ratio_p95: (f64, f64, f64),
    pub true_ratio_p95: Option<f64>,
}

/// The decay's log-log slope in one fluence bin, measured and predicted.
#[derive(Debug, Clone, Serialize)]
pub struct SlopeBin {
    pub fluence_lo_e: f64,
    pub fluence_hi_e: f64,
    /// Time bins used (measured mean above three standard errors).
    pub bins: usize,
    pub time_from_s: f64,
    pub time_to_s: f64,
    pub measured: Mean,
    pub predicted: f64,
    pub truth: Option<f64>,
}

#[derive(Debug, Clone, Serialize)]
pub struct Checks {
    pub slopes: Vec<SlopeBin>,
    /// Predicted minus measured slope, weighted over the fluence bins.
    pub slope_difference: Mean,
    pub decay_agrees: bool,
    /// 1 / (95th percentile of measured / predicted) over all first samples, with the
    /// interval from the percentile's.
    pub margin: (f64, f64, f64),
    /// `ok`, `under-predicts`, `over-conservative` or `no events`.
    pub margin_verdict: String,
    /// Bins whose truth is inside the measured 95 % interval, and bins with a truth.
    pub truth_inside: Option<(usize, usize)>,
}

impl Checks {
    /// The decay and margin checks in one line, as `persist verify` prints them.
    pub fn verdict(&self) -> String {
        format!(
            "decay {} (slope predicted - measured {:.3} +- {:.3}); margin {:.2} ({:.2}-{:.2}): {}",
            if self.decay_agrees {
                "agrees"
            } else {
                "disagrees"
            },
            self.slope_difference.mean,
            self.slope_difference.se,
            self.margin.0,
            self.margin.1,
            self.margin.2,
            self.margin_verdict
        )
    }

    /// Both checks agree (what `persist verify`'s exit code 0 needs, with no
    /// unreadable file).
    pub fn agree(&self) -> bool {
        self.decay_agrees && self.margin_verdict == "ok"
    }
}

#[derive(Debug, Clone, Serialize)]
pub struct FileError {
    pub file: PathBuf,
    pub reason: String,
}

#[derive(Debug, Clone, Serialize)]
pub struct Report {
    pub software_version: String,
    pub params: VerifyParams,
    pub model_ids: Vec<String>,
    pub detectors: Vec<u8>,
    pub exposures: usize,
    pub errors: Vec<FileError>,
    pub samples: usize,
    pub events: u64,
    pub rejected_as_sources: u64,
    pub without_sky: u64,
    pub decay: Vec<DecayBin>,
    pub flags: Vec<FlagBin>,
    pub margins: Vec<MarginBin>,
    pub checks: Checks,
    /// Where the input holds a simulator's truth: the stage's flags against it at the
    /// threshold and at the default low threshold, from exposure
    /// [`crate::flag_quality::FROM_EXPOSURE`] on ([`crate::flag_quality`]).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub flag_quality: Option<crate::flag_quality::TruthTally>,
    /// The cosmic-ray hits followed, and the transient rule they give.
    pub transients: transient::TransientReport,
}

/// Accumulators of one run (all detectors).
#[derive(Default)]
struct Acc {
    /// columns: excess, predicted, truth, time
    decay: BTreeMap<(usize, usize), Bin<4>>,
    /// columns: excess, truth, above threshold by 2 sigma
    flags: BTreeMap<(usize, bool), Bin<3>>,
    margin: BTreeMap<usize, (QuantileBin, QuantileBin)>,
    margin_all: QuantileBin,
    /// Every sample so far had a truth (and there was one).
    has_truth: bool,
    /// A sample without a truth was seen.
    truth_missing: bool,
    samples: usize,
}

impl Acc {
    fn add(&mut self, p: &VerifyParams, s: &Sample, cluster: u64) {
        let Some(tb) = bin_of(&p.time_edges_s, s.time_s) else {
            return;
        };
        let Some(fb) = bin_of(&p.fluence_edges_e, s.event_fluence_e) else {
            return;
        };
        // Without a truth (flight data) its column holds 0, not NaN: the means are
        // linear combinations of all the columns' sums, and 0 x NaN would make every
        // mean NaN. The truth's means are reported only when every sample had one.
        let truth = s.true_excess_e_per_s.unwrap_or(0.0);
        self.truth_missing |= s.true_excess_e_per_s.is_none();
        self.has_truth = !self.truth_missing;
        self.samples += 1;
        let measured = s.excess_e_per_s - s.control_e_per_s;
        let pred = s.predicted_excess_e_per_s;
        let w = sample_weight(s.sigma_e_per_s);
        self.decay.entry((fb, tb)).or_default().add_weighted(
            cluster,
            w,
            [measured, pred, truth, s.time_s],
        );
        let above = s.excess_e_per_s > p.threshold_e_per_s + 2.0 * s.sigma_e_per_s;
        self.flags.entry((tb, s.flagged)).or_default().add_weighted(
            cluster,
            w,
            [measured, truth, f64::from(u8::from(above))],
        );
        if s.first && pred > 0.0 {
            let m = self.margin.entry(fb).or_default();
            m.0.add(cluster, measured / pred);
            m.1.add(cluster, truth / pred);
            self.margin_all.add(cluster, measured / pred);
        }
    }
}

/// A sample's weight in the stacks: inverse variance, from the noise of its annulus
/// (not of the pixel itself, so the weight does not depend on the sample's own noise
/// draw), with the noise floored at [`SIGMA_FLOOR_E_PER_S`]. A crowded field's annulus
/// (a Galactic-plane field, a bright star's halo) is a far worse sky estimate than a
/// quiet one: 8 % of the samples of the two-day simulated sky have a noise above
/// 0.25 e-/s, ten times the variance of the others; unweighted they dominate the
/// means' scatter. The prediction and the truth are stacked with the same weights.
pub fn sample_weight(sigma_e_per_s: f64) -> f64 {
    1.0 / sigma_e_per_s.max(SIGMA_FLOOR_E_PER_S).powi(2)
}

/// The noise below which samples are not weighted up further, e-/s: a line fit over a
/// 112 s exposure reads its sky with about this noise at least (read noise alone).
pub const SIGMA_FLOOR_E_PER_S: f64 = 0.02;

/// The (detector, exposure index) of an output product, from its root attributes only.
fn peek(path: &Path) -> Result<(u8, u64)> {
    let f = crate::h5io::open(path)?;
    let read = |name: &str| -> Result<i64> {
        f.attr(name)
            .and_then(|a| a.read_scalar::<i64>())
            .map_err(|e| {
                Error::new(ErrorKind::Invalid, e.to_string())
                    .path(path)
                    .field(name)
            })
    };
    let det = read("detector")?;
    let idx = read("exposure_index")?;
    let det = u8::try_from(det).map_err(|_| {
        Error::new(ErrorKind::Invalid, format!("detector {det} out of range")).path(path)
    })?;
    let idx = u64::try_from(idx).map_err(|_| {
        Error::new(
            ErrorKind::Invalid,
            format!("exposure_index {idx} is negative"),
        )
        .path(path)
    })?;
    Ok((det, idx))
}

fn read_truth(input: &Path, det: u8, idx: u64) -> Option<Array2<f32>> {
    let p = crate::sim::output::truth_path(input, det, idx);
    if !p.is_file() {
        return None;
    }
    let f = crate::h5io::open(&p).ok()?;
    f.dataset("true_persistence").ok()?.read_2d::<f32>().ok()
}

/// Run the measurement over the stage's outputs in `output` (the products carry the input
/// image and flags unchanged); `input` is the stage's input directory, whose `truth/` is
/// used when present.
pub fn run(input: &Path, output: &Path, params: &VerifyParams) -> Result<Report> {
    run_observing(input, output, params, &mut |_, _| {})
}

/// [`run`], handing every sample (with its detector) to `observe` as well, in the order
/// they are measured (detector, exposure, pixel): what [`crate::pixmap::flight`] learns
/// each pixel's response from.
pub fn run_observing(
    input: &Path,
    output: &Path,
    params: &VerifyParams,
    observe: &mut dyn FnMut(u8, &Sample),
) -> Result<Report> {
    if !input.is_dir() {
        return Err(Error::new(ErrorKind::Usage, "input is not a directory").path(input));
    }
    let mut errors = Vec::new();
    let mut by_det: BTreeMap<u8, Vec<(u64, PathBuf)>> = BTreeMap::new();
    for path in crate::stage::queue::candidates(output)? {
        match peek(&path) {
            Ok((d, i)) => by_det.entry(d).or_default().push((i, path)),
            Err(e) => errors.push(FileError {
                file: path,
                reason: e.to_string(),
            }),
        }
    }
    let mut acc = Acc::default();
    let mut hits = transient::Acc::default();
    let (mut hits_started, mut hits_rejected) = (0, 0);
    let mut tally = crate::flag_quality::TruthTally::new(
        params.threshold_e_per_s,
        crate::model::params::Thresholds::default().low_e_per_s,
        crate::flag_quality::FROM_EXPOSURE,
    );
    let mut any_truth = false;
    let mut model_ids = Vec::new();
    let (mut exposures, mut events, mut rejected, mut no_sky) = (0, 0, 0, 0);
    for (&det, files) in by_det.iter_mut() {
        files.sort();
        let mut tracker: Option<Tracker> = None;
        // The next file is read on its own thread while this one is measured.
        std::thread::scope(|scope| {
            let (send, receive) = std::sync::mpsc::sync_channel(1);
            let files = &*files;
            scope.spawn(move || {
                for (idx, path) in files {
                    let read = read_output(path).map(|v| (v, read_truth(input, det, *idx)));
                    if send.send((path, read)).is_err() {
                        return;
                    }
                }
            });
            for (path, read) in receive {
                let ((e, planes, attrs), truth) = match read {
                    Ok(v) => v,
                    Err(err) => {
                        errors.push(FileError {
                            file: path.clone(),
                            reason: err.to_string(),
                        });
                        continue;
                    }
                };
                if !model_ids.contains(&attrs.model_id) {
                    model_ids.push(attrs.model_id.clone());
                }
                let (ny, nx) = e.image.dim();
                let t = tracker.get_or_insert_with(|| Tracker::new(params.track.clone(), ny, nx));
                if t.shape() != (ny, nx) {
                    errors.push(FileError {
                        file: path.clone(),
                        reason: format!(
                            "image is {ny} x {nx}, the detector's earlier ones {:?}",
                            t.shape()
                        ),
                    });
                    continue;
                }
                if let Some(t) = &truth {
                    any_truth = true;
                    tally.add_pflags(e.meta.exposure_index, &planes.flags, t, &e.flags);
                }
                let frame = Frame::of(
                    &e,
                    planes.current_e_per_s.view(),
                    planes.flags.view(),
                    truth.as_ref().map(|a| a.view()),
                );
                let before = t.clusters_started();
                for s in t.observe(&frame) {
                    let cluster = (u64::from(det) << 48) | s.cluster;
                    acc.add(params, &s, cluster);
                    observe(det, &s);
                }
                events += t.clusters_started() - before;
                for s in t.take_hit_samples() {
                    hits.add(&params.time_edges_s, &s, (u64::from(det) << 48) | s.cluster);
                }
                exposures += 1;
            }
        });
        if let Some(t) = tracker {
            rejected += t.rejected;
            no_sky += t.no_sky;
            hits_started += t.hits_started;
            hits_rejected += t.hit_rejected;
        }
    }
    let mut report = summarise(
        params,
        acc,
        Summary {
            model_ids,
            detectors: by_det.keys().copied().collect(),
            exposures,
            errors,
            events,
            rejected,
            no_sky,
            transients: hits.summarise(
                &params.time_edges_s,
                (hits_started, hits_rejected),
                params.transient_quantile,
                params.seed,
            ),
        },
    );
    report.flag_quality = any_truth.then_some(tally);
    Ok(report)
}

struct Summary {
    model_ids: Vec<String>,
    detectors: Vec<u8>,
    exposures: usize,
    errors: Vec<FileError>,
    events: u64,
    rejected: u64,
    no_sky: u64,
    transients: transient::TransientReport,
}

fn seed_of(p: &VerifyParams, a: usize, b: usize, c: usize) -> u64 {
    p.seed ^ ((a as u64) << 40) ^ ((b as u64) << 20) ^ c as u64
}

fn summarise(p: &VerifyParams, acc: Acc, s: Summary) -> Report {
    let fe = &p.fluence_edges_e;
    let te = &p.time_edges_s;
    let mut decay = Vec::new();
    for (&(fb, tb), bin) in &acc.decay {
        // columns: excess, predicted, truth, time
        let w = [
            [1.0, 0.0, 0.0, 0.0],
            [0.0, 1.0, 0.0, 0.0],
            [-1.0, 1.0, 0.0, 0.0],
            [0.0, 0.0, 0.0, 1.0],
            [0.0, 0.0, 1.0, 0.0],
        ];
        let Some([meas, pred, diff, time, truth]) = bin.means(w, seed_of(p, 1, fb, tb)) else {
            continue;
        };
        let truth_inside = (truth.mean - meas.mean).abs() <= 1.96 * meas.se;
        let truth = acc.has_truth.then_some(truth);
        decay.push(DecayBin {
            fluence_lo_e: fe[fb],
            fluence_hi_e: fe[fb + 1],
            time_lo_s: te[tb],
            time_hi_s: te[tb + 1],
            samples: bin.samples(),
            events: bin.clusters(),
            mean_time_s: time.mean,
            measured: meas,
            predicted: pred,
            difference: diff,
            truth,
            truth_inside: acc.has_truth.then_some(truth_inside),
        });
    }
    let mut flags = Vec::new();
    for (&(tb, flagged), bin) in &acc.flags {
        let w = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        let Some([meas, truth, above]) = bin.means(w, seed_of(p, 2, tb, usize::from(flagged)))
        else {
            continue;
        };
        flags.push(FlagBin {
            time_lo_s: te[tb],
            time_hi_s: te[tb + 1],
            flagged,
            samples: bin.samples(),
            measured: meas,
            truth: acc.has_truth.then_some(truth),
            above_threshold_fraction: above.mean,
        });
    }
    let mut margins = Vec::new();
    for (&fb, (q, qt)) in &acc.margin {
        let Some(p95) = q.quantile(0.95, seed_of(p, 3, fb, 0)) else {
            continue;
        };
        let med = q
            .quantile(0.5, seed_of(p, 4, fb, 0))
            .map_or(f64::NAN, |v| v.0);
        margins.push(MarginBin {
            fluence_lo_e: fe[fb],
            fluence_hi_e: fe[fb + 1],
            pixels: q.samples(),
            ratio_median: med,
            ratio_p95: p95,
            true_ratio_p95: if acc.has_truth {
                qt.quantile(0.95, seed_of(p, 5, fb, 0)).map(|v| v.0)
            } else {
                None
            },
        });
    }
    let checks = checks(p, &decay, &acc);
    Report {
        software_version: crate::VERSION.to_string(),
        params: p.clone(),
        model_ids: s.model_ids,
        detectors: s.detectors,
        exposures: s.exposures,
        errors: s.errors,
        samples: acc.samples,
        events: s.events,
        rejected_as_sources: s.rejected,
        without_sky: s.no_sky,
        decay,
        flags,
        margins,
        checks,
        flag_quality: None,
        transients: s.transients,
    }
}

/// Weighted least-squares slope of `y` on `x` and its standard error.
fn slope(x: &[f64], y: &[f64], sigma_y: &[f64]) -> Mean {
    let w: Vec<f64> = sigma_y.iter().map(|s| 1.0 / (s * s)).collect();
    let sw: f64 = w.iter().sum();
    let xm = x.iter().zip(&w).map(|(x, w)| x * w).sum::<f64>() / sw;
    let ym = y.iter().zip(&w).map(|(y, w)| y * w).sum::<f64>() / sw;
    let sxx: f64 = x.iter().zip(&w).map(|(x, w)| w * (x - xm).powi(2)).sum();
    let sxy: f64 = x
        .iter()
        .zip(y)
        .zip(&w)
        .map(|((x, y), w)| w * (x - xm) * (y - ym))
        .sum();
    Mean {
        mean: sxy / sxx,
        se: (1.0 / sxx).sqrt(),
    }
}

/// Per fluence bin, the log-log slopes of the measured and predicted decay over the time
/// bins where the measurement stands above three standard errors and above `floor_e_per_s`.
fn slopes(decay: &[DecayBin], floor_e_per_s: f64) -> Vec<SlopeBin> {
    let mut by_f: BTreeMap<u64, Vec<&DecayBin>> = BTreeMap::new();
    for b in decay {
        if b.measured.mean > 3.0 * b.measured.se
            && b.measured.mean >= floor_e_per_s
            && b.predicted.mean > 0.0
        {
            by_f.entry(b.fluence_lo_e.to_bits()).or_default().push(b);
        }
    }
    let mut out = Vec::new();
    for bins in by_f.values().filter(|b| b.len() >= 3) {
        let x: Vec<f64> = bins.iter().map(|b| b.mean_time_s.log10()).collect();
        let sig: Vec<f64> = bins
            .iter()
            .map(|b| b.measured.se / (b.measured.mean * std::f64::consts::LN_10))
            .collect();
        let lg = |f: &dyn Fn(&DecayBin) -> f64| -> Vec<f64> {
            bins.iter().map(|b| f(b).log10()).collect()
        };
        let truth = bins
            .iter()
            .all(|b| b.truth.is_some_and(|t| t.mean > 0.0))
            .then(|| slope(&x, &lg(&|b| b.truth.map_or(f64::NAN, |t| t.mean)), &sig).mean);
        out.push(SlopeBin {
            fluence_lo_e: bins[0].fluence_lo_e,
            fluence_hi_e: bins[0].fluence_hi_e,
            bins: bins.len(),
            time_from_s: bins[0].mean_time_s,
            time_to_s: bins[bins.len() - 1].mean_time_s,
            measured: slope(&x, &lg(&|b| b.measured.mean), &sig),
            predicted: slope(&x, &lg(&|b| b.predicted.mean), &sig).mean,
            truth,
        });
    }
    out
}

/// The decay and margin checks (module docs).
fn checks(p: &VerifyParams, decay: &[DecayBin], acc: &Acc) -> Checks {
    let slopes = slopes(decay, p.slope_floor_fraction * p.threshold_e_per_s);
    let (mut sw, mut s) = (0.0, 0.0);
    for b in &slopes {
        let w = 1.0 / b.measured.se.powi(2);
        sw += w;
        s += w * (b.predicted - b.measured.mean);
    }
    let slope_difference = Mean {
        mean: s / sw,
        se: (1.0 / sw).sqrt(),
    };
    let decay_agrees = !slopes.is_empty()
        && (slope_difference.mean.abs() <= p.slope_tolerance
            || slope_difference.mean.abs() < 2.0 * slope_difference.se);
    let margin = acc
        .margin_all
        .quantile(0.95, seed_of(p, 6, 0, 0))
        .map_or((f64::NAN, f64::NAN, f64::NAN), |(q, lo, hi)| {
            (1.0 / q, 1.0 / hi, 1.0 / lo)
        });
    let (low, high) = (
        p.design_margin / p.margin_factor,
        p.design_margin * p.margin_factor,
    );
    let margin_verdict = if margin.0.is_nan() {
        "no events"
    } else if margin.2 < low {
        "under-predicts"
    } else if margin.1 > high {
        "over-conservative"
    } else {
        "ok"
    };
    let with_truth: Vec<bool> = decay.iter().filter_map(|b| b.truth_inside).collect();
    Checks {
        slopes,
        slope_difference,
        decay_agrees,
        margin,
        margin_verdict: margin_verdict.to_string(),
        truth_inside: (!with_truth.is_empty())
            .then(|| (with_truth.iter().filter(|&&b| b).count(), with_truth.len())),
    }
}

/// Write `report.json` and `report.html` into `dir`.
pub fn write_report(report: &Report, dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    let json = serde_json::to_string_pretty(report)
        .map_err(|e| Error::new(ErrorKind::Io, e.to_string()))?;
    let p = dir.join("report.json");
    std::fs::write(&p, json + "\n").map_err(|e| Error::io(&p, e))?;
    let p = dir.join("report.html");
    std::fs::write(&p, report::html(report)?).map_err(|e| Error::io(&p, e))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample(cluster: u64, excess: f64, truth: Option<f64>) -> Sample {
        Sample {
            y: 0,
            x: 0,
            cluster,
            event_fluence_e: 3e5,
            time_s: 100.0,
            excess_e_per_s: excess,
            sigma_e_per_s: 0.05,
            control_e_per_s: 0.0,
            control_true_e_per_s: 0.0,
            predicted_e_per_s: 1.0,
            predicted_excess_e_per_s: 1.0,
            flagged: true,
            true_excess_e_per_s: truth,
            first: true,
        }
    }

    fn summary() -> Summary {
        Summary {
            model_ids: vec![],
            detectors: vec![1],
            exposures: 1,
            errors: vec![],
            events: 8,
            rejected: 0,
            no_sky: 0,
            transients: transient::Acc::default().summarise(&[0.0, 1.0], (0, 0), 0.95, 1),
        }
    }

    /// Flight data have no truth: the measured and predicted means must still be the
    /// samples' (they were NaN when the missing truth entered the sums as NaN), and the
    /// page must be written.
    #[test]
    fn without_a_truth_the_means_are_measured_and_no_truth_is_reported() {
        let p = VerifyParams::default();
        let mut acc = Acc::default();
        for c in 0..8 {
            acc.add(&p, &sample(c, 0.5 + 0.1 * c as f64, None), c);
        }
        let r = summarise(&p, acc, summary());
        assert_eq!(r.decay.len(), 1);
        let b = &r.decay[0];
        assert!((b.measured.mean - 0.85).abs() < 1e-9, "{b:?}");
        assert!((b.predicted.mean - 1.0).abs() < 1e-9, "{b:?}");
        assert!(b.truth.is_none() && b.truth_inside.is_none());
        assert!(r.checks.truth_inside.is_none());
        assert!(report::html(&r).unwrap().contains("Decay by fluence"));
    }

    /// One exposure without its truth file: the truth is not reported rather than
    /// averaged with zeros.
    #[test]
    fn a_truth_missing_for_some_samples_is_not_reported() {
        let p = VerifyParams::default();
        let mut acc = Acc::default();
        for c in 0..8 {
            let truth = (c != 3).then_some(0.4);
            acc.add(&p, &sample(c, 0.5, truth), c);
        }
        let r = summarise(&p, acc, summary());
        assert!(r.decay[0].truth.is_none());
        assert!((r.decay[0].measured.mean - 0.5).abs() < 1e-9);
    }
}
