//! Per-pixel response maps: each pixel's own persistence amplitude relative to its
//! fluence bin, measured on a laboratory sequence, shrunk toward the bin's distribution
//! where the pixel's own data are noisy, stored per detector ([`mod@file`]) and applied by
//! the stage through [`crate::model::pixel_response`] (docs/pixel_map.md).
//!
//! # Measurement ([`build`])
//! The model `M` the map belongs to (normally the global `persist fit` model of the same
//! sequence; early release off) is run over the whole sequence. For every illumination
//! `a` whose next exposure `d` is a dark, and every pixel `p` lit in it:
//! - the measured excess of the first dark over the block's late darks,
//!   `e_p = m_p(d) - median_W m_p`, and the same for the model's prediction,
//!   `e'_p = M_p(d) - median_W M_p`; `W` is the last [`LATE_DARKS`] darks of the
//!   illumination's block (at least 2, from the second half of the block in time). The
//!   difference removes the dark level (the same in both) and most of what earlier
//!   illuminations left (slow by then), so no background pixel is needed (a
//!   laboratory flat lights every pixel);
//! - one observation `x = e / e'` of the pixel's ratio to the model in the fluence
//!   range of its fluence in `a` (range 0: at or below `linear_below_e`, the
//!   depletion-region traps; range 1: at or above `saturated_above_e`, or a ramp that
//!   saturated with no slope: the forward-bias traps whose populations the paper's Fig.
//!   3b shows; pixels in between, transients and non-functional pixels give none),
//!   with `sigma_x = sigma_e / e'`, `sigma_e^2 = s^2 (1 + pi / (2 |W|)) + v max(m(d), 0)`:
//!   `s` the noise of one dark (1.4826 MAD over the pixels of the difference of the
//!   block's last two darks, over `sqrt 2`), `v` the line fit's shot-noise variance per
//!   e-/s ([`crate::measure::data::Sequence::shot_var_per_e_per_s`]); kept when
//!   `e' > MIN_SNR sigma_e`;
//! - each observation is divided by the median of its fluence bin's ([`BINS_PER_DECADE`]
//!   per decade, per illumination; the pixel's "relative to its fluence bin"; bins of
//!   fewer than [`MIN_PIXELS`] give none), and several observations of one range
//!   combine by inverse variance.
//!
//! # Shrinkage (empirical Bayes, [`npmle`])
//! Per range, the prior `g` of the ratio is the nonparametric maximum-likelihood
//! estimate (Kiefer and Wolfowitz 1956) on a grid of [`GRID`] ratios, fitted by EM
//! (Laird 1978; Koenker and Mizera 2014 for the grid form) to the observations
//! `x_i ~ N(theta_i, sigma_i^2)`, `theta_i ~ g`, on at most [`PRIOR_SAMPLE`] pixels (a
//! regular subsample). A nonparametric prior keeps the several peaks of the pixel
//! populations: a normal prior would pull a pixel of the low population toward the
//! middle one. Each pixel's posterior on the grid gives its mean (`/ratio`), standard
//! deviation (`/ratio_sigma`) and upper quantile (`/ratio_upper`, at `upper_quantile`);
//! a pixel with no observation in a range has the prior as its posterior. All three are
//! then divided by the prior's [`REFERENCE_QUANTILE`] quantile, so that a ratio of 1 is
//! the bin's 95th percentile: the level of the model's knots before their amplification. A range with
//! fewer than [`MIN_PIXELS`] observed pixels is not measured: its prior is a point mass
//! at 1 and the stage keeps the knots there (`range_measured_*` 0).
//!
//! # Use ([`file::attach`])
//! The model file names the map files with their SHA-256 and a `margin`; the pixel's
//! response is `A_k(F) margin ratio_upper(F)` (1 where the range is not measured).
//! Determinism: no randomness, sequential sums in pixel order.

pub mod command;
pub mod eval;
pub mod file;
pub mod flight;

use crate::error::{Error, Result};
use crate::flags::bits;
use crate::measure::data::{fluence, Sequence};
use crate::model::{Input, Model, ModelParams, Output};
use crate::stats::median;
use ndarray::{Array2, Array3};

