//! The score test ([`super::diagnose`] module docs, "Score test"): cells of the
//! sampled residuals, the step of each library effect's switch, the one-sided LM
//! score, and its threshold from a parametric bootstrap of the fitted model.
//!
//! Invariant: the bootstrap's replicas are drawn in order from one seeded stream, so
//! the threshold does not depend on how many are scored at once.

use super::config::Statistic;
use super::data::{noisy_quantile, quantile, quantile_in_place, Sequence};
use super::eval::{self, Samples};
use super::spread;
use crate::error::Result;
use crate::model::params::{EffectSpec, ModelParams};
use crate::stats::median;
use rand::{Rng, SeedableRng};
use rand_distr::StandardNormal;
use rayon::prelude::*;
use std::collections::BTreeMap;

/// Family-wise false-alarm level of the score threshold.
pub const ALPHA: f64 = 0.05;

/// Bootstrap replicas drawn before they are scored in parallel (memory: this many
/// copies of the samples).
const BOOT_BATCH: usize = 8;

/// The finite-difference step of the score test for an effect's switch parameter `p`
/// (null value `null`): to its default strength when that differs from the null;
/// otherwise (effects whose default is "off", such as `populations`) a tenth of the way
/// to the farther bound, so that the step is not degenerate. The score is the same for
/// either sign of the step.
pub(super) fn score_step(p: &crate::model::effect::ParamSpec, null: f64) -> f64 {
    if p.default != null {
        return p.default - null;
    }
    let (up, down) = (p.hi - null, p.lo - null);
    let h = 0.1 * if up.abs() >= down.abs() { up } else { down };
    if h != 0.0 && h.is_finite() {
        h
    } else {
        1e-2 * null.abs().max(1e-12)
    }
}

/// Cells of the score test: sample indices per cell, the cell's noise, its group.
pub(super) struct Cells {
    pub(super) members: Vec<Vec<usize>>,
    /// Per member, the standard deviation of its measured minus predicted current under
    /// the fitted model ([`Samples::null_of`]: its exposure's noise but with the
    /// population statistic), e-/s.
    sigma: Vec<Vec<f64>>,
    /// Per member, the mean of the same (0 but with the population statistic), e-/s.
    offset: Vec<Vec<f64>>,
    /// Per cell, the median of the members' measurement noise.
    noise: Vec<f64>,
    group: Vec<usize>,
    pub(super) n_groups: usize,
}

pub(super) fn make_cells(s: &Samples, pred: &[f64], st: Statistic) -> Cells {
    let keys: &[&str] = match st {
        // `auto` is resolved before the cells are made
        Statistic::Pooled | Statistic::Auto => &["fluence", "time"],
        Statistic::Within => &["fluence", "time", "event"],
    };
    let mut g: BTreeMap<Vec<i64>, Vec<usize>> = BTreeMap::new();
    'samples: for (i, p) in pred.iter().enumerate().take(s.len()) {
        if !s.measured[i].is_finite() || !p.is_finite() {
            continue;
        }
        let mut key = Vec::with_capacity(keys.len());
        for k in keys {
            match eval::bin_of(s, k, i) {
                Some(b) => key.push(b),
                None => continue 'samples,
            }
        }
        g.entry(key).or_default().push(i);
    }
    let mut groups: BTreeMap<Vec<i64>, usize> = BTreeMap::new();
    let mut c = Cells {
        members: Vec::new(),
        sigma: Vec::new(),
        offset: Vec::new(),
        noise: Vec::new(),
        group: Vec::new(),
        n_groups: 0,
    };
    for (k, idx) in g {
        if idx.len() < 10 {
            continue;
        }
        let n = groups.len();
        let gi = *groups.entry(k[..2].to_vec()).or_insert(n);
        let (mut offset, mut sd, mut noise) = (Vec::new(), Vec::new(), Vec::new());
        for &i in &idx {
            let (o, d, n) = s.null_of(i, pred[i]);
            offset.push(o);
            sd.push(d);
            noise.push(n);
        }
        c.noise.push(median(&noise));
        c.sigma.push(sd);
        c.offset.push(offset);
        c.members.push(idx);
        c.group.push(gi);
    }
    c.n_groups = groups.len();
    c
}

