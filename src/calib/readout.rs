//! The on-board slope, measured on the first dark: how the product's image was made
//! from its ramp.
//!
//! # Why
//! The model predicts the current at mid-exposure; a product's image is a slope fitted
//! on board to the ramp, and for a decaying persistence current the two differ (the
//! chord of the curved ramp, [`crate::model::effects::chord`], reads the mean current,
//! 64 % above the mid-exposure current for `1/t` from 10 s to 190 s; a least-squares
//! line, [`crate::model::effects::linefit_bias`], weights the middle of the ramp and
//! reads less). Which one a detector's electronics compute is a fact of the readout,
//! not a physical effect, and a laboratory sequence states it: its first dark keeps
//! both the ramp and the image made from it. Held at the wrong one, the first dark
//! after every illumination is mispredicted by tens of percent, a misfit that library
//! effects acting at short times then take in (measured on the second truth generator,
//! [`crate::trapgen`], whose slope is a least-squares line: the description's residual
//! RMS 13.5 with the chord alone, 7.0 with the line; 64 x 64, nothing hidden).
//!
//! # Rule
//! Per pixel of the first dark with a finite image, ramp and no bad flag: the chord
//! `c = (q_last - q_first) / (t_last - t_first)`, the least-squares line's slope `l`
//! (with intercept) over every read, and the image `m`. The image's share of the
//! line, `lambda`, is the least-squares coefficient of `m - c` on `l - c` over the
//! pixels: 0 for a chord, 1 for a line (constant currents, dark current included, drop
//! out: for them `c = l`). Pixels whose `|l - c|` is below 3 times the chord's
//! read-noise error carry no information and are left out. The first read's time after the reset is
//! the ramp's first sample time.
//!
//! # Invariants
//! - Reads nothing but the first dark's image, flags, ramp and sample times.
//! - An image equal to the chord (or the line) of its ramp gives `lambda` 0 (or 1) to
//!   rounding.

use super::knots::CalibRamp;
use crate::measure::data::{Sequence, BAD_BITS};
use serde::Serialize;

/// The readout as the first dark shows it (module docs).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Readout {
    /// The first read after the reset, s.
    pub first_read_s: f64,
    /// The image's share of the least-squares line against the chord (`lambda`).
    pub line_fraction: f64,
    /// Pixels the share was measured on.
    pub pixels: usize,
}

/// Below this share the line is left out of the description (the chord alone).
pub const LINE_FRACTION_MIN: f64 = 0.1;

impl Readout {
    /// The `persist fit --with` arguments that hold this readout: `chord` at strength 1
    /// from the first read, then `linefit_bias` at the measured share when it is at
    /// least [`LINE_FRACTION_MIN`].
    pub fn with_args(&self) -> Vec<String> {
        let fr = self.first_read_s;
        let mut w = vec![format!("chord:strength=1,first_read_s={fr}")];
        if self.line_fraction >= LINE_FRACTION_MIN {
            w.push(format!(
                "linefit_bias:strength={:.3},first_read_s={fr}",
                self.line_fraction.min(1.0)
            ));
        }
        w
    }
}

/// Slopes `(chord, line)` of one pixel's reads `q` at `t` (`t` has at least 3 reads).
fn slopes(t: &[f64], q: &[f64]) -> (f64, f64) {
    let n = t.len() as f64;
    let (tm, qm) = (t.iter().sum::<f64>() / n, q.iter().sum::<f64>() / n);
    let stt: f64 = t.iter().map(|x| (x - tm) * (x - tm)).sum();
    let stq: f64 = t.iter().zip(q).map(|(x, y)| (x - tm) * (y - qm)).sum();
    let k = t.len() - 1;
    ((q[k] - q[0]) / (t[k] - t[0]), stq / stt)
}

/// The readout of `seq`'s first dark `ramp` (module docs); None when fewer than 20
/// pixels show a curvature above the read noise, or the ramp has fewer than 3 reads.
pub fn measure(seq: &Sequence, ramp: &CalibRamp) -> Option<Readout> {
    let e = &seq.exposures[ramp.dark];
    let (q, t) = (e.ramp.as_ref()?, e.ramp_times_s.as_ref()?);
    let t: Vec<f64> = t.to_vec();
    if t.len() < 3 || q.shape()[0] != t.len() {
        return None;
    }
    let mut rows = Vec::new();
    for ((y, x), &m) in e.image.indexed_iter() {
        if !m.is_finite() || e.flags[[y, x]] & BAD_BITS != 0 {
            continue;
        }
        let reads: Vec<f64> = (0..t.len()).map(|s| f64::from(q[[s, y, x]])).collect();
        if reads.iter().any(|v| !v.is_finite()) {
            continue;
        }
        let (c, l) = slopes(&t, &reads);
        rows.push((f64::from(m) - c, l - c));
    }
    // the chord's error from read noise, sqrt(2) sigma_read / span, is the line's
    // (the exposure's measured slope noise, sqrt(12 / N) sigma_read / span) times
    // sqrt(N / 6)
    let noise = seq.noise_e_per_s.get(ramp.dark).copied().unwrap_or(0.0);
    let floor = 3.0 * noise * (t.len() as f64 / 6.0).sqrt();
    rows.retain(|&(_, d)| d.abs() > floor && d.is_finite());
    if rows.len() < 20 {
        return None;
    }
    let sxy: f64 = rows.iter().map(|(a, d)| a * d).sum();
    let sxx: f64 = rows.iter().map(|(_, d)| d * d).sum();
    Some(Readout {
        first_read_s: t[0],
        line_fraction: (sxy / sxx).clamp(0.0, 1.0),
        pixels: rows.len(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The chord and the line of a straight ramp are its slope; of a curved one the
    /// line reads less than the chord (the ramp `ln(t + 1)`, convex decay).
    #[test]
    fn chord_and_line_of_straight_and_curved_ramps() {
        let t: Vec<f64> = (1..=120).map(|i| 1.5 * f64::from(i)).collect();
        let q: Vec<f64> = t.iter().map(|x| 3.0 + 0.25 * x).collect();
        let (c, l) = slopes(&t, &q);
        assert!((c - 0.25).abs() < 1e-12 && (l - 0.25).abs() < 1e-12);
        let q: Vec<f64> = t.iter().map(|x| 100.0 * (x + 1.0).ln()).collect();
        let (c, l) = slopes(&t, &q);
        assert!(l < 0.9 * c, "line {l}, chord {c}");
    }

    /// The arguments hold the chord, and the line only above its minimum share.
    #[test]
    fn with_args_add_the_line_only_when_measured() {
        let r = |f| Readout {
            first_read_s: 1.5,
            line_fraction: f,
            pixels: 100,
        };
        assert_eq!(r(0.02).with_args(), ["chord:strength=1,first_read_s=1.5"]);
        assert_eq!(
            r(0.97).with_args(),
            [
                "chord:strength=1,first_read_s=1.5",
                "linefit_bias:strength=0.970,first_read_s=1.5"
            ]
        );
    }
}
