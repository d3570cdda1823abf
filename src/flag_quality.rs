//! Flags against a truth: how often a model flags a pixel-exposure whose true
//! persistence current is below a threshold (**over-flagged**) and leaves one above it
//! unflagged (**missed**), by band of true current, at the model's two thresholds.
//! Non-functional pixels are left out (masked anyway); [`TruthTally`] counts from a
//! stated exposure index on (the demo and the validation pages: 200, after the first
//! hours of history). One piece of code for `persist demo`, `persist verify` (where the
//! input holds a simulator's truth), `persist compare` and the validation pages.

use crate::flags::{bits, pbits};
use ndarray::Array2;

/// Bands of true current, in units of the threshold: `[1, 1.5)`, `[1.5, 2)`, `[2, 3)`,
/// `[3, inf)` (0.1-0.15, 0.15-0.2, 0.2-0.3, above 0.3 e-/s at 0.1 e-/s).
pub const BANDS: [f64; 4] = [1.0, 1.5, 2.0, 3.0];

/// Counts at one threshold over pixel-exposures.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct FlagTally {
    pub threshold_e_per_s: f64,
    /// Functional pixel-exposures counted.
    pub samples: u64,
    pub flagged: u64,
    /// Flagged while the truth is below the threshold.
    pub over_flagged: u64,
    /// Truth at or above the threshold, per band ([`BANDS`]).
    pub above: [u64; 4],
    /// Of those, not flagged.
    pub missed: [u64; 4],
}

impl FlagTally {
    pub fn new(threshold_e_per_s: f64) -> FlagTally {
        FlagTally {
            threshold_e_per_s,
            ..FlagTally::default()
        }
    }

    /// Add one exposure: `flagged` the model's flag at this threshold per pixel.
    pub fn add(&mut self, flagged: &Array2<bool>, truth: &Array2<f32>, flags: &Array2<u32>) {
        let th = self.threshold_e_per_s;
        for ((f, t), fl) in flagged.iter().zip(truth.iter()).zip(flags.iter()) {
            if fl & bits::NONFUNC != 0 {
                continue;
            }
            self.samples += 1;
            let t = f64::from(*t);
            if *f {
                self.flagged += 1;
            }
            if t < th {
                if *f {
                    self.over_flagged += 1;
                }
                continue;
            }
            let b = BANDS.iter().rposition(|&lo| t >= lo * th).unwrap_or(0);
            self.above[b] += 1;
            if !*f {
                self.missed[b] += 1;
            }
        }
    }

    /// Over-flagged pixel-exposures per functional pixel-exposure.
    pub fn over_flag_fraction(&self) -> f64 {
        self.over_flagged as f64 / self.samples.max(1) as f64
    }

    /// Missed fraction of band `b`'s pixel-exposures (NaN when the band is empty).
    pub fn missed_fraction(&self, b: usize) -> f64 {
        if self.above[b] == 0 {
            f64::NAN
        } else {
            self.missed[b] as f64 / self.above[b] as f64
        }
    }

    /// Missed fraction over every band.
    pub fn missed_fraction_all(&self) -> f64 {
        let a: u64 = self.above.iter().sum();
        let m: u64 = self.missed.iter().sum();
        if a == 0 {
            f64::NAN
        } else {
            m as f64 / a as f64
        }
    }
}

/// Both thresholds' tallies of one flagger over a run, from `from_exposure` on.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct TruthTally {
    /// Exposures with a lower index are not counted.
    pub from_exposure: u64,
    /// At the high threshold (`pflags` `HIGH`, the flag).
    pub high: FlagTally,
    /// At the low threshold (`HIGH` or `LOW`).
    pub low: FlagTally,
}

/// The exposure index from which the demo and the validation pages count.
pub const FROM_EXPOSURE: u64 = 200;

impl TruthTally {
    pub fn new(high_e_per_s: f64, low_e_per_s: f64, from_exposure: u64) -> TruthTally {
        TruthTally {
            from_exposure,
            high: FlagTally::new(high_e_per_s),
            low: FlagTally::new(low_e_per_s),
        }
    }

    /// Add exposure `exposure_index`: the stage's `/persistence/flags` (`pflags`), the
    /// true persistence current and the on-board flags.
    pub fn add_pflags(
        &mut self,
        exposure_index: u64,
        pflags: &Array2<u8>,
        truth: &Array2<f32>,
        flags: &Array2<u32>,
    ) {
        let hi = pflags.mapv(|f| f & pbits::HIGH != 0);
        let lo = pflags.mapv(|f| f & (pbits::LOW | pbits::HIGH) != 0);
        self.add(exposure_index, (&hi, &lo), truth, flags);
    }

    /// Add exposure `exposure_index` flagged `(high, low)` by any flagger.
    pub fn add(
        &mut self,
        exposure_index: u64,
        (high, low): (&Array2<bool>, &Array2<bool>),
        truth: &Array2<f32>,
        flags: &Array2<u32>,
    ) {
        if exposure_index < self.from_exposure {
            return;
        }
        self.high.add(high, truth, flags);
        self.low.add(low, truth, flags);
    }

    /// The flag-quality table (markdown): one row per threshold.
    pub fn table(&self) -> String {
        table(&[("", self)])
    }
}

/// Markdown table of several flaggers' tallies, one row per flagger and threshold:
/// flagged, over-flagged (per functional pixel-exposure), missed per band of true
/// current (in units of the threshold: [`BANDS`]) and missed in all.
pub fn table(rows: &[(&str, &TruthTally)]) -> String {
    let named = rows.iter().any(|r| !r.0.is_empty());
    let mut s = String::new();
    if named {
        s += "| flagger ";
    }
    s += "| threshold | flagged | over-flagged | missed 1-1.5x | missed 1.5-2x | missed 2-3x | \
          missed >3x | missed, all |\n";
    if named {
        s += "|---";
    }
    s += "|---|---|---|---|---|---|---|---|\n";
    let pct = |v: f64| {
        if v.is_nan() {
            "-".to_string()
        } else {
            format!("{:.2} %", 100.0 * v)
        }
    };
    for (name, t) in rows {
        for q in [&t.high, &t.low] {
            if named {
                s += &format!("| {name} ");
            }
            s += &format!(
                "| {} e-/s | {} | {} | {} | {} | {} | {} | {} |\n",
                q.threshold_e_per_s,
                pct(q.flagged as f64 / q.samples.max(1) as f64),
                pct(q.over_flag_fraction()),
                pct(q.missed_fraction(0)),
                pct(q.missed_fraction(1)),
                pct(q.missed_fraction(2)),
                pct(q.missed_fraction(3)),
                pct(q.missed_fraction_all()),
            );
        }
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tally_counts_bands() {
        let mut t = FlagTally::new(0.1);
        let truth =
            Array2::from_shape_vec((1, 6), vec![0.05, 0.05, 0.12, 0.17, 0.25, 0.5]).unwrap();
        let flagged =
            Array2::from_shape_vec((1, 6), vec![true, false, false, true, true, false]).unwrap();
        let mut flags = Array2::<u32>::zeros((1, 6));
        t.add(&flagged, &truth, &flags);
        assert_eq!(t.samples, 6);
        assert_eq!(t.over_flagged, 1);
        assert_eq!(t.above, [1, 1, 1, 1]);
        assert_eq!(t.missed, [1, 0, 0, 1]);
        flags[[0, 0]] = bits::NONFUNC;
        let mut u = FlagTally::new(0.1);
        u.add(&flagged, &truth, &flags);
        assert_eq!((u.samples, u.over_flagged), (5, 0));
    }
}
