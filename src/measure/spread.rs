//! The pixels' spread about the model, correlated between neighbours: what the
//! simulator's hidden `populations` leaves (measured with examples/diagnose_matrix).
//!
//! The cell statistic ([`super::eval`], `--cell-statistic population`) compares each
//! cell's 95th percentile with its reference as if the cell's pixels were independent.
//! When neighbouring pixels share their traps (the truth's field), the pixels above a
//! cell's 95th percentile come in patches, the percentile moves as if the cell had
//! fewer pixels, and its `sigma_q` is too small. That changes no prediction; it is the
//! noise of the statistic. This module measures it from the residuals alone.
//!
//! # Indicators
//! In each cell (the key of [`eval::key_of`] over `s.cells.keys()`), every sample with
//! a finite measurement and prediction is standardised by its reference
//! ([`Samples::null_of`]: `e = (measured - predicted - offset) / sd`), and `J = 1` for
//! the samples at or above the cell's 95th percentile of `e`. With `p` the fraction of
//! ones, `w = (J - p) / sqrt(p (1 - p))`: mean 0 and mean square 1 in every cell, so the
//! mean of `w_a w_b` over all pairs of distinct samples of a cell of `n` is exactly
//! `-1 / (n - 1)`. For independent pixels every pair has that expectation; the
//! *centred* product `w_a w_b + 1 / (n - 1)` has expectation 0.
//!
//! # Pairs
//! Pairs of samples of one cell at two distinct pixels at most [`MAX_LAG_PX`] apart, in
//! the same exposure or in two exposures of the cell; the class of a pair is its
//! distance rounded to a pixel. The same pixel at two exposures is left out: a pixel
//! keeps its own traps with or without the field (measured on the campaign without
//! it, 128 x 128, seed 1: +0.041 against ~0 at every distance).
//!
//! # Kernel, design effect
//! `rho(d) = c exp(-d^2 / (2 l^2))`, the correlation of two distinct pixels' indicators
//! at distance `d` px. Fitted ([`fit_kernel`], Levenberg-Marquardt) to the classes'
//! mean centred products with a constant `b`: the centring spreads the near pairs'
//! excess over every pair, so the far ones read `b < 0` with the field. A cell's 95th
//! percentile has the variance of the mean of its indicators, so its design effect is
//! `deff = 1 + (2 / n) sum over its pairs of distinct pixels of rho(d)` ([`design_effects`])
//! and its `z` under correlated pixels is `z / sqrt(deff)`.
//!
//! # Score
//! The composite (pairwise) likelihood score of `c` at 0 for a fixed length `l0`
//! ([`score`]). A pixel's indicators at the exposures of one cell go together with or
//! without the field (a pixel of the trap-rich population stays above the cell's 95th
//! percentile), so the pairs of samples are not independent and a sum over them
//! scatters several times more than its nominal variance (measured on the campaign
//! without the field, 128 x 128, seed 1: -5.9 against a replica sd of 0.94). The score
//! therefore pairs *pixels*: per cell, each pixel's `w` averaged over the cell's
//! exposures (`wbar`), `v` the mean of `wbar^2` over the cell's `N` pixels, and
//! `T = sum k(d) (wbar_a wbar_b + v / (N - 1)) / sqrt(sum k(d)^2 v^2)`,
//! `k(d) = exp(-d^2 / (2 l0^2))`, over every pair of distinct pixels of every cell
//! (`v / (N - 1)` the centring, as above). Under independent pixels the products are
//! uncorrelated with mean about 0 and variance about `v^2`, so `T` is about standard
//! normal; `c` cannot be negative, so the test is one-sided.
//!
//! # Cost
//! Every pixel of a cell visits every lag up to [`MAX_LAG_PX`] (on a grid of
//! `s.stride`, or of 1 px for random samples). The pairs of samples of two pixels are
//! never visited one by one: their products sum to `W_a W_b` (`W` a pixel's sum of
//! `w` over the cell's exposures), and only the rows both pixels have (the
//! same-exposure pairs) are merged. The work is linear in a cell's exposures. Visiting
//! every pair of samples instead made `compare` on the 256 x 256 14 h lab
//! sequence, whose cells hold hundreds of exposures, take 88.9 s against 11.9 s
//! (medians of three runs each, in turns; measured with examples/diagnose_matrix).

