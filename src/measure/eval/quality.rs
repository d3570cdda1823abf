//! Flag quality: the samples the flags miss and those they flag needlessly, over all
//! samples, a mask of them or per cell.
//!
//! # Flag quality (per threshold `thr`)
//! Missed: measured above `thr + 2 sigma_k` and not flagged (predicted `<= thr`).
//! Over-flagged: flagged and measured below `thr - 2 sigma_k`. The `2 sigma_k` margin
//! keeps read noise (`sigma_k` ~ 0.1 e-/s per pixel, the paper's noise level) from
//! counting as a flag error. Fractions are of all samples, and missed also of the
//! samples measured above `thr + 2 sigma_k`. Flags come from the model as the stage
//! runs it (early release included; on a laboratory sequence against its measured dark
//! level, [`super::predict`]); residuals from the same model with early release off (a
//! release zeroes a prediction the physics still has).

use super::cells::key_of;
use super::samples::Samples;
use ndarray::Array2;
use serde::Serialize;

/// Flag quality at one threshold (module docs).
#[derive(Debug, Clone, Copy, Serialize, PartialEq)]
pub struct FlagQuality {
    pub threshold_e_per_s: f64,
    pub samples: usize,
    pub measured_above: usize,
    pub flagged: usize,
    pub missed: usize,
    pub over_flagged: usize,
    pub missed_flag_fraction: f64,
    pub missed_of_measured_above: f64,
    pub over_flag_fraction: f64,
}

pub fn flag_quality(s: &Samples, pred: &[f64], flagged: Option<&[bool]>, thr: f64) -> FlagQuality {
    flag_quality_of(s, pred, flagged, thr, None)
}

/// [`flag_quality`] over the samples of the pixels where `pixel_mask` (one entry per
/// sampled pixel, [`Samples::pixels`]) is true; all samples when `None`.
pub fn flag_quality_of(
    s: &Samples,
    pred: &[f64],
    flagged: Option<&[bool]>,
    thr: f64,
    pixel_mask: Option<&[bool]>,
) -> FlagQuality {
    flag_quality_where(s, pred, flagged, thr, |i| {
        pixel_mask.is_none_or(|k| k[i % s.npix()])
    })
}

/// [`flag_quality`] over the samples `i` where `sample_mask[i]` is true (one entry per
/// sample, e.g. [`touched_samples`]).
pub fn flag_quality_of_samples(
    s: &Samples,
    pred: &[f64],
    flagged: Option<&[bool]>,
    thr: f64,
    sample_mask: &[bool],
) -> FlagQuality {
    flag_quality_where(s, pred, flagged, thr, |i| sample_mask[i])
}

/// The sampled pixels ([`Samples::pixels`]) where `sample_mask` (one entry per sample)
/// is true at any sample: a per-sample mask as the pixel mask of [`flag_quality_of`].
pub fn pixels_of(s: &Samples, sample_mask: &[bool]) -> Vec<bool> {
    let np = s.npix();
    (0..np)
        .map(|p| sample_mask.iter().skip(p).step_by(np).any(|&x| x))
        .collect()
}

/// The samples an effect touches: where the true persistence current with it differs
/// from the same simulation's without it by more than 10 % (and 0.01 e-/s).
/// `with_truth` and `without_truth` hold one plane per exposure of the sequence
/// (indexed as [`Samples::exposures`]).
pub fn touched_samples(
    s: &Samples,
    with_truth: &[Array2<f32>],
    without_truth: &[Array2<f32>],
) -> Vec<bool> {
    let mut t = Vec::with_capacity(s.len());
    for &k in &s.exposures {
        for &p in &s.pixels {
            let a = f64::from(with_truth[k][p]);
            let b = f64::from(without_truth[k][p]);
            t.push((a - b).abs() > (0.1 * b.abs()).max(0.01));
        }
    }
    t
}

fn flag_quality_where(
    s: &Samples,
    pred: &[f64],
    flagged: Option<&[bool]>,
    thr: f64,
    keep: impl Fn(usize) -> bool,
) -> FlagQuality {
    let mut c = FlagCounts::default();
    for i in 0..s.len() {
        if keep(i) {
            c.add(s, pred, flagged, thr, i);
        }
    }
    c.quality(thr)
}

