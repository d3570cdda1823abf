//! `persist diagnose`: which library effect is missing from a fitted model.
//!
//! # Decision
//! 1. **Statistic** (`--statistic auto`, the default): `within` with two illumination
//!    events or more, `pooled` with one; the output says which and why.
//! 2. **Untestable is an answer**: classes whose covariate has no contrast in the data
//!    are listed with the measurement that would test them and are not scored
//!    ([`super::contrast::testability`]).
//! 3. **A flexible base** ([`super::base`]): the model plus a free response per fluence
//!    knot and free weights over a fixed grid of decay rates, superposed over every
//!    illumination, fitted once; its residual, standardised inside fluence x time
//!    cells, is what an effect must explain.
//! 4. **What the residual depends on** ([`super::contrast::dependences`]): the share of
//!    it each testable covariate explains inside the cells, calibrated by permuting the
//!    covariate among whole pixel-events of one fluence bin; ranked by `z`, the
//!    event-level classes among themselves by effect size (module docs there).
//! 5. **Identify**: the library effects acting on every covariate above all its
//!    permutations are refitted (at most [`REFIT`]); an effect is significant when its
//!    refit passes the change in BIC and the held-out check (below); among significant
//!    ones the best held-out prediction comes first. When the residual depends on a
//!    covariate but no effect on it passes, the verdict says so and prints the
//!    residual by that covariate's bins.
//!
//! The score test and its bootstrap threshold (below) are still computed and printed:
//! they rank the testable effects, they no longer choose which are refitted (a score
//! along one parametric form, calibrated from the fitted model alone, rises with any
//! misfit of the base).
//!
//! # Sample
//! A random subsample of `pixels` (default [`DEFAULT_PIXELS`]) of the pixels lit above
//! the background fluence in some illumination, drawn with ChaCha8 from `--seed`
//! ([`Samples::random`]); every exposure after an illumination. The model always runs
//! on the whole array.
//!
//! # Residuals
//! Cells are groups of samples, keyed by fluence bin x time bin (the cells of
//! [`super::eval`]) and, for the `within` statistic, also by illumination event. Each
//! cell's normalised residual is [`super::eval::group_stat_p95`]:
//! `z_c = (P95(measured) - P95(predicted + noise)) / sigma_c` (the predictions' 95th
//! percentile as a measurement would show it, [`super::data::noisy_quantile`]),
//! `sigma_c` from the measured spread of the cell (`--cell-statistic levels`). With
//! `--cell-statistic paired` (the default, [`super::eval::CellStatistic::Paired`]) it is
//! `z_c = (P95(measured - predicted) - P95(noise)) / sigma_c`, `sigma_c` from the spread
//! of the differences, and a score step's change of the cell's 95th percentile is taken
//! from the differences at the step, anew for each bootstrap replica. With
//! `--cell-statistic population` ([`super::eval::CellStatistic::Population`]) the
//! reference is the population's and follows the predictions: a step's change of the
//! cell also takes in the change of its reference (computed once per step, it does not
//! depend on the measurements).
//!
//! # Score (Lagrange-multiplier) test per library effect
//! For each registry effect not in the model, its switch parameter `theta` is moved from
//! the null value to its default (`h = default - null`, or a tenth of the way to the
//! farther bound when the default is the null: a finite-difference score in the
//! direction of the effect at its default strength; the derivative *at* the null is
//! degenerate for `soak`, whose fill fraction is flat at 0). `j_c = dz_c/dtheta =
//! -(P95_c(theta_0 + h) - P95_c(theta_0)) / (h sigma_c)`. With residual scale
//! `s^2 = r^T r / dof`, `LM = (j^T r)^2 / (s^2 j^T j)` (= `m R^2` of the regression of `r`
//! on `j`).
//!
//! One-sided where the null is a bound (`capacity`, `soak`, `temperature`, ...: the
//! effect can only be switched on in one direction): the residual sum of squares falls
//! for a step `t h` with `t > 0` only when `h j^T r < 0`; otherwise the score is 0 (the
//! Kuhn-Tucker score test for a parameter on the boundary). Without this, an effect whose
//! direction the data reject ranks high and its refit stays at the null (measured: the
//! two-sided score ranked `temperature` at 33-97 on baseline campaigns whose refits ended
//! at the null, delta BIC +5.1). An effect whose null lies inside its bounds keeps the
//! two-sided score. The bootstrap uses the same statistic.
//!
//! - `pooled`: `r` = the fluence x time cells, `dof = m`.
//! - `within` (default): cells split by illumination event; `r` and `j` are demeaned
//!   within each fluence x time group (a fixed effect per group), `dof = m - groups`.
//!   Why: the paper's model is misspecified against the trap-level truth *as a function
//!   of fluence and time* (its `A_k` are calibrated per fluence bin on one
//!   illumination, its `C_n` approximate `1/(t+1)` to ~8 %), which gives baseline
//!   normalised residuals of RMS 10-50 with nothing hidden. Any smooth effect correlates
//!   with that discrepancy, so the pooled score is far above any noise threshold on
//!   baseline data. The fixed effects absorb every discrepancy that is a function of
//!   (fluence, time) alone; what is left is how the residual changes *between
//!   illuminations* of different duration, flux, temperature and history, which is
//!   where soak, temperature, capacity and blooming differ from the baseline. The
//!   price: an effect that is a function of (fluence, time) only, with the same shape
//!   in every illumination, is not testable this way (it is indistinguishable from the
//!   calibration's own freedom); on single-illumination data `within` has no degrees of
//!   freedom and declares nothing.
//!
//! # Spread correlation
//! An effect whose switch parameter states how the pixels' spread is correlated between
//! neighbours (`populations`' `spread_corr`) changes no prediction, so its LM above is 0.
//! Its score is instead `max(T, 0)^2`, `T` the pairwise score of [`super::spread::score`]
//! on the samples and the model's predictions (one-sided: a correlation cannot be
//! negative), about chi-square(1) where positive under independent pixels, as an LM is.
//! The bootstrap below does not recompute it on each replica (the pair loop is too slow
//! for ~200 replicas); its replicas, independent samples, give it 0, so the family-wise
//! threshold leaves out its null. Measured on 20 replicas per campaign at 128 and 256
//! (measured with examples/diagnose_matrix): `T` mean -0.2 to 0.3, sd 0.64-1.18,
//! largest 2.4, against thresholds of 4 and more. Its refit measures the correlation
//! ([`crate::calib::effects`], "The pixels' spread correlation") and the refitted model's
//! cells are widened by it, in the change in BIC and the held-out check alike.
//!
//! # Threshold: parametric bootstrap from the fitted model
//! `B` replicas (`--bootstrap`, default [`DEFAULT_BOOTSTRAP`]) of the measured samples:
//! the fitted model's prediction plus Gaussian noise with the exposure's own noise
//! `sigma_k` ([`super::data`]); with the population statistic, plus the distribution
//! its reference assumes (the pixels' spread below the prediction and each sample's
//! shot noise, [`super::eval::Samples::null_of`]). On each replica the whole score computation is re-run:
//! the cells' measured P95, spread and `sigma_c` (hence `r` and `j`), the residual scale
//! `s^2`, and the LM of every effect. The threshold is the `1 - ALPHA` (95 %) point of
//! the largest LM over the library (a family-wise level over the library). It is the
//! score distribution when the fitted model is exactly true; it knows nothing of the
//! model discrepancy, which is why the gates below exist.
//!
//! # Refit, change in BIC, held-out check (the gates)
//! The [`REFIT`] leading candidates above the threshold are refitted ([`Refit`];
//! [`crate::calib::effects::fit`], fluence x time cells, per illumination with
//! `--cells illumination`, the default):
//! `delta_BIC = m ln(RSS_1/RSS_0) + k ln m`, `k` the candidate's parameters.
//!
//! # Refit
//! `--refit candidate` frees the candidate's parameters alone: the model's own
//! effects stay at the values fitted without it, so a missing effect that those effects
//! partly stood in for (the fitted `refill` leans on temperature's signature: `beta`
//! 0.90 without it, at its bound 1 with it) is judged with that help undone in
//! neither direction. `--refit full` (the default since the baseline declared nothing
//! with it at 10 of 10 seeds, measured with examples/diagnose_matrix, where every
//! earlier configuration gave 9 of 10) frees the candidate's parameters and those of the
//! model's own effects jointly, and `RSS_0` is then the model's own effects refitted
//! alone on the same samples (nested, so only the candidate's parameters count in
//! `k`); in the held-out check both are refitted on the fit half only. Measured (64 x
//! 64 campaign, seed 1, hidden `temperature`, reference refill + chord with the paired
//! cell statistic): candidate-only refits give `populations` (five parameters) a lower
//! BIC than `temperature` (-660 against -487), the full refit reverses it (-616 against
//! -963) and populations' held-out gain falls from 0.46 to 0.15.
//!
//! Held-out check: illumination events are split alternately into two halves (or
//! their pixels, below); the effect is fitted on one half and the normalised residual
//! RMS of the other half is compared with the model's, both ways;
//! `gain = 1 - RMS_after/RMS_before` over the pooled held-out cells.
//! The same gain over the held-out cells the candidate *moves* (its fitted effect
//! changes the cell's `z` by at least [`MOVED_Z`]) is reported as `gain_moved_cells`,
//! not gated: an effect confined to a few cells (the boost of the fast terms lives in
//! the first-dark cells of three fluence bins out of ~170) gains little over all cells
//! although it removes much of the residual where it acts. Gating on the moved cells
//! was measured (measured with examples/diagnose_matrix) and rejected: it declared
//! `short_tau_boost` hidden at one seed of three, but `blooming` in its place at the two
//! others, and `populations` on a baseline campaign (8 of 10 clean instead of 9).
//! Measured again on the second generator (examples/family_matrix, 64 x 64, seeds 1-5,
//! the moved cells counted only with at least 20 of them and every fold gaining
//! there): `capacity` on 2 of the 20 runs with nothing hidden, and `soak` on 8 of the
//! 10 runs with a hidden trap capacity.
//! Significant = `LM > threshold`, `delta_BIC <` [`DBIC_MAX`] and held-out
//! `gain >=` [`HELD_OUT_MIN_GAIN`]. With one illumination event the halves are its
//! sampled pixels, alternately in raster order (each half at least
//! [`MIN_HELD_OUT_PIXELS`]; with fewer the gate is not applied and the output says so):
//! an effect that only absorbs the misfit of the pixels it was fitted on does not
//! predict the others. The pixels are also the halves when the effect acts on an
//! event-level covariate ([`super::refit::EVENT_LEVEL`]: illumination duration,
//! temperature) and one half of the events lacks a value of it: a campaign with one
//! illumination at 78 K and one at 82 K would otherwise fit a temperature effect at
//! 78 K and 80 K and judge it only at 82 K, where any smooth term extrapolates.
//! Measured on the independent generator's single illumination with dark pixels and
//! nothing hidden (examples/family_matrix): without this gate
//! `ipc` was declared there.
//!
//! The ranking lists significant effects first (most negative `delta_BIC` first), then
//! the rest by score; `score_rank` keeps the order by score alone.
//!
//! # Joint check (`--joint`, off by default)
//! Two hidden effects can interact so that neither alone accounts for the residual:
//! the simulator's `soak` and `temperature` nearly cancel in its 82 K illumination
//! (examples/truth_ratios), and then the leading candidate's refit fails its gates
//! while the other effect scores nothing. With `--joint`, when no candidate is
//! significant alone, the leading candidate by score (the first refitted) is refitted
//! with each other library effect in turn, as in the single refits (same cells, same
//! `--refit`). Each pair gets `delta_BIC` against the model (both effects' parameters
//! counted) and against the leader alone (the partner's counted). The pair with the
//! lowest `delta_BIC` is held out (both effects fitted on one half of the events) when
//! both BIC changes are below [`DBIC_MAX`]; it is significant when its held-out gain is
//! at least [`HELD_OUT_MIN_GAIN`]. The verdict then names both and the command that
//! adds them. The pair is one candidate, tested once: no bootstrap covers it, which is
//! why it is asked for, not run by default.
//!
//! # Spatial coherence
//! The cells pool pixels from the whole array, so a misfit that varies across the array
//! in patches (trap populations) leaves them nearly as they are, and no library effect
//! carries a map. [`super::spatial`] asks the pixels instead: does a smoothed map of one
//! illumination's residual predict another's? The result is in the output (`spatial`)
//! and, when the field is there and no candidate is significant, the verdict names it
//! and where it is highest and lowest. It is an effect size with a measured threshold,
//! not part of the ranking, but it is a gate for the effects whose evidence is position
//! (`populations`): with two illumination events or more, such an effect is declared
//! only where the residuals carry a field (`refused_no_field` in the output otherwise;
//! `position_supported`). A position effect that explains residuals with no field
//! shared by neighbours is standing in for something else (radius and fluence go
//! together when the spot is centred).

