//! The flexible base that effects are tested against.
//!
//! What every detector does is not an effect: a response that is some function of the
//! fluence and a decay that is some sum of exponentials. The base is
//!
//! `b(p, k) = m(p, k) + sum_(a <= k) sum_j A_j(F_a(p)) exp(-t(a, k) / tau_j)`
//!
//! with `m` the fitted model's prediction (so the model's own effects, such as
//! `refill`, stay in the base)
//! over the illuminations `a` before exposure `k` (`F_a(p)` the pixel's extrapolated
//! fluence in `a`, `t(a, k)` the time from the end of `a` to the middle of `k` on the
//! model's clock, [`Clock`]; with a model whose hooks change the fluence or couple
//! neighbours in the readout, `ipc`, the fluence after those hooks and each term
//! coupled as the model's prediction is, [`View`]), with
//! `tau_j` a fixed grid of [`TAU_S`] and `A_j(F)` free (a correction of the model's response and decay), piecewise linear in `log10 F`
//! between knots every fifth of a decade: a free response per fluence bin and free
//! weights over a fixed grid of rates, shared by every illumination event and
//! superposed linearly. It follows a t^-0.85 ... t^-1.15 decay, any shape of the
//! response around saturation and any mix of trap populations; what it cannot make is a
//! dependence on anything but the fluence and the time since each illumination (the
//! illumination's duration, the temperature, how full the traps were, the neighbours,
//! the position). It is linear in the `A_j`, fitted once by weighted least squares
//! (weights `1 / (sigma_k^2 + (0.1 p)^2)`, `p` the model's prediction; a small ridge
//! keeps unused knots at 0) on at most [`MAX_FIT_SAMPLES`] samples taken at a fixed
//! stride (deterministic).
//!
//! # Pixel reference
//! [`predict_scaled`] multiplies the base by each pixel's own factor, quadratic in the
//! log of the time since the illumination and quadratic in the log of the
//! illumination's fluence (the pixel's own response: its full well moves its
//! saturation onset), plus an amplitude of its own for the share
//! of its current that comes from illuminations that saturated it (the saturated
//! traps' population, which a campaign that saturates a pixel in some illuminations and
//! not in others shows apart), and gives the pixels saturated in an illumination knots
//! of their own; it is weighted by the measurement noise alone (exposure noise, pooled
//! over the exposures of one integration length, and the shot noise of the reference's
//! own current, each part's variance scaled once by what the residuals of the model
//! under diagnosis show, [`measure_noise_scale`]). Its residuals are those of each pixel, not of a
//! population's 95th percentile: each divided by its noise less its leverage
//! ([`Scaled::cells`]), they measure how far a description that absorbs the decay law,
//! its fluence dependence, the response around saturation and the mix of trap
//! populations stands from the data. `persist diagnose` prints its RMS; nothing-hidden
//! sequences of both truth generators: `docs/validation/reference_rms.md` (`make
//! validation PAGES=reference`). Event-level covariates are tested against it
//! ([`super::contrast`], "Two bases"): what it leaves them is how a pixel's
//! illuminations of equal fluence differ (duration, history, temperature); an effect
//! acting only on the one illumination of its fluence at a pixel is taken in by the
//! pixel's response terms; the effects are still refitted and gated against
//! the measurements' description ([`super::reference`]).

use super::data::{fluence, Sequence, BACKGROUND_FLUENCE_E};
use super::eval::{NoiseScale, Samples};
use crate::model::effect::{Effect, IntervalCtx};
use crate::model::params::ModelParams;
use crate::model::response::Response;
use ndarray::Array2;
use rayon::prelude::*;

/// The fixed grid of decay times, s: four per decade, as fine as the first darks of a
/// laboratory sequence (90-450 s after the illumination) need to be followed to 1-2 %.
pub const TAU_S: [f64; 17] = [
    10.0, 17.8, 31.6, 56.2, 100.0, 178.0, 316.0, 562.0, 1e3, 1.78e3, 3.16e3, 5.62e3, 1e4, 1.78e4,
    3.16e4, 5.62e4, 1e5,
];
/// Response knots per decade of fluence.
const KNOTS_PER_DECADE: f64 = 5.0;
/// Knots from 10^LOG_F_MIN to 10^LOG_F_MAX e-.
const LOG_F_MIN: f64 = 3.0;
const LOG_F_MAX: f64 = 7.0;
/// The correction's normal equations are summed over this many chunks of samples, in
/// parallel, then added in order (deterministic).
const FIT_CHUNKS: usize = 16;
/// Samples used in the fit at most.
pub const MAX_FIT_SAMPLES: usize = 300_000;

fn n_knots() -> usize {
    ((LOG_F_MAX - LOG_F_MIN) * KNOTS_PER_DECADE).round() as usize + 1
}

/// The (knot, weight) pairs of the response at fluence `f` (two neighbouring knots).
fn knots_of(f: f64) -> Option<[(usize, f64); 2]> {
    if !(f.is_finite() && f > BACKGROUND_FLUENCE_E) {
        return None;
    }
    let u = ((f.log10() - LOG_F_MIN) * KNOTS_PER_DECADE).clamp(0.0, (n_knots() - 1) as f64);
    let k0 = (u.floor() as usize).min(n_knots() - 2);
    let w = u - k0 as f64;
    Some([(k0, 1.0 - w), (k0 + 1, w)])
}

/// The time on which the base's decay terms run: the model's clock. A model whose rate
/// hook ([`Effect::rates`]; `temperature`: rates scaled by each exposure's focal-plane
/// temperature) changes its terms' rates from one interval to the next decays on a
/// clock of its own: over each interval from the reset ending exposure `m - 1` to the
/// reset ending `m`, a term of rate `1/tau_j` decays as one of rate `q_mj / tau_j` in
/// real time, `q_mj` the ratio the model's rate hooks give that term's rate in the
/// interval. The base's term `j` then counts `t_j(a, k) = sum_m q_mj dt_m` from the
/// reset ending `a` to the middle of `k` (the last interval up to the middle of `k`)
/// in place of `t(a, k)`: the correction and the pixels' terms follow the model's
/// decay where only the rate, not the shape, differs between illuminations of one
/// pixel. With no rate hook (or one that changes nothing, `temperature` at
/// `activation_ev` 0) every `q` is 1 and the clock is real time, bit for bit.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Clock {
    /// Per exposure of the sequence, per term of [`TAU_S`]: the term's elapsed time on
    /// the model's clock at the reset ending the exposure, from the reset ending the
    /// first exposure, s. Empty: real time.
    at_reset_s: Vec<[f64; TAU_S.len()]>,
    /// Per exposure and term: `q`, the term's rate in the interval ending with the
    /// exposure's reset over its own rate (1 for the first exposure).
    ratio: Vec<[f64; TAU_S.len()]>,
}

impl Clock {
    /// Real time: every term decays at its own rate.
    pub fn real() -> Clock {
        Clock::default()
    }

    /// The clock of a model with the effects `effects` at the temperatures `temps_k`,
    /// one per exposure of `seq`.
    fn of_effects(effects: &[Box<dyn Effect>], seq: &Sequence, temps_k: &[Option<f64>]) -> Clock {
        const N: usize = TAU_S.len();
        let n = seq.exposures.len();
        if effects.is_empty() || n < 2 {
            return Clock::real();
        }
        let end_s = |m: usize| {
            let e = &seq.exposures[m].meta;
            e.t_start.0 + e.t_exposure_s
        };
        let mut ratio = vec![[1.0; N]; n];
        for (m, q) in ratio.iter_mut().enumerate().skip(1) {
            let e = &seq.exposures[m].meta;
            let t_slew_s = e.t_start.0 - end_s(m - 1);
            let ctx = IntervalCtx {
                t_slew_s,
                t_exposure_s: e.t_exposure_s,
                t_meas_s: t_slew_s + 0.5 * e.t_exposure_s,
                t_elapsed_s: t_slew_s + e.t_exposure_s,
                focal_plane_temp_k: temps_k[m],
            };
            let mut c = [1.0; N];
            let mut r = TAU_S.map(|tau| 1.0 / tau);
            for effect in effects {
                effect.rates(&ctx, &mut c, &mut r);
            }
            // the ratio to the term's own rate (1 exactly where a hook changes nothing)
            for ((q, r), tau) in q.iter_mut().zip(r).zip(TAU_S) {
                let v = r / (1.0 / tau);
                if v.is_finite() && v > 0.0 {
                    *q = v;
                }
            }
        }
        if ratio.iter().flatten().all(|&q| q == 1.0) {
            return Clock::real();
        }
        let mut at_reset_s = vec![[0.0; N]; n];
        for m in 1..n {
            let dt = (end_s(m) - end_s(m - 1)).max(0.0);
            for j in 0..N {
                at_reset_s[m][j] = at_reset_s[m - 1][j] + dt * ratio[m][j];
            }
        }
        Clock { at_reset_s, ratio }
    }

