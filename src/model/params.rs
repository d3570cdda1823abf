//! Model parameters and the model file.
//!
//! The model file is JSON, described by `schemas/model.schema.json`. Its identity is
//! the SHA-256 of its *canonical form*: the file parsed, every default filled in,
//! re-serialised with keys sorted and no whitespace, numbers in shortest round-trip
//! form. Two files that mean the same model therefore have the same identity, however
//! they are formatted.
//!
//! Invariants checked by [`ModelParams::validate`]: at least one term; every `c_per_s`
//! finite and >= 0; every `rate_per_s` finite and > 0; knots strictly increasing in
//! fluence, with finite non-negative amplitudes; `0 < low <= high` thresholds; early
//! release with a finite threshold and 1..=255 consecutive exposures; every effect
//! registered in [`crate::model::effects::REGISTRY`], at most once, with known
//! parameters inside their bounds.

// A model file's effect entries and knots are defined beside what reads them (the effect
// trait, the response), which import nothing from this file (src/model/mod.rs).
pub use super::effect::EffectSpec;
pub use super::response::Knot;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

/// Lower-case hex of a digest (the form of model identities and input digests).
pub fn to_hex(digest: &[u8]) -> String {
    digest.iter().map(|b| format!("{b:02x}")).collect()
}

/// SHA-256 of `bytes`, lower-case hex.
pub fn sha256_hex(bytes: &[u8]) -> String {
    to_hex(&Sha256::digest(bytes))
}

/// Version of the model file format this build reads and writes.
pub const MODEL_FORMAT: u32 = 1;

/// One term `C_n exp(-t / tau_n)` of Eq. (percurmodel); `tau_n = 1 / rate_per_s`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Term {
    /// Normalisation coefficient `C_n`, 1/s (so that `A [e-] * C_n` is e-/s).
    pub c_per_s: f64,
    /// Decay rate `1/tau_n`, 1/s. The paper quotes rates, so they are stored as rates.
    pub rate_per_s: f64,
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Thresholds {
    /// Flag (and set PERSIST) above this predicted current, e-/s. Paper: 0.1 (noise level).
    #[serde(default = "default_high")]
    pub high_e_per_s: f64,
    /// Secondary level, e-/s. Paper: 0.01 (dark current level).
    #[serde(default = "default_low")]
    pub low_e_per_s: f64,
}

fn default_high() -> f64 {
    0.1
}
fn default_low() -> f64 {
    0.01
}

impl Default for Thresholds {
    fn default() -> Self {
        Thresholds {
            high_e_per_s: default_high(),
            low_e_per_s: default_low(),
        }
    }
}