/// Flag quality at `thr` per cell of `s` ([`super::Cells`], the keys of [`super::cell_z`]): where the
/// missed and over-flagged samples are. Every cell with a usable sample, in key order.
/// A sample enters its cell when its measurement is finite and its covariates give a
/// key, whatever the prediction (as in [`flag_quality`]), so the cells' samples can
/// outnumber [`super::cell_z`]'s where a prediction is not finite.
pub fn flag_quality_by_cell(
    s: &Samples,
    pred: &[f64],
    flagged: Option<&[bool]>,
    thr: f64,
) -> Vec<(Vec<i64>, FlagQuality)> {
    let keys = s.cells.keys();
    let mut g: std::collections::BTreeMap<Vec<i64>, FlagCounts> = Default::default();
    for i in 0..s.len() {
        if !s.measured[i].is_finite() {
            continue;
        }
        if let Some(key) = key_of(s, keys, i) {
            g.entry(key).or_default().add(s, pred, flagged, thr, i);
        }
    }
    g.into_iter().map(|(k, c)| (k, c.quality(thr))).collect()
}

/// Sample `i` is flagged: `flagged[i]`, or its prediction above `thr` when no flags are
/// given.
fn is_flagged(pred: &[f64], flagged: Option<&[bool]>, thr: f64, i: usize) -> bool {
    flagged.map_or(pred[i] > thr, |f| f[i])
}

/// Sample `i`, flagged or not (`flagged`), is over-flagged at `thr` (module docs):
/// flagged and measured below `thr - 2 sigma_k` (a measurement that is not finite is
/// not).
fn is_over_flagged(s: &Samples, flagged: bool, thr: f64, i: usize) -> bool {
    flagged && s.measured[i] < thr - 2.0 * s.noise[i / s.npix()]
}

/// Per sampled pixel ([`Samples::pixels`], in that order), how many of its samples are
/// over-flagged at `thr`, counted as in [`flag_quality`]: what a comparison of two
/// models' over-flagging pairs by pixel, since a pixel's samples are not independent.
pub fn over_flagged_by_pixel(
    s: &Samples,
    pred: &[f64],
    flagged: Option<&[bool]>,
    thr: f64,
) -> Vec<u32> {
    let mut n = vec![0u32; s.npix()];
    for i in 0..s.len() {
        n[i % s.npix()] += is_over_flagged(s, is_flagged(pred, flagged, thr, i), thr, i) as u32;
    }
    n
}

/// The counts behind a [`FlagQuality`] (module docs: missed is measured above
/// `thr + 2 sigma_k` and not flagged; over-flagged is flagged and measured below
/// `thr - 2 sigma_k`).
#[derive(Debug, Clone, Copy, Default)]
struct FlagCounts {
    samples: usize,
    above: usize,
    flagged: usize,
    missed: usize,
    over: usize,
}

impl FlagCounts {
    /// Counts sample `i` if its measurement is finite. Flagged: `flagged[i]`, or the
    /// prediction above `thr` when no flags are given.
    fn add(&mut self, s: &Samples, pred: &[f64], flagged: Option<&[bool]>, thr: f64, i: usize) {
        let m = s.measured[i];
        if !m.is_finite() {
            return;
        }
        self.samples += 1;
        let f = is_flagged(pred, flagged, thr, i);
        self.flagged += f as usize;
        if m > thr + 2.0 * s.noise[i / s.npix()] {
            self.above += 1;
            self.missed += !f as usize;
        }
        self.over += is_over_flagged(s, f, thr, i) as usize;
    }

    fn quality(&self, thr: f64) -> FlagQuality {
        let fr = |a: usize, b: usize| if b == 0 { 0.0 } else { a as f64 / b as f64 };
        FlagQuality {
            threshold_e_per_s: thr,
            samples: self.samples,
            measured_above: self.above,
            flagged: self.flagged,
            missed: self.missed,
            over_flagged: self.over,
            missed_flag_fraction: fr(self.missed, self.samples),
            missed_of_measured_above: fr(self.missed, self.above),
            over_flag_fraction: fr(self.over, self.samples),
        }
    }
}
