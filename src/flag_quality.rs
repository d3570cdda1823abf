//! Flags against a truth: how often a model flags a pixel-exposure whose true
//! persistence current is below a threshold (**over-flagged**) and leaves one above it
//! unflagged (**missed**), by band of true current, at the model's two thresholds.
//! Non-functional pixels are left out (masked anyway); [`TruthTally`] counts from a
//! stated exposure index on (the demo and the validation pages: 200, after the first
//! hours of history). One piece of code for `persist demo`, `persist verify` (where the
//! input holds a simulator's truth), `persist compare` and the validation pages.
//!
//! A baseline flagger for the validation pages: HST WFC3's persistence model with its
//! published constants ([`Wfc3Params`], [`Wfc3Flagger`]).

use crate::flags::{bits, pbits};
use ndarray::Array2;
use std::collections::VecDeque;

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
/// current (in units of the threshold: [`BANDS`]) and missed in all. The bands from 2x
/// up carry the count of missed pixel-exposures in brackets: there the promise is none.
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
    let counted =
        |q: &FlagTally, b: usize| format!("{} ({})", pct(q.missed_fraction(b)), q.missed[b]);
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
                counted(q, 2),
                counted(q, 3),
                pct(q.missed_fraction_all()),
            );
        }
    }
    s
}

/// HST WFC3's persistence model in closed form, the "fermi" model of kslong/Persistence
/// (`subtract_persist.py`: `calc_fermi`, `calc_decay`, `calc_persist`; Long, Baggett &
/// MacKenty, WFC3 ISR 2015-15 and the ISRs before it). A stimulus of `x` e- (a pixel's
/// fluence in an earlier exposure) leaves, `dt` seconds after that exposure ended,
/// `norm (x / e_fermi)^alpha / (exp((e_fermi - x) / kT) + 1) (dt / 1000 s)^-gamma`
/// e-/s, with `x` clipped at [`Wfc3Params::MIN_STIMULUS_E`]. The constants are WFC3's, in
/// electrons of WFC3's detector, not rescaled to another full well.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Wfc3Params {
    /// The persistence current at 1000 s of a stimulus far above `e_fermi_e`, over
    /// `(x / e_fermi)^alpha`, e-/s.
    pub norm_e_per_s: f64,
    /// The slow rise above the Fermi edge, `(x / e_fermi)^alpha`.
    pub alpha: f64,
    /// The power law of the decay, `(dt / 1000 s)^-gamma`.
    pub gamma: f64,
    /// Where the Fermi factor is one half, e-.
    pub e_fermi_e: f64,
    /// The width of the Fermi edge, e-.
    pub kt_e: f64,
    /// An earlier exposure that ended more than this before the middle of the current
    /// one is not considered, s.
    pub lookback_s: f64,
}

impl Wfc3Params {
    /// `calc_persist`'s constants (norm 0.3 e-/s, alpha 0.159, gamma 1.022, e_fermi
    /// 83,400 e-, kT 18,500 e-) and `do_dataset`'s look-back of 16 h.
    pub const PUBLISHED: Wfc3Params = Wfc3Params {
        norm_e_per_s: 0.3,
        alpha: 0.159,
        gamma: 1.022,
        e_fermi_e: 83_400.0,
        kt_e: 18_500.0,
        lookback_s: 16.0 * 3600.0,
    };

    /// `calc_fermi`'s clip of the stimulus (no negative or zero fluence), e-.
    pub const MIN_STIMULUS_E: f64 = 1e-10;

    /// The persistence current `dt_s` after an exposure that ended with a stimulus of
    /// `x_e` (module docs of [`Wfc3Params`]), e-/s. Increases with `x_e`, decreases with
    /// `dt_s` (`dt_s > 0`).
    pub fn current_e_per_s(&self, x_e: f64, dt_s: f64) -> f64 {
        let x = x_e.max(Self::MIN_STIMULUS_E);
        let fermi = 1.0 / (((self.e_fermi_e - x) / self.kt_e).exp() + 1.0);
        self.norm_e_per_s
            * (x / self.e_fermi_e).powf(self.alpha)
            * fermi
            * (dt_s / 1000.0).powf(-self.gamma)
    }
}

