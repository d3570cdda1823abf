//! Whether the decay's shape depends on the fluence (the class `fluence_x_time`).
//!
//! The flagging model has one decay law for every fluence: its response `A_k` scales
//! the same time shape `sum_n C_n exp(-t / tau_n)`. A detector whose brighter pixels
//! fill other traps than its fainter ones decays with another shape at each fluence.
//! No contrast tests that ([`super::contrast`], "Contrast classes"): it is a function
//! of (fluence, time since illumination) alone, which the flexible base and the pixel
//! reference take in by construction. It is measured here directly from the
//! measurements, as the tilt of the decay of brighter pixels against that of fainter
//! ones.
//!
//! # The tilt between fluence bins
//! Only the samples after the first illumination event are used: the traps were
//! empty before it, so nothing but the fluence differs between its pixels (a later
//! illumination meets what earlier ones left, which differs with the fluence too). They
//! are grouped in cells of [`BINS_PER_DECADE`] fluence bins per decade (from
//! [`MIN_FLUENCE_E`]) and [`TIME_BINS_PER_DECADE`] bins per decade of the time since
//! the illumination; each cell holds the same pixels at every time, and its mean
//! measured current `m` (cells of at least [`MIN_CELL_SAMPLES`] samples whose mean
//! exceeds [`MIN_CELL_SNR`] standard errors) gives `L = log10 m`, with the variance
//! of the mean propagated. For two fluence bins `j < k` the weighted least-squares slope
//! of `L_k - L_j` against `log10 t` over the time bins both hold is the tilt of the
//! brighter bin's decay against the fainter's: 0 when both decay alike, positive when
//! the brighter decays more slowly. It needs no model and no common decay law: any law
//! shared by both bins cancels. A fluence bin is used when its cells span
//! [`MIN_TIME_SPAN_DECADES`] of time.
//!
//! Filling the traps by itself can make the shape depend on the fluence: on the
//! second generator's campaigns with nothing hidden, fainter pixels decay more slowly
//! (the traps that empty fastest fill least at low flux). The rise is the largest
//! positive tilt of a brighter bin against a fainter one, at least [`MIN_RISE_Z`]
//! standard errors; the shape depends on the fluence when it is at least [`MIN_RISE`].
//! Measured with examples/shape_tilt (64 x 64, seeds 1-3, single illuminations and
//! campaigns, with and without dark pixels): with nothing hidden, the rise was 0 on
//! every sequence of the second generator and at most 0.037 (z 5.3) on those of
//! `src/sim`, whose truth tilts by about 0.03 between 10^5 and 10^7 e-; with
//! `shape:fill_depth` (the main population tilted towards slow traps as the fluence
//! grows) it was 0.105-0.34.
//!
//! # Invariants
//! - Pure: samples in, numbers out; same samples, same result.
//! - Every tilt reported is finite.

use super::eval::Samples;
use serde::Serialize;
use std::collections::BTreeMap;

/// Fluence bins per decade.
pub const BINS_PER_DECADE: f64 = 2.0;
/// Time bins per decade.
pub const TIME_BINS_PER_DECADE: f64 = 4.0;
/// The faintest fluence tested, e-: below it the persistence is within the noise of
/// late darks.
pub const MIN_FLUENCE_E: f64 = 1e4;
/// Samples a cell needs.
pub const MIN_CELL_SAMPLES: usize = 30;
/// A cell's mean must exceed this many standard errors (its log is then defined).
pub const MIN_CELL_SNR: f64 = 3.0;
/// Decades of time since the illumination a fluence bin's cells must span.
pub const MIN_TIME_SPAN_DECADES: f64 = 1.0;
/// Smallest rise of the tilt that depends (module docs).
pub const MIN_RISE: f64 = 0.07;
/// Smallest rise in standard errors.
pub const MIN_RISE_Z: f64 = 5.0;

/// One fluence bin.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TiltBin {
    /// The bin's lower edge, log10 e-.
    pub log10_fluence_e: f64,
    /// Samples in its cells used.
    pub samples: usize,
    /// The tilt of its decay against the faintest bin's (0 for that one), per decade of
    /// time.
    pub tilt: f64,
    pub tilt_se: f64,
}

/// The decay's shape against the fluence (module docs).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct DecayShape {
    /// The illumination whose darks it was measured on (exposure index).
    pub illumination_exposure: u64,
    pub bins: Vec<TiltBin>,
    /// The largest tilt of a brighter bin against a fainter one of at least
    /// [`MIN_RISE_Z`] standard errors (0 when none).
    pub rise: f64,
    pub rise_z: f64,
    /// The two bins of the rise (lower edges, log10 e-).
    pub from_log10_fluence_e: f64,
    pub to_log10_fluence_e: f64,
    pub depends: bool,
}

/// A cell's log10 mean, its variance and its mean log10 time.
#[derive(Debug, Clone, Copy)]
struct LogMean {
    y: f64,
    var: f64,
    x: f64,
    n: usize,
}