/// Early release (paper section "Early Release").
///
/// A pixel flagged above the high threshold whose *measured* line-fit current, less the
/// exposure's background when `subtract_background`, shows that its persistence is below
/// both `threshold_e_per_s` and its prediction is released: not flagged in that
/// exposure, and its amplitudes reset to zero. What "shows" means is the `rule`
/// ([`ReleaseRule`]).
///
/// The paper gives no number. The threshold's default, 0.1 e-/s (the high flag
/// threshold), is the largest value that cannot release a pixel whose persistence is
/// really above the flag threshold in expectation: the measured current is persistence +
/// dark + sky, so a background-subtracted measurement below 0.1 e-/s bounds the
/// persistence below the flag threshold, up to noise, as long as the background carries
/// little persistence itself ([`BackgroundEstimate`]: the image median does not where
/// much of the array is persistent).
///
/// Up to noise is the catch: the sky's noise per pixel is about 0.12 e-/s on the demo's
/// sky (the median over its exposures of [`crate::model::step::noise_e_per_s`]), as
/// large as the threshold. The paper-style rule (`consecutive`: three measurements in a
/// row below the threshold) releases a pixel truly at 0.10-0.13 e-/s with a few percent
/// chance in every window of three exposures, so within the hours it stays flagged it
/// is released, and, its amplitudes zero, missed from then on. The default rule
/// (`evidence`, [`ReleaseRule::Evidence`]) sums the evidence in noise sigmas instead, and
/// a pixel measured about at its threshold gathers none on average. A pixel truly at 2-3
/// times the threshold still gathers evidence now and then (the sum is a random walk
/// that drifts down by `(truth - threshold) / noise` per exposure, about 0.7 sigma at
/// twice the threshold), so the larger `evidence_sigma`, the rarer such a release.
/// Its default of 4 is measured on the demo's detector (`examples/flag_quality.rs`,
/// `persist fit`'s default model with the transient rule measured in flight, at 0.1
/// e-/s: missed / over-flagged / pixel-exposures missed with a truth above 0.2 e-/s):
/// seed 1, 3 sigma 4.22 % / 0.26 % / 16, 4 sigma 1.70 % / 0.32 % / 0, 5 sigma
/// 0.83 % / 0.37 % / 0; seed 2 (not used for tuning), 4 sigma 1.76 % / 0.33 % / 0.
/// 4 is the smallest value that misses none above 0.2 e-/s on both; at 0.01 e-/s it
/// over-flags 6.46 % (seed 1) against 5.98 % at 3 sigma and 6.78 % at 5. Before a
/// transient rule is measured in flight the cost is higher (a hit's pixel, flagged at
/// the maximum amplitude, takes longer to release): 0.91 % over-flagged at 3 sigma,
/// 1.24 % at 4 (seed 1). A margin below the prediction on each of the three
/// measurements of the count rule (release only below `prediction - z noise`) did
/// worse than the evidence sum on seed 1: z = 1 6.26 % / 1.08 %, z = 3 0.96 % / 1.50 %.
///
/// The background (`subtract_background`, default on) is the exposure's sky + dark level:
/// without it, a 0.5-2 e-/s zodiacal sky keeps every measurement above 0.1 e-/s
/// and nothing is ever released on the sky, so each cosmic ray (flagged at the maximum
/// amplitude, paper section "Transients") would stay flagged for over two hours
/// (measured with `persist demo`). With it off, the comparison is with the raw
/// measurement (right for dark laboratory data with a known-zero background). How the
/// level is estimated is [`BackgroundEstimate`] (`background`, default `quiet_pixels`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EarlyRelease {
    #[serde(default = "default_true")]
    pub enabled: bool,
    #[serde(default = "default_high")]
    pub threshold_e_per_s: f64,
    /// Exposures in a row under [`ReleaseRule::Consecutive`] (1..=255, default 3).
    #[serde(default = "default_consecutive")]
    pub consecutive: u8,
    #[serde(default = "default_true")]
    pub subtract_background: bool,
    #[serde(default)]
    pub background: BackgroundEstimate,
    /// How the measurements decide a release ([`ReleaseRule`], default `evidence`).
    #[serde(default)]
    pub rule: ReleaseRule,
    /// The evidence that releases under [`ReleaseRule::Evidence`], in noise sigmas
    /// (default 3; > 0 and at most 63.75, the count's 255 quarter sigmas).
    #[serde(default = "default_evidence_sigma")]
    pub evidence_sigma: f64,
    /// What a released pixel keeps of its amplitudes ([`ReleaseKeep`], default `zero`,
    /// the paper's; not written when `zero`, so the identity of a model without it is
    /// unchanged).
    #[serde(default, skip_serializing_if = "ReleaseKeep::is_zero")]
    pub keep: ReleaseKeep,
}