/// WFC3's model ([`Wfc3Params`]) run over one detector's exposures in time order, the
/// way `do_dataset` treats each exposure: per pixel, the largest prediction over the
/// earlier exposures within the look-back, `dt` from the end of the earlier exposure to
/// the middle of the current one (WFC3 keeps the stimulus that gives the most
/// persistence; it does not add them). Flagged `HIGH` above the high threshold, `LOW`
/// above the low one or the high (strictly greater, as the stage).
///
/// The stimulus is the pixel's extrapolated fluence
/// ([`crate::model::fluence::extrapolated_fluence_e`]: the line-fit current times the
/// illumination time, as WFC3 takes the flt rate times the exposure time, saturated
/// pixels included) whatever its on-board flags (the line fit around a `TRANSIENT` jump
/// is unbiased, as calwf3's rate after its cosmic-ray rejection). A functional pixel
/// without a finite current (`SUR_ERROR`) takes the largest stimulus of its 3 x 3
/// neighbours (WFC3's `fixup` for saturated pixels without a value), none when no
/// neighbour has one. Non-functional pixels have no stimulus, no prediction and no
/// flags.
///
/// Invariant (exact: it changes no prediction): per pixel, the kept stimuli are in time
/// order with strictly decreasing fluence. A stimulus followed by a later one at least
/// as large can never give the larger prediction again (the prediction increases with
/// the fluence and decreases with the time since, and the later one always has the
/// shorter time), so it is dropped; one that ended more than the look-back before the
/// middle of the current exposure is dropped for good (the middles only move on).
#[derive(Debug, Clone)]
pub struct Wfc3Flagger {
    params: Wfc3Params,
    high_e_per_s: f64,
    low_e_per_s: f64,
    dim: (usize, usize),
    /// Per pixel, row-major: (end of the exposure, UTC seconds; stimulus, e-).
    stimuli: Vec<VecDeque<(f64, f64)>>,
}

impl Wfc3Flagger {
    pub fn new(params: Wfc3Params, high_e_per_s: f64, low_e_per_s: f64) -> Wfc3Flagger {
        Wfc3Flagger {
            params,
            high_e_per_s,
            low_e_per_s,
            dim: (0, 0),
            stimuli: Vec::new(),
        }
    }

    /// The persistence flags (`pbits`) and the predicted current (e-/s) of exposure `e`
    /// from the exposures stepped before it; then `e` joins the stimuli. An exposure of
    /// another shape than the one before starts from no history.
    pub fn step(&mut self, e: &crate::product::Exposure) -> (Array2<u8>, Array2<f32>) {
        let (ny, nx) = e.image.dim();
        if self.dim != (ny, nx) {
            self.dim = (ny, nx);
            self.stimuli = vec![VecDeque::new(); ny * nx];
        }
        let t_mid_s = e.meta.t_start.0 + 0.5 * e.meta.t_exposure_s;
        let t_end_s = e.meta.t_reset().0;
        let mut pflags = Array2::<u8>::zeros((ny, nx));
        let mut cur = Array2::<f32>::zeros((ny, nx));
        let stimulus = wfc3_stimulus_e(e);
        for (k, kept) in self.stimuli.iter_mut().enumerate() {
            let p = (k / nx, k % nx);
            while kept
                .front()
                .is_some_and(|&(end, _)| t_mid_s - end > self.params.lookback_s)
            {
                kept.pop_front();
            }
            let pred = kept
                .iter()
                .map(|&(end, x)| self.params.current_e_per_s(x, t_mid_s - end))
                .fold(0.0, f64::max);
            let high = pred > self.high_e_per_s;
            let low = high || pred > self.low_e_per_s;
            pflags[p] = (u8::from(high) * pbits::HIGH) | (u8::from(low) * pbits::LOW);
            cur[p] = pred as f32;
            if let Some(x) = stimulus[p] {
                while kept.back().is_some_and(|&(_, earlier)| earlier <= x) {
                    kept.pop_back();
                }
                kept.push_back((t_end_s, x));
            }
        }
        (pflags, cur)
    }
}