    /// Whether this is real time.
    pub fn is_real(&self) -> bool {
        self.ratio.is_empty()
    }

    /// The time term `j` of [`TAU_S`] has decayed from the reset ending exposure `a`
    /// to the middle of exposure `k` (`k > a`), s, at least 0.
    fn elapsed_s(&self, seq: &Sequence, a: usize, k: usize, j: usize) -> f64 {
        if self.is_real() || k <= a || k >= self.ratio.len() {
            return seq.t_mid_after_s(a, k).max(0.0);
        }
        let last = seq.t_mid_after_s(k - 1, k).max(0.0) * self.ratio[k][j];
        (self.at_reset_s[k - 1][j] - self.at_reset_s[a][j] + last).max(0.0)
    }
}

/// The model as the base sees it: the clock its decay terms run on ([`Clock`]) and the
/// readout its correction goes through (the fluence after the model's fluence hooks, and
/// its readout's coupling of neighbours, [`Effect::readout_kernel`]).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct View {
    pub clock: Clock,
    readout: Readout,
}

impl View {
    /// The view of the model `params` over `seq`: its clock and its readout, as the
    /// model's step applies its hooks. An effect that does not build is left out (the
    /// model's own run refuses it).
    pub fn of_model(params: &ModelParams, seq: &Sequence) -> View {
        View::of_model_at_temperatures(params, seq, &seq.temperatures_k())
    }

    /// [`View::of_model`] with each exposure's focal-plane temperature `temps_k[k]` in
    /// place of the one it records (as [`crate::measure::eval::predict_at_temperatures`]).
    pub fn of_model_at_temperatures(
        params: &ModelParams,
        seq: &Sequence,
        temps_k: &[Option<f64>],
    ) -> View {
        let effects: Vec<Box<dyn Effect>> = params
            .effects
            .iter()
            .filter_map(|e| crate::model::effects::build(e).ok())
            .collect();
        View {
            clock: Clock::of_effects(&effects, seq, temps_k),
            readout: Readout::of_effects(&effects, seq),
        }
    }
}

/// How the model reads out what the traps hold, which the base's correction follows:
/// the correction `A_j(F)` corrects the model's response, so it is evaluated at the
/// fluence the model's response is (after its effects' fluence hooks,
/// [`Effect::fluence`]: `ipc` takes out the neighbours' coupled share) and coupled into
/// the neighbours as the model's prediction is ([`Effect::readout_kernel`]: next to a
/// bright pinhole a pixel reads a share of the pinhole's persistence, whose correction
/// is the one at the pinhole's fluence, not at its own). A model without such hooks:
/// the measured fluence and no coupling, bit for bit.
#[derive(Debug, Clone, Default, PartialEq)]
struct Readout {
    /// Per illumination of the sequence (in its order), the fluence after the model's
    /// fluence hooks, e-; empty: the measured fluence.
    fluence: Vec<Array2<f64>>,
    /// `(dy, dx, weight)` of the readout's coupling; the centre keeps `1 - sum`.
    kernel: Vec<(isize, isize, f64)>,
}

impl Readout {
    fn of_effects(effects: &[Box<dyn Effect>], seq: &Sequence) -> Readout {
        let hooked: Vec<&dyn Effect> = effects
            .iter()
            .filter(|e| e.has_fluence())
            .map(|e| e.as_ref())
            .collect();
        let fluence = if hooked.is_empty() {
            Vec::new()
        } else {
            seq.illuminations
                .iter()
                .map(|&a| {
                    let mut f = fluence(&seq.exposures[a]);
                    for e in &hooked {
                        e.fluence(&mut f);
                    }
                    f
                })
                .collect()
        };
        Readout {
            fluence,
            kernel: effects.iter().flat_map(|e| e.readout_kernel()).collect(),
        }
    }
}

/// The response knots of illumination `m` at pixel `(y, x)` as the readout couples
/// them ([`Readout`]): `(knot, weight)`, the pixel's own two knots weighted by the
/// kernel's centre and each coupled neighbour's by its weight; the saturated pixels'
/// knots shifted to their own when `m` splits them.
fn coupled_knots(
    m: &Map,
    kernel: &[(isize, isize, f64)],
    y: usize,
    x: usize,
    out: &mut Vec<(usize, f64)>,
) {
    out.clear();
    let (ny, nx) = m.fluence.dim();
    let centre = 1.0 - kernel.iter().map(|k| k.2).sum::<f64>();
    let own = std::iter::once((0, 0, centre)).chain(kernel.iter().copied());
    for (dy, dx, w) in own {
        let (Some(yy), Some(xx)) = (y.checked_add_signed(dy), x.checked_add_signed(dx)) else {
            continue;
        };
        if yy >= ny || xx >= nx {
            continue;
        }
        let Some(mut kn) = knots_of(m.fluence[(yy, xx)]) else {
            continue;
        };
        if m.overflow.as_ref().is_some_and(|o| o[(yy, xx)]) {
            // the saturated pixels' response: knots of their own
            kn.iter_mut().for_each(|k| k.0 += n_knots());
        }
        out.extend(kn.iter().filter(|k| k.1 > 0.0).map(|&(k, v)| (k, v * w)));
    }
}

/// The base's prediction of every sample: the model's prediction `pred` plus the
/// correction fitted on `s` (module docs); `pred` itself when the fit fails.
pub fn predict(seq: &Sequence, view: &View, s: &Samples, pred: &[f64]) -> Vec<f64> {
    let feat = Features::new(seq, view, s, &fluence_maps(seq, false, &view.readout));
    let ones = vec![1.0; s.len()];
    match fit_correction(&feat, s, pred, &ones, relative_variance) {
        Some(coef) => corrected(&feat, pred, &coef),
        None => pred.to_vec(),
    }
}

/// The variance [`predict`] weights sample `i` by at prediction `p`: its exposure
/// noise and a tenth of the prediction (module docs).
fn relative_variance(s: &Samples, i: usize, p: f64) -> f64 {
    s.noise[i / s.npix().max(1)].powi(2) + (0.1 * p).powi(2)
}

/// The variance of a measurement of sample `i` at current `p`: its exposure noise
/// (`noise`, per row of `s`) and the current's shot noise
/// ([`Samples::shot_var_per_e_per_s`]), each scaled by [`Samples::noise_scale`].
fn measurement_variance(noise: &[f64], s: &Samples, i: usize, p: f64) -> f64 {
    let row = i / s.npix().max(1);
    let scale = s.noise_scale;
    scale.read_var * noise[row].powi(2) + scale.shot_var * s.shot_var_per_e_per_s[row] * p.max(0.0)
}

/// One illumination's fluence map, and which pixels saturated in it when their
/// response has knots of its own.
struct Map {
    /// Index into the sequence.
    illumination: usize,
    fluence: Array2<f64>,
    overflow: Option<Array2<bool>>,
}

/// The fluence map of every illumination; with `split_saturated`, the pixels flagged
/// `OVERFLOW` in it.
fn fluence_maps(seq: &Sequence, split_saturated: bool, readout: &Readout) -> Vec<Map> {
    seq.illuminations
        .iter()
        .enumerate()
        .map(|(i, &a)| {
            let e = &seq.exposures[a];
            Map {
                illumination: a,
                fluence: readout
                    .fluence
                    .get(i)
                    .cloned()
                    .unwrap_or_else(|| fluence(e)),
                overflow: split_saturated
                    .then(|| e.flags.mapv(|f| f & crate::flags::bits::OVERFLOW != 0)),
            }
        })
        .collect()
}

/// Every sample's sparse features ([`features`]), worked out once for the fits and
/// corrections that share them.
struct Features {
    /// Sample `i`'s entries are `entries[start[i]..start[i + 1]]`, one per parameter, in
    /// ascending order of the parameter ([`sample_features`]).
    start: Vec<usize>,
    entries: Vec<(usize, f64)>,
    /// Whether the saturated pixels' response has knots of its own.
    split: bool,
}