use super::command::{fit_command, margin_note, measure_command};
pub use super::config::{Config, Decide, Refit, Statistic, DEFAULT_BOOTSTRAP, DEFAULT_PIXELS};
use super::contrast;
use super::data::Sequence;
use super::eval::{self, Samples};
pub use super::refit::{
    delta_bic, held_out, Fold, HeldOut, DBIC_MAX, HELD_OUT_MIN_GAIN, MIN_HELD_OUT_PIXELS, MOVED_Z,
};
use super::refit::{fit_candidate, held_with_arg, own_effects, refit_own};
pub use super::score::ALPHA;
use super::score::{dof, make_cells, score_step, score_tests, Cells, Scored, Test};
use super::spread;
use crate::error::{Error, ErrorKind, Result};
use crate::model::effects::REGISTRY;
use crate::model::params::ModelParams;
use rayon::prelude::*;
use serde::Serialize;
use std::path::Path;

/// Candidates refitted at most: the library effects acting on the covariates the base's
/// residual depends on, in the order of that dependence.
pub const REFIT: usize = 4;

/// Candidates refitted with [`Decide::Score`] (by score, above the threshold).
pub const REFIT_BY_SCORE: usize = 3;

/// Whether an effect whose evidence is in `covariate` may be declared given the
/// residuals' spatial coherence (module docs, "Spatial coherence"): an effect of
/// position only where the residuals carry a field shared by neighbouring pixels, or
/// where that cannot be measured (one illumination). Measured with examples/diagnose_matrix: with the spot centred, radius and fluence go together and the
/// model's `populations` (a quadratic surface, `u^2 + v^2` the radius) was declared for
/// a hidden linefit_bias + temperature at 128 x 128 (seeds 2 and 3) on residuals with
/// no field (R^2 0.04); the field it then put into the residuals had R^2 0.55-0.66.
fn position_supported(covariate: &str, spatial: Option<&super::spatial::Coherence>) -> bool {
    covariate != "position" || spatial.is_none_or(|c| c.coherent)
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
    /// What the flexible base's residual depends on, ranked ([`contrast::dependences`]).
    pub dependences: Vec<contrast::Dependence>,
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
    pub verdict: String,
    /// What limits the diagnosis of this model (empty when nothing is known to).
    pub cautions: Vec<String>,
}

