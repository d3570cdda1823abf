//! `fit --with NAME`: the fitted parameters of effects, by Levenberg-Marquardt
//! (`levenberg-marquardt` 0.15, forward-difference Jacobian) on the normalised cell
//! residuals `z` of [`crate::diag::eval`] (fluence bin x time since illumination), the
//! paper's calibration held fixed. Parameters are kept inside their bounds (projected
//! after each step). Uncertainties: `s^2 (J^T J)^-1`, `s^2 = SSR / (m - p)`.
//!
//! Start: the model's values (the defaults for an added effect), then, for each switch
//! parameter (one with a null value) that does not start at its null, a coarse scan of
//! [`SCAN`] multiples of its distance from the null (others held at their start; within
//! the bounds; the effects added by this fit first, so that the base model's effects are
//! scanned against the added ones' best start, not their defaults) and the best of these
//! as start. Why: an effect whose response is flat at
//! its null (`soak`: the fill fraction `1 - exp(-t / (r tau))` is 1 to all orders as
//! `r -> 0`) has no gradient there, so Levenberg-Marquardt started far on the other side
//! of the optimum steps over it onto the bound and stays at the null (measured: a hidden
//! truth soak, optimum `capture_ratio` 0.005, fitted from the default 0.1 ended at 0).
//! The steps are projected onto the bounds, which can end above the start's sum of
//! squares; the start is then kept. The null is one of the starts tried, so the fit ends
//! no worse than the model without the effect (measured before: a joint fit of four
//! effects, the reference at RMS 8.146, ended at 8.177).

use crate::diag::data::Sequence;
use crate::diag::eval::{self, Samples};
use crate::error::{Error, Result};
use crate::model::effects;
use crate::model::params::{EffectSpec, ModelParams};
use levenberg_marquardt::{LeastSquaresProblem, LevenbergMarquardt};
use nalgebra::{storage::Owned, DMatrix, DVector, Dyn};
use serde::Serialize;
use std::cell::RefCell;

/// One fitted parameter.
#[derive(Debug, Clone, Serialize)]
pub struct FittedParam {
    pub effect: String,
    pub name: String,
    pub value: f64,
    pub sigma: f64,
    pub lo: f64,
    pub hi: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct EffectFit {
    pub params: Vec<FittedParam>,
    pub cells: usize,
    pub residual_rms_normalised_before: f64,
    pub residual_rms_normalised_after: f64,
    pub evaluations: usize,
    pub termination: String,
}

struct Slot {
    effect: usize,
    name: &'static str,
    lo: f64,
    hi: f64,
    null: Option<f64>,
    /// The effect was added by this fit (not in the base model).
    added: bool,
}

/// Multiples of a switch parameter's distance from its null tried as start (0: the null,
/// so that a fit is never started worse than the model without the effect).
pub const SCAN: [f64; 6] = [0.0, 0.01, 0.05, 0.2, 1.0, 5.0];

type Cache = RefCell<Vec<(Vec<f64>, Option<DVector<f64>>)>>;

struct Problem<'a> {
    base: ModelParams,
    seq: &'a Sequence,
    samples: &'a Samples,
    cells: eval::CellIndex,
    slots: Vec<Slot>,
    p: DVector<f64>,
    cache: Cache,
    evals: RefCell<usize>,
}

impl Problem<'_> {
    fn params_at(&self, p: &[f64]) -> ModelParams {
        let mut m = self.base.clone();
        for (s, v) in self.slots.iter().zip(p) {
            m.effects[s.effect]
                .params
                .insert(s.name.to_string(), serde_json::json!(v.clamp(s.lo, s.hi)));
        }
        m
    }

    fn z_at(&self, p: &[f64]) -> Option<DVector<f64>> {
        if let Some((_, z)) = self.cache.borrow().iter().find(|(q, _)| q == p) {
            return z.clone();
        }
        *self.evals.borrow_mut() += 1;
        let m = self.params_at(p);
        let z = eval::predict(&m, self.seq, self.samples, false)
            .ok()
            .map(|pr| {
                let c = self.cells.z(self.samples, &pr.current);
                DVector::from_iterator(c.len(), c.iter().map(|(_, g)| g.z))
            });
        let mut cache = self.cache.borrow_mut();
        if cache.len() > 8 {
            cache.remove(0);
        }
        cache.push((p.to_vec(), z.clone()));
        z
    }
}

impl LeastSquaresProblem<f64, Dyn, Dyn> for Problem<'_> {
    type ResidualStorage = Owned<f64, Dyn>;
    type JacobianStorage = Owned<f64, Dyn, Dyn>;
    type ParameterStorage = Owned<f64, Dyn>;

    fn set_params(&mut self, p: &DVector<f64>) {
        self.p = DVector::from_iterator(
            p.len(),
            p.iter().zip(&self.slots).map(|(v, s)| v.clamp(s.lo, s.hi)),
        );
    }
    fn params(&self) -> DVector<f64> {
        self.p.clone()
    }
    fn residuals(&self) -> Option<DVector<f64>> {
        self.z_at(self.p.as_slice())
    }
    fn jacobian(&self) -> Option<DMatrix<f64>> {
        let r0 = self.z_at(self.p.as_slice())?;
        let mut j = DMatrix::zeros(r0.len(), self.p.len());
        for (i, s) in self.slots.iter().enumerate() {
            let mut q = self.p.as_slice().to_vec();
            let mut h = 1e-3 * (q[i].abs() + 1e-3 * (s.hi - s.lo).min(1.0));
            if q[i] + h > s.hi {
                h = -h;
            }
            q[i] += h;
            let r = self.z_at(&q)?;
            if r.len() != r0.len() {
                return None;
            }
            j.set_column(i, &((r - &r0) / h));
        }
        Some(j)
    }
}