impl Features {
    /// Sample `i` (row `i / npix`, pixel `i % npix`) has, per illumination `m` before its
    /// exposure, per term `j` of [`TAU_S`], the entries `(knot * TAU_S.len() + j, w
    /// d_j)`: `(knot, w)` the coupled knots of `m` at the pixel ([`coupled_knots`]) and
    /// `d_j = exp(-t_j / tau_j)` on the model's clock, left out below 1e-9. Entries of one
    /// parameter are summed (illuminations of one pixel at neighbouring fluences share
    /// knots, and the normal equations' cost is the square of the entries), in
    /// ascending parameter order. The knots depend on the pixel alone and the decays on
    /// the row alone, so each is worked out once.
    fn new(seq: &Sequence, view: &View, s: &Samples, maps: &[Map]) -> Features {
        let np = s.npix();
        let kernel = &view.readout.kernel;
        let knots: Vec<Vec<Vec<(usize, f64)>>> = s
            .pixels
            .par_iter()
            .map(|&(y, x)| {
                let mut kn = Vec::new();
                maps.iter()
                    .map(|m| {
                        coupled_knots(m, kernel, y, x, &mut kn);
                        merged_by_knot(&mut kn)
                    })
                    .collect()
            })
            .collect();
        let decays: Vec<Vec<Option<[f64; TAU_S.len()]>>> = s
            .exposures
            .iter()
            .map(|&k| maps.iter().map(|m| decay_terms(seq, view, m, k)).collect())
            .collect();
        let per: Vec<Vec<(usize, f64)>> = (0..s.len())
            .into_par_iter()
            .map_init(Vec::new, |scratch, i| {
                let (row, px) = (i / np, i % np);
                sample_features(&knots[px], &decays[row], scratch)
            })
            .collect();
        let mut start = Vec::with_capacity(per.len() + 1);
        start.push(0);
        for f in &per {
            start.push(start[start.len() - 1] + f.len());
        }
        Features {
            start,
            entries: per.concat(),
            split: maps.iter().any(|m| m.overflow.is_some()),
        }
    }

    fn of(&self, i: usize) -> &[(usize, f64)] {
        &self.entries[self.start[i]..self.start[i + 1]]
    }
}

/// `kn` sorted by knot with the weights of one knot summed.
fn merged_by_knot(kn: &mut [(usize, f64)]) -> Vec<(usize, f64)> {
    kn.sort_unstable_by(|a, b| a.0.cmp(&b.0).then(a.1.total_cmp(&b.1)));
    let mut out: Vec<(usize, f64)> = Vec::with_capacity(kn.len());
    for &(k, w) in kn.iter() {
        match out.last_mut() {
            Some(last) if last.0 == k => last.1 += w,
            _ => out.push((k, w)),
        }
    }
    out
}

/// Each term's decay `exp(-t_j / tau_j)` from illumination `m` to the middle of
/// exposure `k` on the model's clock, 0 below 1e-9; None when `m` is not before `k`.
fn decay_terms(seq: &Sequence, view: &View, m: &Map, k: usize) -> Option<[f64; TAU_S.len()]> {
    let a = m.illumination;
    if a >= k {
        return None;
    }
    let mut d = [0.0; TAU_S.len()];
    for (j, tau) in TAU_S.iter().enumerate() {
        let v = (-view.clock.elapsed_s(seq, a, k, j) / tau).exp();
        d[j] = if v < 1e-9 { 0.0 } else { v };
    }
    Some(d)
}

/// One sample's entries ([`Features::new`]) from its pixel's knots per illumination
/// and its row's decays per illumination; `scratch` holds `(knot, illumination)`.
fn sample_features(
    knots: &[Vec<(usize, f64)>],
    decays: &[Option<[f64; TAU_S.len()]>],
    scratch: &mut Vec<(usize, usize, f64)>,
) -> Vec<(usize, f64)> {
    scratch.clear();
    for (m, (kn, d)) in knots.iter().zip(decays).enumerate() {
        if d.is_some() {
            scratch.extend(kn.iter().map(|&(k, w)| (k, m, w)));
        }
    }
    scratch.sort_unstable_by_key(|&(k, m, _)| (k, m));
    let mut out = Vec::new();
    for group in scratch.chunk_by(|a, b| a.0 == b.0) {
        let mut sum = [0.0; TAU_S.len()];
        let mut any = [false; TAU_S.len()];
        for &(_, m, w) in group {
            // gathered above only where the illumination has decays
            if let Some(d) = &decays[m] {
                for j in (0..TAU_S.len()).filter(|&j| d[j] > 0.0) {
                    sum[j] += w * d[j];
                    any[j] = true;
                }
            }
        }
        out.extend(
            (0..TAU_S.len())
                .filter(|&j| any[j])
                .map(|j| (group[0].0 * TAU_S.len() + j, sum[j])),
        );
    }
    out
}

/// `pred` plus the correction `coef` at every sample.
fn corrected(feat: &Features, pred: &[f64], coef: &[f64]) -> Vec<f64> {
    (0..pred.len())
        .into_par_iter()
        .map(|i| pred[i] + feat.of(i).iter().map(|&(a, v)| coef[a] * v).sum::<f64>())
        .collect()
}

/// The correction's coefficients: weighted least squares of `measured / scale_p -
/// pred` on the features (module docs), each sample weighted by `scale_p^2` over its
/// variance; None when the normal equations are singular.
fn fit_correction(
    feat: &Features,
    s: &Samples,
    pred: &[f64],
    scale: &[f64],
    variance: impl Fn(&Samples, usize, f64) -> f64 + Sync,
) -> Option<Vec<f64>> {
    let p = if feat.split { 2 } else { 1 } * n_knots() * TAU_S.len();
    let usable: Vec<usize> = (0..s.len())
        .filter(|&i| s.measured[i].is_finite() && pred[i].is_finite())
        .collect();
    let stride = usable.len().div_ceil(MAX_FIT_SAMPLES).max(1);
    let fit: Vec<usize> = usable.iter().copied().step_by(stride).collect();
    // a fixed number of chunks, summed in their order: the same sums whatever the
    // threads (rayon's `reduce` follows its work stealing, and the last bits of a float
    // sum follow the order)
    let chunk = fit.len().div_ceil(FIT_CHUNKS).max(1);
    let partial: Vec<(Vec<f64>, Vec<f64>)> = fit
        .par_chunks(chunk)
        .map(|chunk| {
            let mut ata = vec![0.0; p * (p + 1) / 2];
            let mut atb = vec![0.0; p];
            for &i in chunk {
                let f = feat.of(i);
                let sc = scale[i];
                if f.is_empty() || sc.is_nan() || sc <= 0.0 {
                    continue;
                }
                let w = sc * sc / variance(s, i, sc * pred[i]).max(1e-12);
                let y = s.measured[i] / sc - pred[i];
                for (q, &(a, va)) in f.iter().enumerate() {
                    let wa = w * va;
                    atb[a] += wa * y;
                    // the lower triangle alone, packed by rows (all that `solve_spd`
                    // reads): `f` ascends by parameter, so its first `q + 1` entries are
                    // those at or below `a`
                    let row = &mut ata[packed_row(a)];
                    for &(b, vb) in &f[..=q] {
                        row[b] += wa * vb;
                    }
                }
            }
            (ata, atb)
        })
        .collect();
    let (mut ata, mut atb) = (vec![0.0; p * (p + 1) / 2], vec![0.0; p]);
    for (a, b) in partial {
        ata.iter_mut().zip(a).for_each(|(x, y)| *x += y);
        atb.iter_mut().zip(b).for_each(|(x, y)| *x += y);
    }
    let mut m = vec![0.0; p * p];
    for a in 0..p {
        m[a * p..=a * p + a].copy_from_slice(&ata[packed_row(a)]);
    }
    let trace: f64 = (0..p).map(|j| m[j * p + j]).sum::<f64>() / p as f64;
    for j in 0..p {
        m[j * p + j] += 1e-6 * trace.max(1e-300);
    }
    solve_spd(&mut m, atb, p)
}

/// Row `a` of a lower triangle packed by rows: its entries `(a, 0) ..= (a, a)`.
fn packed_row(a: usize) -> std::ops::RangeInclusive<usize> {
    let start = a * (a + 1) / 2;
    start..=start + a
}

/// Alternations of the scaled base's fit ([`predict_scaled`]).
pub const SCALE_PASSES: usize = 4;

/// Reference time of the per-pixel decay tilt ([`predict_scaled`]), s.
pub const TILT_REFERENCE_S: f64 = 1000.0;

/// Per-pixel terms of [`predict_scaled`]: `L^0 .. L^(PIXEL_TERMS - 1)`.
pub const PIXEL_TERMS: usize = 3;

/// Per-pixel terms of [`predict_scaled`] in all: the powers of `L`, the amplitude
/// after a saturating illumination, and the response's slope and curvature in log
/// fluence.
const ALL_PIXEL_TERMS: usize = PIXEL_TERMS + 3;

/// The regressors of sample `i`'s factor: `L^0 .. L^(PIXEL_TERMS - 1)`, then `sat`
/// ([`saturated_share`]), then `fl` and `fl^2` ([`fluence_tilt`]).
fn pixel_regressors(l: f64, sat: f64, fl: f64) -> [f64; ALL_PIXEL_TERMS] {
    std::array::from_fn(|j| {
        if j < PIXEL_TERMS {
            l.powi(j as i32)
        } else if j == PIXEL_TERMS {
            sat
        } else if j == PIXEL_TERMS + 1 {
            fl
        } else {
            fl * fl
        }
    })
}

