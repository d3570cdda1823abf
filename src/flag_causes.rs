//! Where a flagger's errors are: its over-flagged and missed pixel-exposures
//! ([`crate::flag_quality`]) at both thresholds, counted by cause along four axes:
//! - **the kind of the pixel's last event**: a saturating exposure (true fluence at
//!   least the full well), a bright unsaturated one (true fluence at least
//!   [`BRIGHT_FRACTION`] of the full well), a `TRANSIENT` (the on-board flag of a
//!   cosmic-ray hit), or none since the counts began;
//! - **the time since that event**, from the reset ending its exposure to the start of
//!   the exposure counted ([`TIME_EDGES_S`]);
//! - **whether early release acted** on the pixel since that event (the step's
//!   `RELEASED` bit in this exposure or any since);
//! - **the ratio predicted / true** persistence current ([`RATIO_EDGES`]).
//!
//! The truth (true fluence, true current) only counts: nothing here reaches a model or
//! its flags. Events are taken from every exposure, counted or not, so that a pixel's
//! history before [`crate::flag_quality::FROM_EXPOSURE`] is known.
//!
//! Invariant: along each axis the categories partition the counted pixel-exposures, so
//! each axis's counts add up to the same totals as the threshold's
//! [`crate::flag_quality::FlagTally`].

use crate::flags::{bits, pbits};
use ndarray::Array2;

/// An unsaturated event: a true fluence of at least this fraction of the full well
/// (5 %: 10,000 e- of 200,000; a source that faint leaves well under 0.1 e-/s).
pub const BRIGHT_FRACTION: f64 = 0.05;

/// Edges of the time-since-event bins, s: under 1,000 s, to 5,600 s (the demo's
/// laboratory sequence ends about there), to 20,000 s, to a day, later.
pub const TIME_EDGES_S: [f64; 4] = [1000.0, 5600.0, 20000.0, 86400.0];

/// Edges of the predicted / true bins.
pub const RATIO_EDGES: [f64; 5] = [0.1, 0.5, 1.0, 2.0, 10.0];

/// The categories of every axis, in table order: (axis, label).
pub const CATEGORIES: [(&str, &str); 18] = [
    ("last event", "saturating"),
    ("last event", "bright, unsaturated"),
    ("last event", "`TRANSIENT`"),
    ("last event", "none"),
    ("time since it", "< 1000 s"),
    ("time since it", "1000-5600 s"),
    ("time since it", "5600-20000 s"),
    ("time since it", "20000-86400 s"),
    ("time since it", "later"),
    ("time since it", "no event"),
    ("early release since it", "acted"),
    ("early release since it", "did not"),
    ("predicted / true", "< 0.1"),
    ("predicted / true", "0.1-0.5"),
    ("predicted / true", "0.5-1"),
    ("predicted / true", "1-2"),
    ("predicted / true", "2-10"),
    ("predicted / true", ">= 10"),
];

const KIND_AT: usize = 0;
const TIME_AT: usize = 4;
const RELEASE_AT: usize = 10;
const RATIO_AT: usize = 12;

/// Kinds of event, in [`CATEGORIES`] order.
const SATURATING: u8 = 0;
const BRIGHT: u8 = 1;
const TRANSIENT: u8 = 2;
const NONE: u8 = 3;

/// Counts of one category at one threshold.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct CauseCounts {
    pub samples: u64,
    pub over_flagged: u64,
    /// Truly at or above the threshold.
    pub above: u64,
    pub missed: u64,
}

/// One flagger's errors by cause, at its two thresholds (module docs).
#[derive(Debug, Clone)]
pub struct CauseTally {
    pub from_exposure: u64,
    pub thresholds_e_per_s: [f64; 2],
    pub full_well_e: f64,
    /// Per threshold (high, low), per [`CATEGORIES`] entry.
    pub counts: [[CauseCounts; CATEGORIES.len()]; 2],
    /// Per pixel: end of its last event's exposure (s), its kind, and whether early
    /// release acted since.
    last: Option<(Array2<f64>, Array2<u8>, Array2<bool>)>,
}

/// One exposure as [`CauseTally::add`] reads it.
pub struct CauseInput<'a> {
    pub exposure_index: u64,
    pub t_start_s: f64,
    pub t_exposure_s: f64,
    /// The flagger's `/persistence/flags` and `/persistence/current`.
    pub pflags: &'a Array2<u8>,
    pub predicted_e_per_s: &'a Array2<f32>,
    /// The true persistence current and the true fluence of this exposure, e-.
    pub truth_e_per_s: &'a Array2<f32>,
    pub true_fluence_e: &'a Array2<f32>,
    /// The on-board flags.
    pub flags: &'a Array2<u32>,
}

impl CauseTally {
    pub fn new(high_e_per_s: f64, low_e_per_s: f64, full_well_e: f64, from: u64) -> CauseTally {
        CauseTally {
            from_exposure: from,
            thresholds_e_per_s: [high_e_per_s, low_e_per_s],
            full_well_e,
            counts: [[CauseCounts::default(); CATEGORIES.len()]; 2],
            last: None,
        }
    }