/// Late darks per block, at most (module docs).
pub const LATE_DARKS: usize = 8;
/// Grid points of the prior.
pub const GRID: usize = 160;
/// Pixels the prior is fitted on, at most.
pub const PRIOR_SAMPLE: usize = 8000;
/// EM iterations of the prior.
pub const EM_ITERATIONS: usize = 300;
/// Fewest observed pixels for a range to be measured.
pub const MIN_PIXELS: usize = 20;
/// Fluence bins per decade: a pixel's ratio is taken relative to its bin's median.
pub const BINS_PER_DECADE: f64 = 10.0;
/// The prior quantile the stored ratios are relative to: the knots' 95th percentile.
pub const REFERENCE_QUANTILE: f64 = 0.95;
/// Smallest predicted excess, in units of its noise, for an observation.
pub const MIN_SNR: f64 = 1.0;

/// How a map is measured.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct MapConfig {
    pub linear_below_e: f64,
    pub saturated_above_e: f64,
    pub upper_quantile: f64,
}

impl Default for MapConfig {
    /// Full well 200,000 e- (paper section 2.1); the transition +-25 % around it
    /// gives no observation (a pixel there mixes both kinds of traps).
    fn default() -> Self {
        MapConfig {
            linear_below_e: 150_000.0,
            saturated_above_e: 250_000.0,
            upper_quantile: 0.95,
        }
    }
}

/// A measured map of one detector (module docs; the file layout: [`mod@file`]).
#[derive(Debug, Clone, PartialEq)]
pub struct PixelMap {
    pub detector: u8,
    pub model_identity: String,
    pub config: MapConfig,
    /// `[2, ny, nx]` each.
    pub ratio: Array3<f32>,
    pub ratio_sigma: Array3<f32>,
    pub ratio_upper: Array3<f32>,
    pub n_obs: Array3<u8>,
    /// `[2, GRID]`: per range, the grid of ratios (relative to the 95th percentile)
    /// and the prior's weights on it.
    pub prior_grid: Array2<f64>,
    pub prior_weight: Array2<f64>,
    pub range_measured: [bool; 2],
    pub source: String,
}

/// The identity of `params` without its pixel map: what a map is measured against.
pub fn base_identity(params: &ModelParams) -> String {
    let mut p = params.clone();
    p.pixel_map = None;
    p.identity()
}

/// One pixel's observations in one range, combined by inverse variance.
#[derive(Debug, Clone, Copy, Default)]
struct Obs {
    sum_wx: f64,
    sum_w: f64,
    n: u8,
}

/// The model's predicted current of every exposure of `seq` in `keep` (whole array).
fn predictions(
    params: &ModelParams,
    seq: &Sequence,
    keep: &[bool],
) -> Result<Vec<Option<Array2<f32>>>> {
    let mut p = params.clone();
    p.early_release.enabled = false;
    p.pixel_map = None;
    let model = Model::new(p)?;
    let (ny, nx) = (seq.ny, seq.nx);
    let mut st = model.new_state(ny, nx);
    let mut cur = Array2::<f32>::zeros((ny, nx));
    let mut pf = Array2::<u8>::zeros((ny, nx));
    let mut out = Vec::with_capacity(seq.exposures.len());
    for (k, e) in seq.exposures.iter().enumerate() {
        step_exposure(&model, &mut st, e, Some(0.0), &mut cur, &mut pf)?;
        out.push(keep[k].then(|| cur.clone()));
    }
    Ok(out)
}

/// Step `model` over one product `e` (its flags copied, history complete), writing the
/// predicted current and the persistence flags; `background_e_per_s` as
/// [`Input::background_e_per_s`].
pub fn step_exposure(
    model: &Model,
    st: &mut crate::model::State,
    e: &crate::product::Exposure,
    background_e_per_s: Option<f64>,
    cur: &mut Array2<f32>,
    pf: &mut Array2<u8>,
) -> Result<()> {
    let mut flags = e.flags.clone();
    let input = Input {
        image_e_per_s: e.image.view(),
        exposure_index: e.meta.exposure_index,
        t_start_unix_s: e.meta.t_start.0,
        t_exposure_s: e.meta.t_exposure_s,
        t_illuminated_s: e.meta.t_illuminated_s(),
        history_incomplete: false,
        background_e_per_s,
    };
    let env = crate::model::StepContext {
        focal_plane_temp_k: e.meta.focal_plane_temp_k,
        ..Default::default()
    };
    model.step_with(
        st,
        &input,
        &env,
        &mut Output {
            flags: &mut flags,
            current_e_per_s: cur,
            pflags: pf,
        },
    )?;
    Ok(())
}