/// The stimulus of each pixel of `e` ([`Wfc3Flagger`]), e-: `None` for a non-functional
/// pixel or one left without a value.
fn wfc3_stimulus_e(e: &crate::product::Exposure) -> Array2<Option<f64>> {
    let t_ill_s = e.meta.t_illuminated_s();
    let fluence = e.image.mapv(|c| {
        c.is_finite()
            .then(|| crate::model::fluence::extrapolated_fluence_e(c, t_ill_s))
            .filter(|x| x.is_finite())
    });
    let (ny, nx) = e.image.dim();
    Array2::from_shape_fn((ny, nx), |(y, x)| {
        if e.flags[(y, x)] & bits::NONFUNC != 0 {
            return None;
        }
        fluence[(y, x)].or_else(|| {
            let rows = y.saturating_sub(1)..(y + 2).min(ny);
            rows.flat_map(|j| (x.saturating_sub(1)..(x + 2).min(nx)).map(move |i| (j, i)))
                .filter_map(|q| fluence[q])
                .reduce(f64::max)
        })
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::product::Exposure;

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

    /// Reference values computed by hand from `calc_persist`'s formula and constants
    /// (kslong/Persistence, `subtract_persist.py`): at `x = e_fermi` the Fermi factor is
    /// 1/2 and `(x / e_fermi)^alpha` is 1, so 0.3 / 2 = 0.15 e-/s at 1000 s; at 2000 s
    /// times 2^-1.022 = 0.492433; at `x = 2 e_fermi`, 0.3 x 2^0.159 / (exp(-83400 /
    /// 18500) + 1) = 0.331303 e-/s; at `x = 0` (clipped at 1e-10 e-),
    /// 0.3 x (1e-10 / 83400)^0.159 / (exp(83400 / 18500) + 1) = 1.38692e-5 e-/s.
    #[test]
    fn wfc3_current_matches_the_published_formula() {
        let w = Wfc3Params::PUBLISHED;
        let close = |a: f64, b: f64| (a - b).abs() <= 1e-5 * b;
        assert!(close(w.current_e_per_s(83_400.0, 1000.0), 0.15));
        assert!(close(w.current_e_per_s(83_400.0, 2000.0), 0.15 * 0.492_433));
        assert!(close(w.current_e_per_s(166_800.0, 1000.0), 0.331_303));
        assert!(close(w.current_e_per_s(0.0, 1000.0), 1.386_92e-5));
        assert!(close(w.current_e_per_s(-5.0, 1000.0), 1.386_92e-5));
    }

    fn exposure(index: u64, t_start_s: f64, image: Array2<f32>, flags: Array2<u32>) -> Exposure {
        let t = crate::units::UtcSeconds(crate::sim::epoch().0 + t_start_s);
        Exposure {
            meta: crate::sim::meta(1, index, t, 112.0, 80.0, None),
            image,
            flags,
            ramp: None,
            ramp_times_s: None,
        }
    }

    /// The flagger's kept stimuli give the same prediction as the largest over every
    /// earlier exposure within 16 h, on a sequence of fluences from 0 to 3 e_fermi at
    /// irregular times over 26 h.
    #[test]
    fn wfc3_flagger_is_the_maximum_over_the_lookback() {
        let w = Wfc3Params::PUBLISHED;
        let mut f = Wfc3Flagger::new(w, 0.1, 0.01);
        let mut seen: Vec<(f64, [f64; 2])> = Vec::new();
        let mut r: u64 = 7;
        let mut draw = || {
            r = r.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1);
            (r >> 11) as f64 / (1u64 << 53) as f64
        };
        let mut t = 0.0;
        let mut largest = 0.0f64;
        for k in 0..600 {
            // a long gap now and then, so the look-back drops stimuli
            t += 132.0 + 40.0 * draw() + if k % 97 == 96 { 20_000.0 } else { 0.0 };
            let x = [250_000.0 * draw().powi(3), 250_000.0 * draw().powi(6)];
            let image = Array2::from_shape_fn((1, 2), |(_, i)| (x[i] / 112.0) as f32);
            let (pf, cur) = f.step(&exposure(k, t, image.clone(), Array2::zeros((1, 2))));
            let mid = t + 56.0;
            for i in 0..2 {
                let want = seen
                    .iter()
                    .filter(|(end, _)| mid - end <= w.lookback_s)
                    .map(|(end, xs)| w.current_e_per_s(xs[i], mid - end))
                    .fold(0.0, f64::max);
                assert!(
                    (f64::from(cur[(0, i)]) - want).abs() <= 1e-6 * want,
                    "exposure {k} pixel {i}: {} != {want}",
                    cur[(0, i)]
                );
                let flags =
                    (u8::from(want > 0.1) * pbits::HIGH) | (u8::from(want > 0.01) * pbits::LOW);
                assert_eq!(pf[(0, i)], flags, "exposure {k} pixel {i}");
                largest = largest.max(want);
            }
            let x_in = image.mapv(|c| f64::from(c) * 112.0);
            seen.push((t + 112.0, [x_in[(0, 0)], x_in[(0, 1)]]));
        }
        assert!(largest > 0.1, "the sequence reaches the high threshold");
    }

    /// Two stimuli of the same fluence predict what the later one alone does (the
    /// maximum, not the sum); 16 h after the end of the last, nothing.
    #[test]
    fn wfc3_flagger_keeps_the_largest_not_the_sum() {
        let w = Wfc3Params::PUBLISHED;
        let mut f = Wfc3Flagger::new(w, 0.1, 0.01);
        let lit = Array2::from_elem((1, 1), (83_400.0 / 112.0) as f32);
        let dark = Array2::zeros((1, 1));
        let none = Array2::zeros((1, 1));
        f.step(&exposure(0, 0.0, lit.clone(), none.clone()));
        f.step(&exposure(1, 1000.0, lit, none.clone()));
        let (_, cur) = f.step(&exposure(2, 3000.0, dark.clone(), none.clone()));
        let later = w.current_e_per_s(83_400.0, 3056.0 - 1112.0);
        assert!((f64::from(cur[(0, 0)]) - later).abs() <= 1e-6 * later);
        let (pf, cur) = f.step(&exposure(3, 1112.0 + w.lookback_s, dark, none));
        assert!(cur[(0, 0)] < 1e-5 && pf[(0, 0)] == 0, "{}", cur[(0, 0)]);
    }

    /// The stimulus: a `TRANSIENT` pixel's current, the largest neighbour's for a pixel
    /// without a value, none for a non-functional pixel.
    #[test]
    fn wfc3_stimulus_follows_wfc3s_rules() {
        let w = Wfc3Params::PUBLISHED;
        let mut f = Wfc3Flagger::new(w, 0.1, 0.01);
        let mut image = Array2::from_elem((3, 3), 100.0f32);
        let mut flags = Array2::<u32>::zeros((3, 3));
        image[(0, 0)] = 900.0;
        flags[(0, 0)] = bits::TRANSIENT;
        image[(1, 1)] = f32::NAN;
        flags[(1, 1)] = bits::SUR_ERROR | bits::OVERFLOW;
        image[(2, 2)] = f32::NAN;
        flags[(2, 2)] = bits::NONFUNC;
        f.step(&exposure(0, 0.0, image, flags.clone()));
        let (pf, cur) = f.step(&exposure(1, 1000.0, Array2::zeros((3, 3)), flags));
        let at = |x_e: f64| w.current_e_per_s(x_e, 1056.0 - 112.0) as f32;
        assert_eq!(cur[(0, 0)], at(900.0 * 112.0));
        assert_eq!(cur[(1, 1)], at(900.0 * 112.0));
        assert_eq!(cur[(0, 1)], at(100.0 * 112.0));
        assert_eq!((cur[(2, 2)], pf[(2, 2)]), (0.0, 0));
        assert_eq!(pf[(0, 0)], pbits::HIGH | pbits::LOW);
    }
}