/// The first event's cells: fluence bin -> time bin -> log mean (module docs).
fn cells(s: &Samples) -> BTreeMap<i64, BTreeMap<i64, LogMean>> {
    let np = s.npix();
    let Some(&first) = s.events().first() else {
        return BTreeMap::new();
    };
    // n, sum, sum of squares, sum of log10 t
    let mut sums: BTreeMap<(i64, i64), (usize, f64, f64, f64)> = BTreeMap::new();
    for (i, &m) in s.measured.iter().enumerate() {
        let (row, f) = (i / np, s.fluence_e[i]);
        let t = s.t_since_s[row];
        if s.event[row] != first || !(m.is_finite() && f.is_finite() && f >= MIN_FLUENCE_E) {
            continue;
        }
        if !(t.is_finite() && t > 0.0) {
            continue;
        }
        let key = (
            (f.log10() * BINS_PER_DECADE).floor() as i64,
            (t.log10() * TIME_BINS_PER_DECADE).floor() as i64,
        );
        let e = sums.entry(key).or_insert((0, 0.0, 0.0, 0.0));
        *e = (e.0 + 1, e.1 + m, e.2 + m * m, e.3 + t.log10());
    }
    let ln10 = std::f64::consts::LN_10;
    let mut out: BTreeMap<i64, BTreeMap<i64, LogMean>> = BTreeMap::new();
    for ((j, tb), (n, s1, s2, lt)) in sums {
        if n < MIN_CELL_SAMPLES {
            continue;
        }
        let nf = n as f64;
        let mean = s1 / nf;
        let var_mean = (s2 / nf - mean * mean).max(0.0) / nf;
        if !(mean > MIN_CELL_SNR * var_mean.sqrt() && mean > 0.0) {
            continue;
        }
        let y = mean.log10();
        let var = var_mean / (mean * mean * ln10 * ln10);
        if y.is_finite() && var.is_finite() {
            out.entry(j).or_default().insert(
                tb,
                LogMean {
                    y,
                    var: var.max(f64::MIN_POSITIVE),
                    x: lt / nf,
                    n,
                },
            );
        }
    }
    out.retain(|_, c| {
        let xs = c.values().map(|l| l.x);
        let (lo, hi) = xs.fold((f64::INFINITY, f64::NEG_INFINITY), |a, x| {
            (a.0.min(x), a.1.max(x))
        });
        hi - lo >= MIN_TIME_SPAN_DECADES
    });
    out
}

/// The tilt of `b`'s decay against `a`'s and its standard error (module docs); None
/// when their common time bins span less than [`MIN_TIME_SPAN_DECADES`].
fn tilt(a: &BTreeMap<i64, LogMean>, b: &BTreeMap<i64, LogMean>) -> Option<(f64, f64)> {
    let (mut sw, mut sx, mut sy, mut sxx, mut sxy) = (0.0, 0.0, 0.0, 0.0, 0.0);
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for (tb, la) in a {
        let Some(lb) = b.get(tb) else {
            continue;
        };
        let w = 1.0 / (la.var + lb.var);
        let (x, y) = (0.5 * (la.x + lb.x), lb.y - la.y);
        sw += w;
        sx += w * x;
        sy += w * y;
        sxx += w * x * x;
        sxy += w * x * y;
        lo = lo.min(x);
        hi = hi.max(x);
    }
    let det = sw * sxx - sx * sx;
    if hi - lo < MIN_TIME_SPAN_DECADES || det.is_nan() || det <= 0.0 {
        return None;
    }
    let slope = (sw * sxy - sx * sy) / det;
    let se = (sw / det).sqrt();
    (slope.is_finite() && se.is_finite()).then_some((slope, se))
}

/// Whether the samples can show a tilt: two fluence bins after the first illumination
/// whose cells span [`MIN_TIME_SPAN_DECADES`] of time (module docs).
pub fn testable(s: &Samples) -> bool {
    measure(s, 0).is_some()
}