use super::eval::{self, Samples};
use levenberg_marquardt::{LeastSquaresProblem, LevenbergMarquardt};
use nalgebra::{storage::Owned, DVector, Dyn, OMatrix, Vector3, U3};
use serde::Serialize;
use std::collections::BTreeMap;

/// The farthest pair, pixels. The field's indicator correlation is below 0.01 from
/// ~10 px on (128 x 128, seed 1), and the farther classes carry the centring's level.
pub const MAX_LAG_PX: usize = 16;

/// The length of the score's kernel, pixels (module docs, "Score"): about the length
/// the indicators of the simulator's default field show (fitted 4.6 px at 128 x 128,
/// seed 1).
pub const SCORE_LENGTH_PX: f64 = 4.0;

/// One cell's members and their standardised indicators.
struct Cell {
    /// Sample indices.
    members: Vec<usize>,
    /// `w` per member (module docs).
    w: Vec<f64>,
}

/// The cells of `s` under the predictions `pred` with their indicators, in key order.
fn cells(s: &Samples, pred: &[f64]) -> Vec<(Vec<i64>, Cell)> {
    let mut g: BTreeMap<Vec<i64>, Vec<usize>> = BTreeMap::new();
    for (i, q) in pred.iter().enumerate().take(s.len()) {
        if s.measured[i].is_finite() && q.is_finite() {
            if let Some(k) = eval::key_of(s, s.cells.keys(), i) {
                g.entry(k).or_default().push(i);
            }
        }
    }
    g.into_iter()
        .filter(|(_, m)| m.len() >= 10)
        .map(|(k, members)| {
            let e: Vec<f64> = members
                .iter()
                .map(|&i| {
                    let (offset, sd, _) = s.null_of(i, pred[i]);
                    (s.measured[i] - pred[i] - offset) / sd.max(1e-300)
                })
                .collect();
            let mut sorted = e.clone();
            sorted.sort_by(f64::total_cmp);
            let q = sorted[((sorted.len() as f64) * 0.95).floor() as usize];
            let ones = e.iter().filter(|&&v| v >= q).count() as f64;
            let p = ones / e.len() as f64;
            let norm = (p * (1.0 - p)).sqrt().max(1e-12);
            let w = e
                .iter()
                .map(|&v| (f64::from(u8::from(v >= q)) - p) / norm)
                .collect();
            (k, Cell { members, w })
        })
        .collect()
}

/// The lags `(dy, dx, distance px)` of one half plane (each unordered pair of distinct
/// pixels once), on a grid of `step` pixels, up to [`MAX_LAG_PX`].
fn lags(step: usize) -> Vec<(i64, i64, f64)> {
    let step = step.max(1) as i64;
    let m = MAX_LAG_PX as i64 / step;
    let mut out = Vec::new();
    for dy in 0..=m {
        for dx in -m..=m {
            if dy == 0 && dx <= 0 {
                continue;
            }
            let d = (((dy * dy + dx * dx) as f64).sqrt()) * step as f64;
            if d <= MAX_LAG_PX as f64 + 1e-9 {
                out.push((dy * step, dx * step, d));
            }
        }
    }
    out
}

/// Calls `f(a, b, d)` for every pair of members `a`, `b` (positions in `c.members`) of
/// one cell at distinct pixels at most [`MAX_LAG_PX`] apart, `d` their distance, px.
/// `head` (one slot per pixel of the `ny x nx` array, all `u32::MAX`) and `next` are
/// scratch space, left as found.
fn visit_pairs(
    s: &Samples,
    c: &Cell,
    lags: &[(i64, i64, f64)],
    (ny, nx): (usize, usize),
    head: &mut [u32],
    next: &mut Vec<u32>,
    f: &mut dyn FnMut(usize, usize, f64),
) {
    let np = s.npix();
    next.clear();
    next.resize(c.members.len(), u32::MAX);
    for (k, &i) in c.members.iter().enumerate() {
        let (y, x) = s.pixels[i % np];
        let slot = y * nx + x;
        next[k] = head[slot];
        head[slot] = k as u32;
    }
    for (a, &i) in c.members.iter().enumerate() {
        let (y, x) = s.pixels[i % np];
        for &(dy, dx, d) in lags {
            let (yb, xb) = (y as i64 + dy, x as i64 + dx);
            if yb < 0 || xb < 0 || yb >= ny as i64 || xb >= nx as i64 {
                continue;
            }
            let mut b = head[yb as usize * nx + xb as usize];
            while b != u32::MAX {
                f(a, b as usize, d);
                b = next[b as usize];
            }
        }
    }
    for &i in &c.members {
        let (y, x) = s.pixels[i % np];
        head[y * nx + x] = u32::MAX;
    }
}

