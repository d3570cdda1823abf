//! The dark level under the calibration's first dark: what is subtracted from its image
//! and from its ramp before the persistence current is binned and fitted.
//!
//! # Two sources
//! - **Background pixels** ([`DarkSource::BackgroundPixels`]): when at least
//!   `min_pixels` pixels stayed below [`crate::measure::data::BACKGROUND_FLUENCE_E`] in every
//!   illumination so far, the dark level of the first dark is theirs, exposure by exposure
//!   (`diag::data`, "Background"), and the dark ramp read by read. This is the
//!   measurement `compare` and `diagnose` use on the same data.
//! - **Late plateau** ([`DarkSource::LatePlateau`]): when every pixel was lit (the
//!   paper's laboratory data: "flux ranging from tens to hundreds of thousands of
//!   electrons per second", no pixel below 3000 e-), there is no background pixel, and
//!   the dark level comes from each pixel's own late darks. The window is the dark
//!   integrations after the calibration's illumination and before the next one (or the
//!   end of the sequence), from half the block's last mid-time on:
//!   `W = { k in block : t_k >= t_last / 2 }`, `t` the time from the end of the
//!   illuminated exposure to the middle of the dark. The block after the calibration's
//!   illumination is used, not the sequence's last darks, because it shares the first
//!   dark's temperature and time, and its persistence comes from one illumination only,
//!   which the calibration itself measures.
//!
//! # Bias and its correction
//! In the window a pixel still releases persistence, which a plain median would take
//! for dark current, so that the first dark's current (first dark minus plateau) would
//! come out low by the ratio `r = D_W / D_1` of the decay's mean over the window to its
//! mean over the first dark. The correction uses the calibration's own decay: Eq.
//! (logfit) `q(t) = A_0 ln(t + tau) + q_0` says a pixel's current is `A / (t + tau)`,
//! so over an integration from `t_a` to `t_b` its mean is
//! `D = A ln((t_b + tau) / (t_a + tau)) / (t_b - t_a)`. With `P_p` the pixel's median
//! over `W` of its image and `I_p` its first-dark image, `P_p = dark_p + r A_p D_1` and
//! `I_p = dark_p + A_p D_1` give each pixel's own dark level
//! `dark_p = (P_p - r I_p) / (1 - r)` (its own persistence, not its bin's median's, so
//! that the bin's spread, which sets the 95th-percentile knots, is not compressed by
//! `1 - r`). `r` is the pixel's bin's, from that bin's fitted `tau`, after a first pass
//! with `r = 0`; [`PLATEAU_PASSES`] passes in all (the knots move by less than 0.1 %
//! between the second and third on the simulator's campaign). What is left is the
//! decay law's misfit at late times times `r`: if the true decay is `t^-0.85` rather
//! than `1/t`, the window holds `(t_W / t_1)^0.15` more than predicted (1.5 times at
//! 3600 s against 222 s), so with `r` at its limit [`MAX_LATE_FRACTION`] the first-dark
//! current is low by about 5 %; with 14 h of darks (`r` about 0.01) by less than 0.5 %.
//!
//! # Limits
//! The window needs at least [`MIN_LATE_DARKS`] darks and the median of `r` over the
//! bins with a fitted decay at most [`MAX_LATE_FRACTION`] (else the correction, not the
//! data, would set the dark level; a bin's `tau` is taken at most the first dark's
//! reset time, beyond which its ramp does not measure it): a sequence whose darks after the calibration's illumination stop too
//! soon is refused with the time it would need. Its noise (`noise_e_per_s`, used to
//! remove the noise from the bins' 95th percentiles in quadrature) is measured in the
//! window: 1.4826 times the median absolute difference of two consecutive darks, over
//! `sqrt 2`, scaled to the first dark's length by `(t_k / t_1)^1.5` (a line fit over
//! evenly spaced reads of read-noise-limited data; the same length needs no scaling).

use crate::error::{Error, Result};
use crate::measure::data::Sequence;
use crate::stats::median;
use ndarray::Array2;
use serde::Serialize;

/// Fewest darks in the late window.
pub const MIN_LATE_DARKS: usize = 2;
/// Largest ratio of the window's predicted persistence to the first dark's (module docs,
/// "Limits").
pub const MAX_LATE_FRACTION: f64 = 0.1;
/// Passes of the calibration with the late plateau (module docs, "Bias").
pub const PLATEAU_PASSES: usize = 3;

/// Where the calibration's dark level came from (module docs).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DarkSource {
    /// Pixels never lit above 3000 e-, exposure by exposure.
    #[default]
    BackgroundPixels,
    /// Each pixel's own late darks, its predicted persistence there removed.
    LatePlateau,
}

impl DarkSource {
    pub fn is_background_pixels(&self) -> bool {
        *self == DarkSource::BackgroundPixels
    }
}

/// What the report says of the dark level.
#[derive(Debug, Clone, Serialize)]
pub struct DarkReport {
    pub source: DarkSource,
    /// Exposure indices of the late window (empty with background pixels).
    pub late_exposures: Vec<u64>,
    /// Mid-times of the window's first and last darks after the end of the illuminated
    /// exposure, s.
    pub late_t_s: Option<[f64; 2]>,
    /// Largest `r` over the bins of the last pass (module docs, "Bias").
    pub late_fraction_max: Option<f64>,
    /// Median dark level over the pixels, e-/s.
    pub median_e_per_s: f64,
    /// Noise of the first dark, e-/s.
    pub noise_e_per_s: f64,
}