/// The decay's shape against the fluence of `s` (module docs), `illumination_exposure`
/// the exposure index to report for the first event; None with fewer than two fluence
/// bins.
pub fn measure(s: &Samples, illumination_exposure: u64) -> Option<DecayShape> {
    let c = cells(s);
    let keys: Vec<i64> = c.keys().copied().collect();
    let faintest = *keys.first()?;
    let bins: Vec<TiltBin> = keys
        .iter()
        .filter_map(|k| {
            let (tilt, tilt_se) = if *k == faintest {
                (0.0, 0.0)
            } else {
                tilt(&c[&faintest], &c[k])?
            };
            Some(TiltBin {
                log10_fluence_e: *k as f64 / BINS_PER_DECADE,
                samples: c[k].values().map(|l| l.n).sum(),
                tilt,
                tilt_se,
            })
        })
        .collect();
    if bins.len() < 2 {
        return None;
    }
    let mut best = (0.0, 0.0, faintest, faintest);
    for (n, &j) in keys.iter().enumerate() {
        for &k in &keys[n + 1..] {
            if let Some((rise, se)) = tilt(&c[&j], &c[&k]) {
                if rise > best.0 && rise >= MIN_RISE_Z * se {
                    best = (rise, rise / se, j, k);
                }
            }
        }
    }
    let (rise, rise_z, j, k) = best;
    Some(DecayShape {
        illumination_exposure,
        bins,
        rise,
        rise_z,
        from_log10_fluence_e: j as f64 / BINS_PER_DECADE,
        to_log10_fluence_e: k as f64 / BINS_PER_DECADE,
        depends: rise >= MIN_RISE,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::measure::eval::Cells;

    /// 200 pixels per fluence, eight rows from 100 s to 10^4.5 s after one
    /// illumination, measured `1e-4 F / t (t / 1000 s)^tilt(F)` times `1 +- 0.01`
    /// alternating from pixel to pixel.
    fn samples(tilt_of: impl Fn(f64) -> f64, fluences: &[f64]) -> Samples {
        let times: Vec<f64> = (0..8)
            .map(|i| 10f64.powf(2.0 + 2.5 * i as f64 / 7.0))
            .collect();
        let np = fluences.len() * 200;
        let n = times.len() * np;
        let mut measured = vec![0.0; n];
        let mut fluence_e = vec![0.0; n];
        for (r, &t) in times.iter().enumerate() {
            for px in 0..np {
                let f = fluences[px / 200];
                let wiggle = if px % 2 == 0 { 1.01 } else { 0.99 };
                measured[r * np + px] = 1e-4 * f / t * (t / 1000.0).powf(tilt_of(f)) * wiggle;
                fluence_e[r * np + px] = f;
            }
        }
        let rows = times.len();
        Samples {
            cells: Cells::default(),
            statistic: Default::default(),
            stride: 1,
            pixels: (0..np).map(|p| (0, p)).collect(),
            exposures: (0..rows).collect(),
            measured,
            noise: vec![0.01; rows],
            shot_var_per_e_per_s: vec![0.0; rows],
            noise_scale: Default::default(),
            spread_rel: vec![0.0; n],
            fluence_e,
            neighbour_excess_e: vec![0.0; n],
            t_since_s: times,
            event: vec![0; rows],
            illumination_time_s: vec![481.0; rows],
            temperature_k: vec![80.0; rows],
            earlier_illuminations: vec![0.0; rows],
            radius: vec![0.0; np],
        }
    }

    /// Fluences in the bins 10^4, 10^5, 10^6 and 10^7 e-.
    const FLUENCES: [f64; 4] = [3e4, 3e5, 3e6, 3e7];

    #[test]
    fn a_decay_law_shared_by_every_fluence_shows_no_tilt() {
        let d = measure(&samples(|_| 0.3, &FLUENCES), 7).expect("four bins");
        assert_eq!(d.bins.len(), 4);
        assert_eq!(d.illumination_exposure, 7);
        assert!(d.bins.iter().all(|b| b.tilt.abs() < 1e-3), "{d:?}");
        assert!(d.rise < 1e-3 && !d.depends, "{d:?}");
    }

    #[test]
    fn fainter_pixels_decaying_more_slowly_as_filling_gives_do_not_depend() {
        let d = measure(&samples(|f| 0.4 - 0.05 * f.log10(), &FLUENCES), 0).expect("bins");
        assert!((d.bins[3].tilt + 0.15).abs() < 0.01, "{d:?}");
        assert_eq!(d.rise, 0.0);
        assert!(!d.depends);
    }

    #[test]
    fn brighter_pixels_decaying_more_slowly_depend_and_the_rise_is_measured() {
        let d = measure(&samples(|f| 0.1 * (f / 3e4).log10(), &FLUENCES), 0).expect("bins");
        assert!(d.depends, "{d:?}");
        assert!((d.rise - 0.3).abs() < 0.01, "{d:?}");
        assert_eq!((d.from_log10_fluence_e, d.to_log10_fluence_e), (4.0, 7.0));
        // a rise under MIN_RISE is measured but does not depend
        let d = measure(&samples(|f| 0.01 * (f / 3e4).log10(), &FLUENCES), 0).expect("bins");
        assert!((d.rise - 0.03).abs() < 0.005 && !d.depends, "{d:?}");
    }

    #[test]
    fn only_the_first_illumination_counts() {
        let mut s = samples(|f| 0.1 * (f / 3e4).log10(), &FLUENCES);
        // the last five rows follow a second illumination: the first's rows alone span
        // under a decade (100 s to 10^(2 + 2.5 * 2 / 7) s)
        for e in s.event.iter_mut().skip(3) {
            *e = 1;
        }
        assert!(measure(&s, 0).is_none());
        assert!(!testable(&s));
    }

    #[test]
    fn one_fluence_bin_or_too_short_a_time_span_cannot_show_a_tilt() {
        assert!(measure(&samples(|_| 0.0, &[3e5]), 0).is_none());
        assert!(!testable(&samples(|_| 0.0, &[3e5])));
        let mut s = samples(|_| 0.0, &FLUENCES);
        assert!(testable(&s));
        s.t_since_s = vec![1000.0; s.t_since_s.len()];
        assert!(measure(&s, 0).is_none());
        assert!(!testable(&s));
    }
}
