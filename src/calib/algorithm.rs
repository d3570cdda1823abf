//! `persist fit`: the paper's calibration from a laboratory sequence (section 2.3 and
//! "Model Parameters and Validation"), then, with `--with`, the effects' parameters.
//!
//! 1. Extrapolated fluence of the (first) illuminated exposure, `image * t_illuminated`,
//!    in log-spaced bins (`bins_per_decade`, default 20; bins with fewer than
//!    `min_pixels` usable pixels are skipped). Pixels dominated by a far brighter
//!    neighbour ([`crate::measure::data::neighbour_dominated`]: below saturation, next to
//!    neighbours whose mean fluence above saturation exceeds their own) are left out
//!    (the report's `neighbour_dominated_left_out`): the paper's `A_k` is a pixel's
//!    response to its own fluence, and what couples neighbours (blooming, inter-pixel
//!    capacitance) would otherwise raise the 95th percentile of the dim bins, which the
//!    model's spatial effects then cannot take back (docs/validation/diagnose_matrix.md).
//!    A smooth illumination has no such pixel; one-pixel pinholes have four each. With
//!    spatial effects in the model ([`calibrate_with`]), so are the pixels whose fluence
//!    hooks leave them less than half their measured fluence
//!    ([`knots::spatial_factor`], [`knots::OWN_SHARE_MIN`]), at any fluence.
//! 2. Per bin, the measured current of the first dark integration (image minus the
//!    dark level, [`dark`]: the background pixels' ([`crate::measure::data`]) when at
//!    least `min_pixels` pixels stayed below 3000 e-, else, when every pixel was lit as
//!    in the paper's laboratory data, each pixel's own late darks with its predicted
//!    persistence there removed; the report's `dark_level` and the model file's
//!    `calibration.late_plateau_dark` say which): its 3-sigma-clipped median and its 95th
//!    percentile ([`crate::measure::data::signal_p95`], read noise removed in quadrature;
//!    with `--cell-statistic population` also the shot noise of the bin's median
//!    current, [`crate::measure::data::shot_noise_added`]: that statistic's reference adds
//!    each sample's shot noise to the prediction, which must then be the noise-free 95th
//!    percentile; the model file records it, `calibration.knots_shot_noise_removed`).
//! 3. Per bin, the clipped median of the first dark ramp (dark ramp subtracted:
//!    per read, the background pixels' median, or with `--background line` their
//!    line's intercept at zero fluence, [`crate::measure::data`] "Background"; with the
//!    late plateau each pixel's dark level times the read's time since the reset)
//!    fitted with Eq. (logfit) `q(t) = A_0 ln(t + tau) + q_0` ([`logfit`]).
//! 4. `A_bin = amplification * A_0` (paper: 1.2) and, through the 95th percentile,
//!    `A_95 = A_bin * p95 / median`; the piecewise-linear `A_k` has one knot per bin
//!    whose median is significant (> 3 standard errors), at the bin's mean fluence.
//! 5. `C_n` for the chosen rates `1/tau_n` (default: the paper's) by linear least
//!    squares of the relative error `sum_n C_n exp(-t/tau_n) (t + 1) - 1` at 400
//!    log-spaced times from `t_min_s` (the shortest slew, default 10 s) to the time the
//!    largest knot amplitude crosses the low threshold under Eq. (invT) with `tau = 1`
//!    (`A_max / (t + 1) = low`); negative `C_n` are dropped (set to 0) and the rest
//!    refitted.
//!
//! # Decay offset
//! The `1` of `1/(t + 1)` is the paper's choice: the decay's origin 1 s before the
//! reset. `--decay-offset-s T0` ([`CalibConfig::decay_offset_s`]) fits the `C_n` to
//! `1/(t + T0)` instead (and the span's end to `A_max / (t + T0) = low`); the default,
//! 1, is the paper's. Why: Eq. (logfit)'s own `tau`, fitted per bin on the first dark
//! ramp, is the data's offset; on the simulator's laboratory campaign it is 0.05-0.3 s
//! above saturation (64 x 64, seed 1; the report's `bins[].logfit.tau_s`). With `1/(t+1)`
//! the model's current over the first dark's reads (1.5 s to 180 s after the reset) is
//! 11 % below a `1/t` decay's, which a readout effect measured over those reads
//! ([`crate::model::effects::chord`], `first_read_s`) then shows as a first-dark
//! deficit (docs/validation/diagnose_matrix.md).

use super::{dark, knots, logfit, readout};
use crate::error::{Error, Result};
use crate::measure::data::{
    fluence, neighbour_dominated, quantile, shot_noise_added, signal_p95, Sequence,
    BACKGROUND_FLUENCE_E,
};
use crate::model::params::{Calibration, Knot, ModelParams, ReleaseKeep, Term, PAPER_TERMS};
use crate::sim::analysis::clipped_median;
use logfit::LogFit;
use nalgebra::{DMatrix, DVector};
use serde::Serialize;

#[derive(Debug, Clone, Serialize)]
pub struct CalibConfig {
    pub amplification: f64,
    pub bins_per_decade: f64,
    pub min_pixels: usize,
    pub t_min_s: f64,
    /// The `C_n` follow `1/(t + decay_offset_s)` (the paper: 1 s; `persist fit
    /// --decay-offset-s`, module docs "Decay offset").
    pub decay_offset_s: f64,
    /// Decay rates `1/tau_n` of the terms, 1/s.
    pub rates_per_s: Vec<f64>,
    /// Residual cells of the effect fit and of the report ([`crate::measure::eval::Cells`]).
    pub cells: crate::measure::eval::Cells,
    /// What those cells compare ([`crate::measure::eval::CellStatistic`]).
    pub cell_statistic: crate::measure::eval::CellStatistic,
    /// How each exposure's background is measured, in the calibration too
    /// ([`crate::measure::data::Background`]).
    pub background: crate::measure::data::Background,
    /// Calibrate the flags to this coverage after the effects ([`super::coverage`]): the
    /// paper preset's default is the paper's 95 %, a flagging model; none for the
    /// readout preset, a reference compared with measurements, whose knots stay at the
    /// measured level (`persist fit --coverage`, `--no-coverage`).
    pub coverage: Option<f64>,
}

