//! The per-pixel map learned in flight: each pixel's own response measured on the sky by
//! `persist verify`'s tracks ([`crate::verify::track`]), accumulated into the same map
//! format as the laboratory map ([`super::PixelMap`], `schemas/pixel_map.schema.json`),
//! optionally starting from the laboratory map.
//!
//! # Observations
//! Every track sample whose predicted excess (the stage's prediction minus its annulus
//! median) stands at least [`MIN_FLIGHT_SNR`] noise standard deviations above zero gives
//! one observation of the pixel's ratio to the model, `x = (e - c) / p`, with
//! `sigma_x = sigma / p`: `e` the measured excess over the annulus, `c` the control
//! pixels' mean in the same exposure (what faint sources add), `p` the predicted excess,
//! `sigma` the annulus's noise. Only events at or above the map's `saturated_above_e` give
//! observations (range 1: the forward-biased traps whose populations the paper's Fig. 3b
//! shows); a sky event below full well is rare and mixes both kinds of traps.
//!
//! The model's decay is not the pixels' mean decay (it is an envelope), so `x` depends on
//! the time since the event and on the fluence. As the laboratory map divides each
//! observation by its fluence bin's median, each observation here is divided by the
//! median of its group: fluence bin ([`super::BINS_PER_DECADE`] per decade) and time bin
//! (four per decade), over all pixels (groups of fewer than [`super::MIN_PIXELS`]
//! observations give none). A pixel's observations combine by inverse variance, then the
//! shrinkage is the laboratory map's (`shrink` in [`super`]): a nonparametric prior fitted on
//! the observed pixels, each pixel's posterior, ratios relative to the prior's 95th
//! percentile.
//!
//! # Starting from the laboratory map
//! With a prior map (same detector and shape), each pixel's laboratory posterior
//! (`ratio`, `ratio_sigma`) is one more observation of its ratio, the flight
//! observations are first put on the laboratory scale (multiplied by the laboratory
//! ratio's median over the pixels seen in flight), and range 0 (below full well, which
//! the sky rarely measures) is the laboratory map's.
//!
//! The predictions must be the model's without a map (the model the map is measured
//! against: `model_identity`); a stage run with a map predicts each pixel's response
//! already scaled.
//!
//! Determinism: observations in sample order, sums in pixel order, no randomness.

use super::{base_identity, shrink, MapConfig, Obs, PixelMap, BINS_PER_DECADE, MIN_PIXELS};
use crate::error::{Error, Result};
use crate::model::ModelParams;
use crate::sim::analysis::median;
use crate::verify::track::Sample;
use std::collections::BTreeMap;

/// Smallest predicted excess, in noise standard deviations, for an observation.
pub const MIN_FLIGHT_SNR: f64 = 3.0;
/// Time bins per decade of the normalisation groups.
pub const TIME_BINS_PER_DECADE: f64 = 4.0;
/// Smallest standard deviation given to a laboratory posterior used as an observation
/// (a ratio measured to better than 2 % is not known to better than the model's own
/// misfit).
pub const PRIOR_SIGMA_FLOOR: f64 = 0.02;

/// Flight observations of one detector, accumulated sample by sample.
#[derive(Debug, Clone)]
pub struct FlightLearner {
    ny: usize,
    nx: usize,
    saturated_above_e: f64,
    /// (pixel, group, x, sigma_x)
    raw: Vec<(u32, (i32, i32), f32, f32)>,
    /// Samples offered and samples kept as observations.
    pub offered: u64,
}

impl FlightLearner {
    pub fn new(ny: usize, nx: usize, cfg: &MapConfig) -> FlightLearner {
        FlightLearner {
            ny,
            nx,
            saturated_above_e: cfg.saturated_above_e,
            raw: Vec::new(),
            offered: 0,
        }
    }

    /// Observations kept so far.
    pub fn observations(&self) -> usize {
        self.raw.len()
    }

    /// Offer one track sample (module docs: which give an observation).
    pub fn add(&mut self, s: &Sample) {
        self.offered += 1;
        let p = s.predicted_excess_e_per_s;
        let e = s.excess_e_per_s - s.control_e_per_s;
        let sigma = s.sigma_e_per_s;
        if s.y >= self.ny
            || s.x >= self.nx
            || s.event_fluence_e < self.saturated_above_e
            || !(sigma > 0.0 && p > MIN_FLIGHT_SNR * sigma && e.is_finite())
        {
            return;
        }
        let group = (
            (BINS_PER_DECADE * s.event_fluence_e.log10()).floor() as i32,
            (TIME_BINS_PER_DECADE * s.time_s.max(1.0).log10()).floor() as i32,
        );
        self.raw.push((
            (s.y * self.nx + s.x) as u32,
            group,
            (e / p) as f32,
            (sigma / p) as f32,
        ));
    }