/// The pixel reference's fit ([`super::base::predict_scaled`]): the flexible base with
/// each pixel's own amplitude and decay shape, its residuals against the noise
/// measured from the data (the exposure noise and the shot noise, less each sample's
/// leverage in its pixel's fit).
#[derive(Debug, Clone, Serialize)]
pub struct PixelReference {
    pub residual_rms_normalised: f64,
    pub cells: usize,
    /// Its three largest cell residuals.
    pub largest_residuals: Vec<eval::GroupStat>,
}

impl PixelReference {
    fn of(cells: &[(Vec<i64>, eval::GroupStat)]) -> PixelReference {
        let mut worst: Vec<eval::GroupStat> = cells.iter().map(|c| c.1).collect();
        worst.sort_by(|a, b| b.z.abs().total_cmp(&a.z.abs()));
        worst.truncate(3);
        PixelReference {
            residual_rms_normalised: eval::rms(cells),
            cells: cells.len(),
            largest_residuals: worst,
        }
    }
}

/// The fewest bootstrap replicas whose 95 % point is not simply their largest value.
pub const MIN_BOOTSTRAP: usize = 19;

/// The diagnosis of `params` against `seq` (module docs): score tests, the bootstrap
/// threshold, refits and held-out checks, the spatial check, the verdict. `input` and
/// `model_path` only name the files in the suggested commands. Refuses fewer than
/// [`MIN_BOOTSTRAP`] replicas and zero pixels, naming the option.
pub fn diagnose(
    params: &ModelParams,
    seq: &Sequence,
    cfg: &Config,
    input: &Path,
    model_path: &Path,
) -> Result<Diagnosis> {
    check_config(cfg)?;
    let samples = Samples::random(seq, cfg.pixels, cfg.seed)
        .with_cells(cfg.cells)
        .with_statistic(cfg.cell_statistic);
    let base = eval::predict(params, seq, &samples, false)?;
    let events = samples.events().len();
    let (statistic, statistic_reason) = cfg.statistic.resolve(events);
    let cells = make_cells(&samples, &base.current, statistic);
    enough_cells(&cells, statistic, events, input)?;
    let (contrasts, tests) = testable_tests(params, seq, &samples, cfg.decide);
    // what the flexible base's residual depends on, by permutation
    let flexible = super::base::predict(seq, &samples, &base.current);
    let pixel_reference = PixelReference::of(
        &super::base::predict_scaled(seq, &samples, &base.current).cells(&samples),
    );
    let dependences = contrast::dependences(seq, &samples, &flexible, &contrasts, cfg.seed);
    let winner = dependences.iter().find(|d| d.depends);
    let scored = score_tests(
        params,
        seq,
        &samples,
        &base.current,
        &cells,
        statistic,
        &tests,
        cfg.bootstrap,
        cfg.seed,
    )?;
    let names: Vec<&'static str> = tests.iter().map(|(def, ..)| def.name).collect();
    let mut ranking = candidates(&names, &scored, params, cfg, input, model_path);
    let refit = chosen_for_refit(cfg.decide, &dependences, &ranking);
    // with a full refit, the model's own effects refitted alone on these samples are
    // what each candidate is compared with
    let own = own_effects(params, cfg.refit);
    let own_refit = if refit.is_empty() {
        params.clone()
    } else {
        refit_own(params, &own, seq, &samples)?
    };
    let results = refit_candidates(
        &refit,
        &ranking,
        (params, &own_refit, &own),
        &base.current,
        seq,
        &samples,
        cfg.refit,
    )?;
    // the leader: the first refitted (`refit` in the order of the dependence, `results`
    // in its order)
    let leader = results.first().map(|r| (r.rank, r.rss_after));
    let spatial = super::spatial::coherence(seq, params)?;
    for r in results {
        let c = &mut ranking[r.rank];
        r.apply(c, spatial.as_ref());
    }
    // no candidate alone (and asked): the leader refitted with each other library effect
    let joint = match leader {
        Some((lead, lead_rss)) if cfg.joint && !ranking.iter().any(|c| c.significant) => {
            joint_check(
                &JointInput {
                    params,
                    base_current: &base.current,
                    own_refit: &own_refit,
                    own: &own,
                    seq,
                    samples: &samples,
                    cfg,
                    input,
                    model_path,
                    spatial: spatial.as_ref(),
                },
                &ranking[lead].effect,
                lead_rss,
                &names,
            )?
        }
        _ => Vec::new(),
    };
    // no library effect on the covariate the residual depends on predicts held-out
    // data: the data-driven term along it ([`super::data_term`])
    let data_term = match winner {
        Some(w)
            if cfg.decide == Decide::Contrast
                && !ranking.iter().any(|c| c.significant)
                && !joint.first().is_some_and(|j| j.significant) =>
        {
            super::data_term::offer(
                &w.class,
                params,
                &own_refit,
                &base.current,
                seq,
                &samples,
                cfg,
                (input, model_path),
            )?
        }
        _ => None,
    };
    order_ranking(&mut ranking, cfg.decide);
    let residual = spread::model_cell_z(params, &samples, &base.current);
    let rms = eval::rms(&residual);
    let mut largest: Vec<&(Vec<i64>, eval::GroupStat)> = residual.iter().collect();
    largest.sort_by(|a, b| b.1.z.abs().total_cmp(&a.1.z.abs()));
    largest.truncate(3);
    let where_cells: Vec<(f64, f64)> = largest
        .iter()
        .map(|(k, _)| eval::cell_fluence_time(k))
        .collect();
    let exposure_index = |a: usize| seq.exposures[a].meta.exposure_index;
    let where_illuminations: Vec<u64> = largest
        .iter()
        .filter_map(|(k, _)| eval::cell_illumination(k).map(exposure_index))
        .collect();
    let verdict = match ranking.iter().find(|c| c.significant) {
        None if joint.first().is_some_and(|j| j.significant) => joint_sentence(&joint[0], params),
        Some(c) => candidate_sentence(c, params),
        None if winner.is_some() && cfg.decide == Decide::Contrast => {
            let w = winner.expect("checked");
            dependence_sentence(w) + &data_term_sentence(data_term.as_ref(), &w.class, params)
        }
        None => format!(
            "no library effect is significant; the residual RMS is {rms:.2}, largest at: {}{}",
            largest_sentence(&largest, &where_cells, &exposure_index),
            field_sentence(spatial.as_ref())
        ),
    };
    Ok(Diagnosis {
        statistic,
        statistic_reason,
        contrasts,
        dependences,
        pixels_sampled: samples.npix(),
        samples: samples.len(),
        cells: cells.members.len(),
        groups: cells.n_groups,
        events,
        residual_cells: samples.cells,
        cell_statistic: samples.statistic,
        background: seq.background,
        refit: cfg.refit,
        residual_rms_normalised: rms,
        pixel_reference,
        bootstrap_replicas: cfg.bootstrap,
        threshold: scored.threshold,
        bootstrap_median_max: scored.median_max,
        ranking,
        largest_residuals: largest.iter().map(|(_, g)| *g).collect(),
        largest_residual_cells: where_cells,
        largest_residual_illuminations: where_illuminations,
        joint,
        spatial,
        data_term,
        verdict,
        cautions: cautions(params),
    })
}