/// What early release leaves of a released pixel's amplitudes (`Kernel::release_amplitudes`
/// in [`crate::model::step`]).
///
/// The evidence that releases a pixel shows that its persistence is below the release
/// threshold, not that it is zero. Reset to zero (the paper's), a released pixel is
/// predicted quiet from then on: on the demo's detector (`examples/flag_quality.rs`,
/// `persist::flag_causes`) over 90 % of the pixel-exposures missed at 0.01 e-/s, and
/// nearly all missed at 0.1 e-/s, are pixels early release acted on since their last
/// event. Scaled to the threshold instead, the prediction starts from the bound the
/// evidence gives and follows the model's decay law from there: the pixel is no longer
/// flagged high, and flagged low as long as that bound says its persistence may still
/// be above the low threshold.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ReleaseKeep {
    /// Amplitudes reset to zero (the paper).
    #[default]
    Zero,
    /// Amplitudes scaled by `threshold / prediction` (the high flag threshold), so that
    /// the prediction of the exposure that releases is the threshold.
    Threshold,
}

impl ReleaseKeep {
    pub fn is_zero(&self) -> bool {
        *self == ReleaseKeep::Zero
    }
}

/// How a flagged pixel's measurements decide its early release
/// ([`crate::model::step`], `Kernel::release_step`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ReleaseRule {
    /// Released after `consecutive` exposures in a row measured (less the background)
    /// below the threshold.
    Consecutive,
    /// A one-sided cumulative sum (CUSUM) of the evidence that the pixel's current is
    /// below both the threshold and its prediction: each exposure adds
    /// `(min(threshold, prediction) - measured) / noise`, the sum never goes below 0,
    /// and the pixel is released when it reaches `evidence_sigma`. The noise is the
    /// exposure's, from its quiet pixels ([`crate::model::step::noise_e_per_s`]). A
    /// measurement consistent with a current at the threshold adds as much as it
    /// takes away on average, so a pixel above the threshold is seldom released, however
    /// long it stays flagged; one measured well below is released in a few exposures.
    #[default]
    Evidence,
}

/// How the early-release background is estimated from the exposure's image
/// ([`crate::model::step::background_e_per_s`]), on a sample of at most 65,536
/// pixels.
///
/// Why not the image median: where a large part of the array carries persistence, the
/// median pixel does too, and subtracting it releases pixels whose persistence is still
/// above the flag threshold. Measured on the 64 x 64 laboratory campaign (seed 1,
/// reference refill + chord): after the
/// 4x-flux illumination the image median holds 0.12 e-/s of persistence (0.27 e-/s when
/// the spot moves between illuminations, `persist simulate lab --spots shifted`), and
/// the missed-flag fraction at 0.1 e-/s was 3.6 % of all samples with the spot moved;
/// the median of the pixels the model predicts quiet is the dark level.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum BackgroundEstimate {
    /// The median of the image (the paper gives no setting).
    ImageMedian,
    /// The median of the image over the pixels whose predicted persistence current (the
    /// plain sum `sum_n A_n C_n exp(-t_meas/tau_n)` of the state, before this exposure's
    /// flagging) is at most the low threshold, and at least the 1/256 of the sample
    /// (and at least 16 pixels) with the lowest prediction. On the sky, where few
    /// pixels carry persistence, this is the image median of the unpersistent pixels;
    /// at the first exposure (empty state) it is the image median.
    #[default]
    QuietPixels,
}

fn default_true() -> bool {
    true
}
fn default_consecutive() -> u8 {
    3
}
fn default_evidence_sigma() -> f64 {
    4.0
}

impl EarlyRelease {
    /// `evidence_sigma` in the count's units (quarter sigmas), rounded up: 1..=255 for a
    /// valid model.
    pub fn evidence_quarter_sigmas(&self) -> u8 {
        (4.0 * self.evidence_sigma).ceil().clamp(1.0, 255.0) as u8
    }
}

impl Default for EarlyRelease {
    fn default() -> Self {
        EarlyRelease {
            enabled: true,
            threshold_e_per_s: default_high(),
            consecutive: default_consecutive(),
            subtract_background: true,
            background: BackgroundEstimate::default(),
            rule: ReleaseRule::default(),
            evidence_sigma: default_evidence_sigma(),
            keep: ReleaseKeep::default(),
        }
    }
}

