//! What `persist diagnose` decided, as data: the candidates with their gates, the
//! joint check, the residual's dependences and the pixel reference. The decisions are
//! made in [`super::diagnose`]; [`super::verdict`] puts them into words.
//!
//! # Invariants
//! - Nothing here computes: these are the fields of the JSON of `persist diagnose`,
//!   and those the verdict reads.
//! - [`Diagnosis::verdict`] is a function of the other fields and the model diagnosed
//!   ([`super::verdict::verdict`]).

use super::config::{Decide, Refit, Statistic};
use super::contrast;
use super::eval;
use super::refit::HeldOut;
use serde::Serialize;

/// Where a cell residual lies besides its fluence and time bins.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Place {
    /// The exposure index of the illumination it follows (per-illumination cells).
    pub illumination_exposure: Option<u64>,
    /// Its pixels lie next to a far brighter one.
    pub next_to_brighter: bool,
}

#[derive(Debug, Clone, Serialize)]
pub struct Candidate {
    pub effect: String,
    pub score: f64,
    pub score_rank: usize,
    pub threshold: f64,
    pub passes_score: bool,
    pub delta_bic: Option<f64>,
    pub rms_before: Option<f64>,
    pub rms_after: Option<f64>,
    pub held_out: Option<HeldOut>,
    pub significant: bool,
    /// A position effect that passed the other gates but is not declared: the residuals
    /// carry no field shared by neighbouring pixels (module docs, "Spatial coherence").
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub refused_no_field: bool,
    /// An effect that passed the gates but is not declared: the data-driven term along
    /// the named kind predicts held-out data better, the effect taking less than
    /// [`super::offer::LIBRARY_SHARE`] of the term's gain ([`super::offer`]).
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub outpredicted_by_term: bool,
    pub covariate: String,
    pub command: String,
    /// When `command` would fit the candidate against knots held at the paper's
    /// flagging margin ([`crate::calib::knots_held_off_level`]): the `--preset readout`
    /// fit that measures its parameters instead (`measure_command`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub measure_command: Option<String>,
    /// The candidate at the values its refit measured, as `persist fit --with` takes it
    /// with every fitted parameter held (`NAME:param=value,...`); `None` when it was
    /// not refitted.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub measured_with: Option<String>,
}

/// A pair of library effects refitted together (module docs, "Joint check").
#[derive(Debug, Clone, Serialize)]
pub struct Joint {
    /// The leading candidate by score, then its partner.
    pub effects: [String; 2],
    /// Against the model (its own effects refitted alone), both effects' parameters
    /// counted.
    pub delta_bic: f64,
    /// Against the leader refitted alone, the partner's parameters counted.
    pub delta_bic_over_leader: f64,
    pub rms_before: f64,
    pub rms_after: f64,
    /// Run for the pair with the lowest `delta_bic` when both BIC gates pass.
    pub held_out: Option<HeldOut>,
    pub significant: bool,
    pub command: String,
    /// As [`Candidate::measure_command`].
    #[serde(skip_serializing_if = "Option::is_none")]
    pub measure_command: Option<String>,
}

#[derive(Debug, Clone, Serialize)]
pub struct Diagnosis {
    /// The statistic used (never `auto`) and why.
    pub statistic: Statistic,
    pub statistic_reason: String,
    /// Per contrast class: whether the data can test it, else the measurement that
    /// would ([`contrast::testability`]). Untestable classes' effects are not scored.
    pub contrasts: Vec<contrast::Testability>,
    /// What the residual depends on, ranked ([`contrast::dependences`]): event-level
    /// classes against the pixel reference, pixel-level ones against the flexible base.
    pub dependences: Vec<contrast::Dependence>,
    /// The two leading event-level kinds the residual depends on, each tested given the
    /// other ([`super::separate`]).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub separation: Option<super::separate::Separation>,
    pub pixels_sampled: usize,
    pub samples: usize,
    pub cells: usize,
    pub groups: usize,
    pub events: usize,
    /// The residual cells of the refits and of `residual_rms_normalised`.
    pub residual_cells: eval::Cells,
    /// What every cell compares.
    pub cell_statistic: eval::CellStatistic,
    /// How each exposure's background was measured.
    pub background: super::data::Background,
    /// What the refits freed.
    pub refit: Refit,
    /// RMS of the cell residuals (as `compare`, on the subsample).
    pub residual_rms_normalised: f64,
    /// How well the pixel reference fits the same samples
    /// ([`super::base::predict_scaled`]).
    pub pixel_reference: PixelReference,
    pub bootstrap_replicas: usize,
    pub threshold: f64,
    /// Median over the replicas of the largest LM (what "nothing missing" looks like).
    pub bootstrap_median_max: f64,
    pub ranking: Vec<Candidate>,
    /// The largest cell residuals (where the model fails).
    pub largest_residuals: Vec<eval::GroupStat>,
    pub largest_residual_cells: Vec<(f64, f64)>,
    /// With per-illumination cells: the exposure index of each one's illumination.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub largest_residual_illuminations: Vec<u64>,
    /// The joint check, when no candidate is significant alone and one was refitted:
    /// every pair tried, lowest `delta_bic` first (module docs, "Joint check").
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub joint: Vec<Joint>,
    /// Whether the residuals carry a field shared by neighbouring pixels
    /// ([`super::spatial`]; absent with one illumination event).
    pub spatial: Option<super::spatial::Coherence>,
    /// The data-driven term along the covariate the residual depends on, when no
    /// library effect acting on it predicts held-out data ([`super::data_term`]).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub data_term: Option<super::data_term::DataTerm>,
    /// The decay's shape against the fluence, measured against the model diagnosed
    /// ([`super::shape`]); None when the samples hold fewer than two fluence bins.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub decay_shape: Option<super::shape::DecayShape>,
    /// The data-driven term along the decay's shape (`smooth_shape`), when a covariate
    /// names a kind that nothing along it follows and [`Self::decay_shape`] depends on
    /// the fluence besides ([`super::diagnose`], step 6).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub shape_term: Option<super::data_term::DataTerm>,
    /// What the verdict offers when it names a kind and nothing is significant: the
    /// data-driven term when it predicts held-out data against the pixel reference
    /// ([`super::offer`]).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub offer: Option<Offer>,
    /// Where each of [`Self::largest_residuals`] lies besides its cell.
    #[serde(skip)]
    pub largest_residual_places: Vec<Place>,
    /// How the candidates refitted were chosen.
    #[serde(skip)]
    pub decide: Decide,
    /// The verdict in words ([`super::verdict::verdict`]), built from the decisions above.
    pub verdict: String,
    /// What limits the diagnosis of this model (empty when nothing is known to).
    pub cautions: Vec<String>,
}

