//! The transient rule measured in flight: what follows a cosmic-ray hit, and the
//! amplitude the model should give a `TRANSIENT` pixel.
//!
//! The paper (section "Transients") gives a hit the knot table's maximum amplitude
//! because the on-board processing removes the jump's size: conservative, and on the sky
//! most of the flags that cost sky for nothing. Here the hits are followed through the
//! later exposures like the saturating events ([`super::track`], "Cosmic-ray hits": a
//! `TRANSIENT` pixel the stage predicted quiet) and measured the same way: the excess
//! over the sky of the same exposure, less the control pixels', stacked by the time since
//! the hit ([`TransientBin`]), next to the stage's prediction.
//!
//! # The rule
//! As the margin check does for saturating events, the first exposure after each hit
//! measures the response with the best signal to noise: per hit, measured / predicted
//! (the stage's prediction there is the flown model's transient amplitude times its decay
//! law, the pixel being quiet before). The rule's factor is the stated quantile of that
//! ratio over the hits (default [`DEFAULT_QUANTILE`], the paper's 95th percentile), taken
//! at the upper end of its bootstrap 95 % interval ([`FirstExposure::ratio`]), with the
//! measurement noise taken out: the noise of each measurement widens the ratio's spread,
//! and a pixel's noise is no persistence. Its distance above the median loses, in
//! quadrature, the same quantile of the noise alone ([`FirstExposure::noise_ratio`]: the
//! mixture of zero-mean normals of each hit's noise / predicted), which is exact for a
//! normal response with normal noise: hits that leave no persistence give about their
//! median, hits that all leave the same give that, a noiseless measurement its own
//! quantile. Sources on a hit's pixel would add a tail the noise does not explain: the
//! first sample is screened for them by their extent ([`super::track`], "Cosmic-ray
//! hits"). The rule's amplitude is that factor times the flown amplitude ([`apply`]).
//! The later exposures follow the model's decay law; the report's decay by time since
//! the hit says how the measurement compares there.
//!
//! With fewer than [`min_events`] hits (ten expected above the quantile) there is no rule:
//! [`rule_ratio`] refuses and says why, and the model keeps the table's maximum. Nothing
//! here knows what charge a cosmic ray deposits: only what the exposures after it measure.
//!
//! Without a rule the exposure after a hit stays flagged whatever the prediction
//! (`MAX_AMPLITUDE`, [`crate::model::step`]): its persistence is not measured until that
//! exposure, so until flight data show otherwise the first exposure is conservative.
//! With the rule, measured at that very exposure, the prediction decides it.
//!
//! [`run`] is the I/O driver of `persist fit --from-verify`; the rest is pure.

use super::stack::{bin_of, Bin, Mean, QuantileBin};
use super::track::Sample;
use crate::error::{Error, ErrorKind, Result};
use crate::model::params::{sha256_hex, TransientProvenance, TransientRule};
use crate::model::ModelParams;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::Path;

/// The quantile of the rule by default: the paper's design percentile.
pub const DEFAULT_QUANTILE: f64 = 0.95;

/// Fewest hits for the quantile `q`: ten expected above it.
pub fn min_events(q: f64) -> u64 {
    (10.0 / (1.0 - q)).ceil() as u64
}

/// The response at the first exposure after the hits.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FirstExposure {
    /// The quantile stated.
    pub quantile: f64,
    /// The hits the quantile needs ([`min_events`]).
    pub min_events: u64,
    /// Hits measured there (with a positive predicted excess).
    pub events: u64,
    /// The quantile of measured / predicted and its bootstrap 95 % interval (`None`
    /// with too few hits for a bootstrap).
    pub ratio: Option<(f64, f64, f64)>,
    /// The median of measured / predicted.
    pub median_ratio: Option<f64>,
    /// The same quantile of the measurement noise alone, in units of the prediction:
    /// of the mixture of normals of zero mean and standard deviation each hit's noise /
    /// predicted ([`crate::measure::data::noisy_quantile`]). Absent in reports without
    /// it: the rule then keeps the noise in.
    #[serde(default)]
    pub noise_ratio: Option<f64>,
    /// The same quantile of true / predicted, where the input held a truth.
    pub true_ratio: Option<f64>,
}