/// Everything the model needs; the content of a model file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ModelParams {
    pub model_format: u32,
    pub name: String,
    #[serde(default)]
    pub description: String,
    pub terms: Vec<Term>,
    pub amplitude_knots: Vec<Knot>,
    #[serde(default)]
    pub thresholds: Thresholds,
    #[serde(default)]
    pub early_release: EarlyRelease,
    #[serde(default)]
    pub effects: Vec<EffectSpec>,
    /// How `persist fit` made this model ([`Calibration`]); absent from a model written
    /// by hand or by a version of `fit` that did not record it (not written when absent,
    /// so such a model keeps its identity).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub calibration: Option<Calibration>,
    /// Per-pixel response maps, one per detector ([`PixelMapRef`]); absent (not written)
    /// without, so models without one keep their identity.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pixel_map: Option<PixelMapRef>,
    /// The response of a `TRANSIENT` pixel ([`TransientRule`]); absent (not written):
    /// the knot table's maximum, the paper's rule, so models without one keep their
    /// identity.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub transient: Option<TransientRule>,
}

/// The amplitude a `TRANSIENT` pixel adds to every term, measured in flight
/// (`persist verify`'s transient measurement, written by `persist fit --from-verify`;
/// docs/verify.md, "The transient rule"). Without it a transient takes the knot table's
/// maximum (paper section "Transients") and the exposure after the hit is flagged
/// whatever the prediction (`MAX_AMPLITUDE`); with it, the rule, measured at that
/// exposure, sets what it and the later exposures predict.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TransientRule {
    /// `A_k` of a `TRANSIENT` pixel, e- (finite, `>= 0`).
    pub amplitude_e: f64,
    /// Where it was measured.
    pub measured: TransientProvenance,
}

/// The verify report a [`TransientRule`] was derived from, and how.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TransientProvenance {
    /// The `report.json` of `persist verify`, as given to `fit --from-verify`.
    pub report: String,
    /// SHA-256 of its bytes, 64 lower-case hex digits.
    pub report_sha256: String,
    /// The quantile of measured / predicted over the hits' first exposures (in `(0, 1)`).
    pub quantile: f64,
    /// The upper end of that quantile's bootstrap 95 % interval: the factor applied.
    pub ratio: f64,
    /// The transient amplitude of the model the measured run was flagged with, e-.
    pub flown_amplitude_e: f64,
    /// Hits measured.
    pub events: u64,
}

/// The per-pixel response maps a model applies (`crate::pixmap`; docs/pixel_map.md):
/// the files and their content hashes (which enter the model identity with the rest of
/// the model file), and the margin the flags keep above each pixel's own response.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PixelMapRef {
    /// One file per detector.
    pub files: Vec<PixelMapFile>,
    /// Each pixel's response is `A_k(F) * margin * ratio_upper(F)`: `ratio_upper` the
    /// map's upper posterior quantile of the pixel's amplitude relative to this model's
    /// knots (`> 0`).
    pub margin: f64,
}

/// One detector's map file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PixelMapFile {
    /// Detector 1..=6.
    pub detector: u8,
    /// The HDF5 map, absolute or relative to the model file's directory.
    pub path: String,
    /// SHA-256 of the file's bytes, 64 lower-case hex digits.
    pub sha256: String,
}