impl CalibConfig {
    /// The model file's record of this configuration (nothing freed after it yet).
    pub fn record(&self) -> Calibration {
        Calibration {
            amplification: self.amplification,
            t_min_s: self.t_min_s,
            decay_offset_s: self.decay_offset_s,
            rates_per_s: self.rates_per_s.clone(),
            fit_cn: false,
            fit_amplification: false,
            decay_exponent: None,
            knots_shot_noise_removed: self.knots_shot_noise_removed(),
            late_plateau_dark: false,
            coverage: self.coverage,
        }
    }

    /// Whether the knots' 95th percentiles leave out the pixels' own shot noise: with the
    /// `population` cell statistic, whose reference adds each sample's shot noise to a
    /// noise-free predicted 95th percentile (module docs, step 2).
    pub fn knots_shot_noise_removed(&self) -> bool {
        self.cell_statistic == crate::measure::eval::CellStatistic::Population
    }

    /// The samples of the effect fit and of the report: every second pixel, grouped and
    /// compared as this configuration says.
    pub fn samples(&self, seq: &Sequence) -> crate::measure::eval::Samples {
        crate::measure::eval::Samples::new(seq, 2)
            .with_cells(self.cells)
            .with_statistic(self.cell_statistic)
    }
}

impl Default for CalibConfig {
    fn default() -> Self {
        CalibConfig {
            amplification: 1.2,
            bins_per_decade: 20.0,
            min_pixels: 20,
            t_min_s: 10.0,
            decay_offset_s: 1.0,
            rates_per_s: PAPER_TERMS.iter().map(|t| t.1).collect(),
            cells: crate::measure::eval::Cells::default(),
            cell_statistic: crate::measure::eval::CellStatistic::default(),
            background: crate::measure::data::Background::default(),
            coverage: Some(super::coverage::CoverageConfig::default().coverage),
        }
    }
}

/// What a caller states on top of a [`Preset`] (`persist fit`'s options): a `None` or an
/// empty list takes the preset's value ([`Preset::config_stated`]).
///
/// The coverage rule: a stated amplification, or a fitted one (`fit_amplification`), is
/// the knots' margin, so the preset's coverage calibration, which would set that margin
/// again, is not applied unless a coverage is stated too; `no_coverage` applies none.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Stated {
    pub amplification: Option<f64>,
    pub t_min_s: Option<f64>,
    pub decay_offset_s: Option<f64>,
    /// Decay rates `1/tau_n`, 1/s; empty: the preset's.
    pub rates_per_s: Vec<f64>,
    pub coverage: Option<f64>,
    pub no_coverage: bool,
    /// The knots' common factor is fitted (`--fit-amplification`).
    pub fit_amplification: bool,
}

impl Stated {
    /// The coverage to calibrate to, given the preset's `preset` (the coverage rule of
    /// the type's docs).
    pub fn coverage_over(&self, preset: Option<f64>) -> Option<f64> {
        let margin_stated = self.amplification.is_some() || self.fit_amplification;
        if self.no_coverage || (self.coverage.is_none() && margin_stated) {
            None
        } else {
            self.coverage.or(preset)
        }
    }
}

/// A named starting point of `persist fit` (`--preset`): a calibration configuration
/// and the effects fitted with it.
///
/// - [`Preset::Paper`] (the default): the paper's calibration
///   (amplification 1.2, the six rates of Eq. (bbdetexpsum), `C_n` to `1/(t + 1)` from
///   10 s), for flagging: the 1.2 is a margin. With it, for flagging too, the effect
///   `refill` fitted (a trap holds what an earlier illumination left and does not fill
///   twice) and early release keeping the threshold ([`Preset::release_keep`]):
///   together, on the simulated detector of the demo and a second seed, the misses at
///   0.01 e-/s fall from 37 % to 1-4 % and the over-flagging at both thresholds does
///   not rise (docs/validation/flag_quality.md); either alone does worse (`refill`
///   alone misses as many; the threshold kept without `refill` doubles the
///   over-flagging at 0.01 e-/s). `--with refill:beta=0 --release-keep zero` is the
///   paper's sum and release.
/// - [`Preset::Readout`]: the reference against which the hidden-effect matrix is
///   measured (the readout reference), for comparing a model
///   with measurements: the knots at the measured level (amplification 1.0; the paper's
///   margin would otherwise be a residual that an effect takes in), thirteen rates 0.4
///   decade apart from 1/s (`10^(-0.4 k)`, k = 0..12), the `C_n` fitted to
///   `1/(t + 0.2 s)` from 1 s (Eq. (logfit)'s own offset on the simulator's campaign,
///   module docs "Decay offset"), and the effects `refill` (fitted) and `chord` held at
///   strength 1 from the first read 1.5 s after the reset (the SPHEREx readout: the
///   on-board slope is the chord between the first and last sample used).
///
/// `persist diagnose` recognises a model calibrated with a preset's options and names
/// the preset in the `fit` command it suggests.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Preset {
    #[default]
    Paper,
    Readout,
}

impl Preset {
    pub const ALL: [Preset; 2] = [Preset::Paper, Preset::Readout];