    /// Count one exposure (from `from_exposure` on), then take its events into the
    /// pixels' histories.
    pub fn add(&mut self, e: &CauseInput<'_>) {
        let dim = e.pflags.dim();
        let (t_end, kind, released) = self.last.get_or_insert_with(|| {
            (
                Array2::from_elem(dim, f64::NEG_INFINITY),
                Array2::from_elem(dim, NONE),
                Array2::from_elem(dim, false),
            )
        });
        for (p, pf) in e.pflags.indexed_iter() {
            released[p] |= pf & pbits::RELEASED != 0;
            if e.exposure_index < self.from_exposure || e.flags[p] & bits::NONFUNC != 0 {
                continue;
            }
            let dt = e.t_start_s - t_end[p];
            let time = if dt.is_finite() {
                TIME_EDGES_S.iter().position(|&x| dt < x).unwrap_or(4)
            } else {
                5
            };
            let truth = f64::from(e.truth_e_per_s[p]);
            let ratio = f64::from(e.predicted_e_per_s[p]) / truth;
            let ratio = RATIO_EDGES
                .iter()
                .position(|&x| ratio < x)
                .unwrap_or(RATIO_EDGES.len());
            let cats = [
                KIND_AT + usize::from(kind[p]),
                TIME_AT + time,
                RELEASE_AT + usize::from(!released[p]),
                RATIO_AT + ratio,
            ];
            let flagged = [pf & pbits::HIGH != 0, pf & (pbits::HIGH | pbits::LOW) != 0];
            for (k, th) in self.thresholds_e_per_s.iter().enumerate() {
                let above = truth >= *th;
                for &c in &cats {
                    let n = &mut self.counts[k][c];
                    n.samples += 1;
                    n.over_flagged += u64::from(flagged[k] && !above);
                    n.above += u64::from(above);
                    n.missed += u64::from(above && !flagged[k]);
                }
            }
        }
        let end = e.t_start_s + e.t_exposure_s;
        for (p, q) in e.true_fluence_e.indexed_iter() {
            let q = f64::from(*q);
            let k = if q >= self.full_well_e {
                SATURATING
            } else if e.flags[p] & bits::TRANSIENT != 0 {
                TRANSIENT
            } else if q >= BRIGHT_FRACTION * self.full_well_e {
                BRIGHT
            } else {
                continue;
            };
            t_end[p] = end;
            kind[p] = k;
            released[p] = false;
        }
    }

    /// The breakdown as a markdown table: one row per category, per threshold the share
    /// of the over-flagged pixel-exposures in the category (and the over-flagged
    /// fraction of its pixel-exposures) and the share of the missed ones (and the missed
    /// fraction of its truly-above pixel-exposures).
    pub fn table(&self) -> String {
        let [h, l] = self.thresholds_e_per_s;
        let mut s = format!(
            "| cause | pixel-exposures | over-flagged at {h} e-/s | missed at {h} e-/s | \
             over-flagged at {l} e-/s | missed at {l} e-/s |\n|---|---|---|---|---|---|\n"
        );
        let pct = |a: u64, b: u64| {
            if b == 0 {
                "-".to_string()
            } else {
                format!("{:.1} %", 100.0 * a as f64 / b as f64)
            }
        };
        // totals along the first axis (every axis has the same)
        let total = |k: usize| {
            self.counts[k][KIND_AT..TIME_AT]
                .iter()
                .fold(CauseCounts::default(), |a, c| CauseCounts {
                    samples: a.samples + c.samples,
                    over_flagged: a.over_flagged + c.over_flagged,
                    above: a.above + c.above,
                    missed: a.missed + c.missed,
                })
        };
        let t = [total(0), total(1)];
        for (i, (axis, label)) in CATEGORIES.iter().enumerate() {
            let mut row = format!(
                "| {axis}: {label} | {} ",
                pct(self.counts[0][i].samples, t[0].samples)
            );
            for (counts, total) in self.counts.iter().zip(&t) {
                let c = &counts[i];
                row += &format!(
                    "| {} ({}) | {} ({}) ",
                    pct(c.over_flagged, total.over_flagged),
                    pct(c.over_flagged, c.samples),
                    pct(c.missed, total.missed),
                    pct(c.missed, c.above),
                );
            }
            s += &row;
            s += "|\n";
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A pixel that saturates, then is missed 2,000 s later, released on the way.
    #[test]
    fn counts_by_last_event_time_and_release() {
        let mut t = CauseTally::new(0.1, 0.01, 2e5, 1);
        let one = |v: f32| Array2::from_elem((1, 1), v);
        let none = Array2::<u32>::zeros((1, 1));
        let mut add = |i: u64, t0: f64, pf: u8, pred: f32, truth: f32, q: f32| {
            t.add(&CauseInput {
                exposure_index: i,
                t_start_s: t0,
                t_exposure_s: 100.0,
                pflags: &Array2::from_elem((1, 1), pf),
                predicted_e_per_s: &one(pred),
                truth_e_per_s: &one(truth),
                true_fluence_e: &one(q),
                flags: &none,
            })
        };
        add(0, 0.0, 0, 0.0, 0.0, 3e5); // not counted: the event
        add(1, 200.0, pbits::RELEASED, 0.0, 0.5, 0.0); // missed at both
        add(2, 2100.0, pbits::LOW, 0.05, 0.005, 0.0); // over-flagged at 0.01
        let c = &t.counts;
        assert_eq!(c[0][KIND_AT + SATURATING as usize].missed, 1);
        assert_eq!(c[1][KIND_AT + SATURATING as usize].missed, 1);
        assert_eq!(c[0][TIME_AT].missed, 1);
        assert_eq!(c[1][TIME_AT + 1].over_flagged, 1);
        assert_eq!(c[1][RELEASE_AT].samples, 2);
        assert_eq!(c[1][RATIO_AT].missed, 1);
        assert_eq!(c[1][RATIO_AT + 5].over_flagged, 1);
        // every axis partitions the samples
        for per_category in c {
            for (a, b) in [
                (KIND_AT, TIME_AT),
                (TIME_AT, RELEASE_AT),
                (RELEASE_AT, RATIO_AT),
            ] {
                let n: u64 = per_category[a..b].iter().map(|x| x.samples).sum();
                assert_eq!(n, 2);
            }
        }
        assert!(t.table().contains("| last event: saturating | 100.0 % "));
    }
}