/// The array size the samples' pixels span.
fn extent(s: &Samples) -> (usize, usize) {
    s.pixels
        .iter()
        .fold((0, 0), |(a, b), &(y, x)| (a.max(y + 1), b.max(x + 1)))
}

/// The measured pair correlations (module docs): per distance class `d` (0 to
/// [`MAX_LAG_PX`]; class 0 is empty), the mean centred product of the pairs of the
/// same exposure and of two exposures, and their counts.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct PairCorrelation {
    pub same_exposure: Vec<f64>,
    pub same_exposure_pairs: Vec<u64>,
    pub other_exposures: Vec<f64>,
    pub other_exposures_pairs: Vec<u64>,
}

impl PairCorrelation {
    /// Both exposure classes pooled: `(distance px, mean centred product, pairs)` of the
    /// classes with pairs.
    pub fn pooled(&self) -> Vec<(f64, f64, u64)> {
        (0..=MAX_LAG_PX)
            .filter_map(|d| {
                let n = self.same_exposure_pairs[d] + self.other_exposures_pairs[d];
                (n > 0).then(|| {
                    let v = (self.same_exposure[d] * self.same_exposure_pairs[d] as f64
                        + self.other_exposures[d] * self.other_exposures_pairs[d] as f64)
                        / n as f64;
                    (d as f64, v, n)
                })
            })
            .collect()
    }
}

/// One cell's members gathered by pixel (module docs, "Cost").
struct ByPixel {
    /// One member per pixel (its first sample in the cell) with `w` the sum of the
    /// pixel's `w` over the cell's exposures ([`score`] divides it by `count`: the
    /// mean): [`visit_pairs`] on it visits each pair of distinct pixels once.
    pixels: Cell,
    /// Per pixel: how many of the cell's samples it has.
    count: Vec<f64>,
    /// Per pixel: its samples' `(row, w)`, rows ascending.
    rows: Vec<Vec<(usize, f64)>>,
    /// The cell's samples (`n` of the module docs).
    samples: usize,
}

/// [`ByPixel`] of one cell.
fn by_pixel(s: &Samples, c: &Cell) -> ByPixel {
    let np = s.npix();
    let mut slot: BTreeMap<usize, usize> = BTreeMap::new();
    let mut out = ByPixel {
        pixels: Cell {
            members: Vec::new(),
            w: Vec::new(),
        },
        count: Vec::new(),
        rows: Vec::new(),
        samples: c.members.len(),
    };
    // members are in index order, so each pixel's rows come ascending
    for (&i, &w) in c.members.iter().zip(&c.w) {
        let k = *slot.entry(i % np).or_insert_with(|| {
            out.pixels.members.push(i);
            out.pixels.w.push(0.0);
            out.count.push(0.0);
            out.rows.push(Vec::new());
            out.pixels.members.len() - 1
        });
        out.pixels.w[k] += w;
        out.count[k] += 1.0;
        out.rows[k].push((i / np, w));
    }
    out
}

/// `(sum of w_a w_b, pairs)` over the rows two pixels share (merge of ascending rows).
fn shared_rows(a: &[(usize, f64)], b: &[(usize, f64)]) -> (f64, f64) {
    let (mut i, mut j, mut sum, mut n) = (0, 0, 0.0, 0.0);
    while i < a.len() && j < b.len() {
        match a[i].0.cmp(&b[j].0) {
            std::cmp::Ordering::Less => i += 1,
            std::cmp::Ordering::Greater => j += 1,
            std::cmp::Ordering::Equal => {
                sum += a[i].1 * b[j].1;
                n += 1.0;
                i += 1;
                j += 1;
            }
        }
    }
    (sum, n)
}

/// The cells of `s` under `pred` ([`cells`]) gathered by pixel, in key order.
fn pixel_cells(s: &Samples, pred: &[f64]) -> Vec<(Vec<i64>, ByPixel)> {
    cells(s, pred)
        .into_iter()
        .map(|(k, c)| (k, by_pixel(s, &c)))
        .collect()
}