/// Per cell, the 95th percentile of a measurement of the predictions (eval module docs).
fn p95s(c: &Cells, pred: &[f64]) -> Vec<f64> {
    c.members
        .iter()
        .zip(&c.sigma)
        .map(|(idx, sg)| {
            let p: Vec<f64> = idx.iter().map(|&i| pred[i]).collect();
            noisy_quantile(&p, sg, 0.95).0
        })
        .collect()
}

/// How the score test sees the cells under the samples' [`eval::CellStatistic`]:
/// what the fitted model predicts, and where each library effect's score step takes
/// the prediction.
enum Steps<'a> {
    /// Per cell the predicted 95th percentile; per effect and cell its derivative
    /// `d P95_c / d theta`.
    Levels { pp0: Vec<f64>, dp: Vec<Vec<f64>> },
    /// The predictions per sample; per cell the reference, the 95th percentile of the
    /// noise alone (of the population's null with the population statistic); per
    /// effect its step `h` and the predictions per sample at the step. The step's
    /// change of `P95(measured - predicted)` depends on the measurements, so it is
    /// taken anew for each set of them.
    Paired {
        pred0: &'a [f64],
        noise_p95: Vec<f64>,
        at_step: Vec<(f64, Vec<f64>)>,
        /// Per effect and cell, whether the step changes any of the cell's predictions
        /// (where it does not, the cell's derivative is 0 whatever the measurements).
        moved: Vec<Vec<bool>>,
        /// Per effect and cell, the change of the reference at the step (0 but with the
        /// population statistic, whose reference follows the predictions).
        ref_shift: Vec<Vec<f64>>,
    },
}

impl<'a> Steps<'a> {
    /// [`Steps::Paired`] for cells `c`: the reference and what each step moves, per
    /// cell. `population`: the samples when their statistic is
    /// [`eval::CellStatistic::Population`] (whose reference follows the predictions).
    fn paired(
        c: &Cells,
        pred0: &'a [f64],
        at_step: Vec<(f64, Vec<f64>)>,
        population: Option<&Samples>,
    ) -> Self {
        let noise_p95: Vec<f64> = c
            .offset
            .iter()
            .zip(&c.sigma)
            .map(|(o, sg)| noisy_quantile(o, sg, 0.95).0)
            .collect();
        let moved: Vec<Vec<bool>> = at_step
            .iter()
            .map(|(_, pred)| {
                c.members
                    .iter()
                    .map(|idx| idx.iter().any(|&i| pred[i].to_bits() != pred0[i].to_bits()))
                    .collect()
            })
            .collect();
        let ref_shift = at_step
            .iter()
            .zip(&moved)
            .map(|((_, pred), moved)| {
                c.members
                    .iter()
                    .zip(moved)
                    .zip(&noise_p95)
                    .map(|((idx, &moved), r0)| {
                        let Some(s) = population.filter(|_| moved) else {
                            return 0.0;
                        };
                        let (o, sg): (Vec<f64>, Vec<f64>) = idx
                            .iter()
                            .map(|&i| {
                                let (o, sd, _) = s.null_of(i, pred[i]);
                                (o, sd)
                            })
                            .unzip();
                        noisy_quantile(&o, &sg, 0.95).0 - r0
                    })
                    .collect()
            })
            .collect();
        Steps::Paired {
            pred0,
            noise_p95,
            moved,
            ref_shift,
            at_step,
        }
    }

