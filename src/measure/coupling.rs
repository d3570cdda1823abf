//! The readout's coupling of neighbours (inter-pixel capacitance) measured on the
//! illuminated images' isolated bright pixels: the classic single-pixel method
//! (Moore, Ninkov & Forrest 2006; Kannawadi et al. 2016, PASP 128, 095001).
//!
//! # Method
//! A source is a pixel of an illuminated exposure's fluence map
//! ([`super::data::fluence`]) that stands alone: its excess `E` over the local level
//! `b` (the median of the 16 pixels two steps away, all finite) is at least
//! [`MIN_SNR`] times those pixels' robust spread, each of its 8 neighbours' excess is at
//! most [`ISOLATION`] of `E` (a pixel with a bright neighbour, or a spot wider than one
//! pixel, is not a source), and none of the 16 is farther than [`RING_ISOLATION`] of
//! `E` from `b` (no other bright pixel couples into its neighbours). At least two steps
//! from the array's edge. For each source the neighbours' excesses as shares of `E`:
//! `r_x` the mean of the two row neighbours (`x +- 1`), `r_y` of the two column
//! neighbours, `r_d` of the four diagonal ones.
//!
//! The measured image is `K` of the received one ([`crate::model::effects::ipc`]): a
//! lone pixel of received fluence `F` reads `c F` and its row neighbours `alpha_x F`,
//! so `r_x = alpha_x / c` and `c = 1 / (1 + 2 r_x + 2 r_y + 4 r_d)`. Each ratio is the
//! median over the sources; its standard error `1.2533 * 1.4826 * MAD / sqrt(n)`.
//!
//! # Invariants
//! - Pure array code: no files; deterministic (medians do not depend on order).
//! - `None` below [`MIN_SOURCES`] sources: the caller keeps its defaults.
//! - Charge that truly moved into a neighbour before it was trapped (blooming) is
//!   measured here too; what the persistence of the neighbours then shows separates
//!   the two (`diagnose` offers `blooming` beside `ipc`).

use super::data::Sequence;
use crate::stats::median;
use ndarray::Array2;

/// Sources needed for a measurement.
pub const MIN_SOURCES: usize = 8;
/// A source's neighbours' excess at most this share of its own.
pub const ISOLATION: f64 = 0.1;
/// The pixels two steps from a source at most this share of its excess from the level.
pub const RING_ISOLATION: f64 = 0.02;
/// A source's excess at least this many times the robust spread around it.
pub const MIN_SNR: f64 = 50.0;

/// The measured coupling (module docs).
#[derive(Debug, Clone, PartialEq)]
pub struct Coupling {
    /// Per row neighbour (`x +- 1`), per column neighbour, per diagonal neighbour.
    pub alpha_x: f64,
    pub alpha_y: f64,
    pub alpha_d: f64,
    /// Their standard errors.
    pub sigma_x: f64,
    pub sigma_y: f64,
    pub sigma_d: f64,
    /// Sources used, and the exposures (indices into the sequence) they were found in.
    pub sources: usize,
    pub exposures: Vec<usize>,
}

/// The neighbours' shares `(r_x, r_y, r_d)` of each source of one fluence map.
/// The offsets `(dy, dx)` of a pixel's 8 neighbours.
const NEIGHBOURS: [(isize, isize); 8] = [
    (0, -1),
    (0, 1),
    (-1, 0),
    (1, 0),
    (-1, -1),
    (-1, 1),
    (1, -1),
    (1, 1),
];

pub fn source_ratios(f: &Array2<f64>) -> Vec<[f64; 3]> {
    let (ny, nx) = f.dim();
    let mut out = Vec::new();
    if ny < 5 || nx < 5 {
        return out;
    }
    let mut ring = Vec::with_capacity(16);
    for y in 2..ny - 2 {
        for x in 2..nx - 2 {
            let c = f[[y, x]];
            // a source is brighter than each of its 8 neighbours (their excess is at
            // most ISOLATION of its own): most pixels end here, before any median
            let at =
                |dy: isize, dx: isize| f[[y.wrapping_add_signed(dy), x.wrapping_add_signed(dx)]];
            if !c.is_finite() || !NEIGHBOURS.iter().all(|&(dy, dx)| at(dy, dx) < c) {
                continue;
            }
            ring.clear();
            for dy in -2isize..=2 {
                for dx in -2isize..=2 {
                    if dy.abs() == 2 || dx.abs() == 2 {
                        ring.push(at(dy, dx));
                    }
                }
            }
            if ring.iter().any(|v| !v.is_finite()) {
                continue;
            }
            let b = median(&ring);
            let e = c - b;
            let dev: Vec<f64> = ring.iter().map(|v| (v - b).abs()).collect();
            let spread = 1.4826 * median(&dev);
            let far = dev.iter().fold(0.0f64, |a, v| a.max(*v));
            if !(e > 0.0 && e >= MIN_SNR * spread && far <= RING_ISOLATION * e) {
                continue;
            }
            let ex = |dy: isize, dx: isize| at(dy, dx) - b;
            let row = [ex(0, -1), ex(0, 1)];
            let col = [ex(-1, 0), ex(1, 0)];
            let diag = [ex(-1, -1), ex(-1, 1), ex(1, -1), ex(1, 1)];
            let all = row.iter().chain(&col).chain(&diag);
            if all.clone().any(|v| !v.is_finite() || *v > ISOLATION * e) {
                continue;
            }
            let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64 / e;
            out.push([mean(&row), mean(&col), mean(&diag)]);
        }
    }
    out
}