/// The `persist fit` options a model was calibrated with, so that a refit of the same
/// campaign (the command `persist diagnose` suggests) repeats them. The model step does
/// not read them.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Calibration {
    /// `A_bin = amplification * A_0` (`--amplification`; the paper: 1.2).
    pub amplification: f64,
    /// Start of the span of the `C_n` fit, s (`--t-min-s`).
    pub t_min_s: f64,
    /// The `C_n` follow `1/(t + decay_offset_s)` (`--decay-offset-s`; the paper: 1 s).
    pub decay_offset_s: f64,
    /// The terms' decay rates as given (`--rates-per-s`; equal to the terms'
    /// `rate_per_s`).
    pub rates_per_s: Vec<f64>,
    /// The `C_n` were then fitted to the campaign (`--fit-cn`).
    #[serde(default)]
    pub fit_cn: bool,
    /// The knots' level was then fitted to the campaign (`--fit-amplification`).
    #[serde(default)]
    pub fit_amplification: bool,
    /// The `C_n` were then refitted to `(t + decay_offset_s)^-p` with this exponent `p`
    /// fitted to the campaign (`--fit-decay-exponent`, `persist::calib::exponent`).
    /// Absent when the exponent is the paper's 1, so older files keep their identity.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub decay_exponent: Option<f64>,
    /// Each bin's 95th percentile had the shot noise of the pixels' own current removed
    /// in quadrature as well as the exposure noise (`fit --cell-statistic population`,
    /// whose reference takes the predictions for noise-free 95th percentiles;
    /// `persist::calib`, step 2). Absent (false) otherwise, so older files keep their
    /// identity.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub knots_shot_noise_removed: bool,
    /// The first dark's dark level came from each pixel's own late darks, its predicted
    /// persistence there removed, because no pixel stayed unlit (`persist::calib::dark`).
    /// Absent (false) when it came from the background pixels, so older files keep their
    /// identity.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub late_plateau_dark: bool,
    /// The knots were then scaled so that this share of the laboratory samples measured
    /// above each threshold is flagged (`fit --coverage`, the paper preset's default
    /// 0.95; `persist::calib::coverage`). Absent when the knots keep the amplification
    /// (`--no-coverage`), so older files keep their identity.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub coverage: Option<f64>,
}

/// Eq. (bbdetexpsum): `(C_n, 1/tau_n)` for detector BBDet.
pub const PAPER_TERMS: [(f64, f64); 6] = [
    (0.183, 0.1),
    (0.029, 0.0158),
    (0.0046, 0.00251),
    (0.000729, 0.000398),
    (0.000115, 6.31e-5),
    (1.83e-5, 1e-5),
];

/// Table 1: (fluence [e-], A_bin [e-]). The paper fits its `A_k` knots to the 95th
/// percentile response but does not publish them; these sigma-clipped-median values
/// (already amplified by 1.2) stand in until a calibration fit replaces them.
pub const PAPER_TABLE1_A_BIN: [(f64, f64); 5] = [
    (101_000.0, 54.1),
    (201_000.0, 144.2),
    (401_000.0, 711.1),
    (1_540_000.0, 676.9),
    (3_833_000.0, 878.0),
];

impl Default for ModelParams {
    fn default() -> Self {
        ModelParams {
            model_format: MODEL_FORMAT,
            name: "bbdet-fazar".into(),
            description: "Fazar et al., 'Image persistence flagging for SPHEREx': terms of \
                          Eq. (bbdetexpsum); amplitude knots from the A_bin column of Table 1 \
                          (sigma-clipped median x 1.2; the paper's 95th-percentile knots are \
                          not published)."
                .into(),
            terms: PAPER_TERMS
                .iter()
                .map(|&(c_per_s, rate_per_s)| Term {
                    c_per_s,
                    rate_per_s,
                })
                .collect(),
            amplitude_knots: PAPER_TABLE1_A_BIN
                .iter()
                .map(|&(fluence_e, amplitude_e)| Knot {
                    fluence_e,
                    amplitude_e,
                })
                .collect(),
            thresholds: Thresholds::default(),
            early_release: EarlyRelease::default(),
            effects: Vec::new(),
            calibration: None,
            pixel_map: None,
            transient: None,
        }
    }
}

impl ModelParams {
    /// Parse and validate a model file's text.
    pub fn from_json(text: &str) -> Result<Self, String> {
        let p: ModelParams = serde_json::from_str(text).map_err(|e| e.to_string())?;
        p.validate()?;
        Ok(p)
    }

    /// Pretty JSON for humans (`persist model default`).
    pub fn to_json_pretty(&self) -> String {
        serde_json::to_string_pretty(self).expect("model params serialise")
    }