/// One illumination's first dark and late darks (module docs), if it has them.
fn block_of(seq: &Sequence, a: usize) -> Option<(usize, Vec<usize>)> {
    let d = a + 1;
    if d >= seq.exposures.len() || seq.illuminations.contains(&d) {
        return None;
    }
    let end = seq
        .illuminations
        .iter()
        .copied()
        .find(|&i| i > a)
        .unwrap_or(seq.exposures.len());
    let darks: Vec<usize> = (d + 1..end).collect();
    let t_last = seq.t_mid_after_s(a, *darks.last()?);
    let late: Vec<usize> = darks
        .into_iter()
        .filter(|&k| seq.t_mid_after_s(a, k) >= 0.5 * t_last)
        .collect();
    let late = late[late.len().saturating_sub(LATE_DARKS)..].to_vec();
    (late.len() >= 2).then_some((d, late))
}

/// 1.4826 MAD over the pixels of `(b - a) / sqrt 2` (finite pairs).
fn pair_noise(a: &Array2<f64>, b: &Array2<f64>) -> f64 {
    let d: Vec<f64> = a
        .iter()
        .zip(b.iter())
        .map(|(x, y)| (y - x) / std::f64::consts::SQRT_2)
        .filter(|v| v.is_finite())
        .collect();
    let m = median(&d);
    1.4826 * median(&d.iter().map(|v| (v - m).abs()).collect::<Vec<_>>())
}