    /// For measurements `y`: per cell `z` and `sigma`, and per effect and cell the
    /// derivative of the cell's compared 95th percentile with the sign of a predicted
    /// one (`dz_c / d theta = -dp_c / sigma_c`).
    fn linearise<'s>(
        &'s self,
        c: &Cells,
        y: &[f64],
    ) -> (Vec<f64>, Vec<f64>, std::borrow::Cow<'s, [Vec<f64>]>) {
        let m = c.members.len();
        let (mut z, mut sg) = (Vec::with_capacity(m), Vec::with_capacity(m));
        let mut buf = Vec::new();
        match self {
            Steps::Levels { pp0, dp } => {
                for (k, idx) in c.members.iter().enumerate() {
                    buf.clear();
                    buf.extend(idx.iter().map(|&i| y[i]));
                    let g = eval::group_stat_p95(&buf, pp0[k], c.noise[k]).expect(">= 10 members");
                    z.push(g.z);
                    sg.push(g.sigma_e_per_s);
                }
                (z, sg, std::borrow::Cow::Borrowed(dp.as_slice()))
            }
            Steps::Paired {
                pred0,
                noise_p95,
                at_step,
                moved,
                ref_shift,
            } => {
                let mut p0 = Vec::with_capacity(m);
                for (k, idx) in c.members.iter().enumerate() {
                    buf.clear();
                    buf.extend(idx.iter().map(|&i| y[i] - pred0[i]));
                    let (p, sigma, zk) = eval::paired_z(&buf, c.noise[k], noise_p95[k]);
                    z.push(zk);
                    sg.push(sigma);
                    p0.push(p);
                }
                let dp = at_step
                    .iter()
                    .zip(moved)
                    .zip(ref_shift)
                    .map(|(((h, pred), moved), shift)| {
                        c.members
                            .iter()
                            .zip(&p0)
                            .zip(moved)
                            .zip(shift)
                            .map(|(((idx, p), moved), shift)| {
                                if !moved {
                                    // the same residuals: the same percentile as `p`
                                    return -0.0 / h;
                                }
                                if idx.iter().any(|&i| !pred[i].is_finite()) {
                                    // not comparable with the base's cell: no direction
                                    return 0.0;
                                }
                                buf.clear();
                                buf.extend(idx.iter().map(|&i| y[i] - pred[i]));
                                // the change of `z`'s numerator, with the sign of a
                                // predicted percentile
                                -((quantile_in_place(&mut buf, 0.95) - p) - shift) / h
                            })
                            .collect()
                    })
                    .collect();
                (z, sg, std::borrow::Cow::Owned(dp))
            }
        }
    }
}

/// Demean within groups (the `within` statistic); identity for `pooled`.
fn project(c: &Cells, v: &[f64], st: Statistic) -> Vec<f64> {
    if st != Statistic::Within {
        return v.to_vec();
    }
    let mut sum = vec![0.0; c.n_groups];
    let mut n = vec![0usize; c.n_groups];
    for (k, x) in v.iter().enumerate() {
        sum[c.group[k]] += x;
        n[c.group[k]] += 1;
    }
    v.iter()
        .enumerate()
        .map(|(k, x)| x - sum[c.group[k]] / n[c.group[k]] as f64)
        .collect()
}

pub(super) fn dof(c: &Cells, st: Statistic) -> f64 {
    match st {
        Statistic::Pooled | Statistic::Auto => c.members.len() as f64,
        Statistic::Within => (c.members.len() as f64 - c.n_groups as f64).max(1.0),
    }
}

/// The direction in which a score test's parameter may move from its null: the sign of
/// its step when the null is one of its bounds, None (either) when it is inside.
fn one_sided(p: &crate::model::effect::ParamSpec, null: f64, h: f64) -> Option<f64> {
    (null <= p.lo || null >= p.hi).then_some(h.signum())
}

/// Whether `def` with its switch `p` at `value` (its other parameters at their
/// defaults) states a spread correlation ([`crate::model::effect::Effect::spread_correlation`]).
fn states_spread(
    def: &crate::model::effect::EffectDef,
    p: &crate::model::effect::ParamSpec,
    value: f64,
) -> bool {
    let mut map = serde_json::Map::new();
    map.insert(p.name.into(), serde_json::json!(value));
    crate::model::effects::build(&EffectSpec {
        params: map,
        ..EffectSpec::named(def.name)
    })
    .is_ok_and(|e| e.spread_correlation().is_some())
}