    /// Append the effect `e`, its unfitted parameters (configuration, not fitted:
    /// [`crate::model::effect::ParamSpec::fitted`] false, e.g. the readout's
    /// `first_read_s`, `temperature`'s `t_ref_k`) that it does not give taken from an
    /// effect already in the model that gives a parameter of the same name. The readout
    /// is one: a `linefit_bias` added to a model whose `chord` reads from 1.5 s after the
    /// reset reads from there too.
    pub fn push_effect(&mut self, mut e: EffectSpec) {
        if let Some(def) = super::effects::lookup(&e.name) {
            for p in def.params.iter().filter(|p| !p.fitted) {
                if e.params.contains_key(p.name) {
                    continue;
                }
                if let Some(v) = self.effects.iter().find_map(|o| o.params.get(p.name)) {
                    e.params.insert(p.name.to_string(), v.clone());
                }
            }
        }
        self.effects.push(e);
    }

    /// Canonical form: defaults filled, keys sorted, no whitespace.
    pub fn canonical_json(&self) -> String {
        // serde_json's Map is a BTreeMap without the `preserve_order` feature: sorted keys.
        let v = serde_json::to_value(self).expect("model params serialise");
        serde_json::to_string(&v).expect("value serialises")
    }

    /// The model identity: SHA-256 of the canonical form, lower-case hex.
    pub fn identity(&self) -> String {
        sha256_hex(self.canonical_json().as_bytes())
    }

    /// Every knot's amplitude times `factor` (the flags' margin, a fitted knot scale).
    pub fn scale_knots(&mut self, factor: f64) {
        for k in self.amplitude_knots.iter_mut() {
            k.amplitude_e *= factor;
        }
    }

    /// The largest amplitude of the knot table (used for transients and unknown fluence).
    pub fn max_amplitude_e(&self) -> f64 {
        self.amplitude_knots
            .iter()
            .map(|k| k.amplitude_e)
            .fold(0.0, f64::max)
    }

    /// The amplitude a `TRANSIENT` pixel adds to every term, e-: the measured rule's
    /// ([`TransientRule`]), or the knot table's maximum without one.
    pub fn transient_amplitude_e(&self) -> f64 {
        self.transient
            .as_ref()
            .map_or_else(|| self.max_amplitude_e(), |r| r.amplitude_e)
    }