/// The coupling from the sources' ratios (module docs); `None` below [`MIN_SOURCES`].
/// Returns the weights `[alpha_x, alpha_y, alpha_d]` and their standard errors.
pub fn from_ratios(ratios: &[[f64; 3]]) -> Option<([f64; 3], [f64; 3])> {
    if ratios.len() < MIN_SOURCES {
        return None;
    }
    let n = ratios.len() as f64;
    let stat = |k: usize| {
        let v: Vec<f64> = ratios.iter().map(|r| r[k]).collect();
        let m = median(&v);
        let mad = median(&v.iter().map(|x| (x - m).abs()).collect::<Vec<_>>());
        (m, 1.2533 * 1.4826 * mad / n.sqrt())
    };
    let (rx, sx) = stat(0);
    let (ry, sy) = stat(1);
    let (rd, sd) = stat(2);
    let c = 1.0 / (1.0 + 2.0 * rx + 2.0 * ry + 4.0 * rd);
    c.is_finite()
        .then_some(([rx * c, ry * c, rd * c], [sx * c, sy * c, sd * c]))
}

/// The coupling measured on `seq`'s illuminated exposures (module docs).
pub fn measure(seq: &Sequence) -> Option<Coupling> {
    let mut ratios = Vec::new();
    let mut exposures = Vec::new();
    for &i in &seq.illuminations {
        let r = source_ratios(&super::data::fluence(&seq.exposures[i]));
        if !r.is_empty() {
            exposures.push(i);
        }
        ratios.extend(r);
    }
    let (a, s) = from_ratios(&ratios)?;
    Some(Coupling {
        alpha_x: a[0],
        alpha_y: a[1],
        alpha_d: a[2],
        sigma_x: s[0],
        sigma_y: s[1],
        sigma_d: s[2],
        sources: ratios.len(),
        exposures,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::effects::ipc::{couple, Kernel};

    /// Lone pixels on a flat level, coupled by a known anisotropic kernel, give back
    /// its weights (the measured image is `K` of the received one: module docs).
    #[test]
    fn lone_pixels_give_back_the_kernel_they_were_coupled_by() {
        let (ax, ay, ad) = (0.025, 0.01, 0.004);
        let mut f = Array2::from_elem((40, 40), 50.0);
        for y in (4..36).step_by(8) {
            for x in (4..36).step_by(8) {
                f[[y, x]] = 1e5 + 1e3 * (y + x) as f64;
            }
        }
        let measured = couple(&f, &Kernel::new(ax, ay, ad));
        let r = source_ratios(&measured);
        assert_eq!(r.len(), 16);
        let (a, s) = from_ratios(&r).unwrap();
        for (got, want) in a.iter().zip([ax, ay, ad]) {
            assert!((got - want).abs() < 1e-9, "{a:?}");
        }
        assert!(s.iter().all(|s| *s < 1e-9), "{s:?}");
    }

    /// A spot wider than a pixel, a pair of bright neighbours and a pixel near another
    /// bright one are not sources; too few sources measure nothing.
    #[test]
    fn spots_pairs_and_crowded_pixels_are_not_sources() {
        let mut f = Array2::from_elem((30, 30), 10.0);
        // a 2-pixel pair
        f[[5, 5]] = 1e5;
        f[[5, 6]] = 8e4;
        // a lone pixel two steps from another bright one
        f[[15, 15]] = 1e5;
        f[[15, 17]] = 5e4;
        // a spot: centre and a ring at 30 %
        f[[24, 24]] = 1e5;
        for (dy, dx) in [(-1, 0), (1, 0), (0, -1), (0, 1)] {
            f[[(24 + dy) as usize, (24 + dx) as usize]] = 3e4;
        }
        assert!(source_ratios(&f).is_empty());
        let lone = [[0.01, 0.01, 0.0]; MIN_SOURCES - 1];
        assert!(from_ratios(&lone).is_none());
    }
}