/// The pixel reference's fit ([`super::base::predict_scaled`]): the flexible base with
/// each pixel's own amplitude, decay shape and response, its residuals against the noise
/// measured from the data (the exposure noise and the shot noise, less each sample's
/// leverage in its pixel's fit).
#[derive(Debug, Clone, Serialize)]
pub struct PixelReference {
    pub residual_rms_normalised: f64,
    pub cells: usize,
    /// Its three largest cell residuals.
    pub largest_residuals: Vec<eval::GroupStat>,
    /// Its RMS fitted to each illumination event alone
    /// ([`super::base::per_event_rms`]); None with one event.
    pub per_event_rms: Option<f64>,
    /// The scales of its read-noise and shot-noise variances measured on its residuals
    /// ([`super::base::measure_noise_scale`]); None: not measured (too few samples),
    /// 1 and 1.
    pub noise_scale: Option<eval::NoiseScale>,
    /// The samples the scales were measured on (0 when not measured).
    pub noise_scale_samples: usize,
}

impl PixelReference {
    /// The pixel reference of the model's prediction `pred` over `samples`, as
    /// `persist diagnose` reports it: the noise scales measured on its residuals
    /// ([`super::base::scale_noise`], set into `samples` for every later fit on them),
    /// the fit with them ([`super::base::predict_scaled`]), its cells' RMS and the same
    /// fitted to each illumination event alone ([`super::base::per_event_rms`]).
    /// `view` is the model's clock and `response` its amplitude per fluence.
    pub fn fit(
        seq: &super::data::Sequence,
        view: &super::base::View,
        samples: &mut eval::Samples,
        pred: &[f64],
        response: &crate::model::response::Response,
    ) -> (PixelReference, super::base::Scaled) {
        use super::base;
        let noise_scale = base::scale_noise(seq, view, samples, pred, response);
        let scaled = base::predict_scaled(seq, view, samples, pred, response);
        let reference = PixelReference {
            per_event_rms: base::per_event_rms(seq, view, samples, pred, response).map(|r| r.0),
            noise_scale: noise_scale.map(|n| n.0),
            noise_scale_samples: noise_scale.map_or(0, |n| n.1),
            ..PixelReference::of(&scaled.cells(samples))
        };
        (reference, scaled)
    }

    pub(super) fn of(cells: &[(Vec<i64>, eval::GroupStat)]) -> PixelReference {
        let mut worst: Vec<eval::GroupStat> = cells.iter().map(|c| c.1).collect();
        worst.sort_by(|a, b| b.z.abs().total_cmp(&a.z.abs()));
        worst.truncate(3);
        PixelReference {
            residual_rms_normalised: eval::rms(cells),
            cells: cells.len(),
            largest_residuals: worst,
            per_event_rms: None,
            noise_scale: None,
            noise_scale_samples: 0,
        }
    }
}

/// The addition `persist diagnose` offers ([`super::offer`], its rule).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Offer {
    /// The library effect's name, or the data-driven term's.
    pub effect: String,
    /// Whether it is the data-driven term ([`super::finding::Diagnosis::data_term`]),
    /// else a candidate of the ranking.
    pub data_term: bool,
    /// Its held-out check against the pixel reference.
    pub pixel_reference: super::refit::PixelHeldOut,
}