/// The largest LM of each of `b` parametric bootstrap replicas: measurements drawn
/// as `pred` plus each member's Gaussian null (`c.offset`, `c.sigma`), in order from `rng`, and
/// scored in parallel `batch` replicas at a time (the same maxima whatever `batch`).
#[allow(clippy::too_many_arguments)]
fn bootstrap_maxima(
    c: &Cells,
    pred: &[f64],
    steps: &Steps,
    dirs: &[Option<f64>],
    st: Statistic,
    b: usize,
    rng: &mut impl Rng,
    batch: usize,
) -> Vec<f64> {
    let mut maxes: Vec<f64> = Vec::with_capacity(b);
    let mut ys: Vec<Vec<f64>> = Vec::new();
    while maxes.len() < b {
        ys.resize_with(batch.max(1).min(b - maxes.len()), || {
            vec![f64::NAN; pred.len()]
        });
        for y in &mut ys {
            for ((idx, sg), of) in c.members.iter().zip(&c.sigma).zip(&c.offset) {
                for ((&i, sd), o) in idx.iter().zip(sg).zip(of) {
                    y[i] = pred[i] + o + sd * rng.sample::<f64, _>(StandardNormal);
                }
            }
        }
        maxes.par_extend(ys.par_iter().map(|y| {
            scores(c, y, steps, dirs, st)
                .into_iter()
                .fold(0.0, f64::max)
        }));
    }
    maxes
}

/// LM of every effect for measurements `y` (module docs); `dirs[i]` the allowed sign of
/// effect `i`'s step (per unit of its parameter) or None when both are.
fn scores(c: &Cells, y: &[f64], steps: &Steps, dirs: &[Option<f64>], st: Statistic) -> Vec<f64> {
    let (z, sg, dp) = steps.linearise(c, y);
    let r = project(c, &z, st);
    let s2 = r.iter().map(|v| v * v).sum::<f64>() / dof(c, st);
    dp.iter()
        .zip(dirs)
        .map(|(d, dir)| {
            let j: Vec<f64> = d.iter().zip(&sg).map(|(a, s)| -a / s).collect();
            let j = project(c, &j, st);
            let jr: f64 = j.iter().zip(&r).map(|(a, b)| a * b).sum();
            let jj: f64 = j.iter().map(|a| a * a).sum();
            // the residual falls along `dir` only if `dir * j^T r < 0`
            let allowed = dir.is_none_or(|sgn| sgn * jr < 0.0);
            if allowed && jj > 0.0 && s2 > 0.0 {
                jr * jr / (s2 * jj)
            } else {
                0.0
            }
        })
        .collect()
}

/// One library effect under test: its definition, its switch parameter, the switch's
/// null value and the score step ([`score_step`]).
pub(super) type Test = (
    &'static crate::model::effect::EffectDef,
    &'static crate::model::effect::ParamSpec,
    f64,
    f64,
);

/// The score test of every [`Test`], in their order.
pub(super) struct Scored {
    /// The LM score of each test at the measurements.
    pub lm: Vec<f64>,
    /// The 95 % point ([`ALPHA`]) of the bootstrap replicas' largest score.
    pub threshold: f64,
    /// The replicas' median largest score.
    pub median_max: f64,
}