/// The late window and each pixel's plateau there (module docs).
#[derive(Debug, Clone)]
pub struct LatePlateau {
    /// Indices (into the sequence) of the window's darks.
    pub window: Vec<usize>,
    /// Each window dark's start and end after the end of the illuminated exposure, s.
    pub spans_s: Vec<(f64, f64)>,
    /// The first dark's start and end after the same reference, s.
    pub first_span_s: (f64, f64),
    /// `P_p`: each pixel's median over the window, e-/s (NaN where no good value).
    pub plateau: Array2<f64>,
    /// The first dark's image `I_p` (NaN where flagged), e-/s.
    pub first: Array2<f64>,
    pub noise_e_per_s: f64,
}

/// Span of exposure `k` after the end of exposure `a`, s.
fn span_after(seq: &Sequence, a: usize, k: usize) -> (f64, f64) {
    let t = seq.exposures[k].meta.t_exposure_s;
    let mid = seq.t_mid_after_s(a, k);
    (mid - 0.5 * t, mid + 0.5 * t)
}

/// An exposure's image with flagged or non-finite pixels as NaN, e-/s.
fn image(seq: &Sequence, k: usize) -> Array2<f64> {
    // `measured` subtracts the exposure's background; add it back
    let b = seq.background_e_per_s[k];
    seq.measured(k).mapv(|v| v + b)
}

impl LatePlateau {
    /// The window after illumination `i0` whose first dark is `d` (module docs); errors
    /// say what the sequence lacks.
    pub fn of(seq: &Sequence, i0: usize, d: usize) -> Result<LatePlateau> {
        let end = seq
            .illuminations
            .iter()
            .copied()
            .find(|&i| i > i0)
            .unwrap_or(seq.exposures.len());
        let block: Vec<usize> = (d + 1..end).collect();
        let window = seq.late_window(i0, &block);
        let index = |k: usize| seq.exposures[k].meta.exposure_index;
        if window.len() < MIN_LATE_DARKS {
            return Err(Error::invalid(
                "image",
                format!(
                    "no background pixel (every pixel was lit above {} e-) and {} dark \
                     integration(s) after the first dark of illumination {} (exposure {}): the \
                     dark level then comes from each pixel's late darks, which needs at least \
                     {} darks after the first, ending where its persistence has fallen below \
                     {} % of the first dark's (about {:.0} s after the illumination for a \
                     1/t decay); add such darks, or pixels masked from the source",
                    crate::measure::data::BACKGROUND_FLUENCE_E,
                    block.len(),
                    index(i0),
                    index(d),
                    2 * MIN_LATE_DARKS,
                    100.0 * MAX_LATE_FRACTION,
                    1.5 * seq.t_mid_after_s(i0, d) / MAX_LATE_FRACTION,
                ),
            ));
        }
        let (ny, nx) = (seq.ny, seq.nx);
        let images: Vec<Array2<f64>> = window.iter().map(|&k| image(seq, k)).collect();
        let mut plateau = Array2::<f64>::from_elem((ny, nx), f64::NAN);
        let mut v = Vec::with_capacity(images.len());
        for ((y, x), o) in plateau.indexed_iter_mut() {
            v.clear();
            v.extend(images.iter().map(|im| im[[y, x]]));
            *o = median(&v);
        }
        // noise from consecutive pairs, scaled to the first dark's length
        let t_first = seq.exposures[d].meta.t_exposure_s;
        let mut sigmas = Vec::new();
        for (w, pair) in window.windows(2).enumerate() {
            let (a, b) = (pair[0], pair[1]);
            let (ta, tb) = (
                seq.exposures[a].meta.t_exposure_s,
                seq.exposures[b].meta.t_exposure_s,
            );
            if ta != tb {
                continue;
            }
            let dev: Vec<f64> = images[w]
                .iter()
                .zip(images[w + 1].iter())
                .map(|(p, q)| p - q)
                .filter(|x| x.is_finite())
                .collect();
            let m = median(&dev);
            let mad = median(&dev.iter().map(|x| (x - m).abs()).collect::<Vec<_>>());
            let s = 1.4826 * mad / 2f64.sqrt() * (ta / t_first).powf(1.5);
            if s.is_finite() && s > 0.0 {
                sigmas.push(s);
            }
        }
        let noise = median(&sigmas);
        if !(noise.is_finite() && noise > 0.0) {
            return Err(Error::invalid(
                "image",
                format!(
                    "no background pixel and no two consecutive late darks of equal length \
                     after exposure {} with a measurable difference: the first dark's noise \
                     cannot be measured",
                    index(d)
                ),
            ));
        }
        Ok(LatePlateau {
            spans_s: window.iter().map(|&k| span_after(seq, i0, k)).collect(),
            first_span_s: span_after(seq, i0, d),
            window,
            plateau,
            first: image(seq, d),
            noise_e_per_s: noise,
        })
    }

    /// `r = D_W / D_1` for a decay `1 / (t + tau)` (module docs, "Bias").
    pub fn late_fraction(&self, tau_s: f64) -> f64 {
        let mean = |(a, b): (f64, f64)| ((b + tau_s) / (a + tau_s)).ln() / (b - a);
        let w: Vec<f64> = self.spans_s.iter().map(|s| mean(*s)).collect();
        median(&w) / mean(self.first_span_s)
    }

    /// Pixel `p`'s dark level for a late fraction `r` (module docs, "Bias").
    pub fn dark_at(&self, p: (usize, usize), r: f64) -> f64 {
        let (pl, i) = (self.plateau[p], self.first[p]);
        if r == 0.0 {
            pl
        } else {
            (pl - r * i) / (1.0 - r)
        }
    }

    pub fn exposure_indices(&self, seq: &Sequence) -> Vec<u64> {
        self.window
            .iter()
            .map(|&k| seq.exposures[k].meta.exposure_index)
            .collect()
    }
}