/// Each pixel's factor at sample `i` from its terms `c` ([`pixel_regressors`]).
fn pixel_factor(c: &[f64], l: f64, sat: f64, fl: f64) -> f64 {
    c.iter()
        .zip(pixel_regressors(l, sat, fl))
        .map(|(c, x)| c * x)
        .sum()
}

/// Per sample: the share of its persistence current that comes from illuminations
/// that saturated the pixel (`OVERFLOW`), each illumination `a` weighted as the
/// paper's 1/t law has it, by the amplitude the model's response gives its fluence,
/// `A(F_a) / t(a, k)` (the response's rise around saturation: on the paper's Table 1 a
/// saturating illumination leaves about three times the amplitude per electron of an
/// unsaturated one); for a pixel whose sampled shares are not
/// all on one side of one half, else 0 (the saturated traps' amplitude is then a term
/// of its own, which a pixel always or never saturated cannot separate from its
/// overall amplitude).
fn saturated_share(seq: &Sequence, s: &Samples, maps: &[Map], response: &Response) -> Vec<f64> {
    let np = s.npix().max(1);
    let share = |i: usize| -> f64 {
        let (row, (y, x)) = (i / np, s.pixels[i % np]);
        let k = s.exposures[row];
        let (mut sat, mut all) = (0.0, 0.0);
        for m in maps.iter().filter(|m| m.illumination < k) {
            let f = m.fluence[(y, x)];
            if !(f.is_finite() && f > BACKGROUND_FLUENCE_E) {
                continue;
            }
            let w = response.amplitude_e(f) / seq.t_mid_after_s(m.illumination, k).max(1.0);
            all += w;
            if m.overflow.as_ref().is_some_and(|o| o[(y, x)]) {
                sat += w;
            }
        }
        if all > 0.0 {
            sat / all
        } else {
            0.0
        }
    };
    let shares: Vec<f64> = (0..s.len()).map(share).collect();
    let mut sides = vec![(false, false); np];
    for (i, v) in shares.iter().enumerate() {
        let side = &mut sides[i % np];
        if *v > 0.5 {
            side.0 = true;
        } else {
            side.1 = true;
        }
    }
    shares
        .iter()
        .enumerate()
        .map(|(i, v)| {
            if sides[i % np] == (true, true) {
                *v
            } else {
                0.0
            }
        })
        .collect()
}

/// Per sample: the natural log of the fluence of the illumination it follows, less
/// its pixel's mean over the usable samples; 0 for a pixel whose fluences span less
/// than a tenth of an e-fold (its amplitude alone then stands for it). A pixel's
/// response is the population's shifted and bent: its own full well moves the
/// saturation onset (on the simulator's campaign, pixels at 195-198 ke- in the
/// bright illuminations, just below the flag, show 1.5-2 times the population's current
/// in the first dark after the half-fluence ones, 7 % of such a cell beyond 4 sigma
/// without these terms).
fn fluence_tilt(s: &Samples) -> Vec<f64> {
    let np = s.npix().max(1);
    let lf: Vec<f64> = s
        .fluence_e
        .iter()
        .map(|&f| {
            if f.is_finite() && f > BACKGROUND_FLUENCE_E {
                f.ln()
            } else {
                f64::NAN
            }
        })
        .collect();
    let mut acc = vec![(0.0f64, 0usize, f64::INFINITY, f64::NEG_INFINITY); np];
    for (i, &v) in lf.iter().enumerate() {
        if v.is_finite() {
            let a = &mut acc[i % np];
            a.0 += v;
            a.1 += 1;
            a.2 = a.2.min(v);
            a.3 = a.3.max(v);
        }
    }
    lf.iter()
        .enumerate()
        .map(|(i, &v)| {
            let a = acc[i % np];
            if v.is_finite() && a.1 > 0 && a.3 - a.2 >= 0.1 {
                v - a.0 / a.1 as f64
            } else {
                0.0
            }
        })
        .collect()
}

/// The base with a per-pixel amplitude, decay shape and response: `f_p * (pred +
/// correction)`, `f_p = sum_j c_pj L^j + c_s sat + c_f fl + c_ff fl^2` over
/// [`PIXEL_TERMS`] powers of `L = ln(t / TILT_REFERENCE_S)` (`t` since the last
/// illumination), the share `sat` of the current from saturating illuminations
/// (`saturated_share`, its illuminations weighed by `response`, the model's
/// amplitude per fluence) and the log fluence `fl` about the pixel's mean
/// (`fluence_tilt`), the correction as
/// [`predict`]'s (with knots of their own for the pixels saturated in the
/// illumination: the response around saturation) and `c_p` each sampled pixel's own
/// (the mix of trap populations: pixels of one fluence and history differ by a factor
/// and by their share of fast and slow traps, a tilt and a bend of the decay in log
/// time), fitted by alternating the correction and the pixels' terms
/// ([`SCALE_PASSES`]). Each pixel's terms are the weighted least-squares fit of its
/// measurements on its unscaled prediction times `L^j`, weights one over the
/// measurement's variance (exposure noise, pooled over the exposures of one integration
/// length (`pooled_noise`), and the prediction's shot noise). Returns
/// the predictions, each sample's noise and its leverage in its pixel's fit (`h_i`:
/// under the fit, a residual's variance is `sigma_i^2 (1 - h_i)`).
pub fn predict_scaled(
    seq: &Sequence,
    view: &View,
    s: &Samples,
    pred: &[f64],
    response: &Response,
) -> Scaled {
    // each pixel's terms weigh its illuminations at the measured fluence; the correction
    // takes the model's readout, the same maps when it has no fluence hook
    let measured = fluence_maps(seq, true, &Readout::default());
    let terms = PixelTerms::new(seq, s, &measured, response);
    let hooked;
    let maps = if view.readout.fluence.is_empty() {
        &measured
    } else {
        hooked = fluence_maps(seq, true, &view.readout);
        &hooked
    };
    let feat = Features::new(seq, view, s, maps);
    let variance = |s: &Samples, i: usize, p: f64| measurement_variance(&terms.noise, s, i, p);
    let mut scale = vec![1.0; s.len()];
    let mut unscaled = pred.to_vec();
    let mut normal = Vec::new();
    for pass in 0..=SCALE_PASSES {
        if pass > 0 {
            if let Some(coef) = fit_correction(&feat, s, pred, &scale, variance) {
                unscaled = corrected(&feat, pred, &coef);
            }
        }
        (scale, normal) = terms.pass(s, &unscaled, &scale);
    }
    terms.finish(s, pred, unscaled, scale, &normal)
}

/// The pixel reference fitted to each illumination event's samples alone
/// ([`predict_scaled`] per event: its own correction and its own pixel terms), the
/// events' cells pooled: their normalised residual RMS, and the cells. What it leaves
/// is what no addition acting on how a pixel's illuminations differ (duration, history,
/// temperature, in any form) can take away from the pixel reference: a floor for the
/// offer ([`super::offer`]). None with fewer than two events or no cell.
pub fn per_event_rms(
    seq: &Sequence,
    view: &View,
    s: &Samples,
    pred: &[f64],
    response: &Response,
) -> Option<(f64, usize)> {
    let events = s.events();
    if events.len() < 2 {
        return None;
    }
    let cells: Vec<_> = events
        .par_iter()
        .map(|&e| {
            let rows = s.row_indices(|x| x == e);
            let es = s.rows(&rows);
            predict_scaled(seq, view, &es, &s.rows_of(pred, &rows), response).cells(&es)
        })
        .collect::<Vec<_>>()
        .concat();
    (!cells.is_empty()).then(|| (super::eval::rms(&cells), cells.len()))
}

/// [`predict_scaled`] of `pred` with the shared correction held at `held`'s (a fit of
/// the same samples `s`): only each pixel's terms are refitted (as many passes). A
/// prediction compared with another on this footing differs only by what each pixel's
/// own terms can take in; it costs a small part of a full fit.
pub fn predict_scaled_held(
    seq: &Sequence,
    s: &Samples,
    pred: &[f64],
    response: &Response,
    held: &Scaled,
) -> Scaled {
    let terms = PixelTerms::new(
        seq,
        s,
        &fluence_maps(seq, true, &Readout::default()),
        response,
    );
    let unscaled: Vec<f64> = pred
        .iter()
        .zip(&held.correction)
        .map(|(p, c)| p + c)
        .collect();
    let mut scale = vec![1.0; s.len()];
    let mut normal = Vec::new();
    for _ in 0..=SCALE_PASSES {
        (scale, normal) = terms.pass(s, &unscaled, &scale);
    }
    terms.finish(s, pred, unscaled, scale, &normal)
}