/// Runs `f(cell index, cell, a, b, d)` over every pair of distinct pixels `a`, `b`
/// (positions in the [`ByPixel`]) of every cell up to [`MAX_LAG_PX`] apart (module docs,
/// "Pairs" and "Cost").
fn for_each_pixel_pair(
    s: &Samples,
    cells: &[(Vec<i64>, ByPixel)],
    mut f: impl FnMut(usize, &ByPixel, usize, usize, f64),
) {
    let (ny, nx) = extent(s);
    let lags = lags(s.stride);
    let mut head = vec![u32::MAX; ny * nx];
    let mut next = Vec::new();
    for (ci, (_, bp)) in cells.iter().enumerate() {
        visit_pairs(
            s,
            &bp.pixels,
            &lags,
            (ny, nx),
            &mut head,
            &mut next,
            &mut |a, b, d| f(ci, bp, a, b, d),
        );
    }
}

/// [`PairCorrelation`] of the samples `s` under the predictions `pred`.
///
/// Per pair of distinct pixels `a`, `b` of a cell, the products of all their samples'
/// `w` sum to `W_a W_b` (`W` the pixel's sum over the cell's exposures) over
/// `m_a m_b` pairs; the rows both pixels have are the same-exposure pairs and the rest
/// the pairs of two exposures.
pub fn pair_correlation(s: &Samples, pred: &[f64]) -> PairCorrelation {
    let cells = pixel_cells(s, pred);
    let nclass = MAX_LAG_PX + 1;
    let (mut sum, mut cnt) = (vec![0.0; 2 * nclass], vec![0.0_f64; 2 * nclass]);
    for_each_pixel_pair(s, &cells, |_, bp, a, b, d| {
        let centre = 1.0 / (bp.samples as f64 - 1.0);
        let all = bp.pixels.w[a] * bp.pixels.w[b];
        let n_all = bp.count[a] * bp.count[b];
        let (same, n_same) = shared_rows(&bp.rows[a], &bp.rows[b]);
        let k = d.round() as usize;
        sum[k] += same + n_same * centre;
        cnt[k] += n_same;
        sum[nclass + k] += all - same + (n_all - n_same) * centre;
        cnt[nclass + k] += n_all - n_same;
    });
    let mean = |k: usize| {
        if cnt[k] > 0.0 {
            sum[k] / cnt[k]
        } else {
            0.0
        }
    };
    let pairs = |r: std::ops::Range<usize>| cnt[r].iter().map(|&n| n as u64).collect();
    PairCorrelation {
        same_exposure: (0..nclass).map(mean).collect(),
        same_exposure_pairs: pairs(0..nclass),
        other_exposures: (nclass..2 * nclass).map(mean).collect(),
        other_exposures_pairs: pairs(nclass..2 * nclass),
    }
}

/// The indicators' correlation between two distinct pixels (module docs, "Kernel"):
/// the model's statement of it ([`crate::model::effect::SpreadCorrelation`], the
/// `populations` effect's `spread_corr` and `spread_length_px`).
pub use crate::model::effect::SpreadCorrelation as Kernel;

/// Each cell's `z` divided and its `sigma_e_per_s` multiplied by the square root of
/// its design effect in `deff` (cells not in it: 1).
pub fn widen(z: &mut [(Vec<i64>, eval::GroupStat)], deff: &BTreeMap<Vec<i64>, f64>) {
    for (k, g) in z.iter_mut() {
        let f = deff.get(k).copied().unwrap_or(1.0).max(1.0).sqrt();
        g.z /= f;
        g.sigma_e_per_s *= f;
    }
}

/// [`eval::cell_z`] of a model's predictions `pred` at the samples `s`, widened by
/// the design effects of the spread correlation the model states
/// ([`crate::model::effects::spread_correlation`]; the plain cells when it states
/// none). What `compare`, `fit` and `diagnose` call a model's cells.
pub fn model_cell_z(
    params: &crate::model::ModelParams,
    s: &Samples,
    pred: &[f64],
) -> Vec<(Vec<i64>, eval::GroupStat)> {
    let mut z = eval::cell_z(s, pred);
    widen_for_model(params, s, pred, &mut z);
    z
}

/// `params` run over `seq`: [`eval::rss`] of its cells at the samples `s`, widened as
/// the model states ([`model_cell_z`]).
pub fn rss_cells(
    params: &crate::model::ModelParams,
    seq: &super::data::Sequence,
    s: &Samples,
) -> crate::error::Result<(f64, usize)> {
    let pr = eval::predict(params, seq, s, false)?;
    Ok(eval::rss(&model_cell_z(params, s, &pr.current)))
}