    pub fn validate(&self) -> Result<(), String> {
        if self.model_format != MODEL_FORMAT {
            return Err(format!(
                "model_format: this build reads format {MODEL_FORMAT}, the file is format {}",
                self.model_format
            ));
        }
        if self.terms.is_empty() {
            return Err("terms: at least one term is required".into());
        }
        for (i, t) in self.terms.iter().enumerate() {
            if !(t.c_per_s.is_finite() && t.c_per_s >= 0.0) {
                return Err(format!("terms[{i}].c_per_s: must be finite and >= 0"));
            }
            if !(t.rate_per_s.is_finite() && t.rate_per_s > 0.0) {
                return Err(format!("terms[{i}].rate_per_s: must be finite and > 0"));
            }
        }
        if self.amplitude_knots.is_empty() {
            return Err("amplitude_knots: at least one knot is required".into());
        }
        let mut prev = 0.0;
        for (i, k) in self.amplitude_knots.iter().enumerate() {
            if !(k.fluence_e.is_finite() && k.fluence_e > prev) {
                return Err(format!(
                    "amplitude_knots[{i}].fluence_e: must be finite and increase strictly from 0"
                ));
            }
            if !(k.amplitude_e.is_finite() && k.amplitude_e >= 0.0) {
                return Err(format!(
                    "amplitude_knots[{i}].amplitude_e: must be finite and >= 0"
                ));
            }
            prev = k.fluence_e;
        }
        let th = &self.thresholds;
        if !(th.low_e_per_s.is_finite() && th.low_e_per_s > 0.0) {
            return Err("thresholds.low_e_per_s: must be finite and > 0".into());
        }
        if !(th.high_e_per_s.is_finite() && th.high_e_per_s >= th.low_e_per_s) {
            return Err("thresholds.high_e_per_s: must be finite and >= low_e_per_s".into());
        }
        let er = &self.early_release;
        if !er.threshold_e_per_s.is_finite() {
            return Err("early_release.threshold_e_per_s: must be finite".into());
        }
        if !(er.evidence_sigma > 0.0 && er.evidence_sigma <= 63.75) {
            return Err("early_release.evidence_sigma: must be > 0 and <= 63.75".into());
        }
        if er.consecutive == 0 {
            return Err("early_release.consecutive: must be >= 1".into());
        }
        if let Some(m) = &self.pixel_map {
            if !(m.margin.is_finite() && m.margin > 0.0) {
                return Err("pixel_map.margin: must be finite and > 0".into());
            }
            let mut dets = Vec::new();
            for (i, f) in m.files.iter().enumerate() {
                if !(1..=6).contains(&f.detector) || dets.contains(&f.detector) {
                    return Err(format!(
                        "pixel_map.files[{i}].detector: must be 1..=6 and given once"
                    ));
                }
                dets.push(f.detector);
                if f.path.is_empty() {
                    return Err(format!("pixel_map.files[{i}].path: must not be empty"));
                }
                if !is_sha256_hex(&f.sha256) {
                    return Err(format!(
                        "pixel_map.files[{i}].sha256: must be 64 lower-case hex digits"
                    ));
                }
            }
        }
        if let Some(t) = &self.transient {
            t.validate()?;
        }
        let mut seen: Vec<&str> = Vec::new();
        for (i, e) in self.effects.iter().enumerate() {
            super::effects::resolve(e).map_err(|m| format!("effects[{i}].{m}"))?;
            if seen.contains(&e.name.as_str()) {
                return Err(format!(
                    "effects[{i}].name: effect `{}` given twice",
                    e.name
                ));
            }
            seen.push(&e.name);
        }
        Ok(())
    }
}

impl TransientRule {
    fn validate(&self) -> Result<(), String> {
        if !(self.amplitude_e.is_finite() && self.amplitude_e >= 0.0) {
            return Err("transient.amplitude_e: must be finite and >= 0".into());
        }
        let m = &self.measured;
        if !(m.quantile > 0.0 && m.quantile < 1.0) {
            return Err("transient.measured.quantile: must be in (0, 1)".into());
        }
        for (name, v) in [
            ("ratio", m.ratio),
            ("flown_amplitude_e", m.flown_amplitude_e),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(format!(
                    "transient.measured.{name}: must be finite and >= 0"
                ));
            }
        }
        if !is_sha256_hex(&m.report_sha256) {
            return Err(
                "transient.measured.report_sha256: must be 64 lower-case hex digits".into(),
            );
        }
        Ok(())
    }
}