/// One time bin of the measured persistence after the hits.
#[derive(Debug, Clone, Serialize)]
pub struct TransientBin {
    pub time_lo_s: f64,
    pub time_hi_s: f64,
    pub samples: usize,
    pub events: usize,
    pub mean_time_s: f64,
    pub measured: Mean,
    pub predicted: Mean,
    pub truth: Option<Mean>,
}

/// The report's transient section.
#[derive(Debug, Clone, Serialize)]
pub struct TransientReport {
    /// Hits followed (module docs).
    pub hits: u64,
    pub samples: usize,
    /// Hit samples rejected as sources in the pixel.
    pub rejected_as_sources: u64,
    pub first: FirstExposure,
    /// By time since the hit.
    pub decay: Vec<TransientBin>,
    /// What `persist fit --from-verify` does with this report, in words.
    pub rule: String,
}

/// Accumulators of the hits' samples (all detectors).
#[derive(Default)]
pub(super) struct Acc {
    /// columns: measured excess, predicted, truth, time
    decay: BTreeMap<usize, Bin<4>>,
    first: QuantileBin,
    /// Each first-exposure sample's noise / predicted.
    first_noise: Vec<f64>,
    first_truth: QuantileBin,
    truth_missing: bool,
    samples: usize,
}

impl Acc {
    /// One hit sample; `cluster` its hit.
    pub(super) fn add(&mut self, time_edges_s: &[f64], s: &Sample, cluster: u64) {
        let Some(tb) = bin_of(time_edges_s, s.time_s) else {
            return;
        };
        self.truth_missing |= s.true_excess_e_per_s.is_none();
        let truth = s.true_excess_e_per_s.unwrap_or(0.0);
        let measured = s.excess_e_per_s - s.control_e_per_s;
        let pred = s.predicted_excess_e_per_s;
        self.samples += 1;
        self.decay.entry(tb).or_default().add_weighted(
            cluster,
            super::sample_weight(s.sigma_e_per_s),
            [measured, pred, truth, s.time_s],
        );
        if s.first && pred > 0.0 && (measured / pred).is_finite() {
            self.first.add(cluster, measured / pred);
            self.first_noise.push(s.sigma_e_per_s / pred);
            self.first_truth.add(cluster, truth / pred);
        }
    }

    /// The section of the report: `hits` followed, `rejected` samples, the rule's
    /// `quantile`, the bootstraps seeded from `seed`.
    pub(super) fn summarise(
        self,
        time_edges_s: &[f64],
        (hits, rejected): (u64, u64),
        quantile: f64,
        seed: u64,
    ) -> TransientReport {
        let has_truth = !self.truth_missing && self.samples > 0;
        let w = [
            [1.0, 0.0, 0.0, 0.0],
            [0.0, 1.0, 0.0, 0.0],
            [0.0, 0.0, 0.0, 1.0],
            [0.0, 0.0, 1.0, 0.0],
        ];
        let decay = self
            .decay
            .iter()
            .filter_map(|(&tb, bin)| {
                let [measured, predicted, time, truth] =
                    bin.means(w, seed ^ (7 << 40) ^ tb as u64)?;
                Some(TransientBin {
                    time_lo_s: time_edges_s[tb],
                    time_hi_s: time_edges_s[tb + 1],
                    samples: bin.samples(),
                    events: bin.clusters(),
                    mean_time_s: time.mean,
                    measured,
                    predicted,
                    truth: has_truth.then_some(truth),
                })
            })
            .collect();
        let first = FirstExposure {
            quantile,
            min_events: min_events(quantile),
            events: self.first.samples() as u64,
            ratio: self.first.quantile(quantile, seed ^ (8 << 40)),
            median_ratio: self.first.quantile(0.5, seed ^ (9 << 40)).map(|v| v.0),
            noise_ratio: (!self.first_noise.is_empty()).then(|| {
                let zero = vec![0.0; self.first_noise.len()];
                crate::measure::data::noisy_quantile(&zero, &self.first_noise, quantile).0
            }),
            true_ratio: if has_truth {
                self.first_truth
                    .quantile(quantile, seed ^ (10 << 40))
                    .map(|v| v.0)
            } else {
                None
            },
        };
        let rule = match rule_ratio(&first) {
            Ok(r) => format!(
                "the transient amplitude times {r:.4}: the upper end of the 95 % interval of \
                 the {:.0}th percentile of measured / predicted at the first exposure after \
                 {} hits, less the noise's in quadrature",
                100.0 * quantile,
                first.events
            ),
            Err(why) => format!("no rule ({why}): the transient amplitude stays"),
        };
        TransientReport {
            hits,
            samples: self.samples,
            rejected_as_sources: rejected,
            first,
            decay,
            rule,
        }
    }
}