/// Refuses fewer than [`MIN_BOOTSTRAP`] replicas and zero pixels, naming the option.
fn check_config(cfg: &Config) -> Result<()> {
    if cfg.bootstrap < MIN_BOOTSTRAP {
        return Err(Error::invalid(
            "--bootstrap",
            format!(
                "{}: at least {MIN_BOOTSTRAP} replicas (the threshold is the 95 % point of \
                 their largest scores; default {DEFAULT_BOOTSTRAP})",
                cfg.bootstrap
            ),
        ));
    }
    if cfg.pixels == 0 {
        return Err(Error::invalid("--pixels", "0: at least one pixel"));
    }
    Ok(())
}

/// Refuses cells too few for the score test's degrees of freedom, saying why when the
/// within statistic meets one illumination event.
fn enough_cells(cells: &Cells, statistic: Statistic, events: usize, input: &Path) -> Result<()> {
    let m = cells.members.len();
    if (m as f64) >= 3.0 + (m as f64 - dof(cells, statistic)) {
        return Ok(());
    }
    Err(Error::new(
        ErrorKind::Usage,
        format!(
            "{m} residual cells in {} groups: too few to test (statistic {:?}){}",
            cells.n_groups,
            statistic,
            if statistic == Statistic::Within && events < 2 {
                "; the within statistic compares illumination events and this input \
                 has one: use --statistic pooled"
            } else {
                ""
            }
        ),
    )
    .path(input))
}