/// Measure the map of `seq`'s detector against `params` (module docs).
pub fn build(seq: &Sequence, params: &ModelParams, cfg: &MapConfig) -> Result<PixelMap> {
    if !(cfg.linear_below_e > 0.0
        && cfg.saturated_above_e >= cfg.linear_below_e
        && cfg.saturated_above_e.is_finite())
    {
        return Err(Error::invalid(
            "--linear-below-e",
            "need 0 < linear_below_e <= saturated_above_e, finite",
        ));
    }
    if !(cfg.upper_quantile > 0.0 && cfg.upper_quantile < 1.0) {
        return Err(Error::invalid("--upper-quantile", "must be in (0, 1)"));
    }
    let blocks: Vec<(usize, usize, Vec<usize>)> = seq
        .illuminations
        .iter()
        .filter_map(|&a| block_of(seq, a).map(|(d, w)| (a, d, w)))
        .collect();
    let lab = seq
        .exposures
        .iter()
        .any(|e| e.meta.t_illuminated_s.is_some());
    if !lab || blocks.is_empty() {
        return Err(Error::invalid(
            "t_illuminated_s",
            "no illumination followed by a first dark and at least 3 darks (a laboratory sequence is needed)",
        ));
    }
    let mut keep = vec![false; seq.exposures.len()];
    for (_, d, w) in &blocks {
        keep[*d] = true;
        w.iter().for_each(|k| keep[*k] = true);
    }
    let pred = predictions(params, seq, &keep)?;
    let (ny, nx) = (seq.ny, seq.nx);
    let mut obs = vec![[Obs::default(); 2]; ny * nx];
    for (a, d, w) in &blocks {
        // (pixel, range, fluence bin, x, sigma_x) of this illumination
        let mut raw: Vec<(usize, usize, i64, f64, f64)> = Vec::new();
        let f = fluence(&seq.exposures[*a]);
        let fl = &seq.exposures[*a].flags;
        let md = seq.measured(*d);
        let mw: Vec<Array2<f64>> = w.iter().map(|k| seq.measured(*k)).collect();
        let pd = pred[*d].as_ref().expect("kept");
        let pw: Vec<&Array2<f32>> = w.iter().map(|k| pred[*k].as_ref().expect("kept")).collect();
        let s = pair_noise(&mw[mw.len() - 2], &mw[mw.len() - 1]);
        let s = if s.is_finite() { s } else { 0.0 };
        let v = seq.shot_var_per_e_per_s(*d);
        let late_var = 1.0 + std::f64::consts::PI / (2.0 * w.len() as f64);
        for y in 0..ny {
            for x in 0..nx {
                let flags = fl[[y, x]];
                if flags & (bits::NONFUNC | bits::TRANSIENT) != 0 {
                    continue;
                }
                let fe = f[[y, x]];
                let no_slope = fe.is_nan() && flags & bits::SUR_ERROR != 0;
                let range = if no_slope || fe >= cfg.saturated_above_e {
                    1
                } else if fe > 0.0 && fe <= cfg.linear_below_e {
                    0
                } else {
                    continue;
                };
                let late_m: Vec<f64> = mw
                    .iter()
                    .map(|m| m[[y, x]])
                    .filter(|v| v.is_finite())
                    .collect();
                let m1 = md[[y, x]];
                if !m1.is_finite() || late_m.len() < 2 {
                    continue;
                }
                let e = m1 - median(&late_m);
                let late_p: Vec<f64> = pw.iter().map(|p| f64::from(p[[y, x]])).collect();
                let ep = f64::from(pd[[y, x]]) - median(&late_p);
                let sigma = (s * s * late_var + v * m1.max(0.0)).sqrt();
                if !(ep > 0.0 && ep > MIN_SNR * sigma && sigma > 0.0) {
                    continue;
                }
                let bin = if no_slope {
                    i64::MAX
                } else {
                    (BINS_PER_DECADE * fe.log10()).floor() as i64
                };
                raw.push((y * nx + x, range, bin, e / ep, sigma / ep));
            }
        }
        // relative to the bin's median (bins of fewer than MIN_PIXELS give none)
        let mut by_bin: std::collections::BTreeMap<i64, Vec<f64>> = Default::default();
        raw.iter()
            .for_each(|o| by_bin.entry(o.2).or_default().push(o.3));
        let medians: std::collections::BTreeMap<i64, f64> = by_bin
            .into_iter()
            .filter(|(_, v)| v.len() >= MIN_PIXELS)
            .map(|(b, v)| (b, median(&v)))
            .filter(|(_, m)| m.is_finite() && *m > 0.0)
            .collect();
        for (i, range, bin, xr, sx) in raw {
            let Some(m) = medians.get(&bin) else { continue };
            let (xr, sx) = (xr / m, sx / m);
            let o = &mut obs[i][range];
            let wgt = 1.0 / (sx * sx);
            o.sum_wx += wgt * xr;
            o.sum_w += wgt;
            o.n = o.n.saturating_add(1);
        }
    }
    let sh = shrink(&obs, ny, nx, cfg);
    Ok(sh.into_map(
        seq.exposures[0].meta.detector.0,
        base_identity(params),
        cfg,
        String::new(),
    ))
}

impl Shrunk {
    fn into_map(
        self,
        detector: u8,
        model_identity: String,
        cfg: &MapConfig,
        source: String,
    ) -> PixelMap {
        PixelMap {
            detector,
            model_identity,
            config: cfg.clone(),
            ratio: self.ratio,
            ratio_sigma: self.ratio_sigma,
            ratio_upper: self.ratio_upper,
            n_obs: self.n_obs,
            prior_grid: self.prior_grid,
            prior_weight: self.prior_weight,
            range_measured: self.range_measured,
            source,
        }
    }
}

/// A map's arrays from per-pixel combined observations.
struct Shrunk {
    ratio: Array3<f32>,
    ratio_sigma: Array3<f32>,
    ratio_upper: Array3<f32>,
    n_obs: Array3<u8>,
    prior_grid: Array2<f64>,
    prior_weight: Array2<f64>,
    range_measured: [bool; 2],
}