/// The factor the measurement puts on the flown transient amplitude (module docs, "The
/// rule"), or why there is none.
pub fn rule_ratio(first: &FirstExposure) -> std::result::Result<f64, String> {
    if !(first.quantile > 0.0 && first.quantile < 1.0) {
        return Err(format!("quantile {} is not in (0, 1)", first.quantile));
    }
    let need = min_events(first.quantile);
    if first.events < need {
        return Err(format!(
            "{} hits measured at their first exposure, the {:.0}th percentile needs {need}",
            first.events,
            100.0 * first.quantile
        ));
    }
    match first.ratio {
        Some((_, _, hi)) if hi.is_finite() => Ok(without_noise(
            hi,
            first.median_ratio.unwrap_or(0.0),
            first.noise_ratio.unwrap_or(0.0),
        )),
        _ => Err("the quantile of measured / predicted is not finite".into()),
    }
}

/// The quantile of the response with the measurement noise taken out (module docs,
/// "The rule"): the measured quantile's distance from the median, `measured - median`,
/// less the noise's quantile `noise` in quadrature, added to the median; at least 0.
/// Exact for a normal response measured with normal noise; a response with no spread
/// of its own gives its median, a measurement without noise its quantile. Non-finite
/// noise or median count as 0.
fn without_noise(measured: f64, median: f64, noise: f64) -> f64 {
    let median = if median.is_finite() {
        median.min(measured)
    } else {
        0.0
    };
    let noise = if noise.is_finite() {
        noise.max(0.0)
    } else {
        0.0
    };
    let spread = measured - median;
    (median + (spread * spread - noise * noise).max(0.0).sqrt()).max(0.0)
}

/// `model` with the rule of the measurement `first` (module docs), `report` naming the
/// verify report (as given) and `report_sha256` its bytes' hash. `model_ids` are the
/// models the measured run was flagged with: the ratio is relative to `model`'s
/// transient amplitude, so `model` must be the only one.
pub fn apply(
    model: &ModelParams,
    model_ids: &[String],
    first: &FirstExposure,
    (report, report_sha256): (&str, &str),
) -> std::result::Result<ModelParams, String> {
    let id = model.identity();
    if model_ids != [id.clone()] {
        return Err(format!(
            "the report measured a run flagged with model(s) {model_ids:?}; the model given is \
             {id}: the ratio is relative to the transient amplitude the run was flagged with"
        ));
    }
    let ratio = rule_ratio(first)?;
    let flown = model.transient_amplitude_e();
    let mut out = model.clone();
    out.transient = Some(TransientRule {
        amplitude_e: flown * ratio,
        measured: TransientProvenance {
            report: report.to_string(),
            report_sha256: report_sha256.to_string(),
            quantile: first.quantile,
            ratio,
            flown_amplitude_e: flown,
            events: first.events,
        },
    });
    out.validate()?;
    Ok(out)
}

/// `persist fit --from-verify REPORT`: read the verify report, set the rule of `model` (the
/// model the measured run was flagged with) from it and write the model to `out`. Returns
/// the line to print. Refuses (nothing written) when the report gives no rule.
pub fn run(report: &Path, model: &ModelParams, out: &Path) -> Result<String> {
    let bytes = std::fs::read(report).map_err(|e| Error::io(report, e))?;
    let invalid = |field: &str, why: String| {
        Error::new(ErrorKind::Invalid, why)
            .path(report)
            .field(field)
    };
    let v: serde_json::Value =
        serde_json::from_slice(&bytes).map_err(|e| invalid("/", format!("not JSON: {e}")))?;
    let first: FirstExposure = serde_json::from_value(v["transients"]["first"].clone())
        .map_err(|e| invalid("/transients/first", e.to_string()))?;
    let ids: Vec<String> = serde_json::from_value(v["model_ids"].clone())
        .map_err(|e| invalid("/model_ids", e.to_string()))?;
    let rule = apply(
        model,
        &ids,
        &first,
        (&report.display().to_string(), &sha256_hex(&bytes)),
    )
    .map_err(|why| invalid("/transients", format!("no transient rule: {why}")))?;
    std::fs::write(out, rule.to_json_pretty() + "\n").map_err(|e| Error::io(out, e))?;
    let t = rule.transient.as_ref().expect("set by apply");
    Ok(format!(
        "transient amplitude {:.1} e- (the flown {:.1} e- x {:.4}: {} hits, {:.0}th percentile); \
         the exposure after a hit follows the prediction. Model: {}",
        t.amplitude_e,
        t.measured.flown_amplitude_e,
        t.measured.ratio,
        t.measured.events,
        100.0 * t.measured.quantile,
        out.display()
    ))
}