/// Scores `tests` on `cells` of `samples` (module docs): each effect's model at its
/// step predicted (its knots rescaled for the effect on the calibration ramp, as in the
/// refits), the scores at the measurements, and `bootstrap` replicas
/// from `base_current` (the model's prediction) seeded by `seed`.
#[allow(clippy::too_many_arguments)]
pub(super) fn score_tests(
    params: &ModelParams,
    seq: &Sequence,
    samples: &Samples,
    base_current: &[f64],
    cells: &Cells,
    statistic: Statistic,
    tests: &[Test],
    bootstrap: usize,
    seed: u64,
) -> Result<Scored> {
    // the knots of each stepped model carry its effect, as in the refit
    let calib_ramp = crate::calib::knots::scale_of(params, seq)?;
    let at_step: Vec<(f64, Vec<f64>)> = tests
        .par_iter()
        .map(|&(def, p, null, h)| {
            let mut q = params.clone();
            let mut map = serde_json::Map::new();
            map.insert(p.name.into(), serde_json::json!(null + h));
            q.push_effect(EffectSpec {
                params: map,
                ..EffectSpec::named(def.name)
            });
            if let Some((s_from, r)) = &calib_ramp {
                crate::calib::knots::rescale(s_from, &mut q, r)?;
            }
            Ok((h, eval::predict(&q, seq, samples, false)?.current))
        })
        .collect::<Result<_>>()?;
    let steps = match samples.statistic {
        eval::CellStatistic::Levels => {
            let pp0 = p95s(cells, base_current);
            Steps::Levels {
                dp: at_step
                    .iter()
                    .map(|(h, pred)| {
                        let pp = p95s(cells, pred);
                        pp.iter().zip(&pp0).map(|(a, b)| (a - b) / h).collect()
                    })
                    .collect(),
                pp0,
            }
        }
        eval::CellStatistic::Paired | eval::CellStatistic::Population => {
            let population =
                (samples.statistic == eval::CellStatistic::Population).then_some(samples);
            Steps::paired(cells, base_current, at_step, population)
        }
    };
    let dirs: Vec<Option<f64>> = tests
        .iter()
        .map(|&(_, p, null, h)| one_sided(p, null, h))
        .collect();
    let mut lm = scores(cells, &samples.measured, &steps, &dirs, statistic);
    // an effect whose switch states the pixels' spread correlation changes no
    // prediction: its score is the spread score (module docs, "Spread correlation")
    for (i, &(def, p, null, h)) in tests.iter().enumerate() {
        if states_spread(def, p, null + h) {
            let (t, _) = spread::score(samples, base_current, spread::SCORE_LENGTH_PX);
            lm[i] = t.max(0.0).powi(2);
        }
    }
    // parametric bootstrap from the fitted model
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed ^ 0x9e37_79b9_7f4a_7c15);
    let mut maxes = bootstrap_maxima(
        cells,
        base_current,
        &steps,
        &dirs,
        statistic,
        bootstrap,
        &mut rng,
        BOOT_BATCH,
    );
    maxes.sort_by(|a, b| a.total_cmp(b));
    Ok(Scored {
        lm,
        threshold: quantile(&maxes, 1.0 - ALPHA),
        median_max: quantile(&maxes, 0.5),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The one-sided score (module docs): with the data above the prediction in every
    /// cell, an effect that raises the prediction where the data are highest scores
    /// above 0; one that lowers it scores 0 when its null is a bound and the same as
    /// the raising one when it is not (two-sided).
    #[test]
    fn one_sided_score_is_zero_against_the_allowed_direction() {
        // 4 cells of 10 equal measurements: P95 = the value, sigma = 2.12 noise / sqrt(10)
        let values = [1.0, 2.0, 3.0, 4.0];
        let cells = Cells {
            members: (0..4).map(|k| (10 * k..10 * k + 10).collect()).collect(),
            sigma: vec![vec![0.1; 10]; 4],
            offset: vec![vec![0.0; 10]; 4],
            noise: vec![0.1; 4],
            group: vec![0; 4],
            n_groups: 1,
        };
        let y: Vec<f64> = (0..40).map(|i| values[i / 10]).collect();
        // predicted below measured, by more where the value is larger
        let pp0: Vec<f64> = values.iter().map(|v| v - 0.1 * v).collect();
        let up: Vec<f64> = values.to_vec();
        let down: Vec<f64> = values.iter().map(|v| -v).collect();
        let steps = Steps::Levels {
            pp0,
            dp: vec![up, down],
        };
        let st = Statistic::Pooled;
        let one = scores(&cells, &y, &steps, &[Some(1.0), Some(1.0)], st);
        let two = scores(&cells, &y, &steps, &[None, None], st);
        assert!(one[0] > 1.0, "{one:?}");
        assert_eq!(one[1], 0.0);
        assert!(
            (two[1] - two[0]).abs() < 1e-9 * two[0] && two[0] == one[0],
            "{two:?}"
        );
        // a negative allowed step (a parameter bounded above at its null) flips it
        let neg = scores(&cells, &y, &steps, &[Some(-1.0), Some(-1.0)], st);
        assert_eq!(neg[0], 0.0);
        assert!(neg[1] > 1.0);
        // which effects are one-sided
        // (populations: its switch is `spread_corr`, null 0 at its lower bound, since the
        // it was the surface's `gx`, null inside its bounds)
        for (name, want) in [("capacity", true), ("soak", true), ("populations", true)] {
            let def = crate::model::effects::lookup(name).expect("registered");
            let (p, null) = def.switch().expect("has a switch");
            let h = score_step(p, null);
            assert_eq!(one_sided(p, null, h).is_some(), want, "{name}");
        }
    }

    /// The paired statistic's score step (`Steps::Paired`): a step that raises every
    /// prediction of a cell by `c` lowers that cell's `P95(measured - predicted)` by
    /// exactly `c`, so its derivative (with the sign of a predicted 95th percentile) is
    /// `c / h`, and the cell's `z` is that of the differences.
    /// With the population statistic the reference follows the predictions (eval module
    /// docs, "Population statistic"): the cells' null comes from `Samples::null_of` at
    /// the fitted model's predictions, and a step's derivative takes in the change of
    /// the reference as well as that of `P95(measured - predicted)`; a cell the step
    /// does not move keeps both.
    #[test]
    fn population_steps_move_the_reference_with_the_predictions() {
        let (np, rows) = (40, 2);
        let n = np * rows;
        let s = Samples {
            cells: eval::Cells::Pooled,
            statistic: eval::CellStatistic::Population,
            stride: 0,
            pixels: (0..np).map(|i| (0, i)).collect(),
            exposures: vec![1, 2],
            measured: (0..n).map(|i| 0.5 + 0.01 * ((i * 7) % 13) as f64).collect(),
            noise: vec![0.02; rows],
            shot_var_per_e_per_s: vec![eval::SHOT_VAR_LINE_FIT / 180.0; rows],
            noise_scale: Default::default(),
            spread_rel: vec![0.075; n],
            fluence_e: vec![5e4; n],
            neighbour_excess_e: vec![0.0; n],
            // two time bins: one cell per row
            t_since_s: vec![100.0, 1000.0],
            event: vec![0; rows],
            illumination_time_s: vec![481.0; rows],
            temperature_k: vec![80.0; rows],
            earlier_illuminations: vec![0.0; rows],
            radius: vec![0.5; np],
        };
        let pred0: Vec<f64> = (0..n).map(|i| 0.55 + 0.001 * (i % np) as f64).collect();
        let cells = make_cells(&s, &pred0, Statistic::Pooled);
        assert_eq!(cells.members.len(), 2);
        for (k, idx) in cells.members.iter().enumerate() {
            for (j, &i) in idx.iter().enumerate() {
                let (o, sd, _) = s.null_of(i, pred0[i]);
                assert_eq!((cells.offset[k][j], cells.sigma[k][j]), (o, sd));
                assert!(o < 0.0 && sd > 0.02);
            }
        }
        // the step raises the first row's predictions by 10 %, leaves the second's
        let h = 0.1;
        let at = scaled_first(&pred0, 1.1, np);
        let reference = |pred: &[f64], idx: &[usize]| {
            let (o, sd): (Vec<f64>, Vec<f64>) = idx
                .iter()
                .map(|&i| {
                    let (o, sd, _) = s.null_of(i, pred[i]);
                    (o, sd)
                })
                .unzip();
            noisy_quantile(&o, &sd, 0.95).0
        };
        let steps = Steps::paired(&cells, &pred0, vec![(h, at.clone())], Some(&s));
        let (_, _, dp) = steps.linearise(&cells, &s.measured);
        let idx = &cells.members[0];
        let p95 = |pred: &[f64]| {
            let d: Vec<f64> = idx.iter().map(|&i| s.measured[i] - pred[i]).collect();
            quantile(&d, 0.95)
        };
        let shift = reference(&at, idx) - reference(&pred0, idx);
        assert!(shift.abs() > 1e-4, "{shift}");
        let want = -((p95(&at) - p95(&pred0)) - shift) / h;
        assert!((dp[0][0] - want).abs() < 1e-9, "{} vs {want}", dp[0][0]);
        assert_eq!(dp[0][1], 0.0);
        // without the samples (the paired statistic) the reference stays
        let paired = Steps::paired(&cells, &pred0, vec![(h, at)], None);
        let (_, _, dp) = paired.linearise(&cells, &s.measured);
        let want = -(p95(&scaled_first(&pred0, 1.1, np)) - p95(&pred0)) / h;
        assert!((dp[0][0] - want).abs() < 1e-9, "{} vs {want}", dp[0][0]);
    }

    /// `pred` with its first `np` values scaled by `f`.
    fn scaled_first(pred: &[f64], f: f64, np: usize) -> Vec<f64> {
        pred.iter()
            .enumerate()
            .map(|(i, p)| if i < np { p * f } else { *p })
            .collect()
    }

    #[test]
    fn paired_steps_move_a_cell_by_the_change_of_its_predictions() {
        let cells = Cells {
            members: (0..3).map(|k| (10 * k..10 * k + 10).collect()).collect(),
            sigma: vec![vec![0.1; 10]; 3],
            offset: vec![vec![0.0; 10]; 3],
            noise: vec![0.1; 3],
            group: vec![0; 3],
            n_groups: 1,
        };
        let pred0: Vec<f64> = (0..30).map(|i| 1.0 + 0.01 * i as f64).collect();
        let y: Vec<f64> = (0..30)
            .map(|i| pred0[i] + 0.05 * ((i * 7) % 10) as f64)
            .collect();
        let (h, shift) = (0.5, [0.2, 0.0, -0.1]);
        let at: Vec<f64> = (0..30).map(|i| pred0[i] + shift[i / 10]).collect();
        let steps = Steps::paired(&cells, &pred0, vec![(h, at)], None);
        let Steps::Paired { noise_p95, .. } = &steps else {
            unreachable!()
        };
        let (z, sg, dp) = steps.linearise(&cells, &y);
        for k in 0..3 {
            // the unmoved cell (1) included: its derivative is 0
            assert!((dp[0][k] - shift[k] / h).abs() < 1e-12, "{k}: {:?}", dp[0]);
            let d: Vec<f64> = (10 * k..10 * k + 10).map(|i| y[i] - pred0[i]).collect();
            let (p, sigma, _) = eval::p95_sigma_median(&d, 0.1);
            assert_eq!((z[k], sg[k]), ((p - noise_p95[k]) / sigma, sigma));
        }
    }

    /// The bootstrap's replicas are drawn in order from one stream and scored a batch
    /// at a time in parallel: the maxima must not depend on the batch.
    #[test]
    fn bootstrap_maxima_do_not_depend_on_the_batch() {
        let cells = Cells {
            members: (0..4).map(|k| (12 * k..12 * k + 12).collect()).collect(),
            sigma: (0..4).map(|k| vec![0.1 + 0.05 * k as f64; 12]).collect(),
            offset: vec![vec![0.0; 12]; 4],
            noise: (0..4).map(|k| 0.1 + 0.05 * k as f64).collect(),
            group: vec![0, 0, 1, 1],
            n_groups: 2,
        };
        let pred: Vec<f64> = (0..48).map(|i| 1.0 + 0.02 * i as f64).collect();
        let at = |f: f64| -> Vec<f64> { pred.iter().map(|p| p * f).collect() };
        let steps = Steps::paired(&cells, &pred, vec![(0.1, at(1.1)), (-0.2, at(0.9))], None);
        let dirs = [None, Some(-1.0)];
        let run = |batch| {
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
            bootstrap_maxima(
                &cells,
                &pred,
                &steps,
                &dirs,
                Statistic::Pooled,
                13,
                &mut rng,
                batch,
            )
        };
        let one = run(1);
        assert_eq!(one.len(), 13);
        assert!(one.iter().any(|m| *m > 0.0), "{one:?}");
        for batch in [2, 8, 13, 40] {
            assert_eq!(run(batch), one, "batch {batch}");
        }
    }

    /// `populations` switches on from a default equal to its null (0, bounds [-2, 2]):
    /// the step must not be degenerate (it was 1e-14, so its score was always ~0).
    #[test]
    fn score_step_is_not_degenerate_when_the_default_is_the_null() {
        let def = crate::model::effects::lookup("populations").expect("registered");
        let (p, null) = def.switch().expect("has a switch");
        assert_eq!(p.default, null);
        let h = score_step(p, null);
        assert!(h.abs() >= 0.1 * (p.hi - p.lo) / 2.0 - 1e-12, "step {h}");
        let soak = crate::model::effects::lookup("soak").expect("registered");
        let (q, n) = soak.switch().expect("has a switch");
        assert_eq!(score_step(q, n), q.default - n);
    }
}
