//! Flags against the simulator's truth: how often a model flags a pixel-exposure whose
//! true persistence current is below a threshold (over-flagged) and leaves one above it
//! unflagged (missed), by band of true current. Non-functional pixels are left out
//! (masked anyway). Used by `examples/pixel_map_validation` and the tests.

pub use crate::flag_quality::{FlagTally, BANDS};
use crate::flags::pbits;
use crate::model::{Model, State};
use ndarray::Array2;

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

/// Darks after the first illumination of [`paper_lab_campaign`]: 280 of 180 s, 14 h, as
/// the paper's laboratory measured ("the subsequent integrations taken every three
/// minutes over the following fourteen hours", section 2.1).
pub const PAPER_DARKS_AFTER_FIRST: usize = 280;

/// [`lab_campaign`] with the paper's 14 h of darks after the first illumination
/// ([`PAPER_DARKS_AFTER_FIRST`]): the laboratory sequence `persist demo` and the
/// flag-quality page calibrate the flags on, whose coverage then reaches the times of
/// the decay's long terms (`persist::calib::coverage`, "The tail").
pub fn paper_lab_campaign() -> Vec<crate::sim::lab::Illumination> {
    let mut c = lab_campaign();
    c[0].darks_after = PAPER_DARKS_AFTER_FIRST;
    c
}

/// The laboratory half of the measurement: [`lab_campaign`] on the simulated detector
/// `(size, seed)`, the global model calibrated on it (`persist fit`'s calibration) and
/// the per-pixel map measured against that model.
pub fn lab_model_and_map(
    size: usize,
    seed: u64,
) -> crate::Result<(
    crate::sim::lab::LabConfig,
    crate::model::ModelParams,
    super::PixelMap,
)> {
    let (cfg, seq) = lab_sequence(size, seed, false)?;
    let (params, _) = crate::calib::calibrate(&seq, &crate::calib::CalibConfig::default())?;
    let map = super::build(&seq, &params, &super::MapConfig::default())?;
    Ok((cfg, params, map))
}

/// [`lab_campaign`] on the simulated detector `(size, seed)` (the paper's pattern, every
/// pixel lit, or with `dark_pixels` a corner of `size/8 x size/8` pixels kept unlit, whose
/// dark level and noise the measured currents are then taken against,
/// [`crate::measure::data`]): its configuration and the sequence.
pub fn lab_sequence(
    size: usize,
    seed: u64,
    dark_pixels: bool,
) -> crate::Result<(crate::sim::lab::LabConfig, crate::measure::data::Sequence)> {
    lab_sequence_of(size, seed, dark_pixels, lab_campaign())
}

/// [`lab_sequence`] of another campaign (e.g. [`paper_lab_campaign`]).
pub fn lab_sequence_of(
    size: usize,
    seed: u64,
    dark_pixels: bool,
    campaign: Vec<crate::sim::lab::Illumination>,
) -> crate::Result<(crate::sim::lab::LabConfig, crate::measure::data::Sequence)> {
    use crate::sim::lab;
    let cfg = lab::LabConfig {
        size,
        seed,
        campaign: Some(campaign),
        paper_pattern: Some(lab::PaperPattern { dark_pixels }),
        ..lab::LabConfig::default()
    };
    let mut exposures = Vec::new();
    lab::run(&cfg, |s| {
        exposures.push(s.exposure);
        Ok(())
    })?;
    let seq = crate::measure::data::Sequence::from_exposures(exposures)?;
    Ok((cfg, seq))
}