/// A transient rule measured in flight ([`measure_in_flight`]): the model with it (or as
/// given, when the report gave no rule, with the reason) and what `verify` measured.
pub struct InFlight {
    pub params: ModelParams,
    /// Why there is no rule (`fit --from-verify` refused); `None`: `params` holds it.
    pub refused: Option<String>,
    pub report: TransientReport,
}

/// The transient rule measured the way operations measure it: the stage flags the
/// products of `sim` with `params` (its outputs and checkpoints in `dir`), `persist
/// verify` measures them (`dir/report`), and `persist fit --from-verify` ([`run`])
/// writes `dir/model.json`, read back. A report that gives no rule (too few hits
/// measured) is not an error: the model keeps its transient amplitude, as in
/// operations, and [`InFlight::refused`] says why.
pub fn measure_in_flight(sim: &Path, params: &ModelParams, dir: &Path) -> Result<InFlight> {
    let run_cfg = crate::stage::RunConfig {
        input: sim.to_path_buf(),
        output: dir.join("output"),
        checkpoints: dir.join("checkpoints"),
        model: crate::model::Model::new(params.clone())?,
        from_checkpoint: None,
        allow_model_change: false,
        checkpoint_every: u64::MAX,
        checkpoint_idle: std::time::Duration::ZERO,
        retention: Default::default(),
        processed_utc: crate::stage::processing_time(),
    };
    let ran = crate::stage::run(&run_cfg, &|_| {});
    if let Some(e) = ran.errors.into_iter().next() {
        return Err(e);
    }
    let report = super::run(sim, &run_cfg.output, &super::VerifyParams::default())?;
    super::write_report(&report, &dir.join("report"))?;
    let model = dir.join("model.json");
    let (params, refused) = match run(&dir.join("report").join("report.json"), params, &model) {
        Ok(_) => (crate::model_file::load(&model)?, None),
        Err(e) if e.context.field.as_deref() == Some("/transients") => {
            (params.clone(), Some(e.message))
        }
        Err(e) => return Err(e),
    };
    Ok(InFlight {
        params,
        refused,
        report: report.transients,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn hit(cluster: u64, excess: f64, pred: f64) -> Sample {
        Sample {
            y: 0,
            x: 0,
            cluster,
            event_fluence_e: f64::NAN,
            time_s: 100.0,
            excess_e_per_s: excess,
            sigma_e_per_s: 0.05,
            control_e_per_s: 0.0,
            control_true_e_per_s: 0.0,
            predicted_e_per_s: pred,
            predicted_excess_e_per_s: pred,
            flagged: true,
            true_excess_e_per_s: None,
            first: true,
        }
    }

    fn edges() -> Vec<f64> {
        super::super::VerifyParams::default().time_edges_s
    }

    /// Data without a transient give no rule, and the model keeps the table's maximum:
    /// `apply` refuses and says how many hits it had and needed.
    #[test]
    fn no_hits_no_rule() {
        let r = Acc::default().summarise(&edges(), (0, 0), DEFAULT_QUANTILE, 1);
        assert_eq!(r.first.events, 0);
        let why = rule_ratio(&r.first).unwrap_err();
        assert!(why.contains("0 hits") && why.contains("200"), "{why}");
        assert!(r.rule.starts_with("no rule"), "{}", r.rule);
        let m = ModelParams::default();
        let e = apply(&m, &[m.identity()], &r.first, ("r.json", &"0".repeat(64))).unwrap_err();
        assert!(e.contains("0 hits"), "{e}");
    }

    /// Too few hits for the quantile: refused, whatever their ratios.
    #[test]
    fn too_few_hits_no_rule() {
        let mut acc = Acc::default();
        for c in 0..150 {
            acc.add(&edges(), &hit(c, 0.01 * c as f64, 6.0), c);
        }
        let r = acc.summarise(&edges(), (150, 0), DEFAULT_QUANTILE, 1);
        assert_eq!(r.first.events, 150);
        assert!(rule_ratio(&r.first).unwrap_err().contains("needs 200"));
    }

    /// 1000 hits whose first exposures measure 0.000, 0.001, ..., 0.999 of the
    /// prediction: the 95th percentile is 0.95 (interpolated: 0.949 at rank 949.05), the
    /// rule takes its interval's upper end, and the model records where it came from.
    #[test]
    fn the_rule_is_the_stated_quantile_of_measured_over_predicted() {
        let mut acc = Acc::default();
        for c in 0..1000u64 {
            acc.add(&edges(), &hit(c, 6.0 * c as f64 / 1000.0, 6.0), c);
        }
        let r = acc.summarise(&edges(), (1000, 0), DEFAULT_QUANTILE, 1);
        let (q, lo, hi) = r.first.ratio.unwrap();
        assert!((q - 0.94905).abs() < 1e-9, "{q}");
        assert!(lo <= q && q <= hi && hi < 0.97, "{lo} {q} {hi}");
        // the noise (0.05 / 6 per hit, its 95th percentile 0.0137) barely moves it:
        // 0.5 + sqrt(0.46^2 - 0.0137^2) = 0.9598 for hi = 0.96
        let ratio = rule_ratio(&r.first).unwrap();
        let median = r.first.median_ratio.unwrap();
        let noise = r.first.noise_ratio.unwrap();
        assert!((noise - 1.644_854 * 0.05 / 6.0).abs() < 1e-6, "{noise}");
        let want = median + ((hi - median).powi(2) - noise * noise).sqrt();
        assert!((ratio - want).abs() < 1e-12 && ratio < hi && hi - ratio < 1e-3);
        let m = ModelParams::default();
        let sha = "a".repeat(64);
        let out = apply(&m, &[m.identity()], &r.first, ("v/report.json", &sha)).unwrap();
        let t = out.transient.as_ref().unwrap();
        assert!((t.amplitude_e - 878.0 * ratio).abs() < 1e-9);
        assert_eq!(t.measured.events, 1000);
        assert_eq!(t.measured.report, "v/report.json");
        assert_eq!(out.transient_amplitude_e(), t.amplitude_e);
        assert_ne!(out.identity(), m.identity());
        // measured against another model: refused
        let mut other = m.clone();
        other.name = "other".into();
        assert!(apply(&other, &[m.identity()], &r.first, ("r", &sha))
            .unwrap_err()
            .contains("flagged with"));
    }

    /// Hits measured with noise: 0.05 e-/s per pixel, each predicted 0.5 e-/s (noise
    /// 0.1 of the prediction), 1000 hits drawn from a normal. Hits that leave no
    /// persistence give a rule near zero, where the noisy quantile alone is 0.16; hits
    /// that all leave 0.4 of the prediction give 0.4; hits whose response spreads as
    /// N(0.4, 0.1) give its 95th percentile, 0.4 + 1.645 x 0.1 = 0.56.
    #[test]
    fn the_rule_takes_the_measurement_noise_out() {
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal};
        let rule_of = |mean: f64, spread: f64| -> (f64, f64) {
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
            let response = Normal::new(mean, spread.max(1e-300)).unwrap();
            let noise = Normal::new(0.0, 0.05).unwrap();
            let mut acc = Acc::default();
            for c in 0..1000u64 {
                let excess = 0.5 * response.sample(&mut rng) + noise.sample(&mut rng);
                acc.add(&edges(), &hit(c, excess, 0.5), c);
            }
            let r = acc.summarise(&edges(), (1000, 0), DEFAULT_QUANTILE, 1);
            (rule_ratio(&r.first).unwrap(), r.first.ratio.unwrap().2)
        };
        let (none, noisy) = rule_of(0.0, 0.0);
        assert!(
            noisy > 0.15 && none < 0.06,
            "no persistence: {none} (noisy {noisy})"
        );
        let (same, _) = rule_of(0.4, 0.0);
        assert!((same - 0.4).abs() < 0.06, "all 0.4: {same}");
        let (spread, _) = rule_of(0.4, 0.1);
        assert!((spread - 0.564).abs() < 0.06, "N(0.4, 0.1): {spread}");
    }
}