/// Per range: the prior (NPMLE on the observed pixels), then every pixel's posterior,
/// relative to the prior's [`REFERENCE_QUANTILE`] (module docs). `obs[y * nx + x]`.
fn shrink(obs: &[[Obs; 2]], ny: usize, nx: usize, cfg: &MapConfig) -> Shrunk {
    // per range: the prior, then every pixel's posterior
    let all: Vec<(f64, f64)> = obs
        .iter()
        .flat_map(|o| o.iter())
        .filter(|o| o.n > 0)
        .map(|o| (o.sum_wx / o.sum_w, (1.0 / o.sum_w).sqrt()))
        .collect();
    let hi = quantile_of(all.iter().map(|o| o.0 + 2.0 * o.1).collect(), 0.999).clamp(2.0, 20.0);
    let grid: Vec<f64> = (0..GRID)
        .map(|i| hi * i as f64 / (GRID - 1) as f64)
        .collect();
    let mut prior_weight = Array2::<f64>::zeros((2, GRID));
    let mut prior_grid = Array2::<f64>::zeros((2, GRID));
    let mut ratio = Array3::<f32>::zeros((2, ny, nx));
    let mut ratio_sigma = Array3::<f32>::zeros((2, ny, nx));
    let mut ratio_upper = Array3::<f32>::zeros((2, ny, nx));
    let mut n_obs = Array3::<u8>::zeros((2, ny, nx));
    let mut range_measured = [false; 2];
    for r in 0..2 {
        let pts: Vec<(usize, f64, f64)> = obs
            .iter()
            .enumerate()
            .filter(|(_, o)| o[r].n > 0)
            .map(|(i, o)| (i, o[r].sum_wx / o[r].sum_w, (1.0 / o[r].sum_w).sqrt()))
            .collect();
        let g = if pts.len() >= MIN_PIXELS {
            range_measured[r] = true;
            let stride = pts.len().div_ceil(PRIOR_SAMPLE).max(1);
            let sample: Vec<(f64, f64)> = pts.iter().step_by(stride).map(|p| (p.1, p.2)).collect();
            npmle(&grid, &sample, EM_ITERATIONS)
        } else {
            // a point mass at 1 (the grid point nearest)
            let mut g = vec![0.0; GRID];
            let j = grid
                .iter()
                .enumerate()
                .min_by(|a, b| (a.1 - 1.0).abs().total_cmp(&(b.1 - 1.0).abs()))
                .map_or(0, |(j, _)| j);
            g[j] = 1.0;
            g
        };
        // ratios relative to the prior's 95th percentile (the knots' level, without
        // their amplification)
        let c = if range_measured[r] {
            posterior_summary(&grid, &g, None, REFERENCE_QUANTILE).2
        } else {
            1.0
        };
        let c = if c > 0.0 { c } else { 1.0 };
        for (j, w) in g.iter().enumerate() {
            prior_weight[[r, j]] = *w;
            prior_grid[[r, j]] = grid[j] / c;
        }
        let rel = |s: (f64, f64, f64)| (s.0 / c, s.1 / c, s.2 / c);
        let prior = rel(posterior_summary(&grid, &g, None, cfg.upper_quantile));
        for y in 0..ny {
            for x in 0..nx {
                let o = obs[y * nx + x][r];
                let s = if o.n > 0 && range_measured[r] {
                    rel(posterior_summary(
                        &grid,
                        &g,
                        Some((o.sum_wx / o.sum_w, (1.0 / o.sum_w).sqrt())),
                        cfg.upper_quantile,
                    ))
                } else {
                    prior
                };
                ratio[[r, y, x]] = s.0 as f32;
                ratio_sigma[[r, y, x]] = s.1 as f32;
                ratio_upper[[r, y, x]] = s.2 as f32;
                n_obs[[r, y, x]] = o.n;
            }
        }
    }
    Shrunk {
        ratio,
        ratio_sigma,
        ratio_upper,
        n_obs,
        prior_grid,
        prior_weight,
        range_measured,
    }
}
/// The `q` quantile of `v` (nearest rank; 0 when empty).
fn quantile_of(mut v: Vec<f64>, q: f64) -> f64 {
    v.retain(|x| x.is_finite());
    if v.is_empty() {
        return 0.0;
    }
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * q).round() as usize]
}