/// [`widen`] the cells `z` of `pred` by the design effects of the spread correlation
/// `params` states (nothing when it states none).
pub fn widen_for_model(
    params: &crate::model::ModelParams,
    s: &Samples,
    pred: &[f64],
    z: &mut [(Vec<i64>, eval::GroupStat)],
) {
    if let Some(k) = crate::model::effects::spread_correlation(&params.effects) {
        widen(z, &design_effects(s, pred, &k).into_iter().collect());
    }
}

/// [`fit_kernel`]'s result.
#[derive(Debug, Clone, Copy, Serialize, PartialEq)]
pub struct KernelFit {
    pub kernel: Kernel,
    /// The centring's level `b` (module docs).
    pub level: f64,
    pub sigma_corr: f64,
    pub sigma_length_px: f64,
    /// RMS of the weighted residuals (1 when the classes scatter as independent pairs
    /// would; the sigmas are scaled by it when above 1).
    pub rms_weighted: f64,
    pub converged: bool,
}

struct KernelProblem<'a> {
    /// `(d, mean, pairs)`.
    classes: &'a [(f64, f64, u64)],
    p: Vector3<f64>,
    /// The nearest class's distance: a shorter length leaves `c` undetermined (it is
    /// the correlation at distance 0, where no pair is).
    length_lo_px: f64,
}

impl KernelProblem<'_> {
    fn model(&self, d: f64) -> (f64, [f64; 3]) {
        let (c, l, b) = (self.p[0], self.p[1], self.p[2]);
        let g = (-d * d / (2.0 * l * l)).exp();
        (c * g + b, [g, c * g * d * d / (l * l * l), 1.0])
    }
}

impl LeastSquaresProblem<f64, Dyn, U3> for KernelProblem<'_> {
    type ResidualStorage = Owned<f64, Dyn>;
    type JacobianStorage = Owned<f64, Dyn, U3>;
    type ParameterStorage = Owned<f64, U3>;

    fn set_params(&mut self, p: &Vector3<f64>) {
        // c >= 0, nearest class <= l <= MAX_LAG_PX
        self.p = Vector3::new(
            p[0].max(0.0),
            p[1].clamp(self.length_lo_px, MAX_LAG_PX as f64),
            p[2],
        );
    }
    fn params(&self) -> Vector3<f64> {
        self.p
    }
    fn residuals(&self) -> Option<DVector<f64>> {
        Some(DVector::from_iterator(
            self.classes.len(),
            self.classes
                .iter()
                .map(|&(d, v, n)| (self.model(d).0 - v) * (n as f64).sqrt()),
        ))
    }
    fn jacobian(&self) -> Option<OMatrix<f64, Dyn, U3>> {
        let mut j = OMatrix::<f64, Dyn, U3>::zeros(self.classes.len());
        for (r, &(d, _, n)) in self.classes.iter().enumerate() {
            let g = self.model(d).1;
            for (k, v) in g.iter().enumerate() {
                j[(r, k)] = v * (n as f64).sqrt();
            }
        }
        Some(j)
    }
}

/// Fits the kernel and the centring's level to the pooled classes of `pc` (module
/// docs), each class weighted by its pairs (the variance of a mean of `n` products of
/// unit variance). None with fewer than four classes.
pub fn fit_kernel(pc: &PairCorrelation) -> Option<KernelFit> {
    let classes = pc.pooled();
    if classes.len() < 4 {
        return None;
    }
    // start: the nearest class's excess over the farthest third as c, 4 px
    let far: Vec<f64> = classes
        .iter()
        .filter(|c| c.0 >= MAX_LAG_PX as f64 * 2.0 / 3.0)
        .map(|c| c.1)
        .collect();
    let b0 = if far.is_empty() {
        0.0
    } else {
        far.iter().sum::<f64>() / far.len() as f64
    };
    let c0 = (classes[0].1 - b0).max(1e-3);
    let length_lo_px = classes[0].0.max(1.0);
    let problem = KernelProblem {
        classes: &classes,
        p: Vector3::new(c0, SCORE_LENGTH_PX.max(length_lo_px), b0),
        length_lo_px,
    };
    let (problem, report) = LevenbergMarquardt::new().minimize(problem);
    let r = problem.residuals()?;
    let j = problem.jacobian()?;
    let m = classes.len() as f64;
    let rms_weighted = (r.norm_squared() / (m - 3.0).max(1.0)).sqrt();
    // the classes scatter more than independent pairs would (pixels recur across
    // exposures and classes): the uncertainties scaled by the weighted RMS when above 1
    let cov = (j.transpose() * &j).try_inverse();
    let sig = |i: usize| {
        cov.as_ref().map_or(f64::NAN, |c| {
            c[(i, i)].max(0.0).sqrt() * rms_weighted.max(1.0)
        })
    };
    Some(KernelFit {
        kernel: Kernel {
            corr: problem.p[0],
            length_px: problem.p[1],
        },
        level: problem.p[2],
        sigma_corr: sig(0),
        sigma_length_px: sig(1),
        rms_weighted,
        converged: report.termination.was_successful(),
    })
}