/// 64 lower-case hex digits.
fn is_sha256_hex(s: &str) -> bool {
    s.len() == 64
        && s.chars()
            .all(|c| c.is_ascii_digit() || ('a'..='f').contains(&c))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_is_valid_and_round_trips() {
        let p = ModelParams::default();
        p.validate().unwrap();
        let back = ModelParams::from_json(&p.to_json_pretty()).unwrap();
        assert_eq!(back, p);
        assert_eq!(back.identity(), p.identity());
    }

    /// `push_effect`: an added effect takes the unfitted parameters (configuration) that
    /// another effect of the model gives, not the fitted ones, and not over its own.
    #[test]
    fn an_added_effect_shares_the_model_s_configuration() {
        let mut p = ModelParams::default();
        let mut chord = EffectSpec::named("chord");
        chord
            .params
            .insert("strength".into(), serde_json::json!(1.0));
        chord
            .params
            .insert("first_read_s".into(), serde_json::json!(1.5));
        chord.fixed = vec!["strength".into(), "first_read_s".into()];
        p.push_effect(chord);
        p.push_effect(EffectSpec::named("linefit_bias"));
        let lb = &p.effects[1];
        assert_eq!(lb.params.get("first_read_s"), Some(&serde_json::json!(1.5)));
        assert!(lb.params.get("strength").is_none(), "fitted: not shared");
        assert!(lb.fixed.is_empty());
        let mut own = EffectSpec::named("linefit_bias");
        own.params
            .insert("first_read_s".into(), serde_json::json!(3.0));
        let mut q = p.clone();
        q.effects.truncate(1);
        q.push_effect(own);
        assert_eq!(q.effects[1].params["first_read_s"], serde_json::json!(3.0));
    }

    #[test]
    fn identity_ignores_formatting_and_defaults() {
        let p = ModelParams::default();
        // Same model, written with defaults omitted and numbers spelled differently.
        let mut v: serde_json::Value = serde_json::from_str(&p.to_json_pretty()).unwrap();
        v.as_object_mut().unwrap().remove("thresholds");
        v.as_object_mut().unwrap().remove("early_release");
        let text = serde_json::to_string_pretty(&v)
            .unwrap()
            .replace("0.183", "1.83e-1");
        let q = ModelParams::from_json(&text).unwrap();
        assert_eq!(q.identity(), p.identity());
        let mut r = p.clone();
        r.thresholds.high_e_per_s = 0.2;
        assert_ne!(r.identity(), p.identity());
    }

    #[test]
    fn refuses_unknown_fields_and_bad_values() {
        let p = ModelParams::default();
        let mut v: serde_json::Value = serde_json::to_value(&p).unwrap();
        v["colour"] = serde_json::json!("red");
        assert!(ModelParams::from_json(&v.to_string())
            .unwrap_err()
            .contains("colour"));
        let mut q = p.clone();
        q.amplitude_knots[1].fluence_e = 50.0;
        assert!(q.validate().unwrap_err().contains("amplitude_knots[1]"));
        let mut q = p.clone();
        q.terms[2].rate_per_s = f64::NAN;
        assert!(q.validate().unwrap_err().contains("terms[2].rate_per_s"));
        for bad in [0.0, -1.0, 64.0, f64::NAN, f64::INFINITY] {
            let mut q = p.clone();
            q.early_release.evidence_sigma = bad;
            let e = q.validate().unwrap_err();
            assert!(e.contains("early_release.evidence_sigma"), "{bad}: {e}");
        }
        let mut q = p.clone();
        q.early_release.evidence_sigma = 63.75;
        assert_eq!(q.early_release.evidence_quarter_sigmas(), 255);
        q.validate().unwrap();
    }

    /// A transient rule: its amplitude replaces the maximum for transients, it changes
    /// the identity, and bad values are refused naming the field.
    #[test]
    fn a_transient_rule_is_validated_and_enters_the_identity() {
        let p = ModelParams::default();
        assert_eq!(p.transient_amplitude_e(), 878.0);
        let mut q = p.clone();
        q.transient = Some(TransientRule {
            amplitude_e: 30.0,
            measured: TransientProvenance {
                report: "r/report.json".into(),
                report_sha256: "ab".repeat(32),
                quantile: 0.95,
                ratio: 30.0 / 878.0,
                flown_amplitude_e: 878.0,
                events: 500,
            },
        });
        q.validate().unwrap();
        assert_eq!(q.transient_amplitude_e(), 30.0);
        assert_ne!(q.identity(), p.identity());
        assert_eq!(ModelParams::from_json(&q.to_json_pretty()).unwrap(), q);
        let mut r = q.clone();
        r.transient.as_mut().unwrap().amplitude_e = f64::NAN;
        assert!(r
            .validate()
            .unwrap_err()
            .starts_with("transient.amplitude_e"));
        let mut r = q.clone();
        r.transient.as_mut().unwrap().measured.report_sha256 = "xyz".into();
        assert!(r
            .validate()
            .unwrap_err()
            .starts_with("transient.measured.report_sha256"));
    }

    #[test]
    fn max_amplitude_is_table1_largest() {
        assert_eq!(ModelParams::default().max_amplitude_e(), 878.0);
    }
}