/// The nonparametric maximum-likelihood prior on `grid` of the observations
/// `(x, sigma)` (module docs), by `iterations` EM steps from the uniform prior.
pub fn npmle(grid: &[f64], obs: &[(f64, f64)], iterations: usize) -> Vec<f64> {
    let k = grid.len();
    let mut g = vec![1.0 / k as f64; k];
    if obs.is_empty() {
        return g;
    }
    // likelihoods, each row scaled by its largest entry (the EM step is invariant)
    let lik: Vec<Vec<f64>> = obs
        .iter()
        .map(|&(x, s)| {
            let row: Vec<f64> = grid
                .iter()
                .map(|t| (-0.5 * ((x - t) / s).powi(2)).exp())
                .collect();
            let m = row.iter().copied().fold(0.0, f64::max);
            if m > 0.0 {
                row.iter().map(|v| v / m).collect()
            } else {
                // far from every grid point: the nearest carries it
                let j = grid
                    .iter()
                    .enumerate()
                    .min_by(|a, b| (a.1 - x).abs().total_cmp(&(b.1 - x).abs()))
                    .map_or(0, |(j, _)| j);
                let mut r = vec![0.0; k];
                r[j] = 1.0;
                r
            }
        })
        .collect();
    let mut next = vec![0.0; k];
    for _ in 0..iterations {
        next.fill(0.0);
        for row in &lik {
            let den: f64 = row.iter().zip(&g).map(|(l, w)| l * w).sum();
            if den > 0.0 {
                for j in 0..k {
                    next[j] += row[j] * g[j] / den;
                }
            }
        }
        let total: f64 = next.iter().sum();
        if total > 0.0 {
            for j in 0..k {
                g[j] = next[j] / total;
            }
        }
    }
    g
}

/// `(mean, sd, quantile q)` of the posterior on `grid` for prior `g` and one
/// observation `(x, sigma)` (`None`: the prior itself).
pub fn posterior_summary(
    grid: &[f64],
    g: &[f64],
    obs: Option<(f64, f64)>,
    q: f64,
) -> (f64, f64, f64) {
    let w: Vec<f64> = match obs {
        None => g.to_vec(),
        Some((x, s)) => {
            let logs: Vec<f64> = grid.iter().map(|t| -0.5 * ((x - t) / s).powi(2)).collect();
            let m = logs.iter().copied().fold(f64::NEG_INFINITY, f64::max);
            let w: Vec<f64> = logs.iter().zip(g).map(|(l, p)| p * (l - m).exp()).collect();
            if w.iter().sum::<f64>() > 0.0 {
                w
            } else {
                g.to_vec()
            }
        }
    };
    let total: f64 = w.iter().sum();
    if total <= 0.0 {
        return (1.0, 0.0, 1.0);
    }
    let mean = grid.iter().zip(&w).map(|(t, p)| t * p).sum::<f64>() / total;
    let var = grid
        .iter()
        .zip(&w)
        .map(|(t, p)| (t - mean).powi(2) * p)
        .sum::<f64>()
        / total;
    let mut acc = 0.0;
    let mut upper = *grid.last().unwrap_or(&1.0);
    for (t, p) in grid.iter().zip(&w) {
        acc += p / total;
        if acc >= q {
            upper = *t;
            break;
        }
    }
    (mean, var.max(0.0).sqrt(), upper)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two well separated populations (0.2 and 1.0) observed with noise 0.05: the NPMLE
    /// puts its mass near both, and a noisy observation between them gets a posterior
    /// quantile reaching the upper one (a normal prior would not).
    #[test]
    fn npmle_keeps_two_populations() {
        let grid: Vec<f64> = (0..121).map(|i| i as f64 * 0.0125).collect();
        let mut obs = Vec::new();
        for i in 0..400 {
            let z = ((i * 37 % 101) as f64 / 101.0 - 0.5) * 0.1;
            obs.push((if i % 4 == 0 { 0.2 } else { 1.0 } + z, 0.05));
        }
        let g = npmle(&grid, &obs, 300);
        let mass = |lo: f64, hi: f64| -> f64 {
            grid.iter()
                .zip(&g)
                .filter(|(t, _)| (lo..hi).contains(*t))
                .map(|(_, w)| w)
                .sum()
        };
        assert!((mass(0.1, 0.3) - 0.25).abs() < 0.03, "{}", mass(0.1, 0.3));
        assert!((mass(0.9, 1.1) - 0.75).abs() < 0.03);
        let (m, _, up) = posterior_summary(&grid, &g, Some((0.6, 0.4)), 0.95);
        assert!(up > 0.95 && m < 1.0, "{m} {up}");
        let (m, s, _) = posterior_summary(&grid, &g, Some((0.21, 0.01)), 0.95);
        assert!((m - 0.21).abs() < 0.03 && s < 0.05, "{m} {s}");
    }
}
