//! Flags against the simulator's truth: how often a model flags a pixel-exposure whose
//! true persistence current is below a threshold (over-flagged) and leaves one above it
//! unflagged (missed), by band of true current. Non-functional pixels are left out
//! (masked anyway). Used by `examples/pixel_map_validation` and the tests.

use crate::flags::{bits, pbits};
use crate::model::{Model, State};
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

/// One model stepped through a sky run next to the truth, tallied at its high and low
/// thresholds (`pflags` `HIGH` and `LOW`) from `t_skip_s` after the first exposure.
pub struct Tracker {
    pub model: Model,
    state: Option<State>,
    pub high: FlagTally,
    pub low: FlagTally,
    t_first: Option<f64>,
    pub t_skip_s: f64,
}

impl Tracker {
    pub fn new(model: Model, t_skip_s: f64) -> Tracker {
        let th = model.params().thresholds;
        Tracker {
            model,
            state: None,
            high: FlagTally::new(th.high_e_per_s),
            low: FlagTally::new(th.low_e_per_s),
            t_first: None,
            t_skip_s,
        }
    }

    /// Step one simulated exposure and tally it against its truth.
    pub fn step(&mut self, s: &crate::sim::SimExposure) -> crate::Result<()> {
        let e = &s.exposure;
        let (ny, nx) = e.image.dim();
        let st = self
            .state
            .get_or_insert_with(|| self.model.new_state(ny, nx));
        let mut cur = Array2::<f32>::zeros((ny, nx));
        let mut pf = Array2::<u8>::zeros((ny, nx));
        super::step_exposure(&self.model, st, e, None, &mut cur, &mut pf)?;
        let t0 = *self.t_first.get_or_insert(e.meta.t_start.0);
        if e.meta.t_start.0 - t0 >= self.t_skip_s {
            let hi = pf.mapv(|f| f & pbits::HIGH != 0);
            let lo = pf.mapv(|f| f & (pbits::LOW | pbits::HIGH) != 0);
            self.high.add(&hi, &s.true_persistence, &e.flags);
            self.low.add(&lo, &s.true_persistence, &e.flags);
        }
        Ok(())
    }
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

/// The measurement of docs/validation/pixel_map.md on one simulated detector: a
/// laboratory sequence ([`lab_campaign`]) gives the global model (`persist fit`'s
/// calibration) and the per-pixel map; a sky run of the same detector (same seed and
/// size: the same pixels) is flagged by the global model and by the model with the map
/// at each margin, against the truth.
#[derive(Debug, Clone)]
pub struct Experiment {
    pub size: usize,
    pub seed: u64,
    pub sky_exposures: u64,
    /// Tally from this long after the first sky exposure, s.
    pub t_skip_s: f64,
    pub margins: Vec<f64>,
    /// The sky's cosmic-ray rate, hits per cm^2 per s (`None`: the simulator's 5).
    pub cosmic_rate_per_cm2_s: Option<f64>,
}

/// What [`Experiment::run`] measured.
#[derive(Debug, Clone, serde::Serialize)]
pub struct ExperimentResult {
    /// Pixels with an observation per range.
    pub observed: [usize; 2],
    pub pixels: usize,
    /// The global model's tallies at (high, low).
    pub global: (FlagTally, FlagTally),
    /// Per margin, the map model's tallies at (high, low).
    pub with_map: Vec<(f64, FlagTally, FlagTally)>,
    /// Per range, the pixels' posterior mean ratio against their true population
    /// (simulator truth): mean ratio per population (low, mid, high) in the saturated
    /// range.
    pub saturated_ratio_by_population: Vec<(String, f64, usize)>,
}

/// The laboratory sequence of the measurement: the paper's pattern (every pixel lit,
/// `--spots paper`) at the calibration's illumination (481 s, 30 darks), then two flats
/// of the same pattern, 5 and 20 times brighter (481 s each, 10 darks): every pixel is
/// measured below full well (14,400 and 72,000 e-) and above it (289,000 e- and more).
pub fn lab_campaign() -> Vec<crate::sim::lab::Illumination> {
    let i = |scale: f64, darks: usize| crate::sim::lab::Illumination {
        t_illuminated_s: 481.0,
        flux_scale: scale,
        temp_k: 80.0,
        darks_after: darks,
        spot_offset: [0.0, 0.0],
        points: false,
        dark_s: None,
        after_shutter_s: None,
    };
    vec![i(1.0, 30), i(5.0, 10), i(20.0, 10)]
}

impl Experiment {
    pub fn run(&self) -> crate::Result<ExperimentResult> {
        use crate::sim::{lab, sky};
        let cfg = lab::LabConfig {
            size: self.size,
            seed: self.seed,
            campaign: Some(lab_campaign()),
            paper_pattern: Some(lab::PaperPattern { dark_pixels: false }),
            ..lab::LabConfig::default()
        };
        let mut exposures = Vec::new();
        lab::run(&cfg, |s| {
            exposures.push(s.exposure);
            Ok(())
        })?;
        let seq = crate::measure::data::Sequence::from_exposures(exposures)?;
        let (params, _) = crate::calib::calibrate(&seq, &crate::calib::CalibConfig::default())?;
        let map = super::build(&seq, &params, &super::MapConfig::default())?;
        drop(seq);
        let global = Model::new(params.clone())?;
        let mut trackers = vec![Tracker::new(global, self.t_skip_s)];
        for &m in &self.margins {
            let r =
                super::file::response(&map, m).map_err(|e| crate::Error::invalid("margin", e))?;
            let model = Model::new(params.clone())?
                .with_pixel_maps([(1u8, r)].into_iter().collect())
                .for_detector(1)?;
            trackers.push(Tracker::new(model, self.t_skip_s));
        }
        let mut sky_cfg = sky::SkyConfig {
            size: self.size,
            detectors: 1,
            exposures: self.sky_exposures,
            seed: self.seed,
            ..sky::SkyConfig::default()
        };
        if let Some(r) = self.cosmic_rate_per_cm2_s {
            sky_cfg.detector.cosmic_rate_per_cm2_s = r;
        }
        sky::run(&sky_cfg, |s| {
            for t in trackers.iter_mut() {
                t.step(&s)?;
            }
            Ok(())
        })?;
        // the map against the truth: the posterior mean in the saturated range per
        // population
        let truth = crate::sim::traps::draw_pixels(
            &cfg.traps,
            &cfg.detector,
            self.size,
            self.size,
            self.seed,
            1,
        );
        let mut by_pop = Vec::new();
        for (k, p) in cfg.traps.populations.iter().enumerate() {
            let v: Vec<f64> = truth
                .population
                .indexed_iter()
                .filter(|(_, q)| usize::from(**q) == k)
                .map(|((y, x), _)| f64::from(map.ratio[[1, y, x]]))
                .collect();
            let mean = v.iter().sum::<f64>() / v.len().max(1) as f64;
            by_pop.push((p.name.clone(), mean, v.len()));
        }
        let mut it = trackers.into_iter();
        let g = it.next().expect("the global model");
        Ok(ExperimentResult {
            observed: super::file::observed(&map),
            pixels: self.size * self.size,
            global: (g.high, g.low),
            with_map: self
                .margins
                .iter()
                .zip(it)
                .map(|(m, t)| (*m, t.high, t.low))
                .collect(),
            saturated_ratio_by_population: by_pop,
        })
    }
}