/// The per-pixel part of [`predict_scaled`]: the regressors of every sample and the
/// pooled noise.
struct PixelTerms {
    noise: Vec<f64>,
    sat: Vec<f64>,
    fl: Vec<f64>,
    tilt: Vec<f64>,
}

/// Per pixel, the normal equations of its terms.
type Normal = Vec<(Vec<f64>, Vec<f64>)>;

impl PixelTerms {
    /// The terms of the samples `s`; their illuminations weighed at the fluence of
    /// `maps`, the measured one (what each pixel itself received and read).
    fn new(seq: &Sequence, s: &Samples, maps: &[Map], response: &Response) -> PixelTerms {
        let np = s.npix().max(1);
        PixelTerms {
            noise: pooled_noise(seq, s),
            sat: saturated_share(seq, s, maps, response),
            fl: fluence_tilt(s),
            tilt: (0..s.len())
                .map(|i| (s.t_since_s[i / np].max(1.0) / TILT_REFERENCE_S).ln())
                .collect(),
        }
    }

    fn variance(&self, s: &Samples, i: usize, p: f64) -> f64 {
        measurement_variance(&self.noise, s, i, p)
    }

    /// One fit of every pixel's terms on `unscaled`, each sample weighted at its
    /// prediction under `scale` (the previous pass's): the new scale and the normal
    /// equations.
    fn pass(&self, s: &Samples, unscaled: &[f64], scale: &[f64]) -> (Vec<f64>, Normal) {
        const K: usize = ALL_PIXEL_TERMS;
        let np = s.npix().max(1);
        let mut normal: Normal = vec![(vec![0.0f64; K * K], vec![0.0f64; K]); np];
        for (i, (&m, &u)) in s.measured.iter().zip(unscaled).enumerate() {
            if !(m.is_finite() && u.is_finite()) {
                continue;
            }
            let w = 1.0 / self.variance(s, i, scale[i] * u).max(1e-12);
            let x = pixel_regressors(self.tilt[i], self.sat[i], self.fl[i]).map(|r| u * r);
            let (ata, atb) = &mut normal[i % np];
            for a in 0..K {
                atb[a] += w * m * x[a];
                for b in 0..K {
                    ata[a * K + b] += w * x[a] * x[b];
                }
            }
        }
        let terms: Vec<Vec<f64>> = normal
            .iter()
            .map(|(ata, atb)| {
                let tr = (0..K).map(|j| ata[j * K + j]).sum::<f64>();
                match solve_spd(&mut ridged(ata, K), atb.clone(), K) {
                    Some(c) if tr > 0.0 => c,
                    _ => std::iter::once(1.0)
                        .chain(std::iter::repeat(0.0))
                        .take(K)
                        .collect(),
                }
            })
            .collect();
        let scale = (0..s.len())
            .map(|i| pixel_factor(&terms[i % np], self.tilt[i], self.sat[i], self.fl[i]).max(0.0))
            .collect();
        (scale, normal)
    }

    /// The predictions, noise and leverage of the last pass.
    fn finish(
        &self,
        s: &Samples,
        pred: &[f64],
        unscaled: Vec<f64>,
        scale: Vec<f64>,
        normal: &Normal,
    ) -> Scaled {
        const K: usize = ALL_PIXEL_TERMS;
        let prediction: Vec<f64> = unscaled.iter().zip(&scale).map(|(u, c)| c * u).collect();
        let sigma: Vec<f64> = (0..s.len())
            .map(|i| self.variance(s, i, prediction[i]).sqrt())
            .collect();
        // leverage of each sample in its pixel's fit (the last pass's normal equations)
        let inverse: Vec<Option<Vec<f64>>> = normal
            .iter()
            .map(|(ata, _)| inverse_spd(&ridged(ata, K), K))
            .collect();
        let np = s.npix().max(1);
        let leverage = (0..s.len())
            .map(|i| {
                let Some(inv) = &inverse[i % np] else {
                    return 0.0;
                };
                let u = unscaled[i];
                let w = 1.0 / sigma[i].powi(2).max(1e-12);
                let x = pixel_regressors(self.tilt[i], self.sat[i], self.fl[i]).map(|r| u * r);
                let mut h = 0.0;
                for a in 0..K {
                    for b in 0..K {
                        h += x[a] * inv[a * K + b] * x[b];
                    }
                }
                let h = w * h;
                if h.is_finite() {
                    h.clamp(0.0, 1.0)
                } else {
                    0.0
                }
            })
            .collect();
        let correction = unscaled.iter().zip(pred).map(|(u, p)| u - p).collect();
        Scaled {
            prediction,
            sigma,
            leverage,
            correction,
        }
    }
}

/// Each row's exposure noise of `s`, replaced by the median over its sampled exposures
/// of the same integration length where that is measured: the read noise does not change from one dark to the
/// next, and one exposure's estimate scatters (1.4826 MAD of the background pixels: a
/// corner of 8 x 8 dark pixels at 64 x 64 gives it about 13 % per exposure, which
/// widens the normalised residuals by 4-6 % and takes the simulator's single
/// illumination with dark pixels, seed 3, from 1.40 to 1.94).
fn pooled_noise(seq: &Sequence, s: &Samples) -> Vec<f64> {
    let length = |row: usize| seq.exposures[s.exposures[row]].meta.t_exposure_s.to_bits();
    let mut by_length: std::collections::BTreeMap<u64, Vec<f64>> = Default::default();
    for (row, &n) in s.noise.iter().enumerate() {
        if n.is_finite() && n > 0.0 {
            by_length.entry(length(row)).or_default().push(n);
        }
    }
    let pooled: std::collections::BTreeMap<u64, f64> = by_length
        .into_iter()
        .map(|(length, v)| (length, crate::stats::median(&v)))
        .collect();
    s.noise
        .iter()
        .enumerate()
        .map(|(row, &n)| pooled.get(&length(row)).copied().unwrap_or(n))
        .collect()
}

/// `m` (`n x n`) plus a ridge of 1e-9 of its mean diagonal: a term with no samples
/// (a column of zeros) gets a zero coefficient and a zero leverage.
fn ridged(m: &[f64], n: usize) -> Vec<f64> {
    let tr = (0..n).map(|j| m[j * n + j]).sum::<f64>() / n as f64;
    let mut r = m.to_vec();
    for j in 0..n {
        r[j * n + j] += 1e-9 * tr;
    }
    r
}

/// The inverse of a symmetric positive definite `n x n` matrix (row major), by
/// [`solve_spd`] column by column; None when it is not positive definite.
fn inverse_spd(m: &[f64], n: usize) -> Option<Vec<f64>> {
    let mut inv = vec![0.0; n * n];
    for c in 0..n {
        let mut e = vec![0.0; n];
        e[c] = 1.0;
        let col = solve_spd(&mut m.to_vec(), e, n)?;
        for r in 0..n {
            inv[r * n + c] = col[r];
        }
    }
    Some(inv)
}

/// What [`predict_scaled`] returns.
#[derive(Debug, Clone)]
pub struct Scaled {
    /// Per sample, e-/s.
    pub prediction: Vec<f64>,
    /// Per sample: the measurement's noise at the prediction (exposure noise and shot
    /// noise), e-/s.
    pub sigma: Vec<f64>,
    /// Per sample: its leverage `h_i` in its pixel's fit.
    pub leverage: Vec<f64>,
    /// Per sample: the shared correction added to the prediction before each pixel's
    /// terms, e-/s ([`predict_scaled_held`] holds it).
    pub correction: Vec<f64>,
}

impl Scaled {
    /// The noise of sample `i`'s residual: `sigma_i sqrt(1 - h_i)`.
    fn residual_sd(&self, i: usize) -> f64 {
        self.sigma[i] * (1.0 - self.leverage[i]).max(0.0).sqrt()
    }