    pub fn name(self) -> &'static str {
        match self {
            Preset::Paper => "paper",
            Preset::Readout => "readout",
        }
    }

    /// The calibration options (the residual cells stay the library's defaults).
    pub fn config(self) -> CalibConfig {
        match self {
            Preset::Paper => CalibConfig::default(),
            Preset::Readout => CalibConfig {
                amplification: 1.0,
                t_min_s: 1.0,
                decay_offset_s: 0.2,
                rates_per_s: (0..13).map(|k| 10f64.powf(-0.4 * f64::from(k))).collect(),
                coverage: None,
                ..CalibConfig::default()
            },
        }
    }

    /// The preset's configuration with the options a caller states (`persist fit`'s)
    /// in place of its own ([`Stated`]); the residual cells stay the library's defaults.
    pub fn config_stated(self, s: &Stated) -> CalibConfig {
        let p = self.config();
        CalibConfig {
            amplification: s.amplification.unwrap_or(p.amplification),
            t_min_s: s.t_min_s.unwrap_or(p.t_min_s),
            decay_offset_s: s.decay_offset_s.unwrap_or(p.decay_offset_s),
            rates_per_s: if s.rates_per_s.is_empty() {
                p.rates_per_s.clone()
            } else {
                s.rates_per_s.clone()
            },
            coverage: s.coverage_over(p.coverage),
            ..p
        }
    }

    /// The effects fitted with it, each as `persist fit --with` takes it.
    pub fn effects(self) -> &'static [&'static str] {
        match self {
            Preset::Paper => &["refill"],
            Preset::Readout => &["refill", "chord:strength=1,first_read_s=1.5"],
        }
    }

    /// What early release leaves of a released pixel in the models it writes: the
    /// flagging preset keeps the threshold (the type's docs), the readout reference the
    /// paper's zero (it is compared with measurements, not flagged with).
    pub fn release_keep(self) -> ReleaseKeep {
        match self {
            Preset::Paper => ReleaseKeep::Threshold,
            Preset::Readout => ReleaseKeep::Zero,
        }
    }

    /// The preset's effects, then `with`; an entry of `with` naming an effect the
    /// preset has replaces the preset's (`--with chord:strength=0.9` holds another
    /// strength).
    pub fn with(self, with: &[String]) -> Vec<String> {
        let own: Vec<String> = self.effects().iter().map(|e| e.to_string()).collect();
        merge_with(&own, with)
    }

    /// [`Preset::with`] for the sequence `seq`: the readout preset's on-board slope as
    /// `seq`'s first dark shows it ([`readout`]; its [`Preset::effects`] when the first
    /// dark cannot tell), and that measurement.
    pub fn with_for(
        self,
        seq: &Sequence,
        with: &[String],
    ) -> (Vec<String>, Option<readout::Readout>) {
        let measured = match self {
            Preset::Paper => None,
            Preset::Readout => knots::CalibRamp::of(seq)
                .ok()
                .and_then(|r| readout::measure(seq, &r)),
        };
        let Some(r) = measured else {
            return (self.with(with), None);
        };
        let own: Vec<String> = self
            .effects()
            .iter()
            .filter(|e| !e.starts_with("chord"))
            .map(|e| e.to_string())
            .chain(r.with_args())
            .collect();
        (merge_with(&own, with), Some(r))
    }

    /// True if calibration record `c` has this preset's options (before anything was
    /// freed after it).
    pub fn matches(self, c: &Calibration) -> bool {
        // (the knots' noise follows the cell statistic, not the preset; the coverage is
        // an option of its own)
        let before_freeing = Calibration {
            fit_cn: false,
            fit_amplification: false,
            decay_exponent: None,
            knots_shot_noise_removed: false,
            late_plateau_dark: false,
            coverage: None,
            ..c.clone()
        };
        before_freeing
            == Calibration {
                coverage: None,
                ..self.config().record()
            }
    }
}

/// `own`, less the effects `with` names, then `with`.
fn merge_with(own: &[String], with: &[String]) -> Vec<String> {
    let name = |s: &str| s.split(':').next().unwrap_or(s).trim().to_string();
    let given: Vec<String> = with.iter().map(|w| name(w)).collect();
    own.iter()
        .filter(|e| !given.contains(&name(e)))
        .cloned()
        .chain(with.iter().cloned())
        .collect()
}

impl std::fmt::Display for Preset {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for Preset {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        Preset::ALL
            .into_iter()
            .find(|p| p.name() == s)
            .ok_or_else(|| {
                let words = Preset::ALL.map(Preset::name);
                Error::invalid(
                    "--preset",
                    format!("`{s}`: expected {}", crate::choice::one_of(&words)),
                )
            })
    }
}

#[derive(Debug, Clone, Serialize)]
pub struct BinResult {
    pub fluence_lo_e: f64,
    pub fluence_hi_e: f64,
    pub fluence_mean_e: f64,
    pub pixels: usize,
    pub median_e_per_s: f64,
    pub sd_e_per_s: f64,
    pub p95_e_per_s: f64,
    pub logfit: Option<LogFit>,
    pub a_bin_e: Option<f64>,
    pub a_95_e: Option<f64>,
    /// Used as a knot of `A_k`.
    pub knot: bool,
}