    /// The map of these observations for the model `params` (without a map), optionally
    /// starting from the laboratory map `prior`; `source` is recorded as its provenance.
    pub fn build(
        &self,
        detector: u8,
        params: &ModelParams,
        cfg: &MapConfig,
        prior: Option<&PixelMap>,
        source: &str,
    ) -> Result<PixelMap> {
        let (ny, nx) = (self.ny, self.nx);
        let identity = base_identity(params);
        if let Some(p) = prior {
            if p.ratio.dim() != (2, ny, nx) {
                return Err(Error::invalid(
                    "ratio",
                    format!(
                        "the prior map is {:?}, the flight data {ny} x {nx}",
                        p.ratio.dim()
                    ),
                ));
            }
            if p.detector != detector {
                return Err(Error::invalid(
                    "detector",
                    format!(
                        "the prior map is detector {}, the flight data {detector}",
                        p.detector
                    ),
                ));
            }
            if p.model_identity != identity {
                return Err(Error::invalid(
                    "model_identity",
                    "the prior map was measured against another model",
                ));
            }
        }
        let mut by_group: BTreeMap<(i32, i32), Vec<f64>> = BTreeMap::new();
        for r in &self.raw {
            by_group.entry(r.1).or_default().push(f64::from(r.2));
        }
        let medians: BTreeMap<(i32, i32), f64> = by_group
            .into_iter()
            .filter(|(_, v)| v.len() >= MIN_PIXELS)
            .map(|(g, v)| (g, median(&v)))
            .filter(|(_, m)| m.is_finite() && *m > 0.0)
            .collect();
        let mut obs = vec![[Obs::default(); 2]; ny * nx];
        for &(i, g, x, sx) in &self.raw {
            let Some(m) = medians.get(&g) else { continue };
            let (x, sx) = (f64::from(x) / m, f64::from(sx) / m);
            let o = &mut obs[i as usize][1];
            let w = 1.0 / (sx * sx);
            o.sum_wx += w * x;
            o.sum_w += w;
            o.n = o.n.saturating_add(1);
        }
        if let Some(p) = prior {
            // the flight observations on the laboratory scale
            let seen: Vec<f64> = obs
                .iter()
                .enumerate()
                .filter(|(_, o)| o[1].n > 0)
                .map(|(i, _)| f64::from(p.ratio[[1, i / nx, i % nx]]))
                .collect();
            let c = if seen.is_empty() { 1.0 } else { median(&seen) };
            let c = if c.is_finite() && c > 0.0 { c } else { 1.0 };
            for o in obs.iter_mut().filter(|o| o[1].n > 0) {
                // x -> c x and sigma -> c sigma: w x -> (w / c^2) c x
                o[1].sum_wx /= c;
                o[1].sum_w /= c * c;
            }
            for (i, o) in obs.iter_mut().enumerate() {
                let (y, x) = (i / nx, i % nx);
                for (r, or) in o.iter_mut().enumerate() {
                    if !p.range_measured[r] || p.n_obs[[r, y, x]] == 0 {
                        continue;
                    }
                    let v = f64::from(p.ratio[[r, y, x]]);
                    let s = f64::from(p.ratio_sigma[[r, y, x]]).max(PRIOR_SIGMA_FLOOR);
                    or.sum_wx += v / (s * s);
                    or.sum_w += 1.0 / (s * s);
                    or.n = or.n.saturating_add(1);
                }
            }
        }
        Ok(shrink(&obs, ny, nx, cfg).into_map(detector, identity, cfg, source.to_string()))
    }
}

/// `persist verify --flight-map OUT --map-model MODEL [--prior-map LAB]`: run the
/// verification ([`crate::verify::run_observing`]) and learn the first detector's flight
/// map from its samples, written to `out` with its provenance (`source`: the input and
/// output directories, the prior map).
pub fn learn_and_write(
    input: &std::path::Path,
    output: &std::path::Path,
    params: &crate::verify::VerifyParams,
    out: &std::path::Path,
    model: Option<&std::path::Path>,
    prior: Option<&std::path::Path>,
) -> Result<crate::verify::Report> {
    let Some(model) = model else {
        return Err(Error::new(
            crate::error::ErrorKind::Usage,
            "--flight-map needs --map-model (the model the stage ran with, without a map)",
        ));
    };
    let mparams = crate::model_file::load(model)?;
    let prior = prior.map(super::file::read).transpose()?;
    let cfg = prior
        .as_ref()
        .map_or_else(MapConfig::default, |p| p.config.clone());
    // the first product gives the detector and its shape
    let first = crate::stage::queue::candidates(output)?
        .into_iter()
        .next()
        .ok_or_else(|| {
            Error::invalid("products", "no product in the stage's output").path(output)
        })?;
    let (e, _, _) = crate::product::read::read_output(&first)?;
    let (det, (ny, nx)) = (e.meta.detector.0, e.image.dim());
    let mut learner = FlightLearner::new(ny, nx, &cfg);
    let report = crate::verify::run_observing(input, output, params, &mut |d, s| {
        if d == det {
            learner.add(s);
        }
    })?;
    let source = format!(
        "flight: verify of {} (stage output {}), {} observations{}",
        input.display(),
        output.display(),
        learner.observations(),
        if prior.is_some() {
            "; prior: a laboratory map"
        } else {
            ""
        }
    );
    let map = learner
        .build(det, &mparams, &cfg, prior.as_ref(), &source)
        .map_err(|e| e.path(out))?;
    if let Some(d) = out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(d).map_err(|e| Error::io(d, e))?;
    }
    super::file::write(out, &map)?;
    Ok(report)
}