/// Per cell of `s` under `pred` (the cells of [`eval::cell_z`] with at least 10
/// samples, in key order): its key and design effect under `kernel` (module docs).
pub fn design_effects(s: &Samples, pred: &[f64], kernel: &Kernel) -> Vec<(Vec<i64>, f64)> {
    let cells = pixel_cells(s, pred);
    let mut acc = vec![0.0; cells.len()];
    for_each_pixel_pair(s, &cells, |ci, bp, a, b, d| {
        acc[ci] += kernel.at(d) * bp.count[a] * bp.count[b];
    });
    cells
        .iter()
        .zip(acc)
        .map(|((k, bp), a)| (k.clone(), (1.0 + 2.0 * a / bp.samples as f64).max(1.0)))
        .collect()
}

/// [`check`]'s result: whether the cells' pixels move together, and what the cells'
/// residual would be if the statistic knew it (module docs).
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct SpreadCheck {
    /// [`score`] at [`SCORE_LENGTH_PX`]: about standard normal for independent pixels.
    pub score: f64,
    /// Pairs of pixels the score sums.
    pub score_pairs: u64,
    /// [`fit_kernel`] of [`pair_correlation`]; None with fewer than four classes.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub kernel: Option<KernelFit>,
    /// The cells' normalised residual RMS with each `z` divided by the square root of
    /// its design effect under the fitted kernel (the plain RMS without a kernel).
    pub residual_rms_normalised_correlated: f64,
    /// The median design effect over the cells.
    pub design_effect_median: f64,
}

/// [`SpreadCheck`] of the samples `s` under the predictions `pred`, whose cells are
/// `z` ([`eval::cell_z`]).
pub fn check(s: &Samples, pred: &[f64], z: &[(Vec<i64>, eval::GroupStat)]) -> SpreadCheck {
    let (score, score_pairs) = score(s, pred, SCORE_LENGTH_PX);
    let kernel = fit_kernel(&pair_correlation(s, pred));
    let deff: BTreeMap<Vec<i64>, f64> = kernel
        .map(|k| design_effects(s, pred, &k.kernel).into_iter().collect())
        .unwrap_or_default();
    let widened: Vec<f64> = z
        .iter()
        .map(|(k, g)| g.z / deff.get(k).copied().unwrap_or(1.0).sqrt())
        .collect();
    let mut d: Vec<f64> = z
        .iter()
        .map(|(k, _)| deff.get(k).copied().unwrap_or(1.0))
        .collect();
    d.sort_by(f64::total_cmp);
    SpreadCheck {
        score,
        score_pairs,
        kernel,
        residual_rms_normalised_correlated: (widened.iter().map(|v| v * v).sum::<f64>()
            / widened.len().max(1) as f64)
            .sqrt(),
        design_effect_median: d.get(d.len() / 2).copied().unwrap_or(1.0),
    }
}