/// Which contrast classes the data can test ([`super::contrast`]), and the library
/// effects the model does not have, each with its switch, null and score step, in
/// registry order: those of testable classes, or all of them with [`Decide::Score`].
/// The untestable ones are listed, not scored.
fn testable_tests(
    params: &ModelParams,
    seq: &Sequence,
    samples: &Samples,
    decide: Decide,
) -> (Vec<contrast::Testability>, Vec<Test>) {
    let library: Vec<Test> = REGISTRY
        .iter()
        .filter(|def| !params.effects.iter().any(|e| e.name == def.name))
        .filter_map(|def| {
            def.switch()
                .map(|(p, null)| (def, p, null, score_step(p, null)))
        })
        .collect();
    let contrasts = contrast::testability(
        seq,
        samples,
        &library
            .iter()
            .map(|(def, ..)| (def.name, def.covariate))
            .collect::<Vec<_>>(),
    );
    let testable = |def: &crate::model::effect::EffectDef| {
        let class = contrast::class_of(def.name, def.covariate);
        contrasts.iter().any(|c| c.class == class && c.testable)
    };
    let tests = library
        .into_iter()
        .filter(|t| decide == Decide::Score || testable(t.0))
        .collect();
    (contrasts, tests)
}

/// The tested effects as candidates, by score (highest first), with the commands that
/// add them; nothing refitted yet.
fn candidates(
    names: &[&'static str],
    scored: &Scored,
    params: &ModelParams,
    cfg: &Config,
    input: &Path,
    model_path: &Path,
) -> Vec<Candidate> {
    let lm = &scored.lm;
    let mut order: Vec<usize> = (0..names.len()).collect();
    order.sort_by(|&a, &b| lm[b].total_cmp(&lm[a]));
    order
        .iter()
        .enumerate()
        .map(|(rank, &i)| {
            let name = names[i];
            let def = crate::model::effects::lookup(name).expect("registered");
            Candidate {
                effect: name.to_string(),
                score: lm[i],
                score_rank: rank + 1,
                threshold: scored.threshold,
                passes_score: lm[i] > scored.threshold,
                delta_bic: None,
                rms_before: None,
                rms_after: None,
                held_out: None,
                significant: false,
                refused_no_field: false,
                covariate: def.covariate.into(),
                command: fit_command(input, model_path, params, &[name], cfg),
                measure_command: measure_command(input, model_path, params, &[name], cfg),
                measured_with: None,
            }
        })
        .collect()
}

/// The places in `ranking` of the candidates refitted (module docs, "Decision"): the
/// library effects acting on the covariates the base's residual depends on, in the
/// order of the dependence, or with [`Decide::Score`] the leaders above the threshold.
fn chosen_for_refit(
    decide: Decide,
    dependences: &[contrast::Dependence],
    ranking: &[Candidate],
) -> Vec<usize> {
    match decide {
        Decide::Contrast => dependences
            .iter()
            .filter(|d| d.refits())
            .flat_map(|d| &d.effects)
            .filter_map(|name| ranking.iter().position(|c| &c.effect == name))
            .take(REFIT)
            .collect(),
        Decide::Score => ranking
            .iter()
            .enumerate()
            .filter(|(_, c)| c.passes_score)
            .map(|(i, _)| i)
            .take(REFIT_BY_SCORE)
            .collect(),
    }
}

/// Each chosen candidate refitted (in parallel, each fit its own computation) from
/// `own_refit` (the model with `own`, its effects freed, refitted alone), and held out
/// when its change in BIC passes. `model.0` is the model diagnosed.
fn refit_candidates(
    chosen: &[usize],
    ranking: &[Candidate],
    model: (&ModelParams, &ModelParams, &[String]),
    base_current: &[f64],
    seq: &Sequence,
    samples: &Samples,
    refit: Refit,
) -> Result<Vec<Refitted>> {
    let (params, own_refit, own) = model;
    chosen
        .par_iter()
        .map(|&i| {
            let name = &ranking[i].effect;
            let (fitted, f) = fit_candidate(own_refit, own, None, &[name], seq, samples)?;
            let (rss0, rss1) = f.rss_before_after();
            // the candidate's parameters are the ones added
            let k = f.params.iter().filter(|p| &p.effect == name).count();
            let dbic = delta_bic(rss0, rss1, k, f.cells);
            let ho = if dbic < DBIC_MAX {
                held_out(
                    params,
                    base_current,
                    Some(&fitted),
                    &[name],
                    seq,
                    samples,
                    refit,
                )?
            } else {
                None
            };
            Ok(Refitted {
                rank: i,
                delta_bic: dbic,
                rms_before: f.residual_rms_normalised_before,
                rms_after: f.residual_rms_normalised_after,
                held_out: ho,
                rss_after: rss1,
                measured_with: held_with_arg(&fitted, name),
            })
        })
        .collect()
}

/// Significant ones first, by the best held-out prediction (the lowest dBIC with the
/// score decision, or without a held-out check); the rest by score.
fn order_ranking(ranking: &mut [Candidate], decide: Decide) {
    ranking.sort_by(|a, b| match (a.significant, b.significant) {
        (true, true) => match (&a.held_out, &b.held_out) {
            (Some(x), Some(y)) if decide == Decide::Contrast => y.gain.total_cmp(&x.gain),
            _ => a
                .delta_bic
                .unwrap_or(0.0)
                .total_cmp(&b.delta_bic.unwrap_or(0.0)),
        },
        (true, false) => std::cmp::Ordering::Less,
        (false, true) => std::cmp::Ordering::Greater,
        (false, false) => b.score.total_cmp(&a.score),
    });
}

/// The verdict on a significant pair of the joint check.
fn joint_sentence(j: &Joint, params: &ModelParams) -> String {
    format!(
        "no library effect is significant alone, but {} and {} are together \
         (dBIC {:.1} against the model, {:.1} against {} alone; held-out gain {:.2}): \
         neither accounts for the residual without the other, so they act \
         together; add both with: {}{}",
        j.effects[0],
        j.effects[1],
        j.delta_bic,
        j.delta_bic_over_leader,
        j.effects[0],
        j.held_out.as_ref().map_or(f64::NAN, |h| h.gain),
        j.command,
        margin_note(j.measure_command.as_deref(), params)
    )
}

/// The verdict on a significant candidate.
fn candidate_sentence(c: &Candidate, params: &ModelParams) -> String {
    format!(
        "missing effect: {} (the evidence is in the residual against {}{}); add it with: {}{}",
        c.effect,
        c.covariate,
        if c.held_out.is_none() {
            "; no held-out check: too few sampled pixels to split into halves"
        } else {
            ""
        },
        c.command,
        margin_note(c.measure_command.as_deref(), params)
    )
}

/// The verdict when the residual depends on `w`'s covariate and no library effect on
/// it predicts held-out data.
fn dependence_sentence(w: &contrast::Dependence) -> String {
    format!(
        "the base's residual depends on {} (it explains {:.1} % of the residual's sum \
         of squares inside the fluence x time cells, {:.1} % at most over {} \
         permutations; z {:.1}), but no library effect acting on it ({}) predicts \
         held-out data: the missing physics is of this kind in another form. The \
         residual by {}: {}",
        w.class,
        100.0 * w.r2,
        100.0 * w.r2_null_max,
        w.permutations,
        w.z,
        w.effects.join(", "),
        w.class,
        w.by_bin
            .iter()
            .map(|(b, n, e)| format!("{b}: {e:+.2} ({n} pixel-events)"))
            .collect::<Vec<_>>()
            .join("; ")
    )
}

/// Where the largest cell residuals are, for the verdict with nothing found.
fn largest_sentence(
    largest: &[&(Vec<i64>, eval::GroupStat)],
    where_cells: &[(f64, f64)],
    exposure_index: &dyn Fn(usize) -> u64,
) -> String {
    let w: Vec<String> = largest
        .iter()
        .zip(where_cells)
        .map(|((k, g), (f, t))| {
            let mut after = eval::cell_illumination(k).map_or(String::new(), |a| {
                format!(" after the illumination at exposure {}", exposure_index(a))
            });
            if eval::cell_next_to_brighter(k) {
                after.push_str(", next to a far brighter pixel");
            }
            format!(
                "fluence >= {f:.3e} e-, t >= {t:.0} s{after}: measured {:.3} vs predicted {:.3} e-/s (z {:.1})",
                g.measured_p95_e_per_s, g.predicted_p95_e_per_s, g.z
            )
        })
        .collect();
    w.join("; ")
}

/// The verdict's clause on a field shared by neighbouring pixels, empty without one.
fn field_sentence(spatial: Option<&super::spatial::Coherence>) -> String {
    spatial.filter(|c| c.coherent).map_or(String::new(), |c| {
        format!(
            "; and the residuals carry a field shared by neighbouring pixels: a {:.0}-pixel \
             map of one illumination's residual predicts {:.0} % of another's (R^2; \
             threshold {:.2}), so the trap density varies across the array in patches, \
             which no library effect carries (the model's populations is a quadratic \
             surface over the whole array){}",
            c.best_length_px,
            100.0 * c.best_r2,
            c.threshold,
            match (c.highest, c.lowest) {
                (Some(((y, x), hi)), Some(((y0, x0), lo))) => format!(
                    "; measured against predicted, x{hi:.2} around (y {y}, x {x}) and \
                     x{lo:.2} around (y {y0}, x {x0}) (the map averaged over the \
                     illuminations, relative to its fluence bin)"
                ),
                _ => String::new(),
            }
        )
    })
}

/// The verdict's sentence on the data-driven term: offered with its command, or why not.
/// `class`: the covariate's class.
fn data_term_sentence(
    t: Option<&super::data_term::DataTerm>,
    class: &str,
    params: &ModelParams,
) -> String {
    let Some(t) = t else {
        return match super::data_term::held(class, params) {
            Some(d) => format!(
                ". The model already holds the data-driven term along it ({}): the \
                 residual it leaves still depends on this covariate",
                d.name
            ),
            None => ". No data-driven term follows this covariate".into(),
        };
    };
    let gain = t
        .held_out
        .as_ref()
        .map_or("no held-out check".to_string(), |h| {
            format!("held-out gain {:.2}", h.gain)
        });
    if t.offered {
        format!(
            ". A data-driven term along it ({}: a smooth function of the covariate fitted \
             from these data) lowers the residual RMS from {:.2} to {:.2} (dBIC {:.1}, {gain}); \
             add it with: {}{}",
            t.effect,
            t.rms_before,
            t.rms_after,
            t.delta_bic,
            t.command,
            margin_note(t.measure_command.as_deref(), params)
        )
    } else {
        format!(
            ". A data-driven term along it ({}) does not predict held-out data either \
             (dBIC {:.1}, {gain}): not offered",
            t.effect, t.delta_bic
        )
    }
}

/// One candidate's refit: its place in the ranking (by score) and what the refit gave.
struct Refitted {
    rank: usize,
    delta_bic: f64,
    rms_before: f64,
    rms_after: f64,
    held_out: Option<HeldOut>,
    /// Its sum of squared normalised residuals after the fit (the joint check's
    /// baseline for the leader).
    rss_after: f64,
    /// [`Candidate::measured_with`].
    measured_with: Option<String>,
}

impl Refitted {
    /// The refit's results in its candidate `c`, and the gates: the change in BIC, the
    /// held-out check where there is one, and for a position effect the field.
    fn apply(self, c: &mut Candidate, spatial: Option<&super::spatial::Coherence>) {
        c.delta_bic = Some(self.delta_bic);
        c.rms_before = Some(self.rms_before);
        c.rms_after = Some(self.rms_after);
        let gates = self.delta_bic < DBIC_MAX && self.held_out.as_ref().is_none_or(|h| h.passes);
        c.refused_no_field = gates && !position_supported(&c.covariate, spatial);
        c.significant = gates && !c.refused_no_field;
        c.held_out = self.held_out;
        c.measured_with = self.measured_with;
    }
}

/// What the joint check shares with the single refits.
struct JointInput<'a> {
    params: &'a ModelParams,
    base_current: &'a [f64],
    own_refit: &'a ModelParams,
    own: &'a [String],
    seq: &'a Sequence,
    samples: &'a Samples,
    cfg: &'a Config,
    input: &'a Path,
    model_path: &'a Path,
    spatial: Option<&'a super::spatial::Coherence>,
}