    /// The reference's cells ([`crate::measure::eval::cell_z`]'s keys): the paired
    /// statistic of the normalised residuals `(measured_i - reference_i) / (sigma_i
    /// sqrt(1 - h_i))` against unit normal noise, so that every sample counts against its
    /// own noise. A cell mixes samples of very different noise: a pixel's first dark
    /// after a bright illumination carries most of its fit's weight (leverage near 1, a
    /// residual noise a few hundredths of an e-/s) beside pixels whose fit it barely
    /// steers; the statistic on the residuals themselves would judge the noisy ones by
    /// the quiet ones' spread. The figures (95th percentiles, median) are those of the
    /// measurements and predictions; `sigma_e_per_s` is the statistic's `sigma_q` times
    /// the cell's median residual noise.
    pub fn cells(&self, s: &Samples) -> Vec<(Vec<i64>, crate::measure::eval::GroupStat)> {
        use crate::measure::eval;
        let cells = eval::groups_by(
            s,
            &self.prediction,
            s.cells.keys(),
            eval::CellStatistic::Paired,
            |i| {
                let sd = self.residual_sd(i);
                (0.0, sd, sd)
            },
        );
        let mut normalised: std::collections::BTreeMap<Vec<i64>, (Vec<f64>, Vec<f64>)> =
            Default::default();
        for i in 0..s.len() {
            let (m, p, sd) = (s.measured[i], self.prediction[i], self.residual_sd(i));
            if !(m.is_finite() && p.is_finite() && sd > 0.0) {
                continue;
            }
            if let Some(key) = eval::key_of(s, s.cells.keys(), i) {
                let e = normalised.entry(key).or_default();
                e.0.push((m - p) / sd);
                e.1.push(sd);
            }
        }
        let unit_p95 = eval::noise_p95(&[1.0]);
        cells
            .into_iter()
            .filter_map(|(key, mut stat)| {
                let (r, sd) = normalised.get(&key)?;
                if r.len() < 10 {
                    return None;
                }
                let (_, sigma_q, z) = eval::paired_z(r, 1.0, unit_p95);
                stat.n = r.len();
                stat.sigma_e_per_s = sigma_q * crate::stats::median(sd);
                stat.z = z;
                Some((key, stat))
            })
            .collect()
    }
}

/// Measures the noise scales on the pixel reference of `pred` over `s`
/// ([`measure_noise_scale`]) and sets them into `s`, for every later fit of the pixel
/// reference on these samples or on their rows (the candidates' are judged with the
/// noise the user's model's reference showed). What was measured; None leaves `s`'s.
pub fn scale_noise(
    seq: &Sequence,
    view: &View,
    s: &mut Samples,
    pred: &[f64],
    response: &Response,
) -> Option<(NoiseScale, usize)> {
    let measured = measure_noise_scale(&predict_scaled(seq, view, s, pred, response), s);
    if let Some((scale, _)) = measured {
        s.noise_scale = scale;
    }
    measured
}

/// Samples at least, centred in their cells, for [`measure_noise_scale`] to measure.
pub const NOISE_SCALE_MIN_SAMPLES: usize = 2000;
/// Samples at least in a cell whose samples [`measure_noise_scale`] centres on their
/// median (the median of fewer takes a visible share of their spread with it).
pub const NOISE_SCALE_MIN_CELL: usize = 30;
/// Bins of the shot-noise share [`measure_noise_scale`] fits over.
pub const NOISE_SCALE_BINS: usize = 10;
/// The least span of the bins' shot-noise shares over which the two parts' scales are
/// told apart; under it one scale stands for both.
pub const NOISE_SCALE_MIN_SPAN: f64 = 0.3;
/// Bounds of a measured scale.
pub const NOISE_SCALE_BOUNDS: (f64, f64) = (0.25, 4.0);

/// The scales of the read-noise and shot-noise variances that the residuals of the
/// pixel reference `scaled` of `s` show (fitted with `s.noise_scale` 1 and 1). The
/// exposure noise is measured from the data ([`crate::measure::data`]); the shot noise
/// is Poisson's for a line fit, which the readout need not give: the gain's error scales
/// it, and a readout that couples neighbours (inter-pixel capacitance) narrows each
/// pixel's noise, the shot noise with it (the second truth generator's `ipc:cross4`,
/// 64 x 64 campaign, seed 1: pairs of late darks differ by 0.92 of the spread of the
/// same seed without it, and the pixel reference's first-dark cells by 0.84-0.89 of
/// their noise, cell z down to -4.7, where nothing-hidden data show 0.90-0.97). Each
/// sample's residual over its noise (less its leverage) is centred on its cell's
/// median (what a cell's misfit shifts is not noise); the centred samples are split
/// into [`NOISE_SCALE_BINS`] equal-count bins of the shot noise's share `psi` of their
/// variance; in each, `v` is the square of 1.4826 times the median absolute value; `a`
/// and `g` are the least-squares fit of `v = a (1 - psi) + g psi` over the bins, each
/// within [`NOISE_SCALE_BOUNDS`]. When the bins' shares span less than
/// [`NOISE_SCALE_MIN_SPAN`] one scale, the bins' mean `v`, stands for both. None with
/// fewer than [`NOISE_SCALE_MIN_SAMPLES`] samples in cells of at least
/// [`NOISE_SCALE_MIN_CELL`].
pub fn measure_noise_scale(scaled: &Scaled, s: &Samples) -> Option<(NoiseScale, usize)> {
    use crate::measure::eval;
    let mut by_cell: std::collections::BTreeMap<Vec<i64>, Vec<(f64, f64)>> = Default::default();
    for i in 0..s.len() {
        let (m, p, sd) = (s.measured[i], scaled.prediction[i], scaled.residual_sd(i));
        let var = scaled.sigma[i].powi(2);
        if !(m.is_finite() && p.is_finite() && sd > 0.0 && var > 0.0) {
            continue;
        }
        let shot = s.shot_var_per_e_per_s[i / s.npix().max(1)] * p.max(0.0);
        if let Some(key) = eval::key_of(s, s.cells.keys(), i) {
            by_cell
                .entry(key)
                .or_default()
                .push(((m - p) / sd, (shot / var).clamp(0.0, 1.0)));
        }
    }
    let mut centred: Vec<(f64, f64)> = Vec::new();
    for v in by_cell.values().filter(|v| v.len() >= NOISE_SCALE_MIN_CELL) {
        let mid = crate::stats::median(&v.iter().map(|x| x.0).collect::<Vec<_>>());
        centred.extend(v.iter().map(|&(z, psi)| ((z - mid).abs(), psi)));
    }
    if centred.len() < NOISE_SCALE_MIN_SAMPLES {
        return None;
    }
    centred.sort_by(|a, b| a.1.total_cmp(&b.1).then(a.0.total_cmp(&b.0)));
    let per = centred.len().div_ceil(NOISE_SCALE_BINS);
    let bins: Vec<(f64, f64)> = centred
        .chunks(per)
        .map(|c| {
            let abs: Vec<f64> = c.iter().map(|x| x.0).collect();
            let psi = c.iter().map(|x| x.1).sum::<f64>() / c.len() as f64;
            (psi, (1.4826 * crate::stats::median(&abs)).powi(2))
        })
        .collect();
    let (lo, hi) = NOISE_SCALE_BOUNDS;
    let span = bins.iter().map(|b| b.0).fold(f64::NEG_INFINITY, f64::max)
        - bins.iter().map(|b| b.0).fold(f64::INFINITY, f64::min);
    let scale = if span < NOISE_SCALE_MIN_SPAN {
        let v = (bins.iter().map(|b| b.1).sum::<f64>() / bins.len() as f64).clamp(lo, hi);
        NoiseScale {
            read_var: v,
            shot_var: v,
        }
    } else {
        // normal equations of v = a (1 - psi) + g psi
        let (mut aa, mut ag, mut gg, mut av, mut gv) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for &(psi, v) in &bins {
            let (x, y) = (1.0 - psi, psi);
            aa += x * x;
            ag += x * y;
            gg += y * y;
            av += x * v;
            gv += y * v;
        }
        let det = aa * gg - ag * ag;
        if !(det.is_finite() && det > 0.0) {
            return None;
        }
        NoiseScale {
            read_var: ((gg * av - ag * gv) / det).clamp(lo, hi),
            shot_var: ((aa * gv - ag * av) / det).clamp(lo, hi),
        }
    };
    Some((scale, centred.len()))
}

/// Solves `m x = b` for a symmetric positive definite `m` (n x n, row major) by
/// Cholesky; None when it is not positive definite. Reads the lower triangle of `m`
/// (the diagonal and below) only, where it leaves the factor.
///
/// The factor of a row is zero before the row's first non-zero entry (its envelope),
/// so the sums start there: the terms left out are exact zeros, and the result is the
/// dense factorisation's. In the base's normal equations the knots and the saturated
/// pixels' own response that no sample uses leave rows empty before the diagonal.
fn solve_spd(m: &mut [f64], mut b: Vec<f64>, n: usize) -> Option<Vec<f64>> {
    let first: Vec<usize> = (0..n)
        .map(|i| (0..i).find(|&k| m[i * n + k] != 0.0).unwrap_or(i))
        .collect();
    for j in 0..n {
        let row_j = j * n;
        let mut d = m[row_j + j];
        for k in first[j]..j {
            d -= m[row_j + k] * m[row_j + k];
        }
        if d <= 0.0 || !d.is_finite() {
            return None;
        }
        let d = d.sqrt();
        m[row_j + j] = d;
        for i in j + 1..n {
            let mut v = m[i * n + j];
            for k in first[i].max(first[j])..j {
                v -= m[i * n + k] * m[row_j + k];
            }
            m[i * n + j] = v / d;
        }
    }
    for i in 0..n {
        let mut v = b[i];
        for k in first[i]..i {
            v -= m[i * n + k] * b[k];
        }
        b[i] = v / m[i * n + i];
    }
    for i in (0..n).rev() {
        let mut v = b[i];
        for k in i + 1..n {
            v -= m[k * n + i] * b[k];
        }
        b[i] = v / m[i * n + i];
    }
    Some(b)
}