/// The score `T` of module docs, "Score", with a kernel of length `length_px`, and the
/// number of pairs of pixels it sums.
pub fn score(s: &Samples, pred: &[f64], length_px: f64) -> (f64, u64) {
    let mut cells = pixel_cells(s, pred);
    // each pixel's w averaged over the cell's exposures (module docs, "Score")
    for (_, bp) in &mut cells {
        for (w, n) in bp.pixels.w.iter_mut().zip(&bp.count) {
            *w /= n;
        }
    }
    // per cell: the mean square of its pixels' w, the null variance of one product
    let v: Vec<f64> = cells
        .iter()
        .map(|(_, bp)| {
            let w = &bp.pixels.w;
            w.iter().map(|w| w * w).sum::<f64>() / w.len().max(1) as f64
        })
        .collect();
    let shape = Kernel {
        corr: 1.0,
        length_px,
    };
    let (mut num, mut den, mut n) = (0.0, 0.0, 0u64);
    for_each_pixel_pair(s, &cells, |ci, bp, a, b, d| {
        let (k, w) = (shape.at(d), &bp.pixels.w);
        let m = w.len() as f64;
        num += k * (w[a] * w[b] + v[ci] / (m - 1.0).max(1.0));
        den += k * k * v[ci] * v[ci];
        n += 1;
    });
    (if den > 0.0 { num / den.sqrt() } else { 0.0 }, n)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::measure::eval::{CellStatistic, Cells};
    use rand::{Rng, SeedableRng};
    use rand_distr::StandardNormal;

    /// One cell (one fluence bin, one time bin) of `n x n` pixels over `rows` exposures:
    /// predictions 1 e-/s, exposure noise 1 e-/s, measured `1 + field[pixel] + N(0, 1)`.
    fn one_cell(n: usize, rows: usize, field: &[f64], seed: u64) -> (Samples, Vec<f64>) {
        let np = n * n;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let measured: Vec<f64> = (0..rows * np)
            .map(|i| 1.0 + field[i % np] + rng.sample::<f64, _>(StandardNormal))
            .collect();
        let len = measured.len();
        let s = Samples {
            cells: Cells::Pooled,
            statistic: CellStatistic::Paired,
            stride: 0,
            pixels: (0..np).map(|i| (i / n, i % n)).collect(),
            exposures: (1..=rows).collect(),
            measured,
            noise: vec![1.0; rows],
            shot_var_per_e_per_s: vec![0.0; rows],
            noise_scale: Default::default(),
            spread_rel: vec![0.0; len],
            fluence_e: vec![5e4; len],
            neighbour_excess_e: vec![0.0; len],
            t_since_s: vec![100.0; rows],
            event: vec![0; rows],
            illumination_time_s: vec![481.0; rows],
            temperature_k: vec![80.0; rows],
            earlier_illuminations: vec![0.0; rows],
            radius: vec![0.5; np],
        };
        (s, vec![1.0; len])
    }

    /// Unit-variance white noise over `n x n` pixels smoothed by a box of half-width
    /// `h` (correlated over ~`h` px), times `scale`.
    fn smooth_field(n: usize, h: usize, scale: f64, seed: u64) -> Vec<f64> {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let white: Vec<f64> = (0..n * n)
            .map(|_| rng.sample::<f64, _>(StandardNormal))
            .collect();
        let mut out = vec![0.0; n * n];
        for y in 0..n {
            for x in 0..n {
                let (mut sum, mut cnt) = (0.0, 0.0_f64);
                for yy in y.saturating_sub(h)..(y + h + 1).min(n) {
                    for xx in x.saturating_sub(h)..(x + h + 1).min(n) {
                        sum += white[yy * n + xx];
                        cnt += 1.0;
                    }
                }
                out[y * n + x] = scale * sum / cnt.sqrt();
            }
        }
        out
    }

    /// Independent pixels: the score is a standard normal draw, the fitted kernel has
    /// no correlation and the design effect is 1.
    #[test]
    fn independent_pixels_score_near_zero_and_no_design_effect() {
        let (s, pred) = one_cell(48, 4, &vec![0.0; 48 * 48], 1);
        let (t, pairs) = score(&s, &pred, SCORE_LENGTH_PX);
        assert!(pairs > 100_000, "{pairs}");
        assert!(t.abs() < 3.5, "T {t}");
        let kf = fit_kernel(&pair_correlation(&s, &pred)).expect("fit");
        assert!(kf.kernel.corr < 0.01, "{kf:?}");
        let deff = design_effects(&s, &pred, &kf.kernel);
        assert_eq!(deff.len(), 1);
        assert!(deff[0].1 < 1.2, "{deff:?}");
    }

    /// A pixel field shared over ~3 px (the same at every exposure): the score is far
    /// above any standard normal draw, the kernel finds a positive correlation over a
    /// few pixels and the cell's design effect is well above 1.
    #[test]
    fn a_shared_field_is_scored_and_widens_the_cell() {
        let n = 48;
        let (s, pred) = one_cell(n, 4, &smooth_field(n, 3, 1.0, 9), 1);
        let (t, _) = score(&s, &pred, SCORE_LENGTH_PX);
        assert!(t > 10.0, "T {t}");
        let pc = pair_correlation(&s, &pred);
        // the nearest pixels' indicators go together, in the same exposure and across
        assert!(
            pc.same_exposure[1] > 0.05 && pc.other_exposures[1] > 0.05,
            "{pc:?}"
        );
        let kf = fit_kernel(&pc).expect("fit");
        assert!(kf.kernel.corr > 0.05, "{kf:?}");
        assert!((1.0..10.0).contains(&kf.kernel.length_px), "{kf:?}");
        let deff = design_effects(&s, &pred, &kf.kernel);
        assert!(deff[0].1 > 5.0, "{deff:?}");
    }

    /// Regression (compare took 88.9 s on the 256 x 256 14 h lab sequence): the pair
    /// correlations and design effects summed per pixel equal the sums over every pair
    /// of samples, with pixels missing some exposures (unusable samples).
    #[test]
    fn sums_over_pixels_equal_the_sums_over_pairs_of_samples() {
        let n = 20;
        let rows = 5;
        let (mut s, pred) = one_cell(n, rows, &smooth_field(n, 2, 1.0, 3), 2);
        for i in (0..s.measured.len()).step_by(7) {
            s.measured[i] = f64::NAN;
        }
        let np = s.npix();
        let cs = cells(&s, &pred);
        assert_eq!(cs.len(), 1);
        let c = &cs[0].1;
        let nclass = MAX_LAG_PX + 1;
        let kernel = Kernel {
            corr: 0.2,
            length_px: 3.0,
        };
        let (mut sum, mut cnt, mut acc) = (vec![0.0; 2 * nclass], vec![0u64; 2 * nclass], 0.0);
        for a in 0..c.members.len() {
            for b in a + 1..c.members.len() {
                let (ia, ib) = (c.members[a], c.members[b]);
                let ((ya, xa), (yb, xb)) = (s.pixels[ia % np], s.pixels[ib % np]);
                let d = ((ya as f64 - yb as f64).powi(2) + (xa as f64 - xb as f64).powi(2)).sqrt();
                if ia % np == ib % np || d > MAX_LAG_PX as f64 + 1e-9 {
                    continue;
                }
                let k = usize::from(ia / np != ib / np) * nclass + d.round() as usize;
                sum[k] += c.w[a] * c.w[b] + 1.0 / (c.w.len() as f64 - 1.0);
                cnt[k] += 1;
                acc += kernel.at(d);
            }
        }
        let pc = pair_correlation(&s, &pred);
        let counts = [
            pc.same_exposure_pairs.clone(),
            pc.other_exposures_pairs.clone(),
        ]
        .concat();
        assert_eq!(counts, cnt);
        let means = [pc.same_exposure.clone(), pc.other_exposures.clone()].concat();
        assert!(cnt.iter().sum::<u64>() > 10_000);
        for k in 0..2 * nclass {
            let want = if cnt[k] > 0 {
                sum[k] / cnt[k] as f64
            } else {
                0.0
            };
            assert!(
                (means[k] - want).abs() < 1e-12,
                "class {k}: {} {want}",
                means[k]
            );
        }
        let deff = design_effects(&s, &pred, &kernel)[0].1;
        let want = 1.0 + 2.0 * acc / c.members.len() as f64;
        assert!((deff - want).abs() < 1e-9 * want, "{deff} {want}");
    }

    /// Each unordered pair of distinct pixels up to the largest lag is visited once.
    #[test]
    fn the_lags_cover_each_pair_once() {
        let l = lags(1);
        let mut seen = std::collections::BTreeSet::new();
        for &(dy, dx, d) in &l {
            assert!(d > 0.0 && d <= MAX_LAG_PX as f64 + 1e-9);
            assert!(!seen.contains(&(-dy, -dx)), "({dy}, {dx}) and its opposite");
            seen.insert((dy, dx));
        }
        let m = MAX_LAG_PX as i64;
        let all = (-m..=m)
            .flat_map(|dy| (-m..=m).map(move |dx| (dy, dx)))
            .filter(|&(dy, dx)| (dy, dx) != (0, 0) && dy * dy + dx * dx <= m * m)
            .count();
        assert_eq!(2 * l.len(), all);
        // on a grid of 2 px only even lags
        assert!(lags(2)
            .iter()
            .all(|&(dy, dx, _)| dy % 2 == 0 && dx % 2 == 0));
    }
}