/// The coarse scan of the module docs: move each switch parameter's start to the best
/// of [`SCAN`] multiples of its distance from the null (sum of squared residuals).
fn scan_start(problem: &mut Problem<'_>) {
    let rss = |pr: &Problem<'_>, p: &[f64]| {
        let r = pr.z_at(p).map_or(f64::NAN, |z| z.norm_squared());
        if r.is_finite() {
            r
        } else {
            f64::INFINITY
        }
    };
    // the effects added by this fit first, while the others hold the base's values
    let mut order: Vec<usize> = (0..problem.slots.len()).collect();
    order.sort_by_key(|&i| !problem.slots[i].added);
    for i in order {
        let (lo, hi) = (problem.slots[i].lo, problem.slots[i].hi);
        let Some(null) = problem.slots[i].null else {
            continue;
        };
        let mut p = problem.p.as_slice().to_vec();
        let d = p[i] - null;
        if d == 0.0 {
            continue;
        }
        let mut best = (rss(problem, &p), p[i]);
        for f in SCAN {
            p[i] = (null + f * d).clamp(lo, hi);
            let r = rss(problem, &p);
            if r < best.0 {
                best = (r, p[i]);
            }
        }
        problem.p[i] = best.1;
    }
}

/// Add the effects `names` (each `NAME`, defaults as start) to `base` and fit their
/// fitted parameters. Returns the model and the fit.
pub fn fit(
    base: &ModelParams,
    names: &[String],
    seq: &Sequence,
    samples: &Samples,
) -> Result<(ModelParams, EffectFit)> {
    let mut m = base.clone();
    let n_base = base.effects.len();
    for n in names {
        if m.effects.iter().any(|e| &e.name == n) {
            continue;
        }
        if effects::lookup(n).is_none() {
            return Err(Error::invalid(
                "--with",
                format!(
                    "unknown effect `{n}` (known: {})",
                    effects::names().join(", ")
                ),
            ));
        }
        m.effects.push(EffectSpec {
            name: n.clone(),
            params: serde_json::Map::new(),
        });
    }
    // fill defaults so every parameter is explicit in the model file
    let mut slots = Vec::new();
    let mut start = Vec::new();
    for (i, e) in m.effects.iter_mut().enumerate() {
        let (def, vals) =
            effects::resolve(e).map_err(|r| Error::invalid(format!("effects[{i}]"), r))?;
        for (k, v) in &vals {
            e.params.insert(k.clone(), serde_json::json!(v));
        }
        if names.contains(&e.name) {
            for p in def.params.iter().filter(|p| p.fitted) {
                slots.push(Slot {
                    effect: i,
                    name: p.name,
                    lo: p.lo,
                    hi: p.hi,
                    null: p.null,
                    added: i >= n_base,
                });
                start.push(vals[p.name]);
            }
        }
    }
    let cells = eval::CellIndex::new(samples);
    let before = {
        let pr = eval::predict(base, seq, samples, false)?;
        eval::rms(&cells.z(samples, &pr.current))
    };
    let mut problem = Problem {
        base: m.clone(),
        seq,
        samples,
        cells,
        slots,
        p: DVector::from_vec(start),
        cache: RefCell::new(Vec::new()),
        evals: RefCell::new(0),
    };
    scan_start(&mut problem);
    let p0 = problem.p.as_slice().to_vec();
    let rss0 = problem.z_at(&p0).map(|z| z.norm_squared());
    let (mut problem, report) = LevenbergMarquardt::new()
        .with_patience(20)
        .minimize(problem);
    let mut termination = format!("{:?}", report.termination);
    if let Some(r0) = rss0 {
        let r1 = problem.z_at(problem.p.as_slice()).map(|z| z.norm_squared());
        if !r1.is_some_and(|r1| r1 <= r0) {
            problem.p = DVector::from_vec(p0);
            termination.push_str(" (start kept: the projected steps ended worse)");
        }
    }
    let p = problem.p.as_slice().to_vec();
    let fitted = problem.params_at(&p);
    let r = problem.z_at(&p).unwrap_or_else(|| DVector::zeros(0));
    let cells = r.len();
    let after = if cells == 0 {
        f64::NAN
    } else {
        (r.norm_squared() / cells as f64).sqrt()
    };
    let cov = problem
        .jacobian()
        .and_then(|j| (j.transpose() * &j).try_inverse());
    let s2 = r.norm_squared() / (cells as f64 - p.len() as f64).max(1.0);
    let params = problem
        .slots
        .iter()
        .enumerate()
        .map(|(i, s)| FittedParam {
            effect: fitted.effects[s.effect].name.clone(),
            name: s.name.to_string(),
            value: p[i],
            sigma: cov
                .as_ref()
                .map_or(f64::NAN, |c| (s2 * c[(i, i)]).max(0.0).sqrt()),
            lo: s.lo,
            hi: s.hi,
        })
        .collect();
    let evals = *problem.evals.borrow();
    fitted
        .validate()
        .map_err(|e| Error::invalid("effects", e))?;
    Ok((
        fitted,
        EffectFit {
            params,
            cells,
            residual_rms_normalised_before: before,
            residual_rms_normalised_after: after,
            evaluations: evals,
            termination,
        },
    ))
}