#[derive(Debug, Clone, Serialize)]
pub struct CnFit {
    pub t_min_s: f64,
    pub t_max_s: f64,
    /// The offset `t_0` of the target `(t + t_0)^-p` (the paper: 1 s).
    pub offset_s: f64,
    /// The exponent `p` of that target (the paper: 1; [`super::exponent`]).
    pub exponent: f64,
    pub terms: Vec<Term>,
    /// Largest and RMS `|sum_n C_n e^{-t/tau_n} (t + t_0)^p - 1|` over the span.
    pub max_relative_error: f64,
    pub rms_relative_error: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct CalibReport {
    pub config: CalibConfig,
    pub illumination_exposure_index: u64,
    pub first_dark_exposure_index: u64,
    /// The first dark's dark level (with the late plateau, the median of the pixels'),
    /// e-/s, and its noise, e-/s.
    pub background_e_per_s: f64,
    pub noise_e_per_s: f64,
    /// Where the dark level came from ([`dark`]).
    pub dark_level: dark::DarkReport,
    /// Pixels left out of the fluence bins as neighbour-dominated (module docs, step 1).
    pub neighbour_dominated_left_out: usize,
    pub bins: Vec<BinResult>,
    pub knots: Vec<Knot>,
    pub c_n: CnFit,
}

/// Steps 1-5 of the module docs on the first illumination of `seq`.
pub fn calibrate(seq: &Sequence, cfg: &CalibConfig) -> Result<(ModelParams, CalibReport)> {
    calibrate_with(seq, cfg, None)
}

/// [`calibrate`], each pixel's first-dark current and ramp divided by its spatial
/// factor `w` ([`knots::spatial_factor`]) when one is given.
pub fn calibrate_with(
    seq: &Sequence,
    cfg: &CalibConfig,
    w: Option<&ndarray::Array2<f64>>,
) -> Result<(ModelParams, CalibReport)> {
    if !(cfg.amplification.is_finite() && cfg.amplification > 0.0) {
        return Err(Error::invalid("--amplification", "must be finite and > 0"));
    }
    let cr = knots::CalibRamp::of(seq)?;
    let (i0, d) = (cr.illumination, cr.dark);
    let f = fluence(&seq.exposures[i0]);
    if !f
        .iter()
        .any(|v| v.is_finite() && *v >= BACKGROUND_FLUENCE_E)
    {
        return Err(Error::invalid(
            "image",
            format!(
                "exposure {}: no pixel has an extrapolated fluence of {BACKGROUND_FLUENCE_E} e- \
                 or more (image times t_illuminated_s = {} s): nothing was lit, so there is no \
                 persistence to calibrate; an illumination reaching at least 1e4 e- over a few \
                 hundred pixels is needed",
                seq.exposures[i0].meta.exposure_index, cr.t_illuminated_s
            ),
        ));
    }
    let meas = seq.measured(d);
    // the background pixels of the first dark
    let bg_px: Vec<(usize, usize)> = f
        .indexed_iter()
        .filter(|(p, v)| **v < BACKGROUND_FLUENCE_E && meas[*p].is_finite())
        .map(|(p, _)| p)
        .collect();
    let late = if bg_px.len() >= cfg.min_pixels.max(1) {
        None
    } else {
        Some(dark::LatePlateau::of(seq, i0, d)?)
    };
    // bins
    let fmax = f
        .iter()
        .copied()
        .filter(|v| v.is_finite())
        .fold(0.0, f64::max);
    let lo_exp = 3.0;
    let n_bins = (((fmax.max(1e4)).log10() - lo_exp) * cfg.bins_per_decade).ceil() as usize + 1;
    let mut members: Vec<Vec<(usize, usize)>> = vec![Vec::new(); n_bins];
    let dominated = neighbour_dominated(&f);
    let usable = |p: (usize, usize)| match &late {
        None => meas[p].is_finite(),
        Some(l) => l.first[p].is_finite() && l.plateau[p].is_finite(),
    };
    let mut left_out = 0;
    for ((y, x), v) in f.indexed_iter() {
        if !(v.is_finite() && *v > 0.0 && usable((y, x))) {
            continue;
        }
        // left out as neighbour-dominated: by the measured fluences, or by the model's
        // fluence hooks (NaN in `w`, knots::spatial_factor)
        if dominated[(y, x)] || w.is_some_and(|w| w[(y, x)].is_nan()) {
            left_out += 1;
            continue;
        }
        let b = ((v.log10() - lo_exp) * cfg.bins_per_decade).floor();
        if b >= 0.0 && (b as usize) < n_bins {
            members[b as usize].push((y, x));
        }
    }
    let (bins, dark_report) = match &late {
        None => {
            let noise = seq.noise_e_per_s[d];
            let bins: Vec<BinResult> = bin_results(
                seq,
                cfg,
                &cr,
                &f,
                &members,
                &BinDark::Background(&bg_px),
                (noise, w),
            )
            .into_iter()
            .map(|b| b.1)
            .collect();
            let rep = dark::DarkReport {
                source: dark::DarkSource::BackgroundPixels,
                late_exposures: Vec::new(),
                late_t_s: None,
                late_fraction_max: None,
                median_e_per_s: seq.background_e_per_s[d],
                noise_e_per_s: noise,
            };
            (bins, rep)
        }
        Some(l) => {
            // module docs of `dark`, "Bias": a first pass with r = 0, then each bin's r
            // from its fitted tau
            let mut r = vec![0.0; n_bins];
            let mut bins = Vec::new();
            for _ in 0..dark::PLATEAU_PASSES {
                bins = bin_results(
                    seq,
                    cfg,
                    &cr,
                    &f,
                    &members,
                    &BinDark::Late(l, &r),
                    (l.noise_e_per_s, w),
                );
                r.iter_mut().for_each(|v| *v = 0.0);
                for (b, res) in &bins {
                    // a bin whose ramp has no fitted decay keeps the plain plateau
                    if let Some(lf) = res
                        .logfit
                        .filter(|lf| !lf.undetermined && lf.a0_e > 0.0 && lf.tau_s.is_finite())
                    {
                        // a tau beyond the first read is not a decay the ramp measured; one
                        // at or below zero (the fit's lower bound) is not measured either:
                        // the calibration's own decay offset (the paper's 1 s) stands in
                        let tau = if lf.tau_s > 0.0 {
                            lf.tau_s.min(cr.t_reset_s)
                        } else {
                            cfg.decay_offset_s
                        };
                        r[*b] = l.late_fraction(tau);
                    }
                }
            }
            let bins: Vec<BinResult> = bins.into_iter().map(|b| b.1).collect();
            let r_max = r.iter().copied().fold(0.0, f64::max);
            let fitted: Vec<f64> = r.iter().copied().filter(|v| *v > 0.0).collect();
            let r_typical = crate::stats::median(&fitted);
            if r_typical > dark::MAX_LATE_FRACTION {
                let t_end = l.spans_s.last().map_or(0.0, |s| s.1);
                return Err(Error::invalid(
                    "image",
                    format!(
                        "no background pixel, and the darks after exposure {} end {t_end:.0} s \
                         after the illumination, where persistence is still {:.0} % of the first \
                         dark's (at most {:.0} % for the dark level to come from the pixels' late \
                         darks; `persist::calib::dark`): add darks up to about {:.0} s after the \
                         illumination, or pixels masked from the source",
                        seq.exposures[d].meta.exposure_index,
                        100.0 * r_typical,
                        100.0 * dark::MAX_LATE_FRACTION,
                        t_end * r_typical / dark::MAX_LATE_FRACTION * 1.5,
                    ),
                ));
            }
            let levels: Vec<f64> = members
                .iter()
                .zip(&r)
                .flat_map(|(px, &rb)| px.iter().map(move |&p| l.dark_at(p, rb)))
                .collect();
            let rep = dark::DarkReport {
                source: dark::DarkSource::LatePlateau,
                late_exposures: l.exposure_indices(seq),
                late_t_s: Some([
                    l.spans_s.first().map_or(f64::NAN, |s| 0.5 * (s.0 + s.1)),
                    l.spans_s.last().map_or(f64::NAN, |s| 0.5 * (s.0 + s.1)),
                ]),
                late_fraction_max: Some(r_max),
                median_e_per_s: crate::stats::median(&levels),
                noise_e_per_s: l.noise_e_per_s,
            };
            (bins, rep)
        }
    };
    let knots: Vec<Knot> = bins
        .iter()
        .filter(|b| b.knot)
        .map(|b| Knot {
            fluence_e: b.fluence_mean_e,
            amplitude_e: b.a_95_e.unwrap_or(0.0),
        })
        .collect();
    if knots.is_empty() {
        return Err(Error::invalid(
            "image",
            format!(
                "exposure {}: no fluence bin has a significant first-dark current (median \
                 above 3 standard errors and a rising ramp) after the dark level ({}) is \
                 removed: nothing to calibrate; {} bins of at least {} pixels were tried",
                seq.exposures[d].meta.exposure_index,
                match dark_report.source {
                    dark::DarkSource::BackgroundPixels => "background pixels",
                    dark::DarkSource::LatePlateau => "the pixels' late darks",
                },
                bins.len(),
                cfg.min_pixels
            ),
        ));
    }
    let base = ModelParams::default();
    let (t_min, t_max) = cn_span_s(
        &knots,
        base.thresholds.low_e_per_s,
        cfg.t_min_s,
        cfg.decay_offset_s,
    );
    let c_n = fit_cn(&cfg.rates_per_s, t_min, t_max, cfg.decay_offset_s)?;
    let target = if cfg.decay_offset_s == 1.0 {
        String::new()
    } else {
        format!(" to 1/(t + {} s)", cfg.decay_offset_s)
    };
    let params = ModelParams {
        name: "fit".into(),
        description: format!(
            "persist fit: paper calibration (A_bin = {} A_0, A_k through the 95th percentile, \
             C_n fitted{target} from {:.0} s to {:.0} s)",
            cfg.amplification, c_n.t_min_s, c_n.t_max_s
        ),
        terms: c_n.terms.clone(),
        amplitude_knots: knots.clone(),
        calibration: Some(Calibration {
            late_plateau_dark: !dark_report.source.is_background_pixels(),
            // set by `persist fit` when the coverage is reached (`super::command`)
            coverage: None,
            ..cfg.record()
        }),
        ..base
    };
    params.validate().map_err(|m| Error::invalid("model", m))?;
    Ok((
        params,
        CalibReport {
            config: cfg.clone(),
            illumination_exposure_index: seq.exposures[i0].meta.exposure_index,
            first_dark_exposure_index: seq.exposures[d].meta.exposure_index,
            background_e_per_s: dark_report.median_e_per_s,
            noise_e_per_s: dark_report.noise_e_per_s,
            dark_level: dark_report,
            neighbour_dominated_left_out: left_out,
            bins,
            knots,
            c_n,
        },
    ))
}

/// The span of step 5 (module docs): from `t_min_s` to the time the largest knot
/// amplitude crosses `low_e_per_s` under `1/(t + offset_s)`, at least `10 t_min_s`.
pub fn cn_span_s(knots: &[Knot], low_e_per_s: f64, t_min_s: f64, offset_s: f64) -> (f64, f64) {
    let a_max = knots.iter().map(|k| k.amplitude_e).fold(0.0, f64::max);
    let t_max = a_max / low_e_per_s - offset_s;
    (t_min_s, t_max.max(t_min_s * 10.0))
}

/// The dark level under the first dark ([`dark`]): the background pixels, or each
/// pixel's late plateau with each bin's late fraction `r`.
enum BinDark<'a> {
    Background(&'a [(usize, usize)]),
    Late(&'a dark::LatePlateau, &'a [f64]),
}

/// Steps 2-4 of the module docs for every bin of at least `min_pixels` pixels, with its
/// index in `members`.
fn bin_results(
    seq: &Sequence,
    cfg: &CalibConfig,
    cr: &knots::CalibRamp,
    f: &ndarray::Array2<f64>,
    members: &[Vec<(usize, usize)>],
    dark: &BinDark,
    (noise, w): (f64, Option<&ndarray::Array2<f64>>),
) -> Vec<(usize, BinResult)> {
    let w_of = |p: (usize, usize)| w.map_or(1.0, |w| w[p]);
    let d = cr.dark;
    let ramp = seq.exposures[d]
        .ramp
        .as_ref()
        .expect("checked by CalibRamp::of");
    let t = &cr.t_s;
    let nsamp = ramp.shape()[0];
    // the read times since the first dark's reset (the dark current's charge)
    let t_since_reset: Vec<f64> = t.iter().map(|x| x - cr.t_reset_s).collect();
    let meas = seq.measured(d);
    // the background ramp, by the sequence's background (its median, or its line's
    // intercept at zero fluence, crate::measure::data "Background")
    let bg_ramp: Vec<f64> = match dark {
        BinDark::Background(bg_px) => (0..nsamp)
            .map(|s| {
                let v: Vec<(f64, f64)> = bg_px
                    .iter()
                    .map(|&(y, x)| (f[[y, x]], f64::from(ramp[[s, y, x]])))
                    .collect();
                seq.background_of(&v)
            })
            .collect(),
        BinDark::Late(..) => vec![0.0; nsamp],
    };
    // the first dark's shot-noise variance per e-/s, when the knots leave it out
    let knot_shot_var = cfg
        .knots_shot_noise_removed()
        .then(|| seq.shot_var_per_e_per_s(d));
    let lo_exp = 3.0;
    let mut bins = Vec::new();
    for (b, px) in members.iter().enumerate() {
        if px.len() < cfg.min_pixels {
            continue;
        }
        // each pixel's dark level, e-/s (0 with background pixels: removed as a whole)
        let dark_of = |p: (usize, usize)| match dark {
            BinDark::Background(_) => 0.0,
            BinDark::Late(l, r) => l.dark_at(p, r[b]),
        };
        let edge = |i: f64| 10f64.powf(lo_exp + i / cfg.bins_per_decade);
        let cur: Vec<f64> = match dark {
            BinDark::Background(_) => px.iter().map(|&p| meas[p] / w_of(p)).collect(),
            BinDark::Late(l, _) => px
                .iter()
                .map(|&p| (l.first[p] - dark_of(p)) / w_of(p))
                .collect(),
        };
        let (med, sd) = clipped_median(&cur, 3.0);
        // the measurement noise in the same units as `cur` (the bin's median factor)
        let noise = match w {
            None => noise,
            Some(_) => {
                noise / crate::stats::median(&px.iter().map(|&p| w_of(p)).collect::<Vec<_>>())
            }
        };
        let p95 = match knot_shot_var {
            Some(g) => signal_p95(&cur, med, shot_noise_added(noise, g, med)),
            None => signal_p95(&cur, med, noise),
        };
        let q: Vec<f64> = (0..nsamp)
            .map(|s| {
                let v: Vec<f64> = px
                    .iter()
                    .map(|&(y, x)| {
                        let q = f64::from(ramp[[s, y, x]]) - dark_of((y, x)) * t_since_reset[s];
                        // with spatial factors, each pixel's own persistence ramp
                        match w {
                            None => q,
                            Some(w) => (q - bg_ramp[s]) / w[(y, x)],
                        }
                    })
                    .collect();
                let m = clipped_median(&v, 3.0).0;
                if w.is_some() {
                    m
                } else {
                    m - bg_ramp[s]
                }
            })
            .collect();
        let ok: Vec<usize> = (0..nsamp)
            .filter(|&s| q[s].is_finite() && t[s] > 0.0)
            .collect();
        let ts: Vec<f64> = ok.iter().map(|&s| t[s]).collect();
        let qs: Vec<f64> = ok.iter().map(|&s| q[s]).collect();
        let lf = logfit::fit(&ts, &qs);
        let significant = med > 3.0 * sd / (px.len() as f64).sqrt() && med > 0.0;
        let a_bin = lf
            .filter(|l| l.a0_e > 0.0 && !l.undetermined)
            .map(|l| cfg.amplification * l.a0_e);
        let a_95 = a_bin
            .map(|a| a * p95 / med)
            .filter(|a| a.is_finite() && *a >= 0.0);
        bins.push((
            b,
            BinResult {
                fluence_lo_e: edge(b as f64),
                fluence_hi_e: edge(b as f64 + 1.0),
                fluence_mean_e: px.iter().map(|p| f[*p]).sum::<f64>() / px.len() as f64,
                pixels: px.len(),
                median_e_per_s: med,
                sd_e_per_s: sd,
                p95_e_per_s: p95,
                logfit: lf,
                a_bin_e: a_bin,
                a_95_e: a_95,
                knot: significant && a_95.is_some(),
            },
        ));
    }
    bins
}

/// Step 5 of the module docs.
pub fn fit_cn(rates: &[f64], t_min_s: f64, t_max_s: f64, offset_s: f64) -> Result<CnFit> {
    fit_cn_power(rates, t_min_s, t_max_s, offset_s, 1.0)
}

/// Step 5 of the module docs with the target `(t + offset_s)^-exponent` instead of
/// `1/(t + offset_s)` ([`super::exponent`]): least squares of the relative error
/// `sum_n C_n exp(-t/tau_n) (t + t_0)^p - 1`.
pub fn fit_cn_power(
    rates: &[f64],
    t_min_s: f64,
    t_max_s: f64,
    offset_s: f64,
    exponent: f64,
) -> Result<CnFit> {
    if !(exponent.is_finite() && exponent > 0.0) {
        return Err(Error::invalid(
            "decay exponent",
            format!("{exponent}: must be finite and > 0"),
        ));
    }
    if rates.is_empty() || rates.iter().any(|r| !(r.is_finite() && *r > 0.0)) {
        return Err(Error::invalid(
            "--rates-per-s",
            "need at least one rate, each finite and > 0",
        ));
    }
    if !(t_min_s.is_finite() && t_min_s > 0.0) {
        return Err(Error::invalid(
            "--t-min-s",
            format!("{t_min_s}: must be finite and > 0 s"),
        ));
    }
    if t_max_s.is_nan() || t_max_s <= t_min_s {
        return Err(Error::invalid(
            "--t-min-s",
            format!("span [{t_min_s}, {t_max_s}] s is empty"),
        ));
    }
    if !(offset_s.is_finite() && offset_s > 0.0) {
        return Err(Error::invalid(
            "--decay-offset-s",
            format!("{offset_s}: must be finite and > 0"),
        ));
    }
    let target = |t: f64| (t + offset_s).powf(-exponent);
    let mut f = fit_cn_to(rates, t_min_s, t_max_s, &target).map_err(|_| {
        // every term decayed before the span begins: a model that predicts nothing
        Error::invalid(
            "--t-min-s",
            format!(
                "no term follows (t + {offset_s})^-{exponent} over [{t_min_s}, {t_max_s}] s: every \
                 C_n came out 0 (the slowest rate, {} 1/s, has decayed by then)",
                rates.iter().copied().fold(f64::INFINITY, f64::min)
            ),
        )
    })?;
    f.offset_s = offset_s;
    f.exponent = exponent;
    Ok(f)
}

/// Step 5 of the module docs with any positive target `q(t)`: least squares of the
/// relative error `sum_n C_n exp(-t/tau_n) / q(t) - 1` at 400 log-spaced times over
/// `[t_min_s, t_max_s]`, negative `C_n` dropped and the rest refitted. The returned
/// fit's `offset_s` and `exponent` are NaN (the target is not a power law); errors
/// when the span is empty or every `C_n` comes out 0.
pub fn fit_cn_to(
    rates: &[f64],
    t_min_s: f64,
    t_max_s: f64,
    target: &dyn Fn(f64) -> f64,
) -> Result<CnFit> {
    if t_max_s.is_nan() || t_max_s <= t_min_s || t_min_s.is_nan() || t_min_s <= 0.0 {
        return Err(Error::invalid(
            "--t-min-s",
            format!("span [{t_min_s}, {t_max_s}] s is empty"),
        ));
    }
    let m = 400;
    let ts: Vec<f64> = (0..m)
        .map(|i| t_min_s * (t_max_s / t_min_s).powf(i as f64 / (m - 1) as f64))
        .collect();
    let mut active: Vec<bool> = vec![true; rates.len()];
    let mut c = vec![0.0; rates.len()];
    for _ in 0..rates.len() {
        let idx: Vec<usize> = (0..rates.len()).filter(|&i| active[i]).collect();
        let a = DMatrix::from_fn(m, idx.len(), |j, k| {
            (-rates[idx[k]] * ts[j]).exp() / target(ts[j])
        });
        let b = DVector::from_element(m, 1.0);
        let sol = a.svd(true, true).solve(&b, 1e-14).map_err(|e| {
            Error::invalid("--rates-per-s", format!("C_n least squares failed: {e}"))
        })?;
        c.iter_mut().for_each(|v| *v = 0.0);
        for (k, &i) in idx.iter().enumerate() {
            c[i] = sol[k];
        }
        match (0..rates.len())
            .filter(|&i| active[i] && c[i] < 0.0)
            .min_by(|&a, &b| c[a].total_cmp(&c[b]))
        {
            Some(i) => active[i] = false,
            None => break,
        }
    }
    c.iter_mut().for_each(|v| *v = v.max(0.0));
    if c.iter().all(|v| *v == 0.0) {
        return Err(Error::invalid(
            "C_n",
            format!("every C_n came out 0 over [{t_min_s}, {t_max_s}] s"),
        ));
    }
    let err: Vec<f64> = ts
        .iter()
        .map(|t| {
            let s: f64 = c.iter().zip(rates).map(|(ci, r)| ci * (-r * t).exp()).sum();
            s / target(*t) - 1.0
        })
        .collect();
    Ok(CnFit {
        t_min_s,
        t_max_s,
        offset_s: f64::NAN,
        exponent: f64::NAN,
        terms: c
            .iter()
            .zip(rates)
            .map(|(&c_per_s, &rate_per_s)| Term {
                c_per_s,
                rate_per_s,
            })
            .collect(),
        max_relative_error: err.iter().map(|e| e.abs()).fold(0.0, f64::max),
        rms_relative_error: (err.iter().map(|e| e * e).sum::<f64>() / m as f64).sqrt(),
    })
}

/// Quantile helper re-exported for reports.
pub fn p95(v: &[f64]) -> f64 {
    quantile(v, 0.95)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The presets: `paper` is `fit`'s defaults; `readout` is the readout reference (docs/validation/diagnose_matrix.md); a `--with` replaces the preset's entry of the same effect.
    #[test]
    fn presets_give_their_options_and_effects() {
        assert_eq!(
            Preset::Paper.config().record(),
            CalibConfig::default().record()
        );
        assert_eq!(Preset::Paper.with(&[]), ["refill"]);
        assert_eq!(Preset::Paper.release_keep(), ReleaseKeep::Threshold);
        assert_eq!(Preset::Readout.release_keep(), ReleaseKeep::Zero);
        let r = Preset::Readout.config();
        assert_eq!(
            (r.amplification, r.t_min_s, r.decay_offset_s),
            (1.0, 1.0, 0.2)
        );
        assert_eq!(r.rates_per_s.len(), 13);
        assert!((r.rates_per_s[1] - 0.398107).abs() < 1e-6);
        assert!((r.rates_per_s[12] - 1.58489e-5).abs() < 1e-10);
        assert!(Preset::Readout.matches(&r.record()));
        assert!(!Preset::Readout.matches(&CalibConfig::default().record()));
        let w = Preset::Readout.with(&["soak".into(), "chord:strength=0.9".into()]);
        assert_eq!(w, ["refill", "soak", "chord:strength=0.9"]);
        assert_eq!("readout".parse::<Preset>().unwrap(), Preset::Readout);
        let e = "r14".parse::<Preset>().unwrap_err().to_string();
        assert!(e.contains("--preset") && e.contains("r14"), "{e}");
    }

    /// The coverage rule of [`Stated`]: the preset's coverage unless an amplification is
    /// stated or fitted; a stated coverage wins over both; `no_coverage` clears it.
    #[test]
    fn stated_margin_means_no_preset_coverage() {
        let paper = Preset::Paper.config().coverage;
        assert_eq!(paper, Some(0.95));
        let cov = |s: Stated| Preset::Paper.config_stated(&s).coverage;
        assert_eq!(cov(Stated::default()), paper);
        let amp = Stated {
            amplification: Some(1.1),
            ..Stated::default()
        };
        assert_eq!(cov(amp.clone()), None);
        assert_eq!(Preset::Paper.config_stated(&amp).amplification, 1.1);
        let fitted = Stated {
            fit_amplification: true,
            ..Stated::default()
        };
        assert_eq!(cov(fitted.clone()), None);
        let both = Stated {
            coverage: Some(0.9),
            ..fitted
        };
        assert_eq!(cov(both), Some(0.9));
        let off = Stated {
            no_coverage: true,
            ..Stated::default()
        };
        assert_eq!(cov(off), None);
        assert_eq!(
            Preset::Readout.config_stated(&Stated::default()).coverage,
            None
        );
        let t = Stated {
            t_min_s: Some(3.0),
            rates_per_s: vec![0.5, 0.05],
            ..Stated::default()
        };
        let c = Preset::Readout.config_stated(&t);
        assert_eq!((c.t_min_s, c.decay_offset_s), (3.0, 0.2));
        assert_eq!(c.rates_per_s, [0.5, 0.05]);
    }

    /// Under `--cell-statistic population` the knots leave out the shot noise and the
    /// model file says so; the preset is still recognised, and a record without it
    /// writes no such key (older model files keep their identity).
    #[test]
    fn population_statistic_calibrates_noise_free_knots_and_records_it() {
        let pop = CalibConfig {
            cell_statistic: crate::measure::eval::CellStatistic::Population,
            ..Preset::Readout.config()
        };
        assert!(pop.knots_shot_noise_removed() && pop.record().knots_shot_noise_removed);
        assert!(Preset::Readout.matches(&pop.record()));
        assert!(!Preset::Readout.config().record().knots_shot_noise_removed);
        let json = |c: &CalibConfig| serde_json::to_string(&c.record()).unwrap();
        assert!(json(&pop).contains("\"knots_shot_noise_removed\":true"));
        assert!(!json(&Preset::Readout.config()).contains("knots_shot_noise_removed"));
    }

    #[test]
    fn cn_fit_follows_inverse_time() {
        let rates: Vec<f64> = PAPER_TERMS.iter().map(|t| t.1).collect();
        let f = fit_cn(&rates, 10.0, 1e5, 1.0).unwrap();
        assert!(f.max_relative_error < 0.10, "{f:?}");
        // close to the paper's fastest coefficient
        assert!((f.terms[0].c_per_s / 0.183 - 1.0).abs() < 0.3, "{f:?}");
    }

    /// `persist fit --rates-per-s`: terms 0.4 decade apart instead of the paper's 0.8-decade
    /// spacing follow `1/(t+1)` more closely over the same span (measured from 10 s to
    /// 1.4e5 s: RMS relative error 1.1 % against 3.3 %, largest 5.8 % against 8.6 %, the
    /// largest at the span's ends for both).
    #[test]
    fn finer_terms_follow_inverse_time_more_closely() {
        let paper: Vec<f64> = PAPER_TERMS.iter().map(|t| t.1).collect();
        let fine: Vec<f64> = (0..11).map(|k| 10f64.powf(-1.0 - 0.4 * k as f64)).collect();
        let (p, f) = (
            fit_cn(&paper, 10.0, 1.4e5, 1.0).unwrap(),
            fit_cn(&fine, 10.0, 1.4e5, 1.0).unwrap(),
        );
        assert_eq!(f.terms.len(), 11);
        assert!(
            f.rms_relative_error < 0.5 * p.rms_relative_error,
            "{p:?} {f:?}"
        );
        assert!(f.max_relative_error < p.max_relative_error, "{p:?} {f:?}");
        let e = fit_cn(&[0.1, -1.0], 10.0, 1e5, 1.0)
            .unwrap_err()
            .to_string();
        assert!(e.contains("--rates-per-s"), "{e}");
    }

    /// `--decay-offset-s` (module docs, "Decay offset"): the sum follows `1/(t + T0)`,
    /// not `1/(t + 1)`. Thirteen terms from 1 s: within 20 % of `1/(t + 0.2)` over the
    /// span, where `1/(t + 1)` differs from it by 2.7x at 1 s; a `T0` that is not a
    /// positive number is refused.
    #[test]
    fn decay_offset_moves_the_target() {
        let rates: Vec<f64> = (0..13).map(|k| 10f64.powf(-0.4 * k as f64)).collect();
        let f = fit_cn(&rates, 1.0, 1e5, 0.2).unwrap();
        assert_eq!(f.offset_s, 0.2);
        assert!(f.max_relative_error < 0.2, "{f:?}");
        let sum = |f: &CnFit, t: f64| -> f64 {
            f.terms
                .iter()
                .map(|c| c.c_per_s * (-c.rate_per_s * t).exp())
                .sum()
        };
        let paper = fit_cn(&rates, 1.0, 1e5, 1.0).unwrap();
        // at 1 s: 1/1.2 against 1/2
        let (a, b) = (sum(&f, 1.0), sum(&paper, 1.0));
        assert!(a / b > 1.4, "{a} {b}");
        // at 1000 s both are ~1/t
        let (a, b) = (sum(&f, 1000.0), sum(&paper, 1000.0));
        assert!((a / b - 1.0).abs() < 0.05, "{a} {b}");
        for bad in [0.0, -1.0, f64::NAN] {
            let e = fit_cn(&rates, 1.0, 1e5, bad).unwrap_err().to_string();
            assert!(e.contains("--decay-offset-s"), "{e}");
        }
    }

    /// Regression: `persist fit --t-min-s 1e9` wrote a model whose `C_n` were all 0 (the
    /// span, pushed to [1e9, 1e10] s, begins after every term has decayed), and
    /// `--t-min-s 0` was refused as an "empty span". Both now say what is wrong.
    #[test]
    fn a_span_no_term_reaches_or_a_zero_start_is_refused() {
        let rates: Vec<f64> = PAPER_TERMS.iter().map(|t| t.1).collect();
        let e = fit_cn(&rates, 1e9, 1e10, 1.0).unwrap_err().to_string();
        assert!(
            e.contains("--t-min-s") && e.contains("every C_n came out 0"),
            "{e}"
        );
        let e = fit_cn(&rates, 0.0, 1e5, 1.0).unwrap_err().to_string();
        assert!(
            e.contains("--t-min-s") && e.contains("must be finite and > 0"),
            "{e}"
        );
    }
}