#[cfg(test)]
pub(super) mod tests {
    use super::*;

    proptest::proptest! {
        /// A sample's entries are, per parameter `knot * TAU_S.len() + j`, the sum over
        /// the illuminations before it of `w d_j` (the terms not left out), in ascending
        /// order and one entry each: the plain sum over every pair, kept in a map.
        #[test]
        fn sample_features_sum_every_illuminations_knots_and_decays(
            knots in proptest::collection::vec(
                proptest::collection::vec((0usize..8, 0.01f64..2.0), 0..5), 1..5),
            decay_seeds in proptest::collection::vec(
                proptest::option::of(proptest::collection::vec(0.0f64..1.0, TAU_S.len())), 4),
        ) {
            let decays: Vec<Option<[f64; TAU_S.len()]>> = decay_seeds
                .iter()
                .take(knots.len())
                .map(|d| {
                    d.as_ref().map(|v| {
                        let mut a = [0.0; TAU_S.len()];
                        // every third term left out (0), as decays below 1e-9 are
                        for (j, x) in v.iter().enumerate() {
                            a[j] = if j % 3 == 2 { 0.0 } else { *x + 1e-6 };
                        }
                        a
                    })
                })
                .collect();
            let merged: Vec<Vec<(usize, f64)>> =
                knots.iter().map(|k| merged_by_knot(&mut k.clone())).collect();
            let got = sample_features(&merged, &decays, &mut Vec::new());
            let mut want: std::collections::BTreeMap<usize, f64> = Default::default();
            for (kn, d) in knots.iter().zip(&decays) {
                let Some(d) = d else { continue };
                for &(k, w) in kn {
                    for (j, dj) in d.iter().enumerate().filter(|(_, dj)| **dj > 0.0) {
                        *want.entry(k * TAU_S.len() + j).or_default() += w * dj;
                    }
                }
            }
            proptest::prop_assert_eq!(got.len(), want.len());
            for ((a, v), (b, u)) in got.iter().zip(&want) {
                proptest::prop_assert_eq!(a, b);
                proptest::prop_assert!((v - u).abs() <= 1e-12 * u.abs().max(1.0), "{} {} {}", a, v, u);
            }
        }
    }

    #[test]
    fn cholesky_solves_a_small_system() {
        // [[4, 2], [2, 3]] x = [2, 1] -> x = [0.5, 0]
        let mut m = vec![4.0, 2.0, 2.0, 3.0];
        let x = solve_spd(&mut m, vec![2.0, 1.0], 2).unwrap();
        assert!((x[0] - 0.5).abs() < 1e-12 && x[1].abs() < 1e-12, "{x:?}");
        let mut bad = vec![0.0, 1.0, 1.0, 0.0];
        assert!(solve_spd(&mut bad, vec![1.0, 1.0], 2).is_none());
    }

    /// `fit_correction` sums the lower triangle of its normal equations alone: whatever
    /// stands above the diagonal, the solution is the same, to the bit.
    #[test]
    fn cholesky_reads_the_lower_triangle_only() {
        let full = vec![4.0, 2.0, 1.0, 2.0, 5.0, 0.5, 1.0, 0.5, 3.0];
        let mut lower = full.clone();
        for (i, j) in [(0, 1), (0, 2), (1, 2)] {
            lower[i * 3 + j] = f64::NAN;
        }
        let b = vec![1.0, -2.0, 0.25];
        let x = solve_spd(&mut full.clone(), b.clone(), 3).unwrap();
        let y = solve_spd(&mut lower, b, 3).unwrap();
        assert_eq!(
            x.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
            y.iter().map(|v| v.to_bits()).collect::<Vec<_>>()
        );
    }

    /// A system whose rows start late (zeros before their first entry, the envelope the
    /// factorisation skips) is solved: `m x = b` to rounding, on a 5 x 5 matrix with a
    /// decoupled block, an unused parameter (a ridge alone) and a row coupled back
    /// across the block.
    #[test]
    fn cholesky_solves_a_system_whose_rows_start_late() {
        let n = 5;
        #[rustfmt::skip]
        let full = vec![
            4.0, 1.0, 0.0, 0.0, 0.5,
            1.0, 3.0, 0.0, 0.0, 0.0,
            0.0, 0.0, 1e-6, 0.0, 0.0,
            0.0, 0.0, 0.0, 2.0, 0.7,
            0.5, 0.0, 0.0, 0.7, 5.0,
        ];
        let b = vec![1.0, -1.0, 2e-6, 0.5, 3.0];
        let x = solve_spd(&mut full.clone(), b.clone(), n).unwrap();
        for i in 0..n {
            let mx: f64 = (0..n).map(|j| full[i * n + j] * x[j]).sum();
            assert!(
                (mx - b[i]).abs() < 1e-12 * (1.0 + b[i].abs()),
                "row {i}: {mx} vs {}",
                b[i]
            );
        }
        assert!((x[2] - 2.0).abs() < 1e-9, "{x:?}");
    }

    /// Through `ipc`'s readout, a pixel next to a bright one takes the bright one's
    /// knots at the coupling's weight and keeps its own at the centre's (the model's
    /// `K`); without a coupling, its own knots alone.
    #[test]
    fn the_readout_couples_a_bright_pixels_knots_into_its_neighbours() {
        let mut fluence = Array2::from_elem((3, 3), 1e4);
        fluence[(1, 1)] = 1e6;
        let m = Map {
            illumination: 0,
            fluence,
            overflow: None,
        };
        let ipc = crate::model::effects::ipc::Ipc::isotropic(0.02);
        let kernel = ipc.readout_kernel();
        let mut kn = Vec::new();
        coupled_knots(&m, &kernel, 0, 1, &mut kn);
        let weight_at = |f: f64| -> f64 {
            let [a, b] = knots_of(f).unwrap();
            kn.iter()
                .filter(|k| k.0 == a.0 || k.0 == b.0)
                .map(|k| k.1)
                .sum()
        };
        assert!((weight_at(1e6) - 0.02).abs() < 1e-12, "{kn:?}");
        // its own (1 - 4 alpha) and two neighbours at its fluence, inside the array
        assert!(
            (weight_at(1e4) - (0.92 + 2.0 * 0.02)).abs() < 1e-12,
            "{kn:?}"
        );
        coupled_knots(&m, &[], 0, 1, &mut kn);
        assert_eq!(kn.iter().map(|k| k.1).sum::<f64>(), 1.0);
        assert!(kn
            .iter()
            .all(|k| knots_of(1e4).unwrap().iter().any(|o| o.0 == k.0)));
    }

    /// Samples of a 24 x 24 campaign measured as the default model's prediction plus
    /// noise of variance `read_var` times the exposure noise's and `shot_var` times the
    /// shot noise's, each cell's samples shifted by `shift_sd` times its noise (a
    /// misfit); the reference taken as the prediction itself with noise 1 and 1.
    fn scaled_with_noise(read_var: f64, shot_var: f64, shift: f64) -> (Samples, Scaled) {
        use rand::SeedableRng;
        use rand_distr::Distribution;
        let seq = campaign_at(&[80.0, 80.0, 80.0]);
        let model = ModelParams::default();
        let (mut s, pred) = measured_as(&seq, &model, &model);
        let np = s.npix();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let sigma: Vec<f64> = (0..s.len())
            .map(|i| measurement_variance(&s.noise, &s, i, pred[i]).sqrt())
            .collect();
        s.measured = (0..s.len())
            .map(|i| {
                let row = i / np;
                let var = read_var * s.noise[row].powi(2)
                    + shot_var * s.shot_var_per_e_per_s[row] * pred[i].max(0.0);
                let z: f64 = rand_distr::StandardNormal.sample(&mut rng);
                let cell = crate::measure::eval::key_of(&s, s.cells.keys(), i)
                    .map_or(0, |k| k.iter().sum::<i64>());
                pred[i] + var.sqrt() * z + shift * sigma[i] * (cell % 3 - 1) as f64
            })
            .collect();
        let scaled = Scaled {
            prediction: pred.clone(),
            sigma,
            leverage: vec![0.0; pred.len()],
            correction: vec![0.0; pred.len()],
        };
        (s, scaled)
    }