/// The joint check (module docs, "Joint check"): `leader` (the top-scored candidate,
/// refitted alone to `leader_rss`) refitted with each other effect of `names`; the
/// pairs sorted by their change in BIC, the best one held out.
fn joint_check(
    j: &JointInput<'_>,
    leader: &str,
    leader_rss: f64,
    names: &[&'static str],
) -> Result<Vec<Joint>> {
    let partners: Vec<&str> = names.iter().copied().filter(|n| *n != leader).collect();
    let mut fits: Vec<(Joint, ModelParams)> = partners
        .par_iter()
        .map(|&other| {
            let pair = [leader, other];
            let (fitted, f) = fit_candidate(j.own_refit, j.own, None, &pair, j.seq, j.samples)?;
            let (rss0, rss1) = f.rss_before_after();
            let k_pair = f
                .params
                .iter()
                .filter(|p| pair.contains(&p.effect.as_str()))
                .count();
            let k_other = f.params.iter().filter(|p| p.effect == other).count();
            Ok((
                Joint {
                    effects: [leader.to_string(), other.to_string()],
                    delta_bic: delta_bic(rss0, rss1, k_pair, f.cells),
                    delta_bic_over_leader: delta_bic(leader_rss, rss1, k_other, f.cells),
                    rms_before: f.residual_rms_normalised_before,
                    rms_after: f.residual_rms_normalised_after,
                    held_out: None,
                    significant: false,
                    command: fit_command(j.input, j.model_path, j.params, &pair, j.cfg),
                    measure_command: measure_command(j.input, j.model_path, j.params, &pair, j.cfg),
                },
                fitted,
            ))
        })
        .collect::<Result<_>>()?;
    fits.sort_by(|a, b| a.0.delta_bic.total_cmp(&b.0.delta_bic));
    if let Some((best, fitted)) = fits.first_mut() {
        if best.delta_bic < DBIC_MAX && best.delta_bic_over_leader < DBIC_MAX {
            let pair = [best.effects[0].as_str(), best.effects[1].as_str()];
            best.held_out = held_out(
                j.params,
                j.base_current,
                Some(fitted),
                &pair,
                j.seq,
                j.samples,
                j.cfg.refit,
            )?;
            best.significant = best.held_out.as_ref().is_none_or(|h| h.passes)
                && pair.iter().all(|e| {
                    crate::model::effects::lookup(e)
                        .is_none_or(|d| position_supported(d.covariate, j.spatial))
                });
        }
    }
    Ok(fits.into_iter().map(|(joint, _)| joint).collect())
}

/// What is known to limit a diagnosis against `params`.
fn cautions(params: &ModelParams) -> Vec<String> {
    let mut c = Vec::new();
    if crate::calib::cn_fitted_to_campaign(params) {
        c.push(
            "the model's C_n were fitted to this campaign (persist fit --fit-cn): they have \
             taken in the decay-shape part of any missing effect (a hidden short_tau_boost \
             was found at 3 of 3 seeds against a model without --fit-cn, at none with it \
             before the capacity fix; docs/validation/diagnose_matrix.md); diagnose against a model \
             fitted without --fit-cn too"
                .to_string(),
        );
    }
    if crate::calib::level_fitted_to_campaign(params) {
        c.push(
            "the model's knot level was fitted to this campaign (persist fit \
             --fit-amplification): it has taken in the level part of any missing effect (a \
             hidden short_tau_boost was declared at 1 of 3 seeds against such a model, at 3 \
             of 3 with the level fixed; measured with examples/diagnose_matrix); diagnose \
             against a model with a fixed --amplification too"
                .to_string(),
        );
    }
    c
}

/// The printed ranking.
pub fn render(d: &Diagnosis) -> String {
    let mut s = format!(
        "persist diagnose: statistic {}, {} pixels, {} cells in {} groups, {} illumination events, \
         residual RMS {:.2} ({} cells{}{})\npixel reference (the flexible base with each pixel's own \
         amplitude and decay shape): residual RMS {:.2} over {} cells\nthreshold {:.2} (95 % of the largest score over {} bootstrap replicas \
         from the fitted model; median {:.2}; the score ranks, it does not decide)\n\
         {:<16} {:>10} {:>6} {:>9} {:>15} {:>9} {:>15}  covariate\n",
        d.statistic_reason,
        d.pixels_sampled,
        d.cells,
        d.groups,
        d.events,
        d.residual_rms_normalised,
        d.residual_cells.describe(),
        d.cell_statistic.note(),
        match d.refit {
            Refit::Full => "; candidates refitted with the model's own effects (--refit full)",
            Refit::Candidate => "; candidates refitted alone (--refit candidate)",
        },
        d.pixel_reference.residual_rms_normalised,
        d.pixel_reference.cells,
        d.threshold,
        d.bootstrap_replicas,
        d.bootstrap_median_max,
        "effect",
        "score",
        "pass",
        "dBIC",
        "RMS",
        "held-out",
        "(moved cells)"
    );
    for c in &d.ranking {
        s += &format!(
            "{:<16} {:>10.2} {:>6} {:>9} {:>15} {:>9} {:>15}  {}{}\n",
            c.effect,
            c.score,
            c.passes_score,
            c.delta_bic.map_or("-".into(), |v| format!("{v:.1}")),
            match (c.rms_before, c.rms_after) {
                (Some(a), Some(b)) => format!("{a:.2}->{b:.2}"),
                _ => "-".into(),
            },
            c.held_out
                .as_ref()
                .map_or("-".into(), |h| format!("{:+.0}%", -100.0 * h.gain)),
            c.held_out.as_ref().map_or("-".into(), |h| format!(
                "{:+.0}% of {}",
                -100.0 * h.gain_moved_cells,
                h.moved_cells
            )),
            c.covariate,
            if c.significant {
                "  SIGNIFICANT"
            } else if c.refused_no_field {
                "  (passes the gates, but the residuals carry no field shared by neighbours)"
            } else {
                ""
            }
        );
    }
    for c in d.contrasts.iter().filter(|c| !c.testable) {
        s += &format!(
            "{:<16} untestable, needs {} ({})\n",
            c.effects.join(", "),
            c.needs.as_deref().unwrap_or("-"),
            c.why
        );
    }
    if !d.dependences.is_empty() {
        s += "what the base's residual depends on (share of its sum of squares inside the \
              fluence x time cells; permutations' largest; z):\n";
        for x in &d.dependences {
            s += &format!(
                "  {:<26} {:>6.2} % {:>6.2} % {:>7.1}  {}{}\n",
                x.class,
                100.0 * x.r2,
                100.0 * x.r2_null_max,
                x.z,
                x.effects.join(", "),
                if x.depends { "  DEPENDS" } else { "" }
            );
        }
    }
    if !d.joint.is_empty() {
        s += "joint check (no effect significant alone; the leader refitted with each other):\n";
        for j in &d.joint {
            s += &format!(
                "{:<32} {:>9.1} {:>9.1} {:>15} {:>9}{}\n",
                format!("{} + {}", j.effects[0], j.effects[1]),
                j.delta_bic,
                j.delta_bic_over_leader,
                format!("{:.2}->{:.2}", j.rms_before, j.rms_after),
                j.held_out
                    .as_ref()
                    .map_or("-".into(), |h| format!("{:+.0}%", -100.0 * h.gain)),
                if j.significant { "  SIGNIFICANT" } else { "" }
            );
        }
    }
    if let Some(c) = &d.spatial {
        s += &format!(
            "spatial coherence: a map of one illumination's residual smoothed over {} px \
             predicts R^2 {} of another's (unsmoothed {:.2}; {} pairs, {} pixels per \
             illumination): {}\n",
            c.r2_smoothed
                .iter()
                .map(|(l, _)| format!("{l:.0}"))
                .collect::<Vec<_>>()
                .join("/"),
            c.r2_smoothed
                .iter()
                .map(|(_, r)| format!("{r:.2}"))
                .collect::<Vec<_>>()
                .join("/"),
            c.r2_raw,
            c.pairs,
            c.pixels_per_event,
            if c.coherent {
                format!("a field shared by neighbours (>= {:.2})", c.threshold)
            } else {
                format!("none shared by neighbours (< {:.2})", c.threshold)
            }
        );
    }
    s += &d.verdict;
    for c in &d.cautions {
        s += "\ncaution: ";
        s += c;
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A model whose `C_n` `persist fit --fit-cn` fitted carries a caution; the same
    /// model without the mark does not.
    #[test]
    fn a_model_with_c_n_fitted_to_the_campaign_is_cautioned() {
        let mut p = ModelParams::default();
        assert!(cautions(&p).is_empty());
        p.description += crate::calib::FIT_CN_NOTE;
        let c = cautions(&p);
        assert_eq!(c.len(), 1);
        assert!(c[0].contains("--fit-cn"), "{c:?}");
    }

    /// The same for a knot level fitted by `persist fit --fit-amplification`.
    #[test]
    fn a_model_with_its_level_fitted_to_the_campaign_is_cautioned() {
        let mut p = ModelParams::default();
        p.description += &format!(
            "{}0.7236 (--fit-amplification: amplification 0.8683)",
            crate::calib::FIT_AMPLIFICATION_NOTE
        );
        let c = cautions(&p);
        assert_eq!(c.len(), 1);
        assert!(c[0].contains("--fit-amplification"), "{c:?}");
    }

    /// A position effect needs the field; other effects and one illumination (no
    /// spatial check) are not gated.
    #[test]
    fn position_effects_need_a_field_shared_by_neighbours() {
        let c = |coherent: bool| super::super::spatial::Coherence {
            events: 5,
            pairs: 20,
            pixels_per_event: 100,
            r2_raw: 0.7,
            r2_smoothed: vec![(4.0, if coherent { 0.5 } else { 0.05 })],
            best_length_px: 4.0,
            best_r2: if coherent { 0.5 } else { 0.05 },
            threshold: 0.2,
            coherent,
            highest: None,
            lowest: None,
            field: super::super::spatial::FieldMap::of(&ndarray::Array2::zeros((2, 2))),
        };
        let pop = crate::model::effects::lookup("populations")
            .unwrap()
            .covariate;
        assert_eq!(pop, "position");
        assert!(position_supported(pop, Some(&c(true))));
        assert!(!position_supported(pop, Some(&c(false))));
        assert!(position_supported(pop, None));
        assert!(position_supported("temperature", Some(&c(false))));
    }
}