impl Experiment {
    pub fn run(&self) -> crate::Result<ExperimentResult> {
        use crate::sim::sky;
        let (cfg, params, map) = lab_model_and_map(self.size, self.seed)?;
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

/// The flight map's measurement (docs/validation/pixel_map.md, "Learned in flight"): one
/// simulated detector's laboratory sequence gives the global model and the laboratory
/// map ([`lab_model_and_map`]); its sky is flagged by the global model and followed by
/// `verify`'s tracker, whose samples a [`super::flight::FlightLearner`] accumulates; after
/// each of `learn_days` a flight map is built (alone, and starting from the laboratory
/// map). From the last learning day on, the global model, the laboratory map and every
/// flight map flag the next `eval_days` of sky (sky none of them learned from), each
/// started there, tallied from `t_skip_s` after that start against the truth.
#[derive(Debug, Clone)]
pub struct FlightExperiment {
    pub size: usize,
    pub seed: u64,
    /// Days of sky learned from, ascending.
    pub learn_days: Vec<f64>,
    pub eval_days: f64,
    pub t_skip_s: f64,
    /// The margin of every map model.
    pub margin: f64,
}

/// Mean ratio per true population: (name, mean, pixels).
pub type ByPopulation = Vec<(String, f64, usize)>;

/// One model of a [`FlightExperiment`].
#[derive(Debug, Clone, serde::Serialize)]
pub struct FlightRow {
    pub name: String,
    /// Pixels with a flight (or laboratory) observation in the saturated range.
    pub observed_pixels: usize,
    /// Flight observations used.
    pub observations: usize,
    pub high: FlagTally,
    pub low: FlagTally,
    /// Mean posterior ratio (saturated range) of the observed pixels per true population
    /// of the simulator: (name, mean, pixels).
    pub ratio_by_population: Vec<(String, f64, usize)>,
}

/// Every pixel's true population index, `[ny, nx]`.
pub fn true_populations(
    lab: &crate::sim::lab::LabConfig,
    size: usize,
    seed: u64,
) -> (Array2<u8>, Vec<String>) {
    let truth = crate::sim::traps::draw_pixels(&lab.traps, &lab.detector, size, size, seed, 1);
    let names = lab
        .traps
        .populations
        .iter()
        .map(|p| p.name.clone())
        .collect();
    (truth.population, names)
}

/// Mean of `map`'s saturated-range ratio per true population over the pixels it
/// observed.
pub fn ratio_by_population(
    map: &super::PixelMap,
    pop: &Array2<u8>,
    names: &[String],
) -> Vec<(String, f64, usize)> {
    names
        .iter()
        .enumerate()
        .map(|(k, name)| {
            let v: Vec<f64> = pop
                .indexed_iter()
                .filter(|((y, x), q)| usize::from(**q) == k && map.n_obs[[1, *y, *x]] > 0)
                .map(|((y, x), _)| f64::from(map.ratio[[1, y, x]]))
                .collect();
            (
                name.clone(),
                v.iter().sum::<f64>() / v.len().max(1) as f64,
                v.len(),
            )
        })
        .collect()
}

impl FlightExperiment {
    pub fn run(&self) -> crate::Result<Vec<FlightRow>> {
        use crate::sim::sky;
        use crate::verify::track::{Frame, TrackParams, Tracker as Follow};
        const DAY_S: f64 = 86_400.0;
        let (lab, params, lab_map) = lab_model_and_map(self.size, self.seed)?;
        let (pop, names) = true_populations(&lab, self.size, self.seed);
        let cfg = super::MapConfig::default();
        let last = self.learn_days.iter().copied().fold(0.0, f64::max);
        let mut sky_cfg = sky::SkyConfig {
            size: self.size,
            detectors: 1,
            seed: self.seed,
            ..sky::SkyConfig::default()
        };
        // 1143 exposures in the simulator's two days
        sky_cfg.exposures = ((last + self.eval_days) * 1143.0 / 2.0).ceil() as u64 + 1;
        let global = Model::new(params.clone())?;
        let mut state = global.new_state(self.size, self.size);
        let mut follow = Follow::new(TrackParams::default(), self.size, self.size);
        let mut learner = super::flight::FlightLearner::new(self.size, self.size, &cfg);
        let mut maps: Vec<(String, super::PixelMap, usize)> = Vec::new();
        let mut pending: Vec<f64> = self.learn_days.clone();
        let mut eval: Vec<(String, Tracker, usize, usize, ByPopulation)> = Vec::new();
        let mut t0 = None;
        let mut cur = Array2::<f32>::zeros((self.size, self.size));
        let mut pf = Array2::<u8>::zeros((self.size, self.size));
        let with_map = |map: &super::PixelMap| -> crate::Result<Model> {
            let r = super::file::response(map, self.margin)
                .map_err(|e| crate::Error::invalid("margin", e))?;
            Model::new(params.clone())?
                .with_pixel_maps([(1u8, r)].into_iter().collect())
                .for_detector(1)
        };
        sky::run(&sky_cfg, |s| {
            let e = &s.exposure;
            let t = e.meta.t_start.0 - *t0.get_or_insert(e.meta.t_start.0);
            while pending.first().is_some_and(|d| t >= d * DAY_S) {
                let d = pending.remove(0);
                let n = learner.observations();
                let src = format!("simulated sky, seed {}, first {d} days", self.seed);
                let m = learner.build(1, &params, &cfg, None, &format!("flight: {src}"))?;
                maps.push((format!("flight map, {d} days"), m, n));
                let m = learner.build(
                    1,
                    &params,
                    &cfg,
                    Some(&lab_map),
                    &format!("flight: {src}; prior: laboratory map"),
                )?;
                maps.push((format!("laboratory map + flight, {d} days"), m, n));
            }
            if t < last * DAY_S {
                super::step_exposure(&global, &mut state, e, None, &mut cur, &mut pf)?;
                let frame = Frame::of(e, cur.view(), pf.view(), None);
                for sample in follow.observe(&frame) {
                    learner.add(&sample);
                }
                return Ok(());
            }
            if eval.is_empty() {
                let obs = |m: &super::PixelMap| super::file::observed(m)[1];
                eval.push((
                    "global (95th percentile x 1.2)".into(),
                    Tracker::new(Model::new(params.clone())?, self.t_skip_s),
                    0,
                    0,
                    Vec::new(),
                ));
                eval.push((
                    "laboratory map".into(),
                    Tracker::new(with_map(&lab_map)?, self.t_skip_s),
                    obs(&lab_map),
                    0,
                    ratio_by_population(&lab_map, &pop, &names),
                ));
                for (name, m, n) in &maps {
                    eval.push((
                        name.clone(),
                        Tracker::new(with_map(m)?, self.t_skip_s),
                        obs(m),
                        *n,
                        ratio_by_population(m, &pop, &names),
                    ));
                }
            }
            for (_, tr, ..) in eval.iter_mut() {
                tr.step(&s)?;
            }
            Ok(())
        })?;
        Ok(eval
            .into_iter()
            .map(
                |(name, tr, observed_pixels, observations, ratio_by_population)| FlightRow {
                    name,
                    observed_pixels,
                    observations,
                    high: tr.high,
                    low: tr.low,
                    ratio_by_population,
                },
            )
            .collect())
    }
}