    /// The two scales are recovered from residuals drawn with them, and a misfit that
    /// shifts whole cells (by a noise either way) leaves them as they are.
    #[test]
    fn the_noise_scales_are_measured_from_residuals_and_not_from_a_cells_misfit() {
        let (s, scaled) = scaled_with_noise(0.9, 0.6, 0.0);
        let (scale, n) = measure_noise_scale(&scaled, &s).expect("measured");
        assert!(n >= NOISE_SCALE_MIN_SAMPLES, "{n} samples");
        assert!((scale.read_var - 0.9).abs() < 0.06, "{scale:?}");
        assert!((scale.shot_var - 0.6).abs() < 0.08, "{scale:?}");
        let (s, scaled) = scaled_with_noise(0.9, 0.6, 1.0);
        let (shifted, _) = measure_noise_scale(&scaled, &s).expect("measured");
        assert!(
            (shifted.read_var - scale.read_var).abs() < 0.03,
            "{shifted:?} {scale:?}"
        );
        assert!(
            (shifted.shot_var - scale.shot_var).abs() < 0.04,
            "{shifted:?} {scale:?}"
        );
        // the noise the reference is weighed and judged with
        let mut s = s;
        s.noise_scale = scale;
        let v = measurement_variance(&s.noise, &s, 0, 0.5);
        let expected =
            scale.read_var * s.noise[0].powi(2) + scale.shot_var * s.shot_var_per_e_per_s[0] * 0.5;
        assert!((v - expected).abs() < 1e-15);
    }

    /// A simulated laboratory campaign at 24 x 24 (the paper's pattern, a corner of
    /// dark pixels) of equal illuminations held at `temps_k`, each followed by 12
    /// darks of 180 s.
    pub(in crate::diag) fn campaign_at(temps_k: &[f64]) -> Sequence {
        use crate::sim::lab;
        let campaign = temps_k
            .iter()
            .map(|&temp_k| lab::Illumination {
                t_illuminated_s: 481.0,
                flux_scale: 1.0,
                temp_k,
                darks_after: 12,
                spot_offset: [0.0, 0.0],
                points: false,
                dark_s: None,
                after_shutter_s: None,
            })
            .collect();
        let cfg = lab::LabConfig {
            size: 24,
            seed: 1,
            campaign: Some(campaign),
            paper_pattern: Some(lab::PaperPattern { dark_pixels: true }),
            ..lab::LabConfig::default()
        };
        let mut exposures = Vec::new();
        lab::run(&cfg, |e| {
            exposures.push(e.exposure);
            Ok(())
        })
        .unwrap();
        Sequence::from_exposures(exposures).unwrap()
    }

    /// `seq`'s samples as `diagnose` draws them by default, measured as `truth`'s
    /// prediction plus each exposure's noise (seeded), and `model`'s prediction of them.
    pub(in crate::diag) fn measured_as(
        seq: &Sequence,
        truth: &ModelParams,
        model: &ModelParams,
    ) -> (Samples, Vec<f64>) {
        use rand::SeedableRng;
        use rand_distr::Distribution;
        let cfg = super::super::config::Config::default();
        let mut s = Samples::random(seq, cfg.pixels, cfg.seed)
            .with_cells(cfg.cells)
            .with_statistic(cfg.cell_statistic);
        let predict = |m: &ModelParams| {
            crate::measure::eval::predict(m, seq, &s, false)
                .unwrap()
                .current
        };
        let (measured, pred) = (predict(truth), predict(model));
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        let np = s.npix();
        s.measured = measured
            .iter()
            .enumerate()
            .map(|(i, m)| {
                let z: f64 = rand_distr::StandardNormal.sample(&mut rng);
                m + s.noise[i / np] * z
            })
            .collect();
        (s, pred)
    }

    /// The default model with `temperature` at `activation_ev`.
    pub(in crate::diag) fn model_with_temperature(activation_ev: f64) -> ModelParams {
        let mut m = ModelParams::default();
        let mut spec = crate::model::effect::EffectSpec::named("temperature");
        spec.params
            .insert("activation_ev".into(), serde_json::json!(activation_ev));
        m.push_effect(spec);
        m
    }

    /// The clock of a model with `temperature`: each interval counts `dt / f`, `f` the
    /// Arrhenius factor of the exposure ending it (the same for every term); real time
    /// at 80 K (within the recorded temperature's 0.01 K), at `activation_ev` 0 and
    /// without the effect.
    #[test]
    fn the_clock_of_a_rate_hook_runs_at_each_intervals_arrhenius_factor() {
        let seq = campaign_at(&[78.0, 82.0, 80.0]);
        let clock = View::of_model(&model_with_temperature(0.25), &seq).clock;
        assert!(!clock.is_real());
        let t = crate::model::effects::temperature::Temperature {
            activation_ev: 0.25,
            t_ref_k: 80.0,
        };
        // the second illumination (82 K) and its darks
        let a = seq.illuminations[1];
        // each exposure's recorded temperature (the simulator's, within 0.01 K)
        let temp = |k: usize| seq.exposures[k].meta.focal_plane_temp_k.unwrap();
        assert!((temp(a + 1) - 82.0).abs() < 0.01, "{}", temp(a + 1));
        for k in [a + 1, a + 5, a + 12] {
            let mut expected = 0.0;
            for m in a + 1..=k {
                let dt = seq.t_mid_after_s(m - 1, m)
                    + if m < k {
                        0.5 * seq.exposures[m].meta.t_exposure_s
                    } else {
                        0.0
                    };
                expected += dt / t.factor(temp(m));
            }
            let real = seq.t_mid_after_s(a, k);
            // 1 / f(82 K) = exp(0.25 / 8.617333e-5 (1/80 - 1/82)) = 2.42
            assert!(expected > 2.0 * real, "{expected} {real}");
            for j in [0, 8, 16] {
                let on = clock.elapsed_s(&seq, a, k, j);
                assert!((on - expected).abs() < 1e-9 * expected, "{on} {expected}");
            }
        }
        let a = seq.illuminations[2];
        let real = seq.t_mid_after_s(a, a + 3);
        let on = clock.elapsed_s(&seq, a, a + 3, 4);
        // 80 K within 0.01 K: f within 0.5 %
        assert!((on - real).abs() < 5e-3 * real, "{on} {real}");
        assert!(View::of_model(&model_with_temperature(0.0), &seq)
            .clock
            .is_real());
        assert!(View::of_model(&ModelParams::default(), &seq)
            .clock
            .is_real());
    }

    /// The pixel reference of the default model with `temperature` at 0.25 eV, on
    /// measurements that are that model's prediction with a decay shape of their own
    /// (each term's `C_n` times `(r_n / r_1)^0.2`, `r_n` its rate: what the reference's
    /// shared correction takes in) plus each exposure's noise: on a campaign whose
    /// illuminations are held at 78, 82 and 80 K its shared correction follows the
    /// three illuminations' decays on the model's clock and not in real time (their
    /// rates a factor exp(0.25 eV / k (1/78 - 1/82 K)) = 4.2 apart), so it fits better
    /// there; at 80 K throughout the two agree.
    #[test]
    fn the_pixel_reference_fits_illuminations_at_three_temperatures_better_on_the_models_clock() {
        let model = model_with_temperature(0.25);
        let mut truth = model.clone();
        let r1 = truth.terms[0].rate_per_s;
        for t in truth.terms.iter_mut() {
            t.c_per_s *= (t.rate_per_s / r1).powf(0.2);
        }
        let response = Response::new(&model.amplitude_knots);
        let rms = |temps_k: [f64; 3]| -> (f64, f64) {
            let seq = campaign_at(&temps_k);
            let (s, pred) = measured_as(&seq, &truth, &model);
            let on = |view: &View| {
                crate::measure::eval::rms(
                    &predict_scaled(&seq, view, &s, &pred, &response).cells(&s),
                )
            };
            (on(&View::of_model(&model, &seq)), on(&View::default()))
        };
        let (on_clock, real) = rms([78.0, 82.0, 80.0]);
        assert!(
            on_clock < 0.8 * real,
            "model's clock {on_clock}, real time {real}"
        );
        let (on_clock, real) = rms([80.0, 80.0, 80.0]);
        assert!(
            (on_clock - real).abs() < 0.01 * real,
            "at 80 K: model's clock {on_clock}, real time {real}"
        );
    }

    #[test]
    fn response_knots_interpolate_in_log_fluence() {
        assert!(knots_of(100.0).is_none());
        let k = knots_of(1e4).unwrap();
        assert_eq!(k[0].0 + 1, k[1].0);
        assert!((k[0].1 + k[1].1 - 1.0).abs() < 1e-12);
    }
}
